"""The soak tool, short: every fault once, and every sample still accounted for.

The figures' trends need the long run (``python -m ballbar.tools.soak --minutes 30``, README "Soak");
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
        [sys.executable, "-m", "ballbar.tools.soak", "--minutes", "0.6", "--fault-every-s", "7", "--unplug-s", "1",
         "--freeze-s", "3", "--disk-full-s", "2", "--disk-mb", "96", "--sample-s", "1", "--samples-hz", "50",
         "--workdir", str(tmp_path / "work"), "--json", str(report)],
        capture_output=True, text=True, timeout=300,
    )
    assert report.exists(), proc.stdout + proc.stderr
    r = json.loads(report.read_text())
    assert [f["fault"] for f in r["faults"]] == ["unplug", "reset", "garbage", "freeze", "disk-full"]
    acc = r["accounting"]
    assert acc["problems"] == [], proc.stdout
    assert acc["lost"] > 0 and acc["lost_by_cause"].keys() == {"outage"}  # the unplug cost samples, all counted
    assert acc["decode"].get("skipped_bytes", 0) >= acc["device"]["garbage_bytes"]  # and a cut frame: checked above
    if r["disk"]["tmpfs"]:
        assert acc["mcap"]["samples_lost"] > 0 and acc["recorded"]["log_gaps"] == 1  # the spell, and its log_gap
    else:
        assert "skipped" in r["faults"][-1]
    assert r["daemon"]["exit_code"] == 0
