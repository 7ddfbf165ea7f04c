"""Events: a source's (its device or port), the analysis' (a test's steps and fate), the MCAP logger's.

Each event is a ``TypedDict`` of its own, told apart by ``event``.  The
analysis makes the bodies of its events (:class:`FeedInBody`...); the daemon
publishes them with the envelope and :class:`~.envelope.MaybeLastSample`
(:class:`FeedIn`...).  A source's events come from
``ballbar.daemon.samples.SourceEvent.to_dict`` and go out with the envelope,
``origin: "source"`` and the source's URL.  The MCAP log stores every event
without ``kind`` (and a source's as the source reported them, without the
envelope): the ``mcap-event`` schema is derived from these (:mod:`.documents`);
:class:`LogGap` is the logger's own, in the MCAP log only.
"""

from typing import Annotated, Literal, NotRequired, TypedDict, TypeVar

from .envelope import MachineId, MaybeLastSample, SourceUrl, THost, TWall, Version
from .fields import doc

T = TypeVar("T")

EventKind = Annotated[Literal["event"], doc("what the payload is")]
Name = Annotated[T, doc("which event this is")]
Detail = Annotated[str, doc("what was seen")]
GapS = Annotated[float, doc("the gap", "s")]


class SourceStamp(TypedDict):
    """The envelope of a source's event."""

    schema_version: Version
    kind: EventKind
    machine_id: MachineId
    t_wall: TWall
    origin: Annotated[Literal["source"], doc("source: the device or its port")]
    t_host: THost
    source: SourceUrl


class PipelineStamp(TypedDict):
    """The envelope of an event of the analysis, or one found at start (``origin: "recovery"``); with
    :class:`~.envelope.MaybeLastSample`."""

    schema_version: Version
    machine_id: MachineId
    t_wall: TWall
    origin: NotRequired[Annotated[Literal["recovery"], doc("recovery: found at start (absent: the analysis')")]]


# --------------------------------------------------------------------------- a source's


class Opened(SourceStamp):
    """the port, simulator or recording is open"""

    event: Name[Literal["opened"]]
    detail: NotRequired[Annotated[str, doc("what was opened")]]


class Unplugged(SourceStamp):
    """the port failed mid-read; the source closes it and retries with backoff"""

    event: Name[Literal["unplugged"]]
    detail: NotRequired[Annotated[str, doc("the error")]]


class Replugged(SourceStamp):
    """the port is open again (the samples lost across the outage follow as a lost event)"""

    event: Name[Literal["replugged"]]
    gap_s: NotRequired[Annotated[float, doc("the outage", "s")]]
    detail: NotRequired[Annotated[str, doc("the port")]]


class Lost(SourceStamp):
    """samples never received"""

    event: Name[Literal["lost"]]
    count: Annotated[int, doc("how many", minimum=1)]
    seq: NotRequired[Annotated[int, doc("the first one's sample number")]]
    detail: NotRequired[Annotated[str, doc("gap, outage, stall, poll_timeout, poll_late or restart")]]


class DecodeErrors(SourceStamp):
    """decoder drops since the last report"""

    event: Name[Literal["decode_errors"]]
    counts: Annotated[dict[str, int], doc("by reason (bad_crc, bad_line, skipped_bytes, ...): how many")]


class Stall(SourceStamp):
    """no bytes while connected"""

    event: Name[Literal["stall"]]
    gap_s: NotRequired[Annotated[float, doc("the silence so far", "s")]]


class Resumed(SourceStamp):
    """bytes again after a stall"""

    event: Name[Literal["resumed"]]
    gap_s: NotRequired[Annotated[float, doc("the silence", "s")]]


class DeviceReset(SourceStamp):
    """the device restarted (its sample counter or clock ran back): a break in the time axis"""

    event: Name[Literal["device_reset"]]
    seq: NotRequired[Annotated[int, doc("the first sample after the restart")]]
    detail: NotRequired[Detail]


class ClockJump(SourceStamp):
    """the device clock stepped beyond its sample counter: a break in the time axis"""

    event: Name[Literal["clock_jump"]]
    seq: NotRequired[Annotated[int, doc("the first sample after the step")]]
    gap_s: NotRequired[Annotated[float, doc("the step", "s")]]
    detail: NotRequired[Detail]


class CounterJump(SourceStamp):
    """the device's sample counter leapt while its clock ran on: a counter fault, no sample lost, no break"""

    event: Name[Literal["counter_jump"]]
    seq: NotRequired[Annotated[int, doc("the first sample after the leap")]]
    count: NotRequired[Annotated[int, doc("the counter's leap beyond the samples the clock says were taken")]]
    detail: NotRequired[Detail]


class End(SourceStamp):
    """a finite source (replay, sim: with a repeat count) has ended"""

    event: Name[Literal["end"]]
    detail: NotRequired[Annotated[str, doc("why")]]


class Timing(SourceStamp):
    """a polled gauge's stamps (no device clock): sent when first known and whenever their uncertainty grows by a
    quarter; the MCAP log repeats the last at the head of each file"""

    event: Name[Literal["timing"]]
    detail: NotRequired[Annotated[str, doc("what the stamps are, in words")]]
    t_uncertainty_s: Annotated[float, doc("half the p99 request/answer window", "s")]
    t_jitter_s: Annotated[float, doc("half the windows' p1..p99 spread", "s")]
    window_median_s: NotRequired[Annotated[float, doc("the windows' median", "s")]]
    window_p99_s: NotRequired[Annotated[float, doc("their 99th percentile", "s")]]
    achieved_hz: NotRequired[Annotated[float, doc("answers per second", "Hz")]]
    repeated: NotRequired[Annotated[bool, doc("MCAP only: true on the copy at the head of a file")]]


SourceEvent = (Opened | Unplugged | Replugged | Lost | DecodeErrors | Stall | Resumed | DeviceReset | ClockJump | End
               | Timing)

# --------------------------------------------------------------------------- the analysis'

TestIndex = Annotated[int, doc("the test's number in this daemon run, from 1")]
TS = Annotated[float | None, doc("where on the time axis", "s")]


class FeedInBody(TypedDict):
    """The analysis' ``feed_in`` event, as the daemon publishes it in :class:`FeedIn`."""

    kind: EventKind
    event: Name[Literal["feed_in"]]
    test_index: TestIndex
    t_s: TS
    height_mm: NotRequired[Annotated[float, doc("the step's height", "mm")]]
    method: NotRequired[Annotated[str, doc("how it was timed (centroid, ...)")]]
    plan: NotRequired[Annotated[str | None, doc("a library of several plans: the plan the feed-in tells (its "
                                                "program's signature, a choice)", null="the timing decides at the "
                                                "feed-out")]]


class FeedOutBody(TypedDict):
    """The analysis' ``feed_out`` event, as the daemon publishes it in :class:`FeedOut`."""

    kind: EventKind
    event: Name[Literal["feed_out"]]
    test_index: TestIndex
    t_s: TS
    height_mm: NotRequired[Annotated[float, doc("the step's height", "mm")]]
    method: NotRequired[Annotated[str, doc("how it was timed")]]


class TestRejectedBody(TypedDict):
    """The analysis' ``test_rejected`` event, as the daemon publishes it in :class:`TestRejected`."""

    kind: EventKind
    event: Name[Literal["test_rejected"]]
    test_index: TestIndex
    t_s: NotRequired[TS]
    message: Annotated[str, doc("the reason, where and when")]
    gap_s: NotRequired[Annotated[float | None, doc("the time missing from the axis, where it shows", "s")]]


class TestIncompleteBody(TypedDict):
    """The analysis' ``test_incomplete`` event, as the daemon publishes it in :class:`TestIncomplete`."""

    kind: EventKind
    event: Name[Literal["test_incomplete"]]
    test_index: NotRequired[TestIndex]
    t_s: NotRequired[TS]
    message: Annotated[str, doc("what happened")]
    file: NotRequired[Annotated[str, doc("origin recovery: the recording that holds its samples")]]


class AnalysisResetBody(TypedDict):
    """The analysis' ``analysis_reset`` event, as the daemon publishes it in :class:`AnalysisReset`."""

    kind: EventKind
    event: Name[Literal["analysis_reset"]]
    message: Annotated[str, doc("why")]


class TestUnrecognisedBody(TypedDict):
    """The analysis' ``test_unrecognised`` event, as the daemon publishes it in :class:`TestUnrecognised`."""

    kind: EventKind
    event: Name[Literal["test_unrecognised"]]
    test_index: TestIndex
    t_s: NotRequired[TS]
    reason: Annotated[Literal["no_match", "ambiguous"], doc("no_match or ambiguous")]
    candidates: Annotated[list[str], doc("the plans whose timing fits the test")]
    signature: NotRequired[Annotated[int | None, doc("the signature's code read before the feed-in", null="none")]]
    message: Annotated[str, doc("why, with the candidates")]


class PlanChosenBody(TypedDict):
    """The daemon's ``plan_chosen`` event (a choice on ballbar/<m>/control/next_plan), in :class:`PlanChosen`."""

    kind: EventKind
    event: Name[Literal["plan_chosen"]]
    plan: Annotated[str | None, doc("the plan's name", null="the choice was withdrawn")]
    message: Annotated[str, doc("in words")]


class PlanChoiceRefusedBody(TypedDict):
    """The daemon's ``plan_choice_refused`` event, in :class:`PlanChoiceRefused`."""

    kind: EventKind
    event: Name[Literal["plan_choice_refused"]]
    message: Annotated[str, doc("why")]


class ControllerDisagreesBody(TypedDict):
    """The analysis' ``controller_disagrees`` event, as the daemon publishes it in :class:`ControllerDisagrees`."""

    kind: EventKind
    event: Name[Literal["controller_disagrees"]]
    test_index: TestIndex
    t_s: NotRequired[TS]
    plan: Annotated[str, doc("the plan the controller's program names: the test's")]
    program: Annotated[str, doc("the main program the controller ran at the feed-in")]
    signature_plan: Annotated[str | None, doc("the plan the program's signature named", null="none read")]
    candidates: Annotated[list[str], doc("the plans whose timing fits the test")]
    message: Annotated[str, doc("what disagrees, in words")]


class TestSkippedBody(TypedDict):
    """Offline only (``ballbar analyze --test N``): a test not analysed because another was asked for."""

    kind: Literal["event"]
    event: Name[Literal["test_skipped"]]
    test_index: int
    t_s: float | None
    message: str


class FeedIn(PipelineStamp, FeedInBody, MaybeLastSample):
    """a test began: the feed-in step was recognised"""


class FeedOut(PipelineStamp, FeedOutBody, MaybeLastSample):
    """the test's feed-out step; the test result follows"""


class TestRejected(PipelineStamp, TestRejectedBody, MaybeLastSample):
    """the test gives no result: a break in its time axis or an analysis failure"""


class TestIncomplete(PipelineStamp, TestIncompleteBody, MaybeLastSample):
    """the test never finished: the stream ended, or the daemon was killed during it (origin recovery, published at
    the next start)"""


class AnalysisReset(PipelineStamp, AnalysisResetBody, MaybeLastSample):
    """the analysis could not take the time axis and started afresh (the test in progress is rejected)"""


class TestUnrecognised(PipelineStamp, TestUnrecognisedBody, MaybeLastSample):
    """the test matches no plan of the library, or more than one: it is not analysed as any of them
    (analysis/plans.py)"""


class PlanChosen(PipelineStamp, PlanChosenBody, MaybeLastSample):
    """an explicit choice of the next test's plan was taken (ballbar/<m>/control/next_plan)"""


class PlanChoiceRefused(PipelineStamp, PlanChoiceRefusedBody, MaybeLastSample):
    """a choice of the next plan named no plan of the library, or was not understood"""


class ControllerDisagrees(PipelineStamp, ControllerDisagreesBody, MaybeLastSample):
    """the controller's program named the test's plan, and its signature or its timing say otherwise (the
    controller's plan is taken; the result's controller block says so too)"""


PipelineEvent = (FeedIn | FeedOut | TestRejected | TestIncomplete | AnalysisReset | TestUnrecognised | PlanChosen
                 | PlanChoiceRefused | ControllerDisagrees)
EventBody = (FeedInBody | FeedOutBody | TestRejectedBody | TestIncompleteBody | AnalysisResetBody | TestSkippedBody
             | TestUnrecognisedBody | PlanChosenBody | PlanChoiceRefusedBody | ControllerDisagreesBody)
Event = SourceEvent | PipelineEvent


class LogGap(TypedDict):
    """MCAP only: samples the logger could not write (a write error, a full disk)"""

    event: Name[Literal["log_gap"]]
    t_host: THost
    count: Annotated[int, doc("samples not logged")]
    gap_s: NotRequired[Annotated[float, doc("over this long", "s")]]
    detail: NotRequired[Annotated[str, doc("the error")]]
    lost_t_host: NotRequired[Annotated[list[float | None], doc(
        "samples lost: their span on the host clock, from the newest sample written before to the first after "
        "(or the newest lost); null: not known", "s")]]
    lost_t_device: NotRequired[Annotated[list[float | None], doc("the same span on the device clock", "s")]]
    lost_utc: NotRequired[Annotated[list[str | None], doc("the same span as UTC times (ISO 8601)")]]
