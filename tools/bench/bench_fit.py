"""Benchmark: one test's analysis, alone and as ``ballbar analyze`` makes it, against a baseline in the same run.

For each sample rate, a simulated test with every pattern of the library
(``MACHINE``, noisy) is analysed as ``ballbar analyze`` does (detection, the
nonlinear parameters, the joint fit with its corrections, ranking, ISO 230-4,
noise, checks; no provisional circles):

- ``analysis``: the CPU time of :func:`ballbar.analysis.engine.analyze_recording`
  in this process (median of ``--repeats``), with the misfit evaluations and
  designs the fit reports;
- ``command``: the wall time of ``python -m ballbar.daemon.cli analyze FILE
  --json`` on the same test written as CSV, less that of ``python -c "import
  numpy, scipy.linalg"`` measured beside it (starting Python and the numerical
  libraries, which no change of ours removes).

``--baseline PYTHON``: the same measurements with another interpreter (another
checkout's venv, e.g. the code before a change), interleaved with ours so that
both see the same machine; ratios are ours over the baseline's.  Run:
``python -m ballbar.tools.bench.bench_fit --repeats 7 --baseline ../base/.venv/bin/python``.
"""

from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

from ballbar.analysis import TestPlan  # noqa: E402
from ballbar.tools.simulator import MachineModel, simulate  # noqa: E402
from ballbar.tools.simulator_cli import write_csv  # noqa: E402

MACHINE = MachineModel(
    centre_x_um=12.0, backlash_x_um=4.0, backlash_y_um=2.0, kv_y_per_s=32.0, master_slave_a_um=1.0,
    squareness_urad=15.0, scale_x_ppm=5.0, lateral_play_x_um=1.0, straightness_y_um=0.8, spike_x_um=2.0,
    cyclic_x_um=0.3, pitch_x_mm=10.0, drift_um_per_min=0.2, noise_um=0.2,
)

# Run by each interpreter on the saved test: the analysis' CPU times and what the fit reports of its work.
_ANALYSIS = """
import json, sys, time, os
for v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(v, "1")
import numpy as np
from ballbar.analysis import AnalysisOptions, MachineConfig, TestPlan
from ballbar.analysis.engine import analyze_recording
data = np.load(sys.argv[1])
plan, machine = TestPlan(sample_hz=float(data["fs"])), MachineConfig(pitch_x_mm=10.0)
times, res = [], None
for _ in range(int(sys.argv[2])):
    t0 = time.process_time()
    out = analyze_recording(data["t"], data["L"], plan, machine, AnalysisOptions(), circles=False)
    times.append(time.process_time() - t0)
    res = [r for r in out if r["kind"] == "test"][0]
fit = res["fit"]
print(json.dumps({"cpu_s": times, "evaluations": fit.get("evaluations"), "designs": fit.get("designs")}))
"""


def _analysis(python: str, npz: Path, repeats: int) -> dict[str, Any]:
    out = subprocess.run([python, "-c", _ANALYSIS, str(npz), str(repeats)], capture_output=True, text=True,
                         check=True)
    return dict(json.loads(out.stdout.strip().splitlines()[-1]))


def _wall(cmd: Sequence[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, capture_output=True, check=True)
    return time.perf_counter() - t0


_COMPILE = (
    "import compileall, pathlib, re, ballbar.daemon as d\n"
    "root = pathlib.Path(d.__file__).resolve().parents[1]\n"
    "compileall.compile_dir(root, quiet=1, rx=re.compile(r'[/\\\\](\\.venv|\\.git|tests)[/\\\\]'))\n"
)


def _compile(python: str) -> None:
    """Write the checkout's bytecode, so that each command is timed as it runs installed (``PYTHONDONTWRITEBYTECODE``
    or a read-only tree would otherwise have it compile every module at every run)."""
    subprocess.run([python, "-c", _COMPILE], capture_output=True, check=True)


def _command(python: str, csv: Path, fs: float, repeats: int) -> tuple[float, float]:
    """Median wall times (s) of ``ballbar analyze`` on ``csv`` and of starting Python with numpy and scipy.linalg,
    alternated."""
    analyze = [python, "-m", "ballbar.daemon.cli", "analyze", str(csv), "--json", "--sample-hz", f"{fs:g}",
               "--pitch-x-mm", "10"]
    start = [python, "-c", "import numpy, scipy.linalg"]
    a, s = [], []
    for _ in range(repeats):
        a.append(_wall(analyze))
        s.append(_wall(start))
    return statistics.median(a), statistics.median(s)


def bench(fs: float, repeats: int, pythons: dict[str, str], work: Path) -> dict[str, dict[str, float]]:
    sim = simulate(TestPlan(sample_hz=fs), MACHINE, fs)
    npz = work / f"test_{fs:g}.npz"
    np.savez(npz, t=sim.t_s, L=sim.length_mm, fs=fs)
    csv = work / f"test_{fs:g}.csv"
    write_csv(str(csv), sim.t_s, sim.length_mm)
    out: dict[str, dict[str, float]] = {name: {} for name in pythons}
    for name, python in pythons.items():  # one after the other, each a fresh process: the same machine
        got = _analysis(python, npz, repeats)
        cpu = [float(v) for v in got["cpu_s"]]
        out[name]["analysis_s"] = statistics.median(cpu)
        out[name]["evaluations"] = float(got["evaluations"]) if got["evaluations"] is not None else float("nan")
        out[name]["designs"] = float(got["designs"]) if got["designs"] is not None else float("nan")
    for name, python in pythons.items():
        _compile(python)
        total, start = _command(python, csv, fs, max(3, repeats // 2))
        out[name]["command_s"] = total
        out[name]["start_s"] = start
        out[name]["beyond_start_s"] = total - start
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_fit", description=__doc__.splitlines()[0])
    p.add_argument("--rates", default="15.625,1000,10000", help="sample rates (Hz), comma-separated")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--baseline", metavar="PYTHON", help="another interpreter (checkout) to measure beside this one")
    p.add_argument("--json", action="store_true", help="one JSON object of all figures")
    args = p.parse_args(argv)
    pythons = {"this": sys.executable}
    if args.baseline:
        pythons["baseline"] = args.baseline
    rates = [float(r) for r in args.rates.split(",")]
    results: dict[str, dict[str, dict[str, float]]] = {}
    with tempfile.TemporaryDirectory(prefix="bench_fit_") as tmp:
        for fs in rates:
            results[f"{fs:g}"] = bench(fs, args.repeats, pythons, Path(tmp))
            if not args.json:
                for name, r in results[f"{fs:g}"].items():
                    print(f"{fs:9.3f} Hz {name:9s} analysis {1000 * r['analysis_s']:8.1f} ms  "
                          f"evaluations {r['evaluations']:5.0f}  designs {r['designs']:5.0f}  "
                          f"command {1000 * r['command_s']:7.0f} ms  start {1000 * r['start_s']:5.0f} ms  "
                          f"beyond start {1000 * r['beyond_start_s']:7.0f} ms")
                if "baseline" in pythons:
                    a, b = results[f"{fs:g}"]["this"], results[f"{fs:g}"]["baseline"]
                    print(f"{'':13s} ratio     analysis {a['analysis_s'] / b['analysis_s']:8.2f}     "
                          f"beyond start {a['beyond_start_s'] / b['beyond_start_s']:.2f}")
                sys.stdout.flush()
    if args.json:
        print(json.dumps(results, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
