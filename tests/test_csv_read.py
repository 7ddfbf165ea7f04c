"""Reading a CSV recording in a bounded stream (:func:`ballbar.daemon.csvfile.read_csv`).

The file is parsed a block of :data:`~ballbar.daemon.csvfile.BLOCK_BYTES`
at a time and its time axis checked :data:`~ballbar.daemon.csvfile.SCAN_ROWS`
samples at a time.  Both are shrunk here so that small files cross many
blocks: the samples, the warnings and the errors (with their file lines) must
be the same whatever the block size, as if the file had been read whole.
The messages themselves are pinned in ``tests/test_cli_analyze.py``.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbar.analysis.errors import DataError
from ballbar.daemon import csvfile
from ballbar.daemon.recordings import read_csv

SIZES = [(1, 1), (7, 2), (64, 5), (1 << 20, 1 << 20)]  # (BLOCK_BYTES, SCAN_ROWS)


def rows(n: int, t0: float = 0.0) -> list[str]:
    return [f"{t0 + 0.01 * i:.4f},{100.0 + 0.001 * (i % 7):.4f}" for i in range(n)]


def write(tmp_path: Path, lines: list[str], name: str = "rec.csv", newline: str = "\n", prefix: bytes = b"") -> Path:
    p = tmp_path / name
    p.write_bytes(prefix + (newline.join(lines) + newline).encode("utf-8"))
    return p


def read_all_ways(path: Path, monkeypatch: pytest.MonkeyPatch) -> list[tuple[np.ndarray, np.ndarray] | str]:
    """read_csv's answer (the arrays, or the error's message) at each block size."""
    out: list[tuple[np.ndarray, np.ndarray] | str] = []
    for block, scan in SIZES:
        monkeypatch.setattr(csvfile, "BLOCK_BYTES", block)
        monkeypatch.setattr(csvfile, "SCAN_ROWS", scan)
        try:
            out.append(read_csv(path))
        except DataError as err:
            out.append(str(err))
    return out


def one_error(path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    got = read_all_ways(path, monkeypatch)
    assert all(isinstance(g, str) for g in got), got
    assert len(set(got)) == 1, got
    return str(got[0])


def test_samples_are_the_same_at_any_block_size(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    i = np.arange(300)
    t, length = np.round(0.01 * i, 4), np.round(100.0 + 0.001 * (i % 7), 4)
    lines = [f"x,{b:.4f},{a:.4f}" for a, b in zip(t, length, strict=True)]  # columns in another order
    lines[250:250] = ["# a comment", "", "#"]
    lines[40:40] = [""]
    lines[0:0] = ["# recorded by hand", "", "extra,length_mm,t_s"]
    for newline in ("\n", "\r\n"):
        got = read_all_ways(write(tmp_path, lines, newline=newline, prefix=b"\xef\xbb\xbf"), monkeypatch)
        for g in got:
            assert not isinstance(g, str), g
            assert np.array_equal(g[0], t) and np.array_equal(g[1], length)
            assert g[0].flags.c_contiguous and g[1].flags.c_contiguous


def test_rows_out_of_order_within_jitter_are_sorted_across_blocks(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    lines = ["t_s,length_mm", *rows(200)]
    lines[151], lines[152] = lines[152], lines[151]  # samples 150 and 151, far beyond the first block
    path = write(tmp_path, lines)
    with caplog.at_level(logging.WARNING):
        got = read_all_ways(path, monkeypatch)
    i = np.arange(200)
    for g in got:  # sorted back into place, each length with its time
        assert not isinstance(g, str), g
        assert np.array_equal(g[0], np.round(0.01 * i, 4)) and np.array_equal(g[1], np.round(100 + 0.001 * (i % 7), 4))
    warned = [r.getMessage() for r in caplog.records if "out of time order" in r.getMessage()]
    assert len(warned) == len(SIZES) and all("1 samples out of time order by at most 0.01 s" in w for w in warned)


@pytest.mark.parametrize(
    "value, needle",
    [
        ("2.4600,abc", "not a number: 'abc'"),
        ("2.46", "expected 2 comma-separated values, got '2.46'"),
        ("2.4600,nan", "length_mm is not a finite number ('2.4600,nan')"),
        ("inf,100.0", "t_s is not a finite number ('inf,100.0')"),
        ("1.0000,100.0", "t_s runs backwards by 1.45 s (to 1.000000 s), more than timestamp jitter"),
    ],
)
def test_errors_beyond_the_first_block_name_their_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, value: str, needle: str
) -> None:
    lines = ["# comment", "t_s,length_mm", *rows(300)]
    lines[30:30] = ["", "# more"]  # the data rows after them lie two lines further down
    assert lines[250].startswith("2.4600,")
    lines[250] = value
    assert f"rec.csv:251: {needle}" in one_error(write(tmp_path, lines), monkeypatch)


def test_the_first_bad_line_wins_whichever_block_fails(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # loadtxt takes an inline comment; the whole file's line check does not: it is the error a later bad line
    # brings out, as when the file was read whole
    lines = ["t_s,length_mm", *rows(300)]
    lines[20] = "0.1900,100.0 # note"
    lines[280] = "2.7900,oops"
    assert ":21: not a number: '100.0 # note'" in one_error(write(tmp_path, lines), monkeypatch)
    # a blank-looking line loadtxt refuses but the line check skips: the next bad line, in a later block
    lines = ["t_s,length_mm", *rows(300)]
    lines[20] = "   "
    lines[280] = "2.7900,oops"
    assert ":281: not a number: 'oops'" in one_error(write(tmp_path, lines, "b.csv"), monkeypatch)
    lines[280] = rows(300)[279]
    assert one_error(write(tmp_path, lines, "c.csv"), monkeypatch).endswith("c.csv: malformed CSV")
    # a non-finite value before a line that does not parse: the parse error comes first
    lines = ["t_s,length_mm", *rows(300)]
    lines[20] = "0.1900,inf"
    lines[280] = "2.7900"
    assert ":281: expected 2 comma-separated values" in one_error(write(tmp_path, lines, "d.csv"), monkeypatch)


def test_invalid_utf8_anywhere_comes_first(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    lines = ["t_s,length_mm", *rows(300)]
    lines[5] = "0.0400,abc"  # a bad number early on; the bad byte later still decides
    data = ("\n".join(lines) + "\n").encode()
    at = data.index(b"\n2.5000,") + 3
    p = tmp_path / "bin.csv"
    p.write_bytes(data[:at] + b"\xff" + data[at:])
    assert one_error(p, monkeypatch).endswith(f"bin.csv:252: not a text CSV file (byte {at} is not UTF-8)")
    # behind a byte order mark: the byte counts from the file's start (the mark's three bytes too)
    p.write_bytes(b"\xef\xbb\xbf" + data[:at] + b"\xc3(" + data[at:])
    assert one_error(p, monkeypatch).endswith(f"bin.csv:252: not a text CSV file (byte {at + 3} is not UTF-8)")
    # header missing: still the bad byte first
    p.write_bytes(b"time,len\n" + data[data.index(b"\n") + 1 : at] + b"\xff\n")
    assert "not a text CSV file" in one_error(p, monkeypatch)


def test_a_line_longer_than_the_limit_is_an_error_naming_it_at_any_block_size(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    long = "9" * (csvfile.MAX_LINE_BYTES + 1)
    lines = ["t_s,length_mm", *rows(300)]
    for at in (0, 1, 150, len(lines)):  # the header, the first sample, mid-file, the last (without its newline)
        path = write(tmp_path, [*lines[:at], f"1.0,{long}", *lines[at:]])
        if at == len(lines):
            path.write_bytes(path.read_bytes().rstrip(b"\n"))
        assert f"rec.csv:{at + 1}: a line longer than {csvfile.MAX_LINE_BYTES} bytes" in one_error(path, monkeypatch)
    # a bad number before it: the long line, like a read error, comes first; invalid UTF-8 before it still first
    bad = [*lines[:5], "0.04,abc", *lines[5:200], long, *lines[200:]]
    assert ":202: a line longer than" in one_error(write(tmp_path, bad), monkeypatch)
    data = ("\n".join([*lines[:5], *lines[5:200], long, *lines[200:]]) + "\n").encode()
    at = data.index(b"\n1.0000,") + 3
    p = tmp_path / "utf.csv"
    p.write_bytes(data[:at] + b"\xff" + data[at:])
    assert "not a text CSV file" in one_error(p, monkeypatch)


def test_the_long_line_is_not_read_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Read stops a block past the limit: the rest of a 64 MiB line is never read."""
    path = tmp_path / "flat.csv"
    path.write_bytes(b"t_s,length_mm\n" + b"\0" * (64 << 20))
    reads: list[int] = []
    real = csvfile._read

    def counting(fh: Any, name: str) -> bytes:
        chunk = real(fh, name)
        reads.append(len(chunk))
        return chunk

    monkeypatch.setattr(csvfile, "_read", counting)
    with pytest.raises(DataError, match=r"flat.csv:2: a line longer than"):
        read_csv(path)
    assert sum(reads) <= csvfile.MAX_LINE_BYTES + 2 * csvfile.BLOCK_BYTES


def test_empty_and_headless_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert "empty file" in one_error(write(tmp_path, ["# only", "", "# comments"] * 20), monkeypatch)
    assert "header but no samples" in one_error(write(tmp_path, ["# c"] * 30 + ["t_s,length_mm"] + ["# c"] * 30),
                                                monkeypatch)
    lines = ["# c"] * 30 + ["a,b,length_mm"] + rows(10)
    assert ":31: header must name the columns t_s,length_mm (missing t_s; found 'a,b,length_mm')" in one_error(
        write(tmp_path, lines), monkeypatch)
    flat = ["t_s,length_mm"] + [f"5,{100 + 0.001 * i:.3f}" for i in range(50)]
    assert "t_s is 5 s in every one of the 50 samples" in one_error(write(tmp_path, flat), monkeypatch)


def test_memory_is_bounded(tmp_path: Path) -> None:
    """Peak memory while reading 1.5 M rows: the output (16 bytes a row) and little more, not the file's lines."""
    n = 1_500_000
    k = np.arange(n)
    t = np.char.mod("%.6f", k * 1e-3)
    length = np.char.mod("%.6f", 100.0 + 1e-3 * np.sin(k * 1e-3))
    path = tmp_path / "big.csv"
    with open(path, "w", encoding="ascii") as fh:
        fh.write("t_s,length_mm\n")
        fh.write("\n".join(np.char.add(np.char.add(t, ","), length).tolist()))
        fh.write("\n")
    del t, length
    script = textwrap.dedent(f"""
        import sys
        from ballbar.daemon.recordings import read_csv
        def status(key):
            with open("/proc/self/status") as fh:
                return next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith(key + ":"))
        before = status("VmRSS")
        t, length = read_csv({str(path)!r})
        assert t.size == {n}
        print(status("VmHWM") - before)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    grown = int(proc.stdout)
    output = 16 * n
    assert grown < 3 * output + 60e6, f"read_csv grew by {grown / 1e6:.0f} MB for {output / 1e6:.0f} MB of samples"
