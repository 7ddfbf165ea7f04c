"""The serve mode's Rerun server in a child process, supervised; and the connect mode's prober.

Rerun's server accepts data from any client and keeps some of it outside its memory limit, so it runs in
its own process (``rerun --serve-grpc``), restarted when it exits, outgrows its cap or stops taking the
daemon's stream (:class:`ServerProcess`).  In connect mode a :class:`Prober` looks for the viewer over TCP.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from .. import procfs
from .options import ViewerConfigError, host_for_url

log = logging.getLogger(__name__)

def _tcp_listening(host: str, port: int, timeout: float) -> bool:
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return True
    except OSError:
        return False


def _sockets_of(pid: int) -> set[str]:
    """The sockets a process holds (``socket:[inode]``): its listener, and a socket per connection.

    46 us for the rerun server here, against 6.7 ms for reading ``/proc/net/tcp`` (the kernel walks
    every socket for it), once a second for months.
    """
    out: set[str] = set()
    d = f"/proc/{pid}/fd"
    try:
        fds = os.listdir(d)
    except OSError:
        return out
    for fd in fds:
        try:
            link = os.readlink(f"{d}/{fd}")
        except OSError:
            continue
        if link.startswith("socket:"):
            out.add(link)
    return out


def _port_free(bind: str, port: int) -> bool:
    """Whether ``bind:port`` can be listened on (SO_REUSEADDR, as the SDK's server does)."""
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((bind, port))
        except OSError:
            return False
    return True


class Prober:
    """Probes a viewer's address over TCP on its own thread (connect mode).

    ``up``: the last probe's answer; ``failures``: failed probes so far, so
    that the listener can tell that the viewer was gone at some moment since
    it made its sink (a restarted viewer needs a new sink).
    """

    def __init__(self, host: str, port: int, period_s: float) -> None:
        self.host, self.port, self.period_s = host, port, period_s
        self.up = False
        self.failures = 0
        self.probes = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="rerun-viewer-probe", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            ok = _tcp_listening(self.host, self.port, timeout=min(0.5, self.period_s))
            if not ok:
                self.failures += 1
            self.up = ok
            self.probes += 1
            self._stop.wait(self.period_s)

    def close(self, timeout: float = 0.6) -> None:
        self._stop.set()
        self._thread.join(timeout)


# Started through Python so that the server dies with the daemon even on kill -9: PR_SET_PDEATHSIG (1)
# survives the exec, and the parent check closes the window between fork and prctl.
_LAUNCHER = (
    "import ctypes,os,signal,sys\n"
    "ctypes.CDLL(None).prctl(1, signal.SIGKILL)\n"
    "if os.getppid() != int(sys.argv[1]): sys.exit(1)\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


def rerun_binary() -> str | None:
    """The ``rerun`` executable that rerun-sdk ships (its viewer and CLI), or None."""
    spec = importlib.util.find_spec("rerun_cli")
    if spec is None or spec.origin is None:
        return None
    exe = Path(spec.origin).parent / "rerun"
    return str(exe) if exe.is_file() and os.access(exe, os.X_OK) else None


def _rss_bytes(pid: int) -> int | None:
    try:
        return procfs.rss_bytes(pid)
    except (OSError, KeyError, ValueError):
        return None


class ServerProcess:
    """The serve mode's gRPC server: ``rerun --serve-grpc`` in a child process, supervised.

    Rerun's server accepts data from any client that reaches it (``WriteMessages``), and keeps
    blueprint and store-info messages outside its memory limit: a client can grow it without bound
    (checked with rerun 0.41: 200 MB of blueprints took a 32 MiB-limited server from 115 to 332 MB).
    In its own process, whatever clients push never touches the daemon's memory; this supervisor
    restarts the server when it exits and kills it when its resident memory passes ``rss_cap``
    (the daemon then sends the scene again).  A server that takes none of the daemon's own stream
    (a client flooding or wedging it; the viewer's health check sees its flush time out) is
    restarted on the viewer's :meth:`request_restart`: once the loopback socket's buffers are full
    (minutes of the daemon's stream), the daemon's gRPC client keeps all it cannot send in the
    daemon's memory until that connection ends (rerun 0.41: freed at once when the server is
    killed; swapping or disconnecting the sink instead blocks for as long as the server does).
    ``generation`` counts the starts: a new one needs a new sink.  It looks every ``period_s``
    while the server starts, or while its memory grows fast
    enough to reach half its headroom to the cap within ``IDLE_PERIOD_S``; else every
    ``IDLE_PERIOD_S``: four looks a second cost more than the rest of the viewer at the lowest
    sample rates.
    """

    IDLE_PERIOD_S = 1.0

    def __init__(self, bind: str, port: int, memory_limit: str, rss_cap: int, period_s: float = 0.25) -> None:
        exe = rerun_binary()
        if exe is None:
            raise ViewerConfigError("rerun.mode = \"serve\" needs the rerun binary of rerun-sdk (rerun_cli)")
        self.exe, self.bind, self.port = exe, bind, port
        self.memory_limit, self.rss_cap, self.period_s = memory_limit, rss_cap, period_s
        host = {"0.0.0.0": "127.0.0.1", "::": "::1"}.get(bind, bind)
        self.url = f"rerun+http://{host_for_url(host)}:{port}/proxy"  # where the daemon pushes
        self._probe = (host, port)
        self.generation = 0
        self.listening = False
        self.restarts = 0
        self.rss_kills = 0
        self.stall_kills = 0
        self.clients_ended = 0  # connections to the server (viewers, or clients pushing into it) that ended
        self._clients: set[str] = set()  # the server's sockets at the last look
        self._first_clients: set[str] = set()  # ... and at the first once listening (the probe's among them)
        self._restart_request: tuple[int, str] | None = None  # (generation, why), from the viewer's thread
        self.max_rss = 0
        self.last_rss = 0
        self._looked = 0.0  # when last_rss was read
        self._growth_bps = 0.0  # its growth since the look before (bytes/s)
        self.proc: subprocess.Popen[bytes] | None = None
        self._backoff = 0.5
        self._next_start = 0.0
        self._warned_busy = False
        self._stop = threading.Event()
        self._kick = threading.Event()  # wakes the supervisor: a restart requested, or close()
        self._thread = threading.Thread(target=self._run, name="rerun-server", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        # Popen from this thread, which lives as long as the server may: PR_SET_PDEATHSIG follows the thread.
        while not self._stop.is_set():
            try:
                self._step(time.monotonic())
            except Exception:  # the supervisor must outlive any surprise
                log.exception("rerun server: supervisor error")
            self._kick.wait(self.IDLE_PERIOD_S if self._calm() else self.period_s)
            self._kick.clear()
        self._terminate()

    def request_restart(self, generation: int, why: str) -> None:
        """Restart the server of start ``generation`` (if it is still the one running), at once; any thread."""
        self._restart_request = (generation, why)
        self._kick.set()

    def _calm(self) -> bool:
        """Listening, and at the growth of the last look not within half its headroom of the cap in IDLE_PERIOD_S."""
        return (self.listening and self.proc is not None
                and self._growth_bps * self.IDLE_PERIOD_S < 0.5 * (self.rss_cap - self.last_rss))

    def _step(self, now: float) -> None:
        proc = self.proc
        if proc is not None and proc.poll() is not None:
            log.warning("rerun server (pid %d) exited with code %s; restarting", proc.pid, proc.returncode)
            self.proc, self.listening = None, False
            self.restarts += 1
            self._next_start = now + self._backoff
            self._backoff = min(2 * self._backoff, 30.0)
            return
        if proc is None:
            if now >= self._next_start:
                self._start(now)
            return
        request, self._restart_request = self._restart_request, None
        if request is not None and request[0] == self.generation:
            self.stall_kills += 1
            self._restart(now, request[1])
            return
        rss = _rss_bytes(proc.pid) or 0
        if self.last_rss and now > self._looked:
            self._growth_bps = max(0.0, (rss - self.last_rss) / (now - self._looked))
        self.last_rss, self._looked = rss, now
        self.max_rss = max(self.max_rss, rss)
        if rss > self.rss_cap:
            self.rss_kills += 1
            self._restart(now, f"{rss / 2**20:.0f} MiB resident, over its {self.rss_cap / 2**20:.0f} MiB cap "
                               "(a client pushed data into it)")
            return
        if not self.listening and _tcp_listening(*self._probe, timeout=0.2):
            self.listening = True
            self._backoff = 0.5
            self._clients = self._first_clients = _sockets_of(proc.pid)  # its own, and the probe's
        elif self.listening:
            clients = _sockets_of(proc.pid)
            self.clients_ended += len(self._clients - clients - self._first_clients)
            self._clients = clients

    def _restart(self, now: float, why: str) -> None:
        log.warning("rerun server: %s; restarting it, and sending viewers the scene again", why)
        self._terminate(grace_s=0.0)
        self.restarts += 1
        self._next_start = now

    def _start(self, now: float) -> None:
        if not _port_free(self.bind, self.port):
            if not self._warned_busy:
                log.warning("rerun viewer: %s:%d is in use; retrying", self.bind, self.port)
                self._warned_busy = True
            self._next_start = now + 2.0
            return
        self._warned_busy = False
        args = [sys.executable, "-I", "-S", "-c", _LAUNCHER, str(os.getpid()), self.exe, "--serve-grpc",
                "--bind", self.bind, "--port", str(self.port), "--server-memory-limit", self.memory_limit]
        env = {k: v for k, v in os.environ.items() if not k.startswith(("NOTIFY_SOCKET", "WATCHDOG_"))}
        env.setdefault("RUST_LOG", "warn")
        # Its own session: a terminal's Ctrl-C, or a signal to the daemon's process group, must not end the server
        # before the daemon has flushed its stream to it (the SDK then logged two ERROR lines at every clean stop:
        # "Write messages call failed: transport error", "Failed to flush previous sink"); the daemon ends it.
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, env=env, close_fds=True, start_new_session=True)
        self.generation += 1
        self.listening = False
        log.debug("rerun server started (pid %d) on %s:%d", self.proc.pid, self.bind, self.port)

    def _terminate(self, grace_s: float = 1.0) -> None:
        proc, self.proc = self.proc, None
        self.listening = False
        if proc is None or proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(signal.SIGTERM if grace_s > 0 else signal.SIGKILL)
        try:
            proc.wait(grace_s if grace_s > 0 else 5.0)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                proc.kill()
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(5.0)

    def stats(self) -> dict[str, Any]:
        return {
            "pid": self.proc.pid if self.proc is not None else None,
            "listening": self.listening,
            "rss_mb": round(self.last_rss / 2**20, 1),
            "max_rss_mb": round(self.max_rss / 2**20, 1),
            "rss_cap_mb": round(self.rss_cap / 2**20, 1),
            "restarts": self.restarts,
            "rss_kills": self.rss_kills,
            "stall_kills": self.stall_kills,
            "clients_ended": self.clients_ended,
        }

    def close(self, timeout: float = 3.0) -> None:
        self._stop.set()
        self._kick.set()
        self._thread.join(timeout)

__all__ = ["Prober", "ServerProcess", "rerun_binary"]
