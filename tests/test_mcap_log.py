"""The MCAP log: round trip, size, crash safety, rotation, retention, full disk, analyze equivalence."""

from __future__ import annotations

import errno
import io
import json
import logging
import math
import os
import signal
import subprocess
import sys
import time
from decimal import ROUND_HALF_EVEN, Decimal
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zstandard
from mcap.reader import NonSeekingReader, make_reader
from mcap.writer import Writer

from ballbar.analysis.errors import DataError
from ballbar.analysis.plan import TestPlan
from ballbar.daemon import mcap as mcap_log
from ballbar.daemon.cli import main as cli_main
from ballbar.daemon.listeners import to_json
from ballbar.daemon.mcap import (
    SCHEMAS,
    TOPIC_CONTROLLER,
    TOPIC_OTHER,
    TOPIC_SAMPLES,
    LogConfigError,
    McapLogger,
    list_recordings,
    read_log,
    read_logs,
    read_mcap,
    read_results,
    scaled_ints,
)
from ballbar.daemon.mcap import writer as mcap_writer
from ballbar.daemon.recordings import read_recording
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.daemon.spool import read_spool
from ballbar.protocol import Status
from ballbar.tools.bench.bench_mcap import feed_paced, serial_batches
from ballbar.tools.simulator import MachineModel, simulate
from ballbar.tools.simulator_cli import write_csv

pytestmark = pytest.mark.usefixtures("no_leaks")


# ----------------------------------------------------------------------------- helpers


def grid(ns: np.ndarray) -> np.ndarray:
    """Numbers the log stores exactly: integers of 1e-9 (ns of a second, pm of a millimetre)."""
    return np.asarray(ns, dtype=np.int64) / 1e9


def make_batch(
    k0: int, n: int, *, fs: float = 1000.0, t0: float = 100.0, device: bool = True, source: str = "sim:",
    status: int = 0, events: tuple[SourceEvent, ...] = (),
) -> SampleBatch:
    """n samples from sample number k0, on the exact grid; the length wobbles by micrometres."""
    k = np.arange(k0, k0 + n)
    step_ns = round(1e9 / fs)
    t_dev = grid(k * step_ns) if device else np.full(n, np.nan)
    t_host = grid(round(t0 * 1e9) + k * (step_ns + 13))  # a host clock 13 ppm fast
    length = grid(100_000_000_000 + np.rint(3e6 * np.sin(k / 50.0)).astype(np.int64) + (k * 7919) % 211)
    return SampleBatch.from_columns(t_host, t_dev, length, k, np.full(n, status), events, source)


def files(state: Path) -> list[Path]:
    return list_recordings(state / "recordings")


def one_file(state: Path) -> Path:
    """A finished log file of samples 0 to 1999, one chunk per 100 of them."""
    lg = McapLogger(state, "m")
    for k in range(0, 2000, 100):
        lg.on_batch(make_batch(k, 100))
        lg.flush()
    lg.stop()
    (path,) = files(state)
    return path


def assert_same_samples(a: SampleBatch, b: SampleBatch) -> None:
    assert len(a) == len(b)
    for name in ("t_host", "t_device", "length_mm"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
    assert np.array_equal(a.seq, b.seq)
    assert np.array_equal(a.status, b.status)


@pytest.fixture
def state(tmp_path: Path) -> Path:
    return tmp_path / "state"


# ----------------------------------------------------------------------------- round trip


def test_round_trip_is_exact(state: Path) -> None:
    lost = SourceEvent(EventKind.LOST, t_host=100.5, source="sim:", count=3, seq=40, detail="gap")
    unplug = SourceEvent(EventKind.UNPLUGGED, t_host=100.9, source="sim:", detail="device reports readiness")
    parts = [
        make_batch(0, 40),
        make_batch(43, 30, events=(lost,)),  # a 3-sample gap
        make_batch(73, 25, device=False),  # no device clock: split into its own message
        make_batch(98, 10, source="serial:/dev/ttyUSB1"),  # another source
        make_batch(108, 5, status=int(Status.OVER_RANGE)),
        SampleBatch.empty(events=(unplug,), source="sim:"),
    ]
    fault = make_batch(113, 6, status=int(Status.SENSOR_FAULT))
    fault = SampleBatch.from_columns(
        fault.t_host, fault.t_device, np.where(np.arange(6) % 2, np.nan, fault.length_mm), fault.seq, fault.status
    )
    parts.append(fault)
    parts.append(make_batch(119, 1))  # a lone sample
    config = {"kind": "config", "machine_id": "m1", "plan": {"radius_mm": 100.0}, "t_host": 99.0}
    circle = {"kind": "circle", "test_index": 1, "t_host": 100.2, "parameters": {"x": {"value": 1.5}}}
    test = {"kind": "test", "test_index": 1, "t_host": 100.3, "nan": math.nan, "np": np.float64(2.5)}
    status = {"kind": "status", "t_host": 100.4, "rate_hz": 999.8}
    feed_in = {"kind": "event", "event": "feed_in", "t_host": 100.1, "t_s": 1.25}
    odd = {"kind": "weird", "x": 1}
    lg = McapLogger(state, "mill 7/A")
    lg.on_message(config)
    for i, b in enumerate(parts):
        lg.on_batch(b)
        if i == 1:
            for m in (feed_in, circle, test, status, odd):
                lg.on_message(m)
    # the pipeline forwards source events as messages too, after (here) or before their batch: written once
    lg.on_message({"kind": "event", **{("event" if k == "kind" else k): v for k, v in lost.to_dict().items()}})
    late = SourceEvent(EventKind.RESUMED, t_host=101.0, source="sim:", gap_s=0.5)
    lg.on_message({"kind": "event", "origin": "source", **{("event" if k == "kind" else k): v
                                                           for k, v in late.to_dict().items()}})
    lg.on_batch(SampleBatch.empty(events=(late,), source="sim:"))
    lg.stop()
    lg.stop()  # idempotent
    (path,) = files(state)
    assert path.name.startswith("mill-7-A_") and path.name.endswith("_0001.mcap")
    out = read_log(path)
    assert out.complete and out.problem == ""
    assert_same_samples(SampleBatch.concat([b for b in parts if len(b)]), out.samples)
    assert not out.preroll.any()
    assert out.metadata["format"] == "ballbar-mcap/1" and out.metadata["machine_id"] == "mill 7/A"
    # host wall time = monotonic + the offset, exactly
    assert np.array_equal(out.t_wall_ns, scaled_ints(out.samples.t_host, 10**9) + lg.host_clock_offset_ns)
    assert [e["event"] for e in out.events] == ["lost", "feed_in", "unplugged", "resumed"]
    assert out.events[-1]["origin"] == "source"  # the first comer is kept
    assert out.events[0] == {"event": "lost", **{k: v for k, v in lost.to_dict().items() if k != "kind"}}
    assert out.config == [config]
    assert [r["kind"] for r in out.results] == ["circle", "test"]
    assert out.results[1]["nan"] is None and out.results[1]["np"] == 2.5
    assert out.status == [status] and out.other == [odd]
    st = lg.stats()
    assert st["samples"] == len(out.samples) and st["samples_lost"] == 0 and st["state"] == "stopped"

    # read_mcap: the valid samples only; the device clock is missing for some, so the host clock
    t, L = read_mcap(path)
    v = out.samples.valid
    assert np.array_equal(t, out.samples.t_host[v]) and np.array_equal(L, out.samples.length_mm[v])


def test_device_clock_is_the_axis_where_every_sample_has_one(state: Path) -> None:
    lg = McapLogger(state, "m")
    batches = [make_batch(0, 50), make_batch(50, 50, status=int(Status.SENSOR_FAULT)), make_batch(100, 50)]
    for b in batches:
        lg.on_batch(b)
    lg.stop()
    t, L = read_recording(files(state)[0])
    allb = SampleBatch.concat(batches)
    v = allb.valid
    assert np.array_equal(t, allb.t_device[v]) and np.array_equal(L, allb.length_mm[v]) and t.size == 100


@pytest.mark.parametrize("scale", [10**9])
def test_values_round_like_the_csv_format(scale: int) -> None:
    """Any float is stored as the integer that "%.9f" prints, including ties and near-ties."""
    rng = np.random.default_rng(3)
    x = np.concatenate([
        rng.uniform(-1e3, 1e3, 20000),
        100.0 + rng.normal(0, 1e-3, 20000),
        (np.arange(2000) + 0.5) / 1e9 + 100.0,  # near half-picometre after rounding to float
        np.arange(-50, 50) / 1024.0,  # exact binary ties at the 10th decimal
        np.array([0.0, -0.0, 5e-10, -5e-10, 1.5e-9, 2.5e-9]),
    ])
    got = scaled_ints(x, scale)
    want = np.array([int(Decimal(v).scaleb(9).quantize(Decimal(1), rounding=ROUND_HALF_EVEN)) for v in x.tolist()])
    assert np.array_equal(got, want)
    # and the CSV text of each value parses to the same float as the stored integer / 1e9
    assert all(float(f"{v:.9f}") == k / 1e9 for v, k in zip(x[::97].tolist(), got[::97].tolist(), strict=True))


# ----------------------------------------------------------------------------- size


def test_under_8_bytes_per_sample_at_1khz(state: Path) -> None:
    plan = TestPlan()
    r = simulate(plan, MachineModel(noise_um=0.1, backlash_x_um=3.0, squareness_urad=15.0), 1000.0)
    lg = McapLogger(state, "m", rotate_per_test=False)
    n = feed_paced(lg, serial_batches(r.t_s, r.length_mm, 1000.0), 1000.0, lg.flush_s)
    lg.stop()
    (path,) = files(state)
    per = path.stat().st_size / n
    logging.getLogger(__name__).warning("MCAP log at 1 kHz, noise 0.1 um: %.2f bytes/sample (%d samples)", per, n)
    print(f"\nMCAP log at 1 kHz, noise 0.1 um: {per:.2f} bytes/sample over {n} samples")
    assert per < 8.0
    t, _L = read_mcap(path)  # and it is all there
    assert t.size == n and np.array_equal(t, r.t_s)


# ----------------------------------------------------------------------------- crash safety

CHILD = r"""
import os, sys, time
import numpy as np
from ballbar.analysis.plan import TestPlan
from ballbar.daemon.mcap import McapLogger
from ballbar.daemon.samples import SampleBatch
from ballbar.tools.simulator import MachineModel, simulate

state, report, queued = sys.argv[1], sys.argv[2], sys.argv[3] == "queued"
r = simulate(TestPlan(), MachineModel(noise_um=0.1), 1000.0, seed=5)
lg = McapLogger(state, "crash")
if queued:  # as the daemon feeds it: through its listener queue, which merges batches for 0.25 s
    from ballbar.daemon.listeners import ListenerQueue
    q = ListenerQueue(lg, 6000, "drop_newest")
fd = os.open(report, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
start = time.monotonic()
i = 0
while i < r.t_s.size:
    time.sleep(0.02)
    now = time.monotonic()
    j = int(np.searchsorted(r.t_s, now - start, side="right"))
    if j <= i:
        continue
    t = r.t_s[i:j]
    b = SampleBatch.from_columns(now - (t[-1] - t), t, r.length_mm[i:j], np.arange(i, j), np.zeros(j - i))
    q.put_batch(b) if queued else lg.on_batch(b)
    os.write(fd, f"{j - 1} {time.monotonic():.6f}\n".encode())  # handed over up to sample j - 1, at this time
    i = j
"""


@pytest.mark.parametrize("path", ["direct", "queued"])
def test_kill_9_loses_nothing_older_than_1_s(state: Path, tmp_path: Path, path: str) -> None:
    report = tmp_path / "report.txt"
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(state), str(report), path])  # a fresh interpreter
    try:
        deadline = time.monotonic() + 30.0
        handed_s = 0.0
        while time.monotonic() < deadline and handed_s < 3.0:
            time.sleep(0.1)
            lines = report.read_text().splitlines() if report.exists() else []
            if len(lines) > 1:
                handed_s = float(lines[-2].split()[1]) - float(lines[0].split()[1])
        assert handed_s >= 3.0, "the writer never got going"
        t_kill = time.monotonic()
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    records = [ln.split() for ln in report.read_text().splitlines()]  # whole lines: one small O_APPEND write each
    old_enough = [int(s) for s, t in records if float(t) <= t_kill - 1.0]
    must_have = old_enough[-1]
    assert len(old_enough) >= 50 and must_have >= 1500  # the test means something

    (path,) = files(state)
    # the seeking reader needs the footer that never came (any of its errors will do)
    with open(path, "rb") as fh, pytest.raises(Exception):  # noqa: B017
        list(make_reader(fh).iter_messages())
    out = read_log(path)
    assert not out.complete and "ends early" in out.problem
    seq = out.samples.seq
    assert seq.size > must_have and np.array_equal(seq, np.arange(seq.size)), "a hole or a loss before the end"
    r = simulate(TestPlan(), MachineModel(noise_um=0.1), 1000.0, seed=5)
    m = seq.size
    assert np.array_equal(out.samples.t_device, grid(scaled_ints(r.t_s[:m], 10**9)))
    assert np.array_equal(out.samples.length_mm, grid(scaled_ints(r.length_mm[:m], 10**9)))
    # the independent reader recovers the same closed chunks
    with open(path, "rb") as fh:
        n_indep = 0
        try:
            for _s, ch, msg in NonSeekingReader(fh).iter_messages(log_time_order=False):
                if ch.topic == TOPIC_SAMPLES:
                    n_indep += json.loads(msg.data)["count"]
        except Exception:  # EndOfFile or a torn record: where the writer died
            pass
    assert n_indep == m

    # restart: a new file beside the killed one, both read, joined without loss
    lg = McapLogger(state, "crash")
    lg.on_batch(make_batch(100_000, 100, t0=10_000.0))
    lg.stop()
    assert len(files(state)) == 2 and files(state)[0] == path
    joined = read_logs(files(state))
    assert len(joined.samples) == m + 100 and not joined.complete


def test_flush_thread_bounds_the_unwritten_tail(state: Path) -> None:
    """With no further call, what was handed over is in a closed chunk within flush_s."""
    lg = McapLogger(state, "m", flush_s=0.2)
    try:
        lg.on_batch(make_batch(0, 30))
        lg.on_message({"kind": "status", "t_host": 100.0})
        time.sleep(0.6)
        out = read_log(files(state)[0])  # still open: no footer yet
        assert not out.complete and len(out.samples) == 30 and len(out.status) == 1
    finally:
        lg.stop()


def test_the_flush_deadline_counts_from_when_samples_were_read(state: Path) -> None:
    """Samples handed over merged, a quarter second after they were read: their chunk still closes within
    flush_s of the read (the kill -9 promise), not flush_s after they reached the logger."""
    lg = McapLogger(state, "m", flush_s=0.5)
    try:
        read_at = time.monotonic() - 0.25  # what the listener queue held them for
        b = make_batch(0, 250, t0=read_at)
        lg.on_batch(SampleBatch.from_columns(read_at + np.arange(250) / 1000, b.t_device, b.length_mm, b.seq,
                                             b.status))
        time.sleep(0.4)  # 0.65 s after the read: closed (flush_s after arrival would be 0.75 s)
        out = read_log(files(state)[0])
        assert len(out.samples) == 250
    finally:
        lg.stop()


def test_stop_writes_a_file_the_seeking_reader_opens(state: Path) -> None:
    lg = McapLogger(state, "m")
    lg.on_message({"kind": "config", "x": 1})
    for k in range(0, 300, 20):
        lg.on_batch(make_batch(k, 20))
    lg.stop()
    lg.on_batch(make_batch(300, 20))  # after stop: ignored, no new file
    (path,) = files(state)
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        topics = {c.id: c.topic for c in summary.channels.values()}
        counts = {topics[cid]: n for cid, n in summary.statistics.channel_message_counts.items()}
        assert counts == {"/ballbar/config": 1, TOPIC_SAMPLES: counts[TOPIC_SAMPLES]}
        total = sum(json.loads(m.data)["count"] for _s, _c, m in reader.iter_messages(topics=[TOPIC_SAMPLES]))
    assert total == 300


# ----------------------------------------------------------------------------- independent reading


def _validate(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """The JSON Schema subset the log's schemas use (type, properties, required, items, oneOf, const, enum)."""
    if "oneOf" in schema:
        errors = []
        for alt in schema["oneOf"]:
            try:
                _validate(value, alt, where)
            except AssertionError as err:
                errors.append(err)
        assert len(errors) == len(schema["oneOf"]) - 1, f"{where}: matches not exactly one of oneOf"
        return
    types = schema.get("type")
    py: dict[str, type | tuple[type, ...]] = {
        "object": dict, "array": list, "string": str, "boolean": bool, "null": type(None),
        "integer": int, "number": (int, float),
    }
    if types is not None:
        names = types if isinstance(types, list) else [types]
        ok = any(isinstance(value, py[t]) and not (t in ("integer", "number") and isinstance(value, bool))
                 for t in names)
        assert ok, f"{where}: {value!r:.40} is not {types}"
    if "const" in schema:
        assert value == schema["const"], where
    if "enum" in schema:
        assert value in schema["enum"], where
    if isinstance(value, dict):
        for key in schema.get("required", []):
            assert key in value, f"{where}: missing {key}"
        for key, sub in schema.get("properties", {}).items():
            if key in value:
                _validate(value[key], sub, f"{where}.{key}")
        if schema.get("additionalProperties") is False:
            assert set(value) <= set(schema.get("properties", {})), where
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            _validate(item, schema["items"], f"{where}[{i}]")


def test_mcap_package_reads_every_channel_and_messages_follow_their_schemas(state: Path) -> None:
    lg = McapLogger(state, "m")
    lg.on_message({"kind": "config", "t_host": 99.0})
    lg.on_batch(make_batch(0, 50, events=(SourceEvent(EventKind.OPENED, 99.5, "sim:", detail="x"),)))
    lg.on_batch(make_batch(50, 20, device=False))
    lg.on_message({"kind": "event", "event": "feed_in", "t_host": 100.0})
    lg.on_message({"kind": "circle", "t_host": 100.1})
    lg.on_message({"kind": "test", "t_host": 100.2, "test_id": "t1"})
    lg.on_message({"kind": "status", "t_host": 100.3})
    lg.on_message({"schema_version": 2, "kind": "controller", "machine_id": "m", "t_wall": "2026-12-08T00:00:00.000Z",
                   "t_host": 100.35, "endpoint": "opc.tcp://cnc:4840", "state": "data", "clock_offset_s": 0.002,
                   "values": [{"name": "override", "value": 80.0, "t_source": "2026-12-08T00:00:00.000Z",
                               "t_host": 100.3}, {"name": "block", "value": ["N10", "N20"], "t_source": None,
                                                 "t_host": 100.3}]})
    lg.on_message({"kind": "other"})
    lg.stop()
    (path,) = files(state)
    seen: dict[str, int] = {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages():
            assert schema is not None and schema.encoding == "jsonschema" and channel.message_encoding == "json"
            name, sch, _desc = SCHEMAS[channel.topic]
            assert schema.name == name and json.loads(schema.data) == json.loads(json.dumps(sch))
            if channel.topic in (TOPIC_SAMPLES, TOPIC_OTHER, TOPIC_CONTROLLER):  # the rest: in test_e2e
                _validate(json.loads(message.data), json.loads(schema.data), channel.topic)
            seen[channel.topic] = seen.get(channel.topic, 0) + 1
            assert channel.metadata["description"]
        assert reader.get_header().library.startswith("ballbar")
        (meta,) = list(reader.iter_metadata())
        assert meta.name == "ballbar" and meta.metadata["format"] == "ballbar-mcap/1"
    assert set(seen) == set(SCHEMAS)
    assert seen[TOPIC_SAMPLES] == 2  # split where the device clock stops


# ----------------------------------------------------------------------------- truncation and bad files


def test_any_truncation_reads_a_prefix(state: Path, tmp_path: Path) -> None:
    path = one_file(state)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    previous = -1
    for size in [*range(8, len(data), max(1, len(data) // 150)), len(data) - 1]:
        cut.write_bytes(data[:size])
        out = read_log(cut)
        seq = out.samples.seq
        assert np.array_equal(seq, np.arange(seq.size)) and seq.size >= previous
        previous = seq.size
    assert previous == 2000  # all chunks are in before the summary starts


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "empty file"),
        (b"t_s,length_mm\n0,1\n", "not an MCAP file"),
        (b"\x89MCAP0\r\n", "no samples on /ballbar/samples"),
    ],
)
def test_bad_files_give_one_line_errors(tmp_path: Path, content: bytes, message: str) -> None:
    p = tmp_path / "x.mcap"
    p.write_bytes(content)
    with pytest.raises(DataError, match=message) as info:
        read_recording(p)
    assert "\n" not in str(info.value) and str(p) in str(info.value)


def test_foreign_mcap_and_directories(tmp_path: Path) -> None:
    p = tmp_path / "foreign.mcap"
    with open(p, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        w.add_message(w.register_channel("/other", "json", sid), log_time=1, data=b"{}", publish_time=1)
        w.finish()
    with pytest.raises(DataError, match="no samples on /ballbar/samples"):
        read_mcap(p)
    bad = tmp_path / "bad.mcap"
    with open(bad, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        w.add_message(w.register_channel(TOPIC_SAMPLES, "json", sid), log_time=1, data=b'{"count":2}', publish_time=1)
        w.finish()
    with pytest.raises(DataError, match=r"message 1 on /ballbar/samples is not a ballbar.Samples record"):
        read_mcap(bad)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DataError, match=r"no such file|is a directory"):
        read_recording(empty / "nothing.mcap")
    with pytest.raises(DataError, match="is a directory"):
        read_recording(empty)  # a directory without .mcap files goes to the CSV reader, which says so


# ----------------------------------------------------------------------------- rotation and retention


def test_rotation_per_test_gives_each_test_its_own_whole_file(state: Path) -> None:
    lg = McapLogger(state, "m", preroll_s=2.0)
    lg.on_message({"kind": "config", "n": 1})
    batches = [make_batch(k, 10, fs=100.0) for k in range(0, 1500, 10)]  # 15 s at 100 Hz
    for b in batches[:20]:
        lg.on_batch(b)
    lg.on_message({"kind": "event", "event": "feed_in", "t_host": 101.9})  # 2 s after start: no new file yet
    assert len(files(state)) == 1
    for b in batches[20:80]:
        lg.on_batch(b)
    lg.on_message({"kind": "test", "t_host": 107.0})
    for b in batches[80:100]:
        lg.on_batch(b)
    lg.on_message({"kind": "event", "event": "feed_in", "t_host": 109.9})  # the second test: a new file
    for b in batches[100:]:
        lg.on_batch(b)
    lg.stop()
    f1, f2 = files(state)
    a, b2 = read_log(f1), read_log(f2)
    assert a.samples.seq[0] == 0 and a.samples.seq[-1] == 999 and not a.preroll.any()
    assert b2.metadata["reason"] == "test" and b2.config == [{"kind": "config", "n": 1}]
    assert b2.preroll[0] and b2.samples.seq[0] <= 999 - 150  # at least ~2 s before the feed-in, repeated
    assert not b2.preroll[b2.samples.seq >= 1000].any()
    assert [e["event"] for e in b2.events] == ["feed_in"] and [e["event"] for e in a.events] == ["feed_in"]
    joined = read_logs([f1, f2])
    assert_same_samples(joined.samples, SampleBatch.concat(batches))
    t, _L = read_mcap(state / "recordings")  # a directory: the same, joined
    assert t.size == 1500


def test_preroll_is_written_in_messages_of_the_flush_period(state: Path) -> None:
    """The preroll at the head of a test's file comes one message per ``flush_s`` of samples, as the flushes
    write them, not one per source batch; and with the file before, every sample exactly once."""
    lg = McapLogger(state, "m", preroll_s=10.0, flush_s=0.5)
    batches = [make_batch(k, 23) for k in range(0, 14_000, 23)]  # 14 s at 1 kHz in 23 ms batches
    feed_ins = (1_000, 12_000)  # the first test's, in the first file; the second's starts the second file
    for b in batches:
        if any(int(b.seq[0]) <= k < int(b.seq[0]) + len(b) for k in feed_ins):
            lg.on_message({"kind": "event", "event": "feed_in", "t_host": float(b.t_host[0])})
        lg.on_batch(b)
    lg.stop()
    f1, f2 = files(state)
    spans, counts, pre_seq = [], [], []
    with open(f2, "rb") as fh:
        for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC_SAMPLES]):
            d = mcap_log.decode_samples(json.loads(m.data))
            if d.preroll:
                spans.append((int(d.t_host_ns[-1]) - int(d.t_host_ns[0])) / 1e9)
                counts.append(d.seq.size)
                pre_seq.append(d.seq)
    seq = np.concatenate(pre_seq)
    # about 10 s of preroll (whole batches) in 20 or 21 messages of at most the flush period, not ~435
    assert 10.0 <= (seq[-1] - seq[0] + 1) / 1000.0 <= 10.0 + 2 * 0.023
    assert 20 <= len(counts) <= 21, counts
    # a message takes the batches that start within 0.5 s of its first sample: it spans 0.5 s, give or take
    # a batch (23 ms); every message but the last is full
    assert all(s < 0.5 + 0.023 for s in spans), spans
    assert all(s > 0.5 - 0.023 for s in spans[:-1]), spans
    assert np.array_equal(seq, np.arange(seq[0], seq[-1] + 1))  # in order, none lost or repeated
    b2 = read_log(f2)
    own = b2.samples.seq[~b2.preroll]
    assert own[0] == seq[-1] + 1  # the preroll runs up to the file's own samples
    joined = read_logs([f1, f2])
    assert_same_samples(joined.samples, SampleBatch.concat(batches))


def test_rotation_by_size_and_age(state: Path) -> None:
    lg = McapLogger(state, "m", rotate_bytes=4096, quota_bytes=1 << 30, rotate_per_test=False)
    batches = [make_batch(k, 100) for k in range(0, 20_000, 100)]
    for i, b in enumerate(batches):
        lg.on_batch(b)
        if i % 5 == 4:
            lg.flush()
    lg.stop()
    fs = files(state)
    assert len(fs) >= 5
    raw = b"".join(to_json(sch) for _n, sch, _d in SCHEMAS.values())
    schemas = len(raw) + len(zstandard.compress(raw))  # in the first chunk, and again in the summary
    assert all(p.stat().st_size < 2 * 4096 + 8192 + schemas for p in fs)
    assert [read_log(p).metadata["reason"] for p in fs][:2] == ["start", "size"]
    assert_same_samples(read_logs(fs).samples, SampleBatch.concat(batches))

    aged = state.parent / "aged"
    lg = McapLogger(aged, "m", rotate_s=0.25)
    for k in range(0, 600, 50):
        lg.on_batch(make_batch(k, 50))
        time.sleep(0.07)
    lg.stop()
    fs = files(aged)
    assert len(fs) >= 2 and read_log(fs[1]).metadata["reason"] == "age"
    assert read_logs(fs).samples.seq.tolist() == list(range(600))


def test_size_rotation_waits_for_the_test_to_end(state: Path) -> None:
    lg = McapLogger(state, "m", rotate_bytes=4096, quota_bytes=1 << 30, rotate_per_test=False)
    lg.on_message({"kind": "event", "event": "feed_in", "t_host": 100.0})
    k = 0
    assert lg._file is not None
    while not lg._file.overhead or lg.stats()["bytes"] - lg._file.overhead < 6000:  # past the schemas' chunk
        lg.on_batch(make_batch(k, 100))
        lg.flush()
        k += 100
    assert len(files(state)) == 1  # past rotate_bytes, but in a test
    lg.on_message({"kind": "test", "t_host": 110.0})
    lg.on_batch(make_batch(k, 100))
    lg.flush()
    lg.stop()
    assert len(files(state)) == 2


def test_retention_deletes_the_oldest_beyond_quota_and_the_too_old(state: Path) -> None:
    rec = state / "recordings"
    rec.mkdir(parents=True)
    now = time.time()
    made = []
    for i, (ts, age_days) in enumerate(
        [("20240101T000000Z", 30), ("20240102T000000Z", 20), ("20240103T000000Z", 400),  # last written long ago
         ("20240104T000000Z", 10), ("20240105T000000Z", 1)]
    ):
        p = rec / f"m_{ts}_{i + 1:04d}.mcap"
        p.write_bytes(b"x" * 3000)
        os.utime(p, (now - age_days * 86400, now - age_days * 86400))
        made.append(p)
    keep = rec / "notes.mcap.txt"
    keep.write_bytes(b"y" * 100_000)  # not a log file: never touched, not counted
    lg = McapLogger(state, "m", rotate_bytes=4096, quota_bytes=10_000, keep_days=365)
    lg.on_batch(make_batch(0, 10))
    current = lg.current_path
    lg.stop()
    left = files(state)
    # oldest first until <= 10 000 bytes with the open file counted (two go), and the one older than keep_days
    assert made[0] not in left and made[1] not in left and made[2] not in left
    assert made[3] in left and made[4] in left and current in left and keep.exists()
    assert lg.stats()["deleted_files"] == 3


def test_recovery_and_retention_leave_a_file_another_process_holds_alone(
    state: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A file without a footer that another live process holds an ``flock`` on (its writer: here a child process
    holding it) is neither rewritten by recovery nor deleted by retention, each saying so in one line (retention
    once, however often it runs); once the holder is gone the same file is recovered and deleted (so it was the
    lock that kept them off, nothing else).  On the old code recovery rewrote it at once."""
    path = one_file(state)
    data = path.read_bytes()[:-200]  # the footer and summary cut off: what a live writer's file looks like
    path.write_bytes(data)
    old = time.time() - 400 * 86400
    os.utime(path, (old, old))
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, sys\n"
         "fh = open(sys.argv[1], 'rb'); fcntl.flock(fh, fcntl.LOCK_EX); print('held', flush=True); sys.stdin.read()",
         str(path)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline() == "held\n"
        with caplog.at_level(logging.WARNING, logger="ballbar.daemon.mcap"):
            assert mcap_log.recover_crashed(state / "recordings") == []
            other = McapLogger(state, "m", rotate_bytes=4096, quota_bytes=8192, keep_days=1)
            try:
                other._retention(time.monotonic())
                other._retention(time.monotonic())
                assert other.stats()["deleted_files"] == 0
            finally:
                other.stop()
        assert path.read_bytes() == data and path.stat().st_mtime == old
        said = [r.getMessage() for r in caplog.records if path.name in r.getMessage()]
        assert len(said) == 2, said
        assert "open in another process" in said[0] and "left alone" in said[0]
        assert "open in another process: retention leaves it alone" in said[1]
    finally:
        assert holder.stdin is not None
        holder.stdin.close()
        assert holder.wait(10) == 0
        assert holder.stdout is not None
        holder.stdout.close()
    (r,) = mcap_log.recover_crashed(state / "recordings")
    assert r.path == path and read_log(path).complete
    os.utime(path, (old, old))
    again = McapLogger(state, "m", rotate_bytes=4096, quota_bytes=8192, keep_days=1)
    try:
        again._retention(time.monotonic())
    finally:
        again.stop()
    assert path not in files(state) and again.stats()["deleted_files"] >= 1


# ----------------------------------------------------------------------------- write errors


class _Disk:
    full = False


class _FullDiskRaw(io.FileIO):
    """A file on a disk that can fill up: writes fail with ENOSPC while ``_Disk.full``."""

    def write(self, b: Any) -> int:
        if _Disk.full:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)


class _ChunkThenFullRaw(io.FileIO):
    """A disk that fills up in the middle of a flush: once armed, the next write gets its first record (a chunk)
    onto the disk whole, and then no more bytes fit (ENOSPC)."""

    armed = False
    full = False

    def write(self, b: Any) -> int:
        if _ChunkThenFullRaw.full:
            raise OSError(errno.ENOSPC, "No space left on device")
        if _ChunkThenFullRaw.armed and len(b) and b[0] == 0x06:  # a chunk record: opcode, length, body
            _ChunkThenFullRaw.armed, _ChunkThenFullRaw.full = False, True
            return super().write(bytes(b[: 9 + int.from_bytes(bytes(b[1:9]), "little")]))
        return super().write(b)


def test_a_write_cut_short_after_a_whole_chunk_counts_its_samples_as_written(
    state: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The samples of a chunk that reached the disk whole before the write failed are in the file: not lost too
    (the 30-minute soak found 1376 samples counted both ways)."""
    monkeypatch.setattr(mcap_writer, "_open_output", lambda p: io.BufferedWriter(_ChunkThenFullRaw(p, "xb")))
    monkeypatch.setattr(_ChunkThenFullRaw, "armed", False)
    monkeypatch.setattr(_ChunkThenFullRaw, "full", False)
    lg = McapLogger(state, "m", retry_min_s=60.0)
    try:
        for k in range(0, 1000, 100):
            lg.on_batch(make_batch(k, 100))
            lg.flush()
        _ChunkThenFullRaw.armed = True
        lg.on_batch(make_batch(1000, 300))
        lg.flush()  # the chunk of these 300 gets onto the disk, its message index does not
        assert lg.stats()["state"] == "failed"
    finally:
        lg.stop()
    st = lg.stats()
    (path,) = files(state)
    out = read_log(path)
    assert len(out.samples) == 1300 and st["samples"] == 1300 and st["samples_lost"] == 0, st


class _BudgetRaw(io.FileIO):
    """A disk that is full (``full``), or takes only ``budget`` more writes."""

    full = False
    budget: int | None = None

    def write(self, b: Any) -> int:
        if _BudgetRaw.full or _BudgetRaw.budget == 0:
            raise OSError(errno.ENOSPC, "No space left on device")
        if _BudgetRaw.budget is not None:
            _BudgetRaw.budget -= 1
        return super().write(b)


def test_what_an_outage_held_survives_a_stop_whose_last_file_cannot_be_finished(
    state: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At stop, the held results go into a last file whose footer no longer fits: that file is kept (its chunk
    holds them), and the spool says the run ended in an outage, so the next start names the cut file so."""
    monkeypatch.setattr(mcap_writer, "_open_output", lambda p: io.BufferedWriter(_BudgetRaw(p, "xb")))
    monkeypatch.setattr(mcap_writer, "_disk_space", lambda _p: (0, 64 << 30))  # no headroom: no resume before stop
    monkeypatch.setattr(_BudgetRaw, "full", False)
    monkeypatch.setattr(_BudgetRaw, "budget", None)
    lg = McapLogger(state, "m", retry_min_s=60.0)
    for k in range(0, 500, 50):
        lg.on_batch(make_batch(k, 50))
    lg.flush()
    _BudgetRaw.full = True
    lg.on_batch(make_batch(500, 50))
    lg.flush()
    lg.on_message({"kind": "test", "test_id": "m-held", "t_host": 101.0})
    assert lg.stats()["held_messages"] == 1
    _BudgetRaw.full, _BudgetRaw.budget = False, 2  # the last file's head and its held records fit, its footer not
    lg.stop()
    kept = [p for p in files(state) if any(r.get("test_id") == "m-held" for r in read_log(p, samples=False).results)]
    assert kept, [p.name for p in files(state)]
    spool = read_spool(state)
    assert spool.run_id == lg.run_id and [p["event"] for _t, p, _l in spool.entries] == ["log_gap"]
    (r,) = [r for r in mcap_log.recover_crashed(state / "recordings") if r.path == kept[0]]
    assert r.outage and "No space left" in r.outage


def test_full_disk_drops_the_file_counts_losses_and_resumes(
    state: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setattr(mcap_writer, "_open_output", lambda p: io.BufferedWriter(_FullDiskRaw(p, "xb")))
    monkeypatch.setattr(_Disk, "full", False)
    caplog.set_level(logging.INFO, logger="ballbar.daemon.mcap")
    lg = McapLogger(state, "m", retry_min_s=0.1, retry_max_s=0.2)
    k = 0
    total = 0

    def feed(n_batches: int, flush_every: int = 5) -> float:
        nonlocal k, total
        worst = 0.0
        for i in range(n_batches):
            t0 = time.perf_counter()
            lg.on_batch(make_batch(k, 50))
            if i % flush_every == flush_every - 1:
                lg.flush()
            worst = max(worst, time.perf_counter() - t0)
            k += 50
            total += 50
        return worst

    try:
        feed(20)
        first = lg.current_path
        _Disk.full = True
        worst = feed(40)  # 2000 samples into a full disk
        time.sleep(0.25)
        worst = max(worst, feed(20))  # retries fail too
        st = lg.stats()
        assert st["state"] == "failed" and st["samples_lost"] > 0 and "No space left" in st["last_error"]
        assert worst < 0.5  # nothing stalls: no call waits for the disk or the backoff
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1 and "No space left on device" in errors[0].getMessage()
        assert "\n" not in errors[0].getMessage()
        _Disk.full = False
        time.sleep(0.25)  # past the backoff
        feed(20)
        assert lg.stats()["state"] == "writing"
        assert any("writing again" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    finally:
        _Disk.full = False
        lg.stop()
    st = lg.stats()
    fs = files(state)
    assert fs[0] == first and len(fs) == 2  # the stub files of failed retries were removed
    joined = read_logs(fs)
    assert len(joined.samples) + st["samples_lost"] == total  # every sample is in a file or counted lost
    seq = joined.samples.seq
    assert np.array_equal(seq, np.unique(seq))
    gap = [e for e in read_log(fs[1]).events if e["event"] == "log_gap"]
    assert len(gap) == 1 and gap[0]["count"] == st["samples_lost"] and "No space left" in gap[0]["detail"]
    assert read_log(fs[1]).metadata["reason"] == "recovery"


def test_unwritable_state_dir_never_raises(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    blocker = tmp_path / "state"
    blocker.write_text("a file where the state directory should be")
    lg = McapLogger(blocker, "m", retry_min_s=0.05)
    for k in range(0, 500, 50):
        lg.on_batch(make_batch(k, 50))
        lg.on_message({"kind": "status"})
    lg.stop()
    assert lg.stats()["samples_lost"] == 500 and lg.stats()["write_errors"] >= 1
    assert sum(r.levelno >= logging.ERROR for r in caplog.records) == 1


@pytest.mark.parametrize(
    "kw",
    [{"flush_s": 1.5}, {"flush_s": 0}, {"rotate_bytes": 10}, {"quota_bytes": 1000}, {"retry_min_s": 0}],
)
def test_bad_options_are_one_line_errors(tmp_path: Path, kw: dict[str, Any]) -> None:
    with pytest.raises(LogConfigError, match=r"^mcap log: ") as info:
        McapLogger(tmp_path, "m", **kw)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- analyze equivalence


def test_analyze_of_the_log_equals_analyze_of_the_csv(
    state: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    plan = TestPlan(feed_mm_min=2000.0, sample_hz=250.0)  # small enough to analyse twice in about a second
    machine = MachineModel(noise_um=0.2, backlash_x_um=4.0, squareness_urad=20.0)
    r = simulate(plan, machine, 250.0, seed=11)
    csv = tmp_path / "test.csv"
    write_csv(str(csv), r.t_s, r.length_mm)
    lg = McapLogger(state, "m")
    lg.on_message({"kind": "config", "plan": {"feed_mm_min": 2000.0, "sample_hz": 250.0}})
    feed_paced(lg, serial_batches(r.t_s, r.length_mm, 250.0, status=int(Status.SIMULATED)), 250.0, 0.5)
    lg.stop()
    (path,) = files(state)
    args = ["--feed-mm-min", "2000", "--sample-hz", "250", "--json"]
    outs = []
    # a directory whose files record no test (no analysis ran): its newest daemon run's samples, the same
    for p in (csv, path, state / "recordings"):
        code = cli_main(["analyze", str(p), *args])
        out, err = capsys.readouterr()
        assert code == 0, err
        res = json.loads(out)
        res.pop("source")
        outs.append(res)
    assert outs[0] == outs[1] == outs[2]
    assert outs[0]["parameters"]["backlash_x_um"]["significant"]


def test_from_config(tmp_path: Path) -> None:
    from types import SimpleNamespace

    cfg = SimpleNamespace(
        daemon=SimpleNamespace(machine_id="mill-3", state_dir=str(tmp_path)),
        mcap=SimpleNamespace(enabled=True, rotate_per_test=False, rotate_mb=1.0, rotate_minutes=2.0, quota_mb=8.0,
                             keep_days=30.0, flush_s=0.25),
    )
    lg = McapLogger.from_config(cfg)
    lg.stop()
    assert (lg.machine_id, lg.directory) == ("mill-3", tmp_path / "recordings")
    assert (lg.rotate_bytes, lg.quota_bytes, lg.rotate_s) == (1 << 20, 8 << 20, 120.0)
    assert (lg.rotate_per_test, lg.keep_days, lg.flush_s) == (False, 30.0, 0.25)


def test_full_disk_resumes_within_2_s_of_space_with_headroom_and_keeps_the_results(
    state: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Default backoff (up to 60 s): a full disk is retried on a free-space probe instead, only with headroom,
    and the results and events of the outage are written when it ends."""
    free = {"bytes": 1 << 30}
    monkeypatch.setattr(mcap_writer, "_open_output", lambda p: io.BufferedWriter(_FullDiskRaw(p, "xb")))
    monkeypatch.setattr(mcap_writer, "_disk_space", lambda _p: (free["bytes"], 64 << 30))
    monkeypatch.setattr(_Disk, "full", False)
    caplog.set_level(logging.INFO, logger="ballbar.daemon.mcap")
    lg = McapLogger(state, "m")  # retry_min_s 1, retry_max_s 60
    try:
        lg.on_message({"kind": "config", "config": {"x": 1}})
        lg.on_batch(make_batch(0, 50))
        lg.flush()
        _Disk.full, free["bytes"] = True, 28 << 10  # 28 KB left
        for k in range(50, 2050, 50):
            lg.on_batch(make_batch(k, 50))
        lg.flush()
        assert lg.stats()["state"] == "failed"
        lg.on_message({"kind": "event", "event": "feed_in", "t_host": 123.0})
        lg.on_message({"kind": "test", "test_id": "m-outage", "t_host": 124.0})
        lg.on_message({"kind": "status", "t_host": 124.5})
        errors_before = lg.stats()["write_errors"]
        time.sleep(1.5)  # a sliver of space: no retry, no "writing again" that fails at once
        for k in range(2050, 2550, 50):
            lg.on_batch(make_batch(k, 50))
        assert lg.stats()["write_errors"] == errors_before
        assert not any("writing again" in r.getMessage() for r in caplog.records)
        _Disk.full, free["bytes"] = False, 1 << 30
        t0 = time.monotonic()
        while lg.stats()["state"] != "writing":  # no data needed: the flush thread probes
            assert time.monotonic() - t0 < 2.0, lg.stats()
            time.sleep(0.05)
        st = lg.stats()
        assert st["messages_held_written"] == 2 and st["held_messages"] == 0
    finally:
        _Disk.full = False
        lg.stop()
    fs = files(state)
    after = read_log(fs[-1])
    assert [r["test_id"] for r in after.results] == ["m-outage"]
    assert [e["event"] for e in after.events][:2] == ["log_gap", "feed_in"]


def test_deeply_nested_json_costs_only_its_own_record(state: Path, tmp_path: Path) -> None:
    lg = McapLogger(state, "m")
    for i in range(3):
        lg.on_message({"kind": "test", "test_id": f"m-{i}", "t_host": float(i)})
        lg._rotate("size", time.monotonic())  # one result per file
    lg.stop()
    good = files(state)
    # a hostile file: a result nested 100000 deep (json.loads raises RecursionError on it)
    bad = state / "recordings" / "m_19700101T000000Z_0001.mcap"
    with open(bad, "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema("ballbar.Result", "jsonschema", b"{}")
        ch = w.register_channel(mcap_log.TOPIC_RESULTS, "json", sid)
        w.add_message(ch, log_time=0, data=b"[" * 100_000 + b"]" * 100_000, publish_time=0)
        w.add_message(ch, log_time=1, data=b'{"kind": "test", "test_id": "m-bad-file"}', publish_time=1)
        w.finish()
    results = read_results(list_recordings(state / "recordings"))
    assert [r["test_id"] for r in results] == ["m-bad-file", "m-0", "m-1", "m-2"], good
