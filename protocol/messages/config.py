"""The effective configuration as the daemon sends it: at start (``ballbar/<m>/config``, ``last/config``) and at
the head of every MCAP file; secrets ``"<redacted>"``.

Its sections and keys are ``daemon/default.toml``'s (described there); a test
keeps the two the same.
"""

from typing import Annotated, Literal, NotRequired, TypedDict

from .envelope import MachineId, TWall, Version
from .fields import doc
from .results import Plan


class DaemonSection(TypedDict):
    """[daemon]"""

    machine_id: Annotated[str, doc("the key chunk <m>")]
    state_dir: Annotated[str, doc("recordings, history")]
    status_interval_s: Annotated[float, doc("the status' period", "s")]
    log_level: Annotated[str, doc("debug, info, warning or error")]
    analysis_worker: Annotated[bool, doc("each test's fit in a child process")]


class SourceSection(TypedDict):
    """[source]"""

    url: Annotated[str, doc("the source actually read: with --simulate, the simulated device's pty")]
    cal_mm: Annotated[float | None, doc("the bar's length at zero displacement", "mm", null="the plan's radius")]


_LEGACY = "absent: recorded before the machine's axes were named, when x and y were each plan's first and second axis"


class MachineSection(TypedDict):
    """[machine]: per machine axis, each plan taking its plane's two (XY: X, Y; YZ: Y, Z; ZX: Z, X)"""

    pitch_x_mm: Annotated[float | None, doc("the X axis' screw pitch (cyclic error)", "mm", null="unknown")]
    pitch_y_mm: Annotated[float | None, doc("the Y axis' screw pitch", "mm", null="unknown")]
    pitch_z_mm: NotRequired[Annotated[float | None, doc(f"the Z axis' screw pitch ({_LEGACY})", "mm",
                                                        null="unknown")]]
    kv_x_per_s: Annotated[float | None, doc("the X axis' configured position-loop gain", "1/s", null="unknown")]
    kv_y_per_s: Annotated[float | None, doc("the Y axis' configured position-loop gain", "1/s", null="unknown")]
    kv_z_per_s: NotRequired[Annotated[float | None, doc(f"the Z axis' configured position-loop gain ({_LEGACY})",
                                                        "1/s", null="unknown")]]
    controller: Annotated[str, doc("generic, fanuc, siemens or heidenhain: parameter names in the advice")]


class AnalysisSection(TypedDict):
    """[analysis]"""

    significance: Annotated[float, doc("F-test level")]
    servo_model: Annotated[str, doc("auto, linear or physical")]
    lost_motion: Annotated[str, doc("physical or step")]
    min_effect_um: Annotated[float, doc("minimum radial effect of a significant pattern", "um")]
    vif_limit: Annotated[float, doc("variance inflation above which a parameter is not identifiable")]
    vibration_cutoff_cpr: Annotated[float, doc("residual content above this is vibration", "cycles per revolution")]
    spike_width_min_deg: Annotated[float, doc("the spikes' width searched from", "deg")]
    spike_width_max_deg: Annotated[float, doc("... up to", "deg")]
    estimate_lag: Annotated[bool, doc("estimate the arc start's lag")]
    max_lag_s: Annotated[float, doc("its search range, +-", "s")]
    patterns: Annotated[list[str] | None, doc("the patterns fitted", null="all")]
    standards: NotRequired[Annotated[list[Literal["iso230_4", "jis_b6190_4", "asme_b5_54"]], doc(
        "the circular-test standards whose figures a test result carries (absent before it existed)")]]


class McapSection(TypedDict):
    """[mcap]"""

    enabled: Annotated[bool, doc("log to MCAP")]
    rotate_per_test: Annotated[bool, doc("a new file at each feed-in")]
    rotate_mb: Annotated[float, doc("a new file at this size", "MB")]
    rotate_minutes: Annotated[float, doc("a new file at this age", "min")]
    quota_mb: Annotated[float, doc("the oldest files go above this", "MB")]
    keep_days: Annotated[float, doc("files older than this go", "days")]
    flush_s: Annotated[float, doc("a chunk closes within this", "s")]


class ZenohSection(TypedDict):
    """[zenoh]"""

    enabled: Annotated[bool, doc("publish on Zenoh")]
    mode: Annotated[str, doc("peer, client, router or empty")]
    listen: Annotated[list[str], doc("endpoints")]
    connect: Annotated[list[str], doc("endpoints")]
    config_file: Annotated[str, doc("a Zenoh JSON5 file (empty: none)")]
    multicast_scouting: Annotated[bool, doc("scouting by multicast")]
    history_size: Annotated[int, doc("results kept per history topic")]
    close_timeout_s: Annotated[float, doc("the session's close waits at most this", "s")]
    options: Annotated[dict[str, object], doc("raw Zenoh keys (secrets '<redacted>')")]
    samples_hz: Annotated[float, doc("decimated samples (0: off)", "Hz")]


class RerunSection(TypedDict):
    """[rerun]"""

    mode: Annotated[str, doc("serve, connect or off")]
    bind: Annotated[str, doc("address")]
    port: Annotated[int, doc("TCP port")]
    url: Annotated[str, doc("with mode connect")]
    memory_limit_mb: Annotated[float, doc("the server's memory limit", "MB")]
    tolerance_um: Annotated[float, doc("the polar plots' tolerance band", "um")]
    magnification: Annotated[float, doc("0: automatic")]
    history_tests: Annotated[int, doc("the last tests a viewer that connects later is sent whole")]


class LimitsSection(TypedDict):
    """[limits]: acceptance limits, verdicts, trends and alerts (off by default)"""

    enabled: Annotated[bool, doc("limits, verdicts and alerts on")]
    G_um: Annotated[float | None, doc("ISO 230-4 circular deviation G, each direction", "um", null="no limit")]
    G_b_um: Annotated[float | None, doc("bidirectional circular deviation G(b)", "um", null="no limit")]
    H_um: Annotated[float | None, doc("circular hysteresis H", "um", null="no limit")]
    parameters: Annotated[dict[str, float], doc("result parameter name -> bound on its absolute value, in its unit")]
    warn_fraction: Annotated[float, doc("a warning from this fraction of a limit")]
    warn_fractions: Annotated[dict[str, float], doc("per limit, its own warning fraction")]
    coverage_k: Annotated[float, doc("coverage factor of the uncertainty a limit must be exceeded beyond")]
    trend_tests: Annotated[int, doc("the trend over at most this many tests")]
    trend_days: Annotated[float, doc("... or over this many days (0: by count)")]
    min_tests: Annotated[int, doc("no trend from fewer tests")]
    horizon_days: Annotated[float, doc("a forecast crossing within this many days is due", "days")]
    confidence: Annotated[float, doc("the forecast interval's confidence")]
    clear_after: Annotated[int, doc("a due forecast clears after this many tests not due")]


class QueuesSection(TypedDict):
    """[queues]: bounds, items"""

    analysis: Annotated[int, doc("the analysis' queue", "items")]
    mcap: Annotated[int, doc("the MCAP log's queue", "items")]
    zenoh: Annotated[int, doc("the bus' queue", "items")]
    rerun: Annotated[int, doc("the viewer's queue", "items")]


class ReportSection(TypedDict):
    """[report]: what ballbar report states beside the results (absent before it existed)"""

    operator: Annotated[str, doc("who ran the test")]
    bar_serial: Annotated[str, doc("the ball-bar's serial number")]
    bar_calibrated: Annotated[str, doc("the bar's last calibration, a date")]
    machine_temperature_c: Annotated[float | None, doc("the machine's temperature", "deg C", null="not given")]
    air_temperature_c: Annotated[float | None, doc("the air's temperature", "deg C", null="not given")]
    notes: Annotated[str, doc("notes")]
    sign_off: Annotated[list[str], doc("a signature line per role")]


class PlanEntry(Plan):
    """one plan: [plan]'s keys, its program's signature and its own limits"""

    signature: Annotated[int | None, doc("the code its program carries before the feed-in, 0..124",
                                         null="none, a library of one")]
    limits: NotRequired[Annotated[dict[str, object], doc("its own [limits] (over the global one; absent: the global "
                                                         "one)")]]
    program: NotRequired[Annotated[str, doc("the controller's main program while it runs, a name or a glob pattern "
                                            "([controller]; absent: none)")]]


class SetEntry(TypedDict):
    """one set"""

    plans: Annotated[list[str], doc("the names of its plans")]
    window_minutes: Annotated[float, doc("the time within which its tests must all have run", "min")]


class ControllerSection(TypedDict):
    """[controller]: the CNC's OPC UA server (absent: no [controller] section)"""

    endpoint: Annotated[str, doc("opc.tcp://host:port[/path]")]
    security_policy: Annotated[str, doc("None or Basic256Sha256")]
    security_mode: Annotated[str, doc("None, Sign or SignAndEncrypt")]
    certificate: Annotated[str, doc("the daemon's certificate file (empty: none)")]
    private_key: Annotated[str, doc("its private key file ('<redacted>')")]
    server_certificate: Annotated[str, doc("the server's trusted certificate file (empty: none)")]
    user: Annotated[str, doc("the user (empty: anonymous)")]
    password: Annotated[str, doc("the password ('<redacted>')")]
    namespace: Annotated[str, doc("the URI a cnc: prefix in a browse path stands for")]
    channel: Annotated[str, doc("the channel's browse name")]
    axes: Annotated[list[str], doc("the axes' browse names")]
    nodes: Annotated[dict[str, str], doc("name -> browse path or node id, over the default map (empty: not read)")]
    publish_ms: Annotated[float, doc("the subscription's publishing interval", "ms")]
    sample_ms: Annotated[float, doc("the monitored items' sampling interval", "ms")]
    timeout_s: Annotated[float, doc("a request's time-out", "s")]
    reconnect_min_s: Annotated[float, doc("the first back-off", "s")]
    reconnect_max_s: Annotated[float, doc("the longest back-off", "s")]


class Settings(TypedDict):
    """the effective configuration: daemon/default.toml's sections and keys (see there), secrets '<redacted>'"""

    daemon: DaemonSection
    source: SourceSection
    plan: Plan
    plans: NotRequired[Annotated[dict[str, PlanEntry], doc("[plans.<name>]: the library of plans, in order (absent: "
                                                           "[plan] alone, named default)")]]
    sets: NotRequired[Annotated[dict[str, SetEntry], doc("[sets.<name>]: tests that together give one picture of "
                                                         "the machine (absent: none)")]]
    machine: MachineSection
    analysis: AnalysisSection
    mcap: McapSection
    zenoh: ZenohSection
    rerun: RerunSection
    limits: LimitsSection
    queues: QueuesSection
    report: NotRequired[ReportSection]
    controller: NotRequired[ControllerSection]


class ConfigMessage(TypedDict):
    """ballbar.Config: the daemon's effective configuration, at start (ballbar/<m>/config, last/config) and at the
    head of every MCAP file; secrets redacted."""

    schema_version: Version
    kind: Annotated[Literal["config"], doc("what the payload is")]
    machine_id: MachineId
    t_wall: TWall
    config: Settings
