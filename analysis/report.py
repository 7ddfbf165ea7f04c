"""Result dictionaries and the human-readable summary.

``parameters`` is keyed by every field of the library (analysis/README.md, "The pattern library"),
whether fitted or not: a parameter that was not fitted has ``value`` None,
``identifiable`` False and a ``reason``.  Cyclic errors are fitted as a sine and
cosine pair and reported as amplitude (``cyclic_x_um``) and phase
(``cyclic_x_phase_deg``), their standard errors by the delta method.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from .fit import FitResult, ParameterResult
from .patterns import LIBRARY, Pattern
from .plan import MachineConfig


def _why_absent(pat: Pattern, machine: MachineConfig) -> str:
    if pat.needs == "pitch_x":
        return "no X screw pitch configured (pitch_x_mm): cyclic error not fitted"
    if pat.needs == "pitch_y":
        return "no Y screw pitch configured (pitch_y_mm): cyclic error not fitted"
    if pat.reversal is not None:
        return "this direction is not in the test"
    return "not in the selected patterns"


def parameters_dict(fit: FitResult, patterns: Sequence[Pattern], machine: MachineConfig) -> dict[str, Any]:
    fitted = {p.name: i for i, p in enumerate(fit.patterns)}
    slices = fit.column_slices()
    out: dict[str, Any] = {}
    for pat in LIBRARY:
        results: list[ParameterResult]
        i = fitted.get(pat.name)
        if i is None or not fit.used[i]:
            reason = fit.reasons.get(pat.name) or _why_absent(pat, machine)
            results = [ParameterResult(f, u, None, None, identifiable=False, reason=reason)
                       for f, u in _report_fields(pat)]
        else:
            sl = slices[pat.name]
            x = fit.x[sl]
            cov = fit.cov[sl, sl]
            term = fit.terms.get(pat.name)
            pv = term.p_value if term else None
            share = term.share_pct if term else None
            sig = bool(term.significant) if term else False
            if pat.name.startswith("cyclic_"):
                results = _cyclic(pat, x, cov, pv, share, sig)
            else:
                results = [
                    ParameterResult(f, u, float(x[k]), math.sqrt(max(cov[k, k], 0.0)), pv, share, sig)
                    for k, (f, u) in enumerate(zip(pat.fields, pat.units, strict=True))
                ]
            for r in results:
                r.significance_reason = term.reason if term else ""
        for r in results:
            out[r.field] = r.to_dict()
    return out


def _report_fields(pat: Pattern) -> list[tuple[str, str]]:
    if pat.name.startswith("cyclic_"):
        return [(f"{pat.name}_um", "um"), (f"{pat.name}_phase_deg", "deg")]
    return list(zip(pat.fields, pat.units, strict=True))


def _cyclic(
    pat: Pattern, x: np.ndarray, cov: np.ndarray, pv: float | None, share: float | None, sig: bool
) -> list[ParameterResult]:
    a, b = float(x[0]), float(x[1])  # c cos(phi), c sin(phi)
    amp = math.hypot(a, b)
    phase = math.degrees(math.atan2(b, a))
    if amp > 0:
        ja = np.array([a / amp, b / amp])
        jp = np.array([-b / amp**2, a / amp**2])
        se_amp = math.sqrt(max(float(ja @ cov @ ja), 0.0))
        se_ph = math.degrees(math.sqrt(max(float(jp @ cov @ jp), 0.0)))
    else:
        se_amp = math.sqrt(max(float(np.trace(cov)) / 2, 0.0))
        se_ph = float("inf")
    return [
        ParameterResult(f"{pat.name}_um", "um", amp, se_amp, pv, share, sig),
        ParameterResult(f"{pat.name}_phase_deg", "deg", phase, se_ph, pv, share, sig),
    ]


def ranking_list(fit: FitResult) -> list[dict[str, Any]]:
    terms = sorted(fit.terms.values(), key=lambda t: -t.ssr)
    return [
        {
            "pattern": t.pattern,
            "share_pct": t.share_pct,
            "F": t.F if math.isfinite(t.F) else None,
            "p_value": t.p_value,
            "significant": t.significant,
            "effect_um": t.effect_um,
            **({"significance_reason": t.reason} if t.reason else {}),
        }
        for t in terms
    ]


def _fmt(v: Any, nd: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def summary(result: dict[str, Any]) -> str:
    """A readable multi-line summary of a test result."""
    plan = result["plan"]
    tm = result.get("timing", {})
    lines = [
        f"Ball-bar test: plane {plan['plane']}, R {plan['radius_mm']:g} mm, F {plan['feed_mm_min']:g} mm/min "
        f"(measured {_fmt(tm.get('measured_feed_mm_min'), 1)}), data arc {plan['data_arc_deg']:g} deg, "
        f"{plan['directions']}",
        f"Samples: {result.get('samples', {}).get('in_data_arcs', '-')} in the data arcs at "
        f"{_fmt(result.get('samples', {}).get('sample_hz'), 3)} Hz; residual RMS "
        f"{_fmt(result.get('residual_rms_um'))} um",
        f"Timing: lag {_fmt(tm.get('lag_s'), 4)} s ({_fmt(tm.get('lag_deg'), 3)} deg), spike width "
        f"{_fmt(tm.get('spike_width_deg'), 2)} deg",
        "",
        "Ranked findings (extra sum of squares):",
        f"  {'pattern':<28} {'share %':>8} {'p-value':>10}  significant",
    ]
    for r in result["ranking"]:
        lines.append(
            f"  {r['pattern']:<28} {r['share_pct']:8.2f} {r['p_value']:10.2e}  {'yes' if r['significant'] else 'no'}"
            + (f" ({r['significance_reason']})" if r.get("significance_reason") else "")
        )
    rule = result.get("fit", {}).get("significance_rule")
    if rule:
        lines.append(f"  Significant: {rule}.")
    lines += ["", "Parameters:", f"  {'field':<34} {'value':>12} {'+-':>10}  unit"]
    for key, p in result["parameters"].items():
        if p["value"] is None:
            continue
        mark = "*" if p["significant"] else " "
        lines.append(f" {mark}{key:<34} {p['value']:12.4f} {_fmt(p['stderr'], 4):>10}  {p['unit']}")
    missing = [k for k, p in result["parameters"].items() if p["value"] is None and "not in the test" not in
               p.get("reason", "") and "not configured" not in p.get("reason", "")]
    for k in missing:
        lines.append(f"  {k}: not identifiable: {result['parameters'][k].get('reason', '')}")
    iso = result.get("iso230_4")
    if iso:
        lines += ["", "ISO 230-4:"]
        for k in ("G_ccw_um", "G_cw_um", "G_b_um", "H_um", "F_max_um", "F_min_um"):
            lines.append(f"  {k:<10} {_fmt(iso.get(k))}")
    nz = result.get("noise")
    if nz:
        verdict = "significant" if nz.get("vibration_significant") else "not significant"
        lines += ["", f"Vibration: {_fmt(nz.get('vibration_um'))} um above {nz.get('vibration_cutoff_cpr')} "
                  f"cpr (strongest line {_fmt(nz.get('vibration_peak_um'))} um at "
                  f"{_fmt(nz.get('vibration_peak_hz'), 1)} Hz, {verdict}); "
                  f"stick-slip X {_fmt(nz.get('stick_slip_x_um'))} um, Y {_fmt(nz.get('stick_slip_y_um'))} um"]
    lines += ["", "Advice:"]
    if not result.get("advice"):
        lines.append("  nothing significant to adjust")
    for a in result.get("advice", []):
        cp = f"  [{a['controller_parameter']}]" if a.get("controller_parameter") else ""
        lines.append(f"  - {a['action']}{cp}")
    return "\n".join(lines)


SETUP_PATTERNS = ("centre", "radius")  # set-up terms, not machine findings


def headline(result: dict[str, Any], findings: int = 3) -> dict[str, Any]:
    """A test result's headline: ``G_b_um``, ``measured_feed_mm_min`` and its strongest significant findings.

    ``findings``: up to that many ``{"parameter", "value", "unit"}`` of the
    significant machine patterns (set-up terms left out), in ranking order.
    """
    params = result.get("parameters", {})
    found: list[dict[str, Any]] = []
    for r in result.get("ranking", []):
        if len(found) >= findings:
            break
        if not r.get("significant") or r.get("pattern") in SETUP_PATTERNS:
            continue
        for key, p in params.items():
            if key.startswith(f"{r['pattern']}_") and p.get("value") is not None and not key.endswith("_phase_deg"):
                found.append({"parameter": key, "value": p["value"], "unit": p.get("unit", "")})
                break
    return {
        "G_b_um": result.get("iso230_4", {}).get("G_b_um"),
        "measured_feed_mm_min": result.get("timing", {}).get("measured_feed_mm_min"),
        "findings": found,
    }


def headline_text(h: dict[str, Any]) -> str:
    """:func:`headline` in one short line: ``G(b) 5.21 um, feed 999.8 mm/min; backlash_x_um 4.02, ...``."""
    parts = []
    if h.get("G_b_um") is not None:
        parts.append(f"G(b) {h['G_b_um']:.2f} um")
    if h.get("measured_feed_mm_min") is not None:
        parts.append(f"feed {h['measured_feed_mm_min']:.1f} mm/min")
    text = ", ".join(parts)
    found = ", ".join(f"{f['parameter']} {f['value']:.3g}" for f in h.get("findings", []))
    return f"{text}; {found}" if found else text


#: A trend's axis spans at least this many standard errors either side of its mean: a change within
#: the parameter's uncertainty then looks flat, not like a drift (3.0306 to 3.0318 ms, autoscaled,
#: filled a plot although the standard error was about 0.01 ms).
TREND_STDERR_SPAN = 4.0


def trend_limits(
    values: Sequence[float | None], stderrs: Sequence[float | None], span: float = TREND_STDERR_SPAN,
) -> tuple[float, float] | None:
    """The axis range of a trend: the points with their error bars and 5 % to spare, and at least
    ``span`` typical standard errors (their median) either side of the mean.

    None when there is no finite value, or no standard error to scale by (left to autoscaling).
    """
    pairs = [(float(v), None if s is None or not math.isfinite(s) else abs(float(s)))
             for v, s in zip(values, stderrs, strict=True) if v is not None and math.isfinite(v)]
    errs = [s for _v, s in pairs if s is not None]
    if not pairs or not errs:
        return None
    lo = min(v - (s or 0.0) for v, s in pairs)
    hi = max(v + (s or 0.0) for v, s in pairs)
    pad = 0.05 * (hi - lo)
    lo, hi = lo - pad, hi + pad
    mean = sum(v for v, _s in pairs) / len(pairs)
    half = span * float(np.median(errs))
    return min(lo, mean - half), max(hi, mean + half)
