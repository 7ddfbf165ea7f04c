"""A whole recording in one chunk: the analysis works through it in bounded pieces, with the same answers.

``ballbar analyze`` feeds a file's samples to the analyzer at once.  The time
axis is then checked :data:`~ballbar.analysis.timeaxis.CHECK_BLOCK` samples at
a time, the detector looks for the next level crossing in growing windows
(:data:`~ballbar.analysis.detect.FIND_FIRST` first) and keeps views of the
recording instead of a copy.  Here the pieces are shrunk and the answers
compared with the unshrunk ones; and the peak memory of ``ballbar analyze`` on
a long CSV is measured against its samples.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from masksynth import FULL_TRUTH, mask_recording

from ballbar.analysis import AnalysisOptions, MachineConfig, detect, engine, timeaxis
from ballbar.analysis.engine import TestAnalyzer, analyze_recording
from ballbar.analysis.errors import DataError
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.timeaxis import TimeAxis, TimeAxisError, positive_steps
from ballbar.daemon.recordings import analyze, analyze_file, load_recording, outcomes

PLAN = TestPlan(sample_hz=100)


def stream(rng: np.random.Generator, n: int) -> np.ndarray:
    """Times at 1 kHz with jitter, repeated stamps, gaps and (rarely) a clock that runs back."""
    steps = 1e-3 + rng.normal(0.0, 2e-4, n)
    steps[rng.random(n) < 0.01] = 0.0
    steps[rng.random(n) < 0.002] *= 20.0
    steps[rng.random(n) < 0.0005] = -0.05
    return np.cumsum(steps)


def run_axis(t: np.ndarray, cuts: list[int], marks: set[int]) -> tuple[list[object], dict[str, object]]:
    ax = TimeAxis()
    seen: list[object] = []
    for a, b in zip([0, *cuts], [*cuts, t.size], strict=True):
        if a in marks:
            ax.mark(f"told at {a}")
        try:
            seen.append(ax.check(t[a:b]))
        except TimeAxisError as err:
            seen.append((str(err), err.index))
    state = {k: getattr(ax, k) for k in ("n", "last_t", "max_t", "first_t", "forward_steps", "period_s",
                                         "_since_median")}
    state["_recent"] = ax._recent.tolist()
    return seen, state


@pytest.mark.parametrize("seed", range(4))
def test_time_axis_in_small_blocks_is_the_same(seed: int, monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(seed)
    t = stream(rng, 40_000)
    # chunks of a live stream (a few samples) and whole stretches (more than the period's window)
    cuts = sorted(set(rng.integers(1, t.size, 30).tolist()) | {5, 9, 20, 25_000})
    marks = set(rng.choice(cuts, 4).tolist())
    whole = run_axis(t, cuts, marks)
    assert any(isinstance(s, tuple) for s in whole[0]) and any(isinstance(s, list) and s for s in whole[0])
    for block in (1, 3, 1000):
        monkeypatch.setattr(timeaxis, "CHECK_BLOCK", block)
        assert run_axis(t, cuts, marks) == whole


def test_positive_steps_in_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    t = stream(np.random.default_rng(9), 10_000)
    for before in (None, float(t[0]) - 0.5, float(t[0]) + 0.5):
        full = np.diff(t if before is None else np.concatenate(([before], t)))
        want = full[full > 0]
        for block in (1, 7, 1 << 20):
            monkeypatch.setattr(timeaxis, "CHECK_BLOCK", block)
            assert np.array_equal(positive_steps(t, before), want)


@pytest.fixture(scope="module")
def two_tests() -> tuple[np.ndarray, np.ndarray]:
    """Two tests a minute apart, the bar standing at R + f between them."""
    t, L = mask_recording(PLAN, FULL_TRUTH, fs=100.0, noise_um=0.1)
    rng = np.random.default_rng(3)
    wait = np.arange(1, 6000) * 0.01
    R, f = PLAN.radius_mm, PLAN.feed_in_mm
    t2 = np.concatenate((t, t[-1] + wait, t[-1] + wait[-1] + 0.01 + t))
    L2 = np.concatenate((L, R + f + rng.normal(0.0, 1e-4, wait.size), L + rng.normal(0.0, 1e-4, L.size)))
    return t2, L2


def test_detection_in_small_windows_and_on_borrowed_samples_is_the_same(
    two_tests: tuple[np.ndarray, np.ndarray], monkeypatch: pytest.MonkeyPatch
) -> None:
    t, L = two_tests
    t0, L0 = t.copy(), L.copy()
    whole = analyze_recording(t, L, PLAN)
    assert np.array_equal(t, t0) and np.array_equal(L, L0)  # the samples are borrowed, not changed
    assert [r["kind"] for r in whole].count("test") == 2
    dump = json.dumps(whole, sort_keys=True)
    monkeypatch.setattr(detect, "FIND_FIRST", 1)
    assert json.dumps(analyze_recording(t, L, PLAN), sort_keys=True) == dump
    # copied, not borrowed: the same
    an = TestAnalyzer(PLAN)
    out = an.feed(t, L) + an.finish()
    assert json.dumps(out, sort_keys=True) == dump


def write_csv(path: Path, t: np.ndarray, L: np.ndarray) -> Path:
    with open(path, "w", encoding="ascii") as fh:
        fh.write("t_s,length_mm\n")
        fh.write("\n".join(np.char.add(np.char.add(np.char.mod("%.4f", t), ","), np.char.mod("%.6f", L)).tolist()))
        fh.write("\n")
    return path


def test_the_test_asked_for_is_fitted_alone_and_gives_the_whole_analysis_result(
    two_tests: tuple[np.ndarray, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ballbar analyze --test N`` (and the report) fit only test N of a recording: the others are found, not
    fitted, and N's result is the one the analysis of every test gives."""
    path = write_csv(tmp_path / "two.csv", *two_tests)
    machine, options = MachineConfig(), AnalysisOptions()
    everything = outcomes(analyze(load_recording(path), PLAN, machine, options))
    assert [e["status"] for e in everything] == ["complete", "complete"]
    fitted: list[float] = []
    whole_fit = engine.analyze_test

    def counted(*args: object) -> dict[str, object]:
        fitted.append(args[5].t_s)  # type: ignore[attr-defined]  # the feed-in
        return whole_fit(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(engine, "analyze_test", counted)
    for n in (1, 2):
        fitted.clear()
        got = analyze_file(path, PLAN, machine, options, test=n)
        want = everything[n - 1]["result"]
        assert fitted == [want["timing"]["feed_in_s"]]
        assert got["source"]["tests_found"] == 2
        assert json.dumps({k: v for k, v in got.items() if k != "source"}, sort_keys=True) == json.dumps(
            {k: v for k, v in want.items() if k != "source"}, sort_keys=True)
    statuses = [e["status"] for e in outcomes(analyze(load_recording(path), PLAN, machine, options, only=2))]
    assert statuses == ["skipped", "complete"]
    with pytest.raises(DataError, match="holds 2 test"):
        analyze_file(path, PLAN, machine, options, test=3)
    with pytest.raises(ValueError, match="circles=False"):
        TestAnalyzer(PLAN, only=1)


def analyze_growth(path: Path) -> int:
    """How far ``ballbar analyze PATH --json`` raises a fresh process's peak memory (bytes) above its imports."""
    script = textwrap.dedent(f"""
        import contextlib, io, json
        from ballbar.daemon.cli import main
        def status(key):
            with open("/proc/self/status") as fh:
                return next(int(ln.split()[1]) * 1024 for ln in fh if ln.startswith(key + ":"))
        before = status("VmRSS")
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            code = main(["analyze", {str(path)!r}, "--sample-hz", "100", "--json"])
        assert code == 0 and json.loads(out.getvalue())["source"]["tests_found"] == 1
        print(status("VmHWM") - before)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return int(proc.stdout.strip().splitlines()[-1])


def test_analyze_memory_is_bounded(tmp_path: Path) -> None:
    """``ballbar analyze`` on 1.5 M rows (one test, then hours of standing): per extra row, the samples and a little.

    Measured against the same test alone, which costs the analysis's lazy imports and the fit.
    """
    t, L = mask_recording(PLAN, FULL_TRUTH, fs=100.0, noise_um=0.1)
    n = 1_500_000
    k = np.arange(1, n - t.size + 1)
    long_t = np.concatenate((t, t[-1] + 0.01 * k))
    long_L = np.concatenate((L, PLAN.radius_mm + PLAN.feed_in_mm + 1e-4 * np.sin(0.1 * k)))
    grown = analyze_growth(write_csv(tmp_path / "long.csv", long_t, long_L)) - analyze_growth(
        write_csv(tmp_path / "one.csv", t, L))
    samples = 16 * (n - t.size)  # t and L
    assert grown < 3 * samples + 60e6, f"analyze grew {grown / 1e6:.0f} MB more for {samples / 1e6:.0f} MB of samples"


def test_bench_csv_runs(capsys: pytest.CaptureFixture[str]) -> None:
    from ballbar.tools.bench import bench_csv

    assert bench_csv.main(["--rows", "3000", "--sample-hz", "100", "--modes", "read"]) == 0
    out = capsys.readouterr().out
    assert "3000 rows" in out and " read " in out and "peak" in out
