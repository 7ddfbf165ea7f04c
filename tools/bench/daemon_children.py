"""The processes the daemon bench (:mod:`.bench_daemon`) starts beside the daemon, and its handles on them: the
latency probe (a Zenoh subscriber), the bare baseline reader, ``ballbar run`` with its Python threads' names
copied to their kernel names, each driven as a :class:`Child` through one JSON line per thing it saw.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import IO, Any

PORTS = range(7700, 7800)


# ----------------------------------------------------------------------------- helper processes


def _stop_on_signals(stop: threading.Event) -> None:
    def handler(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def _stop_on_stdin_eof(stop: threading.Event) -> None:
    def watch() -> None:
        with contextlib.suppress(OSError, ValueError):
            while os.read(sys.stdin.fileno(), 4096):
                pass
        stop.set()

    threading.Thread(target=watch, name="stdin-eof", daemon=True).start()


def _say(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj, separators=(",", ":")) + "\n")
    sys.stdout.flush()


def subscriber_main(endpoint: str, machine: str) -> int:
    """The latency probe: a Zenoh client of the daemon, one JSON line per result, status and event.

    The receipt time is taken first thing in Zenoh's callback; parsing happens on the main thread.
    """
    import zenoh

    from ballbar.daemon.bus import ZenohConfig

    stop = threading.Event()
    _stop_on_signals(stop)
    _stop_on_stdin_eof(stop)
    inbox: queue.SimpleQueue[tuple[float, str, bytes]] = queue.SimpleQueue()

    def on_sample(sample: zenoh.Sample) -> None:
        inbox.put((time.monotonic(), str(sample.key_expr), sample.payload.to_bytes()))

    session = zenoh.open(ZenohConfig(mode="client", connect=[endpoint]).to_zenoh_config())
    subs = [session.declare_subscriber(f"ballbar/{machine}/{k}", on_sample) for k in ("result/*", "status", "event")]
    _say({"k": "ready"})
    try:
        while not stop.is_set():
            try:
                rx, key, payload = inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                msg = json.loads(payload)
            except ValueError:
                continue
            kind = msg.get("kind")
            if kind in ("circle", "test"):
                _say({
                    "k": kind, "rx": rx, "last_sample_t_host": msg.get("last_sample_t_host"),
                    "t_host": msg.get("t_host"), "latency_ms": msg.get("latency_ms"),
                    "test_id": msg.get("test_id"), "direction": msg.get("direction"), "bytes": len(payload),
                })
            elif kind == "status":
                outputs = msg.get("outputs") or {}
                _say({
                    "k": "status", "rx": rx, "samples": msg.get("samples"), "lost_samples": msg.get("lost_samples"),
                    "sample_rate_hz": msg.get("sample_rate_hz"), "queues": msg.get("queues") or {},
                    "fit_latency_ms": (msg.get("analysis") or {}).get("fit_latency_ms"),
                    "mcap": {k: v for k, v in (outputs.get("mcap") or {}).items()
                             if k in ("samples_lost", "messages_lost", "write_errors", "pending_samples")},
                    "zenoh": {k: v for k, v in (outputs.get("zenoh") or {}).items()
                              if k in ("slow_puts", "put_errors", "skipped", "history")},
                    "rerun_server": {k: v for k, v in ((outputs.get("rerun") or {}).get("server") or {}).items()
                                     if k in ("restarts", "rss_kills")},
                })
            elif kind == "event":
                _say({"k": "event", "rx": rx, "event": msg.get("event"), "key": key})
    finally:
        for sub in subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        with contextlib.suppress(Exception):
            session.close()
    return 0


def reader_main(kind: str, target: str) -> int:
    """The baseline: read the device's pty and decode its frames, nothing else.

    ``raw``: pyserial ``read`` with a 20 ms timeout (the daemon's batching period) and the
    protocol's :class:`~ballbar.protocol.BinaryDecoder`; ``source``: the daemon's own
    ``open_source(url)`` and ``read``, with no outputs.  On stop: one line with the counts.
    """
    stop = threading.Event()
    _stop_on_signals(stop)
    _stop_on_stdin_eof(stop)
    samples = nbytes = 0
    if kind == "raw":
        import serial

        from ballbar.protocol import BinaryDecoder

        port = serial.serial_for_url(target, baudrate=2_000_000, timeout=0.02, exclusive=True)
        decoder = BinaryDecoder()
        _say({"k": "ready"})
        try:
            while not stop.is_set():
                data = port.read(1 << 16)
                if data:
                    nbytes += len(data)
                    samples += len(decoder.feed(data))
        finally:
            port.close()
    else:
        from ballbar.daemon.sources import open_source

        src = open_source(target)
        _say({"k": "ready"})
        try:
            while not stop.is_set():
                batch = src.read(timeout=0.2)
                if batch is not None:
                    samples += len(batch)
            nbytes = int(src.stats().bytes_read)
        finally:
            src.close()
    _say({"k": "done", "samples": samples, "bytes": nbytes})
    return 0


def _comm_name(name: str) -> str:
    """A Python thread's name as a kernel ``comm`` (at most 15 bytes), its telling part kept."""
    name = name.replace("listener-", "L-").replace("ThreadPoolExecutor-", "pool-")
    m = re.fullmatch(r"Thread-\d+ \((.+)\)", name)
    if m:
        name = "T-" + m.group(1)
    return name.encode("utf-8", "replace")[:15].decode("utf-8", "ignore") or "thread"


def _set_comm(name: str) -> None:
    with contextlib.suppress(OSError), open("/proc/thread-self/comm", "w", encoding="utf-8") as fh:
        fh.write(_comm_name(name))


def daemon_main(argv: list[str]) -> int:
    """``ballbar run`` with each Python thread's name copied to its kernel name (for the per-thread table)."""
    boot = threading.Thread._bootstrap_inner  # type: ignore[attr-defined]

    def named_boot(self: threading.Thread) -> None:
        _set_comm(self.name)
        boot(self)

    threading.Thread._bootstrap_inner = named_boot  # type: ignore[attr-defined]
    _set_comm("main")
    from ballbar.daemon.cli import main

    return main(argv)


class Child:
    """A helper process that speaks JSON lines on stdout, read by a thread of ours."""

    def __init__(self, name: str, argv: list[str], stderr: IO[bytes] | int | None,
                 on_line: Callable[[dict[str, Any]], None] | None = None) -> None:
        self.name = name
        self.lines: list[dict[str, Any]] = []
        self._on_line = on_line
        self._cv = threading.Condition()
        self.proc = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=stderr)
        self._thread = threading.Thread(target=self._pump, name=f"bench-{name}", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for raw in self.proc.stdout:
            try:
                obj = json.loads(raw)
            except ValueError:
                continue
            if self._on_line is not None:
                self._on_line(obj)
            with self._cv:
                self.lines.append(obj)
                self._cv.notify_all()
        with self._cv:
            self._cv.notify_all()

    def wait_line(self, kind: str, timeout: float) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        with self._cv:
            while True:
                for obj in self.lines:
                    if obj.get("k") == kind:
                        return obj
                left = deadline - time.monotonic()
                if left <= 0 or (self.proc.poll() is not None and not self._thread.is_alive()):
                    raise RuntimeError(f"{self.name}: no {kind!r} line within {timeout:g} s "
                                       f"(exit code {self.proc.poll()})")
                self._cv.wait(min(left, 0.5))

    def stop(self, timeout: float = 10.0) -> int | None:
        """Close its stdin (its signal to finish), wait, kill it if it will not go."""
        if self.proc.stdin is not None:
            with contextlib.suppress(OSError):
                self.proc.stdin.close()
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout)
        self._thread.join(timeout)
        return self.proc.returncode


class Notify:
    """A ``NOTIFY_SOCKET`` for the daemon: when it said READY=1."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.25)

    def wait_ready(self, proc: subprocess.Popen[bytes], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with contextlib.suppress(TimeoutError, OSError):
                if b"READY=1" in self.sock.recv(4096).split(b"\n"):
                    return
            if proc.poll() is not None:
                raise RuntimeError(f"the daemon exited with code {proc.returncode} before READY=1")
        raise RuntimeError(f"the daemon did not send READY=1 within {timeout:g} s")

    def close(self) -> None:
        self.sock.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)


_ports_taken: set[int] = set()


def free_port() -> int:
    """A free TCP port on loopback within 7700-7799 (the bench's range)."""
    for port in PORTS:
        if port in _ports_taken:
            continue
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
        _ports_taken.add(port)
        return port
    raise RuntimeError(f"no free port in {PORTS.start}-{PORTS.stop - 1}")
