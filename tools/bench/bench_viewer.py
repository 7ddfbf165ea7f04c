"""Viewer benchmark: the Rerun streamer's memory and CPU over hours of device time.

    python -m ballbar.tools.bench.bench_viewer                  # 1 kHz and 10 kHz; this viewer against main's
    python -m ballbar.tools.bench.bench_viewer --quick          # a few minutes, smaller figures
    python -m ballbar.tools.bench.bench_viewer --baseline none  # this viewer only

A :class:`~ballbar.daemon.rerun.RerunViewer` in ``serve`` mode (its own
``rerun --serve-grpc`` child, as in the daemon) is fed as the daemon feeds it,
through the daemon's :class:`~ballbar.daemon.listeners.ListenerQueue` (500
items, drop oldest; it merges batches for a listener that asks for it):
:class:`~ballbar.daemon.samples.SampleBatch` objects of 20 ms of wall time and
the analysis' messages, wrapped as the service wraps them.  The stream is one test of the physical simulator
(:mod:`ballbar.tools.simulator`, the default plan: 154.5 s a test) analysed by
:class:`~ballbar.analysis.engine.TestAnalyzer`, replayed back to back on a
continuous clock (times, sample numbers and test numbers shifted), so an hour
of device time costs the simulation and the analysis of one test.

Each measurement runs in a fresh process (``--child``), paced: device time runs
``speedup`` times faster than the wall clock, and the samples' host times are
compressed the same way (as ``ballbar run --simulate --speedup N`` stamps
them).  Reported, for each viewer and rate:

- ``rss``: this process's resident memory (the viewer, the Rerun SDK and the
  harness), sampled each second; ``slope``: the least-squares slope over the
  second half of the run (after the buffers filled), in MiB per hour of device
  time and per minute of wall time; the server child's resident memory too
  (bounded by ``server_memory_limit`` and restarted above its cap);
- ``cpu``: this process's CPU time (all threads: the viewer's calls and the
  SDK's encoder and gRPC threads) per second of device time, in percent of
  one core; ``calls``: the part spent inside the listener calls; the
  harness's own share is measured with a listener that does nothing
  (``null``) in the same run.  The CPU runs go at ``--cpu-speedup`` (default
  1: real time, the daemon's conditions); the memory runs at ``--speedup``.
- ``late``: with ``--late-viewer``, what a viewer that connects at the end
  receives: a headless ``rerun`` saves it, and :func:`summarize_rrd` reads
  it back (tests whose polar plots are whole, the length series' span and
  rate, trend points).

The baseline (``--baseline REV``, default ``455c11f``: before issue 11) is
``daemon/viewer.py`` of that git revision, loaded in place of this one.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import importlib.util
import json
import os
import resource
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any, cast

import numpy as np

from ballbar.analysis.engine import TestAnalyzer
from ballbar.analysis.plan import MachineConfig, TestPlan
from ballbar.daemon import procfs
from ballbar.daemon.listeners import Listener, ListenerQueue, Message, to_json
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.tools.simulator import MachineModel, iter_tests

MACHINE = MachineModel(backlash_x_um=4.0, kv_y_per_s=33.0, squareness_urad=15.0, centre_x_um=8.0, noise_um=0.1)
BATCH_WALL_S = 0.02  # a source's batch: 20 ms of wall time
# absolute times in results and events, shifted with each replay (the rest of ``timing`` are durations)
_TIMING_TIMES = ("feed_in_s", "feed_out_s", "data_start_s", "data_end_s")

Replayed = dict[str, Any]  # one of the analysis' messages, as JSON: replayed with its times moved on


# --------------------------------------------------------------------------- the stream


@dataclass
class Stream:
    """One simulated test and the analysis' messages, ready to be replayed back to back."""

    rate_hz: float
    t: np.ndarray  # device time of each sample (s)
    L: np.ndarray  # bar length (mm)
    messages: list[tuple[int, Replayed]]  # (samples fed before it, message)
    plan: TestPlan

    @property
    def period_s(self) -> float:
        """Device time of one replay: the next test starts on the next sample instant."""
        return self.t.size / self.rate_hz

    def save(self, path: Path) -> None:
        np.savez(path.with_suffix(".npz"), t=self.t, L=self.L)
        meta = {"rate_hz": self.rate_hz, "plan": self.plan.to_dict(),
                "messages": [[i, json.loads(to_json(m))] for i, m in self.messages]}
        path.with_suffix(".json").write_text(json.dumps(meta))

    @classmethod
    def load(cls, path: Path) -> Stream:
        arr = np.load(path.with_suffix(".npz"))
        meta = json.loads(path.with_suffix(".json").read_text())
        return cls(float(meta["rate_hz"]), arr["t"], arr["L"], [(int(i), m) for i, m in meta["messages"]],
                   TestPlan.from_dict(meta["plan"]))


def make_stream(rate_hz: float, seed: int = 1, machine: MachineModel = MACHINE) -> Stream:
    """One test of the simulator at ``rate_hz`` and what the analysis says about it, fed in 20 ms chunks."""
    plan = TestPlan(sample_hz=rate_hz)
    res = next(iter_tests(plan, machine, rate_hz, seed=seed, repeat=1))
    an = TestAnalyzer(plan, MachineConfig())
    chunk = max(1, round(rate_hz * 0.02))
    messages: list[tuple[int, Replayed]] = []
    for i in range(0, res.t_s.size, chunk):
        for msg in an.feed(res.t_s[i : i + chunk], res.length_mm[i : i + chunk]):
            messages.append((min(i + chunk, res.t_s.size), dict(msg)))
    kinds = [m["kind"] for _i, m in messages]
    if kinds.count("test") != 1:
        raise RuntimeError(f"the simulated test was not analysed whole: {kinds}")
    return Stream(rate_hz, res.t_s, res.length_mm, messages, plan)


def cached_stream(rate_hz: float, cache: Path | None) -> Stream:
    if cache is None:
        return make_stream(rate_hz)
    path = cache / f"stream-{rate_hz:g}"
    if path.with_suffix(".json").exists():
        return Stream.load(path)
    cache.mkdir(parents=True, exist_ok=True)
    s = make_stream(rate_hz)
    s.save(path)
    return s


def shifted(msg: Replayed, k: int, period_s: float, tests: int = 1) -> Replayed:
    """Message ``msg`` of replay ``k`` of a stream of ``tests`` tests: its test number and absolute times moved on."""
    out = copy.deepcopy(msg)
    dt = k * period_s
    for key in ("t_s", "last_sample_t"):
        if isinstance(out.get(key), int | float):
            out[key] += dt
    if isinstance(out.get("test_index"), int):
        out["test_index"] += k * tests
    tm = out.get("timing")
    if isinstance(tm, dict):
        for key in _TIMING_TIMES:
            if isinstance(tm.get(key), int | float):
                tm[key] += dt
        for arc in (tm.get("data_arcs") or {}).values():
            for key in ("start_s", "end_s"):
                if isinstance(arc.get(key), int | float):
                    arc[key] += dt
    return out


def replay(
    put_batch: Callable[[SampleBatch], Any],
    put_message: Callable[[Message], Any],
    stream: Stream,
    device_s: float,
    speedup: float,
    on_second: Callable[[float], None] | None = None,
) -> float:
    """Feed ``device_s`` seconds of ``stream``, repeated, at ``speedup``; the seconds the feed fell behind.

    ``put_batch``/``put_message``: a :class:`ListenerQueue`'s (as the daemon's
    source does) or a listener's own ``on_batch``/``on_message``.  Batches
    hold 20 ms of wall time; host times are ``monotonic at the start + device
    time / speedup``, as a source at that speedup stamps them.
    ``on_second(device time)``: called about once a wall second.
    """
    n, per = stream.t.size, max(1, round(stream.rate_hz * BATCH_WALL_S * speedup))
    total = int(device_s * stream.rate_hz)
    mono0 = time.monotonic()
    next_tick = mono0 + 1.0
    behind = 0.0
    msg_at = stream.messages
    first = True
    pos = 0  # sample number
    mi = 0  # next message of this replay
    while pos < total:
        k, i = divmod(pos, n)
        j = min(n, i + per, i + (total - pos))
        t_dev = stream.t[i:j] + k * stream.period_s
        t_host = mono0 + t_dev / speedup
        due = float(t_host[-1])
        now = time.monotonic()
        if due > now:
            time.sleep(due - now)
        else:
            behind = max(behind, now - due)
        events = [SourceEvent(EventKind.OPENED, mono0, "sim:", detail="bench")] if first else []
        first = False
        batch = SampleBatch.from_columns(t_host, t_dev, stream.L[i:j], np.arange(pos, pos + j - i),
                                         np.zeros(j - i, np.uint8), events, "sim:")
        put_batch(batch)
        if i == 0:
            mi = 0
        while mi < len(msg_at) and msg_at[mi][0] <= j:
            msg = shifted(msg_at[mi][1], k, stream.period_s)
            mi += 1
            now = time.monotonic()
            msg.update(machine_id="bench", test_id=f"bench-{msg.get('test_index')}", t_host=now,
                       last_sample_t=float(t_dev[-1]), last_sample_t_host=due,
                       latency_ms=1000.0 * (now - due), time_axis="device")
            put_message(cast(Message, msg))  # the analysis' output wrapped as the service wraps it
        pos += j - i
        if on_second is not None and time.monotonic() >= next_tick:
            next_tick += 1.0
            on_second(pos / stream.rate_hz)
    if on_second is not None:
        on_second(pos / stream.rate_hz)
    return behind


class Timed(Listener):
    """Forwards to ``inner`` (its batch period and idle time too), adding up the thread CPU time of its calls."""

    def __init__(self, inner: Listener) -> None:
        self.inner = inner
        self.name = inner.name
        self.batch_period_s = getattr(inner, "batch_period_s", 0.0)
        self.idle_s = getattr(inner, "idle_s", 1.0)
        self.cpu_s = 0.0

    def on_batch(self, batch: SampleBatch) -> None:
        t0 = time.thread_time()
        try:
            self.inner.on_batch(batch)
        finally:
            self.cpu_s += time.thread_time() - t0

    def on_message(self, msg: Message) -> None:
        t0 = time.thread_time()
        try:
            self.inner.on_message(msg)
        finally:
            self.cpu_s += time.thread_time() - t0

    def on_idle(self) -> None:
        t0 = time.thread_time()
        try:
            self.inner.on_idle()
        finally:
            self.cpu_s += time.thread_time() - t0

    def stop(self) -> None:
        self.inner.stop()


# --------------------------------------------------------------------------- one measurement


class NullListener(Listener):
    """Does nothing: the harness's own cost."""

    name = "null"

    def stop(self) -> None:
        pass


def load_viewer_module(path: Path | None) -> ModuleType:
    """``ballbar.daemon.rerun``, or the viewer module in file ``path`` (a baseline) under another name."""
    if path is None:
        import ballbar.daemon.rerun as mod

        return mod
    name = "ballbar.daemon._bench_baseline_viewer"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def _rss_mib(pid: int) -> float | None:
    try:
        return procfs.rss_bytes(pid) / 2**20
    except (OSError, KeyError, ValueError):
        return None


def _cpu_s(pid: int) -> float | None:
    try:
        return procfs.cpu_seconds(pid)
    except (OSError, ValueError, IndexError):
        return None


def _self_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return ru.ru_utime + ru.ru_stime


def slope_per(xs: Sequence[float], ys: Sequence[float]) -> float | None:
    """Least-squares slope of ``ys`` against ``xs``; None with fewer than 3 points."""
    if len(xs) < 3:
        return None
    x, y = np.asarray(xs, float), np.asarray(ys, float)
    x = x - x.mean()
    den = float((x * x).sum())
    return float((x * (y - y.mean())).sum() / den) if den > 0 else None


def measure(
    viewer: str,
    rate_hz: float,
    device_s: float,
    speedup: float,
    port: int,
    memory_limit: str,
    cache: Path | None,
    late_viewer: bool = False,
    tmp: Path | None = None,
    idle: bool = False,
) -> dict[str, Any]:
    """One run in this process: ``viewer`` is ``new``, ``null`` or a path to a baseline viewer.py.

    ``idle``: the machine stands still (the bar at its nominal length, no test, no message).
    """
    stream = cached_stream(rate_hz, cache)
    if idle:
        stream = Stream(stream.rate_hz, stream.t, np.full(stream.t.size, stream.plan.radius_mm), [], stream.plan)
    listener: Listener
    rerun_viewer: Any = None  # the viewer's module is loaded by path: its listener's own methods are untyped here
    server_pid: Callable[[], int | None] = lambda: None  # noqa: E731
    if viewer == "null":
        listener = NullListener()
    else:
        mod = load_viewer_module(None if viewer == "new" else Path(viewer))
        opts = mod.ViewerOptions(mode="serve", bind="127.0.0.1", port=port, server_memory_limit=memory_limit)
        v = mod.RerunViewer(opts, plan=stream.plan)
        deadline = time.monotonic() + 30.0
        while not v.connected:
            if time.monotonic() > deadline:
                raise RuntimeError(f"the viewer's server did not come up: {v.stats()}")
            v.on_idle()
            time.sleep(0.05)
        listener = rerun_viewer = v

        def server_pid() -> int | None:
            srv = getattr(v, "_server", None)
            proc = getattr(srv, "proc", None)
            return proc.pid if proc is not None else None

    rows: list[dict[str, float | None]] = []
    wall0, cpu0 = time.monotonic(), _self_cpu_s()
    spid0 = server_pid()
    scpu0 = _cpu_s(spid0) if spid0 else None

    def sample(device: float) -> None:
        spid = server_pid()
        rows.append({
            "wall_s": time.monotonic() - wall0,
            "device_s": device,
            "rss_mib": _rss_mib(os.getpid()),
            "cpu_s": _self_cpu_s() - cpu0,
            "server_rss_mib": _rss_mib(spid) if spid else None,
        })

    timed = Timed(listener)
    queue = ListenerQueue(timed, capacity=500, policy="drop_oldest")  # the daemon's queue for the viewer
    sample(0.0)
    behind = replay(queue.put_batch, queue.put_message, stream, device_s, speedup, sample)
    queue.wait_idle(30.0)
    wall = time.monotonic() - wall0
    cpu = _self_cpu_s() - cpu0
    spid = server_pid()
    scpu = (_cpu_s(spid) or 0.0) - (scpu0 or 0.0) if spid and spid == spid0 else None
    out: dict[str, Any] = {
        "viewer": viewer, "rate_hz": rate_hz, "device_s": device_s, "speedup": speedup, "wall_s": wall,
        "behind_s": behind, "cpu_pct_of_device_s": 100.0 * cpu / device_s,
        "calls_cpu_pct_of_device_s": 100.0 * timed.cpu_s / device_s,
        "queue": queue.stats.to_dict(),
        "server_cpu_pct_of_device_s": 100.0 * scpu / device_s if scpu is not None else None,
        "rows": rows,
    }
    half = [r for r in rows if r["device_s"] is not None and r["device_s"] >= device_s / 2]
    xs = [float(r["device_s"] or 0.0) / 3600.0 for r in half if r["rss_mib"] is not None]
    ys = [float(r["rss_mib"] or 0.0) for r in half if r["rss_mib"] is not None]
    out["rss_slope_mib_per_device_h"] = slope_per(xs, ys)
    ws = [float(r["wall_s"] or 0.0) / 60.0 for r in half if r["rss_mib"] is not None]
    out["rss_slope_mib_per_wall_min"] = slope_per(ws, ys)
    out["rss_first_mib"] = rows[0]["rss_mib"]
    out["rss_last_mib"] = rows[-1]["rss_mib"]
    out["server_rss_last_mib"] = rows[-1]["server_rss_mib"]
    out["server_rss_max_mib"] = max((r["server_rss_mib"] or 0.0) for r in rows)
    srv = [(float(r["device_s"] or 0.0) / 3600.0, float(r["server_rss_mib"])) for r in half
           if r["server_rss_mib"] is not None]
    out["server_rss_slope_mib_per_device_h"] = slope_per([x for x, _y in srv], [y for _x, y in srv])
    if viewer != "null":
        out["stats"] = {k: v for k, v in rerun_viewer.stats().items() if k != "server"}
        out["server"] = rerun_viewer.stats().get("server")
        if late_viewer:
            deadline = time.monotonic() + 15.0  # the queue calls on_idle: a history being sent in slices finishes
            while rerun_viewer.stats().get("history_pending") and time.monotonic() < deadline:
                time.sleep(0.1)
            out["late"] = late_view(rerun_viewer.address, tmp or Path(tempfile.mkdtemp()), port + 1)
    t0 = time.monotonic()
    queue.close()  # and the listener's stop()
    out["stop_s"] = time.monotonic() - t0
    return out


# --------------------------------------------------------------------------- what a late viewer gets


def _rerun_exe() -> str:
    spec = importlib.util.find_spec("rerun_cli")
    if spec is None or spec.origin is None:
        raise RuntimeError("the rerun CLI (rerun-sdk's rerun_cli) is not installed")
    return str(Path(spec.origin).parent / "rerun")


def _listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


def late_view(address: str, tmp: Path, port: int, settle_s: float = 2.0, timeout_s: float = 120.0) -> dict[str, Any]:
    """Connect a headless ``rerun`` to ``address`` as a late viewer, save what it receives, summarize it."""
    rrd = tmp / f"late-{port}.rrd"
    args = [_rerun_exe(), "--serve-grpc", "--bind", "127.0.0.1", "--port", str(port), "--connect", address,
            "--save", str(rrd)]
    with open(tmp / f"late-{port}.log", "wb") as log:
        proc = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        last, since = -1, time.monotonic()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            size = rrd.stat().st_size if rrd.exists() else 0
            if size != last:
                last, since = size, time.monotonic()
            elif size > 0 and time.monotonic() - since > settle_s:
                break
            time.sleep(0.1)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5.0)
    return {"bytes": rrd.stat().st_size if rrd.exists() else 0, **summarize_rrd(rrd)}


def read_entities(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every row of an ``.rrd`` by entity: its timelines' values and its non-indicator components."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    out: dict[str, list[dict[str, Any]]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file saved by --save has no footer
        for ch in RrdReader(path).stream():
            rb = ch.to_record_batch()
            cols = [n for n in rb.schema.names if n in ("time", "test") or (":" in n and not n.startswith("rerun."))]
            data = {n: (rb.column(n).cast(pa.int64()) if n == "time" else rb.column(n)).to_pylist() for n in cols}
            rows = out.setdefault(str(ch.entity_path), [])
            for r in range(rb.num_rows):
                rows.append({n: data[n][r] for n in cols})
    return out


def summarize_rrd(path: Path) -> dict[str, Any]:
    """What a recording of the stream holds: tests with whole polar plots, the length series, trends."""
    ents = read_entities(path)

    def tests_with(entity: str) -> set[int]:
        return {int(r["test"]) for r in ents.get(entity, []) if r.get("test") is not None
                and any(v is not None for k, v in r.items() if k not in ("time", "test"))}

    whole = tests_with("/polar/ccw/model") & tests_with("/polar/cw/model") & tests_with(
        "/polar/ccw/measured") & tests_with("/polar/cw/measured")
    times, n_len = [], 0
    for r in ents.get("/length", []):
        v = r.get("Scalars:scalars")
        if v is None or r.get("time") is None:
            continue
        n_len += len(v) if isinstance(v, list) else 1
        times.append(r["time"])
    span = None
    if times:
        ts = sorted(float(t) / 1e9 for t in times)
        span = ts[-1] - ts[0]
    trend = sum(len(r["Scalars:scalars"]) if isinstance(r.get("Scalars:scalars"), list) else 1
                for r in ents.get("/trends/backlash_um/x", []) if r.get("Scalars:scalars") is not None)
    return {
        "tests_whole": sorted(whole),
        "length_points": n_len,
        "length_rows": len(ents.get("/length", [])),
        "length_span_s": span,
        "length_hz": n_len / span if span else None,
        "trend_points": trend,
        "entities": len(ents),
    }


# --------------------------------------------------------------------------- the report


def _child(args: argparse.Namespace) -> int:
    tmp = Path(tempfile.mkdtemp(prefix="bench-viewer-"))
    out = measure(args.viewer, args.rate, args.device_s, args.speedup, args.port, args.memory_limit,
                  Path(args.cache) if args.cache else None, args.late_viewer, tmp, args.idle)
    print(json.dumps(out))
    return 0


def run_child(viewer: str, rate: float, device_s: float, speedup: float, port: int, memory_limit: str,
              cache: Path, late_viewer: bool = False, idle: bool = False) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "ballbar.tools.bench.bench_viewer", "--child", "--viewer", viewer, "--rate", str(rate),
           "--device-s", str(device_s), "--speedup", str(speedup), "--port", str(port),
           "--memory-limit", memory_limit, "--cache", str(cache)] + (["--late-viewer"] if late_viewer else []) + (
           ["--idle"] if idle else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"bench child failed ({' '.join(cmd)}):\n{proc.stderr[-3000:]}")
    return dict(json.loads(proc.stdout.strip().splitlines()[-1]))


def baseline_file(rev: str, tmp: Path) -> Path:
    """``daemon/viewer.py`` of git revision ``rev`` of the checkout this module lives in."""
    root = Path(__file__).resolve().parent.parent
    text = subprocess.run(["git", "-C", str(root), "show", f"{rev}:daemon/viewer.py"], check=True,
                          capture_output=True, text=True).stdout
    path = tmp / f"viewer_{rev.replace('/', '_')}.py"
    path.write_text(text)
    return path


def _fmt(x: Any, nd: int = 2) -> str:
    return "–" if x is None else f"{x:.{nd}f}"


def report(results: Mapping[str, Any]) -> Iterator[str]:
    a = results["args"]
    yield (f"CPU, percent of one core per second of device time (x{a['cpu_speedup']:g}, medians of "
           f"{a['repeats']}); stream: what the server holds per hour of operation (a late viewer's bytes):")
    yield (f"  {'rate':>7}  {'viewer':<10} {'process':>8}  {'in calls':>8}  {'server':>7}  {'behind s':>8}  "
           f"{'stream MiB/h':>12}  {'window at ' + a['memory_limit']:>16}")
    for row in results["cpu"]:
        rate_h = row["late_bytes"] / 2**20 / (row["device_s"] / 3600.0) if row.get("late_bytes") else None
        limit = _limit_mib(a["memory_limit"])
        window = f"{limit / rate_h:.1f} h" if rate_h and limit else "–"
        yield (f"  {row['rate_hz']:>7g}  {row['viewer']:<10} {_fmt(row['cpu_pct']):>8}  "
               f"{_fmt(row['calls_pct']):>8}  {_fmt(row['server_pct']):>7}  {_fmt(row['behind_s']):>8}  "
               f"{_fmt(rate_h, 1):>12}  {window:>16}")
    for row in results.get("idle", []):
        rate_h = row["late_bytes"] / 2**20 / (row["device_s"] / 3600.0)
        limit = _limit_mib(a["memory_limit"])
        yield (f"  idle {row['rate_hz']:g} Hz, {row['viewer']}: CPU {_fmt(row['cpu_pct'])} %, stream "
               f"{rate_h:.1f} MiB/h, window at {a['memory_limit']}: "
               + (f"{limit / rate_h:.1f} h" if limit else "–"))
    yield (f"Memory, x{a['speedup']:g}, server_memory_limit {a['rss_memory_limit']}: resident MiB, slopes over the "
           "second half (MiB per device hour):")
    yield (f"  {'rate':>7}  {'viewer':<10} {'device h':>8}  {'daemon RSS':>15}  {'slope':>6}  {'CPU %':>6}  "
           f"{'server RSS max':>14}  {'slope':>6}")
    for row in results["rss"]:
        yield (f"  {row['rate_hz']:>7g}  {row['viewer']:<10} {row['device_s'] / 3600:>8.2f}  "
               f"{_fmt(row['rss_first_mib'], 0):>6} -> {_fmt(row['rss_last_mib'], 0):>5}  "
               f"{_fmt(row['rss_slope_mib_per_device_h']):>6}  {_fmt(row['cpu_pct_of_device_s']):>6}  "
               f"{_fmt(row['server_rss_max_mib'], 0):>14}  {_fmt(row['server_rss_slope_mib_per_device_h']):>6}")
        if row.get("late"):
            late = row["late"]
            tw = late["tests_whole"]
            yield (f"           late viewer: {len(tw)} tests whole ({tw[0] if tw else '–'}..{tw[-1] if tw else '–'}), "
                   f"length {late['length_points']} points over {_fmt(late['length_span_s'], 0)} s, "
                   f"{late['trend_points']} trend points, {late['bytes'] / 2**20:.1f} MiB")


def _limit_mib(text: str) -> float | None:
    import re

    m = re.fullmatch(r"([0-9.]+)\s*MiB", text.strip())
    return float(m[1]) if m else None


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_viewer", description=__doc__.split("\n")[0])
    p.add_argument("--rates", default="1000,10000", help="sample rates, Hz (default 1000,10000)")
    p.add_argument("--hours", type=float, default=1.0, help="device hours per memory run (default 1)")
    p.add_argument("--speedup", type=float, default=20.0, help="memory runs: device time / wall time (default 20)")
    p.add_argument("--cpu-seconds", type=float, default=0.0,
                   help="device seconds per CPU run (default 0: one whole test, 154.5 s)")
    p.add_argument("--cpu-speedup", type=float, default=1.0, help="CPU runs: speedup (default 1, real time)")
    p.add_argument("--repeats", type=int, default=1, help="CPU runs per viewer and rate (default 1)")
    p.add_argument("--baseline", default="455c11f",
                   help="git revision whose viewer is compared (default 455c11f, before issue 11), or 'none'")
    p.add_argument("--memory-limit", default="128MiB", help="server_memory_limit of the CPU runs (default 128MiB)")
    p.add_argument("--rss-memory-limit", default="16MiB",
                   help="server_memory_limit of the memory runs, small enough to fill (default 16MiB)")
    p.add_argument("--port", type=int, default=7880, help="first port to use (each run takes two)")
    p.add_argument("--late-viewer", action="store_true",
                   help="connect a viewer at the end of each run and summarize what it gets")
    p.add_argument("--quick", action="store_true", help="0.25 device hours, 30 s CPU runs")
    p.add_argument("--cache", help="directory for the simulated streams (default: a temporary one)")
    p.add_argument("--json", help="also write the results to this file")
    # one measurement (internal)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--viewer", default="new", help=argparse.SUPPRESS)
    p.add_argument("--rate", type=float, default=1000.0, help=argparse.SUPPRESS)
    p.add_argument("--device-s", type=float, default=60.0, help=argparse.SUPPRESS)
    p.add_argument("--idle", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--idle-seconds", type=float, default=300.0,
                   help="with --late-viewer: device seconds of a run with no test, at --cpu-speedup (the stream's "
                        "rate when idle; 0: none)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.child:
        return _child(args)
    if args.quick:
        args.hours, args.cpu_seconds = 0.25, 30.0
    tmp = Path(tempfile.mkdtemp(prefix="bench-viewer-"))
    cache = Path(args.cache) if args.cache else tmp
    viewers = ["new"] if args.baseline == "none" else [str(baseline_file(args.baseline, tmp)), "new"]
    names = {v: ("new" if v == "new" else args.baseline) for v in viewers}
    names["null"] = "null"
    rates = [float(r) for r in args.rates.split(",")]
    results: dict[str, Any] = {"cpu": [], "rss": [], "args": vars(args)}
    port = args.port
    for rate in rates:
        print(f"simulating and analysing one test at {rate:g} Hz ...", file=sys.stderr, flush=True)
        cpu_s = args.cpu_seconds or cached_stream(rate, cache).period_s
        runs: dict[str, list[dict[str, Any]]] = {}
        for _rep in range(args.repeats):
            for v in ["null", *viewers]:  # interleaved: the machine's load hits every viewer alike
                print(f"  CPU run: {names[v]} at {rate:g} Hz, {cpu_s:g} device s", file=sys.stderr, flush=True)
                runs.setdefault(v, []).append(run_child(v, rate, cpu_s, args.cpu_speedup, port, args.memory_limit,
                                                        cache, args.late_viewer and v != "null"))
                port += 2
        for v, rs in runs.items():
            results["cpu"].append({
                "rate_hz": rate, "viewer": names[v], "speedup": args.cpu_speedup,
                "cpu_pct": statistics.median(r["cpu_pct_of_device_s"] for r in rs),
                "calls_pct": statistics.median(r["calls_cpu_pct_of_device_s"] for r in rs),
                "server_pct": statistics.median(r["server_cpu_pct_of_device_s"] or 0.0 for r in rs),
                "behind_s": max(r["behind_s"] for r in rs),
                "device_s": cpu_s,
                "late_bytes": statistics.median(r["late"]["bytes"] for r in rs) if rs[0].get("late") else None,
            })
        for v in viewers:
            print(f"  memory run: {names[v]} at {rate:g} Hz, {args.hours:g} device h at x{args.speedup:g}",
                  file=sys.stderr, flush=True)
            r = run_child(v, rate, args.hours * 3600.0, args.speedup, port, args.rss_memory_limit, cache,
                          args.late_viewer)
            port += 2
            r["viewer"] = names[v]
            results["rss"].append(r)
    if args.late_viewer and args.idle_seconds > 0:
        rate = rates[0]
        for v in ["new"]:  # (the baseline streams the same with or without tests: 50 length messages a second)
            print(f"  idle run: {names[v]} at {rate:g} Hz, {args.idle_seconds:g} device s", file=sys.stderr, flush=True)
            r = run_child(v, rate, args.idle_seconds, args.cpu_speedup, port, args.memory_limit, cache, True, True)
            port += 2
            results.setdefault("idle", []).append({
                "rate_hz": rate, "viewer": names[v], "device_s": args.idle_seconds,
                "cpu_pct": r["cpu_pct_of_device_s"], "late_bytes": r["late"]["bytes"],
            })
    for line in report(results):
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
