"""False alarms: how often the analyzer reports an error a simulated machine does not have.

Each random machine (:func:`random_machine`) has the errors a real one
usually has, in random sizes: backlash of either sign (a negative one is an
over-set compensation), position-loop gains of 20..50/s, unequal on most
machines, squareness, scale, a pivot offset, sometimes a master-slave
changeover, noise of 0.05..0.3 um, a jerk limit, a coarse gauge (0.1 um
steps), dropped and jittered samples; at 15.625, 250, 500 or 1000 Hz. It has
no reversal spikes, lateral play, straightness or drift, and often no servo
mismatch or changeover. Every significant pattern whose true value is zero
(``simulate``'s truth) is a false alarm.

``--draw independent`` draws the two axes' gains independently (20..50/s,
equal on 30 % of machines) with the pivot up to 20 um off centre, the machines
of a survey in which a linear mask fit read the pivot offset times the servo
mismatch as drift and lateral play; ``--rates 15.625`` restricts either draw
to one rate (at 15.625 Hz the feed-in's settling is not resolved and the
loops' lag is searched with the timing: the drift survey).  ``--quantum-um Q``
reads every machine as a digital indicator of resolution ``Q`` whose own noise
is below its step (the noise drawn times ``Q``: 0.05..0.3 of a step), the
survey of issue 34's quantised gauges (``--rates 15.625,50``).

Printed: per family, the share of machines that showed it falsely (with a
Wilson 95 % interval); the share with any false finding, in all and per
sample rate; each false finding with its p-value; and, for the patterns the
machines do have, how many of their fitted values lie within three stated
standard errors of the truth. Run:
``python -m ballbar.tools.bench.false_alarms --machines 200 --seed 1000 --jobs 2``.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from ballbar.analysis import TestPlan
from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.fit import family
from ballbar.analysis.patterns import BY_NAME, LIBRARY
from ballbar.tools.simulator import MachineModel, simulate

RATES = (15.625, 250.0, 500.0, 1000.0)


def random_machine(
    rng: np.random.Generator, draw: str = "standard", rates: Sequence[float] = RATES
) -> tuple[MachineModel, float]:
    """A machine without spikes, lateral play, straightness or drift, and a sample rate.  ``draw``: how the
    gains are drawn, ``standard`` (within 10 % of each other on 60 % of machines, else equal) or
    ``independent`` (each 20..50/s, equal on 30 %)."""
    kx = float(rng.uniform(20.0, 50.0))
    if draw == "independent":
        ky = float(rng.uniform(20.0, 50.0)) if rng.random() >= 0.3 else kx
    else:
        ky = kx * float(rng.uniform(0.9, 1.1)) if rng.random() < 0.6 else kx
    kw: dict[str, Any] = dict(
        backlash_x_um=float(rng.uniform(-6, 6)), backlash_y_um=float(rng.uniform(-6, 6)), kv_x_per_s=kx,
        kv_y_per_s=ky, squareness_urad=float(rng.uniform(-30, 30)), scale_x_ppm=float(rng.uniform(-10, 10)),
        centre_x_um=float(rng.uniform(-20, 20)), centre_y_um=float(rng.uniform(-20, 20)),
        noise_um=float(rng.uniform(0.05, 0.3)), jerk_mm_s3=float(rng.choice([math.inf, 50_000.0, 20_000.0])),
        master_slave_a_um=float(rng.uniform(-1, 1)) if rng.random() < 0.3 else 0.0,
        quantum_um=0.1 if rng.random() < 0.3 else 0.0,
    )
    if rng.random() < 0.3:
        kw.update(drop_fraction=0.02, jitter_s=0.0005, jitter_stamped=bool(rng.random() < 0.5))
    return MachineModel(**kw), float(rng.choice(list(rates)))


def analyse(machine: MachineModel, fs: float, seed: int = 0, **plan: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """The one test of a simulated recording of ``machine`` at ``fs``, and the simulation's truth."""
    test_plan = TestPlan(sample_hz=fs, **plan)
    sim = simulate(test_plan, machine, fs, seed=seed)
    tests = [r for r in analyze_recording(sim.t_s, sim.length_mm, test_plan) if r["kind"] == "test"]
    if len(tests) != 1:
        raise AssertionError(f"{len(tests)} tests found in one simulated test")
    return dict(tests[0]), sim.truth


def false_findings(result: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """The machine patterns ``result`` calls significant whose truth is zero: name -> p-value."""
    out = {}
    for r in result["ranking"]:
        pat = BY_NAME.get(r["pattern"])
        if (pat is not None and pat.kind == "setup") or not r["significant"]:
            continue
        fields = pat.fields if pat is not None else (f"{r['pattern']}_um",)  # a reversal spike
        if all(k in truth for k in fields) and all(truth[k] == 0.0 for k in fields):
            out[r["pattern"]] = float(r["p_value"])
    return out


def coverage(result: dict[str, Any], truth: dict[str, Any]) -> tuple[int, int, dict[str, float]]:
    """Of the fitted machine parameters whose truth is not zero, how many lie within three stated standard
    errors of it, how many there are (the set-up's and the spikes' left out), and those outside with their
    error in standard errors."""
    inside = total = 0
    outside: dict[str, float] = {}
    for key, p in result["parameters"].items():
        want = truth.get(key)
        if not want or p["value"] is None or p["stderr"] is None or key.startswith(("centre_", "radius_")):
            continue
        total += 1
        z = abs(p["value"] - want) / p["stderr"] if p["stderr"] > 0 else math.inf
        if z <= 3.0:
            inside += 1
        else:
            outside[key] = z
    return inside, total, outside


Row = tuple[int, float, dict[str, float], tuple[int, int, dict[str, float]], bool]


def _one(job: tuple[int, MachineModel, float]) -> Row:
    i, machine, fs = job
    res, truth = analyse(machine, fs, seed=i)
    return i, fs, false_findings(res, truth), coverage(res, truth), bool(res["fit"].get("valid", True))


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The Wilson score interval of a proportion ``k/n``."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def survey(
    machines: int, seed: int, jobs: int = 1, draw: str = "standard", rates: Sequence[float] = RATES,
    quantum_um: float = 0.0,
) -> list[Row]:
    """Analyse ``machines`` random machines drawn from ``seed``: per machine its rate, false findings, the
    coverage of its present patterns and whether the test was judged valid.  ``quantum_um``: read each on
    that step, its noise drawn times the step (0: as drawn)."""
    rng = np.random.default_rng(seed)
    work = [(i, *random_machine(rng, draw, rates)) for i in range(machines)]
    if quantum_um > 0:
        work = [(i, replace(m, quantum_um=quantum_um, noise_um=m.noise_um * quantum_um), fs) for i, m, fs in work]
    if jobs <= 1:
        return [_one(w) for w in work]
    with multiprocessing.get_context("spawn").Pool(jobs) as pool:
        return sorted(pool.imap_unordered(_one, work), key=lambda r: r[0])


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.false_alarms", description=__doc__.splitlines()[0])
    p.add_argument("--machines", type=int, default=100)
    p.add_argument("--seed", type=int, default=1000)
    p.add_argument("--jobs", type=int, default=1, help="processes (one per core)")
    p.add_argument("--draw", choices=("standard", "independent"), default="standard",
                   help="the gains: within 10 %% of each other (standard) or drawn independently, with pivot "
                        "offsets up to 20 um (independent)")
    p.add_argument("--rates", default=",".join(f"{r:g}" for r in RATES), help="sample rates (Hz), comma-separated")
    p.add_argument("--quantum-um", type=float, default=0.0,
                   help="read every machine on this step (um), its noise below it (0.05..0.3 of a step)")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    rows = survey(a.machines, a.seed, a.jobs, a.draw, [float(r) for r in a.rates.split(",")], a.quantum_um)
    n = len(rows)
    read = f", read on {a.quantum_um:g} um steps" if a.quantum_um > 0 else ""
    print(f"{n} random machines ({a.draw} draw{read}) from seed {a.seed}, {time.perf_counter() - t0:.0f} s")
    for i, fs, found, _, valid in rows:
        if found:
            print(f"  machine {i} at {fs:g} Hz: " + ", ".join(f"{k} (p = {v:.2g})" for k, v in found.items()))
        if not valid:
            print(f"  machine {i} at {fs:g} Hz: marked invalid")
    for i, fs, _, (_, _, outside), _ in rows:
        if outside:
            print(f"  machine {i} at {fs:g} Hz, beyond 3 standard errors: "
                  + ", ".join(f"{k} ({z:.1f})" for k, z in sorted(outside.items())))
    families = sorted({family(pat.name) for pat in LIBRARY if pat.kind != "setup"} | {"reversal_spike"})
    print("false alarm rate per family (machines with it falsely significant, Wilson 95 %):")
    for fam in families:
        k = sum(any(family(name) == fam for name in found) for _, _, found, _, _ in rows)
        lo, hi = wilson(k, n)
        print(f"  {fam:18s} {k:4d}/{n} = {100 * k / n:5.1f} %  [{100 * lo:.1f}, {100 * hi:.1f}]")
    k = sum(bool(found) for _, _, found, _, _ in rows)
    lo, hi = wilson(k, n)
    print(f"  {'any':18s} {k:4d}/{n} = {100 * k / n:5.1f} %  [{100 * lo:.1f}, {100 * hi:.1f}]")
    for rate in sorted({fs for _, fs, _, _, _ in rows}):
        sub = [found for _, fs, found, _, _ in rows if fs == rate]
        k = sum(bool(found) for found in sub)
        print(f"  any at {rate:g} Hz: {k}/{len(sub)} = {100 * k / len(sub):.1f} %")
    inside = sum(c[0] for _, _, _, c, _ in rows)
    total = sum(c[1] for _, _, _, c, _ in rows)
    print(f"present patterns within 3 stated standard errors of the truth: {inside}/{total}")
    invalid = sum(not v for *_, v in rows)
    print(f"tests marked invalid: {invalid}/{n}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
