"""`ballbar analyze`: the readable summary, --json, and one-line errors on bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from masksynth import FULL_TRUTH, mask_recording

from ballbar.analysis import TestPlan
from ballbar.daemon.cli import main

PLAN = TestPlan(sample_hz=100)


@pytest.fixture(scope="module")
def good_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    t, L = mask_recording(PLAN, FULL_TRUTH, fs=100.0, noise_um=0.1)
    p = tmp_path_factory.mktemp("rec") / "test.csv"
    np.savetxt(p, np.column_stack([t, L]), delimiter=",", header="t_s,length_mm", comments="", fmt="%.9f")
    return p


def run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(args)
    out, err = capsys.readouterr()
    return code, out, err


def test_json_has_the_contract(good_csv: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the recording follows the masks exactly: the seed's step backlash, no servo dynamics
    masks = ["--lost-motion", "step", "--servo-model", "linear"]
    code, out, err = run(["analyze", str(good_csv), "--sample-hz", "100", "--json", *masks], capsys)
    assert code == 0, err
    res = json.loads(out)
    for key in ("parameters", "iso230_4", "timing", "advice", "residual_rms_um"):
        assert key in res
    p = res["parameters"]["backlash_x_um"]
    assert set(p) >= {"value", "stderr", "unit", "p_value", "share_pct", "significant", "identifiable"}
    assert abs(p["value"] - 4.0) < 0.1 and p["unit"] == "um" and p["significant"]
    for k in ("x_pos_ccw", "x_neg_cw", "y_pos_cw", "y_neg_ccw"):
        assert f"reversal_spike_{k}_um" in res["parameters"]
    for k in ("G_ccw_um", "G_cw_um", "G_b_um", "H_um", "F_max_um", "F_min_um", "conditions"):
        assert k in res["iso230_4"]
    assert res["timing"]["measured_feed_mm_min"] == pytest.approx(1000.0, abs=1.0)
    assert any(a["pattern"] == "backlash_x_um" and a["unit"] == "um" for a in res["advice"])


def test_summary_is_readable(good_csv: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run(["analyze", str(good_csv), "--sample-hz", "100"], capsys)
    assert code == 0
    assert "Ranked findings" in out and "ISO 230-4" in out and "Advice" in out and "backlash_x_um" in out


def test_plan_file_and_flags(good_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plan = tmp_path / "plan.toml"
    plan.write_text('[plan]\nradius_mm = 100.0\nsample_hz = 100\n[machine]\ncontroller = "fanuc"\n')
    code, out, err = run(["analyze", str(good_csv), "--plan", str(plan), "--json"], capsys)
    assert code == 0, err
    res = json.loads(out)
    assert any("No.1851" in a.get("controller_parameter", "") for a in res["advice"])
    bad = tmp_path / "bad.toml"
    bad.write_text("[plan]\nradius = 100\n")
    code, _, err = run(["analyze", str(good_csv), "--plan", str(bad)], capsys)
    assert code == 2 and "unknown plan key 'radius'" in err


def _write(tmp_path: Path, name: str, text: str) -> str:
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize(
    "content, needle",
    [
        ("", "empty file"),
        ("time,len\n0,1\n", "header must name the columns t_s,length_mm"),
        ("t_s,length_mm\n", "header but no samples"),
        ("t_s,length_mm\n0.0,101.5\n0.1,abc\n", ":3: not a number: 'abc'"),
        ("t_s,length_mm\n0.0,101.5\n0.1\n", ":3: expected 2 comma-separated values"),
        ("t_s,length_mm\n0.0,101.5\n0.1,nan\n", ":3: length_mm is not a finite number"),
        ("t_s,length_mm\n0.0,101.5\n0.1,101.5\n", "no feed-in found"),
    ],
)
def test_bad_input_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str, needle: str
) -> None:
    path = _write(tmp_path, "bad.csv", content)
    code, out, err = run(["analyze", path], capsys)
    assert code == 1
    assert needle in err
    assert err.count("\n") == 1 and "Traceback" not in err and out == ""


def test_binary_and_missing_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    p = tmp_path / "bin.csv"
    p.write_bytes(b"t_s,length_mm\n\xff\xfe\x00garbage")
    code, _, err = run(["analyze", str(p)], capsys)
    assert code == 1 and "not a text CSV file" in err
    code, _, err = run(["analyze", str(tmp_path / "nope.csv")], capsys)
    assert code == 1 and "no such file" in err


def test_plan_that_does_not_match_the_data(good_csv: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run(["analyze", str(good_csv), "--feed-mm-min", "500"], capsys)
    assert code == 1 and "plan does not match the data" in err
    code, _, err = run(["analyze", str(good_csv), "--radius-mm", "150"], capsys)
    assert code == 1 and "no feed-in found" in err
    code, _, err = run(["analyze", str(good_csv), "--feed-in-mm", "1.0"], capsys)
    assert code == 1 and ("no feed-in found" in err or "plan does not match" in err)
    code, _, err = run(["analyze", str(good_csv), "--radius-mm", "-3"], capsys)
    assert code == 2 and "radius_mm must be > 0" in err


def test_truncated_recording(good_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lines = good_csv.read_text().splitlines()
    short = _write(tmp_path, "short.csv", "\n".join(lines[: len(lines) // 2]) + "\n")
    code, _, err = run(["analyze", short], capsys)
    assert code == 1 and "before the feed-out" in err


def test_console_script_runs_without_traceback(tmp_path: Path) -> None:
    path = _write(tmp_path, "bad.csv", "t_s,length_mm\n0,inf\n")
    proc = subprocess.run(
        [sys.executable, "-m", "ballbar.daemon.cli", "analyze", path], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 1 and "Traceback" not in proc.stderr and "not a finite number" in proc.stderr


# ----------------------------------------------------------------------------- bad time axes


def _shifted(good_csv: Path, tmp_path: Path, name: str, change) -> str:
    data = np.loadtxt(good_csv, delimiter=",", skiprows=1)
    t = change(data[:, 0].copy())
    p = tmp_path / name
    np.savetxt(p, np.column_stack([t, data[:, 1]]), delimiter=",", header="t_s,length_mm", comments="", fmt="%.9f")
    return str(p)


def _one_line_error(args: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    code, out, err = run(args, capsys)
    assert code == 1 and out == "" and err.count("\n") == 1 and "Traceback" not in err, (code, err)
    return err


def test_a_clock_jump_mid_test_is_rejected_not_analysed(
    good_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def jump(t: np.ndarray) -> np.ndarray:
        t[t > 60.0] += 10.0
        return t

    err = _one_line_error(["analyze", _shifted(good_csv, tmp_path, "jump.csv", jump), "--sample-hz", "100", "--json"],
                          capsys)
    assert "clock jump or outage of 10.000 s at t=60.000 s" in err and "run it again" in err


def test_a_time_that_runs_back_beyond_jitter_is_an_error_with_its_line(
    good_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def back(t: np.ndarray) -> np.ndarray:
        t[5000:] -= 50.0
        return t

    err = _one_line_error(["analyze", _shifted(good_csv, tmp_path, "back.csv", back), "--json"], capsys)
    assert ":5002: t_s runs backwards by 49.99 s" in err and "more than timestamp jitter" in err


def test_a_constant_time_column_is_one_line(good_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    err = _one_line_error(["analyze", _shifted(good_csv, tmp_path, "flat.csv", lambda t: np.full_like(t, 5.0))],
                          capsys)
    assert "t_s is 5 s in every one of the" in err and "no time axis to analyse" in err


def test_rows_out_of_order_within_jitter_are_sorted_with_a_warning(
    good_csv: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    def swap(t: np.ndarray) -> np.ndarray:
        t[[3000, 3001]] = t[[3001, 3000]]
        return t

    path = _shifted(good_csv, tmp_path, "jitter.csv", swap)
    code, out, err = run(["analyze", path, "--sample-hz", "100", "--json"], capsys)
    assert code == 0, err
    assert any("1 samples out of time order by at most 0.01 s" in r.getMessage() for r in caplog.records)
    code, plain, _ = run(["analyze", str(good_csv), "--sample-hz", "100", "--json"], capsys)
    a, b = json.loads(out)["timing"], json.loads(plain)["timing"]
    assert a["measured_feed_mm_min"] == pytest.approx(b["measured_feed_mm_min"], abs=1e-3)


def test_list_of_a_csv_and_usage_errors(good_csv: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = run(["analyze", str(good_csv), "--sample-hz", "100", "--list", "--json"], capsys)
    assert code == 0, err
    (row,) = json.loads(out)
    assert row["status"] == "complete" and row["number"] == 1
    assert row["headline"]["findings"][0]["parameter"] and row["headline"]["G_b_um"] > 0
    code, out, _ = run(["analyze", str(good_csv), "--sample-hz", "100", "--list"], capsys)
    assert code == 0 and out.startswith("  1  feed-in at t=") and "complete  G(b) " in out
    code, _, err = run(["analyze", str(good_csv), "--test-id", "latest"], capsys)
    assert code == 2 and "--test-id picks a test from the daemon's MCAP records" in err
    code, _, err = run(["analyze", str(good_csv), "--test", "1", "--test-id", "x"], capsys)
    assert code == 2 and "not both" in err
    code, _, err = run(["analyze", str(good_csv), "--test", "2"], capsys)
    assert code == 1 and "holds 1 test(s), test 2 asked for" in err
