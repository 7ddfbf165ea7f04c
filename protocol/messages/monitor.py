"""The monitor's messages: a test's verdict, a trend's forecast, the alerts, the trend history's entries.

A :class:`Verdict` is a test result's ``verdict`` with ``[limits]`` on
(``ballbar.analysis.monitor.evaluate``); an alert (:data:`Alert`) goes out on
``ballbar/<m>/alert`` when a verdict changes or a forecast becomes due or
clears; a :class:`HistoryEntry` is one line of the monitor's
``<machine>-history.jsonl``, what a trend keeps of a test.
"""

from typing import Annotated, Literal, NotRequired, TypedDict

from .envelope import Version
from .fields import doc

Status = Literal["pass", "warning", "fail"]


class Conditions(TypedDict):
    """the test conditions a trend is kept under (the report's trend selection): per plan"""

    plan: NotRequired[Annotated[str, doc("the plan's name in the library (default: a single [plan]; absent in alerts "
                                         "made before plans were a library)")]]
    plane: Annotated[Literal["XY", "YZ", "ZX"], doc("the plane of the circle")]
    radius_mm: Annotated[float, doc("the programmed radius", "mm")]
    feed_mm_min: Annotated[float, doc("the programmed feed", "mm/min")]
    data_arc_deg: Annotated[float, doc("the data arc", "deg")]
    directions: Annotated[Literal["both", "ccw", "cw"], doc("the directions run")]


class LimitEntry(TypedDict):
    """one configured limit against a test"""

    name: Annotated[str, doc("the result field: a parameter name or G_ccw_um, G_cw_um, G_b_um, H_um")]
    limit_name: Annotated[str, doc("the configured limit (G_um applies to G_ccw_um and G_cw_um)")]
    group: Annotated[Literal["parameters", "iso230_4"], doc("where the value comes from: the result's parameters or "
                                                            "its ISO 230-4 figures")]
    limit: Annotated[float, doc("bound on |value|, in unit", exclusiveMinimum=0)]
    warn_fraction: Annotated[float, doc("a warning from this fraction of the limit", exclusiveMinimum=0, maximum=1)]
    warning_level: Annotated[float, doc("warn_fraction * limit, in unit")]
    unit: Annotated[str, doc("the value's unit")]
    status: Annotated[Literal["pass", "warning", "fail", "not_evaluated"], doc(
        "this limit's verdict (not_evaluated: the value is missing, see reason)")]
    value: Annotated[float | None, doc("the value, in unit", null="not evaluated")]
    stderr: Annotated[float | None, doc("standard uncertainty u")]
    uncertainty: Annotated[float | None, doc("expanded uncertainty k u")]
    margin: Annotated[float | None, doc("limit - |value| (negative: above the limit)")]
    margin_pct: NotRequired[Annotated[float | None, doc("margin in % of the limit")]]
    within_uncertainty: Annotated[bool, doc("|margin| <= k u: may or may not exceed the limit")]
    note: NotRequired[Annotated[str, doc("a remark in words (e.g. within uncertainty of the limit)")]]
    reason: NotRequired[Annotated[str | None, doc("not_evaluated: why")]]


class Verdict(TypedDict):
    """a test's verdict against the limits ([limits])"""

    status: Annotated[Status, doc("the worst status of the evaluated limits")]
    coverage_k: Annotated[float, doc("the coverage factor k of the expanded uncertainty k u", exclusiveMinimum=0)]
    rule: Annotated[str, doc("the verdict's rule, in words")]
    uncertainty: Annotated[str, doc("how each uncertainty was obtained")]
    limits: Annotated[list[LimitEntry], doc("each configured limit against this test")]
    not_evaluated: Annotated[int, doc("how many limits could not be evaluated", minimum=0)]
    summary: Annotated[str, doc("one line")]
    trend_excluded: NotRequired[Annotated[str, doc("present when this test does not enter trends: why")]]


class Forecast(TypedDict):
    """a limited field's trend and when it crosses its limit"""

    name: Annotated[str, doc("the limited field (a parameter name, G_ccw_um, G_cw_um, G_b_um or H_um)")]
    limit_name: Annotated[str, doc("the configured limit it is held to")]
    limit: Annotated[float, doc("the limit, in the field's unit")]
    bound: NotRequired[Annotated[float, doc("the bound the trend heads for: +limit (a positive value rising) or "
                                            "-limit (a negative one falling)")]]
    n: Annotated[int, doc("valid tests in the trend", minimum=0)]
    min_tests: Annotated[int, doc("no forecast from fewer valid tests")]
    horizon_days: Annotated[float, doc("a crossing within this many days is due", "days")]
    confidence: Annotated[float, doc("the crossing interval's confidence (e.g. 0.95)")]
    watched: NotRequired[Annotated[int, doc("quantities watched together (the Bonferroni correction)", minimum=1)]]
    slope_confidence: NotRequired[Annotated[float, doc("the slope interval's confidence: 1 - (1 - confidence) / "
                                                       "watched")]]
    method: Annotated[str, doc("how the trend and its interval were found, in words")]
    due: Annotated[bool, doc("a significant trend heads for the limit and its crossing's later bound is within the "
                             "horizon and within the tests' span ahead")]
    reason: NotRequired[Annotated[str, doc("when not due: why")]]
    test_ids: Annotated[list[str], doc("the tests in the trend")]
    slope_per_day: NotRequired[Annotated[float, doc("the trend's slope (wall-clock days between tests)",
                                                    "unit per day")]]
    slope_lo: NotRequired[Annotated[float | None, doc("the slope's lower confidence bound", "unit per day",
                                                      null="too few tests")]]
    slope_hi: NotRequired[Annotated[float | None, doc("its upper bound", "unit per day", null="too few tests")]]
    significant: NotRequired[Annotated[bool, doc("the slope's interval (slope_confidence) excludes zero")]]
    span_days: NotRequired[Annotated[float, doc("from the trend's first test to its last", "days")]]
    reach_days: NotRequired[Annotated[float, doc("how far ahead a crossing may be forecast: the horizon or the span, "
                                                 "the shorter", "days")]]
    value_now: NotRequired[Annotated[float, doc("the trend's value at the last test, in the field's unit")]]
    first: NotRequired[Annotated[str, doc("t_wall of the trend's first test (ISO 8601 UTC)")]]
    last: NotRequired[Annotated[str, doc("t_wall of its last test (ISO 8601 UTC)")]]
    crossing: NotRequired[Annotated[str | None, doc("ISO 8601 UTC", null="no crossing ahead: flat, heading away, "
                                                    "or already there")]]
    crossing_lo: NotRequired[Annotated[str | None, doc("the crossing's early confidence bound, never before the "
                                                       "last test, ISO 8601 UTC",
                                                       null="none")]]
    crossing_hi: NotRequired[Annotated[str | None, doc("its late bound, ISO 8601 UTC",
                                                       null="unbounded within the confidence")]]
    days_to_crossing: NotRequired[Annotated[float | None, doc("from the last test to the crossing", "days",
                                                              null="no crossing")]]
    days_to_crossing_lo: NotRequired[Annotated[float | None, doc("to its early bound", "days", null="none")]]
    days_to_crossing_hi: NotRequired[Annotated[float | None, doc("to its late bound", "days", null="unbounded")]]


AlertMachine = Annotated[str, doc("the daemon's machine_id (the key chunk <m>)", minLength=1)]
AlertTWall = Annotated[str, doc("ISO 8601 UTC: when the alert was made")]
AlertId = Annotated[str, doc("<machine>-alert-<n>, n counting every alert of the machine")]
Cleared = Annotated[bool, doc("true when the alert ends an earlier one (back to pass, forecast clear)")]
AlertTestId = Annotated[str | None, doc("the test result the alert refers to")]
TTest = Annotated[str, doc("t_wall of that test result")]
Message = Annotated[str, doc("one readable line")]


class VerdictAlert(TypedDict):
    """a test's verdict changed"""

    schema_version: Version
    kind: Annotated[Literal["alert"], doc("alert")]
    machine_id: AlertMachine
    t_wall: AlertTWall
    alert_id: AlertId
    alert: Annotated[Literal["verdict"], doc("verdict: a test's verdict changed")]
    state: Annotated[Status, doc("the new verdict")]
    previous: Annotated[Status | None, doc("the verdict before this alert", null="the first verdict")]
    cleared: Cleared
    test_id: AlertTestId
    t_test: TTest
    conditions: Conditions
    verdict: Verdict
    message: Message


class ForecastAlert(TypedDict):
    """a trend's forecast became due or cleared"""

    schema_version: Version
    kind: Annotated[Literal["alert"], doc("alert")]
    machine_id: AlertMachine
    t_wall: AlertTWall
    alert_id: AlertId
    alert: Annotated[Literal["forecast"], doc("forecast: a trend's forecast became due or cleared")]
    state: Annotated[Literal["due", "clear"], doc("due (the trend crosses its limit within the horizon) or clear")]
    previous: Annotated[Literal["due", "clear"], doc("the state before this alert")]
    cleared: Cleared
    limit: Annotated[str, doc("the limited field (e.g. backlash_x_um, G_b_um)")]
    test_id: AlertTestId
    t_test: TTest
    conditions: Conditions
    forecast: Forecast
    message: Message


Alert = VerdictAlert | ForecastAlert


class HistoryEntry(TypedDict):
    """What a trend keeps of one test: a line of the monitor's <machine>-history.jsonl."""

    test_id: Annotated[str | None, doc("the test's id")]
    machine_id: Annotated[str | None, doc("the daemon's machine_id")]
    t_wall: Annotated[str, doc("the test result's t_wall (ISO 8601 UTC)")]
    conditions: Conditions
    invalid: Annotated[str | None, doc("why the test does not enter a trend", null="it does")]
    status: Annotated[Status | None, doc("its verdict's status", null="no verdict")]
    values: Annotated[dict[str, list[float | None]], doc("each limited field's [value, standard uncertainty], in its "
                                                         "unit")]
