"""The payloads' JSON Schemas: generated from the message types, shipped, valid draft 2020-12, closed, and matched
by real payloads; the payload tables generated likewise.

The daemon's own payloads are checked where they are made: the end-to-end tests
(``test_e2e.py``, ``test_plant.py``) validate every message a subscriber receives
and every MCAP record.  Here: the files, and `ballbar analyze --json` on simulated
recordings that take the optional paths (null parameters with reasons, the
controller's parameter names, cyclic errors, a partial arc in one direction, a
rate warning, the loop gain profile of a slow rate).
"""

from __future__ import annotations

import copy
import json
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any, get_args, is_typeddict

import numpy as np
import pytest
from jsonschema import Draft202012Validator
from schemacheck import problems, validate

from ballbar import SCHEMA_VERSION
from ballbar.analysis.patterns import LIBRARY
from ballbar.analysis.report import _report_fields
from ballbar.daemon.config import load
from ballbar.daemon.mcap import (
    SCHEMAS,
    TOPIC_CONFIG,
    TOPIC_CONTROLLER,
    TOPIC_EVENTS,
    TOPIC_OTHER,
    TOPIC_RESULTS,
    TOPIC_SAMPLES,
    TOPIC_STATUS,
)
from ballbar.daemon.schemas import NAMES, PARAMETERS, main, schema, schema_text, shipped_dir
from ballbar.protocol.messages import SchemaVersion, tables
from ballbar.protocol.messages.config import Settings
from ballbar.protocol.messages.fields import fields_of

REPO = Path(__file__).resolve().parents[1]


def test_shipped_files_are_the_schemas() -> None:
    d = shipped_dir()
    assert sorted(p.name for p in d.glob("*.schema.json")) == sorted(f"{n}.schema.json" for n in NAMES)
    for name in NAMES:
        text = (d / f"{name}.schema.json").read_text(encoding="utf-8")
        assert text == schema_text(name), (
            f"ballbar/schema/{name}.schema.json is stale: python -m ballbar.daemon.schemas --write ballbar/schema"
        )
        doc = json.loads(text)
        Draft202012Validator.check_schema(doc)
        assert doc["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert doc["$id"] == f"urn:ballbar:schema:{SCHEMA_VERSION}:{name}"


def test_mcap_channels_register_the_same_schemas() -> None:
    names = {TOPIC_RESULTS: ("ballbar.Result", "result"), TOPIC_EVENTS: ("ballbar.Event", "mcap-event"),
             TOPIC_STATUS: ("ballbar.Status", "status"), TOPIC_CONFIG: ("ballbar.Config", "config"),
             TOPIC_SAMPLES: ("ballbar.Samples", "mcap-samples"), TOPIC_OTHER: ("ballbar.Message", "mcap-other"),
             TOPIC_CONTROLLER: ("ballbar.Controller", "controller")}
    assert set(SCHEMAS) == set(names)
    for topic, (mcap_name, name) in names.items():
        assert SCHEMAS[topic][0] == mcap_name, topic
        assert SCHEMAS[topic][1] == schema(name), topic


def test_the_payload_tables_are_generated(tmp_path: Path) -> None:
    doc = REPO / "protocol" / "messages" / "README.md"
    assert doc.read_text(encoding="utf-8") == tables.markdown(), (
        "protocol/messages/README.md is stale: python -m ballbar.daemon.schemas --doc protocol/messages/README.md"
    )
    # the command writes both, as the messages say
    assert main(["--write", str(tmp_path / "s"), "--doc", str(tmp_path / "README.md")]) == 0
    assert (tmp_path / "README.md").read_text(encoding="utf-8") == tables.markdown()
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == sorted(f"{n}.schema.json" for n in NAMES)


def test_one_table_names_each_field_with_its_unit() -> None:
    text = tables.markdown()
    assert "| `backlash_x_um` | [Parameter](#parameter) | um | lost motion of the first axis" in text
    assert "| `latency_ms` | number or null | ms |" in text
    assert "| `count` | integer |  | how many |" in text  # the lost event's


def test_the_daemon_runs_without_loading_the_types() -> None:
    """The daemon makes and sends plain dicts: the types and the generator are for mypy and the tests (its MCAP
    channels' schemas are the shipped files, checked above)."""
    code = ("import sys, ballbar.daemon.run, ballbar.daemon.service, ballbar.daemon.mcap, ballbar.daemon.bus, "
            "ballbar.daemon.monitor, ballbar.daemon.rerun.listener, ballbar.daemon.testindex; "
            "print(' '.join(sorted(m for m in sys.modules if m.startswith('ballbar.protocol.messages'))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = set(out.split())
    light = {f"ballbar.protocol.messages{m}" for m in ("", ".channels", ".envelope", ".fields", ".publish")}
    assert loaded == light, loaded - light
    # ... and every name the package exports is there when asked for (loaded then)
    from ballbar.protocol import messages

    assert all(getattr(messages, name) is not None for name in messages.__all__)


def test_schema_version_is_the_types_literal() -> None:
    assert get_args(SchemaVersion) == (SCHEMA_VERSION,)


def test_parameters_are_the_pattern_librarys_fields_with_their_units() -> None:
    fields = dict(f for pat in LIBRARY for f in _report_fields(pat))
    assert {k: u for k, (u, _text) in PARAMETERS.items()} == fields


def _keys(td: Any, given: Any) -> dict[str, Any]:
    """The keys of ``td``, nested: the required ones and those of the others that ``given`` has."""
    out: dict[str, Any] = {}
    for name, (tp, _d, required) in fields_of(td).items():
        if required or (isinstance(given, dict) and name in given):
            out[name] = _keys(tp, given.get(name) if isinstance(given, dict) else None) if is_typeddict(tp) else None
    return out


def _shape(d: dict[str, Any], like: dict[str, Any]) -> dict[str, Any]:
    return {k: _shape(v, like.get(k) or {}) if isinstance(like.get(k), dict) else None for k, v in d.items()}


def test_the_config_message_has_every_section_and_key_of_the_configuration() -> None:
    sent = load(env={}).to_dict()  # the shipped defaults: what the daemon sends (redacted) as ballbar/<m>/config
    assert _shape(sent, _keys(Settings, sent)) == _keys(Settings, sent)


def _closed(node: Any, path: str, out: list[str]) -> None:
    """Every object schema with properties is closed; every leaf says what it is."""
    if isinstance(node, dict):
        if "properties" in node and node.get("additionalProperties") is not False:
            out.append(path)
        for k, v in node.get("properties", {}).items():
            if isinstance(v, dict) and "$ref" not in v and not v.get("description"):
                out.append(f"{path}/{k}: no description")
        for k, v in node.items():
            if k not in ("if", "then", "else"):  # conditions on a shape described elsewhere, not shapes
                _closed(v, f"{path}/{k}", out)
    elif isinstance(node, list):
        for i, v in enumerate(node):
            _closed(v, f"{path}/{i}", out)


@pytest.mark.parametrize("name", [n for n in NAMES if n not in ("history", "mcap-other")])
def test_objects_are_closed_and_described(name: str) -> None:
    bad: list[str] = []
    doc = schema(name)
    _closed(doc, name, bad)
    assert not bad, bad


def _analyze(tmp: Path, sim: list[str], analyze: list[str]) -> dict[str, Any]:
    csv = tmp / "rec.csv"
    subprocess.run([sys.executable, "-m", "ballbar.tools.simulator_cli", "--out", str(csv), *sim], check=True,
                   capture_output=True)
    out = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(csv), "--json", *analyze],
                         check=True, capture_output=True, text=True).stdout
    res: dict[str, Any] = json.loads(out)
    return res


@pytest.fixture(scope="module")
def analyses(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    out = {}
    # cyclic error with the pitch configured, gains configured, FANUC's parameter names in the advice
    t = tmp_path_factory.mktemp("a")
    out["full"] = _analyze(
        t, ["--sample-hz", "500", "--set", "backlash_x_um=5", "--set", "pitch_x_mm=10", "--set", "cyclic_x_um=1"],
        ["--sample-hz", "500", "--pitch-x-mm", "10", "--kv-x", "30", "--kv-y", "30", "--controller", "fanuc"],
    )
    # a 220 deg arc in ZX, CCW only, with a plan rate other than the recording's: spikes not reached, a warning
    t = tmp_path_factory.mktemp("b")
    plan = ["--plane", "ZX", "--start-deg", "-110", "--overshoot-deg", "5", "--data-arc-deg", "220",
            "--feed-mm-min", "3000", "--directions", "ccw"]
    out["partial"] = _analyze(t, ["--sample-hz", "200", *plan], ["--sample-hz", "100", *plan])
    # 15.625 Hz: the loop's lag searched with the timing, negative backlash (compensation model)
    t = tmp_path_factory.mktemp("c")
    out["slow"] = _analyze(t, ["--sample-hz", "15.625", "--set", "backlash_x_um=-3"], ["--sample-hz", "15.625"])
    return out


def test_offline_results_validate(analyses: dict[str, dict[str, Any]]) -> None:
    full, partial, slow = analyses["full"], analyses["partial"], analyses["slow"]
    # the optional paths were taken, so the schema was tried on them
    assert any("controller_parameter" in a for a in full["advice"])
    assert full["parameters"]["cyclic_x_um"]["value"] is not None
    nulls = [p for p in partial["parameters"].values() if p["value"] is None]
    assert nulls and all(p.get("reason") for p in nulls)
    assert partial.get("warnings") and partial["iso230_4"]["G_cw_um"] is None
    assert slow["timing"]["loop_lag_stderr_ms"] is not None  # the loop's lag searched with the timing
    for res in analyses.values():
        assert res["schema_version"] == SCHEMA_VERSION
        validate(res, "analysis")


def test_a_field_without_a_schema_entry_fails(analyses: dict[str, dict[str, Any]]) -> None:
    base = analyses["full"]
    validate(base, "analysis")
    for where in ([], ["timing"], ["parameters"], ["parameters", "backlash_x_um"], ["iso230_4", "conditions"],
                  ["fit", "lost_motion", "x"], ["noise"], ["source"]):
        doc = copy.deepcopy(base)
        node = doc
        for k in where:
            node = node[k]
        node["surprise_um"] = 1.0
        assert problems(doc, "analysis"), where
    doc = copy.deepcopy(base)
    doc["ranking"][0]["surprise"] = 1
    assert problems(doc, "analysis")
    doc = copy.deepcopy(base)
    doc["parameters"]["backlash_x_um"]["value"] = "4"  # a wrong type
    assert problems(doc, "analysis")
    doc = copy.deepcopy(base)
    del doc["parameters"]["squareness_urad"]  # every parameter is there, fitted or not
    assert problems(doc, "analysis")


def test_every_parameter_has_a_unit_in_its_schema(analyses: dict[str, dict[str, Any]]) -> None:
    props = schema("result")["$defs"]["parameters"]["properties"]
    for key, p in analyses["full"]["parameters"].items():
        assert PARAMETERS[key][0] == p["unit"], key
        assert props[key]["description"].endswith(p["unit"]), key


def test_events_are_checked_per_kind() -> None:
    ok = {"schema_version": SCHEMA_VERSION, "kind": "event", "event": "lost", "origin": "source",
          "machine_id": "m", "t_wall": "2026-01-01T00:00:00.000Z", "t_host": 1.0, "source": "serial:x",
          "count": 3, "seq": 10, "detail": "gap"}
    validate(ok)
    assert problems({**ok, "count": "3"})  # a count is an integer
    assert problems({k: v for k, v in ok.items() if k != "count"})  # lost says how many
    assert problems({**ok, "message": "x"})  # a lost event has no message
    assert problems({**ok, "event": "no_such_event"})
    assert problems({**ok, "schema_version": SCHEMA_VERSION - 1})


# --------------------------------------------------------------------------- payloads the old schemas refused


def test_a_history_alert_reply_and_its_alerts_follow_their_schemas(analyses: dict[str, dict[str, Any]],
                                                                     tmp_path: Path) -> None:
    """history/alert is answered like the others; its reply is a history document (topic alert)."""
    from ballbar.analysis.monitor import settings_from_dict
    from ballbar.daemon.bus import ZenohBus, ZenohConfig
    from ballbar.daemon.monitor import Monitor, MonitorStore

    test = {**analyses["full"], "machine_id": "m", "test_id": "m-20260101T000000Z", "t_wall": "2026-01-01T00:00:00Z"}
    settings = settings_from_dict({"enabled": True, "parameters": {"backlash_x_um": 1.0}})
    alerts = Monitor(settings, "m", MonitorStore(tmp_path, "m")).on_test(test)
    assert [(a["alert"], a["state"]) for a in alerts] == [("verdict", "fail")]  # 5 um of backlash against 1 um
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    bus = ZenohBus("m", ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]))
    try:
        for a in alerts:
            bus.on_message(a)
        reply = json.loads(bus.history_payload("alert"))
    finally:
        bus.stop()
    validate(reply, "history")
    assert reply["topic"] == "alert" and reply["count"] == 1
    validate(reply["results"][0], "alert")


def test_a_polled_gauges_per_test_files_follow_their_channels_schemas(tmp_path: Path) -> None:
    """The timing event the MCAP log repeats at the head of each file (``repeated``) is in the mcap-event schema."""
    from schemacheck import validate_recordings

    from ballbar.daemon.config import load
    from ballbar.daemon.mcap import McapLogger, read_log
    from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
    from ballbar.daemon.secrets import redacted
    from ballbar.protocol.messages import ConfigMessage, stamp
    from ballbar.protocol.messages.events import FeedIn
    from ballbar.protocol.messages.publish import source_event

    lg = McapLogger(tmp_path, "m")
    config: ConfigMessage = {**stamp("m"), "kind": "config", "config": redacted(load(env={}).to_dict())}
    lg.on_message(config)
    timing = SourceEvent(EventKind.TIMING, 100.0, "serial:/dev/ttyUSB0?protocol=mitutoyo", detail="polled",
                         values={"t_uncertainty_s": 0.004, "t_jitter_s": 0.001, "achieved_hz": 50.0})
    k = np.arange(200)
    for i, t0 in enumerate((100.0, 102.0)):
        t_host = t0 + k[:100] * 0.02
        batch = SampleBatch.from_columns(t_host, np.full(100, np.nan), np.full(100, 100.0), k[:100] + 100 * i,
                                         np.zeros(100), (timing,) if i == 0 else (), timing.source)
        if i == 0:  # the daemon hands each source event over as its message, then in its batch: logged once
            lg.on_message(source_event(stamp("m"), timing.to_dict()))
        lg.on_batch(batch)
        feed_in: FeedIn = {**stamp("m"), "kind": "event", "event": "feed_in", "test_index": i + 1,
                           "t_s": float(t_host[50]), "test_id": f"m-{i}", "t_host": float(t_host[-1])}
        lg.on_message(feed_in)  # each test: a new file, which repeats the timing event at its head
    lg.stop()
    seen = validate_recordings(tmp_path / "recordings")
    events = [[e["event"] for e in read_log(p).events] for p in sorted((tmp_path / "recordings").glob("*.mcap"))]
    assert len(events) == 2 and events[1][0] == "timing", events  # the second test's file opens with it
    assert read_log(sorted((tmp_path / "recordings").glob("*.mcap"))[1]).events[0]["repeated"] is True
    assert seen["/ballbar/events"] == sum(map(len, events)) and seen["/ballbar/config"] == 2


# --------------------------------------------------------------------------- every producer, in process


def test_every_message_the_daemon_makes_follows_its_schema(tmp_path: Path) -> None:
    """The daemon's producers as `ballbar run` wires them (source events, the analysis' results and events, the
    config, the status, the monitor's verdict and alerts, the MCAP log's records), on a simulated test: every
    message handed to the outputs, and every record written, follows its schema."""
    import threading

    from schemacheck import validate_all, validate_recordings

    from ballbar.daemon.listeners import Listener, Message
    from ballbar.daemon.run import build_listeners
    from ballbar.daemon.samples import SampleBatch
    from ballbar.daemon.service import Daemon
    from ballbar.daemon.sources import open_source
    from ballbar.tools.simulator import MachineModel

    class Recorder(Listener):
        name = "recorder"

        def __init__(self) -> None:
            self.messages: list[Message] = []

        def on_batch(self, batch: SampleBatch) -> None:
            pass

        def on_message(self, msg: Message) -> None:
            self.messages.append(msg)

        def stop(self) -> None:
            pass

    cfg = load(None, [f'daemon.state_dir="{tmp_path}"', "zenoh.enabled=false", 'rerun.mode="off"',
                      "daemon.analysis_worker=false", "limits.enabled=true", "limits.parameters={backlash_x_um=1.0}"],
               env={})
    rec = Recorder()
    src = open_source("sim:?speedup=max&rate=100&repeat=2", machine=MachineModel(backlash_x_um=5.0))
    d = Daemon(cfg, src, [*build_listeners(cfg), (rec, 10_000, "drop_newest")])
    # two tests: the first's alert (pass to fail) reaches every output before the run ends
    assert d.run(threading.Event(), max_tests=2, duration_s=120.0) == 0
    seen = validate_all([*rec.messages, d.status()])
    for kind in ("config", "event:opened", "event:feed_in", "event:feed_out", "circle", "test", "alert", "status"):
        assert seen[kind] > 0, (kind, seen)
    tests = [m for m in rec.messages if m["kind"] == "test"]
    assert [t["verdict"]["status"] for t in tests] == ["fail", "fail"]  # the monitor's: 5 um of backlash against 1 um
    assert "monitor" in d.status()["outputs"]
    records = validate_recordings(tmp_path / "recordings")
    assert records["/ballbar/results"] >= 3 and records["/ballbar/config"] >= 1
