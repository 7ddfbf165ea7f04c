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
"""

from .config import ConfigMessage, Settings
from .documents import MCAP_CHANNELS, NAMES, schema, schema_text
from .envelope import SchemaVersion, Stamp, stamp, to_json, utc_now, utc_text
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
AnalysisOutput = CircleBody | TestBody | EventBody

#: Every message a listener of the daemon is handed (``ballbar.daemon.listeners.Listener.on_message``).
Message = CircleResult | TestResult | SetResult | Event | Status | ConfigMessage | Alert | Samples

__all__ = [
    "MCAP_CHANNELS",
    "NAMES",
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
    "schema",
    "schema_text",
    "stamp",
    "to_json",
    "utc_now",
    "utc_text",
]
