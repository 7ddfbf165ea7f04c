"""The ``ballbar report`` renderer: one self-contained HTML file an engineer can file.

:func:`render` turns a :class:`~ballbar.tools.report.ReportData` into one HTML
file with everything inline (CSS, the plots as SVG; no script, no external
URL: the report must open the same on an air-gapped shop-floor PC in ten
years as today) and, optionally, the plots as PNG files beside it for slides
and tickets (``<stem>-polar.png``, ``<stem>-deviation.png``, and
``<stem>-trend.png`` when there is history).

The report follows the order an engineer reads a ball-bar test in: what was
tested (machine, test, conditions), the verdict (circularity and the main
findings in words), the polar plot, the deviation against angle, the ranked
findings with their uncertainty, the ISO 230-4 figures with their conditions,
what to adjust, noise, how the fit was made, and the trend over the machine's
earlier tests.

Plots.  Deviations are drawn with the set-up terms of the fit (pivot offset
``centre_*_um`` and bar length ``radius_um``) removed from the measured and the
model curves alike, as commercial ball-bar software draws them and as the
daemon's live viewer does: what is left is the machine.  In the polar plot a
deviation ``dR`` is drawn at ``1 + dR / (10 s)`` times the reference circle,
``s`` the scale in um per division (a round 1, 2, 5 x 10^n chosen so that the
test fits in a few divisions); the rings mark the divisions.  Curves are
decimated for drawing with a min/max envelope over consecutive samples, so a
one-sample spike survives and a 1 kHz test stays a few hundred kilobytes.

matplotlib draws through explicit ``Figure`` objects on the Agg canvas, never
``pyplot``: importing this module or rendering changes no global backend and
opens no window, which matters inside the daemon and in tests.
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
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ballbar.analysis.patterns import LIBRARY, Pattern
from ballbar.analysis.plan import PLANE_AXES
from ballbar.analysis.report import TREND_STDERR_SPAN, trend_limits
from ballbar.daemon.output import write_atomic

from .report import ReportData

if TYPE_CHECKING:
    from matplotlib.figure import Figure

log = logging.getLogger(__name__)

__all__ = ["envelope_indices", "polar_scale_um", "render"]

#: Colours of the two directions (CCW blue, CW red as in common ball-bar software) and their models.
COLOURS = {"ccw": "#1f5fbf", "cw": "#d0342c"}
MODEL_COLOURS = {"ccw": "#0a2350", "cw": "#5c0d09"}
DIRECTION_NAMES = {"ccw": "CCW", "cw": "CW"}
#: The fitted model's line style in both plots: dashed, so that it is told from the measured curve (solid)
#: where the two lie on each other, as they do where the fit is good.
MODEL_DASH = (0, (4, 2))
#: Drawn points per direction for the measured curves (min/max envelope), the model and the residual.
MEASURED_POINTS = 2000
MODEL_POINTS = 1000
#: Share of the reference circle's radius that one division of the polar plot takes.
POLAR_DIVISION = 0.1
PNG_DPI = 150
_MISSING = "–"


# --------------------------------------------------------------------------- small helpers


def _num(v: Any) -> float | None:
    """A finite float, or None for anything else (None, NaN, inf, text): what the report can print."""
    if isinstance(v, bool) or v is None:
        return None
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) else None


def _e(v: Any) -> str:
    return html.escape(str(v), quote=True)


def _fmt(v: Any, nd: int = 2, *, signed: bool = False) -> str:
    x = _num(v)
    if x is None:
        return _MISSING
    return f"{x:+.{nd}f}" if signed else f"{x:.{nd}f}"


def _unit(u: Any) -> str:
    """A result unit for display: ``um`` is µm, ``urad`` µrad (the result's ASCII units)."""
    return re.sub(r"\burad\b", "µrad", re.sub(r"\bum\b", "µm", str(u or "")))


def _prose(text: Any) -> str:
    """Result text (advice, methods, reasons) for display: µm and µrad, ± for ``+-``."""
    text = _unit(str(text or "")).replace("+-", "±")
    return re.sub(r"(\d) deg\b", "\\1°", text)


def _decimals(se: float | None, default: int) -> int:
    """Decimals that show a value to its standard error's second significant digit (0..4)."""
    if se is None or se <= 0:
        return default
    return int(min(max(1 - math.floor(math.log10(se)), 0), 4))


def _value_pm(value: Any, se: Any, default_nd: int = 3) -> str:
    v, s = _num(value), _num(se)
    if v is None:
        return _MISSING
    nd = _decimals(s, default_nd)
    return f"{v:.{nd}f} ± {s:.{nd}f}" if s is not None else f"{v:.{nd}f}"


def _p_text(p: Any) -> str:
    x = _num(p)
    if x is None:
        return _MISSING
    if x == 0.0:
        return "< 1e-300"  # the F distribution's tail underflowed: far beyond any level
    return f"{x:.3f}" if x >= 1e-3 else f"{x:.1e}"


def _f_text(f: Any) -> str:
    x = _num(f)
    if x is None:
        return _MISSING
    if abs(x) >= 1e3:
        m, ex = f"{x:.2e}".split("e")
        return f"{m}e{int(ex)}"
    return f"{x:.3g}"


def _share_text(s: Any) -> str:
    x = _num(s)
    if x is None:
        return _MISSING
    return "< 0.01" if 0 <= x < 0.005 else f"{x:.2f}"


def _parse_time(t: Any) -> dt.datetime | None:
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


def _time_text(t: Any) -> str:
    d = _parse_time(t)
    if d is None:
        return str(t) if t else _MISSING
    return d.strftime("%Y-%m-%d %H:%M:%S UTC")


def _version() -> str:
    try:
        return metadata.version("ballbar")
    except metadata.PackageNotFoundError:
        return "unknown"


def _axes(plan: Mapping[str, Any]) -> tuple[str, str]:
    return PLANE_AXES.get(str(plan.get("plane", "XY")), ("X", "Y"))


def _param(result: Mapping[str, Any], key: str) -> Mapping[str, Any]:
    p = (result.get("parameters") or {}).get(key)
    return p if isinstance(p, Mapping) else {}


def _pvalue(result: Mapping[str, Any], key: str) -> float | None:
    return _num(_param(result, key).get("value"))


# --------------------------------------------------------------------------- patterns in words


_REVERSAL_AT = {"x_pos": ("x", "+", 0), "y_pos": ("y", "+", 90), "x_neg": ("x", "−", 180), "y_neg": ("y", "−", 270)}


def _pattern_fields(p: Pattern) -> list[str]:
    """The result fields of a pattern (cyclic errors are reported as amplitude and phase)."""
    if p.name.startswith("cyclic_"):
        return [f"{p.name}_um", f"{p.name}_phase_deg"]
    return list(p.fields)


_FIELDS: dict[str, list[str]] = {p.name: _pattern_fields(p) for p in LIBRARY}
_KIND: dict[str, str] = {p.name: p.kind for p in LIBRARY}


def _axis_name(xy: str, axes: tuple[str, str]) -> str:
    return axes[0] if xy == "x" else axes[1]


def pattern_label(name: str, axes: tuple[str, str]) -> str:
    """A pattern's name as an engineer says it, with the plane's own axes."""
    a1, a2 = axes
    m = re.fullmatch(r"reversal_spike_([xy]_(?:pos|neg))_(ccw|cw)", name)
    if m:
        xy, sign, at = _REVERSAL_AT[m[1]]
        return f"Reversal spike {sign}{_axis_name(xy, axes)} ({at}°), {m[2].upper()}"
    m = re.fullmatch(r"(backlash|lateral_play|straightness|cyclic)_([xy])", name)
    if m:
        what = {"backlash": "Backlash", "lateral_play": "Lateral play", "straightness": "Straightness",
                "cyclic": "Cyclic error"}[m[1]]
        return f"{what} {_axis_name(m[2], axes)}"
    return {
        "centre": "Centre offset (set-up)",
        "radius": "Radius / bar length (set-up)",
        "servo_mismatch": "Servo mismatch",
        "master_slave": "Master-slave changeover",
        "squareness": f"Squareness {a1}{a2}",
        "scale_mismatch": f"Scale mismatch {a1}/{a2}",
        "drift": "Thermal drift",
    }.get(name, name.replace("_", " ").capitalize())


def field_label(key: str, axes: tuple[str, str]) -> str:
    """The short name of one field inside its pattern's row (``X``, ``a (45°/225°)``, ``phase``)."""
    a1, a2 = axes
    return {
        "centre_x_um": a1, "centre_y_um": a2,
        "master_slave_a_um": "a (45°/225°)", "master_slave_b_um": "b (135°/315°)",
    }.get(key, "phase" if key.endswith("_phase_deg") else ("amplitude" if key.startswith("cyclic_") else ""))


def _finding_words(name: str, result: Mapping[str, Any], axes: tuple[str, str]) -> str:
    """One significant pattern as a sentence fragment with its value and sign spelt out."""
    a1, a2 = axes
    v = _pvalue(result, (_FIELDS.get(name) or [""])[0])
    if name == "servo_mismatch" and v is not None:
        slow, fast = (a1, a2) if v > 0 else (a2, a1)
        return f"servo mismatch: {slow} lags {fast} by {abs(v):.2f} ms"
    if name == "squareness" and v is not None:
        return f"squareness: {a1} leans toward {'+' if v > 0 else '−'}{a2} by {abs(v):.1f} µrad"
    if name == "scale_mismatch" and v is not None:
        return f"scale mismatch: {a1} {v:+.1f} ppm relative to {a2}"
    if name.startswith("backlash_") and v is not None:
        return f"backlash of {_axis_name(name[-1], axes)} {v:.2f} µm"
    vals = []
    for key in _FIELDS.get(name, []):
        p = _param(result, key)
        if _num(p.get("value")) is not None:
            fl = field_label(key, axes)
            vals.append(f"{fl + ' ' if fl else ''}{_num(p.get('value')):+.2f} {_unit(p.get('unit'))}")
    label = pattern_label(name, axes)
    return f"{label[0].lower() + label[1:]}: {', '.join(vals)}" if vals else label


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
class _Curve:
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
    x0, y0, c = (_pvalue(result, k) or 0.0 for k in ("centre_x_um", "centre_y_um", "radius_um"))
    return np.asarray(x0 * np.cos(u) + y0 * np.sin(u) + c)


def _curves(data: ReportData) -> list[_Curve]:
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
        out.append(_Curve(name, u, meas - setup, None if model is None else model[ok] - setup))
    return out


def polar_scale_um(max_abs_um: float) -> float:
    """The polar plot's division: 1, 2 or 5 x 10^n um, so the largest deviation spans at most 3 divisions."""
    x = max_abs_um / 3.0 if math.isfinite(max_abs_um) and max_abs_um > 0 else 1.0
    x = max(x, 0.01)
    e = 10.0 ** math.floor(math.log10(x))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * e >= x * (1 - 1e-9):
            return m * e
    return 10.0 * e  # pragma: no cover - the loop always returns


def _um_text(x: float) -> str:
    return f"{x:g}"


# --------------------------------------------------------------------------- figures


@contextlib.contextmanager
def _style(salt: str) -> Iterator[None]:
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


def _polar_figure(curves: Sequence[_Curve], axes: tuple[str, str], g_text: str) -> tuple[Figure, float]:
    """Both directions around a reference circle, the model over each; returns the figure and its scale."""
    allv = [c.measured_um for c in curves] + [c.model_um for c in curves if c.model_um is not None]
    max_abs = max((float(np.max(np.abs(v))) for v in allv if v.size), default=0.0)
    div = polar_scale_um(max_abs)
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
                lw=1.0 if main else 0.6, zorder=1, gid="polar-reference" if main else None)
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
    ax.text(-lim, -lim, f"Scale {_um_text(div)} µm/div", fontsize=9, ha="left", va="bottom", color="#222222",
            gid="polar-scale")
    ax.text(lim, -lim, g_text, fontsize=9, ha="right", va="bottom", color="#222222")
    if curves:
        fig.legend(loc="outside lower center", ncol=4, fontsize=8.5, handlelength=1.8)
    return fig, div


@dataclass
class _AngleAxis:
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
    def of(cls, curves: Sequence[_Curve]) -> _AngleAxis:
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


def _deviation_figure(curves: Sequence[_Curve], axes: tuple[str, str]) -> Figure:
    """Deviation against angle for both directions with the model, and the fit's residual below."""
    has_res = any(c.model_um is not None for c in curves)
    angle = _AngleAxis.of(curves)
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
class _Quantity:
    key: str  # a parameter field, or "G" for the circularity
    label: str
    unit: str


def _g_of(result: Mapping[str, Any]) -> tuple[float | None, str]:
    """The test's circularity: G(b) when both directions ran, else the one direction's G."""
    iso = result.get("iso230_4") or {}
    for key, name in (("G_b_um", "G(b)"), ("G_ccw_um", "G CCW"), ("G_cw_um", "G CW")):
        v = _num(iso.get(key))
        if v is not None:
            return v, name
    return None, "G(b)"


def _trend_quantities(tests: Sequence[Mapping[str, Any]], axes: tuple[str, str]) -> list[_Quantity]:
    """G(b) and each machine parameter significant in any of the tests, in the library's order.

    Reversal spikes (eight fields) and phases are left to the findings table:
    a trend of each would bury the few figures an engineer tracks.
    """
    out = [_Quantity("G", "Circularity " + _g_of(tests[-1])[1], "µm")]
    for pat in LIBRARY:
        if pat.kind != "machine":
            continue
        for key in _FIELDS[pat.name]:
            if key.endswith("_phase_deg"):
                continue
            if any(_param(r, key).get("significant") and _num(_param(r, key).get("value")) is not None
                   for r in tests):
                fl = field_label(key, axes)
                label = pattern_label(pat.name, axes) + (f" {fl}" if fl else "")
                unit = _unit(next((_param(r, key).get("unit") for r in tests if _param(r, key).get("unit")), ""))
                out.append(_Quantity(key, label, unit))
    return out


def _trend_value(r: Mapping[str, Any], q: _Quantity) -> tuple[float | None, float | None, bool]:
    if q.key == "G":
        return _g_of(r)[0], None, True
    p = _param(r, q.key)
    return _num(p.get("value")), _num(p.get("stderr")), bool(p.get("significant"))


def _trend_figure(tests: Sequence[Mapping[str, Any]], quantities: Sequence[_Quantity]) -> Figure:
    """One small plot per quantity against the test date (or the test's order when dates are missing)."""
    times = [_parse_time(r.get("t_wall")) for r in tests]
    use_dates = all(t is not None for t in times)
    xs: list[Any] = list(range(1, len(tests) + 1))
    if use_dates:
        xs = [t.replace(tzinfo=None) for t in times if t is not None]
    ncols = min(3, len(quantities))
    nrows = math.ceil(len(quantities) / ncols)
    fig = _new_figure(10.0, 0.4 + 2.15 * nrows)
    grid = fig.subplots(nrows, ncols, squeeze=False, sharex=True)
    for i, q in enumerate(quantities):
        ax = grid[i // ncols][i % ncols]
        vals = [_trend_value(r, q) for r in tests]
        pts = [(x, v, s, sig) for x, (v, s, sig) in zip(xs, vals, strict=True) if v is not None]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], color="#8a94a3", lw=0.8, zorder=1)
        for j, (x, v, s, sig) in enumerate(pts):
            current = x == xs[-1] and j == len(pts) - 1 and vals[-1][0] is not None
            colour = "#1f5fbf" if current else "#4b5563"
            ax.errorbar([x], [v], yerr=[s] if s is not None else None, fmt="o", ms=5 if current else 4,
                        color=colour, mfc=colour if sig else "white", mec=colour, elinewidth=0.8, capsize=2,
                        zorder=3)
        lim = trend_limits([v for v, _s, _g in vals], [s for _v, s, _g in vals])
        if lim is not None and lim[1] > lim[0]:
            ax.set_ylim(*lim)  # a change within the standard errors looks flat, not like a drift
        ax.set_title(f"{q.label} ({q.unit})" if q.unit else q.label, fontsize=8.5, loc="left")
        ax.grid(True, color="#e3e6ea", lw=0.5)
        ax.tick_params(labelsize=7.5)
        ax.set_gid(f"trend-{q.key}")
    for j in range(len(quantities), nrows * ncols):
        grid[j // ncols][j % ncols].set_visible(False)
    if use_dates:
        import matplotlib.dates as mdates

        for row in grid:
            for ax in row:
                loc = mdates.AutoDateLocator(minticks=2, maxticks=5)
                ax.xaxis.set_major_locator(loc)
                ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(loc))
    else:
        for row in grid:
            for ax in row:
                ax.set_xticks(xs)
                ax.set_xlabel("test (oldest first)", fontsize=7.5)
    return fig


# --------------------------------------------------------------------------- SVG and files


def _svg(fig: Figure, key: str, label: str) -> str:
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
    head += f' class="plot" id="{_e(key)}-svg" role="img" aria-label="{_e(label)}"'
    return head + text[head_end:]


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=PNG_DPI, facecolor="white", metadata={"Software": None})
    return buf.getvalue()


# --------------------------------------------------------------------------- HTML sections


CSS = """
:root { --ink:#1c2430; --muted:#5b6472; --faint:#8a94a3; --rule:#d9dee5; --band:#f4f6f9; --accent:#1f5fbf;
  --ccw:#1f5fbf; --cw:#d0342c; --good:#1d7a46; --warn:#a4590b; }
* { box-sizing: border-box; }
html { -webkit-text-size-adjust: 100%; }
body { margin: 0 auto; max-width: 1060px; padding: 28px 36px 40px; color: var(--ink); background: #fff;
  font: 14px/1.45 "Segoe UI", "Helvetica Neue", Arial, "Liberation Sans", "DejaVu Sans", sans-serif;
  font-variant-numeric: tabular-nums; }
header.top { display: flex; justify-content: space-between; align-items: flex-end; gap: 24px;
  border-bottom: 3px solid var(--ink); padding-bottom: 10px; margin-bottom: 18px; }
header.top h1 { margin: 0; font-size: 24px; letter-spacing: .2px; }
header.top .sub { color: var(--muted); margin-top: 4px; font-size: 14px; }
header.top .sub b { color: var(--ink); }
header.top .brand { text-align: right; color: var(--muted); font-size: 12px; line-height: 1.35; white-space: nowrap; }
header.top .brand b { color: var(--ink); font-size: 13px; letter-spacing: 1.5px; text-transform: uppercase; }
section { margin: 22px 0 0; }
h2 { font-size: 15px; text-transform: uppercase; letter-spacing: .8px; color: var(--ink); margin: 0 0 8px;
  padding-bottom: 4px; border-bottom: 1px solid var(--rule); }
h2 .n { color: var(--accent); margin-right: 8px; }
h3 { font-size: 13px; margin: 14px 0 6px; color: var(--muted); text-transform: uppercase; letter-spacing: .5px; }
p { margin: 6px 0; }
.note, .caption { color: var(--muted); font-size: 12.5px; }
.note.warning { color: #8a4b00; }
.caption { margin-top: 4px; }
dl.kv { display: grid; grid-template-columns: repeat(3, max-content minmax(0, 1fr)); gap: 3px 12px; margin: 0;
  font-size: 13px; }
dl.kv dt { color: var(--muted); white-space: nowrap; }
dl.kv dd { margin: 0; font-weight: 600; }
.verdict { display: grid; grid-template-columns: 220px 1fr; gap: 18px; background: var(--band);
  border: 1px solid var(--rule); border-left: 5px solid var(--accent); padding: 14px 18px; }
.verdict .big { font-size: 34px; font-weight: 700; line-height: 1.05; }
.verdict .big small { font-size: 16px; font-weight: 600; color: var(--muted); }
.verdict .lbl { color: var(--muted); font-size: 12px; text-transform: uppercase; letter-spacing: .6px; }
.verdict .fig2 { margin-top: 8px; font-size: 12.5px; color: var(--muted); }
.verdict ol, .verdict ul { margin: 4px 0 0; padding-left: 20px; }
.verdict li { margin: 2px 0; }
figure { margin: 8px 0 0; break-inside: avoid; page-break-inside: avoid; }
figure.polar { max-width: 620px; margin-left: auto; margin-right: auto; }
svg.plot { display: block; width: 100%; height: auto; }
table { border-collapse: collapse; width: 100%; font-size: 13px; }
th, td { padding: 4px 8px; border-bottom: 1px solid var(--rule); vertical-align: top; text-align: left; }
thead th { background: var(--band); border-bottom: 1.5px solid var(--ink); font-weight: 600; font-size: 12px;
  color: var(--ink); white-space: nowrap; }
td.num, th.num { text-align: right; white-space: nowrap; }
td.date, td.tid { white-space: nowrap; }
td.rank { color: var(--faint); width: 28px; text-align: right; }
table.trend thead th { white-space: normal; }
table.trend td.tid { white-space: normal; overflow-wrap: anywhere; }
table.trend .u { font-weight: 400; color: var(--muted); }
.wide { overflow-x: auto; }
tr.sig td.pat { font-weight: 600; }
tr.nsig td { color: var(--muted); }
tr.absent td { color: var(--faint); font-style: italic; }
tbody.absent tr:first-child td { border-top: 1.5px solid var(--rule); }
.pill { display: inline-block; padding: 0 7px; border-radius: 9px; font-size: 11.5px; font-weight: 600; }
.pill.yes { background: #fdebd3; color: #8a4a00; }
.pill.no { background: #eef0f3; color: var(--muted); }
.pill.kind { background: #e7eefa; color: var(--accent); margin-right: 6px; }
.pill.setup { background: #fbefe0; color: var(--warn); }
.sw { display: inline-block; width: 14px; height: 3px; vertical-align: middle; margin-right: 4px; }
table.iso td, table.iso th { text-align: center; }
table.iso td { font-size: 16px; font-weight: 600; }
table.iso td.gb { color: var(--accent); }
ul.advice { margin: 4px 0; padding-left: 0; list-style: none; }
ul.advice li { padding: 5px 0; border-bottom: 1px solid var(--rule); }
code { font-family: "DejaVu Sans Mono", "Liberation Mono", Consolas, monospace; font-size: 12px;
  background: var(--band); padding: 0 4px; border-radius: 3px; }
.cols { display: grid; grid-template-columns: 1fr 1fr; gap: 24px; }
footer { margin-top: 28px; padding-top: 8px; border-top: 1px solid var(--rule); color: var(--muted);
  font-size: 11.5px; display: flex; justify-content: space-between; gap: 16px; flex-wrap: wrap; }
@media (max-width: 760px) { dl.kv { grid-template-columns: max-content 1fr; } .cols, .verdict {
  grid-template-columns: 1fr; } body { padding: 16px; } }
@media print {
  @page { size: A4; margin: 13mm 12mm 14mm; }
  body { max-width: none; padding: 0; font-size: 10pt; }
  * { -webkit-print-color-adjust: exact; print-color-adjust: exact; }
  h2 { break-after: avoid; page-break-after: avoid; }
  section { break-inside: auto; }
  tr, figure, .verdict, dl.kv, ul.advice li { break-inside: avoid; page-break-inside: avoid; }
  figure.polar { max-width: 150mm; }
  a { color: inherit; text-decoration: none; }
}
"""


class _Doc:
    """Numbered sections in reading order."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.n = 0

    def section(self, sid: str, title: str, body: str) -> None:
        self.n += 1
        self.parts.append(
            f'<section id="sec-{_e(sid)}"><h2><span class="n">{self.n}</span>{_e(title)}</h2>\n{body}\n</section>'
        )


def _kv(items: Sequence[tuple[str, str]]) -> str:
    return '<dl class="kv">' + "".join(f"<dt>{_e(k)}</dt><dd>{_e(v)}</dd>" for k, v in items) + "</dl>"


def _conditions(result: Mapping[str, Any]) -> str:
    plan = result.get("plan") or {}
    tm = result.get("timing") or {}
    samples = result.get("samples") or {}
    iso = result.get("iso230_4") or {}
    cond = iso.get("conditions") or {}
    a1, a2 = _axes(plan)
    machine = result.get("machine") or {}
    feed_m = _num(tm.get("measured_feed_mm_min"))
    feed_p = _num(plan.get("feed_mm_min"))
    ratio = f" ({(feed_m / feed_p - 1) * 100:+.2f} %)" if feed_m is not None and feed_p else ""
    dirs = {"both": "CCW then CW", "ccw": "CCW only", "cw": "CW only"}.get(str(plan.get("directions")),
                                                                          str(plan.get("directions", _MISSING)))
    sample_hz = _num(samples.get("sample_hz")) or _num(plan.get("sample_hz"))
    items = [
        ("Plane", f"{plan.get('plane', _MISSING)} ({a1}, {a2})"),
        ("Radius", f"{_fmt(plan.get('radius_mm'), 3)} mm"),
        ("Feed, programmed", f"{_fmt(feed_p, 1)} mm/min"),
        ("Feed, measured", f"{_fmt(feed_m, 1)} mm/min{ratio}"),
        ("Data arc", f"{_fmt(plan.get('data_arc_deg'), 1)}°"),
        ("Start angle", f"{_fmt(plan.get('start_deg'), 1)}°"),
        ("Overshoot", f"{_fmt(plan.get('overshoot_deg'), 1)}°"),
        ("Directions", dirs),
        ("Sample rate", f"{_fmt(sample_hz, 1)} Hz"),
        ("Samples used", f"{samples.get('in_data_arcs', _MISSING)} of {samples.get('in_test', _MISSING)}"),
        ("Feed-in", f"{_fmt(plan.get('feed_in_mm'), 2)} mm, dwell {_fmt(plan.get('dwell_s'), 2)} s"),
        ("Controller", str(machine.get("controller") or _MISSING)),
    ]
    removal = cond.get("centre_removal")
    body = _kv(items)
    if removal:
        body += f'<p class="note">Centre removal: {_e(_prose(removal))}.</p>'
    return body


def _verdict(result: Mapping[str, Any], curves: Sequence[_Curve]) -> str:
    plan = result.get("plan") or {}
    axes = _axes(plan)
    iso = result.get("iso230_4") or {}
    g, gname = _g_of(result)
    alpha = _num((result.get("fit") or {}).get("significance")) or 0.05
    ranking = [r for r in result.get("ranking") or [] if isinstance(r, Mapping)]
    sig = [r for r in ranking if r.get("significant") and _KIND.get(str(r.get("pattern")), "machine") != "setup"]
    items = []
    for r in sig[:3]:
        name = str(r.get("pattern"))
        items.append(f"<li>{_e(_finding_words(name, result, axes))} <span class='note'>"
                     f"({_e(_share_text(r.get('share_pct')))} % of the explained error)</span></li>")
    more = len(sig) - 3
    if items:
        found = f"<ol>{''.join(items)}</ol>"
        if more > 0:
            found += f'<p class="note">{more} more significant pattern{"s" if more > 1 else ""} in the findings.</p>'
    else:
        found = f"<p>No machine error pattern is significant ({_e(_rule_words(result, alpha))}).</p>"
    setup = []
    cx, cy = _pvalue(result, "centre_x_um"), _pvalue(result, "centre_y_um")
    if cx is not None or cy is not None:
        setup.append(f"pivot off the programmed centre by ({cx or 0:+.1f}, {cy or 0:+.1f}) µm")
    rad = _pvalue(result, "radius_um")
    if rad is not None and abs(rad) >= 0.05:
        setup.append(f"circle {rad:+.2f} µm from the nominal radius")
    setup_txt = (f'<p class="note">Set-up (removed from the plots and figures, not a machine error): '
                 f'{_e("; ".join(setup))}.</p>') if setup else ""
    others = []
    for key, name in (("G_ccw_um", "G CCW"), ("G_cw_um", "G CW"), ("H_um", "H")):
        if _num(iso.get(key)) is not None and name != gname:
            others.append(f"{name} {_fmt(iso.get(key), 2)} µm")
    rms = _num(result.get("residual_rms_um"))
    if rms is not None:
        others.append(f"residual {rms:.3f} µm rms")
    provisional = (result.get("timing") or {}).get("provisional")
    prov = ('<p class="note"><b>Provisional timing:</b> the feed was not measured; angles assume the '
            "programmed feed.</p>") if provisional else ""
    no_curves = "" if curves else '<p class="note">No curves in the data: plots omitted.</p>'
    warn = "".join(f'<p class="note warning"><b>Warning:</b> {_e(w)}</p>'
                   for w in result.get("warnings") or [] if isinstance(w, str))
    return (
        '<div class="verdict"><div>'
        f'<div class="lbl">Circularity {_e(gname)}</div>'
        f'<div class="big" id="verdict-g">{_e(_fmt(g, 1))} <small>µm</small></div>'
        f'<div class="fig2">{_e(" · ".join(others))}</div>{_limits_verdict(result)}</div>'
        f'<div><div class="lbl">Main findings</div>{found}{setup_txt}{prov}{no_curves}{warn}</div></div>'
    )


def _limits_verdict(result: Mapping[str, Any]) -> str:
    """The verdict against the configured limits ([limits]), under the circularity: status and each limit."""
    v = result.get("verdict")
    if not isinstance(v, Mapping) or not v.get("limits"):
        return '<p class="note" id="verdict-limits">No acceptance limits configured: no pass/fail verdict.</p>'
    status = str(v.get("status", ""))
    rows = []
    for e in v["limits"]:
        if not isinstance(e, Mapping):
            continue
        st = str(e.get("status", ""))
        if e.get("within_uncertainty"):
            st = f"{st}: within uncertainty of the limit"
        elif st == "not_evaluated":
            st = f"not evaluated: {e.get('reason', '')}"
        value = "–" if e.get("value") is None else f"{_fmt(e.get('value'), 3)} ± {_fmt(e.get('uncertainty'), 2)}"
        rows.append(f"<li><b>{_e(e.get('name'))}</b> {_e(value)} / {_e(_fmt(e.get('limit'), 3))} "
                    f"{_e(_unit(e.get('unit')))} <span class='note'>({_e(st)})</span></li>")
    return (f'<div class="lbl" style="margin-top:10px">Limits</div>'
            f'<div class="big" id="verdict-status">{_e(status.upper())}</div>'
            f'<ul id="verdict-limits">{"".join(rows)}</ul>'
            f'<p class="note">Fail only beyond the uncertainty (k = {_e(_fmt(v.get("coverage_k"), 1))}).</p>')


def _findings(result: Mapping[str, Any]) -> str:
    axes = _axes(result.get("plan") or {})
    params: Mapping[str, Any] = result.get("parameters") or {}
    rows = []
    shown: set[str] = set()
    ranking = [r for r in result.get("ranking") or [] if isinstance(r, Mapping)]
    for i, r in enumerate(ranking, 1):
        name = str(r.get("pattern"))
        keys = [k for k in _FIELDS.get(name, []) if k in params] or [
            k for k in params if k.startswith(name + "_")
        ]
        shown.update(keys)
        vals, units = [], []
        for k in keys:
            p = params.get(k) or {}
            fl = field_label(k, axes)
            vals.append((f'<span class="note">{_e(fl)}</span> ' if fl else "") + _e(_value_pm(p.get("value"),
                                                                                              p.get("stderr"))))
            units.append(_e(_unit(p.get("unit"))))
        sig = bool(r.get("significant"))
        kind = _KIND.get(name, "machine")
        tag = ' <span class="pill setup">set-up</span>' if kind == "setup" else ""
        why = r.get("significance_reason")
        verdict = ("yes" if sig else "no") + (f'<br><span class="note">{_e(_prose(str(why)))}</span>' if why else "")
        rows.append(
            f'<tr class="{"sig" if sig else "nsig"}" data-pattern="{_e(name)}">'
            f'<td class="rank">{i}</td><td class="pat">{_e(pattern_label(name, axes))}{tag}</td>'
            f'<td class="num">{"<br>".join(vals) or _MISSING}</td><td>{"<br>".join(units)}</td>'
            f'<td class="num">{_e(_share_text(r.get("share_pct")))}</td><td class="num">{_e(_f_text(r.get("F")))}</td>'
            f'<td class="num">{_e(_p_text(r.get("p_value")))}</td>'
            f'<td><span class="pill {"yes" if sig else "no"}">{verdict}</span></td></tr>'
        )
    absent: dict[str, list[str]] = {}
    for k, p in params.items():
        if k in shown or not isinstance(p, Mapping):
            continue
        if _num(p.get("value")) is None:
            absent.setdefault(str(p.get("reason") or "no value"), []).append(k)
        else:  # a fitted value no ranked pattern covers: still shown, unranked
            rows.append(
                f'<tr class="nsig" data-pattern="{_e(k)}"><td class="rank"></td><td class="pat">{_e(k)}</td>'
                f'<td class="num">{_e(_value_pm(p.get("value"), p.get("stderr")))}</td><td>{_e(_unit(p.get("unit")))}'
                f'</td><td class="num">{_e(_share_text(p.get("share_pct")))}</td><td class="num">{_MISSING}</td>'
                f'<td class="num">{_e(_p_text(p.get("p_value")))}</td><td></td></tr>'
            )
    absent_rows = []
    by_pattern = {k: name for name, ks in _FIELDS.items() for k in ks}
    for reason, keys in absent.items():
        names: list[str] = []
        for k in keys:
            label = pattern_label(by_pattern[k], axes) if k in by_pattern else k
            if label not in names:
                names.append(label)
        absent_rows.append(
            f'<tr class="absent"><td class="rank"></td><td class="pat">{_e(", ".join(names))}</td>'
            f'<td colspan="6">{_e(_prose(reason))}</td></tr>'
        )
    alpha = _num((result.get("fit") or {}).get("significance")) or 0.05
    head = (
        '<table id="findings"><thead><tr><th class="num">#</th><th>Pattern</th><th class="num">Value ± SE</th>'
        '<th>Unit</th><th class="num">Share %</th><th class="num">F</th><th class="num">p</th><th>Significant</th>'
        "</tr></thead>"
    )
    body = f"<tbody>{''.join(rows)}</tbody>"
    if absent_rows:
        body += f'<tbody class="absent">{"".join(absent_rows)}</tbody>'
    method = (result.get("fit") or {}).get("uncertainty_method")
    note = (f'<p class="caption">Ranked by the extra sum of squares (share of the explained error); F and p of each '
            f"pattern's F-test. Significant: {_e(_rule_words(result, alpha))}. SE: standard error"
            + (f" ({_e(_prose(method))})" if method else "") + ".</p>")
    return head + body + "</table>" + note


def _rule_words(result: Mapping[str, Any], alpha: float) -> str:
    """The result's significance rule as it states it (older results: the level alone)."""
    rule = (result.get("fit") or {}).get("significance_rule")
    return _prose(rule) if rule else f"p < {alpha:g}"


def _iso(result: Mapping[str, Any]) -> str:
    iso = result.get("iso230_4")
    if not isinstance(iso, Mapping) or not iso:
        return '<p class="note" id="iso-missing">No ISO 230-4 figures in this result.</p>'
    cols = [("G_ccw_um", "G CCW"), ("G_cw_um", "G CW"), ("G_b_um", "G(b)"), ("H_um", "H"),
            ("F_max_um", "F max"), ("F_min_um", "F min")]
    head = "".join(f"<th>{_e(n)} (µm)</th>" for _, n in cols)
    cells = "".join(
        f'<td id="iso-{k}"{" class=gb" if k == "G_b_um" else ""}>{_e(_fmt(iso.get(k), 2))}</td>' for k, _ in cols
    )
    cond = iso.get("conditions") or {}
    a1, a2 = _axes(cond or (result.get("plan") or {}))
    items = [
        ("Standard", str(cond.get("standard", "ISO 230-4"))),
        ("Plane", f"{cond.get('plane', _MISSING)} ({a1}, {a2})"),
        ("Radius", f"{_fmt(cond.get('radius_mm'), 3)} mm"),
        ("Feed", f"{_fmt(cond.get('feed_mm_min'), 1)} mm/min (measured {_fmt(cond.get('measured_feed_mm_min'), 1)})"),
        ("Data arc", f"{_fmt(cond.get('data_arc_deg'), 1)}° from {_fmt(cond.get('start_deg'), 1)}°"),
        ("Directions", str(cond.get("directions", _MISSING))),
        ("Sample rate", f"{_fmt(cond.get('sample_hz'), 1)} Hz"),
    ]
    removal = cond.get("centre_removal")
    note = f"Centre removal: {_prose(removal)}. " if removal else ""
    return (
        f'<table class="iso" id="iso"><thead><tr>{head}</tr></thead><tbody><tr>{cells}</tr></tbody></table>'
        f'<h3>Test conditions of these figures</h3>{_kv(items)}'
        f'<p class="note">{_e(note)}F needs a calibrated bar length.</p>'
    )


def _advice(result: Mapping[str, Any]) -> str:
    advice = [a for a in result.get("advice") or [] if isinstance(a, Mapping)]
    if not advice:
        return '<p>Nothing significant to adjust.</p>'
    items = []
    for a in advice:
        kind = str(a.get("kind") or "")
        pill = (f'<span class="pill {"setup" if kind == "setup" else "kind"}">'
                f'{"set-up" if kind == "setup" else _e(kind or "machine")}</span>')
        cp = a.get("controller_parameter")
        cp_html = f' <span class="note">Controller: <code>{_e(cp)}</code></span>' if cp else ""
        items.append(f"<li>{pill}{_e(_prose(a.get('action', '')))}{cp_html}</li>")
    machine = result.get("machine") or {}
    ctl = machine.get("controller")
    note = ""
    if not ctl or ctl == "generic":
        note = ('<p class="note">Controller parameter names are given when the machine\'s controller is configured '
                "(FANUC, SINUMERIK, HEIDENHAIN).</p>")
    return f'<ul class="advice" id="advice">{"".join(items)}</ul>{note}'


def _noise(result: Mapping[str, Any]) -> str:
    nz = result.get("noise")
    if not isinstance(nz, Mapping) or not nz:
        return '<p class="note">No noise findings in this result.</p>'

    def yn(v: Any) -> str:
        return '<span class="pill yes">significant</span>' if v else '<span class="pill no">not significant</span>'

    peak = ""
    if _num(nz.get("vibration_peak_hz")) is not None:
        line = _num(nz.get("vibration_peak_um"))
        peak = (f"strongest line {_fmt(line, 3)} µm rms " if line is not None else "") + (
            f"at {_fmt(nz.get('vibration_peak_cpr'), 0)} cycles/rev ({_fmt(nz.get('vibration_peak_hz'), 1)} Hz)")
    axes = _axes(result.get("plan") or {})
    rows = [
        f"<tr><td>Vibration (residual above {_e(_fmt(nz.get('vibration_cutoff_cpr'), 0))} cycles/rev)</td>"
        f'<td class="num">{_e(_fmt(nz.get("vibration_um"), 3))} µm rms</td><td>{yn(nz.get("vibration_significant"))}'
        f"</td><td>{_e(peak)}</td></tr>",
    ]
    for xy, ax in (("x", axes[0]), ("y", axes[1])):
        rows.append(
            f'<tr><td>Stick-slip near {_e(ax)} reversals</td><td class="num">'
            f"{_e(_fmt(nz.get(f'stick_slip_{xy}_um'), 3))} µm</td>"
            f"<td>{yn(nz.get(f'stick_slip_{xy}_significant'))}</td><td></td></tr>"
        )
    method = nz.get("method")
    return ('<table id="noise"><thead><tr><th>Finding</th><th class="num">Value</th><th>Verdict</th><th>Detail</th>'
            f"</tr></thead><tbody>{''.join(rows)}</tbody></table>"
            + (f'<p class="caption">Method: {_e(_prose(method))}.</p>' if method else ""))


def _lost_motion_words(fit: Mapping[str, Any], axes: Sequence[str]) -> str:
    """Each axis' lost-motion model and where its table reverses, in words."""
    lm = fit.get("lost_motion")
    if not isinstance(lm, Mapping):
        return str(fit.get("lost_motion_model") or _MISSING)
    parts = []
    for key, name in zip(("x", "y"), axes, strict=False):
        d = lm.get(key) or {}
        parts.append(f"{name}: {d.get('description') or d.get('model') or _MISSING}; friction from "
                     f"{_fmt(d.get('onset_deg'), 3)}° after the reversal point")
    return " — ".join(parts)


def _diagnostics(result: Mapping[str, Any]) -> str:
    tm = result.get("timing") or {}
    fit = result.get("fit") or {}
    take = tm.get("backlash_takeup_deg") or {}
    axes = _axes(result.get("plan") or {})
    lag_se, lag_s = _num(tm.get("lag_stderr_s")), _num(tm.get("lag_s"))
    lag = f"{_fmt(None if lag_s is None else lag_s * 1000, 2)}" + (
        f" ± {lag_se * 1000:.2f}" if lag_se is not None else "") + f" ms ({_fmt(tm.get('lag_deg'), 3)}°)"
    timing = [
        ("Measured feed", f"{_fmt(tm.get('measured_feed_mm_min'), 2)} mm/min (ratio {_fmt(tm.get('feed_ratio'), 5)})"),
        ("Arc-start lag", lag),
        ("Loop lag", f"{_fmt(tm.get('loop_lag_ms'), 2)} ms"),
        ("Loop-lag source", _prose(tm.get("loop_lag_source") or _MISSING)),
        ("Spike width", f"{_fmt(tm.get('spike_width_deg'), 2)}°" + (
            f" ± {_fmt(tm.get('spike_width_stderr_deg'), 2)}°" if tm.get("spike_width_stderr_deg") else "")),
        ("Backlash take-up", f"{axes[0]} {_fmt(take.get('x'), 2)}°, {axes[1]} {_fmt(take.get('y'), 2)}°"
         if take else _MISSING),
        ("Data arcs' shift", ", ".join(f"{k.upper()} {_fmt((v.get('shift_s') or 0.0) * 1000, 2)} ms"
                                       for k, v in (tm.get("data_arcs") or {}).items()) or _MISSING),
        ("Feed-in / out", f"{tm.get('feed_in_method', _MISSING)} at {_fmt(tm.get('feed_in_s'), 3)} s / "
         f"{_fmt(tm.get('feed_out_s'), 3)} s"),
        ("Timing method", _prose(tm.get("method") or _MISSING)),
    ]
    fits = [
        ("Residual RMS", f"{_fmt(result.get('residual_rms_um'), 3)} µm"),
        ("Sigma", f"{_fmt(fit.get('sigma_um'), 3)} µm"),
        ("Lag-1 autocorrelation", _fmt(fit.get("residual_lag1_autocorrelation"), 3)),
        ("Variance inflation", _fmt(fit.get("variance_inflation"), 3)),
        ("Condition number", _fmt(fit.get("condition_number"), 1)),
        ("Samples / parameters", f"{fit.get('n_samples', _MISSING)} / {fit.get('n_parameters', _MISSING)} "
         f"(dof {fit.get('dof', _MISSING)})"),
        ("Significance", _rule_words(result, _num(fit.get("significance")) or 0.05)),
        ("Servo model", f"{fit.get('servo_model', _MISSING)}"
         + (f" — {fit['servo_model_note']}" if fit.get("servo_model_note") else "")),
        ("Lost-motion model", _lost_motion_words(fit, axes)),
    ]

    def table(rows: Sequence[tuple[str, str]], tid: str) -> str:
        return (f'<table id="{tid}"><tbody>' + "".join(
            f'<tr><td class="note" style="width:38%">{_e(k)}</td><td>{_e(v)}</td></tr>' for k, v in rows)
            + "</tbody></table>")

    return (f'<div class="cols"><div><h3>Timing</h3>{table(timing, "diag-timing")}</div>'
            f'<div><h3>Fit</h3>{table(fits, "diag-fit")}</div></div>')


def _history(data: ReportData) -> list[Mapping[str, Any]]:
    return [h for h in data.history or [] if isinstance(h, Mapping)]


def _trend(data: ReportData, qs: Sequence[_Quantity], svg: str | None) -> str:
    """The trend section: the plot and a table of the key figures per test, or why there is none."""
    history = _history(data)
    note = f'<p class="note">{_e(data.history_note)}</p>' if data.history_note else ""
    if not history:
        return f'<p id="trend-none">No earlier comparable test of this machine: no trend yet.</p>{note}'
    tests = [*history, data.result]
    # The unit under the name and the test id wrapping at any character: seven columns fit the page (the
    # names and ids on one line overflowed it by 42 px at 1200 px); on a narrower screen the table scrolls.
    head = "".join(f'<th class="num">{_e(q.label)} <br><span class="u">({_e(q.unit)})</span></th>' for q in qs)
    this = ' <span class="pill kind">this test</span>'
    rows = []
    for i, r in enumerate(tests):
        cur = i == len(tests) - 1
        cells = []
        for q in qs:
            v, s, sig = _trend_value(r, q)
            nd = 2 if q.key == "G" else min(_decimals(s, 3), 3)
            text = _MISSING if v is None else f"{v:.{nd}f}"
            cells.append(f'<td class="num">{"<b>" + text + "</b>" if sig and q.key != "G" else _e(text)}</td>')
        tid = str(r.get("test_id") or f"test {r.get('test_index', i + 1)}")
        rows.append(
            f'<tr class="{"sig" if cur else "hist"}"><td class="tid">{_e(tid)}{this if cur else ""}</td>'
            f"<td class=\"date\">{_e(_time_text(r.get('t_wall')))}</td>{''.join(cells)}</tr>"
        )
    figure = f'<figure class="trend">{svg}</figure>' if svg else ""
    return (f"{note}{figure}"
            f'<div class="wide"><table id="trend-table" class="trend"><thead><tr><th>Test</th><th>Date</th>{head}'
            f"</tr></thead><tbody>{''.join(rows)}</tbody></table></div>"
            '<p class="caption">Bold: significant in that test. Plots: filled markers significant, hollow not; '
            "bars ± one standard error; blue is this test; each axis spans at least ± "
            f"{TREND_STDERR_SPAN:g} standard errors about the mean, so a change within them looks flat.</p>")


# --------------------------------------------------------------------------- render


def render(data: ReportData, html_path: Path, *, png: bool = True) -> list[Path]:
    """Write the report of ``data`` to ``html_path`` (and its plots as PNGs beside it when ``png``).

    Returns the paths written, the HTML first.  Every file is written through
    a temporary file and a rename, the HTML last, so a report on disk is
    always whole.
    """
    html_path = Path(html_path)
    result: Mapping[str, Any] = data.result or {}
    plan = result.get("plan") or {}
    axes = _axes(plan)
    curves = _curves(data)
    stem = html_path.stem
    pngs: list[tuple[Path, bytes]] = []
    svgs: dict[str, str] = {}
    g, gname = _g_of(result)
    div = None
    if curves:
        with _style("polar"):
            fig, div = _polar_figure(curves, axes, f"{gname} {_fmt(g, 1)} µm" if g is not None else "")
            svgs["polar"] = _svg(fig, "polar", "Polar plot of the radial deviation, both directions")
            if png:
                pngs.append((html_path.with_name(f"{stem}-polar.png"), _png(fig)))
        with _style("deviation"):
            fig = _deviation_figure(curves, axes)
            svgs["deviation"] = _svg(fig, "deviation", "Radial deviation against angle")
            if png:
                pngs.append((html_path.with_name(f"{stem}-deviation.png"), _png(fig)))
    history = _history(data)
    qs = _trend_quantities([*history, result], axes) if history else []
    if qs:
        with _style("trend"):
            fig = _trend_figure([*history, result], qs)
            svgs["trend"] = _svg(fig, "trend", "Key figures of this machine's tests over time")
            if png:
                pngs.append((html_path.with_name(f"{stem}-trend.png"), _png(fig)))

    machine_id = result.get("machine_id") or (result.get("machine") or {}).get("machine_id")
    test_id = result.get("test_id")
    when = _time_text(result.get("t_wall")) if result.get("t_wall") else None
    title_bits = ["Ball-bar test report"]
    if machine_id:
        title_bits.append(str(machine_id))
    if test_id:
        title_bits.append(str(test_id))
    title = " — ".join(title_bits)
    sub = []
    if machine_id:
        sub.append(f"Machine <b>{_e(machine_id)}</b>")
    if test_id:
        sub.append(f"Test <b>{_e(test_id)}</b>")
    elif result.get("test_index") is not None:
        sub.append(f"Test #{_e(result.get('test_index'))}")
    if when:
        sub.append(f"<b>{_e(when)}</b>")
    sub.append(f"{_e(plan.get('plane', '?'))} plane · R {_e(_fmt(plan.get('radius_mm'), 0))} mm · "
               f"F {_e(_fmt(plan.get('feed_mm_min'), 0))} mm/min")

    doc = _Doc()
    doc.section("conditions", "Test conditions", _conditions(result))
    doc.section("verdict", "Verdict", _verdict(result, curves))
    if curves:
        dirs = " and ".join(
            f'<span class="sw" style="background:{COLOURS[c.name]}"></span>{DIRECTION_NAMES[c.name]}' for c in curves)
        doc.section("polar", "Polar plot", (
            f'<figure class="polar">{svgs["polar"]}<figcaption class="caption">Radial deviation of {dirs}, '
            f"magnified about the reference circle: <b>{_e(_um_text(div or 1.0))} µm per division</b>; dashed dark "
            "lines: the fitted model (legend under the plot). Set-up terms (pivot offset, bar length) removed. "
            f"Angles counter-clockwise from +{_e(axes[0])}.</figcaption></figure>"))
        doc.section("deviation", "Deviation against angle", (
            f'<figure>{svgs["deviation"]}<figcaption class="caption">Measured deviation (solid) and fitted model '
            "(dashed) per direction, set-up terms removed; below, the residual (measured − model). Curves drawn "
            f"as a min/max envelope of at most {MEASURED_POINTS} points per direction: spikes are kept."
            "</figcaption></figure>"))
    doc.section("findings", "Ranked findings", _findings(result))
    doc.section("iso230", "ISO 230-4 circular test figures", _iso(result))
    doc.section("advice", "Advice", _advice(result))
    doc.section("noise", "Noise", _noise(result))
    doc.section("diagnostics", "Fit and timing diagnostics", _diagnostics(result))
    doc.section("trend", "Trend over earlier tests", _trend(data, qs, svgs.get("trend")))

    generated = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    footer = (
        f'<footer><span>Source: {_e(data.source or _MISSING)}</span>'
        f"<span>ballbar {_e(_version())} · result schema {_e(result.get('schema_version', _MISSING))}</span>"
        f"<span>Generated {_e(generated)}</span></footer>"
    )
    page = (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f'<meta name="generator" content="ballbar {_e(_version())}">'
        f"<title>{_e(title)}</title><style>{CSS}</style></head>\n<body>"
        f'<header class="top"><div><h1>Ball-bar test report</h1><div class="sub">{" · ".join(sub)}</div></div>'
        f'<div class="brand"><b>ballbar</b><br>Circular test, ISO 230-4<br>Suh &amp; Lee pattern fit</div></header>\n'
        + "\n".join(doc.parts) + footer + "</body></html>\n"
    )
    written = []
    for path, blob in pngs:
        write_atomic(path, blob)
        written.append(path)
    write_atomic(html_path, page.encode("utf-8"))
    log.info("report written to %s (%d bytes, %d PNGs)", html_path, len(page.encode("utf-8")), len(written))
    return [html_path, *written]
