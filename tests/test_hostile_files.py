"""Nothing a file can hold takes ``ballbar analyze`` down: bounded memory on any shape, one-line errors.

The memory cases run ``ballbar analyze`` as a real process on sparse files (a 2 GB file takes no disk) and
take its peak resident set (``VmHWM``) as ``tools/bench/bench_csv.py`` does; each child's address space is capped
(``RLIMIT_AS``) so that a regression fails the test instead of the machine.  The property-based tests cut,
truncate and mutate a real daemon recording and a real CSV at random and hold the readers and the command to
their contract: a :class:`DataError` (or a result), one line, exit code 1.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ballbar.analysis.errors import DataError
from ballbar.analysis.plan import TestPlan
from ballbar.daemon import csvfile
from ballbar.daemon.cli import main
from ballbar.daemon.csvfile import MAX_LINE_BYTES, read_csv
from ballbar.daemon.mcap import MAX_RECORD_BYTES, list_recordings, read_log
from ballbar.daemon.recordings import load_recording
from ballbar.tools.bench.bench_csv import peak_run
from ballbar.tools.simulator import MachineModel, simulate
from ballbar.tools.simulator_cli import write_csv

MB = 1 << 20
CAP_BYTES = 6 << 30  # each child's address space: the old code's 2 GB line needs some 20 GB
MEMORY_BOUND = 300 * MB  # the bound, beyond the samples kept (these files keep none)
LOG_LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} (INFO|WARNING) ")


def analyze_process(path: Path, *args: str) -> tuple[int, str, str, int]:
    """``ballbar analyze PATH ARGS`` in a fresh process: exit code, stdout, stderr and peak RSS (bytes)."""
    r = peak_run(sys.executable, "analyze", ["analyze", str(path), *args], CAP_BYTES)
    return r["exit"], r["stdout"], r["stderr"], int(r["peak_rss_mb"] * MB)


def one_line_error(code: int, err: str, needle: str) -> str:
    """The error line of a failed run: exit 1, no traceback, the error the last line and every other a log line."""
    assert code == 1, (code, err[-3000:])
    assert "Traceback" not in err, err[-3000:]
    lines = err.strip().splitlines()
    assert lines and lines[-1].startswith("error: ") and needle in lines[-1], err[-3000:]
    assert all(LOG_LINE.match(ln) for ln in lines[:-1]), err[-3000:]
    return lines[-1]


# ----------------------------------------------------------------------------- item 1: bounded memory


def test_a_200_mb_line_of_nul_bytes_is_an_error_naming_it_in_bounded_memory(tmp_path: Path) -> None:
    path = tmp_path / "nul.csv"
    path.write_bytes(b"t_s,length_mm\n0,100\n")
    os.truncate(path, 200 * MB)
    code, out, err, peak = analyze_process(path, "--json")
    line = one_line_error(code, err, f"nul.csv:3: a line longer than {MAX_LINE_BYTES} bytes")
    assert out == "" and peak < MEMORY_BOUND, (line, peak / MB)


@pytest.mark.parametrize(("head", "line"), [(b"", 1), (b"t_s,length_mm\n", 2)])
def test_a_2_gb_file_without_a_newline_is_an_error_naming_its_line_in_bounded_memory(
    tmp_path: Path, head: bytes, line: int
) -> None:
    path = tmp_path / "flat.csv"
    path.write_bytes(head)
    os.truncate(path, 2 << 30)
    code, _out, err, peak = analyze_process(path)
    one_line_error(code, err, f"flat.csv:{line}: a line longer than")
    assert peak < MEMORY_BOUND, peak / MB


def test_an_mcap_record_that_claims_a_gigabyte_costs_no_gigabyte(tmp_path: Path, daemon_file: Path) -> None:
    """A corrupt length field (the chunk's records, 0.9 GB) in a file that has that many bytes after it."""
    data = bytearray(daemon_file.read_bytes())
    at = 8  # after the magic: walk the records (opcode, length, body) to the first chunk (opcode 6)
    while data[at] != 0x06:
        at += 9 + int.from_bytes(data[at + 1 : at + 9], "little")
    records_length_at = at + 9 + 8 + 8 + 8 + 4 + 4 + len("zstd")  # opcode, length, times, size, crc, compression
    assert data[records_length_at - 4 : records_length_at] == b"zstd"
    data[records_length_at : records_length_at + 8] = (900 * MB).to_bytes(8, "little")
    data[at + 1 : at + 9] = (900 * MB + 64).to_bytes(8, "little")
    path = tmp_path / "claims.mcap"
    path.write_bytes(bytes(data))
    os.truncate(path, 1 << 30)
    code, _out, err, peak = analyze_process(path, "--json")
    one_line_error(code, err, "claims.mcap: no samples on /ballbar/samples")
    assert peak < MEMORY_BOUND and 900 * MB > MAX_RECORD_BYTES, peak / MB


# ----------------------------------------------------------------------------- item 2: no traceback


@pytest.fixture(scope="module")
def daemon_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One test recorded by the real daemon (250 Hz, the simulated machine): events, results, samples."""
    state = tmp_path_factory.mktemp("state")
    cmd = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=250&speedup=100&repeat=0",
           "--tests", "1", "--state-dir", str(state), "--machine-id", "mill7", "--set", "plan.overshoot_deg=20",
           "--set", "plan.sample_hz=250", "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"']
    env = {k: v for k, v in os.environ.items() if k != "BALLBAR_CONFIG"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    files = [p for p in list_recordings(state / "recordings") if read_log(p, samples=False).results]
    return files[0]


@pytest.fixture(scope="module")
def good_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    r = simulate(PLAN_250, MachineModel(noise_um=0.2, backlash_x_um=4.0), 250.0, seed=3)
    path = tmp_path_factory.mktemp("csv") / "test.csv"
    write_csv(str(path), r.t_s, r.length_mm)
    return path


PLAN_ARGS = ["--sample-hz", "250", "--overshoot-deg", "20"]
PLAN_250 = TestPlan(sample_hz=250.0, overshoot_deg=20.0)


def test_one_absurd_length_in_a_test_is_left_out_counted_and_said(tmp_path: Path, good_csv: Path) -> None:
    lines = good_csv.read_text().splitlines()
    t = np.array([float(ln.split(",")[0]) for ln in lines[1:]])
    mid = 1 + int(np.searchsorted(t, t[-1] / 2))  # the middle of the test: on a data arc
    for i, value in ((mid, "1e308"), (mid + 40, "-1e308"), (mid + 80, "0")):
        lines[i] = f"{lines[i].split(',')[0]},{value}"
    path = tmp_path / "absurd.csv"
    path.write_text("\n".join(lines) + "\n")
    code, out, err, _peak = analyze_process(path, "--json", *PLAN_ARGS)
    assert code == 0 and "Traceback" not in err, err[-3000:]
    warnings = json.loads(out)["warnings"]
    assert any("3 sample(s) left out" in w and "1e+308" in w for w in warnings), warnings


@pytest.mark.parametrize("size", [8, 20])
def test_an_mcap_file_cut_to_a_few_bytes_is_one_line(tmp_path: Path, daemon_file: Path, size: int) -> None:
    path = tmp_path / f"cut{size}.mcap"
    path.write_bytes(daemon_file.read_bytes()[:size])
    code, _out, err, _peak = analyze_process(path, "--json")
    one_line_error(code, err, f"cut{size}.mcap: no samples on /ballbar/samples")


def test_a_bad_file_in_a_recordings_directory_costs_only_itself(tmp_path: Path, daemon_file: Path) -> None:
    records = tmp_path / "recordings"
    records.mkdir()
    good = records / daemon_file.name
    good.write_bytes(daemon_file.read_bytes())
    cut = daemon_file.name.replace("_0001.mcap", "_0002.mcap")
    (records / cut).write_bytes(daemon_file.read_bytes()[:20])
    foreign = daemon_file.name.replace("_0001.mcap", "_0003.mcap")  # the newest: named as the logger's, not MCAP
    (records / foreign).write_bytes(b"t_s,length_mm\n0,100\n")
    for args in (["--json"], ["--list", "--json"]):
        code, out, err, _peak = analyze_process(records, *args)
        assert code == 0 and "Traceback" not in err, err[-3000:]
        assert cut in err and foreign in err  # warnings that name them
        got = json.loads(out)
        assert (got["source"]["file"] if "--list" not in args else got[0]["files"][0]).endswith(daemon_file.name)
    # the samples of the directory as one recording: the bad files left out, named
    rec = load_recording(records)
    assert rec.t.size == load_recording(good).t.size


# ----------------------------------------------------------------------------- property-based


KINDS = ["truncate", "cut", "flip", "insert", "overwrite", "repeat"]
# where: a fraction of the file's length, or a byte offset in its head (the magic, the header record)
WHERE = st.one_of(st.floats(0, 1), st.integers(0, 300))
# one to three edits of a file: (what, where, a size or bit, bytes)
EDITS = st.lists(st.tuples(st.sampled_from(KINDS), WHERE, st.integers(0, 5000), st.binary(max_size=64)),
                 min_size=1, max_size=3)


def mutate(data: bytes, edits: list[tuple[str, float | int, int, bytes]]) -> bytes:
    """``data`` cut, truncated, bit-flipped, with bytes inserted or overwritten, or a slice repeated."""
    out = bytearray(data)
    for kind, where, size, blob in edits:
        n = len(out)
        a = min(n, where if isinstance(where, int) else int(where * n))
        if kind == "truncate":
            del out[a:]
        elif kind == "cut":
            del out[a : a + size]
        elif kind == "flip" and a < n:
            out[a] ^= 1 << (size % 8)
        elif kind == "insert":
            out[a:a] = blob or b"\x00"
        elif kind == "overwrite":
            out[a : a + len(blob)] = blob
        elif kind == "repeat":
            out[a + size : a + size] = out[a : a + size]
    return bytes(out)


TOKENS = ["nan", "inf", "-inf", "1e308", "-1e308", "1e-308", "0", "", "abc", "1,2,3", "9" * 40, "1e400", "#", "\x00"]


# values replaced by tokens a hostile file holds: (where as a fraction of the lines, which field, the token)
TOKEN_EDITS = st.lists(st.tuples(st.floats(0, 1), st.integers(0, 1), st.sampled_from(TOKENS)), max_size=4)


def with_tokens(text: str, edits: list[tuple[float, int, str]]) -> bytes:
    lines = text.split("\n")
    for where, field, token in edits:
        i = min(len(lines) - 1, int(where * len(lines)))
        parts = lines[i].split(",")
        parts[min(field, len(parts) - 1)] = token
        lines[i] = ",".join(parts)
    return "\n".join(lines).encode()


def analyze_in_process(path: Path) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(["analyze", str(path), "--json", *PLAN_ARGS])
    return code, out.getvalue(), err.getvalue()


def holds_the_contract(path: Path, reader: Any) -> None:
    """The reader gives samples or one DataError line; ``ballbar analyze`` a result (0) or one error line (1)."""
    try:
        reader(path)
    except DataError as e:
        assert "\n" not in str(e) and str(e).startswith(str(path)), str(e)
    code, out, err = analyze_in_process(path)
    if code == 0:
        assert json.loads(out)["kind"] == "test"
    else:
        assert code == 1 and out == "" and err.startswith("error: ") and err.count("\n") == 1, (code, err)


# BALLBAR_FUZZ_EXAMPLES=2000 explores further (some 10 minutes); a run of the suite tries 40 new cases of each
SLOW = settings(max_examples=int(os.environ.get("BALLBAR_FUZZ_EXAMPLES", "40")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


@SLOW
@given(edits=EDITS)
def test_a_mutated_daemon_recording_gives_a_result_or_one_line(
    daemon_file: Path, edits: list[tuple[str, float | int, int, bytes]]
) -> None:
    blob = mutate(daemon_file.read_bytes(), edits)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.mcap"
        path.write_bytes(blob)
        holds_the_contract(path, lambda p: load_recording(p))
        holds_the_contract(path, lambda p: read_log(p, samples=False))


@SLOW
@given(tokens=TOKEN_EDITS, edits=st.one_of(st.just([]), EDITS))
def test_a_mutated_csv_gives_a_result_or_one_line(
    good_csv: Path, tokens: list[tuple[float, int, str]], edits: list[tuple[str, float | int, int, bytes]]
) -> None:
    blob = mutate(with_tokens(good_csv.read_text(), tokens), edits)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.csv"
        path.write_bytes(blob)
        holds_the_contract(path, read_csv)


# ----------------------------------------------------------------------------- the vectorised CSV parser


NUMBER = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64).map(repr),
    st.integers(0, 12).flatmap(lambda p: st.decimals(allow_nan=False, allow_infinity=False, places=p)).map(str),
    st.tuples(st.sampled_from(["", "-", "+"]), st.text("0123456789", min_size=1, max_size=19),
              st.sampled_from(["", "."]), st.text("0123456789", max_size=19)).map("".join),
    st.sampled_from(["0", "-0", "+0.0", ".5", "5.", "-.5", "007.50", "1e3", "1E-3", " 1.5", "1.5 "]),
)


@settings(max_examples=300, deadline=None)
@given(rows=st.lists(st.tuples(NUMBER, NUMBER), min_size=1, max_size=60), crlf=st.booleans(),
       repeat=st.integers(1, 40), block=st.sampled_from([7, 64, 1 << 20]))
def test_values_are_the_doubles_float_gives(
    rows: list[tuple[str, str]], crlf: bool, repeat: int, block: int
) -> None:
    """Plain decimals take the vectorised path, the rest loadtxt's: either way float()'s double, exactly."""
    rows = rows * repeat  # runs of lines of one shape, as a recorder writes them
    text = ("\r\n" if crlf else "\n").join(["x,t_s,length_mm", *(f"1,{a},{b}" for a, b in rows)]) + "\n"
    parser = csvfile._CsvParser("x.csv", io.BytesIO(text.encode()))
    old = csvfile.BLOCK_BYTES
    csvfile.BLOCK_BYTES = block
    try:
        parser.parse()
    except DataError as e:  # only where float() refuses one too
        bad = [v for row in rows for v in row if not _is_float(v)]
        assert bad, str(e)
        return
    finally:
        csvfile.BLOCK_BYTES = old
    want = np.array([[float(a), float(b)] for a, b in rows])
    assert np.array_equal(parser.t[: parser.n], want[:, 0]) and np.array_equal(parser.L[: parser.n], want[:, 1])
    assert np.array_equal(np.signbit(parser.t[: parser.n]), np.signbit(want[:, 0]))


def _is_float(v: str) -> bool:
    try:
        return np.isfinite(float(v)) and v.strip() == v and v != ""
    except ValueError:
        return False
