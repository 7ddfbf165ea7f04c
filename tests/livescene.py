"""A live scene for the view's screenshots: a simulated machine's tests as the daemon hands them to the Rerun
viewer, with a verdict against limits chosen to pass, warn or fail, and the machine's earlier tests.

The tests are the physical simulator's (servo mismatch, backlash, squareness, a centre offset), analysed by
:class:`~ballbar.analysis.engine.TestAnalyzer` as the daemon does, each test result annotated with its
verdict as the daemon's monitor does (:func:`ballbar.analysis.monitor.evaluate`).  The limits are set from
the last test's own figures: twice them (pass), 1.1 times (above the warning level: warning), 0.6 times
(fail).  Earlier tests are the first test's result re-dated a day apart with its values drifting up to today.
"""

from __future__ import annotations

import copy
import datetime as dt
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ballbar.analysis import monitor
from ballbar.analysis.engine import TestAnalyzer
from ballbar.analysis.plan import MachineConfig, TestPlan
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.tools.simulator import MachineModel, iter_chunks

PLAN = TestPlan(radius_mm=50.0, feed_mm_min=3000.0, overshoot_deg=30.0, dwell_s=0.2, sample_hz=100.0)
MACHINE = MachineModel(backlash_x_um=4.0, kv_x_per_s=30.0, kv_y_per_s=33.0, squareness_urad=20.0, centre_x_um=3.0,
                       noise_um=0.1)
FACTORS = {"pass": 2.0, "warning": 1.1, "fail": 0.6}


@dataclass
class Scene:
    items: list[tuple[str, Any]]  # batches and messages, the third test cut in its CCW arc
    results: list[dict[str, Any]]  # the complete tests' results


def build(n_tests: int = 2) -> Scene:
    an = TestAnalyzer(PLAN, MachineConfig())
    host0 = time.monotonic() - 200.0
    items: list[tuple[str, Any]] = []
    results = []
    seq = 0
    first = True
    for t, L in iter_chunks(PLAN, MACHINE, PLAN.sample_hz, seed=5, repeat=n_tests + 1, chunk=4):
        n = t.size
        events = [SourceEvent(EventKind.OPENED, host0, "sim:", detail="simulator")] if first else []
        first = False
        items.append(("batch", SampleBatch.from_columns(host0 + t, t, L, np.arange(seq, seq + n), np.zeros(n),
                                                        events, "sim:")))
        seq += n
        for msg in an.feed(t, L):
            msg.update(machine_id="mill-3", test_id=f"mill-3-{msg.get('test_index')}", t_host=time.monotonic(),
                       last_sample_t=float(t[-1]), time_axis="device")
            items.append(("message", msg))
            if msg["kind"] == "test":
                results.append(msg)
            if msg["kind"] == "circle" and msg.get("test_index") == n_tests + 1:
                return Scene(items, results)  # the next test in progress, its CCW circle fitted
    return Scene(items, results)


def limits_for(status: str, result: dict[str, Any]) -> dict[str, Any]:
    """A ``[limits]`` table that the result passes, warns or fails."""
    f = FACTORS[status]
    g = result["iso230_4"]["G_b_um"]
    p = result["parameters"]
    return {"enabled": True, "G_b_um": round(g * f, 1),
            "parameters": {"backlash_x_um": round(abs(p["backlash_x_um"]["value"]) * f, 2),
                           "servo_mismatch_ms": round(abs(p["servo_mismatch_ms"]["value"]) * f, 3)}}


def annotated(scene: Scene, status: str) -> tuple[list[tuple[str, Any]], list[dict[str, Any]]]:
    """The scene's items with each test result carrying its verdict, and 20 earlier tests (oldest first)."""
    settings = monitor.settings_from_dict(limits_for(status, scene.results[-1]))
    items = []
    for kind, x in scene.items:
        if kind == "message" and x.get("kind") == "test":
            x = {**x, "verdict": monitor.evaluate(x, settings)}
        items.append((kind, x))
    earlier = []
    now = dt.datetime.now(dt.UTC)
    base = scene.results[0]
    for i in range(20):
        r = copy.deepcopy(base)
        drift = 0.75 + 0.0125 * i
        for p in r["parameters"].values():
            if p.get("value") is not None and p.get("unit") != "deg":
                p["value"] *= drift
        r["iso230_4"]["G_b_um"] *= drift
        r.update(test_id=f"mill-3-earlier-{i + 1}", t_wall=(now - dt.timedelta(days=20 - i)).isoformat())
        r["verdict"] = monitor.evaluate(r, settings)
        earlier.append(r)
    return items, earlier
