"""The engine inverts its own model exactly; live (chunked) equals offline."""

from __future__ import annotations

import math

import numpy as np
import pytest
from masksynth import FULL_TRUTH, mask_recording

from ballbar.analysis import AnalysisOptions, TestPlan, engine
from ballbar.analysis.engine import FOLD_SAMPLES, TestAnalyzer, analyze_recording
from ballbar.analysis.errors import DetectionError

# The recordings here follow the masks exactly: no dead band, no servo dynamics.
MASKS = AnalysisOptions(servo_model="linear", lost_motion="step")


def _test_result(results: list[dict]) -> dict:
    tests = [r for r in results if r["kind"] == "test"]
    assert len(tests) == 1, [r.get("event") for r in results]
    return tests[0]


@pytest.mark.parametrize("fs", [15.625, 100.0, 1000.0])
def test_whole_library_noise_free_is_exact(fs: float) -> None:
    plan = TestPlan(sample_hz=fs)
    t, L = mask_recording(plan, FULL_TRUTH, fs=fs)
    res = _test_result(analyze_recording(t, L, plan, options=MASKS))
    for key, p in res["parameters"].items():
        if p["value"] is None:
            assert "cyclic" in key
            continue
        tol = 0.02 if not key.startswith("reversal_spike") else 0.05
        assert abs(p["value"] - FULL_TRUTH.get(key, 0.0)) < tol, (key, p["value"])
    assert abs(res["timing"]["measured_feed_mm_min"] - 1000.0) < 0.5
    assert abs(res["timing"]["spike_width_deg"] - 4.0) < 0.2


def test_cyclic_error_with_a_configured_pitch() -> None:
    from ballbar.analysis import MachineConfig

    plan = TestPlan(sample_hz=1000)
    phi = math.radians(40.0)
    truth = {"cyclic_x_sin_um": 0.8 * math.cos(phi), "cyclic_x_sin_um_": 0, "centre_x_um": 5.0}
    truth["cyclic_x_cos_um"] = 0.8 * math.sin(phi)
    t, L = mask_recording(plan, truth, fs=1000.0, pitch=(5.0, None))
    res = _test_result(analyze_recording(t, L, plan, MachineConfig(pitch_x_mm=5.0), MASKS))
    assert abs(res["parameters"]["cyclic_x_um"]["value"] - 0.8) < 0.01
    assert abs(res["parameters"]["cyclic_x_phase_deg"]["value"] - 40.0) < 1.0
    assert res["parameters"]["cyclic_y_um"]["identifiable"] is False


def test_noise_within_three_standard_errors() -> None:
    plan = TestPlan(sample_hz=100)
    t, L = mask_recording(plan, FULL_TRUTH, fs=100.0, noise_um=0.5, seed=3)
    res = _test_result(analyze_recording(t, L, plan, options=MASKS))
    for key, want in FULL_TRUTH.items():
        p = res["parameters"][key]
        assert abs(p["value"] - want) <= 3 * p["stderr"], (key, p)


def test_lag_is_estimated_not_assumed_zero() -> None:
    plan = TestPlan(sample_hz=1000)
    truth = dict(FULL_TRUTH)
    t, L = mask_recording(plan, truth, fs=1000.0, overhead_s=0.03)
    res = _test_result(analyze_recording(t, L, plan, options=MASKS))
    assert abs(res["timing"]["overhead_s"] - 0.03) < 0.003
    assert abs(res["parameters"]["centre_x_um"]["value"] - 12.0) < 0.02


def test_streamed_in_chunks_equals_whole_file() -> None:
    plan = TestPlan(sample_hz=100)
    t, L = mask_recording(plan, FULL_TRUTH, fs=100.0, noise_um=0.2)
    whole = _test_result(analyze_recording(t, L, plan, options=MASKS))
    an = TestAnalyzer(plan, options=MASKS)
    out: list[dict] = []
    rng = np.random.default_rng(0)
    i = 0
    while i < t.size:
        n = int(rng.integers(1, 700))
        out.extend(an.feed(t[i : i + n], L[i : i + n]))
        i += n
    out.extend(an.finish())
    kinds = [(r["kind"], r.get("event"), r.get("direction")) for r in out]
    assert kinds == [
        ("event", "feed_in", None),
        ("circle", None, "ccw"),
        ("circle", None, "cw"),
        ("event", "feed_out", None),
        ("test", None, None),
    ]
    live = _test_result(out)
    for key, p in whole["parameters"].items():
        assert p["value"] == live["parameters"][key]["value"], key
    circle = out[1]
    assert circle["timing"]["provisional"] is True
    # one direction, provisional timing and spike width: close, not exact
    assert abs(circle["parameters"]["backlash_x_um"]["value"] - 4.0) < 0.4


def test_a_live_stream_folds_in_blocks_and_its_circles_do_not_depend_on_the_chunks(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Samples arriving a few at a time (a 20 ms batch) are folded into the circles in blocks, not per chunk:
    the circle results are those of large chunks, to rounding."""
    plan = TestPlan(sample_hz=1000)
    t, L = mask_recording(plan, FULL_TRUTH, fs=1000.0, noise_um=0.2)
    folds: list[int] = []
    real_add = engine.CircleFit.add

    def add(self: engine.CircleFit, tt: np.ndarray, LL: np.ndarray) -> None:
        folds.append(tt.size)
        real_add(self, tt, LL)

    monkeypatch.setattr(engine.CircleFit, "add", add)

    def circles(sizes: np.random.Generator | int) -> list[dict]:
        an = TestAnalyzer(plan, options=MASKS)
        out: list[dict] = []
        i = 0
        while i < t.size:
            n = sizes if isinstance(sizes, int) else int(sizes.integers(1, 30))
            out.extend(r for r in an.feed(t[i : i + n], L[i : i + n]) if r["kind"] == "circle")
            i += n
        return out

    def no_test(*_a: object, **_k: object) -> dict:
        raise engine.DataError("the circles only")

    monkeypatch.setattr(engine, "analyze_test", no_test)
    small = circles(np.random.default_rng(1))
    small_folds = folds[:]
    folds.clear()
    large = circles(5000)
    assert [c["direction"] for c in small] == [c["direction"] for c in large] == ["ccw", "cw"]
    # per circle, all but the fold that completes it hold at least FOLD_SAMPLES new samples
    assert len(small_folds) < t.size / FOLD_SAMPLES * 2 + 10, len(small_folds)
    assert sum(n >= FOLD_SAMPLES for n in small_folds) >= len(small_folds) - 6
    for a, b in zip(small, large, strict=True):
        for key, p in a["parameters"].items():
            v, w = p["value"], b["parameters"][key]["value"]
            assert (v is None and w is None) or abs(v - w) <= 1e-9 * max(1.0, abs(w)), key


def test_single_direction_cannot_separate_squareness_from_servo() -> None:
    plan = TestPlan(sample_hz=100, directions="ccw")
    t, L = mask_recording(plan, {"servo_mismatch_ms": 1.0, "squareness_urad": 30.0}, fs=100.0)
    res = _test_result(analyze_recording(t, L, plan, options=MASKS))
    sq = res["parameters"]["squareness_urad"]
    assert sq["identifiable"] is False and "servo_mismatch" in sq["reason"]
    assert res["parameters"]["reversal_spike_x_pos_cw_um"]["identifiable"] is False


def test_partial_arc_reports_what_it_cannot_see() -> None:
    plan = TestPlan(sample_hz=100, data_arc_deg=220, start_deg=-20, overshoot_deg=10, plane="ZX")
    truth = {"centre_x_um": 5.0, "backlash_x_um": 3.0, "servo_mismatch_ms": 0.5, "squareness_urad": 15.0}
    t, L = mask_recording(plan, truth, fs=100.0, noise_um=0.05)
    res = _test_result(analyze_recording(t, L, plan, options=MASKS))
    params = res["parameters"]
    # the arc -10..210 deg never reaches 270 deg: no Y reversal spike there
    assert params["reversal_spike_y_neg_ccw_um"]["identifiable"] is False
    assert "270" in params["reversal_spike_y_neg_ccw_um"]["reason"]
    for key, want in truth.items():
        p = params[key]
        if p["identifiable"]:
            assert abs(p["value"] - want) <= 3 * p["stderr"] + 0.02, (key, p)
    assert sum(not p["identifiable"] for p in params.values()) >= 3


def test_no_feed_in_is_a_clear_error() -> None:
    plan = TestPlan()
    t = np.arange(0, 10, 0.01)
    with pytest.raises(DetectionError, match="no feed-in found"):
        analyze_recording(t, np.full(t.size, 150.0), plan)


def test_feed_override_is_measured() -> None:
    plan = TestPlan(sample_hz=100)
    run = TestPlan(sample_hz=100, feed_mm_min=950.0)
    t, L = mask_recording(run, FULL_TRUTH, fs=100.0)
    res = _test_result(analyze_recording(t, L, plan, options=MASKS))
    assert abs(res["timing"]["measured_feed_mm_min"] - 950.0) < 0.5
    assert abs(res["timing"]["feed_ratio"] - 0.95) < 1e-3
    assert abs(res["parameters"]["backlash_x_um"]["value"] - 4.0) < 0.05


def test_options_restrict_the_library() -> None:
    plan = TestPlan(sample_hz=100)
    t, L = mask_recording(plan, {"backlash_x_um": 2.0, "centre_x_um": 3.0}, fs=100.0)
    opts = AnalysisOptions(patterns=("centre", "radius", "backlash_x"), servo_model="linear", lost_motion="step")
    res = _test_result(analyze_recording(t, L, plan, options=opts))
    assert abs(res["parameters"]["backlash_x_um"]["value"] - 2.0) < 1e-3
    assert res["parameters"]["squareness_urad"]["value"] is None


def test_a_line_is_placed_right_on_an_arc_whose_length_has_a_large_prime_factor() -> None:
    """The noise findings take each arc up to a fast FFT length and shorten the arc with it: a line stays at its
    cycles per revolution and its Hz (without the shortened arc it would read 0.2 % low: 1.8 of 1000 cpr)."""
    from ballbar.analysis import noise

    n, fs, arc = 376_991, 10_000.0, 360.0  # a 10 kHz circle: 376 991 = 11 x 34 271, no fast FFT
    rng = np.random.default_rng(3)
    k = np.arange(n)
    u = np.radians(arc) * k / n
    r = 0.5 * np.sin(2.0 * np.pi * 1000.0 * k / n) + rng.normal(0.0, 0.1, n)  # 1000 cycles/rev
    found = noise.findings([(u, r, arc, fs)], 30.0)
    assert abs(found["vibration_peak_cpr"] - 1000.0) < 0.5, found["vibration_peak_cpr"]
    assert abs(found["vibration_peak_hz"] - 1000.0 * fs / n) < 0.5 * fs / n, found["vibration_peak_hz"]
    assert found["vibration_significant"] and abs(found["vibration_peak_um"] - 0.5 / math.sqrt(2)) < 0.02


def test_the_final_fit_brings_its_corrections_to_their_fixed_point_and_stops_once_they_settle(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The physical corrections are made at the fit's own values (the servo mismatch, the centre, the backlash),
    which they change: the final fit steps until they move by less than OFFSET_SETTLED_UM, and the result is
    the one that stepping on to the limit gives."""
    from ballbar.analysis import fitresult, testfit
    from ballbar.tools.simulator import MachineModel, simulate

    plan = TestPlan(sample_hz=250.0)
    sim = simulate(plan, MachineModel(kv_y_per_s=36.0, backlash_x_um=3.0, centre_x_um=15.0, noise_um=0.1), 250.0)
    factors: list[int] = []
    real = testfit.Objective.factor

    def counted(self: testfit.Objective, *args: object) -> object:
        factors.append(1)
        return real(self, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(testfit.Objective, "factor", counted)

    def run() -> tuple[dict, int]:
        factors.clear()
        res = [r for r in analyze_recording(sim.t_s, sim.length_mm, plan) if r.get("kind") == "test"][-1]
        return res, len(factors)

    settled, steps = run()
    assert abs(settled["parameters"]["servo_mismatch_ms"]["value"]) > 0.1  # a correction to settle
    monkeypatch.setattr(fitresult, "OFFSET_SETTLED_UM", 0.0)  # step while anything moves, up to the limit
    to_the_end, more = run()
    assert more > steps, (steps, more)
    for name, p in to_the_end["parameters"].items():
        q = settled["parameters"][name]
        if p["value"] is None:
            assert q["value"] is None
            continue
        assert abs(q["value"] - p["value"]) <= 1e-3 * p["stderr"], (name, q["value"], p["value"])
        assert q["significant"] == p["significant"]


@pytest.mark.parametrize("fs", [15.625, 250.0, 1000.0, 10_000.0])
def test_a_test_costs_at_most_forty_misfit_evaluations(fs: float) -> None:
    """The fit's nonlinear parameters are found by Gauss-Newton on a smooth objective: a test's analysis
    evaluates the misfit at most 40 times, and makes at most 50 designs with their slopes, on a machine with
    every pattern."""
    from ballbar.analysis import MachineConfig
    from ballbar.tools.simulator import MachineModel, simulate

    plan = TestPlan(sample_hz=fs)
    machine = MachineModel(
        centre_x_um=12.0, backlash_x_um=4.0, backlash_y_um=2.0, kv_y_per_s=32.0, master_slave_a_um=1.0,
        squareness_urad=15.0, scale_x_ppm=5.0, lateral_play_x_um=1.0, straightness_y_um=0.8, spike_x_um=2.0,
        cyclic_x_um=0.3, pitch_x_mm=10.0, drift_um_per_min=0.2, noise_um=0.2,
    )
    sim = simulate(plan, machine, fs)
    res = _test_result(analyze_recording(sim.t_s, sim.length_mm, plan, MachineConfig(pitch_x_mm=10.0), circles=False))
    assert res["fit"]["evaluations"] <= 40, res["fit"]["evaluations"]
    assert res["fit"]["designs"] <= 50, res["fit"]["designs"]


def test_an_analysis_without_provisional_circles_gives_the_same_tests() -> None:
    """``circles=False`` (``ballbar analyze``, which reads only the tests) leaves the circles out and nothing
    else."""
    plan = TestPlan(sample_hz=250.0)
    t, L = mask_recording(plan, FULL_TRUTH, fs=250.0)
    live = analyze_recording(t, L, plan, options=MASKS)
    offline = analyze_recording(t, L, plan, options=MASKS, circles=False)
    assert any(r["kind"] == "circle" for r in live)
    assert [r for r in live if r["kind"] != "circle"] == offline


def test_a_fit_that_fails_unexpectedly_costs_its_test_only(monkeypatch: pytest.MonkeyPatch) -> None:
    """A bug in a test's fit (anything but a DataError) rejects that test with the reason, and the next test is
    analysed as usual: the live daemon keeps running (it once exited on a ValueError from the fit)."""
    plan = TestPlan(sample_hz=100)
    t1, L1 = mask_recording(plan, FULL_TRUTH, fs=100.0, noise_um=0.2)
    t = np.concatenate([t1, t1 + t1[-1] + 5.0])
    L = np.concatenate([L1, L1])
    real, calls = engine.analyze_test, []

    def first_fails(*args: object, **kw: object) -> dict:
        calls.append(1)
        if len(calls) == 1:
            raise ValueError("4 is not in list")
        return real(*args, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(engine, "analyze_test", first_fails)
    out = analyze_recording(t, L, plan, options=MASKS)
    rejected = [r for r in out if r.get("event") == "test_rejected"]
    tests = [r for r in out if r["kind"] == "test"]
    assert len(rejected) == 1 and "ValueError: 4 is not in list" in rejected[0]["message"], rejected
    assert len(tests) == 1 and tests[0]["test_index"] == 2


def test_the_last_stage_may_search_a_coordinate_the_earlier_did_not() -> None:
    """The polish can add the loops' feed-forward (once an over-set compensation shows) to what the earlier stage
    searched: the merged curvature keeps the polish's block, the held coordinates' own block, the cross terms
    both stages share, and none for the new one (it crashed with "4 is not in list" on a 500 Hz YZ test)."""
    from ballbar.analysis.search import Found
    from ballbar.analysis.testfit import _merge

    def found(active: list[int], h: np.ndarray) -> Found:
        return Found(None, h, 0.1 * h, np.ones((3, len(active))) * np.arange(len(active)), active, 1.0, 1)  # type: ignore[arg-type]

    earlier = found([0, 1, 2], np.array([[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]]))
    polished = found([0, 4], np.array([[5.0, 0.3], [0.3, 1.5]]))
    m = _merge(polished, earlier, keep=[2])
    assert m.active == [0, 4, 2]
    assert np.allclose(m.jtj, [[5.0, 0.3, 0.5], [0.3, 1.5, 0.0], [0.5, 0.0, 2.0]])
    assert np.allclose(m.hprior, 0.1 * m.jtj)
    assert np.allclose(m.dx[:, :2], polished.dx) and np.allclose(m.dx[:, 2], earlier.dx[:, 2])
