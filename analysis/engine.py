"""From samples to results: one code path for the live daemon and offline files.

:class:`TestAnalyzer` is fed ``(t, length)`` chunks of any size.  It finds each
test (:mod:`.detect`), fits each circle as soon as its data arc has passed, and
fits the whole test (both directions jointly) after the feed-out.

Timing.  The angle of a sample comes from the feed-in's centroid and the
program's timing (:mod:`.program`), at a path feed ``V`` and a per-move
overhead ``c`` (the acceleration's delay).  A circle finishes before the
feed-out, so its *provisional* fit uses the programmed feed times the feed
ratio and overhead learnt on the previous test (``TimingHints``).  After the
feed-out the test's fit measures the feed from the centroid span, estimates the
overhead ``c`` (the arc start's lag) and the reversal spikes' width ``w`` by
maximising the profile likelihood of the full model (with a weak prior on ``c``
so that it stays near zero where the data cannot tell), and refits both circles
at those values: one pass over that test's own samples, none over older ones.

Breaks.  Every angle hangs on the time axis, so :class:`TestAnalyzer` watches
it (:mod:`.timeaxis`): a step backwards beyond jitter is a :class:`DataError`;
a gap longer than a few sample periods, and any break the caller tells it of
(:meth:`TestAnalyzer.mark_break`: a device reset, lost samples), rejects the
test it falls in (``test_rejected``, with the break's time and size), from the
feed-in step's first sample to the feed-out step's last.  Only a test that
passed, with a plausible feed, teaches the next one its timing hints.

In the background.  Given an ``executor`` (the daemon's child process), the
test's fit runs there while the next test's samples come in: :meth:`TestAnalyzer.collect`
returns its result once done.  The analyzer waits for it before the next
feed-in (and at :meth:`~TestAnalyzer.finish` and :meth:`~TestAnalyzer.abort`),
so the hints it teaches reach the next test exactly as inline: the results
are the same either way.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from scipy.linalg.blas import dsymv as _symv
from scipy.linalg.lapack import dpotrf as _potrf
from scipy.linalg.lapack import dpotri as _potri

from ballbar import SCHEMA_VERSION  # the payloads' version, one for all (daemon/schemas.py)

from . import iso230, noise, stats
from .advice import advise
from .detect import StepEvent, TestDetector
from .errors import DataError, DetectionError
from .fit import Factor, FitResult, significance_rule, solve
from .patterns import Geometry, Pattern, design, select, wrap
from .physics import MODEL_WORDS, LostMotion, Offset, axis_reversals, loop_angles, make_offset, mean_lag
from .plan import AnalysisOptions, MachineConfig, TestPlan
from .program import (
    Schedule,
    accel_from_spread,
    arc_start_deg,
    data_start_deg,
    feed_from_span,
    model_limits,
    schedule,
)
from .timeaxis import Break, TimeAxis

log = logging.getLogger(__name__)

FOLD_SAMPLES = 256  # a live circle folds new samples in blocks of at least this many (or as it completes)
SEARCH_SAMPLES_PER_CIRCLE = 400  # thinned samples per circle away from the sharp features
FOLD_ROWS = 16384  # samples folded into a QR factor at a time: the block's design and factor stay in cache
SEARCH_BATCH_ROWS = 60_000  # the search's timings evaluated together: at most this many samples in all
# Near each 45 deg point (before, after it; deg) the search keeps samples up to one per spacing (deg): over the
# whole lag range (which moves the points by up to ~3 deg) coarsely, then where they are finely (at 10 kHz 1 in 4).
COARSE_NEAR_DEG, COARSE_SPACING_DEG = (1.0, 4.5), 0.03
FINE_NEAR_DEG, FINE_SPACING_DEG = (0.7, 1.0), 0.004
FINE_TRIM_S = 0.03  # the fine set's data arcs, trimmed for lags within this of the coarse one
LAG_SEARCH_BELOW_S = 0.1  # a negative per-move overhead is unphysical: search only this far below 0
LAG_GRID_S = (0.015, 0.0015)  # the lag's grids: over its whole range, and around the best
STAIR_REACH_S = 0.001  # a stair's reach either side (at most, unless half a sample period is more)
STAIR_BISECT = 4  # bisections of each stair edge once bracketed
STAIR_NATS = 0.01  # likelihood levels this close are one stair of the lag's staircase
LAG_CI_NATS = 2.0  # lags whose full-model likelihood is this close to the best are not told apart by it
NEWTON_START_S = 0.003  # the smoothed descent's first stencil spacing in the arcs' starts (s): the grids' resolution
NEWTON_LOCAL_S = 0.001  # ... where it starts from a timing found at corrections that moved little
NEWTON_SHRINK = 3.0  # the spacing's shrink once the minimum lies within the stencil
NEWTON_STEPS = 10  # at most this many stencils
NEWTON_REACH = 1.5  # a fitted quadratic's minimum is taken at most this many spacings away
NEWTON_STRETCH = 4.0  # the stencil stretched along a flat valley by at most this much
FLAT_CURVATURE = 1e-3  # a fitted curvature below this share of the largest is taken as flat (a valley's floor)
FINE_SCALE_S = 0.002  # the finest timing scale the descents resolve: a sample period, at most this (s)
STAIR_SAMPLES = 3.0  # a stair's reach either side: this many sample periods, at most STAIR_REACH_S
STAIR_FIRST = 0.02  # the first step (sample periods) out to a stair's edges, doubled until off the stair
COMPASS_EVALS, COMPASS_GAIN_NATS = 120, 0.5  # a compass search on point samples: at most this many objectives;
# a step must gain this much
COMPASS_FIRST, COMPASS_LAST = 0.25, 0.02  # ... from and down to this many sample periods
CONTINUE_SAMPLES = 0.03  # the smoothing followed down to this many sample periods
WAIT_LAG_STEPS = 4.0  # the best lag without the extra wait: a compass search from this many sample periods
COMPASS_DIRS = ((1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (-1, -1), (1, -1), (-1, 1))  # (lag, wait)
SMOOTH_MAX_SAMPLE_DEG = 0.025  # samples further apart (deg) are searched as points: no smoothing
WAIT_MAX_S = 0.3  # no extra wait beyond this (s), either sign
WAIT_PRIOR_S = 0.1  # prior on it: where the data cannot see it (low rates), it stays near 0
WAIT_GRID_S = (0.01, 15)  # the wait's grid: steps (s) and how many either side
LAG_PRIOR_S = 0.05
SSE_FLOOR_UM = 1e-3
DEFAULT_KV_PER_S = 30.0
PROFILE_KV_PER_S = (12.0, 19.0, 30.0, 48.0, 76.0)  # the gains tried where the feed-in does not show the loop
PROFILE_REFINE = 3  # parabola steps after the grid
PROFILE_FLOOR_UM = 0.01  # no gauge resolves finer: a misfit below it tells no gain apart
PROFILE_NATS = 2.0  # another gain must beat the default by this much log-likelihood
TAIL_SAMPLES = 1.8  # samples per loop time constant the settling fit needs (6 within ~3.4 tau)
FAST_LOOP_S = 0.02  # a loop lag the settling fit must be able to see before "none seen" means "fast"
DEFAULT_SPIKE_WIDTH_DEG = 0.5
RESOLVE_SAMPLES = 2.0  # samples per spike width below which a spike cannot be sized
WIDTH_AT_BOUND = 1.03  # a fitted width within 3 % of a bound of its search has run onto it
WIDTH_STEP_LN = 0.05  # the step in ln w of the width's error estimate
WIDTH_GRID, WIDTH_XTOL = 9, 0.015  # the width's search: a grid over its range in ln w, refined to this step
SPIKE_Z = 2.0  # a significant spike's height is at least this many of its (full) standard errors
SKIP_SAMPLES = 2.0  # samples after each table reversal left out where spikes are below the resolution
KAPPA_RESEARCH = 0.5  # the timing is searched again where the residual's correlation has fallen below this share
ONSET_MOVE_SAMPLES = 0.1  # the timing is searched again when a table's reversal moves by more (samples)
OFFSET_SETTLED_UM = 1e-4  # the final fit is not refolded for a correction that would move by less (um)
SLOPE_MS = 1e-3  # the step (ms of servo mismatch) of the correction's slope, folded with the final fit
FOLD_SLOPE = True  # fold that slope (False: refold every sample at each new correction)
FINAL_STEPS = 6  # the final fit's correction brought to its fixed point in at most this many steps
# A measured feed this far from the programmed one is not the machine's habit (controls hold the feed to well
# under 1 % at 100 % override): something else went wrong, and the next test must not assume it.
HINT_MAX_FEED_DEVIATION = 0.1


@dataclass
class TimingHints:
    """What the previous test taught: used for the provisional circle fits."""

    feed_ratio: float = 1.0
    overhead_s: float = 0.0
    spike_width_deg: float = DEFAULT_SPIKE_WIDTH_DEG

    @classmethod
    def learnt(cls, timing: dict[str, Any], before: TimingHints | None = None) -> TimingHints | None:
        """The hints a test result's ``timing`` teaches, or None where they are implausible.

        Implausible: a feed ratio more than ``HINT_MAX_FEED_DEVIATION`` from 1, or
        a value that is not a finite number.  ``before`` supplies the spike width
        where the test had none.
        """
        try:
            ratio = float(timing["feed_ratio"])
            overhead = float(timing["overhead_s"])
        except (KeyError, TypeError, ValueError):
            return None
        width = timing.get("spike_width_deg")
        if not (math.isfinite(ratio) and math.isfinite(overhead) and abs(ratio - 1.0) <= HINT_MAX_FEED_DEVIATION):
            return None
        if not (isinstance(width, int | float) and math.isfinite(width) and width > 0):
            width = (before or cls()).spike_width_deg
        return cls(ratio, overhead, float(width))


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
) -> Timing:
    """The timing at feed ``V`` and per-move overhead ``c``; ``shift_s``: per direction, how much later its data
    arc runs than equal overheads put it (a wait before that arc longer than the others', e.g. in-position);
    ``accel_s``: the part of ``c`` that is acceleration (:func:`.program.feed_in_half`), None: all of it."""
    sched = schedule(plan, feed_mm_s, overhead_s, accel_s)
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


def _kappa(rho: float) -> float:
    """The AR(1) variance inflation ``(1 + rho) / (1 - rho)`` of a residual's lag-1 correlation, 1..400."""
    return min(max((1 + rho) / (1 - rho), 1.0), 400.0) if rho < 1 else 400.0


def _lag1(residuals: Sequence[np.ndarray]) -> float:
    num = sum(float(np.dot(r[1:], r[:-1])) for r in residuals if r.size > 1)
    den = sum(float(np.dot(r, r)) for r in residuals)
    return num / den if den > 0 else 0.0


class TestAnalyzer:
    """Streaming test detection and fitting; see the module docstring.

    :meth:`feed` returns result dictionaries as they complete: ``kind`` is
    ``"circle"`` (one direction, provisional timing) or ``"test"``; and event
    dictionaries (``kind = "event"``: ``feed_in``, ``feed_out``,
    ``test_rejected``, ``test_incomplete``).  A test is rejected as soon as a
    break in its time axis is seen (live: at once, not at its feed-out); its
    feed-out is still reported, and no result follows.

    ``executor``: where each test's fit runs (see the module docstring;
    ``None``: inline, its result returned with the feed-out); ``on_submit``
    is handed each background job's future (to be told when it is done).
    ``circles``: False for the tests' results alone (no provisional circles:
    an offline analysis that reads only the test's result).  ``only``: fit
    only the test of that number (from 1, the feed-ins in order); the
    others' feed-outs come with a ``test_skipped`` event instead of a fit.
    A test's fit does not depend on the tests before it (only the
    provisional circles take the hints they teach), so its result is the
    one the whole analysis gives; ``only`` needs ``circles=False``.
    """

    __test__ = False

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig | None = None,
        options: AnalysisOptions | None = None,
        hints: TimingHints | None = None,
        curves: bool = False,
        executor: cf.Executor | None = None,
        on_submit: Callable[[cf.Future[dict[str, Any]]], None] | None = None,
        circles: bool = True,
        only: int | None = None,
    ) -> None:
        if only is not None and circles:
            raise ValueError("only: a test's provisional circles take the hints the tests before it teach; "
                             "pass circles=False")
        self.plan = plan
        self.circles = circles
        self.only = only
        self.executor = executor
        self.on_submit = on_submit
        self._pending: tuple[int, StepEvent, cf.Future[dict[str, Any]]] | None = None
        self.curves = curves
        self.machine = machine or MachineConfig()
        self.options = options or AnalysisOptions()
        self.hints = hints or TimingHints()
        self.detector = TestDetector(plan)
        self.axis = TimeAxis()
        self.patterns = select(
            self.options.patterns, plan.direction_list, self.machine.pitch_x_mm, self.machine.pitch_y_mm
        )
        self.test_index = 0
        self._fi: StepEvent | None = None
        self._rejected = False  # the test in progress has been rejected
        self._circles: list[CircleFit] = []
        self._emitted: set[int] = set()
        self._added = 0
        self._breaks: list[Break] = []
        self.last_t = float("nan")

    def feed(self, t: np.ndarray, L: np.ndarray, borrow: bool = False) -> list[dict[str, Any]]:
        """Take the next samples (times in seconds, any origin; lengths in mm).

        Raises :class:`DataError` for a non-finite value and
        :class:`~.timeaxis.TimeAxisError` for a time that runs backwards beyond
        jitter; nothing of the chunk is taken then.  ``borrow``: the detector
        may keep views of ``t`` and ``L`` instead of a copy (the caller leaves
        them unchanged while the analyzer lives: a whole recording).
        """
        t = np.asarray(t, dtype=float)
        L = np.asarray(L, dtype=float)
        if t.size and not (np.isfinite(t).all() and np.isfinite(L).all()):
            k = int(np.argmax(~(np.isfinite(t) & np.isfinite(L))))
            raise DataError(f"sample {self.detector.n_seen + k}: time or length is not a finite number")
        self._breaks.extend(self.axis.check(t))
        if t.size:
            self.last_t = float(t[-1])
        self.detector.feed(t, L, borrow)
        return self._drain()

    def mark_break(self, reason: str) -> None:
        """A discontinuity between the samples fed so far and the next ones, which the times may not show.

        ``reason`` names it in the rejection's message (``"device reset"``,
        ``"1200 samples lost (outage)"``).  A test it falls in is rejected.
        """
        self.axis.mark(reason)

    def abort(self, reason: str) -> list[dict[str, Any]]:
        """The stream cannot go on as it is (the caller starts afresh): the result of the test in the
        background, if any; reject the test in progress, if any."""
        out = self.collect(wait=True)
        if self._fi is None or self._rejected:
            return out
        fi = self._fi
        return [*out, self._reject(self.last_t, None, f"{reason}, {self.last_t - fi.t_s:.1f} s after the feed-in at "
                             f"t={fi.t_s:.3f} s: the test in progress is abandoned")]

    def finish(self) -> list[dict[str, Any]]:
        """End of the stream: settle the last step; the last result; report a test left unfinished."""
        self.detector.finish()
        out = self._drain()
        out.extend(self.collect(wait=True))
        if self._fi is not None and not self._rejected:
            out.append(
                {
                    "kind": "event",
                    "event": "test_incomplete",
                    "test_index": self.test_index,
                    "t_s": self.last_t,
                    "message": f"the stream ended {self.last_t - self._fi.t_s:.1f} s after the feed-in "
                    f"at t={self._fi.t_s:.3f} s, before the feed-out",
                }
            )
        return out

    def next_due(self) -> float | None:
        """When, on the samples' clock, the next result may be due: the end of the first circle not yet
        fitted; after the last one, now (the feed-out may come with any sample); None between tests and in
        a rejected test (nothing is due until the next feed-in)."""
        if self._fi is None or self._rejected:
            return None
        ends = [c.t_end for c in self._circles if c.d not in self._emitted]
        return min(ends) if ends else self.last_t

    @property
    def pending(self) -> bool:
        """A test's fit is running in the background."""
        return self._pending is not None

    def collect(self, wait: bool = False, timeout: float | None = None) -> list[dict[str, Any]]:
        """The result of the test analysed in the background, once its fit is done (``wait``: wait for it, up
        to ``timeout``); ``[]`` while it runs, or when there is none.  A fit that raised is raised here; a child
        process that died rejects its test."""
        if self._pending is None:
            return []
        index, fo, fut = self._pending
        if not fut.done():
            if not wait:
                return []
            cf.wait([fut], timeout=timeout)
            if not fut.done():
                return []
        self._pending = None
        try:
            return self._settle(index, fo, fut.result)
        except (cf.BrokenExecutor, cf.CancelledError) as err:
            why = f"ended before its result ({err})" if str(err) else "was stopped before its result"
            return [{"kind": "event", "event": "test_rejected", "test_index": index, "t_s": fo.t_s,
                     "message": f"the process analysing the test {why}; ballbar analyze of its recording gives it"}]

    def _drain(self) -> list[dict[str, Any]]:
        out = self.collect()
        while True:
            ev = self.detector.poll()
            if ev is None:
                break
            if self.axis.forward_steps == 0:
                raise DataError(
                    f"the time does not advance: all {self.axis.n} samples so far have t={self.axis.first_t:g} s"
                )
            if ev.kind == "feed_in":
                out.extend(self.collect(wait=True))  # its hints are the next test's
                self._start(ev)
                out.append(_event(ev, self.test_index))
                continue
            assert self._fi is not None
            if not self._rejected and (brk := self._break_in(self._fi.t_begin_s, ev.t_end_s)) is not None:
                out.append(self._break_rejection(brk))
            if self._rejected:
                out.append(_event(ev, self.test_index))
                self._fi, self._rejected = None, False
                continue
            out.extend(self._advance(final=True))
            out.append(_event(ev, self.test_index))
            out.extend(self._finish_test(ev))
        if self._fi is not None and not self._rejected:
            brk = self._break_in(self._fi.t_begin_s, math.inf)
            if brk is not None:
                out.append(self._break_rejection(brk))
            else:
                out.extend(self._advance(final=False))
        if self._fi is None and self._breaks:
            # a later test begins after the first sample the detector still holds
            tb, _ = self.detector.samples()
            first = float(tb.min()) if tb.size else self.last_t
            self._breaks = [b for b in self._breaks if b.t_after >= first]
        return out

    def _break_in(self, t0: float, t1: float) -> Break | None:
        """The first break between the samples at ``t0`` and ``t1`` (a test's first and last step sample)."""
        return next((b for b in self._breaks if b.t_after > t0 and b.t_before < t1), None)

    def _break_rejection(self, brk: Break) -> dict[str, Any]:
        assert self._fi is not None
        fi = self._fi
        where = ("during the feed-in" if brk.t_after <= fi.t_end_s
                 else f"{brk.t_after - fi.t_s:.1f} s after the feed-in at t={fi.t_s:.3f} s")
        return self._reject(
            brk.t_after, brk.missing_s if brk.visible else None,
            f"{brk.describe()}, {where}: the test spans a break in its time axis, so its feed and angles "
            "cannot be trusted; run it again",
        )

    def _reject(self, t_s: float, gap_s: float | None, message: str) -> dict[str, Any]:
        self._rejected = True
        self._circles = []
        log.info("test %d rejected: %s", self.test_index, message)
        ev: dict[str, Any] = {"kind": "event", "event": "test_rejected", "test_index": self.test_index,
                              "t_s": t_s, "message": message}
        if gap_s is not None:
            ev["gap_s"] = gap_s
        return ev

    def _start(self, fi: StepEvent) -> None:
        self.test_index += 1
        self._fi = fi
        self._rejected = False
        V = self.plan.feed_mm_s * self.hints.feed_ratio
        timing = make_timing(self.plan, fi.t_s, V, self.hints.overhead_s, accel_s=feed_accel(self.plan, [fi], V))
        self._circles = [
            CircleFit(self.plan, self.machine, _for_direction(self.patterns, d), d, timing, self.hints.spike_width_deg)
            for d in self.plan.direction_list
        ] if self.circles else []
        self._emitted = set()
        self._added = 0

    def _advance(self, final: bool) -> list[dict[str, Any]]:
        """Fold new samples into the running circles, ``FOLD_SAMPLES`` at a time or as a circle completes;
        emit the circles now complete."""
        tb, Lb = self.detector.samples()
        t_last = tb[-1] if tb.size else -math.inf
        due = final or any(c.d not in self._emitted and t_last >= c.t_end for c in self._circles)
        if self._added < tb.size and (due or tb.size - self._added >= FOLD_SAMPLES):
            t_new, L_new = tb[self._added :], Lb[self._added :]
            for c in self._circles:
                c.add(t_new, L_new)
            self._added = tb.size
        out = []
        for c in self._circles:
            if c.d in self._emitted or (t_last < c.t_end and not final):
                continue
            self._emitted.add(c.d)
            if c.factor.n < c.p + 2:
                continue
            try:
                fit = solve(c.factor, c.patterns, significance=self.options.significance,
                            min_effect_um=self.options.min_effect_um, vif_limit=self.options.vif_limit,
                            effect_scale=c.colmax)
            except (np.linalg.LinAlgError, ValueError) as err:  # pragma: no cover - defensive
                log.warning("circle fit failed: %s", err)
                continue
            out.append(self._circle_result(c, fit))
        return out

    def _circle_result(self, c: CircleFit, fit: FitResult) -> dict[str, Any]:
        res = _result_body(self.plan, self.machine, self.options, fit, c.patterns)
        res.update(
            kind="circle",
            direction="ccw" if c.d > 0 else "cw",
            test_index=self.test_index,
            timing={
                "provisional": True,
                "feed_in_s": c.timing.t_ref,
                "assumed_feed_mm_min": c.timing.feed_mm_s * 60.0,
                "assumed_overhead_s": c.timing.overhead_s,
                "data_start_s": c.t_start,
                "data_end_s": c.t_end,
                "spike_width_deg": math.degrees(c.w),
            },
            residual_rms_um=math.sqrt(fit.sse / max(fit.n, 1)),
        )
        return res

    def _finish_test(self, fo: StepEvent) -> list[dict[str, Any]]:
        assert self._fi is not None
        fi, self._fi = self._fi, None
        if self.only is not None and self.test_index != self.only:
            return [{"kind": "event", "event": "test_skipped", "test_index": self.test_index, "t_s": fo.t_s,
                     "message": f"not analysed (test {self.only} was asked for)"}]
        tb, Lb = self.detector.samples()
        m = (tb >= fi.t_begin_s) & (tb <= fo.t_end_s)
        args = (self.plan, self.machine, self.options, tb[m], Lb[m], fi, fo, self.curves)
        if self.executor is None:
            return self._settle(self.test_index, fo, lambda: analyze_test(*args))
        fut = self.executor.submit(analyze_test, *args)
        self._pending = (self.test_index, fo, fut)
        if self.on_submit is not None:
            self.on_submit(fut)
        return []

    def _settle(self, index: int, fo: StepEvent, fit: Callable[[], dict[str, Any]]) -> list[dict[str, Any]]:
        """A test's fit, done: its result, and the hints it teaches; or its rejection."""
        try:
            result = fit()
        except DataError as err:
            return [{"kind": "event", "event": "test_rejected", "test_index": index, "t_s": fo.t_s,
                     "message": str(err)}]
        result["test_index"] = index
        hints = TimingHints.learnt(result["timing"], self.hints)
        if hints is None:
            log.warning("test %d: a measured feed of %.1f mm/min (programmed %g) is no timing hint for the next "
                        "test's provisional circles", index, result["timing"]["measured_feed_mm_min"],
                        self.plan.feed_mm_min)
        else:
            self.hints = hints
        return [result]


def _event(ev: StepEvent, test_index: int) -> dict[str, Any]:
    return {
        "kind": "event",
        "event": ev.kind,
        "test_index": test_index,
        "t_s": ev.t_s,
        "height_mm": ev.height_mm,
        "method": ev.method,
    }


def _for_direction(patterns: Sequence[Pattern], d: int) -> list[Pattern]:
    return [p for p in patterns if p.reversal is None or p.reversal[2] == d]


# --------------------------------------------------------------------------- whole test


def feed_accel(plan: TestPlan, steps: Sequence[StepEvent], feed_mm_s: float) -> float | None:
    """The acceleration part of the per-move overhead, from the feed-in's (and feed-out's) spread in time.

    The rest of the overhead (an in-position wait after each move, a
    control's block change) does not shape a move: only this decides whether
    the short feed-in reaches the feed (:func:`.program.feed_in_half`).  None
    where the steps' spread was not resolved (then all the overhead is taken
    as acceleration, as before).
    """
    found = [accel_from_spread(plan.feed_in_mm, feed_mm_s, e.move_var_s2) for e in steps
             if math.isfinite(e.move_var_s2) and e.move_var_s2 > 0]
    return float(np.mean(found)) if found else None


def check_plan(plan: TestPlan, fi: StepEvent, fo: StepEvent) -> float:
    """Raise DataError where the recording does not match the plan; return the feed (mm/s) at c = 0."""
    f = plan.feed_in_mm
    for ev in (fi, fo):
        if not 0.75 * f <= ev.height_mm <= 1.25 * f:
            raise DataError(
                f"plan does not match the data: the {ev.kind.replace('_', '-')} at t={ev.t_s:.3f} s "
                f"is a {ev.height_mm:.3f} mm step, the plan's feed-in is {f:g} mm"
            )
    span = fo.t_s - fi.t_s
    V0 = feed_from_span(plan, span, 0.0)
    nominal = schedule(plan, plan.feed_mm_s).feed_out_centroid_s
    if not (math.isfinite(V0) and 0.5 <= V0 / plan.feed_mm_s <= 1.5):
        raise DataError(
            f"plan does not match the data: feed-in to feed-out takes {span:.2f} s, the plan's program "
            f"takes {nominal:.2f} s at {plan.feed_mm_min:g} mm/min (check feed, radius, arcs and dwell)"
        )
    return V0


@dataclass
class _Hyper:
    overhead_s: float = 0.0
    spike_width_deg: float = DEFAULT_SPIKE_WIDTH_DEG
    lag_stderr_s: float = float("nan")
    wait_s: float = 0.0  # how much more the feed-in's move costs than each arc's (in-position waits)
    wait_free: bool = True  # the wait was fitted (False: the data did not need one, and it is 0)
    shift_s: dict[int, float] = field(default_factory=dict)  # per direction: its data arc's delay from that
    # the spikes' likelihood ratio (nats) against the spike-free model at its own best timing (nan: not found)
    spike_lr_nats: float = float("nan")
    # what finds it, where the search left that to whoever reads it (:meth:`spike_lr`)
    spike_lr_search: Callable[[], float] | None = field(default=None, repr=False, compare=False)

    def spike_lr(self) -> float:
        """``spike_lr_nats``, found on first use: of the search's passes only the last one's is read, and of the
        loop gains a profile tries only the taken one's (it costs a compass search of its own)."""
        if self.spike_lr_search is not None:
            self.spike_lr_nats, self.spike_lr_search = self.spike_lr_search(), None
        return self.spike_lr_nats


def _has_spikes(patterns: Sequence[Pattern]) -> bool:
    return any(p.reversal is not None for p in patterns)


class _Joint:
    """Both circles of one test at one timing, spike width and correction."""

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig,
        patterns: Sequence[Pattern],
        timing: Timing,
        spike_width_deg: float,
        t: np.ndarray,
        L: np.ndarray,
        offset: Offset | None,
        keep: bool,
        windows: dict[int, tuple[float, float]] | None = None,
        loop_lag_s: float | None = None,
        lost: LostMotion | None = None,
        aperture_rad: float = 0.0,
        skip_rad: float = 0.0,
        slope: Offset | None = None,
    ) -> None:
        self.patterns = list(patterns)
        self.circles: list[CircleFit] = []
        for d in plan.direction_list:
            cf = CircleFit(
                plan, machine, _for_direction(patterns, d), d, timing, spike_width_deg, keep, offset, loop_lag_s, lost,
                aperture_rad, skip_rad, slope,
            )
            if windows is not None:
                cf.t_start, cf.t_end = windows[d]  # the same samples whatever the timing
            cf.add(t, L)
            self.circles.append(cf)

    def factor(self) -> Factor:
        f = _embed(self.circles[0].factor, self.circles[0].patterns, self.patterns)
        for c in self.circles[1:]:
            f = f.merged(_embed(c.factor, c.patterns, self.patterns))
        return f

    def colmax(self) -> np.ndarray:
        out = np.zeros(sum(p.q for p in self.patterns))
        for c in self.circles:
            out = np.maximum(out, _embed_vec(c.colmax, c.patterns, self.patterns))
        return out

    def residuals(self, x: np.ndarray) -> list[np.ndarray]:
        """Per circle: the corrected deviation minus the model at ``x`` (NaN: left out)."""
        x = np.nan_to_num(x)
        return [c.residual(_take(x, c.patterns, self.patterns)) for c in self.circles]

    def solve(
        self, options: AnalysisOptions, rho: float = 0.0, exclude: dict[str, str] | None = None,
        family_dof: dict[str, int] | None = None, family_lr: dict[str, float] | None = None, rank: bool = True,
        timing_cov: np.ndarray | None = None,
    ) -> FitResult:
        return solve(self.factor(), self.patterns, rho=rho, significance=options.significance,
                     min_effect_um=options.min_effect_um, vif_limit=options.vif_limit, effect_scale=self.colmax(),
                     exclude=exclude, family_dof=family_dof, family_lr=family_lr, rank=rank, timing_cov=timing_cov)


def _spike_timing_error(res: dict[str, Any], hyper: _Hyper, omega_rad_s: float) -> None:
    """Add the onset's timing uncertainty to each spike's standard error.

    A spike is sized at its onset, which the timing places: an onset off by
    ``du`` scales the height by ``exp(du / w)``.  With the lag known to
    ``s_c``, ``du`` is known to about ``Omega s_c``; that relative error of
    the height is added in quadrature.
    """
    s_c = hyper.lag_stderr_s
    if not (math.isfinite(s_c) and s_c > 0):
        return
    rel = omega_rad_s * s_c / math.radians(hyper.spike_width_deg)
    for key, p in res["parameters"].items():
        if key.startswith("reversal_spike_") and p["value"] is not None and p["stderr"] is not None:
            p["stderr"] = math.hypot(p["stderr"], abs(p["value"]) * rel)
    res["fit"]["uncertainty_method"] += (
        f"; each reversal spike's also holds its onset's timing: the lag's {1000 * s_c:.2g} ms place the onset "
        f"to {math.degrees(omega_rad_s * s_c):.2g} deg, {100 * rel:.2g} % of the height at this width"
    )


def _spike_width_error(res: dict[str, Any], sigma_ln_w: float, slope: dict[str, float]) -> None:
    """Add the fitted width's uncertainty to each spike's standard error (:meth:`_LagSearch.width_error`)."""
    res["timing"]["spike_width_stderr_deg"] = (
        res["timing"]["spike_width_deg"] * sigma_ln_w if math.isfinite(sigma_ln_w) else None
    )
    for key, ds in slope.items():
        p = res["parameters"].get(key)
        if p and p["value"] is not None and p["stderr"] is not None:
            extra = abs(ds) * sigma_ln_w
            p["stderr"] = math.hypot(p["stderr"], extra) if math.isfinite(extra) else None
    res["fit"]["uncertainty_method"] += (
        "; and its width's: the heights' change with the width, times the width's standard error from the "
        "likelihood's curvature"
    )


def _spike_significance(res: dict[str, Any]) -> None:
    """A spike is significant only at least ``SPIKE_Z`` standard errors from zero, its timing and width counted.

    Its F-test holds the timing and the width as known; the standard error
    does not (:func:`_spike_timing_error`, :func:`_spike_width_error`).  A
    height the timing or the width could take away is no finding.
    """
    res["fit"]["significance_rule"] += (
        f"; a reversal spike also must be at least {SPIKE_Z:g} of its standard errors from zero, which count its "
        "onset's timing and its width"
    )
    ranking = {r["pattern"]: r for r in res["ranking"]}
    for key, p in res["parameters"].items():
        if not (key.startswith("reversal_spike_") and p["significant"] and p["stderr"] is not None):
            continue
        if abs(p["value"]) < SPIKE_Z * p["stderr"]:
            why = (f"its height, {p['value']:.3g} um, is within {SPIKE_Z:g} standard errors ({p['stderr']:.2g} um) "
                   "of zero once its onset's timing and its width are counted")
            p["significant"] = False
            p["significance_reason"] = why
            r = ranking.get(key[: -len("_um")])
            if r is not None:
                r["significant"], r["significance_reason"] = False, why


def _credible_backlash(fit: FitResult, kappa: float, min_um: float) -> dict[str, float]:
    """The fit's values with a backlash that is no finding set to 0.

    What decides an axis' lost-motion model and where its table reverses: a
    take-up angle grows as the root of the backlash (0.04 deg for 0.03 um at
    R 100 mm), so a backlash of nothing, from noise or from a spike's misfit
    leaking into the step, would move the spikes' onset by several samples and
    feed on itself.  A backlash counts when it exceeds three standard errors
    (inflated by ``kappa`` for correlated residuals) and the minimum effect.
    """
    out = _values(fit)
    slices = fit.column_slices()
    for key, name in (("backlash_x_um", "backlash_x"), ("backlash_y_um", "backlash_y")):
        if key in out:
            se = math.sqrt(max(float(fit.cov[slices[name].start, slices[name].start]) * kappa, 0.0))
            if abs(out[key]) <= max(3.0 * se, min_um):
                out[key] = 0.0
    return out


def _values(fit: FitResult) -> dict[str, float]:
    out: dict[str, float] = {}
    j = 0
    for pat, used in zip(fit.patterns, fit.used, strict=True):
        for k, f in enumerate(pat.fields):
            if used:
                out[f] = float(fit.x[j + k])
        j += pat.q
    return out


def search_samples(
    plan: TestPlan,
    timing: Timing,
    t: np.ndarray,
    windows: dict[int, tuple[float, float]],
    sample_hz: float,
    near_deg: tuple[float, float],
    near_spacing_deg: float,
) -> np.ndarray:
    """Indices of the samples a timing search works on.

    The arc-start lag and the spikes' width show where the model has sharp
    features: at the axis reversals (steps, take-up, spikes) and the
    master-slave changeovers, every 45 deg.  Within ``near_deg`` (before,
    after in the direction of travel) of each point at ``timing``, samples are
    kept up to one per ``near_spacing_deg``; elsewhere a thinned, even set of
    about ``SEARCH_SAMPLES_PER_CIRCLE`` per circle.
    """
    spacing = math.degrees(timing.feed_mm_s / plan.radius_mm / sample_hz) if sample_hz > 0 else 0.0
    near_step = max(1, int(near_spacing_deg / spacing)) if spacing > 0 else 1
    keep = []
    for d in plan.direction_list:
        a, b = windows[d]
        idx = np.flatnonzero((t >= a) & (t <= b))
        if idx.size == 0:
            continue
        u = timing.sched.angle_deg(plan, d, t[idx] - timing.t_ref)
        pos = np.mod(d * u, 45.0)  # travel past the last 45 deg point
        near = (pos <= near_deg[1]) | (pos >= 45.0 - near_deg[0])
        sel = np.zeros(idx.size, dtype=bool)
        sel[:: max(1, idx.size // SEARCH_SAMPLES_PER_CIRCLE)] = True
        sel[np.flatnonzero(near)[::near_step]] = True
        keep.append(idx[sel])
    return np.concatenate(keep) if keep else np.empty(0, dtype=np.int64)


def spike_width_bounds(
    plan: TestPlan, options: AnalysisOptions, feed_mm_s: float, sample_hz: float
) -> tuple[tuple[float, float], str]:
    """The spike width's search range (deg) at this sample rate, and why spikes cannot be sized at all ("").

    A spike is sized from the samples on its decay: it needs ``RESOLVE_SAMPLES``
    of them per width, so the range starts there (or at the configured minimum).
    """
    spacing = math.degrees(feed_mm_s / plan.radius_mm / sample_hz) if sample_hz > 0 else math.inf
    lo = max(options.spike_width_min_deg, RESOLVE_SAMPLES * spacing)
    hi = options.spike_width_max_deg
    if not lo * 1.5 < hi:
        return (min(lo, hi), hi), (
            f"below the resolution at {sample_hz:.6g} Hz: the samples are {spacing:.2f} deg apart and the widest "
            f"spike searched for decays within {hi:g} deg (spike_width_max_deg)"
        )
    return (lo, hi), ""


@dataclass
class _SampleSet:
    idx: np.ndarray  # into the test's samples
    windows: dict[int, tuple[float, float]]  # per direction: the data arc's samples, whatever the lag tried
    # per direction, what every timing shares (:meth:`_LagSearch.parts`): the times from the feed-in, the
    # deviation (um) and the minutes from the drift's origin
    parts: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None


class _LagSearch:
    """Estimate the per-move overhead (the arc start's lag) and the spike width.

    The objective is the profile negative log-likelihood of the full model on a
    fixed set of samples (:func:`search_samples`), ``(n_eff / 2) ln SSE``, plus
    ``c^2 / (2 s^2)`` with ``s`` = 50 ms: where the data cannot see the lag, it
    stays near zero.

    On point samples the likelihood is a staircase: a sharp onset (a spike's, a
    step's) moves between two samples without changing the fit, and an
    exponential spike trades a shift for its height exactly.  A bracketing
    optimiser stops on whichever stair it meets, so the timing is found on grids
    and descents smoothed at their own scale (:meth:`run`: where it lies), then
    on point samples (:meth:`finish`: the lowest stair near, its middle).  The
    width is found on a grid in ``ln w`` refined about the best (:meth:`width`).
    """

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig,
        options: AnalysisOptions,
        patterns: Sequence[Pattern],
        t: np.ndarray,
        L: np.ndarray,
        fi: StepEvent,
        span: float,
        base: Timing,
        windows: dict[int, tuple[float, float]],
        tau: float | None,
        width_bounds: tuple[float, float],
        accel_s: float | None = None,
    ) -> None:
        self.plan, self.machine, self.options, self.patterns = plan, machine, options, patterns
        self.accel_s = accel_s
        self.t, self.L, self.fi, self.span, self.base, self.windows = t, L, fi, span, base, windows
        self.tau, self.width_bounds = tau, width_bounds
        self.sample_hz = _rate(t)
        # the angle one sample covers: the search's smoothing of the sharp features is at least that wide
        self.sample_rad = base.feed_mm_s / plan.radius_mm / self.sample_hz if self.sample_hz > 0 else 0.0
        self.aperture_rad = 0.0
        self.kappa = 1.0
        self.omega = base.feed_mm_s / plan.radius_mm  # rad/s
        # the finest timing scale the descents resolve (s): a sample period, where the point samples' stairs begin
        self.fine_s = min(1.0 / self.sample_hz, FINE_SCALE_S) if self.sample_hz > 0 else FINE_SCALE_S
        # a descent from a timing found at corrections that moved little starts this far apart (s)
        self.local_s = max(NEWTON_LOCAL_S, self.fine_s)
        self.lo_c, self.hi_c = -min(options.max_lag_s, LAG_SEARCH_BELOW_S), options.max_lag_s
        start = {}
        self.p = 0
        for pat in patterns:
            start[pat.name] = self.p
            self.p += pat.q
        self.spike_cols = np.array([p.reversal is not None for p in patterns for _ in range(p.q)], dtype=bool)
        # how much worse (nats) the spike-free model may be than the full one before the spikes' joint test,
        # their heights and width as parameters, calls them significant
        self.spike_nats = float(stats.chi2.isf(options.significance, int(self.spike_cols.sum()) + 1)) / 2
        # how much worse (nats) the model without the feed-in's extra wait may be before the wait is kept
        self.wait_nats = float(stats.chi2.isf(options.significance, 1)) / 2
        self.last_x = np.zeros(0)  # the full model's coefficients of the last sse()
        self._memo: dict[tuple[object, ...], tuple[float, float, np.ndarray]] = {}  # sse() by timing and width
        self._memo_for: tuple[object, ...] = ()  # ... on this sample set, correction and lost-motion model
        self.by_direction = {}  # per direction: its patterns and their columns among all
        for d in plan.direction_list:
            mine = _for_direction(patterns, d)
            self.by_direction[d] = (mine, np.array([start[p.name] + k for p in mine for k in range(p.q)], dtype=int))
        self.coarse = self.samples(base, windows, COARSE_NEAR_DEG, COARSE_SPACING_DEG)
        self.fine = self.coarse
        # the objective being searched (:meth:`_begin`): its samples, corrections, timing and lowest full value
        self._begin(self.coarse, None, LostMotion(), _Hyper())

    def samples(
        self, timing: Timing, windows: dict[int, tuple[float, float]], near: tuple[float, float], spacing: float
    ) -> _SampleSet:
        idx = search_samples(self.plan, timing, self.t, windows, self.sample_hz, near, spacing)
        return _SampleSet(idx, windows)

    def fine_samples(self, c: float, wait: float = 0.0) -> _SampleSet:
        """Every sample near the features where they are at lag ``c`` and extra wait ``wait``, in the data arcs
        there but for what the lags still to be tried could move in or out (the features at the arcs' ends
        included)."""
        timing = self.timing(c, self.shifts(wait))
        windows = {}
        for d in self.plan.direction_list:
            a, b = timing.window(d)
            windows[d] = (a + FINE_TRIM_S, b - FINE_TRIM_S) if b - a > 4 * FINE_TRIM_S else (a, b)
        return self.samples(timing, windows, FINE_NEAR_DEG, FINE_SPACING_DEG)

    def timing(self, c: float, shift_s: dict[int, float] | None = None) -> Timing:
        V = feed_from_span(self.plan, self.span, c, self.accel_s)
        timing = make_timing(self.plan, self.fi.t_s, V, c, shift_s, self.accel_s)
        timing.t_mid = self.base.t_mid
        return timing

    def joint(
        self, at: _SampleSet, hyper: _Hyper, offset: Offset | None, lost: LostMotion, keep: bool = False
    ) -> _Joint:
        return _Joint(self.plan, self.machine, self.patterns, self.timing(hyper.overhead_s, hyper.shift_s),
                      hyper.spike_width_deg, self.t[at.idx], self.L[at.idx], offset, keep, at.windows, self.tau, lost)

    def sse(
        self,
        at: _SampleSet,
        c: float,
        w_deg: float,
        offset: Offset | None,
        lost: LostMotion,
        shift_s: dict[int, float] | None = None,
    ) -> tuple[float, float]:
        """The residual sums of squares on ``at`` at lag ``c`` and spike width ``w_deg``: of the full model, and
        of the model without the reversal spikes (:meth:`sse_many` of one timing)."""
        return self.sse_many(at, [(c, shift_s)], w_deg, offset, lost)[0]

    def sse_many(
        self,
        at: _SampleSet,
        points: Sequence[tuple[float, dict[int, float] | None]],
        w_deg: float,
        offset: Offset | None,
        lost: LostMotion,
    ) -> list[tuple[float, float]]:
        """:meth:`sse` at each ``(lag, shifts)`` of ``points``; ``last_x``: the full model's coefficients at the
        last.

        By the normal equations of the column-scaled design, and the sum of
        squares as ``y'y - 2 x'b + x'Gx`` (exact for any ``x``, so second order
        in the solution's rounding; the cancellation costs about 4 of 16 digits
        at the misfits seen): several times cheaper than folding a QR factor or
        forming the residual, and this runs hundreds of times a test.  The
        searches revisit timings: the values are kept, for one sample set,
        correction and lost-motion model.  The timings not kept yet are
        evaluated together, as one stack of samples (``SEARCH_BATCH_ROWS`` at
        most): at low rates each timing's samples are few and the cost is
        per call, not per sample.
        """
        self._memo_context(at, offset, lost)
        keys = [(c, w_deg, self.aperture_rad, *sorted((shift or {}).items())) for c, shift in points]
        todo: dict[tuple[object, ...], tuple[float, dict[int, float] | None]] = {}
        for key, point in zip(keys, points, strict=True):
            if key not in self._memo:
                todo.setdefault(key, point)
        if todo:
            parts = self.parts(at)
            per = max(1, SEARCH_BATCH_ROWS // max(sum(v[0].size for v in parts.values()), 1))
            items = list(todo.items())
            for i in range(0, len(items), per):
                chunk = items[i : i + per]
                for (key, _), value in zip(chunk, self._evaluate(parts, [v for _, v in chunk], w_deg, offset, lost),
                                           strict=True):
                    self._memo[key] = value
        out = [self._memo[key] for key in keys]
        self.last_x = out[-1][2]
        return [(full, bare) for full, bare, _ in out]

    def sse_widths(
        self, at: _SampleSet, c: float, widths_deg: Sequence[float], offset: Offset | None, lost: LostMotion,
        shift_s: dict[int, float] | None = None,
    ) -> list[float]:
        """The full model's sums of squares on ``at`` at lag ``c`` and each spike width (kept as :meth:`sse_many`
        keeps its own; the widths not kept yet evaluated together, :meth:`_evaluate_widths`)."""
        self._memo_context(at, offset, lost)
        keys = [(c, w, self.aperture_rad, *sorted((shift_s or {}).items())) for w in widths_deg]
        todo = [(key, w) for key, w in zip(keys, widths_deg, strict=True) if key not in self._memo]
        if todo:
            got = self._evaluate_widths(self.parts(at), (c, shift_s), [w for _, w in todo], offset, lost)
            for (key, _), value in zip(todo, got, strict=True):
                self._memo[key] = value
        return [self._memo[key][0] for key in keys]

    def _memo_context(self, at: _SampleSet, offset: Offset | None, lost: LostMotion) -> None:
        """The kept objectives hold for one sample set, correction and lost-motion model: forget them for
        another."""
        context = (at, offset, lost)
        if len(self._memo_for) != 3 or any(a is not b for a, b in zip(context, self._memo_for, strict=True)):
            self._memo, self._memo_for = {}, context

    def parts(self, at: _SampleSet) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per direction, the samples of ``at`` in its window: times from the feed-in (the timings' reference),
        deviation (um) and minutes from the drift's origin."""
        if at.parts is None:
            t, L = self.t[at.idx], self.L[at.idx]
            at.parts = {}
            for d in self.by_direction:
                lo, hi = at.windows[d]
                m = (t >= lo) & (t <= hi)
                at.parts[d] = (t[m] - self.fi.t_s, (L[m] - self.plan.radius_mm) * 1000.0,
                               (t[m] - self.base.t_mid) / 60.0)
        return at.parts

    def _evaluate(
        self,
        parts: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]],
        points: Sequence[tuple[float, dict[int, float] | None]],
        w_deg: float,
        offset: Offset | None,
        lost: LostMotion,
    ) -> list[tuple[float, float, np.ndarray]]:
        """Full and spike-free sums of squares and the full model's coefficients at each timing of ``points``:
        the timings' samples stacked into one geometry (:attr:`.patterns.Geometry.feeds`), one Gram matrix of
        ``[A | y]`` per timing."""
        timings = [self.timing(c, shift) for c, shift in points]
        return self._solve_grams({d: self._direction_gram(d, parts[d], timings, w_deg, offset, lost)
                                  for d in self.by_direction if parts[d][0].size}, len(points))

    def _evaluate_widths(
        self,
        parts: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]],
        point: tuple[float, dict[int, float] | None],
        widths_deg: Sequence[float],
        offset: Offset | None,
        lost: LostMotion,
    ) -> list[tuple[float, float, np.ndarray]]:
        """:meth:`_evaluate` of one timing at several spike widths: everything but the spike columns is the
        same at each, so it is made once, and only the spikes' blocks of the Gram matrix per width."""
        timing = self.timing(*point)
        grams = {}
        for d, (patterns, cols) in self.by_direction.items():
            if not parts[d][0].size:
                continue
            g = self._geometry(d, parts[d], [timing], lost)
            at = np.cumsum([0] + [p.q for p in patterns])
            steady = [i for i, p in enumerate(patterns) if p.reversal is None]
            spikes = [i for i, p in enumerate(patterns) if p.reversal is not None]
            # the steady columns and y, and the spikes' columns, in the direction's [A | y]
            rest = np.array([c for i in steady for c in range(at[i], at[i + 1])] + [cols.size])
            sharp = np.array([c for i in spikes for c in range(at[i], at[i + 1])], dtype=int)
            N = np.empty((g.u.size, rest.size))  # [A without the spikes | y]
            design([patterns[i] for i in steady], g, 0.0, out=N[:, :-1])
            N[:, -1] = parts[d][1] - offset(g) if offset is not None else parts[d][1]
            gram = np.empty((len(widths_deg), cols.size + 1, cols.size + 1))
            gram[:, rest[:, None], rest] = N.T @ N
            for i, w_deg in enumerate(widths_deg):
                S = design([patterns[j] for j in spikes], g, math.radians(w_deg))
                NS = N.T @ S
                gram[i, rest[:, None], sharp] = NS
                gram[i, sharp[:, None], rest] = NS.T
                gram[i, sharp[:, None], sharp] = S.T @ S
            grams[d] = gram
        return self._solve_grams(grams, len(widths_deg))

    def _solve_grams(self, grams: dict[int, np.ndarray], k: int) -> list[tuple[float, float, np.ndarray]]:
        """Full and spike-free sums of squares and the full model's coefficients from each direction's stack of
        ``[A | y]`` Gram matrices (k, q + 1, q + 1), its columns placed among the model's."""
        G = np.zeros((k, self.p, self.p))
        b = np.zeros((k, self.p))
        yy = np.zeros(k)
        for d, gram in grams.items():
            cols = self.by_direction[d][1]
            q = cols.size
            G[:, cols[:, None], cols] += gram[:, :q, :q]
            b[:, cols] += gram[:, :q, q]
            yy += gram[:, q, q]
        x = _normal_solve_many(G, b)
        full = _sse_at(x, G, b, yy)
        bare = full
        if self.spike_cols.any():
            use = ~self.spike_cols
            Gu, bu = G[:, use][:, :, use], b[:, use]
            bare = _sse_at(_normal_solve_many(Gu, bu), Gu, bu, yy)
        return [(float(full[i]), float(bare[i]), x[i]) for i in range(k)]

    def _direction_gram(
        self,
        d: int,
        part: tuple[np.ndarray, np.ndarray, np.ndarray],
        timings: Sequence[Timing],
        w_deg: float,
        offset: Offset | None,
        lost: LostMotion,
    ) -> np.ndarray:
        """One direction's Gram matrices of ``[A | y]`` (k, q + 1, q + 1), its samples stacked by timing."""
        patterns, cols = self.by_direction[d]
        y0 = part[1]
        k, n = len(timings), y0.size
        g = self._geometry(d, part, timings, lost)
        q = cols.size
        MT = np.empty((q + 1, g.u.size))  # [A | y] transposed: each column contiguous, stacked by timing
        design(patterns, g, math.radians(w_deg), out=MT[:q].T)
        MT[q].reshape(k, n)[:] = y0
        if offset is not None:
            MT[q] -= offset(g)
        X = MT.reshape(q + 1, k, n).transpose(1, 0, 2)
        return np.asarray(np.matmul(X, X.transpose(0, 2, 1)))

    def _geometry(
        self, d: int, part: tuple[np.ndarray, np.ndarray, np.ndarray], timings: Sequence[Timing], lost: LostMotion
    ) -> Geometry:
        """Direction ``d``'s samples of ``part`` at each of ``timings``, stacked (:attr:`.patterns.Geometry.feeds`)."""
        t_rel, _, t_min = part
        k = len(timings)
        # Schedule.angle_deg of each timing, as one expression over the stack
        start = np.array([[tm.sched.data_start_s[d]] for tm in timings])
        feed = np.array([[tm.feed_mm_s] for tm in timings])
        u_deg = data_start_deg(self.plan, d) + d * np.degrees(feed * (t_rel - start) / self.plan.radius_mm)
        u = np.radians(u_deg).reshape(-1)
        return Geometry(
            u=u, d=np.full(u.size, float(d)), t_min=np.tile(t_min, k), V=timings[0].feed_mm_s,
            R=self.plan.radius_mm, pitch_x_mm=self.machine.pitch_x_mm, pitch_y_mm=self.machine.pitch_y_mm,
            travel=d * (u - math.radians(arc_start_deg(self.plan, d))), loop_lag_s=self.tau,
            aperture_rad=self.aperture_rad, feeds=feed[:, 0] if k > 1 else None, **lost.geometry(self.tau),
        )

    def width_error(self, hyper: _Hyper, offset: Offset | None, lost: LostMotion) -> tuple[float, dict[str, float]]:
        """The spike width's standard error in ``ln w`` and each spike height's change per unit ``ln w``.

        From the full model's likelihood on the fine set at ``w`` and ``w e^(+-d)``: its curvature, and the
        heights' central difference.  A spike height and its width trade off (a wider decay with a lower
        start fits much the same samples); the width is fitted, so that is part of the height's error.
        """
        n = self.fine.idx.size
        d = WIDTH_STEP_LN
        vals, xs = [], []
        for k in (-1, 0, 1):
            full, _ = self.sse(self.fine, hyper.overhead_s, hyper.spike_width_deg * math.exp(k * d), offset, lost,
                               hyper.shift_s)
            vals.append(0.5 * n / self.kappa * math.log(full + n * SSE_FLOOR_UM**2))
            xs.append(self.last_x)
        curv = (vals[0] - 2 * vals[1] + vals[2]) / d**2
        sigma = 1.0 / math.sqrt(curv) if curv > 0 else math.inf
        names = [p.name for p in self.patterns for _ in range(p.q)]
        slope = {f"{nm}_um": float((xs[2][j] - xs[0][j]) / (2 * d)) for j, nm in enumerate(names) if self.spike_cols[j]}
        return sigma, slope

    def timing_spread(
        self, offset: Offset | None, lost: LostMotion, hyper: _Hyper
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """The timing's covariance in (lag, wait), and the full model's coefficients' change per unit of each.

        The timing is fixed by the same samples as the patterns, so what moves
        with it is uncertain by as much as it is: a pattern that trades with
        the timing (above all, with a large servo mismatch, the scale mismatch
        with the two arcs' relative start: the wait) is known only as well as
        the timing.  The timing rules (each stair's middle, the spike-free
        model's choice) take any timing the full model cannot tell from its
        best, so the spread is that region's, ``LAG_CI_NATS`` (not the
        likelihood's own curvature): its ellipse from a quadratic fitted to a
        3 x 3 stencil of the objective smoothed at a sample (the envelope, not
        the stairs), spaced as the region, found twice.  The coefficients'
        change is their least-squares slope over the same stencil.  None where
        the lag was not searched or the objective is no bowl there.
        """
        if not self.options.estimate_lag or self.fine.idx.size <= 50:
            return None
        self._begin(self.fine, offset, lost, replace(hyper))
        try:
            return self._timing_spread(hyper)
        finally:
            self.aperture_rad = 0.0

    def _timing_spread(self, hyper: _Hyper) -> tuple[np.ndarray, np.ndarray] | None:
        self.smooth(self.fine_s)
        here = np.array([hyper.overhead_s, hyper.wait_s])
        se = hyper.lag_stderr_s if math.isfinite(hyper.lag_stderr_s) and hyper.lag_stderr_s > 0 else self.fine_s
        steps = np.array([max(se, self.fine_s), max(2.0 * se, self.fine_s)])
        if not hyper.wait_free:  # the lag alone: no wait was fitted
            grid = np.array([(a, 0) for a in (-2, -1, 0, 1, 2)], dtype=float)
        else:
            grid = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], dtype=float)
        region, slope = None, None
        for _ in range(2):
            points = [self.bounded(*(here + steps * g)) for g in grid]
            self.prefetch(points)
            vals, coefs = [], []
            for c, w in points:
                vals.append(self.objs(c, w)[0])
                coefs.append(self.last_x)
            x = (np.array(points) - here) / steps
            if hyper.wait_free:
                _, hess = _quadratic_minimum(x, np.array(vals), NEWTON_REACH)
                if hess is None:
                    return None
                region = 2.0 * LAG_CI_NATS * np.linalg.inv(hess)  # in stencil units
            else:
                curv = np.polyfit(x[:, 0], np.array(vals), 2)[0] * 2.0
                if not curv > 0:
                    return None
                region = np.diag([2.0 * LAG_CI_NATS / curv, 0.0])
            M = np.column_stack([np.ones(len(points)), x])
            slope = np.linalg.lstsq(M, np.array(coefs), rcond=None)[0][1:].T  # (p, 2), per stencil unit
            half = np.sqrt(np.maximum(np.diag(region), 0.0))
            if not hyper.wait_free:
                half[1] = 1.0
            if np.all((half > 0.5) & (half < 2.0)):
                break
            steps = steps * np.clip(half, 0.25, 4.0)
        assert region is not None and slope is not None
        return np.diag(steps) @ region @ np.diag(steps), slope @ np.diag(1.0 / steps)

    # ------------------------------------------------------------------------------------------ the objective

    def _begin(self, at: _SampleSet, offset: Offset | None, lost: LostMotion, hyper: _Hyper) -> None:
        """Search ``hyper`` on ``at`` with these corrections: the objective's context, until the next begin."""
        self.at, self.offset, self.lost, self.hyper = at, offset, lost, hyper
        self.best = math.inf

    def nll(self, value: float) -> float:
        """The profile negative log-likelihood of a sum of squares on the current set: a residual below 1 nm
        rms is numerical, not signal, and there the prior decides."""
        n = self.at.idx.size
        return 0.5 * n / self.kappa * math.log(value + n * SSE_FLOOR_UM**2)

    def objs(self, c: float, wait: float) -> tuple[float, float, float]:
        """The full and the spike-free model's objectives at ``(c, wait)``, priors included, and the prior.
        ``best`` follows the lowest full objective seen on the current objective."""
        full, bare = self.sse(self.at, c, self.hyper.spike_width_deg, self.offset, self.lost, self.shifts(wait))
        prior = c * c / (2 * LAG_PRIOR_S**2) + wait * wait / (2 * WAIT_PRIOR_S**2)
        f = self.nll(full) + prior
        self.best = min(self.best, f)
        return f, self.nll(bare) + prior, prior

    def prefetch(self, points: Sequence[tuple[float, float]]) -> None:
        """Evaluate the objectives at these ``(lag, wait)`` together (:meth:`sse_many` keeps them)."""
        if len(points) > 1:
            self.sse_many(self.at, [(c, self.shifts(w)) for c, w in points], self.hyper.spike_width_deg,
                          self.offset, self.lost)

    def smooth(self, step: float | None, floor: bool = True) -> None:
        """Average the sharp features over the angle a timing step moves them (``floor``: at least a sample's):
        the objective is then smooth at that scale, and its stairs and narrow wells are not missed.  None:
        point samples, as the data are and the final fit takes them."""
        aperture = 0.0 if step is None else max(self.sample_rad if floor else 0.0, self.omega * step)
        if self.sample_rad > math.radians(SMOOTH_MAX_SAMPLE_DEG):
            aperture = 0.0  # samples this far apart: no smoothing (a box a sample wide misfits point samples)
        if aperture != self.aperture_rad:
            self.aperture_rad = aperture
            self.best = math.inf  # another objective

    def choose(self, full: np.ndarray, bare: np.ndarray) -> int:
        return _pick(full, bare, self.best, self.spike_nats)

    def bounded(self, c: float, wait: float) -> tuple[float, float]:
        return min(max(c, self.lo_c), self.hi_c), min(max(wait, -WAIT_MAX_S), WAIT_MAX_S)

    # ------------------------------------------------------------------------------ the timing's coordinates

    def start_of(self, d: int, c: float, wait: float) -> float:
        return float(self.timing(c).sched.data_start_s[d]) + self.shifts(wait).get(d, 0.0)

    def coords(self, c: float, wait: float) -> np.ndarray:
        """What the samples fix of a timing, nearly independently: each data arc's start (s); in a test of one
        direction its start and the lag (which sets the feed)."""
        dirs = self.plan.direction_list
        if len(dirs) > 1:
            return np.array([self.start_of(d, c, wait) for d in dirs])
        return np.array([self.start_of(dirs[0], c, wait), c])

    def _inverse_jacobian(self, c: float, wait: float) -> np.ndarray:
        """d(lag, wait) / d(coords) at ``(c, wait)``: the coordinates are affine in the wait and nearly so in the
        lag (which moves the feed a little)."""
        e = 1e-4
        here = self.coords(c, wait)
        J = np.column_stack([(self.coords(c + e, wait) - here) / e, (self.coords(c, wait + e) - here) / e])
        return np.asarray(np.linalg.inv(J))

    # --------------------------------------------------------------------------------------------- the stages

    def grid(self, lo: float, hi: float, step: float, wait: bool = False) -> tuple[np.ndarray, ...]:
        """The objectives over the lag or (``wait``) the feed-in's extra wait, ``lo..hi`` about its value."""
        h = self.hyper
        now, (b0, b1) = (h.wait_s, (-WAIT_MAX_S, WAIT_MAX_S)) if wait else (h.overhead_s, (self.lo_c, self.hi_c))
        g = np.arange(max(now + lo, b0), min(now + hi, b1) + 0.5 * step, step)
        at = self.line(wait, None)
        points = [at(float(x)) for x in g]
        self.prefetch(points)
        v = np.array([self.objs(c, w) for c, w in points])
        return g, v[:, 0], v[:, 1], v[:, 2], np.array(points)

    def line(self, wait: bool, hold: int | None) -> Callable[[float], tuple[float, float]]:
        """The (lag, wait) at a coordinate of a line through the current timing: along the lag, or (``wait``)
        the wait; ``hold``: along the lag with that direction's data arc held where it starts (the wait
        follows), so that only the other arc's start and the feed move."""
        h = self.hyper
        if hold is not None:
            target = self.start_of(hold, h.overhead_s, h.wait_s)
            coef = self.shifts(1.0)[hold]
            return lambda x: (x, (target - self.start_of(hold, x, 0.0)) / coef)
        c0, w0 = h.overhead_s, h.wait_s
        return (lambda x: (c0, x)) if wait else (lambda x: (x, w0))

    def pick(self, lo: float, hi: float, step: float, wait: bool = False) -> np.ndarray:
        """Take the best timing of a smoothed grid along the lag or the wait; return the full objectives."""
        self.smooth(step)
        _, full, bare, _, points = self.grid(lo, hi, step, wait)
        self.hyper.overhead_s, self.hyper.wait_s = (float(v) for v in points[self.choose(full, bare)])
        return np.asarray(full)

    def width(self) -> None:
        """The spikes' width: the full model's best in ``ln w`` over its range.

        The objective is smooth in the width, but not always of one well: a grid over the range
        (``WIDTH_GRID`` points), then about the best a step a third as wide either side and the vertex of the
        parabola through the three, while the step is above ``WIDTH_XTOL``.  Each round's widths are made
        together at this timing, where only the spikes' columns differ (:meth:`sse_widths`).
        """
        h = self.hyper
        lo, hi = (math.log(v) for v in self.width_bounds)
        seen: dict[float, float] = {}

        def evaluate(lws: Sequence[float]) -> None:
            new = [lw for lw in dict.fromkeys(min(max(v, lo), hi) for v in lws) if lw not in seen]
            if new:
                values = self.sse_widths(self.at, h.overhead_s, [math.exp(v) for v in new], self.offset, self.lost,
                                         self.shifts(h.wait_s))
                seen.update(zip(new, values, strict=True))

        evaluate(list(np.linspace(lo, hi, WIDTH_GRID)))
        step = (hi - lo) / (WIDTH_GRID - 1)
        while step > WIDTH_XTOL:
            best = min(seen, key=seen.__getitem__)
            step /= 3.0
            evaluate([best - step, best + step])
            a, b = seen[max(best - step, lo)], seen[min(best + step, hi)]
            bend = a + b - 2.0 * seen[best]
            if bend > 0:  # the parabola's vertex, within the step
                evaluate([best + 0.5 * step * (a - b) / bend])
        h.spike_width_deg = float(math.exp(min(seen, key=seen.__getitem__)))

    def newton(
        self, value: Callable[[tuple[float, float, float]], float], h0: float, h_min: float, floor: bool = True
    ) -> None:
        """Move the timing to the minimum of ``value`` (of :meth:`objs`) smoothed at a shrinking scale.

        Around the current timing a 3 x 3 stencil of the coordinates (:meth:`coords`), ``h`` apart, is
        evaluated at once with the features averaged over ``h`` (:meth:`smooth`; ``floor``: over a sample at
        least); a quadratic fitted to it proposes its minimum (at most ``NEWTON_REACH`` spacings away), and the
        best of the ten points is the next centre.  The next stencil is turned along the fitted bowl's axes
        and stretched (by up to ``NEWTON_STRETCH``) where it is flat: a valley the two arcs' starts trade along
        at a slant (each moves the feed too; free spikes or a large servo pattern trade with the wait) is
        followed, not crossed by steps along the axes.  ``h`` shrinks by ``NEWTON_SHRINK`` once the minimum is
        within half a spacing, from ``h0`` down to ``h_min``.
        """
        h = self.hyper
        step = max(h0, h_min)
        axes = np.eye(2)  # the stencil's axes in the coordinates, per unit spacing: along the valley, stretched
        grid = np.array([(a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)], dtype=float)
        for _ in range(NEWTON_STEPS):
            self.smooth(step, floor)
            here = np.array([h.overhead_s, h.wait_s])
            base = self.coords(*here)
            to_timing = self._inverse_jacobian(*here) @ axes * step  # stencil units -> (lag, wait)
            points = [self.bounded(*(here + to_timing @ o)) for o in grid]
            self.prefetch(points)
            vals = [value(self.objs(c, w)) for c, w in points]
            to_stencil = np.linalg.inv(axes) / step  # coordinates -> stencil units
            where = [to_stencil @ (self.coords(c, w) - base) for c, w in points]
            proposal, hess = _quadratic_minimum(np.array(where), np.array(vals), NEWTON_REACH)
            if proposal is not None:
                p = self.bounded(*(here + to_timing @ proposal))
                points.append(p)
                vals.append(value(self.objs(*p)))
                where.append(to_stencil @ (self.coords(*p) - base))
            k = int(np.argmin(vals))
            h.overhead_s, h.wait_s = points[k]
            if hess is not None:  # the next stencil along the bowl's axes, stretched where it is flat
                curv, turn = np.linalg.eigh(to_stencil.T @ hess @ to_stencil)
                stretch = np.sqrt(curv.max() / np.maximum(curv, FLAT_CURVATURE * curv.max()))
                axes = turn * np.minimum(stretch, NEWTON_STRETCH)
            if float(np.abs(where[k]).max()) < 0.5:  # within half a spacing: look closer, or stop at the finest
                if step <= h_min * 1.0001:
                    break
                step = max(step / NEWTON_SHRINK, h_min)

    def stair(self, hold: int | None = None, wait: bool = False) -> float:
        """Move to the middle of the stair the timing stands on, along a :meth:`line`; return a uniform spread
        over it.

        On point samples the likelihood is a staircase: a sharp onset moves between two samples without
        changing the fit, so every timing on a stair fits the samples equally, and its middle is the least
        biased.  The stair is where the spike-free likelihood stays within ``STAIR_NATS`` of its value here,
        among the timings the full model cannot tell from its best (or where the spike-free model is within
        the spikes' joint test of it).  Its edges are bracketed by steps doubling from ``STAIR_FIRST`` sample
        periods either way (out to the stair reach), then bisected; both edges are worked on together.
        """
        self.smooth(None)
        at = self.line(wait, hold)
        x0 = self.hyper.wait_s if wait else self.hyper.overhead_s
        _, b, p = self.objs(*at(x0))
        level = b - p + STAIR_NATS  # the stair is a level of the likelihood, not of the prior

        def on(x: float) -> bool:
            f, b, p = self.objs(*at(x))
            return (f <= self.best + LAG_CI_NATS or b <= self.best + self.spike_nats) and b - p <= level

        period = 1.0 / self.sample_hz
        reach = max(0.5 * period, min(STAIR_REACH_S, STAIR_SAMPLES * period))
        inside = [x0, x0]  # per side (-, +): the farthest point found on the stair, and the nearest off it
        outside: list[float | None] = [None, None]

        def probe(xs: dict[int, float]) -> None:  # per side, a point: on the stair or off it (evaluated together)
            self.prefetch([at(x) for x in xs.values()])
            for k, x in xs.items():
                if on(x):
                    inside[k] = x
                else:
                    outside[k] = x

        step = min(STAIR_FIRST * period, reach)
        while any(o is None for o in outside):
            probe({k: x0 + (2 * k - 1) * step for k in (0, 1) if outside[k] is None})
            if step >= reach:
                break
            step = min(2 * step, reach)
        for _ in range(STAIR_BISECT):  # both brackets halved together
            if all(o is None for o in outside):
                break
            probe({k: 0.5 * (inside[k] + o) for k, o in enumerate(outside) if o is not None})
        edges = [inside[k] if o is None else 0.5 * (inside[k] + o) for k, o in enumerate(outside)]
        self.hyper.overhead_s, self.hyper.wait_s = at(0.5 * (edges[0] + edges[1]))
        return float(abs(edges[1] - edges[0]) / math.sqrt(12.0))

    # -------------------------------------------------------------------------------------------- the search

    def run(
        self,
        offset: Offset | None,
        lost: LostMotion,
        start: _Hyper | None = None,
        misfit_only: bool = False,
        local: bool = False,
    ) -> _Hyper:
        """The timing at these corrections.  ``start``: refine from there on the fine set (no search over the
        whole range).  ``misfit_only``: only the best timing is wanted (a loop gain's profile value).
        ``local``: ``start`` is near (the corrections moved little since it was found): only the smoothed
        descent, not the grids.  The point-sample finish (:meth:`finish`) is the caller's, once the
        corrections have settled.

        The grids (over the whole lag range on the coarse set, then the lag and the feed-in's extra wait
        about the best on the fine set) are smoothed at their steps, so that no narrow well is stepped over;
        :meth:`newton` then finds the smoothed objective's minimum in both arcs' starts down to a sample
        period.

        The feed-in may also cost more or less than the arcs (``wait_s``): a control that waits for
        in-position after each move waits longer after a move whose axes end with more following error (the
        feed-in ends radially, the arcs tangentially; with unequal gains on other axes).  With equal
        overheads for the rest, the ``k``-th of ``n`` data arcs then runs ``(n + 1 - k) / (n + 1)`` of that
        difference later (the feed itself, from the span, is unchanged).  It is found on a grid too, with a
        weak prior (``WAIT_PRIOR_S``) where the data cannot see it.
        """
        options = self.options
        hyper = _Hyper() if start is None else replace(start)
        self._begin(self.coarse if start is None else self.fine, offset, lost, hyper)
        spikes = _has_spikes(self.patterns)
        if start is None:
            hyper.spike_width_deg = min(max(DEFAULT_SPIKE_WIDTH_DEG, self.width_bounds[0]), self.width_bounds[1])
        if options.estimate_lag and start is None:
            self.pick(self.lo_c - hyper.overhead_s, self.hi_c - hyper.overhead_s, LAG_GRID_S[0])
            # from here on every sample near the features, where they are at this lag
            self.fine = self.fine_samples(hyper.overhead_s)
            self._begin(self.fine, offset, lost, hyper)
        local = local and start is not None
        if spikes and not local:
            self.smooth(LAG_GRID_S[1])
            self.width()
        if options.estimate_lag:
            if not local:
                reach = LAG_GRID_S[0] if start is None else LAG_GRID_S[0] / 2
                full = self.pick(-reach, reach, LAG_GRID_S[1])
                if full.size >= 5:  # the lag's uncertainty: the full objective's curvature over that grid
                    g = np.arange(full.size) * LAG_GRID_S[1]
                    a2 = np.polyfit(g - g[int(np.argmin(full))], full, 2)[0]
                    hyper.lag_stderr_s = 1.0 / math.sqrt(2 * a2) if a2 > 0 else float("inf")
                # the feed-in's extra wait over its whole range (the lag's grids above held it at 0)
                if start is None or misfit_only:  # (from another loop gain's timing: the wait moves with the gain)
                    self.pick(-WAIT_GRID_S[0] * WAIT_GRID_S[1], WAIT_GRID_S[0] * WAIT_GRID_S[1], WAIT_GRID_S[0],
                              wait=True)
            self.newton(lambda o: o[0], self.local_s if local else NEWTON_START_S, self.fine_s)
        elif spikes and start is None:
            self.fine = self.fine_samples(hyper.overhead_s)
            self._begin(self.fine, offset, lost, hyper)
            self.width()
        hyper.shift_s = self.shifts(hyper.wait_s)
        self.aperture_rad = 0.0
        return hyper

    def finish(self, offset: Offset | None, lost: LostMotion, start: _Hyper) -> _Hyper:
        """The timing on point samples, as the data are and the final fit takes them, from :meth:`run`'s.

        Spikes and timing trade off: where a reversal carries a step (backlash,
        above all a compensation step filtered by the loop), a lag that puts
        the step a sample off leaves a residual the shape of a spike, and the
        free spike heights take it up, so the full model's likelihood can be
        flat over several milliseconds, or even a little better a sample off.
        Of the lags the full model cannot tell apart (``LAG_CI_NATS``, a 95 %
        profile interval), and of those where the model without spikes is not
        worse than the full model's best by more than the spikes' joint test
        allows (``spike_nats``: their count and the width as parameters, at the
        significance level), the one the model without spikes fits best is
        taken: spikes do not buy a timing the steps refute, and where spikes
        are real the model without them is far worse everywhere.

        On point samples the likelihood is a staircase, and where spikes are large its stairs are a fraction
        of a sample wide and tens of nats apart.  So first the smoothing is shrunk below a sample (to
        ``CONTINUE_SAMPLES``), :meth:`newton` following the minimum into the stairs (where samples are close
        enough to smooth at all); then a compass search on point samples takes the lowest stair near, and
        another, among the timings the full model cannot tell apart, the one the spike-free model fits best.
        The spikes' width is found again at that timing; the feed-in's extra wait is kept only where the data
        need it (:meth:`wait_needed`).  Last, every timing on a stair fits the samples equally and its middle is
        the least biased: the stair is resolved along the wait and along each arc's start (the other's held),
        or, without a wait, along the lag, and its middle taken.
        """
        hyper = replace(start)
        self._begin(self.fine, offset, lost, hyper)
        spikes = _has_spikes(self.patterns)
        if self.options.estimate_lag:
            dirs = self.plan.direction_list
            first = self.fine_s
            if self.sample_rad <= math.radians(SMOOTH_MAX_SAMPLE_DEG):
                # the smoothing shrunk below a sample, following the minimum into the point samples' stairs
                self.newton(lambda o: o[0], self.fine_s, CONTINUE_SAMPLES * self.fine_s, floor=False)
                first = COMPASS_FIRST * self.fine_s
            self.smooth(None)
            self.compass(lambda o: o[0], first, COMPASS_LAST * self.fine_s)
            if spikes:
                self.compass(self.bare_value, 0.5 * self.fine_s, COMPASS_LAST * self.fine_s)
                self.width()
            hyper.wait_free = self.wait_needed()
            if hyper.wait_free:
                # along the feed-in's extra wait first (both arcs' starts together: where free spikes or a large
                # servo pattern trade with the timing, the stairs are flat along it), then along each arc's start
                self.stair(wait=True)
                spread = 0.0
                for d in dirs:
                    spread = max(spread, self.stair(hold=-d if len(dirs) > 1 else d))
            else:
                spread = self.stair()  # along the lag alone
            hyper.lag_stderr_s = max(hyper.lag_stderr_s, spread)
            if spikes:
                hyper.spike_lr_search = self._spike_lr_search(replace(hyper))
        hyper.shift_s = self.shifts(hyper.wait_s)
        self.aperture_rad = 0.0
        return hyper

    def wait_needed(self) -> bool:
        """Whether the feed-in's extra wait earns its place: else the timing moves to the best lag without one.

        The wait is an optional part of the timing model (a control that waits
        for in-position after each move); where the data do not need it, a free
        wait only trades with what else moves both arcs' starts (a large servo
        pattern turned by it reads as scale mismatch).  It is kept where the
        full model without it, at its own best lag (a compass search along the
        lag), is worse by more than the chi-square test of one parameter allows
        at the significance level (``wait_nats``).
        """
        h = self.hyper
        if h.wait_s == 0.0:
            return False
        kept, with_wait = (h.overhead_s, h.wait_s), self.objs(h.overhead_s, h.wait_s)[0]
        h.wait_s = 0.0
        without = self.compass(lambda o: o[0], WAIT_LAG_STEPS * self.fine_s, COMPASS_LAST * self.fine_s,
                               dirs=((1, 0), (-1, 0)))
        if without - with_wait > self.wait_nats:
            h.overhead_s, h.wait_s = kept
            return True
        return False

    def _spike_lr_search(self, chosen: _Hyper) -> Callable[[], float]:
        """The spikes' likelihood ratio against the spike-free model at its own best timing, found when read
        (:meth:`_Hyper.spike_lr`) on this objective: at the timing the full model chose, free spikes may be
        taking up a step a sample off that another timing fits."""
        context = (self.at, self.offset, self.lost, self.kappa)

        def spike_lr() -> float:
            kept = (self.at, self.offset, self.lost, self.kappa, self.hyper, self.best, self.aperture_rad)
            self.at, self.offset, self.lost, self.kappa = context
            self.hyper, self.best = replace(chosen), math.inf
            try:
                self.smooth(None)
                full_here, _, prior_here = self.objs(chosen.overhead_s, chosen.wait_s)
                bare_only = lambda o: o[1] - o[2]  # noqa: E731
                self.newton(bare_only, self.local_s, self.fine_s)
                self.smooth(None)
                bare_best = self.compass(bare_only, 0.5 * self.fine_s, 0.05 * self.fine_s, STAIR_NATS)
            finally:
                self.at, self.offset, self.lost, self.kappa, self.hyper, self.best, self.aperture_rad = kept
            return max(bare_best - (full_here - prior_here), 0.0)

        return spike_lr

    def bare_value(self, o: tuple[float, float, float]) -> float:
        """The spike-free model's objective where the full model cannot tell the timing from its best, or where
        it is within the spikes' joint test of that best; elsewhere infinite."""
        f, b, _ = o
        return b if f <= self.best + LAG_CI_NATS or b <= self.best + self.spike_nats else math.inf

    def compass(
        self, value: Callable[[tuple[float, float, float]], float], first: float, last: float,
        gain: float = COMPASS_GAIN_NATS, dirs: Sequence[tuple[int, int]] = COMPASS_DIRS,
    ) -> float:
        """Move the timing by compass steps (``dirs`` of the lag and the wait: by default the axes and
        diagonals, evaluated together) while ``value`` falls by ``gain``, halving the step from ``first`` to
        ``last``; return the last value."""
        h = self.hyper
        here = value(self.objs(h.overhead_s, h.wait_s))
        step = first
        evals = 0
        while step >= last and evals < COMPASS_EVALS:
            steps = [self.bounded(h.overhead_s + dc * step, h.wait_s + dw * step) for dc, dw in dirs]
            self.prefetch(steps)
            vals = [value(self.objs(c, w)) for c, w in steps]
            evals += len(steps)
            k = int(np.argmin(vals))
            if vals[k] < here - gain:
                h.overhead_s, h.wait_s = steps[k]
                here = vals[k]
            else:
                step /= 2
        return here

    def shifts(self, wait_s: float) -> dict[int, float]:
        """Per direction, how much later its data arc runs when the feed-in costs ``wait_s`` more than each arc."""
        dirs = self.plan.direction_list
        n = len(dirs)
        return {d: (n - k) / (n + 1) * wait_s for k, d in enumerate(dirs)} if wait_s else {}


def _unreached_spikes(plan: TestPlan, patterns: Sequence[Pattern]) -> dict[str, str]:
    """The spikes whose reversal point a (partial) data arc never passes, with that reason."""
    out = {}
    for p in patterns:
        if p.reversal is None:
            continue
        axis, at, d = p.reversal
        start = data_start_deg(plan, d)
        if math.fmod(d * (at - start), 360.0) % 360.0 >= plan.data_arc_deg:
            end = start + d * plan.data_arc_deg
            out[p.name] = (
                f"the {'CCW' if d > 0 else 'CW'} data arc ({start:g}..{end:g} deg) does not pass the "
                f"{axis.upper()} reversal at {at:g} deg"
            )
    return out


def _width_verdict(w: float, bounds: tuple[float, float], options: AnalysisOptions, sample_hz: float) -> str:
    """Why spikes of the fitted width ``w`` (deg) are not sized, or "" when they are.

    A width on a bound of its search is no estimate: at the lower one where
    that is the sample spacing's, the spikes are below the resolution; at the
    configured lower one, the reversals show nothing as gradual as friction
    (a bump of one or two samples is noise); at the upper one, what follows
    the reversals is a smooth change of the path, not a friction spike.
    """
    lo, hi = bounds
    if w <= lo * WIDTH_AT_BOUND and lo > options.spike_width_min_deg:
        return (
            f"below the resolution at {sample_hz:.6g} Hz: the spikes decay within {w:.2f} deg or less, about "
            f"{lo / RESOLVE_SAMPLES:.2f} deg between samples; at least {RESOLVE_SAMPLES:g} samples per width are "
            "needed to size them"
        )
    if w <= lo * WIDTH_AT_BOUND:
        return (
            f"no reversal spike: the fitted width runs onto its lower bound, {lo:g} deg (spike_width_min_deg); "
            "nothing after the reversals decays as gradually as friction does"
        )
    if w >= hi / WIDTH_AT_BOUND:
        return (
            f"no reversal spike: the fitted width runs onto its upper bound, {hi:g} deg (spike_width_max_deg); what "
            "follows the reversals changes too slowly for friction"
        )
    return ""


def _quadratic_minimum(
    x: np.ndarray, values: np.ndarray, limit: float
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The minimum of the quadratic fitted (least squares) to ``values`` at the points ``x`` (m, 2), at most
    ``limit`` from 0 in either coordinate (scaled down to it), and its Hessian; ``(None, None)`` where the fit
    is no bowl."""
    x1, x2 = x[:, 0], x[:, 1]
    M = np.column_stack([np.ones_like(x1), x1, x2, 0.5 * x1 * x1, x1 * x2, 0.5 * x2 * x2])
    finite = np.isfinite(values)
    if finite.sum() < M.shape[1]:
        return None, None
    coef = np.linalg.lstsq(M[finite], values[finite] - values[finite].min(), rcond=None)[0]
    curv, turn = np.linalg.eigh(np.array([[coef[3], coef[4]], [coef[4], coef[5]]]))
    if not curv.max() > 0:
        return None, None
    # a valley narrower than the stencil fits no bowl along its floor: there the curvature is taken as nearly
    # flat, and the minimum lies along the floor, downhill, as far as the limit allows
    curv = np.maximum(curv, FLAT_CURVATURE * curv.max())
    H = turn @ np.diag(curv) @ turn.T
    p = -turn @ ((turn.T @ coef[1:3]) / curv)
    big = float(np.abs(p).max())
    if not math.isfinite(big):
        return None, None
    return (p * (limit / big) if big > limit else p), H


def _pick(full: np.ndarray, bare: np.ndarray, best: float, spike_nats: float) -> int:
    """Of the grid's timings the full model cannot tell from its ``best``, or where the spike-free model is
    within ``spike_nats`` of it, the index of the one the spike-free model fits best (the grid's own best where
    none is that close)."""
    ok = np.flatnonzero((full <= best + LAG_CI_NATS) | (bare <= best + spike_nats))
    if ok.size == 0:
        return int(np.argmin(full))
    return int(ok[np.argmin(bare[ok])])


def _normal_solve_many(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares solutions from a stack of normal equations ``G`` (k, p, p), ``b`` (k, p), column-scaled,
    rank-deficient directions left out (eigenvalues below 1e-12 of the largest).

    Where the scaled matrix is well conditioned (its inverse's Frobenius norm at most ``1e5``: every
    eigenvalue above ``1e-5``, none left out) by its inverse from the Cholesky factor, else by its
    eigen-decomposition: the same solution, to rounding, several times cheaper for the p ~ 25 of the search.
    """
    scale = np.sqrt(np.diagonal(G, axis1=1, axis2=2))
    empty = scale == 0  # a column of zeros: a row and column of zeros, which the solution leaves at 0
    scale = np.where(empty, 1.0, scale)
    Gs, bs = G / (scale[:, :, None] * scale[:, None, :]), b / scale
    if empty.any():
        Gs[:, np.arange(Gs.shape[1]), np.arange(Gs.shape[1])] += empty
    x = np.empty_like(bs)
    for i in range(len(G)):
        c, info = _potrf(Gs[i], lower=0, clean=1)
        if info == 0:
            inv, info = _potri(c, lower=0, overwrite_c=1)  # its upper triangle; the lower is zero
            diag = np.diagonal(inv)
            if info == 0 and 2.0 * np.vdot(inv, inv) - np.dot(diag, diag) <= 1e10:
                x[i] = _symv(1.0, inv, bs[i], lower=0)
                continue
        scaled = G[i] / np.outer(scale[i], scale[i])
        vals, vecs = np.linalg.eigh(scaled)
        keep = vals > vals[-1] * 1e-12
        x[i] = vecs[:, keep] @ ((vecs[:, keep].T @ bs[i]) / vals[keep])
    return x / scale


def _sse_at(x: np.ndarray, G: np.ndarray, b: np.ndarray, yy: np.ndarray) -> np.ndarray:
    """``y'y - 2 x'b + x'Gx`` of each of a stack (at least 0)."""
    xb = np.matmul(x[:, None, :], b[:, :, None])[:, 0, 0]
    xGx = np.matmul(np.matmul(x[:, None, :], G), x[:, :, None])[:, 0, 0]
    return np.asarray(np.maximum(yy - 2.0 * xb + xGx, 0.0))


def _embed(f: Factor, sub: Sequence[Pattern], full: Sequence[Pattern]) -> Factor:
    """Factor of ``sub``'s columns placed within ``full``'s (missing columns zero)."""
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    cols: list[int] = []
    for p in sub:
        cols.extend(range(pos[p.name], pos[p.name] + p.q))
    out = Factor(j)
    R = f.rows if f.R.shape[0] else f.R
    M = np.zeros((R.shape[0], j + 1))
    M[:, cols] = R[:, :-1]
    M[:, -1] = R[:, -1]
    out.R, out.n = M, f.n
    return out


class Lag(NamedTuple):
    """The position loops' mean lag for the physical servo model (:func:`loop_lag`).

    ``tau`` (s): ``(1/KX + 1/KY)/2``, None for no servo correction; ``cos2``:
    where it was measured along the feed-in/out's radial direction, that
    direction's mean ``cos 2u`` (the lag there is ``tau_bar + (m/2) cos 2u``).
    ``origin``: ``configured``, ``feed_in``, ``fast`` (no settling seen where
    it would have been), ``linear`` (chosen), ``assumed`` (a default gain) or
    ``fitted`` (to the data arcs, :func:`_profile_lag`); ``source`` says it in words.
    """

    tau: float | None
    cos2: float | None
    source: str
    origin: str


def loop_lag(
    plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, fi: StepEvent, fo: StepEvent, sample_hz: float
) -> Lag:
    """Position-loop lag for the physical servo model.

    From configured gains, or measured on the feed-in/out's approach to the
    circle.  Where no settling was seen although the rate would have shown a
    loop slower than ``FAST_LOOP_S``, the loops are fast: no correction.  Else
    the lag is assumed (a common default gain), and the result says so.
    """
    if options.servo_model == "linear":
        return Lag(None, None, "linear model chosen", "linear")
    if machine.kv_x_per_s and machine.kv_y_per_s:
        tau = 0.5 * (1.0 / machine.kv_x_per_s + 1.0 / machine.kv_y_per_s)
        return Lag(tau, None, "configured gains kv_x, kv_y", "configured")
    u_in = math.radians(arc_start_deg(plan, plan.direction_list[0]))
    resolvable_s = TAIL_SAMPLES / sample_hz if sample_hz > 0 else math.inf
    u_last = math.radians(arc_start_deg(plan, plan.direction_list[-1]))
    u_out = u_last + plan.direction_list[-1] * math.radians(plan.arc_deg)
    found = [(e.tau_s, math.cos(2 * u)) for e, u in ((fi, u_in), (fo, u_out)) if math.isfinite(e.tau_s)]
    if found:
        return Lag(
            float(np.mean([f[0] for f in found])),
            float(np.mean([f[1] for f in found])),
            "approach of the feed-in/feed-out to the circle (first-order loop fit)",
            "feed_in",
        )
    if resolvable_s <= FAST_LOOP_S:
        # A loop as slow as machines' usually are would have shown its settling at this rate.
        return Lag(None, None, (
            f"no loop settling after the feed-in: the position loops are faster than {resolvable_s * 1000:.0f} ms "
            "at this sample rate (no servo dynamics to correct)"
        ), "fast")
    return Lag(
        1.0 / DEFAULT_KV_PER_S,
        None,
        f"assumed {DEFAULT_KV_PER_S:g}/s (a common default position gain): the feed-in's settling is not "
        "resolved at this sample rate and no kv_x/kv_y is configured",
        "assumed",
    )


def analyze_test(
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    t: np.ndarray,
    L: np.ndarray,
    fi: StepEvent,
    fo: StepEvent,
    curves: bool = False,
) -> dict[str, Any]:
    """The joint fit of one test whose feed-in and feed-out are known.

    ``curves``: also return, under ``"curves"``, each data arc's samples as
    numpy arrays (not JSON; for plots): ``t_s``, ``u_deg`` (commanded angle at
    the fitted timing), ``measured_um`` (``L - R``) and ``model_um`` (the
    fitted model in the same space, physical corrections included, so that
    ``measured_um - model_um`` is the fit's residual).
    """
    check_plan(plan, fi, fo)
    lag = loop_lag(plan, machine, options, fi, fo, _rate(t))
    if lag.origin != "assumed":
        return _analyze_at(plan, machine, options, t, L, fi, fo, curves, lag)
    return _profile_lag(plan, machine, options, t, L, fi, fo, curves, lag)


def _profile_lag(
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    t: np.ndarray,
    L: np.ndarray,
    fi: StepEvent,
    fo: StepEvent,
    curves: bool,
    assumed: Lag,
) -> dict[str, Any]:
    """The fit at the position-loop gain the data arcs prefer, where the feed-in does not show it.

    At a low sample rate the feed-in's settling is not resolved, but the loop
    still shapes what the fit sees: a backlash compensation's step reaches the
    table through it, and the servo remainder is its size.  With the wrong gain
    that misfit is slow, and the slow patterns (drift above all) take it for
    signal.  The whole fit is run over a grid of gains (``PROFILE_KV_PER_S``)
    and a parabola through the best three, in the logarithm of the gain (each
    other gain's timing refined from the default's, the one taken searched
    whole again: see ``analysis/README.md``); the
    default gain stays unless another is better by more than ``PROFILE_NATS``
    of likelihood (the residual's inflation counted, its rms floored at
    ``PROFILE_FLOOR_UM``).
    """
    runs: dict[float, _Fitted] = {}

    def fit(kv: float, near: _Hyper | None) -> _Fitted | None:
        try:
            return _fit_at(plan, machine, options, t, L, fi, fo, curves, Lag(1.0 / kv, None, assumed.source, "fitted"),
                           near)
        except DataError:
            return None

    def misfit(fitted: _Fitted | None) -> float:
        # per sample, times the default's count: the runs may keep a few samples more or less
        return math.inf if fitted is None else 0.5 * n / inflation * math.log(fitted.rms_um**2 + PROFILE_FLOOR_UM**2)

    def run(kv: float) -> float:
        if kv not in runs:
            # refined, in one pass, from the default's timing moved by the change in the loop's lag: what the
            # data fix is when the table reaches each point, the arc-start lag plus the loop's
            near = replace(default.hyper, overhead_s=default.hyper.overhead_s + 1.0 / DEFAULT_KV_PER_S - 1.0 / kv)
            got = fit(kv, near)
            if got is None:
                return math.inf
            runs[kv] = got
        return misfit(runs[kv])

    default = _fit_at(plan, machine, options, t, L, fi, fo, curves, assumed)
    runs[DEFAULT_KV_PER_S] = default
    inflation = max(default.kappa, 1.0)
    n = default.n
    grid = sorted({*PROFILE_KV_PER_S, DEFAULT_KV_PER_S})
    for kv in grid:
        run(kv)
    for _ in range(PROFILE_REFINE):  # a parabola through the best and its neighbours, in log(gain)
        tried = sorted(runs)
        nll = [run(kv) for kv in tried]
        k = int(np.argmin(nll))
        if not (0 < k < len(tried) - 1 and all(math.isfinite(v) for v in nll[k - 1 : k + 2])):
            break
        a, b, _ = np.polyfit(np.log(tried[k - 1 : k + 2]), nll[k - 1 : k + 2], 2)
        kv = float(round(math.exp(-b / (2 * a)), 1)) if a > 0 else tried[k]
        if min(abs(math.log(kv / x)) for x in tried) < 0.02:
            break
        run(kv)
    best = min(runs, key=run)
    gain = run(DEFAULT_KV_PER_S) - run(best)
    span = f"{min(grid):g}..{max(grid):g}/s"
    # the data fix the gain only where both ends of the range are clearly worse than the best
    bounded = min(run(min(grid)), run(max(grid))) - run(best) > PROFILE_NATS
    if gain > PROFILE_NATS and bounded:
        # The profile's values come from searches refined from the default's timing, without the lag's
        # uncertainty or the spikes' test; the gain taken is searched whole, as the default was, its result is
        # that search's, and it must still beat the default.
        whole = fit(best, None)
        if whole is None:
            gain = -math.inf
        else:
            runs[best] = whole
            gain = run(DEFAULT_KV_PER_S) - run(best)
    if gain > PROFILE_NATS and bounded:
        res = runs[best].report()
        res["timing"]["loop_lag_source"] = (
            f"fitted to the data arcs: {best:g}/s, {gain:.1f} nats better than the default {DEFAULT_KV_PER_S:g}/s "
            f"over {span} (the feed-in's settling is not resolved at this sample rate and no kv_x/kv_y is "
            "configured; a backlash compensation's step and the servo remainder pass through the loop)"
        )
    else:
        res = default.report()
        why = (f"another gain is at most {gain:.1f} nats better (best {best:g}/s), not more than {PROFILE_NATS:g}"
               if gain <= PROFILE_NATS else
               f"the best, {best:g}/s, is not more than {PROFILE_NATS:g} nats better than both ends of the range")
        res["timing"]["loop_lag_source"] = f"{assumed.source}; the data arcs do not fix the gain in {span}: {why}"
    res["fit"]["servo_model_note"] = res["timing"]["loop_lag_source"]
    res["timing"]["loop_gain_profile"] = {f"{kv:g}": round(run(kv) - run(best), 3) for kv in sorted(runs)}
    return res


def _analyze_at(
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    t: np.ndarray,
    L: np.ndarray,
    fi: StepEvent,
    fo: StepEvent,
    curves: bool,
    lag: Lag,
) -> dict[str, Any]:
    """:func:`analyze_test` at a position-loop lag ``(tau, cos2, source)`` (:func:`loop_lag`)."""
    return _fit_at(plan, machine, options, t, L, fi, fo, curves, lag).report()


class _Fitted(NamedTuple):
    """A test fitted at one loop lag (:func:`_fit_at`): its misfit, and its result when asked for."""

    rms_um: float  # the residual's rms over the data arcs
    n: int  # samples in the data arcs
    kappa: float  # the residual's variance inflation (lag-1 correlation)
    report: Callable[[], dict[str, Any]]  # the result
    hyper: _Hyper  # the timing and spike width found


def _fit_at(
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    t: np.ndarray,
    L: np.ndarray,
    fi: StepEvent,
    fo: StepEvent,
    curves: bool,
    lag: Lag,
    near: _Hyper | None = None,
) -> _Fitted:
    """The search and the fit of :func:`_analyze_at`; the result is built only when asked for (a loop gain
    the profile does not take needs only its misfit).

    ``near``: a timing found at another loop gain: the search refines from it (no search over the whole
    range), in one pass: a loop gain's profile value, not a result.
    """
    span = fo.t_s - fi.t_s
    patterns = select(options.patterns, plan.direction_list, machine.pitch_x_mm, machine.pitch_y_mm)
    tau, cos2, tau_source, _ = lag
    # 1. A preliminary fit on the search's coarse set of samples: the corrections' first values.
    sample_hz = _rate(t)
    base = make_timing(plan, fi.t_s, feed_from_span(plan, span, 0.0), 0.0)
    margin = options.max_lag_s * 1.5 * base.feed_mm_s / plan.radius_mm  # rad
    windows = {}
    for d in plan.direction_list:
        a, b = base.window(d)
        trim = margin * plan.radius_mm / base.feed_mm_s
        windows[d] = (a + trim, b - trim) if b - a > 4 * trim else (a, b)
    widths, unresolved = spike_width_bounds(plan, options, base.feed_mm_s, sample_hz)
    accel = feed_accel(plan, [fi, fo], base.feed_mm_s)
    search = _LagSearch(plan, machine, options, patterns, t, L, fi, span, base, windows, tau, widths, accel)
    hyper = _Hyper(spike_width_deg=min(max(DEFAULT_SPIKE_WIDTH_DEG, widths[0]), widths[1]))
    offset = None
    offset_m = 0.0  # the servo mismatch (ms) the correction was made with (correction())
    lost = LostMotion()
    spacing_rad = base.feed_mm_s / plan.radius_mm / sample_hz if sample_hz > 0 else 0.0
    u_in = arc_start_deg(plan, plan.direction_list[0])
    frame_cos2 = math.cos(2.0 * math.radians(u_in))  # the feed-in's delay is the angles' frame

    def choose(fit: FitResult) -> LostMotion:
        values = _credible_backlash(fit, search.kappa if fit.kappa == 1.0 else 1.0, options.min_effect_um)
        m, omega = values.get("servo_mismatch_ms", 0.0), base.feed_mm_s / plan.radius_mm
        loops = loop_angles(mean_lag(tau, cos2, m), m, omega, u_in)
        # each axis' own lag moves where it reverses: physics of the loops, not of the seed's linear masks
        axes = axis_reversals(m, omega, u_in) if tau is not None else (0.0, 0.0)
        return LostMotion.choose(values, options.lost_motion, plan.radius_mm, loops, axes)

    def correction(fit: FitResult, lost: LostMotion) -> tuple[Offset | None, float]:
        """The physical correction at the fit's values, and the servo mismatch (ms) it was made with: the one
        value it takes from them."""
        values = _values(fit)
        return make_offset(values, tau, lost, cos2, frame_cos2), values.get("servo_mismatch_ms") or 0.0

    def slope(m: float, lost: LostMotion) -> Offset | None:
        """The correction's change per ms of servo mismatch at ``m`` (a central difference), None where it does
        not depend on it (no servo correction)."""
        if tau is None or not FOLD_SLOPE:
            return None
        up, down = (make_offset({"servo_mismatch_ms": m + s}, tau, lost, cos2, frame_cos2)
                    for s in (SLOPE_MS, -SLOPE_MS))
        if up is None or down is None:
            return None
        return lambda g: (up(g) - down(g)) / (2.0 * SLOPE_MS)

    if search.coarse.idx.size > 50:
        pre = search.joint(search.coarse, hyper, None, lost, keep=True)
        pre_fit = pre.solve(options, rank=False)
        search.kappa = _kappa(_lag1(pre.residuals(pre_fit.x)))
        lost = choose(pre_fit)
        offset, offset_m = correction(pre_fit, lost)
        # 2. Lag and spike width with the corrections applied; then, where the fit at that timing changes a
        # lost-motion model or moves a table's reversal by a tenth of a sample (a sample at the onset decides a
        # spike's height), again from there.
        start = None
        if near is not None:
            search.fine = search.fine_samples(near.overhead_s)
            start = replace(near, spike_lr_search=None)
        local = False
        for _pass in range(3 if near is None else 1):
            if start is not None and _pass:  # the features where the last pass put them
                search.fine = search.fine_samples(start.overhead_s, start.wait_s)
            hyper = search.run(offset, lost, start, misfit_only=near is not None, local=local)
            joint_s = search.joint(search.fine, hyper, offset, lost, keep=True)
            fit_s = joint_s.solve(options, rank=False)
            chosen = choose(fit_s)
            offset, offset_m = correction(fit_s, chosen)
            moved = max(abs(a - b) for a, b in zip(chosen.onset_rad, lost.onset_rad, strict=True))
            same = chosen.models == lost.models and moved <= ONSET_MOVE_SAMPLES * spacing_rad
            # The residual's correlation, judged before the timing was found, may have been the misfit's
            # (a large servo pattern turned by a wrong start): judged again, it can sharpen the likelihood.
            kappa = _kappa(_lag1(joint_s.residuals(fit_s.x)))
            rejudged = kappa < KAPPA_RESEARCH * search.kappa
            if rejudged:
                search.kappa, same = kappa, False
            # a reversal moved by less than a sample, the rest as it was: the timing moves little, nearby
            local = chosen.models == lost.models and moved <= search.omega * search.local_s and not rejudged
            lost, start = chosen, hyper
            if same:
                break
        if near is None:
            # on point samples, at the corrections the passes settled on; then the corrections at that timing
            hyper = search.finish(offset, lost, hyper)
            fit_s = search.joint(search.fine, hyper, offset, lost, keep=True).solve(options, rank=False)
            lost = choose(fit_s)
            offset, offset_m = correction(fit_s, lost)
    # Spikes the data arcs do not reach, or whose width the data do not fix, are left out, with the reason.
    exclude = _unreached_spikes(plan, patterns)
    resolution_limited = bool(unresolved) or (
        widths[0] > options.spike_width_min_deg and hyper.spike_width_deg <= widths[0] * WIDTH_AT_BOUND)
    if _has_spikes(patterns):
        why = unresolved or _width_verdict(hyper.spike_width_deg, widths, options, sample_hz)
        if why:
            exclude = {p.name: exclude.get(p.name, why) for p in patterns if p.reversal is not None}
    # 3. The full fit at those values, then the corrections to a fixed point.
    V = feed_from_span(plan, span, hyper.overhead_s, accel)
    timing = make_timing(plan, fi.t_s, V, hyper.overhead_s, hyper.shift_s, accel)

    # Spikes too narrow to size still touch the first samples after each table reversal: those are left out,
    # so that no other pattern (a backlash step, above all) takes them up.
    skip = SKIP_SAMPLES * search.sample_rad if resolution_limited else 0.0

    def full(lost: LostMotion, offset: Offset | None, m: float) -> _Joint:
        return _Joint(plan, machine, patterns, timing, hyper.spike_width_deg, t, L, offset, True, None, tau, lost,
                      0.0, skip, slope(m, lost) if offset is not None else None)

    joint = full(lost, offset, offset_m)
    folded_m = offset_m  # the servo mismatch the fold's correction was made at
    for c in joint.circles:
        if c.factor.n < 8:
            raise DataError(
                f"the {'CCW' if c.d > 0 else 'CW'} data arc ({c.t_start:.2f}..{c.t_end:.2f} s) holds "
                f"{c.factor.n} samples: too few to fit"
            )
    fit = joint.solve(options, exclude=exclude, rank=False)
    refolds = 0
    for _ in range(FINAL_STEPS):
        chosen = choose(fit)
        if chosen.models != lost.models and refolds < 2:  # the final fit turned a backlash's sign: the other model
            lost, refolds = chosen, refolds + 1
            offset, offset_m = correction(fit, lost)
            joint, folded_m = full(lost, offset, offset_m), offset_m
            fit = joint.solve(options, exclude=exclude, rank=False)
            continue
        # The correction moves by at most |dm| V (um; the servo's linear mask moves by half that) where the fit's
        # mismatch moved by dm: below OFFSET_SETTLED_UM the fold is already at its fixed point; without a servo
        # correction it does not move with the fit at all.
        now, now_m = correction(fit, lost)
        if (now is None) == (offset is None) and (tau is None or abs(now_m - offset_m) * V < OFFSET_SETTLED_UM):
            break
        offset, offset_m = now, now_m
        if offset is not None and all(c.with_slope is not None for c in joint.circles):
            for c in joint.circles:  # along the folded slope: no fold
                c.move_correction(offset_m - folded_m, offset)
        elif refolds < 2:
            refolds += 1
            for c in joint.circles:
                c.refit(offset)
        else:
            break
        fit = joint.solve(options, exclude=exclude, rank=False)
    residuals = joint.residuals(fit.x)
    all_r = np.concatenate(residuals)
    rms = float(np.sqrt(np.mean(all_r**2)))

    def report() -> dict[str, Any]:
        # what moves with the timing is known only as well as the timing (the spikes count theirs themselves:
        # their onset's, _spike_timing_error)
        spread = search.timing_spread(offset, lost, hyper) if near is None else None
        timing_cov = None
        if spread is not None:
            region, slope = spread
            timing_cov = slope @ region @ slope.T
            timing_cov[search.spike_cols, :] = 0.0
            timing_cov[:, search.spike_cols] = 0.0
        # the spikes' width was fitted to these samples: their joint test counts it
        fit = joint.solve(options, rho=_lag1(residuals), exclude=exclude, family_dof={"reversal_spike": 1},
                          family_lr={"reversal_spike": hyper.spike_lr()}, timing_cov=timing_cov)
        res = _result_body(plan, machine, options, fit, patterns)
        if timing_cov is not None:
            res["fit"]["uncertainty_method"] += (
                "; every parameter's also holds the timing's spread (the lag and the feed-in's extra wait the full "
                "model cannot tell from its best, times the parameter's change with them), and each F-test keeps "
                "the share of its Wald statistic left once that is counted"
            )
        _spike_timing_error(res, hyper, V / plan.radius_mm)
        res["fit"]["servo_model"] = "physical" if tau is not None else "linear"
        res["fit"]["servo_model_note"] = tau_source
        res["fit"]["lost_motion"] = lost.to_dict()
        res["fit"]["lost_motion_model"] = "; ".join(
            f"{axis.upper()}: {MODEL_WORDS[m]}" for axis, m in zip("xy", lost.models, strict=True)
        )
        res["kind"] = "test"
        res["timing"] = _timing_dict(plan, fi, fo, timing, hyper, V)
        if _has_spikes(patterns) and not exclude and search.fine.idx.size > 50:
            _spike_width_error(res, *search.width_error(hyper, offset, lost))
        _spike_significance(res)
        res["advice"] = advise(res["parameters"], plan, machine)  # on the final verdicts
        res["timing"]["loop_lag_ms"] = tau * 1000.0 if tau is not None else None
        res["timing"]["loop_lag_source"] = tau_source
        res["timing"]["loop_lag_origin"] = lag.origin
        res["timing"]["loop_lag_radial_cos2u"] = cos2
        res["timing"]["backlash_takeup_deg"] = {
            axis: math.degrees(o) if m == "deadband" else 0.0
            for axis, m, o in zip("xy", lost.models, lost.onset_rad, strict=True)
        }
        res["timing"]["reversal_onset_deg"] = {
            axis: math.degrees(o) for axis, o in zip("xy", lost.onset_rad, strict=True)
        }
        # The arc-start lag of a trapezoid profile is V / A: a plan whose data arcs begin before the feed is
        # reached at that acceleration leaves the timing model, and the measured feed and angles with it.
        if hyper.overhead_s > 0 and math.isfinite(hyper.overhead_s):
            limits = model_limits(plan.with_(feed_mm_min=V * 60.0), V / hyper.overhead_s)
            if limits:
                res["warnings"] = [
                    f"timing model: {why} (acceleration from the measured arc-start lag); the measured feed and the "
                    "angles are biased: lengthen overshoot_deg" for why in limits
                ]
        res["iso230_4"] = iso230.figures({c.d: c.measured() for c in joint.circles})
        res["iso230_4"]["conditions"] = iso230.conditions(plan.to_dict(), V * 60.0, sample_hz)
        res["noise"] = noise.findings(
            [(c.measured()[0], r, plan.data_arc_deg, sample_hz) for c, r in zip(joint.circles, residuals, strict=True)],
            options.vibration_cutoff_cpr,
        )
        if curves:
            res["curves"] = {}
            for c, r in zip(joint.circles, residuals, strict=True):
                uc, dr = c.measured()
                res["curves"]["ccw" if c.d > 0 else "cw"] = {
                    "t_s": c.times(), "u_deg": np.degrees(uc), "measured_um": dr,
                    "model_um": dr - r,
                }
        res["residual_rms_um"] = rms
        res["samples"] = {
            "in_test": int(t.size),
            "in_data_arcs": int(sum(c.factor.n for c in joint.circles)),
            "sample_hz": sample_hz,
        }
        return res

    return _Fitted(rms, sum(c.factor.n for c in joint.circles), _kappa(_lag1(residuals)), report, hyper)


def _embed_vec(v: np.ndarray, sub: Sequence[Pattern], full: Sequence[Pattern]) -> np.ndarray:
    out = np.zeros(sum(p.q for p in full))
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    k = 0
    for p in sub:
        out[pos[p.name] : pos[p.name] + p.q] = v[k : k + p.q]
        k += p.q
    return out


def _take(x: np.ndarray, sub: Sequence[Pattern], full: Sequence[Pattern]) -> np.ndarray:
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    return np.concatenate([x[pos[p.name] : pos[p.name] + p.q] for p in sub])


def _rate(t: np.ndarray) -> float:
    if t.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(t)))


def _timing_dict(
    plan: TestPlan, fi: StepEvent, fo: StepEvent, timing: Timing, hyper: _Hyper, V: float
) -> dict[str, Any]:
    omega = V / plan.radius_mm  # rad/s
    out: dict[str, Any] = {
        "provisional": False,
        "programmed_feed_mm_min": plan.feed_mm_min,
        "measured_feed_mm_min": V * 60.0,
        "feed_ratio": V / plan.feed_mm_s,
        "overhead_s": hyper.overhead_s,
        "lag_s": hyper.overhead_s,
        "lag_deg": math.degrees(omega * hyper.overhead_s),
        "lag_stderr_s": hyper.lag_stderr_s if math.isfinite(hyper.lag_stderr_s) else None,
        "spike_width_deg": hyper.spike_width_deg,
        "feed_in_s": fi.t_s,
        "feed_out_s": fo.t_s,
        "feed_in_method": fi.method,
        "feed_out_method": fo.method,
        "feed_in_height_mm": fi.height_mm,
        "feed_out_height_mm": fo.height_mm,
        "data_arcs": {
            ("ccw" if d > 0 else "cw"): {
                "start_s": timing.window(d)[0], "end_s": timing.window(d)[1], "shift_s": hyper.shift_s.get(d, 0.0)
            }
            for d in plan.direction_list
        },
        "method": (
            "feed from the feed-in to feed-out centroid span; arc-start lag (per-move overhead), each data arc's "
            "shift against it (unequal waits before the arcs, fitted only where the data need them: "
            + ("fitted" if hyper.wait_free else "not needed here, 0")
            + ") and spike width by profile likelihood of the full model, the lag among those the full model "
            "cannot tell apart where the model without spikes fits best, each stair's middle on point samples"
        ),
    }
    return out


# --------------------------------------------------------------------------- result body


def _result_body(
    plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, fit: FitResult, patterns: Sequence[Pattern]
) -> dict[str, Any]:
    from .report import parameters_dict, ranking_list

    params = parameters_dict(fit, patterns, machine)
    return {
        "schema_version": SCHEMA_VERSION,
        "plan": plan.to_dict(),
        "machine": machine.to_dict(),
        "parameters": params,
        "ranking": ranking_list(fit),
        "advice": advise(params, plan, machine),
        "fit": {
            "n_samples": fit.n,
            "n_parameters": fit.p,
            "dof": fit.dof,
            "sigma_um": fit.sigma,
            "residual_lag1_autocorrelation": fit.rho,
            "variance_inflation": fit.kappa,
            "condition_number": fit.condition if math.isfinite(fit.condition) else None,
            "significance": options.significance,
            "min_effect_um": options.min_effect_um,
            "significance_rule": significance_rule(options.significance, options.min_effect_um),
            "servo_model": "linear",
            "uncertainty_method": (
                "least squares covariance sigma^2 (A^T A)^-1 with sigma^2 = SSE/(n-p), inflated by "
                "(1+rho)/(1-rho) for the residual's lag-1 autocorrelation rho (AR(1) effective sample "
                "count); F-tests use the same inflated variance"
            ),
        },
    }


def analyze_recording(
    t: np.ndarray,
    L: np.ndarray,
    plan: TestPlan,
    machine: MachineConfig | None = None,
    options: AnalysisOptions | None = None,
    curves: bool = False,
    breaks: Sequence[tuple[int, str]] = (),
    circles: bool = True,
    only: int | None = None,
) -> list[dict[str, Any]]:
    """Everything :class:`TestAnalyzer` reports on a whole recording, in order.

    ``curves``: see :func:`analyze_test`.  ``breaks``: ``(index, reason)``, a
    discontinuity the times may not show (a device reset) just before sample
    ``index`` (:meth:`TestAnalyzer.mark_break`).  ``circles``: False for no
    provisional circle results (the tests' results are the same).  ``only``:
    fit that test alone (see :class:`TestAnalyzer`; with ``circles=False``).
    """
    t = np.asarray(t, dtype=float)
    L = np.asarray(L, dtype=float)
    if t.size >= 2 and np.all(np.isfinite(t)) and not np.any(t[1:] > t[:-1]):  # no full-length np.diff
        what = f"all {t.size} samples have t={t[0]:g} s" if np.all(t == t[0]) else "it never increases"
        raise DataError(f"the time axis does not advance ({what}): no test can be timed")
    an = TestAnalyzer(plan, machine, options, curves=curves, circles=circles, only=only)
    out: list[dict[str, Any]] = []
    i = 0
    for j, reason in sorted(breaks, key=lambda b: b[0]):
        j = min(max(int(j), i), t.size)
        out.extend(an.feed(t[i:j], L[i:j], borrow=True))
        an.mark_break(reason)
        i = j
    out.extend(an.feed(t[i:], L[i:], borrow=True))
    out.extend(an.finish())
    if not any(r.get("event") == "feed_in" for r in out):
        lo, hi = an.detector.seen_range()
        raise DetectionError(
            f"no feed-in found: the bar never stepped from about {plan.radius_mm + plan.feed_in_mm:g} mm "
            f"(R + feed-in) to {plan.radius_mm:g} mm (R); its length ranged {lo:.4f}..{hi:.4f} mm"
        )
    return out


__all__ = ["HINT_MAX_FEED_DEVIATION", "CircleFit", "TestAnalyzer", "TimingHints", "analyze_recording", "analyze_test"]
