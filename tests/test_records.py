"""A directory of the daemon's records from more than one daemon run: listed, chosen, timed on its own clock.

The records are made by the real daemon (``ballbar run`` on the ``sim:``
source), stopped and started again: the simulated device's clock starts
afresh with each run, as a real device's does when it is power-cycled with
the daemon, so no single time axis spans the directory.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbar.daemon import testindex
from ballbar.daemon.cli import main
from ballbar.daemon.mcap import McapLogger, list_recordings, read_log, recording
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.tools.report import from_records

SETS = ["plan.overshoot_deg=20", "plan.sample_hz=250", "zenoh.enabled=false", 'rerun.mode="off"']


def daemon_run(state: Path, tests: int) -> None:
    """One daemon run until ``tests`` test results (a test more may be in progress when it stops)."""
    cmd = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source",
           "sim:?rate=250&speedup=100&repeat=0&gap_s=100", "--tests", str(tests), "--state-dir", str(state),
           "--machine-id", "mill7"]
    for s in SETS:
        cmd += ["--set", s]
    env = {k: v for k, v in os.environ.items() if k != "BALLBAR_CONFIG"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=180, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]


@pytest.fixture(scope="module")
def records(tmp_path_factory: pytest.TempPathFactory) -> Path:
    state = tmp_path_factory.mktemp("state")
    daemon_run(state, 2)
    time.sleep(1.1)  # test ids are the feed-in's UTC second
    daemon_run(state, 2)
    return state / "recordings"


def published(records: Path) -> list[dict[str, Any]]:
    return [r for p in list_recordings(records) for r in read_log(p, samples=False).results if r["kind"] == "test"]


def analyze(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    capsys.readouterr()
    code = main(["analyze", *args])
    out, err = capsys.readouterr()
    return code, out, err


def same_numbers(a: dict[str, Any], b: dict[str, Any]) -> None:
    for key, p in a["parameters"].items():
        if p["value"] is not None:
            assert p["value"] == pytest.approx(b["parameters"][key]["value"], rel=1e-6, abs=1e-6), key


def test_the_index_lists_both_runs_tests_without_reading_samples(
    records: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(testindex, "read_logs", lambda *a, **k: pytest.fail("--list decodes samples"))
    code, out, err = analyze([str(records), "--list", "--json"], capsys)
    assert code == 0, err
    rows = json.loads(out)
    done = [r for r in rows if r["status"] == "complete"]
    assert [r["test_id"] for r in done] == [p["test_id"] for p in published(records)]
    assert all(r["status"] in ("complete", "incomplete") for r in rows)
    assert [r["number"] for r in rows] == list(range(1, len(rows) + 1))
    for r in done:
        assert r["start"].endswith("Z") and r["time_axis"] == "device" and r["files"]
        assert r["headline"]["measured_feed_mm_min"] == pytest.approx(1000.0, abs=1.0)
    index = testindex.index_recordings(records)
    assert len(index.runs()) == 2
    # each run stopped after (at least) two test results
    assert sorted({t.run for t in index.tests if t.status == "complete"}) == [0, 1]
    assert all(sum(t.run == run and t.status == "complete" for t in index.tests) >= 2 for run in (0, 1))
    code, out, _ = analyze([str(records), "--list"], capsys)
    assert code == 0 and len(out.splitlines()) == len(rows)
    assert out.splitlines()[0].startswith(f"  1  {rows[0]['test_id']}  {rows[0]['start']}  {rows[0]['files'][0]}")


def test_a_directory_of_two_runs_gives_its_newest_complete_test_from_its_own_files(
    records: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    decoded: list[list[str]] = []
    real = testindex.read_logs

    def spy(paths: Any, **kw: Any) -> Any:
        decoded.append([Path(p).name for p in paths])
        return real(paths, **kw)

    monkeypatch.setattr(testindex, "read_logs", spy)
    t0 = time.perf_counter()
    code, out, err = analyze([str(records), "--json"], capsys)
    elapsed = time.perf_counter() - t0
    assert code == 0, err
    res = json.loads(out)
    newest = published(records)[-1]
    assert res["source"]["test_id"] == newest["test_id"] and res["source"]["time_axis"] == "device"
    same_numbers(res, newest)
    # only the test's own file was decoded, of the directory's
    assert decoded == [[Path(res["source"]["file"]).name]], decoded
    assert len(list_recordings(records)) > 2
    assert elapsed < 30.0


def test_a_test_of_the_first_run_by_id_and_by_number(records: Path, capsys: pytest.CaptureFixture[str]) -> None:
    first = published(records)[0]
    code, out, err = analyze([str(records), "--test-id", first["test_id"], "--json"], capsys)
    assert code == 0, err
    res = json.loads(out)
    assert res["source"]["test_id"] == first["test_id"]
    same_numbers(res, first)
    code, out, err = analyze([str(records), "--test", "1", "--json"], capsys)
    assert code == 0 and json.loads(out)["source"]["test_id"] == first["test_id"]
    code, out, _ = analyze([str(records), "--test-id", "latest"], capsys)
    assert code == 0 and out.startswith(f"Test {published(records)[-1]['test_id']} (")
    code, _, err = analyze([str(records), "--test-id", "mill7-nope"], capsys)
    assert code == 1 and "no test 'mill7-nope' in the records (the newest: mill7-" in err
    code, _, err = analyze([str(records), "--test", "99"], capsys)
    assert code == 1 and "test 99 asked for (--list shows them)" in err


def test_the_report_picks_tests_the_same_way(records: Path) -> None:
    tests = published(records)
    index = testindex.index_recordings(records)
    second_run = next(t.test_id for t in index.tests if t.run == 1 and t.status == "complete")
    k = [t["test_id"] for t in tests].index(second_run)
    data = from_records(str(records), second_run)
    assert data.result["test_id"] == second_run and "warnings" not in data.result
    assert [h["test_id"] for h in data.history] == [t["test_id"] for t in tests[:k]]  # the first run's
    assert from_records(str(records), "latest").result["test_id"] == tests[-1]["test_id"]


# ----------------------------------------------------------------------------- breaks from recorded events


def test_recorded_events_place_breaks_on_their_samples(tmp_path: Path) -> None:
    def batch(k0: int, n: int, events: tuple[SourceEvent, ...] = ()) -> SampleBatch:
        k = np.arange(k0, k0 + n)
        return SampleBatch.from_columns(100.0 + k / 1000, k / 1000, np.full(n, 100.0), k, np.zeros(n), events, "s")

    reset = SourceEvent(EventKind.DEVICE_RESET, 100.35, "s", seq=300)
    lost = SourceEvent(EventKind.LOST, 100.5, "s", count=20, seq=500)
    few = SourceEvent(EventKind.LOST, 100.6, "s", count=2, seq=620)  # two samples: no break
    old_reset = SourceEvent(EventKind.DEVICE_RESET, 100.7995, "s")  # a record from before events named a sample
    lg = McapLogger(tmp_path, "m")
    for b in (batch(0, 250), batch(250, 250, (reset,)), batch(520, 100, (lost,)), batch(622, 300, (few, old_reset))):
        lg.on_batch(b)
    lg.stop()
    rec = recording(read_log(list_recordings(tmp_path / "recordings")[0]), "x")
    assert rec.axis == "device"
    seq = np.concatenate([np.arange(0, 500), np.arange(520, 620), np.arange(622, 922)])
    assert [(int(seq[i]), why.split(" (")[0]) for i, why in rec.breaks] == [
        (300, "device reset"), (520, "20 samples lost"), (800, "device reset")]


def test_records_without_samples_come_from_the_summary_or_from_a_killed_file_read_through(
    records: Path, tmp_path: Path
) -> None:
    path = list_recordings(records)[-1]
    full, light = read_log(path), read_log(path, samples=False)
    assert light.complete and len(light.samples) == 0 and light.metadata == full.metadata
    assert (light.events, light.results, light.config) == (full.events, full.results, full.config)
    cut = tmp_path / path.name
    data = path.read_bytes()
    cut.write_bytes(data[: len(data) - 2000])  # no footer, no summary: a killed writer's file
    torn, torn_light = read_log(cut), read_log(cut, samples=False)
    assert not torn_light.complete and torn_light.events == torn.events and torn_light.results == torn.results
    assert torn_light.config == full.config


def test_a_report_of_the_directory_is_its_newest_complete_test(records: Path, tmp_path: Path) -> None:
    out = tmp_path / "r.html"
    assert main(["report", str(records), "-o", str(out), "--no-png"]) == 0
    newest = published(records)[-1]["test_id"]
    assert newest in out.read_text()


def test_two_runs_stay_two_when_their_clock_offsets_are_the_same(
    records: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """time_ns - monotonic_ns is one number for every start in a boot but for the nanoseconds between the two
    readings: two runs once shared it here and were taken as one. Each start draws its own run_id."""
    ids = {read_log(p, samples=False).metadata["run_id"] for p in list_recordings(records)}
    assert len(ids) == 2

    def same_offset(path: Path, samples: bool = True, warn: bool = True) -> Any:
        lg = read_log(path, samples=samples, warn=warn)
        lg.metadata["host_clock_offset_ns"] = "1700000000000000000"
        return lg

    monkeypatch.setattr(testindex, "read_log", same_offset)
    index = testindex.index_recordings(records)
    assert len(index.runs()) == 2
