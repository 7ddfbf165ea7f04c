"""ballbar.protocol.messages: every message ballbar publishes or records, one typed definition each.

The other half of the protocol: what the daemon speaks to plant services (the
Zenoh payloads, the MCAP records, ``ballbar analyze --json``, the monitor's
files), as ``TypedDict``\\ s whose fields carry their description and unit
(:mod:`.fields`).  The JSON Schemas shipped in ``ballbar/schema/``, the MCAP
channels' schemas and the payload tables of ``protocol/messages/README.md`` are
generated from them (:mod:`.documents`, :mod:`.tables`; ``python -m
ballbar.daemon.schemas --write ballbar/schema --doc protocol/messages/README.md``)
and tests keep the shipped copies equal to what they give.  On the wire the
messages stay plain JSON (:func:`to_json`); producers make the envelope with
:func:`stamp`, and mypy checks producers and consumers against the types.

Importing this package loads the envelope alone; the types load when first
named.  The daemon names them only under ``TYPE_CHECKING`` (its annotations
are postponed, its MCAP channels' schemas are the shipped files,
:mod:`.channels`): it runs on plain dicts and pays nothing for them.  The
generator is built of this package's types, so the package does not name it:
its ``NAMES``, ``schema`` and ``schema_text`` are imported from
``ballbar.protocol.messages.documents`` itself.
"""

from functools import reduce
from importlib import import_module
from operator import or_
from typing import TYPE_CHECKING, Any

from .envelope import SchemaVersion, Stamp, stamp, to_json, utc_now, utc_text

if TYPE_CHECKING:
    from typing import TypeAlias

    from .channels import MCAP_CHANNELS
    from .config import ConfigMessage, Settings
    from .controller import ControllerMessage
    from .events import Event, EventBody, LogGap, PipelineEvent, SourceEvent
    from .monitor import Alert, Conditions, Forecast, ForecastAlert, HistoryEntry, LimitEntry, Verdict, VerdictAlert
    from .replies import HistoryReply, QueryError
    from .results import (
        Analysis,
        Body,
        CircleBody,
        CircleResult,
        CircleTiming,
        Parameter,
        Parameters,
        Result,
        TestBody,
        TestResult,
        TestTiming,
    )
    from .samples import McapSamples, Samples
    from .sets import SetResult
    from .status import Status

    #: What ``ballbar.analysis`` returns as a stream goes by (``TestAnalyzer.feed``): results and test events.
    AnalysisOutput: TypeAlias = CircleBody | TestBody | EventBody

    #: Every message a listener of the daemon is handed (``ballbar.daemon.listeners.Listener.on_message``).
    Message: TypeAlias = (CircleResult | TestResult | SetResult | Event | Status | ConfigMessage | Alert | Samples
                         | ControllerMessage)

# Where each name is, loaded when first asked for (the imports above are mypy's); the unions built of them.
_LAZY = {
    "ConfigMessage": "config", "Settings": "config", "MCAP_CHANNELS": "channels", "Event": "events",
    "EventBody": "events", "LogGap": "events", "PipelineEvent": "events", "SourceEvent": "events", "Alert": "monitor",
    "Conditions": "monitor", "Forecast": "monitor", "ForecastAlert": "monitor", "HistoryEntry": "monitor",
    "LimitEntry": "monitor", "Verdict": "monitor", "VerdictAlert": "monitor", "HistoryReply": "replies",
    "QueryError": "replies", "Analysis": "results", "Body": "results", "CircleBody": "results",
    "CircleResult": "results", "CircleTiming": "results", "Parameter": "results", "Parameters": "results",
    "Result": "results", "TestBody": "results", "TestResult": "results", "TestTiming": "results",
    "McapSamples": "samples", "Samples": "samples", "SetResult": "sets", "Status": "status",
    "ControllerMessage": "controller",
}
_UNIONS = {
    "AnalysisOutput": ("CircleBody", "TestBody", "EventBody"),
    "Message": ("CircleResult", "TestResult", "SetResult", "Event", "Status", "ConfigMessage", "Alert", "Samples",
                "ControllerMessage"),
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    if name in _UNIONS:
        return reduce(or_, (__getattr__(part) for part in _UNIONS[name]))
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "MCAP_CHANNELS",
    "Alert",
    "Analysis",
    "AnalysisOutput",
    "Body",
    "CircleBody",
    "CircleResult",
    "CircleTiming",
    "Conditions",
    "ConfigMessage",
    "Event",
    "EventBody",
    "Forecast",
    "ForecastAlert",
    "HistoryEntry",
    "HistoryReply",
    "LimitEntry",
    "LogGap",
    "McapSamples",
    "Message",
    "Parameter",
    "Parameters",
    "PipelineEvent",
    "QueryError",
    "Result",
    "Samples",
    "SchemaVersion",
    "SetResult",
    "Settings",
    "SourceEvent",
    "Stamp",
    "Status",
    "TestBody",
    "TestResult",
    "TestTiming",
    "Verdict",
    "VerdictAlert",
    "stamp",
    "to_json",
    "utc_now",
    "utc_text",
]
