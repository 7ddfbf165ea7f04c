"""Plans as a library, and each test's plan recognised from the recording alone (analysis/plans.py).

Every recording here comes from the physical simulator running the plan's program as ``ballbar gcode`` writes
it (its signature before the feed-in) or without the signature (a program from elsewhere), on the 3D machine's
projection into the plan's plane, and is read as the bar assembled for the plan reads it.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from ballbar.analysis.engine import TestAnalyzer, analyze_recording
from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.plans import (
    SIGNATURE_CODES,
    NamedPlan,
    PlanLibrary,
    at_feed_out,
    default_signature,
    plan_of_result,
    read_signature,
    signature_code,
    signature_symbols,
)
from ballbar.tools.machine3d import Machine3D, program_of, set_tests
from ballbar.tools.simulator import simulate


def vertical(plane: str, **kw: float) -> TestPlan:
    start = {"ZX": -115.0, "YZ": -25.0}[plane]
    return TestPlan(plane=plane, start_deg=start, overshoot_deg=5.0, data_arc_deg=220.0, **kw)  # type: ignore[arg-type]


LIB = PlanLibrary.from_plans({
    "xy": TestPlan(), "xy_fast": TestPlan(feed_mm_min=2000.0), "xy_r150": TestPlan(radius_mm=150.0),
    "zx": vertical("ZX"), "yz": vertical("YZ"),
})
MACHINE = Machine3D.from_settings(dict(
    backlash_x_um=4, backlash_y_um=2.5, backlash_z_um=3, kv_x_per_s=30, kv_y_per_s=33, kv_z_per_s=28,
    squareness_xy_urad=15, squareness_yz_urad=-10, squareness_zx_urad=20, centre_x_um=8, centre_z_um=-5,
    noise_um=0.1))


def record(name: str, fs: float, *, signed: bool = True, override: float = 1.0, seed: int = 0,
           library: PlanLibrary = LIB, **machine: float) -> tuple[np.ndarray, np.ndarray]:
    """One test of plan ``name`` as the bar reads it (at the first plan's length)."""
    p = library.get(name) if name in library.names else next(f for f in FOREIGN if f.name == name)
    m = MACHINE.with_(feed_override=override, **machine)
    sim = simulate(p.plan.with_(sample_hz=fs), m.project(p.plan.plane), fs, seed=seed,
                   program=program_of(p if signed else NamedPlan(p.name, p.plan, None)))
    return sim.t_s, sim.length_mm - (p.plan.radius_mm - library.first.plan.radius_mm)


def outcome(t: np.ndarray, L: np.ndarray, library: PlanLibrary = LIB, **kw: object) -> list[dict]:
    return [r for r in analyze_recording(t, L, library.detection_plan(), library=library, circles=False, **kw)
            if r["kind"] == "test" or r.get("event") == "test_unrecognised"]


FOREIGN = (NamedPlan("stranger", TestPlan(), next(c for c in range(125) if LIB.by_signature(c) is None)),
           NamedPlan("short", TestPlan(directions="ccw", data_arc_deg=45.0, overshoot_deg=10.0)))


# --------------------------------------------------------------------------- the code


def test_every_code_round_trips_and_no_single_misreading_is_another_code() -> None:
    for code in range(SIGNATURE_CODES):
        symbols = signature_symbols(code)
        assert signature_code(symbols) == code
        for k, s in itertools.product(range(4), range(1, 6)):  # one depth misread
            if s != symbols[k]:
                assert signature_code([*symbols[:k], s, *symbols[k + 1:]]) is None
        for k in range(3):  # two neighbours swapped
            if symbols[k] != symbols[k + 1]:
                swapped = list(symbols)
                swapped[k], swapped[k + 1] = swapped[k + 1], swapped[k]
                assert signature_code(swapped) is None
    assert signature_code([1, 2, 3]) is None and signature_code([0, 1, 1, 1]) is None
    with pytest.raises(PlanError, match=r"0\.\.124"):
        signature_symbols(125)


def test_the_library_refuses_what_recognition_cannot_take() -> None:
    with pytest.raises(PlanError, match="twice"):
        PlanLibrary((NamedPlan("a", TestPlan(), 1), NamedPlan("a", TestPlan(), 2)))
    with pytest.raises(PlanError, match="same signature 7"):
        PlanLibrary((NamedPlan("a", TestPlan(), 7), NamedPlan("b", vertical("ZX"), 7)))
    with pytest.raises(PlanError, match="feed-in of the first"):
        PlanLibrary((NamedPlan("a", TestPlan(), 1), NamedPlan("b", TestPlan(feed_in_mm=2.0), 2)))
    with pytest.raises(PlanError, match="has a signature"):
        PlanLibrary((NamedPlan("a", TestPlan(), 1), NamedPlan("b", vertical("ZX"))))
    with pytest.raises(PlanError, match="letters"):
        PlanLibrary((NamedPlan("a b", TestPlan()),))
    assert default_signature("zx") == default_signature("zx") != default_signature("yz")
    assert plan_of_result({**TestPlan().to_dict(), "name": "xy", "axes": ["X", "Y"]}) == TestPlan()


# --------------------------------------------------------------------------- the signature read


@pytest.mark.parametrize("override", [0.8, 1.2])
@pytest.mark.parametrize("name", ["zx", "yz", "xy_fast"])
def test_the_signature_survives_15_625_hz_override_drops_and_jitter(name: str, override: float) -> None:
    t, L = record(name, 15.625, override=override, drop_fraction=0.03, jitter_s=0.002, seed=3)
    (res,) = outcome(t, L)
    assert res["kind"] == "test", res
    assert res["plan"]["name"] == name and res["recognition"]["method"] == "signature"
    assert res["recognition"]["signature"] == LIB.get(name).signature
    assert abs(res["recognition"]["feed_ratio"] - override) < 0.02
    assert res["plan"]["axes"] == list({"ZX": ("Z", "X"), "YZ": ("Y", "Z"), "XY": ("X", "Y")}[res["plan"]["plane"]])


def test_a_signature_with_an_excursion_lost_is_not_read_and_the_timing_decides() -> None:
    t, L = record("zx", 15.625)
    p = LIB.get("zx").plan
    # the samples of the second excursion's dwell lost (a burst), the rest as recorded
    sim = simulate(p.with_(sample_hz=15.625), MACHINE.project("ZX"), 15.625, program=program_of(LIB.get("zx")))
    cut = (t >= sim.events["sig_in_2_start"]) & (t <= sim.events["sig_out_2_end"])
    reading = read_signature(t[~cut], L[~cut], sim.events["sig_rest_end"], 101.5, 1.5)
    # the chain of excursions ends at the gap: the last two are read, and are no code
    assert reading.code is None and "partial" in reading.note
    assert reading.symbols == signature_symbols(LIB.get("zx").signature)[2:]
    whole = read_signature(t, L, sim.events["sig_rest_end"], 101.5, 1.5)
    assert whole.code == LIB.get("zx").signature
    (res,) = outcome(t[~cut], L[~cut])
    assert res["event"] == "test_unrecognised" and res["reason"] == "ambiguous"
    assert sorted(res["candidates"]) == ["yz", "zx"] and "partial signature" in res["message"]


# --------------------------------------------------------------------------- recognition


@pytest.mark.parametrize("name,override", [("xy", 0.85), ("xy_fast", 1.15), ("xy_r150", 1.0), ("zx", 0.9)])
def test_plans_that_differ_in_timing_are_told_apart_by_it(name: str, override: float) -> None:
    t, L = record(name, 100.0, signed=False, override=override)
    (res,) = outcome(t, L)
    if name == "zx":  # zx and yz run the same timing: without a signature, no plan
        assert res["event"] == "test_unrecognised" and res["reason"] == "ambiguous", res
        assert sorted(res["candidates"]) == ["yz", "zx"] and res["signature"] is None
        return
    assert res["kind"] == "test" and res["plan"]["name"] == name, res
    assert res["recognition"]["method"] == "timing" and res["recognition"]["candidates"] == [name]
    truth = MACHINE.truth(res["plan"]["plane"])
    p = res["parameters"]
    assert abs(p["backlash_x_um"]["value"] - truth["backlash_x_um"]) < 0.1
    assert abs(p["squareness_urad"]["value"] - truth["squareness_urad"]) < 1.0
    assert abs(p["servo_mismatch_ms"]["value"] - truth["servo_mismatch_ms"]) < 0.05


def test_a_program_of_no_plan_is_not_analysed_and_the_event_says_why() -> None:
    t, L = record("stranger", 100.0)
    (res,) = outcome(t, L)
    assert res["event"] == "test_unrecognised" and res["reason"] == "no_match"
    assert f"code {FOREIGN[0].signature}" in res["message"] and res["signature"] == FOREIGN[0].signature
    assert res["candidates"] == ["xy"]  # its timing is xy's: the signature says it is another configuration's
    t, L = record("short", 100.0, signed=False)
    (res,) = outcome(t, L)
    assert res["event"] == "test_unrecognised" and res["reason"] == "no_match" and res["candidates"] == []
    assert "no plan's timing fits" in res["message"] and "xy 12" in res["message"]


def test_a_signature_whose_timing_does_not_fit_is_no_match() -> None:
    t, L = record("xy", 100.0, override=0.6)  # a feed override the timing check does not take
    (res,) = outcome(t, L)
    assert res["event"] == "test_unrecognised" and res["reason"] == "no_match"
    assert "the signature names xy" in res["message"]


def test_an_explicit_choice_wins_over_signature_and_timing() -> None:
    t, L = record("zx", 100.0)
    (res,) = outcome(t, L, chosen="yz")
    assert res["plan"]["name"] == "yz" and res["plan"]["plane"] == "YZ"
    assert res["recognition"]["method"] == "chosen" and res["recognition"]["signature"] == LIB.get("zx").signature
    with pytest.raises(PlanError, match="no plan 'nope'"):
        outcome(t, L, chosen="nope")


def test_at_feed_out_names_the_window_it_used() -> None:
    lib = PlanLibrary.from_plans({"a": TestPlan(), "b": TestPlan(feed_mm_min=1500.0)})
    # 1000 mm/min at 120 % and 1500 mm/min at 80 % take the same time: both fit, neither is taken
    from ballbar.analysis.program import schedule

    span = schedule(TestPlan(), TestPlan().feed_mm_s * 1.2, 0.01).feed_out_centroid_s
    rec = at_feed_out(lib, None, None, span)
    assert rec.name is None and rec.reason == "ambiguous" and rec.candidates == ("a", "b")


def test_a_library_of_one_is_analysed_exactly_as_before() -> None:
    plan = TestPlan(sample_hz=100.0)
    sim = simulate(plan, MACHINE.project("XY"), 100.0)
    old = next(r for r in analyze_recording(sim.t_s, sim.length_mm, plan) if r["kind"] == "test")
    one = next(r for r in analyze_recording(sim.t_s, sim.length_mm, plan, library=PlanLibrary.single(plan, "mill"))
           if r["kind"] == "test")
    assert old["plan"]["name"] == "default" and one["plan"]["name"] == "mill"
    assert old["recognition"] == one["recognition"] | {"message": ""} and old["recognition"]["method"] == "only"
    for key, p in old["parameters"].items():
        assert p["value"] == one["parameters"][key]["value"], key
    assert old["timing"] == one["timing"]


def test_a_plan_of_its_own_feed_and_dwell_is_timed_with_them() -> None:
    """The detector looks for steps with the first plan's feed and the shortest dwell; a plan with another
    feed or dwell has its steps found again with its own, and its result is its single-plan result."""
    lib = PlanLibrary.from_plans({"xy": TestPlan(), "slow": TestPlan(feed_mm_min=600.0, dwell_s=1.0)})
    fs = 15.625  # few samples in a step: the step's centroid comes from a ramp at the plan's feed
    t, L = record("slow", fs, library=lib)
    (res,) = outcome(t, L, lib)
    alone = lib.get("slow").plan.with_(sample_hz=fs)
    single = next(r for r in analyze_recording(t, L, alone) if r["kind"] == "test")
    assert res["plan"]["name"] == "slow" and res["timing"]["feed_in_s"] == single["timing"]["feed_in_s"]
    assert res["parameters"]["backlash_x_um"]["value"] == single["parameters"]["backlash_x_um"]["value"]


def test_live_chunks_give_the_whole_recordings_results_and_circles_name_their_plan() -> None:
    """A set streamed in 20 ms chunks (as the daemon feeds it) and the whole recording at once: the same
    plans, the same results; the provisional circles of a signed test carry its plan from the feed-in on."""
    t_parts, L_parts, names = [], [], []
    for name, res in set_tests(LIB, ["zx", "xy_r150", "yz"], MACHINE, 100.0, seed=4, repeat=3, gap_s=3.0):
        t_parts.append(res.t_s)
        L_parts.append(res.length_mm)
        names.append(name)
    t, L = np.concatenate(t_parts), np.concatenate(L_parts)
    whole = [r for r in analyze_recording(t, L, LIB.detection_plan(), library=LIB, circles=False)
             if r["kind"] == "test"]
    an = TestAnalyzer(LIB.detection_plan(), library=LIB)
    live: list[dict] = []
    for i in range(0, t.size, 2):
        live.extend(an.feed(t[i : i + 2], L[i : i + 2]))
    live.extend(an.finish())
    tests = [r for r in live if r["kind"] == "test"]
    assert [r["plan"]["name"] for r in tests] == [r["plan"]["name"] for r in whole] == names
    for a, b in zip(tests, whole, strict=True):
        assert a["parameters"]["squareness_urad"]["value"] == pytest.approx(b["parameters"]["squareness_urad"]["value"],
                                                                            abs=1e-9)
    feed_ins = [r for r in live if r.get("event") == "feed_in"]
    assert [e["plan"] for e in feed_ins] == names
    circles = [r for r in live if r["kind"] == "circle"]
    assert len(circles) == 6 and [c["plan"]["name"] for c in circles[::2]] == names
    truth = MACHINE.truth("XY")
    r150 = tests[1]
    assert r150["plan"]["radius_mm"] == 150.0
    assert abs(r150["parameters"]["radius_um"]["value"] - truth["radius_um"]) < 0.2  # read at its own length
    assert math.isclose(r150["timing"]["feed_ratio"], 1.0, abs_tol=0.01)


# --------------------------------------------------------------------------- the controller's program ([controller])


PROGRAMS = PlanLibrary(tuple(NamedPlan(p.name, p.plan, p.signature, f"O_{p.name.upper()}") for p in LIB.plans))


@pytest.mark.parametrize("name", ["zx", "yz"])
def test_the_controllers_program_tells_unsigned_zx_and_yz_apart(name: str) -> None:
    """Unsigned ZX and YZ programs run the same timing: ambiguous from the bar alone, each recognised by the
    program the controller ran (offline as live: a mark from the first sample on)."""
    t, L = record(name, 100.0, signed=False)
    (alone,) = outcome(t, L, PROGRAMS)
    assert alone["event"] == "test_unrecognised" and alone["reason"] == "ambiguous"
    (res,) = outcome(t, L, PROGRAMS, controller=[(0, True, f"O_{name.upper()}")])
    assert res["kind"] == "test" and res["plan"]["name"] == name and res["recognition"]["method"] == "controller"
    assert res["controller"] == {**res["controller"], "program": f"O_{name.upper()}", "plan": name, "used": True,
                                 "signature_plan": None, "timing_fits": True, "agrees": True}
    assert abs(res["parameters"]["backlash_x_um"]["value"] - MACHINE.truth(res["plan"]["plane"])["backlash_x_um"]) < 0.2


def test_a_signed_test_under_another_plans_program_is_a_disagreement() -> None:
    """A signed zx test while the controller runs yz's program: analysed as yz (the controller's), and a
    controller_disagrees event naming the signature's zx comes before the result; a program no plan names, or
    the controller lost, leaves the recognition to the signature."""
    t, L = record("zx", 100.0)
    out = [r for r in analyze_recording(t, L, PROGRAMS.detection_plan(), library=PROGRAMS, circles=False,
                                        controller=[(0, True, "O_YZ")])
           if r["kind"] == "test" or r.get("event") in ("controller_disagrees", "test_unrecognised")]
    assert [r.get("event", r["kind"]) for r in out] == ["controller_disagrees", "test"]
    ev, res = out
    assert ev["plan"] == "yz" and ev["signature_plan"] == "zx" and "signature names zx" in ev["message"]
    assert res["plan"]["name"] == "yz" and res["controller"]["agrees"] is False
    assert res["controller"]["timing_fits"] is True  # zx and yz: the same timing
    for marks in ([(0, True, "O_OTHER")], [(0, True, "O_YZ"), (0, False, None)]):
        (res,) = outcome(t, L, PROGRAMS, controller=marks)
        assert res["plan"]["name"] == "zx" and res["recognition"]["method"] == "signature"
        assert ("controller" in res) == (marks[-1][1] is True)  # a program no plan names: said; lost: nothing
        if "controller" in res:
            assert res["controller"]["used"] is False and res["controller"]["program"] == "O_OTHER"
