"""Shared fixtures.

``no_leaks`` (opt-in: ``pytestmark = pytest.mark.usefixtures("no_leaks")``) fails a
test that leaves threads, open file descriptors (ports, ptys, sockets, pipes) or
child processes behind.  It gives them a moment to wind down first, so a clean
``close()`` that takes a few milliseconds is not a leak.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import pytest

# One BLAS thread, as the ``ballbar`` command sets for the daemon and its worker (daemon/cli.py), before numpy loads
# in this process: the tests' fits then run as the daemon's do, without OpenBLAS's other threads spinning beside the
# other workers (on two cores they took twice the CPU and up to ten times the wall time of one thread).
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")


def _fds() -> dict[int, str]:
    from multiprocessing import resource_tracker

    tracker = getattr(resource_tracker._resource_tracker, "_fd", None)  # its pipe: see _children
    out: dict[int, str] = {}
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd == tracker:
            continue
        try:
            out[fd] = os.readlink(f"/proc/self/fd/{name}")
        except OSError:
            continue  # the directory's own descriptor, closed by now
    return out


def _children() -> set[int]:
    """This process's children, but for multiprocessing's resource tracker: one per interpreter once the
    daemon's analysis worker started a process, kept for the interpreter's life (not a test's leak)."""
    from multiprocessing import resource_tracker

    tracker = getattr(resource_tracker._resource_tracker, "_pid", None)
    kids: set[int] = set()
    for tid in os.listdir("/proc/self/task"):
        try:
            with open(f"/proc/self/task/{tid}/children", encoding="ascii") as fh:
                kids.update(int(p) for p in fh.read().split())
        except OSError:
            pass
    return kids - {tracker}


@pytest.fixture
def no_leaks() -> Iterator[None]:
    threads = set(threading.enumerate())
    fds = _fds()
    kids = _children()
    yield
    deadline = time.monotonic() + 2.0
    while True:
        new_threads = [t for t in threading.enumerate() if t not in threads and t.is_alive()]
        now_fds = _fds()
        new_fds = {fd: target for fd, target in now_fds.items() if fds.get(fd) != target}
        new_kids = _children() - kids
        if not (new_threads or new_fds or new_kids) or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    problems = []
    if new_threads:
        problems.append(f"threads left running: {[t.name for t in new_threads]}")
    if new_fds:
        problems.append(f"file descriptors left open: {new_fds}")
    if new_kids:
        problems.append(f"child processes left running: {sorted(new_kids)}")
    if problems:
        pytest.fail("; ".join(problems))
