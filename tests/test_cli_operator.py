"""The operator commands `ballbar gcode` and `ballbar report` through the real command line."""

from __future__ import annotations

from pathlib import Path

import pytest

from ballbar.analysis.plan import TestPlan
from ballbar.daemon.cli import main
from ballbar.tools.nccheck import check_against_plan
from ballbar.tools.simulator import MachineModel, simulate
from ballbar.tools.simulator_cli import write_csv


def test_gcode_writes_the_plan_from_the_daemons_configuration(tmp_path: Path) -> None:
    cfg = tmp_path / "ballbar.toml"
    cfg.write_text("[plan]\nradius_mm = 50.0\nfeed_mm_min = 800.0\nplane = \"YZ\"\n")
    out = tmp_path / "bb.ngc"
    assert main(["gcode", "--dialect", "linuxcnc", "--config", str(cfg), "-o", str(out)]) == 0
    text = out.read_text()
    plan = TestPlan(radius_mm=50.0, feed_mm_min=800.0, plane="YZ")
    assert check_against_plan(text, "linuxcnc", plan) == []
    # The same program against the default plan is wrong, so the check above could fail.
    assert check_against_plan(text, "linuxcnc", TestPlan()) != []


def test_gcode_flags_override_the_plan_file_and_the_origin_is_checked(tmp_path: Path) -> None:
    plan_file = tmp_path / "plan.toml"
    plan_file.write_text("[plan]\nradius_mm = 150.0\nfeed_mm_min = 2000.0\n")
    out = tmp_path / "bb.nc"
    args = ["gcode", "--dialect", "fanuc", "--plan", str(plan_file), "--feed-mm-min", "1500",
            "--origin", "10,20,30", "--work-offset", "G55", "-o", str(out)]
    assert main(args) == 0
    text = out.read_text()
    assert "G55" in text
    plan = TestPlan(radius_mm=150.0, feed_mm_min=1500.0)
    assert check_against_plan(text, "fanuc", plan, origin=(10.0, 20.0, 30.0)) == []
    assert check_against_plan(text, "fanuc", plan) != []  # about the wrong pivot


def test_gcode_to_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["gcode", "--dialect", "siemens", "--directions", "ccw", "--data-arc-deg", "220",
                 "--overshoot-deg", "5", "--plane", "ZX", "--start-deg", "-110"]) == 0
    text = capsys.readouterr().out
    assert "G18" in text and "G2 " not in text and "M30" in text
    plan = TestPlan(directions="ccw", data_arc_deg=220.0, overshoot_deg=5.0, plane="ZX", start_deg=-110.0)
    assert check_against_plan(text, "siemens", plan) == []


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--dialect", "haas"], "invalid choice"),
        (["--dialect", "fanuc", "--origin", "1,2"], "--origin must be three"),
        (["--dialect", "fanuc", "--radius-mm", "-5"], "radius_mm must be > 0"),
        (["--dialect", "fanuc", "--repeat", "0"], "--repeat must be at least 1"),
    ],
)
def test_gcode_usage_errors_exit_2(args: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["gcode", *args]) == 2
    assert message in capsys.readouterr().err


def test_gcode_outside_the_timing_model_warns_and_still_writes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    out = tmp_path / "fast.nc"
    # At 6000 mm/min the acceleration to the feed takes V^2/2A = 2.5 mm at 2000 mm/s^2: more than 1 deg at R 100.
    assert main(["gcode", "--dialect", "fanuc", "--feed-mm-min", "6000", "--overshoot-deg", "1", "-o", str(out)]) == 0
    assert out.stat().st_size > 0
    assert any("outside the analyzer's timing model" in r.getMessage() for r in caplog.records)


def test_report_from_a_csv_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plan = TestPlan(overshoot_deg=20.0, sample_hz=250.0)
    sim = simulate(plan, MachineModel(backlash_x_um=4.0, squareness_urad=15.0))
    rec = tmp_path / "run 1.csv"
    write_csv(str(rec), sim.t_s, sim.length_mm)
    out = tmp_path / "r.html"
    assert main(["report", str(rec), "--overshoot-deg", "20", "--sample-hz", "250", "-o", str(out)]) == 0
    written = capsys.readouterr().out.split()
    assert written[0] == str(out)
    assert all(Path(p).stat().st_size > 0 for p in written)
    html = out.read_text(encoding="utf-8")
    assert "Backlash X" in html and "run 1" in html


def test_an_output_that_cannot_be_written_is_one_line_and_exit_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    assert main(["gcode", "--dialect", "fanuc", "-o", str(blocker / "bb.nc")]) == 1
    err = capsys.readouterr().err
    assert err.startswith(f"error: {blocker / 'bb.nc'}: cannot write:") and err.count("\n") == 1
    plan = TestPlan(overshoot_deg=20.0, sample_hz=250.0)
    sim = simulate(plan, MachineModel(backlash_x_um=4.0))
    rec = tmp_path / "rec.csv"
    write_csv(str(rec), sim.t_s, sim.length_mm)
    args = ["report", str(rec), "--overshoot-deg", "20", "--sample-hz", "250", "-o", str(blocker / "r.html")]
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "cannot write" in err and err.count("\n") == 1 and "Traceback" not in err
    assert sorted(tmp_path.iterdir()) == sorted([blocker, rec])  # no temporary file left behind
