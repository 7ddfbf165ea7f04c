"""What the controller's OPC UA client costs the daemon: CPU and memory with ``[controller]`` and without.

Two daemons run side by side over the same windows, so that both see the same contention on a shared machine:
``ballbar run`` on the in-process simulator (``sim:?rate=RATE``, MCAP on, Zenoh and Rerun off, each test's fit in
the analysis thread) without a controller, and the same with ``[controller]`` connected to the simulated CNC
(:mod:`ballbar.tools.simcnc`, its own process, values changing at ``--update-hz``: six positions and the
channel's values).  Per window, each daemon's CPU (utime + stime of its whole thread group, from ``/proc``) as %
of one core and its resident memory; the difference is the controller's cost.  Then the controller's values
recorded per second (from the MCAP files), to show it was fed.

    python -m ballbar.tools.bench.bench_controller                  # 1 kHz, positions at 50 Hz, 3 x 30 s
    python -m ballbar.tools.bench.bench_controller --window-s 10 --windows 1    # a smoke test

Exit code 0, 1 when a process failed, 2 on a usage error.
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from ballbar.tools.bench.daemon_usage import CLK_TCK, snapshot


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _daemon(state: Path, rate: float, endpoint: str | None) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", f"sim:?rate={rate:g}&speedup=1&repeat=0",
           "--state-dir", str(state), "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"',
           "--set", "daemon.analysis_worker=false", "--set", f"plan.sample_hz={rate:g}"]
    if endpoint is not None:
        cmd += ["--set", f'controller.endpoint="{endpoint}"']
    log = open(state.with_suffix(".log"), "wb")  # noqa: SIM115 - the child holds it
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"))


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_controller", description=__doc__.split("\n\n")[0])
    p.add_argument("--rate", type=float, default=1000.0, help="the bar's sample rate (Hz)")
    p.add_argument("--update-hz", type=float, default=50.0, help="how often the CNC's values change (Hz)")
    p.add_argument("--window-s", type=float, default=30.0)
    p.add_argument("--windows", type=int, default=3)
    p.add_argument("--warmup-s", type=float, default=10.0)
    args = p.parse_args(argv)
    if not args.window_s > 0 or args.windows < 1 or not 15.625 <= args.rate <= 10_000:
        print("bench_controller: --window-s > 0, --windows >= 1, --rate within 15.625..10000", file=sys.stderr)
        return 2
    from ballbar.daemon.mcap import list_recordings, read_controller

    work = Path(tempfile.mkdtemp(prefix="bench-controller-"))
    port = _port()
    cnc = subprocess.Popen([sys.executable, "-m", "ballbar.tools.simcnc", "--port", str(port), "--update-hz",
                            f"{args.update_hz:g}", "--exit-on-eof", "--idle-s", "2"],
                           stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert cnc.stdout is not None
    endpoint = cnc.stdout.readline().strip()
    procs = {"without": _daemon(work / "without", args.rate, None), "with": _daemon(work / "with", args.rate, endpoint)}
    code = 0
    rows: list[dict[str, float]] = []
    try:
        time.sleep(args.warmup_s)
        t_start = time.time()
        for _ in range(args.windows):
            a = {k: snapshot(pr.pid) for k, pr in procs.items()}
            time.sleep(args.window_s)
            b = {k: snapshot(pr.pid) for k, pr in procs.items()}
            row: dict[str, float] = {}
            for k in procs:
                sa, sb = a[k], b[k]
                if sa is None or sb is None:
                    print(f"bench_controller: the daemon {k} the controller has gone", file=sys.stderr)
                    return 1
                row[f"cpu_{k}"] = 100.0 * (sb.ticks - sa.ticks) / CLK_TCK / (sb.t - sa.t)
                row[f"rss_{k}"] = sb.rss_kib / 1024
            rows.append(row)
        t_end = time.time()
    finally:
        for pr in procs.values():
            pr.terminate()
        for k, pr in procs.items():
            if pr.wait(15) != 0:
                print(f"bench_controller: the daemon {k} the controller exited {pr.returncode}", file=sys.stderr)
                code = 1
        if cnc.stdin is not None:
            cnc.stdin.close()
        cnc.wait(15)
    msgs = read_controller(list_recordings(work / "with" / "recordings"))
    n = sum(len(m["values"]) for m in msgs if t_start <= _wall(m["t_wall"]) <= t_end)
    print(f"rate {args.rate:g} Hz, CNC values changing at {args.update_hz:g} Hz, {args.windows} x {args.window_s:g} s")
    print("window | CPU without (% core) | CPU with | difference | RSS without (MiB) | RSS with")
    for i, r in enumerate(rows, 1):
        print(f"{i} | {r['cpu_without']:.2f} | {r['cpu_with']:.2f} | {r['cpu_with'] - r['cpu_without']:+.2f} | "
              f"{r['rss_without']:.1f} | {r['rss_with']:.1f}")
    diffs = [r["cpu_with"] - r["cpu_without"] for r in rows]
    spread = f" (sd {statistics.stdev(diffs):.2f})" if len(diffs) > 1 else ""
    print(f"mean difference {statistics.fmean(diffs):+.2f} % of a core{spread}; controller values recorded "
          f"{n / (t_end - t_start):.0f}/s")
    return code


def _wall(text: str) -> float:
    import datetime as dt

    return dt.datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


if __name__ == "__main__":
    sys.exit(main())
