"""The live view's words: the findings of the last complete test, the test in progress, the events' times.

The findings panel answers the engineer's first question before the detail, as the report's first half
page does and with the same words (:mod:`ballbar.analysis.report`): the verdict against the limits and by
how much, what matters most (the machine's error patterns ranked by their share of the machine's error,
the set-up terms stated apart), what to do; then the limits, the figures, and the statistics.
"""

from __future__ import annotations

import datetime
from collections.abc import Mapping
from typing import Any

from ballbar.analysis.numbers import limit_texts, measured
from ballbar.analysis.plan import PLANE_AXES
from ballbar.analysis.report import (
    advice_lines,
    finding_words,
    machine_ranking,
    pattern_label,
    quantity_label,
    setup_words,
    share_text,
    significance_words,
    unit_text,
    value_text,
    verdict_summary,
)
from ballbar.analysis.sets import AXES, PAIRS, set_words

from .geometry import num


def _fmt(v: Any, nd: int = 3) -> str:
    x = num(v)
    return "–" if x is None else f"{x:.{nd}f}"


def _p_text(p: Any) -> str:
    x = num(p)
    if x is None:
        return "–"
    return "< 1e-12" if x < 1e-12 else f"{x:.1e}"


def clock_text(wall: float) -> str:
    """A wall-clock time as the viewer's events show it: UTC, to the millisecond."""
    return datetime.datetime.fromtimestamp(wall, datetime.UTC).strftime("%H:%M:%S.%f")[:-3] + " UTC"


def _axes(result: Mapping[str, Any]) -> tuple[str, str]:
    return PLANE_AXES.get(str((result.get("plan") or {}).get("plane", "XY")), ("X", "Y"))


def _conditions(result: Mapping[str, Any]) -> str:
    plan = result.get("plan") or {}
    tm = result.get("timing") or {}
    machine = (result.get("machine") or {}).get("machine_id") or result.get("machine_id") or ""
    feed = num(tm.get("measured_feed_mm_min")) or num(tm.get("assumed_feed_mm_min"))
    parts = [f"machine {machine}"] if machine else []
    parts += [f"plane {plan.get('plane', '?')}", f"R {plan.get('radius_mm', '?')} mm",
              f"F {plan.get('feed_mm_min', '?')} mm/min ({'measured' if result.get('kind') == 'test' else 'assumed'} "
              f"{_fmt(feed, 1)})", f"data arc {plan.get('data_arc_deg', '?')}°", str(plan.get("directions", "?"))]
    return " · ".join(parts)


def headline(result: Mapping[str, Any]) -> tuple[str, str]:
    """The verdict's status (``pass``, ``warning``, ``fail``, ``none``) and a line short enough for the polar
    plot's verdict bar at 1280 px: ``FAIL · test 12 · Circularity G(b) 53.7 µm, limit 25 µm``."""
    axes = _axes(result)
    vs = verdict_summary(result, axes)
    head = f"{vs['word']} · test {result.get('test_index', '?')}"
    worst = vs.get("worst")
    if isinstance(worst, Mapping) and num(worst.get("value")) is not None:
        raw = str(worst.get("unit") or "")
        se = num(worst.get("stderr"))
        lim_t, _m = limit_texts(worst.get("value"), se, worst.get("limit"), None, raw)
        return vs["status"], (f"{head} · {quantity_label(str(worst.get('name')), axes)} "
                              f"{measured(worst['value'], se, raw, shown=0)}, limit {lim_t} {unit_text(raw)}")
    iso = result.get("iso230_4") or {}
    g = num(iso.get("G_b_um"))
    return vs["status"], f"{head} · G(b) {measured(g, None, 'um')}" if g is not None else head


def findings_markdown(result: Mapping[str, Any], wall: float | None = None) -> str:
    """A test result (or a circle's, provisional) as markdown: the verdict first, then the detail."""
    axes = _axes(result)
    idx = result.get("test_index", "?")
    circle = result.get("kind") == "circle"
    vs = verdict_summary(result, axes)
    when = f" · {clock_text(wall)[:8]} UTC" if wall is not None else ""
    if circle:
        lines = [f"## Test {idx} in progress: {str(result.get('direction', '')).upper()} circle (provisional)"]
    else:
        lines = [f"## {vs['word']} · test {idx}{when}", "", f"**{vs['headline']}**"]
    ranking = [r for r in machine_ranking(result) if r.get("significant")]
    lines += ["", "### What matters most (share of the machine's error)", ""]
    if not ranking:
        lines.append("No machine error pattern stands out from the noise.")
    for i, r in enumerate(ranking[:5], 1):
        name = str(r["pattern"])
        lines.append(f"{i}. **{pattern_label(name, axes)}** {share_text(r.get('machine_share_pct'))}: "
                     f"{finding_words(name, result, axes)}")
    todo = [a for a in advice_lines(result, axes) if a["kind"] != "setup"]
    lines += ["", "### What to do", ""]
    lines += [f"- {a['text']}" for a in todo[:4]] or ["- nothing to adjust on the machine"]
    lines += ["", (f"test id `{result['test_id']}` · " if result.get("test_id") else "") + _conditions(result)]
    setup = setup_words(result)
    if setup:
        lines += ["", f"Set-up, not the machine (removed from the plot and the shares): {'; '.join(setup)}."]
    for w in result.get("warnings") or []:
        lines += ["", f"**Warning:** {w}"]
    lines += verdict_markdown(result.get("verdict"), axes)
    iso = result.get("iso230_4")
    if iso:
        lines += [
            "", "### ISO 230-4 (µm)", "",
            "| G CCW | G CW | G(b) | H | F max | F min |",
            "|---:|---:|---:|---:|---:|---:|",
            "| " + " | ".join(measured(iso.get(k), None, "um", with_unit=False)
                             for k in ("G_ccw_um", "G_cw_um", "G_b_um", "H_um", "F_max_um", "F_min_um")) + " |",
        ]
    nz = result.get("noise")
    if nz:
        lines += [
            "",
            f"Vibration {_fmt(nz.get('vibration_um'))} µm above {nz.get('vibration_cutoff_cpr')} cycles/rev "
            f"({'significant' if nz.get('vibration_significant') else 'not significant'}); "
            f"stick-slip X {_fmt(nz.get('stick_slip_x_um'))} µm, Y {_fmt(nz.get('stick_slip_y_um'))} µm",
        ]
    lines += _statistics(result, axes)
    tm = result.get("timing") or {}
    fit = [f"residual {_fmt(result.get('residual_rms_um'))} µm rms"]
    if num(tm.get("lag_s")) is not None:
        fit.append(f"arc-start lag {float(tm['lag_s']) * 1000:.1f} ms")
    if num(tm.get("spike_width_deg")) is not None:
        fit.append(f"spike width {_fmt(tm.get('spike_width_deg'), 2)}°")
    lines += ["", " · ".join(fit)]
    return "\n".join(lines) + "\n"


def _statistics(result: Mapping[str, Any], axes: tuple[str, str]) -> list[str]:
    params = result.get("parameters") or {}
    lines = ["", "### Detail: every machine pattern", "",
             "| # | pattern (field) | value ± SE | share | p | counted |", "|---|---|---:|---:|---:|---|"]
    for i, r in enumerate(machine_ranking(result)[:12], 1):
        name = str(r["pattern"])
        fields = [k for m in r["members"] for k in params if k.startswith(m + "_") and not k.endswith("_phase_deg")]
        val = "; ".join(value_text(params[k].get("value"), params[k].get("stderr"),
                                   unit=str(params[k].get("unit") or ""))
                        for k in fields[:2] if num(params[k].get("value")) is not None) or "–"
        why = r.get("significance_reason")
        counted = "**yes**" if r.get("significant") else (significance_words(str(why)).split(":")[0] if why else "no")
        field_names = ", ".join(f"`{k}`" for k in fields[:2]) + (" …" if len(fields) > 2 else "")
        lines.append(f"| {i} | {pattern_label(name, axes)} ({field_names}) | {val} | "
                     f"{share_text(r.get('machine_share_pct'))} | {_p_text(r.get('p_value'))} | {counted} |")
    return lines


def verdict_markdown(verdict: Any, axes: tuple[str, str] = ("X", "Y")) -> list[str]:
    """The verdict against the configured limits (``[limits]``) as markdown lines; none without limits."""
    if not isinstance(verdict, Mapping) or not verdict.get("limits"):
        return ["", "No acceptance limits set (`[limits]`): no pass/fail verdict."]
    k = num(verdict.get("coverage_k")) or 2.0
    lines = ["", f"### Limits: **{str(verdict.get('status', '?')).upper()}**", "",
             "| status | quantity (field) | value ± k u | limit | margin |", "|---|---|---:|---:|---:|"]
    for e in verdict["limits"]:
        st = str(e.get("status", "")).replace("_", " ").upper()
        if e.get("within_uncertainty"):
            st += " (within uncertainty)"
        margin = num(e.get("margin"))
        raw = str(e.get("unit") or "")
        se = num(e.get("stderr"))
        lim_t, m_t = limit_texts(e.get("value"), se, e.get("limit"), margin, raw)
        u = unit_text(raw)
        m_text = "–" if margin is None else (f"over by {m_t} {u}" if margin < 0 else f"{m_t} {u} below")
        lines.append(f"| **{st}** | {quantity_label(str(e.get('name')), axes)} (`{e.get('name')}`) | "
                     f"{measured(e.get('value'), se, raw, shown=e.get('uncertainty'))} | {lim_t} {u} | "
                     f"{m_text} |")
    lines += ["", f"fail only beyond the uncertainty (k = {k:g} standard uncertainties)"]
    return lines


__all__ = ["clock_text", "findings_markdown", "headline", "verdict_markdown"]


def set_headline(s: Mapping[str, Any]) -> tuple[str, str]:
    """The set's status (``pass``, ``warning``, ``fail``, ``none``) and its line for the machine's verdict bar:
    ``PASS · set machine: xy pass, zx pass, yz pass; 5 of 5 checks passed``."""
    w = set_words(s)
    return w["status"], f"{w['word']} · {w['headline']}"


def _fig(f: Mapping[str, Any] | None) -> str:
    if not isinstance(f, Mapping) or num(f.get("value")) is None:
        return "–"
    return measured(f["value"], f.get("stderr"), str(f.get("unit") or ""), with_unit=False) + (
        "" if f.get("trusted", True) else " (untrusted)")


def set_markdown(s: Mapping[str, Any]) -> str:
    """The set's verdict and its machine-wide figures in words: the head of the findings with a library of plans."""
    w = set_words(s)
    lines = [f"## Machine: {w['word']} · set {(s.get('set') or {}).get('name', '?')}", "", f"**{w['headline']}**"]
    for why in w["problems"][:3]:
        lines += ["", f"**Not trusted:** {why}"]
    lm, sq = s.get("lost_motion") or {}, s.get("squareness") or {}
    lines += ["", "| axis | lost motion µm | relative scale ppm | lag vs mean ms |", "|---|---:|---:|---:|"]
    for a in AXES:
        lines.append(f"| {a} | {_fig(lm.get(a))} | {_fig((s.get('scale') or {}).get('axes', {}).get(a))} | "
                     f"{_fig((s.get('servo') or {}).get('axes', {}).get(a))} |")
    lines += ["", "Squareness µrad: " + ", ".join(f"{p} {_fig(sq.get(p))}" for p in PAIRS)]
    vol = s.get("volumetric") or {}
    lcd, sph = vol.get("largest_circular_deviation") or {}, vol.get("geometric_sphericity") or {}
    lines += ["", f"Largest circular deviation {_fig(lcd)} µm ({lcd.get('plan') or '–'}); geometric sphericity "
                  f"{_fig(sph)} µm", "", "---", ""]
    return "\n".join(lines)
