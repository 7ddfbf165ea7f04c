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
from collections.abc import Mapping, Sequence
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


#: A machine key's unit, by the ending of its name (the project's naming rule: the unit is the key's last part).
UNIT_ENDINGS = (("_um_per_min", "um/min"), ("_mm_s2", "mm/s^2"), ("_mm_s3", "mm/s^3"), ("_mm_s", "mm/s"),
                ("_per_s", "1/s"), ("_urad", "urad"), ("_ppm", "ppm"), ("_deg", "deg"), ("_um", "um"),
                ("_mm", "mm"), ("_hz", "Hz"), ("_s", "s"))


def key_unit(key: str) -> str:
    """The unit of machine key ``key`` from its name (``""``: a plain number, a flag or a list)."""
    return next((unit for ending, unit in UNIT_ENDINGS if key.endswith(ending)), "")


def keys_table(defaults: Mapping[str, Any], width: int = 100) -> str:
    """``key (unit) = default`` for each of ``defaults``, sorted, in columns of at most ``width`` characters."""
    cells = []
    for key in sorted(defaults):
        value = defaults[key]
        text = ",".join(map(str, value)) if isinstance(value, tuple) else f"{value:g}" if isinstance(
            value, float) else str(value).lower()
        unit = key_unit(key)
        cells.append(f"{key} = {text or '(none)'}" + (f" {unit}" if unit else ""))
    col = max(len(c) for c in cells) + 2
    per_line = max(1, width // col)
    rows = [cells[i:i + per_line] for i in range(0, len(cells), per_line)]
    return "\n".join("  " + "".join(c.ljust(col) for c in row).rstrip() for row in rows)


def machine_keys_help() -> str:
    """The machine keys ``--set`` (and ``--drift``) take, with their defaults and units, from the models' own
    fields: the plane's (:class:`MachineModel`) and, with ``--library``, the 3D machine's."""
    import textwrap

    from .machine3d import AXIS_KEYS, PLANE_ONLY, SQUARENESS_KEYS

    model = MachineModel()
    plane = {f.name: getattr(model, f.name) for f in fields(MachineModel)}
    axis = ", ".join(k.format("{x,y,z}") for k in AXIS_KEYS)
    three_d = textwrap.fill(
        f"with --library, the 3D machine's: the axis keys {axis} (the machine's X, Y, Z; defaults and units as "
        f"above), {', '.join(SQUARENESS_KEYS.values())} (urad, 0), and the keys above that belong to no plane "
        f"(not {', '.join(PLANE_ONLY)})", 100)
    return ("machine keys of --set and --drift, each with its default (x, y: the plane's first and second axis):\n"
            f"{keys_table(plane)}\n\n{three_d}")


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
        epilog=machine_keys_help().split("\n\n")[0].replace("--set and --drift", "--set"),
        formatter_class=argparse.RawDescriptionHelpFormatter,
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
