"""One test's fit: the timing, the spike width and the loops' lag by separable least squares, then the patterns.

:func:`analyze_test` is the whole-test analysis of analysis/README.md ("The
fit"): from a test's samples and its feed-in and feed-out, the measured feed
and the nonlinear parameters (:mod:`.search`), the physical corrections at
their fixed point (:mod:`.physics`), the fit with its ranking, uncertainty
and significance (:mod:`.fit`), the checks that the model fits at all
(:mod:`.validity`), and the result (:mod:`.result`).

The stages (each a few Gauss-Newton steps of :func:`.search.minimise`):

1. a fit of the masks alone at the starting timing, on coarse bins: the
   corrections' first values and the noise;
2. the timing (arc-start lag and the feed-in's extra wait; the loops' lag
   where nothing else tells it) with the sharp features integrated over a
   wider interval: the objective is a bowl over the whole lag range;
3. with the corrections at that timing, fine bins about the sharp features
   where they now lie, the features integrated over the bins alone, the
   spikes' width with the timing; again where the lost-motion model changed;
4. the feed-in's wait kept only where the data need it (its Wald test);
5. the final fit, its corrections brought to their fixed point.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from . import iso230, noise, standards
from .advice import advise
from .circle import Timing
from .detect import StepEvent
from .errors import DataError
from .fit import Factor, FitResult, solve
from .loops import DEFAULT_KV_PER_S, FAST_LOOP_S, Lag, loop_lag
from .patterns import FEED_FORWARD, Geometry, Pattern, design, select, wrap
from .physics import MODEL_WORDS, LostMotion, Offset, axis_reversals, loop_angles, make_offset, mean_lag
from .plan import AnalysisOptions, MachineConfig, TestPlan
from .program import accel_from_spread, arc_start_deg, data_start_deg, feed_from_span, model_limits, schedule
from .result import (
    result_body,
    spike_significance,
    timing_dict,
    unreached_spikes,
    values_of,
    width_verdict,
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
from .validity import check_model, quantisation_bias, reading_step, sensor_noise

LAG_PRIOR_S = 0.05  # prior on the arc-start lag: where the data cannot see it, it stays near the feed-in's shape's
WAIT_PRIOR_S = 0.1  # ... and on the feed-in's extra wait
WAIT_MAX_S = 0.3
LAG_BELOW_S = 0.1  # a negative per-move overhead is unphysical: only this far below 0
TAU_PRIOR_LN = math.log(2.5)  # the loops' lag where nothing tells it: within a factor 2.5 of the default's
TAU_BOUNDS_PER_S = (8.0, 150.0)  # ... and between these gains
DEFAULT_SPIKE_WIDTH_DEG = 0.5
RESOLVE_SAMPLES = 2.0  # samples per spike width below which a spike cannot be sized
WIDTH_AT_BOUND = 1.03  # a fitted width within 3 % of a bound of its search has run onto it
WIDTH_BOUND_SE = 2.0  # ... and a width within this many of its standard errors of the lower bound is not told from it
SMOOTH_S = 0.02  # the first stage integrates the sharp features over this much travel (s of the feed)
SKIP_SAMPLES = 2.0  # samples after each table reversal left out where spikes are below the resolution
ONSET_MOVE_SAMPLES = 0.1  # the timing is searched again when a table's reversal moves by more (samples)
OFFSET_SETTLED_UM = 1e-3  # the corrections' fixed point: they move by less than this (um)
FINAL_STEPS = 4
FOLD_ROWS = 16384  # samples whose model is made at a time
FF_MAX = 0.98  # the feed-forward share's bound (at 1 the loops would not lag on the circle at all)
FF_PRIOR = 0.5  # ... its prior's spread about 0, where the data do not place the command's steps
FF_GRID = (0.0, 0.25, 0.5, 0.75, 0.95)  # its search starts from the best of these
TAU_NATS = 2.0  # the data must prefer another loop lag than the default gain's by this much log-likelihood
WAIT_Z = 4.0  # the feed-in's extra wait is kept where it is this many standard errors from 0: a nuisance that
# trades with what moves one arc against the other (lateral play, at low rates), kept only where clearly needed
STAGE_CAPS = (8, 14, 6, 6)  # designs per search: the coarse stage's, the fine's, the spike-free model's, each
# point-sample share's (the first Jacobian and a step always)
SEARCH_BUDGET = 44  # designs the searches may make in all (a search always makes its first Jacobian and a step);
# a test the model does not describe makes them wander, the final fit and its checks come after
SERVO_VAR_SHARE = 0.3  # each axis' loop variance in time known to this share of the loops' lag squared
SERVO_MEAN_SHARE = 0.5  # ... and the two axes' mean to this share
POINT_APERTURES = (0.2, 0.03)  # the last stage integrates the sharp features over these shares of a sample's
# interval in turn
MODEL_ERROR_UM = 0.005  # the model's own error, of each pattern's largest radial effect (analysis/README.md,
# "Uncertainty"): a floor its standard error keeps at any sample count
FINE_TRIM_S = 0.03  # the fine stage's data arcs, trimmed for timings within this of the coarse stage's


def _rate(t: np.ndarray) -> float:
    if t.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(t)))


def _lag1(residuals: Sequence[np.ndarray]) -> float:
    num = sum(float(np.dot(r[1:], r[:-1])) for r in residuals if r.size > 1)
    den = sum(float(np.dot(r, r)) for r in residuals)
    return num / den if den > 0 else 0.0


def _kappa(rho: float) -> float:
    """The AR(1) variance inflation ``(1 + rho) / (1 - rho)`` of a residual's lag-1 correlation, 1..400."""
    return min(max((1 + rho) / (1 - rho), 1.0), 400.0) if rho < 1 else 400.0


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


class TestFit:
    """The analysis of one test (see the module docstring); :meth:`run` then :meth:`report`."""

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
        self.state = _State(Theta(self.c0, 0.0, w0, lag.tau), {}, LostMotion())
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

    # ------------------------------------------------------------------ pieces

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
                  3: (-math.log(TAU_BOUNDS_PER_S[1]), -math.log(TAU_BOUNDS_PER_S[0])), 4: (0.0, FF_MAX)}
        # finite differences on the scale the objective is smooth on: a tenth of a bin's travel, at least a
        # hundredth of a sample period
        fine_s = math.radians(FINE_BIN_DEG) / self.omega0
        h_t = max(0.1 * max(fine_s, self.period_s), 1e-5)
        steps = {0: h_t, 1: h_t, 2: 0.02, 3: 0.02, 4: 0.02}
        priors = [Prior(0, self.c0, LAG_PRIOR_S), Prior(1, 0.0, WAIT_PRIOR_S), Prior(4, 0.0, FF_PRIOR)]
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
        return out

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

    # ------------------------------------------------------------------ the stages

    def run(self) -> TestFit:
        plan = self.plan
        no_offset = lambda th: None  # noqa: E731
        # 1. the masks alone at the starting timing, on coarse bins: the corrections' first values
        coarse = self._bins(None, self.windows)
        if sum(b.samples for b in coarse.values()) <= self.ctx.p + 2:
            raise DataError("the data arcs hold too few samples to fit")
        obj = Objective(self.ctx, coarse, LostMotion(), no_offset, 0.0)
        pre = obj.evaluate(self.state.theta)
        self._account(obj)
        self._update(obj, pre)
        # 2. the timing with the sharp features integrated over a wider interval, on coarse bins
        active = [k for k in self._active() if k not in (3, 4)]
        if active:
            obj = Objective(self.ctx, coarse, self._lost_for(),
                            self._offset_for(self.state.values, self.state.lost),
                            smooth_rad=self.omega0 * SMOOTH_S)
            found = self._search(obj, active, max_iter=6, cap=STAGE_CAPS[0])
            self._update(obj, found.best)
            # spikes narrower than the samples resolve already here (the wider integration only widens them):
            # they are not sized, and the rest of the search goes without them
            lo = self.widths[0]
            if self.sized and lo > self.options.spike_width_min_deg and self.state.theta.w_deg <= lo * WIDTH_AT_BOUND:
                self.sized, self.below_resolution = False, True
                self.ctx = Context(plan, self.machine, [p for p in self.patterns if p.reversal is None], self.fi.t_s,
                                   self.span, self.accel)
        # 3. fine bins about the features where they now lie, the features integrated over the bins alone; the
        # data arcs where they now lie, but for what the timing's last steps could move in or out.  Free spikes
        # can take up what a step a few samples off leaves and hold the timing there: the model without them,
        # searched from that timing, must not fit better (it is nested in the full one), else the full model is
        # searched again from the spike-free model's timing
        restarted = False
        for _pass in range(4):
            if _pass and self.designs + 6 > SEARCH_BUDGET:
                break  # a test the model barely describes: no more passes
            timing = self.ctx.timing(self.state.theta)
            windows = {}
            for d in plan.direction_list:
                a, b = timing.window(d)
                windows[d] = (a + FINE_TRIM_S, b - FINE_TRIM_S)
            obj = Objective(self.ctx, self._bins(timing, windows), self._lost_for(),
                            self._offset_for(self.state.values, self.state.lost))
            active = self._active()
            if not active:
                e = obj.evaluate(self.state.theta)
                self._account(obj)
                self._update(obj, e)
                break
            if 4 in active and not self.ff_started:
                self._start_ff(obj)
            found = self._search(obj, active, max_iter=8, cap=STAGE_CAPS[1])
            self.state.found = found
            again = self._update(obj, found.best)
            if not again and self.sized and not restarted and self.designs + 6 <= SEARCH_BUDGET:
                bare = self._bare(obj, found.best.theta, wait=True)
                # the spikes' likelihood ratio against the spike-free model at its own best timing, on these bins
                self.spike_sse = (found.best.sse, bare.best.sse, obj.samples)
                if bare.best.sse < found.best.sse:
                    nb = bare.best.theta
                    self.state.theta = replace(found.best.theta, c=nb.c, wait=nb.wait, tau=nb.tau, ff=nb.ff)
                    restarted, again = True, True
            if not again:
                break
        # 4. the feed-in's extra wait only where the data need it (its Wald test at WAIT_Z); where it is not, the other
        # coordinates move to their best given a wait of 0 (the likelihood's quadratic), and the fit is made there
        last: Found | None = self.state.found
        self.wait_free = False
        if last is not None and 1 in last.active:
            cov = last.cov(self._noise(last.best, obj.samples))
            j = last.active.index(1)
            if abs(self.state.theta.wait) > WAIT_Z * math.sqrt(max(cov[j, j], 0.0)):
                self.wait_free = True
            else:
                self._hold(obj, last, 1, 0.0, drop=True)
        # the loops' lag, where nothing but the data arcs tell it, moves off the default gain only where the data
        # prefer another by more than TAU_NATS (what they say of it with the rest profiled out)
        last = self.state.found
        if last is not None and 3 in last.active and self.state.theta.tau is not None:
            j = last.active.index(3)
            H = last.jtj / self._noise(last.best, obj.samples)
            try:
                var = float(np.linalg.inv(H)[j, j])
            except np.linalg.LinAlgError:
                var = math.inf
            moved = math.log(self.state.theta.tau) + math.log(DEFAULT_KV_PER_S)
            if not (var > 0 and 0.5 * moved * moved / var > TAU_NATS):
                self._hold(obj, last, 3, -math.log(DEFAULT_KV_PER_S), drop=False)
        # 5. point samples: the sharp features integrated over a shrinking share of each sample's interval, from
        # the timing that integrating them over the whole interval found (on point samples, that is up to half a
        # sample off for each feature: a step or an onset between two samples); each share's minimum is the next
        # one's start, so that every feature is led to the right side of its samples
        last = self.state.found
        at_bound = not self.widths[0] * WIDTH_AT_BOUND < self.state.theta.w_deg < self.widths[1] / WIDTH_AT_BOUND
        active = [k for k in self._active(wait=self.wait_free, width=not at_bound) if k != 3]
        # (only where the bins about the features are single samples: a bin of several samples is their mean,
        # which its whole interval's integral models; and there a sample is short against every feature anyway)
        singles = self.omega0 * self.period_s >= math.radians(FINE_BIN_DEG)
        if active and last is not None and singles:
            polished = found = last
            for scale in POINT_APERTURES:
                if self.designs + 4 > SEARCH_BUDGET:
                    break
                obj.aperture_scale = scale
                start = self.state.theta.vector()
                polished = self._search(obj, active, max_iter=3, scale=scale, cap=STAGE_CAPS[3])
                self.state.theta = polished.best.theta
                self.aperture_scale = scale
                _, steps, _ = self._space(active)
                if all(abs(polished.best.theta.vector()[k] - start[k]) < 0.1 * steps[k] * scale for k in active):
                    break  # the features already lie where the samples put them: a finer share moves nothing
            if polished is not found:
                keep = [i for i, k in enumerate(found.active) if k not in active]
                self.state.found = _merge(polished, found, keep)
                self._update(obj, polished.best)
        self.search_samples = obj.samples
        return self

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

    def _start_ff(self, obj: Objective) -> None:
        """The feed-forward share's start, the best of a coarse grid: far from where the data put the
        compensation's steps, the other columns take up most of the misplaced step and the misfit is flat in
        ``ff``, so a descent from 0 would stay there."""
        self.ff_started = True
        best = None
        for ff in FF_GRID:
            e = obj.evaluate(replace(self.state.theta, ff=ff))
            if best is None or e.sse < best.sse:
                best = e
        self._account(obj)
        assert best is not None
        self.state.theta = best.theta

    def _hold(self, obj: Objective, found: Found, k: int, value: float, drop: bool) -> None:
        """Hold coordinate ``k`` of :meth:`.search.Theta.vector` at ``value``: the others move to their best
        given it (the likelihood's quadratic: their regression on it), and the fit is made there.  ``drop``:
        it leaves the search (the wait: not part of the model here); else its spread stays counted (the
        loops' lag: the prior's, as the data barely tell it)."""
        j = found.active.index(k)
        cov = found.cov(self._noise(found.best, obj.samples))
        v = self.state.theta.vector()
        shift = value - v[k]
        for i, kk in enumerate(found.active):
            if kk != k and cov[j, j] > 0:
                v[kk] += cov[i, j] / cov[j, j] * shift
        v[k] = value
        bounds, _, _ = self._space(found.active)
        for kk, (lo, hi) in bounds.items():
            v[kk] = min(max(v[kk], lo), hi)
        best = obj.evaluate(Theta.of(v, self.state.theta.tau is not None))
        self._account(obj)
        if drop:
            keep = [i for i, kk in enumerate(found.active) if kk != k]
            self.state.found = Found(best, found.jtj[np.ix_(keep, keep)], found.hprior[np.ix_(keep, keep)],
                                     found.dx[:, keep], [found.active[i] for i in keep], found.phi, found.iterations)
        else:
            self.state.found = replace(found, best=best)
        self._update(obj, best)
        self.held.add(k)

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

    # ------------------------------------------------------------------ the final fit and the result

    def report(self, curves: bool = False) -> dict[str, Any]:
        plan, options = self.plan, self.options
        theta = self.state.theta
        timing = self.full_ctx.timing(theta)
        V = timing.feed_mm_s
        windows = {d: timing.window(d) for d in plan.direction_list}
        w_deg = self._width_for_verdict(theta)
        resolution_limited = bool(self.unresolved) or self.below_resolution or (
            self.sized and self.widths[0] > options.spike_width_min_deg
            and w_deg <= self.widths[0] * WIDTH_AT_BOUND)
        if self.sized or self.below_resolution:
            why = width_verdict(w_deg, self.widths, options, self.sample_hz, RESOLVE_SAMPLES, WIDTH_AT_BOUND)
            if why:
                self.exclude = {p.name: self.exclude.get(p.name, why) for p in self.patterns
                                if p.reversal is not None}
        self._exclude_spikes_of_compensated_axes(theta, V)
        # Spikes too narrow to size still touch the first samples after each table reversal: those are left out,
        # so that no other pattern (a backlash step, above all) takes them up.
        omega = V / plan.radius_mm
        self.skip_rad = SKIP_SAMPLES * omega * self.period_s if resolution_limited else 0.0
        values, lost = self.state.values, self.state.lost
        bins = self._bins(timing, windows, skip=lost)
        for d, b in bins.items():
            if b.samples < 8:
                a, z = windows[d]
                raise DataError(f"the {'CCW' if d > 0 else 'CW'} data arc ({a:.2f}..{z:.2f} s) holds "
                                f"{b.samples} samples: too few to fit")
        fit = None
        obj = None
        factor, colmax = None, None
        refolds = 0
        for _ in range(FINAL_STEPS):
            obj = Objective(self.full_ctx, bins, lost, self._offset_for(values, lost))
            obj.aperture_scale = self.aperture_scale
            factor, colmax = obj.factor(theta)
            self._account(obj)
            fit = solve(factor, self.patterns, significance=options.significance,
                        min_effect_um=options.min_effect_um, vif_limit=options.vif_limit,
                        effect_scale=colmax, exclude=self.exclude, rank=False)
            new_values = values_of(fit)
            se = {f: math.sqrt(max(fit.cov[i, i], 0.0)) for i, f in enumerate(_fields(self.patterns))
                  if np.isfinite(fit.cov[i, i])}
            chosen = self._choose(new_values, se, theta)
            if chosen.models != lost.models and refolds < 2:
                lost, refolds = chosen, refolds + 1
                values = new_values
                bins = self._bins(timing, windows, skip=lost)
                continue
            moved = _correction_moved(values, new_values, V)
            values = new_values
            if moved < OFFSET_SETTLED_UM:
                break
        assert fit is not None and obj is not None and factor is not None and colmax is not None
        offset = make_offset(values, theta.tau, lost, self.lag.cos2, self.frame_cos2)
        # the residual at every sample of the data arcs
        per_dir = self._residuals(timing, windows, theta, fit.x, lost, offset, obj)
        residuals = [r for _, _, r in per_dir.values()]
        rho = _lag1(residuals)
        # the nonlinear parameters' covariance at the final fit's noise, its correlation counted
        found = self.state.found
        self.final_kappa = _kappa(rho)
        noise_var = max(fit.sigma**2, NOISE_FLOOR_UM**2) * self.final_kappa
        self.theta_cov = found.cov(noise_var) if found is not None else np.zeros((0, 0))
        timing_cov = self._timing_cov(fit)
        servo_cov, servo_note = self._servo_cov(fit, theta, V)
        if servo_cov is not None:
            timing_cov = servo_cov if timing_cov is None else timing_cov + servo_cov
        model_cov = self._model_cov(fit, colmax)
        bias = self.quantisation_bias_um(fit)
        timing_cov = model_cov if timing_cov is None else timing_cov + model_cov
        res = self._solve_report(obj, theta, factor, colmax, rho, timing_cov)
        if servo_note:
            res["fit"]["uncertainty_method"] += servo_note
        res["fit"]["uncertainty_method"] += (
            f"; and every parameter's holds the model's own error, {MODEL_ERROR_UM:g} um of its largest radial "
            "effect (what the model leaves of the machine at any sample count)"
            + (f", or the mean quantisation error that follows the signal where larger ({bias:.2g} um: readings on "
               f"{self.step_um:.3g} um steps)" if bias > MODEL_ERROR_UM else "")
        )
        fit_final = res.pop("_fit")
        all_r = np.concatenate(residuals) if residuals else np.empty(0)
        rms = float(np.sqrt(np.mean(all_r**2))) if all_r.size else math.nan
        res["fit"]["servo_model"] = "physical" if theta.tau is not None else "linear"
        res["fit"]["servo_model_note"] = self.lag.source
        res["fit"]["lost_motion"] = lost.to_dict()
        res["fit"]["lost_motion_model"] = "; ".join(
            f"{axis.upper()}: {MODEL_WORDS[m]}" for axis, m in zip("xy", lost.models, strict=True)
        )
        res["fit"]["evaluations"] = self.misfits
        res["fit"]["designs"] = self.designs
        res["kind"] = "test"
        lag_se = math.nan
        w_se = math.nan
        if found is not None:
            for j, k in enumerate(found.active):
                s = math.sqrt(max(self.theta_cov[j, j], 0.0))
                if k == 0:
                    lag_se = s
                elif k == 2:
                    w_se = s * theta.w_deg
        res["timing"] = timing_dict(plan, self.fi, self.fo, timing, theta, V, lag_se, self.wait_free,
                                    self.ctx.shifts(theta.wait))
        res["timing"]["spike_width_stderr_deg"] = w_se if math.isfinite(w_se) else None
        spike_significance(res)
        res["advice"] = advise(res["parameters"], plan, self.machine)
        tau = theta.tau
        res["timing"]["loop_lag_ms"] = tau * 1000.0 if tau is not None else None
        origin, source = self._lag_origin(found)
        if found is not None and 3 in found.active and tau is not None:
            sd = math.sqrt(max(self.theta_cov[found.active.index(3), found.active.index(3)], 0.0))
            res["timing"]["loop_lag_stderr_ms"] = tau * 1000.0 * sd
        ff_j = found.active.index(4) if found is not None and 4 in found.active else None
        res["timing"]["loop_feed_forward"] = theta.ff if ff_j is not None else None
        res["timing"]["loop_feed_forward_stderr"] = (
            math.sqrt(max(float(self.theta_cov[ff_j, ff_j]), 0.0)) if ff_j is not None else None)
        res["timing"]["loop_lag_source"] = source
        res["timing"]["loop_lag_origin"] = origin
        res["fit"]["servo_model_note"] = source
        res["timing"]["loop_lag_radial_cos2u"] = self.lag.cos2
        # the dead band's own take-up, from where the axis reverses (its lag moves that: reversal_onset_deg holds
        # both)
        res["timing"]["backlash_takeup_deg"] = {
            axis: math.degrees(o - r) if m == "deadband" else 0.0
            for axis, m, o, r in zip("xy", lost.models, lost.onset_rad, lost.reversal_rad, strict=True)
        }
        res["timing"]["reversal_onset_deg"] = {axis: math.degrees(o) for axis, o in zip("xy", lost.onset_rad,
                                                                                      strict=True)}
        if theta.c > 0 and math.isfinite(theta.c):
            limits = model_limits(plan.with_(feed_mm_min=V * 60.0), V / theta.c)
            if limits:
                res["warnings"] = [
                    f"timing model: {why} (acceleration from the measured arc-start lag); the measured feed and the "
                    "angles are biased: lengthen overshoot_deg" for why in limits
                ]
        measured = {d: (u, y) for d, (u, y, _) in per_dir.items()}
        res["iso230_4"] = iso230.figures(measured)
        res["iso230_4"]["conditions"] = iso230.conditions(plan.to_dict(), V * 60.0, self.sample_hz)
        if any(name != standards.ISO for name in options.standards):
            res["standards"] = standards.figures(measured, options.standards, res["iso230_4"])
        res["noise"] = noise.findings(
            [(per_dir[d][0], per_dir[d][2], plan.data_arc_deg, self.sample_hz) for d in per_dir],
            options.vibration_cutoff_cpr, options.significance,
        )
        feed = (math.nan, 0.0)
        if len(plan.direction_list) > 1:
            # on the smooth objective (each sample's whole interval): the slope of a feed change is then the
            # model's along the whole arc, not the point samples' next to each step
            scale, obj.aperture_scale = obj.aperture_scale, 1.0
            e = obj.evaluate(theta)
            _, steps, _ = self._space([0, 1])
            feed = obj.last_arc_feed(e, steps, max(fit_final.sigma**2, NOISE_FLOOR_UM**2) * self.final_kappa)
            obj.aperture_scale = scale
            self._account(obj)
        check_model(res, per_dir, self.sample_hz, fit_final, feed, self.step_um)
        if curves:
            res["curves"] = {}
            for d, (u, y, r) in per_dir.items():
                tt = self.t[self._arc_samples(d, windows)]
                res["curves"]["ccw" if d > 0 else "cw"] = {
                    "t_s": tt, "u_deg": np.degrees(u), "measured_um": y, "model_um": y - r,
                }
        res["residual_rms_um"] = rms
        res["samples"] = {
            "in_test": int(self.t.size),
            "in_data_arcs": int(sum(per_dir[d][0].size for d in per_dir)),
            "sample_hz": self.sample_hz,
        }
        return res

    def _lag_origin(self, found: Found | None) -> tuple[str, str]:
        lag = self.lag
        if not self.tau_fitted or found is None or 3 not in found.active:
            return lag.origin, lag.source
        if 3 in self.held:
            return "assumed", (f"{lag.source}; the data arcs do not prefer another gain by more than {TAU_NATS:g} "
                               "nats (the loop's lag searched with the timing)")
        j = found.active.index(3)
        sd = math.sqrt(max(self.theta_cov[j, j], 0.0))
        kv = 1.0 / (self.state.theta.tau or 1.0 / DEFAULT_KV_PER_S)
        return "fitted", (
            f"fitted to the data arcs with the timing: {kv:.3g}/s (its log known to {sd:.2g}; the data prefer it to "
            f"the default {DEFAULT_KV_PER_S:g}/s by more than {TAU_NATS:g} nats); the feed-in's settling is not "
            "resolved at this sample rate and no kv_x/kv_y is configured"
        )

    def _timing_cov(self, fit: FitResult) -> np.ndarray | None:
        """The coefficients' covariance through the nonlinear parameters the same data fixed: ``J S J^T`` with
        ``S`` their covariance and ``J`` the coefficients' change with them (:class:`.search.Found`)."""
        found = self.state.found
        if found is None or not found.active:
            return None
        # the search's columns are the full model's, or all but the spikes' where they are not sized
        dx = np.zeros((fit.x.size, len(found.active)))
        full_cols = _column_map(self.ctx.patterns, self.patterns)
        dx[full_cols] = found.dx
        return np.asarray(dx @ self.theta_cov @ dx.T)

    def _exclude_spikes_of_compensated_axes(self, theta: Theta, V: float) -> None:
        """Leave out the spikes of an axis whose lost motion is an over-set compensation through the loop: the
        compensation's step reaches the axis partly at once (velocity feed-forward, a share no test of one feed
        pins down, :data:`.patterns.FEED_FORWARD`) and partly settling through the loop, from where the command
        reverses, and whatever of that response the model misses has the shape of a reversal spike there: it
        would be read as friction that the machine may not have."""
        tau = theta.tau
        if tau is None or not self.has_spikes:
            return
        lost = self.state.lost
        settle_deg = math.degrees(V / self.plan.radius_mm * tau)
        for axis, model in zip("xy", lost.models, strict=True):
            if model != "compensation":
                continue
            why = (f"on the {axis.upper()} axis the backlash compensation is set too high: its step reaches the axis "
                   "partly at once (velocity feed-forward) and partly settling through the loop "
                   f"({settle_deg:.2g} deg), which reversal spikes there cannot be told from")
            for p in self.patterns:
                if p.reversal is not None and p.reversal[0] == axis:
                    self.exclude.setdefault(p.name, why)

    def _model_cov(self, fit: FitResult, colmax: np.ndarray) -> np.ndarray:
        """The model's own error: each pattern's coefficient known to no better than ``MODEL_ERROR_UM`` of its
        largest radial effect over the data (``colmax``: um per unit), however many samples fix it.  The
        corrections, the timing and the loops' shapes are models: what they leave grows with the sample count
        against the fit's own standard error (at 1 kHz 0.003 um of lost motion), and two tests of one axis would
        then disagree by many of them on a consistent machine.  The loops' own properties carry none."""
        floor = max(MODEL_ERROR_UM, self.quantisation_bias_um(fit))
        cov = np.zeros((fit.x.size, fit.x.size))
        slices = fit.column_slices()
        for p in fit.patterns:
            if p.kind == "loop" or p.name not in slices:
                continue
            for j in range(slices[p.name].start, slices[p.name].stop):
                if j < colmax.size and colmax[j] > 0:
                    cov[j, j] = (floor / colmax[j]) ** 2
        return cov

    def quantisation_bias_um(self, fit: FitResult) -> float:
        """The mean quantisation error that follows the signal (:func:`.validity.quantisation_bias`), at the
        gauge's own noise the residual leaves once the quantisation's ``step^2 / 12`` is taken off it."""
        if not self.step_um > 0:
            return 0.0
        own = math.sqrt(max(fit.sigma**2 - self.step_um**2 / 12.0, 0.0)) if math.isfinite(fit.sigma) else 0.0
        return quantisation_bias(self.step_um, own)

    def _servo_cov(self, fit: FitResult, theta: Theta, V: float) -> tuple[np.ndarray | None, str]:
        """The scale mismatch's and the radius' covariance through what one circle cannot tell of the axes'
        dynamics, and its words.

        On a circle at ``Omega = V/R`` each axis answers with a gain ``g`` below 1: ``1 - g^2`` is
        ``Omega^2`` times the variance in time of the loop's impulse response (``1/K^2`` for a first-order
        loop, the model the corrections take).  Velocity feed-forward raises it (``(1 - ff^2)/K^2``), a
        velocity loop of finite bandwidth lowers it (by about ``2/(K wv)``), by as much as a third of
        ``1/K^2`` for controls of today.  The mean moves the radius (``R Omega^2 Var / 2``), the two axes'
        difference reads exactly as a scale mismatch (``cos 2u``; ``-(Omega^2 / 2) (VarX - VarY)``, in
        ppm): one feed cannot tell them apart, only a second, slower one (the term falls as the feed's
        square).  So each axis' variance is taken as known to ``SERVO_VAR_SHARE`` of the loops' lag
        squared, independently (the axes' dynamics differ: between velocity loops of 30 and 200 Hz the two
        axes' variances differ by 0.4 to 0.6 of the lag squared, between 45 and 60 Hz by under 0.15), and
        their mean to ``SERVO_MEAN_SHARE`` of it (feed-forward of 0.7 takes half of it off both), and the
        scale's and the radius' covariance hold that."""
        tau = theta.tau if theta.tau is not None else (FAST_LOOP_S if self.lag.origin == "fast" else None)
        if tau is None or not math.isfinite(tau):
            return None, ""
        R = self.plan.radius_mm
        omega2 = (V / R) ** 2
        sd_var = SERVO_VAR_SHARE * tau * tau  # s^2, per axis
        slices = fit.column_slices()
        cov = np.zeros((fit.x.size, fit.x.size))
        sd_scale = 0.5 * omega2 * math.sqrt(2.0) * sd_var * 1e6  # ppm
        sd_radius = 0.5 * R * 1000.0 * omega2 * SERVO_MEAN_SHARE * tau * tau  # um
        for name, sd in (("scale_mismatch", sd_scale), ("radius", sd_radius)):
            if name in slices:
                j = slices[name].start
                cov[j, j] = sd * sd
        return cov, (
            f"; the scale mismatch's also holds what one feed cannot tell of the axes' dynamics ({sd_scale:.2g} ppm: "
            f"each axis' loop variance known to {SERVO_VAR_SHARE:g} of its lag squared, feed-forward and velocity "
            f"loops unknown; a slower feed separates it), and the radius' the same for their mean ({sd_radius:.2g} um, "
            f"{SERVO_MEAN_SHARE:g} of it)"
        )

    def _solve_report(
        self, obj: Objective, theta: Theta, factor: Factor, colmax: np.ndarray, rho: float,
        timing_cov: np.ndarray | None
    ) -> dict[str, Any]:
        options = self.options
        # the spikes are also tested by their likelihood ratio against the spike-free model at its own best
        # timing (where the search made that model): the larger p counts
        lr = self._spike_lr() if self.sized else math.nan
        final = solve(factor, self.patterns, rho=rho, significance=options.significance,
                      min_effect_um=options.min_effect_um, vif_limit=options.vif_limit, effect_scale=colmax,
                      exclude=self.exclude, family_dof={"reversal_spike": 1},
                      family_lr={"reversal_spike": lr} if math.isfinite(lr) else None, timing_cov=timing_cov)
        res: dict[str, Any] = dict(result_body(self.plan, self.machine, options, final, self.patterns))
        if timing_cov is not None:
            res["fit"]["uncertainty_method"] += (
                "; every parameter's also holds the spread of the nonlinear parameters the same samples fixed (the "
                "arc-start lag, the feed-in's extra wait, the spikes' width, the loops' lag where fitted: their "
                "covariance from the likelihood's curvature, times each coefficient's change with them), and each "
                "F-test keeps the share of its Wald statistic left once that is counted"
            )
        res["_fit"] = final
        return res

    def _bare(self, obj: Objective, theta: Theta, wait: bool) -> Found:
        """The model without the spikes, its timing searched from ``theta`` on ``obj``'s bins."""
        bare_obj = Objective(obj.ctx, obj.bins, obj.lost, obj.offset, 0.0, spikes=False)
        bare_obj.aperture_scale = obj.aperture_scale
        active = [k for k in self._active(wait=wait) if k != 2]
        bounds, steps, priors = self._space(active)
        budget = max(min(SEARCH_BUDGET - self.designs, STAGE_CAPS[2]), 2)
        found = minimise(bare_obj, theta, active, bounds=bounds, steps=steps, priors=priors, max_iter=4,
                         max_evals=budget)
        self._account(bare_obj)
        return found

    def _spike_lr(self) -> float:
        """The spikes' likelihood ratio (nats) against the spike-free model at its own best timing, both on the
        fine bins of the search (:meth:`run`): free spikes could be buying a timing that the steps refute."""
        if self.spike_sse is None:
            return math.nan
        full, bare, samples = self.spike_sse
        n_eff = samples / self.final_kappa
        return max(0.5 * n_eff * math.log(max(bare, 1e-12) / max(full, 1e-12)), 0.0)

    def _arc_samples(self, d: int, windows: dict[int, tuple[float, float]]) -> np.ndarray:
        """The indices of direction ``d``'s data-arc samples (those just after a table reversal left out where
        :attr:`skip_rad` says)."""
        a, b = windows[d]
        i, j = int(np.searchsorted(self.t, a, side="left")), int(np.searchsorted(self.t, b, side="right"))
        idx = np.arange(i, j)
        if self.skip_rad > 0:
            timing = self.full_ctx.timing(self.state.theta)
            g = self._sample_geometry(d, self.t[i:j], timing, self.state.theta.tau, self.state.lost)
            idx = idx[~_after_onsets(g, self.skip_rad)]
        return idx

    def _residuals(
        self, timing: Timing, windows: dict[int, tuple[float, float]], theta: Theta, x: np.ndarray,
        lost: LostMotion, offset: Offset | None, obj: Objective,
    ) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per direction: each data-arc sample's angle (rad), deviation as measured (um) and residual (um).

        The model is made at every sample about the sharp features (the zones the bins are fine in); elsewhere
        it is smooth on a scale of degrees and is the bins' model interpolated (linearly, between bins a tenth
        of a degree or so apart: its error is the model's curvature times the square of that, below 1e-3 um)."""
        x = np.nan_to_num(x)
        w = math.radians(theta.w_deg)
        A, yw = obj.rows(theta)
        self._account(obj)
        wts = obj.weights
        model_w = A @ x  # the masks at each bin, weighted
        offset_b = np.concatenate([b.y for b in obj.bins.values()]) - yw / wts
        at_bins = model_w / wts + offset_b
        out = {}
        i0 = 0
        for d in self.plan.direction_list:
            idx = self._arc_samples(d, windows)
            t = self.t[idx]
            y = (self.L[idx] - self.plan.radius_mm) * 1000.0
            u = np.radians(timing.sched.angle_deg(self.plan, d, t - timing.t_ref))
            model = np.empty(t.size)
            b = obj.bins.get(d)
            nb = len(b) if b is not None else 0
            zone = np.zeros(t.size, dtype=bool)
            for za, zb in feature_zones(self.plan, timing, d, windows[d]):
                i, j = np.searchsorted(t - self.fi.t_s, (za, zb))
                zone[i:j] = True
            if b is None or nb < 2:
                zone[:] = True
            else:
                far = ~zone
                model[far] = np.interp(t[far] - self.fi.t_s, b.t, at_bins[i0 : i0 + nb])
            i0 += nb
            mine, cols = self.full_ctx.by_direction[d]
            near = np.flatnonzero(zone)
            for k in range(0, near.size, FOLD_ROWS):
                rows = near[k : k + FOLD_ROWS]
                g = self._sample_geometry(d, t[rows], timing, theta.tau, lost)
                m = design(mine, g, w) @ x[cols]
                model[rows] = m + offset(g) if offset is not None else m
            out[d] = (u, y, y - model)
        return out


def _merge(polished: Found, earlier: Found, keep: Sequence[int]) -> Found:
    """The last stage's minimum with the earlier one's curvature and slopes for the coordinates it held
    (``keep``: their indices in ``earlier.active``): the covariance of all, the held ones' cross terms as
    the earlier stage found them."""
    active = list(polished.active) + [earlier.active[i] for i in keep]
    n, m = len(active), len(polished.active)
    held = list(keep)
    # a coordinate the last stage searched and the earlier one did not (the loops' feed-forward, once an
    # over-set compensation shows) has no cross terms with the held ones: zero
    mine = [(i, earlier.active.index(k)) for i, k in enumerate(polished.active) if k in earlier.active]

    def merged(last: np.ndarray, before: np.ndarray) -> np.ndarray:
        out = np.zeros((n, n))
        out[:m, :m] = last
        out[m:, m:] = before[np.ix_(held, held)]
        for i, j in mine:
            out[i, m:] = before[j, held]
            out[m:, i] = before[held, j]
        return out

    jtj = merged(polished.jtj, earlier.jtj)
    hprior = merged(polished.hprior, earlier.hprior)
    if np.linalg.eigvalsh(jtj).min() < -1e-9 * max(float(np.abs(jtj).max()), 1e-300):
        # the earlier stage's cross terms do not fit the new block: the two blocks alone (each is a curvature)
        jtj[:m, m:] = 0.0
        jtj[m:, :m] = 0.0
    dx = np.zeros((polished.dx.shape[0], n))
    dx[:, :m] = polished.dx
    dx[:, m:] = earlier.dx[:, list(keep)]
    return Found(polished.best, jtj, hprior, dx, active, polished.phi, polished.iterations)


def _fields(patterns: Sequence[Pattern]) -> list[str]:
    return [f for p in patterns for f in p.fields]


def _column_map(sub: Sequence[Pattern], full: Sequence[Pattern]) -> np.ndarray:
    """The columns of ``full`` that ``sub``'s columns are."""
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    return np.array([pos[p.name] + k for p in sub for k in range(p.q)], dtype=int)


def _correction_moved(before: dict[str, float], after: dict[str, float], V: float) -> float:
    """How far (um) the corrections can have moved between two fits' values: the servo correction moves by at
    most ``|dm| V``; the centre's share of the exact bar length and the dead band's take-up far less."""
    dm = abs(after.get("servo_mismatch_ms", 0.0) - before.get("servo_mismatch_ms", 0.0))
    dc = math.hypot(after.get("centre_x_um", 0.0) - before.get("centre_x_um", 0.0),
                    after.get("centre_y_um", 0.0) - before.get("centre_y_um", 0.0))
    db = max(abs(after.get(k, 0.0) - before.get(k, 0.0)) for k in ("backlash_x_um", "backlash_y_um"))
    return dm * V + 1e-2 * dc + 1e-2 * db


def _after_onsets(g: Geometry, reach_rad: float) -> np.ndarray:
    """Samples within ``reach_rad`` past a table's reversal (where friction sets in), any axis."""
    out = np.zeros(len(g), dtype=bool)
    for axis, points in ((0, (0.0, math.pi)), (1, (0.5 * math.pi, 1.5 * math.pi))):
        for at in points:
            du = wrap(g.d * (g.u - at) - g.onset_rad[axis], 2.0 * math.pi)  # travel past the onset
            out |= du < reach_rad
    return out


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
    hz = _rate(t)
    lag = loop_lag(plan, machine, options, fi, fo, hz)
    return TestFit(plan, machine, options, t, L, fi, fo, lag, hz).run().report(curves)


__all__ = ["TestFit", "analyze_test", "check_plan", "feed_accel", "spike_width_bounds"]
_ = (data_start_deg, wrap)
