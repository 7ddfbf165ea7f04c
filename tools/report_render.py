"""The ``ballbar report`` renderer: one self-contained HTML file an engineer can file.

:func:`render` turns a :class:`~ballbar.tools.report.ReportData` into one HTML
file with everything inline (CSS, the plots as SVG; no script, no external
URL: the report must open the same on an air-gapped shop-floor PC in ten
years as today) and, optionally, the plots as PNG files beside it for slides
and tickets (``<stem>-polar.png``, ``<stem>-deviation.png``, and
``<stem>-trend.png`` when there is history).

The report follows the order an engineer reads a ball-bar test in.  The first
half page answers the first question: the verdict against the limits in a word
and a colour, by how much, what matters most and what to do
(:func:`~ballbar.tools.report_html.verdict`); then the polar plot, the test
conditions with who tested and with which bar, the deviation against angle,
the ranked findings (the statistics folded away), ISO 230-4, the advice, the
trend with its limits and forecast, noise, how the fit was made, and the
sign-off.  The plots are :mod:`.report_plots`, the sections :mod:`.report_html`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ballbar.analysis.numbers import measured
from ballbar.daemon.output import write_atomic

from . import report_html as H
from .report import ReportData
from .report_plots import (
    COLOURS,
    DIRECTION_NAMES,
    MEASURED_POINTS,
    coverage_k,
    curves_of,
    deviation_figure,
    envelope_indices,
    g_of,
    plane_axes,
    polar_figure,
    polar_scale_um,
    style,
    svg,
    trend_caption,
    trend_figure,
    trend_quantities,
    um_text,
)
from .report_plots import png as png_bytes

if TYPE_CHECKING:
    from ballbar.protocol.messages import LimitEntry, Verdict

log = logging.getLogger(__name__)

__all__ = ["envelope_indices", "forecast_words", "polar_scale_um", "render"]

FORECAST_TESTS = 50  # the forecast's trend over the last tests at most (Theil-Sen and its bootstrap: all pairs)


def _version() -> str:
    try:
        return metadata.version("ballbar")
    except metadata.PackageNotFoundError:
        return "unknown"


def forecast_words(tests: Sequence[Mapping[str, Any]], axes: tuple[str, str]) -> list[str]:
    """Per limit of the newest test's verdict, when its trend crosses the limit (the daemon's forecast,
    :func:`ballbar.analysis.monitor.forecast`, over these tests), or why no date can be given."""
    from ballbar.analysis import monitor
    from ballbar.analysis.report import quantity_label, unit_text

    # the newest test is the report's own result: its verdict is attach_verdict's (typed), the others are records
    v: Verdict | None = tests[-1].get("verdict")
    if not v or not v["limits"]:
        return []
    groups: dict[str, list[LimitEntry]] = {}
    for en in v["limits"]:
        groups.setdefault(en["limit_name"], []).append(en)
    limits = tuple(monitor.Limit(name, es[0]["limit"], es[0]["warn_fraction"], tuple(x["name"] for x in es),
                                 es[0]["group"]) for name, es in groups.items())
    settings = monitor.MonitorSettings(limits=limits, coverage_k=v["coverage_k"],
                                       trend_tests=min(max(len(tests), 3), FORECAST_TESTS))
    history = [monitor.history_entry(r, monitor.evaluate(r, settings), str(r.get("t_wall")))
               for r in tests if r.get("t_wall")]
    out = []
    cond = monitor.conditions(tests[-1])
    for lim, name in settings.quantities():
        pts = monitor.points(history, name, cond, settings)
        f = monitor.forecast(pts, lim, name, settings)
        label = quantity_label(name, axes)
        unit = unit_text(next((en["unit"] for en in v["limits"] if en["name"] == name), ""))
        if crossing := f.get("crossing"):
            lo, hi = f.get("crossing_lo"), f.get("crossing_hi")
            span = f" ({100 * settings.confidence:g} %: {(lo or 'never')[:10]} .. {(hi or 'never')[:10]})"
            slope = f.get("slope_per_day") or 0.0
            when = crossing[:10]
            flat = "" if f.get("significant") else "; the slope is within its uncertainty"
            se = monitor.slope_stderr(f.get("slope_lo"), f.get("slope_hi"), settings.confidence)
            lim_t = measured(lim.bound, None, unit, with_unit=False)  # the quantity's limit, as the verdict shows it
            out.append(f"{label}: trend {measured(slope, se, unit + '/day', signed=True)}, reaches its limit "
                       f"{lim_t} {unit} about {when}{span}{flat}")
        else:
            out.append(f"{label}: no crossing date ({unit_text(f.get('reason') or 'the trend heads away from it')})")
    return out


def report_sections(data: ReportData, html_path: Path, png: bool, key: str = "",
                  ) -> tuple[list[tuple[str, str, str]], list[tuple[Path, bytes]]]:
    """A test's sections, ``(id, title, body)`` in reading order, and its plots as PNGs (when ``png``);
    ``key``: names the plots' files apart (several tests in one document; their ids are the caller's to
    prefix)."""
    result: Mapping[str, Any] = data.result or {}
    plan = result.get("plan") or {}
    axes = plane_axes(plan)
    curves = curves_of(data)
    stem = html_path.stem + (f"-{key.rstrip('-')}" if key else "")
    pngs: list[tuple[Path, bytes]] = []
    svgs: dict[str, str] = {}
    g, gname, _gkey = g_of(result)
    div = None
    if curves:
        with style("polar"):
            fig, div = polar_figure(curves, axes, f"{gname} {H.fmt(g, 1)} µm" if g is not None else "")
            svgs["polar"] = svg(fig, "polar", "Polar plot of the radial deviation, both directions")
            if png:
                pngs.append((html_path.with_name(f"{stem}-polar.png"), png_bytes(fig)))
        with style("deviation"):
            fig = deviation_figure(curves, axes)
            svgs["deviation"] = svg(fig, "deviation", "Radial deviation against angle")
            if png:
                pngs.append((html_path.with_name(f"{stem}-deviation.png"), png_bytes(fig)))
    history = H.history_of(data)
    tests = [*history, result]
    qs = trend_quantities(tests, axes) if history else []
    forecasts: list[str] = []
    if qs:
        with style("trend"):
            fig = trend_figure(tests, qs)
            svgs["trend"] = svg(fig, "trend", "Key figures of this machine's tests, test by test")
            if png:
                pngs.append((html_path.with_name(f"{stem}-trend.png"), png_bytes(fig)))
        forecasts = forecast_words(tests, axes)
    meta = data.meta or {}
    out: list[tuple[str, str, str]] = [("verdict", "Verdict", H.verdict(result, curves))]
    if curves:
        dirs = " and ".join(
            f'<span class="sw" style="background:{COLOURS[c.name]}"></span>{DIRECTION_NAMES[c.name]}' for c in curves)
        out.append(("polar", "Polar plot", (
            f'<figure class="polar">{svgs["polar"]}<figcaption class="caption">Radial deviation of {dirs}, '
            f"magnified about the reference circle: <b>{H.e(um_text(div or 1.0))} µm per division</b>, every point "
            "inside the outermost ring; dashed dark lines: the fitted model (legend under the plot). Set-up terms "
            f"(pivot offset, bar length) removed. Angles counter-clockwise from +{H.e(axes[0])}.</figcaption>"
            "</figure>")))
    out.append(("conditions", "Test conditions", H.metadata(result, meta) + H.conditions(result)))
    if curves:
        out.append(("deviation", "Deviation against angle", (
            f'<figure>{svgs["deviation"]}<figcaption class="caption">Measured deviation (solid) and fitted model '
            "(dashed) per direction, set-up terms removed; below, the residual (measured − model). Curves drawn "
            f"as a min/max envelope of at most {MEASURED_POINTS} points per direction: spikes are kept."
            "</figcaption></figure>")))
    out.append(("findings", "What the machine's error is made of", H.findings(result)))
    out.append(("iso230", "ISO 230-4 circular test figures", H.iso(result)))
    if result.get("standards"):
        out.append(("standards", "Other standards' circular test figures", H.standards(result)))
    out.append(("advice", "Advice", H.advice(result)))
    out.append(("trend", "Trend over this machine's tests",
                H.trend(data, qs, svgs.get("trend"), trend_caption(qs, coverage_k(result), axes), forecasts)))
    out.append(("noise", "Noise", H.noise(result)))
    out.append(("diagnostics", "Fit and timing diagnostics", H.diagnostics(result)))
    return out, pngs


def render(data: ReportData, html_path: Path, *, png: bool = True) -> list[Path]:
    """Write the report of ``data`` to ``html_path`` (and its plots as PNGs beside it when ``png``).

    Returns the paths written, the HTML first.  Every file is written through
    a temporary file and a rename, the HTML last, so a report on disk is
    always whole.
    """
    html_path = Path(html_path)
    result: Mapping[str, Any] = data.result or {}
    plan = result.get("plan") or {}
    sections, pngs = report_sections(data, html_path, png)
    machine_id = result.get("machine_id") or (result.get("machine") or {}).get("machine_id")
    test_id = result.get("test_id")
    when = H.time_text(result.get("t_wall")) if result.get("t_wall") else None
    title_bits = ["Ball-bar test report"]
    if machine_id:
        title_bits.append(str(machine_id))
    if test_id:
        title_bits.append(str(test_id))
    title = " — ".join(title_bits)
    sub = []
    if machine_id:
        sub.append(f"Machine <b>{H.e(machine_id)}</b>")
    if test_id:
        sub.append(f"Test <b>{H.e(test_id)}</b>")
    elif result.get("test_index") is not None:
        sub.append(f"Test #{H.e(result.get('test_index'))}")
    if when:
        sub.append(f"<b>{H.e(when)}</b>")
    sub.append(f"{H.e(plan.get('plane', '?'))} plane · R {H.e(H.fmt(plan.get('radius_mm'), 0))} mm · "
               f"F {H.e(H.fmt(plan.get('feed_mm_min'), 0))} mm/min")

    meta = data.meta or {}
    doc = H.Doc()
    for sid, heading, body in sections:
        doc.section(sid, heading, body)
    doc.section("signoff", "Sign-off", H.sign_off(meta))

    footer = (
        f'<footer><span>Source: {H.e(data.source or H.MISSING)}</span>'
        f"<span>ballbar {H.e(_version())} · result schema {H.e(result.get('schema_version', H.MISSING))}</span>"
        f"<span>Generated {H.e(H.generated_text())}</span></footer>"
    )
    header = (f'<div><h1>Ball-bar test report</h1><div class="sub">{" · ".join(sub)}</div></div>'
              '<div class="brand"><b>BALLBAR</b><br>Circular test, ISO 230-4<br>Suh &amp; Lee pattern fit</div>')
    return write_page(html_path, title, header, "\n".join(doc.parts) + footer, pngs)


def write_page(html_path: Path, title: str, header: str, body: str, pngs: list[tuple[Path, bytes]]) -> list[Path]:
    """The report's document around ``header`` and ``body``, written with its PNGs (each through a temporary
    file and a rename, the HTML last); the paths written, the HTML first."""
    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f'<meta name="generator" content="ballbar {H.e(_version())}">'
        f"<title>{H.e(title)}</title><style>{H.CSS}</style></head>\n<body>"
        f'<header class="top">{header}</header>\n{body}</body></html>\n'
    )
    written = []
    for path, blob in pngs:
        write_atomic(path, blob)
        written.append(path)
    write_atomic(html_path, page.encode("utf-8"))
    log.info("report written to %s (%d bytes, %d PNGs)", html_path, len(page.encode("utf-8")), len(written))
    return [html_path, *written]
