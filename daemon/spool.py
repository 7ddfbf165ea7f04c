"""The spool: results and events the MCAP logger held through a write outage that lasted until it stopped.

``STATE_DIR/mcap-held.spool`` is allocated (``posix_fallocate``) while the disk
has room, so that writing into it later needs no free space: at stop, what the
logger still holds goes there (zstd-compressed JSON lines, the newest that
fit), with the outage's ``log_gap`` event; the next start reads it, writes it
to its first file and marks the spool empty (its space stays reserved).

Layout: a magic line, the run id (32 bytes), the compressed size (8 bytes,
little-endian), then the compressed lines ``[topic, log_time_ns, payload]``;
zeros after.  An empty spool is all zeros.
"""

from __future__ import annotations

import errno
import json
import logging
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zstandard

from .listeners import to_json

log = logging.getLogger(__name__)

SPOOL_NAME = "mcap-held.spool"
SPOOL_MIN_BYTES = 64 << 10
SPOOL_MAX_BYTES = 1 << 20  # some 150 test results
_MAGIC = b"ballbar-held/1\n"
_HEAD = len(_MAGIC) + 32 + 8
_TOPICS = ("/ballbar/results", "/ballbar/events", "/ballbar/config")


def spool_size(total: int | None) -> int:
    """The spool's size on a file system of ``total`` bytes: a 32nd of it, within the bounds above."""
    return SPOOL_MAX_BYTES if total is None else max(SPOOL_MIN_BYTES, min(SPOOL_MAX_BYTES, total // 32))


@dataclass
class Spool:
    """What a run held through a write outage until it stopped: its ``run_id`` and ``entries``, ``(topic, payload,
    log time ns)`` oldest first (the outage's ``log_gap`` event last)."""

    run_id: str = ""
    entries: list[tuple[str, dict[str, Any], int]] = field(default_factory=list)


def reserve_spool(path: Path, size: int) -> bool:
    """Allocate the spool (empty, ``size`` bytes) while the disk has room: writing into it later needs none."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as err:
        log.warning("mcap log: cannot make the spool %s: %s", path, err.strerror or err)
        return False
    try:
        if os.fstat(fd).st_size < size:
            try:
                os.posix_fallocate(fd, 0, size)
            except OSError as err:
                if err.errno not in (errno.EOPNOTSUPP, errno.EINVAL):
                    raise
                os.pwrite(fd, bytes(size), 0)  # a file system without fallocate: the blocks written
        os.fsync(fd)
        return True
    except OSError as err:
        log.warning("mcap log: cannot reserve %s: %s", path, err.strerror or err)
        return False
    finally:
        os.close(fd)


def write_spool(path: Path, run_id: str, entries: Sequence[tuple[str, Mapping[str, Any], int]], size: int) -> int:
    """Write ``entries`` (topic, payload, log time) of run ``run_id`` into the spool, in place: the newest that fit
    in its reserved size (or ``size``).  Returns how many."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError:
        return 0
    try:
        room = min(SPOOL_MAX_BYTES, max(os.fstat(fd).st_size, size)) - _HEAD
        lines = [to_json([topic, log_time, payload]) for topic, payload, log_time in entries]
        first = 0
        while first < len(lines):
            data = zstandard.ZstdCompressor(level=9).compress(b"\n".join(lines[first:]))
            if len(data) <= room:
                break
            first += max(1, (len(lines) - first) // 8)  # the oldest go first
        else:
            return 0
        os.pwrite(fd, _MAGIC + run_id.encode()[:32].ljust(32) + len(data).to_bytes(8, "little") + data, 0)
        os.fsync(fd)
        return len(lines) - first
    except (OSError, TypeError, ValueError) as err:
        log.warning("mcap log: cannot write the spool %s: %s", path, err)
        return 0
    finally:
        os.close(fd)


def read_spool(state_dir: str | os.PathLike[str]) -> Spool:
    """The spool of ``state_dir`` (empty when there is none); a damaged one is ignored, with a warning."""
    path = Path(state_dir) / SPOOL_NAME
    try:
        with open(path, "rb") as fh:
            head = fh.read(_HEAD)
            if len(head) < _HEAD or not head.startswith(_MAGIC):
                return Spool()
            size = int.from_bytes(head[_HEAD - 8 :], "little")
            if not 0 < size <= SPOOL_MAX_BYTES:
                return Spool()
            data = fh.read(size)
        out = Spool(head[len(_MAGIC) : _HEAD - 8].decode().strip())
        for line in zstandard.ZstdDecompressor().decompress(data, max_output_size=64 * SPOOL_MAX_BYTES).split(b"\n"):
            topic, log_time, payload = json.loads(line)
            if topic in _TOPICS and isinstance(log_time, int) and isinstance(payload, dict):
                out.entries.append((str(topic), payload, log_time))
        return out
    except FileNotFoundError:
        return Spool()
    except (OSError, ValueError, TypeError, zstandard.ZstdError) as err:
        log.warning("mcap log: the spool %s cannot be read (%s); ignored", path, err)
        return Spool()


def empty_spool(path: Path) -> bool:
    """Mark the spool empty (its space stays reserved); False if that failed (it is tried again)."""
    try:
        fd = os.open(path, os.O_RDWR)
    except FileNotFoundError:
        return True
    except OSError:
        return False
    try:
        os.pwrite(fd, bytes(_HEAD), 0)
        os.fsync(fd)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


__all__ = ["SPOOL_NAME", "Spool", "empty_spool", "read_spool", "reserve_spool", "spool_size", "write_spool"]
