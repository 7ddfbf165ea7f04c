"""The daemon: a source feeding listeners through bounded queues.

::

    source --read()--> main loop --> [queue] analysis (detector + incremental fit) <--> child: each test's fit
                           |                   \\--> results/events --> the queues below
                           +-------------> [queue] MCAP logger
                           +-------------> [queue] Zenoh bus
                           +-------------> [queue] Rerun viewer

The main loop only reads the source and puts what it read into each queue that
wants batches; it never waits on a consumer.  The analysis takes every ~20 ms
batch (its latency budget); the MCAP logger and the viewer take them merged,
about every 0.25 s; the bus only when it publishes samples; the log none.  Each
queue has a bound and a drop policy (:mod:`.listeners`); what a queue drops is
counted and shown in the status.
The analysis queue and the MCAP queue drop new items when full (a contiguous
prefix, the gap counted); the bus and the viewer drop the oldest (the newest
matters).  The main loop also sends ``READY=1`` once the source is open,
``WATCHDOG=1`` each status interval, and the status message.

Results carry, besides the ``ballbar analyze --json`` object, ``machine_id``,
``test_id`` (``<machine>-<UTC time of the feed-in>``, then ``-2``, ``-3`` for
more tests started within the same second), ``t_wall`` (ISO time of
publication), ``t_host`` (monotonic), ``last_sample_t`` (the time axis
value of the last sample the analysis had seen), ``last_sample_t_host`` (that
sample's host time, on the same monotonic clock as ``t_host``) and
``latency_ms`` (``t_host - last_sample_t_host``: how long after its last sample
a result went out).
"""

from __future__ import annotations

import collections
import concurrent.futures as cf
import contextlib
import datetime as dt
import functools
import logging
import math
import re
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from ballbar.analysis.engine import TestAnalyzer, TimingHints
from ballbar.analysis.errors import BallbarError
from ballbar.analysis.numbers import measured
from ballbar.analysis.plan import PLANE_AXES
from ballbar.analysis.polled import Timing, from_events, state_span
from ballbar.analysis.report import finding_words, pattern_label
from ballbar.protocol.messages import stamp
from ballbar.protocol.messages.publish import parameter_map, published, source_event

from .analysis_worker import AnalysisWorker, freeze_long_lived, release_freed_memory
from .config import Config
from .listeners import (
    MERGE_S,
    TEST_END_EVENTS,
    Annotator,
    DropPolicy,
    Listener,
    ListenerQueue,
    Message,
    PlanChoice,
    PlanControl,
    Sender,
    StartsLate,
    Wake,
)
from .mcap import scaled_ints
from .samples import EventKind, SampleBatch, breaks_in
from .secrets import redacted
from .sources import Source
from .systemd import Notifier

if TYPE_CHECKING:
    from ballbar.protocol.messages import AnalysisOutput, CircleResult, ConfigMessage, Settings, Status, TestResult
    from ballbar.protocol.messages.controller import ControllerMessage
    from ballbar.protocol.messages.envelope import LastSample
    from ballbar.protocol.messages.events import PlanChoiceRefusedBody, PlanChosenBody, SourceEvent, TestIncomplete
    from ballbar.protocol.messages.publish import Published
    from ballbar.protocol.messages.status import AnalysisStats, Outputs, Queue, SourceState, SourceStats

    from .controller import ControllerClient

log = logging.getLogger(__name__)

FINISH_ANALYSIS_S = 120.0  # after a finite source's end, at most this for the analysis to catch up
STOP_RESULT_S = 1.0  # at a stop, at most this for a test's fit still running in the worker
WAKE: Wake = {"kind": "analysis_done"}  # what the worker's callback posts to the analysis queue


class AnalysisListener(Listener):
    """Feeds valid samples to :class:`TestAnalyzer`; hands its output to ``emit``.

    The time axis is the device clock where the source has one (evenly spaced,
    and with a simulated device sped up, the simulated time), else host time.
    A device reset, a device clock jump and a long loss that a batch's events
    report become a break (:meth:`TestAnalyzer.mark_break`) just before the
    sample they name: the test in progress is rejected.  A time axis the
    analysis refuses (a clock that ran back) rejects the test in progress and
    starts the analysis afresh from the offending sample; the timing hints are
    kept (they only ever come from tests that passed).

    A polled source's ``timing`` events (its stamps' uncertainty and jitter)
    are stated on every result (:func:`ballbar.analysis.polled.state_span`):
    the largest of the last before the feed-in and those up to the feed-out.

    Between tests and mid-circle no result can be due: the batches then come
    merged, every ``MERGE_S`` (:meth:`batch_period_now`); as the end of a
    circle nears (within three merge periods at the rate the samples' clock
    has been running against the host's), and from the last circle's end to
    the feed-out, each batch comes as it is read.  At 1 kHz that is about
    four wake-ups a second instead of fifty for most of a test.

    ``executor``: where each test's fit runs (the daemon's
    :class:`~.analysis_worker.AnalysisWorker`; ``None``: in this thread).  Its
    result is emitted when it is done (``wake``, set by the daemon, posts a
    message to this listener's queue then) or at the next batch; it carries the
    ``last_sample_t`` of the batch that ended the test, as inline.
    """

    name = "analysis"
    batch_period_s = 0.0  # every batch as read, as a result nears: the results' latency budget
    idle_s = None

    def __init__(self, cfg: Config, emit: Callable[[Message], None], executor: cf.Executor | None = None) -> None:
        self.cfg = cfg
        self.emit = emit
        self.executor = executor
        self.wake: Callable[[], object] | None = None
        self._program: str | None = None  # the controller's main program now (None: none)
        self._controller_known = False  # a controller's state has come (and was not lost since)
        self.analyzer = self._new_analyzer()
        self._test_end: tuple[float, float, float] | None = None  # last_t, last_t_host, perf time at feed-out
        self._period = 0.0  # batch_period_now()
        self._clock_rate = 1.0  # the samples' clock's seconds per host second, lately (a speed-up shows here)
        self.use_device_time: bool | None = None
        self.test_id: str | None = None
        self._id_base, self._same_second = "", 0
        self.last_t = math.nan
        self.last_t_host = math.nan
        self.results = 0
        self.tests = 0
        self.errors = 0
        self.fit_latency_ms: float | None = None
        self.invalid = 0
        self._timings: collections.deque[Timing] = collections.deque(maxlen=256)  # a polled source's timing events
        self._lock = threading.Lock()

    def _new_analyzer(self, hints: TimingHints | None = None,
                      plan_hints: dict[str, TimingHints] | None = None) -> TestAnalyzer:
        an = TestAnalyzer(self.cfg.plan, self.cfg.machine, self.cfg.analysis, hints, executor=self.executor,
                          on_submit=self._submitted, library=self.cfg.library, plan_hints=plan_hints)
        if self._controller_known:
            an.set_controller(self._program)
        return an

    def _on_controller(self, msg: ControllerMessage) -> None:
        """The CNC controller's news: the main program it runs now (the analyzer finds its plan).  Lost: not
        known (:func:`~ballbar.analysis.plans.controller_program` is the same rule, offline)."""
        from ballbar.analysis.plans import controller_program

        known, program = controller_program(msg)
        if known is None:
            return
        if not known:
            self._controller_known = False
            self.analyzer.forget_controller()
            return
        if not self._controller_known or program != self._program:
            p = self.cfg.library.by_program(program)
            log.info("the controller runs %s%s", program or "no program",
                     f": plan {p.name}" if p else (" (no plan's program)" if program else ""))
        self._program, self._controller_known = program, True
        self.analyzer.set_controller(program)

    def _submitted(self, fut: cf.Future[dict[str, Any]]) -> None:
        fut.add_done_callback(lambda _f: self.wake() if self.wake is not None else None)

    @property
    def pending(self) -> bool:
        """A test's fit is running in the worker."""
        return self.analyzer.pending

    def on_batch(self, batch: SampleBatch) -> None:
        with self._lock:  # stop() may run on another thread at shutdown
            self._on_batch(batch)
            self._period = self._next_period()

    def batch_period_now(self) -> float:
        """0 (each batch) while a result may soon be due, else ``MERGE_S`` (see the class docstring)."""
        return self._period

    def _next_period(self) -> float:
        due = self.analyzer.next_due()
        if due is None or not math.isfinite(self.last_t):
            return MERGE_S
        return 0.0 if due - self.last_t <= 3.0 * MERGE_S * self._clock_rate else MERGE_S

    def on_message(self, msg: Message) -> None:
        if msg["kind"] == "analysis_done":
            self.settle()
        elif msg["kind"] == "controller":
            with self._lock:
                self._on_controller(msg)
        elif msg["kind"] == "plan_choice":
            with self._lock:
                answer = self._choose(msg["plan"])
                if answer is not None:
                    self._emit_all([answer])

    def _choose(self, name: object) -> PlanChosenBody | PlanChoiceRefusedBody | None:
        """An explicit choice of the next test's plan (from the bus): taken, or refused with the reason; None for
        the choice standing put again (a peer that repeats itself makes no event, log line or record)."""
        if name == self.analyzer.chosen:
            log.debug("the choice of the next plan repeated: %r", name)
            return None
        library = self.cfg.library
        if name is not None and (not isinstance(name, str) or name not in library.names):
            why = (f"no plan {name!r} in the library ({', '.join(library.names)})" if isinstance(name, str)
                   else f"a plan's name is a string, not {name!r}")
            log.warning("the choice of the next plan was refused: %s", why)
            return {"kind": "event", "event": "plan_choice_refused", "message": why}
        self.analyzer.choose(name)
        text = (f"the next test is analysed as plan {name}, whatever its signature or timing say" if name is not None
                else "the choice of the next plan is withdrawn: the next test's plan is recognised")
        log.info("%s", text)
        return {"kind": "event", "event": "plan_chosen", "plan": name, "message": text}

    def settle(self, timeout: float = 0.0) -> None:
        """Emit the result of the test fitted in the worker, if it is done (waiting up to ``timeout``)."""
        with self._lock:
            self._emit_all(self.analyzer.collect(wait=timeout > 0, timeout=timeout))

    def _on_batch(self, batch: SampleBatch) -> None:
        for ev in batch.events:
            if ev.kind == EventKind.TIMING:
                self._timings.extend(from_events([ev.to_dict()]))
        valid = batch.valid
        self.invalid += int((~valid).sum())
        if self.use_device_time is None and len(batch):
            self.use_device_time = bool(np.isfinite(batch.t_device).all())
        t = batch.t_device if self.use_device_time else batch.t_host
        good = valid & np.isfinite(t)
        t, L, seq = t[good], batch.length_mm[good], batch.seq[good]
        # As the log records them (1 ns, 1 pm): ``ballbar analyze`` of the log then sees these very numbers,
        # and its result is the one published (the timing search's decisions are discrete).
        t, L = scaled_ints(t, 10**9) / 1e9, scaled_ints(L, 10**9) / 1e9
        # A device reset, clock jump or long loss the batch reports: a break before its first sample after it.
        cuts = breaks_in(batch.events, seq)
        if not t.size and not cuts:
            return
        if t.size:
            th = batch.t_host[good]
            if t.size > 1 and th[-1] > th[0]:
                rate = float(t[-1] - t[0]) / float(th[-1] - th[0])
                self._clock_rate = max(rate, 0.5 * self._clock_rate)  # rises at once, falls by half a batch at most
            self.last_t, self.last_t_host = float(t[-1]), float(th[-1])
        t0 = time.perf_counter()
        out: list[AnalysisOutput] = []
        i = 0
        for j, reason in cuts:
            self._feed(t[i:j], L[i:j], out)
            self.analyzer.mark_break(reason)
            i = j
        self._feed(t[i:], L[i:], out)
        self._emit_all(out, t0)

    def _emit_all(self, out: list[AnalysisOutput], t0: float | None = None) -> None:
        """Wrap and emit what the analyzer returned for a batch started at ``t0`` (perf time; None: a result
        from the worker)."""
        now = time.perf_counter()
        for msg in out:
            if msg["kind"] == "event" and msg["event"] == "feed_out":
                self._test_end = (self.last_t, self.last_t_host, now if t0 is None else t0)
            if msg["kind"] != "event" and self._timings and not self.use_device_time:
                state_span(msg, self._timings)
            if msg["kind"] != "event":
                began = self._test_end[2] if msg["kind"] == "test" and self._test_end else (t0 or now)
                self.fit_latency_ms = 1000.0 * (now - began)
                self.results += 1
                self.tests += msg["kind"] == "test"
            self.emit(self._wrap(msg))
        if self.executor is None and any(m["kind"] == "test" or m.get("event") in TEST_END_EVENTS for m in out):
            release_freed_memory()  # the worker gives back its own

    def _feed(self, t: np.ndarray, L: np.ndarray, out: list[AnalysisOutput]) -> None:
        """Feed a piece; on an error, reject the test in progress and start afresh from the offending sample."""
        try:
            out.extend(self.analyzer.feed(t, L))
            return
        except BallbarError as err:
            index = getattr(err, "index", None)
            start = min(max(index - self.analyzer.axis.n, 0), t.size) if isinstance(index, int) else t.size
            # A time axis the analysis cannot take (a clock that ran back): the test in progress is lost.
            # Its hints are not: TestAnalyzer only learns them from tests that passed.
            self.errors += 1
            log.warning("analysis: %s; restarting test detection", err)
            out.extend(self.analyzer.abort(f"the analysis restarted: {err}"))
            out.append({"kind": "event", "event": "analysis_reset", "message": str(err)})
            chosen = self.analyzer.chosen
            self.analyzer = self._new_analyzer(self.analyzer.hints, self.analyzer.plan_hints)
            if chosen is not None:  # a choice not yet used holds for the next test still
                self.analyzer.choose(chosen)
        if start < t.size:
            self._feed(t[start:], L[start:], out)

    def _wrap(self, msg: AnalysisOutput) -> Published:
        if msg["kind"] == "event" and msg["event"] == "feed_in":
            second = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
            base = f"{self.cfg.daemon.machine_id}-{second}"
            # Tests replayed faster than real time can start within one second: keep the ids unique.
            self._same_second = self._same_second + 1 if base == self._id_base else 1
            self._id_base = base
            self.test_id = base if self._same_second == 1 else f"{base}-{self._same_second}"
        now = time.monotonic()
        last_t, last_t_host = self.last_t, self.last_t_host
        if msg["kind"] == "test" and self._test_end is not None:  # the batch that ended the test
            last_t, last_t_host, _ = self._test_end
        last: LastSample = {
            "test_id": self.test_id, "t_host": now, "last_sample_t": last_t, "last_sample_t_host": last_t_host,
            "latency_ms": 1000.0 * (now - last_t_host), "time_axis": "device" if self.use_device_time else "host",
        }
        return published(msg, stamp(self.cfg.daemon.machine_id), last)

    def stop(self) -> None:
        with self._lock, contextlib.suppress(BallbarError):
            if self.analyzer.pending:  # a test's fit in the worker: its result, if it comes within STOP_RESULT_S
                self._emit_all(self.analyzer.collect(wait=True, timeout=STOP_RESULT_S))
                if self.analyzer.pending:
                    log.warning("analysis: test %d was still being fitted at the stop; its result is not published "
                                "(ballbar analyze of its recording gives it)", self.analyzer.test_index)
                    return
            for msg in self.analyzer.finish():
                if msg["kind"] == "event" and msg["event"] in TEST_END_EVENTS:
                    self.emit(self._wrap(msg))


class LogListener(Listener):
    """One log line per result and per notable event (journald under systemd)."""

    name = "log"
    batch_period_s = None  # results and events only (source events come as messages)
    idle_s = None

    def on_message(self, msg: Message) -> None:
        if msg["kind"] == "circle" or msg["kind"] == "test":
            self._result(msg)
        elif msg["kind"] == "set":
            log.info("%s set %s: %s", msg["machine_id"], msg["set_id"], msg["verdict"]["summary"])
        elif msg["kind"] == "event" and msg["event"] in (
            "unplugged", "replugged", "lost", "stall", "resumed", "device_reset", "clock_jump", "counter_jump",
            "test_rejected",
            "test_incomplete", "analysis_reset", "test_unrecognised", "plan_choice_refused",
        ):
            log.warning("%s", event_sentence(msg))

    @staticmethod
    def _result(msg: CircleResult | TestResult) -> None:
        setup = ("centre", "radius")
        ranked = _per_axis_spikes([r["pattern"] for r in msg["ranking"] if r["significant"]
                                   and r["pattern"] not in setup])
        top = ", ".join(_finding(msg, p) for p in ranked[:5]) or "nothing significant"
        name = msg["plan"].get("name")
        of = f" of plan {name}" if name and name != "default" else ""  # a library of plans: which
        if msg["kind"] == "circle":
            log.info("%s %s circle%s: %s", msg["test_id"], msg["direction"].upper(), of, top)
            return
        feed = msg["timing"]["measured_feed_mm_min"]
        log.info("%s test%s: %s; G(b) %s, feed %.1f mm/min", msg["test_id"], of, top,
                 measured(msg["iso230_4"]["G_b_um"], None, "um"), math.nan if feed is None else feed)
        verdict = msg.get("verdict")
        if verdict is not None and verdict["limits"]:
            log.info("%s verdict: %s", msg["test_id"], verdict["summary"])

    def stop(self) -> None:
        pass


def event_sentence(msg: Mapping[str, Any]) -> str:
    """An event as one sentence for the log (the payload itself is on the bus and in the recordings)."""
    name = str(msg.get("event"))
    detail = msg.get("detail") or ""
    gap = msg.get("gap_s")
    gap_s = f"{gap:.3g} s" if isinstance(gap, int | float) else "an unknown time"
    test = msg.get("test_id") or "the test"
    texts = {
        "unplugged": f"the source was unplugged ({detail}); retrying",
        "replugged": f"the source is back after {gap_s} ({detail})",
        "lost": f"{msg.get('count')} samples lost from sample {msg.get('seq')} ({detail})",
        "stall": f"the source stalled: no bytes for {gap_s}",
        "resumed": f"the source resumed after {gap_s} without bytes",
        "device_reset": f"the device restarted at sample {msg.get('seq')} ({detail})",
        "clock_jump": f"the device clock jumped {gap_s} at sample {msg.get('seq')}",
        "counter_jump": f"the device's sample counter leapt {msg.get('count')} ahead at sample {msg.get('seq')} "
                        "while its clock ran on (a counter fault: no sample lost)",
        "test_rejected": f"{test} rejected: {msg.get('message')}",
        "test_incomplete": f"{test} incomplete: {msg.get('message')}",
        "analysis_reset": f"the analysis restarted: {msg.get('message')}",
        "test_unrecognised": f"{test} not recognised: {msg.get('message')}",
        "plan_choice_refused": f"a choice of the next plan was refused: {msg.get('message')}",
    }
    return texts.get(name, f"event {name}: {detail or msg.get('message') or ''}".rstrip(": "))


_SPIKE = re.compile(r"reversal_spike_([xy])_(?:pos|neg)_(?:ccw|cw)")


def _per_axis_spikes(patterns: list[str]) -> list[str]:
    """``patterns`` (ranked) with the eight reversal spikes as one entry per axis (``reversal_spike_x``), X before
    Y, where the first of them ranked: which of an axis's four spikes ranks first is noise on an unchanged
    machine, and the log line would name another each test."""
    axes = sorted({m[1] for p in patterns if (m := _SPIKE.fullmatch(p))})
    out: list[str] = []
    for p in patterns:
        if _SPIKE.fullmatch(p) is None:
            out.append(p)
        elif axes:
            out += [f"reversal_spike_{a}" for a in axes]
            axes = []
    return out


def _finding(msg: CircleResult | TestResult, pattern: str) -> str:
    """A finding as the live view says it (:func:`ballbar.analysis.report.finding_words`: the plan's axes, the
    value by the one rounding rule): ``Backlash Z: backlash of Z 4.0 µm`` for a ZX test's first axis."""
    params = parameter_map(msg["parameters"])
    if pattern in ("reversal_spike_x", "reversal_spike_y"):  # the axis's largest spike, by size
        spikes = [p["value"] for k, p in params.items() if _SPIKE.fullmatch(k[: -len("_um")])
                  and k.startswith(pattern + "_") and p["value"] is not None and p["significant"]]
        return f"{pattern}_max_um {max(spikes, key=abs):.3g}" if spikes else pattern
    keys = [k for k in params if k.startswith(pattern + "_") and params[k]["value"] is not None]
    if not keys:
        return pattern
    axes = PLANE_AXES.get(str(msg["plan"].get("plane")), ("X", "Y"))
    return f"{pattern_label(pattern, axes)}: {finding_words(pattern, {'parameters': params}, axes)}"


# What a source's event makes of its state (events not named leave it as it is).
_SOURCE_STATES: dict[str, SourceState] = {
    "unplugged": "unplugged", "replugged": "connected", "opened": "connected", "stall": "stalled",
    "resumed": "connected", "end": "ended",
}


class Daemon:
    """Runs the pipeline until ``stop`` is set; see the module docstring."""

    def __init__(
        self,
        cfg: Config,
        source: Source,
        listeners: Sequence[tuple[Listener, int, DropPolicy]],
        notifier: Notifier | None = None,
        speedup: float = 1.0,
        controller: ControllerClient | None = None,
    ) -> None:
        self.cfg = cfg
        # The CNC's OPC UA client ([controller]): started after the configuration goes out, its messages
        # broadcast like the outputs' own, stopped with the source.
        self.controller = controller
        if controller is not None:
            controller.emit = self.broadcast
        # Device time per host time: a simulated device sped up (``--simulate --speedup``) reports its rates and
        # clock in device terms, so that a 5x speed-up does not read as a 5 kHz rate and a -800000 ppm drift.
        self.speedup = float(speedup)
        self.source = source
        self.notifier = notifier or Notifier()
        # Outputs that add to a test result before it fans out (the monitor's verdict), and may send messages
        # of their own through broadcast (its alerts).  They are handed each message last: an alert their
        # thread sends about a test then reaches every other queue after that test, never before it.
        self.annotators = [lst for lst, _c, _p in listeners if isinstance(lst, Annotator)]
        # Outputs that send messages of their own (the monitor's alerts, the sets) get the broadcast, and come last
        # for the same reason.
        senders = [lst for lst, _c, _p in listeners if isinstance(lst, Sender)]
        outputs = [*(o for o in listeners if o[0] not in senders), (LogListener(), 100, "drop_oldest"),
                   *(o for o in listeners if o[0] in senders)]
        for lst in senders:
            lst.bind(self.broadcast)
        self.outputs = [ListenerQueue(lst, cap, pol) for lst, cap, pol in outputs]
        # Each test's fit in a child process, off the daemon's reading and circles (``daemon.analysis_worker``)
        self.worker = AnalysisWorker() if cfg.daemon.analysis_worker else None
        self.analysis = AnalysisListener(cfg, self.broadcast, self.worker)
        self.analysis_queue = ListenerQueue(self.analysis, cfg.queues.analysis, "drop_newest")
        self.analysis.wake = functools.partial(self.analysis_queue.put_message, WAKE)
        # An explicit choice of the next plan that an output receives (the bus's control key) reaches the
        # analysis through its queue, in order with the batches.
        for out, _c, _p in listeners:
            if isinstance(out, PlanControl):
                out.bind_control(self.choose_plan)
        # Batches go only where they are wanted (the log and, without samples_hz, the bus take none).  The
        # analysis last: its thread wakes at once, and the reader is then about to sleep, not to contend for
        # the GIL with it (the merging queues before it only append).
        self.batch_queues = [q for q in [*self.outputs, self.analysis_queue] if q.wants_batches]
        self.started = time.monotonic()
        self.samples = 0
        self.lost = 0
        self.source_state: SourceState = "starting"
        self.source_reason: str | None = None  # why the source is waiting or unplugged
        self.last_event: SourceEvent | None = None
        self._rate_mark = (self.started, 0)
        self.rate_hz = 0.0
        self.results_seen = 0
        self.tests_seen = 0
        # events found at start (a test a crash cut), sent after the config
        self.startup_messages: list[TestIncomplete] = []
        # called after a batch with a device_reset: the sample numbers' offset from the device's counter changed
        self.on_device_reset: Callable[[], None] | None = None
        self._count_lock = threading.Lock()

    def choose_plan(self, name: str | None) -> None:
        """Analyse the next test as plan ``name`` (None: withdraw the choice); taken on the analysis thread,
        which says so in a ``plan_chosen`` (or ``plan_choice_refused``) event."""
        choice: PlanChoice = {"kind": "plan_choice", "plan": name}
        self.analysis_queue.put_message(choice)

    def broadcast(self, msg: Message) -> None:
        """Hand a message to every output (never blocks: each queue has its policy); the controller's to the
        analysis too (the program it runs: the plan of the next test)."""
        if msg["kind"] == "controller" and (msg["state"] != "data" or any(v["name"] == "program"
                                                                       for v in msg["values"])):
            self.analysis_queue.put_message(msg)  # (positions alone: the analysis has no use for them yet)
        if msg["kind"] == "test":
            for lst in self.annotators:
                msg = lst.annotate(msg)
        if msg["kind"] == "circle" or msg["kind"] == "test":
            with self._count_lock:
                self.results_seen += 1
                self.tests_seen += msg["kind"] == "test"
        for q in self.outputs:
            q.put_message(msg)

    def _source_events(self, batch: SampleBatch) -> None:
        for ev in batch.events:
            d = ev.to_dict()
            kind = d.pop("kind")
            if kind == "lost":
                self.lost += ev.count
            elif kind == "device_reset" and self.on_device_reset is not None:
                self.on_device_reset()
            if kind == "unplugged":
                self.source_reason = ev.detail
            elif kind in ("replugged", "opened", "resumed"):
                self.source_reason = None
            if kind == "unplugged" and self.source_state in ("starting", "waiting"):
                self.source_state = "waiting"  # never opened: a service waits for its adapter to appear
            else:
                self.source_state = _SOURCE_STATES.get(kind, self.source_state)
            msg = source_event(stamp(self.cfg.daemon.machine_id), ev.to_dict())
            self.last_event = msg
            self.broadcast(msg)

    def status(self) -> Status:
        now = time.monotonic()
        t_mark, n_mark = self._rate_mark
        if now - t_mark > 0:
            self.rate_hz = (self.samples - n_mark) / (now - t_mark)
        self._rate_mark = (now, self.samples)
        queues: dict[str, Queue] = {q.listener.name: q.stats.to_dict() for q in [self.analysis_queue, *self.outputs]}
        outputs: dict[str, Any] = {}
        for q in self.outputs:
            stats = getattr(q.listener, "stats", None)
            if callable(stats):
                with contextlib.suppress(Exception):
                    outputs[q.listener.name] = stats()
        src: dict[str, Any] = {}
        with contextlib.suppress(Exception):
            st = self.source.stats()
            src = st.to_dict() if hasattr(st, "to_dict") else dict(vars(st))
        if self.speedup != 1.0 and isinstance(src.get("clock_ratio"), float):
            src["clock_ratio"] *= self.speedup  # host s per device s, as if the device ran at its own speed
            src["drift_ppm"] = (src["clock_ratio"] - 1.0) * 1e6
        analysis: AnalysisStats = {
            "results": self.analysis.results,
            "tests": self.analysis.tests,
            "fit_latency_ms": self.analysis.fit_latency_ms,
            "invalid_samples": self.analysis.invalid,
            "errors": self.analysis.errors,
            "test_id": self.analysis.test_id,
        }
        if self.worker is not None:
            analysis["worker"] = {"pid": self.worker.pid, "started": self.worker.started,
                                  "busy": self.analysis.pending}
        out: Status = {
            **stamp(self.cfg.daemon.machine_id),
            "kind": "status",
            "uptime_s": now - self.started,
            "speedup": self.speedup,
            "source_state": self.source_state,
            "source_reason": self.source_reason,
            "source": cast("SourceStats", src),
            "samples": self.samples,
            "sample_rate_hz": self.rate_hz / self.speedup,  # per second of device time
            "lost_samples": self.lost,
            "queues": queues,
            # each output's own stats() under its name: the source's and the outputs' counters are theirs to
            # state (their shapes: SourceStats, McapStats, ZenohStats, RerunStats, MonitorStats)
            "outputs": cast("Outputs", outputs),
            "analysis": analysis,
        }
        if self.controller is not None:
            out["controller"] = self.controller.stats()
        return out

    def run(self, stop: threading.Event, max_tests: int | None = None, duration_s: float | None = None) -> int:
        """Read, fan out, report, until ``stop`` (or the limits) say so; then shut down cleanly."""
        if stop.is_set():  # stopped during start-up: nothing announced, nothing recorded, the outputs closed
            log.info("stopped during start-up, before it was ready")
            self.shutdown()
            return 0
        interval = self.cfg.daemon.status_interval_s
        if self.notifier.watchdog_s:
            interval = min(interval, self.notifier.watchdog_s / 2)
        # Redacted here, once: this one message is what the bus, last/config and every MCAP file get.
        config: ConfigMessage = {**stamp(self.cfg.daemon.machine_id), "kind": "config",
                                 "config": cast("Settings", redacted(self.cfg.to_dict()))}
        self.broadcast(config)
        for msg in self.startup_messages:  # stamped as they go out
            self.broadcast({**msg, **stamp(self.cfg.daemon.machine_id), "t_host": time.monotonic()})
        if self.controller is not None:
            self.controller.start()
        # READY=1 once the source is set up, whether or not its port is there yet: a service waits for its
        # adapter (the status says "waiting" and why, and a warning repeats every minute).
        self.notifier.ready(f"reading {self.source.url}")
        freeze_long_lived()  # start-up's objects: no full collection walks them again (the viewer's, once made)
        log.info("ready: reading %s", self.source.url)
        next_status = time.monotonic() + interval
        deadline = time.monotonic() + duration_s if duration_s else math.inf
        code = 0
        try:
            while not stop.is_set():
                batch = self.source.read(timeout=min(0.2, interval))
                if batch is not None:
                    if batch.events:
                        self._source_events(batch)
                    self.samples += len(batch)
                    for q in self.batch_queues:
                        q.put_batch(batch)
                    # read as often as the most pressed output wants batches: 20 ms as a result nears
                    self.source.pace(min((q.period() for q in self.batch_queues), default=0.0))
                    if self.source_state == "starting" and len(batch):
                        self.source_state = "connected"
                elif self.source.finished:
                    log.info("the source has ended; finishing the analysis")
                    self._finish_analysis(stop, max_tests)
                    break
                now = time.monotonic()
                if now >= next_status:
                    self.notifier.watchdog()
                    st = self.status()
                    self.broadcast(st)
                    why = f" ({self.source_reason})" if self.source_state in ("waiting", "unplugged") else ""
                    self.notifier.status(
                        f"{st['source_state']}{why}, {st['sample_rate_hz']:.0f} samples/s, {st['lost_samples']} lost, "
                        f"{st['analysis']['tests']} tests"
                    )
                    next_status = now + interval
                if max_tests is not None and self.tests_seen >= max_tests:
                    break
                if now >= deadline:
                    break
        finally:
            self.shutdown()
        return code

    def _finish_analysis(
        self, stop: threading.Event, max_tests: int | None, limit_s: float = FINISH_ANALYSIS_S
    ) -> None:
        """A finite source (a replay, a simulation) has ended: the analysis takes all it was given first.

        Faster than real time the source ends well before the analysis, whose
        queue the shutdown gives only a moment; a replay is meant to be analysed
        whole.  A stop signal, ``max_tests`` or ``limit_s`` end the wait; the
        watchdog is kept fed meanwhile.
        """
        deadline = time.monotonic() + limit_s
        while not stop.is_set() and time.monotonic() < deadline:
            if max_tests is not None and self.tests_seen >= max_tests:
                return
            if self.analysis_queue.wait_idle(min(1.0, deadline - time.monotonic()), stop):
                if not self.analysis.pending:
                    return
                self.analysis.settle(min(1.0, max(0.0, deadline - time.monotonic())))  # a test's fit in the worker
            self.notifier.watchdog()
        if not stop.is_set():
            log.warning("the analysis did not finish within %.0f s of the source's end", limit_s)

    def shutdown(self, budget_s: float = 4.0) -> None:
        """Stop within ``budget_s``: the source, the analysis, the outputs that send (alerts, sets), then the rest
        in parallel."""
        self.notifier.stopping()
        t0 = time.monotonic()
        for q in self.outputs:
            if isinstance(q.listener, StartsLate):
                q.listener.cancel_start()  # not started now only to be stopped
        with contextlib.suppress(Exception):
            self.source.close()
        if self.controller is not None:  # before the outputs close: its last messages reach them
            self.controller.stop(timeout=min(1.0, budget_s * 0.25))
        self.analysis_queue.close(timeout=budget_s * 0.4)
        if self.worker is not None:
            self.worker.shutdown(wait=False)
        # Outputs that send messages of their own first (the monitor's alerts, the sets): what they send as they
        # drain (the set a run's last test completes) must find the other outputs still open.
        senders = [q for q in self.outputs if isinstance(q.listener, Sender)]
        for group, share in ((senders, 0.3), ([q for q in self.outputs if q not in senders], 1.0)):
            left = max(0.5, (budget_s - (time.monotonic() - t0)) * share)
            threads = [threading.Thread(target=q.close, args=(left * 0.9,), daemon=True) for q in group]
            for th in threads:
                th.start()
            for th in threads:
                th.join(left)
        log.info("stopped in %.2f s", time.monotonic() - t0)
        self.notifier.close()
