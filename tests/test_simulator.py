"""The simulator against analysis/README.md's physics, computed here independently of analysis/."""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np
import pytest

from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import centroid_span_s, feed_from_span
from ballbar.tools.simulator import (
    MachineModel,
    SimResult,
    iter_chunks,
    iter_tests,
    simulate,
)
from ballbar.tools.simulator_cli import main, parse_set

PLAN = TestPlan(sample_hz=250.0)  # R = 100 mm, F = 1000 mm/min, 180 deg overshoots, 360 deg data arc
R = PLAN.radius_mm
V = PLAN.feed_mm_s
FAST = 1.0e-3  # integration step for tests that need no sub-millisecond timing


def run(machine: MachineModel, plan: TestPlan = PLAN, step_s: float = FAST, **kw: float) -> SimResult:
    return simulate(plan, machine, step_s=step_s, **kw)


def data_arc(res: SimResult, d: int) -> np.ndarray:
    name = "ccw" if d > 0 else "cw"
    return (res.t_s >= res.events[f"data_start_{name}"]) & (res.t_s <= res.events[f"data_end_{name}"])


def away_from(u: np.ndarray, points_deg: tuple[float, ...], margin_deg: float) -> np.ndarray:
    """True where the angle ``u`` (rad) is more than ``margin_deg`` from every point (mod 360)."""
    ok = np.ones(u.shape, dtype=bool)
    for p in points_deg:
        diff = (np.degrees(u) - p + 180.0) % 360.0 - 180.0
        ok &= np.abs(diff) > margin_deg
    return ok


DFunc = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray]]


def compare_first_order(
    res: SimResult, D: DFunc, tol_um: float, skip: tuple[float, ...] = (), margin_deg: float = 0.0
) -> None:
    """Measured dR vs analysis/README.md: dR = DX cos u + DY sin u, at the commanded angles."""
    for d in res.plan.direction_list:
        m = data_arc(res, d)
        u = np.radians(res.angle_deg[m])
        keep = away_from(u, skip, margin_deg) if skip else np.ones(u.shape, dtype=bool)
        DX, DY = D(u, d)
        pred = DX * np.cos(u) + DY * np.sin(u)
        err = res.deviation_um[m][keep] - pred[keep]
        assert keep.sum() > 1000
        assert np.max(np.abs(err)) < tol_um, (d, float(np.max(np.abs(err))))


def velocities(u: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    return -d * V * np.sin(u), d * V * np.cos(u)


# --------------------------------------------------------------------------- ideal machine


def test_ideal_machine_is_exact() -> None:
    res = run(MachineModel.ideal(), step_s=1e-4)
    t, L, ev = res.t_s, res.length_mm, res.events
    f = PLAN.feed_in_mm
    before = t < ev["feed_in_start"]
    assert before.sum() >= 200
    assert np.max(np.abs(L[before] - (R + f))) < 1e-12
    after = t > ev["feed_out_end"]
    assert np.max(np.abs(L[after] - (R + f))) < 1e-12
    on = (t >= ev["feed_in_end"]) & (t <= ev["feed_out_start"])
    assert np.max(np.abs(L[on] - R)) < 1e-9  # 1e-6 um
    feed_in = (t >= ev["feed_in_start"]) & (t <= ev["feed_in_end"])
    assert np.all(np.diff(L[feed_in]) < 0)
    # The commanded angle runs the program: both data arcs cover the same angles.
    for d in (1, -1):
        a = res.angle_deg[data_arc(res, d)]
        assert a.min() == pytest.approx(180.0, abs=0.1)
        assert a.max() == pytest.approx(540.0, abs=0.1)
    assert res.truth["feed_mm_min"] == pytest.approx(1000.0)
    assert res.truth["servo_mismatch_ms"] == 0.0


def test_default_test_duration_and_sizes() -> None:
    res = run(MachineModel(), sample_hz=100.0)
    # 1 s lead, feed-in, 3 dwells, two 720 deg arcs, feed-out, 1 s tail: ~155 s.
    assert 154.0 < res.t_s[-1] < 156.0
    assert res.t_s.dtype == np.float64 and res.length_mm.dtype == np.float64
    assert np.allclose(np.diff(res.t_s), 0.01)
    assert res.t_s[0] == 0.0


# --------------------------------------------------------------------------- servo


def test_equal_gains_shrink_radius_and_lag_angle() -> None:
    K = 30.0
    x = V / (R * K)  # angular lag, rad
    x0 = 50.0
    res = run(MachineModel(kv_x_per_s=K, kv_y_per_s=K, centre_x_um=x0))
    for d in (1, -1):
        m = data_arc(res, d)
        u = np.radians(res.angle_deg[m])
        A = np.column_stack([np.ones_like(u), np.cos(u), np.sin(u)])
        c, a, b = np.linalg.lstsq(A, res.deviation_um[m], rcond=None)[0]
        # Radius: R (1/sqrt(1 + x^2) - 1) ~ -R x^2 / 2 = -1.54 um (plus x0^2 / 4R from the offset).
        assert c == pytest.approx(-R * x**2 / 2 / 1e-3 + x0**2 / (4 * R * 1e3), rel=0.01)
        # The offset's cosine appears at the actual angle u - d x: lag in the direction of travel.
        lag = d * math.atan2(b, a)
        assert lag == pytest.approx(x, rel=0.01)
        assert math.hypot(a, b) == pytest.approx(x0, rel=1e-3)
    assert res.truth["servo_radius_um"] == pytest.approx(-R * x**2 / 2 / 1e-3, rel=0.01)


def test_velocity_feed_forward_reduces_the_lag() -> None:
    res = run(MachineModel(velocity_ff=0.5, centre_x_um=50.0))
    m = data_arc(res, 1)
    u = np.radians(res.angle_deg[m])
    A = np.column_stack([np.ones_like(u), np.cos(u), np.sin(u)])
    _, a, b = np.linalg.lstsq(A, res.deviation_um[m], rcond=None)[0]
    assert math.atan2(b, a) == pytest.approx(0.5 * V / (R * 30.0), rel=0.02)
    assert res.truth["lag_x_ms"] == pytest.approx(1000 * 0.5 / 30.0)


def test_servo_mismatch_mask_sign_and_size() -> None:
    kx, ky = 30.0, 33.0
    res = run(MachineModel(kv_x_per_s=kx, kv_y_per_s=ky))
    m_ms = 1000.0 * (1 / kx - 1 / ky)  # analysis/README.md: m = 1/KX - 1/KY in ms
    assert res.truth["servo_mismatch_ms"] == pytest.approx(m_ms)
    for d in (1, -1):
        sel = data_arc(res, d)
        u = np.radians(res.angle_deg[sel])
        dr = res.deviation_um[sel]
        first = d * V / 2 * m_ms * np.sin(2 * u)  # (d V / 2) m sin 2u, um
        # First order up to second-order terms in V/(R K): R x^2 ~ 1.5 um.
        assert np.max(np.abs(dr - first)) < 2.5
        A = np.column_stack([np.ones_like(u), np.cos(2 * u), np.sin(2 * u)])
        c0, c2, s2 = np.linalg.lstsq(A, dr, rcond=None)[0]
        assert s2 == pytest.approx(d * V / 2 * m_ms, rel=0.01)
        # The second-order terms: a mean shrink and the spurious scale mismatch
        # analysis/README.md quotes (about -8 ppm for 30/33 at R = 100, F = 1000, commanded angles).
        assert c0 == pytest.approx(res.truth["servo_radius_um"], abs=0.02)
        apparent_ppm = 2 * c2 * 1e-3 / R * 1e6
        assert apparent_ppm == pytest.approx(res.truth["servo_scale_ppm"], abs=0.3)
    assert -9.0 < res.truth["servo_scale_ppm"] < -7.0


# --------------------------------------------------------------------------- lost motion


def test_backlash_sign_away_from_reversals() -> None:
    bx, by = 8.0, 6.0
    res = run(MachineModel.ideal(backlash_x_um=bx, backlash_y_um=by))

    def D(u: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
        vx, vy = velocities(u, d)
        return -bx / 2 * np.sign(vx), -by / 2 * np.sign(vy)

    # Each deadband lasts acos(1 - b/R) ~ 0.7 deg of travel past a reversal.
    compare_first_order(res, D, tol_um=0.01, skip=(0, 90, 180, 270), margin_deg=1.5)
    assert res.truth["backlash_x_um"] == bx and res.truth["backlash_y_um"] == by


def test_backlash_deadband_holds_the_table_after_a_reversal() -> None:
    bx, by = 8.0, 6.0
    res = run(MachineModel.ideal(backlash_x_um=bx, backlash_y_um=by), step_s=1e-4, sample_hz=2000)
    gap = math.degrees(math.acos(1 - bx * 1e-3 / R))  # motor travel to cross the gap: 0.72 deg
    a = np.where(data_arc(res, 1), res.angle_deg, np.nan)
    # CCW through u = 360: X reverses at its + end, Y moves + all along.
    inside = (a > 360.0 + 0.05 * gap) & (a < 360.0 + 0.95 * gap)
    u = np.radians(a[inside])
    held = np.hypot(R - bx / 2e3, R * np.sin(u) - by / 2e3)  # table X stands at R - b/2
    assert inside.sum() > 20
    assert np.max(np.abs(res.length_mm[inside] - held)) < 1e-7
    # Once the gap is crossed the table lags by b/2 the other way.
    out = (a > 360.0 + 1.2 * gap) & (a < 365.0)
    u = np.radians(a[out])
    moving = np.hypot(R * np.cos(u) + bx / 2e3, R * np.sin(u) - by / 2e3)
    assert np.max(np.abs(res.length_mm[out] - moving)) < 1e-7


def test_overcompensated_backlash_leads() -> None:
    bx = -4.0
    res = run(MachineModel.ideal(backlash_x_um=bx))
    compare_first_order(res, lambda u, d: (-bx / 2 * np.sign(velocities(u, d)[0]), 0 * u), 0.01, (0, 180), 0.5)


@pytest.mark.parametrize("takeup_um", [0.0, 20.0])
def test_lateral_play(takeup_um: float) -> None:
    lx, ly = 6.0, -4.0
    res = run(MachineModel.ideal(lateral_play_x_um=lx, lateral_play_y_um=ly, lateral_takeup_um=takeup_um))

    def D(u: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
        vx, vy = velocities(u, d)
        return -ly / 2 * np.sign(vy), -lx / 2 * np.sign(vx)

    compare_first_order(res, D, tol_um=0.01, skip=(0, 90, 180, 270), margin_deg=1.5)


def test_reversal_spikes_decay_from_each_table_reversal() -> None:
    hx, hy, tx, ty = 5.0, 3.0, 0.05, 0.1
    m = MachineModel.ideal(spike_x_um=hx, spike_y_um=hy, spike_tau_x_s=tx, spike_tau_y_s=ty)
    res = run(m, step_s=1e-4, sample_hz=500)
    t, a = res.t_s, res.angle_deg
    for d in (1, -1):
        sel = data_arc(res, d)
        # Reversal times: the commanded angle crosses an axis end (X: k 180, Y: 90 + k 180).
        name = "ccw" if d > 0 else "cw"
        arc = (t >= res.events[f"{name}_start"]) & (t <= res.events[f"{name}_end"])
        ta, aa = t[arc], a[arc]
        expected = np.zeros(sel.sum())
        u = np.radians(a[sel])
        for axis, h, tau, offset in (("x", hx, tx, 0.0), ("y", hy, ty, 90.0)):
            k = np.floor((aa - offset) / 180.0)
            cross = np.flatnonzero(np.diff(k) != 0)
            t_rev = np.array(
                [np.interp(offset + 180.0 * max(k[i], k[i + 1]), aa[i : i + 2][::d], ta[i : i + 2][::d]) for i in cross]
            )
            idx = np.searchsorted(t_rev, t[sel], side="right") - 1
            assert np.all(idx >= 0)
            age = t[sel] - t_rev[idx]
            vx, vy = velocities(u, d)
            v_new = vx if axis == "x" else vy
            D = -h * np.sign(v_new) * np.exp(-age / tau)  # lag against the new direction
            expected += D * (np.cos(u) if axis == "x" else np.sin(u))
            # The bump is outward: right after a reversal of this axis dR ~ +h.
            fresh = age < 0.004
            assert fresh.sum() >= 2
            assert np.all(res.deviation_um[sel][fresh] > 0.9 * min(hx, hy))
            for end in ("pos", "neg"):
                assert res.truth[f"reversal_spike_{axis}_{end}_{name}_um"] == h
        # The reversal is timed to the 0.1 ms grid: h * 1e-4 / tau ~ 0.01 um.
        assert np.max(np.abs(res.deviation_um[sel] - expected)) < 0.03
    assert res.truth["reversal_spike_width_x_deg"] == pytest.approx(math.degrees(V * tx / R))


def test_stick_slip_steps_near_reversals_only() -> None:
    step = 0.5
    res = run(MachineModel.ideal(stick_slip_um=step, stick_slip_speed_mm_s=0.5), step_s=1e-4, sample_hz=2000)
    sel = data_arc(res, 1)
    u = np.radians(res.angle_deg[sel])
    dr = res.deviation_um[sel]
    slow = (np.abs(V * np.sin(u)) < 0.5) | (np.abs(V * np.cos(u)) < 0.5)
    assert np.max(np.abs(dr[~away_from(u, (0, 90, 180, 270), 2.0)])) <= step + 1e-6
    assert np.max(np.abs(dr[~slow & away_from(u, (0, 90, 180, 270), 2.0)])) < 1e-9
    near = ~away_from(u, (0, 90, 180, 270), 1.0)
    assert np.std(dr[near]) > 0.05 * step  # a sawtooth, not a constant


# --------------------------------------------------------------------------- controller, geometry, set-up


def test_master_slave_steps_at_the_changeover() -> None:
    a_um, b_um = 6.0, -4.0
    res = run(MachineModel.ideal(master_slave_a_um=a_um, master_slave_b_um=b_um))

    def D(u: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
        sigma = np.where(np.abs(np.sin(u)) >= np.abs(np.cos(u)), 1.0, -1.0)
        s2 = math.sqrt(2.0)
        return sigma / 2 * (a_um + b_um) / s2, sigma / 2 * (a_um - b_um) / s2

    compare_first_order(res, D, tol_um=0.01, skip=(45, 135, 225, 315), margin_deg=0.2)
    # The library's mask: a step of a at 45 deg.
    for d in (1, -1):
        sel = data_arc(res, d)
        u = res.angle_deg[sel] % 360.0
        dr = res.deviation_um[sel]
        below = dr[(u > 44.0) & (u < 44.8)].mean()
        above = dr[(u > 45.2) & (u < 46.0)].mean()
        assert above - below == pytest.approx(a_um, abs=0.1)


def _cyclic(u: np.ndarray, c: float, p: float, ph: float, axis: int) -> np.ndarray:
    pos = R * (np.cos(u) if axis == 0 else np.sin(u))
    return c * np.sin(2 * np.pi * pos / p + math.radians(ph))


GEOMETRY: list[tuple[str, dict[str, float], DFunc, float]] = [
    ("centre", {"centre_x_um": 30.0, "centre_y_um": -20.0}, lambda u, d: (30.0 + 0 * u, -20.0 + 0 * u), 0.02),
    ("squareness", {"squareness_urad": 100.0}, lambda u, d: (100e-6 * R * np.sin(u) * 1e3, 0 * u), 0.01),
    (
        "scale",
        {"scale_x_ppm": 30.0, "scale_y_ppm": -10.0},
        lambda u, d: (30e-6 * R * np.cos(u) * 1e3, -10e-6 * R * np.sin(u) * 1e3),
        0.01,
    ),
    (
        "straightness",
        {"straightness_x_um": 4.0, "straightness_y_um": -3.0},
        lambda u, d: (-3.0 * np.sin(u) ** 2, 4.0 * np.cos(u) ** 2),
        0.01,
    ),
    (
        "cyclic",
        {"cyclic_x_um": 2.0, "pitch_x_mm": 5.0, "cyclic_x_phase_deg": 30.0, "cyclic_y_um": 1.5, "pitch_y_mm": 8.0},
        lambda u, d: (_cyclic(u, 2.0, 5.0, 30.0, 0), _cyclic(u, 1.5, 8.0, 0.0, 1)),
        0.01,
    ),
]


@pytest.mark.parametrize(("name", "params", "D", "tol"), GEOMETRY, ids=[g[0] for g in GEOMETRY])
def test_geometric_errors_first_order(name: str, params: dict[str, float], D: DFunc, tol: float) -> None:
    res = run(MachineModel.ideal(**params))
    compare_first_order(res, D, tol_um=tol)
    for key, value in params.items():
        if key in res.truth:
            assert res.truth[key] == value
    if name == "scale":
        assert res.truth["scale_mismatch_ppm"] == 40.0


def test_bar_calibration_drift_and_vibration() -> None:
    m = MachineModel.ideal(
        radius_um=7.0, drift_um_per_min=2.0, vibration_um=0.3, vibration_hz=37.0, vibration_phase_deg=20.0
    )
    res = run(m)
    t0 = res.events["feed_in_start"]
    on = (res.t_s >= res.events["feed_in_end"]) & (res.t_s <= res.events["feed_out_start"])
    t = res.t_s[on]
    expected = 7.0 + 2.0 * (t - t0) / 60.0 + 0.3 * np.sin(2 * np.pi * 37.0 * t + math.radians(20))
    assert np.max(np.abs(res.deviation_um[on] - expected)) < 1e-6


# --------------------------------------------------------------------------- timing


def _half_crossing(t: np.ndarray, L: np.ndarray, level: float, rising: bool) -> float:
    i = np.flatnonzero((L[:-1] > level) & (L[1:] <= level) if not rising else (L[:-1] < level) & (L[1:] >= level))[0]
    return float(
        np.interp(level, *((L[i : i + 2], t[i : i + 2]) if rising else (L[i : i + 2][::-1], t[i : i + 2][::-1])))
    )


@pytest.mark.parametrize("kv", [math.inf, 30.0])
def test_feed_override_and_the_programs_timing_model(kv: float) -> None:
    plan = PLAN.with_(sample_hz=1000.0)
    m = MachineModel(kv_x_per_s=kv, kv_y_per_s=kv, feed_override=0.95, accel_mm_s2=1500.0)
    res = run(m, plan)
    V95 = plan.feed_mm_s * 0.95
    c = V95 / 1500.0
    arc_len = R * math.radians(plan.arc_deg)
    ev = res.events
    assert ev["ccw_end"] - ev["ccw_start"] == pytest.approx(arc_len / V95 + c, abs=1e-9)
    assert res.truth["feed_mm_min"] == pytest.approx(950.0)
    assert res.truth["overhead_s"] == pytest.approx(c)
    # The feed-in / feed-out centroids (half-way crossings: symmetric profiles, a linear
    # loop delays both alike) are what analysis.program's schedule predicts.
    level = R + plan.feed_in_mm / 2
    t_in = _half_crossing(res.t_s, res.length_mm, level, rising=False)
    t_out = _half_crossing(res.t_s, res.length_mm, level, rising=True)
    assert t_out - t_in == pytest.approx(centroid_span_s(plan, V95, c), abs=2e-4)
    assert feed_from_span(plan, t_out - t_in, c) * 60 == pytest.approx(950.0, rel=1e-5)
    if math.isinf(kv):
        assert t_in == pytest.approx(ev["feed_in_centroid"], abs=1e-6)


@pytest.mark.parametrize(
    ("length", "accel", "jerk"),
    [
        (100.0, 2000.0, math.inf),
        (1.5, 2000.0, 5e4),
        (0.05, 2000.0, 5e4),
        (0.05, 500.0, math.inf),
        (3.0, math.inf, math.inf),
    ],
)
def test_motion_profile_is_symmetric_and_complete(length: float, accel: float, jerk: float) -> None:
    from ballbar.tools.feed_profile import _Profile

    smooth = accel / jerk if math.isfinite(accel) else 0.0
    p = _Profile(length, V, accel, smooth)
    tau = np.linspace(-0.1, p.duration + 0.1, 20001)
    s = p.position(tau)
    assert s[0] == 0.0 and s[-1] == length
    assert np.all(np.diff(s) >= -1e-12)
    assert np.allclose(p.position(p.duration - tau), length - s, atol=1e-9)
    speed = np.diff(s) / np.diff(tau)
    assert speed.max() <= V * (1 + 1e-6)
    if length / V > V / accel + smooth:  # long enough to reach the feed: s/V + c
        assert p.duration == pytest.approx(length / V + V / accel + smooth)
        assert p.time_at(length / 2) == pytest.approx(p.duration / 2, abs=1e-9)


def test_interpolation_cycle_delays_the_command_by_half_a_cycle() -> None:
    ipo = 0.008
    res = run(MachineModel(ipo_s=ipo, centre_x_um=50.0), step_s=1e-4)
    m = data_arc(res, 1)
    u = np.radians(res.angle_deg[m])
    A = np.column_stack([np.ones_like(u), np.cos(u), np.sin(u)])
    _, a, b = np.linalg.lstsq(A, res.deviation_um[m], rcond=None)[0]
    assert math.atan2(b, a) == pytest.approx(V / R * (1 / 30.0 + ipo / 2), rel=0.01)


def test_jerk_limit_adds_its_smoothing_time() -> None:
    m = MachineModel.ideal(accel_mm_s2=1000.0, jerk_mm_s3=50_000.0)
    res = run(m, step_s=1e-4)
    c = V / 1000.0 + 1000.0 / 50_000.0
    ev = res.events
    assert ev["ccw_end"] - ev["ccw_start"] == pytest.approx(R * math.radians(PLAN.arc_deg) / V + c)
    on = (res.t_s >= ev["feed_in_end"]) & (res.t_s <= ev["feed_out_start"])
    assert np.max(np.abs(res.deviation_um[on])) < 1e-6


# --------------------------------------------------------------------------- sampling


def test_jitter_at_the_sampling_instant() -> None:
    plan = PLAN.with_(sample_hz=10_000.0, overshoot_deg=5.0, data_arc_deg=30.0)
    clean = run(MachineModel.ideal(), plan)
    jit = run(MachineModel.ideal(jitter_s=2e-4), plan)
    assert np.array_equal(clean.t_s, jit.t_s)  # stamped on the nominal clock
    slope = np.gradient(clean.length_mm, clean.t_s)
    fast = np.abs(slope) > 0.9 * V  # feed-in and feed-out cruise, dL/dt = -/+ V
    assert fast.sum() > 1000
    e = (jit.length_mm - clean.length_mm)[fast] / slope[fast]
    assert np.std(e) == pytest.approx(2e-4, rel=0.1)


def test_jitter_on_the_timestamps() -> None:
    clean = run(MachineModel())
    jit = run(MachineModel(jitter_s=1e-3, jitter_stamped=True))
    assert np.array_equal(clean.length_mm, jit.length_mm)
    assert np.std(jit.t_s - clean.t_s) == pytest.approx(1e-3, rel=0.05)


def test_dropped_samples() -> None:
    clean = run(MachineModel(noise_um=0.1))
    n = clean.t_s.size
    res = run(MachineModel(noise_um=0.1, drop_fraction=0.1, drop_indices=(3, 4, 5, 1000)))
    lost = n - res.t_s.size
    assert abs(lost - 0.1 * n) < 5 * math.sqrt(0.09 * n) + 4
    kept = np.isin(clean.t_s, res.t_s)
    assert not kept[[3, 4, 5, 1000]].any()
    # The surviving samples are the same samples: drops draw from their own stream.
    assert np.array_equal(clean.length_mm[kept], res.length_mm)
    only = run(MachineModel(drop_indices=(0, 7)))
    assert only.t_s.size == n - 2 and only.t_s[0] == pytest.approx(1 / PLAN.sample_hz)


def test_noise_std_and_quantisation() -> None:
    clean = run(MachineModel())
    noisy = run(MachineModel(noise_um=0.25))
    assert np.std(noisy.deviation_um - clean.deviation_um) == pytest.approx(0.25, rel=0.03)
    q = run(MachineModel(noise_um=0.25, quantum_um=0.1))
    steps = q.length_mm / 1e-4
    assert np.max(np.abs(steps - np.round(steps))) < 1e-4
    assert np.max(np.abs(q.length_mm - noisy.length_mm)) <= 0.5e-4 + 1e-12


def test_deterministic_for_a_seed() -> None:
    m = MachineModel(noise_um=0.2, jitter_s=1e-4, drop_fraction=0.01)
    a, b, c = run(m, seed=7), run(m, seed=7), run(m, seed=8)
    assert np.array_equal(a.t_s, b.t_s) and np.array_equal(a.length_mm, b.length_mm)
    assert a.t_s.size != c.t_s.size or not np.array_equal(a.length_mm, c.length_mm)


def test_streaming_keeps_one_sample_clock() -> None:
    plan = PLAN.with_(overshoot_deg=5.0, data_arc_deg=30.0, sample_hz=100.0)
    m = MachineModel(noise_um=0.1)
    tests = list(iter_tests(plan, m, seed=3, repeat=3, gap_s=0.5))
    t = np.concatenate([r.t_s for r in tests])
    assert np.allclose(np.diff(t), 0.01)
    assert [r.index for r in tests] == [0, 1, 2]
    span = tests[1].events["test_start"] - tests[0].events["test_start"]
    assert tests[2].events["feed_in_start"] - tests[1].events["feed_in_start"] == pytest.approx(span)
    assert not np.array_equal(tests[0].deviation_um[:50], tests[1].deviation_um[:50])
    first = simulate(plan, m, seed=3)
    assert np.array_equal(first.length_mm, tests[0].length_mm[: first.length_mm.size])
    chunks = list(iter_chunks(plan, m, seed=3, repeat=1, chunk=128))
    assert all(c[0].size <= 128 for c in chunks)
    assert np.array_equal(np.concatenate([c[1] for c in chunks]), tests[0].length_mm[: sum(c[1].size for c in chunks)])


# --------------------------------------------------------------------------- model and command line


def test_model_validation_and_set_parsing() -> None:
    with pytest.raises(PlanError, match="kv_x_per_s"):
        MachineModel(kv_x_per_s=-1.0)
    with pytest.raises(PlanError, match="no_such_key"):
        MachineModel.from_dict({"no_such_key": 1})
    with pytest.raises(PlanError, match="sample_hz"):
        simulate(PLAN, MachineModel(), sample_hz=20_000.0)
    got = parse_set(["backlash_x_um=5", "kv_y_per_s=inf", "drop_indices=1,2", "jitter_stamped=true"])
    assert got == {"backlash_x_um": 5.0, "kv_y_per_s": math.inf, "drop_indices": (1, 2), "jitter_stamped": True}
    m = MachineModel(**got)
    assert MachineModel.from_dict(m.to_dict()) == m


def test_cli_writes_csv_and_truth(tmp_path: pytest.TempPathFactory) -> None:
    out = tmp_path / "sim.csv"  # type: ignore[operator]
    truth = tmp_path / "truth.json"  # type: ignore[operator]
    argv = [
        "--out",
        str(out),
        "--truth",
        str(truth),
        "--radius-mm",
        "50",
        "--feed-mm-min",
        "2000",
        "--overshoot-deg",
        "10",
        "--data-arc-deg",
        "90",
        "--sample-hz",
        "100",
        "--seed",
        "4",
        "--set",
        "backlash_x_um=5",
        "--set",
        "kv_y_per_s=inf",
        "--set",
        "noise_um=0.1",
    ]
    assert main(argv) == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "t_s,length_mm"
    data = np.loadtxt(out, delimiter=",", skiprows=1)
    plan = TestPlan(radius_mm=50.0, feed_mm_min=2000.0, overshoot_deg=10.0, data_arc_deg=90.0, sample_hz=100.0)
    ref = simulate(plan, MachineModel(backlash_x_um=5.0, kv_y_per_s=math.inf, noise_um=0.1), seed=4)
    assert np.allclose(data[:, 0], ref.t_s, atol=1e-9)
    assert np.allclose(data[:, 1], ref.length_mm, atol=1e-9)
    doc = json.loads(truth.read_text())
    assert doc["truth"]["backlash_x_um"] == 5.0
    assert doc["machine"]["kv_y_per_s"] == "inf"
    assert doc["tests"][0]["events"]["feed_in_start"] == pytest.approx(1.0)
    assert main(["--out", str(out), "--set", "nonsense_um=1"]) == 2
