"""The MCAP logger: the listener that writes every sample, event and result; its flush thread, rotation, retention,
and what it does when writing fails (the package's docstring)."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import math
import os
import re
import threading
import time
import uuid
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
from mcap.writer import CompressionType, Writer

from ballbar import __version__
from ballbar.protocol.messages.envelope import utc_text

from ..listeners import MERGE_S, TEST_END_EVENTS, Listener, to_json
from ..listeners import Message as ListenerMessage
from ..samples import SampleBatch, SourceEvent
from ..spool import SPOOL_NAME, empty_spool, read_spool, reserve_spool, spool_size, write_spool
from .format import (
    _NAME_RE,
    FLUSHER_MAX_WAIT_S,
    FORMAT,
    MAX_ABS_LENGTH_MM,
    MAX_BLOCK,
    METADATA_NAME,
    NS,
    PM_PER_MM,
    RECORDINGS,
    RETENTION_EVERY_S,
    SCHEMAS,
    TOPIC_CONFIG,
    TOPIC_CONTROLLER,
    TOPIC_EVENTS,
    TOPIC_OTHER,
    TOPIC_RESULTS,
    TOPIC_SAMPLES,
    TOPIC_STATUS,
    LogConfigError,
    _group_by_period,
    _runs,
    _take,
    controller_state,
    encode_samples,
    hold_file,
    list_recordings,
    scaled_ints,
)
from .reader import _samples_after

if TYPE_CHECKING:
    from ballbar.protocol.messages.events import LogGap

log = logging.getLogger(__name__)

def _open_output(path: Path) -> IO[bytes]:
    """A new file for writing; refuses to overwrite.  (Tests replace this to simulate a full disk.)

    The file is held with an exclusive ``flock`` while it is open (the lock goes with the descriptor, at its close
    or the process's end): recovery and retention in any other process leave a file so held alone."""
    fh = open(path, "xb")  # noqa: SIM115 - the caller keeps it open
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        raise
    return fh


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
    last_ns: int | None = None  # the newest sample's stored host time (wall ns), written to it (maybe not flushed)
    last_td: float = math.nan  # and its device time (s; NaN: none)
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
        # The controller's last value of each node ([controller]), repeated at each file's head: a test's file then
        # says which program ran (the server sends only changes)
        self._controller: tuple[dict[str, Any], dict[str, Any]] | None = None  # (last message, values by name)
        self._seen_events: dict[tuple[str, float, str], None] = {}  # recent events, oldest first
        self._in_test = False
        self._stopped = False
        self._file_seq = 0
        self._last_retention = time.monotonic()  # first run when the first file opens
        # The stored host time (wall ns) of the newest sample known to be in a file: after a write outage, what the
        # preroll ring holds beyond it was counted lost, and is written when writing resumes.
        self._kept_ns: int | None = None
        self._kept_td = math.nan  # that sample's device time (s)
        # The newest sample counted lost in a write outage (host s, device s): where its lost span ends, when the
        # preroll ring gives none of them back.
        self._lost_last: tuple[float, float] | None = None
        self._held_elsewhere: set[Path] = set()  # files retention left alone, another process writing them (said once)
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
            ok = self._ensure_file(now)  # (a file opened now after an outage takes the ring's lost samples first)
            if n:
                self._remember(batch)
            if not ok:
                self._lose(n)
                if n:
                    self._note_lost(batch)
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
                "config": TOPIC_CONFIG, "controller": TOPIC_CONTROLLER,
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
            elif kind == "controller":
                self._controller = controller_state(self._controller, msg)
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

    def _log_gap(self, now: float, resumed: SampleBatch | None = None, span: bool = True) -> LogGap:
        """The ``log_gap`` event of the write outage going on: what it cost so far, and (``span``, samples lost)
        their span: from the newest sample in a file before it to ``resumed``'s first (the first written after
        it), else to the newest lost."""
        gap: LogGap = {"event": "log_gap", "t_host": now, "count": self._fail_lost,
                       "gap_s": round(now - self._fail_since, 3), "detail": self._fail_detail}
        if not (self._fail_lost and span):
            return gap
        first = (math.nan, math.nan) if self._kept_ns is None else (
            (self._kept_ns - self.host_clock_offset_ns) / NS, self._kept_td)
        end = (float(resumed.t_host[0]), float(resumed.t_device[0])) if resumed is not None and len(resumed) else (
            self._lost_last or (math.nan, math.nan))
        gap["lost_t_host"] = [_or_none(first[0]), _or_none(end[0])]
        gap["lost_t_device"] = [_or_none(first[1]), _or_none(end[1])]
        gap["lost_utc"] = [None if not math.isfinite(t) else
                           utc_text(datetime.fromtimestamp((t * NS + self.host_clock_offset_ns) / NS, UTC))
                           for t in (first[0], end[0])]
        return gap

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

    def _rescue(self) -> list[SampleBatch]:
        """The samples of a write outage that the preroll ring still holds (those after the newest sample known to
        be in a file), taken off the outage's lost count: the file that resumes writing takes them first, so that a
        test whose feed-in the outage covered is in it from its feed-in (when the ring reaches back that far)."""
        out: list[SampleBatch] = []
        n = 0
        for b in self._ring:
            stored = scaled_ints(b.t_host, NS) + self.host_clock_offset_ns
            keep = np.isfinite(b.t_host) if self._kept_ns is None else stored > self._kept_ns
            if keep.any():
                part = b if keep.all() else _take(b, keep)
                out.append(part)
                n += len(part)
        if n > self._fail_lost:  # never more than was counted lost (the newest are the ones to keep)
            extra = n - self._fail_lost
            while out and extra >= len(out[0]):
                extra -= len(out[0])
                n -= len(out[0])
                out.pop(0)
            if out and extra:
                out[0] = _take(out[0], slice(extra, None))
                n -= extra
        self._fail_lost -= n
        self._c["samples_lost"] -= n
        return out

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
        if self._controller is not None and self._controller[1]:
            last, values = self._controller
            self._write(TOPIC_CONTROLLER, {**last, "state": "data", "values": list(values.values()), "repeated": True},
                        self._wall_ns(now))
        rescued: list[SampleBatch] = []
        if self._failing:
            rescued = self._rescue()
            self._write(TOPIC_EVENTS, self._log_gap(now, rescued[0] if rescued else None), self._wall_ns(now))
            self._lost_last = None
        if self._held and self._file is not None:
            held = len(self._held)
            self._file.holds_held = True
            self._write_held()
            log.info("mcap log: wrote %d results and events held in memory during the outage", held)
        if rescued and self._file is not None:
            n = sum(len(b) for b in rescued)
            for group in _group_by_period(rescued, self.flush_s):
                self._write_samples(group, preroll=False)
            if self._file is not None:
                log.info("mcap log: wrote the last %d samples of the outage, which the preroll buffer still held", n)
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
        if f.last_ns is not None:
            self._kept_ns, self._kept_td = f.last_ns, f.last_td
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
        if f.last_ns is not None:
            self._kept_ns, self._kept_td = f.last_ns, f.last_td
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
            # (no span: the next run's files hold it, and that run's clocks are not this one's)
            gap = [(TOPIC_EVENTS, self._log_gap(now, span=False), self._wall_ns(now))]
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
                    f.last_ns = int(t_host_ns[j - 1])
                    f.last_td = float(td[j - 1])
        if done < total and not preroll:
            self._lose(total - done)

    def _note_lost(self, batch: SampleBatch) -> None:
        if len(batch):
            self._lost_last = (float(batch.t_host[-1]), float(batch.t_device[-1]))

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
            if f.flushed_records <= 1 and not f.holds_held and f.samples == f.unflushed_samples:
                delete = f.path  # at most the head (metadata, config): nothing to keep
            elif f.unflushed_samples:  # a write cut short can have left whole chunks of them: those are not lost
                made, last_ns, last_td = _samples_after(f.path, f.bytes_counted, f.channels[TOPIC_SAMPLES])
                unwritten = f.unflushed_samples - min(f.unflushed_samples, made)
                if made and last_ns is not None:
                    self._kept_ns, self._kept_td = last_ns, last_td
            if delete == f.path:
                unwritten = f.unflushed_samples
        lost = self._pending.n + unwritten
        if self._pending.batches:
            self._note_lost(self._pending.batches[-1])
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
                fd = hold_file(p)
                if fd is None:  # another process writes it (a daemon on this directory without its lock)
                    if p not in self._held_elsewhere:
                        self._held_elsewhere.add(p)
                        log.warning("mcap log: %s is open in another process: retention leaves it alone", p.name)
                    continue
                try:
                    p.unlink()
                finally:
                    os.close(fd)
            except FileNotFoundError:
                pass
            except OSError as err:
                log.warning("mcap log: cannot delete %s: %s", p.name, err.strerror or err)
                continue
            total -= sizes[p]
            self._c["deleted_files"] += 1
            self._c["deleted_bytes"] += sizes[p]
            log.info("mcap log: deleted %s (%s)", p.name, "older than keep_days" if old else "over quota")


def _or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None
