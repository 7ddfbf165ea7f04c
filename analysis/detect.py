"""Test detection on a stream of ``(t, length)`` samples.

The feed-in is a radial step of ``f`` (1.5 mm by default) from about ``R + f``
down to about ``R``; the feed-out the same step back up.  Against micrometre
contouring errors they are unmistakable, so the detector works on levels: a
sample is *out* when within ``f/4`` of ``R + f`` and *on* when within ``f/4`` of
``R``.  A feed-in is the passage from out to on; a feed-out from on to out.

Each step's time is its centroid ``sum(t dL) / sum(dL)``, the mean time of the
length change.  For any linear servo and any symmetric acceleration profile
that is the commanded move's middle plus the loop's mean delay, the same delay
by which the machine's actual position trails the command on the arcs: the
angles assigned from it are the actual ones.  Where the step holds fewer than
six samples (a low sample rate), the centroid comes from the samples inside the
step on a ramp of the programmed feed instead.

The detector is fed chunks of any size (one sample to a whole file) and keeps
only what it needs: the samples since the last feed-in while a test runs, a few
seconds before that.  A whole file is simply one chunk.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .plan import TestPlan

log = logging.getLogger(__name__)

BAND = 0.25  # of the feed-in distance: how close to R or R + f counts as "on" or "out"
PRE_KEEP_S = 5.0  # samples kept before a feed-in while waiting for one
SETTLE_S = (0.4, 0.8)  # window after a step's band entry that gives the new level (within the dwell)
CENTROID_INNER = 5  # samples inside a step from which its centroid is summed whatever their spacing
CENTROID_INNER_EVEN = 3  # ... and from which it is summed where they are evenly spaced (no sample lost)
EVEN_GAP = 1.5  # a step's samples are evenly spaced where no interval exceeds this many times their median


@dataclass(frozen=True)
class StepEvent:
    """A feed-in (``kind = "feed_in"``) or feed-out step."""

    kind: str
    t_s: float  # centroid time
    t_begin_s: float  # last sample on the level before the step
    t_end_s: float  # first sample settled on the level after it
    level_before_mm: float
    level_after_mm: float
    samples_in_step: int
    method: str  # "centroid" or "ramp"
    tau_s: float = float("nan")  # time constant of the approach to the new level (position loop), if resolved
    move_var_s2: float = float("nan")  # variance in time of the commanded move's velocity profile, if resolved

    @property
    def height_mm(self) -> float:
        return abs(self.level_after_mm - self.level_before_mm)


class _Buffer:
    """Growable (t, L) storage without quadratic copying.

    An empty buffer may *borrow* a chunk (:meth:`extend` with ``borrow``):
    it keeps views of the caller's arrays instead of a copy, drops samples
    by slicing them, and copies only when more samples come.
    """

    def __init__(self) -> None:
        self.t = np.empty(1024)
        self.L = np.empty(1024)
        self.n = 0
        self.borrowed = False

    def extend(self, t: np.ndarray, L: np.ndarray, borrow: bool = False) -> None:
        if borrow and self.n == 0:
            self.t, self.L, self.n, self.borrowed = t, L, t.size, True
            return
        need = self.n + t.size
        if need > self.t.size or self.borrowed:
            cap = max(need, 2 * self.t.size)
            for name in ("t", "L"):
                new = np.empty(cap)
                new[: self.n] = getattr(self, name)[: self.n]
                setattr(self, name, new)
            self.borrowed = False
        self.t[self.n : need] = t
        self.L[self.n : need] = L
        self.n = need

    def drop_before(self, k: int) -> None:
        if k <= 0:
            return
        rest = self.n - k
        if self.borrowed:
            self.t, self.L = self.t[k : self.n], self.L[k : self.n]
        else:
            self.t[:rest] = self.t[k : self.n]
            self.L[:rest] = self.L[k : self.n]
        self.n = rest

    def view(self) -> tuple[np.ndarray, np.ndarray]:
        return self.t[: self.n], self.L[: self.n]


class TestDetector:
    """Finds feed-in and feed-out steps in a stream, chunk by chunk.

    :meth:`feed` returns the steps completed by the chunk.  A step counts as
    complete once the length has settled on the new level (or the test's
    samples run on past it), so a step split across chunks is found once.
    """

    __test__ = False

    def __init__(self, plan: TestPlan) -> None:
        self.plan = plan
        self.f = plan.feed_in_mm
        self.high = plan.radius_mm + plan.feed_in_mm
        self.low = plan.radius_mm
        self.buf = _Buffer()
        self.in_test = False
        self.scan_from = 0  # index into buf from which to look for the next transition
        self.lmin = np.inf
        self.lmax = -np.inf
        self.n_seen = 0
        self.final = False
        self._in_shape: tuple[np.ndarray, np.ndarray] | None = None

    # What the samples held, for the error message when nothing was found.
    def seen_range(self) -> tuple[float, float]:
        return float(self.lmin), float(self.lmax)

    def feed(self, t: np.ndarray, L: np.ndarray, borrow: bool = False) -> None:
        """Append a chunk; then call :meth:`poll` until it returns None.

        ``borrow``: where nothing is held yet, keep views of ``t`` and ``L``
        rather than a copy (the caller leaves them unchanged from then on).
        """
        t = np.asarray(t, dtype=float)
        L = np.asarray(L, dtype=float)
        if t.size == 0:
            return
        self.n_seen += t.size
        self.lmin = min(self.lmin, float(L.min()))
        self.lmax = max(self.lmax, float(L.max()))
        self.buf.extend(t, L, borrow)

    def poll(self) -> StepEvent | None:
        """The next completed step, or None when the samples so far hold no more.

        After a feed-out the test's samples stay readable through
        :meth:`samples` until the next call of :meth:`poll`.
        """
        ev = self._next_step()
        if ev is None and not self.in_test:
            tb, _ = self.buf.view()
            if tb.size:
                keep_from = int(np.searchsorted(tb, tb[-1] - PRE_KEEP_S))
                keep_from = min(keep_from, self.scan_from)
                self.buf.drop_before(keep_from)
                self.scan_from -= keep_from
        return ev

    def finish(self) -> None:
        """The stream has ended: settle on whatever follows the last step."""
        self.final = True

    def feed_all(self, t: np.ndarray, L: np.ndarray) -> list[StepEvent]:
        """Feed a chunk and return every step it completes (samples not kept)."""
        self.feed(t, L)
        out = []
        while (ev := self.poll()) is not None:
            out.append(ev)
        return out

    def _next_step(self) -> StepEvent | None:
        tb, Lb = self.buf.view()
        s = self.scan_from
        if s >= tb.size:
            return None
        # "on" within BAND * f of R, "out" of R + f; a feed-in goes from out to on, a feed-out back
        src, dst = (self.high, self.low) if not self.in_test else (self.low, self.high)
        band = BAND * self.f
        # the first destination sample preceded (somewhere) by a source sample
        first_src = _first_near(Lb, src, band, s, tb.size)
        if first_src is None:
            self.scan_from = tb.size
            return None
        i2 = _first_near(Lb, dst, band, first_src, tb.size)
        if i2 is None:
            last_src = _last_near(Lb, src, band, first_src, tb.size)
            if self.final and self.in_test:
                return self._truncated_feed_out(tb, Lb, last_src)
            # keep scanning from the last source sample next time
            self.scan_from = last_src
            return None
        i1 = _last_near(Lb, src, band, first_src, i2)
        # settle: need samples after i2 on the new level to fix it
        level_after, b, settled = self._settle(tb, Lb, i2, forward=True)
        if not settled:
            self.scan_from = i1
            return None
        level_before, a, _ = self._settle(tb, Lb, i1, forward=False)
        kind = "feed_in" if not self.in_test else "feed_out"
        ev = self._step(kind, tb, Lb, a, b, level_before, level_after)
        self.in_test = not self.in_test
        self.scan_from = b
        if kind == "feed_in":
            # keep the samples from the step on: they belong to the test
            self.buf.drop_before(a)
            self.scan_from -= a
        return ev

    def _settle(self, t: np.ndarray, L: np.ndarray, i: int, forward: bool) -> tuple[float, int, bool]:
        """Level next to index ``i`` and where the step meets it.

        Forward: the new level after the step, from samples in the 0.2 s after it
        settles; returns the first index within tolerance of it.  Backward: the
        old level before the step; returns the last index within tolerance.
        """
        target = self.low if (forward != self.in_test) else self.high
        band = BAND * self.f
        if forward:
            j = i
            # The level: the median over the later part of the dwell that follows, when
            # the position loop has closed its following error and the arc has not begun.
            w0, w1 = self._settle_window()
            k_lo = int(np.searchsorted(t, t[i] + w0))
            k_end = int(np.searchsorted(t, t[i] + w1, side="right"))
            if k_end >= L.size and not self.final:
                return float("nan"), i, False
            k_lo = min(k_lo, max(k_end - 1, i))
            e = max(k_end, i + 1)
            if k_lo >= i:  # the samples near the target in the window (not the whole rest: a file may follow)
                seg = L[k_lo:e][np.abs(L[k_lo:e] - target) <= band]
            else:  # times out of order before i
                near = np.abs(L[i:] - target) <= band
                seg = L[k_lo:e][near[k_lo - i : e - i]]
            level = float(np.median(seg)) if seg.size else float(L[i])
            tol = self._tolerance(seg)
            k = i
            while k < L.size and abs(L[k] - level) > tol:
                k += 1
            j = min(k, L.size - 1)
            return level, j, True
        # Backward: walk back window by window until two neighbouring windows agree:
        # that is the plateau the step left, wherever the plan's level says it should be.
        dt = float(np.median(np.diff(t[max(0, i - 64) : i + 1]))) if i > 1 else 0.0
        win = max(0.02, 3.0 * dt)
        tol = self._tolerance(L[max(0, i - 200) : i + 1][np.abs(L[max(0, i - 200) : i + 1] - target) <= band])
        hi = i
        lo = int(np.searchsorted(t, t[hi] - win))
        cur = float(np.median(L[lo : hi + 1]))
        while True:
            if lo <= 0:
                # the recording begins on (or in) the step: its first sample is the level, and the
                # samples seen are the step's, not noise
                cur = float(L[0])
                tol = self._tolerance(np.empty(0))
                break
            lo2 = min(int(np.searchsorted(t, t[lo] - win)), lo - 1)
            prev = float(np.median(L[lo2:lo]))
            if abs(prev - cur) <= tol:
                cur = prev
                break
            cur, hi, lo = prev, lo - 1, lo2
        level = cur
        k = i
        while k > 0 and abs(L[k] - level) > tol:
            k -= 1
        return level, k, True

    def _settle_window(self) -> tuple[float, float]:
        """Seconds after a step's band entry whose median is the new level."""
        D = self.plan.dwell_s if not self.in_test else max(self.plan.dwell_s, SETTLE_S[1])
        if D < 0.1:
            return 0.0, 0.05
        return min(SETTLE_S[0], 0.45 * D), min(SETTLE_S[1], 0.9 * D)

    def _tolerance(self, seg: np.ndarray) -> float:
        """How far from a level still counts as on it: noise-aware, at least 2 um."""
        if seg.size >= 4:
            noise = 1.4826 * float(np.median(np.abs(np.diff(seg) - np.median(np.diff(seg))))) / np.sqrt(2)
        else:
            noise = 0.0
        return max(0.002, 6.0 * noise, 1e-3 * self.f)

    def _step(
        self, kind: str, t: np.ndarray, L: np.ndarray, a: int, b: int, before: float, after: float
    ) -> StepEvent:
        height = after - before
        inner = b - a - 1
        if _centroid_resolves(t[a : b + 1], inner):
            dL = np.diff(L[a : b + 1])
            tm = 0.5 * (t[a:b] + t[a + 1 : b + 1])
            total = float(dL.sum())
            tc = float(np.dot(tm, dL) / total) if total != 0 else float(0.5 * (t[a] + t[b]))
            method = "centroid"
        else:
            # Few samples: those on the ramp's straight middle each give the centre of a
            # ramp of the programmed feed; with none there, the 50 % crossing interpolated.
            ramp_s = self.f / self.plan.feed_mm_s
            frac = (L[a : b + 1] - before) / height
            mid = (frac > 0.1) & (frac < 0.9)
            if mid.any():
                tc = float(np.mean(t[a : b + 1][mid] - ramp_s * (frac[mid] - 0.5)))
            else:
                j = int(np.argmax(frac >= 0.5))
                j = max(j, 1)
                f0, f1 = frac[j - 1], frac[j]
                x = (0.5 - f0) / (f1 - f0) if f1 != f0 else 0.5
                tc = float(t[a + j - 1] + x * (t[a + j] - t[a + j - 1]))
            method = "ramp"
        tau = self._tail_tau(t, L, a, b, tc, after)
        total = float(L[b] - L[a])
        move_var = float("nan")
        if method == "centroid" and math.isfinite(tau) and total != 0:
            # The step is summed up to the first sample within tolerance of the new level; the loop's
            # exponential approach goes on (2 um of a 1.5 mm step, over ~1/Kv), and leaving it out would
            # time the step early by about rest/height x (t_b + tau - tc): 0.24 ms at 30/s.
            rest = after - float(L[b])
            tc = (tc * total + rest * (float(t[b]) + tau)) / (total + rest)
            # Its spread in time, the same way: the loop's lag adds tau^2 to the commanded move's, whose
            # shape tells how much of the per-move overhead is acceleration (program.accel_from_spread).
            dL = np.diff(L[a : b + 1])
            tm = 0.5 * (t[a:b] + t[a + 1 : b + 1])
            tail = rest * ((float(t[b]) + tau - tc) ** 2 + tau * tau)
            move_var = (float(np.dot((tm - tc) ** 2, dL)) + tail) / (total + rest) - tau * tau
        if kind == "feed_in":
            # the step's shape, progress 0..1 against time from its centroid: a feed-out cut short by
            # the end of a recording is timed against it (the same move, mirrored)
            self._in_shape = (t[a : b + 1] - tc, (L[a : b + 1] - before) / height)
        log.debug("%s at %.4f s (%s, %d samples, tau %.4f s)", kind, tc, method, inner, tau)
        return StepEvent(kind, tc, float(t[a]), float(t[b]), before, after, inner, method, tau, move_var)

    def _tail_tau(self, t: np.ndarray, L: np.ndarray, a: int, b: int, tc: float, after: float) -> float:
        """Time constant of the exponential approach to the new level, where resolved.

        After the command stops, a first-order position loop closes its following
        error as ``exp(-t / tau)`` with ``tau = 1 / Kv``.  The approach is fitted
        log-linearly between ``max(5 um, 10 x noise)`` and ``min(150 um, f/10)``
        from the level, after the step's centroid; it needs at least six samples
        there and a log residual below 0.05, or no estimate is made.
        """
        # up to the end of the dwell's level window: after it the arc may start moving the radius
        t_stop = min(t[b] + 0.5, tc + self._settle_window()[1])
        settle_end = min(L.size, b + 1 + int(np.searchsorted(t[b + 1 :], t_stop)))
        k0 = int(np.searchsorted(t, tc))
        seg_t, seg_L = t[k0:settle_end], L[k0:settle_end]
        sign = 1.0 if L[a] > after else -1.0
        e = sign * (seg_L - after)
        noise = self._tolerance(L[b:settle_end]) / 6.0
        lo, hi = max(0.005, 10.0 * noise), min(0.15, 0.1 * self.f)
        m = (e > lo) & (e < hi)
        # only the monotone approach: stop at the first sample below the band
        below = np.flatnonzero(e <= lo)
        if below.size:
            m[below[0] :] = False
        if m.sum() < 6:
            return float("nan")
        x, y = seg_t[m], np.log(e[m])
        k, _ = np.polyfit(x, y, 1)
        if k >= 0:
            return float("nan")
        # refine with a free asymptote: the level itself carries the dwell's small errors
        use = (e < hi) & (seg_t >= x[0])
        tt, ee = seg_t[use] - x[0], e[use]
        fitted = _exp_approach(tt, ee, -1.0 / k)
        if fitted is None:
            return float("nan")
        amp, tau, off = fitted
        resid = ee - (amp * np.exp(-tt / tau) + off)
        if not (tau > 0 and float(np.sqrt(np.mean(resid**2))) < 0.05 * amp):
            return float("nan")
        return float(tau)

    def _truncated_feed_out(self, t: np.ndarray, L: np.ndarray, last_on: int) -> StepEvent | None:
        """A feed-out the recording ends inside: timed against the feed-in's mirrored shape.

        Needs the step to be at least half done; each sample between 10 % and
        90 % of it gives the centroid through the feed-in's progress curve.
        """
        if self._in_shape is None:
            return None
        s_in, p_in = self._in_shape
        order = np.argsort(p_in, kind="stable")
        p_sorted, s_sorted = np.maximum.accumulate(p_in[order]), s_in[order]
        level, a, _ = self._settle(t, L, last_on, forward=False)
        p = (L[a:] - level) / self.f
        if p.size < 2 or p[-1] < 0.5:
            return None
        use = (p > 0.1) & (p < 0.9)
        if not use.any():
            return None
        tc = float(np.mean(t[a:][use] - np.interp(p[use], p_sorted, s_sorted)))
        self.in_test = False
        self.scan_from = t.size
        log.warning("the recording ends inside the feed-out: timed against the feed-in's shape")
        return StepEvent("feed_out", tc, float(t[a]), float(t[-1]), level, level + self.f,
                         int(t.size - a), "mirrored", float("nan"))

    def samples(self) -> tuple[np.ndarray, np.ndarray]:
        """The samples held: from the current (or just ended) test's feed-in on."""
        return self.buf.view()


def _centroid_resolves(t: np.ndarray, inner: int) -> bool:
    """Whether the step's samples ``t`` (from the last on the old level to the first on the new, ``inner``
    between them) time it by their centroid rather than by a ramp of the programmed feed.

    The centroid summed over the samples is the trapezoid rule for ``t_b - integral of the step's progress``:
    its error is the aliasing of the step's velocity profile at the sample rate, which is small once the
    step spreads over several sample intervals (the loop's lag and the acceleration's jerk limit smooth it)
    and has no mean over the samples' phase, so the feed-in's and the feed-out's do not add up to a bias of
    the span.  The ramp instead takes the step as a straight line at the programmed feed: exact for a step
    too sharp to hold more than two samples (a ramp of 90 ms at 64 ms between samples), but on a step the
    loop's lag has bent it errs by milliseconds that depend on which fractions of the step the samples hit
    (at 15.625 Hz up to 10 ms: a span 10 to 50 ppm off).  A lost sample inside a short step leaves an
    interval the trapezoid cannot follow: there the ramp's samples are used (each gives the centre alone).
    """
    if inner >= CENTROID_INNER:
        return True
    if inner < CENTROID_INNER_EVEN:
        return False
    gaps = np.diff(t)
    return bool(gaps.max() <= EVEN_GAP * float(np.median(gaps)))


FIND_FIRST = 4096  # samples looked at first for the next level crossing; twice as many each time after


def _first_near(L: np.ndarray, level: float, band: float, lo: int, hi: int) -> int | None:
    """The first index in ``lo:hi`` with ``|L - level| <= band``, or None: looked for in growing windows."""
    w = FIND_FIRST
    while lo < hi:
        b = min(hi, lo + w)
        hit = np.flatnonzero(np.abs(L[lo:b] - level) <= band)
        if hit.size:
            return lo + int(hit[0])
        lo, w = b, min(2 * w, 1 << 20)
    return None


def _last_near(L: np.ndarray, level: float, band: float, lo: int, hi: int) -> int:
    """The last index in ``lo:hi`` with ``|L - level| <= band`` (there is one): looked for from ``hi`` back."""
    w = FIND_FIRST
    while hi > lo:
        a = max(lo, hi - w)
        hit = np.flatnonzero(np.abs(L[a:hi] - level) <= band)
        if hit.size:
            return a + int(hit[-1])
        hi, w = a, min(2 * w, 1 << 20)
    raise AssertionError("no sample near the level")  # pragma: no cover - callers pass a range holding one


def _exp_approach(t: np.ndarray, e: np.ndarray, tau0: float) -> tuple[float, float, float] | None:
    """Least squares of ``e = amp exp(-t / tau) + off``: ``(amp, tau, off)``, or None where it has no minimum.

    Separable: for each ``tau`` the amplitude and the asymptote are a linear solve, so only ``tau`` is
    searched, by golden section on ``log tau`` within a factor of 8 of the log-linear start ``tau0``
    (a minimum at either end is none).
    """

    def solve(tau: float) -> tuple[float, np.ndarray]:
        a = np.column_stack((np.exp(-t / tau), np.ones_like(t)))
        coef, *_ = np.linalg.lstsq(a, e, rcond=None)
        r = e - a @ coef
        return float(r @ r), coef

    lo, hi = math.log(tau0 / 8.0), math.log(tau0 * 8.0)
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = solve(math.exp(x1))[0], solve(math.exp(x2))[0]
    while hi - lo > 1e-7:
        if f1 <= f2:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - g * (hi - lo)
            f1 = solve(math.exp(x1))[0]
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + g * (hi - lo)
            f2 = solve(math.exp(x2))[0]
    x = (lo + hi) / 2.0
    if min(x - math.log(tau0 / 8.0), math.log(tau0 * 8.0) - x) < 1e-3:
        return None
    tau = math.exp(x)
    _, (amp, off) = solve(tau)
    return float(amp), tau, float(off)
