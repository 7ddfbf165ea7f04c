"""The physical simulator's command line (``ballbar-sim``): a plan and a machine from arguments, the simulated
test written as CSV with its truth as JSON.  The simulator itself is :mod:`ballbar.tools.simulator`.

Command line::

    python -m ballbar.tools.simulator_cli --out test.csv --truth truth.json \\
        --radius-mm 100 --feed-mm-min 1000 --sample-hz 1000 --set backlash_x_um=5
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from collections.abc import Sequence
from dataclasses import fields
from typing import Any

import numpy as np

from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import TestPlan

from .simulator import MachineModel, iter_tests, truth_of

log = logging.getLogger(__name__)


def parse_set(items: Sequence[str]) -> dict[str, Any]:
    """``["backlash_x_um=5", "kv_x_per_s=inf"]`` -> machine keys; unknown keys are errors."""
    types = {f.name: f.type for f in fields(MachineModel)}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep:
            raise PlanError(f"--set needs KEY=VALUE, not {item!r}")
        if key not in types:
            raise PlanError(f"unknown machine key {key!r} (known: {', '.join(sorted(types))})")
        text = text.strip()
        try:
            if key == "drop_indices":
                out[key] = tuple(int(v) for v in text.split(",") if v.strip())
            elif key == "jitter_stamped":
                if text.lower() not in ("1", "0", "true", "false", "yes", "no"):
                    raise ValueError(text)
                out[key] = text.lower() in ("1", "true", "yes")
            else:
                out[key] = float(text)
        except ValueError as err:
            raise PlanError(f"machine key {key!r}: bad value {text!r}") from err
    return out


def write_csv(path: str, t_s: np.ndarray, length_mm: np.ndarray, *, append: bool = False) -> None:
    """CSV ``t_s,length_mm`` with nanosecond / nanometre digits."""
    with open(path, "a" if append else "w", encoding="ascii", newline="\n") as fh:
        if not append:
            fh.write("t_s,length_mm\n")
        step = 100_000
        for i in range(0, t_s.size, step):
            block = np.column_stack([t_s[i : i + step], length_mm[i : i + step]])
            np.savetxt(fh, block, fmt="%.9f", delimiter=",")


def add_plan_arguments(p: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The test plan's options (all but the sample rate) and ``--set`` for the machine model."""
    d = TestPlan()
    p.add_argument("--radius-mm", type=float, default=d.radius_mm)
    p.add_argument("--feed-mm-min", type=float, default=d.feed_mm_min)
    p.add_argument("--plane", default=d.plane, choices=["XY", "YZ", "ZX"])
    p.add_argument("--start-deg", type=float, default=d.start_deg)
    p.add_argument("--overshoot-deg", type=float, default=d.overshoot_deg)
    p.add_argument("--data-arc-deg", type=float, default=d.data_arc_deg)
    p.add_argument("--feed-in-mm", type=float, default=d.feed_in_mm)
    p.add_argument("--dwell-s", type=float, default=d.dwell_s)
    p.add_argument("--directions", default=d.directions, choices=["both", "ccw", "cw"])
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="machine model parameter, e.g. backlash_x_um=5 or kv_x_per_s=inf (repeatable)",
    )


def plan_from_args(args: argparse.Namespace, sample_hz: float) -> TestPlan:
    """The plan that :func:`add_plan_arguments`' options describe."""
    return TestPlan(
        plane=args.plane,
        radius_mm=args.radius_mm,
        feed_mm_min=args.feed_mm_min,
        start_deg=args.start_deg,
        overshoot_deg=args.overshoot_deg,
        data_arc_deg=args.data_arc_deg,
        feed_in_mm=args.feed_in_mm,
        dwell_s=args.dwell_s,
        directions=args.directions,
        sample_hz=sample_hz,
    )


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m ballbar.tools.simulator_cli",
        description="Simulate ball-bar tests on a physical machine model and write t_s,length_mm CSV.",
    )
    p.add_argument("--out", required=True, help="CSV file to write (t_s,length_mm)")
    p.add_argument("--truth", help="JSON file for the expected results, events and model")
    add_plan_arguments(p)
    p.add_argument("--sample-hz", type=float, default=TestPlan().sample_hz)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeat", type=int, default=1, help="tests in a row on one sample clock")
    p.add_argument("--gap-s", type=float, default=0.0, help="extra wait between repeated tests")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    try:
        plan = plan_from_args(args, args.sample_hz)
        machine = MachineModel(**parse_set(args.set))
        if args.repeat < 1:
            raise PlanError(f"--repeat must be >= 1, not {args.repeat}")
        tests = []
        for i, res in enumerate(iter_tests(plan, machine, args.sample_hz, args.seed, args.repeat, args.gap_s)):
            write_csv(args.out, res.t_s, res.length_mm, append=i > 0)
            tests.append({"index": res.index, "events": res.events})
            log.info("test %d: %d samples, %.3f..%.3f s", i, res.t_s.size, res.t_s[0], res.t_s[-1])
    except PlanError as err:
        log.error("%s", err)
        return 2
    except OSError as err:
        log.error("cannot write: %s", err)
        return 1
    if args.truth:
        doc = {
            "truth": truth_of(plan, machine),
            "tests": tests,
            "plan": plan.to_dict(),
            "machine": machine.to_dict(),
            "sample_hz": args.sample_hz,
            "seed": args.seed,
        }
        try:
            with open(args.truth, "w", encoding="utf-8") as fh:
                json.dump(doc, fh, indent=2, allow_nan=False)
                fh.write("\n")
        except OSError as err:
            log.error("cannot write: %s", err)
            return 1
    return 0


__all__ = ["add_plan_arguments", "main", "parse_set", "plan_from_args", "write_csv"]

if __name__ == "__main__":
    sys.exit(main())
