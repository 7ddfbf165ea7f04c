"""The ``ballbar`` command: ``analyze`` a recording offline (more subcommands join it).

Exit codes: 0 success; 1 the input could not be analysed (the one-line message
says what and where); 2 a usage or configuration error.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import tomllib
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.errors import BallbarError, DataError, PlanError
from ballbar.analysis.patterns import BY_NAME
from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan
from ballbar.analysis.report import summary

from .recordings import read_recording

log = logging.getLogger(__name__)

PLAN_FLAGS: tuple[tuple[str, str, type, str], ...] = (
    ("--radius-mm", "radius_mm", float, "bar length / circle radius R (mm)"),
    ("--feed-mm-min", "feed_mm_min", float, "programmed feed F (mm/min)"),
    ("--plane", "plane", str, "XY, YZ or ZX"),
    ("--start-deg", "start_deg", float, "start angle u0 (deg)"),
    ("--overshoot-deg", "overshoot_deg", float, "overshoot o before and after the data arc (deg)"),
    ("--data-arc-deg", "data_arc_deg", float, "data arc a (deg): 360, or e.g. 220 in vertical planes"),
    ("--feed-in-mm", "feed_in_mm", float, "feed-in distance f (mm)"),
    ("--dwell-s", "dwell_s", float, "dwell at each stop (s)"),
    ("--sample-hz", "sample_hz", float, "nominal sample rate (Hz); the timestamps rule"),
    ("--directions", "directions", str, "both, ccw or cw"),
)
MACHINE_FLAGS: tuple[tuple[str, str, type, str], ...] = (
    ("--pitch-x-mm", "pitch_x_mm", float, "ball-screw pitch of the plane's first axis (mm), for cyclic error"),
    ("--pitch-y-mm", "pitch_y_mm", float, "ball-screw pitch of the plane's second axis (mm)"),
    ("--kv-x", "kv_x_per_s", float, "configured position-loop gain of the first axis (1/s)"),
    ("--kv-y", "kv_y_per_s", float, "configured position-loop gain of the second axis (1/s)"),
    ("--controller", "controller", str, "generic, fanuc, siemens or heidenhain (names in the advice)"),
)


class UsageError(BallbarError, ValueError):
    """A command-line or configuration mistake: exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message}")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="ballbar", description="Ball-bar contouring monitor")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (repeatable)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    an = sub.add_parser("analyze", help="analyse a recording (CSV t_s,length_mm)",
                        description="Analyse a ball-bar recording: ranked findings, ISO 230-4, advice.")
    an.add_argument("file", help="recording: CSV with header t_s,length_mm, or the daemon's MCAP "
                    "(a file or a directory; its recorded plan is the default)")
    an.add_argument("--plan", dest="plan_file", help="TOML or JSON file with [plan], [machine], [analysis]")
    for flags in (PLAN_FLAGS, MACHINE_FLAGS):
        for flag, dest, typ, help_ in flags:
            an.add_argument(flag, dest=dest, type=typ, help=help_)
    an.add_argument("--significance", type=float, help="F-test level (default 0.05)")
    an.add_argument("--servo-model", choices=("auto", "linear", "physical"), help="servo mismatch model")
    an.add_argument("--lost-motion", choices=("deadband", "step"),
                    help="backlash as a dead band with take-up (default) or the seed's step")
    an.add_argument("--patterns", help="comma-separated pattern names to fit (default: all that apply)")
    an.add_argument("--test", type=int, default=1, help="which test of the recording (1 = first)")
    an.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")

    run = sub.add_parser("run", help="run the daemon (the service's main job)",
                         description="Sample the ball-bar, fit each circle and test, log to MCAP, publish on "
                         "Zenoh, stream to Rerun. Configuration: see daemon/default.toml.")
    run.add_argument("--config", help="TOML configuration file (default: $BALLBAR_CONFIG, /etc/ballbar/ballbar.toml)")
    run.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                     help="override one configuration key (value in TOML syntax); repeatable")
    run.add_argument("--simulate", action="store_true",
                     help="run against the built-in simulated ball-bar on a pty (state in ./ballbar-state)")
    run.add_argument("--speedup", type=float, default=5.0, help="with --simulate: device time per wall time")
    run.add_argument("--machine-id", help="daemon.machine_id")
    run.add_argument("--state-dir", help="daemon.state_dir")
    run.add_argument("--source", help="source.url")
    run.add_argument("--tests", type=int, help="exit after this many test results")
    run.add_argument("--duration-s", type=float, help="exit after this many seconds")
    run.add_argument("--print-config", action="store_true", help="print the effective configuration and exit")
    return parser


def load_config_file(path: str) -> dict[str, Any]:
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise UsageError(f"{path}: cannot read: {err.strerror or err}") from err
    try:
        data = json.loads(text) if p.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as err:
        raise UsageError(f"{path}: not valid {'JSON' if p.suffix.lower() == '.json' else 'TOML'}: {err}") from err
    unknown = sorted(set(data) - {"plan", "machine", "analysis"})
    if unknown:
        raise UsageError(f"{path}: unknown section {unknown[0]!r} (known: plan, machine, analysis)")
    return data


def recorded_config(path: str) -> dict[str, Any]:
    """The plan, machine and analysis a daemon recording was made with (empty for CSV)."""
    if not (path.lower().endswith(".mcap") or os.path.isdir(path)):
        return {}
    from .mcap_log import list_recordings, read_log, read_logs

    try:
        configs = (read_logs(list_recordings(path)) if os.path.isdir(path) else read_log(path)).config
    except BallbarError:
        return {}  # read_recording reports what is wrong with the file
    if not configs:
        return {}
    cfg = configs[-1].get("config", {})
    return {k: dict(cfg[k]) for k in ("plan", "machine", "analysis") if isinstance(cfg.get(k), dict)}


def configs_from_args(args: argparse.Namespace) -> tuple[TestPlan, MachineConfig, AnalysisOptions]:
    """Recorded configuration (MCAP), then --plan FILE, then the flags."""
    base: dict[str, Any] = recorded_config(args.file) if getattr(args, "file", None) else {}
    if args.plan_file:
        for key, value in load_config_file(args.plan_file).items():
            base.setdefault(key, {}).update(value)
    plan_d = dict(base.get("plan", {}))
    machine_d = dict(base.get("machine", {}))
    analysis_d = dict(base.get("analysis", {}))
    for flags, target in ((PLAN_FLAGS, plan_d), (MACHINE_FLAGS, machine_d)):
        for _flag, dest, _t, _h in flags:
            v = getattr(args, dest, None)
            if v is not None:
                target[dest] = v
    if getattr(args, "significance", None) is not None:
        analysis_d["significance"] = args.significance
    if getattr(args, "servo_model", None) is not None:
        analysis_d["servo_model"] = args.servo_model
    if getattr(args, "lost_motion", None) is not None:
        analysis_d["lost_motion"] = args.lost_motion
    if getattr(args, "patterns", None):
        names = tuple(n.strip() for n in args.patterns.split(",") if n.strip())
        bad = [n for n in names if n not in BY_NAME]
        if bad:
            raise UsageError(f"unknown pattern {bad[0]!r} (known: {', '.join(BY_NAME)})")
        analysis_d["patterns"] = names
    for key, value in (("plan", plan_d), ("machine", machine_d)):
        for k, v in value.items():
            if isinstance(v, float) and not math.isfinite(v):
                raise UsageError(f"{key} value {k} must be finite, not {v}")
    try:
        plan = TestPlan.from_dict(plan_d)
        machine = MachineConfig.from_dict(machine_d)
        if "patterns" in analysis_d and isinstance(analysis_d["patterns"], list):
            analysis_d["patterns"] = tuple(analysis_d["patterns"])
        options = _options_from_dict(analysis_d)
    except PlanError as err:
        raise UsageError(str(err)) from err
    return plan, machine, options


def _options_from_dict(d: dict[str, Any]) -> AnalysisOptions:
    from dataclasses import fields

    known = {f.name for f in fields(AnalysisOptions)}
    unknown = sorted(set(d) - known)
    if unknown:
        raise PlanError(f"unknown analysis key {unknown[0]!r} (known: {', '.join(sorted(known))})")
    return AnalysisOptions(**d)


def cmd_analyze(args: argparse.Namespace) -> int:
    plan, machine, options = configs_from_args(args)
    t, L = read_recording(args.file)
    results = analyze_recording(t, L, plan, machine, options)
    tests = [r for r in results if r["kind"] == "test"]
    problems = [r for r in results if r.get("event") in ("test_rejected", "test_incomplete")]
    if args.test < 1:
        raise UsageError("--test counts from 1")
    if len(tests) < args.test:
        if problems:
            raise DataError(f"{args.file}: {problems[0]['message']}")
        raise DataError(f"{args.file}: holds {len(tests)} complete test(s), --test {args.test} asked for")
    result = tests[args.test - 1]
    result["source"] = {"file": os.path.abspath(args.file), "tests_found": len(tests)}
    if abs(result["samples"]["sample_hz"] / plan.sample_hz - 1.0) > 0.2:
        result.setdefault("warnings", []).append(
            f"the recording samples at {result['samples']['sample_hz']:.3f} Hz, the plan says "
            f"{plan.sample_hz:g} Hz; the timestamps were used"
        )
    if args.json:
        json.dump(result, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print(summary(result))
        for w in result.get("warnings", []):
            print(f"warning: {w}")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except UsageError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from .run import cmd_run

    handlers = {"analyze": cmd_analyze, "run": cmd_run}
    from .config import ConfigError

    try:
        return handlers[args.command](args)
    except (UsageError, ConfigError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except BallbarError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    except MemoryError:
        print("error: the recording does not fit in memory", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
