"""Reading recordings: CSV, and the daemon's MCAP logs (:mod:`.mcap_log`).

CSV format: a header line naming at least the columns ``t_s`` (seconds, any
origin, increasing) and ``length_mm`` (absolute bar length in millimetres), then
one sample per line, comma separated.  Other columns are ignored; lines that
start with ``#`` are comments.  Rows out of time order by no more than timestamp
jitter (:data:`~ballbar.analysis.timeaxis.JITTER_PERIODS` median sample periods)
are sorted, with a warning; a time that runs back further, or never advances,
is an error.

Every problem is raised as :class:`~ballbar.analysis.errors.DataError` with a
one-line message that names the file and the line.
"""

from __future__ import annotations

import io
import logging
import math
import os
import warnings
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.errors import BallbarError, DataError
from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan
from ballbar.analysis.timeaxis import JITTER_PERIODS, backward_steps

log = logging.getLogger(__name__)

REQUIRED = ("t_s", "length_mm")


def open_recording(name: str) -> BinaryIO:
    """Open a recording for reading; the reasons it cannot be, as one-line DataErrors."""
    try:
        return open(name, "rb")
    except FileNotFoundError:
        raise DataError(f"{name}: no such file") from None
    except IsADirectoryError:
        raise DataError(f"{name}: is a directory, not a recording") from None
    except OSError as err:
        raise DataError(f"{name}: cannot read: {err.strerror or err}") from err


def read_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read ``(t_s, length_mm)`` from a CSV recording; sorted by time, all finite."""
    name = os.fspath(path)
    with open_recording(name) as fh:
        try:
            raw = fh.read()
        except OSError as err:
            raise DataError(f"{name}: cannot read: {err.strerror or err}") from err
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        line = raw[: err.start].count(b"\n") + 1
        raise DataError(f"{name}:{line}: not a text CSV file (byte {err.start} is not UTF-8)") from None
    lines = text.splitlines()
    header_at = next((i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")), None)
    if header_at is None:
        raise DataError(f"{name}: empty file, expected a header 't_s,length_mm' and samples")
    cols = [c.strip() for c in lines[header_at].split(",")]
    missing = [c for c in REQUIRED if c not in cols]
    if missing:
        raise DataError(
            f"{name}:{header_at + 1}: header must name the columns t_s,length_mm "
            f"(missing {', '.join(missing)}; found {lines[header_at].strip()[:60]!r})"
        )
    it, il = cols.index("t_s"), cols.index("length_mm")
    body = "\n".join(lines[header_at + 1 :])
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)  # "input contained no data": checked below
            data = np.loadtxt(
                io.StringIO(body), delimiter=",", comments="#", usecols=(it, il), ndmin=2, dtype=float
            )
    except ValueError:
        _raise_bad_line(name, lines, header_at, len(cols), (it, il))
        raise  # _raise_bad_line always raises; this keeps the type checker honest
    if data.shape[0] == 0:
        raise DataError(f"{name}: header but no samples")
    t, length = data[:, 0], data[:, 1]
    bad = ~np.isfinite(t) | ~np.isfinite(length)
    if bad.any():
        k = int(np.argmax(bad))
        line = _data_line_number(lines, header_at, k)
        what = "t_s" if not math.isfinite(t[k]) else "length_mm"
        raise DataError(f"{name}:{line}: {what} is not a finite number ({lines[line - 1].strip()[:60]!r})")
    if t.size >= 2 and not np.any(np.diff(t) > 0):
        what = f"is {t[0]:g} s in every one of the {t.size} samples" if np.all(t == t[0]) else "never increases"
        raise DataError(f"{name}: t_s {what}: no time axis to analyse")
    behind, jitter = backward_steps(t)
    if np.any(behind > jitter):
        k = int(np.argmax(behind > jitter))
        line = _data_line_number(lines, header_at, k)
        raise DataError(
            f"{name}:{line}: t_s runs backwards by {behind[k]:.6g} s (to {t[k]:.6f} s), more than timestamp "
            f"jitter ({JITTER_PERIODS:g} sample periods, {jitter:.3g} s): a clock that restarted or jumped back, "
            "or rows out of order"
        )
    if np.any(behind > 0):
        order = np.argsort(t, kind="stable")
        log.warning("%s: %d samples out of time order by at most %.3g s (timestamp jitter); sorted",
                    name, int(np.count_nonzero(behind)), float(behind.max()))
        t, length = t[order], length[order]
    return np.ascontiguousarray(t), np.ascontiguousarray(length)


def _data_line_number(lines: list[str], header_at: int, k: int) -> int:
    """1-based file line of the k-th data row (comments and blank lines skipped)."""
    seen = -1
    for i in range(header_at + 1, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            continue
        seen += 1
        if seen == k:
            return i + 1
    return len(lines)


def _raise_bad_line(name: str, lines: list[str], header_at: int, ncols: int, use: tuple[int, int]) -> None:
    for i in range(header_at + 1, len(lines)):
        s = lines[i].strip()
        if not s or s.startswith("#"):
            continue
        parts = s.split(",")
        if len(parts) < max(use) + 1:
            raise DataError(f"{name}:{i + 1}: expected {ncols} comma-separated values, got {s[:60]!r}")
        for j in use:
            try:
                float(parts[j])
            except ValueError:
                raise DataError(f"{name}:{i + 1}: not a number: {parts[j].strip()[:40]!r}") from None
    raise DataError(f"{name}: malformed CSV")


def read_recording(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, length_mm)`` of a recording, by its file type.

    ``.mcap``: the daemon's log (:func:`ballbar.daemon.mcap_log.read_mcap`: the
    device clock where the samples have one, else the host's; samples flagged
    over range or sensor fault left out; a killed writer's file up to its last
    whole chunk).  A directory holding ``.mcap`` files: those files joined, in
    the order of their names.  Anything else: CSV.
    """
    name = os.fspath(path)
    if name.lower().endswith(".mcap") or (os.path.isdir(name) and any(Path(name).glob("*.mcap"))):
        from .mcap_log import read_mcap  # imported here: reading CSV needs no MCAP machinery

        return read_mcap(name)
    return read_csv(name)


def recorded_config(path: str) -> dict[str, Any]:
    """The plan, machine and analysis a daemon recording was made with (empty for CSV).

    A directory: the newest file's configuration that has one.
    """
    if not (path.lower().endswith(".mcap") or os.path.isdir(path)):
        return {}
    from .mcap_log import mcap_files, read_log  # here: reading CSV needs no MCAP machinery

    files = mcap_files(path) if os.path.isdir(path) else [Path(path)]
    for f in reversed(files):
        try:
            configs = read_log(f, samples=False).config
        except BallbarError:
            continue  # read_recording reports what is wrong with the file
        if configs:
            return config_sections(configs)
    return {}


def config_sections(configs: list[dict[str, Any]]) -> dict[str, Any]:
    """The ``plan``, ``machine`` and ``analysis`` tables of the newest of a log's config records."""
    cfg = configs[-1].get("config", {}) if configs else {}
    return {k: dict(cfg[k]) for k in ("plan", "machine", "analysis") if isinstance(cfg.get(k), dict)}


def pick_test(
    results: list[dict[str, Any]], test: int, name: str, plan: TestPlan
) -> dict[str, Any]:
    """The ``test``-th (from 1) complete test result of an analysed recording, with ``source`` and warnings."""
    tests = [r for r in results if r["kind"] == "test"]
    problems = [r for r in results if r.get("event") in ("test_rejected", "test_incomplete")]
    if len(tests) < test:
        if problems:
            raise DataError(f"{name}: {problems[0]['message']}")
        raise DataError(f"{name}: holds {len(tests)} complete test(s), test {test} asked for")
    result = tests[test - 1]
    result["source"] = {"file": os.path.abspath(name), "tests_found": len(tests)}
    if abs(result["samples"]["sample_hz"] / plan.sample_hz - 1.0) > 0.2:
        result.setdefault("warnings", []).append(
            f"the recording samples at {result['samples']['sample_hz']:.3f} Hz, the plan says "
            f"{plan.sample_hz:g} Hz; the timestamps were used"
        )
    return result


def analyze_file(
    path: str,
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    test: int = 1,
    curves: bool = False,
) -> dict[str, Any]:
    """Read a recording (:func:`read_recording`), analyse it and return its ``test``-th test result."""
    t, L = read_recording(path)
    return pick_test(analyze_recording(t, L, plan, machine, options, curves=curves), test, path, plan)
