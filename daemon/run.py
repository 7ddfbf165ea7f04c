"""``ballbar run``: configuration, signals, the simulated device, the listeners."""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import logging
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from .analysis_worker import freeze_long_lived
from .config import Config, ConfigError, check_addresses, load
from .errors import SourceConfigError
from .listeners import MERGE_S, DropPolicy, Listener, Message
from .lock import StateLock
from .samples import SampleBatch
from .service import Daemon
from .sources import Source, open_source, split_url

if TYPE_CHECKING:
    from ballbar.protocol.messages.events import TestIncomplete

log = logging.getLogger(__name__)

SIM_STATE_DIR = "ballbar-state"
#: ``--simulate``'s limits, a layer under the configuration (any ``[limits]`` key configured wins, so
#: ``limits.enabled = false`` turns them off), so that its machines get a verdict: lost motion and a gain mismatch
#: an engineer would send for repair, squareness as ``systemd/ballbar.toml.example`` has it.  The passing
#: machine's are well within them, the failing one's well over.
SIM_LIMITS: dict[str, Any] = {
    "enabled": True,
    "parameters": {"backlash_x_um": 8.0, "backlash_y_um": 8.0, "servo_mismatch_ms": 8.0, "squareness_urad": 50.0},
}


class StoppedInStartUp(Exception):
    """A stop (SIGTERM, SIGINT) came while the outputs were being started: those started are stopped again."""


def _stopped_in_start_up() -> int:
    log.info("stopped during start-up, before it was ready")
    return 0


def build_listeners(cfg: Config, stop: threading.Event | None = None) -> list[tuple[Listener, int, DropPolicy]]:
    """The outputs the configuration turns on, each with its queue bound and drop policy.

    If one fails to start, those already started are stopped before the error
    goes on: a Zenoh session left open would keep the process alive.  So they
    are when ``stop`` is set between two of them (:class:`StoppedInStartUp`).
    """

    def check() -> None:
        if stop is not None and stop.is_set():
            raise StoppedInStartUp

    out: list[tuple[Listener, int, DropPolicy]] = []
    try:
        loader: Callable[[], list[dict[str, Any]]] | None = None
        if cfg.mcap.enabled:
            from .mcap import McapLogger

            logger = McapLogger.from_config(cfg)
            out.append((logger, cfg.queues.mcap, "drop_newest"))
            check()
            spooled = [m for m in logger.spooled if m.get("kind") in ("circle", "test")]  # held by the last run
            loader = _chain(recorded_results(cfg), lambda: spooled)
        if cfg.limits_enabled:  # before the bus: its history/alert is seeded from the monitor's store
            from .monitor import MonitorListener

            monitor = MonitorListener.from_config(cfg, seed=recorded_results(cfg) if cfg.mcap.enabled else None)
            out.append((monitor, 1000, "drop_newest"))
            check()
            alerts = monitor.alert_history
            loader = _chain(loader, alerts) if loader is not None else alerts
        if cfg.to_dict().get("sets"):  # the sets' results, sent through the broadcast like the alerts
            from .sets import SetListener

            sets = SetListener.from_config(cfg, seed=recorded_results(cfg) if cfg.mcap.enabled else None)
            if sets is not None:
                out.append((sets, 1000, "drop_newest"))
        if cfg.zenoh.enabled:
            from .bus import ZenohBus

            out.append((ZenohBus.from_config(cfg, history_loader=loader), cfg.queues.zenoh, "drop_oldest"))
            check()
        if cfg.rerun.mode != "off":
            # the viewer's own period (MERGE_S), which its queue needs before Rerun is imported
            out.append((StartedLater("rerun", lambda: _rerun_viewer(cfg), batch_period_s=MERGE_S),
                        cfg.queues.rerun, "drop_oldest"))
        check()
    except BaseException:
        for listener, _cap, _policy in reversed(out):
            try:
                listener.stop()
            except Exception:
                log.exception("stopping %s after a failed start", listener.name)
        raise
    return out


def _chain(*loaders: Callable[[], list[dict[str, Any]]]) -> Callable[[], list[dict[str, Any]]]:
    return lambda: [m for load in loaders for m in load()]


def _rerun_viewer(cfg: Config) -> Listener:
    from .rerun import RerunViewer

    return RerunViewer.from_config(cfg)


class StartedLater(Listener):
    """A listener made on its own queue's thread when the first item (or idle tick) reaches it.

    For the Rerun viewer: importing Rerun and starting its recording take about half a
    second, which READY=1 does not wait for; what arrives meanwhile waits in the queue.
    If it cannot be made, that is logged once and everything sent to it is dropped
    (the daemon's other outputs run on).  ``batch_period_s`` and ``idle_s`` are
    the made listener's, which its queue needs before it exists (without them
    the viewer was woken for every 20 ms batch instead of four times a second).
    """

    def __init__(self, name: str, make: Callable[[], Listener], batch_period_s: float | None = 0.0,
                 idle_s: float | None = 1.0) -> None:
        self.name = name
        self.batch_period_s = batch_period_s
        self.idle_s = idle_s
        self._make = make
        self._inner: Listener | None = None
        self._failed = False
        self._stopped = False
        self._cancelled = False  # the daemon is stopping: never made from now on (no lock: a start may hold it)
        self._lock = threading.Lock()

    def cancel_start(self) -> None:
        self._cancelled = True

    def _listener(self) -> Listener | None:
        if self._inner is None and not self._failed and not self._cancelled:
            with self._lock:
                if self._inner is None and not self._failed and not self._stopped and not self._cancelled:
                    t0 = time.monotonic()
                    try:
                        self._inner = self._make()
                    except Exception:
                        self._failed = True
                        log.exception("%s: could not start; its output is off", self.name)
                    else:
                        log.debug("%s: started in %.2f s", self.name, time.monotonic() - t0)
                        freeze_long_lived()  # its imports and set-up are for good too
        return self._inner

    def on_batch(self, batch: SampleBatch) -> None:
        if (inner := self._listener()) is not None:
            inner.on_batch(batch)

    def on_message(self, msg: Message) -> None:
        if (inner := self._listener()) is not None:
            inner.on_message(msg)

    def on_idle(self) -> None:
        if (inner := self._listener()) is not None:
            inner.on_idle()

    def stats(self) -> dict[str, Any]:
        inner = self._inner
        stats = getattr(inner, "stats", None)
        if callable(stats):
            out: dict[str, Any] = stats()
            return out
        return {"state": "failed" if self._failed else "starting"}

    def stop(self) -> None:
        with self._lock:  # waits for a start in progress: what it started is stopped too
            self._stopped = True
            inner = self._inner
        if inner is not None:
            inner.stop()


def preflight(cfg: Config, url: str, source_options: dict[str, Any]) -> None:
    """Check what the outputs and the source will be given, before any of them opens.

    Each problem is a :class:`ConfigError` naming its key (exit code 2).
    """
    from .sources import check_source

    try:
        check_source(url, **source_options)
    except SourceConfigError as err:
        raise ConfigError(f"source.url: {err}") from None
    if cfg.zenoh.enabled:
        from .bus import BusConfigError, check_endpoints, check_machine, zenoh_config

        try:
            check_machine(cfg.daemon.machine_id)
            check_endpoints(zenoh_config(cfg))
        except BusConfigError as err:
            raise ConfigError(str(err)) from None
    if cfg.rerun.mode != "off":
        from .rerun import ViewerConfigError, rerun_binary, viewer_options  # without Rerun itself

        try:
            options = viewer_options(cfg)
        except ViewerConfigError as err:
            raise ConfigError(str(err)) from None
        if options.mode == "serve" and rerun_binary() is None:
            raise ConfigError('rerun.mode = "serve" needs the rerun binary of rerun-sdk (rerun_cli)')
        check_addresses(cfg)
    if cfg.mcap.enabled:
        _check_writable(os.path.join(cfg.daemon.state_dir, "recordings"))
    if cfg.controller is not None:
        import importlib.util

        if importlib.util.find_spec("asyncua") is None:
            raise ConfigError('[controller] needs the OPC UA client asyncua: pip install "ballbar[controller]"')


def _check_writable(directory: str) -> None:
    try:
        os.makedirs(directory, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".probe-", dir=directory)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise ConfigError(f"daemon.state_dir: cannot write {directory}: {err.strerror or err}") from None


def recorded_results(cfg: Config, newest_files: int = 200) -> Callable[[], list[dict[str, Any]]]:
    """Results the daemon logged before this start (its MCAP records), for the bus's history."""

    def load() -> list[dict[str, Any]]:
        from .mcap import list_recordings, read_results

        directory = os.path.join(cfg.daemon.state_dir, "recordings")
        if not os.path.isdir(directory):
            return []  # a first start: nothing recorded yet
        return read_results(list_recordings(directory)[-newest_files:])

    return load


def simulated_plans(cfg: Config) -> list[str]:
    """What ``--simulate`` runs of a library of several plans: its first set's plans, else all its plans, in
    turn; empty for a single plan (the demo machine runs it)."""
    if len(cfg.library) < 2:
        return []
    return list(next(iter(cfg.sets.values())).plans) if cfg.sets else list(cfg.library.names)


def _overrides(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    ov: dict[str, dict[str, Any]] = {}
    # "is not None": an empty value given on the command line is a mistake to report, not "unset"
    if args.machine_id is not None:
        ov.setdefault("daemon", {})["machine_id"] = args.machine_id
    if args.state_dir is not None:
        ov.setdefault("daemon", {})["state_dir"] = args.state_dir
    elif args.simulate:
        ov.setdefault("daemon", {})["state_dir"] = SIM_STATE_DIR
    if args.source is not None:
        ov.setdefault("source", {})["url"] = args.source
    return ov


def simulate_sentence(args: argparse.Namespace, cfg: Config) -> str:
    """The one line ``--simulate`` logs at start: which machine, where its state goes instead of the configured
    ``daemon.state_dir`` and why, and which limits it is held to."""
    state = os.path.abspath(cfg.daemon.state_dir)
    where = (f"state in {state} (--state-dir)" if args.state_dir is not None else
             f"state in {state}, not daemon.state_dir, to keep simulated tests out of a real machine's records "
             f"(--state-dir to choose)")
    changed = "".join(f", {item}" for item in (*args.sim_set, *(f"{d} per test" for d in args.sim_drift)))
    if not cfg.limits_enabled:
        held = "limits off (limits.enabled = false configured): no verdicts"
    elif cfg.limits.enabled and cfg.limits.parameters == SIM_LIMITS["parameters"] and not any(
            (cfg.limits.G_um, cfg.limits.G_b_um, cfg.limits.H_um)):
        limits = ", ".join(f"{k} {v:g}" for k, v in SIM_LIMITS["parameters"].items())
        held = f"no limits configured, so the simulated machine's: {limits}"
    else:
        held = "held to the configured limits"
    return f"simulating a {args.simulate} machine{changed} at x{args.speedup:g}; {where}; {held}"


def _recover(cfg: Config) -> list[TestIncomplete]:
    """Files a killed daemon left without a footer, rewritten once; a ``test_incomplete`` event for each
    test the crash cut, to publish at start (stamped again as it goes out)."""
    if not cfg.mcap.enabled:
        return []
    from ballbar.protocol.messages import stamp

    from .mcap import recover_crashed

    out: list[TestIncomplete] = []
    for r in recover_crashed(os.path.join(cfg.daemon.state_dir, "recordings")):
        if r.cut_test is None or r.outcome:  # (a test whose result was recorded though its file was cut: complete)
            continue
        if r.outage:
            why = f"the disk could not be written during this test ({r.outage}) and its outcome was never recorded"
        else:
            why = "the daemon stopped (killed) during this test"
        out.append({
            **stamp(cfg.daemon.machine_id), "kind": "event", "event": "test_incomplete", "origin": "recovery",
            "test_id": r.cut_test.get("test_id"), "t_host": time.monotonic(), "file": r.path.name,
            "message": f"{why}; its samples up to then are in {r.path.name}",
        })
    return out


def _source_options(cfg: Config, url: str) -> dict[str, Any]:
    try:
        _, _, query = split_url(url)
    except SourceConfigError as err:
        raise ConfigError(f"source.url: {err}") from None
    if url.startswith("sim:"):
        names = simulated_plans(cfg)
        return {"plan": cfg.plan, "library": cfg.library, "run_plans": names} if names else {"plan": cfg.plan}
    return {} if "cal_mm" in query or not url.startswith("serial") else {"cal_mm": cfg.cal_mm}


def cmd_run(args: argparse.Namespace, stop: threading.Event | None = None) -> int:
    """``ballbar run``; ``stop`` is the event the caller's SIGTERM and SIGINT handlers set."""
    if stop is None:
        stop = threading.Event()
    if not args.simulate and (args.sim_set or args.sim_drift):
        raise ConfigError("--sim-set and --sim-drift change the simulated machine: they need --simulate")
    # --simulate's limits under every layer but the shipped defaults: any [limits] key configured wins
    cfg = load(args.config, args.set, overrides=_overrides(args),
               base={"limits": SIM_LIMITS} if args.simulate else None)
    logging.getLogger().setLevel(cfg.daemon.log_level.upper())
    if args.print_config:
        from .secrets import redacted

        json.dump(redacted(cfg.to_dict()), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    url = "sim:" if args.simulate else cfg.source.url  # the simulated device's pty comes later
    if getattr(args, "simulate_cnc", False):
        if not args.simulate:
            raise ConfigError("--simulate-cnc goes with --simulate")
        from .config import ControllerSection

        # its endpoint comes when it runs: a placeholder that passes the checks until then
        cfg.controller = cfg.controller or ControllerSection(endpoint="opc.tcp://127.0.0.1:4840")
    preflight(cfg, url, _source_options(cfg, url))
    if stop.is_set():
        return 0
    with contextlib.ExitStack() as stack:
        stack.enter_context(StateLock(cfg.daemon.state_dir))
        source: Source
        if args.simulate:
            from . import plugins

            log.info("%s", simulate_sentence(args, cfg))
            simulated_device: plugins.SimulatedDevice = plugins.load(plugins.SIMULATED, "device")
            source = stack.enter_context(
                simulated_device(cfg, args.speedup, args.simulate, tuple(args.sim_set), tuple(args.sim_drift)))
            cfg.source.url = source.url  # the configuration published says what is read: the device's pty
            if getattr(args, "simulate_cnc", False) and cfg.controller is not None:
                simulated_cnc: plugins.SimulatedCnc = plugins.load(plugins.SIMULATED, "cnc")
                cfg.controller.endpoint = stack.enter_context(simulated_cnc(cfg))
        else:
            try:
                source = open_source(url, **_source_options(cfg, url))
            except SourceConfigError as err:
                raise ConfigError(f"source.url: {err}") from err
            stack.callback(source.close)
        if stop.is_set():
            return _stopped_in_start_up()
        cut = _recover(cfg)  # before the bus reads the history from the recordings
        if stop.is_set():
            return _stopped_in_start_up()
        if cfg.mcap.enabled:  # after recovery: the last recorded sample, to count what the restart lost
            from .restarts import resume_count, save_counter

            resume_count(cfg.daemon.state_dir, source)
        try:
            listeners = build_listeners(cfg, stop)
        except StoppedInStartUp:
            return _stopped_in_start_up()
        controller = None
        if cfg.controller is not None:
            from .controller import ControllerClient

            controller = ControllerClient(cfg.controller, cfg.daemon.machine_id)
        daemon = Daemon(cfg, source, listeners, speedup=args.speedup if args.simulate else 1.0,
                        controller=controller)
        if cfg.mcap.enabled:
            daemon.on_device_reset = functools.partial(save_counter, cfg.daemon.state_dir, source)
        daemon.startup_messages.extend(cut)
        return daemon.run(stop, max_tests=args.tests, duration_s=args.duration_s)
