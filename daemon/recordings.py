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

import bisect
import codecs
import logging
import math
import os
import stat
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO, NoReturn

import numpy as np

from ballbar.analysis.engine import analyze_recording
from ballbar.analysis.errors import BallbarError, DataError
from ballbar.analysis.plan import AnalysisOptions, MachineConfig, TestPlan
from ballbar.analysis.timeaxis import JITTER_PERIODS, positive_steps

log = logging.getLogger(__name__)

REQUIRED = ("t_s", "length_mm")


@dataclass
class Recording:
    """What the analysis takes from a recording.

    ``t``, ``L``: the samples' times (s) and lengths (mm); ``breaks``:
    ``(index, reason)``, a discontinuity the times may not show just before
    sample ``index`` (:func:`ballbar.analysis.engine.analyze_recording`);
    ``axis``: which clock ``t`` is (``"device"``, ``"host"``, or ``"t_s"`` for
    a CSV); ``name``: the file or directory, for messages; ``timing``: a
    polled source's ``timing`` events, ``(t_host, uncertainty, jitter)``
    (:mod:`ballbar.analysis.polled`), stated on each result.
    """

    t: np.ndarray
    L: np.ndarray
    breaks: list[tuple[int, str]] = field(default_factory=list)
    axis: str = "t_s"
    name: str = ""
    timing: list[tuple[float, float, float]] = field(default_factory=list)


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


BLOCK_BYTES = 1 << 20  # a CSV is read, decoded and parsed this many bytes (whole lines) at a time
SCAN_ROWS = 1 << 20  # and its time axis checked this many samples at a time


def read_csv(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Read ``(t_s, length_mm)`` from a CSV recording; sorted by time, all finite.

    A bounded stream: the file is read, decoded and parsed :data:`BLOCK_BYTES`
    at a time straight into the two output arrays (16 bytes a sample), then its
    time axis is checked :data:`SCAN_ROWS` samples at a time.  Beyond the
    output it holds one block's text and, for the check, the positive time
    steps (8 bytes a sample).  The errors are those of the whole file, in the
    same order: the first bad byte or line, whichever block it lies in.
    """
    name = os.fspath(path)
    with open_recording(name) as fh:
        csv = _CsvParser(name, fh)
        csv.parse()
    t, length = csv.t, csv.L
    csv.t = csv.L = np.empty(0)
    if t.size < 2:
        return t, length
    pos = positive_steps(t)
    if pos.size == 0:
        what = f"is {t[0]:g} s in every one of the {t.size} samples" if np.all(t == t[0]) else "never increases"
        raise DataError(f"{name}: t_s {what}: no time axis to analyse")
    # backward_steps(t), a block at a time: its median period, and how far each sample lies behind the latest before
    period = float(np.median(pos, overwrite_input=True))
    del pos
    jitter = JITTER_PERIODS * period if math.isfinite(period) else 0.0
    latest, late, most = float(t[0]), 0, 0.0
    for a in range(0, t.size, SCAN_ROWS):
        seg = t[a : a + SCAN_ROWS]
        prior = np.maximum.accumulate(np.concatenate(([latest], seg[:-1])))
        latest = max(float(prior[-1]), float(seg[-1]))
        behind = np.maximum(prior - seg, 0.0)
        if np.any(behind > jitter):
            j = int(np.argmax(behind > jitter))
            raise DataError(
                f"{name}:{csv.line_of(a + j)}: t_s runs backwards by {behind[j]:.6g} s (to {seg[j]:.6f} s), more "
                f"than timestamp jitter ({JITTER_PERIODS:g} sample periods, {jitter:.3g} s): a clock that restarted "
                "or jumped back, or rows out of order"
            )
        if np.any(behind > 0):
            late += int(np.count_nonzero(behind))
            most = max(most, float(behind.max()))
    if late:
        log.warning("%s: %d samples out of time order by at most %.3g s (timestamp jitter); sorted", name, late, most)
        order = np.argsort(t, kind="stable")
        t = t[order]
        length = length[order]
    return t, length


class _CsvParser:
    """One pass over a CSV file's blocks into ``t`` and ``L``; see :func:`read_csv`.

    A block's lines are parsed by ``np.loadtxt``; only where it fails, or for
    lines with a ``#`` past their start, does Python look at lines one by one
    (:func:`_bad_line`), so that the error names the file's first bad line.
    """

    def __init__(self, name: str, fh: BinaryIO) -> None:
        self.name = name
        self.blocks = _text_blocks(fh, name)
        try:
            st = os.fstat(fh.fileno())
            self.size = st.st_size if stat.S_ISREG(st.st_mode) else 0
        except (OSError, AttributeError):  # no file descriptor: grow the arrays as the samples come
            self.size = 0
        self.lines = 0  # lines of the file before the block in hand
        self.header: list[str] | None = None
        self.use = (0, 1)
        self.t = np.empty(0)
        self.L = np.empty(0)
        self.n = 0  # samples so far
        # per block of samples: its first sample, the 0-based file line of its first line, and which of its
        # lines hold no sample (None: all do)
        self.spans: list[tuple[int, int, np.ndarray | None]] = []
        self.nonfinite: str | None = None  # the first sample with a value that is not a finite number
        self.suspect: str | None = None  # the first line loadtxt took that the line check does not (a "#" in it)

    def parse(self) -> None:
        nbytes = 0
        for text, size in self.blocks:
            nbytes += size
            lines = text.splitlines()
            first = self.lines
            self.lines += len(lines)
            if self.header is None:
                at = next((i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")), None)
                if at is None:
                    continue
                self._read_header(lines[at], first + at)
                lines, first = lines[at + 1 :], first + at + 1
            if lines:
                self._block(lines, first, "#" in text, nbytes)
        if self.header is None:
            raise DataError(f"{self.name}: empty file, expected a header 't_s,length_mm' and samples")
        if self.n == 0:
            raise DataError(f"{self.name}: header but no samples")
        if self.nonfinite is not None:
            raise DataError(self.nonfinite)
        if self.t.size != self.n:  # give back the spare capacity (in place: realloc)
            self.t.resize(self.n, refcheck=False)
            self.L.resize(self.n, refcheck=False)

    def _read_header(self, line: str, index: int) -> None:
        cols = [c.strip() for c in line.split(",")]
        missing = [c for c in REQUIRED if c not in cols]
        if missing:
            self._fail(
                f"{self.name}:{index + 1}: header must name the columns t_s,length_mm "
                f"(missing {', '.join(missing)}; found {line.strip()[:60]!r})"
            )
        self.header = cols
        self.use = (cols.index("t_s"), cols.index("length_mm"))

    def _fail(self, message: str | None) -> NoReturn:
        """Raise ``message`` once the rest of the file is read: a read or UTF-8 error there comes first."""
        for text, _ in self.blocks:
            if message is None:  # the first bad line after a block that loadtxt could not parse
                lines = text.splitlines()
                message = self._bad_line(lines, self.lines)
                self.lines += len(lines)
        raise DataError(message or f"{self.name}: malformed CSV")

    def _bad_line(self, lines: list[str], first: int, hashed: bool = False) -> str | None:
        """The error of the first line of ``lines`` (file line ``first`` + 1 on) with too few values or not a number.

        ``hashed``: look only at lines with a ``#`` (loadtxt took the others as they are).
        """
        assert self.header is not None
        for i, ln in enumerate(lines):
            if hashed and "#" not in ln:
                continue
            s = ln.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split(",")
            if len(parts) < max(self.use) + 1:
                return (f"{self.name}:{first + i + 1}: expected {len(self.header)} comma-separated values, "
                        f"got {s[:60]!r}")
            for j in self.use:
                try:
                    float(parts[j])
                except ValueError:
                    return f"{self.name}:{first + i + 1}: not a number: {parts[j].strip()[:40]!r}"
        return None

    def _block(self, lines: list[str], first: int, hashed: bool, nbytes: int) -> None:
        """Parse the sample lines ``lines``, the first of them the file's line ``first`` + 1."""
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "input contained no data": see parse()
                data = np.loadtxt(lines, delimiter=",", comments="#", usecols=self.use, ndmin=2, dtype=float)
        except ValueError:
            self._fail(self.suspect or self._bad_line(lines, first))
        k = data.shape[0]
        if k == 0:
            return
        if hashed and self.suspect is None:
            self.suspect = self._bad_line(lines, first, hashed=True)
        # loadtxt skips exactly the lines that are blank or comments (where it takes the others, any other is
        # an error), so where it gave fewer samples than lines, those are the lines without one
        skip = None if k == len(lines) else np.array(
            [i for i, ln in enumerate(lines) if not (s := ln.strip()) or s.startswith("#")], dtype=np.int64)
        self.spans.append((self.n, first, skip))
        if self.nonfinite is None:
            bad = ~np.isfinite(data[:, 0]) | ~np.isfinite(data[:, 1])
            if bad.any():
                j = int(np.argmax(bad))
                i = _nth_kept(skip, j)
                what = "t_s" if not math.isfinite(data[j, 0]) else "length_mm"
                self.nonfinite = (f"{self.name}:{first + i + 1}: {what} is not a finite number "
                                  f"({lines[i].strip()[:60]!r})")
        need = self.n + k
        if need > self.t.size:
            # room for the whole file at the bytes per sample so far (and a little more), or a quarter more
            cap = need + need // 4
            if self.size > nbytes:
                cap = max(need + need // 8, int(need * self.size / nbytes * 1.01))
            self.t.resize(cap, refcheck=False)
            self.L.resize(cap, refcheck=False)
        self.t[self.n : need] = data[:, 0]
        self.L[self.n : need] = data[:, 1]
        self.n = need

    def line_of(self, k: int) -> int:
        """The 1-based file line of sample ``k`` (as read, before any sorting)."""
        b = bisect.bisect_right([s[0] for s in self.spans], k) - 1
        start, first, skip = self.spans[b]
        return first + _nth_kept(skip, k - start) + 1


def _nth_kept(skip: np.ndarray | None, j: int) -> int:
    """The index of the ``j``-th (from 0) index not in the sorted ``skip``."""
    if skip is not None:
        for s in skip.tolist():
            if s > j:
                break
            j += 1
    return j


def _text_blocks(fh: BinaryIO, name: str) -> Iterator[tuple[str, int]]:
    """The file as text, in whole lines of about :data:`BLOCK_BYTES` each, with their size in bytes.

    A UTF-8 byte order mark at the start is dropped.  Invalid UTF-8 is a
    DataError naming the byte and its line, raised once the rest of the file
    is read (a read error anywhere comes first, as when it was read whole).
    """
    offset = newlines = 0  # bytes and b"\n" before the block
    carry: list[bytes] = []  # the start of a line the last read cut
    while True:
        chunk = _read(fh, name)
        if chunk:
            cut = chunk.rfind(b"\n") + 1
            if cut == 0:
                carry.append(chunk)
                continue
            block = b"".join([*carry, chunk[:cut]]) if carry else chunk[:cut]
            carry = [chunk[cut:]] if cut < len(chunk) else []
        elif carry:
            block, carry = b"".join(carry), []
        else:
            return
        skip = len(codecs.BOM_UTF8) if offset == 0 and block.startswith(codecs.BOM_UTF8) else 0
        try:
            text = (block[skip:] if skip else block).decode("utf-8")
        except UnicodeDecodeError as err:
            at = skip + err.start
            line = newlines + block[:at].count(b"\n") + 1
            while _read(fh, name):
                pass
            raise DataError(f"{name}:{line}: not a text CSV file (byte {offset + at} is not UTF-8)") from None
        offset += len(block)
        newlines += block.count(b"\n")
        yield text, len(block)


def _read(fh: BinaryIO, name: str) -> bytes:
    try:
        return fh.read(BLOCK_BYTES)
    except OSError as err:
        raise DataError(f"{name}: cannot read: {err.strerror or err}") from err


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
    """The ``plan``, ``machine``, ``analysis`` (and ``limits``) tables of the newest of a log's config records."""
    cfg = configs[-1].get("config", {}) if configs else {}
    return {k: dict(cfg[k]) for k in ("plan", "machine", "analysis", "limits") if isinstance(cfg.get(k), dict)}


OUTCOME_EVENTS = {"test_rejected": "rejected", "test_incomplete": "incomplete", "test_skipped": "skipped"}


def outcomes(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One entry per test an analysis found, in order.

    Each: ``number`` (from 1), ``feed_in_s``, ``status`` (``complete``,
    ``rejected``, ``incomplete``, or ``skipped``: not fitted, another test
    was asked for), ``message`` (why not complete) and ``result`` (the test
    result, or None).
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
        elif r.get("event") in OUTCOME_EVENTS and entry["status"] == "incomplete":
            entry.update(status=OUTCOME_EVENTS[r["event"]], message=str(r.get("message", "")))
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
        others = [e["number"] for e in found if e["status"] in ("complete", "skipped")]
        hint = f" (whole: test {', '.join(map(str, others))}; choose with --test N)" if others else ""
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
    """Read a recording (:func:`load_recording`), analyse it and return its ``test``-th test result (the
    other tests are found, not fitted)."""
    rec = load_recording(path)
    return pick_test(analyze(rec, plan, machine, options, curves, only=test), test, path, plan)


def analyze(
    rec: Recording,
    plan: TestPlan,
    machine: MachineConfig,
    options: AnalysisOptions,
    curves: bool = False,
    only: int | None = None,
) -> list[dict[str, Any]]:
    """:func:`~ballbar.analysis.engine.analyze_recording` of a recording, its tests' results and events (no
    provisional circles: what the daemon published of them live is in the recording); its errors name the
    recording.  ``only``: fit that test alone (from 1), the others reported ``test_skipped``: its result is
    the one the whole analysis gives."""
    try:
        out = analyze_recording(rec.t, rec.L, plan, machine, options, curves=curves, breaks=rec.breaks,
                                circles=False, only=only)
    except DataError as err:
        if rec.name and not str(err).startswith(rec.name):
            err.args = (f"{rec.name}: {err}",)
        raise
    if rec.timing and rec.axis == "host":
        from ballbar.analysis.polled import state_span

        for r in out:
            if r.get("kind") in ("circle", "test"):
                state_span(r, rec.timing)
    return out
