"""The explicit choice of the next test's plan: a put on ``ballbar/<m>/control/next_plan``, taken by the daemon's
analysis in order with the samples (the secure setup's part: tests/test_zenoh_secure.py)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh
from schemacheck import validate
from test_bus import client, running_bus, wait_until, zenoh_runtime  # noqa: F401 - its runtime, made once
from test_monitor import _Recorder as Recorder

from ballbar.analysis.plans import PlanLibrary
from ballbar.daemon.config import load
from ballbar.daemon.service import Daemon
from ballbar.daemon.sources import open_source

pytestmark = pytest.mark.usefixtures("no_leaks")

SET = """
[plans.zx]
plane = "ZX"
start_deg = -115.0
overshoot_deg = 5.0
data_arc_deg = 220.0
sample_hz = 100.0

[plans.yz]
plane = "YZ"
start_deg = -25.0
overshoot_deg = 5.0
data_arc_deg = 220.0
sample_hz = 100.0
"""


def test_a_put_on_the_control_key_reaches_the_daemon() -> None:
    got: list[Any] = []
    with running_bus("ctl") as (bus, ep), client(ep) as s:
        bus.bind_control(got.append)
        time.sleep(0.5)  # the subscription propagates
        s.put("ballbar/ctl/control/next_plan", json.dumps({"plan": "yz"}), encoding=zenoh.Encoding.APPLICATION_JSON)
        s.put("ballbar/ctl/control/next_plan", "zx")  # the bare name
        s.put("ballbar/ctl/control/next_plan", "null")  # withdrawn
        s.put("ballbar/other/control/next_plan", "zx")  # another machine's
        wait_until(lambda: len(got) >= 3, what="three choices")
        time.sleep(0.3)
        assert bus.stats()["controls"] == 3
    assert got == ["yz", "zx", None]


def test_the_chosen_plan_is_the_next_tests_and_a_bad_name_is_refused(tmp_path: Path) -> None:
    """Two tests of the zx program (its signature before each feed-in): the first is analysed as yz, chosen
    before it; the second as zx again (a choice is for the next test only).  A name the library lacks is
    refused with an event, and changes nothing."""
    f = tmp_path / "set.toml"
    f.write_text(SET)
    cfg = load(str(f), ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"',
                        "daemon.analysis_worker=false", f'daemon.state_dir="{tmp_path}"'], env={})
    rec = Recorder()
    src = open_source("sim:?speedup=max&rate=100&repeat=2&gap_s=3", library=cfg.library, run_plans=["zx"])
    d = Daemon(cfg, src, [(rec, 10_000, "drop_newest")])
    d.choose_plan("nope")
    d.choose_plan("yz")
    stop = threading.Event()
    assert d.run(stop, max_tests=2) == 0
    events = [m for m in rec.messages if m.get("event") in ("plan_chosen", "plan_choice_refused")]
    assert [(e["event"], e.get("plan")) for e in events] == [("plan_choice_refused", None), ("plan_chosen", "yz")]
    assert "no plan 'nope' in the library (zx, yz)" in events[0]["message"]
    tests = [m for m in rec.messages if m.get("kind") == "test"]
    assert [(t["plan"]["name"], t["recognition"]["method"]) for t in tests] == [("yz", "chosen"), ("zx", "signature")]
    assert tests[0]["recognition"]["signature"] == cfg.library.get("zx").signature
    feed_ins = [m for m in rec.messages if m.get("event") == "feed_in"]
    assert [e["plan"] for e in feed_ins] == ["yz", "zx"]


def test_a_live_test_of_no_plan_gets_no_result_and_an_event_with_the_candidates(tmp_path: Path) -> None:
    """The daemon, live: a program of another configuration (its signature no plan carries, zx's timing) is
    analysed as no plan; its event says why and names the plans its timing fits, and matches its schema."""
    f = tmp_path / "set.toml"
    f.write_text(SET)
    cfg = load(str(f), ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"',
                        "daemon.analysis_worker=false", f'daemon.state_dir="{tmp_path}"'], env={})
    zx = cfg.library.get("zx")
    code = next(c for c in range(125) if cfg.library.by_signature(c) is None)
    other = PlanLibrary.from_plans({"other": zx.plan, "xy": zx.plan.with_(plane="XY")},
                                   {"other": code, "xy": None})  # the simulated device runs a library of two
    rec = Recorder()
    src = open_source("sim:?speedup=max&rate=100&repeat=1", library=other, run_plans=["other"])
    d = Daemon(cfg, src, [(rec, 10_000, "drop_newest")])
    d.run(threading.Event(), duration_s=600)
    assert not [m for m in rec.messages if m.get("kind") in ("test", "circle")]
    (ev,) = [m for m in rec.messages if m.get("event") == "test_unrecognised"]
    validate(ev)
    assert ev["reason"] == "no_match" and ev["signature"] == code and sorted(ev["candidates"]) == ["yz", "zx"]
    assert f"code {code}" in ev["message"]


@pytest.mark.parametrize(
    ("payload", "why"),
    [
        (b"[" * 200_000 + b"]" * 200_000, "bytes, more than 1024"),
        (b"[" * 500 + b"]" * 500, "a plan's name is a string, not list"),
        (b'{"foo": 1}', "the key 'plan' alone (it has 'foo')"),
        (b'{"plan": "xy", "also": 2}', "the key 'plan' alone"),
        (b'{"plan": 7}', "not int"),
        (b"42", "not int"),
        (b'{"plan": ', "not valid JSON"),
        (b"two words", "not a plan's name"),
        (b"x" * 65, "not a plan's name"),
        (b'"\\u0007bell"', "not a plan's name"),
    ],
)
def test_the_control_key_refuses_what_is_not_its_documented_shape(payload: bytes, why: str) -> None:
    from ballbar.daemon.bus import parse_control

    name, reason = parse_control(payload)
    assert name is None and reason is not None and why in reason and len(reason) < 200, reason


def test_the_documented_shapes_of_the_control_key() -> None:
    from ballbar.daemon.bus import parse_control

    assert [parse_control(p) for p in (b'{"plan": "zx"}', b'"zx"', b"zx", b"null", b'{"plan": null}')] == [
        ("zx", None), ("zx", None), ("zx", None), (None, None), (None, None)]


def test_a_flood_of_hostile_puts_hands_on_nothing_and_logs_one_line(caplog: pytest.LogCaptureFixture) -> None:
    """A deep JSON (a RecursionError traceback before), no 'plan' key (read as a withdrawal before), 1 MB names:
    none reaches the analysis, the counter says how many, and 2 000 of them make one log line, not thousands."""
    got: list[Any] = []
    hostile = [b"[" * 200_000 + b"]" * 200_000, b'{"foo": 1}', b"n" * 1_000_000] + [b'{"x": 1}'] * 1997
    with caplog.at_level("INFO", logger="ballbar.daemon.bus"), running_bus("ctl") as (bus, ep), client(ep) as s:
        bus.bind_control(got.append)
        time.sleep(0.5)  # the subscription propagates
        for p in hostile:
            s.put("ballbar/ctl/control/next_plan", p)
        s.put("ballbar/ctl/control/next_plan", "zx")  # a real choice after the flood still arrives
        wait_until(lambda: got == ["zx"], what="the real choice")
        assert bus.stats()["controls_refused"] == len(hostile) and bus.stats()["controls"] == 1
    lines = [r for r in caplog.records if "next_plan" in r.getMessage()]
    assert len([r for r in lines if "refused" in r.getMessage()]) == 1, [r.getMessage()[:100] for r in lines]
    assert all(len(r.getMessage()) < 300 for r in lines)


def test_analyze_and_report_of_a_recorded_test_take_the_plan_a_service_chose(tmp_path: Path) -> None:
    """The zx program (its signature says zx) analysed live as yz, the plan a service chose for it: the choice
    is recorded (a ``plan_chosen`` event, the result's recognition), and ``ballbar analyze DIR --test-id`` and
    ``ballbar report DIR --test 1``, run as processes, analyse it as yz again, not as its signature says."""
    import subprocess
    import sys

    from ballbar.daemon.mcap import McapLogger

    f = tmp_path / "set.toml"
    f.write_text(SET)
    state = tmp_path / "state"
    cfg = load(str(f), ["zenoh.enabled=false", 'rerun.mode="off"', "daemon.analysis_worker=false",
                        f'daemon.state_dir="{state}"'], env={})
    src = open_source("sim:?speedup=max&rate=100&repeat=1", library=cfg.library, run_plans=["zx"])
    d = Daemon(cfg, src, [(McapLogger.from_config(cfg), 10_000, "drop_newest")])
    d.choose_plan("yz")
    assert d.run(threading.Event(), max_tests=1) == 0
    records = state / "recordings"
    listed = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(records), "--list", "--json"],
                            capture_output=True, text=True, timeout=120)
    (row,) = json.loads(listed.stdout)
    assert row["status"] == "complete" and row["plan"] == "yz", listed.stderr

    out = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(records), "--test-id",
                          row["test_id"], "--json"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)
    assert (result["plan"]["name"], result["recognition"]["method"]) == ("yz", "chosen")
    assert result["plan"]["plane"] == "YZ"

    html = tmp_path / "report.html"
    rep = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "report", str(records), "--test", "1",
                          "-o", str(html), "--no-png"], capture_output=True, text=True, timeout=300)
    assert rep.returncode == 0, rep.stderr
    assert "ambiguous" not in rep.stderr and "YZ" in html.read_text()
