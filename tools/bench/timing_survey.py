"""Stalled hosts and drop-outs: how far the values move, against their stated standard errors.

One simulated test per seed (R 100 mm at 1500 mm/min, 250 Hz, 3 um of X
backlash, 20 urad of squareness), analysed clean and then:

- ``stalls``: stamped on receipt by a host 0.5 ms late on average that stalls
  every 3 s for 40 to 100 ms (the samples taken meanwhile arrive together);
- ``drop D``: D seconds lost from the CW data arc at 225 deg (between two
  reversals), the samples after it on the same clock.

Per case: the largest deviation from the clean analysis of backlash_x,
squareness and servo_mismatch in units of the case's stated standard error,
the misfit evaluations, and for a drop-out its stated squareness factor against
the squareness standard error's actual growth.  Run:
``python -m ballbar.tools.bench.timing_survey --seeds 5``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

import numpy as np

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import data_start_deg, schedule
from ballbar.tools.simulator import MachineModel, simulate

FS = 250.0
PLAN = TestPlan(radius_mm=100, feed_mm_min=1500, overshoot_deg=10, dwell_s=0.2, sample_hz=FS)
CHECKED = ("backlash_x_um", "squareness_urad", "servo_mismatch_ms")


def stalled(t: np.ndarray, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out = t + rng.exponential(0.5e-3, t.size)
    for s0 in np.arange(t[0] + 1.0, t[-1], 3.0):
        dur = rng.uniform(0.04, 0.1)
        idx = np.flatnonzero((t >= s0) & (t < s0 + dur))
        out[idx] = s0 + dur + 1e-4 + 2e-6 * np.arange(idx.size)
    return out


def test_of(out: list[Any]) -> dict[str, Any] | str:
    for r in out:
        if r.get("event") == "test_rejected":
            return str(r["message"])
    return next(r for r in out if r.get("kind") == "test")


def at_deg(clean: dict[str, Any], deg: float) -> float:
    tm = clean["timing"]
    sched = schedule(PLAN, tm["measured_feed_mm_min"] / 60.0, tm["overhead_s"])
    return float(tm["feed_in_s"] + sched.data_start_s[-1]
                 + np.radians(data_start_deg(PLAN, -1) - deg) * PLAN.radius_mm / sched.feed_mm_s)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5)
    args = ap.parse_args(argv)
    print("seed case        max|dev|/se  evals  stated  grown")
    for seed in range(args.seeds):
        m = MachineModel(lead_s=0.5, tail_s=2.0, backlash_x_um=3.0, squareness_urad=20.0, noise_um=0.1)
        r = simulate(PLAN, m, FS, seed=seed)
        t, L = r.t_s, r.length_mm
        clean = test_of(analyze_recording(t, L, PLAN))
        assert isinstance(clean, dict), clean
        cases: list[tuple[str, np.ndarray, np.ndarray]] = [("stalls", stalled(t, seed + 100), L)]
        for d in (0.5, 1.0, 1.5, 2.0):
            a = at_deg(clean, 225.0)
            keep = ~((t > a) & (t <= a + d))
            cases.append((f"drop {d:.1f} s", t[keep], L[keep]))
        for name, tc, Lc in cases:
            res = test_of(analyze_recording(tc, Lc, PLAN))
            if isinstance(res, str):
                print(f"{seed:4d} {name:11s} rejected: {res}")
                continue
            dev = max(abs(res["parameters"][k]["value"] - clean["parameters"][k]["value"])
                      / res["parameters"][k]["stderr"] for k in CHECKED)
            stated = grown = float("nan")
            if res.get("dropouts"):
                cost = {c["pattern"]: c["stderr_factor"] for c in res["dropouts"][0].get("cost", [])}
                stated = cost.get("squareness", float("nan"))
                se = "squareness_urad"
                grown = res["parameters"][se]["stderr"] / clean["parameters"][se]["stderr"]
            print(f"{seed:4d} {name:11s} {dev:11.2f} {res['fit']['evaluations']:6d} {stated:7.4f} {grown:6.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
