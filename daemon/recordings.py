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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.errors import BallbarError, DataError
from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan
from ballbar.analysis.timeaxis import JITTER_PERIODS, backward_steps

log = logging.getLogger(__name__)

REQUIRED = ("t_s", "length_mm")


@dataclass
class Recording:
    """What the analysis takes from a recording.

    ``t``, ``L``: the samples' times (s) and lengths (mm); ``breaks``:
    ``(index, reason)``, a discontinuity the times may not show just before
    sample ``index`` (:func:`ballbar.analysis.engine.analyze_recording`);
    ``axis``: which clock ``t`` is (``"device"``, ``"host"``, or ``"t_s"`` for
    a CSV); ``name``: the file or directory, for messages.
    """

    t: np.ndarray
    L: np.ndarray
    breaks: list[tuple[int, str]] = field(default_factory=list)
    axis: str = "t_s"
    name: str = ""


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


def is_mcap(path: str | os.PathLike[str]) -> bool:
    """An MCAP file, or a directory holding MCAP files (else: a CSV)."""
    name = os.fspath(path)
    return name.lower().endswith(".mcap") or (os.path.isdir(name) and any(Path(name).glob("*.mcap")))


def load_recording(path: str | os.PathLike[str]) -> Recording:
    """A recording for the analysis, by its file type.

    ``.mcap``: the daemon's log (:func:`ballbar.daemon.mcap_log.recording`: the
    device clock where the samples have one, else the host's; samples flagged
    over range or sensor fault left out; a killed writer's file up to its last
    whole chunk; the breaks its events report).  A directory holding ``.mcap``
    files: those files joined, in the order of their names.  Anything else: CSV.
    """
    name = os.fspath(path)
    if is_mcap(name):
        from .mcap_log import mcap_files, read_log, read_logs, recording  # here: CSV needs no MCAP machinery

        if os.path.isdir(name):
            return recording(read_logs(mcap_files(name)), name)
        return recording(read_log(name), name)
    t, L = read_csv(name)
    return Recording(t, L, [], "t_s", name)


def read_recording(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, length_mm)`` of a recording (:func:`load_recording`)."""
    rec = load_recording(path)
    return rec.t, rec.L


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


def outcomes(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per test an analysis found, in order.

    Each: ``number`` (from 1), ``feed_in_s``, ``status`` (``complete``,
    ``rejected`` or ``incomplete``), ``message`` (why not complete) and
    ``result`` (the test result, or None).
    """
    tests: dict[int, dict[str, Any]] = {}
    for r in results:
        i = r.get("test_index")
        if not isinstance(i, int):
            continue
        if r.get("event") == "feed_in":
            tests[i] = {"number": len(tests) + 1, "feed_in_s": r.get("t_s"), "status": "incomplete",
                        "message": "", "result": None}
            continue
        entry = tests.get(i)
        if entry is None:
            continue
        if r.get("kind") == "test":
            entry.update(status="complete", result=r)
        elif r.get("event") in ("test_rejected", "test_incomplete") and entry["status"] == "incomplete":
            entry.update(status="rejected" if r["event"] == "test_rejected" else "incomplete",
                         message=str(r.get("message", "")))
    return list(tests.values())


def pick_test(
    results: list[dict[str, Any]], test: int, name: str, plan: TestPlan
) -> dict[str, Any]:
    """The ``test``-th (from 1) test of an analysed recording, with ``source`` and warnings.

    A test that was rejected or left incomplete is a :class:`DataError` with
    its reason.
    """
    found = outcomes(results)
    if len(found) < test:
        raise DataError(f"{name}: holds {len(found)} test(s), test {test} asked for")
    entry = found[test - 1]
    if entry["result"] is None:
        others = [e["number"] for e in found if e["result"] is not None]
        hint = f" (complete: test {', '.join(map(str, others))}; choose with --test N)" if others else ""
        which = f"test {test} of {len(found)}: " if len(found) > 1 else ""
        raise DataError(f"{name}: {which}{entry['message'] or entry['status']}{hint}")
    return with_source(entry["result"], {"file": os.path.abspath(name), "tests_found": len(found)}, plan)


def with_source(result: dict[str, Any], source: dict[str, Any], plan: TestPlan) -> dict[str, Any]:
    """``result`` with ``source`` set, and a warning where its sample rate is not the plan's."""
    result["source"] = source
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
    """Read a recording (:func:`load_recording`), analyse it and return its ``test``-th test result."""
    rec = load_recording(path)
    return pick_test(analyze(rec, plan, machine, options, curves), test, path, plan)


def analyze(
    rec: Recording, plan: TestPlan, machine: MachineConfig, options: AnalysisOptions, curves: bool = False
) -> list[dict[str, Any]]:
    """:func:`~ballbar.analysis.engine.analyze_recording` of a recording; its errors name the recording."""
    try:
        return analyze_recording(rec.t, rec.L, plan, machine, options, curves=curves, breaks=rec.breaks)
    except DataError as err:
        if rec.name and not str(err).startswith(rec.name):
            err.args = (f"{rec.name}: {err}",)
        raise
