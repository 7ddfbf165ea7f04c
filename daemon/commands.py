"""The ``ballbar`` command's subcommands (the entry point is :mod:`.cli`): ``run`` the daemon and ``analyze`` a
recording here; the others (``gcode``: the NC program, ``report``: a test report) are the operator tools',
plugged in as :class:`Command` entry points (:mod:`.plugins`) and loaded only when asked for.

Exit codes: 0 success; 1 the input could not be analysed (the one-line message
says what and where); 2 a usage or configuration error.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import math
import os
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ballbar.analysis.errors import BallbarError, PlanError

from .plugins import SIM_MACHINES

if TYPE_CHECKING:
    from ballbar.analysis.plan import AnalysisOptions, MachineAxes, MachineConfig, TestPlan
    from ballbar.analysis.plans import PlanLibrary
    from ballbar.protocol.messages import Analysis, Verdict

# numpy, scipy, the analysis, MCAP and the bus come in with the command that needs them (``ballbar analyze`` of
# a CSV imports no MCAP, Zenoh or Rerun; ``ballbar run`` has its SIGTERM handler from :mod:`.cli` already).

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
    # the machine's axes: each plan takes its plane's two (XY: X, Y; YZ: Y, Z; ZX: Z, X)
    ("--pitch-x-mm", "pitch_x_mm", float, "ball-screw pitch of the machine's X axis (mm), for cyclic error"),
    ("--pitch-y-mm", "pitch_y_mm", float, "ball-screw pitch of the Y axis (mm)"),
    ("--pitch-z-mm", "pitch_z_mm", float, "ball-screw pitch of the Z axis (mm)"),
    ("--kv-x", "kv_x_per_s", float, "configured position-loop gain of the machine's X axis (1/s)"),
    ("--kv-y", "kv_y_per_s", float, "configured position-loop gain of the Y axis (1/s)"),
    ("--kv-z", "kv_z_per_s", float, "configured position-loop gain of the Z axis (1/s)"),
    ("--controller", "controller", str, "generic, fanuc, siemens or heidenhain (names in the advice)"),
)
#: analysis.plan.STANDARDS, written out: the parser is built before anything slow is imported.
STANDARD_CHOICES = ("iso230_4", "jis_b6190_4", "asme_b5_54")


class UsageError(BallbarError, ValueError):
    """A command-line or configuration mistake: exit code 2."""


@dataclass(frozen=True)
class Command:
    """A subcommand that plugs into ``ballbar`` (entry point group ``ballbar.commands``, :mod:`.plugins`).

    ``add_arguments`` declares its options on its subparser; ``run`` does it and returns the exit code, raising
    :class:`UsageError` (exit 2) or another :class:`~ballbar.analysis.errors.BallbarError` (exit 1) for one line
    on standard error.
    """

    name: str
    help: str
    description: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


BUILT_IN = ("analyze", "run")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        raise UsageError(f"{self.prog}: {message}")


def plugged_in(only: str | None = None) -> list[Command]:
    """The subcommands plugged in (``only``: that one, if it is one; a built-in name: none)."""
    from . import plugins

    if only in BUILT_IN:
        return []
    wanted = plugins.names(plugins.COMMANDS)
    if only in wanted:
        wanted = [only]
    out = []
    for name in wanted:
        cmd = plugins.load(plugins.COMMANDS, name)
        if not isinstance(cmd, Command) or cmd.name != name:
            raise UsageError(f"the plug-in {name!r} is not a ballbar command")
        out.append(cmd)
    return out


def build_parser(commands: Sequence[Command] | None = None) -> argparse.ArgumentParser:
    """The ``ballbar`` command's parser: the built-in subcommands, then ``commands`` (default: every one plugged
    in, in name order; :func:`plugged_in`)."""
    parser = _Parser(prog="ballbar", description="Ball-bar contouring monitor")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (repeatable)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    an = sub.add_parser("analyze", help="analyse a recording (CSV t_s,length_mm)",
                        description="Analyse a ball-bar recording: ranked findings, ISO 230-4, advice.")
    an.add_argument("file", help="recording: CSV with header t_s,length_mm, or the daemon's MCAP "
                    "(a file, or a directory of them: its newest complete test; its recorded plan is the default)")
    an.add_argument("--plan", dest="plan_arg", metavar="NAME|FILE",
                    help="a plan of the library (the recording's, or --config's [plans.*]) by name: every test "
                    "analysed as it; or a TOML or JSON file with [plan], [machine], [analysis]")
    for flags in (PLAN_FLAGS, MACHINE_FLAGS):
        for flag, dest, typ, help_ in flags:
            an.add_argument(flag, dest=dest, type=typ, help=help_)
    an.add_argument("--significance", type=float, help="F-test level (default 0.05)")
    an.add_argument("--servo-model", choices=("auto", "linear", "physical"), help="servo mismatch model")
    an.add_argument("--lost-motion", choices=("physical", "deadband", "step"),
                    help="per axis a dead band or over-set compensation through the loop (physical, default), "
                    "or the seed's step")
    an.add_argument("--patterns", help="comma-separated pattern names to fit (default: all that apply)")
    an.add_argument("--standard", dest="standards", action="append", choices=STANDARD_CHOICES,
                    help="also the circular-test figures of this standard (repeatable; ISO 230-4's always; default: "
                    "the configuration's [analysis] standards)")
    an.add_argument("--test", type=int, help="which test: the N-th in a file (default 1), the N-th that "
                    "--list shows for a directory")
    an.add_argument("--test-id", help="a test id from the daemon's records (MCAP file or directory), or 'latest' "
                    "(the newest complete test: a directory's default)")
    an.add_argument("--set", dest="set_name", metavar="NAME",
                    help="the daemon's records: make the set NAME again ([sets.NAME] as recorded) from the latest "
                    "recorded test of each of its plans, each analysed again from its samples")
    an.add_argument("--list", action="store_true", help="list the tests (number, id, start, status, file, "
                    "headline) instead of analysing one; with --json a JSON list")
    an.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")
    an.add_argument("--config", help="the daemon's TOML configuration: its [limits] give the verdict (default: "
                    "the --plan file's [limits], else those the recording was made with)")

    run = sub.add_parser("run", help="run the daemon (the service's main job)",
                         description="Sample the ball-bar, fit each circle and test, log to MCAP, publish on "
                         "Zenoh, stream to Rerun. Configuration: see daemon/default.toml.")
    run.add_argument("--config", help="TOML configuration file (default: $BALLBAR_CONFIG, /etc/ballbar/ballbar.toml)")
    run.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                     help="override one configuration key (value in TOML syntax); repeatable")
    run.add_argument("--simulate", nargs="?", const="passing", choices=SIM_MACHINES, metavar="MACHINE",
                     help="run against the built-in simulated ball-bar on a pty: a machine that is passing (the "
                     "default), failing (backlash and servo mismatch over their limits) or wearing (its X backlash "
                     "and servo mismatch grow test by test); state in ./ballbar-state, not daemon.state_dir "
                     "(--state-dir to choose); with no limits configured, the simulated machine's (logged)")
    run.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                     help="with --simulate: one key of the simulated machine over the named machine's, e.g. "
                     "backlash_y_um=9 (ballbar-simdevice --help lists them); repeatable")
    run.add_argument("--sim-drift", action="append", default=[], metavar="KEY=STEP",
                     help="with --simulate: a machine key that changes by STEP from one test to the next (wear); "
                     "repeatable")
    run.add_argument("--speedup", type=float, default=5.0, help="with --simulate: device time per wall time")
    run.add_argument("--simulate-cnc", action="store_true",
                     help="with --simulate: the simulated CNC (OPC UA, ballbar-simcnc) beside it, read as [controller] "
                          "(needs ballbar[controller])")
    run.add_argument("--machine-id", help="daemon.machine_id")
    run.add_argument("--state-dir", help="daemon.state_dir")
    run.add_argument("--source", help="source.url")
    run.add_argument("--tests", type=int, help="exit after this many test results")
    run.add_argument("--duration-s", type=float, help="exit after this many seconds")
    run.add_argument("--print-config", action="store_true", help="print the effective configuration and exit")
    for cmd in plugged_in() if commands is None else commands:
        sp = sub.add_parser(cmd.name, help=cmd.help, description=cmd.description)
        cmd.add_arguments(sp)
    return parser


def load_config_file(path: str) -> dict[str, Any]:
    import tomllib  # here: a command without a file to read needs none of it

    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as err:
        raise UsageError(f"{path}: cannot read: {err.strerror or err}") from err
    try:
        data = json.loads(text) if p.suffix.lower() == ".json" else tomllib.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as err:
        raise UsageError(f"{path}: not valid {'JSON' if p.suffix.lower() == '.json' else 'TOML'}: {err}") from err
    unknown = sorted(set(data) - {"plan", "machine", "analysis", "limits"})
    if unknown:
        raise UsageError(f"{path}: unknown section {unknown[0]!r} (known: plan, machine, analysis, limits)")
    return data


def resolve_plan_arg(args: argparse.Namespace, names: Sequence[str]) -> None:
    """``--plan NAME|FILE``: ``args.plan_name`` where it names a plan (or set) of ``names``, else
    ``args.plan_file``; a value that is neither a name nor a file, with names to choose from, is a usage error."""
    value = getattr(args, "plan_arg", None)
    args.plan_name, args.plan_file = None, None
    if value is None:
        return
    if value in names:
        args.plan_name = value
    elif names and not os.path.exists(value):
        raise UsageError(f"--plan {value}: no plan of that name ({', '.join(names)}) and no such file")
    else:
        args.plan_file = value


def own_plan(args: argparse.Namespace) -> bool:
    """A plan given by ``--plan FILE`` or plan flags: the library of the configuration is set aside."""
    return bool(getattr(args, "plan_file", None)) or any(
        getattr(args, dest, None) is not None for _f, dest, _t, _h in PLAN_FLAGS)


def library_from_args(
    args: argparse.Namespace, sections: dict[str, Any], plan: TestPlan,
) -> tuple[PlanLibrary, str | None]:
    """The plans a recording's tests may run (``sections``' ``plans``: the recorded or --config's), and the one
    ``--plan NAME`` chose.  A plan of one's own (``--plan FILE``, plan flags) is a library of that plan alone."""
    from ballbar.analysis.plans import PlanLibrary

    if own_plan(args):
        if getattr(args, "plan_name", None):
            raise UsageError(f"--plan {args.plan_name} names a plan of the library: plan flags cannot change it")
        return PlanLibrary.single(plan), None
    if not sections.get("plans"):  # no library: this plan alone (without loading the configuration's machinery)
        return PlanLibrary.single(plan), None
    from .config import ConfigError, library_of

    try:
        library = library_of(sections)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    if library is None:
        return PlanLibrary.single(plan), None
    return library, getattr(args, "plan_name", None)


def library_sections(args: argparse.Namespace, base: dict[str, Any]) -> dict[str, Any]:
    """Where the library comes from: ``--config``'s ``[plans.*]`` where it has some, else ``base`` (the
    recorded configuration)."""
    if getattr(args, "config", None):
        from .config import load

        cfg = load(args.config, env={})
        if cfg.plans:
            return cfg.to_dict()
    return base


def machine_given(args: argparse.Namespace) -> dict[str, Any]:
    """The machine's keys that ``--plan FILE``'s ``[machine]`` and the flags give (the machine's axes)."""
    given = dict(load_config_file(args.plan_file).get("machine", {})) if getattr(args, "plan_file", None) else {}
    return given | {dest: getattr(args, dest) for _f, dest, _t, _h in MACHINE_FLAGS
                    if getattr(args, dest, None) is not None}


def configs_from_args(
    args: argparse.Namespace, base: dict[str, Any] | None = None
) -> tuple[TestPlan, MachineAxes | MachineConfig, AnalysisOptions]:
    """``base`` (default: the recorded configuration of an MCAP file), then --plan FILE, then the flags.

    The machine: its axes (:class:`~ballbar.analysis.plan.MachineAxes`); or, where a configuration recorded
    before the axes were named is neither changed by a file nor by a flag, its one plane's (every plan's first
    and second axis, as the daemon analysed it then)."""
    from ballbar.analysis.patterns import BY_NAME
    from ballbar.analysis.plan import AnalysisOptions, MachineAxes, MachineConfig, TestPlan, machine_of

    from .recordings import recorded_config

    if base is None:
        base = recorded_config(args.file) if getattr(args, "file", None) else {}
    plan_d = dict(base.get("plan", {}))
    machine_d = dict(base.get("machine", {}))
    given = machine_given(args)
    if given:
        try:
            recorded = machine_of(machine_d)
            if isinstance(recorded, MachineConfig):  # recorded as a plane's: named by the machine's axes
                machine_d = dict(MachineAxes.of_plane(TestPlan.from_dict(plan_d).plane, recorded).to_dict())
        except PlanError as err:
            raise UsageError(str(err)) from err
    if getattr(args, "plan_file", None):
        for key, value in load_config_file(args.plan_file).items():
            base.setdefault(key, {}).update(value)
        plan_d = dict(base.get("plan", {}))
    machine_d |= given
    analysis_d = dict(base.get("analysis", {}))
    for _flag, dest, _t, _h in PLAN_FLAGS:
        v = getattr(args, dest, None)
        if v is not None:
            plan_d[dest] = v
    if getattr(args, "significance", None) is not None:
        analysis_d["significance"] = args.significance
    if getattr(args, "servo_model", None) is not None:
        analysis_d["servo_model"] = args.servo_model
    if getattr(args, "lost_motion", None) is not None:
        analysis_d["lost_motion"] = args.lost_motion
    if getattr(args, "standards", None):
        analysis_d["standards"] = tuple(dict.fromkeys(("iso230_4", *args.standards)))
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
        machine = MachineAxes.from_dict(machine_d) if given else machine_of(machine_d)
        options = AnalysisOptions.from_dict(analysis_d)
    except PlanError as err:
        raise UsageError(str(err)) from err
    return plan, machine, options


def cmd_analyze(args: argparse.Namespace) -> int:
    from .recordings import analyze_file, is_mcap

    if args.test is not None and args.test < 1:
        raise UsageError("--test counts from 1")
    if args.test is not None and args.test_id is not None:
        raise UsageError("give --test N or --test-id ID, not both")
    mcap = is_mcap(args.file)
    if args.test_id is not None and not mcap:
        raise UsageError(f"--test-id picks a test from the daemon's MCAP records; {args.file} is not one")
    if args.list:
        return _list_tests(args, mcap)
    if args.set_name is not None:
        return _analyze_set(args, mcap)
    base: dict[str, Any] = {}
    result: Analysis
    if mcap and (os.path.isdir(args.file) or args.test_id is not None):
        result = _analyze_records(args, base)
    else:
        from .recordings import recorded_config

        base = recorded_config(args.file)
        plan, machine, options, library, chosen = _configs_and_library(args, base)
        result = analyze_file(args.file, plan, machine, options, args.test or 1, library=library, chosen=chosen)
    limits = limits_table(args, base, result.get("plan", {}).get("name"))
    if limits is not None:
        result["verdict"] = verdict_of(result, limits)
    if args.json:
        json.dump(result, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        from ballbar.analysis.report import summary
        from ballbar.analysis.standards import lines as standards_lines

        src = result.get("source", {})
        if src.get("test_id"):
            print(f"Test {src['test_id']} ({Path(src['file']).name})")
        print(summary(result))
        for line in standards_lines(result):
            print(line)
        for w in result.get("warnings", []):
            print(f"warning: {w}")
        if "verdict" in result:
            print(verdict_lines(result["verdict"]))
    return 0


def _analyze_set(args: argparse.Namespace, mcap: bool) -> int:
    """``--set NAME``: the set made again from the daemon's records (:mod:`.setrecords`)."""
    from ballbar.analysis.sets import summary_lines

    from .setrecords import set_from_records

    if not (mcap and os.path.isdir(args.file)):
        raise UsageError(f"--set makes a set from a directory of the daemon's MCAP records; {args.file} is not one")
    result = set_from_records(args.file, args.set_name)
    if args.json:
        json.dump(result, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
    else:
        print("\n".join(summary_lines(result)))
    return 0


def limits_table(args: argparse.Namespace, base: dict[str, Any], plan: str | None = None) -> dict[str, Any] | None:
    """The ``[limits]`` that give an offline verdict: ``--config``'s, else ``--plan``'s, else the recorded ones
    (of plan ``plan``, where it has its own); None when none of them turns limits on."""
    table: dict[str, Any] | None = None
    if getattr(args, "config", None):
        from .config import load

        table = asdict(load(args.config, env={}).limits_of(plan or ""))
    elif getattr(args, "plan_file", None) and "limits" in load_config_file(args.plan_file):
        table = dict(load_config_file(args.plan_file)["limits"])
    else:
        own = (base.get("plans") or {}).get(plan or "", {}).get("limits")
        if isinstance(own, dict):
            table = dict(own)
        elif isinstance(base.get("limits"), dict):
            table = dict(base["limits"])
    return table if table and table.get("enabled") else None


def verdict_of(result: Mapping[str, Any], table: dict[str, Any]) -> Verdict:
    """The verdict of a result against a ``[limits]`` table, as the daemon gives it live."""
    from ballbar.analysis import monitor

    try:
        settings = monitor.settings_from_dict(table)
    except PlanError as err:
        raise UsageError(str(err)) from err
    verdict = monitor.evaluate(result, settings)
    why = monitor.validity(result)
    if why is not None:
        verdict["trend_excluded"] = why
    return verdict


def verdict_lines(verdict: Mapping[str, Any]) -> str:
    from ballbar.analysis.numbers import limit_texts, measured

    lines = [f"Verdict: {verdict['summary']}", f"  (k = {verdict['coverage_k']:g}; {verdict['rule']})"]
    for e in verdict["limits"]:
        if e["status"] == "not_evaluated":
            lines.append(f"  {e['name']:<28} not evaluated: {e.get('reason')}")
            continue
        note = " (within uncertainty of the limit)" if e["within_uncertainty"] else ""
        value = measured(e["value"], e.get("stderr"), e["unit"], shown=e["uncertainty"], ascii=True)
        lim, margin = limit_texts(e["value"], e.get("stderr"), e["limit"], e["margin"], e["unit"])
        lines.append(f"  {e['name']:<28} {value:>22} limit {lim:<8} "
                     f"margin {'-' if e['margin'] < 0 else '+'}{margin} {e['unit']}: {e['status']}{note}")
    return "\n".join(lines)


def _analyze_records(args: argparse.Namespace, base: dict[str, Any]) -> Analysis:
    """A test from the daemon's records: a directory's newest complete one, or the one asked for.

    ``base`` receives the recorded configuration used (its ``limits`` give the verdict)."""
    from .mcap import read_logs, recording
    from .recordings import analyze, config_sections, pick_test
    from .testindex import analyze_recorded, index_recordings

    index = index_recordings(args.file)
    if index.tests or args.test_id is not None:
        test = index.select(args.test_id, args.test)
        base.update(index.config_for(test))
        plan, machine, options, library, chosen = _configs_and_library(args, base)
        return analyze_recorded(index, test, plan, machine, options, library=library, chosen=chosen)
    # Files without test records (the daemon's analysis off, or not the daemon's): the newest run's samples.
    run = index.runs()[-1]
    log.info("%s: no test recorded; analysing the samples of its newest daemon run (%d file(s))", args.file, len(run))
    files = [index.files[i] for i in run]
    base.update(next((config_sections(f.config) for f in reversed(files) if f.config), {}))
    plan, machine, options, library, chosen = _configs_and_library(args, base)
    rec = recording(read_logs([f.path for f in files], skip_bad=True, status=False), args.file)
    return pick_test(analyze(rec, plan, machine, options, only=args.test or 1, library=library, chosen=chosen),
                     args.test or 1, args.file, plan)


def _configs_and_library(
    args: argparse.Namespace, base: dict[str, Any],
) -> tuple[TestPlan, MachineAxes | MachineConfig, AnalysisOptions, PlanLibrary, str | None]:
    """The plan, machine and options (:func:`configs_from_args`) and the library with the plan chosen
    (:func:`library_from_args`) of a recording whose configuration is ``base``."""
    sections = library_sections(args, base)
    names = library_from_sections(sections).names if sections.get("plans") else ()
    resolve_plan_arg(args, names)
    plan, machine, options = configs_from_args(args, base=dict(base))
    library, chosen = library_from_args(args, sections, plan)
    given = {k: v for k, v in machine_given(args).items() if k != "controller"}
    if given:  # written now: X or Y keys alone for an axis no plan moves were a plan's first and second axis
        from ballbar.analysis.plan import MachineAxes, check_axes

        try:
            check_axes(MachineAxes.from_dict(given), [p.plan.plane for p in library.plans])
        except PlanError as err:
            raise UsageError(str(err)) from err
    return plan, machine, options, library, chosen


def library_from_sections(sections: dict[str, Any]) -> PlanLibrary:
    from .config import ConfigError, library_of

    try:
        library = library_of(sections)
    except ConfigError as err:
        raise UsageError(str(err)) from err
    assert library is not None
    return library


def _list_tests(args: argparse.Namespace, mcap: bool) -> int:
    """``--list``: the recorded tests of the daemon's MCAP records, or the tests an analysis finds in a CSV."""
    from ballbar.analysis.report import headline, headline_text

    from .recordings import analyze, load_recording, outcomes

    rows: list[dict[str, Any]]
    why = ""
    if mcap:
        from .testindex import index_recordings

        index = index_recordings(args.file)
        rows = [index.describe(t) for t in index.tests]
        if not rows and len(index.problems) == 1:
            why = f" (it {next(iter(index.problems.values()))})"
    else:
        plan, machine, options, library, chosen = _configs_and_library(args, {})
        rows = [
            {"number": e["number"], "feed_in_s": e["feed_in_s"], "status": e["status"], "message": e["message"],
             "headline": headline(e["result"]) if e["result"] is not None else None}
            for e in outcomes(analyze(load_recording(args.file), plan, machine, options, library=library,
                                      chosen=chosen))
        ]
    if args.json:
        json.dump(rows, sys.stdout, allow_nan=False)
        sys.stdout.write("\n")
        return 0
    if not rows:
        print(f"{args.file}: no test recorded{why}")
    for r in rows:
        what = headline_text(r["headline"]) if r["headline"] else r["message"]
        if r.get("reportable") is False and r["headline"]:  # a result recorded, but not its samples
            what = f"{what}; {r['message']}"
        if mcap:
            files = r["files"][0] + (f" +{len(r['files']) - 1}" if len(r["files"]) > 1 else "")
            of = f"  {r['plan']}" if r.get("plan") else ""
            print(f"{r['number']:>3}  {r['test_id']}  {r['start'] or '-'}  {files}{of}  {r['status']}  {what}")
        else:
            print(f"{r['number']:>3}  feed-in at t={r['feed_in_s']:.3f} s  {r['status']}  {what}")
    return 0


def log_format(env: dict[str, str] | None = None) -> str:
    """Log lines with a local timestamp (milliseconds), except under systemd, whose journal stamps its own."""
    env = dict(os.environ) if env is None else env
    plain = "%(levelname)s %(name)s: %(message)s"
    return plain if env.get("JOURNAL_STREAM") else "%(asctime)s " + plain


def run_command(argv: Sequence[str], stop: threading.Event, asked: str | None = None) -> int:
    """Parse ``argv`` and run its subcommand; ``stop`` is the event :mod:`.cli`'s SIGTERM and SIGINT handlers set
    for ``run``.  ``asked``: the subcommand :mod:`.cli` found in ``argv``, whose plug-in alone is then imported
    (None: every one plugged in)."""
    from .plugins import PluginError

    try:
        commands = plugged_in(asked)  # only the one asked for is imported
        parser = build_parser(commands)
        args = parser.parse_args(argv)
    except (UsageError, PluginError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except SystemExit as exc:  # --help
        return int(exc.code or 0)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format=log_format(),
        stream=sys.stderr,
    )
    from .errors import ConfigError
    from .lock import StateLockError

    def run(a: argparse.Namespace) -> int:
        from .run import cmd_run

        return cmd_run(a, stop)

    handlers = {"analyze": cmd_analyze, "run": run, **{c.name: c.run for c in commands}}
    try:
        return handlers[args.command](args)
    except (UsageError, ConfigError, StateLockError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except BallbarError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    except MemoryError:
        print("error: the recording does not fit in memory", file=sys.stderr)
        return 1
    except BrokenPipeError:  # the reader of our output went away (ballbar analyze ... | head): nothing to say
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except KeyboardInterrupt:
        return 130
