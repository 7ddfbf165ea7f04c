"""End to end on real parts: the simulated ball-bar on a pty, the daemon as a process,
a separate Zenoh subscriber process, the MCAP log; and the faults a daemon lives with."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from schemacheck import validate_all, validate_recordings
from test_viewer import RERUN, Receiver, last, read_rrd

from ballbar.daemon.cli import main as cli_main
from ballbar.daemon.mcap import list_recordings, read_logs
from ballbar.tools.simdevice import DeviceProcess

pytestmark = pytest.mark.usefixtures("no_leaks")

MACHINE = ("backlash_x_um=4", "kv_y_per_s=33", "squareness_urad=15", "centre_x_um=8", "noise_um=0.1")
SPEEDUP = 20.0


def recordings(tmp: Path) -> Any:
    return read_logs(list_recordings(tmp / "state" / "recordings"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Daemon:
    """``ballbar run`` as a child process, with a notify socket to see READY=1."""

    def __init__(self, tmp: Path, url: str, zenoh_port: int, *extra: str, rerun: str = 'rerun.mode="off"') -> None:
        self.sock_path = str(tmp / f"notify-{time.monotonic_ns()}.sock")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.sock_path)
        self.sock.settimeout(0.5)
        env = dict(os.environ, NOTIFY_SOCKET=self.sock_path, PYTHONUNBUFFERED="1")
        self.log_path = tmp / f"daemon-{time.monotonic_ns()}.log"
        self.log = open(self.log_path, "w")  # noqa: SIM115 - closed in close()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", url, "--machine-id", "e2e",
             "--state-dir", str(tmp / "state"), "--set", f'zenoh.listen=["tcp/127.0.0.1:{zenoh_port}"]',
             "--set", rerun, "--set", "daemon.status_interval_s=0.5", *extra],
            env=env, stdout=self.log, stderr=subprocess.STDOUT,
        )

    def wait_ready(self, timeout: float = 60.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if b"READY=1" in self.sock.recv(4096):
                    return
            except TimeoutError:
                if self.proc.poll() is not None:
                    break
        raise AssertionError(f"daemon not ready: {self.output()[-2000:]}")

    def output(self) -> str:
        self.log.flush()
        return self.log_path.read_text()

    def terminate(self, timeout: float = 10.0) -> tuple[int, float]:
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(timeout)
        return code, time.monotonic() - t0

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        self.sock.close()
        self.log.close()


class Subscriber:
    """``python -m ballbar.tools.subscribe`` connected to the daemon, collecting JSON lines (in a file: a pipe
    nobody reads until the end would hold the subscriber up once 64 kB of payloads fill it)."""

    def __init__(self, port: int, *args: str) -> None:
        self.out = tempfile.TemporaryFile(mode="w+")  # noqa: SIM115 - closed in close()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", "e2e", "--connect",
             f"tcp/127.0.0.1:{port}", *args],
            stdout=self.out, stderr=subprocess.PIPE, text=True,
        )

    def results(self, timeout: float) -> list[dict[str, Any]]:
        _, err = self.proc.communicate(timeout=timeout)
        assert self.proc.returncode == 0, err[-2000:]
        self.out.seek(0)
        return [json.loads(line) for line in self.out.read().splitlines() if line.strip()]

    def stop(self) -> list[dict[str, Any]]:
        """SIGTERM (a clean exit, 0) and what it printed."""
        self.proc.send_signal(signal.SIGTERM)
        return self.results(timeout=10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()
        self.out.close()


@pytest.fixture
def device() -> Iterator[DeviceProcess]:
    args = ["--rate", "1000", "--speedup", f"{SPEEDUP:g}", "--repeat", "1", "--wait"]
    for item in MACHINE:
        args += ["--set", item]
    with DeviceProcess(*args) as dev:
        yield dev


@pytest.mark.skipif(RERUN is None, reason="the rerun CLI binary is not installed")
def test_daemon_end_to_end(device: DeviceProcess, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    port = free_port()
    viewer = Receiver(tmp_path, "viewer", free_port())  # a headless rerun that saves what it receives
    daemon = Daemon(tmp_path, device.url, port, "--set", f'rerun.url="rerun+http://127.0.0.1:{viewer.port}/proxy"',
                    rerun='rerun.mode="connect"')
    sub = everything = None
    try:
        daemon.wait_ready()
        everything = Subscriber(port, "--topic", "all", "--history")  # every payload, to check against its schema
        sub = Subscriber(port, "--topic", "circle", "--topic", "test", "--count", "3", "--timeout", "120")
        time.sleep(1.0)  # the subscriber's session finds the daemon
        device.send("start")
        lines = sub.results(timeout=150)
        device.wait_event("done", timeout=60)
        time.sleep(1.0)  # the last samples reach the log
        payloads = everything.stop()
        code, elapsed = daemon.terminate()
        viewer.finish()
    finally:
        for s in (sub, everything):
            if s is not None:
                s.close()
        daemon.close()
        viewer.close()
    assert code == 0 and elapsed < 5.0, daemon.output()[-2000:]
    # Every payload the daemon sent, and every record it logged, matches its schema.
    seen = validate_all(payloads + lines)
    for kind in ("circle", "test", "status", "event:feed_in", "event:feed_out", "event:opened"):
        assert seen[kind] > 0, (kind, seen)
    assert validate_recordings(tmp_path / "state" / "recordings")["/ballbar/results"] == 3
    # The live view reached the viewer: both polar plots, the models, the length, findings, trends.
    saved = read_rrd(viewer.rrd)
    for entity in ("/polar/ccw/measured", "/polar/cw/measured", "/polar/ccw/model", "/polar/cw/model", "/length",
                   "/findings", "/trends/backlash_um/x"):
        assert saved.rows.get(entity, 0) > 0, (entity, sorted(saved.rows))
    findings = last(saved, "/findings", "TextDocument:text")
    text = "".join(findings) if isinstance(findings, list) else str(findings)
    assert "backlash_x_um" in text
    kinds = [(m["kind"], m.get("direction")) for m in lines]
    assert kinds == [("circle", "ccw"), ("circle", "cw"), ("test", None)], kinds
    test = lines[-1]
    assert test["machine_id"] == "e2e" and test["test_id"].startswith("e2e-")
    # Each result says when its last sample arrived, on the host clock of its publication time.
    for m in lines:
        assert 0.0 < m["t_host"] - m["last_sample_t_host"] < 30.0, m
        assert m["latency_ms"] == pytest.approx(1000.0 * (m["t_host"] - m["last_sample_t_host"]))
    p = test["parameters"]
    assert abs(p["backlash_x_um"]["value"] - 4.0) < 0.1
    assert abs(p["servo_mismatch_ms"]["value"] - 1000 * (1 / 30 - 1 / 33)) < 0.05
    assert abs(p["squareness_urad"]["value"] - 15.0) < 0.5
    assert abs(p["centre_x_um"]["value"] - 8.0) < 0.1
    # The log holds every sample the device sent, in order, none lost.
    stats = device.stats()
    log = recordings(tmp_path)
    seq = np.unique(log.samples.seq)
    assert seq.size == stats["sent"], (seq.size, stats)
    assert np.all(np.diff(seq) == 1)
    assert not any(e.get("event") == "lost" for e in log.events)
    # ... and ballbar analyze of the log gives the live result.
    capsys.readouterr()
    assert cli_main(["analyze", str(tmp_path / "state" / "recordings"), "--json"]) == 0
    offline = json.loads(capsys.readouterr().out)
    for key, value in p.items():
        a, b = value["value"], offline["parameters"][key]["value"]
        assert (a is None and b is None) or abs(a - b) <= 1e-6 * max(1.0, abs(a)), key


def test_unplug_garbage_kill_and_restart(device: DeviceProcess, tmp_path: Path) -> None:
    port = free_port()
    daemon = Daemon(tmp_path, device.url, port)
    subs: list[Subscriber] = []
    try:
        daemon.wait_ready()
        subs.append(Subscriber(port, "--topic", "all"))  # every payload, to check against its schema
        time.sleep(1.0)
        device.send("start")
        time.sleep(2.0)
        device.send("garbage 300")
        device.send("corrupt 3")
        device.send("unplug 1.0")  # the adapter is pulled; back after a second
        device.wait_event("replugged", timeout=30)
        time.sleep(2.0)
        assert daemon.proc.poll() is None, daemon.output()[-2000:]
        out = daemon.output()
        assert "unplugged" in out and "replugged" in out
        # kill -9 in the middle of the test: what was logged a second before stays readable
        time.sleep(1.5)
        daemon.proc.send_signal(signal.SIGKILL)
        daemon.proc.wait(10)
        t_kill = time.time()
        payloads = subs[0].stop()
        log = recordings(tmp_path)
        assert not log.complete  # no footer: it was killed
        t_last = log.t_wall_ns.max() / 1e9 if log.t_wall_ns.size else 0.0
        assert t_kill - t_last < 1.5, t_kill - t_last
        n_before = np.unique(log.samples.seq).size
        # restart: the daemon picks the device up again and logs on in a new file
        daemon.close()
        daemon = Daemon(tmp_path, device.url, port)
        daemon.wait_ready()
        subs.append(Subscriber(port, "--topic", "all", "--history"))
        time.sleep(2.0)
        payloads += subs[1].stop()
        code, elapsed = daemon.terminate()
        assert code == 0 and elapsed < 5.0
        after = recordings(tmp_path)
        assert np.unique(after.samples.seq).size > n_before
        lost = [e for e in after.events if e.get("event") == "lost"]
        assert lost, "the outage and the corrupted frames are counted as lost samples"
        # Every payload of both runs, the faults' events and the crash's recovery among them, matches its schema;
        # so does every record of the files, the one the kill cut included.
        seen = validate_all(payloads)
        for kind in ("status", "event:unplugged", "event:replugged", "event:decode_errors", "event:lost"):
            assert seen[kind] > 0, (kind, seen)
        assert validate_recordings(tmp_path / "state" / "recordings")["/ballbar/events"] > 0
    finally:
        for s in subs:
            s.close()
        daemon.close()


def _lines_so_far(sub: Subscriber) -> list[dict[str, Any]]:
    sub.out.flush()
    sub.out.seek(0)
    return [json.loads(line) for line in sub.out.read().splitlines() if line.strip()]


def _wait_lines(sub: Subscriber, ok: Any, timeout: float, what: str) -> list[dict[str, Any]]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        lines = _lines_so_far(sub)
        if ok(lines):
            return lines
        time.sleep(0.2)
    raise AssertionError(f"no {what} within {timeout} s")


def test_the_analysis_worker_killed_is_replaced_and_the_daemon_goes_on(tmp_path: Path) -> None:
    """kill -9 of the child that fits each test: the daemon keeps measuring, says so, and the next test is fitted
    by a new child (the status counts the children started)."""
    args = ["--rate", "1000", "--speedup", f"{SPEEDUP:g}", "--repeat", "2", "--gap-s", "20", "--wait"]
    for item in MACHINE:
        args += ["--set", item]
    port = free_port()
    with DeviceProcess(*args) as device:
        daemon = Daemon(tmp_path, device.url, port)
        sub = None
        try:
            daemon.wait_ready()
            sub = Subscriber(port, "--topic", "test", "--topic", "status", "--topic", "event")
            time.sleep(1.0)
            device.send("start")
            lines = _wait_lines(sub, lambda ls: any(m["kind"] == "test" for m in ls), 120, "first test result")
            worker = next(m for m in reversed(lines) if m["kind"] == "status")["analysis"]["worker"]
            assert worker["started"] == 1 and isinstance(worker["pid"], int)
            os.kill(worker["pid"], signal.SIGKILL)
            lines = _wait_lines(sub, lambda ls: sum(m["kind"] == "test" for m in ls) == 2, 120, "second test result")
            time.sleep(1.5)  # a status after it
            assert daemon.proc.poll() is None
            code, _ = daemon.terminate()
            payloads = sub.stop()
            output = daemon.output()
        finally:
            if sub is not None:
                sub.close()
            daemon.close()
    assert code == 0
    tests = [m for m in payloads if m["kind"] == "test"]
    assert [t["test_index"] for t in tests] == [1, 2]
    assert abs(tests[1]["parameters"]["backlash_x_um"]["value"] - 4.0) < 0.1
    worker = [m for m in payloads if m["kind"] == "status"][-1]["analysis"]["worker"]
    assert worker["started"] == 2 and worker["pid"] not in (None, os.getpid())
    assert "analysis worker: process" in output and "starting another" in output
    validate_all(payloads)
