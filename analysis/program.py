"""The test program of analysis/README.md as a list of moves, and its timing.

Coordinates are in the plane's frame (first axis, second axis), in millimetres,
relative to the pivot.  Angles are radians internally.

Timing model.  Every move starts and ends at rest.  For any acceleration profile
that is symmetric (acceleration mirrored by deceleration) and reaches the path
feed ``V``, a move of length ``s`` lasts ``s / V + c``; ``c`` is the move's
overhead (``V / A`` for a trapezoid of acceleration ``A``), and in the constant
speed part the path position is ``V * (t - t_start - c / 2)``.  A move shorter
than ``V c`` (``V^2 / A``: at high feeds, the 1.5 mm feed-in) never reaches
``V``; taken as a trapezoid's triangle it lasts ``2 sqrt(s c / V)``
(:func:`move_duration`).  The data arcs must run at ``V``: an overshoot
shorter than ``V c / 2`` breaks the model (:func:`model_limits`).  The analyzer
estimates ``V`` and ``c`` (:mod:`ballbar.analysis.timing`); the simulator runs a
real profile.  The schedule below is that model's prediction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .plan import TestPlan

MoveKind = Literal["line", "arc", "dwell"]

ACCEL_SHARE = 0.8  # a move's shape showing less than this share of the overhead as acceleration: the rest waits


@dataclass(frozen=True)
class Move:
    """One block of the program.

    ``line``: straight from ``start`` to ``end``.  ``arc``: about the pivot at
    radius ``radius`` from angle ``u_start`` through signed ``sweep``
    (positive CCW).  ``dwell``: standing at ``start`` for ``duration_s``.
    """

    kind: MoveKind
    name: str
    start: tuple[float, float]
    end: tuple[float, float]
    radius: float = 0.0
    u_start: float = 0.0
    sweep: float = 0.0
    duration_s: float = 0.0

    @property
    def length_mm(self) -> float:
        if self.kind == "line":
            return math.dist(self.start, self.end)
        if self.kind == "arc":
            return abs(self.sweep) * self.radius
        return 0.0

    def point_at(self, s: np.ndarray) -> np.ndarray:
        """Commanded position at path length ``s`` (clipped to the move), shape (n, 2)."""
        s = np.clip(np.asarray(s, dtype=float), 0.0, self.length_mm)
        if self.kind == "line":
            L = self.length_mm
            frac = s / L if L > 0 else np.zeros_like(s)
            p0, p1 = np.array(self.start), np.array(self.end)
            return p0 + frac[:, None] * (p1 - p0)
        if self.kind == "arc":
            u = self.u_start + math.copysign(1.0, self.sweep) * s / self.radius
            return self.radius * np.column_stack([np.cos(u), np.sin(u)])
        return np.broadcast_to(np.array(self.start), (s.size, 2)).copy()


def _polar(r: float, u: float) -> tuple[float, float]:
    return (r * math.cos(u), r * math.sin(u))


def arc_start_deg(plan: TestPlan, direction: int) -> float:
    """Where the arc of ``direction`` starts (degrees): CCW at ``u0``, CW at ``u0 + a + 2o``."""
    return plan.start_deg if direction > 0 else plan.start_deg + plan.arc_deg


def data_start_deg(plan: TestPlan, direction: int) -> float:
    """First angle of the data arc in the direction of travel (analysis/README.md, "The angle of each sample")."""
    if direction > 0:
        return plan.start_deg + plan.overshoot_deg
    return plan.start_deg + plan.overshoot_deg + plan.data_arc_deg


def moves(plan: TestPlan) -> list[Move]:
    """The program: wait, feed-in, dwell, arcs with dwells, feed-out.

    With ``directions = "cw"`` the test starts where a CCW arc would have ended,
    ``u0 + a + 2o``, so that the data arc covers the same angles.
    """
    R, f = plan.radius_mm, plan.feed_in_mm
    dirs = plan.direction_list
    u_first = math.radians(arc_start_deg(plan, dirs[0]))
    out: list[Move] = []
    p_out = _polar(R + f, u_first)
    p_on = _polar(R, u_first)
    out.append(Move("line", "feed_in", p_out, p_on))
    out.append(Move("dwell", "dwell_in", p_on, p_on, duration_s=plan.dwell_s))
    u = u_first
    sweep = math.radians(plan.arc_deg)
    for d in dirs:
        name = "ccw" if d > 0 else "cw"
        u_end = u + d * sweep
        out.append(Move("arc", name, _polar(R, u), _polar(R, u_end), R, u, d * sweep))
        out.append(Move("dwell", f"dwell_{name}", _polar(R, u_end), _polar(R, u_end), duration_s=plan.dwell_s))
        u = u_end
    out.append(Move("line", "feed_out", _polar(R, u), _polar(R + f, u)))
    return out


@dataclass(frozen=True)
class Schedule:
    """Predicted times (s) of one test, relative to the feed-in's centroid time.

    The centroid is the mean time of the feed-in's length change: what the
    detector measures, whatever the acceleration profile and (linear) servo.
    """

    feed_mm_s: float
    overhead_s: float
    data_start_s: dict[int, float]  # per direction: when the data arc begins
    data_end_s: dict[int, float]
    arc_start_s: dict[int, float]  # constant-speed extrapolation of the arc start
    feed_out_centroid_s: float

    def angle_deg(self, plan: TestPlan, direction: int, t_rel: np.ndarray) -> np.ndarray:
        """Commanded angle (degrees) at times ``t_rel`` (relative to the feed-in centroid)."""
        u_ds = data_start_deg(plan, direction)
        tau = np.asarray(t_rel, dtype=float) - self.data_start_s[direction]
        return u_ds + direction * np.degrees(self.feed_mm_s * tau / plan.radius_mm)


def move_duration(length_mm: float, feed_mm_s: float, overhead_s: float) -> float:
    """Rest-to-rest duration of a move: ``s / V + c`` when it reaches the feed (``s >= V c``), else the
    triangle ``2 sqrt(s c / V)`` of a trapezoid with ``A = V / c`` (the two agree at ``s = V c``)."""
    if overhead_s <= 0.0 or length_mm >= feed_mm_s * overhead_s:
        return length_mm / feed_mm_s + overhead_s
    return 2.0 * math.sqrt(length_mm * overhead_s / feed_mm_s)


def short_move_duration(length_mm: float, feed_mm_s: float, overhead_s: float, smooth_share: float = 0.0) -> float:
    """Rest-to-rest duration of a move whose shape takes ``overhead_s``, where it may be too short to reach the
    feed: between the trapezoid's triangle ``2 sqrt(s c / V)`` (all of ``c`` accelerates: ``smooth_share`` 0)
    and ``s / V + c`` (the trapezoid averaged over ``c``, a jerk limit's S-curve or a filter after
    interpolation, lasts that whether it reaches the feed or not: 1), at ``smooth_share`` of the way; the two
    differ by ``(sqrt(s / V) - sqrt(c))^2``.  A move that reaches the feed lasts ``s / V + c`` either way."""
    if overhead_s <= 0.0 or length_mm >= feed_mm_s * overhead_s:
        return length_mm / feed_mm_s + overhead_s
    q = min(max(smooth_share, 0.0), 1.0)
    tri = 2.0 * math.sqrt(length_mm * overhead_s / feed_mm_s)
    return tri + q * (length_mm / feed_mm_s + overhead_s - tri)


def feed_in_half(f: float, V: float, c: float, accel_s: float | None, smooth_share: float = 0.0) -> float:
    """From the feed-in's centroid (its middle) to the end of its share of the per-move overhead ``c``.

    ``accel_s``: the part of ``c`` that shapes the move (the rest, e.g. an
    in-position wait, does not); None: all of it.  ``smooth_share``: where
    the feed-in is shorter than ``V accel_s``, how far its duration lies from
    the trapezoid's triangle toward the average's ``f/V + accel_s``
    (:func:`short_move_duration`; analysis/README.md, "The feed-in's own
    duration").
    """
    a = accel_part(c, accel_s)
    return short_move_duration(f, V, a, smooth_share) / 2 + (c - a) / 2


def accel_part(c: float, accel_s: float | None) -> float:
    """The acceleration part of a per-move overhead ``c``: ``accel_s`` where the move's shape shows clearly less
    than ``c`` (an in-position wait makes up the rest), else all of ``c`` (the shape's estimate is a few per cent
    rough, the overhead's is not)."""
    if c <= 0:
        return c
    if accel_s is None or accel_s >= ACCEL_SHARE * c:
        return c
    return max(accel_s, 0.0)


def accel_from_spread(f: float, V: float, var_s2: float) -> float:
    """The acceleration overhead of a rest-to-rest move of length ``f`` at feed ``V`` whose velocity profile has
    variance ``var_s2`` (s^2) in time.

    Reaching the feed, the profile is a rectangle ``f/V`` long convolved with
    the acceleration's kernel (a box ``c`` long for a trapezoid):
    ``12 var = (f/V)^2 + c^2``; a triangle of base ``2 sqrt(f c / V)`` has
    ``var = f c / (6 V)``.  The two meet at ``c = f/V``.  A jerk-limited
    profile's kernel is two boxes: this gives ``sqrt(ta^2 + tj^2)``, less than
    their sum.
    """
    T = f / V
    s2 = 12.0 * var_s2
    if s2 <= 2.0 * T * T:
        return math.sqrt(max(s2 - T * T, 0.0))
    return 6.0 * V * var_s2 / f


def schedule(
    plan: TestPlan, feed_mm_s: float, overhead_s: float = 0.0, accel_s: float | None = None, smooth_share: float = 0.0
) -> Schedule:
    """Predicted timing of ``plan`` at path feed ``feed_mm_s`` and per-move overhead ``overhead_s``.

    ``accel_s``: the part of the overhead that shapes the move, where known; ``smooth_share``: where a short
    feed-in's duration lies between its triangle and ``f/V + accel_s`` (:func:`feed_in_half`).
    """
    V, c = feed_mm_s, overhead_s
    R, f, D = plan.radius_mm, plan.feed_in_mm, plan.dwell_s
    o, a = math.radians(plan.overshoot_deg), math.radians(plan.data_arc_deg)
    arc_len = R * (a + 2 * o)
    # The feed-in's centroid sits at its middle, whether or not it reaches the feed.
    half_feed_in = feed_in_half(f, V, c, accel_s, smooth_share)
    t = half_feed_in  # end of feed-in, relative to its centroid
    ds: dict[int, float] = {}
    de: dict[int, float] = {}
    arc_start: dict[int, float] = {}
    for d in plan.direction_list:
        t += D
        arc_start[d] = t + c / 2  # constant-speed part extrapolated back to zero length
        ds[d] = arc_start[d] + R * o / V
        de[d] = ds[d] + R * a / V
        t += arc_len / V + c
    t += D
    feed_out_centroid = t + half_feed_in
    return Schedule(V, c, ds, de, arc_start, feed_out_centroid)


def centroid_span_s(
    plan: TestPlan, feed_mm_s: float, overhead_s: float, accel_s: float | None = None, smooth_share: float = 0.0
) -> float:
    """Time from the feed-in's centroid to the feed-out's."""
    return schedule(plan, feed_mm_s, overhead_s, accel_s, smooth_share).feed_out_centroid_s


def feed_from_span(
    plan: TestPlan, span_s: float, overhead_s: float = 0.0, accel_s: float | None = None, smooth_share: float = 0.0
) -> float:
    """Invert :func:`centroid_span_s` for the feed (mm/s).

    Where the feed-in reaches the feed the span is linear in ``1/V``; where it
    does not (its two halves last ``2 sqrt(f c / V)``) it is quadratic in
    ``1/sqrt(V)``.  Both branches are solved in closed form and the one whose
    feed is consistent with it is taken (the span falls monotonically with
    ``V``, so exactly one is).
    """
    n_dirs = len(plan.direction_list)
    n_dwells = n_dirs + 1
    f, c = plan.feed_in_mm, overhead_s
    acc = accel_part(c, accel_s)
    q = min(max(smooth_share, 0.0), 1.0)
    arcs = n_dirs * plan.radius_mm * math.radians(plan.arc_deg)
    # Reaching the feed: span = dwells + n_dirs c + c (two half feed moves) + (f + arcs) / V.
    moving = span_s - n_dwells * plan.dwell_s - (n_dirs + 1) * c
    V = (f + arcs) / moving if moving > 0 else float("nan")
    if acc <= 0.0 or not math.isfinite(V) or f >= V * acc:
        return V
    # A short feed-in, (1 - q) of the triangle and q of f/V + acc (:func:`short_move_duration`): with
    # x = 1/sqrt(V), span = dwells + n_dirs c + (c - acc) + q acc + (arcs + q f) x^2 + (1 - q) 2 sqrt(f acc) x.
    m = span_s - n_dwells * plan.dwell_s - n_dirs * c - (c - acc) - q * acc
    a2 = arcs + q * f
    b = (1.0 - q) * 2.0 * math.sqrt(f * acc)
    if m <= 0:
        return float("nan")
    x = (-b + math.sqrt(b * b + 4.0 * a2 * m)) / (2.0 * a2)
    return 1.0 / (x * x)


def model_limits(plan: TestPlan, accel_mm_s2: float = 2000.0) -> list[str]:
    """Where ``plan`` itself breaks the analyzer's timing model at path acceleration ``accel_mm_s2``.

    :func:`schedule` takes a move too short to reach the feed ``V`` as a
    trapezoid's triangle, but the data arcs must run at ``V``: an overshoot
    shorter than the acceleration distance ``V^2 / 2A`` lets a data arc begin
    while the machine still accelerates.  Then no program can run the plan's
    timing, and :func:`ballbar.tools.nccheck.check_against_plan` reports the
    resulting timing errors too.  The analyzer measures ``V / A`` as the
    arc-start lag and warns through this function as well.
    """
    V = plan.feed_mm_s
    need = V**2 / (2.0 * accel_mm_s2)
    over = plan.radius_mm * math.radians(plan.overshoot_deg)
    if over < need:
        return [
            f"the overshoot ({over:.4g} mm) is shorter than the acceleration distance V^2/2A ({need:.4g} mm at "
            f"{accel_mm_s2:g} mm/s^2): the data arcs begin before the feed is reached"
        ]
    return []
