"""The time axis of a stream of samples: its period, its jitter, and its breaks.

A test's angles are computed from time: the feed-in to feed-out span gives the
feed, and a sample's angle is its time since the feed-in at that feed.  A time
axis that jumps therefore gives confident wrong answers, so the analysis
watches it (:class:`TimeAxis`), with the median sample period as its yardstick:

- A step *backwards* by more than ``JITTER_PERIODS`` median periods is not
  timestamp jitter but a clock that ran back (a device that restarted, a
  recording spliced out of order): :class:`TimeAxisError`, naming the sample.
  Smaller reorders are jitter and harmless (an angle error of a few periods).
- A step *forward* longer than ``GAP_PERIODS`` median periods is a *break*.
  Lost samples and a clock that jumped look the same on the time axis; lost
  samples only cost samples, but a jump makes the feed-in to feed-out span,
  and with it the feed and every angle, wrong.  Which one it was cannot be
  told from the times, so a test that spans a break is rejected.

  Eight periods: with 2 % of the samples dropped at random and 0.5 ms of
  timestamp jitter at 500 Hz (0.35 periods rms on a step), a step that long
  needs six drops in a row (p = 6e-11 a sample); at 15.625 Hz a couple of
  drops are three periods (192 ms) against the 512 ms threshold.
- A break the caller knows of and the times cannot show (a device reset, after
  which the daemon re-bases the restarted clock so that it runs on; samples the
  logger lost) is told with :meth:`TimeAxis.mark` and lands between the samples
  fed so far and the next.

The period is the median of the recent positive steps (the last
``PERIOD_WINDOW``), so repeated timestamps (a host stamping a whole read at
once) and a few losses do not move it.  Once the window is full it is taken
again every ``PERIOD_REFRESH`` steps, not on every chunk: a live stream comes
in chunks of a few samples, and the period changes slowly if at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import DataError

GAP_PERIODS = 8.0  # a forward step longer than this many median periods is a break
JITTER_PERIODS = 3.0  # a backward step up to this many median periods is timestamp jitter
PERIOD_WINDOW = 2048  # positive steps the median period is taken over
PERIOD_REFRESH = 256  # ... and taken again after this many more, once the window is full
MIN_STEPS = 8  # positive steps needed before a forward step is judged
CHECK_BLOCK = 1 << 20  # samples of a long chunk checked at a time (the size of the temporaries)


class Lost(str):
    """A told break's reason that is samples lost on a clock that ran on (the times show how long): a gap the
    analysis may judge as a drop-out (:mod:`.dropout`), unlike a device reset or a clock jump."""

    __slots__ = ()


class TimeAxisError(DataError):
    """The time axis runs backwards beyond jitter (``index``: the offending sample, counted from 0)."""

    def __init__(self, message: str, index: int) -> None:
        super().__init__(message)
        self.index = index


@dataclass(frozen=True)
class Break:
    """A discontinuity between two neighbouring samples of a stream.

    ``index``: the first sample after it (counted from the stream's start);
    ``t_before``, ``t_after``: the times of the samples either side;
    ``period_s``: the median sample period then (NaN if not yet known);
    ``reason``: what the caller said it was ("" when only the times showed it).
    """

    index: int
    t_before: float
    t_after: float
    period_s: float
    reason: str = ""

    @property
    def gap_s(self) -> float:
        return self.t_after - self.t_before

    @property
    def missing_s(self) -> float:
        """Time the axis skips beyond one sample period: a clock jump's size, or the samples lost times the period."""
        return self.gap_s - (self.period_s if math.isfinite(self.period_s) else 0.0)

    @property
    def visible(self) -> bool:
        """Whether the time axis itself shows the break (a gap longer than ``GAP_PERIODS``)."""
        return math.isfinite(self.period_s) and self.gap_s > GAP_PERIODS * self.period_s

    def describe(self) -> str:
        """One phrase: what and where, e.g. ``clock jump or outage of 10.000 s at t=57.123 s (...)``."""
        if self.reason:
            text = f"{self.reason} at t={self.t_after:.3f} s"
            if self.visible:
                text += f" (the time axis steps {self.gap_s:.3f} s there)"
            return text
        periods = f", {self.gap_s / self.period_s:.0f} sample periods" if self.period_s > 0 else ""
        return (f"clock jump or outage of {self.missing_s:.3f} s at t={self.t_before:.3f} s "
                f"(no sample until t={self.t_after:.3f} s{periods})")


def median_period(t: np.ndarray) -> float:
    """The median positive step of ``t`` (s), NaN when the times never advance."""
    steps = np.diff(np.asarray(t, dtype=float))
    pos = steps[steps > 0]
    return float(np.median(pos)) if pos.size else float("nan")


def backward_steps(t: np.ndarray) -> tuple[np.ndarray, float]:
    """How far each sample lies behind the latest time before it (0 if not), and the jitter allowed (s).

    A whole recording's check, the same rule as :class:`TimeAxis`: a sample
    more than ``JITTER_PERIODS`` median periods behind is a clock that ran back.
    """
    t = np.asarray(t, dtype=float)
    if t.size < 2:
        return np.zeros(t.size), 0.0
    prior = np.maximum.accumulate(np.concatenate(([t[0]], t[:-1])))
    period = median_period(t)
    return np.maximum(prior - t, 0.0), JITTER_PERIODS * period if math.isfinite(period) else 0.0


class TimeAxis:
    """Checks a stream's times chunk by chunk; see the module docstring."""

    def __init__(self) -> None:
        self.n = 0  # samples seen
        self.last_t = math.nan
        self.max_t = -math.inf
        self.first_t = math.nan
        self.forward_steps = 0  # positive steps seen
        self.period_s = math.nan
        self._recent = np.empty(0)
        self._since_median = 0  # positive steps since the period was last taken
        self._told: list[str] = []

    def mark(self, reason: str) -> None:
        """A break the caller knows of, between the samples checked so far and the next."""
        if self.n:
            self._told.append(reason)

    def check(self, t: np.ndarray) -> list[Break]:
        """The breaks before and within the chunk ``t`` (finite times); updates the state.

        Raises :class:`TimeAxisError` for a step backwards beyond jitter (the
        state is then unchanged).  A long chunk (a whole recording) is worked
        through :data:`CHECK_BLOCK` samples at a time, with the same answers.
        """
        t = np.asarray(t, dtype=float)
        if t.size == 0:
            return []
        pos = positive_steps(t, self.last_t if self.n else None)
        npos = pos.size
        since = self._since_median + npos
        if npos >= PERIOD_WINDOW:
            recent = pos[-PERIOD_WINDOW:].copy()  # not a view: pos may be a whole recording's
            period, since = float(np.median(pos, overwrite_input=True)), 0  # pos is ours; the same median
        else:
            recent = np.concatenate((self._recent[npos - PERIOD_WINDOW :], pos))
            if recent.size < PERIOD_WINDOW or since >= PERIOD_REFRESH or not math.isfinite(self.period_s):
                period, since = (float(np.median(recent)) if recent.size else math.nan), 0
            else:
                period = self.period_s
            recent = recent[-PERIOD_WINDOW:]
        del pos
        tol = JITTER_PERIODS * period if math.isfinite(period) else 0.0
        judged = self.forward_steps + npos >= MIN_STEPS and math.isfinite(period)
        gaps: list[tuple[int, float, float]] = []  # (index in t, latest time before it, its time)
        latest = self.max_t
        first_prior = latest
        for a in range(0, t.size, CHECK_BLOCK):
            seg = t[a : a + CHECK_BLOCK]
            # Against the latest time so far, so that one sample stamped late cannot hide a clock that ran back.
            prior = np.maximum.accumulate(np.concatenate(([latest], seg[:-1])))
            latest = max(float(prior[-1]), float(seg[-1]))
            back = prior - seg
            if np.any(back > tol):
                j = int(np.argmax(back > tol))
                allowed = f"{tol:.3g} s, {JITTER_PERIODS:g} sample periods" if tol > 0 else "no period known yet"
                raise TimeAxisError(
                    f"sample {self.n + a + j}: the time runs backwards by {back[j]:.6g} s (t={seg[j]:.6f} s after "
                    f"t={prior[j]:.6f} s), more than timestamp jitter ({allowed}): a clock that restarted or "
                    "jumped back, or samples out of order",
                    self.n + a + j,
                )
            if a == 0:
                first_prior = float(prior[0])
            if judged:
                fwd = seg - prior
                if a == 0 and self.n == 0:
                    fwd[0] = 0.0  # the stream's first sample follows nothing
                gaps.extend((a + k, float(prior[k]), float(seg[k]))
                            for k in np.flatnonzero(fwd > GAP_PERIODS * period).tolist())
        out: list[Break] = []
        told, self._told = self._told, []
        if told and self.n and not (gaps and gaps[0][0] == 0):
            gaps.insert(0, (0, first_prior, float(t[0])))
        for k, before, after in gaps:
            reason = (told[0] if len(told) == 1 else "; ".join(told)) if k == 0 and told else ""
            out.append(Break(self.n + k, before, after, period, reason))
        if self.n == 0:
            self.first_t = float(t[0])
        self.n += t.size
        self.last_t = float(t[-1])
        self.max_t = max(self.max_t, latest)
        self.forward_steps += npos
        self.period_s = period
        self._since_median = since
        self._recent = recent
        return out


def positive_steps(t: np.ndarray, before: float | None = None) -> np.ndarray:
    """The positive steps of ``t`` (after ``before``, if given), in order: ``np.diff`` a block at a time."""
    t = np.asarray(t, dtype=float)
    if t.size <= CHECK_BLOCK:
        steps = np.diff(t if before is None else np.concatenate(([before], t)))
        return steps[steps > 0]
    out = np.empty(t.size if before is not None else t.size - 1)
    m = 0
    if before is not None and t.size and t[0] - before > 0:
        out[0] = t[0] - before
        m = 1
    for a in range(0, t.size - 1, CHECK_BLOCK):
        steps = np.diff(t[a : a + CHECK_BLOCK + 1])
        pos = steps[steps > 0]
        out[m : m + pos.size] = pos
        m += pos.size
    return out[:m]


__all__ = [
    "GAP_PERIODS", "JITTER_PERIODS", "PERIOD_REFRESH", "Break", "Lost", "TimeAxis", "TimeAxisError", "backward_steps",
    "median_period", "positive_steps",
]
