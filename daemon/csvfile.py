"""CSV recordings: a bounded, vectorised reader.

Format: a header line naming at least the columns ``t_s`` (seconds, any origin,
increasing) and ``length_mm`` (absolute bar length in millimetres), then one
sample per line, comma separated; lines end with ``\\n`` or ``\\r\\n``.  Other
columns are ignored; lines that start with ``#`` are comments, blank lines are
skipped.  Rows out of time order by no more than timestamp jitter
(:data:`~ballbar.analysis.timeaxis.JITTER_PERIODS` median sample periods) are
sorted, with a warning; a time that runs back further, or never advances, is
an error.

Every problem is raised as :class:`~ballbar.analysis.errors.DataError` with a
one-line message that names the file and the line.

Memory: the file is read :data:`BLOCK_BYTES` at a time, in whole lines, and
parsed straight into the two output arrays (16 bytes a sample); beyond them
it holds one block and, while checking the time axis, the positive time
steps (8 bytes a sample).  A line longer than :data:`MAX_LINE_BYTES` (a real
line is some 30 bytes) is an error naming it as soon as that many bytes of it
have been read: the rest of it is never read.

Speed: a block whose lines are plain decimal numbers (``-12.345``, the shape
every recorder writes) is parsed by numpy on its bytes, without a Python
object per line or per value, exactly (each value is the correctly rounded
double of its decimal, as ``float()`` gives); any other block (exponents,
comments, blank lines, ``nan``, other characters, a field of more than 18
digits) goes through ``np.loadtxt`` line by line, whose errors name the line.
"""

from __future__ import annotations

import bisect
import codecs
import logging
import math
import os
import stat
import warnings
from collections.abc import Iterator
from typing import BinaryIO, NoReturn

import numpy as np

from ballbar.analysis.errors import DataError
from ballbar.analysis.timeaxis import JITTER_PERIODS, positive_steps

log = logging.getLogger(__name__)

REQUIRED = ("t_s", "length_mm")
BLOCK_BYTES = 1 << 20  # a CSV is read, checked and parsed this many bytes (whole lines) at a time
SCAN_ROWS = 1 << 20  # and its time axis checked this many samples at a time
MAX_LINE_BYTES = 1 << 16  # a line longer than this is not a recording's (theirs are some 30 bytes)

_NL, _CR, _COMMA, _DOT, _MINUS, _PLUS = (ord(c) for c in "\n\r,.-+")
_MAX_DIGITS = 18  # an int64 holds 18 decimal digits; the mantissa must also stay below 2**53 (exact as a double)
_POW10_INT = 10 ** np.arange(_MAX_DIGITS + 1, dtype=np.int64)
_POW10 = 10.0 ** np.arange(_MAX_DIGITS + 1)  # exact doubles (10**22 is the last)


def open_recording(name: str) -> BinaryIO:
    """Open a recording for reading; the reasons it cannot be, as one-line DataErrors."""
    try:
        return open(name, "rb")
    except FileNotFoundError:
        raise DataError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise DataError(f"{name}: is a directory, not a recording") from None
    except OSError as err:
        raise DataError(f"{name}: cannot read: {err.strerror or err}") from err


def read_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read ``(t_s, length_mm)`` from a CSV recording; sorted by time, all finite.

    A bounded stream (see the module docstring).  The errors are those of the
    whole file, in the same order whatever the block size: the first bad byte
    or line, whichever block it lies in (an over-long line, a read error or
    invalid UTF-8 anywhere first).
    """
    name = os.fspath(path)
    with open_recording(name) as fh:
        csv = _CsvParser(name, fh)
        csv.parse()
    t, length = csv.t, csv.L
    csv.t = csv.L = np.empty(0)
    if t.size < 2:
        return t, length
    pos = positive_steps(t)
    if pos.size == 0:
        what = f"is {t[0]:g} s in every one of the {t.size} samples" if np.all(t == t[0]) else "never increases"
        raise DataError(f"{name}: t_s {what}: no time axis to analyse")
    # backward_steps(t), a block at a time: its median period, and how far each sample lies behind the latest before
    period = float(np.median(pos, overwrite_input=True))
    del pos
    jitter = JITTER_PERIODS * period if math.isfinite(period) else 0.0
    latest, late, most = float(t[0]), 0, 0.0
    for a in range(0, t.size, SCAN_ROWS):
        seg = t[a : a + SCAN_ROWS]
        prior = np.maximum.accumulate(np.concatenate(([latest], seg[:-1])))
        latest = max(float(prior[-1]), float(seg[-1]))
        with np.errstate(over="ignore", invalid="ignore"):  # absurd times: +-1e308 apart is an infinite step
            behind = np.maximum(prior - seg, 0.0)
        if np.any(behind > jitter):
            j = int(np.argmax(behind > jitter))
            raise DataError(
                f"{name}:{csv.line_of(a + j)}: t_s runs backwards by {behind[j]:.6g} s (to {seg[j]:.6f} s), more "
                f"than timestamp jitter ({JITTER_PERIODS:g} sample periods, {jitter:.3g} s): a clock that restarted "
                "or jumped back, or rows out of order"
            )
        if np.any(behind > 0):
            late += int(np.count_nonzero(behind))
            most = max(most, float(behind.max()))
    if late:
        log.warning("%s: %d samples out of time order by at most %.3g s (timestamp jitter); sorted", name, late, most)
        order = np.argsort(t, kind="stable")
        t = t[order]
        length = length[order]
    return t, length


class _CsvParser:
    """One pass over a CSV file's blocks into ``t`` and ``L``; see :func:`read_csv`.

    A block of plain decimal lines is parsed on its bytes (:func:`_plain_block`);
    any other by ``np.loadtxt``, and only where that fails, or for lines with a
    ``#`` past their start, does Python look at lines one by one
    (:meth:`_bad_line`), so that the error names the file's first bad line.
    """

    def __init__(self, name: str, fh: BinaryIO) -> None:
        self.name = name
        self.blocks = _byte_blocks(fh, name)
        try:
            st = os.fstat(fh.fileno())
            self.size = st.st_size if stat.S_ISREG(st.st_mode) else 0
        except (OSError, AttributeError):  # no file descriptor: grow the arrays as the samples come
            self.size = 0
        self.lines = 0  # lines of the file before the block in hand
        self.header: list[str] | None = None
        self.use = (0, 1)
        self.t = np.empty(0)
        self.L = np.empty(0)
        self.n = 0  # samples so far
        # per block of samples: its first sample, the 0-based file line of its first line, and which of its
        # lines hold no sample (None: all do)
        self.spans: list[tuple[int, int, np.ndarray | None]] = []
        self.nonfinite: str | None = None  # the first sample with a value that is not a finite number
        self.suspect: str | None = None  # the first line loadtxt took that the line check does not (a "#" in it)

    def parse(self) -> None:
        nbytes = 0
        for block, lines in self.blocks:
            nbytes += len(block)
            first = self.lines
            self.lines += lines
            if self.header is None:
                at, block = self._find_header(block, first)
                if self.header is None:
                    continue
                first = at + 1
            if not block:
                continue
            data = _plain_block(block, len(self.header), self.use)
            if data is None:
                text = block.decode("utf-8")  # valid: _byte_blocks checked it
                self._block(_split_lines(text), first, "#" in text, nbytes)
            else:
                self._store(data, first, None, [], nbytes)
        if self.header is None:
            raise DataError(f"{self.name}: empty file, expected a header 't_s,length_mm' and samples")
        if self.n == 0:
            raise DataError(f"{self.name}: header but no samples")
        if self.nonfinite is not None:
            raise DataError(self.nonfinite)
        if self.t.size != self.n:  # give back the spare capacity (in place: realloc)
            self.t.resize(self.n, refcheck=False)
            self.L.resize(self.n, refcheck=False)

    def _find_header(self, block: bytes, first: int) -> tuple[int, bytes]:
        """The header among ``block``'s lines (the file's from ``first`` on), if there: its 0-based file line and
        the bytes after it."""
        pos = 0
        line = first
        while pos < len(block):
            end = block.find(b"\n", pos)
            end = len(block) if end < 0 else end
            text = block[pos:end].decode("utf-8").strip()
            pos = end + 1
            if text and not text.startswith("#"):
                self._read_header(text, line)
                return line, block[pos:]
            line += 1
        return line, b""

    def _read_header(self, line: str, index: int) -> None:
        cols = [c.strip() for c in line.split(",")]
        missing = [c for c in REQUIRED if c not in cols]
        if missing:
            self._fail(
                f"{self.name}:{index + 1}: header must name the columns t_s,length_mm "
                f"(missing {', '.join(missing)}; found {line.strip()[:60]!r})"
            )
        self.header = cols
        self.use = (cols.index("t_s"), cols.index("length_mm"))

    def _fail(self, message: str | None) -> NoReturn:
        """Raise ``message`` once the rest of the file is read: a read, UTF-8 or line-length error there comes
        first."""
        for block, lines in self.blocks:
            if message is None:  # the first bad line after a block that loadtxt could not parse
                message = self._bad_line(_split_lines(block.decode("utf-8")), self.lines)
            self.lines += lines
        raise DataError(message or f"{self.name}: malformed CSV")

    def _bad_line(self, lines: list[str], first: int, hashed: bool = False) -> str | None:
        """The error of the first line of ``lines`` (file line ``first`` + 1 on) with too few values or not a number.

        ``hashed``: look only at lines with a ``#`` (loadtxt took the others as they are).
        """
        assert self.header is not None
        for i, ln in enumerate(lines):
            if hashed and "#" not in ln:
                continue
            s = ln.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split(",")
            if len(parts) < max(self.use) + 1:
                return (f"{self.name}:{first + i + 1}: expected {len(self.header)} comma-separated values, "
                        f"got {s[:60]!r}")
            for j in self.use:
                try:
                    float(parts[j])
                except ValueError:
                    return f"{self.name}:{first + i + 1}: not a number: {parts[j].strip()[:40]!r}"
        return None

    def _block(self, lines: list[str], first: int, hashed: bool, nbytes: int) -> None:
        """Parse the sample lines ``lines`` with loadtxt, the first of them the file's line ``first`` + 1."""
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "input contained no data": see parse()
                data = np.loadtxt(lines, delimiter=",", comments="#", usecols=self.use, ndmin=2, dtype=float)
        except ValueError:
            self._fail(self.suspect or self._bad_line(lines, first))
        if data.shape[0] == 0:
            return
        if hashed and self.suspect is None:
            self.suspect = self._bad_line(lines, first, hashed=True)
        # loadtxt skips exactly the lines that are blank or comments (where it takes the others, any other is
        # an error), so where it gave fewer samples than lines, those are the lines without one
        skip = None if data.shape[0] == len(lines) else np.array(
            [i for i, ln in enumerate(lines) if not (s := ln.strip()) or s.startswith("#")], dtype=np.int64)
        self._store(data, first, skip, lines, nbytes)

    def _store(self, data: np.ndarray, first: int, skip: np.ndarray | None, lines: list[str], nbytes: int) -> None:
        """Append ``data`` (k x 2: t, L), the samples of the block whose first line is file line ``first`` + 1."""
        k = data.shape[0]
        self.spans.append((self.n, first, skip))
        if self.nonfinite is None:
            bad = ~np.isfinite(data[:, 0]) | ~np.isfinite(data[:, 1])
            if bad.any():  # only loadtxt's blocks can hold one ("nan", "inf", "1e999")
                j = int(np.argmax(bad))
                i = _nth_kept(skip, j)
                what = "t_s" if not math.isfinite(data[j, 0]) else "length_mm"
                self.nonfinite = (f"{self.name}:{first + i + 1}: {what} is not a finite number "
                                  f"({lines[i].strip()[:60]!r})")
        need = self.n + k
        if need > self.t.size:
            # room for the whole file at the bytes per sample so far (and a little more), or a quarter more; but
            # at most four times what is read so far: a file whose first lines are short and the rest is not lines
            # at all (2 GB of NUL bytes) must not have its arrays sized for 70 M samples
            cap = need + need // 4
            if self.size > nbytes:
                cap = max(need + need // 8, min(int(need * self.size / nbytes * 1.01), 4 * need + (1 << 16)))
            self.t.resize(cap, refcheck=False)
            self.L.resize(cap, refcheck=False)
        self.t[self.n : need] = data[:, 0]
        self.L[self.n : need] = data[:, 1]
        self.n = need

    def line_of(self, k: int) -> int:
        """The 1-based file line of sample ``k`` (as read, before any sorting)."""
        b = bisect.bisect_right([s[0] for s in self.spans], k) - 1
        start, first, skip = self.spans[b]
        return first + _nth_kept(skip, k - start) + 1


def _split_lines(text: str) -> list[str]:
    """A block's lines (each ended by ``\\n``, the last one perhaps by the file's end), without ``\\r\\n``."""
    lines = text.split("\n")
    if lines and not lines[-1]:
        lines.pop()
    return [ln[:-1] if ln.endswith("\r") else ln for ln in lines] if "\r" in text else lines


def _nth_kept(skip: np.ndarray | None, j: int) -> int:
    """The index of the ``j``-th (from 0) index not in the sorted ``skip``."""
    if skip is not None:
        for s in skip.tolist():
            if s > j:
                break
            j += 1
    return j


def _plain_block(block: bytes, ncols: int, use: tuple[int, int]) -> np.ndarray | None:
    """The ``(t, L)`` columns of a block of plain decimal lines, parsed on its bytes; None for any other block.

    Plain: every line has ``ncols`` fields (commas between), no blank line,
    and each used field is ``[+-]digits[.digits]`` (or ``digits.``, ``.digits``)
    of at most 18 digits with a mantissa below 2**53.  Then the value is that
    mantissa over a power of ten, both exact doubles, so the one rounding of
    the division is the correct rounding of the decimal: the double that
    ``float()`` gives.

    A recorder writes its numbers in a fixed format, so most lines of a block
    have one of a few lengths and their fields one of a few shapes: the lines
    of one length and shape are a 2-D array of bytes, each field a few fixed
    columns of digits (:func:`_fixed_fields`); the other lines are parsed field
    by field (:func:`_decimals`), and a block mostly of those goes to
    ``np.loadtxt``.
    """
    if block.translate(None, _PLAIN_BYTES):
        return None  # a byte no plain decimal line has
    a = np.frombuffer(block, dtype=np.uint8)
    ends = np.flatnonzero(a == _NL)
    if a[-1] != _NL:  # the file's last line, without its newline: one more line, parsed alone
        tail = block[ends[-1] + 1 if ends.size else 0 :] + b"\n"
        head = _plain_block(block[: len(block) - len(tail) + 1], ncols, use) if ends.size else np.empty((0, 2))
        last = _plain_block(tail, ncols, use)
        return None if head is None or last is None else np.concatenate((head, last))
    starts = np.empty_like(ends)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    out = np.empty((ends.size, 2))
    done = np.zeros(ends.size, dtype=bool)
    width = ends - starts + 1
    counts = np.bincount(width)
    for w in np.flatnonzero(counts >= _MIN_RUN).tolist():
        windows = np.lib.stride_tricks.sliding_window_view(a, w)  # row i: the w bytes from byte i on
        lines = np.flatnonzero(width == w)
        while lines.size >= _MIN_RUN:  # the lines of one length that have the shape of the first of them
            got = _fixed_fields(windows[starts[lines]], ncols, use)
            if got is None:
                break
            same, values = got
            if values.shape[0] == ends.size:
                return values  # every line of the block has this one shape (a recorder's block)
            out[lines[same]] = values
            done[lines[same]] = True
            lines = lines[~same]
    rest = np.flatnonzero(~done)
    if rest.size > ends.size // 2:
        return None
    if rest.size:
        s, e = starts[rest], ends[rest]
        e = e - (a[np.maximum(e - 1, 0)] == _CR)
        cr = np.flatnonzero(a == _CR)
        if np.any(e <= s) or np.any(a[cr + 1] != _NL):
            return None  # a blank line, or a \r not of \r\n
        at = np.flatnonzero(a == _COMMA)
        lo, hi = np.searchsorted(at, s), np.searchsorted(at, e)
        if np.any(hi - lo != ncols - 1):
            return None
        commas = at[lo[:, None] + np.arange(ncols - 1)]
        for k, col in enumerate(use):
            parsed = _decimals(a, s if col == 0 else commas[:, col - 1] + 1, e if col == ncols - 1 else commas[:, col])
            if parsed is None:
                return None
            out[rest, k] = parsed
    return out


_PLAIN_BYTES = b"0123456789,.-+\r\n"  # the bytes of a block the vectorised parser takes
_MIN_RUN = 16  # lines of one length and shape parsed as a 2-D array of bytes


def _fixed_fields(rows: np.ndarray, ncols: int, use: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """The used fields of the lines (rows of bytes, newline included, of a block of :data:`_PLAIN_BYTES`) that
    have the first line's shape.

    Shape: which columns hold digits, and the bytes of the others (commas, the
    dot, signs, the line's end).  Returns which rows have it and their
    ``(t, L)`` values, or None where the first line is not ``ncols`` plain
    decimal fields.
    """
    first = rows[0]
    stop = first.size - (2 if first.size > 1 and first[-2] == _CR else 1)
    if np.any((first[:stop] == _CR) | (first[:stop] == _NL)):
        return None
    commas = np.flatnonzero(first[:stop] == _COMMA)
    if commas.size != ncols - 1:
        return None
    # the same shape: the first line's other bytes, and digits where it has digits (the block holds nothing but
    # digits and ",.-+\r\n", all below "0": a digit is a byte from "0" on)
    digit = first >= ord("0")
    other = np.flatnonzero(~digit)
    same = np.all(rows[:, other] == first[other], axis=1)
    same &= np.all(rows[:, np.flatnonzero(digit)] >= ord("0"), axis=1)
    picked = rows if same.all() else rows[same]
    starts, stops = [0, *(commas + 1).tolist()], [*commas.tolist(), stop]
    out = np.empty((picked.shape[0], 2))
    for k, col in enumerate(use):
        s, e = starts[col], stops[col]
        field = first[s:e]
        digits = np.flatnonzero(field >= ord("0"))
        dots = np.flatnonzero(field == _DOT)
        signs = np.flatnonzero((field == _MINUS) | (field == _PLUS))
        if not 1 <= digits.size <= 15 or dots.size > 1 or (signs.size and signs.tolist() != [0]):
            return None  # (16 to 18 digits: _decimals, whose integers stay exact)
        weights = _POW10[digits.size - 1 - np.arange(digits.size)]
        values = (picked[:, s + digits].astype(np.float64) - ord("0")) @ weights  # integers < 1e15: exact
        if dots.size:
            values /= _POW10[np.count_nonzero(digits > dots[0])]
        out[:, k] = -values if signs.size and field[0] == _MINUS else values
    return same, out


def _decimals(a: np.ndarray, s: np.ndarray, e: np.ndarray) -> np.ndarray | None:
    """The numbers in ``a[s[i]:e[i]]`` (bytes of digits, ``.``, ``-``, ``+`` only), or None if one is not a plain
    decimal (see :func:`_plain_block`)."""
    width = e - s
    if width.min() < 1 or width.max() > _MAX_DIGITS + 2:
        return None
    cols = np.arange(int(width.max()))
    inside = cols < width[:, None]
    c = np.where(inside, a[np.minimum(s[:, None] + cols, a.size - 1)], 0)
    digit = inside & (c >= ord("0")) & (c <= ord("9"))
    dot = c == _DOT
    signed = (c[:, 0] == _MINUS) | (c[:, 0] == _PLUS)
    if np.any((c[:, 1:] == _MINUS) | (c[:, 1:] == _PLUS)) or np.any(np.count_nonzero(dot, axis=1) > 1):
        return None
    seen = np.cumsum(digit, axis=1)  # digits up to and including each column
    ndig = seen[:, -1]
    if ndig.min() < 1 or ndig.max() > _MAX_DIGITS:
        return None
    place = np.where(digit, ndig[:, None] - seen, 0)  # a digit's power of ten in the mantissa
    mantissa = np.sum(np.where(digit, (c - ord("0")).astype(np.int64), 0) * _POW10_INT[place], axis=1)
    if mantissa.max() > 2**53:
        return None
    decimals = np.where(dot.any(axis=1), ndig - seen[np.arange(c.shape[0]), np.argmax(dot, axis=1)], 0)
    values = mantissa / _POW10[decimals]
    return np.where(signed & (c[:, 0] == _MINUS), -values, values)


def _byte_blocks(fh: BinaryIO, name: str) -> Iterator[tuple[bytes, int]]:
    """The file in blocks of whole lines of about :data:`BLOCK_BYTES` each, with the number of lines in each.

    A UTF-8 byte order mark at the start is dropped.  A line longer than
    :data:`MAX_LINE_BYTES` is a DataError naming it at once (the lines before it
    are yielded first).  Invalid UTF-8 is a DataError naming the byte and its
    line, raised once the rest of the file is read (a read error anywhere comes
    first, as when it was read whole).
    """
    offset = newlines = 0  # bytes and b"\n" before the block
    carry: list[bytes] = []  # the start of a line the last read cut
    carried = 0
    while True:
        chunk = _read(fh, name)
        if chunk:
            cut = chunk.rfind(b"\n") + 1
            if cut == 0:
                carry.append(chunk)
                carried += len(chunk)
                if carried > MAX_LINE_BYTES:
                    _too_long(name, newlines + 1)
                continue
            block = b"".join([*carry, chunk[:cut]]) if carry else chunk[:cut]
            carry = [chunk[cut:]] if cut < len(chunk) else []
            carried = len(chunk) - cut
        elif carry:
            block, carry, carried = b"".join(carry), [], 0
        else:
            return
        skip = len(codecs.BOM_UTF8) if offset == 0 and block.startswith(codecs.BOM_UTF8) else 0
        long_at = _first_long_line(block)
        if long_at is not None:  # the lines before it first: an error there comes first
            at, line = long_at
            if at:
                yield from _checked(block[:at], line, skip, offset, newlines, fh, name)
            _too_long(name, newlines + line + 1)
        count = block.count(b"\n")
        yield from _checked(block, count, skip, offset, newlines, fh, name)
        if carried > MAX_LINE_BYTES:
            _too_long(name, newlines + count + 1)
        offset += len(block)
        newlines += count


def _checked(
    block: bytes, count: int, skip: int, offset: int, newlines: int, fh: BinaryIO, name: str
) -> Iterator[tuple[bytes, int]]:
    """``block`` (without its first ``skip`` bytes; ``count`` newlines in it) and its number of lines, once it is
    known to be UTF-8 (see :func:`_byte_blocks`)."""
    if not block.isascii():
        try:
            block.decode("utf-8")
        except UnicodeDecodeError as err:
            at = err.start
            line = newlines + block[:at].count(b"\n") + 1
            while _read(fh, name):
                pass
            raise DataError(f"{name}:{line}: not a text CSV file (byte {offset + at} is not UTF-8)") from None
    yield (block[skip:] if skip else block), count + (not block.endswith(b"\n"))


def _first_long_line(block: bytes) -> tuple[int, int] | None:
    """Where the first line of ``block`` longer than :data:`MAX_LINE_BYTES` starts, and its index; None if none."""
    if len(block) <= MAX_LINE_BYTES:
        return None
    nl = np.flatnonzero(np.frombuffer(block, dtype=np.uint8) == _NL)
    ends = nl if block.endswith(b"\n") else np.append(nl, len(block))
    lengths = np.diff(ends, prepend=-1) - 1
    long = np.flatnonzero(lengths > MAX_LINE_BYTES)
    if not long.size:
        return None
    i = int(long[0])
    return (int(ends[i - 1]) + 1 if i else 0), i


def _too_long(name: str, line: int) -> NoReturn:
    raise DataError(f"{name}:{line}: a line longer than {MAX_LINE_BYTES} bytes: not a CSV recording "
                    "(its lines are some 30 bytes)")


def _read(fh: BinaryIO, name: str) -> bytes:
    try:
        return fh.read(BLOCK_BYTES)
    except OSError as err:
        raise DataError(f"{name}: cannot read: {err.strerror or err}") from err


__all__ = ["BLOCK_BYTES", "MAX_LINE_BYTES", "REQUIRED", "SCAN_ROWS", "open_recording", "read_csv"]
