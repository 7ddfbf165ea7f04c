"""The daemon's cost, measured: CPU, context switches, memory and result latency per sample rate.

For each rate the bench starts the simulated ball-bar (:mod:`ballbar.tools.simdevice`, on a pty,
the demo machine of ``ballbar run --simulate``) and ``ballbar run`` reading it with every output
on, as a service runs: MCAP into a state directory of its own, Zenoh as a peer listening on
loopback, the Rerun server on loopback (ports from 7700-7799).  Beside it, over the same
window, the **baseline**: a second simulated device at the same rate and a bare reader of its
pty (pyserial reads every 20 ms, the protocol's decoder; nothing else), measured the same way.
The two run together so that both see the same contention on a shared machine, and the
daemon's figures are given as ratios to the baseline's.  The two devices are a control: their
CPU should agree (``device/baseline device`` near 1) when the window was fair to both.

Per rate, over the window (default: one whole test of the plan, from 10 s after the device
starts; at speedup 1 a test of the default plan takes 160 s including the 5 s gap):

- CPU per process (daemon, its children such as the Rerun server, device, baseline reader,
  baseline device) and per thread of the daemon, as % of one core, from
  ``/proc/PID/task/*/stat`` (utime + stime); the daemon's Python threads carry their
  ``threading`` names (the daemon runs under a small wrapper that copies each Python thread's
  name to its kernel ``comm``; ``--no-thread-names`` runs ``ballbar run`` bare);
- context switches per second (voluntary + involuntary), per process, summed over its
  threads (``/proc/PID/task/*/status``; threads that exit inside the window are not counted);
- resident memory (``VmRSS``) every second: start, end, and its least-squares slope over the
  window in MiB/min;
- the latency of circle and test results as seen by a separate Zenoh subscriber process:
  ``time.monotonic()`` at receipt minus the result's ``last_sample_t_host`` (the host time of
  the last sample it used, same clock), and the daemon's own ``latency_ms``; median and p99;
- from the daemon's status messages: the queues' largest depth and drops, lost samples.

Run::

    python -m ballbar.tools.bench.bench_daemon                        # 15.625 Hz, 1 kHz, 10 kHz at x1, ~10 min
    python -m ballbar.tools.bench.bench_daemon --rates 1000 --speedup 20 --tests 5   # latency at x20
    python -m ballbar.tools.bench.bench_daemon --quick --rates 1000   # x5, a 20 s window: a smoke test
    python -m ballbar.tools.bench.bench_daemon --outputs mcap         # only the MCAP log (diagnosis)
    python -m ballbar.tools.bench.bench_daemon --soak-min 60 --speedup 20 --json soak.json

Soak (``--soak-min``): one rate (default 1 kHz) at x20 (unless ``--speedup``) for that many
minutes; after ``--soak-warmup-min`` (default 35: at x20 a test takes 8 s, so by then the
daemon's circle and event histories on Zenoh hold their 500 entries each; its test history
fills only after 500 tests, 67 min) the resident memory's growth per hour of wall time and
per hour of operation (device time: wall x speedup), by 5-minute medians too, the queue
depths (median, p99, max) and every loss counter.

Exit code 0, 1 when a process failed or the daemon lost samples, 2 on a usage error.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from ballbar.daemon import procfs
from ballbar.daemon.analysis_worker import WORKER, child_role
from ballbar.tools.bench.daemon_children import Child, Notify, daemon_main, free_port, reader_main, subscriber_main
from ballbar.tools.bench.daemon_usage import (
    CLK_TCK,
    ProcSnapshot,
    _restarts,
    descendants,
    distribution,
    rss_mib,
    rss_summary,
    slope_per_min,
    snapshot,
    usage,
)

log = logging.getLogger("ballbar.bench_daemon")

MACHINE = "bench"
DEFAULT_RATES = (15.625, 1000.0, 10000.0)
OUTPUTS = ("mcap", "zenoh", "rerun")
# The issue's goals for the daemon's CPU (% of one core, x1) and result latency (1 kHz at x20).
CPU_GOAL_PCT = {15.625: 2.0, 1000.0: 5.0, 10000.0: 8.0}
LATENCY_GOAL_P99_MS = {"circle": 50.0, "test": 250.0}
FALLBACK_TEST_PERIOD_S = 160.0
ANALYSIS_WORKER = f"daemon child {WORKER}"  # the daemon's child that fits each test: its CPU is the daemon's too
SLOWEST = 12  # the slowest results listed per kind, with when they came




# ----------------------------------------------------------------------------- one rate


def schedule_period_s(cfg: Any) -> float:
    """Device seconds from one test's first sample to the next's (the simulated device's schedule)."""
    try:
        from ballbar.tools.simulate import SIM_MACHINE, simdevice_args
        from ballbar.tools.simulator import MachineModel, iter_tests
        from ballbar.tools.simulator_cli import parse_set

        argv = simdevice_args(cfg, 1.0)
        gap = float(argv[argv.index("--gap-s") + 1])
        tests = iter_tests(cfg.plan, MachineModel(**parse_set(SIM_MACHINE)), 15.625, 0, 2, gap)
        first, second = next(tests), next(tests)
        return float(second.t_s[0] - first.t_s[0])
    except Exception as err:  # the schedule is a convenience: the bench still runs on the fallback
        log.warning("cannot compute the test period (%s); assuming %g s", err, FALLBACK_TEST_PERIOD_S)
        return FALLBACK_TEST_PERIOD_S


@dataclass
class Plan:
    """What one measurement does (resolved from the command line)."""

    rate: float
    speedup: float
    outputs: tuple[str, ...]
    baseline: str  # raw, source or off
    warmup_s: float
    window_s: float
    expect_tests: int  # wait (after the window) until this many test results came, within a grace
    test_period_s: float
    grace_s: float
    sets: tuple[str, ...] = ()
    thread_names: bool = True
    soak: bool = False
    progress_s: float = 0.0  # soak: a progress line every this many seconds


class Measurement:
    """One rate: the processes, the sampling loop, the figures."""

    def __init__(self, plan: Plan, workdir: Path) -> None:
        self.p = plan
        self.dir = workdir
        self.dir.mkdir(parents=True, exist_ok=True)
        self.stack = contextlib.ExitStack()
        self._lock = threading.Lock()
        self.results: dict[str, list[dict[str, Any]]] = {"circle": [], "test": []}
        self.statuses: list[dict[str, Any]] = []
        self.events: dict[str, int] = {}
        self.rss: dict[str, tuple[list[float], list[float]]] = {}
        self.problems: list[str] = []

    # -- the subscriber's lines, on its reader thread
    def _on_bus(self, obj: dict[str, Any]) -> None:
        k = obj.get("k")
        with self._lock:
            if k in ("circle", "test"):
                self.results[str(k)].append(obj)
            elif k == "status":
                self.statuses.append(obj)
            elif k == "event":
                name = str(obj.get("event"))
                self.events[name] = self.events.get(name, 0) + 1

    def run(self) -> dict[str, Any]:
        with self.stack:
            return self._run()

    def _config(self) -> tuple[Path, Any]:
        from ballbar.daemon.config import load

        p = self.p
        self.zport = free_port() if "zenoh" in p.outputs else 0
        self.rport = free_port() if "rerun" in p.outputs else 0
        self.endpoint = f"tcp/127.0.0.1:{self.zport}"
        state = self.dir / "state"
        conf = self.dir / "bench.toml"
        conf.write_text(
            f'[daemon]\nmachine_id = "{MACHINE}"\nstate_dir = "{state}"\nstatus_interval_s = 1.0\n'
            f'[mcap]\nenabled = {"true" if "mcap" in p.outputs else "false"}\n'
            f'[zenoh]\nenabled = {"true" if "zenoh" in p.outputs else "false"}\nmode = "peer"\n'
            f'listen = ["{self.endpoint}"]\n'
            f'[rerun]\nmode = "{"serve" if "rerun" in p.outputs else "off"}"\nbind = "127.0.0.1"\n'
            f'port = {self.rport or 9880}\n'
        )
        self.sets = [f"plan.sample_hz={p.rate:g}", *p.sets]
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("BALLBAR") and k != "NOTIFY_SOCKET"}
        cfg = load(str(conf), self.sets, env=self.env)
        return conf, cfg

    def _device(self, cfg: Any, name: str) -> Any:
        from ballbar.tools.simdevice import DeviceProcess
        from ballbar.tools.simulate import simdevice_args

        dev = DeviceProcess(*simdevice_args(cfg, self.p.speedup), "--wait", "--seed", "0", timeout=60.0)
        self.stack.callback(dev.close)
        log.debug("%s on %s", name, dev.path)
        return dev

    def _start(self) -> None:
        p = self.p
        conf, cfg = self._config()
        self.dev = self._device(cfg, "device")
        self.base_dev = self._device(cfg, "baseline device") if p.baseline != "off" else None
        notify = Notify(self.dir / "notify.sock")
        self.stack.callback(notify.close)
        env = dict(self.env, NOTIFY_SOCKET=notify.path, PYTHONUNBUFFERED="1")
        args = ["run", "--config", str(conf), "--source", self.dev.url]
        for s in self.sets:
            args += ["--set", s]
        head = ([sys.executable, "-m", "ballbar.tools.bench.bench_daemon", "_daemon"] if p.thread_names
                else [sys.executable, "-m", "ballbar.daemon.cli"])
        self.daemon_log_path = self.dir / "daemon.log"
        daemon_log = open(self.daemon_log_path, "wb")  # noqa: SIM115 - closed by the stack
        self.stack.callback(daemon_log.close)
        self.daemon = subprocess.Popen([*head, *args], env=env, stdin=subprocess.DEVNULL, stdout=daemon_log,
                                       stderr=subprocess.STDOUT)
        self.stack.callback(self._kill, self.daemon)
        notify.wait_ready(self.daemon, 120.0)
        helpers_log = open(self.dir / "helpers.log", "wb")  # noqa: SIM115 - closed by the stack
        self.stack.callback(helpers_log.close)
        me = [sys.executable, "-m", "ballbar.tools.bench.bench_daemon"]
        self.sub: Child | None = None
        if "zenoh" in p.outputs:
            self.sub = Child("subscriber", [*me, "_subscriber", self.endpoint, MACHINE], helpers_log, self._on_bus)
            self.stack.callback(self.sub.stop)
            self.sub.wait_line("ready", 60.0)
        self.reader: Child | None = None
        if self.base_dev is not None:
            target = self.base_dev.path if p.baseline == "raw" else self.base_dev.url
            self.reader = Child("baseline reader", [*me, "_reader", p.baseline, target], helpers_log)
            self.stack.callback(self.reader.stop)
            self.reader.wait_line("ready", 60.0)
        self.dev.send("start")
        if self.base_dev is not None:
            self.base_dev.send("start")

    @staticmethod
    def _kill(proc: subprocess.Popen[bytes]) -> None:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)

    def _processes(self) -> dict[str, int]:
        """Role -> pid of what is measured now (the daemon's children by name)."""
        out = {"daemon": self.daemon.pid, "device": self.dev.proc.pid}
        for kid in descendants(self.daemon.pid):
            name = str(kid)
            with contextlib.suppress(OSError, ValueError, IndexError):
                name = procfs.stat(kid)[0]
            role = f"daemon child {child_role(kid) or name}"
            out[role if role not in out else f"{role} [{kid}]"] = kid
        if self.reader is not None and self.base_dev is not None:
            out["baseline reader"] = self.reader.proc.pid
            out["baseline device"] = self.base_dev.proc.pid
        if self.sub is not None:
            out["subscriber"] = self.sub.proc.pid
        return out

    def _snapshots(self) -> dict[str, ProcSnapshot]:
        snaps = {}
        for role, pid in self._processes().items():
            s = snapshot(pid)
            if s is not None:
                snaps[role] = s
        return snaps

    def _sample_rss(self, t_rel: float) -> None:
        for role, pid in self._processes().items():
            v = rss_mib(pid)
            if v is not None:
                ts, vs = self.rss.setdefault(role, ([], []))
                ts.append(t_rel)
                vs.append(v)

    def _check_alive(self) -> None:
        if self.daemon.poll() is not None:
            raise RuntimeError(f"the daemon exited with code {self.daemon.returncode} (see {self.daemon_log_path})")
        for dev in (self.dev, self.base_dev):
            if dev is not None and dev.proc.poll() is not None:
                raise RuntimeError(f"a simulated device exited with code {dev.proc.returncode}")

    def _progress(self, t_rel: float) -> None:
        with self._lock:
            st = self.statuses[-1] if self.statuses else {}
            n_c, n_t = len(self.results["circle"]), len(self.results["test"])
        rss = self.rss.get("daemon", ([], []))[1]
        depth = {k: v.get("depth") for k, v in (st.get("queues") or {}).items()}
        log.info("%6.1f min  daemon RSS %.1f MiB  results %d circles, %d tests  lost %s  queues %s",
                 t_rel / 60, rss[-1] if rss else math.nan, n_c, n_t, st.get("lost_samples"), depth)

    def _loop(self) -> tuple[dict[str, ProcSnapshot], dict[str, ProcSnapshot], float]:
        p = self.p
        t0 = time.monotonic()
        w0, w1 = t0 + p.warmup_s, t0 + p.warmup_s + p.window_s
        snap_a: dict[str, ProcSnapshot] | None = None
        snap_b: dict[str, ProcSnapshot] | None = None
        next_sample = t0
        next_progress = t0 + p.progress_s if p.progress_s else math.inf
        while True:
            now = time.monotonic()
            if snap_a is None and now >= w0:
                snap_a = self._snapshots()
            if snap_b is None and now >= w1:
                snap_b = self._snapshots()
                self._sample_rss(now - t0)
                break
            if now >= next_sample:
                self._sample_rss(now - t0)
                next_sample += 1.0
                self._check_alive()
                for dev in (self.dev, self.base_dev):
                    if dev is not None:
                        dev.poll_events()
            if now >= next_progress:
                self._progress(now - t0)
                next_progress += p.progress_s
            time.sleep(max(0.0, min(next_sample, w0 if snap_a is None else w1) - time.monotonic()))
        assert snap_a is not None
        # Results still due (the window ends before the last test's analysis): a grace, not measured.
        deadline = time.monotonic() + p.grace_s
        while self.sub is not None and time.monotonic() < deadline:
            with self._lock:
                if len(self.results["test"]) >= p.expect_tests:
                    break
            self._check_alive()
            time.sleep(0.5)
        return snap_a, snap_b, t0

    def _settle(self) -> dict[str, Any]:
        """The device stops sending; once the daemon has read everything, its count against the device's."""
        sent_before = int(self.dev.stats().get("sent", 0))
        for dev in (self.dev, self.base_dev):
            if dev is not None:
                dev.send("stall 1e9")
        sent = int(self.dev.stats().get("sent", 0))
        if self.sub is None:
            time.sleep(1.0)  # the reader and the daemon take what is on the wire
            return {"device_sent": sent}
        deadline = time.monotonic() + 15.0
        last = None
        steady = 0
        while time.monotonic() < deadline:
            time.sleep(0.5)
            with self._lock:
                st = self.statuses[-1] if self.statuses else None
            key = (st or {}).get("samples")
            steady = steady + 1 if key is not None and key == last else 0
            last = key
            if steady >= 4 and key is not None and key >= sent:
                break
        with self._lock:
            st = self.statuses[-1] if self.statuses else {}
        return {"device_sent": sent, "device_sent_before_stall": sent_before, "daemon_samples": st.get("samples"),
                "daemon_lost_samples": st.get("lost_samples")}

    def _run(self) -> dict[str, Any]:
        self._start()
        snap_a, snap_b, t0 = self._loop()
        accounting = self._settle()
        base_sent = int(self.base_dev.stats().get("sent", 0)) if self.base_dev is not None else None
        t_stop = time.monotonic()
        self.daemon.send_signal(signal.SIGTERM)
        try:
            code = self.daemon.wait(30)
        except subprocess.TimeoutExpired:
            code = None
            self.problems.append("the daemon did not exit within 30 s of SIGTERM")
        stop_s = time.monotonic() - t_stop
        if code not in (0, None):
            self.problems.append(f"the daemon exited with code {code}")
        reader_done: dict[str, Any] = {}
        if self.reader is not None:
            self.reader.stop()
            reader_done = next((x for x in self.reader.lines if x.get("k") == "done"), {})
        if self.sub is not None:
            self.sub.stop()
        return self._figures(snap_a, snap_b, t0, accounting, base_sent, reader_done, code, stop_s)

    def _figures(self, snap_a: dict[str, ProcSnapshot], snap_b: dict[str, ProcSnapshot], t0: float,
                 accounting: dict[str, Any], base_sent: int | None, reader_done: dict[str, Any],
                 code: int | None, stop_s: float) -> dict[str, Any]:
        p = self.p
        w0 = snap_a["daemon"].t - t0
        w1 = snap_b["daemon"].t - t0
        procs: dict[str, Any] = {}
        for role, b in snap_b.items():
            a = snap_a.get(role)
            if a is None or a.pid != b.pid:
                continue  # started (or restarted) inside the window: no whole-window figure
            u = usage(a, b)
            ts, vs = self.rss.get(role, ([], []))
            inside = [(t, v) for t, v in zip(ts, vs, strict=True) if w0 - 0.5 <= t <= w1 + 0.5]
            u["rss"] = rss_summary([t for t, _ in inside], [v for _, v in inside])
            if role not in ("daemon",):
                u.pop("threads")
            procs[role] = u
        ratios: dict[str, float | None] = {}
        d, r = procs.get("daemon"), procs.get("baseline reader")
        if d is not None and ANALYSIS_WORKER in procs:
            d["cpu_pct_with_worker"] = d["cpu_pct"] + procs[ANALYSIS_WORKER]["cpu_pct"]
        if d is not None and r is not None:
            ratios["cpu"] = d["cpu_pct"] / r["cpu_pct"] if r["cpu_pct"] > 0 else None
            if "cpu_pct_with_worker" in d and r["cpu_pct"] > 0:
                ratios["cpu_with_worker"] = d["cpu_pct_with_worker"] / r["cpu_pct"]
            ratios["ctx"] = d["ctx_per_s"] / r["ctx_per_s"] if r["ctx_per_s"] > 0 else None
            dr, rr = d["rss"], r["rss"]
            if dr.get("end_mib") and rr.get("end_mib"):
                ratios["rss"] = dr["end_mib"] / rr["end_mib"]
        dv, bv = procs.get("device"), procs.get("baseline device")
        if dv is not None and bv is not None and bv["cpu_pct"] > 0:
            ratios["device_control"] = dv["cpu_pct"] / bv["cpu_pct"]
        with self._lock:
            results = {k: list(v) for k, v in self.results.items()}
            statuses = list(self.statuses)
            events = dict(self.events)
        latency: dict[str, Any] = {}
        for kind, rows in results.items():
            # the subscriber's latency, ms, of each result that carries its last sample's host time
            timed = [(1000.0 * (r["rx"] - r["last_sample_t_host"]), r) for r in rows
                     if isinstance(r.get("last_sample_t_host"), int | float)]
            own = [ms for ms, _ in timed]
            latency[kind] = {
                "subscriber_ms": distribution(own),
                "published_ms": distribution(r.get("latency_ms") for r in rows),
                "delivery_ms": distribution(1000.0 * (r["rx"] - r["t_host"]) for r in rows
                                            if isinstance(r.get("t_host"), int | float)),
                "payload_bytes": distribution(r.get("bytes") for r in rows),
                "count": len(rows),
                # where the tail comes from: the slowest, by when in the window (beside the restarts below)
                "slowest": [{"at_s": round(r["rx"] - snap_a["daemon"].t, 3), "ms": round(ms, 1),
                             "test_id": r.get("test_id"), "direction": r.get("direction")}
                            for ms, r in sorted(timed, key=lambda x: -x[0])[:SLOWEST]],
            }
        latency["rerun_restarts_at_s"] = _restarts(statuses, snap_a["daemon"].t)
        queues = self._queues(statuses, t0 + p.warmup_s)
        last = statuses[-1] if statuses else {}
        lost = last.get("lost_samples")
        if lost:
            self.problems.append(f"the daemon counted {lost} lost samples")
        dropped = {k: v["dropped"] for k, v in queues.items() if v.get("dropped")}
        if dropped:
            self.problems.append(f"queues dropped items: {dropped}")
        out: dict[str, Any] = {
            "rate_hz": p.rate, "speedup": p.speedup, "outputs": list(p.outputs), "baseline": p.baseline,
            "warmup_s": p.warmup_s, "window_s": w1 - w0, "window_tests": (w1 - w0) * p.speedup / p.test_period_s,
            "test_period_device_s": p.test_period_s, "thread_names": p.thread_names, "sets": list(p.sets),
            "processes": procs, "ratios": ratios, "latency": latency, "queues": queues,
            "status": {"messages": len(statuses), "last": last}, "events": events,
            "accounting": dict(accounting, baseline_device_sent=base_sent,
                               baseline_reader_samples=reader_done.get("samples"),
                               baseline_reader_bytes=reader_done.get("bytes")),
            "daemon_exit": {"code": code, "stop_s": stop_s},
            "rss_series": {role: {"t_s": ts, "mib": vs} for role, (ts, vs) in self.rss.items()},
            "problems": self.problems,
        }
        if p.soak:
            out["soak"] = self._soak_figures(t0, statuses)
        return out

    @staticmethod
    def _queues(statuses: list[dict[str, Any]], t_from: float) -> dict[str, Any]:
        names = sorted({n for s in statuses for n in (s.get("queues") or {})})
        out: dict[str, Any] = {}
        for name in names:
            depths = [(s["queues"][name] or {}).get("depth") for s in statuses
                      if s["rx"] >= t_from and name in (s.get("queues") or {})]
            last = (statuses[-1].get("queues") or {}).get(name) or {}
            out[name] = {"depth": distribution(depths), "dropped": last.get("dropped", 0),
                         "errors": last.get("errors", 0), "capacity": last.get("capacity")}
        return out

    def _soak_figures(self, t0: float, statuses: list[dict[str, Any]]) -> dict[str, Any]:
        import numpy as np

        p = self.p
        out: dict[str, Any] = {"warmup_min": p.warmup_s / 60, "speedup": p.speedup}
        for role, (ts, vs) in self.rss.items():
            if not (role == "daemon" or role.startswith("daemon child")):
                continue
            t = np.array(ts)
            v = np.array(vs)
            after = t >= p.warmup_s
            per_min = slope_per_min(t[after].tolist(), v[after].tolist())
            segs = []
            for k in range(math.ceil(t[-1] / 300.0) if t.size else 0):
                m = (t >= 300 * k) & (t < 300 * (k + 1))
                if m.any():
                    segs.append({"from_min": 5 * k, "median_mib": float(np.median(v[m]))})
            out[role] = {
                "rss_at_warmup_mib": float(v[after][0]) if after.any() else None,
                "rss_end_mib": float(v[-1]) if v.size else None,
                "growth_mib_per_wall_hour": None if per_min is None else 60.0 * per_min,
                "growth_mib_per_operating_hour": None if per_min is None else 60.0 * per_min / p.speedup,
                "five_minute_medians": segs,
            }
        last = statuses[-1] if statuses else {}
        out["losses"] = {
            "lost_samples": last.get("lost_samples"),
            "queue_dropped": {k: (v or {}).get("dropped", 0) for k, v in (last.get("queues") or {}).items()},
            "mcap": last.get("mcap"), "zenoh": last.get("zenoh"), "rerun_server": last.get("rerun_server"),
        }
        return out


# ----------------------------------------------------------------------------- the report


def _f(v: Any, fmt: str = ".1f", none: str = "-") -> str:
    return none if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def _lat(d: dict[str, Any]) -> str:
    if not d.get("n"):
        return "-"
    return f"{d['median']:.0f}/{d['p99']:.0f} (n={d['n']})"


def report(runs: list[dict[str, Any]]) -> Iterator[str]:
    for r in runs:
        procs = r["processes"]
        yield ""
        yield (f"== {r['rate_hz']:g} Hz at x{r['speedup']:g}: window {r['window_s']:.1f} s "
               f"({r['window_tests']:.2f} tests), outputs {','.join(r['outputs']) or 'none'}, "
               f"baseline {r['baseline']}")
        yield (f"  {'process':<34} {'CPU %':>7} {'ctx/s':>8} {'vol/s':>8} {'invol/s':>8} "
               f"{'RSS MiB start->end':>19} {'MiB/min':>8}")
        for role, u in procs.items():
            rss = u["rss"]
            yield (f"  {role:<34} {u['cpu_pct']:7.2f} {u['ctx_per_s']:8.1f} {u['voluntary_per_s']:8.1f} "
                   f"{u['nonvoluntary_per_s']:8.1f} {_f(rss.get('start_mib')):>8} -> {_f(rss.get('end_mib')):<8} "
                   f"{_f(rss.get('slope_mib_per_min'), '+.2f'):>8}")
        ra = r["ratios"]
        if "cpu_pct_with_worker" in procs.get("daemon", {}):
            yield (f"  daemon with its analysis worker: CPU {procs['daemon']['cpu_pct_with_worker']:.2f} %, "
                   f"{_f(ra.get('cpu_with_worker'), '.1f')}x the baseline reader")
        yield (f"  daemon/baseline reader: CPU {_f(ra.get('cpu'), '.1f')}x, "
               f"context switches {_f(ra.get('ctx'), '.1f')}x, RSS {_f(ra.get('rss'), '.1f')}x;  "
               f"device/baseline device CPU {_f(ra.get('device_control'), '.2f')}"
               " (the control: ~1 when the window was fair)")
        d = procs.get("daemon")
        if d is not None:
            yield f"  daemon threads ({d['threads_end']} at the end; {d['threads_exited']} exited in the window):"
            yield f"    {'thread (comm)':<18} {'n':>3} {'CPU %':>7} {'ctx/s':>8}"
            for th in d["threads"]:
                if th["cpu_pct"] < 0.05 and th["ctx_per_s"] < 1:
                    continue
                yield f"    {th['name']:<18} {th['threads']:>3} {th['cpu_pct']:7.2f} {th['ctx_per_s']:8.1f}"
        lat = r["latency"]
        if lat:
            for kind in ("circle", "test"):
                x = lat.get(kind) or {}
                yield (f"  {kind} latency ms median/p99: subscriber {_lat(x.get('subscriber_ms', {}))}, "
                       f"published {_lat(x.get('published_ms', {}))}, delivery {_lat(x.get('delivery_ms', {}))}")
                if x.get("slowest"):
                    yield "    slowest (ms at s): " + ", ".join(
                        f"{v['ms']:.0f} at {v['at_s']:.0f}" for v in x["slowest"])
            if lat.get("rerun_restarts_at_s"):
                yield "  rerun server restarted at s: " + ", ".join(f"{v:.0f}" for v in lat["rerun_restarts_at_s"])
        q = r["queues"]
        if q:
            yield "  queues (depth median/p99/max, dropped): " + ", ".join(
                f"{n} {_f(v['depth'].get('median'), '.0f')}/{_f(v['depth'].get('p99'), '.0f')}/"
                f"{_f(v['depth'].get('max'), '.0f')} {v['dropped']}" for n, v in q.items())
        acc = r["accounting"]
        yield (f"  samples: device sent {acc.get('device_sent')}, daemon read {acc.get('daemon_samples', '-')}, "
               f"lost {acc.get('daemon_lost_samples', '-')}; baseline device sent {acc.get('baseline_device_sent')},"
               f" reader decoded {acc.get('baseline_reader_samples')}")
        if "soak" in r:
            s = r["soak"]
            yield f"  soak: warm-up {s['warmup_min']:g} min; after it:"
            for role, v in s.items():
                if isinstance(v, dict) and "growth_mib_per_wall_hour" in v:
                    yield (f"    {role}: RSS {_f(v['rss_at_warmup_mib'])} -> {_f(v['rss_end_mib'])} MiB, "
                           f"{_f(v['growth_mib_per_wall_hour'], '+.2f')} MiB per wall hour = "
                           f"{_f(v['growth_mib_per_operating_hour'], '+.3f')} MiB per hour of operation; "
                           "5-min medians " + " ".join(f"{x['median_mib']:.0f}" for x in v["five_minute_medians"]))
            yield f"    losses: {json.dumps(s['losses'], separators=(', ', ': '))}"
        for prob in r["problems"]:
            yield f"  PROBLEM: {prob}"
    yield ""
    yield ("Summary (daemon, with its analysis worker, against the bare serial reader, same window; latency at the "
           "subscriber, ms median/p99):")
    yield (f"  {'rate Hz':>8} {'x':>4} {'daemon CPU%':>11} {'goal':>5} {'base CPU%':>9} {'ratio':>6} "
           f"{'daemon ctx/s':>12} {'base ctx/s':>10} {'ratio':>6} {'RSS MiB/min':>11} {'circle':>16} {'test':>16}")
    for r in runs:
        d = r["processes"].get("daemon", {})
        b = r["processes"].get("baseline reader", {})
        goal = CPU_GOAL_PCT.get(r["rate_hz"]) if r["speedup"] == 1 else None  # the goals are at x1
        lat = r["latency"]
        cpu = d.get("cpu_pct_with_worker", d.get("cpu_pct"))
        ratio = r["ratios"].get("cpu_with_worker", r["ratios"].get("cpu"))
        yield (f"  {r['rate_hz']:>8g} {r['speedup']:>4g} {_f(cpu, '.2f'):>11} {_f(goal, '.0f'):>5} "
               f"{_f(b.get('cpu_pct'), '.2f'):>9} {_f(ratio, '.1f'):>6} "
               f"{_f(d.get('ctx_per_s'), '.0f'):>12} {_f(b.get('ctx_per_s'), '.0f'):>10} "
               f"{_f(r['ratios'].get('ctx'), '.1f'):>6} "
               f"{_f((d.get('rss') or {}).get('slope_mib_per_min'), '+.2f'):>11} "
               f"{_lat(lat.get('circle', {}).get('subscriber_ms', {})):>16} "
               f"{_lat(lat.get('test', {}).get('subscriber_ms', {})):>16}")


# ----------------------------------------------------------------------------- main


def _rates(text: str) -> list[float]:
    try:
        rates = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--rates: a comma-separated list of Hz, not {text!r}") from None
    if not rates or any(not 15.625 <= r <= 10_000 for r in rates):
        raise argparse.ArgumentTypeError("--rates: each within 15.625..10000 Hz")
    return rates


def _outputs(text: str) -> tuple[str, ...]:
    items = tuple(x.strip() for x in text.split(",") if x.strip())
    if items in (("none",), ()):
        return ()
    bad = [x for x in items if x not in OUTPUTS]
    if bad:
        raise argparse.ArgumentTypeError(f"--outputs: unknown {bad}; choose from {', '.join(OUTPUTS)} or none")
    return tuple(o for o in OUTPUTS if o in items)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m ballbar.tools.bench.bench_daemon",
        description="The daemon's CPU, context switches, memory and result latency per rate, against a bare "
                    "serial reader measured in the same window (see the module docstring).",
    )
    p.add_argument("--rates", type=_rates, help="Hz, comma-separated (default 15.625,1000,10000; soak: 1000)")
    p.add_argument("--speedup", type=float, help="device time per wall time (default 1; --quick 5; soak 20)")
    p.add_argument("--tests", type=int, default=1,
                   help="window: this many whole tests of the plan (default 1: 160 s at x1)")
    p.add_argument("--window-s", "--duration-s", dest="window_s", type=float,
                   help="window in wall seconds (overrides --tests)")
    p.add_argument("--warmup-s", type=float, help="from the device's start to the window's (default 10; --quick 5)")
    p.add_argument("--outputs", type=_outputs, default=OUTPUTS,
                   help="the daemon's outputs: any of mcap,zenoh,rerun, or none (default: all)")
    p.add_argument("--baseline", choices=("raw", "source", "off"), default="raw",
                   help="the bare reader: raw (pyserial + the protocol's decoder, default), source (the daemon's "
                        "SerialSource with no outputs) or off")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="a daemon configuration override (repeatable), e.g. zenoh.history_size=100")
    p.add_argument("--no-thread-names", dest="thread_names", action="store_false",
                   help="run `ballbar run` bare (Python threads then all show as the process's name)")
    p.add_argument("--quick", action="store_true", help="x5, 5 s warm-up, a 20 s window, no wait for a test result")
    p.add_argument("--soak-min", type=float, help="soak: one rate for this many minutes (default x20)")
    p.add_argument("--soak-warmup-min", type=float, default=35.0,
                   help="soak: the memory trend is taken after this (default 35: the bus's circle and event "
                        "histories full at x20)")
    p.add_argument("--json", help="write every figure (and the RSS series) to this file")
    p.add_argument("--workdir", help="state directories and logs here (default: a temporary directory, removed)")
    p.add_argument("--keep", action="store_true", help="keep the temporary directory")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def plans(args: argparse.Namespace, period_s: float) -> list[Plan]:
    soak = args.soak_min is not None
    speedup = args.speedup or (20.0 if soak else 5.0 if args.quick else 1.0)
    rates = args.rates or ([1000.0] if soak else list(DEFAULT_RATES))
    if soak:
        rates = rates[:1]
        warmup = args.soak_warmup_min * 60.0
        window = args.soak_min * 60.0 - warmup
        if window < 60.0:
            raise ValueError("--soak-min must exceed --soak-warmup-min by at least a minute")
        expect, grace = 0, 0.0
    else:
        warmup = args.warmup_s if args.warmup_s is not None else (5.0 if args.quick else 10.0)
        if args.window_s is not None:
            window, expect = args.window_s, 0
        elif args.quick:
            window, expect = 20.0, 0
        else:
            window, expect = args.tests * period_s / speedup, args.tests
        # The last test of the window is analysed after it: wait for its result, unmeasured.
        grace = 30.0 + 0.25 * period_s / speedup if expect else 0.0
    return [Plan(rate=r, speedup=speedup, outputs=args.outputs, baseline=args.baseline, warmup_s=warmup,
                 window_s=window, expect_tests=expect, test_period_s=period_s, grace_s=grace,
                 sets=tuple(args.sets), thread_names=args.thread_names, soak=soak,
                 progress_s=60.0 if soak else 0.0) for r in rates]


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "_daemon":
        return daemon_main(argv[1:])
    if argv and argv[0] == "_subscriber" and len(argv) == 3:
        return subscriber_main(argv[1], argv[2])
    if argv and argv[0] == "_reader" and len(argv) == 3:
        return reader_main(argv[1], argv[2])
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, stream=sys.stderr,
                        format="%(asctime)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    if (args.speedup is not None and not args.speedup > 0) or args.tests < 1:
        print("bench_daemon: --speedup must be > 0 and --tests >= 1", file=sys.stderr)
        return 2
    from ballbar.daemon.config import ConfigError, load

    try:
        period = schedule_period_s(load(None, list(args.sets), env={}))
        todo = plans(args, period)
    except (ConfigError, ValueError) as err:
        print(f"bench_daemon: {err}", file=sys.stderr)
        return 2
    temp = args.workdir is None
    root = Path(args.workdir or tempfile.mkdtemp(prefix="ballbar-bench-"))
    runs: list[dict[str, Any]] = []
    failed = False
    stop_requested = threading.Event()

    def on_term(signum: int, frame: FrameType | None) -> None:
        stop_requested.set()
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    try:
        for plan in todo:
            log.info("%g Hz at x%g: warm-up %.0f s, window %.0f s, outputs %s, baseline %s", plan.rate, plan.speedup,
                     plan.warmup_s, plan.window_s, ",".join(plan.outputs) or "none", plan.baseline)
            try:
                runs.append(Measurement(plan, root / f"rate-{plan.rate:g}").run())
            except (RuntimeError, OSError, TimeoutError, EOFError, ValueError) as err:
                log.error("%g Hz: %s", plan.rate, err)
                runs.append({"rate_hz": plan.rate, "error": str(err)})
                failed = True
    except KeyboardInterrupt:
        log.error("interrupted")
        failed = True
    finally:
        if temp and not args.keep and not failed:
            shutil.rmtree(root, ignore_errors=True)
        elif temp or args.keep:
            log.info("logs and state kept in %s", root)
    good = [r for r in runs if "error" not in r]
    for line in report(good):
        print(line)
    for r in runs:
        if "error" in r:
            print(f"{r['rate_hz']:g} Hz: FAILED: {r['error']}")
    if args.json:
        doc = {"settings": {k: v for k, v in vars(args).items() if k != "json"}, "test_period_device_s": period,
               "clk_tck": CLK_TCK, "cpus": os.cpu_count(), "loadavg_end": os.getloadavg(), "runs": runs}
        Path(args.json).write_text(json.dumps(doc, indent=1, default=str) + "\n")
    problems = any(r.get("problems") for r in good)
    return 1 if failed or problems or not good else 0


if __name__ == "__main__":
    sys.exit(main())
