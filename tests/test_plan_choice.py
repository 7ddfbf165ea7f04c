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
from test_bus import client, get, iso, running_bus, wait_until, zenoh_runtime  # noqa: F401 - its runtime, made once
from test_e2e import Daemon as DaemonProcess
from test_e2e import free_port, recordings
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


def _set_daemon(tmp_path: Path, url: str) -> tuple[Daemon, Recorder]:
    """A daemon of the set's library reading the zx program from ``url`` (the simulated device), all it sends
    recorded; nothing on disk, no bus, no viewer, the fit inline."""
    f = tmp_path / "set.toml"
    f.write_text(SET)
    cfg = load(str(f), ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"',
                        "daemon.analysis_worker=false", f'daemon.state_dir="{tmp_path}"'], env={})
    rec = Recorder()
    src = open_source(url, library=cfg.library, run_plans=["zx"])
    return Daemon(cfg, src, [(rec, 10_000, "drop_newest")]), rec


def test_the_chosen_plan_is_the_next_tests_and_a_bad_name_is_refused(tmp_path: Path) -> None:
    """Two tests of the zx program (its signature before each feed-in): the first is analysed as yz, chosen
    before it; the second as zx again (a choice is for the next test only).  A name the library lacks is
    refused with an event, and changes nothing."""
    d, rec = _set_daemon(tmp_path, "sim:?speedup=max&rate=100&repeat=2&gap_s=3")
    d.choose_plan("nope")
    d.choose_plan("yz")
    stop = threading.Event()
    assert d.run(stop, max_tests=2) == 0
    events = [m for m in rec.messages if m.get("event") in ("plan_chosen", "plan_choice_refused")]
    assert [(e["event"], e.get("plan")) for e in events] == [("plan_choice_refused", None), ("plan_chosen", "yz")]
    assert "no plan 'nope' in the library (zx, yz)" in events[0]["message"]
    tests = [m for m in rec.messages if m.get("kind") == "test"]
    assert [(t["plan"]["name"], t["recognition"]["method"]) for t in tests] == [("yz", "chosen"), ("zx", "signature")]
    assert tests[0]["recognition"]["signature"] == d.cfg.library.get("zx").signature
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
        for p in hostile:  # BLOCK: Zenoh's default (DROP) may lose some of a fast burst on a loaded machine
            s.put("ballbar/ctl/control/next_plan", p, congestion_control=zenoh.CongestionControl.BLOCK)
        s.put("ballbar/ctl/control/next_plan", "zx")  # a real choice after the flood still arrives
        wait_until(lambda: got == ["zx"], what="the real choice")
        assert bus.stats()["controls_refused"] == len(hostile) and bus.stats()["controls"] == 1
    lines = [r for r in caplog.records if "next_plan" in r.getMessage()]
    assert len([r for r in lines if "refused" in r.getMessage()]) == 1, [r.getMessage()[:100] for r in lines]
    assert all(len(r.getMessage()) < 300 for r in lines)


def test_well_shaped_puts_beyond_the_rate_are_dropped_and_counted(caplog: pytest.LogCaptureFixture) -> None:
    """200 valid names as fast as a peer can put them: the burst and the rate are handed on, the rest dropped,
    counted and told in one log line (and one more at the stop for the flood's tail)."""
    from ballbar.daemon.bus import CONTROL_BURST, CONTROL_RATE_HZ

    got: list[Any] = []
    with caplog.at_level("INFO", logger="ballbar.daemon.bus"), running_bus("ctl") as (bus, ep), client(ep) as s:
        bus.bind_control(got.append)
        time.sleep(0.5)  # the subscription propagates
        t0 = time.monotonic()
        for i in range(200):
            s.put("ballbar/ctl/control/next_plan", f"plan{i}", congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: bus.stats()["controls"] + bus.stats()["controls_dropped"] == 200, what="every put")
        took = time.monotonic() - t0
        stats = bus.stats()
    assert CONTROL_BURST <= len(got) == stats["controls"] <= CONTROL_BURST + CONTROL_RATE_HZ * took, (len(got), took)
    assert stats["controls_dropped"] == 200 - len(got)
    assert got[:CONTROL_BURST] == [f"plan{i}" for i in range(CONTROL_BURST)]  # the first ones, in order
    floods = [r.getMessage() for r in caplog.records if "a flood" in r.getMessage()]
    assert 1 <= len(floods) <= 2, floods
    assert sum(int(m.split("a flood: ")[1].split()[0]) for m in floods) == stats["controls_dropped"], floods


def test_answers_to_the_control_key_never_push_the_machines_events_out_of_history() -> None:
    """history/event of 5: three machine events, then 300 plan_choice_refused answers: the three are still
    there, and the answers are the newest CONTROL_HISTORY of them, merged in time order."""
    from ballbar.daemon.bus import CONTROL_HISTORY

    def event(name: str, i: int) -> dict[str, Any]:
        return {"kind": "event", "event": name, "schema_version": 1, "machine_id": "ctl", "t_wall": iso(i),
                "test_id": f"ctl-{i}", "message": "x"}

    with running_bus("ctl", history_size=5) as (bus, ep), client(ep) as s:
        for i, name in enumerate(["feed_in", "feed_out", "device_reset"]):
            bus.on_message(event(name, i))
        for i in range(300):
            bus.on_message(event("plan_choice_refused", 10 + i))
        (reply,), _err = get(s, "ballbar/ctl/history/event?limit=1000")
        stats = bus.stats()
    body = json.loads(reply.payload.to_bytes())
    names = [r["event"] for r in body["results"]]
    assert names[:3] == ["feed_in", "feed_out", "device_reset"]
    assert names[3:] == ["plan_choice_refused"] * CONTROL_HISTORY
    assert body["results"][-1]["test_id"] == "ctl-309"
    assert body["results"][3]["test_id"] == f"ctl-{310 - CONTROL_HISTORY}"
    assert stats["history"]["event"] == 3 and stats["history_controls"] == CONTROL_HISTORY


def test_a_rogue_peers_flood_of_valid_names_leaves_the_machines_events_and_a_bounded_trace(tmp_path: Path) -> None:
    """The daemon as a process on the simulated device, a test done, then a rogue peer puts 5 000 well-shaped
    names (the library's plan, names it lacks, withdrawals) as fast as it can.  Afterwards history/event still
    holds the test's feed_in and feed_out; the status counts every put (taken or dropped); the choices taken are
    at most CONTROL_BURST + CONTROL_RATE_HZ a second of the flood, and the log and the MCAP hold no more
    control lines and events than that (plus the flood's few summary lines); before: 5 000 of each."""
    from ballbar.daemon.bus import CONTROL_BURST, CONTROL_HISTORY, CONTROL_LOG_S, CONTROL_RATE_HZ

    port = free_port()
    daemon = DaemonProcess(tmp_path, "sim:?rate=1000&speedup=20&repeat=0", port)
    n = 5000
    try:
        daemon.wait_ready()
        with client(f"tcp/127.0.0.1:{port}") as s:
            def history() -> list[dict[str, Any]]:
                ok, _err = get(s, "ballbar/e2e/history/event?limit=1000")
                return json.loads(ok[0].payload.to_bytes())["results"] if ok else []

            def status() -> dict[str, Any]:
                ok, _err = get(s, "ballbar/e2e/last/status")
                return json.loads(ok[0].payload.to_bytes())["outputs"]["zenoh"] if ok else {}

            wait_until(lambda: any(e.get("event") == "feed_out" for e in history()), timeout=120,
                       what="a test's feed-out")
            own = [(e["event"], e["test_id"]) for e in history() if e.get("event") in ("feed_in", "feed_out")]
            time.sleep(0.5)
            t0 = time.monotonic()
            for i in range(n):
                s.put("ballbar/e2e/control/next_plan",
                      ["default", f"nope{i}", json.dumps({"plan": None}), json.dumps({"plan": f"p{i}"})][i % 4],
                      congestion_control=zenoh.CongestionControl.BLOCK)  # every one arrives: counted exactly
            wait_until(lambda: status().get("controls", 0) + status().get("controls_dropped", 0) >= n, timeout=30,
                       what="the status counting every put")
            took = time.monotonic() - t0
            z = status()
            after = history()
        code, _t = daemon.terminate(timeout=20)
        text = daemon.output()
    finally:
        daemon.close()
    assert code == 0, text[-3000:]
    taken = z["controls"]
    bound = CONTROL_BURST + CONTROL_RATE_HZ * took
    assert CONTROL_BURST <= taken <= bound and z["controls"] + z["controls_dropped"] == n, (z, took)
    kept = [(e["event"], e["test_id"]) for e in after if e.get("event") in ("feed_in", "feed_out")]
    assert own and set(own) <= set(kept), (own, kept)
    answers = [e for e in after if e.get("event") in ("plan_chosen", "plan_choice_refused")]
    assert 1 <= len(answers) <= min(taken, CONTROL_HISTORY)
    recorded = [e for e in recordings(tmp_path).events if e.get("event") in ("plan_chosen", "plan_choice_refused")]
    assert 1 <= len(recorded) <= taken, len(recorded)
    lines = [ln for ln in text.splitlines() if "next_plan" in ln or "next plan" in ln]
    floods = [ln for ln in lines if "a flood" in ln]
    assert 1 <= len(floods) <= 2 + took / CONTROL_LOG_S, floods
    # each choice taken: one line as the bus takes it, at most two as the analysis answers (its line, the event's)
    assert len(lines) - len(floods) <= 3 * taken, lines[:20]
    assert sum(int(ln.split("a flood: ")[1].split()[0]) for ln in floods) == z["controls_dropped"], floods


def test_a_repeat_of_the_choice_standing_makes_no_event(tmp_path: Path) -> None:
    """yz, yz, withdrawn, withdrawn again: two answers, not four (each answer is an event on the bus, a log line
    and an MCAP record)."""
    d, rec = _set_daemon(tmp_path, "sim:?speedup=max&rate=100&repeat=1")
    for name in ("yz", "yz", None, None):
        d.choose_plan(name)
    assert d.run(threading.Event(), max_tests=1) == 0
    events = [(m["event"], m.get("plan")) for m in rec.messages if m.get("event") in ("plan_chosen",
                                                                                     "plan_choice_refused")]
    assert events == [("plan_chosen", "yz"), ("plan_chosen", None)]
    (test,) = [m for m in rec.messages if m.get("kind") == "test"]
    assert test["recognition"]["method"] == "signature"  # the withdrawal stood


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
