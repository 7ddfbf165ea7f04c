"""A simulated ball-bar interface on a pseudo-terminal: the device the daemon's demo
and end-to-end tests run against.

It opens a pty (or a given port), prints the device path on the first line of
stdout, and streams the simulated test of :mod:`ballbar.tools.simulator` (or a
CSV recording) in the binary or ASCII protocol (``protocol/README.md``) at a
chosen sample rate and speed-up, repeating tests on a schedule::

    python -m ballbar.tools.simdevice --protocol binary --rate 1000 --speedup 10 --repeat 0 --gap-s 30

stdout, one line each:

1. the device path: a stable symbolic link to the current pty (``--link``, by
   default in a fresh temporary directory), which survives unplug and replug
   the way ``/dev/serial/by-id/...`` links do;
2. ``{"event": "ready", "path": ..., "url": ...}``: a source URL that reads it
   (``ballbar.daemon.sources.open_source(url)``);
3. and on: one JSON object per command answered and per event (``started``,
   ``unplugged``, ``replugged``, ``test``, ``done``).

ASCII lines are fixed width (zero-padded reading and timestamp), as gauges
write them.  ``--protocol mitutoyo|sylvac|tesa`` is a gauge interface of that
profile (``ballbar.protocol.gauges``): its framing, request and error words;
polled unless ``--mode stream`` (Sylvac and TESA stream too).  A polled gauge
converts at ``--rate`` (device time) and answers each request with its latest
conversion; the URL it prints polls at ``--poll-rate`` (15.625 Hz).  Its line
is emulated at ``--line-baud`` (default: the profile's baud; 0: as fast as the
pty): an answer is written when its last byte would have arrived, after the
request's and its own bytes at that baud.  Device time runs ``speedup`` times faster than wall time: at ``--rate 1000
--speedup 10`` the device clock and sample counter advance as at 1 kHz and
10 000 frames leave per wall second.  Samples go out as they fall due, but
at most one write per ``--burst-ms`` (16 ms, the default latency timer of FTDI
adapters, which deliver in bursts too): at 15.625 Hz each sample on time, at
1 kHz 16 in one write.  The device sleeps in between; the frames and their
counter and clock are the same as with one write per sample (the samples of a
test are encoded a few thousand at a time, ahead of need).  If the reader does
not keep up (the pty buffer fills), the device waits rather than losing samples;
samples are lost only on command.  The simulated interface is powered on its own: across an
unplug or a stall it keeps sampling, so its counter shows the gap.

Commands on stdin, one per line (EOF on stdin is ignored unless ``--exit-on-eof``,
which :class:`DeviceProcess` passes so that its device ends with its parent; SIGTERM ends it):

``start``           begin streaming (with ``--wait``)
``garbage N``       send N junk bytes before the next sample (binary: no byte
                    ``A5`` or ``5A``, so no false sync word; ASCII: one junk line
                    of N bytes, counted as one ``bad_line``)
``corrupt N``       corrupt the next N samples (binary: one bit flipped after the
                    sync word; ASCII: a character of the reading replaced): each
                    costs one lost sample and one ``bad_crc``/``bad_line``
``drop N``          do not send the next N samples (lost)
``stall S``         send nothing for S wall seconds; the samples taken are lost
``unplug [S]``      close the pty (and remove the link); replug after S seconds if given
``replug``          open a new pty behind the same link
``reset``           restart the sample counter and clock at 0 (a device reboot)
``error over|fault [N]``  a gauge profile: answer the next N requests (or send the
                    next N lines) with the profile's over-range or sensor-fault
                    error word (Sylvac ``ERR3``, ``ERR0``; TESA ``ERR<n>``; a
                    Mitutoyo answer has no error word: refused)
``late S [N]``      polled: the next N answers come S wall seconds late
``cut [N]``         polled: the next N answers are cut after half their bytes
                    (no line end), as by a cable pulled mid-answer
``jump S``          the device clock jumps S seconds ahead (S > 0); the counter
                    runs on and no sample is lost
``stats``           counters so far
``quit``            exit
"""

from __future__ import annotations

import argparse
import bisect
import contextlib
import json
import logging
import math
import os
import pty
import select
import signal
import stat
import sys
import tempfile
import threading
import time
import tty
import urllib.parse
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ballbar.protocol import Status
from ballbar.protocol import ascii as ascii_proto
from ballbar.protocol import binary as binary_proto

log = logging.getLogger(__name__)

Chunk = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]
Wire = tuple[bytes, NDArray[np.int64]]  # encoded samples, and where each starts (and the last ends)
PENDING_LIMIT = 16 * 1024  # bytes waiting for the reader before the device waits (at least 4 bursts' worth)
BURST_S = 0.016  # the shortest time between two writes (FTDI adapters' default latency timer)
IDLE_S = 1.0  # the longest sleep with nothing due (commands wake the device at once)
GARBAGE_CHARS = b"#$%&@!*=~^|<>"  # none is a digit, letter, sign, point or separator


# ----------------------------------------------------------------------------- samples


class _NextTest:
    """The next test of ``tests``, made on a thread of its own while the current one streams."""

    def __init__(self, tests: Iterator[Chunk]) -> None:
        self.value: Chunk | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(tests,), name="simdevice-next-test", daemon=True)
        self.thread.start()

    def _run(self, tests: Iterator[Chunk]) -> None:
        try:
            self.value = next(tests, None)
        except BaseException as err:  # handed to the streaming thread, which raises it
            self.error = err

    def result(self) -> Chunk | None:
        self.thread.join()
        if self.error is not None:
            raise self.error
        return self.value


class Feed:
    """Samples of successive tests, taken in device-time order.

    The first test is made at once; each next one on a thread while the one before streams
    (simulating a test takes about a second), so the device keeps sending across the gap
    between tests, as a real ball-bar's LVDT keeps reporting: made on demand, it held the
    stream up for that second, and the daemon reported a stall and a resume between tests.
    """

    def __init__(self, tests: Iterator[Chunk]) -> None:
        self._tests = tests
        self._t: NDArray[np.float64] = np.empty(0)
        self._len: NDArray[np.float64] = np.empty(0)
        self._seq: NDArray[np.int64] = np.empty(0, np.int64)
        self._i = 0
        self.exhausted = False
        self.tests = 0
        self._next: _NextTest | None = None
        self._load()

    def _fetch(self) -> Chunk | None:
        nxt = next(self._tests, None) if self._next is None else self._next.result()  # the first: at once
        self._next = _NextTest(self._tests) if nxt is not None else None
        return nxt

    def _load(self) -> bool:
        while self._i >= self._t.shape[0]:
            if self.exhausted:
                return False
            nxt = self._fetch()
            if nxt is None:
                self.exhausted = True
                return False
            self._t, self._len, self._seq = nxt
            self._i = 0
            self.tests += 1
        return True

    @property
    def next_t(self) -> float:
        return float(self._t[self._i]) if not self.exhausted else math.inf

    def take_until(self, t_lim: float, limit: int = 1 << 16) -> Chunk:
        """Samples with device time <= ``t_lim`` (at most ``limit``), across tests."""
        return self._take(t_lim, limit, None)[0]

    def take_encoded(self, t_lim: float, encoder: BlockEncoder, limit: int = 1 << 16) -> tuple[Chunk, bytes]:
        """:meth:`take_until`, and the samples' wire bytes from ``encoder``."""
        return self._take(t_lim, limit, encoder)

    def _take(self, t_lim: float, limit: int, encoder: BlockEncoder | None) -> tuple[Chunk, bytes]:
        parts: list[Chunk] = []
        data: list[bytes] = []
        n = 0
        while n < limit and self._load() and self._t[self._i] <= t_lim:
            end = int(np.searchsorted(self._t, t_lim, side="right"))
            end = min(end, self._i + limit - n)
            sl = slice(self._i, end)
            parts.append((self._t[sl], self._len[sl], self._seq[sl]))
            if encoder is not None:
                data.append(encoder.wire(self.tests, self._t, self._len, self._seq, self._i, end))
            n += end - self._i
            self._i = end
        self._load()
        wire = data[0] if len(data) == 1 else b"".join(data)
        if not parts:
            return (np.empty(0), np.empty(0), np.empty(0, np.int64)), wire
        if len(parts) == 1:
            return parts[0], wire
        return (
            np.concatenate([p[0] for p in parts]),
            np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]),
        ), wire


class BlockEncoder:
    """The wire bytes of a test's samples, encoded ``block`` samples at a time ahead of need.

    numpy's cost is per call: encoding the few samples of each write one call at a
    time would cost more than all else the device does.  ``encode`` returns a block's
    bytes and the offset of each sample's bytes in them (plus the end); ``key`` is the
    device state they depend on (its counter and clock offsets): change it and what
    is left is encoded again.
    """

    def __init__(
        self,
        encode: Callable[[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]], Wire],
        block: int = 4096,
    ) -> None:
        self.encode = encode
        self.block = block
        self.key: object = None
        self._cache: tuple[int, object, int, int, bytes, NDArray[np.int64]] | None = None
        self.blocks = 0  # blocks encoded so far

    def wire(
        self, test: int, t: NDArray[np.float64], length: NDArray[np.float64], seq: NDArray[np.int64], i0: int, i1: int
    ) -> bytes:
        """The bytes of samples ``i0`` to ``i1`` (excluded) of test number ``test`` (its arrays)."""
        c = self._cache
        if c is None or c[0] != test or c[1] != self.key or not c[2] <= i0 <= i1 <= c[3]:
            b1 = min(t.shape[0], max(i1, i0 + self.block))
            data, off = self.encode(t[i0:b1], length[i0:b1], seq[i0:b1])
            c = self._cache = (test, self.key, i0, b1, data, off)
            self.blocks += 1
        b0, data, off = c[2], c[4], c[5]
        return data[off[i0 - b0] : off[i1 - b0]]


def plans_of(text: str) -> Any:
    """``--library``: a JSON table of plans as the daemon's configuration records them (``config["plans"]``)."""
    from ballbar.analysis.errors import PlanError
    from ballbar.daemon.config import ConfigError, library_of

    try:
        tables = json.loads(text)
        if not isinstance(tables, dict) or not tables:
            raise ValueError("not a table of plans")
        return library_of({"plans": tables})
    except (ValueError, ConfigError) as err:
        raise PlanError(f"--library: {err}") from None


def simulated_set(args: argparse.Namespace) -> Iterator[Chunk]:
    """A set's plans in turn on the 3D machine (:mod:`ballbar.tools.machine3d`), as the bar reads them."""
    from ballbar.analysis.errors import PlanError
    from ballbar.tools.machine3d import Machine3D, set_tests

    library = plans_of(args.library)
    names = [n.strip() for n in args.run_plans.split(",") if n.strip()] if args.run_plans else list(library.names)
    machine = Machine3D.from_settings(_floats(args.set, "--set"))
    drift = _floats(getattr(args, "drift", None) or [], "--drift")
    if args.rate != library.first.plan.sample_hz:
        log.info("the plans sample at %g Hz; the device at %g Hz", library.first.plan.sample_hz, args.rate)
    if not names:
        raise PlanError("--run-plans names no plan")
    repeat = None if args.repeat == 0 else args.repeat
    for _name, res in set_tests(library, names, machine, args.rate, args.seed, repeat, args.gap_s, drift):
        yield res.t_s, res.length_mm, np.rint(res.t_s * args.rate).astype(np.int64)


def _floats(items: Sequence[str], what: str) -> dict[str, float]:
    from ballbar.analysis.errors import PlanError

    out: dict[str, float] = {}
    for item in items:
        key, sep, text = item.partition("=")
        try:
            if not sep:
                raise ValueError(item)
            out[key.strip()] = float(text)
        except ValueError:
            raise PlanError(f"{what} needs KEY=NUMBER, not {item!r}") from None
    return out


def simulator_tests(args: argparse.Namespace) -> Iterator[Chunk]:
    from ballbar.tools.simulator import MachineModel, iter_tests, parse_set, plan_from_args

    if getattr(args, "library", None):
        yield from simulated_set(args)
        return
    plan = plan_from_args(args, args.rate)
    machine = MachineModel(**parse_set(args.set))
    drift = {k: float(v) for k, v in parse_set(getattr(args, "drift", None) or []).items()}
    for res in iter_tests(plan, machine, args.rate, args.seed, None if args.repeat == 0 else args.repeat, args.gap_s,
                          drift=drift):
        yield res.t_s, res.length_mm, np.rint(res.t_s * args.rate).astype(np.int64)


def csv_tests(path: str, rate: float, repeat: int, gap_s: float) -> Iterator[Chunk]:
    from ballbar.daemon.recordings import read_csv

    t, length = read_csv(path)
    t = t - t[0]
    span = (t[-1] if t.shape[0] else 0.0) + 1.0 / rate + gap_s
    i = 0
    while repeat == 0 or i < repeat:
        ti = t + i * span
        yield ti, length, np.rint(ti * rate).astype(np.int64)
        i += 1


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
        except BlockingIOError:
            # Nobody reads our stdout (a pipe left full): lose the line, never stall the device.
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


# ----------------------------------------------------------------------------- driving it


class DeviceProcess:
    """The device as a child process, driven through its stdin and stdout.

    For tests and demos::

        with DeviceProcess("--rate", "1000", "--wait") as dev:
            src = open_source(dev.url)
            dev.send("start")
            dev.send("drop 5")
            done = dev.wait_event("done", timeout=30)

    No threads: stdout is read with ``select`` as replies are awaited.  ``wait=False``
    returns at once, before the device is up (it simulates its first test first):
    :meth:`wait_ready` then says when its port is there.
    """

    def __init__(self, *args: str, timeout: float = 15.0, wait: bool = True) -> None:
        import subprocess

        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.simdevice", "--exit-on-eof", *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        assert self.proc.stdout is not None and self.proc.stdin is not None
        self._out = self.proc.stdout
        self._in = self.proc.stdin
        self._buf = b""
        self.events: list[dict[str, Any]] = []
        self.path = ""
        self.ready: dict[str, Any] = {}
        self.url = ""
        if wait:
            try:
                if not self.wait_ready(timeout):
                    raise TimeoutError(f"simdevice: not ready within {timeout} s")
            except Exception:
                self.close()
                raise

    def wait_ready(self, timeout: float) -> bool:
        """Whether the device is up (its port path and ``ready`` line read), waiting up to ``timeout`` s.

        Raises :class:`EOFError` if it exited first (a bad argument: its stderr says why).
        """
        deadline = time.monotonic() + timeout
        try:
            if not self.path:
                self.path = self._line(timeout)
            if not self.ready:
                self.ready = json.loads(self._line(max(0.0, deadline - time.monotonic())))
                self.url = self.ready["url"]
        except TimeoutError:
            return False
        return True

    def _line(self, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        fd = self._out.fileno()
        while b"\n" not in self._buf:
            ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:
                    raise EOFError(f"simdevice exited (code {self.proc.poll()})")
                self._buf += chunk
            elif time.monotonic() >= deadline:
                raise TimeoutError(f"simdevice: no output within {timeout} s")
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode()

    def _pump(self, timeout: float) -> dict[str, Any]:
        obj: dict[str, Any] = json.loads(self._line(timeout))
        if "event" in obj:
            self.events.append(obj)
        return obj

    def send(self, command: str, timeout: float = 10.0) -> dict[str, Any]:
        """Send a command; its reply (events seen meanwhile go to :attr:`events`)."""
        self._in.write(command.encode() + b"\n")
        self._in.flush()
        deadline = time.monotonic() + timeout
        while True:
            obj = self._pump(max(0.0, deadline - time.monotonic()))
            if "ok" in obj:
                if not obj["ok"]:
                    raise ValueError(f"simdevice: {command!r}: {obj.get('error')}")
                return obj

    def poll_events(self) -> list[dict[str, Any]]:
        """Events that have arrived, without waiting."""
        while b"\n" in self._buf or select.select([self._out.fileno()], [], [], 0)[0]:
            try:
                self._pump(0.5)
            except (TimeoutError, EOFError):
                break
        return self.events

    def wait_event(self, name: str, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        seen = 0
        while True:
            for ev in self.events[seen:]:
                if ev.get("event") == name:
                    return ev
            seen = len(self.events)
            self._pump(max(0.0, deadline - time.monotonic()))

    def stats(self) -> dict[str, Any]:
        stats: dict[str, Any] = self.send("stats")["stats"]
        return stats

    def close(self, timeout: float = 5.0) -> int | None:
        """Ask it to quit (end it if it is not up yet), wait, kill it if it will not; close the pipes."""
        import subprocess

        if self.proc.poll() is None:
            if not self.url:
                self.proc.terminate()  # not up yet: it reads no command until it is
            else:
                with contextlib.suppress(OSError, ValueError):
                    self._in.write(b"quit\n")
                    self._in.flush()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        for pipe in (self._in, self._out):
            with contextlib.suppress(OSError):
                pipe.close()
        return self.proc.returncode

    def __enter__(self) -> DeviceProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ----------------------------------------------------------------------------- main


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m ballbar.tools.simdevice",
        description="A simulated ball-bar interface on a pty; fault injection on stdin (see the module docstring).",
    )
    from ballbar.protocol.gauges import PROFILES

    p.add_argument("--protocol", choices=["binary", "ascii", *PROFILES], default="binary",
                   help="a wire format, or a gauge interface's profile (protocol/README.md)")
    p.add_argument("--mode", choices=["stream", "poll"],
                   help="ascii and gauges: answer requests (poll); default stream, a polled gauge's poll")
    p.add_argument("--poll-rate", type=float, default=15.625, help="a polled gauge: the rate its printed URL asks")
    p.add_argument("--line-baud", type=int, help="a gauge: the emulated line's baud (default the profile's; 0: none)")
    p.add_argument("--rate", type=float, default=1000.0, help="device sample rate, Hz (15.625..10000)")
    p.add_argument("--speedup", type=float, default=1.0, help="device time per wall time")
    p.add_argument("--port", help="use this port (path or pyserial URL) instead of a new pty")
    p.add_argument("--baud", type=int, default=2_000_000, help="with --port")
    p.add_argument("--link", help="stable path to the pty (a symbolic link); default in a temporary directory")
    p.add_argument("--csv", help="stream this recording (t_s,length_mm) instead of the simulator")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--drift", action="append", default=[], metavar="KEY=RATE",
                   help="a machine key that changes by RATE from one test to the next, e.g. backlash_x_um=0.5 "
                   "(a machine that wears; repeatable)")
    p.add_argument("--repeat", type=int, default=1, help="tests in a row (0: forever)")
    p.add_argument("--gap-s", type=float, default=0.0, help="device seconds between tests")
    p.add_argument("--cal-mm", type=float, help="bar length at zero displacement (default: the plan's radius; "
                   "with --library the first plan's)")
    p.add_argument("--range-mm", type=float, default=2.5, help="LVDT linear range, +- mm")
    p.add_argument("--wait", action="store_true", help="stream only after the 'start' command")
    p.add_argument("--exit-when-done", action="store_true", help="exit once every test is sent")
    p.add_argument("--exit-on-eof", action="store_true", help="exit when stdin closes (a child of a program)")
    p.add_argument(
        "--burst-ms", type=float, default=1e3 * BURST_S,
        help="shortest time between two writes of samples, ms (a USB adapter's latency timer; 0: every sample "
        "as it falls due)",
    )
    g = p.add_argument_group("ASCII format")
    g.add_argument("--unit", choices=["mm", "um", "nm", "in"], default="mm")
    g.add_argument("--timestamp", choices=["none", "s", "ms", "us"], default="none")
    g.add_argument("--unit-suffix", action="store_true")
    g.add_argument("--request", default="?\r", help="poll request (default '?\\r')")
    from ballbar.tools.simulator import add_plan_arguments

    add_plan_arguments(p.add_argument_group("test plan and machine (the simulator)"))
    g = p.add_argument_group("a set of plans on a 3D machine (tools/machine3d.py)")
    g.add_argument("--library", help="the plans, as JSON: the daemon's recorded config['plans'] (each plan's keys and "
                   "signature); the device runs them in turn on a machine with X, Y and Z errors, each program with "
                   "its signature; --set then takes the 3D machine's keys (backlash_z_um, squareness_yz_urad, ...)")
    g.add_argument("--run-plans", help="with --library: which plans, in this order, comma-separated (default: all)")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def source_url(path: str, s: Settings) -> str:
    if s.gauge is not None:
        from ballbar.protocol.gauges import PROFILES

        g: dict[str, str] = {"protocol": s.gauge, "rate": f"{s.poll_rate if s.mode == 'poll' else s.rate:g}",
                             "cal_mm": repr(s.cal_mm)}
        if s.mode != ("poll" if PROFILES[s.gauge].polled else "stream"):
            g["mode"] = s.mode
        if s.line_baud and s.line_baud != PROFILES[s.gauge].baud:
            g["baud"] = str(s.line_baud)
        return f"serial:{path}?{urllib.parse.urlencode(g)}"
    q: dict[str, str] = {"protocol": s.protocol, "rate": f"{s.rate:g}", "cal_mm": repr(s.cal_mm)}
    if s.protocol == "ascii":
        q["unit"] = s.fmt.unit
        if s.fmt.ts_unit:
            q["timestamp"] = s.fmt.ts_unit
        if s.mode == "poll":
            q["mode"] = "poll"
            q["request"] = s.fmt.request.decode("latin-1")
    return f"serial:{path}?{urllib.parse.urlencode(q)}"


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from ballbar.analysis.errors import BallbarError

    if not 15.625 <= args.rate <= 10_000 or not args.speedup > 0 or args.repeat < 0 or not 0 <= args.burst_ms <= 1000:
        log.error("--rate must be within 15.625..10000, --speedup > 0, --repeat >= 0, --burst-ms within 0..1000")
        return 2
    from ballbar.protocol.gauges import PROFILES

    gauge = PROFILES.get(args.protocol)
    if args.mode is None:
        args.mode = "poll" if gauge is not None and gauge.polled else "stream"
    if args.mode == "poll" and args.protocol == "binary":
        log.error("--mode poll needs --protocol ascii or a gauge profile")
        return 2
    if gauge is not None and args.mode == "stream" and not gauge.streams:
        log.error("a %s gauge does not stream: it answers requests", args.protocol)
        return 2
    try:
        ts_unit = None if args.timestamp == "none" else args.timestamp
        # Fixed-width lines, as gauges write them: a sign, the digits the range
        # needs, the point and the decimals; timestamps zero-padded to 12 digits.
        probe = ascii_proto.AsciiFormat(unit=args.unit)
        int_digits = len(str(int(args.range_mm / ascii_proto.UNIT_MM[args.unit])))
        fmt = ascii_proto.AsciiFormat(
            unit=args.unit,
            ts_unit=ts_unit,
            unit_suffix=args.unit_suffix,
            request=args.request.encode("latin-1"),
            width=1 + int_digits + 1 + probe.digits if probe.digits else 1 + int_digits,
            ts_width={"s": 13, "ms": 13, "us": 12}.get(args.timestamp, 0),
        )
        if gauge is not None:
            fmt = gauge.fmt
        settings = Settings(
            gauge=gauge.name if gauge is not None else None,
            prefix=gauge.prefix if gauge is not None else "",
            poll_rate=args.poll_rate,
            line_baud=(gauge.baud if args.line_baud is None else args.line_baud) if gauge is not None else 0,
            bits_per_char=gauge.bits_per_char if gauge is not None else 10,
            protocol=args.protocol,
            mode=args.mode,
            rate=args.rate,
            speedup=args.speedup,
            cal_mm=args.cal_mm if args.cal_mm is not None else (
                plans_of(args.library).first.plan.radius_mm if args.library else args.radius_mm),
            range_mm=args.range_mm,
            fmt=fmt,
            seed=args.seed,
            burst_s=args.burst_ms / 1e3,
        )
        tests = csv_tests(args.csv, args.rate, args.repeat, args.gap_s) if args.csv else simulator_tests(args)
        feed = Feed(tests)
    except (BallbarError, ValueError) as err:
        log.error("%s", err)
        return 2

    tmpdir = None
    try:
        if args.port:
            port: PtyPort | SerialPort = SerialPort(args.port, args.baud)
        else:
            link = args.link
            if link is None:
                tmpdir = tempfile.mkdtemp(prefix="ballbar-simdevice-")
                link = os.path.join(tmpdir, "ttyBALLBAR0")
            port = PtyPort(link)
    except OSError as err:
        log.error("cannot open the port: %s", err)
        return 1

    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    # A signal wakes the loop at once (it may sleep up to IDLE_S): its number comes down this pipe.
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    old_wakeup = signal.set_wakeup_fd(wake_w)

    out = sys.stdout.fileno()
    dev = SimDevice(feed, port, settings, out)
    os.write(out, (port.path + "\n").encode())
    dev.emit({"event": "ready", "path": port.path, "url": source_url(port.path, settings)})
    if stat.S_ISFIFO(os.fstat(out).st_mode):
        # A pipe that its reader stops reading must not stall the device (a terminal is
        # left alone: the flag would be shared with the shell).
        os.set_blocking(out, False)
    dev.started = not args.wait
    stdin_fd: int | None = sys.stdin.fileno() if sys.stdin is not None else None
    inbuf = b""
    try:
        while dev.running and not stop:
            rlist = [wake_r] if stdin_fd is None else [wake_r, stdin_fd]
            if settings.mode == "poll" and port.is_open:
                fd = port.fileno()
                if fd is not None:
                    rlist.append(fd)
            wfd = dev.write_fd()
            now = time.monotonic()
            try:
                ready, _, _ = select.select(rlist, [] if wfd is None else [wfd], [], max(0.0, dev.next_wake(now) - now))
            except InterruptedError:
                continue
            now = time.monotonic()
            if wake_r in ready:
                with contextlib.suppress(BlockingIOError):
                    os.read(wake_r, 512)
            if stdin_fd is not None and stdin_fd in ready:
                chunk = os.read(stdin_fd, 4096)
                if not chunk:
                    if args.exit_on_eof:
                        break  # the process driving it has gone (a killed daemon's demo device)
                    stdin_fd = None  # EOF: keep running, commands are optional
                inbuf += chunk
                if b"\n" in inbuf:
                    dev.step(now)  # what fell due before the commands goes out as it was
                while b"\n" in inbuf:
                    line, inbuf = inbuf.split(b"\n", 1)
                    dev.command(line.decode("utf-8", "replace"), now)
            dev.step(now)
            if dev.done and args.exit_when_done:
                break
    except BrokenPipeError:
        pass  # the controlling process went away
    finally:
        signal.set_wakeup_fd(old_wakeup)
        os.close(wake_r)
        os.close(wake_w)
        port.close()
        if tmpdir:
            with contextlib.suppress(OSError):
                os.rmdir(tmpdir)
    return 0


__all__ = [
    "DeviceProcess",
    "DeviceStats",
    "Feed",
    "PtyPort",
    "SerialPort",
    "Settings",
    "SimDevice",
    "main",
    "source_url",
]

if __name__ == "__main__":
    sys.exit(main())
