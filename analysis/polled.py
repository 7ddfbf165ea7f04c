"""What a polled gauge's time stamps cost a result, stated on the result.

A polled gauge (``protocol/README.md``, "Gauge profiles") has no clock: the
host sends a request and stamps the answer at the middle of the request/answer
window.  Where in the window the gauge took its reading is not known, so

- every stamp may be off by up to half the window (``t_uncertainty_s``, half
  the p99 window): an error common to all samples, which the arc start's lag
  absorbs; its standard error is widened by it;
- stamps may differ from one another by up to half the windows' spread
  (``t_jitter_s``, half the p1 to p99 range): what a *differential* timing
  parameter can be off by.  The servo mismatch (a difference of two axes'
  lags) gets it added, in quadrature, to its standard error; a reversal spike
  narrower than two jitters is not placed by these stamps, so it is not a
  finding; the spikes' width gets the jitter (in degrees) in its standard error.

A parameter that was significant and is within two of its widened standard
errors of zero is no longer significant, with the reason.  The result's
``timing`` says all this: ``time_source``, ``t_uncertainty_ms``,
``t_jitter_ms``.  Pure: the caller (the daemon's analysis, ``ballbar
analyze`` of a recording) says the two figures, from the source's ``timing``
events.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

Z = 2.0  # standard errors from zero a timing-dependent parameter must stay to remain a finding


def from_events(events: Iterable[Mapping[str, Any]]) -> tuple[float, float] | None:
    """``(t_uncertainty_s, t_jitter_s)``: the largest of the ``timing`` events among ``events``, or None."""
    unc = jit = -1.0
    for ev in events:
        if str(ev.get("event") or ev.get("kind") or "") != "timing":
            continue
        u, j = ev.get("t_uncertainty_s"), ev.get("t_jitter_s")
        if isinstance(u, int | float) and math.isfinite(u):
            unc = max(unc, float(u))
        if isinstance(j, int | float) and math.isfinite(j):
            jit = max(jit, float(j))
    if unc < 0:
        return None
    return unc, max(jit, 0.0)


def state_timing(result: dict[str, Any], t_uncertainty_s: float, t_jitter_s: float) -> dict[str, Any]:
    """``result`` (a circle's or test's, changed in place and returned) with polled stamps' cost counted."""
    timing = result.get("timing")
    params = result.get("parameters")
    if not isinstance(timing, dict) or not isinstance(params, dict):
        return result
    timing["time_source"] = "host clock, polled: each reading stamped at the middle of its request/answer window"
    timing["t_uncertainty_ms"] = 1e3 * t_uncertainty_s
    timing["t_jitter_ms"] = 1e3 * t_jitter_s
    if isinstance(timing.get("lag_stderr_s"), int | float):
        timing["lag_stderr_s"] = math.hypot(timing["lag_stderr_s"], t_uncertainty_s)
    feed = timing.get("measured_feed_mm_min")
    radius = _radius(result)
    deg_per_s = math.degrees(feed / 60.0 / radius) if isinstance(feed, int | float) and radius else math.nan
    jitter_deg = t_jitter_s * deg_per_s
    timing["t_jitter_deg"] = jitter_deg if math.isfinite(jitter_deg) else None
    if isinstance(timing.get("spike_width_stderr_deg"), int | float) and math.isfinite(jitter_deg):
        timing["spike_width_stderr_deg"] = math.hypot(timing["spike_width_stderr_deg"], jitter_deg)
    ranking = {r.get("pattern"): r for r in result.get("ranking", []) if isinstance(r, dict)}

    def not_a_finding(key: str, why: str) -> None:
        p = params[key]
        if p.get("significant"):
            p["significant"] = False
            p["significance_reason"] = why
            r = ranking.get(key.rsplit("_", 1)[0])
            if r is not None and r.get("significant"):
                r["significant"], r["significance_reason"] = False, why

    servo = params.get("servo_mismatch_ms")
    if isinstance(servo, dict) and isinstance(servo.get("stderr"), int | float):
        servo["stderr"] = math.hypot(servo["stderr"], 1e3 * t_jitter_s)
        if servo.get("value") is not None and abs(servo["value"]) < Z * servo["stderr"]:
            not_a_finding("servo_mismatch_ms", (
                f"within {Z:g} standard errors ({servo['stderr']:.2g} ms) of zero once the polled stamps' jitter "
                f"({1e3 * t_jitter_s:.2g} ms) is counted"))
    width = timing.get("spike_width_deg")
    if isinstance(width, int | float) and math.isfinite(jitter_deg) and width < Z * jitter_deg:
        for key, p in params.items():
            if key.startswith("reversal_spike_") and isinstance(p, dict):
                not_a_finding(key, (
                    f"its width, {width:.2g} deg, is less than {Z:g} times the polled stamps' jitter "
                    f"({jitter_deg:.2g} deg): these stamps do not place it"))
    fit = result.get("fit")
    if isinstance(fit, dict) and isinstance(fit.get("uncertainty_method"), str):
        fit["uncertainty_method"] += (
            "; polled stamps: the arc start's lag widened by their uncertainty, the servo mismatch and the spikes' "
            "width by their jitter"
        )
    return result


def _radius(result: Mapping[str, Any]) -> float | None:
    cond = result.get("iso230_4", {}).get("conditions", {}) if isinstance(result.get("iso230_4"), dict) else {}
    r = cond.get("radius_mm") if isinstance(cond, dict) else None
    return float(r) if isinstance(r, int | float) and r > 0 else None


__all__ = ["Z", "from_events", "state_timing"]
