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
