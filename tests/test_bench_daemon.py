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

from ballbar.tools.bench import bench_daemon as bd


def _burn(seconds: float) -> None:
    end = time.process_time() + seconds
    x = 0
    while time.process_time() < end:
        x += 1


def test_stat_parsing_takes_names_with_spaces_and_parentheses() -> None:
    line = "1234 (a (weird) name) S 1 1234 1234 0 -1 4194560 100 0 0 0 250 75 0 0 20 0 3 0 1000 0 0"
    assert bd.parse_stat(line) == ("a (weird) name", 325)
    status = "Name:\tx\nVmRSS:\t  20480 kB\nThreads:\t3\nvoluntary_ctxt_switches:\t7\nnonvoluntary_ctxt_switches:\t2\n"
    assert bd.parse_status(status) == {"VmRSS": 20480, "Threads": 3, "voluntary_ctxt_switches": 7,
                                       "nonvoluntary_ctxt_switches": 2}


def test_usage_of_this_process_per_thread() -> None:
    stop = threading.Event()

    def sleeper() -> None:
        bd._set_comm("bench-sleeper")
        while not stop.wait(0.005):
            pass

    th = threading.Thread(target=sleeper)
    th.start()
    try:
        time.sleep(0.05)
        a = bd.snapshot(os.getpid())
        _burn(0.3)
        time.sleep(0.2)
        b = bd.snapshot(os.getpid())
    finally:
        stop.set()
        th.join()
    assert a is not None and b is not None
    assert threading.get_native_id() in b.tasks and b.rss_kib > 0
    u = bd.usage(a, b)
    assert 15.0 < u["cpu_pct"] <= 100.0 * (1 + 2 / bd.CLK_TCK / u["seconds"])  # 0.3 s of CPU in about 0.5 s
    assert u["ctx_per_s"] > 0 and u["ctx_per_s"] == pytest.approx(u["voluntary_per_s"] + u["nonvoluntary_per_s"])
    names = {t["name"]: t for t in u["threads"]}
    assert names["bench-sleeper"]["voluntary_per_s"] > 20  # it wakes every 5 ms
    # The kernel rounds each thread's times and the process's total to clock ticks on their own
    # (and splits user from system time per task), so the threads' sum may exceed the total by
    # up to a tick per thread at each of the two snapshots, and by no more.
    slack = 100.0 * 2 * sum(t["threads"] for t in u["threads"]) / bd.CLK_TCK / u["seconds"]
    assert sum(t["cpu_pct"] for t in u["threads"]) <= u["cpu_pct"] + slack


def test_statistics() -> None:
    t = [0.0, 60.0, 120.0, 180.0]
    assert bd.slope_per_min(t, [100.0, 102.0, 104.0, 106.0]) == pytest.approx(2.0)
    assert bd.slope_per_min(t[:2], [1.0, 2.0]) is None
    d = bd.distribution([3.0, 1.0, None, 2.0, float("nan")])
    assert (d["n"], d["median"], d["min"], d["max"]) == (3, 2.0, 1.0, 3.0) and 2.9 < d["p99"] <= 3.0
    assert bd.distribution([]) == {"n": 0}
    assert bd._comm_name("listener-analysis") == "L-analysis"
    assert bd._comm_name("Thread-3 (flusher)") == "T-flusher"
    assert len(bd._comm_name("x" * 40)) == 15


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
