"""The path position of one move that starts and ends at rest, as a controller's interpolator feeds it: the
simulator's commanded motion (:mod:`ballbar.tools.simulator`) and the NC interpreter's timing
(:mod:`ballbar.tools.ncinterp`) both run on it.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _Profile:
    """Path position of one move starting and ending at rest: trapezoid, optionally jerk-limited."""

    length: float
    feed: float
    accel: float
    smooth_s: float  # jerk smoothing time A/J (0: none)

    @property
    def peak(self) -> float:
        if math.isinf(self.accel):
            return self.feed
        return min(self.feed, math.sqrt(self.length * self.accel))

    @property
    def t_acc(self) -> float:
        return 0.0 if math.isinf(self.accel) else self.peak / self.accel

    @property
    def t_cruise(self) -> float:
        return self.length / self.peak - self.t_acc

    @property
    def t_trap(self) -> float:
        return 2.0 * self.t_acc + self.t_cruise

    @property
    def duration(self) -> float:
        return self.t_trap + self.smooth_s

    def _trap(self, tau: np.ndarray) -> np.ndarray:
        L, vp, ta, tt = self.length, self.peak, self.t_acc, self.t_trap
        if ta == 0.0:
            return np.clip(vp * tau, 0.0, L)
        A = self.accel
        s = np.where(tau < ta, 0.5 * A * tau**2, 0.5 * A * ta**2 + vp * (tau - ta))
        dec = L - 0.5 * A * (tt - tau) ** 2
        s = np.where(tau > tt - ta, dec, s)
        s = np.where(tau >= tt, L, s)
        return np.clip(np.where(tau <= 0, 0.0, s), 0.0, L)

    def _trap_integral(self, tau: np.ndarray) -> np.ndarray:
        """Integral of the trapezoid's path position from 0 to ``tau`` (finite accel only)."""
        L, vp, ta, tt, A = self.length, self.peak, self.t_acc, self.t_trap, self.accel
        t2 = tt - ta
        i1 = A * ta**3 / 6.0
        i2 = i1 + 0.5 * A * ta**2 * (t2 - ta) + 0.5 * vp * (t2 - ta) ** 2
        i3 = i2 + L * (tt - t2) - A * ta**3 / 6.0
        tc = np.clip(tau, 0.0, None)
        out = np.where(tc <= ta, A * tc**3 / 6.0, 0.0)
        m = (tc > ta) & (tc <= t2)
        d = tc - ta
        out = np.where(m, i1 + 0.5 * A * ta**2 * d + 0.5 * vp * d**2, out)
        m = (tc > t2) & (tc <= tt)
        out = np.where(m, i2 + L * (tc - t2) - A * (ta**3 - (tt - tc) ** 3) / 6.0, out)
        return np.where(tc > tt, i3 + L * (tc - tt), out)

    def position(self, tau: np.ndarray) -> np.ndarray:
        """Path length travelled ``tau`` seconds after the move's start."""
        tau = np.asarray(tau, dtype=float)
        if self.smooth_s == 0.0:
            return self._trap(tau)
        # The S-curve of jerk A/Tj is the trapezoid averaged over the last Tj seconds.
        tj = self.smooth_s
        s = (self._trap_integral(tau) - self._trap_integral(tau - tj)) / tj
        return np.clip(s, 0.0, self.length)

    def time_at(self, s_target: float) -> float:
        """When the path position reaches ``s_target`` (bisection; the profile is monotone)."""
        lo, hi = 0.0, self.duration
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if float(self.position(np.array([mid]))[0]) < s_target:
                lo = mid
            else:
                hi = mid
        return 0.5 * (lo + hi)
