"""Bad time axes: gaps, clock jumps, device resets and clocks that run back never give a confident answer.

Offline through :func:`analyze_recording`, chunk by chunk through
:class:`TestAnalyzer`, and through the daemon's :class:`AnalysisListener`
with the events a source reports.  The live path over a real pty is in
``tests/test_simdevice.py``; CSV and MCAP files in ``tests/test_cli_analyze.py``
and ``tests/test_records.py``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from ballbar.analysis import TestPlan
from ballbar.analysis.engine import TestAnalyzer, TimingHints, analyze_recording
from ballbar.analysis.errors import DataError
from ballbar.analysis.timeaxis import GAP_PERIODS, TimeAxis, TimeAxisError
from ballbar.daemon import config as cfgmod
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.daemon.service import AnalysisListener
from ballbar.tools.simulator import MachineModel, simulate

# A short test: R 50 mm at 3000 mm/min, 10 deg overshoots, about 14 s.
PLAN = TestPlan(radius_mm=50, feed_mm_min=3000, overshoot_deg=10, dwell_s=0.2, sample_hz=500)
MACHINE = MachineModel(lead_s=0.5, tail_s=0.5, backlash_x_um=3.0, squareness_urad=20.0, noise_um=0.1)


def stream(*machines: MachineModel, fs: float = 500.0, gap_s: float = 2.0, plan: TestPlan = PLAN,
           seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """Tests one after the other on one clock; also each test's start time."""
    ts, Ls, starts = [], [], []
    t0 = 0.0
    for i, m in enumerate(machines):
        r = simulate(plan, m, fs, seed=seed + i)
        starts.append(t0)
        ts.append(r.t_s + t0)
        Ls.append(r.length_mm)
        t0 += r.t_s[-1] + gap_s
    return np.concatenate(ts), np.concatenate(Ls), starts


def by_test(results: list[dict[str, Any]]) -> dict[int, dict[str, Any]]:
    """test_index -> {"result": test result or None, "rejected": message or None, "circles": n}."""
    out: dict[int, dict[str, Any]] = {}
    for r in results:
        i = r.get("test_index")
        if r.get("event") == "feed_in":
            out[i] = {"result": None, "rejected": None, "circles": 0, "feed_in_s": r["t_s"]}
        elif r.get("kind") == "test":
            out[i]["result"] = r
        elif r.get("kind") == "circle":
            out[i]["circles"] += 1
        elif r.get("event") == "test_rejected":
            out[i]["rejected"] = r["message"]
    return out


# ----------------------------------------------------------------------------- what must not break


@pytest.mark.parametrize("seed", range(3))
def test_random_drops_and_timestamp_jitter_at_500_hz_never_break_a_test(seed: int) -> None:
    m = MACHINE.with_(drop_fraction=0.02, jitter_s=0.5e-3, jitter_stamped=True)
    t, L, _ = stream(m, seed=seed)
    assert np.any(np.diff(t) < 0)  # stamped jitter reorders neighbours: within jitter, harmless
    tests = by_test(analyze_recording(t, L, PLAN))
    assert len(tests) == 1 and tests[1]["rejected"] is None and tests[1]["result"] is not None
    assert abs(tests[1]["result"]["timing"]["measured_feed_mm_min"] - 3000.0) < 3.0


def test_twenty_minutes_of_drops_and_jitter_show_no_break() -> None:
    rng = np.random.default_rng(1)
    n = 500 * 1200
    k = np.flatnonzero(rng.random(n) >= 0.02)
    t = k / 500.0 + rng.normal(0.0, 0.5e-3, k.size)
    axis = TimeAxis()
    breaks = [b for i in range(0, t.size, 400) for b in axis.check(t[i : i + 400])]
    assert breaks == [] and axis.period_s == pytest.approx(0.002, rel=0.05)


def test_the_lowest_rate_with_a_couple_of_drops() -> None:
    plan = TestPlan(sample_hz=15.625)
    r = simulate(plan, MachineModel(drop_indices=(1000, 1001), squareness_urad=20.0), 15.625)
    tests = by_test(analyze_recording(r.t_s, r.length_mm, plan))
    assert tests[1]["rejected"] is None and tests[1]["result"] is not None


def test_a_gap_between_tests_costs_nothing() -> None:
    t, L, starts = stream(MACHINE, MACHINE)
    t = np.where(t >= starts[1] - 1.0, t + 10.0, t)  # the clock jumps while the machine waits
    tests = by_test(analyze_recording(t, L, PLAN))
    assert [v["rejected"] for v in tests.values()] == [None, None]
    assert all(v["result"] is not None for v in tests.values())


# ----------------------------------------------------------------------------- what must


def test_a_forward_clock_jump_mid_test_rejects_it_and_the_next_test_passes() -> None:
    t, L, starts = stream(MACHINE, MACHINE)
    mid = starts[0] + 7.0
    t = np.where(t > mid, t + 10.0, t)
    tests = by_test(analyze_recording(t, L, PLAN))
    first, second = tests[1], tests[2]
    assert first["result"] is None and first["circles"] == 0
    assert "clock jump or outage of 10.000 s at t=7.000 s" in first["rejected"], first["rejected"]
    assert "after the feed-in" in first["rejected"] and "run it again" in first["rejected"]
    assert second["rejected"] is None
    assert abs(second["result"]["timing"]["measured_feed_mm_min"] - 3000.0) < 1.0


def test_a_gap_of_lost_samples_inside_the_feed_in_step_rejects_the_test() -> None:
    r = simulate(PLAN, MACHINE, 500.0)
    fi = by_test(analyze_recording(r.t_s, r.length_mm, PLAN))[1]["feed_in_s"]
    keep = np.abs(r.t_s - fi) > 0.01  # 10 ms around the feed-in's centroid: 9 samples lost
    tests = by_test(analyze_recording(r.t_s[keep], r.length_mm[keep], PLAN))
    assert tests[1]["result"] is None and "during the feed-in" in tests[1]["rejected"]


def test_time_that_runs_back_is_an_error_naming_the_sample() -> None:
    r = simulate(PLAN, MACHINE, 500.0)
    t = r.t_s.copy()
    t[3000:] -= 50.0
    with pytest.raises(TimeAxisError, match=r"sample 3000: the time runs backwards by 49.998 s") as info:
        analyze_recording(t, r.length_mm, PLAN)
    assert info.value.index == 3000 and "\n" not in str(info.value)
    # live, the offending chunk is refused whole: nothing of it was taken
    an = TestAnalyzer(PLAN)
    an.feed(t[:2990], r.length_mm[:2990])
    with pytest.raises(TimeAxisError, match="sample 3000"):
        an.feed(t[2990:3010], r.length_mm[2990:3010])
    assert an.axis.n == 2990


@pytest.mark.parametrize("t", [np.zeros(500), np.linspace(10.0, 0.0, 500)])
def test_a_time_column_that_never_advances_is_one_clear_error(t: np.ndarray) -> None:
    L = np.full(t.size, 101.5)
    L[200:] = 100.0
    with pytest.raises(DataError, match="time"):
        analyze_recording(t, L, PLAN)


def test_a_reported_break_rejects_the_test_and_hints_come_only_from_tests_that_passed() -> None:
    # Test 2 runs 5 % fast: had it taught the hints, test 3's provisional circles would assume 3150 mm/min.
    t, L, starts = stream(MACHINE, MACHINE.with_(feed_override=1.05), MACHINE)
    an = TestAnalyzer(PLAN)
    out: list[dict[str, Any]] = []
    reset_at = int(np.searchsorted(t, starts[1] + 8.0))
    for i in range(0, t.size, 97):  # the daemon's chunks
        j = min(i + 97, t.size)
        if i <= reset_at < j:
            out += an.feed(t[i:reset_at], L[i:reset_at])
            an.mark_break("device reset")
            out += an.feed(t[reset_at:j], L[reset_at:j])
        else:
            out += an.feed(t[i:j], L[i:j])
        if any(r.get("event") == "feed_out" and r["test_index"] == 2 for r in out):
            hints_after_2 = an.hints
    out += an.finish()
    tests = by_test(out)
    assert tests[2]["result"] is None
    assert tests[2]["rejected"].startswith(f"device reset at t={t[reset_at]:.3f} s, ")
    assert [r["event"] for r in out if r.get("test_index") == 2 and r["kind"] == "event"] == [
        "feed_in", "test_rejected", "feed_out"]
    learnt = TimingHints.learnt(tests[1]["result"]["timing"])
    assert hints_after_2 == learnt
    assert abs(learnt.feed_ratio - 1.0) < 1e-3
    circles3 = [r for r in out if r["kind"] == "circle" and r["test_index"] == 3]
    assert circles3 and all(abs(c["timing"]["assumed_feed_mm_min"] - 3000.0) < 3.0 for c in circles3)
    assert tests[3]["result"] is not None and tests[1]["result"] is not None


def test_implausible_timing_never_becomes_a_hint() -> None:
    ok = TimingHints.learnt({"feed_ratio": 0.95, "overhead_s": 0.01, "spike_width_deg": None})
    assert ok == TimingHints(0.95, 0.01, TimingHints().spike_width_deg)
    for ratio in (1.2, 0.6, math.nan):
        assert TimingHints.learnt({"feed_ratio": ratio, "overhead_s": 0.0, "spike_width_deg": 2.0}) is None
    assert TimingHints.learnt({"overhead_s": 0.0}) is None


def test_gap_threshold_is_relative_to_the_median_period() -> None:
    for fs in (15.625, 500.0, 10_000.0):
        t = np.arange(200) / fs
        t[100:] += (GAP_PERIODS - 1.5) / fs  # GAP_PERIODS - 0.5 periods: no break
        t[150:] += GAP_PERIODS / fs  # GAP_PERIODS + 1 periods: a break
        breaks = TimeAxis().check(t)
        assert [b.index for b in breaks] == [150], fs
        assert breaks[0].missing_s == pytest.approx(GAP_PERIODS / fs)


# ----------------------------------------------------------------------------- the daemon's listener


def _listener() -> tuple[AnalysisListener, list[dict[str, Any]]]:
    cfg = cfgmod.load(None, ["plan.radius_mm=50", "plan.feed_mm_min=3000", "plan.overshoot_deg=10",
                             "plan.dwell_s=0.2", "plan.sample_hz=500"], env={})
    got: list[dict[str, Any]] = []
    return AnalysisListener(cfg, got.append), got


def _batches(t: np.ndarray, L: np.ndarray, seq: np.ndarray, n: int = 100) -> list[SampleBatch]:
    return [SampleBatch.from_columns(t[i : i + n] + 1000.0, t[i : i + n], L[i : i + n], seq[i : i + n],
                                     np.zeros(min(n, t.size - i))) for i in range(0, t.size, n)]


def test_the_listener_places_a_device_reset_on_its_sample_and_rejects_the_test() -> None:
    t, L, starts = stream(MACHINE, MACHINE.with_(tail_s=2.0))  # the stream ends once the feed-out has settled
    seq = np.arange(t.size)
    at = int(np.searchsorted(t, starts[0] + 6.0)) + 37  # inside a batch, not at its start
    batches = _batches(t, L, seq)
    k = at // 100
    reset = SourceEvent(EventKind.DEVICE_RESET, 0.0, "serial:x", seq=int(seq[at]), detail="went backwards")
    b = batches[k]
    batches[k] = SampleBatch(b.t_host, b.t_device, b.length_mm, b.seq, b.status, (reset,), b.source)
    an, got = _listener()
    for b in batches:
        an.on_batch(b)
    an.stop()
    rejected = [m for m in got if m.get("event") == "test_rejected"]
    assert len(rejected) == 1 and rejected[0]["message"].startswith(f"device reset (its sample counter or clock "
                                                                    f"restarted; how long it was down is unknown) "
                                                                    f"at t={t[at]:.3f} s")
    assert rejected[0]["test_id"] == next(m["test_id"] for m in got if m.get("event") == "feed_in")
    assert [m["kind"] for m in got if m["kind"] == "test"] == ["test"]  # the second test passed


def test_the_listener_gives_freed_memory_back_after_each_test_it_ends(monkeypatch: pytest.MonkeyPatch) -> None:
    from ballbar.daemon import analysis_worker, service

    t, L, starts = stream(MACHINE, MACHINE.with_(tail_s=2.0))
    back = int(np.searchsorted(t, starts[0] + 6.0)) + 37
    t2 = t.copy()
    t2[back:] -= 100.0  # the first test is rejected, the second gets its result
    an, got = _listener()
    seen: list[list[str]] = []  # what had been emitted at each release
    monkeypatch.setattr(service, "release_freed_memory",
                        lambda: seen.append([str(m.get("event") or m["kind"]) for m in got]))
    for b in _batches(t2, L, np.arange(t.size)):
        an.on_batch(b)
    an.stop()
    assert len(seen) == 2  # once per test ended, after its messages went out, never per batch
    assert seen[0][-2:] == ["test_rejected", "analysis_reset"] and seen[1][-1] == "test"
    assert analysis_worker._malloc_trim() is not None  # glibc here


def test_the_listener_rejects_the_test_in_progress_when_the_clock_runs_back() -> None:
    t, L, starts = stream(MACHINE, MACHINE.with_(tail_s=2.0))
    back = int(np.searchsorted(t, starts[0] + 6.0)) + 37
    t2 = t.copy()
    t2[back:] -= 100.0  # a clock that restarted, not re-based
    an, got = _listener()
    for b in _batches(t2, L, np.arange(t.size)):
        an.on_batch(b)
    an.stop()
    events = [m["event"] for m in got if m["kind"] == "event"]
    assert events[:3] == ["feed_in", "test_rejected", "analysis_reset"], events
    rejected = next(m for m in got if m.get("event") == "test_rejected")
    assert "the time runs backwards by 99.998 s" in rejected["message"]
    # the new analysis takes the stream on from the offending sample and finds the second test
    assert [m["kind"] for m in got if m["kind"] == "test"] == ["test"]
    assert an.errors == 1


def test_the_listener_takes_batches_merged_until_a_result_nears_and_is_as_quick() -> None:
    """Merged every MERGE_S between tests and mid-circle, each batch as a circle's end or the feed-out nears:
    the same results at the same samples as with every 20 ms batch, from a fraction of the deliveries."""
    from ballbar.daemon.service import MERGE_S

    t, L, _ = stream(MACHINE, MACHINE.with_(tail_s=2.0))
    seq = np.arange(t.size)
    each, got_each = _listener()
    for b in _batches(t, L, seq, n=10):  # 20 ms at 500 Hz
        each.on_batch(b)
    merged, got = _listener()
    periods, pend, deliveries = [], [], 0
    for b in _batches(t, L, seq, n=10):
        pend.append(b)
        period = merged.batch_period_now()
        periods.append(period)
        if period == 0 or b.t_host[-1] - pend[0].t_host[0] >= period:  # as the queue does
            merged.on_batch(SampleBatch.concat(pend) if len(pend) > 1 else pend[0])
            deliveries += 1
            pend = []
    assert set(periods) == {0.0, MERGE_S}
    assert deliveries < 0.5 * len(periods), (deliveries, len(periods))
    results = [m for m in got if m["kind"] in ("circle", "test")]
    results_each = [m for m in got_each if m["kind"] in ("circle", "test")]
    assert [m["kind"] for m in results] == ["circle", "circle", "test", "circle", "circle", "test"]
    for a, b in zip(results_each, results, strict=True):  # emitted with the same last sample
        assert a["last_sample_t"] == b["last_sample_t"], (a["kind"], a.get("direction"))
