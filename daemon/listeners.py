"""The listener interface and the bounded queue that decouples each listener.

A source's reader thread never calls a listener directly: it puts each
:class:`~ballbar.daemon.samples.SampleBatch` and each message into every
listener's :class:`ListenerQueue`, which a thread of its own drains.  A slow
consumer (a stalled viewer, a slow disk, a frozen bus peer) therefore fills its
own queue and nothing else.  Each queue has a bound and a stated drop policy,
and counts what it dropped:

- ``drop_oldest``: when full, the oldest item goes (live views: the newest
  data matters most).
- ``drop_newest``: when full, the new item is refused (keeps a contiguous
  prefix; for consumers that must not see holes in what they did get).

A listener says what it wants, and its thread wakes only for that:
``batch_period_s`` is ``None`` (no batches: the queue never takes one; source
events still come as ``event`` messages), ``0`` (every batch as it is read: the
analysis, whose latency budget the batches set) or a period in seconds (the
batches are held and handed over merged, one :class:`SampleBatch` of all their
samples and events in order, about once per period, or at once before a
message so that the order holds: the MCAP log, the viewer).  A listener whose
need changes as it goes says so with ``batch_period_now()``, asked at each
batch (the analysis: merged while no result can be due, each batch as one
nears).  ``idle_s`` is how
long without deliveries before :meth:`Listener.on_idle` (``None``: never).  A
merged batch still counts as the items it was made of, delivered or dropped.

Messages are JSON-ready dicts with a ``kind``:

``circle`` / ``test``   an analysis result (the ``ballbar analyze --json`` object
                        plus ``machine_id``, ``test_id``, ``t_host``, ``last_sample_t``,
                        ``last_sample_t_host``, ``latency_ms``)
``event``               ``event``: feed_in, feed_out, circle_done, test_rejected,
                        test_incomplete, analysis_reset, or a source event (unplugged,
                        replugged, lost, decode_errors, stall, resumed, device_reset,
                        clock_jump, end)
``status``              rates, losses, queue depths, source state, fit latency
``config``              the daemon's effective configuration, once at start
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol, TypeAlias, TypedDict, runtime_checkable

from ballbar.protocol.messages import to_json as to_json  # the outputs' one encoding, where they import it from

from .samples import SampleBatch

if TYPE_CHECKING:
    from ballbar.protocol import messages
    from ballbar.protocol.messages.status import Queue

log = logging.getLogger(__name__)


class Wake(TypedDict):
    """A message the daemon posts to one of its own queues to wake its listener; never published."""

    kind: Literal["analysis_done"]


class PlanChoice(TypedDict):
    """A choice of the next test's plan (the bus' control/next_plan), posted to the analysis' queue; never
    published (the analysis answers with a plan_chosen or plan_choice_refused event)."""

    kind: Literal["plan_choice"]
    plan: object  # as it came: the analysis checks that it names a plan of the library (None: withdrawn)


#: What a listener is handed besides samples: one of the daemon's messages (ballbar.protocol.messages), or one
#: of the daemon's own (:class:`Wake`, :class:`PlanChoice`).
Message: TypeAlias = "messages.Message | Wake | PlanChoice"
# How often the outputs that take batches merged get them (the MCAP log, the viewer, the analysis while no
# result can be due): four times a second, not once per 20 ms batch.
MERGE_S = 0.25
# Events that end a test without a result (test_aborted: an older name, still read back from recordings).
TEST_END_EVENTS = frozenset({"test_rejected", "test_incomplete", "test_aborted", "test_unrecognised"})
DropPolicy = Literal["drop_oldest", "drop_newest"]


class Listener(abc.ABC):
    """Receives samples and messages on its own thread; ``stop()`` flushes and closes.

    ``batch_period_s``: ``None`` for no batches, ``0`` for every batch, a period
    to receive them merged about that often (a method ``batch_period_now()``,
    where there is one, gives the period of the moment); ``idle_s``: how long
    without deliveries before ``on_idle`` (``None``: never).  See the module
    docstring.
    """

    name: str = "listener"
    batch_period_s: float | None = 0.0
    idle_s: float | None = 1.0

    def on_batch(self, batch: SampleBatch) -> None:  # noqa: B027 - optional
        """Samples and the source events that came before them."""

    def on_message(self, msg: Message) -> None:  # noqa: B027 - optional
        """An analysis result, an event, the status or the configuration."""

    def on_idle(self) -> None:  # noqa: B027 - optional
        """Called after ``idle_s`` without deliveries, and again every ``idle_s`` (timers: flushes, reconnects)."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Flush and release everything; safe to call twice."""


@dataclass
class QueueStats:
    depth: int = 0
    capacity: int = 0
    delivered: int = 0
    dropped: int = 0
    errors: int = 0
    policy: DropPolicy = "drop_oldest"

    def to_dict(self) -> Queue:
        return {"depth": self.depth, "capacity": self.capacity, "delivered": self.delivered,
                "dropped": self.dropped, "errors": self.errors, "policy": self.policy}


@runtime_checkable
class Annotator(Protocol):
    """An output that adds to each test result before it fans out (the monitor's verdict)."""

    def annotate(self, msg: Message) -> Message: ...


@runtime_checkable
class Sender(Protocol):
    """An output that sends messages of its own (the monitor's alerts, a test set's result) through ``emit``, the
    daemon's broadcast, which it is given before it starts."""

    def bind(self, emit: Callable[[Message], None]) -> None: ...


@runtime_checkable
class PlanControl(Protocol):
    """An output through which a service chooses the next test's plan (the bus's control key): it calls
    ``choose`` with a plan's name, or None to withdraw the choice."""

    def bind_control(self, choose: Callable[[str | None], None]) -> None: ...


@runtime_checkable
class StartsLate(Protocol):
    """An output made on its own thread when the first item reaches it (the viewer): ``cancel_start`` at shutdown,
    so that a stop does not start it only to stop it (what its queue still holds is dropped with it)."""

    def cancel_start(self) -> None: ...


class ListenerQueue:
    """A bounded queue and the thread that feeds one listener.

    ``capacity`` counts items (a batch or a message).  A listener that raises
    is logged and counted, never allowed to stop the others; it keeps
    receiving (a transient error, such as a full disk, may pass).

    The thread sleeps until there is something to deliver: a message, a batch
    for a listener that wants each one, a run of batches whose period is up
    (the putter wakes it then; a timer of its own covers a source that went
    quiet), ``on_idle``'s time, or ``close()``.
    """

    def __init__(self, listener: Listener, capacity: int = 1000, policy: DropPolicy = "drop_oldest") -> None:
        self.listener = listener
        self.capacity = capacity
        self.policy: DropPolicy = policy
        period = getattr(listener, "batch_period_s", 0.0)
        self.batch_period_s: float | None = None if period is None else max(0.0, float(period))
        self._period_now = getattr(listener, "batch_period_now", None) if period is not None else None
        idle = getattr(listener, "idle_s", 1.0)
        self.idle_s: float | None = None if idle is None else max(0.001, float(idle))
        self._items: deque[tuple[str, Any]] = deque()
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)  # the listener's thread waits on it
        self._drained = threading.Condition(self._lock)  # wait_idle() waits on it
        self._closing = False
        self._busy = False  # items taken from the queue are being delivered
        self._ready = 0  # the first this many items are due now (the rest: a run of batches, held)
        self._run_since: float | None = None  # when the held run's first batch came
        self._wait_until = math.inf  # when the thread's current wait ends by itself (inf: not waiting by a timer)
        self._expect_until = -math.inf  # batches came lately: wait by a timer until then, not indefinitely
        self.stats = QueueStats(capacity=capacity, policy=policy)
        self._thread = threading.Thread(target=self._run, name=f"listener-{listener.name}", daemon=True)
        self._thread.start()

    @property
    def wants_batches(self) -> bool:
        return self.batch_period_s is not None

    def put_batch(self, batch: SampleBatch) -> bool:
        if self.batch_period_s is None:
            return False
        return self._put(("batch", batch))

    def put_message(self, msg: Message) -> bool:
        return self._put(("message", msg))

    def _put(self, item: tuple[str, Any]) -> bool:
        with self._cv:
            if self._closing:
                return False
            if len(self._items) >= self.capacity:
                self.stats.dropped += 1
                if self.policy == "drop_newest":
                    return False
                self._items.popleft()
                self._ready = max(0, self._ready - 1)
            self._items.append(item)
            self.stats.depth = len(self._items)
            period = self.period()
            if item[0] == "message" or not period:
                self._release()
                self._cv.notify()
            else:
                now = time.monotonic()
                if self._run_since is None:
                    self._run_since = now
                    if self._wait_until > now + 1.5 * period:  # the thread would not look in time by itself
                        self._cv.notify()
                elif now - self._run_since >= period:
                    self._release()
                    self._cv.notify()
        return True

    def period(self) -> float:
        """The batch period of the moment (0: each batch at once)."""
        if self._period_now is not None:
            return max(0.0, float(self._period_now()))
        return self.batch_period_s or 0.0

    def _release(self) -> None:
        """Everything queued is due (under the lock)."""
        self._ready = len(self._items)
        self._run_since = None

    def _take(self) -> list[tuple[str, Any]] | None:
        """Under the lock: wait for what is due; ``[]`` for ``on_idle``, ``None`` when closed and drained."""
        period = self.period()
        next_idle = time.monotonic() + self.idle_s if self.idle_s is not None else math.inf
        while True:
            now = time.monotonic()
            if self._items and (
                self._closing or (self._run_since is not None and now - self._run_since >= period)
            ):
                self._release()
            if self._ready:
                n = self._ready if period else 1  # with a period, all that is due at once: its batches merged
                out = [self._items.popleft() for _ in range(n)]
                self._ready -= n
                self.stats.depth = len(self._items)
                if period and any(kind == "batch" for kind, _ in out):
                    self._expect_until = now + 2.0 * period
                return out
            if self._closing:
                return None
            if now >= next_idle:
                return []
            until = next_idle
            if self._run_since is not None:
                # The putter wakes us when the run is due; this timer is for a putter that went quiet.
                until = min(until, self._run_since + 1.5 * period)
            elif now < self._expect_until:
                until = min(until, self._expect_until)
            self._wait_until = until
            self._cv.wait(None if until == math.inf else until - now)
            self._wait_until = math.inf

    def _run(self) -> None:
        while True:
            with self._cv:
                items = self._take()
                if items is None:
                    return
                self._busy = True
            try:
                self._deliver(items)
            finally:
                with self._lock:
                    self._busy = False
                    if not self._items:
                        self._drained.notify_all()

    def _deliver(self, items: list[tuple[str, Any]]) -> None:
        if not items:
            self._call(self.listener.on_idle, None, 0)
            return
        i = 0
        while i < len(items):
            kind, payload = items[i]
            if kind == "message":
                self._call(self.listener.on_message, payload, 1)
                i += 1
                continue
            j = i + 1
            while j < len(items) and items[j][0] == "batch":
                j += 1
            merged = payload if j == i + 1 else SampleBatch.concat([b for _, b in items[i:j]])
            self._call(self.listener.on_batch, merged, j - i)
            i = j

    def _call(self, fn: Any, arg: Any, count: int) -> None:
        try:
            if count:
                fn(arg)
                self.stats.delivered += count
            else:
                fn()
        except Exception:  # a listener's failure must not stop the pipeline
            self.stats.errors += 1
            log.exception("listener %s failed", self.listener.name)

    def wait_idle(self, timeout: float, stop: threading.Event | None = None) -> bool:
        """Wait until everything queued has been delivered (True), ``timeout`` passes or ``stop`` is set."""
        deadline = time.monotonic() + timeout
        with self._lock:
            while self._items or self._busy:
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive() or (stop is not None and stop.is_set()):
                    return False
                self._drained.wait(min(left, 0.1))
        return True

    def close(self, timeout: float = 5.0) -> None:
        """Deliver what is queued (within ``timeout``), then stop the listener."""
        with self._cv:
            self._closing = True
            self._cv.notify()
        self._thread.join(timeout)
        if self._thread.is_alive():
            log.warning("listener %s did not drain its queue within %.1f s", self.listener.name, timeout)
        t0 = time.monotonic()
        try:
            self.listener.stop()
        except Exception:
            log.exception("listener %s failed to stop", self.listener.name)
        log.debug("listener %s stopped in %.3f s", self.listener.name, time.monotonic() - t0)
