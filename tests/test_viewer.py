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
import math
import os
import re
import shutil
import signal
import socket
import subprocess
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
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.daemon.viewer import (
    R0,
    RerunViewer,
    ViewerConfigError,
    ViewerOptions,
    default_blueprint,
    findings_markdown,
    model_deviation_um,
    nice_scale_um,
    polar_points,
    result_timing,
)
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


def scale_of(saved: Saved) -> float:
    label = last(saved, "/polar/reference/labels", "Points2D:labels")[3]
    m = re.match(r"\+([0-9.]+) µm", label)
    assert m, label
    return float(m.group(1))


def check_stream(saved: Saved, script: Script, n_tests: int = 2) -> None:
    """The entities of a whole run, with plausible content."""
    for ep in (
        "/polar/reference/nominal",
        "/polar/reference/band",
        "/polar/reference/scale",
        "/polar/reference/axes",
        "/polar/reference/labels",
        "/polar/ccw/measured",
        "/polar/cw/measured",
        "/polar/ccw/model",
        "/polar/cw/model",
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

    # the polar curves: measured and fitted agree, and span the test's circularity
    test = script.results[-1]
    s = scale_of(saved)
    for name in ("ccw", "cw"):
        meas, model = strip(saved, f"/polar/{name}/measured"), strip(saved, f"/polar/{name}/model")
        assert 500 <= len(meas) <= 2000 and len(model) == 2000
        dr_meas = (np.hypot(meas[:, 0], meas[:, 1]) - R0) * 2 * s / R0
        dr_model = (np.hypot(model[:, 0], model[:, 1]) - R0) * 2 * s / R0
        G = test["iso230_4"][f"G_{name}_um"]
        assert np.ptp(dr_meas) == pytest.approx(G, rel=0.1)
        assert np.ptp(dr_model) == pytest.approx(G, rel=0.1)
        assert np.abs(dr_meas).max() < 1.6 * s + 1e-9  # the automatic scale fits the curves
    mantissa = s / 10 ** math.floor(math.log10(s))
    assert min(abs(mantissa - m) for m in (1.0, 2.0, 5.0)) < 1e-9  # an automatic, round scale

    # the findings of the last test
    md = texts(saved, "/findings", "TextDocument:text")[-1]
    assert md.startswith(f"## Test {n_tests}") and "provisional" not in md.split("\n")[0]
    for part in ("Ranked findings", "servo_mismatch", "backlash_x", "ISO 230-4", "Advice", "G(b)"):
        assert part in md

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
    sizes = [len(v[0]) for v in saved.columns["/polar/ccw/measured"]["LineStrips2D:strips"] if v]
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
    assert texts(saved, "/findings", "TextDocument:text")[-1].startswith("## Test 2")


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
    assert texts(saved, "/findings", "TextDocument:text")[-1].startswith("## Test 1 ")
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
    assert md.startswith("## Test 1: CCW circle (provisional)")
    md = findings_markdown(script.results[2])
    assert md.startswith("## Test 1 · `m1-1`")
    assert "| 1 | servo_mismatch |" in md and "### Advice" in md and "backlash" in md
    assert "Warning" not in md
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
    assert [nice_scale_um(x) for x in (0.1, 1.6, 1.7, 30.0, 80.0, 170.0)] == [1.0, 1.0, 2.0, 20.0, 50.0, 200.0]


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
        assert v.options.scale_um == pytest.approx(20.0)  # 500 R / M
        assert v.options.server_memory_limit == "64MiB"
        wait_connected(v)
        assert listening(port)
    finally:
        v.stop()


def test_polar_geometry_and_layout() -> None:
    # +X to the right, +Y up: the view's y axis points down, so the second coordinate is negated
    pts = polar_points(np.array([0.0, math.pi / 2]), np.array([0.0, 20.0]), scale_um=20.0)
    assert np.allclose(pts, [[R0, 0.0], [0.0, -1.5 * R0]])
    assert np.allclose(polar_points(np.array([0.0]), np.array([-100.0]), 20.0), [[0.0, 0.0]])  # clamped at 0
    default_blueprint()  # builds against the installed rerun


def test_stop_without_any_viewer_is_quick(script: Script) -> None:
    v = RerunViewer(ViewerOptions(mode="connect", url=f"rerun+http://127.0.0.1:{free_port()}/proxy"), plan=PLAN)
    costs = feed(v, script.items[:2000])
    assert not v.connected and max(costs) < 0.05
    t0 = time.monotonic()
    v.stop()
    assert time.monotonic() - t0 < 0.7
