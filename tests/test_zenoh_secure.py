"""The secure plant setup, for real: the daemon started with the shipped ``systemd/zenoh-daemon.json5``
(TLS with client certificates, access control), certificates made here with ``openssl``.

An authorised service receives results and gets the daemon's answers; a peer without a certificate,
or without TLS, cannot connect; a service's put is dropped and its queryable cannot answer in the
daemon's place.  The secret (a password in ``zenoh.options``) never leaves the daemon.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[1]
OPENSSL = shutil.which("openssl")
pytestmark = pytest.mark.skipif(OPENSSL is None, reason="openssl is not installed")
MACHINE = "sec"
SECRET = "usrpwd-Xk29-never-published"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _openssl(*args: str) -> None:
    assert OPENSSL is not None
    subprocess.run([OPENSSL, *args], check=True, capture_output=True, timeout=60)


def make_certs(d: Path) -> None:
    """A plant CA, the daemon's certificate (for localhost and 127.0.0.1), a service's, an operator's (who may
    choose the next test's plan), and a stranger CA's."""
    d.mkdir()
    for ca in ("ca", "stranger-ca"):
        _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2",
                 "-subj", f"/CN={ca}", "-keyout", str(d / f"{ca}-key.pem"), "-out", str(d / f"{ca}.pem"))
    ext = d / "leaf.ext"
    ext.write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth,clientAuth\n")
    for name, cn, ca in (("daemon", "ballbar-daemon", "ca"), ("service", "plant-service", "ca"),
                         ("stranger", "plant-service", "stranger-ca"), ("operator", "plant-operator", "ca")):
        _openssl("req", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-subj", f"/CN={cn}",
                 "-keyout", str(d / f"{name}-key.pem"), "-out", str(d / f"{name}.csr"))
        _openssl("x509", "-req", "-in", str(d / f"{name}.csr"), "-CA", str(d / f"{ca}.pem"), "-CAkey",
                 str(d / f"{ca}-key.pem"), "-CAcreateserial", "-days", "2", "-extfile", str(ext),
                 "-out", str(d / f"{name}.pem"))


def shipped(name: str, tls: Path, port: int) -> str:
    """A shipped config with this test's files and loopback port in place of the plant's."""
    text = (ROOT / "systemd" / name).read_text()
    text = text.replace("/run/credentials/ballbar.service/", f"{tls}/").replace("/etc/ballbar/tls/", f"{tls}/")
    return text.replace("tls/0.0.0.0:7447", f"tls/127.0.0.1:{port}").replace("tls/DAEMON_HOST:7447",
                                                                          f"tls/localhost:{port}")


@pytest.fixture
def plant(tmp_path: Path) -> Any:
    tls = tmp_path / "tls"
    make_certs(tls)
    port = free_port()
    daemon_cfg = tmp_path / "zenoh-daemon.json5"
    daemon_cfg.write_text(shipped("zenoh-daemon.json5", tls, port))
    service_cfg = tmp_path / "zenoh-service.json5"
    service_cfg.write_text(shipped("zenoh-service.json5", tls, port))
    log_path = tmp_path / "daemon.log"
    opts = f'zenoh.options={{"transport/auth/usrpwd/password"="{SECRET}"}}'
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=1000&speedup=20&repeat=0",
             "--machine-id", MACHINE, "--state-dir", str(tmp_path / "state"), "--set", 'rerun.mode="off"',
             "--set", f'zenoh.config_file="{daemon_cfg}"', "--set", opts, "--set", "daemon.status_interval_s=0.5"],
            stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
    try:
        deadline = time.monotonic() + 30
        while "zenoh: publishing under" not in log_path.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()[-3000:]
            time.sleep(0.1)
        yield {"port": port, "tls": tls, "service": service_cfg, "log": log_path, "proc": proc, "tmp": tmp_path}
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def subscribe(cfg: Path | None, port: int, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    extra = ["--config", str(cfg), "--connect", f"tls/localhost:{port}"] if cfg else []
    return subprocess.run([sys.executable, "-m", "ballbar.tools.subscribe", "--machine", MACHINE, *extra, *args],
                          capture_output=True, text=True, timeout=timeout)


def client_config(plant: dict[str, Any], cert: str | None) -> Any:
    import zenoh

    c = zenoh.Config()
    for k, v in (("mode", "client"), ("connect/endpoints", [f"tls/localhost:{plant['port']}"]),
                 ("scouting/multicast/enabled", False), ("transport/shared_memory/enabled", False),
                 ("transport/link/tls/root_ca_certificate", str(plant["tls"] / "ca.pem"))):
        c.insert_json5(k, json.dumps(v))
    if cert:
        c.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(plant["tls"] / f"{cert}.pem")))
        c.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(plant["tls"] / f"{cert}-key.pem")))
        c.insert_json5("transport/link/tls/enable_mtls", "true")
    return c


def test_authorised_service_receives_results_and_the_config_without_secrets(plant: dict[str, Any]) -> None:
    got = subscribe(plant["service"], plant["port"], "--topic", "circle", "--count", "1", "--timeout", "120")
    assert got.returncode == 0, got.stderr[-2000:]
    result = json.loads(got.stdout.splitlines()[0])
    assert result["kind"] == "circle" and result["machine_id"] == MACHINE
    # the configuration went out before this subscriber came: ask last/config
    import zenoh

    with zenoh.open(client_config(plant, "service")) as s:
        replies = [r.ok for r in s.get(f"ballbar/{MACHINE}/last/config", timeout=5) if r.ok is not None]
    assert replies
    text = replies[0].payload.to_bytes().decode()
    assert SECRET not in text and "<redacted>" in text
    assert SECRET not in plant["log"].read_text()
    # ... nor in the recordings
    for f in (plant["tmp"] / "state" / "recordings").glob("*.mcap"):
        assert SECRET.encode() not in f.read_bytes()


@pytest.mark.parametrize("how", ["no TLS", "no certificate", "a stranger CA's certificate"])
def test_an_unauthenticated_peer_is_refused(plant: dict[str, Any], how: str) -> None:
    import zenoh

    if how == "no TLS":
        proc = subscribe(None, plant["port"], "--connect", f"tcp/127.0.0.1:{plant['port']}", "--no-wait")
        assert proc.returncode == 1 and "cannot connect" in proc.stderr, proc.stderr
        return
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(client_config(plant, None if how == "no certificate" else "stranger"))


def test_a_service_cannot_publish_or_answer_in_the_daemons_place(plant: dict[str, Any]) -> None:
    import zenoh

    fake = json.dumps({"schema_version": 1, "kind": "test", "machine_id": MACHINE, "fake": True}).encode()
    with zenoh.open(client_config(plant, "service")) as rogue, zenoh.open(client_config(plant, "service")) as good:
        heard: list[bytes] = []
        sub = good.declare_subscriber(f"ballbar/{MACHINE}/**", lambda s: heard.append(s.payload.to_bytes()))
        q = rogue.declare_queryable(f"ballbar/{MACHINE}/last/*",
                                    lambda query: query.reply(f"ballbar/{MACHINE}/last/status", fake), complete=True)
        time.sleep(1.0)  # declarations propagate (or, for the rogue's, are dropped)
        for _ in range(20):
            rogue.put(f"ballbar/{MACHINE}/result/test", fake)
            rogue.put(f"ballbar/{MACHINE}/event", fake)
            rogue.put(f"ballbar/{MACHINE}/status", fake)
            time.sleep(0.05)
        time.sleep(1.5)
        replies = [r.ok.payload.to_bytes() for r in good.get(f"ballbar/{MACHINE}/last/status", timeout=5)
                   if r.ok is not None]
        sub.undeclare()
        q.undeclare()
    assert heard, "the authorised subscriber heard nothing from the daemon"
    assert not any(b'"fake"' in h for h in heard), "a service's put reached a subscriber"
    assert replies and not any(b'"fake"' in r for r in replies), replies
    assert all(json.loads(r)["kind"] == "status" for r in replies)


def test_only_an_operator_may_choose_the_next_plan(plant: dict[str, Any]) -> None:
    """A put on control/next_plan from the plant service's certificate is dropped; the same put from an
    operator's is taken: the daemon says so in a plan_chosen event."""
    import zenoh

    key = f"ballbar/{MACHINE}/control/next_plan"
    with zenoh.open(client_config(plant, "service")) as service, zenoh.open(client_config(plant, "service")) as ear:
        heard: list[dict[str, Any]] = []
        sub = ear.declare_subscriber(f"ballbar/{MACHINE}/event",
                                     lambda s: heard.append(json.loads(s.payload.to_bytes())))
        time.sleep(1.0)
        for _ in range(5):
            service.put(key, json.dumps({"plan": "default"}))
            time.sleep(0.1)
        time.sleep(1.5)
        assert not [e for e in heard if e.get("event") in ("plan_chosen", "plan_choice_refused")], heard
        with zenoh.open(client_config(plant, "operator")) as operator:
            time.sleep(0.5)
            operator.put(key, json.dumps({"plan": "default"}))
            deadline = time.monotonic() + 10
            while not any(e.get("event") == "plan_chosen" for e in heard) and time.monotonic() < deadline:
                time.sleep(0.1)
        sub.undeclare()
    chosen = [e for e in heard if e.get("event") == "plan_chosen"]
    assert len(chosen) == 1 and chosen[0]["plan"] == "default", heard
