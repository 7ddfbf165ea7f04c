"""The ASCII line protocol: grammar, units, faults, and the decoder under any chunking and garbage."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ballbar.protocol import Status
from ballbar.protocol.ascii import AsciiDecoder, AsciiFormat, decode, encode

MM = AsciiFormat()
TS = AsciiFormat(ts_unit="s")


def values(data: bytes, fmt: AsciiFormat = MM) -> list[float]:
    return decode(data, fmt, final=True).readings.value_mm.tolist()


def same(a: list[float], b: list[float]) -> bool:
    return len(a) == len(b) and all((x == y) or (math.isnan(x) and math.isnan(y)) for x, y in zip(a, b, strict=True))


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        (b"+0.01234\r\n", 0.01234),
        (b"-0.01234\n", -0.01234),
        (b"12\r", 12.0),
        (b"  1.5  \n", 1.5),
        (b".5\n", 0.5),
        (b"-.5\n", -0.5),
        (b"1.\n", 1.0),
        (b"0.00001\n", 1e-5),
        (b"1.5 mm\n", 1.5),
        (b"1.5mm\n", 1.5),
        (b"1.5\tMM\n", 1.5),
        (b"123456789012345\n", 123456789012345.0),
        (b"-0.000000000000001\n", -1e-15),
    ],
)
def test_good_lines(line: bytes, expected: float) -> None:
    assert values(line) == [expected]


@pytest.mark.parametrize(
    ("line", "reason"),
    [
        (b"abc\n", "bad_line"),
        (b"1.2.3\n", "bad_line"),
        (b"1-2\n", "bad_line"),
        (b"+\n", "bad_line"),
        (b".\n", "bad_line"),
        (b"1e-3\n", "bad_line"),
        (b"3,5\n", "bad_line"),  # a decimal comma is two fields
        (b"1.5 mm 2\n", "bad_line"),
        (b"12345678901234567\n", "bad_line"),  # 17 digits: more than a double holds exactly
        (b"1.5 um\n", "bad_unit"),
        (b"1.5 inch\n", "bad_unit"),
        (b"\x00\xff1.5\n", "bad_line"),
        (b"9" * 70 + b"\n", "long_line"),
    ],
)
def test_bad_lines_are_counted_by_reason(line: bytes, reason: str) -> None:
    res = decode(line + b"2.5\n", MM)
    assert res.readings.value_mm.tolist() == [2.5]
    assert res.dropped[reason] == 1
    assert res.dropped["skipped_bytes"] == len(line.rstrip(b"\r\n"))
    assert sum(v for k, v in res.dropped.items() if k != "skipped_bytes") == 1


def test_blank_lines_and_crlf_are_not_errors() -> None:
    res = decode(b"\r\n\n  \r1\r\n\r\n2\n", MM)
    assert res.readings.value_mm.tolist() == [1.0, 2.0]
    assert res.dropped == {"bad_line": 0, "long_line": 0, "bad_unit": 0, "skipped_bytes": 0}


def test_fault_words_give_nan_and_status() -> None:
    res = decode(b"OVER\n-OL\nerr\nFault\n1\n", MM)
    assert same(res.readings.value_mm.tolist(), [math.nan] * 4 + [1.0])
    over, fault = int(Status.OVER_RANGE), int(Status.SENSOR_FAULT)
    assert res.readings.status.tolist() == [over, over, fault, fault, 0]


@pytest.mark.parametrize(
    ("fmt", "line", "value_mm", "t_s"),
    [
        (AsciiFormat(unit="um"), b"12.34\n", 0.01234, None),
        (AsciiFormat(unit="um"), "12.5 µm\n".encode(), 0.0125, None),
        (AsciiFormat(unit="um"), "12.5µm\n".encode("latin-1"), 0.0125, None),
        (AsciiFormat(unit="in"), b"0.1 in\n", 2.54, None),
        (AsciiFormat(unit="nm", scale=-10.0), b"123\n", -0.00123, None),
        (AsciiFormat(ts_unit="s"), b"12.5, +0.001\n", 0.001, 12.5),
        (AsciiFormat(ts_unit="ms"), b"12500;-0.001\n", -0.001, 12.5),
        (AsciiFormat(ts_unit="us", unit="um"), b"1500000\t3.25 um\n", 0.00325, 1.5),
        (AsciiFormat(ts_unit="s"), b"7 OVER\n", math.nan, 7.0),
    ],
)
def test_units_scale_and_timestamps(fmt: AsciiFormat, line: bytes, value_mm: float, t_s: float | None) -> None:
    res = decode(line, fmt)
    assert len(res.readings) == 1, res.dropped
    got = res.readings.value_mm[0]
    assert (math.isnan(got) and math.isnan(value_mm)) or got == pytest.approx(value_mm, rel=1e-15)
    if t_s is None:
        assert res.readings.clock_s is None
    else:
        assert res.readings.clock_s is not None and res.readings.clock_s.tolist() == [pytest.approx(t_s)]


def test_timestamped_format_rejects_lines_without_timestamp() -> None:
    res = decode(b"1.5\n-1 2\nERR\n3 4\n", TS)
    assert res.readings.value_mm.tolist() == [4.0]
    assert res.dropped["bad_line"] == 3


def test_long_line_split_across_chunks_is_counted_once() -> None:
    dec = AsciiDecoder(AsciiFormat(max_line=16))
    assert len(dec.feed(b"1\n" + b"7" * 10)) == 1
    assert len(dec.feed(b"7" * 10)) == 0  # now 20 bytes without an end: dropped
    assert dec.pending == 0
    assert len(dec.feed(b"7" * 100)) == 0
    assert dec.feed(b"77\n2\n").value_mm.tolist() == [2.0]
    assert dec.dropped["long_line"] == 1
    assert dec.dropped["skipped_bytes"] == 122


def test_encoder_formats() -> None:
    fmt = AsciiFormat(ts_unit="ms", unit="um", unit_suffix=True, separator=",", eol=b"\n")
    assert encode([0.0123456, -1.0], fmt, t_s=[0.5, 1.25]) == b"500.000,+12.35 um\n1250.000,-1000.00 um\n"
    st_ = [int(Status.OVER_RANGE), int(Status.SENSOR_FAULT)]
    assert encode([1.0, 2.0], MM, status=st_) == b"OVER\r\nERR\r\n"


def test_large_input_vectorised() -> None:
    n = 100_000
    v = np.random.default_rng(3).normal(0, 0.3, n)
    data = encode(v, TS, t_s=np.arange(n) * 1e-3)
    res = decode(data, TS)
    assert res.consumed == len(data)
    expected = np.array([float(f"{x:+.5f}") for x in v])
    assert np.array_equal(res.readings.value_mm, expected)


# ----------------------------------------------------------------------------- properties

FORMATS = st.builds(
    AsciiFormat,
    unit=st.sampled_from(["mm", "um", "nm", "in"]),
    scale=st.sampled_from([1.0, -1.0, 0.5, 10.0]),
    ts_unit=st.sampled_from([None, "s", "ms", "us"]),
    unit_suffix=st.booleans(),
    width=st.sampled_from([0, 12]),
    ts_width=st.sampled_from([0, 14]),
    separator=st.sampled_from([" ", ",", "\t", "; "]),
    eol=st.sampled_from([b"\r\n", b"\n", b"\r"]),
)
VALUES = st.floats(-25.0, 25.0, allow_nan=False)


def feed_chunked(dec: AsciiDecoder, data: bytes, cuts: list[int]) -> tuple[list[float], list[float], list[int]]:
    vals: list[float] = []
    ts: list[float] = []
    stat: list[int] = []
    prev = 0
    for c in [*sorted(set(cuts)), len(data)]:
        if c < prev or c > len(data):
            continue
        for r in (dec.feed(data[prev:c]),):
            vals += r.value_mm.tolist()
            ts += [] if r.clock_s is None else r.clock_s.tolist()
            stat += r.status.tolist()
        prev = c
    r = dec.flush()
    vals += r.value_mm.tolist()
    ts += [] if r.clock_s is None else r.clock_s.tolist()
    stat += r.status.tolist()
    return vals, ts, stat


@settings(deadline=None)
@given(FORMATS, st.lists(st.tuples(VALUES, st.floats(0, 1e5)), max_size=30), st.lists(st.integers(0, 900), max_size=20))
def test_roundtrip_any_format_any_chunking(fmt: AsciiFormat, rows: list[tuple[float, float]], cuts: list[int]) -> None:
    v = np.array([r[0] for r in rows])
    t = np.sort(np.array([r[1] for r in rows]))
    data = encode(v, fmt, t_s=t if fmt.ts_unit else None)
    dec = AsciiDecoder(fmt)
    vals, ts, stat = feed_chunked(dec, data, cuts)
    # What decodes is exactly what the text says, in the format's units.
    expected = [float(f"{x:+.{fmt.digits}f}") * fmt.mm_per_count for x in (v / fmt.mm_per_count).tolist()]
    assert vals == expected
    assert stat == [0] * len(rows)
    if fmt.ts_unit:
        td = {"s": 6, "ms": 3, "us": 0}[fmt.ts_unit]
        f = {"s": 1.0, "ms": 1e-3, "us": 1e-6}[fmt.ts_unit]
        assert ts == [float(f"{x / f:.{td}f}") * f for x in t.tolist()]
    assert dec.dropped == {"bad_line": 0, "long_line": 0, "bad_unit": 0, "skipped_bytes": 0}


@given(st.from_regex(rb"\A[+-]?[0-9]{1,7}(\.[0-9]{0,8})?\Z"))
def test_numbers_parse_like_python_float(token: bytes) -> None:
    assert values(token + b"\n") == [float(token)]


@settings(deadline=None, max_examples=300)
@given(
    st.sampled_from([MM, TS, AsciiFormat(unit="um", max_line=12)]),
    st.binary(max_size=400)
    | st.lists(
        st.sampled_from([b"1.5", b"\n", b"\r", b" ", b"mm", b"OVER", b"-", b".", b"x", b"9" * 20]), max_size=60
    ).map(b"".join),
    st.lists(st.integers(0, 400), max_size=30),
)
def test_any_bytes_never_raise_and_chunking_does_not_matter(fmt: AsciiFormat, data: bytes, cuts: list[int]) -> None:
    whole = decode(data, fmt, final=True)
    dec = AsciiDecoder(fmt)
    vals, ts, stat = feed_chunked(dec, data, cuts)
    assert same(vals, whole.readings.value_mm.tolist())
    assert stat == whole.readings.status.tolist()
    assert ts == ([] if whole.readings.clock_s is None else whole.readings.clock_s.tolist())
    assert dec.dropped == whole.dropped
    assert dec.pending == 0


@pytest.mark.parametrize(
    ("stream", "kept", "skipped"),
    [
        (b"2345\r\n+0.12346\r\n+0.12347\r\n", [0.12346, 0.12347], 4),  # joined mid-line
        (b"+0.12345\r\n+0.12346\r\n", [0.12345, 0.12346], 0),  # joined at a line start
        (b"\n+0.12345\r\n+0.12346\r\n", [0.12345, 0.12346], 0),  # joined between CR and LF
        (b"45 mm\r\n+0.12346 mm\r\n", [0.12346], 5),
    ],
)
def test_rejoined_stream_drops_a_leading_line_tail(stream: bytes, kept: list[float], skipped: int) -> None:
    for chunk in (len(stream), 1, 3):
        dec = AsciiDecoder(MM)
        dec.discard(rejoin=True)
        got: list[float] = []
        for i in range(0, len(stream), chunk):
            got += dec.feed(stream[i : i + chunk]).value_mm.tolist()
        assert got == kept
        assert dec.dropped["skipped_bytes"] == skipped


def test_discard_drops_a_cut_line_instead_of_parsing_it() -> None:
    dec = AsciiDecoder(MM)
    assert dec.feed(b"+0.1\r\n+0.12").value_mm.tolist() == [0.1]
    dec.discard()
    assert dec.pending == 0 and dec.dropped["skipped_bytes"] == 5
    assert len(dec.flush()) == 0


PIECES = [b"0", b"1", b"9", b"12", b".", b"+", b"-", b" ", b",", b"\t", b";", b"mm", b"MM", b"um", "µm".encode()]
PIECES += [b"\xb5m", b"in", b"x", b"OVER", b"err", b"\x00", b"#", b"12345678901234567", b"0.000000001"]


@settings(deadline=None, max_examples=300)
@given(
    st.sampled_from([MM, TS, AsciiFormat(unit="um"), AsciiFormat(unit="in", ts_unit="ms")]),
    st.lists(st.lists(st.sampled_from(PIECES), max_size=8).map(b"".join), min_size=1, max_size=12),
)
def test_the_few_line_parser_agrees_with_the_vectorised_one(fmt: AsciiFormat, lines: list[bytes]) -> None:
    assert_parsers_agree(fmt, lines)


def assert_parsers_agree(fmt: AsciiFormat, lines: list[bytes]) -> None:
    """The few-line parser and the vectorised one give the same values, times, status and drops for ``lines``."""
    from ballbar.protocol.ascii import _parse_block, _parse_lines

    lines = [ln for ln in lines if ln] or [b"1"]
    buf = b"".join(ln + b"\n" for ln in lines)
    lens = np.array([len(ln) for ln in lines])
    starts = np.concatenate(([0], np.cumsum(lens + 1)[:-1]))
    padded = np.frombuffer(buf + bytes(int(lens.max())), np.uint8)
    a = _parse_block(padded, starts, lens, fmt)
    b = _parse_lines(lines, fmt)
    assert same(a[0].tolist(), b[0].tolist()) and same(a[1].tolist(), b[1].tolist())
    assert a[2].tolist() == b[2].tolist() and a[3] == b[3]
