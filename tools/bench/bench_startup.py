"""Start-up time of ``ballbar run --simulate`` with every output on: exec to READY=1.

    python -m ballbar.tools.bench.bench_startup --runs 7
    python -m ballbar.tools.bench.bench_startup --runs 7 --baseline-python /path/to/other/checkout/.venv/bin/python

Each run starts the daemon as systemd would see it (``$NOTIFY_SOCKET`` a datagram
socket of this process), with the default configuration's outputs (MCAP, Zenoh as a
peer, the Rerun server) on ports of ``--port-base`` and a fresh state directory;
records, from just before the process is spawned: the READY=1 datagram (and the
daemon's CPU time then, all threads: a figure the machine's load inflates less than
wall time), the log lines of the source opening the simulated device's pty
(``opened``: samples flow from then on) and of the Rerun server (``serving on``); once
all are there, stops it with SIGTERM and times the exit. Runs of
``--baseline-python`` (another checkout's interpreter) alternate with this one's;
medians over ``--runs`` each, and the ratio. The figure is wall time on whatever else
the machine is doing: compare only runs of one invocation.  Python's bytecode is
allowed (``$PYTHONDONTWRITEBYTECODE`` dropped) and written by one untimed start of
each, as an installation has it (pip compiles at install); ``--no-bytecode`` keeps
the variable, and every start compiles the package's modules (0.2 to 0.3 s).

What the time goes to: ``python -X importtime -m ballbar.daemon.cli run --simulate``.

``--handler`` times something else: from spawn to the SIGTERM handler being in place (the
process's ``SigCgt`` in ``/proc``, polled every millisecond), and the exit code of a SIGTERM sent
``--sigterm-at`` seconds after spawn (0: a clean stop; 143: no handler yet), with the outputs off.
"""

from __future__ import annotations

import argparse
import os
import select
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from typing import Any

from ballbar.daemon import procfs


def proc_cpu_s(pid: int) -> float:
    """utime + stime of a process (all its threads, not its children), seconds."""
    return procfs.cpu_seconds(pid)


MARKS = {
    "ready_log": "ready: reading",
    "opened": ": opened ",  # the serial source opened the device's pty: samples flow from here
    "rerun": "serving on",
}


def run_once(
    python: str, port_base: int, max_after_s: float, extra: Sequence[str], bytecode: bool = True
) -> dict[str, Any]:
    """One start: seconds from spawn to each mark, and to the exit after SIGTERM."""
    with tempfile.TemporaryDirectory(prefix="ballbar-bench-startup-") as tmp:
        path = os.path.join(tmp, "notify")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        sock.bind(path)
        env = dict(os.environ, NOTIFY_SOCKET=path, PYTHONUNBUFFERED="1")
        for k in ("WATCHDOG_USEC", "WATCHDOG_PID", *(() if not bytecode else ("PYTHONDONTWRITEBYTECODE",))):
            env.pop(k, None)
        cmd = [
            python, "-m", "ballbar.daemon.cli", "run", "--simulate", "--state-dir", os.path.join(tmp, "state"),
            "--set", f'zenoh.listen=["tcp/127.0.0.1:{port_base}"]', "--set", f"rerun.port={port_base + 1}", *extra,
        ]
        out: dict[str, Any] = {}
        t0 = time.monotonic()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=tmp)
        assert proc.stderr is not None
        err = proc.stderr.fileno()
        buf = b""
        log: list[str] = []
        try:
            deadline = t0 + 60.0
            stop_at = None
            while time.monotonic() < (stop_at or deadline):
                ready, _, _ = select.select([sock.fileno(), err], [], [], 0.05)
                now = time.monotonic() - t0
                if sock.fileno() in ready:
                    msg = sock.recv(4096).decode(errors="replace")
                    if "READY=1" in msg.split("\n") and "ready" not in out:
                        out["ready"] = now
                        out["cpu"] = proc_cpu_s(proc.pid)
                        stop_at = time.monotonic() + max_after_s
                if err in ready:
                    chunk = os.read(err, 65536)
                    if not chunk:
                        break
                    buf += chunk
                    while b"\n" in buf:
                        line, buf = buf.split(b"\n", 1)
                        text = line.decode(errors="replace")
                        log.append(text)
                        for key, mark in MARKS.items():
                            if mark in text and key not in out:
                                out[key] = now
                if "ready" in out and all(k in out for k in MARKS):
                    break  # everything is up: stop it
            t_term = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            out["code"] = proc.wait(15)
            out["stop"] = time.monotonic() - t_term
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            proc.stderr.close()
            sock.close()
        if "ready" not in out:
            raise RuntimeError("no READY=1 within 60 s:\n" + "\n".join(log[-20:]))
        return out


def _catches_sigterm(pid: int) -> bool:
    try:
        caught = int(procfs.status(pid)["SigCgt"], 16)
    except (OSError, KeyError, ValueError):
        return False
    return bool(caught & (1 << (signal.SIGTERM - 1)))


def handler_once(python: str, state: str, sigterm_at: float | None) -> tuple[float | None, int]:
    """Seconds from spawn to the SIGTERM handler (None: not seen before the signal), and the exit code after a
    SIGTERM at ``sigterm_at`` s (or once the handler is there)."""
    cmd = [python, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=100", "--state-dir", state,
           "--set", "mcap.enabled=false", "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"']
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    seen = None
    while proc.poll() is None and time.monotonic() - t0 < 10.0:
        if seen is None and _catches_sigterm(proc.pid):
            seen = time.monotonic() - t0
        due = seen is not None if sigterm_at is None else time.monotonic() - t0 >= sigterm_at
        if due:
            break
        time.sleep(0.001)
    proc.send_signal(signal.SIGTERM)
    try:
        return seen, proc.wait(20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def handler_main(args: argparse.Namespace) -> int:
    variants = [("current", sys.executable)]
    if args.baseline_python:
        variants.insert(0, ("baseline", args.baseline_python))
    at = [float(x) for x in args.sigterm_at.split(",") if x.strip()]
    with tempfile.TemporaryDirectory(prefix="ballbar-bench-handler-") as tmp:
        for _name, python in variants:  # bytecode written once, as installed
            handler_once(python, tmp, None)
        seen: dict[str, list[float]] = {n: [] for n, _ in variants}
        codes: dict[str, dict[float, list[int]]] = {n: {a: [] for a in at} for n, _ in variants}
        for i in range(args.runs):
            for name, python in variants if i % 2 == 0 else variants[::-1]:
                t, _code = handler_once(python, tmp, None)
                if t is not None:
                    seen[name].append(t)
                for a in at:
                    codes[name][a].append(handler_once(python, tmp, a)[1])
    print(f"ballbar run: spawn to SIGTERM handler, median of {args.runs} (min..max); exit codes of a SIGTERM at")
    for name, _ in variants:
        xs = seen[name]
        line = f"{name:<10} handler {statistics.median(xs):.3f} s ({min(xs):.3f}..{max(xs):.3f})" if xs else name
        print(line + "   " + "   ".join(f"{a:g} s: {codes[name][a]}" for a in at))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_startup", description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--baseline-python", help="also time this interpreter's ballbar (another checkout)")
    p.add_argument("--port-base", type=int, default=7640, help="Zenoh listens here, Rerun serves on the next")
    p.add_argument("--max-after-s", type=float, default=15.0,
                   help="after READY=1, wait at most this long for the other marks before SIGTERM")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="more configuration")
    p.add_argument("--no-bytecode", action="store_true",
                   help="keep $PYTHONDONTWRITEBYTECODE: every start compiles the package's modules again")
    p.add_argument("--handler", action="store_true", help="time the SIGTERM handler instead (see the docstring)")
    p.add_argument("--sigterm-at", default="0.05,0.1,0.15,0.2,0.25", help="with --handler: seconds after spawn")
    args = p.parse_args(argv)
    if args.handler:
        return handler_main(args)
    extra = [x for kv in args.set for x in ("--set", kv)]
    variants = [("current", sys.executable)]
    if args.baseline_python:
        variants.insert(0, ("baseline", args.baseline_python))
    runs: dict[str, list[dict[str, Any]]] = {name: [] for name, _ in variants}
    bytecode = not args.no_bytecode
    if bytecode:  # one untimed start each: the package's bytecode written, as an installation has it
        for _name, python in variants:
            run_once(python, args.port_base, args.max_after_s, extra)
    for i in range(args.runs):
        for name, python in variants if i % 2 == 0 else variants[::-1]:
            r = run_once(python, args.port_base, args.max_after_s, extra, bytecode)
            runs[name].append(r)
            print(
                f"  run {i + 1}/{args.runs} {name}: READY=1 at {r['ready']:.2f} s, "
                + ", ".join(f"{k} {r[k]:.2f} s" for k in MARKS if k in r),
                file=sys.stderr,
                flush=True,
            )
    how = "bytecode compiled, as installed" if bytecode else "no bytecode: modules compiled at every start"
    print(f"ballbar run --simulate, every output on ({how}): seconds from spawn, median of {args.runs} (min..max)")
    print(
        f"{'variant':<10}{'READY=1':>18}{'CPU at READY':>18}{'source opened':>18}{'rerun serving':>18}"
        f"{'SIGTERM->exit':>16}"
    )

    def col(rs: list[dict[str, Any]], key: str) -> str:
        xs = [r[key] for r in rs if key in r]
        if not xs:
            return f"{'-':>18}"
        return f"{statistics.median(xs):>7.2f} ({min(xs):.2f}..{max(xs):.2f})"

    for name, _ in variants:
        rs = runs[name]
        print(f"{name:<10}{col(rs, 'ready')}{col(rs, 'cpu')}{col(rs, 'opened')}{col(rs, 'rerun')}"
              f"{statistics.median(r['stop'] for r in rs):>15.2f}s")
        bad = [r["code"] for r in rs if r["code"] != 0]
        if bad:
            print(f"  exit codes after SIGTERM: {bad}")
    if args.baseline_python:
        base = statistics.median(r["ready"] for r in runs["baseline"])
        cur = statistics.median(r["ready"] for r in runs["current"])
        print(f"READY=1: baseline / current = {base / cur:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
