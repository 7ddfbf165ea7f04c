"""Circular-test figures of ASME B5.54 and JIS B 6190-4 beside ISO 230-4 (analysis/standards.py)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from schemacheck import problems
from scipy.optimize import minimize

from ballbar.analysis import standards
from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.errors import PlanError
from ballbar.analysis.iso230 import _lsc_residual
from ballbar.analysis.plan import STANDARDS, AnalysisOptions, TestPlan
from ballbar.daemon.cli import main as cli_main
from ballbar.daemon.commands import STANDARD_CHOICES
from ballbar.tools.simulator import MachineModel, simulate
from ballbar.tools.simulator_cli import write_csv


def brute_min_zone(u: np.ndarray, dr: np.ndarray) -> float:
    """The minimum-zone range by a derivative-free search from several starts (slow, independent)."""
    def span(x: np.ndarray) -> float:
        return float(np.ptp(dr - x[0] * np.cos(u) - x[1] * np.sin(u)))

    starts = ([0.0, 0.0], [3.0, -2.0], [-4.0, 1.0])
    opts = {"xatol": 1e-11, "fatol": 1e-13, "maxiter": 8000}
    return min(float(minimize(span, x0, method="Nelder-Mead", options=opts).fun) for x0 in starts)


@pytest.mark.parametrize("n,arc", [(40, 360.0), (900, 360.0), (3000, 220.0)])
def test_the_minimum_zone_is_the_smallest_range(n: int, arc: float) -> None:
    rng = np.random.default_rng(n)
    u = np.sort(rng.uniform(0.0, np.radians(arc), n))
    # a lopsided path: a step at one reversal, an ellipse, an offset centre, noise
    dr = 2.5 * (np.sin(u) > 0) + 3.0 * np.cos(2 * u) + 4.0 * np.cos(u) - 1.5 * np.sin(u) + rng.normal(0, 0.2, n)
    mz = np.ptp(standards.min_zone_residual(u, dr))
    assert mz == pytest.approx(brute_min_zone(u, dr), abs=1e-7)
    assert mz < np.ptp(_lsc_residual(u, dr)) - 0.05  # smaller than the least-squares circle's range here


def test_a_round_path_has_no_zone() -> None:
    u = np.linspace(0, 2 * np.pi, 500, endpoint=False)
    r = standards.min_zone_residual(u, 7.0 * np.cos(u) - 2.0 * np.sin(u) + 1.0)
    assert np.ptp(r) < 1e-9


def result(options: AnalysisOptions, tmp: Path | None = None) -> dict[str, Any]:
    plan = TestPlan(sample_hz=500.0)
    m = MachineModel(backlash_x_um=5.0, kv_y_per_s=33.0, spike_y_um=2.0, spike_tau_y_s=0.05, noise_um=0.1)
    s = simulate(plan, m, seed=3)
    if tmp is not None:
        write_csv(str(tmp), s.t_s, s.length_mm)
    out = [r for r in analyze_recording(s.t_s, s.length_mm, plan, options=options, circles=False)
           if r.get("kind") == "test"]
    return json.loads(json.dumps(out[0]))


def test_a_result_carries_the_chosen_standards() -> None:
    plain = result(AnalysisOptions())
    assert "standards" not in plain  # ISO 230-4 alone: as before
    r = result(AnalysisOptions(standards=("iso230_4", "asme_b5_54", "jis_b6190_4")))
    iso, asme, jis = r["iso230_4"], r["standards"]["asme_b5_54"], r["standards"]["jis_b6190_4"]
    # the fit itself is not touched by the choice
    assert r["parameters"] == plain["parameters"] and iso == plain["iso230_4"]
    assert jis["standard"] == "JIS B 6190-4:2008 (ISO 230-4:2005)" and "H_um" not in jis
    for k in ("G_ccw_um", "G_cw_um", "G_b_um", "F_max_um", "F_min_um"):
        assert jis[k] == iso[k]
    assert asme["standard"] == "ASME B5.54-2005" and "minimum-zone" in asme["assumption"]
    assert 0 < asme["circular_deviation_b_um"] <= iso["G_b_um"]
    assert asme["circular_deviation_ccw_um"] <= iso["G_ccw_um"] and asme["circular_deviation_cw_um"] <= iso["G_cw_um"]
    assert asme["H_um"] == pytest.approx(iso["H_um"], abs=1e-9)  # the centre cancels in a difference at one angle
    assert asme["F_max_um"] == iso["F_max_um"]
    for name in ("analysis", "result"):
        payload = dict(r)
        if name == "result":
            payload |= {"machine_id": "m", "t_wall": "2026-01-01T00:00:00.000Z", "test_id": None, "t_host": 0.0,
                        "last_sample_t": None, "last_sample_t_host": None, "latency_ms": None, "time_axis": None}
        else:
            payload["source"] = {"file": "x"}
        assert problems(payload, name) == []


def test_standards_are_named_once_and_checked() -> None:
    assert STANDARD_CHOICES == STANDARDS == standards.KNOWN
    with pytest.raises(PlanError, match="unknown standard 'din'"):
        AnalysisOptions(standards=("din",))
    assert AnalysisOptions.from_dict({"standards": ["asme_b5_54"]}).standards == ("asme_b5_54",)


def test_analyze_states_the_standards(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "t.csv"
    result(AnalysisOptions(), csv)
    capsys.readouterr()
    assert cli_main(["analyze", str(csv), "--sample-hz", "500", "--standard", "asme_b5_54"]) == 0
    out = capsys.readouterr().out
    assert "ASME B5.54-2005: circular deviation CCW" in out and "minimum-zone centre" in out
    assert cli_main(["analyze", str(csv), "--standard", "din"]) == 2
    assert "invalid choice: 'din'" in capsys.readouterr().err
