"""False findings on the independent simulator (issue 34, section 1): a fast arc with a large servo mismatch,
sampled at 15.625 Hz, must not show the lateral play it does not have."""

from __future__ import annotations

from typing import Any

import pytest

from ballbar.analysis import TestPlan
from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.program import centroid_span_s, feed_from_span, move_duration, short_move_duration
from ballbar.tools.bench import physim as ps
from ballbar.tools.bench.false_alarms import analyse, false_findings
from ballbar.tools.simulator import MachineModel

R, F = 100.0, 2000.0  # at 15.625 Hz a sample spans 2.1 mm, 1.2 deg


def _test_result(machine: ps.Machine, rate: float, seed: int) -> dict[str, Any]:
    path = ps.Path(radius_mm=R, feed_mm_min=F)
    t, L = ps.simulate(machine, path, ps.Gauge(sample_hz=rate, noise_um=0.1, phase=0.3), seed=seed)
    tests = [r for r in analyze_recording(t, L, TestPlan(sample_hz=rate, radius_mm=R, feed_mm_min=F))
             if r.get("kind") == "test"]
    assert len(tests) == 1
    return tests[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_servo_mismatch_at_a_low_rate_is_no_lateral_play(seed: int) -> None:
    # gains 43 and 28 1/s: a servo mismatch of 12.5 ms, 208 um on sin 2u at this feed.  The feed-in (1.5 mm,
    # 128 ms from rest to rest with the jerk limit's smoothing) spans two samples: how much of the arcs' schedule
    # it takes is not resolved, and one arc's shift against the other turns the servo pattern by 0.1 % of it
    machine = ps.Machine(x=ps.Axis(kv=43.0), y=ps.Axis(kv=28.0))
    result = _test_result(machine, 15.625, seed)
    params = result["parameters"]
    assert params["servo_mismatch_ms"]["value"] == pytest.approx(1e3 * (1 / 43 - 1 / 28), abs=0.05)
    for name in ("lateral_play_x_um", "lateral_play_y_um"):
        p = params[name]
        assert not p["significant"], (name, p["value"], p["stderr"], p["p_value"])
        assert abs(p["value"]) < 3 * p["stderr"], (name, p["value"], p["stderr"])
    assert result["fit"]["evaluations"] <= 40


@pytest.mark.parametrize("share", [0.0, 0.3, 0.6, 1.0])
def test_the_span_inverts_for_any_smoothing_share_of_a_short_feed_in(share: float) -> None:
    # F 2000 with 83 ms of overhead: the 1.5 mm feed-in (V c = 2.8 mm) may be short; the feed from the span
    # must be the one that made it, wherever the feed-in's duration lies between its two limits
    plan = TestPlan(sample_hz=1000.0, radius_mm=R, feed_mm_min=F)
    V, c = F / 60.0, 0.0833
    span = centroid_span_s(plan, V, c, None, share)
    assert feed_from_span(plan, span, c, None, share) == pytest.approx(V, rel=1e-9)
    # between the trapezoid's triangle and the average's s/V + c, which differ by (sqrt(s/V) - sqrt(c))^2
    f = plan.feed_in_mm
    tri = 2 * (f * c / V) ** 0.5
    assert short_move_duration(f, V, c, share) == pytest.approx(tri + share * ((f / V) ** 0.5 - c**0.5) ** 2)
    assert short_move_duration(f, V, c, 0.0) == pytest.approx(move_duration(f, V, c))


def test_a_short_jerk_limited_feed_in_is_no_lateral_play() -> None:
    # a dead band on each axis and 19 ms of servo mismatch at 1 kHz, F 1287 on R 92: the dead band's steps pin
    # each arc's timing, so the wait cannot take up a feed-in timed as a triangle that the jerk limit's average
    # (93 ms of the 104 ms overhead) makes 3.5 ms longer; the servo pattern, turned between the arcs, read as
    # -0.12 um of lateral play on each axis at ten of its standard errors
    machine = ps.Machine(x=ps.Axis(kv=42.6, play_um=14.9), y=ps.Axis(kv=23.3, play_um=8.2), accel_mm_s2=1855.0)
    path = ps.Path(radius_mm=91.9, feed_mm_min=1287.0)
    t, L = ps.simulate(machine, path, ps.Gauge(sample_hz=1000.0, noise_um=0.16, phase=0.2), seed=5)
    plan = TestPlan(sample_hz=1000.0, radius_mm=path.radius_mm, feed_mm_min=path.feed_mm_min)
    tests = [r for r in analyze_recording(t, L, plan) if r.get("kind") == "test"]
    params = tests[0]["parameters"]
    assert params["backlash_x_um"]["value"] == pytest.approx(14.9, abs=0.1)
    for name in ("lateral_play_x_um", "lateral_play_y_um"):
        p = params[name]
        assert not p["significant"], (name, p["value"], p["stderr"], p["p_value"])
        assert abs(p["value"]) < 3 * p["stderr"], (name, p["value"], p["stderr"])
    assert tests[0]["fit"]["evaluations"] <= 40


@pytest.mark.parametrize("seed", [0, 1])
def test_a_plain_trapezoids_short_feed_in_is_no_lateral_play(seed: int) -> None:
    # the project's simulator without a jerk limit: A 500 at F 2000, so the 1.5 mm feed-in (V c = 2.2 mm) is the
    # trapezoid's true triangle, the other limit of the feed-in's duration; 43/28 1/s and backlash of both signs
    machine = MachineModel(kv_x_per_s=43.0, kv_y_per_s=28.0, accel_mm_s2=500.0, backlash_x_um=6.0,
                           backlash_y_um=-3.0, noise_um=0.1)
    res, truth = analyse(machine, 1000.0, seed=seed, radius_mm=R, feed_mm_min=F)
    assert not false_findings(res, truth)
    for name in ("lateral_play_x_um", "lateral_play_y_um"):
        p = res["parameters"][name]
        assert abs(p["value"]) < 3 * p["stderr"], (name, p["value"], p["stderr"])
