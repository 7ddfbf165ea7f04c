"""The Rerun streamer against real headless ``rerun`` processes on loopback.

A receiver is the rerun CLI binary itself (``rerun --serve-grpc --bind
127.0.0.1 --port N --save out.rrd``), started in a session of its own so that
killing its process group really kills it (``bin/rerun`` is a Python wrapper
that forks the binary: killing the wrapper alone leaves the binary holding
the port).  What it saved is read back with :class:`rerun.chunk.RrdReader`.

The stream is one simulated run of two short tests (physical simulator,
100 Hz), analysed by :class:`~ballbar.analysis.engine.TestAnalyzer` once per
module and wrapped as the daemon's pipeline wraps its messages.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rerun  # noqa: F401 - its runtime's descriptors (opened at import, once) exist before any leak check

from ballbar.analysis.engine import TestAnalyzer
from ballbar.analysis.plan import MachineConfig, TestPlan
from ballbar.daemon.rerun import (
    R0,
    TREND_VIEWS,
    TRENDS,
    RerunViewer,
    ViewerConfigError,
    ViewerOptions,
    default_blueprint,
    findings_markdown,
    model_deviation_um,
    nice_scale_um,
    polar_points,
    result_timing,
    trend_ranges,
)
from ballbar.daemon.rerun import scene as scene_module
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.tools.simulator import MachineModel, iter_chunks

PLAN = TestPlan(radius_mm=50.0, feed_mm_min=3000.0, overshoot_deg=30.0, dwell_s=0.2, sample_hz=100.0)
MACHINE = MachineModel(backlash_x_um=4.0, kv_x_per_s=30.0, kv_y_per_s=33.0, squareness_urad=20.0, centre_x_um=3.0)
SERVO_MS = 1000.0 / 30.0 - 1000.0 / 33.0  # 1/KX - 1/KY


def _rerun_exe() -> str | None:
    with contextlib.suppress(ImportError):
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.exists():
            return str(exe)
    return shutil.which("rerun")


RERUN = _rerun_exe()
pytestmark = [
    pytest.mark.skipif(RERUN is None, reason="the rerun CLI binary is not installed"),
    pytest.mark.usefixtures("no_leaks"),
]


# --------------------------------------------------------------------------- the stream


@dataclass
class Script:
    """Batches and messages in the order the daemon hands them to a listener."""

    items: list[tuple[str, Any]]
    t: np.ndarray  # the analysis clock (device time) of every sample
    L: np.ndarray
    results: list[dict[str, Any]] = field(default_factory=list)

    def split(self, fraction: float) -> tuple[list[tuple[str, Any]], list[tuple[str, Any]]]:
        k = int(len(self.items) * fraction)
        return self.items[:k], self.items[k:]


@pytest.fixture(scope="module")
def script() -> Script:
    an = TestAnalyzer(PLAN, MachineConfig())
    host0 = time.monotonic() - 60.0  # host clock: monotonic-like and unrelated to the device clock
    items: list[tuple[str, Any]] = []
    ts, Ls, results = [], [], []
    seq = 0
    first = True
    for t, L in iter_chunks(PLAN, MACHINE, PLAN.sample_hz, seed=3, repeat=2, chunk=2):
        n = t.size
        events = [SourceEvent(EventKind.OPENED, host0, "sim:", detail="simulator")] if first else []
        first = False
        items.append(
            ("batch", SampleBatch.from_columns(host0 + t, t, L, np.arange(seq, seq + n), np.zeros(n), events, "sim:"))
        )
        seq += n
        ts.append(t)
        Ls.append(L)
        for msg in an.feed(t, L):
            msg.update(
                machine_id="m1",
                test_id=f"m1-{msg.get('test_index')}",
                t_host=time.monotonic(),
                last_sample_t=float(t[-1]),
                time_axis="device",
            )
            items.append(("message", msg))
            if msg["kind"] in ("circle", "test"):
                results.append(msg)
    assert [r["kind"] for r in results] == ["circle", "circle", "test"] * 2
    return Script(items, np.concatenate(ts), np.concatenate(Ls), results)


def feed(viewer: RerunViewer, items: Sequence[tuple[str, Any]]) -> list[float]:
    """Deliver ``items``; the seconds each ``on_batch`` took."""
    costs = []
    for kind, x in items:
        if kind == "batch":
            t0 = time.perf_counter()
            viewer.on_batch(x)
            costs.append(time.perf_counter() - t0)
        else:
            viewer.on_message(x)
    return costs


# --------------------------------------------------------------------------- receivers


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listening(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=0.2):
            return True
    except OSError:
        return False


class Receiver:
    """A headless rerun process that saves what it receives; its own process group."""

    def __init__(self, tmp: Path, name: str, port: int, connect: str | None = None) -> None:
        assert RERUN is not None
        self.port = port
        self.rrd = tmp / f"{name}.rrd"
        self.log = tmp / f"{name}.log"
        args = [RERUN, "--serve-grpc", "--bind", "127.0.0.1", "--port", str(port), "--save", str(self.rrd)]
        if connect:
            args += ["--connect", connect]
        with open(self.log, "wb") as out:
            self.proc = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + 15.0
        while not listening(port):
            assert self.proc.poll() is None, f"rerun exited: {self.log.read_text(errors='replace')[-2000:]}"
            assert time.monotonic() < deadline, "rerun did not listen within 15 s"
            time.sleep(0.05)

    def signal(self, sig: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, sig)

    def finish(self, timeout: float = 5.0) -> None:
        """Let it write what it got (its file stops growing), then end it."""
        last, since = -1, time.monotonic()
        deadline = time.monotonic() + timeout
        while self.proc.poll() is None and time.monotonic() < deadline:
            size = self.rrd.stat().st_size if self.rrd.exists() else 0
            if size != last:
                last, since = size, time.monotonic()
            elif time.monotonic() - since > 0.4:
                break
            time.sleep(0.05)
        self.close()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.signal(signal.SIGCONT)
            self.signal(signal.SIGTERM)
            try:
                self.proc.wait(5.0)
            except subprocess.TimeoutExpired:
                self.signal(signal.SIGKILL)
                self.proc.wait(5.0)


@pytest.fixture
def receivers(tmp_path: Path) -> Iterator[list[Receiver]]:
    made: list[Receiver] = []
    yield made
    for r in made:
        r.close()


def wait_connected(v: RerunViewer, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while not v.connected:
        assert time.monotonic() < deadline, f"the viewer did not connect within {timeout} s: {v.stats()}"
        v.on_idle()
        time.sleep(0.02)


def connected_viewer(url: str, **kw: Any) -> RerunViewer:
    opts = ViewerOptions(mode="connect", url=url, retry_s=0.1, **kw)
    v = RerunViewer(opts, plan=PLAN, recording_id="test-run")
    deadline = time.monotonic() + 10.0
    while not v.connected:
        assert time.monotonic() < deadline, "the viewer did not connect within 10 s"
        v.on_idle()
        time.sleep(0.02)
    return v


# --------------------------------------------------------------------------- reading back


@dataclass
class Saved:
    rows: dict[str, int]
    timelines: dict[str, set[str]]
    columns: dict[str, dict[str, list[Any]]]  # entity -> column -> values, in file order
    recordings: list[Any]


def read_rrd(path: Path) -> Saved:
    from rerun.chunk import RrdReader

    rows: dict[str, int] = {}
    timelines: dict[str, set[str]] = {}
    columns: dict[str, dict[str, list[Any]]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file saved by --save has no footer
        reader = RrdReader(path)
        recordings = list(reader.recordings())
        for ch in reader.stream():
            ep = str(ch.entity_path)
            rows[ep] = rows.get(ep, 0) + ch.num_rows
            timelines.setdefault(ep, set()).update(ch.timeline_names)
            rb = ch.to_record_batch()
            cols = columns.setdefault(ep, {})
            for name in rb.schema.names:
                if ":" in name and not name.startswith("rerun."):
                    cols.setdefault(name, []).extend(rb.column(name).to_pylist())
    return Saved(rows, timelines, columns, recordings)


def last(saved: Saved, entity: str, column: str) -> Any:
    values = [v for v in saved.columns.get(entity, {}).get(column, []) if v is not None]
    assert values, f"{entity} has no {column}: entities {sorted(saved.rows)}"
    return values[-1]


def texts(saved: Saved, entity: str, column: str) -> list[str]:
    """The strings of a text column, one per row."""
    out = []
    for v in saved.columns.get(entity, {}).get(column, []):
        out.extend(v if isinstance(v, list) else [v])
    return [x for x in out if isinstance(x, str)]


def strip(saved: Saved, entity: str) -> np.ndarray:
    strips = last(saved, entity, "LineStrips2D:strips")
    return np.asarray(strips[0], dtype=float)


def scale_of(saved: Saved, view: str = "polar") -> float:
    """The division of a polar view (um): its outermost ring is labelled with three of them."""
    label = last(saved, f"/{view}/reference/labels", "Points2D:labels")[1]
    m = re.fullmatch(r"\+([0-9.]+) µm", label)
    assert m, label
    return float(m.group(1)) / 3


def check_stream(saved: Saved, script: Script, n_tests: int = 2) -> None:
    """The entities of a whole run, with plausible content."""
    for ep in (
        *(f"/{view}/reference/{ref}" for view in ("polar", "live")
          for ref in ("nominal", "band", "scale", "axes", "labels")),
        *(f"/{view}/{d}/{kind}" for view in ("polar", "live") for d in ("ccw", "cw") for kind in ("measured", "model")),
        "/polar/verdict",
        "/polar/verdict/text",
        "/live/status",
        "/length",
        "/findings",
        "/events",
        "/trends/backlash_um/x",
        "/trends/backlash_um/y",
        "/trends/circularity_um/G_b",
        "/trends/servo_mismatch_ms",
        "/trends/squareness_urad",
        "/trends/scale_mismatch_ppm",
    ):
        assert saved.rows.get(ep), f"{ep} missing: {sorted(saved.rows)}"
    assert {"time", "test"} <= saved.timelines["/polar/ccw/measured"]
    assert "time" in saved.timelines["/length"]
    assert saved.recordings and saved.recordings[0].application_id == "ballbar"

    # the last complete test's polar curves: measured and fitted agree, span the test's circularity, and lie
    # inside the outermost ring (three divisions of the scale, each 0.2 R0)
    test = script.results[-1]
    s = scale_of(saved)
    for name in ("ccw", "cw"):
        meas, model = strip(saved, f"/polar/{name}/measured"), strip(saved, f"/polar/{name}/model")
        assert 500 <= len(meas) <= 2000 and len(model) == 2000
        dr_meas = (np.hypot(meas[:, 0], meas[:, 1]) - R0) * s / (0.2 * R0)
        dr_model = (np.hypot(model[:, 0], model[:, 1]) - R0) * s / (0.2 * R0)
        G = test["iso230_4"][f"G_{name}_um"]
        assert np.ptp(dr_meas) == pytest.approx(G, rel=0.1)
        assert np.ptp(dr_model) == pytest.approx(G, rel=0.1)
        assert max(np.abs(dr_meas).max(), np.abs(dr_model).max()) <= 3 * s + 1e-6  # the scale holds the data
        assert np.abs(dr_meas).max() > 3 * s / 2.5 - 1e-6  # and is not far too large (the next smaller would cut)
    mantissa = s / 10 ** math.floor(math.log10(s))
    assert min(abs(mantissa - m) for m in (1.0, 2.0, 5.0)) < 1e-9  # an automatic, round scale

    # the findings of the last test
    md = texts(saved, "/findings", "TextDocument:text")[-1]
    assert md.startswith(f"## NO LIMITS SET · test {n_tests} ") and "provisional" not in md.split("\n")[0]
    for part in ("What matters most", "Servo mismatch", "Backlash X", "ISO 230-4", "What to do", "G(b)"):
        assert part in md
    assert texts(saved, "/polar/verdict/text", "Points2D:labels")[-1].startswith(f"NO LIMITS SET · test {n_tests}")

    # the raw length: every sample (100 Hz is below the 200 Hz cap), in millimetres
    lengths = np.concatenate([np.atleast_1d(v) for v in saved.columns["/length"]["Scalars:scalars"]])
    assert lengths.size == script.L.size
    assert np.allclose(np.sort(lengths), np.sort(script.L))

    # one trend point per test, near the machine's truth
    bx = np.concatenate(saved.columns["/trends/backlash_um/x"]["Scalars:scalars"])
    servo = np.concatenate(saved.columns["/trends/servo_mismatch_ms"]["Scalars:scalars"])
    assert bx.size == n_tests and servo.size == n_tests
    assert np.all(np.abs(bx - 4.0) < 0.6)
    assert np.all(np.abs(servo - SERVO_MS) < 0.15)
    assert {"time", "test"} <= saved.timelines["/trends/backlash_um/x"]

    events = " ".join(texts(saved, "/events", "TextLog:text"))
    assert "feed_in" in events and "feed_out" in events and "opened" in events

    # a test event shows the wall-clock time of its sample (UTC), not the device's seconds
    b0 = script.items[0][1]
    host0 = float(b0.t_host[0] - b0.t_device[0])
    offset = time.time() - time.monotonic()
    feed_ins = [m for k, m in script.items if k == "message" and m.get("event") == "feed_in"]
    lines = [e for e in texts(saved, "/events", "TextLog:text") if ": feed_in" in e]
    assert len(feed_ins) == n_tests and len(lines) >= n_tests
    for m in feed_ins:
        hits = [ln for ln in lines if ln.startswith(f"test {m['test_index']}: feed_in at ")]
        assert hits and all("t=" not in ln for ln in hits), lines
        hh, mm, ss = re.search(r"at (\d\d):(\d\d):(\d\d\.\d{3}) UTC", hits[0]).groups()  # type: ignore[union-attr]
        shown = int(hh) * 3600 + int(mm) * 60 + float(ss)
        want = (host0 + m["t_s"] + offset) % 86400.0
        assert abs((shown - want + 43200.0) % 86400.0 - 43200.0) < 0.5, (hits[0], want)


# --------------------------------------------------------------------------- streams


def test_connect_mode_stream_is_received_and_read_back(
    script: Script, receivers: list[Receiver], tmp_path: Path
) -> None:
    port = free_port()
    rx = Receiver(tmp_path, "rx", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy", polar_update_s=0.005)
    costs = feed(v, script.items)
    assert v.stats()["errors"] == 0
    t0 = time.monotonic()
    v.stop()
    assert time.monotonic() - t0 < 1.0
    v.stop()  # twice is harmless
    rx.finish()
    saved = read_rrd(rx.rrd)
    check_stream(saved, script)
    assert float(np.median(costs)) < 0.002 and max(costs) < 0.25
    # the circle grew live during its data arc, before its result came
    sizes = [len(v[0]) for v in saved.columns["/live/ccw/measured"]["LineStrips2D:strips"] if v]
    assert len(sizes) > 4 and min(sizes) < 0.5 * max(sizes)


def test_serve_mode_late_viewer_gets_the_history(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    port = free_port()
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=port, server_memory_limit="64MiB"), plan=PLAN)
    wait_connected(v)
    assert v.address == f"rerun+http://127.0.0.1:{port}/proxy"
    assert listening(port)
    first, rest = script.split(0.6)
    feed(v, first)  # nobody watches yet: the server keeps it
    # a viewer that connects to the daemon: the rerun CLI as a client, saving what it is sent
    rx = Receiver(tmp_path, "late", free_port(), connect=v.address)
    receivers.append(rx)
    feed(v, rest)
    time.sleep(0.3)
    v.stop()
    # (rerun 0.41 keeps serving a viewer still connected until it leaves or the process exits)
    rx.finish()
    check_stream(read_rrd(rx.rrd), script)


def test_faster_than_real_time_source(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    """A replay at 10x: the length series is decimated on the host clock, the circles on the device's."""
    fast: list[tuple[str, Any]] = []
    for kind, x in script.items:
        if kind == "batch":
            x = SampleBatch.from_columns(1000.0 + x.t_device / 10.0, x.t_device, x.length_mm, x.seq, x.status)
        fast.append((kind, x))
    port = free_port()
    rx = Receiver(tmp_path, "fast", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy", length_hz=200.0)
    feed(v, fast)
    v.stop()
    rx.finish()
    saved = read_rrd(rx.rrd)
    n_length = sum(np.atleast_1d(x).size for x in saved.columns["/length"]["Scalars:scalars"])
    assert n_length == pytest.approx(script.L.size / 5, rel=0.05)  # 1000 Hz on the host clock -> 200 Hz
    for name in ("ccw", "cw"):
        assert len(strip(saved, f"/polar/{name}/measured")) > 500  # every kept sample of the arc


def test_serve_mode_waits_for_a_busy_port(caplog: pytest.LogCaptureFixture) -> None:
    with socket.socket() as blocker:
        blocker.bind(("127.0.0.1", 0))
        blocker.listen()
        port = blocker.getsockname()[1]
        v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=port, retry_s=0.05), plan=PLAN)
        deadline = time.monotonic() + 5.0
        while "in use" not in caplog.text and time.monotonic() < deadline:
            time.sleep(0.02)
        assert not v.connected
        assert "in use" in caplog.text
        v.on_batch(SampleBatch.from_columns([1.0], [1.0], [50.0], [0], [0]))  # logs nothing, keeps nothing big
        assert v.stats()["skipped"] == 1
    wait_connected(v)
    assert listening(port)
    v.stop()
    assert not listening(port)  # the server process goes with the stream


# --------------------------------------------------------------------------- viewers that misbehave


@pytest.mark.parametrize("kind", ["temporal", "static"])
def test_a_late_viewer_gets_the_references_after_a_client_pushed_them_out_of_the_server(
    kind: str, script: Script, receivers: list[Receiver], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The server drops its oldest messages first, whoever sent the new ones: a client pushing four times its
    buffer of static data evicts the daemon's references (checked: without their timer, the static case fails).
    The daemon sends them again every SCENE_REFRESH_S (here shortened), whether or not it saw the client."""
    monkeypatch.setattr(scene_module, "SCENE_REFRESH_S", 0.5)
    port = free_port()
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=port, server_memory_limit="16MiB"), plan=PLAN)
    try:
        wait_connected(v)
        first, rest = script.split(0.5)
        feed(v, first)
        subprocess.run([sys.executable, str(Path(__file__).resolve().parent / "pusher.py"), v.address, kind, "64"],
                       timeout=120, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(0.6)
        half = len(rest) // 2
        feed(v, rest[:half])  # the daemon's next sends
        rx = Receiver(tmp_path, "late", free_port(), connect=v.address)
        receivers.append(rx)
        time.sleep(1.0)  # it has what the server holds
        v.stop()
        rx.finish()
        saved = read_rrd(rx.rrd)
        for path in ("/polar/reference/nominal", "/polar/reference/axes", "/polar/reference/axis_labels"):
            assert saved.rows.get(path, 0) > 0, (path, sorted(saved.rows))
    finally:
        v.stop()


def test_a_connection_to_the_server_that_ends_has_the_history_sent_again(script: Script) -> None:
    """What a client pushed while connected may have evicted the history: when its connection ends (seen at the
    supervisor's next look), the next send starts the history again."""
    port = free_port()
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=port), plan=PLAN)
    try:
        wait_connected(v)
        first, rest = script.split(0.5)
        feed(v, first)
        srv = v._server
        assert srv is not None
        own = len(srv._clients)  # its listener, the daemon's own stream
        with socket.create_connection(("127.0.0.1", port)):
            deadline = time.monotonic() + 5.0
            while len(srv._clients) <= own:
                assert time.monotonic() < deadline, "the supervisor did not see the client"
                time.sleep(0.05)
        deadline = time.monotonic() + 5.0
        while srv.clients_ended == 0:
            assert time.monotonic() < deadline, "the supervisor did not see the client go"
            time.sleep(0.05)
        refreshes = v.stats()["refreshes"]
        feed(v, rest[:20])
        assert v.stats()["refreshes"] == refreshes + 1
        feed(v, rest[20:40])
        assert v.stats()["refreshes"] == refreshes + 1  # once
    finally:
        v.stop()


def test_a_server_that_takes_nothing_is_restarted_and_sent_the_scene(
    script: Script, receivers: list[Receiver], tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A wedged server (here stopped: alive, listening, reading nothing; a flooding client does the same)
    leaves all the daemon sends in the daemon's gRPC client.  Once a flush to it times out twice in a
    row, the supervisor restarts it, and the new one is sent the scene."""
    import rerun as rr

    port = free_port()
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=port, server_memory_limit="64MiB",
                                  health_s=0.2), plan=PLAN)
    try:
        wait_connected(v)
        first, rest = script.split(0.5)
        feed(v, first)
        srv = v._server
        assert srv is not None and srv.proc is not None
        stopped, generation = srv.proc.pid, srv.generation
        os.kill(stopped, signal.SIGSTOP)
        # the stream's own rate takes minutes to fill the sockets' buffers; a busy one does it in seconds
        rec = v._rec
        assert rec is not None
        rng = np.random.default_rng(0)
        deadline = time.monotonic() + 60.0
        while srv.generation == generation:
            assert time.monotonic() < deadline, f"the stopped server was not restarted: {v.stats()}"
            rec.log("busy", rr.Points2D(rng.random((2000, 2))))
            v.on_idle()
            time.sleep(0.002)
        with contextlib.suppress(ProcessLookupError):
            os.kill(stopped, signal.SIGCONT)  # it was killed: nothing to resume
        assert "taken none of the daemon's stream" in caplog.text
        assert srv.stall_kills == 1 and srv.rss_kills == 0 and v.stats()["server_stalls"] == 1
        wait_connected(v)
        assert srv.proc is not None and srv.proc.pid != stopped
        rx = Receiver(tmp_path, "after", free_port(), connect=v.address)
        receivers.append(rx)
        feed(v, rest)
        time.sleep(0.5)
        v.stop()
        rx.finish()
        saved = read_rrd(rx.rrd)
        assert saved.rows.get("/polar/reference/nominal", 0) > 0, sorted(saved.rows)  # the scene, sent again
        assert saved.rows.get("/length", 0) > 0  # and the live stream after it
    finally:
        v.stop()



def test_vanished_viewer_never_slows_the_listener(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    port = free_port()
    rx = Receiver(tmp_path, "doomed", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy")
    first, rest = script.split(0.3)
    feed(v, first)
    rx.signal(signal.SIGKILL)
    rx.proc.wait(5.0)
    half = len(rest) // 2
    costs = feed(v, rest[:half])
    time.sleep(0.4)  # the probe notices the viewer has gone
    costs += feed(v, rest[half:])
    assert not v.connected
    assert max(costs) < 0.25 and float(np.median(costs)) < 0.002
    st = v.stats()
    assert st["errors"] == 0 and st["skipped"] > 0  # nothing is logged (or buffered) for nobody
    t0 = time.monotonic()
    v.stop()
    assert time.monotonic() - t0 < v.options.stop_timeout_s + 1.0


def test_restarted_viewer_is_sent_the_scene_again(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    port = free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    rx = Receiver(tmp_path, "before", port)
    receivers.append(rx)
    v = connected_viewer(url)
    first, rest = script.split(0.7)  # the first test is done, the second under way
    feed(v, first)
    rx.signal(signal.SIGKILL)
    rx.proc.wait(5.0)
    deadline = time.monotonic() + 5.0
    while v.connected:
        assert time.monotonic() < deadline
        v.on_idle()
        time.sleep(0.05)
    rx2 = Receiver(tmp_path, "after", port)
    receivers.append(rx2)
    deadline = time.monotonic() + 10.0
    while not v.connected:
        assert time.monotonic() < deadline, "no reconnection within 10 s"
        v.on_idle()
        time.sleep(0.05)
    assert v.stats()["sinks"] == 2
    feed(v, rest)
    v.stop()
    rx2.finish()
    saved = read_rrd(rx2.rrd)
    # the restarted viewer has the whole picture: history of trends, references, both tests' last results
    check_stream_after_restart(saved)


def check_stream_after_restart(saved: Saved) -> None:
    for ep in (
        "/polar/reference/nominal",
        "/polar/reference/band",
        "/polar/ccw/measured",
        "/polar/cw/model",
        "/findings",
        "/length",
    ):
        assert saved.rows.get(ep), f"{ep} missing: {sorted(saved.rows)}"
    bx = np.concatenate(saved.columns["/trends/backlash_um/x"]["Scalars:scalars"])
    assert bx.size == 2  # test 1 re-sent on reconnection, test 2 live
    assert texts(saved, "/findings", "TextDocument:text")[-1].startswith("## NO LIMITS SET · test 2 ")


def test_absent_viewer_then_present(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    """Nothing is logged for nobody; a viewer that appears later is sent the last test whole."""
    port = free_port()
    v = RerunViewer(ViewerOptions(mode="connect", url=f"rerun+http://127.0.0.1:{port}/proxy", retry_s=0.1), plan=PLAN)
    end_of_test_1 = next(i for i, (k, x) in enumerate(script.items) if k == "message" and x["kind"] == "test")
    costs = feed(v, script.items[: end_of_test_1 + 20])
    assert not v.connected and max(costs) < 0.25
    rx = Receiver(tmp_path, "late", port)
    receivers.append(rx)
    deadline = time.monotonic() + 10.0
    while not v.connected:
        assert time.monotonic() < deadline, "no connection within 10 s"
        v.on_idle()
        time.sleep(0.05)
    v.stop()
    rx.finish()
    saved = read_rrd(rx.rrd)
    for ep in (
        "/polar/reference/nominal",
        "/polar/ccw/measured",
        "/polar/cw/measured",
        "/polar/ccw/model",
        "/polar/cw/model",
    ):
        assert saved.rows.get(ep), f"{ep} missing: {sorted(saved.rows)}"
    assert len(strip(saved, "/polar/cw/measured")) > 500  # from the cache: its samples were let go
    assert texts(saved, "/findings", "TextDocument:text")[-1].startswith("## NO LIMITS SET · test 1 ")
    assert np.concatenate(saved.columns["/trends/backlash_um/x"]["Scalars:scalars"]).size == 1


def test_frozen_viewer_cannot_hold_stop(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    port = free_port()
    rx = Receiver(tmp_path, "frozen", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy", stop_timeout_s=0.5, health_s=3600.0)
    first, rest = script.split(0.3)
    feed(v, first)
    rx.signal(signal.SIGSTOP)  # alive, listening, reading nothing
    costs = feed(v, rest)
    assert max(costs) < 0.25
    t0 = time.monotonic()
    v.stop()
    assert time.monotonic() - t0 < 0.5 + 1.0
    rx.close()  # the stuck disconnect (if any) ends with the connection


# --------------------------------------------------------------------------- pure parts


def test_model_overlay_reproduces_the_fit(script: Script) -> None:
    """The model rebuilt from a result's parameters leaves the fit's own residual."""
    for res in script.results:
        sq = []
        for d in (1, -1):
            tm = result_timing(res, d)
            if tm is None:
                continue
            m = (script.t >= tm.start_s) & (script.t <= tm.end_s)
            u = tm.angle_rad(PLAN, script.t[m])
            model = model_deviation_um(res, d, u)
            assert model is not None
            sq.append(((script.L[m] - PLAN.radius_mm) * 1000.0 - model) ** 2)
        rms = math.sqrt(float(np.mean(np.concatenate(sq))))
        assert rms == pytest.approx(res["residual_rms_um"], rel=0.2, abs=0.005), res["kind"]


def test_findings_markdown(script: Script) -> None:
    md = findings_markdown(script.results[0])
    assert md.startswith("## Test 1 in progress: CCW circle (provisional)")
    md = findings_markdown(script.results[2])
    # the verdict in words first (no limits here), then what matters most in an engineer's words, what to do
    assert md.startswith("## NO LIMITS SET · test 1\n")
    most = md[md.index("### What matters most"):md.index("### What to do")]
    assert most.split("\n")[2].startswith("1. **Servo mismatch** ") and "X lags Y by" in most
    assert "centre" not in most and "Centre" not in most  # the set-up is stated apart
    assert "Set-up, not the machine" in md and "### What to do" in md and "backlash" in md
    assert "`servo_mismatch_ms`" in md  # the field name, for a service developer, in the detail
    assert "Warning" not in md and "machine `" not in md and "lag –" not in md
    md = findings_markdown({**script.results[2], "warnings": ["timing model: the feed-in is too short"]})
    assert "**Warning:** timing model: the feed-in is too short" in md


def test_options() -> None:
    with pytest.raises(ViewerConfigError, match="'colour'"):
        ViewerOptions.from_dict({"colour": "red"})
    for bad in (
        {"mode": "push"},
        {"url": "http://x:1/"},
        {"bind": "localhost"},
        {"port": 0},
        {"scale_um": -1.0},
        {"polar_points": 3},
    ):
        with pytest.raises(ViewerConfigError):
            ViewerOptions.from_dict(bad)
    assert ViewerOptions(bind="0.0.0.0", port=9877).address == "rerun+http://127.0.0.1:9877/proxy"
    xs = (0.1, 1.6, 3.1, 30.0, 80.0, 170.0)
    assert [nice_scale_um(x) for x in xs] == [1.0, 1.0, 2.0, 10.0, 50.0, 100.0]
    assert all(x <= 3 * nice_scale_um(x) for x in xs)  # within the outermost ring


def test_off_mode_does_nothing(script: Script) -> None:
    v = RerunViewer(ViewerOptions(mode="off"), plan=PLAN)
    feed(v, script.items[:50])
    assert not v.connected and v.stats()["batches"] == 0
    v.stop()


def test_from_daemon_config() -> None:
    from ballbar.daemon.config import load

    port = free_port()
    cfg = load(
        None,
        [
            f"rerun.port={port}",
            'rerun.bind="127.0.0.1"',
            "rerun.magnification=2500",
            "rerun.memory_limit_mb=64",
            "plan.radius_mm=100.0",
        ],
    )
    v = RerunViewer.from_config(cfg)
    try:
        assert v.options.scale_um == pytest.approx(8.0)  # 200 R / M: a division at 0.2 R0
        assert v.options.server_memory_limit == "64MiB"
        wait_connected(v)
        assert listening(port)
    finally:
        v.stop()


def test_polar_geometry_and_layout() -> None:
    # +X to the right, +Y up: the view's y axis points down, so the second coordinate is negated
    pts = polar_points(np.array([0.0, math.pi / 2]), np.array([0.0, 20.0]), scale_um=20.0)
    assert np.allclose(pts, [[R0, 0.0], [0.0, -1.2 * R0]])  # a division at 0.2 R0
    assert np.allclose(polar_points(np.array([0.0]), np.array([-200.0]), 20.0), [[0.0, 0.0]])  # clamped at 0
    default_blueprint()  # builds against the installed rerun


def test_trend_views_scale_to_the_uncertainty_and_titles_fit() -> None:
    """A trend that moves within its standard errors gets a y range of at least +-4 of them about its mean (flat,
    not a drift); one that moves far more keeps its points with their bars; a limit line is always in range."""
    n = len(TRENDS)
    j_servo = [p for p, _f, _l, _c in TRENDS].index("servo_mismatch_ms")
    j_bx = [p for p, _f, _l, _c in TRENDS].index("backlash_um/x")
    rows = np.full((3, 2 + 2 * n), np.nan)
    rows[:, 0], rows[:, 1] = [1, 2, 3], [1000.0, 1100.0, 1200.0]
    rows[:, 2 + j_servo] = [3.0306, 3.0312, 3.0318]  # autoscaled, this filled the plot like a drift
    rows[:, 2 + n + j_servo] = 0.01
    rows[:, 2 + j_bx] = [4.0, 8.0, 12.0]  # a real change: 8 um against 0.1 um standard errors
    rows[:, 2 + n + j_bx] = 0.1
    ranges = trend_ranges(rows, k=1.0)
    lo, hi = ranges["servo_mismatch_ms"]
    assert lo <= 3.0312 - 0.04 + 1e-12 and hi >= 3.0312 + 0.04 - 1e-12 and hi - lo < 0.1
    lo, hi = ranges["backlash_um"]
    assert lo <= 4.0 - 0.1 and hi >= 12.0 + 0.1 and hi - lo < 9.5  # the points, not +-4 stderr, set it
    assert "circularity_um" not in ranges and "squareness_urad" not in ranges
    lo, hi = trend_ranges(rows, {"servo_mismatch_ms": (2.0, 1.6)}, k=2.0)["servo_mismatch_ms"]
    assert lo < 1.6 and hi > 3.0318 + 2 * 0.01  # the limit, the warning level and every bar inside
    default_blueprint(ranges)  # builds with the ranges
    # titles short enough for a third of the trends panel (the long ones were cut)
    assert [t for _o, t in TREND_VIEWS] and all(len(t) <= 28 for _o, t in TREND_VIEWS)
    assert {o for o, _t in TREND_VIEWS} == {p.split("/")[0] for p, _f, _l, _c in TRENDS}


def test_layouts_sent_again_and_again_cost_no_thread_and_overwrite_each_other(tmp_path: Path) -> None:
    """rerun 0.41 makes (and never frees) a blueprint stream with two threads per send_blueprint: the viewer sends
    every layout on its one stream, each view and container keeping its id, so a new layout replaces the last."""
    import rerun as rr

    from ballbar.daemon.rerun.blueprint import Blueprints as _Blueprints

    def native_threads() -> int:
        return len(os.listdir("/proc/self/task"))

    rec = rr.RecordingStream("ballbar")
    sink = rec.memory_recording()
    blueprints = _Blueprints(rec, "ballbar")
    before = native_threads()
    for i in range(40):
        if i == 20:
            blueprints.new_sink()  # a viewer (re)connected
        blueprints.send(default_blueprint({"squareness_urad": (10.0, 20.0 + i)}))
    assert native_threads() == before  # (rec.send_blueprint: 80 more)
    rrd = tmp_path / "layouts.rrd"
    rrd.write_bytes(sink.drain_as_bytes())
    printed = subprocess.run([str(RERUN), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=60)
    assert printed.returncode == 0, printed.stderr[-2000:]
    out = printed.stdout
    stores = set(re.findall(r'StoreId\(\s*Blueprint,\s*"ballbar",\s*"(\w+)"', out))
    assert len(stores) == 1  # one blueprint store, its info sent again to the new sink
    assert len(re.findall(r"BlueprintActivationCommand", out)) == 40
    views = set(re.findall(r" - (/view/[0-9a-f-]+) - ", out))
    n_views = len(TREND_VIEWS) + 5  # the trends, the two polar plots, the length, the findings and the events
    assert len(views) == n_views, sorted(views)  # the same views, overwritten: not 40 layouts' worth
    rec.disconnect()


def test_stop_without_any_viewer_is_quick(script: Script) -> None:
    v = RerunViewer(ViewerOptions(mode="connect", url=f"rerun+http://127.0.0.1:{free_port()}/proxy"), plan=PLAN)
    costs = feed(v, script.items[:2000])
    assert not v.connected and max(costs) < 0.05
    t0 = time.monotonic()
    v.stop()
    assert time.monotonic() - t0 < 0.7


# --------------------------------------------------------------------------- bounds: what is kept, sent and served


def replayed(script: Script, times: int) -> Iterator[tuple[str, Any]]:
    """The script's two tests ``times`` over, back to back on one clock (times, numbers, test indices moved on)."""
    from ballbar.tools.bench.bench_viewer import shifted

    n = script.t.size
    period = n / PLAN.sample_hz
    for k in range(times):
        for kind, x in script.items:
            if kind == "batch":
                yield kind, SampleBatch.from_columns(x.t_host + k * period, x.t_device + k * period, x.length_mm,
                                                     x.seq + k * n, x.status, x.events if k == 0 else (), x.source)
            else:
                msg = shifted(x, k, period, tests=2)
                msg["test_id"] = f"m1-{msg.get('test_index')}"
                yield kind, msg


@dataclass
class Row:
    entity: str
    time: int | None  # ns
    test: int | None
    row_id: bytes
    values: dict[str, Any]

    @property
    def key(self) -> tuple[int, bytes]:
        return (self.time if self.time is not None else -1, self.row_id)


def read_rows(path: Path) -> list[Row]:
    """Every row of a saved stream, with its timelines and row id (for latest-at with clears)."""
    import pyarrow as pa
    from rerun.chunk import RrdReader

    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for ch in RrdReader(path).stream():
            rb = ch.to_record_batch()
            names = rb.schema.names
            cols = {n: (rb.column(n).cast(pa.int64()) if n == "time" else rb.column(n)).to_pylist()
                    for n in names if n in ("time", "test", "rerun.controls.RowId")
                    or (":" in n and not n.startswith("rerun."))}
            for i in range(rb.num_rows):
                vals = {n: v[i] for n, v in cols.items() if n not in ("time", "test", "rerun.controls.RowId")}
                out.append(Row(str(ch.entity_path), cols.get("time", [None] * rb.num_rows)[i],
                               cols.get("test", [None] * rb.num_rows)[i], cols["rerun.controls.RowId"][i], vals))
    return out


def text_of(row: Row) -> str:
    v = row.values.get("TextDocument:text")
    return "".join(v) if isinstance(v, list) else str(v or "")


def visible_strips(rows: Sequence[Row], prefix: str, t_ns: int) -> dict[str, np.ndarray]:
    """The line strips under ``prefix`` a viewer shows at time ``t_ns`` (latest-at, clears applied)."""
    clears = [r for r in rows if r.values.get("Clear:is_recursive") is not None and r.time is not None
              and r.time <= t_ns]
    latest: dict[str, Row] = {}
    for r in rows:
        if r.entity.startswith(prefix) and r.values.get("LineStrips2D:strips") is not None and (
                r.time is None or r.time <= t_ns) and (r.entity not in latest or r.key > latest[r.entity].key):
            latest[r.entity] = r
    out = {}
    for ent, r in latest.items():
        cleared = any(c.key > r.key and (c.entity == ent or (c.values["Clear:is_recursive"]
                                                                and ent.startswith(c.entity + "/")))
                      for c in clears)
        if not cleared:
            out[ent] = np.asarray(r.values["LineStrips2D:strips"][0], dtype=float)
    return out


def test_live_circle_is_sent_in_pieces(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    """Each update sends the growing tip and the pieces completed since, never the whole circle again."""
    port = free_port()
    rx = Receiver(tmp_path, "pieces", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy", polar_update_s=0.1)
    feed(v, script.items[: len(script.items) // 2])  # the first test, the second under way
    v.stop()
    rx.finish()
    rows = read_rows(rx.rrd)
    piece = v._piece
    result_1 = min(r.time for r in rows if r.entity == "/live/status/text" and r.time is not None
                   and "CCW circle fitted" in str(r.values.get("Points2D:labels")))
    live = [r for r in rows if r.entity.startswith("/live/ccw/measured") and r.time is not None
            and r.time < result_1 and r.values.get("LineStrips2D:strips")]
    assert len(live) > 20
    assert max(len(r.values["LineStrips2D:strips"][0]) for r in live) <= piece + 1
    children = [r.entity for r in live if r.entity != "/live/ccw/measured"]
    # each completed piece sent once, and again only when the scale grew (everything is redrawn then)
    feed_in = min(r.time for r in rows if r.entity == "/live/ccw" and r.time is not None)
    rescales = sum(1 for r in rows if r.entity == "/live/reference/labels" and r.time is not None
                   and feed_in <= r.time < result_1)
    assert len(set(children)) >= 3 and len(children) <= len(set(children)) * (1 + rescales)
    # just before the result, the pieces join up into the circle so far: shared end points, in order
    shown = visible_strips(rows, "/live/ccw/measured", result_1 - 1)
    parts = [shown[f"/live/ccw/measured/{k}"] for k in range(len(shown) - 1)] + [shown["/live/ccw/measured"]]
    for a, b in itertools.pairwise(parts):
        assert len(a) == piece + 1 and np.allclose(a[-1], b[0])
    pts = np.concatenate([parts[0]] + [p[1:] for p in parts[1:]])
    angles = np.unwrap(np.arctan2(-pts[:, 1], pts[:, 0]))
    assert np.all(np.diff(angles) > 0)  # CCW, each point once, in order
    # after it, the whole circle alone (the pieces cleared)
    shown = visible_strips(rows, "/live/ccw/measured", result_1)
    assert list(shown) == ["/live/ccw/measured"] and len(shown["/live/ccw/measured"]) > 500


def test_the_wall_clock_offset_holds_through_preemption_and_follows_a_step(monkeypatch: pytest.MonkeyPatch) -> None:
    """Points a fixed interval apart on the host clock land the same interval apart on the viewer's time axis: a
    thread preempted between reading the two clocks does not move them; a wall clock that is stepped does."""
    from ballbar.daemon.rerun.listener import WallClock

    wall = [1_000_000.0]
    mono = [50.0]
    reads = iter([0.0, 0.0, 0.0] + [0.004, 0.0, 0.0] * 5 + [0.0] * 3)  # 4 ms lost between the reads, once per call
    monkeypatch.setattr(time, "time", lambda: wall[0])
    monkeypatch.setattr(time, "monotonic", lambda: mono[0] + next(reads, 0.0))
    clock = WallClock()
    assert clock.offset() == 999_950.0
    for _ in range(4):
        assert clock.offset() == 999_950.0  # not 999_949.996
    wall[0] += 3600.0  # the wall clock stepped by an hour
    assert clock.offset() == 999_950.0 + 3600.0


@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_length_series_is_decimated_and_coalesced(rate: float, receivers: list[Receiver], tmp_path: Path) -> None:
    """Whatever the sample rate: length_hz points per second of the host clock, sent every send_interval_s."""
    port = free_port()
    rx = Receiver(tmp_path, "length", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy")
    seconds, per = 12.0, int(rate * 0.02)
    t0 = time.monotonic()
    seq = np.arange(int(seconds * rate))
    t = t0 + seq / rate
    L = 100.0 + 0.001 * np.sin(seq / 137.0)
    for i in range(0, seq.size, per):
        v.on_batch(SampleBatch.from_columns(t[i : i + per], t[i : i + per], L[i : i + per], seq[i : i + per],
                                            np.zeros(per)))
    v.stop()
    rx.finish()
    rows = [r for r in read_rows(rx.rrd) if r.entity == "/length" and r.values.get("Scalars:scalars") is not None]
    values = np.concatenate([np.atleast_1d(r.values["Scalars:scalars"]) for r in rows])
    stamps = np.array([r.time for r in rows], dtype=float) / 1e9
    # (a viewer that reconnects is sent the length history again: the same points, counted once)
    stamps, first = np.unique(stamps, return_index=True)
    values = values[first]
    assert values.size == pytest.approx(seconds * v.options.length_hz, abs=2)
    assert np.allclose(np.diff(stamps), 1.0 / v.options.length_hz, rtol=1e-3)
    assert np.allclose(values, L[:: int(rate / v.options.length_hz)][: values.size])  # samples, not averages
    sends = v.stats()["length_sends"]
    assert seconds / v.options.send_interval_s - 2 <= sends <= seconds / v.options.send_interval_s + 2


def test_a_slow_length_series_is_sent_at_the_polar_cadence(receivers: list[Receiver], tmp_path: Path) -> None:
    """At 15.625 Hz a send every send_interval_s would carry four points, each costing as much as a full one:
    the series goes every polar_update_s instead, every sample in it."""
    from ballbar.daemon.rerun.listener import MIN_SEND_POINTS

    port = free_port()
    rx = Receiver(tmp_path, "slow", port)
    receivers.append(rx)
    v = connected_viewer(f"rerun+http://127.0.0.1:{port}/proxy")
    rate, seconds = 15.625, 20.0
    seq = np.arange(int(seconds * rate))
    t = time.monotonic() + seq / rate
    L = 100.0 + 0.001 * np.sin(seq / 7.0)
    try:
        assert rate * v.options.send_interval_s < MIN_SEND_POINTS
        for i in range(0, seq.size, 2):  # the reader's batches: two samples each
            j = min(i + 2, seq.size)
            v.on_batch(SampleBatch.from_columns(t[i:j], t[i:j], L[i:j], seq[i:j], np.zeros(j - i)))
        sends = v.stats()["length_sends"]
    finally:
        v.stop()
    rx.finish()
    rows = [r for r in read_rows(rx.rrd) if r.entity == "/length" and r.values.get("Scalars:scalars") is not None]
    values = np.concatenate([np.atleast_1d(r.values["Scalars:scalars"]) for r in rows])
    _, first = np.unique(np.array([r.time for r in rows], dtype=float), return_index=True)
    assert np.allclose(values[first], L[: first.size]) and first.size >= seq.size - 2 * MIN_SEND_POINTS
    per_s = seconds / v.options.polar_update_s
    assert per_s - 2 <= sends <= per_s + 2, sends


def test_own_buffers_stay_bounded(script: Script, monkeypatch: pytest.MonkeyPatch) -> None:
    """After many tests the viewer holds no more than it is configured to."""
    import ballbar.daemon.rerun.listener as viewer_mod

    monkeypatch.setattr(viewer_mod, "TRENDS_KEPT", 8)
    opts = ViewerOptions(mode="serve", bind="127.0.0.1", port=free_port(), server_memory_limit="8MiB",
                         max_buffer_samples=10_000, history_tests=3, history_length_s=60.0, history_length_hz=2.0)
    v = RerunViewer(opts, plan=PLAN)
    wait_connected(v)
    peak: dict[str, int] = {}
    try:
        for kind, x in replayed(script, 10):
            feed(v, [(kind, x)])
            st = v.stats()
            for key in ("buffered_samples", "pending_samples", "history_tests", "history_length_points",
                        "trend_points"):
                peak[key] = max(peak.get(key, 0), st[key])
            peak["pending_length"] = max(peak.get("pending_length", 0), sum(w.size for w, _L in v._len_pending))
            peak["store"] = max(peak.get("store", 0), v._samples.data.shape[1])
        # a test that never ends: 40 000 samples after its feed-in, four times what may be kept
        t0 = float(x.t_device[-1]) + 10.0 if kind == "batch" else float(script.t[-1]) * 10 + 10.0
        seq0 = 10**7
        feed(v, [("message", {"kind": "event", "event": "feed_in", "test_index": 999, "t_s": t0,
                              "time_axis": "device"})])
        host0 = v._latest_host + 2.0
        for i in range(0, 40_000, 200):
            t = t0 + np.arange(i, i + 200) / PLAN.sample_hz
            feed(v, [("batch", SampleBatch.from_columns(host0 + t - t0, t, np.full(200, 50.0),
                                                          np.arange(seq0 + i, seq0 + i + 200), np.zeros(200)))])
            peak["buffered_samples"] = max(peak["buffered_samples"], v.stats()["buffered_samples"])
            peak["store"] = max(peak["store"], v._samples.data.shape[1])
        st = v.stats()
        thinned = v._keep_every
    finally:
        v.stop()
    assert thinned >= 2
    assert st["errors"] == 0 and st["refreshes"] >= 2  # the history was sent again as the server filled
    assert 5_000 <= peak["buffered_samples"] <= 10_000  # filled, then thinned
    assert peak["store"] == 10_000 + viewer_mod.MAX_PENDING_SAMPLES  # allocated once, never grown
    assert peak["pending_samples"] <= 100 * v.options.send_interval_s + 2  # 100 Hz: what 0.25 s brings
    assert peak["pending_length"] <= 100 * v.options.send_interval_s + 2
    assert st["history_tests"] == peak["history_tests"] == 3
    assert st["trend_points"] == peak["trend_points"] == 8
    assert peak["history_length_points"] <= 60 * 2 + 1


def test_late_viewer_gets_the_last_tests_whole(script: Script, receivers: list[Receiver], tmp_path: Path) -> None:
    """A server far too small for the run: a late viewer still gets the chosen history, whole."""
    opts = ViewerOptions(mode="serve", bind="127.0.0.1", port=free_port(), server_memory_limit="2MiB",
                         history_tests=4, history_length_s=3600.0)
    v = RerunViewer(opts, plan=PLAN)
    n_tests = 20
    try:
        wait_connected(v)
        feed(v, list(replayed(script, n_tests // 2)))
        while v.stats()["history_pending"]:  # a sending of the history under way goes on while idle
            v.on_idle()
        st = v.stats()
        time.sleep(0.5)
        rx = Receiver(tmp_path, "late", free_port(), connect=v.address)
        receivers.append(rx)
        rx.finish(timeout=20.0)
    finally:
        v.stop()
    assert st["errors"] == 0 and st["sent_mib"] > 4.0 and st["refreshes"] >= 3  # the server dropped a lot
    rows = read_rows(rx.rrd)
    results = {r.test: r for r in rows if r.entity == "/findings"  # at each test's result
               and r.test is not None and f" · test {r.test} · " in text_of(r).split("\n")[0]}
    whole = []
    for idx, r in sorted(results.items()):
        assert r.time is not None
        shown = visible_strips(rows, "/polar/", r.time)
        curves = {e: len(p) for e, p in shown.items() if not e.startswith(("/polar/reference", "/polar/verdict"))}
        if curves == {"/polar/ccw/measured": curves.get("/polar/ccw/measured"), "/polar/cw/measured":
                      curves.get("/polar/cw/measured"), "/polar/ccw/model": 2000, "/polar/cw/model": 2000} and min(
                curves.values()) > 500 and "/polar/reference/band" in shown:
            whole.append(idx)
    assert set(range(n_tests - 3, n_tests + 1)) <= set(whole), whole
    # the trends of every test
    trend_tests = {r.test for r in rows if r.entity == "/trends/backlash_um/x" and r.test is not None}
    assert trend_tests == set(range(1, n_tests + 1))
    # the length: the whole run at history_length_hz, only the recent part at full rate
    # (distinct times: each sending of the history repeats the same points, which may all still be there)
    stamps = np.unique(np.concatenate([np.full(np.atleast_1d(r.values["Scalars:scalars"]).size, r.time)
                                       for r in rows if r.entity == "/length" and r.values.get("Scalars:scalars")
                                       is not None])).astype(float) / 1e9
    run = (script.t.size * n_tests / 2) / PLAN.sample_hz
    assert stamps[-1] - stamps[0] > 0.95 * run
    early = stamps[stamps < stamps[0] + run / 4]
    late = stamps[stamps > stamps[-1] - 10.0]
    assert early.size <= (run / 4) * v.options.history_length_hz * 1.1 + 2
    assert late.size >= 10.0 * v.options.length_hz * 0.9


def test_a_clean_stop_on_ctrl_c_logs_no_error(tmp_path: Path) -> None:
    """Ctrl-C in a terminal signals the whole process group: the server, in a session of its own, outlives the
    daemon's last flush, so Rerun's client logs no ERROR (it logged two at every such stop when the server died
    first: "Write messages call failed: transport error", "Failed to flush previous sink")."""
    code = (
        "import faulthandler, signal, time, sys\n"
        "faulthandler.register(signal.SIGUSR1, all_threads=True)\n"
        # As at a terminal: a suite run as a shell's background job (``cmd &``) starts every child with Ctrl-C
        # ignored, and Python then installs no KeyboardInterrupt (the stop this test is about never came).
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "from ballbar.daemon.rerun import RerunViewer, ViewerOptions\n"
        "v = RerunViewer(ViewerOptions(mode='serve', bind='127.0.0.1', port=int(sys.argv[1])))\n"
        "try:\n"
        "    while not v.connected:\n"
        "        v.on_idle(); time.sleep(0.05)\n"
        "    print('ready', flush=True)\n"
        "    while True:\n"
        "        v.on_idle(); time.sleep(0.05)\n"
        "except KeyboardInterrupt:\n"
        "    v.stop()\n"
        "    print('stopped', flush=True)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(free_port())], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(0.5)
        os.killpg(proc.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole process group
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:  # where it hangs: every thread's stack, then the rest of its output
            os.kill(proc.pid, signal.SIGUSR1)
            time.sleep(1.0)
            os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate(timeout=10)
            pytest.fail(f"no exit within 30 s of Ctrl-C; its threads and log:\n{err[-6000:]}")
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)
    assert "stopped" in out, err[-2000:]
    assert "ERROR" not in err, err[-2000:]


def test_a_late_viewer_is_told_which_verdicts_are_from_the_history(
        script: Script, receivers: list[Receiver], tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A viewer that connects replays the server's buffer oldest first, for 10 s and more after a long run: each
    test of the history's verdict bar says it is one (its time, ``from the history``, its colour dimmed), and so
    does its findings' heading; at the present, where the viewer ends up, the last test's verdict stands as it
    is.  The log names the viewer to run: the one installed beside the daemon."""
    caplog.set_level(logging.INFO, logger="ballbar.daemon.rerun")
    port = free_port()
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=port, server_memory_limit="64MiB",
                                  history_refresh_s=0.3), plan=PLAN)
    try:
        wait_connected(v)
        feed(v, script.items)  # nobody watches: the tests go to the server live
        time.sleep(0.4)
        v.on_idle()  # the history is sent again (history_refresh_s)
        while v.stats()["history_pending"]:
            v.on_idle()
        assert v.stats()["refreshes"] >= 2
        rx = Receiver(tmp_path, "late", free_port(), connect=v.address)
        receivers.append(rx)
        rx.finish(timeout=10.0)
    finally:
        v.stop()
    assert f"(viewers: {Path(sys.executable).parent / 'rerun'} rerun+http://127.0.0.1:{port}/proxy)" in caplog.text
    rows = read_rows(rx.rrd)
    bars = sorted((r for r in rows if r.entity == "/polar/verdict/text" and r.time is not None), key=lambda r: r.key)
    past = [r for r in bars if "from the history" in r.values["Points2D:labels"][0]]
    assert {r.test for r in past} == {1, 2}, [r.values for r in bars]
    for r in past:
        label = r.values["Points2D:labels"][0]
        assert re.fullmatch(rf"NO LIMITS SET · test {r.test} at \d\d:\d\d:\d\d UTC · from the history", label), label
    now = bars[-1]  # latest-at at the newest time: what a viewer that has caught up shows
    assert now.values["Points2D:labels"][0].startswith("NO LIMITS SET · test 2 · G(b) "), now.values
    assert all(r.time is not None and now.time is not None and r.time < now.time for r in past)
    colours = {tuple(r.values["LineStrips2D:colors"]) if isinstance(r.values["LineStrips2D:colors"], list) else
               r.values["LineStrips2D:colors"] for r in rows if r.entity == "/polar/verdict"
               and r.values.get("LineStrips2D:colors") is not None}
    assert len(colours) == 2, colours  # the no-limits grey, and it dimmed
    docs = sorted((r for r in rows if r.entity == "/findings" and r.time is not None and text_of(r)),
                  key=lambda r: r.key)
    heads = [text_of(r).split("\n")[0] for r in docs]
    assert any(h.startswith("## NO LIMITS SET · test 1 · ") and h.endswith(" · from the history") for h in heads)
    assert heads[-1].startswith("## NO LIMITS SET · test 2 · ") and "history" not in heads[-1], heads[-3:]


def test_a_past_verdicts_words_say_when() -> None:
    """The bar of a test from the history: its word and number, when (the date too when it is of another day),
    and that it is from the history; the detail is left for the findings (the bar's width at 1280 px)."""
    import datetime

    from ballbar.daemon.rerun.scene import TestRecord, past_headline

    wall = datetime.datetime(2026, 12, 6, 23, 10, 5, tzinfo=datetime.UTC).timestamp()
    r = TestRecord(9, wall, 5.0, {}, "## FAIL · test 9", "fail",
                   "FAIL · xy test 9 · Backlash X 12.0 ± 0.1 µm, limit 8.0 µm")
    assert past_headline(r, now=wall + 60) == "FAIL · xy test 9 at 23:10:05 UTC · from the history"
    assert past_headline(r, now=wall + 3600) == "FAIL · xy test 9 of 2026-12-06 23:10 UTC · from the history"
