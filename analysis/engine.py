"""From samples to results: one code path for the live daemon and offline files.

:class:`TestAnalyzer` is fed ``(t, length)`` chunks of any size.  It finds each
test (:mod:`.detect`), fits each circle as soon as its data arc has passed, and
fits the whole test (both directions jointly) after the feed-out.

Timing.  The angle of a sample comes from the feed-in's centroid and the
program's timing (:mod:`.program`), at a path feed ``V`` and a per-move
overhead ``c`` (the acceleration's delay).  A circle finishes before the
feed-out, so its *provisional* fit uses the programmed feed times the feed
ratio and overhead learnt on the previous test (``TimingHints``).  After the
feed-out the test's fit measures the feed from the centroid span, estimates the
overhead ``c`` (the arc start's lag) and the reversal spikes' width ``w`` by
maximising the profile likelihood of the full model (with a weak prior on ``c``
so that it stays near zero where the data cannot tell), and refits both circles
at those values: one pass over that test's own samples, none over older ones.

Breaks.  Every angle hangs on the time axis, so :class:`TestAnalyzer` watches
it (:mod:`.timeaxis`): a step backwards beyond jitter is a :class:`DataError`;
a gap longer than a few sample periods, and any break the caller tells it of
(:meth:`TestAnalyzer.mark_break`: a device reset, lost samples), rejects the
test it falls in (``test_rejected``, with the break's time and size), from the
feed-in step's first sample to the feed-out step's last.  Only a test that
passed, with a plausible feed, teaches the next one its timing hints.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import optimize

from . import iso230, noise
from .advice import advise
from .detect import StepEvent, TestDetector
from .errors import DataError, DetectionError
from .fit import Factor, FitResult, solve, sse_subset
from .patterns import Geometry, Pattern, design, select
from .physics import Offset, make_offset, takeup_angles
from .plan import AnalysisOptions, MachineConfig, TestPlan
from .program import Schedule, arc_start_deg, feed_from_span, model_limits, schedule
from .timeaxis import Break, TimeAxis

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
SEARCH_SAMPLES_PER_CIRCLE = 6000
LAG_PRIOR_S = 0.05
SSE_FLOOR_UM = 1e-3
DEFAULT_KV_PER_S = 30.0
TAIL_SAMPLES = 1.8  # samples per loop time constant the settling fit needs (6 within ~3.4 tau)
FAST_LOOP_S = 0.02  # a loop lag the settling fit must be able to see before "none seen" means "fast"
DEFAULT_SPIKE_WIDTH_DEG = 3.0
# A measured feed this far from the programmed one is not the machine's habit (controls hold the feed to well
# under 1 % at 100 % override): something else went wrong, and the next test must not assume it.
HINT_MAX_FEED_DEVIATION = 0.1


@dataclass
class TimingHints:
    """What the previous test taught: used for the provisional circle fits."""

    feed_ratio: float = 1.0
    overhead_s: float = 0.0
    spike_width_deg: float = DEFAULT_SPIKE_WIDTH_DEG

    @classmethod
    def learnt(cls, timing: dict[str, Any], before: TimingHints | None = None) -> TimingHints | None:
        """The hints a test result's ``timing`` teaches, or None where they are implausible.

        Implausible: a feed ratio more than ``HINT_MAX_FEED_DEVIATION`` from 1, or
        a value that is not a finite number.  ``before`` supplies the spike width
        where the test had none.
        """
        try:
            ratio = float(timing["feed_ratio"])
            overhead = float(timing["overhead_s"])
        except (KeyError, TypeError, ValueError):
            return None
        width = timing.get("spike_width_deg")
        if not (math.isfinite(ratio) and math.isfinite(overhead) and abs(ratio - 1.0) <= HINT_MAX_FEED_DEVIATION):
            return None
        if not (isinstance(width, int | float) and math.isfinite(width) and width > 0):
            width = (before or cls()).spike_width_deg
        return cls(ratio, overhead, float(width))


@dataclass
class Timing:
    feed_mm_s: float
    overhead_s: float
    sched: Schedule
    t_ref: float  # feed-in centroid (absolute)
    t_mid: float  # origin of the drift term (absolute): the feed-in centroid

    def window(self, d: int) -> tuple[float, float]:
        return self.t_ref + self.sched.data_start_s[d], self.t_ref + self.sched.data_end_s[d]


def make_timing(plan: TestPlan, t_ref: float, feed_mm_s: float, overhead_s: float) -> Timing:
    # The drift term's origin is the feed-in: radius_um is then the radius when the test began.
    return Timing(feed_mm_s, overhead_s, schedule(plan, feed_mm_s, overhead_s), t_ref, t_ref)


class CircleFit:
    """The growing fit of one direction's data arc at fixed timing and spike width.

    ``offset``: a physical correction (um) subtracted from the deviation before
    the masks see it (:mod:`.physics`).
    """

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig,
        patterns: Sequence[Pattern],
        direction: int,
        timing: Timing,
        spike_width_deg: float,
        keep_design: bool = False,
        offset: Offset | None = None,
        loop_lag_s: float | None = None,
        takeup_rad: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.plan, self.machine, self.patterns = plan, machine, list(patterns)
        self.loop_lag_s = loop_lag_s
        self.takeup_rad = takeup_rad
        self.d = direction
        self.timing = timing
        self.w = math.radians(spike_width_deg)
        self.p = sum(pat.q for pat in self.patterns)
        self.factor = Factor(self.p)
        self.colmax = np.zeros(self.p)
        self.t_start, self.t_end = timing.window(direction)
        self.keep_design = keep_design
        self.offset = offset
        self.kept: list[tuple[np.ndarray, Geometry, np.ndarray, np.ndarray]] = []  # (t, g, dR, A)

    def geometry(self, t: np.ndarray) -> Geometry:
        u = np.radians(self.timing.sched.angle_deg(self.plan, self.d, t - self.timing.t_ref))
        return Geometry(
            u=u,
            d=np.full(t.size, float(self.d)),
            t_min=(t - self.timing.t_mid) / 60.0,
            V=self.timing.feed_mm_s,
            R=self.plan.radius_mm,
            pitch_x_mm=self.machine.pitch_x_mm,
            pitch_y_mm=self.machine.pitch_y_mm,
            travel=self.d * (u - math.radians(arc_start_deg(self.plan, self.d))),
            loop_lag_s=self.loop_lag_s,
            takeup_rad=self.takeup_rad,
        )

    def add(self, t: np.ndarray, L: np.ndarray) -> None:
        """Fold in the samples of ``(t, L)`` that lie in this circle's data arc."""
        m = (t >= self.t_start) & (t <= self.t_end)
        if not m.any():
            return
        t, L = t[m], L[m]
        g = self.geometry(t)
        A = design(self.patterns, g, self.w)
        dr = (L - self.plan.radius_mm) * 1000.0
        self.factor.add(A, dr - self.offset(g) if self.offset is not None else dr)
        np.maximum(self.colmax, np.abs(A).max(axis=0), out=self.colmax)
        if self.keep_design:
            self.kept.append((t, g, dr, A))

    def refit(self, offset: Offset | None) -> None:
        """Refold the kept samples with another correction (the design is reused)."""
        self.offset = offset
        self.factor = Factor(self.p)
        for _t, g, dr, A in self.kept:
            self.factor.add(A, dr - offset(g) if offset is not None else dr)

    def corrected(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Kept ``(t, u, dR, A)`` with ``dR`` as measured minus the correction."""
        if not self.kept:
            return np.empty(0), np.empty(0), np.empty(0), np.empty((0, self.p))
        t = np.concatenate([k[0] for k in self.kept])
        u = np.concatenate([k[1].u for k in self.kept])
        dr = np.concatenate([k[2] - (self.offset(k[1]) if self.offset else 0.0) for k in self.kept])
        A = np.concatenate([k[3] for k in self.kept])
        return t, u, dr, A

    def measured(self) -> tuple[np.ndarray, np.ndarray]:
        """Kept ``(u, dR)`` as measured, for the ISO figures."""
        return (np.concatenate([k[1].u for k in self.kept]), np.concatenate([k[2] for k in self.kept]))


def _lag1(residuals: Sequence[np.ndarray]) -> float:
    num = sum(float(np.dot(r[1:], r[:-1])) for r in residuals if r.size > 1)
    den = sum(float(np.dot(r, r)) for r in residuals)
    return num / den if den > 0 else 0.0


class TestAnalyzer:
    """Streaming test detection and fitting; see the module docstring.

    :meth:`feed` returns result dictionaries as they complete: ``kind`` is
    ``"circle"`` (one direction, provisional timing) or ``"test"``; and event
    dictionaries (``kind = "event"``: ``feed_in``, ``feed_out``,
    ``test_rejected``, ``test_incomplete``).  A test is rejected as soon as a
    break in its time axis is seen (live: at once, not at its feed-out); its
    feed-out is still reported, and no result follows.
    """

    __test__ = False

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig | None = None,
        options: AnalysisOptions | None = None,
        hints: TimingHints | None = None,
        curves: bool = False,
    ) -> None:
        self.plan = plan
        self.curves = curves
        self.machine = machine or MachineConfig()
        self.options = options or AnalysisOptions()
        self.hints = hints or TimingHints()
        self.detector = TestDetector(plan)
        self.axis = TimeAxis()
        self.patterns = select(
            self.options.patterns, plan.direction_list, self.machine.pitch_x_mm, self.machine.pitch_y_mm
        )
        self.test_index = 0
        self._fi: StepEvent | None = None
        self._rejected = False  # the test in progress has been rejected
        self._circles: list[CircleFit] = []
        self._emitted: set[int] = set()
        self._added = 0
        self._breaks: list[Break] = []
        self.last_t = float("nan")

    def feed(self, t: np.ndarray, L: np.ndarray) -> list[dict[str, Any]]:
        """Take the next samples (times in seconds, any origin; lengths in mm).

        Raises :class:`DataError` for a non-finite value and
        :class:`~.timeaxis.TimeAxisError` for a time that runs backwards beyond
        jitter; nothing of the chunk is taken then.
        """
        t = np.asarray(t, dtype=float)
        L = np.asarray(L, dtype=float)
        if t.size and not (np.isfinite(t).all() and np.isfinite(L).all()):
            k = int(np.argmax(~(np.isfinite(t) & np.isfinite(L))))
            raise DataError(f"sample {self.detector.n_seen + k}: time or length is not a finite number")
        self._breaks.extend(self.axis.check(t))
        if t.size:
            self.last_t = float(t[-1])
        self.detector.feed(t, L)
        return self._drain()

    def mark_break(self, reason: str) -> None:
        """A discontinuity between the samples fed so far and the next ones, which the times may not show.

        ``reason`` names it in the rejection's message (``"device reset"``,
        ``"1200 samples lost (outage)"``).  A test it falls in is rejected.
        """
        self.axis.mark(reason)

    def abort(self, reason: str) -> list[dict[str, Any]]:
        """The stream cannot go on as it is (the caller starts afresh): reject the test in progress, if any."""
        if self._fi is None or self._rejected:
            return []
        fi = self._fi
        return [self._reject(self.last_t, None, f"{reason}, {self.last_t - fi.t_s:.1f} s after the feed-in at "
                             f"t={fi.t_s:.3f} s: the test in progress is abandoned")]

    def finish(self) -> list[dict[str, Any]]:
        """End of the stream: settle the last step; report a test left unfinished."""
        self.detector.finish()
        out = self._drain()
        if self._fi is not None and not self._rejected:
            out.append(
                {
                    "kind": "event",
                    "event": "test_incomplete",
                    "test_index": self.test_index,
                    "t_s": self.last_t,
                    "message": f"the stream ended {self.last_t - self._fi.t_s:.1f} s after the feed-in "
                    f"at t={self._fi.t_s:.3f} s, before the feed-out",
                }
            )
        return out

    def _drain(self) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        while True:
            ev = self.detector.poll()
            if ev is None:
                break
            if self.axis.forward_steps == 0:
                raise DataError(
                    f"the time does not advance: all {self.axis.n} samples so far have t={self.axis.first_t:g} s"
                )
            if ev.kind == "feed_in":
                self._start(ev)
                out.append(_event(ev, self.test_index))
                continue
            assert self._fi is not None
            if not self._rejected and (brk := self._break_in(self._fi.t_begin_s, ev.t_end_s)) is not None:
                out.append(self._break_rejection(brk))
            if self._rejected:
                out.append(_event(ev, self.test_index))
                self._fi, self._rejected = None, False
                continue
            out.extend(self._advance(final=True))
            out.append(_event(ev, self.test_index))
            out.extend(self._finish_test(ev))
        if self._fi is not None and not self._rejected:
            brk = self._break_in(self._fi.t_begin_s, math.inf)
            if brk is not None:
                out.append(self._break_rejection(brk))
            else:
                out.extend(self._advance(final=False))
        if self._fi is None and self._breaks:
            # a later test begins after the first sample the detector still holds
            tb, _ = self.detector.samples()
            first = float(tb.min()) if tb.size else self.last_t
            self._breaks = [b for b in self._breaks if b.t_after >= first]
        return out

    def _break_in(self, t0: float, t1: float) -> Break | None:
        """The first break between the samples at ``t0`` and ``t1`` (a test's first and last step sample)."""
        return next((b for b in self._breaks if b.t_after > t0 and b.t_before < t1), None)

    def _break_rejection(self, brk: Break) -> dict[str, Any]:
        assert self._fi is not None
        fi = self._fi
        where = ("during the feed-in" if brk.t_after <= fi.t_end_s
                 else f"{brk.t_after - fi.t_s:.1f} s after the feed-in at t={fi.t_s:.3f} s")
        return self._reject(
            brk.t_after, brk.missing_s if brk.visible else None,
            f"{brk.describe()}, {where}: the test spans a break in its time axis, so its feed and angles "
            "cannot be trusted; run it again",
        )

    def _reject(self, t_s: float, gap_s: float | None, message: str) -> dict[str, Any]:
        self._rejected = True
        self._circles = []
        log.info("test %d rejected: %s", self.test_index, message)
        ev: dict[str, Any] = {"kind": "event", "event": "test_rejected", "test_index": self.test_index,
                              "t_s": t_s, "message": message}
        if gap_s is not None:
            ev["gap_s"] = gap_s
        return ev

    def _start(self, fi: StepEvent) -> None:
        self.test_index += 1
        self._fi = fi
        self._rejected = False
        V = self.plan.feed_mm_s * self.hints.feed_ratio
        timing = make_timing(self.plan, fi.t_s, V, self.hints.overhead_s)
        self._circles = [
            CircleFit(self.plan, self.machine, _for_direction(self.patterns, d), d, timing, self.hints.spike_width_deg)
            for d in self.plan.direction_list
        ]
        self._emitted = set()
        self._added = 0

    def _advance(self, final: bool) -> list[dict[str, Any]]:
        """Fold new samples into the running circles; emit the circles now complete."""
        tb, Lb = self.detector.samples()
        if self._added < tb.size:
            t_new, L_new = tb[self._added :], Lb[self._added :]
            for c in self._circles:
                c.add(t_new, L_new)
            self._added = tb.size
        out = []
        t_last = tb[-1] if tb.size else -math.inf
        for c in self._circles:
            if c.d in self._emitted or (t_last < c.t_end and not final):
                continue
            self._emitted.add(c.d)
            if c.factor.n < c.p + 2:
                continue
            try:
                fit = solve(c.factor, c.patterns, significance=self.options.significance,
                            vif_limit=self.options.vif_limit, effect_scale=c.colmax)
            except (np.linalg.LinAlgError, ValueError) as err:  # pragma: no cover - defensive
                log.warning("circle fit failed: %s", err)
                continue
            out.append(self._circle_result(c, fit))
        return out

    def _circle_result(self, c: CircleFit, fit: FitResult) -> dict[str, Any]:
        res = _result_body(self.plan, self.machine, self.options, fit, c.patterns)
        res.update(
            kind="circle",
            direction="ccw" if c.d > 0 else "cw",
            test_index=self.test_index,
            timing={
                "provisional": True,
                "feed_in_s": c.timing.t_ref,
                "assumed_feed_mm_min": c.timing.feed_mm_s * 60.0,
                "assumed_overhead_s": c.timing.overhead_s,
                "data_start_s": c.t_start,
                "data_end_s": c.t_end,
                "spike_width_deg": math.degrees(c.w),
            },
            residual_rms_um=math.sqrt(fit.sse / max(fit.n, 1)),
        )
        return res

    def _finish_test(self, fo: StepEvent) -> list[dict[str, Any]]:
        assert self._fi is not None
        fi, self._fi = self._fi, None
        tb, Lb = self.detector.samples()
        m = (tb >= fi.t_begin_s) & (tb <= fo.t_end_s)
        try:
            result = analyze_test(self.plan, self.machine, self.options, tb[m], Lb[m], fi, fo, curves=self.curves)
        except DataError as err:
            return [{"kind": "event", "event": "test_rejected", "test_index": self.test_index,
                     "t_s": fo.t_s, "message": str(err)}]
        result["test_index"] = self.test_index
        hints = TimingHints.learnt(result["timing"], self.hints)
        if hints is None:
            log.warning("test %d: a measured feed of %.1f mm/min (programmed %g) is no timing hint for the next "
                        "test's provisional circles", self.test_index, result["timing"]["measured_feed_mm_min"],
                        self.plan.feed_mm_min)
        else:
            self.hints = hints
        return [result]


def _event(ev: StepEvent, test_index: int) -> dict[str, Any]:
    return {
        "kind": "event",
        "event": ev.kind,
        "test_index": test_index,
        "t_s": ev.t_s,
        "height_mm": ev.height_mm,
        "method": ev.method,
    }


def _for_direction(patterns: Sequence[Pattern], d: int) -> list[Pattern]:
    return [p for p in patterns if p.reversal is None or p.reversal[2] == d]


# --------------------------------------------------------------------------- whole test


def check_plan(plan: TestPlan, fi: StepEvent, fo: StepEvent) -> float:
    """Raise DataError where the recording does not match the plan; return the feed (mm/s) at c = 0."""
    f = plan.feed_in_mm
    for ev in (fi, fo):
        if not 0.75 * f <= ev.height_mm <= 1.25 * f:
            raise DataError(
                f"plan does not match the data: the {ev.kind.replace('_', '-')} at t={ev.t_s:.3f} s "
                f"is a {ev.height_mm:.3f} mm step, the plan's feed-in is {f:g} mm"
            )
    span = fo.t_s - fi.t_s
    V0 = feed_from_span(plan, span, 0.0)
    nominal = schedule(plan, plan.feed_mm_s).feed_out_centroid_s
    if not (math.isfinite(V0) and 0.5 <= V0 / plan.feed_mm_s <= 1.5):
        raise DataError(
            f"plan does not match the data: feed-in to feed-out takes {span:.2f} s, the plan's program "
            f"takes {nominal:.2f} s at {plan.feed_mm_min:g} mm/min (check feed, radius, arcs and dwell)"
        )
    return V0


@dataclass
class _Hyper:
    overhead_s: float = 0.0
    spike_width_deg: float = DEFAULT_SPIKE_WIDTH_DEG
    lag_stderr_s: float = float("nan")


def _has_spikes(patterns: Sequence[Pattern]) -> bool:
    return any(p.reversal is not None for p in patterns)


class _Joint:
    """Both circles of one test at one timing, spike width and correction."""

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig,
        patterns: Sequence[Pattern],
        timing: Timing,
        spike_width_deg: float,
        t: np.ndarray,
        L: np.ndarray,
        offset: Offset | None,
        keep: bool,
        windows: dict[int, tuple[float, float]] | None = None,
        loop_lag_s: float | None = None,
        takeup_rad: tuple[float, float] = (0.0, 0.0),
    ) -> None:
        self.patterns = list(patterns)
        self.circles: list[CircleFit] = []
        for d in plan.direction_list:
            cf = CircleFit(
                plan, machine, _for_direction(patterns, d), d, timing, spike_width_deg, keep, offset, loop_lag_s,
                takeup_rad,
            )
            if windows is not None:
                cf.t_start, cf.t_end = windows[d]  # the same samples whatever the timing
            cf.add(t, L)
            self.circles.append(cf)

    def factor(self) -> Factor:
        f = _embed(self.circles[0].factor, self.circles[0].patterns, self.patterns)
        for c in self.circles[1:]:
            f = f.merged(_embed(c.factor, c.patterns, self.patterns))
        return f

    def colmax(self) -> np.ndarray:
        out = np.zeros(sum(p.q for p in self.patterns))
        for c in self.circles:
            out = np.maximum(out, _embed_vec(c.colmax, c.patterns, self.patterns))
        return out

    def residuals(self, x: np.ndarray) -> list[np.ndarray]:
        """Per circle: the corrected deviation minus the model at ``x`` (NaN: left out)."""
        x = np.nan_to_num(x)
        out = []
        for c in self.circles:
            _, _, dr, A = c.corrected()
            out.append(dr - A @ _take(x, c.patterns, self.patterns))
        return out

    def solve(self, options: AnalysisOptions, rho: float = 0.0) -> FitResult:
        return solve(self.factor(), self.patterns, rho=rho, significance=options.significance,
                     vif_limit=options.vif_limit, effect_scale=self.colmax())


def _values(fit: FitResult) -> dict[str, float]:
    out: dict[str, float] = {}
    j = 0
    for pat, used in zip(fit.patterns, fit.used, strict=True):
        for k, f in enumerate(pat.fields):
            if used:
                out[f] = float(fit.x[j + k])
        j += pat.q
    return out


def _search(
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    patterns: Sequence[Pattern],
    ts: np.ndarray,
    Ls: np.ndarray,
    fi: StepEvent,
    span: float,
    base: Timing,
    windows: dict[int, tuple[float, float]],
    offset: Offset | None,
    n_eff: float,
    tau: float | None,
    takeup: tuple[float, float],
) -> _Hyper:
    """Estimate the per-move overhead (the arc start's lag) and the spike width.

    The objective is the profile negative log-likelihood of the full model on a
    decimated, fixed set of samples, ``(n_eff / 2) ln SSE``, plus ``c^2 / (2 s^2)``
    with ``s`` = 50 ms: where the data cannot see the lag, it stays near zero.
    """
    hyper = _Hyper()

    def sse(c: float, w_deg: float) -> float:
        timing = make_timing(plan, fi.t_s, feed_from_span(plan, span, c), c)
        timing.t_mid = base.t_mid
        f = _Joint(plan, machine, patterns, timing, w_deg, ts, Ls, offset, False, windows, tau, takeup).factor()
        return sse_subset(f.rows, range(f.p))

    # A residual below 1 nm rms is numerical, not signal: there the prior decides.
    floor = ts.size * SSE_FLOOR_UM**2
    spikes = _has_spikes(patterns)
    lo_w, hi_w = math.log(options.spike_width_min_deg), math.log(options.spike_width_max_deg)
    c, w = 0.0, hyper.spike_width_deg
    for _round in range(2):
        if spikes:
            r = optimize.minimize_scalar(lambda lw, c=c: sse(c, math.exp(lw)), bounds=(lo_w, hi_w),
                                         method="bounded", options={"xatol": 0.01})
            w = float(math.exp(r.x))
        if options.estimate_lag:
            def obj(cc: float, w: float = w) -> float:
                return 0.5 * n_eff * math.log(sse(cc, w) + floor) + cc * cc / (2 * LAG_PRIOR_S**2)
            r = optimize.minimize_scalar(obj, bounds=(-options.max_lag_s, options.max_lag_s),
                                         method="bounded", options={"xatol": 1e-5})
            c = float(r.x)
            h = 1e-3
            curv = (obj(c + h) - 2 * obj(c) + obj(c - h)) / h**2
            hyper.lag_stderr_s = 1.0 / math.sqrt(curv) if curv > 0 else float("inf")
        if not spikes:
            break
    hyper.overhead_s, hyper.spike_width_deg = c, w
    return hyper


def _embed(f: Factor, sub: Sequence[Pattern], full: Sequence[Pattern]) -> Factor:
    """Factor of ``sub``'s columns placed within ``full``'s (missing columns zero)."""
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    cols: list[int] = []
    for p in sub:
        cols.extend(range(pos[p.name], pos[p.name] + p.q))
    out = Factor(j)
    R = f.rows if f.R.shape[0] else f.R
    M = np.zeros((R.shape[0], j + 1))
    M[:, cols] = R[:, :-1]
    M[:, -1] = R[:, -1]
    out.R, out.n = M, f.n
    return out


def loop_lag(
    plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, fi: StepEvent, fo: StepEvent, sample_hz: float
) -> tuple[float | None, float | None, str]:
    """Position-loop lag for the physical servo model: ``(tau, cos2, source)``.

    ``tau`` (s): the mean lag ``(1/KX + 1/KY)/2`` from configured gains (``cos2``
    None), or the lag measured along the feed-in/out's radial direction, which
    is ``tau_bar + (m/2) cos 2u`` at angle ``u``: ``cos2`` is that mean ``cos 2u``.
    Where no settling was seen although the rate would have shown a loop slower
    than ``FAST_LOOP_S``, the loops are fast: no correction.  Else the lag is
    assumed (a common default gain), and the result says so.
    """
    if options.servo_model == "linear":
        return None, None, "linear model chosen"
    if machine.kv_x_per_s and machine.kv_y_per_s:
        return 0.5 * (1.0 / machine.kv_x_per_s + 1.0 / machine.kv_y_per_s), None, "configured gains kv_x, kv_y"
    u_in = math.radians(arc_start_deg(plan, plan.direction_list[0]))
    resolvable_s = TAIL_SAMPLES / sample_hz if sample_hz > 0 else math.inf
    u_last = math.radians(arc_start_deg(plan, plan.direction_list[-1]))
    u_out = u_last + plan.direction_list[-1] * math.radians(plan.arc_deg)
    found = [(e.tau_s, math.cos(2 * u)) for e, u in ((fi, u_in), (fo, u_out)) if math.isfinite(e.tau_s)]
    if found:
        return (
            float(np.mean([f[0] for f in found])),
            float(np.mean([f[1] for f in found])),
            "approach of the feed-in/feed-out to the circle (first-order loop fit)",
        )
    if resolvable_s <= FAST_LOOP_S:
        # A loop as slow as machines' usually are would have shown its settling at this rate.
        return None, None, (
            f"no loop settling after the feed-in: the position loops are faster than {resolvable_s * 1000:.0f} ms "
            "at this sample rate (no servo dynamics to correct)"
        )
    return (
        1.0 / DEFAULT_KV_PER_S,
        None,
        f"assumed {DEFAULT_KV_PER_S:g}/s (a common default position gain): the feed-in's settling is not "
        "resolved at this sample rate and no kv_x/kv_y is configured",
    )


def analyze_test(
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    t: np.ndarray,
    L: np.ndarray,
    fi: StepEvent,
    fo: StepEvent,
    curves: bool = False,
) -> dict[str, Any]:
    """The joint fit of one test whose feed-in and feed-out are known.

    ``curves``: also return, under ``"curves"``, each data arc's samples as
    numpy arrays (not JSON; for plots): ``t_s``, ``u_deg`` (commanded angle at
    the fitted timing), ``measured_um`` (``L - R``) and ``model_um`` (the
    fitted model in the same space, physical corrections included, so that
    ``measured_um - model_um`` is the fit's residual).
    """
    check_plan(plan, fi, fo)
    span = fo.t_s - fi.t_s
    patterns = select(options.patterns, plan.direction_list, machine.pitch_x_mm, machine.pitch_y_mm)
    tau, cos2, tau_source = loop_lag(plan, machine, options, fi, fo, _rate(t))
    # 1. A preliminary fit on a decimated, fixed sample set: the corrections' first values.
    base = make_timing(plan, fi.t_s, feed_from_span(plan, span, 0.0), 0.0)
    margin = options.max_lag_s * 1.5 * base.feed_mm_s / plan.radius_mm  # rad
    windows = {}
    for d in plan.direction_list:
        a, b = base.window(d)
        trim = margin * plan.radius_mm / base.feed_mm_s
        windows[d] = (a + trim, b - trim) if b - a > 4 * trim else (a, b)
    sel = np.zeros(t.size, dtype=bool)
    for a, b in windows.values():
        sel |= (t >= a) & (t <= b)
    idx = np.flatnonzero(sel)
    step = max(1, idx.size // (SEARCH_SAMPLES_PER_CIRCLE * len(plan.direction_list)))
    ts, Ls = t[idx[::step]], L[idx[::step]]
    hyper = _Hyper()
    offset = None
    takeup = (0.0, 0.0)
    if ts.size > 50:
        pre = _Joint(plan, machine, patterns, base, hyper.spike_width_deg, ts, Ls, None, True, windows, tau)
        pre_fit = pre.solve(options)
        rho = _lag1(pre.residuals(pre_fit.x))
        kappa = min(max((1 + rho) / (1 - rho), 1.0), 400.0) if rho < 1 else 400.0
        offset = make_offset(_values(pre_fit), tau, options.lost_motion, cos2)
        if options.lost_motion == "deadband":
            takeup = takeup_angles(_values(pre_fit), plan.radius_mm)
        # 2. Lag and spike width on that set, with the corrections applied.
        hyper = _search(
            plan, machine, options, patterns, ts, Ls, fi, span, base, windows, offset, ts.size / kappa, tau, takeup
        )
    # 3. The full fit at those values, then the corrections to a fixed point.
    V = feed_from_span(plan, span, hyper.overhead_s)
    timing = make_timing(plan, fi.t_s, V, hyper.overhead_s)
    joint = _Joint(plan, machine, patterns, timing, hyper.spike_width_deg, t, L, offset, True, None, tau, takeup)
    for c in joint.circles:
        if c.factor.n < 8:
            raise DataError(
                f"the {'CCW' if c.d > 0 else 'CW'} data arc ({c.t_start:.2f}..{c.t_end:.2f} s) holds "
                f"{c.factor.n} samples: too few to fit"
            )
    fit = joint.solve(options)
    for _ in range(2):
        offset = make_offset(_values(fit), tau, options.lost_motion, cos2)
        if offset is None and all(c.offset is None for c in joint.circles):
            break
        for c in joint.circles:
            c.refit(offset)
        fit = joint.solve(options)
    residuals = joint.residuals(fit.x)
    fit = joint.solve(options, rho=_lag1(residuals))
    res = _result_body(plan, machine, options, fit, patterns)
    res["fit"]["servo_model"] = "physical" if tau is not None else "linear"
    res["fit"]["servo_model_note"] = tau_source
    res["fit"]["lost_motion_model"] = (
        "dead band: take-up after reversals (backlash > 0)" if options.lost_motion == "deadband" else "step"
    )
    sample_hz = _rate(t)
    res["kind"] = "test"
    res["timing"] = _timing_dict(plan, fi, fo, timing, hyper, V)
    res["timing"]["loop_lag_ms"] = tau * 1000.0 if tau is not None else None
    res["timing"]["loop_lag_source"] = tau_source
    res["timing"]["loop_lag_radial_cos2u"] = cos2
    res["timing"]["backlash_takeup_deg"] = {"x": math.degrees(takeup[0]), "y": math.degrees(takeup[1])}
    # The arc-start lag of a trapezoid profile is V / A: a plan whose data arcs begin before the feed is
    # reached at that acceleration leaves the timing model, and the measured feed and angles with it.
    if hyper.overhead_s > 0 and math.isfinite(hyper.overhead_s):
        limits = model_limits(plan.with_(feed_mm_min=V * 60.0), V / hyper.overhead_s)
        if limits:
            res["warnings"] = [
                f"timing model: {why} (acceleration from the measured arc-start lag); the measured feed and the "
                "angles are biased: lengthen overshoot_deg" for why in limits
            ]
    res["iso230_4"] = iso230.figures({c.d: c.measured() for c in joint.circles})
    res["iso230_4"]["conditions"] = iso230.conditions(plan.to_dict(), V * 60.0, sample_hz)
    res["noise"] = noise.findings(
        [(c.corrected()[1], r, plan.data_arc_deg, sample_hz) for c, r in zip(joint.circles, residuals, strict=True)],
        options.vibration_cutoff_cpr,
    )
    if curves:
        res["curves"] = {}
        for c, r in zip(joint.circles, residuals, strict=True):
            uc, dr = c.measured()  # not corrected(): that would rebuild the correction and the design
            res["curves"]["ccw" if c.d > 0 else "cw"] = {
                "t_s": np.concatenate([k[0] for k in c.kept]), "u_deg": np.degrees(uc), "measured_um": dr,
                "model_um": dr - r,
            }
    all_r = np.concatenate(residuals)
    res["residual_rms_um"] = float(np.sqrt(np.mean(all_r**2)))
    res["samples"] = {
        "in_test": int(t.size),
        "in_data_arcs": int(sum(c.factor.n for c in joint.circles)),
        "sample_hz": sample_hz,
    }
    return res


def _embed_vec(v: np.ndarray, sub: Sequence[Pattern], full: Sequence[Pattern]) -> np.ndarray:
    out = np.zeros(sum(p.q for p in full))
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    k = 0
    for p in sub:
        out[pos[p.name] : pos[p.name] + p.q] = v[k : k + p.q]
        k += p.q
    return out


def _take(x: np.ndarray, sub: Sequence[Pattern], full: Sequence[Pattern]) -> np.ndarray:
    pos, j = {}, 0
    for p in full:
        pos[p.name] = j
        j += p.q
    return np.concatenate([x[pos[p.name] : pos[p.name] + p.q] for p in sub])


def _rate(t: np.ndarray) -> float:
    if t.size < 2:
        return float("nan")
    return float(1.0 / np.median(np.diff(t)))


def _timing_dict(
    plan: TestPlan, fi: StepEvent, fo: StepEvent, timing: Timing, hyper: _Hyper, V: float
) -> dict[str, Any]:
    omega = V / plan.radius_mm  # rad/s
    out: dict[str, Any] = {
        "provisional": False,
        "programmed_feed_mm_min": plan.feed_mm_min,
        "measured_feed_mm_min": V * 60.0,
        "feed_ratio": V / plan.feed_mm_s,
        "overhead_s": hyper.overhead_s,
        "lag_s": hyper.overhead_s,
        "lag_deg": math.degrees(omega * hyper.overhead_s),
        "lag_stderr_s": hyper.lag_stderr_s if math.isfinite(hyper.lag_stderr_s) else None,
        "spike_width_deg": hyper.spike_width_deg,
        "feed_in_s": fi.t_s,
        "feed_out_s": fo.t_s,
        "feed_in_method": fi.method,
        "feed_out_method": fo.method,
        "feed_in_height_mm": fi.height_mm,
        "feed_out_height_mm": fo.height_mm,
        "data_arcs": {
            ("ccw" if d > 0 else "cw"): {"start_s": timing.window(d)[0], "end_s": timing.window(d)[1]}
            for d in plan.direction_list
        },
        "method": (
            "feed from the feed-in to feed-out centroid span; arc-start lag (per-move overhead) "
            "and spike width by profile likelihood of the full model"
        ),
    }
    return out


# --------------------------------------------------------------------------- result body


def _result_body(
    plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, fit: FitResult, patterns: Sequence[Pattern]
) -> dict[str, Any]:
    from .report import parameters_dict, ranking_list

    params = parameters_dict(fit, patterns, machine)
    return {
        "schema_version": SCHEMA_VERSION,
        "plan": plan.to_dict(),
        "machine": machine.to_dict(),
        "parameters": params,
        "ranking": ranking_list(fit),
        "advice": advise(params, plan, machine),
        "fit": {
            "n_samples": fit.n,
            "n_parameters": fit.p,
            "dof": fit.dof,
            "sigma_um": fit.sigma,
            "residual_lag1_autocorrelation": fit.rho,
            "variance_inflation": fit.kappa,
            "condition_number": fit.condition if math.isfinite(fit.condition) else None,
            "significance": options.significance,
            "servo_model": "linear",
            "uncertainty_method": (
                "least squares covariance sigma^2 (A^T A)^-1 with sigma^2 = SSE/(n-p), inflated by "
                "(1+rho)/(1-rho) for the residual's lag-1 autocorrelation rho (AR(1) effective sample "
                "count); F-tests use the same inflated variance"
            ),
        },
    }


def analyze_recording(
    t: np.ndarray,
    L: np.ndarray,
    plan: TestPlan,
    machine: MachineConfig | None = None,
    options: AnalysisOptions | None = None,
    curves: bool = False,
    breaks: Sequence[tuple[int, str]] = (),
) -> list[dict[str, Any]]:
    """Everything :class:`TestAnalyzer` reports on a whole recording, in order.

    ``curves``: see :func:`analyze_test`.  ``breaks``: ``(index, reason)``, a
    discontinuity the times may not show (a device reset) just before sample
    ``index`` (:meth:`TestAnalyzer.mark_break`).
    """
    t = np.asarray(t, dtype=float)
    L = np.asarray(L, dtype=float)
    if t.size >= 2 and np.all(np.isfinite(t)) and not np.any(np.diff(t) > 0):
        what = f"all {t.size} samples have t={t[0]:g} s" if np.all(t == t[0]) else "it never increases"
        raise DataError(f"the time axis does not advance ({what}): no test can be timed")
    an = TestAnalyzer(plan, machine, options, curves=curves)
    out: list[dict[str, Any]] = []
    i = 0
    for j, reason in sorted(breaks, key=lambda b: b[0]):
        j = min(max(int(j), i), t.size)
        out.extend(an.feed(t[i:j], L[i:j]))
        an.mark_break(reason)
        i = j
    out.extend(an.feed(t[i:], L[i:]))
    out.extend(an.finish())
    if not any(r.get("event") == "feed_in" for r in out):
        lo, hi = an.detector.seen_range()
        raise DetectionError(
            f"no feed-in found: the bar never stepped from about {plan.radius_mm + plan.feed_in_mm:g} mm "
            f"(R + feed-in) to {plan.radius_mm:g} mm (R); its length ranged {lo:.4f}..{hi:.4f} mm"
        )
    return out


__all__ = ["HINT_MAX_FEED_DEVIATION", "CircleFit", "TestAnalyzer", "TimingHints", "analyze_recording", "analyze_test"]
