"""Print what ballbar daemons publish on Zenoh, one JSON object per line.

::

    python -m ballbar.tools.subscribe                      # every machine's results, as they come
    python -m ballbar.tools.subscribe --machine mill-3 --history --topic result --topic event
    python -m ballbar.tools.subscribe --connect tcp/10.0.0.5:7447 --topic all
    python -m ballbar.tools.subscribe --machine mill-3 --history --topic alert   # the monitor's alerts

Each line is a payload exactly as published (``kind`` says what it is;
``machine_id`` whose).  With ``--history`` the results the daemons still hold
come first (oldest first, ``--since`` bounding them), then live ones, without
duplicates: the pattern for a plant service that starts late.  On a terminal
(``--format text``) alerts and test verdicts are printed as readable lines.  ``--alive``
adds a line ``{"kind": "alive", "machine_id": ..., "alive": true|false}`` when
a daemon appears or goes.

By default the tool is a Zenoh client of ``tcp/127.0.0.1:7447``, where a
daemon with the default settings listens.  Services start in any order: until
the daemon (or the plant's router) is there, it says once on stderr that it is
waiting and retries with backoff (0.5 s doubling to 5 s); ``--no-wait`` gives
up at once instead.  Once connected, Zenoh reconnects by itself when the
daemon or router restarts.  SIGINT and SIGTERM are answered at once, even while
Zenoh waits on a peer that does not answer (a handshake, a history query, a
close); what was printed is flushed before the exit.  Exit codes: 0 done (SIGINT, SIGTERM, ``--count``
reached, or ``--timeout`` without ``--count``); 1 no connection (``--no-wait``,
or none within ``--timeout``), or ``--timeout`` before ``--count`` lines; 2 a
usage error.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from types import FrameType
from typing import Any, TypeVar

import zenoh

from ballbar.daemon.bus import (
    DEFAULT_CONNECT,
    HISTORY_LIMIT_MAX,
    HISTORY_TOPICS,
    BusConfigError,
    ZenohConfig,
    parse_time_us,
    zenoh_message,
)

log = logging.getLogger("ballbar.subscribe")
T = TypeVar("T")

TOPIC_KEYS = {
    "result": ("result/*",),
    "circle": ("result/circle",),
    "test": ("result/test",),
    "set": ("result/set",),
    "event": ("event",),
    "status": ("status",),
    "config": ("config",),
    "samples": ("samples",),
    "alert": ("alert",),
    "all": ("**",),
}
HISTORY_FOR = {"result": ("circle", "test", "set"), "circle": ("circle",), "test": ("test",), "set": ("set",),
               "event": ("event",), "alert": ("alert",), "all": HISTORY_TOPICS}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(2, f"{self.prog}: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="ballbar-subscribe", description="Print what ballbar daemons publish, one JSON object a line.")
    p.add_argument("--machine", default="*", help="machine_id to follow (default: * = every machine)")
    p.add_argument(
        "--topic",
        action="append",
        choices=sorted(TOPIC_KEYS),
        help="what to print (repeatable; default: result = circle, test and set results)",
    )
    p.add_argument("--history", action="store_true", help="first the results the daemons still hold")
    p.add_argument("--since", help="with --history: only results after this time (ISO 8601 or Unix seconds)")
    p.add_argument(
        "--limit", type=int, default=HISTORY_LIMIT_MAX, help="with --history: at most this many per machine and topic"
    )
    p.add_argument("--alive", action="store_true", help="also print daemons appearing and going (liveliness)")
    p.add_argument("--mode", choices=("client", "peer"), default="client", help="Zenoh mode (default: client)")
    p.add_argument(
        "--connect",
        action="append",
        metavar="ENDPOINT",
        help=f"Zenoh endpoint to connect to (repeatable; default {DEFAULT_CONNECT[0]})",
    )
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="Zenoh endpoint to listen on (peer mode)")
    p.add_argument("--config", metavar="FILE", help="a Zenoh JSON5 config file (TLS, access control)")
    p.add_argument("--no-wait", action="store_true",
                   help="exit 1 at once when nothing answers at the endpoint (default: wait and retry)")
    p.add_argument("--count", type=int, help="exit after printing this many lines")
    p.add_argument("--timeout", type=float, help="exit after this many seconds")
    p.add_argument("--query-timeout", type=float, default=5.0, help="seconds to wait for history replies")
    p.add_argument("--format", choices=("auto", "json", "text"), default="auto",
                   help="json: each payload as one JSON line; text: alerts (and verdicts of test results) as "
                   "readable lines, the rest as JSON; auto (default): text on a terminal, else json")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more logging on stderr")
    return p


def text_line(obj: dict[str, Any]) -> str:
    """A readable line for an alert or a test result with a verdict; JSON for anything else."""
    kind = obj.get("kind")
    if kind == "alert":
        level = "CLEARED" if obj.get("cleared") else str(obj.get("state", "")).upper()
        return f"{obj.get('t_wall')} ALERT {level:8} {obj.get('message', '')}"
    verdict = obj.get("verdict")
    if kind == "set" and isinstance(verdict, dict):
        return f"{obj.get('t_wall')} SET   {obj.get('set_id')}: {verdict.get('summary', '')}"
    if kind == "test" and isinstance(verdict, dict) and verdict.get("limits"):
        return f"{obj.get('t_wall')} TEST  {obj.get('test_id')}: {verdict.get('summary', '')}"
    return json.dumps(obj, separators=(",", ":"))


def _identity(obj: dict[str, Any]) -> tuple[Any, ...]:
    return (obj.get("kind"), obj.get("machine_id"), obj.get("test_id"), obj.get("t_wall"), obj.get("direction"),
            obj.get("event"))


class _Printer:
    def __init__(self, count: int | None, text: bool = False) -> None:
        self.count = count
        self.text = text
        self.printed = 0
        self.seen: set[tuple[Any, ...]] = set()

    def emit(self, obj: dict[str, Any], dedupe: bool = False) -> bool:
        """Print one line; False once ``count`` lines are out."""
        if dedupe:
            ident = _identity(obj)
            if ident in self.seen:
                return True
            self.seen.add(ident)
        sys.stdout.write((text_line(obj) if self.text else json.dumps(obj, separators=(",", ":"))) + "\n")
        sys.stdout.flush()
        self.printed += 1
        return self.count is None or self.printed < self.count


def _history(
    session: zenoh.Session, machine: str, kinds: Sequence[str], since: str | None, limit: int, timeout: float
) -> list[dict[str, Any]]:
    """The results the daemons hold, oldest first: the newest ``limit`` per machine and topic, or,
    with ``since``, up to ``limit`` after it, asking page after page while a daemon says ``more``."""
    out: list[dict[str, Any]] = []
    answered = False
    for kind in kinds:
        todo: list[tuple[str, str | None]] = [(machine, since)]
        got: dict[str, int] = {}
        while todo:
            m, start = todo.pop()
            params = f"limit={min(limit, HISTORY_LIMIT_MAX)}" + (f";since={start}" if start else "")
            for reply in session.get(f"ballbar/{m}/history/{kind}?{params}", timeout=timeout):
                if reply.ok is None:
                    err = reply.err
                    log.warning("history %s: %s", kind, err.payload.to_string() if err is not None else "no reply")
                    continue
                answered = True
                doc = json.loads(reply.ok.payload.to_bytes())
                who = str(doc.get("machine_id", m))
                results = list(doc.get("results") or [])[: limit - got.get(who, 0)]
                got[who] = got.get(who, 0) + len(results)
                out.extend(results)
                if start is not None and doc.get("more") and results and got[who] < limit:
                    todo.append((who, str(results[-1]["t_wall"])))
    if not answered:
        log.warning("no daemon answered on ballbar/%s/history", machine)
    out.sort(key=lambda r: _time_key(r.get("t_wall")))
    return out


def _time_key(t: Any) -> int:
    try:
        return parse_time_us(t) if isinstance(t, str | int | float) else 0
    except ValueError:
        return 0


def main(argv: Sequence[str] | None = None) -> int:
    pending: list[threading.Thread] = []
    code = _main(argv, pending)
    if any(th.is_alive() for th in pending):
        # A Zenoh call that did not end (a peer that does not answer): the interpreter's exit would wait for it,
        # or deadlock with it as the session's objects are freed. Everything printed is out: end here.
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)
    return code


def _in_background(
    fn: Callable[[], T], pending: list[threading.Thread], name: str, stop: threading.Event | None = None,
    timeout: float | None = None,
) -> tuple[bool, T | None]:
    """``fn()`` in a thread, waited for until it returns (True, its value; its exception raised here), ``stop`` is
    set or ``timeout`` passes (False, None; the thread is left in ``pending``).  Python runs signal handlers only in
    the main thread between bytecodes: a ``zenoh.open`` waiting on a handshake held SIGTERM for ten seconds."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as err:  # raised again in the caller's thread
            box["error"] = err

    th = threading.Thread(target=run, name=name, daemon=True)
    th.start()
    end = None if timeout is None else time.monotonic() + timeout
    while th.is_alive():
        if (stop is not None and stop.is_set()) or (end is not None and time.monotonic() >= end):
            pending.append(th)
            return False, None
        th.join(0.05)
    if "error" in box:
        raise box["error"]
    return True, box.get("value")


def _main(argv: Sequence[str] | None, pending: list[threading.Thread]) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2), stream=sys.stderr, format="%(name)s: %(message)s"
    )
    if args.count is not None and args.count < 1:
        print("ballbar-subscribe: --count must be at least 1", file=sys.stderr)
        return 2
    if args.limit < 1:
        print("ballbar-subscribe: --limit must be at least 1", file=sys.stderr)
        return 2
    if args.since:
        try:
            parse_time_us(args.since)
        except ValueError as err:
            print(f"ballbar-subscribe: --since: {err}", file=sys.stderr)
            return 2
    topics = args.topic or ["result"]
    zc = ZenohConfig(
        mode=args.mode,
        connect=args.connect if args.connect else (None if args.config else list(DEFAULT_CONNECT)),
        listen=args.listen if args.listen else ([] if args.mode == "peer" and not args.config else None),
        config_file=args.config,
    )
    try:
        zconfig = zc.to_zenoh_config()
    except BusConfigError as err:
        print(f"ballbar-subscribe: {err}", file=sys.stderr)
        return 2
    deadline = time.monotonic() + args.timeout if args.timeout is not None else None
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    opened = _open(zconfig, zc.describe(), stop, deadline, pending, wait=not args.no_wait)
    if opened is None:
        for s, handler in previous.items():
            signal.signal(s, handler)
        return 0 if stop.is_set() else 1
    session = opened
    inbox: queue.SimpleQueue[dict[str, Any]] = queue.SimpleQueue()

    keys = sorted({k for t in topics for k in TOPIC_KEYS[t]})
    wanted = [zenoh.KeyExpr(f"ballbar/{args.machine}/{k}") for k in keys]

    def on_sample(sample: zenoh.Sample) -> None:
        if len(wanted) > 1 and not any(w.includes(sample.key_expr) for w in wanted):
            return  # (one subscriber on the machine's keys: what else is put there)
        try:
            obj = json.loads(sample.payload.to_bytes())
        except (ValueError, RecursionError):  # a peer's put nested deeper than the parser recurses
            log.warning("%s: not JSON (%d bytes)", sample.key_expr, len(sample.payload))
            return
        inbox.put(obj if isinstance(obj, dict) else {"key": str(sample.key_expr), "value": obj})

    def on_alive(sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        inbox.put(
            {
                "kind": "alive",
                "machine_id": parts[1] if len(parts) > 2 else str(sample.key_expr),
                "alive": sample.kind == zenoh.SampleKind.PUT,
            }
        )

    code = 0
    subs: list[Any] = []
    printer = _Printer(args.count, args.format == "text" or (args.format == "auto" and sys.stdout.isatty()))
    try:
        # One subscriber, so one callback thread: Zenoh runs each subscriber's callbacks on a thread of its own,
        # and two subscribers' would interleave a daemon's puts out of their order (an alert before its test).
        subs.append(session.declare_subscriber(f"ballbar/{args.machine}/{keys[0] if len(keys) == 1 else '**'}",
                                               on_sample))
        if args.alive:
            subs.append(
                session.liveliness().declare_subscriber(f"ballbar/{args.machine}/alive", on_alive, history=True)
            )
        going = True
        dedupe = False
        if args.history:
            kinds = sorted({k for t in topics for k in HISTORY_FOR.get(t, ())})
            _, held = _in_background(
                lambda: _history(session, args.machine, kinds, args.since, args.limit, args.query_timeout),
                pending, "zenoh-history", stop=stop,
                timeout=None if deadline is None else max(0.0, deadline - time.monotonic()),
            )
            for obj in held or ():
                dedupe = True
                going = printer.emit(obj, dedupe=True)
                if not going or stop.is_set():
                    break
        while going and not stop.is_set():
            wait = 0.1
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                wait = min(wait, left)
            try:
                obj = inbox.get(timeout=wait)
            except queue.Empty:
                continue
            going = printer.emit(obj, dedupe=dedupe and obj.get("kind") in HISTORY_TOPICS)
        if args.count is not None and printer.printed < args.count and not stop.is_set():
            log.warning("%d of %d lines before the timeout", printer.printed, args.count)
            code = 1
        log.debug("%d subscriptions, %d lines", len(subs), printer.printed)
    except BrokenPipeError:  # piped into head: the reader is done; keep the interpreter's exit quiet
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    finally:
        _close(session, subs, pending)
        for s, handler in previous.items():
            signal.signal(s, handler)
    return code


def _open(
    config: zenoh.Config, where: str, stop: threading.Event, deadline: float | None, pending: list[threading.Thread],
    wait: bool = True,
) -> zenoh.Session | None:
    """The session; while nothing answers, say so once and retry with backoff (None: stopped or out of time)."""
    delay = 0.5
    said = False
    while True:
        try:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            done, session = _in_background(lambda: zenoh.open(config), pending, "zenoh-open", stop=stop, timeout=left)
            if done:
                return session
            if not stop.is_set():
                print(f"ballbar-subscribe: no connection within the timeout ({where})", file=sys.stderr)
            return None
        except zenoh.ZError as err:
            why = zenoh_message(err)
            if not wait:
                print(f"ballbar-subscribe: cannot connect ({where}): {why}", file=sys.stderr)
                return None
            if not said:
                print(f"ballbar-subscribe: waiting for a daemon or router ({where}): {why}; retrying",
                      file=sys.stderr, flush=True)
                said = True
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            print(f"ballbar-subscribe: no connection within the timeout ({where})", file=sys.stderr)
            return None
        if stop.wait(delay if left is None else min(delay, left)):
            return None
        delay = min(delay * 2, 5.0)
        if said:
            log.debug("retrying %s", where)


def _close(session: zenoh.Session, subs: list[Any], pending: list[threading.Thread], timeout: float = 2.0) -> None:
    """Undeclare and close, in the background: never hang on a peer that stopped reading or is gone."""

    def run() -> None:
        with contextlib.suppress(zenoh.ZError):
            for sub in subs:
                sub.undeclare()
            session.close()

    if not _in_background(run, pending, "zenoh-close", timeout=timeout)[0]:
        log.warning("the Zenoh session did not close within %.1f s; exiting without it", timeout)


if __name__ == "__main__":
    sys.exit(main())
