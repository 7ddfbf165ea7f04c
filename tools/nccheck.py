"""The motion of an executed NC program (:mod:`ballbar.tools.ncinterp`) and its check against the plan.

:func:`test_moves` turns the executed blocks into the moves of one test as
:func:`ballbar.analysis.program.moves` describes them: plane frame (first,
second axis), millimetres from the pivot, angles counter-clockwise from the
first axis, every move starting and ending at rest.  Feed blocks that the
controller runs without stopping are merged into one move: consecutive blocks
at the same feed, in continuous-path mode, tangent at their junction (within
:data:`TANGENT_TOL_RAD`).  The motion stops at a dwell (also of 0 s), a program
stop, a rapid, the end of a block in exact-stop mode, a corner and a feed
change.  Rapids are taken to end at rest (positioning; the generated program
approaches in exact-stop mode anyway).

:func:`signatures` reads the signature each test's program carries before its
feed-in (radial excursions that do not reach the circle; :mod:`ballbar.analysis.plans`),
which the split into tests leaves out.

:func:`check_against_plan` compares a program with the plan and with the
timing the analyzer assumes (:func:`ballbar.analysis.program.schedule`).
:func:`model_limits` says where the plan itself breaks that timing model at a
given acceleration (an overshoot too short to reach the feed): then
no program can pass the check, and the plan, not the program, needs changing.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import Move, arc_start_deg, model_limits, moves, schedule
from ballbar.tools.feed_profile import _Profile
from ballbar.tools.gcode import PLANE_INDEX
from ballbar.tools.ncinterp import _AXES, Block, NcError, Program, Vec3, interpret

TANGENT_TOL_RAD = 1.0e-3  # a junction whose direction turns by less runs through without stopping
TIME_TOL_S = 1.0e-6
ANGLE_TOL_DEG = 1.0e-6
DWELL_TOL_S = 1.0e-9


# --------------------------------------------------------------------------- moves


@dataclass(frozen=True)
class _Seg:
    """A rest-to-rest move of the program with the blocks it came from."""

    move: Move
    blocks: tuple[Block, ...]
    feed: float | None
    stop_reason: str = ""  # why the motion stops after it (for merged feed moves)


def _plane2(p: Vec3, plane: str, origin: Sequence[float]) -> tuple[float, float]:
    i1, i2, _ = PLANE_INDEX[plane]
    return (p[i1] - origin[i1], p[i2] - origin[i2])


def _tangent(b: Block, plane: str, at_end: bool) -> tuple[float, float]:
    """Unit direction of travel at the start or end of a feed block, in the plane's frame."""
    i1, i2, _ = PLANE_INDEX[plane]
    if b.kind == "line":
        dx, dy = b.end[i1] - b.start[i1], b.end[i2] - b.start[i2]
    else:
        assert b.centre is not None
        p = b.end if at_end else b.start
        rx, ry = p[i1] - b.centre[i1], p[i2] - b.centre[i2]
        dx, dy = -b.direction * ry, b.direction * rx
    n = math.hypot(dx, dy)
    return (dx / n, dy / n) if n > 0 else (0.0, 0.0)


def _junction(a: Block, b: Block, plane: str) -> str:
    """Why the motion stops between feed blocks ``a`` and ``b`` ('' if it runs through)."""
    if a.exact_stop:
        return f"exact stop at the end of line {a.line}"
    if a.feed_mm_min != b.feed_mm_min:
        return f"feed change at line {b.line}"
    ta, tb = _tangent(a, plane, True), _tangent(b, plane, False)
    turn = math.atan2(ta[0] * tb[1] - ta[1] * tb[0], ta[0] * tb[0] + ta[1] * tb[1])
    if abs(turn) > TANGENT_TOL_RAD:
        return f"corner of {math.degrees(abs(turn)):.3g} deg at line {b.line}"
    if a.kind != b.kind:
        raise NcError(b.line, "a line and an arc meet tangentially: the controller does not stop there, "
                              "and no rest-to-rest move describes them")
    return ""


def _feed_move(run: list[Block], plane: str, origin: Sequence[float], u_ref: float) -> tuple[Move, float]:
    first, last = run[0], run[-1]
    p0, p1 = _plane2(first.start, plane, origin), _plane2(last.end, plane, origin)
    if first.kind == "line":
        return Move("line", "line", p0, p1), u_ref
    u = math.atan2(p0[1], p0[0])
    u += 2 * math.pi * round((u_ref - u) / (2 * math.pi))
    sweep = math.fsum(b.sweep_rad for b in run)
    radius = math.hypot(*p0)
    name = "ccw" if sweep > 0 else "cw"
    return Move("arc", name, p0, p1, radius, u, sweep), u + sweep


def _segments(program: Program, plane: str, origin: Sequence[float], start_deg: float) -> list[_Seg]:
    """The program from its first feed move on, as rest-to-rest moves (feed blocks merged)."""
    _, _, i3 = PLANE_INDEX[plane]
    out: list[_Seg] = []
    run: list[Block] = []
    u_ref = math.radians(start_deg)
    started = False

    def close(reason: str) -> None:
        nonlocal run, u_ref
        if run:
            mv, u_ref = _feed_move(run, plane, origin, u_ref)
            out.append(_Seg(mv, tuple(run), run[0].feed_mm_min, reason))
            run = []

    for b in program.blocks:
        if b.kind in ("line", "arc"):
            started = True
            if b.kind == "arc" and b.plane != plane:
                raise NcError(b.line, f"arc in the {b.plane} plane, the test's is {plane}")
            if b.kind == "line" and abs(b.end[i3] - b.start[i3]) > 1e-12:
                raise NcError(b.line, f"feed move along {_AXES[i3]}, out of the {plane} plane")
            if run:
                reason = _junction(run[-1], b, plane)
                if reason:
                    close(reason)
            run.append(b)
            continue
        if not started:
            continue
        close(f"{b.kind} at line {b.line}")
        p = _plane2(b.start, plane, origin)
        if b.kind == "dwell":
            out.append(_Seg(Move("dwell", "dwell", p, p, duration_s=b.duration_s), (b,), None))
        elif b.kind == "rapid":
            out.append(_Seg(Move("line", "rapid", p, _plane2(b.end, plane, origin)), (b,), None))
        elif b.kind == "stop":
            out.append(_Seg(Move("dwell", "stop", p, p, duration_s=math.inf), (b,), None))
        else:
            break
    close("end of program")
    return out


def _split_tests(segs: list[_Seg], start_deg: float) -> list[list[_Seg]]:
    """Tests: from an inward line (feed-in) to the next outward line (feed-out), moves named as ``moves``.

    Each test's arcs are shifted by whole turns so that its first arc starts
    within half a turn of ``start_deg`` (a repeated test starts where the plan does).
    """
    tests: list[list[_Seg]] = []
    cur: list[_Seg] | None = None
    for s in segs:
        mv = s.move
        radial = math.hypot(*mv.end) - math.hypot(*mv.start) if mv.kind == "line" and mv.name == "line" else 0.0
        if cur is None:
            if radial < 0:
                cur = [replace(s, move=replace(mv, name="feed_in"))]
            continue
        if radial > 0:
            if not any(x.move.kind == "arc" for x in cur):  # in and out with no arc: a signature's excursion
                cur = None
                continue
            cur.append(replace(s, move=replace(mv, name="feed_out")))
            tests.append(_rewind(cur, math.radians(start_deg)))
            cur = None
            continue
        if mv.kind == "dwell" and mv.name == "dwell":
            prev = cur[-1].move.name
            name = {"feed_in": "dwell_in", "ccw": "dwell_ccw", "cw": "dwell_cw"}.get(prev, "dwell")
            s = replace(s, move=replace(mv, name=name))
        elif radial < 0:
            s = replace(s, move=replace(mv, name="feed_in"))
        cur.append(s)
    return tests


def program_moves(program: Program, plane: str, *, origin: Sequence[float] = (0.0, 0.0, 0.0),
                  start_deg: float = 0.0) -> list[Move]:
    """The whole program from its first feed move on (signatures, tests, the moves between) as rest-to-rest
    moves in the plane's frame, as :func:`test_moves` takes each test's; arcs' angles unwound from
    ``start_deg``.  Names are the program's (``line``, ``arc`` as ``ccw``/``cw``, ``dwell``, ``rapid``,
    ``stop``), not the plan's."""
    return [s.move for s in _segments(program, plane, origin, start_deg)]


def signatures(program: Program, plane: str, *, origin: Sequence[float] = (0.0, 0.0, 0.0)) -> list[list[float]]:
    """Per test, the depths (mm toward the pivot) of the excursions before its feed-in: its signature
    (:mod:`ballbar.analysis.plans`); an empty list where a test has none.  An excursion is an inward line
    followed by an outward one with only dwells between; a test begins at an inward line followed by an arc."""
    out: list[list[float]] = []
    pending: list[float] = []
    segs = _segments(program, plane, origin, 0.0)
    k = 0
    while k < len(segs):
        mv = segs[k].move
        if mv.kind == "line" and mv.name == "line" and math.hypot(*mv.end) < math.hypot(*mv.start):
            j = k + 1
            while j < len(segs) and segs[j].move.kind == "dwell":
                j += 1
            nxt = segs[j].move if j < len(segs) else None
            if nxt is not None and nxt.kind == "line" and math.hypot(*nxt.end) > math.hypot(*nxt.start):
                pending.append(math.hypot(*mv.start) - math.hypot(*mv.end))
                k = j + 1
                continue
            if nxt is not None and nxt.kind == "arc":
                out.append(pending)
                pending = []
                while k < len(segs) and not (segs[k].move.kind == "line"
                                             and math.hypot(*segs[k].move.end) > math.hypot(*segs[k].move.start)):
                    k += 1  # to the test's feed-out
        k += 1
    return out


def _rewind(test: list[_Seg], u_ref: float) -> list[_Seg]:
    first = next((s.move for s in test if s.move.kind == "arc"), None)
    if first is None:
        return test
    shift = 2 * math.pi * round((u_ref - first.u_start) / (2 * math.pi))
    if shift == 0:
        return test
    return [replace(s, move=replace(s.move, u_start=s.move.u_start + shift)) if s.move.kind == "arc" else s
            for s in test]


def test_moves(
    program: Program,
    plane: str,
    *,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    index: int = 0,
    start_deg: float = 0.0,
) -> list[Move]:
    """The moves of test ``index`` (0: the first) from its feed-in to its feed-out.

    Coordinates in ``plane``'s (first, second) frame, mm from the pivot at
    ``origin`` (work coordinates, X Y Z); names as :func:`ballbar.analysis.program.moves`
    gives them (``feed_in``, ``dwell_in``, ``ccw``, ``dwell_ccw``, ``cw``,
    ``dwell_cw``, ``feed_out``; a program stop inside the test is a dwell named
    ``stop`` of infinite duration, a rapid a line named ``rapid``).  The first
    arc's start angle is unwrapped to within 180 deg of ``start_deg`` (pass
    :func:`~ballbar.analysis.program.arc_start_deg` of the plan's first direction
    to get the plan's angles), later ones continue from the arc before.
    Raises :class:`NcError` when the program holds no such test or cannot be
    cut into rest-to-rest moves.
    """
    tests = _split_tests(_segments(program, plane, origin, start_deg), start_deg)
    if not 0 <= index < len(tests):
        raise NcError(None, f"the program holds {len(tests)} test(s) (feed-in to feed-out), no test {index}")
    return [s.move for s in tests[index]]


test_moves.__test__ = False  # type: ignore[attr-defined]  # not a pytest test, whoever imports it


# --------------------------------------------------------------------------- the check


def _dist(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _geometry_ok(got: Move, want: Move, tol: float) -> list[str]:
    """Differences of one move beyond ``tol`` (mm, per coordinate); empty when it matches."""
    out: list[str] = []
    t2 = tol * math.sqrt(2.0)
    if got.kind == "dwell":
        if abs(got.duration_s - want.duration_s) > DWELL_TOL_S:
            out.append(f"lasts {got.duration_s:g} s, the plan's {want.duration_s:g} s")
        return out
    if _dist(got.start, want.start) > t2:
        out.append(f"starts at ({got.start[0]:.6f}, {got.start[1]:.6f}), the plan's "
                   f"({want.start[0]:.6f}, {want.start[1]:.6f})")
    if _dist(got.end, want.end) > t2:
        out.append(f"ends at ({got.end[0]:.6f}, {got.end[1]:.6f}), the plan's ({want.end[0]:.6f}, {want.end[1]:.6f})")
    if got.kind == "arc":
        R = want.radius
        if abs(got.radius - R) > t2:
            out.append(f"radius {got.radius:.6f} mm, the plan's {R:g} mm")
        if abs(got.u_start - want.u_start) > t2 / R:
            u_got, u_want = math.degrees(got.u_start), math.degrees(want.u_start)
            out.append(f"starts at {u_got:.6f} deg, the plan's {u_want:.6f} deg")
        if abs(got.sweep - want.sweep) > 2 * t2 / R:
            out.append(f"sweeps {math.degrees(got.sweep):.6f} deg, the plan's {math.degrees(want.sweep):.6f} deg")
    return out


def _angle_at(moves_: list[Move], profiles: list[_Profile | None], t0: list[float], t: np.ndarray) -> np.ndarray:
    """Commanded angle (rad) at times ``t`` (from the feed-in's start): arcs move it, the rest holds it."""
    first_arc = next((m for m in moves_ if m.kind == "arc"), None)
    out = np.full(t.size, first_arc.u_start if first_arc else math.nan)
    for mv, prof, ts in zip(moves_, profiles, t0, strict=True):
        if mv.kind != "arc" or prof is None:
            continue
        after = t >= ts
        s = prof.position(t[after] - ts)
        out[after] = mv.u_start + math.copysign(1.0, mv.sweep) * s / mv.radius
    return out


def _timing(test: list[_Seg], plan: TestPlan, want: list[Move], matched: list[bool], accel: float) -> list[str]:
    """Angle vs time on the data arcs and the feed-out centroid against :func:`schedule`.

    Each move runs a trapezoid from rest to rest at its own feed.  A move whose
    geometry matched the plan's within the rounding runs the plan's geometry,
    so that the comparison sees the timing (merging, stops, feeds, dwells), not
    the rounding of the coordinates, which the geometry check has bounded.
    """
    mvs: list[Move] = []
    profiles: list[_Profile | None] = []
    starts: list[float] = []
    t = 0.0
    for k, s in enumerate(test):
        mv = want[k] if matched[k] else s.move
        mvs.append(mv)
        starts.append(t)
        if mv.kind == "dwell":
            profiles.append(None)
            t += s.move.duration_s
        else:
            V = (s.feed or plan.feed_mm_min) / 60.0
            prof = _Profile(mv.length_mm, V, accel, 0.0)
            profiles.append(prof)
            t += prof.duration
    if not all(math.isfinite(x) for x in starts):
        return ["timing: not comparable (the test holds a program stop)"]
    out: list[str] = []
    V = plan.feed_mm_s
    out += [f"timing: {x}" for x in model_limits(plan, accel)]  # the plan's own breaks of the model first
    sch = schedule(plan, V, V / accel)
    fi = profiles[0]
    assert fi is not None
    t_fi = starts[0] + fi.duration / 2.0
    for d in plan.direction_list:
        name = "ccw" if d > 0 else "cw"
        rel = np.linspace(sch.data_start_s[d], sch.data_end_s[d], 2001)
        got = np.degrees(_angle_at(mvs, profiles, starts, rel + t_fi))
        exp = sch.angle_deg(plan, d, rel)
        err = np.abs(got - exp)
        k = int(np.argmax(err))
        if not err[k] <= ANGLE_TOL_DEG:
            out.append(
                f"timing: on the {name} data arc the commanded angle departs from the analyzer's schedule by "
                f"{err[k]:.6g} deg (at {rel[k]:.6f} s after the feed-in centroid: {got[k]:.6f} deg, "
                f"the schedule {exp[k]:.6f} deg)"
            )
    fo = profiles[-1]
    if fo is not None and test[-1].move.name == "feed_out":
        t_fo = starts[-1] + fo.duration / 2.0 - t_fi
        if abs(t_fo - sch.feed_out_centroid_s) > TIME_TOL_S:
            out.append(
                f"timing: the feed-out centroid comes {t_fo:.6f} s after the feed-in's, "
                f"the schedule {sch.feed_out_centroid_s:.6f} s"
            )
    return out


def _structure(test: list[_Seg], want: list[Move]) -> list[str]:
    got_names = [s.move.name for s in test]
    want_names = [m.name for m in want]
    if got_names == want_names:
        return []
    out = [f"moves: the program runs {' '.join(got_names)}; the plan {' '.join(want_names)}"]
    for a, b in itertools.pairwise(test):
        if a.move.kind == "arc" and b.move.kind == "arc" and a.move.name == b.move.name:
            out.append(f"the {a.move.name} arc stops ({a.stop_reason}); the plan runs it as one move")
    for k in range(1, len(test) - 1):
        before, m, after = test[k - 1].move, test[k].move, test[k + 1].move
        if m.kind == "dwell" and before.kind == "arc" and after.kind == "arc" and before.name == after.name:
            what = "program stop" if m.name == "stop" else "dwell"
            out.append(f"a {what} at line {test[k].blocks[0].line} splits the {before.name} arc")
    if any(s.move.name == "rapid" for s in test):
        out.append("a rapid inside the test")
    return out


def check_against_plan(
    text: str,
    dialect: str,
    plan: TestPlan,
    accel_mm_s2: float = 2000.0,
    *,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    decimals: int | None = None,
) -> list[str]:
    """Problems of the program ``text`` against ``plan``; empty when it runs exactly the plan's path and timing.

    Each test of the program (feed-in .. feed-out) is compared with
    :func:`~ballbar.analysis.program.moves`: the moves' kinds and order, end
    points, radius, start angle and sweep within the rounding (``0.6 *
    10**-decimals`` mm per coordinate, ``decimals`` read from the program unless
    given), every arc block's centre and radius, the third axis at the pivot's
    level, the feed equal to ``plan.feed_mm_min`` exactly, the dwells.  Then the
    timing: each move as a trapezoid at ``V = F / 60`` and ``accel_mm_s2`` from
    rest to rest, the commanded angle on both data arcs and the feed-out
    centroid against :func:`~ballbar.analysis.program.schedule` ``(plan, V, V / A)``
    to 1e-6 deg and 1e-6 s.  A program the interpreter refuses gives its
    :class:`NcError` message as the one problem.
    """
    o = (float(origin[0]), float(origin[1]), float(origin[2]))
    try:
        prog = interpret(text, dialect)
        first_dir = plan.direction_list[0]
        u0 = arc_start_deg(plan, first_dir)
        tests = _split_tests(_segments(prog, plan.plane, o, u0), u0)
    except NcError as err:
        return [str(err)]
    if not tests:
        return ["no test found: no feed-in (a feed move toward the pivot) followed by a feed-out"]
    dec = prog.decimals if decimals is None else decimals
    unit = 10.0**-dec
    # The pivot rounds to the grid too, and every point with it.
    tol = 0.6 * unit + max(abs(v - round(v / unit) * unit) for v in o)
    t2 = tol * math.sqrt(2.0)
    want = moves(plan)
    R = plan.radius_mm
    _, _, i3 = PLANE_INDEX[plan.plane]
    problems: list[str] = []
    for k, test in enumerate(tests):
        pre = f"test {k + 1}: " if len(tests) > 1 else ""
        out: list[str] = []
        structure = _structure(test, want)
        out += structure
        matched = [False] * len(test)
        if not structure:
            for j, (s, w) in enumerate(zip(test, want, strict=True)):
                diffs = _geometry_ok(s.move, w, tol)
                matched[j] = not diffs
                where = f" (line {s.blocks[0].line})" if s.blocks else ""
                out += [f"{w.name}{where}: {d}" for d in diffs]
        wrong_feed: dict[float | None, list[int]] = {}
        for s in test:
            for b in s.blocks:
                if b.kind in ("line", "arc") and b.feed_mm_min != plan.feed_mm_min:
                    wrong_feed.setdefault(b.feed_mm_min, []).append(b.line)
                if b.kind in ("line", "arc") and abs(b.end[i3] - o[i3]) > tol:
                    out.append(f"line {b.line}: {_AXES[i3]} {b.end[i3]:g}, the pivot's {o[i3]:g}")
                if b.kind == "arc":
                    assert b.centre is not None
                    c = _plane2(b.centre, plan.plane, o)
                    if math.hypot(*c) > t2:
                        out.append(f"line {b.line}: arc centre {math.hypot(*c):.6f} mm from the pivot")
                    for end, p in (("start", b.start), ("end", b.end)):
                        r = math.hypot(*_plane2(p, plan.plane, o))
                        if abs(r - R) > t2:
                            out.append(f"line {b.line}: arc {end} radius {r:.6f} mm, the plan's {R:g} mm")
        for f, lines in wrong_feed.items():
            out.append(f"feed {f!r} mm/min on lines {_ranges(lines)}, the plan's {plan.feed_mm_min!r}")
        out += _timing(test, plan, want, matched, accel_mm_s2) if _comparable(test) else []
        problems += [pre + p for p in dict.fromkeys(out)]
    return problems


def _ranges(lines: list[int]) -> str:
    return ", ".join(str(n) for n in lines[:6]) + (f" and {len(lines) - 6} more" if len(lines) > 6 else "")


def _comparable(test: list[_Seg]) -> bool:
    return (
        test[0].move.name == "feed_in"
        and test[-1].move.name == "feed_out"
        and all(s.move.name != "rapid" for s in test)
    )


__all__ = ["check_against_plan", "model_limits", "program_moves", "signatures", "test_moves"]
