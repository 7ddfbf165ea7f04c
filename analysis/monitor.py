"""Monitoring: acceptance limits, a verdict per test, robust trends, forecasts and alert states.

Pure: numbers in, dictionaries out, no clock, no files.  The daemon
(:mod:`ballbar.daemon.monitor`) keeps the history and publishes; ``ballbar
analyze`` and the report compute the same verdict offline from the same
``[limits]`` table.

Limits
------
``[limits]`` bounds, each an absolute bound on ``|value|`` (a negative backlash
is as bad as a positive one):

- ISO 230-4 figures: ``G_um`` (applies to ``G_ccw_um`` and ``G_cw_um``, each
  direction on its own), ``G_b_um``, ``H_um``;
- any result parameter by its name in ``parameters`` (``backlash_x_um = 8.0``).

Each limit has a warning level, ``warn_fraction`` of it (0.8 by default;
per limit in ``warn_fractions``).

The verdict
-----------
For each limited quantity, with ``x = |value|``, ``U = k * stderr`` (coverage
factor ``k``, 2 by default, about 95 %) and the limit ``L``:

- ``fail``: ``x - U > L``, the limit is exceeded beyond the value's uncertainty;
- ``warning`` and ``within_uncertainty``: ``|x - L| <= U``, the value is within
  its uncertainty of the limit, on either side: it may or may not exceed it;
- ``warning``: ``x`` above the warning level ``warn_fraction * L``;
- ``pass`` otherwise;
- ``not_evaluated``: the result has no value (a parameter left out as not
  identifiable, an ISO figure a one-direction test lacks); it says why.

The test's verdict is the worst evaluated status.  Uncertainties: a parameter's
is its standard error from the fit (the result says how it was computed).
ISO 230-4 figures carry none of their own: ``G`` and ``H`` are differences of
two points of the measured deviation, each off by the noise about the fitted
model, so their standard uncertainty is taken as ``sqrt(2) * sigma`` with
``sigma`` the fit's residual RMS (``residual_rms_um``).  That does not count the
upward bias of picking the extremes of noisy data (at most a few sigma), and the
verdict says so.

Trends and forecasts
--------------------
Per machine, plan and test conditions (the plan's name; plane, radius, feed, data arc, directions:
the report's trend selection), the history of each limited quantity over the
last ``trend_tests`` valid tests (and, if ``trend_days`` > 0, the last so many
days).  A test whose analysis warned about its own validity (a timing model
outside its range), whose measured feed is more than 10 % off the programmed
one, or whose quantity has no value never enters a trend; rejected tests have
no result at all.

The trend is Theil-Sen's: the median of the pairwise slopes, robust to a test in
five being an outlier, with Sen's distribution-free confidence interval of the
slope (Kendall's tau; ``confidence``, 0.95 by default).  Time is wall-clock days
between tests (``t_wall`` of the results).  The crossing date is where the trend
line reaches the bound it heads for (rule 4 below); its
interval comes from a bootstrap of the tests (``BOOTSTRAP`` resamples of the
points, each refitted by Theil-Sen; a resample whose slope does not head for
the bound never crosses: infinity), the percentiles at ``(1 -+ confidence)/2``.
The resamples' generator is seeded from the data: the same history gives the
same interval, live and offline.

A forecast (a crossing date and ``due``) is given only when all hold, in this
order (``reason`` says which did not):

1. the last test does not fail on the quantity (``|value| - k u > L``) and the
   trend line has not reached ``L``: what has happened is the verdict's;
2. at least ``min_tests`` points;
3. the slope is significant at :func:`slope_confidence`, Bonferroni's
   ``1 - (1 - confidence) / m`` over the ``m`` quantities watched together;
4. it moves ``|value|`` away from zero (the bound it heads for is ``+L`` for a
   positive trend value, ``-L`` for a negative one);
5. its change over the span is at least ``k`` x the values' median standard
   uncertainty;
6. the crossing interval's later bound is within ``horizon_days`` and within
   ``MAX_EXTRAPOLATION`` x the span of the tests (``reach_days``).

The crossing interval's early bound is never before the last test.

Alerts
------
:class:`AlertTracker` turns verdicts and forecasts into alerts without repeats:
one alert when the verdict worsens (``warning``, ``fail``; the first verdict
alerts unless it passes, as ``first verdict``), at once; when it
improves, only after ``clear_after`` tests in a row at the better state (a value
hovering at the warning level alerts once, not at every test); a forecast alert
per limit when it becomes due, and a ``clear`` one after ``clear_after`` tests
in a row that are clearly not due: the slope no longer significant, or even the
crossing's earlier bound beyond the horizon, or no crossing at all (heading
away, failing; a later bound wavering about the
horizon clears nothing).  Its state is a plain dict, kept across restarts by the
daemon.
"""

from __future__ import annotations

import hashlib
import math
import statistics
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np

from .errors import PlanError
from .numbers import measured

if TYPE_CHECKING:
    from ballbar.protocol.messages.monitor import Conditions, Forecast, HistoryEntry, LimitEntry, Status, Verdict

#: Test conditions that must match for results to share a trend (the report's selection too).
CONDITION_KEYS = ("plane", "radius_mm", "feed_mm_min", "data_arc_deg", "directions")
#: The plan of a result without a name (a single [plan], or one logged before plans were a library).
DEFAULT_PLAN = "default"
#: ISO 230-4 limits and the result fields (``iso230_4``) each applies to.
ISO_LIMITS: dict[str, tuple[str, ...]] = {
    "G_um": ("G_ccw_um", "G_cw_um"),
    "G_b_um": ("G_b_um",),
    "H_um": ("H_um",),
}
STATUSES = ("pass", "warning", "fail")
_RANK = {s: i for i, s in enumerate(STATUSES)}
MAX_FEED_DEVIATION = 0.1  # the engine's bound on a plausible measured feed (HINT_MAX_FEED_DEVIATION)
BOOTSTRAP = 1000
#: A forecast looks ahead at most this many times the span of the tests it rests on.
MAX_EXTRAPOLATION = 2.0
ISO_UNCERTAINTY = (
    "ISO 230-4 figures: standard uncertainty sqrt(2) x the fit's residual RMS (a difference of two measured "
    "points, each off by the noise about the model); the upward bias of taking extremes of noisy data is not "
    "counted"
)


# --------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class Limit:
    """One configured bound: ``name`` as configured, the result fields it applies to."""

    name: str
    bound: float
    warn_fraction: float
    fields: tuple[str, ...]
    group: str  # "iso230_4" or "parameters"

    @property
    def warning_level(self) -> float:
        return self.bound * self.warn_fraction


@dataclass(frozen=True)
class MonitorSettings:
    """The ``[limits]`` table as the monitor uses it (see the module docstring)."""

    limits: tuple[Limit, ...] = ()
    coverage_k: float = 2.0
    trend_tests: int = 20
    trend_days: float = 0.0
    min_tests: int = 6
    horizon_days: float = 30.0
    confidence: float = 0.95
    clear_after: int = 2

    @property
    def enabled(self) -> bool:
        return bool(self.limits)

    def quantities(self) -> list[tuple[Limit, str]]:
        """Every limited result field with its limit, in the configured order."""
        return [(lim, f) for lim in self.limits for f in lim.fields]

    def describe(self) -> list[str]:
        """One line per limit: what applies, for ``ballbar gcode`` and the report."""
        out = []
        for lim in self.limits:
            what = " and ".join(lim.fields) if lim.group == "iso230_4" else lim.name
            out.append(
                f"{what} <= {lim.bound:g} (warning above {lim.warning_level:g}, {100 * lim.warn_fraction:g} %)"
            )
        return out


def settings_from_dict(d: Mapping[str, Any]) -> MonitorSettings:
    """A :class:`MonitorSettings` from a ``[limits]`` table; ``enabled = false`` (the default) gives no limits.

    Raises :class:`PlanError` naming the key for a bad value.
    """
    d = dict(d)
    k = float(d.get("coverage_k", 2.0))
    warn = float(d.get("warn_fraction", 0.8))
    fractions = dict(d.get("warn_fractions") or {})
    params = dict(d.get("parameters") or {})
    checks = [
        (k > 0, f"limits.coverage_k must be > 0, not {k}"),
        (0 < warn <= 1, f"limits.warn_fraction must be within (0, 1], not {warn}"),
        (int(d.get("trend_tests", 20)) >= 3, "limits.trend_tests must be at least 3"),
        (float(d.get("trend_days", 0.0)) >= 0, "limits.trend_days must be >= 0 (0: no bound in days)"),
        (int(d.get("min_tests", 6)) >= 3, "limits.min_tests must be at least 3"),
        (float(d.get("horizon_days", 30.0)) > 0, "limits.horizon_days must be > 0"),
        (0.5 <= float(d.get("confidence", 0.95)) < 1, "limits.confidence must be within [0.5, 1)"),
        (int(d.get("clear_after", 2)) >= 1, "limits.clear_after must be at least 1"),
    ]
    for ok, message in checks:
        if not ok:
            raise PlanError(message)
    limits: list[Limit] = []
    known = {n for n in ISO_LIMITS if d.get(n) is not None} | set(params)
    for name, f in fractions.items():
        if name not in known:
            raise PlanError(f"limits.warn_fractions.{name}: no such limit configured "
                            f"(configured: {', '.join(sorted(known)) or 'none'})")
        if not (isinstance(f, int | float) and not isinstance(f, bool) and 0 < f <= 1):
            raise PlanError(f"limits.warn_fractions.{name} must be a number within (0, 1], not {f!r}")
    enabled = bool(d.get("enabled", False))
    for name, fields in ISO_LIMITS.items():
        v = d.get(name)
        if v is None:
            continue
        limits.append(Limit(name, _bound(f"limits.{name}", v), float(fractions.get(name, warn)), fields, "iso230_4"))
    for name, v in params.items():
        if not isinstance(name, str) or not name or name in ISO_LIMITS:
            raise PlanError(f"limits.parameters: bad name {name!r}")
        limits.append(Limit(name, _bound(f"limits.parameters.{name}", v), float(fractions.get(name, warn)),
                            (name,), "parameters"))
    return MonitorSettings(
        limits=tuple(limits) if enabled else (),
        coverage_k=k,
        trend_tests=int(d.get("trend_tests", 20)),
        trend_days=float(d.get("trend_days", 0.0)),
        min_tests=int(d.get("min_tests", 6)),
        horizon_days=float(d.get("horizon_days", 30.0)),
        confidence=float(d.get("confidence", 0.95)),
        clear_after=int(d.get("clear_after", 2)),
    )


def _bound(where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v) or v <= 0:
        raise PlanError(f"{where} must be a positive number (an absolute bound), not {v!r}")
    return float(v)


def check_parameter_names(settings: MonitorSettings, known: Iterable[str]) -> None:
    """A limit on a parameter the pattern library does not have is a mistake: :class:`PlanError` naming it."""
    names = set(known)
    for lim in settings.limits:
        if lim.group == "parameters" and lim.name not in names:
            raise PlanError(f"limits.parameters.{lim.name}: no such result parameter")


# --------------------------------------------------------------------------- the verdict


def quantity(result: Mapping[str, Any], lim: Limit, name: str) -> tuple[float | None, float | None, str | None]:
    """``(value, standard uncertainty, why not)`` of one limited field of a test result."""
    if lim.group == "parameters":
        p = result.get("parameters", {}).get(name)
        if p is None:
            return None, None, f"the result has no parameter {name}"
        v, se = p.get("value"), p.get("stderr")
        if v is None or not math.isfinite(v):
            return None, None, str(p.get("reason") or "not fitted")
        return float(v), (float(se) if se is not None and math.isfinite(se) else 0.0), None
    v = result.get("iso230_4", {}).get(name)
    if v is None or not math.isfinite(v):
        return None, None, f"no {name} for this test (its directions: {result.get('plan', {}).get('directions')})"
    sigma = result.get("residual_rms_um")
    if sigma is None:
        sigma = result.get("fit", {}).get("sigma_um")
    u = math.sqrt(2.0) * float(sigma) if sigma is not None and math.isfinite(sigma) else 0.0
    return float(v), u, None


def evaluate(result: Mapping[str, Any], settings: MonitorSettings) -> Verdict:
    """The test's verdict against the limits (see the module docstring)."""
    k = settings.coverage_k
    entries: list[LimitEntry] = []
    for lim, name in settings.quantities():
        v, u, why = quantity(result, lim, name)
        group = cast(Literal["parameters", "iso230_4"], lim.group)
        if v is None or u is None:
            entries.append({
                "name": name, "limit_name": lim.name, "group": group, "limit": lim.bound,
                "warn_fraction": lim.warn_fraction, "warning_level": lim.warning_level,
                "unit": _unit(result, lim, name), "status": "not_evaluated", "value": None, "stderr": None,
                "uncertainty": None, "margin": None, "within_uncertainty": False, "reason": why,
            })
            continue
        x, U = abs(v), k * u
        margin = lim.bound - x
        within = abs(margin) <= U
        status: Status
        if margin < -U:
            status = "fail"
        elif within or x > lim.warning_level:
            status = "warning"
        else:
            status = "pass"
        e: LimitEntry = {
            "name": name, "limit_name": lim.name, "group": group, "limit": lim.bound,
            "warn_fraction": lim.warn_fraction, "warning_level": lim.warning_level, "unit": _unit(result, lim, name),
            "status": status, "value": v, "stderr": u, "uncertainty": U, "margin": margin,
            "margin_pct": 100.0 * margin / lim.bound, "within_uncertainty": within,
        }
        if within:
            e["note"] = "within uncertainty of the limit"
        entries.append(e)
    evaluated: list[Status] = [e["status"] for e in entries if e["status"] != "not_evaluated"]
    worst: Status = max(evaluated, key=lambda s: _RANK[s]) if evaluated else "pass"
    return {
        "status": worst,
        "coverage_k": k,
        "rule": (f"fail: |value| - {k:g} u > limit (exceeded beyond its uncertainty, k = {k:g}); warning: within "
                 f"{k:g} u of the limit, or |value| above the warning level; u: the standard uncertainty"),
        "uncertainty": f"parameters: the fit's standard error; {ISO_UNCERTAINTY}",
        "limits": entries,
        "not_evaluated": sum(e["status"] == "not_evaluated" for e in entries),
        "summary": verdict_text(worst, entries, _plane_axes(result)),
    }


def _unit(result: Mapping[str, Any], lim: Limit, name: str) -> str:
    if lim.group == "parameters":
        return str(result.get("parameters", {}).get(name, {}).get("unit") or "")
    return "um"


def _plane_axes(result: Mapping[str, Any]) -> tuple[str, str]:
    from .plan import PLANE_AXES

    plan = result.get("plan")
    plane = plan.get("plane") if isinstance(plan, Mapping) else None
    return PLANE_AXES.get(str(plane), ("X", "Y"))


def verdict_text(status: str, entries: Sequence[Mapping[str, Any]], axes: tuple[str, str] = ("X", "Y")) -> str:
    """One line: the verdict and the limits that are not passed, in the view's words
    (:func:`ballbar.analysis.report.limit_words`: the quantity with the plane's axes, the limit, by how much)."""
    from .report import limit_words

    bad = [e for e in entries if e["status"] in ("warning", "fail")]
    if not entries:
        return "no limits"
    parts = []
    for e in bad:
        parts.append(limit_words(e, axes) + ("" if e.get("within_uncertainty") else f" ({e['status']})"))
    n_ok = sum(e["status"] == "pass" for e in entries)
    skipped = sum(e["status"] == "not_evaluated" for e in entries)
    tail = f"{n_ok} of {len(entries)} limits passed" + (f", {skipped} not evaluated" if skipped else "")
    return f"{status.upper()}: " + "; ".join([*parts, tail])


# --------------------------------------------------------------------------- trend history


def conditions(result: Mapping[str, Any]) -> Conditions:
    """The test conditions that select a trend: the plan's name (:data:`DEFAULT_PLAN` where a result has
    none, as before plans were a library) and :data:`CONDITION_KEYS` (the keys of Conditions)."""
    plan = result.get("plan", {})
    return cast("Conditions", {"plan": plan.get("name") or DEFAULT_PLAN, **{k: plan.get(k) for k in CONDITION_KEYS}})


def plan_of(result: Mapping[str, Any]) -> str:
    """The name of the plan a result (or a history entry's conditions) is about."""
    plan = result.get("plan")
    name = plan.get("name") if isinstance(plan, Mapping) else plan
    return str(name) if name else DEFAULT_PLAN


def condition_key(cond: Mapping[str, Any]) -> str:
    """A stable text key of the conditions (for grouping and storage): per plan, then per conditions."""
    return f"plan={plan_of(cond)!r};" + ";".join(f"{k}={cond.get(k)!r}" for k in CONDITION_KEYS)


def validity(result: Mapping[str, Any]) -> str | None:
    """Why a test result must not enter a trend, or None when it may."""
    if result.get("kind", "test") != "test":
        return f"a {result.get('kind')} result, not a test's"
    if result.get("warnings"):
        return f"the analysis warned: {result['warnings'][0]}"
    timing = result.get("timing", {})
    fed, prog = timing.get("measured_feed_mm_min"), result.get("plan", {}).get("feed_mm_min")
    if fed is None or prog is None or not math.isfinite(fed) or not prog:
        return "no measured feed"
    if abs(fed / prog - 1.0) > MAX_FEED_DEVIATION:
        return f"measured feed {fed:.1f} mm/min is more than {100 * MAX_FEED_DEVIATION:g} % off the programmed {prog:g}"
    return None


def history_entry(result: Mapping[str, Any], verdict: Mapping[str, Any] | None, t_wall: str) -> HistoryEntry:
    """What the trend keeps of one test: identity, time, conditions, validity and each limited value."""
    values: dict[str, list[float | None]] = {}
    for e in (verdict or {}).get("limits", []):
        if e.get("value") is not None:
            values[e["name"]] = [e["value"], e["stderr"]]
    return {
        "test_id": result.get("test_id"),
        "machine_id": result.get("machine_id"),
        "t_wall": t_wall,
        "conditions": conditions(result),
        "invalid": validity(result),
        "status": (verdict or {}).get("status"),
        "values": values,
    }


def parse_time(text: str) -> datetime:
    t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def time_text(t: datetime) -> str:
    return t.astimezone(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


def points(history: Sequence[Mapping[str, Any]], name: str, cond: Mapping[str, Any], settings: MonitorSettings,
           ) -> list[tuple[datetime, float, float, str]]:
    """``(time, value, stderr, test_id)`` of ``name`` over the trend window, oldest first.

    Only valid tests under the same conditions with a value enter; then the
    last ``trend_tests`` of them, and of those the ones within ``trend_days`` of
    the newest when that is set.
    """
    key = condition_key(cond)
    out = []
    for h in history:
        if h.get("invalid") or condition_key(h.get("conditions", {})) != key:
            continue
        v = h.get("values", {}).get(name)
        if v is None or v[0] is None or not h.get("t_wall"):
            continue
        out.append((parse_time(h["t_wall"]), float(v[0]), float(v[1] or 0.0), str(h.get("test_id"))))
    out.sort(key=lambda p: p[0])
    out = out[-settings.trend_tests:]
    if settings.trend_days > 0 and out:
        first = out[-1][0] - timedelta(days=settings.trend_days)
        out = [p for p in out if p[0] >= first]
    return out


# --------------------------------------------------------------------------- robust trend


@dataclass
class Trend:
    """Theil-Sen line ``y = value_at_pivot + slope * (t - pivot)``, t in days; Sen's interval of the slope."""

    n: int
    slope: float
    slope_lo: float
    slope_hi: float
    pivot: float  # days (the median time)
    value_at_pivot: float
    confidence: float

    @property
    def significant(self) -> bool:
        return self.n >= 3 and (self.slope_lo > 0 or self.slope_hi < 0)

    def at(self, t: float) -> float:
        return self.value_at_pivot + self.slope * (t - self.pivot)


def _norm_ppf(p: float) -> float:
    return statistics.NormalDist().inv_cdf(p)


def _pair_slopes(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    i, j = np.triu_indices(t.size, 1)
    dt = t[j] - t[i]
    ok = dt != 0
    return np.asarray((y[j] - y[i])[ok] / dt[ok])


def theil_sen(t: Sequence[float] | np.ndarray, y: Sequence[float] | np.ndarray, confidence: float = 0.95) -> Trend:
    """Theil-Sen slope with Sen's distribution-free confidence interval (Kendall's tau, no tie correction
    beyond the ties in time, which give no slope)."""
    t = np.asarray(t, dtype=float)
    y = np.asarray(y, dtype=float)
    n = t.size
    slopes = np.sort(_pair_slopes(t, y))
    if slopes.size == 0:
        return Trend(n, 0.0, -math.inf, math.inf, float(np.median(t)) if n else 0.0,
                     float(np.median(y)) if n else math.nan, confidence)
    b = float(np.median(slopes))
    pivot = float(np.median(t))
    a = float(np.median(y - b * (t - pivot)))
    z = _norm_ppf(0.5 + confidence / 2.0)
    var_s = n * (n - 1) * (2 * n + 5) / 18.0
    c = z * math.sqrt(var_s)
    m = slopes.size
    lo_i = round((m - c) / 2.0) - 1  # 0-based indices as scipy.stats.theilslopes takes them
    hi_i = round((m + c) / 2.0)
    lo = float(slopes[lo_i]) if lo_i >= 0 else -math.inf
    hi = float(slopes[hi_i]) if hi_i < m else math.inf
    return Trend(n, b, lo, hi, pivot, a, confidence)


def _seed(t: np.ndarray, y: np.ndarray) -> int:
    return int.from_bytes(hashlib.sha256(t.tobytes() + y.tobytes()).digest()[:8], "little")


def crossing_days(trend: Trend, bound: float) -> float:
    """When the trend line reaches ``+bound`` (rising) or ``-bound`` (falling), in days; inf when flat."""
    if trend.slope > 0:
        return trend.pivot + (bound - trend.value_at_pivot) / trend.slope
    if trend.slope < 0:
        return trend.pivot + (-bound - trend.value_at_pivot) / trend.slope
    return math.inf


def bootstrap_crossings(t: np.ndarray, y: np.ndarray, bound: float, direction: int, n_boot: int = BOOTSTRAP,
                        ) -> np.ndarray:
    """Crossing times (days) of Theil-Sen fits to ``n_boot`` resamples of the points; inf where a resample's
    slope does not head for the bound ``direction * bound``."""
    rng = np.random.default_rng(_seed(t, y))
    n = t.size
    idx = rng.integers(0, n, size=(n_boot, n))
    tb, yb = t[idx], y[idx]
    i, j = np.triu_indices(n, 1)
    dt = tb[:, j] - tb[:, i]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(dt != 0, (yb[:, j] - yb[:, i]) / dt, np.nan)
    with warnings.catch_warnings():  # a resample of one distinct time has no slope: NaN, never crossing
        warnings.simplefilter("ignore", RuntimeWarning)
        slope = np.nanmedian(s, axis=1)
    pivot = np.median(tb, axis=1)
    a = np.median(yb - slope[:, None] * (tb - pivot[:, None]), axis=1)
    target = direction * bound
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = pivot + (target - a) / slope
    heads = np.isfinite(slope) & (direction * slope > 0)
    return np.where(heads, tc, math.inf)


def slope_confidence(confidence: float, watched: int) -> float:
    """The slope interval's confidence for one of ``watched`` quantities: Bonferroni's ``1 - (1 - c) / m``, so
    that a constant machine forecasts any of its quantities at most ``1 - c`` of the time."""
    return 1.0 - (1.0 - confidence) / max(int(watched), 1)


def forecast(pts: Sequence[tuple[datetime, float, float, str]], lim: Limit, name: str, settings: MonitorSettings,
             watched: int | None = None) -> Forecast:
    """The trend of one limited quantity and where it crosses its limit: a JSON-ready dict.

    ``due``: whether the forecast alerts (the rule in the module docstring); ``reason`` says why not.
    ``watched``: how many quantities are watched together (Bonferroni; ``settings.quantities()`` by default).
    Times, only for a trend that heads for its limit and has not reached it: ``crossing`` (ISO UTC) with
    ``crossing_lo`` (never before the last test) and ``crossing_hi`` (null: never, within what the data
    say), and in days after the last test.
    """
    m = len(settings.quantities()) if watched is None else watched
    conf = slope_confidence(settings.confidence, m)
    out: Forecast = {"name": name, "limit_name": lim.name, "limit": lim.bound, "n": len(pts),
                     "min_tests": settings.min_tests, "horizon_days": settings.horizon_days,
                     "confidence": settings.confidence, "watched": m, "slope_confidence": conf, "method": (
                         "Theil-Sen slope with Sen's interval (Bonferroni over the watched quantities); crossing "
                         "interval from a bootstrap of the tests"),
                     "due": False, "crossing": None, "test_ids": [p[3] for p in pts]}
    if len(pts) < 3:
        out["reason"] = f"{len(pts)} valid tests under these conditions: a trend needs at least 3"
        return out
    t0 = pts[0][0]
    t = np.array([(p[0] - t0).total_seconds() / 86400.0 for p in pts])
    y = np.array([p[1] for p in pts])
    tr = theil_sen(t, y, conf)
    last, span = float(t[-1]), float(t[-1] - t[0])
    now = tr.at(last)
    out.update({"slope_per_day": tr.slope, "slope_lo": _finite(tr.slope_lo), "slope_hi": _finite(tr.slope_hi),
                "significant": tr.significant, "value_now": now, "first": time_text(t0),
                "last": time_text(pts[-1][0]), "span_days": span})
    # |value| is bounded: the trend heads for the limit only where it moves away from zero
    direction = 1 if (now > 0 or (now == 0 and tr.slope > 0)) else -1
    y_last, u_last = pts[-1][1], pts[-1][2]
    u_med = float(np.median([p[2] for p in pts]))
    rise = abs(tr.slope) * span
    if abs(y_last) - settings.coverage_k * u_last > lim.bound:
        out["reason"] = (f"it fails: the last test's {y_last:.3g} exceeds the limit {lim.bound:g} beyond its "
                         f"uncertainty (the verdict says so; no forecast)")
        return out
    if abs(now) >= lim.bound:
        out["reason"] = f"the trend is already at its limit ({now:.3g} against {lim.bound:g}; no forecast)"
        return out
    if len(pts) < settings.min_tests:
        out["reason"] = f"{len(pts)} valid tests under these conditions, fewer than min_tests = {settings.min_tests}"
        return out
    if not tr.significant:
        what = "quantity" if m == 1 else "quantities"
        out["reason"] = (f"the trend is flat within its scatter (slope {tr.slope:.3g}/day, {100 * conf:.3g} % "
                         f"interval {tr.slope_lo:.3g} .. {tr.slope_hi:.3g}, {m} {what} watched)")
        return out
    if direction * tr.slope < 0:
        out["reason"] = f"heading away from its limit (|value| falling, slope {tr.slope:.3g}/day)"
        return out
    if rise < settings.coverage_k * u_med:
        out["reason"] = (f"the trend changes {rise:.3g} over its {len(pts)} tests, less than {settings.coverage_k:g} "
                         f"x the values' standard uncertainty {u_med:.3g}")
        return out
    tc = crossing_days(tr, lim.bound)
    boot = bootstrap_crossings(t, y, lim.bound, direction)
    q = (1.0 - settings.confidence) / 2.0
    lo = max(float(np.quantile(boot, q, method="lower")), last)  # order statistics; never before the last test
    hi = float(np.quantile(boot, 1.0 - q, method="higher"))

    def when(d: float) -> str | None:
        return time_text(t0 + timedelta(days=d)) if math.isfinite(d) and abs(d) < 36500.0 else None

    out.update({"bound": direction * lim.bound, "crossing": when(tc), "crossing_lo": when(lo),
                "crossing_hi": when(hi), "days_to_crossing": (tc - last) if math.isfinite(tc) else None,
                "days_to_crossing_lo": lo - last,
                "days_to_crossing_hi": (hi - last) if math.isfinite(hi) else None})
    reach = min(settings.horizon_days, MAX_EXTRAPOLATION * span)
    if not math.isfinite(hi):
        out["reason"] = "the crossing's later bound is unbounded"
    elif hi - last > settings.horizon_days:
        out["reason"] = f"the crossing's later bound is beyond the horizon of {settings.horizon_days:g} days"
    elif hi - last > MAX_EXTRAPOLATION * span:
        out["reason"] = (f"the crossing's later bound is {hi - last:.3g} days ahead, beyond {MAX_EXTRAPOLATION:g} x "
                         f"the trend's span of {span:.3g} days")
    else:
        out["due"] = True
    out["reach_days"] = reach
    return out


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def forecast_words(f: Mapping[str, Any], label: str, unit: str = "") -> str:
    """One line of a forecast for a reader (the report, the viewer): the crossing date only where the forecast
    is due, else why there is none, so that the words say what the trend chart shows."""
    u = f" {unit}" if unit else ""
    n = f.get("n", 0)
    if "slope_per_day" not in f:
        return f"{label}: no trend yet ({f.get('reason', '')})"
    se = slope_stderr(f.get("slope_lo"), f.get("slope_hi"), float(f.get("slope_confidence") or f.get("confidence")
                                                                      or 0.95))
    slope = f"trend {measured(f['slope_per_day'], se, (unit or '') + '/day', signed=True)} over {n} tests"
    crossing = f.get("crossing")
    if f.get("due") and crossing:
        short = (f.get("reach_days") or 0.0) < 2.0  # a trend of hours: the hour matters

        def day(x: Any) -> str:
            return (str(x)[:16].replace("T", " ") if short else str(x)[:10]) if x else "never"

        bound = measured(f.get("bound", f["limit"]), None, unit, with_unit=False)
        return (f"{label}: {slope}, reaches its limit {bound}{u} about {day(crossing)} "
                f"({100 * f.get('confidence', 0.95):g} %: {day(f.get('crossing_lo'))} .. "
                f"{day(f.get('crossing_hi'))})")
    return f"{label}: {slope}: no forecast, {f.get('reason', 'not due')}"


def trend_line(x: Sequence[float], y: Sequence[float], ahead: float) -> tuple[list[float], list[float], bool] | None:
    """The Theil-Sen line through a trend's points (:func:`theil_sen`), from the first point to ``ahead``
    past the last: ``([x0, x_last, x_end], [y0, y_last, y_end], significant)``; None with fewer than 3 points."""
    if len(x) < 3:
        return None
    tr = theil_sen(x, y)
    xs = [float(x[0]), float(x[-1]), float(x[-1]) + ahead]
    return xs, [tr.at(v) for v in xs], tr.significant


def forecast_sentence(name: str, wall_s: Sequence[float] | np.ndarray, values: Sequence[float] | np.ndarray,
                      limit: float, axes: tuple[str, str] = ("X", "Y"), unit: str = "",
                      confidence: float = 0.95, stderrs: Sequence[float] | np.ndarray | None = None,
                      watched: int = 1, coverage_k: float = 2.0) -> str:
    """The monitor's forecast of ``name`` (values at wall-clock seconds, their standard uncertainties) against
    ``|limit|``, in words (:func:`forecast` and :func:`forecast_words`: a date only where the monitor would
    forecast one);
    ``watched``: the quantities watched together; empty with fewer than 3 tests."""
    from .report import quantity_label, unit_text

    t = np.asarray(wall_s, dtype=float)
    y = np.asarray(values, dtype=float)
    if t.size < 3:
        return ""
    u = np.zeros(t.size) if stderrs is None else np.nan_to_num(np.asarray(stderrs, dtype=float))
    lim = Limit(name, abs(float(limit)), 1.0, (name,), "parameters")
    settings = MonitorSettings(limits=(lim,), coverage_k=coverage_k, trend_tests=max(t.size, 3),
                               confidence=confidence)
    pts = [(datetime.fromtimestamp(float(w), UTC), float(v), float(e), str(i))
           for i, (w, v, e) in enumerate(zip(t, y, u, strict=True))]
    f = forecast(pts, lim, name, settings, watched=watched)
    return forecast_words(f, quantity_label(name, axes), unit_text(unit or name.rsplit("_", 1)[-1]))


# --------------------------------------------------------------------------- alerts


@dataclass
class AlertTracker:
    """Alert states of one machine; :meth:`update` per test gives the alerts to send (module docstring).

    ``state`` is JSON-ready (keep it across restarts): ``verdict`` (the
    alerted verdict), ``better`` (tests in a row better than it), ``forecast``
    (per limited field: ``due`` and ``quiet``, tests in a row not due).
    """

    clear_after: int = 2
    state: dict[str, Any] = field(default_factory=lambda: {"verdict": None, "better": [], "forecast": {}})

    def update(self, verdict: Mapping[str, Any] | None, forecasts: Sequence[Mapping[str, Any]],
               ) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        if verdict is not None:
            a = self._verdict(str(verdict["status"]))
            if a is not None:
                out.append(a)
        for f in forecasts:
            a = self._forecast(f)
            if a is not None:
                out.append(a)
        return out

    def _verdict(self, status: str) -> dict[str, Any] | None:
        st = self.state
        current = st.get("verdict")
        if current is None:  # the first verdict: nothing to compare with; a pass needs no alert
            st["verdict"], st["better"] = status, []
            if status == "pass":
                return None
            return {"alert": "verdict", "state": status, "previous": None, "cleared": False}
        if _RANK[status] > _RANK[current]:
            st["verdict"], st["better"] = status, []
            return {"alert": "verdict", "state": status, "previous": current, "cleared": False}
        if _RANK[status] == _RANK[current]:
            st["better"] = []
            return None
        better = [*st.get("better", []), status][-self.clear_after:]
        st["better"] = better
        if len(better) < self.clear_after:
            return None
        new = max(better, key=lambda s: _RANK[s])
        st["verdict"], st["better"] = new, []
        return {"alert": "verdict", "state": new, "previous": current, "cleared": new == "pass"}

    def _forecast(self, f: Mapping[str, Any]) -> dict[str, Any] | None:
        states = self.state.setdefault("forecast", {})
        s = states.setdefault(f["name"], {"due": False, "quiet": 0})
        if f.get("due"):
            s["quiet"] = 0
            if not s["due"]:
                s["due"] = True
                return {"alert": "forecast", "state": "due", "previous": "clear", "cleared": False, "limit": f["name"]}
            return None
        if not s["due"]:
            return None
        if not _clearly_not_due(f):
            s["quiet"] = 0  # the later bound wavers about the horizon: still possibly due, no clear
            return None
        s["quiet"] += 1
        if s["quiet"] < self.clear_after:
            return None
        s["due"], s["quiet"] = False, 0
        return {"alert": "forecast", "state": "clear", "previous": "due", "cleared": True, "limit": f["name"]}


def _clearly_not_due(f: Mapping[str, Any]) -> bool:
    """A due forecast's clearing rule, stricter than the due rule's negation (hysteresis): the slope is no
    longer significant, or even the crossing's earlier bound lies beyond the horizon."""
    if not f.get("significant") or f.get("crossing") is None:  # flat, heading away, failing or at its limit
        return True
    lo, horizon = f.get("days_to_crossing_lo"), f.get("horizon_days")
    return lo is None or (isinstance(horizon, int | float) and lo > horizon)


def slope_stderr(lo: Any, hi: Any, confidence: float) -> float | None:
    """A trend slope's standard error from Sen's interval ``lo .. hi`` at ``confidence`` (its half width over the
    normal quantile): what the rounding rule shows a slope to; None without a finite interval."""
    if isinstance(lo, int | float) and isinstance(hi, int | float) and math.isfinite(lo) and math.isfinite(hi):
        return (hi - lo) / (2.0 * _norm_ppf(0.5 + confidence / 2.0))
    return None


def alert_text(alert: Mapping[str, Any]) -> str:
    """One readable line of an alert message."""
    m = alert.get("machine_id", "?")
    plan = plan_of(alert.get("conditions") or {})
    if plan != DEFAULT_PLAN:  # a library of plans: whose alert
        m = f"{m} plan {plan}"
    if alert.get("alert") == "verdict":
        v = alert.get("verdict") or {}
        change = (f"verdict {alert['previous']} -> {alert['state']}" if alert.get("previous") is not None
                  else f"first verdict: {alert['state']}")
        head = f"{m}: {change}" + (" (cleared)" if alert.get("cleared") else "")
        return f"{head} at test {alert.get('test_id')}: {v.get('summary', '')}"
    f = alert.get("forecast") or {}
    if alert.get("state") == "clear":
        return (f"{m}: forecast for {alert.get('limit')} cleared at test {alert.get('test_id')}: "
                f"{f.get('reason', 'no longer due')}")
    from .numbers import measured
    from .report import quantity_label, unit_text

    name = str(f.get("name") or alert.get("limit") or "")
    unit = "um" if name in ISO_LIMITS or name.startswith("G_") else name.rsplit("_", 1)[-1]
    axes = _plane_axes({"plan": alert.get("conditions") or {}})
    slope, lo, hi = (f.get(k) for k in ("slope_per_day", "slope_lo", "slope_hi"))
    conf = float(f.get("confidence") or 0.95)
    se = slope_stderr(lo, hi, conf)
    bound = f.get("bound", math.nan)
    # the limit is the quantity's (um), not the slope's (um/day): at its unit's resolution, as the verdict shows it
    lim_t = measured(abs(bound) if isinstance(bound, int | float) else None, None, unit, with_unit=False)
    side = "-" if isinstance(bound, int | float) and bound < 0 else ""
    return (f"{m}: {quantity_label(name, axes)} trend {measured(slope, se, f'{unit}/day', signed=True)} crosses "
            f"its limit {side}{lim_t} {unit_text(unit)} on {f.get('crossing')} "
            f"({100 * conf:g} %: {f.get('crossing_lo')} .. {f.get('crossing_hi')}), from {f.get('n')} tests to "
            f"{alert.get('test_id')}")


__all__ = [
    "CONDITION_KEYS",
    "DEFAULT_PLAN",
    "ISO_LIMITS",
    "AlertTracker",
    "Limit",
    "MonitorSettings",
    "Trend",
    "alert_text",
    "bootstrap_crossings",
    "check_parameter_names",
    "condition_key",
    "conditions",
    "crossing_days",
    "evaluate",
    "forecast",
    "forecast_sentence",
    "forecast_words",
    "history_entry",
    "plan_of",
    "points",
    "settings_from_dict",
    "slope_confidence",
    "slope_stderr",
    "theil_sen",
    "trend_line",
    "validity",
]
