"""The whole-test analysis in a child process, beside the live circles.

A test's joint fit takes about a second of CPU at 1 kHz (several at 10 kHz)
and allocates some 100 MB of short-lived arrays.  Run in the analysis thread,
it held back the next test's circle results for its whole duration (at x20:
circle latency p99 3.3 s against a 50 ms goal), and its allocations left the
daemon's heap ragged.  :class:`AnalysisWorker` runs it in one long-lived child
process (``spawn``: a clean interpreter, not a fork of a process with Zenoh's
and Rerun's threads), started at once so that its imports (about 0.6 s) are
done before the first feed-out.  A child that dies (killed, out of memory) is
replaced at the next submission; the test it was analysing is rejected with
the reason (:meth:`ballbar.analysis.engine.TestAnalyzer.collect`).

The results are the same as in-process: the job is
:func:`ballbar.analysis.engine.analyze_test` on the same arrays (pickled: at
1 kHz a test is some 2.6 MB), and
:class:`~ballbar.analysis.engine.TestAnalyzer` waits for a test's result
before the next feed-in, so that the timing hints it teaches are applied
exactly as when the analysis ran inline.

A program that makes a :class:`~ballbar.daemon.service.Daemon` must guard
its main module (``if __name__ == "__main__":``), as for any ``spawn``
child: the child imports it.  ``ballbar run`` does.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import ctypes
import functools
import gc
import logging
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable
from concurrent.futures.process import BrokenProcessPool
from typing import Any

log = logging.getLogger(__name__)

WORKER = "analysis worker"
TRACKER = "resource tracker"


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``, None elsewhere (musl has none)."""
    try:
        return getattr(ctypes.CDLL(None), "malloc_trim", None)
    except OSError:  # pragma: no cover - a libc that cannot be loaded
        return None


def release_freed_memory() -> None:
    """Collect a test's analysis's garbage and hand the heap's free pages back to the system.

    The search leaves reference cycles behind (its nested functions and the
    arrays their scopes hold: some 2.7 MB a 1 kHz test), which Python's
    collector takes only at a full collection: every ten tests or so, and less
    often as survivors pile up.  In a worker fitting 30 tests in a row its RSS
    went 108 -> 143 MiB in a saw-tooth; collected after each test, 105.9 ->
    106.6.  And glibc keeps what the analysis freed (some 100 MB of arrays at
    1 kHz); the next analyses reuse it in pieces that no longer fit together,
    so the resident size creeps up to a plateau some 90 MB above what is
    held: trimmed after each test (24 analyses of a 1 kHz test in a thread:
    218 -> 242 MiB without, 136 -> 140 with).  Tens of milliseconds, once a test.
    """
    gc.collect()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def freeze_long_lived() -> None:
    """Take every object alive now (the imports, the configuration, the outputs just started) out of the cyclic
    collector's sight for good (``gc.freeze``).

    A full collection walks every tracked object, and holds every thread for as long: about 90,000 objects in
    the daemon once Rerun and Zenoh are loaded, 35 to 60 ms a collection (measured at x20, 1 kHz), landing
    on whichever result is being made then.  What the daemon makes later is short-lived or held in bounded
    buffers: frozen after its start-up, a full collection walks some 250 objects, 0.3 ms.  In the analysis
    worker the collection after each test goes from about 20 ms to 0.1 ms.  What is frozen is never freed
    by the collector, only by its reference counts: call this once start-up is done, not on a heap
    holding garbage.
    """
    gc.collect()
    gc.freeze()


PR_SET_PDEATHSIG = 1


def _die_with(parent: int) -> None:
    """In the child: be killed when the daemon dies, even by kill -9 (Linux's parent-death signal), so that
    no worker is left behind; the daemon gone already, go now.  The signal follows the thread that started
    the child: the daemon's main thread, or for a replacement its analysis thread; both live as long as it."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:
        os._exit(0)


def _warm_up() -> int:
    """Import the analysis in the child before the first test needs it; its process id."""
    import ballbar.analysis.engine  # noqa: F401

    freeze_long_lived()
    return os.getpid()


def child_role(pid: int) -> str | None:
    """What a child of the daemon is, if this module started it: ``WORKER`` (the fit) or ``TRACKER``
    (multiprocessing's resource tracker, one per daemon); None for any other (the Rerun server) or a
    process that is gone.  For the benchmarks and the soak, which tell the daemon's children apart."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            cmdline = fh.read()
    except OSError:
        return None
    if b"spawn_main" in cmdline:
        return WORKER
    if b"resource_tracker" in cmdline:
        return TRACKER
    return None


def _unlink_semaphore_names(pool: cf.ProcessPoolExecutor) -> int:
    """Unlink the names of the pool's queue semaphores, once its child has opened them (it has when its first job
    is back); how many.

    Under ``spawn`` each semaphore has a name in /dev/shm until it is collected, for the child to open it by; a
    daemon killed with SIGKILL leaves them to multiprocessing's resource tracker, which unlinks them and warns
    of "leaked semaphore objects" in the journal each time.  Unlinked now (each semaphore lives on, open in both
    processes), with the library's own clean-up (``SemLock._cleanup``: unlink, and tell the tracker), nothing
    is left to leak.  The pool starts no other process (one worker, kept; a dead one means a new pool)."""
    from multiprocessing import synchronize, util

    names: set[str] = set()
    for queue in (getattr(pool, "_call_queue", None), getattr(pool, "_result_queue", None)):
        for attr in ("_rlock", "_wlock", "_sem"):
            name = getattr(getattr(getattr(queue, attr, None), "_semlock", None), "name", None)
            if isinstance(name, str):
                names.add(name)
    cleanup = getattr(synchronize.SemLock, "_cleanup", None)
    done = 0
    for fin in list(getattr(util, "_finalizer_registry", {}).values()):
        args = getattr(fin, "_args", None)
        if cleanup is not None and getattr(fin, "_callback", None) is cleanup and args and args[0] in names:
            try:
                fin()
            except OSError as err:  # already gone: nothing to leak
                log.debug("analysis worker: semaphore %s: %s", args[0], err)
            done += 1
    return done


class AnalysisWorker(cf.Executor):
    """One child process for whole-test analyses; replaced when it dies.  See the module docstring."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pool: cf.ProcessPoolExecutor | None = None
        self._closed = False
        self.started = 0  # child processes started
        self.pid: int | None = None
        self._start()

    def _start(self) -> cf.ProcessPoolExecutor:
        pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=_die_with, initargs=(os.getpid(),))
        self._pool = pool
        self.started += 1
        warm = pool.submit(_warm_up)
        warm.add_done_callback(self._started)
        return pool

    def _started(self, fut: cf.Future[int]) -> None:
        if not fut.cancelled() and fut.exception() is None:
            self.pid = fut.result()
            pool = self._pool
            unlinked = _unlink_semaphore_names(pool) if pool is not None else 0
            log.debug("analysis worker: process %d ready (%d semaphore names unlinked)", self.pid, unlinked)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> cf.Future[Any]:
        with self._lock:
            if self._closed:
                raise RuntimeError("the analysis worker is shut down")
            pool = self._pool or self._start()
            try:
                fut = pool.submit(fn, *args, **kwargs)
            except BrokenProcessPool:
                log.warning("analysis worker: process %s had ended; starting another", self.pid)
                pool.shutdown(wait=False, cancel_futures=True)
                pool = self._start()
                fut = pool.submit(fn, *args, **kwargs)
            # the fit's garbage collected and its freed heap handed back once the job's own arguments and
            # result are gone too: a job of its own, after it
            pool.submit(release_freed_memory)
            return fut

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop the child; with ``wait=False`` an analysis still running is killed, not waited for."""
        with self._lock:
            self._closed = True
            pool, self._pool = self._pool, None
        if pool is None:
            return
        if not wait:
            # ProcessPoolExecutor has no kill: its processes are terminated so that a stop does not wait on a fit
            for proc in list(getattr(pool, "_processes", {}).values()):
                proc.terminate()
        pool.shutdown(wait=wait, cancel_futures=cancel_futures or not wait)
