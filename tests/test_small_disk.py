"""A full disk on a small state file system: writing resumes when space returns, nothing held is lost at stop.

The real daemon (``ballbar run`` on the ``sim:`` source at x20) writes its state to an 8 MiB tmpfs that the test
mounts (root only: elsewhere it skips and says why) and fills to the last byte, twice: once freed while the
daemon runs, once held full until it stops.  How long resuming takes is measured by
``python -m ballbar.tools.bench.bench_diskfull`` (tools/RESULTS.md); here it must happen at all.
"""

from __future__ import annotations

import errno
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ballbar.daemon.mcap import list_recordings, read_log
from ballbar.daemon.spool import read_spool
from ballbar.tools.bench.bench_diskfull import spell, start_daemon, stop_daemon
from ballbar.tools.bench.soak import Disk

TEST_LINE = re.compile(r"ballbar\.daemon\.service: (?P<id>\S+) test: ")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def top_up(path: Path) -> None:
    """Another file, written until the file system is full again."""
    with open(path, "wb", buffering=0) as fh:
        for size in (1 << 16, 1):
            try:
                while fh.write(bytes(size)):
                    pass
            except OSError as err:
                if err.errno != errno.ENOSPC:
                    raise


@pytest.fixture
def small_disk(tmp_path: Path) -> Disk:
    disk = Disk(tmp_path / "small", 8)
    if not disk.mounted:
        disk.close()
        pytest.skip(f"cannot mount an 8 MiB tmpfs here (root only): {disk.why_not}")
    yield disk
    disk.close()


def test_a_full_8_mib_disk_resumes_and_what_the_outage_held_survives_the_stop(small_disk: Disk) -> None:
    state = small_disk.path / "state"
    port = free_port()
    bus = ["--set", "zenoh.enabled=true", "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "--machine-id", "tiny"]
    proc, log = start_daemon(state, *bus)
    try:
        log.wait_for("mcap log: writing", 60.0)
        # 1. filled, then freed while the daemon runs: it writes again (the issue: never, on 8 MiB)
        took = spell(small_disk, log, full_s=1.0)
        assert took is not None, log.text()[-3000:]
        # 2. filled until the daemon stops, a test result made meanwhile: held, then kept in the spool; filled once
        # a test's file has been written a while (a file of one flush is deleted when dropped: nothing to name)
        log.wait_for("mcap log: writing /", 60.0, log.mark())
        time.sleep(1.5)
        at = log.mark()
        small_disk.fill()
        log.wait_for("mcap log: cannot write", 30.0, at)
        _t, line = log.wait_for(" test: ", 60.0, log.mark())
        held_id = TEST_LINE.search(line)["id"]  # type: ignore[index]
        top_up(small_disk.path / "top-up")  # the space the dropped file's deletion gave back: full to the stop
    finally:
        code = stop_daemon(proc)
    first = log.text()
    assert code == 0, first[-3000:]
    assert "held through a write outage are kept in" in first and "are lost" not in first, first[-3000:]
    spooled = read_spool(state).entries
    assert any(p.get("test_id") == held_id and p.get("kind") == "test" for _t, p, _l in spooled), spooled
    assert spooled[-1][1]["event"] == "log_gap" and "No space left" in spooled[-1][1]["detail"]

    # 3. space back, the next start: the spool written to its first file and in the history, the cut test named
    small_disk.release()
    (small_disk.path / "top-up").unlink()
    proc, log = start_daemon(state, *bus)
    try:
        log.wait_for("ready: reading", 60.0)
        got = subprocess.run(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", "tiny", "--connect",
             f"tcp/127.0.0.1:{port}", "--history", "--topic", "test", "--timeout", "10", "--count", "1000"],
            capture_output=True, text=True, timeout=60,
        )
        history = [json.loads(x) for x in got.stdout.splitlines() if x.strip()]
        time.sleep(1.5)  # the first file's first flushes
    finally:
        code = stop_daemon(proc)
    second = log.text()
    assert code == 0, second[-3000:]
    assert held_id in {r.get("test_id") for r in history}, (got.stderr[-2000:], [r.get("test_id") for r in history])
    assert "the last run held through a write outage" in second, second[-3000:]
    said = [ln for ln in second.splitlines() if "cut by" in ln or "incomplete" in ln]
    assert "(killed)" not in second and any("cut by a write outage" in ln for ln in said), said
    assert read_spool(state).entries == []  # written: emptied, its space kept
    assert (state / "mcap-held.spool").stat().st_size > 0
    recorded = [r for p in list_recordings(state / "recordings") for r in read_log(p, samples=False).results]
    assert held_id in {r.get("test_id") for r in recorded if r.get("kind") == "test"}


def test_an_outage_across_a_feed_in_leaves_the_test_reportable(small_disk: Disk) -> None:
    """A full disk that covers a test's feed-in: writing resumes within the preroll's 10 s, and the samples of the
    outage the preroll buffer still holds are written first, so the recordings hold the test from its feed-in and
    ``ballbar analyze --test-id`` gives its result (on the old code: exit 1, "do not hold it from feed-in to
    feed-out").  The lost count is what the buffer did not hold: the log_gap says it, the stop line agrees."""
    state = small_disk.path / "state"
    proc, log = start_daemon(state)
    covered: str | None = None
    try:
        log.wait_for("mcap log: writing", 60.0)
        for _attempt in range(4):  # the disk filled at a test's result, freed 3 s later: the next feed-in inside
            _t, line = log.wait_for(" test: ", 60.0, log.mark())
            at = log.mark()
            small_disk.fill()
            t_fail, _line = log.wait_for("mcap log: cannot write", 30.0, at)
            time.sleep(3.0)
            at = log.mark()
            small_disk.release()
            t_back, _line = log.wait_for("mcap log: writing again", 30.0, at)
            _t, line = log.wait_for(" test: ", 60.0, log.mark())
            test_id = TEST_LINE.search(line)["id"]  # type: ignore[index]
            time.sleep(1.0)
            feed_ins = [e for p in list_recordings(state / "recordings") for e in read_log(p, samples=False).events
                        if e.get("event") == "feed_in" and e.get("test_id") == test_id]
            if feed_ins and t_fail < float(feed_ins[0]["t_host"]) < t_back:
                covered = test_id
                break
    finally:
        code = stop_daemon(proc)
    text = log.text()
    assert code == 0, text[-3000:]
    assert covered is not None, "no feed-in fell inside an outage"
    got = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(state / "recordings"),
                          "--test-id", covered, "--json"], capture_output=True, text=True, timeout=120)
    assert got.returncode == 0, got.stderr[-2000:]
    assert json.loads(got.stdout)["source"]["test_id"] == covered
    assert "which the preroll buffer still held" in text, text[-3000:]
    # every sample written or counted: the stop line's written + lost is what the files hold + the log_gaps' counts
    stop = re.search(r"mcap log stopped: \d+ files, (\d+) samples, .*; (\d+) samples lost", text)
    assert stop is not None, text[-2000:]
    logs = [read_log(p) for p in list_recordings(state / "recordings")]
    held = sum(int((~lg.preroll).sum()) for lg in logs)
    gaps = sum(int(e.get("count") or 0) for lg in logs for e in lg.events if e.get("event") == "log_gap")
    deleted = "mcap log: deleted" in text  # retention (quota 4 MiB) may have taken the oldest files
    assert (held <= int(stop[1]) if deleted else held == int(stop[1])) and gaps <= int(stop[2]), (held, gaps, stop[0])


def test_the_headroom_scales_with_the_file_system() -> None:
    from ballbar.daemon.mcap import FILE_NEEDS_BYTES, McapLogger

    lg = McapLogger(os.devnull + "-not-a-dir", "m")
    try:
        assert lg.headroom(8 << 20) == FILE_NEEDS_BYTES  # 8 MiB: what one file needs
        assert lg.headroom(256 << 20) == 4 << 20  # a 64th
        assert lg.headroom(1 << 40) == lg.headroom_bytes == 64 << 20  # at most headroom_bytes
    finally:
        lg.stop()


def test_an_outage_longer_than_the_preroll_marks_the_tests_it_cut_not_reportable(small_disk: Disk) -> None:
    """A full disk held 22 s, longer than the preroll buffer's 10 s: the feed-ins of the tests early in it are lost
    for good, though their results are recorded (held in memory).  The recording's log_gap says which span of
    samples was lost (its device-clock span matches its count at 1 kHz); ``analyze --list`` shows such a test as
    not reportable and why; ``analyze --test-id`` and ``report --test-id`` exit 1 with one line naming the outage,
    not the generic "do not hold it from feed-in to feed-out"; a test before the outage stays reportable."""
    state = small_disk.path / "state"
    recs = state / "recordings"
    proc, log = start_daemon(state)
    try:
        log.wait_for("mcap log: writing", 60.0)
        _t, line = log.wait_for(" test: ", 60.0)
        before = TEST_LINE.search(line)["id"]  # type: ignore[index]
        time.sleep(1.5)  # its result flushed (one in a chunk the full disk cuts is lost with the chunk)
        at = log.mark()
        small_disk.fill()
        t_fail, _line = log.wait_for("mcap log: cannot write", 30.0, at)
        time.sleep(22.0)  # 12 s lost beyond the ring's 10 s: more than a test takes at x20 (about 8 s)
        at = log.mark()
        small_disk.release()
        t_back, _line = log.wait_for("mcap log: writing again", 30.0, at)
        log.wait_for(" test: ", 60.0, log.mark())  # a test after the outage: the held ones are written by now
        time.sleep(1.0)
    finally:
        code = stop_daemon(proc)
    text = log.text()
    assert code == 0, text[-3000:]
    events = [e for p in list_recordings(recs) for e in read_log(p, samples=False).events]
    (gap,) = [e for e in events if e.get("event") == "log_gap" and e.get("count")]
    lo, hi = gap["lost_t_device"]
    assert abs((hi - lo) * 1000.0 - gap["count"]) <= 0.02 * gap["count"] + 50, gap  # 1 kHz on the device clock
    h_lo, h_hi = gap["lost_t_host"]
    # from before the failure to where the preroll ring (10 s back from the newest batch) begins
    assert h_lo < t_fail + 1.0 and t_back - 12.0 <= h_hi <= t_back - 9.0, (gap, t_fail, t_back)
    cut = [e["test_id"] for e in events if e.get("event") == "feed_in" and t_fail + 1.0 < e["t_host"] < h_hi - 0.5]
    assert cut, (events, t_fail, t_back)
    listed = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(recs), "--list", "--json"],
                            capture_output=True, text=True, timeout=120)
    assert listed.returncode == 0, listed.stderr[-2000:]
    rows = {r["test_id"]: r for r in json.loads(listed.stdout)}
    assert rows[before]["reportable"] is True and rows[before]["status"] == "complete", rows[before]
    done = [t for t in cut if rows[t]["status"] == "complete"]
    assert done, [rows[t] for t in cut]  # its result was held through the outage and recorded
    for t in cut:
        assert rows[t]["reportable"] is False, rows[t]
        assert "write outage (No space left on device" in rows[t]["message"], rows[t]
        assert gap["lost_utc"][0] in rows[t]["message"], rows[t]
    test_id = done[0]
    for cmd in (["analyze", str(recs), "--test-id", test_id], ["report", "--test-id", test_id, "--records", str(recs)]):
        got = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", *cmd], capture_output=True, text=True,
                             timeout=120, cwd=small_disk.path)
        # (besides the reader's warning about the file the outage cut short)
        said = [ln for ln in got.stderr.strip().splitlines() if " WARNING " not in ln]
        assert got.returncode == 1 and len(said) == 1, (cmd, got.stderr[-2000:])
        assert "not reportable" in said[0] and "lost to a write outage" in said[0] and test_id in said[0], said
        assert "do not hold it from feed-in" not in said[0]
    ok = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(recs), "--test-id", before,
                         "--json"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0 and json.loads(ok.stdout)["source"]["test_id"] == before, ok.stderr[-2000:]
