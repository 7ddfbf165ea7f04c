"""Network settings: what can never work is a configuration error before anything opens; what is busy now is a
retry that says so.  (The one-line exit-2 cases run with the others in ``tests/test_hardening.py``.)"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import zenoh

from ballbar.daemon.bus import ZENOH_SCHEMES, BusConfigError, ZenohConfig, check_endpoints
from ballbar.daemon.config import ConfigError, check_listen
from ballbar.tools.bench.bench_diskfull import DaemonLog, stop_daemon


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _open_error(endpoint: str) -> str:
    """What ``zenoh.open`` says of a peer listening on ``endpoint`` ("" if it opens)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    try:
        session = zenoh.open(cfg)
    except zenoh.ZError as err:
        return str(err)
    session.close()
    return ""


def test_the_schemes_are_those_of_the_installed_zenoh(tmp_path: Path) -> None:
    port = free_port()
    for scheme in ZENOH_SCHEMES:
        address = str(tmp_path / "z.sock") if scheme.startswith("unix") else f"127.0.0.1:{port}"
        assert "not supported" not in _open_error(f"{scheme}/{address}"), scheme
    for scheme in ("serial", "vsock", "unixpipe", "foo"):
        assert "not supported" in _open_error(f"{scheme}/x"), scheme


@pytest.mark.parametrize(
    ("listen", "connect", "needle"),
    [
        (["foo/bar"], None, "zenoh.listen: 'foo/bar': Zenoh has no 'foo' link"),
        (None, ["vsock/1:2"], "zenoh.connect: 'vsock/1:2': Zenoh has no 'vsock' link"),
        (["tcp/192.0.2.7:7447"], None, "zenoh.listen: cannot listen on 192.0.2.7:7447: not an address of this host"),
        (["udp/[2001:db8::7]:7447"], None, "zenoh.listen: cannot listen on 2001:db8::7:7447"),
        (["tcp/127.0.0.1:70000"], None, "zenoh.listen: 'tcp/127.0.0.1:70000': expected tcp/HOST:PORT"),
        (["tcp/127.0.0.1"], None, "expected tcp/HOST:PORT"),
        (["tcp/no-such-host.invalid:7447"], None, "is not a name or address of this host"),
    ],
)
def test_endpoints_that_can_never_work(listen: list[str] | None, connect: list[str] | None, needle: str) -> None:
    with pytest.raises(BusConfigError) as info:
        check_endpoints(ZenohConfig(listen=listen, connect=connect))
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_endpoints_that_can_work_now_or_later() -> None:
    port = free_port()
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", port))
        busy.listen()
        # busy now (transient), every local form, remote connects, the default
        check_endpoints(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}", "tcp/0.0.0.0:0", "tcp/localhost:0",
                                            "udp/127.0.0.1:0", "tcp/[::1]:0", "ws/127.0.0.1:0"],
                                    connect=["tcp/192.0.2.10:7447", "tls/router.example:7447"]))
        check_endpoints(ZenohConfig())
        check_listen("rerun.bind", "127.0.0.1", port)
    with pytest.raises(ConfigError) as info:
        check_listen("rerun.bind", "192.0.2.7", 9880)
    assert str(info.value) == "rerun.bind: cannot listen on 192.0.2.7:9880: not an address of this host"


def test_a_busy_address_is_retried_and_said_in_use_until_it_is_free(tmp_path: Path) -> None:
    """A real daemon whose Zenoh and Rerun ports another process holds: it starts, says so, and takes them later."""
    zport, rport = free_port(), free_port()
    holders = []
    for port in (zport, rport):
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", port))
        s.listen()
        holders.append(s)
    env = {k: v for k, v in os.environ.items() if k != "BALLBAR_CONFIG"} | {"PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=100&speedup=1&repeat=0",
         "--state-dir", str(tmp_path / "state"), "--set", "mcap.enabled=false",
         "--set", f'zenoh.listen=["tcp/127.0.0.1:{zport}"]', "--set", f"rerun.port={rport}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env,
    )
    assert proc.stderr is not None
    log = DaemonLog(proc.stderr)
    try:
        _t, zline = log.wait_for("zenoh: cannot open a session", 60.0)
        assert "in use" in zline and "retrying" in zline, zline
        log.wait_for(f"127.0.0.1:{rport} is in use; retrying", 60.0)
        log.wait_for("ready: reading", 60.0)
        at = log.mark()
        for s in holders:
            s.close()
        log.wait_for("zenoh: publishing under", 60.0, at)
        log.wait_for("serving on", 60.0, at)
        assert proc.poll() is None
    finally:
        for s in holders:
            s.close()
        code = stop_daemon(proc)
    assert code == 0, log.text()[-3000:]
