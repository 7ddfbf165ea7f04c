"""What the simulated device costs: its CPU time per wall second, streaming to a reader.

    python -m ballbar.tools.bench.bench_simdevice                         # 15.625 Hz, 1 kHz, 10 kHz; 30 s each
    python -m ballbar.tools.bench.bench_simdevice --baseline main --repeats 3

:mod:`ballbar.tools.simdevice` runs in a child process (``--repeat 0``, the default test
plan, speed-up 1 unless ``--speedup``); this process reads its pty raw, as fast as bytes
come. After ``--warmup-s`` the device's CPU time (utime + stime of ``/proc/PID/stat``,
so the count covers every thread) is read, and again ``--seconds`` later: CPU is that
difference over the wall time, in percent of one core. Also per run: the device's
wake-ups per second (its voluntary context switches), the samples per second that arrived, and
for the binary protocol how late they arrived: each frame's arrival time minus its
device time (over the speed-up), less the smallest such difference of the run (the
delivery delay the bursts add; a real USB adapter adds its own, e.g. FTDI's 16 ms
latency timer).

``--baseline REV``: the same measurement of ``tools/simdevice.py`` as committed at
``REV`` (``git show``), run as a script against this checkout's package, interleaved
with the current one (order alternating from repeat to repeat): on a shared machine
only figures of the same run compare. Reported per rate: medians of the repeats, and
the ratio baseline / current.

The one-time cost of simulating each test (about 0.3 to 0.6 s of CPU per 160 s test
of the default plan, before its first sample goes out) falls outside a window of
less than one test's duration after the start.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import select
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ballbar.daemon import procfs
from ballbar.protocol import binary as binary_proto


def proc_cpu_s(pid: int) -> float:
    """utime + stime of a process, seconds."""
    return procfs.cpu_seconds(pid)


def proc_wakes(pid: int) -> int:
    """Voluntary context switches of a process (all its threads): how often it went to sleep."""
    return sum(int(procfs.status(pid, tid)["voluntary_ctxt_switches"]) for tid in procfs.threads(pid))


def baseline_script(rev: str, directory: str) -> list[str]:
    """``tools/simdevice.py`` as committed at ``rev``, with the modules of ``tools/`` beside it that it imports
    (the device is three modules: :mod:`.simdevice`, :mod:`.simbar`, :mod:`.simfeed`), written to ``directory`` as
    the package ``baseline`` (their imports of ``ballbar.tools.X`` made ``baseline.X``); the command that runs it."""
    root = Path(__file__).resolve().parent.parent
    names = subprocess.run(
        ["git", "-C", str(root), "ls-tree", "--full-tree", "--name-only", rev, "tools/"],
        check=True, capture_output=True, text=True,
    ).stdout.split()
    package = os.path.join(directory, "baseline")
    os.makedirs(package, exist_ok=True)
    with open(os.path.join(package, "__init__.py"), "wb"):
        pass
    for name in (n for n in names if n.endswith(".py") and n != "tools/__init__.py"):
        text = subprocess.run(["git", "-C", str(root), "show", f"{rev}:{name}"], check=True, capture_output=True).stdout
        with open(os.path.join(package, os.path.basename(name)), "wb") as f:
            f.write(text.replace(b"ballbar.tools.", b"baseline."))  # REV's own modules, not the installed ones
    run = f"import runpy, sys; sys.path.insert(0, {directory!r}); runpy.run_module('baseline.simdevice', "
    return [sys.executable, "-c", run + "run_name='__main__')"]


def _line(fd: int, buf: bytearray, deadline: float) -> str:
    while b"\n" not in buf:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("simdevice: no output")
        if select.select([fd], [], [], left)[0]:
            chunk = os.read(fd, 65536)
            if not chunk:
                raise EOFError("simdevice exited")
            buf += chunk
    i = buf.index(b"\n")
    line = bytes(buf[:i]).decode()
    del buf[: i + 1]
    return line


def run_once(
    command: Sequence[str], rate: float, speedup: float, protocol: str, seconds: float, warmup_s: float
) -> dict[str, Any]:
    """One device, one measurement window."""
    with tempfile.TemporaryDirectory(prefix="ballbar-bench-simdevice-") as tmp:
        args = [
            *command, "--exit-on-eof", "--wait", f"--protocol={protocol}", f"--rate={rate:g}",
            f"--speedup={speedup:g}", "--repeat=0", f"--link={tmp}/tty",
        ]
        if protocol == "ascii":
            args.append("--timestamp=us")
        proc = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert proc.stdin is not None and proc.stdout is not None
        fd = -1
        try:
            out = bytearray()
            path = _line(proc.stdout.fileno(), out, time.monotonic() + 60)
            json.loads(_line(proc.stdout.fileno(), out, time.monotonic() + 10))
            fd = os.open(path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
            proc.stdin.write(b"start\n")
            proc.stdin.flush()
            data = bytearray()
            reads: list[tuple[float, int]] = []  # (arrival, bytes so far)
            t_start = time.monotonic()
            t0 = t_start + warmup_s
            t1 = t0 + seconds
            cpu0 = sw0 = None
            n0 = 0
            while True:
                now = time.monotonic()
                if cpu0 is None and now >= t0:
                    cpu0, sw0, n0, t0 = proc_cpu_s(proc.pid), proc_wakes(proc.pid), len(data), now
                if now >= t1:
                    break
                if select.select([fd], [], [], min(0.1, t1 - now))[0]:
                    with contextlib.suppress(BlockingIOError):
                        while True:
                            chunk = os.read(fd, 1 << 16)
                            if not chunk:
                                break
                            data += chunk
                    if cpu0 is not None:
                        reads.append((time.monotonic(), len(data)))
            cpu1, sw1, t1 = proc_cpu_s(proc.pid), proc_wakes(proc.pid), time.monotonic()
            n1 = len(data)
        finally:
            if fd >= 0:
                os.close(fd)
            with contextlib.suppress(OSError):
                proc.stdin.write(b"quit\n")
                proc.stdin.close()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            proc.stdout.close()
    assert cpu0 is not None and sw0 is not None
    wall = t1 - t0
    res: dict[str, Any] = {
        "rate": rate,
        "speedup": speedup,
        "protocol": protocol,
        "seconds": wall,
        "cpu_pct": 100.0 * (cpu1 - cpu0) / wall,
        "wakes_per_s": (sw1 - sw0) / wall,
        "bytes_per_s": (n1 - n0) / wall,
    }
    if protocol == "binary":
        dec = binary_proto.decode(bytes(data))
        fr = dec.frames
        ends = (np.arange(fr.shape[0]) + 1) * binary_proto.FRAME_SIZE
        seq = fr["seq"].astype(np.int64)
        res["ok"] = bool(not any(dec.dropped.values()) and np.all(np.diff(seq) == 1))
        k = np.searchsorted(ends, n0, side="right")  # the first frame completed in the window
        if reads:
            at, cum = np.array([r[0] for r in reads]), np.array([r[1] for r in reads])
            fin = ends[k:]
            fin = fin[fin <= cum[-1]]
            arrival = at[np.searchsorted(cum, fin, side="left")]
            due = fr["clock_us"][k : k + fin.shape[0]].astype(np.float64) / 1e6 / speedup
            delay = arrival - due
            delay -= delay.min()
            res["samples_per_s"] = fin.shape[0] / wall
            res["delay_ms_median"] = 1e3 * float(np.median(delay))
            res["delay_ms_p99"] = 1e3 * float(np.percentile(delay, 99))
    else:
        lines = data[n0:].count(b"\n")
        res["ok"] = True
        res["samples_per_s"] = lines / wall
    return res


def _fmt_row(name: str, rate: float, runs: list[dict[str, Any]]) -> str:
    cpu = [r["cpu_pct"] for r in runs]
    med = statistics.median
    delay = (
        f"{med(r['delay_ms_median'] for r in runs):>10.1f}{med(r['delay_ms_p99'] for r in runs):>8.1f}"
        if "delay_ms_median" in runs[0]
        else f"{'-':>10}{'-':>8}"
    )
    return (
        f"{rate:>9g}  {name:<10}{med(cpu):>8.2f}%{min(cpu):>8.2f}{max(cpu):>8.2f}"
        f"{med(r['wakes_per_s'] for r in runs):>9.0f}{med(r['samples_per_s'] for r in runs):>11.1f}"
        f"{delay}  {'yes' if all(r['ok'] for r in runs) else 'NO'}"
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_simdevice",
                                description=__doc__.split("\n")[0])
    p.add_argument("--rates", default="15.625,1000,10000", help="device sample rates, Hz, comma-separated")
    p.add_argument("--speedup", type=float, default=1.0)
    p.add_argument("--protocol", choices=["binary", "ascii"], default="binary")
    p.add_argument("--seconds", type=float, default=30.0, help="measurement window per run")
    p.add_argument("--warmup-s", type=float, default=2.0, help="streaming before the window opens")
    p.add_argument("--repeats", type=int, default=1)
    p.add_argument("--baseline", metavar="REV", help="also measure tools/simdevice.py as committed at REV")
    p.add_argument("--device-args", default="", help="more arguments for the current device, e.g. '--burst-ms=5'")
    p.add_argument("--json", help="write every run here")
    args = p.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    with tempfile.TemporaryDirectory(prefix="ballbar-bench-simdevice-") as tmp:
        variants: list[tuple[str, list[str]]] = [
            ("current", [sys.executable, "-m", "ballbar.tools.simdevice", *args.device_args.split()])
        ]
        if args.baseline:
            variants.insert(0, (args.baseline, baseline_script(args.baseline, tmp)))
        runs: dict[tuple[str, float], list[dict[str, Any]]] = {}
        for rep in range(args.repeats):
            for rate in rates:
                order = variants if rep % 2 == 0 else variants[::-1]
                for name, command in order:
                    r = run_once(command, rate, args.speedup, args.protocol, args.seconds, args.warmup_s)
                    r["variant"] = name
                    runs.setdefault((name, rate), []).append(r)
                    print(
                        f"  run {rep + 1}/{args.repeats} {name} {rate:g} Hz: {r['cpu_pct']:.2f} % CPU, "
                        f"{r['wakes_per_s']:.0f} wakes/s",
                        file=sys.stderr,
                        flush=True,
                    )
    print(
        f"simdevice CPU, {args.protocol}, speed-up {args.speedup:g}, {args.seconds:g} s windows, "
        f"median of {args.repeats} (% of one core; python {sys.version.split()[0]})"
    )
    print(
        f"{'rate Hz':>9}  {'variant':<10}{'CPU':>9}{'min':>8}{'max':>8}{'wakes/s':>9}{'samples/s':>11}"
        f"{'delay ms':>10}{'p99':>8}  ok"
    )
    for rate in rates:
        for name, _ in variants:
            print(_fmt_row(name, rate, runs[(name, rate)]))
        if args.baseline:
            base = statistics.median(r["cpu_pct"] for r in runs[(args.baseline, rate)])
            cur = statistics.median(r["cpu_pct"] for r in runs[("current", rate)])
            print(f"{'':>9}  ratio {args.baseline} / current: {base / cur if cur > 0 else float('inf'):.1f}x")
    if args.json:
        with open(args.json, "w") as f:
            json.dump([r for rs in runs.values() for r in rs], f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
