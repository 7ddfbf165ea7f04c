"""Gauge profiles over a pty: the simulated gauge in a child process, a source in this one; each fault the
gauge can show is counted, stated in the events and stats, and the source reads on."""

from __future__ import annotations

import math
import os
import pty
import select
import time
import tty

import numpy as np
import pytest
from test_simdevice import PLAN_ARGS, finish, start

from ballbar.daemon.errors import SourceConfigError
from ballbar.daemon.samples import SampleBatch
from ballbar.daemon.sources import check_source, open_source
from ballbar.protocol import Status

pytestmark = pytest.mark.usefixtures("no_leaks")


def test_polled_sylvac_error_words_cut_late_and_silent() -> None:
    dev, col = start("--protocol=sylvac", "--rate=1000", "--repeat=0", *PLAN_ARGS)
    try:
        assert "protocol=sylvac" in dev.url and "rate=15.625" in dev.url
        col.until(lambda: col.n >= 20, 10.0, "20 answers")
        dev.send("error over 2")
        dev.send("error fault 1")
        col.until(lambda: col.n >= 30, 10.0, "the error words")
        lost = lambda cause: col.src.stats().lost_by_cause.get(cause, 0)  # noqa: E731
        dev.send("cut 2")
        col.until(lambda: lost("poll_timeout") >= 2, 10.0, "2 cut answers timed out")
        n0 = col.n
        col.until(lambda: col.n >= n0 + 10, 10.0, "answers after the cut ones")
        dev.send("late 0.5 1")
        col.until(lambda: lost("poll_timeout") >= 3, 10.0, "a late answer timed out")
        n1 = col.n
        col.until(lambda: col.n >= n1 + 20, 10.0, "answers after the late one")
        dev.send("stall 2")  # the gauge stops answering for 2 s
        col.until(lambda: "resumed" in col.kinds(), 10.0, "the gauge answering again")
        n2 = col.n
        col.until(lambda: col.n >= n2 + 10, 10.0, "answers after the silence")
        st = col.src.stats()
        stats = dev.stats()
    finally:
        finish(dev, col)
    got = col.merged()
    # Error words are samples without a length, flagged: ERR3 over range, ERR0 a sensor fault.
    over = got.status & int(Status.OVER_RANGE) != 0
    fault = got.status & int(Status.SENSOR_FAULT) != 0
    assert int(over.sum()) == 2 and int(fault.sum()) == 1
    assert np.isnan(got.length_mm[over | fault]).all() and np.isfinite(got.length_mm[~(over | fault)]).all()
    # The two cut answers: dropped, counted, never parsed; no bad line came of them.
    assert st.decode.get("cut_line") == 2 and st.decode.get("bad_line", 0) == 0
    # The late answer timed out; when it came it was no answer to a request in flight.
    late_seen = st.decode.get("stale_bytes", 0) + st.decode.get("unsolicited", 0)
    assert late_seen >= 1
    # The silence: a stall, every tick of it a counted loss, and the source read on.
    assert "stall" in col.kinds() and st.stalls == 1
    # (each tick of the 2 s a request unanswered, or one a loaded host woke too late to send)
    assert lost("poll_timeout") + lost("poll_late") >= 3 + 2 * 15.625 - 2
    assert got.seq[-1] - got.seq[0] + 1 == st.samples + st.lost
    assert st.samples <= stats["requests"]
    # The status's windows: median and p99 of the request/answer windows, the rate achieved.
    poll = st.poll
    assert 0 < poll["window_median_ms"] <= poll["window_p99_ms"] and poll["achieved_hz"] > 0
    timing = [e for e in col.events if str(e.kind) == "timing"]
    assert timing and timing[0].values["t_uncertainty_s"] > 0


def test_streaming_sylvac_and_its_error_words() -> None:
    dev, col = start("--protocol=sylvac", "--mode=stream", "--rate=15.625", "--repeat=0", *PLAN_ARGS)
    try:
        assert "mode=stream" in dev.url
        col.until(lambda: col.n >= 10, 10.0, "10 lines")
        dev.send("error over 1")
        col.until(lambda: bool((col.merged().status & int(Status.OVER_RANGE)).any()), 10.0, "ERR3")
        st = col.src.stats()
    finally:
        finish(dev, col)
    assert st.poll == {} and st.decode.get("bad_line", 0) == 0
    got = col.merged()
    assert np.all(np.diff(got.t_host) > 0)


def test_mitutoyo_has_no_error_word_and_does_not_stream() -> None:
    dev, col = start("--protocol=mitutoyo", "--rate=1000", "--repeat=0", *PLAN_ARGS)
    try:
        with pytest.raises(ValueError, match="no error words"):
            dev.send("error over 1")
        col.until(lambda: col.n >= 10, 10.0, "10 answers")
    finally:
        finish(dev, col)
    assert all(math.isfinite(x) for x in col.merged().length_mm.tolist())


@pytest.mark.parametrize(
    ("url", "message"),
    [
        ("serial:/dev/ttyNOPE?protocol=mitutoyo&rate=100&cal_mm=1", "at most 68.6 Hz"),
        ("serial:/dev/ttyNOPE?protocol=sylvac&rate=50&cal_mm=1", "4800 baud"),
        ("serial:/dev/ttyNOPE?protocol=tesa&rate=40&cal_mm=1", "at most 33.6 Hz"),
        ("serial:/dev/ttyNOPE?protocol=mitutoyo&mode=stream&rate=15.625&cal_mm=1", "does not stream"),
        ("serial:/dev/ttyNOPE?protocol=mitutoyo&cal_mm=1", "needs rate"),
        ("serial:/dev/ttyNOPE?protocol=tesa&rate=15.625&cal_mm=1&framing=9X1", "framing"),
        ("serial:/dev/ttyNOPE?protocol=keyence&rate=15.625&cal_mm=1", "must be one of"),
    ],
)
def test_a_rate_the_line_cannot_carry_is_refused_before_the_port_opens(url: str, message: str) -> None:
    with pytest.raises(SourceConfigError, match=message):
        check_source(url)


def test_a_faster_line_carries_a_faster_rate() -> None:
    check_source("serial:/dev/ttyNOPE?protocol=mitutoyo&rate=100&baud=115200&cal_mm=1")
    check_source("serial:/dev/ttyNOPE?protocol=sylvac&mode=stream&rate=40&cal_mm=1")  # no request on the line


def test_an_answer_waiting_when_a_late_host_wakes_is_taken_not_timed_out() -> None:
    """A loaded host wakes after the answer timeout: the gauge answered in time and its answer waits in the
    port.  It is a sample (its long window counted in the stamps' uncertainty), not a lost one, and no
    stale bytes are dropped.  (Before: a poll_timeout and the answer discarded as stale.)"""
    master, slave = pty.openpty()
    tty.setraw(slave)
    src = open_source(f"serial:{os.ttyname(slave)}?protocol=mitutoyo&rate=15.625&cal_mm=0")
    got: list[SampleBatch] = []
    try:
        request = b""
        end = time.monotonic() + 5.0
        while b"1" not in request and time.monotonic() < end:  # the mitutoyo request: "1"
            if (batch := src.read(0.02)) is not None:
                got.append(batch)
            if select.select([master], [], [], 0)[0]:
                request += os.read(master, 64)
        assert b"1" in request, request
        os.write(master, b"01A+0000.123\r")  # the gauge answers at once...
        time.sleep(3 * src.poll_timeout_s)  # ... and the host wakes late
        end = time.monotonic() + 2.0
        while sum(len(b) for b in got) < 1 and time.monotonic() < end:
            if (batch := src.read(0.05)) is not None:
                got.append(batch)
        st = src.stats()
    finally:
        src.close()
        os.close(master)
        os.close(slave)
    samples = SampleBatch.concat(got)
    assert len(samples) >= 1 and samples.length_mm[0] == pytest.approx(0.123)
    assert st.lost_by_cause.get("poll_timeout", 0) == 0 and st.decode.get("stale_bytes", 0) == 0, st
    timing = src.poll_timing()
    assert timing is not None and timing["window_max_ms"] >= 3e3 * src.poll_timeout_s
