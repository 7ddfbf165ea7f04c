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
import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .samples import SampleBatch

log = logging.getLogger(__name__)

Message = dict[str, Any]
DropPolicy = Literal["drop_oldest", "drop_newest"]


def _plain(obj: Any) -> Any:
    """What ``json`` cannot take as it is: numpy values, arrays, paths, sets."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Mapping):
        return dict(obj)
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def _finite(obj: Any) -> Any:
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite(obj.tolist())
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def to_json(msg: Any) -> bytes:
    """A message as compact, strict JSON (UTF-8): NaN and infinities become ``null``.

    One encoding for every output (MCAP records, bus payloads).
    """
    try:
        text = json.dumps(msg, separators=(",", ":"), allow_nan=False, default=_plain)
    except ValueError:
        text = json.dumps(_finite(msg), separators=(",", ":"), allow_nan=False, default=_plain)
    return text.encode("utf-8")


class Listener(abc.ABC):
    """Receives samples and messages on its own thread; ``stop()`` flushes and closes."""

    name: str = "listener"

    def on_batch(self, batch: SampleBatch) -> None:  # noqa: B027 - optional
        """Samples and the source events that came before them."""

    def on_message(self, msg: Message) -> None:  # noqa: B027 - optional
        """An analysis result, an event, the status or the configuration."""

    def on_idle(self) -> None:  # noqa: B027 - optional
        """Called about once a second when nothing arrived (timers: flushes, reconnects)."""

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
    policy: str = "drop_oldest"

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


class ListenerQueue:
    """A bounded queue and the thread that feeds one listener.

    ``capacity`` counts items (a batch or a message).  A listener that raises
    is logged and counted, never allowed to stop the others; it keeps
    receiving (a transient error, such as a full disk, may pass).
    """

    def __init__(self, listener: Listener, capacity: int = 1000, policy: DropPolicy = "drop_oldest") -> None:
        self.listener = listener
        self.capacity = capacity
        self.policy: DropPolicy = policy
        self._items: deque[tuple[str, Any]] = deque()
        self._cv = threading.Condition()
        self._closing = False
        self._busy = False  # an item taken from the queue is being delivered
        self.stats = QueueStats(capacity=capacity, policy=policy)
        self._thread = threading.Thread(target=self._run, name=f"listener-{listener.name}", daemon=True)
        self._thread.start()

    def put_batch(self, batch: SampleBatch) -> bool:
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
            self._items.append(item)
            self.stats.depth = len(self._items)
            self._cv.notify()
        return True

    def _run(self) -> None:
        while True:
            with self._cv:
                if not self._items and not self._closing:
                    self._cv.wait(timeout=1.0)
                if not self._items:
                    if self._closing:
                        return
                    item = None
                else:
                    item = self._items.popleft()
                    self.stats.depth = len(self._items)
                    self._busy = True
            try:
                if item is None:
                    self.listener.on_idle()
                elif item[0] == "batch":
                    self.listener.on_batch(item[1])
                else:
                    self.listener.on_message(item[1])
                if item is not None:
                    self.stats.delivered += 1
            except Exception:  # a listener's failure must not stop the pipeline
                self.stats.errors += 1
                log.exception("listener %s failed", self.listener.name)
            finally:
                with self._cv:
                    self._busy = False
                    if not self._items:
                        self._cv.notify_all()

    def wait_idle(self, timeout: float, stop: threading.Event | None = None) -> bool:
        """Wait until everything queued has been delivered (True), ``timeout`` passes or ``stop`` is set."""
        deadline = time.monotonic() + timeout
        with self._cv:
            while self._items or self._busy:
                left = deadline - time.monotonic()
                if left <= 0 or not self._thread.is_alive() or (stop is not None and stop.is_set()):
                    return False
                self._cv.wait(min(left, 0.1))
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
