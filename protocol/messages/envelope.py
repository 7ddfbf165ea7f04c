"""The envelope every published message carries, made in one place; the one JSON encoding.

Every payload on the bus, in the MCAP log and in the monitor's files starts
with ``schema_version``, ``kind``, ``machine_id`` and ``t_wall``.
:func:`stamp` makes the three that do not depend on the message (``kind`` is
each message's own ``Literal``); a producer writes ``{**stamp(machine_id),
"kind": "status", ...}`` and mypy checks the rest against the message's type.
:func:`to_json` is how every output encodes a message.
"""

import datetime as dt
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, NotRequired, TypedDict

import numpy as np

from ballbar import SCHEMA_VERSION

from .fields import doc

#: ``schema_version``'s type: ``Literal[SCHEMA_VERSION]`` (a test keeps the two equal).
SchemaVersion = Literal[2]

Version = Annotated[SchemaVersion, doc("version of these payloads' shapes")]
MachineId = Annotated[str, doc("the daemon's daemon.machine_id: the <m> of ballbar/<m>/...")]
TWall = Annotated[str, doc("when the daemon produced it: ISO 8601 UTC with milliseconds, e.g. "
                           "2026-11-21T10:59:56.123Z")]
THost = Annotated[float, doc("the daemon host's monotonic clock (not wall time; t_wall is that)", "s")]
TestId = Annotated[str | None, doc("the test's id, <machine>-<UTC time of the feed-in YYYYmmddTHHMMSSZ>[-2, -3...]")]
TimeAxis = Literal["device", "host"]
SourceUrl = Annotated[str, doc("the source's URL (e.g. serial:/dev/ttyUSB0?protocol=binary&rate=1000)")]


class Stamp(TypedDict):
    """The envelope's fields that every message of the daemon shares, ``kind`` aside."""

    schema_version: Version
    machine_id: MachineId
    t_wall: TWall


LastSampleT = Annotated[float | None, doc("the time axis value of the last sample the analysis had seen (see "
                                         "time_axis)", "s")]
LastSampleTHost = Annotated[float | None, doc("that sample's host time, on t_host's monotonic clock", "s")]
LatencyMs = Annotated[float | None, doc("t_host - last_sample_t_host: how long after its last sample this went out",
                                        "ms")]
TimeAxisField = Annotated[TimeAxis | None, doc("the analysis' time axis: device (the device's sample clock; with "
                                               "--simulate, simulated seconds) or host")]


class LastSample(TypedDict):
    """What the daemon adds to each analysis output (results, test events): which test, when, how late."""

    test_id: TestId
    t_host: THost
    last_sample_t: LastSampleT
    last_sample_t_host: LastSampleTHost
    latency_ms: LatencyMs
    time_axis: TimeAxisField


class MaybeLastSample(TypedDict):
    """:class:`LastSample` on an event, where all but ``t_host`` may be absent (an event found at start)."""

    test_id: NotRequired[TestId]
    t_host: THost
    last_sample_t: NotRequired[LastSampleT]
    last_sample_t_host: NotRequired[LastSampleTHost]
    latency_ms: NotRequired[LatencyMs]
    time_axis: NotRequired[TimeAxisField]


def utc_text(t: dt.datetime) -> str:
    """``t`` as the messages' wall time: ISO 8601 UTC with milliseconds and ``Z``."""
    return t.astimezone(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def utc_now() -> str:
    """Now, as :func:`utc_text` writes it (the envelope's ``t_wall``)."""
    return utc_text(dt.datetime.now(dt.UTC))


def stamp(machine_id: str, t_wall: str | None = None) -> Stamp:
    """The envelope of a message the daemon sends now (or at ``t_wall``)."""
    return {"schema_version": SCHEMA_VERSION, "machine_id": machine_id,
            "t_wall": utc_now() if t_wall is None else t_wall}


# --------------------------------------------------------------------------- JSON


def _plain(obj: Any) -> Any:
    """What ``json`` cannot take as it is: numpy values, arrays, paths, sets."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Mapping):
        return dict(obj)
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def _finite(obj: Any) -> Any:
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def to_json(msg: Any) -> bytes:
    """A message as compact, strict JSON (UTF-8): NaN and infinities become ``null``, numpy values plain numbers.

    One encoding for every output (MCAP records, bus payloads, the monitor's files).
    """
    try:
        text = json.dumps(msg, separators=(",", ":"), allow_nan=False, default=_plain)
    except ValueError:
        text = json.dumps(_finite(msg), separators=(",", ":"), allow_nan=False, default=_plain)
    return text.encode("utf-8")
