"""End to end over a pty: the simulated device in a child process, a source in this one.

Every test runs a whole (short) simulated test at 1 kHz device rate, sped up, and
checks exact counts: every sample sent arrives in order, and every injected
fault shows up as exactly the losses and decoder drops it must cause.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbar.analysis.plan import TestPlan
from ballbar.daemon import config as cfgmod
from ballbar.daemon.cli import main as cli_main
from ballbar.daemon.listeners import Listener
from ballbar.daemon.mcap import McapLogger, list_recordings
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.daemon.service import AnalysisListener
from ballbar.daemon.sources import Source, open_source
from ballbar.protocol import Status
from ballbar.tools.simdevice import DeviceProcess, main
from ballbar.tools.simulator import MachineModel, simulate

pytestmark = pytest.mark.usefixtures("no_leaks")

# A short test: R 50 mm at 3000 mm/min with 10 deg overshoot, 14 426 samples at 1 kHz.
PLAN = TestPlan(radius_mm=50, feed_mm_min=3000, overshoot_deg=10, dwell_s=0.2)
MACHINE = MachineModel(lead_s=0.2, tail_s=0.2)
PLAN_ARGS = [
    "--radius-mm=50",
    "--feed-mm-min=3000",
    "--overshoot-deg=10",
    "--dwell-s=0.2",
    "--set=lead_s=0.2",
    "--set=tail_s=0.2",
]
RATE = 1000.0
CAL = 50.0


def reference(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    res = simulate(PLAN, MACHINE, RATE, seed)
    return res.t_s, res.length_mm


class Collector:
    """Everything a source delivers, gathered while the test waits for something."""

    def __init__(self, src: Source) -> None:
        self.src = src
        self.batches: list[SampleBatch] = []
        self.events: list[SourceEvent] = []
        self.n = 0

    def pump(self, timeout: float = 0.05) -> None:
        b = self.src.read(timeout)
        if b is not None:
            self.batches.append(b)
            self.events += b.events
            self.n += len(b)

    def until(self, cond: Callable[[], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not cond():
            if time.monotonic() > deadline:
                raise AssertionError(f"timed out waiting for {what}; events {[str(e.kind) for e in self.events]}")
            self.pump()

    def merged(self) -> SampleBatch:
        return SampleBatch.concat(self.batches)

    def kinds(self) -> list[str]:
        return [str(e.kind) for e in self.events]


def run_to_done(dev: DeviceProcess, col: Collector, timeout: float = 40.0, by_count: bool = False) -> dict[str, Any]:
    """Read until the device has sent everything and every intact sample has arrived.

    The source must be read all along: a device whose pty is full waits for its reader.
    ``by_count``: wait for as many samples as were sent (the device's counter restarted).
    """
    deadline = time.monotonic() + timeout
    done: dict[str, Any] | None = None
    while done is None:
        col.pump()
        for ev in dev.poll_events():
            if ev.get("event") == "done":
                done = ev["stats"]
        if time.monotonic() > deadline:
            raise AssertionError(f"device not done; got {col.n} samples")
    if by_count:
        col.until(lambda: col.n >= done["sent"], 10.0, f"{done['sent']} samples")
    else:
        last = done["last_seq"]
        col.until(lambda: col.n > 0 and col.merged().seq[-1] >= last, 10.0, f"sample {last}")
    col.pump(0.1)  # whatever trails (decoder counts)
    return done


def start(*args: str) -> tuple[DeviceProcess, Collector]:
    dev = DeviceProcess(*args, "--wait")
    try:
        src = open_source(dev.url)
        col = Collector(src)
        col.until(lambda: "opened" in col.kinds(), 5.0, "opened")
        dev.send("start")
    except Exception:
        dev.close()
        raise
    return dev, col


def finish(dev: DeviceProcess, col: Collector) -> None:
    col.src.close()
    assert dev.close() == 0


# ----------------------------------------------------------------------------- clean round trips


def test_binary_whole_test_arrives_complete_in_order() -> None:
    dev, col = start("--protocol=binary", "--rate=1000", "--speedup=5", *PLAN_ARGS)
    try:
        done = run_to_done(dev, col)
        st = col.src.stats()
    finally:
        finish(dev, col)
    t, length = reference()
    n = t.shape[0]
    got = col.merged()
    assert done["generated"] == done["sent"] == n
    assert got.seq.tolist() == list(range(n))
    assert st.lost == 0 and st.decode == {} and st.samples == n
    # Lengths exactly as the device quantised them (10 nm counts), calibration added back.
    assert np.array_equal(got.length_mm, CAL + np.rint((length - CAL) * 1e5) / 1e5)
    assert np.array_equal(got.t_device, np.rint(t * 1e6) / 1e6)
    assert np.all(got.status == int(Status.SIMULATED))
    assert np.all(np.diff(got.t_host) >= 0)
    # The device clock runs five times faster than the host's: so do the stamps.  (The status states the ratio
    # once the map rests on 5 s of reads: this run is shorter.)
    assert np.polyfit(got.t_device, got.t_host, 1)[0] == pytest.approx(0.2, rel=0.02)


def test_ascii_timestamped_two_tests_at_10khz_wall_rate() -> None:
    dev, col = start(
        "--protocol=ascii", "--timestamp=ms", "--rate=1000", "--speedup=10", "--repeat=2", "--gap-s=0.5", *PLAN_ARGS
    )
    try:
        done = run_to_done(dev, col)
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    assert done["tests"] == 2 and done["generated"] == done["sent"]
    assert got.seq.shape[0] == done["sent"] and np.all(np.diff(got.seq) >= 1)
    assert st.lost == 0 and st.decode == {}
    # The device numbers samples from its clock: the gap between tests is no loss.
    t, length = reference()
    first = got.length_mm[: t.shape[0]]
    expected = np.array([CAL + float(f"{x:+.5f}") for x in (length - CAL).tolist()])
    assert np.array_equal(first, expected)
    assert np.allclose(got.t_device[: t.shape[0]], t, atol=1e-9)
    assert [e["event"] for e in dev.events if e["event"] == "test"] == ["test"]


# ----------------------------------------------------------------------------- faults


@pytest.mark.parametrize("protocol", ["binary", "ascii"])
def test_injected_faults_are_counted_exactly(protocol: str) -> None:
    extra = ["--timestamp=us"] if protocol == "ascii" else []
    dev, col = start(f"--protocol={protocol}", *extra, "--rate=1000", "--speedup=10", *PLAN_ARGS)
    try:
        col.until(lambda: col.n > 500, 10.0, "500 samples")
        for cmd in ("garbage 100", "corrupt 3", "drop 5", "garbage 7", "stall 0.7", "corrupt 2", "drop 1"):
            dev.send(cmd)
        done = run_to_done(dev, col)
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    lost_on_wire = done["dropped"] + done["corrupted"] + done["stalled"]
    assert done["corrupted"] == 5 and done["dropped"] == 6 and done["stalled"] > 0
    assert st.samples == done["sent"] == got.seq.shape[0]
    assert st.lost == lost_on_wire
    assert st.samples + st.lost == done["generated"]
    assert np.all(np.diff(got.seq) >= 1)
    assert st.stalls == 1 and col.kinds().count("resumed") == 1
    assert st.lost_by_cause.get("stall", 0) >= done["stalled"]
    if protocol == "binary":
        assert st.decode == {"bad_crc": 5, "skipped_bytes": 107 + 5 * 17}
    else:
        # The 100-byte junk line is longer than a line may be (64): a long line, not a bad one.
        assert st.decode == {"long_line": 1, "bad_line": 1 + 5, "skipped_bytes": 107 + done["corrupted_bytes"]}


def test_unplug_and_replug_during_a_test() -> None:
    dev, col = start("--protocol=binary", "--rate=1000", "--speedup=10", *PLAN_ARGS)
    try:
        col.until(lambda: col.n > 1000, 10.0, "1000 samples")
        dev.send("unplug 0.5")
        col.until(lambda: "unplugged" in col.kinds(), 5.0, "unplugged")
        col.until(lambda: "replugged" in col.kinds(), 5.0, "replugged")
        done = run_to_done(dev, col)
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    t, length = reference()
    # The same source object recovered and accounted for every sample the device took.
    assert (st.unplugs, st.replugs) == (1, 1)
    assert st.samples + st.lost == done["generated"] == t.shape[0]
    assert st.lost >= done["unplugged"] > 0  # plus what was in flight in the pty
    outage = [e for e in col.events if e.kind == EventKind.LOST and e.detail == "outage"]
    assert len(outage) == 1 and outage[0].count == st.lost
    replug = next(e for e in col.events if e.kind == EventKind.REPLUGGED)
    assert replug.gap_s >= 0.4
    assert np.all(np.diff(got.seq) >= 1)
    assert np.array_equal(got.length_mm, CAL + np.rint((length[got.seq] - CAL) * 1e5) / 1e5)


def test_device_reset_is_reported() -> None:
    dev, col = start("--protocol=binary", "--rate=1000", "--speedup=10", *PLAN_ARGS)
    try:
        col.until(lambda: col.n > 500, 10.0, "500 samples")
        dev.send("reset")
        done = run_to_done(dev, col, by_count=True)
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    assert st.resets == 1 and "device_reset" in col.kinds()
    assert got.seq.shape[0] == done["generated"] and np.all(np.diff(got.seq) == 1)
    assert np.all(np.diff(got.t_device) > 0)
    # The event names the first sample after the restart: where the device's own clock reads about 0 again.
    reset = next(e for e in col.events if e.kind == EventKind.DEVICE_RESET)
    k = int(np.searchsorted(got.seq, reset.seq))
    assert got.seq[k] == reset.seq and 0 < got.t_device[k] - got.t_device[k - 1] < 0.0015


def test_clock_jump_is_reported_and_costs_no_sample() -> None:
    dev, col = start("--protocol=binary", "--rate=1000", "--speedup=10", *PLAN_ARGS)
    try:
        col.until(lambda: col.n > 500, 10.0, "500 samples")
        assert dev.send("jump 10")["seconds"] == 10.0
        done = run_to_done(dev, col)
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    assert done["clock_jumps"] == 1 and st.clock_jumps == 1 and st.lost == 0 and st.resets == 0
    assert got.seq.tolist() == list(range(done["generated"]))
    jump = next(e for e in col.events if e.kind == EventKind.CLOCK_JUMP)
    assert jump.gap_s == pytest.approx(10.0, abs=1e-6)
    steps = np.diff(got.t_device)
    k = int(np.argmax(steps))
    assert got.seq[k + 1] == jump.seq and steps[k] == pytest.approx(10.001, abs=1e-6)
    assert np.all(np.delete(steps, k) == pytest.approx(0.001, abs=1e-6))
    assert np.all(np.diff(got.t_host) >= 0)


# ----------------------------------------------------------------------------- live analysis across faults


class Feeding(Collector):
    """A collector that also hands every batch to listeners, as the daemon's loop does."""

    def __init__(self, src: Source, *listeners: Listener) -> None:
        super().__init__(src)
        self.listeners = listeners

    def pump(self, timeout: float = 0.05) -> None:
        n = len(self.batches)
        super().pump(timeout)
        for b in self.batches[n:]:
            for lst in self.listeners:
                lst.on_batch(b)


def live_test_with_a_fault(tmp_path: Path, fault: str) -> tuple[list[dict[str, Any]], Path]:
    """Two short tests on the pty device; ``fault`` sent in the middle of the first.

    The samples go through the daemon's analysis and into its MCAP log, as in
    ``ballbar run``; returns what the analysis emitted and the recordings.
    """
    cfg = cfgmod.load(None, [*(f"plan.{k}" for k in ("radius_mm=50", "feed_mm_min=3000", "overshoot_deg=10",
                                                       "dwell_s=0.2", "sample_hz=1000")), "daemon.machine_id=live"],
                      env={})
    logger = McapLogger(tmp_path, "live")
    got: list[dict[str, Any]] = []

    def emit(msg: dict[str, Any]) -> None:
        got.append(msg)
        logger.on_message(msg)

    analysis = AnalysisListener(cfg, emit)
    logger.on_message({"kind": "config", "config": cfg.to_dict()})
    # a longer tail: the second feed-out must settle before the stream ends
    dev = DeviceProcess("--protocol=binary", "--rate=1000", "--speedup=5", "--repeat=2", "--wait", *PLAN_ARGS,
                        "--set=tail_s=1.5")
    col = None
    try:
        col = Feeding(open_source(dev.url), analysis, logger)
        col.until(lambda: "opened" in col.kinds(), 5.0, "opened")
        dev.send("start")
        col.until(lambda: any(m.get("event") == "feed_in" for m in got), 20.0, "the feed-in")
        dev.send(fault)
        run_to_done(dev, col, by_count=fault == "reset")
        col.until(lambda: sum(m["kind"] == "test" for m in got) >= 1, 10.0, "the second test's result")
    finally:
        analysis.stop()
        logger.stop()
        if col is not None:
            col.src.close()
        assert dev.close() == 0
    return got, tmp_path / "recordings"


@pytest.mark.parametrize(
    "fault, reason",
    [("reset", "device reset (its sample counter or clock restarted; how long it was down is unknown) at t="),
     ("jump 10", "device clock jump of +10.000 s (its sample counter ran on) at t=")],
)
def test_a_test_across_a_device_fault_is_rejected_live_and_offline(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fault: str, reason: str
) -> None:
    got, records = live_test_with_a_fault(tmp_path, fault)
    by_index: dict[int, list[str]] = {}
    for m in got:
        if isinstance(m.get("test_index"), int):
            by_index.setdefault(m["test_index"], []).append(m.get("event") or m["kind"])
    # Live: the first test is rejected at once, before its feed-out, with the reason; the second passes.
    assert by_index[1][:2] == ["feed_in", "test_rejected"] and "test" not in by_index[1], by_index
    assert by_index[2][-1] == "test", by_index
    rejected = next(m for m in got if m.get("event") == "test_rejected")
    assert rejected["message"].startswith(reason), rejected["message"]
    first_id, second_id = rejected["test_id"], next(m["test_id"] for m in got if m["kind"] == "test")
    assert first_id != second_id
    # The second test's provisional circles assumed the programmed feed: nothing was learnt from the first.
    circles = [m for m in got if m["kind"] == "circle" and m["test_index"] == 2]
    assert circles and all(abs(c["timing"]["assumed_feed_mm_min"] - 3000.0) < 1e-9 for c in circles)
    # Offline, from the MCAP log: the directory's newest complete test is the second ...
    assert len(list_recordings(records)) == 2
    capsys.readouterr()
    assert cli_main(["analyze", str(records), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["source"]["test_id"] == second_id
    # ... and the first, asked for by id or as its own file, is rejected for the same reason (one line, exit 1).
    for args in (["analyze", str(records), "--test-id", first_id], ["analyze", str(list_recordings(records)[0])]):
        assert cli_main(args) == 1
        err = capsys.readouterr().err
        assert reason in err and err.count("\n") == 1, err
    assert cli_main(["analyze", str(records), "--list", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [(r["test_id"], r["status"]) for r in listed] == [(first_id, "rejected"), (second_id, "complete")]
    assert listed[0]["message"].startswith(reason)


# ----------------------------------------------------------------------------- polled


def test_polled_ascii_gauge() -> None:
    dev, col = start("--protocol=ascii", "--mode=poll", "--rate=200", "--speedup=1", "--repeat=0", *PLAN_ARGS)
    try:
        assert "mode=poll" in dev.url
        col.until(lambda: col.n >= 100, 10.0, "100 answers")
        dev.send("drop 3")
        col.until(lambda: col.src.stats().lost_by_cause.get("poll_timeout", 0) >= 3, 10.0, "3 poll timeouts")
        n0 = col.n
        col.until(lambda: col.n >= n0 + 50, 10.0, "50 more answers")
        dev.send("unplug 0.3")
        col.until(lambda: "replugged" in col.kinds(), 10.0, "replugged")
        n1 = col.n
        col.until(lambda: col.n >= n1 + 50, 10.0, "50 answers after the replug")
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    assert st.lost_by_cause["poll_timeout"] == 3
    # The ticks the host could not poll while the gauge was away are lost, not skipped.
    assert st.lost_by_cause["outage"] >= 0.25 * 200
    assert (st.unplugs, st.replugs) == (1, 1)
    # Every tick is either a sample or a counted loss.
    assert got.seq[-1] - got.seq[0] + 1 == st.samples + st.lost
    assert np.all(np.diff(got.seq) >= 1) and np.all(np.diff(got.t_host) > 0)
    assert np.all(np.abs(got.length_mm - 50.0) < 1.6)
    assert np.isnan(got.t_device).all()


def test_lowest_rate() -> None:
    dev, col = start("--protocol=binary", "--rate=15.625", "--speedup=40", *PLAN_ARGS)
    try:
        done = run_to_done(dev, col)
        st = col.src.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    assert done["generated"] == done["sent"] == st.samples == got.seq.shape[0] > 200
    assert got.seq.tolist() == list(range(got.seq.shape[0])) and st.lost == 0
    # 15.625 Hz: 64 000 us per sample, exactly as the device clock said.
    assert np.array_equal(got.t_device, np.arange(got.seq.shape[0]) * 64_000 / 1e6)


def test_command_line_errors() -> None:
    assert main(["--mode=poll", "--protocol=binary"]) == 2
    assert main(["--rate=20000"]) == 2
    assert main(["--radius-mm=-1"]) == 2


# ----------------------------------------------------------------------------- bursts (in process)


class FakePort:
    """A port that keeps what is written: the device's loop driven by hand, without a pty."""

    path = "fake"

    def __init__(self) -> None:
        self.is_open = True
        self.data = bytearray()
        self.writes = 0

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def fileno(self) -> int | None:
        return None

    def write(self, data: bytes | bytearray) -> int:
        self.data += data
        self.writes += 1
        return len(data)

    def read(self) -> bytes:
        return b""


def synthetic_tests(rate: float, n: int, tests: int = 2, gap_s: float = 0.5) -> Any:
    for i in range(tests):
        t = np.arange(n) / rate + i * (n / rate + gap_s)
        yield t, 100.0 + 0.4 * np.sin(7.0 * t) + 1e-3 * np.cos(91.0 * t), np.rint(t * rate).astype(np.int64)


def drive(settings: Any, steps: list[float], commands: dict[float, str], t0: float, rate: float, n: int) -> Any:
    from ballbar.tools.simbar import SimDevice
    from ballbar.tools.simfeed import Feed

    port = FakePort()
    out = os.open(os.devnull, os.O_WRONLY)
    try:
        dev = SimDevice(Feed(synthetic_tests(rate, n)), port, settings, out)  # type: ignore[arg-type]
        dev.started = True
        dev._last_wall = t0
        for now in sorted({*steps, *commands}):
            dev.step(now)
            if now in commands:
                dev.command(commands[now], now)
                dev.step(now)
    finally:
        os.close(out)
    return dev, port


@pytest.mark.parametrize("protocol", ["binary", "ascii"])
def test_bursts_carry_the_bytes_of_one_write_per_sample(protocol: str) -> None:
    """The device stepped at random coarse times (a write each) sends exactly the bytes and counts
    it sends stepped every millisecond, across faults, a reset, a clock jump and a test boundary."""
    from ballbar.protocol import ascii as ascii_proto
    from ballbar.tools.simbar import Settings

    rate, n, t0 = 1000.0, 3000, 1000.0
    fmt = ascii_proto.AsciiFormat(ts_unit="us", width=9, ts_width=12)
    settings = Settings(protocol=protocol, rate=rate, cal_mm=100.0, fmt=fmt, burst_s=0.016)
    # Commands between two samples' due times (x.xxx5 s), so that no sample sits on a boundary.
    commands = {
        t0 + 0.2505: "garbage 5", t0 + 0.4005: "corrupt 2", t0 + 0.6005: "drop 3", t0 + 0.8005: "stall 0.1",
        t0 + 1.2005: "unplug 0.05", t0 + 1.5005: "reset", t0 + 2.0005: "jump 3", t0 + 2.9995: "stall 0.004",
    }
    fine = [t0 + k / 1000 for k in range(1, 7000)]
    rng = np.random.default_rng(1)
    coarse = (t0 + np.cumsum(rng.uniform(0.0005, 0.04, 400))).tolist()
    a, port_a = drive(settings, fine, commands, t0, rate, n)
    b, port_b = drive(settings, coarse, commands, t0, rate, n)
    assert a.done and b.done
    sa, sb = asdict(a.stats), asdict(b.stats)
    sa.pop("cpu_s")
    sb.pop("cpu_s")
    assert sa == sb
    assert sa["generated"] == 2 * n and sa["stalled"] >= 100 and sa["unplugged"] >= 50
    assert (sa["dropped"], sa["corrupted"], sa["garbage_bytes"], sa["resets"], sa["clock_jumps"]) == (3, 2, 5, 1, 1)
    assert bytes(port_a.data) == bytes(port_b.data)
    assert port_b.writes < 400 and b._encoder.blocks < 20  # encoded a block at a time, not per write


def test_next_wake_is_the_next_sample_or_the_next_burst() -> None:
    from ballbar.tools.simbar import Settings

    t0 = 1000.0
    for rate, expect in ((15.625, 0.064), (1000.0, 0.016)):
        dev, port = drive(Settings(rate=rate, cal_mm=100.0, burst_s=0.016), [t0], {}, t0, rate, 1000)
        assert port.writes == 1 and dev.stats.sent == 1
        wake = dev.next_wake(t0)
        assert wake == pytest.approx(t0 + expect, abs=1e-5)
        dev.step(wake + 1e-6)
        assert dev.stats.sent == (2 if rate < 100 else 17)


# ----------------------------------------------------------------------------- the daemon's simulated device


def test_the_next_test_is_made_while_the_current_one_streams() -> None:
    """Feed starts making test 2 as soon as test 1 is loaded, before any of test 1 is taken."""
    import threading

    from ballbar.tools.simfeed import Feed

    entered, release = threading.Event(), threading.Event()
    made = list(synthetic_tests(RATE, 500, tests=2))

    def tests() -> Any:
        yield made[0]
        entered.set()
        release.wait(30.0)
        yield made[1]

    feed = Feed(tests())
    try:
        assert entered.wait(10.0), "test 2 is not made until test 1 has been sent"
        assert feed.tests == 1 and feed.next_t == made[0][0][0]
    finally:
        release.set()
    _t, _length, seq = feed.take_until(math.inf)
    assert np.array_equal(seq, np.concatenate([made[0][2], made[1][2]])) and feed.tests == 2
    assert feed.exhausted and feed.take_until(math.inf)[0].size == 0


def test_the_demo_device_streams_on_between_tests() -> None:
    """The demo machine of ``ballbar run --simulate`` (its plan and machine, 5 s between tests) keeps sending
    across the change of test: the daemon's serial source sees no stall and loses nothing.  Before, the device
    simulated each next test (about a second) with nothing sent meanwhile: a stall and a resume every test."""
    from ballbar.tools.simulate import simdevice_args

    cfg = cfgmod.load(env={})
    dev = DeviceProcess(*simdevice_args(cfg, 20.0), "--wait")
    try:
        # A stall at half the default 0.5 s: making a test takes the device 0.5 to 0.7 s here (more beside a
        # busy daemon, where the default caught it), while it writes every 16 ms when it streams.
        src = open_source(dev.url + "&stall_s=0.25")
        col = Collector(src)
        col.until(lambda: "opened" in col.kinds(), 5.0, "opened")
        dev.send("start")
        tests: list[dict[str, Any]] = []
        deadline = time.monotonic() + 60.0
        # the device's "test" event comes when it starts sending the second test (the first is there at start)
        while not tests or col.n == 0 or col.merged().seq[-1] < tests[0]["seq"] + 20_000:
            col.pump()
            tests += [e for e in dev.poll_events() if e.get("event") == "test"]
            assert time.monotonic() < deadline, f"the second test did not stream; events {col.kinds()}"
    finally:
        col.src.close()
        assert dev.close() == 0
    assert "stall" not in col.kinds() and "resumed" not in col.kinds(), col.kinds()
    seq = col.merged().seq
    assert np.array_equal(seq, np.arange(seq[0], seq[-1] + 1))  # across the change of test, nothing lost


def test_the_daemons_source_opens_the_simulated_device_once_it_is_up() -> None:
    """``ballbar run --simulate`` does not wait for the device: its source reads nothing, with no event,
    until the device's pty is there, then the serial source on it takes over."""
    from ballbar.tools.simulate import simulated_device

    cfg = cfgmod.load(None, [*(f"plan.{k}" for k in ("radius_mm=50", "feed_mm_min=3000", "overshoot_deg=10",
                                                       "dwell_s=0.2", "sample_hz=1000"))], env={})
    with simulated_device(cfg, 10.0) as src:
        link = src.url.split("?")[0].removeprefix("serial:")
        assert src.url == f"serial:{link}?protocol=binary&rate=1000&cal_mm=50.0"  # known before the device is up
        col = Collector(src)
        col.until(lambda: col.n > 2000, 30.0, "2000 samples")
        assert src.url == src.device.url and col.kinds()[0] == "opened" and "unplugged" not in col.kinds()
        assert src.stats().samples == col.n and src.stats().lost == 0
    assert not os.path.exists(os.path.dirname(link))


def test_a_simulated_device_that_fails_to_start_is_a_source_error() -> None:
    from ballbar.daemon.errors import SourceError
    from ballbar.tools.simulate import SimulatedDeviceSource

    with DeviceProcess("--rate=20000", wait=False) as dev:
        src = SimulatedDeviceSource(dev, "serial:/nonexistent?protocol=binary&rate=1000&cal_mm=50", 1000.0)
        with pytest.raises(SourceError, match="exited before it was up"):
            for _ in range(100):
                src.read(0.2)
        src.close()


def test_help_lists_every_machine_key_with_its_default_and_unit(capsys: pytest.CaptureFixture[str]) -> None:
    """``ballbar-simdevice --help`` names each key ``--set`` takes, with its default and, for those with one, its
    unit, from the model's own fields (a key added to the model is listed without a copy to keep), and the 3D
    machine's axis keys."""
    from dataclasses import fields

    from ballbar.tools.machine3d import AXIS_KEYS

    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    model = MachineModel()
    for f in fields(MachineModel):
        value = getattr(model, f.name)
        if isinstance(value, float):
            assert f"{f.name} = {value:g}" in text, f.name
        else:
            assert f"{f.name} = " in text, f.name
    for shown in ("backlash_x_um = 0 um", "kv_y_per_s = 30 1/s", "accel_mm_s2 = 2000 mm/s^2",
                  "squareness_urad = 0 urad", "spike_tau_x_s = 0.03 s", "scale_x_ppm = 0 ppm"):
        assert shown in text
    for key in AXIS_KEYS:
        assert key.format("{x,y,z}") in text, key


@pytest.mark.parametrize("sets, drifts, needle", [
    (("backlash_q_um=3",), (), "--sim-set: unknown machine key 'backlash_q_um'"),
    (("kv_x_per_s=-3",), (), "--sim-set: machine key 'kv_x_per_s' must be > 0"),
    ((), ("backlash_x_um=fast",), "--sim-drift needs KEY=NUMBER"),
    ((), ("wear_um=1",), "--sim-drift: unknown machine key 'wear_um'"),
])
def test_a_bad_simulated_machine_key_is_named_before_the_device_starts(
        sets: tuple[str, ...], drifts: tuple[str, ...], needle: str) -> None:
    from ballbar.daemon.errors import ConfigError
    from ballbar.tools.simulate import simulated_device

    with pytest.raises(ConfigError, match=re.escape(needle)), simulated_device(cfgmod.load(env={}), 5.0, "passing",
                                                                                 sets, drifts):
        pass


def test_the_named_machines_device_arguments() -> None:
    """``--simulate MACHINE``'s device: the demo machine, the named machine's keys over it and ``--sim-set``'s over
    those, its wear and ``--sim-drift``'s after; the same keys on the 3D machine of a library of several plans,
    which takes them (each plan's plane then sees its axes' gains)."""
    from ballbar.daemon.plugins import SIM_MACHINES
    from ballbar.tools.machine3d import Machine3D
    from ballbar.tools.simulate import MACHINES, SIM_MACHINE, SIM_MACHINE_3D, simdevice_args

    assert tuple(MACHINES) == SIM_MACHINES  # the daemon's choices are the plug-in's machines

    def pairs(args: list[str], flag: str) -> list[str]:
        return [b for a, b in itertools.pairwise(args) if a == flag]

    cfg = cfgmod.load(env={})
    args = simdevice_args(cfg, 20.0, "failing", ("backlash_x_um=15",), ("backlash_y_um=1",))
    sets = pairs(args, "--set")
    assert sets[:len(SIM_MACHINE)] == list(SIM_MACHINE)
    assert sets[len(SIM_MACHINE):] == ["backlash_x_um=12", "kv_x_per_s=25", "kv_y_per_s=35", "backlash_x_um=15"]
    assert pairs(args, "--drift") == ["backlash_y_um=1"]
    assert pairs(simdevice_args(cfg, 20.0, "wearing"), "--drift") == ["backlash_x_um=0.5", "kv_y_per_s=0.5"]
    assert pairs(simdevice_args(cfg, 20.0), "--drift") == []

    lib = cfgmod.load(None, ["plans.xy.plane=\"XY\"", "plans.zx.plane=\"ZX\""], env={})
    args = simdevice_args(lib, 20.0, "failing")
    assert "--library" in args
    sets = pairs(args, "--set")
    assert sets[:len(SIM_MACHINE_3D)] == list(SIM_MACHINE_3D)
    machine = Machine3D.from_settings({k: float(v) for k, v in (s.split("=") for s in sets)})
    xy, zx = machine.project("XY"), machine.project("ZX")
    assert (xy.backlash_x_um, xy.kv_x_per_s, xy.kv_y_per_s) == (12.0, 25.0, 35.0)
    assert (zx.kv_x_per_s, zx.kv_y_per_s) == (28.0, 25.0)  # ZX: Z (the 3D demo's 28/s), then X
