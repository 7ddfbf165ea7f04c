"""Sample sources: one interface for every way samples arrive.

A source is opened from a URL (the configuration's ``source`` key) plus typed
keyword options, and delivers :class:`~ballbar.daemon.samples.SampleBatch`
objects::

    with open_source("serial:/dev/ttyUSB0?protocol=binary&rate=1000", cal_mm=100.0012) as src:
        while running:
            batch = src.read(timeout=0.5)   # None: nothing in 0.5 s
            if batch is not None:
                handle(batch)               # columns + batch.events

    for batch in open_source("replay:run.csv?speed=max"):   # until the recording ends
        ...

The interface (:class:`Source`)
-------------------------------
``read(timeout=None) -> SampleBatch | None``
    Blocks until samples or events are available, at most ``timeout`` seconds
    (plus up to ``batch_s``, the batching period, default 20 ms; ``None`` waits
    indefinitely); returns ``None`` on timeout and, for good, after a finite
    source's ``end`` event.  A batch holds what arrived in about ``batch_s``
    (about 200 samples at 10 kHz).  Never raises for bad bytes, an unplugged
    adapter or a stalled device: those are events.  Raises
    :class:`~ballbar.daemon.errors.SourceClosed` after :meth:`Source.close`.
``iter(source)``
    Batches until the source is finished (a replay's end) or closed.
``close()``
    Safe twice and from another thread (it interrupts a blocked ``read``).
    Sources are context managers.
``stats() -> SourceStats``, ``finished``, ``rate_hz``, ``url``.
``pace(period_s)``
    The consumers can take batches ``period_s`` apart for now: the source reads
    that often (never more often than ``batch_s``, never less than every
    ``RELAXED_BATCH_S``) until told otherwise.  The daemon relaxes it while no
    result can be due (between tests, mid-circle) and tightens it back to
    ``batch_s`` as one nears: the 20 ms batches where latency counts, a
    wake-up as seldom as the outputs merge (every 0.25 s) where it does not:
    each wake-up costs a read's fixed part again (about 0.7 ms of a CPU whose
    caches went cold meanwhile), however few samples it brings.  A serial port
    is never left to hold more than ``TTY_READ_BYTES`` between reads (at the
    byte rate it has been seen to run): past the line discipline's 4 KiB buffer
    the kernel throttles the adapter, and a device without flow control
    overruns.  Where that is sooner than the batch is due (``drain_s``: 1 kHz
    at 17 kB/s every 0.18 s; 10 kHz, or 1 kHz sped up 20 times, every 20 ms)
    the port is read that often, but what is read is only gathered, and
    decoded and stamped once per batch.

A serial source makes at most one batch per batch period (``read_s``) while
samples flow: it sleeps to the next boundary of a ``read_s`` grid on the
monotonic clock, waking every ``drain_s`` on the way to gather what the port
has, and decodes it all at the boundary; when nothing came (idle, or a device
slower than one sample per batch period) it waits for the first bytes with
``poll()`` and takes them at once.  The port's settings (its timeout among
them) are applied once, at open: pyserial re-applies termios and the lock on
each assignment.  ``stats().reads`` counts the reads that returned bytes.

Call ``read`` from one thread that does nothing else (the pipeline's reader):
a serial port's kernel buffer holds only a few tenths of a second at 10 kHz,
so a consumer that is slow must be decoupled by a queue, not by reading late.

URL scheme
----------
``serial:PORT[?options]``
    ``PORT`` is a device path (``/dev/ttyUSB0``, ``/dev/serial/by-id/...``, a
    pty or the link that ``ballbar.tools.simdevice`` prints) or any pyserial
    URL (``loop://``, ``socket://host:port``, ``rfc2217://host:port``);
    ``serial:///dev/ttyUSB0`` is accepted too, and a bare ``/dev/...`` path or
    pyserial URL means ``serial:``.  Options:

    ``protocol``  ``binary`` (default), ``ascii``, or a gauge profile:
                  ``mitutoyo``, ``sylvac``, ``tesa`` (``protocol/README.md``;
                  a profile sets the framing, request, mode, baud and line
                  settings, error words and unit, each of which an option
                  below may override)
    ``mode``      ``stream`` (default) or ``poll`` (ascii and profiles: the
                  host sends ``request`` once per period and reads one
                  answer; a polled profile's default)
    ``cal_mm``    required: the bar's length at zero displacement (its
                  calibration), added to every reading: ``L = cal_mm + x``
    ``rate``      nominal sample rate in Hz, 15.625..10000 (required for
                  ``poll``; for ascii lines with a timestamp it lets lost lines
                  be counted; it sets the stall timeout's default)
    ``baud``      default 2000000 (10 kHz of binary frames needs 1.7 Mbaud;
                  ptys and USB CDC devices ignore it); a profile's own default
                  (Mitutoyo 9600, Sylvac and TESA 4800).  A profile's rate
                  beyond what the line carries at this baud is refused
    ``framing``   data bits, parity, stop bits: ``8N1`` (default), a
                  profile's own (``7E2`` for Sylvac and TESA)
    ``unit``, ``scale``, ``timestamp`` (``s``, ``ms``, ``us``; absent: none),
    ``max_line``, ``request`` (percent-encoded, default ``%3F%0D`` = ``?\\r``)
                  the ASCII format (:class:`~ballbar.protocol.AsciiFormat`)
    ``batch_s``   batching period, default 0.02
    ``stall_s``   silence that counts as a stall, default max(0.5, 20 periods)
    ``poll_timeout_s``  answer timeout in poll mode, default max(0.05, 2 periods)
    ``retry_min_s``, ``retry_max_s``  reopen backoff after an unplug, 0.05..2 s
    ``exclusive`` lock the port against a second reader (default true)

``sim:[?options]``
    The in-process simulator (``ballbar.tools.simulator``) on the host clock:
    ``rate`` (Hz, default the plan's), ``speedup`` (default 1; ``max`` = as
    fast as possible), ``seed`` (0), ``repeat`` (number of tests, default 1;
    0 = forever), ``gap_s`` (between tests, 0), ``batch_s``.  Keyword options
    ``plan`` (:class:`~ballbar.analysis.plan.TestPlan`) and ``machine``
    (``MachineModel``) say what to simulate; or ``library`` (a
    :class:`~ballbar.analysis.plans.PlanLibrary` of several), ``run_plans``
    (which of its plans, in turn; default all) and ``machine`` (a
    ``Machine3D``: ``ballbar.tools.machine3d``), a set of tests on a machine
    with X, Y and Z errors, each program with its signature, the lengths as
    the bar assembled for each plan reads them.  Samples carry ``SIMULATED``.

``replay:PATH[?options]``
    A recording (CSV ``t_s,length_mm`` now; the daemon's MCAP later):
    ``speed`` (1 = real time, default; 10 = ten times faster; ``max`` = as fast
    as possible), ``rate`` (Hz: sample numbers from the recorded times, so that
    gaps count as lost; default: one number per row), ``batch_s``.

Every option may also be given as a keyword argument of :func:`open_source`
(``cal_mm=100.0``, ``rate=1000``); giving one both ways is an error, and so is
an unknown key (named in the message).

Time stamps
-----------
``t_device`` is the device's sample clock where the protocol has one (binary
frames; ASCII lines with a timestamp), unwrapped.  ``t_host`` is that clock
mapped to ``time.monotonic`` by :class:`~ballbar.daemon.timebase.ClockMap`
(lower envelope of read times, with the drift in ``stats().drift_ppm``).
Without a device clock, ``t_host`` is the host's estimate: sample numbers at the
nominal rate mapped the same way, or the read time when no rate is known; in
poll mode the midpoint between request and answer: a polled gauge has no
clock, and when within that window it took its reading is not known.  The
windows' median, p99 and the achieved rate are in ``stats().poll``; the
half-window's p99 (the stamps' uncertainty) goes out as a ``timing`` event
when first known and whenever it grows by a quarter, and the analysis of such
samples states it (:mod:`ballbar.analysis.polled`).  Replays and the simulator
place their own time base on the host clock at their speed.

Losses and faults
-----------------
A gap in the device's sample counter is reported as a ``lost`` event with its
exact count (never interpolated or papered over).  An unplugged adapter (the
port raises mid-read, or cannot be opened at start) is an ``unplugged`` event;
the source retries with exponential backoff and reports ``replugged`` with the
outage when the port returns, then the samples lost across it.  A device that
stops sending is a ``stall``, then ``resumed``.  A restarted device (its
counter or clock went back) is a ``device_reset``, a device clock that steps by
more than its counter says a ``clock_jump``; each names the first sample after
it (``seq``), so that the analysis can place the break exactly.
"""

from __future__ import annotations

import abc
import collections
import contextlib
import dataclasses
import logging
import math
import os
import select
import threading
import time
import urllib.parse
from collections.abc import Callable, Iterator
from typing import Any, ClassVar

import numpy as np
import serial
from numpy.typing import NDArray

from ballbar.protocol import AsciiDecoder, AsciiFormat, BinaryDecoder, Readings, Status
from ballbar.protocol._common import add_counts
from ballbar.protocol.gauges import PROFILES

from .errors import SourceClosed, SourceConfigError, SourceError
from .listeners import MERGE_S
from .samples import EventKind, SampleBatch, SourceEvent, SourceStats
from .timebase import Stamper

log = logging.getLogger(__name__)

RATE_MIN_HZ = 15.625
RATE_MAX_HZ = 10_000.0
DEFAULT_BATCH_S = 0.02
RELAXED_BATCH_S = MERGE_S  # pace()'s longest: the outputs' merge period
TTY_READ_BYTES = 3000  # a relaxed read of a serial port takes at most about this much (a tty buffers 4 KiB)
WAIT_WARNING_S = 60.0  # how often a port that is not there (yet) is reported again
POLL_WINDOWS = 4096  # request/answer windows kept for the status's median and p99
RATE_SPAN_S = 10.0  # the achieved poll rate: answers over about this long
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
            log.debug("%s: decoder dropped %s", self.url, dict(ev.counts))
        elif k in (EventKind.UNPLUGGED, EventKind.STALL, EventKind.DEVICE_RESET, EventKind.CLOCK_JUMP):
            log.warning("%s: %s %s", self.url, k, ev.detail or (f"after {ev.gap_s:.3f} s" if ev.gap_s else ""))
        else:
            log.info("%s: %s %s", self.url, k, ev.detail or (f"after {ev.gap_s:.3f} s" if ev.gap_s else ""))


# ----------------------------------------------------------------------------- serial ports


class SerialSource(Source):
    """A device on a serial port (or anything ``serial.serial_for_url`` opens)."""

    scheme = "serial"

    def __init__(
        self,
        url: str,
        port: str,
        *,
        cal_mm: float,
        protocol: str = "binary",
        mode: str = "stream",
        rate_hz: float | None = None,
        baud: int = 2_000_000,
        fmt: AsciiFormat | None = None,
        batch_s: float = DEFAULT_BATCH_S,
        stall_s: float | None = None,
        poll_timeout_s: float | None = None,
        retry_min_s: float = 0.05,
        retry_max_s: float = 2.0,
        exclusive: bool = True,
        bytesize: int = 8,
        parity: str = "N",
        stopbits: int = 1,
    ) -> None:
        super().__init__(url, rate_hz, batch_s)
        if protocol not in ("binary", "ascii", *PROFILES):
            raise SourceConfigError(f"{url}: protocol must be binary, ascii or {', '.join(PROFILES)}, not {protocol!r}")
        if mode not in ("stream", "poll"):
            raise SourceConfigError(f"{url}: mode must be stream or poll, not {mode!r}")
        if mode == "poll" and protocol == "binary":
            raise SourceConfigError(f"{url}: mode=poll needs protocol=ascii or a gauge profile")
        if mode == "poll" and rate_hz is None:
            raise SourceConfigError(f"{url}: mode=poll needs rate (the polling rate in Hz)")
        self.port_url = port
        self.protocol = protocol
        self.mode = mode
        self.cal_mm = cal_mm
        self.baud = baud
        self.fmt = fmt or AsciiFormat()
        period = 1.0 / rate_hz if rate_hz else 0.05
        self.stall_s = stall_s if stall_s is not None else max(0.5, 20 * period)
        self.poll_timeout_s = poll_timeout_s if poll_timeout_s is not None else max(0.05, 2 * period)
        self.retry_min_s = retry_min_s
        self.retry_max_s = max(retry_max_s, retry_min_s)
        self.exclusive = exclusive
        self.bytesize, self.parity, self.stopbits = bytesize, parity, stopbits
        self._decoder: BinaryDecoder | AsciiDecoder = (
            BinaryDecoder() if protocol == "binary" else AsciiDecoder(self.fmt)
        )
        self._stamper = Stamper(self._decoder.seq_modulus, self._decoder.clock_wrap_s, rate_hz)
        self._reported: dict[str, int] = {}
        self._port: serial.SerialBase | None = None
        self._port_lock = threading.Lock()
        # How the reader waits (see "reading"): the port's descriptor and a poll object on it and on
        # the abort pipe that close() writes to; None for ports without a descriptor.
        self._fd: int | None = None
        self._poller: select.poll | None = None
        self._abort: tuple[int, int] | None = None
        self._napper: select.poll | None = None
        self._io = threading.RLock()  # held by the reader inside read(); close() takes it to release the port
        self._held = b""  # a port without a descriptor: the byte its wait read
        self._flowing = False  # the last read found bytes: the next one waits for the batch boundary
        self._lost: BaseException | None = None  # the port went away after bytes not decoded yet
        self._bytes_per_s = 0.0  # the port's byte rate lately (drain_s keeps a read under TTY_READ_BYTES)
        self._ever_open = False
        self._retry_s = retry_min_s
        self._next_retry = 0.0
        self._down_since: float | None = None
        self._failures = 0
        self._next_wait_warning = 0.0
        self._last_rx = time.monotonic()
        self._stalled = False
        self._gap_cause: str | None = None
        self._duplicates = 0
        self._unsolicited = 0
        # poll mode
        self._tick0: float | None = None
        self._k = 0
        self._out: tuple[int, float] | None = None
        self._pending: list[tuple[int, float, float, int]] = []
        self._poll_batch_start = 0.0
        self._windows: collections.deque[float] = collections.deque(maxlen=POLL_WINDOWS)
        self._answers: collections.deque[float] = collections.deque(maxlen=POLL_WINDOWS)
        self._timing_reported = 0.0  # the stamps' uncertainty last sent as a timing event, s
        self._try_open(time.monotonic(), first=True)

    # -- port life ----------------------------------------------------------------

    def _try_open(self, now: float, first: bool = False) -> None:
        try:
            # The timeout is set here, once: assigning it later re-applies termios (and the lock) each time.
            # 0: a read takes what has arrived; the reader waits for bytes with poll() (see _wait).
            port = serial.serial_for_url(self.port_url, baudrate=self.baud, bytesize=self.bytesize,
                                         parity=self.parity, stopbits=self.stopbits, timeout=0,
                                         exclusive=self.exclusive)
            try:
                self._setup_wait(port)
            except (OSError, ValueError) as err:  # as a port that could not be opened: retried
                with contextlib.suppress(Exception):
                    port.close()
                raise serial.SerialException(f"cannot wait on {self.port_url}: {err}") from err
        except ValueError as err:  # pyserial: bad URL or setting, never a missing device
            raise SourceConfigError(f"{self.url}: {err}") from err
        except (serial.SerialException, OSError) as err:
            self._failures += 1
            self._next_retry = now + self._retry_s
            self._retry_s = min(2 * self._retry_s, self.retry_max_s)
            if first:
                self._down_since = now
                self._event(EventKind.UNPLUGGED, detail=f"cannot open {self.port_url}: {err}")
                self._stats.connected = False
                self._next_wait_warning = now + WAIT_WARNING_S
            elif now >= self._next_wait_warning:
                # A service waits for its adapter, visibly: one warning a minute, not one an attempt.
                self._next_wait_warning = now + WAIT_WARNING_S
                since = now - self._down_since if self._down_since is not None else 0.0
                log.warning("%s: still waiting for %s after %.0f s (%d attempts): %s",
                            self.url, self.port_url, since, self._failures, err)
            return
        with self._port_lock:
            if self._closed:
                port.close()
                return
            self._port = port
        self._flowing = False
        self._held = b""
        self._failures = 0
        self._retry_s = self.retry_min_s
        self._stats.connected = True
        self._last_rx = now
        self._stalled = False
        self._out = None  # the poll clock keeps running: ticks missed while away are lost
        # A stream may be joined mid-line: the first line may be the tail of one.
        self._decoder.discard(rejoin=self.mode == "stream")
        if not self._ever_open:
            self._ever_open = True
            self._event(EventKind.OPENED, detail=f"{self.port_url} ({self.protocol}, {self.mode})")
        else:
            gap = now - self._down_since if self._down_since is not None else 0.0
            self._event(EventKind.REPLUGGED, gap_s=gap, detail=self.port_url)
            self._gap_cause = "outage"
        self._down_since = None

    def _port_lost(self, err: BaseException) -> None:
        now = time.monotonic()
        self._drop_port()
        self._decoder.discard()  # a partial frame or line of the old connection is garbage now
        self._down_since = now
        self._retry_s = self.retry_min_s
        self._next_retry = now + self._retry_s
        self._retry_s = min(2 * self._retry_s, self.retry_max_s)
        self._stats.connected = False
        self._event(EventKind.UNPLUGGED, detail=str(err) or type(err).__name__)
        if self._out is not None:  # the request in flight has no answer to come
            self._lose(self._out[0], 1, "outage")
            self._out = None

    def _setup_wait(self, port: serial.SerialBase) -> None:
        """Wait on the port's descriptor (and the abort pipe) with poll(); a port without one reads with a
        fixed timeout, set once."""
        try:
            fd = port.fileno()
        except Exception:  # loop://, rfc2217://: no descriptor
            fd = None
        if fd is None or fd < 0:
            self._fd, self._poller = None, None
            port.timeout = FALLBACK_WAIT_S
            return
        os.set_blocking(fd, False)  # pyserial opens ttys so already; a socket:// port too
        if self._abort is None:
            r, w = os.pipe()
            os.set_blocking(r, False)
            os.set_blocking(w, False)
            self._abort = (r, w)
            self._napper = select.poll()  # sleeps to the batch boundary: one poll(), close() ends it
            self._napper.register(r, select.POLLIN)
        poller = select.poll()
        poller.register(fd, select.POLLIN | select.POLLPRI)
        poller.register(self._abort[0], select.POLLIN)
        self._fd, self._poller = fd, poller

    def _drop_port(self) -> None:
        with self._port_lock:
            port, self._port = self._port, None
            self._fd, self._poller = None, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()

    def _close(self) -> None:
        # Wake the reader (a poll() on the abort pipe; a port without a descriptor cancels its read), then
        # release the port and the pipe once the reader is out of read(): never under its feet.
        if self._abort is not None:
            with contextlib.suppress(OSError):
                os.write(self._abort[1], b"x")
        port = self._port
        if port is not None and self._fd is None:
            with contextlib.suppress(Exception):
                port.cancel_read()
        got = self._io.acquire(timeout=2.0)
        try:
            self._drop_port()
            if got and self._abort is not None:
                for fd in self._abort:
                    with contextlib.suppress(OSError):
                        os.close(fd)
                self._abort = None
            elif not got:
                log.warning("%s: the reader did not leave read() within 2 s of close()", self.url)
        finally:
            if got:
                self._io.release()

    # -- reading ------------------------------------------------------------------

    def _read(self, deadline: float | None) -> SampleBatch | None:
        with self._io:
            return self._read_locked(deadline)

    def _read_locked(self, deadline: float | None) -> SampleBatch | None:
        while not self._closed:
            now = time.monotonic()
            if self._port is None:
                if now >= self._next_retry:
                    self._try_open(now)
                if self._port is None:
                    batch = self._events_only()
                    if batch is not None:
                        return batch
                    if deadline is not None and now >= deadline:
                        return None
                    self._sleep_until(self._next_retry if deadline is None else min(self._next_retry, deadline))
                    continue
            got = self._poll_step(deadline) if self.mode == "poll" else self._stream_step(deadline)
            if got is not None:
                return got
            if deadline is not None and time.monotonic() >= deadline:
                return None
        return None

    # The port is read in two steps, neither of which touches its settings: wait until it has bytes
    # (poll() on its descriptor, woken by close() through the abort pipe), then take everything it has.

    def _wait(self, until: float | None) -> bool:
        """Wait until the port has bytes (True; also when it hung up), ``until`` passes or close() (False)."""
        poller = self._poller
        if poller is None:
            return self._wait_fallback(until)
        while not self._closed:
            left = None if until is None else until - time.monotonic()
            if left is not None and left <= 0:
                return False
            try:
                ready = poller.poll(None if left is None else max(1, math.ceil(left * 1000.0)))
            except (OSError, ValueError):  # the port went away under a concurrent close()
                return False
            if self._closed:
                return False
            if any(fd == self._fd for fd, _ in ready):
                return True
        return False

    def _nap(self, until: float) -> None:
        """Sleep until ``until``; close() ends it."""
        napper = self._napper
        if napper is None or self._fd is None:
            self._sleep_until(until)
            return
        left = until - time.monotonic()
        if left > 0:
            with contextlib.suppress(OSError, ValueError):
                napper.poll(math.ceil(left * 1000.0))

    def _wait_fallback(self, until: float | None) -> bool:
        port = self._port
        try:
            while port is not None and not self._closed:
                if port.in_waiting:
                    return True
                if until is not None and time.monotonic() >= until:
                    return False
                b = port.read(1)  # the fixed timeout set at open
                if b:
                    self._held += b
                    return True
        except (serial.SerialException, OSError) as err:
            if not self._closed:
                self._port_lost(err)
        except (TypeError, AttributeError):  # pyserial after a concurrent close()
            pass
        return False

    def _read_now(self, waited: bool = False, defer_loss: bool = False) -> bytes | None:
        """Everything the port has now (maybe nothing), or ``None`` when it went away (an event is queued).

        ``waited``: the wait said the port has bytes; none then is a port that hung up.  ``defer_loss``:
        bytes read before are not decoded yet: the loss is kept in ``_lost`` for after them (the decoder's
        partial frame must not be dropped before they reach it).
        """
        port = self._port
        if port is None:
            return None
        fd = self._fd
        try:
            if fd is None:
                n = port.in_waiting
                data = self._held + (port.read(n) if n else b"")
                self._held = b""
            else:
                chunks = []
                total = 0
                # A tty hands over at most its line buffer (4 KiB) a read: a read that long may have left
                # more behind; a shorter one took all (asking again would cost a tty buffer flush).
                while total < READ_BURST_MAX:
                    try:
                        chunk = os.read(fd, READ_MAX)
                    except BlockingIOError:
                        break
                    if not chunk:
                        break
                    chunks.append(chunk)
                    total += len(chunk)
                    if len(chunk) < READ_MORE_AT:
                        break
                data = b"".join(chunks) if len(chunks) != 1 else chunks[0]
            if waited and not data:
                raise serial.SerialException(
                    "device reports readiness to read but returned no data (device disconnected?)"
                )
        except (serial.SerialException, OSError) as err:
            if defer_loss:
                self._lost = err
            elif not self._closed:
                self._port_lost(err)
            return None
        except (TypeError, AttributeError) as err:  # pyserial after a concurrent close()
            if self._closed:
                return None
            raise SourceError(f"{self.url}: {err}") from err
        if data:
            self._stats.bytes_read += len(data)
            self._stats.reads += 1
        return data

    def _check_stall(self, now: float, got_bytes: bool) -> None:
        if got_bytes:
            if self._stalled:
                self._stalled = False
                self._event(EventKind.RESUMED, gap_s=now - self._last_rx)
                self._gap_cause = self._gap_cause or "stall"
            self._last_rx = now
        elif not self._stalled and now - self._last_rx >= self.stall_s:
            self._stalled = True
            self._event(EventKind.STALL, gap_s=now - self._last_rx)

    def _stream_step(self, deadline: float | None) -> SampleBatch | None:
        """One batch: at most one per batch period (``read_s``) while samples flow.

        While bytes flow (the last read found some, and more than one sample comes per batch period),
        gather what comes until the next boundary of a ``read_s`` grid on the monotonic clock
        (:meth:`_drain_until`) and decode it then.  Otherwise (idle, or a slow device) wait for the first
        bytes and take them at once.
        """
        data: bytes | None = b""
        b = self.read_s
        # at most one read per batch period while more than one sample comes per period
        if self._flowing and not (self.rate_hz is not None and 1.0 / self.rate_hz >= b):
            data = self._drain_until((math.floor(time.monotonic() / b) + 1.0) * b)
            if self._closed and not data:
                return None
        if data is not None and not data:
            until = deadline
            if not self._stalled:
                until = self._last_rx + self.stall_s if until is None else min(until, self._last_rx + self.stall_s)
            data = self._read_now(waited=True) if self._wait(until) else b""
        if data is None:
            self._flowing = False
            return self._events_only()
        t_read = time.monotonic()
        if data and self._flowing and t_read > self._last_rx:
            rate = len(data) / (t_read - self._last_rx)  # bytes/s since the last read that had bytes
            self._bytes_per_s = rate if not self._bytes_per_s else 0.8 * self._bytes_per_s + 0.2 * rate
        self._flowing = bool(data)
        self._check_stall(t_read, bool(data))
        if not data:
            return self._events_only()
        batch = self._samples(self._decoder.feed(data), t_read)
        if self._lost is not None:  # the port went away after these bytes: they are decoded, now its event
            err, self._lost = self._lost, None
            if not self._closed:
                self._port_lost(err)
        return batch

    def _drain_until(self, until: float) -> bytes | None:
        """All the port sends until ``until``, read every :attr:`drain_s` and decoded at once after.

        A read's fixed part (the wake-up, the decoder's and the stamper's calls on a CPU whose caches went
        cold meanwhile, about 0.7 ms) is paid once per batch, not once per tty-sized read.  Where the port
        goes away meanwhile, what was read before is returned and the loss is handled after it is decoded
        (``_lost``); ``None``: it went away with nothing read (its event is queued).
        """
        parts: list[bytes] = []
        d = self.drain_s
        while True:
            self._nap(min(until, (math.floor(time.monotonic() / d) + 1.0) * d))
            if self._closed:
                break
            data = self._read_now(defer_loss=bool(parts))
            if data is None:
                if not parts:
                    return None
                break
            if data:
                parts.append(data)
            if time.monotonic() >= until:
                break
        return b"".join(parts) if len(parts) != 1 else parts[0]

    def _samples(self, r: Readings, t_read: float) -> SampleBatch | None:
        st = self._stamper.stamp(r, t_read)
        if st.gaps:
            self._gap_events(st.gaps, self._gap_cause or "gap")
        if len(r):
            self._gap_cause = None
        for seq in st.reset_seqs:
            self._event(EventKind.DEVICE_RESET, seq=seq, detail="sample counter or clock went backwards")
        for seq, excess in st.jumps:
            self._event(EventKind.CLOCK_JUMP, seq=seq, gap_s=excess,
                        detail=f"device clock stepped {excess:+.6f} s beyond its sample counter")
        self._duplicates += st.duplicates
        self._report_decode()
        if self._stamper.clock.ready:
            self._stats.clock_ratio = self._stamper.clock.ratio
            self._stats.clock_offset_s = self._stamper.clock.offset
        keep = st.keep
        status = r.status[keep]
        return self._batch(st.t_host, st.t_device, self.cal_mm + r.value_mm[keep], st.seq, status)

    @property
    def drain_s(self) -> float:
        """How long the port may be left between two reads: ``read_s``, or shorter where the port would then
        hold more than ``TTY_READ_BYTES`` at the byte rate it has been seen to run (``batch_s`` before that
        is known).  Reads within a period are only gathered (:meth:`_drain_until`)."""
        if not self._bytes_per_s > 0:
            return min(self.read_s, self.batch_s)  # its rate not seen yet: no longer reads than the batches
        return min(self.read_s, max(self.batch_s, TTY_READ_BYTES / self._bytes_per_s))

    def _report_decode(self) -> None:
        now = dict(self._decoder.dropped)
        if self._duplicates:
            now["duplicate"] = self._duplicates
        if self._unsolicited:
            now["unsolicited"] = self._unsolicited
        delta = {k: v - self._reported.get(k, 0) for k, v in now.items() if v != self._reported.get(k, 0)}
        if delta:
            self._reported = now
            self._event(EventKind.DECODE_ERRORS, counts=delta)

    # -- poll mode ------------------------------------------------------------------

    def _lose(self, seq0: int, count: int, cause: str) -> None:
        self._event(EventKind.LOST, count=count, seq=seq0, detail=cause)

    def _poll_step(self, deadline: float | None) -> SampleBatch | None:
        assert self.rate_hz is not None
        period = 1.0 / self.rate_hz
        now = time.monotonic()
        if self._tick0 is None:
            self._tick0 = now - self._k * period
            self._poll_batch_start = now
        if self._out is not None and now - self._out[1] > self.poll_timeout_s:
            self._lose(self._out[0], 1, "poll_timeout")
            self._out = None
            if self._decoder.pending:  # an answer cut short (a line pulled mid-answer): never parsed
                self._decoder.dropped["cut_line"] = self._decoder.dropped.get("cut_line", 0) + 1
                self._decoder.discard()
        if self._out is None:
            due = self._tick0 + self._k * period
            if now >= due:
                late = int((now - due) / period)
                if late > 0:
                    self._lose(self._k, late, self._gap_cause or "poll_late")
                    self._k += late
                self._gap_cause = None
                if not self._send_request():
                    return self._flush_poll()
                self._out = (self._k, time.monotonic())
                self._k += 1
        # Wait for the answer, the next tick, the end of the batch or the deadline.
        now = time.monotonic()
        nxt = self._out[1] + self.poll_timeout_s if self._out is not None else self._tick0 + self._k * period
        until = min(nxt, self._poll_batch_start + self.read_s)
        if deadline is not None:
            until = min(until, deadline)
        # Returns at the first byte of the answer; what came is read at once.
        data = self._read_now(waited=True) if self._wait(until) else b""
        if data is None:
            return self._flush_poll()
        t_read = time.monotonic()
        self._check_stall(t_read, bool(data))
        if data:
            r = self._decoder.feed(data)
            for i in range(len(r)):
                if self._out is None:
                    self._unsolicited += 1  # an answer nobody asked for
                    continue
                k, t_sent = self._out
                self._pending.append((k, 0.5 * (t_sent + t_read), float(r.value_mm[i]), int(r.status[i])))
                self._windows.append(t_read - t_sent)
                self._answers.append(t_read)
                self._out = None
        if t_read - self._poll_batch_start >= self.read_s or (deadline is not None and t_read >= deadline):
            return self._flush_poll()
        return None

    def _send_request(self) -> bool:
        port = self._port
        if port is None:
            return False
        try:
            stale = port.in_waiting
            if stale:  # a late answer to a timed-out request: not this one's
                port.read(stale)
                self._decoder.discard()
                self._decoder.dropped["stale_bytes"] = self._decoder.dropped.get("stale_bytes", 0) + stale
            port.write(self.fmt.request)
        except (serial.SerialException, OSError) as err:
            self._port_lost(err)
            return False
        return True

    def poll_timing(self) -> dict[str, float] | None:
        """The request/answer windows so far (the last ``POLL_WINDOWS``), or ``None`` before the first answer.

        ``window_median_ms``, ``window_p99_ms``, ``window_max_ms``; ``t_uncertainty_ms``: half the p99
        window (a reading was taken somewhere within its window; its stamp is the middle); ``t_jitter_ms``:
        half the windows' p1 to p99 spread (how much the stamps' error may differ between readings); ``achieved_hz``:
        answers per second over about the last ``RATE_SPAN_S``; ``answers``: how many the figures cover.
        """
        windows = np.array(self._windows)  # one C-level copy: the reader may append meanwhile
        answers = np.array(self._answers)
        if not windows.size:
            return None
        p1, med, p99 = np.percentile(windows, [1.0, 50.0, 99.0])
        recent = answers[answers >= answers[-1] - RATE_SPAN_S]
        span = float(recent[-1] - recent[0]) if recent.size > 1 else 0.0
        return {
            "window_median_ms": 1e3 * float(med),
            "window_p99_ms": 1e3 * float(p99),
            "window_max_ms": 1e3 * float(windows.max()),
            "t_uncertainty_ms": 0.5e3 * float(p99),
            "t_jitter_ms": 0.5e3 * float(p99 - p1),
            "achieved_hz": (recent.size - 1) / span if span > 0 else 0.0,
            "answers": float(windows.size),
        }

    def stats(self) -> SourceStats:
        st = super().stats()
        if self.mode == "poll":
            st.poll = self.poll_timing() or {}
        return st

    def _report_timing(self) -> None:
        """A ``timing`` event when the stamps' uncertainty is first known, and whenever it grows by a quarter."""
        if len(self._windows) < TIMING_FIRST:
            return
        timing = self.poll_timing()
        assert timing is not None
        unc = 1e-3 * timing["t_uncertainty_ms"]
        if unc > self._timing_reported * TIMING_GROWTH:
            self._timing_reported = unc
            self._event(
                EventKind.TIMING,
                detail="host clock, polled: each reading stamped at the middle of its request/answer window",
                values={"t_uncertainty_s": unc, "t_jitter_s": 1e-3 * timing["t_jitter_ms"],
                        "window_median_s": 1e-3 * timing["window_median_ms"],
                        "window_p99_s": 1e-3 * timing["window_p99_ms"], "achieved_hz": timing["achieved_hz"]},
            )

    def _flush_poll(self) -> SampleBatch | None:
        self._poll_batch_start = time.monotonic()
        self._report_decode()
        self._report_timing()
        p, self._pending = self._pending, []
        n = len(p)
        seq = np.fromiter((x[0] for x in p), np.int64, n)
        th = np.fromiter((x[1] for x in p), np.float64, n)
        val = np.fromiter((x[2] for x in p), np.float64, n)
        st = np.fromiter((x[3] for x in p), np.uint8, n)
        return self._batch(th, np.full(n, math.nan), self.cal_mm + val, seq, st)


# ----------------------------------------------------------------------------- paced arrays


Chunk = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]


class _PacedSource(Source):
    """Samples known in advance (a simulation, a recording), released on the host
    clock at ``speed`` times real time (``inf``: as fast as possible)."""

    MAX_BATCH = 1 << 16

    def __init__(self, url: str, rate_hz: float | None, speed: float, batch_s: float, status: int) -> None:
        super().__init__(url, rate_hz, batch_s)
        self.speed = speed
        self._status = np.uint8(status)
        self._chunks: Iterator[Chunk] | None = None
        self._t: NDArray[np.float64] = np.empty(0)
        self._len: NDArray[np.float64] = np.empty(0)
        self._seq: NDArray[np.int64] = np.empty(0, np.int64)
        self._i = 0
        self._start: float | None = None
        self._t0 = 0.0
        self._last_seq: int | None = None
        self._last_return = -math.inf

    def _begin(self, chunks: Iterator[Chunk], detail: str) -> None:
        self._chunks = chunks
        self._stats.connected = True
        self._event(EventKind.OPENED, detail=detail)

    def _more(self) -> bool:
        """Make sure the current chunk has samples left; False at the end."""
        while self._i >= self._t.shape[0]:
            assert self._chunks is not None
            nxt = next(self._chunks, None)
            if nxt is None:
                return False
            self._t, self._len, self._seq = nxt
            self._i = 0
        return True

    def _read(self, deadline: float | None) -> SampleBatch | None:
        while not self._closed:
            if not self._more():
                self._finished = True
                self._stats.connected = False
                self._event(EventKind.END, detail="no more samples")
                return self._events_only()
            now = time.monotonic()
            if self._start is None:
                self._start, self._t0 = now, float(self._t[self._i])
            if math.isinf(self.speed):
                return self._take(self._i + self.MAX_BATCH, now)
            t_now = self._t0 + (now - self._start) * self.speed
            due = float(self._t[self._i])
            wake = max(self._start + (due - self._t0) / self.speed, self._last_return + self.read_s)
            if now >= wake:
                end = int(np.searchsorted(self._t, t_now, side="right"))
                return self._take(min(max(end, self._i + 1), self._i + self.MAX_BATCH), now)
            if self._events:
                return self._events_only()
            if deadline is not None and now >= deadline:
                return None
            self._sleep_until(wake if deadline is None else min(wake, deadline))
        return None

    def _take(self, end: int, now: float) -> SampleBatch | None:
        sl = slice(self._i, min(end, self._t.shape[0]))
        self._i = sl.stop
        self._last_return = now
        t, length, seq = self._t[sl], self._len[sl], self._seq[sl]
        steps = np.diff(seq, prepend=seq[0] - 1 if self._last_seq is None else self._last_seq)
        gaps = [(int(seq[i] - steps[i] + 1), int(steps[i] - 1)) for i in np.flatnonzero(steps > 1).tolist()]
        self._gap_events(gaps)
        self._last_seq = int(seq[-1])
        assert self._start is not None
        # As fast as possible: stamped when released; otherwise on the paced schedule.
        th = np.full(t.shape[0], now) if math.isinf(self.speed) else self._start + (t - self._t0) / self.speed
        status = np.full(t.shape[0], self._status, np.uint8)
        return self._batch(th, t.copy(), length.copy(), seq.copy(), status)


class SimSource(_PacedSource):
    """The physical simulator, in process, paced on the host clock."""

    scheme = "sim"

    def __init__(
        self,
        url: str,
        *,
        plan: Any = None,
        machine: Any = None,
        library: Any = None,
        run_plans: Any = None,
        rate_hz: float | None = None,
        speedup: float = 1.0,
        seed: int = 0,
        repeat: int = 1,
        gap_s: float = 0.0,
        batch_s: float = DEFAULT_BATCH_S,
    ) -> None:
        # Imported here: the simulator is a tool, and only this source needs it.
        from ballbar.analysis.plan import TestPlan
        from ballbar.tools.simulator import MachineModel, SimResult, iter_tests

        several = library is not None and len(library) > 1
        plan = plan if plan is not None else library.first.plan if several else TestPlan()
        rate = float(rate_hz if rate_hz is not None else plan.sample_hz)
        super().__init__(url, rate, speedup, batch_s, int(Status.SIMULATED))
        times = None if repeat == 0 else repeat
        results: Iterator[SimResult]
        if several:
            from ballbar.tools.machine3d import Machine3D, set_tests

            names = list(run_plans) if run_plans else list(library.names)
            m3 = machine if isinstance(machine, Machine3D) else Machine3D()
            results = (res for _n, res in set_tests(library, names, m3, rate, seed, times, gap_s))
        else:
            results = iter_tests(plan, machine if machine is not None else MachineModel(), rate, seed, times, gap_s)

        def chunks() -> Iterator[Chunk]:
            for res in results:
                seq = np.rint(res.t_s * rate).astype(np.int64)
                yield res.t_s, res.length_mm, seq

        self._begin(chunks(), f"simulator, {rate:g} Hz, speedup {speedup:g}, seed {seed}")


class ReplaySource(_PacedSource):
    """A recording, replayed at ``speed`` times real time."""

    scheme = "replay"

    def __init__(
        self,
        url: str,
        path: str,
        *,
        speed: float = 1.0,
        rate_hz: float | None = None,
        batch_s: float = DEFAULT_BATCH_S,
    ) -> None:
        super().__init__(url, rate_hz, speed, batch_s, 0)
        ext = os.path.splitext(path)[1].lower()
        if ext == ".mcap":
            raise SourceConfigError(f"{url}: replay of MCAP recordings is not supported yet; use a CSV export")
        from .recordings import read_csv  # DataError (one line) on a bad file

        t, length = read_csv(path)
        if rate_hz:
            seq = np.rint((t - t[0]) * rate_hz).astype(np.int64)
            bad = np.flatnonzero(np.diff(seq) <= 0)  # two rows in one sample period
            if bad.shape[0]:
                raise SourceConfigError(
                    f"{url}: rows {int(bad[0]) + 1} and {int(bad[0]) + 2} fall in one sample period at "
                    f"rate={rate_hz:g} Hz; is the rate right?"
                )
        else:
            seq = np.arange(t.shape[0], dtype=np.int64)
        self._begin(iter([(t, length, seq)]), f"{path} ({t.shape[0]} samples, speed {speed:g})")


# ----------------------------------------------------------------------------- registry and URLs

SourceFactory = Callable[[str, str, "_Options"], Source]
_REGISTRY: dict[str, SourceFactory] = {}


def register_source(scheme: str, factory: SourceFactory) -> None:
    """Make ``scheme:`` URLs open with ``factory(url, target, options)``."""
    _REGISTRY[scheme] = factory


def source_schemes() -> list[str]:
    return sorted(_REGISTRY)


class _Options:
    """URL query and keyword options, converted on demand; leftovers are errors."""

    def __init__(self, url: str, query: dict[str, str], kwargs: dict[str, Any], check_only: bool = False) -> None:
        both = sorted(set(query) & set(kwargs))
        if both:
            raise SourceConfigError(f"{url}: option {both[0]!r} given both in the URL and as a keyword")
        self.url = url
        self.values: dict[str, Any] = {**query, **kwargs}
        self.known: list[str] = []
        self.check_only = check_only

    def get(self, key: str, conv: Callable[[Any], Any], default: Any = None) -> Any:
        self.known.append(key)
        if key not in self.values:
            return default
        raw = self.values.pop(key)
        if raw is None:
            return default
        try:
            return conv(raw)
        except (TypeError, ValueError) as err:
            raise SourceConfigError(f"{self.url}: option {key}={raw!r}: {err}") from None

    def require(self, key: str, conv: Callable[[Any], Any], why: str) -> Any:
        if self.values.get(key) is None:
            raise SourceConfigError(f"{self.url}: option {key} is required ({why})")
        return self.get(key, conv)

    def done(self) -> None:
        if self.values:
            key = sorted(self.values)[0]
            raise SourceConfigError(f"{self.url}: unknown option {key!r} (known: {', '.join(sorted(self.known))})")
        if self.check_only:
            raise _Checked


class _Checked(Exception):
    """Raised by :meth:`_Options.done` when only checking: the source is not opened."""


def _pos_float(v: Any) -> float:
    x = float(v)
    if not (math.isfinite(x) and x > 0):
        raise ValueError("must be a finite number > 0")
    return x


def _finite(v: Any) -> float:
    x = float(v)
    if not math.isfinite(x):
        raise ValueError("must be a finite number")
    return x


def _rate(v: Any) -> float:
    x = _pos_float(v)
    if not RATE_MIN_HZ <= x <= RATE_MAX_HZ:
        raise ValueError(f"must be within {RATE_MIN_HZ:g}..{RATE_MAX_HZ:g} Hz")
    return x


def _speed(v: Any) -> float:
    if isinstance(v, str) and v.strip().lower() in ("max", "inf", "fast"):
        return math.inf
    x = float(v)
    if not x > 0:
        raise ValueError("must be > 0 or 'max'")
    return x


def _nonneg_int(v: Any) -> int:
    if isinstance(v, bool):
        raise ValueError("must be an integer")
    x = int(v)
    if x < 0:
        raise ValueError("must be >= 0")
    return x


def _bool(v: Any) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "on"):
        return True
    if s in ("0", "false", "no", "off"):
        return False
    raise ValueError("must be true or false")


def _choice(*allowed: str) -> Callable[[Any], str]:
    def conv(v: Any) -> str:
        s = str(v)
        if s not in allowed:
            raise ValueError(f"must be one of {', '.join(allowed)}")
        return s

    return conv


def _pos_int(v: Any) -> int:
    if isinstance(v, bool):
        raise ValueError("must be an integer")
    x = int(v)
    if x <= 0:
        raise ValueError("must be > 0")
    return x


def _framing(v: Any) -> tuple[int, str, int]:
    """``8N1``, ``7E2``, ...: data bits (5..8), parity (N, E, O), stop bits (1, 2)."""
    if isinstance(v, tuple):
        return v
    s = str(v).strip().upper()
    if len(s) != 3 or s[0] not in "5678" or s[1] not in "NEO" or s[2] not in "12":
        raise ValueError("must be data bits, parity and stop bits, such as 8N1 or 7E2")
    return int(s[0]), s[1], int(s[2])


def _bytes(v: Any) -> bytes:
    if isinstance(v, bytes):
        return v
    return str(v).encode("latin-1")


def _open_serial(url: str, target: str, opt: _Options) -> Source:
    if target.startswith("///"):
        target = target[2:]
    if not target:
        raise SourceConfigError(f"{url}: no port (serial:/dev/ttyUSB0, serial:socket://host:port, ...)")
    protocol = opt.get("protocol", _choice("binary", "ascii", *PROFILES), "binary")
    gauge = PROFILES.get(protocol)
    base = gauge.fmt if gauge is not None else AsciiFormat()
    default_mode = "poll" if gauge is not None and gauge.polled else "stream"
    mode = opt.get("mode", _choice("stream", "poll"), default_mode)
    cal_mm = opt.require("cal_mm", _finite, "the bar's length at zero displacement, from its calibration")
    rate = opt.get("rate", _rate)
    if mode == "poll" and protocol == "binary":
        raise SourceConfigError(f"{url}: mode=poll needs protocol=ascii or a gauge profile")
    if mode == "stream" and gauge is not None and not gauge.streams:
        raise SourceConfigError(f"{url}: a {protocol} gauge does not stream: it answers requests (mode=poll)")
    if mode == "poll" and rate is None:
        raise SourceConfigError(f"{url}: mode=poll needs rate (the polling rate in Hz)")
    ts = opt.get("timestamp", _choice("s", "ms", "us", "none"), "none")
    try:
        fmt = dataclasses.replace(
            base,
            unit=opt.get("unit", _choice("mm", "um", "nm", "in"), base.unit),
            scale=opt.get("scale", _finite, base.scale),
            ts_unit=None if ts == "none" else ts,
            max_line=opt.get("max_line", int, base.max_line),
            request=opt.get("request", _bytes, base.request),
        )
    except ValueError as err:
        raise SourceConfigError(f"{url}: {err}") from None
    baud = opt.get("baud", _pos_int, gauge.baud if gauge is not None else 2_000_000)
    framing = opt.get("framing", _framing, (gauge.bytesize, gauge.parity, gauge.stopbits) if gauge else (8, "N", 1))
    if gauge is not None and rate is not None:
        line = dataclasses.replace(gauge, bytesize=framing[0], parity=framing[1], stopbits=framing[2])
        why = line.check_rate(rate, baud, mode == "poll", fmt.request)
        if why is not None:
            raise SourceConfigError(f"{url}: {why}")
    kwargs = {
        "baud": baud,
        "bytesize": framing[0],
        "parity": framing[1],
        "stopbits": framing[2],
        "batch_s": opt.get("batch_s", _pos_float, DEFAULT_BATCH_S),
        "stall_s": opt.get("stall_s", _pos_float),
        "poll_timeout_s": opt.get("poll_timeout_s", _pos_float),
        "retry_min_s": opt.get("retry_min_s", _pos_float, 0.05),
        "retry_max_s": opt.get("retry_max_s", _pos_float, 2.0),
        "exclusive": opt.get("exclusive", _bool, True),
    }
    opt.done()
    return SerialSource(url, target, cal_mm=cal_mm, protocol=protocol, mode=mode, rate_hz=rate, fmt=fmt, **kwargs)


def _open_sim(url: str, target: str, opt: _Options) -> Source:
    if target.strip("/"):
        raise SourceConfigError(f"{url}: sim: takes no path, only options (sim:?rate=1000&speedup=10)")
    kwargs = {
        "plan": opt.get("plan", lambda v: v),
        "machine": opt.get("machine", lambda v: v),
        "library": opt.get("library", lambda v: v),
        "run_plans": opt.get("run_plans", lambda v: v),
        "rate_hz": opt.get("rate", _rate),
        "speedup": opt.get("speedup", _speed, 1.0),
        "seed": opt.get("seed", _nonneg_int, 0),
        "repeat": opt.get("repeat", _nonneg_int, 1),
        "gap_s": opt.get("gap_s", lambda v: max(0.0, _finite(v)), 0.0),
        "batch_s": opt.get("batch_s", _pos_float, DEFAULT_BATCH_S),
    }
    opt.done()
    return SimSource(url, **kwargs)


def _open_replay(url: str, target: str, opt: _Options) -> Source:
    if target.startswith("///"):
        target = target[2:]
    path = urllib.parse.unquote(target)
    if not path:
        raise SourceConfigError(f"{url}: no file (replay:recording.csv?speed=10)")
    kwargs = {
        "speed": opt.get("speed", _speed, 1.0),
        "rate_hz": opt.get("rate", _rate),
        "batch_s": opt.get("batch_s", _pos_float, DEFAULT_BATCH_S),
    }
    opt.done()
    return ReplaySource(url, path, **kwargs)


register_source("serial", _open_serial)
register_source("sim", _open_sim)
register_source("replay", _open_replay)


def split_url(url: str) -> tuple[str, str, dict[str, str]]:
    """``scheme, target, query`` of a source URL (see the module docstring)."""
    head, _, query = url.partition("?")
    if head.startswith("/"):
        scheme, target = "serial", head
    else:
        scheme, _, target = head.partition(":")
        if scheme in PYSERIAL_SCHEMES and target.startswith("//"):
            scheme, target = "serial", head
    if scheme not in _REGISTRY:
        raise SourceConfigError(
            f"{url}: unknown source {scheme!r} (known: {', '.join(source_schemes())}, a /dev path or a pyserial URL)"
        )
    opts: dict[str, str] = {}
    for k, v in urllib.parse.parse_qsl(query, keep_blank_values=True):
        if k in opts:
            raise SourceConfigError(f"{url}: option {k!r} given twice")
        opts[k] = v
    return scheme, target, opts


def open_source(url: str, **options: Any) -> Source:
    """Open the source that ``url`` names; keyword ``options`` complement the URL's query."""
    scheme, target, query = split_url(url)
    opt = _Options(url, query, {k: v for k, v in options.items() if v is not None})
    return _REGISTRY[scheme](url, target, opt)


def check_source(url: str, **options: Any) -> None:
    """What :func:`open_source` checks of ``url`` and ``options``, without opening anything.

    Raises :class:`SourceConfigError` naming the problem.  (A source registered
    by a plug-in that never calls ``opt.done()`` would be opened: the built-in
    ones all do.)
    """
    scheme, target, query = split_url(url)
    opt = _Options(url, query, {k: v for k, v in options.items() if v is not None}, check_only=True)
    try:
        src = _REGISTRY[scheme](url, target, opt)
    except _Checked:
        return
    src.close()


__all__ = [
    "RATE_MAX_HZ",
    "RATE_MIN_HZ",
    "ReplaySource",
    "SerialSource",
    "SimSource",
    "Source",
    "check_source",
    "open_source",
    "register_source",
    "source_schemes",
    "split_url",
]
