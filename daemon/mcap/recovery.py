"""Crash recovery: each file a killed writer left without its footer is rewritten once, as ``mcap recover`` would."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from ballbar import __version__
from ballbar.analysis.errors import BallbarError

from ..listeners import TEST_END_EVENTS
from ..spool import read_spool
from .format import _MAGIC, NS, TOPIC_EVENTS, TOPIC_RESULTS, TOPIC_SAMPLES, decode_samples, hold_file, list_recordings
from .reader import _records, _why_stopped, read_log

log = logging.getLogger(__name__)

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
    cannot be rewritten is left as it was, with a warning; so is a file another process holds open (its
    writer's ``flock``: a live daemon's file has no footer until it closes, and is never rewritten)."""
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
            fd = hold_file(path)
        except OSError as err:
            log.warning("mcap log: cannot recover %s (left as it is): %s", path.name, err.strerror or err)
            continue
        if fd is None:  # its writer is alive: not cut, only not finished yet
            log.warning("mcap log: %s has no footer but is open in another process (its writer, still running): "
                        "left alone", path.name)
            continue
        try:
            r = recover_file(path)
        except (OSError, McapError) as err:
            log.warning("mcap log: cannot recover %s (left as it is): %s", path.name, err)
            with contextlib.suppress(OSError):
                path.with_name(path.name + ".recovering").unlink()
            continue
        finally:
            os.close(fd)  # after the rename: the file now at the path is the rewritten one
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


@dataclass(frozen=True)
class LastSample:
    """The newest sample of the recordings (see :func:`last_recorded`)."""

    path: Path
    source: str
    seq: int
    t_device_s: float | None
    t_host_ns: int  # wall clock, as stored
    period_s: float | None  # the device clock's step per sample in its last message (None: no clock)


def last_recorded(directory: str | os.PathLike[str], max_files: int = 16) -> LastSample | None:
    """The newest sample in the newest of the logger's files that holds samples (from its summary: one chunk
    read), looking back at most ``max_files`` files; None when none holds any, or the newest that holds samples
    cannot be read so (a file without a summary: a cut one that recovery could not rewrite)."""
    d = Path(directory)
    if not d.is_dir():
        return None
    for path in reversed(list_recordings(d)[-max_files:]):
        try:
            with open(path, "rb") as fh:
                reader = make_reader(fh)
                summary = reader.get_summary()
                if summary is None:
                    return None
                if not any(c.topic == TOPIC_SAMPLES and summary.statistics is not None
                           and summary.statistics.channel_message_counts.get(c.id) for c in summary.channels.values()):
                    continue
                for _schema, _channel, msg in reader.iter_messages(topics=[TOPIC_SAMPLES], reverse=True):
                    dec = decode_samples(json.loads(msg.data))
                    break
                else:
                    continue
        except (OSError, McapError, struct.error, ValueError, KeyError, TypeError, EOFError, MemoryError,
                RecursionError, zstandard.ZstdError) as err:
            log.warning("mcap log: cannot read the last sample of %s: %s", path.name, err)
            return None
        td = dec.t_device_ns
        period = None
        if td is not None and dec.seq.size >= 2:
            steps = np.diff(dec.seq)
            ok = steps > 0
            if ok.any():
                period = float(np.median(np.diff(td)[ok] / steps[ok])) / NS
        return LastSample(path, dec.source, int(dec.seq[-1]), None if td is None else int(td[-1]) / NS,
                          int(dec.t_host_ns[-1]), period)
    return None
