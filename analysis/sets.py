"""A test set combined into the machine's axes: the ``set`` result (analysis/README.md, "Test sets").

A set is the latest test of each of its plans, all run within the set's
window.  Each plane's test sees its two axes (``XY``: X and Y; ``YZ``: Y and
Z; ``ZX``: Z and X, each plane's first axis first): together the three planes
see every axis twice and every axis pair once.  From the tests' fitted
parameters (value and standard error) this module makes:

- lost motion per axis (X, Y, Z): the inverse-variance weighted mean of every
  plane that sees the axis, with a consistency check where two or more do;
- the three squareness errors (``XY``, ``YZ``, ``ZX``), each from the tests of
  its plane;
- the relative scale errors (ppm) and the servo lag mismatches (ms) per axis
  pair, each loop's three pairwise values checked for closure (they must add
  to zero: ``(eX - eY) + (eY - eZ) + (eZ - eX) = 0``), then adjusted to close
  and turned into each axis' value against the three axes' mean;
- volumetric figures: the set's largest circular deviation (the largest
  ``G(b)`` of its tests) and the geometric sphericity (the range of the radial
  deviation that the squareness and relative scale errors make over the whole
  sphere of the set's radius);
- the verdict: the plans' verdicts and the set's checks.

Pure: result dictionaries in, a JSON-ready dictionary out, no clock and no
files.  The daemon (:mod:`ballbar.daemon.sets`) publishes it when a set's
tests are in; ``ballbar analyze DIR --set NAME`` makes it again from the
recordings.

Sign conventions (one for the whole set, written down in analysis/README.md):
each pair is named in the right-handed cyclic order XY, YZ, ZX, the same order
as the planes' first and second axes, so a plane's own fields carry over
unchanged: ``squareness_urad`` of the pair ``ab`` is positive when the +a and
+b axes enclose less than 90 deg; ``scale_mismatch_ppm`` of ``ab`` is
``e_a - e_b`` (a travels that much more than b per command);
``servo_mismatch_ms`` of ``ab`` is ``1/K_a - 1/K_b`` (a lags b by that much).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from statistics import NormalDist
from typing import Any, Literal, NotRequired, TypedDict, TypeGuard

import numpy as np

from .errors import PlanError
from .numbers import measured
from .plan import PLANE_AXES

AXES = ("X", "Y", "Z")
#: The axis pairs, each named in the right-handed cyclic order of its plane's axes.
PAIRS = ("XY", "YZ", "ZX")
STATUS_RANK = {"pass": 0, "warning": 1, "fail": 2}
SPHERE_DRAWS = 4000  # Monte Carlo draws of the geometric sphericity's uncertainty

Status = Literal["passed", "failed", "not_checked"]


# --------------------------------------------------------------------------- the message's shapes


class Observation(TypedDict):
    """One test's estimate of a set quantity."""

    plan: str
    plane: str
    test_id: str | None
    field: str  # the test result's parameter it comes from (in that plane's first/second axis naming)
    value: float | None
    stderr: float | None
    used: bool  # entered the combination
    reason: str | None  # why not used


class Figure(TypedDict):
    """A set figure: its value and standard uncertainty, or why there is none; ``trusted`` false with reasons
    where a value exists but a check failed or a test behind it is in doubt."""

    value: float | None
    stderr: float | None
    unit: str
    trusted: bool
    reasons: list[str]


class Combined(Figure):
    observations: list[Observation]
    check: str | None  # the name of its consistency check (None: seen once)


class Pair(Combined):
    adjusted: Figure  # after the loop's closure is enforced


class Check(TypedDict):
    """A check of the whole set that no single test has."""

    name: str
    kind: Literal["consistency", "closure"]
    quantity: str
    status: Status
    value: float | None  # the discrepancy (consistency: largest from the mean; closure: the sum)
    stderr: float | None
    z: float | None  # value / stderr (consistency of more than two: sqrt of chi-square per degree of freedom)
    coverage_k: float
    min_discrepancy: float
    unit: str
    message: str


class Loop(TypedDict):
    """Pairwise values of one quantity, their closure, and each axis against the three axes' mean."""

    unit: str
    pairs: dict[str, Pair]
    closure: str  # the name of the closure check
    axes: dict[str, Figure]


class Extreme(Figure):
    plan: str | None
    test_id: str | None
    figure: str | None  # the ISO 230-4 field it is


class Sphericity(Figure):
    interval: list[float] | None  # the 95 % interval of the draws, um
    radius_mm: float | None


class Volumetric(TypedDict):
    largest_circular_deviation: Extreme
    geometric_sphericity: Sphericity
    method: str


class Member(TypedDict):
    """One plan's test in the set."""

    plan: str
    plane: str
    test_id: str | None
    t_wall: str | None
    radius_mm: float | None
    feed_mm_min: float | None
    data_arc_deg: float | None
    valid: bool
    invalid_reasons: list[str]
    verdict: str  # the test's own verdict: pass, warning, fail; not_evaluated without limits
    verdict_summary: str | None
    G_b_um: float | None


class PlanVerdict(TypedDict):
    plan: str
    status: str
    summary: str | None


class SetVerdict(TypedDict):
    status: Literal["pass", "warning", "fail"]
    trusted: bool
    plans: list[PlanVerdict]
    failed_checks: list[str]
    reasons: list[str]
    summary: str
    rule: str


class SetInfo(TypedDict):
    name: str
    plans: list[str]
    window_s: float


class SetResult(TypedDict):
    """The ``kind: "set"`` payload (the daemon adds ``machine_id`` and ``t_wall``)."""

    schema_version: NotRequired[int]
    kind: Literal["set"]
    machine_id: NotRequired[str]
    t_wall: NotRequired[str]
    set_id: str
    set: SetInfo
    tests: list[Member]
    span_s: float | None
    lost_motion: dict[str, Combined]
    squareness: dict[str, Combined]
    scale: Loop
    servo: Loop
    volumetric: Volumetric
    checks: list[Check]
    verdict: SetVerdict
    conventions: dict[str, str]
    method: str


# --------------------------------------------------------------------------- definition and options


@dataclass(frozen=True)
class SetDefinition:
    """``[sets.<name>]``: the plans whose latest tests make the set, all run within ``window_s`` of each other."""

    name: str
    plans: tuple[str, ...]
    window_s: float

    def __post_init__(self) -> None:
        if not self.plans:
            raise PlanError(f"sets.{self.name}.plans: a set needs at least one plan")
        if len(set(self.plans)) != len(self.plans):
            raise PlanError(f"sets.{self.name}.plans: a plan is named twice ({', '.join(self.plans)})")
        if not (isinstance(self.window_s, int | float) and math.isfinite(self.window_s) and self.window_s > 0):
            raise PlanError(f"sets.{self.name}: the window must be a positive number of seconds, not {self.window_s!r}")


def definitions(table: Mapping[str, Any] | None) -> list[SetDefinition]:
    """The sets of a configuration's ``sets`` table (``{name: {"plans": [...], "window_minutes": m}}``, as the
    configuration records it)."""
    out = []
    for name, body in (table or {}).items():
        if not isinstance(body, Mapping):
            raise PlanError(f"sets.{name} must be a table with plans and window_minutes")
        minutes = body.get("window_minutes")
        if not (isinstance(minutes, int | float) and not isinstance(minutes, bool)):
            raise PlanError(f"sets.{name}.window_minutes must be a number of minutes, not {minutes!r}")
        out.append(SetDefinition(str(name), tuple(str(p) for p in body.get("plans") or ()), 60.0 * float(minutes)))
    return out


@dataclass(frozen=True)
class SetOptions:
    """How the set's checks judge.

    A check fails where the discrepancy exceeds ``coverage_k`` of its standard
    errors *and* its minimum: below that, a difference between two planes is
    what a sound machine shows between tests (the load on an axis differs
    between a horizontal and a vertical plane; temperature moves between
    tests), not a contradiction.  The fit's standard errors count only what the
    samples say (tens of nanometres of lost motion at 1 kHz).
    """

    coverage_k: float = 3.0
    min_lost_motion_um: float = 0.5
    min_squareness_urad: float = 2.0
    min_scale_ppm: float = 2.0
    min_servo_ms: float = 0.05

    def __post_init__(self) -> None:
        for name in ("coverage_k", "min_lost_motion_um", "min_squareness_urad", "min_scale_ppm", "min_servo_ms"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0) or (name == "coverage_k" and v <= 0):
                raise PlanError(f"set option {name} must be a number >= 0 (coverage_k > 0), not {v!r}")


# --------------------------------------------------------------------------- choosing the tests


def plan_name(result: Mapping[str, Any]) -> str | None:
    """The plan a test result names (``plan.name``), or None for a result of an unnamed plan."""
    name = (result.get("plan") or {}).get("name")
    return str(name) if isinstance(name, str) and name else None


def _time(result: Mapping[str, Any]) -> datetime | None:
    t = result.get("t_wall")
    if not isinstance(t, str):
        return None
    try:
        out = datetime.fromisoformat(t.replace("Z", "+00:00"))
    except ValueError:
        return None
    return out if out.tzinfo is not None else out.replace(tzinfo=UTC)


@dataclass
class Selection:
    """The latest test of each plan of a set, and whether they make the set."""

    tests: dict[str, Mapping[str, Any]]
    missing: list[str]
    span_s: float | None
    complete: bool
    why_not: str | None

    @property
    def key(self) -> tuple[str | None, ...]:
        """The members' test ids: a set already published for these tests is not published again."""
        return tuple(self.tests[p].get("test_id") for p in sorted(self.tests))


def select(definition: SetDefinition, results: Iterable[Mapping[str, Any]]) -> Selection:
    """The latest test result of each of the set's plans among ``results`` (test results, any order).

    The set is complete when every plan has a test and the newest and the
    oldest of them lie within the window.  A test whose time is unknown
    (``t_wall``) is never a member.
    """
    latest: dict[str, tuple[datetime, Mapping[str, Any]]] = {}
    for r in results:
        if r.get("kind", "test") != "test":
            continue
        name = plan_name(r)
        t = _time(r)
        if name is None or name not in definition.plans or t is None:
            continue
        if name not in latest or t >= latest[name][0]:
            latest[name] = (t, r)
    missing = [p for p in definition.plans if p not in latest]
    tests = {p: latest[p][1] for p in definition.plans if p in latest}
    span = None
    if latest:
        times = [t for t, _ in latest.values()]
        span = (max(times) - min(times)).total_seconds()
    why = None
    if missing:
        why = f"no test of plan{'s' if len(missing) > 1 else ''} {', '.join(missing)} yet"
    elif span is not None and span > definition.window_s:
        why = (f"its latest tests span {span:.0f} s, more than the set's window of {definition.window_s:g} s: "
               "run the set's plans again together")
    return Selection(tests, missing, span, why is None, why)


# --------------------------------------------------------------------------- observations


def _test_validity(result: Mapping[str, Any]) -> tuple[bool, list[str]]:
    fit = result.get("fit") or {}
    reasons = [str(r) for r in fit.get("invalid_reasons") or []]
    valid = bool(fit.get("valid", True))
    if not valid and not reasons:
        reasons = ["the test's fit is marked invalid"]
    return valid, reasons


def _param(result: Mapping[str, Any], field: str) -> tuple[float | None, float | None, str | None]:
    p = (result.get("parameters") or {}).get(field)
    if not isinstance(p, Mapping):
        return None, None, f"the test has no {field}"
    v, se = p.get("value"), p.get("stderr")
    if not _finite(v):
        return None, None, str(p.get("reason") or f"{field} was not fitted")
    if not _finite(se) or se <= 0:
        return float(v), None, f"{field} has no standard error"
    return float(v), float(se), None


def _finite(v: Any) -> TypeGuard[float]:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _observe(tests: Mapping[str, Mapping[str, Any]], field_of: Any) -> dict[str, list[Observation]]:
    """Observations by axis or pair: ``field_of(plane)`` gives ``[(key, field), ...]`` for a plane."""
    out: dict[str, list[Observation]] = {}
    for plan, r in tests.items():
        plane = str((r.get("plan") or {}).get("plane", "XY"))
        valid, reasons = _test_validity(r)
        for key, field in field_of(plane, _axes(r)):
            v, se, why = _param(r, field)
            if why is None and not valid:
                why = f"plan {plan}'s test is invalid: {'; '.join(reasons)}"
            out.setdefault(key, []).append(Observation(
                plan=plan, plane=plane, test_id=r.get("test_id"), field=field, value=v, stderr=se,
                used=why is None, reason=why))
    return out


def _axes(result: Mapping[str, Any]) -> tuple[str, str]:
    """The machine axes of the test's first and second axis: ``plan.axes`` where the result names them, else
    its plane's (``XY``: X, Y; ``YZ``: Y, Z; ``ZX``: Z, X)."""
    plan = result.get("plan") or {}
    axes = plan.get("axes")
    if isinstance(axes, list | tuple) and len(axes) == 2 and all(a in AXES for a in axes):
        return str(axes[0]), str(axes[1])
    return PLANE_AXES[str(plan.get("plane", "XY"))]


def _axis_fields(field_x: str, field_y: str) -> Any:
    return lambda plane, axes: [(axes[0], field_x), (axes[1], field_y)]


def _pair_field(field: str) -> Any:
    """The pair a plane's field is about, named in the cyclic order (its first axis first)."""
    return lambda plane, axes: [(axes[0] + axes[1], field)]


# --------------------------------------------------------------------------- combining


def _normal_tail(k: float) -> float:
    return 2.0 * (1.0 - NormalDist().cdf(k))


def _combine(what: str, obs: list[Observation], unit: str, min_disc: float, opt: SetOptions,
             checks: list[Check]) -> Combined:
    """The weighted mean of the used observations, with a consistency check where two or more are used.

    A failed check leaves the value untrusted, and its standard error is
    inflated by the Birge ratio ``sqrt(chi2 / (n - 1))`` (the scatter the
    observations show beyond their standard errors).
    """
    used = [o for o in obs if o["used"]]
    reasons = [f"{o['plan']} ({o['plane']}): {o['reason']}" for o in obs if not o["used"]]
    if not used:
        why = reasons or [f"no test of the set sees {what}"]
        return Combined(value=None, stderr=None, unit=unit, trusted=False, reasons=why, observations=obs, check=None)
    x = np.array([o["value"] for o in used], dtype=float)
    se = np.array([o["stderr"] for o in used], dtype=float)
    w = 1.0 / se**2
    mean = float(np.sum(w * x) / np.sum(w))
    err = float(1.0 / math.sqrt(float(np.sum(w))))
    trusted = True
    name = None
    if len(used) >= 2:
        name = f"consistency of {what}"
        chk = _consistency(name, what, used, mean, unit, min_disc, opt)
        checks.append(chk)
        if chk["status"] == "failed":
            trusted = False
            chi2 = float(np.sum(w * (x - mean) ** 2))
            err *= math.sqrt(chi2 / (len(used) - 1))
            reasons = [chk["message"], *reasons]
    return Combined(value=mean, stderr=err, unit=unit, trusted=trusted, reasons=reasons, observations=obs,
                    check=name)


def _consistency(name: str, what: str, used: list[Observation], mean: float, unit: str, min_disc: float,
                 opt: SetOptions) -> Check:
    x = np.array([o["value"] for o in used], dtype=float)
    se = np.array([o["stderr"] for o in used], dtype=float)
    k = opt.coverage_k
    who = [f"{o['plan']} ({o['plane']}) {measured(o['value'], o['stderr'], unit, with_unit=False, ascii=True)}"
           for o in used]
    if len(used) == 2:
        d = float(x[0] - x[1])
        s = float(math.hypot(se[0], se[1]))
        z = d / s
        beyond = abs(z) > k
        value = d
    else:
        w = 1.0 / se**2
        chi2 = float(np.sum(w * (x - mean) ** 2))
        dof = len(used) - 1
        z = math.sqrt(chi2 / dof)
        from scipy.stats import chi2 as chi2_dist

        beyond = float(chi2_dist.sf(chi2, dof)) < _normal_tail(k)
        i = int(np.argmax(np.abs(x - mean)))
        value = float(x[i] - mean)
        s = float(se[i])
    large = abs(value) > min_disc
    failed = beyond and large
    if failed:
        apart = measured(abs(value), s, unit, shown=0, ascii=True)
        msg = (f"{what} disagrees between the planes: {'; '.join(who)} {unit} differ by {apart}, "
               f"{abs(z):.1f} standard errors (more than {k:g}) and more than {min_disc:g} {unit}")
    elif beyond:
        apart = measured(abs(value), s, unit, shown=0, ascii=True)
        msg = (f"{what} agrees within {min_disc:g} {unit} ({'; '.join(who)} {unit}: {apart} apart, "
               f"{abs(z):.1f} standard errors)")
    else:
        msg = (f"{what} agrees between the planes within {k:g} standard errors ({'; '.join(who)} {unit}: "
               f"{abs(z):.1f} standard errors apart)")
    return Check(name=name, kind="consistency", quantity=what, status="failed" if failed else "passed",
                 value=value, stderr=s, z=z, coverage_k=k, min_discrepancy=min_disc, unit=unit, message=msg)


def _loop(quantity: str, field: str, unit: str, tests: Mapping[str, Mapping[str, Any]], min_disc: float,
          opt: SetOptions, checks: list[Check]) -> Loop:
    """The pairwise values of ``field`` (``e_a - e_b`` for each plane ``ab``), their closure, each axis."""
    obs = _observe(tests, _pair_field(field))
    pairs: dict[str, Pair] = {}
    for p in PAIRS:
        c = _combine(f"the {p} {quantity}", obs.get(p, []), unit, min_disc, opt, checks)
        pairs[p] = Pair(**c, adjusted=Figure(value=c["value"], stderr=c["stderr"], unit=unit, trusted=c["trusted"],
                                             reasons=list(c["reasons"])))
    name = f"closure of the {quantity}"
    have = [p for p in PAIRS if pairs[p]["value"] is not None]
    if len(have) < 3:
        lacking = [p for p in PAIRS if p not in have]
        msg = (f"not checked: no value for the pair{'s' if len(lacking) > 1 else ''} {', '.join(lacking)} "
               f"({'; '.join(r for p in lacking for r in pairs[p]['reasons']) or 'not in the set'})")
        checks.append(Check(name=name, kind="closure", quantity=quantity, status="not_checked", value=None,
                            stderr=None, z=None, coverage_k=opt.coverage_k, min_discrepancy=min_disc, unit=unit,
                            message=msg))
        closed_ok = False
    else:
        q = np.array([pairs[p]["value"] for p in PAIRS], dtype=float)
        var = np.array([pairs[p]["stderr"] for p in PAIRS], dtype=float) ** 2
        total = float(q.sum())
        s = float(math.sqrt(var.sum()))
        z = total / s
        failed = abs(z) > opt.coverage_k and abs(total) > min_disc
        terms = " + ".join(f"{p} {pairs[p]['value']:+.4g}" for p in PAIRS)
        if failed:
            msg = (f"the {quantity} of the three pairs do not close: {terms} = {total:+.3g} {unit}, "
                   f"{abs(z):.1f} standard errors ({s:.2g} {unit}) from zero and more than {min_disc:g} {unit}: "
                   "a test of the set does not describe the machine the others do")
        else:
            msg = (f"the {quantity} of the three pairs close: {terms} = {total:+.3g} {unit} "
                   f"({abs(z):.1f} standard errors of {s:.2g} {unit})")
        checks.append(Check(name=name, kind="closure", quantity=quantity, status="failed" if failed else "passed",
                            value=total, stderr=s, z=z, coverage_k=opt.coverage_k, min_discrepancy=min_disc,
                            unit=unit, message=msg))
        closed_ok = not failed
        # The least-squares values that close: each pair moves by its share of the variance.
        adj = q - var * total / var.sum()
        cov = np.diag(var) - np.outer(var, var) / var.sum()
        for i, p in enumerate(PAIRS):
            reasons = list(pairs[p]["reasons"]) + ([] if closed_ok else [msg])
            pairs[p]["adjusted"] = Figure(value=float(adj[i]), stderr=float(math.sqrt(max(cov[i, i], 0.0))),
                                          unit=unit, trusted=pairs[p]["trusted"] and closed_ok, reasons=reasons)
    return Loop(unit=unit, pairs=pairs, closure=name, axes=_per_axis(quantity, pairs, unit, closed_ok))


def _per_axis(quantity: str, pairs: Mapping[str, Pair], unit: str, closed_ok: bool) -> dict[str, Figure]:
    """Each axis' value against the three axes' mean, by weighted least squares over the pairs there are.

    Pairs ``d_ab = e_a - e_b``; with ``sum e = 0`` two pairs determine all
    three axes, three over-determine them (the closure).  One pair does not.
    """
    have = [p for p in PAIRS if pairs[p]["value"] is not None]
    if len(have) < 2:
        why = (f"the {quantity} of each axis needs at least two of the pairs XY, YZ, ZX; the set has "
               f"{', '.join(have) or 'none'}")
        return {a: Figure(value=None, stderr=None, unit=unit, trusted=False, reasons=[why]) for a in AXES}
    A = np.zeros((len(have) + 1, 3))
    d = np.zeros(len(have) + 1)
    sw = np.zeros(len(have) + 1)
    for i, p in enumerate(have):
        A[i, AXES.index(p[0])], A[i, AXES.index(p[1])] = 1.0, -1.0
        d[i] = float(pairs[p]["value"])  # type: ignore[arg-type]
        sw[i] = 1.0 / float(pairs[p]["stderr"])  # type: ignore[arg-type]
    # the constraint sum e = 0, as a row of overwhelming weight (exact to rounding)
    A[-1] = 1.0
    sw[-1] = 1e6 * float(sw[:-1].max())
    Aw = A * sw[:, None]
    cov = np.linalg.inv(Aw.T @ Aw)
    e = cov @ (Aw.T @ (d * sw))
    trusted = closed_ok or len(have) == 2
    reasons = [r for p in have for r in pairs[p]["reasons"]]
    if not closed_ok and len(have) == 3:
        reasons.append(f"the closure of the {quantity} failed")
    ok_pairs = all(pairs[p]["trusted"] for p in have)
    return {a: Figure(value=float(e[i]), stderr=float(math.sqrt(max(cov[i, i], 0.0))), unit=unit,
                      trusted=trusted and ok_pairs, reasons=reasons) for i, a in enumerate(AXES)}


# --------------------------------------------------------------------------- volumetric figures


def _largest_deviation(tests: Mapping[str, Mapping[str, Any]]) -> Extreme:
    """The largest circular deviation of the set: ``G(b)`` (or, for a one-direction test, its ``G``)."""
    best: tuple[float, str, Mapping[str, Any], str] | None = None
    reasons: list[str] = []
    for plan, r in tests.items():
        valid, why = _test_validity(r)
        iso = r.get("iso230_4") or {}
        keys = ["G_b_um"] if _finite(iso.get("G_b_um")) else [k for k in ("G_ccw_um", "G_cw_um") if _finite(iso.get(k))]
        if not keys:
            reasons.append(f"{plan}: no circular deviation")
            continue
        k = max(keys, key=lambda key: float(iso[key]))
        v = float(iso[k])
        if not valid:
            reasons.append(f"{plan}'s test is invalid ({'; '.join(why)}): its {k}, {v:.3g} um, is left out")
            continue
        if best is None or v > best[0]:
            best = (v, plan, r, k)
    if best is None:
        return Extreme(value=None, stderr=None, unit="um", trusted=False, reasons=reasons or ["no test"], plan=None,
                       test_id=None, figure=None)
    v, plan, r, k = best
    sigma = r.get("residual_rms_um")
    if not _finite(sigma):
        sigma = (r.get("fit") or {}).get("sigma_um")
    se = math.sqrt(2.0) * float(sigma) if _finite(sigma) else None
    return Extreme(value=v, stderr=se, unit="um", trusted=True, reasons=reasons, plan=plan,
                   test_id=r.get("test_id"), figure=k)


def _sym_matrix(scale_ppm: Sequence[float] | np.ndarray, square_urad: Sequence[float] | np.ndarray) -> np.ndarray:
    """The symmetric part of the linear error matrix ``E`` (``D = E P``), dimensionless.

    ``E[a,a] = e_a`` (scale), and one off-diagonal term per pair: a
    squareness ``S_ab`` moves a by ``S_ab`` times b's coordinate; only the
    symmetric part ``S_ab / 2`` reaches the radius.
    """
    S = np.diag(np.asarray(scale_ppm, dtype=float) * 1e-6)
    for p, s in zip(PAIRS, square_urad, strict=True):
        i, j = AXES.index(p[0]), AXES.index(p[1])
        S[i, j] = S[j, i] = 0.5 * s * 1e-6
    return S


def sphericity_um(scale_ppm: Sequence[float] | np.ndarray, square_urad: Sequence[float] | np.ndarray,
                  radius_mm: float) -> float:
    """The range of the radial deviation ``R n' E n`` over the unit sphere's directions ``n``, um.

    The mean scale (a radius change) shifts every eigenvalue alike and drops
    out: the relative scales suffice.
    """
    lam = np.linalg.eigvalsh(_sym_matrix(scale_ppm, square_urad))
    return float((lam[-1] - lam[0]) * radius_mm * 1e3)


def _sphericity(scale: Loop, square: Mapping[str, Combined], tests: Mapping[str, Mapping[str, Any]]
                ) -> Sphericity:
    radii = [float(x) for r in tests.values() if _finite(x := (r.get("plan") or {}).get("radius_mm"))]
    lacking = [f"squareness {p}" for p in PAIRS if square[p]["value"] is None]
    lacking += [f"relative scale of {a}" for a in AXES if scale["axes"][a]["value"] is None]
    if lacking or not radii:
        why = f"needs all three squareness errors and each axis' relative scale; missing: {', '.join(lacking)}"
        return Sphericity(value=None, stderr=None, unit="um", trusted=False, reasons=[why], interval=None,
                          radius_mm=max(radii) if radii else None)
    R = max(radii)
    e = np.array([scale["axes"][a]["value"] for a in AXES], dtype=float)
    s = np.array([square[p]["value"] for p in PAIRS], dtype=float)
    value = sphericity_um(e, s, R)
    # The relative scales are correlated (they come from the same pairs, and sum to zero): draw them from their
    # least-squares covariance, rebuilt from the adjusted pairs; the squareness errors are independent.
    cov_e = _axis_cov(scale)
    se_s = np.array([square[p]["stderr"] for p in PAIRS], dtype=float)
    seed = int.from_bytes(hashlib.sha256(np.concatenate([e, s, se_s, cov_e.ravel()]).tobytes()).digest()[:8],
                          "little")
    rng = np.random.default_rng(seed)
    w, V = np.linalg.eigh(cov_e)
    root = V * np.sqrt(np.clip(w, 0.0, None))
    de = rng.standard_normal((SPHERE_DRAWS, 3)) @ root.T
    ds = rng.standard_normal((SPHERE_DRAWS, 3)) * se_s
    mats = np.zeros((SPHERE_DRAWS, 3, 3))
    ee = (e + de) * 1e-6
    ss = (s + ds) * 0.5e-6
    for k in range(3):
        mats[:, k, k] = ee[:, k]
    for k, p in enumerate(PAIRS):
        i, j = AXES.index(p[0]), AXES.index(p[1])
        mats[:, i, j] = mats[:, j, i] = ss[:, k]
    lam = np.linalg.eigvalsh(mats)
    draws = (lam[:, -1] - lam[:, 0]) * R * 1e3
    reasons = [r for a in AXES for r in scale["axes"][a]["reasons"]] + [r for p in PAIRS for r in square[p]["reasons"]]
    trusted = all(scale["axes"][a]["trusted"] for a in AXES) and all(square[p]["trusted"] for p in PAIRS)
    return Sphericity(value=value, stderr=float(np.std(draws)), unit="um", trusted=trusted,
                      reasons=list(dict.fromkeys(reasons)),
                      interval=[float(np.quantile(draws, 0.025)), float(np.quantile(draws, 0.975))], radius_mm=R)


def _axis_cov(loop: Loop) -> np.ndarray:
    """The covariance of the per-axis values, from the pairs' standard errors (as :func:`_per_axis` has it)."""
    have = [p for p in PAIRS if loop["pairs"][p]["value"] is not None]
    A = np.zeros((len(have) + 1, 3))
    sw = np.zeros(len(have) + 1)
    for i, p in enumerate(have):
        A[i, AXES.index(p[0])], A[i, AXES.index(p[1])] = 1.0, -1.0
        sw[i] = 1.0 / float(loop["pairs"][p]["stderr"])  # type: ignore[arg-type]
    A[-1] = 1.0
    sw[-1] = 1e6 * float(sw[:-1].max())
    Aw = A * sw[:, None]
    return np.asarray(np.linalg.inv(Aw.T @ Aw))


# --------------------------------------------------------------------------- the verdict


VERDICT_RULE = (
    "the worst of the plans' own verdicts (each test against its plan's limits); where a check of the set failed or "
    "a test of the set is invalid, at least warning and not trusted: the set's combined figures then contradict "
    "each other, and the set must be run again before its figures are used"
)


def _verdict(members: list[Member], checks: list[Check]) -> SetVerdict:
    plans = [PlanVerdict(plan=m["plan"], status=m["verdict"], summary=m["verdict_summary"]) for m in members]
    evaluated = [m["verdict"] for m in members if m["verdict"] in STATUS_RANK]
    status = max(evaluated, key=lambda s: STATUS_RANK[s]) if evaluated else "pass"
    failed = [c for c in checks if c["status"] == "failed"]
    invalid = [m for m in members if not m["valid"]]
    reasons = [c["message"] for c in failed]
    reasons += [f"plan {m['plan']}'s test {m['test_id']} is invalid: {'; '.join(m['invalid_reasons'])}"
                for m in invalid]
    trusted = not reasons
    if not trusted and STATUS_RANK[status] < STATUS_RANK["warning"]:
        status = "warning"
    parts = [f"{m['plan']} {m['verdict']}" for m in members]
    head = f"{status.upper()}: " + ", ".join(parts)
    tail = []
    if invalid:
        tail.append(f"invalid: {', '.join(m['plan'] for m in invalid)}")
    tail.insert(0, checks_words(checks))
    return SetVerdict(status=status, trusted=trusted, plans=plans,  # type: ignore[typeddict-item]
                      failed_checks=[c["name"] for c in failed], reasons=reasons,
                      summary=head + "; " + "; ".join(tail), rule=VERDICT_RULE)


# --------------------------------------------------------------------------- the set result


CONVENTIONS = {
    "axes": "X, Y, Z the machine's axes; each plane's first and second axis: XY (X, Y), YZ (Y, Z), ZX (Z, X)",
    "pairs": "each pair named in the right-handed cyclic order XY, YZ, ZX, as its plane's axes are",
    "lost_motion": "lost motion of the axis, um: a moving axis lags its command by half of it (negative: its "
                   "backlash compensation is set too high)",
    "squareness": "squareness of the pair ab, urad: positive when +a and +b enclose less than 90 deg "
                  "(the plane's squareness_urad)",
    "scale": "scale of the pair ab, ppm: e_a - e_b, a travels that much more than b per command "
             "(the plane's scale_mismatch_ppm); each axis: e_a against the mean of the three",
    "servo": "servo lag mismatch of the pair ab, ms: 1/K_a - 1/K_b, a lags b by that much (the plane's "
             "servo_mismatch_ms); each axis: its lag against the mean of the three",
}

METHOD = (
    "each quantity is the inverse-variance weighted mean of the tests that see it (their fitted values and standard "
    "errors); where two or more tests see it, their consistency is checked (their difference against its standard "
    "error); a loop's three pairwise values (scale, servo) must add to zero within their uncertainty (closure), and "
    "are then adjusted by least squares to close and turned into each axis' value against the three axes' mean. "
    "A test whose fit is invalid is listed but not combined. A check fails where the discrepancy is beyond "
    "coverage_k standard errors and above its minimum; a quantity whose check failed keeps its value, untrusted, its "
    "standard error inflated by the Birge ratio"
)

VOLUMETRIC_METHOD = (
    "largest circular deviation: the largest G(b) (ISO 230-4, about each test's least-squares circle) of the set's "
    "valid tests (a one-direction test: its G), standard uncertainty sqrt(2) x that test's residual RMS; a 220 deg "
    "arc shows less of a plane than a full circle. Geometric sphericity: the range R (lambda_max - lambda_min) of "
    "the radial deviation R n'E n over every direction n of the sphere of the set's largest radius R, E the "
    "symmetric linear error matrix of the set's three squareness errors (off-diagonal S/2) and each axis' relative "
    "scale (diagonal): the form error a best-fit sphere would show if the machine had only these six geometric "
    "errors (direction-dependent errors such as lost motion and servo lag are in the circular deviation, not here); "
    f"its standard uncertainty and 95 % interval from {SPHERE_DRAWS} draws of the inputs within their covariance"
)


def combine(definition: SetDefinition, tests: Mapping[str, Mapping[str, Any]], options: SetOptions | None = None,
            ) -> SetResult:
    """The set result from the test result of each of its plans (``{plan name: result}``).

    Every plan of the set must have a test (:func:`select` says whether they
    make the set); a plan's result is used as it is: its ``plan.plane`` says
    which axes it sees, its ``verdict`` (with limits on) is its plan's.
    """
    opt = options or SetOptions()
    missing = [p for p in definition.plans if p not in tests]
    if missing:
        raise PlanError(f"set {definition.name}: no test of plan {', '.join(missing)}")
    tests = {p: tests[p] for p in definition.plans}
    for p, r in tests.items():
        plane = (r.get("plan") or {}).get("plane")
        if plane not in PLANE_AXES:
            raise PlanError(f"set {definition.name}: plan {p}'s test names no plane ({plane!r})")
    checks: list[Check] = []
    lost = _observe(tests, _axis_fields("backlash_x_um", "backlash_y_um"))
    lost_motion = {a: _combine(f"the {a} lost motion", lost.get(a, []), "um", opt.min_lost_motion_um, opt, checks)
                   for a in AXES}
    sq = _observe(tests, _pair_field("squareness_urad"))
    squareness = {p: _combine(f"the {p} squareness", sq.get(p, []), "urad", opt.min_squareness_urad, opt, checks)
                  for p in PAIRS}
    scale = _loop("relative scale", "scale_mismatch_ppm", "ppm", tests, opt.min_scale_ppm, opt, checks)
    servo = _loop("servo lag mismatch", "servo_mismatch_ms", "ms", tests, opt.min_servo_ms, opt, checks)
    members = [_member(p, r) for p, r in tests.items()]
    times = [t for t in (_time(r) for r in tests.values()) if t is not None]
    span = (max(times) - min(times)).total_seconds() if times else None
    newest = max(tests.values(), key=lambda r: _time(r) or datetime.min.replace(tzinfo=UTC))
    return SetResult(
        kind="set",
        set_id=f"{definition.name}@{newest.get('test_id')}",
        set=SetInfo(name=definition.name, plans=list(definition.plans), window_s=float(definition.window_s)),
        tests=members,
        span_s=span,
        lost_motion=lost_motion,
        squareness=squareness,
        scale=scale,
        servo=servo,
        volumetric=Volumetric(largest_circular_deviation=_largest_deviation(tests),
                              geometric_sphericity=_sphericity(scale, squareness, tests), method=VOLUMETRIC_METHOD),
        checks=checks,
        verdict=_verdict(members, checks),
        conventions=dict(CONVENTIONS),
        method=METHOD,
    )


def _member(plan: str, r: Mapping[str, Any]) -> Member:
    valid, reasons = _test_validity(r)
    p = r.get("plan") or {}
    v = r.get("verdict")
    status = str(v.get("status")) if isinstance(v, Mapping) and v.get("limits") else "not_evaluated"
    g = (r.get("iso230_4") or {}).get("G_b_um")
    return Member(plan=plan, plane=str(p.get("plane")), test_id=r.get("test_id"), t_wall=r.get("t_wall"),
                  radius_mm=p.get("radius_mm"), feed_mm_min=p.get("feed_mm_min"), data_arc_deg=p.get("data_arc_deg"),
                  valid=valid, invalid_reasons=reasons, verdict=status,
                  verdict_summary=str(v.get("summary")) if isinstance(v, Mapping) else None,
                  G_b_um=float(g) if _finite(g) else None)


STATUS_WORDS = {"fail": "FAIL", "warning": "WARNING", "pass": "PASS", "none": "NO LIMITS SET"}


def checks_words(checks: Sequence[Mapping[str, Any]]) -> str:
    """The set's own checks in words apart from the plans' verdicts: they say whether the planes' figures agree,
    not whether the machine is within its limits (``FAIL ... 5 of 5 checks passed`` read as a contradiction)."""
    failed = [c for c in checks if c.get("status") == "failed"]
    if failed:
        names = ", ".join(str(c.get("name")) for c in failed)
        return f"{len(failed)} of {len(checks)} consistency checks failed ({names})"
    return f"the planes' figures agree ({len(checks)} of {len(checks)} consistency checks)"


def set_words(s: Mapping[str, Any]) -> dict[str, Any]:
    """The set's verdict in words, for the live view and the report: ``status`` (``pass``, ``warning``,
    ``fail``; ``none`` where no plan has limits and every check passed), ``word``, ``headline`` (one line:
    each plan's verdict, the checks), ``plans`` (``(plan, plane, status)``), ``problems`` (why not trusted)."""
    v = s.get("verdict") or {}
    members = s.get("tests") or []
    status = str(v.get("status", "pass"))
    if v.get("trusted", True) and members and all(m.get("verdict") == "not_evaluated" for m in members):
        status = "none"
    checks = s.get("checks") or []
    failed = [c for c in checks if c.get("status") == "failed"]
    parts = [f"{m.get('plan')} {STATUS_WORDS.get(str(m.get('verdict')), 'no limits').lower()}"
             + ("" if m.get("valid", True) else " (invalid)") for m in members]
    tail = (f"{len(failed)} of {len(checks)} consistency checks failed" if failed else checks_words(checks))
    name = (s.get("set") or {}).get("name", "?")
    return {"status": status, "word": STATUS_WORDS[status],
            "headline": f"set {name}: " + ", ".join(parts) + f"; {tail}",
            "plans": [(m.get("plan"), m.get("plane"), m.get("verdict")) for m in members],
            "problems": list(v.get("reasons") or [])}


def summary_lines(s: Mapping[str, Any]) -> list[str]:
    """The set result in a few readable lines (the log, ``ballbar analyze --set``)."""
    out = [f"Set {s['set']['name']} ({', '.join(s['set']['plans'])}): {s['verdict']['summary']}"]

    def fig(f: Mapping[str, Any]) -> str:
        if f.get("value") is None:
            return "-"
        text = measured(f["value"], f.get("stderr"), str(f.get("unit") or ""), with_unit=False, ascii=True)
        return f"{text}{'' if f.get('trusted') else ' (untrusted)'}"

    out.append("  lost motion um: " + ", ".join(f"{a} {fig(s['lost_motion'][a])}" for a in AXES))
    out.append("  squareness urad: " + ", ".join(f"{p} {fig(s['squareness'][p])}" for p in PAIRS))
    for key, what in (("scale", "relative scale ppm"), ("servo", "servo lag ms")):
        loop = s[key]
        out.append(f"  {what}: " + ", ".join(f"{p} {fig(loop['pairs'][p])}" for p in PAIRS)
                   + "; per axis " + ", ".join(f"{a} {fig(loop['axes'][a])}" for a in AXES))
    vol = s["volumetric"]
    lcd = vol["largest_circular_deviation"]
    out.append(f"  largest circular deviation {fig(lcd)} um ({lcd.get('plan') or '-'}), geometric sphericity "
               f"{fig(vol['geometric_sphericity'])} um")
    for c in s["checks"]:
        if c["status"] != "passed":
            out.append(f"  check {c['status']}: {c['message']}")
    return out


__all__ = [
    "AXES",
    "PAIRS",
    "Check",
    "Figure",
    "Selection",
    "SetDefinition",
    "SetOptions",
    "SetResult",
    "checks_words",
    "combine",
    "definitions",
    "plan_name",
    "select",
    "set_words",
    "sphericity_um",
    "summary_lines",
]
