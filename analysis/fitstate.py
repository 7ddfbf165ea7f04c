"""The state of one test's fit (:mod:`.testfit`) and the pieces its stages and its result share: the bins, the
search space and its priors, the lost-motion models, the noise; the checks of the plan and the spike width's bounds.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .circle import Timing, _after_onsets
from .detect import StepEvent
from .errors import DataError
from .loops import DEFAULT_KV_PER_S, Lag
from .patterns import FEED_FORWARD, Geometry, select
from .physics import LostMotion, Offset, axis_reversals, loop_angles, make_offset, mean_lag
from .plan import AnalysisOptions, MachineConfig, TestPlan
from .program import accel_from_spread, accel_part, arc_start_deg, feed_from_span, schedule
from .result import (
    unreached_spikes,
)
from .search import (
    COARSE_BIN_DEG,
    CYCLIC_BINS,
    FINE_BIN_DEG,
    NOISE_FLOOR_UM,
    Binned,
    Context,
    Evaluation,
    Found,
    Objective,
    Prior,
    Theta,
    feature_zones,
    make_bins,
    minimise,
)
from .validity import reading_step, sensor_noise

LAG_PRIOR_S = 0.05  # prior on the arc-start lag: where the data cannot see it, it stays near the feed-in's shape's
WAIT_PRIOR_S = 0.1  # ... and on the feed-in's extra wait
SMOOTH_PRIOR = (0.5, 0.35)  # ... and on where a short feed-in's duration lies between its limits (0..1)
SMOOTH_STEP = 0.05
WAIT_MAX_S = 0.3
LAG_BELOW_S = 0.1  # a negative per-move overhead is unphysical: only this far below 0
TAU_PRIOR_LN = math.log(2.5)  # the loops' lag where nothing tells it: within a factor 2.5 of the default's
TAU_BOUNDS_PER_S = (8.0, 150.0)  # ... and between these gains
DEFAULT_SPIKE_WIDTH_DEG = 0.5
RESOLVE_SAMPLES = 2.0  # samples per spike width below which a spike cannot be sized
WIDTH_AT_BOUND = 1.03  # a fitted width within 3 % of a bound of its search has run onto it
WIDTH_BOUND_SE = 2.0  # ... and a width within this many of its standard errors of the lower bound is not told from it
ONSET_MOVE_SAMPLES = 0.1  # the timing is searched again when a table's reversal moves by more (samples)
FF_MAX = 0.98  # the feed-forward share's bound (at 1 the loops would not lag on the circle at all)
FF_PRIOR = 0.5  # ... its prior's spread about 0, where the data do not place the command's steps
TAU_NATS = 2.0  # the data must prefer another loop lag than the default gain's by this much log-likelihood
SEARCH_BUDGET = 44  # designs the searches may make in all (a search always makes its first Jacobian and a step);
# a test the model does not describe makes them wander, the final fit and its checks come after


def _rate(t: np.ndarray) -> float:
    if t.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(t)))


def feed_accel(plan: TestPlan, steps: Sequence[StepEvent], feed_mm_s: float) -> float | None:
    """The acceleration part of the per-move overhead, from the feed-in's (and feed-out's) spread in time.

    The rest of the overhead (an in-position wait after each move, a
    control's block change) does not shape a move: only this decides whether
    the short feed-in reaches the feed (:func:`.program.feed_in_half`).  None
    where the steps' spread was not resolved (then all the overhead is taken
    as acceleration).
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


def _credible_backlash(x: dict[str, float], se: dict[str, float], min_um: float) -> dict[str, float]:
    """The fit's values with a backlash that is no finding set to 0.

    What decides an axis' lost-motion model and where its table reverses: a
    take-up angle grows as the root of the backlash (0.04 deg for 0.03 um at
    R 100 mm), so a backlash of nothing would move the spikes' onset by several
    samples and feed on itself.  A backlash counts when it exceeds three
    standard errors and the minimum effect.
    """
    out = dict(x)
    for key in ("backlash_x_um", "backlash_y_um"):
        if key in out and abs(out[key]) <= max(3.0 * se.get(key, 0.0), min_um):
            out[key] = 0.0
    return out


@dataclass
class _State:
    """The fit's current estimates: nonlinear parameters, the linear fit's values, and the corrections'."""

    theta: Theta
    values: dict[str, float]
    lost: LostMotion
    found: Found | None = None
    se: dict[str, float] | None = None


class Pieces:
    """What a test's fit holds and the pieces its stages (:class:`.testfit.TestFit`) and its result
    (:class:`.fitresult.Assembly`) are made of."""

    __test__ = False

    def __init__(
        self, plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, t: np.ndarray, L: np.ndarray,
        fi: StepEvent, fo: StepEvent, lag: Lag, sample_hz: float | None = None,
    ) -> None:
        self.plan, self.machine, self.options = plan, machine, options
        self.t, self.L, self.fi, self.fo, self.lag = t, L, fi, fo, lag
        self.sample_hz = _rate(t) if sample_hz is None else sample_hz  # (the median step: 10 ms at 10 kHz)
        self.period_s = 1.0 / self.sample_hz if self.sample_hz > 0 else 0.0
        self.span = fo.t_s - fi.t_s
        self.patterns = select(options.patterns, plan.direction_list, machine.pitch_x_mm, machine.pitch_y_mm)
        if options.lost_motion != "step":
            # an over-set compensation's step: the share feed-forward passes at once, before the spikes (where the two
            # cannot be told apart, the loop's own response stays and the spikes go)
            k = next((i for i, p in enumerate(self.patterns) if p.reversal is not None), len(self.patterns))
            self.patterns[k:k] = list(FEED_FORWARD)
        V0 = feed_from_span(plan, self.span, 0.0)
        self.accel = feed_accel(plan, [fi, fo], V0)
        self.omega0 = V0 / plan.radius_mm
        self.widths, self.unresolved = spike_width_bounds(plan, options, V0, self.sample_hz)
        self.exclude = unreached_spikes(plan, self.patterns)
        self.has_spikes = any(p.reversal is not None for p in self.patterns)
        if self.has_spikes and self.unresolved:
            self.exclude = {p.name: self.exclude.get(p.name, self.unresolved)
                            for p in self.patterns if p.reversal is not None}
        self.sized = self.has_spikes and not self.unresolved  # the spikes' width is searched
        search_patterns = self.patterns if self.sized else [p for p in self.patterns if p.reversal is None]
        self.ctx = Context(plan, machine, search_patterns, fi.t_s, self.span, self.accel)
        self.full_ctx = Context(plan, machine, self.patterns, fi.t_s, self.span, self.accel)
        self.tau_fitted = lag.origin == "assumed"  # the loops' lag searched with the timing
        self.u_in = arc_start_deg(plan, plan.direction_list[0])
        self.frame_cos2 = math.cos(2.0 * math.radians(self.u_in))
        w0 = min(max(DEFAULT_SPIKE_WIDTH_DEG, self.widths[0]), self.widths[1])
        # the lag starts at, and is drawn toward, the acceleration part of the per-move overhead that the feed-in's
        # and feed-out's spread in time show (the overhead is at least that), 0 where they do not show it
        self.c0 = min(max(self.accel, 0.0), options.max_lag_s) if self.accel is not None else 0.0
        # a feed-in short at the starting lag starts midway between its durations' limits; else at the triangle's
        # (the schedule's model before the share), where the search starts should a later lag make it short
        smooth0 = SMOOTH_PRIOR[0] if options.estimate_lag and self._short_feed_in(self.c0) else 0.0
        self.state = _State(Theta(self.c0, 0.0, w0, lag.tau, smooth=smooth0), {}, LostMotion())
        # the search's samples: the data arcs whatever lag the search tries
        base = self.ctx.timing(Theta())
        trim = 1.5 * options.max_lag_s
        self.windows: dict[int, tuple[float, float]] = {}
        for d in plan.direction_list:
            a, b = base.window(d)
            self.windows[d] = (a + trim, b - trim) if b - a > 4 * trim else (a, b)
        # bins away from the features: at most COARSE_BIN_DEG, and a screw period (cyclic error, where pitches are
        # configured) in CYCLIC_BINS of them: the bins' mean is the model at the mean time to its curvature
        pitches = [v for v in (machine.pitch_x_mm, machine.pitch_y_mm) if v]
        self.coarse_deg = min([COARSE_BIN_DEG] + [math.degrees(v / plan.radius_mm / CYCLIC_BINS) for v in pitches])
        self.designs = 0  # the designs made: misfit evaluations and their slopes
        self.misfits = 0  # the misfit evaluations among them
        self.skip_rad = 0.0
        self.spike_sse: tuple[float, float, int] | None = None  # full and spike-free SSE at their best, samples
        self.wait_free = False
        self.below_resolution = False  # the spikes' width ran onto the samples' resolution in the coarse stage
        self.ff_started = False  # the feed-forward share's search has its start (:meth:`_start_ff`)
        self.held: set[int] = set()  # coordinates held at their prior's value (the loops' lag: the default gain)
        self.aperture_scale = 1.0
        self.search_samples = 0  # the samples (or bins) of the search's last stage
        # the step the readings sit on (a digital gauge's resolution, :func:`.validity.reading_step`), and the
        # sensor's white noise from the samples alone, at least that step's quantisation noise
        arcs = [self.L[(self.t >= a) & (self.t <= b)] for a, b in self.windows.values()]
        self.step_um = 1000.0 * reading_step(np.concatenate(arcs)) if arcs else 0.0
        sw = [sensor_noise((v - plan.radius_mm) * 1000.0, self.step_um) for v in arcs]
        sw = [v for v in sw if math.isfinite(v)]
        self.white_var = float(np.mean(np.square(sw))) if sw else 0.0

    def _bins(self, timing: Timing | None, windows: dict[int, tuple[float, float]], skip: LostMotion | None = None
              ) -> dict[int, Binned]:
        """The samples of ``windows`` in bins: coarse everywhere (``timing`` None) or fine about the sharp
        features where ``timing`` puts them.  ``skip``: leave out the samples just after each table reversal
        (:attr:`skip_rad`)."""
        out = {}
        omega = (timing.feed_mm_s if timing is not None else self.omega0 * self.plan.radius_mm) / self.plan.radius_mm
        fine_s = math.radians(FINE_BIN_DEG) / omega
        coarse_s = math.radians(self.coarse_deg) / omega
        for d in self.plan.direction_list:
            a, b = windows[d]
            i, j = int(np.searchsorted(self.t, a, side="left")), int(np.searchsorted(self.t, b, side="right"))
            t = self.t[i:j]
            y = (self.L[i:j] - self.plan.radius_mm) * 1000.0
            if skip is not None and self.skip_rad > 0 and timing is not None and t.size:
                keep = ~_after_onsets(self._sample_geometry(d, t, timing, self.state.theta.tau, skip), self.skip_rad)
                t, y = t[keep], y[keep]
            zones = feature_zones(self.plan, timing, d, (a, b)) if timing is not None else []
            out[d] = make_bins(d, t - self.fi.t_s, y, self.period_s, zones, fine_s, coarse_s)
        return out

    def _offset_for(self, values: dict[str, float], lost: LostMotion) -> Any:
        """The corrections at ``values`` given the nonlinear parameters (the loops' lag among them)."""
        lag, fc = self.lag, self.frame_cos2

        def at(theta: Theta) -> Offset | None:
            return make_offset(values, theta.tau, lost, lag.cos2, fc)

        return at

    def _choose(self, values: dict[str, float], se: dict[str, float], theta: Theta) -> LostMotion:
        credible = _credible_backlash(values, se, self.options.min_effect_um)
        m = credible.get("servo_mismatch_ms", 0.0)
        V = self.ctx.feed(theta)
        omega = V / self.plan.radius_mm
        tau = theta.tau
        loops = loop_angles(mean_lag(tau, self.lag.cos2, m), m, omega, self.u_in, theta.ff)
        axes = axis_reversals(m, omega, self.u_in) if tau is not None else (0.0, 0.0)
        return LostMotion.choose(credible, self.options.lost_motion, self.plan.radius_mm, loops, axes, theta.ff)

    def _values_se(self, e: Evaluation, obj: Objective) -> tuple[dict[str, float], dict[str, float]]:
        """The evaluation's values by field, and their standard errors (the fit's, its correlation counted)."""
        assert e.normal is not None and e.use is not None
        var = np.zeros(e.x.size)
        var[e.use] = np.diagonal(e.normal.solve(np.eye(int(e.use.sum())))) * self._noise(e, obj.samples)
        values, se = {}, {}
        j = 0
        for p in obj.ctx.patterns:
            for k, f in enumerate(p.fields):
                values[f] = float(e.x[j + k])
                se[f] = math.sqrt(max(float(var[j + k]), 0.0))
            j += p.q
        return values, se

    def _space(self, active: Sequence[int]) -> tuple[dict[int, tuple[float, float]], dict[int, float],
                                                     list[Prior]]:
        lo_c = -min(self.options.max_lag_s, LAG_BELOW_S)
        bounds = {0: (lo_c, self.options.max_lag_s), 1: (-WAIT_MAX_S, WAIT_MAX_S),
                  2: (math.log(self.widths[0]), math.log(self.widths[1])),
                  3: (-math.log(TAU_BOUNDS_PER_S[1]), -math.log(TAU_BOUNDS_PER_S[0])), 4: (0.0, FF_MAX),
                  5: (0.0, 1.0)}
        # finite differences on the scale the objective is smooth on: a tenth of a bin's travel, at least a
        # hundredth of a sample period
        fine_s = math.radians(FINE_BIN_DEG) / self.omega0
        h_t = max(0.1 * max(fine_s, self.period_s), 1e-5)
        steps = {0: h_t, 1: h_t, 2: 0.02, 3: 0.02, 4: 0.02, 5: SMOOTH_STEP}
        priors = [Prior(0, self.c0, LAG_PRIOR_S), Prior(1, 0.0, WAIT_PRIOR_S), Prior(4, 0.0, FF_PRIOR),
                  Prior(5, SMOOTH_PRIOR[0], SMOOTH_PRIOR[1])]
        if self.tau_fitted:
            priors.append(Prior(3, -math.log(DEFAULT_KV_PER_S), TAU_PRIOR_LN))
        return bounds, steps, [p for p in priors if p.index in active]

    def _active(self, wait: bool = True, width: bool = True) -> list[int]:
        out = [0] if self.options.estimate_lag else []
        if wait and self.options.estimate_lag and len(self.plan.direction_list) > 1:
            out.append(1)
        if width and self.sized:
            out.append(2)
        if self.tau_fitted:
            out.append(3)
        elif self._command_steps():
            out.append(4)
        if self.options.estimate_lag and self._short_feed_in():
            out.append(5)
        return out

    def _short_feed_in(self, c: float | None = None) -> bool:
        """Whether the feed-in may be too short to reach the feed at the starting lag: then how long it lasts
        depends on the control (a plain trapezoid's triangle, or as long as if it reached the feed where the
        trapezoid is averaged, a jerk limit's ``A/J`` or a filter's after interpolation: both are common), which
        the fit searches (:func:`.program.short_move_duration`)."""
        c = max(self.c0, self.state.theta.c) if c is None else c
        shape = accel_part(c, self.accel)
        V = feed_from_span(self.plan, self.span, c, self.accel)
        return shape > 0 and math.isfinite(V) and self.plan.feed_in_mm < V * shape

    def _command_steps(self) -> bool:
        """Whether the current estimates hold an over-set backlash compensation, a step made in the command:
        where it lands depends on the loops' lag on the circle, ``(1 - ff)`` times the settling's, so the
        feed-forward share ``ff`` is searched (the share it passes at once is the linear
        :data:`.patterns.FEED_FORWARD` column).  Only where the loops' lag is known (where it is searched, it
        moves the step as well)."""
        return (self.state.theta.tau is not None and self.options.lost_motion != "step"
                and "compensation" in self.state.lost.models)

    def _search(
        self, obj: Objective, active: list[int], max_iter: int, scale: float = 1.0, cap: int = 1_000
    ) -> Found:
        bounds, steps, priors = self._space(active)
        steps = {k: v * scale if k in (0, 1) else v for k, v in steps.items()}
        start = self.state.theta
        budget = max(min(SEARCH_BUDGET - self.designs - obj.designs, cap), 2)
        found = minimise(obj, start, active, bounds=bounds, steps=steps, priors=priors, max_iter=max_iter,
                         max_evals=budget)
        self._account(obj)
        return found

    def _update(self, obj: Objective, e: Evaluation) -> bool:
        """The corrections and lost-motion models at evaluation ``e``; whether the timing must be searched again
        (a model changed, or a table's reversal moved by more than ``ONSET_MOVE_SAMPLES``)."""
        values, se = self._values_se(e, obj)
        lost = self._choose(values, se, e.theta)
        old = self.state.lost
        moved = max(abs(a - b) for a, b in zip(lost.onset_rad, old.onset_rad, strict=True))
        spacing = self.omega0 * self.period_s
        again = lost.models != old.models or moved > ONSET_MOVE_SAMPLES * spacing
        self.state = _State(e.theta, values, lost, self.state.found, se)
        return again

    def _lost_for(self) -> Any:
        """The lost-motion models of the current estimates, their angles at each value of the nonlinear
        parameters (the loops' lag moves a compensation step's lead and rise)."""
        values, se = self.state.values, self.state.se or {}
        return lambda theta: self._choose(values, se, theta)

    def _width_for_verdict(self, theta: Theta) -> float:
        """The spikes' width as the verdict on it reads it: where the lower bound of its search is the samples'
        resolution, on that bound where it lies within ``WIDTH_BOUND_SE`` of its standard errors of it (on the
        log scale it is searched on).  A width the samples
        do not tell from their resolution has not been measured: at 15.625 Hz a 0.19 deg friction decay was
        sized at 1.65 +- 2.3 deg, 0.2 standard errors above the bound, where the sample phase put the fit."""
        found = self.state.found
        lo = self.widths[0]
        if not (self.sized and found is not None and 2 in found.active and lo > self.options.spike_width_min_deg
                and theta.w_deg > lo):
            return theta.w_deg
        j = found.active.index(2)
        var = float(found.cov(self._noise(found.best, self.search_samples))[j, j])
        if var > 0 and math.log(theta.w_deg / lo) < WIDTH_BOUND_SE * math.sqrt(var):
            return lo
        return theta.w_deg

    def _account(self, obj: Objective) -> None:
        """Count ``obj``'s designs and misfit evaluations as the test's, and start it afresh."""
        self.designs += obj.designs
        self.misfits += obj.misfits
        obj.designs = obj.misfits = 0

    def _noise(self, e: Evaluation, samples: int) -> float:
        """The noise variance per sample (um^2) that the search's covariance takes: the residual's, inflated for
        its correlation as the final fit does (a smooth misfit over white noise ``sw^2`` of variance ``M``
        has ``rho = M / (M + sw^2)``, so ``kappa = 2 s^2 / sw^2 - 1``, 1..400)."""
        s2 = max(e.sse / max(samples - self.ctx.p, 1), NOISE_FLOOR_UM**2)
        kappa = min(max(2.0 * s2 / max(self.white_var, 1e-12) - 1.0, 1.0), 400.0)
        return s2 * kappa

    def _sample_geometry(self, d: int, t: np.ndarray, timing: Timing, tau: float | None, lost: LostMotion) -> Geometry:
        plan = self.plan
        u = np.radians(timing.sched.angle_deg(plan, d, t - timing.t_ref))
        omega = timing.feed_mm_s / plan.radius_mm
        return Geometry(
            u=u, d=np.full(t.size, float(d)), t_min=(t - timing.t_mid) / 60.0, V=timing.feed_mm_s, R=plan.radius_mm,
            pitch_x_mm=self.machine.pitch_x_mm, pitch_y_mm=self.machine.pitch_y_mm,
            travel=d * (u - math.radians(arc_start_deg(plan, d))), loop_lag_s=tau,
            aperture_rad=omega * self.period_s * self.aperture_scale, **lost.geometry(tau),
        )
