"""The machine's settings per machine axis (``[machine]``), each plan taking its plane's two.

A set of XY, YZ and ZX on a 3D machine whose axes have distinct gains: each test's analysis gets its own
plane's two (XY X and Y, YZ Y and Z, ZX Z and X), its lag and its advice say so; and the configurations that
cannot mean the machine's axes are refused in one line.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ballbar.analysis.engine import TestAnalyzer, analyze_recording
from ballbar.analysis.plan import MachineAxes, MachineConfig, TestPlan, machine_of
from ballbar.analysis.plans import PlanLibrary
from ballbar.daemon import config as cfgmod
from ballbar.daemon.cli import main
from ballbar.tools.machine3d import Machine3D, set_tests
from ballbar.tools.simulator_cli import write_csv

KV = {"X": 30.0, "Y": 36.0, "Z": 24.0}  # distinct: a plan given another plane's pair shows it
MACHINE = Machine3D.from_settings({"kv_x_per_s": KV["X"], "kv_y_per_s": KV["Y"], "kv_z_per_s": KV["Z"],
                                   "noise_um": 0.1})
AXES = MachineAxes(kv_x_per_s=KV["X"], kv_y_per_s=KV["Y"], kv_z_per_s=KV["Z"], pitch_z_mm=5.0)


def vertical(plane: str) -> TestPlan:
    start = {"ZX": -115.0, "YZ": -25.0}[plane]
    return TestPlan(plane=plane, start_deg=start, overshoot_deg=5.0, data_arc_deg=220.0, sample_hz=100.0)  # type: ignore[arg-type]


LIB = PlanLibrary.from_plans({"xy": TestPlan(sample_hz=100.0), "yz": vertical("YZ"), "zx": vertical("ZX")})
PAIRS = {"xy": ("X", "Y"), "yz": ("Y", "Z"), "zx": ("Z", "X")}


@pytest.fixture(scope="module")
def recording() -> tuple[np.ndarray, np.ndarray]:
    parts = list(set_tests(LIB, ["xy", "yz", "zx"], MACHINE, 100.0, seed=3, repeat=3, gap_s=3.0))
    assert [n for n, _ in parts] == ["xy", "yz", "zx"]
    return np.concatenate([r.t_s for _, r in parts]), np.concatenate([r.length_mm for _, r in parts])


def results_of(t: np.ndarray, L: np.ndarray, machine: MachineAxes | MachineConfig) -> dict[str, dict]:
    out = analyze_recording(t, L, LIB.detection_plan(), machine, library=LIB, circles=False)
    return {r["plan"]["name"]: r for r in out if r["kind"] == "test"}


def test_each_plan_of_a_set_takes_its_planes_two_gains(recording: tuple[np.ndarray, np.ndarray]) -> None:
    res = results_of(*recording, AXES)
    assert sorted(res) == ["xy", "yz", "zx"]
    for name, (first, second) in PAIRS.items():
        r = res[name]
        assert r["plan"]["axes"] == [first, second]
        # what the test's fit was given: its first axis' gain as x, its second's as y
        assert (r["machine"]["kv_x_per_s"], r["machine"]["kv_y_per_s"]) == (KV[first], KV[second]), name
        assert r["machine"]["pitch_x_mm"] == (5.0 if first == "Z" else None), name
        assert r["machine"]["pitch_y_mm"] == (5.0 if second == "Z" else None), name
        lag = r["timing"]
        assert lag["loop_lag_source"] == (f"configured gains kv_{first.lower()}_per_s and "
                                          f"kv_{second.lower()}_per_s"), name
        assert math.isclose(lag["loop_lag_ms"], 500.0 * (1 / KV[first] + 1 / KV[second]), rel_tol=1e-9), name
        # the advice: the slower axis' gain, from the value configured for it, raised to the faster's
        m = r["parameters"]["servo_mismatch_ms"]["value"]
        slow, fast = (first, second) if KV[first] < KV[second] else (second, first)
        assert (m > 0) == (slow == first), (name, m)
        servo = next(a for a in r["advice"] if a["pattern"] == "servo_mismatch_ms")
        assert servo["action"].startswith(f"raise the {slow} position-loop gain from {KV[slow]:.2f} to "), servo
        assert servo["action"].endswith(f"1/s to match {fast}"), servo
        assert math.isclose(KV[slow] + servo["value"], KV[fast], rel_tol=0.03), (name, servo)
    # Z's screw pitch reaches the planes with Z in them, and the others say which key is missing
    assert "cyclic_y_um" in {p for p, v in res["yz"]["parameters"].items() if v.get("identifiable") is not False}
    assert res["xy"]["parameters"]["cyclic_x_um"]["reason"] == (
        "no X screw pitch configured (pitch_x_mm): cyclic error not fitted")
    assert res["zx"]["parameters"]["cyclic_y_um"]["reason"] == (
        "no X screw pitch configured (pitch_x_mm): cyclic error not fitted")


def test_without_gains_the_advice_names_the_keys_of_the_planes_axes(recording: tuple[np.ndarray, np.ndarray],
                                                                     ) -> None:
    res = results_of(*recording, MachineAxes())
    for name, (first, second) in PAIRS.items():
        keys = f"kv_{first.lower()}_per_s and kv_{second.lower()}_per_s"
        servo = next(a for a in res[name]["advice"] if a["pattern"] == "servo_mismatch_ms")
        assert servo["action"].endswith(f"(configure [machine] {keys} for a value)"), servo
        assert "kv_x/kv_y" not in servo["action"]
        assert res[name]["machine"]["kv_x_per_s"] is None
    assert res["zx"]["parameters"]["cyclic_x_um"]["reason"] == (
        "no Z screw pitch configured (pitch_z_mm): cyclic error not fitted")


def test_one_planes_settings_are_every_plans_as_before(recording: tuple[np.ndarray, np.ndarray]) -> None:
    """A MachineConfig (a configuration recorded before the axes were named) goes to every plan as it is, as the
    daemon analysed it then; the live analyzer's ``machine`` follows the plan it uses."""
    old = MachineConfig(kv_x_per_s=KV["X"], kv_y_per_s=KV["Y"])
    res = results_of(*recording, old)
    assert {n: (r["machine"]["kv_x_per_s"], r["machine"]["kv_y_per_s"]) for n, r in res.items()} == dict.fromkeys(
        PAIRS, (KV["X"], KV["Y"]))
    an = TestAnalyzer(LIB.detection_plan(), AXES, library=LIB, circles=False)
    assert an.machine == AXES.for_plane("XY")
    an._use_plan("zx")
    assert an.machine == MachineConfig(pitch_x_mm=5.0, kv_x_per_s=KV["Z"], kv_y_per_s=KV["X"])


def test_machine_axes_round_trip_and_recorded_tables() -> None:
    assert AXES.for_plane("YZ") == MachineConfig(pitch_y_mm=5.0, kv_x_per_s=KV["Y"], kv_y_per_s=KV["Z"])
    assert MachineAxes.of_plane("ZX", AXES.for_plane("ZX")) == MachineAxes(
        kv_z_per_s=KV["Z"], kv_x_per_s=KV["X"], pitch_z_mm=5.0)
    assert machine_of(dict(AXES.to_dict())) == AXES
    assert machine_of({"kv_x_per_s": 30.0}) == MachineAxes(kv_x_per_s=30.0)  # a table written by hand
    recorded = dict(MachineConfig(kv_x_per_s=30.0).to_dict())  # the five keys, as recorded before
    assert machine_of(recorded) == MachineConfig(kv_x_per_s=30.0)


# --------------------------------------------------------------------------- the configuration

SET = """
[plans.xy]
plane = "XY"

[plans.yz]
plane = "YZ"
start_deg = -25.0
overshoot_deg = 5.0
data_arc_deg = 220.0

[plans.zx]
plane = "ZX"
start_deg = -115.0
overshoot_deg = 5.0
data_arc_deg = 220.0

[machine]
kv_x_per_s = 30.0
kv_y_per_s = 36.0
kv_z_per_s = 24.0
pitch_z_mm = 5.0
"""


def ballbar(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", *args], capture_output=True, text=True,
                          timeout=120)


def test_the_configuration_gives_each_plan_its_planes_axes(tmp_path: Path) -> None:
    f = tmp_path / "set.toml"
    f.write_text(SET)
    cfg = cfgmod.load(str(f), env={})
    assert cfg.machine == AXES
    assert {p.name: cfg.machine.for_plane(p.plan.plane).kv_x_per_s for p in cfg.library.plans} == {
        "xy": KV["X"], "yz": KV["Y"], "zx": KV["Z"]}
    assert cfg.to_dict()["machine"]["kv_z_per_s"] == KV["Z"]
    env = cfgmod.load(str(f), env={"BALLBAR__MACHINE__KV_Z_PER_S": "20"})
    assert env.machine.for_plane("ZX").kv_x_per_s == 20.0


@pytest.mark.parametrize("toml", [
    '[machine]\nkv_x_per_s = 30.0\nkv_y_per_s = 33.0\npitch_x_mm = 10.0',  # an XY configuration: as it always was
    '[plan]\nplane = "ZX"\n[machine]\nkv_z_per_s = 24.0\nkv_x_per_s = 30.0',
    '[plan]\nplane = "ZX"\n[machine]\nkv_x_per_s = 30.0\nkv_y_per_s = 36.0\nkv_z_per_s = 24.0',  # Y: a fact, kept
    '[plan]\nplane = "YZ"\n[machine]\nkv_y_per_s = 36.0',
])
def test_what_can_mean_the_machines_axes_is_taken(tmp_path: Path, toml: str) -> None:
    f = tmp_path / "ok.toml"
    f.write_text(toml + "\n")
    cfg = cfgmod.load(str(f), env={})
    if "plane" not in toml:
        assert cfg.machine.for_plane("XY") == MachineConfig(pitch_x_mm=10.0, kv_x_per_s=30.0, kv_y_per_s=33.0)


@pytest.mark.parametrize("toml, needle", [
    (SET + '\n[plans.zx.machine]\nkv_x_per_s = 24.0',
     "plans.zx.machine: the machine's settings are per axis, given once in [machine]"),
    ('[plans.xy]\n[plans.xy.machine]\nkv_x_per_s = 24.0', "plans.xy.machine: the machine's settings are per axis"),
    # x and y as the plan's first and second axis, as they were: Y is not in ZX
    ('[plan]\nplane = "ZX"\n[machine]\nkv_x_per_s = 24.0\nkv_y_per_s = 30.0',
     "machine.kv_y_per_s: no plan moves Y (planes ZX); [machine] keys name the machine's axes now, not a plan's "
     "first and second: set kv_z_per_s and kv_x_per_s for ZX"),
    ('[plan]\nplane = "YZ"\n[machine]\npitch_x_mm = 5.0',
     "machine.pitch_x_mm: no plan moves X (planes YZ)"),
    ('[machine]\nkv_a_per_s = 30.0', "unknown key machine.kv_a_per_s"),
    ('[machine]\nkv_z_per_s = -3.0', "[machine] kv_z_per_s must be > 0"),
])
def test_what_cannot_be_meant_is_refused_in_one_line(tmp_path: Path, toml: str, needle: str) -> None:
    f = tmp_path / "bad.toml"
    f.write_text(toml + "\n")
    proc = ballbar("run", "--config", str(f), "--print-config")
    assert proc.returncode == 2, proc.stderr
    assert needle in proc.stderr and proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_set_of_a_plans_machine_key_is_refused_too(tmp_path: Path) -> None:
    f = tmp_path / "set.toml"
    f.write_text(SET)
    with pytest.raises(cfgmod.ConfigError, match=r"^plans\.zx\.machine: the machine's settings are per axis"):
        cfgmod.load(str(f), ["plans.zx.machine.kv_x_per_s=24"], env={})


def test_analyze_takes_the_machines_axes_from_flags(tmp_path: Path, recording: tuple[np.ndarray, np.ndarray],
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """``ballbar analyze`` of a set's recording: ``--kv-x``, ``--kv-y``, ``--kv-z`` are the machine's axes,
    each test's plan taking its plane's two, as the daemon does."""
    f = tmp_path / "set.toml"
    f.write_text("[plan]\nsample_hz = 100.0\n" + SET.partition("[machine]")[0])  # the set's plans, no [machine]
    csv = tmp_path / "set.csv"
    write_csv(str(csv), *recording)
    for number, name in ((2, "yz"), (3, "zx")):
        assert main(["analyze", str(csv), "--config", str(f), "--test", str(number), "--kv-x", "30", "--kv-y", "36",
                     "--kv-z", "24", "--json"]) == 0
        r = json.loads(capsys.readouterr().out)
        first, second = PAIRS[name]
        assert r["plan"]["name"] == name
        assert (r["machine"]["kv_x_per_s"], r["machine"]["kv_y_per_s"]) == (KV[first], KV[second])


def test_a_recording_made_before_the_axes_were_named_keeps_its_meaning() -> None:
    """A configuration recorded with the five keys of old (x, y: the plan's first and second axis) is analysed as
    the daemon analysed it; a flag that adds a machine axis names its x and y by the recorded plane's axes."""
    from ballbar.daemon.commands import build_parser, configs_from_args, resolve_plan_arg

    zx = vertical("ZX")
    recorded = {"plan": zx.to_dict(), "machine": dict(MachineConfig(kv_x_per_s=KV["Z"], kv_y_per_s=KV["X"]).to_dict())}

    def machine(*flags: str) -> MachineAxes | MachineConfig:
        args = build_parser().parse_args(["analyze", "rec.mcap", *flags])
        resolve_plan_arg(args, ())
        return configs_from_args(args, base={k: dict(v) for k, v in recorded.items()})[1]

    assert machine() == MachineConfig(kv_x_per_s=KV["Z"], kv_y_per_s=KV["X"])
    assert machine("--kv-y", "36") == MachineAxes(kv_z_per_s=KV["Z"], kv_x_per_s=KV["X"], kv_y_per_s=36.0)
    assert machine("--kv-z", "20").for_plane("ZX") == MachineConfig(kv_x_per_s=20.0, kv_y_per_s=KV["X"])


def test_analyze_refuses_flags_written_as_a_plans_first_and_second(tmp_path: Path,
                                                                    recording: tuple[np.ndarray, np.ndarray],
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "set.csv"
    write_csv(str(csv), *recording)
    zx = ["--plane", "ZX", "--start-deg", "-115", "--overshoot-deg", "5", "--data-arc-deg", "220", "--sample-hz", "100"]
    assert main(["analyze", str(csv), *zx, "--kv-x", "24", "--kv-y", "30", "--json"]) == 2
    err = capsys.readouterr().err
    assert "machine.kv_y_per_s: no plan moves Y (planes ZX)" in err and err.count("\n") == 1
    assert main(["analyze", str(csv), *zx, "--kv-z", "24", "--kv-x", "30", "--test", "3", "--json"]) == 0
    r = json.loads(capsys.readouterr().out)
    assert r["plan"]["plane"] == "ZX" and (r["machine"]["kv_x_per_s"], r["machine"]["kv_y_per_s"]) == (24.0, 30.0)
