"""``ballbar run``: configuration, signals, the simulated device, the listeners."""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

from .config import Config, ConfigError, load
from .errors import SourceConfigError
from .listeners import Listener
from .service import Daemon
from .sources import open_source, split_url

log = logging.getLogger(__name__)

SIM_STATE_DIR = "ballbar-state"
# The demo machine: a few faults worth seeing, each within what real machines show.
SIM_MACHINE = (
    "centre_x_um=12", "centre_y_um=-6", "backlash_x_um=4", "backlash_y_um=2.5", "kv_x_per_s=30",
    "kv_y_per_s=33", "squareness_urad=15", "spike_x_um=2", "spike_tau_x_s=0.2", "noise_um=0.1",
)


def build_listeners(cfg: Config) -> list[tuple[Listener, int, str]]:
    """The outputs the configuration turns on, each with its queue bound and drop policy."""
    out: list[tuple[Listener, int, str]] = []
    if cfg.mcap.enabled:
        from .mcap_log import McapLogger

        out.append((McapLogger.from_config(cfg), cfg.queues.mcap, "drop_newest"))
    if cfg.zenoh.enabled:
        from .bus import ZenohBus

        loader = recorded_results(cfg) if cfg.mcap.enabled else None
        out.append((ZenohBus.from_config(cfg, history_loader=loader), cfg.queues.zenoh, "drop_oldest"))
    if cfg.rerun.mode != "off":
        from .viewer import RerunViewer

        out.append((RerunViewer.from_config(cfg), cfg.queues.rerun, "drop_oldest"))
    return out


def recorded_results(cfg: Config, newest_files: int = 200) -> Callable[[], list[dict[str, Any]]]:
    """Results the daemon logged before this start (its MCAP records), for the bus's history."""

    def load() -> list[dict[str, Any]]:
        from .mcap_log import list_recordings, read_results

        directory = os.path.join(cfg.daemon.state_dir, "recordings")
        if not os.path.isdir(directory):
            return []  # a first start: nothing recorded yet
        return read_results(list_recordings(directory)[-newest_files:])

    return load


@contextlib.contextmanager
def simulated_device(cfg: Config, speedup: float) -> Iterator[str]:
    """The built-in simulated ball-bar on a pty, repeating tests; yields its source URL."""
    from ballbar.tools.simdevice import DeviceProcess

    p = cfg.plan
    args = [
        "--rate", f"{p.sample_hz:g}", "--speedup", f"{speedup:g}", "--repeat", "0", "--gap-s", "5",
        "--radius-mm", f"{p.radius_mm:g}", "--feed-mm-min", f"{p.feed_mm_min:g}", "--plane", p.plane,
        "--start-deg", f"{p.start_deg:g}", "--overshoot-deg", f"{p.overshoot_deg:g}",
        "--data-arc-deg", f"{p.data_arc_deg:g}", "--feed-in-mm", f"{p.feed_in_mm:g}",
        "--dwell-s", f"{p.dwell_s:g}", "--directions", p.directions,
    ]
    for item in SIM_MACHINE:
        args += ["--set", item]
    with DeviceProcess(*args) as dev:
        log.info("simulated ball-bar on %s (x%g speed)", dev.path, speedup)
        yield dev.url


def _overrides(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    ov: dict[str, dict[str, Any]] = {}
    if args.machine_id:
        ov.setdefault("daemon", {})["machine_id"] = args.machine_id
    if args.state_dir:
        ov.setdefault("daemon", {})["state_dir"] = args.state_dir
    elif args.simulate:
        ov.setdefault("daemon", {})["state_dir"] = SIM_STATE_DIR
    if args.source:
        ov.setdefault("source", {})["url"] = args.source
    return ov


def cmd_run(args: argparse.Namespace) -> int:
    cfg = load(args.config, args.set, overrides=_overrides(args))
    logging.getLogger().setLevel(cfg.daemon.log_level.upper())
    if args.print_config:
        json.dump(cfg.to_dict(), sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    with contextlib.ExitStack() as stack:
        url = cfg.source.url
        if args.simulate:
            url = stack.enter_context(simulated_device(cfg, args.speedup))
        _, _, query = split_url(url)
        kwargs = {} if "cal_mm" in query or not url.startswith("serial") else {"cal_mm": cfg.cal_mm}
        if url.startswith("sim:"):
            kwargs = {"plan": cfg.plan}
        try:
            source = open_source(url, **kwargs)
        except SourceConfigError as err:
            raise ConfigError(f"source.url: {err}") from err
        stack.callback(source.close)
        listeners = build_listeners(cfg)
        daemon = Daemon(cfg, source, listeners)
        return daemon.run(stop, max_tests=args.tests, duration_s=args.duration_s)
