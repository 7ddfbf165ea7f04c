"""A rogue peer's flood on ``control/next_plan``: what the daemon takes, drops, records, logs and keeps in history.

``ballbar run`` on the ``sim:`` source sped up (Zenoh on a port of its own, MCAP on, Rerun off) is left to finish a
test; then a Zenoh client puts ``--puts`` well-shaped choices (the library's plan, names it lacks, withdrawals) as
fast as it can (``CongestionControl.BLOCK``: every one arrives), waits for the status to count them all and stops
the daemon.  One JSON object: the flood's seconds, the choices taken and dropped, what history/event holds, the
answers in the recordings and the control lines in the log.

Run::

    python -m ballbar.tools.bench.bench_control_flood --puts 5000
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from ballbar.daemon.bus import ZenohConfig
from ballbar.daemon.mcap import list_recordings, read_log
from ballbar.tools.bench.bench_diskfull import DaemonLog, stop_daemon

ANSWERS = ("plan_chosen", "plan_choice_refused")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _get(session: zenoh.Session, selector: str) -> Any:
    for reply in session.get(selector, timeout=5):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return None


def _wait(pred: Callable[[], bool], timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise TimeoutError("the daemon did not get there in time")
        time.sleep(0.1)


def measure(puts: int, speedup: float, workdir: Path) -> dict[str, Any]:
    port = _free_port()
    source = f"sim:?rate=1000&speedup={speedup:g}&repeat=0"
    cmd = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", source,
           "--machine-id", "flood", "--state-dir", str(workdir / "state"), "--set", 'rerun.mode="off"',
           "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "--set", "daemon.status_interval_s=0.5"]
    env = {k: v for k, v in os.environ.items() if k != "BALLBAR_CONFIG"} | {"PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stderr is not None
    log = DaemonLog(proc.stderr)
    try:
        log.wait_for("ready: reading", 60.0)
        conf = ZenohConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]).to_zenoh_config()
        with zenoh.open(conf) as s:
            def history() -> list[dict[str, Any]]:
                got = _get(s, "ballbar/flood/history/event?limit=1000")
                return list(got["results"]) if got else []

            def zstats() -> dict[str, Any]:
                got = _get(s, "ballbar/flood/last/status")
                return dict(got["outputs"]["zenoh"]) if got else {}

            _wait(lambda: any(e.get("event") == "feed_out" for e in history()), 120.0)
            t0 = time.monotonic()
            for i in range(puts):
                s.put("ballbar/flood/control/next_plan",
                      ["default", f"nope{i}", json.dumps({"plan": None}), json.dumps({"plan": f"p{i}"})][i % 4],
                      congestion_control=zenoh.CongestionControl.BLOCK)
            put_s = time.monotonic() - t0
            _wait(lambda: zstats().get("controls", 0) + zstats().get("controls_dropped", 0) >= puts, 60.0)
            counted_s = time.monotonic() - t0
            z, held = zstats(), history()
    finally:
        code = stop_daemon(proc)
    lines = [ln for ln in log.text().splitlines() if "next_plan" in ln or "next plan" in ln]
    recorded = [e for p in list_recordings(workdir / "state" / "recordings")
                for e in read_log(p, samples=False).events if e.get("event") in ANSWERS]
    return {
        "puts": puts, "exit": code, "put_s": round(put_s, 2), "counted_s": round(counted_s, 2),
        "taken": z.get("controls"), "dropped": z.get("controls_dropped"),
        "history_event": len(held), "history_machine": sum(e.get("event") not in ANSWERS for e in held),
        "history_answers": sum(e.get("event") in ANSWERS for e in held),
        "mcap_answers": len(recorded), "log_lines": len(lines), "flood_lines": sum("a flood" in ln for ln in lines),
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--puts", type=int, default=5000)
    ap.add_argument("--speedup", type=float, default=20.0)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ballbar-flood-") as tmp:
        print(json.dumps(measure(args.puts, args.speedup, Path(tmp))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
