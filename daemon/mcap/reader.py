"""Reading the recordings back, from any file: a cut one up to its last whole record, a bad one as one error line."""

from __future__ import annotations

import json
import logging
import math
import os
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
import zstandard
from mcap.exceptions import EndOfFile, McapError
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Footer, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from numpy.typing import NDArray

from ballbar.analysis.errors import BallbarError, DataError
from ballbar.protocol import INVALID

from ..csvfile import open_recording
from ..samples import Recording, SampleBatch, break_reason, break_seq
from .format import (
    _MAGIC,
    MAX_RECORD_BYTES,
    METADATA_NAME,
    NS,
    SIDE_BYTES_MAX,
    TOPIC_CONFIG,
    TOPIC_EVENTS,
    TOPIC_OTHER,
    TOPIC_RESULTS,
    TOPIC_SAMPLES,
    TOPIC_STATUS,
    DecodedSamples,
    _take,
    decode_samples,
    mcap_files,
)

log = logging.getLogger(__name__)

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


def _samples_after(path: Path, offset: int, channel: int) -> tuple[int, int | None, float]:
    """The samples (preroll copies aside) in the whole records of ``path`` from byte ``offset`` on, and the stored
    host time (wall ns) and device time (s, NaN: none) of the newest of them: what a write that failed part way got
    into the file after all."""
    n = 0
    last: int | None = None
    last_td = math.nan
    try:
        with open(path, "rb") as fh:
            fh.seek(offset)
            for rec in _records(fh, skip_magic=offset > 0):
                if isinstance(rec, Message) and rec.channel_id == channel:
                    msg = json.loads(rec.data)
                    if not msg.get("preroll"):
                        n += int(msg["count"])
                        dec = decode_samples(msg)
                        last = int(dec.t_host_ns[-1])
                        last_td = math.nan if dec.t_device_ns is None else int(dec.t_device_ns[-1]) / NS
    except (OSError, McapError, struct.error, ValueError, KeyError, TypeError, EOFError, zstandard.ZstdError):
        pass  # the first record cut short: the end of what is readable
    return n, last, last_td
