"""``ballbar report``: a test's result as a report an engineer can file.

This module gathers what a report shows (:class:`ReportData`): the test's
result, its polar curves (the samples of both data arcs and the fitted model),
and the machine's earlier results under the same test conditions, from a
recording (CSV or the daemon's MCAP) or from the daemon's records by test id.
:mod:`.report_render` turns that into one self-contained HTML file and PNGs.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ballbar.analysis.errors import DataError
from ballbar.analysis.plan import AnalysisOptions, MachineAxes, MachineConfig, TestPlan, machine_of
from ballbar.analysis.plans import PlanLibrary
from ballbar.daemon.mcap import mcap_files, read_results
from ballbar.daemon.recordings import analyze_file
from ballbar.daemon.testindex import RecordedTest, TestIndex

log = logging.getLogger(__name__)


@dataclass
class ReportData:
    """Everything a report shows.

    ``result``: the test result as ``ballbar analyze --json`` prints it (and the
    daemon publishes it), with ``machine_id``, ``test_id`` and ``t_wall`` where
    the daemon's records give them.  ``curves``: per direction (``"ccw"``,
    ``"cw"``) the data arc's samples as arrays ``t_s``, ``u_deg``,
    ``measured_um`` and ``model_um`` (see
    :func:`ballbar.analysis.engine.analyze_test`).  ``history``: the same
    machine's earlier test results under the same conditions (plane, radius,
    feed, data arc, directions), oldest first, each with ``t_wall`` and ``test_id``; empty
    when there are none.  ``history_note``: how the history was chosen (for the
    report's text).  ``source``: what the report was made from.  ``meta``: who
    tested, with which bar, at what temperatures, notes and the sign-off roles
    (the ``[report]`` configuration's keys: ``operator``, ``bar_serial``,
    ``bar_calibrated``, ``machine_temperature_c``, ``air_temperature_c``,
    ``notes``, ``sign_off``), from the daemon's recorded configuration and the
    command line.
    """

    result: dict[str, Any]
    curves: dict[str, dict[str, np.ndarray]]
    history: list[dict[str, Any]] = field(default_factory=list)
    history_note: str = ""
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)


# Test conditions that must match for an earlier result to be comparable in the trend.
COMPARABLE_PLAN_KEYS = ("plane", "radius_mm", "feed_mm_min", "data_arc_deg", "directions")
MATCH_FEED_IN_S = 1.0  # a re-analysed test is the recorded one when their feed-ins are this close


def comparable(a: dict[str, Any], b: dict[str, Any]) -> bool:
    """Whether two results were measured under the same test conditions (plan keys above)."""
    pa, pb = a.get("plan", {}), b.get("plan", {})
    return all(pa.get(k) == pb.get(k) for k in COMPARABLE_PLAN_KEYS)


def _published_order(r: dict[str, Any]) -> tuple[str, float]:
    """When a result was published: its wall time, then (within a millisecond: the same daemon) its last
    sample's host time."""
    host = r.get("last_sample_t_host")
    return str(r["t_wall"]), float(host) if isinstance(host, int | float) else 0.0


def select_history(result: dict[str, Any], candidates: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], str]:
    """The same machine's earlier comparable test results, oldest first, and a sentence saying how they were chosen.

    ``candidates``: published results (any kind, any machine).  A result without
    ``t_wall`` cannot be placed in time and is left out.
    """
    machine = result.get("machine_id")
    t_wall = result.get("t_wall")
    tests = [r for r in candidates if r.get("kind") == "test" and r.get("t_wall")
             and r.get("test_id") != result.get("test_id")]
    if machine is not None:
        tests = [r for r in tests if r.get("machine_id") == machine]
    # Its own published record places it among results published within the same millisecond (a replay
    # at full speed publishes several in one batch), by the host time of the samples that ended each test.
    me = next((r for r in candidates if r.get("kind") == "test" and r.get("t_wall")
               and r.get("test_id") == result.get("test_id")), None)
    if me is not None:
        tests = [r for r in tests if _published_order(r) < _published_order(me)]
    elif t_wall:
        tests = [r for r in tests if str(r["t_wall"]) < str(t_wall)]
    same = [r for r in tests if comparable(result, r)]
    same.sort(key=_published_order)
    what = f"machine {machine}" if machine is not None else "this machine"
    cond = ", ".join(f"{k} {result.get('plan', {}).get(k)}" for k in COMPARABLE_PLAN_KEYS)
    if not tests:
        note = f"no earlier test results of {what} in the records"
    else:
        left = len(tests) - len(same)
        note = (f"{len(same)} earlier test result(s) of {what} under the same conditions ({cond})"
                + (f"; {left} under other conditions left out" if left else ""))
    return same, note


OPEN_FILE_S = 60.0  # a record file modified this recently is taken as being written by a live daemon


class _OpenFileNote(logging.Filter):
    """The reader's 'writer was probably killed' for a file a live daemon is still writing (modified within
    ``OPEN_FILE_S``): its open chunk is not there yet, nothing is wrong; said at INFO, not as a warning."""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if record.levelno == logging.WARNING and msg.endswith("the writer was probably killed"):
            path = msg.split(": ", 1)[0]
            with contextlib.suppress(OSError):
                if time.time() - os.stat(path).st_mtime < OPEN_FILE_S:
                    log.info("%s: still being written; read up to its last whole chunk", path)
                    return False
        return True


def _read_results(files: list[Path]) -> list[dict[str, Any]]:
    """:func:`~ballbar.daemon.mcap.read_results`, a file a live daemon is writing noted as such."""
    reader_log = logging.getLogger("ballbar.daemon.mcap")
    note = _OpenFileNote()
    reader_log.addFilter(note)
    try:
        return read_results(files)
    finally:
        reader_log.removeFilter(note)


def _mcap_files(path: str) -> list[Path]:
    if os.path.isdir(path):
        return mcap_files(path)
    return [Path(path)] if path.lower().endswith(".mcap") else []


def _same_test(a: dict[str, Any], b: dict[str, Any]) -> bool:
    fa, fb = a.get("timing", {}).get("feed_in_s"), b.get("timing", {}).get("feed_in_s")
    return fa is not None and fb is not None and abs(fa - fb) < MATCH_FEED_IN_S


def _adopt_identity(result: dict[str, Any], recorded: dict[str, Any]) -> None:
    for key in ("machine_id", "test_id", "t_wall"):
        if key in recorded:
            result[key] = recorded[key]


def from_recording(
    path: str,
    plan: TestPlan,
    machine: MachineConfig | MachineAxes,
    options: AnalysisOptions,
    test: int = 1,
    records: str | None = None,
    library: PlanLibrary | None = None,
) -> ReportData:
    """Analyse a recording (CSV, or the daemon's MCAP file or directory) and gather its ``test``-th test
    (``library``: the plans its tests may run; None: the recorded ones, else ``plan`` alone).

    A daemon recording names the test (machine, test id, time) through the
    result it published for the same feed-in.  The trend comes from the results
    in the recording itself and, with ``records``, in that directory of the
    daemon's records.
    """
    result: dict[str, Any] = dict(analyze_file(path, plan, machine, options, test, curves=True,  # the report's
                                               library=library))
    curves = result.pop("curves")
    candidates = _read_results(_mcap_files(path))
    recorded = [r for r in candidates if r.get("kind") == "test" and _same_test(result, r)]
    if recorded:
        _adopt_identity(result, recorded[-1])
    if records is not None:
        candidates += _read_results(_records_files(records))
    history, note = select_history(result, _unique(candidates))
    attach_verdict(result, recorded_limits(path))
    return ReportData(result, curves, history, note, source=os.path.abspath(path), meta=recorded_meta(path))


def recorded_meta(path: str) -> dict[str, Any]:
    """The ``[report]`` table a daemon recording was made with (empty for a CSV or a recording without it)."""
    from ballbar.daemon.recordings import recorded_config

    table = recorded_config(path).get("report")
    return {k: v for k, v in table.items() if v not in (None, "")} if isinstance(table, dict) else {}


def recorded_limits(path: str) -> dict[str, Any] | None:
    """The ``[limits]`` a daemon recording was made with (None for a CSV or a recording without them)."""
    from ballbar.daemon.recordings import recorded_config

    table = recorded_config(path).get("limits")
    return dict(table) if isinstance(table, dict) else None


def attach_verdict(result: dict[str, Any], limits: dict[str, Any] | None) -> None:
    """The verdict against ``limits`` (a ``[limits]`` table) into ``result``, as the daemon gives it live;
    nothing when the limits are off.  The report's verdict box draws it."""
    from ballbar.analysis import monitor

    if not limits or not limits.get("enabled"):
        return
    result["verdict"] = monitor.evaluate(result, monitor.settings_from_dict(limits))
    why = monitor.validity(result)
    if why is not None:
        result["verdict"]["trend_excluded"] = why


def _records_files(records: str) -> list[Path]:
    from ballbar.daemon.mcap import list_recordings

    if not os.path.isdir(records):
        raise DataError(f"{records}: no such directory of daemon records")
    files = list_recordings(records)
    if not files:
        raise DataError(f"{records}: holds no ballbar recordings (<machine>_<UTC time>_<n>.mcap)")
    return files


def _unique(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    seen: set[tuple[Any, Any, Any]] = set()
    out = []
    for r in results:
        key = (r.get("test_id"), r.get("kind"), r.get("direction"))
        if key[0] is not None and key in seen:
            continue
        seen.add(key)
        out.append(r)
    return out


def from_records(records: str, test_id: str, options: AnalysisOptions | None = None) -> ReportData:
    """Gather the test ``test_id`` (or ``"latest"``: the newest complete test) from a directory of the daemon's records.

    The test is found and analysed again exactly as ``ballbar analyze DIR
    --test-id`` does (:mod:`ballbar.daemon.testindex`): from its own files'
    samples, with the configuration its daemon run recorded (the same code
    path as live, so it equals the published result) to draw the curves;
    ``options`` replaces the recorded analysis options when given.
    """
    from ballbar.daemon.testindex import index_recordings

    _records_files(records)
    index = index_recordings(records)
    if not any(t.status == "complete" for t in index.tests) and test_id == "latest":
        raise DataError(f"{records}: the records hold no test result yet")
    test = index.select(test_id)
    cfg = index.config_for(test)
    plan = TestPlan.from_dict(cfg.get("plan", {}))
    machine = machine_of(cfg.get("machine", {}))
    opts = options or AnalysisOptions.from_dict(cfg.get("analysis", {}))
    return from_recorded_test(index, test, plan, machine, opts)


def from_recorded_test(
    index: TestIndex,
    test: RecordedTest,
    plan: TestPlan,
    machine: MachineConfig | MachineAxes,
    options: AnalysisOptions,
    records: str | None = None,
    library: PlanLibrary | None = None,
) -> ReportData:
    """Gather one test of an index of the daemon's records (:func:`~ballbar.daemon.testindex.analyze_recorded`;
    ``library``: as there).

    It takes the published result's identity, says where the re-analysis
    differs from it, and draws the trend from the index's results (and those in
    ``records``, a further directory of records, when given).
    """
    from ballbar.daemon.testindex import analyze_recorded

    result: dict[str, Any] = dict(analyze_recorded(index, test, plan, machine, options, curves=True, library=library))
    curves = result.pop("curves")
    published = test.result or {}
    _adopt_identity(result, published)
    result.setdefault("test_id", test.test_id)
    if test.machine_id is not None:
        result.setdefault("machine_id", test.machine_id)
    result["source"] = {"records": os.path.abspath(index.path), "file": result["source"]["file"],
                        "reanalysed": "from the recorded samples with the recorded configuration"}
    drift = published_difference(result, published) if published else None
    if drift is not None:
        result.setdefault("warnings", []).append(drift)
    candidates = index.results()
    if records is not None and os.path.abspath(records) != os.path.abspath(index.path):
        candidates += _read_results(_records_files(records))
    history, note = select_history(result, _unique(candidates))
    limits = index.config_for(test).get("limits")
    attach_verdict(result, dict(limits) if isinstance(limits, dict) else None)
    meta = index.config_for(test).get("report")
    meta = {k: v for k, v in meta.items() if v not in (None, "")} if isinstance(meta, dict) else {}
    return ReportData(result, curves, history, note, source=f"{os.path.abspath(index.path)} test {result['test_id']}",
                      meta=meta)


def published_difference(result: dict[str, Any], published: dict[str, Any], rel: float = 1e-6) -> str | None:
    """Why the re-analysed ``result`` differs from the one the daemon published, or None if it does not.

    They differ when the options were overridden, or when this version of the
    analysis differs from the daemon's that recorded the test.
    """
    worst: tuple[float, str, float, float] | None = None
    for key, p in result.get("parameters", {}).items():
        a, b = p.get("value"), published.get("parameters", {}).get(key, {}).get("value")
        if (a is None) != (b is None):
            return f"{key} was {'not ' if b is None else ''}fitted when published, is {'not ' if a is None else ''}now"
        if a is None or b is None:
            continue
        # Immaterial: a part in 10^6, a hundredth of the standard error, or 1e-4 of the unit (um, ms, urad, ppm).
        allowed = max(rel * abs(b), 0.01 * (p.get("stderr") or 0.0), 1e-4)
        d = abs(a - b) / allowed
        if d > 1 and (worst is None or d > worst[0]):
            worst = (d, key, a, b)
    if worst is None:
        return None
    _, key, a, b = worst
    return f"re-analysed {key} = {a:.4g} differs from the published {b:.4g}: the analysis or its options changed"
