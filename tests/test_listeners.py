"""Listener queues: batches only where wanted, merged where asked for, threads that sleep until there is work."""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import pytest

from ballbar.daemon.listeners import Listener, ListenerQueue
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent

pytestmark = pytest.mark.usefixtures("no_leaks")


class Recorder(Listener):
    name = "recorder"

    def __init__(self, period: float | None, idle_s: float | None = None) -> None:
        self.batch_period_s = period
        self.idle_s = idle_s
        self.calls: list[tuple[str, Any]] = []
        self.idles = 0
        self.tid: int | None = None

    def on_batch(self, batch: SampleBatch) -> None:
        self.tid = threading.get_native_id()
        self.calls.append(("batch", batch))

    def on_message(self, msg: dict[str, Any]) -> None:
        self.tid = threading.get_native_id()
        self.calls.append(("message", msg))

    def on_idle(self) -> None:
        self.tid = threading.get_native_id()
        self.idles += 1

    def stop(self) -> None:
        pass


def batch(k0: int, n: int, events: tuple[SourceEvent, ...] = ()) -> SampleBatch:
    k = np.arange(k0, k0 + n)
    return SampleBatch.from_columns(1000.0 + k / 1000, k / 1000, 100.0 + k * 1e-6, k, np.zeros(n), events, "t")


def lost(seq: int) -> SourceEvent:
    return SourceEvent(EventKind.LOST, time.monotonic(), "t", count=1, seq=seq, detail="gap")


def switches(tid: int) -> int:
    """Context switches of one thread so far (each wake-up from a wait is at least one)."""
    total = 0
    with open(f"/proc/self/task/{tid}/status") as fh:
        for line in fh:
            if line.startswith(("voluntary_ctxt_switches", "nonvoluntary_ctxt_switches")):
                total += int(line.split()[1])
    return total


def test_a_listener_without_batch_interest_gets_none() -> None:
    rec = Recorder(None)
    q = ListenerQueue(rec, 10)
    try:
        assert not q.wants_batches
        assert q.put_batch(batch(0, 20)) is False
        assert q.put_message({"kind": "event", "event": "lost"})
        assert q.wait_idle(2.0)
    finally:
        q.close(1.0)
    assert [kind for kind, _ in rec.calls] == ["message"]
    assert q.stats.dropped == 0 and q.stats.delivered == 1


def test_merged_batches_keep_every_sample_and_event_in_order_around_messages() -> None:
    rec = Recorder(0.2)
    q = ListenerQueue(rec, 1000)
    sent = 0
    try:
        for i in range(60):  # 1.2 s of 20 ms batches, a gap every 7th, a message every 25th
            ev = (lost(i * 20),) if i % 7 == 3 else ()
            q.put_batch(batch(i * 20 + (i % 7 == 3), 20 - (i % 7 == 3), ev))
            sent += 1
            if i % 25 == 24:
                q.put_message({"kind": "status", "after": i})
                sent += 1
            time.sleep(0.02)
        assert q.wait_idle(2.0)
    finally:
        q.close(1.0)
    batches = [b for kind, b in rec.calls if kind == "batch"]
    merged = SampleBatch.concat(batches)
    expect = [k for i in range(60) for k in range(i * 20 + (i % 7 == 3), i * 20 + 20)]
    assert merged.seq.tolist() == expect
    assert [e.seq for e in merged.events] == [i * 20 for i in range(60) if i % 7 == 3]
    # each message comes after exactly the batches put before it
    seen = 0
    for kind, item in rec.calls:
        if kind == "batch":
            seen += len(item)
        else:
            assert seen == sum(len(range(i * 20 + (i % 7 == 3), i * 20 + 20)) for i in range(item["after"] + 1))
    # about one delivery per 0.2 s (plus one before each message), not one per batch
    assert len(batches) <= 1.25 / 0.2 + 2 + 3, len(batches)
    assert q.stats.delivered == sent and q.stats.dropped == 0 and q.stats.errors == 0


def test_a_held_run_is_delivered_when_the_source_goes_quiet() -> None:
    rec = Recorder(0.1)
    q = ListenerQueue(rec, 100)
    try:
        q.put_batch(batch(0, 5))
        t0 = time.monotonic()
        while not rec.calls and time.monotonic() - t0 < 2.0:
            time.sleep(0.005)
        assert rec.calls and time.monotonic() - t0 < 0.5
    finally:
        q.close(1.0)


def test_drops_count_items_and_a_merged_delivery_counts_what_it_merged() -> None:
    rec = Recorder(5.0)  # held long: the queue fills
    q = ListenerQueue(rec, 10, "drop_newest")
    try:
        accepted = sum(q.put_batch(batch(i * 20, 20)) for i in range(15))
        assert accepted == 10 and q.stats.dropped == 5
    finally:
        q.close(1.0)  # delivers what it held, merged
    assert len(rec.calls) == 1 and len(rec.calls[0][1]) == 200
    assert q.stats.delivered == 10


def test_listener_threads_sleep_until_there_is_work() -> None:
    idle = Recorder(0.25, idle_s=None)
    every = Recorder(0.0, idle_s=None)
    qi, qe = ListenerQueue(idle, 1000), ListenerQueue(every, 1000)
    try:
        qi.put_message({"kind": "hello"})
        qe.put_message({"kind": "hello"})
        assert qi.wait_idle(1.0) and qe.wait_idle(1.0)
        assert idle.tid is not None and every.tid is not None
        time.sleep(0.2)
        a0, b0 = switches(idle.tid), switches(every.tid)
        time.sleep(1.0)  # nothing queued, no timers: no wake-ups at all
        assert switches(idle.tid) - a0 == 0 and switches(every.tid) - b0 == 0
        a0, b0 = switches(idle.tid), switches(every.tid)
        for i in range(50):  # 1 s of 20 ms batches
            qi.put_batch(batch(i * 20, 20))
            qe.put_batch(batch(i * 20, 20))
            time.sleep(0.02)
        da, db = switches(idle.tid) - a0, switches(every.tid) - b0
        # merged every 0.25 s: a few deliveries and wake-ups (each may also wait for the GIL once or twice),
        # against about one a batch for the listener that wants each
        assert len(idle.calls) - 1 <= 6 and len(every.calls) - 1 == 50
        assert da < db / 2 and db >= 25, (da, db)
    finally:
        qi.close(1.0)
        qe.close(1.0)


class Shifting(Recorder):
    """Wants batches merged, or each one, as it says from one batch to the next."""

    def __init__(self) -> None:
        super().__init__(0.0)
        self.period = 0.25

    def batch_period_now(self) -> float:
        return self.period


def test_a_listener_can_change_its_period_as_it_goes() -> None:
    rec = Shifting()
    q = ListenerQueue(rec, 1000)
    try:
        for i in range(25):  # 0.5 s of 20 ms batches, merged
            q.put_batch(batch(i * 20, 20))
            time.sleep(0.02)
        assert q.wait_idle(2.0)
        merged = len(rec.calls)
        assert 1 <= merged <= 4, merged
        rec.period = 0.0  # a result nears: each batch as it comes
        for i in range(25, 35):
            q.put_batch(batch(i * 20, 20))
            time.sleep(0.02)
        assert q.wait_idle(2.0)
        assert len(rec.calls) - merged == 10
        seq = np.concatenate([b.seq for _, b in rec.calls])
        assert np.array_equal(seq, np.arange(35 * 20))  # every sample once, in order
    finally:
        q.close(1.0)


def test_on_idle_runs_on_its_own_timer() -> None:
    rec = Recorder(0.0, idle_s=0.1)
    q = ListenerQueue(rec, 10)
    try:
        time.sleep(0.55)
    finally:
        q.close(1.0)
    assert 3 <= rec.idles <= 6


def test_the_daemon_puts_batches_only_where_they_are_wanted() -> None:
    from ballbar.daemon.config import load
    from ballbar.daemon.service import Daemon
    from ballbar.daemon.sources import open_source

    cfg = load(None, ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"'], env={})
    src = open_source("sim:?speedup=max&rate=100")
    rec, merged = Recorder(None), Recorder(0.25)
    merged.name = "merged"
    d = Daemon(cfg, src, [(rec, 10, "drop_oldest"), (merged, 10, "drop_oldest")])
    try:
        assert [q.listener.name for q in d.batch_queues] == ["merged", "analysis"]  # not "recorder", not "log"
    finally:
        d.shutdown(1.0)


def test_the_built_outputs_take_batches_as_their_listeners_say_and_the_reader_follows(tmp_path: Any) -> None:
    """The daemon's own outputs, as `ballbar run` builds them: the viewer (made later, on its queue's thread)
    merged four times a second like the log, not woken for every batch; and the source read as often as the most
    pressed of them wants: every RELAXED_BATCH_S while the analysis merges too, every 20 ms once it wants each batch."""
    from ballbar.daemon.config import load
    from ballbar.daemon.rerun import RerunViewer
    from ballbar.daemon.run import build_listeners
    from ballbar.daemon.service import MERGE_S, Daemon
    from ballbar.daemon.sources import DEFAULT_BATCH_S, RELAXED_BATCH_S, open_source

    sets = ["zenoh.enabled=false", f'daemon.state_dir="{tmp_path}"', "daemon.analysis_worker=false"]
    cfg = load(None, [*sets, 'rerun.mode="connect"', 'rerun.url="rerun+http://127.0.0.1:9/proxy"'], env={})
    d = Daemon(cfg, open_source("sim:?speedup=1&rate=100"), build_listeners(cfg))
    try:  # not run: the viewer is made at its first item (its runtime would outlive the test)
        periods = {q.listener.name: q.period() for q in d.batch_queues}
        assert periods == {"mcap": 0.25, "rerun": RerunViewer.batch_period_s, "analysis": 0.0}
        assert next(q for q in d.outputs if q.listener.name == "rerun").idle_s == RerunViewer.idle_s
    finally:
        d.shutdown(1.0)
    cfg = load(None, [*sets, 'rerun.mode="off"'], env={})
    src = open_source("sim:?speedup=1&rate=100")
    d = Daemon(cfg, src, build_listeners(cfg))
    try:
        d.run(threading.Event(), duration_s=1.5)
        assert d.analysis.batch_period_now() == MERGE_S  # no test in progress: nothing due
        assert src.read_s == RELAXED_BATCH_S
        src.pace(0.0)
        assert src.read_s == DEFAULT_BATCH_S
    finally:
        d.shutdown(1.0)


def test_each_outputs_optional_capabilities_are_its_protocols() -> None:
    """The daemon finds what an output can do beyond taking messages by its type (typed Protocols), not by probing
    attribute names: the monitor annotates test results and sends alerts, the sets send set results, the bus
    takes a service's plan choice, and the plain outputs do none of it."""
    from ballbar.daemon.bus import ZenohBus
    from ballbar.daemon.listeners import Annotator, PlanControl, Sender
    from ballbar.daemon.mcap import McapLogger
    from ballbar.daemon.monitor import MonitorListener
    from ballbar.daemon.service import LogListener
    from ballbar.daemon.sets import SetListener

    def caps(cls: type) -> set[str]:
        return {name for name, proto in (("annotate", Annotator), ("send", Sender), ("control", PlanControl))
                if issubclass(cls, proto)}

    assert caps(MonitorListener) == {"annotate", "send"}
    assert caps(SetListener) == {"send"}
    assert caps(ZenohBus) == {"control"}
    assert caps(McapLogger) == caps(LogListener) == set()


def test_the_log_line_of_each_test_names_the_reversal_spikes_per_axis(
    tmp_path: Any, caplog: pytest.LogCaptureFixture
) -> None:
    """Three tests of the demo machine (``ballbar run --simulate``'s): each test's log line names the same
    findings (the largest reversal spike of each axis, not whichever of its four spikes the noise ranked first)."""
    import logging
    import re

    from ballbar.daemon.config import load
    from ballbar.daemon.service import Daemon
    from ballbar.daemon.sources import open_source

    cfg = load(None, ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"', "daemon.analysis_worker=false",
                      f'daemon.state_dir="{tmp_path}"', "plan.sample_hz=100.0"], env={})
    from ballbar.tools.simulate import SIM_MACHINE
    from ballbar.tools.simulator import MachineModel

    demo = MachineModel(**{k: float(v) for k, v in (item.split("=") for item in SIM_MACHINE)})
    d = Daemon(cfg, open_source("sim:?speedup=max&rate=100&repeat=3&seed=3", machine=demo), [])
    with caplog.at_level(logging.INFO, logger="ballbar.daemon.service"):
        assert d.run(threading.Event(), max_tests=3) == 0
    lines = [r.getMessage() for r in caplog.records if re.search(r" test: ", r.getMessage())]
    assert len(lines) == 3, lines
    names = [re.findall(r"([a-z_]+) -?[0-9.]+(?:e[-+]?\d+)?", ln.split(" test: ", 1)[1].split(";")[0]) for ln in lines]
    assert names[0] == names[1] == names[2], lines
    assert "reversal_spike_x_max_um" in names[0], lines
    assert not any(re.search(r"reversal_spike_[xy]_(pos|neg)_(ccw|cw)", ln) for ln in lines), lines
