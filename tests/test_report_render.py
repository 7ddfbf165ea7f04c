"""The ``ballbar report`` renderer: a self-contained HTML report, its PNGs, and the page in a real browser.

The data is a real analysis: the physical simulator's test (servo mismatch,
centre offset, backlash, squareness, reversal spikes) at 250 Hz on a small
plan, analysed by the engine with its curves.  Earlier tests for the trend
are copies of that result with other ids, dates and values.

The browser test drives Debian's headless Chromium over the DevTools protocol
on a pipe (``tests/browser.py``, standard library only): it loads the report
from ``file://``, asks the page itself (title, SVG sizes, trace ids and
colours, the first findings row, the ISO table), records every network request
and console error, and takes a screenshot.  A control page with a request and
a console error proves those recorders really see them.  It is skipped when no
Chromium is installed, unless ``BALLBAR_REQUIRE_BROWSER=1`` (CI) makes that a
failure.
"""

from __future__ import annotations

import copy
import http.server
import io
import math
import os
import pickle
import re
import struct
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from browser import Chromium, find_chromium

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.plan import TestPlan
from ballbar.tools.report import ReportData
from ballbar.tools.report_render import envelope_indices, polar_scale_um, render
from ballbar.tools.simulator import MachineModel, simulate

PLAN = TestPlan(radius_mm=50.0, feed_mm_min=2000.0, overshoot_deg=20.0, dwell_s=0.2, sample_hz=250.0)
MACHINE = MachineModel(
    kv_x_per_s=30.0, kv_y_per_s=31.0, backlash_x_um=4.0, backlash_y_um=2.5, squareness_urad=20.0,
    centre_x_um=8.0, centre_y_um=-5.0, spike_x_um=2.0, noise_um=0.1,
)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
BROWSER_TIMEOUT_S = 30.0


def _analyse(plan: TestPlan, machine: MachineModel = MACHINE) -> tuple[dict[str, Any], dict[str, Any]]:
    sim = simulate(plan, machine)
    out = analyze_recording(sim.t_s, sim.length_mm, plan, curves=True)
    tests = [r for r in out if r.get("kind") == "test"]
    assert len(tests) == 1, out
    result = tests[0]
    curves = result.pop("curves")
    result.update(machine_id="mill-3", test_id="mill-3-20260301T081500Z", t_wall="2026-03-01T08:15:00Z")
    return result, curves


def _history(result: dict[str, Any], n: int = 2) -> list[dict[str, Any]]:
    """Earlier tests: the same result re-dated and shifted a little, oldest first."""
    out = []
    for i in range(n):
        h = copy.deepcopy(result)
        h["test_id"] = f"mill-3-2026020{i + 1}T080000Z"
        h["t_wall"] = f"2026-02-0{i + 1}T08:00:00Z"
        for p in h["parameters"].values():
            if p.get("value") is not None:
                p["value"] *= 0.8 + 0.1 * i
        h["iso230_4"]["G_b_um"] *= 0.9 + 0.05 * i
        out.append(h)
    return out


@pytest.fixture(scope="module")
def analysed() -> tuple[dict[str, Any], dict[str, Any]]:
    return _analyse(PLAN)


@pytest.fixture
def data(analysed: tuple[dict[str, Any], dict[str, Any]]) -> ReportData:
    result, curves = analysed
    result = copy.deepcopy(result)
    return ReportData(result=result, curves=curves, history=_history(result),
                      history_note="earlier tests of mill-3 with the same plan", source="simulated test")


def _png_size(blob: bytes) -> tuple[int, int]:
    """Width and height from a PNG's IHDR, after checking the signature and the chunk's CRC."""
    assert blob[:8] == PNG_SIGNATURE
    length, kind = struct.unpack(">I4s", blob[8:16])
    assert kind == b"IHDR" and length == 13
    body = blob[16:29]
    (crc,) = struct.unpack(">I", blob[29:33])
    assert zlib.crc32(kind + body) == crc, "IHDR CRC mismatch"
    w, h = struct.unpack(">II", body[:8])
    return w, h


def _pixels(blob: bytes) -> np.ndarray:
    from PIL import Image  # matplotlib's own dependency

    with Image.open(io.BytesIO(blob)) as im:
        return np.asarray(im.convert("RGB"))


# --------------------------------------------------------------------------- files, without a browser


def test_html_is_self_contained_and_pngs_are_valid(data: ReportData, tmp_path: Path) -> None:
    paths = render(data, tmp_path / "r.html")
    assert paths == [tmp_path / n for n in ("r.html", "r-polar.png", "r-deviation.png", "r-trend.png")]
    # the returned paths are all that was written: no temporary file left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in paths)
    text = paths[0].read_text(encoding="utf-8")
    assert text.startswith("<!DOCTYPE html>")
    refs = re.findall(r"""\b(?:src|href)\s*=\s*["']([^"']*)""", text, flags=re.I)
    assert all(r.startswith("#") for r in refs), refs  # only links inside the document
    assert not re.search(r"url\(\s*['\"]?(?!#)", text), "a CSS/SVG url() that is not a fragment"
    assert not re.search(r"<(script|link|img|iframe|object|embed)\b", text, flags=re.I)
    assert "@import" not in text
    assert text.count("<svg") == 3
    ids = re.findall(r'\bid="([^"]+)"', text)
    assert len(ids) == len(set(ids)), "duplicate ids across the inline SVGs"
    for p in paths[1:]:
        blob = p.read_bytes()
        w, h = _png_size(blob)
        assert w >= 600 and h >= 300, (p.name, w, h)
        px = _pixels(blob)  # the whole image decodes
        assert px.shape[:2] == (h, w)
        assert len(np.unique(px.reshape(-1, 3), axis=0)) > 20, f"{p.name} is nearly blank"


def test_content_in_reading_order(data: ReportData, tmp_path: Path) -> None:
    text = render(data, tmp_path / "r.html", png=False)[0].read_text(encoding="utf-8")
    res = data.result
    order = ["sec-verdict", "sec-polar", "sec-conditions", "sec-deviation", "sec-findings", "sec-iso230",
             "sec-advice", "sec-trend", "sec-noise", "sec-diagnostics", "sec-signoff"]
    pos = [text.index(f'id="{s}"') for s in order]
    assert pos == sorted(pos)
    assert text.index("<footer") > pos[-1]
    assert "<title>Ball-bar test report — mill-3 — mill-3-20260301T081500Z</title>" in text
    assert "2026-03-01 08:15:00 UTC" in text
    # the verdict: no limits here, said so; G(b) to one decimal; the top machine finding in words with its
    # share of the machine's error
    g_b = res["iso230_4"]["G_b_um"]
    assert 'id="verdict-status">NO LIMITS SET<' in text and 'data-status="none"' in text
    assert f'id="verdict-g"><b>G(b) {g_b:.1f} µm' in text
    assert "<b>Servo mismatch</b>: X lags Y by" in text  # KX < KY: X lags
    assert "of the machine's error)" in text
    # polar plot scale stated in the caption, in µm per division
    assert re.search(r"<b>\d+(\.\d+)? µm per division</b>", text)
    # the statistics: every ranked pattern in the published order with its significance, the fields that were
    # not fitted with their reason
    rows = re.findall(r'<tr class="(sig|nsig)" data-stat="([^"]+)"', text)
    assert [name for _, name in rows] == [r["pattern"] for r in res["ranking"]]
    assert [cls == "sig" for cls, _ in rows] == [r["significant"] for r in res["ranking"]]
    absent = text[text.index('<tr class="absent">'):]
    assert "no X screw pitch configured" in absent and "cyclic_x_um" in absent
    # ISO figures with their conditions; advice; diagnostics
    # at the place the verdict shows them (their uncertainty sqrt(2) x the residual RMS; 0.1 um at the finest)
    assert f'<td id="iso-G_ccw_um">{res["iso230_4"]["G_ccw_um"]:.1f}</td>' in text
    assert "ISO 230-4:2022" in text
    for a in res["advice"]:
        if not a["pattern"].startswith("reversal_spike_"):
            assert re.sub(r"\bum\b", "µm", a["action"])[:30] in text
    assert f'{res["timing"]["measured_feed_mm_min"]:.2f} mm/min' in text
    assert "ballbar " in text and "Source: simulated test" in text


def test_units_are_displayed_with_micro_signs(data: ReportData, tmp_path: Path) -> None:
    text = render(data, tmp_path / "r.html", png=False)[0].read_text(encoding="utf-8")
    visible = re.sub(r"<svg.*?</svg>|<style>.*?</style>|<[^>]+>", " ", text, flags=re.S)
    assert "µm" in visible and "µrad" in visible
    assert not re.search(r"\d\s*um\b", visible), re.findall(r".{20}\d\s*um\b.{10}", visible)


def test_one_direction_renders(tmp_path: Path) -> None:
    plan = PLAN.with_(directions="ccw")
    result, curves = _analyse(plan)
    assert set(curves) == {"ccw"} and result["iso230_4"]["G_b_um"] is None
    paths = render(ReportData(result=result, curves=curves), tmp_path / "one.html")
    text = paths[0].read_text(encoding="utf-8")
    assert 'id="polar-ccw"' in text and 'id="polar-cw"' not in text
    assert "Circularity G CCW" in text
    assert '<td id="iso-G_b_um" class=gb>–</td>' in text
    assert "this direction is not in the test" in text  # the CW spikes, greyed with their reason
    assert [p.name for p in paths] == ["one.html", "one-polar.png", "one-deviation.png"]


def test_vertical_plane_partial_arc_is_labelled_with_its_axes(tmp_path: Path) -> None:
    plan = PLAN.with_(plane="ZX", data_arc_deg=220.0, start_deg=-20.0)
    result, curves = _analyse(plan)
    text = render(ReportData(result=result, curves=curves), tmp_path / "zx.html", png=False)[0].read_text(
        encoding="utf-8")
    labels = {}
    for ang in (0, 90, 180, 270):
        g = text[text.index(f'<g id="polar-axis-{ang}">'):]
        labels[ang] = re.findall(r"<text[^>]*>([^<]*)</text>", g[: g.index("</g>")])
    assert labels == {0: ["+Z", "0°"], 90: ["+X", "90°"], 180: ["−Z", "180°"], 270: ["−X", "270°"]}
    assert "ZX (Z, X)" in text and "220.0°" in text


def test_trend_with_history_and_without(data: ReportData, tmp_path: Path) -> None:
    text = render(data, tmp_path / "h.html", png=False)[0].read_text(encoding="utf-8")
    assert 'id="trend-svg"' in text
    table = text[text.index('id="trend-table"'):]
    table = table[: table.index("</table>")]
    assert table.count("<tr") == 1 + len(data.history) + 1  # header, history, this test
    assert all(h["test_id"] in table for h in data.history)
    table = " ".join(re.sub(r"<[^>]+>", "", table).split())  # the unit sits on its own line in the header
    assert "Backlash X (µm)" in table and "Servo mismatch (ms)" in table and "Circularity G(b) (µm)" in table
    assert "earlier tests of mill-3 with the same plan" in text
    data.history = []
    paths = render(data, tmp_path / "n.html")
    text = paths[0].read_text(encoding="utf-8")
    assert 'id="trend-none"' in text and "no trend yet" in text and "trend-svg" not in text
    assert not (tmp_path / "n-trend.png").exists() and len(paths) == 3


def test_trend_axes_span_the_uncertainty(data: ReportData) -> None:
    """A figure that moves within its standard error plots flat (the axis spans +-4 of them about the mean);
    one that moves by many keeps the autoscaled range of its points."""
    from ballbar.tools.report_plots import trend_figure as _trend_figure
    from ballbar.tools.report_plots import trend_quantities as _trend_quantities

    tests = [*_history(data.result, 3), data.result]
    servo = [r["parameters"]["servo_mismatch_ms"] for r in tests]
    se = servo[-1]["stderr"]
    for k, p in enumerate(servo):  # a wander of 0.12 standard errors in all
        p["value"], p["stderr"] = servo[-1]["value"] + 0.04 * se * k, se
    qs = _trend_quantities(tests, ("X", "Y"))
    fig = _trend_figure(tests, qs)
    axes = {ax.get_gid(): ax for ax in fig.axes if ax.get_visible()}
    lo, hi = axes["trend-servo_mismatch_ms"].get_ylim()
    mean = sum(p["value"] for p in servo) / len(servo)
    assert lo <= mean - 4 * se + 1e-12 and hi >= mean + 4 * se - 1e-12
    assert hi - lo < 10 * se  # and not wider than that needs
    bx = [r["parameters"]["backlash_x_um"] for r in tests]
    lo, hi = axes["trend-backlash_x_um"].get_ylim()  # 0.8 .. 1.0 of the value: many standard errors
    assert hi - lo < 2.0 * (max(p["value"] + p["stderr"] for p in bx) - min(p["value"] - p["stderr"] for p in bx))
    assert lo <= min(p["value"] for p in bx) and hi >= max(p["value"] for p in bx)


def test_text_is_escaped(data: ReportData, tmp_path: Path) -> None:
    data.result["machine_id"] = '<script>alert("x")</script>'
    data.result["test_id"] = "a&b<i>"
    data.source = "<img src=x onerror=alert(1)>"
    text = render(data, tmp_path / "e.html", png=False)[0].read_text(encoding="utf-8")
    assert "<script" not in text and "<img" not in text and "<i>" not in text
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt;" in text
    assert "a&amp;b&lt;i&gt;" in text and "&lt;img src=x onerror=alert(1)&gt;" in text


def test_the_results_warnings_are_in_the_verdict(data: ReportData, tmp_path: Path) -> None:
    text = render(data, tmp_path / "w.html", png=False)[0].read_text(encoding="utf-8")
    assert "Warning:" not in text
    data.result["warnings"] = ["timing model: the feed-in (1.5 mm) is too short <to reach> the feed"]
    text = render(data, tmp_path / "w.html", png=False)[0].read_text(encoding="utf-8")
    verdict = text[text.index('id="sec-verdict"'):text.index('id="sec-polar"')]
    assert "<b>Warning:</b> timing model: the feed-in (1.5 mm) is too short &lt;to reach&gt; the feed" in verdict


def test_missing_pieces(analysed: tuple[dict[str, Any], dict[str, Any]], tmp_path: Path) -> None:
    result = copy.deepcopy(analysed[0])
    del result["iso230_4"], result["noise"], result["timing"], result["t_wall"], result["machine_id"]
    result["parameters"]["backlash_x_um"].update(value=float("nan"), stderr=None)
    result["ranking"][0]["F"] = None
    text = render(ReportData(result=result, curves={}), tmp_path / "m.html", png=False)[0].read_text(
        encoding="utf-8")
    assert "No ISO 230-4 figures in this result" in text and "No noise findings" in text
    assert "No curves in the data: plots omitted" in text and "<svg" not in text
    assert not re.search(r"\bnan\b", text, flags=re.I)
    row = text[text.index('data-pattern="backlash_x"'):]
    assert row[: row.index("</tr>")].count("–") >= 1
    assert "<title>Ball-bar test report — mill-3-20260301T081500Z</title>" in text


def test_large_1khz_test_stays_small(tmp_path: Path) -> None:
    plan = TestPlan(overshoot_deg=20.0, dwell_s=0.2, sample_hz=1000.0)  # R 100 mm, F 1000: ~37 700 samples a circle
    result, curves = _analyse(plan, MACHINE.with_(spike_y_um=3.0))
    assert curves["ccw"]["u_deg"].size > 30000
    path = render(ReportData(result=result, curves=curves), tmp_path / "big.html", png=False)[0]
    size = path.stat().st_size
    assert size < 2_000_000, size
    text = path.read_text(encoding="utf-8")
    g = text[text.index('<g id="polar-ccw">'):]
    path_d = g[: g.index("</g>")]
    vertices = path_d.count(" L ") + path_d.count("\nL ") + 1
    assert 500 < vertices <= 2000, vertices


def test_envelope_keeps_a_one_sample_spike() -> None:
    n = 40_000
    y = np.sin(np.linspace(0, 6 * math.pi, n))
    y[12_345] = 30.0
    y[33_333] = -25.0
    idx = envelope_indices(y, 2000)
    assert idx.size <= 2000 and np.all(np.diff(idx) > 0)
    assert 12_345 in idx and 33_333 in idx
    assert y[idx].max() == 30.0 and y[idx].min() == -25.0
    assert np.array_equal(envelope_indices(y[:100], 2000), np.arange(100))


@pytest.mark.parametrize(
    "max_abs, div", [(0.0, 1.0), (2.9, 1.0), (3.1, 2.0), (27.0, 10.0), (31.0, 20.0), (140.0, 50.0)]
)
def test_polar_scale_is_round_and_fits(max_abs: float, div: float) -> None:
    assert polar_scale_um(max_abs) == pytest.approx(div)


@pytest.mark.usefixtures("no_leaks")
def test_import_and_render_leave_matplotlib_global_state_alone(tmp_path: Path) -> None:
    code = (
        "import sys, pickle\n"
        "import ballbar.tools.report_render as rr\n"
        "assert 'matplotlib' not in sys.modules, 'import pulled matplotlib in'\n"
        "from ballbar.tools.report import ReportData\n"
        "d = pickle.load(open(sys.argv[1], 'rb'))\n"
        "rr.render(ReportData(**d), __import__('pathlib').Path(sys.argv[2]))\n"
        "assert 'matplotlib.pyplot' not in sys.modules, 'render used pyplot'\n"
        "import matplotlib\n"
        "print(matplotlib.rcParams['svg.fonttype'], matplotlib.rcParams['font.size'])\n"
    )
    result, curves = _analyse(PLAN.with_(directions="cw"))
    blob = tmp_path / "d.pkl"
    blob.write_bytes(pickle.dumps({"result": result, "curves": curves}))
    env = dict(os.environ)
    env.pop("MPLBACKEND", None)
    out = subprocess.run([sys.executable, "-c", code, str(blob), str(tmp_path / "x.html")],
                         capture_output=True, text=True, timeout=60, env=env, check=False)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["path", "10.0"]  # matplotlib's defaults, untouched by the renderer
    assert (tmp_path / "x-polar.png").exists()


# --------------------------------------------------------------------------- in a real browser


def _chromium_or_skip() -> str:
    exe = find_chromium()
    if exe is None:
        msg = "Chromium not found ($BALLBAR_CHROMIUM, chromium on PATH or /usr/bin/chromium)"
        if os.environ.get("BALLBAR_REQUIRE_BROWSER") == "1":
            pytest.fail(f"{msg}, and BALLBAR_REQUIRE_BROWSER=1 requires it")
        pytest.skip(f"{msg}; set BALLBAR_REQUIRE_BROWSER=1 to make this a failure")
    return exe


@pytest.fixture
def pixel_server() -> Iterator[str]:
    """A loopback HTTP server for the control page's external request; shut down after the test."""

    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args: Any) -> None:
            pass

        def do_GET(self) -> None:
            self.send_response(404)
            self.end_headers()

    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Quiet)
    srv.daemon_threads = True
    th = threading.Thread(target=srv.serve_forever, name="pixel-server", daemon=True)
    th.start()
    try:
        yield f"http://127.0.0.1:{srv.server_address[1]}"
    finally:
        srv.shutdown()
        srv.server_close()
        th.join(5)


PAGE_FACTS = """(() => {
  const box = e => { const r = e.getBoundingClientRect(); return [r.width, r.height]; };
  const trace = id => {
    const g = document.getElementById(id);
    if (!g) return null;
    const b = g.getBBox(), p = g.querySelector('path');
    return {w: b.width, h: b.height, stroke: p ? getComputedStyle(p).stroke : null,
            dash: p ? getComputedStyle(p).strokeDasharray : null,
            inSvg: g.closest('svg') ? g.closest('svg').id : null};
  };
  const legend = id => [...document.querySelectorAll('#' + id + ' path')].map(p => getComputedStyle(p).strokeDasharray);
  const de = document.documentElement, trend = document.getElementById('trend-table');
  const first = document.querySelector('#findings tbody tr');
  return {
    title: document.title,
    svgs: [...document.querySelectorAll('svg')].map(s => ({id: s.id, box: box(s)})),
    ccw: trace('polar-ccw'), cw: trace('polar-cw'),
    ccwModel: trace('polar-ccw-model'), cwModel: trace('polar-cw-model'),
    firstPattern: first ? first.dataset.pattern : null,
    firstText: first ? first.cells[1].textContent : null,
    gb: (document.getElementById('iso-G_b_um') || {}).textContent,
    resources: performance.getEntriesByType('resource').map(e => e.name),
    scripts: document.scripts.length,
    height: document.documentElement.scrollHeight,
    page: [de.scrollWidth, de.clientWidth],
    overflowing: [...document.querySelectorAll('section')].filter(s => s.scrollWidth > s.clientWidth).map(s => s.id),
    trendTable: trend ? [trend.getBoundingClientRect().width, trend.closest('section').clientWidth] : null,
    polarLegend: legend('polar-legend_1'), deviationLegend: legend('deviation-legend_1'),
  };
})()"""


@pytest.fixture
def report_html(data: ReportData, tmp_path: Path) -> Path:
    """The report, rendered before ``no_leaks`` starts watching: matplotlib keeps its font files open for
    the life of the process, a cache and not a leak of the browser test."""
    return render(data, tmp_path / "report.html", png=False)[0]


def test_report_in_headless_chromium(
    data: ReportData, report_html: Path, no_leaks: None, pixel_server: str, tmp_path: Path
) -> None:
    exe = _chromium_or_skip()
    html_path = report_html
    res = data.result
    t0 = time.monotonic()
    with Chromium(exe, BROWSER_TIMEOUT_S) as browser:
        session = browser.open_page()
        browser.load(session, html_path.as_uri())
        facts = browser.evaluate(session, PAGE_FACTS)
        requests = browser.requests(session)
        errors = browser.errors(session)
        shot = browser.screenshot(session)

        assert facts["title"] == "Ball-bar test report — mill-3 — mill-3-20260301T081500Z"
        assert [s["id"] for s in facts["svgs"]] == ["polar-svg", "deviation-svg", "trend-svg"]
        for s in facts["svgs"]:
            assert s["box"][0] > 300 and s["box"][1] > 200, s
        for key in ("ccw", "cw", "ccwModel", "cwModel"):
            tr = facts[key]
            assert tr is not None and tr["inSvg"] == "polar-svg", (key, tr)
            assert tr["w"] > 100 and tr["h"] > 100, (key, tr)  # a whole circle, not a dot
        assert facts["ccw"]["stroke"] != facts["cw"]["stroke"]
        # the model is dashed, the measured curve solid, and the legends show which is which
        for key in ("ccw", "cw"):
            assert facts[key]["dash"] == "none" and facts[key + "Model"]["dash"] != "none", facts[key]
        for legend in (facts["polarLegend"], facts["deviationLegend"]):
            assert len(legend) == 4 and sum(d != "none" for d in legend) == 2, legend
        # nothing is wider than the page: the trend table (7 columns here) fits its section
        assert facts["page"][0] <= facts["page"][1], facts["page"]
        assert facts["overflowing"] == [], facts["overflowing"]
        assert facts["trendTable"] is not None and facts["trendTable"][0] <= facts["trendTable"][1]
        assert facts["firstPattern"] == res["ranking"][0]["pattern"] == "servo_mismatch"
        assert facts["firstText"].strip() == "Servo mismatch"
        assert facts["gb"] == f"{res['iso230_4']['G_b_um']:.1f}"  # 0.1 um: analysis/numbers.py
        assert facts["scripts"] == 0
        assert facts["resources"] == []
        assert requests == [html_path.as_uri()], requests  # nothing but the document itself
        assert errors == []
        w, h = _png_size(shot)
        assert (w, h) == (1200, 900)
        px = _pixels(shot)
        assert len(np.unique(px.reshape(-1, 3), axis=0)) > 50
        assert (px.min(axis=2) < 200).mean() > 0.01  # text, rules and curves, not a white page

        # Control: the same recorders do see a request that leaves the page and a console error.
        control = tmp_path / "control.html"
        control.write_text(f'<!DOCTYPE html><title>c</title><img src="{pixel_server}/pixel.png">'
                           '<script>console.error("control error")</script>', encoding="utf-8")
        browser.load(session, control.as_uri())
        seen = browser.evaluate(session, "performance.getEntriesByType('resource').map(e => e.name)")
        assert seen == [f"{pixel_server}/pixel.png"]
        assert f"{pixel_server}/pixel.png" in browser.requests(session)
        assert any("control error" in e for e in browser.errors(session))
    assert time.monotonic() - t0 < BROWSER_TIMEOUT_S


def test_the_words_both_views_use() -> None:
    """Uncertainties never round to zero, no negative zero, shares of the machine's error without the set-up,
    the reversal spikes of an axis as one finding, limits in an engineer's words with their margin."""
    from ballbar.analysis.report import limit_words, machine_ranking, quantity_label, share_text, value_text

    assert value_text(3.0301, 0.0014) == "3.0301 ± 0.0014"  # the report printed "3.030 ± 0.00"
    assert value_text(53.7, 0.71) == "53.7 ± 0.7" and value_text(2.0, None) == "2.00"
    # with its unit, never finer than the unit's resolution (analysis/numbers.py; tests/test_numbers.py)
    assert value_text(3.0301, 0.0014, unit="ms") == "3.03 ± 0.01" and value_text(-0.01, 0.3, unit="um") == "0.0 ± 0.3"
    assert share_text(-0.001) == "< 0.1 %" and share_text(78.48) == "78 %" and share_text(2.04) == "2.0 %"
    ranking = [{"pattern": "centre", "share_pct": 55.6, "significant": True},
               {"pattern": "servo_mismatch", "share_pct": 41.6, "significant": True},
               {"pattern": "radius", "share_pct": 2.0, "significant": True},
               {"pattern": "reversal_spike_x_pos_ccw", "share_pct": 0.4, "significant": True, "p_value": 1e-5},
               {"pattern": "reversal_spike_x_neg_cw", "share_pct": 0.4, "significant": False, "p_value": 0.2}]
    ranked = machine_ranking({"ranking": ranking})
    assert [r["pattern"] for r in ranked] == ["servo_mismatch", "reversal_spikes_x"]
    assert ranked[0]["machine_share_pct"] == pytest.approx(100 * 41.6 / 42.4)
    assert ranked[1]["members"] == ["reversal_spike_x_pos_ccw", "reversal_spike_x_neg_cw"]
    assert ranked[1]["significant"] and ranked[1]["p_value"] == 1e-5
    assert quantity_label("G_b_um") == "Circularity G(b)"
    assert quantity_label("backlash_y_um", ("Z", "X")) == "Backlash X"
    entry = {"name": "servo_mismatch_ms", "unit": "ms", "value": 3.0301, "uncertainty": 0.0028, "limit": 2.0,
             "margin": -1.0301, "status": "fail", "warning_level": 1.6}
    assert limit_words(entry) == "Servo mismatch 3.03 ± 0.01 ms, limit 2.00 ms: over by 1.03 ms"
    # the place from the standard error, the k u shown at it: the same value reads the same as in the detail table
    entry["stderr"], entry["uncertainty"] = 0.06, 0.12
    assert limit_words(entry) == "Servo mismatch 3.03 ± 0.12 ms, limit 2.00 ms: over by 1.03 ms"
