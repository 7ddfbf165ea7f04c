"""The CNC controller over OPC UA ([controller]): a real asyncua client (the daemon's) against the simulated CNC
(tools/simcnc.py), a real asyncua server, over TCP on loopback; the daemon as a process, its MCAP recordings."""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from schemacheck import validate, validate_recordings

from ballbar.daemon.config import ConfigError, ControllerSection, load
from ballbar.daemon.controller import ControllerClient, node_map
from ballbar.daemon.mcap import list_recordings, read_controller, read_logs
from ballbar.tools.simcnc import SimCnc, Story
from ballbar.tools.simdevice import DeviceProcess

pytestmark = pytest.mark.usefixtures("no_leaks")


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class CncProcess:
    """``python -m ballbar.tools.simcnc`` as a child: killed like a controller pulled off the network."""

    def __init__(self, port: int, *args: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.simcnc", "--port", str(port), "--exit-on-eof", "--idle-s", "0.5",
             *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.proc.stdout is not None
        self.endpoint = self.proc.stdout.readline().strip()
        assert self.endpoint.startswith("opc.tcp://"), self.endpoint

    def send(self, line: str) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        answer: dict[str, Any] = json.loads(self.proc.stdout.readline())
        return answer

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for f in (self.proc.stdin, self.proc.stdout):
            if f is not None:
                f.close()


def _wait(pred: Any, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return
        time.sleep(0.05)
    raise AssertionError(f"not within {timeout} s: {what}")


# ----------------------------------------------------------------------------- configuration


def test_a_wrong_endpoint_is_one_line_and_exit_2(tmp_path: Path) -> None:
    for setting, words in [
        ('controller.endpoint="http://cnc:4840"', "controller.endpoint must be opc.tcp://"),
        ('controller.endpoint="opc.tcp://cnc:99999"', "port 99999"),
        ('controller.security_policy="Basic128Rsa15"', "controller.security_policy must be one of"),
    ]:
        out = subprocess.run(
            [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:", "--state-dir",
             str(tmp_path / "state"), "--set", 'controller.endpoint="opc.tcp://127.0.0.1:4840"', "--set", setting],
            capture_output=True, text=True, timeout=60)
        assert out.returncode == 2, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and words in lines[0], out.stderr
        assert not (tmp_path / "state").exists(), "nothing may open before the configuration is checked"


def test_the_endpoint_password_never_shows() -> None:
    with pytest.raises(ConfigError) as err:
        load(sets=['controller.endpoint="opc.tcp://op:hunter2@cnc:4840x"'], env={})
    assert "hunter2" not in str(err.value) and "<redacted>" in str(err.value)


def test_without_a_section_nothing_changes() -> None:
    cfg = load(env={})
    assert cfg.controller is None and "controller" not in cfg.to_dict()
    with_it = load(sets=['controller.endpoint="opc.tcp://127.0.0.1:4840"'], env={})
    assert with_it.controller is not None and with_it.to_dict()["controller"]["endpoint"].startswith("opc.tcp://")


def test_a_plans_program() -> None:
    sets = ['plans.xy.plane="XY"', 'plans.zx.plane="ZX"', 'plans.zx.data_arc_deg=220.0', 'plans.zx.overshoot_deg=5.0',
            'plans.zx.start_deg=-115.0']
    cfg = load(sets=[*sets, 'plans.zx.program="O91*"'], env={})
    assert cfg.plans["zx"].program == "O91*" and cfg.to_dict()["plans"]["zx"]["program"] == "O91*"
    assert "program" not in cfg.to_dict()["plans"]["xy"]
    with pytest.raises(ConfigError, match=r"plans\.zx\.program must name"):
        load(sets=[*sets, 'plans.zx.program=" "'], env={})
    with pytest.raises(ConfigError, match=r"plans\.zx\.program must be a string"):
        load(sets=[*sets, "plans.zx.program=9102"], env={})


def test_no_controller_no_asyncua(tmp_path: Path) -> None:
    """A daemon run without [controller] never imports asyncua; with it, it does (so the check can fail)."""
    code = (
        "import sys\n"
        "from ballbar.daemon.cli import main\n"
        "rc = main(sys.argv[1:])\n"
        "print('ASYNCUA', 'asyncua' in sys.modules, rc)\n"
    )
    base = [sys.executable, "-c", code, "run", "--source", "sim:?rate=100&speedup=10", "--duration-s", "1.5",
            "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"', "--set", "daemon.analysis_worker=false"]
    without = subprocess.run([*base, "--state-dir", str(tmp_path / "a")], capture_output=True, text=True, timeout=120)
    assert "ASYNCUA False 0" in without.stdout, without.stdout + without.stderr[-2000:]
    port = free_port()  # nothing serves there: the client tries, the daemon runs on
    with_it = subprocess.run([*base, "--state-dir", str(tmp_path / "b"), "--set",
                              f'controller.endpoint="opc.tcp://127.0.0.1:{port}"'],
                             capture_output=True, text=True, timeout=120)
    assert "ASYNCUA True 0" in with_it.stdout, with_it.stdout + with_it.stderr[-2000:]


# ----------------------------------------------------------------------------- the client in process


def test_node_map_default_and_overrides() -> None:
    m = node_map(ControllerSection(endpoint="opc.tcp://h:1", channel="Ch2", axes=["X", "B"],
                                   nodes={"block": "", "spindle_speed": "ns=2;s=/Spindle/actSpeed"}))
    assert m["override"] == "CncInterface/CncChannelList/Ch2/ActOverride"
    assert m["act_pos.B"] == "CncInterface/CncAxisList/B/PosIndirect/ActPos"
    assert "block" not in m and "act_pos.Y" not in m and m["spindle_speed"] == "ns=2;s=/Spindle/actSpeed"


@pytest.fixture
def cnc() -> Iterator[SimCnc]:
    with SimCnc(Story(idle_s=0.3), port=free_port(), omit=["ActProgramBlock"]) as server:
        yield server


def test_client_reads_the_map_and_the_override_change(cnc: SimCnc, caplog: pytest.LogCaptureFixture) -> None:
    msgs: list[dict[str, Any]] = []
    lock = threading.Lock()

    def emit(m: Any) -> None:
        with lock:
            msgs.append(m)

    section = ControllerSection(endpoint=cnc.endpoint, nodes={
        "override": "cnc:CncInterface/cnc:CncChannelList/Channel_1/cnc:ActOverride",  # prefixed: the CNC namespace
        "feed_by_id": "ns=3;s=Channel_1.ActFeedrate",  # a node id, as a vendor's map gives them
        "nope": "ns=3;s=Channel_1.NoSuchNode",
    })
    client = ControllerClient(section, "m", emit)
    client.start()
    try:
        _wait(lambda: client.stats()["connected"], 15, "connected")
        time.sleep(1.0)
        cnc.set_override(75.0)
        _wait(lambda: any(v["name"] == "override" and v["value"] == 75.0 for m in list(msgs) for v in m["values"]),
              5, "the override's change")
        _wait(lambda: sum(v["name"] == "cmd_pos.X" for m in list(msgs) for v in m["values"]) >= 60, 10,
              "a second of positions")
        st = client.stats()
    finally:
        client.stop()
    assert sorted(st["missing"]) == ["block", "nope"]
    missing_lines = [r.getMessage() for r in caplog.records if "has no node" in r.getMessage()]
    assert len(missing_lines) == 2 and any("block" in s and "ActProgramBlock" in s for s in missing_lines)
    assert st["reconnects"] == 0 and st["updates"] > 0 and st["last_update_age_s"] is not None
    assert st["clock_offset_s"] is not None and abs(st["clock_offset_s"]) < 0.5  # one host: the same clock
    for m in msgs:
        validate(m, "controller")
    assert msgs[0]["state"] == "connected" and msgs[0]["missing"] == ["block", "nope"]
    names = {v["name"] for m in msgs for v in m["values"]}
    assert {"program", "override", "feed", "feed_by_id", "g_functions", "act_pos.X", "cmd_pos.Y"} <= names
    xs = [v for m in msgs for v in m["values"] if v["name"] == "cmd_pos.X"]
    steps = sorted(_unix(b["t_source"]) - _unix(a["t_source"]) for a, b in itertools.pairwise(xs))
    assert steps[len(steps) // 2] < 0.03, "every position of the server's 50 Hz, none lost between publishes"
    # each value on the daemon's clock, at or before it was handed on (within the publishing interval)
    for m in msgs:
        for v in m["values"]:
            assert v["t_host"] <= m["t_host"] + 0.05 and m["t_host"] - v["t_host"] < 1.0, (v, m["t_host"])
    assert [v["t_host"] for v in xs] == sorted(v["t_host"] for v in xs)


def test_a_server_clock_that_jumps(cnc: SimCnc, caplog: pytest.LogCaptureFixture) -> None:
    """The server's clock jumps 5 s ahead, then back: each jump is counted and said, the offset starts afresh,
    and the values stay on the daemon's clock (near their arrival), not 5 s off."""
    msgs: list[dict[str, Any]] = []
    client = ControllerClient(ControllerSection(endpoint=cnc.endpoint), "m", msgs.append)
    client.start()
    try:
        _wait(lambda: client.stats()["clock_offset_s"] is not None, 15, "an offset")
        assert abs(client.stats()["clock_offset_s"] or 0.0) < 0.5
        cnc.set_clock(5.0)
        _wait(lambda: client.stats()["clock_jumps"] == 1, 10, "the jump ahead")
        assert -5.5 < (client.stats()["clock_offset_s"] or 0.0) < -4.5
        n = len(msgs)
        time.sleep(1.0)
        after_ahead = msgs[n:]
        cnc.set_clock(0.0)
        _wait(lambda: client.stats()["clock_jumps"] == 2, 10, "the jump back")
        assert abs(client.stats()["clock_offset_s"] or 0.0) < 0.5
        n = len(msgs)
        time.sleep(1.0)
        after_back = msgs[n:]
    finally:
        client.stop()
    jumps = [r.getMessage() for r in caplog.records if "clock jumped" in r.getMessage()]
    said = [float(re.search(r"jumped ([-+][0-9.]+) s", j)[1]) for j in jumps]  # type: ignore[index]
    assert len(said) == 2 and abs(said[0] - 5.0) < 0.3 and abs(said[1] + 5.0) < 0.3, jumps
    for batch in (after_ahead, after_back):
        values = [(m["t_host"], v["t_host"]) for m in batch for v in m["values"]]
        assert values and all(-0.05 < a - b < 1.0 for a, b in values), values[:5]


# ----------------------------------------------------------------------------- the daemon, end to end


def _daemon(tmp: Path, endpoint: str) -> tuple[subprocess.Popen[str], Any]:
    log = open(tmp / "daemon.log", "w")  # noqa: SIM115 - closed by the test
    proc = subprocess.Popen(
        [sys.executable, "-m", "ballbar.daemon.cli", "run", "--source", "sim:?rate=200&speedup=1&repeat=0",
         "--machine-id", "cnc", "--state-dir", str(tmp / "state"), "--set", "zenoh.enabled=false",
         "--set", 'rerun.mode="off"', "--set", "daemon.analysis_worker=false",
         "--set", "daemon.status_interval_s=0.25", "--set", f'controller.endpoint="{endpoint}"',
         "--set", "controller.reconnect_max_s=1.0", "--set", "controller.timeout_s=1.0"],
        env=dict(os.environ, PYTHONUNBUFFERED="1"), stdout=log, stderr=subprocess.STDOUT, text=True)
    return proc, log


def test_daemon_absent_server_then_lost_then_back(tmp_path: Path) -> None:
    """The server absent at start, then started (the daemon connects; a node it lacks is one warning), killed
    mid-run (the status says lost and the bar is read on), restarted (a reconnect); every value in MCAP."""
    port = free_port()
    endpoint = f"opc.tcp://127.0.0.1:{port}/ballbar/simcnc"
    proc, log = _daemon(tmp_path, endpoint)
    marks: dict[str, float] = {}
    cnc: CncProcess | None = None
    try:
        def said(words: str, n: int = 1) -> Any:
            return lambda: (tmp_path / "daemon.log").read_text().count(words) >= n

        _wait(said("cannot connect to"), 30, "a failed attempt")
        time.sleep(2.0)  # absent at start: the daemon runs on the bar alone
        assert proc.poll() is None, (tmp_path / "daemon.log").read_text()
        marks["started"] = time.time()
        cnc = CncProcess(port, "--omit", "ActProgramBlock")
        _wait(said("connected to"), 30, "connected")
        time.sleep(1.0)
        assert cnc.send("override 80")["done"] == "override"
        time.sleep(1.0)
        marks["killed"] = time.time()
        cnc.kill()
        _wait(said("lost opc.tcp://"), 30, "the loss")
        time.sleep(1.5)  # lost for a while: the status says so, the bar is read on
        marks["restarted"] = time.time()
        cnc = CncProcess(port)
        _wait(said("(reconnect)"), 30, "the reconnection")
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
    finally:
        if cnc is not None:
            cnc.kill()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.close()
    text = (tmp_path / "daemon.log").read_text()
    missing = [ln for ln in text.splitlines() if "has no node" in ln]
    assert len(missing) == 1 and "block" in missing[0] and "ActProgramBlock" in missing[0], text[-3000:]
    assert "cannot connect to" in text and "lost " in text, text[-3000:]
    assert "Traceback" not in text, text[-3000:]

    directory = tmp_path / "state" / "recordings"
    seen = validate_recordings(directory)  # every record against its channel's registered schema
    assert seen["/ballbar/controller"] > 10, seen
    paths = list_recordings(directory)
    status = read_logs(paths).status
    ctl = [s for s in status if "controller" in s]
    assert ctl and len(ctl) == len(status), "every status has the controller block"
    states = [s["controller"]["state"] for s in ctl]
    first = states.index("connected")
    assert set(states[:first]) == {"connecting"} and first >= 8, states  # absent for the first seconds
    lost = states.index("lost", first)
    back = states.index("connected", lost)
    assert ctl[back]["controller"]["reconnects"] == 1 and ctl[-1]["controller"]["reconnects"] == 1
    assert ctl[lost]["controller"]["connected"] is False and ctl[lost]["controller"]["last_error"]
    assert ctl[first]["controller"]["missing"] == ["block"] and ctl[back]["controller"]["missing"] == []
    during = [s for s in ctl[lost:back]]
    assert during[-1]["samples"] > during[0]["samples"], "the bar is read on while the controller is lost"
    assert all(s["source_state"] == "connected" for s in ctl[lost:back])

    msgs = read_controller(paths)
    assert [m["state"] for m in msgs if m["state"] != "data"] == ["connected", "lost", "connected"]
    values = [v for m in msgs for v in m["values"]]
    overrides = [v["value"] for v in values if v["name"] == "override"]
    assert overrides[0] == 100.0 and 80.0 in overrides and overrides[-1] == 100.0  # a new server: 100 % again
    assert {"program", "feed", "g_functions", "act_pos.X", "cmd_pos.X", "act_pos.Y"} <= {v["name"] for v in values}
    assert "block" in {v["name"] for v in values}, "the restarted server has the block"
    stamps = [v["t_source"] for v in values if v["t_source"]]
    assert len(stamps) == len(values)
    # the server's source times fall where the server ran: between its start and its kill, or after the restart
    for v in values:
        t = _unix(v["t_source"])
        assert marks["started"] - 1 < t < marks["killed"] + 1 or t > marks["restarted"] - 1, v


def _unix(text: str) -> float:
    import datetime as dt

    return dt.datetime.fromisoformat(text.replace("Z", "+00:00")).timestamp()


def test_simulate_with_the_simulated_cnc(tmp_path: Path) -> None:
    """``ballbar run --simulate --simulate-cnc``: the simulated CNC beside the simulated bar, read and recorded;
    ``--simulate-cnc`` alone is one line and exit 2."""
    base = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--state-dir", str(tmp_path / "state"),
            "--set", "zenoh.enabled=false", "--set", 'rerun.mode="off"']
    alone = subprocess.run([*base, "--simulate-cnc"], capture_output=True, text=True, timeout=60)
    assert alone.returncode == 2 and alone.stderr.strip().splitlines() == [
        line for line in alone.stderr.strip().splitlines() if "--simulate-cnc goes with --simulate" in line]
    out = subprocess.run([*base, "--simulate", "--simulate-cnc", "--duration-s", "8"], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "simulated CNC on opc.tcp://127.0.0.1:" in out.stderr and "controller: connected to" in out.stderr
    paths = list_recordings(tmp_path / "state" / "recordings")
    msgs = read_controller(paths)
    assert msgs[0]["state"] == "connected" and sum(len(m["values"]) for m in msgs) > 50
    assert read_logs(paths).status[-1]["controller"]["connected"] is True


# ----------------------------------------------------------------------------- fusion: the plan by program


def test_the_controllers_program_names_the_plan(tmp_path: Path) -> None:
    """A library of xy and zx, each naming its program; the controller runs O9101 (xy's) throughout while the
    simulated bar runs xy, then zx, in turn: the xy tests are xy by the controller with the signature and timing
    agreeing; a zx test is taken as xy, the controller's, and the disagreement is an event before its outcome.
    Offline, ``ballbar analyze`` of each test's files gives the same recognition."""
    port = free_port()
    cnc = CncProcess(port, "--program", "O9101", "--idle-s", "0")
    toml = tmp_path / "ballbar.toml"
    toml.write_text(
        f'[controller]\nendpoint = "{cnc.endpoint}"\nreconnect_max_s = 1.0\n'
        '[plans.xy]\nplane = "XY"\nsample_hz = 200.0\nprogram = "O9101"\n'
        '[plans.zx]\nplane = "ZX"\nsample_hz = 200.0\nstart_deg = -115.0\novershoot_deg = 5.0\ndata_arc_deg = 220.0\n'
        'program = "O91*2"\n')
    library = json.dumps(load(str(toml), env={}).to_dict()["plans"])
    proc = log = None
    try:
        # the bar in a process of its own (a pty: a busy daemon makes it wait, never lose samples)
        with DeviceProcess("--rate", "200", "--speedup", "20", "--repeat", "4", "--gap-s", "2", "--library", library,
                           "--wait") as dev:
            log = open(tmp_path / "daemon.log", "w")  # noqa: SIM115 - closed below
            proc = subprocess.Popen(
                [sys.executable, "-m", "ballbar.daemon.cli", "run", "--config", str(toml), "--source", dev.url,
                 "--machine-id", "cnc", "--state-dir", str(tmp_path / "state"), "--set", "zenoh.enabled=false",
                 "--set", 'rerun.mode="off"'], stdout=log, stderr=subprocess.STDOUT, text=True,
                env=dict(os.environ, PYTHONUNBUFFERED="1"))
            _wait(lambda: "the controller runs O9101" in (tmp_path / "daemon.log").read_text(), 60,
                  "the controller's program")
            dev.send("start")
            dev.wait_event("done", timeout=120)
            # the fourth test is zx's: its disagreement comes at its feed-out, its rejection just after
            _wait(lambda: (tmp_path / "daemon.log").read_text().count("its signature names zx") >= 2, 60,
                  "the fourth test")
            time.sleep(2.0)
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(15) == 0
    finally:
        cnc.kill()
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait()
        if log is not None:
            log.close()
    text = (tmp_path / "daemon.log").read_text()
    lg = read_logs(list_recordings(tmp_path / "state" / "recordings"))
    tests = [r for r in lg.results if r.get("kind") == "test"]
    ours = [r for r in tests if "controller" in r]
    assert ours, text[-3000:]
    agreed = [r for r in ours if r["plan"]["name"] == "xy" and r["controller"]["agrees"]]
    assert agreed, [r["controller"] for r in ours]
    for r in agreed:
        assert r["recognition"]["method"] == "controller"
        assert r["controller"] == {**r["controller"], "program": "O9101", "plan": "xy", "used": True,
                                   "signature_plan": "xy", "timing_fits": True}
    disagreements = [e for e in lg.events if e.get("event") == "controller_disagrees"]
    assert disagreements, text[-3000:]
    for e in disagreements:
        validate(e, "mcap-event")  # as the log stores an event: without kind
        assert e["plan"] == "xy" and e["program"] == "O9101" and e["signature_plan"] == "zx"
        assert "zx" in e["message"] and "xy" in e["message"]
    assert "controller_disagrees" not in {e.get("event") for e in lg.events if e.get("plan") == "zx"}
    # offline, each test's own files (rotated per test) say what the controller ran: the same recognition
    for r in agreed:
        off = subprocess.run([sys.executable, "-m", "ballbar.daemon.cli", "analyze", str(tmp_path / "state" /
                              "recordings"), "--test-id", r["test_id"], "--json"], capture_output=True, text=True,
                             timeout=120)
        assert off.returncode == 0, off.stderr[-2000:]
        res = json.loads(off.stdout)
        assert res["recognition"] == r["recognition"] and res["controller"] == r["controller"]
