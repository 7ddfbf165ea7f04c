"""Gauge profiles: the documented example lines, error words, any chunking, bad and cut lines counted, the
link budget; the profiles are formats of the ASCII decoder (``protocol/gauges.py``)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_protocol_ascii import assert_parsers_agree, feed_chunked, same

from ballbar.protocol import Status
from ballbar.protocol.ascii import AsciiDecoder, AsciiFormat, decode, encode
from ballbar.protocol.gauges import PROFILES

MIT = PROFILES["mitutoyo"].fmt
SYL = PROFILES["sylvac"].fmt
TESA = PROFILES["tesa"].fmt
MIT_IN = AsciiFormat(**{**MIT.__dict__, "unit": "in"})
OVER, FAULT = int(Status.OVER_RANGE), int(Status.SENSOR_FAULT)


def read(data: bytes, fmt: AsciiFormat) -> tuple[list[float], list[int], dict[str, int]]:
    res = decode(data, fmt, final=True)
    return res.readings.value_mm.tolist(), res.readings.status.tolist(), res.dropped


@pytest.mark.parametrize(
    ("fmt", "line", "value_mm", "status"),
    [
        # Mitutoyo Digimatic data output: D1 code, D2 channel, D3 item, D4 sign, D5..D12 data, D13 CR.
        (MIT, b"01A+0000.123\r", 0.123, 0),
        (MIT, b"01A-0012.345\r", -12.345, 0),
        (MIT, b"03A+000.0001\r", 0.0001, 0),
        (MIT_IN, b"01A+00.12345\r", 0.12345 * 25.4, 0),  # inch
        (MIT_IN, b"01A+000.1234\r", 0.1234 * 25.4, 0),
        # Sylvac: [sign | digits "." decimals | CR], the sign "+", "-" or a space.
        (SYL, b"+12.345\r", 12.345, 0),
        (SYL, b"-0.0012\r", -0.0012, 0),
        (SYL, b" 1.2345\r", 1.2345, 0),
        (SYL, b"ERR3\r", math.nan, OVER),
        (SYL, b"ERR0\r", math.nan, FAULT),
        (SYL, b"ERR5\r", math.nan, FAULT),  # an error word not listed: not a measurement
        # TESA TT80/TT90: a signed number, CR LF; ERR<n>.
        (TESA, b"+1.23456\r\n", 1.23456, 0),
        (TESA, b"-0.00120\r\n", -0.0012, 0),
        (TESA, b"ERR23\r\n", math.nan, FAULT),
    ],
)
def test_documented_lines(fmt: AsciiFormat, line: bytes, value_mm: float, status: int) -> None:
    vals, stats, dropped = read(line, fmt)
    assert same(vals, [value_mm]) or (not math.isnan(value_mm) and vals == pytest.approx([value_mm], abs=1e-12))
    assert stats == [status]
    assert dropped["bad_line"] == 0
    # The same line among many (the vectorised path) gives the same.
    vals, stats, _ = read(line * 40, fmt)
    assert len(vals) == 40 and stats == [status] * 40


@pytest.mark.parametrize(
    ("fmt", "line"),
    [
        (MIT, b"+0000.123\r"),  # no header
        (MIT, b"0AA+0000.123\r"),  # the channel a letter... allowed? no: D2 is a digit
        (MIT, b"01a+0000.123\r"),  # the item lower case
        (MIT, b"01A\r"),  # a header and nothing
        (MIT, b"01A+00#0.123\r"),  # a damaged digit
        (SYL, b"+1.2.3\r"),
        (SYL, b"ERRX\r"),
        (TESA, b"+1.23456 um\r\n"),  # another unit than the configured one: bad_unit, never converted
    ],
)
def test_bad_lines_are_counted(fmt: AsciiFormat, line: bytes) -> None:
    good = encode([0.5], fmt, prefix=PROFILES["mitutoyo"].prefix if fmt.header else "")
    for n in (1, 30):  # the few-line and the vectorised paths
        vals, _, dropped = read((line + good) * n, fmt)
        assert vals == [0.5] * n
        assert dropped["bad_line"] + dropped["bad_unit"] == n
        assert dropped["skipped_bytes"] == n * len(line.rstrip(b"\r\n"))


def test_a_cut_answer_is_never_parsed() -> None:
    dec = AsciiDecoder(MIT)
    assert len(dec.feed(b"01A+0000.1")) == 0  # cut: no CR
    assert dec.pending == 10
    dec.discard()
    assert dec.dropped["skipped_bytes"] == 10
    assert dec.feed(b"01A+0000.123\r").value_mm.tolist() == [0.123]


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_encoded_answers_are_the_profiles_length(name: str) -> None:
    """The link budget's answer length is what the (simulated) device writes, at the profile's width."""
    p = PROFILES[name]
    lines = encode([-2.5, 0.0, 2.5], p.fmt, prefix=p.prefix)
    assert {len(x) + len(p.fmt.eol) for x in lines.split(p.fmt.eol) if x} == {p.answer_bytes}


def test_link_budget_and_rate_refusal() -> None:
    mit = PROFILES["mitutoyo"]
    # 1 request + 13 answer bytes of 10 bits at 9600 baud: 14.58 ms, about 68.6 Hz.
    assert mit.line_time_s() == pytest.approx(14 * 10 / 9600)
    assert 65 < mit.max_rate_hz() < 70
    assert mit.check_rate(15.625) is None
    why = mit.check_rate(100.0)
    assert why is not None and "9600 baud" in why and "68.6 Hz" in why
    assert mit.check_rate(100.0, baud=115200) is None
    syl = PROFILES["sylvac"]
    assert syl.bits_per_char == 11  # 7E2
    assert syl.max_rate_hz() == pytest.approx(4800 / ((2 + 9) * 11))
    assert syl.max_rate_hz(polled=False) > syl.max_rate_hz()


def test_header_only_in_formats_without_timestamps() -> None:
    with pytest.raises(ValueError, match="header"):
        AsciiFormat(header="99A", ts_unit="s")
    with pytest.raises(ValueError, match="header"):
        AsciiFormat(header="99Z")
    with pytest.raises(ValueError, match="error word"):
        AsciiFormat(errors=(("3ERR", 1),))


PROFILE_FMTS = st.sampled_from([(MIT, "01A"), (MIT_IN, "02A"), (SYL, ""), (TESA, "")])


@settings(deadline=None)
@given(PROFILE_FMTS, st.lists(st.tuples(st.floats(-2.5, 2.5), st.sampled_from([0, 0, 0, OVER, FAULT])), max_size=30),
       st.lists(st.integers(0, 600), max_size=20))
def test_roundtrip_any_chunking(fmt_prefix: tuple[AsciiFormat, str], rows: list[tuple[float, int]],
                                cuts: list[int]) -> None:
    fmt, prefix = fmt_prefix
    v = np.array([r[0] for r in rows])
    status = np.array([r[1] for r in rows], np.int64)
    if not (fmt.errors or fmt.error_prefix):
        status[:] = 0  # a Mitutoyo answer has no error word
    data = encode(v, fmt, status=status, prefix=prefix)
    dec = AsciiDecoder(fmt)
    vals, _, stat = feed_chunked(dec, data, cuts)
    expected = [float(f"{x:+.{fmt.digits}f}") * fmt.mm_per_count for x in (v / fmt.mm_per_count).tolist()]
    expected = [math.nan if s else x for x, s in zip(expected, status.tolist(), strict=True)]
    # Sylvac writes ERR3 and ERR0; the simulated TESA the generic OVER and ERR.
    assert same(vals, expected) and stat == status.tolist()
    assert dec.dropped == {"bad_line": 0, "long_line": 0, "bad_unit": 0, "skipped_bytes": 0}


PIECES = [b"01A", b"0", b"9", b"+", b"-", b" ", b".", b"ERR", b"3", b"0", b"A", b"#", b"\x00", b"12345", b"mm"]


@settings(deadline=None, max_examples=300)
@given(PROFILE_FMTS, st.binary(max_size=300) | st.lists(st.sampled_from([*PIECES, b"\r", b"\n"]), max_size=60).map(
    b"".join), st.lists(st.integers(0, 300), max_size=30))
def test_any_bytes_never_raise_and_chunking_does_not_matter(fmt_prefix: tuple[AsciiFormat, str], data: bytes,
                                                            cuts: list[int]) -> None:
    fmt = fmt_prefix[0]
    whole = decode(data, fmt, final=True)
    dec = AsciiDecoder(fmt)
    vals, _, stat = feed_chunked(dec, data, cuts)
    assert same(vals, whole.readings.value_mm.tolist()) and stat == whole.readings.status.tolist()
    assert dec.dropped == whole.dropped


@settings(deadline=None, max_examples=300)
@given(PROFILE_FMTS, st.lists(st.lists(st.sampled_from(PIECES), max_size=6).map(b"".join), min_size=1, max_size=12))
def test_the_few_line_parser_agrees_with_the_vectorised_one(fmt_prefix: tuple[AsciiFormat, str],
                                                            lines: list[bytes]) -> None:
    assert_parsers_agree(fmt_prefix[0], lines)
