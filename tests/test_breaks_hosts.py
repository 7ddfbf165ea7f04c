"""Real hosts and links: a host that stalls, a link that drops, a clock that jumps.

A host that stalls stamps the samples taken meanwhile late, in a burst: re-timed
on the grid (analysis/retime.py), offline, chunk by chunk and live through a
serial source on a pty.  A link that drops loses a stretch of samples on a clock
that ran on: analysed and stated, or rejected saying what the gap takes
(analysis/dropout.py).  A clock that jumps is still rejected.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_sources import FakeDevice, read_all

from ballbar.analysis import TestPlan
from ballbar.analysis.engine import TestAnalyzer, analyze_recording
from ballbar.analysis.retime import Retimer, retime
from ballbar.analysis.timeaxis import GAP_PERIODS, TimeAxis
from ballbar.daemon import config as cfgmod
from ballbar.daemon.cli import main
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.daemon.service import AnalysisListener
from ballbar.daemon.sources import open_source
from ballbar.protocol import ascii as ascii_proto
from ballbar.protocol.gauges import PROFILES
from ballbar.tools.simulator import MachineModel, simulate

pytestmark = pytest.mark.usefixtures("no_leaks")

FS = 250.0
P = 1.0 / FS
# R 100 mm at 1500 mm/min: 14.3 deg/s, so 2 s lost are 29 deg; about 56 s a test.
PLAN = TestPlan(radius_mm=100, feed_mm_min=1500, overshoot_deg=10, dwell_s=0.2, sample_hz=FS)
MACHINE = MachineModel(lead_s=0.5, tail_s=2.0, backlash_x_um=3.0, squareness_urad=20.0, noise_um=0.1)
CHECKED = ("backlash_x_um", "squareness_urad", "servo_mismatch_ms")


def stalled(t: np.ndarray, seed: int = 0, every_s: float = 3.0, max_s: float = 0.1) -> np.ndarray:
    """Stamps on receipt by a loaded host: 0.5 ms late on average, and every ``every_s`` a stall of 40 ms to
    ``max_s`` after which the samples taken meanwhile arrive together, 2 us apart."""
    rng = np.random.default_rng(seed)
    out = t + rng.exponential(0.5e-3, t.size)
    for s0 in np.arange(t[0] + 1.0, t[-1], every_s):
        dur = rng.uniform(0.04, max_s)
        idx = np.flatnonzero((t >= s0) & (t < s0 + dur))
        out[idx] = s0 + dur + 1e-4 + 2e-6 * np.arange(idx.size)
    return out


@pytest.fixture(scope="module")
def rec() -> tuple[np.ndarray, np.ndarray]:
    r = simulate(PLAN, MACHINE, FS, seed=0)
    return r.t_s, r.length_mm


@pytest.fixture(scope="module")
def clean(rec: tuple[np.ndarray, np.ndarray]) -> dict[str, Any]:
    return only_test(analyze_recording(*rec, PLAN))


def only_test(out: list[Any]) -> dict[str, Any]:
    rejected = [r["message"] for r in out if r.get("event") == "test_rejected"]
    assert not rejected, rejected
    tests = [r for r in out if r.get("kind") == "test"]
    assert len(tests) == 1
    return tests[0]


def rejection(out: list[Any]) -> str:
    assert not any(r.get("kind") == "test" for r in out)
    return str(next(r["message"] for r in out if r.get("event") == "test_rejected"))


def assert_within(res: dict[str, Any], ref: dict[str, Any], k: float = 2.0) -> None:
    """Each checked parameter within ``k`` of its stated standard errors of the reference analysis's value."""
    for name in CHECKED:
        a, b = res["parameters"][name], ref["parameters"][name]
        assert abs(a["value"] - b["value"]) <= k * a["stderr"], (name, a, b)


def cw_arc_time(clean: dict[str, Any], deg: float) -> float:
    """The time the CW data arc reaches ``deg`` (commanded), at the clean result's timing."""
    from ballbar.analysis.program import data_start_deg, schedule

    tm = clean["timing"]
    sched = schedule(PLAN, tm["measured_feed_mm_min"] / 60.0, tm["overhead_s"])
    u0 = data_start_deg(PLAN, -1)
    return float(tm["feed_in_s"] + sched.data_start_s[-1] + np.radians(u0 - deg) * PLAN.radius_mm
                 / sched.feed_mm_s)


# ----------------------------------------------------------------------------- a host that stalls


def test_a_stalled_hosts_bursts_go_back_on_the_grid() -> None:
    true = np.arange(60 * 250) * P
    t = stalled(true, max_s=0.1)
    assert np.diff(t).max() > GAP_PERIODS * P  # as stamped, every stall is a break
    out = retime(t)
    assert np.diff(out).max() < 3 * P
    late = out - true
    assert late.min() >= -0.5e-3  # no sample before its time, but for the period's estimate (as below)
    stalls = t - true > 0.03
    assert stalls.sum() > 100 and late[stalls].max() < 2 * P
    # chunk by chunk as a live stream comes: the very same times (each window's period is that of the samples
    # before it), so the daemon's result and ballbar analyze of its recording agree
    r = Retimer()
    parts = [r.feed(t[a : a + 37], np.zeros(t[a : a + 37].size))[0] for a in range(0, t.size, 37)]
    parts.append(r.flush()[0])
    chunked = np.concatenate(parts)
    assert np.array_equal(chunked, out)
    assert r.windows == r.caught_up == 20


def test_ordinary_stamps_and_a_loss_are_not_moved() -> None:
    rng = np.random.default_rng(3)
    true = np.arange(30 * 250) * P
    keep = (true < 10.0) | (true > 11.5)
    t = (true + rng.exponential(0.5e-3, true.size))[keep]
    out = retime(t)
    assert np.array_equal(out[true[keep] < 10.0], t[true[keep] < 10.0])  # nothing before the gap moves
    even = np.round(true[keep] * 1e9) / 1e9  # a device's clock, as recorded: nothing moves at all
    assert np.array_equal(retime(even), even)
    step = np.diff(out).max()
    assert step == pytest.approx(1.5, abs=0.01)  # the loss stays, whole periods long
    # on their own grid: no earlier than their time, but for the period's estimate (some 0.1 %, 6 us here) times
    # the 50 periods the envelope looks ahead
    after = true[keep] > 11.5
    assert np.all(out[after] >= true[keep][after] - 0.5e-3)


def test_a_recording_stamped_by_a_stalling_host_is_analysed(rec: tuple[np.ndarray, np.ndarray],
                                                            clean: dict[str, Any]) -> None:
    t, L = rec
    tb = stalled(t, seed=1)
    assert TimeAxis().check(tb)  # the stamps alone break the time axis every stall
    res = only_test(analyze_recording(tb, L, PLAN))
    assert_within(res, clean)
    assert abs(res["parameters"]["backlash_x_um"]["value"] - 3.0) < 3 * res["parameters"]["backlash_x_um"]["stderr"]
    assert res["fit"]["evaluations"] <= 40
    assert "dropouts" not in res
    # live, in chunks of a few samples: the same test passes
    an = TestAnalyzer(PLAN, circles=False)
    out: list[Any] = []
    for a in range(0, tb.size, 50):
        out += an.feed(tb[a : a + 50], L[a : a + 50])
    out += an.finish()
    assert_within(only_test(out), clean)


def test_ballbar_analyze_of_a_csv_with_bursty_stamps(rec: tuple[np.ndarray, np.ndarray], clean: dict[str, Any],
                                                     tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    t, L = rec
    p = tmp_path / "bursty.csv"
    np.savetxt(p, np.column_stack([stalled(t, seed=2), L]), delimiter=",", header="t_s,length_mm", comments="",
               fmt="%.9f")
    args = ["analyze", str(p), "--json", "--radius-mm", "100", "--feed-mm-min", "1500", "--overshoot-deg", "10",
            "--dwell-s", "0.2", "--sample-hz", "250"]
    code = main(args)
    out, err = capsys.readouterr()
    assert code == 0, err
    assert_within(json.loads(out), clean)


class StallingGauge(threading.Thread):
    """A Sylvac gauge streaming at 250 Hz into a pty, behind a host that stalls: every ``every_s`` the lines of
    ``stall_s`` are held back and written together.  ``sent``: each line's due time (monotonic), the truth."""

    def __init__(self, dev: FakeDevice, seconds: float, every_s: float = 1.0, stall_s: float = 0.06) -> None:
        super().__init__(daemon=True)
        self.dev, self.n, self.every, self.stall = dev, int(seconds * FS), every_s, stall_s
        self.t0 = 0.0
        self.held: list[int] = []

    def run(self) -> None:
        fmt = PROFILES["sylvac"].fmt
        self.t0 = time.monotonic() + 0.05
        pending: list[int] = []
        for k in range(self.n):
            due = self.t0 + k * P
            while (now := time.monotonic()) < due:
                time.sleep(min(due - now, 1e-3))
            pending.append(k)
            phase = (k * P) % self.every
            if k * P > 0.5 and self.every - self.stall <= phase:  # the host is stalled: held
                self.held.append(k)
                continue
            self.dev.write(ascii_proto.encode(np.array(pending) * 1e-4, fmt))
            pending = []
        if pending:
            self.dev.write(ascii_proto.encode(np.array(pending) * 1e-4, fmt))


@pytest.fixture
def dev(tmp_path: Path) -> Iterator[FakeDevice]:
    d = FakeDevice(tmp_path / "ttyUSB0")
    yield d
    d.unplug()


def test_a_streaming_gauge_behind_a_stalling_host_keeps_its_grid_live(dev: FakeDevice) -> None:
    gauge = StallingGauge(dev, seconds=6.0)
    with open_source(f"serial:{dev.link}?protocol=sylvac&mode=stream&rate=250&baud=115200", cal_mm=100.0) as src:
        src.read(0.05)
        gauge.start()
        batch, events = read_all(src, gauge.n, timeout=15.0)
        gauge.join(5.0)
    assert len(gauge.held) > 50  # the host held back 15 lines a second
    assert len(batch) == gauge.n and not [e for e in events if e.kind in (EventKind.LOST, EventKind.STALL)]
    assert np.allclose(batch.length_mm - 100.0, np.arange(gauge.n) * 1e-4, atol=1e-9)  # every line, in order
    th = batch.t_host
    assert np.diff(th).max() < GAP_PERIODS * P  # no break in the time axis the analysis sees
    late = th - (gauge.t0 + np.arange(gauge.n) * P)
    settled = late[int(2 * FS):]  # the clock map's first seconds aside
    assert settled.max() - np.median(settled) < 0.01  # the held lines are not 60 ms late
    assert TimeAxis().check(th) == []


# ----------------------------------------------------------------------------- a link that drops


def test_a_drop_out_inside_the_cw_arc_is_analysed_and_stated(rec: tuple[np.ndarray, np.ndarray],
                                                            clean: dict[str, Any]) -> None:
    t, L = rec
    a = cw_arc_time(clean, 225.0)  # 225 deg: midway between the reversals at 180 and 270
    keep = ~((t > a) & (t <= a + 1.5))
    res = only_test(analyze_recording(t[keep], L[keep], PLAN))
    assert_within(res, clean)
    (gap,) = res["dropouts"]
    assert gap["direction"] == "cw" and gap["duration_s"] == pytest.approx(1.5, abs=P)
    assert gap["samples_missing"] == 375
    assert gap["from_deg"] == pytest.approx(225.0, abs=0.5) and gap["to_deg"] == pytest.approx(203.6, abs=0.5)
    assert gap["arc_fraction"] == pytest.approx(21.4 / 360.0, abs=0.01)
    cost = {c["pattern"]: c["stderr_factor"] for c in gap["cost"]}
    assert all(v >= 1.0 for v in cost.values()) and max(cost.values()) > 1.005
    # the stated factor is what the standard errors did grow by, within a few per cent
    grown = res["parameters"]["squareness_urad"]["stderr"] / clean["parameters"]["squareness_urad"]["stderr"]
    assert grown == pytest.approx(cost["squareness"], rel=0.05)


def test_a_two_second_drop_out_live_in_chunks(rec: tuple[np.ndarray, np.ndarray], clean: dict[str, Any]) -> None:
    t, L = rec
    a = cw_arc_time(clean, 135.0)
    keep = ~((t > a) & (t <= a + 2.0))
    tk, Lk = stalled(t, seed=4)[keep], L[keep]  # on a stalling host too
    an = TestAnalyzer(PLAN)
    out: list[Any] = []
    for i in range(0, tk.size, 40):
        out += an.feed(tk[i : i + 40], Lk[i : i + 40])
    out += an.finish()
    res = only_test(out)
    assert_within(res, clean)
    assert [round(g["duration_s"], 1) for g in res["dropouts"]] == [2.0]


@pytest.mark.parametrize(("deg", "dur", "says"), [
    (185.0, 1.0, "the first axis' reversal at 180 deg of the cw data arc"),
    (None, 1.0, "takes the feed-out step"),
])
def test_a_drop_out_that_takes_what_the_result_needs_is_rejected(
    rec: tuple[np.ndarray, np.ndarray], clean: dict[str, Any], deg: float | None, dur: float, says: str,
) -> None:
    t, L = rec
    a = cw_arc_time(clean, deg) if deg is not None else clean["timing"]["feed_out_s"] - 0.5 * dur
    keep = ~((t > a) & (t <= a + dur))
    msg = rejection(analyze_recording(t[keep], L[keep], PLAN))
    assert says in msg and "run it again" in msg, msg


def test_a_drop_out_longer_than_two_seconds_is_still_a_break(rec: tuple[np.ndarray, np.ndarray],
                                                             clean: dict[str, Any]) -> None:
    t, L = rec
    a = cw_arc_time(clean, 225.0)
    keep = ~((t > a) & (t <= a + 2.5))
    msg = rejection(analyze_recording(t[keep], L[keep], PLAN))
    assert "clock jump or outage of 2.500 s" in msg and "spans a break" in msg, msg


# ----------------------------------------------------------------------------- a clock that jumps


def test_a_clock_jump_inside_an_arc_is_still_rejected(rec: tuple[np.ndarray, np.ndarray],
                                                      clean: dict[str, Any]) -> None:
    t, L = rec
    a = cw_arc_time(clean, 225.0)
    msg = rejection(analyze_recording(np.where(t > a, t + 1.5, t), L, PLAN))
    assert "clock jump or outage of 1.500 s" in msg and "the clock jumped, no samples were lost" in msg, msg


def test_a_device_clock_jump_the_source_reports_is_still_rejected(rec: tuple[np.ndarray, np.ndarray],
                                                                  clean: dict[str, Any]) -> None:
    t, L = rec
    a = cw_arc_time(clean, 225.0)
    j = int(np.searchsorted(t, a))
    # a device clock that stepped 0.2 s: the counter ran on, the daemon tells the break
    tj = np.where(np.arange(t.size) >= j, t + 0.2, t)
    msg = rejection(analyze_recording(tj, L, PLAN, breaks=[(j, "device clock jump of +0.200 s")]))
    assert "device clock jump of +0.200 s" in msg and "run it again" in msg, msg


# ----------------------------------------------------------------------------- through the daemon's analysis


def listen(t: np.ndarray, L: np.ndarray, seq: np.ndarray, event: SourceEvent) -> list[dict[str, Any]]:
    """The daemon's analysis of a device-clocked stream (batches of 100), ``event`` on the batch of its sample."""
    cfg = cfgmod.load(None, ["plan.radius_mm=100", "plan.feed_mm_min=1500", "plan.overshoot_deg=10",
                             "plan.dwell_s=0.2", "plan.sample_hz=250"], env={})
    got: list[dict[str, Any]] = []
    an = AnalysisListener(cfg, got.append)
    at = int(np.searchsorted(seq, event.seq))
    for i in range(0, t.size, 100):
        events = (event,) if i <= at < i + 100 else ()
        an.on_batch(SampleBatch(t[i : i + 100] + 1000.0, t[i : i + 100], L[i : i + 100], seq[i : i + 100],
                                np.zeros(min(100, t.size - i), np.uint8), events, "serial:x"))
    an.stop()
    return got


def test_a_loss_the_devices_counter_reports_is_a_drop_out_the_daemon_analyses(
    rec: tuple[np.ndarray, np.ndarray], clean: dict[str, Any],
) -> None:
    t, L = rec
    seq = np.arange(t.size)
    a = cw_arc_time(clean, 225.0)
    keep = ~((t > a) & (t <= a + 1.5))
    first = int(np.argmax(~keep))
    lost = SourceEvent(EventKind.LOST, 0.0, "serial:x", count=375, seq=first, detail="gap")
    got = listen(t[keep], L[keep], seq[keep], lost)
    res = only_test([m for m in got if m.get("kind") in ("test", "event")])
    assert_within(res, clean)
    assert [g["samples_missing"] for g in res["dropouts"]] == [375]


def test_a_device_clock_jump_the_daemon_is_told_of_is_still_rejected(
    rec: tuple[np.ndarray, np.ndarray], clean: dict[str, Any],
) -> None:
    t, L = rec
    seq = np.arange(t.size)
    j = int(np.searchsorted(t, cw_arc_time(clean, 225.0)))
    jump = SourceEvent(EventKind.CLOCK_JUMP, 0.0, "serial:x", seq=j, gap_s=1.5)
    got = listen(np.where(seq >= j, t + 1.5, t), L, seq, jump)
    msg = rejection([m for m in got if m.get("kind") in ("test", "event")])
    assert msg.startswith("device clock jump of +1.500 s") and "run it again" in msg, msg
