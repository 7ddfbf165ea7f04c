"""The daemon's MCAP recordings: every sample, event, result, status and the configuration.

:class:`McapLogger` (:mod:`.writer`) is the listener (name ``"mcap"``) that writes them;
:func:`read_mcap` and :func:`read_log` (:mod:`.reader`) read them back, also from files whose
writer was killed; :func:`recover_crashed` (:mod:`.recovery`) rewrites such files once; :mod:`.format`
holds the names, channels, schemas and the samples' encoding.  Any MCAP reader opens the files (Foxglove, the ``mcap``
CLI, the ``mcap`` Python and npm packages): every channel is JSON
(``message_encoding = "json"``) with a JSON Schema (``encoding = "jsonschema"``).

Files
-----
``STATE_DIR/recordings/<machine>_<UTC start, YYYYmmddTHHMMSSZ>_<seq>.mcap``; the
names sort in time order.  A file starts with a metadata record ``ballbar``
(``format`` = ``ballbar-mcap/1``, ``machine_id``, ``host_clock_offset_ns``, ``run_id`` (one per
daemon start), ``created_utc``, ``reason`` = start, test, size, age or recovery, ``software``).
A new file begins at each test (the analysis's ``feed_in`` event), when a file
reaches ``rotate_bytes`` or ``rotate_s``, and after a write error.  Size and
age rotations wait for a test in progress to end (up to twice the limit), so
that a test is never split.  The per-test file first repeats the last
``preroll_s`` seconds of samples (flagged ``preroll``) since the feed-in was
recognised a little after it happened: a test's file holds the whole test, and
``ballbar analyze FILE`` finds it as the file's first test.  Retention runs at
each new file and every minute: the oldest files go while the directory holds
more than ``quota_bytes``, and every file last written more than ``keep_days``
ago; the open file never goes, nor files not named like the logger's.  The logger holds an exclusive
``flock`` on the file it writes; recovery and retention leave any file so held (another process's) alone.

Channels
--------
All times are integer nanoseconds.  ``log_time`` is host wall-clock time (Unix
epoch, UTC): the host's monotonic clock plus ``host_clock_offset_ns``, measured
once when the logger starts, so that wall-clock steps (NTP) never reorder
samples.  ``publish_time`` is the wall-clock time the record was written.

``/ballbar/samples`` (schema ``ballbar.Samples``): the samples, one message per
flush (about ``flush_s`` of them), columns delta-encoded as JSON integer arrays::

    {"source": "serial:/dev/ttyUSB0", "count": n, "preroll": false,
     "seq_first": 1000, "seq_delta": [1, 1, ...],                       # n - 1 each
     "t_host_first": {"sec": 1767225600, "nsec": 5000}, "t_host_delta_ns": [1000013, ...],
     "t_device_first": {"sec": 12, "nsec": 0}, "t_device_delta_ns": [1000000, ...],
     "length_first_pm": 100001234567, "length_delta_pm": [-120, 87, ...],
     "length_missing": [],                                              # sample indices
     "status": [0, 0, ...]}                                             # n

    value[0] = *_first, value[i] = value[i-1] + *_delta[i-1]

``seq``: the source's sample number.  ``t_host``: when the sample was taken,
on the host's clock (wall-clock ns, see above).  ``t_device``: the device's
sample clock, ns, or ``null`` (both fields) where the source has none.
``length``: the absolute bar length in picometres (1e-9 mm); indices in
``length_missing`` had no number (NaN: a sensor fault) and hold the previous
value as a placeholder.  ``status``: :class:`ballbar.protocol.Status` bits
(1 over range, 2 sensor fault: not measurements; 128 simulated).
``preroll``: samples repeated at the head of a per-test file; the previous file
ended with them.  ``log_time`` is the first sample's host time.  Times and
lengths are stored to 1 ns and 1 pm, the resolution of the CSV format; read
back, each value is the stored integer divided by 1e9 (a correctly rounded
double), the same number the CSV would give.

``/ballbar/events`` (``ballbar.Event``): ``{"event": NAME, "t_host": s, ...}``;
a source's events (``opened``, ``unplugged``, ``replugged``, ``lost`` with
``count`` and ``seq``, ``decode_errors`` with ``counts``, ``stall``,
``resumed``, ``device_reset`` and ``clock_jump`` with ``seq``, ``end``; the fields of
:meth:`~ballbar.daemon.samples.SourceEvent.to_dict`) and the pipeline's
(``feed_in``, ``feed_out``, ``circle_done``, ``test_rejected``,
``test_incomplete``, ...), plus the logger's own ``log_gap``: ``count`` samples
that could not be written over ``gap_s`` seconds, ``detail`` the error.
``t_host`` is the host's monotonic clock in seconds (``log_time`` is the same
instant on the wall clock).

``/ballbar/results`` (``ballbar.Result``): the analysis results, ``kind`` =
``circle``, ``test`` or ``set`` (a test set, :mod:`ballbar.daemon.sets`), the tests as
``ballbar analyze --json`` prints them plus ``machine_id``, ``test_id``, ``t_host``, ``last_sample_t``,
``last_sample_t_host``, ``latency_ms``.

``/ballbar/status`` (``ballbar.Status``): the daemon's status messages
(``kind`` = ``status``: rates, losses, queue depths, source state).

``/ballbar/config`` (``ballbar.Config``): the effective configuration
(``kind`` = ``config``), at start and again at the head of every new file.
A polled source's last ``timing`` event is repeated likewise (``repeated``:
true), so that a test's file alone says how its samples were stamped.

``/ballbar/other`` (``ballbar.Message``): any other message kind, as it came.

Crash safety
------------
Chunks are zstd-compressed and closed (``Writer.flush``) at most ``flush_s``
(0.5 s) after the first record in them was handed over, or for samples after
the first of them was read (their host time: the pipeline hands samples over
merged about every 0.25 s, and the time they waited counts), by a small flush
thread that sleeps until that deadline, whatever the caller does; the kernel
then has them, so a killed daemon (``kill -9``) loses at most that last half
second (a power cut can lose more: files are fsync'ed only when closed).
:func:`read_log` reads such a file up to its last whole chunk.  ``stop()``
(SIGTERM) writes the footer and indexes.

Write errors
------------
A full disk (``ENOSPC``) or any other ``OSError`` on write: one ``ERROR`` log
line, the file is dropped (what reached it stays readable; an empty one is
deleted), its unwritten samples and all that follow are counted as lost, and
a new file is tried after a backoff (``retry_min_s`` doubling to
``retry_max_s``); after a full disk, as soon as a ``statvfs`` every
``space_probe_s`` sees :meth:`McapLogger.headroom` free (what one file needs,
up to ``headroom_bytes`` and a 64th of the file system).  The first file that
works again starts with a ``log_gap`` event and a ``WARNING`` log line.
Results and events meanwhile are held in memory and written after it; at stop,
what no file can take goes to the spool (:mod:`.spool`), which the next start
writes.  Nothing is raised into the pipeline.

Reading
-------
The readers take any file: a cut one up to its last whole record, a damaged
chunk (garbled bytes: it does not decompress or its CRC is wrong) skipped to the
next whole chunk (the byte ranges in one warning, the samples' gap a break of
the analysis), a record or chunk larger than :data:`MAX_RECORD_BYTES` as the end
of the file where no whole chunk follows it, at most
:data:`SIDE_BYTES_MAX` of events, results and status from one file; anything
else wrong is one :class:`~ballbar.analysis.errors.DataError` line naming the
file (and, for a directory, :func:`read_logs` with ``skip_bad`` leaves such a
file out with a warning).
"""

from .format import (
    MAX_RECORD_BYTES,
    SCHEMAS,
    TOPIC_CONFIG,
    TOPIC_CONTROLLER,
    TOPIC_EVENTS,
    TOPIC_OTHER,
    TOPIC_RESULTS,
    TOPIC_SAMPLES,
    TOPIC_STATUS,
    LogConfigError,
    decode_samples,
    encode_samples,
    list_recordings,
    mcap_files,
    scaled_ints,
)
from .reader import McapLog, read_controller, read_log, read_logs, read_mcap, read_results, recording, valid_samples
from .recovery import recover_crashed
from .writer import FILE_NEEDS_BYTES, McapLogger

__all__ = [
    "FILE_NEEDS_BYTES",
    "MAX_RECORD_BYTES",
    "SCHEMAS",
    "TOPIC_CONFIG",
    "TOPIC_CONTROLLER",
    "TOPIC_EVENTS",
    "TOPIC_OTHER",
    "TOPIC_RESULTS",
    "TOPIC_SAMPLES",
    "TOPIC_STATUS",
    "LogConfigError",
    "McapLog",
    "McapLogger",
    "decode_samples",
    "encode_samples",
    "list_recordings",
    "mcap_files",
    "read_controller",
    "read_log",
    "read_logs",
    "read_mcap",
    "read_results",
    "recording",
    "recover_crashed",
    "scaled_ints",
    "valid_samples",
]
