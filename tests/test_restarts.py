"""Samples lost across a restart are counted at the next start, to the sample, by the device's own counter.

The simulated device (``tools/simdevice.py``) runs as a process of its own on a pty behind a fixed link, so that
it goes on sampling while the daemon (``ballbar run``, a real process) is stopped with SIGTERM or killed with
``kill -9`` and started again on the same state directory.  The recordings then hold the device's sample counter
as it sent it: the gap between the last number the first run recorded and the first the second run recorded is
what the restart lost, and it must be counted so (a ``lost`` event, detail ``restart``, in the new file and in
the status), and every number between the first and the last must be recorded or counted lost.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbar.daemon.mcap import list_recordings, read_log
from ballbar.tools.simdevice import DeviceProcess


def _daemon(url: str, state: Path, log_path: Path) -> subprocess.Popen[str]:
    with open(log_path, "w") as log:
        return subprocess.Popen(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", url, "--state-dir", str(state),
             "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"'],
            stdout=log, stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )


def _run(url: str, state: Path, log_path: Path, seconds: float, how: signal.Signals) -> str:
    proc = _daemon(url, state, log_path)
    try:
        deadline = time.monotonic() + 60
        while "ready: reading" not in log_path.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.05)
        time.sleep(seconds)
        proc.send_signal(how)
        code = proc.wait(20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert code == (0 if how == signal.SIGTERM else -signal.SIGKILL), log_path.read_text()[-3000:]
    return log_path.read_text()


def _recorded(state: Path) -> tuple[dict[str, np.ndarray], list[dict[str, Any]], list[dict[str, Any]]]:
    """Each run's recorded sample numbers (preroll copies left out), every event, every status, in file order."""
    seqs: dict[str, list[np.ndarray]] = {}
    events: list[dict[str, Any]] = []
    status: list[dict[str, Any]] = []
    for p in list_recordings(state / "recordings"):
        lg = read_log(p)
        seqs.setdefault(lg.metadata["run_id"], []).append(lg.samples.seq[~lg.preroll])
        events += [{**e, "run_id": lg.metadata["run_id"]} for e in lg.events]
        status += lg.status
    return {k: np.concatenate(v) for k, v in seqs.items()}, events, status


@pytest.mark.parametrize("how", [signal.SIGTERM, signal.SIGKILL], ids=["sigterm", "kill-9"])
def test_a_restart_counts_what_it_lost_to_the_sample(tmp_path: Path, how: signal.Signals) -> None:
    state = tmp_path / "state"
    with DeviceProcess("--protocol", "binary", "--rate", "1000", "--speedup", "5", "--repeat", "0",
                       "--link", str(tmp_path / "ballbar-tty")) as dev:
        _run(dev.url, state, tmp_path / "first.log", 4.0, how)
        time.sleep(1.0)  # the device samples on meanwhile
        second = _run(dev.url, state, tmp_path / "second.log", 3.0, signal.SIGTERM)
    runs, events, status = _recorded(state)
    assert len(runs) == 2, list(runs)
    first_id, second_id = (e["run_id"] for e in events if e.get("event") == "opened")
    a, b = runs[first_id], runs[second_id]
    assert np.all(np.diff(a) >= 1) and np.all(np.diff(b) >= 1)
    gap = int(b[0]) - int(a[-1]) - 1
    assert gap > 0  # a restart always loses some: the reading of a killed daemon, the port's buffer at reopen
    restart = [e for e in events if e.get("event") == "lost" and e.get("detail") == "restart"]
    assert [(e["run_id"], e["count"], e["seq"]) for e in restart] == [(second_id, gap, int(a[-1]) + 1)], restart
    assert "counting on from sample" in second and f"{gap} samples lost" in second, second[-3000:]
    assert not [e for e in events if e.get("event") in ("device_reset", "clock_jump")], events
    # every number from the first recorded to the last: recorded once, or counted lost
    lost = sum(int(e["count"]) for e in events if e.get("event") == "lost")
    seen = np.concatenate([a, b])
    assert np.unique(seen).size == seen.size
    assert seen.size + lost == int(b[-1]) - int(a[0]) + 1
    # the second run's status counts it (its first status may come before the first read)
    mine = [s for s in status if s.get("source", {}).get("lost_by_cause", {}).get("restart")]
    assert mine and mine[-1]["source"]["lost_by_cause"]["restart"] == gap and mine[-1]["lost_samples"] >= gap


def test_a_device_restarted_meanwhile_is_a_reset_and_counts_nothing(tmp_path: Path) -> None:
    """The device rebooted while the daemon was stopped (its counter back at 0): a ``device_reset`` at the
    second run's first sample, no samples counted lost for the restart (how many is unknown)."""
    state = tmp_path / "state"
    with DeviceProcess("--protocol", "binary", "--rate", "1000", "--speedup", "5", "--repeat", "0",
                       "--link", str(tmp_path / "ballbar-tty")) as dev:
        # The first run long enough that the second starts before the restarted counter passes its old value
        # (a counter that grew past it reads as a continuation: 3 s was too short once the second start took
        # 3 s longer than the first, on a loaded host).
        _run(dev.url, state, tmp_path / "first.log", 8.0, signal.SIGTERM)
        dev.send("reset")
        _run(dev.url, state, tmp_path / "second.log", 2.0, signal.SIGTERM)
    runs, events, _status = _recorded(state)
    first_id, second_id = (e["run_id"] for e in events if e.get("event") == "opened")
    a, b = runs[first_id], runs[second_id]
    assert int(b[0]) == int(a[-1]) + 1  # the numbers go on by one across the reset
    resets = [e for e in events if e.get("event") == "device_reset"]
    assert [(e["run_id"], e["seq"]) for e in resets] == [(second_id, int(b[0]))], resets
    assert not [e for e in events if e.get("event") == "lost" and e.get("detail") == "restart"]


def _readings(raw_seq: np.ndarray, clock_s: np.ndarray) -> Any:
    from ballbar.protocol._common import Readings

    n = raw_seq.size
    return Readings(np.zeros(n), np.zeros(n, np.uint8), raw_seq.astype(np.int64), clock_s.astype(np.float64))


@pytest.mark.parametrize("stopped_s", [2.0, 40 * 60.0, 50 * 60.0, 3 * 3600.0])
def test_the_stamper_resumed_counts_the_gap_whatever_the_clock_wrapped(stopped_s: float) -> None:
    """After resume(), a stop of any length within the counter's range is a gap of exactly what the counter
    stepped, also where the device clock (binary: 2**32 us, 71.6 min) wrapped meanwhile, or nearly half or more of
    a wrap went by: no device reset, no clock jump (the host clock map, which settles the wraps while running, is
    not known yet after a start)."""
    from ballbar.daemon.timebase import Stamper
    from ballbar.protocol.binary import CLOCK_WRAP_S, SEQ_MODULUS

    rate = 1000.0
    last_raw, last_clk = 4_000_000, 4_000.0  # recorded: sample 4 000 000 at 4000 s of device time
    st = Stamper(SEQ_MODULUS, CLOCK_WRAP_S, rate)
    st.resume(last_raw, last_raw, last_clk, last_clk, 1.0 / rate)
    missing = round(stopped_s * rate) - 1
    raw = last_raw + 1 + missing + np.arange(200)
    out = st.stamp(_readings(raw % SEQ_MODULUS, ((raw / rate) % CLOCK_WRAP_S)), t_read=100.0)
    assert out.gaps == [(last_raw + 1, missing)] and out.reset_seqs == [] and out.jumps == []
    assert int(out.seq[0]) == int(raw[0]) and abs(float(out.t_device[0]) - raw[0] / rate) < 1e-6


def test_the_stamper_resumed_after_a_device_reset_uses_the_saved_offsets() -> None:
    """A device reset in the previous run re-based the numbers (they went on by one): with the offsets saved then,
    the raw counter of the last recorded number is known, and the gap is still exact."""
    from ballbar.daemon.timebase import Stamper
    from ballbar.protocol.binary import CLOCK_WRAP_S, SEQ_MODULUS

    rate = 1000.0
    first = Stamper(SEQ_MODULUS, CLOCK_WRAP_S, rate)
    a = np.arange(5000, 6000)
    first.stamp(_readings(a, a / rate), 1.0)
    b = np.arange(10, 1010)  # the device restarted: counter and clock from 10
    got = first.stamp(_readings(b, b / rate), 2.0)
    assert got.reset_seqs == [6000]
    offsets = first.offsets()
    last_seq, last_td = int(got.seq[-1]), float(got.t_device[-1])
    again = Stamper(SEQ_MODULUS, CLOCK_WRAP_S, rate)
    again.resume(last_seq, (last_seq - offsets[0]) % SEQ_MODULUS, last_td, (last_td - offsets[1]) % CLOCK_WRAP_S,
                 1.0 / rate)
    c = np.arange(1500, 1600)  # 490 samples not read across the restart
    out = again.stamp(_readings(c, c / rate), 3.0)
    assert out.gaps == [(last_seq + 1, 490)] and out.reset_seqs == [] and out.jumps == []
