"""Plans and sets in the configuration, ``ballbar gcode --plan NAME`` and ``ballbar analyze`` with a library."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ballbar.analysis.plans import SIGNATURE_STEP, PlanLibrary, default_signature, signature_code
from ballbar.analysis.program import arc_start_deg
from ballbar.daemon import config as cfgmod
from ballbar.daemon.cli import main
from ballbar.tools.gcode import DIALECTS
from ballbar.tools.machine3d import Machine3D, program_of, set_tests
from ballbar.tools.nccheck import check_against_plan, program_moves, signatures
from ballbar.tools.ncinterp import interpret
from ballbar.tools.simulator_cli import write_csv

SET_TOML = """
[plan]
sample_hz = 100.0

[plans.xy]
plane = "XY"

[plans.zx]
plane = "ZX"
start_deg = -115.0
overshoot_deg = 5.0
data_arc_deg = 220.0

[plans.yz]
plane = "YZ"
start_deg = -25.0
overshoot_deg = 5.0
data_arc_deg = 220.0

[plans.yz.limits]
enabled = true
G_b_um = 30.0

[plans.big]
radius_mm = 150.0
feed_mm_min = 2000.0
signature = 3

[sets.machine]
plans = ["xy", "zx", "yz"]
window_minutes = 120.0
"""


@pytest.fixture
def set_toml(tmp_path: Path) -> Path:
    p = tmp_path / "set.toml"
    p.write_text(SET_TOML)
    return p


def ballbar(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", *args], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


def test_plans_inherit_plan_and_carry_signatures_and_their_own_limits(set_toml: Path) -> None:
    cfg = cfgmod.load(str(set_toml), env={})
    lib = cfg.library
    assert lib.names == ("xy", "zx", "yz", "big")
    assert cfg.plan == lib.first.plan and cfg.cal_mm == 100.0  # the bar as assembled for the first plan
    assert lib.get("zx").plan.sample_hz == 100.0 and lib.get("zx").plan.feed_mm_min == 1000.0
    assert [p.signature for p in lib.plans] == [default_signature("xy"), default_signature("zx"),
                                                default_signature("yz"), 3]
    assert cfg.limits_of("yz").enabled and cfg.limits_of("yz").G_b_um == 30.0 and not cfg.limits_of("xy").enabled
    assert cfg.limits_enabled and cfg.sets["machine"].plans == ["xy", "zx", "yz"]
    recorded = cfg.to_dict()
    assert recorded["plans"]["yz"]["limits"]["G_b_um"] == 30.0 and recorded["sets"]["machine"]["window_minutes"] == 120
    assert cfgmod.library_of(recorded) == lib  # what the recordings keep gives the same library back
    more = cfgmod.load(str(set_toml), ["plans.zx.feed_mm_min=2000", "plans.xy.limits.enabled=true"], env={})
    assert more.library.get("zx").plan.feed_mm_min == 2000.0 and more.limits_of("xy").enabled


def test_a_single_plan_configuration_is_unchanged() -> None:
    cfg = cfgmod.load(None, ["plan.radius_mm=150"], env={})
    assert cfg.plans == {} and cfg.sets == {}
    assert cfg.library == PlanLibrary.single(cfg.plan) and cfg.library.first.name == "default"
    assert "plans" not in cfg.to_dict() and "sets" not in cfg.to_dict()


@pytest.mark.parametrize("lines, needle", [
    (['[plans.a]\nradius_mm = -1'], "[plans.a] radius_mm must be > 0"),
    (['[plans.a]\nradius = 1'], "unknown key plans.a.radius"),
    (['[plans.a]\n[plans.b]\nfeed_in_mm = 2.0'], "every plan of a library has the feed-in of the first"),
    (['[plans.a]\nsignature = 5\n[plans.b]\nsignature = 5'], "plans a and b have the same signature 5"),
    (['[plans.a]\nsignature = 125\n[plans.b]'], "signature is a whole number within 0..124"),
    (['[plans."a b"]'], "1..40 letters"),
    (['[plans.a]\n[sets.s]\nplans = ["a", "q"]'], "sets.s.plans: no plan 'q'"),
    (['[plans.a]\n[sets.s]\nplans = []'], "sets.s.plans must name at least one plan"),
    (['[plans.a]\n[sets.s]\nplans = ["a"]\nwindow_minutes = 0'], "sets.s.window_minutes must be > 0"),
    (['[plans.a.limits]\nG_b_um = -3.0\nenabled = true'], "plans.a.limits: "),
    (['plans = 3'], "[plans] must be a table"),
])
def test_bad_plans_and_sets_are_one_error_exit_2(tmp_path: Path, lines: list[str], needle: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text("\n".join(lines) + "\n")
    proc = ballbar("run", "--config", str(f), "--print-config")
    assert proc.returncode == 2, proc.stderr
    assert needle in proc.stderr and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


# --------------------------------------------------------------------------- ballbar gcode


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_every_plans_program_carries_its_signature_through_the_interpreter(set_toml: Path, dialect: str) -> None:
    """Each plan's program, as ballbar gcode writes it, read back by the controller's interpreter: the plan's
    path and timing exactly (the signature's excursions split off), and its code read back from the moves."""
    lib = cfgmod.load(str(set_toml), env={}).library
    for p in lib.plans:
        proc = ballbar("gcode", "--dialect", dialect, "--config", str(set_toml), "--plan", p.name, "--repeat", "2")
        assert proc.returncode == 0, proc.stderr
        text = proc.stdout
        assert check_against_plan(text, dialect, p.plan) == []
        step = SIGNATURE_STEP * p.plan.feed_in_mm
        found = signatures(interpret(text, dialect), p.plan.plane)
        assert [signature_code([round(d / step) for d in depths]) for depths in found] == [p.signature] * 2
        for depths in found:  # each depth within the rounding of its symbol's, none near R
            assert all(abs(d / step - round(d / step)) < 0.02 and d < 0.75 * p.plan.feed_in_mm for d in depths)


@pytest.mark.parametrize("dialect", sorted(DIALECTS))
def test_the_simulated_programs_are_those_ballbar_gcode_writes(set_toml: Path, dialect: str) -> None:
    """What the recognition survey and the simulated device run (:func:`~ballbar.tools.machine3d.program_of`)
    is, move by move, what the controller runs of ``ballbar gcode``'s program: the signature's excursions and
    dwells, then the test, at the plan's feed (to the program's decimals)."""
    lib = cfgmod.load(str(set_toml), env={}).library
    for p in lib.plans:
        text = ballbar("gcode", "--dialect", dialect, "--config", str(set_toml), "--plan", p.name).stdout
        ran = program_moves(interpret(text, dialect), p.plan.plane,
                            start_deg=arc_start_deg(p.plan, p.plan.direction_list[0]))
        want = program_of(p)
        ran = ran[: len(want)]  # then the move away from the pivot, which the test does not time
        assert [m.kind for m in ran] == [m.kind for m in want], p.name
        for a, b in zip(ran, want, strict=True):
            assert math.dist(a.start, b.start) < 1e-3 and math.dist(a.end, b.end) < 1e-3, (p.name, a, b)
            assert a.duration_s == b.duration_s, (p.name, a, b)


def test_gcode_of_a_set_writes_one_program_per_plan(set_toml: Path, tmp_path: Path) -> None:
    out = tmp_path / "programs"
    proc = ballbar("gcode", "--dialect", "fanuc", "--config", str(set_toml), "--plan", "machine", "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    files = sorted(p.name for p in out.iterdir())
    assert files == ["xy.nc", "yz.nc", "zx.nc"]
    numbers = sorted(next(line for line in (out / f).read_text().splitlines() if line.startswith("O"))
                     for f in files)
    assert numbers == ["O2304 (BALLBAR)", "O2305 (BALLBAR)", "O2306 (BALLBAR)"]
    assert "G_b_um <= 30" in proc.stderr  # yz's own limits are said


@pytest.mark.parametrize("args, needle", [
    ([], "holds 4 plans (xy, zx, yz, big; sets: machine): choose one with --plan NAME"),
    (["--plan", "machine"], "is a set of 3 plans: give -o DIR"),
    (["--plan", "nope"], "--plan nope: no plan of that name"),
    (["--plan", "zx", "--radius-mm", "150"], "plan flags would change its program"),
])
def test_gcode_with_a_library_refuses_what_is_not_a_plan(set_toml: Path, args: list[str], needle: str) -> None:
    proc = ballbar("gcode", "--dialect", "linuxcnc", "--config", str(set_toml), *args)
    assert proc.returncode == 2 and needle in proc.stderr, proc.stderr


def test_gcode_of_a_single_plan_has_no_signature(tmp_path: Path) -> None:
    proc = ballbar("gcode", "--dialect", "linuxcnc", "--config", "/dev/null", "--radius-mm", "150")
    assert proc.returncode == 0 and "signature" not in proc.stdout and "R 150 mm" in proc.stdout


# --------------------------------------------------------------------------- ballbar analyze


def test_analyze_recognises_each_test_and_takes_a_named_plan(set_toml: Path, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    cfg = cfgmod.load(str(set_toml), env={})
    csv = tmp_path / "set.csv"
    machine = Machine3D.from_settings({"backlash_z_um": 3.0, "squareness_zx_urad": 20.0, "noise_um": 0.1})
    for i, (_name, res) in enumerate(set_tests(cfg.library, ["zx", "big"], machine, 100.0, repeat=2)):
        write_csv(str(csv), res.t_s, res.length_mm, append=i > 0)
    assert main(["analyze", str(csv), "--config", str(set_toml), "--list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [r["status"] for r in rows] == ["complete", "complete"]
    assert main(["analyze", str(csv), "--config", str(set_toml), "--test", "1", "--json"]) == 0
    zx = json.loads(capsys.readouterr().out)
    assert zx["plan"]["name"] == "zx" and zx["plan"]["axes"] == ["Z", "X"]
    assert abs(zx["parameters"]["backlash_x_um"]["value"] - 3.0) < 0.1  # Z's lost motion: ZX's first axis
    assert abs(zx["parameters"]["squareness_urad"]["value"] - 20.0) < 0.5
    assert main(["analyze", str(csv), "--config", str(set_toml), "--test", "2", "--json"]) == 0
    big = json.loads(capsys.readouterr().out)
    assert big["plan"]["name"] == "big" and big["plan"]["radius_mm"] == 150.0
    assert math.isclose(big["timing"]["measured_feed_mm_min"], 2000.0, rel_tol=0.002)
    # --plan NAME: every test analysed as that plan, whatever it ran
    assert main(["analyze", str(csv), "--config", str(set_toml), "--test", "1", "--plan", "yz", "--json"]) == 0
    chosen = json.loads(capsys.readouterr().out)
    assert chosen["plan"]["name"] == "yz" and chosen["recognition"]["method"] == "chosen"
    assert "verdict" not in zx  # no limits for zx; yz's own (G(b) 30 um) give its verdict
    assert [(e["name"], e["limit"]) for e in chosen["verdict"]["limits"]] == [("G_b_um", 30.0)]
    # plan flags: a plan of one's own, the library set aside (the CSV's first test as a 220 deg ZX test)
    assert main(["analyze", str(csv), "--config", str(set_toml), "--plane", "ZX", "--start-deg", "-115",
                 "--overshoot-deg", "5", "--data-arc-deg", "220", "--sample-hz", "100", "--json"]) == 0
    own = json.loads(capsys.readouterr().out)
    assert own["plan"]["name"] == "default" and own["recognition"]["method"] == "only"
    assert own["parameters"]["backlash_x_um"]["value"] == zx["parameters"]["backlash_x_um"]["value"]
    assert main(["analyze", str(csv), "--config", str(set_toml), "--plan", "nope"]) == 2
    assert "no plan of that name" in capsys.readouterr().err


def test_analyze_says_a_test_of_no_plan_is_unrecognised(set_toml: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    lib = cfgmod.load(str(set_toml), env={}).library
    strange = PlanLibrary.from_plans({"xy": lib.get("xy").plan, "other": lib.get("xy").plan.with_(dwell_s=0.7)},
                                     {"xy": lib.get("xy").signature, "other": 77})
    csv = tmp_path / "other.csv"
    (_name, res), = set_tests(strange, ["other"], Machine3D(), 100.0, repeat=1)
    write_csv(str(csv), res.t_s, np.asarray(res.length_mm))
    assert main(["analyze", str(csv), "--config", str(set_toml), "--json"]) == 1
    err = capsys.readouterr().err
    assert "signature reads code 77, which no plan of the library carries" in err and err.count("\n") == 1
