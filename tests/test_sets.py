"""A test set combined into the machine's axes (analysis/sets.py).

The machine is three-dimensional; each plane's test is simulated with that
plane's projection of it, worked out by hand below (the plane's first and
second axis take the 3D axes' errors), and analysed as the daemon does.  The
set must give back the 3D machine.
"""

from __future__ import annotations

import copy
import json
import math
from typing import Any

import numpy as np
import pytest
from schemacheck import problems

from ballbar.analysis import sets
from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import TestPlan
from ballbar.tools.machine3d import Machine3D
from ballbar.tools.simulate import SIM_MACHINE_3D
from ballbar.tools.simulator import MachineModel, simulate

# The 3D machine: per axis a gain (1/s), lost motion (um), scale (ppm); per pair a squareness (urad).
KV = {"X": 30.0, "Y": 33.0, "Z": 27.0}
LOST = {"X": 4.0, "Y": 2.5, "Z": 3.0}
SCALE = {"X": 8.0, "Y": -4.0, "Z": 12.0}
SQUARE = {"XY": 15.0, "YZ": -10.0, "ZX": 20.0}
# The README's recipe: XY over 360 deg, the vertical planes over 220 deg above the pivot, 5 deg overshoots.
PLANS = {"xy": ("XY", 0.0, 360.0, 180.0), "zx": ("ZX", -115.0, 220.0, 5.0), "yz": ("YZ", -25.0, 220.0, 5.0)}
SET = sets.SetDefinition("machine", ("xy", "zx", "yz"), 3600.0)


def projection(plane: str) -> dict[str, float]:
    """The plane's view of the 3D machine, by hand: first axis a, second b."""
    a, b = plane[0], plane[1]
    return {"kv_x_per_s": KV[a], "kv_y_per_s": KV[b], "backlash_x_um": LOST[a], "backlash_y_um": LOST[b],
            "scale_x_ppm": SCALE[a], "scale_y_ppm": SCALE[b], "squareness_urad": SQUARE[plane]}


def run_plan(name: str, i: int, hz: float = 250.0) -> dict[str, Any]:
    plane, start, arc, over = PLANS[name]
    plan = TestPlan(plane=plane, start_deg=start, data_arc_deg=arc, overshoot_deg=over, sample_hz=hz)  # type: ignore[arg-type]
    m = MachineModel(centre_x_um=6.0, centre_y_um=-3.0, noise_um=0.1, **projection(plane))
    s = simulate(plan, m, seed=10 + i)
    out = [r for r in analyze_recording(s.t_s, s.length_mm, plan, circles=False) if r.get("kind") == "test"]
    r = json.loads(json.dumps(out[0]))  # as published: plain JSON
    r["plan"]["name"] = name
    r["test_id"] = f"m-2026010{i + 1}T000000Z"
    r["t_wall"] = f"2026-01-01T00:0{i}:00.000Z"
    return r


@pytest.fixture(scope="module")
def tests3() -> dict[str, dict[str, Any]]:
    return {name: run_plan(name, i) for i, name in enumerate(PLANS)}


def mean(d: dict[str, float]) -> float:
    return sum(d.values()) / 3.0


def test_the_set_gives_back_the_3d_machine_from_its_planes(tests3: dict[str, dict[str, Any]]) -> None:
    s = sets.combine(SET, tests3)
    # every axis seen by two planes, each agreeing
    for a in sets.AXES:
        lm = s["lost_motion"][a]
        assert abs(lm["value"] - LOST[a]) < 0.1, (a, lm)  # type: ignore[operator]
        assert lm["trusted"] and lm["check"] is not None
        assert sum(o["used"] for o in lm["observations"]) == 2
    # X is seen as the XY plane's first axis and as the ZX plane's second
    fields = {(o["plane"], o["field"]) for o in s["lost_motion"]["X"]["observations"]}
    assert fields == {("XY", "backlash_x_um"), ("ZX", "backlash_y_um")}
    for p in sets.PAIRS:
        assert abs(s["squareness"][p]["value"] - SQUARE[p]) < 0.5, (p, s["squareness"][p])  # type: ignore[operator]
    # the servo lag mismatch per pair, 1/K_a - 1/K_b, and each axis' lag against the three axes' mean
    lag = {a: 1000.0 / KV[a] for a in sets.AXES}
    for p in sets.PAIRS:
        want = lag[p[0]] - lag[p[1]]
        assert abs(s["servo"]["pairs"][p]["value"] - want) < 0.05, p  # type: ignore[operator]
    for a in sets.AXES:
        assert abs(s["servo"]["axes"][a]["value"] - (lag[a] - mean(lag))) < 0.05, a  # type: ignore[operator]
    # the relative scales, within their (servo dynamics') uncertainty
    for a in sets.AXES:
        f = s["scale"]["axes"][a]
        assert abs(f["value"] - (SCALE[a] - mean(SCALE))) < 3 * f["stderr"], (a, f)  # type: ignore[operator]
    assert all(c["status"] == "passed" for c in s["checks"]), [c["message"] for c in s["checks"]]
    assert {c["kind"] for c in s["checks"]} == {"consistency", "closure"}
    assert len(s["checks"]) == 5  # three axes' lost motion, two closures
    # the geometric sphericity of the true machine lies within the figure's uncertainty
    truth = sets.sphericity_um([SCALE[a] for a in sets.AXES], [SQUARE[p] for p in sets.PAIRS], 100.0)
    sph = s["volumetric"]["geometric_sphericity"]
    assert sph["value"] is not None and sph["stderr"] is not None
    assert abs(sph["value"] - truth) < 3 * sph["stderr"] + 0.05, (sph, truth)
    lo, hi = sph["interval"]  # type: ignore[misc]
    assert lo < sph["value"] < hi
    big = s["volumetric"]["largest_circular_deviation"]
    g = {n: r["iso230_4"]["G_b_um"] for n, r in tests3.items()}
    assert big["value"] == max(g.values()) and big["plan"] == max(g, key=lambda n: g[n])
    assert s["verdict"]["status"] == "pass" and s["verdict"]["trusted"]
    assert [m["plan"] for m in s["tests"]] == ["xy", "zx", "yz"]
    assert s["set_id"] == "machine@m-20260103T000000Z"


def test_the_sphericity_by_hand() -> None:
    # Squareness alone in XY: E's symmetric part has S/2 off the diagonal, eigenvalues +-S/2: a range of S R.
    assert sets.sphericity_um([0, 0, 0], [20.0, 0, 0], 100.0) == pytest.approx(20e-6 * 100e3)
    # A scale of one axis against the others: the range is that difference times R; the mean drops out.
    assert sets.sphericity_um([10.0, 0, 0], [0, 0, 0], 100.0) == pytest.approx(1.0)
    assert sets.sphericity_um([15.0, 5.0, 5.0], [0, 0, 0], 100.0) == pytest.approx(1.0)


def test_a_tampered_plane_breaks_the_closure(tests3: dict[str, dict[str, Any]]) -> None:
    tampered = copy.deepcopy(tests3)
    tampered["zx"]["parameters"]["servo_mismatch_ms"]["value"] += 0.4  # ZX's servo lag, as if of another machine
    s = sets.combine(SET, tampered)
    closure = next(c for c in s["checks"] if c["name"] == "closure of the servo lag mismatch")
    assert closure["status"] == "failed" and closure["value"] == pytest.approx(0.4, abs=0.01)
    assert abs(closure["z"]) > 100  # type: ignore[arg-type]
    assert not any(s["servo"]["pairs"][p]["adjusted"]["trusted"] for p in sets.PAIRS)
    assert not any(s["servo"]["axes"][a]["trusted"] for a in sets.AXES)
    assert s["verdict"]["status"] == "warning" and not s["verdict"]["trusted"]
    assert "closure of the servo lag mismatch" in s["verdict"]["failed_checks"]
    # the adjusted pairs close exactly
    assert sum(s["servo"]["pairs"][p]["adjusted"]["value"] for p in sets.PAIRS) == pytest.approx(0.0, abs=1e-9)  # type: ignore[misc]
    # the untampered set closes (the same check passes there)
    ok = sets.combine(SET, tests3)
    assert next(c for c in ok["checks"] if c["name"] == closure["name"])["status"] == "passed"


def test_a_tampered_scale_and_lost_motion_fail_their_checks(tests3: dict[str, dict[str, Any]]) -> None:
    tampered = copy.deepcopy(tests3)
    tampered["yz"]["parameters"]["scale_mismatch_ppm"]["value"] += 60.0
    tampered["xy"]["parameters"]["backlash_x_um"]["value"] += 1.5  # X's lost motion, seen again in ZX
    s = sets.combine(SET, tampered)
    by = {c["name"]: c for c in s["checks"]}
    assert by["closure of the relative scale"]["status"] == "failed"
    x = by["consistency of the X lost motion"]
    assert x["status"] == "failed" and x["value"] == pytest.approx(1.5, abs=0.05)
    assert "X lost motion disagrees" in x["message"] and "standard errors" in x["message"]
    assert not s["lost_motion"]["X"]["trusted"] and s["lost_motion"]["Y"]["trusted"]
    # the Birge ratio inflates the untrusted value's uncertainty to its scatter
    assert s["lost_motion"]["X"]["stderr"] > 0.5  # type: ignore[operator]
    assert by["consistency of the Y lost motion"]["status"] == "passed"


def test_a_small_discrepancy_is_no_finding(tests3: dict[str, dict[str, Any]]) -> None:
    t = copy.deepcopy(tests3)
    t["xy"]["parameters"]["backlash_x_um"]["value"] += 0.3  # many standard errors, but below 0.5 um
    s = sets.combine(SET, t)
    c = next(c for c in s["checks"] if c["name"] == "consistency of the X lost motion")
    assert c["status"] == "passed" and abs(c["z"]) > 10 and "agrees within 0.5 um" in c["message"]  # type: ignore[arg-type]


def test_an_invalid_test_is_listed_not_combined(tests3: dict[str, dict[str, Any]]) -> None:
    t = copy.deepcopy(tests3)
    t["zx"]["fit"]["valid"] = False
    t["zx"]["fit"]["invalid_reasons"] = ["the feed changed between the arcs"]
    s = sets.combine(SET, t)
    zx = next(o for o in s["lost_motion"]["X"]["observations"] if o["plane"] == "ZX")
    assert not zx["used"] and "invalid" in str(zx["reason"]) and "feed changed" in str(zx["reason"])
    # X from XY alone: no check; the ZX squareness has nothing left
    assert s["lost_motion"]["X"]["check"] is None and s["lost_motion"]["X"]["value"] is not None
    assert s["squareness"]["ZX"]["value"] is None and not s["squareness"]["ZX"]["trusted"]
    assert "feed changed" in s["squareness"]["ZX"]["reasons"][0]
    closure = next(c for c in s["checks"] if c["kind"] == "closure")
    assert closure["status"] == "not_checked" and "ZX" in closure["message"]
    # two pairs still give each axis
    assert all(s["servo"]["axes"][a]["value"] is not None for a in sets.AXES)
    assert s["volumetric"]["geometric_sphericity"]["value"] is None
    assert s["verdict"]["status"] == "warning" and not s["verdict"]["trusted"]
    assert any("zx's test" in r for r in s["verdict"]["reasons"])


def test_the_plans_verdicts_make_the_sets() -> None:
    def result(plane: str, status: str | None) -> dict[str, Any]:
        r: dict[str, Any] = {"plan": {"plane": plane, "name": plane.lower(), "radius_mm": 100.0},
                             "parameters": {}, "fit": {"valid": True}, "test_id": plane, "t_wall": "2026-01-01T00:00Z"}
        if status:
            r["verdict"] = {"status": status, "summary": f"{status.upper()}: ...", "limits": [{"name": "G_b_um"}]}
        return r

    d = sets.SetDefinition("s", ("xy", "yz"), 60.0)
    s = sets.combine(d, {"xy": result("XY", "pass"), "yz": result("YZ", "fail")})
    assert s["verdict"]["status"] == "fail" and [p["status"] for p in s["verdict"]["plans"]] == ["pass", "fail"]
    s = sets.combine(d, {"xy": result("XY", None), "yz": result("YZ", "warning")})
    assert s["verdict"]["status"] == "warning" and s["tests"][0]["verdict"] == "not_evaluated"
    # no parameters at all: every figure says why it has no value
    assert s["lost_motion"]["X"]["value"] is None and s["lost_motion"]["X"]["reasons"]


def test_weighted_mean_and_closure_by_hand() -> None:
    def r(plane: str, i: int, **params: tuple[float, float]) -> dict[str, Any]:
        return {"plan": {"plane": plane, "name": plane.lower(), "radius_mm": 50.0}, "test_id": f"t{i}",
                "t_wall": f"2026-01-01T00:00:0{i}Z", "fit": {"valid": True},
                "parameters": {k: {"value": v, "stderr": e} for k, (v, e) in params.items()}}

    tests = {"xy": r("XY", 1, backlash_x_um=(4.0, 0.1), servo_mismatch_ms=(1.0, 0.01)),
             "yz": r("YZ", 2, servo_mismatch_ms=(-3.0, 0.02)),
             "zx": r("ZX", 3, backlash_y_um=(4.3, 0.2), servo_mismatch_ms=(2.05, 0.02))}
    s = sets.combine(sets.SetDefinition("s", ("xy", "yz", "zx"), 60.0), tests)
    x = s["lost_motion"]["X"]
    # 1/0.01 and 1/0.04 weights: (4.0 * 100 + 4.3 * 25) / 125
    assert x["value"] == pytest.approx((4.0 * 100 + 4.3 * 25) / 125)
    assert x["stderr"] == pytest.approx(1 / math.sqrt(125))
    chk = next(c for c in s["checks"] if c["name"] == "consistency of the X lost motion")
    assert chk["value"] == pytest.approx(-0.3) and chk["z"] == pytest.approx(-0.3 / math.hypot(0.1, 0.2))
    # closure 1 - 3 + 2.05 = 0.05 over sqrt(0.01^2 + 0.02^2 + 0.02^2) = 0.03: 1.67 standard errors, passes
    c = next(c for c in s["checks"] if c["kind"] == "closure" and "servo" in c["name"])
    assert c["value"] == pytest.approx(0.05) and c["stderr"] == pytest.approx(0.03) and c["status"] == "passed"
    adj = {p: s["servo"]["pairs"][p]["adjusted"]["value"] for p in sets.PAIRS}
    var = {"XY": 1e-4, "YZ": 4e-4, "ZX": 4e-4}
    raw = {"XY": 1.0, "YZ": -3.0, "ZX": 2.05}
    for p in sets.PAIRS:
        assert adj[p] == pytest.approx(raw[p] - var[p] * 0.05 / 9e-4)
    # per axis: (d_XY - d_ZX) / 3 for X, from the adjusted pairs
    assert s["servo"]["axes"]["X"]["value"] == pytest.approx((adj["XY"] - adj["ZX"]) / 3)  # type: ignore[operator]
    assert s["servo"]["axes"]["Y"]["value"] == pytest.approx((adj["YZ"] - adj["XY"]) / 3)  # type: ignore[operator]


def test_select_takes_each_plans_latest_within_the_window() -> None:
    def r(name: str, t: str, tid: str) -> dict[str, Any]:
        return {"kind": "test", "plan": {"name": name, "plane": "XY"}, "t_wall": t, "test_id": tid}

    d = sets.SetDefinition("s", ("a", "b"), 600.0)
    sel = sets.select(d, [r("a", "2026-01-01T00:00:00Z", "a1")])
    assert not sel.complete and sel.missing == ["b"] and "no test of plan b" in str(sel.why_not)
    got = [r("a", "2026-01-01T00:00:00Z", "a1"), r("b", "2026-01-01T00:05:00Z", "b1"),
           r("a", "2026-01-01T00:08:00Z", "a2"), r("c", "2026-01-01T00:09:00Z", "c1"),
           {"kind": "test", "plan": {"plane": "XY"}, "t_wall": "2026-01-01T00:09:00Z"}]
    sel = sets.select(d, got)
    assert sel.complete and {k: v["test_id"] for k, v in sel.tests.items()} == {"a": "a2", "b": "b1"}
    assert sel.span_s == 180.0 and sel.key == ("a2", "b1")
    sel = sets.select(d, [*got, r("a", "2026-01-01T00:20:00Z", "a3")])
    assert not sel.complete and "span 900 s, more than the set's window of 600 s" in str(sel.why_not)


def test_bad_definitions_are_one_line_errors() -> None:
    with pytest.raises(PlanError, match="at least one plan"):
        sets.SetDefinition("s", (), 60.0)
    with pytest.raises(PlanError, match="named twice"):
        sets.SetDefinition("s", ("a", "a"), 60.0)
    with pytest.raises(PlanError, match="positive number of seconds"):
        sets.SetDefinition("s", ("a",), 0.0)
    with pytest.raises(PlanError, match="no test of plan b"):
        sets.combine(sets.SetDefinition("s", ("a", "b"), 60.0), {"a": {"plan": {"plane": "XY"}}})


def test_the_set_message_is_valid_against_its_schema(tests3: dict[str, dict[str, Any]]) -> None:
    for t in (tests3, {**tests3, "zx": {**tests3["zx"], "fit": {**tests3["zx"]["fit"], "valid": False}}}):
        s: dict[str, Any] = json.loads(json.dumps(sets.combine(SET, t)))
        s |= {"schema_version": 2, "machine_id": "m", "t_wall": "2026-01-01T00:10:00.000Z"}
        assert problems(s) == [], problems(s)
        assert problems(s, "result") == []  # the MCAP results channel takes it too
        bad = copy.deepcopy(s)
        bad["lost_motion"]["X"]["extra"] = 1
        assert problems(bad), "a field the schema does not have must fail it"
    assert np.isfinite(s["volumetric"]["largest_circular_deviation"]["value"])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_at_1khz_the_checks_test_the_machine_not_the_fit(seed: int) -> None:
    """The daemon's 3D demo machine (spikes on X among its errors) at 1 kHz, where the fit's own standard error
    is 0.003 um of lost motion: each plane's lost motion and servo mismatch lie within three stated standard
    errors of the truth (they carry the model's own error, analysis/README.md "Uncertainty"), and so the set's
    consistency and closure checks sit within three of theirs (without that floor ZX read its Z lost motion
    3.4 standard errors off on seed 1)."""
    machine = Machine3D.from_settings({k: float(v) for k, v in (item.split("=") for item in SIM_MACHINE_3D)})
    tests = {}
    for i, (name, (plane, start, arc, over)) in enumerate(PLANS.items()):
        plan = TestPlan(plane=plane, start_deg=start, data_arc_deg=arc, overshoot_deg=over, sample_hz=1000.0)  # type: ignore[arg-type]
        sim = simulate(plan, machine.project(plane), seed=100 * seed + i)
        r = json.loads(json.dumps(next(r for r in analyze_recording(sim.t_s, sim.length_mm, plan, circles=False)
                                       if r.get("kind") == "test")))
        r["plan"]["name"], r["test_id"], r["t_wall"] = name, f"m-2026010{i + 1}T000000Z", f"2026-01-01T00:0{i}:00.000Z"
        truth = machine.truth(plane)
        for k in ("backlash_x_um", "backlash_y_um", "servo_mismatch_ms", "squareness_urad"):
            p = r["parameters"][k]
            assert abs(p["value"] - truth[k]) <= 3 * p["stderr"], (name, k, p["value"], p["stderr"], truth[k])
        tests[name] = r
    s = sets.combine(SET, tests)
    assert len(s["checks"]) == 5
    for c in s["checks"]:
        assert c["status"] == "passed" and abs(c["z"]) <= 3.0, c["message"]  # type: ignore[arg-type]
