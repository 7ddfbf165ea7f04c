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

import numpy as np

UM_PER_MM = 1000.0


@dataclass(frozen=True)
class Geometry:
    """Per-sample inputs of the masks.

    ``u``: commanded angle (rad); ``d``: direction (+1/-1); ``t_min``: minutes
    from the test's feed-in; ``V``: path feed (mm/s); ``R``: radius (mm);
    ``pitch``: ball-screw pitch per axis (mm) or None; ``travel``: angle (rad)
    travelled since the arc began, so that a reversal the arc never passed has
    no spike; ``loop_lag_s``: the position loops' mean lag, where known, through
    which a step made in the command (master-slave changeover) reaches the axes.
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
    takeup_rad: tuple[float, float] = (0.0, 0.0)  # X, Y: angle after a reversal until the table moves

    def __len__(self) -> int:
        return int(self.u.size)


ColumnFn = Callable[[Geometry, float], np.ndarray]


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

    @property
    def q(self) -> int:
        return len(self.fields)

    def columns(self, g: Geometry, spike_width_rad: float) -> np.ndarray:
        cols = self.fn(g, spike_width_rad)
        return cols.reshape(len(g), self.q)


def _sigma(u: np.ndarray) -> np.ndarray:
    """+1 where X is the faster (master) axis, |sin u| >= |cos u|; -1 elsewhere."""
    return np.where(np.abs(np.sin(u)) >= np.abs(np.cos(u)), 1.0, -1.0)


def _centre(g: Geometry, _w: float) -> np.ndarray:
    return np.column_stack([np.cos(g.u), np.sin(g.u)])


def _radius(g: Geometry, _w: float) -> np.ndarray:
    return np.ones((len(g), 1))


def _backlash_x(g: Geometry, _w: float) -> np.ndarray:
    # DX = -(bX/2) sgn(vX), vX = -d V sin u
    return 0.5 * g.d * np.sign(np.sin(g.u)) * np.cos(g.u)


def _backlash_y(g: Geometry, _w: float) -> np.ndarray:
    # DY = -(bY/2) sgn(vY), vY = d V cos u
    return -0.5 * g.d * np.sign(np.cos(g.u)) * np.sin(g.u)


def _servo(g: Geometry, _w: float) -> np.ndarray:
    # DX = -vX/KX, DY = -vY/KY; m = 1/KX - 1/KY in ms; V [mm/s] * m [ms] = um
    return 0.5 * g.d * g.V * np.sin(2.0 * g.u)


def _sigma_through_loop(g: Geometry) -> np.ndarray:
    """sigma as the axes see it: a command-side switch through a first-order loop.

    In the frame of the actual position (the analyzer's), the command is
    ``Omega tau`` ahead; after it crosses a 45 deg line, sigma approaches its new
    value as ``1 - 2 exp(-delta / (Omega tau))`` with ``delta`` the command's
    angle travelled since the crossing.
    """
    assert g.loop_lag_s is not None
    lag = g.V / g.R * g.loop_lag_s  # rad
    uc = g.u + g.d * lag
    q = math.pi / 2
    since = np.where(g.d > 0, np.mod(uc - math.pi / 4, q), np.mod(math.pi / 4 - uc, q))
    settle = np.exp(-since / lag)
    if g.travel is not None:
        settle[since > g.travel + lag] = 0.0
    return _sigma(uc) * (1.0 - 2.0 * settle)


def _master_slave(g: Geometry, _w: float) -> np.ndarray:
    sig = _sigma(g.u) if not g.loop_lag_s else _sigma_through_loop(g)
    s = 0.5 * sig
    return np.column_stack([s * np.sin(g.u + math.pi / 4), s * np.cos(g.u + math.pi / 4)])


def _squareness(g: Geometry, _w: float) -> np.ndarray:
    # DX = S Y; S in urad, R in mm: S R sin u cos u * 1e-3 um
    return g.R * 1e-3 * np.sin(g.u) * np.cos(g.u)


def _scale(g: Geometry, _w: float) -> np.ndarray:
    # DX = eX X, DY = eY Y; only eX - eY separates from the radius (ppm * mm = 1e-3 um)
    return 0.5 * g.R * 1e-3 * np.cos(2.0 * g.u)


def _lateral_x(g: Geometry, _w: float) -> np.ndarray:
    # DY = -(lX/2) sgn(vX)
    return 0.5 * g.d * np.abs(np.sin(g.u))


def _lateral_y(g: Geometry, _w: float) -> np.ndarray:
    # DX = -(lY/2) sgn(vY)
    return -0.5 * g.d * np.abs(np.cos(g.u))


def _straight_x(g: Geometry, _w: float) -> np.ndarray:
    # DY = sX (X/R)^2
    return np.cos(g.u) ** 2 * np.sin(g.u)


def _straight_y(g: Geometry, _w: float) -> np.ndarray:
    # DX = sY (Y/R)^2
    return np.sin(g.u) ** 2 * np.cos(g.u)


def _cyclic_x(g: Geometry, _w: float) -> np.ndarray:
    # DX = c sin(2 pi X/p + phi) = c cos(phi) sin(.) + c sin(phi) cos(.)
    assert g.pitch_x_mm is not None
    arg = 2.0 * math.pi * g.R * np.cos(g.u) / g.pitch_x_mm
    c = np.cos(g.u)
    return np.column_stack([np.sin(arg) * c, np.cos(arg) * c])


def _cyclic_y(g: Geometry, _w: float) -> np.ndarray:
    assert g.pitch_y_mm is not None
    arg = 2.0 * math.pi * g.R * np.sin(g.u) / g.pitch_y_mm
    s = np.sin(g.u)
    return np.column_stack([np.sin(arg) * s, np.cos(arg) * s])


def _drift(g: Geometry, _w: float) -> np.ndarray:
    return g.t_min.astype(float, copy=True)


def spike_travel(u: np.ndarray, d: np.ndarray, at_rad: float) -> np.ndarray:
    """Angle travelled (rad, in [0, 2 pi)) since the last pass through ``at_rad``."""
    return np.mod(d * (u - at_rad), 2.0 * math.pi)


def _spike(at_deg: float, direction: int) -> ColumnFn:
    at = math.radians(at_deg)

    axis = 0 if at_deg in (0.0, 180.0) else 1

    def fn(g: Geometry, w: float) -> np.ndarray:
        out = np.zeros(len(g))
        mine = g.d == direction
        if mine.any():
            du = spike_travel(g.u[mine], g.d[mine], at)
            late = du - g.takeup_rad[axis]  # the table reverses once the dead band is taken up
            spike = np.where(late >= 0, np.exp(-np.maximum(late, 0.0) / w), 0.0)
            if g.travel is not None:
                spike[du > g.travel[mine]] = 0.0
            out[mine] = spike
        return out

    return fn


def _spikes() -> list[Pattern]:
    out = []
    for axis, end, at in (("x", "pos", 0.0), ("y", "pos", 90.0), ("x", "neg", 180.0), ("y", "neg", 270.0)):
        for dname, d in (("ccw", 1), ("cw", -1)):
            name = f"reversal_spike_{axis}_{end}_{dname}"
            out.append(Pattern(name, (f"{name}_um",), ("um",), _spike(at, d), "reversal", reversal=(axis, at, d)))
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


def design(patterns: Sequence[Pattern], g: Geometry, spike_width_rad: float) -> np.ndarray:
    """The ``(n, p)`` design matrix of ``patterns`` at ``g``."""
    n = len(g)
    cols = sum(p.q for p in patterns)
    A = np.empty((n, cols))
    j = 0
    for p in patterns:
        A[:, j : j + p.q] = p.columns(g, spike_width_rad)
        j += p.q
    return A
