"""The daemon's periodic status (``ballbar/<m>/status``, every ``daemon.status_interval_s``), and its parts.

Each output's counters (``outputs``) are the output's own ``stats()``: the
MCAP logger's :class:`McapStats`, the bus' :class:`ZenohStats`, the viewer's
:data:`RerunStats`; the source's running totals are :class:`SourceStats`.
"""

from typing import Annotated, Literal, NotRequired, TypedDict

from .envelope import MachineId, TWall, Version
from .fields import doc

Counts = dict[str, int]


class Queue(TypedDict):
    """one output's queue"""

    depth: Annotated[int, doc("items waiting now")]
    capacity: Annotated[int, doc("its bound", "items")]
    delivered: Annotated[int, doc("items handed to the output")]
    dropped: Annotated[int, doc("items dropped by the policy")]
    errors: Annotated[int, doc("items the output raised on")]
    policy: Annotated[Literal["drop_newest", "drop_oldest"], doc("drop_newest or drop_oldest")]


class McapStats(TypedDict):
    """the MCAP logger"""

    state: Annotated[str, doc("writing, failing (a write error; retrying) or stopped")]
    file: NotRequired[Annotated[str | None, doc("the file being written (empty: none)")]]
    files: Annotated[int, doc("files opened in this run")]
    bytes: NotRequired[Annotated[int, doc("bytes written in this run")]]
    samples: Annotated[int, doc("samples written")]
    messages: NotRequired[Annotated[int, doc("results, events, status and config records written")]]
    pending_samples: NotRequired[Annotated[int, doc("samples waiting for the next chunk")]]
    samples_lost: Annotated[int, doc("samples that could not be logged (write errors)")]
    messages_lost: NotRequired[Annotated[int, doc("records that could not be logged")]]
    messages_held: NotRequired[Annotated[int, doc("results and events held in memory during a write outage")]]
    messages_held_written: NotRequired[Annotated[int, doc("of those, written after it")]]
    held_messages: NotRequired[Annotated[int, doc("held now")]]
    write_errors: NotRequired[Annotated[int, doc("write errors")]]
    encode_errors: NotRequired[Annotated[int, doc("records that could not be encoded")]]
    deleted_files: NotRequired[Annotated[int, doc("files deleted by retention")]]
    deleted_bytes: NotRequired[Annotated[int, doc("bytes deleted by retention")]]
    last_error: NotRequired[Annotated[str, doc("the last write error (empty: none)")]]


class ZenohStats(TypedDict):
    """the Zenoh bus"""

    connected: Annotated[bool, doc("the session is open (not whether anyone listens)")]
    open_error: NotRequired[Annotated[str | None, doc("why it could not open (retrying in the background)")]]
    published: Annotated[Counts, doc("puts by topic (result/circle, result/test, result/set, event, status, config, "
                                           "samples, alert)")]
    put_errors: Annotated[int, doc("puts that failed")]
    not_connected: NotRequired[Annotated[int, doc("messages kept for last/history while the session was not open")]]
    slow_puts: NotRequired[Annotated[int, doc("puts that took longer than 0.1 s (a subscriber not reading)")]]
    max_put_ms: NotRequired[Annotated[float, doc("the longest put", "ms")]]
    queries: NotRequired[Annotated[int, doc("last/history queries answered")]]
    query_errors: NotRequired[Annotated[int, doc("replies that failed")]]
    skipped: NotRequired[Annotated[int, doc("messages of a kind with no topic")]]
    controls: NotRequired[Annotated[int, doc("choices of the next plan received on control/next_plan")]]
    controls_refused: NotRequired[Annotated[int, doc(
        "puts on control/next_plan refused as not of the documented shape (too long, not a name, other keys)")]]
    controls_dropped: NotRequired[Annotated[int, doc(
        "choices on control/next_plan dropped by the rate limit (more than 5 at once or 2 a second)")]]
    history: Annotated[Counts, doc("results and events held for history/<topic>, by topic")]
    history_controls: NotRequired[Annotated[int, doc("plan_chosen and plan_choice_refused events held for "
                                                     "history/event apart from the machine's own")]]
    zid: NotRequired[Annotated[str, doc("this session's Zenoh id")]]
    links: NotRequired[Annotated[Counts, doc("sessions connected to this one, by kind (peer, client, router)")]]


class RerunServer(TypedDict):
    """serve mode: the supervised `rerun --serve-grpc` child"""

    pid: Annotated[int | None, doc("its process id", null="not running")]
    listening: Annotated[bool, doc("it accepts viewers")]
    rss_mb: Annotated[float, doc("its resident memory", "MiB")]
    max_rss_mb: Annotated[float, doc("the most seen", "MiB")]
    rss_cap_mb: Annotated[float, doc("restarted above this", "MiB")]
    restarts: Annotated[int, doc("restarts")]
    rss_kills: Annotated[int, doc("restarts for memory")]
    stall_kills: Annotated[int, doc("restarts because it took none of the daemon's stream")]
    clients_ended: Annotated[int, doc("connections to it (viewers, clients pushing) that ended: each has the history "
                                      "sent again")]


class RerunStarting(TypedDict):
    """the viewer, not (yet) started"""

    state: Annotated[Literal["starting", "failed"], doc("starting or failed")]


Counter = Annotated[int, doc("a counter of what the viewer did")]


class RerunViewer(TypedDict):
    """the Rerun viewer"""

    mode: Annotated[Literal["serve", "connect"], doc("serve or connect")]
    address: NotRequired[Annotated[str | None, doc("where viewers connect (serve) or where it pushes (connect)")]]
    connected: Annotated[bool, doc("a sink is live")]
    clock: NotRequired[Annotated[Literal["device", "host"], doc("the clock of its timeline: device or host")]]
    buffered_samples: NotRequired[Annotated[int, doc("samples held for the live circles")]]
    pending_samples: NotRequired[Annotated[int, doc("samples not yet processed")]]
    history_tests: NotRequired[Annotated[int, doc("tests held for late viewers")]]
    history_length_points: NotRequired[Annotated[int, doc("bar-length points held (1 per second)")]]
    trend_points: NotRequired[Annotated[int, doc("trend points held")]]
    sent_mib: NotRequired[Annotated[float, doc("estimate of what the sink was sent", "MiB")]]
    history_pending: NotRequired[Annotated[int, doc("history steps still to send")]]
    batches: NotRequired[Counter]
    samples: NotRequired[Counter]
    messages: NotRequired[Counter]
    flushes: NotRequired[Counter]
    length_sends: NotRequired[Counter]
    polar_draws: NotRequired[Counter]
    sinks: NotRequired[Counter]
    refreshes: NotRequired[Counter]
    errors: NotRequired[Counter]
    skipped: NotRequired[Counter]
    server_stalls: NotRequired[Annotated[int, doc("serve mode: restarts asked of the server, which took none of the "
                                                  "stream")]]
    server: NotRequired[RerunServer]


RerunStats = RerunStarting | RerunViewer


class MonitorStats(TypedDict):
    """the monitor ([limits] on)"""

    tests: Annotated[int, doc("test results it took")]
    alerts: Annotated[int, doc("alerts sent")]
    errors: Annotated[int, doc("verdicts it could not give, state it could not write")]
    history: Annotated[int, doc("tests in its trend history")]


class SetsStats(TypedDict):
    """the test sets' (absent: no [sets])"""

    tests: Annotated[int, doc("test results of a set's plan taken in")]
    sets: Annotated[int, doc("set results sent")]
    errors: Annotated[int, doc("sets not combined, or their state not written (the log says why)")]


class Outputs(TypedDict):
    """each output's own counters"""

    mcap: NotRequired[McapStats]
    zenoh: NotRequired[ZenohStats]
    rerun: NotRequired[Annotated[RerunStats, doc("the Rerun viewer's counters")]]
    monitor: NotRequired[MonitorStats]
    sets: NotRequired[SetsStats]


class Poll(TypedDict):
    """a polled gauge's request/answer windows (the last few thousand; empty: not polled or no answer yet)"""

    window_median_ms: NotRequired[Annotated[float, doc("the windows' median", "ms")]]
    window_p99_ms: NotRequired[Annotated[float, doc("their 99th percentile", "ms")]]
    window_max_ms: NotRequired[Annotated[float, doc("the longest", "ms")]]
    t_uncertainty_ms: NotRequired[Annotated[float, doc("half the p99 window: how far a stamp may be from its "
                                                       "reading", "ms")]]
    t_jitter_ms: NotRequired[Annotated[float, doc("half the windows' p1..p99 spread", "ms")]]
    achieved_hz: NotRequired[Annotated[float, doc("answers per second over about the last 10 s", "Hz")]]
    answers: NotRequired[Annotated[float, doc("how many answers the figures cover")]]


class SourceStats(TypedDict):
    """the source's running totals"""

    samples: Annotated[int, doc("samples received")]
    lost: Annotated[int, doc("samples reported lost, whatever the cause")]
    batches: NotRequired[Annotated[int, doc("batches read")]]
    bytes_read: NotRequired[Annotated[int, doc("bytes read from the port")]]
    reads: NotRequired[Annotated[int, doc("port reads that returned bytes")]]
    unplugs: NotRequired[Annotated[int, doc("times the port failed")]]
    replugs: NotRequired[Annotated[int, doc("times it came back")]]
    stalls: NotRequired[Annotated[int, doc("stalls")]]
    resets: NotRequired[Annotated[int, doc("device resets")]]
    clock_jumps: NotRequired[Annotated[int, doc("device clock jumps")]]
    connected: Annotated[bool, doc("the port is open")]
    decode: NotRequired[Annotated[Counts, doc("decoder drops by reason")]]
    lost_by_cause: NotRequired[Annotated[Counts, doc("lost samples by cause (gap, outage, stall, ...)")]]
    clock_ratio: Annotated[float | None, doc("host seconds per device second, in device terms (divided by "
                                             "status.speedup, so 1 for a healthy clock)",
                                             null="no device clock yet, or under 5 s of it")]
    clock_offset_s: NotRequired[Annotated[float | None, doc("t_host = clock_offset_s + clock_ratio * t_device / "
                                                            "speedup", "s")]]
    drift_ppm: Annotated[float | None, doc("the device clock's drift against the host's, in device terms", "ppm",
                                           null="unknown")]
    poll: NotRequired[Poll]


class Worker(TypedDict):
    """the child process that fits each test (absent: daemon.analysis_worker is off)"""

    pid: Annotated[int | None, doc("its process id", null="starting")]
    started: Annotated[int, doc("processes started: 1, one more each time one died")]
    busy: Annotated[bool, doc("a test's fit is running in it")]


class AnalysisStats(TypedDict):
    """the analysis"""

    results: Annotated[int, doc("circle and test results")]
    tests: Annotated[int, doc("test results")]
    fit_latency_ms: Annotated[float | None, doc("how long the last result's fit took", "ms", null="none yet")]
    invalid_samples: Annotated[int, doc("samples flagged over range or sensor fault (left out)")]
    errors: Annotated[int, doc("times the analysis started afresh")]
    test_id: Annotated[str | None, doc("the current or last test's id", null="none yet")]
    worker: NotRequired[Worker]


SourceState = Literal["starting", "waiting", "connected", "stalled", "unplugged", "ended"]


class ControllerStats(TypedDict):
    """the CNC controller's OPC UA client ([controller]; absent: no [controller] section)"""

    state: Annotated[Literal["connecting", "connected", "lost", "stopped"], doc(
        "connecting (never connected yet, or retrying after a failed attempt), connected, lost (retrying with "
        "back-off) or stopped")]
    connected: Annotated[bool, doc("the session is up and subscribed")]
    endpoint: Annotated[str, doc("the server's endpoint")]
    last_update_age_s: Annotated[float | None, doc("since the last value received", "s", null="none yet")]
    reconnects: Annotated[int, doc("connections made after the first (each loss and return counts one)")]
    attempts: Annotated[int, doc("connection attempts that failed")]
    updates: Annotated[int, doc("values received")]
    missing: Annotated[list[str], doc("the map's names the server lacks (logged once at each connection)")]
    clock_offset_s: Annotated[float | None, doc("the daemon's wall clock minus the server's (smallest arrival minus "
                                                "source timestamp)", "s", null="not known yet")]
    clock_jumps: Annotated[int, doc("times the server's clock jumped (by more than 2 s or four publishing "
                                    "intervals): the offset then starts afresh, and a warning says by how much")]
    last_error: Annotated[str | None, doc("why the last attempt failed or the connection was lost", null="none")]


class Status(TypedDict):
    """ballbar.Status: the daemon's periodic status (ballbar/<m>/status, every daemon.status_interval_s)."""

    schema_version: Version
    kind: Annotated[Literal["status"], doc("what the payload is")]
    machine_id: MachineId
    t_wall: TWall
    uptime_s: Annotated[float, doc("since the daemon started", "s")]
    speedup: Annotated[float, doc("device time per host time: 1 for a real device; the simulated device's speed-up "
                                  "under `ballbar run --simulate --speedup`. Rates and clock figures here are in "
                                  "device terms.", exclusiveMinimum=0)]
    source_state: Annotated[SourceState, doc("starting, waiting (never opened yet), connected, stalled, unplugged or "
                                             "ended")]
    source_reason: Annotated[str | None, doc("why the source is waiting or unplugged")]
    source: SourceStats
    samples: Annotated[int, doc("samples read in this run")]
    sample_rate_hz: Annotated[float, doc("samples per second of device time since the last status", "Hz")]
    lost_samples: Annotated[int, doc("samples reported lost in this run")]
    queues: Annotated[dict[str, Queue], doc("each output's queue, by name (analysis, mcap, zenoh, rerun, log)")]
    outputs: Outputs
    analysis: AnalysisStats
    controller: NotRequired[ControllerStats]
