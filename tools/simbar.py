"""The simulated ball-bar itself: its port (a pty behind a stable link, or an existing port) and its loop, which
paces the samples of a :class:`~ballbar.tools.simfeed.Feed`, applies the faults commanded and writes the frames.

:mod:`ballbar.tools.simdevice` runs it as a process and documents its commands and its output.
"""

from __future__ import annotations

import bisect
import contextlib
import json
import math
import os
import pty
import time
import tty
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ballbar.protocol import Status
from ballbar.protocol import ascii as ascii_proto
from ballbar.protocol import binary as binary_proto

from .simfeed import BlockEncoder, Feed

PENDING_LIMIT = 16 * 1024  # bytes waiting for the reader before the device waits (at least 4 bursts' worth)
BURST_S = 0.016  # the shortest time between two writes (FTDI adapters' default latency timer)
IDLE_S = 1.0  # the longest sleep with nothing due (commands wake the device at once)
GARBAGE_CHARS = b"#$%&@!*=~^|<>"  # none is a digit, letter, sign, point or separator


# ----------------------------------------------------------------------------- the port


class PtyPort:
    """The device's end of a pty, behind a stable symbolic link."""

    def __init__(self, link: str | None) -> None:
        self.link = link
        self.master: int | None = None
        self._slave: int | None = None
        self.name = ""
        self.open()

    @property
    def path(self) -> str:
        return self.link or self.name

    def open(self) -> None:
        master, slave = pty.openpty()
        tty.setraw(slave)  # no echo, no line discipline: bytes pass as they are
        os.set_blocking(master, False)
        self.master, self._slave = master, slave
        self.name = os.ttyname(slave)
        if self.link:
            tmp = f"{self.link}.{os.getpid()}.tmp"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            os.symlink(self.name, tmp)
            os.replace(tmp, self.link)

    def close(self) -> None:
        if self.link:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link)
        for fd in (self.master, self._slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self._slave = None

    @property
    def is_open(self) -> bool:
        return self.master is not None

    def fileno(self) -> int | None:
        return self.master

    def write(self, data: bytes | bytearray) -> int:
        if self.master is None:
            return 0
        try:
            return os.write(self.master, data)
        except BlockingIOError:
            return 0

    def read(self) -> bytes:
        if self.master is None:
            return b""
        try:
            return os.read(self.master, 4096)
        except (BlockingIOError, OSError):
            return b""


class SerialPort:
    """An existing port (``--port``): a real adapter, a socat pty, ``socket://``.

    Unplug and replug close and reopen it: the reader sees a stall, not an unplug.
    """

    def __init__(self, url: str, baud: int) -> None:
        import serial

        self._serial = serial
        self.url = url
        self.baud = baud
        self.port: Any = None
        self.open()

    @property
    def path(self) -> str:
        return self.url

    def open(self) -> None:
        self.port = self._serial.serial_for_url(self.url, baudrate=self.baud, timeout=0)

    def close(self) -> None:
        if self.port is not None:
            self.port.close()
        self.port = None

    @property
    def is_open(self) -> bool:
        return self.port is not None

    def fileno(self) -> int | None:
        try:
            return int(self.port.fileno()) if self.port is not None else None
        except Exception:
            return None

    def write(self, data: bytes | bytearray) -> int:
        return int(self.port.write(data) or 0) if self.port is not None else 0

    def read(self) -> bytes:
        if self.port is None:
            return b""
        n = self.port.in_waiting
        return bytes(self.port.read(n)) if n else b""


# ----------------------------------------------------------------------------- the device


@dataclass
class DeviceStats:
    """What the device did; the host's counts must match these."""

    generated: int = 0  # samples taken
    sent: int = 0  # samples put on the wire intact
    dropped: int = 0  # not sent on command (drop)
    corrupted: int = 0  # sent corrupted (lost to the host)
    corrupted_bytes: int = 0  # their bytes (ASCII: without the line end)
    stalled: int = 0  # taken during a stall (lost)
    unplugged: int = 0  # taken while unplugged (lost)
    garbage_bytes: int = 0
    garbage_lines: int = 0
    resets: int = 0
    clock_jumps: int = 0
    requests: int = 0  # poll mode
    next_seq: int = 0  # device counter of the next sample
    last_seq: int = -1  # device counter of the last sample sent intact
    tests: int = 0
    cpu_s: float = 0.0  # the device process's CPU time so far
    lines_dropped: int = 0  # stdout lines lost because nobody read the pipe


@dataclass
class Settings:
    protocol: str = "binary"
    mode: str = "stream"
    rate: float = 1000.0
    speedup: float = 1.0
    cal_mm: float = 100.0
    range_mm: float = 2.5
    fmt: ascii_proto.AsciiFormat = field(default_factory=ascii_proto.AsciiFormat)
    seed: int = 0
    burst_s: float = BURST_S
    gauge: str | None = None  # a profile of ballbar.protocol.gauges
    prefix: str = ""  # what the gauge writes before each reading (its header)
    poll_rate: float = 15.625  # what the printed URL polls at (a gauge profile)
    line_baud: int = 0  # the emulated line (0: none)
    bits_per_char: int = 10

    def wire_s(self, n: int) -> float:
        """Seconds ``n`` characters take on the emulated line."""
        return n * self.bits_per_char / self.line_baud if self.line_baud else 0.0


class SimDevice:
    """The device's loop: pace samples, apply faults, write frames, obey commands."""

    def __init__(self, feed: Feed, port: PtyPort | SerialPort, settings: Settings, out: int) -> None:
        self.feed = feed
        self.port = port
        self.s = settings
        self.out = out
        self.stats = DeviceStats()
        self.rng = np.random.default_rng(settings.seed)
        self.started = False
        self.running = True
        self.done = False
        self.sim_t = feed.next_t  # device time now
        self._last_wall = time.monotonic()  # wall time that sim_t corresponds to
        self._last_burst = -math.inf  # wall time of the last samples taken out
        self._pending = bytearray()
        self._garbage: list[int] = []
        self._corrupt = 0
        self._drop = 0
        self._stall_until = -math.inf
        self._replug_at: float | None = None
        self._seq0 = 0  # counter offset since the last reset
        self._t0 = 0.0  # clock offset since the last reset (minus the jumps since)
        self._req_buf = b""
        self._last_answer: tuple[float, float, int] | None = None
        self._due: list[tuple[float, bytes]] = []  # polled answers and when their last byte arrives
        self._errors: list[int] = []  # status bits of the next answers sent as error words
        self._late: list[float] = []  # delays of the next answers, s
        self._cut = 0  # answers still to cut
        self._encoder = BlockEncoder(self._encode_block)
        one = self._encode(np.zeros(1), np.full(1, settings.cal_mm), np.zeros(1, np.int64))
        burst = settings.rate * settings.speedup * settings.burst_s * len(one)
        self._pending_limit = max(PENDING_LIMIT, int(4 * burst))

    # -- output -------------------------------------------------------------------

    def emit(self, obj: dict[str, Any]) -> None:
        try:
            os.write(self.out, (json.dumps(obj) + "\n").encode())
        except (BlockingIOError, BrokenPipeError):
            # Nobody reads our stdout (a pipe left full, or its reader gone): lose the line, never stall the device.
            self.stats.lines_dropped += 1

    # -- commands -----------------------------------------------------------------

    def command(self, line: str, now: float | None = None) -> None:
        """Obey one command line, received at wall time ``now`` (default: now)."""
        words = line.split()
        if not words:
            return
        cmd, argv = words[0].lower(), words[1:]
        try:
            reply = self._command(cmd, argv, time.monotonic() if now is None else now)
        except (ValueError, IndexError) as err:
            self.emit({"ok": False, "cmd": cmd, "error": str(err) or "bad arguments"})
            return
        self.emit({"ok": True, "cmd": cmd, **reply})

    def _command(self, cmd: str, argv: list[str], now: float) -> dict[str, Any]:
        def count() -> int:
            n = int(argv[0]) if argv else 1
            if n < 0:
                raise ValueError("count must be >= 0")
            return n

        if cmd == "start":
            self.started = True
            self._last_wall = now
            return {}
        if cmd == "garbage":
            n = count()
            self._garbage.append(n)
            return {"bytes": n}
        if cmd == "corrupt":
            n = count()
            self._corrupt += n
            return {"count": n}
        if cmd == "drop":
            n = count()
            self._drop += n
            return {"count": n}
        if cmd == "stall":
            s = float(argv[0])
            if not s >= 0:
                raise ValueError("seconds must be >= 0")
            self._stall_until = now + s
            return {"seconds": s}
        if cmd == "unplug":
            after = float(argv[0]) if argv else None
            self._unplug()
            self._replug_at = None if after is None else now + after
            return {"replug_after_s": after}
        if cmd == "replug":
            self._replug()
            return {"path": self.port.path}
        if cmd == "reset":
            self._seq0 = self.stats.next_seq + self._seq0
            self._t0 = self.sim_t
            self.stats.resets += 1
            self.stats.next_seq = 0
            return {}
        if cmd == "error":
            bits = {"over": int(Status.OVER_RANGE), "fault": int(Status.SENSOR_FAULT)}.get(argv[0] if argv else "")
            if bits is None:
                raise ValueError("error over|fault [N]")
            if self.s.gauge is None or not self._has_error_words():
                raise ValueError(f"{self.s.gauge or self.s.protocol}: this device has no error words")
            n = int(argv[1]) if len(argv) > 1 else 1
            self._errors += [bits] * max(0, n)
            return {"count": n}
        if cmd == "late":
            s = float(argv[0])
            n = int(argv[1]) if len(argv) > 1 else 1
            if not (math.isfinite(s) and s >= 0) or self.s.mode != "poll":
                raise ValueError("late S [N]: polled devices, S >= 0")
            self._late += [s] * max(0, n)
            return {"seconds": s, "count": n}
        if cmd == "cut":
            if self.s.mode != "poll":
                raise ValueError("cut [N]: polled devices")
            n = count()
            self._cut += n
            return {"count": n}
        if cmd == "jump":
            s = float(argv[0])
            if not (math.isfinite(s) and s > 0):
                raise ValueError("seconds must be > 0")
            self._t0 -= s  # the clock reads t - t0
            self.stats.clock_jumps += 1
            return {"seconds": s}
        if cmd == "stats":
            self.stats.cpu_s = time.process_time()
            return {"stats": asdict(self.stats)}
        if cmd == "quit":
            self.running = False
            return {}
        raise ValueError(f"unknown command {cmd!r}")

    def _has_error_words(self) -> bool:
        from ballbar.protocol.gauges import PROFILES

        fmt = PROFILES[self.s.gauge].fmt if self.s.gauge else self.s.fmt
        return bool(fmt.errors or fmt.error_prefix)

    def _unplug(self) -> None:
        if self.port.is_open:
            self.port.close()
            self._pending.clear()  # what the adapter held is gone with it
            self._due.clear()
            self.emit({"event": "unplugged"})

    def _replug(self) -> None:
        if not self.port.is_open:
            self.port.open()
            self._replug_at = None
            self.emit({"event": "replugged", "path": self.port.path})

    # -- samples ------------------------------------------------------------------

    def _dev_fields(
        self, t: NDArray[np.float64], seq: NDArray[np.int64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """The device's counter and clock (they restart at a reset)."""
        return seq - self._seq0, t - self._t0

    def _displacement(self, length: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        disp = length - self.s.cal_mm
        over = np.abs(disp) > self.s.range_mm
        status = np.where(over, int(Status.OVER_RANGE), 0) | int(Status.SIMULATED)
        if self._errors:  # error words on command: the next samples
            k = min(len(self._errors), status.shape[0])
            status[:k] |= np.array(self._errors[:k], np.int64)
            del self._errors[:k]
        return np.clip(disp, -self.s.range_mm, self.s.range_mm), status.astype(np.int64)

    def _garbage_bytes(self) -> bytes:
        out = b""
        for n in self._garbage:
            if self.s.protocol == "binary":
                # Bytes without A5 or 5A: no false sync word, not even with a neighbour.
                g = self.rng.integers(0, 254, n)
                g += g >= 0x5A
                g += g >= 0xA5
                out += g.astype(np.uint8).tobytes()
            else:
                junk = bytes(GARBAGE_CHARS[i] for i in self.rng.integers(0, len(GARBAGE_CHARS), n))
                out += junk + self.s.fmt.eol
                self.stats.garbage_lines += 1
            self.stats.garbage_bytes += n
        self._garbage.clear()
        return out

    def _encode(self, t: NDArray[np.float64], length: NDArray[np.float64], seq: NDArray[np.int64]) -> bytes:
        dseq, dt = self._dev_fields(t, seq)
        disp, status = self._displacement(length)
        if self.s.protocol == "binary":
            return binary_proto.encode_samples(dseq, dt, disp, status)
        return ascii_proto.encode(
            disp, self.s.fmt, t_s=dt if self.s.fmt.ts_unit else None, status=status, prefix=self.s.prefix
        )

    def _encode_block(
        self, t: NDArray[np.float64], length: NDArray[np.float64], seq: NDArray[np.int64]
    ) -> tuple[bytes, NDArray[np.int64]]:
        """:meth:`_encode`, and where each sample's bytes start (and the last ends)."""
        data = self._encode(t, length, seq)
        if self.s.protocol == "binary":
            off = np.arange(t.shape[0] + 1, dtype=np.int64) * binary_proto.FRAME_SIZE
        else:  # one line each, and no line holds its end's last byte
            ends = np.flatnonzero(np.frombuffer(data, np.uint8) == self.s.fmt.eol[-1]) + 1
            off = np.concatenate((np.zeros(1, np.int64), ends))
        if off.shape[0] != t.shape[0] + 1 or off[-1] != len(data):
            raise AssertionError("simdevice: an encoded block does not split into its samples")
        return data, off

    def _corrupt_one(self, data: bytes) -> bytes:
        """One sample's bytes, damaged so that the decoder must drop exactly this sample."""
        self.stats.corrupted_bytes += len(data.rstrip(b"\r\n")) if self.s.protocol == "ascii" else len(data)
        if self.s.protocol == "binary":
            for _ in range(100):
                pos = int(self.rng.integers(2, binary_proto.FRAME_SIZE))
                b = bytearray(data)
                b[pos] ^= 1 << int(self.rng.integers(0, 8))
                if b.find(binary_proto.SYNC, 1) < 0:  # no false sync word uncovered
                    return bytes(b)
            body = data[:2] + bytes(binary_proto.FRAME_SIZE - 4)
            crc = binary_proto.crc16(body) ^ 0x0101  # a wrong CRC without A5 or 5A in it
            return body + crc.to_bytes(2, "little")
        line = data.rstrip(b"\r\n")
        digits = [i for i, c in enumerate(line) if chr(c).isdigit()]
        i = digits[-1] if digits else 0
        return line[:i] + b"#" + line[i + 1 :] + data[len(line) :]

    def _send_chunk(self, t: NDArray[np.float64], length: NDArray[np.float64], seq: NDArray[np.int64]) -> None:
        n = t.shape[0]
        keep = np.ones(n, bool)
        if self._drop:
            k = min(self._drop, n)
            keep[:k] = False
            self._drop -= k
            self.stats.dropped += k
        idx = np.flatnonzero(keep)
        corrupt = idx[: self._corrupt]
        self._corrupt -= corrupt.shape[0]
        self.stats.corrupted += corrupt.shape[0]
        out = bytearray(self._garbage_bytes())
        if corrupt.shape[0] == 0:
            out += self._encode(t[idx], length[idx], seq[idx])
        else:
            bad = set(corrupt.tolist())
            for i in idx.tolist():
                one = self._encode(t[i : i + 1], length[i : i + 1], seq[i : i + 1])
                out += self._corrupt_one(one) if i in bad else one
        intact = idx.shape[0] - corrupt.shape[0]
        self.stats.sent += intact
        if intact:
            last = int(idx[~np.isin(idx, corrupt)][-1])
            self.stats.last_seq = int(seq[last] - self._seq0)
        self._pending += out

    def _stream(self, now: float) -> None:
        """Take the samples due by wall time ``now`` (none while the reader is too far behind)."""
        blocked = len(self._pending) >= self._pending_limit
        if not blocked:
            self.sim_t += (now - self._last_wall) * self.s.speedup
        self._last_wall = now
        if blocked:
            return
        wire: bytes | None = None
        if self.port.is_open and now > self._stall_until and not (
            self._drop or self._corrupt or self._garbage or self._errors
        ):
            self._encoder.key = (self._seq0, self._t0)  # nothing to inject: the bytes encoded ahead
            (t, length, seq), wire = self.feed.take_encoded(self.sim_t, self._encoder)
        else:
            t, length, seq = self.feed.take_until(self.sim_t)
        n = t.shape[0]
        if n:
            self._last_burst = now
            self.stats.generated += n
            self.stats.next_seq = int(seq[-1] - self._seq0) + 1
            if not self.port.is_open:
                self.stats.unplugged += n
            elif now <= self._stall_until:
                self.stats.stalled += n
            elif wire is not None:
                self._pending += wire
                self.stats.sent += n
                self.stats.last_seq = self.stats.next_seq - 1
            else:
                self._send_chunk(t, length, seq)

    def _poll(self, now: float) -> None:
        self.sim_t += (now - self._last_wall) * self.s.speedup
        self._last_wall = now
        t, length, seq = self.feed.take_until(self.sim_t)
        if t.shape[0]:
            self.stats.generated += t.shape[0]
            self.stats.next_seq = int(seq[-1] - self._seq0) + 1
            self._last_answer = (float(t[-1]), float(length[-1]), int(seq[-1]))
        data = self.port.read() if self.port.is_open else b""
        if not data:
            return
        buf = self._req_buf + data
        req = self.s.fmt.request
        n = buf.count(req)
        self._req_buf = buf[buf.rfind(req) + len(req) :] if n else buf[-len(req) :]
        for _ in range(n):
            self.stats.requests += 1
            if self._last_answer is None or now < self._stall_until:
                continue
            if self._drop:
                self._drop -= 1
                self.stats.dropped += 1
                continue
            ta, la, sa = self._last_answer
            t1, l1, s1 = np.array([ta]), np.array([la]), np.array([sa], np.int64)
            out = self._garbage_bytes()
            one = self._encode(t1, l1, s1)
            if self._corrupt:
                self._corrupt -= 1
                self.stats.corrupted += 1
                one = self._corrupt_one(one)
            elif self._cut:
                self._cut -= 1
                self.stats.corrupted += 1
                self.stats.corrupted_bytes += len(one) // 2
                one = one[: len(one) // 2]
            else:
                self.stats.sent += 1
                self.stats.last_seq = sa - self._seq0
            # The answer's last byte arrives after the request's bytes and its own on the emulated line.
            delay = self.s.wire_s(len(req) + len(out) + len(one)) + (self._late.pop(0) if self._late else 0.0)
            if delay > 0:
                bisect.insort(self._due, (now + delay, out + one))
            else:
                self._pending += out + one

    def _advance(self, now: float) -> None:
        if not self.started:
            self._last_wall = now
        elif self.s.mode == "stream":
            self._stream(now)
        else:
            self._poll(now)

    def _flush(self) -> None:
        if self._due:
            now = time.monotonic()
            while self._due and self._due[0][0] <= now:
                self._pending += self._due.pop(0)[1]
        if self._pending and self.port.is_open:
            n = self.port.write(self._pending)
            del self._pending[:n]

    def step(self, now: float) -> None:
        """Bring the device to wall time ``now``: what fell due since the last step goes out in one write.

        A stall's end or a replug within the interval splits it: the samples taken
        before are judged by the state before (lost), those after go out.
        """
        tests_before = self.feed.tests
        timers = (self._stall_until, self._replug_at)
        for at in sorted(x for x in timers if x is not None and self._last_wall < x < now):
            self._advance(at)
            if self._replug_at is not None and at >= self._replug_at:
                self._replug()
        if self._replug_at is not None and now >= self._replug_at:
            self._replug()
        self._advance(now)
        self._flush()
        if self.feed.tests != tests_before:
            self.emit({"event": "test", "index": self.feed.tests - 1, "seq": self.stats.next_seq})
        self.stats.tests = self.feed.tests
        if self.feed.exhausted and not self._pending and not self._due and not self.done:
            self.done = True
            self.emit({"event": "done", "stats": asdict(self.stats)})

    def next_wake(self, now: float) -> float:
        """Wall time of the next :meth:`step`, unless a command, a request or room for pending bytes comes first.

        Streaming, that is when the next sample falls due, but not sooner than
        ``burst_s`` after the last write of samples: at low rates each sample goes out
        on time, at high rates the samples of ``burst_s`` go out together, as a USB
        adapter delivers them.
        """
        at = now + IDLE_S
        if self._replug_at is not None:
            at = min(at, self._replug_at)
        if self._due:
            at = min(at, self._due[0][0])
        if self.started and self.s.mode == "stream" and not self.feed.exhausted:
            # (a microsecond late: device time computed from the wall clock then surely reaches the sample's)
            due = self._last_wall + (self.feed.next_t - self.sim_t) / self.s.speedup + 1e-6
            at = min(at, max(due, self._last_burst + self.s.burst_s))
        return at

    def write_fd(self) -> int | None:
        """The port's descriptor while bytes wait for room in it (the reader is behind)."""
        return self.port.fileno() if self._pending and self.port.is_open else None
