"""Benchmark of the MCAP log: bytes per sample and write/read throughput by sample rate.

A simulated test (``ballbar.tools.simulator``, LVDT noise ``--noise-um``) is fed to
:class:`~ballbar.daemon.mcap.McapLogger` as a serial source delivers it:
batches of 20 ms, the device clock, a host clock mapped by the lower-envelope
:class:`~ballbar.daemon.timebase.ClockMap` from read times with USB-like latency.
The samples are fed as fast as possible, with a chunk closed after every
``flush_s`` of samples: the chunking the logger's flush timer gives at real-time
pace.  Reported per rate, medians of ``--repeats`` runs:

- bytes/sample: the finished file's size over the samples in it
- write: samples per second of CPU the logger needs (``on_batch`` and flushes)
- read: samples per second of :func:`~ballbar.daemon.mcap.read_mcap`

Run: ``OPENBLAS_NUM_THREADS=1 python -m ballbar.tools.bench.bench_mcap [--rates 15.625,1000,10000]``
"""

from __future__ import annotations

import argparse
import logging
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from ballbar.analysis.plan import TestPlan
from ballbar.daemon.mcap import McapLogger, list_recordings, read_mcap
from ballbar.daemon.samples import SampleBatch
from ballbar.daemon.timebase import ClockMap
from ballbar.tools.simulator import MachineModel, simulate

log = logging.getLogger(__name__)


def serial_batches(
    t_s: np.ndarray, length: np.ndarray, fs: float, batch_s: float = 0.02, status: int = 0
) -> Iterator[SampleBatch]:
    """The samples as a serial source would deliver them (device clock, mapped host clock)."""
    per = max(1, round(fs * batch_s))
    cm = ClockMap()
    rng = np.random.default_rng(7)
    for i in range(0, t_s.size, per):
        t = t_s[i : i + per]
        cm.update(float(t[-1]), 5000.0 + float(t[-1]) * (1 + 30e-6) + rng.exponential(0.5e-3))
        yield SampleBatch.from_columns(
            cm.offset + cm.ratio * t, t, length[i : i + per], np.rint(t * fs), np.full(t.size, status), (),
            "serial:bench",
        )


def feed_paced(lg: McapLogger, batches: Iterable[SampleBatch], fs: float, flush_s: float) -> int:
    """Feed as fast as possible, closing a chunk every ``flush_s`` of samples: the chunking the
    flush timer gives at real-time pace (its worst case: it flushes 0.5..0.55 s after the first
    record).  Returns the number of samples fed."""
    n = since = 0
    per_flush = fs * flush_s
    for b in batches:
        lg.on_batch(b)
        n += len(b)
        since += len(b)
        if since >= per_flush:
            lg.flush()
            since = 0
    return n


def run_once(batches: list[SampleBatch], fs: float, flush_s: float, where: Path) -> tuple[float, float, float]:
    """(bytes/sample, write samples/s, read samples/s) of one run into an empty directory."""
    lg = McapLogger(where, "bench", rotate_per_test=False, flush_s=flush_s, rotate_bytes=1 << 40, quota_bytes=1 << 41)
    t0 = time.perf_counter()
    n = feed_paced(lg, batches, fs, flush_s)
    lg.stop()
    t_write = time.perf_counter() - t0
    (path,) = list_recordings(where / "recordings")
    size = path.stat().st_size
    t0 = time.perf_counter()
    t, _L = read_mcap(path)
    t_read = time.perf_counter() - t0
    if t.size != n:
        raise RuntimeError(f"read back {t.size} samples of {n}")
    return size / n, n / t_write, n / t_read


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bench_mcap", description=__doc__.split("\n", 1)[0])
    p.add_argument("--rates", default="15.625,1000,10000", help="sample rates in Hz, comma separated")
    p.add_argument("--repeats", type=int, default=3, help="runs per rate (medians are reported)")
    p.add_argument("--noise-um", type=float, default=0.1, help="LVDT noise, um rms")
    p.add_argument("--quantum-um", type=float, default=0.0, help="reading quantum, um (a real bar: 0.01)")
    p.add_argument("--flush-s", type=float, default=0.5, help="chunk period, s (the logger's flush_s)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        rates = [float(r) for r in args.rates.split(",") if r.strip()]
    except ValueError:
        print(f"error: --rates must be numbers, not {args.rates!r}", file=sys.stderr)
        return 2
    if args.repeats < 1:
        print("error: --repeats must be >= 1", file=sys.stderr)
        return 2
    machine = MachineModel(noise_um=args.noise_um, quantum_um=args.quantum_um, backlash_x_um=3.0, squareness_urad=15.0)
    print(f"MCAP log benchmark: noise {args.noise_um:g} um, quantum {args.quantum_um:g} um, "
          f"chunk every {args.flush_s:g} s, medians of {args.repeats}")
    print(f"{'rate Hz':>9} {'samples':>9} {'bytes/sample':>13} {'write S/s':>11} {'read S/s':>11}")
    for fs in rates:
        r = simulate(TestPlan(sample_hz=fs), machine, fs)
        batches = list(serial_batches(r.t_s, r.length_mm, fs))
        runs = []
        for _ in range(args.repeats):
            where = Path(tempfile.mkdtemp(prefix="bench_mcap_"))
            try:
                runs.append(run_once(batches, fs, args.flush_s, where))
            finally:
                shutil.rmtree(where, ignore_errors=True)
        bps, w, rd = (statistics.median(x) for x in zip(*runs, strict=True))
        print(f"{fs:>9g} {r.t_s.size:>9d} {bps:>13.2f} {w:>11.3g} {rd:>11.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
