"""The daemon's test sets: a ``set`` result each time a set's tests are in (:mod:`ballbar.analysis.sets`).

:class:`SetListener` is an output on its own queue.  It keeps the latest test
result of each plan that a configured set (``[sets.<name>]``) names; when a
test of such a plan arrives and the latest tests of all the set's plans lie
within the set's window, it combines them (:func:`ballbar.analysis.sets.combine`)
and sends the ``kind: "set"`` message through the daemon's broadcast: the bus
publishes it on ``ballbar/<m>/result/set`` (``last/set``, ``history/set``),
the MCAP log records it on ``/ballbar/results``, the viewer shows its verdict,
the log says it in one line.  A set is sent once for each new combination of
tests: a test of one plan run again within the window makes a new set with
the others' latest.

Test results reach it after the monitor has given them their verdict (the
daemon annotates every test before it fans out), so each plan's verdict in the
set is the one published with its test.

State on disk, ``<state_dir>/sets/<machine>-sets.json`` (replaced atomically):
the latest test result of each plan of a set, and the tests of the last set
sent of each set, so a restart neither forgets the tests already run nor sends
a set again.  On the first start it is seeded from the test results and sets
in the daemon's MCAP records, if a loader is given.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

from ballbar.analysis import sets as aset
from ballbar.analysis.errors import PlanError
from ballbar.protocol.messages import stamp

from .listeners import Listener, Message, to_json
from .output import write_atomic

if TYPE_CHECKING:
    from ballbar.protocol.messages.sets import SetResult

log = logging.getLogger(__name__)


class SetListener(Listener):
    """Combines the sets' tests as they come (see the module docstring); ``bind`` gives it the broadcast."""

    name = "sets"
    batch_period_s = None
    idle_s = None

    def __init__(self, definitions: Sequence[aset.SetDefinition], machine: str,
                 state_dir: str | os.PathLike[str] | None, options: aset.SetOptions | None = None,
                 seed: Callable[[], Iterable[Mapping[str, Any]]] | None = None) -> None:
        self.definitions = list(definitions)
        self.machine = machine
        self.options = options or aset.SetOptions()
        self.plans = {p for d in self.definitions for p in d.plans}
        self.emit: Callable[[Message], None] | None = None
        self.latest: dict[str, Mapping[str, Any]] = {}  # each plan's latest test result (live, or from records)
        self.sent: dict[str, list[str | None]] = {}
        self.counters = {"tests": 0, "sets": 0, "errors": 0}
        self._lock = threading.Lock()
        self.path = Path(state_dir, "sets", f"{machine}-sets.json") if state_dir is not None else None
        if self.path is not None and self.path.exists():
            self._load()
        elif seed is not None:
            try:
                n = self.seed(seed())
            except Exception as err:  # a damaged recording must not keep the daemon from starting
                log.warning("sets: seeding from the records failed: %s", err)
            else:
                if n:
                    log.info("sets: %d earlier test results of the sets' plans from the records", n)

    @classmethod
    def from_config(cls, cfg: Any, seed: Callable[[], Iterable[Mapping[str, Any]]] | None = None
                    ) -> SetListener | None:
        """From the daemon's configuration (its recorded form's ``sets``); None when it has no set."""
        table = cfg.to_dict().get("sets") or {}
        if not table:
            return None
        defs = aset.definitions(table)
        out = cls(defs, cfg.daemon.machine_id, cfg.daemon.state_dir, seed=seed)
        log.info("sets: %s", "; ".join(f"{d.name} = {', '.join(d.plans)} within {d.window_s / 60:g} min"
                                       for d in defs))
        return out

    def bind(self, emit: Callable[[Message], None]) -> None:
        self.emit = emit

    # ------------------------------------------------------------------ state

    def _load(self) -> None:
        assert self.path is not None
        try:
            data = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as err:
            log.warning("sets: cannot read %s (%s); the sets start afresh", self.path, err)
            return
        if isinstance(data, dict):
            self.latest = {k: v for k, v in (data.get("latest") or {}).items() if k in self.plans}
            self.sent = dict(data.get("sent") or {})

    def _save(self) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        write_atomic(str(self.path), to_json({"latest": self.latest, "sent": self.sent}))

    def seed(self, messages: Iterable[Mapping[str, Any]]) -> int:
        """Earlier test results and sets (oldest first, as the records hold them): the latest test of each
        plan, and the tests of each set already sent.  Sends nothing."""
        n = 0
        for m in messages:
            if m.get("machine_id") not in (None, self.machine):
                continue
            if m.get("kind") == "test":
                name = aset.plan_name(m)
                if name in self.plans:
                    self.latest[name] = dict(m)
                    n += 1
            elif m.get("kind") == "set" and isinstance(m.get("set"), dict):
                self.sent[str(m["set"].get("name"))] = [t.get("test_id") for t in
                                                        sorted(m.get("tests") or [], key=lambda t: t.get("plan"))]
        if n:
            self._save()
        return n

    # ------------------------------------------------------------------ listener

    def on_message(self, msg: Message) -> None:
        if msg["kind"] != "test":
            return
        name = aset.plan_name(msg)
        if name not in self.plans:
            return
        with self._lock:
            self.counters["tests"] += 1
            self.latest[name] = msg
            out = []
            for d in self.definitions:
                if name not in d.plans:
                    continue
                try:
                    made = self._make(d)
                except (PlanError, ValueError, KeyError, TypeError) as err:  # one bad result must not stop the rest
                    self.counters["errors"] += 1
                    log.error("sets: set %s not combined: %s", d.name, err)
                    continue
                if made is not None:
                    out.append(made)
            try:
                self._save()
            except OSError as err:
                self.counters["errors"] += 1
                log.error("sets: cannot write %s: %s", self.path, err)
        for s in out:
            self.counters["sets"] += 1
            log.info("%s", aset.summary_lines(s)[0])
            if self.emit is not None:
                self.emit(s)

    def _make(self, d: aset.SetDefinition) -> SetResult | None:
        sel = aset.select(d, self.latest.values())
        if not sel.complete:
            log.debug("sets: %s not complete: %s", d.name, sel.why_not)
            return None
        key = list(sel.key)
        if self.sent.get(d.name) == key:
            return None
        body = aset.combine(d, sel.tests, self.options)
        self.sent[d.name] = key
        # the body is analysis/sets.py's, of SetResult's shape (the schema tests validate it)
        return cast("SetResult", {**stamp(self.machine), **body})

    def stats(self) -> dict[str, Any]:
        return dict(self.counters)

    def stop(self) -> None:
        pass


__all__ = ["SetListener"]
