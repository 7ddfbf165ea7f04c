"""Sample sources: one interface for every way samples arrive.

A source is opened from a URL (the configuration's ``source`` key) plus typed
keyword options, and delivers :class:`~ballbar.daemon.samples.SampleBatch`
objects::

    with open_source("serial:/dev/ttyUSB0?protocol=binary&rate=1000", cal_mm=100.0012) as src:
        while running:
            batch = src.read(timeout=0.5)   # None: nothing in 0.5 s
            if batch is not None:
                handle(batch)               # columns + batch.events

    for batch in open_source("replay:run.csv?speed=max"):   # until the recording ends
        ...

The interface (:class:`Source`)
-------------------------------
``read(timeout=None) -> SampleBatch | None``
    Blocks until samples or events are available, at most ``timeout`` seconds
    (plus up to ``batch_s``, the batching period, default 20 ms; ``None`` waits
    indefinitely); returns ``None`` on timeout and, for good, after a finite
    source's ``end`` event.  A batch holds what arrived in about ``batch_s``
    (about 200 samples at 10 kHz).  Never raises for bad bytes, an unplugged
    adapter or a stalled device: those are events.  Raises
    :class:`~ballbar.daemon.errors.SourceClosed` after :meth:`Source.close`.
``iter(source)``
    Batches until the source is finished (a replay's end) or closed.
``close()``
    Safe twice and from another thread (it interrupts a blocked ``read``).
    Sources are context managers.
``stats() -> SourceStats``, ``finished``, ``rate_hz``, ``url``.
``pace(period_s)``
    The consumers can take batches ``period_s`` apart for now: the source reads
    that often (never more often than ``batch_s``, never less than every
    ``RELAXED_BATCH_S``) until told otherwise.  The daemon relaxes it while no
    result can be due (between tests, mid-circle) and tightens it back to
    ``batch_s`` as one nears: the 20 ms batches where latency counts, a
    wake-up as seldom as the outputs merge (every 0.25 s) where it does not:
    each wake-up costs a read's fixed part again (about 0.7 ms of a CPU whose
    caches went cold meanwhile), however few samples it brings.  A serial port
    is never left to hold more than ``TTY_READ_BYTES`` between reads (at the
    byte rate it has been seen to run): past the line discipline's 4 KiB buffer
    the kernel throttles the adapter, and a device without flow control
    overruns.  Where that is sooner than the batch is due (``drain_s``: 1 kHz
    at 17 kB/s every 0.18 s; 10 kHz, or 1 kHz sped up 20 times, every 20 ms)
    the port is read that often, but what is read is only gathered, and
    decoded and stamped once per batch.

A serial source makes at most one batch per batch period (``read_s``) while
samples flow: it sleeps to the next boundary of a ``read_s`` grid on the
monotonic clock, waking every ``drain_s`` on the way to gather what the port
has, and decodes it all at the boundary; when nothing came (idle, or a device
slower than one sample per batch period) it waits for the first bytes with
``poll()`` and takes them at once.  The port's settings (its timeout among
them) are applied once, at open: pyserial re-applies termios and the lock on
each assignment.  ``stats().reads`` counts the reads that returned bytes.

Call ``read`` from one thread that does nothing else (the pipeline's reader):
a serial port's kernel buffer holds only a few tenths of a second at 10 kHz,
so a consumer that is slow must be decoupled by a queue, not by reading late.

URL scheme
----------
``serial:PORT[?options]``
    ``PORT`` is a device path (``/dev/ttyUSB0``, ``/dev/serial/by-id/...``, a
    pty or the link that ``ballbar.tools.simdevice`` prints) or any pyserial
    URL (``loop://``, ``socket://host:port``, ``rfc2217://host:port``);
    ``serial:///dev/ttyUSB0`` is accepted too, and a bare ``/dev/...`` path or
    pyserial URL means ``serial:``.  Options:

    ``protocol``  ``binary`` (default), ``ascii``, or a gauge profile:
                  ``mitutoyo``, ``sylvac``, ``tesa`` (``protocol/README.md``;
                  a profile sets the framing, request, mode, baud and line
                  settings, error words and unit, each of which an option
                  below may override)
    ``mode``      ``stream`` (default) or ``poll`` (ascii and profiles: the
                  host sends ``request`` once per period and reads one
                  answer; a polled profile's default)
    ``cal_mm``    required: the bar's length at zero displacement (its
                  calibration), added to every reading: ``L = cal_mm + x``
    ``rate``      nominal sample rate in Hz, 15.625..10000 (required for
                  ``poll``; for ascii lines with a timestamp it lets lost lines
                  be counted; it sets the stall timeout's default)
    ``baud``      default 2000000 (10 kHz of binary frames needs 1.7 Mbaud;
                  ptys and USB CDC devices ignore it); a profile's own default
                  (Mitutoyo 9600, Sylvac and TESA 4800).  A profile's rate
                  beyond what the line carries at this baud is refused
    ``framing``   data bits, parity, stop bits: ``8N1`` (default), a
                  profile's own (``7E2`` for Sylvac and TESA)
    ``unit``, ``scale``, ``timestamp`` (``s``, ``ms``, ``us``; absent: none),
    ``max_line``, ``request`` (percent-encoded, default ``%3F%0D`` = ``?\\r``)
                  the ASCII format (:class:`~ballbar.protocol.AsciiFormat`)
    ``batch_s``   batching period, default 0.02
    ``stall_s``   silence that counts as a stall, default max(0.5, 20 periods)
    ``poll_timeout_s``  answer timeout in poll mode, default max(0.05, 2 periods)
    ``retry_min_s``, ``retry_max_s``  reopen backoff after an unplug, 0.05..2 s
    ``exclusive`` lock the port against a second reader (default true)

``sim:[?options]``
    The in-process simulator (``ballbar.tools.simulator``) on the host clock:
    ``rate`` (Hz, default the plan's), ``speedup`` (default 1; ``max`` = as
    fast as possible), ``seed`` (0), ``repeat`` (number of tests, default 1;
    0 = forever), ``gap_s`` (between tests, 0), ``batch_s``.  Keyword options
    ``plan`` (:class:`~ballbar.analysis.plan.TestPlan`) and ``machine``
    (``MachineModel``) say what to simulate; or ``library`` (a
    :class:`~ballbar.analysis.plans.PlanLibrary` of several), ``run_plans``
    (which of its plans, in turn; default all) and ``machine`` (a
    ``Machine3D``: ``ballbar.tools.machine3d``), a set of tests on a machine
    with X, Y and Z errors, each program with its signature, the lengths as
    the bar assembled for each plan reads them.  Samples carry ``SIMULATED``.

``replay:PATH[?options]``
    A recording (CSV ``t_s,length_mm`` now; the daemon's MCAP later):
    ``speed`` (1 = real time, default; 10 = ten times faster; ``max`` = as fast
    as possible), ``rate`` (Hz: sample numbers from the recorded times, so that
    gaps count as lost; default: one number per row), ``batch_s``.

Every option may also be given as a keyword argument of :func:`open_source`
(``cal_mm=100.0``, ``rate=1000``); giving one both ways is an error, and so is
an unknown key (named in the message).

Time stamps
-----------
``t_device`` is the device's sample clock where the protocol has one (binary
frames; ASCII lines with a timestamp), unwrapped.  ``t_host`` is that clock
mapped to ``time.monotonic`` by :class:`~ballbar.daemon.timebase.ClockMap`
(lower envelope of read times, with the drift in ``stats().drift_ppm``).
Without a device clock, ``t_host`` is the host's estimate: sample numbers at the
nominal rate mapped the same way, or the read time when no rate is known; in
poll mode the midpoint between request and answer: a polled gauge has no
clock, and when within that window it took its reading is not known.  The
windows' median, p99 and the achieved rate are in ``stats().poll``; the
half-window's p99 (the stamps' uncertainty) goes out as a ``timing`` event
when first known and whenever it grows by a quarter, and the analysis of such
samples states it (:mod:`ballbar.analysis.polled`).  Replays and the simulator
place their own time base on the host clock at their speed.

Losses and faults
-----------------
A gap in the device's sample counter is reported as a ``lost`` event with its
exact count (never interpolated or papered over).  An unplugged adapter (the
port raises mid-read, or cannot be opened at start) is an ``unplugged`` event;
the source retries with exponential backoff and reports ``replugged`` with the
outage when the port returns, then the samples lost across it.  A device that
stops sending is a ``stall``, then ``resumed``.  A restarted device (its
counter went back, or without a counter its clock) is a ``device_reset``, a device
clock that steps by more than its counter says (ahead, or back while the counter
runs on) a ``clock_jump``, a counter that leaps while the clock runs on a
``counter_jump`` (a counter fault: nothing lost, the numbers run on by the clock);
each names the first sample after it (``seq``), so that the analysis can place
the break exactly.  Decoder drops are logged at INFO, at most once per 10 s
with the counts since.  A source with a
device counter (binary frames) can be told, before its first read, the last sample a
previous daemon run recorded (:meth:`Source.resume`, :mod:`ballbar.daemon.restarts`):
the samples the restart lost are then a ``lost`` event (detail ``restart``), by the
same rules.
"""

from .base import DEFAULT_BATCH_S, RATE_MAX_HZ, RATE_MIN_HZ, RELAXED_BATCH_S, TTY_READ_BYTES, Source
from .paced import ReplaySource, SimSource
from .serial import SerialSource
from .urls import check_source, open_source, register_source, source_schemes, split_url

__all__ = [
    "DEFAULT_BATCH_S",
    "RATE_MAX_HZ",
    "RATE_MIN_HZ",
    "RELAXED_BATCH_S",
    "TTY_READ_BYTES",
    "ReplaySource",
    "SerialSource",
    "SimSource",
    "Source",
    "check_source",
    "open_source",
    "register_source",
    "source_schemes",
    "split_url",
]
