"""Reading the recordings back, from any file: a cut one up to its last whole record, a bad one as one error line."""

from __future__ import annotations

import io
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
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError
from mcap.opcode import Opcode
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
    TOPIC_CONTROLLER,
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
    came from (index into ``paths``).  ``skipped``: where damaged records were
    passed over, each as the index in ``samples`` of the first sample after it
    and what was skipped (the byte range, in words).
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
    skipped: list[tuple[int, str]] = field(default_factory=list)

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


@dataclass
class Walk:
    """How far a walk through a file's records got (:func:`_records`): ``end``, the byte after its last whole
    record; ``size``, the file's; ``skipped``, the byte ranges ``[start, end)`` of damaged records passed over
    (a chunk whose bytes are garbled: the reading goes on at the next whole chunk), each with why."""

    size: int = 0
    end: int = 0
    skipped: list[tuple[int, int, str]] = field(default_factory=list)


_BAD_RECORD = (McapError, struct.error, ValueError, EOFError, MemoryError, zstandard.ZstdError)
_SCAN_WINDOW = 1 << 20
_DATA_END_HEAD = bytes([Opcode.DATA_END]) + struct.pack("<Q", 4)


def _read_at(fh: IO[bytes], pos: int, size: int) -> tuple[int, bytes]:
    """The opcode and whole bytes of the record at ``pos``: :class:`~mcap.exceptions.EndOfFile` where it would
    reach past the end of the file, an McapError where it would be larger than :data:`MAX_RECORD_BYTES`."""
    fh.seek(pos)
    head = fh.read(9)
    if len(head) < 9:
        raise EndOfFile()
    opcode, length = struct.unpack("<BQ", head)
    if length > MAX_RECORD_BYTES:
        raise McapError(f"a record of {length} bytes, more than any the logger writes ({MAX_RECORD_BYTES})")
    if pos + 9 + length > size:
        raise EndOfFile()
    body = fh.read(length)
    if len(body) < length:
        raise EndOfFile()
    return opcode, head + body


def _parse_record(opcode: int, raw: bytes) -> list[Any]:
    """The records of one top-level record's bytes: a chunk's inner records (checked against its CRC), else the
    record itself (none for an opcode the format does not know)."""
    if opcode == Opcode.CHUNK:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(raw[9:])))
        _check_chunk(chunk.uncompressed_size, chunk.compression, chunk.data)
        return list(breakup_chunk(chunk, validate_crc=True))
    reader = StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True, record_size_limit=MAX_RECORD_BYTES)
    records = reader.records
    try:
        return [next(records)]
    except EndOfFile:  # an opcode the format does not know: skipped, as the mcap readers do
        return []


def _resync(fh: IO[bytes], start: int, size: int) -> tuple[int, int, list[Any]] | None:
    """The next whole chunk (its CRC right) or data-end record from byte ``start`` on: ``(its offset, its end,
    its records)``; None when there is none (the file is cut there, not damaged)."""
    pos = start
    while pos < size:
        fh.seek(pos)
        window = fh.read(_SCAN_WINDOW + 9)
        data_end = window.find(_DATA_END_HEAD)
        at = window.find(bytes([Opcode.CHUNK]))
        while 0 <= at < _SCAN_WINDOW:
            if 0 <= data_end < at:
                break
            try:
                _op, raw = _read_at(fh, pos + at, size)
                chunk = Chunk.read(ReadDataStream(io.BytesIO(raw[9:])))
                if chunk.uncompressed_crc != 0:  # else nothing tells a chunk from bytes that look like one
                    _check_chunk(chunk.uncompressed_size, chunk.compression, chunk.data)
                    return pos + at, pos + at + len(raw), list(breakup_chunk(chunk, validate_crc=True))
            except _BAD_RECORD:
                pass
            at = window.find(bytes([Opcode.CHUNK]), at + 1)
        if 0 <= data_end < _SCAN_WINDOW and pos + data_end + 13 <= size:
            return pos + data_end, pos + data_end + 13, []
        pos += _SCAN_WINDOW
    return None


def _records(fh: IO[bytes], skip_magic: bool = False, walk: Walk | None = None) -> Iterator[Any]:
    """The records of an MCAP file from its start (or, ``skip_magic``, from where ``fh`` is), chunks broken up,
    none larger than :data:`MAX_RECORD_BYTES`.

    A damaged chunk (its bytes garbled: it does not decompress, or its CRC is wrong) is passed over, its byte
    range noted in ``walk``; the records go on from the next whole chunk.  Where none follows, the file ends
    there: :class:`~mcap.exceptions.EndOfFile` (cut short) or the error of the record that ended it."""
    walk = walk if walk is not None else Walk()
    start = fh.tell()
    fh.seek(0, os.SEEK_END)
    walk.size = fh.tell()
    fh.seek(start)
    if not skip_magic:
        if fh.read(len(_MAGIC)) != _MAGIC:
            raise McapError("no MCAP magic at the start")
        start += len(_MAGIC)
    pos = walk.end = start
    while True:
        if pos >= walk.size:
            raise EndOfFile()
        try:
            opcode, raw = _read_at(fh, pos, walk.size)
            records = _parse_record(opcode, raw)
            nxt = pos + len(raw)
        except _BAD_RECORD as err:
            found = _resync(fh, pos + 1, walk.size)
            if found is None:
                raise
            at, nxt, records = found
            walk.skipped.append((pos, at, _why_stopped(err)))
        walk.end = nxt
        for rec in records:
            yield rec
            if isinstance(rec, Footer):
                fh.seek(nxt)
                if fh.read(len(_MAGIC)) != _MAGIC:
                    raise EndOfFile()
                walk.end = nxt + len(_MAGIC)
                return
        pos = nxt


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
    walk = Walk()
    skipped: list[tuple[int, str]] = []
    try:
        for rec in _records(fh, walk=walk):
            while len(skipped) < len(walk.skipped):
                a, b, why = walk.skipped[len(skipped)]
                before = sum(d.seq.size for d in decoded) if samples else skipped_blocks
                skipped.append((before, f"bytes {a} to {b} ({why})"))
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
        # A partial record (a killed writer's, a full disk's, a copy cut short), or one no whole chunk follows.
        what = f"{sum(d.seq.size for d in decoded)} samples" if samples else f"{skipped_blocks} sample records"
        if walk.end >= walk.size:
            after = "its magic" if walk.size <= len(_MAGIC) else "a whole record"
            problem = f"ends early at byte {walk.size}, after {after}, without its footer ({what} before it)"
        else:
            problem = f"ends early: {_why_stopped(err)} at byte {walk.end} of {walk.size} ({what} before it)"
    if skipped:
        what = "samples" if samples else "sample records"
        problem = "; ".join(
            [f"damaged: {where} skipped, {k} {what} before it" for k, where in skipped]
            + ([problem] if problem else [])
        )
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
    log_.skipped = skipped if samples else []
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


def read_log(path: str | os.PathLike[str], samples: bool = True, status: bool = True, warn: bool = True) -> McapLog:
    """Everything in one log file; a truncated file (killed writer) is read up to its last whole chunk.

    ``samples=False`` leaves the samples and the status messages out (an empty
    batch, no status): reading only the events, results and configuration is
    then many times faster, the more so for a finished file, whose summary
    says which chunks hold them.  ``status=False`` leaves the status messages
    out (the analysis needs none).

    Memory: the samples, and at most :data:`SIDE_BYTES_MAX` of the other
    records' JSON; a record or chunk larger than :data:`MAX_RECORD_BYTES` ends
    the reading as a cut file's end does.

    A file that ends early or holds damaged records is read as far as it can
    be, with one WARNING (:func:`warn_once`; ``warn=False``: none, the caller
    says it from :attr:`McapLog.problem`; none either for a file read for its
    samples that holds none, whose :func:`recording` is then an error that says it).

    Raises :class:`DataError` (one line, naming the file) when the file is
    missing, unreadable, not MCAP, or holds a malformed samples record.
    """
    name = os.fspath(path)
    out = _read_one(name, samples, status)
    # (a file read for its samples that holds none: :func:`recording`'s error says how it ends, in one line)
    if out.problem and warn and (not samples or len(out.samples)):
        warn_once(name, out.problem)
    return out


_WARNED: dict[tuple[str, int, int], None] = {}


def warn_once(name: str, problem: str) -> None:
    """The WARNING that a file ends early or is damaged (``problem``), once per state of the file in this process:
    reading a file's records, then its samples, says it once.  The record carries ``cut_file`` (the path), for a
    filter that knows the file is still being written."""
    try:
        st = os.stat(name)
        key = (os.path.realpath(name), st.st_size, st.st_mtime_ns)
    except OSError:
        key = (name, -1, -1)
    if key in _WARNED:
        return
    if len(_WARNED) >= 1024:
        _WARNED.clear()
    _WARNED[key] = None
    log.warning("%s: %s", name, problem, extra={"cut_file": name})


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
    paths: Iterable[str | os.PathLike[str]], skip_bad: bool = False, status: bool = True, warn: bool = True
) -> McapLog:
    """Several files in the given order, joined; preroll samples already in the file before are dropped.

    ``skip_bad``: a file that cannot be read is left out with a warning naming it (one bad file in a directory
    costs only itself); a DataError only when none can be read.  ``warn``: as :func:`read_log`.
    """
    names = list(paths)
    parts: list[McapLog] = []
    errors: list[str] = []
    for path in names:
        try:
            parts.append(read_log(path, status=status, warn=warn))
        except DataError as err:
            if not skip_bad:
                raise
            errors.append(str(err))
            log.warning("%s; left out, the other files read", err)
    if warn and len(parts) > 1:
        for p in parts:
            if p.problem and not len(p.samples):
                warn_once(p.paths[0], p.problem)
    if not parts:
        raise DataError(errors[0] if len(errors) == 1 else
                        f"none of the {len(names)} MCAP files could be read (the first: {errors[0]})" if errors else
                        "no MCAP files given")
    keep_batches: list[SampleBatch] = []
    walls: list[NDArray[np.int64]] = []
    pres: list[NDArray[np.bool_]] = []
    starts: list[int] = []
    last_wall: int | None = None
    skipped: list[tuple[int, str]] = []
    for p in parts:
        starts.append(sum(len(b) for b in keep_batches))
        s, wall, pre = p.samples, p.t_wall_ns, p.preroll
        kept = np.ones(wall.size, bool)
        if last_wall is not None and pre.any():
            kept = keep = ~(pre & (wall <= last_wall))
            s, wall, pre = _take(s, keep), wall[keep], pre[keep]
        skipped += [(starts[-1] + int(np.count_nonzero(kept[:k])), f"{p.paths[0]}: {where}") for k, where in p.skipped]
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
        skipped=skipped,
    )
    for k in _TOPIC_LISTS.values():
        setattr(out, k, [x for p in parts for x in getattr(p, k)])
    return out


def read_controller(paths: Iterable[str | os.PathLike[str]]) -> list[dict[str, Any]]:
    """The CNC controller's messages (``/ballbar/controller``, ``[controller]``) of recordings, in file order; a
    file cut by a crash gives what it holds up to the cut, a damaged record is passed over."""
    return [msg for _f, msg in _controller_records(paths)]


def _controller_records(paths: Iterable[str | os.PathLike[str]]) -> Iterator[tuple[int, dict[str, Any]]]:
    """:func:`read_controller`'s records, each with the index of its file in ``paths``."""
    for f, path in enumerate(paths):
        channels: dict[int, str] = {}
        try:
            with open(path, "rb") as fh:
                for rec in _records(fh):
                    if isinstance(rec, Channel):
                        channels[rec.id] = rec.topic
                    elif isinstance(rec, Message) and channels.get(rec.channel_id) == TOPIC_CONTROLLER:
                        try:
                            obj = json.loads(rec.data)
                        except (ValueError, RecursionError):
                            continue
                        if isinstance(obj, dict):
                            yield f, obj
        except (OSError, McapError, EndOfFile, struct.error, zstandard.ZstdError) as err:
            log.warning("%s: controller records read up to a problem: %s", os.fspath(path), err)


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
    write) before the first sample of the file it heads, and a damaged record
    the reader passed over (:attr:`McapLog.skipped`) where it was.
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
    for k, where in lg.skipped:  # the samples of a damaged chunk are missing there
        if 0 < k < n:
            breaks.append((int(np.searchsorted(index, k)), f"samples missing: a damaged record ({where}) skipped"))
    from ballbar.analysis.polled import from_events

    return Recording(np.ascontiguousarray(t, dtype=np.float64), np.ascontiguousarray(L, dtype=np.float64),
                     sorted(breaks), axis, name, from_events(lg.events), _controller_marks(lg, index, t_host))


def _controller_marks(lg: McapLog, index: NDArray[np.intp], t_host: NDArray[np.float64],
                      ) -> list[tuple[int, bool, str | None]]:
    """What the CNC controller said of its main program (``/ballbar/controller``), each from the first sample the
    daemon read after the message came (as the live analysis took it: in order with the batches); a file's
    repeated state from its first sample (its preroll's too)."""
    from ballbar.analysis.plans import controller_program

    out: list[tuple[int, bool, str | None]] = []
    for f, msg in _controller_records(lg.paths):
        known, program = controller_program(msg)
        at = msg.get("t_host")
        if known is None or not isinstance(at, int | float):
            continue
        if msg.get("repeated") and f < len(lg.file_starts):
            k = int(np.searchsorted(index, lg.file_starts[f]))
        else:
            k = int(np.searchsorted(t_host, float(at), side="left"))
        out.append((k, known, program))
    return sorted(out, key=lambda m: m[0])


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
