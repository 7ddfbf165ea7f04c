"""The NC program of a ball-bar test, for FANUC, SINUMERIK, HEIDENHAIN and LinuxCNC.

:func:`generate` writes :func:`ballbar.analysis.program.moves` as a part
program, block for block, so that the timing the analyzer assumes
(:func:`~ballbar.analysis.program.schedule`: every move starts and ends at rest,
each arc is one move) is the timing the machine runs.
:mod:`ballbar.tools.ncinterp` reads the programs back and :mod:`ballbar.tools.nccheck` checks exactly that.

The program
-----------
1. Header comments: the plan, the set-up (the work offset's origin is the pivot
   ball's centre, or ``origin`` in work coordinates), feed override 100 %, and in
   the vertical planes the lowest point of the path relative to the pivot.
2. Modal settings: millimetres, absolute, the plane (G17 XY, G19 YZ, G18 ZX),
   feed per minute, no cutter compensation, spindle stopped, exact stop for
   the approach.
3. Rapid to the wait point at ``R + f`` on the first arc's start angle: first
   the horizontal axes, then Z (the approach comes from above); the third axis
   of the plane goes to the pivot's level and stays there.
4. Optional program stop (``mount_stop``) for mounting the bar.  With a
   ``signature`` (a plan of a library of several), before each feed-in: four
   radial excursions from the wait point toward the pivot (1..5 eighths of
   the feed-in) and back, each with a dwell, that tell the monitor which plan
   runs (:mod:`ballbar.analysis.plans`); none reaches within a quarter of the
   feed-in of ``R``.
5. Continuous-path mode (FANUC G64, SINUMERIK G64, LinuxCNC G64 P..): the
   tangent arc blocks of one arc blend into one move without stopping.  The
   moves that the plan starts and ends at rest are separated by dwells (also
   of 0 s), which every controller finishes at rest.
6. ``repeat`` times: feed-in at ``F``, dwell, the CCW and/or CW arc, a dwell
   after each, feed-out at ``F``; :data:`REPEAT_DWELL_S` between tests.
7. End of program.

Arcs are written in centre format, never with a radius word: I/J/K (the centre
relative to the block's start point) for FANUC, SINUMERIK and LinuxCNC (G91.1
written explicitly), ``CC`` + ``C ... DR+/DR-`` for HEIDENHAIN.  An arc of up
to 360 + 2 x 360 degrees is cut into pieces of at most 180 degrees.  Every
point is rounded once to ``decimals`` and reused: the end of a piece is the
next piece's start, a point half a turn on is the exact negative of the
rounded point (so 180-degree pieces keep their radius exactly), and the
program returns exactly to its wait point.  Only a remainder piece, whose end
is the plan's, has a rounded radius that differs from its start's (by at most
``0.71 * 10**-decimals`` mm).

Arc direction.  G02/G03 and DR-/DR+ are defined looking from the positive end
of the axis normal to the plane toward the negative (ISO 6983, DIN 66025):
seen from +Z in G17, from +Y in G18, from +X in G19.  In a right-handed frame
the rotation seen counter-clockwise from +Z carries X toward Y, from +X carries
Y toward Z, and from +Y carries Z toward X (``Z x X = Y``).  So G03/DR+ is
counter-clockwise in the plane's (first, second) frame of analysis/README.md in all
three planes, ZX included: in G18 the first axis is Z and G03 turns from Z
toward X, the direction in which the plan's angles grow.

Numbers: coordinates with exactly ``decimals`` digits (FANUC always with a
decimal point: without one, ``X100`` means 100 least increments, 0.1 mm);
HEIDENHAIN with an explicit sign.  The feed and dwell times are written
exactly (shortest form, at most 3 decimals, else :class:`GcodeError`).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from decimal import Decimal

from ballbar.analysis.errors import BallbarError
from ballbar.analysis.plan import PLANE_AXES, TestPlan
from ballbar.analysis.plans import (
    SIGNATURE_OFF_S,
    SIGNATURE_ON_S,
    SIGNATURE_REST_S,
    signature_depths_mm,
    signature_symbols,
)
from ballbar.analysis.program import arc_start_deg, moves

DIALECTS: dict[str, str] = {
    "fanuc": "FANUC 0i/30i ISO G-code (IS-B, 0.001 mm), % and O-number",
    "siemens": "SINUMERIK 808D/828D/840D sl native G-code (not ISO mode)",
    "heidenhain": "HEIDENHAIN TNC conversational (Klartext)",
    "linuxcnc": "LinuxCNC RS274NGC",
}

DEFAULT_DECIMALS: dict[str, int] = {"fanuc": 3, "siemens": 4, "heidenhain": 4, "linuxcnc": 4}

REPEAT_DWELL_S = 2.0
"""Dwell between repeated tests (s): the simulator's default stand at ``R + f``
between tests (``tail_s + lead_s``), and room for the detector, which reads the
level 0.4..0.8 s after each step."""

MAX_PIECE_DEG = 180.0  # longest arc block
ARC_RADIUS_LIMIT_MM = 0.005  # rounded end radius vs start radius: half of a typical controller alarm limit
ROUNDING_LIMIT = 0.01  # of the feed-in: the largest move of a point by rounding
EXACT_DECIMALS = 3  # feed (mm/min) and dwell (s) resolution written

# Indices into (X, Y, Z) of the plane's first, second and third axis.
PLANE_INDEX: dict[str, tuple[int, int, int]] = {"XY": (0, 1, 2), "YZ": (1, 2, 0), "ZX": (2, 0, 1)}
PLANE_G: dict[str, str] = {"XY": "17", "YZ": "19", "ZX": "18"}
TOOL_AXIS: dict[str, str] = {"XY": "Z", "YZ": "X", "ZX": "Y"}
AXES = ("X", "Y", "Z")
CENTRE_WORDS = ("I", "J", "K")

WORK_OFFSETS: dict[str, re.Pattern[str]] = {
    "fanuc": re.compile(r"G5[4-9]|G54\.1 ?P([1-9]\d{0,2})"),
    "siemens": re.compile(r"G5[4-7]|G5(0[5-9]|[1-9]\d)"),
    "linuxcnc": re.compile(r"G5[4-9]|G59\.[1-3]"),
}

Point3 = tuple[int, int, int]  # machine X, Y, Z in units of 10**-decimals mm


class GcodeError(BallbarError, ValueError):
    """The requested program cannot be written (dialect, plane, resolution, repeat)."""


# --------------------------------------------------------------------------- numbers


def exact_number(x: float, what: str, max_decimals: int = EXACT_DECIMALS) -> str:
    """``x`` in its shortest exact decimal form ("1000", "1234.5", "0.5"), never rounded.

    Raises :class:`GcodeError` when ``x`` needs more than ``max_decimals`` decimals.
    """
    if not math.isfinite(x):
        raise GcodeError(f"{what} must be finite, not {x!r}")
    d = Decimal(repr(float(x)))
    exp = d.as_tuple().exponent
    assert isinstance(exp, int)
    if -exp > max_decimals:
        raise GcodeError(f"{what} {x!r} cannot be written exactly with {max_decimals} decimals")
    text = format(d.quantize(Decimal(1)) if d == d.to_integral_value() else d.normalize(), "f")
    return "0" if text in ("-0", "0") else text


def format_units(units: int, decimals: int, *, point: bool = False, sign: bool = False) -> str:
    """An integer number of ``10**-decimals`` mm as a fixed-point string."""
    neg = units < 0
    a = abs(units)
    body = f"{a // 10**decimals}.{a % 10**decimals:0{decimals}d}" if decimals > 0 else f"{a}" + ("." if point else "")
    if neg:
        return "-" + body
    return ("+" if sign else "") + body


# --------------------------------------------------------------------------- geometry


def pieces_deg(total_deg: float) -> list[float]:
    """Split a sweep (degrees, > 0) into arc blocks of at most 180 degrees.

    Whole half-turns first (their ends alternate between a point and its exact
    negative); a remainder below 90 degrees shares a half-turn evenly with the
    last one, so that no piece is shorter than 90 degrees unless the whole arc
    is: a tiny piece's chord could round to nothing, and an arc block whose end
    equals its start is a full circle.
    """
    n = math.floor(total_deg / MAX_PIECE_DEG + 1e-12)
    r = total_deg - n * MAX_PIECE_DEG
    if r <= 1e-9:
        return [MAX_PIECE_DEG] * n
    if n == 0:
        return [r]
    if r < 90.0:
        half = (MAX_PIECE_DEG + r) / 2.0
        return [MAX_PIECE_DEG] * (n - 1) + [half, half]
    return [MAX_PIECE_DEG] * n + [r]


def _key(deg: float) -> float:
    return round(deg % 360.0, 9) % 360.0


class _Points:
    """Rounded points of the test, each computed once (see the module docstring)."""

    def __init__(self, plan: TestPlan, decimals: int, origin: tuple[float, float, float]) -> None:
        self.plan = plan
        self.decimals = decimals
        self.scale = 10**decimals
        self.idx = PLANE_INDEX[plan.plane]
        self.origin = origin
        self.origin_u: Point3 = (
            round(origin[0] * self.scale),
            round(origin[1] * self.scale),
            round(origin[2] * self.scale),
        )
        self.limit = ROUNDING_LIMIT * plan.feed_in_mm
        shift = math.dist([u / self.scale for u in self.origin_u], origin)
        if shift > self.limit:
            raise GcodeError(self._too_coarse("the pivot (origin)", shift))
        self._cache: dict[tuple[float, float], tuple[int, int]] = {}

    def _too_coarse(self, where: str, shift: float) -> str:
        return (
            f"decimals={self.decimals} moves {where} by {shift:.4g} mm, more than 1 % of the "
            f"feed-in ({self.limit:.4g} mm): use more decimals"
        )

    def rel(self, radius: float, deg: float) -> tuple[int, int]:
        """The point at ``radius`` and angle ``deg``, (first, second) units from the pivot."""
        key = (radius, _key(deg))
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        u = math.radians(deg)
        exact = (radius * math.cos(u), radius * math.sin(u))
        p = (round(exact[0] * self.scale), round(exact[1] * self.scale))
        o1, o2 = self.origin[self.idx[0]], self.origin[self.idx[1]]
        a1, a2 = self.origin_u[self.idx[0]] + p[0], self.origin_u[self.idx[1]] + p[1]
        shift = math.hypot(a1 / self.scale - (o1 + exact[0]), a2 / self.scale - (o2 + exact[1]))
        if shift > self.limit:
            raise GcodeError(self._too_coarse(f"the point at {deg:g} deg, radius {radius:g} mm,", shift))
        self._cache[key] = p
        self._cache.setdefault((radius, _key(deg + 180.0)), (-p[0], -p[1]))
        return p

    def abs3(self, rel: tuple[int, int]) -> Point3:
        out = list(self.origin_u)
        out[self.idx[0]] += rel[0]
        out[self.idx[1]] += rel[1]
        return (out[0], out[1], out[2])


@dataclass(frozen=True)
class _Op:
    """One step of the program in machine coordinates (units of 10**-decimals mm)."""

    kind: str  # "line" | "arc" | "dwell" | "comment"
    end: Point3 = (0, 0, 0)
    start: Point3 = (0, 0, 0)
    centre: Point3 = (0, 0, 0)
    direction: int = 0
    seconds: float = 0.0
    text: str = ""
    first_feed: bool = False


def _signature_ops(plan: TestPlan, pts: _Points, code: int, name: str | None) -> list[_Op]:
    """The plan's signature (analysis/plans.py): from the wait point, four excursions toward the pivot and back,
    each with its dwell, then the rest before the feed-in."""
    R, f = plan.radius_mm, plan.feed_in_mm
    u = arc_start_deg(plan, plan.direction_list[0])
    wait = pts.abs3(pts.rel(R + f, u))
    depths = signature_depths_mm(code, f)
    ops = [_Op("comment", text=f"signature {code}" + (f" of plan {name}" if name else "")
               + ": " + " ".join(f"{d:g}" for d in depths) + " mm toward the pivot")]
    for k, depth in enumerate(depths):
        point = pts.abs3(pts.rel(R + f - depth, u))
        ops += [_Op("line", end=point, start=wait, first_feed=k == 0), _Op("dwell", seconds=SIGNATURE_ON_S),
                _Op("line", end=wait, start=point),
                _Op("dwell", seconds=SIGNATURE_REST_S if k == len(depths) - 1 else SIGNATURE_OFF_S)]
    return ops


def _test_ops(plan: TestPlan, pts: _Points) -> tuple[Point3, list[_Op], Point3]:
    """The wait point, the ops from feed-in to feed-out, and where the feed-out ends."""
    R, f = plan.radius_mm, plan.feed_in_mm
    dirs = plan.direction_list
    u = arc_start_deg(plan, dirs[0])
    wait = pts.abs3(pts.rel(R + f, u))
    start = pts.abs3(pts.rel(R, u))
    centre = pts.origin_u
    ops = [
        _Op("comment", text="feed-in"),
        _Op("line", end=start, start=wait, first_feed=True),
        _Op("dwell", seconds=plan.dwell_s),
    ]
    here = start
    for d in dirs:
        ops.append(_Op("comment", text=f"{'CCW' if d > 0 else 'CW'} arc, {plan.arc_deg:g} deg"))
        for piece in pieces_deg(plan.arc_deg):
            u += d * piece
            end = pts.abs3(pts.rel(R, u))
            r0 = math.dist(here, centre) / pts.scale
            r1 = math.dist(end, centre) / pts.scale
            if abs(r1 - r0) > ARC_RADIUS_LIMIT_MM:
                raise GcodeError(
                    f"decimals={pts.decimals}: an arc block's rounded end radius differs from its start's "
                    f"by {abs(r1 - r0):.4g} mm (limit {ARC_RADIUS_LIMIT_MM} mm): use more decimals"
                )
            ops.append(_Op("arc", end=end, start=here, centre=centre, direction=d))
            here = end
        ops.append(_Op("dwell", seconds=plan.dwell_s))
    out = pts.abs3(pts.rel(R + f, u))
    ops.append(_Op("comment", text="feed-out"))
    ops.append(_Op("line", end=out, start=here))
    return wait, ops, out


# --------------------------------------------------------------------------- comments


@dataclass(frozen=True)
class PathDepth:
    """How far the program's path goes below the pivot, from the program's own rounded points.

    ``low_mm``: the lowest Z of the whole path (wait point, feed-in, arcs,
    feed-out) relative to the pivot, mm.  ``arc_low_mm``: the arcs' lowest Z;
    ``arc_below_deg``: how far below the pivot's level that is, as an angle
    about the pivot (0 or less: the arcs stay at or above it);
    ``arc_low_at_deg``: the plan angles (degrees, counter-clockwise from the
    plane's first axis) where the arcs reach it.
    """

    low_mm: float
    arc_low_mm: float
    arc_below_deg: float
    arc_low_at_deg: tuple[float, ...]


def _plane_rel(p: Point3, pts: _Points) -> tuple[int, int]:
    i, j = pts.idx[0], pts.idx[1]
    return p[i] - pts.origin_u[i], p[j] - pts.origin_u[j]


def _depth(plan: TestPlan, pts: _Points, wait: Point3, ops: list[_Op]) -> PathDepth:
    """:class:`PathDepth` of one test's ops (see :func:`path_depth`)."""
    s = pts.scale
    zi = 2  # Z in machine (X, Y, Z)

    def z_mm(p: Point3) -> float:
        return (p[zi] - pts.origin_u[zi]) / s

    def angle(p: Point3) -> float:
        a, b = _plane_rel(p, pts)
        return math.degrees(math.atan2(b, a))

    bottom = 270.0 if plan.plane == "YZ" else 180.0  # the plan angle where Z = -R
    line_z = [z_mm(wait)] + [z_mm(op.end) for op in ops if op.kind == "line"]
    arc_pts: list[tuple[float, float]] = []  # (Z mm, plan angle deg) of the arcs' ends and bottoms
    for op in ops:
        if op.kind != "arc":
            continue
        a0, a1 = angle(op.start), angle(op.end)
        arc_pts += [(z_mm(op.start), a0), (z_mm(op.end), a1)]
        lo, hi = (a0, a1) if op.direction > 0 else (a1, a0)
        sweep = (hi - lo) % 360.0 or 360.0
        if (bottom - lo) % 360.0 < sweep:
            r = math.dist(op.start, op.centre) / s
            arc_pts.append((z_mm(op.centre) - r, bottom))
    if not arc_pts:
        return PathDepth(min(line_z), 0.0, 0.0, ())
    arc_low = min(z for z, _ in arc_pts)
    def plan_deg(a: float) -> float:
        """The plan's angle of a rounded point (start .. start + 360), to 0.01 deg (the rounding moves it less)."""
        d = (a - plan.start_deg) % 360.0
        return round(plan.start_deg + (d - 360.0 if d > 359.99 else d), 2) + 0.0

    at = sorted({plan_deg(a) for z, a in arc_pts if z <= arc_low + 0.5 / s})
    radius = plan.radius_mm
    below = math.degrees(math.asin(max(-1.0, min(1.0, -arc_low / radius))))
    return PathDepth(min([*line_z, arc_low]), arc_low, below, tuple(at))


def path_depth(
    plan: TestPlan, decimals: int | None = None, origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> PathDepth:
    """How far the path of the program :func:`generate` writes goes below the pivot (Z).

    Computed from the same rounded points the program moves through (the
    dialect only sets the default ``decimals``: FANUC's 3).  In ``XY`` nothing
    moves in Z: all zeros.
    """
    if plan.plane == "XY":
        return PathDepth(0.0, 0.0, 0.0, ())
    dec = DEFAULT_DECIMALS["fanuc"] if decimals is None else decimals
    pts = _Points(plan, dec, origin)
    wait, ops, _end = _test_ops(plan, pts)
    return _depth(plan, pts, wait, ops)


def lowest_point_mm(plan: TestPlan) -> float:
    """Lowest Z of the path (wait point, arcs, feed-out) relative to the pivot, mm (:func:`path_depth`)."""
    return path_depth(plan).low_mm


def _header_lines(
    plan: TestPlan, dialect: str, decimals: int, origin: tuple[float, float, float], work_offset: str | None,
    repeat: int, mount_stop: bool, depth: PathDepth, signature: int | None = None, plan_name: str | None = None,
) -> list[str]:
    first, second = plan.axes
    third = AXES[PLANE_INDEX[plan.plane][2]]
    dirs = {"both": "CCW then CW", "ccw": "CCW only", "cw": "CW only"}[plan.directions]
    lines = [
        "Ball-bar circular test to ISO 230-4",
        "Written by ballbar.tools.gcode",
        f"Plane {plan.plane}: first axis {first}, second axis {second}",
        f"Radius R {plan.radius_mm:g} mm, "
        f"feed F {plan.feed_mm_min:g} mm/min",
        f"Start {plan.start_deg:g} deg, overshoot {plan.overshoot_deg:g} deg, data arc {plan.data_arc_deg:g} deg, "
        f"arc {plan.arc_deg:g} deg, {dirs}",
        f"Feed-in {plan.feed_in_mm:g} mm, dwell {plan.dwell_s:g} s, {repeat} test{'s' if repeat > 1 else ''}"
        + (f", {REPEAT_DWELL_S:g} s between tests" if repeat > 1 else ""),
        f"Angles counter-clockwise from {first} toward {second}",
        f"Coordinates to {decimals} decimals",
    ]
    offset = work_offset or ("the active preset" if dialect == "heidenhain" else "the active work offset")
    if any(origin):
        o = " ".join(f"{a}{v:g}" for a, v in zip(AXES, origin, strict=True))
        lines.append(f"Pivot ball centre at {o} in the work coordinates of {offset}")
    else:
        lines.append(f"The origin of {offset} must be the pivot ball's centre")
    lines += [
        "The spindle ball's centre is the controlled point: the spindle cup's tool length must be active",
        f"{third} stays at the pivot's {third} {origin[PLANE_INDEX[plan.plane][2]]:g}",
        "Spindle stopped. Feed override must be 100 %: the analyzer times the angles from F",
        "Approach: rapid in the horizontal axes, then in Z: start above the pivot, clear of the set-up",
    ]
    if mount_stop:
        lines.append("At the program stop: mount the bar, then restart")
    if signature is not None:
        lines.append(f"Plan {plan_name}: before each feed-in its signature {signature}, four short moves toward the "
                     "pivot and back, tells the monitor which plan runs" if plan_name else
                     f"Before each feed-in the signature {signature}: four short moves toward the pivot and back")
    if plan.plane != "XY":
        lines.append(f"Lowest point of the path: Z {depth.low_mm:+.{decimals}f} mm relative to the pivot")
        if depth.low_mm < 0.0:
            lines.append(f"WARNING: the path goes {-depth.low_mm:.{decimals}f} mm below the pivot")
            if depth.arc_below_deg > 0.0:
                at = " and ".join(f"{a:+g}" for a in depth.arc_low_at_deg)
                lines.append(
                    f"The arcs go {depth.arc_below_deg:.2f} deg below the pivot's level, "
                    f"to Z {depth.arc_low_mm:+.{decimals}f} mm at {at} deg"
                )
            lines.append("Check that the spindle and the bar clear the table and the pivot's mount there")
    return lines


# --------------------------------------------------------------------------- writers


class _Writer:
    """Renders ops in one dialect; ``self.out`` collects the lines."""

    dialect = ""

    def __init__(self, plan: TestPlan, decimals: int) -> None:
        self.plan = plan
        self.decimals = decimals
        self.out: list[str] = []
        self.idx = PLANE_INDEX[plan.plane]

    def num(self, units: int) -> str:
        return format_units(units, self.decimals)

    def comment(self, text: str) -> None:
        raise NotImplementedError

    def emit(self, line: str) -> None:
        self.out.append(line)

    def words(self, p: Point3, axes: tuple[int, ...]) -> str:
        return " ".join(f"{AXES[i]}{self.num(p[i])}" for i in sorted(axes))


class _IsoWriter(_Writer):
    """FANUC, SINUMERIK and LinuxCNC share the ISO 6983 word structure."""

    g0, g1, g2, g3 = "G00", "G01", "G02", "G03"
    units_g = "G21"
    exact_mode = "G61"
    continuous_mode = "G64"
    end_code = "M30"
    stop_code = "M00"
    spindle_stop = "M05"

    def prologue(self, name: str | None) -> None:
        if name:  # no program-number word in these dialects: the name is a comment
            self.comment(f"Program {name}")

    def modal(self) -> str:
        return f"{self.units_g} G90 G{PLANE_G[self.plan.plane]} G94 G40"

    def dwell(self, seconds: float) -> str:
        raise NotImplementedError

    def feed(self, f: float) -> str:
        return "F" + exact_number(f, "feed")

    def override_off(self) -> None:
        pass

    def override_on(self) -> None:
        pass

    def epilogue(self) -> None:
        pass

    def render(
        self, name: str | None, header: list[str], work_offset: str | None, mount_stop: bool,
        wait: Point3, tests: list[list[_Op]],
    ) -> None:
        self.prologue(name)
        for h in header:
            self.comment(h)
        self.emit(self.modal())
        if work_offset:
            self.emit(work_offset)
        self.emit(self.spindle_stop)
        self.emit(self.exact_mode)
        horizontal = tuple(i for i in range(3) if i != 2)
        self.emit(f"{self.g0} {self.words(wait, horizontal)}")
        self.emit(f"{self.g0} {self.words(wait, (2,))}")
        if mount_stop:
            self.comment("Mount the bar, then restart")
            self.emit(self.stop_code)
        self.override_off()
        self.continuous()
        plane_axes = (self.idx[0], self.idx[1])
        for k, ops in enumerate(tests):
            if len(tests) > 1:
                self.comment(f"Test {k + 1} of {len(tests)}")
                if k > 0:
                    self.emit(self.dwell(REPEAT_DWELL_S))
            for op in ops:
                if op.kind == "comment":
                    self.comment(op.text)
                elif op.kind == "line":
                    tail = f" {self.feed(self.plan.feed_mm_min)}" if op.first_feed else ""
                    self.emit(f"{self.g1} {self.words(op.end, plane_axes)}{tail}")
                elif op.kind == "dwell":
                    self.emit(self.dwell(op.seconds))
                else:
                    g = self.g3 if op.direction > 0 else self.g2
                    inc = " ".join(
                        f"{CENTRE_WORDS[i]}{self.num(op.centre[i] - op.start[i])}" for i in sorted(plane_axes)
                    )
                    self.emit(f"{g} {self.words(op.end, plane_axes)} {inc}")
        self.override_on()
        self.emit(self.end_code)
        self.epilogue()

    def continuous(self) -> None:
        self.emit(self.continuous_mode)


class _Fanuc(_IsoWriter):
    dialect = "fanuc"

    def __init__(self, plan: TestPlan, decimals: int, number: int) -> None:
        super().__init__(plan, decimals)
        self.number = number

    def num(self, units: int) -> str:
        return format_units(units, self.decimals, point=True)

    def comment(self, text: str) -> None:
        self.emit(f"({_fanuc_text(text)})")

    def prologue(self, name: str | None) -> None:
        self.emit("%")
        self.emit(f"O{self.number:04d} (BALLBAR)")

    def modal(self) -> str:
        return super().modal() + " G80"

    def feed(self, f: float) -> str:
        text = exact_number(f, "feed")
        return f"F{text}" + ("" if "." in text else ".")

    def dwell(self, seconds: float) -> str:
        text = exact_number(seconds, "dwell")
        return f"G04 X{text}" + ("" if "." in text else ".")

    def continuous(self) -> None:
        self.emit("G64 (CUTTING MODE: THE ARC BLOCKS BLEND)")

    def epilogue(self) -> None:
        self.emit("%")


class _Siemens(_IsoWriter):
    dialect = "siemens"
    g0, g1, g2, g3 = "G0", "G1", "G2", "G3"
    units_g = "G71"
    exact_mode = "G60"
    stop_code = "M0"
    spindle_stop = "M5"

    def comment(self, text: str) -> None:
        self.emit(f"; {_ascii(text)}")

    def dwell(self, seconds: float) -> str:
        return f"G4 F{exact_number(seconds, 'dwell')}"

    def continuous(self) -> None:
        self.emit("G64 ; continuous path: the arc blocks blend")


class _LinuxCnc(_IsoWriter):
    dialect = "linuxcnc"
    g0, g1, g2, g3 = "G0", "G1", "G2", "G3"
    exact_mode = "G61.1"
    end_code = "M2"
    stop_code = "M0"
    spindle_stop = "M5"
    path_tolerance = "0.005"  # mm; tangent blocks need none, but G64 without P may cut corners at will

    def comment(self, text: str) -> None:
        self.emit(f"({_ascii(text).replace('(', '[').replace(')', ']')})")

    def modal(self) -> str:
        return super().modal() + " G80 G91.1"

    def dwell(self, seconds: float) -> str:
        return f"G4 P{exact_number(seconds, 'dwell')}"

    def override_off(self) -> None:
        self.emit("M49 (feed and spindle override off for the test)")

    def override_on(self) -> None:
        self.emit("M48 (overrides back on)")

    def continuous(self) -> None:
        self.emit(f"G64 P{self.path_tolerance} (continuous path: the arc blocks blend)")


class _Heidenhain(_Writer):
    """HEIDENHAIN conversational: numbered blocks from 0, BEGIN PGM .. END PGM."""

    dialect = "heidenhain"

    def num(self, units: int) -> str:
        return format_units(units, self.decimals, sign=True)

    def emit(self, line: str) -> None:
        self.out.append(f"{len(self.out)} {line}")

    def comment(self, text: str) -> None:
        self.emit(f"; {_ascii(text)}")

    def dwell(self, seconds: float) -> None:
        self.emit("CYCL DEF 9.0 DWELL TIME")
        self.emit(f"CYCL DEF 9.1 DWELL {exact_number(seconds, 'dwell')}")

    def render(self, name: str, header: list[str], mount_stop: bool, wait: Point3, tests: list[list[_Op]]) -> None:
        self.emit(f"BEGIN PGM {name} MM")
        for h in header:
            self.comment(h)
        self.emit(f"TOOL CALL {TOOL_AXIS[self.plan.plane]}")
        horizontal = (0, 1)
        self.emit(f"L {self.words(wait, horizontal)} R0 FMAX")
        self.emit(f"L {self.words(wait, (2,))} R0 FMAX")
        if mount_stop:
            self.comment("Mount the bar, then restart")
            self.emit("STOP")
        plane_axes = (self.idx[0], self.idx[1])
        feed = exact_number(self.plan.feed_mm_min, "feed")
        for k, ops in enumerate(tests):
            if len(tests) > 1:
                self.comment(f"Test {k + 1} of {len(tests)}")
                if k > 0:
                    self.dwell(REPEAT_DWELL_S)
            pole_set = False
            for op in ops:
                if op.kind == "comment":
                    self.comment(op.text)
                elif op.kind == "line":
                    tail = f" F{feed}" if op.first_feed else ""
                    self.emit(f"L {self.words(op.end, plane_axes)} R0{tail}")
                elif op.kind == "dwell":
                    self.dwell(op.seconds)
                else:
                    if not pole_set:
                        self.emit(f"CC {self.words(op.centre, plane_axes)}")
                        pole_set = True
                    self.emit(f"C {self.words(op.end, plane_axes)} DR{'+' if op.direction > 0 else '-'}")
        self.emit(f"END PGM {name} MM")


def _ascii(text: str) -> str:
    return text.replace("°", " deg").encode("ascii", "replace").decode("ascii")


_FANUC_COMMENT_OK = re.compile(r"[^A-Z0-9 .,+\-*/=:#']")


def _fanuc_text(text: str) -> str:
    """Upper case, only characters every FANUC shows in a comment (no %, no nested parentheses, no ;)."""
    t = _ascii(text).upper().replace("%", " PERCENT")
    t = re.sub(r" +", " ", _FANUC_COMMENT_OK.sub(" ", t)).strip()
    return re.sub(r" ([.,:])", r"\1", t)  # a character taken out before punctuation leaves no stray space


# --------------------------------------------------------------------------- entry point


def _fanuc_number(program_name: str | None) -> int:
    if program_name is None:
        return 2304  # after ISO 230-4
    m = re.fullmatch(r"[Oo]?(\d{1,4})", program_name.strip())
    if not m or not 1 <= int(m.group(1)) <= 9999:
        raise GcodeError(f"a FANUC program name is an O-number O1..O9999, not {program_name!r}")
    return int(m.group(1))


def _heidenhain_name(program_name: str | None) -> str:
    name = program_name or "BALLBAR"
    if not re.fullmatch(r"[A-Za-z0-9_\-]{1,32}", name):
        raise GcodeError(f"a HEIDENHAIN program name is 1..32 letters, digits, _ or -, not {name!r}")
    return name


def generate(
    plan: TestPlan,
    dialect: str,
    *,
    decimals: int | None = None,
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0),
    work_offset: str | None = None,
    program_name: str | None = None,
    mount_stop: bool = True,
    repeat: int = 1,
    signature: int | None = None,
    plan_name: str | None = None,
) -> str:
    """The NC program of ``plan`` for ``dialect`` (one of :data:`DIALECTS`), as text ending in a newline.

    ``decimals``: digits after the decimal point of every coordinate, 0..6
    (default :data:`DEFAULT_DECIMALS`: FANUC 3 for IS-B, the others 4).
    ``origin``: the pivot ball's centre in work coordinates (mm, X Y Z).
    ``work_offset``: a work offset to select (FANUC ``G54``..``G59``, ``G54.1 P1``;
    SINUMERIK ``G54``..``G57``, ``G505``..``G599``; LinuxCNC ``G54``..``G59.3``);
    HEIDENHAIN uses the active preset.  ``program_name``: FANUC O-number
    (default O2304), HEIDENHAIN ``BEGIN PGM`` name (default BALLBAR), a comment
    elsewhere.  ``mount_stop``: a program stop after the approach for mounting
    the bar.  ``repeat``: tests in a row (feed-in .. feed-out), with
    :data:`REPEAT_DWELL_S` between them; needs a program that ends where it
    starts.  ``signature``: the code of the plan in its library
    (:mod:`ballbar.analysis.plans`), written before each feed-in so that the
    monitor knows which plan runs; ``plan_name`` names it in the comments.
    Raises :class:`GcodeError` for a request that cannot be met.
    """
    if dialect not in DIALECTS:
        raise GcodeError(f"unknown dialect {dialect!r} (known: {', '.join(DIALECTS)})")
    if plan.plane not in PLANE_AXES:
        raise GcodeError(f"plane must be one of XY, YZ, ZX, not {plan.plane!r}")
    dec = DEFAULT_DECIMALS[dialect] if decimals is None else decimals
    if isinstance(dec, bool) or not isinstance(dec, int) or not 0 <= dec <= 6:
        raise GcodeError(f"decimals must be an integer within 0..6, not {decimals!r}")
    if len(origin) != 3 or not all(isinstance(v, int | float) and math.isfinite(v) for v in origin):
        raise GcodeError(f"origin must be three finite numbers (X, Y, Z in mm), not {origin!r}")
    origin = (float(origin[0]), float(origin[1]), float(origin[2]))
    if isinstance(repeat, bool) or not isinstance(repeat, int) or repeat < 1:
        raise GcodeError(f"repeat must be an integer >= 1, not {repeat!r}")
    if work_offset is not None:
        work_offset = " ".join(work_offset.upper().split())
        if dialect == "heidenhain":
            raise GcodeError(
                "HEIDENHAIN: activate the pivot's preset in the preset table before the run; "
                "work_offset is for the ISO dialects"
            )
        if not WORK_OFFSETS[dialect].fullmatch(work_offset):
            raise GcodeError(f"{dialect}: unknown work offset {work_offset!r}")
    if repeat > 1:
        path = moves(plan)
        if math.dist(path[0].start, path[-1].end) > 1e-9 * plan.radius_mm:
            raise GcodeError(
                "repeat > 1 needs a test that ends where it starts (both directions, or whole turns): "
                f"this one ends {plan.arc_deg:g} deg from its start"
            )
    # Fail on the dwell and feed before writing anything.
    exact_number(plan.feed_mm_min, "feed")
    exact_number(plan.dwell_s, "dwell")

    if signature is not None:
        try:
            signature_symbols(signature)
        except BallbarError as err:
            raise GcodeError(str(err)) from None
    pts = _Points(plan, dec, origin)
    wait = (0, 0, 0)
    tests: list[list[_Op]] = []
    for _ in range(repeat):
        wait, ops, _end = _test_ops(plan, pts)
        depth = PathDepth(0.0, 0.0, 0.0, ()) if plan.plane == "XY" else _depth(plan, pts, wait, ops)
        if signature is not None:
            ops = _signature_ops(plan, pts, signature, plan_name) + ops
        tests.append(ops)
    header = _header_lines(plan, dialect, dec, origin, work_offset, repeat, mount_stop, depth, signature, plan_name)
    writer: _Writer
    if dialect == "heidenhain":
        hw = _Heidenhain(plan, dec)
        hw.render(_heidenhain_name(program_name), header, mount_stop, wait, tests)
        writer = hw
    else:
        iso: _IsoWriter
        if dialect == "fanuc":
            iso = _Fanuc(plan, dec, _fanuc_number(program_name))
        elif dialect == "siemens":
            iso = _Siemens(plan, dec)
        else:
            iso = _LinuxCnc(plan, dec)
        iso.render(program_name, header, work_offset, mount_stop, wait, tests)
        writer = iso
    return "\n".join(writer.out) + "\n"


__all__ = [
    "DEFAULT_DECIMALS", "DIALECTS", "REPEAT_DWELL_S", "GcodeError", "PathDepth", "generate", "lowest_point_mm",
    "path_depth", "pieces_deg",
]
