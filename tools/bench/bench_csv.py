"""Benchmark of a long CSV recording: peak memory and wall time of reading it and of ``ballbar analyze``.

Writes ``--rows`` samples of simulated tests back to back (``ballbar.tools.simulator``,
``--sample-hz``, LVDT noise and a little backlash) as ``t_s,length_mm`` to a temporary
directory, or takes an existing file (``--csv``), then runs in a fresh process each:

- ``imports``: the interpreter with the analysis imported, nothing read (the floor)
- ``read``: :func:`~ballbar.daemon.recordings.read_csv` of the file
- ``analyze``: ``ballbar analyze FILE --sample-hz R --json`` (every test in the file is analysed)

and reports each one's peak resident set (its ``VmHWM`` as it exits) and wall time.
``--python`` adds the same runs with another interpreter, e.g. a virtual environment
of an older checkout, for a before/after on one file; ``--repeat`` alternates them and
gives medians.  ``--shape`` takes a hostile file instead (a 200 MB line of NUL bytes,
2 GB without a newline, with or without the header: :data:`SHAPES`); every run's
address space is capped (``--cap-gb``), so that code that cannot read it in bounded
memory fails with a MemoryError at the cap instead of taking the machine.

Run: ``python -m ballbar.tools.bench.bench_csv --rows 10000000 [--python ../old/.venv/bin/python]``
(10 M rows at 1 kHz: 282 MB of CSV, 65 tests; about a minute to write, five to analyse.)
``python -m ballbar.tools.bench.bench_csv --shape nul-line --modes analyze --python ../old/.venv/bin/python``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from ballbar.analysis.plan import TestPlan
from ballbar.daemon import procfs
from ballbar.tools.simulator import MachineModel, iter_tests

# Each run records its own peak (VmHWM) as it exits: the rusage of a child counts the parent's pages it
from ballbar.tools.simulator_cli import write_csv

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


def peak_run(python: str, mode: str, args: Sequence[str], cap_bytes: int | None = None) -> dict[str, Any]:
    """Run ``mode`` (:data:`MODES`) with ``args`` in a fresh process: its peak RSS (MB), wall time (s), exit code,
    stdout and stderr.

    The peak is the process's own ``VmHWM`` as it exits, or, if it is killed, the last ``VmHWM`` read while it
    ran (every 20 ms; the rusage of a child counts the parent's pages it was forked with).  ``cap_bytes``
    limits its address space (``RLIMIT_AS``): a file the code under test cannot read in bounded memory then
    fails with a MemoryError instead of taking the machine's memory.
    """
    with tempfile.TemporaryDirectory(prefix="bench_csv.") as tmp:
        peak, out, err = Path(tmp) / "peak", Path(tmp) / "stdout", Path(tmp) / "stderr"
        t0 = time.perf_counter()
        with open(out, "wb") as out_fh, open(err, "wb") as err_fh:
            proc = subprocess.Popen([python, "-c", _PEAK + MODES[mode], *args], stdout=out_fh,
                                    stderr=err_fh, env={**os.environ, "BENCH_CSV_PEAK": str(peak)})
            if cap_bytes is not None:
                resource.prlimit(proc.pid, resource.RLIMIT_AS, (cap_bytes, cap_bytes))
            polled = 0
            while proc.poll() is None:
                polled = max(polled, _hwm_kb(proc.pid))
                time.sleep(0.02)
        wall = time.perf_counter() - t0
        kb = int(peak.read_text()) if peak.exists() and peak.read_text() else polled
        stdout, stderr = out.read_text(errors="replace"), err.read_text(errors="replace")
    return {"python": python, "mode": mode, "peak_rss_mb": kb / 1024.0, "wall_s": wall, "exit": proc.returncode,
            "stdout": stdout, "stderr": stderr}


def _hwm_kb(pid: int) -> int:
    try:
        return procfs.kib(procfs.status(pid).get("VmHWM", "0"))
    except (OSError, ValueError):
        return 0


def measure(python: str, mode: str, csv: Path, sample_hz: float, cap_bytes: int | None = None) -> dict[str, Any]:
    """Peak RSS (MB) and wall time (s) of one run in a fresh process (``stderr``: its last line if it failed)."""
    args: list[str] = []
    if mode == "read":
        args.append(str(csv))
    elif mode == "analyze":
        args += ["analyze", str(csv), "--sample-hz", f"{sample_hz:g}", "--json"]
    r = peak_run(python, mode, args, cap_bytes)
    tail = r["stderr"].strip().splitlines()[-1:]
    r["stderr"] = tail[0] if r["exit"] and tail else ""
    del r["stdout"]
    return r


SHAPES = {
    # what the file is: (its head, its size); the rest NUL bytes (a sparse file: it takes no disk)
    "nul-line": (b"t_s,length_mm\n0,100\n", 200 << 20),  # a 200 MB line of NUL bytes after one sample
    "no-newline": (b"", 2 << 30),  # 2 GB without a newline
    "header-no-newline": (b"t_s,length_mm\n", 2 << 30),  # the header, then 2 GB without a newline
}


def make_shape(path: Path, shape: str) -> None:
    head, size = SHAPES[shape]
    path.write_bytes(head)
    os.truncate(path, size)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m ballbar.tools.bench.bench_csv",
        description="Peak memory and wall time of reading a long CSV recording and of ballbar analyze on it.",
    )
    p.add_argument("--rows", type=int, default=2_000_000, help="samples to write (default 2 M)")
    p.add_argument("--sample-hz", type=float, default=1000.0)
    p.add_argument("--csv", type=Path, help="an existing t_s,length_mm file instead (--rows is then ignored)")
    p.add_argument("--keep", type=Path, help="write the CSV here and keep it")
    p.add_argument("--python", action="append", default=[], help="another interpreter to run too (repeatable)")
    p.add_argument("--modes", default="imports,read,analyze", help="comma-separated: imports, read, analyze")
    p.add_argument("--shape", choices=sorted(SHAPES), help="instead of a recording, a hostile file (see SHAPES)")
    p.add_argument("--cap-gb", type=float, default=8.0, help="each run's address space, GB (RLIMIT_AS)")
    p.add_argument("--repeat", type=int, default=1, help="runs of each mode and interpreter (medians)")
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
        if args.shape:
            csv = Path(tmp) / f"{args.shape}.csv"
            make_shape(csv, args.shape)
            print(f"wrote {csv}: {args.shape}, {csv.stat().st_size / 1e6:.0f} MB (sparse)", flush=True)
        elif args.csv is None:
            t0 = time.perf_counter()
            tests = make_csv(csv, args.rows, args.sample_hz)
            print(f"wrote {csv}: {args.rows} rows, {csv.stat().st_size / 1e6:.0f} MB, {tests} tests "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)
        rows = []
        cap = int(args.cap_gb * (1 << 30))
        for i in range(args.repeat):
            pythons = [sys.executable, *args.python]
            for python in pythons if i % 2 == 0 else pythons[::-1]:
                for mode in modes:
                    r = measure(python, mode, csv, args.sample_hz, cap)
                    rows.append(r)
                    note = f"  exit {r['exit']}: {r['stderr']}" if r["exit"] else ""
                    print(f"{python}  {mode:8s} peak {r['peak_rss_mb']:7.0f} MB  {r['wall_s']:7.2f} s{note}",
                          flush=True)
        if args.repeat > 1:
            for python in [sys.executable, *args.python]:
                for mode in modes:
                    mine = [r for r in rows if r["python"] == python and r["mode"] == mode]
                    print(f"median {python}  {mode:8s} peak "
                          f"{statistics.median(r['peak_rss_mb'] for r in mine):7.0f} MB  "
                          f"{statistics.median(r['wall_s'] for r in mine):7.2f} s  ({len(mine)} runs)")
    if args.json:
        args.json.write_text(json.dumps({"csv": str(csv), "sample_hz": args.sample_hz, "runs": rows}, indent=2) + "\n")
    return 0 if args.shape or all(r["exit"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
