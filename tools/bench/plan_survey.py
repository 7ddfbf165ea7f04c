"""Recognition survey: how often a test is taken for the wrong plan, or for none, over random simulated tests.

A library of seven plans (:data:`LIBRARY`): three planes, two feeds, two
radii; the vertical planes over 220 deg with 5 deg overshoots (the README's
recipe), so that ZX and YZ at one feed have the same timing and only their
signatures tell them apart.  Each test draws a plan, a random 3D machine
(:mod:`ballbar.tools.machine3d`: lost motion, gains, scales, squareness,
spikes, pivot offsets, a jerk limit or an in-position wait that lengthens
every move), a feed override of 80..120 %, a sample rate of 15.625 Hz to
1 kHz, dropped samples and timestamp jitter; it is simulated twice, once as
``ballbar gcode`` writes it (its signature before the feed-in) and once
without the signature (a program from elsewhere), and each recording is
analysed with the library as the daemon analyses it.  Besides, ``--foreign``
tests run programs of no plan of the library: one carrying a signature no plan
has (a program of another configuration) and one without, whose timing fits
no plan.

Counted per variant: right (the plan and its plane), wrong (another plan: the
goal is none), no match (``test_unrecognised``, by reason), and any other
outcome (a rejection).  Run:
``python -m ballbar.tools.bench.plan_survey --tests 240 --seed 27 --jobs 2``.
"""

from __future__ import annotations

import argparse
import logging
import math
import multiprocessing
import sys
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any, cast

import numpy as np

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.plan import Plane, TestPlan
from ballbar.analysis.plans import NamedPlan, PlanLibrary
from ballbar.tools.bench.false_alarms import wilson
from ballbar.tools.machine3d import Machine3D, program_of
from ballbar.tools.simulator import MachineModel, simulate

RATES = (15.625, 100.0, 250.0, 500.0, 1000.0)
VERTICAL = {"ZX": -115.0, "YZ": -25.0}  # start angles of the symmetric 220 deg test (README)


def _vertical(plane: str, feed: float) -> TestPlan:
    return TestPlan(plane=cast(Plane, plane), feed_mm_min=feed, start_deg=VERTICAL[plane], overshoot_deg=5.0,
                    data_arc_deg=220.0)


LIBRARY = PlanLibrary.from_plans({
    "xy": TestPlan(),
    "xy_fast": TestPlan(feed_mm_min=2000.0),
    "xy_r150": TestPlan(radius_mm=150.0),
    "zx": _vertical("ZX", 1000.0),
    "yz": _vertical("YZ", 1000.0),
    "zx_fast": _vertical("ZX", 2000.0),
    "yz_fast": _vertical("YZ", 2000.0),
})
#: Programs of no plan of the library: one with a signature no plan carries, one without whose timing fits none.
FOREIGN = (
    NamedPlan("other_config", TestPlan(), next(c for c in range(125) if LIBRARY.by_signature(c) is None)),
    NamedPlan("short_ccw", TestPlan(directions="ccw", data_arc_deg=45.0, overshoot_deg=10.0), None),
)


def random_machine(rng: np.random.Generator) -> tuple[Machine3D, float]:
    """A 3D machine with the errors real ones have, in random sizes, and a sample rate."""
    axes: dict[str, float] = {}
    for a in "xyz":
        axes[f"backlash_{a}_um"] = float(rng.uniform(-3, 8))
        axes[f"kv_{a}_per_s"] = float(rng.uniform(20, 50))
        axes[f"scale_{a}_ppm"] = float(rng.uniform(-10, 10))
        axes[f"centre_{a}_um"] = float(rng.uniform(-20, 20))
        if rng.random() < 0.3:
            axes[f"spike_{a}_um"] = float(rng.uniform(0.5, 4))
            axes[f"spike_tau_{a}_s"] = float(rng.uniform(0.02, 0.2))
    base: dict[str, Any] = dict(
        noise_um=float(rng.uniform(0.05, 0.3)), feed_override=float(rng.uniform(0.8, 1.2)),
        jerk_mm_s3=float(rng.choice([math.inf, 50_000.0, 20_000.0])),
        in_position_um=float(rng.choice([0.0, 0.0, 5.0, 20.0])), lead_s=float(rng.uniform(1.0, 4.0)),
        drop_fraction=float(rng.choice([0.0, 0.01, 0.03])), jitter_s=float(rng.choice([0.0, 0.0002, 0.0005])),
        jitter_stamped=bool(rng.random() < 0.5), quantum_um=0.1 if rng.random() < 0.3 else 0.0,
    )
    sq = {k: float(rng.uniform(-30, 30)) for k in ("squareness_xy_urad", "squareness_yz_urad", "squareness_zx_urad")}
    return Machine3D(axes, base=MachineModel(**base), **sq), float(rng.choice(RATES))


def recognise(p: NamedPlan, machine: Machine3D, fs: float, seed: int, signed: bool) -> tuple[str, str | None, str]:
    """Simulate ``p``'s program (with its signature where ``signed``) and analyse it with :data:`LIBRARY`: the
    outcome (``plan``, ``unrecognised``, ``other``), the plan recognised (or the reason) and the method."""
    plan = p.plan.with_(sample_hz=fs)
    program = program_of(p if signed else NamedPlan(p.name, p.plan, None))
    sim = simulate(plan, machine.project(plan.plane), fs, seed=seed, program=program)
    L = sim.length_mm - (p.plan.radius_mm - LIBRARY.first.plan.radius_mm)  # the bar assembled for the plan
    seen = _Recognised()
    engine_log = logging.getLogger(analyze_recording.__module__)
    engine_log.addHandler(seen)
    try:
        out = analyze_recording(sim.t_s, L, LIBRARY.detection_plan(), library=LIBRARY, circles=False)
    except Exception as err:  # a failure of the fit after the recognition: the recognition still counts
        if seen.plans:
            return "plan", seen.plans[0][0], f"{seen.plans[0][1]} (then the fit failed: {type(err).__name__}: {err})"
        return "other", None, f"{type(err).__name__}: {err}"
    finally:
        engine_log.removeHandler(seen)
    tests = [r for r in out if r["kind"] == "test"]
    if tests:
        return "plan", str(tests[0]["plan"]["name"]), str(tests[0]["recognition"]["method"])
    for r in out:  # the first unrecognised test
        if r["kind"] == "event" and r["event"] == "test_unrecognised":
            return "unrecognised", r["reason"], ",".join(r["candidates"])
    why = [str(r.get("message", r.get("event"))) for r in out
           if r.get("kind") == "event" and r.get("event") != "feed_in"]
    return "other", None, "; ".join(why)[:200]


class _Recognised(logging.Handler):
    """The plans the analysis recognised (its debug record), kept where a fit fails after the recognition."""

    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.plans: list[tuple[str, str]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.msg == "test %d recognised as %s by %s":
            self.plans.append((str(record.args[1]), str(record.args[2])))  # type: ignore[index]


Row = tuple[int, str, float, float, list[tuple[str, str, str | None, str]]]


def _one(job: tuple[int, int, int]) -> Row:
    i, seed, foreign = job
    logging.getLogger("ballbar.analysis").setLevel(logging.ERROR)  # the hints' warnings at overrides off 100 %
    engine_log = logging.getLogger(analyze_recording.__module__)
    engine_log.setLevel(logging.DEBUG)  # its record of each recognition (see _Recognised), and no more
    engine_log.propagate = False
    rng = np.random.default_rng([seed, i])
    machine, fs = random_machine(rng)
    if foreign:
        p = FOREIGN[int(rng.integers(len(FOREIGN)))]
        return i, p.name, fs, machine.base.feed_override, [("foreign", *recognise(p, machine, fs, i, True))]
    p = LIBRARY.plans[int(rng.integers(len(LIBRARY)))]
    runs = [(variant, *recognise(p, machine, fs, i, variant == "signed")) for variant in ("signed", "unsigned")]
    return i, p.name, fs, machine.base.feed_override, runs


def survey(tests: int, seed: int, jobs: int = 1, foreign: float = 0.0) -> list[Row]:
    rng = np.random.default_rng(seed)
    work = [(i, seed, int(rng.random() < foreign)) for i in range(tests)]
    if jobs <= 1:
        return [_one(w) for w in work]
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        return sorted(pool.imap_unordered(_one, work), key=lambda r: r[0])


OVERRIDE_EDGES = (90.0, 110.0)
OVERRIDE_BANDS = ("80..90 %", "90..110 %", "110..120 %")


def _split(runs: list[tuple[str, str, bool]]) -> str:
    """``(group, outcome, right plan)`` per test: per group (in the order of their first numbers), how many,
    how many right, how many without a match."""
    groups = sorted({g for g, _o, _r in runs}, key=lambda g: (float(g.split()[0].split("..")[0]), g))
    return ", ".join(f"{g} {sum(x == g for x, _o, _r in runs)} "
                     f"({sum(x == g and o == 'plan' and r for x, o, r in runs)} right, "
                     f"{sum(x == g and o == 'unrecognised' for x, o, _r in runs)} no match)" for g in groups)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.plan_survey", description=__doc__.splitlines()[0])
    ap.add_argument("--tests", type=int, default=200)
    ap.add_argument("--seed", type=int, default=27)
    ap.add_argument("--jobs", type=int, default=1, help="processes (one per core)")
    ap.add_argument("--foreign", type=float, default=0.1, help="share of tests from programs of no plan")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = survey(a.tests, a.seed, a.jobs, a.foreign)
    print(f"{len(rows)} tests from seed {a.seed} ({len(LIBRARY)} plans: {', '.join(LIBRARY.names)}), "
          f"{time.perf_counter() - t0:.0f} s")
    for variant in ("signed", "unsigned", "foreign"):
        runs = [(name, fs, k, o, got, how) for _i, name, fs, k, rs in rows for v, o, got, how in rs if v == variant]
        if not runs:
            continue
        n = len(runs)
        right = sum(o == "plan" and got == name for name, _fs, _k, o, got, _h in runs)
        wrong = [(name, got, fs, k) for name, fs, k, o, got, _h in runs if o == "plan" and got != name]
        none = Counter(got for _n, _fs, _k, o, got, _h in runs if o == "unrecognised")
        other = [(name, fs, how) for name, fs, _k, o, _g, how in runs if o == "other"]
        methods = Counter(how.split(" ")[0] for _n, _fs, _k, o, _g, how in runs if o == "plan")
        failed = [(i, name, fs, how) for i, name, fs, _k, rs in rows for v, o, _g, how in rs
                  if v == variant and o == "plan" and "the fit failed" in how]
        lo, hi = wilson(len(wrong), n)
        nm = sum(none.values())
        lo2, hi2 = wilson(nm, n)
        print(f"{variant}: {n} tests")
        if variant != "foreign":
            print(f"  right plan      {right:4d} = {100 * right / n:5.1f} %  (by {dict(methods)})")
        print(f"  wrong plan      {len(wrong):4d} = {100 * len(wrong) / n:5.1f} %  [{100 * lo:.1f}, {100 * hi:.1f}]")
        print(f"  no match        {nm:4d} = {100 * nm / n:5.1f} %  [{100 * lo2:.1f}, {100 * hi2:.1f}]  {dict(none)}")
        print(f"  other outcome   {len(other):4d}")
        for i, name, fs, how in failed:
            print(f"    test {i} ({name} at {fs:g} Hz), recognised by {how}")
        for name, got, fs, k in wrong:
            print(f"    {name} taken for {got} at {fs:g} Hz, override {100 * k:.1f} %")
        for name, fs, how in other:
            print(f"    {name} at {fs:g} Hz: {how}")
        print("  per rate: " + _split([(f"{fs:g} Hz", o, got == name) for name, fs, _k, o, got, _h in runs]))
        band = [OVERRIDE_BANDS[int(np.searchsorted(OVERRIDE_EDGES, 100 * k))] for _n, _fs, k, _o, _g, _h in runs]
        print("  per override: " + _split([(b, o, got == name) for b, (name, _fs, _k, o, got, _h) in zip(band, runs,
                                                                                                       strict=True)]))
        if variant == "unsigned":
            pairs = Counter((name, how) for name, _fs, _k, o, _g, how in runs if o == "unrecognised")
            for (name, cands), c in sorted(pairs.items()):
                print(f"    {name}: {c} not told apart from {cands}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
