"""ISO 230-4 circular test figures (analysis/README.md, "ISO 230-4 figures").

- ``G`` circular deviation per direction: range of the radial deviation about
  that direction's least-squares circle (centre and radius fitted).
- ``G(b)`` bidirectional circular deviation: the same over both directions with
  one least-squares circle.
- ``H`` circular hysteresis: the largest radial difference between the CCW and
  CW paths at the same angle (about the bidirectional least-squares circle;
  both paths interpolated on the coarser of their angle grids, over the angles
  both cover).
- ``F`` radial deviation: largest and smallest deviation from the nominal
  radius about the test centre (the pivot), i.e. ``L - R`` as measured; needs
  the bar's length calibration.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from .patterns import cos_sin

if TYPE_CHECKING:
    from ballbar.protocol.messages.results import IsoConditions


def _lsc_residual(u: np.ndarray, dr: np.ndarray, trig: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Radial deviation about the least-squares circle (centre and radius removed); ``trig``: ``cos u, sin u``
    where already made."""
    c, s = cos_sin(u) if trig is None else trig
    # the normal equations of the columns 1, cos u, sin u, from their sums (no n x 3 matrix: a 10 kHz test's
    # 1.5 M samples made it the figures' largest cost)
    cc, cs, ss = float(c @ c), float(c @ s), float(s @ s)
    sc, sn = float(c.sum()), float(s.sum())
    G = np.array([[float(u.size), sc, sn], [sc, cc, cs], [sn, cs, ss]])
    b = np.array([float(dr.sum()), float(c @ dr), float(s @ dr)])
    x, *_ = np.linalg.lstsq(G, b, rcond=None)
    return np.asarray(dr - x[0] - x[1] * c - x[2] * s)


def figures(per_direction: dict[int, tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """ISO 230-4 figures in micrometres from ``{direction: (u_rad, dR_um)}``."""
    out: dict[str, Any] = {"G_ccw_um": None, "G_cw_um": None, "G_b_um": None, "H_um": None}
    trig = {d: cos_sin(u) for d, (u, _) in per_direction.items()}
    for d, key in ((1, "G_ccw_um"), (-1, "G_cw_um")):
        if d in per_direction and per_direction[d][0].size >= 4:
            r = _lsc_residual(*per_direction[d], trig[d])
            out[key] = float(r.max() - r.min())
    all_u = np.concatenate([v[0] for v in per_direction.values()])
    all_dr = np.concatenate([v[1] for v in per_direction.values()])
    if all_u.size >= 4:
        both = tuple(np.concatenate([trig[d][k] for d in per_direction]) for k in (0, 1))
        r_all = _lsc_residual(all_u, all_dr, (both[0], both[1]))
        if len(per_direction) == 2:
            out["G_b_um"] = float(r_all.max() - r_all.min())
            n_ccw = per_direction[1][0].size
            out["H_um"] = _hysteresis(
                (per_direction[1][0], r_all[:n_ccw]), (per_direction[-1][0], r_all[n_ccw:])
            )
        out["F_max_um"] = float(all_dr.max())
        out["F_min_um"] = float(all_dr.min())
    else:
        out["F_max_um"] = out["F_min_um"] = None
    return out


def _hysteresis(ccw: tuple[np.ndarray, np.ndarray], cw: tuple[np.ndarray, np.ndarray]) -> float | None:
    (u1, r1), (u2, r2) = _ascending(*ccw), _ascending(*cw)
    lo, hi = max(u1[0], u2[0]), min(u1[-1], u2[-1])
    if hi <= lo:
        return None
    grid = u1 if u1.size <= u2.size else u2
    grid = grid[(grid >= lo) & (grid <= hi)]
    diff = np.interp(grid, u1, r1) - np.interp(grid, u2, r2)
    return float(np.max(np.abs(diff)))


def _ascending(u: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``u`` and ``r`` in ascending order of ``u``: as they are, or reversed, where the angles run one way (a
    circle's, in time order), else sorted."""
    step = np.diff(u)
    if np.all(step > 0):
        return u, r
    if np.all(step < 0):
        return u[::-1], r[::-1]
    o = np.argsort(u)
    return u[o], r[o]


def conditions(plan_dict: Mapping[str, Any], measured_feed_mm_min: float, sample_hz: float) -> IsoConditions:
    """The test conditions every ISO figure is reported with."""
    return {
        "plane": plan_dict["plane"],
        "radius_mm": plan_dict["radius_mm"],
        "feed_mm_min": plan_dict["feed_mm_min"],
        "measured_feed_mm_min": measured_feed_mm_min if math.isfinite(measured_feed_mm_min) else None,
        "data_arc_deg": plan_dict["data_arc_deg"],
        "start_deg": plan_dict["start_deg"],
        "directions": plan_dict["directions"],
        "sample_hz": sample_hz,
        "centre_removal": "least squares circle: per direction for G, common for G(b) and H; none for F",
        "standard": "ISO 230-4:2022",
    }
