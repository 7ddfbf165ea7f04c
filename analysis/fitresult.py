"""The final fit of one test (:mod:`.testfit`) and the result's assembly: the patterns at the searched timing,
their corrections at their fixed point, the uncertainty of the timing and of the servo parameters, the residuals
and the result's fields.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from . import iso230, noise, standards
from .advice import advise
from .circle import Timing, _after_onsets
from .errors import DataError
from .fit import Factor, FitResult, solve
from .fitstate import RESOLVE_SAMPLES, TAU_NATS, WIDTH_AT_BOUND, Pieces
from .loops import DEFAULT_KV_PER_S, FAST_LOOP_S
from .patterns import Pattern, design
from .physics import MODEL_WORDS, LostMotion, Offset, make_offset
from .plan import plane_keys
from .program import model_limits
from .result import (
    result_body,
    spike_significance,
    timing_dict,
    values_of,
    width_verdict,
)
from .search import (
    NOISE_FLOOR_UM,
    Found,
    Objective,
    Theta,
    feature_zones,
)
from .validity import check_model, quantisation_bias

SKIP_SAMPLES = 2.0  # samples after each table reversal left out where spikes are below the resolution
OFFSET_SETTLED_UM = 1e-3  # the corrections' fixed point: they move by less than this (um)
FINAL_STEPS = 4
FOLD_ROWS = 16384  # samples whose model is made at a time
SERVO_VAR_SHARE = 0.3  # each axis' loop variance in time known to this share of the loops' lag squared
SERVO_MEAN_SHARE = 0.5  # ... and the two axes' mean to this share
MODEL_ERROR_UM = 0.005  # the model's own error, of each pattern's largest radial effect (analysis/README.md,
# "Uncertainty"): a floor its standard error keeps at any sample count


def _lag1(residuals: Sequence[np.ndarray]) -> float:
    num = sum(float(np.dot(r[1:], r[:-1])) for r in residuals if r.size > 1)
    den = sum(float(np.dot(r, r)) for r in residuals)
    return num / den if den > 0 else 0.0


def _kappa(rho: float) -> float:
    """The AR(1) variance inflation ``(1 + rho) / (1 - rho)`` of a residual's lag-1 correlation, 1..400."""
    return min(max((1 + rho) / (1 - rho), 1.0), 400.0) if rho < 1 else 400.0


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


class Assembly(Pieces):
    """The final fit and the result (:meth:`report`) of a test's fit, once its stages have run."""

    __test__ = False

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
            f"resolved at this sample rate and no {plane_keys('kv', self.plan.plane)} is configured"
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
                "arc-start lag, the feed-in's extra wait, the spikes' width, the loops' lag where fitted, the "
                "share of a short feed-in's duration where searched: their "
                "covariance from the likelihood's curvature, times each coefficient's change with them), and each "
                "F-test keeps the share of its Wald statistic left once that is counted"
            )
        res["_fit"] = final
        return res

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
