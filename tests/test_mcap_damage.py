"""Recordings cut or damaged on disk: read as far as they go and past a garbled chunk, each said in one line.

The files are the daemon's own (a simulated test recorded by the real logger), cut and garbled as a disk, a
copy or a killed writer leaves them; the commands run as the operator runs them, in a process of their own.
"""

from __future__ import annotations

import json
import random
import subprocess
import sys
import threading
from pathlib import Path

import pytest
from mcap.reader import make_reader

from ballbar.daemon.config import load
from ballbar.daemon.mcap import McapLogger, list_recordings, read_log
from ballbar.daemon.service import Daemon
from ballbar.daemon.sources import open_source

CHUNK_HEAD = 9 + 8 + 8 + 8 + 4 + 4 + 4 + 8  # opcode, length, times, size, crc, "zstd", records length


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One simulated test (its feed-in, circles and result) recorded by the daemon's logger in many chunks."""
    state = tmp_path_factory.mktemp("state")
    cfg = load(None, ["zenoh.enabled=false", 'rerun.mode="off"', "daemon.analysis_worker=false",
                      f'daemon.state_dir="{state}"', "plan.sample_hz=100.0", "mcap.flush_s=0.1"], env={})
    src = open_source("sim:?speedup=40&rate=100&repeat=1")
    d = Daemon(cfg, src, [(McapLogger.from_config(cfg), 6000, "drop_newest")])
    assert d.run(threading.Event(), max_tests=1) == 0
    (path,) = list_recordings(state / "recordings")
    return path


def analyze(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", *args], capture_output=True,
                          text=True, timeout=120)


def killed_and_garbled(src: Path, dst: Path) -> tuple[int, int]:
    """``src`` without its summary (as a killed writer leaves it), one samples-only chunk between the test's
    feed-in and its result garbled: that chunk's byte range."""
    with open(src, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
    assert summary is not None
    topics = {c.id: c.topic for c in summary.channels.values()}
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    holds = [{topics[k] for k in c.message_index_offsets} for c in chunks]
    first_event = next(i for i, h in enumerate(holds) if "/ballbar/events" in h)
    last_result = max(i for i, h in enumerate(holds) if "/ballbar/results" in h)
    k = next(i for i in range(first_event + 1, last_result) if holds[i] == {"/ballbar/samples"})
    last = chunks[-1]
    data = bytearray(src.read_bytes()[: last.chunk_start_offset + last.chunk_length + last.message_index_length])
    start = chunks[k].chunk_start_offset
    rng = random.Random(7)
    for i in range(start + CHUNK_HEAD, start + chunks[k].chunk_length):
        data[i] = rng.randrange(256)
    dst.write_bytes(bytes(data))
    return start, chunks[k + 1].chunk_start_offset


def test_a_garbled_chunk_is_skipped_once_and_the_result_after_it_is_read(recorded: Path, tmp_path: Path) -> None:
    bad = tmp_path / recorded.name
    start, end = killed_and_garbled(recorded, bad)
    whole = read_log(recorded)
    damaged = read_log(bad)
    assert damaged.results == whole.results and len(whole.results) >= 3  # the circles' and the test's, after it
    assert [e["event"] for e in damaged.events] == [e["event"] for e in whole.events]
    lost = len(whole.samples) - len(damaged.samples)
    assert 0 < lost < len(whole.samples) // 4  # that chunk's samples only
    assert [where for _k, where in damaged.skipped] == [damaged.skipped[0][1]]
    assert damaged.skipped[0][1].startswith(f"bytes {start} to {end} (")

    listed = analyze(str(bad), "--list", "--json")
    assert listed.returncode == 0, listed.stderr
    (row,) = json.loads(listed.stdout)
    assert row["status"] == "complete" and row["headline"] is not None
    warnings = [ln for ln in listed.stderr.splitlines() if ln.strip()]
    assert len(warnings) == 1 and f"damaged: bytes {start} to {end}" in warnings[0], listed.stderr

    directory = tmp_path / "dir"
    directory.mkdir()
    (directory / bad.name).write_bytes(bad.read_bytes())
    again = analyze(str(directory), "--json")  # its samples too (the feed-in's may be the ones lost)
    lines = [ln for ln in again.stderr.splitlines() if "damaged" in ln]
    assert len(lines) == 1 and "WARNING" in lines[0], again.stderr


def test_a_file_cut_to_its_magic_is_one_line_that_says_where_it_ends(recorded: Path, tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recorded.read_bytes()[:8])
    out = analyze(str(cut))
    assert out.returncode == 1 and out.stdout == ""
    (line,) = out.stderr.splitlines()
    assert line.startswith(f"error: {cut}: no samples") and "ends early at byte 8" in line, line
    assert "killed" not in line
    listed = analyze(str(cut), "--list")
    assert listed.returncode == 0 and listed.stderr == ""
    (row,) = listed.stdout.splitlines()
    assert row.startswith(f"{cut}: no test recorded") and "ends early at byte 8" in row


def test_a_file_cut_in_a_record_says_at_which_byte_once(recorded: Path, tmp_path: Path) -> None:
    data = recorded.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    out = analyze(str(cut), "--list")
    warnings = [ln for ln in out.stderr.splitlines() if "WARNING" in ln]
    assert len(warnings) == 1, out.stderr
    assert f"of {len(data) // 2} " in warnings[0] and "ends early" in warnings[0] and "killed" not in warnings[0]
