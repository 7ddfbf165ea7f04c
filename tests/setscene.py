"""A live scene of a test set for the view's screenshots: three plans (XY over 360 deg, ZX and YZ over 220 deg
above the pivot) run in turn on a three-dimensional simulated machine, then XY again in progress, with each
plan's earlier tests and the set's result, as the daemon hands them to the Rerun viewer.

Each plane's test is the physical simulator's on that plane's projection of the machine (its first and second
axis take the 3D axes' errors), analysed by :class:`~ballbar.analysis.engine.TestAnalyzer` as the daemon does
and named for its plan; each test carries its verdict against its plan's limits (:mod:`livescene`'s rule, from
the plan's own figures: ``STATUS`` says which each gets), and the set is :func:`ballbar.analysis.sets.combine`
of the three.
"""

from __future__ import annotations

import copy
import datetime as dt
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import livescene
import numpy as np

from ballbar import SCHEMA_VERSION
from ballbar.analysis import monitor
from ballbar.analysis import sets as aset
from ballbar.analysis.engine import TestAnalyzer
from ballbar.analysis.plan import PLANE_AXES, MachineConfig, TestPlan
from ballbar.analysis.plans import NamedPlan, PlanLibrary, default_signature
from ballbar.daemon.samples import EventKind, SampleBatch, SourceEvent
from ballbar.tools.simulator import MachineModel, iter_chunks

BASE = dict(radius_mm=100.0, feed_mm_min=1000.0, dwell_s=0.2, sample_hz=100.0)  # at F3000, R50 a 5 deg overshoot
# leaves the loops' transient in a 220 deg arc: the analysis marks such a test invalid (the residual 6 x the noise)
PLANS = {
    "xy": TestPlan(plane="XY", overshoot_deg=30.0, **BASE),  # type: ignore[arg-type]
    "zx": TestPlan(plane="ZX", start_deg=-115.0, data_arc_deg=220.0, overshoot_deg=5.0, **BASE),  # type: ignore[arg-type]
    "yz": TestPlan(plane="YZ", start_deg=-25.0, data_arc_deg=220.0, overshoot_deg=5.0, **BASE),  # type: ignore[arg-type]
}
LIBRARY = PlanLibrary(tuple(NamedPlan(n, p, default_signature(n)) for n, p in PLANS.items()))
SET = aset.SetDefinition("machine", tuple(PLANS), 3600.0)
KV = {"X": 30.0, "Y": 33.0, "Z": 27.0}
LOST = {"X": 4.0, "Y": 2.5, "Z": 3.0}
SQUARE = {"XY": 20.0, "YZ": -10.0, "ZX": 15.0}
# each plan's verdict in the scene: the set's is the worst
STATUS = {"xy": "pass", "zx": "fail", "yz": "warning"}


def machine(plane: str) -> MachineModel:
    a, b = PLANE_AXES[plane]
    return MachineModel(kv_x_per_s=KV[a], kv_y_per_s=KV[b], backlash_x_um=LOST[a], backlash_y_um=LOST[b],
                        squareness_urad=SQUARE[plane], centre_x_um=3.0, noise_um=0.1)


@dataclass
class Scene:
    items: list[tuple[str, Any]]  # batches and messages: xy, zx, yz, the set, then xy again cut in its CCW arc
    results: dict[str, dict[str, Any]]  # each plan's complete test
    earlier: list[dict[str, Any]]  # each plan's earlier tests and an earlier set, oldest first
    config: dict[str, Any]  # the configuration's plans and sets, as recorded


def build() -> Scene:
    host0 = time.monotonic() - 300.0
    items: list[tuple[str, Any]] = []
    results: dict[str, dict[str, Any]] = {}
    t0, t_last, seq = 0.0, 0.0, 0
    first = True
    for index, name in enumerate(("xy", "zx", "yz", "xy")):
        plan = PLANS[name]
        # the scene's programs carry no signature and zx, yz take the same time: each plan is chosen, as a
        # service chooses it on the bus (the daemon's explicit choice)
        an = TestAnalyzer(plan, MachineConfig(), library=LIBRARY)
        an.choose(name)
        last = name == "xy" and "xy" in results
        for t, L in iter_chunks(plan, machine(plan.plane), plan.sample_hz, seed=7, repeat=1, chunk=4):
            t = t + t0
            t_last = float(t[-1])
            n = t.size
            events = [SourceEvent(EventKind.OPENED, host0, "sim:", detail="simulator")] if first else []
            first = False
            items.append(("batch", SampleBatch.from_columns(host0 + t, t, L, np.arange(seq, seq + n), np.zeros(n),
                                                            events, "sim:")))
            seq += n
            for msg in an.feed(t, L):
                msg["test_index"] = index + msg.get("test_index", 1)
                msg.update(machine_id="mill-3", test_id=f"mill-3-{msg['test_index']}", t_host=time.monotonic(),
                           last_sample_t=float(t[-1]), time_axis="device")
                if msg.get("event") == "feed_in":
                    msg["plan"] = name
                if "plan" in msg and isinstance(msg["plan"], dict):
                    msg["plan"] |= {"name": name, "axes": list(PLANE_AXES[plan.plane])}
                if msg["kind"] == "test":
                    msg["t_wall"] = (dt.datetime.now(dt.UTC) - dt.timedelta(minutes=30 - 5 * index)).isoformat()
                    msg["verdict"] = monitor.evaluate(msg, limits(STATUS[name], msg))
                    results[name] = msg
                items.append(("message", msg))
                if last and msg["kind"] == "circle":
                    return Scene(items, results, earlier(results), config())
        t0 = t_last + 5.0
        if name == "yz":
            items.append(("message", set_message(results)))
    raise AssertionError("the scene's last test never reached its CCW circle")


def limits(status: str, result: dict[str, Any]) -> monitor.MonitorSettings:
    return monitor.settings_from_dict(livescene.limits_for(status, result))


def set_message(results: dict[str, dict[str, Any]]) -> dict[str, Any]:
    body = aset.combine(SET, results)
    return {"schema_version": SCHEMA_VERSION, "machine_id": "mill-3",
            "t_wall": dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z"), **body}


def earlier(results: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Ten earlier tests of each plan, a day apart, drifting up to today's; and the set they made last."""
    now = dt.datetime.now(dt.UTC)
    out = []
    for i in range(10):
        for k, (name, base) in enumerate(results.items()):
            r = copy.deepcopy(base)
            drift = 0.8 + 0.02 * i
            for p in r["parameters"].values():
                if p.get("value") is not None and p.get("unit") != "deg":
                    p["value"] *= drift
            r["iso230_4"]["G_b_um"] *= drift
            r.update(test_id=f"mill-3-earlier-{name}-{i + 1}",
                     t_wall=(now - dt.timedelta(days=10 - i, minutes=10 - 3 * k)).isoformat())
            r["verdict"] = monitor.evaluate(r, limits(STATUS[name], base))
            out.append(r)
    out.append(set_message({r["plan"]["name"]: r for r in out[-3:]}))
    return out


def config() -> dict[str, Any]:
    return {"plans": {n: p.to_dict() | {"signature": default_signature(n)} for n, p in PLANS.items()},
            "sets": {SET.name: {"plans": list(SET.plans), "window_minutes": SET.window_s / 60}}}


def write_records(scene: Scene, state_dir: Path) -> Path:
    """The scene as the daemon records it, through the real MCAP logger: its configuration (each plan with its
    own limits, those the scene's verdicts come from), each plan's earlier tests (results only: their samples
    are older than the records keep), then the set's three tests and the set; the recordings directory."""
    from ballbar.daemon.mcap import McapLogger

    cfg = config()
    for name, body in cfg["plans"].items():
        body["limits"] = livescene.limits_for(STATUS[name], scene.results[name])
    logger = McapLogger(state_dir, "mill-3")
    try:
        logger.on_message({"kind": "config", "config": cfg})
        for r in scene.earlier[:-1]:
            logger.on_message(r)
        for kind, x in scene.items:
            if kind == "batch":
                logger.on_batch(x)
            else:
                logger.on_message(x)
                if x.get("kind") == "set":
                    break
    finally:
        logger.stop()
    return state_dir / "recordings"
