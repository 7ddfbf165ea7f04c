"""Scene geometry of the live view: each sample's angle from the test program's timing, the fitted model
rebuilt from a result, and the polar plot's display coordinates and scale.

The polar plot.  A deviation ``dR`` (um) is drawn at radius ``R0 + dR * DIVISION * R0 / s`` with
``R0 = 100`` display units and ``s`` the division (um): each division takes ``DIVISION`` of the
nominal radius, and the scale is chosen (:func:`~ballbar.analysis.report.polar_division_um`, as in the
report) so that every point lies within ``POLAR_DIVISIONS`` divisions: inside the outermost ring.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ballbar.analysis.patterns import LIBRARY, Geometry, Pattern, design
from ballbar.analysis.physics import LostMotion, make_offset
from ballbar.analysis.plan import MachineConfig, TestPlan
from ballbar.analysis.plans import plan_of_result
from ballbar.analysis.program import arc_start_deg, data_start_deg, schedule
from ballbar.analysis.report import POLAR_DIVISIONS, polar_division_um

FloatArray = NDArray[np.float64]

R0 = 100.0  # display radius of the nominal circle (arbitrary units of the 2D view)
DIVISION = 0.2  # share of R0 one division of the scale takes: the outermost ring (3 divisions) at 0.4 and 1.6 R0
DIRECTIONS: dict[int, str] = {1: "ccw", -1: "cw"}
# On the viewer's dark background: the measured curves saturated and wide, the model thin and pale (a dark model
# line could not be told from the background nor from the measured curve)
COLOURS: dict[str, tuple[int, int, int]] = {
    "ccw": (40, 120, 255),
    "ccw_model": (190, 215, 255),
    "cw": (245, 95, 40),
    "cw_model": (255, 215, 185),
    "nominal": (175, 175, 175),
    "band": (60, 170, 60),
    "scale": (110, 110, 110),
    "axes": (95, 95, 95),
}
#: Verdict colours (as the report's): fail red, warning amber, pass green, no limits grey.
STATUS_RGB: dict[str, tuple[int, int, int]] = {
    "fail": (200, 40, 30), "warning": (215, 130, 20), "pass": (35, 140, 75), "none": (95, 100, 112),
}
_PLAN_KEYS = frozenset(TestPlan.__dataclass_fields__)


def plan_from(d: Mapping[str, Any]) -> TestPlan:
    """A result's or a configuration's plan: its plan keys (a result names its plan and its axes besides)."""
    return TestPlan.from_dict({k: v for k, v in d.items() if k in _PLAN_KEYS})


def num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def param(result: Mapping[str, Any], field: str) -> float | None:
    p = result.get("parameters", {}).get(field)
    return num(p.get("value")) if isinstance(p, Mapping) else None


@dataclass(frozen=True)
class ArcTiming:
    """The timing of one direction's data arc, on the analysis clock.

    A sample at ``t`` in ``[start_s, end_s]`` is at angle
    ``u = u_ds + d V (t - start_s) / R`` (analysis/README.md, "The angle of each sample").
    """

    direction: int
    feed_in_s: float
    feed_mm_s: float
    start_s: float
    end_s: float
    spike_width_deg: float
    loop_lag_s: float | None = None

    def angle_rad(self, plan: TestPlan, t: FloatArray) -> FloatArray:
        u_ds = math.radians(data_start_deg(plan, self.direction))
        return np.asarray(u_ds + self.direction * self.feed_mm_s * (t - self.start_s) / plan.radius_mm)


def provisional_timing(
    plan: TestPlan, direction: int, feed_in_s: float, feed_ratio: float, overhead_s: float, spike_width_deg: float
) -> ArcTiming:
    """The engine's provisional timing of a test that began (feed-in centroid) at ``feed_in_s``."""
    V = plan.feed_mm_s * feed_ratio
    sched = schedule(plan, V, overhead_s)
    return ArcTiming(
        direction,
        feed_in_s,
        V,
        feed_in_s + sched.data_start_s[direction],
        feed_in_s + sched.data_end_s[direction],
        spike_width_deg,
    )


def result_timing(result: Mapping[str, Any], direction: int) -> ArcTiming | None:
    """A circle or test result's timing of ``direction``'s data arc (None: not in it)."""
    tm = result.get("timing") or {}
    name = DIRECTIONS[direction]
    t_ref = num(tm.get("feed_in_s"))
    w = num(tm.get("spike_width_deg")) or 3.0
    if result.get("kind") == "circle":
        feed, start, end = (num(tm.get(k)) for k in ("assumed_feed_mm_min", "data_start_s", "data_end_s"))
        if result.get("direction") != name or None in (t_ref, feed, start, end):
            return None
        assert t_ref is not None and feed is not None and start is not None and end is not None
        return ArcTiming(direction, t_ref, feed / 60.0, start, end, w)
    arc = (tm.get("data_arcs") or {}).get(name) or {}
    feed, start, end = num(tm.get("measured_feed_mm_min")), num(arc.get("start_s")), num(arc.get("end_s"))
    if None in (t_ref, feed, start, end):
        return None
    assert t_ref is not None and feed is not None and start is not None and end is not None
    lag_ms = num(tm.get("loop_lag_ms"))
    return ArcTiming(direction, t_ref, feed / 60.0, start, end, w, lag_ms / 1000.0 if lag_ms is not None else None)


def _patterns_for(plan: TestPlan, machine: MachineConfig, direction: int) -> list[Pattern]:
    out = []
    for p in LIBRARY:
        if p.needs == "pitch_x" and machine.pitch_x_mm is None:
            continue
        if p.needs == "pitch_y" and machine.pitch_y_mm is None:
            continue
        if p.reversal is not None and p.reversal[2] != direction:
            continue
        out.append(p)
    return out


def _coefficients(result: Mapping[str, Any], patterns: Sequence[Pattern]) -> FloatArray:
    """The fitted parameters in the patterns' column order; not fitted: 0.

    Cyclic errors are reported as amplitude and phase; their columns are
    ``(c cos phi, c sin phi)`` (:mod:`ballbar.analysis.report`).
    """
    x: list[float] = []
    for p in patterns:
        if p.name.startswith("cyclic_"):
            amp = param(result, f"{p.name}_um") or 0.0
            phase = math.radians(param(result, f"{p.name}_phase_deg") or 0.0)
            x += [amp * math.cos(phase), amp * math.sin(phase)]
        else:
            x += [param(result, f) or 0.0 for f in p.fields]
    return np.asarray(x, dtype=float)


def _radial_cos2(plan: TestPlan, machine: MachineConfig, source: str) -> float | None:
    """Mean ``cos 2u`` of the radii along which the loop lag was measured (engine ``loop_lag``).

    The result does not say which of feed-in and feed-out resolved the lag:
    both are assumed (the usual case).
    """
    if (machine.kv_x_per_s and machine.kv_y_per_s) or not source.startswith("approach"):
        return None
    dirs = plan.direction_list
    u_in = math.radians(arc_start_deg(plan, dirs[0]))
    u_out = math.radians(arc_start_deg(plan, dirs[-1])) + dirs[-1] * math.radians(plan.arc_deg)
    return 0.5 * (math.cos(2 * u_in) + math.cos(2 * u_out))


def model_deviation_um(result: Mapping[str, Any], direction: int, u: FloatArray) -> FloatArray | None:
    """The fitted model's radial deviation (um) at angles ``u`` (rad) of ``direction``'s data arc.

    Rebuilt from the result's parameters with the pattern library, the
    result's timing (feed, spike width, loop lag) and, for a test result, the
    physical corrections the fit applied (servo remainder, each axis'
    lost-motion model with its reversal and friction onsets, and the loops'
    angles, all from ``fit.lost_motion``, :mod:`ballbar.analysis.physics`).
    ``u`` must lie within the data arc (``data_start_deg`` onwards in the
    direction of travel).  None when the result lacks what is needed.
    """
    timing = result_timing(result, direction)
    if timing is None or "plan" not in result:
        return None
    plan = plan_of_result(result["plan"])
    machine = MachineConfig.from_dict(dict(result.get("machine") or {}))
    patterns = _patterns_for(plan, machine, direction)
    u = np.asarray(u, dtype=float)
    d = float(direction)
    u_ds = math.radians(data_start_deg(plan, direction))
    test = result.get("kind") == "test"
    lost = LostMotion.from_dict((result.get("fit") or {}).get("lost_motion")) if test else LostMotion()
    values = {f: param(result, f) for f in ("servo_mismatch_ms", "backlash_x_um", "backlash_y_um")}
    t_rel = (timing.start_s - timing.feed_in_s) + d * (u - u_ds) * plan.radius_mm / timing.feed_mm_s
    g = Geometry(
        u=u,
        d=np.full(u.size, d),
        t_min=t_rel / 60.0,
        V=timing.feed_mm_s,
        R=plan.radius_mm,
        pitch_x_mm=machine.pitch_x_mm,
        pitch_y_mm=machine.pitch_y_mm,
        travel=d * (u - math.radians(arc_start_deg(plan, direction))),
        loop_lag_s=timing.loop_lag_s,
        **lost.geometry(timing.loop_lag_s),
    )
    dr = design(patterns, g, math.radians(timing.spike_width_deg)) @ _coefficients(result, patterns)
    if test:
        tm = result.get("timing") or {}
        cos2 = num(tm["loop_lag_radial_cos2u"]) if "loop_lag_radial_cos2u" in tm else _radial_cos2(
            plan, machine, str(tm.get("loop_lag_source", "")))
        frame_cos2 = math.cos(2.0 * math.radians(arc_start_deg(plan, plan.direction_list[0])))
        offset = make_offset(values, timing.loop_lag_s, lost, cos2, frame_cos2)
        if offset is not None:
            dr = dr + offset(g)
    return np.asarray(dr, dtype=float)


def setup_deviation_um(result: Mapping[str, Any] | None, u: FloatArray) -> FloatArray:
    """The set-up terms (pivot offset and bar length) of ``result`` at angles ``u``; 0 without."""
    if result is None:
        return np.zeros_like(u)
    x0, y0, c = (param(result, f) or 0.0 for f in ("centre_x_um", "centre_y_um", "radius_um"))
    return np.asarray(x0 * np.cos(u) + y0 * np.sin(u) + c)


def polar_points(u: FloatArray, dr_um: FloatArray, scale_um: float) -> FloatArray:
    """``(n, 2)`` display points of deviations ``dr_um`` at angles ``u`` (rad), one division ``scale_um``.

    Rerun's 2D views put +y down (image convention): the second coordinate is
    ``-r sin u`` so that the plane's second axis points up and CCW looks CCW.
    """
    r = np.maximum(R0 + (DIVISION * R0 / scale_um) * dr_um, 0.0)
    return np.column_stack([r * np.cos(u), -r * np.sin(u)])


def nice_scale_um(max_abs_um: float) -> float:
    """The automatic division for deviations up to ``max_abs_um``: 1, 2 or 5 x 10^n um, so that they lie within
    ``POLAR_DIVISIONS`` divisions (the report's rule), at least 1 um."""
    return max(polar_division_um(max_abs_um), 1.0)


def circle(radius: float, n: int = 721) -> FloatArray:
    a = np.linspace(0.0, 2.0 * math.pi, n)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a)])


def ring_radius(k: int) -> float:
    """The display radius of the ring ``k`` divisions out (negative: in)."""
    return R0 * (1.0 + DIVISION * k)


__all__ = [
    "COLOURS",
    "DIRECTIONS",
    "POLAR_DIVISIONS",
    "R0",
    "STATUS_RGB",
    "ArcTiming",
    "circle",
    "model_deviation_um",
    "nice_scale_um",
    "plan_from",
    "polar_points",
    "provisional_timing",
    "result_timing",
    "ring_radius",
    "setup_deviation_um",
]
