"""The Zenoh side of the daemon: results, events and status for plant services.

:class:`ZenohBus` is a :class:`~ballbar.daemon.listeners.Listener`: it runs on
its own queue's thread, so nothing it does can hold up sampling, and it
publishes every message it is given under ``ballbar/<machine>/...``.

Key space
---------
``<machine>`` is ``daemon.machine_id`` (one key chunk: no ``/ * $ ? #``).
Every payload is one JSON object, encoding ``application/json``, as its
producer made it (:mod:`ballbar.protocol.messages`: the types, the envelope
``schema_version``, ``kind``, ``machine_id`` and ``t_wall``, the schemas, the
payload tables); non-finite numbers are sent as ``null``.

================================  ==========  ====================================================
key                               how         what
================================  ==========  ====================================================
``ballbar/<m>/result/circle``     put         each circle's fit (``kind: "circle"``), as soon as
                                              its data arc is complete (provisional timing)
``ballbar/<m>/result/test``       put         each test's result (``kind: "test"``): the
                                              ``ballbar analyze --json`` object plus ``test_id``
``ballbar/<m>/result/set``        put         a test set combined into the machine's axes (``kind:
                                              "set"``, :mod:`.sets`), when a set's tests are in
``ballbar/<m>/event``             put         ``kind: "event"``; ``event`` says which: feed_in,
                                              feed_out, test_rejected, test_incomplete, unplugged,
                                              replugged, lost, stall, resumed, device_reset,
                                              clock_jump, ...
``ballbar/<m>/status``            put         ``kind: "status"`` every status interval: rates,
                                              losses, queue depths, source state, fit latency,
                                              ``outputs.zenoh``: this publisher's own counters
``ballbar/<m>/config``            put         ``kind: "config"``: the effective configuration, at
                                              start
``ballbar/<m>/alert``             put         ``kind: "alert"`` (with ``[limits]`` on): a verdict that
                                              turned to warning or fail or back, a forecast that
                                              became due or cleared (:mod:`.monitor`)
``ballbar/<m>/samples``           put         ``kind: "samples"``, decimated samples (off unless
                                              ``samples_hz`` > 0): one message per max(0.1 s,
                                              1/``samples_hz``) with columns ``t_host``,
                                              ``t_device``, ``length_mm``,
                                              ``seq``, ``status``; the first sample of each
                                              1/``samples_hz`` slot, unfiltered: for display only
``ballbar/<m>/last/<topic>``      queryable   the last payload put on ``circle``, ``test``,
                                              ``set`` (results), ``event``, ``status``, ``config``,
                                              ``alert``; no
                                              reply when there is none yet. ``last/*`` gives all.
``ballbar/<m>/history/test``      queryable   results (and events) kept by the daemon, one reply:
``ballbar/<m>/history/circle``                ``{"kind": "history", "topic", "machine_id",
``ballbar/<m>/history/set``
``ballbar/<m>/history/event``                 "count", "more", "results": [...]}``, oldest first.
``ballbar/<m>/history/alert``
                                              Parameters (``;``-separated; ``&`` accepted):
                                              ``since=<ISO 8601 or Unix seconds>`` (exclusive,
                                              compared with ``t_wall``), ``limit=N`` (default 100,
                                              at most 1000). Without ``since``: the newest
                                              ``limit``. With it: the oldest ``limit`` after it;
                                              ``more: true`` means ask again with ``since`` = the
                                              last ``t_wall`` received.
``ballbar/<m>/control/next_plan`` subscribed  an explicit choice of the next test's plan, put by a
                                              service: ``{"plan": NAME}`` (or the bare name; ``null``
                                              withdraws it); the daemon answers with a ``plan_chosen``
                                              or ``plan_choice_refused`` event (none for a repeat of the
                                              choice standing).  At most 5 at once and 2 a second are
                                              taken; more are dropped and counted
                                              (``controls_dropped``).  In the secure setup
                                              only the subjects that ``systemd/zenoh-daemon.json5``
                                              lets put there may
``ballbar/<m>/alive``             liveliness  a token while the daemon runs: withdrawn at once on
                                              a clean stop or a crash, after the lease (10 s) when
                                              the host vanishes
================================  ==========  ====================================================

A late joiner subscribes first, then asks ``history`` (``since`` its last
result), and drops live results it already had (same ``kind``, ``test_id``,
``t_wall``, ``direction``): ``python -m ballbar.tools.subscribe --history``
does exactly that.

Delivery
--------
Order: the daemon puts a test's result before the alerts it causes, and each
put in the order it happened; Zenoh keeps that order to each subscriber, but
zenoh-python runs every subscriber's callbacks on a thread of its own, so a
service that must see a result before its alert subscribes once, on a
wildcard (``ballbar/<m>/**``), and filters the keys (as ``ballbar-subscribe``
does): two subscribers' callbacks interleave out of order.

Results, events, alerts and the configuration are put with ``CongestionControl.BLOCK``
at ``Priority.DATA_HIGH``: a subscriber that is slow for a moment still gets
every one.  To a subscriber that stops reading they are best effort (below),
and Zenoh does not say what it dropped: ``history/test``, ``history/circle``
and ``history/event`` are how a service catches up.  A subscriber that stops reading (a frozen process) can then hold
one put, once its backlog fills Zenoh's queue, for Zenoh's
``transport/link/tx/queue/congestion_control/block/wait_before_close`` (5 s by
default); after that Zenoh drops what that link cannot take without waiting
again, until it drains.  Other subscribers get every result meanwhile (after
the one pause), and the bus's queue (``drop_oldest``) absorbs the pause:
sampling never waits.  The frozen subscriber stays connected and, once it
reads again, receives live results again; those it missed are in ``history``.
Status and samples are best effort (``DROP``, priorities ``DATA`` and
``DATA_LOW``): the next one supersedes.  An event found at start (``origin:
recovery``: a test that a crash cut) is put once a subscriber of ``event`` is
there (checked with each message, at least every status interval; for at most
``RECOVERY_WAIT_S``): the subscribers of the daemon before its restart are
still reconnecting when it starts.  It is in ``last/event`` and
``history/event`` at once.  ``history/event`` keeps the answers to the control
key (``plan_chosen``, ``plan_choice_refused``) apart, the newest 50 of them, so
that what peers put there never pushes the machine's own events out.

The history is the daemon's own: a bounded in-memory record of the results
that went through :meth:`ZenohBus.on_message`, seeded at start by an optional
``history_loader`` (results persisted before a restart, e.g. read back from the
MCAP recordings; each a result message, oldest first).

Connection
----------
:class:`ZenohConfig` passes the Zenoh settings through.  With no config file
the default is a **peer listening on tcp/127.0.0.1:7447**, multicast scouting
off and shared memory off: nothing goes to the LAN, no router is needed, and
``python -m ballbar.tools.subscribe`` (a client of tcp/127.0.0.1:7447 by
default) finds it.  To serve the plant, listen on a routable address
(``listen = ["tcp/0.0.0.0:7447"]``) and let services connect, or make the
daemon a ``client`` of the plant's router (``connect = ["tcp/ROUTER:7447"]``).
A peer that only connects to a router without a listener of its own is not
routed to other peers: give it a listener or use ``client``.  A Zenoh config
file (JSON5; TLS, access control) is the base; fields set here override it.

If the session cannot be opened (the router is down, the port is taken), the
bus logs one line, keeps results for ``last`` and ``history`` and retries in the
background: the daemon keeps measuring and recording.  :meth:`ZenohBus.stop`
withdraws the liveliness token first (immediate, even with a frozen peer), then
closes the session within ``close_timeout_s``; a close that Zenoh cannot finish
(a frozen peer with a backlog holds it ~10 s) is left to end in the background.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import json
import logging
import math
import re
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import zenoh

from ballbar import SCHEMA_VERSION
from ballbar.analysis.errors import BallbarError
from ballbar.protocol.messages import stamp, to_json

from .config import Config, ZenohSection
from .listeners import Listener, Message
from .samples import SampleBatch
from .secrets import REDACTED, is_secret_key

if TYPE_CHECKING:
    from ballbar.protocol.messages import HistoryReply, QueryError, Samples
    from ballbar.protocol.messages.replies import HistoryTopic
    from ballbar.protocol.messages.status import ZenohStats

log = logging.getLogger(__name__)

DEFAULT_PORT = 7447
DEFAULT_LISTEN = (f"tcp/127.0.0.1:{DEFAULT_PORT}",)
DEFAULT_CONNECT = (f"tcp/127.0.0.1:{DEFAULT_PORT}",)  # where tools look for a local daemon
MODES = ("peer", "client", "router")
#: Topics published, by message kind.
TOPICS: dict[str, str] = {
    "circle": "result/circle",
    "test": "result/test",
    "event": "event",
    "status": "status",
    "config": "config",
    "samples": "samples",
    "alert": "alert",
    "set": "result/set",
}
LAST_TOPICS = ("circle", "test", "set", "event", "status", "config", "alert")
HISTORY_TOPICS: tuple[HistoryTopic, ...] = ("circle", "test", "set", "event", "alert")
CONTROL_NEXT_PLAN = "control/next_plan"  # a service names the next test's plan here (subscribed)
CONTROL_MAX_BYTES = 1024  # a put on it longer than this is refused unread
CONTROL_NAME_CHARS = 64  # a plan's name: at most this many printable characters, no white space
CONTROL_LOG_S = 10.0  # refusals, and choices dropped by the rate limit, are logged at most once in this many seconds
# The choices handed on to the analysis (each makes an event, a log line and an MCAP record): a token bucket of
# CONTROL_BURST, refilled at CONTROL_RATE_HZ; a put beyond it is dropped and counted (``controls_dropped``).
CONTROL_RATE_HZ = 2.0
CONTROL_BURST = 5
# Events answering the control key: kept for ``history/event`` apart from the machine's own (feed_in, faults ...),
# in at most this many, so that a peer's puts never push those out.
CONTROL_EVENTS = ("plan_chosen", "plan_choice_refused")
CONTROL_HISTORY = 50


def parse_control(payload: bytes) -> tuple[str | None, str | None]:
    """A put on the control key as ``(name or None, None)``, or ``(None, why)`` for one not of the documented
    shape: ``{"plan": NAME}``, ``{"plan": null}``, ``"NAME"``, the bare ``NAME`` or ``null``.  Bounded before it is
    parsed: no nesting or size a peer sends can make more than one short reason of it."""
    if len(payload) > CONTROL_MAX_BYTES:
        return None, f"{len(payload)} bytes, more than {CONTROL_MAX_BYTES}"
    text = payload.decode("utf-8", "replace").strip()
    body: object
    if text[:1] in ('{', '[', '"') or text == "null" or text[:1].isdigit():
        try:
            body = json.loads(text)
        except (ValueError, RecursionError):
            return None, "not valid JSON"
        if isinstance(body, dict):
            if set(body) != {"plan"}:
                keys = ", ".join(sorted(repr(k)[:40] for k in body)[:5]) or "none"
                return None, f"an object must hold the key 'plan' alone (it has {keys})"
            body = body["plan"]
        if body is None:
            return None, None
    else:
        body = text
    if not isinstance(body, str):
        return None, f"a plan's name is a string, not {type(body).__name__}"
    if not 0 < len(body) <= CONTROL_NAME_CHARS or not body.isprintable() or any(c.isspace() for c in body):
        return None, f"not a plan's name ({CONTROL_NAME_CHARS} printable characters at most, no spaces): {body[:40]!r}"
    return body, None
HISTORY_LIMIT = 100
HISTORY_LIMIT_MAX = 1000
RECOVERY_WAIT_S = 60.0  # an event found at start waits this long for a subscriber to put it to
_RELIABLE = ("circle", "test", "set", "event", "config", "alert")
_BAD_CHUNK = re.compile(r"[/*$?#\s]")


class BusError(BallbarError, ConnectionError):
    """The Zenoh session could not be opened or used."""


class BusConfigError(BallbarError, ValueError):
    """A Zenoh setting is invalid: the message names the key."""


# --------------------------------------------------------------------------- configuration


def zenoh_message(err: BaseException) -> str:
    """A Zenoh error as one line: the inner message, without the Rust source location."""
    text = str(err)
    m = re.search(r'msg: "((?:[^"\\]|\\.)*)"', text)
    if m:
        text = m.group(1).replace('\\"', '"')
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", text)
    text = re.sub(r"\s+", " ", text).strip()
    return text.rstrip(".!").strip() or type(err).__name__


@dataclass
class ZenohConfig:
    """A session's Zenoh settings, passed through to :class:`zenoh.Config`: the daemon's of its ``[zenoh]`` section
    (:func:`zenoh_config`, the one definition of the keys and their defaults), a client's of its command line
    (``ballbar-subscribe``, the benchmarks).

    ``None`` means "not set": the config file's value if there is a file, else
    the loopback default (``peer``; listen on ``tcp/127.0.0.1:7447`` for a peer
    or router, nothing for a client; connect nowhere; multicast scouting off;
    shared memory off).  ``options`` are any other Zenoh keys, as paths
    (``"transport/link/tx/lease": 5000``), applied last.
    """

    mode: str | None = None
    listen: list[str] | None = None
    connect: list[str] | None = None
    config_file: str | None = None
    multicast_scouting: bool | None = None
    options: dict[str, Any] = field(default_factory=dict)

    def to_zenoh_config(self) -> zenoh.Config:
        """The :class:`zenoh.Config`; a bad value raises :class:`BusConfigError` naming its key."""
        if self.mode is not None and self.mode not in MODES:
            raise BusConfigError(f"zenoh.mode: {self.mode!r} is not one of {', '.join(MODES)}")
        for name in ("listen", "connect"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, str) or not all(isinstance(v, str) for v in value)):
                raise BusConfigError(
                    f"zenoh.{name}: expected a list of endpoints such as ['tcp/127.0.0.1:7447'], not {value!r}"
                )
        if self.config_file:
            path = Path(self.config_file)
            if not path.is_file():
                raise BusConfigError(f"zenoh.config_file: {self.config_file}: no such file")
            try:
                cfg = zenoh.Config.from_file(str(path))
            except zenoh.ZError as err:
                raise BusConfigError(f"zenoh.config_file: {self.config_file}: {zenoh_message(err)}") from err
        else:
            cfg = zenoh.Config()
            mode = self.mode or "peer"
            _insert(cfg, "mode", mode, "mode")
            _insert(cfg, "listen/endpoints", [] if mode == "client" else list(DEFAULT_LISTEN), "listen")
            _insert(cfg, "connect/endpoints", [], "connect")
            _insert(cfg, "scouting/multicast/enabled", False, "multicast_scouting")
            # Small JSON payloads gain nothing from it, and each session would keep /dev/shm segments.
            _insert(cfg, "transport/shared_memory/enabled", False, "transport/shared_memory/enabled")
        if self.mode is not None:
            _insert(cfg, "mode", self.mode, "mode")
        if self.listen is not None:
            _insert(cfg, "listen/endpoints", list(self.listen), "listen")
        if self.connect is not None:
            _insert(cfg, "connect/endpoints", list(self.connect), "connect")
        if self.multicast_scouting is not None:
            _insert(cfg, "scouting/multicast/enabled", bool(self.multicast_scouting), "multicast_scouting")
        for key, value in self.options.items():
            _insert(cfg, key, value, f"options {key!r}")
        return cfg

    def describe(self) -> str:
        """One line for the log: where the session listens and connects."""
        cfg = self.to_zenoh_config()
        mode = json.loads(cfg.get_json("mode") or "null") or "peer"
        listen = _endpoints(cfg.get_json("listen/endpoints"), mode)
        connect = _endpoints(cfg.get_json("connect/endpoints"), mode)
        scouting = json.loads(cfg.get_json("scouting/multicast/enabled") or "null")
        return (
            f"{mode}, listen {', '.join(listen) or '-'}, connect {', '.join(connect) or '-'}, "
            f"multicast scouting {'off' if scouting is False else 'on'}"
            + (f", file {self.config_file}" if self.config_file else "")
        )


def _endpoints(text: str, mode: str) -> list[str]:
    value = json.loads(text) if text else []
    if isinstance(value, dict):  # per-mode lists
        value = value.get(mode) or []
    return [str(v) for v in value or []]


def _insert(cfg: zenoh.Config, key: str, value: Any, name: str) -> None:
    shown = REDACTED if is_secret_key(key) else None  # a refused password must not reach the log
    try:
        text = json.dumps(value)
    except (TypeError, ValueError) as err:
        raise BusConfigError(f"zenoh.{name}: {shown or repr(value)} is not a JSON value") from err
    try:
        cfg.insert_json5(key, text)
    except zenoh.ZError as err:
        detail = zenoh_message(err)
        if shown:
            detail = detail.replace(text, REDACTED).replace(str(value), REDACTED)
        raise BusConfigError(f"zenoh.{name}: {shown or text}: {detail}") from err


def zenoh_config(cfg: Config) -> ZenohConfig:
    """The :class:`ZenohConfig` of the daemon's ``[zenoh]`` section (empty values: not set)."""
    z = cfg.zenoh
    return ZenohConfig(
        mode=z.mode or None,
        listen=list(z.listen) or None,
        connect=list(z.connect) or None,
        config_file=z.config_file or None,
        multicast_scouting=z.multicast_scouting,
        options=dict(z.options),
    )


#: The link protocols of the eclipse-zenoh wheel (1.x): a locator with another scheme is refused by
#: ``zenoh.open`` ("Unicast not supported"); ``tests/test_network_config.py`` checks the list against the wheel.
ZENOH_SCHEMES = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream")
_IP_SCHEMES = ("tcp", "udp", "tls", "quic", "ws")  # <scheme>/<host>:<port>


def check_endpoints(config: ZenohConfig) -> None:
    """Endpoints that can never work, as :class:`BusConfigError` naming the key, before a session opens.

    Every endpoint (listen and connect; the config file's and ``options``' too) must name a scheme this
    Zenoh has (:data:`ZENOH_SCHEMES`) and a valid port; every listen address must be one of this host's
    (:func:`~ballbar.daemon.config.check_listen`).  An address on this host that another process holds now
    is not an error: the session retries and says so.
    """
    from .config import ConfigError, check_listen

    zcfg = config.to_zenoh_config()
    mode = json.loads(zcfg.get_json("mode") or "null") or "peer"
    for what in ("listen", "connect"):
        given = getattr(config, what) is not None
        key = (f"zenoh.{what}" if given else f"zenoh.options {what}/endpoints"
               if any(k.startswith(what) for k in config.options) else
               f"zenoh.config_file {config.config_file} ({what}/endpoints)" if config.config_file else
               f"zenoh.{what} (default)")
        for endpoint in _endpoints(zcfg.get_json(f"{what}/endpoints"), mode):
            locator = re.split(r"[?#]", endpoint, maxsplit=1)[0]
            scheme, _, address = locator.partition("/")
            if scheme not in ZENOH_SCHEMES:
                raise BusConfigError(f"{key}: {endpoint!r}: Zenoh has no {scheme!r} link "
                                     f"(it has {', '.join(ZENOH_SCHEMES)})")
            if scheme not in _IP_SCHEMES:
                continue
            m = re.fullmatch(r"\[(?P<v6>[^\]]+)\]:(?P<p6>\d+)|(?P<host>[^:\[\]]+):(?P<port>\d+)", address)
            port = int(m["p6"] or m["port"]) if m else -1
            if not 0 <= port <= 65535:
                raise BusConfigError(f"{key}: {endpoint!r}: expected {scheme}/HOST:PORT with a port within 0..65535")
            if what == "listen":
                assert m is not None
                try:
                    check_listen(key, m["v6"] or m["host"], port, datagram=scheme in ("udp", "quic"))
                except ConfigError as err:
                    raise BusConfigError(str(err)) from None


def check_machine(machine: str) -> str:
    """``machine`` as a key chunk, or :class:`BusConfigError`."""
    if not machine or _BAD_CHUNK.search(machine):
        raise BusConfigError(f"machine_id: {machine!r} must be a non-empty key chunk without / * $ ? # or spaces")
    return machine


# --------------------------------------------------------------------------- time


def parse_time_us(value: str | float | int) -> int:
    """Microseconds since the Unix epoch from Unix seconds or ISO 8601 (naive means UTC)."""
    if isinstance(value, int | float):
        if not math.isfinite(value):
            raise ValueError(f"{value!r} is not a time")
        return round(float(value) * 1e6)
    text = value.strip()
    try:
        return round(float(text) * 1e6)
    except ValueError:
        pass
    try:
        t = dt.datetime.fromisoformat(text)
    except ValueError as err:
        raise ValueError(f"{text!r} is neither ISO 8601 nor Unix seconds") from err
    if t.tzinfo is None:
        t = t.replace(tzinfo=dt.UTC)
    return (t - dt.datetime(1970, 1, 1, tzinfo=dt.UTC)) // dt.timedelta(microseconds=1)


def _params(query: zenoh.Query) -> dict[str, str]:
    """Selector parameters; Zenoh separates them with ``;``, a URL habit with ``&``: both work."""
    out: dict[str, str] = {}
    for part in re.split(r"[;&]", str(query.parameters)):
        if part:
            k, _, v = part.partition("=")
            out[k.strip()] = v.strip()
    return out


# --------------------------------------------------------------------------- the bus


@dataclass
class _Counters:
    published: dict[str, int] = field(default_factory=dict)
    put_errors: int = 0
    not_connected: int = 0
    slow_puts: int = 0
    max_put_ms: float = 0.0
    queries: int = 0
    query_errors: int = 0
    skipped: int = 0
    controls: int = 0
    controls_refused: int = 0
    controls_dropped: int = 0


class ZenohBus(Listener):
    """Publishes messages under ``ballbar/<machine>/``; answers ``last`` and ``history``.

    The session opens in the constructor (a bad setting raises
    :class:`BusConfigError`; a session that cannot open is retried in the
    background).  ``on_message`` and ``on_batch`` never raise for bus trouble:
    it is counted (``stats()``, and ``zenoh`` in the published status).
    """

    name = "zenoh"
    idle_s = None  # no timers here: the session retries on its own

    def __init__(
        self,
        machine: str,
        config: ZenohConfig | None = None,
        *,
        samples_hz: float = ZenohSection.samples_hz,
        history_size: int = ZenohSection.history_size,
        history_loader: Callable[[], Iterable[Mapping[str, Any]]] | None = None,
        close_timeout_s: float = ZenohSection.close_timeout_s,
        slow_put_s: float = 0.1,
    ) -> None:
        self.machine = check_machine(machine)
        self.config = config or ZenohConfig()
        self._zconfig = self.config.to_zenoh_config()  # raises BusConfigError before anything opens
        if samples_hz < 0 or not math.isfinite(samples_hz):
            raise BusConfigError(f"zenoh samples_hz: {samples_hz!r} must be 0 (off) or a positive rate")
        if history_size < 1:
            raise BusConfigError(f"zenoh history_size: {history_size!r} must be at least 1")
        self.samples_hz = float(samples_hz)
        # Batches only to publish samples, merged: one message per max(0.1 s, 1 / samples_hz).
        self.batch_period_s: float | None = max(0.1, 1.0 / self.samples_hz) if self.samples_hz else None
        self.close_timeout_s = close_timeout_s
        self.slow_put_s = slow_put_s
        self.prefix = f"ballbar/{self.machine}"
        self._lock = threading.Lock()
        self._last: dict[str, bytes] = {}
        self._history: dict[str, deque[tuple[int, bytes]]] = {k: deque(maxlen=history_size) for k in HISTORY_TOPICS}
        self._counters = _Counters(published=dict.fromkeys(TOPICS.values(), 0))
        self._refused_since_log = 0
        self._refusal_log_at = 0.0  # monotonic: when the next refusal may be logged
        self._tokens = float(CONTROL_BURST)  # the control key's token bucket (see CONTROL_RATE_HZ)
        self._tokens_at = time.monotonic()
        self._dropped_since_log = 0
        self._drop_log_at = 0.0  # monotonic: when the next line about dropped choices may be logged
        self._control_history: deque[tuple[int, bytes]] = deque(maxlen=CONTROL_HISTORY)
        self._warned_kinds: set[str] = set()
        self._last_slot = -(2**62)
        self._session: zenoh.Session | None = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._keep: list[Any] = []  # queryables and the liveliness token, alive while the session is
        self._token: zenoh.LivelinessToken | None = None
        self._open_error: str | None = None
        self._stopping = threading.Event()
        self._closed = threading.Event()
        self._opener: threading.Thread | None = None
        self._closer: threading.Thread | None = None
        self._deferred: list[tuple[float, bytes]] = []  # (until when, payload): events found at start, see on_message
        self._control: Callable[[str | None], None] | None = None
        if history_loader is not None:
            self._load_history(history_loader)
        try:
            self._open()
        except BusError as err:
            self._open_error = str(err)
            log.warning("%s; retrying in the background", err)
            self._opener = threading.Thread(target=self._retry_open, name=f"zenoh-open-{machine}", daemon=True)
            self._opener.start()

    @classmethod
    def from_config(cls, cfg: Config, history_loader: Callable[[], Iterable[Mapping[str, Any]]] | None = None
                    ) -> ZenohBus:
        """From the daemon's configuration: ``cfg.daemon.machine_id`` and the ``[zenoh]`` section.

        Empty ``listen``, ``connect`` and ``config_file`` mean "not set" (the
        defaults above).
        """
        z = cfg.zenoh
        return cls(
            cfg.daemon.machine_id,
            zenoh_config(cfg),
            samples_hz=z.samples_hz,
            history_size=z.history_size,
            close_timeout_s=z.close_timeout_s,
            history_loader=history_loader,
        )

    # ------------------------------------------------------------------ session

    def _open(self) -> None:
        try:
            session = zenoh.open(self._zconfig)
        except zenoh.ZError as err:
            raise BusError(f"zenoh: cannot open a session ({self.config.describe()}): {zenoh_message(err)}") from err
        try:
            pubs: dict[str, zenoh.Publisher] = {}
            for kind, topic in TOPICS.items():
                if kind == "samples" and not self.samples_hz:
                    continue
                reliable = kind in _RELIABLE
                pubs[kind] = session.declare_publisher(
                    f"{self.prefix}/{topic}",
                    encoding=zenoh.Encoding.APPLICATION_JSON,
                    congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
                    priority=(
                        zenoh.Priority.DATA_HIGH
                        if reliable
                        else zenoh.Priority.DATA_LOW
                        if kind == "samples"
                        else zenoh.Priority.DATA
                    ),
                )
            keep: list[Any] = [
                session.declare_queryable(f"{self.prefix}/last/*", self._on_last, complete=True),
                session.declare_queryable(f"{self.prefix}/history/*", self._on_history, complete=True),
                session.declare_subscriber(f"{self.prefix}/{CONTROL_NEXT_PLAN}", self._on_control),
            ]
            token = session.liveliness().declare_token(f"{self.prefix}/alive")
        except zenoh.ZError as err:
            with contextlib.suppress(zenoh.ZError):
                session.close()
            raise BusError(f"zenoh: cannot declare {self.prefix}/...: {zenoh_message(err)}") from err
        with self._lock:
            if self._stopping.is_set():
                stale = True
            else:
                stale = False
                self._session, self._publishers, self._keep, self._token = session, pubs, keep, token
                self._open_error = None
        if stale:
            with contextlib.suppress(zenoh.ZError):
                session.close()
            return
        log.info("zenoh: publishing under %s/ (%s)", self.prefix, self.config.describe())
        last = self._last.get("config")
        if last is not None:  # the configuration went out before the session was up
            self._put("config", last)

    def _retry_open(self) -> None:
        delay = 0.5
        while not self._stopping.wait(delay):
            try:
                self._open()
                return
            except BusError as err:
                if str(err) != self._open_error:
                    log.warning("%s; still retrying", err)
                self._open_error = str(err)
                delay = min(delay * 2, 30.0)

    @property
    def connected(self) -> bool:
        """Whether the session is open (not whether anyone listens)."""
        return self._session is not None

    def has_subscribers(self, kind: str) -> bool:
        """Whether a subscriber matches the topic of message ``kind`` (``circle``, ``test``, ...)."""
        pub = self._publishers.get(kind)
        if pub is None:
            return False
        try:
            status: Any = pub.matching_status
        except zenoh.ZError:
            return False
        return bool(getattr(status, "matching", status))  # a MatchingStatus, though the stub says bool

    # ------------------------------------------------------------------ listener

    def on_message(self, msg: Message) -> None:
        kind = str(msg.get("kind", ""))
        if kind == "controller":  # the CNC's data: recorded (MCAP), not published in this version
            return
        if kind not in TOPICS or kind == "samples":
            self._counters.skipped += 1
            if kind not in self._warned_kinds:
                self._warned_kinds.add(kind)
                log.warning("zenoh: no topic for messages of kind %r; not published", kind)
            return
        if msg["kind"] == "status" and isinstance(msg.get("outputs"), dict):  # this bus' counters as of this put
            msg = {**msg, "outputs": {**msg["outputs"], "zenoh": self.stats()}}
        payload = to_json(msg)
        with self._lock:
            self._last[kind] = payload
            if kind in self._history:
                self._history_for(msg).append((_record_time(msg), payload))
        if self._deferred:
            self._put_deferred()
        if msg["kind"] == "event" and msg.get("origin") == "recovery" and not self.has_subscribers("event"):
            # Found at start (a test a crash cut): the subscribers that were connected before the restart are
            # reconnecting now (a client retries every few seconds); put it once one is back.
            self._deferred.append((time.monotonic() + RECOVERY_WAIT_S, payload))
            return
        self._put(kind, payload)

    def _history_for(self, msg: Mapping[str, Any]) -> deque[tuple[int, bytes]]:
        """Where a message is kept for ``history``: the answers to the control key apart (CONTROL_HISTORY)."""
        if msg.get("kind") == "event" and msg.get("event") in CONTROL_EVENTS:
            return self._control_history
        return self._history[str(msg["kind"])]

    def _put_deferred(self) -> None:
        """The deferred events, once a subscriber of ``event`` is there; those older than RECOVERY_WAIT_S dropped
        (``history/event`` has them)."""
        now = time.monotonic()
        self._deferred = [(t, p) for t, p in self._deferred if t > now]
        if self._deferred and self.has_subscribers("event"):
            for _t, payload in self._deferred:
                self._put("event", payload)
            self._deferred = []

    def on_batch(self, batch: SampleBatch) -> None:
        if not self.samples_hz or len(batch) == 0 or "samples" not in self._publishers:
            return
        t = batch.t_host
        slot = np.floor(t * self.samples_hz).astype(np.int64)
        before = np.maximum.accumulate(np.concatenate(([self._last_slot], slot[:-1])))
        keep = np.flatnonzero(slot > before)
        self._last_slot = max(self._last_slot, int(slot.max()))
        if keep.size == 0:
            return
        body: Samples = {
            **stamp(self.machine),
            "kind": "samples",
            "source": batch.source,
            "samples_hz": self.samples_hz,
            "t_host": batch.t_host[keep].tolist(),
            "t_device": batch.t_device[keep].tolist(),
            "length_mm": batch.length_mm[keep].tolist(),
            "seq": batch.seq[keep].tolist(),
            "status": batch.status[keep].tolist(),
        }
        self._put("samples", to_json(body))

    def _put(self, kind: str, payload: bytes) -> None:
        pub = self._publishers.get(kind)
        if pub is None:
            self._counters.not_connected += 1
            return
        t0 = time.monotonic()
        try:
            pub.put(payload)
        except zenoh.ZError as err:
            c = self._counters
            c.put_errors += 1
            if c.put_errors == 1 or c.put_errors % 100 == 0:
                log.warning("zenoh: put on %s failed (%d so far): %s", TOPICS[kind], c.put_errors, zenoh_message(err))
            return
        took = time.monotonic() - t0
        c = self._counters
        c.published[TOPICS[kind]] += 1
        c.max_put_ms = max(c.max_put_ms, took * 1000.0)
        if took > self.slow_put_s:
            c.slow_puts += 1
            log.warning("zenoh: a put on %s took %.2f s (a subscriber is not reading)", TOPICS[kind], took)

    def bind_control(self, choose: Callable[[Any], None]) -> None:
        """Where a choice of the next plan put on ``control/next_plan`` goes (the daemon's analysis)."""
        self._control = choose

    def _on_control(self, sample: zenoh.Sample) -> None:
        """``{"plan": NAME}``, ``{"plan": null}``, the name (bare or a JSON string) or ``null``: handed on (the
        analysis checks the name), at most CONTROL_BURST at once and CONTROL_RATE_HZ a second after that;
        anything else is refused here with one reason.  Refusals and drops are each logged at most once every
        ``CONTROL_LOG_S`` seconds (with the count since), so that a flood makes no more lines than a few puts."""
        name, why = parse_control(sample.payload.to_bytes())
        now = time.monotonic()
        if why is not None:
            self._counters.controls_refused += 1
            self._refused_since_log += 1
            if now >= self._refusal_log_at:
                log.warning("zenoh: %s: refused: %s (%d refused since the last such line)", CONTROL_NEXT_PLAN, why,
                            self._refused_since_log)
                self._refused_since_log = 0
                self._refusal_log_at = now + CONTROL_LOG_S
            return
        self._tokens = min(float(CONTROL_BURST), self._tokens + (now - self._tokens_at) * CONTROL_RATE_HZ)
        self._tokens_at = now
        if self._tokens < 1.0:
            self._counters.controls_dropped += 1
            self._dropped_since_log += 1
            if now >= self._drop_log_at:
                self._log_dropped()
                self._drop_log_at = now + CONTROL_LOG_S
            return
        self._tokens -= 1.0
        self._counters.controls += 1
        log.info("zenoh: %s: %r", CONTROL_NEXT_PLAN, name)
        if self._control is not None:
            self._control(name)

    def _log_dropped(self) -> None:
        log.warning("zenoh: %s: a flood: %d choices dropped since the last such line (%d dropped in all; at most "
                    "%d at once and %g a second are taken)", CONTROL_NEXT_PLAN, self._dropped_since_log,
                    self._counters.controls_dropped, CONTROL_BURST, CONTROL_RATE_HZ)
        self._dropped_since_log = 0

    def stats(self) -> ZenohStats:
        """Counters for the status: connection, peers, what went out, what could not."""
        c = self._counters
        out: ZenohStats = {
            "connected": self._session is not None,
            "open_error": self._open_error,
            "published": dict(c.published),
            "put_errors": c.put_errors,
            "not_connected": c.not_connected,
            "slow_puts": c.slow_puts,
            "max_put_ms": round(c.max_put_ms, 3),
            "queries": c.queries,
            "query_errors": c.query_errors,
            "skipped": c.skipped,
            "controls": c.controls,
            "controls_refused": c.controls_refused,
            "controls_dropped": c.controls_dropped,
            "history": {k: len(v) for k, v in self._history.items()},
            "history_controls": len(self._control_history),
        }
        session = self._session
        if session is not None:
            with contextlib.suppress(zenoh.ZError):
                info = session.info
                out["zid"] = str(info.zid())
                links = {"peer": 0, "client": 0, "router": 0}  # sessions connected to this one, by kind
                for tr in info.transports():
                    what = str(tr.whatami).lower()
                    links[what] = links.get(what, 0) + 1
                out["links"] = links
        return out

    # ------------------------------------------------------------------ queryables

    def _on_last(self, query: zenoh.Query) -> None:
        self._counters.queries += 1
        try:
            for kind in LAST_TOPICS:
                key = f"{self.prefix}/last/{kind}"
                if not query.key_expr.intersects(key):
                    continue
                with self._lock:
                    payload = self._last.get(kind)
                if payload is not None:
                    query.reply(key, payload, encoding=zenoh.Encoding.APPLICATION_JSON)
        except zenoh.ZError as err:  # the querier went away, or we are closing
            self._counters.query_errors += 1
            log.debug("zenoh: reply to %s failed: %s", query.selector, zenoh_message(err))

    def _on_history(self, query: zenoh.Query) -> None:
        self._counters.queries += 1
        try:
            try:
                since_us, limit = self._history_params(_params(query))
            except ValueError as err:
                self._counters.query_errors += 1
                reply: QueryError = {"schema_version": SCHEMA_VERSION, "kind": "error", "error": str(err)}
                query.reply_err(to_json(reply), encoding=zenoh.Encoding.APPLICATION_JSON)
                return
            for kind in HISTORY_TOPICS:
                key = f"{self.prefix}/history/{kind}"
                if query.key_expr.intersects(key):
                    query.reply(
                        key, self.history_payload(kind, since_us, limit), encoding=zenoh.Encoding.APPLICATION_JSON
                    )
        except zenoh.ZError as err:
            self._counters.query_errors += 1
            log.debug("zenoh: reply to %s failed: %s", query.selector, zenoh_message(err))

    @staticmethod
    def _history_params(params: Mapping[str, str]) -> tuple[int | None, int]:
        unknown = sorted(set(params) - {"since", "limit"})
        if unknown:
            raise ValueError(f"history: unknown parameter {unknown[0]!r} (since, limit)")
        since = params.get("since") or None
        since_us = None
        if since is not None:
            try:
                since_us = parse_time_us(since)
            except ValueError as err:
                raise ValueError(f"history: since: {err}") from err
        limit_text = params.get("limit") or str(HISTORY_LIMIT)
        try:
            limit = int(limit_text)
        except ValueError:
            raise ValueError(f"history: limit: {limit_text!r} is not a whole number") from None
        if not 1 <= limit <= HISTORY_LIMIT_MAX:
            raise ValueError(f"history: limit: {limit} is not between 1 and {HISTORY_LIMIT_MAX}")
        return since_us, limit

    def history_payload(self, kind: HistoryTopic, since_us: int | None = None, limit: int = HISTORY_LIMIT) -> bytes:
        """The ``history/<kind>`` reply: results after ``since_us``, oldest first (see the module doc)."""
        with self._lock:
            records = list(self._history[kind])
            if kind == "event" and self._control_history:
                records = sorted([*records, *self._control_history], key=lambda r: r[0])
        if since_us is None:
            chosen, more = records[-limit:], len(records) > limit
        else:
            after = [r for r in records if r[0] > since_us]
            chosen, more = after[:limit], len(after) > limit
        reply: HistoryReply = {"schema_version": SCHEMA_VERSION, "kind": "history", "topic": kind,
                               "machine_id": self.machine, "count": len(chosen), "more": more, "results": []}
        empty = to_json(reply)  # ...,"results":[]}: the payloads go in as they were sent
        return empty[:-2] + b",".join(p for _, p in chosen) + b"]}"

    def _load_history(self, loader: Callable[[], Iterable[Mapping[str, Any]]]) -> None:
        t0 = time.monotonic()
        n = 0
        try:
            for msg in loader():
                kind = msg.get("kind")
                if kind not in self._history:
                    continue
                body = dict(msg)  # as recorded, with the version it was recorded with (older records lack it)
                body.setdefault("schema_version", SCHEMA_VERSION)
                body.setdefault("machine_id", self.machine)
                payload = to_json(body)
                self._history_for(body).append((_record_time(body), payload))
                n += 1
        except Exception as err:  # a damaged recording must not keep the bus from starting
            log.warning("zenoh: history loader failed after %d results: %s", n, err)
        for dq in [*self._history.values(), self._control_history]:  # ordered by time, whatever the loader's order
            ordered = sorted(dq, key=lambda r: r[0])
            dq.clear()
            dq.extend(ordered)
        for kind, dq in self._history.items():
            if dq:
                self._last[kind] = dq[-1][1]
        log.info("zenoh: history seeded with %d results in %.2f s", n, time.monotonic() - t0)

    # ------------------------------------------------------------------ stop

    def stop(self) -> None:
        """Withdraw the token, close the session within ``close_timeout_s``; safe to call twice."""
        if self._dropped_since_log and not self._stopping.is_set():  # the end of a flood no line has told yet
            self._log_dropped()
        self._stopping.set()
        if self._opener is not None:
            self._opener.join(min(0.5, self.close_timeout_s))  # it only waits on _stopping, or is mid-open
        with self._lock:
            session, token = self._session, self._token
            self._session, self._token = None, None
            self._publishers = {}
            self._keep = []
        if session is None:
            self._closed.set()
            return
        if token is not None:
            try:
                token.undeclare()  # first: healthy peers see the daemon go even if the close hangs
            except zenoh.ZError as err:
                log.debug("zenoh: undeclaring the liveliness token: %s", zenoh_message(err))
        t0 = time.monotonic()
        self._closer = threading.Thread(
            target=self._close, args=(session,), name=f"zenoh-close-{self.machine}", daemon=True
        )
        self._closer.start()
        self._closer.join(self.close_timeout_s)
        if self._closer.is_alive():
            log.warning(
                "zenoh: the session did not close within %.1f s (a peer is not reading); "
                "leaving it to finish in the background",
                self.close_timeout_s,
            )
        else:
            log.debug("zenoh: session closed in %.3f s", time.monotonic() - t0)

    def _close(self, session: zenoh.Session) -> None:
        t0 = time.monotonic()
        try:
            session.close()
        except zenoh.ZError as err:
            log.warning("zenoh: closing the session after %.1f s: %s", time.monotonic() - t0, zenoh_message(err))
        finally:
            self._closed.set()

    def wait_closed(self, timeout: float | None = None) -> bool:
        """Wait for a close left in the background by :meth:`stop`; True once it is done."""
        return self._closed.wait(timeout)


def _record_time(body: Mapping[str, Any]) -> int:
    t = body.get("t_wall")
    if isinstance(t, str | int | float):
        with contextlib.suppress(ValueError):
            return parse_time_us(t)
    return parse_time_us(time.time())


__all__ = [
    "DEFAULT_CONNECT",
    "DEFAULT_LISTEN",
    "HISTORY_LIMIT",
    "HISTORY_LIMIT_MAX",
    "SCHEMA_VERSION",
    "TOPICS",
    "ZENOH_SCHEMES",
    "BusConfigError",
    "BusError",
    "ZenohBus",
    "ZenohConfig",
    "check_endpoints",
    "check_machine",
    "parse_time_us",
    "zenoh_config",
    "zenoh_message",
]
