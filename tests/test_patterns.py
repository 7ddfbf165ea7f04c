"""Every mask is its physical model projected on the bar (analysis/README.md)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ballbar.analysis.patterns import BY_NAME, LIBRARY, Geometry, design

R, V = 100.0, 1000.0 / 60.0
rng = np.random.default_rng(7)
U = rng.uniform(-math.pi, 3 * math.pi, 4000)
D = rng.choice([-1.0, 1.0], U.size)
G = Geometry(U, D, rng.uniform(-1, 1, U.size), V, R, 5.0, 10.0)


def project(DX: np.ndarray, DY: np.ndarray) -> np.ndarray:
    """Suh & Lee eq. 2 to first order: dR = DX cos u + DY sin u."""
    return DX * np.cos(U) + DY * np.sin(U)


def col(name: str) -> np.ndarray:
    return BY_NAME[name].columns(G, math.radians(3.0))


vX = -D * V * np.sin(U)
vY = D * V * np.cos(U)
X, Y = R * np.cos(U), R * np.sin(U)
ZERO = np.zeros_like(U)

PHYSICAL = {
    # name: (DX, DY) for a parameter of 1 unit
    "backlash_x": (-0.5 * np.sign(vX), ZERO),
    "backlash_y": (ZERO, -0.5 * np.sign(vY)),
    # m = 1/KX - 1/KY = 1 ms: DX = -vX/KX, DY = -vY/KY; only the difference shows, take 1/KY = 0
    "servo_mismatch": (-vX * 1e-3 * 1000.0, ZERO),
    "squareness": (1e-6 * Y * 1000.0, ZERO),
    "lateral_play_x": (ZERO, -0.5 * np.sign(vX)),
    "lateral_play_y": (-0.5 * np.sign(vY), ZERO),
    "straightness_x": (ZERO, (X / R) ** 2),
    "straightness_y": ((Y / R) ** 2, ZERO),
}


@pytest.mark.parametrize("name", sorted(PHYSICAL))
def test_mask_is_projection_of_physical_model(name: str) -> None:
    DX, DY = PHYSICAL[name]
    np.testing.assert_allclose(col(name)[:, 0], project(DX, DY), atol=1e-9)


def test_scale_mismatch_is_the_separable_part_of_two_scales() -> None:
    # DX = eX X, DY = eY Y with eX = 1 ppm, eY = 0: dR = R (eX+eY)/2 + R (eX-eY)/2 cos 2u
    dr = project(1e-6 * X * 1000, ZERO)
    np.testing.assert_allclose(col("scale_mismatch")[:, 0] + R * 1e-3 / 2, dr, atol=1e-12)


def test_master_slave_is_a_flipping_constant_vector() -> None:
    sigma = np.where(np.abs(np.sin(U)) >= np.abs(np.cos(U)), 1.0, -1.0)
    e1, e2 = np.array([1, 1]) / math.sqrt(2), np.array([1, -1]) / math.sqrt(2)
    for k, e in enumerate((e1, e2)):
        np.testing.assert_allclose(col("master_slave")[:, k], project(sigma / 2 * e[0], sigma / 2 * e[1]), atol=1e-12)


def test_seed_equations() -> None:
    """Suh & Lee eq. 4, 6 and 8 in analysis/README.md's reading."""
    a, b = 3.0, -2.0
    # eq. 6: steps a at 45/225 deg and b at 135/315 deg
    ms = col("master_slave") @ np.array([a, b])
    for at, size in ((45, a), (225, a), (135, b), (315, b)):
        u = np.radians([at - 1e-6, at + 1e-6])
        g = Geometry(u, np.ones(2), np.zeros(2), V, R)
        step = BY_NAME["master_slave"].columns(g, 1.0) @ np.array([a, b])
        assert abs(abs(step[1] - step[0]) - abs(size)) < 1e-4
    assert ms.shape == U.shape
    # eq. 8: dR = d (F/2) sin 2u (KY - KX) / (KX KY) with F the path speed
    KX, KY = 30.0, 33.0
    m_ms = (1 / KX - 1 / KY) * 1000.0
    eq8 = D * (V / 2) * np.sin(2 * U) * (KY - KX) / (KX * KY) * 1000.0
    np.testing.assert_allclose(col("servo_mismatch")[:, 0] * m_ms, eq8, rtol=1e-12, atol=1e-12)
    # eq. 4: backlash steps of b/2 at the reversals, sign flipping with direction
    bx = col("backlash_x")[:, 0]
    np.testing.assert_allclose(np.abs(bx), 0.5 * np.abs(np.cos(U)) * (np.sin(U) != 0), atol=1e-12)


def test_domain_magnitude_anchors() -> None:
    """analysis/README.md: at R = 100 mm, F = 1000 mm/min, 1 ms of mismatch is 8.3 um on sin 2u; 10 urad is 0.5 um."""
    assert abs(np.max(np.abs(col("servo_mismatch"))) - 8.333) < 0.01
    assert abs(np.max(np.abs(col("squareness") * 10)) - 0.5) < 0.001


def test_reversal_spike_decays_from_its_reversal_point_in_its_direction() -> None:
    u = np.radians(np.array([0.0, 3.0, 6.0, -3.0]))
    g = Geometry(u, np.ones(4), np.zeros(4), V, R)
    s = BY_NAME["reversal_spike_x_pos_ccw"].columns(g, math.radians(3.0))[:, 0]
    np.testing.assert_allclose(s[:3], np.exp(-np.array([0.0, 1.0, 2.0])), rtol=1e-12)
    assert s[3] < 1e-40  # just before the reversal: a whole turn since the last one
    g_cw = Geometry(u, -np.ones(4), np.zeros(4), V, R)
    assert np.all(BY_NAME["reversal_spike_x_pos_ccw"].columns(g_cw, 0.05) == 0)


def test_cyclic_pair_gives_any_phase() -> None:
    phi = 0.7
    arg = 2 * math.pi * R * np.cos(U) / 5.0
    want = np.sin(arg + phi) * np.cos(U)
    got = col("cyclic_x") @ np.array([math.cos(phi), math.sin(phi)])
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_design_has_every_column() -> None:
    A = design(LIBRARY, G, 0.05)
    assert A.shape == (U.size, sum(p.q for p in LIBRARY))
    assert np.isfinite(A).all()
