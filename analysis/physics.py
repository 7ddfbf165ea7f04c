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

Lost motion, per axis one of two physical models; which one is the data's
choice, through the sign of the fitted backlash:

- ``deadband`` (``b > 0``): a dead band between motor and table.  After a
  reversal the table stands still until the motor has crossed the gap ``b``,
  so the radial error does not step from ``-b/2`` to ``+b/2`` but follows
  ``R (1 - cos du) - b/2`` over ``du < acos(1 - b/R)`` (0.57 deg for 5 um at
  100 mm), and the table reverses (friction acts) only then.  Left to the step
  mask, that transition is read as negative reversal spikes.  The take-up is
  this correction; the spikes' onset moves to its end.
- ``compensation`` (``b < 0``): backlash compensation set too high.  At each
  commanded reversal the control adds a step of ``|b|`` to the axis' command
  and the position loop follows it with its time constant, exactly as the
  master-slave step does (:func:`.patterns.through_loop`): the backlash mask
  itself is the filtered step, which starts ``Omega tau`` before the actual
  reversal (the command leads).  Left to the instant step mask, the filtered
  flank is read as a reversal spike of about ``|b|/2 .. |b|/3``.  The table is
  pulled round early, so friction acts from the commanded reversal on, or from
  where the compensation's pull overcomes the path's own motion
  (:func:`onset_angles`).

``step`` is the seed's instant step for either sign (no correction).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .patterns import Geometry, wrap

Offset = Callable[[Geometry], np.ndarray]



def servo_remainder(g: Geometry, m_ms: float, tau_s: float, frame_cos2: float | None = None) -> np.ndarray:
    """Physical first-order servo minus its linear mask (um), in the analyzer's frame.

    The frame carries the feed-in's delay, ``tau_ref = tau_bar + (m/2) frame_cos2``
    with ``frame_cos2 = cos 2u_in`` (None: the mean lag, 0).  Each axis lags it
    by its own phase less the frame's: ``X = R gX cos(u - d dX)``,
    ``Y = R gY sin(u - d dY)``, ``dX = atan(Omega/KX) - Omega tau_ref``.  The
    mask is the first-order part; the rest holds the dynamic shrinkage, the
    apparent scale mismatch of unequal gains and, with a large mismatch, the
    turn of the mask's own ``sin 2u`` by the frame (0.6 um of ``cos 2u``,
    11 ppm of scale, at 43/23 1/s and 1000 mm/min on R 100 mm).
    """
    inv_kx = tau_s + 0.5 * m_ms / 1000.0
    inv_ky = tau_s - 0.5 * m_ms / 1000.0
    if inv_kx <= 0 or inv_ky <= 0:
        return np.zeros(len(g))
    # one timing: scalars; a stack of timings (g.feeds): a column of its blocks' values against their rows
    V: float | np.ndarray = g.V if g.feeds is None else g.feeds[:, None]
    shape = (len(g),) if g.feeds is None else (g.feeds.size, -1)
    cos_2u, sin_2u = g.cos_2u.reshape(shape), g.sin_2u.reshape(shape)
    d = g.dd if isinstance(g.dd, float) else g.d.reshape(shape)
    omega = V / g.R
    gx2 = 1.0 / (1.0 + (omega * inv_kx) ** 2)
    gy2 = 1.0 / (1.0 + (omega * inv_ky) ** 2)
    ref = omega * (tau_s + 0.5 * m_ms / 1000.0 * (frame_cos2 or 0.0))
    dx = np.arctan(omega * inv_kx) - ref
    dy = np.arctan(omega * inv_ky) - ref
    # cx = cos(u - d dx), sy = sin(u - d dy) (d = +-1): gX^2 cx^2 + gY^2 sy^2 is a + b cos 2u + d c sin 2u with
    # a, b, c per timing (cos^2 u = (1 + cos 2u)/2, sin^2 u = (1 - cos 2u)/2, 2 sin u cos u = sin 2u)
    cdx, sdx, cdy, sdy = np.cos(dx), np.sin(dx), np.cos(dy), np.sin(dy)
    at_cos2 = gx2 * cdx**2 + gy2 * sdy**2  # the coefficients of cos^2 u and sin^2 u
    at_sin2 = gx2 * sdx**2 + gy2 * cdy**2
    a, b = 0.5 * (at_cos2 + at_sin2), 0.5 * (at_cos2 - at_sin2)
    c = gx2 * cdx * sdx - gy2 * cdy * sdy
    L_over_R = np.sqrt(a + b * cos_2u + (c * d) * sin_2u)
    # physical - mask: R (L/R - 1) in um less the mask (d V/2) m sin 2u
    out = g.R * 1000.0 * (L_over_R - 1.0) - (0.5 * V * m_ms) * d * sin_2u
    return np.asarray(out).reshape(-1)


AXIS_FIELDS = ("backlash_x_um", "backlash_y_um")
MODELS = ("deadband", "compensation", "step")
MODEL_WORDS = {
    "deadband": "dead band: the table waits after a reversal until the motor has crossed the gap (backlash > 0)",
    "compensation": "backlash compensation set too high: a command step at each commanded reversal, followed "
    "through the position loop (backlash < 0)",
    "step": "instant step at the reversal (the seed's mask)",
}


@dataclass(frozen=True)
class LostMotion:
    """Per axis (X, Y): the lost-motion model and the angle from each reversal point to the table's reversal."""

    models: tuple[str, str] = ("step", "step")
    onset_rad: tuple[float, float] = (0.0, 0.0)  # where friction acts: the table's own reversal
    reversal_rad: tuple[float, float] = (0.0, 0.0)  # where the axis reverses (its loop's lag against the frame)
    loop_rad: tuple[float, float, float] | None = None  # the command's lead, X's and Y's loop lag (:func:`loop_angles`)
    loop_ff: float = 0.0  # the share of a command step the loops pass at once (velocity feed-forward)

    @classmethod
    def choose(
        cls,
        values: Mapping[str, float | None],
        mode: str,
        radius_mm: float,
        loop_rad: tuple[float, float, float] | None = None,
        reversal_rad: tuple[float, float] = (0.0, 0.0),
        loop_ff: float = 0.0,
    ) -> LostMotion:
        """The models the data chose (``mode`` ``physical``: by the sign of each backlash) and onsets.

        ``reversal_rad``: per axis, how far past each reversal point the axis
        itself reverses (:func:`axis_reversals`).
        """
        if mode == "step":
            return cls(onset_rad=reversal_rad, reversal_rad=reversal_rad, loop_rad=loop_rad, loop_ff=loop_ff)
        models = ("compensation" if (values.get(k) or 0.0) < 0 else "deadband" for k in AXIS_FIELDS)
        mx, my = models
        extra = onset_angles(values, radius_mm, (mx, my), loop_rad)
        onset = (reversal_rad[0] + extra[0], reversal_rad[1] + extra[1])
        return cls((mx, my), onset, reversal_rad, loop_rad, loop_ff)

    def geometry(self, loop_lag_s: float | None) -> dict[str, Any]:
        """The :class:`~.patterns.Geometry` fields that carry this model."""
        return {
            "onset_rad": self.onset_rad,
            "reversal_rad": self.reversal_rad,
            "deadband": (self.models[0] == "deadband", self.models[1] == "deadband"),
            "comp_x": self.models[0] == "compensation" and bool(loop_lag_s),
            "comp_y": self.models[1] == "compensation" and bool(loop_lag_s),
            "loop_rad": self.loop_rad if loop_lag_s else None,
        }

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            axis: {"model": m, "onset_deg": math.degrees(o), "reversal_deg": math.degrees(r),
                   "description": MODEL_WORDS[m]}
            for axis, m, o, r in zip(("x", "y"), self.models, self.onset_rad, self.reversal_rad, strict=True)
        }
        if self.loop_rad is not None:
            out["loop_deg"] = {k: math.degrees(v) for k, v in zip(("lead", "x", "y"), self.loop_rad, strict=True)}
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> LostMotion:
        """From :meth:`to_dict` (a result's ``fit.lost_motion``); the instant step where absent."""
        if not isinstance(data, Mapping):
            return cls()
        models, onsets, revs = [], [], []
        for axis in ("x", "y"):
            d = data.get(axis) or {}
            m = d.get("model")
            models.append(m if m in MODELS else "step")
            onsets.append(math.radians(float(d.get("onset_deg") or 0.0)))
            revs.append(math.radians(float(d.get("reversal_deg") or 0.0)))
        loop = data.get("loop_deg")
        loop_rad = None
        if isinstance(loop, Mapping):
            lead, lx, ly = (math.radians(float(loop.get(k) or 0.0)) for k in ("lead", "x", "y"))
            loop_rad = (lead, lx, ly)
        return cls((models[0], models[1]), (onsets[0], onsets[1]), (revs[0], revs[1]), loop_rad)


def mean_lag(tau_s: float | None, radial_cos2: float | None, mismatch_ms: float) -> float | None:
    """The loops' mean lag ``tau_bar`` from a lag measured along a radius (``tau_bar + (m/2) cos 2u``, where
    ``radial_cos2`` is that mean ``cos 2u``; None: ``tau_s`` is the mean already)."""
    if tau_s is None or radial_cos2 is None or not math.isfinite(mismatch_ms):
        return tau_s
    return tau_s - 0.5 * mismatch_ms / 1000.0 * radial_cos2


def loop_angles(
    tau_s: float | None, mismatch_ms: float, omega_rad_s: float, feed_in_deg: float, ff: float = 0.0
) -> tuple[float, float, float] | None:
    """The command's lead over the analyzer's frame and each axis' loop time constant, as angles (rad).

    The frame carries the feed-in's delay, the loops' lag on a ramp along it:
    ``lam_ref = lam_bar + (m/2) cos 2u_in`` (:func:`axis_reversals`), with ``m`` the mismatch the circle
    shows.  With velocity feed-forward passing a share ``ff`` of the command at once, the loops' lag on a
    ramp is ``lam_bar = (1 - ff) tau_bar`` while a step still settles with the time constant ``tau_bar``;
    each axis' is ``tau_bar +- m / (2 (1 - ff))``.  None where the mean lag ``tau_bar`` is not known.
    """
    if not tau_s:
        return None
    m = mismatch_ms / 1000.0 if math.isfinite(mismatch_ms) else 0.0
    c2 = math.cos(2.0 * math.radians(feed_in_deg))
    keep = 1.0 - min(max(ff, 0.0), 1.0)
    m_settle = m / max(keep, 0.1)
    return (
        omega_rad_s * max(keep * tau_s + 0.5 * m * c2, 0.0),
        omega_rad_s * max(tau_s + 0.5 * m_settle, 0.0),
        omega_rad_s * max(tau_s - 0.5 * m_settle, 0.0),
    )


def axis_reversals(mismatch_ms: float, omega_rad_s: float, feed_in_deg: float) -> tuple[float, float]:
    """Per axis, the angle (rad) from a reversal point to where that axis actually reverses.

    The analyzer's angles are timed from the feed-in's centroid, which carries
    the delay of the loops along the feed-in's direction ``u_in``:
    ``tau_ref = tauX cos^2 u_in + tauY sin^2 u_in``.  Each axis reverses
    ``tau_axis - tau_ref`` later: ``Omega (m/2)(1 - cos 2u_in)`` for X and
    ``-Omega (m/2)(1 + cos 2u_in)`` for Y, ``m = 1/KX - 1/KY`` the servo
    mismatch.  Equal gains: no shift.  A few samples at 1 kHz for 30/33 1/s,
    which moves a sharp spike's onset and so its height.
    """
    m = mismatch_ms / 1000.0 if math.isfinite(mismatch_ms) else 0.0
    c2 = math.cos(2.0 * math.radians(feed_in_deg))
    return omega_rad_s * 0.5 * m * (1.0 - c2), -omega_rad_s * 0.5 * m * (1.0 + c2)


def onset_angles(
    values: Mapping[str, float | None],
    radius_mm: float,
    models: tuple[str, str],
    loop_rad: tuple[float, float, float] | None,
) -> tuple[float, float]:
    """Per axis, the angle (rad) from where the axis reverses to where its table does (friction's onset).

    Dead band: ``acos(1 - b/R)`` after it, once the motor has crossed the gap.
    Compensation: the command steps by ``|b|`` at the commanded reversal, the
    command's ``lead`` before the reversal point, and the axis follows with its
    loop lag ``lag``; near it the table's position along the axis is
    ``R cos du + (|b|/2)(2 exp(-(du + lead)/lag) - 1)``, which turns where its
    slope first vanishes: at once where the step's pull ``|b|/lag`` beats the
    path's ``R sin(lead)``, else between ``-lead`` and 0.
    """
    R_um = radius_mm * 1000.0
    out = []
    for axis, (key, model) in enumerate(zip(AXIS_FIELDS, models, strict=True)):
        b = values.get(key) or 0.0
        if model == "deadband" and 0 < b < R_um:
            out.append(math.acos(1.0 - b / R_um))
        elif model == "compensation" and b < 0 and loop_rad is not None and loop_rad[1 + axis] > 0:
            out.append(_compensation_onset(-b, R_um, loop_rad[0], loop_rad[1 + axis]))
        else:
            out.append(0.0)
    return out[0], out[1]


def _compensation_onset(comp_um: float, R_um: float, lead: float, lag: float) -> float:
    def slope(du: float) -> float:
        return -R_um * math.sin(du) - comp_um / lag * math.exp(-(du + lead) / lag)

    lo, hi = -lead, 0.0
    if slope(lo) <= 0:
        return lo
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if slope(mid) > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def lost_motion_remainder(g: Geometry) -> np.ndarray:
    """The dead band's take-up bump after each reversal (um), for the axes whose model is ``deadband``.

    Per unit backlash the dead band's mask holds ``-1/2`` until the table moves
    again, ``acos(1 - b/R)`` after the axis reversed, then ``+1/2``
    (:mod:`.patterns`: the step sits at ``onset_rad``); in between the table
    stands while the path turns away from it, ``R (1 - cos e)`` radially at
    ``e`` past the axis' reversal.  That bump is this correction: with the
    take-up's width fixed it does not depend on ``b``, so the fit of ``b``
    stays linear and a stale estimate cannot leave a misfit along the take-up.
    """
    out = np.zeros(len(g))
    R_um = g.R * 1000.0
    h = 0.5 * g.aperture_rad
    for axis in (0, 1):
        if not g.deadband[axis]:
            continue
        shift = g.reversal_rad[axis]
        width = g.onset_rad[axis] - shift
        if width <= 0:
            continue
        # signed travel from the nearest of the axis' two reversal points (X: 0, 180 deg; Y: 90, 270 deg)
        du = wrap(g.d * (g.u - 0.5 * math.pi * axis) + 0.5 * math.pi, math.pi) - 0.5 * math.pi
        e = du - shift  # travel since the axis reversed
        near = np.flatnonzero((e > -h) & (e < width + h))
        if g.travel is not None:
            near = near[du[near] <= g.travel[near]]
        if near.size == 0:
            continue
        en = e[near]
        bump = R_um * (1.0 - np.cos(np.clip(en, 0.0, width)))
        hn = np.asarray(h)[near] if np.ndim(h) else h
        if np.ndim(hn) or hn > 0:  # the bump ends where the mask steps: averaged over the same aperture
            # (patterns._switch); an aperture of 0 in a row is a point
            hs = np.maximum(hn, 1e-300)
            bump *= np.clip((width - en + hs) / (2.0 * hs), 0.0, 1.0)
            if np.ndim(hn):
                bump[(hn <= 0) & ((en < 0) | (en >= width))] = 0.0
        else:
            bump[(en < 0) | (en >= width)] = 0.0
        out[near] += bump * np.cos(du[near])
    return out


def servo_point(g: Geometry, m_ms: float, tau_s: float | None, frame_cos2: float | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """The spindle's position (um, from the programmed centre) in the analyzer's frame: on the circle of the
    first-order loops (:func:`servo_remainder`), ``X = R gX cos(u - d dX)``, ``Y = R gY sin(u - d dY)``; the
    commanded circle where the loops' lag is not known."""
    R_um = g.R * 1000.0
    inv_kx = (tau_s or 0.0) + 0.5 * m_ms / 1000.0
    inv_ky = (tau_s or 0.0) - 0.5 * m_ms / 1000.0
    if tau_s is None or inv_kx <= 0 or inv_ky <= 0:
        return R_um * g.cos_u, R_um * g.sin_u
    omega = g.V / g.R
    ref = omega * (tau_s + 0.5 * m_ms / 1000.0 * (frame_cos2 or 0.0))
    dx = math.atan(omega * inv_kx) - ref
    dy = math.atan(omega * inv_ky) - ref
    gx = 1.0 / math.sqrt(1.0 + (omega * inv_kx) ** 2)
    gy = 1.0 / math.sqrt(1.0 + (omega * inv_ky) ** 2)
    d = g.dd
    # cos(u - d dx) = cos u cos dx + d sin u sin dx, sin(u - d dy) = sin u cos dy - d cos u sin dy (d = +-1)
    X = (R_um * gx) * (g.cos_u * math.cos(dx) + d * (g.sin_u * math.sin(dx)))
    Y = (R_um * gy) * (g.sin_u * math.cos(dy) - d * (g.cos_u * math.sin(dy)))
    return np.asarray(X), np.asarray(Y)


def error_vector(g: Geometry, values: Mapping[str, float | None]) -> tuple[np.ndarray, np.ndarray] | None:
    """The machine's and the set-up's displacement ``D = (DX, DY)`` (um) of the patterns whose physical model
    is a vector (analysis/README.md, "The pattern library"), at the fitted ``values``; None where all are 0.

    The masks are its radial component ``D . e_u``; the bar's exact length also holds the rest
    (:func:`second_order`)."""
    v = {k: float(values.get(k) or 0.0) for k in (
        "centre_x_um", "centre_y_um", "squareness_urad", "scale_mismatch_ppm", "backlash_x_um", "backlash_y_um",
        "lateral_play_x_um", "lateral_play_y_um", "straightness_x_um", "straightness_y_um")}
    if not any(v.values()):
        return None
    c, s = g.cos_u, g.sin_u
    R = g.R
    d = g.dd
    DX = np.full(len(g), v["centre_x_um"])
    DY = np.full(len(g), v["centre_y_um"])
    if v["squareness_urad"]:  # DX = S Y: urad x mm = 1e-3 um
        DX += (1e-3 * v["squareness_urad"] * R) * s
    if v["scale_mismatch_ppm"]:  # DX = eX X, DY = eY Y with eX - eY = e, split evenly: ppm x mm = 1e-3 um
        half = 0.5e-3 * v["scale_mismatch_ppm"] * R
        DX += half * c
        DY -= half * s
    if v["backlash_x_um"] or v["lateral_play_x_um"]:  # sgn(vX) = -d sgn(sin u)
        sx = d * np.sign(s)
        DX += (0.5 * v["backlash_x_um"]) * sx
        DY += (0.5 * v["lateral_play_x_um"]) * sx
    if v["backlash_y_um"] or v["lateral_play_y_um"]:  # sgn(vY) = d sgn(cos u)
        sy = d * np.sign(c)
        DY -= (0.5 * v["backlash_y_um"]) * sy
        DX -= (0.5 * v["lateral_play_y_um"]) * sy
    if v["straightness_x_um"]:
        DY += v["straightness_x_um"] * c * c
    if v["straightness_y_um"]:
        DX += v["straightness_y_um"] * s * s
    return DX, DY


def second_order(P: tuple[np.ndarray, np.ndarray], D: tuple[np.ndarray, np.ndarray], g: Geometry) -> np.ndarray:
    """The bar's exact length beyond the masks (um): ``|P + D| - |P| - D . e_u``, with ``P`` the spindle's
    position (:func:`servo_point`) and ``D`` the displacement (:func:`error_vector`).

    The masks keep the first order in ``D`` about the commanded circle.  What they leave is the tangential
    part of ``D`` squared over ``2R`` and, above all, its cross terms with the loops' unequal lags: with the
    pivot ``c`` off centre and a servo mismatch ``m`` the actual path turns away from the frame's angle by
    about ``Omega (m/2) cos 2u``, which moves the bar by ``c_t`` times that, a term whose sign flips with the
    direction: left out it reads as drift and lateral play (0.28 um/min of drift on a noise-free 28 s test,
    R 50 mm, F 3000 mm/min, 7 um off centre, 25/28 1/s).
    """
    X, Y = P
    DX, DY = D
    return np.asarray(np.hypot(X + DX, Y + DY) - np.hypot(X, Y) - (DX * g.cos_u + DY * g.sin_u))


def make_offset(
    values: Mapping[str, float | None],
    tau_s: float | None,
    lost_motion: LostMotion | None = None,
    radial_cos2: float | None = None,
    frame_cos2: float | None = None,
) -> Offset | None:
    """The correction for the current estimates, or None when there is nothing to correct.

    ``tau_s`` None: no servo correction.  ``lost_motion``: the dead-band take-up
    of the axes whose model is ``deadband`` (its width travels in the
    geometry; the compensation step is in the mask itself); None: none.
    ``radial_cos2``: ``tau_s`` was measured along a radius at angles whose mean
    ``cos 2u`` this is, where the lag is ``tau_bar + (m/2) cos 2u``.
    ``frame_cos2``: ``cos 2u`` of the feed-in, whose delay the analyzer's angles
    carry (:func:`servo_remainder`); None: the mean lag's frame.  The bar's
    exact length beyond the masks (:func:`second_order`) at ``values`` is part of it.
    """
    m = values.get("servo_mismatch_ms") or 0.0
    tau_s = mean_lag(tau_s, radial_cos2, m)
    models = lost_motion.models if lost_motion is not None else ("step", "step")
    use_servo = tau_s is not None and math.isfinite(tau_s) and tau_s > 0 and math.isfinite(m)
    vector = any(values.get(k) for k in _VECTOR_FIELDS)
    if not use_servo and "deadband" not in models and not vector:
        return None

    def offset(g: Geometry) -> np.ndarray:
        out = lost_motion_remainder(g)
        if use_servo:
            assert tau_s is not None
            out += servo_remainder(g, m, tau_s, frame_cos2)
        D = error_vector(g, values) if vector else None
        if D is not None:
            out += second_order(servo_point(g, m, tau_s if use_servo else None, frame_cos2), D, g)
        return out

    return offset


_VECTOR_FIELDS = ("centre_x_um", "centre_y_um", "squareness_urad", "scale_mismatch_ppm", "backlash_x_um",
                  "backlash_y_um", "lateral_play_x_um", "lateral_play_y_um", "straightness_x_um", "straightness_y_um")

