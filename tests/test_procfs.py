"""The one /proc reader, against processes this test makes."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time

import pytest

from ballbar.daemon import procfs


def test_status_stat_and_descriptors_of_this_process() -> None:
    me = os.getpid()
    assert procfs.rss_bytes(me) > 10 << 20
    assert int(procfs.status(me)["Threads"]) == len(procfs.threads(me))
    r, w = os.pipe()
    try:
        assert {str(r), str(w)} <= set(procfs.fds(me))
    finally:
        os.close(r)
        os.close(w)
    before = procfs.cpu_seconds(me)
    end = time.process_time() + 0.05
    while time.process_time() < end:
        pass
    assert procfs.cpu_seconds(me) > before


def test_a_thread_name_with_spaces_and_parentheses_is_read_whole() -> None:
    """``comm`` may hold ``)``: the fields start after the last one."""
    done = threading.Event()
    tid: list[int] = []

    def named() -> None:
        tid.append(threading.get_native_id())
        with open("/proc/thread-self/comm", "w", encoding="ascii") as fh:
            fh.write("a) (b c")
        done.wait(5)

    th = threading.Thread(target=named)
    th.start()
    try:
        while not tid:
            time.sleep(0.01)
        time.sleep(0.05)
        name, fields = procfs.stat(os.getpid(), tid[0])
        assert name == "a) (b c" and fields[0] in "RSD" and procfs.cpu_ticks(fields) >= 0
    finally:
        done.set()
        th.join()


def test_children_and_a_vanished_process() -> None:
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        assert child.pid in procfs.children(os.getpid())
    finally:
        child.kill()
        child.wait()
    with pytest.raises(OSError):
        procfs.status(child.pid)
