"""Fixed-size buffers of the live view: what it keeps of the samples and of the history, allocated once."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

def multiples(seq: NDArray[np.int64], every: int) -> NDArray[np.intp]:
    """Positions of the samples whose number is a multiple of ``every`` (arithmetic when none is missing)."""
    n = seq.size
    if not n:
        return np.empty(0, np.intp)
    s0 = int(seq[0])
    if int(seq[-1]) - s0 == n - 1:
        return np.arange((-s0) % every, n, every)
    return np.flatnonzero(seq % every == 0)


def rate_hz(t: FloatArray, previous: float) -> float:
    """Sample rate (Hz) from a batch's times; ``previous`` when they do not tell."""
    d = np.diff(t)
    d = d[np.isfinite(d)]
    if not d.size:
        return previous
    dt = float(np.median(d))
    return 1.0 / dt if dt > 0 else previous


class Ring:
    """A fixed-capacity FIFO of float64 rows (``width`` columns); the oldest rows are overwritten."""

    def __init__(self, capacity: int, width: int) -> None:
        self.buf = np.empty((max(1, capacity), width))
        self.start = 0
        self.n = 0

    def __len__(self) -> int:
        return self.n

    @property
    def capacity(self) -> int:
        return int(self.buf.shape[0])

    def extend(self, rows: FloatArray) -> None:
        cap = self.capacity
        rows = rows[-cap:]
        k = rows.shape[0]
        if not k:
            return
        end = (self.start + self.n) % cap
        first = min(k, cap - end)
        self.buf[end : end + first] = rows[:first]
        self.buf[: k - first] = rows[first:]
        self.n += k
        if self.n > cap:
            self.start = (self.start + self.n - cap) % cap
            self.n = cap

    def rows(self) -> FloatArray:
        """The rows, oldest first (a copy)."""
        end = self.start + self.n
        if end <= self.capacity:
            return self.buf[self.start : end].copy()
        return np.concatenate([self.buf[self.start :], self.buf[: end - self.capacity]])


class Samples:
    """The current test's samples kept for the polar plot: columns of ``capacity`` rows, allocated once.

    The caller keeps them within ``capacity`` (one block for the daemon's life, its pages used as
    needed: no reallocations, so no heap fragments); a larger append grows them, and :meth:`keep`
    returns to ``capacity`` afterwards.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.data = np.empty((3, capacity))  # t_host, t_device, length
        self.n = 0

    def append(self, th: FloatArray, td: FloatArray, L: FloatArray) -> None:
        k = th.size
        if self.n + k > self.data.shape[1]:
            grown = np.empty((3, max(2 * self.data.shape[1], self.n + k)))
            grown[:, : self.n] = self.data[:, : self.n]
            self.data = grown
        self.data[0, self.n : self.n + k] = th
        self.data[1, self.n : self.n + k] = td
        self.data[2, self.n : self.n + k] = L
        self.n += k

    def keep(self, mask_or_slice: Any) -> None:
        """Keep only the rows selected (a boolean mask or a slice), in place."""
        kept = self.data[:, : self.n][:, mask_or_slice]
        self.n = kept.shape[1]
        if self.data.shape[1] > self.capacity and self.n <= self.capacity:
            self.data = np.empty((3, self.capacity))
        self.data[:, : self.n] = kept

    @property
    def t_host(self) -> FloatArray:
        return self.data[0, : self.n]

    @property
    def t_device(self) -> FloatArray:
        return self.data[1, : self.n]

    @property
    def length(self) -> FloatArray:
        return self.data[2, : self.n]


__all__ = ["Ring", "Samples", "multiples", "rate_hz"]
