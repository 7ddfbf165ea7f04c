"""Sample batches and source events: what every acquisition source delivers.

A :class:`SampleBatch` holds columns (numpy arrays of equal length, one row per
sample, in acquisition order) plus the :class:`SourceEvent` objects that
happened since the previous batch (a ``lost`` event says where in the sample
numbers its gap is).  A batch may carry events and no samples (an unplug while
nothing arrives); it is truthy even then.  At 10 kHz a
source returns about 50 batches a second, never one Python object per sample.

Columns
-------
``t_host``     float64, seconds on the host's monotonic clock (``time.monotonic``)
               at which the sample was *taken*: the device clock mapped to host
               time where the protocol has one, else the host's own estimate.
``t_device``   float64, seconds on the device's sample clock, unwrapped; NaN
               when the protocol has no device clock.  Evenly spaced at the
               device's rate: the analysis should prefer it to ``t_host``.
``length_mm``  float64, absolute bar length ``L = cal_mm + displacement``
               (``analysis/README.md``, "The instrument").  Not a measurement where
               ``status`` has OVER_RANGE or SENSOR_FAULT (use :attr:`SampleBatch.valid`).
``seq``        int64, unwrapped sample number, strictly increasing within a
               source's life; a step larger than 1 is a lost sample, already
               reported by a ``lost`` event.
``status``     uint8, :class:`ballbar.protocol.Status` bits.

Events
------
See :class:`EventKind`.  Every loss is reported exactly once, with its count,
in a ``lost`` event; decoder drops (garbage, bad CRC, bad lines) are reported as
``decode_errors`` with the counts since the previous report, by reason.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ballbar.analysis.timeaxis import GAP_PERIODS, Lost
from ballbar.protocol import INVALID

#: One sample as a record, for writers that want rows (MCAP, CSV).
SAMPLE_DTYPE = np.dtype(
    [("t_host", "<f8"), ("t_device", "<f8"), ("length_mm", "<f8"), ("seq", "<i8"), ("status", "u1")]
)


class EventKind(StrEnum):
    """What happened to a source, besides samples.

    ``opened``       the port, simulator or recording is open (``detail``: what)
    ``unplugged``    the port raised mid-read (``detail``: the error); the source
                     closes it and retries with backoff
    ``replugged``    the port is open again; ``gap_s``: the outage (the samples
                     lost across it follow as a ``lost`` event, ``detail="outage"``)
    ``lost``         ``count`` samples never received, from ``seq`` on;
                     ``detail``: ``gap`` (a sequence gap), ``outage`` (across an
                     unplug), ``stall`` (across a stall), ``poll_timeout`` (no
                     answer), ``poll_late`` (the host could not poll in time)
    ``decode_errors`` ``counts``: decoder drops since the last report, by reason
                     (``bad_crc``, ``bad_line``, ``skipped_bytes``, ...)
    ``stall``        no bytes for ``gap_s`` seconds while connected
    ``resumed``      bytes again after a stall; ``gap_s``: the silence
    ``device_reset`` the device's counter or clock went backwards (it restarted);
                     how many samples were lost cannot be known; ``seq``: the
                     first sample after the restart
    ``clock_jump``   the device's clock stepped by more than its sample counter
                     says (``gap_s``: the excess, s; negative: back); ``seq``: the
                     first sample after the step
    ``counter_jump`` the device's sample counter leapt by more than its clock
                     says (``count``: the samples it skipped that the clock
                     says were never taken; none was lost, the numbers run on
                     by the clock); ``seq``: the first sample after the leap
    ``end``          a finite source (a replay, a simulator with a repeat count)
                     has nothing more; ``read`` returns ``None`` from then on
    ``timing``       a polled source's stamps: ``values`` holds ``t_uncertainty_s``
                     (half the p99 request/answer window: how far a reading's
                     stamp may be from when it was taken), ``t_jitter_s`` (half
                     the windows' p1 to p99 spread), ``window_median_s``,
                     ``window_p99_s`` and ``achieved_hz``; sent when first known
                     and whenever the uncertainty grows
    """

    OPENED = "opened"
    UNPLUGGED = "unplugged"
    REPLUGGED = "replugged"
    LOST = "lost"
    DECODE_ERRORS = "decode_errors"
    STALL = "stall"
    RESUMED = "resumed"
    DEVICE_RESET = "device_reset"
    CLOCK_JUMP = "clock_jump"
    COUNTER_JUMP = "counter_jump"
    END = "end"
    TIMING = "timing"


@dataclass(frozen=True)
class SourceEvent:
    """One event of a source; ``t_host`` on the host's monotonic clock."""

    kind: EventKind
    t_host: float
    source: str = ""
    count: int = 0
    gap_s: float = 0.0
    seq: int | None = None
    detail: str = ""
    counts: Mapping[str, int] = field(default_factory=dict)
    values: Mapping[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready dict (for logs, MCAP and the bus)."""
        out: dict[str, Any] = {"kind": str(self.kind), "t_host": self.t_host, "source": self.source}
        if self.count:
            out["count"] = self.count
        if self.gap_s:
            out["gap_s"] = self.gap_s
        if self.seq is not None:
            out["seq"] = self.seq
        if self.detail:
            out["detail"] = self.detail
        if self.counts:
            out["counts"] = dict(self.counts)
        for key, value in self.values.items():
            out.setdefault(key, value)
        return out


def _f8(a: Any) -> NDArray[np.float64]:
    return np.ascontiguousarray(a, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class SampleBatch:
    """Samples (equal-length columns) and the events that preceded them."""

    t_host: NDArray[np.float64]
    t_device: NDArray[np.float64]
    length_mm: NDArray[np.float64]
    seq: NDArray[np.int64]
    status: NDArray[np.uint8]
    events: tuple[SourceEvent, ...] = ()
    source: str = ""

    def __post_init__(self) -> None:
        n = self.t_host.shape[0]
        for name in ("t_device", "length_mm", "seq", "status"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"SampleBatch column {name} has shape {getattr(self, name).shape}, expected ({n},)")

    @classmethod
    def from_columns(
        cls,
        t_host: Any,
        t_device: Any,
        length_mm: Any,
        seq: Any,
        status: Any,
        events: Sequence[SourceEvent] = (),
        source: str = "",
    ) -> SampleBatch:
        return cls(
            _f8(t_host),
            _f8(t_device),
            _f8(length_mm),
            np.ascontiguousarray(seq, dtype=np.int64),
            np.ascontiguousarray(status, dtype=np.uint8),
            tuple(events),
            source,
        )

    @classmethod
    def empty(cls, events: Sequence[SourceEvent] = (), source: str = "") -> SampleBatch:
        z = np.empty(0)
        return cls(z, z, z, np.empty(0, np.int64), np.empty(0, np.uint8), tuple(events), source)

    def __len__(self) -> int:
        return int(self.t_host.shape[0])

    def __bool__(self) -> bool:
        # A batch of events alone is still news: never falsy because it has no samples.
        return True

    @property
    def valid(self) -> NDArray[np.bool_]:
        """Samples whose length is a measurement (no OVER_RANGE or SENSOR_FAULT)."""
        return (self.status & np.uint8(int(INVALID))) == 0

    @property
    def lost(self) -> int:
        """Samples reported lost by this batch's events."""
        return sum(e.count for e in self.events if e.kind == EventKind.LOST)

    def to_records(self) -> NDArray[np.void]:
        """The samples as a structured array of :data:`SAMPLE_DTYPE`."""
        out = np.empty(len(self), SAMPLE_DTYPE)
        for name in SAMPLE_DTYPE.names or ():
            out[name] = getattr(self, name)
        return out

    @staticmethod
    def concat(batches: Sequence[SampleBatch]) -> SampleBatch:
        """One batch of all samples and events, in order."""
        if not batches:
            return SampleBatch.empty()
        return SampleBatch(
            np.concatenate([b.t_host for b in batches]),
            np.concatenate([b.t_device for b in batches]),
            np.concatenate([b.length_mm for b in batches]),
            np.concatenate([b.seq for b in batches]),
            np.concatenate([b.status for b in batches]),
            tuple(e for b in batches for e in b.events),
            batches[0].source,
        )


def break_reason(event: Mapping[str, Any]) -> str | None:
    """Why a source or logger event (``event`` or ``kind`` naming it) breaks the analysis's time axis, or None.

    A device reset (the daemon re-bases the restarted clock, so the times do not
    show the outage), a device clock jump, and ``GAP_PERIODS`` or more samples
    lost or not logged in a row (which the times do show; named here, as
    :class:`~ballbar.analysis.timeaxis.Lost`: the analysis may take a short one
    as a drop-out and analyse the test across it).
    """
    kind = str(event.get("event") or event.get("kind") or "")
    count = int(event.get("count") or 0)
    detail = str(event.get("detail") or "")
    if kind == EventKind.DEVICE_RESET:
        return "device reset (its sample counter or clock restarted; how long it was down is unknown)"
    if kind == EventKind.CLOCK_JUMP:
        return f"device clock jump of {float(event.get('gap_s') or 0.0):+.3f} s (its sample counter ran on)"
    if kind == EventKind.LOST and count >= GAP_PERIODS:
        return Lost(f"{count} samples lost ({detail or 'gap'})")
    if kind == "log_gap" and count:
        return Lost(f"{count} samples not logged ({detail or 'write error'})")
    return None


def break_seq(event: Mapping[str, Any]) -> int | None:
    """The sample number of the first sample after an event's break (None where the event does not say)."""
    seq = event.get("seq")
    if not isinstance(seq, int) or isinstance(seq, bool):
        return None
    kind = str(event.get("event") or event.get("kind") or "")
    return seq + int(event.get("count") or 0) if kind == EventKind.LOST else seq


def breaks_in(events: Sequence[SourceEvent], seq: NDArray[np.int64]) -> list[tuple[int, str]]:
    """``(index, reason)`` of the breaks these events report among samples numbered ``seq`` (increasing).

    ``index``: the first sample after the break (``len(seq)``: after them all).
    An event without a sample number falls before the samples.
    """
    out = []
    for ev in events:
        d = ev.to_dict()
        reason = break_reason(d)
        if reason is None:
            continue
        at = break_seq(d)
        out.append((int(np.searchsorted(seq, at)) if at is not None else 0, reason))
    return out


@dataclass
class SourceStats:
    """Running totals of a source (a copy: :meth:`Source.stats` returns a snapshot).

    ``lost`` counts every sample reported lost, whatever the cause; ``reads`` the
    port reads that returned bytes (a serial source: about one per batch period
    while samples flow); ``decode``
    the decoder's drops by reason; ``clock_ratio`` and ``clock_offset_s`` the
    current device-to-host clock map (``t_host = offset + ratio * t_device``),
    ``drift_ppm`` its ratio's departure from 1; ``poll`` a polled source's
    request/answer windows and achieved rate
    (:meth:`~ballbar.daemon.sources.SerialSource.poll_timing`), else empty.
    """

    samples: int = 0
    lost: int = 0
    batches: int = 0
    bytes_read: int = 0
    reads: int = 0
    unplugs: int = 0
    replugs: int = 0
    stalls: int = 0
    resets: int = 0
    clock_jumps: int = 0
    connected: bool = False
    decode: dict[str, int] = field(default_factory=dict)
    lost_by_cause: dict[str, int] = field(default_factory=dict)
    clock_ratio: float = float("nan")
    clock_offset_s: float = float("nan")
    poll: dict[str, float] = field(default_factory=dict)

    @property
    def drift_ppm(self) -> float:
        return (self.clock_ratio - 1.0) * 1e6

    def copy(self) -> SourceStats:
        return SourceStats(**{**self.__dict__, "decode": dict(self.decode), "lost_by_cause": dict(self.lost_by_cause),
                              "poll": dict(self.poll)})

    def to_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        out["decode"] = dict(self.decode)
        out["lost_by_cause"] = dict(self.lost_by_cause)
        out["poll"] = dict(self.poll)
        out["drift_ppm"] = self.drift_ppm
        return out



@dataclass
class Recording:
    """What the analysis takes from a recording.

    ``t``, ``L``: the samples' times (s) and lengths (mm); ``breaks``:
    ``(index, reason)``, a discontinuity the times may not show just before
    sample ``index`` (:func:`ballbar.analysis.engine.analyze_recording`);
    ``axis``: which clock ``t`` is (``"device"``, ``"host"``, or ``"t_s"`` for
    a CSV); ``name``: the file or directory, for messages; ``timing``: a
    polled source's ``timing`` events, ``(t_host, uncertainty, jitter)``
    (:mod:`ballbar.analysis.polled`), stated on each result; ``controller``: the CNC controller's main
    program from sample ``index`` on, ``(index, known, program)`` (``[controller]``'s records).
    """

    t: np.ndarray
    L: np.ndarray
    breaks: list[tuple[int, str]] = field(default_factory=list)
    axis: str = "t_s"
    name: str = ""
    timing: list[tuple[float, float, float]] = field(default_factory=list)
    controller: list[tuple[int, bool, str | None]] = field(default_factory=list)  # (index, known, program)


__all__ = ["SAMPLE_DTYPE", "EventKind", "Recording", "SampleBatch", "SourceEvent", "SourceStats", "break_reason",
           "break_seq", "breaks_in"]
