"""The recordings' format: file names, channels and schemas, the samples' encoding (the package's docstring)."""

from __future__ import annotations

import errno
import fcntl
import logging
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ballbar.analysis.errors import BallbarError
from ballbar.protocol.messages.channels import MCAP_CHANNELS, shipped_schema

from ..samples import SampleBatch

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
TOPIC_CONTROLLER = "/ballbar/controller"

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


def list_recordings(directory: str | os.PathLike[str]) -> list[Path]:
    """The logger's files in ``directory``, oldest first (by the UTC time and number in their names)."""
    d = Path(directory)
    found = []
    for p in d.iterdir():
        m = _NAME_RE.match(p.name)
        if m and p.is_file():
            found.append((m["ts"], int(m["seq"]), p.name, p))
    return [p for *_k, p in sorted(found)]


def hold_file(path: str | os.PathLike[str]) -> int | None:
    """A descriptor of ``path`` holding an exclusive ``flock`` on it, or ``None`` when another open file holds one:
    the logger that writes a file holds it so (another process's, or a previous start's still alive), and recovery
    and retention leave such a file alone.  ``OSError`` (the file gone, unreadable) passes to the caller."""
    fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        os.close(fd)
        if err.errno in (errno.EWOULDBLOCK, errno.EACCES):
            return None
        raise
    return fd


def mcap_files(directory: str | os.PathLike[str]) -> list[Path]:
    """The MCAP files of a directory to read as one recording: the logger's, oldest first, else any ``*.mcap``
    in name order (files renamed or copied by hand)."""
    return list_recordings(directory) or sorted(Path(directory).glob("*.mcap"))


# ----------------------------------------------------------------------------- reading

def _take(b: SampleBatch, index: Any) -> SampleBatch:
    return SampleBatch(
        b.t_host[index], b.t_device[index], b.length_mm[index], b.seq[index], b.status[index], (), b.source
    )


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


def controller_state(state: tuple[dict[str, Any], dict[str, Any]] | None, msg: Mapping[str, Any],
                     ) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """The controller's last record (without its values) and its last value of each node, after ``msg`` (a
    ``controller`` record): what the logger repeats at a new file's head.  None: lost, nothing to repeat."""
    if msg.get("state") == "lost":
        return None
    values = {} if msg.get("state") == "connected" or state is None else state[1]
    for v in msg.get("values") or ():
        values[v["name"]] = v
    return {k: v for k, v in msg.items() if k not in ("values", "missing", "detail", "repeated")}, values
