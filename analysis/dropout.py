"""A drop-out inside a test: samples lost on a clock that ran on, judged and stated.

A link that drops (a radio link's drop-out) loses a stretch of samples; the
samples after it fall on the same clock grid.  From the times alone that gap
looks like a clock jump (:mod:`.timeaxis`), but a test can tell the two apart
where it matters: a jump lengthens the feed-in to feed-out span by the gap,
so the feed measured from the span falls short of the programmed one by just
that much, while a loss leaves the span alone.  A gap of at most
``MAX_DROPOUT_S`` that only the times show (no device reset or jump was told)
is therefore taken as samples lost, and so is one the source counted as
lost (a device's counter, a logger's gap: :class:`~.timeaxis.Lost`); the test
is analysed with what is there, unless the gap takes what the result cannot do without:

- the feed-in or the feed-out step: every angle hangs on their centroids;
- an axis reversal of a data arc (within ``REVERSAL_MARGIN_DEG`` of it): the
  backlash, lateral play and reversal spikes are read there;
- more than ``MAX_ARC_FRACTION`` of a data arc;
- a span that the gap, taken as a clock jump, explains better than a loss:
  the measured feed is then wrong by the gap (``FEED_TOLERANCE``).

A drop-out the test keeps is stated on its result (``dropouts``): where, how
long, and for each pattern the factor by which its standard error is larger
than with the lost samples present (:func:`costs`: the information the gap's
rows would have added to the design, at the result's own timing; no misfit
evaluation of the fit's).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np

from .detect import StepEvent
from .patterns import Geometry, Pattern, design
from .plan import TestPlan
from .program import data_start_deg, feed_from_span, schedule
from .timeaxis import Break, Lost

if TYPE_CHECKING:
    from ballbar.protocol.messages.results import Dropout, DropoutCost

MAX_DROPOUT_S = 2.0  # a longer gap stays a break: the test is rejected
REVERSAL_MARGIN_DEG = 5.0  # a gap this close to an axis reversal takes it (the spikes decay within a few deg)
MAX_ARC_FRACTION = 0.25  # a gap may take at most this much of a data arc
FEED_TOLERANCE = 0.002  # the measured feed may miss the expected by this much before the gap explains it


def is_dropout(brk: Break) -> bool:
    """Whether a break may be a drop-out: one the times show, of at most ``MAX_DROPOUT_S``, that nobody told of
    or was told as samples lost (:class:`~.timeaxis.Lost`: a device reset or a clock jump never is)."""
    return (not brk.reason or isinstance(brk.reason, Lost)) and brk.visible and brk.missing_s <= MAX_DROPOUT_S


def in_step(brk: Break, step: StepEvent) -> bool:
    """Whether the gap lies within a feed-in or feed-out step (from its last sample before to its first after)."""
    return brk.t_after > step.t_begin_s and brk.t_before < step.t_end_s


@dataclass(frozen=True)
class Judged:
    """A drop-out's verdict: ``rejection`` (why the test cannot do without it, or None) and what is stated."""

    rejection: str | None
    stated: Dropout


def judge(
    plan: TestPlan, fi: StepEvent, fo: StepEvent, brk: Break, expected_feed_mm_s: float, overhead_s: float = 0.0,
    accel_s: float | None = None,
) -> Judged:
    """Where the drop-out ``brk`` falls in the test from ``fi`` to ``fo``, and whether the test can do without it.

    ``expected_feed_mm_s``: the feed the test should run at (programmed, times the feed ratio tests learnt)."""
    period = brk.period_s if math.isfinite(brk.period_s) and brk.period_s > 0 else math.nan
    stated: Dropout = {
        "t_s": brk.t_before, "duration_s": brk.missing_s,
        "samples_missing": round(brk.missing_s / period) if math.isfinite(period) else 0,
        "direction": None, "from_deg": None, "to_deg": None, "arc_fraction": 0.0,
    }
    if in_step(brk, fi):
        return Judged("it takes the feed-in step, whose centroid times every angle", stated)
    if in_step(brk, fo):
        return Judged("it takes the feed-out step, whose centroid gives the feed", stated)
    span = fo.t_s - fi.t_s
    V = feed_from_span(plan, span, overhead_s, accel_s)
    if not (math.isfinite(V) and V > 0):
        return Judged("the feed-in to feed-out span gives no feed", stated)
    V_jump = feed_from_span(plan, span - brk.missing_s, overhead_s, accel_s)
    miss, miss_jump = abs(V / expected_feed_mm_s - 1.0), abs(V_jump / expected_feed_mm_s - 1.0)
    if miss > FEED_TOLERANCE and math.isfinite(V_jump) and miss_jump < 0.5 * miss:
        return Judged(
            f"the feed-in to feed-out span is longer than the feed gives by about the gap (measured feed "
            f"{60 * V:.1f} mm/min, {60 * V_jump:.1f} without the gap, {60 * expected_feed_mm_s:.1f} expected): the "
            "clock jumped, no samples were lost", stated)
    sched = schedule(plan, V, overhead_s, accel_s)
    rb, ra = brk.t_before - fi.t_s, brk.t_after - fi.t_s
    for d in plan.direction_list:
        ds, de = sched.data_start_s[d], sched.data_end_s[d]
        if ra <= ds or rb >= de:
            continue
        a0, a1 = (float(x) for x in sched.angle_deg(plan, d, np.array([max(rb, ds), min(ra, de)])))
        name = cast(Literal["ccw", "cw"], "ccw" if d > 0 else "cw")
        frac = abs(a1 - a0) / plan.data_arc_deg
        stated.update({"direction": name, "from_deg": a0, "to_deg": a1, "arc_fraction": frac})
        lo, hi = min(a0, a1) - REVERSAL_MARGIN_DEG, max(a0, a1) + REVERSAL_MARGIN_DEG
        first, last = data_start_deg(plan, d), data_start_deg(plan, d) + d * plan.data_arc_deg
        arc_lo, arc_hi = min(first, last), max(first, last)
        for k in range(math.ceil(lo / 90.0), math.floor(hi / 90.0) + 1):
            q = 90.0 * k
            if arc_lo <= q <= arc_hi:
                axis = "first" if k % 2 == 0 else "second"
                return Judged(f"it takes the {axis} axis' reversal at {q % 360:.0f} deg of the {name} data arc "
                              f"({a0:.1f} to {a1:.1f} deg lost)", stated)
        if frac > MAX_ARC_FRACTION:
            return Judged(f"it takes {100 * frac:.0f} % of the {name} data arc ({a0:.1f} to {a1:.1f} deg), more than "
                          f"{100 * MAX_ARC_FRACTION:.0f} %", stated)
        break
    return Judged(None, stated)


def costs(
    plan: TestPlan, patterns: Sequence[Pattern], timing: Mapping[str, Any], gaps: Sequence[Dropout],
    sample_hz: float,
) -> list[list[DropoutCost]]:
    """Per drop-out, each pattern's standard error with the gap over what it would be with its samples there.

    The design of the data arcs at the result's timing (``timing``: the result's, its measured feed and spike
    width), one row a sample period, against the same without the rows in the gap: the factor is
    ``sqrt(diag(inv(I_gap)) / diag(inv(I_full)))`` of their information matrices, the largest of a pattern's
    columns.  Patterns the arcs do not determine either way are left out."""
    feed = timing.get("measured_feed_mm_min")
    if not isinstance(feed, int | float) or not feed > 0 or not sample_hz > 0:
        return [[] for _ in gaps]
    V = float(feed) / 60.0
    overhead = timing.get("overhead_s")
    sched = schedule(plan, V, float(overhead) if isinstance(overhead, int | float) else 0.0)
    w = math.radians(float(timing.get("spike_width_deg") or 0.5))
    step = V / plan.radius_mm / sample_hz  # rad a sample
    rows_u, rows_d, rows_t = [], [], []
    for d in plan.direction_list:
        u0 = math.radians(data_start_deg(plan, d))
        k = np.arange(max(int(math.radians(plan.data_arc_deg) / step), 2))
        rows_u.append(u0 + d * step * k)
        rows_d.append(np.full(k.size, float(d)))
        rows_t.append((sched.data_start_s[d] + k / sample_hz) / 60.0)  # minutes from the feed-in (the drift's)
    u, dd, t_min = np.concatenate(rows_u), np.concatenate(rows_d), np.concatenate(rows_t)
    X = design(patterns, Geometry(u, dd, t_min, V, plan.radius_mm), w)
    cols = [p for p in patterns for _ in range(p.q)]
    live = np.linalg.norm(X, axis=0) > 0
    X, cols = X[:, live], [c for c, keep in zip(cols, live, strict=True) if keep]
    full = X.T @ X
    try:
        inv_full = np.diag(np.linalg.inv(full))
    except np.linalg.LinAlgError:
        return [[] for _ in gaps]
    out: list[list[DropoutCost]] = []
    for g in gaps:
        if g["direction"] is None or g["from_deg"] is None or g["to_deg"] is None:
            out.append([])
            continue
        sense = 1.0 if g["direction"] == "ccw" else -1.0
        lo, hi = sorted((math.radians(g["from_deg"]), math.radians(g["to_deg"])))
        gone = (dd == sense) & (u > lo) & (u < hi)
        Xg = X[gone]
        try:
            inv_gap = np.diag(np.linalg.inv(full - Xg.T @ Xg))
        except np.linalg.LinAlgError:
            out.append([])
            continue
        ratio = np.sqrt(np.maximum(inv_gap / inv_full, 1.0))
        best: dict[str, float] = {}
        for c, r in zip(cols, ratio.tolist(), strict=True):
            best[c.name] = max(best.get(c.name, 1.0), r)
        out.append([{"pattern": k, "stderr_factor": v} for k, v in best.items()])
    return out


__all__ = ["FEED_TOLERANCE", "MAX_ARC_FRACTION", "MAX_DROPOUT_S", "REVERSAL_MARGIN_DEG", "Judged", "costs",
           "in_step", "is_dropout", "judge"]
