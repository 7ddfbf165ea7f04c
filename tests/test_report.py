"""`ballbar report`'s gathering: a test from a recording or from the daemon's records, its curves and history.

The records are made by the real daemon (``ballbar run`` on the ``sim:``
source, as fast as it computes) so that the ids, files and results are the
daemon's own.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ballbar.analysis.errors import DataError
from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan
from ballbar.daemon.cli import main
from ballbar.daemon.mcap import list_recordings, read_log
from ballbar.tools.report import from_recording, from_records, published_difference, select_history

MACHINE = "mill<7>"
PLAN_SETS = ["plan.overshoot_deg=20", "plan.sample_hz=250"]


@pytest.fixture(scope="module")
def records(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three tests recorded by the daemon (machine id with characters that need care)."""
    state = tmp_path_factory.mktemp("state")
    cmd = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=250&speedup=max&repeat=3",
           "--tests", "3", "--state-dir", str(state), "--machine-id", MACHINE,
           "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"']
    for s in PLAN_SETS:
        cmd += ["--set", s]
    env = dict(os.environ, BALLBAR_CONFIG="/nonexistent-on-purpose.toml")
    env.pop("BALLBAR_CONFIG")
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return state / "recordings"


def published_tests(records: Path) -> list[dict]:
    return [r for p in list_recordings(records) for r in read_log(p, samples=False).results if r["kind"] == "test"]


def test_the_daemon_gives_every_test_its_own_id(records: Path) -> None:
    ids = [r["test_id"] for r in published_tests(records)]
    assert len(ids) == 3
    assert len(set(ids)) == 3, ids  # three tests within one second still get three ids


def test_latest_from_records_is_the_published_test_with_its_curves_and_history(records: Path) -> None:
    published = published_tests(records)
    data = from_records(str(records), "latest")
    r = data.result
    assert r["test_id"] == published[-1]["test_id"]
    assert r["machine_id"] == MACHINE
    # Re-analysed from the recorded samples with the recorded configuration: the published numbers.
    assert published_difference(r, published[-1]) is None
    assert "warnings" not in r
    for key, p in r["parameters"].items():
        if p["value"] is not None:
            assert p["value"] == pytest.approx(published[-1]["parameters"][key]["value"], rel=1e-6, abs=1e-6)
    # Curves: both data arcs; the residual they imply is the fit's.
    assert set(data.curves) == {"ccw", "cw"}
    res = np.concatenate([c["measured_um"] - c["model_um"] for c in data.curves.values()])
    assert math.sqrt(float(np.mean(res**2))) == pytest.approx(r["residual_rms_um"], rel=1e-9)
    for d, c in data.curves.items():
        assert c["u_deg"].size == c["measured_um"].size == c["model_um"].size == c["t_s"].size > 100
        span = c["u_deg"].max() - c["u_deg"].min()
        assert 355 < span <= 360.0, (d, span)
    # The CCW arc's angles rise with time, the CW arc's fall.
    assert np.all(np.diff(data.curves["ccw"]["u_deg"]) > 0)
    assert np.all(np.diff(data.curves["cw"]["u_deg"]) < 0)
    assert [h["test_id"] for h in data.history] == [p["test_id"] for p in published[:2]]
    assert "2 earlier test result(s)" in data.history_note


def test_a_test_by_id_has_only_the_tests_before_it_as_history(records: Path) -> None:
    published = published_tests(records)
    data = from_records(str(records), published[1]["test_id"])
    assert data.result["test_id"] == published[1]["test_id"]
    assert [h["test_id"] for h in data.history] == [published[0]["test_id"]]
    first = from_records(str(records), published[0]["test_id"])
    assert first.history == []
    assert "no earlier test results" in first.history_note


def test_unknown_test_id_names_the_newest_ids(records: Path) -> None:
    with pytest.raises(DataError, match=r"no test 'nope' in the records \(the newest: mill<7>-"):
        from_records(str(records), "nope")


def test_records_that_are_missing_or_empty_say_so(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no such directory"):
        from_records(str(tmp_path / "absent"), "latest")
    with pytest.raises(DataError, match="holds no ballbar recordings"):
        from_records(str(tmp_path), "latest")


def test_overridden_options_are_reported_as_a_difference(records: Path) -> None:
    data = from_records(str(records), "latest", AnalysisOptions(lost_motion="step", servo_model="linear"))
    assert data.result["warnings"], "a re-analysis with other options must say it differs from the published one"
    assert "differs from the published" in data.result["warnings"][0]


def test_from_one_recorded_file_adopts_the_published_identity(records: Path) -> None:
    files = list_recordings(records)
    published = published_tests(records)
    plan = TestPlan(overshoot_deg=20.0, sample_hz=250.0)
    # The second file starts with a preroll of the host's last 10 s: at speedup=max that is the whole first
    # test, so the second file's own test is the second found in it.
    data = from_recording(str(files[1]), plan, MachineConfig(), AnalysisOptions(), test=2, records=str(records))
    assert data.result["test_id"] == published[1]["test_id"]
    assert [h["test_id"] for h in data.history] == [published[0]["test_id"]]


def test_history_keeps_the_same_machine_earlier_and_comparable() -> None:
    plan = TestPlan().to_dict()
    me = {"kind": "test", "machine_id": "a", "test_id": "a-3", "t_wall": "2026-11-03T00:00:00Z", "plan": plan}

    def res(tid: str, day: int, machine: str = "a", **plan_changes: object) -> dict:
        return {"kind": "test", "machine_id": machine, "test_id": tid, "t_wall": f"2026-11-0{day}T00:00:00Z",
                "plan": dict(plan, **plan_changes)}

    cands = [res("a-2", 2), res("a-1", 1), res("b-1", 1, machine="b"), res("a-4", 4),
             res("a-0", 1, feed_mm_min=2000.0), dict(res("a-c", 1), kind="circle"), me]
    hist, note = select_history(me, cands)
    assert [h["test_id"] for h in hist] == ["a-1", "a-2"]
    assert "1 under other conditions left out" in note


def test_report_cli_usage_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["report"]) == 2
    assert "give a recording FILE or --test-id" in capsys.readouterr().err
    assert main(["report", "x.csv", "--test-id", "latest"]) == 2
    assert main(["report", "--test-id", "latest", "--records", str(tmp_path / "none")]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and "no such directory" in err  # the usage line above, then one line


def test_reading_records_without_samples_gives_the_same_messages(records: Path) -> None:
    for p in list_recordings(records):
        full, light = read_log(p), read_log(p, samples=False)
        assert len(full.samples) > 0 and len(light.samples) == 0
        assert light.results == full.results and light.events == full.events and light.config == full.config


def test_results_published_in_the_same_millisecond_keep_their_order_in_the_history() -> None:
    """A replay at full speed publishes several results in one batch, within one millisecond of wall time:
    the host time of the samples that ended each test orders them."""
    from ballbar.tools.report import select_history

    def res(i: int, host: float) -> dict:
        return {"kind": "test", "machine_id": "m", "test_id": f"m-{i}", "t_wall": "2026-11-23T08:00:55.255Z",
                "last_sample_t_host": host, "plan": {}}

    first, second, third = res(1, 10.0), res(2, 20.0), res(3, 30.0)
    history, note = select_history(dict(second), [third, second, first])
    assert [h["test_id"] for h in history] == ["m-1"], note
    history, _ = select_history(dict(third), [third, second, first])
    assert [h["test_id"] for h in history] == ["m-1", "m-2"]
