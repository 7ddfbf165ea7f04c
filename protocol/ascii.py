"""The ASCII line protocol of plain gauge interfaces: one reading per line.

Grammar (bytes, see ``protocol/README.md``)::

    line      = [timestamp sep] [header] reading [sp unit] eol
    timestamp = digits ["." digits]               device time, in the format's ts_unit
    header    = the format's fixed prefix, by its template (a gauge's "01A": code, channel, item)
    reading   = ["+" | "-"] digits ["." digits]   or ["+" | "-"] "." digits
              | fault word                        OVER, OL, +OL, -OL (over range);
                                                  ERR, ERROR, FAULT (sensor fault);
                                                  the format's own error words (ERR3, ERR0, ...)
    unit      = the configured unit's name: mm, um (also µm in UTF-8 or Latin-1), nm, in
                (letters in any case); when present it must be the configured one
    sep, sp   = one or more of space, tab, "," or ";"  (sp may be empty before a unit)
    eol       = CR, LF or CR LF; empty lines are ignored

No exponent; the digits of a number, read without its point, must stay below
2**53 (15 significant digits always do), so that the value is exact.  The
reading times the format's ``scale`` and unit gives millimetres.  The same
decoder reads streamed lines and the answers to polled requests; in polled
mode the host sends :attr:`AsciiFormat.request` once per sample.  The
device profiles of :mod:`.gauges` (Mitutoyo, Sylvac, TESA) are formats of this
decoder: a header template and error words are data, checked with the same
whole-matrix operations (the header) or on the slow path of lines that are not
a plain reading (the error words).

Decoding is vectorised: line ends are found with numpy, the lines become the
columns of a (character position, line) byte matrix, and tokens and numbers are
found with whole-matrix operations and reductions down the columns: each digit
times ten to the number of digits after it, summed exactly in float64 and
divided once by the power of ten of the fraction, which is the same correctly
rounded double that ``float()`` gives.  Only lines that fail that fast path are
looked at one by one (fault words, errors).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._common import (
    BAD_LINE,
    BAD_UNIT,
    LONG_LINE,
    SKIPPED_BYTES,
    Readings,
    Status,
    add_counts,
)

Unit = Literal["mm", "um", "nm", "in"]
TsUnit = Literal["s", "ms", "us"]

UNIT_MM: dict[str, float] = {"mm": 1.0, "um": 1e-3, "nm": 1e-6, "in": 25.4}
TS_S: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
#: Default digits after the point when encoding: 0.01 um resolution.
DEFAULT_DECIMALS: dict[str, int] = {"mm": 5, "um": 2, "nm": 0, "in": 7}
_UNIT_SPELLINGS: dict[str, tuple[bytes, ...]] = {
    "mm": (b"mm",),
    "um": (b"um", "µm".encode(), "µm".encode("latin-1")),
    "nm": (b"nm",),
    "in": (b"in",),
}
INVALID_BITS = Status.OVER_RANGE | Status.SENSOR_FAULT
FAULT_WORDS: dict[str, int] = {
    "OVER": int(Status.OVER_RANGE),
    "OL": int(Status.OVER_RANGE),
    "+OL": int(Status.OVER_RANGE),
    "-OL": int(Status.OVER_RANGE),
    "ERR": int(Status.SENSOR_FAULT),
    "ERROR": int(Status.SENSOR_FAULT),
    "FAULT": int(Status.SENSOR_FAULT),
}
#: Header template characters: what each position of a line's fixed prefix may hold.
HEADER_CLASSES: dict[str, bytes] = {
    "9": b"0123456789",
    "A": b"ABCDEFGHIJKLMNOPQRSTUVWXYZ",
    "X": b"0123456789ABCDEFGHIJKLMNOPQRSTUVWXYZ",
}
MAX_DIGITS = 15  # significant digits that always fit a double exactly
_MAX_MANTISSA = float(2**53)  # digits without the point must stay below this to be exact
_MAX_FRAC = 22  # 10**22 is the largest exact power of ten in a double


@dataclass(frozen=True)
class AsciiFormat:
    """How a gauge writes its lines.

    Decoding uses ``unit``, ``scale``, ``ts_unit`` (``None``: the lines carry no
    timestamp) and ``max_line`` (longer lines are dropped).  Encoding also uses
    ``decimals`` (``None``: 0.01 um resolution in the unit), ``width`` and
    ``ts_width`` (minimum field widths, zero-padded: gauges write fixed-width
    lines; 0: no padding), ``unit_suffix``, ``separator`` and ``eol``.
    ``request`` is what the host sends in polled mode.

    Device profiles (:mod:`.gauges`) add: ``header``, a template of the fixed
    prefix every reading carries (``9`` a digit, ``A`` an upper-case letter, ``X``
    either; a Mitutoyo ``01A`` is ``99A``), checked and skipped; ``errors``, the
    device's own error words and the status bits each means (``("ERR3", 1)``);
    ``error_prefix``, a prefix of error words not listed (``ERR`` followed by
    digits): such a word is a ``SENSOR_FAULT`` (never a number).  Encoding (the
    simulated devices) also uses ``plus`` (the sign of a positive reading: ``+``
    or a space) and ``over_word`` and ``fault_word`` (what an over-range or
    faulty reading is written as).
    """

    unit: Unit = "mm"
    scale: float = 1.0
    ts_unit: TsUnit | None = None
    max_line: int = 64
    decimals: int | None = None
    width: int = 0
    ts_width: int = 0
    unit_suffix: bool = False
    separator: str = " "
    eol: bytes = b"\r\n"
    request: bytes = b"?\r"
    header: str = ""
    errors: tuple[tuple[str, int], ...] = ()
    error_prefix: str = ""
    plus: str = "+"
    over_word: str = "OVER"
    fault_word: str = "ERR"

    def __post_init__(self) -> None:
        if self.unit not in UNIT_MM:
            raise ValueError(f"unit must be one of {', '.join(UNIT_MM)}, not {self.unit!r}")
        if self.ts_unit is not None and self.ts_unit not in TS_S:
            raise ValueError(f"ts_unit must be one of {', '.join(TS_S)} or None, not {self.ts_unit!r}")
        if not (math.isfinite(self.scale) and self.scale != 0):
            raise ValueError(f"scale must be a finite non-zero number, not {self.scale!r}")
        if not 8 <= self.max_line <= 4096:
            raise ValueError(f"max_line must be within 8..4096, not {self.max_line!r}")
        if self.separator.strip(" \t,;") or not self.separator:
            raise ValueError(f"separator must be spaces, tabs, ',' or ';', not {self.separator!r}")
        if self.eol not in (b"\r\n", b"\n", b"\r"):
            raise ValueError(f"eol must be CR, LF or CR LF, not {self.eol!r}")
        if not self.request:
            raise ValueError("request must not be empty")
        if not (0 <= self.width <= 32 and 0 <= self.ts_width <= 32):
            raise ValueError("width and ts_width must be within 0..32")
        if len(self.header) > 16 or any(c not in HEADER_CLASSES for c in self.header):
            raise ValueError(f"header must be up to 16 of {', '.join(HEADER_CLASSES)}, not {self.header!r}")
        if self.header and self.ts_unit is not None:
            raise ValueError("a format with a header has no timestamp field")
        if self.plus not in ("+", " "):
            raise ValueError(f"plus must be '+' or ' ', not {self.plus!r}")
        for word, bits in self.errors:
            if not re.fullmatch(r"[A-Za-z]+[0-9]*", word) or bits & ~int(INVALID_BITS) or not bits:
                raise ValueError(f"error word {word!r}: letters then digits, meaning over range (1) or fault (2)")

    def error_status(self, word: str) -> int | None:
        """The status bits of a fault or error word (upper case), or ``None`` if it is not one."""
        for w, bits in self.errors:
            if w.upper() == word:
                return bits
        if word in FAULT_WORDS:
            return FAULT_WORDS[word]
        p = self.error_prefix.upper()
        if p and word.startswith(p) and word[len(p) :].isdigit():
            return int(Status.SENSOR_FAULT)
        return None

    @property
    def mm_per_count(self) -> float:
        """Millimetres per unit of the number on the line."""
        return self.scale * UNIT_MM[self.unit]

    @property
    def digits(self) -> int:
        return DEFAULT_DECIMALS[self.unit] if self.decimals is None else self.decimals

    @property
    def resolution_um(self) -> float:
        """The step of the readings the format writes: one unit of its last digit, in um."""
        return 1000.0 * abs(self.mm_per_count) * 10.0 ** -self.digits


# ----------------------------------------------------------------------------- encoder


def encode(
    value_mm: ArrayLike,
    fmt: AsciiFormat = AsciiFormat(),
    t_s: ArrayLike | None = None,
    status: ArrayLike | None = None,
    prefix: str = "",
) -> bytes:
    """Lines for readings in mm (and device times in seconds when the format has them).

    A sample with ``SENSOR_FAULT`` is written ``fault_word`` (``ERR``), one with
    ``OVER_RANGE`` ``over_word`` (``OVER``): gauges do not send a number they
    cannot vouch for.  ``prefix``: what precedes each reading (the header a
    format's template describes, e.g. ``01A``).
    """
    vals = np.atleast_1d(np.asarray(value_mm, dtype=np.float64)) / fmt.mm_per_count
    n = vals.shape[0]
    st = np.zeros(n, np.int64) if status is None else np.broadcast_to(np.asarray(status, np.int64), (n,))
    d = fmt.digits
    suffix = f" {fmt.unit}" if fmt.unit_suffix else ""
    eol = fmt.eol.decode("ascii")
    w = fmt.width
    texts = [f"{v:+0{w}.{d}f}{suffix}" for v in vals.tolist()]
    if fmt.plus != "+":
        texts = [fmt.plus + x[1:] if x[0] == "+" else x for x in texts]
    for i in np.flatnonzero(st & int(Status.OVER_RANGE) | ~np.isfinite(vals)).tolist():
        texts[i] = fmt.over_word
    for i in np.flatnonzero(st & int(Status.SENSOR_FAULT)).tolist():
        texts[i] = fmt.fault_word
    if prefix:
        texts = [prefix + x for x in texts]
    if fmt.ts_unit is not None:
        if t_s is None:
            raise ValueError("this format has timestamps: pass t_s")
        ts = np.broadcast_to(np.asarray(t_s, dtype=np.float64), (n,)) / TS_S[fmt.ts_unit]
        td = {"s": 6, "ms": 3, "us": 0}[fmt.ts_unit]
        sep = fmt.separator
        tw = fmt.ts_width
        texts = [f"{t:0{tw}.{td}f}{sep}{x}" for t, x in zip(ts.tolist(), texts, strict=True)]
    return "".join(x + eol for x in texts).encode("ascii")


# ----------------------------------------------------------------------------- decoder

# Character classes for the byte matrix.
_PAD, _DIGIT, _DOT, _SIGN, _ALPHA, _SEP, _OTHER = range(7)
_CLASS = np.full(256, _OTHER, dtype=np.uint8)
_CLASS[ord("0") : ord("9") + 1] = _DIGIT
_CLASS[ord(".")] = _DOT
_CLASS[[ord("+"), ord("-")]] = _SIGN
_CLASS[ord("a") : ord("z") + 1] = _ALPHA
_CLASS[ord("A") : ord("Z") + 1] = _ALPHA
_CLASS[[0xB5, 0xC2]] = _ALPHA  # µ in Latin-1, and UTF-8's lead byte of µ
_CLASS[[ord(" "), ord("\t"), ord(","), ord(";")]] = _SEP
_LOWER = np.arange(256, dtype=np.int64)
_LOWER[ord("A") : ord("Z") + 1] += 32
_P10 = 10.0 ** np.arange(_MAX_FRAC + 1)
_P256 = 256 ** np.arange(7, dtype=np.int64)  # packs up to 7 letters of a unit into an int64
_SMALL_BYTES = 128  # up to this many bytes (a polled answer) plain Python is faster than numpy
_BLOCK = 8192  # lines per vectorised block: temporaries stay in cache
_EOL_RE = re.compile(rb"[\r\n]")
_ALLOWED_RE = re.compile(rb"[0-9.+\-A-Za-z\xb5\xc2 \t,;]*")
_TOKEN_RE = re.compile(rb"(?P<num>[0-9.+\-]+)|[A-Za-z\xb5\xc2]+")
_LINE_RE = re.compile(rb"[^\r\n]+(?=[\r\n])")  # a complete, non-empty line
_FAULT_RE = re.compile(rb"^[ \t,;]*(?:(?P<ts>\d+(?:\.\d*)?)[ \t,;]+)?(?P<word>[+-]?[A-Za-z]+[0-9]*)[ \t,;]*$")
_HEADER_TABLE = {c: np.isin(np.arange(256), np.frombuffer(chars, np.uint8)) for c, chars in HEADER_CLASSES.items()}


def _strip_header(line: bytes, fmt: AsciiFormat) -> bytes | None:
    """The line after the format's header, or ``None`` if it does not start with one (and a reading)."""
    h = len(fmt.header)
    if not h:
        return line
    if len(line) <= h or any(line[j] not in HEADER_CLASSES[c] for j, c in enumerate(fmt.header)):
        return None
    return line[h:]


class Decoded(NamedTuple):
    """What :func:`decode` found: ``consumed`` bytes (whole lines), the readings, and
    drop counts by reason.  ``discarding``: the buffer ended inside a line that is
    already too long; feed the next call with ``skip_first=True``."""

    consumed: int
    readings: Readings
    dropped: dict[str, int]
    discarding: bool


def decode(
    buffer: bytes | bytearray | memoryview,
    fmt: AsciiFormat = AsciiFormat(),
    final: bool = False,
    skip_first: bool = False,
) -> Decoded:
    """Decode the complete lines in ``buffer``; pure, never raises for any bytes.

    ``final``: the stream ends here, the last line needs no terminator.
    ``skip_first``: the bytes up to the first line end belong to a line that was
    already counted as too long.
    """
    if len(buffer) <= _SMALL_BYTES:
        return _decode_small(bytes(buffer), fmt, final, skip_first)
    buf = np.frombuffer(buffer, dtype=np.uint8)
    n = buf.shape[0]
    dropped = {BAD_LINE: 0, LONG_LINE: 0, BAD_UNIT: 0, SKIPPED_BYTES: 0}
    eol = np.flatnonzero((buf == 10) | (buf == 13))
    ends = eol
    if final and (eol.shape[0] == 0 or eol[-1] != n - 1) and n:
        ends = np.concatenate((eol, [n]))
    consumed = n if final else (int(eol[-1]) + 1 if eol.shape[0] else 0)
    starts = np.concatenate(([0], eol + 1))[: ends.shape[0]]
    lens = ends - starts
    discarding = False
    if skip_first:
        if ends.shape[0]:
            dropped[SKIPPED_BYTES] += int(lens[0])
            starts, ends, lens = starts[1:], ends[1:], lens[1:]
        else:  # still inside the long line: drop everything, keep discarding
            dropped[SKIPPED_BYTES] += n
            return Decoded(n, _empty(fmt), dropped, not final)
    if not final:
        tail = n - consumed
        if tail > fmt.max_line:
            dropped[LONG_LINE] += 1
            dropped[SKIPPED_BYTES] += tail
            consumed, discarding = n, True
    keep = lens > 0
    starts, lens = starts[keep], lens[keep]
    long = lens > fmt.max_line
    dropped[LONG_LINE] += int(np.count_nonzero(long))
    dropped[SKIPPED_BYTES] += int(lens[long].sum())
    starts, lens = starts[~long], lens[~long]

    values: list[NDArray[np.float64]] = []
    stamps: list[NDArray[np.float64]] = []
    stats: list[NDArray[np.uint8]] = []
    if lens.shape[0]:
        padded = np.concatenate((buf, np.zeros(int(lens.max()), np.uint8)))
        for b0 in range(0, lens.shape[0], _BLOCK):
            st_b, ln_b = starts[b0 : b0 + _BLOCK], lens[b0 : b0 + _BLOCK]
            v, t, s, d = _parse_block(padded, st_b, ln_b, fmt)
            values.append(v)
            stamps.append(t)
            stats.append(s)
            add_counts(dropped, d)
    if values:
        value = np.concatenate(values)
        stamp = np.concatenate(stamps)
        status = np.concatenate(stats)
    else:
        value, stamp, status = np.empty(0), np.empty(0), np.empty(0, np.uint8)
    return Decoded(consumed, _readings(value, stamp, status, fmt), dropped, discarding)


def _decode_small(buffer: bytes, fmt: AsciiFormat, final: bool, skip_first: bool) -> Decoded:
    """:func:`decode` for a few bytes (a polled answer): the same rules, in plain Python,
    without numpy's fixed cost per call."""
    n = len(buffer)
    dropped = {BAD_LINE: 0, LONG_LINE: 0, BAD_UNIT: 0, SKIPPED_BYTES: 0}
    eol = [m.start() for m in _EOL_RE.finditer(buffer)]
    ends = [*eol, n] if final and n and (not eol or eol[-1] != n - 1) else eol
    consumed = n if final else (eol[-1] + 1 if eol else 0)
    segs = list(zip([0, *(e + 1 for e in eol)], ends, strict=False))
    discarding = False
    if skip_first:
        if not segs:
            dropped[SKIPPED_BYTES] += n
            return Decoded(n, _empty(fmt), dropped, not final)
        dropped[SKIPPED_BYTES] += segs[0][1] - segs[0][0]
        segs = segs[1:]
    if not final and n - consumed > fmt.max_line:
        dropped[LONG_LINE] += 1
        dropped[SKIPPED_BYTES] += n - consumed
        consumed, discarding = n, True
    lines = []
    for a, b in segs:
        if b - a > fmt.max_line:
            dropped[LONG_LINE] += 1
            dropped[SKIPPED_BYTES] += b - a
        elif b > a:
            lines.append(buffer[a:b])
    value, stamp, status, d = _parse_lines(lines, fmt)
    add_counts(dropped, d)
    return Decoded(consumed, _readings(value, stamp, status, fmt), dropped, discarding)


def _readings(value: np.ndarray, stamp: np.ndarray, status: np.ndarray, fmt: AsciiFormat) -> Readings:
    """Parsed counts as readings in mm, with the device clock in s where the format has one."""
    return Readings(
        value_mm=value * fmt.mm_per_count,
        status=status,
        seq=None,
        clock_s=stamp * TS_S[fmt.ts_unit] if fmt.ts_unit is not None else None,
    )


def _empty(fmt: AsciiFormat) -> Readings:
    return Readings(np.empty(0), np.empty(0, np.uint8), None, np.empty(0) if fmt.ts_unit is not None else None)


def _unit_codes(unit: str) -> list[tuple[int, int]]:
    """(length, code) of each accepted spelling; code packs the lower-cased bytes."""
    out = []
    for word in _UNIT_SPELLINGS[unit]:
        code = 0
        for ch in word.lower():
            code = code * 256 + ch
        out.append((len(word), code))
    return out


def _number(
    mat: NDArray[np.uint8],
    cls: NDArray[np.uint8],
    pos: NDArray[np.int16],
    here: NDArray[np.bool_],
    start: NDArray[np.bool_],
    signed: bool,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The number whose characters are marked ``here`` in each line (column).

    Masks are applied by multiplying (``np.where`` is several times slower here).
    """
    width = mat.shape[0]
    digit = here & (cls == _DIGIT)
    dot = here & (cls == _DOT)
    sign = here & (cls == _SIGN)
    nd = digit.sum(axis=0)
    last = (pos * digit).max(axis=0)
    dot_at = width - ((width - pos) * dot).max(axis=0)  # width: no point
    # A digit weighs ten to the number of digits after it (the point is not a digit):
    # every term is an exact integer in float64, and so is their sum below 2**53.
    exp = last - pos - ((pos < dot_at) & (dot_at < last))
    mant = ((mat - 48.0) * digit * np.take(_P10, exp, mode="clip")).sum(axis=0)
    frac = (digit & (pos > dot_at)).sum(axis=0)
    ok = (nd >= 1) & (mant < _MAX_MANTISSA) & (frac <= _MAX_FRAC) & (dot.sum(axis=0) <= 1)
    ok &= ~np.any(sign & ~start, axis=0) if signed else ~np.any(sign, axis=0)
    val = mant / np.take(_P10, frac, mode="clip")
    if signed:
        val = np.where(np.any(sign & (mat == ord("-")), axis=0), -val, val)
    return val, ok


def _parse_block(
    padded: NDArray[np.uint8], starts: NDArray[np.intp], lens: NDArray[np.intp], fmt: AsciiFormat
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.uint8], dict[str, int]]:
    """Parse lines ``padded[starts[i] : starts[i] + lens[i]]`` all at once.

    The lines are the columns of a (position, line) byte matrix; every step is a
    numpy operation over the whole matrix or a reduction down its columns, so a
    call costs a fixed few dozen numpy operations whatever the number of lines.
    """
    rows = starts.shape[0]
    width = int(lens.max())
    want = 2 if fmt.ts_unit is not None else 1
    col = np.arange(width, dtype=np.int16)[:, None]
    pos = np.repeat(col, rows, axis=1)
    mat = padded[starts[None, :] + col]
    cls = _CLASS[mat] * (col < lens[None, :])  # _PAD (0) past the end of each line
    h = len(fmt.header)
    header_bad = None
    if h:  # the fixed prefix: checked position by position, then skipped as if it were separators
        header_bad = lens <= h
        for j, kind in enumerate(fmt.header[:width]):
            header_bad |= ~_HEADER_TABLE[kind][mat[j]]
        cls[:h] = _SEP
    is_tok = (cls != _PAD) & (cls != _SEP)
    isnum = (cls >= _DIGIT) & (cls <= _SIGN)
    isalpha = cls == _ALPHA
    prev_tok = np.zeros_like(is_tok)
    prev_tok[1:] = is_tok[:-1]
    prev_num = np.zeros_like(isnum)
    prev_num[1:] = isnum[:-1]
    # A token starts after a separator, or where digits turn into letters ("0.12mm").
    start = is_tok & (~prev_tok | (isnum != prev_num))
    nstart = start & isnum
    astart = start & isalpha
    n_num = nstart.sum(axis=0)
    n_alpha = astart.sum(axis=0)
    last_num = (pos * nstart).max(axis=0)  # where the reading (the last number) starts
    first_alpha = width - ((width - pos) * astart).max(axis=0)
    any_tok = is_tok.any(axis=0)
    bad = np.any(cls == _OTHER, axis=0) | (first_alpha < last_num)  # no number after letters
    if header_bad is not None:
        bad |= header_bad
    if want == 1:
        val, ok = _number(mat, cls, pos, isnum, nstart, signed=True)
        ts = np.zeros(rows)
    else:
        val, ok = _number(mat, cls, pos, isnum & (pos >= last_num), nstart, signed=True)
        ts, t_ok = _number(mat, cls, pos, isnum & (pos < last_num), nstart, signed=False)
        ok &= t_ok
    ok &= ~bad & (n_num == want) & (n_alpha <= 1)
    unit_ok = n_alpha == 0
    if not unit_ok.all():
        alen = isalpha.sum(axis=0)
        exp = (pos * isalpha).max(axis=0) - pos
        code = (_LOWER[mat] * isalpha * np.take(_P256, exp, mode="clip")).sum(axis=0)
        for length, c in _unit_codes(fmt.unit):
            unit_ok |= (alen == length) & (code == c)
    good = ok & unit_ok
    status = np.zeros(rows, np.uint8)
    dropped = {BAD_LINE: 0, BAD_UNIT: 0, SKIPPED_BYTES: 0}
    for i in np.flatnonzero(~good & (any_tok | bad)).tolist():
        line = padded[starts[i] : starts[i] + lens[i]].tobytes()
        fault = _not_a_reading(line, bool(ok[i]), fmt, dropped)
        if fault is not None:
            good[i] = True
            val[i], ts[i], status[i] = math.nan, fault[0], fault[1]
    return val[good], ts[good], status[good], dropped


def _not_a_reading(line: bytes, number_ok: bool, fmt: AsciiFormat, dropped: dict[str, int]) -> tuple[float, int] | None:
    """A line that is not a plain reading: ``(timestamp, status)`` of a fault word, or
    ``None`` after counting why it was dropped (a wrong unit, or not the grammar)."""
    if not number_ok:
        body = _strip_header(line, fmt)
        for text in (line,) if body is None or body is line else (body, line):
            m = _FAULT_RE.match(text)
            if m is not None:
                bits = fmt.error_status(m.group("word").upper().decode())
                has_ts = m.group("ts") is not None
                if bits is not None and has_ts == (fmt.ts_unit is not None):
                    return (float(m.group("ts")) if has_ts else 0.0), bits
    dropped[BAD_UNIT if number_ok else BAD_LINE] += 1
    dropped[SKIPPED_BYTES] += len(line)
    return None


def _scalar_number(tok: bytes, signed: bool) -> float | None:
    """One number token, by the same rules as :func:`_number`."""
    neg = tok[:1] == b"-"
    body = tok[1:] if tok[:1] in (b"+", b"-") else tok
    if (body is not tok and not signed) or b"+" in body or b"-" in body or body.count(b".") > 1:
        return None
    digits = body.replace(b".", b"")
    if not digits:
        return None
    mant = int(digits)
    frac = len(body) - body.index(b".") - 1 if b"." in body else 0
    if mant >= 2**53 or frac > _MAX_FRAC:
        return None
    val = float(mant) / _P10[frac]
    return -val if neg else val


def _parse_lines(
    lines: list[bytes], fmt: AsciiFormat
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.uint8], dict[str, int]]:
    """:func:`_parse_block` for a few lines, one by one (same grammar, same results)."""
    want = 2 if fmt.ts_unit is not None else 1
    units = {w.lower() for w in _UNIT_SPELLINGS[fmt.unit]}
    vals: list[float] = []
    stamps: list[float] = []
    stats: list[int] = []
    dropped = {BAD_LINE: 0, BAD_UNIT: 0, SKIPPED_BYTES: 0}
    for line in lines:
        body = _strip_header(line, fmt)
        ok = body is not None and _ALLOWED_RE.fullmatch(body) is not None
        toks = list(_TOKEN_RE.finditer(body)) if ok and body is not None else None
        if toks is not None and not toks:
            continue  # only separators: not a line
        number_ok = unit_ok = False
        if toks is not None:
            nums = [t for t in toks if t.group("num") is not None]
            alphas = [t for t in toks if t.group("num") is None]
            if len(nums) == want and len(alphas) <= 1 and (not alphas or alphas[0].start() > nums[-1].start()):
                v = _scalar_number(nums[-1].group(), signed=True)
                t = _scalar_number(nums[0].group(), signed=False) if want == 2 else 0.0
                number_ok = v is not None and t is not None
                unit_ok = not alphas or alphas[0].group().lower() in units
                if number_ok and unit_ok:
                    assert v is not None and t is not None
                    vals.append(v)
                    stamps.append(t)
                    stats.append(0)
                    continue
        fault = _not_a_reading(line, number_ok, fmt, dropped)
        if fault is not None:
            vals.append(math.nan)
            stamps.append(fault[0])
            stats.append(fault[1])
    return np.array(vals, np.float64), np.array(stamps, np.float64), np.array(stats, np.uint8), dropped


class AsciiDecoder:
    """Streaming line decoder: feed chunks as they arrive, in any sizes.

    Keeps at most one incomplete line (``max_line`` bytes) between calls;
    ``dropped`` accumulates counts by reason and ``lines`` counts readings.
    """

    name = "ascii"
    seq_modulus: int | None = None
    clock_wrap_s: float | None = None

    def __init__(self, fmt: AsciiFormat | None = None) -> None:
        self.fmt = fmt or AsciiFormat()
        self._pending = b""
        self._discarding = False
        self._rejoin = False
        self.lines = 0
        self.dropped: dict[str, int] = {BAD_LINE: 0, LONG_LINE: 0, BAD_UNIT: 0, SKIPPED_BYTES: 0}

    def feed(self, data: bytes | bytearray | memoryview, final: bool = False) -> Readings:
        buffer = self._pending + bytes(data) if self._pending else bytes(data)
        if self._rejoin:
            settled = self._settle(buffer, final)
            if settled is None:
                self._pending = buffer
                return _empty(self.fmt)
            buffer = settled
        res = decode(buffer, self.fmt, final=final, skip_first=self._discarding)
        self._pending = buffer[res.consumed :]
        self._discarding = res.discarding
        self.lines += len(res.readings)
        add_counts(self.dropped, res.dropped)
        return res.readings

    def flush(self) -> Readings:
        """End of stream (a file): parse or drop the unterminated last line."""
        return self.feed(b"", final=True)

    def discard(self, rejoin: bool = False) -> None:
        """Drop an unterminated line (a connection ended mid-line), counting it as skipped.

        Never parsed: ``+0.12`` cut from ``+0.12345`` would be a wrong reading.
        ``rejoin``: the next bytes come from a stream joined at an unknown point
        and may begin with the tail of a line (``2345`` of ``+0.12345``).  The
        first line is then held until the next one arrives and kept only if it
        is as long (gauges write fixed-width lines); a shorter or longer one is
        dropped and counted as skipped bytes.
        """
        self.dropped[SKIPPED_BYTES] += len(self._pending)
        self._pending = b""
        self._discarding = False
        self._rejoin = rejoin

    def _settle(self, buffer: bytes, final: bool) -> bytes | None:
        """Decide on the first line after a rejoin; ``None``: not enough lines yet."""
        lines = _LINE_RE.finditer(buffer)
        first, second = next(lines, None), next(lines, None)
        if first is None or second is None:
            if final or len(buffer) > 4 * self.fmt.max_line:
                self._rejoin = False
                return buffer
            return None
        self._rejoin = False
        if first.end() - first.start() != second.end() - second.start():
            self.dropped[SKIPPED_BYTES] += first.end() - first.start()
            return buffer[first.end() :]
        return buffer

    @property
    def pending(self) -> int:
        return len(self._pending)


__all__ = [
    "DEFAULT_DECIMALS",
    "FAULT_WORDS",
    "HEADER_CLASSES",
    "TS_S",
    "UNIT_MM",
    "AsciiDecoder",
    "AsciiFormat",
    "Decoded",
    "decode",
    "encode",
]
