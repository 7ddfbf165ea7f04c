"""A test set's report (``ballbar report DIR --set NAME``), made from the daemon's records as the real MCAP logger
wrote them (tests/setscene.py: three plans on a 3D machine, each with its limits and ten earlier tests), and read
in headless Chromium at 1400 and 800 px as the single test's report is (tests/test_screens.py): the set's verdict
on the first screen in its colour, each plan's curves inside its own polar scale, its trend's points inside its
axes, nothing wider than the window, every id in the document once.

Also: ``ballbar analyze DIR --set NAME`` makes the set again from the same records with the figures the live
daemon published, and a set the records cannot make is a one-line error with its exit code.

Needs Chromium for the browser test; without it that test skips and says why, unless
``BALLBAR_REQUIRE_BROWSER=1`` (CI) makes that a failure.
"""

from __future__ import annotations

import collections
import json
import re
import shutil
from pathlib import Path
from typing import Any

import pytest
import setscene
from browser import Chromium
from test_report_render import _chromium_or_skip
from test_screens import CSS_RGB, _check_png, _keep, _pixels

from ballbar.analysis.numbers import measured
from ballbar.analysis.sets import STATUS_WORDS
from ballbar.daemon.cli import main
from ballbar.daemon.mcap import list_recordings, read_log

WIDTHS = (1400, 800)
HEIGHT = 900


@pytest.fixture(scope="module")
def scene() -> setscene.Scene:
    return setscene.build()


@pytest.fixture(scope="module")
def records(scene: setscene.Scene, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return setscene.write_records(scene, tmp_path_factory.mktemp("state"))


def published_set(records: Path) -> dict[str, Any]:
    sets = [r for p in list_recordings(records) for r in read_log(p, samples=False).results if r["kind"] == "set"]
    assert len(sets) == 1
    return sets[0]


def run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def report(records: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The set's report, rendered before any leak check starts watching (matplotlib keeps its fonts open)."""
    out = tmp_path_factory.mktemp("report") / "set.html"
    assert main(["report", str(records), "--set", "machine", "-o", str(out), "--operator", "A. Jones"]) == 0
    return out


def test_analyze_makes_the_live_set_again(records: Path, capsys: pytest.CaptureFixture[str]) -> None:
    live = published_set(records)
    code, out, err = run(["analyze", str(records), "--set", "machine", "--json"], capsys)
    assert code == 0, err
    again = json.loads(out)
    assert again["set"] == live["set"] and again["set_id"] == live["set_id"]
    assert [m["test_id"] for m in again["tests"]] == [m["test_id"] for m in live["tests"]]
    assert again["verdict"]["status"] == live["verdict"]["status"] == "fail"
    for key, names in (("lost_motion", "XYZ"), ("squareness", ("XY", "YZ", "ZX"))):
        for n in names:
            a, b = again[key][n], live[key][n]
            # the same samples to the MCAP log's resolution, each test found again in its file (its feed-in
            # within 0.1 ms of the live one's): the same figures within a tenth of their standard error
            assert abs(a["value"] - b["value"]) <= 0.1 * b["stderr"], (key, n, a, b)
            assert a["stderr"] == pytest.approx(b["stderr"], rel=0.05), (key, n)
    assert [c["status"] for c in again["checks"]] == [c["status"] for c in live["checks"]]


def test_the_report_holds_the_set_and_each_plan(report: Path, records: Path) -> None:
    html = report.read_text(encoding="utf-8")
    live = published_set(records)
    ids = collections.Counter(re.findall(r'\bid="([^"]+)"', html))
    assert [i for i, n in ids.items() if n > 1] == []  # three tests' sections in one document, no id twice
    # the set first: its verdict, then each plan's test with all of a test's sections
    order = [html.index(f'id="sec-{s}"') for s in ("verdict", "axes", "volumetric", "checks")]
    for p in setscene.PLANS:
        order += [html.index(f'id="sec-{p}-{s}"') for s in ("verdict", "polar", "findings", "iso230", "trend")]
        for curve in ("ccw", "cw", "ccw-model", "cw-model"):
            assert f'id="{p}-polar-{curve}"' in html
        assert re.search(rf'id="{p}-trend-[^"]+-points"', html), p
    assert order == sorted(order)
    assert html.index('id="sec-signoff"') > order[-1] and "A. Jones" in html
    # the figures are the published set's, each plan's test is named with its plane
    head = html[: html.index('id="sec-axes"')]
    assert f">{STATUS_WORDS[live['verdict']['status']]}<" in head
    for p, plane in (("xy", "XY"), ("zx", "ZX"), ("yz", "YZ")):
        assert f"<b>{p}</b> ({plane} plane)" in head and f"Plan {p} ({plane}): Verdict" in html
    z = live["lost_motion"]["Z"]
    # by the one rounding rule (analysis/numbers.py): the error to its place, never finer than 0.1 um
    zt = measured(z["value"], z["stderr"], "um", signed=True, with_unit=False)
    assert re.fullmatch(r"\+\d+\.\d ± \d\.\d", zt), zt
    assert f'<tr id="axis-Z"><td>Z</td><td class="num">{zt}</td>' in html
    # what to do: the failing plan first, with its advice
    todo = html[html.index('id="verdict-todo"'):html.index("</ul>", html.index('id="verdict-todo"'))]
    assert todo.index("<b>zx</b> (fail)") < todo.index("<b>yz</b> (warning)") and "<b>xy</b>" not in todo
    assert 'href="#sec-zx-advice"' in todo


REPORT_FACTS = """(() => {
  const r = e => {
    if (!e) return null;
    const b = e.getBoundingClientRect();
    return [b.left, b.top, b.right, b.bottom];
  };
  const inside = (a, b) => a && b && a[0] >= b[0] - 1 && a[1] >= b[1] - 1 && a[2] <= b[2] + 1 && a[3] <= b[3] + 1;
  const de = document.documentElement, badge = document.getElementById('verdict-status');
  const plans = PLANS.map(p => {
    const ring = r(document.getElementById(p + '-polar-outer-ring'));
    const curves = ['ccw', 'cw', 'ccw-model', 'cw-model'].map(
      c => inside(r(document.getElementById(p + '-polar-' + c)), ring));
    const points = [...document.querySelectorAll('[id^="' + p + '-trend-"][id$="-points"]')].map(
      g => inside(r(g), r(document.getElementById(g.id.replace(/-points$/, '-area')))));
    const pbadge = document.getElementById(p + '-verdict-status');
    return {plan: p, curves, points, status: pbadge ? pbadge.textContent : null,
            colour: pbadge ? getComputedStyle(pbadge).backgroundColor : null};
  });
  const wide = [...document.querySelectorAll('body *')].filter(e => {
    if (e.closest('.wide') || e.closest('svg')) return false;
    const b = e.getBoundingClientRect();
    return b.width > 0 && (b.right > de.clientWidth + 1 || b.left < -1);
  }).map(e => e.tagName + '#' + e.id + '.' + e.className);
  return {
    page: [de.scrollWidth, de.clientWidth], wide: wide.slice(0, 5),
    status: badge ? badge.textContent : null, colour: badge ? getComputedStyle(badge).backgroundColor : null,
    verdict: r(document.getElementById('verdict')), todo: r(document.getElementById('verdict-todo')),
    plans, resources: performance.getEntriesByType('resource').map(e => e.name),
  };
})()"""


def test_the_set_report_in_headless_chromium(report: Path, records: Path, no_leaks: None) -> None:
    live = published_set(records)
    statuses = {m["plan"]: m["verdict"] for m in live["tests"]}
    facts = REPORT_FACTS.replace("PLANS", json.dumps(list(setscene.PLANS)))
    with Chromium(_chromium_or_skip(), 120.0, window=(WIDTHS[0], HEIGHT)) as browser:
        session = browser.open_page()
        for width in WIDTHS:
            browser.call("Emulation.setDeviceMetricsOverride",
                         {"width": width, "height": HEIGHT, "deviceScaleFactor": 1, "mobile": False}, session)
            browser.load(session, report.as_uri())
            f = browser.evaluate(session, facts)
            assert f["page"][0] <= f["page"][1] and f["wide"] == [], (width, f["page"], f["wide"])
            # the set's verdict on the first screen, in its colour, and what to do beneath it
            assert f["status"] == "FAIL" and f["colour"] == CSS_RGB["fail"], (width, f)
            assert f["verdict"][1] < 0.25 * HEIGHT and f["todo"][1] < 1.5 * HEIGHT, (width, f["verdict"], f["todo"])
            for p in f["plans"]:
                where = (width, p["plan"])
                assert p["status"] == STATUS_WORDS[statuses[p["plan"]]], where
                assert p["colour"] == CSS_RGB[statuses[p["plan"]]], where
                assert len(p["curves"]) == 4 and all(p["curves"]), (where, p["curves"])
                assert p["points"] and all(p["points"]), (where, p["points"])
            assert all(u.startswith("file:") or u.startswith("data:") for u in f["resources"]), f["resources"]
            px = _pixels(browser.screenshot(session))
            assert px.shape[:2] == (HEIGHT, width)
            _keep(f"report-set-{width}.png", px)
        assert browser.errors(session) == []


def test_a_set_the_records_cannot_make_is_a_one_line_error(
    records: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code, _out, err = run(["report", str(records), "--set", "nope", "-o", str(tmp_path / "x.html")], capsys)
    assert code == 1 and "no set 'nope' (sets: machine)" in err and len(err.strip().splitlines()) == 1, err
    one = next(iter(list_recordings(records)))
    code, _out, err = run(["report", str(one), "--set", "machine", "-o", str(tmp_path / "x.html")], capsys)
    assert code == 2 and "--set makes the report of a set from a directory" in err, err
    # the set's last test missing: which plan the set waits for, and nothing written
    partial = tmp_path / "partial"
    partial.mkdir()
    for p in list_recordings(records)[:-1]:
        shutil.copy(p, partial / p.name)
    for cmd in (["report", str(partial), "--set", "machine", "-o", str(tmp_path / "x.html")],
                ["analyze", str(partial), "--set", "machine"]):
        code, _out, err = run(cmd, capsys)
        assert code == 1 and "set machine" in err and "yz" in err and len(err.strip().splitlines()) == 1, (cmd, err)
    assert not (tmp_path / "x.html").exists()


def test_the_committed_screenshots_are_there_and_small() -> None:
    """The README's picture of a set's report: each width, a valid PNG of the window's size under 400 kB."""
    for width in WIDTHS:
        _check_png(Path(__file__).with_name("screenshots") / f"report-set-{width}.png", (width, HEIGHT))
