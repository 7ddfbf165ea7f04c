"""Readings quantised by a gauge's resolution (analysis/README.md, "When the model does not fit").

A digital indicator of 1 um resolution whose own noise is below that step
repeats its reading: second differences of consecutive samples are then
mostly 0, while the reading carries at least ``q / sqrt(12)`` of noise.  The
step is found in the data; the noise floor and the uncertainties carry it.
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbar.analysis import TestPlan
from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.validity import reading_step, sensor_noise
from ballbar.daemon.cli import main
from ballbar.protocol.ascii import decode, encode
from ballbar.protocol.gauges import PROFILES
from ballbar.tools.simulator import MachineModel, simulate

MACHINE = dict(backlash_x_um=3.0, backlash_y_um=-2.0, kv_x_per_s=30.0, kv_y_per_s=33.0, squareness_urad=15.0,
               scale_x_ppm=5.0, centre_x_um=8.0, centre_y_um=-5.0, master_slave_a_um=0.8)


def present(result: dict[str, Any], truth: dict[str, Any]) -> list[tuple[str, float]]:
    """Each machine parameter the machine has (the set-up's left out): its error in stated standard errors."""
    out = []
    for key, p in result["parameters"].items():
        want = truth.get(key)
        if not want or p["value"] is None or key.startswith(("centre_", "radius_")):
            continue
        assert p["stderr"] is not None and p["stderr"] > 0, key
        out.append((key, abs(p["value"] - want) / p["stderr"]))
    return out


def only_test(t: np.ndarray, L: np.ndarray, plan: TestPlan) -> dict[str, Any]:
    tests = [r for r in analyze_recording(t, L, plan) if r["kind"] == "test"]
    assert len(tests) == 1
    return dict(tests[0])


@pytest.mark.parametrize("q", [1e-3, 5e-4, 1e-4])
def test_the_step_is_found_where_nearly_all_values_sit_on_it(q: float) -> None:
    rng = np.random.default_rng(1)
    smooth = 100.0 + 0.004 * np.sin(np.linspace(0.0, 12.0, 4000))
    for noise_steps in (0.05, 0.3, 3.0):
        v = np.round((smooth + rng.normal(0.0, noise_steps * q, smooth.size)) / q) * q
        assert reading_step(v) == pytest.approx(q, rel=1e-6), noise_steps
    # a few glitches off the grid (a reading caught mid-update) do not hide it
    v[::400] += 0.37 * q
    assert reading_step(v) == pytest.approx(q, rel=1e-6)
    # as a CSV's decimals parse: the nearest double to each decimal
    text = "\n".join(f"{x:.{math.ceil(-math.log10(q) - 1e-9)}f}" for x in v[:2000])
    assert reading_step(np.array([float(s) for s in text.split()])) == pytest.approx(q, rel=1e-6)


def test_no_step_where_the_values_sit_on_no_grid() -> None:
    rng = np.random.default_rng(2)
    smooth = 100.0 + 0.004 * np.sin(np.linspace(0.0, 12.0, 4000))
    assert reading_step(smooth + rng.normal(0.0, 1e-4, smooth.size)) == 0.0
    # stored to 1 pm (the CSV's resolution) under 0.1 um of noise: the smallest differences are far below a step
    assert reading_step(np.round((smooth + rng.normal(0.0, 1e-4, smooth.size)) / 1e-9) * 1e-9) == 0.0
    # half the values on a grid is no grid
    v = np.round(smooth / 1e-3) * 1e-3
    v[::2] = smooth[::2] + rng.normal(0.0, 1e-4, v[::2].size)
    assert reading_step(v) == 0.0
    assert reading_step(np.full(100, 100.0)) == 0.0


def test_the_noise_of_a_quantised_reading_is_at_least_its_quantisation() -> None:
    y = np.round(0.004e3 * np.sin(np.linspace(0.0, 12.0, 4000)))  # um, a 1 um step, no noise of its own
    assert sensor_noise(y) < 0.01
    assert sensor_noise(y, 1.0) == pytest.approx(1.0 / math.sqrt(12.0))
    rng = np.random.default_rng(3)
    noisy = y + rng.normal(0.0, 0.5, y.size)  # noise above the floor is the data's own
    assert sensor_noise(noisy, 0.1) == pytest.approx(0.5, rel=0.1)


@pytest.mark.parametrize("decimals", [3, 4])
def test_a_gauge_profiles_readings_give_a_valid_test_within_its_uncertainties(decimals: int) -> None:
    """A Mitutoyo Digimatic reading at 50 Hz: 4 decimals of a mm (the profile's 0.1 um) and 3 (the common
    0.001 mm indicator), the gauge's own noise below its step."""
    fmt = replace(PROFILES["mitutoyo"].fmt, decimals=decimals)
    q_um = fmt.resolution_um
    assert q_um == pytest.approx(10.0 ** (3 - decimals))
    assert PROFILES["mitutoyo"].fmt.resolution_um == pytest.approx(0.1)
    assert PROFILES["tesa"].fmt.resolution_um == pytest.approx(0.01)
    plan = TestPlan(sample_hz=50.0)
    sim = simulate(plan, MachineModel(noise_um=0.2 * q_um, **MACHINE), seed=4)  # type: ignore[arg-type]
    got = decode(encode(sim.length_mm, fmt, prefix=PROFILES["mitutoyo"].prefix), fmt, final=True).readings.value_mm
    assert got.size == sim.length_mm.size
    assert np.max(np.abs(got - sim.length_mm)) <= 0.5e-3 * q_um + 1e-12
    res = only_test(sim.t_s, got, plan)
    checks = res["fit"]["checks"]
    assert res["fit"]["valid"], res["fit"]["invalid_reasons"]
    assert checks["reading_step_um"] == pytest.approx(q_um, rel=1e-6)
    assert checks["sensor_noise_um"] >= q_um / math.sqrt(12.0) * (1.0 - 1e-6)
    errs = present(res, sim.truth)
    assert {k for k, _ in errs} >= {"backlash_x_um", "backlash_y_um", "squareness_urad", "master_slave_a_um"}
    assert all(z < 3.0 for _, z in errs), errs


def test_a_quantised_csv_is_analysed_valid(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`ballbar analyze` of a CSV whose lengths sit on 1 um steps (written with 3 decimals, as a 0.001 mm
    indicator's software exports them), at 15.625 Hz."""
    plan = TestPlan(sample_hz=15.625)
    sim = simulate(plan, MachineModel(noise_um=0.1, quantum_um=1.0, **MACHINE), seed=5)  # type: ignore[arg-type]
    p = tmp_path / "quantised.csv"
    np.savetxt(p, np.column_stack([sim.t_s, sim.length_mm]), delimiter=",", header="t_s,length_mm", comments="",
               fmt=("%.6f", "%.3f"))
    code = main(["analyze", str(p), "--sample-hz", "15.625", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    res = json.loads(out)
    assert res["fit"]["valid"], res["fit"]["invalid_reasons"]
    assert res["fit"]["checks"]["reading_step_um"] == pytest.approx(1.0, rel=1e-6)
    assert all(z < 3.0 for _, z in present(res, sim.truth)), present(res, sim.truth)


def test_random_quantised_machines_are_valid_and_within_their_uncertainties() -> None:
    """Random machines read at 0.1 to 1 um steps, 15.625 and 50 Hz, the gauge's noise below or near its step:
    every test valid, and the present patterns within three stated standard errors of their truth, nearly all
    (at most 1 in 20; a survey of 72 machines had all 399 inside)."""
    rng = np.random.default_rng(34)
    zs: list[tuple[str, float]] = []
    for i, (q, fs) in enumerate([(q, fs) for q in (1.0, 0.5, 0.1) for fs in (15.625, 50.0)] * 2):
        kx = float(rng.uniform(20.0, 50.0))
        m = MachineModel(
            backlash_x_um=float(rng.uniform(-6, 6)), backlash_y_um=float(rng.uniform(-6, 6)), kv_x_per_s=kx,
            kv_y_per_s=kx * float(rng.uniform(0.9, 1.1)), squareness_urad=float(rng.uniform(-30, 30)),
            scale_x_ppm=float(rng.uniform(-10, 10)), centre_x_um=float(rng.uniform(-20, 20)),
            centre_y_um=float(rng.uniform(-20, 20)), noise_um=float(rng.uniform(0.0, 0.3 * q)),
            master_slave_a_um=float(rng.uniform(-1, 1)) if rng.random() < 0.5 else 0.0, quantum_um=q,
        )
        plan = TestPlan(sample_hz=fs)
        sim = simulate(plan, m, seed=i)
        res = only_test(sim.t_s, sim.length_mm, plan)
        assert res["fit"]["valid"], (q, fs, res["fit"]["invalid_reasons"])
        assert res["fit"]["checks"]["reading_step_um"] == pytest.approx(q, rel=1e-6)
        zs += present(res, sim.truth)
    outside = [(k, z) for k, z in zs if z > 3.0]
    assert len(zs) >= 50 and len(outside) <= 0.05 * len(zs), outside
