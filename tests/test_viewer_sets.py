"""The live view of a library of plans and their set: each plan's latest test and trends apart, the machine's
verdict from the set, as a real rerun process receives them (tests/setscene.py's scene)."""

from __future__ import annotations

import re
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import setscene
from test_viewer import RERUN, Receiver, free_port, last, read_rrd, texts

from ballbar.daemon.rerun import RerunViewer, ViewerOptions, default_blueprint
from ballbar.daemon.rerun.findings import set_headline, set_markdown

pytestmark = [pytest.mark.usefixtures("no_leaks"),
              pytest.mark.skipif(RERUN is None, reason="the rerun CLI binary is not installed")]


@pytest.fixture(scope="module")
def scene() -> setscene.Scene:
    return setscene.build()


# "connected first": a viewer that answers the constructor's first probe gets its sink before the daemon seeds the
# earlier tests; it missed the seeded trends (one trend point of eleven, one run in three under load) until the
# seeding sent the scene again.
@pytest.mark.parametrize("order", ["seeded first", "connected first"])
def test_each_plan_and_the_set_reach_the_viewer(scene: setscene.Scene, tmp_path: Path, order: str) -> None:
    port = free_port()
    rx = Receiver(tmp_path, "rx", port)
    try:
        v = RerunViewer(ViewerOptions(mode="connect", url=f"rerun+http://127.0.0.1:{port}/proxy", retry_s=0.1),
                        plan=setscene.PLANS["xy"], plans=scene.config["plans"], sets=scene.config["sets"])

        def connect() -> None:
            deadline = time.monotonic() + 10.0
            while not v.connected:
                assert time.monotonic() < deadline, "the viewer did not connect"
                v.on_idle()
                time.sleep(0.02)

        if order == "connected first":
            connect()
        assert v.seed(scene.earlier) == len(scene.earlier) - 1  # as the daemon does, at its start
        connect()
        for kind, x in scene.items:
            (v.on_batch if kind == "batch" else v.on_message)(x)
        v.on_idle()
        assert v.stats()["errors"] == 0
        v.stop()
        rx.finish()
    finally:
        rx.close()
    saved = read_rrd(rx.rrd)
    for p in setscene.PLANS:  # each plan's latest test in its own view, and its trends apart
        for entity in (f"/plans/{p}/ccw/measured", f"/plans/{p}/cw/model", f"/plans/{p}/verdict",
                       f"/plans/{p}/trends/backlash_um/x", f"/plans/{p}/trends/backlash_um/x/limits"):
            assert saved.rows.get(entity, 0) > 0, (entity, sorted(e for e in saved.rows if "plans" in e))
        bar = " ".join(texts(saved, f"/plans/{p}/verdict/text", "Points2D:labels"))
        assert f"{p} test" in bar and setscene.STATUS[p].upper() in bar, bar
    assert not any(e.startswith("/trends/") for e in saved.rows)  # no trend mixing the planes
    # each plan's axes on its view; the last test's view takes the axes of the plan it shows
    assert last(saved, "/plans/zx/reference/axis_labels", "Points2D:labels") == ["+Z", "+X"]
    assert last(saved, "/polar/reference/axis_labels", "Points2D:labels") == ["+Y", "+Z"]  # yz, the last
    check_last_test_axes(rx.rrd)
    assert last(saved, "/live/reference/axis_labels", "Points2D:labels") == ["+X", "+Y"]  # xy, in progress
    # the machine's verdict: the set's bar and the head of the findings
    assert "FAIL · set machine: xy pass, zx fail, yz warning" in " ".join(texts(saved, "/set/verdict/text",
                                                                                "Points2D:labels"))
    doc = last(saved, "/findings", "TextDocument:text")
    doc = "".join(doc) if isinstance(doc, list) else str(doc)
    assert doc.startswith("## Machine: FAIL · set machine") and "## WARNING · test 3" in doc
    # the trends of a plan are that plan's tests alone: ten earlier ones and today's
    xs = [x for x in saved.columns["/plans/zx/trends/backlash_um/x"]["Scalars:scalars"] if x is not None]
    assert len(xs) == 11, xs


def _rows_at(path: Path, entity: str, column: str) -> tuple[list[tuple[int, Any]], int]:
    """``entity``'s values of ``column`` with their times on the ``time`` timeline (ns), in time order; and how
    many rows of it are static."""
    import warnings

    from rerun.chunk import RrdReader

    rows: list[tuple[int, Any]] = []
    static = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a file saved by --save has no footer
        for ch in RrdReader(path).stream():
            if str(ch.entity_path) != entity:
                continue
            rb = ch.to_record_batch()
            if column not in rb.schema.names:
                continue
            if ch.is_static:
                static += ch.num_rows
                continue
            times = rb.column("time").cast("int64").to_pylist()
            rows += [(t, v) for t, v in zip(times, rb.column(column).to_pylist(), strict=True) if v is not None]
    return sorted(rows, key=lambda r: r[0]), static


def check_last_test_axes(path: Path) -> None:
    """At the time of each test the last test's view draws (its verdict bar names the plan), the view's axis
    labels are that plan's plane's: the first axis to the right, the second up (as each plan's own view)."""
    from ballbar.analysis.plan import PLANE_AXES

    labels, static = _rows_at(path, "/polar/reference/axis_labels", "Points2D:labels")
    assert static == 0 and labels, (static, len(labels))  # a static label would shadow every test's own
    bars, _ = _rows_at(path, "/polar/verdict/text", "Points2D:labels")
    shown = 0
    for t, text in bars:
        m = re.search(r"· (\w+) test (\d+)", " ".join(text))
        assert m, text
        a, b = PLANE_AXES[setscene.PLANS[m.group(1)].plane]
        at = [v for tl, v in labels if tl <= t]
        assert at and at[-1] == [f"+{a}", f"+{b}"], (text, at[-1:] if at else None)
        shown += 1
    assert shown >= 3  # xy, zx and yz at least


def test_the_sets_words() -> None:
    s: dict[str, Any] = setscene.set_message({r["plan"]["name"]: r for r in setscene.earlier(
        {n: setscene.build().results[n] for n in setscene.PLANS})[-4:-1]})
    status, text = set_headline(s)
    assert status == "fail" and text == ("FAIL · set machine: xy pass, zx fail, yz warning; the planes' "
                                                "figures agree (5 of 5 consistency checks)")
    md = set_markdown(s)
    assert "| X |" in md and "Squareness µrad: XY" in md and "geometric sphericity" in md
    # no plan with limits, every check passed: no limits set, grey, as a test's
    for m in s["tests"]:
        m["verdict"] = "not_evaluated"
    assert set_headline(s)[0] == "none"
    s["verdict"]["trusted"] = False
    assert set_headline(s)[0] == "fail"


def test_the_layout_of_a_library_builds() -> None:
    bp = default_blueprint({"xy/backlash_um": (0.0, 5.0)}, {"xy": ("X", "Y"), "zx": ("Z", "X")})
    assert bp is not None
    assert np.isfinite(5.0)


def test_an_id_names_one_kind_of_view_in_every_layout() -> None:
    """A viewer keeps a view's state by its id across recordings: the single plan's layout and the libraries'
    (of two and three plans) never give one id to views of two classes (or containers of two kinds)."""
    import rerun.blueprint as rrb

    from ballbar.analysis.plan import PLANE_AXES
    from ballbar.daemon.rerun.blueprint import stable_ids

    kinds: dict[str, set[str]] = {}

    def walk(item: Any) -> None:
        kind = type(item).__name__ if isinstance(item, rrb.Container) else str(item.class_identifier)
        kinds.setdefault(str(item.id), set()).add(kind)
        if isinstance(item, rrb.Container):
            for sub in item.contents:
                walk(sub)

    layouts = [default_blueprint(), default_blueprint(None, {"xy": ("X", "Y"), "zx": ("Z", "X")}),
               default_blueprint(None, {p: PLANE_AXES[plan.plane] for p, plan in setscene.PLANS.items()})]
    for bp in layouts:
        root = bp.to_blueprint().root_container
        stable_ids(root, "root")
        walk(root)
    assert len(kinds) > 30
    assert all(len(k) == 1 for k in kinds.values()), {i: k for i, k in kinds.items() if len(k) > 1}
