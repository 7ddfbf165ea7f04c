"""The daemon bench: its /proc parsing and statistics on this process, and one short run.

The figures themselves need the long runs (``python -m ballbar.tools.bench.bench_daemon``, README
"Benchmarks"); the short run only checks that every figure is there and sane.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from ballbar.tools.bench import daemon_children as children
from ballbar.tools.bench import daemon_usage as du


def _burn(seconds: float) -> None:
    end = time.process_time() + seconds
    x = 0
    while time.process_time() < end:
        x += 1


def test_snapshot_takes_thread_names_with_spaces_and_parentheses() -> None:
    """A thread's kernel name may hold spaces and parentheses (``Thread-3 (flusher)``): the snapshot reads it
    whole, through ``daemon/procfs.py``, and the thread's counters with it."""
    stop = threading.Event()
    named = threading.Event()
    tid: list[int] = []

    def sleeper() -> None:
        with open("/proc/thread-self/comm", "w", encoding="utf-8") as fh:
            fh.write("a (weird) name")
        tid.append(threading.get_native_id())
        named.set()
        stop.wait(10)

    th = threading.Thread(target=sleeper)
    th.start()
    try:
        assert named.wait(10)
        # once it blocks in its wait it has switched voluntarily (until then, on a loaded machine, it may only have
        # been preempted)
        deadline = time.monotonic() + 10.0
        while True:
            snap = du.snapshot(os.getpid())
            assert snap is not None
            if snap.tasks[tid[0]].voluntary >= 1 or time.monotonic() > deadline:
                break
            time.sleep(0.01)
    finally:
        stop.set()
        th.join()
    assert snap.comm and snap.rss_kib > 0
    task = snap.tasks[tid[0]]
    assert task.comm == "a (weird) name" and task.voluntary >= 1 and task.ticks >= 0
    assert du.rss_mib(os.getpid()) == pytest.approx(snap.rss_kib / 1024.0, rel=0.5)
    assert du.snapshot(2**22 + 1) is None  # beyond pid_max's ceiling: gone


def test_usage_of_this_process_per_thread() -> None:
    stop = threading.Event()

    def sleeper() -> None:
        children._set_comm("bench-sleeper")
        while not stop.wait(0.005):
            pass

    th = threading.Thread(target=sleeper)
    th.start()
    try:
        time.sleep(0.05)
        c0 = time.process_time()
        a = du.snapshot(os.getpid())
        _burn(0.3)
        time.sleep(0.2)
        b = du.snapshot(os.getpid())
        used = time.process_time() - c0
    finally:
        stop.set()
        th.join()
    assert a is not None and b is not None
    assert threading.get_native_id() in b.tasks and b.rss_kib > 0
    u = du.usage(a, b)
    # The CPU this process used between the snapshots (0.3 s and more, over however long a loaded host took), to
    # the kernel's ticks at each end and the snapshot's own reading.
    tick = 100.0 * 2 / du.CLK_TCK / u["seconds"]
    assert u["cpu_pct"] == pytest.approx(100.0 * used / u["seconds"], abs=tick + 2.0) and u["cpu_pct"] > 0, used
    assert u["cpu_pct"] <= 100.0 * (1 + 2 / du.CLK_TCK / u["seconds"])
    assert u["ctx_per_s"] > 0 and u["ctx_per_s"] == pytest.approx(u["voluntary_per_s"] + u["nonvoluntary_per_s"])
    names = {t["name"]: t for t in u["threads"]}
    assert names["bench-sleeper"]["voluntary_per_s"] > 20  # it wakes every 5 ms
    # The kernel rounds each thread's times and the process's total to clock ticks on their own
    # (and splits user from system time per task), so the threads' sum may exceed the total by
    # up to a tick per thread at each of the two snapshots, and by no more.
    slack = 100.0 * 2 * sum(t["threads"] for t in u["threads"]) / du.CLK_TCK / u["seconds"]
    assert sum(t["cpu_pct"] for t in u["threads"]) <= u["cpu_pct"] + slack


def test_statistics() -> None:
    t = [0.0, 60.0, 120.0, 180.0]
    assert du.slope_per_min(t, [100.0, 102.0, 104.0, 106.0]) == pytest.approx(2.0)
    assert du.slope_per_min(t[:2], [1.0, 2.0]) is None
    d = du.distribution([3.0, 1.0, None, 2.0, float("nan")])
    assert (d["n"], d["median"], d["min"], d["max"]) == (3, 2.0, 1.0, 3.0) and 2.9 < d["p99"] <= 3.0
    assert du.distribution([]) == {"n": 0}
    assert children._comm_name("listener-analysis") == "L-analysis"
    assert children._comm_name("Thread-3 (flusher)") == "T-flusher"
    assert len(children._comm_name("x" * 40)) == 15


def test_quick_run_at_1khz(tmp_path: Path) -> None:
    """The quickest run: 1 kHz at x5, a 12 s window; the first circle comes about 10 s in."""
    out = tmp_path / "bench.json"
    t0 = time.monotonic()
    proc = subprocess.run(
        [sys.executable, "-m", "ballbar.tools.bench.bench_daemon", "--quick", "--rates", "1000", "--warmup-s", "3",
         "--window-s", "12", "--workdir", str(tmp_path / "work"), "--json", str(out)],
        capture_output=True, text=True, timeout=180,
    )
    took = time.monotonic() - t0
    assert out.exists(), proc.stdout + proc.stderr
    run = json.loads(out.read_text())["runs"][0]
    assert "error" not in run, run
    procs = run["processes"]
    for role in ("daemon", "device", "baseline reader", "baseline device"):
        assert procs[role]["cpu_pct"] > 0 and procs[role]["ctx_per_s"] > 0, role
        assert procs[role]["rss"]["samples"] >= 10 and procs[role]["rss"]["end_mib"] > 10, role
    assert 11.0 < procs["daemon"]["seconds"] < 14.0
    assert any(k.startswith("daemon child") for k in procs)  # the Rerun server
    threads = {t["name"] for t in procs["daemon"]["threads"]}
    assert {"main", "L-analysis", "L-mcap", "L-zenoh", "L-rerun"} <= threads
    assert run["ratios"]["cpu"] > 0 and run["ratios"]["ctx"] > 0
    circle = run["latency"]["circle"]
    assert circle["count"] >= 1
    assert 0 < circle["subscriber_ms"]["median"] < 5000 and circle["published_ms"]["n"] == circle["count"]
    assert run["accounting"]["daemon_samples"] == run["accounting"]["device_sent"]
    assert run["accounting"]["baseline_reader_samples"] == run["accounting"]["baseline_device_sent"]
    assert run["problems"] == [] and proc.returncode == 0, proc.stdout
    assert "Summary" in proc.stdout
    assert took < 120, f"the quick run took {took:.0f} s"
