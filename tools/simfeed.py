"""What the simulated ball-bar plays: the samples of successive tests (the physical simulator's, a set's on the
3D machine, or a CSV recording's), taken in device-time order, and their wire bytes encoded ahead of need.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import threading
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

log = logging.getLogger(__name__)

Chunk = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]
Wire = tuple[bytes, NDArray[np.int64]]  # encoded samples, and where each starts (and the last ends)


# ----------------------------------------------------------------------------- samples


class _NextTest:
    """The next test of ``tests``, made on a thread of its own while the current one streams."""

    def __init__(self, tests: Iterator[Chunk]) -> None:
        self.value: Chunk | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, args=(tests,), name="simdevice-next-test", daemon=True)
        self.thread.start()

    def _run(self, tests: Iterator[Chunk]) -> None:
        try:
            self.value = next(tests, None)
        except BaseException as err:  # handed to the streaming thread, which raises it
            self.error = err

    def result(self) -> Chunk | None:
        self.thread.join()
        if self.error is not None:
            raise self.error
        return self.value


class Feed:
    """Samples of successive tests, taken in device-time order.

    The first test is made at once; each next one on a thread while the one before streams
    (simulating a test takes about a second), so the device keeps sending across the gap
    between tests, as a real ball-bar's LVDT keeps reporting: made on demand, it held the
    stream up for that second, and the daemon reported a stall and a resume between tests.
    """

    def __init__(self, tests: Iterator[Chunk]) -> None:
        self._tests = tests
        self._t: NDArray[np.float64] = np.empty(0)
        self._len: NDArray[np.float64] = np.empty(0)
        self._seq: NDArray[np.int64] = np.empty(0, np.int64)
        self._i = 0
        self.exhausted = False
        self.tests = 0
        self._next: _NextTest | None = None
        self._load()

    def _fetch(self) -> Chunk | None:
        nxt = next(self._tests, None) if self._next is None else self._next.result()  # the first: at once
        self._next = _NextTest(self._tests) if nxt is not None else None
        return nxt

    def _load(self) -> bool:
        while self._i >= self._t.shape[0]:
            if self.exhausted:
                return False
            nxt = self._fetch()
            if nxt is None:
                self.exhausted = True
                return False
            self._t, self._len, self._seq = nxt
            self._i = 0
            self.tests += 1
        return True

    @property
    def next_t(self) -> float:
        return float(self._t[self._i]) if not self.exhausted else math.inf

    def take_until(self, t_lim: float, limit: int = 1 << 16) -> Chunk:
        """Samples with device time <= ``t_lim`` (at most ``limit``), across tests."""
        return self._take(t_lim, limit, None)[0]

    def take_encoded(self, t_lim: float, encoder: BlockEncoder, limit: int = 1 << 16) -> tuple[Chunk, bytes]:
        """:meth:`take_until`, and the samples' wire bytes from ``encoder``."""
        return self._take(t_lim, limit, encoder)

    def _take(self, t_lim: float, limit: int, encoder: BlockEncoder | None) -> tuple[Chunk, bytes]:
        parts: list[Chunk] = []
        data: list[bytes] = []
        n = 0
        while n < limit and self._load() and self._t[self._i] <= t_lim:
            end = int(np.searchsorted(self._t, t_lim, side="right"))
            end = min(end, self._i + limit - n)
            sl = slice(self._i, end)
            parts.append((self._t[sl], self._len[sl], self._seq[sl]))
            if encoder is not None:
                data.append(encoder.wire(self.tests, self._t, self._len, self._seq, self._i, end))
            n += end - self._i
            self._i = end
        self._load()
        wire = data[0] if len(data) == 1 else b"".join(data)
        if not parts:
            return (np.empty(0), np.empty(0), np.empty(0, np.int64)), wire
        if len(parts) == 1:
            return parts[0], wire
        return (
            np.concatenate([p[0] for p in parts]),
            np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]),
        ), wire


class BlockEncoder:
    """The wire bytes of a test's samples, encoded ``block`` samples at a time ahead of need.

    numpy's cost is per call: encoding the few samples of each write one call at a
    time would cost more than all else the device does.  ``encode`` returns a block's
    bytes and the offset of each sample's bytes in them (plus the end); ``key`` is the
    device state they depend on (its counter and clock offsets): change it and what
    is left is encoded again.
    """

    def __init__(
        self,
        encode: Callable[[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]], Wire],
        block: int = 4096,
    ) -> None:
        self.encode = encode
        self.block = block
        self.key: object = None
        self._cache: tuple[int, object, int, int, bytes, NDArray[np.int64]] | None = None
        self.blocks = 0  # blocks encoded so far

    def wire(
        self, test: int, t: NDArray[np.float64], length: NDArray[np.float64], seq: NDArray[np.int64], i0: int, i1: int
    ) -> bytes:
        """The bytes of samples ``i0`` to ``i1`` (excluded) of test number ``test`` (its arrays)."""
        c = self._cache
        if c is None or c[0] != test or c[1] != self.key or not c[2] <= i0 <= i1 <= c[3]:
            b1 = min(t.shape[0], max(i1, i0 + self.block))
            data, off = self.encode(t[i0:b1], length[i0:b1], seq[i0:b1])
            c = self._cache = (test, self.key, i0, b1, data, off)
            self.blocks += 1
        b0, data, off = c[2], c[4], c[5]
        return data[off[i0 - b0] : off[i1 - b0]]


def plans_of(text: str) -> Any:
    """``--library``: a JSON table of plans as the daemon's configuration records them (``config["plans"]``)."""
    from ballbar.analysis.errors import PlanError
    from ballbar.daemon.config import ConfigError, library_of

    try:
        tables = json.loads(text)
        if not isinstance(tables, dict) or not tables:
            raise ValueError("not a table of plans")
        return library_of({"plans": tables})
    except (ValueError, ConfigError) as err:
        raise PlanError(f"--library: {err}") from None


def simulated_set(args: argparse.Namespace) -> Iterator[Chunk]:
    """A set's plans in turn on the 3D machine (:mod:`ballbar.tools.machine3d`), as the bar reads them."""
    from ballbar.analysis.errors import PlanError
    from ballbar.tools.machine3d import Machine3D, set_tests

    library = plans_of(args.library)
    names = [n.strip() for n in args.run_plans.split(",") if n.strip()] if args.run_plans else list(library.names)
    machine = Machine3D.from_settings(_floats(args.set, "--set"))
    drift = _floats(getattr(args, "drift", None) or [], "--drift")
    if args.rate != library.first.plan.sample_hz:
        log.info("the plans sample at %g Hz; the device at %g Hz", library.first.plan.sample_hz, args.rate)
    if not names:
        raise PlanError("--run-plans names no plan")
    repeat = None if args.repeat == 0 else args.repeat
    for _name, res in set_tests(library, names, machine, args.rate, args.seed, repeat, args.gap_s, drift):
        yield res.t_s, res.length_mm, np.rint(res.t_s * args.rate).astype(np.int64)


def _floats(items: Sequence[str], what: str) -> dict[str, float]:
    from ballbar.analysis.errors import PlanError

    out: dict[str, float] = {}
    for item in items:
        key, sep, text = item.partition("=")
        try:
            if not sep:
                raise ValueError(item)
            out[key.strip()] = float(text)
        except ValueError:
            raise PlanError(f"{what} needs KEY=NUMBER, not {item!r}") from None
    return out


def simulator_tests(args: argparse.Namespace) -> Iterator[Chunk]:
    from ballbar.tools.simulator import MachineModel, iter_tests
    from ballbar.tools.simulator_cli import parse_set, plan_from_args

    if getattr(args, "library", None):
        yield from simulated_set(args)
        return
    plan = plan_from_args(args, args.rate)
    machine = MachineModel(**parse_set(args.set))
    drift = {k: float(v) for k, v in parse_set(getattr(args, "drift", None) or []).items()}
    for res in iter_tests(plan, machine, args.rate, args.seed, None if args.repeat == 0 else args.repeat, args.gap_s,
                          drift=drift):
        yield res.t_s, res.length_mm, np.rint(res.t_s * args.rate).astype(np.int64)


def csv_tests(path: str, rate: float, repeat: int, gap_s: float) -> Iterator[Chunk]:
    from ballbar.daemon.recordings import read_csv

    t, length = read_csv(path)
    t = t - t[0]
    span = (t[-1] if t.shape[0] else 0.0) + 1.0 / rate + gap_s
    i = 0
    while repeat == 0 or i < repeat:
        ti = t + i * span
        yield ti, length, np.rint(ti * rate).astype(np.int64)
        i += 1
