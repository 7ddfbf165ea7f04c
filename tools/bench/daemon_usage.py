"""The daemon bench's figures (:mod:`.bench_daemon`): snapshots of a process' counters from ``/proc`` (read with
:mod:`ballbar.daemon.procfs`), the CPU and context switches between two of them per thread name, and the
statistics of a run (slopes, distributions).
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from ballbar.daemon import procfs

CLK_TCK = procfs.CLK_TCK


# ----------------------------------------------------------------------------- /proc


@dataclass(frozen=True)
class TaskTimes:
    """One thread's counters: CPU ticks (utime + stime) and context switches."""

    comm: str
    ticks: int
    voluntary: int
    nonvoluntary: int


@dataclass
class ProcSnapshot:
    """One process at one moment: its CPU ticks (the whole thread group, exited threads included),
    resident memory and each live thread's counters."""

    pid: int
    t: float  # time.monotonic() when taken
    comm: str
    ticks: int
    rss_kib: int
    tasks: dict[int, TaskTimes] = field(default_factory=dict)


def snapshot(pid: int) -> ProcSnapshot | None:
    """The process's counters now, or ``None`` if it has gone."""
    t = time.monotonic()
    try:
        comm, fields = procfs.stat(pid)
        rss = procfs.kib(procfs.status(pid).get("VmRSS", "0 kB"))
        tids = procfs.threads(pid)
    except (OSError, ValueError, IndexError):
        return None
    snap = ProcSnapshot(pid, t, comm, procfs.cpu_ticks(fields), rss)
    for name in tids:
        try:
            tcomm, tfields = procfs.stat(pid, name)
            st = procfs.status(pid, name)
        except (OSError, ValueError, IndexError):
            continue  # the thread exited meanwhile
        snap.tasks[int(name)] = TaskTimes(
            tcomm, procfs.cpu_ticks(tfields), int(st.get("voluntary_ctxt_switches", "0")),
            int(st.get("nonvoluntary_ctxt_switches", "0")),
        )
    return snap


def rss_mib(pid: int) -> float | None:
    try:
        return procfs.rss_bytes(pid) / float(1 << 20)
    except (OSError, ValueError, KeyError):
        return None


def descendants(pid: int) -> list[int]:
    """Children, grandchildren, ... of ``pid`` (``/proc/PID/task/*/children``)."""
    out: list[int] = []
    todo = [pid]
    while todo:
        with contextlib.suppress(OSError):
            kids = procfs.children(todo.pop())
            out += kids
            todo += kids
    return out


def usage(a: ProcSnapshot, b: ProcSnapshot) -> dict[str, Any]:
    """CPU (% of one core) and context switches per second between two snapshots of one process,
    in total and per thread name (threads of one name summed; a thread born inside the window
    counts from zero; one that exited inside it counts only in the process's CPU)."""
    dt = b.t - a.t
    if dt <= 0:
        raise ValueError("snapshots out of order")
    zero = TaskTimes("", 0, 0, 0)
    groups: dict[str, dict[str, float]] = {}
    vol = nonvol = 0
    for tid, tb in b.tasks.items():
        ta = a.tasks.get(tid, zero)
        d_ticks, d_vol, d_non = tb.ticks - ta.ticks, tb.voluntary - ta.voluntary, tb.nonvoluntary - ta.nonvoluntary
        vol += d_vol
        nonvol += d_non
        g = groups.setdefault(tb.comm, {"threads": 0, "ticks": 0, "voluntary": 0, "nonvoluntary": 0})
        g["threads"] += 1
        g["ticks"] += d_ticks
        g["voluntary"] += d_vol
        g["nonvoluntary"] += d_non
    threads: list[dict[str, Any]] = [
        {
            "name": name, "threads": int(g["threads"]),
            "cpu_pct": 100.0 * g["ticks"] / CLK_TCK / dt,
            "ctx_per_s": (g["voluntary"] + g["nonvoluntary"]) / dt,
            "voluntary_per_s": g["voluntary"] / dt, "nonvoluntary_per_s": g["nonvoluntary"] / dt,
        }
        for name, g in groups.items()
    ]
    threads.sort(key=lambda r: (-r["cpu_pct"], -r["ctx_per_s"], r["name"]))
    return {
        "pid": b.pid, "comm": b.comm, "seconds": dt,
        "cpu_pct": 100.0 * (b.ticks - a.ticks) / CLK_TCK / dt,
        "ctx_per_s": (vol + nonvol) / dt, "voluntary_per_s": vol / dt, "nonvoluntary_per_s": nonvol / dt,
        "threads_start": len(a.tasks), "threads_end": len(b.tasks),
        "threads_exited": len(set(a.tasks) - set(b.tasks)), "threads_born": len(set(b.tasks) - set(a.tasks)),
        "threads": threads,
    }


# ----------------------------------------------------------------------------- statistics


def slope_per_min(t_s: Sequence[float], y: Sequence[float]) -> float | None:
    """Least-squares slope of ``y`` against ``t_s`` (seconds), per minute; None with fewer than 3 points."""
    import numpy as np

    t = np.asarray(t_s, float)
    v = np.asarray(y, float)
    ok = np.isfinite(t) & np.isfinite(v)
    if ok.sum() < 3 or np.ptp(t[ok]) <= 0:
        return None
    return float(np.polyfit(t[ok] / 60.0, v[ok], 1)[0])


def distribution(values: Iterable[float | None]) -> dict[str, Any]:
    """n, min, median, p99, max and mean of the finite values (p99 interpolated: with few values it is
    close to the largest)."""
    import numpy as np

    v = np.array([x for x in values if x is not None and math.isfinite(x)], float)
    if v.size == 0:
        return {"n": 0}
    return {
        "n": int(v.size), "min": float(v.min()), "median": float(np.median(v)),
        "p99": float(np.percentile(v, 99)), "max": float(v.max()), "mean": float(v.mean()),
    }


def _restarts(statuses: Sequence[dict[str, Any]], t0: float) -> list[float]:
    """When (s from ``t0``, the status that first showed it) the daemon's Rerun server was restarted."""
    out, last = [], None
    for st in statuses:
        n = (st.get("rerun_server") or {}).get("restarts")
        if isinstance(n, int):
            if last is not None and n > last:
                out.append(round(st["rx"] - t0, 1))
            last = n
    return out


def rss_summary(t_s: Sequence[float], mib: Sequence[float]) -> dict[str, Any]:
    if not t_s:
        return {"samples": 0}
    return {
        "samples": len(t_s), "start_mib": mib[0], "end_mib": mib[-1], "max_mib": max(mib),
        "slope_mib_per_min": slope_per_min(t_s, mib),
    }
