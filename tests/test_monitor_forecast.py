"""Forecasts that say what the data show (issue 35 §3): the rule of :func:`ballbar.analysis.monitor.forecast`,
the first verdict's alert, the report's and the viewer's words, and a small forecast survey."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np
import pytest

from ballbar.analysis import monitor as mon
from ballbar.analysis.monitor import forecast_sentence
from ballbar.daemon.monitor import Monitor
from ballbar.tools.bench import forecast_survey
from ballbar.tools.report_render import forecast_words

T0 = datetime(2026, 11, 28, 4, 18, tzinfo=UTC)


def settings(**kw: Any) -> mon.MonitorSettings:
    return mon.settings_from_dict({"enabled": True, **kw})


def pts(values: list[float], minutes: float = 1440.0, se: float = 0.1) -> list[tuple[datetime, float, float, str]]:
    return [(T0 + timedelta(minutes=i * minutes), v, se, f"t{i}") for i, v in enumerate(values)]


def result(i: int, when: datetime, gb: float, rms: float = 0.1, **params: float) -> dict[str, Any]:
    return {
        "kind": "test", "machine_id": "m", "test_id": f"m-{i}", "t_wall": mon.time_text(when),
        "plan": {"plane": "XY", "radius_mm": 100.0, "feed_mm_min": 1000.0, "data_arc_deg": 360.0,
                 "directions": "both"},
        "timing": {"measured_feed_mm_min": 1000.0},
        "parameters": {n: {"value": v, "stderr": 0.1 * abs(v) / 4 + 0.05, "unit": "urad" if "urad" in n else "um"}
                       for n, v in params.items()},
        "iso230_4": {"G_b_um": gb, "G_ccw_um": gb, "G_cw_um": gb},
        "residual_rms_um": rms,
    }


def test_a_flat_quantity_tested_minutes_apart_has_no_crossing_date_in_the_report() -> None:
    """G(b) flat at 4.8 um, a test every 5 minutes: a few tenths of scatter make tens of um a day, but the
    report's words say no forecast, as its chart shows a flat line (was: "+31.2 um/day, reaches its limit")."""
    rng = np.random.default_rng(5)
    s = settings(G_b_um=25.0)
    tests = []
    for i in range(12):
        r = result(i, T0 + timedelta(minutes=5 * i), 4.8 + float(rng.normal(0, 0.15)))
        r["verdict"] = mon.evaluate(r, s)
        tests.append(r)
    (line,) = forecast_words(tests, ("X", "Y"))
    assert "G(b): trend " in line and "no forecast" in line, line
    assert "reaches its limit" not in line and "2026-" not in line, line
    assert "verdict" in tests[-1] and tests[-1]["verdict"]["status"] == "pass"


def test_a_falling_value_is_never_said_to_reach_a_positive_limit() -> None:
    """Backlash falling from 6 um towards 0 against a limit of 8 on |value|: heading away, no date."""
    s = settings(parameters={"backlash_x_um": 8.0})
    f = mon.forecast(pts([6.0 - 0.1 * i for i in range(20)]), s.limits[0], "backlash_x_um", s)
    assert f["significant"] and f["slope_per_day"] < 0
    assert not f["due"] and f["crossing"] is None and "heading away from its limit" in f["reason"]
    words = mon.forecast_words(f, "Backlash X", "um")
    assert "reaches its limit" not in words and "heading away" in words
    text = forecast_sentence("backlash_x_um", [p[0].timestamp() for p in pts([0] * 20)],
                             [6.0 - 0.1 * i for i in range(20)], 8.0, unit="um")
    assert "reaches its limit" not in text and "heading away" in text
    # a negative backlash growing more negative does head for -8
    g = mon.forecast(pts([-4.0 - 0.2 * i for i in range(20)]), s.limits[0], "backlash_x_um", s)
    assert g["due"] and g["bound"] == -8.0 and "reaches its limit -8.0 um" in mon.forecast_words(g, "Backlash X", "um")


def test_what_already_fails_gets_no_forecast_and_no_date_is_in_the_past() -> None:
    """G(b) jumping past its limit at the first tests: it fails, so no forecast; a rising trend just below the
    limit has its crossing dates after its last test, never before."""
    s = settings(G_b_um=25.0)
    lim = s.limits[1] if s.limits[0].name != "G_b_um" else s.limits[0]
    failing = mon.forecast(pts([10.0, 18.0, 26.0, 34.0, 42.0, 50.0, 58.0], minutes=15.0), lim, "G_b_um", s)
    assert not failing["due"] and failing["crossing"] is None and failing["reason"].startswith("it fails")
    rng = np.random.default_rng(2)
    rising = [10.0 + 1.5 * i + float(rng.normal(0, 0.8)) for i in range(10)]  # 23.5 at the last test
    f = mon.forecast(pts(rising), lim, "G_b_um", s)
    assert f["due"], f
    last = mon.parse_time(f["last"])
    for key in ("crossing", "crossing_lo", "crossing_hi"):
        assert mon.parse_time(f[key]) >= last, (key, f[key], f["last"])
    assert f["days_to_crossing_lo"] >= 0.0


def test_a_constant_machine_tested_every_few_minutes_forecasts_nothing() -> None:
    """Squareness 25 urad and Y backlash 6 um that never change, G(b) 4.8 um, a test every 6 minutes (the
    simulated machine ten times faster than real time): no forecast alert over 60 tests, and the slopes are
    tested at the Bonferroni level of the five watched quantities."""
    s = settings(G_b_um=25.0, parameters={"squareness_urad": 50.0, "backlash_y_um": 8.0, "backlash_x_um": 8.0})
    assert len(s.quantities()) == 4
    m = Monitor(s, "m")
    rng = np.random.default_rng(11)
    alerts = []
    for i in range(60):
        r = result(i, T0 + timedelta(minutes=6 * i), 4.8 + float(rng.normal(0, 0.3)),
                   squareness_urad=25.0 + float(rng.normal(0, 2.0)), backlash_y_um=6.0 + float(rng.normal(0, 0.3)),
                   backlash_x_um=2.0 + float(rng.normal(0, 0.3)))
        r["verdict"] = m.verdict(r)
        alerts += m.on_test(r)
        for f in m.last_forecasts:
            assert not f["due"], f
            assert f["watched"] == 4 and f["slope_confidence"] == pytest.approx(1 - 0.05 / 4)
    assert [a for a in alerts if a["alert"] == "forecast"] == []


def test_the_span_bounds_how_far_ahead_a_forecast_looks() -> None:
    """A clean rise of 0.2 a day from 2 to 3.8 over 9 days: the crossing of 8 is 21 days ahead, more than twice
    the span; with 24 days of tests the same line is forecast."""
    s = settings(parameters={"backlash_x_um": 8.0})
    short = mon.forecast(pts([2.0 + 0.2 * i for i in range(10)]), s.limits[0], "backlash_x_um", s)
    assert short["significant"] and not short["due"] and "the trend's span" in short["reason"]
    assert short["reach_days"] == pytest.approx(2 * 9.0)
    s30 = settings(parameters={"backlash_x_um": 8.0}, trend_tests=40)
    long = mon.forecast(pts([2.0 + 0.2 * i for i in range(25)]), s30.limits[0], "backlash_x_um", s30)
    assert long["due"] and long["days_to_crossing"] == pytest.approx(30.0 - 24.0, abs=0.01)


def test_a_trend_smaller_than_the_values_uncertainty_is_no_forecast() -> None:
    """Monotone by rank but within the values' stated uncertainty: no forecast."""
    s = settings(parameters={"backlash_x_um": 8.0})
    f = mon.forecast(pts([7.0 + 0.01 * i for i in range(20)], se=0.2), s.limits[0], "backlash_x_um", s)
    assert f["significant"] and not f["due"] and "less than 2 x the values' standard uncertainty" in f["reason"]


def test_the_first_verdict_alerts_as_the_first() -> None:
    tr = mon.AlertTracker(clear_after=2)
    (a,) = tr.update({"status": "fail"}, [])
    assert a["previous"] is None and a["state"] == "fail"
    assert "m: first verdict: fail at test t1" in mon.alert_text({**a, "machine_id": "m", "test_id": "t1"})
    ok = mon.AlertTracker(clear_after=2)
    assert ok.update({"status": "pass"}, []) == []  # a first pass says nothing
    (b,) = ok.update({"status": "fail"}, [])
    assert mon.alert_text({**b, "machine_id": "m"}).startswith("m: verdict pass -> fail")


def test_a_small_forecast_survey() -> None:
    """100 constant machines (tests every 3 min to every day): at most one false forecast; 20 wearing ones:
    every wearing quantity forecast before it crosses; no crossing date in the past, no forecast of what
    fails.  The full survey: ``python -m ballbar.tools.bench.forecast_survey``."""
    machines = ([forecast_survey.Machine(s, "constant", tests=40) for s in range(1, 101)]
                + [forecast_survey.Machine(s, "wearing") for s in range(1, 21)])
    rows = forecast_survey.survey(machines, jobs=1)
    summary = forecast_survey.summarize(rows)
    const, wear = summary["constant"], summary["wearing"]
    assert const["machines"] == 100 and const["machines_with_false_forecast"] <= 1, const["false_examples"]
    assert len(const["by_interval"]) == len(forecast_survey.INTERVALS_MIN)  # every interval was drawn
    assert wear["machines"] == 20 and wear["missed"] == 0, wear["missed_examples"]
    assert wear["lead_tests_min"] >= 1
    for s in (const, wear):
        assert s["due_with_crossing_in_the_past"] == 0 and s["due_while_failing"] == 0


def test_the_viewers_forecast_text_follows_the_monitors_rule() -> None:
    """The live trends' forecast text (daemon/rerun): rows built as the viewer builds them from results a few
    minutes apart; a flat G(b) and a falling X backlash get no crossing date, a rising Y backlash does."""
    from ballbar.daemon.rerun.listener import RerunViewer
    from ballbar.daemon.rerun.scene import TREND_WIDTH

    rng = np.random.default_rng(9)
    s = settings(G_b_um=25.0, parameters={"backlash_x_um": 8.0, "backlash_y_um": 8.0})
    rows = np.zeros((0, TREND_WIDTH))
    for i in range(15):
        when = T0 + timedelta(minutes=4 * i)
        r = result(i, when, 4.8 + float(rng.normal(0, 0.15)), backlash_x_um=6.0 - 0.1 * i + float(rng.normal(0, 0.02)),
                   backlash_y_um=2.0 + 0.4 * i + float(rng.normal(0, 0.05)))
        r["verdict"] = mon.evaluate(r, s)
        row = RerunViewer._trend_row(r, i, when.timestamp(), rows)
        assert row is not None
        rows = np.vstack([rows, row])
    md = RerunViewer._forecast_markdown(object(), rows)  # type: ignore[arg-type]  # uses only the rows given
    lines = {ln.split(":")[0]: ln for ln in md.splitlines() if ln.startswith("- ")}
    assert "no forecast" in lines["- Circularity G(b)"] and "reaches" not in lines["- Circularity G(b)"], md
    assert "heading away" in lines["- Backlash X"], md
    assert "reaches its limit 8" in lines["- Backlash Y"], md
