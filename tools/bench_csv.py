"""Benchmark of a long CSV recording: peak memory and wall time of reading it and of ``ballbar analyze``.

Writes ``--rows`` samples of simulated tests back to back (``ballbar.tools.simulator``,
``--sample-hz``, LVDT noise and a little backlash) as ``t_s,length_mm`` to a temporary
directory, or takes an existing file (``--csv``), then runs in a fresh process each:

- ``imports``: the interpreter with the analysis imported, nothing read (the floor)
- ``read``: :func:`~ballbar.daemon.recordings.read_csv` of the file
- ``analyze``: ``ballbar analyze FILE --sample-hz R --json`` (every test in the file is analysed)

and reports each one's peak resident set (its ``VmHWM`` as it exits) and wall time.
``--python`` adds the same runs with another interpreter, e.g. a virtual environment
of an older checkout, for a before/after on one file.

Run: ``python -m ballbar.tools.bench_csv --rows 10000000 [--python ../old/.venv/bin/python]``
(10 M rows at 1 kHz: 282 MB of CSV, 65 tests; about a minute to write, five to analyse.)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ballbar.analysis.plan import TestPlan
from ballbar.tools.simulator import MachineModel, iter_tests, write_csv

# Each run records its own peak (VmHWM) as it exits: the rusage of a child counts the parent's pages it
# was forked with.
_PEAK = """
import atexit, os
def _peak():
    with open("/proc/self/status") as fh:
        kb = next(int(ln.split()[1]) for ln in fh if ln.startswith("VmHWM:"))
    with open(os.environ["BENCH_CSV_PEAK"], "w") as out:
        out.write(str(kb))
atexit.register(_peak)
"""
MODES = {
    "imports": "import ballbar.daemon.cli, ballbar.daemon.recordings, ballbar.analysis.engine",
    "read": "import sys; from ballbar.daemon.recordings import read_csv; read_csv(sys.argv[1])",
    "analyze": "import runpy, sys\n"
               "sys.argv[0] = 'ballbar'\n"
               "runpy.run_module('ballbar.daemon.cli', run_name='__main__')",
}


def make_csv(path: Path, rows: int, sample_hz: float, seed: int = 0) -> int:
    """``rows`` samples of simulated tests on one clock (the last one cut short); returns the tests begun."""
    plan = TestPlan(sample_hz=sample_hz)
    machine = MachineModel(noise_um=0.2, backlash_x_um=4.0, squareness_urad=20.0, jitter_s=0.1 / sample_hz)
    done = 0
    for i, res in enumerate(iter_tests(plan, machine, sample_hz, seed)):
        take = min(res.t_s.size, rows - done)
        write_csv(str(path), res.t_s[:take], res.length_mm[:take], append=i > 0)
        done += take
        if done >= rows:
            return i + 1
    raise AssertionError("unreachable")  # pragma: no cover - iter_tests runs forever


def measure(python: str, mode: str, csv: Path, sample_hz: float) -> dict[str, Any]:
    """Peak RSS (MB) and wall time (s) of one run in a fresh process."""
    args = [python, "-c", _PEAK + MODES[mode]]
    if mode == "read":
        args.append(str(csv))
    elif mode == "analyze":
        args += ["analyze", str(csv), "--sample-hz", f"{sample_hz:g}", "--json"]
    with tempfile.TemporaryDirectory(prefix="bench_csv.") as tmp:
        peak = Path(tmp) / "peak"
        t0 = time.perf_counter()
        proc = subprocess.run(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, check=False,
                              env={**os.environ, "BENCH_CSV_PEAK": str(peak)})
        wall = time.perf_counter() - t0
        kb = int(peak.read_text()) if peak.exists() else 0
    tail = proc.stderr.strip().splitlines()[-1:]
    return {"python": python, "mode": mode, "peak_rss_mb": kb / 1024.0, "wall_s": wall, "exit": proc.returncode,
            "stderr": tail[0] if proc.returncode and tail else ""}


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m ballbar.tools.bench_csv",
        description="Peak memory and wall time of reading a long CSV recording and of ballbar analyze on it.",
    )
    p.add_argument("--rows", type=int, default=2_000_000, help="samples to write (default 2 M)")
    p.add_argument("--sample-hz", type=float, default=1000.0)
    p.add_argument("--csv", type=Path, help="an existing t_s,length_mm file instead (--rows is then ignored)")
    p.add_argument("--keep", type=Path, help="write the CSV here and keep it")
    p.add_argument("--python", action="append", default=[], help="another interpreter to run too (repeatable)")
    p.add_argument("--modes", default="imports,read,analyze", help="comma-separated: imports, read, analyze")
    p.add_argument("--json", type=Path, help="write the figures here too")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if any(m not in MODES for m in modes):
        print(f"unknown mode in {args.modes!r} (known: {', '.join(MODES)})", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory(prefix="bench_csv.") as tmp:
        csv = args.csv or args.keep or Path(tmp) / "recording.csv"
        if args.csv is None:
            t0 = time.perf_counter()
            tests = make_csv(csv, args.rows, args.sample_hz)
            print(f"wrote {csv}: {args.rows} rows, {csv.stat().st_size / 1e6:.0f} MB, {tests} tests "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
        rows = []
        for python in [sys.executable, *args.python]:
            for mode in modes:
                r = measure(python, mode, csv, args.sample_hz)
                rows.append(r)
                note = f"  exit {r['exit']}: {r['stderr']}" if r["exit"] else ""
                print(f"{python}  {mode:8s} peak {r['peak_rss_mb']:7.0f} MB  {r['wall_s']:7.1f} s{note}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"csv": str(csv), "sample_hz": args.sample_hz, "runs": rows}, indent=2) + "\n")
    return 0 if all(r["exit"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
