"""Parameter adjustment advice (analysis/README.md, "Advice").

For each significant pattern: what to change, by how much, with sign and unit,
and the parameter's name on common controllers where it is well known.  The
names are pointers for the engineer, not a promise that the value can be typed
in as it is: units and conventions differ between controller generations
(FANUC in detection units, SINUMERIK machine data in mm, HEIDENHAIN in mm or
um depending on the TNC), so every item also states the value in um or um/m.

Sign conventions: a positive ``backlash_x_um`` is lost motion the compensation
must add; ``servo_mismatch_ms = 1/KX - 1/KY`` positive means X lags more (its
gain is lower); ``squareness_urad`` positive means X tilted toward +Y, and the
compensation is its opposite, in um/m.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any, cast

from .numbers import decimals, fixed
from .patterns import LIBRARY
from .plan import MachineConfig, TestPlan, plane_keys

if TYPE_CHECKING:
    from ballbar.protocol.messages.results import Advice

CONTROLLER_PARAMS: dict[str, dict[str, str]] = {
    "fanuc": {
        "backlash": "No.1851 (backlash compensation, detection units)",
        "gain": "No.1825 (servo loop gain, 0.01/s)",
        "reversal": "No.2048/2071 (backlash acceleration)",
        "squareness": "straightness/inclination compensation (No.13381 ff.)",
        "scale": "pitch error compensation (No.3620 ff.)",
    },
    "siemens": {
        "backlash": "MD32450 $MA_BACKLASH (mm)",
        "gain": "MD32200 $MA_POSCTRL_GAIN (1000/min)",
        "reversal": "MD32500 $MA_FRICT_COMP_ENABLE / quadrant error compensation (QEC)",
        "squareness": "sag/angularity compensation (CEC, $AN_CEC)",
        "scale": "leadscrew error compensation (LEC, $AA_ENC_COMP)",
    },
    "heidenhain": {
        "backlash": "MP710.x / CfgAxisBacklash (backlash)",
        "gain": "MP1810.x / kvFactor (kv factor)",
        "reversal": "MP1511.x / friction compensation (reversal spikes)",
        "squareness": "axis angle compensation (CfgAxisGeometry)",
        "scale": "nonlinear axis error compensation (MP730.x)",
    },
}


def _value(params: Mapping[str, Any], key: str) -> float | None:
    p = params.get(key)
    if not p or p.get("value") is None or not p.get("significant"):
        return None
    return float(p["value"])


def _se(params: Mapping[str, Any], key: str) -> float | None:
    p = params.get(key) or {}
    se = p.get("stderr")
    return float(se) if isinstance(se, int | float) and se == se and abs(se) != float("inf") else None


def _n(params: Mapping[str, Any], key: str, v: float, unit: str, signed: bool = False) -> str:
    """``v`` (a value of ``key`` or derived from it in ``unit``) at the place the one rule gives ``key``
    (:mod:`ballbar.analysis.numbers`): the advice says its amounts as the findings do."""
    p = params.get(key) or {}
    nd = decimals(v, _se(params, key), str(p.get("unit") or unit or key.rsplit("_", 1)[-1]))
    return fixed(v, nd, signed)


def _name(machine: MachineConfig, what: str) -> str | None:
    return CONTROLLER_PARAMS.get(machine.controller, {}).get(what)


def advise(params: Mapping[str, Any], plan: TestPlan, machine: MachineConfig) -> list[Advice]:
    """Suggested adjustments for the significant patterns, largest effect first (``params``: a result's
    :class:`~ballbar.protocol.messages.results.Parameters`, looked up by name)."""
    ax1, ax2 = plan.axes
    out: list[Advice] = []

    def n(key: str, v: float, signed: bool = False) -> str:
        return _n(params, key, v, "", signed)

    def add(pattern: str, kind: str, text: str, value: float | None, unit: str, what: str | None = None) -> None:
        item: Advice = {"pattern": pattern, "kind": kind, "action": text, "value": value, "unit": unit}
        cp = _name(machine, what) if what else None
        if cp:
            item["controller_parameter"] = cp
        out.append(item)

    for axis, key in ((ax1, "backlash_x_um"), (ax2, "backlash_y_um")):
        b = _value(params, key)
        if b is not None:
            verb = "increase" if b > 0 else "decrease"
            add(key, "machine", f"{verb} the {axis} backlash compensation by {n(key, abs(b))} um", b, "um", "backlash")
    m = _value(params, "servo_mismatch_ms")
    if m is not None:
        slow, fast = (ax1, ax2) if m > 0 else (ax2, ax1)
        kx, ky = machine.kv_x_per_s, machine.kv_y_per_s
        if kx and ky:
            # match the slower axis to the faster: 1/K_new = 1/K_old - |m|
            k_old = kx if m > 0 else ky
            k_new = 1.0 / (1.0 / k_old - abs(m) / 1000.0)
            se = _se(params, "servo_mismatch_ms")
            nd = decimals(k_new, None if se is None else k_new**2 * se / 1000.0, "1/s")  # d(1/K) = dm
            add("servo_mismatch_ms", "machine",
                f"raise the {slow} position-loop gain from {fixed(k_old, nd)} to {fixed(k_new, nd)} 1/s to match "
                f"{fast}",
                k_new - k_old, "1/s", "gain")
        else:
            add("servo_mismatch_ms", "machine",
                f"{slow} lags {fast} by {n('servo_mismatch_ms', abs(m))} ms: raise the {slow} position-loop gain "
                f"(Kv) or lower the {fast} one until the lags match (configure [machine] "
                f"{plane_keys('kv', plan.plane)} for a value)", m, "ms", "gain")
    s = _value(params, "squareness_urad")
    if s is not None:
        add("squareness_urad", "machine",
            f"compensate the {ax1}/{ax2} squareness by {n('squareness_urad', -s, True)} um/m "
            f"({ax1} leans toward {'+' if s > 0 else '-'}{ax2} by {n('squareness_urad', abs(s))} urad)",
            -s, "um/m", "squareness")
    e = _value(params, "scale_mismatch_ppm")
    if e is not None:
        add("scale_mismatch_ppm", "machine",
            f"{ax1} scales {n('scale_mismatch_ppm', e, True)} ppm relative to {ax2}: correct the "
            f"linear (pitch) compensation of one axis by {n('scale_mismatch_ppm', -e, True)} um/m; a laser "
            "measurement tells which axis", -e, "um/m", "scale")
    for axis, key in ((ax1, "lateral_play_x_um"), (ax2, "lateral_play_y_um")):
        v = _value(params, key)
        if v is not None:
            add(key, "machine", f"{axis} reversal shifts the other axis by {n(key, v)} um: check the {axis} "
                "guideway gibs and preload (mechanical, no parameter)", v, "um")
    a, b = _value(params, "master_slave_a_um"), _value(params, "master_slave_b_um")
    if a is not None or b is not None:
        add("master_slave", "machine", "steps where the master axis changes (45 deg lines): check the "
            "interpolator's changeover and the feed-forward of both axes",
            max(abs(a or 0.0), abs(b or 0.0)), "um")
    spikes = {k: v for k, v in params.items() if k.startswith("reversal_spike_") and k.endswith("_um")}
    for key in sorted(spikes):
        h = _value(params, key)
        if h is not None:
            where = key[len("reversal_spike_") : -3].replace("_", " ")
            add(key, "machine", f"reversal spike {n(key, h, True)} um ({where}): adjust the friction / quadrant-glitch "
                "compensation of that axis", h, "um", "reversal")
    for axis, key in ((ax1, "straightness_x_um"), (ax2, "straightness_y_um")):
        v = _value(params, key)
        if v is not None:
            add(key, "machine", f"{axis} bows by {n(key, v)} um over the radius: check the guideway alignment "
                "or apply straightness compensation", v, "um", "squareness")
    for axis, key in ((ax1, "cyclic_x_um"), (ax2, "cyclic_y_um")):
        v = _value(params, key)
        if v is not None:
            add(key, "machine", f"{axis} cyclic error {n(key, v)} um at the screw pitch: check the ball-screw "
                "support bearings and nut, or the encoder", v, "um")
    d = _value(params, "drift_um_per_min")
    if d is not None:
        add("drift_um_per_min", "setup", f"length drifts {n('drift_um_per_min', d, True)} um/min during the "
            "test: let the machine and the bar reach thermal equilibrium before testing", d, "um/min")
    cx, cy = _value(params, "centre_x_um"), _value(params, "centre_y_um")
    if cx is not None or cy is not None:
        add("centre", "setup", f"set-up: the pivot is off the programmed centre by ("
            f"{n('centre_x_um', cx or 0.0)}, {n('centre_y_um', cy or 0.0)}) um; not a machine error (it is "
            "removed before the other figures)",
            float((cx or 0) ** 2 + (cy or 0) ** 2) ** 0.5, "um")
    r = _value(params, "radius_um")
    if r is not None and abs(r) >= 1.0:
        add("radius_um", "setup", f"the circle reads {n('radius_um', r, True)} um from the nominal radius: bar "
            "calibration, temperature, or the servo's dynamic shrinkage at this feed", r, "um")
    return out


# --------------------------------------------------------------------------- which advice, in which order

#: A field's pattern, for its share of the machine's error (cyclic errors: amplitude and phase).
_PATTERN_OF: dict[str, str] = {
    f: p.name for p in LIBRARY
    for f in ((f"{p.name}_um", f"{p.name}_phase_deg") if p.name.startswith("cyclic_") else (*p.fields, p.name))
}
_LIMIT_RANK = {"fail": 0, "warning": 1}


def _fields(item: Mapping[str, Any]) -> tuple[str, ...]:
    """The result fields an advice item is about (``master_slave``: both of its fields)."""
    name = str(item.get("pattern", ""))
    pattern = _PATTERN_OF.get(name)
    if pattern is not None and pattern == name:  # named by its pattern
        return tuple(f for f, n in _PATTERN_OF.items() if n == pattern and f != pattern)
    return (name,)


def ranked_advice(result: Mapping[str, Any]) -> list[Advice]:
    """The advice worth giving, in the order to act on it (analysis/README.md, "Advice"):

    - an item whose own quantity has a limit (``[limits] parameters``) that it passes is left out: inside its
      limit, and (being significant at all) beyond its minimum effect only, it needs no adjustment; an item
      without a limit of its own stays while significant (:func:`advise` gives no other);
    - first the items whose quantity fails its limit, then those at a warning, then the rest; within each, by
      the share of the machine's error of their pattern (the ranking's ``share_pct``), largest first;
    - set-up items last, in the same order.
    """
    limits: dict[str, str] = {}
    v = result.get("verdict")
    for e in (v.get("limits") or []) if isinstance(v, Mapping) else []:
        if isinstance(e, Mapping) and e.get("group") == "parameters" and e.get("status") != "not_evaluated":
            limits[str(e.get("name"))] = str(e.get("status"))
    share: dict[str, float] = {}
    for r in result.get("ranking") or []:
        if isinstance(r, Mapping) and isinstance(r.get("share_pct"), int | float):
            share[str(r.get("pattern"))] = float(r["share_pct"])
    keyed = []
    for i, item in enumerate(result.get("advice") or []):
        if not isinstance(item, Mapping):
            continue
        states = [limits[f] for f in _fields(item) if f in limits]
        rank = min((_LIMIT_RANK.get(s, 2) for s in states), default=2)
        if states and rank == 2:  # every limit of its own passed
            continue
        pattern = _PATTERN_OF.get(str(item.get("pattern")), str(item.get("pattern")))
        keyed.append(((item.get("kind") == "setup", rank, -share.get(pattern, 0.0), i), item))
    keyed.sort(key=lambda k: k[0])
    return [cast("Advice", dict(item)) for _k, item in keyed]
