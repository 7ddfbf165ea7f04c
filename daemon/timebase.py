"""Device clocks and counters to host time and unwrapped sample numbers.

:class:`ClockMap` maps a device's sample clock to the host's monotonic clock,
``t_host = offset + ratio * t_device``.  It sees one point per read: the device
time of the newest sample and the host time at which the read returned.  That
host time is the sampling instant plus a latency that is never negative and is
sometimes small (USB polling, scheduler), so the map is the *lower envelope* of
the points: the ratio is that of the line under the lowest-latency point of each
``bin_s`` of host time over the last ``window`` bins that lies closest to them (an
edge of their lower convex hull, so a bin whose every read was late, as on a
loaded host, does not tilt it), and the offset puts the line under every point.
``ratio - 1`` is the drift (a crystal's tens of ppm; 0.1 for a simulator that
runs ten times faster than real time).  The ratio is refitted once per bin (when
a bin closes: about once a second), not per point; between refits a point only
lowers the offset if it lies under the line (one subtraction), so stamping a read
costs an affine map.

:class:`Stamper` turns a decoder's raw counters and clocks into unwrapped
sample numbers and device times, finds gaps (lost samples), device restarts
and clock jumps, and stamps host times.  Pure bookkeeping: the caller passes
the host time.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ballbar.protocol import Readings


class ClockMap:
    """Lower-envelope linear map from device time to host time (seconds)."""

    def __init__(self, bin_s: float = 1.0, window: int = 600) -> None:
        self.bin_s = bin_s
        self._bins: deque[tuple[float, float]] = deque(maxlen=window)
        self._cur: tuple[int, float, float] | None = None
        self._first: tuple[float, float] | None = None
        self.ratio = 1.0
        self.offset = math.nan
        self.refits = 0  # full refits so far (about one a bin)

    def reset(self) -> None:
        self._bins.clear()
        self._cur = None
        self._first = None
        self.ratio = 1.0
        self.offset = math.nan

    @property
    def ready(self) -> bool:
        return not math.isnan(self.offset)

    @property
    def span_s(self) -> float:
        """Host seconds the fitted points span (0 before the first): a ratio from a second or two of a loaded
        host's reads is off by their latencies' difference over that span, a percent or more."""
        if self._cur is None:
            return 0.0
        first = self._bins[0][1] if self._bins else self._cur[2]
        return self._cur[2] - first

    def update(self, t_device: float, t_host: float) -> None:
        """Add a point: the newest sample's device time and the host time it was read."""
        if not (math.isfinite(t_device) and math.isfinite(t_host)):
            return
        if self._first is None:
            self._first = (t_device, t_host)
        b = math.floor(t_host / self.bin_s)
        cur = self._cur
        if cur is None:
            self._cur = (b, t_device, t_host)
        elif cur[0] == b:
            if t_host - self.ratio * t_device < cur[2] - self.ratio * cur[1]:
                self._cur = (b, t_device, t_host)
        else:
            self._bins.append((cur[1], cur[2]))
            self._cur = (b, t_device, t_host)
        if len(self._bins) >= 2 and cur is not None and cur[0] == b and self.ready:
            # Within a bin, once the ratio comes from a fit: the line only has to stay under the new point.
            self.offset = min(self.offset, t_host - self.ratio * t_device)
            return
        self._refit(t_device, t_host)
        self.refits += 1

    def _refit(self, t_device: float, t_host: float) -> None:
        assert self._cur is not None and self._first is not None
        pts = [*self._bins, (self._cur[1], self._cur[2])]
        td = np.array([p[0] for p in pts])
        th = np.array([p[1] for p in pts])
        ratio = self.ratio
        if len(pts) >= 3 and td[-1] - td[0] > 0:
            ratio = _envelope_slope(td, th)
        elif t_device - self._first[0] > 0.05:
            ratio = (t_host - self._first[1]) / (t_device - self._first[0])
        if math.isfinite(ratio) and ratio > 0:
            self.ratio = ratio
        self.offset = float(np.min(th - self.ratio * td))

    def map(self, t_device: NDArray[np.float64]) -> NDArray[np.float64]:
        return self.offset + self.ratio * t_device


def _envelope_slope(td: NDArray[np.float64], th: NDArray[np.float64]) -> float:
    """The slope of the line under every point that lies closest to them in sum: the edge of their lower
    convex hull over their mean device time.  (A least-squares line through the bins' lowest points would
    be pulled by every bin whose best read was late, as on a loaded host; this one rests on the
    earliest reads only: for latencies that are never negative, the likeliest line.)"""
    order = np.argsort(td, kind="stable")
    hull: list[tuple[float, float]] = []
    for x, y in zip(td[order].tolist(), th[order].tolist(), strict=True):
        if hull and x == hull[-1][0]:
            if y >= hull[-1][1]:
                continue
            hull.pop()
        while len(hull) >= 2:
            (x0, y0), (x1, y1) = hull[-2], hull[-1]
            if (x1 - x0) * (y - y0) - (y1 - y0) * (x - x0) > 0:  # a left turn: hull[-1] stays
                break
            hull.pop()
        hull.append((x, y))
    if len(hull) < 2:
        return math.nan
    mid = float(np.mean(td))
    for (x0, y0), (x1, y1) in itertools.pairwise(hull):
        if x1 >= mid:
            return (y1 - y0) / (x1 - x0)
    return math.nan  # (not reached: the last hull point is the largest device time)


@dataclass
class Stamped:
    """Samples after :meth:`Stamper.stamp`.

    ``keep`` selects the readings that stay (a repeated counter value is a
    duplicate and is dropped); the other arrays are already filtered.
    ``gaps``: ``(first missing seq, count)`` per gap.  ``reset_seqs``: the
    sample number of the first sample after each restart of the device's
    counter or clock seen in these readings.  ``jumps``: ``(seq, seconds)``,
    the first sample after the device clock stepped by more than its counter
    says (a clock jump; ``seconds`` the excess, negative for a step back).
    ``counter_jumps``: ``(seq, count)``, the first sample after the counter
    leapt ``count`` beyond the samples its clock says were taken (no gap).
    """

    keep: NDArray[np.bool_]
    seq: NDArray[np.int64]
    t_device: NDArray[np.float64]
    t_host: NDArray[np.float64]
    gaps: list[tuple[int, int]] = field(default_factory=list)
    reset_seqs: list[int] = field(default_factory=list)
    jumps: list[tuple[int, float]] = field(default_factory=list)
    counter_jumps: list[tuple[int, int]] = field(default_factory=list)

    @property
    def resets(self) -> int:
        return len(self.reset_seqs)

    @property
    def duplicates(self) -> int:
        return int(self.keep.shape[0] - np.count_nonzero(self.keep))


class Stamper:
    """Unwrap counters and clocks, count gaps, stamp host time.

    ``seq_modulus``, ``clock_wrap_s``: how the decoder's raw fields wrap (``None``:
    they do not).  ``rate_hz``: the nominal sample rate, used to derive sample
    numbers from a device clock when the protocol has no counter, and to space
    samples on the host clock when it has neither.

    Sample numbers start at the device's counter (binary), at the device time
    times the rate (a clock and a rate), or at 0.  Across a device restart (the
    counter or clock goes backwards) the numbers continue by one and the device
    time by the restarted clock's reading: how much was lost is unknown, and
    the times no longer show the outage (the restart is reported instead).

    Where the device has both a counter and a clock, a clock step that the
    counter does not account for (more than ``JUMP_PERIODS`` sample periods, and
    more than ``JUMP_FRACTION`` of the step) is a clock jump: reported, and the
    host clock map starts afresh.  The period is the device's own (the median
    clock step per counter step), so a nominal rate that is a little off does
    not matter.  A clock that steps back while the counter runs on (a step of
    at most ``JUMP_PERIODS``) is such a jump too, not a restart: the device
    time then runs on by the counter's step, so that it never runs back.  A
    counter that leaps by more than ``JUMP_PERIODS`` while the clock steps
    at most that many periods is a counter fault, not lost samples: the
    numbers run on by the clock's step (a ``counter_jump``).
    """

    JUMP_PERIODS = 8.0
    JUMP_FRACTION = 0.05
    PERIOD_EVERY_S = 1.0
    fast = True  # the steady-state shortcut (tests compare it with the general path)

    def __init__(self, seq_modulus: int | None, clock_wrap_s: float | None, rate_hz: float | None) -> None:
        self.seq_modulus = seq_modulus
        self.clock_wrap_s = clock_wrap_s
        self.rate_hz = rate_hz
        self.clock = ClockMap()
        self._seq_raw: int | None = None
        self._clk_raw: float | None = None
        self._seq: int | None = None  # last unwrapped sample number handed out
        self._td = math.nan  # last unwrapped device time
        self._clk_base = 0.0  # unwrapped device time minus the raw clock
        self._th = -math.inf  # last host time handed out
        self._th_read = math.nan  # host time of the last read that had samples
        self._clk_period = math.nan  # the device clock's step per counter step (s)
        self._clk_period_at = -math.inf  # the host time it was last measured
        self._resume_period = math.nan  # resume(): the device clock's period, for the first read's wrap count

    @property
    def last_seq(self) -> int | None:
        return self._seq

    def resume(self, seq: int, seq_raw: int, td: float | None, clk_raw: float | None, period_s: float | None) -> None:
        """Go on from a sample stamped before (a previous daemon run's last recorded one): its number ``seq``, the
        raw counter ``seq_raw`` the device sent with it, its device time ``td`` and raw clock ``clk_raw`` (None:
        not known), ``period_s`` the device clock's step per sample then.  The first read is then stamped as if it
        followed that sample: a counter that stepped on is a gap, counted exactly, one that went back a device
        reset, a clock that disagrees with the counter a clock jump.  The clock's wraps over the time between are
        counted from the counter's step (the host clock map is not known yet)."""
        self._seq = int(seq)
        self._seq_raw = int(seq_raw) if self.seq_modulus is not None else None
        if td is not None and clk_raw is not None and math.isfinite(td) and math.isfinite(clk_raw):
            self._td = float(td)
            self._clk_raw = float(clk_raw)
            self._clk_base = float(td) - float(clk_raw)
        self._resume_period = float(period_s) if period_s is not None and period_s > 0 else math.nan

    def offsets(self) -> tuple[int, float]:
        """The sample numbers' and device times' offsets from the raw counter and clock (modulo their wraps): 0 and
        0.0 until a device reset re-bases them; what :meth:`resume` needs to tell the raw values of a number."""
        seq_off = 0
        if self._seq is not None and self._seq_raw is not None and self.seq_modulus is not None:
            seq_off = (self._seq - self._seq_raw) % self.seq_modulus
        clk_off = 0.0
        if self._clk_raw is not None and math.isfinite(self._td):
            clk_off = self._td - self._clk_raw
            if self.clock_wrap_s is not None:
                clk_off %= self.clock_wrap_s
        return seq_off, clk_off

    def stamp(self, r: Readings, t_read: float) -> Stamped:
        n = len(r)
        if n == 0:
            z = np.empty(0)
            return Stamped(np.ones(0, bool), np.empty(0, np.int64), z, z)
        if self.fast:
            done = self._stamp_steady(r, t_read)
            if done is not None:
                return done
        first = self._seq is None
        restart = np.zeros(n, bool)
        clock_back = np.zeros(n, bool)
        keep = np.ones(n, bool)
        steps = np.ones(n, np.int64)
        counter = r.seq is not None and self.seq_modulus is not None
        back_jumps: list[tuple[int, float]] = []  # (index, s): the clock stepped back, the counter ran on
        counter_leaps: list[tuple[int, int]] = []  # (index, samples): the counter leapt, the clock ran on

        if r.seq is not None and self.seq_modulus is not None:
            m = self.seq_modulus
            raw = r.seq
            steps[1:] = np.diff(raw) % m
            if self._seq_raw is not None:
                steps[0] = (int(raw[0]) - self._seq_raw) % m
            restart |= steps >= m // 2
            keep = steps != 0
            self._seq_raw = int(raw[-1])

        td = np.full(n, math.nan)
        clk = r.clock_s
        if clk is not None:
            raw_d = np.empty(n)
            raw_d[1:] = np.diff(clk)
            raw_d[0] = 0.0 if self._clk_raw is None else clk[0] - self._clk_raw
            w = self.clock_wrap_s
            wraps = np.zeros(n)
            if w is not None:
                d = np.mod(raw_d, w)
                back = d > w / 2
                wraps[(raw_d < 0) & ~back] = 1.0
                expect = math.nan
                if self._clk_raw is not None and self.clock.ready and not math.isnan(self._th_read):
                    # After an outage of more than a quarter wrap the wrap count is
                    # ambiguous: the host clock decides.
                    expect = (t_read - self._th_read) / self.clock.ratio
                elif self._clk_raw is not None and self._resume_period > 0 and r.seq is not None and (
                        self.seq_modulus is not None and 0 < int(steps[0]) < self.seq_modulus // 2):
                    expect = float(steps[0]) * self._resume_period  # after resume(): the counter decides
                if expect > w / 4:
                    extra = max(0.0, round((expect - d[0]) / w))
                    d[0] += w * extra
                    wraps[0] = round((d[0] - raw_d[0]) / w)  # every wrap between the two readings (d is the step)
                    back[0] = False
            else:
                d = raw_d
                back = d < 0
            if counter:
                # The clock went back while the counter ran on (a step of a few samples): the clock jumped back,
                # the device did not restart; its time runs on by the counter's step.
                clock_back = back & ~restart & (steps >= 1) & (steps <= self.JUMP_PERIODS)
                restart |= back & ~clock_back
                # The counter leapt while the clock stepped about one period: the counter is at fault, no
                # sample was lost; the clock's step says how many samples it was.
                per = self._clk_period
                if per > 0:
                    leap = keep & ~restart & ~back & (steps > self.JUMP_PERIODS) & (d <= self.JUMP_PERIODS * per)
                    if first:
                        leap[0] = False
                    for i in np.flatnonzero(leap).tolist():
                        counted = max(1, round(float(d[i]) / per))
                        counter_leaps.append((i, int(steps[i]) - counted))
                        steps[i] = counted
            else:
                restart |= back
            if r.seq is None and self.rate_hz:
                steps = np.maximum(np.rint(d * self.rate_hz).astype(np.int64), 1)
            # Device time is the raw clock plus a base that grows by a wrap at each
            # wrap (so it is exactly what the device sent until the first wrap).
            cbase = (0.0 if first else self._clk_base) + (w or 0.0) * np.cumsum(wraps)
            # Across a restart the clock's own reading is the time since it began
            # (a lower bound: at least one period has passed): re-base to continue.
            floor = 1.0 / self.rate_hz if self.rate_hz else 1e-6
            period = self._clk_period if self._clk_period > 0 else floor
            for i in np.flatnonzero(restart | clock_back).tolist():
                if first and i == 0:
                    continue
                prev = self._td if i == 0 else clk[i - 1] + cbase[i - 1]
                if clock_back[i]:  # the step back is the excess (reported); the time runs on by the counter
                    back_jumps.append((i, float(d[i] - (w or 0.0)) - float(steps[i]) * period))
                    cbase[i:] += prev + float(steps[i]) * period - clk[i] - cbase[i]
                else:
                    cbase[i:] += prev + max(float(clk[i]), floor) - clk[i] - cbase[i]
            td = clk + cbase
            self._clk_base = float(cbase[-1])
            self._clk_raw = float(clk[-1])

        jump_at: list[tuple[int, float]] = []
        if clk is not None and counter:
            jump_at = self._clock_jumps(d, steps, keep & ~restart & ~clock_back, 1 if first else 0, t_read)
            jump_at = sorted(jump_at + back_jumps)

        if first:
            restart[0] = False
            if r.seq is not None:
                start = int(r.seq[0])
            elif clk is not None and self.rate_hz:
                start = int(np.rint(clk[0] * self.rate_hz))
            else:
                start = 0
            steps[0] = 0
            base = start
        else:
            assert self._seq is not None
            base = self._seq
        steps = np.where(restart, 1, steps)
        steps = np.where(keep, steps, 0)
        seq = base + np.cumsum(steps)
        if first:
            steps[0] = 1  # not a gap
        gaps = [(int(seq[i] - steps[i] + 1), int(steps[i] - 1)) for i in np.flatnonzero(steps > 1).tolist()]
        reset_seqs = [int(seq[i]) for i in np.flatnonzero(restart).tolist()]
        jumps = [(int(seq[i]), excess) for i, excess in jump_at]
        leaps = [(int(seq[i]), count) for i, count in counter_leaps]
        if reset_seqs or jumps:
            self.clock.reset()

        seq, td = seq[keep], td[keep]
        th = self._host_times(seq, td, t_read)
        self._seq = int(seq[-1]) if seq.shape[0] else self._seq
        if td.shape[0] and not math.isnan(td[-1]):
            self._td = float(td[-1])
        self._th_read = t_read
        self._resume_period = math.nan  # (the first read after resume() only)
        return Stamped(keep, seq, td, th, gaps, reset_seqs, jumps, leaps)

    def _stamp_steady(self, r: Readings, t_read: float) -> Stamped | None:
        """The usual read, in a few array operations: a counter that steps by one throughout, a clock that
        steps by about its period (no wrap, restart, jump, gap or duplicate), a known period that is not
        due to be measured again, no long outage.  ``None``: anything else, for :meth:`stamp` to sort out
        (the same result either way, only slower)."""
        raw, clk = r.seq, r.clock_s
        per = self._clk_period
        if (
            raw is None or clk is None or self.seq_modulus is None or self._seq is None
            or self._seq_raw is None or self._clk_raw is None or not per > 0
            or t_read - self._clk_period_at >= self.PERIOD_EVERY_S or not t_read - self._th_read < 1.0
        ):
            return None
        ds = np.diff(raw, prepend=self._seq_raw)
        if not (ds.min() == 1 and ds.max() == 1):
            return None
        dc = np.diff(clk, prepend=self._clk_raw)
        lo, hi = float(dc.min()), float(dc.max())
        # no restart (a step back), no jump (beyond JUMP_PERIODS periods from the period)
        if not (lo > 0.0 and lo - per >= -self.JUMP_PERIODS * per and hi - per <= self.JUMP_PERIODS * per):
            return None
        n = raw.shape[0]
        self._seq_raw = int(raw[-1])
        self._clk_raw = float(clk[-1])
        seq = np.arange(self._seq + 1, self._seq + 1 + n, dtype=np.int64)
        td = clk + self._clk_base
        th = self._host_times(seq, td, t_read)
        self._seq = int(seq[-1])
        self._td = float(td[-1])
        self._th_read = t_read
        return Stamped(np.ones(n, bool), seq, td, th)

    def _clock_jumps(
        self, d: NDArray[np.float64], steps: NDArray[np.int64], ok: NDArray[np.bool_], start: int, t_read: float
    ) -> list[tuple[int, float]]:
        """``(index, excess s)`` where the clock's step ``d`` exceeds what the counter's ``steps`` explain."""
        if not (self._clk_period > 0) or t_read - self._clk_period_at >= self.PERIOD_EVERY_S:
            # The device's period is its own and steady: measured once a second, not on every read.
            ones = ok & (steps == 1)
            ones[:start] = False
            if np.count_nonzero(ones) >= 4:
                per = float(np.median(d[ones]))
                if per > 0:
                    self._clk_period = per
                    self._clk_period_at = t_read
        per = self._clk_period
        if not per > 0:
            return []
        excess = d - steps * per
        bad = ok & (np.abs(excess) > np.maximum(self.JUMP_PERIODS * per, self.JUMP_FRACTION * steps * per))
        bad[:start] = False
        return [(i, float(excess[i])) for i in np.flatnonzero(bad).tolist()]

    def _host_times(self, seq: NDArray[np.int64], td: NDArray[np.float64], t_read: float) -> NDArray[np.float64]:
        n = seq.shape[0]
        if n == 0:
            return np.empty(0)
        if not np.isnan(td[-1]):
            self.clock.update(float(td[-1]), t_read)
            th = self.clock.map(td)
        elif self.rate_hz:
            # No device clock: the sample numbers at the nominal rate are the clock.
            syn = seq.astype(np.float64) / self.rate_hz
            self.clock.update(float(syn[-1]), t_read)
            th = self.clock.map(syn)
        else:
            th = np.full(n, t_read)
        # Causal (never after the read that returned it) and never backwards.
        th = np.minimum(th, t_read)
        th = np.maximum.accumulate(np.maximum(th, self._th))
        self._th = float(th[-1])
        return th


__all__ = ["ClockMap", "Stamped", "Stamper"]
