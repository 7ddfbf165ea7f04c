"""Benchmark of the polled path: achieved rate and request/answer window of each gauge profile through a pty.

    python -m ballbar.tools.bench.bench_gauges [--seconds 10] [--bauds 9600,115200] [--rate HZ] [--json out.json]

For each profile and baud, the simulated gauge (``ballbar.tools.simdevice``) emulates its line at that baud
on a pty and the daemon's ``SerialSource`` polls it as fast as the line allows (``--rate``: default the
profile's link-budget maximum at that baud, capped at 10 kHz).  It reports the achieved rate and the
window's median and p99 (``SerialSource.poll_timing``) beside the link budget.  Timing goals live here,
never in the unit tests.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

from ballbar.daemon.sources import RATE_MAX_HZ, open_source
from ballbar.protocol.gauges import PROFILES
from ballbar.tools.simdevice import DeviceProcess


def run(profile: str, baud: int, seconds: float, rate: float | None) -> dict[str, Any]:
    """Poll the simulated ``profile`` gauge at ``baud`` for ``seconds``; its figures."""
    p = PROFILES[profile]
    top = p.max_rate_hz(baud)
    ask = min(rate if rate is not None else math.floor(10 * top) / 10, RATE_MAX_HZ)
    with DeviceProcess("--protocol", profile, "--rate", "1000", "--repeat", "0", "--line-baud", str(baud)) as dev:
        url = f"serial:{dev.path}?protocol={profile}&rate={ask:.6g}&baud={baud}&cal_mm=100"
        with open_source(url) as src:
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                src.read(0.2)
            st = src.stats()
    return {"profile": profile, "baud": baud, "asked_hz": ask, "link_budget_hz": top,
            "line_ms": 1e3 * p.line_time_s(baud), "samples": st.samples, "lost": st.lost,
            "lost_by_cause": dict(st.lost_by_cause), **st.poll}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_gauges",
                                 description="achieved rate and request/answer window of the gauge profiles")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--bauds", default="9600,115200")
    ap.add_argument("--profiles", default=",".join(PROFILES))
    ap.add_argument("--rate", type=float, help="poll rate, Hz (default: the link budget's maximum)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args(argv)
    rows = []
    print(f"{'profile':9} {'baud':>6} {'asked Hz':>9} {'budget Hz':>9} {'achieved Hz':>11} {'line ms':>8} "
          f"{'window med ms':>13} {'p99 ms':>7} {'lost':>5}")
    for profile in args.profiles.split(","):
        for baud in (int(b) for b in args.bauds.split(",")):
            r = run(profile, baud, args.seconds, args.rate)
            rows.append(r)
            print(f"{profile:9} {baud:>6} {r['asked_hz']:>9.1f} {r['link_budget_hz']:>9.1f} "
                  f"{r.get('achieved_hz', 0.0):>11.1f} {r['line_ms']:>8.2f} {r.get('window_median_ms', 0.0):>13.2f} "
                  f"{r.get('window_p99_ms', 0.0):>7.2f} {r['lost']:>5}", flush=True)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(rows, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
