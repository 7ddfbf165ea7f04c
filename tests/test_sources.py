"""Sources: URLs, batches, time stamps, losses and faults, with in-process ptys, sockets and files.

The test itself plays the device here (it writes frames into the pty's master);
``test_simdevice.py`` runs the real simulated device in a child process.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import pty
import re
import socket
import threading
import time
import tty
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from ballbar.analysis.errors import BallbarError, DataError
from ballbar.analysis.plan import TestPlan
from ballbar.daemon.errors import SourceClosed, SourceConfigError
from ballbar.daemon.samples import SAMPLE_DTYPE, EventKind, SampleBatch, SourceEvent
from ballbar.daemon.sources import Source, open_source, split_url
from ballbar.daemon.timebase import ClockMap
from ballbar.protocol import Status
from ballbar.protocol import ascii as ascii_proto
from ballbar.protocol.binary import SEQ_MODULUS, encode_samples

pytestmark = pytest.mark.usefixtures("no_leaks")


class FakeDevice:
    """A pty whose master the test writes to, behind a stable link (like /dev/serial/by-id)."""

    def __init__(self, link: Path) -> None:
        self.link = str(link)
        self.master: int | None = None
        self.slave: int | None = None
        self.plug()

    def plug(self) -> None:
        self.master, self.slave = pty.openpty()
        tty.setraw(self.slave)
        tmp = self.link + ".tmp"
        os.symlink(os.ttyname(self.slave), tmp)
        os.replace(tmp, self.link)

    def unplug(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.link)
        for fd in (self.master, self.slave):
            if fd is not None:
                os.close(fd)
        self.master = self.slave = None

    def write(self, data: bytes) -> None:
        assert self.master is not None
        view = memoryview(data)
        while view:
            n = os.write(self.master, view)
            view = view[n:]

    def frames(self, seq: np.ndarray | list[int], rate: float = 1000.0, disp: float | np.ndarray = 0.0) -> None:
        s = np.asarray(seq, dtype=np.int64)
        self.write(encode_samples(s, s / rate, np.broadcast_to(disp, s.shape)))


@pytest.fixture
def dev(tmp_path: Path) -> Iterator[FakeDevice]:
    d = FakeDevice(tmp_path / "ttyBB0")
    yield d
    d.unplug()


def read_all(src: Source, want: int, timeout: float = 5.0) -> tuple[SampleBatch, list[SourceEvent]]:
    """Read until ``want`` samples have arrived (or the time is up); all events too."""
    batches: list[SampleBatch] = []
    deadline = time.monotonic() + timeout
    n = 0
    while n < want and time.monotonic() < deadline:
        b = src.read(0.1)
        if b is not None:
            batches.append(b)
            n += len(b)
    merged = SampleBatch.concat(batches)
    return merged, list(merged.events)


def kinds(events: list[SourceEvent]) -> list[str]:
    return [str(e.kind) for e in events]


def read_until(
    src: Source, kind: EventKind, timeout: float = 5.0, samples: list[int] | None = None
) -> list[SourceEvent]:
    """Events up to and including the first of ``kind``; sample numbers seen go to ``samples``."""
    events: list[SourceEvent] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        b = src.read(0.1)
        if b is not None:
            events += b.events
            if samples is not None:
                samples += b.seq.tolist()
            if any(e.kind == kind for e in b.events):
                return events
    raise AssertionError(f"no {kind} event within {timeout} s; got {kinds(events)}")


# ----------------------------------------------------------------------------- URLs


@pytest.mark.parametrize(
    ("url", "scheme", "target", "query"),
    [
        ("serial:/dev/ttyUSB0?cal_mm=100", "serial", "/dev/ttyUSB0", {"cal_mm": "100"}),
        ("serial:///dev/ttyUSB0", "serial", "///dev/ttyUSB0", {}),
        ("/dev/ttyUSB0?protocol=ascii&rate=15.625", "serial", "/dev/ttyUSB0", {"protocol": "ascii", "rate": "15.625"}),
        ("serial:loop://", "serial", "loop://", {}),
        ("socket://localhost:7000?cal_mm=1", "serial", "socket://localhost:7000", {"cal_mm": "1"}),
        ("replay:runs/a.csv?speed=max", "replay", "runs/a.csv", {"speed": "max"}),
        ("sim:?speedup=10&seed=3", "sim", "", {"speedup": "10", "seed": "3"}),
        ("serial:loop://?request=%3F%0D&cal_mm=0", "serial", "loop://", {"request": "?\r", "cal_mm": "0"}),
    ],
)
def test_split_url(url: str, scheme: str, target: str, query: dict[str, str]) -> None:
    assert split_url(url) == (scheme, target, query)


@pytest.mark.parametrize(
    ("url", "options", "message"),
    [
        ("foo:bar", {}, "unknown source 'foo'"),
        ("serial:loop://", {}, "cal_mm is required"),
        ("serial:loop://?cal_mm=1&bogus=2", {}, "unknown option 'bogus'"),
        ("serial:loop://?cal_mm=1&cal_mm=2", {}, "given twice"),
        ("serial:loop://?cal_mm=1", {"cal_mm": 2.0}, "both in the URL and as a keyword"),
        ("serial:loop://?cal_mm=1&rate=20000", {}, "rate=20000"),
        ("serial:loop://?cal_mm=1&rate=abc", {}, "rate='abc'"),
        ("serial:loop://?cal_mm=nan", {}, "cal_mm='nan'"),
        ("serial:loop://?cal_mm=1&mode=poll", {}, "mode=poll needs protocol=ascii"),
        ("serial:loop://?cal_mm=1&protocol=ascii&mode=poll", {}, "needs rate"),
        ("serial:loop://?cal_mm=1&protocol=morse", {}, "protocol='morse'"),
        ("serial:loop://?cal_mm=1&baud=fast", {}, "baud='fast'"),
        ("serial:?cal_mm=1", {}, "no port"),
        ("replay:x.mcap", {}, "MCAP recordings is not supported yet"),
        ("replay:?speed=1", {}, "no file"),
        ("replay:x.csv?speed=0", {}, "speed=0"),
        ("sim:somewhere", {}, "takes no path"),
        ("sim:?repeat=-1", {}, "repeat=-1"),
    ],
)
def test_bad_configuration_names_the_problem(url: str, options: dict[str, object], message: str) -> None:
    with pytest.raises(SourceConfigError, match=message) as info:
        open_source(url, **options)
    assert isinstance(info.value, ValueError) and isinstance(info.value, BallbarError)
    assert "\n" not in str(info.value)


def test_missing_recording_is_a_data_error(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="no such file"):
        open_source(f"replay:{tmp_path / 'nope.csv'}")


# ----------------------------------------------------------------------------- the interface


def test_loop_url_close_twice_and_read_after_close() -> None:
    src = open_source("serial:loop://?cal_mm=100")
    b = src.read(0.05)
    assert b is not None and len(b) == 0 and kinds(list(b.events)) == ["opened"]
    assert src.read(0.05) is None
    src.close()
    src.close()
    with pytest.raises(SourceClosed):
        src.read(0.01)
    with open_source("serial:loop://", cal_mm=100.0) as again:
        assert again.stats().connected
    assert again.closed


def test_socket_url(tmp_path: Path) -> None:
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        with open_source(f"socket://127.0.0.1:{port}?cal_mm=100&rate=1000") as src:
            conn, _ = server.accept()
            with conn:
                conn.sendall(encode_samples(np.arange(50), np.arange(50) / 1000, np.full(50, 0.001)))
                batch, _ = read_all(src, 50)
    assert batch.seq.tolist() == list(range(50))
    assert np.allclose(batch.length_mm, 100.001)


def test_close_from_another_thread_interrupts_a_blocked_read(dev: FakeDevice) -> None:
    src = open_source(f"serial:{dev.link}?cal_mm=0")
    src.read(0.05)  # the opened event
    result: list[object] = []

    def reader() -> None:
        try:
            result.append(src.read(None))
        except SourceClosed as err:
            result.append(err)

    th = threading.Thread(target=reader)
    th.start()
    time.sleep(0.1)
    t0 = time.monotonic()
    src.close()
    th.join(2.0)
    assert not th.is_alive()
    assert time.monotonic() - t0 < 1.0
    assert len(result) == 1 and (result[0] is None or isinstance(result[0], SourceClosed))


# ----------------------------------------------------------------------------- binary over a pty


def test_stream_values_times_and_exact_gap(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}?protocol=binary&rate=1000", cal_mm=100.0) as src:
        seq = np.r_[0:300, 307:500]  # 7 samples lost in between
        disp = np.sin(seq / 50.0) * 0.25
        dev.frames(seq, disp=disp)
        batch, events = read_all(src, seq.shape[0])
        st = src.stats()
    assert batch.seq.tolist() == seq.tolist()
    assert np.array_equal(batch.length_mm, 100.0 + np.rint(disp * 1e5) / 1e5)
    assert np.allclose(batch.t_device, seq / 1000.0, atol=1e-9)
    assert np.all(np.diff(batch.t_host) >= 0)
    assert batch.t_host[-1] <= time.monotonic()
    lost = [e for e in events if e.kind == EventKind.LOST]
    assert [(e.seq, e.count, e.detail) for e in lost] == [(300, 7, "gap")]
    assert st.samples == 493 and st.lost == 7 and st.decode == {}
    assert batch.status.tolist() == [0] * 493


def test_a_clock_step_back_is_a_clock_jump_and_a_counter_leap_loses_nothing(dev: FakeDevice) -> None:
    """The counter runs on while the clock steps 20 s back: a clock jump of -20 s at that sample (not a device
    reset), the device time running on; the counter leaps 10 000 while the clock runs on: a counter jump, no
    sample counted lost, the numbers and times running on by one period."""
    with open_source(f"serial:{dev.link}?rate=1000", cal_mm=0.0) as src:
        k = np.arange(1000, 1500)
        dev.write(encode_samples(k, k / 1000, np.zeros(k.size)))
        head, _ = read_all(src, k.size)
        k = np.arange(1500, 2000)
        dev.write(encode_samples(k, k / 1000 - 20.0, np.zeros(k.size)))  # the clock 20 s back from 1500 on
        mid, _ = read_all(src, k.size)
        k = np.arange(2000, 2500)
        dev.write(encode_samples(np.where(k >= 2200, k + 10_000, k), k / 1000 - 20.0, np.zeros(k.size)))
        tail, _ = read_all(src, k.size)
        st = src.stats()
    batch = SampleBatch.concat([head, mid, tail])
    events = list(batch.events)
    assert batch.seq.tolist() == list(range(1000, 2500))
    assert np.allclose(np.diff(batch.t_device), 0.001, atol=1e-6)  # never back, never a leap
    assert "device_reset" not in kinds(events) and "lost" not in kinds(events)
    (jump,) = [e for e in events if e.kind == EventKind.CLOCK_JUMP]
    assert jump.seq == 1500 and jump.gap_s == pytest.approx(-20.0, abs=1e-6)
    (leap,) = [e for e in events if e.kind == EventKind.COUNTER_JUMP]
    assert leap.seq == 2200 and leap.count == 10_000
    assert st.lost == 0 and st.resets == 0


def test_line_noise_is_said_at_info_once_per_10_s(dev: FakeDevice, caplog: pytest.LogCaptureFixture) -> None:
    """1 MB of line noise, then samples: the decoder's drops reach the log at INFO, with their counts, in one line
    (not one per read), and the samples after the noise come through."""
    import logging

    noise = np.random.default_rng(5).integers(0, 256, 1 << 20, dtype=np.uint8).tobytes().replace(b"\xa5", b"\x00")
    with caplog.at_level(logging.INFO, logger="ballbar.daemon.sources"), \
            open_source(f"serial:{dev.link}?rate=1000", cal_mm=0.0) as src:
        def send() -> None:  # a pty holds a few kB: written from a thread while the source reads
            dev.write(noise)
            dev.frames(np.arange(100, 200))

        writer = threading.Thread(target=send)
        writer.start()
        batch, _events = read_all(src, 100, timeout=60.0)
        writer.join(10.0)
    assert batch.seq.tolist()[-100:] == list(range(100, 200))
    said = [r for r in caplog.records if "decoder dropped" in r.getMessage()]
    assert len(said) == 1 and said[0].levelno == logging.INFO, [r.getMessage() for r in said]
    assert re.search(r"\d+ skipped_bytes", said[0].getMessage()), said[0].getMessage()


def test_counter_and_clock_wrap_around(dev: FakeDevice) -> None:
    first = SEQ_MODULUS - 5
    with open_source(f"serial:{dev.link}?rate=1000", cal_mm=0.0) as src:
        s = np.arange(first, first + 10)
        clock_s = 4294.967296 - 0.003 + np.arange(10) / 1000  # wraps after 3 samples
        dev.write(encode_samples(s, clock_s, np.zeros(10)))
        batch, events = read_all(src, 10)
    assert batch.seq.tolist() == list(range(first, first + 10))
    assert np.allclose(np.diff(batch.t_device), 0.001, atol=1e-9)
    assert not any(e.kind in (EventKind.LOST, EventKind.DEVICE_RESET) for e in events)


def test_device_restart_is_reported_and_numbers_keep_increasing(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}?rate=1000", cal_mm=0.0) as src:
        dev.frames(np.arange(1000, 1100))
        dev.frames(np.arange(0, 50))  # rebooted: counter and clock from 0
        batch, events = read_all(src, 150)
        st = src.stats()
    assert np.all(np.diff(batch.seq) == 1)
    assert np.all(np.diff(batch.t_device) > 0)
    assert kinds(events).count("device_reset") == 1
    assert st.resets == 1 and st.lost == 0


def test_duplicate_frames_are_dropped_and_counted(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}", cal_mm=0.0) as src:
        dev.frames([0, 1, 2, 2, 3])
        batch, _ = read_all(src, 4)
        src.read(0.05)
        st = src.stats()
    assert batch.seq.tolist() == [0, 1, 2, 3]
    assert st.decode == {"duplicate": 1}


def test_garbage_and_bad_frames_never_raise_and_are_counted(dev: FakeDevice) -> None:
    rng = np.random.default_rng(5)
    with open_source(f"serial:{dev.link}", cal_mm=0.0) as src:
        good = encode_samples(np.arange(20), np.arange(20) / 1000, np.zeros(20))
        bad = bytearray(good[17:34])
        bad[8] ^= 4
        junk = bytes(x for x in rng.integers(0, 256, 1000, dtype=np.uint8).tobytes() if x not in (0xA5, 0x5A))
        dev.write(junk + good[:17] + bytes(bad) + good[34:] + junk)
        batch, _ = read_all(src, 19)
        src.read(0.05)  # the trailing junk, if it came in a read of its own
        st = src.stats()
    assert batch.seq.tolist() == [0, *range(2, 20)]
    assert st.lost == 1
    assert st.decode == {"bad_crc": 1, "skipped_bytes": 2 * len(junk) + 17}


def test_stall_then_resume(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}?rate=1000&stall_s=0.2", cal_mm=0.0) as src:
        dev.frames(np.arange(10))
        read_all(src, 10)
        events = read_until(src, EventKind.STALL, timeout=2.0)
        dev.frames(np.arange(30, 40))  # the device kept sampling: 20 lost in the stall
        seen: list[int] = []
        events += read_until(src, EventKind.RESUMED, samples=seen)
        batch, more = read_all(src, 10 - len(seen))
        events += more
        st = src.stats()
    assert seen + batch.seq.tolist() == list(range(30, 40))
    stall = next(e for e in events if e.kind == EventKind.STALL)
    resumed = next(e for e in events if e.kind == EventKind.RESUMED)
    assert stall.gap_s >= 0.2 and resumed.gap_s >= stall.gap_s
    assert [(e.count, e.detail) for e in events if e.kind == EventKind.LOST] == [(20, "stall")]
    assert st.stalls == 1 and st.lost == 20


def test_unplug_and_replug_without_a_restart(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}?rate=1000&retry_min_s=0.02&retry_max_s=0.1", cal_mm=100.0) as src:
        dev.frames(np.arange(100))
        first, _ = read_all(src, 100)
        dev.unplug()
        events = read_until(src, EventKind.UNPLUGGED)
        time.sleep(0.3)
        assert src.read(0.05) is None  # unplugged is a state: reads just time out
        dev.plug()
        events += read_until(src, EventKind.REPLUGGED)
        dev.frames(np.arange(150, 200))
        second, more = read_all(src, 50)
        events += more
        st = src.stats()
    assert first.seq.tolist() == list(range(100))
    assert second.seq.tolist() == list(range(150, 200))
    replug = next(e for e in events if e.kind == EventKind.REPLUGGED)
    assert replug.gap_s >= 0.3
    assert [(e.seq, e.count, e.detail) for e in events if e.kind == EventKind.LOST] == [(100, 50, "outage")]
    assert (st.unplugs, st.replugs, st.lost, st.connected) == (1, 1, 50, True)


@pytest.mark.parametrize("how", ["hangup", "EIO"])
def test_bytes_read_but_not_decoded_yet_are_kept_when_the_port_goes_away(
    dev: FakeDevice, how: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Relaxed, a fast port is read every drain_s and decoded once per batch: a port that goes away between
    those reads delivers what was read before it, whole (the decoder's partial frame kept for it), then the
    event. A pty whose master closes hangs up (the next wait sees it); a USB adapter pulled mid-read fails
    the read itself with EIO, which no pty does on demand: that read fails here at the os.read it makes."""
    import ballbar.daemon.sources.serial as sources_mod
    from ballbar.daemon.sources import RELAXED_BATCH_S

    fail = threading.Event()
    real_read = os.read

    def read(fd: int, n: int) -> bytes:
        if fail.is_set():
            raise OSError(errno.EIO, "Input/output error")
        return real_read(fd, n)

    monkeypatch.setattr(sources_mod.os, "read", read)
    with open_source(f"serial:{dev.link}?rate=10000&retry_min_s=0.05", cal_mm=0.0) as src:
        got: list[SampleBatch] = []
        stop = threading.Event()

        def reader() -> None:
            while not stop.is_set():
                b = src.read(0.1)
                src.pace(RELAXED_BATCH_S)
                if b is not None:
                    got.append(b)

        t = threading.Thread(target=reader)
        t.start()
        try:
            k = 0
            for _ in range(60):  # 10 kHz for 1.2 s, 20 ms at a time, each write ending mid-frame
                frames = encode_samples(np.arange(k, k + 200), np.arange(k, k + 200) / 1e4, np.zeros(200))
                dev.write(frames[:-7] if k else frames)
                time.sleep(0.02)
                dev.write(frames[-7:] if k else b"")
                k += 200
            assert src.drain_s < src.read_s == RELAXED_BATCH_S  # read every 20 ms, decoded every 0.25 s
            written = 17 * k
            deadline = time.monotonic() + 2.0
            while src.stats().bytes_read < written and time.monotonic() < deadline:
                time.sleep(0.002)
            if how == "EIO":  # now: most likely between two reads of one batch
                fail.set()
            else:
                dev.unplug()
            deadline = time.monotonic() + 3.0
            while not any(e.kind == EventKind.UNPLUGGED for b in got for e in b.events):
                assert time.monotonic() < deadline, "no unplugged event"
                time.sleep(0.01)
        finally:
            stop.set()
            t.join(5)
            fail.clear()
        st = src.stats()
    merged = SampleBatch.concat(got)
    assert merged.seq.tolist() == list(range(k))
    assert st.decode == {} and st.lost == 0, (st.decode, st.lost)
    kinds_in_order = [e.kind for e in merged.events]
    assert kinds_in_order.count(EventKind.UNPLUGGED) == 1
    last_with_samples = max(i for i, b in enumerate(got) if len(b))
    first_unplugged = min(i for i, b in enumerate(got) if any(e.kind == EventKind.UNPLUGGED for e in b.events))
    assert first_unplugged >= last_with_samples  # the event after the samples read before it


def test_port_absent_at_start_is_waited_for(tmp_path: Path) -> None:
    link = tmp_path / "later"
    with open_source(f"serial:{link}?retry_min_s=0.02&retry_max_s=0.05", cal_mm=0.0) as src:
        b = src.read(0.05)
        assert b is not None and kinds(list(b.events)) == ["unplugged"]
        assert "cannot open" in b.events[0].detail
        d = FakeDevice(link)
        try:
            events = read_until(src, EventKind.OPENED)
            d.frames(np.arange(5))
            batch, _ = read_all(src, 5)
        finally:
            d.unplug()
    assert batch.seq.tolist() == list(range(5))
    assert "replugged" not in kinds(events)


# ----------------------------------------------------------------------------- ASCII over a pty


def test_ascii_lines_with_timestamps_count_lost_lines(dev: FakeDevice) -> None:
    fmt = ascii_proto.AsciiFormat(ts_unit="ms", unit="um")
    url = f"serial:{dev.link}?protocol=ascii&timestamp=ms&unit=um&rate=1000"
    with open_source(url, cal_mm=50.0) as src:
        k = np.r_[0:40, 43:60]
        dev.write(ascii_proto.encode(k * 1e-4, fmt, t_s=k / 1000))
        batch, events = read_all(src, k.shape[0])
    assert batch.seq.tolist() == k.tolist()
    assert np.allclose(batch.length_mm, 50.0 + k * 1e-4, atol=1e-12)
    assert np.allclose(batch.t_device, k / 1000)
    assert [(e.seq, e.count) for e in events if e.kind == EventKind.LOST] == [(40, 3)]


def test_ascii_lines_without_clock_get_host_times(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}?protocol=ascii&rate=100", cal_mm=10.0) as src:
        dev.write(b"+0.1\r\n+0.2\r\nOVER\r\nbogus\r\n+0.3\r\n")
        batch, _ = read_all(src, 4)
        src.read(0.05)
        st = src.stats()
    assert batch.seq.tolist() == [0, 1, 2, 3]
    assert np.isnan(batch.t_device).all()
    assert np.all(np.diff(batch.t_host) >= 0)
    assert batch.length_mm[[0, 1, 3]].tolist() == pytest.approx([10.1, 10.2, 10.3])
    assert batch.status.tolist() == [0, 0, int(Status.OVER_RANGE), 0]
    assert batch.valid.tolist() == [True, True, False, True]
    assert st.decode == {"bad_line": 1, "skipped_bytes": 5}


def test_a_line_cut_by_an_unplug_is_dropped_not_parsed(dev: FakeDevice) -> None:
    with open_source(f"serial:{dev.link}?protocol=ascii&retry_min_s=0.02", cal_mm=0.0) as src:
        src.read(0.05)  # opened
        dev.write(b"45\r\n+0.1\r\n+0.12")  # joined mid-line; then the rest of "+0.12345" never comes
        batch, _ = read_all(src, 1)
        time.sleep(0.05)
        dev.unplug()
        events = read_until(src, EventKind.UNPLUGGED)
        dev.plug()
        events += read_until(src, EventKind.REPLUGGED)
        dev.write(b"345\r\n+0.2\r\n")  # the new connection begins mid-line too
        more, _ = read_all(src, 1)
        src.read(0.05)
        st = src.stats()
    assert batch.length_mm.tolist() == [0.1] and more.length_mm.tolist() == [0.2]
    assert st.decode == {"skipped_bytes": 2 + 5 + 3}


# ----------------------------------------------------------------------------- replay and simulator


def write_csv(path: Path, t: np.ndarray, length: np.ndarray) -> None:
    path.write_text("t_s,length_mm\n" + "".join(f"{a:.6f},{b:.6f}\n" for a, b in zip(t, length, strict=True)))


def test_replay_as_fast_as_possible_then_end(tmp_path: Path) -> None:
    t = np.arange(2000) / 1000
    length = 100 + 0.001 * np.sin(t)
    write_csv(tmp_path / "rec.csv", t, length)
    with open_source(f"replay:{tmp_path / 'rec.csv'}?speed=max") as src:
        batches = list(src)
        assert src.finished and src.read(0.01) is None
    merged = SampleBatch.concat(batches)
    assert merged.seq.tolist() == list(range(2000))
    assert np.allclose(merged.t_device, t) and np.allclose(merged.length_mm, length, atol=1e-6)
    assert kinds(list(merged.events)) == ["opened", "end"]


def test_replay_paced_and_gaps_from_rate(tmp_path: Path) -> None:
    k = np.r_[0:100, 110:200]
    write_csv(tmp_path / "rec.csv", k / 100.0, np.full(k.shape, 100.0))
    t0 = time.monotonic()
    with open_source(f"replay:{tmp_path / 'rec.csv'}?speed=10&rate=100") as src:
        merged = SampleBatch.concat(list(src))
    elapsed = time.monotonic() - t0
    assert 0.15 <= elapsed < 1.5  # 1.99 s of recording at 10x
    assert merged.seq.tolist() == k.tolist()
    assert [(e.seq, e.count) for e in merged.events if e.kind == EventKind.LOST] == [(100, 10)]
    assert np.all(np.diff(merged.t_host) >= 0)


def test_sim_source_delivers_the_whole_simulated_test() -> None:
    from ballbar.tools.simulator import MachineModel, simulate

    plan = TestPlan(radius_mm=50, feed_mm_min=3000, overshoot_deg=10, dwell_s=0.1)
    machine = MachineModel(lead_s=0.1, tail_s=0.1, backlash_x_um=4.0)
    ref = simulate(plan, machine, 500.0, seed=2)
    with open_source("sim:?rate=500&speedup=max&seed=2", plan=plan, machine=machine) as src:
        merged = SampleBatch.concat(list(src))
    assert np.array_equal(merged.length_mm, ref.length_mm)
    assert np.array_equal(merged.t_device, ref.t_s)
    assert np.all(merged.status == int(Status.SIMULATED))
    assert kinds(list(merged.events))[-1] == "end"


# ----------------------------------------------------------------------------- pieces


def test_clock_map_finds_drift_under_latency() -> None:
    rng = np.random.default_rng(0)
    cm = ClockMap()
    ratio, offset = 1 + 80e-6, 1234.5
    for td in np.arange(0.0, 300.0, 0.02):
        latency = 2e-4 + rng.exponential(2e-3)
        th = offset + ratio * td + latency
        cm.update(float(td), float(th))
        assert cm.map(np.array([td]))[0] <= th + 1e-12  # never after it was read
    assert abs(cm.ratio - ratio) < 5e-6
    assert abs(cm.map(np.array([150.0]))[0] - (offset + ratio * 150.0)) < 1e-3


def test_clock_map_is_not_tilted_by_seconds_whose_every_read_was_late() -> None:
    """A loaded host: in some seconds every read returns tens of ms late.  The rate is that of the earliest
    reads (within 0.05 % after 5 s), where a line through each second's best read was tilted by 1 %."""
    rng = np.random.default_rng(7)
    cm = ClockMap()
    ratio, offset = 1 + 50e-6, 10.0
    late = {1: 0.03, 2: 0.05, 4: 0.04}  # the second's whole latency floor
    for td in np.arange(0.0, 5.5, 0.01):
        th = offset + ratio * td + late.get(int(td), 0.0) + 2e-4 + rng.exponential(1e-3)
        cm.update(float(td), float(th))
    assert abs(cm.ratio - ratio) < 5e-4, cm.ratio
    assert cm.map(np.array([3.0]))[0] - (offset + ratio * 3.0) < 2e-3


def test_clock_map_refits_once_a_second_not_once_a_read() -> None:
    rng = np.random.default_rng(1)
    cm = ClockMap()
    points = [(td, 50.0 + (1 + 30e-6) * td + 2e-4 + rng.exponential(1e-3)) for td in np.arange(0.0, 60.0, 0.02)]
    for td, th in points[:500]:  # 10 s
        cm.update(float(td), float(th))
    before = cm.refits
    for td, th in points[500:]:  # 50 s more, 2500 reads
        cm.update(float(td), float(th))
        assert cm.map(np.array([td]))[0] <= th + 1e-12
    assert 49 <= cm.refits - before <= 51
    assert abs(cm.ratio - (1 + 30e-6)) < 5e-6


def test_sample_batch_columns_records_and_truthiness() -> None:
    b = SampleBatch.from_columns([1.0, 2.0], [0.1, 0.2], [100.0, 100.1], [5, 6], [0, 2])
    assert len(b) == 2 and b.valid.tolist() == [True, False]
    rec = b.to_records()
    assert rec.dtype == SAMPLE_DTYPE and rec["seq"].tolist() == [5, 6]
    ev = SourceEvent(EventKind.LOST, 1.0, "x", count=3, seq=7, detail="gap")
    empty = SampleBatch.empty([ev])
    assert bool(empty) and len(empty) == 0 and empty.lost == 3
    both = SampleBatch.concat([b, empty, b])
    assert len(both) == 4 and both.events == (ev,)
    assert ev.to_dict() == {"kind": "lost", "t_host": 1.0, "source": "x", "count": 3, "seq": 7, "detail": "gap"}
    with pytest.raises(ValueError, match="length_mm"):
        SampleBatch.from_columns([1.0], [1.0], [1.0, 2.0], [1], [0])
    assert math.isnan(SampleBatch.from_columns([1.0], [math.nan], [1.0], [0], [0]).t_device[0])


def test_stamper_resolves_wraps_across_a_long_outage_with_the_host_clock() -> None:
    from ballbar.daemon.timebase import Stamper
    from ballbar.protocol import Readings
    from ballbar.protocol.binary import CLOCK_WRAP_S

    st = Stamper(SEQ_MODULUS, CLOCK_WRAP_S, 1000.0)

    def readings(k0: int, n: int) -> Readings:
        k = np.arange(k0, k0 + n)
        clock_us = (k * 1000) % 2**32  # 1 kHz on the device's wrapping microsecond clock
        return Readings(np.zeros(n), np.zeros(n, np.uint8), k % SEQ_MODULUS, clock_us / 1e6)

    # One second of samples read in 20 ms batches, host and device clocks in step.
    for i in range(50):
        st.stamp(readings(i * 20, 20), t_read=100.0 + (i + 1) * 0.02)
    # An outage of 1.3 wraps of the 32-bit microsecond clock (93 min), then samples again.
    k0 = 1000 + int(1.3 * CLOCK_WRAP_S * 1000)
    out = st.stamp(readings(k0, 20), t_read=100.0 + (k0 + 20) / 1000)
    assert out.gaps == [(1000, k0 - 1000)]
    assert out.t_device[0] == pytest.approx(k0 / 1000, abs=1e-6)
    assert out.t_host[-1] == pytest.approx(100.0 + (k0 + 19) / 1000, abs=0.05)


def test_stamper_tells_a_clock_jump_from_lost_samples_with_the_devices_own_period() -> None:
    from ballbar.daemon.timebase import Stamper
    from ballbar.protocol import Readings
    from ballbar.protocol.binary import CLOCK_WRAP_S

    # The URL says 1000 Hz; the device really samples at 1024 Hz (its clock in 1/1024 s steps).
    st = Stamper(SEQ_MODULUS, CLOCK_WRAP_S, 1000.0)

    def readings(k: np.ndarray, shift_s: float = 0.0) -> Readings:
        return Readings(np.zeros(k.size), np.zeros(k.size, np.uint8), k % SEQ_MODULUS, k / 1024 + shift_s)

    t = 100.0
    for i in range(20):
        t += 0.02
        out = st.stamp(readings(np.arange(i * 20, i * 20 + 20)), t)
        assert out.jumps == [] and out.reset_seqs == []
    # 5000 samples lost (an outage): a gap the counter explains, no jump
    out = st.stamp(readings(np.arange(5400, 5420)), t + 5.0)
    assert out.gaps == [(400, 5000)] and out.jumps == []
    # the clock steps 2 s ahead while the counter runs on: a jump at the sample after it, nothing lost
    out = st.stamp(readings(np.arange(5420, 5440), 2.0), t + 5.1)
    assert out.gaps == [] and [(s, round(x, 6)) for s, x in out.jumps] == [(5420, 2.0)]
    out = st.stamp(readings(np.arange(5440, 5460), 2.0), t + 5.12)
    assert out.jumps == [] and out.reset_seqs == []
    # a restart: counter and clock from 0, reported with the first sample after it
    out = st.stamp(readings(np.arange(0, 20)), t + 6.0)
    assert out.reset_seqs == [5460] and out.jumps == [] and out.seq[0] == 5460


# ----------------------------------------------------------------------------- wake-ups


def _paced_writer(dev: FakeDevice, n: int, rate: float, written: list[float]) -> threading.Thread:
    """A device that writes one frame per sample period, on time (as a real one does at 1 kHz)."""

    def run() -> None:
        t0 = time.monotonic()
        for k in range(n):
            due = t0 + k / rate
            wait = due - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            written.append(due)  # the sampling instant: the device clock says k / rate
            dev.frames([k], rate=rate)

    th = threading.Thread(target=run)
    th.start()
    return th


def test_a_streaming_device_is_read_once_per_batch_period_with_honest_host_times(
    dev: FakeDevice, monkeypatch: pytest.MonkeyPatch
) -> None:
    import serial

    reconfigured: list[object] = []
    original = serial.Serial._reconfigure_port

    def spy(self: serial.Serial, *args: object, **kwargs: object) -> None:
        reconfigured.append(args)  # termios (and the lock), applied by pyserial at open and at each setting
        original(self, *args, **kwargs)

    monkeypatch.setattr(serial.Serial, "_reconfigure_port", spy)
    n, rate = 2000, 1000.0
    written: list[float] = []
    with open_source(f"serial:{dev.link}?rate=1000", cal_mm=0.0) as src:
        at_open = len(reconfigured)
        writer = _paced_writer(dev, n, rate, written)
        t0 = time.monotonic()
        batch, _ = read_all(src, n, timeout=10.0)
        elapsed = time.monotonic() - t0
        writer.join()
        st = src.stats()
    assert batch.seq.tolist() == list(range(n))
    assert at_open == 1 and len(reconfigured) == at_open, "the port's settings were applied again after open"
    # 2 s of frames, one a millisecond: about one read per 20 ms batch, not one per frame.
    assert st.reads <= elapsed / 0.02 + 10, (st.reads, elapsed)
    assert st.batches <= elapsed / 0.02 + 10
    # Read up to 20 ms late, yet each sample's host time stays close to its sampling instant (the clock
    # map's lower envelope finds the reads that came right after a write).
    err = batch.t_host - np.asarray(written)
    assert np.median(np.abs(err[500:])) < 3e-3, np.percentile(err[500:], [5, 50, 95])


def test_a_slow_device_is_read_as_each_sample_comes(dev: FakeDevice) -> None:
    """Below one sample per batch period the reader waits for bytes: one wake-up per sample, no latency."""
    written: list[float] = []
    with open_source(f"serial:{dev.link}?rate=20", cal_mm=0.0) as src:
        writer = _paced_writer(dev, 10, 20.0, written)
        got: list[tuple[int, float]] = []
        deadline = time.monotonic() + 5.0
        while len(got) < 10 and time.monotonic() < deadline:
            b = src.read(0.2)
            if b is not None and len(b):
                got += [(int(s), time.monotonic()) for s in b.seq]
        writer.join()
        st = src.stats()
    assert [k for k, _ in got] == list(range(10))
    # one read per sample: none waited for the next (how soon it came is the benchmarks' business, under load)
    assert st.reads == 10
    assert all(t >= w for (_, t), w in zip(got, written, strict=True))


def test_the_stampers_steady_shortcut_gives_what_the_general_path_gives() -> None:
    from ballbar.daemon.timebase import Stamper
    from ballbar.protocol import Readings
    from ballbar.protocol.binary import CLOCK_WRAP_S

    rng = np.random.default_rng(7)
    k, clock_us = 1000, 4_294_000_000  # the clock wraps a few seconds in
    reads = []
    outage = 0.0
    for i in range(800):
        n = int(rng.integers(1, 40))
        ks = k + np.arange(n)
        cl = clock_us + 1000 * np.arange(n)
        what = rng.random()
        if what < 0.02:
            ks[n // 2 :] += int(rng.integers(1, 50))  # lost samples
        elif what < 0.03:
            ks[n // 2 :] -= 500  # a restart
            cl[n // 2 :] = 1000 * np.arange(n - n // 2)
        elif what < 0.04:
            cl[n // 2 :] += 3_000_000  # a clock jump
        elif what < 0.05 and n > 1:
            ks[-1], cl[-1] = ks[-2], cl[-2]  # a duplicate
        k, clock_us = int(ks[-1]) + 1, int(cl[-1]) + 1000
        outage += 5.0 if what > 0.995 else 0.0
        t_read = 50.0 + i * 0.02 + outage + rng.exponential(1e-3)
        reads.append((Readings(np.zeros(n), np.zeros(n, np.uint8), ks % SEQ_MODULUS, (cl % 2**32) / 1e6), t_read))
    fast, slow = Stamper(SEQ_MODULUS, CLOCK_WRAP_S, 1000.0), Stamper(SEQ_MODULUS, CLOCK_WRAP_S, 1000.0)
    slow.fast = False
    taken: list[bool] = []
    shortcut = fast._stamp_steady

    def spy(r: Readings, t: float) -> object:
        out = shortcut(r, t)
        taken.append(out is not None)
        return out

    fast._stamp_steady = spy  # type: ignore[method-assign]
    for r, t in reads:
        a, b = fast.stamp(r, t), slow.stamp(r, t)
        assert np.array_equal(a.keep, b.keep) and np.array_equal(a.seq, b.seq)
        assert np.array_equal(a.t_device, b.t_device) and np.array_equal(a.t_host, b.t_host)
        assert (a.gaps, a.reset_seqs, a.jumps) == (b.gaps, b.reset_seqs, b.jumps)
    assert 0.5 * len(reads) < sum(taken) < len(reads) - 50  # both ways were taken, often


@pytest.mark.parametrize(("rate", "drain_s"), [(1000, 3000 / 17000), (10000, 0.02)])
def test_a_relaxed_serial_read_never_leaves_a_tty_more_than_it_buffers(rate: int, drain_s: float) -> None:
    """pace() lengthens the batches up to RELAXED_BATCH_S, but the port is read at least every drain_s:
    never past TTY_READ_BYTES at its byte rate (17 bytes a sample). Beyond a tty's 4 KiB the kernel
    throttles the adapter (a device without flow control overruns; the simulated device's writes block,
    and its samples arrive late). What those reads bring is decoded once per batch."""
    from ballbar.daemon.sources import DEFAULT_BATCH_S, RELAXED_BATCH_S, TTY_READ_BYTES
    from ballbar.tools.simdevice import DeviceProcess

    assert drain_s < RELAXED_BATCH_S  # the byte rate, not the batch, decides how often the port is read
    with DeviceProcess("--rate", str(rate)) as dev, open_source(dev.url) as src:
        assert src.read_s == DEFAULT_BATCH_S
        src.pace(0.25)
        assert src.read_s == RELAXED_BATCH_S and src.drain_s == DEFAULT_BATCH_S  # byte rate not seen yet
        batches, got, late = 0, 0, []
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            b = src.read(timeout=1.0)
            src.pace(0.25)
            if b is not None and len(b):
                batches += 1
                got += len(b)
                late.append(time.monotonic() - float(b.t_host[-1]))
                if batches == 3:
                    reads0, bytes0 = src.stats().reads, src.stats().bytes_read
        assert src.drain_s == pytest.approx(drain_s, rel=0.25)
        st = src.stats()
        per_read = (st.bytes_read - bytes0) / (st.reads - reads0)
        # at most what the tty holds, or what one 20 ms batch brings where that is more (10 kHz: 3.4 kB)
        assert per_read <= max(TTY_READ_BYTES, 17 * rate * DEFAULT_BATCH_S) * 1.2, per_read
        assert batches <= 2.0 / RELAXED_BATCH_S + 3, batches  # one decoded batch per period, not per read
        assert st.reads - reads0 >= 0.7 * (2.0 - 3 * RELAXED_BATCH_S) / drain_s, st.reads - reads0
        assert got > 1.5 * rate and np.median(late[3:]) < 0.05, (got, late)
