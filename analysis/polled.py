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
analyze`` of a recording) hands the source's ``timing`` events; a test takes
the largest of the last one before its feed-in and those up to its feed-out
(host clock: a polled source has no other), live and offline alike.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any, TypeVar, cast

if TYPE_CHECKING:
    from ballbar.protocol.messages import CircleBody, TestBody

R = TypeVar("R", bound="CircleBody | TestBody")

Z = 2.0  # standard errors from zero a timing-dependent parameter must stay to remain a finding


Timing = tuple[float, float, float]  # a timing event: (t_host s, t_uncertainty_s, t_jitter_s)


def from_events(events: Iterable[Mapping[str, Any]]) -> list[Timing]:
    """The ``timing`` events among ``events`` (dicts as logged), in order."""
    out: list[Timing] = []
    for ev in events:
        if str(ev.get("event") or ev.get("kind") or "") != "timing":
            continue
        t, u, j = ev.get("t_host"), ev.get("t_uncertainty_s"), ev.get("t_jitter_s")
        if all(isinstance(x, int | float) and math.isfinite(x) for x in (t, u, j)):
            out.append((float(t), float(u), float(j)))  # type: ignore[arg-type]
    return out


def for_span(timings: Iterable[Timing], t0: float | None, t1: float | None) -> tuple[float, float] | None:
    """``(t_uncertainty_s, t_jitter_s)`` for a test from ``t0`` to ``t1`` (host clock; None: unbounded): the
    largest of the last event at or before ``t0`` and those after it up to ``t1``; None if there is none."""
    lo = -math.inf if t0 is None else t0
    hi = math.inf if t1 is None else t1
    before: Timing | None = None
    chosen: list[Timing] = []
    for ev in sorted(timings):
        if ev[0] <= lo:
            before = ev
        elif ev[0] <= hi:
            chosen.append(ev)
    if before is not None:
        chosen.append(before)
    if not chosen:
        return None
    return max(e[1] for e in chosen), max(e[2] for e in chosen)


def state_span(result: R, timings: Iterable[Timing]) -> R:
    """:func:`state_timing` with the figures :func:`for_span` gives for the result's feed-in to feed-out."""
    timing = cast(Mapping[str, Any], result).get("timing")
    if not isinstance(timing, dict):
        return result
    t0, t1 = timing.get("feed_in_s"), timing.get("feed_out_s")
    got = for_span(timings, t0 if isinstance(t0, int | float) else None, t1 if isinstance(t1, int | float) else None)
    return result if got is None else state_timing(result, *got)


def state_timing(body: R, t_uncertainty_s: float, t_jitter_s: float) -> R:
    """``body`` (a circle's or test's result, changed in place and returned) with polled stamps' cost counted."""
    _state_timing(cast(dict[str, Any], body), t_uncertainty_s, t_jitter_s)
    return body


def _state_timing(result: dict[str, Any], t_uncertainty_s: float, t_jitter_s: float) -> None:
    timing = result.get("timing")
    params = result.get("parameters")
    if not isinstance(timing, dict) or not isinstance(params, dict):
        return
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


def _radius(result: Mapping[str, Any]) -> float | None:
    cond = result.get("iso230_4", {}).get("conditions", {}) if isinstance(result.get("iso230_4"), dict) else {}
    r = cond.get("radius_mm") if isinstance(cond, dict) else None
    return float(r) if isinstance(r, int | float) and r > 0 else None


__all__ = ["Timing", "Z", "for_span", "from_events", "state_span", "state_timing"]
