"""The test's nonlinear parameters by separable least squares: binned samples, a smooth objective, Gauss-Newton.

The model of a test is linear in the pattern amplitudes and nonlinear in a
few parameters: the arc-start lag ``c`` (the per-move overhead, which also
sets the feed from the feed-in to feed-out span), the feed-in's extra wait
``W`` (how much more the feed-in's move costs than each arc's), the reversal
spikes' width ``w`` and, where nothing else tells it, the position loops' lag
``tau``.  For any values of those the amplitudes are a linear least-squares
fit (variable projection): the objective is the residual of that fit, a
function of the nonlinear parameters alone (:class:`Objective`).

Smooth.  A sample is the average of the bar's length over the time it stands
for, so every sharp feature of the model (a lost-motion step, a changeover, a
spike's onset, a dead band's take-up) is integrated over each sample's
interval instead of evaluated at its centre (the patterns' ``aperture_rad``).
The residual is then a smooth function of the timing: a step moves through a
sample's interval continuously, and the fit places it where the samples put
it, half way between the two that straddle it.  There are no stairs to
search, and Gauss-Newton converges in a handful of steps (:func:`minimise`).

Binned.  Away from the sharp features the model is smooth on a scale of
degrees, so samples are grouped into bins (a tenth of a degree or so) whose
mean, weighted by its count, carries everything a linear fit needs of them;
near each 45 deg point (reversals and changeovers) the bins are a few
hundredths of a degree, or single samples.  The sum of squares is the bins'
weighted sum plus the samples' scatter within their bins, a constant.  The
sharp features are integrated over each bin's interval as over a sample's.
A 1 kHz test of 75 000 samples becomes about 5 000 bins; 15.625 Hz is not
binned.

Graduated.  Far from its minimum a step's misfit is a V in the timing,
rounded only over the width it is integrated over.  The first Gauss-Newton
steps therefore integrate the sharp features over a wider interval
(``smooth_rad``), which makes the objective a bowl on that scale; the width
shrinks to the samples' own as the timing settles.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from .circle import Timing, make_timing
from .fit import Factor
from .patterns import Geometry, Pattern, design
from .physics import LostMotion, Offset
from .plan import MachineConfig, TestPlan
from .program import arc_start_deg, feed_from_span

FINE_BIN_DEG = 0.02  # bins near the sharp features (deg of travel), or single samples where these are coarser
COARSE_BIN_DEG = 0.4  # bins elsewhere (at most: a screw's cyclic error wants them shorter, CYCLIC_BINS a period)
CYCLIC_BINS = 20
MIN_SUPPORT = 2.0  # a column holding less than this many samples' worth of its peak is left out of the search
BROYDEN = False  # carry the Jacobian by secant updates (True) or make it anew after each step
DECREMENT = 0.01  # a search stops where its Newton decrement (in chi-square units) is below this
NEAR_DECREMENT = 1.0  # ... or after a full step from where it was below this
NOISE_FLOOR_UM = 0.01  # a misfit below this (um rms) is the model's fine detail, not signal: no gauge resolves it
MIN_PEAK = 1e-6  # ... and one whose values are all below this (a spike decayed long before the window)
SAME_STEP = 0.1  # a damped step within this share of one that failed is not tried (it would fail as well)
ZONE_DEG = (0.6, 1.8)  # the sharp features' zone about each 45 deg point: before, after it in the direction of travel


@dataclass
class Binned:
    """One direction's samples of a fixed window, in bins.

    ``t``: each bin's mean time from the feed-in's centroid (s); ``span_s``:
    the time it stands for, its samples' span plus one sample period;
    ``y``: the mean deviation ``L - R`` (um); ``n``: its samples; ``ss``:
    the samples' sum of squares within their bins (um^2): about each bin's
    own straight line, on the degrees of freedom of the scatter about the
    bins' means (the model's slope across a bin is signal, not noise).
    """

    d: int
    t: np.ndarray
    span_s: np.ndarray
    y: np.ndarray
    n: np.ndarray
    ss: float
    samples: int

    def __len__(self) -> int:
        return int(self.t.size)


def make_bins(
    d: int,
    t_rel: np.ndarray,
    y: np.ndarray,
    period_s: float,
    zones: Sequence[tuple[float, float]],
    fine_s: float,
    coarse_s: float,
) -> Binned:
    """Bins of consecutive samples (``t_rel`` ascending): ``fine_s`` long within ``zones`` (time intervals),
    ``coarse_s`` elsewhere; a bin never straddles a zone's edge.  Bins shorter than a sample are samples."""
    n = t_rel.size
    if n == 0:
        return Binned(d, np.empty(0), np.empty(0), np.empty(0), np.empty(0), 0.0, 0)
    in_zone = np.zeros(n, dtype=bool)
    for a, b in zones:
        i, j = np.searchsorted(t_rel, (a, b))
        in_zone[i:j] = True
    width = np.where(in_zone, max(fine_s, 1e-12), max(coarse_s, 1e-12))
    key = np.floor(t_rel / width)
    new = np.empty(n, dtype=bool)
    new[0] = True
    np.not_equal(key[1:], key[:-1], out=new[1:])
    new[1:] |= in_zone[1:] != in_zone[:-1]
    starts = np.flatnonzero(new)
    count = np.diff(np.append(starts, n)).astype(float)
    ends = np.append(starts[1:], n) - 1
    mean_t = np.add.reduceat(t_rel, starts) / count
    mean_y = np.add.reduceat(y, starts) / count
    # the samples' scatter within their bins about each bin's own straight line: the model's slope across a
    # bin (a large servo pattern's, 2 um over 0.4 deg) is signal, not noise; counted on the dof the scatter
    # about the bins' means would have
    dt = t_rel - np.repeat(mean_t, count.astype(np.int64))
    dy = y - np.repeat(mean_y, count.astype(np.int64))
    stt = np.add.reduceat(dt * dt, starts)
    sty = np.add.reduceat(dt * dy, starts)
    syy = np.add.reduceat(dy * dy, starts)
    with np.errstate(divide="ignore", invalid="ignore"):
        lin = np.where(stt > 0, syy - sty * sty / np.where(stt > 0, stt, 1.0), syy)
    dof_mean = float(np.sum(count - 1.0))
    dof_line = float(np.sum(np.maximum(count - 2.0, 0.0)))
    ss = float(np.sum(np.maximum(lin, 0.0))) * (dof_mean / dof_line if dof_line > 0 else 0.0)
    span = t_rel[ends] - t_rel[starts] + period_s
    return Binned(d, mean_t, span, mean_y, count, max(ss, 0.0), n)


def feature_zones(plan: TestPlan, timing: Timing, d: int, window: tuple[float, float]) -> list[tuple[float, float]]:
    """The time intervals (from the feed-in's centroid) within ``ZONE_DEG`` of each 45 deg point that direction
    ``d``'s data arc passes at ``timing``, inside ``window``."""
    V, R = timing.feed_mm_s, plan.radius_mm
    deg_s = math.degrees(V / R)  # deg per second
    start = timing.sched.data_start_s[d]
    from .program import data_start_deg

    u0 = data_start_deg(plan, d)
    t_lo, t_hi = window[0] - timing.t_ref, window[1] - timing.t_ref
    # travel past the data arc's start at each 45 deg point in the direction of travel
    first = math.ceil((d * u0 - ZONE_DEG[1]) / 45.0)
    out = []
    k = first
    while True:
        travel = 45.0 * k - d * u0  # deg from the data arc's start to this point
        a = start + (travel - ZONE_DEG[0]) / deg_s
        b = start + (travel + ZONE_DEG[1]) / deg_s
        if a > t_hi:
            break
        if b >= t_lo:
            out.append((max(a, t_lo), min(b, t_hi)))
        k += 1
    return out


@dataclass
class Theta:
    """The nonlinear parameters: arc-start lag ``c`` (s), the feed-in's extra wait ``wait`` (s), the spikes'
    width ``w_deg``, the loops' mean lag ``tau`` (s; None: no servo dynamics) and the share ``ff`` of a
    command step that the loops' velocity feed-forward passes at once (their lag on the circle is
    ``(1 - ff) tau``: how far the command leads the axes, and so where a step made in the command lands);
    ``smooth``: where the feed-in is too short to reach the feed, how far its duration lies from the
    trapezoid's triangle (0) toward the average's ``f/V + c_a`` (1: a jerk limit's S-curve, a filter after
    interpolation; :func:`.program.short_move_duration`)."""

    c: float = 0.0
    wait: float = 0.0
    w_deg: float = 0.5
    tau: float | None = None
    ff: float = 0.0
    smooth: float = 0.0

    def vector(self) -> np.ndarray:
        return np.array([self.c, self.wait, math.log(self.w_deg), math.log(self.tau or 1.0), self.ff, self.smooth])

    @classmethod
    def of(cls, v: np.ndarray, tau_known: bool) -> Theta:
        return cls(float(v[0]), float(v[1]), float(math.exp(v[2])), float(math.exp(v[3])) if tau_known else None,
                   float(v[4]), float(v[5]) if len(v) > 5 else 0.0)


@dataclass
class Evaluation:
    """The objective at one ``theta``: the fit's sum of squares (bins and scatter within them), the
    coefficients, the weighted residual per bin, and what the Jacobian needs (the weighted design of the
    columns used and the factor of its normal equations)."""

    theta: Theta
    sse: float
    x: np.ndarray
    r: np.ndarray
    A: np.ndarray | None = None
    normal: Normal | None = None
    use: np.ndarray | None = None  # the columns fitted (with data to stand on)


@dataclass
class Context:
    """What every evaluation of one test shares."""

    plan: TestPlan
    machine: MachineConfig
    patterns: list[Pattern]
    t_ref: float  # the feed-in's centroid (absolute s)
    span_s: float  # feed-in to feed-out centroid span
    accel_s: float | None
    by_direction: dict[int, tuple[list[Pattern], np.ndarray]] = field(default_factory=dict)
    spike_cols: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def __post_init__(self) -> None:
        start, j = {}, 0
        for p in self.patterns:
            start[p.name] = j
            j += p.q
        self.p = j
        for d in self.plan.direction_list:
            mine = [p for p in self.patterns if p.reversal is None or p.reversal[2] == d]
            self.by_direction[d] = (mine, np.array([start[p.name] + k for p in mine for k in range(p.q)], dtype=int))
        self.spike_cols = np.array([p.reversal is not None for p in self.patterns for _ in range(p.q)], dtype=bool)
        self.servo_col = start.get("servo_mismatch")  # the servo pattern's column, whose size is V m/2

    def shifts(self, wait_s: float) -> dict[int, float]:
        """Per direction, how much later its data arc runs when the feed-in costs ``wait_s`` more than each arc
        (the ``k``-th of ``n`` arcs by ``(n + 1 - k) / (n + 1)`` of it)."""
        dirs = self.plan.direction_list
        n = len(dirs)
        return {d: (n - k) / (n + 1) * wait_s for k, d in enumerate(dirs)} if wait_s else {}

    def feed(self, theta: Theta) -> float:
        """The path feed (mm/s): from the feed-in to feed-out span at the arc-start lag."""
        return feed_from_span(self.plan, self.span_s, theta.c, self.accel_s, theta.smooth)

    def timing(self, theta: Theta) -> Timing:
        V = self.feed(theta)
        return make_timing(self.plan, self.t_ref, V, theta.c, self.shifts(theta.wait), self.accel_s, theta.smooth)

    def geometry(
        self, b: Binned, timing: Timing, tau: float | None, lost: LostMotion, smooth_rad: float, du: float = 0.0,
        aperture_scale: float = 1.0,
    ) -> Geometry:
        plan, d = self.plan, b.d
        V = timing.feed_mm_s
        omega = V / plan.radius_mm
        u = np.radians(timing.sched.angle_deg(plan, d, b.t))
        if du:
            u += du
        return Geometry(
            u=u, d=np.full(u.size, float(d)), t_min=b.t / 60.0, V=V, R=plan.radius_mm,
            pitch_x_mm=self.machine.pitch_x_mm, pitch_y_mm=self.machine.pitch_y_mm,
            travel=d * (u - math.radians(arc_start_deg(plan, d))), loop_lag_s=tau,
            aperture_rad=omega * b.span_s * aperture_scale + smooth_rad, **lost.geometry(tau),
        )


OffsetFor = Callable[[Theta], Offset | None]
LostFor = Callable[[Theta], LostMotion]  # the lost-motion models' angles at the nonlinear parameters (the loops' lag)
TIMING = (0, 1)  # the coordinates of Theta.vector that move the samples' angles: the lag and the wait
SMOOTH = 5  # ... and the short feed-in's duration share, which moves them too (and the feed, as the lag does)


class Objective:
    """The residual of the linear fit at each value of the nonlinear parameters (variable projection).

    ``offset``: the physical corrections (um) at the current estimates, given the nonlinear parameters
    (:mod:`.physics`; they need the loops' lag); ``lost``: the lost-motion models, or their angles given the
    nonlinear parameters (a compensation step's lead and rise are the loops').  ``smooth_rad``: the sharp
    features' extra integration width.  ``spikes``: False for the model without the reversal spikes.
    ``designs`` counts the designs made, ``misfits`` the misfit evaluations (the objective at a value of the
    nonlinear parameters) among them.
    """

    def __init__(
        self, ctx: Context, bins: dict[int, Binned], lost: LostMotion | LostFor, offset: OffsetFor,
        smooth_rad: float = 0.0,
        spikes: bool = True,
    ) -> None:
        self.ctx, self.lost, self.offset, self.smooth_rad = ctx, lost, offset, smooth_rad
        self.bins = {d: b for d, b in bins.items() if len(b)}
        self.spikes = spikes  # the spikes' columns in the fit (False: the spike-free model)
        self.designs = 0
        self.misfits = 0
        self.sqrt_n = {d: np.sqrt(b.n) for d, b in self.bins.items()}
        self.weights = np.concatenate(list(self.sqrt_n.values())) if self.bins else np.empty(0)
        self.ss = sum(b.ss for b in self.bins.values())
        self.samples = sum(b.samples for b in self.bins.values())
        self.aperture_scale = 1.0  # each bin's interval is integrated over this share of itself
        self.colmax = np.zeros(ctx.p)  # the last design's columns' largest absolute values (unweighted)
        self._last: tuple[tuple[object, ...], np.ndarray, np.ndarray, np.ndarray] | None = None  # see rows()

    def angles(self, theta: Theta) -> dict[int, np.ndarray]:
        """Each bin's angle (rad) at ``theta``: no design, only the timing."""
        timing = self.ctx.timing(theta)
        return {d: np.radians(timing.sched.angle_deg(self.ctx.plan, d, b.t)) for d, b in self.bins.items()}

    def rows(self, theta: Theta, du: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """The weighted design (bins x all columns) and the weighted corrected deviation at ``theta``; ``du``:
        every angle moved by this much (rad), for the model's slope in the angle.  The last design is kept
        (read-only): the final fit asks for the one at its timing three times over."""
        key = (theta.vector().tobytes(), theta.tau is None, du, self.aperture_scale)
        if self._last is not None and self._last[0] == key:
            self.colmax = self._last[3]
            return self._last[1], self._last[2]
        self.designs += 1
        ctx = self.ctx
        timing = ctx.timing(theta)
        offset = self.offset(theta)
        lost = self.lost(theta) if callable(self.lost) else self.lost
        w = math.radians(theta.w_deg)
        A = np.zeros((self.weights.size, ctx.p), order="F")  # by columns: each is made whole
        ys = []
        i = 0
        for d, b in self.bins.items():
            mine, cols = ctx.by_direction[d]
            g = ctx.geometry(b, timing, theta.tau, lost, self.smooth_rad, du, self.aperture_scale)
            block = A[i : i + len(b)]
            if self.spikes:
                block[:, cols] = design(mine, g, w)
            else:
                steady = [p for p in mine if p.reversal is None]
                block[:, cols[~ctx.spike_cols[cols]]] = design(steady, g, w)
            ys.append(b.y - offset(g) if offset is not None else b.y)
            i += len(b)
        # each column's largest absolute value over the bins (two reductions, no copy of the design)
        self.colmax = np.maximum(A.max(axis=0), -A.min(axis=0)) if A.size else np.zeros(A.shape[1])
        A *= self.weights[:, None]
        y = np.concatenate(ys) * self.weights
        A.flags.writeable = y.flags.writeable = False
        self._last = (key, A, y, self.colmax)
        return A, y

    def evaluate(self, theta: Theta) -> Evaluation:
        self.misfits += 1
        A, y = self.rows(theta)
        use = self.supported(A, self.colmax)
        A = A[:, use]
        normal = Normal(A)
        xu = normal.solve(A.T @ y)
        x = np.zeros(self.ctx.p)
        x[use] = xu
        r = y - A @ xu
        return Evaluation(theta, float(r @ r) + self.ss, x, r, A, normal, use)

    def slopes(self, e: Evaluation, active: Sequence[int], steps: dict[int, float]) -> list[np.ndarray]:
        """Per coordinate of ``active``: the weighted residual's change per unit of it with the coefficients
        held (``-d(A x + offset)/d theta``).  The lag and the wait move the angles: their slopes are the model's
        slope in the angle (one design at angles moved a little) times each bin's angle's change, which needs
        no design; the lag also sets the feed (the span is fixed), which scales the servo pattern (``V m/2``):
        that part is the servo column over the feed times the feed's change.  The width and the loops' lag
        each by a design at a moved value."""
        assert e.use is not None and e.A is not None
        use = e.use
        tau_known = e.theta.tau is not None
        v0 = e.theta.vector()
        out: list[np.ndarray] = []
        slope_u = None
        base = None
        for k in active:
            if k in TIMING or k == SMOOTH:
                if slope_u is None:
                    du = 1e-3 * self._finest_rad(e.theta)
                    A1, y1 = self.rows(e.theta, du)
                    slope_u = ((y1 - A1[:, use] @ e.x[use]) - e.r) / du
                    base = self.angles(e.theta)
                assert base is not None
                v = v0.copy()
                v[k] += steps[k]
                moved_theta = Theta.of(v, tau_known)
                moved = self.angles(moved_theta)
                s = slope_u * np.concatenate([(moved[d] - base[d]) / steps[k] for d in self.bins])
                j = self.ctx.servo_col
                if k in (0, SMOOTH) and j is not None and use[j]:
                    V0, V1 = self.ctx.timing(e.theta).feed_mm_s, self.ctx.timing(moved_theta).feed_mm_s
                    col = e.A[:, int(np.count_nonzero(use[:j]))]  # the servo column, weighted
                    s = s - col * (e.x[j] / V0) * ((V1 - V0) / steps[k])
                out.append(s)
            elif k == 2 and self.spikes:
                # the width moves the spikes' columns alone (nothing else depends on it)
                v = v0.copy()
                v[k] += steps[k]
                sc = np.flatnonzero(use & self.ctx.spike_cols)
                at = np.searchsorted(np.flatnonzero(use), sc)  # their places among the columns used
                A1 = self.spike_rows(Theta.of(v, tau_known))
                out.append(-((A1[:, sc] - e.A[:, at]) @ e.x[sc]) / steps[k])
            else:
                v = v0.copy()
                v[k] += steps[k]
                A1, y1 = self.rows(Theta.of(v, tau_known))
                out.append(((y1 - A1[:, use] @ e.x[use]) - e.r) / steps[k])
        return out

    def spike_rows(self, theta: Theta) -> np.ndarray:
        """The weighted design's reversal-spike columns at ``theta`` (the others 0): what a change of the width
        alone changes.  Counted as a design."""
        self.designs += 1
        ctx = self.ctx
        timing = ctx.timing(theta)
        lost = self.lost(theta) if callable(self.lost) else self.lost
        w = math.radians(theta.w_deg)
        A = np.zeros((self.weights.size, ctx.p), order="F")
        i = 0
        for d, b in self.bins.items():
            mine, cols = ctx.by_direction[d]
            spikes = [p for p in mine if p.reversal is not None]
            if spikes:
                g = ctx.geometry(b, timing, theta.tau, lost, self.smooth_rad, 0.0, self.aperture_scale)
                A[i : i + len(b), cols[ctx.spike_cols[cols]]] = design(spikes, g, w)
            i += len(b)
        A *= self.weights[:, None]
        return A

    def last_arc_feed(self, e: Evaluation, steps: dict[int, float], noise_var: float) -> tuple[float, float]:
        """How much faster the last arc ran than the first, as a share of the feed, and that estimate in its
        standard errors: the residual regressed on the model's slope along a feed change of the last arc
        (each of its bins' angle moves by ``d Omega tau``, ``tau`` the time since that arc's data began), the
        lag's and the wait's slopes and the design's columns held (a score test of the one timing the
        schedule does not have).  ``noise_var``: the noise variance per sample (um^2)."""
        assert e.A is not None and e.normal is not None and e.use is not None
        dirs = self.ctx.plan.direction_list
        last = dirs[-1]
        if len(dirs) < 2 or last not in self.bins:
            return math.nan, 0.0
        tau_known = e.theta.tau is not None
        du = 1e-3 * self._finest_rad(e.theta)
        A1, y1 = self.rows(e.theta, du)
        slope_u = ((y1 - A1[:, e.use] @ e.x[e.use]) - e.r) / du
        base = self.angles(e.theta)
        cols = []
        for k in TIMING:
            v = e.theta.vector()
            v[k] += steps[k]
            moved = self.angles(Theta.of(v, tau_known))
            cols.append(slope_u * np.concatenate([(moved[d] - base[d]) / steps[k] for d in self.bins]))
        timing = self.ctx.timing(e.theta)
        omega = timing.feed_mm_s / self.ctx.plan.radius_mm
        du_rho = np.concatenate([
            (last * omega * (b.t - timing.sched.data_start_s[last])) if d == last else np.zeros(len(b))
            for d, b in self.bins.items()
        ])
        cols.append(slope_u * du_rho)
        S = np.column_stack(cols)
        P = S - e.A @ e.normal.solve(e.A.T @ S)  # off the design's columns
        coef, *_ = np.linalg.lstsq(P, e.r, rcond=None)
        try:
            cov = np.linalg.inv(P.T @ P) * noise_var
        except np.linalg.LinAlgError:
            return math.nan, 0.0
        se = math.sqrt(max(float(cov[-1, -1]), 0.0))
        # the residual is y - model: a slope that fits it is the model's change opposite to it
        rho = -float(coef[-1])
        return rho, abs(rho) / se if se > 0 else 0.0

    def _finest_rad(self, theta: Theta) -> float:
        """The narrowest interval any bin integrates over (rad)."""
        omega = self.ctx.feed(theta) / self.ctx.plan.radius_mm
        spans = [float(b.span_s.min()) for b in self.bins.values()]
        return omega * min(spans) * self.aperture_scale + self.smooth_rad

    def supported(self, A: np.ndarray, peak: np.ndarray) -> np.ndarray:
        """The columns of the weighted design ``A`` with data to stand on: at least ``MIN_SUPPORT`` samples'
        worth of their own ``peak`` (each column's largest absolute value, unweighted: the rule of
        :func:`.fit.solve`), and values above ``MIN_PEAK`` (a spike decayed long before the window would
        otherwise take any value)."""
        energy = np.einsum("ij,ij->j", A, A)
        return np.asarray((peak > MIN_PEAK) & (energy >= MIN_SUPPORT * peak * peak))

    def factor(self, theta: Theta) -> tuple[Factor, np.ndarray]:
        """The QR factor of ``[A | y]`` at ``theta`` for :func:`.fit.solve` (the bins weighted by their counts,
        the scatter within them as one more row of ``y`` alone, ``n`` the samples) and each column's largest
        absolute value over the bins (its largest radial effect per unit)."""
        A, y = self.rows(theta)
        colmax = self.colmax
        f = Factor(A.shape[1])
        f.add(np.vstack([A, np.zeros((1, A.shape[1]))]), np.append(y, math.sqrt(self.ss)))
        f.n = self.samples
        return f, colmax


class Normal:
    """The column-scaled normal equations of a design, factored once: least squares, and projections onto its
    columns, rank-deficient directions (eigenvalues below 1e-12 of the largest) left out."""

    def __init__(self, A: np.ndarray) -> None:
        G = A.T @ A
        scale = np.sqrt(np.diagonal(G)).copy()
        scale[scale == 0] = 1.0
        self.scale = scale
        Gs = G / np.outer(scale, scale)
        self.chol: np.ndarray | None = None
        self.pinv: np.ndarray | None = None
        try:
            c = np.linalg.cholesky(Gs)
            if float(np.diagonal(c).min(initial=1.0)) > 1e-7:
                self.chol = c
        except np.linalg.LinAlgError:
            pass
        if self.chol is None:
            vals, vecs = np.linalg.eigh(Gs)
            keep = vals > vals[-1] * 1e-12 if vals.size else np.zeros(0, dtype=bool)
            self.pinv = (vecs[:, keep] / vals[keep]) @ vecs[:, keep].T

    def solve(self, b: np.ndarray) -> np.ndarray:
        """``(A^T A)^+ b``, for ``b`` a vector or the columns of a matrix."""
        bs = b / (self.scale if b.ndim == 1 else self.scale[:, None])
        if self.chol is not None:
            z = np.linalg.solve(self.chol, bs)
            xs = np.linalg.solve(self.chol.T, z)
        else:
            assert self.pinv is not None
            xs = self.pinv @ bs
        return np.asarray(xs / (self.scale if b.ndim == 1 else self.scale[:, None]))


def solve_normal(A: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares by the column-scaled normal equations (:class:`Normal`)."""
    return Normal(A).solve(A.T @ y)


@dataclass
class Prior:
    """A Gaussian prior on one coordinate of :meth:`Theta.vector`: where the data cannot see it, it stays near
    ``mean``."""

    index: int
    mean: float
    sd: float


@dataclass
class Found:
    """The minimum :func:`minimise` found: its evaluation, and at it the data's ``J^T J`` (unscaled: per um^2
    of noise variance) and the priors' Hessian over the active coordinates (in :meth:`Theta.vector`'s units),
    the coefficients' change per unit of each (columns), and the objective."""

    best: Evaluation
    jtj: np.ndarray
    hprior: np.ndarray
    dx: np.ndarray
    active: list[int]
    phi: float
    iterations: int
    J: np.ndarray | None = None  # the Jacobian at the minimum (bins x active), to start a near search with

    def cov(self, noise_var: float) -> np.ndarray:
        """The active coordinates' covariance at a noise variance per sample (um^2, correlation counted).  A
        coordinate that moves nothing (no information, no prior: the spikes' width where there are none) has
        none: it moves no coefficient either."""
        H = self.jtj / noise_var + self.hprior
        d = np.diagonal(H)
        live = np.flatnonzero(d > 1e-12 * max(float(d.max(initial=0.0)), 1e-300))
        out = np.zeros_like(H)
        if live.size:
            # a curvature pieced together from two stages (:func:`.testfit._merge`) need not be positive
            # definite: its negative directions are no information, not negative variance
            vals, vecs = np.linalg.eigh(0.5 * (H[np.ix_(live, live)] + H[np.ix_(live, live)].T))
            floor = 1e-12 * max(float(vals.max(initial=0.0)), 1e-300)
            keep = vals > floor
            out[np.ix_(live, live)] = (vecs[:, keep] / vals[keep]) @ vecs[:, keep].T
        return out


def minimise(
    obj: Objective,
    start: Theta,
    active: Sequence[int],
    *,
    bounds: dict[int, tuple[float, float]],
    steps: dict[int, float],
    priors: Sequence[Prior] = (),
    tol: dict[int, float] | None = None,
    max_iter: int = 8,
    first: Evaluation | None = None,
    warm: Found | None = None,
    max_evals: int = 1_000,
) -> Found:
    """Gauss-Newton with Levenberg-Marquardt damping on the coordinates ``active`` of :meth:`Theta.vector`.

    The objective is the profile likelihood's, ``n ln SSE`` plus the priors' ``((v - mean) / sd)^2``: each
    step is Gauss-Newton's on ``|r|^2 / s^2`` with ``s^2`` the residual's variance per sample where it
    starts, at least ``NOISE_FLOOR_UM`` squared (so that a noise-free recording's tiny misfits do not
    outweigh the priors).  The Jacobian is the variable projection's (Kaufman's form: the residual's slope
    with the coefficients held, projected off the design's columns, :meth:`Objective.slopes`), made once
    (or taken from ``warm``, a minimum found on a near objective with the same bins) and then carried along
    by Broyden's secant updates, one design a step; it is made again where a step along it fails.  Stops
    when every step is below ``tol`` (default: a tenth of ``steps``), after ``max_iter`` steps, or once it
    has made ``max_evals`` designs.  Bounds are kept by clipping.
    """
    tau_known = start.tau is not None
    active = list(active)
    tol = tol or {k: 0.1 * steps[k] for k in active}
    pri = [p for p in priors if p.index in active]
    n = max(obj.samples, 1)

    def phi(e: Evaluation, nv: float) -> float:
        v = e.theta.vector()
        return (e.sse - obj.ss) / nv + sum(((v[p.index] - p.mean) / p.sd) ** 2 for p in pri)

    def clip(v: np.ndarray) -> np.ndarray:
        v = v.copy()
        for k, (lo, hi) in bounds.items():
            v[k] = min(max(v[k], lo), hi)
        return v

    spent = obj.designs
    here = first if first is not None else obj.evaluate(start)
    Hp = np.zeros((len(active), len(active)))
    for p in pri:
        Hp[active.index(p.index), active.index(p.index)] = 1.0 / p.sd**2
    J: np.ndarray | None = None
    dX = np.zeros((here.x.size, len(active)))
    fresh = False
    if warm is not None and warm.active == active and warm.J is not None and warm.J.shape[0] == here.r.size:
        J, dX = warm.J.copy(), warm.dx.copy()
    lam = 1e-3
    iterations = 0
    nv = max(here.sse / n, NOISE_FLOOR_UM**2)
    while iterations < max_iter and obj.designs - spent < max_evals:
        iterations += 1
        if J is None:
            if obj.designs - spent + _slope_designs(active) + 1 > max_evals:
                break  # no budget left for a step along new slopes
            J, dX = _jacobian(obj, here, active, steps)
            fresh = True
        nv = max(here.sse / n, NOISE_FLOOR_UM**2)
        f_here = phi(here, nv)
        v0 = here.theta.vector()
        rp = np.zeros(len(active))
        for p in pri:
            rp[active.index(p.index)] += (v0[p.index] - p.mean) / p.sd**2
        H = J.T @ J / nv + Hp
        g = J.T @ here.r / nv + rp
        dec = _decrement(H, g)
        if fresh and dec < DECREMENT:
            break  # within a small share of a standard error of the minimum: nothing left to gain
        trial = None
        failed: np.ndarray | None = None  # the last step that did not lower the objective
        for _ in range(4):
            if obj.designs - spent >= max_evals:
                break
            D = np.diag(np.maximum(np.diagonal(H), 1e-12))
            try:
                delta = -np.linalg.solve(H + lam * D, g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            if failed is not None and np.linalg.norm(delta - failed) < SAME_STEP * np.linalg.norm(failed):
                lam *= 8.0  # damped this little, the step is the one that failed: not worth a design
                continue
            v1 = clip(v0 + _embed(delta, active, v0.size))
            if np.allclose(v1, v0, rtol=0.0, atol=1e-15):
                break
            t = obj.evaluate(Theta.of(v1, tau_known))
            if phi(t, nv) <= f_here:
                trial = t
                lam = max(lam / 5.0, 1e-7)
                break
            failed = delta
            lam *= 8.0
            if not fresh:  # a carried Jacobian led astray: make it anew here before damping further
                break
        if trial is None:
            if fresh or obj.designs - spent >= max_evals:
                break
            J, lam = None, 1e-3  # made anew where the search stands
            continue
        step = (trial.theta.vector() - v0)[active]
        ss = float(step @ step)
        if BROYDEN and ss > 0:  # Broyden's update of the Jacobian and the coefficients' slopes along the step
            J += np.outer((trial.r - here.r) - J @ step, step) / ss
            dX += np.outer((trial.x - here.x) - dX @ step, step) / ss
            fresh = False
        here = trial
        if all(abs(step[j]) < tol[k] for j, k in enumerate(active)):
            break
        if fresh and dec < NEAR_DECREMENT and lam < 1e-2:
            # a full Gauss-Newton step from within a standard error of the minimum: the next decrement is of the
            # order of this one squared, and the slopes made here serve the covariance
            break
        if not BROYDEN:
            J = None
    if J is None:  # the slopes, for the covariance and the coefficients' spread
        J, dX = _jacobian(obj, here, active, steps)
    return Found(here, J.T @ J, Hp, dX, active, phi(here, nv), iterations, J)


def _slope_designs(active: Sequence[int]) -> int:
    """The designs :meth:`Objective.slopes` makes: one for the timing coordinates together, one each other."""
    timing = (*TIMING, SMOOTH)
    return int(any(k in timing for k in active)) + sum(k not in timing for k in active)


def _decrement(H: np.ndarray, g: np.ndarray) -> float:
    """Newton's decrement ``g^T H^-1 g``: twice the objective's predicted fall to the minimum of its quadratic."""
    try:
        return float(g @ np.linalg.solve(H, g))
    except np.linalg.LinAlgError:
        return math.inf


def _embed(delta: np.ndarray, active: Sequence[int], size: int) -> np.ndarray:
    out = np.zeros(size)
    out[list(active)] = delta
    return out


def _jacobian(
    obj: Objective, e: Evaluation, active: Sequence[int], steps: dict[int, float]
) -> tuple[np.ndarray, np.ndarray]:
    """The projected residual's Jacobian (bins x active) and the coefficients' change (all columns x active)."""
    assert e.A is not None and e.normal is not None and e.use is not None
    slopes = obj.slopes(e, active, steps)
    S = np.column_stack(slopes) if slopes else np.zeros((e.r.size, 0))
    coef = e.normal.solve(e.A.T @ S)  # the coefficients that take up each slope
    J = S - e.A @ coef  # projected off the design's columns
    dX = np.zeros((e.x.size, len(active)))
    dX[e.use] = coef
    return J, dX


__all__ = [
    "Binned", "Context", "Evaluation", "Found", "Objective", "Prior", "Theta", "feature_zones", "make_bins",
    "minimise", "solve_normal",
]
