"""The incremental orthogonal fit, its ranking and its identifiability report."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ballbar.analysis.fit import Factor, solve, sse_subset
from ballbar.analysis.patterns import Pattern


def _pat(name: str, q: int = 1) -> Pattern:
    return Pattern(name, tuple(f"{name}_{k}" for k in range(q)), ("um",) * q, lambda g, w: np.zeros(0))


def test_chunked_factor_equals_lstsq_on_the_whole_matrix() -> None:
    rng = np.random.default_rng(1)
    A = rng.normal(size=(3000, 6)) * np.array([1, 10, 0.1, 5, 1, 1e-2])
    y = A @ rng.normal(size=6) + rng.normal(scale=0.1, size=3000)
    f = Factor(6)
    for lo, hi in ((0, 1), (1, 10), (10, 1700), (1700, 3000)):
        f.add(A[lo:hi], y[lo:hi])
    x_ref, res, *_ = np.linalg.lstsq(A, y, rcond=None)
    fit = solve(f, [_pat(f"p{i}") for i in range(6)], vif_limit=1e12)
    np.testing.assert_allclose(fit.x, x_ref, rtol=1e-9, atol=1e-12)
    assert math.isclose(fit.sse, float(res[0]), rel_tol=1e-9)
    assert f.n == 3000


def test_merged_factors_equal_the_stacked_fit() -> None:
    rng = np.random.default_rng(2)
    A1, A2 = rng.normal(size=(500, 4)), rng.normal(size=(300, 4))
    y1, y2 = rng.normal(size=500), rng.normal(size=300)
    f1, f2, f = Factor(4), Factor(4), Factor(4)
    f1.add(A1, y1)
    f2.add(A2, y2)
    f.add(np.vstack([A1, A2]), np.concatenate([y1, y2]))
    m = f1.merged(f2)
    assert m.n == 800
    for cols in ([0, 1, 2, 3], [1, 3], [2], []):
        assert math.isclose(sse_subset(m.rows, cols), sse_subset(f.rows, cols), rel_tol=1e-10)


def test_subset_sse_equals_refit_on_those_columns() -> None:
    rng = np.random.default_rng(3)
    A = rng.normal(size=(400, 5))
    y = rng.normal(size=400)
    f = Factor(5)
    f.add(A, y)
    for cols in ([0], [1, 4], [0, 2, 3]):
        _, res, *_ = np.linalg.lstsq(A[:, cols], y, rcond=None)
        assert math.isclose(sse_subset(f.rows, cols), float(res[0]), rel_tol=1e-10)


def test_collinear_pattern_is_reported_not_identifiable_with_its_partner() -> None:
    rng = np.random.default_rng(4)
    u = rng.uniform(0, 2 * np.pi, 2000)
    A = np.column_stack([np.cos(u), np.sin(u), 2.0 * np.sin(u) + 1e-9 * rng.normal(size=u.size)])
    y = A[:, 0] * 3 + A[:, 1] * 2 + rng.normal(scale=0.01, size=u.size)
    f = Factor(3)
    f.add(A, y)
    pats = [_pat("a"), _pat("b"), _pat("c")]
    fit = solve(f, pats)
    assert fit.used == [True, True, False]
    assert "b" in fit.reasons["c"] and "variance inflation" in fit.reasons["c"]
    assert abs(fit.x[0] - 3) < 1e-3 and abs(fit.x[1] - 2) < 1e-3
    assert math.isnan(fit.x[2])


def test_pattern_without_support_is_not_identifiable() -> None:
    rng = np.random.default_rng(5)
    A = np.column_stack([np.ones(500), np.zeros(500)])
    A[7, 1] = 1.0  # a single sample
    y = 2.0 + rng.normal(scale=0.1, size=500)
    f = Factor(2)
    f.add(A, y)
    fit = solve(f, [_pat("a"), _pat("spike")], effect_scale=np.abs(A).max(axis=0))
    assert fit.used == [True, False]
    assert "no samples" in fit.reasons["spike"]


def test_standard_errors_are_calibrated_for_white_noise() -> None:
    rng = np.random.default_rng(6)
    u = np.linspace(0, 2 * np.pi, 600, endpoint=False)
    A = np.column_stack([np.ones_like(u), np.cos(u), np.sin(2 * u)])
    z = []
    for _ in range(300):
        y = A @ np.array([1.0, -2.0, 0.5]) + rng.normal(scale=0.3, size=u.size)
        f = Factor(3)
        f.add(A, y)
        fit = solve(f, [_pat("a"), _pat("b"), _pat("c")])
        z.append((fit.x - [1.0, -2.0, 0.5]) / np.sqrt(np.diag(fit.cov)))
    z = np.array(z)
    assert np.all(np.abs(z.std(axis=0) - 1.0) < 0.15)


def test_autocorrelated_residual_inflates_the_uncertainty() -> None:
    rng = np.random.default_rng(8)
    A = np.column_stack([np.ones(2000), np.linspace(-1, 1, 2000)])
    y = A @ [1.0, 0.5] + rng.normal(size=2000)
    f = Factor(2)
    f.add(A, y)
    pats = [_pat("a"), _pat("b")]
    white = solve(f, pats, rho=0.0)
    corr = solve(f, pats, rho=0.8)
    assert math.isclose(corr.kappa, 9.0)
    np.testing.assert_allclose(np.sqrt(np.diag(corr.cov)), 3.0 * np.sqrt(np.diag(white.cov)))


@pytest.mark.parametrize("amp, expect_sig", [(0.0, False), (2.0, True)])
def test_extra_sum_of_squares_ranks_and_tests(amp: float, expect_sig: bool) -> None:
    rng = np.random.default_rng(9)
    u = np.linspace(0, 2 * np.pi, 1000, endpoint=False)
    A = np.column_stack([np.cos(u), np.sin(2 * u), np.cos(3 * u)])
    y = 5 * A[:, 0] + amp * A[:, 2] + rng.normal(scale=0.2, size=u.size)
    f = Factor(3)
    f.add(A, y)
    fit = solve(f, [_pat("big"), _pat("zero"), _pat("maybe")], effect_scale=np.ones(3))
    assert fit.terms["big"].significant and fit.terms["big"].p_value < 1e-12
    assert fit.terms["maybe"].significant is expect_sig
    assert math.isclose(sum(t.share_pct for t in fit.terms.values()), 100.0)
    assert fit.terms["big"].share_pct > fit.terms["zero"].share_pct


def test_a_timing_spread_widens_the_errors_and_weakens_the_tests_it_reaches() -> None:
    """A covariance through the timing is added to the fit's: the parameter it reaches has the larger standard
    error and the larger p; the one it does not reach is unchanged; a zero one changes nothing."""
    rng = np.random.default_rng(8)
    u = rng.uniform(0, 2 * np.pi, 3000)
    A = np.column_stack([np.ones_like(u), np.cos(2 * u), np.sin(2 * u)])
    y = A @ np.array([1.0, 0.02, 0.5]) + rng.normal(scale=0.1, size=u.size)
    f = Factor(3)
    f.add(A, y)
    pats = [_pat("radius"), _pat("scale"), _pat("servo")]
    plain = solve(f, pats, min_effect_um=0.0)
    same = solve(f, pats, min_effect_um=0.0, timing_cov=np.zeros((3, 3)))
    np.testing.assert_allclose(same.cov, plain.cov)
    assert [t.p_value for t in same.terms.values()] == [t.p_value for t in plain.terms.values()]
    timing = np.zeros((3, 3))
    timing[1, 1] = 0.02**2  # the scale moves with the timing by as much as it is worth
    wide = solve(f, pats, min_effect_um=0.0, timing_cov=timing)
    assert math.sqrt(wide.cov[1, 1]) > 3 * math.sqrt(plain.cov[1, 1])
    assert wide.terms["scale"].p_value > 10 * plain.terms["scale"].p_value
    assert plain.terms["scale"].significant and not wide.terms["scale"].significant
    assert wide.cov[2, 2] == plain.cov[2, 2]
    assert pytest.approx(plain.terms["servo"].F) == wide.terms["servo"].F

