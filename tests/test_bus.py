"""The Zenoh bus: real sessions on loopback, subscribers in separate processes.

Every session listens or connects on 127.0.0.1 only, on free ports, with
multicast scouting off: nothing reaches the LAN.  Subscriber processes are the
``ballbar.tools.subscribe`` command, started with ``subprocess`` (fork+exec:
nothing runs in a forked copy of a process holding a Zenoh session).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from schemacheck import validate

from ballbar import SCHEMA_VERSION
from ballbar.daemon.bus import (
    DEFAULT_LISTEN,
    BusConfigError,
    ZenohBus,
    ZenohConfig,
    parse_time_us,
)
from ballbar.daemon.samples import SampleBatch
from ballbar.protocol.messages import stamp, to_json

pytestmark = pytest.mark.usefixtures("no_leaks")

BASE = dt.datetime(2025, 3, 1, 8, 0, tzinfo=dt.UTC)
WAIT_BEFORE_CLOSE_US = 500_000  # Zenoh's BLOCK give-up time in the frozen-peer test (default 5 s)


# --------------------------------------------------------------------------- helpers


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def endpoint(port: int | None = None) -> str:
    return f"tcp/127.0.0.1:{port or free_port()}"


def iso(seconds: float) -> str:
    return (BASE + dt.timedelta(seconds=seconds)).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def circle(i: int, direction: str = "ccw", pad: int = 0) -> dict[str, Any]:
    return {
        "kind": "circle",
        "schema_version": SCHEMA_VERSION,
        "machine_id": "m",
        "direction": direction,
        "test_index": 1,
        "test_id": f"m-{i}",
        "t_wall": iso(10 * i + (0 if direction == "ccw" else 3)),
        "residual_rms_um": 0.31,
        "parameters": {"backlash_x_um": {"value": 4.1, "unit": "um"}},
        "last_sample_t": math.nan,
        "pad": "x" * pad,
    }


def result_msg(i: int) -> dict[str, Any]:
    return {
        "kind": "test",
        "schema_version": SCHEMA_VERSION,
        "machine_id": "m",
        "test_index": 1,
        "test_id": f"m-{i}",
        "t_wall": iso(10 * i + 5),
        "iso230_4": {"G_b_um": 7.5},
        "timing": {"measured_feed_mm_min": 999.0},
    }


def wait_until(pred: Callable[[], bool], timeout: float = 10.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.01)


def session_config(ep: str, mode: str = "client") -> zenoh.Config:
    return ZenohConfig(mode=mode, connect=[ep], listen=[] if mode == "peer" else None).to_zenoh_config()


@contextlib.contextmanager
def running_bus(machine: str = "m", **kw: Any) -> Iterator[tuple[ZenohBus, str]]:
    ep = endpoint()
    bus = ZenohBus(machine, ZenohConfig(listen=[ep], options=kw.pop("options", {})), **kw)
    try:
        yield bus, ep
    finally:
        bus.stop()
        assert bus.wait_closed(15)


@contextlib.contextmanager
def client(ep: str) -> Iterator[zenoh.Session]:
    s = zenoh.open(session_config(ep))
    try:
        yield s
    finally:
        s.close()


@contextlib.contextmanager
def subscriber(*args: str) -> Iterator[subprocess.Popen[str]]:
    p = subprocess.Popen(
        [sys.executable, "-m", "ballbar.tools.subscribe", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        yield p
    finally:
        if p.poll() is None:
            p.kill()  # also ends a stopped (SIGSTOP) process
        p.communicate(timeout=10)


def lines(out: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in out.splitlines() if line.strip()]


def get(session: zenoh.Session, selector: str) -> tuple[list[zenoh.Sample], list[str]]:
    ok, err = [], []
    for reply in session.get(selector, timeout=5):
        if reply.ok is not None:
            ok.append(reply.ok)
        elif reply.err is not None:
            err.append(reply.err.payload.to_string())
    return ok, err


@pytest.fixture(scope="module", autouse=True)
def zenoh_runtime() -> None:
    """Zenoh's runtime keeps a few descriptors (epoll, eventfd) once first used: not a test's leak."""
    with running_bus("warmup") as (bus, ep), client(ep) as c:
        sub = c.declare_subscriber("ballbar/warmup/**", lambda s: None)
        wait_until(lambda: bus.has_subscribers("test"), what="the warm-up subscriber")
        bus.on_message(result_msg(0))
        get(c, "ballbar/warmup/last/*")
        list(c.liveliness().get("ballbar/warmup/alive", timeout=2))
        sub.undeclare()


# --------------------------------------------------------------------------- configuration


def test_default_is_a_loopback_peer_with_nothing_on_the_lan() -> None:
    cfg = ZenohConfig().to_zenoh_config()
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("listen/endpoints")) == list(DEFAULT_LISTEN) == ["tcp/127.0.0.1:7447"]
    assert json.loads(cfg.get_json("connect/endpoints")) == []
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("transport/shared_memory/enabled")) is False
    client_cfg = ZenohConfig(mode="client", connect=["tcp/10.0.0.5:7447"]).to_zenoh_config()
    assert json.loads(client_cfg.get_json("listen/endpoints")) == []
    assert ZenohConfig().describe() == "peer, listen tcp/127.0.0.1:7447, connect -, multicast scouting off"


def test_settings_pass_through_and_override_a_config_file(tmp_path: Path) -> None:
    f = tmp_path / "zenoh.json5"
    f.write_text(
        '{ mode: "client", connect: { endpoints: ["tcp/10.1.2.3:7447"] },\n'
        "  transport: { link: { tx: { lease: 3000 } } } }  // TLS and ACL would go here\n"
    )
    cfg = ZenohConfig(config_file=str(f)).to_zenoh_config()
    assert json.loads(cfg.get_json("mode")) == "client"
    assert json.loads(cfg.get_json("connect/endpoints")) == ["tcp/10.1.2.3:7447"]
    assert json.loads(cfg.get_json("transport/link/tx/lease")) == 3000
    cfg = ZenohConfig(
        config_file=str(f),
        mode="peer",
        listen=["tcp/0.0.0.0:7447"],
        connect=[],
        multicast_scouting=True,
        options={"transport/link/tx/lease": 5000},
    ).to_zenoh_config()
    assert json.loads(cfg.get_json("mode")) == "peer"
    assert json.loads(cfg.get_json("listen/endpoints")) == ["tcp/0.0.0.0:7447"]
    assert json.loads(cfg.get_json("connect/endpoints")) == []
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is True
    assert json.loads(cfg.get_json("transport/link/tx/lease")) == 5000


@pytest.mark.parametrize(
    ("kwargs", "names"),
    [
        ({"mode": "bogus"}, "zenoh.mode"),
        ({"listen": ["nonsense"]}, "zenoh.listen"),
        ({"connect": "tcp/127.0.0.1:7447"}, "zenoh.connect"),
        ({"options": {"transport/link/tx/lease": "soon"}}, "zenoh.options 'transport/link/tx/lease'"),
        ({"options": {"no/such/key": 1}}, "zenoh.options 'no/such/key'"),
        ({"options": {"scouting/multicast/enabled": "yes"}}, "zenoh.options 'scouting/multicast/enabled'"),
        ({"config_file": "/nonexistent/zenoh.json5"}, "zenoh.config_file: /nonexistent/zenoh.json5"),
        ({"config_file": "BAD"}, "zenoh.config_file"),
    ],
)
def test_a_bad_setting_is_one_line_naming_its_key(tmp_path: Path, kwargs: dict[str, Any], names: str) -> None:
    if kwargs.get("config_file") == "BAD":
        bad = tmp_path / "bad.json5"
        bad.write_text("{ mode: 'peer', listen: ")
        kwargs = {"config_file": str(bad)}
    with pytest.raises(BusConfigError) as info:
        ZenohConfig(**kwargs).to_zenoh_config()
    msg = str(info.value)
    assert msg.startswith(names), msg
    assert "\n" not in msg and ".rs:" not in msg, msg
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize("machine", ["", "a/b", "m*", "mill 3"])
def test_a_machine_id_must_be_one_key_chunk(machine: str) -> None:
    with pytest.raises(BusConfigError, match="machine_id"):
        ZenohBus(machine, ZenohConfig(listen=[endpoint()]))


def test_json_is_strict_and_time_parses_both_ways() -> None:
    text = to_json({"a": math.nan, "b": [np.float64(1.5), np.int64(2), math.inf], "c": (1, 2)})
    assert json.loads(text) == {"a": None, "b": [1.5, 2, None], "c": [1, 2]}
    assert parse_time_us("2025-03-01T08:00:00.250Z") == parse_time_us(BASE.timestamp() + 0.25)
    assert parse_time_us("2025-03-01T08:00:00.250") == parse_time_us("1740816000.25")
    with pytest.raises(ValueError, match="neither ISO 8601 nor Unix seconds"):
        parse_time_us("yesterday")


# --------------------------------------------------------------------------- publishing


def test_a_separate_process_receives_each_circle_and_test() -> None:
    with (
        running_bus() as (bus, ep),
        subscriber("--machine", "m", "--connect", ep, "--count", "3", "--timeout", "20") as p,
    ):
        wait_until(lambda: bus.has_subscribers("circle") and bus.has_subscribers("test"), what="the subscriber")
        sent = [circle(1, "ccw"), circle(1, "cw"), result_msg(1)]
        for msg in sent:
            bus.on_message(msg)
        out, err = p.communicate(timeout=20)
        assert p.returncode == 0, err
    got = lines(out)
    assert [(g["kind"], g.get("direction")) for g in got] == [("circle", "ccw"), ("circle", "cw"), ("test", None)]
    for g, s in zip(got, sent, strict=True):
        assert g["schema_version"] == SCHEMA_VERSION and g["machine_id"] == "m" and g["t_wall"] == s["t_wall"]
    assert got[0]["last_sample_t"] is None  # NaN goes out as null: plain JSON for every plant service


def test_a_test_and_its_alert_reach_a_subscriber_of_both_in_the_order_put() -> None:
    """Zenoh-python runs each subscriber's callbacks on a thread of its own: the tool subscribes once, so a
    test's result and the alert after it (two keys) are never printed the other way round (with two
    subscribers, 8 to 36 of 4000 such puts came out of order here)."""
    n = 1000
    with (
        running_bus() as (bus, ep),
        subscriber("--machine", "m", "--connect", ep, "--topic", "test", "--topic", "alert", "--count", str(2 * n),
                   "--timeout", "60", "--format", "json") as p,
    ):
        wait_until(lambda: bus.has_subscribers("test") and bus.has_subscribers("alert"), what="the subscriber")
        for i in range(n):
            bus.on_message(result_msg(i))
            bus.on_message(circle(i))  # not asked for: not printed
            bus.on_message({**stamp("m"), "kind": "alert", "test_id": f"m-{i}", "alert": "verdict"})
        out, err = p.communicate(timeout=60)
        assert p.returncode == 0, err
    got = [(g["kind"], g["test_id"]) for g in lines(out)]
    assert got == [(k, f"m-{i}") for i in range(n) for k in ("test", "alert")]


def test_topics_encoding_and_payloads() -> None:
    received: list[zenoh.Sample] = []
    with running_bus() as (bus, ep), client(ep) as c:
        c.declare_subscriber("ballbar/m/**", received.append)
        wait_until(lambda: bus.has_subscribers("status"), what="the subscriber")
        bus.on_message(circle(1))
        bus.on_message(result_msg(1))
        # as the daemon makes them: the envelope from stamp(); the bus sends each as it was handed
        bus.on_message({**stamp("m"), "kind": "event", "event": "unplugged", "origin": "source", "detail": "EIO"})
        bus.on_message({**stamp("m"), "kind": "status", "sample_rate_hz": 1000.0, "queues": {"zenoh": {"depth": 0}},
                        "outputs": {}})
        bus.on_message({**stamp("m"), "kind": "config", "config": {"daemon": {"machine_id": "m"}}})
        bus.on_message({"kind": "mystery"})
        wait_until(lambda: len(received) >= 5, what="five samples")
        time.sleep(0.1)
        stats = bus.stats()
    by_key = {str(s.key_expr): s for s in received}
    assert sorted(by_key) == [
        "ballbar/m/config",
        "ballbar/m/event",
        "ballbar/m/result/circle",
        "ballbar/m/result/test",
        "ballbar/m/status",
    ]
    for s in received:
        assert s.encoding == zenoh.Encoding.APPLICATION_JSON
        body = json.loads(s.payload.to_bytes())
        assert body["schema_version"] == SCHEMA_VERSION and body["machine_id"] == "m"
        parse_time_us(body["t_wall"])
    status = json.loads(by_key["ballbar/m/status"].payload.to_bytes())
    zs = status["outputs"]["zenoh"]  # the bus' own counters as of the put, once (not also at the top)
    assert zs["connected"] is True and zs["links"]["client"] == 1 and "zenoh" not in status
    assert json.loads(by_key["ballbar/m/event"].payload.to_bytes())["event"] == "unplugged"
    assert stats["skipped"] == 1 and stats["put_errors"] == 0
    assert stats["published"] == {
        "result/circle": 1,
        "result/test": 1,
        "event": 1,
        "status": 1,
        "config": 1,
        "samples": 0,
        "alert": 0,
        "result/set": 0,
    }


def test_decimated_samples_when_asked_for() -> None:
    received: list[dict[str, Any]] = []
    with running_bus(samples_hz=50.0) as (bus, ep), client(ep) as c:
        c.declare_subscriber("ballbar/m/samples", lambda s: received.append(json.loads(s.payload.to_bytes())))
        wait_until(lambda: bus.has_subscribers("samples"), what="the subscriber")
        n = 1000  # one second at 1 kHz in 50 batches
        t = 5000.0 + np.arange(n) / 1000.0
        for k in range(0, n, 20):
            s = slice(k, k + 20)
            bus.on_batch(
                SampleBatch.from_columns(
                    t[s], np.full(20, np.nan), 100.0 + t[s] * 0, np.arange(k, k + 20), np.zeros(20), source="sim"
                )
            )
        wait_until(lambda: sum(len(m["t_host"]) for m in received) >= 50, what="50 samples")
        time.sleep(0.1)
    t_out = np.concatenate([m["t_host"] for m in received])
    assert 49 <= t_out.size <= 51
    assert np.allclose(np.diff(t_out), 0.02, atol=1e-3)
    assert received[0]["kind"] == "samples" and received[0]["t_device"][0] is None
    for m in received:
        validate(m, "samples")


def test_no_samples_topic_by_default() -> None:
    with running_bus() as (bus, _):
        bus.on_batch(SampleBatch.from_columns([1.0], [1.0], [100.0], [0], [0]))
        assert bus.stats()["published"]["samples"] == 0 and not bus.has_subscribers("samples")


# --------------------------------------------------------------------------- queryables and late joiners


def test_last_and_history_answer_from_the_daemons_records() -> None:
    def loader() -> list[dict[str, Any]]:  # results persisted before a restart
        return [result_msg(-2), result_msg(-1), {"kind": "status"}]

    with running_bus(history_loader=loader) as (bus, ep), client(ep) as c:
        assert get(c, "ballbar/m/last/circle") == ([], [])
        for i in range(3):
            bus.on_message(circle(i))
            bus.on_message(result_msg(i))
        ok, _ = get(c, "ballbar/m/last/test")
        assert [json.loads(s.payload.to_bytes())["test_id"] for s in ok] == ["m-2"]
        assert ok[0].encoding == zenoh.Encoding.APPLICATION_JSON
        ok, _ = get(c, "ballbar/m/last/*")
        assert sorted(str(s.key_expr) for s in ok) == ["ballbar/m/last/circle", "ballbar/m/last/test"]

        def history(selector: str) -> dict[str, Any]:
            ok, err = get(c, selector)
            assert not err and len(ok) == 1, err
            doc: dict[str, Any] = json.loads(ok[0].payload.to_bytes())
            doc["ids"] = [r["test_id"] for r in doc["results"]]
            return doc

        doc = history("ballbar/m/history/test")
        assert doc["ids"] == ["m--2", "m--1", "m-0", "m-1", "m-2"] and doc["more"] is False
        assert doc["schema_version"] == SCHEMA_VERSION and doc["kind"] == "history" and doc["topic"] == "test"
        doc = history("ballbar/m/history/test?limit=2")
        assert doc["ids"] == ["m-1", "m-2"] and doc["more"] is True
        since = result_msg(-1)["t_wall"]
        doc = history(f"ballbar/m/history/test?since={since};limit=2")
        assert doc["ids"] == ["m-0", "m-1"] and doc["more"] is True
        doc = history(f"ballbar/m/history/test?since={doc['results'][-1]['t_wall']}&limit=2")
        assert doc["ids"] == ["m-2"] and doc["more"] is False
        doc = history(f"ballbar/m/history/test?since={parse_time_us(since) / 1e6}")
        assert doc["ids"] == ["m-0", "m-1", "m-2"]
        assert history("ballbar/m/history/circle")["ids"] == ["m-0", "m-1", "m-2"]
        ok, _ = get(c, "ballbar/m/history/*?limit=1")
        assert sorted(str(s.key_expr) for s in ok) == [
            "ballbar/m/history/alert", "ballbar/m/history/circle", "ballbar/m/history/event",
            "ballbar/m/history/set", "ballbar/m/history/test"
        ]
        for bad, says in [
            ("since=yesterday", "since"),
            ("limit=0", "limit"),
            ("limit=x", "limit"),
            ("sinse=1", "unknown parameter 'sinse'"),
        ]:
            ok, err = get(c, f"ballbar/m/history/test?{bad}")
            assert not ok and len(err) == 1 and says in json.loads(err[0])["error"], err
            validate(json.loads(err[0]), "error")


def test_a_late_joiner_catches_up_through_the_history() -> None:
    with running_bus() as (bus, ep):
        for i in range(2):  # nobody listens yet
            bus.on_message(circle(i))
            bus.on_message(result_msg(i))
        with subscriber("--machine", "m", "--connect", ep, "--history", "--count", "5", "--timeout", "20") as p:
            wait_until(lambda: bus.has_subscribers("test"), what="the late subscriber")
            wait_until(lambda: bus.stats()["queries"] >= 2, what="the history queries")
            bus.on_message(result_msg(2))
            out, err = p.communicate(timeout=20)
            assert p.returncode == 0, err
    got = [(g["kind"], g["test_id"]) for g in lines(out)]
    assert got == [("circle", "m-0"), ("test", "m-0"), ("circle", "m-1"), ("test", "m-1"), ("test", "m-2")]


def test_liveliness_token_while_running_withdrawn_on_stop() -> None:
    changes: list[tuple[str, zenoh.SampleKind]] = []
    ep = endpoint()
    bus = ZenohBus("m", ZenohConfig(listen=[ep]))
    try:
        with client(ep) as c:
            replies = list(c.liveliness().get("ballbar/*/alive", timeout=5))
            assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == ["ballbar/m/alive"]
            c.liveliness().declare_subscriber(
                "ballbar/*/alive", lambda s: changes.append((str(s.key_expr), s.kind)), history=True
            )
            wait_until(lambda: len(changes) == 1, what="the token")
            t0 = time.monotonic()
            bus.stop()
            wait_until(lambda: len(changes) == 2, timeout=2, what="the token's withdrawal")
            assert time.monotonic() - t0 < 1.0
    finally:
        bus.stop()
        bus.wait_closed(15)
    assert changes == [("ballbar/m/alive", zenoh.SampleKind.PUT), ("ballbar/m/alive", zenoh.SampleKind.DELETE)]


# --------------------------------------------------------------------------- peers that misbehave


def test_a_frozen_subscriber_stalls_neither_the_bus_nor_the_others_nor_stop() -> None:
    healthy: list[str] = []
    options = {"transport/link/tx/queue/congestion_control/block/wait_before_close": WAIT_BEFORE_CLOSE_US}
    with (
        running_bus(options=options, close_timeout_s=1.0) as (bus, ep),
        client(ep) as c,
        subscriber("--machine", "m", "--connect", ep, "--topic", "all", "--timeout", "60") as frozen,
    ):
        c.declare_subscriber(
            "ballbar/m/result/circle", lambda s: healthy.append(json.loads(s.payload.to_bytes())["test_id"])
        )
        wait_until(
            lambda: bus.stats()["links"]["client"] == 2 and bus.has_subscribers("circle"), what="both subscribers"
        )
        time.sleep(0.3)  # the frozen one's subscriptions are in place too
        os.kill(frozen.pid, signal.SIGSTOP)
        n, pad = 300, 64_000  # ~19 MB: far more than the socket buffers and Zenoh's queues hold
        took = []
        t0 = time.monotonic()
        for i in range(n):
            a = time.monotonic()
            bus.on_message(circle(i, pad=pad))
            if i % 10 == 0:
                bus.on_message({"kind": "status", "i": i})
            took.append(time.monotonic() - a)
        total = time.monotonic() - t0
        stats = bus.stats()
        # BLOCK waits for a frozen reader at most wait_before_close, once; DROP (status) never waits
        assert total < WAIT_BEFORE_CLOSE_US / 1e6 + 4.0, (total, stats)
        assert max(took) < WAIT_BEFORE_CLOSE_US / 1e6 + 1.0
        assert stats["slow_puts"] >= 1, "the frozen subscriber never pushed back: the test proves nothing"
        wait_until(lambda: len(healthy) == n, timeout=10, what="every result at the healthy subscriber")
        assert healthy == [f"m-{i}" for i in range(n)]
        t0 = time.monotonic()
        bus.stop()
        assert time.monotonic() - t0 < 1.5
        frozen.kill()  # the close left in the background ends once the frozen peer is gone
        assert bus.wait_closed(10)


def test_a_vanished_subscriber_is_nothing_to_wait_for() -> None:
    with running_bus() as (bus, ep):
        with subscriber("--machine", "m", "--connect", ep, "--timeout", "60") as p:
            wait_until(lambda: bus.has_subscribers("test"), what="the subscriber")
            p.kill()
        t0 = time.monotonic()
        for i in range(50):
            bus.on_message(circle(i, pad=10_000))
        assert time.monotonic() - t0 < 1.0
        wait_until(lambda: not bus.has_subscribers("test"), timeout=5, what="the subscriber's departure")
        with subscriber("--machine", "m", "--connect", ep, "--count", "1", "--timeout", "20") as p:
            wait_until(lambda: bus.has_subscribers("test"), what="the new subscriber")
            bus.on_message(result_msg(7))
            out, err = p.communicate(timeout=20)
        assert p.returncode == 0, err
        assert [g["test_id"] for g in lines(out)] == ["m-7"]
        assert bus.stats()["put_errors"] == 0


def test_a_session_that_cannot_open_is_retried_and_keeps_the_records() -> None:
    blocker = socket.socket()
    blocker.bind(("127.0.0.1", 0))
    blocker.listen()
    ep = endpoint(blocker.getsockname()[1])
    bus = ZenohBus("m", ZenohConfig(listen=[ep]))
    try:
        assert not bus.connected and "Address already in use" in (bus.stats()["open_error"] or "")
        bus.on_message(result_msg(1))  # not published, but kept
        assert bus.stats()["not_connected"] == 1
        blocker.close()
        wait_until(lambda: bus.connected, timeout=10, what="the retried session")
        with client(ep) as c:
            ok, _ = get(c, "ballbar/m/last/test")
            assert [json.loads(s.payload.to_bytes())["test_id"] for s in ok] == ["m-1"]
    finally:
        blocker.close()
        bus.stop()
        bus.wait_closed(15)
    bus.stop()  # twice is fine
    bus.on_message(result_msg(2))  # after stop: counted, not raised


# --------------------------------------------------------------------------- the subscriber tool


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_tool_exits_cleanly_on_a_signal(sig: signal.Signals) -> None:
    with running_bus() as (bus, ep), subscriber("--machine", "m", "--connect", ep) as p:
        wait_until(lambda: bus.has_subscribers("test"), what="the subscriber")
        t0 = time.monotonic()
        p.send_signal(sig)
        _, err = p.communicate(timeout=5)
        assert p.returncode == 0 and "Traceback" not in err, err
        assert time.monotonic() - t0 < 3.0


def test_the_tool_waits_for_a_daemon_that_starts_later() -> None:
    """Services start in any order: a subscriber started first says it is waiting, then gets the results."""
    ep = endpoint()
    p = subprocess.Popen(
        [sys.executable, "-m", "ballbar.tools.subscribe", "--connect", ep, "--topic", "test", "--count", "1",
         "--timeout", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert p.stderr is not None
        line = p.stderr.readline()  # said at once, before any daemon exists
        assert line.startswith("ballbar-subscribe: waiting for a daemon or router (client") and "retrying" in line
        assert p.poll() is None
        time.sleep(1.0)  # a retry or two fails meanwhile
        bus = ZenohBus("m", ZenohConfig(listen=[ep]))
        try:
            wait_until(lambda: bus.has_subscribers("test"), timeout=30, what="the waiting subscriber")
            bus.on_message(result_msg(1))
            out, err = p.communicate(timeout=20)
        finally:
            bus.stop()
            assert bus.wait_closed(15)
        assert p.returncode == 0, err
        assert [g["test_id"] for g in lines(out)] == ["m-1"]
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()


def test_sigterm_and_the_timeout_are_kept_while_zenoh_waits_on_a_peer_that_does_not_answer() -> None:
    """A listener that accepts TCP and never speaks (a frozen daemon): Zenoh's open waits ~10 s for its
    handshake, and Python runs signal handlers only in the main thread between bytecodes. It held SIGTERM
    ~9 s, and once a subscriber whose daemon was killed took over 10 s to exit."""
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen()
    ep = endpoint(silent.getsockname()[1])
    try:
        with subscriber("--connect", ep, "--timeout", "60") as p:
            time.sleep(1.5)  # mid-handshake
            assert p.poll() is None
            t0 = time.monotonic()
            p.send_signal(signal.SIGTERM)
            p.wait(10)
            took = time.monotonic() - t0
            assert p.returncode == 0 and took < 1.0, (p.returncode, took)
        t0 = time.monotonic()
        r = subprocess.run(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--connect", ep, "--timeout", "1.5"],
            capture_output=True, text=True, timeout=30,
        )
        took = time.monotonic() - t0
        assert r.returncode == 1 and "no connection within the timeout" in r.stderr, r.stderr
        assert took < 1.5 + 3.0, took  # the interpreter's start and exit on a busy machine
    finally:
        silent.close()


def test_the_tool_says_what_went_wrong() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "ballbar.tools.subscribe", "--connect", endpoint(), "--no-wait"],
        capture_output=True,
        text=True,
        timeout=20,
    )
    assert r.returncode == 1 and r.stderr.startswith("ballbar-subscribe: cannot connect"), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run(
        [sys.executable, "-m", "ballbar.tools.subscribe", "--count", "0"], capture_output=True, text=True, timeout=20
    )
    assert r.returncode == 2 and "--count" in r.stderr
    with running_bus() as (_, ep):
        r = subprocess.run(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--connect", ep, "--count", "1", "--timeout", "0.5"],
            capture_output=True,
            text=True,
            timeout=20,
        )
    assert r.returncode == 1 and "0 of 1 lines" in r.stderr


def test_the_defaults_find_each_other() -> None:
    """A daemon with default settings and the tool with default settings: no flags, no router."""
    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", 7447))
        except OSError:
            pytest.skip("port 7447 is in use on this host")
    machine = f"default-{os.getpid()}"
    bus = ZenohBus(machine)
    try:
        if not bus.connected:
            pytest.skip(f"port 7447 was taken meanwhile: {bus.stats()['open_error']}")
        with subscriber("--machine", machine, "--count", "1", "--timeout", "20") as p:
            wait_until(lambda: bus.has_subscribers("test"), what="the subscriber")
            bus.on_message({**result_msg(1), "machine_id": machine})
            out, err = p.communicate(timeout=20)
        assert p.returncode == 0, err
        assert [g["machine_id"] for g in lines(out)] == [machine]
    finally:
        bus.stop()
        bus.wait_closed(15)


def test_stop_is_bounded_even_when_close_hangs(monkeypatch: pytest.MonkeyPatch) -> None:
    ep = endpoint()
    bus = ZenohBus("m", ZenohConfig(listen=[ep]), close_timeout_s=0.3)
    release = threading.Event()
    real = bus._session
    assert real is not None

    class Stuck:
        def close(self) -> None:
            release.wait(10)
            real.close()

    closing = Stuck()
    monkeypatch.setattr(bus, "_session", closing)
    t0 = time.monotonic()
    bus.stop()
    assert time.monotonic() - t0 < 0.6
    assert not bus.wait_closed(0)
    release.set()
    assert bus.wait_closed(10)


def test_events_have_a_history_to_catch_up_from() -> None:
    """Events to a subscriber that stops reading are best effort: ``history/event`` is how it catches up."""
    bus = ZenohBus("evh", ZenohConfig(listen=[f"tcp/127.0.0.1:{free_port()}"]))
    try:
        for i in range(5):
            bus.on_message(
                {"kind": "event", "event": "feed_in", "test_id": f"evh-{i}", "t_wall": f"2026-01-01T00:00:0{i}Z"}
            )
        doc = json.loads(bus.history_payload("event", limit=3))
        assert doc["topic"] == "event" and doc["count"] == 3 and doc["more"] is True
        assert [r["test_id"] for r in doc["results"]] == ["evh-2", "evh-3", "evh-4"]
    finally:
        bus.stop()
