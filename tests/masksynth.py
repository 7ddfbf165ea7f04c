"""Recordings made from the masks themselves (not physics): exactness tests of the engine.

The physical simulator (``ballbar.tools.simulator``) is what the fit is tested
against for physics; this module checks that the engine inverts its own model
exactly, at any sample rate and any chunking.
"""

from __future__ import annotations

import math

import numpy as np

from ballbar.analysis.patterns import Geometry, design, select
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import schedule


def mask_recording(
    plan: TestPlan,
    truth: dict[str, float],
    *,
    fs: float,
    spike_width_deg: float = 4.0,
    t0: float = 2.0,
    noise_um: float = 0.0,
    seed: int = 0,
    overhead_s: float = 0.0,
    pitch: tuple[float | None, float | None] = (None, None),
) -> tuple[np.ndarray, np.ndarray]:
    """``(t, L)`` of a test whose arcs follow the masks of ``truth`` exactly."""
    V, R, f = plan.feed_mm_s, plan.radius_mm, plan.feed_in_mm
    sch = schedule(plan, V, overhead_s)
    t = np.arange(0.0, t0 + sch.feed_out_centroid_s + 2.0, 1.0 / fs)
    rel = t - t0
    T = f / V + overhead_s
    L = np.where(rel < -T / 2, R + f, np.where(rel < T / 2, R + f - f * (rel + T / 2) / T, R))
    tfo = sch.feed_out_centroid_s
    L = np.where(rel > tfo - T / 2, np.where(rel < tfo + T / 2, R + f * (rel - tfo + T / 2) / T, R + f), L)
    pats = select(None, plan.direction_list, *pitch)
    x = np.array([truth.get(fl, 0.0) for p in pats for fl in p.fields])
    dirs = plan.direction_list
    tmid = t0  # the drift's origin: the feed-in centroid
    for d in dirs:
        a = sch.arc_start_s[d]
        b = a + R * math.radians(plan.arc_deg) / V
        m = (rel >= a) & (rel <= b)
        u = np.radians(sch.angle_deg(plan, d, rel[m]))
        travel = d * (u - math.radians(plan.start_deg if d > 0 else plan.start_deg + plan.arc_deg))
        g = Geometry(u, np.full(u.size, float(d)), (t[m] - tmid) / 60.0, V, R, *pitch, travel=travel)
        L[m] = R + design(pats, g, math.radians(spike_width_deg)) @ x / 1000.0
    if noise_um:
        L = L + np.random.default_rng(seed).normal(0.0, noise_um / 1000.0, L.size)
    return t, L


FULL_TRUTH = {
    "centre_x_um": 12.0,
    "centre_y_um": -7.0,
    "radius_um": 3.0,
    "backlash_x_um": 4.0,
    "backlash_y_um": -2.5,
    "servo_mismatch_ms": 0.8,
    "master_slave_a_um": 1.5,
    "master_slave_b_um": -1.0,
    "squareness_urad": 20.0,
    "scale_mismatch_ppm": 5.0,
    "lateral_play_x_um": 1.0,
    "lateral_play_y_um": 0.5,
    "straightness_x_um": 1.2,
    "straightness_y_um": -0.8,
    "drift_um_per_min": 0.3,
    "reversal_spike_x_pos_ccw_um": 3.0,
    "reversal_spike_y_neg_cw_um": 2.0,
}
