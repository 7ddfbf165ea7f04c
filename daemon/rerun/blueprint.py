"""The live view's layout (Rerun blueprints) and the trends it draws.

Layout, for windows from 1280x800 up: on the left the last complete test's polar plot with its verdict
bar, the test in progress beside it, and under them the events and the bar length (tabs); on the right the
findings (the verdict in words first) and the trends.  Each layout goes on one blueprint stream for the
viewer's whole life (:class:`Blueprints`).

Trends: one point per test with its uncertainty (``k u``, the verdict's coverage factor), the limit and
the warning level as lines where limits are set, and the Theil-Sen trend line through the kept history;
on the ``time`` timeline (wall clock) and the ``test`` timeline (the test number), whichever the time
panel shows: Rerun 0.41's time-series views plot against the time panel's timeline, and draw nothing
beyond the newest data on it, so the forecast's date is stated in the findings rather than drawn ahead.
"""

from __future__ import annotations

import uuid
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ballbar.analysis.report import trend_range

from .geometry import R0

if TYPE_CHECKING:
    import rerun as rr
    import rerun.blueprint as rrb
else:  # imported at first use: the configuration check and READY=1 do not wait for it (half a second)
    from ..lazy import LazyModule

    rr, rrb = LazyModule("rerun"), LazyModule("rerun.blueprint")

FloatArray = NDArray[np.float64]

# (entity under trends/, result field or ISO key, series name, colour)
TRENDS: tuple[tuple[str, str, str, tuple[int, int, int]], ...] = (
    ("backlash_um/x", "backlash_x_um", "X", (40, 120, 255)),
    ("backlash_um/y", "backlash_y_um", "Y", (245, 150, 40)),
    ("circularity_um/G_b", "G_b_um", "G(b)", (40, 120, 255)),
    ("servo_mismatch_ms", "servo_mismatch_ms", "servo mismatch", (40, 120, 255)),
    ("squareness_urad", "squareness_urad", "squareness", (40, 120, 255)),
    ("scale_mismatch_ppm", "scale_mismatch_ppm", "scale mismatch", (40, 120, 255)),
)
# (origin under trends/, title): the titles name the quantity in words and fit half the trends panel at 1280 px
TREND_VIEWS: tuple[tuple[str, str], ...] = (
    ("circularity_um", "Circularity G(b) µm"),
    ("backlash_um", "Backlash X, Y µm"),
    ("servo_mismatch_ms", "Servo mismatch ms"),
    ("squareness_urad", "Squareness µrad"),
    ("scale_mismatch_ppm", "Scale mismatch ppm"),
)
# the lines drawn with each trend (children of its entity; two series in one entity where they come together,
# one message a test for both): name, the series' names, colours and widths (ui points)
TREND_LINES: tuple[tuple[str, tuple[str, ...], tuple[tuple[int, ...], ...], tuple[float, ...]], ...] = (
    ("limits", ("limit", "warning level"), ((215, 50, 40), (215, 140, 30)), (2.0, 1.0)),
    ("band", ("+k u", "-k u", "trend"), ((120, 125, 135), (120, 125, 135), (150, 190, 255)), (0.75, 0.75, 1.0)),
    ("pad", ("",), ((0, 0, 0, 0),), (0.0,)),  # transparent: a point before the first test, so none is on the edge
)


def trend_ranges(rows: FloatArray, lines: Mapping[str, tuple[float, ...]] | None = None,
                 k: float = 2.0) -> dict[str, tuple[float, float]]:
    """The y range of each trend view (:data:`TREND_VIEWS`) from trend rows (test, wall time, the values of
    :data:`TRENDS`, then their standard uncertainties; NaN: none): every point with its ``k u`` bar and the
    ``lines`` of its field (limit, warning level), and at least ``TREND_STDERR_SPAN`` standard uncertainties
    either side of the mean (:func:`~ballbar.analysis.report.trend_range`), so that a change within them looks
    flat."""
    out: dict[str, tuple[float, float]] = {}
    n = len(TRENDS)
    lines = lines or {}
    for origin, _title in TREND_VIEWS:
        vals: list[float | None] = []
        errs: list[float | None] = []
        marks: list[float] = []
        for j, (path, field, _l, _c) in enumerate(TRENDS):
            if path == origin or path.startswith(origin + "/"):
                vals += [float(v) if np.isfinite(v) else None for v in rows[:, 2 + j]]
                errs += [float(e) if np.isfinite(e) else None for e in rows[:, 2 + n + j]]
                marks += list(lines.get(field, ()))
        rng = trend_range(vals, errs, k, marks)
        if rng is not None and rng[1] > rng[0]:
            out[origin] = rng
    return out


def _events_view() -> rrb.TextLogView:
    from rerun.blueprint import archetypes as bpa
    from rerun.blueprint import components as bpc

    columns = bpa.TextLogColumns(
        timeline_columns=[bpc.TimelineColumn("time", visible=False), bpc.TimelineColumn("test", visible=False)],
        text_log_columns=[bpc.TextLogColumn("EntityPath", visible=False), bpc.TextLogColumn("LogLevel"),
                          bpc.TextLogColumn("Body")],
    )
    return rrb.TextLogView(name="Events", origin="events", columns=columns)


def _trend_grid(ranges: Mapping[str, tuple[float, float]], prefix: str = "trends", name: str = "Trends across tests",
                axes: tuple[str, str] = ("X", "Y")) -> rrb.Grid:
    """The trend views of the entities under ``prefix``; ``ranges`` by origin (``prefix``-relative)."""
    everything = [rrb.VisibleTimeRange(tl, start=rrb.TimeRangeBoundary.infinite(),
                                       end=rrb.TimeRangeBoundary.infinite()) for tl in ("time", "test")]
    # each view's own x range: linked to the time panel (the default), a plot showed the last 30 s of a day's tests
    whole = rrb.TimeAxis(link="Independent", view_range=rrb.TimeRange(
        start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()))
    return rrb.Grid(
        *(
            rrb.TimeSeriesView(
                name=title.replace("X, Y", ", ".join(axes)), origin=f"{prefix}/{origin}", time_ranges=everything,
                axis_x=whole,
                axis_y=rrb.ScalarAxis(range=ranges[origin], zoom_lock=False) if origin in ranges else None,
                plot_legend=rrb.PlotLegend(visible=False),
            )
            for origin, title in TREND_VIEWS
        ),
        grid_columns=2,
        name=name,
    )


def _polar_view(name: str, origin: str) -> rrb.Spatial2DView:
    bound = 1.85 * R0
    return rrb.Spatial2DView(name=name, origin=origin,
                             visual_bounds=rrb.VisualBounds2D(x_range=[-bound, bound], y_range=[-2.05 * R0, bound]))


def default_blueprint(ranges: Mapping[str, tuple[float, float]] | None = None,
                      plans: Mapping[str, tuple[str, str]] | None = None) -> rrb.Blueprint:
    """The layout (see the module docstring).  ``ranges``: the y range of trend views by origin
    (:func:`trend_ranges`; with ``plans``, ``<plan>/<origin>``); the others autoscale.  ``plans``: a library of
    several plans (name: its plane's axes): :func:`plans_blueprint`."""
    if plans:
        return plans_blueprint(plans, ranges or {})
    ranges = ranges or {}
    trends = _trend_grid(ranges)
    polar = _polar_view("Last complete test: CCW blue, CW orange, model pale", "polar")
    live = _polar_view("Test in progress", "live")
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Horizontal(polar, live, column_shares=[3, 2]),
                rrb.Tabs(_events_view(), _length_view(), active_tab=0),
                row_shares=[3, 1],
            ),
            rrb.Vertical(
                rrb.TextDocumentView(name="Verdict and findings", origin="findings"),
                trends,
                row_shares=[6, 5],
            ),
            column_shares=[3, 2],
        ),
        *_panels(),
    )


def plans_blueprint(plans: Mapping[str, tuple[str, str]], ranges: Mapping[str, tuple[float, float]]
                    ) -> rrb.Blueprint:
    """The layout for a library of plans and their sets: on top of the left column the machine's verdict (the
    sets', a bar in its colour, ``set``); under it the last complete test and, a tab each, every plan's latest
    test (``plans/<name>``), beside the test in progress; on the right the findings (the set's verdict in words
    first) and, a tab per plan, each plan's trends (``plans/<name>/trends``) with its limits and forecast."""
    tabs = rrb.Tabs(
        _polar_view("Last test: CCW blue, CW orange", "polar"),
        *(_polar_view(f"{p} ({''.join(axes)})", f"plans/{p}") for p, axes in plans.items()),
        active_tab=0,
    )
    trends = rrb.Tabs(
        *(_trend_grid({k.split("/", 1)[1]: v for k, v in ranges.items() if k.split("/", 1)[0] == p},
                      f"plans/{p}/trends", f"Trends of plan {p}", axes)
          for p, axes in plans.items()),
        active_tab=0,
    )
    machine = rrb.Spatial2DView(
        name="Machine: the set's verdict", origin="set",
        visual_bounds=rrb.VisualBounds2D(x_range=[-1.62 * R0, 1.62 * R0], y_range=[-2.08 * R0, -1.72 * R0]))
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                machine,
                rrb.Horizontal(tabs, _polar_view("Test in progress", "live"), column_shares=[3, 2]),
                rrb.Tabs(_events_view(), _length_view(), active_tab=0),
                row_shares=[1, 5, 2],
            ),
            rrb.Vertical(
                rrb.TextDocumentView(name="Verdict and findings", origin="findings"),
                trends,
                row_shares=[6, 5],
            ),
            column_shares=[3, 2],
        ),
        *_panels(),
    )


def _length_view() -> rrb.TimeSeriesView:
    recent = rrb.TimeAxis(link="Independent", view_range=rrb.TimeRange(
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-300.0), end=rrb.TimeRangeBoundary.cursor_relative()))
    return rrb.TimeSeriesView(
        name="Bar length L (mm)",
        origin="length",
        time_ranges=rrb.VisibleTimeRange(
            "time",
            start=rrb.TimeRangeBoundary.cursor_relative(seconds=-300.0),
            end=rrb.TimeRangeBoundary.cursor_relative(),
        ),
        axis_x=recent,
        plot_legend=rrb.PlotLegend(visible=False),
    )


def _panels() -> tuple[rrb.TimePanel, rrb.BlueprintPanel, rrb.SelectionPanel]:
    return (rrb.TimePanel(timeline="time", play_state="following", state="collapsed"),  # live: the newest test
            rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


LAYOUT_NAMESPACE = uuid.UUID("5f0c3a7e-6b1d-4c2a-9e57-b0a11ba40001")  # the layout's view and container ids


class Blueprints:
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
        paths = stable_ids(bp.root_container, "root")
        self._stream.set_time("blueprint", sequence=self._step)
        self._step += 1
        bp._log_to_stream(self._stream)
        for path in sorted(self._paths - paths):
            self._stream.log(path, rr.Clear(recursive=True))
        self._paths = paths
        send_blueprint(self._storage.storage, True, True, recording=self._rec.to_native())


def stable_ids(item: rrb.Container | rrb.View, place: str) -> set[str]:
    """Give a container and everything in it ids from their places in the layout and their kinds; return their
    blueprint paths.

    A viewer keeps each view's state (a 2D view's, a time series') by the view's id for as long as it runs,
    across recordings: an id that named a time-series view in one layout and names a 2D view in another (the
    single plan's layout, then a library's, in one viewer) fails every frame ("Failed to downcast view's to
    the re_view_spatial::ui::SpatialViewState") and leaves that view empty.  So the id says what it is as well
    as where: a view's class or a container's kind, the parent's included through its place."""
    kind = item.__class__.__name__ if isinstance(item, rrb.Container) else str(item.class_identifier)
    item.id = uuid.uuid5(LAYOUT_NAMESPACE, f"{place}:{kind}")
    out = {item.blueprint_path()}
    if isinstance(item, rrb.Container):
        for i, sub in enumerate(item.contents):
            out |= stable_ids(sub, f"{place}:{kind}/{i}")
    return out

__all__ = ["TRENDS", "TREND_LINES", "TREND_VIEWS", "Blueprints", "default_blueprint", "plans_blueprint",
           "trend_ranges"]
