"""Each test's fit in the daemon's child process (:mod:`ballbar.daemon.analysis_worker`): the same results as
inline, in the same order, and a child that dies or hangs costs one test's result at most, never the daemon."""

from __future__ import annotations

import concurrent.futures as cf
import gc
import math
import os
import signal
import threading
import time
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import numpy as np
import pytest
from test_timeaxis import MACHINE, PLAN, _batches, _listener, stream

from ballbar.analysis.engine import TestAnalyzer
from ballbar.daemon.analysis_worker import AnalysisWorker
from ballbar.daemon.service import WAKE

# the second test runs 3 % fast: the hints the first teaches move its provisional circles
TESTS = (MACHINE, MACHINE.with_(feed_override=1.03, backlash_x_um=5.0), MACHINE.with_(tail_s=2.0))

HOST_FIELDS = {"t_wall", "t_host", "latency_ms"}  # when it went out: differ between any two runs


@pytest.fixture
def worker() -> Any:
    w = AnalysisWorker()
    try:
        yield w
    finally:
        w.shutdown(wait=False)


def _feed_all(an: TestAnalyzer, t: np.ndarray, L: np.ndarray, start: int = 0, n: int = 250) -> list[dict[str, Any]]:
    """Feed from sample ``start`` to the end, ``n`` at a time, then finish."""
    out = []
    for i in range(start, t.size, n):
        out += an.feed(t[i : i + n], L[i : i + n])
    return out + an.finish()


def _same(a: Any, b: Any) -> bool:
    """Equal, NaN equal to NaN."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


def test_the_worker_gives_the_inline_results_in_the_inline_order(worker: AnalysisWorker) -> None:
    t, L, _ = stream(*TESTS)
    inline = _feed_all(TestAnalyzer(PLAN), t, L)
    background = _feed_all(TestAnalyzer(PLAN, executor=worker), t, L)
    assert [m["kind"] for m in inline].count("test") == 3
    assert [(m["kind"], m.get("event"), m.get("test_index")) for m in background] == \
        [(m["kind"], m.get("event"), m.get("test_index")) for m in inline]
    for a, b in zip(inline, background, strict=True):
        assert _same(a, b), (a.get("kind"), a.get("event"))
    # the second test's provisional circles were made with the first test's hints, as inline
    circles = [m for m in background if m["kind"] == "circle" and m["test_index"] == 2]
    assert circles and all(c["timing"]["assumed_feed_mm_min"] != PLAN.feed_mm_min for c in circles)
    assert worker.pid is not None and worker.pid != os.getpid() and worker.started == 1


def test_the_listener_sends_the_workers_result_when_woken_with_the_test_end_s_last_sample(
    worker: AnalysisWorker,
) -> None:
    t, L, _ = stream(TESTS[0], TESTS[2])  # the second settles its feed-out before the stream ends
    seq = np.arange(t.size)
    inline, got_inline = _listener()
    for b in _batches(t, L, seq):
        inline.on_batch(b)
    an, got = _listener()
    an.executor = worker
    an.analyzer = an._new_analyzer()
    wakes: list[float] = []
    an.wake = lambda: wakes.append(time.monotonic())
    batches = _batches(t, L, seq)
    for batch in batches:
        an.on_batch(batch)
        if an.pending and an.analyzer.test_index == 2:
            break  # the last test's feed-out: its fit is in the worker; no batch follows
    assert an.pending and not [m for m in got if m["kind"] == "test" and m["test_index"] == 2]
    deadline = time.monotonic() + 60
    while len(wakes) < 2 and time.monotonic() < deadline:  # one wake per test fitted
        time.sleep(0.01)
    assert len(wakes) == 2, "the worker's result never woke the listener"
    an.on_message(WAKE)
    assert not an.pending
    tests = [m for m in got if m["kind"] == "test"]
    tests_inline = [m for m in got_inline if m["kind"] == "test"]
    assert len(tests) == len(tests_inline) == 2
    for x, y in zip(tests_inline, tests, strict=True):
        assert _same({k: v for k, v in x.items() if k not in HOST_FIELDS and k != "test_id"},
                     {k: v for k, v in y.items() if k not in HOST_FIELDS and k != "test_id"})
    assert tests[-1]["last_sample_t"] == pytest.approx(float(batch.t_device[-1]), abs=1e-6)  # the batch that ended it
    assert an.fit_latency_ms is not None and an.fit_latency_ms > 0


def test_a_worker_killed_mid_fit_costs_its_test_and_the_next_is_fitted_by_another(worker: AnalysisWorker) -> None:
    t, L, _ = stream(*TESTS)
    deadline = time.monotonic() + 30
    while worker.pid is None and time.monotonic() < deadline:  # its warm-up job back
        time.sleep(0.01)
    first = worker.pid
    assert first is not None and first > 0
    killed: list[int] = []

    def kill_the_first(fut: Any) -> None:
        # the moment the first test's fit is handed to the worker: killed with it (the test's feed-out and the
        # next feed-in may come in one feed, whose call then waits for the fit: no moment between two feeds)
        if not killed:
            killed.append(first)
            os.kill(first, signal.SIGKILL)

    an = TestAnalyzer(PLAN, executor=worker, on_submit=kill_the_first)
    out = _feed_all(an, t, L)
    assert killed == [first]
    rejected = [m for m in out if m.get("event") == "test_rejected"]
    assert len(rejected) == 1 and rejected[0]["test_index"] == 1
    assert "ended before its result" in rejected[0]["message"]
    assert [m["test_index"] for m in out if m["kind"] == "test"] == [2, 3]
    assert worker.started == 2 and worker.pid != first


def test_a_stop_does_not_wait_for_a_fit_and_leaves_no_process() -> None:
    worker = AnalysisWorker()
    fut = worker.submit(time.sleep, 30)  # a fit that would hold the stop
    deadline = time.monotonic() + 30
    while worker.pid is None and time.monotonic() < deadline:
        time.sleep(0.01)
    pid = worker.pid
    assert pid is not None
    t0 = time.monotonic()
    worker.shutdown(wait=False)
    assert time.monotonic() - t0 < 2.0
    with pytest.raises((BrokenProcessPool, cf.CancelledError)):  # not a result
        fut.result(timeout=10)
    deadline = time.monotonic() + 10
    while not _gone(pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _gone(pid)
    with pytest.raises(RuntimeError):
        worker.submit(time.sleep, 0)


def _gone(pid: int) -> bool:
    """Exited (or a zombie its parent has not reaped yet)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def _cycle(mb: int) -> int:
    """A job that leaves ``mb`` MB in a reference cycle behind, as the search's nested functions do."""
    a: dict[str, Any] = {"data": np.ones(mb * 2**20 // 8)}
    a["self"] = a
    return mb


def _rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith("VmRSS")) / 1024


def test_what_a_fit_leaves_in_cycles_is_given_back_after_each(worker: AnalysisWorker) -> None:
    worker.submit(_cycle, 1).result(60)
    assert worker.pid is not None
    worker.submit(int).result(10)  # the collection queued after the job is done too
    base = _rss_mb(worker.pid)
    for _ in range(5):
        assert worker.submit(_cycle, 40).result(60) == 40
    worker.submit(int).result(10)
    assert _rss_mb(worker.pid) - base < 20, (base, _rss_mb(worker.pid))  # 200 MB in cycles, none kept


def test_the_workers_imports_are_out_of_the_collectors_way_before_its_first_test(worker: AnalysisWorker) -> None:
    """The worker's imports (numpy, scipy, the analysis) are frozen once loaded: the collection after each
    test (some 20 ms, walking them all) and any that a fit itself sets off no longer walk them."""
    frozen = worker.submit(gc.get_freeze_count).result(60)  # the first job: nothing of this module imported
    assert frozen > 20_000, frozen  # numpy and scipy alone hold more


def test_the_daemon_freezes_its_start_up_objects_once_ready() -> None:
    """Once READY, the daemon's start-up objects are out of the collector's sight: a full collection holds
    every thread for as long as it walks (35 to 60 ms over the daemon's some 90,000 objects, at x20)."""
    from ballbar.daemon.config import load
    from ballbar.daemon.service import Daemon
    from ballbar.daemon.sources import open_source

    cfg = load(None, ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"',
                      "daemon.analysis_worker=false"], env={})
    gc.unfreeze()
    assert gc.get_freeze_count() == 0
    d = Daemon(cfg, open_source("sim:?speedup=max&rate=100"), [])
    try:
        d.run(threading.Event(), duration_s=0.3)
    finally:
        d.shutdown(1.0)
    assert gc.get_freeze_count() > 10_000
