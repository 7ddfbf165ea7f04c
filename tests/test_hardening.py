"""A daemon that cannot be confused or doubled: the configuration checked whole before anything opens
(one line, exit 2, never a hang), one daemon per state directory, secrets kept in, early SIGTERM.

Every check of the command runs ``ballbar run`` as a real process, with a timeout.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

QUIET = ["--set", "mcap.enabled=false", "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"']
SIM = "sim:?rate=1000&speedup=1&repeat=0"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def ballbar(*args: str, timeout: float = 30, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


def _one_line_exit_2(proc: subprocess.CompletedProcess[str], needle: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr[-2000:])
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], proc.stderr
    assert "Traceback" not in proc.stderr


# ----------------------------------------------------------------------------- configuration


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--set", "mcap.flush_s=-1"], "mcap.flush_s"),
        (["--set", "mcap.rotate_mb=-1"], "mcap.rotate_mb"),
        (["--set", "mcap.quota_mb=-1"], "mcap.quota_mb"),
        (["--set", "mcap.keep_days=-1"], "mcap.keep_days"),
        (["--set", "zenoh.samples_hz=-1"], "zenoh.samples_hz"),
        (["--set", "zenoh.history_size=0"], "zenoh.history_size"),
        (["--machine-id", "mill 7"], "daemon.machine_id"),
        (["--set", "zenoh.options={nope=1}"], "zenoh.options"),
        (["--set", 'zenoh.options={"transport/link/tx/lease"="soon"}'], "zenoh.options"),
        (["--set", 'zenoh.config_file="/nonexistent/zenoh.json5"'], "zenoh.config_file"),
        (["--source", "serail:/dev/ttyUSB0?rate=1000"], "source.url"),
        (["--source", "serial:/dev/ttyUSB0?rate=1000&bogus=1"], "source.url"),
        (["--set", "zenoh.close_timeout_s=-1"], "zenoh.close_timeout_s"),
        (["--set", "analysis.vif_limit=-1"], "vif_limit"),
        (["--set", "analysis.max_lag_s=-1"], "max_lag_s"),
        (["--set", "rerun.memory_limit_mb=-1"], "rerun.memory_limit_mb"),
        (["--source", ""], "source.url"),
        (["--set", "plan.radius_mm=nan"], "plan.radius_mm"),
        # These hung the process for ever while Zenoh was on (its session was never closed).
        (["--set", 'rerun.bind="999.1.1.1"'], "rerun.bind"),
        (["--set", 'rerun.mode="connect"', "--set", 'rerun.url="garbage://x"'], "rerun.url"),
        (["--set", "rerun.tolerance_um=-5"], "rerun.tolerance_um"),
        (["--set", "rerun.port=0"], "rerun.port"),
        (["--set", "rerun.history_tests=-1"], "rerun.history_tests"),
        # Network settings that can never work: these started, opened the port and retried for ever.
        (["--set", 'zenoh.listen=["foo/bar"]'], "zenoh.listen: 'foo/bar': Zenoh has no 'foo' link"),
        (["--set", 'zenoh.listen=["tcp/192.0.2.7:7447"]'], "zenoh.listen: cannot listen on 192.0.2.7:7447: not an"),
        (["--set", 'zenoh.connect=["unixpipe//tmp/x"]'], "zenoh.connect: 'unixpipe//tmp/x': Zenoh has no"),
        (["--set", 'rerun.bind="192.0.2.7"'], "rerun.bind: cannot listen on 192.0.2.7:"),
    ],
)
def test_a_bad_value_is_one_line_exit_2_before_anything_opens(tmp_path: Path, args: list[str], needle: str) -> None:
    port = free_port()
    # Zenoh on (the default) and listening: a session opened by mistake would keep the process alive.
    proc = ballbar("run", "--state-dir", str(tmp_path / "state"), "--source", SIM,
                   "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "--set", "rerun.port=" + str(free_port()),
                   *args, timeout=30)
    _one_line_exit_2(proc, needle)
    assert not (tmp_path / "state" / "recordings").exists() or not any((tmp_path / "state" / "recordings").iterdir())
    with socket.socket() as s:  # nothing kept the port
        s.bind(("127.0.0.1", port))


def test_a_config_file_with_invalid_utf8_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "site.toml"
    bad.write_bytes(b'[daemon]\nmachine_id = "\xff\xfe"\n')
    _one_line_exit_2(ballbar("run", "--config", str(bad), "--print-config"), "not UTF-8")


def test_a_state_dir_that_cannot_be_written_is_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    proc = ballbar("run", "--state-dir", str(blocker / "state"), "--source", SIM, "--set", "zenoh.enabled=false",
                   "--set", 'rerun.mode="off"')
    _one_line_exit_2(proc, "daemon.state_dir")


def test_every_started_output_is_stopped_when_a_later_one_fails(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from ballbar.daemon import config as cfgmod
    from ballbar.daemon import run as runmod
    from ballbar.daemon.bus import ZenohBus
    from ballbar.daemon.mcap import McapLogger
    from ballbar.daemon.rerun import RerunViewer

    cfg = cfgmod.load(None, ["rerun.mode=\"off\"", f'zenoh.listen=["tcp/127.0.0.1:{free_port()}"]'],
                      env={}, overrides={"daemon": {"state_dir": str(tmp_path)}})
    cfg.rerun.mode = "serve"
    stopped: list[str] = []
    for cls in (McapLogger, ZenohBus, RerunViewer):
        original = cls.stop
        monkeypatch.setattr(cls, "stop", lambda self, _o=original: (stopped.append(self.name), _o(self))[1])

    def boom(*_a: Any, **_k: Any) -> Any:
        raise RuntimeError("cannot start")

    for failing, before in (("McapLogger", []), ("ZenohBus", ["mcap"])):
        stopped.clear()
        with monkeypatch.context() as m:
            target = {"McapLogger": McapLogger, "ZenohBus": ZenohBus}[failing]
            m.setattr(target, "from_config", classmethod(boom))
            with pytest.raises(RuntimeError):
                runmod.build_listeners(cfg)
        assert stopped == before, (failing, stopped)
    # The Rerun viewer is made on its own queue's thread (READY=1 does not wait for Rerun): if it cannot be,
    # its output is off and the others run on.
    stopped.clear()
    with monkeypatch.context() as m:
        m.setattr(RerunViewer, "from_config", classmethod(boom))
        listeners = runmod.build_listeners(cfg)
        try:
            viewer = listeners[-1][0]
            assert viewer.name == "rerun" and viewer.stats() == {"state": "starting"}  # type: ignore[attr-defined]
            viewer.on_message({"kind": "status"})
            viewer.on_idle()
            assert viewer.stats() == {"state": "failed"}  # type: ignore[attr-defined]
        finally:
            for lst, _cap, _policy in reversed(listeners):
                lst.stop()
    assert stopped == ["zenoh", "mcap"]


def test_a_listener_started_later_is_made_once_on_first_use_and_stopped() -> None:
    from ballbar.daemon.listeners import Listener
    from ballbar.daemon.run import StartedLater

    made: list[str] = []

    class Inner(Listener):
        name = "inner"

        def __init__(self) -> None:
            made.append("made")
            self.got: list[Any] = []

        def on_message(self, msg: dict[str, Any]) -> None:
            self.got.append(msg)

        def stats(self) -> dict[str, Any]:
            return {"got": len(self.got)}

        def stop(self) -> None:
            made.append("stopped")

    never = StartedLater("x", Inner)
    never.stop()
    never.on_message({})  # after stop: nothing is made
    assert made == []
    lst = StartedLater("x", Inner)
    lst.on_message({"a": 1})
    lst.on_message({"a": 2})
    assert made == ["made"] and lst.stats() == {"got": 2}
    lst.stop()
    assert made == ["made", "stopped"]
    late = StartedLater("x", Inner)
    late.cancel_start()  # the daemon is stopping: what its queue still holds does not make it
    late.on_message({"a": 3})
    late.stop()
    assert made == ["made", "stopped"]


def _catches_sigterm(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/status") as fh:
            caught = next(int(line.split()[1], 16) for line in fh if line.startswith("SigCgt:"))
    except (OSError, StopIteration):
        return False
    return bool(caught & (1 << (signal.SIGTERM - 1)))


def test_sigterm_right_after_start_exits_0(tmp_path: Path) -> None:
    """The handler is in place before anything slow (about 0.07 s after exec on an idle PC); a SIGTERM
    from then on, at any stage of the start, is a clean stop."""
    for delay in (0.0, 0.2, 0.5, 0.8):
        proc = subprocess.Popen([sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", SIM,
                                 "--state-dir", str(tmp_path), *QUIET], stderr=subprocess.PIPE, text=True)
        t0 = time.monotonic()
        while not _catches_sigterm(proc.pid) and proc.poll() is None and time.monotonic() - t0 < 10:
            time.sleep(0.002)
        installed = time.monotonic() - t0
        time.sleep(delay)
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == 0, (delay, installed, proc.returncode, err[-1500:])


def test_the_entry_point_imports_nothing_before_the_handler() -> None:
    """``ballbar run`` installs its handler in ``cli.main`` before importing the subcommands: ``cli`` itself must
    bring in nothing but the package and the standard library's signal and threading."""
    code = ("import sys; before = set(sys.modules); import ballbar.daemon.cli; "
            "print(' '.join(sorted(set(sys.modules) - before)))")
    new = set(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split())
    assert new <= {"ballbar", "ballbar.daemon", "ballbar.daemon.cli", "signal", "threading", "_weakrefset"}, new


def test_blas_threads_are_the_entry_points_choice_not_the_librarys() -> None:
    """Importing the library changes no process-wide setting; the ``ballbar`` command sets one BLAS thread (a
    default the environment overrides) before numpy loads, and its children inherit it."""
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    code = ("import os, sys; import ballbar, ballbar.analysis.engine; "
            "print(os.environ.get('OPENBLAS_NUM_THREADS')); "
            "from ballbar.daemon import cli\n"
            "try:\n    cli.main(['--help'])\nexcept SystemExit:\n    pass\n"
            "print(os.environ.get('OPENBLAS_NUM_THREADS'), os.environ.get('OMP_NUM_THREADS'), file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.splitlines()[0] == "None", out.stdout
    assert out.stderr.split() == ["1", "1"], out.stderr
    env["OPENBLAS_NUM_THREADS"] = "2"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)
    assert out.stderr.split() == ["2", "1"], out.stderr


# ----------------------------------------------------------------------------- one daemon per state dir


def _run_args(tmp_path: Path) -> list[str]:
    """``ballbar run`` on the simulated source with its state in ``tmp_path/state``, no bus, no viewer."""
    return ["run", "--source", SIM, "--state-dir", str(tmp_path / "state"), "--set", "zenoh.enabled=false",
            "--set", 'rerun.mode="off"']


def _start(tmp_path: Path, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "ballbar.daemon.cli", *_run_args(tmp_path), *extra],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )


def _wait_for_lock(tmp_path: Path, pid: int, timeout: float = 30.0) -> None:
    lock = tmp_path / "state" / "ballbar.lock"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if lock.exists() and lock.read_text().strip() == str(pid):
            return
        time.sleep(0.05)
    raise AssertionError("the first daemon did not take the lock")


def _the_open_file(recordings: Path, timeout: float = 30.0) -> Path:
    """The one recording a daemon that just started writes, once it is there."""
    deadline = time.monotonic() + timeout
    while not list(recordings.glob("*.mcap")) and time.monotonic() < deadline:
        time.sleep(0.05)
    (open_file,) = recordings.glob("*.mcap")
    return open_file


def test_a_second_daemon_on_the_same_state_dir_exits_2_naming_the_holder(tmp_path: Path) -> None:
    first = _start(tmp_path)
    try:
        _wait_for_lock(tmp_path, first.pid)
        second = ballbar(*_run_args(tmp_path), timeout=30)
        _one_line_exit_2(second, f"PID {first.pid}")
        assert first.poll() is None
        first.send_signal(signal.SIGTERM)
        assert first.wait(10) == 0
        # the lock went with it: a new daemon starts
        third = _start(tmp_path)
        try:
            _wait_for_lock(tmp_path, third.pid)
        finally:
            third.send_signal(signal.SIGTERM)
            assert third.wait(10) == 0
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()


def test_deleting_the_lock_file_lets_no_second_daemon_in(tmp_path: Path) -> None:
    """The lock is the directory's: an operator who deletes ``ballbar.lock`` as stale lets no second daemon start,
    and the first one's recording is left alone (a lock on the file let the second rewrite it)."""
    first = _start(tmp_path)
    try:
        _wait_for_lock(tmp_path, first.pid)
        recordings = tmp_path / "state" / "recordings"
        open_file = _the_open_file(recordings)
        inode = open_file.stat().st_ino
        (tmp_path / "state" / "ballbar.lock").unlink()
        second = ballbar(*_run_args(tmp_path), timeout=30)
        _one_line_exit_2(second, "is in use by another ballbar daemon")
        assert first.poll() is None
        assert open_file.stat().st_ino == inode and list(recordings.glob("*.mcap")) == [open_file]
        first.send_signal(signal.SIGTERM)
        assert first.wait(10) == 0
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()


def test_a_file_another_process_writes_is_never_recovered_nor_deleted(tmp_path: Path) -> None:
    """Recovery and retention outside the daemon that writes a file (another process: here the test's own, as a
    second daemon that got past the state lock would be) leave it alone: the writer holds an ``flock`` on it.  The
    file then holds every sample its daemon says it wrote, none lost (on the old code recovery rewrote it: the
    daemon went on writing to the replaced inode, and retention deleted it)."""
    from ballbar.daemon.mcap import McapLogger, read_log, recover_crashed
    from ballbar.tools.bench.bench_diskfull import stop_daemon

    first = _start(tmp_path)
    recordings = tmp_path / "state" / "recordings"
    try:
        _wait_for_lock(tmp_path, first.pid)
        open_file = _the_open_file(recordings)
        time.sleep(1.5)  # some chunks in it, no footer yet
        inode = open_file.stat().st_ino
        assert recover_crashed(recordings) == []
        assert open_file.stat().st_ino == inode
        # retention in another writer on the same directory: over its quota and past keep_days, the file stays
        other = McapLogger(tmp_path / "state", "other", rotate_bytes=4096, quota_bytes=8192, keep_days=1e-9)
        try:
            os.utime(open_file, (time.time() - 86400, time.time() - 86400))
            other._retention(time.monotonic())
            assert open_file.exists() and open_file.stat().st_ino == inode
            assert other.stats()["deleted_files"] == 0
        finally:
            other.stop()
        assert first.poll() is None
        time.sleep(1.0)
    finally:
        code = stop_daemon(first)
    assert code == 0
    err = first.stderr.read() if first.stderr is not None else ""
    assert "open in another process" not in err  # the daemon's own retention found nothing held elsewhere
    line = next(x for x in err.splitlines() if "mcap log stopped:" in x)
    written, lost = (int(v) for v in re.search(r"files, (\d+) samples, .*; (\d+) samples lost", line).groups())
    assert lost == 0 and written > 1000, line
    lg = read_log(open_file)
    assert lg.complete and int((~lg.preroll).sum()) == written, (len(lg.samples), written)


def test_a_lock_left_by_kill_9_does_not_block_a_restart(tmp_path: Path) -> None:
    first = _start(tmp_path)
    try:
        _wait_for_lock(tmp_path, first.pid)
        first.send_signal(signal.SIGKILL)
        first.wait(10)
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    assert (tmp_path / "state" / "ballbar.lock").read_text().strip() == str(first.pid)  # stale file, no lock
    second = _start(tmp_path)
    try:
        _wait_for_lock(tmp_path, second.pid)
    finally:
        second.send_signal(signal.SIGTERM)
        code = second.wait(10)
    assert code == 0


# ----------------------------------------------------------------------------- secrets


def test_redacted_hides_passwords_keys_and_certificates() -> None:
    from ballbar.daemon.secrets import REDACTED, redacted

    cfg = {
        "zenoh": {
            "config_file": "/etc/ballbar/zenoh.json5",
            "options": {
                "transport/auth/usrpwd/password": "hunter2",
                "transport/auth/usrpwd/user": "ballbar",
                "transport/link/tls/connect_private_key": "/etc/ballbar/tls/key.pem",
                "transport/link/tls/root_ca_certificate_base64": "TUlJQk...",
                "transport/link/tls": {"listen_private_key_base64": "LS0tLS1CRUdJTi", "enable_mtls": True},
                "transport/link/tx/lease": 5000,
            },
            "connect": ["tls/router:7447"],
        },
        "rerun": {"url": "rerun+http://viewer:s3cret@ws7:9876/proxy"},
        "plan": {"radius_mm": 100.0},
    }
    out = redacted(cfg)
    text = json.dumps(out)
    for secret in ("hunter2", "key.pem", "TUlJQk", "LS0tLS1CRUdJTi", "s3cret"):
        assert secret not in text, secret
    o = out["zenoh"]["options"]
    assert o["transport/auth/usrpwd/password"] == REDACTED
    assert o["transport/link/tx/lease"] == 5000 and o["transport/link/tls"]["enable_mtls"] is True
    assert o["transport/auth/usrpwd/user"] == "ballbar"
    assert out["plan"] == {"radius_mm": 100.0} and out["zenoh"]["connect"] == ["tls/router:7447"]
    assert cfg["zenoh"]["options"]["transport/auth/usrpwd/password"] == "hunter2"  # a copy


SECRET = "Pl4ntP4ssw0rd-7f3a"


def test_print_config_and_a_refused_secret_never_show_it(tmp_path: Path) -> None:
    opt = f'zenoh.options={{"transport/auth/usrpwd/password"="{SECRET}", "transport/auth/usrpwd/user"="bb"}}'
    proc = ballbar("run", "--set", opt, "--print-config")
    assert proc.returncode == 0, proc.stderr
    assert SECRET not in proc.stdout + proc.stderr
    cfg = json.loads(proc.stdout)
    assert cfg["zenoh"]["options"]["transport/auth/usrpwd/password"] == "<redacted>"
    # a value Zenoh refuses: the error names the key, not the value
    bad = ballbar("run", "--source", SIM, "--state-dir", str(tmp_path), "--set",
                  f'zenoh.options={{"transport/auth/usrpwd/password"=["{SECRET}"]}}')
    assert bad.returncode == 2 and SECRET not in bad.stdout + bad.stderr, bad.stderr


# ----------------------------------------------------------------------------- a port that is not there


def test_a_missing_port_is_waiting_visibly(tmp_path: Path) -> None:
    port = free_port()
    missing = tmp_path / "ttyUSB-not-yet"
    proc = subprocess.Popen(
        [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", f"serial:{missing}?rate=1000",
         "--machine-id", "wait", "--state-dir", str(tmp_path / "state"), "--set", 'rerun.mode="off"',
         "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]', "--set", "daemon.status_interval_s=0.5"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while True:  # until the daemon's session listens
            got = subprocess.run(
                [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", "wait", "--connect",
                 f"tcp/127.0.0.1:{port}", "--topic", "status", "--count", "1", "--timeout", "30"],
                capture_output=True, text=True, timeout=60,
            )
            if got.returncode == 0 or time.monotonic() > deadline or proc.poll() is not None:
                break
            time.sleep(0.3)
        assert got.returncode == 0, got.stderr
        status = json.loads(got.stdout.splitlines()[0])
        assert status["source_state"] == "waiting"
        assert "cannot open" in status["source_reason"] and str(missing) in status["source_reason"]
    finally:
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=15)
    assert proc.returncode == 0, err


def test_the_wait_is_reported_again_at_a_slow_cadence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    from ballbar.daemon import sources
    from ballbar.daemon.sources import serial

    monkeypatch.setattr(serial, "WAIT_WARNING_S", 0.5)
    src = sources.open_source(f"serial:{tmp_path / 'nope'}?rate=1000&retry_max_s=0.05", cal_mm=100.0)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 1.3:
            src.read(0.1)
    finally:
        src.close()
    waits = [r for r in caplog.records if "still waiting" in r.getMessage()]
    assert 2 <= len(waits) <= 3 and all(r.levelname == "WARNING" for r in waits), [r.getMessage() for r in waits]


# ----------------------------------------------------------------------------- start after a crash


def _daemon(tmp_path: Path, port: int, log_name: str) -> tuple[subprocess.Popen[str], Path]:
    log_path = tmp_path / log_name
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=1000&speedup=10&repeat=0",
             "--machine-id", "crash", "--state-dir", str(tmp_path / "state"), "--set", 'rerun.mode="off"',
             "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]'],
            stdout=log, stderr=subprocess.STDOUT, text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
    return proc, log_path


def _subscribe(port: int, *args: str, timeout: float = 60) -> list[dict[str, Any]]:
    deadline = time.monotonic() + timeout
    while True:
        got = subprocess.run(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", "crash", "--connect",
             f"tcp/127.0.0.1:{port}", *args], capture_output=True, text=True, timeout=timeout + 30,
        )
        if got.returncode == 0 or time.monotonic() > deadline:
            break
        time.sleep(0.3)
    assert got.returncode == 0, got.stderr[-2000:]
    return [json.loads(line) for line in got.stdout.splitlines() if line.strip()]


def test_a_start_after_kill_9_recovers_the_file_once_and_reports_the_cut_test(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    port = free_port()
    proc, first_log = _daemon(tmp_path, port, "first.log")
    feed_in: list[dict[str, Any]] = []
    live: subprocess.Popen[str] | None = None
    try:
        deadline = time.monotonic() + 30
        while "zenoh: publishing under" not in first_log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, first_log.read_text()[-2000:]
            time.sleep(0.1)
        sub = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", "crash", "--connect",
             f"tcp/127.0.0.1:{port}", "--topic", "event", "--timeout", "60"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )
        try:
            assert sub.stdout is not None
            for line in sub.stdout:  # kill -9 a second after a test starts: the crash cuts it
                if json.loads(line).get("event") == "feed_in":
                    feed_in.append(json.loads(line))
                    break
        finally:
            sub.kill()
            sub.wait()
        assert feed_in, "no test started"
        live = subprocess.Popen(  # a subscriber that stays across the crash and the restart
            [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", "crash", "--connect",
             f"tcp/127.0.0.1:{port}", "--topic", "event", "--timeout", "90"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )
        time.sleep(1.0)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    cut_id = feed_in[-1]["test_id"]
    logs = []
    try:
        for run in ("second", "third"):
            proc, log_path = _daemon(tmp_path, port, f"{run}.log")
            try:
                if run == "second":
                    assert live is not None and live.stdout is not None
                    for line in live.stdout:  # the live subscriber receives it once the bus is up again
                        if json.loads(line).get("event") == "test_incomplete":
                            assert json.loads(line)["test_id"] == cut_id
                            break
                    else:
                        raise AssertionError("the live subscriber never received test_incomplete")
                    events = _subscribe(port, "--topic", "event", "--history", "--count", "1", "--timeout", "30")
                    incomplete = [e for e in events if e.get("event") == "test_incomplete"]
                    assert incomplete and incomplete[0]["test_id"] == cut_id, events
                else:
                    time.sleep(3.0)
            finally:
                proc.send_signal(signal.SIGTERM)
                proc.wait(15)
            logs.append(log_path.read_text())
    finally:
        if live is not None:
            live.kill()
            live.wait()
    assert sum(text.count("was cut by a crash") for text in logs) == 1, logs
    assert "ends early" not in "".join(logs)
    for f in (tmp_path / "state" / "recordings").glob("*.mcap"):
        with open(f, "rb") as fh:  # the mcap library's default (seeking) reader opens every file
            assert sum(1 for _ in make_reader(fh).iter_messages()) > 0
