"""The Rerun streamer: :class:`RerunViewer`, a :class:`~ballbar.daemon.listeners.Listener`.

It logs into its own :class:`rerun.RecordingStream` (application ``ballbar``, one recording per daemon
run), never the global one, and reaches viewers in ``serve`` mode (a supervised server in a child
process, :mod:`.server`), ``connect`` mode (pushing to a viewer that a prober finds), or not at all
(``off``).  What it draws is :mod:`.scene`; its layout :mod:`.blueprint`; its words :mod:`.findings`.

Bounded, and cheap.  A batch is only queued; the samples are processed together, and the length series
sent, at most every ``send_interval_s`` (0.25 s; ``polar_update_s`` while a test is drawn live, and where
a send would carry fewer than ``MIN_SEND_POINTS`` samples) on the samples' host clock, and at each result
or event.  The length series is decimated to ``length_hz`` (100 points per second of the host clock,
whatever the sample rate); a live circle gains a piece at a time (never the whole circle again); the
current test's samples are kept at ``buffer_hz``, at most ``max_buffer_samples``.  What a viewer that
connects late gets is chosen: the last ``history_tests`` tests whole (polar plots, models, verdict,
findings) at their own times, the trends of the last ``TRENDS_KEPT`` tests, the length at
``history_length_hz`` over ``history_length_s``, all kept here in fixed-size buffers and sent with the
scene to every new sink; in ``serve`` mode sent again whenever ``REFRESH_FRACTION`` of ``server_memory_limit`` has been
sent since (an estimate on the high side, ``MSG_BYTES``...), so that the server's buffer, which drops its
oldest messages first, always holds them whole.

Never blocking the daemon.  The listener's own queue already decouples it; beyond that, data is only
logged while a sink exists (no unbounded buffering for an absent viewer), the server's buffer is bounded,
and :meth:`RerunViewer.stop` returns within ``stop_timeout_s`` even when a viewer is frozen mid-stream.
Facts of rerun-sdk 0.41 that shape the ``connect`` mode (checked on this machine):

- a ``GrpcSink`` created while nothing listens never delivers: the bounded flush issued while it is
  still connecting breaks its stream once it connects ("gracefully disconnected"); and a sink whose
  viewer went away never reconnects.  So the viewer probes the address over TCP on a thread of its own
  and (re)creates the sink only when something listens, then re-sends the scene;
- a frozen (stopped, not dead) viewer makes ``disconnect()`` wait forever and the SDK's exit hook with
  it, so :meth:`RerunViewer.stop` disconnects on a helper thread and, if that does not finish in time,
  keeps the recording referenced and unregisters the SDK's exit hook (logged) so that the daemon can
  still exit.

In ``serve`` mode :meth:`RerunViewer.stop` ends the server process (SIGTERM, then SIGKILL after a
second); a daemon killed outright takes it along (``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import contextlib
import datetime
import logging
import math
import os
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from numpy.typing import NDArray

from ballbar.analysis.engine import TimingHints
from ballbar.analysis.plan import MachineConfig, TestPlan, for_plane, machine_of
from ballbar.analysis.plans import plan_of_result
from ballbar.protocol import INVALID

from ..listeners import MERGE_S, TEST_END_EVENTS, Listener, Message
from ..samples import EventKind, SampleBatch, SourceEvent
from .blueprint import TRENDS, Blueprints, default_blueprint
from .buffers import Ring, Samples, multiples, rate_hz
from .findings import clock_text, findings_markdown
from .geometry import DIRECTIONS, ArcTiming, num, param, plan_from, provisional_timing, result_timing
from .options import ViewerOptions, memory_bytes, proxy_address, viewer_options
from .scene import (
    MSG_BYTES,
    POINT_BYTES,
    ROW_BYTES,
    STRIP_BYTES,
    TREND_FIT_TESTS,
    TREND_WIDTH,
    Curve,
    Scene,
    TestRecord,
)
from .server import Prober, ServerProcess

if TYPE_CHECKING:
    import rerun as rr

    from ballbar.protocol.messages import CircleResult, PipelineEvent, TestResult
    from ballbar.protocol.messages.config import MachineSection
    from ballbar.protocol.messages.results import Machine, Plan
else:  # imported at first use: the configuration check and READY=1 do not wait for it (half a second)
    from ..lazy import LazyModule

    rr = LazyModule("rerun")

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
_INVALID = np.uint8(int(INVALID))  # status bits of a sample that is not a measurement

WARN_EVENTS = frozenset(
    {"test_rejected", "test_incomplete", "test_aborted", "unplugged", "lost", "stall", "device_reset", "clock_jump",
     "counter_jump", "decode_errors"}
)
START_DIVISION_UM = 5.0  # the live plot's division before any test has set one
PRE_TEST_S = 10.0  # samples kept while no test runs: the feed-in event comes after the step settled
TRENDS_KEPT = 5000  # tests whose trend points are re-sent to a viewer that (re)connects
HISTORY_SHARE_WARN = 0.25  # warn when the history needs more than this share of the server's limit
MAX_PENDING_SAMPLES = 200_000  # samples waiting to be processed: at most this many
MIN_SEND_POINTS = 8  # fewer new samples than this in a send_interval_s: sent every polar_update_s instead
WAITING = "waiting for a test"  # short: the label must fit the view of the test in progress at 1280 px
SEED_FILES = 200  # the newest record files read for the earlier tests (one test each when rotated per test)
OPEN_FILE_S = 10.0  # a record file modified this recently is being written


class WallClock:
    """The wall-clock time of a host monotonic time, by one offset between the two clocks.

    Read afresh at each call, ``time.time() - time.monotonic()`` moves by however long the thread was
    preempted between the two reads (milliseconds under load), and points logged a fixed interval apart
    would land unevenly on the viewer's time axis.  The offset is kept, and taken anew only when the wall
    clock has really been stepped (by more than ``STEP_S``: NTP slews far more slowly).
    """

    STEP_S = 0.05

    def __init__(self) -> None:
        self._offset = self._read()

    @staticmethod
    def _read() -> float:
        # the largest of a few paired reads: a preemption between the two reads only ever takes from one
        return max(time.time() - time.monotonic() for _ in range(3))

    def offset(self) -> float:
        now = self._read()
        if abs(now - self._offset) > self.STEP_S:
            self._offset = now
        return self._offset


def _epoch(t: Any) -> float | None:
    """A result's ``t_wall`` (ISO 8601) as Unix seconds."""
    try:
        d = datetime.datetime.fromisoformat(str(t))
    except ValueError:
        return None
    return (d if d.tzinfo else d.replace(tzinfo=datetime.UTC)).timestamp()

_ABANDONED: list[rr.RecordingStream] = []  # recordings whose disconnect did not finish: never collected


class RerunViewer(Scene, Listener):
    """Streams samples and results to Rerun viewers; see the module docstring.

    ``plan``/``machine``: the configured test plan, needed to draw the live
    circle before the first result arrives (a ``config`` or result message
    carrying a ``plan`` also sets it).  ``recording_id``: default a new UUID.
    """

    name = "rerun"
    batch_period_s = MERGE_S  # the listener queue hands batches over merged, four a second

    def __init__(
        self,
        options: ViewerOptions | None = None,
        *,
        plan: TestPlan | None = None,
        machine: MachineConfig | None = None,
        recording_id: str | None = None,
        plans: Mapping[str, Mapping[str, Any]] | None = None,
        sets: Mapping[str, Mapping[str, Any]] | None = None,
    ) -> None:
        self.options = options or ViewerOptions()
        self.plan = plan
        self.machine = machine
        # a library of several plans and their sets (the configuration's plans and sets tables)
        self._library: dict[str, TestPlan] = {}
        self._plans = {}
        self._plan_records = {}
        self._plan_trends = {}
        self._sets: dict[str, list[str]] = {}
        self._set_bar = ("none", "no set yet")
        self._set_md = ""
        self._set_library(plans or {}, sets or {})
        self.recording_id = recording_id or str(uuid.uuid4())
        self._recording_name = self.options.recording_name or f"ballbar {time.strftime('%Y-%m-%d %H:%M:%S')}"
        self._closed = False
        self._stop_lock = threading.Lock()
        self._rec: rr.RecordingStream | None = None
        self._sink_live = False
        self._clock = WallClock()
        self._sink_failures = 0  # the prober's failure count when the sink was made
        self._next_retry = 0.0
        self._next_health = 0.0
        self._stalled_since: float | None = None  # serve mode: when a flush to the server first timed out
        self._prober: Prober | None = None
        self._err_next_log = 0.0
        self._err_count = 0
        self.counters: dict[str, int] = {
            "batches": 0,
            "samples": 0,
            "messages": 0,
            "flushes": 0,
            "length_sends": 0,
            "polar_draws": 0,
            "sinks": 0,
            "refreshes": 0,
            "errors": 0,
            "skipped": 0,
            "server_stalls": 0,  # serve mode: restarts asked for because the server took none of the stream
        }
        self._sent_bytes = 0  # estimate of what the sink was sent (MSG_BYTES ...), for the refresh
        self._refreshed_at = 0  # _sent_bytes when the history was last sent
        self._refreshed_mono = time.monotonic()  # ... and when
        self._clients_ended = 0  # the server's count of connections that ended, then
        self._static_mono = time.monotonic()  # when the references were last sent
        self._history_steps: deque[Callable[[], None]] = deque()  # the rest of a sliced sending
        # the analysis clock (see ViewerOptions.clock) and the latest sample times seen on each
        self._use_host = self.options.clock == "host"
        self._latest_host = -math.inf
        self._latest_device = -math.inf
        # batches not processed yet (sent at most every send_interval_s)
        self._pending: list[SampleBatch] = []
        self._n_pending = 0
        self._next_flush = -math.inf  # on the samples' host clock, as _next_polar
        self._len_pending: list[tuple[FloatArray, FloatArray]] = []  # (wall, L) for the next length send
        # samples kept for the polar plot
        self._samples = Samples(self.options.max_buffer_samples + MAX_PENDING_SAMPLES)
        self._keep_every = 1  # extra thinning after the buffer hit max_buffer_samples
        self._rate_hz = float("nan")  # on the analysis clock
        self._host_hz = float("nan")
        # the current test
        self._test_index = 0
        self._in_test = False
        self._test_start_wall = time.time()
        self._live: dict[int, ArcTiming] = {}  # provisional timing per direction
        self._live_status = WAITING
        self._final: dict[int, Mapping[str, Any]] = {}  # direction -> latest result drawn for it
        self._next_polar = -math.inf
        # what a (re)connecting viewer is sent again; see "polar plot" below
        self._curves: dict[str, Curve] = {}
        self._piece = max(2, math.ceil(self.options.polar_points / self.options.polar_pieces))
        self._scale_um = self.options.scale_um or START_DIVISION_UM
        self._setup_result: Mapping[str, Any] | None = None
        self._hints = (1.0, 0.0, 3.0)  # feed ratio, overhead (s), spike width (deg) from the last test
        self._findings_md = ""
        self._last: TestRecord | None = None  # the last complete test, as its view draws it
        # the history a late viewer gets (see ViewerOptions): tests whole, trends, the length decimated
        self._history: deque[TestRecord] = deque(maxlen=self.options.history_tests)
        self._trends = Ring(TRENDS_KEPT, TREND_WIDTH)  # test, wall, values, uncertainties, limits, k (NaN: none)
        self._trend_ranges: dict[str, tuple[float, float]] = {}  # the y ranges in the blueprint sent last
        self._length_history = Ring(
            math.ceil(self.options.history_length_s * self.options.history_length_hz) + 1, 2
        )  # wall, L
        self._server: ServerProcess | None = None
        self._sink_generation = 0
        if self.options.mode == "off":
            self._closed = True
            return
        if self.options.mode == "serve":
            need, limit = self.history_bytes_max(), memory_bytes(self.options.server_memory_limit) or 0
            if need > HISTORY_SHARE_WARN * limit:
                log.warning(
                    "rerun viewer: the history for late viewers (%d tests, %g h of length) needs about %.0f MiB, "
                    "more than %d %% of server_memory_limit %s: late viewers may get less of it",
                    self.options.history_tests, self.options.history_length_s / 3600.0, need / 2**20,
                    round(100 * HISTORY_SHARE_WARN), self.options.server_memory_limit,
                )
        self._rec = rr.RecordingStream(self.options.application_id, recording_id=self.recording_id)
        self._blueprints = Blueprints(self._rec, self.options.application_id)
        if self.options.mode == "serve":
            self._server = ServerProcess(
                self.options.bind, self.options.port, self.options.server_memory_limit, self.options.server_rss_cap
            )
        if self.options.mode == "connect":
            addr = proxy_address(self.options.url)
            assert addr is not None  # validated by ViewerOptions
            self._prober = Prober(addr[0], addr[1], self.options.retry_s)
        self._maintain(time.monotonic())

    @classmethod
    def from_config(cls, cfg: Any) -> RerunViewer:
        """From the daemon's configuration (:func:`viewer_options`), with its ``plan`` and ``machine`` (and its
        ``plans`` and ``sets``, where it has a library of several); seeded with the machine's earlier tests from
        the daemon's records (:meth:`seed`, the newest ``SEED_FILES`` files)."""
        whole = cfg.to_dict() if callable(getattr(cfg, "to_dict", None)) else {}
        plan, machine = getattr(cfg, "plan", None), getattr(cfg, "machine", None)
        if plan is not None and machine is not None:  # the first plan's two axes of the machine's
            machine = for_plane(machine, plan.plane)
        v = cls(viewer_options(cfg), plan=plan, machine=machine,
                plans=whole.get("plans"), sets=whole.get("sets"))
        mcap = getattr(cfg, "mcap", None)
        if mcap is not None and mcap.enabled and v.options.mode != "off":
            directory = os.path.join(cfg.daemon.state_dir, "recordings")
            try:
                if os.path.isdir(directory):
                    from ..mcap import list_recordings, read_results

                    machine_id = cfg.daemon.machine_id
                    # the file this daemon is writing (modified in the last seconds) holds nothing earlier, and its
                    # open chunk would read as a killed writer's
                    files = [p for p in list_recordings(directory)[-SEED_FILES:]
                             if p.stat().st_mtime < time.time() - OPEN_FILE_S]
                    v.seed(r for r in read_results(files) if r.get("machine_id") in (None, machine_id))
            except Exception:  # the history is a convenience: the live view runs without it
                log.exception("rerun viewer: could not read the earlier tests from %s", directory)
        return v

    def _set_library(self, plans: Mapping[str, Mapping[str, Any]], sets: Mapping[str, Mapping[str, Any]]) -> None:
        """The configuration's plans (several: the per-plan layout) and sets."""
        from ballbar.analysis.plan import PLANE_AXES

        if len(plans) < 2 and not sets:
            return
        for name, body in plans.items():
            try:
                self._library[name] = plan_from(body)
            except (TypeError, ValueError) as err:
                log.warning("rerun viewer: plan %s: %s", name, err)
                continue
            self._plans.setdefault(name, PLANE_AXES[self._library[name].plane])
        self._sets = {n: [str(p) for p in (b.get("plans") or [])] for n, b in sets.items() if isinstance(b, Mapping)}
        if self._sets and self._set_bar[1] == "no set yet":
            name, members = next(iter(self._sets.items()))
            self._set_bar = ("none", f"set {name}: waiting for its tests ({', '.join(members)})")

    def _add_plan(self, name: str, res: Mapping[str, Any]) -> None:
        """A test of a plan the layout does not show yet: its tab, from now on."""
        from ballbar.analysis.plan import PLANE_AXES

        plan = res.get("plan") or {}
        axes = plan.get("axes")
        self._plans[name] = (str(axes[0]), str(axes[1])) if isinstance(axes, list | tuple) and len(axes) == 2 \
            else PLANE_AXES.get(str(plan.get("plane")), ("X", "Y"))
        if self._sink_live:
            self._log_static()
            self._blueprints.send(default_blueprint(self._trend_ranges, self._plans))

    def seed(self, results: Iterable[Mapping[str, Any]]) -> int:
        """Earlier tests (the daemon's records, oldest first) under the configured plan's conditions: their trend
        points at their own wall-clock time and at test numbers up to 0 (this run's tests count from 1), and the
        newest as the last complete test (its verdict, findings and fitted model: its samples are not read).
        With a library of plans, every plan's tests, each plan's trends apart, and the newest set.
        Returns how many were taken.

        A sink made before the seeding (a viewer that answered the constructor's first probe, or a server up at
        once) was sent the scene without them: it is sent the scene again."""
        n = self._seed_plans(list(results)) if self._plans else self._seed_one(list(results))
        if n and self._sink_live:
            self._send_scene()
        return n

    def _seed_one(self, results: list[Mapping[str, Any]]) -> int:
        """:meth:`seed` with one plan: its tests' trend and the newest as the last complete test."""
        from ballbar.analysis.monitor import CONDITION_KEYS

        want = {k: getattr(self.plan, k, None) for k in CONDITION_KEYS} if self.plan is not None else None
        tests = [r for r in results if r.get("kind") == "test" and _epoch(r.get("t_wall")) is not None
                 and (want is None or {k: (r.get("plan") or {}).get(k) for k in CONDITION_KEYS} == want)]
        tests = tests[-TRENDS_KEPT:]
        recent: deque[FloatArray] = deque(maxlen=TREND_FIT_TESTS)
        for i, r in enumerate(tests):
            before = np.concatenate(list(recent)) if recent else np.empty((0, TREND_WIDTH))
            row = self._trend_row(r, i - len(tests) + 1, float(_epoch(r.get("t_wall")) or 0.0), before)
            if row is not None:
                self._trends.extend(row)
                recent.append(row)
        if tests:
            self._seed_complete(tests[-1])
        log.info("rerun viewer: %d earlier tests from the records", len(tests))
        return len(tests)

    def _seed_plans(self, results: list[Mapping[str, Any]]) -> int:
        """:meth:`seed` with a library of plans: each plan's trend and latest test; the newest test the last
        complete one; the newest set the machine's verdict."""
        tests = [r for r in results if r.get("kind") == "test" and _epoch(r.get("t_wall")) is not None
                 and isinstance((r.get("plan") or {}).get("name"), str)]
        by_plan: dict[str, list[Mapping[str, Any]]] = {}
        for r in tests:
            by_plan.setdefault(str(r["plan"]["name"]), []).append(r)
        for name, rs in by_plan.items():
            if name not in self._plans:
                self._add_plan(name, rs[-1])
            ring = self._plan_trends.setdefault(name, Ring(TRENDS_KEPT, TREND_WIDTH))
            rs = rs[-TRENDS_KEPT:]
            for i, r in enumerate(rs):
                row = self._trend_row(r, i - len(rs) + 1, float(_epoch(r.get("t_wall")) or 0.0),
                                      ring.rows()[-TREND_FIT_TESTS:])
                if row is not None:
                    ring.extend(row)
        newest = tests[-1] if tests else None
        for name, rs in by_plan.items():  # each plan's latest (the newest overall last: it is the last complete)
            last = rs[-1]
            if last is newest:
                continue
            self._seed_complete(last, self._plan_trends[name].rows())
        if newest is not None:
            self._seed_complete(newest, self._plan_trends[str(newest["plan"]["name"])].rows())
        sets = [r for r in results if r.get("kind") == "set"]
        if sets:
            self._on_set(sets[-1])
        log.info("rerun viewer: %d earlier tests of %d plans from the records", len(tests), len(by_plan))
        return len(tests)

    def _seed_complete(self, last: Mapping[str, Any], rows: FloatArray | None = None) -> None:
        """The latest of the records' tests drawn as the last complete one (``rows``: its plan's trend; None:
        the one trend)."""
        wall = float(_epoch(last.get("t_wall")) or 0.0)
        self._findings_md = findings_markdown(last, wall) + self._forecast_markdown(rows)
        self._final = {}
        self._curves.clear()
        for d in DIRECTIONS:
            if result_timing(last, d) is not None and "plan" in last:
                self._update_model(d, last)
        if self.options.remove_setup and param(last, "centre_x_um") is not None:
            self._setup_result = last
        self._complete(last, wall, index=0)
        self._curves.clear()

    # ------------------------------------------------------------------ state

    @property
    def connected(self) -> bool:
        """A sink exists: serving, or pushing to a viewer that answered the last probe."""
        return self._sink_live

    def history_bytes_max(self) -> int:
        """Bytes (estimated, on the high side) of the history a late viewer is sent, when full."""
        o = self.options
        per_test = 12 * MSG_BYTES + 6 * STRIP_BYTES + POINT_BYTES * (4 * o.polar_points + 2 * 361) + 8000
        length = len(TRENDS) * MSG_BYTES + ROW_BYTES * (
            TRENDS_KEPT * 6 * len(TRENDS) + self._length_history.capacity
        )
        return o.history_tests * per_test + length

    def stats(self) -> dict[str, Any]:
        return {
            "mode": self.options.mode,
            "address": self.address,
            "connected": self._sink_live,
            "clock": "host" if self._use_host else "device",
            "buffered_samples": self._samples.n,
            "pending_samples": self._n_pending,
            "history_tests": len(self._history),
            "history_length_points": len(self._length_history),
            "trend_points": len(self._trends) + sum(len(r) for r in self._plan_trends.values()),
            "sent_mib": round(self._sent_bytes / 2**20, 3),
            "history_pending": len(self._history_steps),
            **self.counters,
            **({"server": self._server.stats()} if self._server is not None else {}),
        }

    # ------------------------------------------------------------------ listener interface

    def on_batch(self, batch: SampleBatch) -> None:
        if self._closed:
            return
        try:
            self._on_batch(batch)
        except Exception:
            self._failed("on_batch")

    def on_message(self, msg: Message) -> None:
        if self._closed:
            return
        try:
            self._on_message(msg)
        except Exception:
            self._failed("on_message")

    def on_idle(self) -> None:
        if self._closed:
            return
        try:
            self._flush(time.monotonic())
        except Exception:
            self._failed("on_idle")

    def _failed(self, where: str) -> None:
        # Logged at most once a minute: a bug that fails every batch must not flood the journal.
        if self._closed:
            return  # stop() took the stream away mid-call
        self.counters["errors"] += 1
        self._err_count += 1
        now = time.monotonic()
        if now >= self._err_next_log:
            log.exception("rerun viewer: %s failed (%d failures since the last report)", where, self._err_count)
            self._err_count = 0
            self._err_next_log = now + 60.0

    # ------------------------------------------------------------------ samples
    #
    # A batch is only queued here (a few scalar updates); the samples are processed together, and the
    # length series sent, at most every send_interval_s (polar_update_s while a test is drawn live),
    # before any message that concerns them (results, events) and when the queue is idle.  Both
    # periods are on the samples' host clock (when they were taken), which a live source shares with
    # the wall clock; a backlog or a recorded stream is drawn as it was acquired.

    def _on_batch(self, batch: SampleBatch) -> None:
        self.counters["batches"] += 1
        if batch.events:
            self._process_pending()  # the samples before these events first
            for ev in batch.events:
                self._source_event(ev)
        if not self._sink_live:
            self.counters["skipped"] += 1
        n = len(batch)
        if n:
            self.counters["samples"] += n
            th, td = float(batch.t_host[-1]), float(batch.t_device[-1])
            if math.isfinite(th):
                self._latest_host = max(self._latest_host, th)
            if math.isfinite(td):
                self._latest_device = max(self._latest_device, td)
            elif self.options.clock == "auto":
                self._use_host = True
            self._pending.append(batch)
            self._n_pending += n
        t = self._latest_host
        live = self._in_test and self._sink_live and t >= self._next_polar
        if t >= self._next_flush or live or self._n_pending >= MAX_PENDING_SAMPLES:
            self._flush(time.monotonic())

    def _flush(self, now: float) -> None:
        """Process the queued samples; send the length series and the live polar curve when due."""
        self._next_flush = self._latest_host + self._send_period()
        self._maintain(now)
        self._process_pending()
        if not self._sink_live:
            self._len_pending.clear()
            return
        self.counters["flushes"] += 1
        self._send_pending_length()
        if self._in_test and self._latest_host >= self._next_polar:
            self._next_polar = self._latest_host + self.options.polar_update_s
            self._redraw_live()
        self._refresh_if_due()

    def _send_period(self) -> float:
        """``send_interval_s``, or ``polar_update_s`` (if longer) where the samples come too slowly to bring
        ``MIN_SEND_POINTS`` in ``send_interval_s``: a send's cost is mostly its own, not its points'."""
        period = self.options.send_interval_s
        if self._host_hz * period < MIN_SEND_POINTS:  # False while the rate is not known (NaN)
            return max(period, self.options.polar_update_s)
        return period

    def _send_pending_length(self, rec: rr.RecordingStream | None = None) -> None:
        if self._len_pending:
            wall = np.concatenate([w for w, _L in self._len_pending])
            L = np.concatenate([x for _w, x in self._len_pending])
            self._len_pending.clear()
            self._send_length(wall, L, rec)
            self.counters["length_sends"] += 1

    def _process_pending(self) -> None:
        """The queued samples: kept for the polar plot, picked for the length series and its history.

        Only the picked samples are looked at (positions from the sample numbers, checked for
        validity afterwards): no temporary as large as the batch, whatever the rate.
        """
        if not self._pending:
            return
        batches, self._pending, self._n_pending = self._pending, [], 0
        if len(batches) == 1:
            b = batches[0]
            th, td, L, seq, status = b.t_host, b.t_device, b.length_mm, b.seq, b.status
        else:
            th = np.concatenate([b.t_host for b in batches])
            td = np.concatenate([b.t_device for b in batches])
            L = np.concatenate([b.length_mm for b in batches])
            seq = np.concatenate([b.seq for b in batches])
            status = np.concatenate([b.status for b in batches])

        def picked(every: int) -> NDArray[np.intp]:
            i = multiples(seq, every)
            return i[((status[i] & _INVALID) == 0) & np.isfinite(th[i]) & np.isfinite(L[i])]

        if th.size >= 2:
            # sample rates on the host clock (the length series) and on the analysis clock (the
            # polar plot); they differ for a simulator or a replay running faster than real time
            head = slice(0, 4096)
            self._host_hz = rate_hz(th[head], self._host_hz)
            self._rate_hz = rate_hz((th if self._use_host else td)[head], self._rate_hz)
        keep = picked(self._stride(self.options.buffer_hz) * self._keep_every)
        self._keep(th[keep], td[keep], L[keep])
        stride = self._stride(self.options.length_hz, self._host_hz)
        i = picked(stride)
        if i.size:
            wall = th[i] + self._clock.offset()
            if self._sink_live:
                self._len_pending.append((wall, L[i]))
            # the history: a subset of the live points (same times, same values)
            every = stride * max(1, math.ceil(self.options.length_hz / self.options.history_length_hz - 1e-9))
            h = seq[i] % every == 0
            if h.any():
                self._length_history.extend(np.column_stack([wall[h], L[i][h]]))

    def _stride(self, limit_hz: float, rate_hz: float | None = None) -> int:
        rate = self._rate_hz if rate_hz is None else rate_hz
        if not math.isfinite(rate):
            return 1
        return max(1, int(rate / limit_hz * (1.0 + 1e-6)))  # 9999.9998 Hz from float times is 10 kHz

    def _keep(self, th: FloatArray, td: FloatArray, L: FloatArray) -> None:
        """Keep samples (picked by sample number) that the polar plot may need, within max_buffer_samples."""
        buf = self._samples
        if th.size:
            buf.append(th, td, L)
        if not self._in_test:
            # only the last PRE_TEST_S seconds; dropped in halves, so that this stays cheap
            old = int(np.searchsorted(buf.t_host, self._latest_host - PRE_TEST_S))
            if old > buf.n // 2:
                buf.keep(slice(old, None))
            if buf.n > self.options.max_buffer_samples:
                buf.keep(slice(buf.n - self.options.max_buffer_samples // 2, None))
        elif buf.n > self.options.max_buffer_samples:
            buf.keep(slice(None, None, 2))
            self._keep_every *= 2
            log.info(
                "rerun viewer: test longer than %d samples kept; now keeping every %d-th",
                self.options.max_buffer_samples,
                self._stride(self.options.buffer_hz) * self._keep_every,
            )

    def _analysis_time(self) -> tuple[FloatArray, FloatArray]:
        buf = self._samples
        return (buf.t_host if self._use_host else buf.t_device), buf.length

    def _send_length(self, wall: FloatArray, L: FloatArray, rec: rr.RecordingStream | None = None) -> None:
        rec = rec or self._rec
        assert rec is not None
        rec.send_columns(
            "length",
            indexes=[rr.TimeColumn("time", timestamp=wall)],
            columns=rr.Scalars.columns(scalars=L),
        )
        self._sent_bytes += MSG_BYTES + ROW_BYTES * wall.size

    def _source_event(self, ev: SourceEvent) -> None:
        detail = ", ".join(
            f"{k} {v}" for k, v in (("count", ev.count), ("gap_s", round(ev.gap_s, 3)), ("detail", ev.detail)) if v
        )
        if ev.counts:
            detail += (", " if detail else "") + ", ".join(f"{k} {v}" for k, v in ev.counts.items())
        level = "WARN" if str(ev.kind) in WARN_EVENTS else "INFO"
        if ev.kind == EventKind.DEVICE_RESET:
            self._end_test()
        self._text_event(
            f"source {ev.source or ''} {ev.kind}: {detail}".replace("  ", " "),
            level,
            ev.t_host + self._clock.offset(),
        )

    def _text_event(self, text: str, level: str, wall: float | None = None) -> None:
        if not self._sink_live:
            return
        rec = self._rec
        assert rec is not None
        rec.set_time("time", timestamp=wall if wall is not None else time.time())
        self._log("events", rr.TextLog(text, level=level), len(text))

    # ------------------------------------------------------------------ messages

    def _on_message(self, msg: Message) -> None:
        """A message of the daemon (live, typed: ``ballbar.protocol.messages``); records read back from files, of
        any version, go through :meth:`seed` instead."""
        self.counters["messages"] += 1
        if msg["kind"] == "alert":  # the monitor's alerts: one line in the events
            self._text_event(f"alert: {msg['message'] or msg['state']}", "INFO" if msg["cleared"] else "WARN")
            return
        if msg["kind"] == "set":  # a set's result: the machine's verdict, and a line in the events
            self._on_set(msg)
            verdict = msg["verdict"]
            self._text_event(f"set {msg['set_id']}: {verdict['summary']}",
                             "INFO" if verdict["status"] == "pass" else "WARN")
            return
        if msg["kind"] == "config":
            self._flush(time.monotonic())  # a boundary: the samples before it are drawn and sent first
            cfg = msg["config"]
            plans = cfg.get("plans")
            if plans is not None and not self._plans:
                self._set_library(plans, cfg.get("sets") or {})
                if self._plans and self._sink_live:
                    self._send_scene()
            self._set_plan(cfg["plan"], cfg["machine"])
        elif msg["kind"] == "circle" or msg["kind"] == "test":
            self._flush(time.monotonic())
            self._set_plan(msg["plan"], msg["machine"])
            self._check_clock(msg)
            self._result(msg)
        elif msg["kind"] == "event":
            self._flush(time.monotonic())
            if msg.get("origin") != "source":  # source events come with their batch
                event = cast("PipelineEvent", msg)  # the analysis' or one found at start
                self._check_clock(event)
                self._event(event)
        # status, samples: nothing to draw

    def _set_plan(self, plan: Plan, machine: Machine | MachineSection) -> None:
        try:
            new = plan_of_result(plan)
            mach = for_plane(machine_of(machine), new.plane)  # a config's: the machine's axes; a result's: its own
        except (TypeError, ValueError) as err:
            log.warning("rerun viewer: ignoring a plan it cannot read: %s", err)
            return
        changed = new != self.plan
        self.plan, self.machine = new, mach
        if changed and self._sink_live:
            self._log_static()
            self._set_times()
            self._log_scale("live")

    def _check_clock(self, msg: CircleResult | TestResult | PipelineEvent) -> None:
        """Follow the clock the analysis runs on: the message's ``time_axis``, else its times.

        Without ``time_axis``, an engine time (``last_sample_t``, an event's
        ``t_s``) must lie near the newest sample's time on that clock.
        """
        if self.options.clock != "auto":
            return
        axis = msg.get("time_axis")
        use_host = self._use_host
        if axis is not None:
            use_host = axis == "host"
        elif (t := num(msg.get("last_sample_t")) or num(msg.get("t_s"))) is not None:

            def near(latest: float) -> bool:
                return latest - 600.0 <= t <= latest + 60.0

            if use_host and not near(self._latest_host) and near(self._latest_device):
                use_host = False
            elif not use_host and not near(self._latest_device) and near(self._latest_host):
                use_host = True
        if use_host == self._use_host:
            return
        self._use_host = use_host
        log.info("rerun viewer: the analysis runs on the %s clock", "host" if self._use_host else "device")
        self._redraw_all()

    def _event(self, msg: PipelineEvent) -> None:
        ev = msg["event"]
        idx = msg.get("test_index")
        t_s = num(msg.get("t_s"))
        wall = self._wall_of(t_s) if t_s is not None else None
        text = f"test {idx}: {ev}"
        if wall is not None:
            text += f" at {clock_text(wall)}"
        elif t_s is not None:  # its samples are gone: the analysis clock's time, and which clock
            text += f" at t={t_s:.3f} s on the {'host' if self._use_host else 'device'} clock"
        if msg.get("message"):
            text += f": {msg.get('message')}"
        if msg["event"] == "feed_in":
            plan = msg.get("plan")
            if isinstance(plan, str) and plan in self._library:
                self.plan = self._library[plan]  # recognised at the feed-in: its timing draws the live circles
                text += f" (plan {plan})"
            if t_s is not None:
                self._start_test(msg["test_index"], t_s)
        elif ev in TEST_END_EVENTS:
            self._end_test()
        self._text_event(text, "WARN" if ev in WARN_EVENTS else "INFO", wall)

    def _wall_of(self, t_s: float) -> float | None:
        """The wall-clock time of ``t_s`` on the analysis clock (the device's seconds since it started, or the
        host's monotonic clock): the host time of the nearest buffered sample, as wall time.  None when no
        sample lies within a second of it (the buffer has let it go)."""
        buf = self._samples
        t = buf.t_host if self._use_host else buf.t_device
        if not t.size:
            return None
        i = int(np.clip(np.searchsorted(t, t_s), 1, t.size - 1)) if t.size > 1 else 0
        if t.size > 1 and abs(t[i - 1] - t_s) < abs(t[i] - t_s):
            i -= 1
        if not abs(float(t[i]) - t_s) <= 1.0:
            return None
        return float(buf.t_host[i]) + self._clock.offset()

    def _start_test(self, index: int, feed_in_s: float) -> None:
        self._test_index = index
        self._in_test = True
        self._test_start_wall = time.time()
        self._final = {}
        self._live = {}
        if self.plan is not None:
            ratio, overhead, width = self._hints
            self._live = {
                d: provisional_timing(self.plan, d, feed_in_s, ratio, overhead, width) for d in self.plan.direction_list
            }
        # keep the samples from shortly before the feed-in: the data arc may start right after it
        t, _L = self._analysis_time()
        if t.size:
            self._samples.keep(t >= feed_in_s - 1.0)
        self._curves.clear()
        self._live_status = f"test {index} in progress"
        if self._sink_live:
            self._set_times()
            for name in DIRECTIONS.values():
                self._log(f"live/{name}", rr.Clear(recursive=True))
            if self._plans and self.plan is not None:  # the plan recognised at the feed-in: its plane's axes
                self._log_axis_labels("live", self.plan.axes)
            self._log_status()

    def _end_test(self) -> None:
        self._in_test = False
        self._live = {}
        self._keep_every = 1
        if self._live_status != WAITING:
            self._live_status = f"test {self._test_index} ended; waiting"
            if self._sink_live:
                self._set_times()
                self._log_status()

    def _result(self, res: CircleResult | TestResult) -> None:
        idx = res["test_index"]
        self._test_index = idx
        test = res["kind"] == "test"
        if res["kind"] == "test":
            # the analyzer's own rule: an implausible feed teaches the next test's provisional timing nothing
            hints = TimingHints.learnt(res["timing"], TimingHints(*self._hints))
            if hints is not None:
                self._hints = (hints.feed_ratio, hints.overhead_s, hints.spike_width_deg)
            for d in DIRECTIONS:
                if result_timing(res, d) is not None:
                    self._final[d] = res
        else:
            self._final[1 if res["direction"] == "ccw" else -1] = res
        if self.options.remove_setup and param(res, "centre_x_um") is not None:
            self._setup_result = res
        wall = time.time()
        name = res["plan"].get("name") if self._plans else None
        if isinstance(name, str) and test and name not in self._plans:
            self._add_plan(name, res)
        ring = self._plan_trends.setdefault(name, Ring(TRENDS_KEPT, TREND_WIDTH)) if isinstance(name, str) \
            else self._trends
        prefix = f"plans/{name}/trends" if isinstance(name, str) else "trends"
        first = not len(ring)
        row = self._trend_row(res, idx, wall, ring.rows()[-TREND_FIT_TESTS:]) if test else None
        if row is not None:
            ring.extend(row)
        if res["kind"] == "test":
            self._findings_md = findings_markdown(res, wall) + self._forecast_markdown(ring.rows())
            verdict = res.get("verdict")
            self._live_status = f"test {idx} complete" + (f": {verdict['status'].upper()}" if verdict else "")
        else:
            self._live_status = f"test {idx}: {res['direction'].upper()} circle fitted"
        if self._sink_live:
            self._set_times(wall)
            self._log_status()
            if row is not None:
                self._send_trends(row, first, prefix)
                self._rescale_trends()
        # cached even without a viewer: one that connects later gets this test.  A complete test goes to the last
        # complete test's view alone: the view of the test in progress is cleared for the next
        self._redraw_all(wall, emit=not test)
        if test:
            self._complete(res, wall)
            self._curves.clear()
            if self._sink_live:
                for name in DIRECTIONS.values():
                    self._log(f"live/{name}", rr.Clear(recursive=True))
            self._end_test()

    def _forecast_markdown(self, rows: FloatArray | None = None) -> str:
        """When each limited trend crosses its limit, in words (the monitor's forecast over the kept tests of the
        test's plan)."""
        from ballbar.analysis.monitor import forecast_sentence

        rows = self._trends.rows() if rows is None else rows
        lines = []
        n = len(TRENDS)
        limited = [j for j in range(n) if rows.shape[0] and np.isfinite(rows[-1, 2 + 2 * n + 2 * j])]
        k = float(rows[-1, -1]) if rows.shape[0] and np.isfinite(rows[-1, -1]) else 2.0
        for j, (_p, field, _l, _c) in enumerate(TRENDS):
            if j not in limited:
                continue
            lim = rows[-1, 2 + 2 * n + 2 * j]
            ok = np.flatnonzero(np.isfinite(rows[:, 2 + j]))[-TREND_FIT_TESTS:]
            text = forecast_sentence(field, rows[ok, 1], rows[ok, 2 + j], float(lim), stderrs=rows[ok, 2 + n + j],
                                     watched=len(limited), coverage_k=k)
            if text:
                lines.append(f"- {text}")
        return ("\n### Trend and forecast (the kept tests)\n\n" + "\n".join(lines) + "\n") if lines else ""

    # ------------------------------------------------------------------ stop

    def stop(self) -> None:
        """Close the sink within ``stop_timeout_s``, whatever the viewer does; safe to call twice."""
        with self._stop_lock:
            was_open = not self._closed
            self._closed = True
            rec, self._rec = self._rec, None
            prober, self._prober = self._prober, None
            server, self._server = self._server, None
        if prober is not None:
            prober.close()
        if rec is None:
            if server is not None:
                server.close()
            return
        t0 = time.monotonic()
        done = threading.Event()

        def close() -> None:
            if was_open and self._sink_live:
                with contextlib.suppress(Exception):  # the samples still queued (a frozen viewer may hold this)
                    self._process_pending()
                    self._send_pending_length(rec)
            with contextlib.suppress(Exception):  # a lost viewer fails the flush; nothing to do about it
                rec.flush(timeout_sec=max(0.1, self.options.stop_timeout_s / 2))
            rec.disconnect()
            done.set()

        th = threading.Thread(target=close, name="rerun-viewer-stop", daemon=True)
        th.start()
        th.join(self.options.stop_timeout_s)
        self._sink_live = False
        if server is not None:  # after the stream: what was flushed to it reaches connected viewers
            server.close()
        if not done.is_set():
            # A frozen viewer holds the SDK's connection: dropping the recording or the SDK's own
            # exit hook would wait for it forever.  Keep it referenced and let the process exit.
            _ABANDONED.append(rec)
            rr.unregister_shutdown()
            log.warning(
                "rerun viewer: the viewer did not let go within %.1f s; abandoning the stream",
                self.options.stop_timeout_s,
            )
        log.info(
            "rerun viewer stopped in %.3f s (%s)",
            time.monotonic() - t0,
            ", ".join(f"{k} {v}" for k, v in self.counters.items()),
        )

__all__ = ["RerunViewer"]
