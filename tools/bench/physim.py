"""An independent ball-bar simulator, written from the physics alone.

A second opinion on the project's simulator for the false-alarm surveys: it
shares no code and no assumptions with the fit or with ``tools/simulator.py``.
The path is built from the test plan's fields as the NC program runs it (a
radial feed-in, one blended CCW arc of ``a + 2o``, one CW arc back, dwells,
the feed-out); each move runs from rest to rest with a trapezoidal feed profile
of acceleration ``accel`` smoothed to a jerk limit. Each axis is a position loop
of gain ``kv`` with velocity feed-forward ``ff`` and an optional second-order
velocity loop, integrated at a fine internal step (trapezoidal rule, via its
discrete recursion); mechanical lost motion after the motor is a play operator,
an over-set backlash compensation a step in the command followed by the loop.
Scale, squareness and the pivot's offset enter the geometry, and the bar's
length is the exact distance between the spindle ball and the pivot ball. The
gauge samples that length on its own clock, as point readings or averaged
over each sample interval, with noise and optional quantisation.

Units: mm, s internally; the machine's fields carry their unit in the name.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from ballbar.analysis import TestPlan


@dataclass(frozen=True)
class Axis:
    """One axis: its loop, its lost motion, its scale."""

    kv: float = 30.0  # position-loop gain, 1/s
    ff: float = 0.0  # velocity feed-forward, 0..1
    vel_bw_hz: float = 0.0  # velocity loop's natural frequency; 0: ideal velocity loop
    vel_zeta: float = 0.7
    play_um: float = 0.0  # mechanical dead band after the motor (>= 0)
    comp_um: float = 0.0  # backlash compensation added to the command at a reversal (>= 0)
    scale_ppm: float = 0.0

    @property
    def lost_motion_um(self) -> float:
        """The net lost motion the bar sees: play less its compensation."""
        return self.play_um - self.comp_um

    @property
    def lag_s(self) -> float:
        """Steady-state velocity lag of the loop, (1 - ff)/kv."""
        return (1.0 - self.ff) / self.kv


@dataclass(frozen=True)
class Machine:
    x: Axis = field(default_factory=Axis)
    y: Axis = field(default_factory=Axis)
    squareness_urad: float = 0.0  # DX = S Y
    centre_x_um: float = 0.0  # the programmed centre lies (x0, y0) from the pivot
    centre_y_um: float = 0.0
    accel_mm_s2: float = 1000.0
    jerk_mm_s3: float = 20000.0


@dataclass(frozen=True)
class Gauge:
    sample_hz: float = 1000.0
    noise_um: float = 0.1
    quantum_um: float = 0.0
    averaging: bool = False  # False: a point reading at each tick; True: the mean over the interval
    phase: float = 0.0  # first tick after the start, as a fraction of the period
    length_offset_um: float = 0.0  # the bar's calibration error


# The programme as it runs is the plan's: start at R + f, feed in, arcs, feed out.
Path = TestPlan
PRE_S = 1.0  # at rest before the feed-in
POST_S = 1.0  # at rest after the feed-out


def _profile(length: float, v: float, a: float, j: float, dt: float) -> np.ndarray:
    """Path position s(t) of one move from rest to rest, at steps of ``dt``.

    A trapezoidal velocity profile (or triangular where the move is short),
    then smoothed by a moving average of ``a / j``: the acceleration ramps at
    the jerk limit and the move keeps its length.
    """
    t_acc = v / a
    if a * t_acc**2 > length:  # triangular
        t_acc = np.sqrt(length / a)
        v = a * t_acc
    t_cruise = (length - a * t_acc**2) / v
    total = 2 * t_acc + t_cruise
    n = int(np.ceil(total / dt)) + 1
    t = np.arange(n) * dt
    vel = np.minimum.reduce([a * t, np.full(n, v), a * (total - t)])
    vel = np.clip(vel, 0.0, None)
    k = max(1, round(a / j / dt))
    if k > 1:
        vel = np.convolve(np.concatenate([vel, np.zeros(k)]), np.ones(k) / k)[: n + k]
    s = np.concatenate([[0.0], np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt)])
    return s * (length / s[-1])


def command(path: Path, machine: Machine, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The interpolator's commanded X, Y (mm, about the programmed centre)."""
    R, f = path.radius_mm, path.feed_in_mm
    v = path.feed_mm_min / 60.0
    a, j = machine.accel_mm_s2, machine.jerk_mm_s3
    o, arc = np.radians(path.overshoot_deg), np.radians(path.data_arc_deg)
    sweep = arc + 2 * o
    u0 = np.radians(path.start_deg)
    dirs = {"both": (1, -1), "ccw": (1,), "cw": (-1,)}[path.directions]
    u = u0 if dirs[0] == 1 else u0 + sweep
    xs: list[np.ndarray] = []
    ys: list[np.ndarray] = []

    def rest(seconds: float, r: float, ang: float) -> None:
        n = round(seconds / dt)
        xs.append(np.full(n, r * np.cos(ang)))
        ys.append(np.full(n, r * np.sin(ang)))

    def radial(r0: float, r1: float, ang: float) -> None:
        s = _profile(abs(r1 - r0), v, a, j, dt)
        r = r0 + np.sign(r1 - r0) * s
        xs.append(r * np.cos(ang))
        ys.append(r * np.sin(ang))

    rest(PRE_S, R + f, u)
    radial(R + f, R, u)
    rest(path.dwell_s, R, u)
    for d in dirs:
        s = _profile(R * sweep, v, a, j, dt)
        ang = u + d * s / R
        xs.append(R * np.cos(ang))
        ys.append(R * np.sin(ang))
        u = ang[-1]
        rest(path.dwell_s, R, u)
    radial(R, R + f, u)
    rest(POST_S, R + f, u)
    return np.concatenate(xs), np.concatenate(ys)


def _last_sign(v: np.ndarray, first: float) -> np.ndarray:
    """Sign of the last non-zero velocity at each step (``first`` before any)."""
    s = np.sign(v)
    idx = np.where(s != 0, np.arange(len(s)), -1)
    idx = np.maximum.accumulate(idx)
    out = np.where(idx >= 0, s[np.maximum(idx, 0)], first)
    return out


def _first_sign(v: np.ndarray) -> float:
    nz = np.flatnonzero(np.abs(v) > 0)
    return float(np.sign(v[nz[0]])) if len(nz) else 1.0


def _loop(axis: Axis, xc: np.ndarray, dt: float) -> np.ndarray:
    """The motor's position following the command ``xc``, integrated at ``dt``.

    Position loop ``v_cmd = kv (xc - x) + ff xc'``; the velocity loop is ideal
    (``x' = v_cmd``) or second order (``x'' = w^2 (v_cmd - x') - 2 zeta w x'``
    rewritten with the damping on the velocity error). Discretised by the
    trapezoidal rule (bilinear transform) and run as a recursion from rest at
    the first command.
    """
    kv, ff = axis.kv, axis.ff
    if axis.vel_bw_hz > 0:
        w = 2 * np.pi * axis.vel_bw_hz
        z = axis.vel_zeta
        # x (s^3 + 2 z w s^2 + w^2 s + w^2 kv) = w^2 (ff s + kv) xc
        num = [w**2 * ff, w**2 * kv]
        den = [1.0, 2 * z * w, w**2, w**2 * kv]
    else:
        num = [ff, kv]
        den = [1.0, kv]
    b, a = signal.bilinear(num, den, fs=1.0 / dt)
    x0 = xc[0]
    zi = signal.lfilter_zi(b, a) * 0.0
    y, _ = signal.lfilter(b, a, xc - x0, zi=zi)
    return y + x0


def _play(xm: np.ndarray, half: float, first: float) -> np.ndarray:
    """Play operator: the table follows the motor ``xm`` through a gap of 2 ``half``.

    The table sits ``half`` behind the motor against its last direction of
    travel; at a reversal it stays put until the motor has crossed the gap.
    Exact, per monotone stretch of the motor's path.
    """
    if half <= 0:
        return xm.copy()
    dx = np.diff(xm)
    s = np.where(np.abs(dx) > 1e-12, np.sign(dx), 0.0)
    nz = np.flatnonzero(s)
    out = np.empty_like(xm)
    y = xm[0] - first * half
    if len(nz) == 0:
        out[:] = y
        return out
    # stretches of constant sign among non-zero steps
    sn = s[nz]
    change = np.flatnonzero(np.diff(sn)) + 1
    starts = np.concatenate([[0], nz[change]])
    ends = np.concatenate([nz[change], [len(xm) - 1]])
    out[: starts[0] + 1] = y
    for st, en, sg in zip(starts, ends, sn[np.concatenate([[0], change])], strict=False):
        seg = xm[st : en + 1]
        yy = np.maximum(y, seg - half) if sg > 0 else np.minimum(y, seg + half)
        out[st : en + 1] = yy
        y = yy[-1]
    return out


def _axis(axis: Axis, xc: np.ndarray, dt: float) -> np.ndarray:
    """Commanded position to the table's position (mm), before scale."""
    vc = np.gradient(xc, dt)
    vc[np.abs(vc) < 1e-9] = 0.0
    first = _first_sign(vc)
    if axis.comp_um:
        xc = xc + 0.5e-3 * axis.comp_um * _last_sign(vc, first)
    xm = _loop(axis, xc, dt)
    return _play(xm, 0.5e-3 * axis.play_um, first)


def bar_length(machine: Machine, path: Path, dt: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and the exact ball-to-ball distance (mm) at every internal step."""
    xc, yc = command(path, machine, dt)
    xt = _axis(machine.x, xc, dt)
    yt = _axis(machine.y, yc, dt)
    X = xt * (1 + 1e-6 * machine.x.scale_ppm) + 1e-6 * machine.squareness_urad * yc
    Y = yt * (1 + 1e-6 * machine.y.scale_ppm)
    L = np.hypot(X + 1e-3 * machine.centre_x_um, Y + 1e-3 * machine.centre_y_um)
    return np.arange(len(L)) * dt, L


def sample(
    t: np.ndarray, L: np.ndarray, gauge: Gauge, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """The gauge's readings (s, mm) on its own clock."""
    period = 1.0 / gauge.sample_hz
    ts = np.arange(gauge.phase * period, t[-1] - period, period)
    if gauge.averaging:
        dt = t[1] - t[0]
        c = np.concatenate([[0.0], np.cumsum(0.5 * (L[1:] + L[:-1]) * dt)])
        ci = np.interp(ts, t, c)
        lo = np.interp(np.maximum(ts - period, 0.0), t, c)
        vals = (ci - lo) / np.maximum(ts - np.maximum(ts - period, 0.0), 1e-12)
        ts, vals = ts[ts >= period], vals[ts >= period]
    else:
        vals = np.interp(ts, t, L)
    vals = vals + 1e-3 * (gauge.length_offset_um + gauge.noise_um * rng.standard_normal(len(vals)))
    if gauge.quantum_um > 0:
        q = 1e-3 * gauge.quantum_um
        vals = np.round(vals / q) * q
    return ts, vals


def simulate(
    machine: Machine, path: Path, gauge: Gauge, seed: int = 0, dt: float = 1e-4
) -> tuple[np.ndarray, np.ndarray]:
    """One recording: the gauge's times (s) and lengths (mm)."""
    t, L = bar_length(machine, path, dt)
    return sample(t, L, gauge, np.random.default_rng(seed))


def truth(machine: Machine, path: Path) -> dict[str, float]:
    """The machine mapped onto the published fields (DOMAIN / analysis README)."""
    return {
        "centre_x_um": machine.centre_x_um,
        "centre_y_um": machine.centre_y_um,
        "backlash_x_um": machine.x.lost_motion_um,
        "backlash_y_um": machine.y.lost_motion_um,
        "servo_mismatch_ms": 1e3 * (machine.x.lag_s - machine.y.lag_s),
        "squareness_urad": machine.squareness_urad,
        "scale_mismatch_ppm": machine.x.scale_ppm - machine.y.scale_ppm,
    }
