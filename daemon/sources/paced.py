"""Sources that pace samples they already have: the in-process simulator (``sim:``) and a CSV replay (``replay:``)."""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ballbar.protocol import Status

from ..errors import SourceConfigError
from ..samples import EventKind, SampleBatch
from .base import DEFAULT_BATCH_S, Source

log = logging.getLogger(__name__)

Chunk = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]

class _PacedSource(Source):
    """Samples known in advance (a simulation, a recording), released on the host
    clock at ``speed`` times real time (``inf``: as fast as possible)."""

    MAX_BATCH = 1 << 16

    def __init__(self, url: str, rate_hz: float | None, speed: float, batch_s: float, status: int) -> None:
        super().__init__(url, rate_hz, batch_s)
        self.speed = speed
        self._status = np.uint8(status)
        self._chunks: Iterator[Chunk] | None = None
        self._t: NDArray[np.float64] = np.empty(0)
        self._len: NDArray[np.float64] = np.empty(0)
        self._seq: NDArray[np.int64] = np.empty(0, np.int64)
        self._i = 0
        self._start: float | None = None
        self._t0 = 0.0
        self._last_seq: int | None = None
        self._last_return = -math.inf

    def _begin(self, chunks: Iterator[Chunk], detail: str) -> None:
        self._chunks = chunks
        self._stats.connected = True
        self._event(EventKind.OPENED, detail=detail)

    def _more(self) -> bool:
        """Make sure the current chunk has samples left; False at the end."""
        while self._i >= self._t.shape[0]:
            assert self._chunks is not None
            nxt = next(self._chunks, None)
            if nxt is None:
                return False
            self._t, self._len, self._seq = nxt
            self._i = 0
        return True

    def _read(self, deadline: float | None) -> SampleBatch | None:
        while not self._closed:
            if not self._more():
                self._finished = True
                self._stats.connected = False
                self._event(EventKind.END, detail="no more samples")
                return self._events_only()
            now = time.monotonic()
            if self._start is None:
                self._start, self._t0 = now, float(self._t[self._i])
            if math.isinf(self.speed):
                return self._take(self._i + self.MAX_BATCH, now)
            t_now = self._t0 + (now - self._start) * self.speed
            due = float(self._t[self._i])
            wake = max(self._start + (due - self._t0) / self.speed, self._last_return + self.read_s)
            if now >= wake:
                end = int(np.searchsorted(self._t, t_now, side="right"))
                return self._take(min(max(end, self._i + 1), self._i + self.MAX_BATCH), now)
            if self._events:
                return self._events_only()
            if deadline is not None and now >= deadline:
                return None
            self._sleep_until(wake if deadline is None else min(wake, deadline))
        return None

    def _take(self, end: int, now: float) -> SampleBatch | None:
        sl = slice(self._i, min(end, self._t.shape[0]))
        self._i = sl.stop
        self._last_return = now
        t, length, seq = self._t[sl], self._len[sl], self._seq[sl]
        steps = np.diff(seq, prepend=seq[0] - 1 if self._last_seq is None else self._last_seq)
        gaps = [(int(seq[i] - steps[i] + 1), int(steps[i] - 1)) for i in np.flatnonzero(steps > 1).tolist()]
        self._gap_events(gaps)
        self._last_seq = int(seq[-1])
        assert self._start is not None
        # As fast as possible: stamped when released; otherwise on the paced schedule.
        th = np.full(t.shape[0], now) if math.isinf(self.speed) else self._start + (t - self._t0) / self.speed
        status = np.full(t.shape[0], self._status, np.uint8)
        return self._batch(th, t.copy(), length.copy(), seq.copy(), status)


class SimSource(_PacedSource):
    """The physical simulator, in process, paced on the host clock: the operator tools' simulator, found as the
    ``tests`` plug-in of :data:`ballbar.daemon.plugins.SIMULATED` (the daemon does not import the tools)."""

    scheme = "sim"

    def __init__(
        self,
        url: str,
        *,
        plan: Any = None,
        machine: Any = None,
        library: Any = None,
        run_plans: Any = None,
        rate_hz: float | None = None,
        speedup: float = 1.0,
        seed: int = 0,
        repeat: int = 1,
        gap_s: float = 0.0,
        batch_s: float = DEFAULT_BATCH_S,
    ) -> None:
        from ballbar.analysis.plan import TestPlan

        from .. import plugins

        tests: plugins.SimulatedTests = plugins.load(plugins.SIMULATED, "tests")
        several = library is not None and len(library) > 1
        plan = plan if plan is not None else library.first.plan if several else TestPlan()
        rate = float(rate_hz if rate_hz is not None else plan.sample_hz)
        super().__init__(url, rate, speedup, batch_s, int(Status.SIMULATED))
        times = None if repeat == 0 else repeat

        def chunks() -> Iterator[Chunk]:
            for t_s, length_mm in tests(plan, machine, rate, seed, times, gap_s, library=library if several else None,
                                        run_plans=run_plans):
                seq = np.rint(t_s * rate).astype(np.int64)
                yield t_s, length_mm, seq

        self._begin(chunks(), f"simulator, {rate:g} Hz, speedup {speedup:g}, seed {seed}")


class ReplaySource(_PacedSource):
    """A recording, replayed at ``speed`` times real time."""

    scheme = "replay"

    def __init__(
        self,
        url: str,
        path: str,
        *,
        speed: float = 1.0,
        rate_hz: float | None = None,
        batch_s: float = DEFAULT_BATCH_S,
    ) -> None:
        super().__init__(url, rate_hz, speed, batch_s, 0)
        ext = os.path.splitext(path)[1].lower()
        if ext == ".mcap":
            raise SourceConfigError(f"{url}: replay of MCAP recordings is not supported yet; use a CSV export")
        from ..recordings import read_csv  # DataError (one line) on a bad file

        t, length = read_csv(path)
        if rate_hz:
            seq = np.rint((t - t[0]) * rate_hz).astype(np.int64)
            bad = np.flatnonzero(np.diff(seq) <= 0)  # two rows in one sample period
            if bad.shape[0]:
                raise SourceConfigError(
                    f"{url}: rows {int(bad[0]) + 1} and {int(bad[0]) + 2} fall in one sample period at "
                    f"rate={rate_hz:g} Hz; is the rate right?"
                )
        else:
            seq = np.arange(t.shape[0], dtype=np.int64)
        self._begin(iter([(t, length, seq)]), f"{path} ({t.shape[0]} samples, speed {speed:g})")
