"""The daemon's sets (daemon/sets.py): sent once when a set's tests are in, kept across a restart, published on
the bus (result/set, last/set, history/set) and recorded on the MCAP results channel."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import pytest
from schemacheck import problems, validate_recordings
from test_bus import client, get, running_bus, wait_until, zenoh_runtime  # noqa: F401 - its autouse warm-up
from test_sets import PLANS, run_plan

from ballbar.analysis import sets as aset
from ballbar.daemon.mcap import McapLogger, list_recordings, read_results
from ballbar.daemon.sets import SetListener

pytestmark = pytest.mark.usefixtures("no_leaks")

DEFS = aset.definitions({"machine": {"plans": ["xy", "zx", "yz"], "window_minutes": 60},
                         "horizontal": {"plans": ["xy"], "window_minutes": 5}})


@pytest.fixture(scope="module")
def tests3() -> dict[str, dict[str, Any]]:
    return {name: run_plan(name, i) for i, name in enumerate(PLANS)}


def feed(listener: SetListener, *msgs: dict[str, Any]) -> list[dict[str, Any]]:
    sent: list[dict[str, Any]] = []
    listener.bind(sent.append)
    for m in msgs:
        listener.on_message({**m, "kind": "test", "machine_id": "m"})
    return sent


def later(r: dict[str, Any], test_id: str, t_wall: str) -> dict[str, Any]:
    out = copy.deepcopy(r)
    out["test_id"], out["t_wall"] = test_id, t_wall
    return out


def test_a_set_is_sent_once_its_tests_are_in(tests3: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    lst = SetListener(DEFS, "m", tmp_path)
    # xy alone makes the one-plan set; the machine set waits for zx and yz
    sent = feed(lst, tests3["xy"], tests3["zx"])
    assert [s["set"]["name"] for s in sent] == ["horizontal"]
    sent = feed(lst, tests3["yz"])
    assert [s["set"]["name"] for s in sent] == ["machine"]
    s = sent[0]
    assert s["kind"] == "set" and s["machine_id"] == "m" and s["t_wall"].endswith("Z")
    assert s["set_id"] == f"machine@{tests3['yz']['test_id']}"
    assert problems(json.loads(json.dumps(s))) == []
    # the same test again: nothing new to send
    assert feed(lst, tests3["yz"]) == []
    # a test of a plan in no set, a circle: ignored
    assert feed(lst, {**tests3["xy"], "plan": {**tests3["xy"]["plan"], "name": "other"}}) == []
    lst.on_message({**tests3["xy"], "kind": "circle"})
    # xy run again within the window: a new set of each that names it, with the others' latest
    again = later(tests3["xy"], "m-20260104T000000Z", "2026-01-01T00:10:00.000Z")
    sent = feed(lst, again)
    assert sorted(s["set"]["name"] for s in sent) == ["horizontal", "machine"]
    machine = next(s for s in sent if s["set"]["name"] == "machine")
    assert [t["test_id"] for t in machine["tests"]] == [again["test_id"], tests3["zx"]["test_id"],
                                                       tests3["yz"]["test_id"]]
    # ... and outside the window: the one-plan set only
    late = later(tests3["xy"], "m-20260105T000000Z", "2026-01-01T03:00:00.000Z")
    assert [s["set"]["name"] for s in feed(lst, late)] == ["horizontal"]
    assert lst.stats() == {"tests": 6, "sets": 5, "errors": 0}


def test_a_restart_keeps_the_tests_and_sends_nothing_twice(tests3: dict[str, dict[str, Any]], tmp_path: Path,
                                                           ) -> None:
    first = SetListener(DEFS, "m", tmp_path)
    assert len(feed(first, *tests3.values())) == 2
    second = SetListener(DEFS, "m", tmp_path)  # the state file
    assert set(second.latest) == {"xy", "zx", "yz"}
    assert feed(second, tests3["yz"]) == []
    assert [s["set"]["name"] for s in feed(second, later(tests3["zx"], "m-9", "2026-01-01T00:11:00.000Z"))] == [
        "machine"]
    # the first start after an update: no state file, seeded from the records (tests, and the sets already sent)
    records = [*({**t, "kind": "test", "machine_id": "m"} for t in tests3.values())]
    made = feed(SetListener(DEFS, "m", tmp_path / "a"), *tests3.values())
    seeded = SetListener(DEFS, "m", tmp_path / "b", seed=lambda: [*records, *made])
    assert feed(seeded, tests3["yz"]) == []
    unsent = SetListener(DEFS, "m", tmp_path / "c", seed=lambda: records)  # recorded tests, no set: it is due
    assert [s["set"]["name"] for s in feed(unsent, tests3["yz"])] == ["machine"]


def test_a_damaged_state_file_starts_afresh(tests3: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    path = tmp_path / "sets" / "m-sets.json"
    path.parent.mkdir()
    path.write_text("{not json")
    lst = SetListener(DEFS, "m", tmp_path)
    assert lst.latest == {} and len(feed(lst, *tests3.values())) == 2
    assert json.loads(path.read_text())["sent"]["machine"]


def test_the_bus_publishes_and_keeps_the_set(tests3: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    lst = SetListener(DEFS, "m", tmp_path)
    made = feed(lst, *tests3.values())
    with running_bus() as (bus, ep), client(ep) as c:
        got: list[Any] = []
        sub = c.declare_subscriber("ballbar/m/result/set", lambda s: got.append(json.loads(s.payload.to_bytes())))
        wait_until(lambda: bus.has_subscribers("set"), what="the set's subscriber")
        for s in made:
            bus.on_message(s)
        wait_until(lambda: len(got) == 2, what="both sets")
        sub.undeclare()
        assert [g["set_id"] for g in got] == [s["set_id"] for s in made]
        ok, _ = get(c, "ballbar/m/last/set")
        assert len(ok) == 1 and json.loads(ok[0].payload.to_bytes())["set_id"] == made[-1]["set_id"]
        ok, _ = get(c, "ballbar/m/history/set")
        doc = json.loads(ok[0].payload.to_bytes())
        assert doc["topic"] == "set" and doc["count"] == 2
        assert problems(doc) == []


def test_the_mcap_log_records_the_set(tests3: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    made = feed(SetListener(DEFS, "m", tmp_path / "s"), *tests3.values())
    lg = McapLogger(tmp_path, "m")
    for s in made:
        lg.on_message(s)
    lg.stop()
    files = list_recordings(tmp_path / "recordings")
    assert validate_recordings(tmp_path / "recordings")["/ballbar/results"] == 2
    back = [r for r in read_results(files) if r.get("kind") == "set"]
    assert [r["set_id"] for r in back] == [s["set_id"] for s in made]


def test_a_set_made_as_the_daemon_stops_is_still_recorded(tests3: dict[str, dict[str, Any]], tmp_path: Path) -> None:
    """``ballbar run --tests N`` stops at its last test: the set that test completes still reaches the outputs
    (here the real MCAP log), though the set's listener sends it while the daemon shuts them down."""
    from ballbar.daemon.config import load
    from ballbar.daemon.service import Daemon
    from ballbar.daemon.sources import open_source

    cfg = load(None, ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"', "daemon.analysis_worker=false",
                      "daemon.machine_id=m"], env={})
    logger = McapLogger(tmp_path, "m")
    daemon = Daemon(cfg, open_source("sim:?speedup=max&rate=100"),
                    [(logger, 1000, "drop_newest"), (SetListener(DEFS, "m", tmp_path), 1000, "drop_newest")])
    try:
        for t in tests3.values():
            daemon.broadcast({**t, "kind": "test", "machine_id": "m"})
    finally:
        daemon.shutdown()
    recorded = [r for r in read_results(list_recordings(tmp_path / "recordings")) if r["kind"] == "set"]
    assert sorted(r["set"]["name"] for r in recorded) == ["horizontal", "machine"]
