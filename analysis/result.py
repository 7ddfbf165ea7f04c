"""A test's or a circle's result object: its body, its timing, and the reversal spikes' verdicts.

The result is the published contract (analysis/README.md; the schema of
``ballbar/<m>/result/test``): ``parameters`` and ``ranking`` from the fit
(:mod:`.report`), ``advice``, ``fit`` (how it was fitted and judged) and
``timing`` (the measured feed and the nonlinear parameters).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

from ballbar import SCHEMA_VERSION  # the payloads' version, one for all (ballbar.protocol.messages)

from .advice import advise
from .circle import Timing
from .detect import StepEvent
from .fit import FitResult, significance_rule
from .patterns import Pattern
from .plan import AnalysisOptions, MachineConfig, TestPlan
from .program import data_start_deg
from .search import Theta

if TYPE_CHECKING:
    from ballbar.protocol.messages.results import BodyCommon

SPIKE_Z = 2.0  # a significant spike's height is at least this many of its (full) standard errors


def result_body(
    plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, fit: FitResult, patterns: Sequence[Pattern]
) -> BodyCommon:
    from .report import parameters_dict, ranking_list

    params = parameters_dict(fit, patterns, plan.axes)
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


def values_of(fit: FitResult) -> dict[str, float]:
    """The fitted values by field (those left out absent)."""
    out: dict[str, float] = {}
    j = 0
    for pat, used in zip(fit.patterns, fit.used, strict=True):
        for k, f in enumerate(pat.fields):
            if used:
                out[f] = float(fit.x[j + k])
        j += pat.q
    return out


def timing_dict(
    plan: TestPlan, fi: StepEvent, fo: StepEvent, timing: Timing, theta: Theta, V: float, lag_stderr_s: float,
    wait_free: bool, shifts: dict[int, float],
) -> dict[str, Any]:
    omega = V / plan.radius_mm  # rad/s
    return {
        "provisional": False,
        "programmed_feed_mm_min": plan.feed_mm_min,
        "measured_feed_mm_min": V * 60.0,
        "feed_ratio": V / plan.feed_mm_s,
        "overhead_s": theta.c,
        "lag_s": theta.c,
        "lag_deg": math.degrees(omega * theta.c),
        "lag_stderr_s": lag_stderr_s if math.isfinite(lag_stderr_s) else None,
        "spike_width_deg": theta.w_deg,
        "feed_in_s": fi.t_s,
        "feed_out_s": fo.t_s,
        "feed_in_method": fi.method,
        "feed_out_method": fo.method,
        "feed_in_height_mm": fi.height_mm,
        "feed_out_height_mm": fo.height_mm,
        "data_arcs": {
            ("ccw" if d > 0 else "cw"): {
                "start_s": timing.window(d)[0], "end_s": timing.window(d)[1], "shift_s": shifts.get(d, 0.0)
            }
            for d in plan.direction_list
        },
        "method": (
            "feed from the feed-in to feed-out centroid span; the arc-start lag (per-move overhead), each data "
            "arc's shift against it (unequal waits before the arcs, or the feed-in's own duration off the "
            "schedule's model of it: fitted, its spread counted in every parameter's"
            + ("" if wait_free else "; not fitted here, 0")
            + "), the spikes' width and, where nothing else tells it, the loops' lag, by separable least squares "
            "of the full model (Gauss-Newton on the residual of the linear fit), every sharp feature integrated "
            "over each sample's interval"
        ),
    }


def spike_significance(res: dict[str, Any]) -> None:
    """A spike is significant only at least ``SPIKE_Z`` standard errors from zero, its timing and width counted.

    Its F-test holds the timing and the width as known; the standard error
    does not.  A height the timing or the width could take away is no finding.
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


def unreached_spikes(plan: TestPlan, patterns: Sequence[Pattern]) -> dict[str, str]:
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


def width_verdict(
    w: float, bounds: tuple[float, float], options: AnalysisOptions, sample_hz: float, resolve_samples: float,
    at_bound: float,
) -> str:
    """Why spikes of the fitted width ``w`` (deg) are not sized, or "" when they are.

    A width on a bound of its search is no estimate: at the lower one where
    that is the sample spacing's, the spikes are below the resolution; at the
    configured lower one, the reversals show nothing as gradual as friction
    (a bump of one or two samples is noise); at the upper one, what follows
    the reversals is a smooth change of the path, not a friction spike.
    """
    lo, hi = bounds
    if w <= lo * at_bound and lo > options.spike_width_min_deg:
        return (
            f"below the resolution at {sample_hz:.6g} Hz: the spikes decay within {w:.2f} deg or less, about "
            f"{lo / resolve_samples:.2f} deg between samples; at least {resolve_samples:g} samples per width are "
            "needed to size them"
        )
    if w <= lo * at_bound:
        return (
            f"no reversal spike: the fitted width runs onto its lower bound, {lo:g} deg (spike_width_min_deg); "
            "nothing after the reversals decays as gradually as friction does"
        )
    if w >= hi / at_bound:
        return (
            f"no reversal spike: the fitted width runs onto its upper bound, {hi:g} deg (spike_width_max_deg); what "
            "follows the reversals changes too slowly for friction"
        )
    return ""
