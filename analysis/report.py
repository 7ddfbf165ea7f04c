"""Result dictionaries and the human-readable summary.

``parameters`` is keyed by every field of the library (analysis/README.md, "The pattern library"),
whether fitted or not: a parameter that was not fitted has ``value`` None,
``identifiable`` False and a ``reason``.  Cyclic errors are fitted as a sine and
cosine pair and reported as amplitude (``cyclic_x_um``) and phase
(``cyclic_x_phase_deg``), their standard errors by the delta method.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from .fit import FitResult, ParameterResult
from .numbers import decimals, fixed, limit_texts, measured, shown_stderr
from .patterns import LIBRARY, Pattern
from .plan import axis_key

if TYPE_CHECKING:
    from ballbar.protocol.messages.results import Parameters, RankingEntry


def _why_absent(pat: Pattern, axes: tuple[str, str]) -> str:
    if pat.needs in ("pitch_x", "pitch_y"):  # the plane's first, second axis
        axis = axes[0] if pat.needs == "pitch_x" else axes[1]
        return f"no {axis} screw pitch configured ({axis_key('pitch', axis)}): cyclic error not fitted"
    if pat.reversal is not None:
        return "this direction is not in the test"
    return "not in the selected patterns"


def parameters_dict(fit: FitResult, patterns: Sequence[Pattern], axes: tuple[str, str]) -> Parameters:
    """The result's parameters; ``axes``: the machine axes of the plane's first and second axis (``plan.axes``)."""
    fitted = {p.name: i for i, p in enumerate(fit.patterns)}
    slices = fit.column_slices()
    out: dict[str, Any] = {}
    for pat in LIBRARY:
        results: list[ParameterResult]
        i = fitted.get(pat.name)
        if i is None or not fit.used[i]:
            reason = fit.reasons.get(pat.name) or _why_absent(pat, axes)
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
    # keyed by every field of the library: the keys of Parameters (tests/test_schemas.py keeps the two the same)
    return cast("Parameters", out)


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


def ranking_list(fit: FitResult) -> list[RankingEntry]:
    out: list[RankingEntry] = []
    for t in sorted(fit.terms.values(), key=lambda t: -t.ssr):
        entry: RankingEntry = {"pattern": t.pattern, "share_pct": t.share_pct, "F": t.F if math.isfinite(t.F) else None,
                               "p_value": t.p_value, "significant": t.significant, "effect_um": t.effect_um}
        if t.reason:
            entry["significance_reason"] = t.reason
        out.append(entry)
    return out


def _fmt(v: Any, nd: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def summary(result: Mapping[str, Any]) -> str:
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
    name, rec = plan.get("name"), result.get("recognition") or {}
    if name and rec.get("method") not in (None, "only"):  # a library of plans: which, and how it was known
        lines.insert(1, f"Plan {name} (axes {'/'.join(plan.get('axes') or [])}): {rec.get('message', '')}")
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
        nd = decimals(p["value"], p["stderr"], p["unit"])
        se = "-" if p["stderr"] is None or not math.isfinite(p["stderr"]) else fixed(shown_stderr(p["stderr"], nd), nd)
        lines.append(f" {mark}{key:<34} {fixed(p['value'], nd):>12} {se:>10}  {p['unit']}")
    missing = [k for k, p in result["parameters"].items() if p["value"] is None and "not in the test" not in
               p.get("reason", "") and "not configured" not in p.get("reason", "")]
    for k in missing:
        lines.append(f"  {k}: not identifiable: {result['parameters'][k].get('reason', '')}")
    iso = result.get("iso230_4")
    if iso:
        lines += ["", "ISO 230-4:"]
        for k in ("G_ccw_um", "G_cw_um", "G_b_um", "H_um", "F_max_um", "F_min_um"):
            lines.append(f"  {k:<10} {measured(iso.get(k), None, 'um', with_unit=False, ascii=True)}")
    nz = result.get("noise")
    if nz:
        verdict = "significant" if nz.get("vibration_significant") else "not significant"
        lines += ["", f"Vibration: {_fmt(nz.get('vibration_um'))} um above {nz.get('vibration_cutoff_cpr')} "
                  f"cpr (strongest line {_fmt(nz.get('vibration_peak_um'))} um at "
                  f"{_fmt(nz.get('vibration_peak_hz'), 1)} Hz, {verdict}); "
                  f"stick-slip X {_fmt(nz.get('stick_slip_x_um'))} um, Y {_fmt(nz.get('stick_slip_y_um'))} um"]
    lines += ["", "Advice:"]
    from .advice import ranked_advice

    advice = ranked_advice(result)
    if not advice:
        lines.append("  nothing significant to adjust")
    for a in advice:
        cp = f"  [{a['controller_parameter']}]" if a.get("controller_parameter") else ""
        lines.append(f"  - {a['action']}{cp}")
    return "\n".join(lines)


SETUP_PATTERNS = ("centre", "radius")  # set-up terms, not machine findings


def headline(result: Mapping[str, Any], findings: int = 3) -> dict[str, Any]:
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


# --------------------------------------------------------------------------- presentation: the words both the live
# view and the report use, so that the two say the same thing about the same test

STATUS_WORDS = {"fail": "FAIL", "warning": "WARNING", "pass": "PASS", "none": "NO LIMITS SET"}
_STATUS_RANK = {"pass": 0, "warning": 1, "fail": 2}
_REVERSAL_AT = {"x_pos": ("x", "+", 0), "y_pos": ("y", "+", 90), "x_neg": ("x", "−", 180), "y_neg": ("y", "−", 270)}
_KIND = {p.name: p.kind for p in LIBRARY}
ISO_WORDS = {"G_b_um": "Circularity G(b)", "G_ccw_um": "Circularity G CCW", "G_cw_um": "Circularity G CW",
             "H_um": "Hysteresis H", "F_max_um": "Radial deviation F max", "F_min_um": "Radial deviation F min",
             "G_um": "Circularity G"}


def _axis(xy: str, axes: tuple[str, str]) -> str:
    return axes[0] if xy == "x" else axes[1]


def pattern_label(name: str, axes: tuple[str, str] = ("X", "Y")) -> str:
    """A pattern's name as an engineer says it, with the plane's own axes (``servo_mismatch``: Servo mismatch)."""
    a1, a2 = axes
    m = re.fullmatch(r"reversal_spike_([xy]_(?:pos|neg))_(ccw|cw)", name)
    if m:
        xy, sign, at = _REVERSAL_AT[m[1]]
        return f"Reversal spike {sign}{_axis(xy, axes)} ({at}°), {m[2].upper()}"
    m = re.fullmatch(r"reversal_spikes_([xy])", name)
    if m:
        return f"Reversal spikes {_axis(m[1], axes)}"
    m = re.fullmatch(r"(backlash|lateral_play|straightness|cyclic)_([xy])", name)
    if m:
        what = {"backlash": "Backlash", "lateral_play": "Lateral play", "straightness": "Straightness",
                "cyclic": "Cyclic error"}[m[1]]
        return f"{what} {_axis(m[2], axes)}"
    return {
        "centre": "Centre offset (set-up)",
        "radius": "Radius / bar length (set-up)",
        "servo_mismatch": "Servo mismatch",
        "master_slave": "Master-slave changeover",
        "squareness": f"Squareness {a1}{a2}",
        "scale_mismatch": f"Scale mismatch {a1}/{a2}",
        "drift": "Thermal drift",
    }.get(name, name.replace("_", " ").capitalize())


def field_label(key: str, axes: tuple[str, str] = ("X", "Y")) -> str:
    """The short name of one field inside its pattern's row (``X``, ``a (45°/225°)``, ``phase``)."""
    a1, a2 = axes
    return {
        "centre_x_um": a1, "centre_y_um": a2,
        "master_slave_a_um": "a (45°/225°)", "master_slave_b_um": "b (135°/315°)",
    }.get(key, "phase" if key.endswith("_phase_deg") else ("amplitude" if key.startswith("cyclic_") else ""))


def quantity_label(name: str, axes: tuple[str, str] = ("X", "Y")) -> str:
    """A limited or trended quantity (an ISO 230-4 key or a result field) in words: ``Backlash X``, ``Circularity
    G(b)``, ``Servo mismatch``."""
    if name in ISO_WORDS:
        return ISO_WORDS[name]
    for p in LIBRARY:
        fields = [f"{p.name}_um", f"{p.name}_phase_deg"] if p.name.startswith("cyclic_") else list(p.fields)
        if name in fields:
            fl = field_label(name, axes)
            label = pattern_label(p.name, axes)
            return f"{label} {fl}" if fl and fl != "amplitude" else label
    return name.replace("_", " ")


def unit_text(unit: Any) -> str:
    """A result unit for display: ``um`` is µm, ``urad`` µrad (the results' ASCII units)."""
    return re.sub(r"\burad\b", "µrad", re.sub(r"\bum\b", "µm", str(unit or "")))


def _finite(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def uncertainty_decimals(u: float | None, default: int = 2, unit: str = "") -> int:
    """The decimal place :func:`~ballbar.analysis.numbers.decimals` shows a value with uncertainty ``u`` at
    (``default`` without one and without a unit)."""
    if (u is None or u <= 0) and not unit:
        return default
    return decimals(None, u, unit)


def value_text(value: Any, u: Any = None, default_nd: int = 2, unit: str = "", shown: Any = None) -> str:
    """``3.03 ± 0.01``: the value with its standard error ``u`` by the one rule (:mod:`ballbar.analysis.numbers`),
    without the unit; ``shown``: the uncertainty the line quotes (k u) at the same place."""
    if _finite(u) is None and not unit and _finite(value) is not None:
        return fixed(float(value), default_nd)
    return measured(value, u, unit, shown=shown, with_unit=False)


def pattern_kind(name: str) -> str:
    """``setup``, ``machine`` or ``reversal`` (a grouped ``reversal_spikes_x``: ``reversal``)."""
    return "reversal" if name.startswith("reversal_spikes_") else _KIND.get(name, "machine")


def machine_ranking(result: Mapping[str, Any], group_spikes: bool = True) -> list[dict[str, Any]]:
    """The ranked machine patterns, each with its share of the machine's explained error, set-up terms left out.

    The published ``share_pct`` is each pattern's share of all the explained error, set-up (pivot offset, bar
    length) included (analysis/README.md, "Ranking"); commercial software states the set-up apart and ranks the
    machine's terms among themselves: ``machine_share_pct`` is ``share_pct`` over the sum of the machine terms'.
    ``group_spikes``: the reversal spikes of one axis as one entry (``reversal_spikes_x``, shares summed, the
    smallest p, significant when any is).  Entries keep the published keys (``pattern``, ``share_pct``, ``F``,
    ``p_value``, ``significant``, ``effect_um``) and add ``machine_share_pct``, ``label`` and ``members``.
    """
    entries: list[dict[str, Any]] = []
    groups: dict[str, dict[str, Any]] = {}
    for r in result.get("ranking") or []:
        if not isinstance(r, Mapping):
            continue
        name = str(r.get("pattern"))
        if _KIND.get(name, "machine") == "setup":
            continue
        m = re.fullmatch(r"reversal_spike_([xy])_(?:pos|neg)_(?:ccw|cw)", name)
        if group_spikes and m:
            key = f"reversal_spikes_{m[1]}"
            g = groups.get(key)
            if g is None:
                g = groups[key] = {"pattern": key, "share_pct": 0.0, "F": None, "p_value": None,
                                   "significant": False, "effect_um": 0.0, "members": []}
                entries.append(g)
            g["share_pct"] += _finite(r.get("share_pct")) or 0.0
            p = _finite(r.get("p_value"))
            if p is not None and (g["p_value"] is None or p < g["p_value"]):
                g["p_value"], g["F"] = p, r.get("F")
            g["significant"] = bool(g["significant"] or r.get("significant"))
            g["effect_um"] = max(g["effect_um"], _finite(r.get("effect_um")) or 0.0)
            g["members"].append(name)
            continue
        entries.append({**dict(r), "members": [name]})
    total = sum(_finite(e.get("share_pct")) or 0.0 for e in entries)
    for e in entries:
        s = _finite(e.get("share_pct"))
        e["machine_share_pct"] = 100.0 * s / total if s is not None and total > 0 else None
    entries.sort(key=lambda e: -(e["machine_share_pct"] or 0.0))
    return entries


def share_text(share: Any) -> str:
    """A percentage for a ranking: ``78 %``, ``3.4 %``, ``< 0.1 %`` (never ``-0.00``)."""
    x = _finite(share)
    if x is None:
        return "–"
    if x < 0.05:
        return "< 0.1 %"
    return f"{x:.0f} %" if x >= 9.95 else f"{x:.1f} %"


def _pv(result: Mapping[str, Any], key: str) -> float | None:
    p = (result.get("parameters") or {}).get(key)
    return _finite(p.get("value")) if isinstance(p, Mapping) else None


def param_text(result: Mapping[str, Any], key: str, *, magnitude: bool = False, signed: bool = False,
               value: float | None = None) -> str:
    """A result parameter's value with its unit by the one rule (its standard error sets the place, not shown):
    ``3.03 ms``; ``magnitude``: its absolute value; ``value``: another value of the same place (its opposite)."""
    p = (result.get("parameters") or {}).get(key)
    p = p if isinstance(p, Mapping) else {}
    v = _finite(p.get("value")) if value is None else value
    if v is None:
        return "–"
    unit = str(p.get("unit") or key.rsplit("_", 1)[-1])
    nd = decimals(v, _finite(p.get("stderr")), unit)
    return f"{fixed(abs(v) if magnitude else v, nd, signed)} {unit_text(unit)}"


def finding_words(name: str, result: Mapping[str, Any], axes: tuple[str, str] = ("X", "Y")) -> str:
    """One machine pattern as a phrase with its value and sign spelt out (``X lags Y by 3.03 ms``)."""
    a1, a2 = axes
    params: Mapping[str, Any] = result.get("parameters") or {}
    if name.startswith("reversal_spikes_"):
        xy = name[-1]
        spikes = [(k, x) for k in params if re.fullmatch(rf"reversal_spike_{xy}_(pos|neg)_(ccw|cw)_um", k)
                  and (x := _pv(result, k)) is not None]
        if spikes:
            k, _x = max(spikes, key=lambda kx: abs(kx[1]))
            return f"reversal spikes of {_axis(xy, axes)} up to {param_text(result, k, signed=True)}"
        return pattern_label(name, axes)
    key = (list(LIBRARY_FIELDS.get(name, ())) or [""])[0]
    v = _pv(result, key)
    if name == "servo_mismatch" and v is not None:
        slow, fast = (a1, a2) if v > 0 else (a2, a1)
        return f"{slow} lags {fast} by {param_text(result, key, magnitude=True)}"
    if name == "squareness" and v is not None:
        return f"{a1} leans toward {'+' if v > 0 else '−'}{a2} by {param_text(result, key, magnitude=True)}"
    if name == "scale_mismatch" and v is not None:
        return f"{a1} scales {param_text(result, key, signed=True)} relative to {a2}"
    if name.startswith("backlash_") and v is not None:
        return f"backlash of {_axis(name[-1], axes)} {param_text(result, key)}"
    parts: list[str] = []
    for k in LIBRARY_FIELDS.get(name, ()):
        p = params.get(k)
        if isinstance(p, Mapping) and _finite(p.get("value")) is not None:
            fl = field_label(k, axes)
            parts.append(f"{fl + ' ' if fl else ''}{param_text(result, k, signed=True)}")
    label = pattern_label(name, axes)
    return f"{label[0].lower() + label[1:]} {', '.join(parts)}" if parts else label.lower()


#: Each pattern's result fields (cyclic errors as amplitude and phase).
LIBRARY_FIELDS: dict[str, tuple[str, ...]] = {
    p.name: ((f"{p.name}_um", f"{p.name}_phase_deg") if p.name.startswith("cyclic_") else tuple(p.fields))
    for p in LIBRARY
}


def setup_words(result: Mapping[str, Any]) -> list[str]:
    """The set-up terms in words (removed from the plots and figures; not a machine error)."""
    out = []
    cx, cy = _pv(result, "centre_x_um"), _pv(result, "centre_y_um")
    if cx is not None or cy is not None:
        x, y = (param_text(result, k, signed=True, value=v or 0.0).split()[0]
                for k, v in (("centre_x_um", cx), ("centre_y_um", cy)))
        out.append(f"pivot off the programmed centre by ({x}, {y}) µm")
    rad = _pv(result, "radius_um")
    if rad is not None and abs(rad) >= 0.05:
        out.append(f"circle {param_text(result, 'radius_um', signed=True)} from the nominal radius")
    return out


def limit_words(entry: Mapping[str, Any], axes: tuple[str, str] = ("X", "Y")) -> str:
    """One limit of a verdict in words: ``Circularity G(b) 53.7 ± 1.4 µm, limit 25.0 µm: over by 28.7 µm``
    (the value ± its k standard uncertainties, the limit and the margin at the value's place)."""
    name = str(entry.get("name", ""))
    raw_unit = str(entry.get("unit") or "")
    unit = unit_text(raw_unit)
    label = quantity_label(name, axes)
    lim = _finite(entry.get("limit"))
    if entry.get("status") == "not_evaluated" or _finite(entry.get("value")) is None:
        why = f"{label}: not evaluated ({entry.get('reason') or 'no value'})"
        return f"{why}, limit {lim:g} {unit}" if lim is not None else why
    se = _finite(entry.get("stderr"))
    if se is None:
        se = _finite(entry.get("uncertainty"))
    value = measured(entry.get("value"), se, raw_unit, shown=entry.get("uncertainty"))
    margin = _finite(entry.get("margin"))
    lim_t, m_t = limit_texts(entry.get("value"), se, lim, margin, raw_unit)
    if margin is None or lim is None:
        return f"{label} {value}, limit {lim_t} {unit}"
    how = f"over by {m_t} {unit}" if margin < 0 else f"{m_t} {unit} ({100 * margin / lim:.0f} %) below it"
    if entry.get("within_uncertainty"):
        how += ", within uncertainty of the limit"
    elif entry.get("status") == "warning":
        wl = _finite(entry.get("warning_level")) or 0.0
        how += f", above the warning level {limit_texts(entry.get('value'), se, wl, None, raw_unit)[0]} {unit}"
    return f"{label} {value}, limit {lim_t} {unit}: {how}"


def verdict_summary(result: Mapping[str, Any], axes: tuple[str, str] = ("X", "Y")) -> dict[str, Any]:
    """The first thing an engineer asks, in words: is this machine fine, by how much?

    ``status``: ``pass``, ``warning``, ``fail`` (the result's verdict against its limits) or ``none`` (no limits
    configured); ``word`` (``FAIL`` ...); ``headline``: the worst limit in words (what failed and by how much), or
    without limits the circularity; ``limits``: every limit in words, worst first (``(status, text)``);
    ``counts``: how many limits are in each status.
    """
    v = result.get("verdict")
    iso = result.get("iso230_4") or {}
    g = next(((k, _finite(iso.get(k))) for k in ("G_b_um", "G_ccw_um", "G_cw_um") if _finite(iso.get(k)) is not None),
             None)
    g_text = f"{ISO_WORDS[g[0]]} {measured(g[1], None, 'um')}" if g is not None else "no circularity figure"
    if not isinstance(v, Mapping) or not v.get("limits"):
        return {"status": "none", "word": STATUS_WORDS["none"], "headline": f"{g_text}; no acceptance limits set",
                "limits": [], "counts": {}, "worst": None}
    entries = [e for e in v["limits"] if isinstance(e, Mapping)]

    def badness(e: Mapping[str, Any]) -> tuple[int, float]:
        pct = _finite(e.get("margin_pct"))
        return (_STATUS_RANK.get(str(e.get("status")), -1), -(pct if pct is not None else 1e9))

    ranked = sorted(entries, key=badness, reverse=True)
    status = str(v.get("status", "pass"))
    counts: dict[str, int] = {}
    for e in entries:
        counts[str(e.get("status"))] = counts.get(str(e.get("status")), 0) + 1
    worst = ranked[0] if ranked else None
    headline = limit_words(worst, axes) if worst is not None else g_text
    return {"status": status, "word": STATUS_WORDS.get(status, status.upper()), "headline": headline,
            "limits": [(str(e.get("status")), limit_words(e, axes)) for e in ranked], "counts": counts,
            "worst": worst}


def advice_lines(result: Mapping[str, Any], axes: tuple[str, str] = ("X", "Y")) -> list[dict[str, Any]]:
    """The result's advice for display, worth giving and in the order to act on it
    (:func:`ballbar.analysis.advice.ranked_advice`: what fails its limit first, then by share of the machine's
    error, set-up last; a finding inside its own limit is no advice); the reversal spikes one line per axis,
    where the axis' first spike ranks.

    Each ``{"kind", "text", "controller_parameter"}``; ``text`` with µm and µrad.
    """
    from .advice import ranked_advice

    out: list[dict[str, Any]] = []
    spikes: dict[str, list[tuple[str, str]]] = {}
    cps: dict[str, str] = {}
    for a in ranked_advice(result):
        m = re.fullmatch(r"reversal_spike_([xy])_(pos|neg)_(ccw|cw)_um", str(a.get("pattern", "")))
        if m:
            v = _finite(a.get("value"))
            if v is not None:
                if m[1] not in spikes:
                    spikes[m[1]] = []
                    out.append({"kind": "machine", "spikes": m[1]})
                spikes[m[1]].append((f"{_REVERSAL_AT[m[1] + '_' + m[2]][2]}° {m[3].upper()}",
                                     param_text(result, str(a["pattern"]), signed=True, value=v)))
                if a.get("controller_parameter"):
                    cps[m[1]] = str(a["controller_parameter"])
            continue
        text = unit_text(str(a.get("action", ""))).replace("+-", "±")
        text = re.sub(r"(\d) deg\b", "\\1°", text)
        out.append({"kind": str(a.get("kind") or "machine"), "text": text,
                    "controller_parameter": a.get("controller_parameter")})
    for item in out:
        xy = item.pop("spikes", None)
        if xy is not None:
            where = ", ".join(f"{w} {v}" for w, v in spikes[xy])
            item.update(text=f"reversal spikes of {_axis(xy, axes)} ({where}): adjust the friction / quadrant-glitch "
                        f"compensation of {_axis(xy, axes)}", controller_parameter=cps.get(xy))
    return out


def significance_words(reason: str) -> str:
    """Why a pattern whose F-test passed is still not counted, said without the contradiction ``no: statistically
    significant``: ``too small: ...`` or ``not proven: ...``."""
    m = re.match(r"statistically significant \(p = ([^)]+)\) but its largest radial effect, ([^ ]+) um, is below "
                 r"the minimum effect of ([^ ]+) um", reason)
    if m:
        return f"too small: its largest effect {m[2]} µm is below the {m[3]} µm that counts (p = {m[1]})"
    return "not proven: " + unit_text(reason)


#: The polar plots (live view and report) draw the largest deviation within this many divisions of their scale.
POLAR_DIVISIONS = 3


def polar_division_um(max_abs_um: float) -> float:
    """A polar plot's division: 1, 2 or 5 x 10^n um, so that the largest deviation spans at most
    :data:`POLAR_DIVISIONS` divisions (the outermost ring then contains every point)."""
    x = max_abs_um / POLAR_DIVISIONS if math.isfinite(max_abs_um) and max_abs_um > 0 else 1.0
    x = max(x, 0.01)
    e = 10.0 ** math.floor(math.log10(x))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * e >= x * (1 - 1e-9):
            return m * e
    return 10.0 * e  # pragma: no cover - the loop always returns


def trend_range(values: Sequence[float | None], stderrs: Sequence[float | None], k: float = 1.0,
                lines: Sequence[float] = ()) -> tuple[float, float] | None:
    """A trend's y range: :func:`trend_limits` (at least +-4 standard errors about the mean), widened to hold
    every point with its error bar (``k`` standard errors) and the ``lines`` (limit, warning level), with 5 %
    to spare."""
    pts = [(float(v), abs(float(u)) if u is not None and math.isfinite(u) else None)
           for v, u in zip(values, stderrs, strict=True) if v is not None and math.isfinite(v)]
    if not pts:
        return None
    base = trend_limits([v for v, _u in pts], [u for _v, u in pts])
    lo = min([v - k * (u or 0.0) for v, u in pts] + list(lines))
    hi = max([v + k * (u or 0.0) for v, u in pts] + list(lines))
    pad = 0.05 * (hi - lo) if hi > lo else max(abs(hi) * 0.05, 1e-3)
    lo, hi = lo - pad, hi + pad
    if base is not None:
        lo, hi = min(lo, base[0]), max(hi, base[1])
    return lo, hi
