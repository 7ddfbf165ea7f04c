"""A three-dimensional simulated machine: X, Y and Z axis errors, and what each plane's test sees of them.

:class:`Machine3D` holds per-axis errors (lost motion, position-loop gains,
velocity loops, reversal spikes, scales, cyclic errors, the pivot's set-up
offset) and the three squareness errors; the rest (feed override,
acceleration, noise, sampling, the bar) is one plane-free
:class:`~ballbar.tools.simulator.MachineModel`, ``base``.  A test in plane
``P`` with first axis ``a`` and second axis ``b`` (``XY``: X, Y; ``YZ``: Y, Z;
``ZX``: Z, X) runs on :meth:`Machine3D.project`: the plane's ``_x`` keys are
axis ``a``'s, its ``_y`` keys axis ``b``'s, and its squareness is the plane's.
The bar's length depends on the errors along the plane's normal only to second
order (``D^2 / 2R``: 0.5 nm for 10 um at 100 mm), so the projection is the
whole first-order picture.

Signs (analysis/README.md, "Three planes, one machine"): ``squareness_xy_urad
= S``: ``DX = S Y``; ``squareness_yz_urad``: ``DY = S Z``;
``squareness_zx_urad``: ``DZ = S X``; each is the ``squareness_urad`` that
its plane's test reports.  ``scale_*_ppm``: ``D = e x`` along each axis.
``centre_*_um``: the pivot sits that far from the programmed centre, along
each axis (the library's ``D = (x0, y0)`` of each plane).

:func:`set_tests` runs a set's plans in turn on one sample clock, each
program with its signature where its plan has one, and gives the lengths as
the bar reads them assembled for each plan (:class:`~ballbar.analysis.plans.PlanLibrary`):
``L - (R - R0)``.  :func:`simulated_tests` is the daemon's ``sim:`` plug-in: a
set's tests on this machine, or one plan's on a plane-free
:class:`~ballbar.tools.simulator.MachineModel`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, cast

import numpy as np

from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import PLANE_AXES, Plane, TestPlan
from ballbar.analysis.plans import NamedPlan, PlanLibrary, signature_moves
from ballbar.analysis.program import Move, moves

from .simulator import MachineModel, SimResult, iter_programs, iter_tests, truth_of

AXIS_KEYS = (
    "backlash_{}_um", "backlash_comp_{}_um", "kv_{}_per_s", "velocity_loop_{}_hz", "spike_{}_um", "spike_tau_{}_s",
    "scale_{}_ppm", "cyclic_{}_um", "cyclic_{}_phase_deg", "pitch_{}_mm", "centre_{}_um",
)
SQUARENESS_KEYS = {"XY": "squareness_xy_urad", "YZ": "squareness_yz_urad", "ZX": "squareness_zx_urad"}
# The plane keys of MachineModel that the 3D machine leaves at zero: they belong to one plane, not to an axis.
PLANE_ONLY = ("lateral_play_x_um", "lateral_play_y_um", "lateral_takeup_um", "straightness_x_um",
              "straightness_y_um", "master_slave_a_um", "master_slave_b_um", "squareness_urad")
_PLANE_KEYS = {k.format(c) for k in AXIS_KEYS for c in "xy"} | set(PLANE_ONLY)
_DEFAULT = MachineModel()


def machine_keys() -> dict[str, float]:
    """The flat keys :meth:`Machine3D.from_settings` takes, each with its default: every axis key for ``x``, ``y``
    and ``z``, the three squareness errors, and the plane-free keys of the plane's machine model."""
    out = {key.format(c): _axis_default(key) for key in AXIS_KEYS for c in "xyz"}
    out.update({k: 0.0 for k in SQUARENESS_KEYS.values()})
    out.update({f.name: getattr(_DEFAULT, f.name) for f in fields(MachineModel) if f.name not in _PLANE_KEYS})
    return out


def _axis_default(key: str) -> float:
    return float(getattr(_DEFAULT, key.format("x")))


@dataclass(frozen=True)
class Machine3D:
    """The 3D machine: ``axes[key]`` for each of :data:`AXIS_KEYS` with ``x``, ``y`` or ``z``, the three
    squareness errors (urad), and ``base`` for everything that is not an axis's or a plane's."""

    axes: Mapping[str, float] = field(default_factory=dict)
    squareness_xy_urad: float = 0.0
    squareness_yz_urad: float = 0.0
    squareness_zx_urad: float = 0.0
    base: MachineModel = field(default_factory=MachineModel)

    def __post_init__(self) -> None:
        known = {k.format(c) for k in AXIS_KEYS for c in "xyz"}
        for key, v in self.axes.items():
            if key not in known:
                raise PlanError(f"unknown axis key {key!r} (known: {', '.join(sorted(known))})")
            if isinstance(v, bool) or not isinstance(v, int | float) or math.isnan(v):
                raise PlanError(f"axis key {key!r} must be a number, not {v!r}")
        for plane in SQUARENESS_KEYS:
            self.project(plane)  # each plane's machine must be a valid MachineModel

    def get(self, key: str, axis: str) -> float:
        """The value of ``key`` (a pattern of :data:`AXIS_KEYS`) for ``axis`` (``x``, ``y``, ``z``)."""
        return float(self.axes.get(key.format(axis), _axis_default(key)))

    def project(self, plane: str) -> MachineModel:
        """The machine a test in ``plane`` sees: its first axis' errors as ``_x``, its second's as ``_y``."""
        a, b = (c.lower() for c in PLANE_AXES[plane])
        changes: dict[str, Any] = {k: getattr(_DEFAULT, k) for k in PLANE_ONLY}
        for key in AXIS_KEYS:
            changes[key.format("x")] = self.get(key, a)
            changes[key.format("y")] = self.get(key, b)
        changes["squareness_urad"] = float(getattr(self, SQUARENESS_KEYS[plane]))
        return replace(self.base, **changes)

    @classmethod
    def from_settings(cls, items: Mapping[str, Any]) -> Machine3D:
        """From flat keys: the axis keys with ``x``/``y``/``z``, the three squareness keys, and any key of
        :class:`~ballbar.tools.simulator.MachineModel` that belongs to no plane (``noise_um``,
        ``feed_override``, ...); a plane key (``backlash_x_um`` means X here, ``lateral_play_x_um``) is an axis
        key or an error."""
        axis_keys = {k.format(c) for k in AXIS_KEYS for c in "xyz"}
        axes: dict[str, float] = {}
        sq: dict[str, float] = {}
        base: dict[str, Any] = {}
        model = {f.name for f in fields(MachineModel)}
        for key, value in items.items():
            if key in axis_keys:
                axes[key] = value
            elif key in SQUARENESS_KEYS.values():
                sq[key] = float(value)
            elif key in model and key not in _PLANE_KEYS:
                base[key] = value
            else:
                raise PlanError(f"unknown 3D machine key {key!r}: an axis key ({', '.join(AXIS_KEYS)} with x, y or "
                                f"z), {', '.join(SQUARENESS_KEYS.values())}, or a plane-free machine key")
        return cls(axes, base=MachineModel.from_dict(base) if base else MachineModel(), **sq)

    def to_dict(self) -> dict[str, Any]:
        base = {k: v for k, v in self.base.to_dict().items() if k not in _PLANE_KEYS}
        return {**base, **dict(self.axes), **{k: getattr(self, k) for k in SQUARENESS_KEYS.values()}}

    def truth(self, plane: str) -> dict[str, float]:
        """What a test in ``plane`` should report (:func:`~ballbar.tools.simulator.truth_of` of its projection,
        radius and plan aside): the fields each plane's result carries."""
        return truth_of(TestPlan(plane=cast(Plane, plane)), self.project(plane))

    def with_(self, **changes: Any) -> Machine3D:
        axes = dict(self.axes)
        sq = {k: changes.pop(k) for k in list(changes) if k in SQUARENESS_KEYS.values()}
        for k in list(changes):
            if any(k == key.format(c) for key in AXIS_KEYS for c in "xyz"):
                axes[k] = changes.pop(k)
        base = replace(self.base, **changes) if changes else self.base
        return replace(self, axes=axes, base=base, **sq)


def program_of(p: NamedPlan) -> list[Move]:
    """A plan's moves as ``ballbar gcode`` writes them: its signature (where it has one), then the test."""
    return (signature_moves(p.plan, p.signature) if p.signature is not None else []) + moves(p.plan)


def set_tests(
    library: PlanLibrary,
    names: Sequence[str],
    machine: Machine3D,
    sample_hz: float,
    seed: int = 0,
    repeat: int | None = None,
    gap_s: float = 5.0,
    drift: Mapping[str, float] | None = None,
) -> Iterator[tuple[str, SimResult]]:
    """The plans ``names`` of ``library`` in turn (cycled; ``repeat`` tests in all, None: forever) on
    ``machine``, each as its plane sees it, on one sample clock; each result's lengths as the bar reads them
    (see the module docstring).  ``drift``: 3D machine keys and how much each changes from one test to the
    next (a machine that wears)."""
    if not names:
        raise PlanError("a set needs at least one plan")
    chosen = [library.get(n) for n in names]
    if drift:
        Machine3D.from_settings(dict.fromkeys(drift, 0.0))  # the keys are the 3D machine's

    def stream() -> Iterator[tuple[TestPlan, MachineModel, list[Move]]]:
        i = 0
        while repeat is None or i < repeat:
            p = chosen[i % len(chosen)]
            m = machine
            if drift:
                flat = m.to_dict()
                m = Machine3D.from_settings({**flat, **{k: float(flat.get(k, 0.0)) + i * float(r)
                                                        for k, r in drift.items()}})
            yield p.plan.with_(sample_hz=sample_hz), m.project(p.plan.plane), program_of(p)
            i += 1

    for i, res in enumerate(iter_programs(stream(), sample_hz, seed, gap_s)):
        p = chosen[i % len(chosen)]
        off = library.offset_mm(p.name)
        if off:
            res.length_mm = res.length_mm - off
        yield p.name, res


def simulated_tests(
    plan: TestPlan,
    machine: MachineModel | None,
    sample_hz: float,
    seed: int = 0,
    repeat: int | None = None,
    gap_s: float = 0.0,
    *,
    library: Any = None,
    run_plans: Sequence[str] | None = None,
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The daemon's ``sim:`` source's tests (the ``tests`` plug-in, ``ballbar.daemon.plugins``): each test's sample
    times (s) and lengths (mm), one after the other on one clock; ``machine`` None is the default machine.  With
    a ``library`` of plans, its ``run_plans`` (default all) in turn on a machine with X, Y and Z errors
    (``machine`` a :class:`Machine3D`, default one), each program with its signature."""
    if library is not None:
        names = list(run_plans) if run_plans else list(library.names)
        m3 = machine if isinstance(machine, Machine3D) else Machine3D()
        for _name, res in set_tests(library, names, m3, sample_hz, seed, repeat, gap_s):
            yield res.t_s, res.length_mm
        return
    for res in iter_tests(plan, machine if machine is not None else MachineModel(), sample_hz, seed, repeat, gap_s):
        yield res.t_s, res.length_mm


def truth_table(machine: Machine3D, planes: Sequence[str] = ("XY", "YZ", "ZX")) -> dict[str, dict[str, float]]:
    """Each plane's expected result fields (:meth:`Machine3D.truth`)."""
    return {plane: machine.truth(plane) for plane in planes}


__all__ = ["AXIS_KEYS", "SQUARENESS_KEYS", "Machine3D", "program_of", "set_tests", "simulated_tests", "truth_table"]
