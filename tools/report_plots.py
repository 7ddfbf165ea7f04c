"""The report's plots: the polar plot, the deviation against angle, and the trend (matplotlib, SVG and PNG).

Deviations are drawn with the set-up terms of the fit (pivot offset ``centre_*_um`` and bar length
``radius_um``) removed from the measured and the model curves alike, as commercial ball-bar software
draws them and as the daemon's live view does: what is left is the machine.  In the polar plot a
deviation ``dR`` is drawn at ``1 + dR / (10 s)`` times the reference circle, ``s`` the scale in um per
division (a round 1, 2, 5 x 10^n chosen so that the test fits in three divisions,
:func:`~ballbar.analysis.report.polar_division_um`); the rings mark the divisions, the outermost holds
every point.  Curves are decimated for drawing with a min/max envelope over consecutive samples, so a
one-sample spike survives and a 1 kHz test stays a few hundred kilobytes.

The trend: one small plot per key figure, the machine's tests on a test axis (each tick its test number
and date), each point with its uncertainty (``k u``, the verdict's coverage factor), the limit and the
warning level where limits are set, and the Theil-Sen trend line carried a quarter of the history ahead
(the forecast).

matplotlib draws through explicit ``Figure`` objects on the Agg canvas, never ``pyplot``: importing this
module or rendering changes no global backend and opens no window, which matters inside the daemon and in
tests.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import html
import io
import logging
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ballbar.analysis.monitor import trend_line
from ballbar.analysis.patterns import LIBRARY
from ballbar.analysis.plan import PLANE_AXES
from ballbar.analysis.report import (
    LIBRARY_FIELDS,
    POLAR_DIVISIONS,
    field_label,
    pattern_label,
    polar_division_um,
    quantity_label,
    trend_range,
    unit_text,
)

from .report import ReportData

if TYPE_CHECKING:
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

#: Colours of the two directions (CCW blue, CW red as in common ball-bar software) and their models.
COLOURS = {"ccw": "#1f5fbf", "cw": "#d0342c"}
MODEL_COLOURS = {"ccw": "#0a2350", "cw": "#5c0d09"}
DIRECTION_NAMES = {"ccw": "CCW", "cw": "CW"}
#: Verdict colours (the report's banner and the trend's limit lines; the live view uses the same).
STATUS_COLOURS = {"fail": "#b42318", "warning": "#b25e09", "pass": "#1d7a46", "none": "#5b6472"}
#: The fitted model's line style in both plots: dashed, so that it is told from the measured curve (solid)
#: where the two lie on each other, as they do where the fit is good.
MODEL_DASH = (0, (4, 2))
#: Drawn points per direction for the measured curves (min/max envelope), the model and the residual.
MEASURED_POINTS = 2000
MODEL_POINTS = 1000
#: Share of the reference circle's radius that one division of the polar plot takes.
POLAR_DIVISION = 0.1
PNG_DPI = 150
TREND_AHEAD = 0.25  # the trend line is carried this share of the history (in tests, at least 3) ahead


# --------------------------------------------------------------------------- small helpers


def num(v: Any) -> float | None:
    """A finite float, or None for anything else (None, NaN, inf, text): what the report can print."""
    if isinstance(v, bool) or v is None:
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def parse_time(t: Any) -> dt.datetime | None:
    """A result's ``t_wall`` (ISO 8601 text or Unix seconds) as an aware UTC datetime."""
    if t is None or isinstance(t, bool):
        return None
    if isinstance(t, int | float):
        return dt.datetime.fromtimestamp(float(t), dt.UTC) if math.isfinite(float(t)) else None
    try:
        d = dt.datetime.fromisoformat(str(t).strip())
    except ValueError:
        return None
    return d.replace(tzinfo=dt.UTC) if d.tzinfo is None else d.astimezone(dt.UTC)


def plane_axes(plan: Mapping[str, Any]) -> tuple[str, str]:
    return PLANE_AXES.get(str(plan.get("plane", "XY")), ("X", "Y"))


def param(result: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    p = (result.get("parameters") or {}).get(key)
    return p if isinstance(p, Mapping) else {}


def pvalue(result: Mapping[str, Any], key: str) -> float | None:
    return num(param(result, key).get("value"))


def um_text(x: float) -> str:
    return f"{x:g}"


# --------------------------------------------------------------------------- curves


def envelope_indices(y: np.ndarray, max_points: int) -> np.ndarray:
    """Indices of ``y`` to draw: all of them when few, else each run's min and max, in order.

    Consecutive samples are split into ``max_points // 2`` runs and each run
    keeps its smallest and largest sample, so a one-sample spike is drawn at
    its full height however far the curve is thinned (plain striding would
    drop it).  The indices ascend, so the curve keeps its order of travel.
    """
    n = int(y.size)
    if n <= max_points:
        return np.arange(n)
    bins = max(max_points // 2, 1)
    edges = np.linspace(0, n, bins + 1).astype(int)
    keep = np.empty(2 * bins, dtype=int)
    for i in range(bins):
        a, b = edges[i], edges[i + 1]
        seg = y[a:b]
        keep[2 * i] = a + int(np.argmin(seg))
        keep[2 * i + 1] = a + int(np.argmax(seg))
    return np.unique(keep)


@dataclass
class Curve:
    """One direction's data arc ready to draw: angle (rad), deviations with the set-up removed (um)."""

    name: str  # "ccw" or "cw"
    u_rad: np.ndarray
    measured_um: np.ndarray
    model_um: np.ndarray | None

    @property
    def residual_um(self) -> np.ndarray | None:
        return None if self.model_um is None else self.measured_um - self.model_um


def _setup_um(result: Mapping[str, Any], u: np.ndarray) -> np.ndarray:
    """The fit's set-up terms at angles ``u``: pivot offset and bar length (0 where not fitted)."""
    x0, y0, c = (pvalue(result, k) or 0.0 for k in ("centre_x_um", "centre_y_um", "radius_um"))
    return np.asarray(x0 * np.cos(u) + y0 * np.sin(u) + c)


def curves_of(data: ReportData) -> list[Curve]:
    out = []
    for name in ("ccw", "cw"):
        c = (data.curves or {}).get(name)
        if not c or "u_deg" not in c or "measured_um" not in c:
            continue
        u = np.radians(np.asarray(c["u_deg"], dtype=float))
        meas = np.asarray(c["measured_um"], dtype=float)
        model = np.asarray(c["model_um"], dtype=float) if c.get("model_um") is not None else None
        if model is not None and model.shape != meas.shape:
            log.warning("the %s model curve has %d samples for %d measured: not drawn", name, model.size, meas.size)
            model = None
        ok = np.isfinite(u) & np.isfinite(meas)
        if model is not None:
            ok &= np.isfinite(model)
        if not ok.any():
            continue
        u, meas = u[ok], meas[ok]
        setup = _setup_um(data.result, u)
        out.append(Curve(name, u, meas - setup, None if model is None else model[ok] - setup))
    return out


def polar_scale_um(max_abs_um: float) -> float:
    """The polar plot's division (:func:`~ballbar.analysis.report.polar_division_um`)."""
    return polar_division_um(max_abs_um)


# --------------------------------------------------------------------------- figures


@contextlib.contextmanager
def style(salt: str) -> Iterator[None]:
    """matplotlib settings for one figure, restored afterwards (nothing global changes).

    ``rc_context`` swaps the process-wide rcParams for the duration: two threads drawing with
    matplotlib at once would see each other's settings, so render reports from one thread.
    """
    try:
        import matplotlib as mpl
    except ImportError as err:  # a clear message instead of a bare traceback from deep inside
        raise ImportError("the report's plots need matplotlib (pip install 'matplotlib>=3.8')") from err

    with mpl.rc_context({
        "font.family": "sans-serif",
        "font.sans-serif": ["DejaVu Sans", "Liberation Sans", "Arial", "Helvetica"],
        "font.size": 9.0,
        "axes.titlesize": 10.0,
        "axes.labelsize": 9.0,
        "axes.edgecolor": "#555555",
        "axes.linewidth": 0.8,
        "axes.grid": False,
        "xtick.color": "#333333",
        "ytick.color": "#333333",
        "legend.frameon": False,
        "svg.fonttype": "none",  # text stays text: small, selectable, searchable
        "svg.hashsalt": salt,  # clip-path ids stable and distinct per figure
        "path.simplify": False,  # the envelope already thinned the curves; keep every kept spike
        "axes.formatter.useoffset": False,  # tick labels say the value itself, not an offset above the axis
    }):
        yield


def _new_figure(w_in: float, h_in: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w_in, h_in), layout="constrained")
    FigureCanvasAgg(fig)  # the raster canvas, explicitly: no pyplot, no GUI backend
    return fig
def polar_figure(curves: Sequence[Curve], axes: tuple[str, str], g_text: str) -> tuple[Figure, float]:
    """Both directions around a reference circle, the model over each; returns the figure and its scale."""
    allv = [c.measured_um for c in curves] + [c.model_um for c in curves if c.model_um is not None]
    max_abs = max((float(np.max(np.abs(v))) for v in allv if v.size), default=0.0)
    div = polar_division_um(max_abs)
    n_div = max(1, math.ceil(max_abs / div - 1e-9))
    k = POLAR_DIVISION / div
    fig = _new_figure(6.2, 6.6)
    ax = fig.add_subplot()
    ax.set_aspect("equal")
    ax.axis("off")
    t = np.linspace(0.0, 2.0 * math.pi, 721)
    r_out = 1.0 + POLAR_DIVISION * n_div
    for i in range(-n_div, n_div + 1):
        r = 1.0 + POLAR_DIVISION * i
        main = i == 0
        ax.plot(r * np.cos(t), r * np.sin(t), color="#444444" if main else "#c9ced6",
                lw=1.0 if main else 0.6, zorder=1,
                gid="polar-reference" if main else ("polar-outer-ring" if i == n_div else None))
        if not main:
            at = math.radians(67.5)
            ax.annotate(f"{i * div:+g}" + (" µm" if i == n_div else ""), xy=(r * math.cos(at), r * math.sin(at)),
                        fontsize=6.5, color="#6b7380", ha="center", va="center", zorder=4,
                        bbox={"boxstyle": "round,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.8})
    for ang in range(0, 360, 45):
        a = math.radians(ang)
        ax.plot([0.0, r_out * math.cos(a)], [0.0, r_out * math.sin(a)], color="#d5d9df",
                lw=0.5 if ang % 90 else 0.8, zorder=0)
    labels = {0: f"+{axes[0]}", 90: f"+{axes[1]}", 180: f"−{axes[0]}", 270: f"−{axes[1]}"}
    for ang, text in labels.items():
        a = math.radians(ang)
        rr = r_out + 0.1
        ax.text(rr * math.cos(a), rr * math.sin(a), f"{text}\n{ang}°", ha="center", va="center",
                fontsize=9.5, fontweight="bold", color="#222222", linespacing=1.1, gid=f"polar-axis-{ang}")
    for c in curves:
        idx = envelope_indices(c.measured_um, MEASURED_POINTS)
        r = 1.0 + k * c.measured_um[idx]
        u = c.u_rad[idx]
        ax.plot(r * np.cos(u), r * np.sin(u), color=COLOURS[c.name], lw=1.1, zorder=2,
                label=f"{DIRECTION_NAMES[c.name]} measured", gid=f"polar-{c.name}")
    for c in curves:
        if c.model_um is None:
            continue
        idx = envelope_indices(c.model_um, MODEL_POINTS)
        r = 1.0 + k * c.model_um[idx]
        u = c.u_rad[idx]
        ax.plot(r * np.cos(u), r * np.sin(u), color=MODEL_COLOURS[c.name], lw=0.8, ls=MODEL_DASH, zorder=3,
                label=f"{DIRECTION_NAMES[c.name]} model", gid=f"polar-{c.name}-model")
    lim = r_out + 0.25
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.text(-lim, -lim, f"Scale {um_text(div)} µm/div", fontsize=9, ha="left", va="bottom", color="#222222",
            gid="polar-scale")
    ax.text(lim, -lim, g_text, fontsize=9, ha="right", va="bottom", color="#222222")
    if curves:
        fig.legend(loc="outside lower center", ncol=4, fontsize=8.5, handlelength=1.8)
    return fig, div


@dataclass
class AngleAxis:
    """How the deviation plot's x axis shows angles.

    A full circle is drawn over 0..360 deg, broken where the arc passes 0.  A
    partial arc (220 deg in a vertical plane) is drawn continuously over its
    own span, shifted by whole turns so that it starts within 0..360, and
    labelled modulo 360: no empty half plot, no break in the middle.
    """

    lo: float
    hi: float
    shift_deg: float | None  # None: full circle, wrapped into 0..360

    @classmethod
    def of(cls, curves: Sequence[Curve]) -> AngleAxis:
        u = np.degrees(np.concatenate([c.u_rad for c in curves])) if curves else np.zeros(1)
        lo, hi = float(u.min()), float(u.max())
        if hi - lo >= 359.0:
            return cls(0.0, 360.0, None)
        shift = 360.0 * math.floor(lo / 360.0)
        return cls(lo - shift, hi - shift, shift)

    def x(self, u_rad: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        deg = np.degrees(u_rad)
        if self.shift_deg is not None:
            return deg - self.shift_deg, y.astype(float)
        x = np.mod(deg, 360.0)
        jumps = np.flatnonzero(np.abs(np.diff(x)) > 180.0) + 1
        return np.insert(x, jumps, np.nan), np.insert(y.astype(float), jumps, np.nan)

    def ticks(self, ax: Any, axes: tuple[str, str]) -> None:
        names = {0: f"+{axes[0]}", 90: f"+{axes[1]}", 180: f"−{axes[0]}", 270: f"−{axes[1]}"}
        ticks = [t for t in range(math.ceil(self.lo / 45) * 45, math.floor(self.hi / 45) * 45 + 1, 45)]
        ax.set_xticks(ticks)
        ax.set_xticklabels([f"{t % 360}°\n{names[t % 360]}" if t % 360 in names else f"{t % 360}°" for t in ticks])
        ax.set_xlim(self.lo, self.hi)


def deviation_figure(curves: Sequence[Curve], axes: tuple[str, str]) -> Figure:
    """Deviation against angle for both directions with the model, and the fit's residual below."""
    has_res = any(c.model_um is not None for c in curves)
    angle = AngleAxis.of(curves)
    fig = _new_figure(10.0, 4.9 if has_res else 3.6)
    if has_res:
        top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[3, 1.25])
    else:
        top, bottom = fig.add_subplot(), None
    for c in curves:
        idx = envelope_indices(c.measured_um, MEASURED_POINTS)
        x, y = angle.x(c.u_rad[idx], c.measured_um[idx])
        top.plot(x, y, color=COLOURS[c.name], lw=0.9, label=f"{DIRECTION_NAMES[c.name]} measured",
                 gid=f"deviation-{c.name}")
    for c in curves:
        if c.model_um is None:
            continue
        idx = envelope_indices(c.model_um, MODEL_POINTS)
        x, y = angle.x(c.u_rad[idx], c.model_um[idx])
        top.plot(x, y, color=MODEL_COLOURS[c.name], lw=0.7, ls=MODEL_DASH,
                 label=f"{DIRECTION_NAMES[c.name]} model", gid=f"deviation-{c.name}-model")
    top.axhline(0.0, color="#888888", lw=0.6, zorder=0)
    top.set_ylabel("deviation (µm)")
    top.grid(True, color="#e3e6ea", lw=0.5)
    if curves:
        fig.legend(loc="outside upper center", ncol=4, fontsize=8.5, handlelength=1.8)
    if bottom is not None:
        for c in curves:
            res = c.residual_um
            if res is None:
                continue
            idx = envelope_indices(res, MEASURED_POINTS)
            x, y = angle.x(c.u_rad[idx], res[idx])
            bottom.plot(x, y, color=COLOURS[c.name], lw=0.5, alpha=0.75, gid=f"deviation-residual-{c.name}")
        bottom.axhline(0.0, color="#888888", lw=0.6, zorder=0)
        bottom.set_ylabel("residual (µm)")
        bottom.grid(True, color="#e3e6ea", lw=0.5)
        angle.ticks(bottom, axes)
        bottom.set_xlabel("angle (counter-clockwise from +" + axes[0] + ")")
    else:
        angle.ticks(top, axes)
        top.set_xlabel("angle (counter-clockwise from +" + axes[0] + ")")
    return fig



# --------------------------------------------------------------------------- trend


@dataclass
class Quantity:
    """A trended figure: ``key`` a parameter field, or ``G`` for the circularity (G(b), else one direction's G)."""

    key: str
    label: str
    unit: str
    limit: float | None = None  # the limit on |value| where one is set, and its warning level
    warning: float | None = None
    limit_key: str = ""  # the limit's name in the verdict (``G_b_um``, ``backlash_x_um``)
    extra: dict[str, Any] = field(default_factory=dict)


def g_of(result: Mapping[str, Any]) -> tuple[float | None, str, str]:
    """The test's circularity: G(b) when both directions ran, else the one direction's G; value, name, key."""
    iso = result.get("iso230_4") or {}
    for key, name in (("G_b_um", "G(b)"), ("G_ccw_um", "G CCW"), ("G_cw_um", "G CW")):
        v = num(iso.get(key))
        if v is not None:
            return v, name, key
    return None, "G(b)", "G_b_um"


def _limits_of(result: Mapping[str, Any]) -> dict[str, tuple[float, float | None]]:
    """Limit and warning level per limited field of the result's verdict."""
    out: dict[str, tuple[float, float | None]] = {}
    v = result.get("verdict")
    for e in (v.get("limits") or []) if isinstance(v, Mapping) else []:
        lim = num(e.get("limit")) if isinstance(e, Mapping) else None
        if lim is not None:
            out[str(e.get("name"))] = (lim, num(e.get("warning_level")))
    return out


def coverage_k(result: Mapping[str, Any]) -> float:
    """The verdict's coverage factor (2 without a verdict): error bars are ``k u``."""
    v = result.get("verdict")
    return (num(v.get("coverage_k")) if isinstance(v, Mapping) else None) or 2.0


def trend_quantities(tests: Sequence[Mapping[str, Any]], axes: tuple[str, str]) -> list[Quantity]:
    """The circularity, each limited quantity, and each machine parameter significant in any of the tests.

    Reversal spikes (eight fields) and phases are left to the findings table: a trend of each would bury
    the few figures an engineer tracks.  Limits are those of the newest test's verdict.
    """
    limits = _limits_of(tests[-1])
    _g, gname, gkey = g_of(tests[-1])
    lim = limits.get(gkey)
    out = [Quantity("G", "Circularity " + gname, "µm", lim[0] if lim else None, lim[1] if lim else None, gkey)]
    for pat in LIBRARY:
        if pat.kind != "machine":
            continue
        for key in LIBRARY_FIELDS[pat.name]:
            if key.endswith("_phase_deg"):
                continue
            if key in limits or any(param(r, key).get("significant") and num(param(r, key).get("value")) is not None
                                    for r in tests):
                fl = field_label(key, axes)
                label = pattern_label(pat.name, axes) + (f" {fl}" if fl else "")
                unit = unit_text(next((param(r, key).get("unit") for r in tests if param(r, key).get("unit")), ""))
                lim = limits.get(key)
                out.append(Quantity(key, label, unit, lim[0] if lim else None, lim[1] if lim else None, key))
    return out


def trend_value(r: Mapping[str, Any], q: Quantity) -> tuple[float | None, float | None, bool]:
    """A test's value of ``q``, its standard uncertainty and whether it is significant.  The circularity's
    uncertainty is the verdict's: sqrt(2) x the fit's residual RMS (analysis/monitor.py)."""
    if q.key == "G":
        rms = num(r.get("residual_rms_um"))
        return g_of(r)[0], math.sqrt(2.0) * rms if rms is not None else None, True
    p = param(r, q.key)
    return num(p.get("value")), num(p.get("stderr")), bool(p.get("significant"))


def _tick_positions(n: int, most: int = 6) -> list[int]:
    step = max(1, math.ceil(n / most))
    ticks = list(range(1, n + 1, step))
    if ticks[-1] != n:
        ticks.append(n)
    return ticks


def trend_figure(tests: Sequence[Mapping[str, Any]], quantities: Sequence[Quantity]) -> Figure:
    """One plot per quantity against the test (1 = the oldest shown; each tick its date below)."""
    from matplotlib.ticker import FixedLocator, NullLocator

    n = len(tests)
    xs = np.arange(1, n + 1, dtype=float)
    dates = [parse_time(r.get("t_wall")) for r in tests]
    k = coverage_k(tests[-1])
    ncols = 1 if len(quantities) == 1 else 2
    nrows = math.ceil(len(quantities) / ncols)
    fig = _new_figure(8.0, 0.3 + 2.3 * nrows)
    grid = fig.subplots(nrows, ncols, squeeze=False)
    ticks = _tick_positions(n)
    labels = [f"{t}\n{d.strftime('%m-%d')}" if (d := dates[t - 1]) is not None else str(t) for t in ticks]
    for i, q in enumerate(quantities):
        ax = grid[i // ncols][i % ncols]
        vals = [trend_value(r, q) for r in tests]
        pts = [(x, v, s, sig) for x, (v, s, sig) in zip(xs, vals, strict=True) if v is not None]
        lines: list[float] = []
        if q.limit is not None:
            mean = float(np.mean([p[1] for p in pts])) if pts else 0.0
            side = -1.0 if mean < 0 else 1.0
            ax.axhline(side * q.limit, color=STATUS_COLOURS["fail"], lw=1.1, zorder=2, gid=f"trend-{q.key}-limit")
            lines.append(side * q.limit)
            if q.warning is not None:
                ax.axhline(side * q.warning, color=STATUS_COLOURS["warning"], lw=0.9, ls=(0, (4, 2)), zorder=2)
                lines.append(side * q.warning)
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], color="#8a94a3", lw=0.8, zorder=3)
        xe, ye, ee, ce, fe = [], [], [], [], []
        for j, (x, v, s, sig) in enumerate(pts):
            current = j == len(pts) - 1 and vals[-1][0] is not None
            colour = "#1f5fbf" if current else "#4b5563"
            xe.append(x)
            ye.append(v)
            ee.append(k * s if s is not None else 0.0)
            ce.append(colour)
            fe.append(colour if sig else "white")
        if pts:
            ax.errorbar(xe, ye, yerr=ee, fmt="none", ecolor="#8a94a3", elinewidth=0.8, capsize=2, zorder=4)
            ax.scatter(xe, ye, s=[30 if c == "#1f5fbf" else 18 for c in ce], c=fe, edgecolors=ce, linewidths=1.0,
                       zorder=5, gid=f"trend-{q.key}-points")
        line = trend_line([p[0] for p in pts], [p[1] for p in pts], max(3.0, TREND_AHEAD * n))
        if line is not None:
            lx, ly, significant = line
            ax.plot(lx[:2], ly[:2], color="#1f5fbf", lw=0.9, alpha=0.6, zorder=3)
            ax.plot(lx[1:], ly[1:], color="#1f5fbf", lw=1.1, ls=(0, (2, 2)), alpha=0.9 if significant else 0.45,
                    zorder=3, gid=f"trend-{q.key}-forecast")
        rng = trend_range([v for v, _s, _g in vals], [s for _v, s, _g in vals], k, lines)
        if rng is not None and rng[1] > rng[0]:
            ax.set_ylim(*rng)
        ax.set_xlim(0.5, n + 0.5 + (max(3.0, TREND_AHEAD * n) if line is not None else 0.0))
        ax.xaxis.set_major_locator(FixedLocator(ticks))
        ax.set_xticklabels(labels)
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set_title(f"{q.label} ({q.unit})" if q.unit else q.label, fontsize=9.5, loc="left")
        ax.grid(True, color="#e3e6ea", lw=0.5)
        ax.tick_params(labelsize=8.5)
        ax.set_gid(f"trend-{q.key}")
        ax.patch.set_gid(f"trend-{q.key}-area")
    for j in range(len(quantities), nrows * ncols):
        grid[j // ncols][j % ncols].set_visible(False)
    return fig


def trend_caption(quantities: Sequence[Quantity], k: float, axes: tuple[str, str]) -> str:
    """What the trend plot shows, in words (no configuration keys)."""
    limited = [q.label for q in quantities if q.limit is not None]
    lim = (f" Red: the limit; amber dashed: the warning level ({', '.join(limited)})." if limited
           else " No limits set: no limit lines.")
    return ("Each test of this machine under the same conditions, oldest first (the tick says the test's number "
            f"and date); filled markers significant, hollow not; bars ± {k:g} standard uncertainties; blue is this "
            "test. Blue line: the Theil-Sen trend, dashed ahead of the last test (the forecast, faint where the "
            f"slope is not significant).{lim} Each axis spans at least ± 4 standard errors about the mean, so a "
            "change within them looks flat.")


# --------------------------------------------------------------------------- SVG and files


def svg(fig: Figure, key: str, label: str) -> str:
    """The figure as an inline ``<svg>`` element: responsive, its ids prefixed with ``key`` so several figures
    can share one HTML document without clashing ids (gids already starting with ``key-`` are kept)."""
    buf = io.StringIO()
    fig.savefig(buf, format="svg", metadata={"Date": None})
    text = buf.getvalue()
    text = text[text.index("<svg"):]
    text = re.sub(r"\s*<metadata>.*?</metadata>", "", text, count=1, flags=re.S)
    # path data to 1/100 pt (a hundredth of a screen pixel): a third smaller, nothing visible lost
    text = re.sub(r'\bd="[^"]*"', lambda m: re.sub(r"(\.\d\d)\d+", r"\1", m[0]), text)
    ids = set(re.findall(r'\bid="([^"]+)"', text))
    mapping = {i: f"{key}-{i}" for i in ids if not i.startswith(key + "-")}

    def ren(m: re.Match[str]) -> str:
        return m[0].replace(m[2], mapping.get(m[2], m[2]))

    text = re.sub(r'(\bid=")([^"]+)(")', ren, text)
    text = re.sub(r"(url\(#)([^)]+)(\))", ren, text)
    text = re.sub(r'(href="#)([^"]+)(")', ren, text)
    head_end = text.index(">")
    head = text[:head_end]
    head = re.sub(r'\s(width|height)="[^"]*"', "", head)
    head += f' class="plot" id="{html.escape(key, quote=True)}-svg" role="img" aria-label="{html.escape(label)}"'
    return head + text[head_end:]


def png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI, facecolor="white", metadata={"Software": None})
    return buf.getvalue()


__all__ = ["POLAR_DIVISIONS", "Curve", "Quantity", "curves_of", "deviation_figure", "envelope_indices",
           "polar_figure", "polar_scale_um", "quantity_label", "svg", "trend_figure", "trend_quantities"]
