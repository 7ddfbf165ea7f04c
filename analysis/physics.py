"""Physical models beyond the linear masks, applied as corrections to the data.

Two effects that the masks of analysis/README.md describe only to first order leave a
bias a good analyzer removes.  Each is the difference between the physical
model and its mask, evaluated at the current estimates and subtracted from the
measured deviation before the masks are fitted again (a fixed-point iteration:
both differences depend only weakly on the estimates).

Servo (the "physical servo model").  Each axis is a first-order position loop,
``1/K = tau_bar +- m/2`` with ``m = servo_mismatch_ms`` and ``tau_bar`` the mean
loop lag.  On a circle at ``Omega = V/R`` an axis answers with gain
``g = 1/sqrt(1 + (Omega/K)^2)`` and phase lag ``phi = atan(Omega/K)``.  In the
frame of the mean lag (which is the frame the analyzer's angles are in: the
feed-in centroid carries the same delay) the bar reads

    L/R = sqrt(gX^2 cos^2(u - d eps) + gY^2 sin^2(u + d eps)),  eps = (phiX - phiY)/2

whose first-order part is the mask ``(d V/2) m sin 2u``.  The rest is the
dynamic shrinkage of the radius (``-R Omega^2 tau^2 / 2``, which otherwise
lands in ``radius_um``) and ``-(R Omega^2 / 4)(1/KX^2 - 1/KY^2) cos 2u``, which
a linear fit reads as a spurious ``scale_mismatch_ppm`` (-2.7 ppm for KX = 30,
KY = 33 /s at R = 100 mm, F = 1000 mm/min; -8 ppm in the commanded frame that
analysis/README.md mentions).  ``tau_bar`` comes from the configured gains or from the
exponential approach that ends the feed-in and feed-out (:mod:`.detect`).

Lost motion.  Backlash is a dead band between motor and table: after a
reversal the table stands still until the motor has crossed the gap ``b``, so
the radial error does not step from ``-b/2`` to ``+b/2`` but follows
``R (1 - cos du) - b/2`` over ``du < acos(1 - b/R)`` (0.57 deg for 5 um at
100 mm).  Left to the step mask, that transition is read as negative reversal
spikes.  Over-compensated backlash (``b < 0``) flips at once: no transition.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numpy as np

from .patterns import Geometry, spike_travel

Offset = Callable[[Geometry], np.ndarray]

X_REVERSALS = (0.0, math.pi)
Y_REVERSALS = (0.5 * math.pi, 1.5 * math.pi)


def servo_remainder(g: Geometry, m_ms: float, tau_s: float) -> np.ndarray:
    """Physical first-order servo minus its linear mask (um), in the mean-lag frame."""
    inv_kx = tau_s + 0.5 * m_ms / 1000.0
    inv_ky = tau_s - 0.5 * m_ms / 1000.0
    if inv_kx <= 0 or inv_ky <= 0:
        return np.zeros(len(g))
    omega = g.V / g.R
    gx2 = 1.0 / (1.0 + (omega * inv_kx) ** 2)
    gy2 = 1.0 / (1.0 + (omega * inv_ky) ** 2)
    eps = 0.5 * (math.atan(omega * inv_kx) - math.atan(omega * inv_ky))
    L_over_R = np.sqrt(gx2 * np.cos(g.u - g.d * eps) ** 2 + gy2 * np.sin(g.u + g.d * eps) ** 2)
    physical = g.R * 1000.0 * (L_over_R - 1.0)
    mask = 0.5 * g.d * g.V * m_ms * np.sin(2.0 * g.u)
    return np.asarray(physical - mask)


def lost_motion_remainder(g: Geometry, bx_um: float, by_um: float) -> np.ndarray:
    """Dead-band take-up after each reversal minus the step mask (um)."""
    out = np.zeros(len(g))
    R_um = g.R * 1000.0
    for b, points in ((bx_um, X_REVERSALS), (by_um, Y_REVERSALS)):
        if not b > 0 or b >= R_um:
            continue
        width = math.acos(1.0 - b / R_um)
        for at in points:
            du = spike_travel(g.u, g.d, at)
            m = du < width
            if g.travel is not None:
                m &= du <= g.travel
            if m.any():
                out[m] += (R_um * (1.0 - np.cos(du[m])) - b) * np.cos(du[m])
    return out


def make_offset(
    values: Mapping[str, float | None],
    tau_s: float | None,
    lost_motion: str = "deadband",
    radial_cos2: float | None = None,
) -> Offset | None:
    """The correction for the current estimates, or None when there is nothing to correct.

    ``tau_s`` None: no servo correction; ``lost_motion = "step"``: none for backlash.
    ``radial_cos2``: ``tau_s`` was measured along a radius at angles whose mean
    ``cos 2u`` this is, where the lag is ``tau_bar + (m/2) cos 2u``.
    """
    m = values.get("servo_mismatch_ms") or 0.0
    if tau_s is not None and radial_cos2 is not None:
        tau_s = tau_s - 0.5 * m / 1000.0 * radial_cos2
    bx = (values.get("backlash_x_um") or 0.0) if lost_motion == "deadband" else 0.0
    by = (values.get("backlash_y_um") or 0.0) if lost_motion == "deadband" else 0.0
    use_servo = tau_s is not None and math.isfinite(tau_s) and tau_s > 0 and math.isfinite(m)
    if not use_servo and bx <= 0 and by <= 0:
        return None

    def offset(g: Geometry) -> np.ndarray:
        out = lost_motion_remainder(g, bx, by)
        if use_servo:
            assert tau_s is not None
            out += servo_remainder(g, m, tau_s)
        return out

    return offset


def takeup_angles(values: Mapping[str, float | None], radius_mm: float) -> tuple[float, float]:
    """Per axis, the angle (rad) after a reversal before the table follows its motor."""
    R_um = radius_mm * 1000.0
    out = []
    for key in ("backlash_x_um", "backlash_y_um"):
        b = values.get(key) or 0.0
        out.append(math.acos(1.0 - b / R_um) if 0 < b < R_um else 0.0)
    return out[0], out[1]
