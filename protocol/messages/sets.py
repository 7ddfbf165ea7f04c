"""A test set's result: its tests combined into the machine's axes (``kind: "set"``, ``ballbar/<m>/result/set``,
the MCAP results channel); ``ballbar.analysis.sets`` makes it, analysis/README.md "Test sets" explains it.

Every figure says its unit in ``unit`` and whether it can be trusted (``trusted``, ``reasons``).
"""

from typing import Annotated, Literal, TypedDict

from .envelope import MachineId, TWall, Version
from .fields import doc

Reasons = Annotated[list[str], doc("why it is not trusted, or observations left out (may be empty)")]


class Figure(TypedDict):
    """a set figure"""

    value: Annotated[float | None, doc("the figure, in unit", null="none; reasons say why")]
    stderr: Annotated[float | None, doc("its standard uncertainty, in unit", null="none")]
    unit: Annotated[str, doc("the unit")]
    trusted: Annotated[bool, doc("false where no value, a check behind it failed, or a test behind it is invalid")]
    reasons: Reasons


class Observation(TypedDict):
    """one test's estimate of the quantity"""

    plan: Annotated[str, doc("the test's plan")]
    plane: Annotated[Literal["XY", "YZ", "ZX"], doc("its plane")]
    test_id: Annotated[str | None, doc("the test's id")]
    field: Annotated[str, doc("the test's parameter it is (in the plane's first/second axis naming)")]
    value: Annotated[float | None, doc("its value", null="not fitted")]
    stderr: Annotated[float | None, doc("its standard error", null="none")]
    used: Annotated[bool, doc("entered the combination")]
    reason: Annotated[str | None, doc("why not used")]


class Combined(Figure):
    """a quantity combined from the tests that see it"""

    observations: Annotated[list[Observation], doc("each test's estimate")]
    check: Annotated[str | None, doc("the name of its consistency check", null="seen by one test")]


class Pair(Combined):
    """an axis pair's figure (e_a - e_b for the pair ab)"""

    adjusted: Annotated[Figure, doc("the least-squares value once the loop's closure is enforced")]


class Pairs(TypedDict):
    """per axis pair"""

    XY: Pair
    YZ: Pair
    ZX: Pair


class AxisFigures(TypedDict):
    """each axis against the mean of the three"""

    X: Figure
    Y: Figure
    Z: Figure


class Loop(TypedDict):
    """a figure of the three axis pairs: per pair, the loop's closure, each axis against the three axes' mean"""

    unit: Annotated[str, doc("ppm or ms")]
    pairs: Pairs
    closure: Annotated[str, doc("the name of the closure check in checks")]
    axes: AxisFigures


class AxesLostMotion(TypedDict):
    """lost motion per axis, um"""

    X: Annotated[Combined, doc("the X axis' lost motion", "um")]
    Y: Annotated[Combined, doc("the Y axis' lost motion", "um")]
    Z: Annotated[Combined, doc("the Z axis' lost motion", "um")]


class PairsSquareness(TypedDict):
    """squareness per pair, urad (+: +a and +b enclose less than 90 deg)"""

    XY: Annotated[Combined, doc("the XY squareness", "urad")]
    YZ: Annotated[Combined, doc("the YZ squareness", "urad")]
    ZX: Annotated[Combined, doc("the ZX squareness", "urad")]


class Check(TypedDict):
    """a check of the whole set"""

    name: Annotated[str, doc("its name")]
    kind: Annotated[Literal["consistency", "closure"], doc(
        "consistency (two tests see one quantity) or closure (a loop of three pairs)")]
    quantity: Annotated[str, doc("what is checked")]
    status: Annotated[Literal["passed", "failed", "not_checked"], doc("passed, failed or not_checked")]
    value: Annotated[float | None, doc("the discrepancy: consistency, the difference (more than two: the largest from "
                                       "the mean); closure, the sum of the three pairs", null="not checked")]
    stderr: Annotated[float | None, doc("its standard error", null="not checked")]
    z: Annotated[float | None, doc("value / stderr (more than two tests: sqrt of chi-square per degree of freedom)")]
    coverage_k: Annotated[float, doc("fails beyond this many standard errors ...")]
    min_discrepancy: Annotated[float, doc("... and above this, in unit")]
    unit: Annotated[str, doc("the unit")]
    message: Annotated[str, doc("the check in words")]


class Member(TypedDict):
    """one plan's test in the set"""

    plan: Annotated[str, doc("the plan")]
    plane: Annotated[str, doc("its plane")]
    test_id: Annotated[str | None, doc("the test's id")]
    t_wall: Annotated[str | None, doc("when its result was published (ISO 8601 UTC)")]
    radius_mm: Annotated[float | None, doc("its radius", "mm")]
    feed_mm_min: Annotated[float | None, doc("its programmed feed", "mm/min")]
    data_arc_deg: Annotated[float | None, doc("its data arc", "deg")]
    valid: Annotated[bool, doc("its fit's checks held (fit.valid)")]
    invalid_reasons: Annotated[list[str], doc("why not valid")]
    verdict: Annotated[Literal["pass", "warning", "fail", "not_evaluated"], doc(
        "its own verdict against its plan's limits; not_evaluated without limits")]
    verdict_summary: Annotated[str | None, doc("its verdict in one line")]
    G_b_um: Annotated[float | None, doc("its G(b)", "um")]


class Extreme(Figure):
    """the largest circular deviation of the set's valid tests (unit um)"""

    plan: Annotated[str | None, doc("the plan whose test has it")]
    test_id: Annotated[str | None, doc("that test")]
    figure: Annotated[str | None, doc("G_b_um, or G_ccw_um / G_cw_um for a one-direction test")]


class Sphericity(Figure):
    """the geometric sphericity: the range of the radial deviation the squareness and relative scale errors make over
    the sphere (unit um)"""

    interval: Annotated[list[float] | None, doc("its 95 % interval", "um", null="no value", minItems=2, maxItems=2)]
    radius_mm: Annotated[float | None, doc("the sphere's radius: the set's largest", "mm")]


class Volumetric(TypedDict):
    """volumetric figures"""

    largest_circular_deviation: Extreme
    geometric_sphericity: Sphericity
    method: Annotated[str, doc("how both are computed, in words")]


class PlanVerdict(TypedDict):
    """a plan's verdict"""

    plan: Annotated[str, doc("the plan")]
    status: Annotated[str, doc("its test's verdict")]
    summary: Annotated[str | None, doc("in one line")]


class SetVerdict(TypedDict):
    """the set's verdict"""

    status: Annotated[Literal["pass", "warning", "fail"], doc("pass, warning or fail")]
    trusted: Annotated[bool, doc("every check passed and every test is valid")]
    plans: Annotated[list[PlanVerdict], doc("each plan's own verdict")]
    failed_checks: Annotated[list[str], doc("names of failed checks")]
    reasons: Annotated[list[str], doc("why not trusted")]
    summary: Annotated[str, doc("the verdict in one line")]
    rule: Annotated[str, doc("how the verdict is made, in words")]


class SetDefinition(TypedDict):
    """the set's definition ([sets.<name>])"""

    name: Annotated[str, doc("its name")]
    plans: Annotated[list[str], doc("its plans")]
    window_s: Annotated[float, doc("its tests must all lie within this", "s")]


class SetResult(TypedDict):
    """a set result as the daemon publishes it"""

    schema_version: Version
    kind: Annotated[Literal["set"], doc("what the payload is")]
    machine_id: MachineId
    t_wall: TWall
    set_id: Annotated[str, doc("<set name>@<the newest member test's id>")]
    set: SetDefinition
    tests: Annotated[list[Member], doc("the latest test of each plan, in the set's order")]
    span_s: Annotated[float | None, doc("from the oldest to the newest member test", "s")]
    lost_motion: AxesLostMotion
    squareness: PairsSquareness
    scale: Annotated[Loop, doc("relative scale, ppm: per pair, the loop's closure, each axis against the three axes' "
                               "mean")]
    servo: Annotated[Loop, doc("servo lag mismatch, ms: per pair, the loop's closure, each axis against the three "
                               "axes' mean")]
    volumetric: Volumetric
    checks: Annotated[list[Check], doc("every consistency and closure check")]
    verdict: SetVerdict
    conventions: Annotated[dict[str, str], doc("the sign conventions, in words")]
    method: Annotated[str, doc("how the figures are combined, in words")]
