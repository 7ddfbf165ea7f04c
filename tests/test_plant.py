"""A plant: several ``ballbar run --simulate`` daemons as Zenoh clients of one router.

The scenario is ``tools/bench/bench_plant.py``'s (its timings are the benchmark's; here only
what must hold): a subscriber started before the daemons gets every machine's test
results; a late one gets them from ``history``; a daemon killed with ``kill -9`` drops
out of the liveliness; the router closed and opened again is survived by the daemons and
the subscriber (results flow again, no process restarted), and a history query afterwards
holds every result the daemons logged while it was down.  Every payload received is
checked against its schema.
"""

from __future__ import annotations

from pathlib import Path

from schemacheck import validate_all

from ballbar.tools.bench.bench_plant import run

DAEMONS = 3  # each is a daemon and its simulated device: 6 processes on a 2-core machine


def test_a_plant_of_daemons_on_one_router(tmp_path: Path) -> None:
    res = run(DAEMONS, speedup=20.0, rate=100.0, down_s=10.0, tmp=tmp_path)
    assert res["late_history_machines"] == DAEMONS
    assert res["early_exit"] == 0  # the subscriber that lived through the restart stops cleanly
    assert res["results_received"] >= DAEMONS
    # the killed daemon's token went with its process (a lease would take 10 s)
    assert res["liveliness_drop_s"] < 5.0, res
    # a test takes about 9.5 s of wall time at x20: each daemon published at least one while the router was down
    assert res["published_while_down"] >= 1, res
    seen = validate_all(p for p in res["payloads"] if p["kind"] != "alive")
    assert seen["test"] >= 2 * DAEMONS and seen["event:feed_in"] >= DAEMONS, seen
