"""The tests in the daemon's MCAP records, found from the records alone.

A directory of recordings holds the samples of many tests, often of several
daemon runs.  Decoding every sample to find one test is slow (15 files of a
1 kHz daemon: about 20 s), and joining the runs is wrong: each run's device
clock starts afresh, so no single time axis spans them.  Instead:

- :func:`index_recordings` reads each file's events, results and configuration
  without its samples (:func:`~.mcap.read_log` with ``samples=False``) and
  lists the tests (:class:`RecordedTest`) by the ``test_id`` their ``feed_in``
  event, results and ``test_rejected``/``test_incomplete`` events carry: when
  each began, which files hold it, whether it completed, was rejected (and
  why) or never finished, and its result.
- :meth:`TestIndex.select` picks one: the newest complete test (``latest``), a
  test id, or the N-th listed.
- :func:`analyze_recorded` decodes only the files that hold that test (all of
  one daemon run, so one device clock; the file before it too where its head
  lacks the test's start) and analyses them, with the breaks their events
  report, exactly as :func:`~.recordings.analyze_file` does.

A daemon run is the files that share the logger's ``run_id`` (drawn once per
start; older files: ``host_clock_offset_ns``, measured once per start).
``ballbar analyze DIR`` and ``ballbar report --test-id`` both go through here.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ballbar.analysis.errors import BallbarError, DataError, DetectionError
from ballbar.analysis.plan import AnalysisOptions, MachineAxes, MachineConfig, TestPlan
from ballbar.analysis.plans import PlanLibrary
from ballbar.analysis.report import headline

from .mcap import McapLog, mcap_files, read_log, read_logs, recording
from .recordings import Outcome, analyze, config_sections, outcomes, recorded_library, with_source
from .samples import Recording

if TYPE_CHECKING:
    from ballbar.protocol.messages import Analysis
    from ballbar.protocol.messages.results import AnalysisSource

log = logging.getLogger(__name__)

MATCH_FEED_IN_S = 1.0  # a re-analysed test is the recorded one when their feed-ins are this close (same clock)
NO_OUTCOME = "no result recorded: the daemon stopped during the test (or is still running it)"


@dataclass
class LogFile:
    """One file's records (no samples) and the daemon run it belongs to (0, 1, ... in file order)."""

    path: Path
    run: int
    metadata: dict[str, str]
    config: list[dict[str, Any]]
    events: list[dict[str, Any]]
    results: list[dict[str, Any]]


@dataclass
class RecordedTest:
    """One test as the daemon recorded it.

    ``number``: its place in the index (1 = the oldest).  ``start``: the
    ``t_wall`` (ISO 8601 UTC) of its ``feed_in`` event.  ``feed_in_s`` and
    ``time_axis``: the feed-in's time on the live analysis's clock, and which
    clock that was.  ``status``: ``complete`` (a test result was recorded),
    ``rejected``, ``unrecognised`` (no plan of the library, or several, fitted
    it) or ``incomplete``; ``message``: why not complete.  ``unreportable``:
    why a test (complete or not) cannot be analysed again from the records:
    samples between its feed-in and feed-out were lost to a write outage (a
    ``log_gap`` event with a lost span on its clock).
    ``files``: indices into :attr:`TestIndex.files` of the files that hold it.
    """

    number: int
    test_id: str
    machine_id: str | None
    start: str | None
    feed_in_s: float | None
    time_axis: str | None
    run: int
    files: list[int]
    status: str = "incomplete"
    message: str = NO_OUTCOME
    result: dict[str, Any] | None = None
    plan: str | None = None  # the plan's name (a library of several: from its result or its feed-in)
    feed_out_s: float | None = None  # the feed-out's time on the same clock as feed_in_s
    unreportable: str | None = None  # why the records cannot give it again (samples lost to a write outage)


@dataclass
class TestIndex:
    """The tests of a directory of recordings (or of one file), oldest first."""

    __test__ = False

    path: str
    files: list[LogFile]
    tests: list[RecordedTest] = field(default_factory=list)

    def results(self) -> list[dict[str, Any]]:
        """Every result recorded (circle and test), in file order: the history a report's trend draws on."""
        return [r for f in self.files for r in f.results]

    def runs(self) -> list[list[int]]:
        """The files of each daemon run, oldest run first."""
        out: list[list[int]] = []
        for i, f in enumerate(self.files):
            if not out or self.files[out[-1][-1]].run != f.run:
                out.append([])
            out[-1].append(i)
        return out

    def select(self, test_id: str | None = None, number: int | None = None) -> RecordedTest:
        """The test asked for: ``number`` (from 1), ``test_id``, or (None or ``"latest"``) the newest complete one."""
        n = len(self.tests)
        if not n:
            raise DataError(f"{self.path}: no test recorded (no feed-in event in {len(self.files)} file(s))")
        if number is not None:
            if not 1 <= number <= n:
                raise DataError(f"{self.path}: holds {n} recorded test(s), test {number} asked for (--list shows them)")
            return self.tests[number - 1]
        if test_id is None or test_id == "latest":
            done = [t for t in self.tests if t.status == "complete" and t.unreportable is None]
            if not done:
                last = self.tests[-1]
                raise DataError(
                    f"{self.path}: none of the {n} recorded test(s) is complete (the newest, {last.test_id}, is "
                    f"{last.status}: {last.message}); choose one with --test-id"
                )
            return done[-1]
        found = [t for t in self.tests if t.test_id == test_id]
        if not found:
            known = ", ".join(t.test_id for t in self.tests[-5:])
            raise DataError(f"{self.path}: no test {test_id!r} in the records (the newest: {known})")
        if len(found) > 1:
            log.warning("%s: %d tests have the id %s (daemon runs that started tests within one second); "
                        "the newest is taken", self.path, len(found), test_id)
        return found[-1]

    def config_for(self, test: RecordedTest) -> dict[str, Any]:
        """The ``plan``, ``machine`` and ``analysis`` the daemon ran the test with (its run's newest before it)."""
        first = test.files[0]
        for i in range(first, -1, -1):
            f = self.files[i]
            if f.run != test.run:
                break
            if f.config:
                return config_sections(f.config)
        return {}

    def describe(self, test: RecordedTest) -> dict[str, Any]:
        """The JSON line of ``ballbar analyze --list``."""
        return {
            "number": test.number,
            "test_id": test.test_id,
            "machine_id": test.machine_id,
            "start": test.start,
            "status": test.status,
            "message": test.unreportable or (test.message if test.status != "complete" else ""),
            "reportable": test.unreportable is None,
            "files": [self.files[i].path.name for i in test.files],
            "time_axis": test.time_axis,
            "plan": test.plan,
            "headline": headline(test.result) if test.result is not None else None,
        }


def index_recordings(path: str | os.PathLike[str]) -> TestIndex:
    """Index the tests of a directory of the daemon's recordings, or of one recording file.

    Reads no samples.  A file that cannot be read is left out with a warning
    (one bad file does not hide the others' tests).
    """
    name = os.fspath(path)
    if os.path.isdir(name):
        paths = mcap_files(name)
        if not paths:
            raise DataError(f"{name}: a directory without .mcap files")
    else:
        paths = [Path(name)]
    files: list[LogFile] = []
    runs: list[str] = []
    for p in paths:
        try:
            lg = read_log(p, samples=False)
        except BallbarError as err:
            if len(paths) == 1:
                raise
            log.warning("%s", err)
            continue
        # (files of an older version carry no run_id: their clock offset, which two starts rarely share)
        run = lg.metadata.get("run_id") or lg.metadata.get("host_clock_offset_ns") or f"file {p.name}"
        if not runs or runs[-1] != run:
            runs.append(run)
        files.append(LogFile(p, len(runs) - 1, lg.metadata, lg.config, lg.events, lg.results))
    index = TestIndex(name, files)
    by_key: dict[tuple[int, str], RecordedTest] = {}
    for fi, f in enumerate(files):
        for ev in f.events:
            tid = ev.get("test_id")
            if not isinstance(tid, str):
                continue
            key = (f.run, tid)
            what = ev.get("event")
            if what == "feed_in":
                if key not in by_key:
                    t_s = ev.get("t_s")
                    by_key[key] = RecordedTest(
                        len(by_key) + 1, tid, ev.get("machine_id"), ev.get("t_wall"),
                        float(t_s) if isinstance(t_s, int | float) else None, ev.get("time_axis"), f.run, [fi],
                        plan=ev.get("plan") if isinstance(ev.get("plan"), str) else None,
                    )
                continue
            test = by_key.get(key)
            if test is None:
                continue
            _holds(test, fi)
            if what == "feed_out" and isinstance(ev.get("t_s"), int | float):
                test.feed_out_s = float(ev["t_s"])
            if what in ("test_rejected", "test_unrecognised") and test.status != "complete":
                test.status = "rejected" if what == "test_rejected" else "unrecognised"
                test.message = str(ev.get("message", ""))
            elif what == "test_incomplete" and test.status == "incomplete":
                test.message = str(ev.get("message", "")) or NO_OUTCOME
        for r in f.results:
            rid = r.get("test_id")
            test = by_key.get((f.run, rid)) if isinstance(rid, str) else None
            if test is None:
                continue
            _holds(test, fi)
            if r.get("kind") == "test":
                test.status, test.message, test.result = "complete", "", r
                named = (r.get("plan") or {}).get("name")
                test.plan = named if isinstance(named, str) else test.plan
    gaps = [(f.run, ev) for f in files for ev in f.events if ev.get("event") == "log_gap" and ev.get("count")]
    for test in by_key.values():
        test.unreportable = _lost_in(test, [ev for run, ev in gaps if run == test.run])
    last_of_run = {f.run: i for i, f in enumerate(files)}
    for test in by_key.values():
        end = last_of_run[test.run] if test.status == "incomplete" else test.files[-1]
        test.files = list(range(test.files[0], end + 1))
    index.tests = list(by_key.values())
    return index


def _lost_in(test: RecordedTest, gaps: list[dict[str, Any]]) -> str | None:
    """Why ``test`` is not in its records whole: the first write outage (``log_gap``) whose lost samples fall
    between its feed-in and its feed-out (or its end, not recorded), on the test's own clock; None if none does."""
    if test.feed_in_s is None:
        return None
    end = test.feed_out_s if test.feed_out_s is not None else float("inf")
    span_key = "lost_t_device" if test.time_axis == "device" else "lost_t_host"
    for ev in gaps:
        span = ev.get(span_key)
        if not (isinstance(span, list) and len(span) == 2):
            continue
        lo = span[0] if isinstance(span[0], int | float) else float("-inf")
        hi = span[1] if isinstance(span[1], int | float) else float("inf")
        if lo < end and hi > test.feed_in_s:
            given = ev.get("lost_utc")
            utc: list[Any] = given if isinstance(given, list) and len(given) == 2 else [None, None]
            when = f"from {utc[0] or 'the start'} to {utc[1] or 'the end'}"
            return (f"not reportable: {ev.get('count')} samples {when} were lost to a write outage "
                    f"({ev.get('detail') or 'a write error'}); the recordings do not hold the test from feed-in to "
                    "feed-out")
    return None


def _holds(test: RecordedTest, fi: int) -> None:
    if fi > test.files[-1]:
        test.files.append(fi)


def analyze_recorded(
    index: TestIndex,
    test: RecordedTest,
    plan: TestPlan,
    machine: MachineConfig | MachineAxes,
    options: AnalysisOptions,
    curves: bool = False,
    library: PlanLibrary | None = None,
    chosen: str | None = None,
) -> Analysis:
    """Analyse one recorded test from the files that hold it (see the module docstring).

    ``library``: the plans its test may run (None: those its daemon run recorded, if any, else ``plan``
    alone); ``chosen``: analysed as that plan of the library.

    Returns its result with ``source`` (``file``: its first file, ``files``,
    ``test_id``, ``machine_id``, ``time_axis``).  A test the analysis rejects,
    or whose samples are gone, is a :class:`DataError` with the reason.
    """
    if test.unreportable is not None:
        raise DataError(f"{index.files[test.files[0]].path}: test {test.test_id}: {test.unreportable}")
    if library is None:
        library = recorded_library(index.config_for(test))
    tries = [test.files]
    before = test.files[0] - 1
    if before >= 0 and index.files[before].run == test.run:
        tries.append([before, *test.files])  # a preroll that did not reach back to the feed-in
    problem: BallbarError | None = None
    for fidx in tries:
        paths = [index.files[i].path for i in fidx]
        lg = read_logs(paths, status=False)
        own = fidx.index(test.files[0])
        name = os.fspath(paths[own]) if len(paths) == 1 else f"{paths[own]} (+{len(paths) - 1} file(s))"
        rec = recording(lg, name)
        try:
            found = outcomes(analyze(rec, plan, machine, options, curves, library=library, chosen=chosen))
        except DetectionError as err:
            problem = err
            continue
        entry = _match(found, test, rec, lg, own)
        if entry is None:
            continue
        if entry["result"] is None:
            raise DataError(f"{name}: test {test.test_id}: {entry['message'] or entry['status']}")
        source: AnalysisSource = {"file": os.path.abspath(paths[own]),
                                  "files": [os.path.abspath(p) for p in paths[own:]],
                                  "test_id": test.test_id, "machine_id": test.machine_id, "time_axis": rec.axis,
                                  "tests_recorded": len(index.tests)}
        return with_source(entry["result"], source, plan)
    first = index.files[test.files[0]].path
    why = f" ({problem})" if problem is not None else ""
    raise DataError(f"{first}: the samples of test {test.test_id} do not hold it from feed-in to feed-out{why}")


def _match(
    found: list[Outcome], test: RecordedTest, rec: Recording, lg: McapLog, own: int
) -> Outcome | None:
    """The analysed test that is the recorded one: the same feed-in on the same clock, else by the file's start.

    A test's file begins with a preroll of samples from before its feed-in was
    recognised (which may hold earlier tests); the test is the last one whose
    feed-in lies before the file's own samples begin.
    """
    timed = [(e, e["feed_in_s"]) for e in found if e["feed_in_s"] is not None]
    if test.feed_in_s is not None and test.time_axis in (None, rec.axis) and timed:
        at = test.feed_in_s
        best, best_s = min(timed, key=lambda ef: abs(ef[1] - at))
        if abs(best_s - at) < MATCH_FEED_IN_S:
            return best
        if test.time_axis is not None:
            return None
    start = lg.file_starts[own] if own < len(lg.file_starts) else 0
    mine = np.flatnonzero(~lg.preroll[start:])
    if not mine.size:
        return None
    k = start + int(mine[0])
    clock = lg.samples.t_device if rec.axis == "device" else lg.samples.t_host
    before = [e for e, s in timed if s <= clock[k]]
    return before[-1] if before else None


__all__ = ["LogFile", "RecordedTest", "TestIndex", "analyze_recorded", "index_recordings"]
