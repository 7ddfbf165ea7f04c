"""The schema files: which message each is, its ``$defs``, and the MCAP channels' schemas.

Each document is generated from the message types (:mod:`.jsonschema`); the
package ships them as ``ballbar/schema/<name>.schema.json`` and a test keeps
the files equal to what this module makes.  ``$id`` is
``urn:ballbar:schema:<schema_version>:<name>``.
"""

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from typing import Any, Union

from ballbar import SCHEMA_VERSION

from . import controller, monitor, replies, results, samples, sets, status
from . import events as ev
from .config import ConfigMessage
from .jsonschema import Builder, Schema, document

_MONITOR_DEFS = {"verdict": monitor.Verdict, "limit_entry": monitor.LimitEntry}
_RESULT_DEFS = {"parameter": results.Parameter, "parameters": results.Parameters, **_MONITOR_DEFS}
_SET_DEFS = {"figure": sets.Figure, "observation": sets.Observation}

#: A source's events, the analysis' and the logger's, by name.
SOURCE_EVENTS: dict[str, Any] = {
    "opened": ev.Opened, "unplugged": ev.Unplugged, "replugged": ev.Replugged, "lost": ev.Lost,
    "decode_errors": ev.DecodeErrors, "stall": ev.Stall, "resumed": ev.Resumed, "device_reset": ev.DeviceReset,
    "clock_jump": ev.ClockJump, "counter_jump": ev.CounterJump, "end": ev.End, "timing": ev.Timing,
}
PIPELINE_EVENTS: dict[str, Any] = {
    "feed_in": ev.FeedIn, "feed_out": ev.FeedOut, "test_rejected": ev.TestRejected,
    "test_incomplete": ev.TestIncomplete, "analysis_reset": ev.AnalysisReset,
    "test_unrecognised": ev.TestUnrecognised, "plan_chosen": ev.PlanChosen,
    "plan_choice_refused": ev.PlanChoiceRefused, "controller_disagrees": ev.ControllerDisagrees,
}
EVENTS = {**SOURCE_EVENTS, **PIPELINE_EVENTS}

#: The envelope's keys: an event in the MCAP log may lack them (a source's is logged as the source reported it).
_ENVELOPE = ("schema_version", "kind", "machine_id", "t_wall", "origin", "source")


@dataclass(frozen=True)
class Document:
    """A schema file: its root type (its docstring the file's description, unless ``description``) and its defs."""

    root: Any
    defs: dict[str, Any] = field(default_factory=dict)
    description: str = ""
    extra: Schema = field(default_factory=dict)  # keywords beside the root's (an event's "required": ["event"])


def _events(branches: dict[str, Any]) -> Document:
    return Document(
        Union[tuple(branches.values())],  # noqa: UP007 - built from the branches
        branches,
        "An event on ballbar/<m>/event: a source's (origin source: the device or its port), the analysis' (test "
        "events, with the test's test_id), or one found at start (origin recovery). One branch per event name.",
        {"type": "object", "required": ["event"]},
    )


DOCUMENTS: dict[str, Document] = {
    "result": Document(
        results.CircleResult | results.TestResult | sets.SetResult,
        {"circle": results.CircleResult, "test": results.TestResult, "set": sets.SetResult, **_RESULT_DEFS,
         **_SET_DEFS},
        "ballbar.Result: an analysis result, a circle's (kind circle, provisional timing, after each data arc) or a "
        "test's (kind test): the `ballbar analyze --json` object plus the daemon's machine_id, test_id, t_wall, "
        "t_host, last_sample_t, last_sample_t_host, latency_ms and time_axis; or a set's (kind set, the set "
        "schema).",
    ),
    "analysis": Document(results.Analysis, _RESULT_DEFS),
    "event": _events(EVENTS),
    "status": Document(status.Status),
    "config": Document(ConfigMessage),
    "samples": Document(samples.Samples),
    "history": Document(replies.HistoryReply),
    "alert": Document(
        monitor.Alert,
        {"verdict_alert": monitor.VerdictAlert, "forecast_alert": monitor.ForecastAlert,
         "conditions": monitor.Conditions, "forecast": monitor.Forecast, **_MONITOR_DEFS},
        "ballbar/<m>/alert (also last/alert and history/alert): a verdict that changed, or a forecast that became "
        "due or cleared. $defs.verdict is the 'verdict' of a test result (ballbar/<m>/result/test) when [limits] is "
        "enabled. See ballbar.analysis.monitor.",
    ),
    "error": Document(replies.QueryError),
    "monitor-history": Document(monitor.HistoryEntry),
    "mcap-samples": Document(samples.McapSamples),
    "set": Document(sets.SetResult, _SET_DEFS),
    "controller": Document(controller.ControllerMessage),
}


def _build(name: str, d: Document) -> Schema:
    b = Builder(d.defs)
    body = b.node(d.root, inline=True)
    description = d.description or str(body.pop("description", ""))
    body.pop("description", None)
    return document(name, SCHEMA_VERSION, description, {**d.extra, **body}, b.definitions())


def _mcap_events() -> Schema:
    """The events as the MCAP log stores them: without ``kind``; the envelope not required; plus ``log_gap``."""
    doc = _build("mcap-event", _events({**EVENTS, "log_gap": ev.LogGap}))
    for branch in doc["$defs"].values():
        branch["properties"].pop("kind", None)
        branch["required"] = [k for k in branch["required"] if k not in _ENVELOPE]
    doc["description"] = (
        "ballbar.Event as the MCAP log stores it: the event payload without kind; a source's events as the source "
        "reported them (event, t_host, source and the event's own fields), the pipeline's as published"
    )
    return doc


def _mcap_other() -> Schema:
    """Any other message kind in the MCAP log (/ballbar/other), as it came: by definition not closed."""
    return document("mcap-other", SCHEMA_VERSION, "ballbar.Message: a pipeline message of another kind (an alert, "
                    "...), as it came.", {"type": "object", "properties": {"kind": {
                        "type": "string", "description": "the message's kind"}}, "additionalProperties": True})


_SPECIAL: dict[str, Callable[[], Schema]] = {"mcap-event": _mcap_events, "mcap-other": _mcap_other}
NAMES = (*DOCUMENTS, *_SPECIAL)


@cache
def schema_text(name: str) -> str:
    """The schema ``name`` as the shipped file holds it."""
    if name in _SPECIAL:
        doc = _SPECIAL[name]()
    elif name in DOCUMENTS:
        doc = _build(name, DOCUMENTS[name])
    else:
        raise KeyError(f"no schema {name!r} (one of {', '.join(NAMES)})")
    return json.dumps(doc, indent=2) + "\n"


def schema(name: str) -> Schema:
    """The schema ``name`` (one of :data:`NAMES`) as a fresh dict."""
    out: Schema = json.loads(schema_text(name))
    return out
