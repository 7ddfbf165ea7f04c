"""The independent simulator's physics, checked without the fit."""

from __future__ import annotations

import numpy as np
import pytest

from ballbar.tools.bench import physim as ps

R = 100.0
F = 1000.0
V = F / 60.0


def _ccw_arc(machine: ps.Machine, path: ps.Path, dt: float = 1e-4):
    """Steps of the CCW arc's middle turn: commanded angle (rad) and exact length (mm)."""
    _t, L = ps.bar_length(machine, path, dt)
    xc, yc = ps.command(path, machine, dt)
    u = np.unwrap(np.arctan2(yc, xc))
    r = np.hypot(xc, yc)
    on = np.abs(r - R) < 1e-9
    # the CCW arc: from 90 deg past its start to 90 deg before its end (transient gone)
    sweep = np.radians(path.data_arc_deg + 2 * path.overshoot_deg)
    first = np.flatnonzero(on & (u > np.radians(path.start_deg) + 1e-6))[0]
    sel = on & (np.arange(len(u)) >= first) & (u > np.pi / 2) & (u < sweep - np.pi / 2)
    sel &= np.concatenate([[False], np.diff(u) > 0])
    return u[sel], L[sel]


def test_perfect_machine_reads_the_programmed_radius() -> None:
    axis = ps.Axis(kv=30.0, ff=1.0)
    m = ps.Machine(x=axis, y=axis)
    path = ps.Path(radius_mm=R, feed_mm_min=F)
    _u, L = _ccw_arc(m, path)
    assert np.max(np.abs(L - R)) < 1e-6  # under a nanometre
    _t, s = ps.simulate(m, path, ps.Gauge(sample_hz=250, noise_um=0.1), seed=3)
    arc = np.abs(s - R) < 0.01
    assert 0.08 < np.std(1e3 * (s[arc] - R)) < 0.12
    assert abs(np.mean(1e3 * (s[arc] - R))) < 0.02


def test_servo_mismatch_gives_the_ellipse_of_its_gains() -> None:
    kx, ky = 25.0, 40.0
    m = ps.Machine(x=ps.Axis(kv=kx), y=ps.Axis(kv=ky))
    u, L = _ccw_arc(m, ps.Path(radius_mm=R, feed_mm_min=F))
    A = np.column_stack([np.ones_like(u), np.sin(2 * u), np.cos(2 * u)])
    c, *_ = np.linalg.lstsq(A, 1e3 * (L - R), rcond=None)
    m_ms = 1e3 * (1 / kx - 1 / ky)
    # mask (d V/2) m sin 2u with d = +1, V in mm/s, m in ms: micrometres
    assert c[1] == pytest.approx(V / 2 * m_ms, rel=0.02)
    assert abs(c[2]) < 0.02 * abs(c[1])
    # both axes shrink the circle by their lag: about -(V/K)^2/(2R) each
    shrink = -1e3 * (V**2) * (1 / kx**2 + 1 / ky**2) / (4 * R)
    assert c[0] == pytest.approx(shrink, rel=0.1)


@pytest.mark.parametrize("play, comp", [(10.0, 0.0), (0.0, 8.0), (12.0, 4.0)])
def test_lost_motion_steps_at_the_reversal(play: float, comp: float) -> None:
    axis_y = ps.Axis(kv=30.0, ff=1.0)
    m = ps.Machine(x=ps.Axis(kv=30.0, ff=1.0, play_um=play, comp_um=comp), y=axis_y)
    u, L = _ccw_arc(m, ps.Path(radius_mm=R, feed_mm_min=F))
    dr = 1e3 * (L - R)
    before = dr[np.argmin(np.abs(u - np.radians(170)))]
    after = dr[np.argmin(np.abs(u - np.radians(190)))]
    b = play - comp
    # mask (b/2) d sgn(sin u) cos u: -b/2 cos(10 deg) before X reverses at 180 deg, +b/2 after
    assert after - before == pytest.approx(b * np.cos(np.radians(10)), abs=0.02)


def test_dead_band_holds_the_table_while_the_motor_crosses_the_gap() -> None:
    play = 20.0
    m = ps.Machine(x=ps.Axis(kv=30.0, ff=1.0, play_um=play), y=ps.Axis(kv=30.0, ff=1.0))
    u, L = _ccw_arc(m, ps.Path(radius_mm=R, feed_mm_min=F))
    dr = 1e3 * (L - R)
    near = np.abs(u - np.pi) < np.radians(3)
    # the step is spread over about sqrt(2 b / R) rad past the reversal, not an instant
    width = np.sqrt(2 * play * 1e-3 / R)
    mid = dr[np.argmin(np.abs(u - (np.pi + width / 2)))]
    assert -play / 2 < mid < play / 2
    assert np.ptp(dr[near]) == pytest.approx(play, rel=0.05)


def test_bar_length_is_the_exact_distance() -> None:
    x0, y0 = 1000.0, -500.0  # um: large, where the first-order mask is visibly off
    axis = ps.Axis(kv=30.0, ff=1.0)
    m = ps.Machine(x=axis, y=axis, centre_x_um=x0, centre_y_um=y0)
    u, L = _ccw_arc(m, ps.Path(radius_mm=R, feed_mm_min=F))
    exact = np.hypot(R * np.cos(u) + 1e-3 * x0, R * np.sin(u) + 1e-3 * y0)
    assert np.max(np.abs(L - exact)) < 1e-6
    first_order = R + 1e-3 * (x0 * np.cos(u) + y0 * np.sin(u))
    assert np.max(np.abs(L - first_order)) > 4e-3  # (x0, y0)^2 / 2R: up to 6 um


def test_averaging_gauge_attenuates_by_its_window() -> None:
    kx, ky = 25.0, 40.0
    m = ps.Machine(x=ps.Axis(kv=kx), y=ps.Axis(kv=ky))
    path = ps.Path(radius_mm=50.0, feed_mm_min=2000.0)
    fs = 15.625
    amps = []
    for averaging in (False, True):
        t, s = ps.simulate(m, path, ps.Gauge(sample_hz=fs, noise_um=0.0, averaging=averaging))
        arc = (t > 8) & (t < 14)  # inside the CCW arc, away from its ends
        w = 2 * (path.feed_mm_min / 60 / path.radius_mm)  # sin 2u in time
        A = np.column_stack([np.ones(arc.sum()), np.sin(w * t[arc]), np.cos(w * t[arc])])
        c, *_ = np.linalg.lstsq(A, s[arc], rcond=None)
        amps.append(np.hypot(c[1], c[2]))
    f = w / (2 * np.pi)
    assert amps[1] / amps[0] == pytest.approx(np.sinc(f / fs), rel=2e-3)


def test_quantised_gauge_reads_in_steps() -> None:
    m = ps.Machine()
    t, s = ps.simulate(m, ps.Path(), ps.Gauge(sample_hz=50, noise_um=0.1, quantum_um=1.0))
    steps = np.round(s * 1e3)
    assert np.max(np.abs(s * 1e3 - steps)) < 1e-6
    assert np.median(np.diff(t)) == pytest.approx(1 / 50)
