"""``ballbar.analysis.stats`` gives what ``scipy.stats`` gives, to the bit, edge cases included."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sps

from ballbar.analysis import stats

XS = [-1.0, -0.0, 0.0, 1e-300, 1e-12, 1e-3, 0.1, 0.5, 1.0, 1.7, 3.0, 10.0, 55.5, 1e3, 1e6, math.inf, math.nan]
DFS = [-1.0, 0.0, 0.5, 1.0, 2.0, 3.0, 7.0, 40.0, 1234.0, 1e6, math.nan]


def same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def test_f_sf() -> None:
    for x in XS:
        for d1 in DFS:
            for d2 in DFS:
                assert same(stats.f.sf(x, d1, d2), float(sps.f.sf(x, d1, d2))), (x, d1, d2)


def test_chi2_sf_and_isf() -> None:
    for x in XS:
        for df in DFS:
            assert same(stats.chi2.sf(x, df), float(sps.chi2.sf(x, df))), (x, df)
    for q in [-0.1, 0.0, 1e-300, 1e-9, 0.001, 0.01, 0.05, 0.5, 0.95, 1.0 - 1e-16, 1.0, 1.5, math.nan]:
        for df in DFS:
            assert same(stats.chi2.isf(q, df), float(sps.chi2.isf(q, df))), (q, df)


@pytest.mark.parametrize("seed", range(3))
def test_random_arguments(seed: int) -> None:
    rng = np.random.default_rng(seed)
    for _ in range(2000):
        x = float(rng.lognormal(0.0, 3.0))
        d1, d2 = int(rng.integers(1, 60)), int(rng.integers(1, 200_000))
        assert stats.f.sf(x, d1, d2) == float(sps.f.sf(x, d1, d2))
        assert stats.chi2.sf(x, d1) == float(sps.chi2.sf(x, d1))
        q = float(rng.uniform())
        assert stats.chi2.isf(q, d1) == float(sps.chi2.isf(q, d1))


def test_a_tests_analysis_imports_no_heavy_scipy_subpackage(tmp_path: Path) -> None:
    """``ballbar analyze`` pays for every import at every run: a whole test's analysis (settling fit, noise
    findings, p-values) must not pull in scipy.stats, scipy.optimize or scipy.fft, which together cost more
    to import than the analysis of a 15.625 Hz test takes."""
    from ballbar.analysis.plan import TestPlan
    from ballbar.tools.simulator import MachineModel, simulate

    s = simulate(TestPlan(sample_hz=1000.0), MachineModel(noise_um=0.1, backlash_x_um=3.0), seed=1)
    np.savez(tmp_path / "test.npz", t=s.t_s, L=s.length_mm)
    code = (
        "import sys, numpy as np\n"
        "from ballbar.analysis.engine import analyze_recording\n"
        "from ballbar.analysis.plan import TestPlan\n"
        f"d = np.load({str(tmp_path / 'test.npz')!r})\n"
        "out = analyze_recording(d['t'], d['L'], TestPlan(sample_hz=1000.0))\n"
        "assert any(r['kind'] == 'test' and r['timing']['loop_lag_ms'] for r in out), out\n"
        "print(' '.join(sorted(sys.modules)))\n"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    heavy = [m for m in loaded if m.split(".")[:2] in (["scipy", "stats"], ["scipy", "optimize"], ["scipy", "fft"])]
    assert not heavy, heavy
