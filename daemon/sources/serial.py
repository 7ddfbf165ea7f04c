"""A serial port: the LVDT interface streaming its protocol, or a gauge interface polled (the package's docstring)."""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import os
import select
import threading
import time

import numpy as np
import serial

from ballbar.protocol import AsciiDecoder, AsciiFormat, BinaryDecoder, Readings
from ballbar.protocol.gauges import PROFILES

from ..errors import SourceConfigError, SourceError
from ..samples import EventKind, SampleBatch, SourceStats
from ..timebase import Stamper
from .base import (
    DEFAULT_BATCH_S,
    FALLBACK_WAIT_S,
    POLL_WINDOWS,
    RATE_SPAN_S,
    RATIO_MIN_SPAN_S,
    READ_BURST_MAX,
    READ_MAX,
    READ_MORE_AT,
    TIMING_FIRST,
    TIMING_GROWTH,
    TTY_READ_BYTES,
    WAIT_WARNING_S,
    Source,
)

log = logging.getLogger(__name__)

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

    def resume(self, seq: int, t_device_s: float | None, period_s: float | None, offsets: tuple[int, float]) -> bool:
        m, w = self._decoder.seq_modulus, self._decoder.clock_wrap_s
        if m is None or self.mode != "stream" or self._stamper.last_seq is not None:
            return False
        seq_off, clk_off = offsets
        clk_raw = None
        if t_device_s is not None and w is not None:
            clk_raw = (t_device_s - clk_off) % w
        self._stamper.resume(seq, (seq - seq_off) % m, t_device_s, clk_raw, period_s)
        self._gap_cause = "restart"
        return True

    def counter_offsets(self) -> tuple[int, float] | None:
        if self._decoder.seq_modulus is None or self.mode != "stream":
            return None
        return self._stamper.offsets()

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
        for seq, count in st.counter_jumps:
            self._event(EventKind.COUNTER_JUMP, seq=seq, count=count,
                        detail=f"sample counter leapt {count} beyond its clock (no sample lost)")
        self._duplicates += st.duplicates
        self._report_decode()
        clock = self._stamper.clock
        if clock.ready:
            # (the map stamps from the first read; its rate is stated once it rests on enough of them)
            self._stats.clock_ratio = clock.ratio if clock.span_s >= RATIO_MIN_SPAN_S else math.nan
            self._stats.clock_offset_s = clock.offset
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
        # A host that wakes late (a loaded PC) may find the answer waiting in the port: that is no timeout, and its
        # window (how late it was read) enters the stamps' stated uncertainty.
        waiting = self._out is not None and now - self._out[1] > self.poll_timeout_s and self._answer_waiting()
        if self._out is not None and now - self._out[1] > self.poll_timeout_s and not waiting:
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
        data = self._read_now(waited=True) if waiting or self._wait(until) else b""
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

    def _answer_waiting(self) -> bool:
        port = self._port
        try:
            return port is not None and port.in_waiting > 0
        except (serial.SerialException, OSError):
            return False  # (the read that follows finds the port gone)

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
