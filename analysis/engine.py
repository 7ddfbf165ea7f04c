"""From samples to results: one code path for the live daemon and offline files.

:class:`TestAnalyzer` is fed ``(t, length)`` chunks of any size.  It finds each
test (:mod:`.detect`), fits each circle as soon as its data arc has passed, and
fits the whole test (both directions jointly) after the feed-out.

Timing.  The angle of a sample comes from the feed-in's centroid and the
program's timing (:mod:`.program`), at a path feed ``V`` and a per-move
overhead ``c`` (the acceleration's delay).  A circle finishes before the
feed-out, so its *provisional* fit uses the programmed feed times the feed
ratio and overhead learnt on the previous test (``TimingHints``).  After the
feed-out the test's fit measures the feed from the centroid span, estimates the
overhead ``c`` (the arc start's lag) and the reversal spikes' width ``w`` by
maximising the profile likelihood of the full model (with a weak prior on ``c``
so that it stays near zero where the data cannot tell), and refits both circles
at those values: one pass over that test's own samples, none over older ones.

Breaks.  Every angle hangs on the time axis, so :class:`TestAnalyzer` watches
it (:mod:`.timeaxis`): a step backwards beyond jitter is a :class:`DataError`;
a gap longer than a few sample periods, and any break the caller tells it of
(:meth:`TestAnalyzer.mark_break`: a device reset, lost samples), rejects the
test it falls in (``test_rejected``, with the break's time and size), from the
feed-in step's first sample to the feed-out step's last.  Two kinds of gap are
no break: a stalled host's, whose bunched samples :mod:`.retime` puts back on
their grid before the time axis sees them (held back only while the samples
after a long step come in), and a drop-out (samples lost on a clock that ran
on, :mod:`.dropout`), judged at the feed-out: the test is rejected where it
takes what the result needs, else analysed and the drop-out stated on its
result (``dropouts``).  Only a test that passed, with a plausible feed, teaches
the next one its timing hints.

In the background.  Given an ``executor`` (the daemon's child process), the
test's fit runs there while the next test's samples come in: :meth:`TestAnalyzer.collect`
returns its result once done.  The analyzer waits for it before the next
feed-in (and at :meth:`~TestAnalyzer.finish` and :meth:`~TestAnalyzer.abort`),
so the hints it teaches reach the next test exactly as inline: the results
are the same either way.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np

from .circle import CircleFit, make_timing
from .detect import StepEvent, TestDetector
from .dropout import costs, in_step, is_dropout, judge
from .errors import DataError, DetectionError
from .fit import FitResult, solve
from .fitstate import DEFAULT_SPIKE_WIDTH_DEG, feed_accel
from .patterns import Pattern, select
from .plan import AnalysisOptions, MachineAxes, MachineConfig, TestPlan
from .plans import (
    PlanLibrary,
    RecentSamples,
    Recognition,
    SignatureReading,
    at_feed_in,
    at_feed_out,
    by_controller,
    controller_checked,
    read_signature,
)
from .result import result_body
from .retime import Retimer
from .testfit import analyze_test
from .timeaxis import Break, TimeAxis

if TYPE_CHECKING:
    from ballbar.protocol.messages import AnalysisOutput, CircleBody, TestBody, results
    from ballbar.protocol.messages.events import FeedInBody, FeedOutBody, TestRejectedBody
    from ballbar.protocol.messages.results import Dropout, MachineAxis

log = logging.getLogger(__name__)

FOLD_SAMPLES = 256  # a live circle folds new samples in blocks of at least this many (or as it completes)
# A measured feed this far from the programmed one is not the machine's habit (controls hold the feed to well
# under 1 % at 100 % override): something else went wrong, and the next test must not assume it.
HINT_MAX_FEED_DEVIATION = 0.1
RECENT_PIECE_S = 5.0  # a library of several takes a long chunk in pieces of this many seconds (the signature's)


@dataclass
class TimingHints:
    """What the previous test taught: used for the provisional circle fits."""

    feed_ratio: float = 1.0
    overhead_s: float = 0.0
    spike_width_deg: float = DEFAULT_SPIKE_WIDTH_DEG

    @classmethod
    def learnt(cls, timing: Mapping[str, Any], before: TimingHints | None = None) -> TimingHints | None:
        """The hints a test result's ``timing`` teaches, or None where they are implausible.

        Implausible: a feed ratio more than ``HINT_MAX_FEED_DEVIATION`` from 1, or
        a value that is not a finite number.  ``before`` supplies the spike width
        where the test had none.
        """
        try:
            ratio = float(timing["feed_ratio"])
            overhead = float(timing["overhead_s"])
        except (KeyError, TypeError, ValueError):
            return None
        width = timing.get("spike_width_deg")
        if not (math.isfinite(ratio) and math.isfinite(overhead) and abs(ratio - 1.0) <= HINT_MAX_FEED_DEVIATION):
            return None
        if not (isinstance(width, int | float) and math.isfinite(width) and width > 0):
            width = (before or cls()).spike_width_deg
        return cls(ratio, overhead, float(width))


def _kappa(rho: float) -> float:
    """The AR(1) variance inflation ``(1 + rho) / (1 - rho)`` of a residual's lag-1 correlation, 1..400."""
    return min(max((1 + rho) / (1 - rho), 1.0), 400.0) if rho < 1 else 400.0


def _lag1(residuals: Sequence[np.ndarray]) -> float:
    num = sum(float(np.dot(r[1:], r[:-1])) for r in residuals if r.size > 1)
    den = sum(float(np.dot(r, r)) for r in residuals)
    return num / den if den > 0 else 0.0


class TestAnalyzer:
    """Streaming test detection and fitting; see the module docstring.

    :meth:`feed` returns result dictionaries as they complete: ``kind`` is
    ``"circle"`` (one direction, provisional timing) or ``"test"``; and event
    dictionaries (``kind = "event"``: ``feed_in``, ``feed_out``,
    ``test_rejected``, ``test_incomplete``).  A test is rejected as soon as a
    break in its time axis is seen (live: at once, not at its feed-out; a
    drop-out at its feed-out); its feed-out is still reported, and no result
    follows.

    ``executor``: where each test's fit runs (see the module docstring;
    ``None``: inline, its result returned with the feed-out); ``on_submit``
    is handed each background job's future (to be told when it is done).
    ``circles``: False for the tests' results alone (no provisional circles:
    an offline analysis that reads only the test's result).  ``only``: fit
    only the test of that number (from 1, the feed-ins in order); the
    others' feed-outs come with a ``test_skipped`` event instead of a fit.
    A test's fit does not depend on the tests before it (only the
    provisional circles take the hints they teach), so its result is the
    one the whole analysis gives; ``only`` needs ``circles=False``.

    ``library``: the plans the tests may run (:mod:`.plans`); by default
    ``plan`` alone, named ``default``.  Of a library of several, each test's
    plan is recognised (:func:`~.plans.at_feed_in`: a chosen plan or the
    program's signature; :func:`~.plans.at_feed_out`: the timing), its steps
    timed with that plan and its samples read at its radius
    (:meth:`~.plans.PlanLibrary.offset_mm`); a test that matches no plan or
    several gives a ``test_unrecognised`` event instead of a result.  The
    provisional circles run only where the plan is known at the feed-in.
    :meth:`choose` names the next test's plan.  Every result says its plan:
    ``plan.name``, ``plan.axes`` and ``recognition``.

    ``machine``: the machine's axes (:class:`~.plan.MachineAxes`), each test's
    plan taking its plane's two; or one plane's (:class:`~.plan.MachineConfig`),
    which every plan then takes as its first and second axis (a recording made
    before the machine's axes were named).  :attr:`machine` is the current
    plan's.
    """

    __test__ = False

    def __init__(
        self,
        plan: TestPlan,
        machine: MachineConfig | MachineAxes | None = None,
        options: AnalysisOptions | None = None,
        hints: TimingHints | None = None,
        curves: bool = False,
        executor: cf.Executor | None = None,
        on_submit: Callable[[cf.Future[dict[str, Any]]], None] | None = None,
        circles: bool = True,
        only: int | None = None,
        library: PlanLibrary | None = None,
        plan_hints: dict[str, TimingHints] | None = None,
    ) -> None:
        if only is not None and circles:
            raise ValueError("only: a test's provisional circles take the hints the tests before it teach; "
                             "pass circles=False")
        self.plan = plan
        self.circles = circles
        self.only = only
        self.executor = executor
        self.on_submit = on_submit
        self._pending: tuple[int, StepEvent, cf.Future[dict[str, Any]], Recognition | None] | None = None
        self.curves = curves
        self.machine_axes = machine if isinstance(machine, MachineAxes) else None
        self.machine = machine if isinstance(machine, MachineConfig) else MachineConfig()
        self.options = options or AnalysisOptions()
        self.hints = hints or TimingHints()
        self.library = library if library is not None else PlanLibrary.single(plan)
        self.multi = len(self.library) > 1
        self.plan_name = self.library.first.name
        if self.multi:
            plan = self.plan = self.library.detection_plan()
        elif library is not None:
            self.plan = self.library.first.plan
        if self.machine_axes is not None:
            self.machine = self.machine_axes.for_plane(self.plan.plane)
        self.plan_hints: dict[str, TimingHints] = dict(plan_hints or {})
        self._recent = RecentSamples() if self.multi else None
        self._pre: tuple[np.ndarray, np.ndarray] = (np.empty(0), np.empty(0))
        self._chosen: str | None = None
        self._chosen_always = False
        self._reading: SignatureReading | None = None
        self._early: Recognition | None = None
        self._controller: tuple[str | None, str | None] | None = None  # (program, its plan) now; None: no controller
        self._ctl_use: results.ControllerUse | None = None  # what the controller said of the test in progress
        self._offset = 0.0
        self.detector = TestDetector(self.plan)
        self.axis = TimeAxis()
        self.retimer = Retimer()
        self._queue: list[tuple[np.ndarray, np.ndarray] | str] = []  # settled samples and breaks, for the next feed
        self.patterns = select(
            self.options.patterns, plan.direction_list, self.machine.pitch_x_mm, self.machine.pitch_y_mm
        )
        self.test_index = 0
        self._fi: StepEvent | None = None
        self._rejected = False  # the test in progress has been rejected
        self._circles: list[CircleFit] = []
        self._emitted: set[int] = set()
        self._added = 0
        self._breaks: list[Break] = []
        self._dropouts: dict[int, list[Dropout]] = {}  # per test, the drop-outs its result states
        self.last_t = float("nan")

    def feed(self, t: np.ndarray, L: np.ndarray, borrow: bool = False) -> list[AnalysisOutput]:
        """Take the next samples (times in seconds, any origin; lengths in mm).

        Raises :class:`DataError` for a non-finite value and
        :class:`~.timeaxis.TimeAxisError` for a time that runs backwards beyond
        jitter; nothing of the chunk is taken then.  ``borrow``: the detector
        may keep views of ``t`` and ``L`` instead of a copy (the caller leaves
        them unchanged while the analyzer lives: a whole recording).
        """
        t = np.asarray(t, dtype=float)
        L = np.asarray(L, dtype=float)
        if t.size and not (np.isfinite(t).all() and np.isfinite(L).all()):
            k = int(np.argmax(~(np.isfinite(t) & np.isfinite(L))))
            raise DataError(f"sample {self.detector.n_seen + k}: time or length is not a finite number")
        out = self._unqueue()
        state = self.retimer.state()
        t, L = self.retimer.feed(t, L)
        try:
            out.extend(self._take(t, L, borrow))
        except DataError:
            self.retimer.restore(state)
            raise
        return out

    def _unqueue(self) -> list[AnalysisOutput]:
        """Feed what :meth:`mark_break` left queued: the samples settled before a break, and the break."""
        out: list[AnalysisOutput] = []
        queue, self._queue = self._queue, []
        for item in queue:
            if isinstance(item, str):
                self.axis.mark(item)
            else:
                out.extend(self._take(*item))
        return out

    def _take(self, t: np.ndarray, L: np.ndarray, borrow: bool = False) -> list[AnalysisOutput]:
        """Samples on their final time axis (re-timed where a stalled host bunched them)."""
        if self._recent is not None and t.size > 1 and t[-1] - t[0] > RECENT_PIECE_S:
            # in pieces: the samples before each feed-in must still be at hand when it is found
            cuts = np.searchsorted(t, np.arange(t[0] + RECENT_PIECE_S, t[-1], RECENT_PIECE_S)).tolist()
            out: list[AnalysisOutput] = []
            for a, b in zip([0, *cuts], [*cuts, t.size], strict=True):
                if b > a:
                    out.extend(self._take(t[a:b], L[a:b], borrow))
            return out
        self._breaks.extend(self.axis.check(t))
        if t.size:
            self.last_t = float(t[-1])
        if self._recent is not None:
            self._recent.add(t, L)
        self.detector.feed(t, L, borrow)
        return self._drain()

    def choose(self, name: str | None, every_test: bool = False) -> None:
        """Analyse the next test (the next feed-in; ``every_test``: every test from then on) as plan ``name``,
        whatever its signature or timing say: an operator's or a service's explicit choice (None: none).
        Raises :class:`~.errors.PlanError` for a name the library does not have."""
        if name is not None:
            self.library.get(name)
        self._chosen, self._chosen_always = name, every_test

    def set_controller(self, program: str | None) -> None:
        """What the CNC controller runs now: its main ``program`` (None or empty: none).  A library of several
        takes the plan whose program that is (:meth:`~.plans.PlanLibrary.by_program`) for a test whose feed-in
        comes while it runs (an explicit choice aside), and says what its signature and timing say of it
        (:func:`~.plans.controller_checked`).  Never called: no controller, nothing changes."""
        p = self.library.by_program(program)
        self._controller = (program or None, p.name if p is not None else None)

    @property
    def controller(self) -> tuple[str | None, str | None] | None:
        """The controller's (program, its plan) now; None: no controller known."""
        return self._controller

    def forget_controller(self) -> None:
        """The controller is not known now (lost): the tests are recognised as without one."""
        self._controller = None

    @property
    def chosen(self) -> str | None:
        """The plan chosen for the next test (None: it is recognised)."""
        return self._chosen

    def mark_break(self, reason: str) -> None:
        """A discontinuity between the samples fed so far and the next ones, which the times may not show.

        ``reason`` names it in the rejection's message (``"device reset"``,
        ``"1200 samples lost (outage)"``).  A test it falls in is rejected, but for samples lost
        (:class:`~.timeaxis.Lost`) where the times show a drop-out the test can do without.
        Samples held for re-timing (:mod:`.retime`) are settled first: the break follows them.
        """
        if self.retimer.held or self._queue:
            t, L = self.retimer.flush()
            if t.size:
                self._queue.append((t, L))
            self._queue.append(reason)
        else:
            self.axis.mark(reason)

    def abort(self, reason: str) -> list[AnalysisOutput]:
        """The stream cannot go on as it is (the caller starts afresh): the result of the test in the
        background, if any; reject the test in progress, if any."""
        self.retimer.reset()
        self._queue = []
        out = self.collect(wait=True)
        if self._fi is None or self._rejected:
            return out
        fi = self._fi
        return [*out, self._reject(self.last_t, None, f"{reason}, {self.last_t - fi.t_s:.1f} s after the feed-in at "
                             f"t={fi.t_s:.3f} s: the test in progress is abandoned")]

    def finish(self) -> list[AnalysisOutput]:
        """End of the stream: settle the last step; the last result; report a test left unfinished."""
        out = self._unqueue()
        out.extend(self._take(*self.retimer.flush()))
        self.detector.finish()
        out.extend(self._drain())
        out.extend(self.collect(wait=True))
        if self._fi is not None and not self._rejected:
            out.append(
                {
                    "kind": "event",
                    "event": "test_incomplete",
                    "test_index": self.test_index,
                    "t_s": self.last_t,
                    "message": f"the stream ended {self.last_t - self._fi.t_s:.1f} s after the feed-in "
                    f"at t={self._fi.t_s:.3f} s, before the feed-out",
                }
            )
        return out

    def next_due(self) -> float | None:
        """When, on the samples' clock, the next result may be due: the end of the first circle not yet
        fitted; after the last one, now (the feed-out may come with any sample); None between tests and in
        a rejected test (nothing is due until the next feed-in)."""
        if self._fi is None or self._rejected:
            return None
        ends = [c.t_end for c in self._circles if c.d not in self._emitted]
        return min(ends) if ends else self.last_t

    @property
    def pending(self) -> bool:
        """A test's fit is running in the background."""
        return self._pending is not None

    def collect(self, wait: bool = False, timeout: float | None = None) -> list[AnalysisOutput]:
        """The result of the test analysed in the background, once its fit is done (``wait``: wait for it, up
        to ``timeout``); ``[]`` while it runs, or when there is none.  A fit that raised is raised here; a child
        process that died rejects its test."""
        if self._pending is None:
            return []
        index, fo, fut, rec = self._pending
        if not fut.done():
            if not wait:
                return []
            cf.wait([fut], timeout=timeout)
            if not fut.done():
                return []
        self._pending = None
        try:
            return self._settle(index, fo, fut.result, rec)
        except (cf.BrokenExecutor, cf.CancelledError) as err:
            why = f"ended before its result ({err})" if str(err) else "was stopped before its result"
            return [{"kind": "event", "event": "test_rejected", "test_index": index, "t_s": fo.t_s,
                     "message": f"the process analysing the test {why}; ballbar analyze of its recording gives it"}]

    def _drain(self) -> list[AnalysisOutput]:
        out = self.collect()
        while True:
            ev = self.detector.poll()
            if ev is None:
                break
            if self.axis.forward_steps == 0:
                raise DataError(
                    f"the time does not advance: all {self.axis.n} samples so far have t={self.axis.first_t:g} s"
                )
            if ev.kind == "feed_in":
                out.extend(self.collect(wait=True))  # its hints are the next test's
                self._start(ev)
                event = _feed_in(ev, self.test_index)
                if self.multi:  # the plan where the feed-in tells it (a signature, a choice), else null
                    event["plan"] = self._early.name if self._early is not None else None
                out.append(event)
                continue
            assert self._fi is not None
            if not self._rejected and (brk := self._break_in(self._fi.t_begin_s, ev.t_end_s)) is not None:
                out.append(self._break_rejection(brk))
            if not self._rejected:
                self._judge_dropouts(ev, out)
            if self._rejected:
                out.append(_event(ev, self.test_index))
                self._fi, self._rejected = None, False
                continue
            out.extend(self._advance(final=True))
            out.append(_event(ev, self.test_index))
            out.extend(self._finish_test(ev))
        if self._fi is not None and not self._rejected:
            brk = self._break_in(self._fi.t_begin_s, math.inf)
            if brk is not None:
                out.append(self._break_rejection(brk))
            else:
                out.extend(self._advance(final=False))
        if self._fi is None and self._breaks:
            # a later test begins after the first sample the detector still holds
            tb, _ = self.detector.samples()
            first = float(tb.min()) if tb.size else self.last_t
            self._breaks = [b for b in self._breaks if b.t_after >= first]
        return out

    def _break_in(self, t0: float, t1: float) -> Break | None:
        """The first break between the samples at ``t0`` and ``t1`` (a test's first and last step sample) that
        is no drop-out the test may do without (:mod:`.dropout`: judged at the feed-out)."""
        fi = self._fi
        return next((b for b in self._breaks if b.t_after > t0 and b.t_before < t1
                     and not (is_dropout(b) and fi is not None and not in_step(b, fi))), None)

    def _judge_dropouts(self, fo: StepEvent, out: list[AnalysisOutput]) -> None:
        """At the feed-out: reject the test for a drop-out it cannot do without, else keep them to state."""
        assert self._fi is not None
        fi = self._fi
        stated = []
        for b in self._breaks:
            if not (b.t_after > fi.t_begin_s and b.t_before < fo.t_end_s and is_dropout(b)):
                continue
            verdict = judge(self.plan, fi, fo, b, self.plan.feed_mm_s * self.hints.feed_ratio, self.hints.overhead_s)
            if verdict.rejection is not None:
                out.append(self._reject(
                    b.t_after, b.missing_s,
                    f"{b.describe()}, {b.t_after - fi.t_s:.1f} s after the feed-in at t={fi.t_s:.3f} s: a drop-out "
                    f"the test cannot do without ({verdict.rejection}); run it again"))
                return
            stated.append(verdict.stated)
        if stated:
            self._dropouts[self.test_index] = stated

    def _break_rejection(self, brk: Break) -> TestRejectedBody:
        assert self._fi is not None
        fi = self._fi
        where = ("during the feed-in" if brk.t_after <= fi.t_end_s
                 else f"{brk.t_after - fi.t_s:.1f} s after the feed-in at t={fi.t_s:.3f} s")
        return self._reject(
            brk.t_after, brk.missing_s if brk.visible else None,
            f"{brk.describe()}, {where}: the test spans a break in its time axis, so its feed and angles "
            "cannot be trusted; run it again",
        )

    def _reject(self, t_s: float, gap_s: float | None, message: str) -> TestRejectedBody:
        self._rejected = True
        self._circles = []
        log.info("test %d rejected: %s", self.test_index, message)
        ev: TestRejectedBody = {"kind": "event", "event": "test_rejected", "test_index": self.test_index,
                              "t_s": t_s, "message": message}
        if gap_s is not None:
            ev["gap_s"] = gap_s
        return ev

    def _recognise_start(self, fi: StepEvent) -> StepEvent | None:
        """A library of several: read the signature before the feed-in, and what it (or a choice) says; the
        feed-in timed with the plan where that is known, else None (no provisional circles)."""
        assert self._recent is not None
        self._pre = self._recent.before(fi.t_begin_s)
        self._reading = read_signature(*self._pre, fi.t_begin_s, fi.level_before_mm, self.library.first.plan.feed_in_mm)
        self._early = at_feed_in(self.library, self._reading, self._chosen)
        self._ctl_use = None
        if self._controller is not None and self._chosen is None:
            self._early, self._ctl_use = by_controller(self.library, self._early, self._reading, *self._controller)
        if not self._chosen_always:
            self._chosen = None
        if self._early is None or self._early.name is None:
            return None
        self._use_plan(self._early.name)
        steps = self._steps_as(self._early.name, fi, None)
        return steps[0] if steps is not None else None

    def _use_plan(self, name: str) -> None:
        p = self.library.get(name)
        self.plan, self.plan_name = p.plan, name
        self._offset = self.library.offset_mm(name)
        self.hints = self.plan_hints.get(name, TimingHints())
        if self.machine_axes is not None:
            self.machine = self.machine_axes.for_plane(self.plan.plane)
        self.patterns = select(self.options.patterns, self.plan.direction_list, self.machine.pitch_x_mm,
                               self.machine.pitch_y_mm)

    def _steps_as(self, name: str, fi: StepEvent, fo: StepEvent | None) -> tuple[StepEvent, StepEvent | None] | None:
        """The test's feed-in (and feed-out) as the detector times them for plan ``name`` at its radius: the
        detection's own, moved by the plan's offset, where its feed and dwell are the detection plan's;
        else found again by a detector of that plan in the samples (from before the feed-in on).  None
        where that detector does not find them."""
        off = self._offset
        if self.library.same_steps(name):
            return _moved(fi, off), (_moved(fo, off) if fo is not None else None)
        tb, Lb = self.detector.samples()
        pre_t, pre_L = self._pre
        t = np.concatenate([pre_t, tb])
        L = np.concatenate([pre_L, Lb]) + off
        det = TestDetector(self.library.get(name).plan)
        det.feed(t, L, borrow=True)
        if fo is not None:
            det.finish()
        steps = []
        while (ev := det.poll()) is not None:
            steps.append(ev)
        fi2 = next((e for e in steps if e.kind == "feed_in" and abs(e.t_s - fi.t_s) < 1.0), None)
        if fi2 is None:
            return None
        if fo is None:
            return fi2, None
        fo2 = next((e for e in steps if e.kind == "feed_out" and abs(e.t_s - fo.t_s) < 1.0), None)
        return (fi2, fo2) if fo2 is not None else None

    def _start(self, fi: StepEvent) -> None:
        self.test_index += 1
        self._fi = fi
        self._rejected = False
        if self.multi:
            fi_plan = self._recognise_start(fi)
            if fi_plan is None:
                self._circles = []
                self._emitted = set()
                self._added = 0
                return
            fi = fi_plan
        V = self.plan.feed_mm_s * self.hints.feed_ratio
        timing = make_timing(self.plan, fi.t_s, V, self.hints.overhead_s, accel_s=feed_accel(self.plan, [fi], V))
        self._circles = [
            CircleFit(self.plan, self.machine, _for_direction(self.patterns, d), d, timing, self.hints.spike_width_deg)
            for d in self.plan.direction_list
        ] if self.circles else []
        self._emitted = set()
        self._added = 0

    def _advance(self, final: bool) -> list[AnalysisOutput]:
        """Fold new samples into the running circles, ``FOLD_SAMPLES`` at a time or as a circle completes;
        emit the circles now complete."""
        tb, Lb = self.detector.samples()
        t_last = tb[-1] if tb.size else -math.inf
        due = final or any(c.d not in self._emitted and t_last >= c.t_end for c in self._circles)
        if self._added < tb.size and (due or tb.size - self._added >= FOLD_SAMPLES):
            t_new, L_new = tb[self._added :], Lb[self._added :]
            if self._offset:
                L_new = L_new + self._offset
            for c in self._circles:
                c.add(t_new, L_new)
            self._added = tb.size
        out: list[AnalysisOutput] = []
        for c in self._circles:
            if c.d in self._emitted or (t_last < c.t_end and not final):
                continue
            self._emitted.add(c.d)
            if c.factor.n < c.p + 2:
                continue
            try:
                fit = solve(c.factor, c.patterns, significance=self.options.significance,
                            min_effect_um=self.options.min_effect_um, vif_limit=self.options.vif_limit,
                            effect_scale=c.colmax)
            except (np.linalg.LinAlgError, ValueError) as err:  # pragma: no cover - defensive
                log.warning("circle fit failed: %s", err)
                continue
            out.append(self._circle_result(c, fit))
        return out

    def _circle_result(self, c: CircleFit, fit: FitResult) -> CircleBody:
        res: CircleBody = {
            **result_body(self.plan, self.machine, self.options, fit, c.patterns),
            "kind": "circle",
            "direction": "ccw" if c.d > 0 else "cw",
            "test_index": self.test_index,
            "timing": {
                "provisional": True,
                "feed_in_s": c.timing.t_ref,
                "assumed_feed_mm_min": c.timing.feed_mm_s * 60.0,
                "assumed_overhead_s": c.timing.overhead_s,
                "data_start_s": c.t_start,
                "data_end_s": c.t_end,
                "spike_width_deg": math.degrees(c.w),
            },
            "residual_rms_um": math.sqrt(fit.sse / max(fit.n, 1)),
        }
        self._name_plan(res, self._early)
        return res

    def _finish_test(self, fo: StepEvent) -> list[AnalysisOutput]:
        assert self._fi is not None
        fi, self._fi = self._fi, None
        if self.only is not None and self.test_index != self.only:
            return [{"kind": "event", "event": "test_skipped", "test_index": self.test_index, "t_s": fo.t_s,
                     "message": f"not analysed (test {self.only} was asked for)"}]
        rec: Recognition | None = None
        pre: list[AnalysisOutput] = []  # a disagreement of the controller's plan, before the result
        if self.multi:
            rec = at_feed_out(self.library, self._early, self._reading, fo.t_s - fi.t_s)
            if rec.name is None:
                log.info("test %d not recognised: %s", self.test_index, rec.message)
                return [{"kind": "event", "event": "test_unrecognised", "test_index": self.test_index,
                         "t_s": fo.t_s, "reason": cast(Literal["no_match", "ambiguous"], rec.reason),
                         "candidates": list(rec.candidates),
                         "signature": rec.signature, "message": rec.message}]
            log.debug("test %d recognised as %s by %s", self.test_index, rec.name, rec.method)
            if rec.method == "controller":
                rec, disagreement = controller_checked(rec)
                if disagreement is not None:
                    log.warning("test %d: %s", self.test_index, disagreement)
                    assert rec.controller is not None and rec.name is not None
                    pre = [self._disagrees(fo.t_s, rec.name, rec.controller, list(rec.candidates), disagreement)]
            elif self._ctl_use is not None:
                rec = replace(rec, controller=self._ctl_use)
            assert rec.name is not None
            if self._early is None or rec.name != self._early.name:
                self._use_plan(rec.name)
            steps = self._steps_as(rec.name, fi, fo)
            if steps is None or steps[1] is None:
                return [*pre, self._reject(fo.t_s, None, f"the steps of the test, recognised as {rec.name}, are not "
                                           f"found again with that plan's feed and dwell")]
            fi, fo = steps[0], steps[1]
        tb, Lb = self.detector.samples()
        if self.multi and not self.library.same_steps(self.plan_name):
            tb, Lb = np.concatenate([self._pre[0], tb]), np.concatenate([self._pre[1], Lb])
        m = (tb >= fi.t_begin_s) & (tb <= fo.t_end_s)
        L_test = Lb[m] + self._offset if self._offset else Lb[m]
        args = (self.plan, self.machine, self.options, tb[m], L_test, fi, fo, self.curves)
        if self.executor is None:
            return [*pre, *self._settle(self.test_index, fo, lambda: analyze_test(*args), rec)]
        fut = self.executor.submit(analyze_test, *args)
        self._pending = (self.test_index, fo, fut, rec)
        if self.on_submit is not None:
            self.on_submit(fut)
        return pre

    def _disagrees(self, t_s: float, plan: str, use: results.ControllerUse, candidates: list[str],
                   message: str) -> AnalysisOutput:
        return {"kind": "event", "event": "controller_disagrees", "test_index": self.test_index, "t_s": t_s,
                "plan": plan, "program": use["program"] or "", "signature_plan": use["signature_plan"],
                "candidates": candidates, "message": message}

    def _settle(self, index: int, fo: StepEvent, fit: Callable[[], dict[str, Any]], rec: Recognition | None = None,
                ) -> list[AnalysisOutput]:
        """A test's fit, done: its result, and the hints it teaches; or its rejection."""
        gaps = self._dropouts.pop(index, None)
        try:
            result = fit()
        except DataError as err:
            return [{"kind": "event", "event": "test_rejected", "test_index": index, "t_s": fo.t_s,
                     "message": str(err)}]
        except (cf.BrokenExecutor, cf.CancelledError):
            raise  # the worker process, not the fit: collect() says so
        except Exception as err:  # a bug in the fit costs its test only, never the daemon or the next tests
            what = f"{type(err).__name__}: {err}"
            log.error("test %d: the analysis failed (%s); the test is rejected", index, what)
            log.debug("test %d: the analysis' traceback", index, exc_info=True)
            return [{"kind": "event", "event": "test_rejected", "test_index": index, "t_s": fo.t_s,
                     "message": f"the analysis failed on this test ({what}): please report it with the recording"}]
        result["test_index"] = index
        if gaps:
            hz = result.get("samples", {}).get("sample_hz")
            for g, cost in zip(gaps, costs(self.plan, self.patterns, result["timing"], gaps, float(hz or 0.0)),
                               strict=True):
                g["cost"] = cost
            result["dropouts"] = gaps
        # assembled field by field (analysis/fitresult.py): its shape is TestBody's, which the schema tests check
        body = cast("TestBody", result)
        self._name_plan(body, rec)
        if rec is not None and rec.controller is not None:
            body["controller"] = rec.controller
        if self.multi:
            self.hints = self.plan_hints.get(self.plan_name, TimingHints())
        hints = TimingHints.learnt(body["timing"], self.hints)
        if hints is None:
            log.warning("test %d: a measured feed of %.1f mm/min (programmed %g) is no timing hint for the next "
                        "test's provisional circles", index, body["timing"]["measured_feed_mm_min"],
                        self.plan.feed_mm_min)
        else:
            self.hints = hints
            self.plan_hints[self.plan_name] = hints
        return [body]

    def _name_plan(self, res: CircleBody | TestBody, rec: Recognition | None) -> None:
        """The plan's name, its axes and how it was recognised, beside the plan's keys."""
        res["plan"]["name"] = self.plan_name
        res["plan"]["axes"] = list(cast("tuple[MachineAxis, MachineAxis]", self.library.get(self.plan_name).axes))
        res["recognition"] = (rec or Recognition(self.plan_name, "only")).to_dict()


def _moved(ev: StepEvent, offset_mm: float) -> StepEvent:
    """A step's levels read at another radius (the plan's offset)."""
    if not offset_mm:
        return ev
    return replace(ev, level_before_mm=ev.level_before_mm + offset_mm, level_after_mm=ev.level_after_mm + offset_mm)


def _feed_in(ev: StepEvent, test_index: int) -> FeedInBody:
    return {"kind": "event", "event": "feed_in", "test_index": test_index, "t_s": ev.t_s, "height_mm": ev.height_mm,
            "method": ev.method}


def _event(ev: StepEvent, test_index: int) -> FeedInBody | FeedOutBody:
    if ev.kind == "feed_in":
        return _feed_in(ev, test_index)
    return {
        "kind": "event",
        "event": "feed_out",
        "test_index": test_index,
        "t_s": ev.t_s,
        "height_mm": ev.height_mm,
        "method": ev.method,
    }


def _for_direction(patterns: Sequence[Pattern], d: int) -> list[Pattern]:
    return [p for p in patterns if p.reversal is None or p.reversal[2] == d]


def analyze_recording(
    t: np.ndarray,
    L: np.ndarray,
    plan: TestPlan,
    machine: MachineConfig | MachineAxes | None = None,
    options: AnalysisOptions | None = None,
    curves: bool = False,
    breaks: Sequence[tuple[int, str]] = (),
    circles: bool = True,
    only: int | None = None,
    library: PlanLibrary | None = None,
    chosen: str | None = None,
    controller: Sequence[tuple[int, bool, str | None]] = (),
) -> list[AnalysisOutput]:
    """Everything :class:`TestAnalyzer` reports on a whole recording, in order.

    ``library``: the plans its tests may run (see :class:`TestAnalyzer`);
    ``chosen``: analyse every test as that plan of the library.

    ``curves``: see :func:`analyze_test`.  ``breaks``: ``(index, reason)``, a
    discontinuity the times may not show (a device reset) just before sample
    ``index`` (:meth:`TestAnalyzer.mark_break`).  ``circles``: False for no
    provisional circle results (the tests' results are the same).  ``only``:
    fit that test alone (see :class:`TestAnalyzer`; with ``circles=False``).  ``controller``: ``(index, known,
    program)``, what the CNC controller said from sample ``index`` on (:meth:`TestAnalyzer.set_controller`;
    ``known`` False: lost), as the daemon took it live.
    """
    t = np.asarray(t, dtype=float)
    L = np.asarray(L, dtype=float)
    if t.size >= 2 and np.all(np.isfinite(t)) and not np.any(t[1:] > t[:-1]):  # no full-length np.diff
        what = f"all {t.size} samples have t={t[0]:g} s" if np.all(t == t[0]) else "it never increases"
        raise DataError(f"the time axis does not advance ({what}): no test can be timed")
    an = TestAnalyzer(plan, machine, options, curves=curves, circles=circles, only=only, library=library)
    if chosen is not None and an.multi:
        an.choose(chosen, every_test=True)
    plan = an.plan
    out: list[AnalysisOutput] = []
    i = 0
    # the breaks and the controller's news, in sample order (a break first where both fall before one sample)
    marks: list[tuple[int, int, Any]] = [(int(k), 0, why) for k, why in breaks]
    marks += [(int(k), 1, (known, program)) for k, known, program in controller]
    for at, kind, arg in sorted(marks, key=lambda m: (m[0], m[1])):
        j = min(max(at, i), t.size)
        out.extend(an.feed(t[i:j], L[i:j], borrow=True))
        if kind == 0:
            an.mark_break(arg)
        elif arg[0]:
            an.set_controller(arg[1])
        else:
            an.forget_controller()
        i = j
    out.extend(an.feed(t[i:], L[i:], borrow=True))
    out.extend(an.finish())
    if not any(r.get("event") == "feed_in" for r in out):
        lo, hi = an.detector.seen_range()
        raise DetectionError(
            f"no feed-in found: the bar never stepped from about {plan.radius_mm + plan.feed_in_mm:g} mm "
            f"(R + feed-in) to {plan.radius_mm:g} mm (R); its length ranged {lo:.4f}..{hi:.4f} mm"
        )
    return out


__all__ = ["HINT_MAX_FEED_DEVIATION", "CircleFit", "TestAnalyzer", "TimingHints", "analyze_recording", "analyze_test"]
