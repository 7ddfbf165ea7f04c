"""The monitor: limits and verdicts, Theil-Sen trends, forecasts, alert states, the store, the schema.

The forecast and false-alert tests run the physical simulator and the daemon's
engine on every test (``ballbar.tools.bench.alert_survey``), with one test a day.
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbar.analysis import monitor as mon
from ballbar.analysis.engine import analyze_recording
from ballbar.daemon import schemas
from ballbar.daemon.config import ConfigError, load, monitor_settings
from ballbar.daemon.listeners import Listener
from ballbar.daemon.monitor import Monitor, MonitorStore
from ballbar.tools.bench import alert_survey
from ballbar.tools.simulator import MachineModel, simulate

SCHEMA = schemas.schema("alert")  # the shipped one, generated from ballbar.protocol.messages.monitor
try:
    import jsonschema
except ImportError:  # pragma: no cover - the test extras install it
    jsonschema = None


def validate(obj: Any, definition: str | None = None) -> None:
    if jsonschema is None:
        pytest.skip("jsonschema is not installed")
    schema = SCHEMA if definition is None else {**SCHEMA, "$ref": f"#/$defs/{definition}"}
    if definition is not None:
        schema = {"$schema": SCHEMA["$schema"], "$defs": SCHEMA["$defs"], "$ref": f"#/$defs/{definition}"}
    jsonschema.Draft202012Validator(schema).validate(json.loads(json.dumps(obj)))


def settings(**kw: Any) -> mon.MonitorSettings:
    return mon.settings_from_dict({"enabled": True, **kw})


def fake_result(backlash: float, se: float, t_wall: str = "2026-01-01T00:00:00Z", **extra: Any) -> dict[str, Any]:
    return {
        "kind": "test", "machine_id": "m", "test_id": f"m-{t_wall}", "t_wall": t_wall,
        "plan": {"plane": "XY", "radius_mm": 100.0, "feed_mm_min": 1000.0, "data_arc_deg": 360.0,
                 "directions": "both"},
        "timing": {"measured_feed_mm_min": 1000.2},
        "parameters": {"backlash_x_um": {"value": backlash, "stderr": se, "unit": "um"},
                       "cyclic_x_um": {"value": None, "stderr": None, "unit": "um", "reason": "no screw pitch"}},
        "iso230_4": {"G_ccw_um": 4.0, "G_cw_um": 4.2, "G_b_um": 5.0, "H_um": 3.0},
        "residual_rms_um": 0.1,
        **extra,
    }


# ----------------------------------------------------------------------------- verdict


@pytest.mark.parametrize(
    ("value", "status", "within"),
    [
        (3.0, "pass", False),  # below the warning level 8
        (8.5, "warning", False),  # above 0.8 x 10, clear of the limit
        (9.9, "warning", True),  # 0.1 below the limit, U = 0.2: may exceed it
        (10.1, "warning", True),  # 0.1 above, U = 0.2: within uncertainty, not fail
        (-10.1, "warning", True),  # a bound on |value|
        (10.3, "fail", False),  # beyond the uncertainty
    ],
)
def test_verdict_rule(value: float, status: str, within: bool) -> None:
    v = mon.evaluate(fake_result(value, 0.1), settings(parameters={"backlash_x_um": 10.0}))
    (e,) = v["limits"]
    assert (e["status"], e["within_uncertainty"]) == (status, within)
    assert v["status"] == status
    assert e["uncertainty"] == pytest.approx(0.2) and e["margin"] == pytest.approx(10.0 - abs(value))
    assert ("within uncertainty of the limit" in v["summary"]) == within
    validate(v, "verdict")


def test_iso_limits_carry_an_uncertainty_and_g_applies_per_direction() -> None:
    v = mon.evaluate(fake_result(1.0, 0.01), settings(G_um=4.1, G_b_um=20.0, H_um=2.0, coverage_k=3.0))
    by = {e["name"]: e for e in v["limits"]}
    assert set(by) == {"G_ccw_um", "G_cw_um", "G_b_um", "H_um"}
    assert by["G_ccw_um"]["stderr"] == pytest.approx(np.sqrt(2) * 0.1)  # sqrt(2) x residual RMS
    assert by["G_ccw_um"]["status"] == "warning" and by["G_ccw_um"]["within_uncertainty"]  # 4.0 vs 4.1, U = 0.42
    assert by["H_um"]["status"] == "fail"  # 3.0 - 0.42 > 2
    assert v["status"] == "fail" and v["coverage_k"] == 3.0
    validate(v, "verdict")


def test_a_parameter_without_a_value_is_not_evaluated_and_says_why() -> None:
    v = mon.evaluate(fake_result(1.0, 0.01), settings(parameters={"cyclic_x_um": 1.0}))
    (e,) = v["limits"]
    assert e["status"] == "not_evaluated" and e["reason"] == "no screw pitch"
    assert v["status"] == "pass" and v["not_evaluated"] == 1


def test_within_uncertainty_on_a_simulated_test_is_not_a_fail() -> None:
    """A physical simulated test; limits placed about its fitted backlash by its own standard error."""
    plan = alert_survey.PLAN
    sim = simulate(plan, replace(alert_survey.BASE, backlash_x_um=6.0, noise_um=0.3), plan.sample_hz, seed=4)
    res = next(r for r in analyze_recording(sim.t_s, sim.length_mm, plan) if r.get("kind") == "test")
    p = res["parameters"]["backlash_x_um"]
    value, se = p["value"], p["stderr"]
    assert 0 < se < 0.2 and abs(value - 6.0) < 0.3
    for limit, status, within in ((value - 1.0 * se, "warning", True), (value + 1.5 * se, "warning", True),
                                  (value - 3.0 * se, "fail", False), (value / 0.7, "pass", False)):
        v = mon.evaluate(res, settings(parameters={"backlash_x_um": limit}))
        e = v["limits"][0]
        assert (e["status"], e["within_uncertainty"]) == (status, within), (limit, value, se)
        assert v["status"] == status
    above = mon.evaluate(res, settings(parameters={"backlash_x_um": value - 1.0 * se}))
    assert "within uncertainty of the limit" in above["summary"] and above["status"] != "fail"


def test_limits_configuration_is_validated() -> None:
    cfg = load(None, ["limits.enabled=true", "limits.G_b_um=20", "limits.parameters={backlash_x_um=8}",
                      "limits.warn_fractions={G_b_um=0.9}"], env={})
    s = monitor_settings(cfg)
    assert [(lim.name, lim.warn_fraction) for lim in s.limits] == [("G_b_um", 0.9), ("backlash_x_um", 0.8)]
    assert not monitor_settings(load(None, ["limits.G_b_um=20"], env={})).enabled  # off by default
    for bad, words in [
        ("limits.parameters={backlash_q_um=8}", "limits.parameters.backlash_q_um"),
        ("limits.G_um=0", "limits.G_um"),
        ("limits.warn_fraction=0", "limits.warn_fraction"),
        ("limits.warn_fractions={H_um=0.5}", "limits.warn_fractions.H_um"),
        ("limits.min_tests=2", "limits.min_tests"),
        ("limits.horizon=3", "unknown key limits.horizon"),
    ]:
        with pytest.raises(ConfigError, match=words.replace(".", r"\.")):
            load(None, [bad], env={})


# ----------------------------------------------------------------------------- trend


def test_theil_sen_matches_scipy() -> None:
    stats = pytest.importorskip("scipy.stats")
    rng = np.random.default_rng(3)
    for n in (5, 9, 20):
        t = np.sort(rng.uniform(0, 30, n))
        y = 0.2 * t + rng.standard_t(2, n)  # heavy tails: what Theil-Sen is for
        ours = mon.theil_sen(t, y, 0.9)
        ref = stats.theilslopes(y, t, 0.9)
        assert (ours.slope, ours.slope_lo, ours.slope_hi) == pytest.approx((ref.slope, ref.low_slope, ref.high_slope))


def _pts(values: list[float], days: float = 1.0) -> list[tuple[datetime, float, float, str]]:
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    return [(t0 + timedelta(days=i * days), v, 0.05, f"t{i}") for i, v in enumerate(values)]


def test_a_flat_trend_forecasts_nothing() -> None:
    s = settings(parameters={"backlash_x_um": 5.0}, horizon_days=1e4)
    rng = np.random.default_rng(1)
    f = mon.forecast(_pts(list(4.0 + 0.3 * rng.standard_normal(20))), s.limits[0], "backlash_x_um", s)
    assert not f["significant"] and not f["due"] and "flat within its scatter" in f["reason"]
    few = mon.forecast(_pts([1, 2, 3, 4]), s.limits[0], "backlash_x_um", s)
    assert not few["due"] and "fewer than min_tests" in few["reason"]
    validate(f, "forecast")


def test_a_falling_trend_heads_for_the_negative_bound() -> None:
    s = settings(parameters={"backlash_x_um": 5.0})
    f = mon.forecast(_pts([-1.0 - 0.2 * i for i in range(15)]), s.limits[0], "backlash_x_um", s)
    assert f["due"] and f["bound"] == -5.0
    assert f["days_to_crossing"] == pytest.approx(20.0 - 14.0, abs=0.01)  # -1 - 0.2 t = -5 at t = 20


def test_invalid_tests_never_enter_a_trend() -> None:
    s = settings(parameters={"backlash_x_um": 10.0}, min_tests=3)
    m = Monitor(s, "m")
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    for i in range(8):
        extra: dict[str, Any] = {}
        if i % 2:  # every other test: one the analysis warned about, or with an implausible feed
            extra = {"warnings": ["timing model: ..."]} if i % 4 == 1 else {"timing": {"measured_feed_mm_min": 800.0}}
        r = fake_result(1.0 + i, 0.01, mon.time_text(t0 + timedelta(days=i)), **extra)
        r["verdict"] = m.verdict(r)
        assert ("trend_excluded" in r["verdict"]) == bool(i % 2)
        m.on_test(r)
    (f, *_) = m.forecasts(fake_result(0, 0, "2026-02-01T00:00:00Z"))
    assert f["n"] == 4 and f["test_ids"] == [f"m-{mon.time_text(t0 + timedelta(days=i))}" for i in (0, 2, 4, 6)]


# ----------------------------------------------------------------------------- alert states


def test_alert_tracker_sends_each_change_once_with_hysteresis() -> None:
    tr = mon.AlertTracker(clear_after=2)

    def step(status: str, due: bool = False) -> list[tuple[str, str]]:
        alerts = tr.update({"status": status}, [{"name": "b", "due": due}])
        return [(a["alert"], a["state"]) for a in alerts]

    assert step("pass") == []
    assert step("warning") == [("verdict", "warning")]
    assert step("warning") == []  # unchanged: no repeat
    assert step("pass") == []  # one better test is not enough
    assert step("warning") == []  # ... and resets the count
    assert step("fail", due=True) == [("verdict", "fail"), ("forecast", "due")]
    assert step("fail", due=True) == []
    assert step("warning") == []
    assert step("pass") == [("verdict", "warning"), ("forecast", "clear")]  # the worse of the two better ones
    assert step("pass") == []
    assert step("pass") == [("verdict", "pass")]


def test_a_due_forecast_clears_only_when_clearly_not_due() -> None:
    """The later bound wavering about the horizon (due, not due, due) alerts once; it clears when the slope is
    no longer significant, or when even the earlier bound is beyond the horizon."""
    tr = mon.AlertTracker(clear_after=2)

    def step(due: bool, significant: bool = True, lo_days: float | None = 10.0) -> list[str]:
        f = {"name": "b", "due": due, "significant": significant, "days_to_crossing_lo": lo_days,
             "horizon_days": 30.0, "crossing": "2026-02-01T00:00:00Z"}
        return [a["state"] for a in tr.update(None, [f])]

    assert step(True) == ["due"]
    assert step(False) == [] and step(False) == [] and step(False) == []  # the early bound still within 30 days
    assert step(True) == []  # due again: no second alert
    assert step(False, lo_days=45.0) == []
    assert step(False, lo_days=45.0) == ["clear"]  # twice clearly beyond the horizon
    assert step(True) == ["due"]
    assert step(False, significant=False) == [] and step(False, significant=False) == ["clear"]
    assert step(True) == ["due"]
    assert step(False, lo_days=None) == [] and step(False, lo_days=12.0) == []  # the count restarts
    assert step(False, lo_days=None) == [] and step(False, lo_days=None) == ["clear"]  # unbounded: beyond


def test_the_store_keeps_trend_and_alert_states_across_a_restart(tmp_path: Path) -> None:
    s = settings(parameters={"backlash_x_um": 8.5}, min_tests=5)
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    sent: list[dict[str, Any]] = []

    def run(days: range) -> None:
        m = Monitor(s, "m", MonitorStore(tmp_path, "m"))
        for i in days:
            r = fake_result(2.0 + 0.5 * i, 0.05, mon.time_text(t0 + timedelta(days=i)))
            r["verdict"] = m.verdict(r)
            sent.extend(m.on_test(r))

    run(range(0, 4))  # 2.0 .. 3.5: no alert yet (fewer than 5 tests)
    assert sent == []
    # a restart: the trend goes on from the stored tests; 2 + 0.5 t reaches 8.5 at day 13, due from day 5, the
    # first test whose span (5 days) reaches twice as far as that is ahead (8 days; day 4: 9 days, span 4)
    run(range(4, 8))
    assert [(a["alert"], a["state"], a["test_id"]) for a in sent] == [
        ("forecast", "due", f"m-{mon.time_text(t0 + timedelta(days=5))}")]
    f = sent[0]["forecast"]
    assert f["n"] == 6 and f["crossing"] == mon.time_text(t0 + timedelta(days=13))
    run(range(8, 10))  # another restart: still due, not sent again
    assert len(sent) == 1
    assert [a["alert_id"] for a in MonitorStore(tmp_path, "m").alerts()] == ["m-alert-1"]
    for a in sent:
        validate(a)


class _Recorder(Listener):
    name = "recorder"
    batch_period_s = None
    idle_s = None

    def __init__(self) -> None:
        self.messages: list[dict[str, Any]] = []

    def on_message(self, msg: dict[str, Any]) -> None:
        self.messages.append(msg)

    def stop(self) -> None:
        pass


def test_an_alert_reaches_every_other_output_after_the_test_it_is_about(tmp_path: Path) -> None:
    """The monitor is built before the bus (its store seeds history/alert), so it comes first in the outputs; but
    an alert its thread sends at once must not overtake, on the bus, the test result it refers to.  The other
    queue is slowed here where it takes a test, as a broadcaster descheduled between two queues would be."""
    from ballbar.daemon.config import load
    from ballbar.daemon.monitor import MonitorListener
    from ballbar.daemon.service import Daemon
    from ballbar.daemon.sources import open_source

    cfg = load(None, ["mcap.enabled=false", "zenoh.enabled=false", 'rerun.mode="off"', "limits.enabled=true",
                      "limits.parameters={backlash_x_um=5.0}", f'daemon.state_dir="{tmp_path}"'], env={})
    monitor, rec = MonitorListener.from_config(cfg), _Recorder()
    d = Daemon(cfg, open_source("sim:?speedup=1&rate=100"), [(monitor, 10, "drop_newest"), (rec, 10, "drop_newest")])
    q = next(q for q in d.outputs if q.listener is rec)
    put = q.put_message

    def slow_put(msg: dict[str, Any]) -> None:
        if msg.get("kind") == "test":
            time.sleep(0.3)
        put(msg)

    q.put_message = slow_put
    try:
        d.broadcast(fake_result(9.0, 0.05))  # beyond the limit: a fail alert
        deadline = time.monotonic() + 5.0
        while len(rec.messages) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        d.shutdown(1.0)
    assert [(m["kind"], m.get("alert")) for m in rec.messages] == [("test", None), ("alert", "verdict")]
    assert rec.messages[0]["verdict"]["status"] == "fail" and rec.messages[1]["state"] == "fail"


# ----------------------------------------------------------------------------- simulated machines


def test_a_wearing_machine_is_forecast_within_the_interval() -> None:
    """Backlash growing 0.15 um a day from 3 um, limit 8 um: the true crossing is day 33.3, 14 days after the
    last of 20 daily tests.  Its forecast is due and its interval holds the true date."""
    out = alert_survey.run(alert_survey.Scenario(seed=11, rate_um_day=0.15))
    f = out["forecast"]
    assert f["due"] and f["n"] == 20 and f["significant"], f
    assert out["covered"], (f["crossing_lo"], out["true_crossing"], f["crossing_hi"])
    assert abs(out["error_days"]) < 3.0
    # one alert: the forecast, when it first became due; the verdict stays pass (below 80 % of 8 um)
    assert [(a["alert"], a["state"], a["limit"]) for a in out["alerts"]] == [("forecast", "due", "backlash_x_um")]


@pytest.mark.parametrize("seed", [101, 102, 103])
def test_a_stable_machine_sends_no_alert(seed: int) -> None:
    """20 daily tests of a machine that does not change (sensor noise 0.3 um, backlash scatter 0.2 um):
    no alert at all.  The survey over 200 seeds: ``python -m ballbar.tools.bench.alert_survey --seeds 200``."""
    out = alert_survey.run(alert_survey.Scenario(seed=seed))
    assert out["alerts"] == [], out["alerts"]
    assert not out["forecast"]["due"]


def test_simulated_drift_changes_the_machine_from_test_to_test() -> None:
    from ballbar.tools.simulator import iter_tests

    plan = alert_survey.PLAN
    fitted = []
    for res in iter_tests(plan, MachineModel(backlash_x_um=2.0), plan.sample_hz, repeat=3, gap_s=1.0,
                          drift={"backlash_x_um": 1.5}):
        out = analyze_recording(res.t_s - res.t_s[0], res.length_mm, plan)
        fitted.append(next(r for r in out if r.get("kind") == "test")["parameters"]["backlash_x_um"]["value"])
    assert fitted == pytest.approx([2.0, 3.5, 5.0], abs=0.1)


# ----------------------------------------------------------------------------- offline: analyze, report, gcode


@pytest.fixture(scope="module")
def simulated_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from ballbar.tools.simulator_cli import write_csv

    plan = alert_survey.PLAN
    path = tmp_path_factory.mktemp("csv") / "test.csv"
    sim = simulate(plan, replace(alert_survey.BASE, backlash_x_um=7.0, noise_um=0.2), plan.sample_hz, seed=2)
    write_csv(path, sim.t_s, sim.length_mm)
    return path


def test_analyze_gives_the_verdict_of_the_plan_files_limits(simulated_csv: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    from ballbar.daemon.cli import main as cli_main

    plan = alert_survey.PLAN
    cfg = tmp_path / "plan.toml"
    cfg.write_text(f"[plan]\nfeed_mm_min = {plan.feed_mm_min}\novershoot_deg = {plan.overshoot_deg}\n"
                   f"sample_hz = {plan.sample_hz}\n[limits]\nenabled = true\nG_b_um = 30.0\n"
                   "parameters = {backlash_x_um = 8.0}\n")
    assert cli_main(["analyze", str(simulated_csv), "--plan", str(cfg), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    v = result["verdict"]
    assert v["status"] == "warning"  # 7 um of backlash against 8 (warning above 6.4)
    assert [e["name"] for e in v["limits"]] == ["G_b_um", "backlash_x_um"]
    assert v == mon.evaluate(result, settings(G_b_um=30.0, parameters={"backlash_x_um": 8.0}))
    validate(v, "verdict")
    assert cli_main(["analyze", str(simulated_csv), "--plan", str(cfg)]) == 0
    text = capsys.readouterr().out
    # the verdict in the view's words and by the one rounding rule (analysis/numbers.py): the quantity and its
    # axis, the value to its standard error (0.1 um at the finest), the limit and the margin at that place
    assert re.search(r"Verdict: WARNING: Backlash X 7\.\d ± 0\.\d µm, limit 8\.0 µm: 1\.\d µm \(\d+ %\) below it, "
                     r"above the warning level 6\.4 µm \(warning\); 1 of 2 limits passed", text), text
    assert "G_b_um" in text  # the per-field table keeps the field names for scripts
    # without limits: no verdict
    cfg.write_text(f"[plan]\nfeed_mm_min = {plan.feed_mm_min}\novershoot_deg = {plan.overshoot_deg}\n")
    assert cli_main(["analyze", str(simulated_csv), "--plan", str(cfg), "--json"]) == 0
    assert "verdict" not in json.loads(capsys.readouterr().out)


def test_the_reports_verdict_box_shows_the_limits(simulated_csv: Path, tmp_path: Path) -> None:
    from ballbar.daemon.cli import main as cli_main

    plan = alert_survey.PLAN
    daemon_cfg = tmp_path / "ballbar.toml"
    daemon_cfg.write_text("[limits]\nenabled = true\nparameters = { backlash_x_um = 6.0 }\n")
    out = tmp_path / "r.html"
    assert cli_main(["report", str(simulated_csv), "--config", str(daemon_cfg), "-o", str(out), "--no-png",
                     "--feed-mm-min", f"{plan.feed_mm_min:g}", "--overshoot-deg", f"{plan.overshoot_deg:g}",
                     "--sample-hz", f"{plan.sample_hz:g}"]) == 0
    html = out.read_text()
    assert '<span class="badge" id="verdict-status">FAIL</span>' in html and 'data-status="fail"' in html
    # the limit and the margin at the value's place (0.1 um), the same words as the log's verdict
    assert re.search(r"Backlash X 7\.\d ± 0\.\d µm, limit 6\.0 µm: over by 1\.\d µm", html)
    assert "± 2 standard uncertainties" in html
    assert "<code>backlash_x_um</code>" in html  # the field name, in the statistics


def test_gcode_says_which_limits_apply(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from ballbar.daemon.cli import main as cli_main

    daemon_cfg = tmp_path / "ballbar.toml"
    daemon_cfg.write_text("[limits]\nenabled = true\nG_b_um = 25.0\nparameters = { backlash_x_um = 8.0 }\n")
    assert cli_main(["gcode", "--dialect", "fanuc", "--config", str(daemon_cfg)]) == 0
    err = capsys.readouterr().err
    assert "G_b_um <= 25 (warning above 20, 80 %)" in err and "backlash_x_um <= 8" in err


def test_the_viewers_findings_and_the_subscribers_text_show_the_verdict() -> None:
    from ballbar.daemon.rerun import findings_markdown
    from ballbar.tools.subscribe import text_line

    r = fake_result(10.1, 0.1)
    r["verdict"] = mon.evaluate(r, settings(parameters={"backlash_x_um": 10.0}, G_b_um=4.0))
    md = findings_markdown(r)
    assert md.startswith("## FAIL · test") and "### Limits: **FAIL**" in md  # G(b) 5.0 - 0.28 > 4
    # value ± k u, limit and margin at the value's place (0.1 um: the 0.1 um standard error's own place)
    assert ("| **WARNING (within uncertainty)** | Backlash X (`backlash_x_um`) | 10.1 ± 0.2 µm | 10.0 µm | "
            "over by 0.1 µm |" in md)
    plain = findings_markdown(fake_result(1.0, 0.1))
    assert plain.startswith("## NO LIMITS SET") and "### Limits" not in plain  # no limits, no verdict
    line = text_line({"kind": "alert", "t_wall": "T", "state": "fail", "cleared": False, "message": "m: x"})
    assert line == "T ALERT FAIL     m: x"
    assert text_line(r).startswith("2026-01-01T00:00:00Z TEST  m-2026-01-01T00:00:00Z: FAIL: ")


def test_a_forecast_alert_reads_as_the_view_does() -> None:
    """The forecast's line: the quantity with the plan's axes, the slope to its uncertainty in its unit per day,
    the limit at the slope's place; not ``backlash_x_um trend +1.77e+03/day crosses 8``."""
    t0 = datetime(2026, 1, 1, tzinfo=UTC)
    lim = settings(parameters={"backlash_x_um": 8.0}, min_tests=3).limits[0]
    pts = [(t0 + timedelta(days=d), 3.0 + 0.5 * d + 0.01 * (d % 2), 0.05, f"m-{d}") for d in range(6)]
    f = mon.forecast(pts, lim, "backlash_x_um", settings(parameters={"backlash_x_um": 8.0}, min_tests=3))
    assert f["significant"] and f["crossing"]
    alert = {"alert": "forecast", "machine_id": "m", "state": "due", "limit": "backlash_x_um", "forecast": f,
             "conditions": {"plan": "zx", "plane": "ZX"}, "test_id": "m-5"}
    text = mon.alert_text(alert)
    # a rate takes its quantity's resolution (0.1 um/day): the slope's 0.01 um/day standard error is shown as that step
    assert re.fullmatch(r"m plan zx: Backlash Z trend \+0\.5 ± 0\.1 µm/day crosses its limit 8\.0 µm on "
                        r"2026-01-1[01]T\S+ \(95 %: \S+ \.\. \S+\), from 6 tests to m-5", text), text
    # the view's trend sentence (analysis/monitor.py forecast_sentence): the same slope, the same limit
    from ballbar.analysis.monitor import forecast_sentence

    walls = [p[0].timestamp() for p in pts]
    words = forecast_sentence("backlash_x_um", walls, [p[1] for p in pts], 8.0, ("Z", "X"), "um")
    assert re.fullmatch(r"Backlash Z: trend \+0\.5 ± 0\.1 µm/day over 6 tests, reaches its limit 8\.0 µm about "
                        r"2026-01-1[01] \(95 %: \S+ \.\. \S+\)", words), words


# ----------------------------------------------------------------------------- per plan


def test_each_plan_has_its_limits_trend_and_alert_states(tmp_path: Path) -> None:
    """Two plans of a library: each test is held to its plan's limits, its trend is its plan's tests', its
    alerts are its plan's (a failing plan's alert neither repeats on nor clears by another plan's tests), and
    the states survive a restart; a single plan's saved states (before plans) still load."""
    glob = settings(parameters={"backlash_x_um": 10.0}, min_tests=3)
    tight = {"zx": settings(parameters={"backlash_x_um": 2.0}, min_tests=3)}
    t0 = datetime(2026, 1, 1, tzinfo=UTC)

    def result(plan: str, backlash: float, day: int) -> dict[str, Any]:
        r = fake_result(backlash, 0.01, mon.time_text(t0 + timedelta(days=day)))
        r["plan"] = {**r["plan"], "name": plan, "plane": "ZX" if plan == "zx" else "XY"}
        r["test_id"] = f"m-{plan}-{day}"
        return r

    sent: list[dict[str, Any]] = []
    m = Monitor(glob, "m", MonitorStore(tmp_path, "m"), tight)
    for day, (plan, b) in enumerate([("xy", 3.0), ("zx", 3.0), ("xy", 3.1), ("zx", 3.0), ("xy", 3.2)]):
        r = result(plan, b, day)
        r["verdict"] = m.verdict(r)
        assert r["verdict"]["status"] == ("fail" if plan == "zx" else "pass")  # 3 um: over zx's 2, under 10
        sent.extend(m.on_test(r))
    assert [(a["conditions"]["plan"], a["state"]) for a in sent] == [("zx", "fail")]  # once, though xy passed between
    assert "m plan zx: first verdict: fail" in sent[0]["message"]
    # the alert in the view's words: a ZX test's first axis is Z, the figures by the one rounding rule (a 0.01 um
    # standard error shown as the 0.1 um step)
    assert sent[0]["message"].endswith(": FAIL: Backlash Z 3.0 ± 0.1 µm, limit 2.0 µm: over by 1.0 µm (fail); "
                                       "0 of 1 limits passed"), sent[0]["message"]
    (f,) = m.forecasts(result("xy", 0.0, 9))
    assert f["n"] == 3 and all("-xy-" in tid for tid in f["test_ids"])  # xy's trend: xy's tests alone
    state = json.loads((tmp_path / "m-state.json").read_text())
    assert state["trackers"]["zx"]["verdict"] == "fail" and state["trackers"]["xy"]["verdict"] == "pass"
    assert state["tracker"]["verdict"] is None  # the default plan: no test, no verdict yet
    again = Monitor(glob, "m", MonitorStore(tmp_path, "m"), tight)  # a restart: zx's fail is not sent again
    r = result("zx", 3.0, 7)
    r["verdict"] = again.verdict(r)
    assert again.on_test(r) == []
    for a in sent:
        validate(a)
    old = tmp_path / "old"
    old.mkdir()
    (old / "m-state.json").write_text(json.dumps({"tracker": {"verdict": "warning", "better": [], "forecast": {}},
                                                  "alerts": 4}))
    m = Monitor(glob, "m", MonitorStore(old, "m"))
    assert m.tracker.state["verdict"] == "warning" and m.alert_count == 4
    assert mon.conditions(fake_result(1.0, 0.1))["plan"] == "default"  # a result of before names no plan
