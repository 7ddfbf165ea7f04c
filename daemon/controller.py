"""The CNC controller's own account over OPC UA: the client of ``[controller]``.

The controller beside the bar knows what the bar can only infer: the program that runs, the feed override, the
block, the active G functions, the axes' actual and commanded positions.  Current controllers serve them over
OPC UA, in the model of OPC 40502 (OPC UA for CNC Systems) or in a vendor's own.  This module is the daemon's
client: asyncua (a pure-Python OPC UA stack) on a thread of its own (``controller``) with its own event loop, so
that neither a slow server nor the stack's coroutines ever touch the reader, the watchdog or the outputs.

* **The node map.** Each thing read has a name (``program``, ``override``, ``feed``, ``g_functions``, ``block``,
  ``act_pos.<axis>``, ``cmd_pos.<axis>``) and a place: a browse path from the Objects folder
  (``CncInterface/CncChannelList/Channel_1/ActOverride``), each segment matched by its browse name (in any
  namespace; ``cnc:Name`` in ``[controller] namespace``'s, ``3:Name`` in namespace 3), or a node id
  (``ns=2;s=/Channel/State/actFeedRateIpo``).  :data:`DEFAULT_NODES` is OPC 40502's;
  ``[controller] nodes`` changes or adds names (an empty value drops one).  A name the server lacks is one
  warning naming it at each connection where the set of missing names changed; the rest are read.
* **Subscriptions.** One subscription at ``publish_ms``, each node sampled every ``sample_ms``, queued so that
  nothing sampled between two publishes is lost.  What arrives is handed on once per publishing interval, one
  ``controller`` message (:class:`~ballbar.protocol.messages.controller.ControllerMessage`) for all the values that
  changed, through ``emit`` (the daemon's broadcast: the MCAP logger records it on ``/ballbar/controller``).
* **Time.** Each value carries the server's source timestamp; ``t_host`` is that time on the daemon's monotonic
  clock: ``t_source + clock_offset_s`` as wall time, then wall to monotonic, once per publish (all its values
  with one offset, so that their order in time holds).
  ``clock_offset_s`` (wall minus server) is the smallest arrival minus source timestamp seen over the last
  minute: it holds the server's clock offset plus the shortest delay through the stack, never the publishing
  interval's wait.  A value without a source timestamp gets its arrival time.
* **Faults.** A server absent at start or lost later is retried with back-off (``reconnect_min_s`` doubling up to
  ``reconnect_max_s``); meanwhile the daemon reads the bar alone.  The state (:meth:`ControllerClient.stats`, the
  status' ``controller`` block) says connecting, connected or lost, the last update's age and how many
  reconnects; a loss is a ``controller`` message with ``state: "lost"`` (and a warning).  Secrets never reach a
  log line or a message: the endpoint is masked (:func:`~ballbar.daemon.secrets.mask_url`).

asyncua is imported on the client's thread when it starts, never with this module: without ``[controller]`` the
daemon never imports it.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from ballbar.protocol.messages import stamp

from .secrets import mask_url

if TYPE_CHECKING:
    from ballbar.protocol.messages.controller import ControllerMessage, ControllerValue, Value
    from ballbar.protocol.messages.status import ControllerStats

    from .config import ControllerSection

log = logging.getLogger(__name__)

_CHANNEL = "CncInterface/CncChannelList/{channel}"
_AXIS = "CncInterface/CncAxisList/{axis}/PosIndirect"
#: OPC 40502's places of what the daemon reads (browse names of the specification; {channel} and {axis} are the
#: configured instances' names).
DEFAULT_NODES: dict[str, str] = {
    "program": f"{_CHANNEL}/ActMainProgramName",
    "override": f"{_CHANNEL}/ActOverride",
    "feed": f"{_CHANNEL}/ActFeedrate",
    "g_functions": f"{_CHANNEL}/ActGFunctions",
    "block": f"{_CHANNEL}/ActProgramBlock",
}
AXIS_NODES: dict[str, str] = {"act_pos": f"{_AXIS}/ActPos", "cmd_pos": f"{_AXIS}/CmdPos"}
_NODE_ID_PREFIXES = ("ns=", "nsu=", "i=", "s=", "g=", "b=")
OFFSET_WINDOW_S = 60.0  # the clock offset is the smallest delay seen over about this long
JUMP_PUBLISHES = 3  # publishes in a row late by more than the jump threshold: the server's clock went back
WARN_EVERY_S = 60.0  # a server still absent is said again this often
EVENT_QUEUE = 10_000  # data changes waiting for the client's task (the oldest dropped beyond)
SESSION_TIMEOUT_MS = 60_000  # a session the server may drop a minute after a loss (asyncua asks for an hour)


def node_map(section: ControllerSection) -> dict[str, str]:
    """The names read and where: :data:`DEFAULT_NODES` and :data:`AXIS_NODES` for each configured axis, then
    ``section.nodes`` over them (an empty place drops the name)."""
    out = {name: path.format(channel=section.channel) for name, path in DEFAULT_NODES.items()}
    for axis in section.axes:
        for name, path in AXIS_NODES.items():
            out[f"{name}.{axis}"] = path.format(axis=axis)
    for name, path in section.nodes.items():
        if path:
            out[name] = path.format(channel=section.channel)
        else:
            out.pop(name, None)
    return out


def _jsonable(v: Any) -> Value:
    """A node's value as plain JSON data (an array element by element; text of what has no JSON form)."""
    if v is None or isinstance(v, bool | int | str):
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, list | tuple):
        items = [_jsonable(x) for x in v]  # an array's element that is itself none of these becomes its text
        return [x if isinstance(x, str | int | float) else str(x) for x in items]
    text = getattr(v, "Text", None)  # a LocalizedText
    if isinstance(text, str):
        return text
    if isinstance(v, dt.datetime):
        return _utc(v)
    return str(v)


def _unix(t: dt.datetime) -> float:
    return (t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)).timestamp()


def _utc(t: dt.datetime) -> str:
    t = t if t.tzinfo is not None else t.replace(tzinfo=dt.UTC)
    return t.astimezone(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class _Offset:
    """The daemon's wall clock minus the server's: the smallest arrival minus source timestamp over the last
    :data:`OFFSET_WINDOW_S` (two half windows, so that an old minimum ages out).

    A server clock that jumps: ahead (every delay drops by the jump: the first such value starts the estimate
    afresh), or back (every delay rises: :data:`JUMP_PUBLISHES` publishes in a row whose smallest delay is more
    than ``jump_s`` above the estimate start it afresh; fewer are a slow network, not a jump).  Each returns the
    change of the offset (s)."""

    def __init__(self, jump_s: float = 2.0) -> None:
        self._blocks: deque[tuple[float, float]] = deque()  # (block start, smallest delay in it)
        self.jump_s = jump_s
        self._high = 0  # publishes in a row above the estimate by more than jump_s

    def add(self, delay_s: float, now: float) -> float | None:
        """One value's delay (arrival minus source time); the offset's change where it shows a jump ahead."""
        old = self.value
        if old is not None and delay_s < old - self.jump_s:
            self._blocks.clear()
            self._blocks.append((now, delay_s))
            return delay_s - old
        self._add(delay_s, now)
        return None

    def publish(self, smallest_s: float, now: float) -> float | None:
        """The smallest delay of one publish; the offset's change where the last publishes show a jump back."""
        old = self.value
        if old is None or smallest_s <= old + self.jump_s:
            self._high = 0
            return None
        self._high += 1
        if self._high < JUMP_PUBLISHES:
            return None
        self._high = 0
        self._blocks.clear()
        self._blocks.append((now, smallest_s))
        return smallest_s - old

    def _add(self, delay_s: float, now: float) -> None:
        half = OFFSET_WINDOW_S / 2
        if not self._blocks or now - self._blocks[-1][0] >= half:
            self._blocks.append((now, delay_s))
            while len(self._blocks) > 2:
                self._blocks.popleft()
        elif delay_s < self._blocks[-1][1]:
            self._blocks[-1] = (self._blocks[-1][0], delay_s)

    @property
    def value(self) -> float | None:
        return min(b[1] for b in self._blocks) if self._blocks else None


class ControllerClient:
    """The OPC UA client on its own thread; see the module docstring.

    ``emit`` is handed each ``controller`` message (from the client's thread); :meth:`start` once, :meth:`stop`
    safe to call twice; :meth:`stats` from any thread.
    """

    def __init__(self, section: ControllerSection, machine_id: str,
                 emit: Callable[[ControllerMessage], None] | None = None) -> None:
        self.section = section
        self.machine_id = machine_id
        self.endpoint = mask_url(section.endpoint)
        self.nodes = node_map(section)
        self.emit = emit or (lambda _msg: None)
        self.state: str = "connecting"
        self.connected = False
        self.connections = 0
        self.attempts_failed = 0
        self.updates = 0
        self.missing: list[str] = []
        self.last_error: str | None = None
        self.last_update: float | None = None  # host monotonic
        self._offset = _Offset(jump_s=max(2.0, 4 * section.publish_ms / 1000))
        self.clock_jumps = 0
        self._batch_min = math.inf  # the smallest delay of the publish being read
        self._pending: list[ControllerValue] = []
        self._unmapped: list[int] = []  # those of _pending whose t_host is still the server's time
        self._flush_soon = False
        self._warned_missing: list[str] | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_event: asyncio.Event | None = None
        self._stopping = threading.Event()

    # ------------------------------------------------------------------ the daemon's side

    def start(self) -> None:
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, name="controller", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 2.0) -> None:
        """Close the session and end the thread, within about ``timeout``."""
        self._stopping.set()
        loop, ev = self._loop, self._stop_event
        if loop is not None and ev is not None:
            with contextlib.suppress(RuntimeError):  # the loop has ended already
                loop.call_soon_threadsafe(ev.set)
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("controller: the client did not stop within %.1f s", timeout)
        self.state = "stopped"
        self.connected = False

    def stats(self) -> ControllerStats:
        last = self.last_update
        return {
            "state": self.state,  # type: ignore[typeddict-item]
            "connected": self.connected,
            "endpoint": self.endpoint,
            "last_update_age_s": None if last is None else round(time.monotonic() - last, 3),
            "reconnects": max(0, self.connections - 1),
            "attempts": self.attempts_failed,
            "updates": self.updates,
            "missing": list(self.missing),
            "clock_offset_s": self._offset.value,
            "clock_jumps": self.clock_jumps,
            "last_error": self.last_error,
        }

    # ------------------------------------------------------------------ the client's thread

    def _run(self) -> None:
        try:
            asyncio.run(self._main())
        except Exception:
            log.exception("controller: the client failed; the daemon reads the bar alone")
            self.state = "stopped"
            self.connected = False

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop_event = asyncio.Event()
        if self._stopping.is_set():
            return
        if not log.isEnabledFor(logging.DEBUG):  # the client says what matters in its own lines, once
            logging.getLogger("asyncua").setLevel(logging.CRITICAL)
        from asyncua import Client

        delay = self.section.reconnect_min_s
        warned_at = -math.inf
        while not self._stop_event.is_set():
            lost = asyncio.Event()
            client = Client(self.section.endpoint, timeout=self.section.timeout_s,
                            watchdog_intervall=min(1.0, self.section.timeout_s))
            # the asyncua logger would repeat the endpoint (and its credentials) with each warning
            client.strip_url_credentials = True
            client.session_timeout = SESSION_TIMEOUT_MS

            async def on_lost(exc: Exception, lost: asyncio.Event = lost) -> None:
                self.last_error = _why(exc)
                lost.set()

            client.connection_lost_callback = on_lost
            try:
                if not await self._until_stopped(client.connect()):
                    await self._disconnect(client)
                    break
            except Exception as err:
                self.attempts_failed += 1
                self.last_error = _why(err)
                now = time.monotonic()
                if now - warned_at >= WARN_EVERY_S:
                    warned_at = now
                    log.warning("controller: cannot connect to %s (%s); retrying, the daemon reads the bar alone",
                                self.endpoint, self.last_error)
                await self._disconnect(client)
                if await self._wait(self._stop_event, delay):
                    break
                delay = min(delay * 2, self.section.reconnect_max_s)
                continue
            try:
                await self._session(client, lost)
                delay = self.section.reconnect_min_s
                warned_at = -math.inf
            except Exception as err:
                self.last_error = _why(err)
                log.warning("controller: %s: %s", self.endpoint, self.last_error)
            was = self.connected
            self.connected = False
            await self._disconnect(client)
            if self._stop_event.is_set():
                break
            self.state = "lost" if was or self.connections else "connecting"
            if was:
                log.warning("controller: lost %s (%s); reconnecting, the daemon reads the bar alone",
                            self.endpoint, self.last_error or "connection closed")
                self._send("lost", [], detail=self.last_error or "connection closed")
            if await self._wait(self._stop_event, delay):
                break
            delay = min(delay * 2, self.section.reconnect_max_s)

    async def _session(self, client: Any, lost: asyncio.Event) -> None:
        """Resolve the map, subscribe, and hand on what arrives until the connection is lost or the daemon
        stops."""
        from asyncua import ua

        found, missing = await self._resolve_all(client)
        self.missing = missing
        if missing != self._warned_missing:
            for name in missing:
                log.warning("controller: %s has no node %s (%s): not read", self.endpoint, name, self.nodes[name])
            self._warned_missing = missing
        by_node: dict[Any, list[str]] = {}  # a node two names share is monitored once
        unique: list[Any] = []
        for name, node in found.items():
            if node.nodeid not in by_node:
                by_node[node.nodeid] = []
                unique.append(node)
            by_node[node.nodeid].append(name)
        # The subscription's own queue, read by one task: a handler would be called from a task per value
        sub = await client.create_subscription(self.section.publish_ms, None, queue_maxsize=EVENT_QUEUE)
        events = sub.__aiter__()  # the queue exists before the first publish
        queue = max(1, math.ceil(self.section.publish_ms / self.section.sample_ms) + 1)
        if unique:
            handles = await sub.subscribe_data_change(unique, queuesize=queue,
                                                      sampling_interval=self.section.sample_ms)
            for node, h in zip(unique, handles, strict=True):
                if isinstance(h, ua.StatusCode):
                    for name in by_node[node.nodeid]:
                        log.warning("controller: %s refused to monitor %s (%s)", self.endpoint, name,
                                    self.nodes[name])
        self.connections += 1
        self.connected = True
        self.state = "connected"
        self.last_error = None
        log.info("controller: connected to %s, %d of %d nodes subscribed%s", self.endpoint, len(found),
                 len(self.nodes), " (reconnect)" if self.connections > 1 else "")
        self._send("connected", [], missing=missing)
        consumer = asyncio.ensure_future(self._consume(events, by_node))
        ends = [asyncio.ensure_future(lost.wait()), asyncio.ensure_future(self._stop_event.wait()),  # type: ignore[union-attr]
                consumer]
        try:
            await asyncio.wait(ends, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in ends:
                t.cancel()
            with contextlib.suppress(BaseException):
                await consumer
        self._flush()

    async def _consume(self, events: Any, by_node: Mapping[Any, list[str]]) -> None:
        """Each data change, by name; what one publish brought is handed on together, once the queue is drained
        (the flush is called soon after: when this task next waits)."""
        loop = asyncio.get_running_loop()
        async for ev in events:
            data = getattr(ev, "data", None)
            if data is None:  # a status change of the subscription
                log.debug("controller: subscription event %s", ev)
                continue
            names = by_node.get(ev.node.nodeid, ())
            for name in names:
                self._on_value(name, data.monitored_item.Value)
            if names and not self._flush_soon:
                self._flush_soon = True
                loop.call_soon(self._flush)

    async def _resolve_all(self, client: Any) -> tuple[dict[str, Any], list[str]]:
        namespaces: list[str] = await client.get_namespace_array()
        cnc = namespaces.index(self.section.namespace) if self.section.namespace in namespaces else None
        cache: dict[str, list[Any]] = {}
        found: dict[str, Any] = {}
        missing: list[str] = []
        for name, path in self.nodes.items():
            node = await _resolve(client, path, cnc, cache)
            if node is None:
                missing.append(name)
            else:
                found[name] = node
        return found, missing

    def _on_value(self, name: str, data_value: Any) -> None:
        """A value as it arrives: its time on the daemon's clock is given at the flush, with the offset that
        the whole publish taught (one offset for all its values: their order in time stays)."""
        now, wall = time.monotonic(), time.time()
        ts = data_value.SourceTimestamp
        t_source: str | None = None
        t_host: float = now
        if isinstance(ts, dt.datetime):
            ts_unix = _unix(ts)
            delay = wall - ts_unix
            self._batch_min = min(self._batch_min, delay)
            self._jumped(self._offset.add(delay, now))
            t_source = _utc(ts)
            t_host = ts_unix  # (server time until the flush maps it)
            self._unmapped.append(len(self._pending))
        status = data_value.StatusCode
        good = status is None or getattr(status, "is_good", lambda: True)()
        value = _jsonable(data_value.Value.Value) if (good and data_value.Value is not None) else None
        item: ControllerValue = {"name": name, "value": value, "t_source": t_source, "t_host": t_host}
        if not good:
            item["status"] = getattr(status, "name", str(status))
        self._pending.append(item)
        self.updates += 1
        self.last_update = now

    def _flush(self) -> None:
        self._flush_soon = False
        if self._pending:
            values, self._pending = self._pending, []
            unmapped, self._unmapped = self._unmapped, []
            if math.isfinite(self._batch_min):
                self._jumped(self._offset.publish(self._batch_min, time.monotonic()))
            self._batch_min = math.inf
            offset = self._offset.value
            shift = (offset if offset is not None else 0.0) + (time.monotonic() - time.time())  # server -> monotonic
            for i in unmapped:
                values[i]["t_host"] = float(values[i]["t_host"] or 0.0) + shift
            self._send("data", values)

    def _jumped(self, change: float | None) -> None:
        if change is not None:
            self.clock_jumps += 1
            log.warning("controller: %s: the server's clock jumped %+.3f s (its timestamps against the daemon's); "
                        "the clock offset starts afresh", self.endpoint, -change)

    def _send(self, state: str, values: list[ControllerValue], **extra: Any) -> None:
        msg: ControllerMessage = {
            **stamp(self.machine_id), "kind": "controller", "t_host": time.monotonic(), "endpoint": self.endpoint,
            "state": state, "values": values, "clock_offset_s": self._offset.value,  # type: ignore[typeddict-item]
        }
        msg.update(extra)  # type: ignore[typeddict-item]
        try:
            self.emit(msg)
        except Exception:
            log.exception("controller: a message could not be handed on")

    async def _until_stopped(self, coro: Any) -> bool:
        """Await ``coro`` unless the daemon stops first (then it is cancelled: False)."""
        assert self._stop_event is not None
        task = asyncio.ensure_future(coro)
        stop = asyncio.ensure_future(self._stop_event.wait())
        await asyncio.wait({task, stop}, return_when=asyncio.FIRST_COMPLETED)
        stop.cancel()
        if not task.done():
            task.cancel()
            with contextlib.suppress(BaseException):
                await task
            return False
        task.result()  # its error, if it failed
        return True

    @staticmethod
    async def _wait(event: asyncio.Event, timeout: float) -> bool:
        """Whether ``event`` was set within ``timeout``."""
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(event.wait(), timeout)
        return event.is_set()

    async def _disconnect(self, client: Any) -> None:
        """Close the session, within a second once the daemon stops (the server may be gone)."""
        limit = min(1.0, self.section.timeout_s) if self._stopping.is_set() else self.section.timeout_s
        with contextlib.suppress(Exception):
            await asyncio.wait_for(client.disconnect(), limit)


async def _resolve(client: Any, path: str, cnc: int | None, cache: dict[str, list[Any]]) -> Any:
    """The node at ``path`` (a node id, or a browse path from Objects; see the module docstring), None where the
    server has none.  ``cache`` keeps each node's children across the map's paths."""
    from asyncua import ua

    path = path.strip()
    if path.startswith(_NODE_ID_PREFIXES):
        node = client.get_node(path)
        try:
            await node.read_browse_name()
        except (ua.UaStatusCodeError, ValueError):
            return None
        return node
    node = client.nodes.objects
    for segment in (s for s in path.strip("/").split("/") if s):
        prefix, colon, name = segment.partition(":")
        ns: int | None = None
        if not colon:
            name = segment
        elif prefix == "cnc":
            if cnc is None:
                return None  # the server has no CNC namespace
            ns = cnc
        elif prefix.isdigit():
            ns = int(prefix)
        else:
            name = segment  # a colon inside a name
        key = node.nodeid.to_string()
        if key not in cache:
            cache[key] = await node.get_children_descriptions()
        match = next((d for d in cache[key] if d.BrowseName.Name == name
                      and (ns is None or d.BrowseName.NamespaceIndex == ns)), None)
        if match is None:
            return None
        node = client.get_node(match.NodeId)
    return node


def _why(err: BaseException) -> str:
    """An error in words, masked (a URL's password never shows)."""
    text = str(err) or type(err).__name__
    return mask_url(f"{type(err).__name__}: {text}" if text != type(err).__name__ else text)


__all__ = ["AXIS_NODES", "DEFAULT_NODES", "ControllerClient", "node_map"]
