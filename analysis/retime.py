"""Samples a stalled host stamped late, put back on the device's grid.

A gauge that streams at a fixed rate and sends no clock of its own is stamped
by the host as its samples arrive.  A stamp is only ever late, never early:
the sampling instant plus the transport's and the scheduler's latency.  Most
latencies are small, but a loaded host stalls now and then (tens of
milliseconds, up to 100 ms every few seconds on a busy PC): the samples taken
meanwhile wait in the USB adapter or the kernel and arrive together,
microseconds apart.  On the time axis that is a forward step of many sample
periods followed by a burst, and the time axis (:mod:`.timeaxis`) would call
it a break.  Unlike a loss, the burst catches up: counted one period a sample
from before the step, the samples after it come back to the grid.

:class:`Retimer` therefore looks at every forward step longer than
``GAP_PERIODS`` median periods, and at the samples stamped within ``HOLD_S``
after it (held back until they are in).  Each sample of that window is put no
later than any later sample of it allows, one period per sample between them
(``t'_j = min over k >= j of t_k - (k - j) P``, the early envelope of the
window, counted on the device's grid; ``P`` the period of the
``PERIOD_WINDOW`` samples before the long step (their median step, refined by
the mean time over ``SPAN`` steps), so that the answer does not depend on how
the stream came chunked; ``k`` up to ``STALL_MAX_S`` ahead, since ``P``'s error
grows with the distance).  After a stall the burst falls back on the grid and the step is
gone; after a loss (a radio link's drop-out) the
samples after it stay where their stamps put them, on their own grid, and the
time axis sees the gap for what it is, a gap of whole periods, which the
analysis then judges (:mod:`.dropout`).

Where the device sends a clock and a counter, the daemon maps that clock to
the host's (``daemon/timebase.py``: a lower-envelope fit of rate and offset
over minutes); the samples then come evenly spaced and nothing here changes
them (a move under ``RESOLUTION_S`` is none).  Outside the windows after a long step no sample is moved at all, so
ordinary jitter and single lost samples are as they were.
"""

from __future__ import annotations

import math

import numpy as np

from .timeaxis import CHECK_BLOCK, GAP_PERIODS, MIN_STEPS, PERIOD_WINDOW, median_period

HOLD_S = 0.5  # how long after a long step its window runs (and live, how long samples are held for it)
STALL_MAX_S = 0.2  # the longest stall re-timed: how far ahead of a sample the envelope looks
RESOLUTION_S = 1e-9  # a move this small is none (the recordings' resolution)
PERIOD_SAMPLE = 1 << 14  # the first guess of the period: the median step of at most this many samples
SPAN = 16  # steps over which a window's period is refined (see _period)


class Retimer:
    """Re-times the windows after long forward steps; see the module docstring.

    :meth:`feed` takes the next chunk and returns what is settled: every
    sample except those of a window still open, which come with a later call
    (or :meth:`flush`, at the stream's end or before a break the caller
    knows of).  ``moved``: samples put earlier so far; ``windows``: long
    steps looked at; ``caught_up``: of those, the ones a burst made good.
    """

    def __init__(self, hold_s: float = HOLD_S) -> None:
        self.hold_s = hold_s
        self.reset()

    def reset(self) -> None:
        """Start afresh (the stream cannot go on as it was): what is held is dropped."""
        self._t = np.empty(0)
        self._L = np.empty(0)
        self._recent = np.empty(0)  # the last released times (the period's yardstick)
        self.moved = 0
        self.windows = 0
        self.caught_up = 0

    @property
    def held(self) -> int:
        return int(self._t.size)

    def state(self) -> tuple[object, ...]:
        """Everything :meth:`feed` changes (for :meth:`restore` where a chunk is refused after it)."""
        return (self._t, self._L, self._recent, self.moved, self.windows, self.caught_up)

    def restore(self, state: tuple[object, ...]) -> None:
        self._t, self._L, self._recent, self.moved, self.windows, self.caught_up = state  # type: ignore[assignment]

    def feed(self, t: np.ndarray, L: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The settled samples of the held ones and ``(t, L)``, in order."""
        if self._t.size:
            t, L = np.concatenate((self._t, t)), np.concatenate((self._L, L))
        return self._work(t, L, final=False)

    def flush(self) -> tuple[np.ndarray, np.ndarray]:
        """The samples still held, their window closed where it is."""
        t, L = self._t, self._L
        self._t, self._L = np.empty(0), np.empty(0)
        return self._work(t, L, final=True) if t.size else (t, L)

    def _period(self, t: np.ndarray, g: int | None = None) -> float:
        """The median period of the ``PERIOD_WINDOW`` steps before sample ``g`` of ``t`` (the stream so far is
        the released samples and ``t``), the same however the stream came chunked; ``None``: a first guess, from
        the head of ``t`` too, to find the long steps by."""
        part = t[:PERIOD_SAMPLE] if g is None else t[max(0, g - PERIOD_WINDOW - 1) : g]
        if part.size <= PERIOD_WINDOW and self._recent.size:
            part = np.concatenate((self._recent[-(PERIOD_WINDOW + 1 - part.size):], part))
        if part.size <= MIN_STEPS:
            return math.nan
        P = median_period(part)
        if g is None or not P > 0 or part.size <= 4 * SPAN:
            return P
        # The median step is good to the latency's spread over sqrt(n) only (11 us at 250 Hz over 2048 steps
        # with 0.5 ms of exponential latency); the time over SPAN steps carries the same latency once, not SPAN
        # times: the mean of those spans, less any holding a lost sample (a period more) or a late stamp.
        span = (part[SPAN:] - part[:-SPAN]) / SPAN
        ok = np.abs(span - P) < 0.25 * P / SPAN
        return float(np.mean(span[ok])) if np.count_nonzero(ok) >= part.size // 4 else P

    def _work(self, t: np.ndarray, L: np.ndarray, final: bool) -> tuple[np.ndarray, np.ndarray]:
        self._t, self._L = np.empty(0), np.empty(0)
        if not t.size:
            return t, L
        P = self._period(t)
        if not P > 0:
            self._keep(t)
            return t, L
        prev = float(self._recent[-1]) if self._recent.size else math.nan
        found = _long_steps(t, prev, 0.5 * GAP_PERIODS * P)  # candidates; each judged by the period before it
        if not found.size:
            self._keep(t)
            return t, L
        t = t.copy()
        end = t.size  # where the settled samples end
        h = 0  # the last window's end
        for g in found.tolist():
            if g < h:
                continue
            before = float(t[g - 1]) if g else prev
            P = self._period(t, g)
            if not (P > 0 and t[g] - before > GAP_PERIODS * P):  # no long step (or no more, after a window)
                continue
            h = g + int(np.searchsorted(t[g:], t[g] + self.hold_s, side="left"))
            if h >= t.size and not final:
                end = g  # the window is not in yet: hold it
                break
            self._settle(t, g, h, before, P)
            # a window that ends against another long step: that step is looked at next
        if end < t.size:
            self._t, self._L = t[end:], L[end:]
            t, L = t[:end], L[:end]
        self._keep(t)
        return t, L

    def _settle(self, t: np.ndarray, g: int, h: int, before: float, P: float) -> None:
        w = t[g:h]
        cap = w.copy()
        for m in range(1, min(w.size, math.ceil(STALL_MAX_S / P) + 1)):
            np.minimum(cap[:-m], w[m:] - m * P, out=cap[:-m])  # no later than a later sample allows
        cap = np.where(w - cap > RESOLUTION_S, cap, w)  # an evenly spaced clock's rounding is left alone
        if math.isfinite(before):
            cap = np.maximum(cap, before)  # never before the sample before the step
        cap = np.maximum.accumulate(cap)
        self.windows += 1
        if math.isfinite(before) and cap[0] - before <= GAP_PERIODS * P:
            self.caught_up += 1
        self.moved += int(np.count_nonzero(cap < w - 0.5 * P))
        t[g:h] = cap

    def _keep(self, t: np.ndarray) -> None:
        if not t.size:
            return
        tail = t[-(PERIOD_WINDOW + 1):]
        self._recent = np.concatenate((self._recent, tail))[-(PERIOD_WINDOW + 1):]


def _long_steps(t: np.ndarray, prev: float, limit: float) -> np.ndarray:
    """Indices of ``t`` whose step from the sample before (``prev`` before the first) is longer than ``limit``."""
    out = []
    for a in range(0, t.size, CHECK_BLOCK):
        seg = np.concatenate(([prev], t[:CHECK_BLOCK])) if a == 0 else t[a - 1 : a + CHECK_BLOCK]
        idx = np.flatnonzero(np.diff(seg) > limit)
        if idx.size:
            out.append(idx + a)
    found = np.concatenate(out) if out else np.empty(0, np.int64)
    return np.unique(found[found < t.size])


def retime(t: np.ndarray) -> np.ndarray:
    """A whole stream's times re-timed (:class:`Retimer` over one chunk)."""
    r = Retimer()
    t = np.asarray(t, dtype=float)
    out, _ = r.feed(t, np.zeros(t.size))
    rest, _ = r.flush()
    return np.concatenate((out, rest)) if rest.size else out


__all__ = ["HOLD_S", "RESOLUTION_S", "STALL_MAX_S", "Retimer", "retime"]
