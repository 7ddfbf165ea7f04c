"""What the live view draws, and how it reaches a viewer: the sinks, the history a late viewer gets, the
references, the last complete test, the test in progress, and the trends.

:class:`Scene` is the drawing half of :class:`~ballbar.daemon.rerun.listener.RerunViewer` (a mixin: the
listener half feeds it samples and results).  Entities (timelines ``time``, the wall clock, and ``test``,
the test's number within this daemon run)::

    polar/...                   the last complete test, drawn at its result and kept until the next one:
      polar/{ccw,cw}/measured     the measured radial deviation, set-up removed, magnified
      polar/{ccw,cw}/model        the fitted model
      polar/verdict               a bar in the verdict's colour (fail red, warning amber, pass green, no
                                  limits grey), labelled with the verdict in words; a test sent with the
                                  history says so, on a dimmed bar (:meth:`Scene._send_record`)
      polar/reference/...         nominal circle, axes, the scale rings (+-1..3 divisions) and their labels
    live/...                    the test in progress, from its feed-in: the same entities, the measured
                                  curves grown live in pieces (each completed piece once in
                                  measured/<k>), the circles' provisional models; live/status says what
                                  the test is doing
    findings                    TextDocument: the last complete test's verdict in words, then the detail
    trends/<quantity>           one point per test; children limits (the limit and the warning level), band
                                  (value +- k u, and the Theil-Sen trend as it stood at each test), pad
    length, events              the bar length (mm); feed-in/out, rejected tests, source events, alerts

A curve is kept in micrometres (angle, raw dR = L - R, or the model's dR) and turned into display points
when logged: a new scale, a new set-up estimate or a viewer that connects later all re-emit it
consistently, even after the samples behind it were let go.  Each view has its own scale (a division of
1, 2 or 5 x 10^n um) so that every point of its curves lies inside its outermost ring.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ballbar.analysis.plan import MachineConfig, TestPlan
from ballbar.analysis.plans import plan_of_result
from ballbar.analysis.program import data_start_deg

from .blueprint import TREND_LINES, TRENDS, Blueprints, default_blueprint, trend_ranges
from .buffers import Ring, Samples
from .findings import headline, set_headline, set_markdown
from .geometry import (
    COLOURS,
    DIRECTIONS,
    POLAR_DIVISIONS,
    R0,
    STATUS_RGB,
    ArcTiming,
    circle,
    model_deviation_um,
    nice_scale_um,
    num,
    param,
    polar_points,
    result_timing,
    ring_radius,
    setup_deviation_um,
)
from .options import ViewerOptions, memory_bytes
from .server import ServerProcess

if TYPE_CHECKING:
    import rerun as rr
else:
    from ..lazy import LazyModule

    rr = LazyModule("rerun")

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

# What the serve mode's server counts of what is sent (its history is bounded by those bytes), estimated
# on the high side from rerun-sdk 0.41's encoding (LZ4-compressed Arrow chunks, measured in .rrd files):
# a message costs 1.2-1.6 kB whatever it holds (a styled line strip 2-2.4 kB), a line-strip point 8 B,
# a scalar row (time, value, row id) about 20 B.
MSG_BYTES = 2000
STRIP_BYTES = 800
POINT_BYTES = 8
ROW_BYTES = 24
# serve mode: the history is re-sent after this fraction of the server's limit; with the history at most
# HISTORY_SHARE_WARN (0.25) of it, the last whole sending and all sent since fit (0.65 + 0.25 < 1). More often is
# not safer: a small server lost part of the last sending more often at 0.5 and 0.35 (commit body).
REFRESH_FRACTION = 0.65
SCENE_REFRESH_S = 10.0  # serve mode: the references (static, a few kB) are re-sent this often
HISTORY_SLICE_BYTES = 512 * 1024  # a periodic sending of the history: at most this much per flush
STALL_FLUSH_S = 2.0  # serve mode: a flush to the (local) server that takes longer says it takes nothing
STALL_RECHECK_S = 1.0  # ... and is tried again this much later; a second such flush restarts the server
BAR_Y = -1.9 * R0  # the verdict bar and the status line, above the plot (+y is down in the view)
# trend rows: test, wall time, the TRENDS values, their standard uncertainties, per TRENDS entry its limit and
# warning level (NaN: none), the Theil-Sen trend of each as it stood at that test, and the coverage factor k
N_TRENDS = len(TRENDS)
TREND_FIT_TESTS = 30  # the Theil-Sen trend and its forecast over the last tests (all pairs: O(n^2) each)
TREND_WIDTH = 2 + 5 * N_TRENDS + 1


@dataclass
class Curve:
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


def viewer_command() -> str:
    """The viewer to run on this PC: the ``rerun`` beside this interpreter (the venv's, which rerun-sdk installed:
    the daemon's version), else ``rerun`` on the PATH."""
    import os
    import sys

    exe = os.path.join(os.path.dirname(sys.executable), "rerun")
    return exe if os.access(exe, os.X_OK) else "rerun"


PAST_GREY = (70, 74, 84)  # a test of the history's verdict bar: its colour half way to this grey
PAST_WORDS = "from the history"


def past_headline(r: TestRecord, now: float | None = None) -> str:
    """``FAIL · test 9 at 23:10:05 UTC · from the history`` (a test of another day than ``now``'s: ``of 2026-12-06
    23:10 UTC``): short enough for the bar at 1280 px."""
    import datetime

    head = " · ".join(r.headline.split(" · ")[:2])  # the verdict's word and the test (with its plan)
    when = datetime.datetime.fromtimestamp(r.wall, datetime.UTC)
    today = datetime.datetime.fromtimestamp(time.time() if now is None else now, datetime.UTC).date()
    at = f"at {when:%H:%M:%S} UTC" if when.date() == today else f"of {when:%Y-%m-%d %H:%M} UTC"
    return f"{head} {at} · {PAST_WORDS}"


def past_findings(r: TestRecord) -> str:
    """The findings of a test of the history, their heading saying so."""
    head, sep, rest = r.findings.partition("\n")
    return f"{head} · {PAST_WORDS}{sep}{rest}"


@dataclass
class TestRecord:
    """A finished test as the last-complete-test view draws it (and a late viewer is sent it): display points,
    scale, verdict, findings, and when."""

    index: int
    wall: float  # its result
    scale_um: float
    curves: dict[str, tuple[NDArray[np.float32], str, float, float]]  # name -> (points, colour, width, order)
    findings: str
    status: str  # pass, warning, fail, none
    headline: str
    plan: str | None = None  # the plan's name, with a library of several
    axes: tuple[str, str] | None = None  # its plane's axes, with a library of several


class Scene:
    """The drawing half of :class:`~ballbar.daemon.rerun.listener.RerunViewer` (see the module docstring)."""

    options: ViewerOptions
    plan: TestPlan | None
    machine: MachineConfig | None
    counters: dict[str, int]
    _rec: rr.RecordingStream | None
    _blueprints: Blueprints
    _server: ServerProcess | None
    _prober: Any
    _recording_name: str
    _sink_live: bool
    _sink_failures: int
    _sink_generation: int
    _next_retry: float
    _next_health: float
    _stalled_since: float | None
    _sent_bytes: int
    _refreshed_at: int
    _refreshed_mono: float
    _clients_ended: int
    _static_mono: float
    _history_steps: deque[Callable[[], None]]
    _history: deque[TestRecord]
    _trends: Ring
    _trend_ranges: dict[str, tuple[float, float]]
    _length_history: Ring
    _curves: dict[str, Curve]
    _piece: int
    _scale_um: float
    _setup_result: Mapping[str, Any] | None
    _findings_md: str
    _last: TestRecord | None
    _live_status: str
    _final: dict[int, Mapping[str, Any]]
    _live: dict[int, ArcTiming]
    _samples: Samples
    _use_host: bool
    _rate_hz: float
    _keep_every: int
    _test_index: int
    # a library of several plans (the per-plan layout; empty: one plan, the single view): name -> its axes
    _plans: dict[str, tuple[str, str]]
    _plan_records: dict[str, TestRecord]  # each plan's latest test, as its view draws it
    _plan_trends: dict[str, Ring]  # each plan's trend rows
    _set_bar: tuple[str, str]  # the machine's verdict bar: status and text
    _set_md: str  # the set's verdict and figures in words, the head of the findings

    @property
    def address(self) -> str:
        """Where viewers find the stream: the URL to give ``rerun``."""
        return self.options.address

    def _stride(self, limit_hz: float, rate_hz: float | None = None) -> int:
        raise NotImplementedError

    def _analysis_time(self) -> tuple[FloatArray, FloatArray]:
        raise NotImplementedError

    def _send_length(self, wall: FloatArray, L: FloatArray, rec: rr.RecordingStream | None = None) -> None:
        raise NotImplementedError

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
                    "serving on %s:%d (viewers: %s %s)", self.options.bind, self.options.port, viewer_command(),
                    self.address,
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

    def _check_server_stream(self, rec: rr.RecordingStream, srv: ServerProcess) -> None:
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
        self._trend_ranges = self._ranges()
        self._blueprints.new_sink()
        self._blueprints.send(default_blueprint(self._trend_ranges, self._plans or None))
        rec.send_recording_name(self._recording_name)
        self._log_static()
        self._send_history()
        self._redraw_all()

    def _send_history(self, sliced: bool = False) -> None:
        """What a late viewer gets: the last tests whole, the trends, the length decimated; then the present.

        Each at its own place on the timelines (a viewer that has it already gets the same again).
        In ``serve`` mode this is sent again whenever ``REFRESH_FRACTION`` of the server's memory limit has been sent
        since (:meth:`_refresh_if_due`), so that the server's bounded buffer, which drops the oldest
        messages first, always holds it whole; ``sliced``: then a slice of at most
        ``HISTORY_SLICE_BYTES`` at each flush (the SDK's buffers stay small), else all at once.
        """
        self.counters["refreshes"] += 1
        self._refreshed_at = self._sent_bytes
        self._refreshed_mono = time.monotonic()
        if self._server is not None:
            self._clients_ended = self._server.clients_ended
        steps: list[Callable[[], None]] = [functools.partial(self._send_record, r, past=True) for r in self._history]
        steps += [functools.partial(self._send_record, r, f"plans/{p}", past=True)
                  for p, r in self._plan_records.items()]
        if len(self._trends) and not self._plans:
            steps.append(functools.partial(self._send_trends, self._trends.rows()))
        for p, ring in self._plan_trends.items():
            if len(ring):
                steps.append(functools.partial(self._send_trends, ring.rows(), True, f"plans/{p}/trends"))
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

    def _send_record(self, r: TestRecord, view: str = "polar", past: bool = False) -> None:
        """A finished test in the last-complete-test view (or ``view``: its plan's), at its own time.

        ``past``: sent with the history.  A viewer that connects gets the server's buffer oldest first, a bounded
        amount per frame, and shows each test as it arrives for 10 s and more; so the verdict bar and the
        findings' heading of a test from the history say so (its time, ``from the history``, the bar's colour
        dimmed), and :meth:`_send_present` states the last test's verdict again at the present, undimmed.
        """
        rec = self._rec
        assert rec is not None
        rec.set_time("test", sequence=r.index)
        rec.set_time("time", timestamp=r.wall - 0.001)  # what the last test drew goes just before
        for name in DIRECTIONS.values():
            self._log(f"{view}/{name}", rr.Clear(recursive=True))
        rec.set_time("time", timestamp=r.wall)
        self._log_scale(view, r.scale_um)
        if r.axes is not None and view == "polar":  # it shows every plan's tests in turn: their axes with them,
            self._log_axis_labels(view, r.axes, static=False)  # at the test's time (a refresh re-sends older ones)
        for name, (pts, colour, width, order) in r.curves.items():
            self._log_strip(f"{view}/{name}", pts, colour, width, order)
        if past:
            self._log_past_verdict(r, view)
        else:
            self._log_verdict(r.status, r.headline, view)
        if view == "polar":
            self._log_findings(past_findings(r) if past else r.findings)
        self._set_times()

    def _log_past_verdict(self, r: TestRecord, view: str) -> None:
        """A test of the history's verdict: its word and test, when, ``from the history``, on a dimmed bar."""
        colour = STATUS_RGB.get(r.status, STATUS_RGB["none"])
        dimmed = tuple((c + g) // 2 for c, g in zip(colour, PAST_GREY, strict=True))
        self._log_bar(f"{view}/verdict", (dimmed[0], dimmed[1], dimmed[2]), past_headline(r))

    def _log_findings(self, md: str) -> None:
        """The findings document: with a library of plans, the set's verdict first."""
        text = (self._set_md + md) if self._plans else md
        self._log("findings", rr.TextDocument(text, media_type=rr.MediaType.MARKDOWN), len(text))

    def _log_set(self) -> None:
        """The machine's verdict: a bar in the set's colour, the verdict in words on it (at the current time)."""
        status, text = self._set_bar
        self._log_bar("set/verdict", STATUS_RGB.get(status, STATUS_RGB["none"]), text)

    def _on_set(self, s: Mapping[str, Any]) -> None:
        """A set result: the machine's verdict bar and the head of the findings."""
        self._set_bar = set_headline(s)
        self._set_md = set_markdown(s)
        if self._plans and self._sink_live:
            self._set_times()
            self._log_set()
            if self._last is not None:
                self._log_findings(self._last.findings)

    def _send_present(self, emit: bool) -> None:
        """The references, the last test and the test in progress at the current time; ``emit``: the current
        curves too."""
        self._set_times()
        self._log_scale("live")
        self._log_status()
        if self._plans:
            self._log_set()
        if self._last is not None and not any(r is self._last for r in self._history):
            self._send_record(self._last)
        elif self._last is not None:  # sent with the history, as past: its verdict stated as the present's
            self._log_verdict(self._last.status, self._last.headline)
            self._log_findings(self._last.findings)
        for p, r in self._plan_records.items():
            self._log_verdict(r.status, r.headline, f"plans/{p}")
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
        limit = memory_bytes(self.options.server_memory_limit) or 0
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
            self._log_static(styles=bool(why))
        self._continue_history()

    def _log_static(self, styles: bool = True) -> None:
        """The references that do not depend on the scale, in both polar views: static, a few kB; ``styles``: the
        series' names, colours and widths too (with the scene and the history; every SCENE_REFRESH_S only the
        references, which another client's static data can evict: a lost style costs a colour, not a circle)."""
        self._static_mono = time.monotonic()
        e = 1.7 * R0
        views = [("polar", None), ("live", None), *((f"plans/{p}", axes) for p, axes in self._plans.items())]
        for view, axes in views:
            ax1, ax2 = axes or (self.plan.axes if self.plan else ("X", "Y"))
            self._log(
                f"{view}/reference/nominal",
                rr.LineStrips2D([circle(R0)], colors=[COLOURS["nominal"]], radii=rr.Radius.ui_points(0.75),
                                draw_order=1.0),
                POINT_BYTES * 721,
                static=True,
            )
            self._log(
                f"{view}/reference/axes",
                rr.LineStrips2D([[[-e, 0.0], [e, 0.0]], [[0.0, -e], [0.0, e]]], colors=[COLOURS["axes"]],
                                radii=rr.Radius.ui_points(0.5), draw_order=0.4),
                static=True,
            )
            if not (view == "polar" and self._plans):  # with a library, its tests' own, at their times
                self._log_axis_labels(view, (ax1, ax2))
            # the scale rings sit at fixed display radii (+-1..3 divisions, whatever the division is)
            rings = [circle(ring_radius(k), 361) for k in range(-POLAR_DIVISIONS, POLAR_DIVISIONS + 1) if k]
            self._log(
                f"{view}/reference/scale",
                rr.LineStrips2D(rings, colors=[COLOURS["scale"]], radii=rr.Radius.ui_points(0.5), draw_order=0.5),
                POINT_BYTES * len(rings) * 361,
                static=True,
            )
        if not styles:
            return
        self._log("length", rr.SeriesLines(names="L (mm)", colors=[(150, 150, 150)]), static=True)
        prefixes = [f"plans/{p}/trends" for p in self._plans] or ["trends"]
        for prefix, (path, _field, label, colour) in ((x, t) for x in prefixes for t in TRENDS):
            self._log(f"{prefix}/{path}", rr.SeriesLines(names=label, colors=[colour], widths=1.0), static=True)
            self._log(f"{prefix}/{path}", rr.SeriesPoints(names=label, colors=[colour], marker_sizes=4.0),
                      static=True)
            for name, names, colours, widths in TREND_LINES:
                self._log(f"{prefix}/{path}/{name}", rr.SeriesLines(names=[f"{label} {n}" for n in names],
                                                                    colors=list(colours), widths=list(widths)),
                          static=True)
                if name == "pad":
                    self._log(f"{prefix}/{path}/{name}", rr.SeriesPoints(colors=list(colours), marker_sizes=[0.0]),
                              static=True)

    def _log_axis_labels(self, view: str, axes: tuple[str, str], *, static: bool = True) -> None:
        """The plane's axes at the ends of the view's axis lines: the first to the right, the second up.  Static
        where a view shows one plane; the last test's view of a library takes each test's at the test's time
        (a static label would shadow them: Rerun shows static data over temporal)."""
        e = 1.7 * R0
        self._log(
            f"{view}/reference/axis_labels",
            rr.Points2D([[e, 0.0], [0.0, -e]], labels=[f"+{axes[0]}", f"+{axes[1]}"],  # +y is down in the view
                        colors=[COLOURS["axes"]], radii=rr.Radius.ui_points(2.0), show_labels=True),
            static=static,
        )

    def _log_scale(self, view: str, scale_um: float | None = None) -> None:
        """The scale-dependent references of ``view`` (``polar`` or ``live``): the tolerance band and the
        rings' labels, at the current time (the caller sets the timelines)."""
        tol = self.options.tolerance_um
        s = scale_um or self._scale_um
        k = 0.2 * R0 / s
        self._log(
            f"{view}/reference/band",
            rr.LineStrips2D(
                [circle(R0 + k * tol, 361), circle(max(R0 - k * tol, 0.0), 361)],
                colors=[COLOURS["band"]],
                radii=rr.Radius.ui_points(0.75),
                draw_order=2.0,
            ),
            POINT_BYTES * 2 * 361,
        )
        # Labels on points beside the rings (a strip's own label sits at its centroid, the centre), each ring's at
        # its own angle so that none covers another
        rings = [(R0, 60.0, f"R {self.plan.radius_mm:g} mm" if self.plan else "nominal", COLOURS["nominal"])]
        for j in (POLAR_DIVISIONS, -POLAR_DIVISIONS):
            rings.append((ring_radius(j), 75.0, f"{j * s:+g} µm", COLOURS["scale"]))
        if R0 + k * tol < ring_radius(POLAR_DIVISIONS):
            rings.append((R0 + k * tol, 112.0, f"±{tol:g} µm band", COLOURS["band"]))
        self._log(
            f"{view}/reference/labels",
            rr.Points2D(
                [[r * math.cos(math.radians(a)), -r * math.sin(math.radians(a))] for r, a, _t, _c in rings],
                labels=[t for _r, _a, t, _c in rings],
                colors=[c for _r, _a, _t, c in rings],
                radii=rr.Radius.ui_points(2.0),
                show_labels=True,
                draw_order=3.0,
            ),
            200,
        )

    def _log_verdict(self, status: str, text: str, view: str = "polar") -> None:
        """The last complete test's verdict: a bar in its colour above the plot, and the verdict in words on it
        (a label's text takes its entity's colour: white on the bar)."""
        self._log_bar(f"{view}/verdict", STATUS_RGB.get(status, STATUS_RGB["none"]), text)

    def _log_status(self) -> None:
        """What the test in progress is doing, and since when (UTC): a viewer still replaying the server's buffer
        (Rerun replays it oldest first, a bounded amount per frame) shows an old time here."""
        from .findings import clock_text

        self._log_bar("live/status", (70, 74, 84), f"{self._live_status} · {clock_text(time.time())[:8]}")

    def _log_bar(self, path: str, colour: tuple[int, int, int], text: str) -> None:
        self._log(
            path,
            rr.LineStrips2D([[[-1.5 * R0, BAR_Y], [1.5 * R0, BAR_Y]]], radii=[0.11 * R0], colors=[colour],
                            draw_order=20.0),
            200,
        )
        self._log(
            f"{path}/text",
            rr.Points2D([[0.0, BAR_Y - 0.03 * R0]], radii=rr.Radius.ui_points(0.1), colors=[(255, 255, 255)],
                        labels=[text], show_labels=True, draw_order=21.0),
            200 + len(text),
        )

    # ------------------------------------------------------------------ the last complete test

    def _complete(self, res: Mapping[str, Any], wall: float, index: int | None = None) -> None:
        """Test ``res`` is complete: draw it in the last-complete-test view (its own scale, its verdict) and keep
        it for late viewers; ``index``: its place on the ``test`` timeline (default its ``test_index``)."""
        idx = res.get("test_index") if index is None else index
        curves: dict[str, tuple[FloatArray, FloatArray, str, float, float]] = {}
        for path, c in self._curves.items():
            name = path.split("/", 1)[1]  # ccw/measured ...
            curves[name] = (c.u, c.dr - setup_deviation_um(self._setup_result, c.u), c.colour, c.width, c.order)
        peaks = [float(np.abs(dr).max()) for _u, dr, *_ in curves.values() if dr.size]
        scale = self.options.scale_um or nice_scale_um(max(peaks, default=0.0))
        status, text = headline(res)
        plan = (res.get("plan") or {}).get("name") if self._plans else None
        if not isinstance(plan, str):
            plan = None
        axes = self._plans.get(plan) if plan is not None else None
        if plan is not None:
            text = text.replace(" · test ", f" · {plan} test ", 1)
        record = TestRecord(
            int(idx) if isinstance(idx, int) else self._test_index, wall, scale,
            {n: (polar_points(u, dr, scale).astype(np.float32), col, w, o) for n, (u, dr, col, w, o) in curves.items()},
            self._findings_md, status, text, plan, axes)
        self._last = record
        if self.options.history_tests > 0:
            self._history.append(record)
        if record.plan is not None:
            self._plan_records[record.plan] = record
        if self._sink_live:
            self._send_record(record)
            if record.plan is not None:
                self._send_record(record, f"plans/{record.plan}")

    # ------------------------------------------------------------------ trends

    @staticmethod
    def _trend_values(res: Mapping[str, Any]) -> dict[str, tuple[float, float]]:
        """Per trend entity: (value, standard uncertainty; NaN: none).  The circularity's is the verdict's:
        sqrt(2) x the fit's residual RMS (:func:`ballbar.analysis.monitor.quantity`)."""
        out: dict[str, tuple[float, float]] = {}
        iso = res.get("iso230_4") or {}
        rms = num(res.get("residual_rms_um"))
        for path, field, _label, _c in TRENDS:
            if field.startswith("G_"):
                v, se = num(iso.get(field)), (math.sqrt(2.0) * rms if rms is not None else None)
            else:
                v = param(res, field)
                p = (res.get("parameters") or {}).get(field)
                se = num(p.get("stderr")) if isinstance(p, Mapping) else None
            if v is not None:
                out[path] = (v, math.nan if se is None else se)
        return out

    @staticmethod
    def _trend_row(res: Mapping[str, Any], idx: int, wall: float, before: FloatArray) -> FloatArray | None:
        """One test's trend row (:data:`TREND_WIDTH` columns), None when it has no trend value; ``before``: the
        rows of the tests before it (the last ``TREND_FIT_TESTS`` count for its trend)."""
        from ballbar.analysis.monitor import theil_sen

        values = Scene._trend_values(res)
        if not values:
            return None
        verdict = res.get("verdict") if isinstance(res.get("verdict"), Mapping) else {}
        limits = {str(e.get("name")): e for e in (verdict or {}).get("limits") or [] if isinstance(e, Mapping)}
        nan = (math.nan, math.nan)
        row = [float(idx), wall, *(values.get(p, nan)[0] for p, _f, _l, _c in TRENDS),
               *(values.get(p, nan)[1] for p, _f, _l, _c in TRENDS)]
        for _p, field, _l, _c in TRENDS:
            e = limits.get(field) or {}
            row += [num(e.get("limit")) or math.nan, num(e.get("warning_level")) or math.nan]
        for j in range(N_TRENDS):
            v = row[2 + j]
            ok = np.isfinite(before[:, 2 + j]) if before.shape[0] else np.zeros(0, bool)
            t = np.append(before[ok, 1][-(TREND_FIT_TESTS - 1):], wall) / 86400.0
            y = np.append(before[ok, 2 + j][-(TREND_FIT_TESTS - 1):], v)
            row.append(theil_sen(t, y).at(float(t[-1])) if math.isfinite(v) and t.size >= 3 else math.nan)
        row.append(num((verdict or {}).get("coverage_k")) or 2.0)
        return np.array([row], dtype=float)

    def _lines(self, rows: FloatArray | None = None) -> dict[str, tuple[float, ...]]:
        """The limit and warning lines of the newest trend row, by field, on the side of each trend's data."""
        rows = self._trends.rows() if rows is None else rows
        if not rows.shape[0]:
            return {}
        out: dict[str, tuple[float, ...]] = {}
        for j, (_p, field, _l, _c) in enumerate(TRENDS):
            lim, warn = rows[-1, 2 + 2 * N_TRENDS + 2 * j], rows[-1, 3 + 2 * N_TRENDS + 2 * j]
            vals = rows[:, 2 + j][np.isfinite(rows[:, 2 + j])]
            side = -1.0 if vals.size and float(np.mean(vals)) < 0 else 1.0
            out[field] = tuple(side * x for x in (lim, warn) if np.isfinite(x))
        return out

    def _ranges(self) -> dict[str, tuple[float, float]]:
        """The trend views' y ranges (:func:`trend_ranges`) for the kept rows, their limit lines and bars."""
        if self._plans:  # each plan's views, keyed <plan>/<origin>
            out: dict[str, tuple[float, float]] = {}
            for p, ring in self._plan_trends.items():
                rows = ring.rows()
                if rows.shape[0]:
                    got = trend_ranges(rows, self._lines(rows), float(rows[-1, -1]))
                    out |= {f"{p}/{k}": v for k, v in got.items()}
            return out
        rows = self._trends.rows()
        return trend_ranges(rows, self._lines(), float(rows[-1, -1])) if rows.shape[0] else {}

    def _rescale_trends(self) -> None:
        """A new blueprint when a trend's y range (:func:`trend_ranges`) moved by more than a tenth of itself:
        once per test at most, and rarely once the trends have settled (the server keeps every blueprint)."""
        new = self._ranges()
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
            self._blueprints.send(default_blueprint(new, self._plans or None))

    def _send_trends(self, rows: FloatArray, pad: bool = True, prefix: str = "trends") -> None:
        """Trend rows (:meth:`_trend_row`): each value with its uncertainty band (``k u``), its limit and warning
        level, and the Theil-Sen trend as it stood at each test; ``pad``: the rows start the history (a transparent
        point goes before them, so that no point sits on the plot's edge)."""
        rec = self._rec
        assert rec is not None
        for j, (path, _field, _label, _c) in enumerate(TRENDS):
            vals, ses = rows[:, 2 + j], rows[:, 2 + N_TRENDS + j]
            m = np.isfinite(vals)
            if not m.any():
                continue
            k = rows[:, -1]
            idx = [rr.TimeColumn("test", sequence=rows[m, 0].astype(np.int64)),
                   rr.TimeColumn("time", timestamp=rows[m, 1])]
            series: list[tuple[str, FloatArray]] = [("", vals[m])]
            trend = rows[:, 2 + 4 * N_TRENDS + j]
            series.append(("/band", np.column_stack([(vals + k * ses)[m], (vals - k * ses)[m], trend[m]])))
            lim, warn = rows[:, 2 + 2 * N_TRENDS + 2 * j], rows[:, 3 + 2 * N_TRENDS + 2 * j]
            side = np.where(vals < 0, -1.0, 1.0)
            if np.isfinite(lim[m]).all() and np.isfinite(warn[m]).all():
                series.append(("/limits", np.column_stack([(side * lim)[m], (side * warn)[m]])))
            if pad:
                t0, t1 = rows[m, 1][0], rows[m, 1][-1]
                rec.send_columns(
                    f"{prefix}/{path}/pad",
                    indexes=[rr.TimeColumn("test", sequence=[int(rows[m, 0][0]) - 1]),
                             rr.TimeColumn("time", timestamp=[t0 - max(0.05 * (t1 - t0), 60.0)])],
                    columns=rr.Scalars.columns(scalars=[float(np.mean(vals[m]))]),
                )
                self._sent_bytes += MSG_BYTES + ROW_BYTES
            for suffix, ys in series:
                ok = np.isfinite(ys) if ys.ndim == 1 else np.isfinite(ys).any(axis=1)
                if not ok.any():
                    continue
                rec.send_columns(
                    f"{prefix}/{path}{suffix}",
                    indexes=[rr.TimeColumn("test", sequence=rows[m, 0][ok].astype(np.int64)),
                             rr.TimeColumn("time", timestamp=rows[m, 1][ok])] if not ok.all() else idx,
                    columns=rr.Scalars.columns(scalars=ys[ok]),
                )
                self._sent_bytes += MSG_BYTES + ROW_BYTES * ys[ok].size

    # ------------------------------------------------------------------ polar plot
    #
    # Curves are kept in micrometres (angle, raw dR = L - R, or the model's dR) and turned into
    # display points when logged: a new scale, a new set-up estimate or a viewer that connects
    # later all re-emit them consistently, even after the samples behind them were let go.
    # A live curve is sent in pieces (see Curve): each update sends its growing tip and the
    # pieces completed since the last one, never the whole curve again.

    def _redraw_live(self) -> None:
        t, _L = self._analysis_time()
        if not t.size:
            return
        paths = []
        for d, timing in self._live.items():
            if d not in self._final and t[-1] > timing.start_s and self._update_measured(d, timing, live=True):
                paths.append(f"live/{DIRECTIONS[d]}/measured")
        if paths and not self._fit_scale(grow_only=True):
            self._emit(paths, full=False)

    def _redraw_all(self, wall: float | None = None, emit: bool = True) -> None:
        """Recompute every curve of the current test that the kept samples allow, rescale, emit (``emit``)."""
        for d in DIRECTIONS:
            res = self._final.get(d)
            timing = result_timing(res, d) if res is not None else self._live.get(d)
            if timing is not None:
                self._update_measured(d, timing, live=res is None)
            if res is not None:
                self._update_model(d, res)
        if emit:
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
        path = f"live/{name}/measured"
        old = self._curves.get(path)
        new = Curve(u, dr, name, 2.0, 10.0, live=live, key=key if live else None)
        if old is not None:
            new.pieces = old.pieces
            # the pieces sent so far stay valid only for the same live curve, grown
            new.stale = old.stale or (old.pieces > 0 and (not live or old.key != key))
        self._curves[path] = new
        return True

    def _update_model(self, d: int, res: Mapping[str, Any]) -> None:
        plan = plan_of_result(res["plan"])
        u_ds = math.radians(data_start_deg(plan, d))
        u = u_ds + d * np.linspace(0.0, math.radians(plan.data_arc_deg), self.options.polar_points)
        dr = model_deviation_um(res, d, u)
        if dr is None:
            return
        name = DIRECTIONS[d]
        self._curves[f"live/{name}/model"] = Curve(u, dr, f"{name}_model", 0.75, 11.0)

    def _fit_scale(self, grow_only: bool, wall: float | None = None) -> bool:
        """The automatic scale for the measured curves; True when it changed (everything re-emitted)."""
        if self.options.scale_um is not None:
            return False
        peaks = [  # measured and model alike: the outermost ring holds every point
            float(np.abs(c.dr - setup_deviation_um(self._setup_result, c.u)).max())
            for c in self._curves.values() if c.u.size
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
            self._log_scale("live")
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

    def _emit_live(self, path: str, c: Curve, full: bool) -> None:
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

    def _display(self, c: Curve, a: int = 0, b: int | None = None) -> FloatArray:
        u, dr = c.u[a:b], c.dr[a:b]
        return polar_points(u, dr - setup_deviation_um(self._setup_result, u), self._scale_um)

    def _set_times(self, wall: float | None = None) -> None:
        rec = self._rec
        assert rec is not None
        rec.set_time("time", timestamp=wall if wall is not None else time.time())
        rec.set_time("test", sequence=self._test_index)
