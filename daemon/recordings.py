"""Reading recordings for the analysis: CSV (:mod:`.csvfile`) and the daemon's MCAP logs (:mod:`.mcap`).

Every problem is raised as :class:`~ballbar.analysis.errors.DataError` with a
one-line message that names the file (and, in a CSV, the line).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypedDict

import numpy as np

from ballbar.analysis.errors import BallbarError, DataError

from .csvfile import read_csv
from .samples import Recording

if TYPE_CHECKING:
    from ballbar.analysis.plan import AnalysisOptions, MachineAxes, MachineConfig, TestPlan
    from ballbar.analysis.plans import PlanLibrary
    from ballbar.protocol.messages import Analysis, AnalysisOutput, TestBody
    from ballbar.protocol.messages.results import AnalysisSource

log = logging.getLogger(__name__)

# No ball-bar's transducer travels this far: a length further than this from the recording's typical one is not a
# measurement of the bar (a corrupt value, 1e308 in a CSV), and is left out before the analysis (see screen()).
TRAVEL_MM = 25.0
MAX_BAR_MM = 1.0e4  # nor is a bar 10 m long, or one of no length: the typical length is taken among (0, this)




def screen(rec: Recording) -> tuple[Recording, str]:
    """``rec`` without the samples whose length cannot be a measurement of the bar, and why (or "").

    Such a length lies more than :data:`TRAVEL_MM` from the median of the
    recording's lengths within (0, :data:`MAX_BAR_MM`) mm (the median of all of
    them if none is).  Those samples are left out, counted and named in the
    returned warning (the analysis then sees a gap of one sample period per
    sample, within what it takes for lost samples); the breaks keep their
    place.  A finite but absurd value (``1e308``) would otherwise overflow the
    fit's arithmetic.
    """
    L = rec.L
    if not L.size:
        return rec, ""
    with np.errstate(over="ignore", invalid="ignore"):
        plausible = L[(L > 0) & (L < MAX_BAR_MM)]
        mid = float(np.median(plausible if plausible.size else L))
        off = ~(np.abs(L - mid) <= TRAVEL_MM)
    del plausible
    n = int(np.count_nonzero(off))
    if not n:
        return rec, ""
    gone = np.flatnonzero(off)
    first = int(gone[0])
    why = (f"{n} sample(s) left out: a length more than {TRAVEL_MM:g} mm from the recording's typical {mid:.4f} mm "
           f"is not a measurement of the bar (the first: {L[first]:.6g} mm at t = {rec.t[first]:.6f} s)")
    log.warning("%s: %s", rec.name, why)
    keep = ~off
    breaks = [(at - int(np.searchsorted(gone, at)), reason) for at, reason in rec.breaks]
    return replace(rec, t=rec.t[keep], L=L[keep], breaks=breaks), why


def is_mcap(path: str | os.PathLike[str]) -> bool:
    """An MCAP file, or a directory holding MCAP files (else: a CSV)."""
    name = os.fspath(path)
    return name.lower().endswith(".mcap") or (os.path.isdir(name) and any(Path(name).glob("*.mcap")))


def load_recording(path: str | os.PathLike[str]) -> Recording:
    """A recording for the analysis, by its file type.

    ``.mcap``: the daemon's log (:func:`ballbar.daemon.mcap.recording`: the
    device clock where the samples have one, else the host's; samples flagged
    over range or sensor fault left out; a killed writer's file up to its last
    whole chunk; the breaks its events report).  A directory holding ``.mcap``
    files: those files joined, in the order of their names.  Anything else: CSV.
    """
    name = os.fspath(path)
    if is_mcap(name):
        from .mcap import mcap_files, read_log, read_logs, recording  # here: CSV needs no MCAP machinery

        if os.path.isdir(name):
            return recording(read_logs(mcap_files(name), skip_bad=True, status=False), name)
        return recording(read_log(name, status=False), name)
    t, L = read_csv(name)
    return Recording(t, L, [], "t_s", name)


def read_recording(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, length_mm)`` of a recording (:func:`load_recording`)."""
    rec = load_recording(path)
    return rec.t, rec.L


def recorded_config(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The plan, machine and analysis a daemon recording was made with (empty for CSV).

    A directory: the newest file's configuration that has one.
    """
    path = os.fspath(path)
    if not (path.lower().endswith(".mcap") or os.path.isdir(path)):
        return {}
    from .mcap import mcap_files, read_log  # here: reading CSV needs no MCAP machinery

    files = mcap_files(path) if os.path.isdir(path) else [Path(path)]
    for f in reversed(files):
        try:
            configs = read_log(f, samples=False, warn=False).config  # (the samples, read next, say how it ends)
        except BallbarError:
            continue  # read_recording reports what is wrong with the file
        if configs:
            return config_sections(configs)
    return {}


def config_sections(configs: list[dict[str, Any]]) -> dict[str, Any]:
    """The ``plan``, ``machine``, ``analysis`` (and ``limits``, ``plans``, ``sets``) tables of the newest of a log's
    config records."""
    cfg = configs[-1].get("config", {}) if configs else {}
    return {k: dict(cfg[k]) for k in ("plan", "machine", "analysis", "limits", "plans", "sets")
            if isinstance(cfg.get(k), dict)}


OUTCOME_EVENTS = {"test_rejected": "rejected", "test_incomplete": "incomplete", "test_skipped": "skipped",
                  "test_unrecognised": "unrecognised"}


class Outcome(TypedDict):
    """What became of one test an analysis found (:func:`outcomes`)."""

    number: int
    feed_in_s: float | None
    status: str
    message: str
    result: TestBody | None


def outcomes(results: Sequence[AnalysisOutput]) -> list[Outcome]:
    """One entry per test an analysis found, in order.

    Each: ``number`` (from 1), ``feed_in_s``, ``status`` (``complete``,
    ``rejected``, ``incomplete``, ``unrecognised`` (its plan is not known:
    analysis/plans.py), or ``skipped``: not fitted, another test was asked
    for), ``message`` (why not complete) and ``result`` (the test result, or
    None).
    """
    tests: dict[int, Outcome] = {}
    for r in results:
        i = r.get("test_index")
        if not isinstance(i, int):
            continue
        if r["kind"] == "event" and r["event"] == "feed_in":
            tests[i] = {"number": len(tests) + 1, "feed_in_s": r["t_s"], "status": "incomplete", "message": "",
                        "result": None}
            continue
        entry = tests.get(i)
        if entry is None:
            continue
        if r["kind"] == "test":
            entry["status"], entry["result"] = "complete", r
        elif r["kind"] == "event" and r["event"] in OUTCOME_EVENTS and entry["status"] == "incomplete":
            entry["status"], entry["message"] = OUTCOME_EVENTS[r["event"]], str(r.get("message", ""))
    return list(tests.values())


def pick_test(
    results: Sequence[AnalysisOutput], test: int, name: str, plan: TestPlan
) -> Analysis:
    """The ``test``-th (from 1) test of an analysed recording, with ``source`` and warnings.

    A test that was rejected or left incomplete is a :class:`DataError` with
    its reason.
    """
    found = outcomes(results)
    if len(found) < test:
        raise DataError(f"{name}: holds {len(found)} test(s), test {test} asked for")
    entry = found[test - 1]
    if entry["result"] is None:
        others = [e["number"] for e in found if e["status"] in ("complete", "skipped")]
        hint = f" (whole: test {', '.join(map(str, others))}; choose with --test N)" if others else ""
        which = f"test {test} of {len(found)}: " if len(found) > 1 else ""
        raise DataError(f"{name}: {which}{entry['message'] or entry['status']}{hint}")
    return with_source(entry["result"], {"file": os.path.abspath(name), "tests_found": len(found)}, plan)


def with_source(result: TestBody, source: AnalysisSource, plan: TestPlan) -> Analysis:
    """``result`` with ``source`` (``ballbar analyze --json``), and a warning where its sample rate is not the
    plan's."""
    out: Analysis = {**result, "source": source}
    rate = out["samples"]["sample_hz"]
    if rate is not None and abs(rate / plan.sample_hz - 1.0) > 0.2:
        out.setdefault("warnings", []).append(
            f"the recording samples at {rate:.3f} Hz, the plan says {plan.sample_hz:g} Hz; the timestamps were used"
        )
    return out


def analyze_file(
    path: str,
    plan: TestPlan,
    machine: MachineConfig | MachineAxes,
    options: AnalysisOptions,
    test: int = 1,
    curves: bool = False,
    library: PlanLibrary | None = None,
    chosen: str | None = None,
) -> Analysis:
    """Read a recording (:func:`load_recording`), analyse it and return its ``test``-th test result (the
    other tests are found, not fitted).  ``library``, ``chosen``: see :func:`analyze`."""
    rec = load_recording(path)
    if library is None:
        library = recorded_library(recorded_config(path))
    return pick_test(analyze(rec, plan, machine, options, curves, only=test, library=library, chosen=chosen),
                     test, path, plan)


def recorded_library(sections: dict[str, Any]) -> PlanLibrary | None:
    """The library of plans a recording's configuration held (None: its plan alone); a recorded library the
    analysis cannot take is a :class:`DataError`."""
    from .config import ConfigError, library_of

    try:
        return library_of(sections)
    except ConfigError as err:
        raise DataError(f"the recorded plans: {err}") from err


def analyze(
    rec: Recording,
    plan: TestPlan,
    machine: MachineConfig | MachineAxes,
    options: AnalysisOptions,
    curves: bool = False,
    only: int | None = None,
    library: PlanLibrary | None = None,
    chosen: str | None = None,
) -> list[AnalysisOutput]:
    """:func:`~ballbar.analysis.engine.analyze_recording` of a recording, its tests' results and events (no
    provisional circles: what the daemon published of them live is in the recording); its errors name the
    recording.  ``only``: fit that test alone (from 1), the others reported ``test_skipped``: its result is
    the one the whole analysis gives.  ``library``: the plans the tests may run (None: ``plan`` alone), each
    test's recognised as the daemon does; ``chosen``: every test analysed as that plan of the library."""
    from ballbar.analysis.engine import analyze_recording  # here: listing and reading need none of the fit

    rec, left_out = screen(rec)
    try:
        out = analyze_recording(rec.t, rec.L, plan, machine, options, curves=curves, breaks=rec.breaks,
                                circles=False, only=only, library=library, chosen=chosen, controller=rec.controller)
    except DataError as err:
        if rec.name and not str(err).startswith(rec.name):
            err.args = (f"{rec.name}: {err}",)
        if left_out and left_out not in str(err):
            err.args = (f"{err.args[0]} ({left_out})",)
        raise
    if left_out:
        for r in out:
            if r["kind"] == "test":
                r.setdefault("warnings", []).append(left_out)
    if rec.timing and rec.axis == "host":
        from ballbar.analysis.polled import state_span

        for r in out:
            if r["kind"] == "circle" or r["kind"] == "test":
                state_span(r, rec.timing)
    return out
