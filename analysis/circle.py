"""One direction's data arc at a fixed timing: the timing's schedule, and the circle's growing fit.

:class:`Timing` places each sample on the circle (analysis/README.md, "The
angle of each sample"); :class:`CircleFit` folds a data arc's samples into a
QR factor as they arrive (the live, provisional circle results) or all at once
(a test's final fit), with a physical correction subtracted where there is one.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace

import numpy as np

from .fit import Factor
from .patterns import Geometry, Pattern, design, wrap
from .physics import LostMotion, Offset
from .plan import MachineConfig, TestPlan
from .program import Schedule, arc_start_deg, schedule

FOLD_ROWS = 16384  # samples folded into a QR factor at a time: the block's design and factor stay in cache


@dataclass
class Timing:
    feed_mm_s: float
    overhead_s: float
    sched: Schedule
    t_ref: float  # feed-in centroid (absolute)
    t_mid: float  # origin of the drift term (absolute): the feed-in centroid

    def window(self, d: int) -> tuple[float, float]:
        return self.t_ref + self.sched.data_start_s[d], self.t_ref + self.sched.data_end_s[d]


def make_timing(
    plan: TestPlan,
    t_ref: float,
    feed_mm_s: float,
    overhead_s: float,
    shift_s: dict[int, float] | None = None,
    accel_s: float | None = None,
    smooth_share: float = 0.0,
) -> Timing:
    """The timing at feed ``V`` and per-move overhead ``c``; ``shift_s``: per direction, how much later its data
    arc runs than equal overheads put it (a wait before that arc longer than the others', e.g. in-position);
    ``accel_s``: the part of ``c`` that shapes the move, None: all of it; ``smooth_share``: the share of that
    which averages the trapezoid rather than accelerating it (:func:`.program.feed_in_half`)."""
    sched = schedule(plan, feed_mm_s, overhead_s, accel_s, smooth_share)
    if shift_s:
        sched = replace(
            sched,
            data_start_s={d: v + shift_s.get(d, 0.0) for d, v in sched.data_start_s.items()},
            data_end_s={d: v + shift_s.get(d, 0.0) for d, v in sched.data_end_s.items()},
            arc_start_s={d: v + shift_s.get(d, 0.0) for d, v in sched.arc_start_s.items()},
        )
    # The drift term's origin is the feed-in: radius_um is then the radius when the test began.
    return Timing(feed_mm_s, overhead_s, sched, t_ref, t_ref)


class CircleFit:
    """The growing fit of one direction's data arc at fixed timing and spike width.

    ``offset``: a physical correction (um) subtracted from the deviation before
    the masks see it (:mod:`.physics`).
    """

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig,
        patterns: Sequence[Pattern],
        direction: int,
        timing: Timing,
        spike_width_deg: float,
        keep_design: bool = False,
        offset: Offset | None = None,
        loop_lag_s: float | None = None,
        lost: LostMotion | None = None,
        aperture_rad: float = 0.0,
        skip_rad: float = 0.0,
        slope: Offset | None = None,
    ) -> None:
        self.plan, self.machine, self.patterns = plan, machine, list(patterns)
        self.loop_lag_s = loop_lag_s
        self.lost = lost or LostMotion()
        self.aperture_rad = aperture_rad
        self.skip_rad = skip_rad  # samples this far past a table's reversal are left out (unsized spikes)
        self.d = direction
        self.timing = timing
        self.w = math.radians(spike_width_deg)
        self.p = sum(pat.q for pat in self.patterns)
        self.factor = Factor(self.p)
        self.colmax = np.zeros(self.p)
        self.t_start, self.t_end = timing.window(direction)
        self.keep_design = keep_design
        self.offset = offset
        # The correction's change per ms of servo mismatch, folded as one more column of [A | -slope | y]: the
        # factor at another mismatch is then that column's multiple added to y's (:meth:`move_correction`),
        # without a fold.
        self.slope = slope
        self.with_slope = Factor(self.p + 1) if slope is not None else None
        self.kept: list[tuple[np.ndarray, np.ndarray]] = []  # (t, dR as measured) of the samples folded in

    def geometry(self, t: np.ndarray) -> Geometry:
        u = np.radians(self.timing.sched.angle_deg(self.plan, self.d, t - self.timing.t_ref))
        return Geometry(
            u=u,
            d=np.full(t.size, float(self.d)),
            t_min=(t - self.timing.t_mid) / 60.0,
            V=self.timing.feed_mm_s,
            R=self.plan.radius_mm,
            pitch_x_mm=self.machine.pitch_x_mm,
            pitch_y_mm=self.machine.pitch_y_mm,
            travel=self.d * (u - math.radians(arc_start_deg(self.plan, self.d))),
            loop_lag_s=self.loop_lag_s,
            aperture_rad=self.aperture_rad,
            **self.lost.geometry(self.loop_lag_s),
        )

    def add(self, t: np.ndarray, L: np.ndarray) -> None:
        """Fold in the samples of ``(t, L)`` that lie in this circle's data arc."""
        m = (t >= self.t_start) & (t <= self.t_end)
        if not m.any():
            return
        t, L = t[m], L[m]
        if self.skip_rad > 0:
            keep = ~_after_onsets(self.geometry(t), self.skip_rad)
            if not keep.all():
                t, L = t[keep], L[keep]
        dr = (L - self.plan.radius_mm) * 1000.0
        self._fold(t, dr)
        if self.keep_design:
            self.kept.append((t, dr))

    def _fold(self, t: np.ndarray, dr: np.ndarray) -> None:
        """Fold samples into the factor ``FOLD_ROWS`` at a time (no design matrix of a whole circle in memory)."""
        for g, A, rows in self._blocks(t):
            y = dr[rows] - self.offset(g) if self.offset is not None else dr[rows]
            if self.with_slope is not None and self.slope is not None:
                self.with_slope.add(np.column_stack([A, -self.slope(g)]), y)
            else:
                self.factor.add(A, y)
            np.maximum(self.colmax, np.abs(A).max(axis=0), out=self.colmax)
        if self.with_slope is not None:
            self.factor = self._factor_at(0.0)

    def _factor_at(self, delta: float) -> Factor:
        """The factor of ``[A | y - offset - delta slope]`` from the one folded with the slope's column."""
        assert self.with_slope is not None
        R, p = self.with_slope.rows, self.p
        y = R[:, p + 1] + delta * R[:, p]  # in the folded rows' frame: y's column less delta slopes
        out = Factor(p)
        out.R = np.zeros((p + 1, p + 1))
        out.R[:p, :p] = R[:p, :p]
        out.R[:p, p] = y[:p]
        out.R[p, p] = math.hypot(y[p], y[p + 1])
        out.n = self.with_slope.n
        return out

    def move_correction(self, delta_ms: float, offset: Offset | None) -> None:
        """The correction made at a servo mismatch ``delta_ms`` away from the folded one, ``offset``: the factor
        moved along the folded slope (exact to the correction's second order in the mismatch; the residuals
        are made at ``offset`` itself)."""
        self.factor = self._factor_at(delta_ms)
        self.offset = offset

    def _blocks(self, t: np.ndarray) -> Iterator[tuple[Geometry, np.ndarray, slice]]:
        """The geometry and design of ``t`` in blocks of ``FOLD_ROWS`` samples, with each block's rows."""
        for i in range(0, t.size, FOLD_ROWS):
            rows = slice(i, min(i + FOLD_ROWS, t.size))
            g = self.geometry(t[rows])
            yield g, design(self.patterns, g, self.w), rows

    def refit(self, offset: Offset | None) -> None:
        """Refold the kept samples with another correction (the design is made again, block by block)."""
        self.offset = offset
        self.factor = Factor(self.p)
        self.slope, self.with_slope = None, None
        for t, dr in self.kept:
            self._fold(t, dr)

    def residual(self, x: np.ndarray) -> np.ndarray:
        """The kept samples' deviation as measured, minus the correction, minus the model at ``x``."""
        out = []
        for t, dr in self.kept:
            for g, A, rows in self._blocks(t):
                r = dr[rows] - self.offset(g) if self.offset is not None else dr[rows].copy()
                out.append(r - A @ x)
        return np.concatenate(out) if out else np.empty(0)

    def times(self) -> np.ndarray:
        """The kept samples' times."""
        return np.concatenate([t for t, _ in self.kept]) if self.kept else np.empty(0)

    def measured(self) -> tuple[np.ndarray, np.ndarray]:
        """Kept ``(u, dR)`` as measured: angles (rad) and deviations (um), for the ISO figures."""
        if not self.kept:
            return np.empty(0), np.empty(0)
        u = [np.radians(self.timing.sched.angle_deg(self.plan, self.d, t - self.timing.t_ref)) for t, _ in self.kept]
        return np.concatenate(u), np.concatenate([dr for _, dr in self.kept])


def _after_onsets(g: Geometry, reach_rad: float) -> np.ndarray:
    """Samples within ``reach_rad`` past a table's reversal (where friction sets in), any axis."""
    out = np.zeros(len(g), dtype=bool)
    for axis, points in ((0, (0.0, math.pi)), (1, (0.5 * math.pi, 1.5 * math.pi))):
        for at in points:
            du = wrap(g.d * (g.u - at) - g.onset_rad[axis], 2.0 * math.pi)  # travel past the onset
            out |= du < reach_rad
    return out
