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
4. the feed-in's wait kept free, its spread counted in every parameter's;
5. the final fit, its corrections brought to their fixed point.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from .detect import StepEvent
from .errors import DataError
from .fitresult import Assembly
from .fitstate import SEARCH_BUDGET, TAU_NATS, WIDTH_AT_BOUND, _rate, check_plan
from .loops import DEFAULT_KV_PER_S, loop_lag
from .patterns import wrap
from .physics import LostMotion
from .plan import AnalysisOptions, MachineConfig, TestPlan
from .program import data_start_deg
from .search import (
    FINE_BIN_DEG,
    Context,
    Found,
    Objective,
    Theta,
    minimise,
)

SMOOTH_S = 0.02  # the first stage integrates the sharp features over this much travel (s of the feed)
FF_GRID = (0.0, 0.25, 0.5, 0.75, 0.95)  # its search starts from the best of these
STAGE_CAPS = (8, 14, 6, 6)  # designs per search: the coarse stage's, the fine's, the spike-free model's, each
# point-sample share's (the first Jacobian and a step always)
POINT_APERTURES = (0.2, 0.03)  # the last stage integrates the sharp features over these shares of a sample's
# interval in turn
FINE_TRIM_S = 0.03  # the fine stage's data arcs, trimmed for timings within this of the coarse stage's


class TestFit(Assembly):
    """The analysis of one test (see the module docstring); :meth:`run` then :meth:`report`."""

    __test__ = False

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
                    self.state.theta = replace(found.best.theta, c=nb.c, wait=nb.wait, tau=nb.tau, ff=nb.ff,
                                               smooth=nb.smooth)
                    restarted, again = True, True
            if not again:
                break
        # 4. the feed-in's extra wait stays free, its spread counted: what the schedule puts between the feed-in's
        # centroid and each arc (a short move's profile, how much of the overhead shapes the move, an
        # in-position wait) is known only to milliseconds where the feed-in spans a few samples, and one arc's
        # shift against the other turns a large servo pattern into lateral play
        last = self.state.found
        self.wait_free = last is not None and 1 in last.active
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


__all__ = ["TestFit", "analyze_test"]
_ = (data_start_deg, wrap)
