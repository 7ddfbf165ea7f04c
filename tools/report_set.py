"""``ballbar report DIR --set NAME``: a test set's report, the set's verdict first, then each plan's test.

:class:`SetReportData` holds the set result (:mod:`ballbar.analysis.sets`) and
each member test's :class:`~.report.ReportData` (its curves and its plan's
earlier tests); :func:`render_set` writes one self-contained HTML file as
:func:`~.report_render.render` does: first the set's verdict in a word and a
colour (each plan's verdict, the set's checks, the machine's figures, what to
do, worst plan first), then the machine's axes (lost
motion, squareness, relative scale and servo lag with their closure), the
volumetric figures and every check, and then each plan's test with all the
sections of a test's report.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ballbar.analysis.numbers import measured
from ballbar.analysis.sets import AXES, PAIRS, set_words

from . import report_html as H
from .report import ReportData, _unique, select_history


@dataclass
class SetReportData:
    """A set's result and, by plan, each member test's report data."""

    result: dict[str, Any]
    plans: dict[str, ReportData]
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)


def from_set_records(records: str, name: str) -> SetReportData:
    """Set ``name`` from a directory of the daemon's records: its members analysed again from their samples (with
    their curves), each with its plan's earlier tests, and combined as the daemon does."""
    from ballbar.daemon.setrecords import combined, recorded_set

    rs = recorded_set(records, name, curves=True)
    result = combined(rs)
    candidates = _unique(rs.index.results())
    plans = {}
    for p, r in rs.results.items():
        curves = r.pop("curves")
        r.pop("source", None)
        same = [c for c in candidates if (c.get("plan") or {}).get("name") in (None, p)]
        history, note = select_history(r, same)
        plans[p] = ReportData(r, curves, history, note, source=f"{os.path.abspath(records)} test {r.get('test_id')}")
    meta = rs.config.get("report")
    meta = {k: v for k, v in meta.items() if v not in (None, "")} if isinstance(meta, dict) else {}
    return SetReportData(result, plans, source=f"{os.path.abspath(records)} set {name}", meta=meta)


# --------------------------------------------------------------------------- the set's sections


FIGURE_NAMES = {"G_b_um": "G(b)", "G_um": "G", "G_ccw_um": "G CCW", "G_cw_um": "G CW"}


def _fig(f: Mapping[str, Any] | None, nd: int = 2, signed: bool = True) -> str:
    """A set figure with its standard uncertainty by the one rule (:mod:`ballbar.analysis.numbers`); ``nd``:
    the decimals of a figure without a unit."""
    if not isinstance(f, Mapping) or H.num(f.get("value")) is None:
        return H.MISSING
    unit = str(f.get("unit") or "")
    if not unit and H.num(f.get("stderr")) is None:
        return H.fmt(f["value"], nd, signed=signed)
    return measured(f["value"], f.get("stderr"), unit, signed=signed, with_unit=False)


def _trust(f: Mapping[str, Any] | None) -> str:
    if not isinstance(f, Mapping):
        return ""
    if f.get("trusted", True):
        return ""
    why = "; ".join(str(r) for r in f.get("reasons") or []) or "not trusted"
    return f'<span class="st warning">UNTRUSTED</span> <span class="note">{H.e(why)}</span>'


def set_todo(s: Mapping[str, Any], results: Mapping[str, Mapping[str, Any]]) -> str:
    """What to do, worst plan first: each failing or warning plan's first advice on the machine (a link to the
    rest), then a check of the set that failed."""
    rank = {"fail": 0, "warning": 1}
    members = sorted((m for m in s.get("tests") or [] if m.get("verdict") in rank),
                     key=lambda m: rank[str(m.get("verdict"))])
    items = []
    for m in members:
        p = str(m.get("plan"))
        r = results.get(p) or {}
        todo = [a for a in H.advice_lines(r, H.plane_axes(r.get("plan") or {})) if a["kind"] != "setup"]
        first = todo[0]["text"] if todo else "see its findings"
        items.append(f'<li><b>{H.e(p)}</b> ({H.e(str(m.get("verdict")))}): {H.e(first)} '
                     f'<a href="#sec-{H.e(p)}-advice">plan {H.e(p)}\'s advice</a></li>')
    for c in s.get("checks") or []:
        if c.get("status") == "failed":
            items.append(f"<li>{H.e(c.get('message'))}: run again the tests of the planes that disagree, from the "
                         "same set-up, before adjusting the machine</li>")
    return "".join(items) or "<li>Nothing to adjust on the machine.</li>"


def set_verdict(s: Mapping[str, Any], results: Mapping[str, Mapping[str, Any]] | None = None) -> str:
    """Is the machine fine: the set's verdict in a word and a colour, each plan's, the checks, what to do
    (``results``: each plan's test result, for its advice)."""
    w = set_words(s)
    status = w["status"]
    plans = "".join(
        f'<li><span class="st {H.e(st)}">{H.e(str(st).replace("_", " ").upper())}</span>'
        f'<b>{H.e(p)}</b> ({H.e(plane)} plane)</li>' for p, plane, st in w["plans"])
    checks = s.get("checks") or []
    failed = [c for c in checks if c.get("status") == "failed"]
    check_items = "".join(f'<li><span class="st fail">FAILED</span>{H.e(c.get("message"))}</li>' for c in failed) or (
        f'<li><span class="st pass">PASSED</span>all {len(checks)} checks of the set: each axis seen twice agrees, '
        "each loop closes</li>")
    problems = "".join(f'<p class="note warning setup"><b>Not trusted:</b> {H.e(p)}</p>' for p in w["problems"])
    lm = s.get("lost_motion") or {}
    most = "".join(f"<li>Lost motion {H.e(a)} <b>{H.e(_fig(lm.get(a)))} µm</b></li>" for a in AXES)
    sq = s.get("squareness") or {}
    most += "<li>Squareness " + ", ".join(f"{H.e(p)} <b>{H.e(_fig(sq.get(p), 1))} µrad</b>" for p in PAIRS) + "</li>"
    vol = s.get("volumetric") or {}
    lcd, sph = vol.get("largest_circular_deviation") or {}, vol.get("geometric_sphericity") or {}
    most += (f"<li>Largest circular deviation <b>{H.e(_fig(lcd, 1, signed=False))} µm</b> "
             f"({H.e(lcd.get('plan') or H.MISSING)}); geometric sphericity <b>{H.e(_fig(sph, 2, signed=False))} µm"
             "</b></li>")
    colour = H.STATUS_COLOURS.get(status, H.STATUS_COLOURS["none"])
    return (
        f'<div class="verdict {H.e(status)}" id="verdict" data-status="{H.e(status)}" data-colour="{colour}">'
        f'<div class="head"><span class="badge" id="verdict-status">{H.e(w["word"])}</span>'
        f'<span class="headline" id="verdict-headline">{H.e(w["headline"])}</span></div>'
        f'<div><div class="lbl">Each plan\'s test</div><ul id="verdict-plans">{plans}</ul>'
        f'<div class="lbl">The set\'s checks</div><ul id="verdict-checks">{check_items}</ul></div>'
        f'<div><div class="lbl">The machine</div><ul id="verdict-most">{most}</ul>'
        f'<div class="lbl">What to do</div><ul id="verdict-todo">{set_todo(s, results or {})}</ul></div>'
        f"{problems}</div>"
    )


def _observations(f: Mapping[str, Any]) -> str:
    obs = f.get("observations") or []
    return "; ".join(
        f"{o.get('plan')} ({o.get('plane')}) {_fig({'unit': f.get('unit'), **o})}"
        + ("" if o.get("used") else f" (left out: {o.get('reason')})")
        for o in obs) or H.MISSING


def axes_table(s: Mapping[str, Any]) -> str:
    """The machine's axes: lost motion from every plane that sees each, squareness per pair, relative scale and
    servo lag per pair (with the loop's closure) and per axis."""
    lm, sq = s.get("lost_motion") or {}, s.get("squareness") or {}
    rows = "".join(f'<tr id="axis-{H.e(a)}"><td>{H.e(a)}</td><td class="num">{H.e(_fig(lm.get(a)))}</td>'
                   f'<td>{H.e(_observations(lm.get(a) or {}))} {_trust(lm.get(a))}</td></tr>' for a in AXES)
    lost = (f'<div class="wide"><table id="set-lost-motion"><thead><tr><th>axis</th><th>lost motion (µm)</th>'
            f"<th>seen by</th></tr></thead><tbody>{rows}</tbody></table></div>")
    rows = "".join(f'<tr id="pair-{H.e(p)}"><td>{H.e(p)}</td><td class="num">{H.e(_fig(sq.get(p), 2))}</td>'
                   f'<td>{H.e(_observations(sq.get(p) or {}))} {_trust(sq.get(p))}</td></tr>' for p in PAIRS)
    square = (f'<div class="wide"><table id="set-squareness"><thead><tr><th>pair</th><th>squareness (µrad)</th>'
              f"<th>seen by</th></tr></thead><tbody>{rows}</tbody></table></div>")
    loops = ""
    checks = {c.get("name"): c for c in s.get("checks") or []}
    for key, what, unit, nd in (("scale", "Relative scale", "ppm", 1), ("servo", "Servo lag mismatch", "ms", 4)):
        loop = s.get(key) or {}
        pairs = loop.get("pairs") or {}
        prow = "".join(
            f'<tr><td>{H.e(p)}</td><td class="num">{H.e(_fig(pairs.get(p), nd))}</td>'
            f'<td class="num">{H.e(_fig((pairs.get(p) or {}).get("adjusted"), nd))}</td>'
            f'<td>{_trust(pairs.get(p))}</td></tr>' for p in PAIRS)
        per_axis = loop.get("axes") or {}
        arow = "".join(f'<tr><td>{H.e(a)}</td><td class="num" colspan="2">{H.e(_fig(per_axis.get(a), nd))}'
                       f"</td><td>{_trust(per_axis.get(a))}</td></tr>" for a in AXES)
        c = checks.get(loop.get("closure")) or {}
        st = str(c.get("status", "not_checked"))
        css = {"passed": "pass", "failed": "fail"}.get(st, "none")
        loops += (
            f'<h3>{H.e(what)} ({H.e(unit)})</h3><div class="wide"><table id="set-{H.e(key)}"><thead><tr><th>pair</th>'
            f"<th>measured</th><th>closed</th><th></th></tr></thead><tbody>{prow}"
            f'<tr><th colspan="4">each axis against the mean of the three</th></tr>{arow}</tbody></table></div>'
            f'<p id="closure-{H.e(key)}"><span class="st {css}">{H.e(st.replace("_", " ").upper())}</span>'
            f"{H.e(c.get('message') or '')}</p>")
    conv = s.get("conventions") or {}
    return (lost + "<h3>Squareness</h3>" + square + loops
            + "<h3>Sign conventions</h3>" + H.kv([(str(k), str(v)) for k, v in conv.items()])
            + f'<p class="note">{H.e(s.get("method") or "")}</p>')


def volumetric(s: Mapping[str, Any]) -> str:
    vol = s.get("volumetric") or {}
    lcd, sph = vol.get("largest_circular_deviation") or {}, vol.get("geometric_sphericity") or {}
    interval = sph.get("interval")
    figure = FIGURE_NAMES.get(str(lcd.get("figure")), lcd.get("figure") or H.MISSING)
    items = [
        ("Largest circular deviation", f"{_fig(lcd, 2, signed=False)} µm ({figure} of plan "
                                       f"{lcd.get('plan') or H.MISSING}, test {lcd.get('test_id') or H.MISSING})"),
        ("Geometric sphericity", f"{_fig(sph, 2, signed=False)} µm" + (
            f", 95 % interval {interval[0]:.2f} … {interval[1]:.2f} µm" if isinstance(interval, list) else "")
         + f" over a sphere of R {H.fmt(sph.get('radius_mm'), 0)} mm"),
    ]
    why = [r for f in (lcd, sph) for r in f.get("reasons") or []]
    return H.kv(items) + "".join(f'<p class="note">{H.e(r)}</p>' for r in why) + (
        f'<p class="note">{H.e(vol.get("method") or "")}</p>')


def checks_table(s: Mapping[str, Any]) -> str:
    rows = []
    for c in s.get("checks") or []:
        st = str(c.get("status"))
        css = {"passed": "pass", "failed": "fail"}.get(st, "none")
        z = H.num(c.get("z"))
        rows.append(f'<tr><td><span class="st {css}">{H.e(st.replace("_", " ").upper())}</span></td>'
                    f"<td>{H.e(c.get('name'))}</td><td class=\"num\">{H.e(_fig(c, 4))} {H.e(c.get('unit'))}</td>"
                    f'<td class="num">{H.e(f"{z:.1f}" if z is not None else H.MISSING)}</td>'
                    f"<td>{H.e(c.get('message'))}</td></tr>")
    k = next((H.num(c.get("coverage_k")) for c in s.get("checks") or []), None) or 3.0
    return (f'<div class="wide"><table id="set-checks"><thead><tr><th>status</th><th>check</th><th>discrepancy</th>'
            f"<th>z</th><th>in words</th></tr></thead><tbody>{''.join(rows)}</tbody></table></div>"
            f'<p class="note">A check fails beyond {k:g} standard errors and above its minimum discrepancy.</p>')


def _prefixed(html: str, prefix: str) -> str:
    """Every id of a plan's sections (and what refers to it) prefixed: several tests in one document."""
    ids = set(re.findall(r'\bid="([^"]+)"', html))
    mapping = {i: f"{prefix}{i}" for i in ids if not i.startswith(prefix)}

    def ren(m: re.Match[str]) -> str:
        return m[1] + mapping.get(m[2], m[2]) + m[3]

    html = re.sub(r'(\bid=")([^"]+)(")', ren, html)
    html = re.sub(r"(url\(#)([^)]+)(\))", ren, html)
    return re.sub(r'(href="#)([^"]+)(")', ren, html)


def render_set(data: SetReportData, html_path: Path, *, png: bool = True) -> list[Path]:
    """Write the set's report to ``html_path`` (and every plan's plots as PNGs beside it when ``png``): the set's
    verdict first, then each plan's test (module docstring).  The paths written, the HTML first."""
    from .report_render import _version, report_sections, write_page

    html_path = Path(html_path)
    s = data.result
    name = (s.get("set") or {}).get("name", "?")
    machine_id = s.get("machine_id") or ""
    doc = H.Doc()
    doc.section("verdict", f"Verdict of set {name}", set_verdict(s, {p: rd.result for p, rd in data.plans.items()}))
    doc.section("axes", "The machine's axes", axes_table(s))
    doc.section("volumetric", "Volumetric figures", volumetric(s))
    doc.section("checks", "Checks of the set", checks_table(s))
    pngs: list[tuple[Path, bytes]] = []
    for p, rd in data.plans.items():
        if data.meta and not rd.meta:
            rd.meta = dict(data.meta)
        plan = rd.result.get("plan") or {}
        sections, plots = report_sections(rd, html_path, png, key=f"{p}-")
        pngs += plots
        for sid, heading, body in sections:
            doc.section(f"{p}-{sid}", f"Plan {p} ({plan.get('plane', '?')}): {heading}", _prefixed(body, f"{p}-"))
    doc.section("signoff", "Sign-off", H.sign_off(data.meta))
    members = s.get("tests") or []
    title = " — ".join(x for x in ("Ball-bar set report", str(machine_id), f"set {name}") if x)
    sub = [f"Machine <b>{H.e(machine_id)}</b>" if machine_id else "", f"Set <b>{H.e(name)}</b>",
           " · ".join(f"{H.e(m.get('plan'))} {H.e(m.get('plane'))} {H.e(m.get('test_id'))}" for m in members)]
    footer = (f'<footer><span>Source: {H.e(data.source or H.MISSING)}</span>'
              f"<span>ballbar {H.e(_version())} · set schema {H.e(s.get('schema_version', H.MISSING))}</span>"
              f"<span>Generated {H.e(H.generated_text())}</span></footer>")
    header = (f'<div><h1>Ball-bar set report</h1><div class="sub">{" · ".join(x for x in sub if x)}</div></div>'
              f'<div class="brand"><b>BALLBAR</b><br>Test set: {len(members)} plans<br>ISO 230-4 and the '
              "machine's axes</div>")
    return write_page(html_path, title, header, "\n".join(doc.parts) + footer, pngs)


__all__ = ["SetReportData", "from_set_records", "render_set"]
