"""``ballbar.analysis.stats``: the F and chi-squared tails, against closed forms and ``scipy.stats``."""

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
RTOL = 1e-10


def close(a: float, b: float, rtol: float = RTOL) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b or abs(a - b) <= rtol * abs(b)


def test_closed_forms_over_the_whole_range() -> None:
    """Where the tails have closed forms, they hold to 1e-10 down to 1e-300, in both tails: F with 2 degrees of
    freedom in the numerator or the denominator, chi-squared with 1 and 2 (the fit's commonest tests)."""
    for x in np.geomspace(1e-9, 1e9, 400):
        x = float(x)
        for d in (1, 2, 3, 7, 40, 1234, 75_373, 1_545_099):
            want = math.exp(-(d / 2) * math.log1p(2 * x / d))  # F(2, d): (1 + 2x/d)^(-d/2)
            if want > 1e-300:
                assert close(stats.f.sf(x, 2, d), want), (x, d)
            want = -math.expm1(-(d / 2) * math.log1p(2 / (d * x)))  # F(d, 2): 1 - (d x / (2 + d x))^(d/2)
            if want > 1e-300:
                assert close(stats.f.sf(x, d, 2), want), (x, d)
        assert close(stats.f.sf(x, 1, 1), 1 - 2 / math.pi * math.atan(math.sqrt(x))), x  # F(1, 1)
        if x / 2 < 690:
            assert close(stats.chi2.sf(x, 2), math.exp(-x / 2)), x
        if math.erfc(math.sqrt(x / 2)) > 1e-300:
            assert close(stats.chi2.sf(x, 1), math.erfc(math.sqrt(x / 2))), x


def test_symmetric_f_is_one_half_at_one() -> None:
    """F(d, d) has its median at 1, also where both degrees of freedom are large (Stirling's series)."""
    for d in (1, 2, 7, 29, 30, 31, 100, 10_000, 1_000_000):
        assert close(stats.f.sf(1.0, d, d), 0.5, 1e-12), d


def test_the_rules_of_scipy_stats_at_the_edges() -> None:
    """Invalid degrees of freedom or NaN give NaN, the support's start a tail of 1, +inf a tail of 0; elsewhere
    the values agree with scipy.stats (whose own last digits are not the reference: see the closed forms)."""
    for x in XS:
        for d1 in DFS:
            for d2 in DFS:
                got, want = stats.f.sf(x, d1, d2), float(sps.f.sf(x, d1, d2))
                assert close(got, want, 1e-9) or abs(got - want) < 1e-10, (x, d1, d2, got, want)
        for df in DFS:
            got, want = stats.chi2.sf(x, df), float(sps.chi2.sf(x, df))
            assert close(got, want, 1e-9) or abs(got - want) < 1e-10, (x, df, got, want)


@pytest.mark.parametrize("seed", range(3))
def test_random_arguments_as_the_fit_meets_them(seed: int) -> None:
    """The arguments of the fit's F-tests (a few numerator degrees of freedom, up to a 10 kHz test's samples in
    the denominator) and of its likelihood-ratio tests: scipy's values to 1e-9 wherever it is above 1e-250 (below,
    scipy's own error grows: 20 % at 1e-290)."""
    rng = np.random.default_rng(seed)
    for _ in range(2000):
        x = float(rng.lognormal(0.0, 3.0))
        d1, d2 = int(rng.integers(1, 60)), int(rng.integers(1, 1_600_000))
        want = float(sps.f.sf(x, d1, d2))
        if want > 1e-250:
            assert close(stats.f.sf(x, d1, d2), want, 1e-9), (x, d1, d2)
        want = float(sps.chi2.sf(x, d1))
        if want > 1e-250:
            assert close(stats.chi2.sf(x, d1), want, 1e-9), (x, d1)


def test_a_tests_analysis_imports_no_heavy_scipy_subpackage(tmp_path: Path) -> None:
    """``ballbar analyze`` pays for every import at every run: a whole test's analysis (settling fit, noise
    findings, p-values) must not pull in scipy.stats, scipy.optimize, scipy.fft or scipy.special, which cost more
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
    heavy = [m for m in loaded if m.split(".")[:2] in (
        ["scipy", "stats"], ["scipy", "optimize"], ["scipy", "fft"], ["scipy", "special"])]
    assert not heavy, heavy
