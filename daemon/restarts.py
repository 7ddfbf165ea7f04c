"""Samples lost across a restart, counted at the next start by the device's own sample counter.

A daemon that stops (SIGTERM) or is killed (``kill -9``: its last half second or so of reading never reached
the file) leaves a gap between the last sample its recordings hold and the first the next start reads: what the
device sent meanwhile, and what the serial port held at the reopen.  At start, before the first read,
:func:`resume_count` finds the newest recorded sample (:func:`~ballbar.daemon.mcap.recovery.last_recorded`)
and, where it came from the same source and the source has a device counter (the binary protocol), hands it to
the source (:meth:`~ballbar.daemon.sources.Source.resume`): the first read is then stamped as following it, and
the sources' own rules count the gap, as any gap is counted: a counter that stepped on by ``n`` is ``n - 1``
samples ``lost`` (detail ``restart``: the status's ``lost_samples``, the source's ``lost_by_cause``, an event in
the new file and on the bus), one that went back a ``device_reset`` (the device restarted meanwhile: how many
were lost is unknown and nothing is counted), a clock that disagrees with the counter a ``clock_jump``.  The
counter's wraps (2**32) are its own; the device clock's wraps (71 min) are counted from the counter's step.

The sample numbers the daemon hands out follow the device's raw counter but for a device reset, after which they
go on by one (so a test's numbers never run back): ``STATE_DIR/device-counter.json`` keeps the offset between
the two (and the device clock's), written at each start and at each device reset, so that the next start can
tell which raw counter value the last recorded number stood for.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

from .mcap.format import RECORDINGS
from .mcap.recovery import last_recorded
from .sources import Source

log = logging.getLogger(__name__)

COUNTER_NAME = "device-counter.json"


def _saved_offsets(state_dir: Path, url: str) -> tuple[int, float]:
    try:
        saved = json.loads((state_dir / COUNTER_NAME).read_text())
        if isinstance(saved, dict) and saved.get("source") == url:
            return int(saved["seq_offset"]), float(saved["clock_offset_s"])
    except (OSError, ValueError, KeyError, TypeError, RecursionError):
        pass
    return 0, 0.0  # none kept (a first start, or a version before): no device reset re-based the numbers


def resume_count(state_dir: str | os.PathLike[str], source: Source) -> bool:
    """Before the first read: have ``source`` count on from the newest recorded sample (see the module
    docstring); whether it does.  Then the counter's offsets are saved for the next start."""
    state = Path(state_dir)
    resumed = False
    last = last_recorded(state / RECORDINGS)
    if last is not None and last.source == source.url:
        resumed = source.resume(last.seq, last.t_device_s, last.period_s, _saved_offsets(state, source.url))
        if resumed:
            log.info("%s: counting on from sample %d, the last recorded (%s): what the device sent until this "
                     "start's first sample is counted lost (restart)", source.url, last.seq, last.path.name)
    elif last is not None:
        log.info("%s: the last recorded samples came from %s: samples lost across the restart are not counted",
                 source.url, last.source)
    save_counter(state, source)
    return resumed


def save_counter(state_dir: str | os.PathLike[str], source: Source) -> None:
    """``STATE_DIR/device-counter.json`` from the source's offsets now (removed where it has no counter)."""
    path = Path(state_dir) / COUNTER_NAME
    offsets = source.counter_offsets()
    try:
        if offsets is None:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
            return
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps({"source": source.url, "seq_offset": offsets[0], "clock_offset_s": offsets[1]}))
        os.replace(tmp, path)
    except OSError as err:  # a full disk: the next start may count a restart after a device reset wrongly
        log.warning("cannot write %s: %s", path, err.strerror or err)


__all__ = ["COUNTER_NAME", "resume_count", "save_counter"]
