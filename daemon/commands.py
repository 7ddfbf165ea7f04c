"""The ``ballbar`` command's subcommands (the entry point is :mod:`.cli`): ``run`` the daemon, ``analyze`` a
recording, write the NC program (``gcode``) and a test ``report``.

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
import tomllib
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ballbar.analysis.errors import BallbarError, PlanError

if TYPE_CHECKING:
    from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan
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
    ("--pitch-x-mm", "pitch_x_mm", float, "ball-screw pitch of the plane's first axis (mm), for cyclic error"),
    ("--pitch-y-mm", "pitch_y_mm", float, "ball-screw pitch of the plane's second axis (mm)"),
    ("--kv-x", "kv_x_per_s", float, "configured position-loop gain of the first axis (1/s)"),
    ("--kv-y", "kv_y_per_s", float, "configured position-loop gain of the second axis (1/s)"),
    ("--controller", "controller", str, "generic, fanuc, siemens or heidenhain (names in the advice)"),
)
#: analysis.plan.STANDARDS, written out: the parser is built before anything slow is imported.
STANDARD_CHOICES = ("iso230_4", "jis_b6190_4", "asme_b5_54")


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

    gc = sub.add_parser("gcode", help="write the NC test program that matches the test plan",
                        description="Write the ball-bar test program (feed-in, CCW and CW arcs with overshoots, "
                        "feed-out, dwells) for a controller, with exactly the timing the analyzer assumes. "
                        "The plan comes from the daemon's configuration (--config, $BALLBAR_CONFIG, "
                        "/etc/ballbar/ballbar.toml), then --plan FILE, then the flags.")
    gc.add_argument("--dialect", required=True, choices=("fanuc", "siemens", "heidenhain", "linuxcnc"),
                    help="controller dialect (fanuc also suits compatible controls)")
    gc.add_argument("-o", "--output", help="write the program to this file (default: standard output)")
    gc.add_argument("--config", help="the daemon's TOML configuration, whose [plan] to use")
    gc.add_argument("--plan", dest="plan_arg", metavar="NAME|FILE",
                    help="a plan of the configuration's library, or a set (its programs into -o DIR), by name; or "
                    "a TOML or JSON file with [plan] (overrides --config)")
    for flag, dest, typ, help_ in PLAN_FLAGS:
        gc.add_argument(flag, dest=dest, type=typ, help=help_)
    gc.add_argument("--decimals", type=int, help="decimals of coordinates (default: 3 for fanuc, else 4)")
    gc.add_argument("--origin", help="pivot ball centre in work coordinates, X,Y,Z in mm (default 0,0,0)")
    gc.add_argument("--work-offset", help="work offset to select, e.g. G54 (default: none, the active one)")
    gc.add_argument("--program-name", help="program number or name (dialect rules apply)")
    gc.add_argument("--no-stop", action="store_true", help="no program stop to mount the bar at the start")
    gc.add_argument("--repeat", type=int, default=1, help="run the test this many times (default 1)")

    rp = sub.add_parser("report", help="write a test report (HTML with embedded plots, and PNGs)",
                        description="Write one self-contained HTML report of a test: polar plot of both "
                        "directions with the fitted model, ranked findings, ISO 230-4, advice and the "
                        "machine's trend. From a recording (CSV or MCAP), or from the daemon's records by "
                        "test id.")
    rp.add_argument("file", nargs="?", help="recording: CSV or the daemon's MCAP (file or directory)")
    rp.add_argument("--test-id", help="a test id from the daemon's records, or 'latest'")
    rp.add_argument("--records", help="directory of the daemon's MCAP records (default: <state_dir>/recordings "
                    "of the daemon's configuration); with FILE it supplies the trend")
    rp.add_argument("--config", help="the daemon's TOML configuration (for its state_dir)")
    rp.add_argument("-o", "--output", help="HTML file to write (default: ballbar-report-<test>.html)")
    rp.add_argument("--no-png", action="store_true", help="do not write the plots as PNG files beside the HTML")
    rp.add_argument("--plan", dest="plan_arg", metavar="FILE",
                    help="TOML or JSON file with [plan], [machine], [analysis] (default: the recorded plans)")
    for flags in (PLAN_FLAGS, MACHINE_FLAGS):
        for flag, dest, typ, help_ in flags:
            rp.add_argument(flag, dest=dest, type=typ, help=help_)
    rp.add_argument("--test", type=int, help="with FILE: which test of the recording (1 = first; for a directory of "
                    "the daemon's records the N-th that analyze --list shows, default its newest complete test)")
    for flag, dest, typ, help_ in REPORT_FLAGS:
        rp.add_argument(flag, dest=dest, type=typ, help=help_)
    rp.add_argument("--set", dest="set_name", metavar="NAME",
                    help="with a directory of the daemon's records: the report of the set NAME (its verdict first, "
                    "then each plan's test), made again from the latest recorded test of each of its plans")
    rp.add_argument("--standard", dest="standards", action="append", choices=STANDARD_CHOICES,
                    help="the circular-test standards the report states (repeatable; default: the configuration's "
                    "[analysis] standards, ISO 230-4 always)")

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

    from .config import ConfigError, library_of

    if own_plan(args):
        if getattr(args, "plan_name", None):
            raise UsageError(f"--plan {args.plan_name} names a plan of the library: plan flags cannot change it")
        return PlanLibrary.single(plan), None
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


def configs_from_args(
    args: argparse.Namespace, base: dict[str, Any] | None = None
) -> tuple[TestPlan, MachineConfig, AnalysisOptions]:
    """``base`` (default: the recorded configuration of an MCAP file), then --plan FILE, then the flags."""
    from ballbar.analysis.patterns import BY_NAME
    from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan

    from .recordings import recorded_config

    if base is None:
        base = recorded_config(args.file) if getattr(args, "file", None) else {}
    if getattr(args, "plan_file", None):
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
        machine = MachineConfig.from_dict(machine_d)
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
    from .config import load

    table: dict[str, Any] | None = None
    if getattr(args, "config", None):
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
    lines = [f"Verdict: {verdict['summary']}", f"  (k = {verdict['coverage_k']:g}; {verdict['rule']})"]
    for e in verdict["limits"]:
        if e["status"] == "not_evaluated":
            lines.append(f"  {e['name']:<28} not evaluated: {e.get('reason')}")
            continue
        note = " (within uncertainty of the limit)" if e["within_uncertainty"] else ""
        lines.append(f"  {e['name']:<28} {e['value']:10.4g} +- {e['uncertainty']:<8.2g} limit {e['limit']:<8g} "
                     f"margin {e['margin']:+.3g} {e['unit']}: {e['status']}{note}")
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
) -> tuple[TestPlan, MachineConfig, AnalysisOptions, PlanLibrary, str | None]:
    """The plan, machine and options (:func:`configs_from_args`) and the library with the plan chosen
    (:func:`library_from_args`) of a recording whose configuration is ``base``."""
    sections = library_sections(args, base)
    names = library_from_sections(sections).names if sections.get("plans") else ()
    resolve_plan_arg(args, names)
    plan, machine, options = configs_from_args(args, base=dict(base))
    library, chosen = library_from_args(args, sections, plan)
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
    if mcap:
        from .testindex import index_recordings

        index = index_recordings(args.file)
        rows = [index.describe(t) for t in index.tests]
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
        print(f"{args.file}: no test recorded")
    for r in rows:
        what = headline_text(r["headline"]) if r["headline"] else r["message"]
        if mcap:
            files = r["files"][0] + (f" +{len(r['files']) - 1}" if len(r["files"]) > 1 else "")
            of = f"  {r['plan']}" if r.get("plan") else ""
            print(f"{r['number']:>3}  {r['test_id']}  {r['start'] or '-'}  {files}{of}  {r['status']}  {what}")
        else:
            print(f"{r['number']:>3}  feed-in at t={r['feed_in_s']:.3f} s  {r['status']}  {what}")
    return 0


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


def cmd_gcode(args: argparse.Namespace) -> int:
    from .config import load, monitor_settings
    from .output import write_atomic

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
    from ballbar.tools.ncinterp import check_against_plan, interpret, model_limits, signatures

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
    from .output import write_atomic

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


def cmd_report(args: argparse.Namespace) -> int:
    from ballbar.analysis.plans import PlanLibrary
    from ballbar.tools.report import from_recording, from_records

    from .config import load

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
        from .testindex import index_recordings

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
    from .config import load

    if args.config:
        meta.update({k: v for k, v in asdict(load(args.config).report).items() if v not in (None, "")})
    meta.update({dest: getattr(args, dest) for _f, dest, _t, _h in REPORT_FLAGS if getattr(args, dest, None)
                 is not None})


def _report_set(args: argparse.Namespace) -> int:
    """``ballbar report DIR --set NAME``: the set's report (:mod:`ballbar.tools.report_set`)."""
    from .config import load

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


def run_command(argv: Sequence[str], stop: threading.Event) -> int:
    """Parse ``argv`` and run its subcommand; ``stop`` is the event :mod:`.cli`'s SIGTERM and SIGINT handlers set
    for ``run``."""
    from .cli import log_format

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
        format=log_format(),
        stream=sys.stderr,
    )
    from .config import ConfigError
    from .lock import StateLockError

    def run(a: argparse.Namespace) -> int:
        from .run import cmd_run

        return cmd_run(a, stop)

    handlers = {"analyze": cmd_analyze, "gcode": cmd_gcode, "report": cmd_report, "run": run}
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
