"""The Rerun streamer: live polar plots, findings and trends for a remote viewer.

:class:`RerunViewer` is a :class:`~ballbar.daemon.listeners.Listener`.  It logs
into its own :class:`rerun.RecordingStream` (application ``ballbar``, one
recording per daemon run), never the global one, and reaches viewers one of two
ways:

``serve``    (default) a gRPC server on ``bind``:``port`` (127.0.0.1:9880: this PC
             only, and not the viewer's own 9876); viewers connect whenever they
             like with ``rerun rerun+http://127.0.0.1:9880/proxy`` and receive what
             the server holds, bounded by ``server_memory_limit`` (oldest messages
             dropped first; static data such as the reference circles is kept),
             which always includes the history chosen for late viewers (below).
             The server is ``rerun --serve-grpc`` in a child process that the
             daemon pushes to (see :class:`_ServerProcess`): Rerun's server takes
             data from any client, and some of it outside its memory limit, so
             it is kept out of the daemon's memory, capped and restarted.
``connect``  the daemon pushes to a viewer listening at ``url``
             (``rerun`` started on a workstation listens on 9876 by default).
``off``      nothing is created; every call is a no-op.

What is logged (timelines: ``time``, wall clock of the sample or of the
message; ``test``, the test's sequence number within this daemon run)::

    polar/reference/{nominal,axes,axis_labels,scale}  static: the nominal circle, the plane's
                                     axes, the +-s scale rings
    polar/reference/{band,labels}  the tolerance band and the rings' labels (they depend
                                     on the scale s; logged when it changes, and with the history)
    polar/{ccw,cw}/measured    LineStrips2D of the magnified radial deviation: grown live
                               during the data arc in pieces (the growing tip here, each
                               completed piece once in measured/<k>), redrawn whole with
                               each result's timing (the pieces cleared)
    polar/{ccw,cw}/model       the fitted model, rebuilt from the result's parameters
    length                     Scalars: the bar length L (mm), decimated to <= length_hz
    findings                   TextDocument (markdown): ranking, parameters, ISO 230-4, advice
    trends/backlash_um/{x,y}, trends/circularity_um/G_b, trends/servo_mismatch_ms,
    trends/squareness_urad, trends/scale_mismatch_ppm
                               Scalars, one point per test
    events                     TextLog: feed-in/out, rejected tests, source events

The polar plot.  A sample's deviation ``dR = L - R`` (um) is drawn at radius
``R0 + k dR`` with ``R0 = 100`` display units and ``k = R0 / (2 s)``: a
deviation of ``s`` sits halfway between the nominal circle and its centre or
its double (the scale rings, labelled, mark ``+-s``).  ``s`` is ``scale_um``,
or, by default, automatic: a round value (1, 2, 5 x 10^n um) that fits the
last test, growing at once when a live circle outgrows it; the band and the
scale rings are logged on the timelines whenever ``s`` changes, so that an
older circle is always seen against its own scale.  With
``remove_setup`` the set-up terms of the latest result (pivot offset
``centre_*_um`` and ``radius_um``) are subtracted from the measured and the
model curves alike, as commercial ball-bar software draws them.  A sample's
angle comes from the test program's timing (analysis/README.md): live, from
the feed-in event and the feed ratio and overhead learnt on the previous test
(exactly the engine's provisional timing); after each circle and test result,
from that result's ``timing``.

Bounded, and cheap.  A batch is only queued; the samples are processed
together, and the length series sent, at most every ``send_interval_s``
(0.25 s; ``polar_update_s`` while a test is drawn live, and where a send would
carry fewer than ``MIN_SEND_POINTS`` samples: at 15.625 Hz a send of four points
costs what one of 250 does) on the samples' host clock, and at each result or
event.  The length series is decimated to
``length_hz`` (100 points per second of the host clock, whatever the sample
rate); a live circle gains a piece at a time (never the whole circle again);
the current test's samples are kept at ``buffer_hz``, at most
``max_buffer_samples``.  What a viewer that connects late gets is chosen: the
last ``history_tests`` tests whole (polar plots, models, band, findings) at
their own times, the trends of the last ``TRENDS_KEPT`` tests, the length at
``history_length_hz`` over ``history_length_s``, all kept here in fixed-size
buffers and sent with the scene to every new sink; in ``serve`` mode sent again
whenever half of ``server_memory_limit`` has been sent since (an estimate on
the high side, ``MSG_BYTES``...), so that the server's buffer, which drops its
oldest messages first, always holds them whole, besides the last hours of the
live stream (everything: full-rate length, live circles, events).

Never blocking the daemon.  The listener's own queue already decouples it;
beyond that, data is only logged while a sink exists (no unbounded buffering
for an absent viewer), the server's buffer is bounded, and :meth:`stop`
returns within ``stop_timeout_s`` even when a viewer is frozen mid-stream.
Facts of rerun-sdk 0.41 that shape the ``connect`` mode (checked on this
machine):

- a ``GrpcSink`` created while nothing listens never delivers: the bounded
  flush issued while it is still connecting breaks its stream once it connects
  ("gracefully disconnected"); and a sink whose viewer went away never
  reconnects.  So the viewer probes the address over TCP on a thread of its
  own and (re)creates the sink only when something listens, then re-sends
  the scene (blueprint, references, the current test, findings, trends);
- a frozen (stopped, not dead) viewer makes ``disconnect()`` wait forever and
  the SDK's exit hook with it, so :meth:`stop` disconnects on a helper thread
  and, if that does not finish in time, keeps the recording referenced and
  unregisters the SDK's exit hook (logged) so that the daemon can still exit.
  Until its TCP connection times out, a frozen viewer also holds what is sent
  to it, and ``log`` blocks once the SDK's queues (hundreds of MB) are full:
  at this streamer's rate (tens of kB/s) that takes hours, and the listener's
  queue shields the daemon meanwhile.

In ``serve`` mode :meth:`stop` ends the server process (SIGTERM, then SIGKILL
after a second); a daemon killed outright takes it along (``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import importlib.util
import ipaddress
import logging
import math
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.parse
import uuid
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb
else:  # imported at first use: the configuration check and READY=1 do not wait for it (half a second)
    from .lazy import LazyModule

    rr, rrb = LazyModule("rerun"), LazyModule("rerun.blueprint")

from ballbar.analysis.engine import TimingHints
from ballbar.analysis.errors import BallbarError
from ballbar.analysis.patterns import LIBRARY, Geometry, Pattern, design
from ballbar.analysis.physics import LostMotion, make_offset
from ballbar.analysis.plan import MachineConfig, TestPlan
from ballbar.analysis.program import arc_start_deg, data_start_deg, schedule
from ballbar.analysis.report import trend_limits
from ballbar.protocol import INVALID

from .listeners import MERGE_S, TEST_END_EVENTS, Listener, Message
from .samples import EventKind, SampleBatch, SourceEvent

log = logging.getLogger(__name__)

Mode = Literal["serve", "connect", "off"]
Clock = Literal["auto", "device", "host"]
FloatArray = NDArray[np.float64]
_INVALID = np.uint8(int(INVALID))  # status bits of a sample that is not a measurement

APPLICATION_ID = "ballbar"
# Not the viewer's own 9876: a user's `rerun some.rrd` on this PC must not stream into the daemon's view.
DEFAULT_SERVE_PORT = 9880
R0 = 100.0  # display radius of the nominal circle (arbitrary units of the 2D view)
DIRECTIONS: dict[int, str] = {1: "ccw", -1: "cw"}
COLOURS: dict[str, tuple[int, int, int]] = {
    "ccw": (40, 110, 230),
    "ccw_model": (10, 30, 110),
    "cw": (235, 85, 40),
    "cw_model": (120, 25, 0),
    "nominal": (175, 175, 175),
    "band": (60, 170, 60),
    "scale": (95, 95, 95),
    "axes": (95, 95, 95),
}
# (entity under trends/, result field or ISO key, label)
TRENDS: tuple[tuple[str, str, str], ...] = (
    ("backlash_um/x", "backlash_x_um", "X"),
    ("backlash_um/y", "backlash_y_um", "Y"),
    ("circularity_um/G_b", "G_b_um", "G(b)"),
    ("servo_mismatch_ms", "servo_mismatch_ms", "1/KX - 1/KY"),
    ("squareness_urad", "squareness_urad", "squareness"),
    ("scale_mismatch_ppm", "scale_mismatch_ppm", "eX - eY"),
)
# (origin under trends/, title): short, so that the titles fit a third of the trends panel
# ("circularity G(b) (µm)" and "servo mismatch (ms)" were cut to "circularity G" and "servo mism")
TREND_VIEWS: tuple[tuple[str, str], ...] = (
    ("backlash_um", "backlash µm"),
    ("circularity_um", "G(b) µm"),
    ("servo_mismatch_ms", "servo ms"),
    ("squareness_urad", "square µrad"),
    ("scale_mismatch_ppm", "scale ppm"),
)
WARN_EVENTS = frozenset(
    {"test_rejected", "test_incomplete", "test_aborted", "unplugged", "lost", "stall", "device_reset", "clock_jump",
     "decode_errors"}
)
AUTO_SCALE_START_UM = 20.0
AUTO_SCALE_FILL = 1.6  # automatic scale: the largest deviation reaches 0.8 R0 from the nominal circle
PRE_TEST_S = 10.0  # samples kept while no test runs: the feed-in event comes after the step settled
TRENDS_KEPT = 5000  # tests whose trend points are re-sent to a viewer that (re)connects


class ViewerConfigError(BallbarError, ValueError):
    """An invalid viewer option (unknown key or bad value); the message names it."""


@dataclass(frozen=True)
class ViewerOptions:
    """The streamer's configuration (from the daemon's ``[rerun]`` section: :meth:`RerunViewer.from_config`).

    ``mode``: ``serve``, ``connect`` or ``off``.  ``bind``/``port``: where the
    ``serve`` mode listens (default ``127.0.0.1``: this PC only; ``0.0.0.0``:
    every interface, viewers anywhere on the network, and anyone there can
    push data into the server too).  ``server_rss_cap_mb``: the server
    process is restarted when its resident memory passes this (default
    ``2 x server_memory_limit + 128 MiB``).  ``url``: the viewer to push to in ``connect`` mode,
    ``rerun+http://HOST:PORT/proxy``.  ``server_memory_limit``: the serve
    mode's history buffer (rerun syntax: ``256MiB``, ``10%``).

    ``tolerance_um``: half-width of the tolerance band; ``scale_um``: the
    deviation drawn halfway between the nominal circle and its centre (None:
    automatic, starting at ``AUTO_SCALE_START_UM``);
    ``polar_points``: points per drawn circle; ``polar_update_s``: how often
    the live circle is extended; ``polar_pieces``: how many pieces a live
    circle is sent in (each update sends the growing piece and those
    completed since, never the whole circle again); ``length_hz``: the
    length series' rate, on the host clock, whatever the sample rate;
    ``send_interval_s``: samples are processed and the length series sent
    at most this often (and at each result or event); ``buffer_hz``: rate at
    which the current test's samples are kept for the polar plot, at most
    ``max_buffer_samples`` of them; ``remove_setup``: subtract the latest
    centre and radius estimates from the curves.

    What a viewer that connects late is sent, besides what the server still
    holds of the live stream (see the module docstring): the last
    ``history_tests`` tests whole (polar plots, models, findings), the trends
    of the last ``TRENDS_KEPT`` tests, and the length series at
    ``history_length_hz`` over the last ``history_length_s``.

    ``clock``: which sample time the analysis runs on (``auto``: the device
    clock where the source has one, corrected by the times the analysis
    messages carry).  ``retry_s``: probe/rebind period;
    ``health_s``: how often a pushed stream is checked (a flush that fails
    at once: the viewer restarted between two probes; in ``serve`` mode one
    that times out: the server takes nothing); ``history_refresh_s``: in
    ``serve`` mode the history is sent again at least this often (other
    clients may have pushed it out of the server's buffer); ``stop_timeout_s``:
    bound on :meth:`RerunViewer.stop`.
    """

    mode: Mode = "serve"
    bind: str = "127.0.0.1"  # this PC only; viewers elsewhere: bind an address on purpose, or connect mode
    port: int = DEFAULT_SERVE_PORT
    url: str = "rerun+http://127.0.0.1:9876/proxy"
    server_memory_limit: str = "128MiB"
    server_rss_cap_mb: float | None = None  # None: 2 x server_memory_limit + 128 MiB
    application_id: str = APPLICATION_ID
    recording_name: str = ""
    tolerance_um: float = 10.0
    scale_um: float | None = None
    polar_points: int = 2000
    polar_update_s: float = 0.5
    polar_pieces: int = 16
    length_hz: float = 100.0
    send_interval_s: float = 0.25
    buffer_hz: float = 1000.0
    max_buffer_samples: int = 250_000
    history_tests: int = 50
    history_length_hz: float = 1.0
    history_length_s: float = 86_400.0
    remove_setup: bool = True
    clock: Clock = "auto"
    retry_s: float = 2.0
    health_s: float = 10.0
    history_refresh_s: float = 600.0
    stop_timeout_s: float = 2.0

    def __post_init__(self) -> None:
        checks: list[tuple[bool, str]] = [
            (self.mode in ("serve", "connect", "off"), f"rerun.mode must be serve, connect or off, not {self.mode!r}"),
            (_is_ip(self.bind), f"rerun.bind must be an IP address, not {self.bind!r}"),
            (isinstance(self.port, int) and 0 < self.port < 65536, f"rerun.port must be 1..65535, not {self.port!r}"),
            (
                _proxy_address(self.url) is not None,
                f"rerun.url must be rerun+http://HOST:PORT/proxy, not {self.url!r}",
            ),
            (
                self.clock in ("auto", "device", "host"),
                f"rerun.clock must be auto, device or host, not {self.clock!r}",
            ),
            (bool(self.application_id), "rerun.application_id must not be empty"),
            (
                _memory_bytes(self.server_memory_limit) is not None,
                f"rerun.server_memory_limit must be a size such as 128MiB, not {self.server_memory_limit!r}",
            ),
            (
                self.server_rss_cap_mb is None
                or (isinstance(self.server_rss_cap_mb, int | float) and self.server_rss_cap_mb >= 64),
                f"rerun.server_rss_cap_mb must be at least 64, not {self.server_rss_cap_mb!r}",
            ),
        ]
        for name in (
            "tolerance_um",
            "polar_update_s",
            "length_hz",
            "send_interval_s",
            "buffer_hz",
            "history_length_hz",
            "history_length_s",
            "retry_s",
            "health_s",
            "history_refresh_s",
            "stop_timeout_s",
        ):
            v = getattr(self, name)
            ok = isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) and v > 0
            checks.append((ok, f"rerun.{name} must be a number > 0, not {v!r}"))
        s = self.scale_um
        ok = s is None or (isinstance(s, int | float) and not isinstance(s, bool) and math.isfinite(s) and s > 0)
        checks.append((ok, f"viewer scale_um must be a number > 0 or unset (automatic), not {s!r}"))
        for name, lo in (("polar_points", 16), ("max_buffer_samples", 10_000), ("polar_pieces", 1),
                         ("history_tests", 0)):
            v = getattr(self, name)
            ok = isinstance(v, int) and not isinstance(v, bool) and v >= lo
            checks.append((ok, f"rerun.{name} must be an integer >= {lo}, not {v!r}"))
        for ok, msg in checks:
            if not ok:
                raise ViewerConfigError(msg)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ViewerOptions:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ViewerConfigError(f"unknown viewer key {unknown[0]!r} (known: {', '.join(sorted(known))})")
        return cls(**dict(data))

    @property
    def server_rss_cap(self) -> int:
        """Bytes of resident memory above which the serve mode's server process is restarted."""
        if self.server_rss_cap_mb is not None:
            return int(self.server_rss_cap_mb * 2**20)
        limit = _memory_bytes(self.server_memory_limit)
        return 2 * (limit if limit is not None else 128 * 2**20) + 128 * 2**20

    @property
    def address(self) -> str:
        """Where viewers find the stream: the URL to give ``rerun``."""
        if self.mode == "serve":
            host = "127.0.0.1" if self.bind in ("0.0.0.0", "::") else self.bind
            return f"rerun+http://{_host_for_url(host)}:{self.port}/proxy"
        return self.url


def _memory_bytes(text: str) -> int | None:
    """``128MiB``, ``1GB``, ``512kB`` as bytes (rerun's size syntax, without its percentages), or None."""
    m = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]+)?)\s*([kMGT]i?B|B)\s*", str(text))
    if not m:
        return None
    mult = {"B": 1, "kB": 10**3, "MB": 10**6, "GB": 10**9, "TB": 10**12,
            "kiB": 2**10, "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}.get(m[2])
    return int(float(m[1]) * mult) if mult else None


def _is_ip(text: str) -> bool:
    try:
        ipaddress.ip_address(text)
    except ValueError:
        return False
    return True


def _host_for_url(host: str) -> str:
    return f"[{host}]" if ":" in host else host


def _proxy_address(url: str) -> tuple[str, int] | None:
    """``(host, port)`` of a ``rerun+http://HOST:PORT/proxy`` URL, None if it is not one."""
    try:
        p = urllib.parse.urlsplit(url)
        port = p.port
    except ValueError:
        return None
    if p.scheme not in ("rerun", "rerun+http", "rerun+https") or not p.hostname or p.path != "/proxy":
        return None
    return p.hostname, port or 9876


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


def viewer_options(cfg: Any) -> ViewerOptions:
    """The :class:`ViewerOptions` of the daemon's configuration: ``[rerun]``, ``plan``, ``daemon.machine_id``.

    Every :class:`ViewerOptions` field the section has is taken as it is;
    besides, ``memory_limit_mb`` (MiB) sets ``server_memory_limit`` and
    ``magnification`` (0: automatic) how many times a deviation is drawn
    larger than the radius (``r/R0 = 1 + M dR/R``), i.e.
    ``scale_um = 500 R / M``.  Keys the section lacks keep the defaults.
    Raises :class:`ViewerConfigError` naming a bad value.
    """
    sec = cfg.rerun
    plan: TestPlan | None = getattr(cfg, "plan", None)
    kw: dict[str, Any] = {f.name: getattr(sec, f.name) for f in fields(ViewerOptions) if hasattr(sec, f.name)}
    mem = getattr(sec, "memory_limit_mb", None)
    if mem is not None:
        if not (isinstance(mem, int | float) and math.isfinite(mem) and mem >= 1):
            raise ViewerConfigError(f"rerun.memory_limit_mb must be a number >= 1, not {mem!r}")
        kw["server_memory_limit"] = f"{round(float(mem))}MiB"
    mag = getattr(sec, "magnification", None)
    if mag and plan is not None:
        kw["scale_um"] = 500.0 * plan.radius_mm / float(mag)
    machine_id = getattr(getattr(cfg, "daemon", None), "machine_id", "") or ""
    kw.setdefault("recording_name", f"ballbar {machine_id} {time.strftime('%Y-%m-%d %H:%M:%S')}".strip())
    return ViewerOptions(**kw)


# --------------------------------------------------------------------------- pure helpers


def _num(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def _param(result: Mapping[str, Any], field: str) -> float | None:
    p = result.get("parameters", {}).get(field)
    return _num(p.get("value")) if isinstance(p, Mapping) else None


@dataclass(frozen=True)
class ArcTiming:
    """The timing of one direction's data arc, on the analysis clock.

    A sample at ``t`` in ``[start_s, end_s]`` is at angle
    ``u = u_ds + d V (t - start_s) / R`` (analysis/README.md, "The angle of each sample").
    """

    direction: int
    feed_in_s: float
    feed_mm_s: float
    start_s: float
    end_s: float
    spike_width_deg: float
    loop_lag_s: float | None = None

    def angle_rad(self, plan: TestPlan, t: FloatArray) -> FloatArray:
        u_ds = math.radians(data_start_deg(plan, self.direction))
        return np.asarray(u_ds + self.direction * self.feed_mm_s * (t - self.start_s) / plan.radius_mm)


def provisional_timing(
    plan: TestPlan, direction: int, feed_in_s: float, feed_ratio: float, overhead_s: float, spike_width_deg: float
) -> ArcTiming:
    """The engine's provisional timing of a test that began (feed-in centroid) at ``feed_in_s``."""
    V = plan.feed_mm_s * feed_ratio
    sched = schedule(plan, V, overhead_s)
    return ArcTiming(
        direction,
        feed_in_s,
        V,
        feed_in_s + sched.data_start_s[direction],
        feed_in_s + sched.data_end_s[direction],
        spike_width_deg,
    )


def result_timing(result: Mapping[str, Any], direction: int) -> ArcTiming | None:
    """A circle or test result's timing of ``direction``'s data arc (None: not in it)."""
    tm = result.get("timing") or {}
    name = DIRECTIONS[direction]
    t_ref = _num(tm.get("feed_in_s"))
    w = _num(tm.get("spike_width_deg")) or 3.0
    if result.get("kind") == "circle":
        feed, start, end = (_num(tm.get(k)) for k in ("assumed_feed_mm_min", "data_start_s", "data_end_s"))
        if result.get("direction") != name or None in (t_ref, feed, start, end):
            return None
        assert t_ref is not None and feed is not None and start is not None and end is not None
        return ArcTiming(direction, t_ref, feed / 60.0, start, end, w)
    arc = (tm.get("data_arcs") or {}).get(name) or {}
    feed, start, end = _num(tm.get("measured_feed_mm_min")), _num(arc.get("start_s")), _num(arc.get("end_s"))
    if None in (t_ref, feed, start, end):
        return None
    assert t_ref is not None and feed is not None and start is not None and end is not None
    lag_ms = _num(tm.get("loop_lag_ms"))
    return ArcTiming(direction, t_ref, feed / 60.0, start, end, w, lag_ms / 1000.0 if lag_ms is not None else None)


def _patterns_for(plan: TestPlan, machine: MachineConfig, direction: int) -> list[Pattern]:
    out = []
    for p in LIBRARY:
        if p.needs == "pitch_x" and machine.pitch_x_mm is None:
            continue
        if p.needs == "pitch_y" and machine.pitch_y_mm is None:
            continue
        if p.reversal is not None and p.reversal[2] != direction:
            continue
        out.append(p)
    return out


def _coefficients(result: Mapping[str, Any], patterns: Sequence[Pattern]) -> FloatArray:
    """The fitted parameters in the patterns' column order; not fitted: 0.

    Cyclic errors are reported as amplitude and phase; their columns are
    ``(c cos phi, c sin phi)`` (:mod:`ballbar.analysis.report`).
    """
    x: list[float] = []
    for p in patterns:
        if p.name.startswith("cyclic_"):
            amp = _param(result, f"{p.name}_um") or 0.0
            phase = math.radians(_param(result, f"{p.name}_phase_deg") or 0.0)
            x += [amp * math.cos(phase), amp * math.sin(phase)]
        else:
            x += [_param(result, f) or 0.0 for f in p.fields]
    return np.asarray(x, dtype=float)


def _radial_cos2(plan: TestPlan, machine: MachineConfig, source: str) -> float | None:
    """Mean ``cos 2u`` of the radii along which the loop lag was measured (engine ``loop_lag``).

    The result does not say which of feed-in and feed-out resolved the lag:
    both are assumed (the usual case).
    """
    if (machine.kv_x_per_s and machine.kv_y_per_s) or not source.startswith("approach"):
        return None
    dirs = plan.direction_list
    u_in = math.radians(arc_start_deg(plan, dirs[0]))
    u_out = math.radians(arc_start_deg(plan, dirs[-1])) + dirs[-1] * math.radians(plan.arc_deg)
    return 0.5 * (math.cos(2 * u_in) + math.cos(2 * u_out))


def model_deviation_um(result: Mapping[str, Any], direction: int, u: FloatArray) -> FloatArray | None:
    """The fitted model's radial deviation (um) at angles ``u`` (rad) of ``direction``'s data arc.

    Rebuilt from the result's parameters with the pattern library, the
    result's timing (feed, spike width, loop lag) and, for a test result, the
    physical corrections the fit applied (servo remainder, each axis'
    lost-motion model with its reversal and friction onsets, and the loops'
    angles, all from ``fit.lost_motion``, :mod:`ballbar.analysis.physics`).
    ``u`` must lie within the data arc (``data_start_deg`` onwards in the
    direction of travel).  None when the result lacks what is needed.
    """
    timing = result_timing(result, direction)
    if timing is None or "plan" not in result:
        return None
    plan = TestPlan.from_dict(dict(result["plan"]))
    machine = MachineConfig.from_dict(dict(result.get("machine") or {}))
    patterns = _patterns_for(plan, machine, direction)
    u = np.asarray(u, dtype=float)
    d = float(direction)
    u_ds = math.radians(data_start_deg(plan, direction))
    test = result.get("kind") == "test"
    lost = LostMotion.from_dict((result.get("fit") or {}).get("lost_motion")) if test else LostMotion()
    values = {f: _param(result, f) for f in ("servo_mismatch_ms", "backlash_x_um", "backlash_y_um")}
    t_rel = (timing.start_s - timing.feed_in_s) + d * (u - u_ds) * plan.radius_mm / timing.feed_mm_s
    g = Geometry(
        u=u,
        d=np.full(u.size, d),
        t_min=t_rel / 60.0,
        V=timing.feed_mm_s,
        R=plan.radius_mm,
        pitch_x_mm=machine.pitch_x_mm,
        pitch_y_mm=machine.pitch_y_mm,
        travel=d * (u - math.radians(arc_start_deg(plan, direction))),
        loop_lag_s=timing.loop_lag_s,
        **lost.geometry(timing.loop_lag_s),
    )
    dr = design(patterns, g, math.radians(timing.spike_width_deg)) @ _coefficients(result, patterns)
    if test:
        tm = result.get("timing") or {}
        cos2 = _num(tm["loop_lag_radial_cos2u"]) if "loop_lag_radial_cos2u" in tm else _radial_cos2(
            plan, machine, str(tm.get("loop_lag_source", "")))
        frame_cos2 = math.cos(2.0 * math.radians(arc_start_deg(plan, plan.direction_list[0])))
        offset = make_offset(values, timing.loop_lag_s, lost, cos2, frame_cos2)
        if offset is not None:
            dr = dr + offset(g)
    return np.asarray(dr, dtype=float)


def setup_deviation_um(result: Mapping[str, Any] | None, u: FloatArray) -> FloatArray:
    """The set-up terms (pivot offset and bar length) of ``result`` at angles ``u``; 0 without."""
    if result is None:
        return np.zeros_like(u)
    x0, y0, c = (_param(result, f) or 0.0 for f in ("centre_x_um", "centre_y_um", "radius_um"))
    return np.asarray(x0 * np.cos(u) + y0 * np.sin(u) + c)


def polar_points(u: FloatArray, dr_um: FloatArray, scale_um: float) -> FloatArray:
    """``(n, 2)`` display points of deviations ``dr_um`` at angles ``u`` (rad), magnified.

    Rerun's 2D views put +y down (image convention): the second coordinate is
    ``-r sin u`` so that the plane's second axis points up and CCW looks CCW.
    """
    r = np.maximum(R0 + (R0 / (2.0 * scale_um)) * dr_um, 0.0)
    return np.column_stack([r * np.cos(u), -r * np.sin(u)])


def nice_scale_um(max_abs_um: float) -> float:
    """The automatic scale for deviations up to ``max_abs_um``: 1, 2 or 5 x 10^n um, at least 1 um."""
    x = max(max_abs_um / AUTO_SCALE_FILL, 1.0)
    e = 10.0 ** math.floor(math.log10(x))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * e >= x * (1 - 1e-9):
            return m * e
    return 10.0 * e  # pragma: no cover - the loop always returns


def _multiples(seq: NDArray[np.int64], every: int) -> NDArray[np.intp]:
    """Positions of the samples whose number is a multiple of ``every`` (arithmetic when none is missing)."""
    n = seq.size
    if not n:
        return np.empty(0, np.intp)
    s0 = int(seq[0])
    if int(seq[-1]) - s0 == n - 1:
        return np.arange((-s0) % every, n, every)
    return np.flatnonzero(seq % every == 0)


def _rate(t: FloatArray, previous: float) -> float:
    """Sample rate (Hz) from a batch's times; ``previous`` when they do not tell."""
    d = np.diff(t)
    d = d[np.isfinite(d)]
    if not d.size:
        return previous
    dt = float(np.median(d))
    return 1.0 / dt if dt > 0 else previous


def _circle(radius: float, n: int = 721) -> FloatArray:
    a = np.linspace(0.0, 2.0 * math.pi, n)
    return np.column_stack([radius * np.cos(a), radius * np.sin(a)])


def _fmt(v: Any, nd: int = 3) -> str:
    x = _num(v)
    return "–" if x is None else f"{x:.{nd}f}"


def _fmt_p(p: Any) -> str:
    x = _num(p)
    if x is None:
        return "–"
    return "< 1e-300" if x == 0 else f"{x:.1e}"


def findings_markdown(result: Mapping[str, Any]) -> str:
    """A circle or test result as a markdown report: ranking, parameters, ISO 230-4, advice."""
    plan = result.get("plan") or {}
    tm = result.get("timing") or {}
    idx = result.get("test_index", "?")
    if result.get("kind") == "circle":
        title = f"## Test {idx}: {str(result.get('direction', '')).upper()} circle (provisional)"
    else:
        title = f"## Test {idx}"
    if result.get("test_id"):
        title += f" · `{result['test_id']}`"
    machine = (result.get("machine") or {}).get("machine_id") or result.get("machine_id") or ""
    feed = _num(tm.get("measured_feed_mm_min")) or _num(tm.get("assumed_feed_mm_min"))
    lines = [
        title,
        "",
        f"machine `{machine}` · plane {plan.get('plane', '?')} · R {plan.get('radius_mm', '?')} mm · "
        f"F {plan.get('feed_mm_min', '?')} mm/min ({'measured' if result.get('kind') == 'test' else 'assumed'} "
        f"{_fmt(feed, 1)}) · data arc {plan.get('data_arc_deg', '?')}° · {plan.get('directions', '?')}",
        "",
        f"residual {_fmt(result.get('residual_rms_um'))} µm rms · arc-start lag {_fmt(tm.get('lag_s'), 4)} s · "
        f"spike width {_fmt(tm.get('spike_width_deg'), 2)}°",
        "",
        "### Ranked findings",
        "",
        "| # | pattern | share % | effect µm | p | significant |",
        "|---|---|---:|---:|---:|---|",
    ]
    ranking = list(result.get("ranking") or [])
    shown = [r for r in ranking if r.get("significant")] or ranking[:3]
    for i, r in enumerate(shown[:12], 1):
        lines.append(
            f"| {i} | {r.get('pattern')} | {_fmt(r.get('share_pct'), 2)} | {_fmt(r.get('effect_um'))} | "
            f"{_fmt_p(r.get('p_value'))} | {'**yes**' if r.get('significant') else 'no'} |"
        )
    params = result.get("parameters") or {}
    sig = [
        (k, p)
        for k, p in params.items()
        if isinstance(p, Mapping) and p.get("significant") and _num(p.get("value")) is not None
    ]
    if sig:
        lines += ["", "### Parameters (significant)", "", "| parameter | value | ± | unit |", "|---|---:|---:|---|"]
        for k, p in sig:
            lines.append(f"| {k} | {_fmt(p.get('value'), 3)} | {_fmt(p.get('stderr'), 3)} | {p.get('unit', '')} |")
    iso = result.get("iso230_4")
    if iso:
        lines += [
            "",
            "### ISO 230-4",
            "",
            "| G CCW | G CW | G(b) | H | F max | F min |",
            "|---:|---:|---:|---:|---:|---:|",
            "| "
            + " | ".join(_fmt(iso.get(k), 2) for k in ("G_ccw_um", "G_cw_um", "G_b_um", "H_um", "F_max_um", "F_min_um"))
            + " |",
            "",
            "µm; " + str((iso.get("conditions") or {}).get("centre_removal", "")),
        ]
    nz = result.get("noise")
    if nz:
        lines += [
            "",
            f"Vibration {_fmt(nz.get('vibration_um'))} µm above {nz.get('vibration_cutoff_cpr')} cycles/rev "
            f"(strongest line {_fmt(nz.get('vibration_peak_um'))} µm, "
            f"{'significant' if nz.get('vibration_significant') else 'not significant'}); "
            f"stick-slip X {_fmt(nz.get('stick_slip_x_um'))} µm, Y {_fmt(nz.get('stick_slip_y_um'))} µm",
        ]
    for w in result.get("warnings") or []:
        lines += ["", f"**Warning:** {w}"]
    lines += verdict_markdown(result.get("verdict"))
    lines += ["", "### Advice", ""]
    advice = list(result.get("advice") or [])
    if not advice:
        lines.append("nothing significant to adjust")
    for a in advice:
        cp = f" (`{a['controller_parameter']}`)" if a.get("controller_parameter") else ""
        lines.append(f"- {a.get('action', '')}{cp}")
    return "\n".join(lines) + "\n"


def _clock_text(wall: float) -> str:
    """A wall-clock time as the viewer's events show it: UTC, to the millisecond."""
    return datetime.datetime.fromtimestamp(wall, datetime.UTC).strftime("%H:%M:%S.%f")[:-3] + " UTC"


def verdict_markdown(verdict: Any) -> list[str]:
    """The verdict against the configured limits (``[limits]``) as markdown lines; none without limits."""
    if not isinstance(verdict, Mapping) or not verdict.get("limits"):
        return []
    status = str(verdict.get("status", "?"))
    lines = ["", f"### Verdict: **{status.upper()}**", "",
             f"limits with k = {_fmt(verdict.get('coverage_k'), 1)} (fail only beyond the uncertainty)", "",
             "| quantity | value | ± (k u) | limit | margin | status |", "|---|---:|---:|---:|---:|---|"]
    for e in verdict["limits"]:
        st = str(e.get("status", ""))
        if e.get("within_uncertainty"):
            st += " (within uncertainty of the limit)"
        elif st == "not_evaluated":
            st += f": {e.get('reason', '')}"
        lines.append(f"| {e.get('name')} | {_fmt(e.get('value'), 3)} | {_fmt(e.get('uncertainty'), 3)} | "
                     f"{_fmt(e.get('limit'), 3)} | {_fmt(e.get('margin'), 3)} | {st} |")
    return lines


def trend_ranges(rows: FloatArray) -> dict[str, tuple[float, float]]:
    """The y range of each trend view (:data:`TREND_VIEWS`) from trend rows (test, wall time, the
    values of :data:`TRENDS`, then their standard errors; NaN: none): at least
    ``TREND_STDERR_SPAN`` standard errors either side of the mean (:func:`trend_limits`), so that a
    change within them looks flat.  A view without standard errors (G(b)) is left out: autoscaled."""
    out: dict[str, tuple[float, float]] = {}
    n = len(TRENDS)
    for origin, _title in TREND_VIEWS:
        vals: list[float | None] = []
        errs: list[float | None] = []
        for j, (path, _f, _l) in enumerate(TRENDS):
            if path == origin or path.startswith(origin + "/"):
                vals += [float(v) for v in rows[:, 2 + j]]
                errs += [float(e) for e in rows[:, 2 + n + j]]
        lim = trend_limits(vals, errs)
        if lim is not None and lim[1] > lim[0]:
            out[origin] = lim
    return out


def default_blueprint(ranges: Mapping[str, tuple[float, float]] | None = None) -> rrb.Blueprint:
    """The layout: polar plot and length on the left; findings, trends and events on the right.

    ``ranges``: the y range of trend views by origin (:func:`trend_ranges`); the others autoscale.
    """
    bound = 1.75 * R0
    ranges = ranges or {}
    trends = rrb.Grid(
        *(
            rrb.TimeSeriesView(
                name=title, origin=f"trends/{origin}",
                axis_y=rrb.ScalarAxis(range=ranges[origin], zoom_lock=False) if origin in ranges else None,
            )
            for origin, title in TREND_VIEWS
        ),
        grid_columns=3,
        name="Trends across tests",
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial2DView(
                    name="Radial deviation (magnified): CCW blue, CW orange, fits dark",
                    origin="polar",
                    visual_bounds=rrb.VisualBounds2D(x_range=[-bound, bound], y_range=[-bound, bound]),
                ),
                rrb.TimeSeriesView(
                    name="Bar length L (mm)",
                    origin="length",
                    time_ranges=rrb.VisibleTimeRange(
                        "time",
                        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-300.0),
                        end=rrb.TimeRangeBoundary.cursor_relative(),
                    ),
                ),
                row_shares=[3, 1],
            ),
            rrb.Vertical(
                rrb.TextDocumentView(name="Findings", origin="findings"),
                trends,
                rrb.TextLogView(name="Events", origin="events"),
                row_shares=[3, 2, 1],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="time", play_state="following"),  # live: always the newest circle
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


# --------------------------------------------------------------------------- the listener


class _Prober:
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
        with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        return None
    return None


class _ServerProcess:
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
        self.url = f"rerun+http://{_host_for_url(host)}:{port}/proxy"  # where the daemon pushes
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
        self.proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL, env=env, close_fds=True)
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


_ABANDONED: list[rr.RecordingStream] = []  # recordings whose disconnect did not finish: never collected

# What the serve mode's server counts of what is sent (its history is bounded by those bytes), estimated
# on the high side from rerun-sdk 0.41's encoding (LZ4-compressed Arrow chunks, measured in .rrd files):
# a message costs 1.2-1.6 kB whatever it holds (a styled line strip 2-2.4 kB), a line-strip point 8 B,
# a scalar row (time, value, row id) about 20 B.
MSG_BYTES = 2000
STRIP_BYTES = 800
POINT_BYTES = 8
ROW_BYTES = 24
REFRESH_FRACTION = 0.5  # serve mode: the history is re-sent after this fraction of the server's limit
SCENE_REFRESH_S = 10.0  # serve mode: the references (static, a few kB) are re-sent this often
HISTORY_SHARE_WARN = 0.25  # warn when the history needs more than this share of the server's limit
MAX_PENDING_SAMPLES = 200_000  # samples waiting to be processed: at most this many
MIN_SEND_POINTS = 8  # fewer new samples than this in a send_interval_s: sent every polar_update_s instead
HISTORY_SLICE_BYTES = 512 * 1024  # a periodic sending of the history: at most this much per flush
STALL_FLUSH_S = 2.0  # serve mode: a flush to the (local) server that takes longer says it takes nothing
STALL_RECHECK_S = 1.0  # ... and is tried again this much later; a second such flush restarts the server


class _Ring:
    """A fixed-capacity FIFO of float64 rows (``width`` columns); the oldest rows are overwritten."""

    def __init__(self, capacity: int, width: int) -> None:
        self.buf = np.empty((max(1, capacity), width))
        self.start = 0
        self.n = 0

    def __len__(self) -> int:
        return self.n

    @property
    def capacity(self) -> int:
        return int(self.buf.shape[0])

    def extend(self, rows: FloatArray) -> None:
        cap = self.capacity
        rows = rows[-cap:]
        k = rows.shape[0]
        if not k:
            return
        end = (self.start + self.n) % cap
        first = min(k, cap - end)
        self.buf[end : end + first] = rows[:first]
        self.buf[: k - first] = rows[first:]
        self.n += k
        if self.n > cap:
            self.start = (self.start + self.n - cap) % cap
            self.n = cap

    def rows(self) -> FloatArray:
        """The rows, oldest first (a copy)."""
        end = self.start + self.n
        if end <= self.capacity:
            return self.buf[self.start : end].copy()
        return np.concatenate([self.buf[self.start :], self.buf[: end - self.capacity]])


class _Samples:
    """The current test's samples kept for the polar plot: columns of ``capacity`` rows, allocated once.

    The caller keeps them within ``capacity`` (one block for the daemon's life, its pages used as
    needed: no reallocations, so no heap fragments); a larger append grows them, and :meth:`keep`
    returns to ``capacity`` afterwards.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.data = np.empty((3, capacity))  # t_host, t_device, length
        self.n = 0

    def append(self, th: FloatArray, td: FloatArray, L: FloatArray) -> None:
        k = th.size
        if self.n + k > self.data.shape[1]:
            grown = np.empty((3, max(2 * self.data.shape[1], self.n + k)))
            grown[:, : self.n] = self.data[:, : self.n]
            self.data = grown
        self.data[0, self.n : self.n + k] = th
        self.data[1, self.n : self.n + k] = td
        self.data[2, self.n : self.n + k] = L
        self.n += k

    def keep(self, mask_or_slice: Any) -> None:
        """Keep only the rows selected (a boolean mask or a slice), in place."""
        kept = self.data[:, : self.n][:, mask_or_slice]
        self.n = kept.shape[1]
        if self.data.shape[1] > self.capacity and self.n <= self.capacity:
            self.data = np.empty((3, self.capacity))
        self.data[:, : self.n] = kept

    @property
    def t_host(self) -> FloatArray:
        return self.data[0, : self.n]

    @property
    def t_device(self) -> FloatArray:
        return self.data[1, : self.n]

    @property
    def length(self) -> FloatArray:
        return self.data[2, : self.n]


@dataclass
class _Curve:
    """A polar curve in micrometres: angles ``u`` (rad) and raw deviations ``dr`` (um), and its style.

    ``live``: a measured curve growing during its data arc, sent in pieces: completed pieces of
    ``piece`` points go to child entities ``<path>/<k>`` once, the growing tip to ``<path>`` itself.
    ``key``: what the points so far depend on (first sample time, decimation step): while it holds
    they are a prefix of the next update's.  ``pieces``: completed pieces logged since the entity was
    last cleared; ``stale``: the logged pieces no longer match (clear them first).
    """

    u: FloatArray
    dr: FloatArray
    colour: str
    width: float
    order: float
    live: bool = False
    key: tuple[float, int] | None = None
    pieces: int = 0
    stale: bool = False


@dataclass
class _TestRecord:
    """A finished test as a late viewer is sent it: display points, scale, findings, and when."""

    index: int
    start_wall: float  # its feed-in (the polar plot was cleared then)
    wall: float  # its result
    scale_um: float
    curves: dict[str, tuple[NDArray[np.float32], str, float, float]]  # path -> (points, colour, width, order)
    findings: str


LAYOUT_NAMESPACE = uuid.UUID("5f0c3a7e-6b1d-4c2a-9e57-b0a11ba40001")  # the layout's view and container ids


class _Blueprints:
    """The viewer's layouts, sent on one blueprint stream for the viewer's whole life.

    rerun 0.41's ``send_blueprint`` (and ``set_sinks(..., default_blueprint=)``)
    makes a new blueprint stream for every call, and a dropped stream is never
    freed: two threads and about 0.3 MB each (measured; neither ``flush``,
    ``disconnect`` nor ``flush_and_cleanup_orphaned_recordings`` frees it).  A
    daemon that sends a layout at every viewer's connection and whenever a
    trend's range moves grows by that much each time, for months.  Here each
    layout is logged to the one stream, at the next step of its ``blueprint``
    timeline (a viewer takes the latest), and what the stream collected is
    sent to the recording's sinks as rerun's own ``send_blueprint`` does.  A new
    sink gets the stream's store info again (:meth:`new_sink`: a fresh memory
    sink starts with it).
    """

    def __init__(self, rec: rr.RecordingStream, application_id: str) -> None:
        from rerun.recording_stream import RecordingStream
        from rerun_bindings import new_blueprint

        self._rec = rec
        self._stream = RecordingStream._from_native(
            new_blueprint(application_id=application_id, make_default=False, make_thread_default=False,
                          default_enabled=True))
        self._storage = self._stream.memory_recording()
        self._step = 0
        self._paths: set[str] = set()  # the views and containers of the last layout sent

    def new_sink(self) -> None:
        """The recording's sinks changed: the next layout goes out with the store's info."""
        self._storage = self._stream.memory_recording()

    def send(self, blueprint: rrb.Blueprint) -> None:
        from rerun_bindings import send_blueprint

        bp = blueprint.to_blueprint()
        # Each view and container keeps its place's id from layout to layout (rerun draws a new one for every
        # object), so that a new layout overwrites the last instead of leaving it in the store unreachable (a
        # viewer warns of each such entity); one that is no longer in the layout is cleared.
        paths = _stable_ids(bp.root_container, "root")
        self._stream.set_time("blueprint", sequence=self._step)
        self._step += 1
        bp._log_to_stream(self._stream)
        for path in sorted(self._paths - paths):
            self._stream.log(path, rr.Clear(recursive=True))
        self._paths = paths
        send_blueprint(self._storage.storage, True, True, recording=self._rec.to_native())


def _stable_ids(item: rrb.Container | rrb.View, place: str) -> set[str]:
    """Give a container and everything in it ids from their places in the layout; return their blueprint paths."""
    item.id = uuid.uuid5(LAYOUT_NAMESPACE, place)
    out = {item.blueprint_path()}
    if isinstance(item, rrb.Container):
        for i, sub in enumerate(item.contents):
            out |= _stable_ids(sub, f"{place}/{i}")
    return out


class RerunViewer(Listener):
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
    ) -> None:
        self.options = options or ViewerOptions()
        self.plan = plan
        self.machine = machine
        self.recording_id = recording_id or str(uuid.uuid4())
        self._recording_name = self.options.recording_name or f"ballbar {time.strftime('%Y-%m-%d %H:%M:%S')}"
        self._closed = False
        self._stop_lock = threading.Lock()
        self._rec: rr.RecordingStream | None = None
        self._sink_live = False
        self._sink_failures = 0  # the prober's failure count when the sink was made
        self._next_retry = 0.0
        self._next_health = 0.0
        self._stalled_since: float | None = None  # serve mode: when a flush to the server first timed out
        self._prober: _Prober | None = None
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
        self._samples = _Samples(self.options.max_buffer_samples + MAX_PENDING_SAMPLES)
        self._keep_every = 1  # extra thinning after the buffer hit max_buffer_samples
        self._rate_hz = float("nan")  # on the analysis clock
        self._host_hz = float("nan")
        # the current test
        self._test_index = 0
        self._in_test = False
        self._test_start_wall = time.time()
        self._live: dict[int, ArcTiming] = {}  # provisional timing per direction
        self._final: dict[int, Mapping[str, Any]] = {}  # direction -> latest result drawn for it
        self._next_polar = -math.inf
        # what a (re)connecting viewer is sent again; see "polar plot" below
        self._curves: dict[str, _Curve] = {}
        self._piece = max(2, math.ceil(self.options.polar_points / self.options.polar_pieces))
        self._scale_um = self.options.scale_um or AUTO_SCALE_START_UM
        self._setup_result: Mapping[str, Any] | None = None
        self._hints = (1.0, 0.0, 3.0)  # feed ratio, overhead (s), spike width (deg) from the last test
        self._findings_md = ""
        # the history a late viewer gets (see ViewerOptions): tests whole, trends, the length decimated
        self._history: deque[_TestRecord] = deque(maxlen=self.options.history_tests)
        self._trends = _Ring(TRENDS_KEPT, 2 + 2 * len(TRENDS))  # test, wall, values, stderrs (NaN: none)
        self._trend_ranges: dict[str, tuple[float, float]] = {}  # the y ranges in the blueprint sent last
        self._length_history = _Ring(
            math.ceil(self.options.history_length_s * self.options.history_length_hz) + 1, 2
        )  # wall, L
        self._server: _ServerProcess | None = None
        self._sink_generation = 0
        if self.options.mode == "off":
            self._closed = True
            return
        if self.options.mode == "serve":
            need, limit = self.history_bytes_max(), _memory_bytes(self.options.server_memory_limit) or 0
            if need > HISTORY_SHARE_WARN * limit:
                log.warning(
                    "rerun viewer: the history for late viewers (%d tests, %g h of length) needs about %.0f MiB, "
                    "more than %d %% of server_memory_limit %s: late viewers may get less of it",
                    self.options.history_tests, self.options.history_length_s / 3600.0, need / 2**20,
                    round(100 * HISTORY_SHARE_WARN), self.options.server_memory_limit,
                )
        self._rec = rr.RecordingStream(self.options.application_id, recording_id=self.recording_id)
        self._blueprints = _Blueprints(self._rec, self.options.application_id)
        if self.options.mode == "serve":
            self._server = _ServerProcess(
                self.options.bind, self.options.port, self.options.server_memory_limit, self.options.server_rss_cap
            )
        if self.options.mode == "connect":
            addr = _proxy_address(self.options.url)
            assert addr is not None  # validated by ViewerOptions
            self._prober = _Prober(addr[0], addr[1], self.options.retry_s)
        self._maintain(time.monotonic())

    @classmethod
    def from_config(cls, cfg: Any) -> RerunViewer:
        """From the daemon's configuration (:func:`viewer_options`), with its ``plan`` and ``machine``."""
        return cls(viewer_options(cfg), plan=getattr(cfg, "plan", None), machine=getattr(cfg, "machine", None))

    # ------------------------------------------------------------------ state

    @property
    def address(self) -> str:
        return self.options.address

    @property
    def connected(self) -> bool:
        """A sink exists: serving, or pushing to a viewer that answered the last probe."""
        return self._sink_live

    def history_bytes_max(self) -> int:
        """Bytes (estimated, on the high side) of the history a late viewer is sent, when full."""
        o = self.options
        per_test = 10 * MSG_BYTES + 5 * STRIP_BYTES + POINT_BYTES * (4 * o.polar_points + 2 * 361) + 6000
        length = len(TRENDS) * MSG_BYTES + ROW_BYTES * (
            TRENDS_KEPT * len(TRENDS) + self._length_history.capacity
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
            "trend_points": len(self._trends),
            "sent_mib": round(self._sent_bytes / 2**20, 3),
            "history_pending": len(self._history_steps),
            **self.counters,
            **({"server": self._server.stats()} if self._server is not None else {}),
        }

    # ------------------------------------------------------------------ sinks

    def _maintain(self, now: float) -> None:
        """(Re)create the sink when needed; in connect mode, notice a viewer that went away."""
        rec = self._rec
        if rec is None:
            return
        if self.options.mode == "serve":
            srv = self._server
            assert srv is not None
            if self._sink_live and srv.generation != self._sink_generation:
                log.info("rerun viewer: the server was restarted; sending the scene again")
                self._sink_live = False
            if self._sink_live and now >= self._next_health:
                self._check_server_stream(rec, srv)
            if not self._sink_live and srv.listening and now >= self._next_retry:
                self._next_retry = now + min(self.options.retry_s, 0.5)
                self._sink_generation = srv.generation
                self._next_health = now + self.options.health_s
                self._stalled_since = None
                rec.set_sinks(rr.GrpcSink(srv.url))
                self._on_new_sink(
                    "serving on %s:%d (viewers: rerun %s)", self.options.bind, self.options.port, self.address
                )
            return
        pr = self._prober
        assert pr is not None
        if self._sink_live and pr.failures != self._sink_failures:
            log.info("rerun viewer at %s went away; reconnecting when it answers", self.options.url)
            self._sink_live = False
        if self._sink_live and now >= self._next_health:
            # A dead sink (viewer restarted between two probes) fails its flush at once.
            self._next_health = now + self.options.health_s
            try:
                rec.flush(timeout_sec=1.0)
            except Exception as err:  # rerun raises a bare RuntimeError
                log.info("rerun viewer at %s: stream lost (%s); reconnecting", self.options.url, err)
                self._sink_live = False
        if not self._sink_live and pr.up and now >= self._next_retry:
            self._next_retry = now + self.options.retry_s
            self._sink_failures = pr.failures
            rec.set_sinks(rr.GrpcSink(self.options.url))
            self._next_health = now + self.options.health_s
            self._on_new_sink("pushing to %s", self.options.url)

    def _check_server_stream(self, rec: rr.RecordingStream, srv: _ServerProcess) -> None:
        """Serve mode: whether the server takes the daemon's stream; one that has not for a while is restarted.

        A flush that times out (``STALL_FLUSH_S``) is looked at again ``STALL_RECHECK_S`` later; a
        second one in a row has the supervisor restart the server (what the gRPC client holds is
        the daemon's memory).  A flush that fails at once (the stream severed, the server alive)
        makes a new sink.
        """
        began = time.monotonic()
        try:
            rec.flush(timeout_sec=STALL_FLUSH_S)
        except Exception as err:  # rerun raises a bare RuntimeError
            now = time.monotonic()
            if now - began < 0.5 * STALL_FLUSH_S:
                log.info("rerun viewer: the stream to the server was lost (%s); sending the scene again", err)
                self._sink_live = False
                return
            if self._stalled_since is None:
                self._stalled_since = began
                self._next_health = now + STALL_RECHECK_S
                return
            self.counters["server_stalls"] += 1
            srv.request_restart(self._sink_generation,
                                f"it has taken none of the daemon's stream for {now - self._stalled_since:.0f} s "
                                "(a client flooding or wedging it)")
            self._stalled_since = None
            self._next_health = now + self.options.health_s
            return
        self._stalled_since = None
        self._next_health = time.monotonic() + self.options.health_s

    def _on_new_sink(self, msg: str, *args: Any) -> None:
        self._sink_live = True
        self.counters["sinks"] += 1
        log.info("rerun viewer: " + msg, *args)
        self._send_scene()

    def _log(self, path: str, entity: Any, nbytes: int = 0, *, static: bool = False) -> None:
        """``rec.log``, counting (an estimate of) what it sends: ``nbytes`` besides the message's own."""
        rec = self._rec
        assert rec is not None
        rec.log(path, entity, static=static)
        self._sent_bytes += MSG_BYTES + nbytes

    def _send_scene(self) -> None:
        """Everything a viewer that has just (re)connected needs, besides the live stream."""
        rec = self._rec
        assert rec is not None
        for c in self._curves.values():  # a new viewer has none of the pieces
            c.pieces, c.stale = 0, False
        self._trend_ranges = trend_ranges(self._trends.rows()) if len(self._trends) else {}
        self._blueprints.new_sink()
        self._blueprints.send(default_blueprint(self._trend_ranges))
        rec.send_recording_name(self._recording_name)
        self._log_static()
        self._send_history()
        self._redraw_all()

    def _send_history(self, sliced: bool = False) -> None:
        """What a late viewer gets: the last tests whole, the trends, the length decimated; then the present.

        Each at its own place on the timelines (a viewer that has it already gets the same again).
        In ``serve`` mode this is sent again whenever half the server's memory limit has been sent
        since (:meth:`_refresh_if_due`), so that the server's bounded buffer, which drops the oldest
        messages first, always holds it whole; ``sliced``: then a slice of at most
        ``HISTORY_SLICE_BYTES`` at each flush (the SDK's buffers stay small), else all at once.
        """
        self.counters["refreshes"] += 1
        self._refreshed_at = self._sent_bytes
        self._refreshed_mono = time.monotonic()
        if self._server is not None:
            self._clients_ended = self._server.clients_ended
        steps: list[Callable[[], None]] = [functools.partial(self._send_record, r) for r in self._history]
        if len(self._trends):
            steps.append(functools.partial(self._send_trends, self._trends.rows()))
        hist = self._length_history.rows()
        if hist.shape[0]:
            hist = hist[hist[:, 0] >= hist[-1, 0] - self.options.history_length_s]
            for i in range(0, hist.shape[0], 20_000):
                steps.append(functools.partial(self._send_length, hist[i : i + 20_000, 0], hist[i : i + 20_000, 1]))
        steps.append(functools.partial(self._send_present, sliced))
        self._history_steps = deque(steps)
        if not sliced:
            self._continue_history(math.inf)

    def _continue_history(self, budget: float = HISTORY_SLICE_BYTES) -> None:
        start = self._sent_bytes
        while self._history_steps and self._sent_bytes - start < budget:
            self._history_steps.popleft()()

    def _send_record(self, r: _TestRecord) -> None:
        rec = self._rec
        assert rec is not None
        rec.set_time("test", sequence=r.index)
        rec.set_time("time", timestamp=r.start_wall)
        for name in DIRECTIONS.values():
            self._log(f"polar/{name}", rr.Clear(recursive=True))
        rec.set_time("time", timestamp=r.wall)
        self._log_scale(r.scale_um)
        for path, (pts, colour, width, order) in r.curves.items():
            self._log_strip(path, pts, colour, width, order)
        self._log("findings", rr.TextDocument(r.findings, media_type=rr.MediaType.MARKDOWN), len(r.findings))
        self._set_times()

    def _send_present(self, emit: bool) -> None:
        """The references and the findings at the current time; ``emit``: the current curves too."""
        self._set_times()
        self._log_scale()
        if self._findings_md:
            self._log("findings", rr.TextDocument(self._findings_md, media_type=rr.MediaType.MARKDOWN),
                      len(self._findings_md))
        if emit:
            self._emit()

    def _refresh_if_due(self) -> None:
        """Serve mode: the history and the references sent again before the server's buffer can have lost them.

        The server drops its oldest messages first, whoever sent the new ones.  Due when half its limit
        has been sent by the daemon since; when a connection to the server ended since (a client that
        pushed into it, or a viewer that left: what it pushed may have evicted the scene); and every
        ``history_refresh_s`` (a client that floods it and stays connected).  The references (nominal
        circle, axes and their labels: a few kB, static) every ``SCENE_REFRESH_S``: a client's static data evicts
        them, and one that pushes for less than a second comes and goes between the supervisor's looks.
        """
        srv = self._server
        if self.options.mode != "serve" or srv is None:
            return  # a connected viewer keeps what it got; one that reconnects gets the scene again
        limit = _memory_bytes(self.options.server_memory_limit) or 0
        now = time.monotonic()
        why = ""
        if self._sent_bytes - self._refreshed_at >= REFRESH_FRACTION * limit:
            why = f"{(self._sent_bytes - self._refreshed_at) / 2**20:.1f} MiB sent since"
        elif srv.clients_ended != self._clients_ended:
            why = f"{srv.clients_ended - self._clients_ended} connection(s) to the server ended since"
        elif now - self._refreshed_mono >= self.options.history_refresh_s:
            why = f"{now - self._refreshed_mono:.0f} s since"
        if why:
            log.debug("rerun viewer: sending the history again (%s)", why)
            self._send_history(sliced=True)
        if why or now - self._static_mono >= SCENE_REFRESH_S:
            self._log_static()
        self._continue_history()

    def _log_static(self) -> None:
        self._static_mono = time.monotonic()
        ax1, ax2 = self.plan.axes if self.plan else ("X", "Y")
        radii = rr.Radius.ui_points(0.75)
        self._log(
            "polar/reference/nominal",
            rr.LineStrips2D([_circle(R0)], colors=[COLOURS["nominal"]], radii=radii, draw_order=1.0),
            POINT_BYTES * 721,
            static=True,
        )
        e = 1.65 * R0
        self._log(
            "polar/reference/axes",
            rr.LineStrips2D(
                [[[-e, 0.0], [e, 0.0]], [[0.0, -e], [0.0, e]]],
                colors=[COLOURS["axes"]],
                radii=rr.Radius.ui_points(0.5),
                draw_order=0.4,
            ),
            static=True,
        )
        self._log(
            "polar/reference/axis_labels",
            rr.Points2D(
                [[e, 0.0], [0.0, -e]],  # +y is down in the view
                labels=[f"+{ax1}", f"+{ax2}"],
                colors=[COLOURS["axes"]],
                radii=rr.Radius.ui_points(2.0),
                show_labels=True,
            ),
            static=True,
        )
        # the scale rings sit at fixed display radii (+-s, whatever s is); their labels change with s
        self._log(
            "polar/reference/scale",
            rr.LineStrips2D(
                [_circle(R0 * 1.5), _circle(R0 * 0.5)],
                colors=[COLOURS["scale"]],
                radii=rr.Radius.ui_points(0.5),
                draw_order=0.5,
            ),
            POINT_BYTES * 2 * 721,
            static=True,
        )
        self._log("length", rr.SeriesLines(names="L (mm)", colors=[(90, 90, 90)]), static=True)
        for path, _field, label in TRENDS:
            self._log(f"trends/{path}", rr.SeriesLines(names=label), static=True)
            self._log(f"trends/{path}", rr.SeriesPoints(names=label, marker_sizes=4.0), static=True)

    def _log_scale(self, scale_um: float | None = None) -> None:
        """The scale-dependent references, at the current time (the caller sets the timelines)."""
        tol, s = self.options.tolerance_um, scale_um or self._scale_um
        k = R0 / (2.0 * s)
        self._log(
            "polar/reference/band",
            rr.LineStrips2D(
                [_circle(R0 + k * tol, 361), _circle(max(R0 - k * tol, 0.0), 361)],
                colors=[COLOURS["band"]],
                radii=rr.Radius.ui_points(0.75),
                draw_order=2.0,
            ),
            POINT_BYTES * 2 * 361,
        )
        # Labels on points beside the rings: a strip's own label sits at its centroid, the centre.
        a = math.radians(75.0)
        rings = [
            (R0, f"R {self.plan.radius_mm:g} mm" if self.plan else "nominal", COLOURS["nominal"]),
            (R0 + k * tol, f"+{tol:g} µm", COLOURS["band"]),
            (max(R0 - k * tol, 0.0), f"-{tol:g} µm", COLOURS["band"]),
            (1.5 * R0, f"+{s:g} µm", COLOURS["scale"]),
            (0.5 * R0, f"-{s:g} µm", COLOURS["scale"]),
        ]
        self._log(
            "polar/reference/labels",
            rr.Points2D(
                [[r * math.cos(a), -r * math.sin(a)] for r, _t, _c in rings],
                labels=[t for _r, t, _c in rings],
                colors=[c for _r, _t, c in rings],
                radii=rr.Radius.ui_points(2.0),
                show_labels=True,
                draw_order=3.0,
            ),
            200,
        )

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
            i = _multiples(seq, every)
            return i[((status[i] & _INVALID) == 0) & np.isfinite(th[i]) & np.isfinite(L[i])]

        if th.size >= 2:
            # sample rates on the host clock (the length series) and on the analysis clock (the
            # polar plot); they differ for a simulator or a replay running faster than real time
            head = slice(0, 4096)
            self._host_hz = _rate(th[head], self._host_hz)
            self._rate_hz = _rate((th if self._use_host else td)[head], self._rate_hz)
        keep = picked(self._stride(self.options.buffer_hz) * self._keep_every)
        self._keep(th[keep], td[keep], L[keep])
        stride = self._stride(self.options.length_hz, self._host_hz)
        i = picked(stride)
        if i.size:
            wall = th[i] + (time.time() - time.monotonic())
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
            ev.t_host + (time.time() - time.monotonic()),
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
        self.counters["messages"] += 1
        kind = msg.get("kind")
        if kind == "alert":  # the monitor's alerts: one line in the events
            self._text_event(f"alert: {msg.get('message', msg.get('state'))}",
                             "INFO" if msg.get("cleared") else "WARN")
            return
        if kind not in ("config", "circle", "test", "event"):
            return  # status: nothing to draw
        self._flush(time.monotonic())  # a boundary: the samples before it are drawn and sent first
        if kind == "config":
            cfg = msg.get("config")
            if isinstance(cfg, Mapping) and isinstance(cfg.get("plan"), Mapping):
                self._set_plan(cfg["plan"], cfg.get("machine"))
        elif kind in ("circle", "test"):
            if isinstance(msg.get("plan"), Mapping):
                self._set_plan(msg["plan"], msg.get("machine"))
            self._check_clock(msg)
            self._result(msg)
        elif kind == "event" and msg.get("origin") != "source":  # source events come with their batch
            self._check_clock(msg)
            self._event(msg)

    def _set_plan(self, plan: Mapping[str, Any], machine: Any) -> None:
        try:
            new = TestPlan.from_dict(dict(plan))
            mach = MachineConfig.from_dict(dict(machine)) if isinstance(machine, Mapping) else self.machine
        except (TypeError, ValueError) as err:
            log.warning("rerun viewer: ignoring a plan it cannot read: %s", err)
            return
        changed = new != self.plan
        self.plan, self.machine = new, mach
        if changed and self._sink_live:
            self._log_static()
            self._set_times()
            self._log_scale()

    def _check_clock(self, msg: Message) -> None:
        """Follow the clock the analysis runs on: the message's ``time_axis``, else its times.

        Without ``time_axis``, an engine time (``last_sample_t``, an event's
        ``t_s``) must lie near the newest sample's time on that clock.
        """
        if self.options.clock != "auto":
            return
        axis = msg.get("time_axis")
        use_host = self._use_host
        if axis in ("device", "host"):
            use_host = axis == "host"
        elif (t := _num(msg.get("last_sample_t")) or _num(msg.get("t_s"))) is not None:

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

    def _event(self, msg: Message) -> None:
        ev = str(msg.get("event", ""))
        idx = msg.get("test_index")
        t_s = _num(msg.get("t_s"))
        wall = self._wall_of(t_s) if t_s is not None else None
        text = f"test {idx}: {ev}"
        if wall is not None:
            text += f" at {_clock_text(wall)}"
        elif t_s is not None:  # its samples are gone: the analysis clock's time, and which clock
            text += f" at t={t_s:.3f} s on the {'host' if self._use_host else 'device'} clock"
        if msg.get("message"):
            text += f": {msg['message']}"
        if ev == "feed_in" and isinstance(idx, int) and _num(msg.get("t_s")) is not None:
            self._start_test(idx, float(msg["t_s"]))
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
        return float(buf.t_host[i]) + (time.time() - time.monotonic())

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
        if self._sink_live:
            self._set_times()
            for name in DIRECTIONS.values():
                self._log(f"polar/{name}", rr.Clear(recursive=True))

    def _end_test(self) -> None:
        self._in_test = False
        self._live = {}
        self._keep_every = 1

    def _result(self, res: Message) -> None:
        idx = res.get("test_index")
        if isinstance(idx, int) and idx != self._test_index:
            self._test_index = idx
        if res.get("kind") == "test":
            # the analyzer's own rule: an implausible feed teaches the next test's provisional timing nothing
            hints = TimingHints.learnt(res.get("timing") or {}, TimingHints(*self._hints))
            if hints is not None:
                self._hints = (hints.feed_ratio, hints.overhead_s, hints.spike_width_deg)
            for d in DIRECTIONS:
                if result_timing(res, d) is not None:
                    self._final[d] = res
        else:
            d = 1 if res.get("direction") == "ccw" else -1
            self._final[d] = res
        if self.options.remove_setup and _param(res, "centre_x_um") is not None:
            self._setup_result = res
        self._findings_md = findings_markdown(res)
        trend = self._trend_values(res) if res.get("kind") == "test" else {}
        wall = time.time()
        if trend and isinstance(idx, int):
            row = np.array([[idx, wall, *(trend.get(p, (math.nan, math.nan))[0] for p, _f, _l in TRENDS),
                             *(trend.get(p, (math.nan, math.nan))[1] for p, _f, _l in TRENDS)]])
            self._trends.extend(row)
        if self._sink_live:
            self._set_times(wall)
            self._log("findings", rr.TextDocument(self._findings_md, media_type=rr.MediaType.MARKDOWN),
                      len(self._findings_md))
            if trend and isinstance(idx, int):
                self._send_trends(row)
                self._rescale_trends()
        self._redraw_all(wall)  # cached even without a viewer: one that connects later gets this test
        if res.get("kind") == "test":
            if isinstance(idx, int):
                self._record(idx, wall)
            self._end_test()

    def _record(self, index: int, wall: float) -> None:
        """Keep test ``index``'s final state for late viewers (:meth:`_send_history`)."""
        if self.options.history_tests <= 0:
            return
        curves = {}
        for path, c in self._curves.items():
            pts = polar_points(c.u, c.dr - setup_deviation_um(self._setup_result, c.u), self._scale_um)
            curves[path] = (pts.astype(np.float32), c.colour, c.width, c.order)
        self._history.append(
            _TestRecord(index, self._test_start_wall, wall, self._scale_um, curves, self._findings_md)
        )

    @staticmethod
    def _trend_values(res: Mapping[str, Any]) -> dict[str, tuple[float, float]]:
        """Per trend entity: (value, standard error; NaN: none)."""
        out: dict[str, tuple[float, float]] = {}
        iso = res.get("iso230_4") or {}
        for path, field, _label in TRENDS:
            if field.startswith("G_"):
                v, se = _num(iso.get(field)), None
            else:
                v = _param(res, field)
                p = res.get("parameters", {}).get(field)
                se = _num(p.get("stderr")) if isinstance(p, Mapping) else None
            if v is not None:
                out[path] = (v, math.nan if se is None else se)
        return out

    def _rescale_trends(self) -> None:
        """A new blueprint when a trend's y range (:func:`trend_ranges`) moved by more than a tenth of itself:
        once per test at most, and rarely once the trends have settled (the server keeps every blueprint)."""
        new = trend_ranges(self._trends.rows())
        old = self._trend_ranges

        def moved(k: str) -> bool:
            if (k in new) != (k in old):
                return True
            if k not in new:
                return False
            (a0, a1), (b0, b1) = new[k], old[k]
            return max(abs(a0 - b0), abs(a1 - b1)) > 0.1 * (b1 - b0)

        if any(moved(k) for k in {*new, *old}):
            self._trend_ranges = new
            self._blueprints.send(default_blueprint(new))

    def _send_trends(self, rows: FloatArray) -> None:
        """Trend points: rows of (test, wall time, one value per TRENDS entry, NaN where none)."""
        rec = self._rec
        assert rec is not None
        for j, (path, _field, _label) in enumerate(TRENDS):
            m = np.isfinite(rows[:, 2 + j])
            if not m.any():
                continue
            rec.send_columns(
                f"trends/{path}",
                indexes=[
                    rr.TimeColumn("test", sequence=rows[m, 0].astype(np.int64)),
                    rr.TimeColumn("time", timestamp=rows[m, 1]),
                ],
                columns=rr.Scalars.columns(scalars=rows[m, 2 + j]),
            )
            self._sent_bytes += MSG_BYTES + ROW_BYTES * int(m.sum())

    # ------------------------------------------------------------------ polar plot
    #
    # Curves are kept in micrometres (angle, raw dR = L - R, or the model's dR) and turned into
    # display points when logged: a new scale, a new set-up estimate or a viewer that connects
    # later all re-emit them consistently, even after the samples behind them were let go.
    # A live curve is sent in pieces (see _Curve): each update sends its growing tip and the
    # pieces completed since the last one, never the whole curve again.

    def _redraw_live(self) -> None:
        t, _L = self._analysis_time()
        if not t.size:
            return
        paths = []
        for d, timing in self._live.items():
            if d not in self._final and t[-1] > timing.start_s and self._update_measured(d, timing, live=True):
                paths.append(f"polar/{DIRECTIONS[d]}/measured")
        if paths and not self._fit_scale(grow_only=True):
            self._emit(paths, full=False)

    def _redraw_all(self, wall: float | None = None) -> None:
        """Recompute every curve of the current test that the kept samples allow, rescale, emit."""
        for d in DIRECTIONS:
            res = self._final.get(d)
            timing = result_timing(res, d) if res is not None else self._live.get(d)
            if timing is not None:
                self._update_measured(d, timing, live=res is None)
            if res is not None:
                self._update_model(d, res)
        self._fit_scale(grow_only=not any(r.get("kind") == "test" for r in self._final.values()), wall=wall)
        self._emit(wall=wall)

    def _measured(self, d: int, timing: ArcTiming) -> tuple[FloatArray, FloatArray, tuple[float, int] | None]:
        """Angles (rad), raw deviations ``L - R`` (um) of the kept samples of ``d``'s data arc, and their key."""
        plan = self.plan
        t, L = self._analysis_time()
        m = (t >= timing.start_s) & (t <= timing.end_s)
        if plan is None or np.count_nonzero(m) < 2:
            z = np.empty(0)
            return z, z, None
        t, L = t[m], L[m]
        # a fixed step over the whole arc, so that a growing live curve keeps its points
        kept_hz = (self._rate_hz if math.isfinite(self._rate_hz) else 1.0) / (
            self._stride(self.options.buffer_hz) * self._keep_every
        )
        step = max(1, math.ceil(min((timing.end_s - timing.start_s) * kept_hz, 1e9) / self.options.polar_points))
        t, L = t[::step], L[::step]
        return timing.angle_rad(plan, t), (L - plan.radius_mm) * 1000.0, (float(t[0]), step)

    def _update_measured(self, d: int, timing: ArcTiming, live: bool = False) -> bool:
        u, dr, key = self._measured(d, timing)
        if not u.size:
            return False
        name = DIRECTIONS[d]
        path = f"polar/{name}/measured"
        old = self._curves.get(path)
        new = _Curve(u, dr, name, 1.5, 10.0, live=live, key=key if live else None)
        if old is not None:
            new.pieces = old.pieces
            # the pieces sent so far stay valid only for the same live curve, grown
            new.stale = old.stale or (old.pieces > 0 and (not live or old.key != key))
        self._curves[path] = new
        return True

    def _update_model(self, d: int, res: Mapping[str, Any]) -> None:
        plan = TestPlan.from_dict(dict(res["plan"]))
        u_ds = math.radians(data_start_deg(plan, d))
        u = u_ds + d * np.linspace(0.0, math.radians(plan.data_arc_deg), self.options.polar_points)
        dr = model_deviation_um(res, d, u)
        if dr is None:
            return
        name = DIRECTIONS[d]
        self._curves[f"polar/{name}/model"] = _Curve(u, dr, f"{name}_model", 0.6, 11.0)

    def _fit_scale(self, grow_only: bool, wall: float | None = None) -> bool:
        """The automatic scale for the measured curves; True when it changed (everything re-emitted)."""
        if self.options.scale_um is not None:
            return False
        peaks = [
            float(np.abs(c.dr - setup_deviation_um(self._setup_result, c.u)).max())
            for path, c in self._curves.items()
            if path.endswith("/measured")
        ]
        if not peaks:
            return False
        new = nice_scale_um(max(peaks))
        if new == self._scale_um or (grow_only and new < self._scale_um):
            return False
        log.debug("rerun viewer: polar scale %g -> %g um", self._scale_um, new)
        self._scale_um = new
        if self._sink_live:
            self._set_times(wall)
            self._log_scale()
        self._emit(wall=wall)
        return True

    def _emit(self, paths: Sequence[str] | None = None, full: bool = True, wall: float | None = None) -> None:
        """Log cached curves at the current scale, set-up removed (all of them by default).

        ``full``: a live curve's pieces all again (a new scale or set-up); else only what it
        gained since the last update.
        """
        if not self._sink_live:
            return
        self._set_times(wall)
        for path in paths if paths is not None else list(self._curves):
            c = self._curves[path]
            if c.live:
                self._emit_live(path, c, full)
                continue
            if c.pieces or c.stale:  # it was drawn live: its pieces go
                self._log(path, rr.Clear(recursive=True))
                c.pieces, c.stale = 0, False
            self._log_strip(path, self._display(c), c.colour, c.width, c.order)
            self.counters["polar_draws"] += 1

    def _emit_live(self, path: str, c: _Curve, full: bool) -> None:
        P = self._piece
        n = c.u.size
        done = max(0, (n - 1) // P)  # complete pieces: piece k holds points kP .. (k+1)P (shared end point)
        if c.stale or (full and c.pieces > done):
            self._log(path, rr.Clear(recursive=True))
            c.pieces, c.stale = 0, False
        first = 0 if full else c.pieces
        for k in range(first, done):
            self._log_strip(f"{path}/{k}", self._display(c, k * P, (k + 1) * P + 1), c.colour, c.width, c.order)
            self.counters["polar_draws"] += 1
        c.pieces = done
        self._log_strip(path, self._display(c, done * P, n), c.colour, c.width, c.order)
        self.counters["polar_draws"] += 1

    def _log_strip(self, path: str, points: Any, colour: str, width: float, order: float) -> None:
        """One polar curve (or a piece of one)."""
        self._log(
            path,
            rr.LineStrips2D([points], colors=[COLOURS[colour]], radii=rr.Radius.ui_points(width), draw_order=order),
            STRIP_BYTES + POINT_BYTES * len(points),
        )

    def _display(self, c: _Curve, a: int = 0, b: int | None = None) -> FloatArray:
        u, dr = c.u[a:b], c.dr[a:b]
        return polar_points(u, dr - setup_deviation_um(self._setup_result, u), self._scale_um)

    def _set_times(self, wall: float | None = None) -> None:
        rec = self._rec
        assert rec is not None
        rec.set_time("time", timestamp=wall if wall is not None else time.time())
        rec.set_time("test", sequence=self._test_index)

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


__all__ = [
    "TREND_VIEWS",
    "ArcTiming",
    "RerunViewer",
    "ViewerConfigError",
    "ViewerOptions",
    "default_blueprint",
    "findings_markdown",
    "model_deviation_um",
    "polar_points",
    "provisional_timing",
    "result_timing",
    "setup_deviation_um",
    "trend_ranges",
    "viewer_options",
]
