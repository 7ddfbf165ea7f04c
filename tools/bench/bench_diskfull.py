"""Disk full on a small state file system: the time from space returning to the daemon writing again.

For each of ``--sizes`` (MiB) a tmpfs of that size is mounted (root only; :class:`~ballbar.tools.bench.soak.Disk`) and
``ballbar run`` started on the ``sim:`` source sped up, its state directory on it (MCAP on, Zenoh and Rerun
off).  Once the daemon writes its first file, ``--spells`` times: the file system is filled to the last byte,
the daemon's "cannot write" error awaited, the disk held full ``--full-s`` more (and up to half a second, at
random: the logger looks for space every 0.5 s), then the filler removed and the time to the daemon's
"writing again" line taken (the line's arrival on its stderr, read as it comes).
Medians (min..max) per size; a spell that does not resume within ``--timeout-s`` counts as never (and ends the
runs of that size).  ``--python`` adds the same runs with another interpreter, e.g. a virtual environment of an
older checkout, for a before/after.

Run (root)::

    python -m ballbar.tools.bench.bench_diskfull --sizes 8,256 --spells 5 [--python ../old/.venv/bin/python]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO, Any

from ballbar.tools.bench.soak import Disk


class DaemonLog:
    """A daemon's stderr, line by line as it comes, with when each line arrived (``time.monotonic``)."""

    def __init__(self, stream: IO[str]) -> None:
        self.lines: list[tuple[float, str]] = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True)
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            with self._cond:
                self.lines.append((time.monotonic(), line.rstrip("\n")))
                self._cond.notify_all()

    def mark(self) -> int:
        """Where the log is now: :meth:`wait_for` from here looks only at lines that come later."""
        with self._cond:
            return len(self.lines)

    def wait_for(self, needle: str, timeout: float, start: int = 0) -> tuple[float, str]:
        """The first line from line ``start`` on holding ``needle`` (arrival time, line), waiting for it at most
        ``timeout`` s (TimeoutError)."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for item in self.lines[start:]:
                    if needle in item[1]:
                        return item
                start = len(self.lines)
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no line with {needle!r} within {timeout:g} s")
                self._cond.wait(left)

    def text(self) -> str:
        return "\n".join(line for _t, line in self.lines)


def start_daemon(state: Path, *extra: str, python: str = sys.executable) -> tuple[subprocess.Popen[str], DaemonLog]:
    """``ballbar run`` on the simulated source at x20, MCAP on (a small quota), Zenoh and Rerun off."""
    cmd = [python, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=1000&speedup=20&repeat=0",
           "--state-dir", str(state), "--set", "mcap.rotate_mb=1", "--set", "mcap.quota_mb=4",
           "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"', *extra]
    env = {k: v for k, v in os.environ.items() if k != "BALLBAR_CONFIG"} | {"PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stderr is not None
    return proc, DaemonLog(proc.stderr)


def stop_daemon(proc: subprocess.Popen[str], timeout: float = 15.0) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        return -9


def spell(disk: Disk, log: DaemonLog, full_s: float, timeout: float = 30.0, jitter_s: float = 0.0) -> float | None:
    """One full-disk spell: fill, await the error, hold ``full_s`` plus up to ``jitter_s`` (at random), free; the
    seconds from freeing to writing again (None: not within ``timeout``)."""
    at = log.mark()
    disk.fill()
    log.wait_for("mcap log: cannot write", timeout, at)
    time.sleep(full_s + random.uniform(0.0, jitter_s))
    at = log.mark()
    t0 = time.monotonic()
    disk.release()
    try:
        t1, _line = log.wait_for("mcap log: writing again", timeout, at)
    except TimeoutError:
        return None
    return t1 - t0


def measure(size_mb: int, spells: int, full_s: float, workdir: Path, python: str, timeout: float) -> dict[str, Any]:
    disk = Disk(workdir / f"tmpfs-{size_mb}", size_mb)
    if not disk.mounted:
        disk.close()
        return {"size_mb": size_mb, "python": python, "skipped": f"cannot mount a tmpfs: {disk.why_not}"}
    proc, log = start_daemon(disk.path / "state", python=python)
    times: list[float | None] = []
    try:
        log.wait_for("mcap log: writing", 60.0)
        for _ in range(spells):
            # the logger looks for space every 0.5 s from the error on: a hold of a whole number of half seconds
            # would free the disk just before (or after) each look
            times.append(spell(disk, log, full_s, timeout, jitter_s=0.5))
            if times[-1] is None:
                break
            time.sleep(1.0)
    finally:
        code = stop_daemon(proc)
        disk.close()
    done = [t for t in times if t is not None]
    return {"size_mb": size_mb, "python": python, "resume_s": times,
            "median_s": statistics.median(done) if len(done) == len(times) else None, "exit": code}


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.bench_diskfull", description=__doc__.split("\n")[0])
    p.add_argument("--sizes", default="8,256", help="tmpfs sizes, MiB, comma-separated")
    p.add_argument("--spells", type=int, default=5, help="full-disk spells per size")
    p.add_argument("--full-s", type=float, default=3.0, help="how long the disk stays full after the error")
    p.add_argument("--timeout-s", type=float, default=30.0, help="a spell not resumed by then counts as never")
    p.add_argument("--python", action="append", default=[], help="another interpreter to run too (repeatable)")
    p.add_argument("--json", type=Path, help="write the figures here too")
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="ballbar-diskfull-") as tmp:
        for size in (int(s) for s in args.sizes.split(",") if s.strip()):
            for python in [*args.python, sys.executable]:
                r = measure(size, args.spells, args.full_s, Path(tmp), python, args.timeout_s)
                rows.append(r)
                if "skipped" in r:
                    print(f"{size:5d} MiB  {python}  skipped: {r['skipped']}")
                    continue
                got = r["resume_s"]
                what = (f"median {r['median_s']:.2f} s ({min(got):.2f}..{max(got):.2f}, {len(got)} spells)"
                        if r["median_s"] is not None else
                        f"never within {args.timeout_s:g} s (spell {len(got)}; before: {got[:-1]})")
                print(f"{size:5d} MiB  {python}  space back -> writing again: {what}, exit {r['exit']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0 if all(r.get("exit", 0) == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
