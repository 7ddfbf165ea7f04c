"""The operator's subcommands of ``ballbar`` that live in the tools: ``gcode`` (the NC test program, checked by
the interpreter before it is written) and ``report`` (a test's HTML report).  They plug into the command as
:class:`~ballbar.daemon.commands.Command` entry points (``pyproject.toml``; :mod:`ballbar.daemon.plugins`), and
this module imports what each needs only when it runs.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import sys
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ballbar.analysis.errors import BallbarError
from ballbar.daemon.commands import (
    MACHINE_FLAGS,
    PLAN_FLAGS,
    STANDARD_CHOICES,
    Command,
    UsageError,
    configs_from_args,
    own_plan,
    resolve_plan_arg,
)

if TYPE_CHECKING:
    from ballbar.analysis.plan import TestPlan

log = logging.getLogger(__name__)


def _gcode_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dialect", required=True, choices=("fanuc", "siemens", "heidenhain", "linuxcnc"),
                   help="controller dialect (fanuc also suits compatible controls)")
    p.add_argument("-o", "--output", help="write the program to this file (default: standard output)")
    p.add_argument("--config", help="the daemon's TOML configuration, whose [plan] to use")
    p.add_argument("--plan", dest="plan_arg", metavar="NAME|FILE",
                   help="a plan of the configuration's library, or a set (its programs into -o DIR), by name; or "
                   "a TOML or JSON file with [plan] (overrides --config)")
    for flag, dest, typ, help_ in PLAN_FLAGS:
        p.add_argument(flag, dest=dest, type=typ, help=help_)
    p.add_argument("--decimals", type=int, help="decimals of coordinates (default: 3 for fanuc, else 4)")
    p.add_argument("--origin", help="pivot ball centre in work coordinates, X,Y,Z in mm (default 0,0,0)")
    p.add_argument("--work-offset", help="work offset to select, e.g. G54 (default: none, the active one)")
    p.add_argument("--program-name", help="program number or name (dialect rules apply)")
    p.add_argument("--no-stop", action="store_true", help="no program stop to mount the bar at the start")
    p.add_argument("--repeat", type=int, default=1, help="run the test this many times (default 1)")


def _report_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", nargs="?", help="recording: CSV or the daemon's MCAP (file or directory)")
    p.add_argument("--test-id", help="a test id from the daemon's records, or 'latest'")
    p.add_argument("--records", help="directory of the daemon's MCAP records (default: <state_dir>/recordings "
                   "of the daemon's configuration); with FILE it supplies the trend")
    p.add_argument("--config", help="the daemon's TOML configuration (for its state_dir)")
    p.add_argument("-o", "--output", help="HTML file to write (default: ballbar-report-<test>.html)")
    p.add_argument("--no-png", action="store_true", help="do not write the plots as PNG files beside the HTML")
    p.add_argument("--plan", dest="plan_arg", metavar="FILE",
                   help="TOML or JSON file with [plan], [machine], [analysis] (default: the recorded plans)")
    for flags in (PLAN_FLAGS, MACHINE_FLAGS):
        for flag, dest, typ, help_ in flags:
            p.add_argument(flag, dest=dest, type=typ, help=help_)
    p.add_argument("--test", type=int, help="with FILE: which test of the recording (1 = first; for a directory of "
                   "the daemon's records the N-th that analyze --list shows, default its newest complete test)")
    for flag, dest, typ, help_ in REPORT_FLAGS:
        p.add_argument(flag, dest=dest, type=typ, help=help_)
    p.add_argument("--set", dest="set_name", metavar="NAME",
                   help="with a directory of the daemon's records: the report of the set NAME (its verdict first, "
                   "then each plan's test), made again from the latest recorded test of each of its plans")
    p.add_argument("--standard", dest="standards", action="append", choices=STANDARD_CHOICES,
                   help="the circular-test standards the report states (repeatable; default: the configuration's "
                   "[analysis] standards, ISO 230-4 always)")


def _origin(text: str | None) -> tuple[float, float, float]:
    if text is None:
        return (0.0, 0.0, 0.0)
    try:
        xyz = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"--origin must be X,Y,Z in mm, not {text!r}") from None
    if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
        raise UsageError(f"--origin must be three finite numbers X,Y,Z in mm, not {text!r}")
    return (xyz[0], xyz[1], xyz[2])


PROGRAM_SUFFIX = {"fanuc": ".nc", "siemens": ".mpf", "heidenhain": ".h", "linuxcnc": ".ngc"}


def _gcode(args: argparse.Namespace) -> int:
    from ballbar.daemon.config import load, monitor_settings
    from ballbar.daemon.output import write_atomic

    cfg = load(args.config)
    library = cfg.library
    names = (*library.names, *cfg.sets) if cfg.plans else ()
    resolve_plan_arg(args, names)
    if args.repeat < 1:
        raise UsageError("--repeat must be at least 1")
    chosen: list[str] = []
    if args.plan_name is not None:
        chosen = list(cfg.sets[args.plan_name].plans) if args.plan_name in cfg.sets else [args.plan_name]
        if own_plan(args):
            raise UsageError(f"--plan {args.plan_name} names a plan of the configuration: plan flags would change its "
                             f"program, not its plan; change [plans.{chosen[0]}] instead")
    elif len(library) > 1 and not own_plan(args):
        sets = f"; sets: {', '.join(cfg.sets)}" if cfg.sets else ""
        raise UsageError(f"the configuration holds {len(library)} plans ({', '.join(library.names)}{sets}): "
                         "choose one with --plan NAME")
    if not chosen:  # one plan: the configuration's only one, or one of its own (a file, flags)
        plan, _machine, _options = configs_from_args(args, base={"plan": cfg.plan.to_dict()})
        text = _program(args, plan, None, None, args.program_name)
        _write_program(args, text, plan)
        _say_limits(monitor_settings(cfg))
        return 0
    many = args.plan_name in cfg.sets
    if many and args.output is None:
        raise UsageError(f"--plan {args.plan_name} is a set of {len(chosen)} plans: give -o DIR for its programs")
    out_dir = Path(args.output) if many else None
    if out_dir is not None:
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise UsageError(f"-o {args.output}: cannot make the directory: {err.strerror or err}") from err
    number = _program_number(args)
    for k, name in enumerate(chosen):
        p = library.get(name)
        signature = p.signature if len(library) > 1 else None
        program_name = (name if args.dialect == "heidenhain" else str(number + k) if number is not None
                        else args.program_name)
        text = _program(args, p.plan, signature, name, program_name)
        if out_dir is None:
            _write_program(args, text, p.plan, name)
        else:
            path = out_dir / f"{name}{PROGRAM_SUFFIX[args.dialect]}"
            write_atomic(str(path), text.encode("utf-8"))
            print(f"wrote {path}: {args.dialect} program of plan {name}, plane {p.plan.plane}, R "
                  f"{p.plan.radius_mm:g} mm, F {p.plan.feed_mm_min:g} mm/min"
                  + (f", signature {signature}" if signature is not None else ""), file=sys.stderr)
        _say_limits(monitor_settings(cfg, name), name)
    return 0


def _program_number(args: argparse.Namespace) -> int | None:
    """FANUC: the O-number of a set's first program (the next ones count on); else None."""
    if args.dialect != "fanuc":
        return None
    text = (args.program_name or "O2304").strip().lstrip("Oo")
    return int(text) if text.isdigit() else None


def _program(args: argparse.Namespace, plan: TestPlan, signature: int | None, name: str | None,
             program_name: str | None) -> str:
    """One plan's program, read back by the interpreter: it must run the plan (where the plan is inside the
    timing model) and carry its signature."""
    from ballbar.analysis.plans import SIGNATURE_STEP, signature_code
    from ballbar.tools.gcode import generate
    from ballbar.tools.nccheck import check_against_plan, model_limits, signatures
    from ballbar.tools.ncinterp import interpret

    origin = _origin(args.origin)
    text = generate(plan, args.dialect, decimals=args.decimals, origin=origin, work_offset=args.work_offset,
                    program_name=program_name, mount_stop=not args.no_stop, repeat=args.repeat, signature=signature,
                    plan_name=name)
    # Where the plan itself leaves the analyzer's timing model (an overshoot too short to reach the feed), no
    # program can match it: say so and write the program; otherwise a mismatch is the generator's bug.
    limits = model_limits(plan)
    for why in limits:
        log.warning("the plan%s is outside the analyzer's timing model: %s", f" {name}" if name else "", why)
    problems = check_against_plan(text, args.dialect, plan, origin=origin)
    if problems and not limits:
        raise BallbarError(f"the {args.dialect} program does not run the plan: {problems[0]}")
    if signature is not None:
        step = SIGNATURE_STEP * plan.feed_in_mm
        found = signatures(interpret(text, args.dialect), plan.plane, origin=origin)
        if len(found) != args.repeat:
            raise BallbarError(f"the {args.dialect} program of plan {name} holds {len(found)} tests, not {args.repeat}")
        for depths in found:
            if signature_code([round(d / step) for d in depths]) != signature:
                raise BallbarError(f"the {args.dialect} program of plan {name} does not carry its signature "
                                   f"{signature}: it reads {[round(d, 4) for d in depths]} mm")
    return text


def _write_program(args: argparse.Namespace, text: str, plan: TestPlan, name: str | None = None) -> None:
    from ballbar.daemon.output import write_atomic

    if args.output is None:
        sys.stdout.write(text)
        return
    write_atomic(args.output, text.encode("utf-8"))
    print(f"wrote {args.output}: {args.dialect} program" + (f" of plan {name}" if name else "")
          + f", plane {plan.plane}, R {plan.radius_mm:g} mm, F {plan.feed_mm_min:g} mm/min", file=sys.stderr)


def _say_limits(settings: Any, name: str | None = None) -> None:
    if settings.enabled:  # what the daemon will hold this test to
        which = f"plan {name}'s" if name else "this test's"
        print(f"limits that apply to {which} results ([limits], k = {settings.coverage_k:g}):", file=sys.stderr)
        for line in settings.describe():
            print(f"  {line}", file=sys.stderr)


REPORT_FLAGS: list[tuple[str, str, Any, str]] = [  # the report's [report] keys, from the command line
    ("--operator", "operator", str, "who ran the test (default: [report] operator)"),
    ("--bar-serial", "bar_serial", str, "the ball-bar's serial number"),
    ("--bar-calibrated", "bar_calibrated", str, "the bar's last calibration date"),
    ("--machine-temp", "machine_temperature_c", float, "machine temperature at the test, deg C"),
    ("--air-temp", "air_temperature_c", float, "air temperature at the test, deg C"),
    ("--notes", "notes", str, "notes printed in the report"),
    ("--sign-off", "sign_off", lambda s: [r.strip() for r in s.split(",") if r.strip()],
     "signature lines, comma-separated roles (default: Tested by, Approved by)"),
]


def _report(args: argparse.Namespace) -> int:
    from ballbar.analysis.plans import PlanLibrary
    from ballbar.daemon.config import load
    from ballbar.tools.report import from_recording, from_records

    if args.test is not None and args.test < 1:
        raise UsageError("--test counts from 1")
    if args.set_name is not None:
        return _report_set(args)
    if (args.file is None) == (args.test_id is None):
        raise UsageError("give a recording FILE or --test-id (one of the two)")
    resolve_plan_arg(args, ())  # a file: the report of a library's test takes the recorded library
    records = args.records
    index = None
    if args.file is not None and os.path.isdir(args.file):
        from ballbar.daemon.testindex import index_recordings

        index = index_recordings(args.file)
    if index is not None and index.tests:
        # a directory of the daemon's records: its newest complete test (or the N-th listed), as analyze DIR
        from ballbar.tools.report import from_recorded_test

        test = index.select(None, args.test)
        plan, machine, options = configs_from_args(args, base=index.config_for(test))
        data = from_recorded_test(index, test, plan, machine, options, records=records,
                                  library=PlanLibrary.single(plan) if own_plan(args) else None)
        default_name = test.test_id
    elif args.file is not None:
        plan, machine, options = configs_from_args(args)
        data = from_recording(args.file, plan, machine, options, args.test or 1, records=records,
                              library=PlanLibrary.single(plan) if own_plan(args) else None)
        default_name = Path(args.file.rstrip("/")).stem
    else:
        if records is None:
            records = os.path.join(load(args.config).daemon.state_dir, "recordings")
        data = from_records(records, args.test_id)
        default_name = str(data.result.get("test_id", "test"))
    if args.config and args.file is not None:  # the daemon's configuration file: its [limits] give the verdict
        from ballbar.tools.report import attach_verdict

        attach_verdict(data.result, asdict(load(args.config).limits))
    _report_meta(data.meta, args)
    from ballbar.tools.report_render import render  # matplotlib: only once there is something to draw

    out = Path(args.output or f"ballbar-report-{_safe_name(default_name)}.html")
    for path in render(data, out, png=not args.no_png):
        print(path)
    return 0


def _report_meta(meta: dict[str, Any], args: argparse.Namespace) -> None:
    """Who tested, with which bar, ...: the configuration's [report] over the recorded one, the flags over both."""
    from ballbar.daemon.config import load

    if args.config:
        meta.update({k: v for k, v in asdict(load(args.config).report).items() if v not in (None, "")})
    meta.update({dest: getattr(args, dest) for _f, dest, _t, _h in REPORT_FLAGS if getattr(args, dest, None)
                 is not None})


def _report_set(args: argparse.Namespace) -> int:
    """``ballbar report DIR --set NAME``: the set's report (:mod:`ballbar.tools.report_set`)."""
    from ballbar.daemon.config import load

    records = args.file or args.records or (os.path.join(load(args.config).daemon.state_dir, "recordings")
                                            if args.config else None)
    if records is None or not os.path.isdir(records):
        raise UsageError("--set makes the report of a set from a directory of the daemon's MCAP records: give it "
                         "(DIR, --records DIR or --config FILE)")
    from ballbar.tools.report_set import from_set_records, render_set

    data = from_set_records(records, args.set_name)
    _report_meta(data.meta, args)
    out = Path(args.output or f"ballbar-set-report-{_safe_name(args.set_name)}.html")
    for path in render_set(data, out, png=not args.no_png):
        print(path)
    return 0


def _safe_name(text: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in text)[:100] or "test"


GCODE = Command(
    name="gcode",
    help="write the NC test program that matches the test plan",
    description="Write the ball-bar test program (feed-in, CCW and CW arcs with overshoots, feed-out, dwells) for "
    "a controller, with exactly the timing the analyzer assumes. The plan comes from the daemon's configuration "
    "(--config, $BALLBAR_CONFIG, /etc/ballbar/ballbar.toml), then --plan FILE, then the flags.",
    add_arguments=_gcode_arguments,
    run=_gcode,
)
REPORT = Command(
    name="report",
    help="write a test report (HTML with embedded plots, and PNGs)",
    description="Write one self-contained HTML report of a test: polar plot of both directions with the fitted "
    "model, ranked findings, ISO 230-4, advice and the machine's trend. From a recording (CSV or MCAP), or from "
    "the daemon's records by test id.",
    add_arguments=_report_arguments,
    run=_report,
)
