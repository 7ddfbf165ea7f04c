"""The test program of DOMAIN.md section 1 as a list of moves, and its timing.

Coordinates are in the plane's frame (first axis, second axis), in millimetres,
relative to the pivot.  Angles are radians internally.

Timing model.  Every move starts and ends at rest.  For any acceleration profile
that is symmetric (acceleration mirrored by deceleration) and reaches the path
feed ``V``, a move of length ``s`` lasts ``s / V + c``; ``c`` is the move's
overhead (``V / A`` for a trapezoid of acceleration ``A``), and in the constant
speed part the path position is ``V * (t - t_start - c / 2)``.  The analyzer
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
    """First angle of the data arc in the direction of travel (DOMAIN.md section 1)."""
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


def schedule(plan: TestPlan, feed_mm_s: float, overhead_s: float = 0.0) -> Schedule:
    """Predicted timing of ``plan`` at path feed ``feed_mm_s`` and per-move overhead ``overhead_s``."""
    V, c = feed_mm_s, overhead_s
    R, f, D = plan.radius_mm, plan.feed_in_mm, plan.dwell_s
    o, a = math.radians(plan.overshoot_deg), math.radians(plan.data_arc_deg)
    arc_len = R * (a + 2 * o)
    # The feed-in lasts f/V + c; its centroid sits at its middle.
    t = f / (2 * V) + c / 2  # end of feed-in, relative to its centroid
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
    feed_out_centroid = t + f / (2 * V) + c / 2
    return Schedule(V, c, ds, de, arc_start, feed_out_centroid)


def centroid_span_s(plan: TestPlan, feed_mm_s: float, overhead_s: float) -> float:
    """Time from the feed-in's centroid to the feed-out's."""
    return schedule(plan, feed_mm_s, overhead_s).feed_out_centroid_s


def feed_from_span(plan: TestPlan, span_s: float, overhead_s: float = 0.0) -> float:
    """Invert :func:`centroid_span_s` for the feed (mm/s): the span is linear in 1/V."""
    n_moves = len(plan.direction_list) + 1  # arcs plus half the feed-in and half the feed-out
    n_dwells = len(plan.direction_list) + 1
    path = plan.feed_in_mm + len(plan.direction_list) * plan.radius_mm * math.radians(plan.arc_deg)
    moving = span_s - n_dwells * plan.dwell_s - n_moves * overhead_s
    if moving <= 0:
        return float("nan")
    return path / moving


def model_limits(plan: TestPlan, accel_mm_s2: float = 2000.0) -> list[str]:
    """Where ``plan`` itself breaks the analyzer's timing model at path acceleration ``accel_mm_s2``.

    :func:`~ballbar.analysis.program.schedule` assumes every move reaches the
    feed ``V`` (a move of length ``s`` lasts ``s / V + V / A``) and the data arcs
    run at constant speed.  A feed-in shorter than ``V^2 / A`` never reaches
    ``V``; an overshoot shorter than ``V^2 / 2A`` lets the data arc begin while
    the machine still accelerates.  Then no program can run the plan's timing,
    and :func:`ballbar.tools.ncinterp.check_against_plan` reports the resulting
    timing errors too.  The analyzer measures ``V / A`` as the arc-start lag and
    warns through this function as well.
    """
    V = plan.feed_mm_s
    out: list[str] = []
    need = V**2 / accel_mm_s2
    if plan.feed_in_mm < need:
        out.append(
            f"the feed-in ({plan.feed_in_mm:g} mm) is too short to reach the feed at {accel_mm_s2:g} mm/s^2 "
            f"(it needs {need:.4g} mm)"
        )
    over = plan.radius_mm * math.radians(plan.overshoot_deg)
    if over < need / 2.0:
        out.append(
            f"the overshoot ({over:.4g} mm) is shorter than the acceleration distance V^2/2A ({need / 2.0:.4g} mm): "
            "the data arcs begin before the feed is reached"
        )
    return out
