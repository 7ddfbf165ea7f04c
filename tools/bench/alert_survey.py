"""How often the monitor alerts on a stable machine, and how well it forecasts a wearing one.

Every test is simulated on the physical machine model (:mod:`.simulator`) and
analysed by the daemon's engine; the results go through the daemon's monitor
(:class:`ballbar.daemon.monitor.Monitor`: verdict, history, Theil-Sen trend,
forecast, alert states) with synthetic timestamps, one test per day (plus up
to an hour of jitter).  Two scenarios, each over ``--seeds`` machines:

- ``stable``: a machine that does not change (backlash, squareness, servo
  mismatch well inside the limits), measured ``--tests`` times with the sensor
  noise ``--noise-um`` and a test-to-test scatter of the backlash
  (``--scatter-um``, the repeatability of a real machine, which the
  simulator's sensor noise alone does not give).  Any alert is a false alert:
  the rate is the fraction of machines with at least one.
- ``wear``: the same machine whose X backlash grows by ``--rate-um-day`` per
  test (per day).  After the last test, the forecast of ``backlash_x_um``
  crossing its limit: whether it is due, and whether its interval holds the
  true crossing date (where the simulated backlash reaches the limit).

::

    python -m ballbar.tools.bench.alert_survey --seeds 200 --jobs 2 --json survey.json

The plan is short (3000 mm/min, 20 deg overshoots, 250 Hz) so that a test
takes a fraction of a second to simulate and analyse.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np

from ballbar.analysis import monitor as mon
from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.plan import TestPlan
from ballbar.daemon.monitor import Monitor
from ballbar.tools.simulator import MachineModel, simulate

PLAN = TestPlan(feed_mm_min=3000.0, overshoot_deg=20.0, sample_hz=250.0)
BASE = MachineModel(backlash_x_um=3.0, backlash_y_um=1.5, squareness_urad=15.0, centre_x_um=5.0)
LIMITS = {"enabled": True, "G_b_um": 12.0, "parameters": {"backlash_x_um": 8.0, "squareness_urad": 40.0}}
START = datetime(2026, 1, 5, 6, 0, tzinfo=UTC)


@dataclass
class Scenario:
    seed: int
    tests: int = 20
    noise_um: float = 0.3
    scatter_um: float = 0.2
    rate_um_day: float = 0.0  # backlash_x_um growth per day (one test a day)
    horizon_days: float = 30.0
    min_tests: int = 6


def run(sc: Scenario) -> dict[str, Any]:
    """One machine over ``sc.tests`` daily tests: the alerts, the last forecast of backlash_x_um, the truth."""
    settings = mon.settings_from_dict({**LIMITS, "horizon_days": sc.horizon_days, "min_tests": sc.min_tests})
    monitor = Monitor(settings, "survey")
    rng = np.random.default_rng([sc.seed, 7])
    alerts: list[dict[str, Any]] = []
    last_forecast: Mapping[str, Any] | None = None
    times = []
    for i in range(sc.tests):
        when = START + timedelta(days=i, minutes=float(rng.uniform(0, 60)))
        times.append(when)
        b = BASE.backlash_x_um + sc.rate_um_day * (when - START).total_seconds() / 86400.0
        b += float(rng.normal(0.0, sc.scatter_um)) if sc.scatter_um > 0 else 0.0
        machine = replace(BASE, backlash_x_um=b, noise_um=sc.noise_um)
        sim = simulate(PLAN, machine, PLAN.sample_hz, seed=sc.seed * 1000 + i)
        result = dict(next(r for r in analyze_recording(sim.t_s, sim.length_mm, PLAN) if r["kind"] == "test"))
        result.update(machine_id="survey", test_id=f"survey-{sc.seed}-{i}", t_wall=mon.time_text(when))
        result["verdict"] = monitor.verdict(result)
        for a in monitor.on_test(result):
            alerts.append({k: a.get(k) for k in ("alert", "state", "limit", "test_id", "message")})
        last_forecast = next(f for f in monitor.forecasts(result) if f["name"] == "backlash_x_um")
    out: dict[str, Any] = {"seed": sc.seed, "alerts": alerts, "forecast": last_forecast}
    if sc.rate_um_day > 0:
        true_days = (LIMITS["parameters"]["backlash_x_um"] - BASE.backlash_x_um) / sc.rate_um_day  # type: ignore[index]
        true = START + timedelta(days=true_days)
        out["true_crossing"] = mon.time_text(true)
        f = last_forecast or {}
        lo, hi = f.get("crossing_lo"), f.get("crossing_hi")
        out["covered"] = bool(lo and hi and mon.parse_time(lo) <= true <= mon.parse_time(hi))
        if f.get("crossing"):
            out["error_days"] = (mon.parse_time(f["crossing"]) - true).total_seconds() / 86400.0
    return out


def survey(scenarios: Sequence[Scenario], jobs: int) -> list[dict[str, Any]]:
    if jobs <= 1:
        return [run(s) for s in scenarios]
    with ProcessPoolExecutor(jobs) as ex:
        return list(ex.map(run, scenarios))


def summarize(stable: Sequence[dict[str, Any]], wear: Sequence[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    if stable:
        alerted = [r for r in stable if r["alerts"]]
        out["stable"] = {
            "machines": len(stable),
            "machines_with_alerts": len(alerted),
            "false_alert_rate": len(alerted) / len(stable),
            "alerts": [a for r in alerted for a in r["alerts"]][:20],
        }
    if wear:
        due = [r for r in wear if r["forecast"] and r["forecast"].get("due")]
        covered = [r for r in wear if r.get("covered")]
        errors = [abs(r["error_days"]) for r in wear if r.get("error_days") is not None]
        widths = []
        for r in wear:
            f = r["forecast"] or {}
            if f.get("crossing_lo") and f.get("crossing_hi"):
                span = mon.parse_time(f["crossing_hi"]) - mon.parse_time(f["crossing_lo"])
                widths.append(span.total_seconds() / 86400.0)
        out["wear"] = {
            "machines": len(wear),
            "forecast_due": len(due),
            "coverage": len(covered) / len(wear),
            "median_abs_error_days": float(np.median(errors)) if errors else None,
            "median_interval_days": float(np.median(widths)) if widths else None,
            "true_crossing": wear[0].get("true_crossing"),
        }
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.alert_survey", description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, default=200, help="machines per scenario")
    p.add_argument("--tests", type=int, default=20, help="tests per machine, one a day")
    p.add_argument("--scenario", choices=("both", "stable", "wear"), default="both")
    p.add_argument("--noise-um", type=float, default=0.3, help="sensor noise (RMS)")
    p.add_argument("--scatter-um", type=float, default=0.2, help="test-to-test scatter of the backlash (SD)")
    p.add_argument("--rate-um-day", type=float, default=0.15, help="wear: backlash growth per day")
    p.add_argument("--horizon-days", type=float, default=30.0)
    p.add_argument("--min-tests", type=int, default=6)
    p.add_argument("--first-seed", type=int, default=1)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--json", help="write every machine's outcome and the summary here")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    t0 = time.monotonic()
    common = {"tests": args.tests, "noise_um": args.noise_um, "scatter_um": args.scatter_um,
              "horizon_days": args.horizon_days, "min_tests": args.min_tests}
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    stable = survey([Scenario(s, **common) for s in seeds], args.jobs) if args.scenario != "wear" else []
    wear = (survey([Scenario(s, rate_um_day=args.rate_um_day, **common) for s in seeds], args.jobs)
            if args.scenario != "stable" else [])
    summary = summarize(stable, wear)
    summary["settings"] = {**vars(args), "limits": LIMITS, "plan": PLAN.to_dict(),
                           "seconds": round(time.monotonic() - t0, 1)}
    print(json.dumps(summary, indent=2, default=str))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"summary": summary, "stable": stable, "wear": wear}, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

__all__ = ["Scenario", "main", "run", "summarize", "survey"]
