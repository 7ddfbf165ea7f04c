"""What an engineer sees first: screenshots of the live view (Rerun 0.41's own viewer, off-screen) and of the
report (headless Chromium) for a passing machine, one in warning and a failing one, checked as the report's
browser test checks the report: the verdict present and in its colour, every point inside its scale, nothing
wider than the window.  And the live view's and the report's rankings of the same test agree.

The scene is :mod:`livescene`: a simulated machine's tests as the daemon hands them to the viewer, each with a
verdict against limits it passes, warns on or fails, after 20 earlier tests.  The viewer is
:class:`~ballbar.daemon.rerun.RerunViewer` in serve mode; a real ``rerun`` viewer, headless (``--headless``: its
offscreen harness, no X server) on Mesa's CPU Vulkan driver (lavapipe), opens it and is shot through its control
API (:class:`Viewer`) at 1600x1000 and 1280x800 once it holds the whole scene; an ERROR line from it fails.
The report is rendered from the same results and loaded at 1400 and 800 px.

Needs Debian's ``mesa-vulkan-drivers`` for the viewer and ``chromium`` for the
report; without them those tests skip and say why, unless ``BALLBAR_REQUIRE_SCREENSHOTS=1`` (CI) makes that a
failure.  ``BALLBAR_SCREENSHOTS=1`` writes the screenshots, small, to ``tests/screenshots/`` (the README's).
"""

from __future__ import annotations

import copy
import io
import os
import re
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import livescene
import numpy as np
import pytest
import setscene
from browser import Chromium, find_chromium

from ballbar.analysis.report import STATUS_WORDS, machine_ranking, pattern_label, share_text
from ballbar.daemon.rerun import RerunViewer, ViewerOptions, findings_markdown, rerun_binary
from ballbar.daemon.rerun.geometry import COLOURS, STATUS_RGB
from ballbar.tools.report import ReportData
from ballbar.tools.report_render import render

STATUSES = ("pass", "warning", "fail")
VIEWER_SIZES = ((1600, 1000), (1280, 800))
REPORT_WIDTHS = (1400, 800)
REPORT_HEIGHT = 900
ARTEFACTS = Path(__file__).with_name("screenshots")
LAVAPIPE = "/usr/share/vulkan/icd.d/lvp_icd.x86_64.json"


def _required(what: str) -> None:
    msg = f"{what}; BALLBAR_REQUIRE_SCREENSHOTS=1 makes this a failure"
    if os.environ.get("BALLBAR_REQUIRE_SCREENSHOTS") == "1":
        pytest.fail(f"{what}, and BALLBAR_REQUIRE_SCREENSHOTS=1 requires it")
    pytest.skip(msg)


def _pixels(blob: bytes, size: tuple[int, int] | None = None) -> np.ndarray:
    from PIL import Image  # matplotlib's own dependency

    with Image.open(io.BytesIO(blob)) as im:
        im = im.convert("RGB")
        if size is not None and im.size != size:  # the viewer renders at the screen's scale factor
            im = im.resize(size, Image.Resampling.LANCZOS)
        return np.asarray(im)


def _keep(name: str, px: np.ndarray) -> None:
    """With BALLBAR_SCREENSHOTS=1, the screenshot as a small PNG (96 colours) in tests/screenshots/."""
    if os.environ.get("BALLBAR_SCREENSHOTS") != "1":
        return
    from PIL import Image

    ARTEFACTS.mkdir(exist_ok=True)
    Image.fromarray(px).quantize(colors=96, method=Image.Quantize.MEDIANCUT).save(ARTEFACTS / name, optimize=True)


def _bar_rows(mask: np.ndarray) -> slice:
    """The rows of a horizontal bar in ``mask`` (those with at least half its widest row's pixels), and 3 more
    either side."""
    per_row = mask.sum(axis=1)
    full = np.nonzero(per_row >= 0.5 * per_row.max())[0]
    return slice(max(int(full.min()) - 3, 0), int(full.max()) + 4)


def _near(px: np.ndarray, rgb: tuple[int, ...], tol: float = 40.0) -> np.ndarray:
    return np.asarray(np.linalg.norm(px.astype(float) - np.asarray(rgb[:3], float), axis=2) < tol)


@pytest.fixture(scope="module")
def scene() -> livescene.Scene:
    return livescene.build()


# --------------------------------------------------------------------------- the live view


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _viewer_or_skip() -> str:
    exe = rerun_binary()
    if exe is None:
        _required("the rerun viewer binary (rerun-sdk's rerun_cli) is not installed")
    if not os.path.exists(LAVAPIPE):
        _required(f"no CPU Vulkan driver ({LAVAPIPE}; Debian: apt-get install mesa-vulkan-drivers)")
    assert exe is not None
    return exe


FED = "fed"  # the timeline of the mark a test logs after the scene: the viewer has it all when it has the mark


def _feed(v: RerunViewer, items: Sequence[tuple[str, Any]]) -> None:
    """Once the viewer's server is up, hand it a scene's batches and messages, and let it send all it holds;
    then a mark on the ``fed`` timeline, after everything else on the same stream (the server keeps the order)."""
    import rerun as rr

    deadline = time.monotonic() + 20.0
    while not v.connected:
        assert time.monotonic() < deadline, f"the viewer's server did not come up: {v.stats()}"
        v.on_idle()
        time.sleep(0.05)
    for kind, x in items:
        (v.on_batch if kind == "batch" else v.on_message)(x)
    while v.stats()["history_pending"]:
        v.on_idle()
    v.on_idle()
    assert v.stats()["errors"] == 0
    rec = v._rec
    assert rec is not None
    rec.set_time(FED, sequence=1)
    rec.log(FED, rr.AnyValues(done=[True]))
    rec.disable_timeline(FED)
    rec.flush()


@pytest.fixture
def served(scene: livescene.Scene, request: pytest.FixtureRequest) -> Iterator[RerunViewer]:
    """The daemon's viewer in serve mode, fed the scene with the verdicts of ``request.param``."""
    items, earlier = livescene.annotated(scene, request.param)
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=_free_port(), server_memory_limit="64MiB"),
                    plan=livescene.PLAN)
    try:
        assert v.seed(earlier) == len(earlier)
        _feed(v, items)
        yield v
    finally:
        v.stop()


class Viewer:
    """Rerun 0.41's own viewer, headless (its offscreen harness on Mesa's CPU Vulkan driver, no X server),
    driven through its control API (``rerun.experimental.ViewerClient``): it opens a URL, and the screenshot
    is taken once the viewer holds everything the daemon's viewer sent (its ``fed`` mark) and has painted it.
    Its own state (the blueprints it keeps per application, its settings) lives under ``home``: a layout a
    viewer saved in another test or session is not this one's."""

    def __init__(self, exe: str, size: tuple[int, int], home: Path) -> None:
        from rerun.experimental import ViewerClient

        home.mkdir(parents=True, exist_ok=True)
        runtime = home / "run"
        runtime.mkdir(mode=0o700, exist_ok=True)
        env = {**os.environ, "VK_ICD_FILENAMES": LAVAPIPE, "RUST_LOG": "warn", "HOME": str(home),
               "XDG_DATA_HOME": str(home / "data"), "XDG_CONFIG_HOME": str(home / "config"),
               "XDG_CACHE_HOME": str(home / "cache"), "XDG_RUNTIME_DIR": str(runtime)}
        env.pop("DISPLAY", None)
        env.pop("WAYLAND_DISPLAY", None)
        self.port = _free_port()
        self._shot_timeouts = 0
        self._stderr_path = home / "viewer.stderr"
        self._stderr = self._stderr_path.open("w")
        self.proc = subprocess.Popen(
            [exe, "--headless", "--bind", "127.0.0.1", "--port", str(self.port),
             "--window-size", f"{size[0]}x{size[1]}", "--hide-welcome-screen"],
            stdin=subprocess.DEVNULL, stdout=self._stderr, stderr=subprocess.STDOUT, env=env, start_new_session=True)
        deadline = time.monotonic() + 60.0
        while True:
            assert self.proc.poll() is None, f"the viewer exited: {self.stderr()[-3000:]}"
            try:
                self.client = ViewerClient.connect(f"rerun+http://127.0.0.1:{self.port}/proxy")
                self.client.get_state()
                break
            except Exception:  # not listening yet: its control API answers once the viewer runs
                assert time.monotonic() < deadline, f"the viewer did not answer: {self.stderr()[-3000:]}"
                time.sleep(0.1)

    def stderr(self) -> str:
        self._stderr.flush()
        return self._stderr_path.read_text(errors="replace")

    def shoot(self, url: str, recording_id: str, timeout: float = 120.0) -> bytes:
        """Open ``url``, wait until the viewer has the recording's ``fed`` mark and loads nothing, then a
        screenshot; every view healthy and no ERROR line from the viewer, before and after it."""
        self.client.open(url)
        deadline = time.monotonic() + timeout
        while True:
            state = self.client.get_state()
            rec = next((r for r in state.recordings if r.store_id.endswith(":" + recording_id)), None)
            fed = next((t for t in rec.timelines if t.name == FED), None) if rec is not None else None
            if fed is not None and fed.end == 1 and not state.loading:
                break
            assert self.proc.poll() is None, f"the viewer exited: {self.stderr()[-3000:]}"
            assert time.monotonic() < deadline, f"the viewer never got the whole scene: {state}"
            time.sleep(0.1)
        for attempt in range(3):  # a frame the viewer paints within its 15 s, on a CPU shared with others
            try:
                png = self.client.take_screenshot()
                break
            except TimeoutError:
                assert attempt < 2, "the viewer painted no screenshot in three tries"
                self._shot_timeouts += 1
        self.check_healthy()
        return png

    def check_healthy(self) -> None:
        """No view reports an error, and the viewer logged none."""
        state = self.client.get_state()
        sick = [(v.name, r.summary) for v in state.views for r in v.reports if r.severity == "error"]
        assert not sick, sick
        errors = [f"{e.target}: {e.message}" for e in self.client.get_logs() if e.level == "ERROR"]
        lines = [re.sub(r"\x1b\[[0-9;]*m", "", line) for line in self.stderr().splitlines()]
        errors += [line for line in lines if " ERROR " in line]
        # a screenshot that timed out and was taken again (above) is the harness's, not the view's
        late = [e for e in errors if "Failed to render screenshot" in e and "timed out" in e]
        errors = [e for e in errors if e not in late[: 2 * self._shot_timeouts]]
        assert not errors, f"{len(errors)} ERROR lines from the viewer: {errors[:5]}"

    def close(self) -> None:
        import signal

        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(10.0)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(10.0)
        self._stderr.close()


def _viewer_screenshot(exe: str, served: RerunViewer, size: tuple[int, int], home: Path) -> np.ndarray:
    viewer = Viewer(exe, size, home)
    try:
        return _pixels(viewer.shoot(served.address, served.recording_id), size)
    finally:
        viewer.close()


def check_viewer_screenshot(px: np.ndarray, status: str) -> dict[str, float]:
    """The first screen of the live view: the verdict bar in the status colour above the last complete test's
    polar plot, its curves drawn and every one of their pixels inside the outermost ring (three divisions,
    1.6 R0), the test in progress beside it with its status bar; nothing of them outside their views."""
    h, w, _ = px.shape
    left = px[:, : int(0.36 * w)]  # the last complete test's view: 3/5 of the width, 3/5 of that
    bar = _near(left, STATUS_RGB[status], 30.0)
    ys, xs = np.nonzero(bar[: int(0.3 * h)])
    assert xs.size > 0.004 * w * h / 10, f"no {status} verdict bar ({xs.size} pixels)"
    rows = _bar_rows(bar[: int(0.3 * h)])  # the bar's own rows: the scale rings and the band run through the rest
    for other, rgb in STATUS_RGB.items():
        if other != status:
            assert _near(left[rows], rgb, 25.0).sum() < 0.2 * xs.size, f"{other} colour in the bar"
    # the bar spans x = -1.5 R0 .. 1.5 R0 plus its round caps (radius 0.11 R0) at y = -1.9 R0: a ruler for R0
    x0, x1 = float(np.percentile(xs, 0.5)), float(np.percentile(xs, 99.5))
    r0 = (x1 - x0) / 3.22
    cx, cy = (x0 + x1) / 2, float(np.median(ys)) + 1.9 * r0
    assert x0 > 1 and x1 < left.shape[1] - 2, "the verdict bar is cut"
    yy, xx = np.mgrid[0:h, 0 : left.shape[1]]
    dist = np.hypot(xx - cx, yy - cy) / r0
    curve = (_near(left, COLOURS["ccw"]) | _near(left, COLOURS["cw"])) & (dist < 2.2) & (yy > np.median(ys) + 0.2 * r0)
    assert curve.sum() > 10 * r0, f"the polar curves are not drawn ({curve.sum()} pixels, R0 {r0:.0f} px)"
    reach = float(np.percentile(dist[curve], 99.9))
    assert reach <= 1.6 + 6.0 / r0, f"curves reach {reach:.3f} R0, beyond the outermost ring (1.6 R0)"
    assert cy + 1.7 * r0 < 0.75 * h and cx - 1.7 * r0 > 0, "the polar plot is cut by its view"
    live = px[: int(0.3 * h), int(0.36 * w) : int(0.6 * w)]
    assert _near(live, (70, 74, 84), 12.0).sum() > 0.15 * xs.size, "no status bar over the test in progress"
    return {"r0_px": r0, "reach_r0": reach}


@pytest.mark.parametrize("served", STATUSES, indirect=True)
def test_live_view_screenshots(served: RerunViewer, tmp_path: Path, request: pytest.FixtureRequest) -> None:
    status = request.node.callspec.params["served"]
    exe = _viewer_or_skip()
    for size in VIEWER_SIZES:
        px = _viewer_screenshot(exe, served, size, tmp_path / f"viewer-{size[0]}")
        assert px.shape[:2] == (size[1], size[0])
        check_viewer_screenshot(px, status)
        _keep(f"viewer-{status}-{size[0]}x{size[1]}.png", px)


@pytest.fixture(scope="module")
def set_scene() -> setscene.Scene:
    return setscene.build()


@pytest.fixture
def served_set(set_scene: setscene.Scene) -> Iterator[RerunViewer]:
    """The daemon's viewer with a library of three plans and their set, fed the set's scene."""
    v = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=_free_port(), server_memory_limit="64MiB"),
                    plan=setscene.PLANS["xy"], plans=set_scene.config["plans"], sets=set_scene.config["sets"])
    try:
        assert v.seed(set_scene.earlier) == len(set_scene.earlier) - 1  # the tests, and the set
        _feed(v, set_scene.items)
        yield v
    finally:
        v.stop()


def check_set_screenshot(px: np.ndarray, set_status: str, test_status: str) -> None:
    """The first screen with a set: the machine's verdict bar in the set's colour across the top of the left
    column, above the last complete test's view with its own verdict bar in the test's colour."""
    h, w, _ = px.shape
    top = px[: int(0.16 * h), : int(0.6 * w)]
    bar = _near(top, STATUS_RGB[set_status], 30.0)
    ys, xs = np.nonzero(bar)
    assert xs.size > 0.002 * w * h, f"no {set_status} bar for the machine ({xs.size} pixels)"
    assert np.ptp(xs) > 0.35 * w, f"the machine's bar spans {np.ptp(xs)} px of {w}"
    # under it and the tabs' strip (each plan's latest test a tab): the last test's bar, in its colour alone
    below = int(ys.max()) + int(0.045 * h)
    left = px[:, : int(0.36 * w)]
    band = slice(below, below + int(0.08 * h))
    tys, txs = np.nonzero(_near(left[band], STATUS_RGB[test_status], 30.0))
    assert txs.size > 0.0004 * w * h, f"no {test_status} verdict bar over the last test ({txs.size} pixels)"
    for other, rgb in STATUS_RGB.items():
        if other not in (test_status, "none"):
            assert _near(left[band], rgb, 25.0).sum() < 0.2 * txs.size, f"{other} colour in the last test's bar"
    # its polar plot: the bar (3 R0 and its caps wide, at y = -1.9 R0) is the ruler; every curve inside 1.6 R0
    x0, x1 = float(np.percentile(txs, 0.5)), float(np.percentile(txs, 99.5))
    r0 = (x1 - x0) / 3.22
    cx, cy = (x0 + x1) / 2, below + float(np.median(tys)) + 1.9 * r0
    yy, xx = np.mgrid[0:h, 0 : left.shape[1]]
    dist = np.hypot(xx - cx, yy - cy) / r0
    curve = (_near(left, COLOURS["ccw"]) | _near(left, COLOURS["cw"])) & (dist < 2.2) & (yy > cy - 1.7 * r0)
    assert curve.sum() > 10 * r0, f"the last test's curves are not drawn ({curve.sum()} pixels)"
    reach = float(np.percentile(dist[curve], 99.9))
    assert reach <= 1.6 + 6.0 / r0, f"curves reach {reach:.3f} R0, beyond the outermost ring (1.6 R0)"
    assert cy + 1.7 * r0 < 0.8 * h and cx - 1.7 * r0 > 0, "the polar plot is cut by its view"


def check_live_of_a_set(px: np.ndarray) -> None:
    """Beside the last test, under the machine's bar: the test in progress, its status bar and its CCW curve."""
    h, w, _ = px.shape
    live = px[int(0.16 * h) : int(0.75 * h), int(0.38 * w) : int(0.58 * w)]
    bar = _near(live, (70, 74, 84), 12.0).sum()
    assert bar > 0.0004 * w * h, f"no status bar over the test in progress ({bar} pixels)"
    curve = _near(live, COLOURS["ccw"]).sum()
    assert curve > 0.0003 * w * h, f"the test in progress is not drawn ({curve} CCW pixels)"


def test_live_view_of_a_set(served_set: RerunViewer, set_scene: setscene.Scene, scene: livescene.Scene,
                            tmp_path: Path) -> None:
    """The set's live view in a viewer that showed a single plan's live view first (one viewer, a daemon
    restarted with a library of plans): every view healthy, no ERROR line (a view id that changed its class
    between the two layouts failed every frame), the set's bars, the last test and the test in progress."""
    exe = _viewer_or_skip()
    worst = max(setscene.STATUS.values(), key=("pass", "warning", "fail").index)
    last = setscene.STATUS["yz"]  # the last complete test is the set's third, yz; xy runs again
    items, earlier = livescene.annotated(scene, "pass")
    single = RerunViewer(ViewerOptions(mode="serve", bind="127.0.0.1", port=_free_port(),
                                       server_memory_limit="64MiB"), plan=livescene.PLAN)
    try:
        assert single.seed(earlier) == len(earlier)
        _feed(single, items)
        for size in VIEWER_SIZES:
            viewer = Viewer(exe, size, tmp_path / f"viewer-{size[0]}")
            try:
                check_viewer_screenshot(_pixels(viewer.shoot(single.address, single.recording_id), size), "pass")
                px = _pixels(viewer.shoot(served_set.address, served_set.recording_id), size)
            finally:
                viewer.close()
            _keep(f"viewer-set-{size[0]}x{size[1]}.png", px)
            check_set_screenshot(px, worst, last)
            check_live_of_a_set(px)
    finally:
        single.stop()


# --------------------------------------------------------------------------- the report


def _report_data(scene: livescene.Scene, status: str) -> ReportData:
    items, earlier = livescene.annotated(scene, status)
    result = copy.deepcopy(next(x for k, x in reversed(items) if k == "message" and x.get("kind") == "test"))
    curves = result.pop("curves", None)
    if curves is None:  # the stream's results carry no curves: the report's come from a re-analysis
        from ballbar.analysis.engine import analyze_recording

        t = np.concatenate([x.t_device for k, x in items if k == "batch"])
        L = np.concatenate([x.length_mm for k, x in items if k == "batch"])
        tests = [r for r in analyze_recording(t, L, livescene.PLAN, curves=True) if r.get("kind") == "test"]
        curves = tests[result["test_index"] - 1]["curves"]
    result["t_wall"] = earlier[-1]["t_wall"][:10] + "T23:00:00+00:00"
    return ReportData(result, curves, earlier, "20 earlier tests of mill-3 under the same conditions", "livescene",
                      meta={"operator": "A. Jones", "bar_serial": "QC20-1234", "bar_calibrated": "2026-01-15",
                            "machine_temperature_c": 21.5, "air_temperature_c": 20.5, "notes": "after the X gib"})


REPORT_FACTS = """(() => {
  const r = e => {
    if (!e) return null;
    const b = e.getBoundingClientRect();
    return [b.left, b.top, b.right, b.bottom];
  };
  const de = document.documentElement, badge = document.getElementById('verdict-status');
  const inside = (a, b) => a && b && a[0] >= b[0] - 1 && a[1] >= b[1] - 1 && a[2] <= b[2] + 1 && a[3] <= b[3] + 1;
  const points = [...document.querySelectorAll('[id^="trend-"][id$="-points"]')].map(g => {
    const area = document.getElementById(g.id.replace(/-points$/, '-area'));
    return [g.id, inside(r(g), r(area))];
  });
  const ring = r(document.getElementById('polar-outer-ring'));
  const curves = ['polar-ccw', 'polar-cw', 'polar-ccw-model', 'polar-cw-model'].map(
    id => [id, inside(r(document.getElementById(id)), ring)]);
  const wide = [...document.querySelectorAll('body *')].filter(e => {
    if (e.closest('.wide') || e.closest('svg')) return false;
    const b = e.getBoundingClientRect();
    return b.width > 0 && (b.right > de.clientWidth + 1 || b.left < -1);
  }).map(e => e.tagName + '#' + e.id + '.' + e.className);
  return {
    page: [de.scrollWidth, de.clientWidth],
    wide: wide.slice(0, 5),
    status: badge ? badge.textContent : null,
    colour: badge ? getComputedStyle(badge).backgroundColor : null,
    verdict: r(document.getElementById('verdict')),
    most: r(document.getElementById('verdict-most')),
    todo: r(document.getElementById('verdict-todo')),
    curves, points,
  };
})()"""

CSS_RGB = {"fail": "rgb(180, 35, 24)", "warning": "rgb(178, 94, 9)", "pass": "rgb(29, 122, 70)"}


@pytest.fixture(scope="module")
def reports(scene: livescene.Scene, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The three reports, rendered before any leak check starts watching (matplotlib keeps its fonts open)."""
    d = tmp_path_factory.mktemp("reports")
    return {s: render(_report_data(scene, s), d / f"{s}.html", png=False)[0] for s in STATUSES}


def test_report_screenshots(reports: dict[str, Path], no_leaks: None) -> None:
    exe = find_chromium()
    if exe is None:
        _required("Chromium not found ($BALLBAR_CHROMIUM, chromium on PATH or /usr/bin/chromium)")
    assert exe is not None
    with Chromium(exe, 120.0, window=(REPORT_WIDTHS[0], REPORT_HEIGHT)) as browser:
        session = browser.open_page()
        for status in STATUSES:
            for width in REPORT_WIDTHS:
                browser.call("Emulation.setDeviceMetricsOverride",
                             {"width": width, "height": REPORT_HEIGHT, "deviceScaleFactor": 1, "mobile": False},
                             session)
                browser.load(session, reports[status].as_uri())
                f = browser.evaluate(session, REPORT_FACTS)
                where = f"{status} at {width} px"
                assert f["page"][0] <= f["page"][1] and f["wide"] == [], (where, f["page"], f["wide"])
                assert f["status"] == STATUS_WORDS[status] and f["colour"] == CSS_RGB[status], (where, f)
                # the first screen says it: the verdict from the top, what matters most and what to do on it
                assert f["verdict"][1] < 0.25 * REPORT_HEIGHT, (where, f["verdict"])
                assert f["most"][3] < REPORT_HEIGHT and f["todo"][1] < REPORT_HEIGHT, (where, f["most"], f["todo"])
                assert all(ok for _id, ok in f["curves"]) and len(f["curves"]) == 4, (where, f["curves"])
                assert f["points"] and all(ok for _id, ok in f["points"]), (where, f["points"])
                px = _pixels(browser.screenshot(session))
                assert px.shape[:2] == (REPORT_HEIGHT, width)
                want = np.array([int(c) for c in re.findall(r"\d+", CSS_RGB[status])])
                assert (np.abs(px.astype(int) - want).sum(axis=2) < 20).sum() > 2000, where  # the badge, in colour
                _keep(f"report-{status}-{width}.png", px)
        assert browser.errors(session) == []


# --------------------------------------------------------------------------- the same words, live and filed


def test_live_view_and_report_rank_the_same_test_alike(reports: dict[str, Path], scene: livescene.Scene) -> None:
    """For the same test, the live view's findings and the report name the same machine errors in the same order
    with the same shares of the machine's error, and state the set-up apart in both."""
    items, _earlier = livescene.annotated(scene, "fail")
    result = next(x for k, x in reversed(items) if k == "message" and x.get("kind") == "test")
    md = findings_markdown(result)
    live = re.findall(r"^\d+\. \*\*(.+?)\*\* (.+?): ", md, flags=re.M)
    html = reports["fail"].read_text(encoding="utf-8")
    most = html[html.index('id="verdict-most"'):html.index("</ol>", html.index('id="verdict-most"'))]
    filed = re.findall(r"<li><b>(.+?)</b>:.*?\((.+?) of the machine", most)
    ranking = [r for r in machine_ranking(result) if r.get("significant")]
    expected = [(pattern_label(str(r["pattern"])), share_text(r["machine_share_pct"])) for r in ranking]
    assert live[: len(filed)] == filed == expected[: len(filed)] and len(filed) >= 2, (live, filed, expected)
    assert len(live) == min(5, len(expected))
    # set-up terms in neither ranking; shares of the machine's error sum to 100 % over the machine's patterns
    assert not any("set-up" in name.lower() or "centre" in name.lower() for name, _s in live + filed)
    assert abs(sum(r["machine_share_pct"] for r in machine_ranking(result)) - 100.0) < 1e-6
    assert "Set-up, not the machine" in md and "Set-up, not the machine" in html


def test_the_committed_screenshots_are_there_and_small() -> None:
    """The README's pictures: every status and size, each a valid PNG of the window's size under 400 kB."""
    for status in STATUSES:
        for w, h in VIEWER_SIZES:
            _check_png(ARTEFACTS / f"viewer-{status}-{w}x{h}.png", (w, h))
        for width in REPORT_WIDTHS:
            _check_png(ARTEFACTS / f"report-{status}-{width}.png", (width, REPORT_HEIGHT))
    for w, h in VIEWER_SIZES:
        _check_png(ARTEFACTS / f"viewer-set-{w}x{h}.png", (w, h))


def _check_png(path: Path, size: tuple[int, int]) -> None:
    assert path.exists(), f"{path.name} missing: BALLBAR_SCREENSHOTS=1 pytest tests/test_screens.py makes it"
    blob = path.read_bytes()
    assert len(blob) < 400_000, (path.name, len(blob))
    px = _pixels(blob)
    assert px.shape[:2] == (size[1], size[0]), path.name
    assert len(np.unique(px.reshape(-1, 3), axis=0)) > 16, f"{path.name} is nearly blank"


