"""The pattern library of analysis/README.md: one mask per physical error.

Every mask is the radial deviation ``dR(u, d)`` (micrometres) that a physical
error model ``D = (DX, DY)`` produces through ``dR = DX cos u + DY sin u``
(analysis/README.md; Suh & Lee eq. 2).  ``u`` is the commanded angle in
radians, counter-clockwise from the plane's first axis, ``d`` the direction
(+1 CCW, -1 CW), ``V`` the path feed in mm/s, ``R`` the radius in mm and ``t``
the time in minutes from the test's feed-in.

Each :class:`Pattern` is linear in its parameters and is a *group* for the
extra-sum-of-squares ranking: ``centre`` has two parameters (x0, y0) and is
tested as one term; each axis' backlash is its own term.  The order of
:data:`LIBRARY` is the priority when two patterns cannot be told apart in the
data: the later one is left out.

The seed's three patterns (backlash eq. 3-4, master-slave changeover eq. 5-6,
servo mismatch eq. 7-8) are the analysis/README.md forms of those equations.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

UM_PER_MM = 1000.0
SPIKE_REACH = 50.0  # widths past its onset beyond which a spike's exp(-du / w) is taken as 0 (e^-50 = 2e-22)


@dataclass(frozen=True)
class Geometry:
    """Per-sample inputs of the masks.

    ``u``: commanded angle (rad); ``d``: direction (+1/-1); ``t_min``: minutes
    from the test's feed-in; ``V``: path feed (mm/s); ``R``: radius (mm);
    ``pitch``: ball-screw pitch per axis (mm) or None; ``travel``: angle (rad)
    travelled since the arc began, so that a reversal the arc never passed has
    no spike; ``loop_lag_s``: the position loops' mean lag, where known, through
    which a step made in the command (master-slave changeover, backlash
    compensation) reaches the axes.  ``onset_rad``: per axis, the angle from a
    reversal point to where the table itself reverses and friction acts
    (positive after a dead band's take-up, negative where an over-compensated
    command step pulls the table round early).  ``comp_x``/``comp_y``: that
    axis' lost motion is the control's compensation step passed through the
    loop (backlash < 0), not a step at the reversal.
    """

    u: np.ndarray
    d: np.ndarray
    t_min: np.ndarray
    V: float
    R: float
    pitch_x_mm: float | None = None
    pitch_y_mm: float | None = None
    travel: np.ndarray | None = None  # angle travelled since the arc began (rad); None: long enough
    loop_lag_s: float | None = None  # mean position-loop lag, where known: smooths command-side steps
    onset_rad: tuple[float, float] = (0.0, 0.0)  # X, Y: from a reversal point to the table's own reversal
    reversal_rad: tuple[float, float] = (0.0, 0.0)  # X, Y: from a reversal point to the axis' (motor's) reversal
    comp_x: bool = False  # X's lost motion is a compensation step through the loop
    comp_y: bool = False
    deadband: tuple[bool, bool] = (False, False)  # X, Y: a dead band, whose step sits at the take-up's end
    loop_rad: tuple[float, float, float] | None = None  # the command's lead, X's and Y's loop lag, as angles
    # angle a sample (or a bin of samples) averages over, per row or for all (0: an instant); see _switch
    aperture_rad: float | np.ndarray = 0.0
    # A stack of timings (a search's batch): the rows are len(feeds) equal blocks, each at its own feed (V is
    # the first's); None: one timing at V.
    feeds: np.ndarray | None = None

    def loop_angles(self, axis: int | None) -> tuple[float | np.ndarray, float | np.ndarray]:
        """The command's lead over the frame and an axis' loop time constant (None: the mean), as angles
        (per sample for a stack of timings at their own feeds)."""
        if self.loop_rad is not None:
            lead, lx, ly = self.loop_rad
            lag = 0.5 * (lx + ly) if axis is None else (lx, ly)[axis]
            return lead, max(lag, 1e-12)
        assert self.loop_lag_s is not None
        mean = self.feed / self.R * self.loop_lag_s
        return mean, mean

    @cached_property
    def phase(self) -> np.ndarray:
        """Angle travelled past 0 (rad, in [0, 2 pi)): ``spike_travel(u, d, 0)``."""
        return wrap(self.d * self.u, 2.0 * math.pi)

    @cached_property
    def direction(self) -> int:
        """The direction all samples share (+1, -1); 0 where they do not."""
        if self.d.size and bool((self.d == self.d[0]).all()):
            return int(self.d[0])
        return 0

    @cached_property
    def dd(self) -> float | np.ndarray:
        """The direction as a factor: the scalar all samples share (one pass over them fewer per use), else
        ``d``."""
        return float(self.direction) if self.direction else self.d

    @cached_property
    def feed(self) -> float | np.ndarray:
        """The path feed: ``V``, or per sample for a stack of timings (``feeds``)."""
        if self.feeds is None:
            return self.V
        return np.repeat(self.feeds, len(self) // self.feeds.size)

    def __len__(self) -> int:
        return int(self.u.size)

    # The masks share a few functions of the angle: each is computed once per geometry.
    @cached_property
    def _cos_sin_u(self) -> tuple[np.ndarray, np.ndarray]:
        return cos_sin(self.u)

    @property
    def cos_u(self) -> np.ndarray:
        return self._cos_sin_u[0]

    @property
    def sin_u(self) -> np.ndarray:
        return self._cos_sin_u[1]

    @cached_property
    def sin_2u(self) -> np.ndarray:
        return 2.0 * self.sin_u * self.cos_u

    @cached_property
    def cos_2u(self) -> np.ndarray:
        return (self.cos_u - self.sin_u) * (self.cos_u + self.sin_u)


# A mask's columns: an (n, q) array, or q arrays of n (each written into its column as made)
Columns = np.ndarray | tuple[np.ndarray, ...]
ColumnFn = Callable[[Geometry, float], Columns]
# a reversal spike's rows where it acts, and the angle travelled past its onset there (None: not one circle's rows)
SupportFn = Callable[[Geometry, float], tuple[np.ndarray, np.ndarray] | None]


@dataclass(frozen=True)
class Pattern:
    """One term of the model.

    ``fields``: the result fields of its parameters; ``units``: their units;
    ``fn(geometry, spike_width_rad)`` returns the ``(n, q)`` mask columns for a
    parameter of 1 unit each.  ``kind``: ``setup`` (the set-up, not the
    machine), ``machine`` or ``reversal``.  ``reversal`` is the (axis, angle,
    direction) of a reversal spike.
    """

    name: str
    fields: tuple[str, ...]
    units: tuple[str, ...]
    fn: ColumnFn
    kind: str = "machine"
    needs: str = ""  # "pitch_x", "pitch_y": left out when the machine config lacks it
    reversal: tuple[str, float, int] | None = None
    support: SupportFn | None = None  # a spike's: where its column is not 0 (:func:`design` batches them)

    @property
    def q(self) -> int:
        return len(self.fields)

    def columns(self, g: Geometry, spike_width_rad: float) -> np.ndarray:
        cols = self.fn(g, spike_width_rad)
        if isinstance(cols, tuple):
            return np.column_stack(cols)
        return cols.reshape(len(g), self.q)


def _switch(g: Geometry, value: np.ndarray, from_first: np.ndarray, period: float) -> np.ndarray:
    """``sign(value)``, a sign that switches every ``period`` (``from_first``: the angle past a switching
    point), averaged over the sample's aperture: a ramp across each switch ``aperture_rad`` wide.

    A sample is an average over its acquisition, and an instant step placed
    between two samples would make the fit's timing a staircase.
    """
    s = np.sign(value)
    h = 0.5 * g.aperture_rad
    if np.ndim(h) == 0 and h <= 0:
        return s
    half = 0.5 * period
    dist = np.abs(wrap(from_first + half, period) - half)  # to the nearest switching point
    return s * np.minimum(dist / np.maximum(h, 1e-300), 1.0)


def cos_sin(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cos x, sin x`` from ``t = tan(x / 2)``: ``(1 - t^2) / (1 + t^2)``, ``2 t / (1 + t^2)``, within 3e-16
    of the exact values (np.cos and np.sin: 6e-17) and several times cheaper: numpy's float64 tangent is
    vectorised, its sine and cosine are not."""
    t = np.tan(0.5 * x)
    t2 = t * t
    den = 1.0 + t2
    return (1.0 - t2) / den, (2.0 * t) / den


def wrap(x: np.ndarray, period: float) -> np.ndarray:
    """``x`` modulo ``period``, in ``[0, period)`` as ``np.mod`` (to its rounding): several times cheaper."""
    return _wrap_count(x, period)[0]


def _wrap_count(x: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """``x`` modulo ``period`` and the whole periods taken off (``floor(x / period)``)."""
    k = np.floor(x / period)
    r = x - period * k
    low = r < 0.0  # x / period rounded up to a whole number
    if low.any():
        r[low] += period
        k[low] -= 1.0
    return r, k


def _centre(g: Geometry, _w: float) -> Columns:
    return g.cos_u, g.sin_u


def _radius(g: Geometry, _w: float) -> np.ndarray:
    return np.ones(len(g))


def _backlash_x(g: Geometry, _w: float) -> np.ndarray:
    # DX = -(bX/2) sgn(vX), vX = -d V sin u
    if g.comp_x and g.loop_lag_s:
        # the command's sign, d sgn(sin uc), is +1 on the even half-turns after 0 (either direction)
        out = _loop_steps(g, 0.0, math.pi, (0,))[0]
        out *= 0.5
        out *= g.cos_u
        return out
    s = _step_at(g, 0)
    if s == 0.0:
        out = _switch(g, g.sin_u, g.u, math.pi)
    else:
        us = g.u - g.dd * s
        sin_us = g.sin_u * math.cos(s) - g.dd * (g.cos_u * math.sin(s))  # sin(u - d s), d = +-1
        out = _switch(g, sin_us, us, math.pi)
    out *= 0.5 * g.dd
    out *= g.cos_u
    return out


def _backlash_y(g: Geometry, _w: float) -> np.ndarray:
    # DY = -(bY/2) sgn(vY), vY = d V cos u
    if g.comp_y and g.loop_lag_s:
        # -d sgn(cos uc): +1 on the even half-turns after 90 deg (either direction)
        out = _loop_steps(g, 0.5 * math.pi, math.pi, (1,))[0]
        out *= 0.5
        out *= g.sin_u
        return out
    s = _step_at(g, 1)
    if s == 0.0:
        out = _switch(g, g.cos_u, g.u - 0.5 * math.pi, math.pi)
    else:
        us = g.u - g.dd * s
        cos_us = g.cos_u * math.cos(s) + g.dd * (g.sin_u * math.sin(s))  # cos(u - d s)
        out = _switch(g, cos_us, us - 0.5 * math.pi, math.pi)
    out *= -0.5 * g.dd
    out *= g.sin_u
    return out


def _step_at(g: Geometry, axis: int) -> float:
    """Where after a reversal point an axis' lost motion steps (rad): where its table moves again after a
    dead band's take-up (its remainder, :func:`.physics.lost_motion_remainder`, is the bump before), else where
    the axis itself reverses."""
    return g.onset_rad[axis] if g.deadband[axis] else g.reversal_rad[axis]


def _servo(g: Geometry, _w: float) -> np.ndarray:
    # DX = -vX/KX, DY = -vY/KY; m = 1/KX - 1/KY in ms; V [mm/s] * m [ms] = um
    if g.feeds is None or not g.direction:
        return 0.5 * g.feed * g.dd * g.sin_2u
    # a stack of timings: each block at its own feed
    k = g.feeds.size
    return (g.sin_2u.reshape(k, -1) * (0.5 * g.direction * g.feeds)[:, None]).reshape(-1)


def through_loop(
    g: Geometry, sign: Callable[[np.ndarray], np.ndarray], first_rad: float, period_rad: float, axis: int | None
) -> np.ndarray:
    """A sign the control switches in the command, as an axis sees it through its first-order loop.

    ``sign(uc)`` is the command-side value (+-1) at the commanded angle ``uc``;
    it switches at ``first_rad + k period_rad``.  In the frame of the actual
    position (the analyzer's) the command is ``lead`` ahead; after it crosses a
    switching angle the axis approaches the new value as
    ``1 - 2 exp(-delta / lag)``, ``delta`` the command's angle travelled since
    the crossing and ``lag`` the axis' time constant as an angle (``axis``
    None: the mean).  A switch the command has not passed since the arc began
    (``travel``) is taken as long settled.
    """
    lead, lag = g.loop_angles(axis)
    uc = g.u + g.d * lead
    since = wrap(g.d * (uc - first_rad), period_rad)
    settle = np.exp(-since / lag)
    if g.travel is not None:
        settle[since > g.travel + lead] = 0.0
    return sign(uc) * (1.0 - 2.0 * settle)


def _loop_steps(g: Geometry, first_rad: float, period_rad: float, axes: Sequence[int]) -> list[np.ndarray]:
    """:func:`through_loop` for each of ``axes``, of a command-side sign that is +1 from each even-numbered
    switching angle after ``first_rad`` (in the direction of travel) to the next, -1 from each odd one: the
    angles travelled and the sign are shared, the axes differ only in their lag.

    ``sign (1 - 2 settle)`` is ``sign`` but where the loop still settles: the exponential is made only where it
    is not below ``exp(-SPIKE_REACH)`` (a few degrees after each switch), as the spikes' are.
    """
    lead = g.loop_angles(axes[0])[0]  # the command's lead is the frame's, the same for both axes
    since, k = _wrap_count(g.d * (g.u - first_rad) + lead, period_rad)  # d (uc - first), uc = u + d lead
    sign = 1.0 - 2.0 * (k - 2.0 * np.floor(0.5 * k))  # (-1)^k
    out: list[np.ndarray] = []
    last: float | np.ndarray | None = None
    for axis in axes:
        lag = g.loop_angles(axis)[1]
        if out and isinstance(lag, float) and lag == last:  # equal loops
            out.append(out[-1])
            continue
        reach = SPIKE_REACH * lag
        near = np.flatnonzero(since < reach)
        if g.travel is not None:  # a switch the command has not passed since the arc began: long settled
            limit = g.travel[near] + (lead if isinstance(lead, float) else lead[near])
            near = near[since[near] <= limit]
        lag_near = lag if isinstance(lag, float) else lag[near]
        col = sign.copy()
        col[near] -= 2.0 * sign[near] * np.exp(-since[near] / lag_near)
        out.append(col)
        last = lag
    return out


def _loop_settle(g: Geometry, first_rad: float, period_rad: float, axis: int) -> np.ndarray:
    """``sign settle`` of :func:`_loop_steps` (the part of a command step that settles through the loop), its
    start averaged over each sample's aperture: the column whose coefficient is the share of the step that the
    axis' velocity feed-forward passes at once, times the step (:data:`FEED_FORWARD`)."""
    lead, lag = g.loop_angles(axis)
    since, k = _wrap_count(g.d * (g.u - first_rad) + lead, period_rad)
    sign = 1.0 - 2.0 * (k - 2.0 * np.floor(0.5 * k))
    h = _half(g)
    h_max = float(np.max(h)) if np.ndim(h) else float(h)
    # from the switch the settling starts at (the next one for the samples whose aperture reaches it)
    before = since > period_rad - h_max
    x = np.where(before, since - period_rad, since)
    s = np.where(before, -sign, sign)
    lag_f = lag if isinstance(lag, float) else np.asarray(lag)
    near = np.flatnonzero(x <= SPIKE_REACH * (lag_f if np.ndim(lag_f) == 0 else float(np.max(lag_f))) + h_max)
    out = np.zeros(len(g))
    if near.size == 0:
        return out
    hn = np.asarray(h)[near] if np.ndim(h) else h
    lag_n = lag_f if np.ndim(lag_f) == 0 else np.asarray(lag_f)[near]
    xn = x[near]
    if np.ndim(hn) == 0 and hn <= 0:
        val = np.where(xn >= 0.0, np.exp(-np.maximum(xn, 0.0) / lag_n), 0.0)
    else:
        hs = np.maximum(hn, 1e-12)
        lo, hi = np.maximum(xn - hs, 0.0), np.maximum(xn + hs, 0.0)
        val = (lag_n / (2.0 * hs)) * (np.exp(-lo / lag_n) - np.exp(-hi / lag_n))
    if g.travel is not None:  # a switch the command has not passed since the arc began: long settled
        lead_n = lead if np.ndim(lead) == 0 else np.asarray(lead)[near]
        val[xn > g.travel[near] + lead_n] = 0.0
    out[near] = s[near] * val
    return out


def _feed_forward_x(g: Geometry, _w: float) -> np.ndarray:
    if not (g.comp_x and g.loop_lag_s):
        return np.zeros(len(g))
    out = _loop_settle(g, 0.0, math.pi, 0)
    out *= g.cos_u
    return out


def _feed_forward_y(g: Geometry, _w: float) -> np.ndarray:
    if not (g.comp_y and g.loop_lag_s):
        return np.zeros(len(g))
    out = _loop_settle(g, 0.5 * math.pi, math.pi, 1)
    out *= g.sin_u
    return out


def _master_slave(g: Geometry, _w: float) -> Columns:
    # a command-side switch at each 45 deg line (where X and Y trade the master's role), which each axis'
    # loop follows: DX = sigma_X (a + b) / (2 sqrt 2), DY = sigma_Y (a - b) / (2 sqrt 2)
    if not g.loop_lag_s:
        sx = sy = _switch(g, -g.cos_2u, g.u - 0.25 * math.pi, 0.5 * math.pi)
        k: float | np.ndarray = 0.5 / math.sqrt(2.0)
    else:
        # sigma(uc): +1 where X is the faster (master) axis, |sin uc| >= |cos uc| (cos 2uc <= 0), -1 elsewhere;
        # that is d (-1)^k on the k-th quarter turn after 45 deg in the direction of travel
        sx, sy = _loop_steps(g, math.pi / 4, math.pi / 2, (0, 1))
        k = 0.5 / math.sqrt(2.0) * g.dd
    xs, ys = sx * g.cos_u, sy * g.sin_u
    xs *= k
    ys *= k
    return xs + ys, xs - ys  # sigma (sin, cos) of u + 45 deg for equal loops


def _squareness(g: Geometry, _w: float) -> np.ndarray:
    # DX = S Y; S in urad, R in mm: S R sin u cos u * 1e-3 um
    return g.R * 0.5e-3 * g.sin_2u


def _scale(g: Geometry, _w: float) -> np.ndarray:
    # DX = eX X, DY = eY Y; only eX - eY separates from the radius (ppm * mm = 1e-3 um)
    return 0.5e-3 * g.R * g.cos_2u


def _lateral_x(g: Geometry, _w: float) -> np.ndarray:
    # DY = -(lX/2) sgn(vX)
    out = np.abs(g.sin_u)
    out *= 0.5 * g.dd
    return out


def _lateral_y(g: Geometry, _w: float) -> np.ndarray:
    # DX = -(lY/2) sgn(vY)
    out = np.abs(g.cos_u)
    out *= -0.5 * g.dd
    return out


def _straight_x(g: Geometry, _w: float) -> np.ndarray:
    # DY = sX (X/R)^2
    return g.cos_u * g.cos_u * g.sin_u


def _straight_y(g: Geometry, _w: float) -> np.ndarray:
    # DX = sY (Y/R)^2
    return g.sin_u * g.sin_u * g.cos_u


def _cyclic_x(g: Geometry, _w: float) -> Columns:
    # DX = c sin(2 pi X/p + phi) = c cos(phi) sin(.) + c sin(phi) cos(.)
    assert g.pitch_x_mm is not None
    c = g.cos_u
    cos_a, sin_a = cos_sin(2.0 * math.pi * g.R / g.pitch_x_mm * c)
    sin_a *= c
    cos_a *= c
    return sin_a, cos_a


def _cyclic_y(g: Geometry, _w: float) -> Columns:
    assert g.pitch_y_mm is not None
    s = g.sin_u
    cos_a, sin_a = cos_sin(2.0 * math.pi * g.R / g.pitch_y_mm * s)
    sin_a *= s
    cos_a *= s
    return sin_a, cos_a


def _drift(g: Geometry, _w: float) -> np.ndarray:
    return g.t_min


def _half(g: Geometry, idx: np.ndarray | None = None) -> float | np.ndarray:
    """Half the aperture (rad): of every row, or of the rows ``idx`` where it is per row."""
    h = 0.5 * g.aperture_rad
    if np.ndim(h) and idx is not None:
        return np.asarray(h)[idx]
    return h


def _decay(du: np.ndarray, w: float, h: float | np.ndarray, travel: np.ndarray | None) -> np.ndarray:
    """``exp(-du / w)`` from ``du = 0`` on, averaged over each sample's aperture ``2 h`` where there is one."""
    if np.ndim(h) == 0 and h <= 0:
        out = np.exp(-du / w)
    else:
        x = np.where(du > math.pi, du - 2.0 * math.pi, du)  # just before the onset: negative
        lo, hi = np.maximum(x - h, 0.0), np.maximum(x + h, 0.0)
        hs = np.maximum(h, 1e-12 * w)  # an aperture this small against the width is an instant
        out = (w / (2.0 * hs)) * (np.exp(-lo / w) - np.exp(-hi / w))
        if np.ndim(h):
            point = np.asarray(h) <= 1e-12 * w
            if point.any():
                out[point] = np.exp(-du[point] / w)
    if travel is not None:
        out[du > travel] = 0.0
    return out


def _decay_near(
    g: Geometry, du: np.ndarray, w: float, travel: np.ndarray | None, mine: np.ndarray | None = None
) -> np.ndarray:
    """:func:`_decay` where it is not below ``exp(-SPIKE_REACH)`` of its peak (out to ``SPIKE_REACH`` widths
    past the onset, and the aperture's half before it), 0 elsewhere: a spike acts on a few degrees of the
    circle, and the exponential costs most of a column.  ``mine``: the rows of ``g`` that ``du`` holds."""
    h = _half(g, mine)
    near = du <= SPIKE_REACH * w + h
    near |= du > 2.0 * math.pi - h
    idx = np.flatnonzero(near)
    out = np.zeros(du.size)
    if idx.size:
        hi = np.asarray(h)[idx] if np.ndim(h) else h
        out[idx] = _decay(du[idx], w, hi, travel[idx] if travel is not None else None)
    return out


def spike_travel(u: np.ndarray, d: np.ndarray, at_rad: float) -> np.ndarray:
    """Angle travelled (rad, in [0, 2 pi)) since the last pass through ``at_rad``."""
    return wrap(d * (u - at_rad), 2.0 * math.pi)


def _spike_support(at_deg: float, direction: int) -> SupportFn:
    """Where a reversal spike at ``at_deg`` in ``direction`` acts on one circle's rows (the geometry's
    ``direction``), and the angle travelled past its onset there: its phase within ``[start - h, start +
    reach]``."""
    at = math.radians(at_deg)
    axis = 0 if at_deg in (0.0, 180.0) else 1

    def support(g: Geometry, w: float) -> tuple[np.ndarray, np.ndarray] | None:
        if g.direction != direction:
            return None
        # friction acts where the table reverses: the onset moves it off the reversal point.  spike_travel(u, d,
        # onset) = (phase - start) mod 2 pi, from the geometry's travel past 0 (shared by the circle's spikes)
        start = (direction * (at + direction * g.onset_rad[axis])) % (2.0 * math.pi)
        h = _half(g)
        h_max = float(np.max(h)) if np.ndim(h) else float(h)
        lo, hi = start - h_max, start + SPIKE_REACH * w + h_max
        ph = g.phase
        inside = (ph >= lo) & (ph <= hi)
        if lo < 0.0:
            inside |= ph >= lo + 2.0 * math.pi
        if hi >= 2.0 * math.pi:
            inside |= ph <= hi - 2.0 * math.pi
        idx = np.flatnonzero(inside)
        du = ph[idx] - start
        du[du < 0.0] += 2.0 * math.pi
        return idx, du

    return support


def _spike(at_deg: float, direction: int) -> ColumnFn:
    at = math.radians(at_deg)
    axis = 0 if at_deg in (0.0, 180.0) else 1
    support = _spike_support(at_deg, direction)

    def fn(g: Geometry, w: float) -> np.ndarray:
        out = np.zeros(len(g))
        got = support(g, w)
        if got is not None:  # one circle's samples: no selection to copy
            idx, du = got
            if idx.size:
                out[idx] = _decay(du, w, _half(g, idx), g.travel[idx] if g.travel is not None else None)
            return out
        onset = at + direction * g.onset_rad[axis]
        if g.direction == 0:
            mine = g.d == direction
            if mine.any():
                out[mine] = _decay_near(g, spike_travel(g.u[mine], g.d[mine], onset), w,
                                        g.travel[mine] if g.travel is not None else None, np.flatnonzero(mine))
        return out

    return fn


def _spikes() -> list[Pattern]:
    out = []
    for axis, end, at in (("x", "pos", 0.0), ("y", "pos", 90.0), ("x", "neg", 180.0), ("y", "neg", 270.0)):
        for dname, d in (("ccw", 1), ("cw", -1)):
            name = f"reversal_spike_{axis}_{end}_{dname}"
            out.append(Pattern(name, (f"{name}_um",), ("um",), _spike(at, d), "reversal", reversal=(axis, at, d),
                               support=_spike_support(at, d)))
    return out


LIBRARY: tuple[Pattern, ...] = (
    Pattern("centre", ("centre_x_um", "centre_y_um"), ("um", "um"), _centre, "setup"),
    Pattern("radius", ("radius_um",), ("um",), _radius, "setup"),
    Pattern("backlash_x", ("backlash_x_um",), ("um",), _backlash_x),
    Pattern("backlash_y", ("backlash_y_um",), ("um",), _backlash_y),
    Pattern("servo_mismatch", ("servo_mismatch_ms",), ("ms",), _servo),
    Pattern("master_slave", ("master_slave_a_um", "master_slave_b_um"), ("um", "um"), _master_slave),
    Pattern("squareness", ("squareness_urad",), ("urad",), _squareness),
    Pattern("scale_mismatch", ("scale_mismatch_ppm",), ("ppm",), _scale),
    Pattern("lateral_play_x", ("lateral_play_x_um",), ("um",), _lateral_x),
    Pattern("lateral_play_y", ("lateral_play_y_um",), ("um",), _lateral_y),
    Pattern("straightness_x", ("straightness_x_um",), ("um",), _straight_x),
    Pattern("straightness_y", ("straightness_y_um",), ("um",), _straight_y),
    Pattern("cyclic_x", ("cyclic_x_sin_um", "cyclic_x_cos_um"), ("um", "um"), _cyclic_x, needs="pitch_x"),
    Pattern("cyclic_y", ("cyclic_y_sin_um", "cyclic_y_cos_um"), ("um", "um"), _cyclic_y, needs="pitch_y"),
    Pattern("drift", ("drift_um_per_min",), ("um/min",), _drift),
    *_spikes(),
)

BY_NAME: dict[str, Pattern] = {p.name: p for p in LIBRARY}

# Where an axis' lost motion is an over-set compensation (a command step through the loop), the share of the step
# that its velocity feed-forward passes at once: the step's settling part, with the share times the backlash as its
# coefficient.  A property of the loop fitted beside the patterns, not a finding (kind "loop": not ranked or
# tested, not in the result); of the same shape as a reversal spike about as wide as the loop's settling, whose
# spikes are then left out (:mod:`.testfit`).
FEED_FORWARD: tuple[Pattern, ...] = (
    Pattern("feed_forward_x", ("feed_forward_x_um",), ("um",), _feed_forward_x, "loop"),
    Pattern("feed_forward_y", ("feed_forward_y_um",), ("um",), _feed_forward_y, "loop"),
)



# The seed's patterns (Suh & Lee 2000): the paper's Fig. 7 verification uses these.
SEED_PATTERNS: tuple[str, ...] = ("backlash_x", "backlash_y", "master_slave", "servo_mismatch")


def select(
    names: Sequence[str] | None,
    directions: Sequence[int],
    pitch_x_mm: float | None,
    pitch_y_mm: float | None,
) -> list[Pattern]:
    """The patterns to fit: ``names`` (None: all that apply), in library order.

    Cyclic error needs the axis' screw pitch; a reversal spike needs its direction
    in the data.  Unknown names raise ``KeyError`` naming the pattern.
    """
    if names is not None:
        for n in names:
            if n not in BY_NAME:
                raise KeyError(n)
    wanted = set(names) if names is not None else None
    out = []
    for p in LIBRARY:
        if wanted is not None and p.name not in wanted:
            continue
        if p.needs == "pitch_x" and pitch_x_mm is None:
            continue
        if p.needs == "pitch_y" and pitch_y_mm is None:
            continue
        if p.reversal is not None and p.reversal[2] not in directions:
            continue
        out.append(p)
    return out


def design(
    patterns: Sequence[Pattern], g: Geometry, spike_width_rad: float, out: np.ndarray | None = None
) -> np.ndarray:
    """The ``(n, p)`` design matrix of ``patterns`` at ``g`` (into ``out`` where given), stored by columns (each
    pattern makes whole columns: written in place, not across rows; some 15 % of a design at 1 kHz).

    The reversal spikes of one circle's rows are made together: each acts on a few rows, where the exponentials
    of all of them are one call of :func:`_decay` (a spike's own call cost more than its rows)."""
    n = len(g)
    cols = sum(p.q for p in patterns)
    A = np.empty((n, cols), order="F") if out is None else out
    j = 0
    spikes: list[tuple[int, np.ndarray, np.ndarray]] = []
    for p in patterns:
        got = p.support(g, spike_width_rad) if p.support is not None else None
        if got is not None:
            A[:, j] = 0.0
            spikes.append((j, *got))
            j += 1
            continue
        made = p.fn(g, spike_width_rad)
        if isinstance(made, tuple):
            for k, col in enumerate(made):
                A[:, j + k] = col
        elif made.ndim == 1:
            A[:, j] = made
        else:
            A[:, j : j + p.q] = made.reshape(n, p.q)
        j += p.q
    if spikes:
        idx = np.concatenate([i for _, i, _ in spikes])
        if idx.size:
            du = np.concatenate([u for _, _, u in spikes])
            vals = _decay(du, spike_width_rad, _half(g, idx), g.travel[idx] if g.travel is not None else None)
            at = 0
            for k, i, _ in spikes:
                A[i, k] = vals[at : at + i.size]
                at += i.size
    return A
