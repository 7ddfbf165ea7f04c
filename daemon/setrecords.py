"""A test set made again from the daemon's records: ``ballbar analyze DIR --set NAME``.

The set (``[sets.<name>]`` as the records' newest configuration has it) is the
latest recorded complete test of each of its plans, as the daemon chose them
(:func:`ballbar.analysis.sets.select` over the recorded test results, by the
``plan.name`` each carries and the time it was published).  Each member is
analysed again from its own samples (:func:`~.testindex.analyze_recorded`)
with its plan as the daemon ran it (recognised again from the recording as
the daemon did, a different plan an error; as that plan where a service
chose it, or the records predate recognition), given the recorded test's id and time,
and its verdict against its plan's limits; then combined exactly as the
daemon does (:func:`ballbar.analysis.sets.combine`).  The figures are the
live set's: the analysis is the same code on the same samples.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ballbar import SCHEMA_VERSION
from ballbar.analysis import sets as aset
from ballbar.analysis.errors import DataError, PlanError
from ballbar.analysis.plan import AnalysisOptions, TestPlan, machine_of

from .testindex import RecordedTest, TestIndex, analyze_recorded, index_recordings

log = logging.getLogger(__name__)


def newest_config(index: TestIndex) -> dict[str, Any]:
    """The whole configuration the newest file that has one recorded (empty: none)."""
    for f in reversed(index.files):
        if f.config:
            cfg = f.config[-1].get("config")
            return dict(cfg) if isinstance(cfg, Mapping) else {}
    return {}


def plan_config(cfg: Mapping[str, Any], name: str) -> tuple[TestPlan, dict[str, Any] | None]:
    """Plan ``name`` of a recorded configuration (``plans.<name>``, or the single ``[plan]`` as ``default``)
    and its own limits table (None: the configuration's)."""
    plans = cfg.get("plans") or {}
    body = plans.get(name)
    if body is None and name == "default" and isinstance(cfg.get("plan"), Mapping):
        body = cfg["plan"]
    if not isinstance(body, Mapping):
        raise DataError(f"the records' configuration has no plan {name!r} (plans: {', '.join(plans) or 'none'})")
    keys = {f.name for f in dataclasses.fields(TestPlan)}
    plan = TestPlan.from_dict({k: v for k, v in body.items() if k in keys})
    own = body.get("limits")
    return plan, dict(own) if isinstance(own, Mapping) else None


def limits_for(cfg: Mapping[str, Any], own: Mapping[str, Any] | None) -> dict[str, Any] | None:
    """The ``[limits]`` table a plan's tests are judged by: its own over the configuration's; None when off."""
    table = dict(cfg.get("limits") or {})
    if own:
        table.update(own)
        table.setdefault("enabled", True)
    return table if table.get("enabled") else None


@dataclass
class RecordedSet:
    """A set's members as the records hold them, analysed again: ``results`` by plan (with curves when asked),
    ``tests`` the recorded tests, ``config`` the records' newest configuration."""

    definition: aset.SetDefinition
    index: TestIndex
    tests: dict[str, RecordedTest]
    results: dict[str, dict[str, Any]]
    config: dict[str, Any]


def recorded_set(path: str | os.PathLike[str], name: str, options: AnalysisOptions | None = None,
                 curves: bool = False) -> RecordedSet:
    """The members of set ``name`` in a directory of the daemon's records, each analysed again from its samples
    (module docstring); ``curves``: with each data arc's samples and model (the report's plots).

    A set the configuration does not name, or whose tests are not all there
    within its window, is a :class:`DataError` saying which.
    """
    from ballbar.analysis import monitor

    index = index_recordings(path)
    cfg = newest_config(index)
    try:
        defs = {d.name: d for d in aset.definitions(cfg.get("sets"))}
    except PlanError as err:
        raise DataError(f"{path}: the recorded sets: {err}") from err
    if name not in defs:
        raise DataError(f"{path}: the records' configuration has no set {name!r} (sets: {', '.join(defs) or 'none'})")
    d = defs[name]
    done = [t for t in index.tests if t.status == "complete" and t.result is not None]
    sel = aset.select(d, [t.result for t in done if t.result is not None])
    if not sel.complete:
        raise DataError(f"{path}: set {name}: {sel.why_not}")
    members: dict[str, dict[str, Any]] = {}
    tests: dict[str, RecordedTest] = {}
    for plan_name, recorded in sel.tests.items():
        test = _recorded(done, recorded)
        tcfg = index.config_for(test)
        plan, own = plan_config(cfg, plan_name)
        machine = machine_of(dict(tcfg.get("machine") or cfg.get("machine") or {}))
        opts = options or AnalysisOptions.from_dict(dict(tcfg.get("analysis") or cfg.get("analysis") or {}))
        # the plan the daemon took it for: recognised again as the daemon did, or (chosen by a service, or
        # recorded before plans were recognised) as that plan
        method = (recorded.get("recognition") or {}).get("method")
        result: dict[str, Any] = dict(analyze_recorded(index, test, plan, machine, opts, curves=curves,
                                                       chosen=plan_name if method in (None, "chosen") else None))
        again = (result.get("plan") or {}).get("name")
        if again not in (None, plan_name):
            raise DataError(f"{path}: set {name}: test {test.test_id} was plan {plan_name} live, plan {again} "
                            "analysed again")
        result["plan"]["name"] = plan_name
        if "axes" in recorded.get("plan", {}):
            result["plan"]["axes"] = recorded["plan"]["axes"]
        for key in ("test_id", "t_wall", "machine_id"):
            result[key] = recorded.get(key)
        table = limits_for(cfg, own)
        if table is not None:
            result["verdict"] = monitor.evaluate(result, monitor.settings_from_dict(table))
        members[plan_name] = result
        tests[plan_name] = test
        log.info("set %s: plan %s is test %s", name, plan_name, test.test_id)
    return RecordedSet(d, index, tests, members, cfg)


def combined(rs: RecordedSet) -> dict[str, Any]:
    """The set message of a :class:`RecordedSet`, as the daemon publishes it (its curves and sources left out)."""
    plain = {p: {k: v for k, v in r.items() if k not in ("curves", "source")} for p, r in rs.results.items()}
    body = aset.combine(rs.definition, plain)
    newest = max(plain.values(), key=lambda r: str(r.get("t_wall")))
    return {"schema_version": SCHEMA_VERSION, "machine_id": newest.get("machine_id") or "",
            "t_wall": newest["t_wall"], **body}


def set_from_records(path: str | os.PathLike[str], name: str, options: AnalysisOptions | None = None,
                     ) -> dict[str, Any]:
    """The set ``name`` from a directory of the daemon's records, as the daemon made it (module docstring)."""
    return combined(recorded_set(path, name, options))


def _recorded(done: list[RecordedTest], result: Mapping[str, Any]) -> RecordedTest:
    return next(t for t in done if t.result is result)


__all__ = ["RecordedSet", "combined", "limits_for", "newest_config", "plan_config", "recorded_set", "set_from_records"]
