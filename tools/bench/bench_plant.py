"""A plant of daemons on one Zenoh router: delivery, catch-up, liveliness, a router restart.

::

    python -m ballbar.tools.bench.bench_plant                       # 10 daemons, ~90 s
    python -m ballbar.tools.bench.bench_plant --daemons 4 --json plant.json

Starts a Zenoh router (a session in router mode, standing in for ``zenohd``) on
loopback, a subscriber of every machine's results and events (``ballbar-subscribe
--alive``) before any daemon, then N ``ballbar run --simulate`` daemons, each a
Zenoh client of the router with its own machine id, state directory and
simulated device (100 Hz, sped up).  It then checks and measures:

- the early subscriber receives test results from every machine; the
  end-to-end latency of each result (receipt minus ``last_sample_t_host``: the
  daemons and the subscriber share this host's monotonic clock), and its transit
  (receipt minus ``t_host``, the publication);
- a late subscriber (``--history``) gets every machine's results;
- ``kill -9`` of one daemon: how long until the subscriber sees it leave
  (liveliness);
- the router closed for ``--down-s`` and opened again: how long until results
  flow again, and whether a ``--history --since`` query afterwards holds every
  result the daemons logged (their MCAP records) while it was down;
- the router's message rate: Zenoh messages through it per second (its
  transports' counters are not exposed to Python, so: the payloads its
  subscribers received, counted by a second subscriber of ``ballbar/**``, per
  second of the run).

Loopback only (ports 17500-17599 unless ``--port``); everything stops by itself.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from ballbar.daemon.bus import ZenohConfig


def free_port(lo: int = 17500, hi: int = 17599) -> int:
    for port in range(lo, hi + 1):
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"no free port in {lo}..{hi}")


class Router:
    """A Zenoh session in router mode on ``tcp/127.0.0.1:<port>``, counting what passes ``ballbar/**``."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self.session: zenoh.Session | None = None
        self.messages = 0
        self.bytes = 0
        self._sub: Any = None
        self.open()

    def open(self) -> None:
        cfg = ZenohConfig(mode="router", listen=[self.endpoint]).to_zenoh_config()
        deadline = time.monotonic() + 10
        while True:
            try:
                self.session = zenoh.open(cfg)
                break
            except zenoh.ZError:  # the port is still in TIME_WAIT after a close
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self._sub = self.session.declare_subscriber("ballbar/**", self._count)

    def _count(self, sample: zenoh.Sample) -> None:
        self.messages += 1
        self.bytes += len(sample.payload)

    def close(self) -> None:
        if self.session is not None:
            self.session.close()
            self.session = None


class Subscriber:
    """``ballbar-subscribe`` as a process, its JSON lines in a file, each stamped on receipt (monotonic)."""

    def __init__(self, tmp: Path, endpoint: str, *args: str, name: str = "sub") -> None:
        self.path = tmp / f"{name}.jsonl"
        self.err_path = tmp / f"{name}.err"
        self.lines: list[tuple[float, dict[str, Any]]] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--connect", endpoint, *args],
            stdout=subprocess.PIPE, stderr=open(self.err_path, "w"), text=True,  # noqa: SIM115
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            if line.strip():
                self.lines.append((time.monotonic(), json.loads(line)))

    def of(self, kind: str) -> list[tuple[float, dict[str, Any]]]:
        return [(t, o) for t, o in self.lines if o.get("kind") == kind]

    def stop(self, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self._reader.join(5)
        return code

    def wait(self, timeout: float) -> int:
        code = self.proc.wait(timeout)
        self._reader.join(5)
        return code


@dataclass
class Daemon:
    machine: str
    state: Path
    proc: subprocess.Popen[bytes]
    log: Path

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@dataclass
class Plant:
    tmp: Path
    router: Router
    daemons: list[Daemon] = field(default_factory=list)

    def start_daemon(self, machine: str, speedup: float, rate: float) -> Daemon:
        state = self.tmp / machine
        log = self.tmp / f"{machine}.log"
        proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--simulate", "--speedup", f"{speedup:g}",
             "--machine-id", machine, "--state-dir", str(state),
             "--set", 'zenoh.mode="client"', "--set", f'zenoh.connect=["{self.router.endpoint}"]',
             "--set", 'rerun.mode="off"', "--set", f"plan.sample_hz={rate:g}", "--set", "daemon.status_interval_s=2"],
            stdout=open(log, "w"), stderr=subprocess.STDOUT,  # noqa: SIM115
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        d = Daemon(machine, state, proc, log)
        self.daemons.append(d)
        return d

    def stop(self) -> None:
        for d in self.daemons:
            if d.proc.poll() is None:
                d.proc.send_signal(signal.SIGTERM)
        for d in self.daemons:
            try:
                d.proc.wait(15)
            except subprocess.TimeoutExpired:
                d.kill()


@contextlib.contextmanager
def plant(tmp: Path, port: int | None = None) -> Iterator[Plant]:
    router = Router(port or free_port())
    p = Plant(tmp, router)
    try:
        yield p
    finally:
        p.stop()
        router.close()


def wait_for(pred: Any, timeout: float, what: str) -> float:
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(f"timed out after {timeout:.0f} s waiting for {what}")
        time.sleep(0.05)
    return time.monotonic() - t0


def machines_with(sub: Subscriber, kind: str, since: float = 0.0) -> set[str]:
    return {o["machine_id"] for t, o in sub.of(kind) if t >= since}


def logged_results(state: Path) -> list[dict[str, Any]]:
    from ballbar.daemon.mcap import list_recordings, read_results

    rec = state / "recordings"
    logging.getLogger("ballbar.daemon.mcap").setLevel(logging.ERROR)  # the open files end early: expected
    return read_results(list_recordings(rec)) if rec.is_dir() else []


def run(n: int, speedup: float, rate: float, down_s: float, tmp: Path, port: int | None = None) -> dict[str, Any]:
    """The scenario of the module docstring; the figures as a dict (raises on a failed check)."""
    out: dict[str, Any] = {"daemons": n, "speedup": speedup, "sample_hz": rate}
    with plant(tmp, port) as p:
        early = Subscriber(tmp, p.router.endpoint, "--topic", "test", "--topic", "event", "--alive", name="early")
        t_start = time.monotonic()
        names = [f"m{i:02d}" for i in range(n)]
        for m in names:
            p.start_daemon(m, speedup, rate)
        out["all_results_s"] = wait_for(lambda: machines_with(early, "test") >= set(names), 60 + 12 * n,
                                        "a test result from every machine")
        out["all_results_s"] = round(time.monotonic() - t_start, 1)
        # A late subscriber catches up from history, every machine.
        late = Subscriber(tmp, p.router.endpoint, "--history", "--topic", "test", "--timeout", "8", name="late")
        late.wait(30)
        got = {o["machine_id"] for _, o in late.of("test")}
        assert got >= set(names), f"history: missing {sorted(set(names) - got)}"
        out["late_history_machines"] = len(got)
        # kill -9: the daemon leaves the liveliness at once.
        victim = p.daemons[0]
        t_kill = time.monotonic()
        victim.kill()
        wait_for(lambda: any(o.get("alive") is False and o["machine_id"] == victim.machine and t >= t_kill
                             for t, o in early.of("alive")), 15, "the killed daemon's liveliness to go")
        gone = [t for t, o in early.of("alive") if o.get("alive") is False and o["machine_id"] == victim.machine]
        out["liveliness_drop_s"] = round(gone[-1] - t_kill, 3)
        # The router restarts: nobody else restarts, and history holds what was published meanwhile.
        living = names[1:]
        t_down_wall = time.time()
        t_down = time.monotonic()
        p.router.close()
        time.sleep(down_s)
        p.router.open()
        t_up = time.monotonic()
        t_up_wall = time.time()
        out["router_down_s"] = round(t_up - t_down, 1)
        out["results_again_s"] = round(wait_for(
            lambda: machines_with(early, "test", since=t_up) >= set(living), 60 + 12 * n,
            "results from every living machine after the router restart"), 1)
        # What each daemon logged as published while the router was down: a history query gets every one.
        during: set[tuple[str, str]] = set()
        for d in p.daemons[1:]:
            for r in logged_results(d.state):
                if r.get("kind") == "test" and t_down_wall <= _unix(r.get("t_wall")) <= t_up_wall:
                    during.add((d.machine, r["t_wall"]))
        since = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(t_down_wall - 1))
        after = Subscriber(tmp, p.router.endpoint, "--history", "--since", since, "--topic", "test", "--timeout", "8",
                           name="after")
        after.wait(30)
        have = {(o["machine_id"], o["t_wall"]) for _, o in after.of("test")}
        missing = during - have
        assert not missing, f"results published while the router was down, missing from history: {sorted(missing)}"
        out["published_while_down"] = len(during)
        # Latency, across the router, of every live result the early subscriber got.
        lat = sorted(1000.0 * (t - o["last_sample_t_host"]) for t, o in early.of("test")
                     if isinstance(o.get("last_sample_t_host"), float))
        pub = sorted(o["latency_ms"] for _, o in early.of("test") if isinstance(o.get("latency_ms"), float))
        transit = sorted(1000.0 * (t - o["t_host"]) for t, o in early.of("test") if isinstance(o.get("t_host"), float))
        out["results_received"] = len(lat)
        out["transit_ms"] = _quantiles(transit)  # publication to receipt, through the router
        out["latency_ms"] = _quantiles(lat)
        out["published_latency_ms"] = _quantiles(pub)
        elapsed = time.monotonic() - t_start
        out["router_messages"] = p.router.messages
        out["router_msgs_per_s"] = round(p.router.messages / elapsed, 1)
        out["router_kbytes_per_s"] = round(p.router.bytes / elapsed / 1000, 1)
        out["elapsed_s"] = round(elapsed, 1)
        out["early_exit"] = early.stop()
        out["payloads"] = [o for _, o in early.lines + late.lines + after.lines]
    return out


def _unix(t: Any) -> float:
    from ballbar.daemon.bus import parse_time_us

    try:
        return parse_time_us(t) / 1e6 if isinstance(t, str) else float("nan")
    except ValueError:
        return float("nan")


def _quantiles(xs: list[float]) -> dict[str, float | None]:
    if not xs:
        return {"median": None, "p90": None, "max": None}
    return {"median": round(xs[len(xs) // 2], 1), "p90": round(xs[int(0.9 * (len(xs) - 1))], 1),
            "max": round(xs[-1], 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_plant", description=__doc__.split("\n\n")[0])
    ap.add_argument("--daemons", type=int, default=10)
    ap.add_argument("--speedup", type=float, default=20.0, help="each simulated device's speed-up")
    ap.add_argument("--rate", type=float, default=100.0, help="each device's sample rate, Hz")
    ap.add_argument("--down-s", type=float, default=10.0, help="how long the router stays down")
    ap.add_argument("--port", type=int, help="the router's port (default: free in 17500-17599)")
    ap.add_argument("--json", metavar="FILE", help="write the figures here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ballbar-plant-") as tmp:
        res = run(args.daemons, args.speedup, args.rate, args.down_s, Path(tmp), args.port)
    res.pop("payloads")
    text = json.dumps(res, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
