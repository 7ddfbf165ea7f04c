"""Ball-bar test simulator: a physical model of the machine, not of the error masks.

The simulator runs the test program of :func:`ballbar.analysis.program.moves`
through a model of the controller, the position loops, the drive train, the
machine's geometry, the bar and the sampling electronics, and reports the bar
length ``|P + D - pivot|`` computed exactly from the simulated positions.  It
never evaluates a mask of ``analysis/README.md``: a fit that recovers the
parameters from this data has recovered physics, not its own formulas.

Frames and units
----------------
"X" and "Y" are the plane's first and second axes (``XY``: X, Y; ``YZ``: Y, Z;
``ZX``: Z, X).  Positions are millimetres in the plane, measured from the
programmed circle centre; angles are counter-clockwise from X.  Machine errors
are given in micrometres (um), micro-radians (urad) or parts per million (ppm);
times in seconds; ``t_s`` is the time since the start of the simulated test.

The chain, evaluated on a fine time grid (``step_s``, default 0.1 ms, aligned so
that every nominal sample instant is a grid point)
---------------------------------------------------------------------------
1. Command.  The program (feed-in, dwell, CCW arc, dwell, CW arc, dwell,
   feed-out) at feed ``F * feed_override`` (from the second arc on at
   ``F * feed_override_later`` where that is set: a test not run as planned).  Every move starts and ends at
   rest with a trapezoidal path speed of acceleration ``accel_mm_s2``; with a
   finite ``jerk_mm_s3`` the trapezoid is averaged over ``A / J`` seconds (the
   exact jerk-limited S-curve).  A move of length ``s`` then lasts
   ``s / V + c`` with ``c = V / A + A / J``, as :mod:`~ballbar.analysis.program`
   assumes.  ``lead_s`` of standing at ``R + f`` before, ``tail_s`` after.
   ``ipo_s > 0`` holds the command constant over each interpolation cycle.
   ``in_position_um > 0``: after each move that ends in a dwell the control
   waits until both axes' following errors are within that band before the
   dwell begins (an in-position check; 0: none).  With loops of equal shape
   the wait adds the same time to each such move, i.e. to the per-move
   overhead ``c``: ``truth_of`` cannot know it, ``SimResult.events`` holds
   each wait (``inpos_<move>``).
2. Master-slave changeover (a controller quirk, added to the command):
   ``D = sigma/2 (a e1 + b e2)``, ``e1 = (1, 1)/sqrt2``, ``e2 = (1, -1)/sqrt2``,
   ``sigma = +1`` while the commanded ``|vX| >= |vY|`` (X is the master), else
   ``-1``; held while the command stands still.  It passes through the loops.
3. Position loop per axis (semi-closed, on the motor): ``dp/dt = Kv (c - p) +
   ff dc/dt``, solved exactly for a command linear between grid points.  The
   steady following error on a ramp is ``(1 - ff) v / Kv`` against the motion.
   With ``velocity_loop_*_hz > 0`` the motor's velocity follows that command
   through a velocity loop of that natural frequency and
   ``velocity_loop_damping`` (second order), the position loop closed around
   it: the axis is then third order, its lag on a ramp unchanged.
4. Lost motion, ``backlash_*_um = b``.  ``b > 0``: a dead band between motor
   and table (play operator) of half-width ``b/2`` centred at the start, so a
   moving table lags its motor by ``b/2`` (``DX = -(b/2) sgn(vX)``) and stands
   still after a reversal until the motor has crossed the gap.  ``b < 0``:
   backlash compensation set too high, on an axis without play.  At each
   commanded reversal the control steps the axis' command by ``|b|`` (it holds
   ``+(|b|/2) sgn(v_command)``) and the position loop follows that step
   (step 3): the table leads by ``|b|/2``, and the flip at a reversal is a
   first-order approach with the loop's time constant.
   ``backlash_comp_*_um = c`` adds such a compensation to a dead band
   (``b >= 0`` the gap): the net lost motion is ``b - c``.
5. Friction at reversals (table, after the lost motion): when the table
   reverses, it lags extra against its new direction of travel,
   ``DX = -h sgn(vX_new) exp(-(t - t_rev)/tau)`` (``spike_*_um = h``,
   ``spike_tau_*_s = tau``): an outward radial bump of ``h`` at the reversal.
   Stick-slip: while ``|v_table| < stick_slip_speed_mm_s`` the table sticks
   and slips in steps of ``stick_slip_um`` (a sawtooth lag in ``[0, step)``).
6. Lateral play: when X reverses, Y shifts against X's direction of travel,
   ``DY = -(lX/2) sgn(vX)`` (and ``DX = -(lY/2) sgn(vY)``); instantaneous at
   the table's reversal, or spread over ``lateral_takeup_um`` of travel.
7. Geometry, applied to the table position ``(X, Y)``:
   squareness ``DX = S Y`` (urad), scale ``DX = eX X``, ``DY = eY Y`` (ppm),
   straightness ``DY = sX (X/R)^2``, ``DX = sY (Y/R)^2`` (um, ``R`` the plan's
   radius), cyclic screw error ``DX = cX sin(2 pi X / pX + phiX)`` (and Y).
8. The bar: ``L = |P + D + (x0, y0)|`` (the pivot sits at ``-(x0, y0)`` from the
   programmed centre, so ``centre_*_um`` is the library's ``D = (x0, y0)``),
   plus ``length_step_um`` from ``length_step_s`` after the feed-in starts (a
   ball seating anew), plus ``radius_um`` (calibration) plus ``drift_um_per_min`` times the minutes
   since the feed-in started, plus a radial vibration
   ``vibration_um sin(2 pi f t + phi)``.
9. Sampling at ``k / sample_hz``.  Jitter: by default sample ``k`` is taken at
   ``k/fs + e`` (``e ~ N(0, jitter_s)``) but stamped ``k/fs`` (a device whose
   timestamps are ideal and whose acquisition wobbles); with
   ``jitter_stamped`` it is taken at ``k/fs`` and stamped ``k/fs + e``.
   Then white LVDT noise (``noise_um`` rms), quantisation (``quantum_um``),
   dropped samples (``drop_fraction`` at random and/or ``drop_indices``).
   Each random effect has its own stream from ``seed``: switching one on does
   not change the others' draws.

Everything is zero or ideal by default except the loop gains (30/s), the
acceleration (2000 mm/s^2) and ``lead_s``/``tail_s`` (1 s).

What the physics adds to the library's first-order masks (a fit meets these):
the loops shrink the circle by ``R x^2 / 2`` (``x = V/(R Kv)``, 1.5 um at 30/s)
and unequal gains add an apparent ``scale_mismatch_ppm`` (-8 ppm for 30/33/s),
both in :func:`truth_of`; a reversal is seen ``x`` rad after the commanded one;
lost motion is not a step but, after the table stops, a parabolic rise
``-b/2 + R (1 - cos du)`` lasting ``acos(1 - b/R)`` (0.6 deg for 6 um at
100 mm); the loops round master-slave steps over ~``x``; the feed-in's
length change is ``f - bX/2`` on an X feed-in.  With ideal loops a
master-slave step against the direction of travel is a real (tiny) reversal.

Output: :func:`simulate` returns a :class:`SimResult`; :func:`iter_tests`
streams tests on one sample clock; ``events`` are commanded times.

Command line: :mod:`ballbar.tools.simulator_cli` (``ballbar-sim``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any

import numpy as np
from scipy.signal import cont2discrete, lfilter

from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import Move, data_start_deg, moves

from .feed_profile import _Profile

log = logging.getLogger(__name__)

SAMPLE_HZ_MIN = 15.625
SAMPLE_HZ_MAX = 10_000.0
UM = 1.0e-3  # mm per micrometre
_EPS_MM = 1.0e-12  # movements below this per grid step do not change an axis's direction


@dataclass(frozen=True)
class MachineModel:
    """The simulated machine, controller, bar and sampling; see the module docstring.

    ``_x``/``_y``: the plane's first/second axis.  ``inf`` is allowed for
    ``kv_*_per_s`` (ideal loop), ``accel_mm_s2`` and ``jerk_mm_s3``.
    """

    # Controller and motion
    feed_override: float = 1.0  # actual feed = programmed feed * this
    feed_override_later: float = 0.0  # the override from the second arc on (0: unchanged): a test not run as planned
    accel_mm_s2: float = 2000.0  # path acceleration of the trapezoid
    jerk_mm_s3: float = math.inf  # path jerk (S-curve) when finite
    ipo_s: float = 0.0  # interpolation cycle: command held per cycle (0 = continuous)
    in_position_um: float = 0.0  # in-position band checked before each dwell (0: no check)
    lead_s: float = 1.0  # standing at R + f before the feed-in
    tail_s: float = 1.0  # standing at R + f after the feed-out
    # Position loops
    kv_x_per_s: float = 30.0
    kv_y_per_s: float = 30.0
    velocity_ff: float = 0.0  # velocity feed-forward fraction, 0..1, both axes
    # velocity loop inside each position loop: its natural frequency (Hz; 0: ideal, the axis a first-order loop)
    velocity_loop_x_hz: float = 0.0
    velocity_loop_y_hz: float = 0.0
    velocity_loop_damping: float = 0.7
    # Lost motion, friction
    backlash_x_um: float = 0.0
    backlash_y_um: float = 0.0
    backlash_comp_x_um: float = 0.0  # compensation the control adds at commanded reversals (net = b - comp)
    backlash_comp_y_um: float = 0.0
    lateral_play_x_um: float = 0.0  # Y shift when X reverses
    lateral_play_y_um: float = 0.0  # X shift when Y reverses
    lateral_takeup_um: float = 0.0  # travel over which the lateral shift completes (0: at once)
    spike_x_um: float = 0.0
    spike_y_um: float = 0.0
    spike_tau_x_s: float = 0.03
    spike_tau_y_s: float = 0.03
    stick_slip_um: float = 0.0
    stick_slip_speed_mm_s: float = 0.5
    # Controller quirk
    master_slave_a_um: float = 0.0
    master_slave_b_um: float = 0.0
    # Geometry
    squareness_urad: float = 0.0
    scale_x_ppm: float = 0.0
    scale_y_ppm: float = 0.0
    straightness_x_um: float = 0.0  # DY = sX (X/R)^2
    straightness_y_um: float = 0.0  # DX = sY (Y/R)^2
    cyclic_x_um: float = 0.0
    cyclic_y_um: float = 0.0
    cyclic_x_phase_deg: float = 0.0
    cyclic_y_phase_deg: float = 0.0
    pitch_x_mm: float = 10.0
    pitch_y_mm: float = 10.0
    # Set-up and bar
    centre_x_um: float = 0.0
    centre_y_um: float = 0.0
    radius_um: float = 0.0  # bar calibration error, added to the reported length
    drift_um_per_min: float = 0.0
    length_step_um: float = 0.0  # the bar's length steps by this once (a ball seating anew, a loose pivot) ...
    length_step_s: float = 0.0  # ... this long after the feed-in starts
    vibration_um: float = 0.0  # radial amplitude
    vibration_hz: float = 50.0
    vibration_phase_deg: float = 0.0
    # Sampling
    jitter_s: float = 0.0
    jitter_stamped: bool = False
    drop_fraction: float = 0.0
    drop_indices: tuple[int, ...] = ()
    noise_um: float = 0.0
    quantum_um: float = 0.0

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "drop_indices":
                if not all(isinstance(i, int | np.integer) and i >= 0 for i in v):
                    raise PlanError("drop_indices must be non-negative integers")
                continue
            if f.name == "jitter_stamped":
                continue
            if not isinstance(v, int | float) or isinstance(v, bool) or math.isnan(v):
                raise PlanError(f"machine key {f.name!r} must be a number, not {v!r}")
            if math.isinf(v) and f.name not in _INF_OK:
                raise PlanError(f"machine key {f.name!r} must be finite, not {v!r}")
        positive = (
            "feed_override",
            "accel_mm_s2",
            "jerk_mm_s3",
            "kv_x_per_s",
            "kv_y_per_s",
            "spike_tau_x_s",
            "spike_tau_y_s",
            "pitch_x_mm",
            "pitch_y_mm",
            "stick_slip_speed_mm_s",
            "vibration_hz",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise PlanError(f"machine key {name!r} must be > 0, not {getattr(self, name)!r}")
        non_negative = (
            "ipo_s",
            "in_position_um",
            "backlash_comp_x_um",
            "backlash_comp_y_um",
            "lead_s",
            "tail_s",
            "velocity_loop_x_hz",
            "velocity_loop_y_hz",
            "feed_override_later",
            "length_step_s",
            "velocity_loop_damping",
            "lateral_takeup_um",
            "stick_slip_um",
            "jitter_s",
            "noise_um",
            "quantum_um",
        )
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise PlanError(f"machine key {name!r} must be >= 0, not {getattr(self, name)!r}")
        if not 0 <= self.velocity_ff <= 1:
            raise PlanError(f"velocity_ff must be within 0..1, not {self.velocity_ff!r}")
        if not 0 <= self.drop_fraction < 1:
            raise PlanError(f"drop_fraction must be within [0, 1), not {self.drop_fraction!r}")

    @classmethod
    def ideal(cls, **changes: Any) -> MachineModel:
        """A perfect machine: ideal loops, no errors (``changes`` added)."""
        return cls(kv_x_per_s=math.inf, kv_y_per_s=math.inf, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON types; infinities as the strings ``"inf"``/``"-inf"``."""
        d = asdict(self)
        d["drop_indices"] = list(self.drop_indices)
        for k, v in d.items():
            if isinstance(v, float) and math.isinf(v):
                d[k] = str(v)
        return d

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MachineModel:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise PlanError(f"unknown machine key {unknown[0]!r} (known: {', '.join(sorted(known))})")
        kw: dict[str, Any] = {}
        for key, value in data.items():
            if key == "drop_indices":
                value = tuple(int(i) for i in value)
            elif key == "jitter_stamped":
                value = bool(value)
            elif isinstance(value, str):
                try:
                    value = float(value)
                except ValueError as err:
                    raise PlanError(f"machine key {key!r} must be a number, not {value!r}") from err
            elif isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            kw[key] = value
        return cls(**kw)

    def with_(self, **changes: Any) -> MachineModel:
        return replace(self, **changes)


_INF_OK = frozenset({"accel_mm_s2", "jerk_mm_s3", "kv_x_per_s", "kv_y_per_s"})


@dataclass
class SimResult:
    """One simulated test.

    ``t_s``: reported sample times (s since the simulation start; continuous across
    :func:`iter_tests`).  ``length_mm``: reported absolute bar length.
    ``angle_deg``: the commanded angle (unwrapped, degrees) at the instant each
    sample was taken, for tests and plots; the analyzer must not use it.
    ``truth``: the result fields this machine should produce, plus
    extras (documented in :func:`truth_of`).  ``events``: commanded times (same
    clock as ``t_s``) of the program's moves and data arcs.
    """

    t_s: np.ndarray
    length_mm: np.ndarray
    angle_deg: np.ndarray
    truth: dict[str, float]
    events: dict[str, float]
    plan: TestPlan
    machine: MachineModel
    sample_hz: float
    index: int = 0  # which test of a stream
    n_slots: int = field(default=0, repr=False)  # nominal sample instants covered (before drops)

    @property
    def deviation_um(self) -> np.ndarray:
        """``L - R`` in micrometres."""
        return (self.length_mm - self.plan.radius_mm) / UM


# --------------------------------------------------------------------------- motion



@dataclass(frozen=True)
class _Segment:
    move: Move
    t_start: float
    duration: float
    profile: _Profile | None

    @property
    def t_end(self) -> float:
        return self.t_start + self.duration


def _timeline(
    plan: TestPlan, m: MachineModel, program: Sequence[Move] | None = None, h: float = 1.0e-4
) -> list[_Segment]:
    """The program's segments in time; ``h``: the grid step the in-position check runs the loops on."""
    V = plan.feed_mm_s * m.feed_override
    smooth = m.accel_mm_s2 / m.jerk_mm_s3 if math.isfinite(m.accel_mm_s2) else 0.0
    out: list[_Segment] = []
    t = m.lead_s
    arcs = 0
    for mv in moves(plan) if program is None else program:
        if mv.kind == "arc":
            arcs += 1
            if arcs == 2 and m.feed_override_later > 0:
                V = plan.feed_mm_s * m.feed_override_later
        if mv.kind == "dwell":
            wait = _in_position_wait(out, m, h) if out and out[-1].profile is not None else 0.0
            if wait > 0:
                out.append(_Segment(Move("dwell", f"inpos_{out[-1].move.name}", mv.start, mv.start,
                                         duration_s=wait), t, wait, None))
                t = out[-1].t_end
            out.append(_Segment(mv, t, mv.duration_s, None))
        else:
            prof = _Profile(mv.length_mm, V, m.accel_mm_s2, smooth)
            out.append(_Segment(mv, t, prof.duration, prof))
        t = out[-1].t_end
    return out


def _in_position_wait(segs: list[_Segment], m: MachineModel, h: float) -> float:
    """Seconds after the last segment's end until both following errors are within ``in_position_um``.

    Once the command stands, a first-order loop closes its error as ``exp(-Kv t)``.
    """
    tol = m.in_position_um * UM
    if tol <= 0:
        return 0.0
    grid = np.arange(math.ceil(segs[-1].t_end / h) + 1) * h
    cx, cy, _ = _axis_commands(segs, grid, m)
    wait = 0.0
    for c, motor, kv in zip((cx, cy), _motors(cx, cy, m, h), (m.kv_x_per_s, m.kv_y_per_s), strict=True):
        # the grid may end up to one step past the move: extrapolate the error back to its end
        err = abs(float(c[-1] - motor[-1])) * (math.exp(kv * (grid[-1] - segs[-1].t_end)) if math.isfinite(kv) else 1)
        if err > tol:
            wait = max(wait, math.log(err / tol) / kv)
    return wait


def _axis_commands(segs: list[_Segment], grid: np.ndarray, m: MachineModel) -> tuple[np.ndarray, ...]:
    """Per axis, what the control commands the position loop (mm), and the program's angle (rad).

    The interpolated path (held per interpolation cycle), the backlash compensation
    (``+(comp/2) sgn(v)`` of the path's command, stepping at each commanded
    reversal) and the master-slave changeover.
    """
    cx, cy, cu = _command(segs, grid)
    if m.ipo_s > 0:
        # The interpolator updates the command once per cycle; the angle reported
        # for the samples stays the continuous program's.
        cx, cy, _ = _command(segs, np.floor(grid / m.ipo_s + 1e-9) * m.ipo_s)
    # Both quirks follow the path's command, not each other's steps.
    px, py = cx, cy
    comp_x = m.backlash_comp_x_um + max(-m.backlash_x_um, 0.0)
    comp_y = m.backlash_comp_y_um + max(-m.backlash_y_um, 0.0)
    if comp_x:
        cx = cx + 0.5 * comp_x * UM * _direction(px)
    if comp_y:
        cy = cy + 0.5 * comp_y * UM * _direction(py)
    if m.master_slave_a_um or m.master_slave_b_um:
        sig = 0.5 * _master_sigma(px, py) * UM / math.sqrt(2.0)
        a, b = m.master_slave_a_um, m.master_slave_b_um
        cx = cx + sig * (a + b)
        cy = cy + sig * (a - b)
    return cx, cy, cu


def _motors(cx: np.ndarray, cy: np.ndarray, m: MachineModel, h: float) -> list[np.ndarray]:
    return [_axis(cx, m.kv_x_per_s, m.velocity_ff, m.velocity_loop_x_hz, m.velocity_loop_damping, h),
            _axis(cy, m.kv_y_per_s, m.velocity_ff, m.velocity_loop_y_hz, m.velocity_loop_damping, h)]


def _axis(c: np.ndarray, kv: float, ff: float, vel_hz: float, zeta: float, h: float) -> np.ndarray:
    """One axis' motor position for the command ``c``: the position loop alone (first order) or, with a
    velocity loop of natural frequency ``vel_hz`` and damping ``zeta``, the position loop closed around it."""
    if vel_hz <= 0 or math.isinf(kv):
        return _servo(c, kv, ff, h)
    return _servo_velocity_loop(c, kv, ff, 2.0 * math.pi * vel_hz, zeta, h)


def _servo_velocity_loop(c: np.ndarray, kv: float, ff: float, wv: float, zeta: float, h: float) -> np.ndarray:
    """Response of a position loop around a second-order velocity loop to ``c`` linear between grid points.

    The position controller commands the velocity ``kv (c - p) + ff dc/dt``; the velocity loop follows that
    command as ``v'' + 2 zeta wv v' + wv^2 v = wv^2 v_cmd``, and ``p' = v``.  From command to position:
    ``wv^2 (kv + ff s) / (s^3 + 2 zeta wv s^2 + wv^2 s + wv^2 kv)``, discretised with a first-order hold
    (exact for a command linear between grid points), from rest on the first command.
    """
    num = [wv * wv * ff, wv * wv * kv] if ff else [wv * wv * kv]
    den = [1.0, 2.0 * zeta * wv, wv * wv, wv * wv * kv]
    b, a, _ = cont2discrete((num, den), h, method="foh")
    b = np.asarray(b).ravel()
    out = lfilter(b, a, c - c[0])
    return np.asarray(out + c[0])


def _command(segs: list[_Segment], times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Commanded X, Y (mm) and angle (rad, unwrapped as the program's arcs) at ``times``."""
    first, last = segs[0].move.start, segs[-1].move.end
    x = np.full(times.size, first[0])
    y = np.full(times.size, first[1])
    u0 = next((s.move.u_start for s in segs if s.move.kind == "arc"), math.atan2(first[1], first[0]))
    u = np.full(times.size, u0)
    for seg in segs:
        i0, i1 = np.searchsorted(times, [seg.t_start, seg.t_end], side="left")
        mv = seg.move
        if seg.profile is None:
            x[i0:i1], y[i0:i1] = mv.start
        else:
            s = seg.profile.position(times[i0:i1] - seg.t_start)
            p = mv.point_at(s)
            x[i0:i1], y[i0:i1] = p[:, 0], p[:, 1]
            if mv.kind == "arc":
                u[i0:i1] = mv.u_start + math.copysign(1.0, mv.sweep) * s / mv.radius
        if mv.kind != "arc" and i0 > 0:
            u[i0:i1] = u[i0 - 1]  # lines are radial, dwells stand: the angle holds
    i_end = int(np.searchsorted(times, segs[-1].t_end, side="left"))
    x[i_end:], y[i_end:] = last
    if i_end > 0:
        u[i_end:] = u[i_end - 1]
    return x, y, u


# --------------------------------------------------------------------------- drives


def _servo(c: np.ndarray, kv: float, ff: float, h: float) -> np.ndarray:
    """Exact response of ``dp/dt = kv (c - p) + ff dc/dt`` to ``c`` linear between grid points."""
    if math.isinf(kv) or ff == 1.0:
        return c.copy()
    a = math.exp(-kv * h)
    g = (ff - 1.0) * np.diff(c) / (kv * h)  # the error's steady value on each step
    e = np.empty_like(c)
    e[0] = 0.0  # starts at rest on its command
    e[1:] = lfilter([1.0 - a], [1.0, -a], g)
    return c + e


def _direction(x: np.ndarray) -> np.ndarray:
    """Direction of motion per grid point: sign of the last real movement, 0 before any."""
    dx = np.diff(x)
    s = np.sign(dx).astype(np.int8)
    s[np.abs(dx) <= _EPS_MM] = 0
    idx = np.where(s != 0, np.arange(s.size), -1)
    np.maximum.accumulate(idx, out=idx)
    state = np.zeros(x.size, dtype=np.int8)
    state[1:] = np.where(idx >= 0, s[np.maximum(idx, 0)], 0)
    return state


def _runs(state: np.ndarray) -> Iterator[tuple[int, int, int]]:
    bounds = np.flatnonzero(np.diff(state)) + 1
    starts = np.concatenate([[0], bounds])
    ends = np.concatenate([bounds, [state.size]])
    for i, j in zip(starts.tolist(), ends.tolist(), strict=True):
        yield i, j, int(state[i])


def _play(x: np.ndarray, half: float) -> np.ndarray:
    """Play (deadband) operator of half-width ``half``, starting centred.

    ``y_n = clip(y_{n-1}, x_n - half, x_n + half)``, computed per monotone run.
    """
    if half <= 0:
        return x.copy()
    y = np.empty_like(x)
    y_prev = float(x[0])
    for i, j, s in _runs(_direction(x)):
        seg = x[i:j]
        if s > 0:
            y[i:j] = np.maximum(y_prev, np.maximum.accumulate(seg - half))
        elif s < 0:
            y[i:j] = np.minimum(y_prev, np.minimum.accumulate(seg + half))
        else:
            y[i:j] = y_prev
        np.clip(y[i:j], seg - half, seg + half, out=y[i:j])
        y_prev = float(y[j - 1])
    return y


def _stick_slip(x: np.ndarray, h: float, step: float, speed: float) -> np.ndarray:
    """Position error of a table that sticks and slips by ``step`` while slower than ``speed``."""
    err = np.zeros_like(x)
    if step <= 0:
        return err
    slow = np.abs(np.gradient(x, h)) < speed
    edges = np.flatnonzero(np.diff(slow.astype(np.int8))) + 1
    starts = np.concatenate([[0], edges])
    ends = np.concatenate([edges, [x.size]])
    for i0, i1 in zip(starts.tolist(), ends.tolist(), strict=True):
        if not slow[i0]:
            continue
        xs = x[i0:i1]
        y = np.empty_like(xs)
        y_prev = float(xs[0])
        for i, j, s in _runs(_direction(xs)):
            seg = xs[i:j]
            if s > 0:
                y[i:j] = y_prev + step * np.floor(np.maximum(np.maximum.accumulate(seg) - y_prev, 0.0) / step)
            elif s < 0:
                y[i:j] = y_prev - step * np.floor(np.maximum(y_prev - np.minimum.accumulate(seg), 0.0) / step)
            else:
                y[i:j] = y_prev
            y_prev = float(y[j - 1])
        err[i0:i1] = y - xs
    return err


def _spike(grid: np.ndarray, state: np.ndarray, height_mm: float, tau: float) -> np.ndarray:
    """Extra lag against the new direction after each reversal, decaying with time."""
    out = np.zeros(grid.size)
    if height_mm == 0:
        return out
    rev = np.zeros(grid.size, dtype=bool)
    rev[1:] = state[1:].astype(np.int16) * state[:-1] < 0
    last = np.where(rev, np.arange(grid.size), -1)
    np.maximum.accumulate(last, out=last)
    have = last >= 0
    dt = grid[have] - grid[last[have]]
    out[have] = -height_mm * state[have] * np.exp(-dt / tau)
    return out


def _lateral_factor(x_table: np.ndarray, takeup_um: float, state: np.ndarray) -> np.ndarray:
    """-sgn(v) of an axis, switching at its reversals (over ``takeup_um`` of travel if > 0)."""
    if takeup_um <= 0:
        return -state.astype(float)
    half = 0.5 * takeup_um * UM
    return (_play(x_table, half) - x_table) / half


def _master_sigma(cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
    """+1 where the commanded |vX| >= |vY|, -1 elsewhere, held while the command stands."""
    vx, vy = np.abs(np.gradient(cx)), np.abs(np.gradient(cy))
    moving = (vx + vy) > _EPS_MM
    sig = np.where(vx >= vy, 1.0, -1.0)
    if not moving.any():
        return np.ones(cx.size)
    idx = np.where(moving, np.arange(cx.size), -1)
    np.maximum.accumulate(idx, out=idx)
    idx[idx < 0] = int(np.argmax(moving))  # before the first motion: the first master
    return sig[idx]


# --------------------------------------------------------------------------- truth


def truth_of(plan: TestPlan, m: MachineModel) -> dict[str, float]:
    """What a fit of a test of ``plan`` on ``m`` should report (analysis/README.md field names).

    Extras: ``feed_mm_min`` (actual), ``overhead_s`` (per-move ``c``), ``lag_*_ms``
    (steady following-error time ``(1 - ff)/Kv``), ``servo_radius_um`` and
    ``servo_scale_ppm`` (second-order effects of the loops on a circle: mean radius
    change and the apparent ``scale_mismatch_ppm`` a linear fit reads),
    ``radius_total_um`` (expected constant term: calibration + mean scale + loops),
    ``reversal_spike_width_{x|y}_deg`` (``V tau / R``).  Spike keys: ``pos``/``neg`` is
    the axis end where it reverses (X: 0/180 deg, Y: 90/270 deg); the height is the
    radial bump right after the table's reversal, outward for ``h > 0``.
    """
    R = plan.radius_mm
    V = plan.feed_mm_s * m.feed_override
    w = V / R
    ff = m.velocity_ff

    def loop(kv: float, vel_hz: float) -> tuple[float, float, float]:
        if math.isinf(kv):
            return 0.0, 1.0, 0.0
        s = complex(0.0, w)
        g = complex(kv, ff * w) / complex(kv, w)
        if vel_hz > 0:
            wv, z = 2.0 * math.pi * vel_hz, m.velocity_loop_damping
            g = wv * wv * (kv + ff * s) / (s**3 + 2 * z * wv * s**2 + wv * wv * s + wv * wv * kv)
        return (1.0 - ff) / kv, abs(g), -math.atan2(g.imag, g.real)

    lag_x, amp_x, ph_x = loop(m.kv_x_per_s, m.velocity_loop_x_hz)
    lag_y, amp_y, ph_y = loop(m.kv_y_per_s, m.velocity_loop_y_hz)
    servo_radius = R * ((amp_x**2 + amp_y**2) / 2.0 - 1.0) / 2.0 / UM
    servo_scale = (amp_x**2 * math.cos(2 * ph_x) - amp_y**2 * math.cos(2 * ph_y)) / 2.0 * 1e6
    smooth = m.accel_mm_s2 / m.jerk_mm_s3 if math.isfinite(m.accel_mm_s2) else 0.0
    overhead = (V / m.accel_mm_s2 if math.isfinite(m.accel_mm_s2) else 0.0) + smooth
    t: dict[str, float] = {
        "centre_x_um": m.centre_x_um,
        "centre_y_um": m.centre_y_um,
        "radius_um": m.radius_um,
        "backlash_x_um": m.backlash_x_um - m.backlash_comp_x_um,
        "backlash_y_um": m.backlash_y_um - m.backlash_comp_y_um,
        "servo_mismatch_ms": 1000.0 * (lag_x - lag_y),
        "master_slave_a_um": m.master_slave_a_um,
        "master_slave_b_um": m.master_slave_b_um,
        "squareness_urad": m.squareness_urad,
        "scale_mismatch_ppm": m.scale_x_ppm - m.scale_y_ppm,
        "lateral_play_x_um": m.lateral_play_x_um,
        "lateral_play_y_um": m.lateral_play_y_um,
        "straightness_x_um": m.straightness_x_um,
        "straightness_y_um": m.straightness_y_um,
        "cyclic_x_um": m.cyclic_x_um,
        "cyclic_y_um": m.cyclic_y_um,
        "cyclic_x_phase_deg": m.cyclic_x_phase_deg,
        "cyclic_y_phase_deg": m.cyclic_y_phase_deg,
        "pitch_x_mm": m.pitch_x_mm,
        "pitch_y_mm": m.pitch_y_mm,
        "drift_um_per_min": m.drift_um_per_min,
        "feed_mm_min": V * 60.0,
        "overhead_s": overhead,
        "lag_x_ms": 1000.0 * lag_x,
        "lag_y_ms": 1000.0 * lag_y,
        "servo_radius_um": servo_radius,
        "servo_scale_ppm": servo_scale,
        "radius_total_um": m.radius_um + R * (m.scale_x_ppm + m.scale_y_ppm) / 2.0 * 1e-6 / UM + servo_radius,
        "reversal_spike_width_x_deg": math.degrees(V * m.spike_tau_x_s / R),
        "reversal_spike_width_y_deg": math.degrees(V * m.spike_tau_y_s / R),
        "stick_slip_um": m.stick_slip_um,
        "vibration_um": m.vibration_um,
        "vibration_hz": m.vibration_hz,
        "noise_um": m.noise_um,
    }
    for d in plan.direction_list:
        name = "ccw" if d > 0 else "cw"
        for axis, h in (("x", m.spike_x_um), ("y", m.spike_y_um)):
            for end in ("pos", "neg"):
                t[f"reversal_spike_{axis}_{end}_{name}_um"] = h
    return t


def _events(plan: TestPlan, segs: list[_Segment], t0: float) -> dict[str, float]:
    ev: dict[str, float] = {"test_start": t0}
    for seg in segs:
        ev[f"{seg.move.name}_start"] = t0 + seg.t_start
        ev[f"{seg.move.name}_end"] = t0 + seg.t_end
        if seg.move.kind == "arc" and seg.profile is not None:
            d = 1 if seg.move.sweep > 0 else -1
            u_ds = math.radians(data_start_deg(plan, d))
            s0 = abs(u_ds - seg.move.u_start) * seg.move.radius
            s1 = s0 + math.radians(plan.data_arc_deg) * seg.move.radius
            ev[f"data_start_{seg.move.name}"] = t0 + seg.t_start + seg.profile.time_at(s0)
            ev[f"data_end_{seg.move.name}"] = t0 + seg.t_start + seg.profile.time_at(s1)
    fi = next(s for s in segs if s.move.name == "feed_in")  # after a signature, where there is one
    ev["feed_in_centroid"] = t0 + fi.t_start + 0.5 * fi.duration
    fo = segs[-1]
    ev["feed_out_centroid"] = t0 + fo.t_start + 0.5 * fo.duration
    return ev


# --------------------------------------------------------------------------- simulation


def _check_rate(plan: TestPlan, sample_hz: float | None) -> float:
    fs = float(plan.sample_hz if sample_hz is None else sample_hz)
    if not SAMPLE_HZ_MIN <= fs <= SAMPLE_HZ_MAX:
        raise PlanError(f"sample_hz must be within {SAMPLE_HZ_MIN}..{SAMPLE_HZ_MAX:g}, not {fs!r}")
    return fs


def _rngs(seed: int, index: int) -> dict[str, np.random.Generator]:
    ss = np.random.SeedSequence([int(seed), int(index)])
    names = ("jitter", "drop", "noise")
    return dict(zip(names, (np.random.default_rng(s) for s in ss.spawn(len(names))), strict=True))


def _run(
    plan: TestPlan,
    m: MachineModel,
    fs: float,
    seed: int,
    index: int,
    k0: int,
    extra_tail_s: float,
    step_s: float,
    program: Sequence[Move] | None = None,
) -> SimResult:
    if not step_s > 0:
        raise PlanError(f"step_s must be > 0, not {step_s!r}")
    sub = max(1, math.ceil(1.0 / (fs * step_s)))  # grid points per sample period
    h = 1.0 / (fs * sub)
    segs = _timeline(plan, m, program, h)
    span = segs[-1].t_end + m.tail_s + extra_tail_s
    n = math.ceil(span * fs) + 1  # nominal sample instants k0 .. k0 + n - 1
    grid = np.arange((n - 1) * sub + 1) * h  # local time, s
    R = plan.radius_mm

    cx, cy, cu = _axis_commands(segs, grid, m)
    axes = [_play(motor, 0.5 * max(b_um, 0.0) * UM) for motor, b_um in
            zip(_motors(cx, cy, m, h), (m.backlash_x_um, m.backlash_y_um), strict=True)]
    del cx, cy
    tx, ty = axes
    sx, sy = _direction(tx), _direction(ty)
    px = tx + _spike(grid, sx, m.spike_x_um * UM, m.spike_tau_x_s)
    py = ty + _spike(grid, sy, m.spike_y_um * UM, m.spike_tau_y_s)
    if m.stick_slip_um > 0:
        step = m.stick_slip_um * UM
        px += _stick_slip(tx, h, step, m.stick_slip_speed_mm_s)
        py += _stick_slip(ty, h, step, m.stick_slip_speed_mm_s)
    # Lateral play: -(l/2) sgn(v) of the other axis.
    if m.lateral_play_x_um:
        py += 0.5 * m.lateral_play_x_um * UM * _lateral_factor(tx, m.lateral_takeup_um, sx)
    if m.lateral_play_y_um:
        px += 0.5 * m.lateral_play_y_um * UM * _lateral_factor(ty, m.lateral_takeup_um, sy)
    del tx, ty, sx, sy

    # Sample instants (local time): taken at t_take, reported at t_rep.
    rng = _rngs(seed, index)
    k = np.arange(n)
    t_nom = k / fs
    jit = rng["jitter"].normal(0.0, m.jitter_s, n) if m.jitter_s > 0 else None
    t_take, t_rep = t_nom, t_nom
    if jit is not None and m.jitter_stamped:
        t_rep = t_nom + jit
    elif jit is not None:
        t_take = np.clip(t_nom + jit, grid[0], grid[-1])
    if jit is None or m.jitter_stamped:
        sel = k * sub
        X, Y, U = px[sel], py[sel], cu[sel]
    else:
        X, Y, U = (np.interp(t_take, grid, arr) for arr in (px, py, cu))
    del px, py, cu, grid

    # Geometry on the table position (mm, from the programmed centre).
    DX = (
        m.squareness_urad * 1e-6 * Y
        + m.scale_x_ppm * 1e-6 * X
        + m.straightness_y_um * UM * (Y / R) ** 2
        + m.cyclic_x_um * UM * np.sin(2 * np.pi * X / m.pitch_x_mm + math.radians(m.cyclic_x_phase_deg))
    )
    DY = (
        m.scale_y_ppm * 1e-6 * Y
        + m.straightness_x_um * UM * (X / R) ** 2
        + m.cyclic_y_um * UM * np.sin(2 * np.pi * Y / m.pitch_y_mm + math.radians(m.cyclic_y_phase_deg))
    )
    L = np.hypot(X + DX + m.centre_x_um * UM, Y + DY + m.centre_y_um * UM)
    del X, Y, DX, DY
    L += m.radius_um * UM
    if m.drift_um_per_min:
        L += m.drift_um_per_min * UM * (t_take - segs[0].t_start) / 60.0
    if m.length_step_um:
        L += m.length_step_um * UM * (t_take >= segs[0].t_start + m.length_step_s)
    if m.vibration_um:
        phase = 2 * np.pi * m.vibration_hz * t_take + math.radians(m.vibration_phase_deg)
        L += m.vibration_um * UM * np.sin(phase)
    if m.noise_um > 0:
        L += rng["noise"].normal(0.0, m.noise_um * UM, n)
    if m.quantum_um > 0:
        q = m.quantum_um * UM
        L = np.round(L / q) * q

    keep = np.ones(n, dtype=bool)
    if m.drop_fraction > 0:
        keep &= rng["drop"].random(n) >= m.drop_fraction
    if m.drop_indices:
        idx = np.asarray(m.drop_indices, dtype=np.int64)
        keep[idx[idx < n]] = False
    t0 = k0 / fs
    return SimResult(
        t_s=(t0 + t_rep)[keep],
        length_mm=L[keep],
        angle_deg=np.degrees(U[keep]),
        truth=truth_of(plan, m),
        events=_events(plan, segs, t0),
        plan=plan,
        machine=m,
        sample_hz=fs,
        index=index,
        n_slots=n,
    )


def simulate(
    plan: TestPlan,
    machine: MachineModel,
    sample_hz: float | None = None,
    seed: int = 0,
    *,
    step_s: float = 1.0e-4,
    program: Sequence[Move] | None = None,
) -> SimResult:
    """Simulate one test of ``plan`` on ``machine``, sampled at ``sample_hz`` (default: the plan's).

    ``step_s`` is the longest internal integration step (the grid is aligned to the
    sample instants).  The same ``seed`` gives the same samples.  ``program``: the
    moves to run instead of ``moves(plan)`` (e.g. an NC program read back by
    :func:`ballbar.tools.ncinterp.test_moves`), in the plan's frame and angles, run
    at the plan's feed; the truth and the data-arc events still come from the plan.
    """
    fs = _check_rate(plan, sample_hz)
    return _run(plan, machine, fs, seed, 0, 0, 0.0, step_s, program)


def iter_tests(
    plan: TestPlan,
    machine: MachineModel,
    sample_hz: float | None = None,
    seed: int = 0,
    repeat: int | None = None,
    gap_s: float = 0.0,
    *,
    step_s: float = 1.0e-4,
    drift: Mapping[str, float] | None = None,
) -> Iterator[SimResult]:
    """Successive tests on one continuous sample clock, forever if ``repeat`` is None.

    ``drift``: machine keys and how much each changes from one test to the next
    (test ``i`` runs ``machine`` with ``key + i * rate``): a machine that wears.

    Between tests the machine stands at ``R + f`` for ``tail_s + gap_s + lead_s``; the
    samples of that wait belong to the test before (its tail) and after (its lead).
    Test ``i`` draws its random effects from ``(seed, i)``; the first equals
    :func:`simulate` when ``gap_s`` is 0.  A program that ends elsewhere than it
    starts (a one-direction partial arc) jumps back during the gap: not simulated.
    """
    fs = _check_rate(plan, sample_hz)
    if not gap_s >= 0:
        raise PlanError(f"gap_s must be >= 0, not {gap_s!r}")
    k0, i = 0, 0
    names = {f.name for f in fields(MachineModel)}
    for key in drift or {}:
        if key not in names or key in ("jitter_stamped", "drop_indices"):
            raise PlanError(f"drift: {key!r} is not a numeric machine key")
    while repeat is None or i < repeat:
        m = machine
        if drift:
            m = replace(machine, **{k: getattr(machine, k) + i * float(r) for k, r in drift.items()})
        res = _run(plan, m, fs, seed, i, k0, gap_s, step_s)
        k0 += res.n_slots
        i += 1
        yield res


def iter_programs(
    tests: Iterable[tuple[TestPlan, MachineModel, Sequence[Move] | None]],
    sample_hz: float,
    seed: int = 0,
    gap_s: float = 0.0,
    *,
    step_s: float = 1.0e-4,
) -> Iterator[SimResult]:
    """Tests of several plans in turn on one sample clock (a set): each ``(plan, machine, program)`` of
    ``tests`` run as :func:`simulate` runs it, ``gap_s`` between them as in :func:`iter_tests` (test ``i``
    draws its random effects from ``(seed, i)``).  Each program starts and ends at its plan's wait point: a
    set's programs move between planes during the gap (the operator re-mounts the bar), not simulated."""
    fs = float(sample_hz)
    if not gap_s >= 0:
        raise PlanError(f"gap_s must be >= 0, not {gap_s!r}")
    k0 = 0
    for i, (plan, m, program) in enumerate(tests):
        _check_rate(plan, fs)
        res = _run(plan, m, fs, seed, i, k0, gap_s, step_s, program)
        k0 += res.n_slots
        yield res


def iter_chunks(
    plan: TestPlan,
    machine: MachineModel,
    sample_hz: float | None = None,
    seed: int = 0,
    repeat: int | None = None,
    gap_s: float = 0.0,
    chunk: int = 1000,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """``(t_s, length_mm)`` chunks of at most ``chunk`` samples of :func:`iter_tests`."""
    for res in iter_tests(plan, machine, sample_hz, seed, repeat, gap_s):
        for i in range(0, res.t_s.size, chunk):
            yield res.t_s[i : i + chunk], res.length_mm[i : i + chunk]


# --------------------------------------------------------------------------- command line




__all__ = [
    "MachineModel",
    "SimResult",
    "iter_chunks",
    "iter_programs",
    "iter_tests",
    "simulate",
    "truth_of",
]
