"""The binary frame: CRC, layout, encoder, and the decoder under any chunking and garbage."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ballbar.protocol import Status
from ballbar.protocol.binary import (
    CLOCK_WRAP_S,
    FRAME_DTYPE,
    FRAME_SIZE,
    SYNC,
    BinaryDecoder,
    crc16,
    crc16_rows,
    decode,
    displacement_to_counts,
    encode,
    encode_samples,
)

U32 = st.integers(0, 2**32 - 1)
I32 = st.integers(-(2**31), 2**31 - 1)
FIELDS = st.tuples(U32, U32, I32, st.integers(0, 255))


def frame(seq: int, clock: int = 0, value: int = 0, status: int = 0) -> bytes:
    return encode(seq, clock, value, status)


def fields_of(frames: np.ndarray) -> list[tuple[int, int, int, int]]:
    return list(
        zip(
            frames["seq"].tolist(),
            frames["clock_us"].tolist(),
            frames["value"].tolist(),
            frames["status"].tolist(),
            strict=True,
        )
    )


def feed_chunked(data: bytes, cuts: list[int]) -> tuple[BinaryDecoder, list[tuple[int, int, int, int]]]:
    dec = BinaryDecoder()
    out: list[tuple[int, int, int, int]] = []
    prev = 0
    for c in [*sorted(set(cuts)), len(data)]:
        if c < prev or c > len(data):
            continue
        out += fields_of(dec.feed_frames(data[prev:c]))
        prev = c
    return dec, out


# ----------------------------------------------------------------------------- CRC and layout


def test_crc_reference_value() -> None:
    # The catalogue check value of CRC-16/CCITT-FALSE.
    assert crc16(b"123456789") == 0x29B1


def test_vectorised_crc_matches_reference() -> None:
    rows = np.random.default_rng(7).integers(0, 256, (500, 15), dtype=np.uint8)
    assert crc16_rows(rows).tolist() == [crc16(r.tobytes()) for r in rows]


def test_layout_matches_struct_and_readme_example() -> None:
    # protocol/README.md documents exactly this frame.
    data = frame(seq=1, clock=1000, value=-123456, status=int(Status.OVER_RANGE))
    assert data.hex(" ") == "a5 5a 01 00 00 00 e8 03 00 00 c0 1d fe ff 01 00 5b"
    sync, seq, clock, value, status, crc = struct.unpack("<2sIIiBH", data)
    assert (sync, seq, clock, value, status) == (SYNC, 1, 1000, -123456, 1)
    assert crc == crc16(data[:15])
    assert FRAME_DTYPE.itemsize == FRAME_SIZE == len(data)


def test_encode_samples_units_and_wrap() -> None:
    data = encode_samples([0, 2**32 + 5], [0.5, CLOCK_WRAP_S + 0.25], [0.0123456, -1.5], 0)
    fr = decode(data).frames
    assert fr["seq"].tolist() == [0, 5]
    assert fr["clock_us"].tolist() == [500_000, 250_000]
    assert fr["value"].tolist() == [1235, -150_000]  # 10 nm counts, rounded


def test_displacement_clamps_and_flags_over_range() -> None:
    counts, status = displacement_to_counts([0.0, 1e9, -1e9, np.nan])
    assert counts.tolist() == [0, 2**31 - 1, -(2**31), 0]
    assert status.tolist() == [0, 1, 1, 1]


# ----------------------------------------------------------------------------- decoder cases

F1, F2, F3 = frame(1, 10, 100), frame(2, 20, -200), frame(3, 30, 300, 2)
BAD = F2[:9] + bytes([F2[9] ^ 0x10]) + F2[10:]  # one bit flipped in the clock
SYNC_IN_PAYLOAD = frame(0xA55A, 0x5AA5A55A, 0x5AA5A55A)  # sync words inside fields


@pytest.mark.parametrize(
    ("data", "seqs", "consumed", "bad_crc", "skipped"),
    [
        pytest.param(b"", [], 0, 0, 0, id="empty"),
        pytest.param(b"\xa5", [], 0, 0, 0, id="half-sync-waits"),
        pytest.param(b"\x00\xa5", [], 1, 0, 1, id="garbage-then-half-sync"),
        pytest.param(b"hello", [], 5, 0, 5, id="garbage-only"),
        pytest.param(F1[:10], [], 0, 0, 0, id="incomplete-frame-waits"),
        pytest.param(F1 + F2 + F3, [1, 2, 3], 51, 0, 0, id="clean"),
        pytest.param(b"xyz" + F1 + b"\x00" + F2, [1, 2], 38, 0, 4, id="garbage-between"),
        pytest.param(F1 + BAD + F3, [1, 3], 51, 1, 17, id="bad-crc-in-middle"),
        pytest.param(F1[:8] + F2, [2], 25, 1, 8, id="truncated-frame-resync"),
        pytest.param(F1 + F2[:5], [1], 17, 0, 0, id="tail-waits-for-more"),
        pytest.param(SYNC_IN_PAYLOAD + F1, [0xA55A, 1], 34, 0, 0, id="sync-in-payload-not-counted"),
        pytest.param(SYNC + SYNC + F1, [1], 21, 2, 4, id="false-syncs"),
        pytest.param(BAD, [], 17, 1, 17, id="bad-crc-alone"),
    ],
)
def test_decode_cases(data: bytes, seqs: list[int], consumed: int, bad_crc: int, skipped: int) -> None:
    res = decode(data)
    assert res.frames["seq"].tolist() == seqs
    assert res.consumed == consumed
    assert res.dropped == {"bad_crc": bad_crc, "skipped_bytes": skipped}


def test_final_drops_the_incomplete_tail() -> None:
    res = decode(F1 + F2[:5], final=True)
    assert res.consumed == 22
    assert res.dropped["skipped_bytes"] == 5
    dec = BinaryDecoder()
    dec.feed(F1 + F2[:5])
    assert dec.pending == 5
    assert len(dec.flush()) == 0
    assert dec.dropped["skipped_bytes"] == 5 and dec.pending == 0


def test_readings_units() -> None:
    dec = BinaryDecoder()
    r = dec.feed(frame(7, 2_500_000, 123_456, 2))
    assert r.value_mm.tolist() == [1.23456]
    assert r.seq is not None and r.seq.tolist() == [7]
    assert r.clock_s is not None and r.clock_s.tolist() == [2.5]
    assert r.status.tolist() == [2]


def test_large_buffer_is_decoded_in_one_call() -> None:
    n = 200_000
    seq = np.arange(n)
    data = encode(seq, seq * 100, seq - n // 2, seq % 4)
    res = decode(data)
    assert res.consumed == len(data)
    assert np.array_equal(res.frames["seq"], seq)
    assert np.array_equal(res.frames["value"], seq - n // 2)


# ----------------------------------------------------------------------------- properties


@settings(deadline=None)
@given(st.lists(FIELDS, max_size=40), st.lists(st.integers(0, 800), max_size=30))
def test_roundtrip_any_chunking(fields: list[tuple[int, int, int, int]], cuts: list[int]) -> None:
    data = b"".join(frame(*f) for f in fields)
    dec, out = feed_chunked(data, cuts)
    assert out == fields
    assert dec.dropped == {"bad_crc": 0, "skipped_bytes": 0}
    assert dec.pending == 0


NO_SYNC = st.binary(max_size=40).map(lambda b: b.replace(b"\xa5", b"\x00"))


@settings(deadline=None)
@given(st.lists(st.tuples(NO_SYNC, FIELDS), max_size=30), NO_SYNC, st.lists(st.integers(0, 1500), max_size=30))
def test_garbage_between_frames_is_skipped_and_counted(
    parts: list[tuple[bytes, tuple[int, int, int, int]]], trailer: bytes, cuts: list[int]
) -> None:
    data = b"".join(g + frame(*f) for g, f in parts) + trailer
    dec, out = feed_chunked(data, cuts)
    dec.flush()
    assert out == [f for _, f in parts]
    assert dec.dropped == {"bad_crc": 0, "skipped_bytes": sum(len(g) for g, _ in parts) + len(trailer)}


@settings(deadline=None)
@given(
    st.lists(st.tuples(FIELDS, st.booleans(), st.integers(2, FRAME_SIZE - 1), st.integers(0, 7)), max_size=40),
    st.lists(st.integers(0, 800), max_size=20),
)
def test_corrupted_frames_are_dropped_and_counted(
    spec: list[tuple[tuple[int, int, int, int], bool, int, int]], cuts: list[int]
) -> None:
    chunks = []
    for f, corrupt, byte, bit in spec:
        data = bytearray(frame(*f))
        if corrupt:
            data[byte] ^= 1 << bit
        chunks.append(bytes(data))
    dec, out = feed_chunked(b"".join(chunks), cuts)
    dec.flush()
    n_bad = sum(1 for s in spec if s[1])
    assert out == [s[0] for s in spec if not s[1]]
    assert dec.dropped["skipped_bytes"] == FRAME_SIZE * n_bad
    # Each corrupted frame costs one CRC failure; a sync word that the corruption
    # uncovers inside it could add one, never fewer.
    assert dec.dropped["bad_crc"] >= n_bad


@settings(deadline=None, max_examples=300)
@given(st.binary(max_size=600), st.lists(st.integers(0, 600), max_size=40))
def test_any_bytes_never_raise_and_chunking_does_not_matter(data: bytes, cuts: list[int]) -> None:
    whole = decode(data, final=True)
    dec, out = feed_chunked(data, cuts)
    out += fields_of(decode(b"", final=True).frames)
    dec.flush()
    assert out == fields_of(whole.frames)
    assert dec.dropped == whole.dropped
    assert FRAME_SIZE * len(out) + dec.dropped["skipped_bytes"] == len(data)


@settings(deadline=None)
@given(st.lists(st.sampled_from([F1, F2, F3, BAD, SYNC, b"\xa5", b"\x5a", b"\x00"]), max_size=40), st.data())
def test_adversarial_pieces_chunking_invariant(pieces: list[bytes], data: st.DataObject) -> None:
    blob = b"".join(pieces)
    cuts = data.draw(st.lists(st.integers(0, len(blob)), max_size=20))
    whole = decode(blob, final=True)
    dec, out = feed_chunked(blob, cuts)
    dec.flush()
    assert out == fields_of(whole.frames)
    assert dec.dropped == whole.dropped
    # No fragment can complete a frame or hide one: the intact frames all survive.
    intact = {F1: (1, 10, 100, 0), F2: (2, 20, -200, 0), F3: (3, 30, 300, 2)}
    assert out == [intact[p] for p in pieces if p in intact]


@settings(deadline=None, max_examples=300)
@given(
    st.lists(st.sampled_from([F1, F2, F3, F1 + F2 + F3, BAD, SYNC, b"\xa5", b"\x5a", b"\x00", F1[:9]]), max_size=12),
    st.booleans(),
)
def test_the_clean_run_shortcut_decodes_as_the_general_walk(pieces: list[bytes], final: bool) -> None:
    from ballbar.protocol import binary

    blob = b"".join(pieces)
    fast = decode(blob, final=final)
    binary._SHORTCUT = False
    try:
        slow = decode(blob, final=final)
    finally:
        binary._SHORTCUT = True
    assert fast.consumed == slow.consumed and fast.dropped == slow.dropped
    assert fields_of(fast.frames) == fields_of(slow.frames)
