"""False findings and calibration of the fit on the independent simulator.

    python -m ballbar.tools.bench.physim_survey --machines 120 --seed 1 \\
        --rates 15.625,100,250,1000 --jobs 1

Machines are drawn as issue 34 states: the two axes' gains independent 20 to
50 1/s, per axis lost motion of either sign (a mechanical dead band, an
over-set compensation, or both), R 50 to 150 mm, F 500 to 2000 mm/min, pivot
offsets up to 20 um, squareness and scale; no lateral play, spikes,
straightness, master-slave, cyclic error or drift. Rates are dealt in turn.
"""

from __future__ import annotations

import argparse
import math
import time
from concurrent.futures import ProcessPoolExecutor
from typing import Any, cast

import numpy as np

from ballbar.analysis import TestPlan
from ballbar.analysis.engine import analyze_recording
from ballbar.tools.bench import physim as ps

PRESENT = ("centre_x_um", "centre_y_um", "backlash_x_um", "backlash_y_um",
           "servo_mismatch_ms", "squareness_urad", "scale_mismatch_ppm")
ABSENT_PREFIX = ("lateral_play", "master_slave", "straightness", "reversal_spike", "cyclic", "drift")


def _lost_motion(rng: np.random.Generator) -> tuple[float, float]:
    """(play, compensation) in um: a dead band, an over-set compensation, or both."""
    kind = rng.integers(3)
    if kind == 0:
        return float(rng.uniform(0, 15)), 0.0
    if kind == 1:
        return 0.0, float(rng.uniform(0, 10))
    play = float(rng.uniform(0, 15))
    return play, float(rng.uniform(0, 1.5) * play)


def draw(rng: np.random.Generator, rate: float) -> tuple[ps.Machine, ps.Path, ps.Gauge]:
    axes = []
    for _ in range(2):
        play, comp = _lost_motion(rng)
        axes.append(ps.Axis(kv=float(rng.uniform(20, 50)), play_um=play, comp_um=comp,
                            scale_ppm=float(rng.uniform(-20, 20))))
    ang = rng.uniform(0, 2 * np.pi)
    off = rng.uniform(0, 20)
    machine = ps.Machine(x=axes[0], y=axes[1], squareness_urad=float(rng.uniform(-30, 30)),
                         centre_x_um=float(off * np.cos(ang)), centre_y_um=float(off * np.sin(ang)),
                         accel_mm_s2=float(rng.uniform(500, 2000)))
    path = ps.Path(radius_mm=float(rng.uniform(50, 150)), feed_mm_min=float(rng.uniform(500, 2000)))
    gauge = ps.Gauge(sample_hz=rate, noise_um=float(rng.uniform(0.05, 0.3)), phase=float(rng.uniform()))
    return machine, path, gauge


def _kind(axis: ps.Axis) -> str:
    if axis.comp_um == 0:
        return "dead band"
    return "over-set compensation" if axis.play_um == 0 else "dead band and compensation"


def run_one(args: tuple[int, int, float]) -> dict[str, Any]:
    seed, index, rate = args
    rng = np.random.default_rng([seed, index])
    machine, path, gauge = draw(rng, rate)
    t, L = ps.simulate(machine, path, gauge, seed=int(rng.integers(2**31)))
    plan = TestPlan(sample_hz=rate, radius_mm=path.radius_mm, feed_mm_min=path.feed_mm_min)
    tests = [r for r in analyze_recording(t, L, plan) if r.get("kind") == "test"]
    out: dict[str, Any] = {"rate": rate, "tests": len(tests), "absent": {}, "present": {},
                           "kind": {"x": _kind(machine.x), "y": _kind(machine.y)}}
    if not tests:
        return out
    params: dict[str, Any] = dict(cast(dict[str, Any], tests[0].get("parameters") or {}))
    for name, p in params.items():
        if name.startswith(ABSENT_PREFIX) and p.get("p_value") is not None:
            out["absent"][name] = (float(p["p_value"]), bool(p.get("significant")))
    tr = ps.truth(machine, path)
    for name in PRESENT:
        p = params.get(name)
        if p and p.get("value") is not None and p.get("stderr"):
            out["present"][name] = (float(p["value"]) - tr[name]) / float(p["stderr"])
    return out


def wilson(k: int, n: int) -> tuple[float, float]:
    if n == 0:
        return 0.0, 1.0
    z = 1.959964
    ph = k / n
    den = 1 + z * z / n
    c = (ph + z * z / (2 * n)) / den
    h = z * math.sqrt(ph * (1 - ph) / n + z * z / (4 * n * n)) / den
    return max(0.0, c - h), min(1.0, c + h)


def report(results: list[dict[str, Any]], rates: list[float]) -> None:
    print("false findings (any absent pattern significant), Wilson 95 %:")
    for rate in [*rates, 0.0]:
        rs = [r for r in results if (rate == 0.0 or r["rate"] == rate)]
        k = sum(any(sig for _, sig in r["absent"].values()) for r in rs)
        lo, hi = wilson(k, len(rs))
        label = "all" if rate == 0.0 else f"{rate:g} Hz"
        print(f"  {label:>10}: {k:3d} of {len(rs):3d}  {100 * k / max(len(rs), 1):5.1f} %"
              f"  [{100 * lo:4.1f}, {100 * hi:4.1f}]")
    missing = sum(r["tests"] == 0 for r in results)
    if missing:
        print(f"  ({missing} recordings gave no test result)")
    print("p-value calibration of absent patterns (share p < 0.05, p < 0.01, significant):")
    names = sorted({n for r in results for n in r["absent"]})
    for n in names:
        ps_ = [r["absent"][n] for r in results if n in r["absent"]]
        a = sum(p < 0.05 for p, _ in ps_) / len(ps_)
        b = sum(p < 0.01 for p, _ in ps_) / len(ps_)
        s = sum(sig for _, sig in ps_)
        print(f"  {n:34s} n={len(ps_):3d}  {100 * a:5.1f} %  {100 * b:5.1f} %  sig {s}")
    print("present patterns: fitted within 3 stated standard errors of the truth:")
    for n in PRESENT:
        zs = [r["present"][n] for r in results if n in r["present"]]
        k = sum(abs(z) <= 3 for z in zs)
        med = float(np.median(np.abs(zs))) if zs else float("nan")
        print(f"  {n:22s} {k:3d} of {len(zs):3d}  median |z| {med:6.2f}")
    print("lost motion within 3 stated standard errors, by its kind:")
    for kind in ("dead band", "over-set compensation", "dead band and compensation"):
        zs = [r["present"][f"backlash_{a}_um"] for r in results for a in "xy"
              if r.get("kind", {}).get(a) == kind and f"backlash_{a}_um" in r["present"]]
        k = sum(abs(z) <= 3 for z in zs)
        print(f"  {kind:28s} {k:3d} of {len(zs):3d}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--machines", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rates", default="15.625,100,250,1000")
    ap.add_argument("--jobs", type=int, default=1)
    a = ap.parse_args(argv)
    rates = [float(x) for x in a.rates.split(",")]
    jobs = [(a.seed, i, rates[i % len(rates)]) for i in range(a.machines)]
    t0 = time.monotonic()
    if a.jobs > 1:
        with ProcessPoolExecutor(a.jobs) as ex:
            results = list(ex.map(run_one, jobs))
    else:
        results = [run_one(j) for j in jobs]
    report(results, rates)
    print(f"{a.machines} machines in {time.monotonic() - t0:.0f} s")


if __name__ == "__main__":
    main()
