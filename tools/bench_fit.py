"""Benchmark: the fit's cost per circle and per test against a plain lstsq.

For 15.625 Hz, 1 kHz and 10 kHz, on a simulated test with every pattern of
the library (``ballbar.tools.simulator``, noisy), it measures on one core:

- ``circle_update``: what finishing a circle costs live, the samples having
  been folded in as they arrived (0.1 s chunks): the last chunk, the solve with
  ranking and identifiability, and the result object.
- ``circle_fold``: folding a whole circle's samples in (design + QR), summed
  over its chunks: the work spread over the circle's duration.
- ``lstsq_circle``: ``numpy.linalg.lstsq`` of the same circle's design matrix
  (built beforehand, not timed): the baseline.
- ``test``: the whole analysis of a recording as ``ballbar analyze`` makes it
  (detection, lag and spike width search, the joint fit with physical
  corrections, ISO, noise, advice; no provisional circles, which only the live
  daemon publishes), and ``lstsq_test``: lstsq of the whole test's design
  matrix.

Medians over repeats, with the ratio to the baseline measured in the same run.
Run: ``OPENBLAS_NUM_THREADS=1 python -m ballbar.tools.bench_fit`` (it sets the
single-thread variables itself when they are unset).
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402

import numpy as np  # noqa: E402

from ballbar.analysis import AnalysisOptions, MachineConfig, TestPlan  # noqa: E402
from ballbar.analysis.engine import CircleFit, TestAnalyzer, analyze_recording, make_timing  # noqa: E402
from ballbar.analysis.fit import solve  # noqa: E402
from ballbar.analysis.patterns import design, select  # noqa: E402
from ballbar.tools.simulator import MachineModel, simulate  # noqa: E402

MACHINE = MachineModel(
    centre_x_um=12.0, backlash_x_um=4.0, backlash_y_um=2.0, kv_y_per_s=32.0, master_slave_a_um=1.0,
    squareness_urad=15.0, scale_x_ppm=5.0, lateral_play_x_um=1.0, straightness_y_um=0.8, spike_x_um=2.0,
    cyclic_x_um=0.3, pitch_x_mm=10.0, drift_um_per_min=0.2, noise_um=0.2,
)


def _median_ms(fn: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000.0 * statistics.median(times)


def bench(fs: float, repeats: int) -> dict[str, float]:
    plan = TestPlan(sample_hz=fs)
    machine = MachineConfig(pitch_x_mm=10.0)
    sim = simulate(plan, MACHINE, fs)
    t, L = sim.t_s, sim.length_mm
    an = TestAnalyzer(plan, machine)
    an.feed(t, L)  # finds the feed-in, so that the circles have their windows
    circle = an._circles[0] if an._circles else None
    assert circle is not None
    patterns = circle.patterns
    timing = circle.timing
    m = (t >= circle.t_start) & (t <= circle.t_end)
    tc, Lc = t[m], L[m]
    chunk = max(1, round(0.1 * fs))

    def fresh() -> CircleFit:
        return CircleFit(plan, machine, patterns, 1, timing, 3.0)

    def fold_all() -> CircleFit:
        cf = fresh()
        for i in range(0, tc.size, chunk):
            cf.add(tc[i : i + chunk], Lc[i : i + chunk])
        return cf

    last = slice(max(0, tc.size - chunk), tc.size)
    before_last = fresh()
    for i in range(0, last.start, chunk):
        before_last.add(tc[i : min(i + chunk, last.start)], Lc[i : min(i + chunk, last.start)])

    def update() -> None:
        cf = fresh()
        cf.factor = before_last.factor.merged(cf.factor)  # a copy: the circle so far
        cf.colmax = before_last.colmax.copy()
        cf.add(tc[last], Lc[last])  # the circle's last chunk arrives
        fit = solve(cf.factor, cf.patterns, effect_scale=cf.colmax)
        an._circle_result(cf, fit)

    A = design(patterns, circle.geometry(tc), np.radians(3.0))
    y = (Lc - plan.radius_mm) * 1000.0

    full_patterns = select(None, (1, -1), 10.0, None)
    tm = make_timing(plan, timing.t_ref, timing.feed_mm_s, 0.0)
    parts = []
    for d in (1, -1):
        mine = [p for p in full_patterns if p.reversal is None or p.reversal[2] == d]
        cf = CircleFit(plan, machine, mine, d, tm, 3.0)
        mm = (t >= cf.t_start) & (t <= cf.t_end)
        g = cf.geometry(t[mm])
        parts.append((design(full_patterns, g, np.radians(3.0)), (L[mm] - plan.radius_mm) * 1000.0))
    A_test = np.vstack([p[0] for p in parts])
    y_test = np.concatenate([p[1] for p in parts])
    test_repeats = max(1, repeats // 3)
    out = {
        "samples_circle": float(tc.size),
        "columns": float(A.shape[1]),
        "circle_update_ms": _median_ms(update, repeats),
        "circle_fold_ms": _median_ms(fold_all, max(1, repeats // 2)),
        "lstsq_circle_ms": _median_ms(lambda: np.linalg.lstsq(A, y, rcond=None), repeats),
        "test_ms": _median_ms(lambda: analyze_recording(t, L, plan, machine, AnalysisOptions(), circles=False),
                              test_repeats),
        "lstsq_test_ms": _median_ms(lambda: np.linalg.lstsq(A_test, y_test, rcond=None), test_repeats),
    }
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench_fit", description=__doc__.splitlines()[0])
    p.add_argument("--rates", default="15.625,1000,10000", help="sample rates (Hz), comma-separated")
    p.add_argument("--repeats", type=int, default=9)
    args = p.parse_args(argv)
    rates = [float(r) for r in args.rates.split(",")]
    print(f"threads: OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS')}; medians of {args.repeats}")
    head = (f"{'rate Hz':>9} {'n/circle':>9} {'cols':>5} {'update ms':>10} {'fold ms':>9} {'lstsq c ms':>11} "
            f"{'upd/lstsq':>9} {'test ms':>9} {'lstsq t ms':>11} {'test/lstsq':>10}")
    print(head)
    for fs in rates:
        r = bench(fs, args.repeats)
        print(
            f"{fs:9.3f} {r['samples_circle']:9.0f} {r['columns']:5.0f} {r['circle_update_ms']:10.2f} "
            f"{r['circle_fold_ms']:9.1f} {r['lstsq_circle_ms']:11.2f} "
            f"{r['circle_update_ms'] / r['lstsq_circle_ms']:9.2f} {r['test_ms']:9.1f} {r['lstsq_test_ms']:11.1f} "
            f"{r['test_ms'] / r['lstsq_test_ms']:10.2f}"
        )
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
