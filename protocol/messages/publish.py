"""The typed constructors of what the daemon sends (the analysis' output wrapped, a source's event stamped), and
a result's parameters looked up by a name made at run time.

Every message the daemon makes starts from :func:`~.envelope.stamp` (the
envelope, once); these put the rest together where the parts come from two
places: the analysis' body and the daemon's :class:`~.envelope.LastSample`;
a source's fields (``ballbar.daemon.samples.SourceEvent.to_dict``) and the
envelope.  The types are imported to type-check only: the daemon runs on plain
dicts and loads none of them.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, cast

if TYPE_CHECKING:
    from typing import TypeAlias

    from .envelope import LastSample, Stamp
    from .events import EventBody, PipelineEvent, SourceEvent
    from .results import CircleBody, CircleResult, Parameter, Parameters, Produced, TestBody, TestResult

    Published: TypeAlias = CircleResult | TestResult | PipelineEvent


def published(body: CircleBody | TestBody | EventBody, stamp: Stamp, last: LastSample) -> Published:
    """An output of the analysis as the daemon publishes it: the body, the envelope, the test's last sample.

    A result keeps its body's ``schema_version``; an event gets the envelope's.
    """
    produced: Produced = {"machine_id": stamp["machine_id"], "t_wall": stamp["t_wall"]}
    if body["kind"] == "circle":
        return {**body, **produced, **last}
    if body["kind"] == "test":
        return {**body, **produced, **last}
    # one of the test events: its body's event and fields are that event's (test_skipped never comes live)
    return cast("PipelineEvent", {**body, **stamp, **last})


def source_event(stamp: Stamp, fields: Mapping[str, Any]) -> SourceEvent:
    """A source's event as published: ``fields`` are ``SourceEvent.to_dict()``'s (``kind`` is its name)."""
    own = {k: v for k, v in fields.items() if k != "kind"}
    # the fields of the event that fields["kind"] names (ballbar.daemon.samples.EventKind; the schema tests check)
    return cast("SourceEvent", {"kind": "event", "event": str(fields["kind"]), "origin": "source", **stamp, **own})


def parameter_map(parameters: Parameters) -> Mapping[str, Parameter]:
    """``parameters`` looked up by a name made at run time (every value of ``Parameters`` is a ``Parameter``)."""
    return cast("Mapping[str, Parameter]", parameters)
