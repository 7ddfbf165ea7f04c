"""Soak: the real daemon for a long run, sped up, with a fault every minute.

``ballbar run`` reads the simulated ball-bar (:mod:`ballbar.tools.simdevice`) on a pty, sped
up, with its MCAP log, Zenoh (its own free port, decimated samples on) and its Rerun server
(its own free port) on, exactly as a service runs it.  Every ``--fault-every-s`` one fault is
injected, in turn:

``unplug``       the adapter goes for ``--unplug-s`` and comes back behind the same link
``reset``        the device restarts its sample counter and clock
``garbage``      ``--garbage-bytes`` junk bytes on the line
``freeze``       a subscriber of every topic (``ballbar-subscribe --topic all``) is stopped
                 (SIGSTOP) for ``--freeze-s``, then resumed, or killed and started again
                 (alternately)
``disk-full``    the file system of the state directory is filled for ``--disk-full-s``,
                 then the filler is removed
``restart``      the daemon is stopped (SIGTERM, exit 0 expected) and started again on the same
                 state directory and device
``kill``         the daemon is killed (``kill -9``) and started again: its last half second of
                 reading never reached the file, and the next start rewrites its cut file

The state directory is on a tmpfs of ``--disk-mb`` that the soak mounts (root only); where
it cannot mount one, the state directory is an ordinary directory and the disk-full spell is
skipped, as the report says.

Every ``--sample-s`` it records the daemon's resident memory, open descriptors and threads
(``/proc``), its Rerun server's resident memory, and from the daemon's status messages
(subscribed on Zenoh) the queue depths and drops and the loss counters; also the gaps
between ``WATCHDOG=1`` pings (the daemon gets a ``NOTIFY_SOCKET``).  The report gives each
figure's min, median and max, and its trend per minute over the samples taken just before
each fault (the previous fault over, the next not begun; after ``--warmup-min``): the trend
of a leak, not of the faults (Theil-Sen: the median of the slopes between every two samples).

At the end the device stops sending (a stall) and, once the daemon has read everything, the
samples are accounted for, over every life of the daemon (the restarts'), from what the recordings hold:

- device: taken = sent + lost while unplugged + stalled (the final stall's tail excepted);
- daemon: taken = samples in the MCAP files (preroll copies excepted) + samples the logger
  could not write (the disk-full spells: the files' ``log_gap`` counts) + samples counted lost
  (the ``lost`` events of every life's files, by cause); of these, lost across unplugs and
  restarts (``outage``, ``restart``: what each next start counted by the device's counter) =
  what the device lost while unplugged + what it sent that no life recorded (on the wire when
  the adapter went, in the port or the killed daemon's last reading at a restart); a
  ``restart`` fault that the next start did not count is a problem too;
- recording, the last life: received = its samples in the files + what its logger counted lost
  (= its files' ``log_gap`` counts) + samples in batches its queue dropped (must be none).

Exit code 0 when everything adds up and memory, descriptors, threads and queues are flat
(criteria in :func:`verdict`), 1 otherwise, 2 on a usage error.

Run (root, for the disk-full spell)::

    python -m ballbar.tools.bench.soak --minutes 30 --json soak.json
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import functools
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO, Any

import numpy as np

from ballbar.daemon import procfs
from ballbar.daemon.analysis_worker import WORKER, child_role
from ballbar.protocol.binary import FRAME_SIZE

log = logging.getLogger(__name__)

MACHINE = "soak"
FAULTS = ("unplug", "reset", "garbage", "freeze", "disk-full", "restart", "kill")
QUIET_BEFORE_S = 2.0  # the "quiet" sample is taken this long before each fault


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


# ----------------------------------------------------------------------------- the pieces


class Disk:
    """The state directory, on a tmpfs of its own when this process may mount one."""

    def __init__(self, path: Path, size_mb: int) -> None:
        self.path = path
        self.mounted = False
        self.why_not = ""
        path.mkdir(parents=True, exist_ok=True)
        proc = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m,mode=0700", "ballbar-soak", str(path)],
            capture_output=True, text=True, check=False,
        ) if shutil.which("mount") else None
        if proc is not None and proc.returncode == 0:
            self.mounted = True
        else:
            self.why_not = (proc.stderr.strip() if proc is not None else "") or "no mount command"
        self.filler = path / "soak-filler"

    def fill(self) -> int:
        """Fill the file system to the last byte; the bytes written."""
        block = bytes(1 << 20)
        n = 0
        with open(self.filler, "wb", buffering=0) as fh:
            for size in (1 << 20, 1 << 12, 1):
                while True:
                    try:
                        n += fh.write(block[:size])
                    except OSError as err:
                        if err.errno not in (errno.ENOSPC, errno.EDQUOT):
                            raise
                        break
        return n

    def release(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.filler.unlink()

    def free_mb(self) -> float:
        st = os.statvfs(self.path)
        return st.f_bavail * st.f_frsize / 2**20

    def close(self) -> None:
        self.release()
        if self.mounted:
            subprocess.run(["umount", "-l", str(self.path)], capture_output=True, check=False)
            self.mounted = False


class Notify:
    """The daemon's ``NOTIFY_SOCKET``: when READY came, and the gaps between watchdog pings."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.sock.settimeout(0.2)
        self.ready = threading.Event()
        self.last_watchdog: float | None = None
        self.max_watchdog_gap_s = 0.0
        self.watchdogs = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="soak-notify", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                text = self.sock.recv(4096).decode(errors="replace")
            except (TimeoutError, OSError):
                continue
            now = time.monotonic()
            for line in text.splitlines():
                if line == "READY=1":
                    self.ready.set()
                elif line == "WATCHDOG=1":
                    if self.last_watchdog is not None:
                        self.max_watchdog_gap_s = max(self.max_watchdog_gap_s, now - self.last_watchdog)
                    self.last_watchdog = now
                    self.watchdogs += 1

    def restarted(self) -> None:
        """A new daemon: READY awaited again; the watchdog's gaps count within each life, not across."""
        self.ready.clear()
        self.last_watchdog = None

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)


class Bus:
    """A Zenoh client of the daemon: its latest status, and its events and results counted."""

    def __init__(self, endpoint: str) -> None:
        import zenoh

        from ballbar.daemon.bus import ZenohConfig

        self._lock = threading.Lock()
        self.status: dict[str, Any] | None = None
        self.status_at = 0.0
        self.statuses = 0
        self.events: dict[str, int] = {}
        self.results: dict[str, int] = {}
        self.session = zenoh.open(ZenohConfig(mode="client", connect=[endpoint]).to_zenoh_config())
        self._subs = [
            self.session.declare_subscriber(f"ballbar/{MACHINE}/status", self._on_status),
            self.session.declare_subscriber(f"ballbar/{MACHINE}/event", self._on_event),
            self.session.declare_subscriber(f"ballbar/{MACHINE}/result/*", self._on_result),
        ]

    @staticmethod
    def _payload(sample: Any) -> dict[str, Any]:
        obj: dict[str, Any] = json.loads(sample.payload.to_bytes())
        return obj

    def _on_status(self, sample: Any) -> None:
        st = self._payload(sample)
        with self._lock:
            self.status, self.status_at = st, time.monotonic()
            self.statuses += 1

    def _on_event(self, sample: Any) -> None:
        name = str(self._payload(sample).get("event"))
        with self._lock:
            self.events[name] = self.events.get(name, 0) + 1

    def _on_result(self, sample: Any) -> None:
        kind = str(self._payload(sample).get("kind"))
        with self._lock:
            self.results[kind] = self.results.get(kind, 0) + 1

    def latest(self) -> tuple[dict[str, Any] | None, float]:
        with self._lock:
            return self.status, self.status_at

    def close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        with contextlib.suppress(Exception):
            self.session.close()


class Subscriber:
    """The subscriber that gets frozen: ``ballbar-subscribe --topic all``, its output to a file."""

    def __init__(self, endpoint: str, out: Path) -> None:
        self.endpoint = endpoint
        self.out = out
        self.proc: subprocess.Popen[bytes] | None = None
        self._fh: IO[bytes] | None = None
        self.frozen = False
        self.starts = 0

    def start(self) -> None:
        self._fh = open(self.out, "ab")  # noqa: SIM115 - held for the child's life
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.subscribe", "--machine", MACHINE, "--connect", self.endpoint,
             "--topic", "all"],
            stdout=self._fh, stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL,
        )
        self.starts += 1

    def freeze(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGSTOP)
            self.frozen = True

    def thaw(self, kill: bool) -> None:
        if self.proc is None:
            return
        if kill:
            self.stop()
            self.start()
        else:
            self.proc.send_signal(signal.SIGCONT)
        self.frozen = False

    def stop(self) -> None:
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.kill()  # also ends a stopped process
            self.proc.wait(10)
            self.proc = None
        if self._fh is not None:
            self._fh.close()
            self._fh = None

    def lines(self) -> int:
        with contextlib.suppress(OSError), open(self.out, "rb") as fh:
            return sum(1 for _ in fh)
        return 0


def proc_figures(pid: int) -> dict[str, float]:
    """Resident memory (MiB), descriptors, threads and CPU seconds of one process (``/proc``)."""
    st = procfs.status(pid)
    return {"rss_mb": procfs.kib(st["VmRSS"]) / 1024, "threads": int(st["Threads"]), "fds": len(procfs.fds(pid)),
            "cpu_s": procfs.cpu_seconds(pid)}


def children(pid: int) -> list[int]:
    try:
        return procfs.children(pid)
    except OSError:
        return []


# ----------------------------------------------------------------------------- figures


@dataclass
class Series:
    """Samples of the figures over time (minutes since the start)."""

    t_min: list[float] = field(default_factory=list)
    rows: list[dict[str, float]] = field(default_factory=list)
    quiet: list[int] = field(default_factory=list)  # indices of the samples taken just before a fault

    def add(self, t_min: float, row: dict[str, float], quiet: bool) -> None:
        if quiet:
            self.quiet.append(len(self.rows))
        self.t_min.append(t_min)
        self.rows.append(row)

    def summary(self, warmup_min: float) -> dict[str, dict[str, float | None]]:
        names = sorted({k for r in self.rows for k in r})
        t = np.array(self.t_min)
        out: dict[str, dict[str, float | None]] = {}
        for name in names:
            v = np.array([r.get(name, np.nan) for r in self.rows], float)
            ok = np.isfinite(v)
            if not ok.any():
                continue
            q = np.array([i for i in self.quiet if t[i] >= warmup_min and np.isfinite(v[i])], int)
            slope = theil_sen(t[q], v[q]) if q.size >= 3 else None
            out[name] = {
                "min": float(v[ok].min()), "median": float(np.median(v[ok])), "max": float(v[ok].max()),
                "first_quiet": float(v[q[0]]) if q.size else None, "last_quiet": float(v[q[-1]]) if q.size else None,
                "trend_per_min": slope, "quiet_samples": int(q.size),
            }
        return out


def status_figures(st: dict[str, Any]) -> dict[str, float]:
    """The figures of one status message worth following over time."""
    out: dict[str, float] = {
        "received": st.get("samples", 0),
        "lost_samples": st.get("lost_samples", 0),
    }
    for name, q in (st.get("queues") or {}).items():
        out[f"queue_{name}_depth"] = q.get("depth", 0)
        out[f"queue_{name}_dropped"] = q.get("dropped", 0)
    outputs = st.get("outputs") or {}
    mcap = outputs.get("mcap") or {}
    for key in ("samples_lost", "pending_samples", "held_messages", "messages_lost", "write_errors"):
        if key in mcap:
            out[f"mcap_{key}"] = mcap[key]
    z = outputs.get("zenoh") or {}
    for key in ("slow_puts", "put_errors", "skipped"):
        if key in z:
            out[f"zenoh_{key}"] = z[key]
    hist = z.get("history") or {}
    if hist:
        out["zenoh_history"] = sum(hist.values())
    rr = outputs.get("rerun") or {}
    server = rr.get("server") or {}
    for key in ("restarts", "rss_kills"):
        if key in server:
            out[f"rerun_server_{key}"] = server[key]
    return out


def theil_sen(t: np.ndarray, v: np.ndarray) -> float:
    """The median of the slopes between every two samples: a trend that one sample taken during a test's
    analysis (a queue's backlog, a heap not yet trimmed) does not move, as it moves a least-squares line."""
    i, j = np.triu_indices(t.size, 1)
    dt = t[j] - t[i]
    ok = dt > 0
    return float(np.median((v[j] - v[i])[ok] / dt[ok]))


QUEUE_DEPTH_MAX = 20  # batches: the MCAP and Rerun queues hold about 0.25 s of 20 ms batches by design (merged)
QUEUE_GROWTH_MAX = 5  # batches a queue's depth may grow by over the run


def verdict(summary: dict[str, dict[str, float | None]], minutes_span: float) -> list[str]:
    """What is not flat.  Over the quiet samples after the warm-up (the trend times the span): resident
    memory (the daemon's, and its analysis worker's) may grow by less than max(4 MiB, 3 % of its
    median), descriptors and threads by less than one; every queue's median depth, and its depth at
    the last quiet sample, is at most ``QUEUE_DEPTH_MAX`` items (the outputs that take batches merged,
    MCAP and Rerun, hold a quarter second of them, about 12 at 20 ms), and it grows by less than
    ``QUEUE_GROWTH_MAX``."""
    bad: list[str] = []

    def drift(name: str) -> float | None:
        s = summary.get(name)
        if s is None or s["trend_per_min"] is None:
            return None
        return float(s["trend_per_min"]) * minutes_span

    for name, who in (("rss_mb", "daemon"), ("worker_rss_mb", "analysis worker")):
        d = drift(name)
        rss = summary.get(name)
        if d is not None and rss is not None and d > max(4.0, 0.03 * float(rss["median"] or 0)):
            bad.append(f"{who} RSS grows {d:.1f} MiB over the run")
    for name in ("fds", "threads"):
        d = drift(name)
        s = summary.get(name)
        if d is not None and d >= 1.0 and s is not None and (s["last_quiet"] or 0) > (s["first_quiet"] or 0):
            bad.append(f"{name} grow {d:.1f} over the run ({s['first_quiet']:.0f} -> {s['last_quiet']:.0f})")
    for name, s in summary.items():
        if not (name.startswith("queue_") and name.endswith("_depth")):
            continue
        deep = (s["last_quiet"] or 0) > QUEUE_DEPTH_MAX or (s["median"] or 0) > QUEUE_DEPTH_MAX
        d = drift(name)
        if deep or (d is not None and d >= QUEUE_GROWTH_MAX):
            bad.append(f"{name}: median {s['median']:.0f}, last quiet {s['last_quiet']}, "
                       f"trend {0.0 if d is None else d:+.1f} over the run")
    return bad


# ----------------------------------------------------------------------------- the run


class Soak:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.workdir = Path(args.workdir or tempfile.mkdtemp(prefix="ballbar-soak-"))
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.series = Series()
        self.faults: list[dict[str, Any]] = []
        self.timers: list[tuple[float, Callable[[], None]]] = []
        self.t0 = 0.0
        self.stack = contextlib.ExitStack()

    def at(self, t: float, fn: Callable[[], None]) -> None:
        self.timers.append((t, fn))

    def note(self, what: str, **fields: Any) -> None:
        now = (time.monotonic() - self.t0) / 60.0
        self.faults.append({"t_min": round(now, 3), "fault": what, **fields})
        log.info("%6.2f min  %s %s", now, what, fields or "")

    def run(self) -> dict[str, Any]:
        with self.stack:
            return self._run()

    def _start(self) -> None:
        from ballbar.daemon.config import load
        from ballbar.tools.simdevice import DeviceProcess
        from ballbar.tools.simulate import simdevice_args

        a = self.args
        self.disk = Disk(self.workdir / "state", a.disk_mb)
        self.stack.callback(self.disk.close)
        self.zport, self.rport = free_port(), free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.zport}"
        conf = self.workdir / "soak.toml"
        conf.write_text(
            f'[daemon]\nmachine_id = "{MACHINE}"\nstate_dir = "{self.disk.path}"\n'
            f'[zenoh]\nlisten = ["{self.endpoint}"]\nsamples_hz = {a.samples_hz}\n'
            f'[rerun]\nmode = "serve"\nbind = "127.0.0.1"\nport = {self.rport}\n'
        )
        env = {k: v for k, v in os.environ.items() if not k.startswith("BALLBAR")}
        cfg = load(str(conf), list(a.sets), env=env)
        self.dev = DeviceProcess(*simdevice_args(cfg, a.speedup), "--wait", "--seed", str(a.seed))
        self.stack.callback(self.dev.close)
        self.notify = Notify(self.workdir / "notify.sock")
        self.stack.callback(self.notify.close)
        env.update(NOTIFY_SOCKET=self.notify.path, WATCHDOG_USEC="10000000", PYTHONUNBUFFERED="1")
        env.pop("WATCHDOG_PID", None)
        self.daemon_log = open(self.workdir / "daemon.log", "wb")  # noqa: SIM115 - closed by the stack
        self.stack.callback(self.daemon_log.close)
        self._cmd = [sys.executable, "-m", "ballbar.daemon.cli", "run", "--config", str(conf), "--source", self.dev.url,
                     *(x for item in a.sets for x in ("--set", item))]
        self._env = env
        self.lives: list[dict[str, Any]] = []
        self._spawn()
        self.stack.callback(self._kill_daemon)
        self.bus = Bus(self.endpoint)
        self.stack.callback(self.bus.close)
        self.sub = Subscriber(self.endpoint, self.workdir / "subscriber.jsonl")
        self.sub.start()
        self.stack.callback(self.sub.stop)
        self.dev.send("start")

    def _spawn(self) -> None:
        self.daemon = subprocess.Popen(self._cmd, env=self._env, stdin=subprocess.DEVNULL, stdout=self.daemon_log,
                                       stderr=subprocess.STDOUT)
        if not self.notify.ready.wait(60):
            raise RuntimeError(f"the daemon did not send READY=1 within 60 s (see {self.workdir / 'daemon.log'})")
        self.lives.append({"pid": self.daemon.pid,
                           "started_min": round((time.monotonic() - self.t0) / 60.0, 3) if self.t0 else 0.0})

    def _restart(self, sig: signal.Signals) -> dict[str, Any]:
        """Stop the daemon with ``sig`` and start it again; what it took."""
        t0 = time.monotonic()
        self.daemon.send_signal(sig)
        try:
            code = self.daemon.wait(30)
        except subprocess.TimeoutExpired:
            self.daemon.kill()
            code = self.daemon.wait(10)
            self.lives[-1]["stop_timeout"] = True
        self.lives[-1].update(ended_by=sig.name, exit_code=code, stop_s=round(time.monotonic() - t0, 3))
        self.notify.restarted()
        t1 = time.monotonic()
        self._spawn()
        now = time.monotonic()
        return {"exit_code": code, "down_s": round(now - t0, 3), "start_s": round(now - t1, 3)}

    def _kill_daemon(self) -> None:
        if self.daemon.poll() is None:
            self.daemon.kill()
            self.daemon.wait(10)

    def _fault(self, k: int) -> None:
        a = self.args
        faults = a.faults
        what = faults[k % len(faults)]
        now = time.monotonic()
        if what == "unplug":
            self.dev.send(f"unplug {a.unplug_s:g}")
            self.note(what, seconds=a.unplug_s)
        elif what == "reset":
            self.dev.send("reset")
            self.note(what)
        elif what == "garbage":
            self.dev.send(f"garbage {a.garbage_bytes}")
            self.note(what, bytes=a.garbage_bytes)
        elif what == "freeze":
            kill = (k // len(faults)) % 2 == 1
            self.sub.freeze()
            self.note(what, seconds=a.freeze_s, then="kill and restart" if kill else "resume")
            self.at(now + a.freeze_s, lambda: self.sub.thaw(kill))
        elif what == "disk-full":
            if not self.disk.mounted:
                self.note(what, skipped=f"no tmpfs of our own: {self.disk.why_not}")
                return
            n = self.disk.fill()
            self.note(what, seconds=a.disk_full_s, filled_mb=round(n / 2**20, 1), free_mb=self.disk.free_mb())
            self.at(now + a.disk_full_s, self.disk.release)
        elif what in ("restart", "kill"):
            self.note(what, **self._restart(signal.SIGTERM if what == "restart" else signal.SIGKILL))

    def _sample(self, quiet: bool) -> None:
        row: dict[str, float] = {}
        with contextlib.suppress(OSError, ValueError):
            row.update(proc_figures(self.daemon.pid))
        for kid in children(self.daemon.pid):
            with contextlib.suppress(OSError, ValueError):
                rss = proc_figures(kid)["rss_mb"]
                row["child_rss_mb"] = row.get("child_rss_mb", 0.0) + rss
                if child_role(kid) == WORKER:  # the test's fit: its memory is the daemon's
                    row["worker_rss_mb"] = rss
        st, at = self.bus.latest()
        if st is not None:
            row.update(status_figures(st))
            row["status_age_s"] = time.monotonic() - at
        row["watchdog_max_gap_s"] = self.notify.max_watchdog_gap_s
        self.series.add((time.monotonic() - self.t0) / 60.0, row, quiet)

    def _loop(self) -> None:
        a = self.args
        end = self.t0 + a.minutes * 60.0
        every = a.fault_every_s
        fault_times = [self.t0 + (k + 0.5) * every for k in range(int(a.minutes * 60.0 / every))]
        for k, t in enumerate(fault_times):
            self.at(t - QUIET_BEFORE_S, lambda: self._sample(quiet=True))
            self.at(t, functools.partial(self._fault, k))
        self.at(end - QUIET_BEFORE_S, lambda: self._sample(quiet=True))
        next_sample = self.t0
        while True:
            now = time.monotonic()
            if now >= end:
                break
            due = sorted((x for x in self.timers if x[0] <= now), key=lambda x: x[0])
            self.timers = [x for x in self.timers if x[0] > now]
            for _, fn in due:
                fn()
            if now >= next_sample:
                self._sample(quiet=False)
                next_sample = now + a.sample_s
            if self.daemon.poll() is not None:
                raise RuntimeError(f"the daemon exited with {self.daemon.returncode} during the soak")
            self.dev.poll_events()
            time.sleep(0.2)
        for _, fn in sorted(self.timers, key=lambda x: x[0]):  # end what is still on (a freeze, a full disk)
            fn()
        self.timers = []

    def _settle(self, timeout: float = 60.0) -> dict[str, Any]:
        """The device stops sending; the daemon's status once it has read and handed on everything."""
        before = self.dev.stats()
        self.dev.send("stall 1e9")
        last: tuple[int, int] | None = None
        steady = 0
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            time.sleep(1.0)
            st, _ = self.bus.latest()
            if st is None:
                continue
            depth = sum(q.get("depth", 0) for q in st["queues"].values())
            key = (st["samples"], st["lost_samples"])
            steady = steady + 1 if key == last and depth == 0 else 0
            last = key
            if steady >= 3:
                break
        after = self.dev.stats()
        st, _ = self.bus.latest()
        if st is None:
            raise RuntimeError("no status message from the daemon")
        return {"device_before_stall": before, "device": after, "status": st}

    def _run(self) -> dict[str, Any]:
        a = self.args
        self._start()
        self.t0 = time.monotonic()
        self._loop()
        self._sample(quiet=False)
        final = self._settle()
        t_stop = time.monotonic()
        self.daemon.send_signal(signal.SIGTERM)
        code = self.daemon.wait(30)
        stop_s = time.monotonic() - t_stop
        self.lives[-1].update(ended_by="SIGTERM", exit_code=code, stop_s=round(stop_s, 3))
        files = self._read_recordings()
        events = dict(self.bus.events)
        results = dict(self.bus.results)
        self.sub.stop()
        summary = self.series.summary(a.warmup_min)
        restarts = sum(1 for f in self.faults if f["fault"] in ("restart", "kill"))
        accounting = account(final, files, restarts)
        quiet_span = a.minutes - a.warmup_min
        bad = verdict(summary, quiet_span)
        bad += [f"accounting: {c}" for c in accounting["problems"]]
        if code != 0:
            bad.append(f"the daemon exited with {code} on SIGTERM")
        bad += [f"a restart's SIGTERM: exit {life['exit_code']}" for life in self.lives[:-1]
                if life.get("ended_by") == "SIGTERM" and life.get("exit_code") != 0]
        return {
            "settings": {k: v for k, v in vars(a).items() if k != "json"},
            "workdir": str(self.workdir),
            "disk": {"tmpfs": self.disk.mounted, "why_not": self.disk.why_not, "size_mb": a.disk_mb},
            "faults": self.faults,
            "figures": summary,
            "series": {"t_min": self.series.t_min, "rows": self.series.rows, "quiet": self.series.quiet},
            "accounting": accounting,
            "bus": {"events": events, "results": results, "statuses": self.bus.statuses,
                    "frozen_subscriber_lines": self.sub.lines(), "frozen_subscriber_starts": self.sub.starts},
            "watchdog": {"pings": self.notify.watchdogs, "max_gap_s": self.notify.max_watchdog_gap_s},
            "daemon": {"exit_code": code, "stop_s": stop_s, "lives": self.lives},
            "problems": bad,
        }

    def _read_recordings(self) -> dict[str, Any]:
        from ballbar.daemon.mcap import list_recordings, read_log

        paths = list_recordings(self.disk.path / "recordings")
        samples = preroll = gaps = gap_events = unplugs = skipped = 0
        last_run = {"samples": 0, "log_gap_samples": 0}
        lost: dict[str, int] = {}
        restarts: list[int] = []
        incomplete = []
        runs: list[str] = []
        for p in paths:
            lg = read_log(p)
            run = lg.metadata.get("run_id", "")
            if not runs or runs[-1] != run:
                runs.append(run)
                last_run = {"samples": 0, "log_gap_samples": 0}
            own = int((~lg.preroll).sum())
            samples += own
            last_run["samples"] += own
            preroll += int(lg.preroll.sum())
            for ev in lg.events:
                name = ev.get("event")
                if name == "log_gap":
                    gaps += int(ev.get("count", 0))
                    last_run["log_gap_samples"] += int(ev.get("count", 0))
                    gap_events += 1
                elif name == "lost":
                    cause = str(ev.get("detail") or "gap")
                    lost[cause] = lost.get(cause, 0) + int(ev.get("count", 0))
                    if cause == "restart":
                        restarts.append(int(ev.get("count", 0)))
                elif name == "unplugged":
                    unplugs += 1
                elif name == "decode_errors":
                    skipped += int((ev.get("counts") or {}).get("skipped_bytes", 0))
            if not lg.complete:
                incomplete.append(p.name)
        size = sum(p.stat().st_size for p in paths)
        return {"files": len(paths), "bytes": size, "newest": paths[-1].name if paths else None,
                "samples": samples, "preroll": preroll, "log_gap_samples": gaps, "log_gaps": gap_events,
                "incomplete": incomplete, "runs": len(runs), "last_run": last_run, "lost_by_cause": lost,
                "restart_losses": restarts, "unplugs": unplugs, "skipped_bytes": skipped}


def account(final: dict[str, Any], files: dict[str, Any], restarts: int = 0) -> dict[str, Any]:
    """Every sample the device took, followed to where it went, over every life of the daemon (see the module
    docstring); ``restarts``: how many restart and kill faults there were."""
    dev, before, st = final["device"], final["device_before_stall"], final["status"]
    tail = dev["stalled"] - before["stalled"]  # taken after the last one sent: nobody could see them
    taken = dev["generated"] - tail
    received, lost = int(st["samples"]), int(st["lost_samples"])  # the last life's
    by_cause = dict(files["lost_by_cause"])  # every life's, as recorded
    counted = sum(by_cause.values())
    kept = files["samples"] + files["log_gap_samples"]  # in the files, or counted not written by a logger
    in_transit = dev["sent"] - kept  # sent, and never recorded: on the wire at an unplug, in the port at a restart
    mcap = st["outputs"].get("mcap", {})
    mq = st["queues"].get("mcap", {})
    problems = []
    device_sum = dev["sent"] + dev["unplugged"] + dev["stalled"] + dev["dropped"] + dev["corrupted"]
    if device_sum != dev["generated"]:
        problems.append(f"device: taken {dev['generated']} != sent + lost on the device {device_sum}")
    if kept + counted != taken:
        problems.append(f"daemon: recorded {files['samples']} + not written {files['log_gap_samples']} + counted "
                        f"lost {counted} = {kept + counted} != taken {taken}")
    across = by_cause.get("outage", 0) + by_cause.get("restart", 0)
    if across != dev["unplugged"] + in_transit:
        problems.append(f"lost across unplugs and restarts {across} != lost while unplugged "
                        f"{dev['unplugged']} + sent and never recorded {in_transit}")
    if restarts and len(files["restart_losses"]) != restarts:
        problems.append(f"{restarts} restarts, {len(files['restart_losses'])} counted what they lost")
    # The decoder skips the junk, and at each unplug or restart at most the part of a frame cut off by it.
    skipped = int(files["skipped_bytes"])
    cuts = int(files["unplugs"]) + restarts
    if not dev["garbage_bytes"] <= skipped < dev["garbage_bytes"] + FRAME_SIZE * cuts + 1:
        problems.append(f"the decoder skipped {skipped} bytes: not the {dev['garbage_bytes']} junk bytes sent "
                        f"plus less than a frame at each of {cuts} unplugs and restarts")
    other = {k: v for k, v in by_cause.items() if k not in ("outage", "restart") and v}
    if other:
        problems.append(f"losses nobody injected: {other}")
    last = files["last_run"]
    recorded = last["samples"] + int(mcap.get("samples_lost", 0))
    if mq.get("dropped", 0):
        problems.append(f"the MCAP queue dropped {mq['dropped']} batches")
    if recorded != received:
        problems.append(f"recording (the last life): {last['samples']} in the files + {mcap.get('samples_lost', 0)} "
                        f"counted lost by the logger = {recorded} != received {received}")
    if last["log_gap_samples"] != int(mcap.get("samples_lost", 0)):
        problems.append(f"log_gap events of the last life say {last['log_gap_samples']} samples, its logger counted "
                        f"{mcap.get('samples_lost', 0)}")
    # A file a write error cut has no footer (the next start rewrites it, as after a crash); the others must.
    cut = files["incomplete"]
    if len(cut) > int(mcap.get("write_errors", 0)) or (cut and cut[-1] == files["newest"]):
        problems.append(f"files without a footer after SIGTERM: {cut} ({mcap.get('write_errors', 0)} write errors)")
    return {
        "device": {k: dev[k] for k in ("generated", "sent", "unplugged", "stalled", "dropped", "corrupted",
                                       "garbage_bytes", "resets")},
        "final_stall_tail": tail,
        "taken": taken,
        "received": received,
        "lost": lost,
        "counted_lost": counted,
        "lost_by_cause": by_cause,
        "restart_losses": files["restart_losses"],
        "in_transit_at_unplug": in_transit,
        "decode": dict(st["source"].get("decode", {})),
        "skipped_bytes": skipped,
        "recorded": files,
        "mcap": {k: mcap.get(k) for k in ("samples", "samples_lost", "messages_lost", "messages_held",
                                          "messages_held_written", "write_errors", "files")},
        "mcap_queue": mq,
        "problems": problems,
    }


# ----------------------------------------------------------------------------- the report


def report(r: dict[str, Any]) -> Iterator[str]:
    s = r["settings"]
    where = f"a tmpfs of {s['disk_mb']} MiB" if r["disk"]["tmpfs"] else "an ordinary directory"
    yield (f"soak: {s['minutes']:g} min at x{s['speedup']:g} (device 1000 Hz), a fault every {s['fault_every_s']:g} s "
           f"({', '.join(s['faults'])}); state on {where}")
    if not r["disk"]["tmpfs"]:
        yield f"  disk-full spells skipped: {r['disk']['why_not']}"
    counts: dict[str, int] = {}
    for f in r["faults"]:
        counts[f["fault"]] = counts.get(f["fault"], 0) + 1
    yield "faults: " + ", ".join(f"{k} x{v}" for k, v in counts.items())
    yield ""
    yield (f"{'figure':<28}{'min':>11}{'median':>11}{'max':>11}{'1st quiet':>11}{'last quiet':>11}"
           f"{'trend/min':>11}")
    for name, f in r["figures"].items():
        trend = "" if f["trend_per_min"] is None else f"{f['trend_per_min']:+.3g}"
        fq = "" if f["first_quiet"] is None else f"{f['first_quiet']:.6g}"
        lq = "" if f["last_quiet"] is None else f"{f['last_quiet']:.6g}"
        yield f"{name:<28}{f['min']:>11.6g}{f['median']:>11.6g}{f['max']:>11.6g}{fq:>11}{lq:>11}{trend:>11}"
    a = r["accounting"]
    d = a["device"]
    yield ""
    yield "samples:"
    yield (f"  device   taken {d['generated']} = sent {d['sent']} + while unplugged {d['unplugged']} "
           f"+ stalled {d['stalled']} (of them {a['final_stall_tail']} after the last sent, at the end)"
           f" + dropped {d['dropped']} + corrupted {d['corrupted']}")
    rec = a["recorded"]
    yield (f"  daemon   taken before the end {a['taken']} = in {rec['files']} MCAP files of {rec['runs']} lives "
           f"{rec['samples']} (+ {rec['preroll']} preroll copies) + not written {rec['log_gap_samples']} "
           f"(log_gap events: {rec['log_gaps']}) + counted lost {a['counted_lost']} {a['lost_by_cause']}")
    yield (f"           lost across unplugs and restarts = while unplugged {d['unplugged']} + sent and never "
           f"recorded {a['in_transit_at_unplug']}; each restart counted {a['restart_losses']}")
    yield (f"  record   the last life received {a['received']} = its samples in the files "
           f"{rec['last_run']['samples']} + lost by its logger {a['mcap']['samples_lost']}; MCAP queue dropped "
           f"{a['mcap_queue'].get('dropped', 0)}")
    yield (f"  garbage  device sent {d['garbage_bytes']} junk bytes; decoders skipped {a['skipped_bytes']} "
           f"(and the frames that unplugs and restarts cut); resets {d['resets']}")
    yield (f"  held     results/events held through disk-full spells: {a['mcap']['messages_held']} "
           f"(written {a['mcap']['messages_held_written']}); status messages lost {a['mcap']['messages_lost']}")
    b = r["bus"]
    yield ""
    yield (f"bus: results {b['results']}, events {b['events']}; the frozen subscriber printed "
           f"{b['frozen_subscriber_lines']} lines over {b['frozen_subscriber_starts']} lives")
    yield (f"watchdog: {r['watchdog']['pings']} pings, longest gap {r['watchdog']['max_gap_s']:.2f} s; "
           f"SIGTERM: exit {r['daemon']['exit_code']} in {r['daemon']['stop_s']:.2f} s")
    yield ""
    yield "verdict: " + ("flat, and every sample accounted for" if not r["problems"] else "; ".join(r["problems"]))


# ----------------------------------------------------------------------------- main


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m ballbar.tools.bench.soak", description=__doc__.split("\n", 1)[0])
    p.add_argument("--minutes", type=float, default=30.0, help="length of the run")
    p.add_argument("--speedup", type=float, default=5.0, help="device time per wall time (device at 1000 Hz)")
    p.add_argument("--fault-every-s", type=float, default=60.0)
    p.add_argument("--sample-s", type=float, default=5.0, help="figures taken this often")
    p.add_argument("--warmup-min", type=float, help="trends leave out this first part (default: min(2, minutes/4))")
    p.add_argument("--faults", default=",".join(FAULTS), help="the rotation (default: %(default)s)")
    p.add_argument("--unplug-s", type=float, default=5.0)
    p.add_argument("--garbage-bytes", type=int, default=20_000)
    p.add_argument("--freeze-s", type=float, default=40.0)
    p.add_argument("--disk-full-s", type=float, default=20.0)
    p.add_argument("--disk-mb", type=int, default=256, help="size of the state directory's tmpfs")
    p.add_argument("--samples-hz", type=float, default=1000.0, help="zenoh.samples_hz (load for the subscribers)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="a configuration key for the daemon (repeatable), e.g. buffers small enough to fill")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workdir", help="logs, the configuration, the report (default: a new temporary directory)")
    p.add_argument("--json", help="write the full report (with every sample of the figures) here")
    p.add_argument("-v", "--verbose", action="store_true", help="log each fault as it is injected")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
    if not (args.minutes > 0 and args.speedup > 0 and args.fault_every_s > 0 and args.sample_s > 0):
        print("soak: --minutes, --speedup, --fault-every-s and --sample-s must be > 0", file=sys.stderr)
        return 2
    args.faults = [f.strip() for f in args.faults.split(",") if f.strip()]
    if not args.faults or set(args.faults) - set(FAULTS):
        print(f"soak: --faults must name some of {', '.join(FAULTS)}", file=sys.stderr)
        return 2
    if args.warmup_min is None:
        args.warmup_min = min(2.0, args.minutes / 4)

    def on_term(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    soak = Soak(args)
    try:
        result = soak.run()
    except KeyboardInterrupt:
        print("soak: interrupted", file=sys.stderr)
        return 1
    out = Path(args.json) if args.json else soak.workdir / "soak.json"
    out.write_text(json.dumps(result, indent=1))
    for line in report(result):
        print(line)
    print(f"(full report: {out}; logs: {soak.workdir})")
    return 0 if not result["problems"] else 1


if __name__ == "__main__":
    sys.exit(main())
