"""End to end, a set: ``ballbar run --simulate --config FILE`` with three plans of the same radius and feed (XY
over 360 deg; ZX from -115 deg and YZ from -25 deg, 220 deg data arcs with 5 deg overshoots: the README's
recipe) runs them in turn on the 3D demo machine; every test is recognised (its signature, checked against its
timing), each plane's result recovers the machine's axis errors that the plane sees, the set's result combines
them into the machine's X, Y and Z (published on ``result/set``, valid against its schema, recorded), and
``ballbar analyze`` of the recordings directory gives the same, each test and the set.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from schemacheck import validate_all, validate_recordings
from test_e2e import Subscriber, free_port

from ballbar.analysis.sets import set_words
from ballbar.daemon.cli import main as cli_main
from ballbar.daemon.mcap import list_recordings, read_logs
from ballbar.tools.machine3d import Machine3D
from ballbar.tools.simulate import SIM_MACHINE_3D

pytestmark = pytest.mark.usefixtures("no_leaks")

SET = """
[daemon]
machine_id = "e2e"

[plans.xy]
plane = "XY"

[plans.zx]
plane = "ZX"
start_deg = -115.0
overshoot_deg = 5.0
data_arc_deg = 220.0

[plans.yz]
plane = "YZ"
start_deg = -25.0
overshoot_deg = 5.0
data_arc_deg = 220.0

[sets.machine]
plans = ["xy", "zx", "yz"]
window_minutes = 60.0
"""
# The demo machine's gains, configured per machine axis: each plan takes its plane's two (ZX: Z and X)
GAINS = {k: float(v) for k, v in (item.split("=") for item in SIM_MACHINE_3D) if k.startswith("kv_")}
SET += "\n[machine]\n" + "".join(f"{k} = {v}\n" for k, v in GAINS.items())
# The existing end-to-end tolerances (tests/test_e2e.py)
TOL = {"backlash_x_um": 0.1, "backlash_y_um": 0.1, "servo_mismatch_ms": 0.05, "squareness_urad": 0.5,
       "centre_x_um": 0.1, "centre_y_um": 0.1}


def test_a_set_runs_is_recognised_and_recovers_each_axis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "set.toml"
    cfg.write_text(SET)
    port = free_port()
    sock_path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(sock_path)
    sock.settimeout(0.5)
    log_path = tmp_path / "daemon.log"
    state = tmp_path / "state"
    with open(log_path, "w") as log:
        proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--simulate", "--config", str(cfg), "--speedup", "20",
             "--state-dir", str(state), "--tests", "3", "--set", f'zenoh.listen=["tcp/127.0.0.1:{port}"]',
             "--set", 'rerun.mode="off"', "--set", "daemon.status_interval_s=0.5",
             "--set", "limits.enabled=false"],  # the set without limits (not --simulate's): "no limits" below
            stdout=log, stderr=subprocess.STDOUT, env=dict(os.environ, NOTIFY_SOCKET=sock_path, PYTHONUNBUFFERED="1"),
        )
    sub = None
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if b"READY=1" in sock.recv(4096):
                    break
            except TimeoutError:
                assert proc.poll() is None, log_path.read_text()[-3000:]
        sub = Subscriber(port, "--topic", "all", "--history")
        code = proc.wait(180)
        time.sleep(0.5)
        payloads = sub.stop()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        if sub is not None:
            sub.close()
        sock.close()
    output = log_path.read_text()
    assert code == 0, output[-3000:]
    # Every payload the daemon sent, and every record it logged, matches its schema.
    validate_all(payloads)
    assert validate_recordings(state / "recordings")["/ballbar/results"] >= 3
    log = read_logs(list_recordings(state / "recordings"))
    tests = [r for r in log.results if r.get("kind") == "test"]
    assert [(t["plan"]["name"], t["plan"]["plane"], t["plan"]["axes"]) for t in tests] == [
        ("xy", "XY", ["X", "Y"]), ("zx", "ZX", ["Z", "X"]), ("yz", "YZ", ["Y", "Z"])]
    assert all(t["recognition"]["method"] == "signature" for t in tests), [t["recognition"] for t in tests]
    published = {t["test_id"]: t for t in payloads if t.get("kind") == "test"}
    assert sorted(published) == sorted(t["test_id"] for t in tests)
    feed_ins = [e for e in log.events if e.get("event") == "feed_in"]
    assert [e["plan"] for e in feed_ins[:3]] == ["xy", "zx", "yz"]
    # Each test's analysis took its plane's two gains of [machine], first axis first.
    for t in tests:
        first, second = (f"kv_{a.lower()}_per_s" for a in t["plan"]["axes"])
        assert (t["machine"]["kv_x_per_s"], t["machine"]["kv_y_per_s"]) == (GAINS[first], GAINS[second])
        assert t["timing"]["loop_lag_source"] == f"configured gains {first} and {second}", t["timing"]
    # Each plane recovers what it sees of the 3D machine (Z's lost motion, ZX and YZ squareness among it).
    machine = Machine3D.from_settings({k: float(v) for k, v in (item.split("=") for item in SIM_MACHINE_3D)})
    for t in tests:
        truth = machine.truth(t["plan"]["plane"])
        p = t["parameters"]
        errors = {k: (round(p[k]["value"], 4), truth[k]) for k, tol in TOL.items()
                  if abs(p[k]["value"] - truth[k]) > tol}
        assert not errors, (t["plan"]["name"], errors)
    zx, yz = tests[1]["parameters"], tests[2]["parameters"]
    assert abs(zx["backlash_x_um"]["value"] - machine.get("backlash_{}_um", "z")) < 0.1  # Z, ZX's first axis
    assert abs(yz["backlash_y_um"]["value"] - machine.get("backlash_{}_um", "z")) < 0.1  # Z, YZ's second axis
    assert abs(zx["squareness_urad"]["value"] - machine.squareness_zx_urad) < 0.5
    assert abs(yz["squareness_urad"]["value"] - machine.squareness_yz_urad) < 0.5
    # ballbar analyze of the recordings directory gives each test's result again, and its plan.
    capsys.readouterr()
    for t in tests:
        assert cli_main(["analyze", str(state / "recordings"), "--test-id", t["test_id"], "--json"]) == 0
        offline = json.loads(capsys.readouterr().out)
        assert offline["plan"]["name"] == t["plan"]["name"] and offline["recognition"] == t["recognition"]
        for key, value in t["parameters"].items():
            a, b = value["value"], offline["parameters"][key]["value"]
            assert (a is None and b is None) or abs(a - b) <= 1e-6 * max(1.0, abs(a)), (t["plan"]["name"], key)
    # The set: published once its three tests are in, valid against its schema (validate_all above), recorded.
    sets = [m for m in payloads if m.get("kind") == "set"]
    assert sets and all(m["set_id"] == f"machine@{tests[2]['test_id']}" for m in sets), output[-3000:]
    live = sets[0]
    recorded = [r for r in log.results if r.get("kind") == "set"]
    assert [r["set_id"] for r in recorded] == [live["set_id"]]
    assert [(m["plan"], m["plane"], m["test_id"]) for m in live["tests"]] == [
        (t["plan"]["name"], t["plan"]["plane"], t["test_id"]) for t in tests]
    assert all(c["status"] == "passed" for c in live["checks"]) and live["verdict"]["trusted"], live["checks"]
    # ... the machine's axes within the end-to-end tolerances: each axis' lost motion from both planes that see
    # it, each pair's squareness from its plane, each pair's servo lag mismatch (the position-loop gains)
    for axis in "XYZ":
        lm = live["lost_motion"][axis]
        assert abs(lm["value"] - machine.get("backlash_{}_um", axis.lower())) < TOL["backlash_x_um"], (axis, lm)
        assert sum(o["used"] for o in lm["observations"]) == 2, (axis, lm["observations"])
    for pair in ("XY", "YZ", "ZX"):
        sq, servo = live["squareness"][pair], live["servo"]["pairs"][pair]
        assert abs(sq["value"] - getattr(machine, f"squareness_{pair.lower()}_urad")) < TOL["squareness_urad"], sq
        assert abs(servo["value"] - machine.truth(pair)["servo_mismatch_ms"]) < TOL["servo_mismatch_ms"], servo
    # ... and made again by ballbar analyze from the recordings directory: the same tests, the same figures
    assert cli_main(["analyze", str(state / "recordings"), "--set", "machine", "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["set_id"] == live["set_id"] and again["verdict"]["status"] == live["verdict"]["status"]
    for key, names in (("lost_motion", "XYZ"), ("squareness", ("XY", "YZ", "ZX"))):
        for n in names:
            a, b = again[key][n], live[key][n]
            assert abs(a["value"] - b["value"]) <= 1e-6 * max(1.0, abs(b["value"])), (key, n, a["value"], b["value"])
    for pair in ("XY", "YZ", "ZX"):
        a, b = again["servo"]["pairs"][pair]["value"], live["servo"]["pairs"][pair]["value"]
        assert abs(a - b) <= 1e-6 * max(1.0, abs(b)), (pair, a, b)
    # ... and its report, from the same records: the set's verdict, then each plan's test
    out = tmp_path / "set.html"
    made = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "report", str(state / "recordings"), "--set",
                           "machine", "-o", str(out), "--no-png"], capture_output=True, text=True, timeout=120)
    assert made.returncode == 0, made.stderr[-2000:]
    html = out.read_text(encoding="utf-8")
    assert f'data-status="{set_words(live)["status"]}"' in html and "no limits" in set_words(live)["headline"]
    assert all(f'id="{t["plan"]["name"]}-polar-ccw"' in html for t in tests)
