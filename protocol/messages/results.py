"""The analysis' results: a circle's and a test's body, as the analysis makes them and the daemon publishes them.

:class:`CircleBody` and :class:`TestBody` are what ``ballbar.analysis`` returns
(``analysis/result.py``, ``analysis/engine.py``, ``analysis/fitresult.py``);
:class:`Analysis` is ``ballbar analyze --json`` (a test body with ``source``);
:class:`CircleResult` and :class:`TestResult` are the daemon's
``ballbar/<m>/result/circle`` and ``result/test`` (the body plus the daemon's
envelope and :class:`~.envelope.LastSample`).  Every parameter of the pattern
library is in :class:`Parameters`, fitted or not, with its unit.
"""

from typing import Annotated, Literal, NotRequired, TypedDict

from .envelope import LastSample, MachineId, TWall, Version
from .fields import doc
from .monitor import Verdict

Direction = Literal["ccw", "cw"]
Plane = Literal["XY", "YZ", "ZX"]
Directions = Literal["both", "ccw", "cw"]


class Parameter(TypedDict):
    """one fitted parameter"""

    value: Annotated[float | None, doc("the estimate, in unit; null when not fitted or not identifiable (reason says "
                                       "why)")]
    stderr: Annotated[float | None, doc("its standard error, in unit (autocorrelation-inflated); null when not "
                                        "fitted")]
    unit: Annotated[str, doc("um, ms, urad, ppm, deg or um/min")]
    p_value: Annotated[float | None, doc("its pattern's F-test p-value, 0..1; null when not fitted", minimum=0,
                                         maximum=1)]
    share_pct: Annotated[float | None, doc("its pattern's share of the explained sum of squares", "%",
                                           null="not fitted")]
    significant: Annotated[bool, doc("a finding: passes the significance rule (fit.significance_rule)")]
    identifiable: Annotated[bool, doc("fitted: false when left out (reason)")]
    reason: NotRequired[Annotated[str, doc("why it was not fitted (partial arc, not separable, no screw pitch, ...)")]]
    significance_reason: NotRequired[Annotated[str, doc("why a parameter whose F-test passed is not significant (may "
                                                        "be empty)")]]


class Parameters(TypedDict):
    """every field of the pattern library, fitted or not, keyed by name (unit in the name)"""

    centre_x_um: Annotated[Parameter, doc("set-up: the programmed circle's centre from the pivot, X (first axis of "
                                          "the plane)", "um")]
    centre_y_um: Annotated[Parameter, doc("set-up: the programmed circle's centre from the pivot, Y (second axis)",
                                          "um")]
    radius_um: Annotated[Parameter, doc("the bar's length at the feed-in beyond R (calibration, temperature, mean "
                                        "scale)", "um")]
    backlash_x_um: Annotated[Parameter, doc("lost motion of the first axis (negative: compensation set too high)",
                                            "um")]
    backlash_y_um: Annotated[Parameter, doc("lost motion of the second axis", "um")]
    servo_mismatch_ms: Annotated[Parameter, doc("1/KX - 1/KY: the first axis' position loop lags the second's by "
                                                "this", "ms")]
    master_slave_a_um: Annotated[Parameter, doc("master-slave changeover step along (1,1)/sqrt2", "um")]
    master_slave_b_um: Annotated[Parameter, doc("master-slave changeover step along (1,-1)/sqrt2", "um")]
    squareness_urad: Annotated[Parameter, doc("the axes enclose 90 deg minus this", "urad")]
    scale_mismatch_ppm: Annotated[Parameter, doc("the first axis travels this much more than the second per command",
                                                 "ppm")]
    lateral_play_x_um: Annotated[Parameter, doc("lateral play when the first axis reverses", "um")]
    lateral_play_y_um: Annotated[Parameter, doc("lateral play when the second axis reverses", "um")]
    straightness_x_um: Annotated[Parameter, doc("bow of the first axis at +-R", "um")]
    straightness_y_um: Annotated[Parameter, doc("bow of the second axis at +-R", "um")]
    cyclic_x_um: Annotated[Parameter, doc("amplitude of the first axis' screw-pitch cyclic error (needs "
                                          "machine.pitch_x_mm)", "um")]
    cyclic_x_phase_deg: Annotated[Parameter, doc("phase of that cyclic error", "deg")]
    cyclic_y_um: Annotated[Parameter, doc("amplitude of the second axis' screw-pitch cyclic error (needs "
                                          "machine.pitch_y_mm)", "um")]
    cyclic_y_phase_deg: Annotated[Parameter, doc("phase of that cyclic error", "deg")]
    drift_um_per_min: Annotated[Parameter, doc("growth of the bar reading during the test (thermal drift)",
                                               "um/min")]
    reversal_spike_x_pos_ccw_um: Annotated[Parameter, doc("friction spike where the first axis reverses at its pos "
                                                          "end, CCW direction", "um")]
    reversal_spike_x_pos_cw_um: Annotated[Parameter, doc("friction spike where the first axis reverses at its pos "
                                                         "end, CW direction", "um")]
    reversal_spike_x_neg_ccw_um: Annotated[Parameter, doc("friction spike where the first axis reverses at its neg "
                                                          "end, CCW direction", "um")]
    reversal_spike_x_neg_cw_um: Annotated[Parameter, doc("friction spike where the first axis reverses at its neg "
                                                         "end, CW direction", "um")]
    reversal_spike_y_pos_ccw_um: Annotated[Parameter, doc("friction spike where the second axis reverses at its pos "
                                                          "end, CCW direction", "um")]
    reversal_spike_y_pos_cw_um: Annotated[Parameter, doc("friction spike where the second axis reverses at its pos "
                                                         "end, CW direction", "um")]
    reversal_spike_y_neg_ccw_um: Annotated[Parameter, doc("friction spike where the second axis reverses at its neg "
                                                          "end, CCW direction", "um")]
    reversal_spike_y_neg_cw_um: Annotated[Parameter, doc("friction spike where the second axis reverses at its neg "
                                                         "end, CW direction", "um")]


class RankingEntry(TypedDict):
    """one pattern's test"""

    pattern: Annotated[str, doc("the pattern's name (backlash_x, servo_mismatch, reversal_spike_x_pos_ccw, ...)")]
    share_pct: Annotated[float | None, doc("its share of the explained sum of squares", "%")]
    F: Annotated[float | None, doc("its F statistic", null="infinite")]
    p_value: Annotated[float | None, doc("its p-value, 0..1")]
    significant: Annotated[bool, doc("passes the significance rule")]
    effect_um: NotRequired[Annotated[float | None, doc("its largest radial effect", "um")]]
    significance_reason: NotRequired[Annotated[str, doc("why it is not significant although its F-test passed")]]


class Advice(TypedDict):
    """one suggestion"""

    pattern: Annotated[str, doc("the parameter it comes from (e.g. backlash_x_um)")]
    kind: Annotated[str, doc("what is to be done: machine (a compensation or repair), setup, ...")]
    action: Annotated[str, doc("the suggestion in words")]
    value: Annotated[float | None, doc("the amount, in unit")]
    unit: Annotated[str, doc("the amount's unit")]
    controller_parameter: NotRequired[Annotated[str, doc("the controller's parameter for it (machine.controller)")]]


class Plan(TypedDict):
    """the test plan the analysis assumed (daemon [plan], analysis/README.md)"""

    plane: Annotated[Plane, doc("XY, YZ or ZX")]
    radius_mm: Annotated[float, doc("R, the bar's nominal length", "mm")]
    feed_mm_min: Annotated[float, doc("F, the programmed feed", "mm/min")]
    start_deg: Annotated[float, doc("where the first arc starts", "deg")]
    overshoot_deg: Annotated[float, doc("swept before and after the data arc", "deg")]
    data_arc_deg: Annotated[float, doc("the analysed arc", "deg")]
    feed_in_mm: Annotated[float, doc("the radial feed-in and feed-out", "mm")]
    dwell_s: Annotated[float, doc("each dwell", "s")]
    directions: Annotated[Directions, doc("both, ccw or cw")]
    sample_hz: Annotated[float, doc("the expected sample rate", "Hz")]


MachineAxis = Literal["X", "Y", "Z"]


class ResultPlan(Plan):
    """the test plan the analysis assumed: one of the library's (daemon [plan] or [plans.<name>], analysis/README.md)"""

    name: NotRequired[Annotated[str, doc("the plan's name in the library (default: a single [plan])")]]
    axes: NotRequired[Annotated[list[MachineAxis], doc(
        "the machine axes of the plane's first and second axis: every _x field is about the first, every _y field "
        "about the second", minItems=2, maxItems=2)]]


class Recognition(TypedDict):
    """how the test's plan was known (analysis/plans.py)"""

    method: Annotated[Literal["only", "signature", "timing", "chosen", "controller"], doc(
        "only: a library of one; signature: the code before its feed-in (checked against its timing); timing: the "
        "only plan whose timing fits; chosen: named by an operator or service; controller: the plan whose program "
        "the controller ran at the feed-in ([controller], plans.<name>.program)")]
    signature: Annotated[int | None, doc("the signature's code read before the feed-in", null="none read")]
    feed_ratio: Annotated[float | None, doc("the feed-in to feed-out span's feed over the plan's (a feed override), "
                                            "at no per-move overhead", null="not computed")]
    candidates: Annotated[list[str], doc("the plans whose timing fits the test at a feed override of 80..120 %")]
    message: Annotated[str, doc("in words")]


class ControllerUse(TypedDict):
    """what the CNC controller said of the test ([controller]): the program it ran at the feed-in, the plan that
    program names, and whether the signature and the timing agree"""

    program: Annotated[str | None, doc("the main program the controller ran at the feed-in",
                                       null="none known (not connected, or no program running)")]
    plan: Annotated[str | None, doc("the plan whose program pattern it matches", null="none")]
    used: Annotated[bool, doc("the controller's plan is the test's (recognition.method controller)")]
    signature_plan: Annotated[str | None, doc("the plan the program's signature named", null="none read")]
    timing_fits: Annotated[bool | None, doc("the plan's timing fits the test at a feed override of 80..120 %",
                                            null="not checked")]
    agrees: Annotated[bool, doc("the signature (where read) and the timing agree with the controller's plan")]
    message: Annotated[str, doc("in words")]


class Machine(TypedDict):
    """what the analysis knew of the machine: [machine] of the plane's two axes, x the first and y the second
    (plan.axes: in ZX, x is Z's and y X's)"""

    pitch_x_mm: Annotated[float | None, doc("first axis' screw pitch", "mm", null="unknown, no cyclic error fitted")]
    pitch_y_mm: Annotated[float | None, doc("second axis' screw pitch", "mm", null="unknown")]
    kv_x_per_s: Annotated[float | None, doc("first axis' configured position-loop gain", "1/s", null="unknown")]
    kv_y_per_s: Annotated[float | None, doc("second axis' configured position-loop gain", "1/s", null="unknown")]
    controller: Annotated[str, doc("generic, fanuc, siemens or heidenhain: parameter names in the advice")]


# --------------------------------------------------------------------------- fit


class LostAxis(TypedDict):
    """one axis' lost-motion model"""

    model: Annotated[Literal["deadband", "compensation", "step"], doc("deadband, compensation or step")]
    onset_deg: Annotated[float, doc("where friction starts after the reversal point", "deg")]
    reversal_deg: Annotated[float, doc("where the table reverses, past the commanded reversal", "deg")]
    description: Annotated[str, doc("the model in words")]


class LoopDeg(TypedDict):
    """the loops' lag as angles, deg"""

    lead: Annotated[float, doc("the lead", "deg")]
    x: Annotated[float, doc("first axis", "deg")]
    y: Annotated[float, doc("second axis", "deg")]


class LostMotion(TypedDict):
    """the lost-motion model per axis"""

    x: LostAxis
    y: LostAxis
    loop_deg: NotRequired[LoopDeg]


class LevelChange(TypedDict):
    """one data arc's largest level change"""

    direction: Annotated[Direction, doc("ccw or cw")]
    at_deg: Annotated[float | None, doc("where", "deg")]
    step_um: Annotated[float, doc("its size", "um")]
    z: Annotated[float, doc("in standard errors of the two windows' difference")]


class Checks(TypedDict):
    """the checks that the model describes the test (analysis/README.md, 'When the model does not fit')"""

    sensor_noise_um: Annotated[float | None, doc("the sensor's white noise from the samples alone, at least the "
                                                 "quantisation noise of reading_step_um / sqrt(12)", "um")]
    reading_step_um: Annotated[float | None, doc("the step (resolution) the readings sit on", "um",
                                                 null="not quantised")]
    residual_rms_um: Annotated[float | None, doc("the fit's residual", "um")]
    last_arc_feed_ratio: Annotated[float | None, doc("the last arc's feed against the first's, as the residual tells "
                                                     "it", null="one direction")]
    last_arc_feed_z: Annotated[float | None, doc("its difference from 1 in standard errors", null="one direction")]
    level_change: Annotated[list[LevelChange], doc("per data arc, the residual's largest step away from the "
                                                   "reversals")]


class Fit(TypedDict):
    """the fit's diagnostics"""

    n_samples: Annotated[int, doc("samples fitted")]
    n_parameters: Annotated[int, doc("parameters fitted")]
    dof: Annotated[int, doc("degrees of freedom of the residual")]
    sigma_um: Annotated[float | None, doc("residual standard deviation", "um")]
    residual_lag1_autocorrelation: Annotated[float | None, doc("rho, the residual's lag-1 autocorrelation")]
    variance_inflation: Annotated[float | None, doc("(1+rho)/(1-rho), applied to the covariance")]
    condition_number: Annotated[float | None, doc("of the scaled design matrix", null="infinite")]
    significance: Annotated[float, doc("the F-test level")]
    min_effect_um: Annotated[float, doc("the minimum radial effect of a significant pattern", "um")]
    significance_rule: Annotated[str, doc("the whole significance rule in words")]
    servo_model: Annotated[Literal["linear", "physical"], doc("linear or physical")]
    uncertainty_method: Annotated[str, doc("how the standard errors were computed, in words")]


class TestFit(Fit):
    """the fit's diagnostics"""

    servo_model_note: NotRequired[Annotated[str | None, doc("where the loop lag came from")]]
    lost_motion: LostMotion
    lost_motion_model: Annotated[str, doc("lost_motion in words")]
    evaluations: NotRequired[Annotated[int, doc("misfit evaluations the fit made (the objective at a value of its "
                                                "nonlinear parameters)")]]
    designs: NotRequired[Annotated[int, doc("designs the fit made: its misfit evaluations and their slopes")]]
    valid: Annotated[bool, doc("false: the model does not describe this test (invalid_reasons say why); no parameter "
                               "is then significant")]
    invalid_reasons: NotRequired[Annotated[list[str], doc("why the model does not describe the test, in words")]]
    checks: NotRequired[Checks]


# --------------------------------------------------------------------------- timing


class Arc(TypedDict):
    """one data arc on the time axis"""

    start_s: Annotated[float, doc("start", "s")]
    end_s: Annotated[float, doc("end", "s")]
    shift_s: Annotated[float, doc("how much later it ran than equal per-move overheads put it", "s")]


class DataArcs(TypedDict):
    """the data arcs by direction"""

    ccw: NotRequired[Arc]
    cw: NotRequired[Arc]


class Axes(TypedDict):
    """an angle per axis"""

    x: Annotated[float, doc("first axis", "deg")]
    y: Annotated[float, doc("second axis", "deg")]


class PolledTiming(TypedDict):
    """A polled gauge's stamps, stated on its results (``analysis.polled``: stamped at the middle of each
    request/answer window)."""

    time_source: NotRequired[Annotated[str, doc("present for a polled gauge: what the time stamps are, in words")]]
    t_uncertainty_ms: NotRequired[Annotated[float, doc("polled gauge: the stamps' uncertainty (half the p99 "
                                                       "request/answer window)", "ms")]]
    t_jitter_ms: NotRequired[Annotated[float, doc("polled gauge: the stamps' jitter (half the p1..p99 window spread)",
                                                  "ms")]]
    t_jitter_deg: NotRequired[Annotated[float | None, doc("polled gauge: that jitter as an angle at the measured feed",
                                                          "deg", null="no feed")]]


class TestTiming(PolledTiming):
    """the test's timing: feed, arc-start lag, spike width, feed-in and feed-out, data arcs, position loops"""

    provisional: Annotated[Literal[False], doc("false: the test's own timing")]
    programmed_feed_mm_min: Annotated[float, doc("F", "mm/min")]
    measured_feed_mm_min: Annotated[float | None, doc("from the feed-in to feed-out span", "mm/min")]
    feed_ratio: NotRequired[Annotated[float | None, doc("measured / programmed feed")]]
    overhead_s: NotRequired[Annotated[float | None, doc("per-move overhead (the arc start's lag)", "s")]]
    lag_s: NotRequired[Annotated[float | None, doc("the arc start's lag", "s")]]
    lag_deg: NotRequired[Annotated[float | None, doc("the same as an angle", "deg")]]
    lag_stderr_s: NotRequired[Annotated[float | None, doc("its standard error", "s", null="not estimated")]]
    spike_width_deg: NotRequired[Annotated[float | None, doc("the reversal spikes' decay width", "deg")]]
    spike_width_stderr_deg: NotRequired[Annotated[float | None, doc("its standard error", "deg",
                                                                    null="not estimated")]]
    feed_in_s: Annotated[float, doc("the feed-in's centroid on the time axis", "s")]
    feed_out_s: Annotated[float, doc("the feed-out's centroid", "s")]
    feed_in_method: NotRequired[Annotated[str, doc("how the feed-in was timed (centroid, ...)")]]
    feed_out_method: NotRequired[Annotated[str, doc("how the feed-out was timed")]]
    feed_in_height_mm: NotRequired[Annotated[float, doc("the feed-in step's height", "mm")]]
    feed_out_height_mm: NotRequired[Annotated[float, doc("the feed-out step's height", "mm")]]
    data_arcs: DataArcs
    method: NotRequired[Annotated[str, doc("how the timing was found, in words")]]
    loop_lag_ms: Annotated[float | None, doc("the position loop's mean lag", "ms", null="no physical servo model")]
    loop_lag_source: NotRequired[Annotated[str | None, doc("where the loop lag came from, in words")]]
    loop_lag_origin: Annotated[str, doc("configured, feed_in, fitted, assumed, none or linear")]
    loop_lag_radial_cos2u: NotRequired[Annotated[float | None, doc("the loops' radial cos 2u term", "um",
                                                                   null="none")]]
    loop_lag_stderr_ms: NotRequired[Annotated[float | None, doc("where the loop lag was searched with the timing "
                                                                "(nothing else told it): its standard error", "ms")]]
    loop_feed_forward: NotRequired[Annotated[float | None, doc(
        "where an over-set backlash compensation's steps place it: the share of a command step the loops pass at "
        "once (velocity feed-forward), 0..0.98; their lag on the circle is (1 - this) times the settling's",
        null="not searched")]]
    loop_feed_forward_stderr: NotRequired[Annotated[float | None, doc("its standard error", null="not searched")]]
    backlash_takeup_deg: NotRequired[Annotated[Axes, doc("the travel over which each axis' dead band is taken up "
                                                         "after the axis reverses, deg")]]
    reversal_onset_deg: NotRequired[Annotated[Axes, doc("where friction starts after each reversal point, deg")]]


class CircleTiming(PolledTiming):
    """a circle's provisional timing (assumed from the plan or the last good test)"""

    provisional: Annotated[Literal[True], doc("true: assumed timing, the test's result will refine it")]
    feed_in_s: Annotated[float, doc("the feed-in's centroid on the time axis", "s")]
    assumed_feed_mm_min: Annotated[float, doc("the feed assumed", "mm/min")]
    assumed_overhead_s: Annotated[float, doc("the arc start's lag assumed", "s")]
    data_start_s: Annotated[float, doc("the data arc's start", "s")]
    data_end_s: Annotated[float, doc("the data arc's end", "s")]
    spike_width_deg: Annotated[float, doc("the spike width assumed", "deg")]


# --------------------------------------------------------------------------- a test's figures


class IsoConditions(TypedDict):
    """the test conditions ISO 230-4 asks to state"""

    plane: Annotated[str, doc("XY, YZ or ZX")]
    radius_mm: Annotated[float, doc("the radius", "mm")]
    feed_mm_min: Annotated[float, doc("programmed", "mm/min")]
    measured_feed_mm_min: Annotated[float | None, doc("measured", "mm/min")]
    data_arc_deg: Annotated[float, doc("the data arc", "deg")]
    start_deg: Annotated[float, doc("where it starts", "deg")]
    directions: Annotated[str, doc("both, ccw or cw")]
    sample_hz: Annotated[float | None, doc("the sample rate", "Hz")]
    centre_removal: Annotated[str, doc("how the centre was removed, in words")]
    standard: Annotated[str, doc("the edition, ISO 230-4:2022")]


class Iso230(TypedDict):
    """ISO 230-4 figures and their conditions (null: the direction was not run)"""

    G_ccw_um: Annotated[float | None, doc("circular deviation G, CCW", "um")]
    G_cw_um: Annotated[float | None, doc("circular deviation G, CW", "um")]
    G_b_um: Annotated[float | None, doc("bidirectional circular deviation G(b)", "um")]
    H_um: Annotated[float | None, doc("circular hysteresis H", "um")]
    F_max_um: Annotated[float | None, doc("largest radial deviation F from the nominal radius", "um")]
    F_min_um: Annotated[float | None, doc("smallest radial deviation F", "um")]
    conditions: IsoConditions


class _StandardText(TypedDict):
    standard: Annotated[str, doc("the standard and its edition")]


class _StandardNotes(TypedDict):
    centre_removal: Annotated[str, doc("how the centre was removed, in words")]
    computes: Annotated[str, doc("what the figures are, in words")]
    differs_from_iso230_4: Annotated[str, doc("where they differ from ISO 230-4's (iso230_4), in words")]
    assumption: Annotated[str, doc("what was assumed of the standard's text (empty: nothing)")]


class _JisFigures(_StandardText):
    G_ccw_um: Annotated[float | None, doc("circular deviation G, CCW", "um")]
    G_cw_um: Annotated[float | None, doc("circular deviation G, CW", "um")]
    G_b_um: Annotated[float | None, doc("bidirectional circular deviation G(b)", "um")]
    F_max_um: Annotated[float | None, doc("largest radial deviation F", "um")]
    F_min_um: Annotated[float | None, doc("smallest radial deviation F", "um")]


class Jis(_JisFigures, _StandardNotes):
    """JIS B 6190-4:2008 (ISO 230-4:2005)'s circular-test figures (analysis/standards.py)"""


class _AsmeFigures(_StandardText):
    circular_deviation_ccw_um: Annotated[float | None, doc("circular deviation about the minimum-zone centre, CCW",
                                                           "um")]
    circular_deviation_cw_um: Annotated[float | None, doc("the same, CW", "um")]
    circular_deviation_b_um: Annotated[float | None, doc("both directions about one minimum-zone centre", "um")]
    H_um: Annotated[float | None, doc("circular hysteresis", "um")]
    F_max_um: Annotated[float | None, doc("largest radial deviation", "um")]
    F_min_um: Annotated[float | None, doc("smallest radial deviation", "um")]


class Asme(_AsmeFigures, _StandardNotes):
    """ASME B5.54-2005's circular-test figures (analysis/standards.py)"""


class Standards(TypedDict):
    """the other standards chosen ([analysis] standards), each under its id; ISO 230-4's are iso230_4"""

    jis_b6190_4: NotRequired[Jis]
    asme_b5_54: NotRequired[Asme]


class Noise(TypedDict):
    """vibration and stick-slip"""

    vibration_um: Annotated[float | None, doc("the residual's RMS above vibration_cutoff_cpr (sensor noise included)",
                                              "um")]
    vibration_cutoff_cpr: NotRequired[Annotated[float, doc("the cutoff", "cycles per revolution")]]
    vibration_peak_um: NotRequired[Annotated[float | None, doc("the strongest spectral line's amplitude", "um")]]
    vibration_peak_hz: NotRequired[Annotated[float | None, doc("its frequency", "Hz")]]
    vibration_peak_cpr: NotRequired[Annotated[float | None, doc("its frequency", "cycles per revolution")]]
    vibration_significant: Annotated[bool, doc("the line stands out of the noise floor")]
    stick_slip_x_um: NotRequired[Annotated[float | None, doc("stick-slip of the first axis", "um")]]
    stick_slip_x_p_value: NotRequired[Annotated[float | None, doc("the F-test of the variance near the reversals "
                                                                  "against elsewhere")]]
    stick_slip_x_significant: NotRequired[Annotated[bool, doc("significant")]]
    stick_slip_y_um: NotRequired[Annotated[float | None, doc("stick-slip of the second axis", "um")]]
    stick_slip_y_p_value: NotRequired[Annotated[float | None, doc("the same for the second axis")]]
    stick_slip_y_significant: NotRequired[Annotated[bool, doc("significant")]]
    method: Annotated[str, doc("how, in words")]


class SamplesUsed(TypedDict):
    """samples the test used"""

    in_test: Annotated[int, doc("valid samples from the feed-in to the feed-out")]
    in_data_arcs: Annotated[int, doc("of those, in the data arcs")]
    sample_hz: Annotated[float | None, doc("the rate measured from the timestamps", "Hz")]


# --------------------------------------------------------------------------- the results

_KIND = "circle: one direction's fit, provisional; test: the whole test"
TestIndex = Annotated[int, doc("the test's number in this stream (daemon run or file), from 1")]
Ranking = Annotated[list[RankingEntry], doc("the fitted patterns by extra sum of squares, largest first")]
AdviceList = Annotated[list[Advice], doc("suggested adjustments for the significant patterns, largest effect first")]
ResidualRms = Annotated[float | None, doc("the fit's residual RMS", "um")]
Warnings = Annotated[list[str], doc("what makes the result less trustworthy: a sample rate other than the plan's, an "
                                    "overshoot too short to reach the feed (timing model), ...")]


class BodyCommon(TypedDict):
    """What a circle's and a test's body share, as ``ballbar.analysis.result.result_body`` makes it."""

    schema_version: Version
    plan: ResultPlan
    recognition: NotRequired[Recognition]
    machine: Machine
    parameters: Parameters
    ranking: Ranking
    advice: AdviceList
    fit: Fit


class CircleBody(TypedDict):
    """A circle's result as the analysis makes it: one direction's fit, after its data arc, on provisional timing."""

    schema_version: Version
    kind: Annotated[Literal["circle"], doc(_KIND)]
    direction: Annotated[Direction, doc("ccw or cw")]
    test_index: TestIndex
    plan: ResultPlan
    recognition: NotRequired[Recognition]
    machine: Machine
    parameters: Parameters
    ranking: Ranking
    advice: AdviceList
    fit: Fit
    timing: CircleTiming
    residual_rms_um: ResidualRms
    warnings: NotRequired[Warnings]


class DropoutCost(TypedDict):
    """what a drop-out costs one pattern"""

    pattern: Annotated[str, doc("the pattern's name (backlash_x, squareness, ...)")]
    stderr_factor: Annotated[float, doc("its standard errors over what they would be with the lost samples "
                                        "present, the largest of its parameters'", minimum=1)]


class Dropout(TypedDict):
    """samples lost inside the test, on a clock that ran on (analysis/README.md, "Drop-outs")"""

    t_s: Annotated[float, doc("the time of the last sample before the gap", "s")]
    duration_s: Annotated[float, doc("the time lost, beyond one sample period", "s")]
    samples_missing: Annotated[int, doc("about how many samples that is, at the median period", minimum=0)]
    direction: Annotated[Literal["ccw", "cw"] | None, doc("the data arc the gap falls in", null="in none")]
    from_deg: Annotated[float | None, doc("the commanded angle where the gap begins", "deg", null="in no data arc")]
    to_deg: Annotated[float | None, doc("the commanded angle where it ends", "deg", null="in no data arc")]
    arc_fraction: Annotated[float, doc("the part of that data arc lost, 0..1", minimum=0, maximum=1)]
    cost: NotRequired[Annotated[list[DropoutCost], doc("per pattern, what the gap costs its standard error")]]


class TestBody(TypedDict):
    """A test's result as the analysis makes it: the whole test, on its own timing."""

    schema_version: Version
    kind: Annotated[Literal["test"], doc(_KIND)]
    test_index: TestIndex
    plan: ResultPlan
    recognition: NotRequired[Recognition]
    controller: NotRequired[ControllerUse]
    machine: Machine
    parameters: Parameters
    ranking: Ranking
    advice: AdviceList
    fit: TestFit
    timing: TestTiming
    residual_rms_um: ResidualRms
    warnings: NotRequired[Warnings]
    iso230_4: Iso230
    standards: NotRequired[Standards]
    noise: Noise
    samples: SamplesUsed
    dropouts: NotRequired[Annotated[list[Dropout], doc("drop-outs the test was analysed across (none: no field)")]]
    verdict: NotRequired[Annotated[Verdict, doc("with [limits] on: pass, warning or fail against each limit")]]


class Produced(TypedDict):
    """Who produced a result, and when (the envelope's other fields are the body's)."""

    machine_id: MachineId
    t_wall: TWall


class CircleResult(CircleBody, Produced, LastSample):
    """a circle result as the daemon publishes it"""


class TestResult(TestBody, Produced, LastSample):
    """a test result as the daemon publishes it"""


class AnalysisSource(TypedDict):
    """what was analysed"""

    file: Annotated[str, doc("absolute path of the file (records: the test's first file)")]
    tests_found: NotRequired[Annotated[int, doc("tests found in the file")]]
    files: NotRequired[Annotated[list[str], doc("the test's files (records)")]]
    test_id: NotRequired[Annotated[str | None, doc("the test's id (records)")]]
    machine_id: NotRequired[Annotated[str | None, doc("the daemon's machine_id (records)")]]
    time_axis: NotRequired[Annotated[str, doc("device or host (records)")]]
    tests_recorded: NotRequired[Annotated[int, doc("tests in the records")]]


class Analysis(TestBody):
    """`ballbar analyze --json`: one test's result (the daemon's result/test payload has the same fields without
    source, plus its own)."""

    source: AnalysisSource


Result = CircleResult | TestResult
Body = CircleBody | TestBody

