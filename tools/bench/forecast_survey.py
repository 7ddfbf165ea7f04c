"""Forecasts over a survey of constant, noisy and wearing machines, tested every few minutes to every day.

Synthetic test results (no simulator: the survey is about the monitor, not the
fit) go through the daemon's monitor (:class:`ballbar.daemon.monitor.Monitor`:
verdict, history, Theil-Sen trend, forecast, alert states) exactly as the
daemon feeds it, with synthetic timestamps.  Each machine watches five limited
quantities (``G_b_um``, ``backlash_x_um``, ``backlash_y_um``,
``squareness_urad``, ``servo_mismatch_ms``); each quantity has a true value, a
test-to-test scatter (the machine's repeatability, 2 to 6 % of its limit) and a
stated standard uncertainty (what the fit reports: 0.3 to 1 times the scatter,
as fits understate the repeatability).  The interval between tests is drawn per
machine from 3 min, 15 min, 1 h, 8 h, 1 day (each test jittered by +-50 %).

- ``constant``: nothing changes; values 10 to 75 % of their limits, Gaussian
  scatter.  Any due forecast is a false one.
- ``noisy``: constant, with twice the scatter, Student-t (3 degrees of freedom)
  and one test in twenty an outlier of 4 scatters.
- ``wearing``: one quantity grows linearly from 20 to 50 % of its limit and
  reaches it after 25 to 80 tests (its rate is set per test, whatever the
  interval); the machine is tested until 3 tests past that.  Its forecast must
  be due before it crosses; the others are constant (a forecast of them is false).

Reported: machines with a false forecast (due on a constant quantity), wearing
quantities missed (never due before they cross), the lead time (from the first
due forecast to the true crossing, in tests and in days), due forecasts whose
crossing is before their last test, and due forecasts of a quantity whose test
fails::

    python -m ballbar.tools.bench.forecast_survey --machines 500 --jobs 2 --json survey.json
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np

from ballbar.analysis import monitor as mon
from ballbar.daemon.monitor import Monitor

#: name, limit, unit, whether the quantity takes both signs
QUANTITIES: tuple[tuple[str, float, str, bool], ...] = (
    ("G_b_um", 25.0, "um", False),
    ("backlash_x_um", 8.0, "um", True),
    ("backlash_y_um", 8.0, "um", True),
    ("squareness_urad", 50.0, "urad", True),
    ("servo_mismatch_ms", 2.0, "ms", True),
)
LIMITS: dict[str, Any] = {"enabled": True, "G_b_um": 25.0,
                          "parameters": {n: lim for n, lim, _u, _s in QUANTITIES if n != "G_b_um"}}
INTERVALS_MIN = (3.0, 15.0, 60.0, 480.0, 1440.0)
KINDS = ("constant", "noisy", "wearing")
START = datetime(2026, 1, 5, 6, 0, tzinfo=UTC)


@dataclass
class Machine:
    seed: int
    kind: str = "constant"
    tests: int = 60  # constant and noisy machines; a wearing one runs to 3 tests past its crossing
    interval_min: float | None = None  # None: drawn from INTERVALS_MIN


def _result(i: int, when: datetime, values: dict[str, tuple[float, float]]) -> dict[str, Any]:
    gb, gb_u = values["G_b_um"]
    return {
        "kind": "test", "machine_id": "survey", "test_id": f"survey-{i}", "t_wall": mon.time_text(when),
        "plan": {"plane": "XY", "radius_mm": 100.0, "feed_mm_min": 1000.0, "data_arc_deg": 360.0,
                 "directions": "both"},
        "timing": {"measured_feed_mm_min": 1000.0},
        "parameters": {n: {"value": v, "stderr": u, "unit": next(q[2] for q in QUANTITIES if q[0] == n)}
                       for n, (v, u) in values.items() if n != "G_b_um"},
        "iso230_4": {"G_b_um": gb},
        "residual_rms_um": gb_u / math.sqrt(2.0),  # the monitor's u(G) = sqrt(2) x residual RMS
    }


def run(m: Machine) -> dict[str, Any]:
    """One machine: every due forecast, the wearing quantity's first due forecast and its true crossing."""
    rng = np.random.default_rng([m.seed, KINDS.index(m.kind), 35])
    interval = m.interval_min if m.interval_min is not None else float(rng.choice(INTERVALS_MIN))
    settings = mon.settings_from_dict(LIMITS)
    monitor = Monitor(settings, "survey")
    base, scatter, stated = {}, {}, {}
    for name, lim, _u, signed in QUANTITIES:
        sign = float(rng.choice((-1.0, 1.0))) if signed else 1.0
        base[name] = sign * lim * float(rng.uniform(0.10, 0.75))
        scatter[name] = lim * float(rng.uniform(0.02, 0.06)) * (2.0 if m.kind == "noisy" else 1.0)
        stated[name] = scatter[name] * float(rng.uniform(0.3, 1.0))
    wear_name, rate = None, 0.0
    n_tests = m.tests
    if m.kind == "wearing":
        wear_name, lim, _u, signed = QUANTITIES[int(rng.integers(len(QUANTITIES)))]
        sign = float(rng.choice((-1.0, 1.0))) if signed else 1.0
        base[wear_name] = sign * lim * float(rng.uniform(0.2, 0.5))
        cross_test = int(rng.integers(25, 81))
        rate = (sign * lim - base[wear_name]) / (cross_test * interval)  # per minute: crosses after cross_test
    when = START
    true_crossing = None
    if wear_name is not None:
        lim = next(q[1] for q in QUANTITIES if q[0] == wear_name)
        true_crossing = START + timedelta(minutes=(math.copysign(lim, rate) - base[wear_name]) / rate)
    crossed_at: int | None = None
    false: list[dict[str, Any]] = []
    past: list[dict[str, Any]] = []
    failing_due: list[dict[str, Any]] = []
    first_due: dict[str, Any] | None = None
    alerts: list[str] = []
    i, after = -1, 0
    while True:
        i += 1
        if wear_name is None and i >= n_tests:
            break
        if true_crossing is not None and when >= true_crossing:
            after += 1
            if after > 3:
                break
        if i:
            when += timedelta(minutes=interval * float(rng.uniform(0.5, 1.5)))
        minutes = (when - START).total_seconds() / 60.0
        values = {}
        for name, _lim, _u, _s in QUANTITIES:
            true = base[name] + (rate * minutes if name == wear_name else 0.0)
            if m.kind == "noisy":
                e = float(rng.standard_t(3)) * scatter[name] / math.sqrt(3.0)  # unit variance x scatter
                if rng.uniform() < 0.05:
                    e += float(rng.choice((-4.0, 4.0))) * scatter[name]
            else:
                e = float(rng.normal(0.0, scatter[name]))
            values[name] = (true + e, stated[name])
        if true_crossing is not None and crossed_at is None and when >= true_crossing:
            crossed_at = i  # the first test after the true crossing
        result = _result(i, when, values)
        result["verdict"] = monitor.verdict(result)
        status = {e["name"]: e["status"] for e in result["verdict"]["limits"]}
        alerts += [a["message"] for a in monitor.on_test(result)]
        for f in monitor.last_forecasts:
            if not f["due"]:
                continue
            rec = {"test": i, "name": f["name"], "t_test": mon.time_text(when), "crossing": f.get("crossing"),
                   "crossing_lo": f.get("crossing_lo"), "slope_per_day": f.get("slope_per_day")}
            lo = f.get("crossing_lo")
            if lo is None or mon.parse_time(lo) < when - timedelta(seconds=1):
                past.append(rec)
            if status.get(f["name"]) == "fail":
                failing_due.append(rec)
            if f["name"] != wear_name:
                false.append(rec)
            elif first_due is None and true_crossing is not None and when < true_crossing:
                first_due = {**rec, "t": when}
    out: dict[str, Any] = {"seed": m.seed, "kind": m.kind, "interval_min": interval, "tests": i,
                           "false": false, "past": past, "failing_due": failing_due, "alerts": len(alerts)}
    if wear_name is not None and true_crossing is not None:
        out.update(wear=wear_name, cross_test=crossed_at, true_crossing=mon.time_text(true_crossing),
                   forecast=first_due is not None)
        if first_due is not None:
            out["lead_tests"] = (crossed_at or i) - first_due["test"]
            out["lead_days"] = (true_crossing - first_due.pop("t")).total_seconds() / 86400.0
            out["first_due"] = first_due
    return out


def survey(machines: Sequence[Machine], jobs: int) -> list[dict[str, Any]]:
    if jobs <= 1:
        return [run(m) for m in machines]
    with ProcessPoolExecutor(jobs) as ex:
        return list(ex.map(run, machines, chunksize=8))


def summarize(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for kind in KINDS:
        rs = [r for r in rows if r["kind"] == kind]
        if not rs:
            continue
        s: dict[str, Any] = {
            "machines": len(rs),
            "machines_with_false_forecast": sum(bool(r["false"]) for r in rs),
            "false_forecasts": sum(len(r["false"]) for r in rs),
            "due_with_crossing_in_the_past": sum(len(r["past"]) for r in rs),
            "due_while_failing": sum(len(r["failing_due"]) for r in rs),
        }
        s["false_forecast_rate"] = s["machines_with_false_forecast"] / len(rs)
        by_interval = {}
        for iv in sorted({r["interval_min"] for r in rs}):
            sub = [r for r in rs if r["interval_min"] == iv]
            entry: dict[str, Any] = {"machines": len(sub), "with_false": sum(bool(r["false"]) for r in sub)}
            if kind == "wearing":
                entry["missed"] = sum(not r["forecast"] for r in sub)
                leads = [r["lead_tests"] for r in sub if r["forecast"]]
                days = [r["lead_days"] for r in sub if r["forecast"]]
                entry["lead_tests_median"] = float(np.median(leads)) if leads else None
                entry["lead_tests_min"] = int(min(leads)) if leads else None
                entry["lead_days_median"] = float(np.median(days)) if days else None
            by_interval[f"{iv:g} min"] = entry
        s["by_interval"] = by_interval
        if kind == "wearing":
            s["missed"] = sum(not r["forecast"] for r in rs)
            leads = [r["lead_tests"] for r in rs if r["forecast"]]
            frac = [r["lead_tests"] / r["cross_test"] for r in rs if r["forecast"]]
            s["lead_tests_median"] = float(np.median(leads)) if leads else None
            s["lead_tests_min"] = int(min(leads)) if leads else None
            s["lead_fraction_of_run_median"] = float(np.median(frac)) if frac else None
            s["missed_examples"] = [{k: r[k] for k in ("seed", "wear", "interval_min", "cross_test")}
                                    for r in rs if not r["forecast"]][:10]
        s["false_examples"] = [{"seed": r["seed"], "interval_min": r["interval_min"], **r["false"][0]}
                               for r in rs if r["false"]][:10]
        out[kind] = s
    return out


def main(argv: Sequence[str] | None = None) -> int:
    doc = (__doc__ or "").split("\n\n")[0]
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.forecast_survey", description=doc)
    p.add_argument("--machines", type=int, default=500, help="constant machines (noisy and wearing: --others)")
    p.add_argument("--others", type=int, default=200, help="noisy machines, and as many wearing ones")
    p.add_argument("--tests", type=int, default=60, help="tests per constant or noisy machine")
    p.add_argument("--first-seed", type=int, default=1)
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--json", help="write every machine's outcome and the summary here")
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    t0 = time.monotonic()
    s0 = args.first_seed
    machines = ([Machine(s, "constant", args.tests) for s in range(s0, s0 + args.machines)]
                + [Machine(s, "noisy", args.tests) for s in range(s0, s0 + args.others)]
                + [Machine(s, "wearing") for s in range(s0, s0 + args.others)])
    rows = survey(machines, args.jobs)
    summary = summarize(rows)
    summary["settings"] = {**vars(args), "limits": LIMITS, "seconds": round(time.monotonic() - t0, 1)}
    print(json.dumps(summary, indent=2, default=str))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"summary": summary, "machines": rows}, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

__all__ = ["KINDS", "LIMITS", "QUANTITIES", "Machine", "main", "run", "summarize", "survey"]
