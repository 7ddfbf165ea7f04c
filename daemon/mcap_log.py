"""The daemon's MCAP log: every sample, event, result, status and the configuration.

:class:`McapLogger` is the listener (name ``"mcap"``) that writes them;
:func:`read_mcap` and :func:`read_log` read them back, also from files whose
writer was killed.  Any MCAP reader opens the files (Foxglove, the ``mcap``
CLI, the ``mcap`` Python and npm packages): every channel is JSON
(``message_encoding = "json"``) with a JSON Schema (``encoding = "jsonschema"``).

Files
-----
``STATE_DIR/recordings/<machine>_<UTC start, YYYYmmddTHHMMSSZ>_<seq>.mcap``; the
names sort in time order.  A file starts with a metadata record ``ballbar``
(``format`` = ``ballbar-mcap/1``, ``machine_id``, ``host_clock_offset_ns``, ``run_id`` (one per
daemon start), ``created_utc``, ``reason`` = start, test, size, age or recovery, ``software``).
A new file begins at each test (the analysis's ``feed_in`` event), when a file
reaches ``rotate_bytes`` or ``rotate_s``, and after a write error.  Size and
age rotations wait for a test in progress to end (up to twice the limit), so
that a test is never split.  The per-test file first repeats the last
``preroll_s`` seconds of samples (flagged ``preroll``) since the feed-in was
recognised a little after it happened: a test's file holds the whole test, and
``ballbar analyze FILE`` finds it as the file's first test.  Retention runs at
each new file and every minute: the oldest files go while the directory holds
more than ``quota_bytes``, and every file last written more than ``keep_days``
ago; the open file never goes, nor files not named like the logger's.

Channels
--------
All times are integer nanoseconds.  ``log_time`` is host wall-clock time (Unix
epoch, UTC): the host's monotonic clock plus ``host_clock_offset_ns``, measured
once when the logger starts, so that wall-clock steps (NTP) never reorder
samples.  ``publish_time`` is the wall-clock time the record was written.

``/ballbar/samples`` (schema ``ballbar.Samples``): the samples, one message per
flush (about ``flush_s`` of them), columns delta-encoded as JSON integer arrays::

    {"source": "serial:/dev/ttyUSB0", "count": n, "preroll": false,
     "seq_first": 1000, "seq_delta": [1, 1, ...],                       # n - 1 each
     "t_host_first": {"sec": 1767225600, "nsec": 5000}, "t_host_delta_ns": [1000013, ...],
     "t_device_first": {"sec": 12, "nsec": 0}, "t_device_delta_ns": [1000000, ...],
     "length_first_pm": 100001234567, "length_delta_pm": [-120, 87, ...],
     "length_missing": [],                                              # sample indices
     "status": [0, 0, ...]}                                             # n

    value[0] = *_first, value[i] = value[i-1] + *_delta[i-1]

``seq``: the source's sample number.  ``t_host``: when the sample was taken,
on the host's clock (wall-clock ns, see above).  ``t_device``: the device's
sample clock, ns, or ``null`` (both fields) where the source has none.
``length``: the absolute bar length in picometres (1e-9 mm); indices in
``length_missing`` had no number (NaN: a sensor fault) and hold the previous
value as a placeholder.  ``status``: :class:`ballbar.protocol.Status` bits
(1 over range, 2 sensor fault: not measurements; 128 simulated).
``preroll``: samples repeated at the head of a per-test file; the previous file
ended with them.  ``log_time`` is the first sample's host time.  Times and
lengths are stored to 1 ns and 1 pm, the resolution of the CSV format; read
back, each value is the stored integer divided by 1e9 (a correctly rounded
double), the same number the CSV would give.

``/ballbar/events`` (``ballbar.Event``): ``{"event": NAME, "t_host": s, ...}``;
a source's events (``opened``, ``unplugged``, ``replugged``, ``lost`` with
``count`` and ``seq``, ``decode_errors`` with ``counts``, ``stall``,
``resumed``, ``device_reset`` and ``clock_jump`` with ``seq``, ``end``; the fields of
:meth:`~ballbar.daemon.samples.SourceEvent.to_dict`) and the pipeline's
(``feed_in``, ``feed_out``, ``circle_done``, ``test_rejected``,
``test_incomplete``, ...), plus the logger's own ``log_gap``: ``count`` samples
that could not be written over ``gap_s`` seconds, ``detail`` the error.
``t_host`` is the host's monotonic clock in seconds (``log_time`` is the same
instant on the wall clock).

``/ballbar/results`` (``ballbar.Result``): the analysis results, ``kind`` =
``circle``, ``test`` or ``set`` (a test set, :mod:`.sets`), the tests as ``ballbar analyze --json`` prints them plus
``machine_id``, ``test_id``, ``t_host``, ``last_sample_t``, ``last_sample_t_host``, ``latency_ms``.

``/ballbar/status`` (``ballbar.Status``): the daemon's status messages
(``kind`` = ``status``: rates, losses, queue depths, source state).

``/ballbar/config`` (``ballbar.Config``): the effective configuration
(``kind`` = ``config``), at start and again at the head of every new file.
A polled source's last ``timing`` event is repeated likewise (``repeated``:
true), so that a test's file alone says how its samples were stamped.

``/ballbar/other`` (``ballbar.Message``): any other message kind, as it came.

Crash safety
------------
Chunks are zstd-compressed and closed (``Writer.flush``) at most ``flush_s``
(0.5 s) after the first record in them was handed over, or for samples after
the first of them was read (their host time: the pipeline hands samples over
merged about every 0.25 s, and the time they waited counts), by a small flush
thread that sleeps until that deadline, whatever the caller does; the kernel
then has them, so a killed daemon (``kill -9``) loses at most that last half
second (a power cut can lose more: files are fsync'ed only when closed).
:func:`read_log` reads such a file up to its last whole chunk.  ``stop()``
(SIGTERM) writes the footer and indexes.

Write errors
------------
A full disk (``ENOSPC``) or any other ``OSError`` on write: one ``ERROR`` log
line, the file is dropped (what reached it stays readable; an empty one is
deleted), its unwritten samples and all that follow are counted as lost, and
a new file is tried after a backoff (``retry_min_s`` doubling to
``retry_max_s``); after a full disk, as soon as a ``statvfs`` every
``space_probe_s`` sees :meth:`McapLogger.headroom` free (what one file needs,
up to ``headroom_bytes`` and a 64th of the file system).  The first file that
works again starts with a ``log_gap`` event and a ``WARNING`` log line.
Results and events meanwhile are held in memory and written after it; at stop,
what no file can take goes to the spool (:mod:`.spool`), which the next start
writes.  Nothing is raised into the pipeline.

Reading
-------
The readers take any file: a cut one up to its last whole record, a record or
chunk larger than :data:`MAX_RECORD_BYTES` as the end of the file, at most
:data:`SIDE_BYTES_MAX` of events, results and status from one file; anything
else wrong is one :class:`~ballbar.analysis.errors.DataError` line naming the
file (and, for a directory, :func:`read_logs` with ``skip_bad`` leaves such a
file out with a warning).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import math
import os
import re
import struct
import threading
import time
import uuid
from collections import deque
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer
from numpy.typing import NDArray

from ballbar import __version__
from ballbar.analysis.errors import BallbarError, DataError
from ballbar.protocol import INVALID
from ballbar.protocol.messages.channels import MCAP_CHANNELS, shipped_schema

from .csvfile import open_recording
from .listeners import MERGE_S, TEST_END_EVENTS, Listener, to_json
from .listeners import Message as ListenerMessage
from .recordings import Recording
from .samples import SampleBatch, SourceEvent, break_reason, break_seq
from .spool import SPOOL_NAME, empty_spool, read_spool, reserve_spool, spool_size, write_spool

if TYPE_CHECKING:
    from ballbar.protocol.messages.events import LogGap

log = logging.getLogger(__name__)

FORMAT = "ballbar-mcap/1"
METADATA_NAME = "ballbar"
RECORDINGS = "recordings"

TOPIC_SAMPLES = "/ballbar/samples"
TOPIC_EVENTS = "/ballbar/events"
TOPIC_RESULTS = "/ballbar/results"
TOPIC_STATUS = "/ballbar/status"
TOPIC_CONFIG = "/ballbar/config"
TOPIC_OTHER = "/ballbar/other"

NS = 1_000_000_000
PM_PER_MM = 1_000_000_000
MAX_BLOCK = 1 << 16  # samples per message at most
MAX_ABS_LENGTH_MM = 1.0e6  # beyond this a length is stored as missing (it would overflow the integers' exactness)
RETENTION_EVERY_S = 60.0
FLUSHER_MAX_WAIT_S = 1.0
_MAGIC = b"\x89MCAP0\r\n"
# Reading: a record (or a chunk's records, uncompressed) larger than this is not the logger's (a samples message
# is at most MAX_BLOCK samples, ~2 MB; a chunk closes past chunk_size, 4 MiB): a corrupt length field stops the
# reading there instead of taking gigabytes of memory.
MAX_RECORD_BYTES = 16 << 20
# ... and the events, results, configuration and status kept from one file at most this much JSON (beyond it,
# they are left out with a warning; the samples are read on).  A daemon's file holds some kB to a few MB.
SIDE_BYTES_MAX = 64 << 20
_NAME_RE = re.compile(r"^(?P<machine>.+)_(?P<ts>\d{8}T\d{6}Z)_(?P<seq>\d+)\.mcap$")


class LogConfigError(BallbarError, ValueError):
    """An invalid option of the MCAP logger."""


# ----------------------------------------------------------------------------- schemas

# The channels' schemas: the files shipped in ballbar/schema/, generated from the message types
# (ballbar.protocol.messages; tests/test_schemas.py keeps the two the same).
SCHEMAS: dict[str, tuple[str, dict[str, Any], str]] = {
    topic: (name, shipped_schema(document), description)
    for topic, (name, document, description) in MCAP_CHANNELS.items()
}

_RESULT_KINDS = frozenset({"circle", "test"})


# ----------------------------------------------------------------------------- exact scaling


_SPLIT = 134217729.0  # 2**27 + 1: Veltkamp's splitter for float64


def _split(a: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    c = _SPLIT * a
    hi = c - (c - a)
    return hi, a - hi


def scaled_ints(x: NDArray[np.float64], scale: int) -> NDArray[np.int64]:
    """``round(x * scale)`` computed exactly (ties to even), as ``"%.9f" % x`` rounds for ``scale = 1e9``.

    ``x * scale`` in floating point can land on the other side of a half; the
    product's error term (Dekker's two-product) says which side is right.  Only
    finite ``|x * scale| < 2**62`` are meaningful.
    """
    b = float(scale)
    p = x * b
    ah, al = _split(x)
    bh, bl = _split(np.array(b))
    err = ((ah * bh - p) + ah * bl + al * bh) + al * bl
    r = np.rint(p)
    # Only a product that rounded onto a half can be on the wrong side; then the error's sign decides.
    # (An exact half, err == 0, is a true tie: rint already rounded it to even, as printf does.)
    frac = p - r  # exact
    r = r + ((frac == 0.5) & (err > 0)) - ((frac == -0.5) & (err < 0))
    return r.astype(np.int64)


def _time_obj(ns: int) -> dict[str, int]:
    sec, nsec = divmod(int(ns), NS)
    return {"sec": sec, "nsec": nsec}


def _time_ns(obj: Mapping[str, Any]) -> int:
    return int(obj["sec"]) * NS + int(obj["nsec"])


# ----------------------------------------------------------------------------- samples records


def encode_samples(
    t_host_ns: NDArray[np.int64],
    t_device_ns: NDArray[np.int64] | None,
    length_pm: NDArray[np.int64],
    missing: NDArray[np.intp],
    seq: NDArray[np.int64],
    status: NDArray[np.uint8],
    source: str,
    preroll: bool = False,
) -> dict[str, Any]:
    """One ``ballbar.Samples`` message (a dict) from integer columns; see the module docstring."""
    n = int(t_host_ns.shape[0])
    return {
        "source": source,
        "count": n,
        "preroll": preroll,
        "seq_first": int(seq[0]),
        "seq_delta": np.diff(seq).tolist(),
        "t_host_first": _time_obj(int(t_host_ns[0])),
        "t_host_delta_ns": np.diff(t_host_ns).tolist(),
        "t_device_first": None if t_device_ns is None else _time_obj(int(t_device_ns[0])),
        "t_device_delta_ns": None if t_device_ns is None else np.diff(t_device_ns).tolist(),
        "length_first_pm": int(length_pm[0]),
        "length_delta_pm": np.diff(length_pm).tolist(),
        "length_missing": missing.tolist(),
        "status": status.tolist(),
    }


@dataclass
class DecodedSamples:
    """The integer columns of one ``ballbar.Samples`` message."""

    t_host_ns: NDArray[np.int64]
    t_device_ns: NDArray[np.int64] | None
    length_pm: NDArray[np.int64]
    missing: NDArray[np.intp]
    seq: NDArray[np.int64]
    status: NDArray[np.uint8]
    source: str
    preroll: bool


def _undelta(first: int, delta: Sequence[int], n: int, what: str) -> NDArray[np.int64]:
    if len(delta) != n - 1:
        raise ValueError(f"{what} has {len(delta)} steps for {n} samples")
    out = np.empty(n, np.int64)
    out[0] = first
    if n > 1:
        np.cumsum(np.asarray(delta, dtype=np.int64), out=out[1:])
        out[1:] += first
    return out


def decode_samples(msg: Mapping[str, Any]) -> DecodedSamples:
    """Integer columns of a ``ballbar.Samples`` message; ``ValueError``/``KeyError``/``TypeError`` if malformed."""
    n = int(msg["count"])
    if n < 1:
        raise ValueError(f"count is {n}")
    dev_first = msg.get("t_device_first")
    status = np.asarray(msg["status"], dtype=np.int64)
    if status.shape != (n,) or (status.size and (status.min() < 0 or status.max() > 255)):
        raise ValueError("status is not n bytes")
    missing = np.asarray(msg.get("length_missing") or [], dtype=np.intp)
    if missing.size and (missing.min() < 0 or missing.max() >= n):
        raise ValueError("length_missing index out of range")
    return DecodedSamples(
        t_host_ns=_undelta(_time_ns(msg["t_host_first"]), msg["t_host_delta_ns"], n, "t_host_delta_ns"),
        t_device_ns=None
        if dev_first is None
        else _undelta(_time_ns(dev_first), msg["t_device_delta_ns"], n, "t_device_delta_ns"),
        length_pm=_undelta(int(msg["length_first_pm"]), msg["length_delta_pm"], n, "length_delta_pm"),
        missing=missing,
        seq=_undelta(int(msg["seq_first"]), msg["seq_delta"], n, "seq_delta"),
        status=status.astype(np.uint8),
        source=str(msg.get("source", "")),
        preroll=bool(msg.get("preroll", False)),
    )


# ----------------------------------------------------------------------------- the writer


def _open_output(path: Path) -> IO[bytes]:
    """A new file for writing; refuses to overwrite.  (Tests replace this to simulate a full disk.)"""
    return open(path, "xb")


def _disk_space(path: Path) -> tuple[int, int] | None:
    """Bytes available to this process, and the size, of the file system of ``path`` (None: cannot tell).  Cheap:
    one statvfs.  (Tests replace this together with ``_open_output``.)"""
    try:
        st = os.statvfs(path)
    except OSError:
        return None
    return st.f_bavail * st.f_frsize, st.f_blocks * st.f_frsize


_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)
HELD_MAX = 2000  # results and events kept in memory while nothing can be written (oldest dropped, counted)
# A new file needs room for its head (the schemas, ~20 kB compressed) and its first seconds of samples (10 kHz:
# ~50 kB/s): after a full disk, writing resumes once this much is free, and at most headroom_bytes, and at most a
# 64th of the file system (a small one never has 64 MiB free).
FILE_NEEDS_BYTES = 256 << 10
_HELD_TOPICS = (TOPIC_RESULTS, TOPIC_EVENTS, TOPIC_CONFIG)


def _safe_machine(machine_id: str) -> str:
    s = re.sub(r"[^A-Za-z0-9.-]+", "-", machine_id).strip("-.")
    return s or "machine"


@dataclass
class _LogFile:
    path: Path
    fh: IO[bytes]
    writer: Writer
    channels: dict[str, int]
    opened: float  # host monotonic
    reason: str
    seqs: dict[int, int] = field(default_factory=dict)
    samples: int = 0
    unflushed_samples: int = 0
    flushed_records: int = 0
    bytes_counted: int = 0
    first_t: float = math.nan  # host time of the first and newest sample in it
    last_t: float = math.nan
    has_test: bool = False
    holds_held: bool = False  # results and events held through an outage were written to it: never deleted
    header: int = 0  # the header and metadata
    overhead: int = 0  # the size with the first chunk (schemas, first records): not counted against rotate_bytes

    def close_quietly(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.fh.close()


@dataclass
class _Pending:
    batches: list[SampleBatch] = field(default_factory=list)
    n: int = 0

    def clear(self) -> None:
        self.batches.clear()
        self.n = 0


class McapLogger(Listener):
    """Writes everything a pipeline delivers to rotating MCAP files; see the module docstring.

    Thread-safe: the pipeline's listener thread calls ``on_*``, a small flush
    thread (``mcap-flush``) closes chunks on time, and ``stop()`` may come from
    any thread.  Never raises from ``on_*``: write errors are logged, counted and
    retried (:meth:`stats`).
    """

    name = "mcap"
    batch_period_s = MERGE_S  # samples merged: a write a quarter second, not one per 20 ms batch
    idle_s = None  # the flush thread keeps the time

    def __init__(
        self,
        state_dir: str | os.PathLike[str],
        machine_id: str,
        *,
        rotate_bytes: int = 256 << 20,
        rotate_s: float = 3600.0,
        rotate_per_test: bool = True,
        quota_bytes: int = 8 << 30,
        keep_days: float = 365.0,
        flush_s: float = 0.5,
        chunk_size: int = 4 << 20,
        preroll_s: float = 10.0,
        retry_min_s: float = 1.0,
        retry_max_s: float = 60.0,
        headroom_bytes: int = 64 << 20,
        space_probe_s: float = 0.5,
    ) -> None:
        checks = [
            (rotate_bytes >= 4096, f"rotate_bytes must be >= 4096, not {rotate_bytes!r}"),
            (rotate_s > 0, f"rotate_s must be > 0, not {rotate_s!r}"),
            (quota_bytes >= 2 * rotate_bytes, f"quota_bytes {quota_bytes} must be >= 2 * rotate_bytes {rotate_bytes}"),
            (keep_days > 0, f"keep_days must be > 0, not {keep_days!r}"),
            (0 < flush_s <= 0.9, f"flush_s must be within (0, 0.9] (1 s old samples must be on disk), not {flush_s!r}"),
            (chunk_size >= 1024, f"chunk_size must be >= 1024, not {chunk_size!r}"),
            (preroll_s >= 0, f"preroll_s must be >= 0, not {preroll_s!r}"),
            (0 < retry_min_s <= retry_max_s, f"need 0 < retry_min_s <= retry_max_s, not {retry_min_s}, {retry_max_s}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise LogConfigError(f"mcap log: {msg}")
        self.state_dir = Path(state_dir)
        self.directory = self.state_dir / RECORDINGS
        self.machine_id = machine_id
        self._machine = _safe_machine(machine_id)
        self.rotate_bytes = int(rotate_bytes)
        self.rotate_s = float(rotate_s)
        self.rotate_per_test = rotate_per_test
        self.quota_bytes = int(quota_bytes)
        self.keep_days = float(keep_days)
        self.flush_s = float(flush_s)
        self.chunk_size = int(chunk_size)
        self.preroll_s = float(preroll_s)
        self.retry_min_s = float(retry_min_s)
        self.retry_max_s = float(retry_max_s)
        # A full disk: retried as soon as a cheap probe sees this much free (never on a sliver of space), or less on
        # a small file system (headroom()).
        self.headroom_bytes = int(headroom_bytes)
        self.space_probe_s = float(space_probe_s)
        self._no_space = False
        self._next_probe = 0.0
        self._held: deque[tuple[str, Mapping[str, Any], int]] = deque()
        # Host monotonic -> wall clock, once: log times stay monotonic if the wall clock steps.
        self.host_clock_offset_ns = time.time_ns() - time.monotonic_ns()
        # This daemon run's files share it; the offset above cannot tell runs apart (it is the same number
        # for every start of one boot but for the nanoseconds between two clock readings).
        self.run_id = uuid.uuid4().hex

        self._lock = threading.RLock()
        self._file: _LogFile | None = None
        self._pending = _Pending()
        self._ring: deque[SampleBatch] = deque()
        self._dirty_since: float | None = None
        self._config: ListenerMessage | None = None
        self._timing: dict[str, Any] | None = None  # a polled source's last timing event: repeated at each file's head
        self._seen_events: dict[tuple[str, float, str], None] = {}  # recent events, oldest first
        self._in_test = False
        self._stopped = False
        self._file_seq = 0
        self._last_retention = time.monotonic()  # first run when the first file opens
        self._next_reason = "start"
        # failures
        self._failing = False
        self._fail_since = 0.0
        self._fail_lost = 0
        self._fail_detail = ""
        self._retry_at = -math.inf
        self._backoff = self.retry_min_s
        # counters
        self._c: dict[str, int] = dict.fromkeys(
            ("files", "bytes", "samples", "messages", "samples_lost", "messages_lost", "write_errors",
             "deleted_files", "deleted_bytes", "encode_errors", "messages_held", "messages_held_written"),
            0,
        )
        self._last_error = ""
        # Results and events a previous run held through a write outage until it stopped: written to this run's
        # first file (then the spool is emptied), and given to the bus's history (spooled).
        self.spool_path = self.state_dir / SPOOL_NAME
        self._spool_reserved = False
        held = read_spool(self.state_dir).entries
        self._held.extend(held)
        self._spool_pending = bool(held)
        self.spooled: list[dict[str, Any]] = [dict(payload) for _t, payload, _l in held]
        if held:
            log.warning("mcap log: %d results and events the last run held through a write outage are in %s; "
                        "writing them to this run's first file", len(held), self.spool_path)

        self._wake = threading.Event()
        self._flusher_until = math.inf
        self._thread = threading.Thread(target=self._flusher, name="mcap-flush", daemon=True)
        self._thread.start()

    @classmethod
    def from_config(cls, cfg: Any) -> McapLogger:
        """From the daemon's configuration: ``cfg.daemon`` (``machine_id``, ``state_dir``) and ``[mcap]``.

        ``rotate_mb`` and ``quota_mb`` are MiB (2**20 bytes), ``rotate_minutes``
        minutes; keys the section lacks keep the defaults above.
        """
        m = cfg.mcap
        kw: dict[str, Any] = {}
        if getattr(m, "rotate_mb", None) is not None:
            kw["rotate_bytes"] = int(float(m.rotate_mb) * (1 << 20))
        if getattr(m, "quota_mb", None) is not None:
            kw["quota_bytes"] = int(float(m.quota_mb) * (1 << 20))
        if getattr(m, "rotate_minutes", None) is not None:
            kw["rotate_s"] = float(m.rotate_minutes) * 60.0
        for key in ("rotate_per_test", "keep_days", "flush_s", "preroll_s", "chunk_size"):
            if getattr(m, key, None) is not None:
                kw[key] = getattr(m, key)
        return cls(cfg.daemon.state_dir, cfg.daemon.machine_id, **kw)

    # ------------------------------------------------------------------ Listener

    def on_batch(self, batch: SampleBatch) -> None:
        with self._lock:
            if self._stopped:
                return
            now = time.monotonic()
            n = len(batch)
            if n:
                self._remember(batch)
            if not self._ensure_file(now):
                self._lose(n)
                self._c["messages_lost"] += len(batch.events)
                return
            for ev in batch.events:
                d = self._event_dict(ev)
                if self._first_sighting(d["event"], ev.t_host, ev.source):
                    self._write(TOPIC_EVENTS, d, self._wall_ns(ev.t_host))
            if n:
                self._pending.batches.append(batch)
                self._pending.n += n
                # The flush deadline counts from when the first sample was read, not from when it got here
                # (it waited up to a batch period in the queue; longer, and it was no read time of this run).
                t0 = float(batch.t_host[0])
                waited = min(now - t0, self.batch_period_s + 0.05) if math.isfinite(t0) else 0.0
                self._mark_dirty(now - max(0.0, waited))
                if self._pending.n >= MAX_BLOCK:
                    self._write_pending()
            self._tick(now)

    def on_message(self, msg: ListenerMessage) -> None:
        with self._lock:
            if self._stopped:
                return
            now = time.monotonic()
            kind = str(msg.get("kind", ""))
            topic = {
                "circle": TOPIC_RESULTS, "test": TOPIC_RESULTS, "set": TOPIC_RESULTS, "status": TOPIC_STATUS,
                "config": TOPIC_CONFIG,
            }.get(kind, TOPIC_OTHER)
            if kind == "event":
                self._on_event_message(msg, now)
            elif not self._ensure_file(now):
                self._hold_or_lose(topic, msg, self._msg_time_ns(msg))
            else:
                self._write(topic, msg, self._msg_time_ns(msg))
                if kind == "test":
                    self._in_test = False
            if kind == "config":  # after the write: a file opened for it must not repeat it
                self._config = msg
            self._tick(now)

    def on_idle(self) -> None:
        with self._lock:
            if not self._stopped:
                self._tick(time.monotonic())

    def flush(self) -> None:
        """Write what is pending and close the chunk now."""
        with self._lock:
            if self._file is not None and not self._stopped:
                self._flush_file()

    def stop(self) -> None:
        """Write what is pending, finish the file (footer, indexes), stop the flush thread.  Idempotent."""
        with self._lock:
            if self._stopped:
                return
            if self._file is None and self._held:  # a write outage: one last try, whatever the headroom
                self._open_file(time.monotonic())
            self._stopped = True
            if self._file is not None:
                self._close_file()
            if self._pending.n:  # no file could take them
                self._lose_pending()
            if self._held or self._failing:  # (the outage's log_gap alone tells the next start what cut this run)
                self._spool_held()
            self._ring.clear()
        self._wake.set()
        if threading.current_thread() is not self._thread:
            self._thread.join(5.0)
        c = self._c
        log.info(
            "mcap log stopped: %d files, %d samples, %d messages, %d bytes written; %d samples lost",
            c["files"], c["samples"], c["messages"], c["bytes"], c["samples_lost"],
        )

    # ------------------------------------------------------------------ inspection

    @property
    def current_path(self) -> Path | None:
        with self._lock:
            return self._file.path if self._file is not None else None

    def stats(self) -> dict[str, Any]:
        """Counters and state, JSON-ready (for the status message)."""
        with self._lock:
            state = "stopped" if self._stopped else "failed" if self._failing else "writing" if self._file else "idle"
            return {
                **self._c,
                "state": state,
                "file": str(self._file.path) if self._file else None,
                "pending_samples": self._pending.n,
                "held_messages": len(self._held),
                "last_error": self._last_error,
            }

    # ------------------------------------------------------------------ internals: timing

    def _flusher(self) -> None:
        """Sleeps until the next flush deadline (or at most ``FLUSHER_MAX_WAIT_S``: rotation by age,
        retention); ``_mark_dirty`` wakes it when a new deadline comes before its wake-up."""
        while True:
            try:
                with self._lock:
                    if self._stopped:
                        return
                    now = time.monotonic()
                    self._tick(now)
                    if self._dirty_since is not None:
                        wait = self._dirty_since + self.flush_s - now
                    elif self._file is None and self._failing:
                        wait = min(0.05, self.flush_s / 5.0)  # a write outage: look for space back often
                    else:
                        wait = FLUSHER_MAX_WAIT_S
                    wait = max(0.001, wait)
                    self._flusher_until = now + wait
                    self._wake.clear()
            except Exception:  # the flush thread must outlive any surprise
                log.exception("mcap log: flush thread error")
                wait = 0.05
            self._wake.wait(wait)

    def _mark_dirty(self, since: float) -> None:
        if self._dirty_since is None:
            self._dirty_since = since
            if since + self.flush_s < self._flusher_until:
                self._wake.set()  # the flush thread sleeps past this deadline

    def _tick(self, now: float) -> None:
        if self._file is None and self._failing and not self._stopped:
            self._ensure_file(now)  # space came back: resume now, with what was held, not at the next batch
        f = self._file
        if f is not None and self._dirty_since is not None and now - self._dirty_since >= self.flush_s:
            self._flush_file()
            f = self._file
        if f is not None and now - f.opened >= self.rotate_s * (2.0 if self._in_test else 1.0):
            self._rotate("age", now)
        if now - self._last_retention >= RETENTION_EVERY_S:
            self._retention(now)

    def _wall_ns(self, t_host: float) -> int:
        return self.host_clock_offset_ns + round(t_host * 1e9)

    def _msg_time_ns(self, msg: Mapping[str, Any]) -> int:
        t = msg.get("t_host")
        if isinstance(t, int | float) and not isinstance(t, bool) and math.isfinite(t):
            return self._wall_ns(float(t))
        return self._wall_ns(time.monotonic())

    def _remember(self, batch: SampleBatch) -> None:
        """Keep the last ``preroll_s`` of samples for the head of a per-test file."""
        if not (self.rotate_per_test and self.preroll_s > 0):
            return
        self._ring.append(batch)
        newest = float(batch.t_host[-1])
        while self._ring and float(self._ring[0].t_host[-1]) < newest - self.preroll_s:
            self._ring.popleft()

    # ------------------------------------------------------------------ internals: events and rotation

    @staticmethod
    def _event_dict(ev: SourceEvent) -> dict[str, Any]:
        d = ev.to_dict()
        name = d.pop("kind")
        return {"event": name, **d}

    def _on_event_message(self, msg: ListenerMessage, now: float) -> None:
        d = {k: v for k, v in msg.items() if k != "kind"}
        name = str(d.get("event", ""))
        d["event"] = name
        t = d.get("t_host")
        if isinstance(t, int | float) and not self._first_sighting(name, float(t), str(d.get("source", ""))):
            return
        if name == "feed_in":
            self._test_started(now)
        if name == "timing":
            self._timing = d
        if not self._ensure_file(now):
            self._hold_or_lose(TOPIC_EVENTS, d, self._msg_time_ns(d))
            return
        self._write(TOPIC_EVENTS, d, self._msg_time_ns(d))
        if name == "feed_in" and self._file is not None:
            self._file.has_test = True
        if name in TEST_END_EVENTS:
            self._in_test = False

    def _log_gap(self, now: float) -> LogGap:
        """The ``log_gap`` event of the write outage going on: what it cost so far."""
        return {"event": "log_gap", "t_host": now, "count": self._fail_lost, "gap_s": round(now - self._fail_since, 3),
                "detail": self._fail_detail}

    def _first_sighting(self, name: str, t_host: float, source: str) -> bool:
        """False for an event already written: a source event comes both in its batch and as the
        pipeline's message (either first); it is written once, as it came first."""
        key = (name, round(t_host, 6), source)
        if key in self._seen_events:
            return False
        self._seen_events[key] = None
        if len(self._seen_events) > 256:
            del self._seen_events[next(iter(self._seen_events))]
        return True

    def _test_started(self, now: float) -> None:
        f = self._file
        if f is not None and self.rotate_per_test:
            span = f.last_t - f.first_t if f.samples else 0.0
            if f.has_test or span > self.preroll_s:
                self._rotate("test", now)
                self._write_preroll()
        self._in_test = True

    def _write_preroll(self) -> None:
        """The ring's samples at the head of the new file, one message per ``flush_s`` of them (the size of the
        messages the flushes write), not one per batch (a 10 s preroll came as hundreds of small messages)."""
        if self._file is None or not self._ring:
            return
        for group in _group_by_period(list(self._ring), self.flush_s):
            self._write_samples(group, preroll=True)
            if self._file is None:
                return
        self._mark_dirty(time.monotonic())

    def _rotate(self, reason: str, now: float) -> None:
        if self._file is not None:
            log.info("mcap log: rotating %s (%s)", self._file.path.name, reason)
            self._close_file()
        self._next_reason = reason
        self._ensure_file(now)

    # ------------------------------------------------------------------ internals: files

    def _ensure_file(self, now: float) -> bool:
        if self._file is not None:
            return True
        if self._stopped:
            return False
        if self._no_space:
            # Out of space: not the backoff, but a statvfs every space_probe_s; a retry only with headroom.
            if now < self._next_probe:
                return False
            self._next_probe = now + self.space_probe_s
            space = _disk_space(self.directory if self.directory.exists() else self.state_dir)
            if space is not None and space[0] < self.headroom(space[1]):
                return False
            if space is None and now < self._retry_at:
                return False
        elif now < self._retry_at:
            return False
        return self._open_file(now)

    def headroom(self, total: int | None = None) -> int:
        """Bytes that must be free before writing resumes after a full disk, on a file system of ``total`` bytes
        (None: the state directory's): :data:`FILE_NEEDS_BYTES`, up to ``headroom_bytes`` and a 64th of it."""
        if total is None:
            space = _disk_space(self.directory if self.directory.exists() else self.state_dir)
            total = space[1] if space is not None else None
        if total is None:
            return self.headroom_bytes
        return max(FILE_NEEDS_BYTES, min(self.headroom_bytes, total // 64))

    def _new_path(self) -> Path:
        ts = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        prefix = f"{self._machine}_{ts}_"
        taken = [int(m["seq"]) for p in self.directory.glob(f"{prefix}*.mcap") if (m := _NAME_RE.match(p.name))]
        self._file_seq = max([self._file_seq, *taken]) + 1
        return self.directory / f"{prefix}{self._file_seq:04d}.mcap"

    def _open_file(self, now: float) -> bool:
        path: Path | None = None
        fh: IO[bytes] | None = None
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            path = self._new_path()
            fh = _open_output(path)
            writer = Writer(fh, chunk_size=self.chunk_size, compression=CompressionType.ZSTD)
            writer.start(profile="", library=f"ballbar {__version__}")
            writer.add_metadata(
                METADATA_NAME,
                {
                    "format": FORMAT,
                    "machine_id": self.machine_id,
                    "host_clock_offset_ns": str(self.host_clock_offset_ns),
                    "run_id": self.run_id,
                    "created_utc": datetime.now(UTC).isoformat(timespec="milliseconds"),
                    "reason": "recovery" if self._failing else self._next_reason,
                    "software": f"ballbar {__version__}",
                },
            )
            channels: dict[str, int] = {}
            for topic, (schema_name, schema, description) in SCHEMAS.items():
                sid = writer.register_schema(schema_name, "jsonschema", to_json(schema))
                channels[topic] = writer.register_channel(topic, "json", sid, {"description": description})
            writer.flush()  # the header and metadata (the schemas wait for the first chunk)
            header = fh.tell()
        except OSError as err:
            if fh is not None:
                with contextlib.suppress(OSError, ValueError):
                    fh.close()
            self._failed(err, path, delete=path if fh is not None else None, now=now)
            return False
        self._file = _LogFile(path, fh, writer, channels, now, self._next_reason, header=header)
        self._c["files"] += 1
        self._next_reason = "recovery"  # a file opened other than by _rotate follows a write error
        # At the file's own start: an old log_time would stretch the file's time range to the daemon's start.
        if self._config is not None:
            self._write(TOPIC_CONFIG, self._config, self._wall_ns(now))
        if self._timing is not None:  # a test's file alone says how its polled samples were stamped
            self._write(TOPIC_EVENTS, {**self._timing, "repeated": True}, self._wall_ns(now))
        if self._failing:
            self._write(TOPIC_EVENTS, self._log_gap(now), self._wall_ns(now))
        if self._held and self._file is not None:
            held = len(self._held)
            self._file.holds_held = True
            self._write_held()
            log.info("mcap log: wrote %d results and events held in memory during the outage", held)
        if self._file is not None:
            self._flush_file()  # proves the disk takes data again, and makes the head readable at once
        if self._file is None:
            return False
        if self._spool_pending and not self._held:  # what the spool held is in this file now
            self._spool_pending = not empty_spool(self.spool_path)
        if not self._spool_reserved:
            self._spool_reserved = reserve_spool(self.spool_path, self._spool_bytes())
        if self._failing:
            log.warning(
                "mcap log: writing again to %s after %.1f s; %d samples could not be logged",
                path.name, now - self._fail_since, self._fail_lost,
            )
            self._failing = False
            self._no_space = False
            self._backoff = self.retry_min_s
        log.info("mcap log: writing %s", path)
        self._retention(now)
        return True

    def _close_file(self) -> None:
        f = self._file
        assert f is not None
        self._write_pending()
        if self._file is None:
            return
        try:
            f.writer.finish()
            f.fh.flush()
            os.fsync(f.fh.fileno())
            size = f.fh.tell()
            f.fh.close()
        except OSError as err:
            self._failed(err, f.path)
            return
        except ValueError as err:  # a file object closed under us: treat as a write error
            self._failed(OSError(errno.EIO, str(err)), f.path)
            return
        self._c["bytes"] += size - f.bytes_counted
        self._file = None
        self._dirty_since = None

    def _flush_file(self) -> None:
        f = self._file
        if f is None:
            return
        self._write_pending()
        if self._file is None:
            return
        try:
            f.writer.flush()
            size = f.fh.tell()
        except OSError as err:
            self._failed(err, f.path)
            return
        self._c["bytes"] += size - f.bytes_counted
        f.bytes_counted = size
        if not f.overhead and size > f.header:
            f.overhead = size  # the first chunk holds the schemas (~70 kB before compression): not counted
        f.unflushed_samples = 0
        f.flushed_records += 1
        self._dirty_since = None
        if size - f.overhead >= self.rotate_bytes * (2 if self._in_test else 1):
            self._rotate("size", time.monotonic())

    def _write(self, topic: str, payload: Mapping[str, Any], log_time: int) -> None:
        """One message on ``topic``; an encoding problem drops the message, a write error the file."""
        f = self._file
        if f is None:
            self._hold_or_lose(topic, payload, log_time)
            return
        try:
            data = to_json(payload)
        except (TypeError, ValueError, RecursionError) as err:
            self._c["encode_errors"] += 1
            log.error("mcap log: cannot encode a message for %s (dropped): %s", topic, err)
            return
        ch = f.channels[topic]
        seq = f.seqs.get(ch, 0)
        f.seqs[ch] = seq + 1
        try:
            f.writer.add_message(ch, log_time=max(0, log_time), data=data, publish_time=time.time_ns(), sequence=seq)
        except OSError as err:
            self._failed(err, f.path)
            self._hold_or_lose(topic, payload, log_time)
            return
        self._c["messages"] += 1
        self._mark_dirty(time.monotonic())

    def _hold_or_lose(self, topic: str, payload: Mapping[str, Any], log_time: int) -> None:
        """A message no file can take now: results, events and the configuration wait in memory (bounded)
        for the next file; anything else (status, samples' side records) is counted lost."""
        if topic not in _HELD_TOPICS or self._stopped:
            self._c["messages_lost"] += 1
            return
        if topic == TOPIC_CONFIG:  # the next file starts with the configuration anyway
            return
        if len(self._held) >= HELD_MAX:
            self._held.popleft()
            self._c["messages_lost"] += 1
        self._held.append((topic, payload, log_time))
        self._c["messages_held"] += 1

    def _write_held(self) -> None:
        while self._held and self._file is not None:
            topic, payload, log_time = self._held.popleft()
            self._write(topic, payload, log_time)
            if self._file is not None:
                self._c["messages_held_written"] += 1

    def _spool_bytes(self) -> int:
        space = _disk_space(self.state_dir)
        return spool_size(space[1] if space is not None else None)

    def _spool_held(self) -> None:
        """At stop, results and events held through a write outage that no file could take: into the spool, with
        a ``log_gap`` event saying what the outage cost, for the next start to write (:func:`read_spool`)."""
        now = time.monotonic()
        held = list(self._held)
        self._held.clear()
        gap = []
        if self._failing:
            gap = [(TOPIC_EVENTS, self._log_gap(now), self._wall_ns(now))]
        kept = write_spool(self.spool_path, self.run_id, [*held, *gap], self._spool_bytes())  # the newest first
        lost = len(held) - max(0, kept - len(gap))
        self._c["messages_lost"] += lost
        if not held:
            log.debug("mcap log: the write outage %s in %s", "noted" if kept else "could not be noted", self.spool_path)
        elif lost < len(held):
            log.warning("mcap log: %d results and events held through a write outage are kept in %s; the next "
                        "start writes them%s", len(held) - lost, self.spool_path,
                        f" ({lost} of the oldest did not fit and are lost)" if lost else "")
        else:
            log.error("mcap log: %d results and events held through a write outage are lost (%s could not be "
                      "written either)", lost, self.spool_path)

    def _write_pending(self) -> None:
        if not self._pending.n:
            return
        batches = list(self._pending.batches)
        self._pending.clear()
        self._write_samples(batches, preroll=False)

    def _write_samples(self, batches: list[SampleBatch], preroll: bool) -> None:
        """Samples as ``ballbar.Samples`` messages: split where the source or the device clock's presence changes.

        On a write error the samples of this call not yet written are counted lost (preroll copies are not:
        the previous file has them).
        """
        total = sum(len(b) for b in batches)
        done = 0
        for source, b in _runs(batches):
            f = self._file
            if f is None:
                break
            th = b.t_host
            ok = np.isfinite(th)
            if not ok.all():
                bad = int((~ok).sum())
                log.warning("mcap log: %d samples without a host time dropped", bad)
                if not preroll:
                    self._c["samples_lost"] += bad
                done += bad
                b = _take(b, ok)
                th = b.t_host
                if not len(b):
                    continue
            L = b.length_mm
            finite = np.isfinite(L) & (np.abs(np.where(np.isfinite(L), L, 0.0)) < MAX_ABS_LENGTH_MM)
            missing = np.flatnonzero(~finite)
            if missing.size:  # placeholder: the previous finite value (0 before the first)
                idx = np.where(finite, np.arange(L.size), 0)
                np.maximum.accumulate(idx, out=idx)
                L = np.where(finite[idx], L[idx], 0.0)
            length_pm = scaled_ints(L, PM_PER_MM)
            t_host_ns = scaled_ints(th, NS) + self.host_clock_offset_ns
            td = b.t_device
            t_device_ns = scaled_ints(td, NS) if np.isfinite(td[0]) else None
            for i in range(0, len(b), MAX_BLOCK):
                j = min(i + MAX_BLOCK, len(b))
                m = missing[(missing >= i) & (missing < j)] - i
                msg = encode_samples(
                    t_host_ns[i:j], None if t_device_ns is None else t_device_ns[i:j], length_pm[i:j], m,
                    b.seq[i:j], b.status[i:j], source, preroll,
                )
                self._write(TOPIC_SAMPLES, msg, int(t_host_ns[i]))
                if self._file is None:
                    break
                done += j - i
                if not preroll:
                    f.samples += j - i
                    f.unflushed_samples += j - i
                    self._c["samples"] += j - i
                    if math.isnan(f.first_t):
                        f.first_t = float(th[i])
                    f.last_t = float(th[j - 1])
        if done < total and not preroll:
            self._lose(total - done)

    def _lose(self, n: int) -> None:
        self._c["samples_lost"] += n
        self._fail_lost += n

    def _lose_pending(self) -> None:
        self._lose(self._pending.n)
        self._pending.clear()

    def _failed(self, err: OSError, path: Path | None, *, delete: Path | None = None, now: float | None = None) -> None:
        """A write error: drop the file, count what it did not get, retry later."""
        now = time.monotonic() if now is None else now
        f = self._file
        unwritten = 0
        if f is not None:
            f.close_quietly()
            if f.flushed_records <= 1 and not f.holds_held:  # at most the head (metadata, config): nothing to keep
                delete = f.path
            elif f.unflushed_samples:  # a write cut short can have left whole chunks of them: those are not lost
                unwritten = f.unflushed_samples - min(
                    f.unflushed_samples, _samples_after(f.path, f.bytes_counted, f.channels[TOPIC_SAMPLES]))
            if delete == f.path:
                unwritten = f.unflushed_samples
        lost = self._pending.n + unwritten
        self._pending.clear()
        self._c["write_errors"] += 1
        self._c["samples"] -= unwritten
        detail = f"{err.strerror or err}" + (f" (errno {err.errno})" if err.errno else "")
        self._last_error = f"{path.name if path else self.directory}: {detail}"
        self._no_space = err.errno in _NO_SPACE
        self._next_probe = now + self.space_probe_s
        if not self._failing:
            self._failing = True
            self._fail_since = now
            self._fail_lost = 0
            self._fail_detail = detail
            when = (
                f"when {self.headroom() / 2**20:.2g} MiB are free (checked every {self.space_probe_s:g} s)"
                if self._no_space else f"in {self._backoff:.0f} s"
            )
            log.error(
                "mcap log: cannot write %s: %s; dropping the file and logging no samples until writes work "
                "again (retrying %s; results and events are held in memory)",
                path or self.directory, detail, when,
            )
        else:
            log.debug("mcap log: still cannot write %s: %s", path or self.directory, detail)
        self._lose(lost)
        self._file = None
        self._dirty_since = None
        if delete is not None:
            with contextlib.suppress(OSError):
                delete.unlink()
        self._retry_at = now + self._backoff
        self._backoff = min(self._backoff * 2.0, self.retry_max_s)

    # ------------------------------------------------------------------ retention

    def _retention(self, now: float) -> None:
        self._last_retention = now
        current = self._file.path if self._file is not None else None
        try:
            files = list_recordings(self.directory)
        except FileNotFoundError:
            return
        except OSError as err:
            log.warning("mcap log: cannot list %s for retention: %s", self.directory, err.strerror or err)
            return
        sizes: dict[Path, int] = {}
        mtimes: dict[Path, float] = {}
        for p in files:
            try:
                st = p.stat()
            except OSError:
                continue
            sizes[p], mtimes[p] = st.st_size, st.st_mtime
        total = sum(sizes.values())
        cutoff = time.time() - self.keep_days * 86400.0
        for p in sizes:
            if p == current:
                continue
            old = mtimes[p] < cutoff
            if not (old or total > self.quota_bytes):
                continue
            try:
                p.unlink()
            except FileNotFoundError:
                pass
            except OSError as err:
                log.warning("mcap log: cannot delete %s: %s", p.name, err.strerror or err)
                continue
            total -= sizes[p]
            self._c["deleted_files"] += 1
            self._c["deleted_bytes"] += sizes[p]
            log.info("mcap log: deleted %s (%s)", p.name, "older than keep_days" if old else "over quota")


def _samples_after(path: Path, offset: int, channel: int) -> int:
    """The samples (preroll copies aside) in the whole records of ``path`` from byte ``offset`` on: what a write
    that failed part way got into the file after all."""
    n = 0
    try:
        with open(path, "rb") as fh:
            fh.seek(offset)
            for rec in _records(fh, skip_magic=offset > 0):
                if isinstance(rec, Message) and rec.channel_id == channel:
                    msg = json.loads(rec.data)
                    n += 0 if msg.get("preroll") else int(msg["count"])
    except (OSError, McapError, struct.error, ValueError, KeyError, TypeError, EOFError, zstandard.ZstdError):
        pass  # the first record cut short: the end of what is readable
    return n


def _group_by_period(batches: Sequence[SampleBatch], period_s: float) -> list[list[SampleBatch]]:
    """Consecutive non-empty batches in groups that start at most ``period_s`` (host time) apart: a group takes
    every batch whose first sample is less than ``period_s`` after the group's first sample."""
    groups: list[list[SampleBatch]] = []
    start = math.nan
    for b in batches:
        if not len(b):
            continue
        t0 = float(b.t_host[0])
        if groups and t0 - start < period_s:
            groups[-1].append(b)
        else:
            groups.append([b])
            start = t0
    return groups


def _runs(batches: Sequence[SampleBatch]) -> Iterator[tuple[str, SampleBatch]]:
    """Consecutive samples with one source and one device-clock presence, as single batches."""
    parts: list[tuple[str, bool, SampleBatch]] = []
    for b in batches:
        if not len(b):
            continue
        has = np.isfinite(b.t_device)
        cuts = np.flatnonzero(np.diff(has.astype(np.int8))) + 1
        for piece in np.split(np.arange(len(b)), cuts):
            sub = b if piece.size == len(b) else _take(b, piece)
            key = bool(has[piece[0]])
            if parts and parts[-1][0] == b.source and parts[-1][1] == key:
                prev = parts[-1][2]
                parts[-1] = (b.source, key, SampleBatch.concat([prev, sub]))
            else:
                parts.append((b.source, key, sub))
    for source, _key, b in parts:
        yield source, b


def _take(b: SampleBatch, index: Any) -> SampleBatch:
    return SampleBatch(
        b.t_host[index], b.t_device[index], b.length_mm[index], b.seq[index], b.status[index], (), b.source
    )


def list_recordings(directory: str | os.PathLike[str]) -> list[Path]:
    """The logger's files in ``directory``, oldest first (by the UTC time and number in their names)."""
    d = Path(directory)
    found = []
    for p in d.iterdir():
        m = _NAME_RE.match(p.name)
        if m and p.is_file():
            found.append((m["ts"], int(m["seq"]), p.name, p))
    return [p for *_k, p in sorted(found)]


def mcap_files(directory: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a directory to read as one recording: the logger's, oldest first, else any ``*.mcap``
    in name order (files renamed or copied by hand)."""
    return list_recordings(directory) or sorted(Path(directory).glob("*.mcap"))


# ----------------------------------------------------------------------------- reading


@dataclass
class McapLog:
    """What a log file (or several) holds.

    ``samples``: every sample in file order (valid or not), ``t_host`` on the
    writer's monotonic clock in seconds (wall time minus the file's
    ``host_clock_offset_ns``).  ``t_wall_ns``: the same instants on the wall
    clock.  ``preroll``: samples repeated at the head of a per-test file.
    ``complete``: every file ended with its footer; ``problem``: why reading
    stopped early ("" if it did not).  ``file_starts``: where each file's
    samples begin in ``samples``, and ``file_events``: which file each event
    came from (index into ``paths``).
    """

    paths: list[str]
    samples: SampleBatch
    t_wall_ns: NDArray[np.int64]
    preroll: NDArray[np.bool_]
    events: list[dict[str, Any]] = field(default_factory=list)
    results: list[dict[str, Any]] = field(default_factory=list)
    status: list[dict[str, Any]] = field(default_factory=list)
    config: list[dict[str, Any]] = field(default_factory=list)
    other: list[dict[str, Any]] = field(default_factory=list)
    metadata: dict[str, str] = field(default_factory=dict)
    complete: bool = True
    problem: str = ""
    file_starts: list[int] = field(default_factory=lambda: [0])
    file_events: list[int] = field(default_factory=list)

    def time_axis(self) -> tuple[NDArray[np.float64], str]:
        """The analysis time axis of the valid samples: ``(t_s, "device" | "host")``.

        The device clock where every valid sample has one and it runs forward
        (it is evenly spaced and free of host latency); else the host's
        monotonic clock, the time the live pipeline used for such a source.
        """
        valid = self.samples.valid
        td = self.samples.t_device[valid]
        if td.size and np.isfinite(td).all() and bool(np.all(np.diff(td) > 0)):
            return td, "device"
        return self.samples.t_host[valid], "host"


_TOPIC_LISTS = {TOPIC_EVENTS: "events", TOPIC_RESULTS: "results", TOPIC_STATUS: "status",
                TOPIC_CONFIG: "config", TOPIC_OTHER: "other"}


def _read_one(path: str, samples: bool = True, status: bool = True) -> McapLog:
    name = path
    with open_recording(name) as fh:
        try:
            head = fh.read(len(_MAGIC))
            if head != _MAGIC:
                what = "empty file" if not head else "not an MCAP file (no MCAP magic at the start)"
                raise DataError(f"{name}: {what}")
            fh.seek(0)
            if not samples and (indexed := _records_indexed(name, fh)) is not None:
                return indexed
            fh.seek(0)
            return _parse(name, fh, samples, status)
        except OSError as err:  # a read error (EIO), or a file that cannot seek
            raise DataError(f"{name}: cannot read: {err.strerror or err}") from None


class _BoundedReads:
    """A binary file whose reads are refused beyond :data:`MAX_RECORD_BYTES`: the mcap library reads a record's
    fields by the lengths the file states, so a corrupt length would read gigabytes into memory."""

    def __init__(self, fh: IO[bytes]) -> None:
        self._fh = fh

    def read(self, n: int = -1) -> bytes:
        if n < 0 or n > MAX_RECORD_BYTES:
            raise McapError(f"a record field of {n} bytes, more than any the logger writes ({MAX_RECORD_BYTES})")
        return self._fh.read(n)

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        return self._fh.seek(offset, whence)

    def tell(self) -> int:
        return self._fh.tell()

    def seekable(self) -> bool:
        return True


def _records(fh: IO[bytes], skip_magic: bool = False) -> Iterator[Any]:
    """The records of an MCAP file from its start (or, ``skip_magic``, from where ``fh`` is), chunks broken up,
    none larger than :data:`MAX_RECORD_BYTES` (an McapError where one is)."""
    reader = StreamReader(_BoundedReads(fh), skip_magic=skip_magic, emit_chunks=True,  # type: ignore[arg-type]
                          record_size_limit=MAX_RECORD_BYTES)
    for rec in reader.records:
        if isinstance(rec, Chunk):
            _check_chunk(rec.uncompressed_size, rec.compression, rec.data)
            yield from breakup_chunk(rec)
        else:
            yield rec


def _check_chunk(size: int, compression: str, data: bytes | None = None) -> None:
    """A chunk whose records, uncompressed, would be larger than :data:`MAX_RECORD_BYTES` is refused before it is
    decompressed (the zstd frame states its own size, which a corrupt file can set to anything)."""
    claimed = zstandard.frame_content_size(data) if data and compression == "zstd" else -1
    if max(size, claimed) > MAX_RECORD_BYTES:
        raise McapError(f"a chunk of {max(size, claimed)} bytes, more than any the logger writes ({MAX_RECORD_BYTES})")


def _records_indexed(name: str, fh: IO[bytes]) -> McapLog | None:
    """The events, results and configuration of a finished file, from the chunks its summary says hold them.

    A file flushes a chunk every half second, and only a few hold anything but
    samples and status: this skips the rest (about 3.5 times faster than
    reading every chunk).  None when the file has no usable summary (a killed
    writer's): then it is read through.
    """
    wanted = {TOPIC_EVENTS: "events", TOPIC_RESULTS: "results", TOPIC_CONFIG: "config", TOPIC_OTHER: "other"}
    try:
        if os.fstat(fh.fileno()).st_size < 2 * len(_MAGIC) + 1 + 8:
            return None  # no room for a footer: a cut file
        reader = make_reader(_BoundedReads(fh))  # type: ignore[arg-type]
        summary = reader.get_summary()
        if summary is None or not summary.chunk_indexes:
            return None
        if any(max(ci.uncompressed_size, ci.chunk_length) > MAX_RECORD_BYTES for ci in summary.chunk_indexes):
            return None  # not the logger's: read through, up to such a chunk
        lists: dict[str, list[dict[str, Any]]] = {k: [] for k in wanted.values()}
        kept = 0
        for _schema, channel, msg in reader.iter_messages(topics=list(wanted), log_time_order=False):
            kept += len(msg.data)
            if kept > SIDE_BYTES_MAX:
                return None  # reading it through keeps what fits, and says so
            try:
                obj = json.loads(msg.data)
            except (ValueError, RecursionError):  # deeply nested JSON: one bad record costs only itself
                continue
            if isinstance(obj, dict):
                lists[wanted[channel.topic]].append(obj)
        meta = next((dict(m.metadata) for m in reader.iter_metadata() if m.name == METADATA_NAME), {})
    except (McapError, struct.error, ValueError, EOFError, KeyError, MemoryError, zstandard.ZstdError,
            OSError) as err:
        log.debug("%s: no usable summary (%s); reading it through", name, err)
        return None
    if meta and not meta.get("format", "").startswith("ballbar-mcap/1"):
        raise DataError(f"{name}: format {meta.get('format')!r} is not one this version reads (ballbar-mcap/1)")
    out = McapLog([name], SampleBatch.empty(), np.empty(0, np.int64), np.empty(0, bool), metadata=meta)
    for k, v in lists.items():
        setattr(out, k, v)
    out.file_events = [0] * len(out.events)
    return out


def _parse(name: str, fh: IO[bytes], samples: bool = True, status: bool = True) -> McapLog:
    channels: dict[int, str] = {}
    lists: dict[str, list[dict[str, Any]]] = {k: [] for k in _TOPIC_LISTS.values()}
    meta: dict[str, str] = {}
    decoded: list[DecodedSamples] = []
    complete = False
    problem = ""
    n_msg = 0
    skipped_blocks = 0  # sample records not decoded (samples=False)
    side = 0  # bytes of JSON kept in ``lists``
    try:
        for rec in _records(fh):
            if isinstance(rec, Channel):
                channels[rec.id] = rec.topic
            elif isinstance(rec, Metadata) and rec.name == METADATA_NAME:
                meta = dict(rec.metadata)
            elif isinstance(rec, Message):
                n_msg += 1
                topic = channels.get(rec.channel_id)
                if topic is None:
                    raise DataError(f"{name}: message {n_msg} is on channel {rec.channel_id}, never declared")
                if topic == TOPIC_SAMPLES:
                    if not samples:
                        skipped_blocks += 1
                        continue
                    try:
                        decoded.append(decode_samples(json.loads(rec.data)))
                    except (ValueError, KeyError, TypeError, OverflowError, RecursionError) as err:
                        raise DataError(
                            f"{name}: message {n_msg} on {TOPIC_SAMPLES} is not a ballbar.Samples record: {err}"
                        ) from None
                elif topic in _TOPIC_LISTS and (status or topic != TOPIC_STATUS):
                    side += len(rec.data)
                    if side > SIDE_BYTES_MAX:
                        if side - len(rec.data) <= SIDE_BYTES_MAX:
                            log.warning("%s: more than %d MiB of events, results and status: the rest left out",
                                        name, SIDE_BYTES_MAX >> 20)
                        continue
                    try:
                        obj = json.loads(rec.data)
                    except (ValueError, RecursionError):  # deeply nested JSON: RecursionError
                        continue  # a bad side record does not hide the samples
                    if isinstance(obj, dict):
                        lists[_TOPIC_LISTS[topic]].append(obj)
            elif isinstance(rec, Footer):
                complete = True
            elif isinstance(rec, Schema | Chunk):
                pass
    except (McapError, struct.error, ValueError, EOFError, MemoryError, zstandard.ZstdError) as err:
        # A killed writer leaves a partial record: a short read, a torn zstd frame, a bad length.
        detail = _why_stopped(err)
        what = f"{sum(d.seq.size for d in decoded)} samples" if samples else f"{skipped_blocks} sample records"
        problem = f"ends early after {what} ({detail})"
    if meta and not meta.get("format", "").startswith("ballbar-mcap/1"):
        raise DataError(f"{name}: format {meta.get('format')!r} is not one this version reads (ballbar-mcap/1)")
    try:
        offset = int(meta.get("host_clock_offset_ns", "0") or 0)
    except ValueError:
        raise DataError(f"{name}: its metadata's host_clock_offset_ns is not a whole number") from None
    log_ = _assemble([name], decoded, offset)
    log_.metadata = meta
    log_.complete = complete
    log_.problem = problem
    for k, v in lists.items():
        setattr(log_, k, v)
    log_.file_events = [0] * len(log_.events)
    return log_


def _why_stopped(err: BaseException) -> str:
    """Why reading a file's records stopped, in words."""
    if isinstance(err, struct.error | EOFError | EndOfFile):
        return "a record cut short"
    return f"{type(err).__name__}: {err}" if str(err) else type(err).__name__


def _assemble(paths: list[str], decoded: list[DecodedSamples], offset_ns: int) -> McapLog:
    if not decoded:
        empty = SampleBatch.empty()
        return McapLog(paths, empty, np.empty(0, np.int64), np.empty(0, bool))
    wall = np.concatenate([d.t_host_ns for d in decoded])
    t_host = (wall - offset_ns) / 1e9
    t_dev = np.concatenate([
        d.t_device_ns / 1e9 if d.t_device_ns is not None else np.full(d.seq.size, np.nan) for d in decoded
    ])
    length = np.concatenate([d.length_pm / 1e9 for d in decoded])
    base = 0
    for d in decoded:
        if d.missing.size:
            length[base + d.missing] = np.nan
        base += d.seq.size
    batch = SampleBatch.from_columns(
        t_host, t_dev, length,
        np.concatenate([d.seq for d in decoded]),
        np.concatenate([d.status for d in decoded]),
        source=decoded[0].source,
    )
    pre = np.concatenate([np.full(d.seq.size, d.preroll) for d in decoded])
    return McapLog(paths, batch, wall, pre)


def read_log(path: str | os.PathLike[str], samples: bool = True, status: bool = True) -> McapLog:
    """Everything in one log file; a truncated file (killed writer) is read up to its last whole chunk.

    ``samples=False`` leaves the samples and the status messages out (an empty
    batch, no status): reading only the events, results and configuration is
    then many times faster, the more so for a finished file, whose summary
    says which chunks hold them.  ``status=False`` leaves the status messages
    out (the analysis needs none).

    Memory: the samples, and at most :data:`SIDE_BYTES_MAX` of the other
    records' JSON; a record or chunk larger than :data:`MAX_RECORD_BYTES` ends
    the reading as a cut file's end does.

    Raises :class:`DataError` (one line, naming the file) when the file is
    missing, unreadable, not MCAP, or holds a malformed samples record.
    """
    out = _read_one(os.fspath(path), samples, status)
    if out.problem:
        log.warning("%s: %s; the writer was probably killed", os.fspath(path), out.problem)
    return out


def read_results(paths: Iterable[str | os.PathLike[str]]) -> list[dict[str, Any]]:
    """The results recorded in these files, in order, without reading their samples.

    A file that cannot be read is skipped with a warning: one bad file does not
    hide the others' history.
    """
    out: list[dict[str, Any]] = []
    for path in paths:
        try:
            out.extend(read_log(path, samples=False).results)
        except (BallbarError, OSError, RecursionError, MemoryError) as err:  # one bad file costs only itself
            log.warning("results: %s: %s", os.fspath(path), err)
    return out


def read_logs(
    paths: Iterable[str | os.PathLike[str]], skip_bad: bool = False, status: bool = True
) -> McapLog:
    """Several files in the given order, joined; preroll samples already in the file before are dropped.

    ``skip_bad``: a file that cannot be read is left out with a warning naming it (one bad file in a directory
    costs only itself); a DataError only when none can be read.
    """
    names = list(paths)
    parts: list[McapLog] = []
    errors: list[str] = []
    for path in names:
        try:
            parts.append(read_log(path, status=status))
        except DataError as err:
            if not skip_bad:
                raise
            errors.append(str(err))
            log.warning("%s; left out, the other files read", err)
    if not parts:
        raise DataError(errors[0] if len(errors) == 1 else
                        f"none of the {len(names)} MCAP files could be read (the first: {errors[0]})" if errors else
                        "no MCAP files given")
    keep_batches: list[SampleBatch] = []
    walls: list[NDArray[np.int64]] = []
    pres: list[NDArray[np.bool_]] = []
    starts: list[int] = []
    last_wall: int | None = None
    for p in parts:
        starts.append(sum(len(b) for b in keep_batches))
        s, wall, pre = p.samples, p.t_wall_ns, p.preroll
        if last_wall is not None and pre.any():
            keep = ~(pre & (wall <= last_wall))
            s, wall, pre = _take(s, keep), wall[keep], pre[keep]
        if wall.size:
            last_wall = int(wall.max()) if last_wall is None else max(last_wall, int(wall.max()))
        keep_batches.append(s)
        walls.append(wall)
        pres.append(pre)
    out = McapLog(
        [q for p in parts for q in p.paths],
        SampleBatch.concat(keep_batches),
        np.concatenate(walls),
        np.concatenate(pres),
        complete=all(p.complete for p in parts),
        problem="; ".join(f"{p.paths[0]}: {p.problem}" for p in parts if p.problem),
        metadata=parts[0].metadata,
        file_starts=starts,
        file_events=[i for i, p in enumerate(parts) for _e in p.events],
    )
    for k in _TOPIC_LISTS.values():
        setattr(out, k, [x for p in parts for x in getattr(p, k)])
    return out


def read_mcap(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(t_s, length_mm)`` of the valid samples of a log file, or of a directory of them joined.

    ``t_s``: :meth:`McapLog.time_axis` (device clock where present, else host
    monotonic clock), seconds.  Samples with OVER_RANGE or SENSOR_FAULT are left out.
    """
    name = os.fspath(path)
    if os.path.isdir(name):
        files = mcap_files(name)
        if not files:
            raise DataError(f"{name}: a directory without .mcap files")
        lg = read_logs(files, skip_bad=True, status=False)
    else:
        lg = read_log(name, status=False)
    return valid_samples(lg, name)


def valid_samples(lg: McapLog, name: str) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(t_s, length_mm)`` of the valid samples of ``lg`` (see :func:`read_mcap`); ``name`` for messages."""
    rec = recording(lg, name)
    return rec.t, rec.L


def recording(lg: McapLog, name: str) -> Recording:
    """The analysis's input from a log: the valid samples on :meth:`McapLog.time_axis`, and the breaks.

    Breaks (:func:`~ballbar.daemon.samples.break_reason`): a ``device_reset``
    or ``clock_jump`` before the sample it names (files written before events
    named one: the first sample stamped after the event), ``GAP_PERIODS`` or
    more samples ``lost``, and a ``log_gap`` (samples the logger could not
    write) before the first sample of the file it heads.
    """
    n = len(lg.samples)
    if n == 0:
        why = f" ({lg.problem})" if lg.problem else ""
        raise DataError(f"{name}: no samples on {TOPIC_SAMPLES}{why}")
    valid = lg.samples.valid
    nv = int(valid.sum())
    if nv == 0:
        raise DataError(f"{name}: all {n} samples are flagged over range or sensor fault")
    t, axis = lg.time_axis()
    L = lg.samples.length_mm[valid]
    index = np.flatnonzero(valid)
    bad = ~np.isfinite(L)
    if bad.any():  # a NaN without a fault flag: not a measurement either
        log.warning("%s: %d samples without a length (and no fault flag) left out", name, int(bad.sum()))
        t, L, index = t[~bad], L[~bad], index[~bad]
        if not L.size:
            raise DataError(f"{name}: no sample has a length")
    if nv < n:
        log.info("%s: %d of %d samples flagged invalid (%s) and left out", name, n - nv, n, INVALID)
    seq, t_host = lg.samples.seq[index], lg.samples.t_host[index]
    breaks: list[tuple[int, str]] = []
    for ev, f in zip(lg.events, lg.file_events or [0] * len(lg.events), strict=False):
        reason = break_reason(ev)
        if reason is None:
            continue
        if ev.get("event") == "log_gap":
            start = lg.file_starts[f] if f < len(lg.file_starts) else 0
            own = np.flatnonzero(~lg.preroll[start:]) + start  # the file's own samples, after its preroll
            at = int(np.searchsorted(index, own[0])) if own.size else len(index)
        elif (s := break_seq(ev)) is not None:
            at = int(np.searchsorted(seq, s))
        elif isinstance(ev.get("t_host"), int | float):
            at = int(np.searchsorted(t_host, float(ev["t_host"]), side="right"))
        else:
            continue
        breaks.append((at, reason))
    from ballbar.analysis.polled import from_events

    return Recording(np.ascontiguousarray(t, dtype=np.float64), np.ascontiguousarray(L, dtype=np.float64),
                     sorted(breaks), axis, name, from_events(lg.events))


# ----------------------------------------------------------------------------- after a crash


@dataclass
class Recovered:
    """A crashed file rewritten with its index and summary (see :func:`recover_crashed`)."""

    path: Path
    messages: int
    cut_test: dict[str, Any] | None  # the feed_in event of a test the crash cut (no result, no verdict)
    problem: str
    outage: str = ""  # the write error that made the logger drop the file ("": the daemon was killed)
    outcome: bool = False  # the cut test's result (or rejection) is recorded after all: in a later file, the spool


def _has_footer(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            fh.seek(0, os.SEEK_END)
            if fh.tell() < 2 * len(_MAGIC):
                return False
            fh.seek(-len(_MAGIC), os.SEEK_END)
            return fh.read(len(_MAGIC)) == _MAGIC
    except OSError:
        return True  # cannot tell: leave it alone


def recover_file(path: Path) -> Recovered:
    """Rewrite a file whose writer was killed, as ``mcap recover`` does: every whole record, then a footer,
    indexes and summary.  The original stays until the rewrite is complete (an atomic rename replaces it)."""
    tmp = path.with_name(path.name + ".recovering")
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    topics: dict[int, str] = {}
    n = 0
    problem = ""
    feed_in: dict[str, Any] | None = None
    with open(path, "rb") as src, open(tmp, "wb") as dst:
        w = Writer(dst, compression=CompressionType.ZSTD)
        w.start(profile="", library=f"ballbar {__version__} (recovered)")
        try:
            for rec in _records(src):
                if isinstance(rec, Schema):
                    schemas[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    channels[rec.id] = w.register_channel(
                        rec.topic, rec.message_encoding, schemas.get(rec.schema_id, 0), dict(rec.metadata)
                    )
                    topics[rec.id] = rec.topic
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))
                elif isinstance(rec, Message) and rec.channel_id in channels:
                    w.add_message(channels[rec.channel_id], log_time=rec.log_time, data=rec.data,
                                  publish_time=rec.publish_time, sequence=rec.sequence)
                    n += 1
                    topic = topics[rec.channel_id]
                    if topic in (TOPIC_EVENTS, TOPIC_RESULTS):
                        with contextlib.suppress(ValueError, RecursionError):
                            obj = json.loads(rec.data)
                            if isinstance(obj, dict):
                                if obj.get("event") == "feed_in":
                                    feed_in = obj
                                elif obj.get("kind") == "test" or obj.get("event") in TEST_END_EVENTS:
                                    feed_in = None
        except (McapError, struct.error, ValueError, EOFError, MemoryError, zstandard.ZstdError) as err:
            problem = _why_stopped(err)
        w.finish()
        dst.flush()
        os.fsync(dst.fileno())
    os.replace(tmp, path)
    return Recovered(path, n, feed_in, problem)


def recover_crashed(directory: str | os.PathLike[str]) -> list[Recovered]:
    """Each of the logger's files in ``directory`` left without a footer by a killed daemon, rewritten once
    with its index (so every reader opens it, and no later start warns about it again).  A file that
    cannot be rewritten is left as it was, with a warning."""
    out: list[Recovered] = []
    d = Path(directory)
    if not d.is_dir():
        return out
    for stale in d.glob("*.mcap.recovering"):  # a rewrite that was itself cut: the original is intact
        with contextlib.suppress(OSError):
            stale.unlink()
    for path in list_recordings(d):
        if _has_footer(path):
            continue
        try:
            r = recover_file(path)
        except (OSError, McapError) as err:
            log.warning("mcap log: cannot recover %s (left as it is): %s", path.name, err)
            with contextlib.suppress(OSError):
                path.with_name(path.name + ".recovering").unlink()
            continue
        _cut_by(r, d)
        what = f"a write outage ({r.outage})" if r.outage else "a crash"
        test = ""
        if r.cut_test:
            test = f" (the test {r.cut_test.get('test_id')} was cut{'; its result is recorded' if r.outcome else ''})"
        log.warning("mcap log: %s was cut by %s; rewrote its %d whole records with an index%s",
                    path.name, what, r.messages, test)
        out.append(r)
    return out


def _cut_by(r: Recovered, directory: Path) -> None:
    """Whether the logger dropped ``r``'s file after a write error (the next file of its run begins with a
    ``log_gap``, or the run's spool holds one), and whether its cut test's outcome is recorded after all."""
    try:
        run_id = read_log(r.path, samples=False).metadata.get("run_id", "")
    except BallbarError:
        return
    if not run_id:
        return
    test_id = r.cut_test.get("test_id") if r.cut_test else None
    later: list[dict[str, Any]] = []
    files = list_recordings(directory)
    for p in files[files.index(r.path) + 1 :] if r.path in files else []:
        try:
            lg = read_log(p, samples=False)
        except BallbarError:
            continue
        if lg.metadata.get("run_id") != run_id:
            continue
        later += [*lg.events, *lg.results]
    spool = read_spool(directory.parent)
    if spool.run_id == run_id:
        later += [payload for _topic, payload, _t in spool.entries]
    gaps = [e for e in later if e.get("event") == "log_gap"]
    if gaps:
        r.outage = str(gaps[0].get("detail", "")) or "a write error"
    r.outcome = test_id is not None and any(
        m.get("test_id") == test_id and (m.get("kind") == "test" or m.get("event") in TEST_END_EVENTS) for m in later
    )


__all__ = [
    "FORMAT",
    "SCHEMAS",
    "TOPIC_CONFIG",
    "TOPIC_EVENTS",
    "TOPIC_OTHER",
    "TOPIC_RESULTS",
    "TOPIC_SAMPLES",
    "TOPIC_STATUS",
    "DecodedSamples",
    "LogConfigError",
    "McapLog",
    "McapLogger",
    "decode_samples",
    "encode_samples",
    "list_recordings",
    "mcap_files",
    "read_log",
    "read_logs",
    "read_mcap",
    "read_results",
    "read_spool",
    "recording",
    "recover_crashed",
    "scaled_ints",
    "to_json",
    "valid_samples",
]
