"""The daemon's configuration: one typed object, filled in layers.

Layers, later ones winning:

1. the shipped defaults (``daemon/default.toml``, every key commented), and over them what the command
   brings where the configuration says nothing (``ballbar run --simulate``: its limits);
2. the configuration file: ``--config FILE``, else ``$BALLBAR_CONFIG``, else
   ``/etc/ballbar/ballbar.toml`` when it exists;
3. the environment: ``BALLBAR__SECTION__KEY=value`` (double underscores; the
   value is read as TOML, so ``BALLBAR__ZENOH__CONNECT='["tcp/10.0.0.5:7447"]'``,
   and taken as a plain string when it is not valid TOML);
4. the command line: ``--set section.key=value`` (TOML value) and the named flags.

Plans and sets.  ``[plan]`` is the test plan; ``[plans.<name>]`` tables make a
library of several (analysis/plans.py), each ``[plan]`` with the keys it
gives changed, plus ``signature`` (the code its program carries; default: from
its name) and its own ``[plans.<name>.limits]`` over ``[limits]``.  Without
them the library is ``[plan]`` alone, named ``default``.  ``[sets.<name>]``:
``plans`` (names of the library) and ``window_minutes`` (the time within which
a set's tests must all have run).  ``--set plans.NAME.KEY=VALUE`` sets one key
of one plan.  :attr:`Config.plan` is the library's first plan: the bar's
calibration ``cal_mm`` is for the bar as assembled for it.

The machine.  ``[machine]`` gives the per-axis settings once, by the machine's
own axes (``kv_x_per_s``, ``kv_y_per_s``, ``kv_z_per_s``, ``pitch_x_mm`` ...);
each plan takes its plane's two (:meth:`~ballbar.analysis.plan.MachineAxes.for_plane`),
so there is no ``[plans.<name>.machine]``.  Before Z had keys, x and y were
each plan's first and second axis: a configuration with x or y keys alone, for
an axis no plan moves, meant that, and is refused (:func:`check_machine_axes`).

An unknown section or key, or a value of the wrong type, is one
:class:`ConfigError` naming it (the command exits with code 2).
"""

from __future__ import annotations

import errno
import math
import os
import re
import socket
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ballbar.analysis.errors import PlanError
from ballbar.analysis.plan import AnalysisOptions, MachineAxes, TestPlan, check_axes

from .errors import ConfigError
from .secrets import REDACTED, is_secret_key

if TYPE_CHECKING:  # the plans' module (numpy) comes in with a library: a single [plan] needs none of it
    from ballbar.analysis.plans import PlanLibrary

DEFAULT_FILE = Path(__file__).with_name("default.toml")
SYSTEM_FILE = Path("/etc/ballbar/ballbar.toml")
ENV_PREFIX = "BALLBAR__"
HISTORY_SIZE_MAX = 10_000  # zenoh.history_size: five topics of up to this many results, some 10 to 20 kB each


@dataclass
class DaemonSection:
    machine_id: str = "machine"
    state_dir: str = "/var/lib/ballbar"
    status_interval_s: float = 1.0
    log_level: str = "info"
    analysis_worker: bool = True  # each test's fit in a child process, off the daemon's reading and circles


@dataclass
class SourceSection:
    url: str = "serial:/dev/ttyUSB0?protocol=binary&rate=1000"
    cal_mm: float | None = None  # the bar's length at zero displacement; default: the plan's radius


@dataclass
class McapSection:
    enabled: bool = True
    rotate_per_test: bool = True
    rotate_mb: float = 256.0
    rotate_minutes: float = 60.0
    quota_mb: float = 4096.0
    keep_days: float = 90.0
    flush_s: float = 0.5


@dataclass
class ZenohSection:
    enabled: bool = True
    mode: str = ""  # peer, client, router; empty: the config file's, else peer
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    config_file: str = ""
    multicast_scouting: bool = False
    history_size: int = 500
    close_timeout_s: float = 2.0
    options: dict[str, Any] = field(default_factory=dict)  # raw zenoh keys, applied last
    samples_hz: float = 0.0  # decimated samples on ballbar/<machine>/samples; 0 = off


@dataclass
class RerunSection:
    mode: str = "serve"  # serve: viewers connect here; connect: push to url; off
    bind: str = "127.0.0.1"  # this PC only; "0.0.0.0" (or one address) lets viewers elsewhere in
    port: int = 9880  # not the viewer's own 9876
    url: str = "rerun+http://127.0.0.1:9876/proxy"
    memory_limit_mb: float = 128.0
    tolerance_um: float = 10.0
    magnification: float = 0.0  # 0: automatic
    history_tests: int = 50  # the last tests a viewer that connects later is sent whole


def _monitor_default(name: str) -> Any:
    """A default of :class:`~ballbar.analysis.monitor.MonitorSettings` (imported when a configuration is built, not
    with this module: the monitor brings numpy, which ``ballbar analyze`` of a CSV without limits does not need
    so early)."""
    from ballbar.analysis.monitor import MonitorSettings

    return getattr(MonitorSettings, name)


@dataclass
class LimitsSection:
    """Acceptance limits, verdicts, trends and alerts (:mod:`ballbar.analysis.monitor`); off by default."""

    enabled: bool = False
    G_um: float | None = None  # ISO 230-4 circular deviation, each direction
    G_b_um: float | None = None  # bidirectional circular deviation
    H_um: float | None = None  # circular hysteresis
    parameters: dict[str, float] = field(default_factory=dict)  # result parameter name -> bound on |value|
    warn_fraction: float = 0.8
    warn_fractions: dict[str, float] = field(default_factory=dict)  # per limit, overrides warn_fraction
    # the monitor's own defaults (one place for them)
    coverage_k: float = field(default_factory=lambda: _monitor_default("coverage_k"))
    trend_tests: int = field(default_factory=lambda: _monitor_default("trend_tests"))
    trend_days: float = field(default_factory=lambda: _monitor_default("trend_days"))
    min_tests: int = field(default_factory=lambda: _monitor_default("min_tests"))
    horizon_days: float = field(default_factory=lambda: _monitor_default("horizon_days"))
    confidence: float = field(default_factory=lambda: _monitor_default("confidence"))
    clear_after: int = field(default_factory=lambda: _monitor_default("clear_after"))


@dataclass
class ReportSection:
    """What ``ballbar report`` states beside the results (its command-line flags override each)."""

    operator: str = ""  # who ran the test
    bar_serial: str = ""  # the ball-bar's serial number
    bar_calibrated: str = ""  # the bar's last calibration, a date
    machine_temperature_c: float | None = None
    air_temperature_c: float | None = None
    notes: str = ""
    sign_off: list[str] = field(default_factory=lambda: ["Tested by", "Approved by"])  # the signature lines


@dataclass
class SetSection:
    """A set of tests (``[sets.<name>]``): the plans it holds, and the time within which its tests must all
    have run to count as one picture of the machine."""

    plans: list[str] = field(default_factory=list)
    window_minutes: float = 240.0


@dataclass(frozen=True)
class PlanEntry:
    """One plan of the library as configured: the plan, its program's signature, its own limits (the
    effective ``[limits]`` for its tests; None: the global one)."""

    plan: TestPlan
    signature: int | None = None
    limits: LimitsSection | None = None
    program: str | None = None  # the controller's main program name (a glob) while this plan runs ([controller])

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {**self.plan.to_dict(), "signature": self.signature}
        if self.program is not None:
            out["program"] = self.program
        if self.limits is not None:
            out["limits"] = asdict(self.limits)
        return out


@dataclass
class QueueSection:
    analysis: int = 6000  # batches (~20 ms each): two minutes; drop_newest, counted
    mcap: int = 6000  # drop_newest: a contiguous log, the gap counted
    zenoh: int = 1000  # drop_oldest: the newest matters
    rerun: int = 500  # drop_oldest


@dataclass
class ControllerSection:
    """The CNC's own account over OPC UA (``[controller]``; daemon/README.md "Controller").  Absent: no client,
    asyncua never imported.  Security: ``None`` in this version; the keys for ``Basic256Sha256`` with
    ``Sign``/``SignAndEncrypt`` (the daemon's certificate and key, the server's certificate trusted) and for a
    user and password are read and checked already, and refused as not yet supported."""

    endpoint: str = ""  # opc.tcp://host:port[/path]
    security_policy: str = "None"  # None; Basic256Sha256 (not yet)
    security_mode: str = "None"  # None; Sign, SignAndEncrypt (with Basic256Sha256)
    certificate: str = ""  # the daemon's certificate file (DER or PEM)
    private_key: str = ""  # its private key file
    server_certificate: str = ""  # the server's certificate, trusted
    user: str = ""  # empty: anonymous
    password: str = ""  # never logged nor published
    namespace: str = "http://opcfoundation.org/UA/CNC"  # the URI a "cnc:" prefix of a browse name stands for
    channel: str = "Channel_1"  # the channel's browse name under CncChannelList ({channel} in the map)
    axes: list[str] = field(default_factory=lambda: ["X", "Y", "Z"])  # the axes' browse names under CncAxisList
    nodes: dict[str, str] = field(default_factory=dict)  # name -> browse path or node id, over the default map
    publish_ms: float = 250.0  # the subscription's publishing interval (each wake-up costs: 100 ms doubled the CPU)
    sample_ms: float = 20.0  # the monitored items' sampling interval (positions: 50 Hz)
    timeout_s: float = 4.0  # a request's time-out; the connection is checked as often
    reconnect_min_s: float = 0.5  # the back-off after a failed connection, doubled up to ...
    reconnect_max_s: float = 30.0  # ... this


SECTIONS: dict[str, type] = {
    "daemon": DaemonSection,
    "source": SourceSection,
    "plan": TestPlan,
    "machine": MachineAxes,
    "analysis": AnalysisOptions,
    "mcap": McapSection,
    "zenoh": ZenohSection,
    "rerun": RerunSection,
    "queues": QueueSection,
    "limits": LimitsSection,
    "report": ReportSection,
}


@dataclass
class Config:
    daemon: DaemonSection
    source: SourceSection
    plan: TestPlan
    machine: MachineAxes
    analysis: AnalysisOptions
    mcap: McapSection
    zenoh: ZenohSection
    rerun: RerunSection
    queues: QueueSection
    limits: LimitsSection = field(default_factory=LimitsSection)
    report: ReportSection = field(default_factory=ReportSection)
    plans: dict[str, PlanEntry] = field(default_factory=dict)  # [plans.<name>]; empty: [plan] alone
    sets: dict[str, SetSection] = field(default_factory=dict)
    controller: ControllerSection | None = None  # [controller]; None: no section, no client

    @property
    def cal_mm(self) -> float:
        return self.source.cal_mm if self.source.cal_mm is not None else self.plan.radius_mm

    @property
    def library(self) -> PlanLibrary:
        """The plans the daemon recognises: ``[plans.*]`` in order, else ``[plan]`` named ``default``."""
        from ballbar.analysis.plans import NamedPlan, PlanLibrary

        if not self.plans:
            return PlanLibrary.single(self.plan)
        return PlanLibrary(tuple(NamedPlan(n, e.plan, e.signature, e.program) for n, e in self.plans.items()))

    @property
    def limits_enabled(self) -> bool:
        """Limits on for any plan: the monitor runs."""
        return self.limits.enabled or any(e.limits is not None and e.limits.enabled for e in self.plans.values())

    def limits_of(self, name: str) -> LimitsSection:
        """The limits that plan ``name``'s tests are held to."""
        entry = self.plans.get(name)
        return entry.limits if entry is not None and entry.limits is not None else self.limits

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name in SECTIONS:
            v = getattr(self, name)
            out[name] = v.to_dict() if hasattr(v, "to_dict") else asdict(v)
        for k, v in list(out["analysis"].items()):
            if isinstance(v, tuple):
                out["analysis"][k] = list(v)
        if self.plans:  # a single [plan] leaves its configuration as it was
            out["plans"] = {n: e.to_dict() for n, e in self.plans.items()}
        if self.sets:
            out["sets"] = {n: asdict(s) for n, s in self.sets.items()}
        if self.controller is not None:  # absent, the configuration stays as it was
            out["controller"] = asdict(self.controller)
        return out


def _check_type(where: str, value: Any, tp: Any) -> Any:
    """``value`` converted to the field type ``tp``, or a ConfigError naming ``where`` (never a secret's value)."""
    try:
        return _convert(where, value, tp)
    except ConfigError:
        if is_secret_key(where):
            raise ConfigError(f"{where}: bad value ({REDACTED})") from None
        raise


def _convert(where: str, value: Any, tp: Any) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check_type(where, value, a)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where} must be one of {', '.join(map(repr, args))}, not {value!r}")
        return value
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where} must be a table, not {value!r}")
        return dict(value)
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where} must be a list, not {value!r}")
        inner = args[0] if args else Any
        items = [_check_type(f"{where}[{i}]", v, inner) for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if tp is Any:
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, not {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be a whole number, not {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{where} must be a number, not {value!r}")
        if not math.isfinite(value):
            raise ConfigError(f"{where} must be a finite number, not {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, not {value!r}")
        return value
    return value


def _build(name: str, cls: type, data: Mapping[str, Any]) -> Any:
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls)}
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        if key not in known:
            raise ConfigError(f"unknown key {name}.{key} (known: {', '.join(sorted(known))})")
        kwargs[key] = _check_type(f"{name}.{key}", value, hints[key])
    try:
        return cls(**kwargs)
    except PlanError as err:
        raise ConfigError(f"[{name}] {err}") from err


NESTED = ("plans", "sets")  # tables of named tables
OPTIONAL: dict[str, type] = {"controller": ControllerSection}  # sections that exist only when given


def _merge(base: dict[str, dict[str, Any]], layer: Mapping[str, Any], origin: str) -> None:
    for section, values in layer.items():
        if section not in SECTIONS and section not in NESTED and section not in OPTIONAL:
            known = ", ".join([*SECTIONS, *NESTED, *OPTIONAL])
            raise ConfigError(f"{origin}: unknown section [{section}] (known: {known})")
        if not isinstance(values, Mapping):
            raise ConfigError(f"{origin}: [{section}] must be a table")
        if section not in NESTED:
            base.setdefault(section, {}).update(values)
            continue
        for name, table in values.items():
            if not isinstance(table, Mapping):
                raise ConfigError(f"{origin}: [{section}.{name}] must be a table")
            into = base.setdefault(section, {}).setdefault(name, {})
            for key, value in table.items():
                if key == "limits" and isinstance(value, Mapping) and isinstance(into.get(key), dict):
                    into[key].update(value)
                else:
                    into[key] = dict(value) if isinstance(value, Mapping) else value


def read_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as err:
        raise ConfigError(f"{os.fspath(path)}: cannot read: {err.strerror or err}") from err
    except UnicodeDecodeError as err:
        raw = Path(path).read_bytes()
        line = raw[: err.start].count(b"\n") + 1
        raise ConfigError(f"{os.fspath(path)}:{line}: not valid TOML: byte {err.start} is not UTF-8") from None
    import tomllib  # here: reading a recording needs none of it

    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{os.fspath(path)}: not valid TOML: {err}") from err


def parse_value(text: str) -> Any:
    """A TOML value (``3``, ``true``, ``"x"``, ``[1, 2]``), or the text itself."""
    import tomllib

    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def parse_assignment(item: str, origin: str) -> tuple[str, str, Any]:
    key, sep, value = item.partition("=")
    section, dot, name = key.strip().partition(".")
    if not sep or not dot or not name:
        raise ConfigError(f"{origin}: expected section.key=value, not {item!r}")
    return section, name, parse_value(value.strip())


def _assignment_layer(section: str, name: str, value: Any) -> dict[str, Any]:
    """``--set`` of one key: ``plans.NAME.KEY`` (and ``plans.NAME.limits.KEY``) reach into a named table."""
    if section in NESTED and "." in name:
        table, _, key = name.partition(".")
        if section == "plans" and key.startswith("limits."):
            return {section: {table: {"limits": {key.partition(".")[2]: value}}}}
        return {section: {table: {key: value}}}
    return {section: {name: value}}


def load(
    config_file: str | None = None,
    sets: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
    overrides: Mapping[str, Mapping[str, Any]] | None = None,
    base: Mapping[str, Mapping[str, Any]] | None = None,
) -> Config:
    """The configuration from the four layers (see the module docstring); ``base`` goes over the shipped
    defaults, under everything else."""
    env = os.environ if env is None else env
    merged: dict[str, dict[str, Any]] = {}
    _merge(merged, read_toml(DEFAULT_FILE), str(DEFAULT_FILE))
    if base:
        _merge(merged, base, "the command's defaults")
    path = config_file or env.get("BALLBAR_CONFIG") or (str(SYSTEM_FILE) if SYSTEM_FILE.exists() else None)
    if path:
        _merge(merged, read_toml(path), path)
    for var, text in sorted(env.items()):
        if not var.startswith(ENV_PREFIX):
            continue
        parts = var[len(ENV_PREFIX) :].lower().split("__")
        if len(parts) != 2:
            raise ConfigError(f"environment {var}: expected BALLBAR__SECTION__KEY")
        _merge(merged, {parts[0]: {parts[1]: parse_value(text)}}, f"environment {var}")
    for item in sets:
        section, name, value = parse_assignment(item, "--set")
        _merge(merged, _assignment_layer(section, name, value), "--set")
    if overrides:
        _merge(merged, overrides, "command line")
    built = {name: _build(name, cls, merged.get(name, {})) for name, cls in SECTIONS.items()}
    cfg = Config(**built)
    cfg.plans = build_plans(merged.get("plan", {}), merged.get("plans", {}), merged.get("limits", {}))
    if cfg.plans:
        cfg.plan = next(iter(cfg.plans.values())).plan
    cfg.sets = {name: _build(f"sets.{name}", SetSection, table) for name, table in merged.get("sets", {}).items()}
    if "controller" in merged:
        cfg.controller = _build("controller", ControllerSection, merged["controller"])
    _validate(cfg)
    return cfg


def library_of(sections: Mapping[str, Any]) -> PlanLibrary | None:
    """The library of a configuration's tables (a recorded one: ``plan``, ``plans``, ``limits``), None where
    it has no ``plans`` (its ``plan`` alone).  A bad table is a :class:`ConfigError`."""
    from ballbar.analysis.plans import NamedPlan, PlanLibrary

    tables = sections.get("plans")
    if not isinstance(tables, Mapping) or not tables:
        return None
    entries = build_plans(sections.get("plan") or {}, tables, sections.get("limits") or {})
    return PlanLibrary(tuple(NamedPlan(n, e.plan, e.signature, e.program) for n, e in entries.items()))


def build_plans(base: Mapping[str, Any], tables: Mapping[str, Mapping[str, Any]], limits: Mapping[str, Any],
                ) -> dict[str, PlanEntry]:
    """The ``[plans.<name>]`` tables as a library: each ``base`` (``[plan]``) with its keys changed, its
    signature (given, else :func:`~ballbar.analysis.plans.default_signature` of its name where there are
    several), its limits over ``limits`` (``[limits]``).  Errors name the plan and key."""
    from ballbar.analysis.plans import NamedPlan, PlanLibrary, default_signature

    out: dict[str, PlanEntry] = {}
    for name, table in tables.items():
        where = f"plans.{name}"
        data = dict(table)
        if any(k == "machine" or k.startswith("machine.") for k in data):  # a TOML table, or --set plans.N.machine.K
            raise ConfigError(f"{where}.machine: the machine's settings are per axis, given once in [machine] "
                              f"({', '.join(MachineAxes.axis_keys())}); each plan takes its plane's two")
        known = {f.name for f in fields(TestPlan)} | {"signature", "limits", "program"}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ConfigError(f"unknown key {where}.{unknown[0]} (known: {', '.join(sorted(known))})")
        signature = data.pop("signature", None)
        own = data.pop("limits", None)
        program = data.pop("program", None)
        if program is not None:
            program = _check_type(f"{where}.program", program, str)
            if not program.strip():
                raise ConfigError(f"{where}.program must name the controller's program (a name or a pattern such "
                                  'as "O9101" or "BALLBAR_*"), not empty')
        plan = _build(where, TestPlan, {**base, **data})
        if signature is not None:
            signature = _check_type(f"{where}.signature", signature, int)
        elif len(tables) > 1:
            signature = default_signature(name)
        entry_limits = None
        if own is not None:
            if not isinstance(own, Mapping):
                raise ConfigError(f"[{where}.limits] must be a table")
            entry_limits = _build(f"{where}.limits", LimitsSection, {**limits, **own})
        out[name] = PlanEntry(plan, signature, entry_limits, program)
    if out:
        try:
            PlanLibrary(tuple(NamedPlan(n, e.plan, e.signature, e.program) for n, e in out.items()))
        except PlanError as err:
            raise ConfigError(f"[plans] {err}") from None
    return out


_BAD_CHUNK = re.compile(r"[/*$?#\s]")


def _validate(cfg: Config) -> None:
    """Values that type checks alone let through; each error names its key."""
    checks: list[tuple[bool, str]] = [
        (
            bool(cfg.daemon.machine_id) and not _BAD_CHUNK.search(cfg.daemon.machine_id),
            f"daemon.machine_id must be a non-empty key segment without / * ? $ # or spaces, "
            f"not {cfg.daemon.machine_id!r}",
        ),
        (
            cfg.daemon.log_level in ("debug", "info", "warning", "error"),
            f"daemon.log_level must be debug, info, warning or error, not {cfg.daemon.log_level!r}",
        ),
        (bool(cfg.daemon.state_dir.strip()), "daemon.state_dir must not be empty"),
        (0 < cfg.daemon.status_interval_s <= 60, "daemon.status_interval_s must be within (0, 60]"),
        (bool(cfg.source.url.strip()), "source.url must not be empty (serial:/dev/ttyUSB0?..., sim:, replay:FILE)"),
        (cfg.source.cal_mm is None or cfg.source.cal_mm > 0, f"source.cal_mm must be > 0, not {cfg.source.cal_mm}"),
        (
            cfg.rerun.mode in ("serve", "connect", "off"),
            f"rerun.mode must be serve, connect or off, not {cfg.rerun.mode!r}",
        ),
        (
            cfg.zenoh.mode in ("", "peer", "client", "router"),
            f"zenoh.mode must be peer, client or router, not {cfg.zenoh.mode!r}",
        ),
        (1 <= cfg.rerun.port <= 65535, f"rerun.port must be within 1..65535, not {cfg.rerun.port}"),
        (cfg.rerun.memory_limit_mb >= 1, f"rerun.memory_limit_mb must be at least 1, not {cfg.rerun.memory_limit_mb}"),
        (cfg.rerun.tolerance_um > 0, f"rerun.tolerance_um must be > 0, not {cfg.rerun.tolerance_um}"),
        (cfg.rerun.magnification >= 0, f"rerun.magnification must be >= 0 (0: auto), not {cfg.rerun.magnification}"),
        (cfg.zenoh.samples_hz >= 0, f"zenoh.samples_hz must be 0 (off) or a positive rate, not {cfg.zenoh.samples_hz}"),
        (1 <= cfg.zenoh.history_size <= HISTORY_SIZE_MAX,
         f"zenoh.history_size must be within 1..{HISTORY_SIZE_MAX} (each kept result is held in memory), "
         f"not {cfg.zenoh.history_size}"),
        (cfg.zenoh.close_timeout_s > 0, f"zenoh.close_timeout_s must be > 0, not {cfg.zenoh.close_timeout_s}"),
        (
            cfg.mcap.rotate_mb * (1 << 20) >= 4096,
            f"mcap.rotate_mb must be at least 0.004 (4 KiB), not {cfg.mcap.rotate_mb}",
        ),
        (cfg.mcap.rotate_minutes > 0, f"mcap.rotate_minutes must be > 0, not {cfg.mcap.rotate_minutes}"),
        (
            cfg.mcap.quota_mb >= 2 * cfg.mcap.rotate_mb,
            f"mcap.quota_mb must be at least twice mcap.rotate_mb ({2 * cfg.mcap.rotate_mb:g}), "
            f"not {cfg.mcap.quota_mb}",
        ),
        (cfg.mcap.keep_days > 0, f"mcap.keep_days must be > 0, not {cfg.mcap.keep_days}"),
        (
            0 < cfg.mcap.flush_s <= 0.9,
            f"mcap.flush_s must be within (0, 0.9] (1 s old samples must be on disk), not {cfg.mcap.flush_s}",
        ),
    ]
    for name in ("analysis", "mcap", "zenoh", "rerun"):
        checks.append((getattr(cfg.queues, name) >= 1, f"queues.{name} must be at least 1"))
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)
    names = cfg.library.names
    for set_name, st in cfg.sets.items():
        where = f"sets.{set_name}"
        if not st.plans:
            raise ConfigError(f"{where}.plans must name at least one plan")
        for p in st.plans:
            if p not in names:
                raise ConfigError(f"{where}.plans: no plan {p!r} (plans: {', '.join(names)})")
        if len(set(st.plans)) != len(st.plans):
            raise ConfigError(f"{where}.plans names a plan twice: {st.plans}")
        if not st.window_minutes > 0:
            raise ConfigError(f"{where}.window_minutes must be > 0, not {st.window_minutes}")
    check_machine_axes(cfg)
    if cfg.controller is not None:
        check_controller(cfg.controller)
    monitor_settings(cfg)
    for name, entry in cfg.plans.items():
        if entry.limits is not None:
            monitor_settings(cfg, name)


_OPC_ENDPOINT = re.compile(r"^opc\.tcp://(?P<host>\[[0-9A-Fa-f:.]+\]|[^:/\s\[\]]+)(?::(?P<port>\d+))?(?:/\S*)?$")
SECURITY_POLICIES = ("None", "Basic256Sha256")
SECURITY_MODES = ("None", "Sign", "SignAndEncrypt")


def check_controller(c: ControllerSection) -> None:
    """``[controller]``'s values, each error naming its key (never a secret's value): what can never work is
    refused at start, before anything opens."""
    from .secrets import mask_url

    if not _OPC_ENDPOINT.match(c.endpoint):
        raise ConfigError(f"controller.endpoint must be opc.tcp://HOST[:PORT][/PATH], not {mask_url(c.endpoint)!r}")
    port = _OPC_ENDPOINT.match(c.endpoint)["port"]  # type: ignore[index]
    if port is not None and not 1 <= int(port) <= 65535:
        raise ConfigError(f"controller.endpoint: port {port} is not within 1..65535")
    if c.security_policy not in SECURITY_POLICIES:
        raise ConfigError(f"controller.security_policy must be one of {', '.join(SECURITY_POLICIES)}, "
                          f"not {c.security_policy!r}")
    if c.security_mode not in SECURITY_MODES:
        raise ConfigError(f"controller.security_mode must be one of {', '.join(SECURITY_MODES)}, "
                          f"not {c.security_mode!r}")
    if (c.security_policy == "None") != (c.security_mode == "None"):
        raise ConfigError(f"controller.security_mode {c.security_mode!r} does not go with security_policy "
                          f"{c.security_policy!r} (None with None; Basic256Sha256 with Sign or SignAndEncrypt)")
    if c.security_policy != "None":
        raise ConfigError(f"controller.security_policy {c.security_policy!r} is not supported by this version yet "
                          "(None only)")
    if c.user or c.password:
        raise ConfigError("controller.user and controller.password are not supported by this version yet "
                          "(anonymous only)")
    for key in ("publish_ms", "sample_ms", "timeout_s", "reconnect_min_s"):
        if not getattr(c, key) > 0:
            raise ConfigError(f"controller.{key} must be > 0, not {getattr(c, key)}")
    if c.reconnect_max_s < c.reconnect_min_s:
        raise ConfigError(f"controller.reconnect_max_s must be at least reconnect_min_s ({c.reconnect_min_s:g}), "
                          f"not {c.reconnect_max_s}")
    for name, path in c.nodes.items():
        if not isinstance(path, str):
            raise ConfigError(f"controller.nodes.{name} must be a string (a browse path or a node id; "
                              f"empty: not read), not {path!r}")


def check_machine_axes(cfg: Config) -> None:
    """:func:`~ballbar.analysis.plan.check_axes` of ``[machine]`` and the library's planes, as a ConfigError:
    X or Y keys alone, one for an axis no plan moves, were written as a plan's first and second axis."""
    try:
        check_axes(cfg.machine, [p.plan.plane for p in cfg.library.plans])
    except PlanError as err:
        raise ConfigError(str(err)) from None


def check_listen(key: str, host: str, port: int, datagram: bool = False) -> None:
    """A ConfigError naming ``key`` when ``host:port`` can never be listened on here: an address that is not one
    of this host's, a name that does not resolve, a port the process may not take.

    A port that another process holds now is not an error (it may be free later: the output retries and says
    so), nor is a name the resolver cannot answer for now.  The check binds a socket to the address and closes
    it at once, as the output's own listener would bind it (``SO_REUSEADDR``).
    """
    kind = socket.SOCK_DGRAM if datagram else socket.SOCK_STREAM
    try:
        infos = socket.getaddrinfo(host or None, port, type=kind, flags=socket.AI_PASSIVE)
    except socket.gaierror as err:
        if err.errno in (socket.EAI_NONAME, getattr(socket, "EAI_NODATA", socket.EAI_NONAME)):
            raise ConfigError(f"{key}: {host!r} is not a name or address of this host ({err.strerror})") from None
        return  # the resolver does not answer now: the output retries
    except (UnicodeError, ValueError) as err:
        raise ConfigError(f"{key}: {host!r} is not a host name or address ({err})") from None
    why = ""
    for family, type_, proto, _name, sockaddr in infos:
        with socket.socket(family, type_, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(sockaddr)
                return
            except OSError as err:
                if err.errno == errno.EADDRINUSE:
                    return  # held by another process now: transient
                why = ("not an address of this host" if err.errno == errno.EADDRNOTAVAIL
                       else err.strerror or str(err))
    raise ConfigError(f"{key}: cannot listen on {host}:{port}: {why}")


def check_addresses(cfg: Config) -> None:
    """The checks of :func:`check_listen` for the Rerun server's ``rerun.bind`` (``mode = "serve"``).

    Made by ``ballbar run`` only, before anything opens: the other commands read a configuration that may
    come from another host.
    """
    if cfg.rerun.mode == "serve":
        check_listen("rerun.bind", cfg.rerun.bind, cfg.rerun.port)


def monitor_settings(cfg: Config, plan: str | None = None) -> Any:
    """The :class:`~ballbar.analysis.monitor.MonitorSettings` of ``[limits]`` (of plan ``plan``'s own limits,
    where it has them); a bad value is a ConfigError."""
    from ballbar.analysis.monitor import check_parameter_names, settings_from_dict
    from ballbar.analysis.patterns import LIBRARY
    from ballbar.analysis.report import _report_fields

    limits = cfg.limits if plan is None else cfg.limits_of(plan)
    try:
        settings = settings_from_dict(asdict(limits) | {"enabled": True})
        check_parameter_names(settings, (f for p in LIBRARY for f, _u in _report_fields(p)))
        return settings if limits.enabled else settings_from_dict(asdict(limits))
    except PlanError as err:
        where = f"plans.{plan}.limits: " if plan is not None and cfg.plans.get(plan) is not None else ""
        raise ConfigError(f"{where}{err}") from None
