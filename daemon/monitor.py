"""The monitor: verdicts on test results, the trend history on disk, forecasts and alerts.

The pure parts (limits, verdict, Theil-Sen trend, forecast, alert states) are
:mod:`ballbar.analysis.monitor`; this is the daemon's side.

- :meth:`MonitorListener.annotate` puts the verdict into each test result before
  it fans out (the daemon calls it on the analysis thread; it is a few dozen
  comparisons), so the published result, the MCAP record, the viewer's findings
  and the log line all carry the same verdict.
- :meth:`MonitorListener.on_message` (its own queue's thread) appends the test
  to the history, fits the trends of the limited quantities under the test's
  conditions, and sends the alerts (``kind: "alert"``) through the daemon's
  broadcast: the bus publishes them on ``ballbar/<m>/alert`` reliably, the MCAP
  log keeps them, the log says them in one line.

State on disk, under ``<state_dir>/monitor/`` (one daemon per state directory):

- ``<machine>-history.jsonl``: one line per test result (identity, ``t_wall``,
  conditions, why it is invalid for a trend if it is, the limited values with
  their standard uncertainties, the verdict's status);
- ``<machine>-alerts.jsonl``: every alert sent, which seeds ``history/alert``
  and ``last/alert`` after a restart;
- ``<machine>-state.json``: the alert states (replaced atomically), so a
  restart neither repeats an alert nor forgets one.

Everything is per plan (a library of several: analysis/plans.py): each test
is held to its plan's limits (``[plans.<name>.limits]`` over ``[limits]``),
its trend is its plan's tests', and each plan has its own alert states.

On the first start with limits (no history file yet) the history is seeded from
the test results in the daemon's MCAP records, if a loader is given: the trend
then starts from the machine's past.  Seeding sends no alerts.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
from collections.abc import Callable, Iterable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ballbar.analysis import monitor as mon
from ballbar.protocol.messages import stamp

from .listeners import Listener, Message, to_json
from .output import write_atomic

if TYPE_CHECKING:
    from ballbar.protocol.messages import Alert, Forecast, HistoryEntry, TestResult, Verdict
    from ballbar.protocol.messages.status import MonitorStats

log = logging.getLogger(__name__)

HISTORY_KEEP = 5000  # history lines read back at start (the trend needs the last trend_tests of them)
ALERTS_KEEP = 1000  # alerts read back at start (history/alert answers at most this many)


class MonitorStore:
    """The monitor's files in ``directory`` (see the module docstring)."""

    def __init__(self, directory: str | os.PathLike[str], machine: str) -> None:
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.history_path = self.dir / f"{machine}-history.jsonl"
        self.alerts_path = self.dir / f"{machine}-alerts.jsonl"
        self.state_path = self.dir / f"{machine}-state.json"

    @staticmethod
    def _read_lines(path: Path, keep: int) -> list[dict[str, Any]]:
        out: list[dict[str, Any]] = []
        try:
            with path.open(encoding="utf-8") as fh:
                for n, line in enumerate(fh, 1):
                    if not line.strip():
                        continue
                    try:
                        out.append(json.loads(line))
                    except json.JSONDecodeError:  # a line a crash cut short: the rest is good
                        log.warning("monitor: %s:%d is not JSON; skipped", path, n)
        except FileNotFoundError:
            return []
        return out[-keep:]

    @staticmethod
    def _append(path: Path, obj: Any) -> None:
        with path.open("ab") as fh:
            fh.write(to_json(obj) + b"\n")
            fh.flush()
            os.fsync(fh.fileno())

    def has_history(self) -> bool:
        return self.history_path.exists()

    def history(self) -> list[dict[str, Any]]:
        """The trend history's lines (:class:`~ballbar.protocol.messages.HistoryEntry` as written, any version)."""
        return self._read_lines(self.history_path, HISTORY_KEEP)

    def append_history(self, entry: HistoryEntry) -> None:
        self._append(self.history_path, entry)

    def alerts(self) -> list[dict[str, Any]]:
        """The alerts sent (:data:`~ballbar.protocol.messages.Alert` as sent, any version)."""
        return self._read_lines(self.alerts_path, ALERTS_KEEP)

    def append_alert(self, alert: Alert) -> None:
        self._append(self.alerts_path, alert)

    def state(self) -> dict[str, Any] | None:
        try:
            data = json.loads(self.state_path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            return None
        except (OSError, json.JSONDecodeError) as err:
            log.warning("monitor: cannot read %s (%s); alert states start afresh", self.state_path, err)
            return None
        return data if isinstance(data, dict) else None

    def save_state(self, state: dict[str, Any]) -> None:
        write_atomic(str(self.state_path), to_json(state))


class Monitor:
    """Verdicts, history, trends and alert states of one machine, without threads (the listener drives it).

    Per plan (``result["plan"]["name"]``; :data:`~ballbar.analysis.monitor.DEFAULT_PLAN` where a result has
    none): its limits (``plan_settings``, else ``settings``), its trends (the history's conditions carry the
    plan) and its alert states (``trackers``; the default plan's are saved as ``tracker``, as before plans
    were a library, the others under ``trackers``).
    """

    def __init__(self, settings: mon.MonitorSettings, machine: str, store: MonitorStore | None = None,
                 plan_settings: Mapping[str, mon.MonitorSettings] | None = None) -> None:
        self.settings = settings
        self.plan_settings = dict(plan_settings or {})
        self.machine = machine
        self.store = store
        self.history: list[Mapping[str, Any]] = list(store.history()) if store is not None else []
        self.trackers: dict[str, mon.AlertTracker] = {}
        saved = store.state() if store is not None else None
        if saved is not None:
            states = dict(saved.get("trackers") or {})
            if isinstance(saved.get("tracker"), dict):
                states[mon.DEFAULT_PLAN] = saved["tracker"]
            for name, state in states.items():
                if isinstance(state, dict):
                    self.tracker_of(name).state = state
        self.alert_count = int(saved.get("alerts", 0)) if saved else 0
        self.last_forecasts: list[Forecast] = []  # the last valid test's (none after an invalid one)

    def settings_of(self, result: Mapping[str, Any]) -> mon.MonitorSettings:
        """The limits the result's plan is held to."""
        return self.plan_settings.get(mon.plan_of(result), self.settings)

    def tracker_of(self, plan: str) -> mon.AlertTracker:
        if plan not in self.trackers:
            self.trackers[plan] = mon.AlertTracker(self.plan_settings.get(plan, self.settings).clear_after)
        return self.trackers[plan]

    @property
    def tracker(self) -> mon.AlertTracker:
        """The default plan's alert states (a single [plan])."""
        return self.tracker_of(mon.DEFAULT_PLAN)

    def _state(self) -> dict[str, Any]:
        out: dict[str, Any] = {"tracker": self.tracker.state}
        others = {n: t.state for n, t in self.trackers.items() if n != mon.DEFAULT_PLAN}
        if others:
            out["trackers"] = others
        return out | {"alerts": self.alert_count}

    def seed(self, results: Iterable[Mapping[str, Any]]) -> int:
        """Earlier test results (oldest first) into an empty history; no alerts.  Returns how many."""
        n = 0
        for r in results:
            if r.get("kind") != "test" or not r.get("t_wall") or r.get("machine_id") not in (None, self.machine):
                continue
            entry = mon.history_entry(r, r.get("verdict") or mon.evaluate(r, self.settings_of(r)), str(r["t_wall"]))
            self.history.append(entry)
            if self.store is not None:
                self.store.append_history(entry)
            n += 1
        return n

    def verdict(self, result: Mapping[str, Any]) -> Verdict:
        v = mon.evaluate(result, self.settings_of(result))
        why = mon.validity(result)
        if why is not None:
            v["trend_excluded"] = why
        return v

    def forecasts(self, result: Mapping[str, Any]) -> list[Forecast]:
        cond = mon.conditions(result)
        settings = self.settings_of(result)
        out = []
        for lim, name in settings.quantities():
            pts = mon.points(self.history, name, cond, settings)
            out.append(mon.forecast(pts, lim, name, settings))
        return out

    def on_test(self, result: Mapping[str, Any]) -> list[Alert]:
        """A test result (with its verdict, or one is computed): history, forecasts, and the alerts to send."""
        verdict: Verdict = result.get("verdict") or self.verdict(result)
        t_wall = str(result.get("t_wall") or mon.time_text(datetime.now(UTC)))
        entry = mon.history_entry(result, verdict, t_wall)
        self.history.append(entry)
        del self.history[:-mon_history_keep(self.settings_of(result))]
        if self.store is not None:
            self.store.append_history(entry)
        # An invalid test gives a verdict but changes no trend: its forecasts would be the previous test's.
        forecasts = self.forecasts(result) if entry["invalid"] is None else []
        self.last_forecasts = forecasts
        changes = self.tracker_of(mon.plan_of(result)).update(verdict, forecasts)
        by_name = {f["name"]: f for f in forecasts}
        alerts: list[Alert] = []
        for ch in changes:
            self.alert_count += 1
            alert_id = f"{self.machine}-alert-{self.alert_count}"
            a: Alert
            if ch["alert"] == "verdict":
                a = {**stamp(self.machine), "kind": "alert", "alert_id": alert_id, "alert": "verdict",
                     "state": ch["state"], "previous": ch["previous"], "cleared": ch["cleared"],
                     "test_id": result.get("test_id"), "t_test": t_wall, "conditions": entry["conditions"],
                     "verdict": verdict, "message": ""}
            else:
                a = {**stamp(self.machine), "kind": "alert", "alert_id": alert_id, "alert": "forecast",
                     "state": ch["state"], "previous": ch["previous"], "cleared": ch["cleared"], "limit": ch["limit"],
                     "test_id": result.get("test_id"), "t_test": t_wall, "conditions": entry["conditions"],
                     "forecast": by_name[ch["limit"]], "message": ""}
            a["message"] = mon.alert_text(a)
            alerts.append(a)
            if self.store is not None:
                self.store.append_alert(a)
        if self.store is not None:
            self.store.save_state(self._state())
        return alerts


def mon_history_keep(settings: mon.MonitorSettings) -> int:
    return max(HISTORY_KEEP, 10 * settings.trend_tests)


class MonitorListener(Listener):
    """The monitor as a daemon output: annotates test results, keeps the history, sends alerts.

    ``emit`` (the daemon's broadcast) is bound by the daemon (:meth:`bind`);
    until then alerts only go to the log and the store.
    """

    name = "monitor"
    batch_period_s = None
    idle_s = None

    def __init__(self, monitor: Monitor, emit: Callable[[Message], None] | None = None) -> None:
        self.monitor = monitor
        self.emit = emit
        self.counters = {"tests": 0, "alerts": 0, "errors": 0}
        self._lock = threading.Lock()

    @classmethod
    def from_config(cls, cfg: Any, seed: Callable[[], Iterable[Mapping[str, Any]]] | None = None
                    ) -> MonitorListener:
        from .config import monitor_settings

        settings = monitor_settings(cfg)
        plan_settings = {name: monitor_settings(cfg, name) for name in cfg.plans if cfg.plans[name].limits}
        store = MonitorStore(os.path.join(cfg.daemon.state_dir, "monitor"), cfg.daemon.machine_id)
        fresh = not store.has_history()
        monitor = Monitor(settings, cfg.daemon.machine_id, store, plan_settings)
        if fresh and seed is not None:
            try:
                n = monitor.seed(seed())
            except Exception as err:  # a damaged recording must not keep the daemon from starting
                log.warning("monitor: seeding the history from the records failed: %s", err)
            else:
                if n:
                    log.info("monitor: history seeded with %d earlier test results", n)
        with contextlib.suppress(OSError):
            store.history_path.touch()
        log.info("monitor: limits %s; %d tests in the history", "; ".join(settings.describe()) or "none",
                 len(monitor.history))
        for name, ps in plan_settings.items():
            log.info("monitor: plan %s's own limits %s", name, "; ".join(ps.describe()))
        return cls(monitor, None)

    def bind(self, emit: Callable[[Message], None]) -> None:
        self.emit = emit

    def annotate(self, msg: TestResult) -> TestResult:
        """The test result with its ``verdict`` (none where its plan's limits are off)."""
        if "verdict" in msg or not self.monitor.settings_of(msg).enabled:
            return msg
        try:
            return {**msg, "verdict": self.monitor.verdict(msg)}
        except Exception:  # runs on the analysis thread: a bug here must not cost the result itself
            self.counters["errors"] += 1
            log.exception("monitor: no verdict for test %s", msg["test_id"])
        return msg

    def alert_history(self) -> list[dict[str, Any]]:
        return self.monitor.store.alerts() if self.monitor.store is not None else []

    def on_message(self, msg: Message) -> None:
        if msg["kind"] != "test":
            return
        with self._lock:
            self.counters["tests"] += 1
            try:
                alerts = self.monitor.on_test(msg)
            except OSError as err:
                self.counters["errors"] += 1
                log.error("monitor: cannot write its state: %s", err)
                return
        for a in alerts:
            self.counters["alerts"] += 1
            log.warning("alert: %s", a["message"])
            if self.emit is not None:
                self.emit(a)

    def stats(self) -> MonitorStats:
        return {"tests": self.counters["tests"], "alerts": self.counters["alerts"], "errors": self.counters["errors"],
                "history": len(self.monitor.history)}

    def stop(self) -> None:
        pass


__all__ = ["Monitor", "MonitorListener", "MonitorStore"]
