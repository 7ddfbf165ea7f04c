"""The binary LVDT frame: 17 bytes per sample, little-endian.

=======  ====  ========  ===================================================
offset   size  field     meaning
=======  ====  ========  ===================================================
0        2     sync      ``A5 5A``
2        4     seq       sample counter (uint32), +1 per sample, wraps at 2**32
6        4     clock_us  device sample clock (uint32), microseconds, wraps at
                         2**32 us (71.6 min)
10       4     value     LVDT displacement (int32), unit 10 nm = 0.01 um
14       1     status    :class:`~ballbar.protocol.Status` bits
15       2     crc       CRC-16/CCITT-FALSE of bytes 0..14 (poly 0x1021,
                         init 0xFFFF, not reflected, no final xor)
=======  ====  ========  ===================================================

See ``protocol/README.md`` for examples and the reasoning.

Decoding is vectorised: the buffer is searched for sync words with numpy, every
candidate's CRC is checked at once (one table lookup per byte column), and the
frames are taken greedily from the start: the first valid frame at or after the
current position is accepted and the position moves past it.  Bytes that are
not part of an accepted frame are counted as skipped; a sync word whose frame
fails its CRC is counted as ``bad_crc``.  The result does not depend on how the
stream is chunked: nothing is decided on bytes that have not arrived.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._common import BAD_CRC, SKIPPED_BYTES, Readings, Status, add_counts

SYNC = b"\xa5\x5a"
FRAME_SIZE = 17
#: One count of ``value`` in millimetres (10 nm).
VALUE_UNIT_MM = 1e-5
#: Counts per millimetre, the exact divisor used to convert ``value`` to mm.
COUNTS_PER_MM = 100_000.0
CLOCK_HZ = 1_000_000
SEQ_MODULUS = 1 << 32
CLOCK_WRAP_S = (1 << 32) / CLOCK_HZ
VALUE_MIN = -(1 << 31)
VALUE_MAX = (1 << 31) - 1

#: The wire layout as a numpy dtype: ``np.frombuffer(frame_bytes, FRAME_DTYPE)``.
FRAME_DTYPE = np.dtype(
    {
        "names": ["sync", "seq", "clock_us", "value", "status", "crc"],
        "formats": ["<u2", "<u4", "<u4", "<i4", "u1", "<u2"],
        "offsets": [0, 2, 6, 10, 14, 15],
        "itemsize": FRAME_SIZE,
    }
)

_CRC_POLY = 0x1021
_CRC_INIT = 0xFFFF
_SYNC0, _SYNC1 = SYNC[0], SYNC[1]
_BODY = FRAME_SIZE - 2  # bytes covered by the CRC


def _byte_table() -> list[int]:
    table = []
    for b in range(256):
        crc = b << 8
        for _ in range(8):
            crc = ((crc << 1) ^ _CRC_POLY) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_TABLE = _byte_table()


def crc16(data: bytes | bytearray | memoryview, crc: int = _CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE, one byte at a time (the reference; ``crc16(b"123456789") == 0x29B1``)."""
    for b in bytes(data):
        crc = ((crc << 8) & 0xFFFF) ^ _TABLE[(crc >> 8) ^ b]
    return crc


def _position_tables() -> tuple[NDArray[np.uint16], int]:
    """Per-position tables of the CRC as a linear map over GF(2).

    With a zero initial value the CRC of a message is the xor of the CRCs of the
    message with all bytes but one zeroed, so ``crc = const ^ xor_i T[i][byte_i]``,
    where ``const`` is the CRC of ``_BODY`` zero bytes with the real initial value.
    """
    table = np.array(_TABLE, dtype=np.uint16)
    pos = np.empty((_BODY, 256), dtype=np.uint16)
    crc = table.copy()  # CRC (init 0) of the single byte b
    for i in range(_BODY - 1, -1, -1):
        pos[i] = crc  # byte at position i is followed by _BODY - 1 - i zero bytes
        crc = ((crc << 8) & 0xFFFF) ^ table[crc >> 8]
    const = crc16(bytes(_BODY))
    return pos, const


_POS_TABLES, _CRC_CONST = _position_tables()
_POS_INDEX = np.arange(_BODY)
_SYNC_WORD = np.uint16(int.from_bytes(SYNC, "little"))
_SHORTCUT = True  # decode's clean-run shortcut (the tests compare it with the general walk)
_FRAME_OFFSETS = np.arange(FRAME_SIZE)


def crc16_rows(rows: NDArray[np.uint8]) -> NDArray[np.uint16]:
    """CRC of each row of a ``(n, 15)`` byte matrix, vectorised over rows and positions."""
    crc: NDArray[np.uint16] = np.bitwise_xor.reduce(_POS_TABLES[_POS_INDEX, rows[:, :_BODY]], axis=1)
    return crc ^ np.uint16(_CRC_CONST)


# ----------------------------------------------------------------------------- encoder


def displacement_to_counts(displacement_mm: ArrayLike) -> tuple[NDArray[np.int32], NDArray[np.uint8]]:
    """Round millimetres to 10 nm counts; values beyond int32 are clamped and flagged OVER_RANGE."""
    counts = np.rint(np.asarray(displacement_mm, dtype=np.float64) * COUNTS_PER_MM)
    bad = ~np.isfinite(counts)
    over = (counts < VALUE_MIN) | (counts > VALUE_MAX)
    status = np.where(over | bad, np.uint8(Status.OVER_RANGE), np.uint8(0)).astype(np.uint8)
    counts = np.clip(np.where(bad, 0.0, counts), VALUE_MIN, VALUE_MAX)
    return counts.astype(np.int32), status


def encode(
    seq: ArrayLike,
    clock_us: ArrayLike,
    value: ArrayLike,
    status: ArrayLike = 0,
) -> bytes:
    """Frames for arrays (or scalars) of raw fields: ``seq`` and ``clock_us`` are taken
    modulo 2**32, ``value`` in 10 nm counts (int32), ``status`` a byte."""
    seq_a = np.atleast_1d(np.asarray(seq)).astype(np.int64)
    n = seq_a.shape[0]
    frames = np.zeros(n, dtype=FRAME_DTYPE)
    frames["sync"] = int.from_bytes(SYNC, "little")
    frames["seq"] = (seq_a % SEQ_MODULUS).astype(np.uint32)
    frames["clock_us"] = (np.broadcast_to(np.asarray(clock_us, dtype=np.int64), (n,)) % SEQ_MODULUS).astype(np.uint32)
    val = np.broadcast_to(np.asarray(value), (n,))
    if np.any((val < VALUE_MIN) | (val > VALUE_MAX)):
        raise ValueError("value out of int32 range: use displacement_to_counts to clamp and flag it")
    frames["value"] = val.astype(np.int32)
    frames["status"] = np.broadcast_to(np.asarray(status, dtype=np.int64) & 0xFF, (n,)).astype(np.uint8)
    raw = frames.view(np.uint8).reshape(n, FRAME_SIZE)
    frames["crc"] = crc16_rows(raw[:, :_BODY])
    return frames.tobytes()


def encode_samples(
    seq: ArrayLike,
    t_s: ArrayLike,
    displacement_mm: ArrayLike,
    status: ArrayLike = 0,
) -> bytes:
    """Frames for samples in physical units: device time in seconds, displacement in mm."""
    counts, over = displacement_to_counts(displacement_mm)
    clock = np.rint(np.asarray(t_s, dtype=np.float64) * CLOCK_HZ).astype(np.int64)
    st = np.asarray(status, dtype=np.int64) | over
    return encode(seq, clock, counts, st)


# ----------------------------------------------------------------------------- decoder


class Decoded(NamedTuple):
    """What :func:`decode` found in a buffer.

    ``consumed``: bytes of the buffer that are decided (frames and skipped bytes);
    keep the rest and prepend it to the next chunk.  ``frames``: structured array of
    :data:`FRAME_DTYPE`.  ``dropped``: counts by reason for the consumed bytes.
    """

    consumed: int
    frames: NDArray[np.void]
    dropped: dict[str, int]


_EMPTY = np.empty(0, dtype=FRAME_DTYPE)


def decode(buffer: bytes | bytearray | memoryview, final: bool = False) -> Decoded:
    """Decode every frame in ``buffer``; pure, never raises for any bytes.

    ``final``: the stream ends here; an incomplete tail is dropped (counted as
    skipped bytes) instead of being left unconsumed.
    """
    buf = np.frombuffer(buffer, dtype=np.uint8)
    n = buf.shape[0]
    if n == 0:
        return Decoded(0, _EMPTY, {BAD_CRC: 0, SKIPPED_BYTES: 0})
    clean = _clean_run(buf, final) if _SHORTCUT else None
    if clean is not None:
        return clean
    cand = np.flatnonzero((buf[:-1] == _SYNC0) & (buf[1:] == _SYNC1))
    full = cand[cand <= n - FRAME_SIZE]
    if full.shape[0]:
        windows = buf[full[:, None] + _FRAME_OFFSETS]
        crc = windows[:, _BODY].astype(np.uint16) | (windows[:, _BODY + 1].astype(np.uint16) << 8)
        ok = crc16_rows(windows[:, :_BODY]) == crc
        valid_idx = np.flatnonzero(ok)
    else:
        windows = np.empty((0, FRAME_SIZE), np.uint8)
        ok = np.zeros(0, bool)
        valid_idx = np.empty(0, np.intp)
    valid = full[valid_idx]

    # Greedy walk over valid candidates, one Python step per run of back-to-back
    # frames (one run in a clean stream), not per frame.
    taken: list[NDArray[np.intp]] = []
    pos = 0
    if valid.shape[0]:
        brk = np.flatnonzero(np.diff(valid) != FRAME_SIZE)
        starts = np.concatenate(([0], brk + 1)).tolist()
        ends = np.concatenate((brk, [valid.shape[0] - 1])).tolist()
        for s, e in zip(starts, ends, strict=True):
            if int(valid[e]) < pos:
                continue
            k = s + int(np.searchsorted(valid[s : e + 1], pos))
            taken.append(np.arange(k, e + 1))
            pos = int(valid[e]) + FRAME_SIZE
    accepted = np.concatenate(taken) if taken else np.empty(0, np.intp)

    # Where the undecided tail begins: a sync word (or its first byte) at or after
    # ``pos`` whose frame has not fully arrived.
    if final:
        consumed = n
    else:
        consumed = n
        late = cand[(cand > n - FRAME_SIZE) & (cand >= pos)]
        if late.shape[0]:
            consumed = int(late[0])
        elif buf[n - 1] == _SYNC0 and n - 1 >= pos:
            consumed = n - 1

    bad = full[~ok]
    n_bad = 0
    if bad.shape[0]:
        starts_acc = valid[accepted]
        if starts_acc.shape[0]:
            j = np.searchsorted(starts_acc, bad, side="right") - 1
            inside = (j >= 0) & (bad < starts_acc[np.maximum(j, 0)] + FRAME_SIZE)
            n_bad = int(np.count_nonzero(~inside & (bad < consumed)))
        else:
            n_bad = int(np.count_nonzero(bad < consumed))

    frames = np.ascontiguousarray(windows[valid_idx[accepted]]).view(FRAME_DTYPE).reshape(-1)
    dropped = {BAD_CRC: n_bad, SKIPPED_BYTES: consumed - FRAME_SIZE * frames.shape[0]}
    return Decoded(consumed, frames, dropped)


def _clean_run(buf: NDArray[np.uint8], final: bool) -> Decoded | None:
    """The usual buffer in a few array operations: whole valid frames back to back from its start, then
    nothing or the start of the next frame (``A5`` or ``A5 5A ...``).  ``None``: anything else, for
    :func:`decode`'s general walk (which gives the same result for these)."""
    n = buf.shape[0]
    k = n // FRAME_SIZE
    end = k * FRAME_SIZE
    if k == 0 or buf[0] != _SYNC0 or buf[1] != _SYNC1:
        return None
    if end < n and (final or buf[end] != _SYNC0 or (end + 1 < n and buf[end + 1] != _SYNC1)):
        return None
    rows = buf[:end].reshape(k, FRAME_SIZE)
    frames = rows.view(FRAME_DTYPE).reshape(k)
    if not (frames["sync"] == _SYNC_WORD).all() or not (crc16_rows(rows) == frames["crc"]).all():
        return None
    return Decoded(end, frames.copy(), {BAD_CRC: 0, SKIPPED_BYTES: 0})


def frames_to_readings(frames: NDArray[np.void]) -> Readings:
    """Fields of decoded frames in physical units (mm, seconds), as :class:`Readings`."""
    return Readings(
        value_mm=frames["value"].astype(np.float64) / COUNTS_PER_MM,
        status=frames["status"].astype(np.uint8),
        seq=frames["seq"].astype(np.int64),
        clock_s=frames["clock_us"].astype(np.float64) / CLOCK_HZ,
    )


class BinaryDecoder:
    """Streaming decoder: feed chunks as they arrive, in any sizes.

    Keeps at most one incomplete frame between calls; ``dropped`` accumulates
    the counts by reason and ``frames`` the number of frames decoded.  No I/O.
    """

    name = "binary"
    seq_modulus: int | None = SEQ_MODULUS
    clock_wrap_s: float | None = CLOCK_WRAP_S

    def __init__(self) -> None:
        self._pending = b""
        self.frames = 0
        self.dropped: dict[str, int] = {BAD_CRC: 0, SKIPPED_BYTES: 0}

    def feed_frames(self, data: bytes | bytearray | memoryview) -> NDArray[np.void]:
        """Raw frames (:data:`FRAME_DTYPE`) completed by ``data``."""
        buffer = self._pending + bytes(data) if self._pending else bytes(data)
        res = decode(buffer)
        self._pending = buffer[res.consumed :]
        self.frames += res.frames.shape[0]
        add_counts(self.dropped, res.dropped)
        return res.frames

    def feed(self, data: bytes | bytearray | memoryview) -> Readings:
        return frames_to_readings(self.feed_frames(data))

    def flush(self) -> Readings:
        """End of stream (or a reconnection): drop an incomplete tail, counting it."""
        res = decode(self._pending, final=True)
        self._pending = b""
        self.frames += res.frames.shape[0]
        add_counts(self.dropped, res.dropped)
        return frames_to_readings(res.frames)

    def discard(self, rejoin: bool = False) -> None:
        """Drop an incomplete tail (a connection ended mid-frame), counting it as skipped.

        ``rejoin`` is for the line protocol's sake: frames resynchronise by themselves.
        """
        self.dropped[SKIPPED_BYTES] += len(self._pending)
        self._pending = b""

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a frame."""
        return len(self._pending)


__all__ = [
    "CLOCK_HZ",
    "CLOCK_WRAP_S",
    "COUNTS_PER_MM",
    "FRAME_DTYPE",
    "FRAME_SIZE",
    "SEQ_MODULUS",
    "SYNC",
    "VALUE_UNIT_MM",
    "BinaryDecoder",
    "Decoded",
    "crc16",
    "crc16_rows",
    "decode",
    "displacement_to_counts",
    "encode",
    "encode_samples",
    "frames_to_readings",
]
