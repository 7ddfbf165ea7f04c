"""The simulated ball-bar of ``ballbar run --simulate [MACHINE]``: the device process on a pty (:mod:`.simdevice`)
running a named machine (:data:`MACHINES`), and the daemon's source that opens it once it is up.  The daemon finds
:func:`simulated_device` as the ``device`` plug-in of ``ballbar.daemon.plugins.SIMULATED``.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import tempfile
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields

from ballbar.daemon.config import Config, ConfigError
from ballbar.daemon.errors import SourceClosed, SourceError
from ballbar.daemon.run import simulated_plans
from ballbar.daemon.samples import SampleBatch, SourceStats
from ballbar.daemon.sources import Source, open_source

from .simbar import Settings
from .simdevice import DeviceProcess, source_url

log = logging.getLogger(__name__)

# The demo machine: a few faults worth seeing, each within what real machines show.
SIM_MACHINE = (
    "centre_x_um=12", "centre_y_um=-6", "backlash_x_um=4", "backlash_y_um=2.5", "kv_x_per_s=30",
    "kv_y_per_s=33", "squareness_urad=15", "spike_x_um=2", "spike_tau_x_s=0.2", "noise_um=0.1",
)
# The demo machine of a set (tools/machine3d.py): each axis its own lost motion and gain, the three squareness
# errors, the pivot a little off in each axis.
SIM_MACHINE_3D = (
    "centre_x_um=12", "centre_y_um=-6", "centre_z_um=5", "backlash_x_um=4", "backlash_y_um=2.5", "backlash_z_um=3",
    "kv_x_per_s=30", "kv_y_per_s=33", "kv_z_per_s=28", "squareness_xy_urad=15", "squareness_yz_urad=-10",
    "squareness_zx_urad=20", "spike_x_um=2", "spike_tau_x_s=0.2", "noise_um=0.1",
)


@dataclass(frozen=True)
class NamedMachine:
    """A machine of ``ballbar run --simulate MACHINE``: its keys over the demo machine's (``KEY=VALUE``, the same
    for the plane's and the 3D machine: ``_x`` is X, ``_y`` Y), and what changes by how much per test."""

    changes: tuple[str, ...] = ()
    drift: tuple[str, ...] = ()


#: The machines against the daemon's simulated limits (``ballbar.daemon.run.SIM_LIMITS``: backlash 8 um, servo
#: mismatch 8 ms, squareness 50 urad).  Passing: the demo machine (a servo mismatch of 3 ms, X backlash 4 um).
#: Failing: X backlash 12 um and gains of 25 and 35 1/s (X lags Y by 11 ms), the two faults a ball-bar is most
#: often sent for.  Wearing: the demo machine whose X backlash grows 0.5 um and Y gain 0.5 1/s a test (its servo
#: mismatch about 0.4 ms a test): a warning from about the 6th test, a forecast once the trend is significant
#: (``limits.min_tests``, the 6th), a fail at the 10th (its servo mismatch at about the 14th).
MACHINES: dict[str, NamedMachine] = {
    "passing": NamedMachine(),
    "failing": NamedMachine(changes=("backlash_x_um=12", "kv_x_per_s=25", "kv_y_per_s=35")),
    "wearing": NamedMachine(drift=("backlash_x_um=0.5", "kv_y_per_s=0.5")),
}


def check_machine(three_d: bool, sets: Sequence[str], drifts: Sequence[str]) -> None:
    """A :class:`ConfigError` naming ``--sim-set`` or ``--sim-drift`` for an unknown machine key or a bad value
    (before the device starts, whose own message would only be on its stderr)."""
    from ballbar.analysis.errors import PlanError

    from .machine3d import Machine3D, machine_keys
    from .simfeed import _floats
    from .simulator import MachineModel
    from .simulator_cli import parse_set

    demo = SIM_MACHINE_3D if three_d else SIM_MACHINE
    try:
        if three_d:
            Machine3D.from_settings(_floats((*demo, *sets), "--sim-set"))
        else:
            MachineModel(**parse_set((*demo, *sets)))
    except PlanError as err:
        raise ConfigError(f"--sim-set: {err}") from None
    try:
        steps = _floats(drifts, "--sim-drift")
    except PlanError as err:
        raise ConfigError(str(err)) from None
    known = machine_keys() if three_d else {f.name for f in fields(MachineModel)}
    for key in steps:
        if key not in known:
            raise ConfigError(f"--sim-drift: unknown machine key {key!r} (known: {', '.join(sorted(known))})")


def simdevice_args(cfg: Config, speedup: float, machine: str = "passing", sets: Sequence[str] = (),
                   drifts: Sequence[str] = ()) -> list[str]:
    """``python -m ballbar.tools.simdevice`` arguments: the named machine (:data:`MACHINES`) with ``sets`` over its
    keys and ``drifts`` added to its wear, running the configured plan, forever; with a library of several plans,
    the 3D demo machine so changed running its set (:func:`simulated_plans`), each program with its signature."""
    p = cfg.plan
    named = MACHINES[machine]
    wear = [a for item in (*named.drift, *drifts) for a in ("--drift", item)]
    if simulated_plans(cfg):
        args = ["--rate", f"{p.sample_hz:g}", "--speedup", f"{speedup:g}", "--repeat", "0", "--gap-s", "5",
                "--library", json.dumps(cfg.to_dict()["plans"]), "--run-plans", ",".join(simulated_plans(cfg))]
        for item in (*SIM_MACHINE_3D, *named.changes, *sets):
            args += ["--set", item]
        return args + wear
    args = [
        "--rate", f"{p.sample_hz:g}", "--speedup", f"{speedup:g}", "--repeat", "0", "--gap-s", "5",
        "--radius-mm", f"{p.radius_mm:g}", "--feed-mm-min", f"{p.feed_mm_min:g}", "--plane", p.plane,
        "--start-deg", f"{p.start_deg:g}", "--overshoot-deg", f"{p.overshoot_deg:g}",
        "--data-arc-deg", f"{p.data_arc_deg:g}", "--feed-in-mm", f"{p.feed_in_mm:g}",
        "--dwell-s", f"{p.dwell_s:g}", "--directions", p.directions,
    ]
    for item in (*SIM_MACHINE, *named.changes, *sets):
        args += ["--set", item]
    return args + wear


class SimulatedDeviceSource(Source):
    """The simulated device's serial source, opened once the device is up.

    The device starts beside the daemon: it imports the simulator and simulates its
    first test (about a second) before its pty appears, and READY=1 does not wait for
    that.  Until then a read waits for the device and returns nothing, without an
    event (the port is not missing, it is being made); then the serial source on its
    pty takes over (its ``opened`` event first).  A device that exits before it is up
    is a :class:`SourceError`.
    """

    scheme = "serial"

    def __init__(self, dev: DeviceProcess, url: str, rate_hz: float, start_timeout_s: float = 60.0) -> None:
        super().__init__(url, rate_hz)
        self.device = dev
        self._inner: Source | None = None
        self._give_up = time.monotonic() + start_timeout_s
        self._lock = threading.Lock()

    def read(self, timeout: float | None = None) -> SampleBatch | None:
        if self._closed:
            raise SourceClosed(f"{self.url}: read after close")
        inner = self._inner
        if inner is None:
            deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
            inner = self._open(deadline)
            if inner is None:
                return None
            timeout = None if deadline is None else max(0.0, deadline - time.monotonic())
        return inner.read(timeout)

    def _open(self, deadline: float | None) -> Source | None:
        while True:
            left = 0.5 if deadline is None else min(0.5, max(0.0, deadline - time.monotonic()))
            try:
                up = self.device.wait_ready(left)
            except EOFError:
                raise SourceError(
                    f"{self.url}: the simulated device exited before it was up (code {self.device.proc.poll()})"
                ) from None
            if up:
                break
            if time.monotonic() > self._give_up:
                raise SourceError(f"{self.url}: the simulated device was not up within a minute")
            if self._closed or (deadline is not None and time.monotonic() >= deadline):
                return None
        if self.device.url != self.url:
            log.warning("the simulated device reads as %s, not %s", self.device.url, self.url)
        inner = open_source(self.device.url)
        inner.pace(self.read_s)
        with self._lock:
            if self._closed:
                inner.close()
                return None
            self._inner = inner
        return inner

    def _read(self, deadline: float | None) -> SampleBatch | None:
        raise NotImplementedError  # read() hands over to the serial source

    def pace(self, period_s: float) -> None:
        super().pace(period_s)
        if self._inner is not None:
            self._inner.pace(period_s)

    @property
    def finished(self) -> bool:
        return self._inner is not None and self._inner.finished

    def stats(self) -> SourceStats:
        return self._inner.stats() if self._inner is not None else super().stats()

    def _close(self) -> None:
        with self._lock:
            inner = self._inner
        if inner is not None:
            inner.close()


@contextlib.contextmanager
def simulated_device(cfg: Config, speedup: float, machine: str = "passing", sets: Sequence[str] = (),
                     drifts: Sequence[str] = ()) -> Iterator[SimulatedDeviceSource]:
    """The built-in simulated ball-bar on a pty, repeating tests on the named machine (:func:`simdevice_args`): its
    source (see :class:`SimulatedDeviceSource`)."""
    if machine not in MACHINES:
        raise ConfigError(f"--simulate: no machine {machine!r} (known: {', '.join(MACHINES)})")
    if sets or drifts:  # (the named machines are sound; the check imports the simulator, 0.5 s before READY)
        check_machine(bool(simulated_plans(cfg)), sets, drifts)
    tmpdir = tempfile.mkdtemp(prefix="ballbar-simdevice-")
    try:
        link = os.path.join(tmpdir, "ttyBALLBAR0")
        p = cfg.plan
        # The URL the device will print (simdevice_args: binary, the plan's rate, calibrated at the radius).
        url = source_url(link, Settings(protocol="binary", rate=p.sample_hz, cal_mm=p.radius_mm))
        with DeviceProcess(*simdevice_args(cfg, speedup, machine, sets, drifts), "--link", link, wait=False) as dev:
            log.info("simulated ball-bar on %s (x%g speed), starting", link, speedup)
            source = SimulatedDeviceSource(dev, url, p.sample_hz)
            try:
                yield source
            finally:
                source.close()
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)  # the link, if the device could not remove it
