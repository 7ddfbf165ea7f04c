"""The daemon's extension points, and how it finds what plugs into them.

The layers run one way: ``tools`` over ``daemon`` over ``analysis`` over ``protocol`` (``daemon/README.md``,
"How it is built"; CI checks it).  So the daemon never imports the operator tools, yet three of its features are
theirs: the ``gcode`` and ``report`` subcommands of the ``ballbar`` command, the in-process simulator behind
``sim:`` URLs, and the simulated ball-bar that ``ballbar run --simulate`` starts.  Each is declared in
``pyproject.toml`` as an entry point of the installed distribution, and the daemon loads it by group and name
when it is needed (never at the start of ``ballbar run``):

* ``ballbar.commands``: a :class:`~ballbar.daemon.commands.Command` per subcommand (``gcode``, ``report``);
* ``ballbar.simulated``: ``tests`` (the simulated tests' samples for ``sim:``, :data:`SimulatedTests`),
  ``device`` (the simulated ball-bar on a pty for ``--simulate``, :data:`SimulatedDevice`) and ``cnc`` (the
  simulated CNC's OPC UA server for ``--simulate-cnc``, :data:`SimulatedCnc`).

Another distribution can add subcommands the same way.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from importlib import metadata
from typing import Any

COMMANDS = "ballbar.commands"
SIMULATED = "ballbar.simulated"

#: ``tests(plan, machine, library, run_plans, rate_hz, seed, repeat, gap_s)``: per simulated test its sample
#: times (s) and lengths (mm), tests one after the other on one clock; ``repeat`` None is forever.
SimulatedTests = Callable[..., Iterator[tuple[Any, Any]]]
#: ``device(cfg, speedup, machine, sets, drifts)``: a context manager giving the simulated ball-bar's source, the
#: named machine of :data:`SIM_MACHINES` with ``sets`` (``KEY=VALUE``) over its keys and ``drifts`` (``KEY=STEP``,
#: a change per test) added to its wear; a bad key or value is a :class:`~ballbar.daemon.errors.ConfigError`.
SimulatedDevice = Callable[..., Any]
#: ``cnc(cfg)``: a context manager giving the simulated CNC's OPC UA endpoint (``--simulate-cnc``).
SimulatedCnc = Callable[..., Any]
#: The machines ``ballbar run --simulate MACHINE`` offers: within the simulated limits, over them, and one whose
#: errors grow test by test.
SIM_MACHINES = ("passing", "failing", "wearing")


class PluginError(LookupError):
    """A feature that lives in a plug-in which is not installed."""


def names(group: str) -> list[str]:
    """The names declared in ``group``, sorted."""
    return sorted({ep.name for ep in metadata.entry_points(group=group)})


def load(group: str, name: str) -> Any:
    """The object ``name`` of ``group`` (its module imported now)."""
    for ep in metadata.entry_points(group=group):
        if ep.name == name:
            return ep.load()
    raise PluginError(f"{name!r} is not installed (entry point group {group}): is ballbar installed "
                      f"(pip install ballbar, or pip install -e . in a checkout)?")
