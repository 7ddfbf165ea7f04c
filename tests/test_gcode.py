"""NC programs of the test (tools/gcode) read back by the interpreter (tools/ncinterp).

The check is only worth something if it can fail: each mutation of a generated
program (an exact stop or a dwell between arc blocks, a feed off by 1 mm/min, a
dwell changed, G02/G03 swapped, a coordinate moved by 0.01 mm) must be reported
for what it is.  The end-to-end test runs an interpreted FANUC program through
the physical simulator and the analyzer.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import arc_start_deg, moves
from ballbar.tools.gcode import (
    DEFAULT_DECIMALS,
    DIALECTS,
    REPEAT_DWELL_S,
    GcodeError,
    generate,
    lowest_point_mm,
    path_depth,
    pieces_deg,
)
from ballbar.tools.nccheck import check_against_plan, model_limits, test_moves
from ballbar.tools.ncinterp import NcError, interpret
from ballbar.tools.simulator import MachineModel, simulate

PLANS = {
    "default": TestPlan(),
    "partial": TestPlan(data_arc_deg=220.0, start_deg=-20.0, overshoot_deg=5.0),
    "ccw_only": TestPlan(directions="ccw"),
    "cw_only": TestPlan(directions="cw"),
    "start_45": TestPlan(start_deg=45.0),
    "r150_f2000": TestPlan(radius_mm=150.0, feed_mm_min=2000.0),
    "dwell_0": TestPlan(dwell_s=0.0),
}
PLANES = ("XY", "YZ", "ZX")
ISO_EXACT_STOP = {"fanuc": "G61", "siemens": "G60", "linuxcnc": "G61.1"}
DWELL_LINE = {"fanuc": "G04 X0.", "siemens": "G4 F0", "linuxcnc": "G4 P0"}


# --------------------------------------------------------------------------- helpers


def arc_lines(text: str, dialect: str) -> list[int]:
    """Indices (0-based) of the arc blocks in ``text``."""
    pat = r"^\d+ C " if dialect == "heidenhain" else r"^G0?[23] "
    return [i for i, s in enumerate(text.splitlines()) if re.match(pat, s)]


def insert(text: str, dialect: str, at: int, new: list[str]) -> str:
    """Lines ``new`` inserted before line index ``at`` (HEIDENHAIN blocks renumbered)."""
    lines = text.splitlines()
    lines[at:at] = [f"0 {s}" for s in new] if dialect == "heidenhain" else new
    if dialect == "heidenhain":
        lines = [f"{n} {s.split(' ', 1)[1]}" for n, s in enumerate(lines)]
    return "\n".join(lines) + "\n"


def shift_word(line: str, axis: str, delta: float, dialect: str) -> str:
    """``line`` with the coordinate of ``axis`` moved by ``delta`` mm, in the same format."""
    m = re.search(rf"\b{axis}([+-]?\d+\.(\d*))", line)
    assert m, (line, axis)
    dec = len(m.group(2))
    v = float(m.group(1)) + delta
    body = f"{v:.{dec}f}"
    if dialect == "heidenhain" and not body.startswith("-"):
        body = "+" + body
    return line[: m.start(1)] + body + line[m.end(1) :]


def second_axis(plane: str) -> str:
    return {"XY": "Y", "YZ": "Z", "ZX": "X"}[plane]


# --------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
@pytest.mark.parametrize("plane", PLANES)
@pytest.mark.parametrize("case", sorted(PLANS))
def test_generated_program_runs_the_plan(dialect: str, plane: str, case: str) -> None:
    plan = PLANS[case].with_(plane=plane)
    text = generate(plan, dialect)
    assert check_against_plan(text, dialect, plan) == []
    prog = interpret(text, dialect)
    got = test_moves(prog, plane, start_deg=arc_start_deg(plan, plan.direction_list[0]))
    want = moves(plan)
    assert [m.name for m in got] == [m.name for m in want]
    tol = 0.6 * 10.0 ** -DEFAULT_DECIMALS[dialect] * math.sqrt(2)
    for g, w in zip(got, want, strict=True):
        assert math.dist(g.start, w.start) <= tol and math.dist(g.end, w.end) <= tol, (g, w)
        if w.kind == "arc":
            assert abs(g.u_start - w.u_start) <= tol / w.radius and abs(g.sweep - w.sweep) <= 2 * tol / w.radius
        assert g.duration_s == w.duration_s


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_repeat_origin_and_decimals(dialect: str) -> None:
    plan = TestPlan(plane="YZ", start_deg=30.0, sample_hz=100.0)
    origin = (12.5, -40.0, 250.25)
    offset = None if dialect == "heidenhain" else "G55"
    text = generate(plan, dialect, origin=origin, work_offset=offset, repeat=3, decimals=5)
    assert check_against_plan(text, dialect, plan, origin=origin) == []
    prog = interpret(text, dialect)
    assert prog.decimals == 5 and prog.work_offset == offset
    third = test_moves(prog, "YZ", origin=origin, index=2, start_deg=30.0)
    assert [m.name for m in third] == [m.name for m in moves(plan)]
    dwells = [b.duration_s for b in prog.blocks if b.kind == "dwell"]
    assert dwells.count(REPEAT_DWELL_S) == 2
    # Read against the wrong pivot, every arc is off-centre.
    problems = check_against_plan(text, dialect, plan)
    assert any("arc centre" in p for p in problems)
    with pytest.raises(NcError, match="3 test"):
        test_moves(prog, "YZ", origin=origin, index=3)


@settings(max_examples=60, deadline=None)
@given(
    dialect=st.sampled_from(sorted(DIALECTS)),
    plane=st.sampled_from(PLANES),
    radius=st.sampled_from([10.0, 50.0, 100.0, 150.0, 1234.567]),
    feed=st.sampled_from([100.0, 1000.0, 1234.5, 2000.0, 5000.0]),
    start=st.integers(-400_000, 400_000).map(lambda k: k / 1000.0),
    overshoot=st.sampled_from([0.5, 5.0, 90.0, 180.0, 359.9, 360.0]),
    data=st.sampled_from([30.0, 45.5, 179.99, 180.0, 220.0, 360.0]),
    feed_in=st.sampled_from([0.5, 1.5, 3.0]),
    dwell=st.sampled_from([0.0, 0.25, 1.001]),
    directions=st.sampled_from(["both", "ccw", "cw"]),
    decimals=st.sampled_from([None, 3, 4, 6]),
    origin=st.sampled_from([(0.0, 0.0, 0.0), (12.3456, -7.5, 100.0)]),
)
def test_any_plan_runs_exactly_unless_the_plan_breaks_the_model(
    dialect: str, plane: str, radius: float, feed: float, start: float, overshoot: float, data: float,
    feed_in: float, dwell: float, directions: str, decimals: int | None, origin: tuple[float, float, float],
) -> None:
    plan = TestPlan.from_dict(dict(plane=plane, radius_mm=radius, feed_mm_min=feed, start_deg=start,
                                   overshoot_deg=overshoot, data_arc_deg=data, feed_in_mm=feed_in, dwell_s=dwell,
                                   directions=directions))
    problems = check_against_plan(generate(plan, dialect, decimals=decimals, origin=origin), dialect, plan,
                                  origin=origin)
    limits = model_limits(plan)
    assert (problems == []) == (limits == []), (problems, limits)
    assert all(f"timing: {x}" in problems for x in limits)


def test_model_limits() -> None:
    assert model_limits(TestPlan()) == []
    # V^2/A = 3.47 mm > the 1.5 mm feed-in: the feed-in is a triangle, which the timing model includes.
    fast = TestPlan(feed_mm_min=5000.0)
    assert model_limits(fast) == []
    assert check_against_plan(generate(fast, "fanuc"), "fanuc", fast) == []
    # V^2/2A = 1.74 mm > one degree at R 100 (1.745 mm) only below about 2000 mm/s^2.
    edge = TestPlan(feed_mm_min=5000.0, overshoot_deg=1.0)
    assert model_limits(edge, accel_mm_s2=1900.0) == [
        "the overshoot (1.745 mm) is shorter than the acceleration distance V^2/2A (1.827 mm at 1900 mm/s^2): "
        "the data arcs begin before the feed is reached"
    ]
    assert model_limits(edge, accel_mm_s2=2100.0) == []
    short = TestPlan(overshoot_deg=0.0)
    assert model_limits(short)[0].startswith("the overshoot (0 mm) is shorter than the acceleration distance")
    assert any(p.startswith("timing: on the ccw data arc") for p in check_against_plan(generate(short, "fanuc"),
                                                                                         "fanuc", short))


def test_pieces_keep_the_radius() -> None:
    for total, want in [(720.0, [180.0] * 4), (230.0, [115.0, 115.0]), (370.0, [180.0, 95.0, 95.0]),
                        (300.0, [180.0, 120.0]), (30.0, [30.0]), (1080.0, [180.0] * 6)]:
        assert pieces_deg(total) == pytest.approx(want)
    # 45 deg does not round to the circle; half-turn pieces keep the rounded radius exactly.
    prog = interpret(generate(TestPlan(start_deg=45.0), "fanuc"), "fanuc")
    radii = {math.hypot(p[0], p[1]) for b in prog.blocks if b.kind == "arc" for p in (b.start, b.end)}
    assert len(radii) == 1 and radii != {100.0}


def test_zx_arc_direction() -> None:
    """G18 G03 is counter-clockwise seen from +Y: from Z toward X, the plan's growing angle."""
    plan = TestPlan(plane="ZX", data_arc_deg=30.0, overshoot_deg=0.0, directions="ccw")
    text = generate(plan, "fanuc")
    assert "G18" in text
    assert "G03 X50.000 Z86.603 I0.000 K-100.000" in text  # from (Z 100, X 0) through 30 deg
    hh = generate(plan, "heidenhain")
    assert "TOOL CALL Y" in hh and "C X+50.0000 Z+86.6025 DR+" in hh


def test_lowest_point_and_warning() -> None:
    above = TestPlan(plane="YZ", start_deg=0.0, overshoot_deg=5.0, data_arc_deg=170.0)
    assert lowest_point_mm(above) == pytest.approx(0.0, abs=1e-9)
    assert "WARNING" not in generate(above, "siemens")
    below = TestPlan(plane="YZ", start_deg=-20.0, overshoot_deg=5.0, data_arc_deg=220.0)
    # both directions: the feed-in and feed-out are at -20 deg, the arcs end at 210 deg (R sin 210 = -50)
    assert lowest_point_mm(below) == pytest.approx(-50.0)
    # CCW only: the feed-out runs out to R + f on 210 deg
    assert lowest_point_mm(TestPlan(plane="YZ", start_deg=-20.0, overshoot_deg=5.0, data_arc_deg=220.0,
                                    directions="ccw")) == pytest.approx(-101.5 / 2)
    assert "below the pivot" in generate(below, "siemens")
    assert lowest_point_mm(TestPlan(plane="ZX")) == -100.0
    assert path_depth(TestPlan(plane="ZX")).arc_low_at_deg == (180.0,)
    assert "LOWEST POINT" in generate(TestPlan(plane="ZX"), "fanuc")
    assert "Lowest" not in generate(TestPlan(plane="XY"), "linuxcnc")


def _comments(text: str) -> list[str]:
    return [c for line in text.splitlines() for c in re.findall(r"\(([^)]*)\)", line)]


def test_fanuc_header_lines() -> None:
    """The header is one statement a comment line, no run-on and no stray space before punctuation."""
    plan = TestPlan(plane="ZX", start_deg=-115.0, overshoot_deg=5.0, data_arc_deg=220.0)
    comments = _comments(generate(plan, "fanuc"))
    assert comments[1:6] == [
        "BALL-BAR CIRCULAR TEST TO ISO 230-4",
        "WRITTEN BY BALLBAR.TOOLS.GCODE",
        "PLANE ZX: FIRST AXIS Z, SECOND AXIS X",
        "RADIUS R 100 MM, FEED F 1000 MM/MIN",
        "START -115 DEG, OVERSHOOT 5 DEG, DATA ARC 220 DEG, ARC 230 DEG, CCW THEN CW",
    ]
    assert "ANGLES COUNTER-CLOCKWISE FROM Z TOWARD X" in comments
    assert "COORDINATES TO 3 DECIMALS" in comments
    for c in comments:
        assert not re.search(r" [,.:]", c), c
    siemens = generate(plan, "siemens").splitlines()
    assert "; Angles counter-clockwise from Z toward X" in siemens and "; Coordinates to 4 decimals" in siemens


def _readme_recipes() -> list[tuple[str, TestPlan]]:
    readme = (Path(__file__).resolve().parents[1] / "tools" / "README.md").read_text()
    out = []
    for m in re.finditer(r"ballbar gcode --dialect (\w+) (--plane \w+ [^\n]*)", readme):
        flags = dict(re.findall(r"--([\w-]+) (\S+)", m.group(2)))
        plan = TestPlan(plane=flags["plane"], start_deg=float(flags["start-deg"]),
                        overshoot_deg=float(flags["overshoot-deg"]), data_arc_deg=float(flags["data-arc-deg"]))
        out.append((m.group(1), plan))
    return out


def test_readme_vertical_recipe_is_symmetric_and_warned_exactly() -> None:
    """tools/README.md's 220 deg recipes: the path the interpreter runs is symmetric about the vertical and goes
    exactly as deep (mm, and degrees below the pivot's level, and where) as the header warns."""
    recipes = _readme_recipes()
    assert {p.plane for _d, p in recipes} == {"YZ", "ZX"}
    for dialect, plan in recipes:
        text = generate(plan, dialect)
        prog = interpret(text, dialect)
        i, j = {"YZ": (1, 2), "ZX": (2, 0)}[plan.plane]  # the plane's first, second axis in X Y Z
        zs: list[float] = []
        arc_z: list[tuple[float, float]] = []  # (Z, angle from the vertical, deg) along the arcs
        for b in prog.blocks:
            if b.kind in ("line", "rapid"):
                zs += [b.start[2], b.end[2]]
            elif b.kind == "arc":
                assert b.centre is not None
                a0 = math.atan2(b.start[j] - b.centre[j], b.start[i] - b.centre[i])
                r = math.dist(b.start, b.centre)
                for t in np.linspace(0.0, 1.0, 20001):
                    a = a0 + t * b.sweep_rad
                    p = [0.0, 0.0, 0.0]
                    p[i], p[j] = b.centre[i] + r * math.cos(a), b.centre[j] + r * math.sin(a)
                    up = math.degrees(a) - (90.0 if plan.plane == "YZ" else 0.0)  # from +Z
                    arc_z.append((p[2], (up + 180.0) % 360.0 - 180.0))
        zs = [z for z in zs if math.isfinite(z)]
        low_arc = min(z for z, _a in arc_z)
        low = min([*zs, low_arc])
        extremes = [a for z, a in arc_z if z < low_arc + 1e-6]
        # symmetric about the vertical: the arcs reach as far on one side as on the other
        assert min(extremes) == pytest.approx(-max(extremes), abs=1e-3)
        below_deg = math.degrees(math.asin(-low_arc / plan.radius_mm))
        assert below_deg == pytest.approx(plan.data_arc_deg / 2 - 90.0 + plan.overshoot_deg, abs=1e-3)
        comments = _comments(text) if dialect == "fanuc" else text.splitlines()
        header = "\n".join(comments).upper()
        m = re.search(r"THE PATH GOES ([\d.]+) MM BELOW THE PIVOT", header)
        assert m and float(m.group(1)) == pytest.approx(-low, abs=1e-3)
        m = re.search(r"THE ARCS GO ([\d.]+) DEG BELOW THE PIVOT'S LEVEL, TO Z (-[\d.]+) MM AT (.*) DEG", header)
        assert m, header
        assert float(m.group(1)) == pytest.approx(below_deg, abs=0.005)
        assert float(m.group(2)) == pytest.approx(low_arc, abs=1e-3)
        at = sorted(float(a) for a in m.group(3).split(" AND "))
        assert len(at) == 2 and at[1] - at[0] == pytest.approx(plan.arc_deg)
        # and tools/README.md states those figures
        readme = (Path(__file__).resolve().parents[1] / "tools" / "README.md").read_text()
        assert f"goes {-low:.3f} mm below the pivot" in " ".join(readme.split())
        assert f"{below_deg:.2f} deg below" in readme


# --------------------------------------------------------------------------- the check fails


@pytest.mark.parametrize("dialect", sorted(ISO_EXACT_STOP))
def test_exact_stop_between_arc_blocks(dialect: str) -> None:
    plan = TestPlan()
    text = generate(plan, dialect)
    at = arc_lines(text, dialect)[1]
    problems = check_against_plan(insert(text, dialect, at, [ISO_EXACT_STOP[dialect]]), dialect, plan)
    assert any("the ccw arc stops (exact stop" in p for p in problems), problems
    assert any(p.startswith("moves:") for p in problems)
    assert any(p.startswith("timing:") for p in problems)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_dwell_between_arc_blocks(dialect: str) -> None:
    plan = TestPlan()
    text = generate(plan, dialect)
    at = arc_lines(text, dialect)[1]
    new = ["CYCL DEF 9.0 DWELL TIME", "CYCL DEF 9.1 DWELL 0"] if dialect == "heidenhain" else [DWELL_LINE[dialect]]
    problems = check_against_plan(insert(text, dialect, at, new), dialect, plan)
    assert any(re.fullmatch(r"a dwell at line \d+ splits the ccw arc", p) for p in problems), problems
    assert any("feed-out centroid" in p for p in problems)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_feed_off_by_one(dialect: str) -> None:
    plan = TestPlan()
    text = generate(plan, dialect)
    bad = re.sub(r"F1000\.?(?=\s|$)", "F1001", text, count=1, flags=re.M)
    assert bad != text
    problems = check_against_plan(bad, dialect, plan)
    assert any(p.startswith("feed 1001.0 mm/min on lines") for p in problems), problems
    assert any("feed-out centroid" in p for p in problems)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_dwell_value_changed(dialect: str) -> None:
    plan = TestPlan()
    text = generate(plan, dialect)
    pat = {"fanuc": "G04 X0.5", "siemens": "G4 F0.5", "linuxcnc": "G4 P0.5", "heidenhain": "DWELL 0.5"}[dialect]
    problems = check_against_plan(text.replace(pat, pat[:-1] + "6", 1), dialect, plan)
    assert any(re.fullmatch(r"dwell_in \(line \d+\): lasts 0.6 s, the plan's 0.5 s", p) for p in problems), problems
    assert any("timing: on the ccw data arc" in p for p in problems)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_arc_direction_swapped(dialect: str) -> None:
    plan = TestPlan()
    text = generate(plan, dialect)
    lines = text.splitlines()
    k = arc_lines(text, dialect)[1]
    swap = {"G03": "G02", "G3": "G2", "DR+": "DR-"}
    lines[k] = re.sub(r"G03|G3\b|DR\+", lambda m: swap[m.group(0)], lines[k])
    problems = check_against_plan("\n".join(lines) + "\n", dialect, plan)
    assert any(p.startswith("moves: the program runs feed_in dwell_in ccw cw ccw") for p in problems), problems


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
@pytest.mark.parametrize("plane", PLANES)
def test_coordinate_moved_by_10um(dialect: str, plane: str) -> None:
    plan = TestPlan(plane=plane, start_deg=45.0)
    text = generate(plan, dialect)
    arcs = arc_lines(text, dialect)
    # The junction of two arc blocks: 0.01 mm on a 45 deg point is 0.007 mm off the radius.
    lines = text.splitlines()
    k = arcs[1]
    lines[k] = shift_word(lines[k], second_axis(plane), 0.01, dialect)
    problems = check_against_plan("\n".join(lines) + "\n", dialect, plan)
    assert any(re.fullmatch(rf"line {k + 1}: arc end radius 100.00\d+ mm, the plan's 100 mm", p) for p in problems), (
        problems
    )
    if dialect != "heidenhain":  # I/J/K hang the next block's centre on the moved start point
        assert any(re.fullmatch(rf"line {k + 2}: arc centre 0.0100\d+ mm from the pivot", p) for p in problems)
    # The end of the last arc block moved: the arc no longer ends where the plan's does.
    lines = text.splitlines()
    k = arcs[-1]
    lines[k] = shift_word(lines[k], second_axis(plane), 0.01, dialect)
    problems = check_against_plan("\n".join(lines) + "\n", dialect, plan)
    assert any(re.match(r"cw \(line \d+\): ends at", p) for p in problems), problems


def test_heidenhain_junction_moved_along_the_circle_is_the_same_path() -> None:
    """CC is absolute: a junction slid along the circle leaves the path unchanged (I/J/K would move a centre)."""
    plan = TestPlan()
    text = generate(plan, "heidenhain")
    lines = text.splitlines()
    k = arc_lines(text, "heidenhain")[1]
    assert lines[k].endswith("C X+100.0000 Y+0.0000 DR+")
    lines[k] = shift_word(lines[k], "Y", 0.01, "heidenhain")
    assert check_against_plan("\n".join(lines) + "\n", "heidenhain", plan) == []
    fanuc = generate(plan, "fanuc").splitlines()
    k = arc_lines("\n".join(fanuc), "fanuc")[1]
    fanuc[k] = shift_word(fanuc[k], "Y", 0.01, "fanuc")
    assert any("arc centre" in p for p in check_against_plan("\n".join(fanuc) + "\n", "fanuc", plan))


# --------------------------------------------------------------------------- interpreter errors


@pytest.mark.parametrize(
    ("dialect", "old", "new", "message"),
    [
        ("fanuc", "G04 X0.5", "G04 X0.5 Q1", "unknown word Q1"),
        ("fanuc", "M05", "M08", "unsupported M-code M8"),
        ("fanuc", "G21 G90", "G20 G90", "unsupported G-code G20"),
        ("fanuc", " F1000.", "", "feed move without a feed"),
        ("siemens", "G90", "G91", "unsupported G-code G91"),
        ("linuxcnc", "G4 P0.5", "G4", "G4 without P"),
        ("linuxcnc", "G91.1", "G90.1", "unsupported G-code G90.1"),
        ("heidenhain", "TOOL CALL Z", "TOOL CALL Z RL", "unknown or unsupported block"),
        ("heidenhain", " F1000", "", "feed move without a feed"),
        ("heidenhain", "DR+", "DR", "C needs one DR+ or DR-"),
    ],
)
def test_interpreter_errors_carry_the_line(dialect: str, old: str, new: str, message: str) -> None:
    text = generate(TestPlan(), dialect)
    line = next(i + 1 for i, s in enumerate(text.splitlines()) if old in s)
    with pytest.raises(NcError, match=re.escape(message)) as info:
        interpret(text.replace(old, new, 1), dialect)
    assert info.value.line == line
    assert str(info.value).startswith(f"line {line}: ")
    problems = check_against_plan(text.replace(old, new, 1), dialect, TestPlan())
    assert problems == [str(info.value)]


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_arc_radius_alarm(dialect: str) -> None:
    plan = TestPlan()
    text = generate(plan, dialect)
    lines = text.splitlines()
    k = arc_lines(text, dialect)[0]
    lines[k] = shift_word(lines[k], "X", -0.02, dialect)  # ends at X -100.02: 0.02 mm off the radius
    with pytest.raises(NcError, match=r"arc end radius .*more than 0\.01 mm") as info:
        interpret("\n".join(lines) + "\n", dialect)
    assert info.value.line == k + 1


def test_structural_errors() -> None:
    fanuc = generate(TestPlan(), "fanuc")
    with pytest.raises(NcError, match="starts with '%'"):
        interpret(fanuc.lstrip("%\n"), "fanuc")
    with pytest.raises(NcError, match="no end"):
        interpret(fanuc.replace("M30\n", ""), "fanuc")
    with pytest.raises(NcError, match=r"arc end radius 0\.100000 mm"):
        interpret(fanuc.replace("G03 X-100.000", "G03 X-100", 1), "fanuc")  # X-100 is -0.1 mm on IS-B
    hh = generate(TestPlan(), "heidenhain").splitlines()
    with pytest.raises(NcError, match="block number 7, expected 6") as info:
        interpret("\n".join(hh[:6] + hh[7:]), "heidenhain")
    assert info.value.line == 7
    with pytest.raises(NcError, match="does not match BEGIN PGM BALLBAR"):
        interpret("\n".join([*hh[:-1], hh[-1].replace("BALLBAR", "OTHER")]), "heidenhain")
    with pytest.raises(NcError, match="unknown dialect"):
        interpret("", "haas")


# --------------------------------------------------------------------------- generator refusals


def test_generator_refuses_what_it_cannot_write() -> None:
    plan = TestPlan()
    with pytest.raises(GcodeError, match="unknown dialect"):
        generate(plan, "haas")
    with pytest.raises(GcodeError, match="decimals"):
        generate(plan, "fanuc", decimals=7)
    with pytest.raises(GcodeError, match="more than 1 % of the feed-in"):
        generate(TestPlan(start_deg=45.0), "fanuc", decimals=0)
    with pytest.raises(GcodeError, match="cannot be written exactly"):
        generate(TestPlan(feed_mm_min=1000.0 / 3.0), "siemens")
    with pytest.raises(GcodeError, match="cannot be written exactly"):
        generate(TestPlan(dwell_s=0.0005), "fanuc")
    with pytest.raises(GcodeError, match="ends where it starts"):
        generate(TestPlan(directions="ccw", data_arc_deg=220.0, overshoot_deg=5.0), "linuxcnc", repeat=2)
    with pytest.raises(GcodeError, match="preset"):
        generate(plan, "heidenhain", work_offset="G54")
    with pytest.raises(GcodeError, match="work offset"):
        generate(plan, "siemens", work_offset="G59")
    with pytest.raises(GcodeError, match="O-number"):
        generate(plan, "fanuc", program_name="BALLBAR")
    bad = TestPlan()
    object.__setattr__(bad, "plane", "XZ")
    with pytest.raises(GcodeError, match="plane"):
        generate(bad, "fanuc")
    assert isinstance(GcodeError("x"), ValueError)
    # A one-direction test of whole turns ends where it starts: it may repeat.
    text = generate(TestPlan(directions="ccw"), "linuxcnc", repeat=2)
    assert check_against_plan(text, "linuxcnc", TestPlan(directions="ccw")) == []


# --------------------------------------------------------------------------- readability


def test_fanuc_layout() -> None:
    text = generate(TestPlan(), "fanuc", program_name="O1234", work_offset="g54.1 p2")
    lines = text.splitlines()
    assert lines[0] == "%" and lines[-1] == "%"
    assert re.fullmatch(r"O1234 \(BALLBAR\)", lines[1])
    assert "G54.1 P2" in lines
    assert interpret(text, "fanuc").name == "O1234"
    for s in lines:
        for c in re.findall(r"\(([^)]*)\)", s):
            assert c == c.upper() and "%" not in c and ";" not in c
        code = re.sub(r"\(.*?\)", "", s)
        for w in re.findall(r"[XYZIJK][+-]?[\d.]+", code.replace("G04 X", "G04 T")):
            assert re.fullmatch(r"[XYZIJK]-?\d+\.\d{3}", w), w  # always a decimal point, IS-B digits
    assert "M30" in lines and "G64 (CUTTING MODE: THE ARC BLOCKS BLEND)" in lines


def test_heidenhain_layout() -> None:
    text = generate(TestPlan(plane="YZ"), "heidenhain", program_name="BB_TEST", repeat=2)
    lines = text.splitlines()
    assert [int(s.split()[0]) for s in lines] == list(range(len(lines)))
    assert lines[0] == "0 BEGIN PGM BB_TEST MM" and lines[-1].endswith(" END PGM BB_TEST MM")
    assert any(s.endswith(" TOOL CALL X") for s in lines)
    assert any(s.endswith(" STOP") for s in lines)
    assert sum(s.endswith("CYCL DEF 9.0 DWELL TIME") for s in lines) == 2 * 3 + 1  # 3 per test, 1 between
    for s in lines:
        for w in re.findall(r"\b[XYZ][+-][\d.]+", s):
            assert re.fullmatch(r"[XYZ][+-]\d+\.\d{4}", w), w


def test_iso_layouts() -> None:
    sie = generate(TestPlan(plane="ZX"), "siemens", program_name="BALLBAR_ZX")
    assert sie.startswith("; Program BALLBAR_ZX\n")
    assert "G71 G90 G18 G94 G40" in sie and "\nG60\n" in sie and "\nG64 ;" in sie and sie.endswith("M30\n")
    assert "(" not in sie.replace("; ", "")[:0]  # comments only after ';'
    lcnc = generate(TestPlan(), "linuxcnc", mount_stop=False)
    lines = lcnc.splitlines()
    assert "G21 G90 G17 G94 G40 G80 G91.1" in lines and "M0" not in lines
    assert not any(s.startswith("O") for s in lines)  # an O-word is a subroutine in LinuxCNC
    i49 = next(i for i, s in enumerate(lines) if s.startswith("M49"))
    i48 = next(i for i, s in enumerate(lines) if s.startswith("M48"))
    first_feed = next(i for i, s in enumerate(lines) if s.startswith("G1 "))
    last_feed = max(i for i, s in enumerate(lines) if s.startswith("G1 "))
    assert i49 < first_feed and last_feed < i48 and lines[-1] == "M2"
    assert interpret(lcnc, "linuxcnc").blocks[-1].kind == "end"


# --------------------------------------------------------------------------- through the simulator


def test_simulator_default_program_is_the_plan() -> None:
    plan = TestPlan(sample_hz=100.0, data_arc_deg=90.0, overshoot_deg=10.0)
    m = MachineModel(backlash_x_um=3.0)
    a = simulate(plan, m, step_s=1e-3)
    b = simulate(plan, m, step_s=1e-3, program=moves(plan))
    assert np.array_equal(a.length_mm, b.length_mm) and a.events == b.events


def test_fanuc_program_through_simulator_and_analyzer() -> None:
    """The interpreted program on a physical machine model: the analyzer recovers the machine."""
    plan = TestPlan(start_deg=45.0, sample_hz=250.0)
    text = generate(plan, "fanuc")
    assert check_against_plan(text, "fanuc", plan) == []
    program = test_moves(interpret(text, "fanuc"), plan.plane, start_deg=arc_start_deg(plan, 1))
    rounded_radius_um = (program[2].radius - plan.radius_mm) * 1e3  # 45 deg rounds to 70.711: +0.455 um
    assert 0.4 < rounded_radius_um < 0.5
    machine = MachineModel(backlash_x_um=4.0, squareness_urad=20.0)
    sim = simulate(plan, machine, program=program)
    results = analyze_recording(sim.t_s, sim.length_mm, plan)
    tests = [r for r in results if r["kind"] == "test"]
    assert len(tests) == 1
    p = tests[0]["parameters"]
    assert abs(p["backlash_x_um"]["value"] - 4.0) < 0.05
    assert abs(p["backlash_y_um"]["value"]) < 0.05
    assert abs(p["squareness_urad"]["value"] - 20.0) < 0.02 / (plan.radius_mm * 1e-3 / 2)
    assert abs(p["radius_um"]["value"] - rounded_radius_um) < 0.05
