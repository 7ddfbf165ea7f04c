"""The report's HTML: its style sheet and its sections, each a function of the result.

The first half page answers the engineer's first question (:func:`verdict`): is this machine fine
(the verdict against the configured limits, in a word and a colour), by how much (the worst limit and
its margin, every limit below it), what matters most (the machine's error patterns ranked by their share
of the machine's error, the set-up stated apart) and what to do (the advice, one line per axis).  The
detail follows: the plots, the findings with their statistics, ISO 230-4, noise, diagnostics, trend.
Names are the words an engineer uses; a configuration key or a result field appears only in the
statistics and in the field column that a service developer needs.
"""

from __future__ import annotations

import datetime as dt
import html
import math
from collections.abc import Mapping, Sequence
from typing import Any

from ballbar.analysis.numbers import measured
from ballbar.analysis.report import (
    LIBRARY_FIELDS,
    advice_lines,
    field_label,
    finding_words,
    machine_ranking,
    pattern_kind,
    pattern_label,
    setup_words,
    share_text,
    significance_words,
    unit_text,
    value_text,
    verdict_summary,
)

from .report import ReportData
from .report_plots import STATUS_COLOURS, Curve, g_of, num, parse_time, plane_axes

MISSING = "–"


def e(v: Any) -> str:
    return html.escape(str(v), quote=True)


def fmt(v: Any, nd: int = 2, *, signed: bool = False) -> str:
    x = num(v)
    if x is None:
        return MISSING
    if x == 0 or abs(x) < 0.5 * 10 ** -nd:
        x = 0.0  # never "-0.00"
    return f"{x:+.{nd}f}" if signed else f"{x:.{nd}f}"


def prose(text: Any) -> str:
    """Result text (advice, methods, reasons) for display: µm and µrad, ± for ``+-``."""
    import re

    text = unit_text(str(text or "")).replace("+-", "±")
    return re.sub(r"(\d) deg\b", "\\1°", text)


def p_text(p: Any) -> str:
    x = num(p)
    if x is None:
        return MISSING
    if x < 1e-12:
        return "< 1e-12"  # far beyond any level (the F tail may even underflow to 0)
    return f"{x:.3f}" if x >= 1e-3 else f"{x:.1e}"


def f_text(f: Any) -> str:
    x = num(f)
    if x is None:
        return MISSING
    if abs(x) >= 1e4:
        return "> 10 000"
    return f"{x:.3g}"


def time_text(t: Any) -> str:
    d = parse_time(t)
    if d is None:
        return str(t) if t else MISSING
    return d.strftime("%Y-%m-%d %H:%M:%S UTC")


CSS = """
:root { --ink:#1c2430; --muted:#5b6472; --faint:#8a94a3; --rule:#d9dee5; --band:#f4f6f9; --accent:#1f5fbf;
  --ccw:#1f5fbf; --cw:#d0342c; --fail:#b42318; --warning:#b25e09; --pass:#1d7a46; --none:#5b6472; }
* { box-sizing: border-box; }
html { -webkit-text-size-adjust: 100%; }
body { margin: 0 auto; max-width: 1060px; padding: 24px 32px 40px; color: var(--ink); background: #fff;
  font: 14px/1.45 "Segoe UI", "Helvetica Neue", Arial, "Liberation Sans", "DejaVu Sans", sans-serif;
  font-variant-numeric: tabular-nums; overflow-wrap: break-word; }
header.top { display: flex; justify-content: space-between; align-items: flex-end; gap: 24px;
  border-bottom: 3px solid var(--ink); padding-bottom: 10px; margin-bottom: 14px; }
header.top h1 { margin: 0; font-size: 24px; letter-spacing: .2px; }
header.top .sub { color: var(--muted); margin-top: 4px; font-size: 14px; }
header.top .sub b { color: var(--ink); }
header.top .brand { text-align: right; color: var(--muted); font-size: 12px; line-height: 1.35; white-space: nowrap; }
header.top .brand b { color: var(--ink); font-size: 13px; letter-spacing: 1.5px; }
section { margin: 22px 0 0; }
h2 { font-size: 16px; letter-spacing: .3px; color: var(--ink); margin: 0 0 8px;
  padding-bottom: 4px; border-bottom: 1px solid var(--rule); }
h2 .n { color: var(--accent); margin-right: 8px; }
h3 { font-size: 13.5px; margin: 12px 0 4px; color: var(--muted); letter-spacing: .2px; }
p { margin: 6px 0; }
.note, .caption { color: var(--muted); font-size: 12.5px; }
.note.warning { color: #8a4b00; }
.caption { margin-top: 4px; }
dl.kv { display: grid; grid-template-columns: repeat(3, max-content minmax(0, 1fr)); gap: 3px 12px; margin: 0;
  font-size: 13px; }
dl.kv dt { color: var(--muted); white-space: nowrap; }
dl.kv dd { margin: 0; font-weight: 600; }
.verdict { border: 1px solid var(--rule); border-left: 10px solid var(--status); background: var(--tint);
  padding: 12px 18px 10px; display: grid; grid-template-columns: minmax(0, 1fr) minmax(0, 1fr); gap: 6px 28px; }
.verdict.fail { --status: var(--fail); --tint: #fdeceb; }
.verdict.warning { --status: var(--warning); --tint: #fff4e2; }
.verdict.pass { --status: var(--pass); --tint: #e8f5ec; }
.verdict.none { --status: var(--none); --tint: var(--band); }
.verdict .head { grid-column: 1 / -1; display: flex; flex-wrap: wrap; align-items: baseline; gap: 6px 16px; }
.verdict .badge { display: inline-block; background: var(--status); color: #fff; font-size: 26px; font-weight: 700;
  letter-spacing: 1px; padding: 2px 14px; border-radius: 4px; }
.verdict .headline { font-size: 17px; font-weight: 600; min-width: 0; }
.verdict .lbl { color: var(--muted); font-size: 12.5px; font-weight: 600; margin: 6px 0 2px; }
.verdict ol, .verdict ul { margin: 2px 0 0; padding-left: 20px; }
.verdict li { margin: 2px 0; }
.verdict .setup { grid-column: 1 / -1; }
.st { display: inline-block; min-width: 58px; text-align: center; padding: 0 6px; border-radius: 9px;
  font-size: 11.5px; font-weight: 700; color: #fff; margin-right: 6px; }
.st.fail { background: var(--fail); } .st.warning { background: var(--warning); } .st.pass { background: var(--pass); }
.st.not_evaluated { background: var(--faint); }
.share { display: inline-block; height: 8px; background: var(--accent); border-radius: 2px; vertical-align: middle;
  margin-right: 6px; }
figure { margin: 8px 0 0; break-inside: avoid; page-break-inside: avoid; }
figure.polar { max-width: 620px; margin-left: auto; margin-right: auto; }
svg.plot { display: block; width: 100%; height: auto; }
table { border-collapse: collapse; width: 100%; font-size: 13px; }
th, td { padding: 4px 8px; border-bottom: 1px solid var(--rule); vertical-align: top; text-align: left; }
thead th { background: var(--band); border-bottom: 1.5px solid var(--ink); font-weight: 600; font-size: 12px;
  color: var(--ink); }
td.num, th.num { text-align: right; white-space: nowrap; }
td.date, td.tid { white-space: nowrap; }
td.rank { color: var(--faint); width: 28px; text-align: right; }
td.pat { min-width: 9em; }
table.trend td.tid { white-space: normal; overflow-wrap: anywhere; }
table.trend .u { font-weight: 400; color: var(--muted); }
.wide { overflow-x: auto; }
tr.sig td.pat { font-weight: 600; }
tr.nsig td { color: var(--muted); }
tr.absent td { color: var(--faint); font-style: italic; }
.pill { display: inline-block; padding: 0 7px; border-radius: 9px; font-size: 11.5px; font-weight: 600; }
.pill.yes { background: #fdebd3; color: #8a4a00; }
.pill.no { background: #eef0f3; color: var(--muted); }
.pill.kind { background: #e7eefa; color: var(--accent); margin-right: 6px; }
.pill.setup { background: #fbefe0; color: var(--warning); }
.sw { display: inline-block; width: 14px; height: 3px; vertical-align: middle; margin-right: 4px; }
table.iso td, table.iso th { text-align: center; }
table.iso td { font-size: 16px; font-weight: 600; }
table.iso td.gb { color: var(--accent); }
ul.advice { margin: 4px 0; padding-left: 0; list-style: none; }
ul.advice li { padding: 5px 0; border-bottom: 1px solid var(--rule); }
code { font-family: "DejaVu Sans Mono", "Liberation Mono", Consolas, monospace; font-size: 12px;
  background: var(--band); padding: 0 4px; border-radius: 3px; overflow-wrap: anywhere; }
details { margin-top: 8px; } summary { cursor: pointer; color: var(--muted); font-size: 12.5px; }
.cols { display: grid; grid-template-columns: minmax(0, 1fr) minmax(0, 1fr); gap: 24px; }
.signoff { display: grid; grid-template-columns: repeat(auto-fit, minmax(220px, 1fr)); gap: 18px 28px;
  margin-top: 10px; }
.signoff div { border-top: 1px solid var(--ink); padding-top: 4px; font-size: 12.5px; color: var(--muted);
  min-height: 54px; }
footer { margin-top: 28px; padding-top: 8px; border-top: 1px solid var(--rule); color: var(--muted);
  font-size: 11.5px; display: flex; justify-content: space-between; gap: 16px; flex-wrap: wrap; }
footer span { min-width: 0; overflow-wrap: anywhere; }
@media (max-width: 860px) { dl.kv { grid-template-columns: max-content minmax(0, 1fr); }
  .cols, .verdict { grid-template-columns: minmax(0, 1fr); } body { padding: 14px; }
  header.top { flex-wrap: wrap; } header.top .brand { display: none; } th, td { padding: 4px 5px; } }
@media print {
  @page { size: A4; margin: 13mm 12mm 14mm; }
  body { max-width: none; padding: 0; font-size: 10pt; }
  * { -webkit-print-color-adjust: exact; print-color-adjust: exact; }
  h2 { break-after: avoid; page-break-after: avoid; }
  section { break-inside: auto; }
  tr, figure, .verdict, dl.kv, ul.advice li, .signoff { break-inside: avoid; page-break-inside: avoid; }
  figure.polar { max-width: 150mm; }
  a { color: inherit; text-decoration: none; }
}
"""


class Doc:
    """Numbered sections in reading order."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.n = 0

    def section(self, sid: str, title: str, body: str) -> None:
        self.n += 1
        self.parts.append(
            f'<section id="sec-{e(sid)}"><h2><span class="n">{self.n}</span>{e(title)}</h2>\n{body}\n</section>'
        )


def kv(items: Sequence[tuple[str, str]]) -> str:
    return '<dl class="kv">' + "".join(f"<dt>{e(k)}</dt><dd>{e(v)}</dd>" for k, v in items) + "</dl>"


def rule_words(result: Mapping[str, Any], alpha: float) -> str:
    """The result's significance rule as it states it (older results: the level alone)."""
    rule = (result.get("fit") or {}).get("significance_rule")
    return prose(rule) if rule else f"p < {alpha:g}"


# --------------------------------------------------------------------------- the first half page


def verdict(result: Mapping[str, Any], curves: Sequence[Curve]) -> str:
    """Is this machine fine, by how much, what matters most, what to do: in words and colour."""
    axes = plane_axes(result.get("plan") or {})
    vs = verdict_summary(result, axes)
    status = vs["status"]
    iso = result.get("iso230_4") or {}
    g, gname, _gkey = g_of(result)
    limits = ""
    if vs["limits"]:
        items = "".join(f'<li><span class="st {e(st)}">{e(st.replace("_", " ").upper())}</span>{e(text)}</li>'
                        for st, text in vs["limits"])
        counts = vs["counts"]
        tally = ", ".join(f"{counts[s]} {s.replace('_', ' ')}" for s in ("fail", "warning", "pass", "not_evaluated")
                          if counts.get(s))
        k = num((result.get("verdict") or {}).get("coverage_k")) or 2.0
        limits = (f'<div class="lbl">Limits ({e(tally)})</div><ul id="verdict-limits">{items}</ul>'
                  f'<p class="note">Fail only beyond the uncertainty: ± {k:g} standard uncertainties.</p>')
    else:
        limits = ('<p class="note" id="verdict-limits">No acceptance limits configured ([limits] in the daemon\'s '
                  "configuration): no pass/fail verdict.</p>")
    figs = [f"{gname} {fmt(g, 1)} µm"] if g is not None else []
    for key, name in (("G_ccw_um", "G CCW"), ("G_cw_um", "G CW"), ("H_um", "H")):
        if num(iso.get(key)) is not None and name != gname:
            figs.append(f"{name} {fmt(iso.get(key), 1)} µm")
    ranking = [r for r in machine_ranking(result) if r.get("significant")]
    most = []
    for r in ranking[:3]:
        name = str(r["pattern"])
        most.append(f"<li><b>{e(pattern_label(name, axes))}</b>: {e(finding_words(name, result, axes))} "
                    f"<span class='note'>({e(share_text(r.get('machine_share_pct')))} of the machine's error)</span>"
                    "</li>")
    alpha = num((result.get("fit") or {}).get("significance")) or 0.05
    if most:
        more = len(ranking) - 3
        most_html = f'<ol id="verdict-most">{"".join(most)}</ol>' + (
            f'<p class="note">{more} more in the findings.</p>' if more > 0 else "")
    else:
        most_html = ('<p id="verdict-most">No machine error pattern stands out from the noise '
                     f'<span class="note">(none significant at p &lt; {alpha:g})</span>.</p>')
    todo = [a for a in advice_lines(result, axes) if a["kind"] != "setup"]
    todo_html = ("".join(f"<li>{e(a['text'])}</li>" for a in todo[:3]) if todo else
                 "<li>Nothing to adjust on the machine.</li>")
    setup = setup_words(result)
    setup_html = (f'<p class="note setup">Set-up, not the machine (removed from the plots, figures and shares): '
                  f'{e("; ".join(setup))}.</p>') if setup else ""
    prov = ('<p class="note setup"><b>Provisional timing:</b> the feed was not measured; angles assume the '
            "programmed feed.</p>") if (result.get("timing") or {}).get("provisional") else ""
    no_curves = "" if curves else '<p class="note setup">No curves in the data: plots omitted.</p>'
    warn = "".join(f'<p class="note warning setup"><b>Warning:</b> {e(w)}</p>'
                   for w in result.get("warnings") or [] if isinstance(w, str))
    colour = STATUS_COLOURS.get(status, STATUS_COLOURS["none"])
    return (
        f'<div class="verdict {e(status)}" id="verdict" data-status="{e(status)}" data-colour="{colour}">'
        f'<div class="head"><span class="badge" id="verdict-status">{e(vs["word"])}</span>'
        f'<span class="headline" id="verdict-headline">{e(vs["headline"])}</span></div>'
        f'<div><div class="lbl">Circularity</div><div id="verdict-g"><b>{e(" · ".join(figs) or MISSING)}</b></div>'
        f'{limits}</div>'
        f'<div><div class="lbl">What matters most</div>{most_html}'
        f'<div class="lbl">What to do</div><ul id="verdict-todo">{todo_html}</ul></div>'
        f"{setup_html}{prov}{no_curves}{warn}</div>"
    )


def metadata(result: Mapping[str, Any], meta: Mapping[str, Any]) -> str:
    """Who tested, with which bar, at what temperatures, and the notes (the ``[report]`` configuration or the
    command line)."""

    def temp(key: str) -> str:
        v = num(meta.get(key))
        return f"{v:.1f} °C" if v is not None else MISSING

    items = [
        ("Operator", str(meta.get("operator") or MISSING)),
        ("Ball-bar serial", str(meta.get("bar_serial") or MISSING)),
        ("Bar calibrated", str(meta.get("bar_calibrated") or MISSING)),
        ("Machine temperature", temp("machine_temperature_c")),
        ("Air temperature", temp("air_temperature_c")),
        ("Controller", str((result.get("machine") or {}).get("controller") or MISSING)),
    ]
    notes = str(meta.get("notes") or "")
    return kv(items) + (f'<p id="report-notes"><b>Notes:</b> {e(notes)}</p>' if notes else "")


def sign_off(meta: Mapping[str, Any]) -> str:
    roles = [str(r) for r in meta.get("sign_off") or ["Tested by", "Approved by"] if str(r).strip()]
    operator = str(meta.get("operator") or "")
    boxes = "".join(
        f"<div>{e(role)}{': <b>' + e(operator) + '</b>' if i == 0 and operator else ''}<br>Date, signature</div>"
        for i, role in enumerate(roles))
    return f'<div class="signoff" id="signoff">{boxes}</div>'


def conditions(result: Mapping[str, Any]) -> str:
    plan = result.get("plan") or {}
    tm = result.get("timing") or {}
    samples = result.get("samples") or {}
    iso = result.get("iso230_4") or {}
    cond = iso.get("conditions") or {}
    a1, a2 = plane_axes(plan)
    feed_m = num(tm.get("measured_feed_mm_min"))
    feed_p = num(plan.get("feed_mm_min"))
    ratio = f" ({(feed_m / feed_p - 1) * 100:+.2f} %)" if feed_m is not None and feed_p else ""
    dirs = {"both": "CCW then CW", "ccw": "CCW only", "cw": "CW only"}.get(str(plan.get("directions")),
                                                                          str(plan.get("directions", MISSING)))
    sample_hz = num(samples.get("sample_hz")) or num(plan.get("sample_hz"))
    items = [
        ("Plane", f"{plan.get('plane', MISSING)} ({a1}, {a2})"),
        ("Radius", f"{fmt(plan.get('radius_mm'), 3)} mm"),
        ("Feed, programmed", f"{fmt(feed_p, 1)} mm/min"),
        ("Feed, measured", f"{fmt(feed_m, 1)} mm/min{ratio}"),
        ("Data arc", f"{fmt(plan.get('data_arc_deg'), 1)}°"),
        ("Start angle", f"{fmt(plan.get('start_deg'), 1)}°"),
        ("Overshoot", f"{fmt(plan.get('overshoot_deg'), 1)}°"),
        ("Directions", dirs),
        ("Sample rate", f"{fmt(sample_hz, 1)} Hz"),
        ("Samples used", f"{samples.get('in_data_arcs', MISSING)} of {samples.get('in_test', MISSING)}"),
        ("Feed-in", f"{fmt(plan.get('feed_in_mm'), 2)} mm, dwell {fmt(plan.get('dwell_s'), 2)} s"),
    ]
    removal = cond.get("centre_removal")
    body = kv(items)
    if removal:
        body += f'<p class="note">Centre removal: {e(prose(removal))}.</p>'
    return body


# --------------------------------------------------------------------------- the detail


def findings(result: Mapping[str, Any]) -> str:
    """The machine's patterns ranked by their share of the machine's error; the set-up apart; the statistics
    (F, p, the field names) folded away for who wants them."""
    axes = plane_axes(result.get("plan") or {})
    params: Mapping[str, Any] = result.get("parameters") or {}
    ranking = machine_ranking(result)
    sig = [r for r in ranking if r.get("significant")]
    rows = []
    for i, r in enumerate(sig, 1):
        name = str(r["pattern"])
        keys = [k for m in r["members"] for k in LIBRARY_FIELDS.get(m, ()) if k in params]
        vals = []
        for k in keys:
            p = params.get(k) or {}
            if num(p.get("value")) is None:
                continue
            fl = field_label(k, axes)
            if name.startswith("reversal_spikes_"):
                fl = pattern_label(k[:-3], axes).split(" ", 2)[-1]
            vals.append((f'<span class="note">{e(fl)}</span> ' if fl else "")
                        + e(value_text(p.get("value"), p.get("stderr"), unit=str(p.get("unit") or "")))
                        + " " + e(unit_text(p.get("unit"))))
        share = num(r.get("machine_share_pct")) or 0.0
        rows.append(
            f'<tr class="sig" data-pattern="{e(name)}"><td class="rank">{i}</td>'
            f'<td class="pat">{e(pattern_label(name, axes))}</td>'
            f'<td class="num">{"<br>".join(vals) or MISSING}</td>'
            f'<td class="num"><span class="share" style="width:{max(share * 0.6, 1):.0f}px"></span>'
            f"{e(share_text(share))}</td></tr>"
        )
    body = "".join(rows) or ('<tr class="nsig"><td></td><td colspan="3">No machine error pattern is significant.'
                            "</td></tr>")
    quiet = [pattern_label(str(r["pattern"]), axes) for r in ranking if not r.get("significant")]
    quiet_html = (f'<p class="note" id="findings-quiet">Not significant (within the noise, or too small to count): '
                  f'{e(", ".join(quiet))}.</p>') if quiet else ""
    setup_rows = []
    for r in result.get("ranking") or []:
        if isinstance(r, Mapping) and pattern_kind(str(r.get("pattern"))) == "setup":
            name = str(r.get("pattern"))
            vals = [f"{field_label(k, axes) + ' ' if field_label(k, axes) else ''}"
                    f"{value_text(params[k].get('value'), params[k].get('stderr'), unit='um')} µm"
                    for k in LIBRARY_FIELDS.get(name, ()) if k in params and num(params[k].get("value")) is not None]
            setup_rows.append(f"<li>{e(pattern_label(name, axes))}: {e(', '.join(vals) or MISSING)}</li>")
    setup_html = (f'<h3>Set-up (removed before the machine\'s figures; not a machine error)</h3>'
                  f'<ul id="findings-setup">{"".join(setup_rows)}</ul>') if setup_rows else ""
    alpha = num((result.get("fit") or {}).get("significance")) or 0.05
    method = (result.get("fit") or {}).get("uncertainty_method")
    return (
        '<table id="findings"><thead><tr><th class="num">#</th><th>Machine error</th><th class="num">Value ± SE</th>'
        '<th class="num">Share of the machine\'s error</th></tr></thead>'
        f"<tbody>{body}</tbody></table>{quiet_html}{setup_html}"
        "<details><summary>Statistics of every pattern (F-test, p-value, result fields)</summary>"
        f"{statistics(result)}"
        f'<p class="caption">Ranked by the extra sum of squares. Shares are of the machine\'s explained error, the '
        f"set-up terms left out (the result's <code>share_pct</code> counts them too). Significant: "
        f"{e(rule_words(result, alpha))}. SE: standard error"
        + (f" ({e(prose(method))})" if method else "") + ".</p></details>"
    )


def _unit(p: Mapping[str, Any]) -> str:
    return str(p.get("unit") or "")


def statistics(result: Mapping[str, Any]) -> str:
    """Every ranked pattern with its field names, share of all the explained error, F and p; then the parameters
    that were not fitted, with the reason."""
    axes = plane_axes(result.get("plan") or {})
    params: Mapping[str, Any] = result.get("parameters") or {}
    rows = []
    shown: set[str] = set()
    for i, r in enumerate([r for r in result.get("ranking") or [] if isinstance(r, Mapping)], 1):
        name = str(r.get("pattern"))
        keys = [k for k in LIBRARY_FIELDS.get(name, ()) if k in params]
        shown.update(keys)
        why = r.get("significance_reason")
        sig = bool(r.get("significant"))
        verdict_text = "yes" if sig else ("no" if not why else significance_words(str(why)))
        vals = "<br>".join(f"<code>{e(k)}</code> "
                           f"{e(value_text(params[k].get('value'), params[k].get('stderr'), unit=_unit(params[k])))}"
                           for k in keys)
        rows.append(
            f'<tr class="{"sig" if sig else "nsig"}" data-stat="{e(name)}"><td class="rank">{i}</td>'
            f'<td class="pat">{e(pattern_label(name, axes))}</td><td>{vals or MISSING}</td>'
            f'<td class="num">{e(fmt(r.get("share_pct"), 2))}</td><td class="num">{e(f_text(r.get("F")))}</td>'
            f'<td class="num">{e(p_text(r.get("p_value")))}</td><td>{e(verdict_text)}</td></tr>'
        )
    absent: dict[str, list[str]] = {}
    for k, p in params.items():
        if k in shown or not isinstance(p, Mapping) or num(p.get("value")) is not None:
            continue
        absent.setdefault(str(p.get("reason") or "no value"), []).append(k)
    for reason, keys in absent.items():
        rows.append(f'<tr class="absent"><td class="rank"></td><td class="pat">{e(", ".join(keys))}</td>'
                    f'<td colspan="5">not fitted: {e(prose(reason))}</td></tr>')
    return ('<div class="wide"><table id="statistics"><thead><tr><th class="num">#</th><th>Pattern</th>'
            '<th>Field, value ± SE</th><th class="num">% of all</th><th class="num">F</th><th class="num">p</th>'
            f"<th>Significant</th></tr></thead><tbody>{''.join(rows)}</tbody></table></div>")


def iso(result: Mapping[str, Any]) -> str:
    iso = result.get("iso230_4")
    if not isinstance(iso, Mapping) or not iso:
        return '<p class="note" id="iso-missing">No ISO 230-4 figures in this result.</p>'
    cols = [("G_ccw_um", "G CCW"), ("G_cw_um", "G CW"), ("G_b_um", "G(b)"), ("H_um", "H"),
            ("F_max_um", "F max"), ("F_min_um", "F min")]
    head = "".join(f"<th>{e(n)} (µm)</th>" for _, n in cols)
    rms = num(result.get("residual_rms_um"))
    u = math.sqrt(2.0) * rms if rms is not None else None  # the verdict's uncertainty of G and H (monitor.py)
    cells = "".join(
        f'<td id="iso-{k}"{" class=gb" if k == "G_b_um" else ""}>'
        f'{e(measured(iso.get(k), u, "um", shown=0, with_unit=False))}</td>' for k, _ in cols
    )
    cond = iso.get("conditions") or {}
    a1, a2 = plane_axes(cond or (result.get("plan") or {}))
    items = [
        ("Standard", str(cond.get("standard", "ISO 230-4"))),
        ("Plane", f"{cond.get('plane', MISSING)} ({a1}, {a2})"),
        ("Radius", f"{fmt(cond.get('radius_mm'), 3)} mm"),
        ("Feed", f"{fmt(cond.get('feed_mm_min'), 1)} mm/min (measured {fmt(cond.get('measured_feed_mm_min'), 1)})"),
        ("Data arc", f"{fmt(cond.get('data_arc_deg'), 1)}° from {fmt(cond.get('start_deg'), 1)}°"),
        ("Directions", str(cond.get("directions", MISSING))),
        ("Sample rate", f"{fmt(cond.get('sample_hz'), 1)} Hz"),
    ]
    removal = cond.get("centre_removal")
    note = f"Centre removal: {prose(removal)}. " if removal else ""
    return (
        f'<div class="wide"><table class="iso" id="iso"><thead><tr>{head}</tr></thead><tbody><tr>{cells}</tr></tbody>'
        f'</table></div><h3>Test conditions of these figures</h3>{kv(items)}'
        f'<p class="note">{e(note)}F needs a calibrated bar length.</p>'
    )


def standards(result: Mapping[str, Any]) -> str:
    """The other standards' figures ([analysis] standards, ``--standard``), each with what it computes, where it
    differs from ISO 230-4 and what was assumed of its text."""
    from ballbar.analysis.standards import FIGURES

    parts = []
    for sid, body in (result.get("standards") or {}).items():
        if not isinstance(body, Mapping):
            continue
        cols = FIGURES.get(str(sid), ())
        head = "".join(f"<th>{e(n)} (µm)</th>" for _, n in cols)
        cells = "".join(f'<td id="std-{e(sid)}-{e(k)}">{e(fmt(body.get(k), 2))}</td>' for k, _ in cols)
        notes = [("What it computes", str(body.get("computes") or MISSING)),
                 ("Where it differs from ISO 230-4", str(body.get("differs_from_iso230_4") or MISSING)),
                 ("Centre removal", str(body.get("centre_removal") or MISSING))]
        if body.get("assumption"):
            notes.append(("Assumed", str(body["assumption"])))
        parts.append(f'<h3 id="std-{e(sid)}">{e(body.get("standard") or sid)}</h3>'
                     f'<div class="wide"><table class="iso"><thead><tr>{head}</tr></thead><tbody><tr>{cells}</tr>'
                     f"</tbody></table></div>{kv(notes)}")
    return "".join(parts) or '<p class="note">No other standard chosen.</p>'


def advice(result: Mapping[str, Any]) -> str:
    axes = plane_axes(result.get("plan") or {})
    lines = advice_lines(result, axes)
    if not lines:
        return '<p>Nothing significant to adjust.</p>'
    items = []
    for a in lines:
        kind = a["kind"]
        pill = (f'<span class="pill {"setup" if kind == "setup" else "kind"}">'
                f'{"set-up" if kind == "setup" else e(kind)}</span>')
        cp = a.get("controller_parameter")
        cp_html = f' <span class="note">Controller: <code>{e(cp)}</code></span>' if cp else ""
        items.append(f"<li>{pill}{e(a['text'])}{cp_html}</li>")
    ctl = (result.get("machine") or {}).get("controller")
    note = ""
    if not ctl or ctl == "generic":
        note = ('<p class="note">Controller parameter names are given when the machine\'s controller is configured '
                "(FANUC, SINUMERIK, HEIDENHAIN).</p>")
    return f'<ul class="advice" id="advice">{"".join(items)}</ul>{note}'


def noise(result: Mapping[str, Any]) -> str:
    nz = result.get("noise")
    if not isinstance(nz, Mapping) or not nz:
        return '<p class="note">No noise findings in this result.</p>'

    def yn(v: Any) -> str:
        return '<span class="pill yes">significant</span>' if v else '<span class="pill no">not significant</span>'

    peak = ""
    if num(nz.get("vibration_peak_hz")) is not None:
        line = num(nz.get("vibration_peak_um"))
        peak = (f"strongest line {fmt(line, 3)} µm rms " if line is not None else "") + (
            f"at {fmt(nz.get('vibration_peak_cpr'), 0)} cycles/rev ({fmt(nz.get('vibration_peak_hz'), 1)} Hz)")
    axes = plane_axes(result.get("plan") or {})
    rows = [
        f"<tr><td>Vibration (residual above {e(fmt(nz.get('vibration_cutoff_cpr'), 0))} cycles/rev)</td>"
        f'<td class="num">{e(fmt(nz.get("vibration_um"), 3))} µm rms</td><td>{yn(nz.get("vibration_significant"))}'
        f"</td><td>{e(peak)}</td></tr>",
    ]
    for xy, ax in (("x", axes[0]), ("y", axes[1])):
        rows.append(
            f'<tr><td>Stick-slip near {e(ax)} reversals</td><td class="num">'
            f"{e(fmt(nz.get(f'stick_slip_{xy}_um'), 3))} µm</td>"
            f"<td>{yn(nz.get(f'stick_slip_{xy}_significant'))}</td><td></td></tr>"
        )
    method = nz.get("method")
    return ('<table id="noise"><thead><tr><th>Finding</th><th class="num">Value</th><th>Verdict</th><th>Detail</th>'
            f"</tr></thead><tbody>{''.join(rows)}</tbody></table>"
            + (f'<p class="caption">Method: {e(prose(method))}.</p>' if method else ""))


def _lost_motion_words(fit: Mapping[str, Any], axes: Sequence[str]) -> str:
    """Each axis' lost-motion model and where its table reverses, in words."""
    lm = fit.get("lost_motion")
    if not isinstance(lm, Mapping):
        return str(fit.get("lost_motion_model") or MISSING)
    parts = []
    for key, name in zip(("x", "y"), axes, strict=False):
        d = lm.get(key) or {}
        parts.append(f"{name}: {d.get('description') or d.get('model') or MISSING}; friction from "
                     f"{fmt(d.get('onset_deg'), 3)}° after the reversal point")
    return " — ".join(parts)


def diagnostics(result: Mapping[str, Any]) -> str:
    tm = result.get("timing") or {}
    fit = result.get("fit") or {}
    take = tm.get("backlash_takeup_deg") or {}
    axes = plane_axes(result.get("plan") or {})
    lag_se, lag_s = num(tm.get("lag_stderr_s")), num(tm.get("lag_s"))
    lag = (f"{value_text(lag_s * 1000, lag_se * 1000 if lag_se is not None else None, unit='ms')} ms "
           f"({fmt(tm.get('lag_deg'), 3)}°)") if lag_s is not None else "not measured"
    timing = [
        ("Measured feed", f"{fmt(tm.get('measured_feed_mm_min'), 2)} mm/min (ratio {fmt(tm.get('feed_ratio'), 5)})"),
        ("Arc-start lag", lag),
        ("Loop lag", f"{fmt(tm.get('loop_lag_ms'), 2)} ms"),
        ("Loop-lag source", prose(tm.get("loop_lag_source") or MISSING)),
        ("Spike width", f"{fmt(tm.get('spike_width_deg'), 2)}°" + (
            f" ± {fmt(tm.get('spike_width_stderr_deg'), 2)}°" if tm.get("spike_width_stderr_deg") else "")),
        ("Backlash take-up", f"{axes[0]} {fmt(take.get('x'), 2)}°, {axes[1]} {fmt(take.get('y'), 2)}°"
         if take else MISSING),
        ("Data arcs' shift", ", ".join(f"{k.upper()} {fmt((v.get('shift_s') or 0.0) * 1000, 2)} ms"
                                       for k, v in (tm.get("data_arcs") or {}).items()) or MISSING),
        ("Feed-in / out", f"{tm.get('feed_in_method', MISSING)} at {fmt(tm.get('feed_in_s'), 3)} s / "
         f"{fmt(tm.get('feed_out_s'), 3)} s"),
        ("Timing method", prose(tm.get("method") or MISSING)),
    ]
    fits = [
        ("Residual RMS", f"{fmt(result.get('residual_rms_um'), 3)} µm"),
        ("Sigma", f"{fmt(fit.get('sigma_um'), 3)} µm"),
        ("Lag-1 autocorrelation", fmt(fit.get("residual_lag1_autocorrelation"), 3)),
        ("Variance inflation", fmt(fit.get("variance_inflation"), 3)),
        ("Condition number", fmt(fit.get("condition_number"), 1)),
        ("Samples / parameters", f"{fit.get('n_samples', MISSING)} / {fit.get('n_parameters', MISSING)} "
         f"(dof {fit.get('dof', MISSING)})"),
        ("Servo model", f"{fit.get('servo_model', MISSING)}"
         + (f" — {fit['servo_model_note']}" if fit.get("servo_model_note") else "")),
        ("Lost-motion model", _lost_motion_words(fit, axes)),
    ]

    def table(rows: Sequence[tuple[str, str]], tid: str) -> str:
        return (f'<table id="{tid}"><tbody>' + "".join(
            f'<tr><td class="note" style="width:38%">{e(k)}</td><td>{e(v)}</td></tr>' for k, v in rows)
            + "</tbody></table>")

    return (f'<div class="cols"><div><h3>Timing</h3>{table(timing, "diag-timing")}</div>'
            f'<div><h3>Fit</h3>{table(fits, "diag-fit")}</div></div>')


def history_of(data: ReportData) -> list[Mapping[str, Any]]:
    return [h for h in data.history or [] if isinstance(h, Mapping)]


def trend(data: ReportData, qs: Sequence[Any], svg: str | None, caption: str, forecasts: Sequence[str]) -> str:
    """The trend section: the plot and a table of the key figures per test, or why there is none."""
    from .report_plots import trend_value

    history = history_of(data)
    note = f'<p class="note">{e(data.history_note)}</p>' if data.history_note else ""
    if not history:
        return f'<p id="trend-none">No earlier comparable test of this machine: no trend yet.</p>{note}'
    tests = [*history, data.result]
    head = "".join(f'<th class="num">{e(q.label)} <br><span class="u">({e(q.unit)})</span></th>' for q in qs)
    this = ' <span class="pill kind">this test</span>'
    rows = []
    for i, r in enumerate(tests):
        cur = i == len(tests) - 1
        cells = []
        for q in qs:
            v, s, sig = trend_value(r, q)
            text = MISSING if v is None else value_text(v, s, unit=q.unit, shown=0)
            cells.append(f'<td class="num">{"<b>" + e(text) + "</b>" if sig and q.key != "G" else e(text)}</td>')
        tid = str(r.get("test_id") or f"test {r.get('test_index', i + 1)}")
        rows.append(
            f'<tr class="{"sig" if cur else "hist"}"><td class="rank">{i + 1}</td><td class="tid">{e(tid)}'
            f"{this if cur else ''}</td><td class=\"date\">{e(time_text(r.get('t_wall')))}</td>{''.join(cells)}</tr>"
        )
    figure = f'<figure class="trend">{svg}</figure><p class="caption">{e(caption)}</p>' if svg else ""
    fc = "".join(f"<li>{e(f)}</li>" for f in forecasts)
    fc_html = f'<h3>Forecast</h3><ul id="trend-forecast">{fc}</ul>' if fc else ""
    return (f"{note}{fc_html}{figure}"
            f'<div class="wide"><table id="trend-table" class="trend"><thead><tr><th class="num">#</th><th>Test</th>'
            f"<th>Date</th>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table></div>"
            '<p class="caption">Bold: significant in that test.</p>')


def generated_text() -> str:
    return dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")


__all__ = ["CSS", "Doc", "advice", "conditions", "diagnostics", "findings", "iso", "metadata", "noise", "sign_off",
           "trend", "verdict"]
