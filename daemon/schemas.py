"""JSON Schemas (draft 2020-12) of every payload the daemon publishes and logs.

The schemas are the contract with plant services: a service validates what it
reads against them instead of guessing from examples.  They are built here and
shipped as files in the package, ``ballbar/schema/<name>.schema.json``
(``importlib.resources.files("ballbar") / "schema"``); ``python -m
ballbar.daemon.schemas --write DIR`` writes them anywhere, and the MCAP
recordings register the same documents as their channels' schemas
(``ballbar.Result``, ``ballbar.Event``, ``ballbar.Status``, ``ballbar.Config``).

=============  ===================================================  ==================================
name           payload                                              where
=============  ===================================================  ==================================
``result``     a circle's (``kind: "circle"``) or a test's          ``ballbar/<m>/result/circle``,
               (``kind: "test"``) analysis result                   ``.../result/test``, MCAP
                                                                    ``/ballbar/results``
``analysis``   ``ballbar analyze --json`` (a test result without    stdout
               the daemon's fields, with ``source``)
``event``      every event, one branch per ``event`` name           ``ballbar/<m>/event``
``mcap-event`` the same as the MCAP log stores them (no ``kind``;   MCAP ``/ballbar/events``
               a source's events as the source reported them)
``status``     the periodic status                                  ``ballbar/<m>/status``, MCAP
``config``     the effective configuration (secrets redacted)       ``ballbar/<m>/config``, MCAP
``samples``    decimated samples                                    ``ballbar/<m>/samples``
``history``    a ``history/<topic>`` reply                          ``ballbar/<m>/history/*``
``set``        a test set combined into the machine's axes          ``ballbar/<m>/result/set``, MCAP
               (``kind: "set"``, :mod:`ballbar.analysis.sets`)      ``/ballbar/results``
=============  ===================================================  ==================================

Every object whose shape is the daemon's own is closed (``additionalProperties:
false``): a field the daemon starts to send without a schema entry fails the
schema tests.  Units are in each field's description (and in its name).
Every payload carries ``schema_version`` (:data:`ballbar.SCHEMA_VERSION`): it
changes, and so do the schemas' ``$id``, whenever a payload changes in a way
that can break a reader (a field removed, renamed, retyped or given another
meaning); new optional fields do not change it.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from functools import cache
from pathlib import Path
from typing import Any

from ballbar import SCHEMA_VERSION

DRAFT = "https://json-schema.org/draft/2020-12/schema"
NAMES = ("result", "analysis", "event", "mcap-event", "status", "config", "samples", "history", "alert", "set")

Schema = dict[str, Any]


# --------------------------------------------------------------------------- building blocks


def _t(kind: str | list[str], desc: str, nullable: bool = False, **kw: Any) -> Schema:
    types = [kind] if isinstance(kind, str) else list(kind)
    if nullable:
        types.append("null")
    return {"type": types[0] if len(types) == 1 else types, "description": desc, **kw}


def num(desc: str, nullable: bool = False, **kw: Any) -> Schema:
    """A number (JSON has no NaN: the daemon sends a non-finite value as null, so such fields are nullable)."""
    return _t("number", desc, nullable, **kw)


def integer(desc: str, nullable: bool = False, **kw: Any) -> Schema:
    return _t("integer", desc, nullable, **kw)


def string(desc: str, nullable: bool = False, **kw: Any) -> Schema:
    return _t("string", desc, nullable, **kw)


def boolean(desc: str) -> Schema:
    return _t("boolean", desc)


def obj(desc: str, props: dict[str, Schema], required: Sequence[str] | None = None, nullable: bool = False) -> Schema:
    """A closed object; ``required`` defaults to every property."""
    return {
        "type": ["object", "null"] if nullable else "object",
        "description": desc,
        "properties": props,
        "required": list(props) if required is None else list(required),
        "additionalProperties": False,
    }


def counts(desc: str, item: str = "integer") -> Schema:
    """A map whose keys are open-ended names (decoder reasons, causes, gains...)."""
    return {"type": "object", "description": desc, "additionalProperties": {"type": item}}


def _envelope(kind: str) -> dict[str, Schema]:
    return {
        "schema_version": {"const": SCHEMA_VERSION, "description": "version of these payloads' shapes"},
        "kind": {"const": kind, "description": "what the payload is"},
        "machine_id": string("the daemon's daemon.machine_id: the <m> of ballbar/<m>/..."),
        "t_wall": string("when the daemon produced it: ISO 8601 UTC with milliseconds, e.g. 2026-11-21T10:59:56.123Z"),
    }


_T_HOST = num("the daemon host's monotonic clock, s (not wall time; t_wall is that)")
_LAST_SAMPLE = {
    "test_id": string("the test's id, <machine>-<UTC time of the feed-in YYYYmmddTHHMMSSZ>[-2, -3...]", True),
    "t_host": _T_HOST,
    "last_sample_t": num("the time axis value of the last sample the analysis had seen, s (see time_axis)", True),
    "last_sample_t_host": num("that sample's host time, s, on t_host's monotonic clock", True),
    "latency_ms": num("t_host - last_sample_t_host: how long after its last sample this went out, ms", True),
    "time_axis": string(
        "the analysis' time axis: device (the device's sample clock; with --simulate, simulated seconds) or host",
        True, enum=["device", "host", None],
    ),
}


# --------------------------------------------------------------------------- analysis results

#: The pattern library's result fields (analysis/README.md, "The pattern library"), with their units.
PARAMETERS: dict[str, tuple[str, str]] = {
    "centre_x_um": ("um", "set-up: the programmed circle's centre from the pivot, X (first axis of the plane)"),
    "centre_y_um": ("um", "set-up: the programmed circle's centre from the pivot, Y (second axis)"),
    "radius_um": ("um", "the bar's length at the feed-in beyond R (calibration, temperature, mean scale)"),
    "backlash_x_um": ("um", "lost motion of the first axis (negative: compensation set too high)"),
    "backlash_y_um": ("um", "lost motion of the second axis"),
    "servo_mismatch_ms": ("ms", "1/KX - 1/KY: the first axis' position loop lags the second's by this"),
    "master_slave_a_um": ("um", "master-slave changeover step along (1,1)/sqrt2"),
    "master_slave_b_um": ("um", "master-slave changeover step along (1,-1)/sqrt2"),
    "squareness_urad": ("urad", "the axes enclose 90 deg minus this"),
    "scale_mismatch_ppm": ("ppm", "the first axis travels this much more than the second per command"),
    "lateral_play_x_um": ("um", "lateral play when the first axis reverses"),
    "lateral_play_y_um": ("um", "lateral play when the second axis reverses"),
    "straightness_x_um": ("um", "bow of the first axis at +-R"),
    "straightness_y_um": ("um", "bow of the second axis at +-R"),
    "cyclic_x_um": ("um", "amplitude of the first axis' screw-pitch cyclic error (needs machine.pitch_x_mm)"),
    "cyclic_x_phase_deg": ("deg", "phase of that cyclic error"),
    "cyclic_y_um": ("um", "amplitude of the second axis' screw-pitch cyclic error (needs machine.pitch_y_mm)"),
    "cyclic_y_phase_deg": ("deg", "phase of that cyclic error"),
    "drift_um_per_min": ("um/min", "growth of the bar reading during the test (thermal drift)"),
    **{
        f"reversal_spike_{a}_{e}_{d}_um": ("um", f"friction spike where the {'first' if a == 'x' else 'second'} "
                                                 f"axis reverses at its {e} end, {d.upper()} direction")
        for a in "xy" for e in ("pos", "neg") for d in ("ccw", "cw")
    },
}

_PARAMETER = obj(
    "one fitted parameter",
    {
        "value": num("the estimate, in unit; null when not fitted or not identifiable (reason says why)", True),
        "stderr": num("its standard error, in unit (autocorrelation-inflated); null when not fitted", True),
        "unit": string("um, ms, urad, ppm, deg or um/min"),
        "p_value": num("its pattern's F-test p-value, 0..1; null when not fitted", True, minimum=0, maximum=1),
        "share_pct": num("its pattern's share of the explained sum of squares, %; null when not fitted", True),
        "significant": boolean("a finding: passes the significance rule (fit.significance_rule)"),
        "identifiable": boolean("fitted: false when left out (reason)"),
        "reason": string("why it was not fitted (partial arc, not separable, no screw pitch, ...)"),
        "significance_reason": string("why a parameter whose F-test passed is not significant (may be empty)"),
    },
    required=["value", "stderr", "unit", "p_value", "share_pct", "significant", "identifiable"],
)


def _parameters() -> Schema:
    props = {k: {"$ref": "#/$defs/parameter", "description": f"{desc}; {unit}"}
             for k, (unit, desc) in PARAMETERS.items()}
    return obj("every field of the pattern library, fitted or not, keyed by name (unit in the name)", props)


_RANKING = {
    "type": "array",
    "description": "the fitted patterns by extra sum of squares, largest first",
    "items": obj(
        "one pattern's test",
        {
            "pattern": string("the pattern's name (backlash_x, servo_mismatch, reversal_spike_x_pos_ccw, ...)"),
            "share_pct": num("its share of the explained sum of squares, %", True),
            "F": num("its F statistic (null: infinite)", True),
            "p_value": num("its p-value, 0..1", True),
            "significant": boolean("passes the significance rule"),
            "effect_um": num("its largest radial effect, um", True),
            "significance_reason": string("why it is not significant although its F-test passed"),
        },
        required=["pattern", "share_pct", "F", "p_value", "significant"],
    ),
}

_ADVICE = {
    "type": "array",
    "description": "suggested adjustments for the significant patterns, largest effect first",
    "items": obj(
        "one suggestion",
        {
            "pattern": string("the parameter it comes from (e.g. backlash_x_um)"),
            "kind": string("what is to be done: machine (a compensation or repair), setup, ..."),
            "action": string("the suggestion in words"),
            "value": num("the amount, in unit", True),
            "unit": string("the amount's unit"),
            "controller_parameter": string("the controller's parameter for it (machine.controller)"),
        },
        required=["pattern", "kind", "action", "value", "unit"],
    ),
}

_PLAN = obj(
    "the test plan the analysis assumed (daemon [plan], analysis/README.md)",
    {
        "plane": string("XY, YZ or ZX", enum=["XY", "YZ", "ZX"]),
        "radius_mm": num("R, the bar's nominal length, mm"),
        "feed_mm_min": num("F, the programmed feed, mm/min"),
        "start_deg": num("where the first arc starts, deg"),
        "overshoot_deg": num("swept before and after the data arc, deg"),
        "data_arc_deg": num("the analysed arc, deg"),
        "feed_in_mm": num("the radial feed-in and feed-out, mm"),
        "dwell_s": num("each dwell, s"),
        "directions": string("both, ccw or cw", enum=["both", "ccw", "cw"]),
        "sample_hz": num("the expected sample rate, Hz"),
    },
)
_PLAN_FIELDS = dict(_PLAN["properties"])

#: A result's plan: the keys of its plan, its name in the library and its machine axes (analysis/plans.py).
_RESULT_PLAN = obj(
    "the test plan the analysis assumed: one of the library's (daemon [plan] or [plans.<name>], analysis/README.md)",
    {**_PLAN_FIELDS,
     "name": string("the plan's name in the library (default: a single [plan])"),
     "axes": {"type": "array", "items": {"enum": ["X", "Y", "Z"]}, "minItems": 2, "maxItems": 2,
              "description": "the machine axes of the plane's first and second axis: every _x field is about the "
                             "first, every _y field about the second"}},
    required=list(_PLAN_FIELDS),  # name and axes: in every result since plans became a library (not in older logs)
)

_RECOGNITION = obj(
    "how the test's plan was known (analysis/plans.py)",
    {"method": string("only: a library of one; signature: the code before its feed-in (checked against its "
                      "timing); timing: the only plan whose timing fits; chosen: named by an operator or service",
                      enum=["only", "signature", "timing", "chosen"]),
     "signature": integer("the signature's code read before the feed-in (null: none read)", nullable=True),
     "feed_ratio": num("the feed-in to feed-out span's feed over the plan's (a feed override), at no per-move "
                       "overhead (null: not computed)", True),
     "candidates": {"type": "array", "items": {"type": "string"},
                    "description": "the plans whose timing fits the test at a feed override of 80..120 %"},
     "message": string("in words")},
    required=["method", "signature", "feed_ratio", "candidates", "message"],
)

_MACHINE = obj(
    "what the analysis knows of the machine ([machine])",
    {
        "pitch_x_mm": num("first axis' screw pitch, mm (null: unknown, no cyclic error fitted)", True),
        "pitch_y_mm": num("second axis' screw pitch, mm (null: unknown)", True),
        "kv_x_per_s": num("first axis' configured position-loop gain, 1/s (null: unknown)", True),
        "kv_y_per_s": num("second axis' configured position-loop gain, 1/s (null: unknown)", True),
        "controller": string("generic, fanuc, siemens or heidenhain: parameter names in the advice"),
    },
)

_AXES = {"x": num("first axis, deg"), "y": num("second axis, deg")}
_LOST_AXIS = obj(
    "one axis' lost-motion model",
    {
        "model": string("deadband, compensation or step", enum=["deadband", "compensation", "step"]),
        "onset_deg": num("where friction starts after the reversal point, deg"),
        "reversal_deg": num("where the table reverses, deg past the commanded reversal"),
        "description": string("the model in words"),
    },
)


def _fit(test: bool) -> Schema:
    props: dict[str, Schema] = {
        "n_samples": integer("samples fitted"),
        "n_parameters": integer("parameters fitted"),
        "dof": integer("degrees of freedom of the residual"),
        "sigma_um": num("residual standard deviation, um", True),
        "residual_lag1_autocorrelation": num("rho, the residual's lag-1 autocorrelation", True),
        "variance_inflation": num("(1+rho)/(1-rho), applied to the covariance", True),
        "condition_number": num("of the scaled design matrix (null: infinite)", True),
        "significance": num("the F-test level"),
        "min_effect_um": num("the minimum radial effect of a significant pattern, um"),
        "significance_rule": string("the whole significance rule in words"),
        "servo_model": string("linear or physical", enum=["linear", "physical"]),
        "uncertainty_method": string("how the standard errors were computed, in words"),
    }
    required = list(props)
    if test:
        props |= {
            "servo_model_note": string("where the loop lag came from", True),
            "lost_motion": obj(
                "the lost-motion model per axis",
                {"x": _LOST_AXIS, "y": _LOST_AXIS,
                 "loop_deg": obj("the loops' lag as angles, deg",
                                 {"lead": num("the lead, deg"), "x": num("first axis, deg"),
                                  "y": num("second axis, deg")})},
                required=["x", "y"],
            ),
            "lost_motion_model": string("lost_motion in words"),
            "evaluations": integer("misfit evaluations the fit made (the objective at a value of its nonlinear "
                                   "parameters)"),
            "designs": integer("designs the fit made: its misfit evaluations and their slopes"),
            "valid": boolean("false: the model does not describe this test (invalid_reasons say why); no "
                             "parameter is then significant"),
            "invalid_reasons": {"type": "array", "items": {"type": "string"},
                                "description": "why the model does not describe the test, in words"},
            "checks": obj(
                "the checks that the model describes the test (analysis/README.md, 'When the model does not fit')",
                {
                    "sensor_noise_um": num("the sensor's white noise from the samples alone, um", True),
                    "residual_rms_um": num("the fit's residual, um", True),
                    "last_arc_feed_ratio": num("the last arc's feed against the first's, as the residual tells it "
                                               "(null: one direction)", True),
                    "last_arc_feed_z": num("its difference from 1 in standard errors (null: one direction)", True),
                    "level_change": {
                        "type": "array",
                        "description": "per data arc, the residual's largest step away from the reversals",
                        "items": obj("one data arc's largest level change", {
                            "direction": string("ccw or cw", enum=["ccw", "cw"]),
                            "at_deg": num("where, deg", True),
                            "step_um": num("its size, um"),
                            "z": num("in standard errors of the two windows' difference"),
                        }),
                    },
                },
            ),
        }
        required += ["lost_motion", "lost_motion_model", "valid"]
    return obj("the fit's diagnostics", props, required)


def _arc() -> Schema:
    return obj(
        "one data arc on the time axis",
        {"start_s": num("start, s"), "end_s": num("end, s"),
         "shift_s": num("how much later it ran than equal per-move overheads put it, s")},
    )


_POLLED = {  # analysis.polled: a gauge polled by the host, stamped at the middle of each request/answer window
    "time_source": string("present for a polled gauge: what the time stamps are, in words"),
    "t_uncertainty_ms": num("polled gauge: the stamps' uncertainty (half the p99 request/answer window), ms"),
    "t_jitter_ms": num("polled gauge: the stamps' jitter (half the p1..p99 window spread), ms"),
    "t_jitter_deg": num("polled gauge: that jitter as an angle at the measured feed, deg (null: no feed)", True),
}

_TIMING_TEST = obj(
    "the test's timing: feed, arc-start lag, spike width, feed-in and feed-out, data arcs, position loops",
    {
        "provisional": {"const": False, "description": "false: the test's own timing"},
        "programmed_feed_mm_min": num("F, mm/min"),
        "measured_feed_mm_min": num("from the feed-in to feed-out span, mm/min", True),
        "feed_ratio": num("measured / programmed feed", True),
        "overhead_s": num("per-move overhead (the arc start's lag), s", True),
        "lag_s": num("the arc start's lag, s", True),
        "lag_deg": num("the same as an angle, deg", True),
        "lag_stderr_s": num("its standard error, s (null: not estimated)", True),
        "spike_width_deg": num("the reversal spikes' decay width, deg", True),
        "spike_width_stderr_deg": num("its standard error, deg (null: not estimated)", True),
        "feed_in_s": num("the feed-in's centroid on the time axis, s"),
        "feed_out_s": num("the feed-out's centroid, s"),
        "feed_in_method": string("how the feed-in was timed (centroid, ...)"),
        "feed_out_method": string("how the feed-out was timed"),
        "feed_in_height_mm": num("the feed-in step's height, mm"),
        "feed_out_height_mm": num("the feed-out step's height, mm"),
        "data_arcs": obj("the data arcs by direction", {"ccw": _arc(), "cw": _arc()}, required=[]),
        "method": string("how the timing was found, in words"),
        "loop_lag_ms": num("the position loop's mean lag, ms (null: no physical servo model)", True),
        "loop_lag_source": string("where the loop lag came from, in words", True),
        "loop_lag_origin": string("configured, feed_in, fitted, assumed, none or linear"),
        "loop_lag_radial_cos2u": num("the loops' radial cos 2u term, um (null: none)", True),
        "loop_lag_stderr_ms": num("where the loop lag was searched with the timing (nothing else told it): its "
                                  "standard error, ms", True),
        "loop_feed_forward": num("where an over-set backlash compensation's steps place it: the share of a command "
                                 "step the loops pass at once (velocity feed-forward), 0..0.98; their lag on the "
                                 "circle is (1 - this) times the settling's (null: not searched)", True),
        "loop_feed_forward_stderr": num("its standard error (null: not searched)", True),
        "backlash_takeup_deg": obj("the travel over which each axis' dead band is taken up after the axis "
                                   "reverses, deg", _AXES),
        "reversal_onset_deg": obj("where friction starts after each reversal point, deg", _AXES),
        **_POLLED,
    },
    required=["provisional", "programmed_feed_mm_min", "measured_feed_mm_min", "feed_in_s", "feed_out_s",
              "data_arcs", "loop_lag_ms", "loop_lag_origin"],
)

_TIMING_CIRCLE = obj(
    "a circle's provisional timing (assumed from the plan or the last good test)",
    {
        "provisional": {"const": True, "description": "true: assumed timing, the test's result will refine it"},
        "feed_in_s": num("the feed-in's centroid on the time axis, s"),
        "assumed_feed_mm_min": num("the feed assumed, mm/min"),
        "assumed_overhead_s": num("the arc start's lag assumed, s"),
        "data_start_s": num("the data arc's start, s"),
        "data_end_s": num("the data arc's end, s"),
        "spike_width_deg": num("the spike width assumed, deg"),
        **_POLLED,
    },
    required=["provisional", "feed_in_s", "assumed_feed_mm_min", "assumed_overhead_s", "data_start_s", "data_end_s",
              "spike_width_deg"],
)

_ISO = obj(
    "ISO 230-4 figures and their conditions (null: the direction was not run)",
    {
        "G_ccw_um": num("circular deviation G, CCW, um", True),
        "G_cw_um": num("circular deviation G, CW, um", True),
        "G_b_um": num("bidirectional circular deviation G(b), um", True),
        "H_um": num("circular hysteresis H, um", True),
        "F_max_um": num("largest radial deviation F from the nominal radius, um", True),
        "F_min_um": num("smallest radial deviation F, um", True),
        "conditions": obj(
            "the test conditions ISO 230-4 asks to state",
            {
                "plane": string("XY, YZ or ZX"),
                "radius_mm": num("mm"),
                "feed_mm_min": num("programmed, mm/min"),
                "measured_feed_mm_min": num("measured, mm/min", True),
                "data_arc_deg": num("deg"),
                "start_deg": num("deg"),
                "directions": string("both, ccw or cw"),
                "sample_hz": num("Hz", True),
                "centre_removal": string("how the centre was removed, in words"),
                "standard": string("the edition, ISO 230-4:2022"),
            },
        ),
    },
)

def _standard(title: str, figures: dict[str, Schema]) -> Schema:
    return obj(f"{title}'s circular-test figures (analysis/standards.py)", {
        "standard": string("the standard and its edition"),
        **figures,
        "centre_removal": string("how the centre was removed, in words"),
        "computes": string("what the figures are, in words"),
        "differs_from_iso230_4": string("where they differ from ISO 230-4's (iso230_4), in words"),
        "assumption": string("what was assumed of the standard's text (empty: nothing)"),
    })


_STANDARDS = obj(
    "the other standards chosen ([analysis] standards), each under its id; ISO 230-4's are iso230_4",
    {
        "jis_b6190_4": _standard("JIS B 6190-4:2008 (ISO 230-4:2005)", {
            "G_ccw_um": num("circular deviation G, CCW, um", True),
            "G_cw_um": num("circular deviation G, CW, um", True),
            "G_b_um": num("bidirectional circular deviation G(b), um", True),
            "F_max_um": num("largest radial deviation F, um", True),
            "F_min_um": num("smallest radial deviation F, um", True)}),
        "asme_b5_54": _standard("ASME B5.54-2005", {
            "circular_deviation_ccw_um": num("circular deviation about the minimum-zone centre, CCW, um", True),
            "circular_deviation_cw_um": num("the same, CW, um", True),
            "circular_deviation_b_um": num("both directions about one minimum-zone centre, um", True),
            "H_um": num("circular hysteresis, um", True),
            "F_max_um": num("largest radial deviation, um", True),
            "F_min_um": num("smallest radial deviation, um", True)}),
    },
    required=[],
)

_NOISE = obj(
    "vibration and stick-slip",
    {
        "vibration_um": num("the residual's RMS above vibration_cutoff_cpr (sensor noise included), um", True),
        "vibration_cutoff_cpr": num("cycles per revolution"),
        "vibration_peak_um": num("the strongest spectral line's amplitude, um", True),
        "vibration_peak_hz": num("its frequency, Hz", True),
        "vibration_peak_cpr": num("its frequency, cycles per revolution", True),
        "vibration_significant": boolean("the line stands out of the noise floor"),
        "stick_slip_x_um": num("stick-slip of the first axis, um", True),
        "stick_slip_x_p_value": num("the F-test of the variance near the reversals against elsewhere", True),
        "stick_slip_x_significant": boolean("significant"),
        "stick_slip_y_um": num("stick-slip of the second axis, um", True),
        "stick_slip_y_p_value": num("the same for the second axis", True),
        "stick_slip_y_significant": boolean("significant"),
        "method": string("how, in words"),
    },
    required=["vibration_um", "vibration_significant", "method"],
)

_SAMPLES = obj(
    "samples the test used",
    {"in_test": integer("valid samples from the feed-in to the feed-out"),
     "in_data_arcs": integer("of those, in the data arcs"),
     "sample_hz": num("the rate measured from the timestamps, Hz", True)},
)

_WARNINGS = {"type": "array", "items": {"type": "string"},
             "description": "what makes the result less trustworthy: a sample rate other than the plan's, an "
                            "overshoot too short to reach the feed (timing model), ..."}


def _analysis_props(kind: str) -> dict[str, Schema]:
    props: dict[str, Schema] = {
        "schema_version": {"const": SCHEMA_VERSION, "description": "version of these payloads' shapes"},
        "kind": {"const": kind, "description": "circle: one direction's fit, provisional; test: the whole test"},
        "test_index": integer("the test's number in this stream (daemon run or file), from 1"),
        "plan": _RESULT_PLAN,
        "recognition": _RECOGNITION,
        "machine": _MACHINE,
        "parameters": {"$ref": "#/$defs/parameters"},
        "ranking": _RANKING,
        "advice": _ADVICE,
        "fit": _fit(kind == "test"),
        "timing": _TIMING_TEST if kind == "test" else _TIMING_CIRCLE,
        "residual_rms_um": num("the fit's residual RMS, um", True),
        "warnings": _WARNINGS,
    }
    if kind == "test":
        props |= {"iso230_4": _ISO, "standards": _STANDARDS, "noise": _NOISE, "samples": _SAMPLES,
                  "verdict": {"$ref": "#/$defs/verdict",
                              "description": "with [limits] on: pass, warning or fail against each limit"}}
    else:
        props["direction"] = string("ccw or cw", enum=["ccw", "cw"])
    return props


_REQUIRED_ANALYSIS = ["schema_version", "kind", "test_index", "plan", "machine", "parameters", "ranking", "advice",
                      "fit", "timing", "residual_rms_um"]


def _daemon_result(kind: str) -> Schema:
    props = _analysis_props(kind) | {
        k: v for k, v in _envelope(kind).items() if k != "kind" and k != "schema_version"
    } | _LAST_SAMPLE
    required = [*_REQUIRED_ANALYSIS, "machine_id", "t_wall", *_LAST_SAMPLE]
    if kind == "test":
        required += ["iso230_4", "noise", "samples"]
    else:
        required.append("direction")
    return obj(f"a {kind} result as the daemon publishes it", props, required)


def _monitor_source() -> Schema:
    """``daemon/schemas/alert.json``: the monitor's shapes (alert, verdict, forecast), written beside its code."""
    doc: Schema = json.loads((Path(__file__).parent / "schemas" / "alert.json").read_text(encoding="utf-8"))
    return doc


def _monitor_defs() -> dict[str, Schema]:
    """The verdict a test result carries with ``[limits]`` on, and what it refers to."""
    return dict(_monitor_source()["$defs"])


def alert_schema() -> Schema:
    src = _monitor_source()
    body = {k: v for k, v in src.items() if k not in ("$schema", "$id", "title", "description", "$defs")}
    body["properties"] = dict(body["properties"]) | {
        "schema_version": {"const": SCHEMA_VERSION, "description": "version of these payloads' shapes"}}
    return _document("alert", src["description"], body, _monitor_defs())


def result_schema() -> Schema:
    return _document(
        "result",
        "ballbar.Result: an analysis result, a circle's (kind circle, provisional timing, after each data arc) or "
        "a test's (kind test): the `ballbar analyze --json` object plus the daemon's machine_id, test_id, t_wall, "
        "t_host, last_sample_t, last_sample_t_host, latency_ms and time_axis; or a set's (kind set, the set "
        "schema).",
        {"oneOf": [{"$ref": "#/$defs/circle"}, {"$ref": "#/$defs/test"}, {"$ref": "#/$defs/set"}]},
        {"circle": _daemon_result("circle"), "test": _daemon_result("test"), "set": _set_object(),
         "parameter": _PARAMETER, "parameters": _parameters(), **_monitor_defs(), **_set_defs()},
    )


def analysis_schema() -> Schema:
    source = obj(
        "what was analysed",
        {
            "file": string("absolute path of the file (records: the test's first file)"),
            "tests_found": integer("tests found in the file"),
            "files": {"type": "array", "items": {"type": "string"}, "description": "the test's files (records)"},
            "test_id": string("the test's id (records)", True),
            "machine_id": string("the daemon's machine_id (records)", True),
            "time_axis": string("device or host (records)"),
            "tests_recorded": integer("tests in the records"),
        },
        required=["file"],
    )
    props = _analysis_props("test") | {"source": source}
    return _document(
        "analysis",
        "`ballbar analyze --json`: one test's result (the daemon's result/test payload has the same fields "
        "without source, plus its own).",
        obj("a test's result", props, [*_REQUIRED_ANALYSIS, "iso230_4", "noise", "samples", "source"]),
        {"parameter": _PARAMETER, "parameters": _parameters(), **_monitor_defs()},
    )


# --------------------------------------------------------------------------- events

_SOURCE = string("the source's URL (e.g. serial:/dev/ttyUSB0?protocol=binary&rate=1000)")

#: Each event: (what it says, its own fields, which of them are required).
SOURCE_EVENTS: dict[str, tuple[str, dict[str, Schema], list[str]]] = {
    "opened": ("the port, simulator or recording is open", {"detail": string("what was opened")}, []),
    "unplugged": ("the port failed mid-read; the source closes it and retries with backoff",
                  {"detail": string("the error")}, []),
    "replugged": ("the port is open again (the samples lost across the outage follow as a lost event)",
                  {"gap_s": num("the outage, s"), "detail": string("the port")}, []),
    "lost": ("samples never received",
             {"count": integer("how many", minimum=1), "seq": integer("the first one's sample number"),
              "detail": string("gap, outage, stall, poll_timeout or poll_late")}, ["count"]),
    "decode_errors": ("decoder drops since the last report",
                      {"counts": counts("by reason (bad_crc, bad_line, skipped_bytes, ...): how many")}, ["counts"]),
    "stall": ("no bytes while connected", {"gap_s": num("the silence so far, s")}, []),
    "resumed": ("bytes again after a stall", {"gap_s": num("the silence, s")}, []),
    "device_reset": ("the device restarted (its sample counter or clock ran back): a break in the time axis",
                     {"seq": integer("the first sample after the restart"), "detail": string("what was seen")}, []),
    "clock_jump": ("the device clock stepped beyond its sample counter: a break in the time axis",
                   {"seq": integer("the first sample after the step"), "gap_s": num("the step, s"),
                    "detail": string("what was seen")}, []),
    "end": ("a finite source (replay, sim: with a repeat count) has ended", {"detail": string("why")}, []),
    "timing": ("a polled gauge's stamps (no device clock): sent when first known and whenever their uncertainty "
               "grows by a quarter; the MCAP log repeats the last at the head of each file",
               {"detail": string("what the stamps are, in words"),
                "t_uncertainty_s": num("half the p99 request/answer window, s"),
                "t_jitter_s": num("half the windows' p1..p99 spread, s"),
                "window_median_s": num("the windows' median, s"),
                "window_p99_s": num("their 99th percentile, s"),
                "achieved_hz": num("answers per second, Hz")},
               ["t_uncertainty_s", "t_jitter_s"]),
}

_TEST_FIELDS: dict[str, Schema] = {
    "test_index": integer("the test's number in this daemon run, from 1"),
    "t_s": num("where on the time axis, s", True),
}

PIPELINE_EVENTS: dict[str, tuple[str, dict[str, Schema], list[str]]] = {
    "feed_in": ("a test began: the feed-in step was recognised",
                {**_TEST_FIELDS, "height_mm": num("the step's height, mm"),
                 "method": string("how it was timed (centroid, ...)"),
                 "plan": string("a library of several plans: the plan the feed-in tells (its program's signature, "
                                "a choice); null: the timing decides at the feed-out", True)},
                ["test_index", "t_s"]),
    "feed_out": ("the test's feed-out step; the test result follows",
                 {**_TEST_FIELDS, "height_mm": num("the step's height, mm"),
                  "method": string("how it was timed")}, ["test_index", "t_s"]),
    "test_rejected": ("the test gives no result: a break in its time axis or an analysis failure",
                      {**_TEST_FIELDS, "message": string("the reason, where and when"),
                       "gap_s": num("the time missing from the axis, s, where it shows", True)},
                      ["test_index", "message"]),
    "test_incomplete": ("the test never finished: the stream ended, or the daemon was killed during it "
                        "(origin recovery, published at the next start)",
                        {**_TEST_FIELDS, "message": string("what happened"),
                         "file": string("origin recovery: the recording that holds its samples")}, ["message"]),
    "analysis_reset": ("the analysis could not take the time axis and started afresh (the test in progress is "
                       "rejected)", {"message": string("why")}, ["message"]),
    "test_unrecognised": ("the test matches no plan of the library, or more than one: it is not analysed as any "
                          "of them (analysis/plans.py)",
                          {**_TEST_FIELDS,
                           "reason": string("no_match or ambiguous", enum=["no_match", "ambiguous"]),
                           "candidates": {"type": "array", "items": {"type": "string"},
                                          "description": "the plans whose timing fits the test"},
                           "signature": integer("the signature's code read before the feed-in (null: none)",
                                                nullable=True),
                           "message": string("why, with the candidates")},
                          ["test_index", "reason", "candidates", "message"]),
    "plan_chosen": ("an explicit choice of the next test's plan was taken (ballbar/<m>/control/next_plan)",
                    {"plan": string("the plan's name (null: the choice was withdrawn)", True),
                     "message": string("in words")}, ["plan", "message"]),
    "plan_choice_refused": ("a choice of the next plan named no plan of the library, or was not understood",
                            {"message": string("why")}, ["message"]),
}

LOGGER_EVENTS: dict[str, tuple[str, dict[str, Schema], list[str]]] = {
    "log_gap": ("MCAP only: samples the logger could not write (a write error, a full disk)",
                {"count": integer("samples not logged"), "gap_s": num("over this long, s"),
                 "detail": string("the error")}, ["count"]),
}


def _event_branch(name: str, what: str, fields: dict[str, Schema], required: list[str], origin: str,
                  mcap: bool) -> Schema:
    env = _envelope("event")
    props: dict[str, Schema] = {
        **env,
        "event": {"const": name, "description": what},
        "origin": {"const": origin, "description": "source: the device or port; recovery: found at start"}
        if origin == "source" else {"enum": ["recovery"], "description": "recovery: found at start"},
        "t_host": _T_HOST,
    }
    if origin == "source":
        props["source"] = _SOURCE
    else:
        props |= {k: v for k, v in _LAST_SAMPLE.items()}
    props |= fields
    req = ["event", *required]
    if not mcap:
        req += ["schema_version", "kind", "machine_id", "t_wall", "t_host"]
        if origin == "source":
            req += ["origin", "source"]
    else:
        props.pop("kind")
        req.append("t_host")
    return obj(f"event {name}: {what}", props, req)


def event_schema(mcap: bool = False) -> Schema:
    branches: dict[str, Schema] = {}
    for name, (what, fields, req) in SOURCE_EVENTS.items():
        branches[name] = _event_branch(name, what, fields, req, "source", mcap)
    for name, (what, fields, req) in PIPELINE_EVENTS.items():
        branches[name] = _event_branch(name, what, fields, req, "pipeline", mcap)
    if mcap:
        for name, (what, fields, req) in LOGGER_EVENTS.items():
            b = _event_branch(name, what, fields, req, "pipeline", mcap)
            for k in ("origin", "test_id", "last_sample_t", "last_sample_t_host", "latency_ms", "time_axis",
                      "schema_version", "machine_id", "t_wall"):
                b["properties"].pop(k, None)
            branches[name] = b
    title = "mcap-event" if mcap else "event"
    desc = (
        "ballbar.Event as the MCAP log stores it: the event payload without kind; a source's events as the source "
        "reported them (event, t_host, source and the event's own fields), the pipeline's as published"
        if mcap else
        "An event on ballbar/<m>/event: a source's (origin source: the device or its port), the analysis' (test "
        "events, with the test's test_id), or one found at start (origin recovery). One branch per event name."
    )
    return _document(title, desc, {
        "type": "object",
        "required": ["event"],
        "oneOf": [{"$ref": f"#/$defs/{n}"} for n in branches],
    }, branches)


# --------------------------------------------------------------------------- status

_QUEUE = obj(
    "one output's queue",
    {"depth": integer("items waiting now"), "capacity": integer("its bound, items"),
     "delivered": integer("items handed to the output"), "dropped": integer("items dropped by the policy"),
     "errors": integer("items the output raised on"),
     "policy": string("drop_newest or drop_oldest", enum=["drop_newest", "drop_oldest"])},
)

_MCAP_STATS = obj(
    "the MCAP logger",
    {
        "state": string("writing, failing (a write error; retrying) or stopped"),
        "file": string("the file being written (empty: none)", True),
        "files": integer("files opened in this run"),
        "bytes": integer("bytes written in this run"),
        "samples": integer("samples written"),
        "messages": integer("results, events, status and config records written"),
        "pending_samples": integer("samples waiting for the next chunk"),
        "samples_lost": integer("samples that could not be logged (write errors)"),
        "messages_lost": integer("records that could not be logged"),
        "messages_held": integer("results and events held in memory during a write outage"),
        "messages_held_written": integer("of those, written after it"),
        "held_messages": integer("held now"),
        "write_errors": integer("write errors"),
        "encode_errors": integer("records that could not be encoded"),
        "deleted_files": integer("files deleted by retention"),
        "deleted_bytes": integer("bytes deleted by retention"),
        "last_error": string("the last write error (empty: none)"),
    },
    required=["state", "files", "samples", "samples_lost"],
)

_ZENOH_STATS = obj(
    "the Zenoh bus",
    {
        "connected": boolean("the session is open (not whether anyone listens)"),
        "open_error": string("why it could not open (retrying in the background)", True),
        "published": counts("puts by topic (result/circle, result/test, result/set, event, status, config, samples, "
                            "alert)"),
        "put_errors": integer("puts that failed"),
        "not_connected": integer("messages kept for last/history while the session was not open"),
        "slow_puts": integer("puts that took longer than 0.1 s (a subscriber not reading)"),
        "max_put_ms": num("the longest put, ms"),
        "queries": integer("last/history queries answered"),
        "query_errors": integer("replies that failed"),
        "skipped": integer("messages of a kind with no topic"),
        "controls": integer("choices of the next plan received on control/next_plan"),
        "history": counts("results and events held for history/<topic>, by topic"),
        "zid": string("this session's Zenoh id"),
        "links": counts("sessions connected to this one, by kind (peer, client, router)"),
    },
    required=["connected", "published", "put_errors", "history"],
)


def _rerun_stats() -> Schema:
    c = "a counter of what the viewer did"
    server = obj(
        "serve mode: the supervised `rerun --serve-grpc` child",
        {"pid": integer("its process id (null: not running)", True), "listening": boolean("it accepts viewers"),
         "rss_mb": num("its resident memory, MiB"), "max_rss_mb": num("the most seen, MiB"),
         "rss_cap_mb": num("restarted above this, MiB"), "restarts": integer("restarts"),
         "rss_kills": integer("restarts for memory"),
         "stall_kills": integer("restarts because it took none of the daemon's stream"),
         "clients_ended": integer("connections to it (viewers, clients pushing) that ended: each has the "
                                  "history sent again")},
    )
    one_of = [
        obj("the viewer, not (yet) started", {"state": string("starting or failed", enum=["starting", "failed"])}),
        obj(
            "the Rerun viewer",
            {
                "mode": string("serve or connect", enum=["serve", "connect"]),
                "address": string("where viewers connect (serve) or where it pushes (connect)", True),
                "connected": boolean("a sink is live"),
                "clock": string("the clock of its timeline: device or host", enum=["device", "host"]),
                "buffered_samples": integer("samples held for the live circles"),
                "pending_samples": integer("samples not yet processed"),
                "history_tests": integer("tests held for late viewers"),
                "history_length_points": integer("bar-length points held (1 per second)"),
                "trend_points": integer("trend points held"),
                "sent_mib": num("estimate of what the sink was sent, MiB"),
                "history_pending": integer("history steps still to send"),
                **{k: integer(c) for k in ("batches", "samples", "messages", "flushes", "length_sends",
                                           "polar_draws", "sinks", "refreshes", "errors", "skipped")},
                "server_stalls": integer("serve mode: restarts asked of the server, which took none of the stream"),
                "server": server,
            },
            required=["mode", "connected"],
        ),
    ]
    return {"description": "the Rerun viewer's counters", "oneOf": one_of}


def status_schema() -> Schema:
    source = obj(
        "the source's running totals",
        {
            "samples": integer("samples received"),
            "lost": integer("samples reported lost, whatever the cause"),
            "batches": integer("batches read"),
            "bytes_read": integer("bytes read from the port"),
            "reads": integer("port reads that returned bytes"),
            "unplugs": integer("times the port failed"),
            "replugs": integer("times it came back"),
            "stalls": integer("stalls"),
            "resets": integer("device resets"),
            "clock_jumps": integer("device clock jumps"),
            "connected": boolean("the port is open"),
            "decode": counts("decoder drops by reason"),
            "lost_by_cause": counts("lost samples by cause (gap, outage, stall, ...)"),
            "clock_ratio": num("host seconds per device second, in device terms (divided by status.speedup, so "
                               "1 for a healthy clock); null: no device clock yet", True),
            "clock_offset_s": num("t_host = clock_offset_s + clock_ratio * t_device / speedup, s", True),
            "drift_ppm": num("the device clock's drift against the host's, ppm, in device terms (null: unknown)",
                             True),
            "poll": obj(
                "a polled gauge's request/answer windows (the last few thousand; empty: not polled or no answer yet)",
                {
                    "window_median_ms": num("the windows' median, ms"),
                    "window_p99_ms": num("their 99th percentile, ms"),
                    "window_max_ms": num("the longest, ms"),
                    "t_uncertainty_ms": num("half the p99 window: how far a stamp may be from its reading, ms"),
                    "t_jitter_ms": num("half the windows' p1..p99 spread, ms"),
                    "achieved_hz": num("answers per second over about the last 10 s, Hz"),
                    "answers": num("how many answers the figures cover"),
                },
                required=[],
            ),
        },
        required=["samples", "lost", "connected", "clock_ratio", "drift_ppm"],
    )
    outputs = obj(
        "each output's own counters",
        {"mcap": _MCAP_STATS, "zenoh": _ZENOH_STATS, "rerun": _rerun_stats(),
         "sets": obj("the test sets' (absent: no [sets])", {
             "tests": integer("test results of a set's plan taken in"),
             "sets": integer("set results sent"),
             "errors": integer("sets not combined, or their state not written (the log says why)")})},
        required=[],
    )
    props = _envelope("status") | {
        "uptime_s": num("since the daemon started, s"),
        "speedup": num("device time per host time: 1 for a real device; the simulated device's speed-up under "
                       "`ballbar run --simulate --speedup`. Rates and clock figures here are in device terms.",
                       exclusiveMinimum=0),
        "source_state": string("starting, waiting (never opened yet), connected, stalled, unplugged or ended",
                               enum=["starting", "waiting", "connected", "stalled", "unplugged", "ended"]),
        "source_reason": string("why the source is waiting or unplugged", True),
        "source": source,
        "samples": integer("samples read in this run"),
        "sample_rate_hz": num("samples per second of device time since the last status, Hz"),
        "lost_samples": integer("samples reported lost in this run"),
        "queues": {"type": "object", "description": "each output's queue, by name (analysis, mcap, zenoh, rerun, log)",
                   "additionalProperties": _QUEUE},
        "outputs": outputs,
        "analysis": obj(
            "the analysis",
            {"results": integer("circle and test results"), "tests": integer("test results"),
             "fit_latency_ms": num("how long the last result's fit took, ms (null: none yet)", True),
             "invalid_samples": integer("samples flagged over range or sensor fault (left out)"),
             "errors": integer("times the analysis started afresh"),
             "test_id": string("the current or last test's id (null: none yet)", True),
             "worker": obj("the child process that fits each test (absent: daemon.analysis_worker is off)", {
                 "pid": integer("its process id (null: starting)", True),
                 "started": integer("processes started: 1, one more each time one died"),
                 "busy": boolean("a test's fit is running in it")})},
            required=["results", "tests", "fit_latency_ms", "invalid_samples", "errors", "test_id"],
        ),
    }
    return _document("status", "ballbar.Status: the daemon's periodic status (ballbar/<m>/status, every "
                     "daemon.status_interval_s).", obj("the status", props))


# --------------------------------------------------------------------------- config


def config_schema() -> Schema:
    from ballbar.analysis.plan import AnalysisOptions

    analysis_opts = {
        "significance": num("F-test level"),
        "servo_model": string("auto, linear or physical"),
        "lost_motion": string("physical or step"),
        "min_effect_um": num("minimum radial effect of a significant pattern, um"),
        "vif_limit": num("variance inflation above which a parameter is not identifiable"),
        "vibration_cutoff_cpr": num("cycles per revolution"),
        "spike_width_min_deg": num("deg"),
        "spike_width_max_deg": num("deg"),
        "estimate_lag": boolean("estimate the arc start's lag"),
        "max_lag_s": num("its search range, +- s"),
        "patterns": {"type": ["array", "null"], "items": {"type": "string"},
                     "description": "the patterns fitted (null: all)"},
        "standards": {"type": "array", "items": {"type": "string", "enum": ["iso230_4", "jis_b6190_4", "asme_b5_54"]},
                      "description": "the circular-test standards whose figures a test result carries (absent "
                                     "before it existed)"},
    }
    assert set(analysis_opts) >= set(AnalysisOptions.__dataclass_fields__)  # kept in step with the dataclass
    config = obj(
        "the effective configuration: daemon/default.toml's sections and keys (see there), secrets '<redacted>'",
        {
            "daemon": obj("[daemon]", {
                "machine_id": string("the key chunk <m>"), "state_dir": string("recordings, history"),
                "status_interval_s": num("s"), "log_level": string("debug, info, warning or error"),
                "analysis_worker": boolean("each test's fit in a child process")}),
            "source": obj("[source]", {
                "url": string("the source actually read: with --simulate, the simulated device's pty"),
                "cal_mm": num("the bar's length at zero displacement, mm (null: the plan's radius)", True)}),
            "plan": _PLAN,
            "plans": {"type": "object", "description": "[plans.<name>]: the library of plans, in order (absent: "
                      "[plan] alone, named default)", "additionalProperties": obj(
                          "one plan: [plan]'s keys, its program's signature and its own limits",
                          {**_PLAN_FIELDS,
                           "signature": integer("the code its program carries before the feed-in, 0..124 (null: "
                                                "none, a library of one)", nullable=True),
                           "limits": {"type": "object", "description": "its own [limits] (over the global one; "
                                      "absent: the global one)"}},
                          required=[*_PLAN_FIELDS, "signature"])},
            "sets": {"type": "object", "description": "[sets.<name>]: tests that together give one picture of the "
                     "machine (absent: none)", "additionalProperties": obj(
                         "one set", {"plans": {"type": "array", "items": {"type": "string"},
                                               "description": "the names of its plans"},
                                     "window_minutes": num("the time within which its tests must all have run, "
                                                           "min")})},
            "machine": _MACHINE,
            "analysis": obj("[analysis]", analysis_opts, required=[k for k in analysis_opts if k != "standards"]),
            "mcap": obj("[mcap]", {
                "enabled": boolean("log to MCAP"), "rotate_per_test": boolean("a new file at each feed-in"),
                "rotate_mb": num("MB"), "rotate_minutes": num("min"), "quota_mb": num("MB"),
                "keep_days": num("days"), "flush_s": num("s")}),
            "zenoh": obj("[zenoh]", {
                "enabled": boolean("publish on Zenoh"), "mode": string("peer, client, router or empty"),
                "listen": {"type": "array", "items": {"type": "string"}, "description": "endpoints"},
                "connect": {"type": "array", "items": {"type": "string"}, "description": "endpoints"},
                "config_file": string("a Zenoh JSON5 file (empty: none)"),
                "multicast_scouting": boolean("scouting by multicast"),
                "history_size": integer("results kept per history topic"),
                "close_timeout_s": num("s"),
                "options": {"type": "object", "description": "raw Zenoh keys (secrets '<redacted>')"},
                "samples_hz": num("decimated samples, Hz (0: off)")}),
            "rerun": obj("[rerun]", {
                "mode": string("serve, connect or off"), "bind": string("address"), "port": integer("TCP port"),
                "url": string("with mode connect"), "memory_limit_mb": num("MB"),
                "tolerance_um": num("um"), "magnification": num("0: automatic"),
                "history_tests": integer("the last tests a viewer that connects later is sent whole")}),
            "limits": obj("[limits]: acceptance limits, verdicts, trends and alerts (off by default)", {
                "enabled": boolean("limits, verdicts and alerts on"),
                "G_um": num("ISO 230-4 circular deviation G, each direction, um (null: no limit)", True),
                "G_b_um": num("bidirectional circular deviation G(b), um (null: no limit)", True),
                "H_um": num("circular hysteresis H, um (null: no limit)", True),
                "parameters": counts("result parameter name -> bound on its absolute value, in its unit", "number"),
                "warn_fraction": num("a warning from this fraction of a limit"),
                "warn_fractions": counts("per limit, its own warning fraction", "number"),
                "coverage_k": num("coverage factor of the uncertainty a limit must be exceeded beyond"),
                "trend_tests": integer("the trend over at most this many tests"),
                "trend_days": num("... or over this many days (0: by count)"),
                "min_tests": integer("no trend from fewer tests"),
                "horizon_days": num("a forecast crossing within this many days is due, days"),
                "confidence": num("the forecast interval's confidence"),
                "clear_after": integer("a due forecast clears after this many tests not due")}),
            "queues": obj("[queues]: bounds, items", {
                "analysis": integer("items"), "mcap": integer("items"), "zenoh": integer("items"),
                "rerun": integer("items")}),
            "report": obj("[report]: what ballbar report states beside the results (absent before it existed)", {
                "operator": string("who ran the test"), "bar_serial": string("the ball-bar's serial number"),
                "bar_calibrated": string("the bar's last calibration, a date"),
                "machine_temperature_c": num("deg C (null: not given)", True),
                "air_temperature_c": num("deg C (null: not given)", True), "notes": string("notes"),
                "sign_off": {"type": "array", "items": {"type": "string"},
                             "description": "a signature line per role"}}),
        },
        required=["daemon", "source", "plan", "machine", "analysis", "mcap", "zenoh", "rerun", "limits", "queues"],
    )
    props = _envelope("config") | {"config": config}
    return _document("config", "ballbar.Config: the daemon's effective configuration, at start (ballbar/<m>/config, "
                     "last/config) and at the head of every MCAP file; secrets redacted.", obj("the config", props))


# --------------------------------------------------------------------------- samples, history


def samples_schema() -> Schema:
    col = {"type": "array", "description": ""}
    props = _envelope("samples") | {
        "source": _SOURCE,
        "samples_hz": num("the decimation rate, Hz"),
        "t_host": {**col, "items": {"type": ["number", "null"]}, "description": "host monotonic time, s"},
        "t_device": {**col, "items": {"type": ["number", "null"]},
                     "description": "the device's sample clock, s (null: none)"},
        "length_mm": {**col, "items": {"type": ["number", "null"]},
                      "description": "absolute bar length, mm (null: no reading)"},
        "seq": {**col, "items": {"type": "integer"}, "description": "sample numbers"},
        "status": {**col, "items": {"type": "integer"},
                   "description": "status bits: 1 over range, 2 sensor fault, 128 simulated"},
    }
    return _document("samples", "Decimated samples on ballbar/<m>/samples (for display; the first sample of each "
                     "1/samples_hz slot).", obj("decimated samples", props))


def history_schema() -> Schema:
    props: dict[str, Schema] = {
        "schema_version": {"const": SCHEMA_VERSION, "description": "version of these payloads' shapes"},
        "kind": {"const": "history", "description": "a history reply"},
        "topic": string("circle, test, set, event or alert", enum=["circle", "test", "set", "event", "alert"]),
        "machine_id": string("the daemon's machine_id"),
        "count": integer("results in this reply"),
        "more": boolean("more after the last: ask again with since = its t_wall"),
        "results": {"type": "array", "items": {"type": "object"},
                    "description": "payloads as published (result or event schema), oldest first; results "
                                   "seeded from the recordings keep the schema_version they were logged with"},
    }
    return _document("history", "A reply of ballbar/<m>/history/<topic>.", obj("a history reply", props))


# --------------------------------------------------------------------------- the set result (analysis/sets.py)


def _figure_props(unit: str) -> dict[str, Schema]:
    return {
        "value": num(f"the figure, {unit} (null: none; reasons say why)", True),
        "stderr": num(f"its standard uncertainty, {unit} (null: none)", True),
        "unit": string("the unit"),
        "trusted": boolean("false where no value, a check behind it failed, or a test behind it is invalid"),
        "reasons": {"type": "array", "items": {"type": "string"},
                    "description": "why it is not trusted, or observations left out (may be empty)"},
    }


_OBSERVATION = obj(
    "one test's estimate of the quantity",
    {
        "plan": string("the test's plan"),
        "plane": string("its plane", enum=["XY", "YZ", "ZX"]),
        "test_id": string("the test's id", True),
        "field": string("the test's parameter it is (in the plane's first/second axis naming)"),
        "value": num("its value (null: not fitted)", True),
        "stderr": num("its standard error (null: none)", True),
        "used": boolean("entered the combination"),
        "reason": string("why not used", True),
    },
)


def _combined(desc: str) -> Schema:
    return obj(desc, {
        **_figure_props("unit"),
        "observations": {"type": "array", "items": {"$ref": "#/$defs/observation"},
                         "description": "each test's estimate"},
        "check": string("the name of its consistency check (null: seen by one test)", True),
    })


def _loop_schema(what: str) -> Schema:
    pair = _combined(f"the pair's {what} (e_a - e_b for the pair ab)")
    pair["properties"]["adjusted"] = {"$ref": "#/$defs/figure",
                                      "description": "the least-squares value once the loop's closure is enforced"}
    pair["required"].append("adjusted")
    return obj(f"{what}: per pair, the loop's closure, each axis against the three axes' mean", {
        "unit": string("ppm or ms"),
        "pairs": obj("per axis pair", {p: pair for p in ("XY", "YZ", "ZX")}),
        "closure": string("the name of the closure check in checks"),
        "axes": obj("each axis against the mean of the three", {a: {"$ref": "#/$defs/figure"} for a in "XYZ"}),
    })


SET_DESCRIPTION = (
    "ballbar.Set: a test set combined into the machine's axes (kind set, ballbar/<m>/result/set, and the MCAP "
    "results channel): analysis/sets.py, analysis/README.md \"Test sets\"."
)


def _set_defs() -> dict[str, Schema]:
    return {"figure": obj("a set figure", _figure_props("unit")), "observation": _OBSERVATION}


def _set_object() -> Schema:
    check = obj("a check of the whole set", {
        "name": string("its name"),
        "kind": string("consistency (two tests see one quantity) or closure (a loop of three pairs)",
                       enum=["consistency", "closure"]),
        "quantity": string("what is checked"),
        "status": string("passed, failed or not_checked", enum=["passed", "failed", "not_checked"]),
        "value": num("the discrepancy: consistency, the difference (more than two: the largest from the mean); "
                     "closure, the sum of the three pairs (null: not checked)", True),
        "stderr": num("its standard error (null: not checked)", True),
        "z": num("value / stderr (more than two tests: sqrt of chi-square per degree of freedom)", True),
        "coverage_k": num("fails beyond this many standard errors ..."),
        "min_discrepancy": num("... and above this, in unit"),
        "unit": string("the unit"),
        "message": string("the check in words"),
    })
    member = obj("one plan's test in the set", {
        "plan": string("the plan"),
        "plane": string("its plane"),
        "test_id": string("the test's id", True),
        "t_wall": string("when its result was published (ISO 8601 UTC)", True),
        "radius_mm": num("its radius, mm", True),
        "feed_mm_min": num("its programmed feed, mm/min", True),
        "data_arc_deg": num("its data arc, deg", True),
        "valid": boolean("its fit's checks held (fit.valid)"),
        "invalid_reasons": {"type": "array", "items": {"type": "string"}, "description": "why not valid"},
        "verdict": string("its own verdict against its plan's limits; not_evaluated without limits",
                          enum=["pass", "warning", "fail", "not_evaluated"]),
        "verdict_summary": string("its verdict in one line", True),
        "G_b_um": num("its G(b), um", True),
    })
    extreme = obj("the largest circular deviation of the set's valid tests", {
        **_figure_props("um"),
        "plan": string("the plan whose test has it", True),
        "test_id": string("that test", True),
        "figure": string("G_b_um, or G_ccw_um / G_cw_um for a one-direction test", True),
    })
    sphere = obj("the geometric sphericity: the range of the radial deviation the squareness and relative scale "
                 "errors make over the sphere", {
                     **_figure_props("um"),
                     "interval": {"type": ["array", "null"], "items": {"type": "number"}, "minItems": 2,
                                  "maxItems": 2, "description": "its 95 % interval, um (null: no value)"},
                     "radius_mm": num("the sphere's radius: the set's largest, mm", True),
                 })
    verdict = obj("the set's verdict", {
        "status": string("pass, warning or fail", enum=["pass", "warning", "fail"]),
        "trusted": boolean("every check passed and every test is valid"),
        "plans": {"type": "array", "description": "each plan's own verdict", "items": obj("a plan's verdict", {
            "plan": string("the plan"), "status": string("its test's verdict"),
            "summary": string("in one line", True)})},
        "failed_checks": {"type": "array", "items": {"type": "string"}, "description": "names of failed checks"},
        "reasons": {"type": "array", "items": {"type": "string"}, "description": "why not trusted"},
        "summary": string("the verdict in one line"),
        "rule": string("how the verdict is made, in words"),
    })
    props: dict[str, Schema] = {
        **_envelope("set"),
        "set_id": string("<set name>@<the newest member test's id>"),
        "set": obj("the set's definition ([sets.<name>])", {
            "name": string("its name"),
            "plans": {"type": "array", "items": {"type": "string"}, "description": "its plans"},
            "window_s": num("its tests must all lie within this, s"),
        }),
        "tests": {"type": "array", "items": member, "description": "the latest test of each plan, in the set's order"},
        "span_s": num("from the oldest to the newest member test, s", True),
        "lost_motion": obj("lost motion per axis, um", {a: _combined(f"the {a} axis' lost motion, um") for a in "XYZ"}),
        "squareness": obj("squareness per pair, urad (+: +a and +b enclose less than 90 deg)",
                          {p: _combined(f"the {p} squareness, urad") for p in ("XY", "YZ", "ZX")}),
        "scale": _loop_schema("relative scale, ppm"),
        "servo": _loop_schema("servo lag mismatch, ms"),
        "volumetric": obj("volumetric figures", {
            "largest_circular_deviation": extreme,
            "geometric_sphericity": sphere,
            "method": string("how both are computed, in words"),
        }),
        "checks": {"type": "array", "items": check, "description": "every consistency and closure check"},
        "verdict": verdict,
        "conventions": counts("the sign conventions, in words", "string"),
        "method": string("how the figures are combined, in words"),
    }
    return obj("a set result as the daemon publishes it", props)


def set_schema() -> Schema:
    return _document("set", SET_DESCRIPTION, _set_object(), _set_defs())


# --------------------------------------------------------------------------- documents


def _document(name: str, description: str, body: Schema, defs: dict[str, Schema] | None = None) -> Schema:
    doc: Schema = {
        "$schema": DRAFT,
        "$id": f"urn:ballbar:schema:{SCHEMA_VERSION}:{name}",
        "title": f"ballbar {name} (schema_version {SCHEMA_VERSION})",
        "description": description,
        **body,
    }
    if defs:
        doc["$defs"] = defs
    return doc


@cache
def _built(name: str) -> str:
    makers = {
        "result": result_schema, "analysis": analysis_schema, "event": event_schema,
        "mcap-event": lambda: event_schema(mcap=True), "status": status_schema, "config": config_schema,
        "samples": samples_schema, "history": history_schema, "alert": alert_schema, "set": set_schema,
    }
    if name not in makers:
        raise KeyError(f"no schema {name!r} (one of {', '.join(NAMES)})")
    return json.dumps(makers[name](), indent=2, sort_keys=False) + "\n"


def schema(name: str) -> Schema:
    """The schema ``name`` (one of :data:`NAMES`) as a fresh dict."""
    doc: Schema = json.loads(_built(name))
    return doc


def schema_text(name: str) -> str:
    """The schema as the shipped file holds it."""
    return _built(name)


def shipped_dir() -> Path:
    """Where the package ships the files: ``ballbar/schema/`` in the installed package."""
    from importlib.resources import files

    return Path(str(files("ballbar") / "schema"))


def write(directory: str | Path) -> list[Path]:
    out = []
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    for name in NAMES:
        p = d / f"{name}.schema.json"
        p.write_text(schema_text(name), encoding="utf-8")
        out.append(p)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ballbar.daemon.schemas", description=__doc__.split("\n\n")[0])
    p.add_argument("--write", metavar="DIR", help="write every schema as DIR/<name>.schema.json")
    p.add_argument("name", nargs="?", choices=NAMES, help="print this schema")
    args = p.parse_args(argv)
    if args.write:
        for path in write(args.write):
            print(path)
    elif args.name:
        sys.stdout.write(schema_text(args.name))
    else:
        print("\n".join(NAMES))
    return 0


if __name__ == "__main__":
    sys.exit(main())
