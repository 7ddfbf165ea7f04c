"""The soak tool, short: every fault once (the restarts too), and every sample still accounted for.

The figures' trends need the long run (``python -m ballbar.tools.bench.soak --minutes 30``, README "Soak");
this only checks that the tool works and that the accounting adds up across each kind of fault.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def test_a_short_soak_accounts_for_every_sample(tmp_path: Path) -> None:
    report = tmp_path / "soak.json"
    proc = subprocess.run(
        [sys.executable, "-m", "ballbar.tools.bench.soak", "--minutes", "0.9", "--fault-every-s", "7",
         "--unplug-s", "1",
         "--freeze-s", "3", "--disk-full-s", "2", "--disk-mb", "96", "--sample-s", "1", "--samples-hz", "50",
         "--workdir", str(tmp_path / "work"), "--json", str(report)],
        capture_output=True, text=True, timeout=300,
    )
    assert report.exists(), proc.stdout + proc.stderr
    r = json.loads(report.read_text())
    assert [f["fault"] for f in r["faults"]] == ["unplug", "reset", "garbage", "freeze", "disk-full", "restart", "kill"]
    acc = r["accounting"]
    assert acc["problems"] == [], proc.stdout
    # the unplug and each restart cost samples, all counted (the restarts by the next start, from the device's counter)
    assert acc["counted_lost"] > 0 and acc["lost_by_cause"].keys() == {"outage", "restart"}
    assert len(acc["restart_losses"]) == 2 and min(acc["restart_losses"]) > 0
    assert acc["skipped_bytes"] >= acc["device"]["garbage_bytes"]  # and a cut frame: checked above
    assert [life["exit_code"] for life in r["daemon"]["lives"]] == [0, -9, 0]
    if r["disk"]["tmpfs"]:
        # the spell and its log_gap; the samples of its 2 s are written when writing resumes, from the preroll buffer
        assert acc["recorded"]["log_gaps"] == 1
        assert "which the preroll buffer still held" in (tmp_path / "work" / "daemon.log").read_text()
    else:
        assert "skipped" in r["faults"][-1]
    assert r["daemon"]["exit_code"] == 0


def test_the_verdict_passes_a_merging_queue_and_flags_growth() -> None:
    from ballbar.tools.bench.soak import QUEUE_DEPTH_MAX, verdict

    def fig(first: float, median: float, last: float, trend: float) -> dict[str, float | None]:
        return {"first_quiet": first, "median": median, "last_quiet": last, "trend_per_min": trend}

    flat = {"rss_mb": fig(230, 231, 232, 0.02), "threads": fig(32, 32, 32, 0.0), "fds": fig(42, 42, 42, 0.0),
            "queue_mcap_depth": fig(9, 9, 9, -0.01), "queue_analysis_depth": fig(1, 1, 1, 0.0)}
    assert verdict(flat, 25.0) == []  # the MCAP queue holds a quarter second of batches by design
    deep = {**flat, "queue_analysis_depth": fig(QUEUE_DEPTH_MAX + 5, QUEUE_DEPTH_MAX + 5, QUEUE_DEPTH_MAX + 5, 0.0)}
    assert [b.split(":")[0] for b in verdict(deep, 25.0)] == ["queue_analysis_depth"]
    growing = {**flat, "queue_zenoh_depth": fig(1, 4, 8, 0.3)}  # 7.5 batches over 25 minutes
    assert [b.split(":")[0] for b in verdict(growing, 25.0)] == ["queue_zenoh_depth"]
    leak = {**flat, "rss_mb": fig(206, 236, 253, 1.34), "threads": fig(28, 32, 32, 0.108)}
    assert verdict(leak, 25.0) == ["daemon RSS grows 33.5 MiB over the run", "threads grow 2.7 over the run (28 -> 32)"]
    worker = {**flat, "worker_rss_mb": fig(80, 84, 95, 0.5)}  # the test's fit moved out: its memory still counts
    assert verdict(worker, 25.0) == ["analysis worker RSS grows 12.5 MiB over the run"]


def test_the_trend_is_not_moved_by_one_sample_in_a_backlog() -> None:
    import numpy as np

    from ballbar.tools.bench.soak import theil_sen

    t = np.arange(20.0)
    flat = np.full(20, 1.0)
    flat[15] = 110.0  # one quiet sample taken while a test's analysis held the queue
    assert theil_sen(t, flat) == 0.0 and np.polyfit(t, flat, 1)[0] > 0.5  # (least squares: 17 over the run)
    assert theil_sen(t, 230.0 + 0.5 * t) == 0.5  # a steady climb is still seen
