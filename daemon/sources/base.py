"""The interface every source implements (:class:`Source`), and the limits they share."""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
from collections.abc import Iterator
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from ballbar.protocol._common import add_counts

from ..errors import SourceClosed
from ..listeners import MERGE_S
from ..samples import EventKind, SampleBatch, SourceEvent, SourceStats

log = logging.getLogger(__name__)

RATE_MIN_HZ = 15.625
RATE_MAX_HZ = 10_000.0
DEFAULT_BATCH_S = 0.02
RELAXED_BATCH_S = MERGE_S  # pace()'s longest: the outputs' merge period
TTY_READ_BYTES = 3000  # a relaxed read of a serial port takes at most about this much (a tty buffers 4 KiB)
WAIT_WARNING_S = 60.0  # how often a port that is not there (yet) is reported again
POLL_WINDOWS = 4096  # request/answer windows kept for the status's median and p99
RATE_SPAN_S = 10.0  # the achieved poll rate: answers over about this long
RATIO_MIN_SPAN_S = 5.0  # a device clock's rate is stated once its map rests on reads over this long
TIMING_FIRST = 64  # answers before the first timing event
TIMING_GROWTH = 1.25  # a timing event again when the stamps' uncertainty grows by this factor
READ_MAX = 1 << 16
READ_MORE_AT = 4000  # a read at least this long is followed by another
READ_BURST_MAX = 1 << 20  # at most this much in one go, however fast the device floods the port
FALLBACK_WAIT_S = 0.02  # ports without a file descriptor (loop://, rfc2217://): their fixed read timeout
PYSERIAL_SCHEMES = ("loop", "socket", "rfc2217", "spy", "alt", "hwgrep", "cp2110")


# ----------------------------------------------------------------------------- the interface


class Source(abc.ABC):
    """Where samples come from.  Subclasses implement :meth:`_read` and :meth:`_close`."""

    scheme: ClassVar[str] = ""

    def __init__(self, url: str, rate_hz: float | None = None, batch_s: float = DEFAULT_BATCH_S) -> None:
        self.url = url
        self.rate_hz = rate_hz
        self.batch_s = batch_s
        self.read_s = batch_s  # the batching period of the moment (pace())
        self._closed = False
        self._finished = False
        self._stats = SourceStats()
        self._events: list[SourceEvent] = []
        self._wake = threading.Event()
        self._close_lock = threading.Lock()
        self._lost_logged_at = -math.inf
        self._decode_logged_at = -math.inf
        self._decode_unlogged: dict[str, int] = {}
        self._lost_unlogged = 0

    # -- public -------------------------------------------------------------------

    def pace(self, period_s: float) -> None:
        """Batches may come ``period_s`` apart for now (see the module docstring)."""
        self.read_s = min(max(self.batch_s, period_s), max(self.batch_s, RELAXED_BATCH_S))

    def read(self, timeout: float | None = None) -> SampleBatch | None:
        """The next batch of samples and events, or ``None`` after ``timeout`` seconds."""
        if self._closed:
            raise SourceClosed(f"{self.url}: read after close")
        if self._finished:
            return None
        deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
        batch = self._read(deadline)
        if batch is not None:
            self._account(batch)
        return batch

    def __iter__(self) -> Iterator[SampleBatch]:
        while not (self._finished or self._closed):
            try:
                batch = self.read(0.5)
            except SourceClosed:
                return
            if batch is not None:
                yield batch

    @property
    def finished(self) -> bool:
        """True once a finite source has delivered everything (its ``end`` event)."""
        return self._finished

    @property
    def closed(self) -> bool:
        return self._closed

    def stats(self) -> SourceStats:
        """A snapshot of the running totals."""
        return self._stats.copy()

    def resume(self, seq: int, t_device_s: float | None, period_s: float | None, offsets: tuple[int, float]) -> bool:
        """Count on from a previous run's last recorded sample (number ``seq``, device time ``t_device_s``, the
        device clock's period ``period_s``; ``offsets``: what :meth:`counter_offsets` said then), before the first
        read: what the device sent meanwhile is then counted lost (``lost``, detail ``restart``), exactly, by its
        own counter.  False where this source cannot (no device counter): the default."""
        return False

    def counter_offsets(self) -> tuple[int, float] | None:
        """How the sample numbers and device times handed out differ from the device's raw counter and clock
        (modulo their wraps; they change at a device reset), for a later run's :meth:`resume`; None: no counter."""
        return None

    def close(self) -> None:
        """Release the port or file; safe twice, and from another thread."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
        self._wake.set()
        self._close()
        self._stats.connected = False
        log.debug("%s: closed", self.url)

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.url}>"

    # -- for subclasses -----------------------------------------------------------

    @abc.abstractmethod
    def _read(self, deadline: float | None) -> SampleBatch | None: ...

    def _close(self) -> None:  # noqa: B027 - optional hook
        pass

    def _event(self, kind: EventKind, **fields: Any) -> SourceEvent:
        ev = SourceEvent(kind, time.monotonic(), self.url, **fields)
        self._events.append(ev)
        self._log_event(ev)
        return ev

    def _take_events(self) -> tuple[SourceEvent, ...]:
        events, self._events = tuple(self._events), []
        return events

    def _sleep_until(self, t: float) -> None:
        """Sleep until monotonic time ``t``; ``close()`` wakes it."""
        wait = t - time.monotonic()
        if wait > 0:
            self._wake.wait(wait)

    def _batch(
        self,
        t_host: NDArray[np.float64],
        t_device: NDArray[np.float64],
        length_mm: NDArray[np.float64],
        seq: NDArray[np.int64],
        status: NDArray[np.uint8],
    ) -> SampleBatch | None:
        """A batch of these samples and the pending events; ``None`` if both are empty."""
        if t_host.shape[0] == 0 and not self._events:
            return None
        return SampleBatch(t_host, t_device, length_mm, seq, status, self._take_events(), self.url)

    def _events_only(self) -> SampleBatch | None:
        if not self._events:
            return None
        return SampleBatch.empty(self._take_events(), self.url)

    def _gap_events(self, gaps: list[tuple[int, int]], detail: str = "gap") -> None:
        for seq0, count in gaps:
            self._event(EventKind.LOST, count=count, seq=seq0, detail=detail)
            detail = "gap"

    def _account(self, batch: SampleBatch) -> None:
        s = self._stats
        s.samples += len(batch)
        s.batches += 1
        for e in batch.events:
            if e.kind == EventKind.LOST:
                s.lost += e.count
                s.lost_by_cause[e.detail] = s.lost_by_cause.get(e.detail, 0) + e.count
            elif e.kind == EventKind.UNPLUGGED:
                s.unplugs += 1
            elif e.kind == EventKind.REPLUGGED:
                s.replugs += 1
            elif e.kind == EventKind.STALL:
                s.stalls += 1
            elif e.kind == EventKind.DEVICE_RESET:
                s.resets += 1
            elif e.kind == EventKind.CLOCK_JUMP:
                s.clock_jumps += 1
            elif e.kind == EventKind.DECODE_ERRORS:
                add_counts(s.decode, dict(e.counts))

    def _log_event(self, ev: SourceEvent) -> None:
        k = ev.kind
        if k == EventKind.LOST:
            # Rate-limited: a bad cable must not flood the journal.
            self._lost_unlogged += ev.count
            if ev.t_host - self._lost_logged_at >= 10.0 or ev.detail == "outage":
                log.warning("%s: %d samples lost (%s, from seq %s)", self.url, self._lost_unlogged, ev.detail, ev.seq)
                self._lost_logged_at, self._lost_unlogged = ev.t_host, 0
        elif k == EventKind.DECODE_ERRORS:
            # Line noise drops bytes all the time: the counts at INFO, rate-limited like the losses.
            add_counts(self._decode_unlogged, dict(ev.counts))
            if ev.t_host - self._decode_logged_at >= 10.0:
                log.info("%s: the decoder dropped %s", self.url,
                         ", ".join(f"{v} {k}" for k, v in sorted(self._decode_unlogged.items())))
                self._decode_logged_at, self._decode_unlogged = ev.t_host, {}
        elif k in (EventKind.UNPLUGGED, EventKind.STALL, EventKind.DEVICE_RESET, EventKind.CLOCK_JUMP,
                   EventKind.COUNTER_JUMP):
            log.warning("%s: %s %s", self.url, k, ev.detail or (f"after {ev.gap_s:.3f} s" if ev.gap_s else ""))
        else:
            log.info("%s: %s %s", self.url, k, ev.detail or (f"after {ev.gap_s:.3f} s" if ev.gap_s else ""))


# ----------------------------------------------------------------------------- serial ports
