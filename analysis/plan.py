"""The test plan, the machine's configuration and the analysis options.

Names, units and defaults: analysis/README.md, "The test program".  The plan
is configuration: the analyzer assumes the timing of the program that
:mod:`ballbar.analysis.program` generates from it.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import TYPE_CHECKING, Any, Literal, cast

from .errors import PlanError

if TYPE_CHECKING:
    from ballbar.protocol.messages.config import MachineSection
    from ballbar.protocol.messages.results import Machine, ResultPlan

Plane = Literal["XY", "YZ", "ZX"]
Directions = Literal["both", "ccw", "cw"]

PLANE_AXES: dict[str, tuple[str, str]] = {"XY": ("X", "Y"), "YZ": ("Y", "Z"), "ZX": ("Z", "X")}
#: The circular-test standards whose figures a result can carry (analysis/standards.py).
STANDARDS = ("iso230_4", "jis_b6190_4", "asme_b5_54")


@dataclass(frozen=True)
class TestPlan:
    """One ball-bar test as programmed.

    Angles in degrees, counter-clockwise from the plane's first axis; lengths in
    millimetres; feed in mm/min; times in seconds.
    """

    __test__ = False  # not a pytest class

    plane: Plane = "XY"
    radius_mm: float = 100.0
    feed_mm_min: float = 1000.0
    start_deg: float = 0.0
    overshoot_deg: float = 180.0
    data_arc_deg: float = 360.0
    feed_in_mm: float = 1.5
    dwell_s: float = 0.5
    directions: Directions = "both"
    sample_hz: float = 1000.0

    def __post_init__(self) -> None:
        checks: list[tuple[bool, str]] = [
            (self.plane in PLANE_AXES, f"plane must be one of XY, YZ, ZX, not {self.plane!r}"),
            (_pos(self.radius_mm), f"radius_mm must be > 0, not {self.radius_mm!r}"),
            (_pos(self.feed_mm_min), f"feed_mm_min must be > 0, not {self.feed_mm_min!r}"),
            (_finite(self.start_deg), f"start_deg must be finite, not {self.start_deg!r}"),
            (
                _finite(self.overshoot_deg) and 0 <= self.overshoot_deg <= 360,
                f"overshoot_deg must be within 0..360, not {self.overshoot_deg!r}",
            ),
            (
                _finite(self.data_arc_deg) and 30 <= self.data_arc_deg <= 360,
                f"data_arc_deg must be within 30..360, not {self.data_arc_deg!r}",
            ),
            (
                _finite(self.feed_in_mm) and 0 < self.feed_in_mm < self.radius_mm,
                f"feed_in_mm must be > 0 and below the radius, not {self.feed_in_mm!r}",
            ),
            (_finite(self.dwell_s) and self.dwell_s >= 0, f"dwell_s must be >= 0, not {self.dwell_s!r}"),
            (
                self.directions in ("both", "ccw", "cw"),
                f"directions must be both, ccw or cw, not {self.directions!r}",
            ),
            (_pos(self.sample_hz), f"sample_hz must be > 0, not {self.sample_hz!r}"),
        ]
        for ok, msg in checks:
            if not ok:
                raise PlanError(msg)

    @property
    def feed_mm_s(self) -> float:
        return self.feed_mm_min / 60.0

    @property
    def axes(self) -> tuple[str, str]:
        return PLANE_AXES[self.plane]

    @property
    def arc_deg(self) -> float:
        """Angle swept by one arc: overshoot, data arc, overshoot."""
        return self.data_arc_deg + 2.0 * self.overshoot_deg

    @property
    def direction_list(self) -> tuple[int, ...]:
        """Directions in the order the program runs them: +1 CCW, -1 CW."""
        return {"both": (1, -1), "ccw": (1,), "cw": (-1,)}[self.directions]

    def to_dict(self) -> ResultPlan:
        # the fields of Plan (the config and result schemas' tests keep the two the same); a result adds its
        # name and axes (ResultPlan)
        return cast("ResultPlan", asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> TestPlan:
        return _from_dict(cls, data, "plan")

    def with_(self, **changes: Any) -> TestPlan:
        return replace(self, **changes)


@dataclass(frozen=True)
class MachineConfig:
    """What the analyzer of one test may know of the machine besides the plan: its plane's two axes.

    ``x`` and ``y`` here are the plane's first and second axis (``plan.axes``:
    XY takes X, Y; YZ takes Y, Z; ZX takes Z, X), whatever the machine calls
    them: :meth:`MachineAxes.for_plane` makes one from the machine's own axes.
    ``pitch_*_mm``: ball-screw pitch, for the cyclic-error pattern (left out
    when unknown).  ``kv_*_per_s``: configured position-loop gains in 1/s, for
    the servo advice and the physical servo model.  ``controller``: names the
    compensation parameters in the advice.
    """

    pitch_x_mm: float | None = None
    pitch_y_mm: float | None = None
    kv_x_per_s: float | None = None
    kv_y_per_s: float | None = None
    controller: Literal["generic", "fanuc", "siemens", "heidenhain"] = "generic"

    def __post_init__(self) -> None:
        _check_machine(self, ("pitch_x_mm", "pitch_y_mm", "kv_x_per_s", "kv_y_per_s"))

    def to_dict(self) -> Machine:
        return cast("Machine", asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MachineConfig:
        return _from_dict(cls, data, "machine")


def _check_machine(m: Any, names: tuple[str, ...]) -> None:
    """A machine section's settings ``names`` positive where given, its controller one of those named."""
    for name in names:
        v = getattr(m, name)
        if v is not None and not _pos(v):
            raise PlanError(f"{name} must be > 0, not {v!r}")
    if m.controller not in ("generic", "fanuc", "siemens", "heidenhain"):
        raise PlanError(f"controller must be generic, fanuc, siemens or heidenhain, not {m.controller!r}")


MACHINE_AXES = ("X", "Y", "Z")
#: The per-axis settings of [machine]: each a key per machine axis (:func:`axis_key`).
AXIS_SETTINGS = ("pitch", "kv")


def axis_key(setting: str, axis: str) -> str:
    """The key of ``setting`` (``pitch``, ``kv``) for machine axis ``axis``: ``axis_key("kv", "Z")`` is
    ``kv_z_per_s``."""
    return f"pitch_{axis.lower()}_mm" if setting == "pitch" else f"kv_{axis.lower()}_per_s"


def plane_keys(setting: str, plane: str) -> str:
    """The ``[machine]`` keys of ``setting`` for ``plane``'s two axes, in words: ``kv_z_per_s and kv_x_per_s``
    for ZX (what advice and reasons tell the user to configure)."""
    first, second = PLANE_AXES[plane]
    return f"{axis_key(setting, first)} and {axis_key(setting, second)}"


@dataclass(frozen=True)
class MachineAxes:
    """The machine's settings per machine axis X, Y, Z (the daemon's ``[machine]``), given once for every plane.

    Each plan takes its plane's two (:meth:`for_plane`): XY takes X and Y, YZ
    takes Y and Z, ZX takes Z and X (first axis first, :data:`PLANE_AXES`).
    Units and use as :class:`MachineConfig`.
    """

    pitch_x_mm: float | None = None
    pitch_y_mm: float | None = None
    pitch_z_mm: float | None = None
    kv_x_per_s: float | None = None
    kv_y_per_s: float | None = None
    kv_z_per_s: float | None = None
    controller: Literal["generic", "fanuc", "siemens", "heidenhain"] = "generic"

    def __post_init__(self) -> None:
        _check_machine(self, self.axis_keys())

    @staticmethod
    def axis_keys(axes: tuple[str, ...] = MACHINE_AXES) -> tuple[str, ...]:
        """The per-axis keys of ``axes``, in field order."""
        return tuple(axis_key(s, a) for s in AXIS_SETTINGS for a in axes)

    def for_plane(self, plane: str) -> MachineConfig:
        """What a test in ``plane`` knows: its first axis' settings as ``x``, its second's as ``y``."""
        first, second = PLANE_AXES[plane]
        return MachineConfig(
            pitch_x_mm=getattr(self, axis_key("pitch", first)),
            pitch_y_mm=getattr(self, axis_key("pitch", second)),
            kv_x_per_s=getattr(self, axis_key("kv", first)),
            kv_y_per_s=getattr(self, axis_key("kv", second)),
            controller=self.controller,
        )

    @classmethod
    def of_plane(cls, plane: str, machine: MachineConfig) -> MachineAxes:
        """The machine's axes that ``machine`` (a test's, of ``plane``) names; the third axis unknown."""
        first, second = PLANE_AXES[plane]
        return cls(**{
            axis_key("pitch", first): machine.pitch_x_mm, axis_key("pitch", second): machine.pitch_y_mm,
            axis_key("kv", first): machine.kv_x_per_s, axis_key("kv", second): machine.kv_y_per_s,
        }, controller=machine.controller)

    def to_dict(self) -> MachineSection:
        return cast("MachineSection", asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MachineAxes:
        return _from_dict(cls, data, "machine")


def check_axes(machine: MachineAxes, planes: Sequence[str]) -> None:
    """A :class:`PlanError` naming the key where ``machine`` gives only X and Y keys and one of them is for an
    axis no plane of ``planes`` moves: written when x and y were a plan's first and second axis
    (``kv_y_per_s`` of a ZX plan was X's gain), it cannot mean the machine's Y.  A Z key says the table names
    the machine's axes: then a key of an axis no plan moves is a fact about the machine, kept."""
    if any(getattr(machine, key) is not None for key in MachineAxes.axis_keys(("Z",))):
        return
    planes = list(dict.fromkeys(planes))
    moved = {axis for plane in planes for axis in PLANE_AXES[plane]}
    for setting in AXIS_SETTINGS:
        for axis in MACHINE_AXES[:2]:
            key = axis_key(setting, axis)
            if getattr(machine, key) is not None and axis not in moved:
                raise PlanError(
                    f"machine.{key}: no plan moves {axis} (planes {', '.join(planes)}); [machine] keys name the "
                    f"machine's axes now, not a plan's first and second: set "
                    f"{'; '.join(f'{plane_keys(setting, p)} for {p}' for p in planes)}")


def machine_of(data: Mapping[str, Any] | Machine | MachineSection) -> MachineAxes | MachineConfig:
    """A configuration's ``[machine]`` table: the machine's axes (:class:`MachineAxes`); or, where it has the
    keys of :class:`MachineConfig` and no others (a configuration recorded before the machine's axes were named,
    whose x and y were each plan's first and second axis), that.  A bad table is a :class:`PlanError`."""
    if set(data) == {f.name for f in fields(MachineConfig)}:
        return MachineConfig.from_dict(dict(data))
    return MachineAxes.from_dict(dict(data))


def for_plane(machine: MachineAxes | MachineConfig, plane: str) -> MachineConfig:
    """What a test in ``plane`` knows of ``machine`` (a :class:`MachineConfig` is one plane's already)."""
    return machine.for_plane(plane) if isinstance(machine, MachineAxes) else machine


@dataclass(frozen=True)
class AnalysisOptions:
    """How the analyzer works; the defaults are what `ballbar analyze` uses.

    ``significance``: the F-test level below which a pattern counts as found.
    ``servo_model``: ``linear`` is the seed's mask; ``physical`` fits a first-order
    loop per axis (needs the mean loop lag, from ``kv_*`` or measured from the
    feed-in); ``auto`` uses ``physical`` when that lag is known.
    ``lost_motion``: ``physical`` lets the data choose each axis' model by the
    sign of its backlash: a dead band (the table stands still after a reversal
    until the motor has crossed the gap) or, for negative backlash, the
    control's compensation step followed through the position loop
    (:mod:`.physics`); ``step`` is the seed's mask alone.  ``deadband`` is the
    earlier name of ``physical``.
    ``min_effect_um``: besides ``p < significance``, a pattern is significant
    only if its largest radial effect over the data reaches this (um); a
    pattern that passes the F-test but not this says so in its result.
    ``vif_limit``: a parameter whose variance inflation exceeds this cannot be
    separated from the others in this data and is left out with the reason.
    ``vibration_cutoff_cpr``: residual content above this many cycles per
    revolution counts as vibration.
    ``standards``: the circular-test standards whose figures a test result
    carries (:data:`STANDARDS`): ISO 230-4's always (``iso230_4``), the others'
    under ``standards.<id>`` (:mod:`.standards`).
    """

    significance: float = 0.05
    servo_model: Literal["auto", "linear", "physical"] = "auto"
    min_effect_um: float = 0.05
    lost_motion: Literal["physical", "deadband", "step"] = "physical"
    vif_limit: float = 1.0e4
    vibration_cutoff_cpr: float = 30.0
    spike_width_min_deg: float = 0.05
    spike_width_max_deg: float = 10.0
    estimate_lag: bool = True
    max_lag_s: float = 0.5
    patterns: tuple[str, ...] | None = None  # None: the whole library that the data supports
    standards: tuple[str, ...] = ("iso230_4",)  # whose circular-test figures a test result carries (ISO always)

    def __post_init__(self) -> None:
        if not 0 < self.significance < 1:
            raise PlanError(f"significance must be within (0, 1), not {self.significance!r}")
        if self.lost_motion not in ("physical", "deadband", "step"):
            raise PlanError(f"lost_motion must be physical or step, not {self.lost_motion!r}")
        if not (math.isfinite(self.min_effect_um) and self.min_effect_um >= 0):
            raise PlanError(f"min_effect_um must be >= 0, not {self.min_effect_um!r}")
        if self.servo_model not in ("auto", "linear", "physical"):
            raise PlanError(f"servo_model must be auto, linear or physical, not {self.servo_model!r}")
        if not 0 < self.spike_width_min_deg < self.spike_width_max_deg:
            raise PlanError("spike widths must satisfy 0 < min < max")
        # VIF >= 1 by construction: a limit at or below 1 would leave every parameter out.
        if not (_finite(self.vif_limit) and self.vif_limit > 1):
            raise PlanError(f"vif_limit must be a number > 1, not {self.vif_limit!r}")
        if not _pos(self.max_lag_s):
            raise PlanError(f"max_lag_s must be a number > 0, not {self.max_lag_s!r}")
        for name in self.standards:
            if name not in STANDARDS:
                raise PlanError(f"standards: unknown standard {name!r} (known: {', '.join(STANDARDS)})")
        if not _pos(self.vibration_cutoff_cpr):
            raise PlanError(f"vibration_cutoff_cpr must be a number > 0, not {self.vibration_cutoff_cpr!r}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> AnalysisOptions:
        """From a configuration table (``patterns`` may be a list, as TOML and JSON give it)."""
        data = dict(data)
        for key in ("patterns", "standards"):
            if isinstance(data.get(key), list):
                data[key] = tuple(data[key])
        return _from_dict(cls, data, "analysis")


def _pos(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0


def _finite(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _from_dict(cls: Any, data: dict[str, Any], what: str) -> Any:
    known = {f.name: f for f in fields(cls)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise PlanError(f"unknown {what} key {unknown[0]!r} (known: {', '.join(sorted(known))})")
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        ftype = str(known[key].type)
        if "float" in ftype and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if "float" in ftype and value is not None and not _finite(value):
            raise PlanError(f"{what} key {key!r} must be a number, not {value!r}")
        kwargs[key] = value
    return cls(**kwargs)


__all__ = [
    "AXIS_SETTINGS",
    "MACHINE_AXES",
    "PLANE_AXES",
    "STANDARDS",
    "AnalysisOptions",
    "Directions",
    "MachineAxes",
    "MachineConfig",
    "Plane",
    "TestPlan",
    "axis_key",
    "check_axes",
    "for_plane",
    "machine_of",
    "plane_keys",
]
