"""A simulated ball-bar interface on a pseudo-terminal: the device the daemon's demo
and end-to-end tests run against.

It opens a pty (or a given port), prints the device path on the first line of
stdout, and streams the simulated test of :mod:`ballbar.tools.simulator` (or a
CSV recording) in the binary or ASCII protocol (``protocol/README.md``) at a
chosen sample rate and speed-up, repeating tests on a schedule::

    python -m ballbar.tools.simdevice --protocol binary --rate 1000 --speedup 10 --repeat 0 --gap-s 30

stdout, one line each:

1. the device path: a stable symbolic link to the current pty (``--link``, by
   default in a fresh temporary directory), which survives unplug and replug
   the way ``/dev/serial/by-id/...`` links do;
2. ``{"event": "ready", "path": ..., "url": ...}``: a source URL that reads it
   (``ballbar.daemon.sources.open_source(url)``);
3. and on: one JSON object per command answered and per event (``started``,
   ``unplugged``, ``replugged``, ``test``, ``done``).

ASCII lines are fixed width (zero-padded reading and timestamp), as gauges
write them.  ``--protocol mitutoyo|sylvac|tesa`` is a gauge interface of that
profile (``ballbar.protocol.gauges``): its framing, request and error words;
polled unless ``--mode stream`` (Sylvac and TESA stream too).  A polled gauge
converts at ``--rate`` (device time) and answers each request with its latest
conversion; the URL it prints polls at ``--poll-rate`` (15.625 Hz).  Its line
is emulated at ``--line-baud`` (default: the profile's baud; 0: as fast as the
pty): an answer is written when its last byte would have arrived, after the
request's and its own bytes at that baud.  Device time runs ``speedup`` times faster than wall time: at ``--rate 1000
--speedup 10`` the device clock and sample counter advance as at 1 kHz and
10 000 frames leave per wall second.  Samples go out as they fall due, but
at most one write per ``--burst-ms`` (16 ms, the default latency timer of FTDI
adapters, which deliver in bursts too): at 15.625 Hz each sample on time, at
1 kHz 16 in one write.  The device sleeps in between; the frames and their
counter and clock are the same as with one write per sample (the samples of a
test are encoded a few thousand at a time, ahead of need).  If the reader does
not keep up (the pty buffer fills), the device waits rather than losing samples;
samples are lost only on command.  The simulated interface is powered on its own: across an
unplug or a stall it keeps sampling, so its counter shows the gap.

Commands on stdin, one per line (EOF on stdin is ignored unless ``--exit-on-eof``,
which :class:`DeviceProcess` passes so that its device ends with its parent; SIGTERM ends it):

``start``           begin streaming (with ``--wait``)
``garbage N``       send N junk bytes before the next sample (binary: no byte
                    ``A5`` or ``5A``, so no false sync word; ASCII: one junk line
                    of N bytes, counted as one ``bad_line``)
``corrupt N``       corrupt the next N samples (binary: one bit flipped after the
                    sync word; ASCII: a character of the reading replaced): each
                    costs one lost sample and one ``bad_crc``/``bad_line``
``drop N``          do not send the next N samples (lost)
``stall S``         send nothing for S wall seconds; the samples taken are lost
``unplug [S]``      close the pty (and remove the link); replug after S seconds if given
``replug``          open a new pty behind the same link
``reset``           restart the sample counter and clock at 0 (a device reboot)
``error over|fault [N]``  a gauge profile: answer the next N requests (or send the
                    next N lines) with the profile's over-range or sensor-fault
                    error word (Sylvac ``ERR3``, ``ERR0``; TESA ``ERR<n>``; a
                    Mitutoyo answer has no error word: refused)
``late S [N]``      polled: the next N answers come S wall seconds late
``cut [N]``         polled: the next N answers are cut after half their bytes
                    (no line end), as by a cable pulled mid-answer
``jump S``          the device clock jumps S seconds ahead (S > 0); the counter
                    runs on and no sample is lost
``stats``           counters so far
``quit``            exit
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import select
import signal
import stat
import sys
import tempfile
import time
import urllib.parse
from collections.abc import Sequence
from typing import Any

from ballbar.protocol import ascii as ascii_proto

from .simbar import BURST_S, PtyPort, SerialPort, Settings, SimDevice
from .simfeed import Feed, csv_tests, plans_of, simulator_tests

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- driving it


class DeviceProcess:
    """The device as a child process, driven through its stdin and stdout.

    For tests and demos::

        with DeviceProcess("--rate", "1000", "--wait") as dev:
            src = open_source(dev.url)
            dev.send("start")
            dev.send("drop 5")
            done = dev.wait_event("done", timeout=30)

    No threads: stdout is read with ``select`` as replies are awaited.  ``wait=False``
    returns at once, before the device is up (it simulates its first test first):
    :meth:`wait_ready` then says when its port is there.
    """

    def __init__(self, *args: str, timeout: float = 15.0, wait: bool = True) -> None:
        import subprocess

        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ballbar.tools.simdevice", "--exit-on-eof", *args],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
        )
        assert self.proc.stdout is not None and self.proc.stdin is not None
        self._out = self.proc.stdout
        self._in = self.proc.stdin
        self._buf = b""
        self.events: list[dict[str, Any]] = []
        self.path = ""
        self.ready: dict[str, Any] = {}
        self.url = ""
        if wait:
            try:
                if not self.wait_ready(timeout):
                    raise TimeoutError(f"simdevice: not ready within {timeout} s")
            except Exception:
                self.close()
                raise

    def wait_ready(self, timeout: float) -> bool:
        """Whether the device is up (its port path and ``ready`` line read), waiting up to ``timeout`` s.

        Raises :class:`EOFError` if it exited first (a bad argument: its stderr says why).
        """
        deadline = time.monotonic() + timeout
        try:
            if not self.path:
                self.path = self._line(timeout)
            if not self.ready:
                self.ready = json.loads(self._line(max(0.0, deadline - time.monotonic())))
                self.url = self.ready["url"]
        except TimeoutError:
            return False
        return True

    def _line(self, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        fd = self._out.fileno()
        while b"\n" not in self._buf:
            ready, _, _ = select.select([fd], [], [], max(0.0, deadline - time.monotonic()))
            if ready:
                chunk = os.read(fd, 65536)
                if not chunk:
                    raise EOFError(f"simdevice exited (code {self.proc.poll()})")
                self._buf += chunk
            elif time.monotonic() >= deadline:
                raise TimeoutError(f"simdevice: no output within {timeout} s")
        line, self._buf = self._buf.split(b"\n", 1)
        return line.decode()

    def _pump(self, timeout: float) -> dict[str, Any]:
        obj: dict[str, Any] = json.loads(self._line(timeout))
        if "event" in obj:
            self.events.append(obj)
        return obj

    def send(self, command: str, timeout: float = 10.0) -> dict[str, Any]:
        """Send a command; its reply (events seen meanwhile go to :attr:`events`)."""
        self._in.write(command.encode() + b"\n")
        self._in.flush()
        deadline = time.monotonic() + timeout
        while True:
            obj = self._pump(max(0.0, deadline - time.monotonic()))
            if "ok" in obj:
                if not obj["ok"]:
                    raise ValueError(f"simdevice: {command!r}: {obj.get('error')}")
                return obj

    def poll_events(self) -> list[dict[str, Any]]:
        """Events that have arrived, without waiting."""
        while b"\n" in self._buf or select.select([self._out.fileno()], [], [], 0)[0]:
            try:
                self._pump(0.5)
            except (TimeoutError, EOFError):
                break
        return self.events

    def wait_event(self, name: str, timeout: float = 30.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        seen = 0
        while True:
            for ev in self.events[seen:]:
                if ev.get("event") == name:
                    return ev
            seen = len(self.events)
            self._pump(max(0.0, deadline - time.monotonic()))

    def stats(self) -> dict[str, Any]:
        stats: dict[str, Any] = self.send("stats")["stats"]
        return stats

    def close(self, timeout: float = 5.0) -> int | None:
        """Ask it to quit (end it if it is not up yet), wait, kill it if it will not; close the pipes."""
        import subprocess

        if self.proc.poll() is None:
            if not self.url:
                self.proc.terminate()  # not up yet: it reads no command until it is
            else:
                with contextlib.suppress(OSError, ValueError):
                    self._in.write(b"quit\n")
                    self._in.flush()
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout)
        for pipe in (self._in, self._out):
            with contextlib.suppress(OSError):
                pipe.close()
        return self.proc.returncode

    def __enter__(self) -> DeviceProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ----------------------------------------------------------------------------- main


def _parser() -> argparse.ArgumentParser:
    from ballbar.tools.simulator_cli import machine_keys_help

    p = argparse.ArgumentParser(
        prog="python -m ballbar.tools.simdevice",
        description="A simulated ball-bar interface on a pty; fault injection on stdin (see the module docstring).",
        epilog=machine_keys_help(), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from ballbar.protocol.gauges import PROFILES

    p.add_argument("--protocol", choices=["binary", "ascii", *PROFILES], default="binary",
                   help="a wire format, or a gauge interface's profile (protocol/README.md)")
    p.add_argument("--mode", choices=["stream", "poll"],
                   help="ascii and gauges: answer requests (poll); default stream, a polled gauge's poll")
    p.add_argument("--poll-rate", type=float, default=15.625, help="a polled gauge: the rate its printed URL asks")
    p.add_argument("--line-baud", type=int, help="a gauge: the emulated line's baud (default the profile's; 0: none)")
    p.add_argument("--rate", type=float, default=1000.0, help="device sample rate, Hz (15.625..10000)")
    p.add_argument("--speedup", type=float, default=1.0, help="device time per wall time")
    p.add_argument("--port", help="use this port (path or pyserial URL) instead of a new pty")
    p.add_argument("--baud", type=int, default=2_000_000, help="with --port")
    p.add_argument("--link", help="stable path to the pty (a symbolic link); default in a temporary directory")
    p.add_argument("--csv", help="stream this recording (t_s,length_mm) instead of the simulator")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--drift", action="append", default=[], metavar="KEY=RATE",
                   help="a machine key that changes by RATE from one test to the next, e.g. backlash_x_um=0.5 "
                   "(a machine that wears; repeatable)")
    p.add_argument("--repeat", type=int, default=1, help="tests in a row (0: forever)")
    p.add_argument("--gap-s", type=float, default=0.0, help="device seconds between tests")
    p.add_argument("--cal-mm", type=float, help="bar length at zero displacement (default: the plan's radius; "
                   "with --library the first plan's)")
    p.add_argument("--range-mm", type=float, default=2.5, help="LVDT linear range, +- mm")
    p.add_argument("--wait", action="store_true", help="stream only after the 'start' command")
    p.add_argument("--exit-when-done", action="store_true", help="exit once every test is sent")
    p.add_argument("--exit-on-eof", action="store_true", help="exit when stdin closes (a child of a program)")
    p.add_argument(
        "--burst-ms", type=float, default=1e3 * BURST_S,
        help="shortest time between two writes of samples, ms (a USB adapter's latency timer; 0: every sample "
        "as it falls due)",
    )
    g = p.add_argument_group("ASCII format")
    g.add_argument("--unit", choices=["mm", "um", "nm", "in"], default="mm")
    g.add_argument("--timestamp", choices=["none", "s", "ms", "us"], default="none")
    g.add_argument("--unit-suffix", action="store_true")
    g.add_argument("--request", default="?\r", help="poll request (default '?\\r')")
    from ballbar.tools.simulator_cli import add_plan_arguments

    add_plan_arguments(p.add_argument_group("test plan and machine (the simulator)"))
    g = p.add_argument_group("a set of plans on a 3D machine (tools/machine3d.py)")
    g.add_argument("--library", help="the plans, as JSON: the daemon's recorded config['plans'] (each plan's keys and "
                   "signature); the device runs them in turn on a machine with X, Y and Z errors, each program with "
                   "its signature; --set then takes the 3D machine's keys (backlash_z_um, squareness_yz_urad, ...)")
    g.add_argument("--run-plans", help="with --library: which plans, in this order, comma-separated (default: all)")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def source_url(path: str, s: Settings) -> str:
    if s.gauge is not None:
        from ballbar.protocol.gauges import PROFILES

        g: dict[str, str] = {"protocol": s.gauge, "rate": f"{s.poll_rate if s.mode == 'poll' else s.rate:g}",
                             "cal_mm": repr(s.cal_mm)}
        if s.mode != ("poll" if PROFILES[s.gauge].polled else "stream"):
            g["mode"] = s.mode
        if s.line_baud and s.line_baud != PROFILES[s.gauge].baud:
            g["baud"] = str(s.line_baud)
        return f"serial:{path}?{urllib.parse.urlencode(g)}"
    q: dict[str, str] = {"protocol": s.protocol, "rate": f"{s.rate:g}", "cal_mm": repr(s.cal_mm)}
    if s.protocol == "ascii":
        q["unit"] = s.fmt.unit
        if s.fmt.ts_unit:
            q["timestamp"] = s.fmt.ts_unit
        if s.mode == "poll":
            q["mode"] = "poll"
            q["request"] = s.fmt.request.decode("latin-1")
    return f"serial:{path}?{urllib.parse.urlencode(q)}"


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    from ballbar.analysis.errors import BallbarError

    if not 15.625 <= args.rate <= 10_000 or not args.speedup > 0 or args.repeat < 0 or not 0 <= args.burst_ms <= 1000:
        log.error("--rate must be within 15.625..10000, --speedup > 0, --repeat >= 0, --burst-ms within 0..1000")
        return 2
    from ballbar.protocol.gauges import PROFILES

    gauge = PROFILES.get(args.protocol)
    if args.mode is None:
        args.mode = "poll" if gauge is not None and gauge.polled else "stream"
    if args.mode == "poll" and args.protocol == "binary":
        log.error("--mode poll needs --protocol ascii or a gauge profile")
        return 2
    if gauge is not None and args.mode == "stream" and not gauge.streams:
        log.error("a %s gauge does not stream: it answers requests", args.protocol)
        return 2
    try:
        ts_unit = None if args.timestamp == "none" else args.timestamp
        # Fixed-width lines, as gauges write them: a sign, the digits the range
        # needs, the point and the decimals; timestamps zero-padded to 12 digits.
        probe = ascii_proto.AsciiFormat(unit=args.unit)
        int_digits = len(str(int(args.range_mm / ascii_proto.UNIT_MM[args.unit])))
        fmt = ascii_proto.AsciiFormat(
            unit=args.unit,
            ts_unit=ts_unit,
            unit_suffix=args.unit_suffix,
            request=args.request.encode("latin-1"),
            width=1 + int_digits + 1 + probe.digits if probe.digits else 1 + int_digits,
            ts_width={"s": 13, "ms": 13, "us": 12}.get(args.timestamp, 0),
        )
        if gauge is not None:
            fmt = gauge.fmt
        settings = Settings(
            gauge=gauge.name if gauge is not None else None,
            prefix=gauge.prefix if gauge is not None else "",
            poll_rate=args.poll_rate,
            line_baud=(gauge.baud if args.line_baud is None else args.line_baud) if gauge is not None else 0,
            bits_per_char=gauge.bits_per_char if gauge is not None else 10,
            protocol=args.protocol,
            mode=args.mode,
            rate=args.rate,
            speedup=args.speedup,
            cal_mm=args.cal_mm if args.cal_mm is not None else (
                plans_of(args.library).first.plan.radius_mm if args.library else args.radius_mm),
            range_mm=args.range_mm,
            fmt=fmt,
            seed=args.seed,
            burst_s=args.burst_ms / 1e3,
        )
        tests = csv_tests(args.csv, args.rate, args.repeat, args.gap_s) if args.csv else simulator_tests(args)
        feed = Feed(tests)
    except (BallbarError, ValueError) as err:
        log.error("%s", err)
        return 2

    tmpdir = None
    try:
        if args.port:
            port: PtyPort | SerialPort = SerialPort(args.port, args.baud)
        else:
            link = args.link
            if link is None:
                tmpdir = tempfile.mkdtemp(prefix="ballbar-simdevice-")
                link = os.path.join(tmpdir, "ttyBALLBAR0")
            port = PtyPort(link)
    except OSError as err:
        log.error("cannot open the port: %s", err)
        return 1

    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    # A signal wakes the loop at once (it may sleep up to IDLE_S): its number comes down this pipe.
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    old_wakeup = signal.set_wakeup_fd(wake_w)

    out = sys.stdout.fileno()
    dev = SimDevice(feed, port, settings, out)
    try:
        os.write(out, (port.path + "\n").encode())
    except BrokenPipeError:  # whoever started it is gone before reading where its port is (a daemon killed -9)
        return 0
    dev.emit({"event": "ready", "path": port.path, "url": source_url(port.path, settings)})
    if stat.S_ISFIFO(os.fstat(out).st_mode):
        # A pipe that its reader stops reading must not stall the device (a terminal is
        # left alone: the flag would be shared with the shell).
        os.set_blocking(out, False)
    dev.started = not args.wait
    stdin_fd: int | None = sys.stdin.fileno() if sys.stdin is not None else None
    inbuf = b""
    try:
        while dev.running and not stop:
            rlist = [wake_r] if stdin_fd is None else [wake_r, stdin_fd]
            if settings.mode == "poll" and port.is_open:
                fd = port.fileno()
                if fd is not None:
                    rlist.append(fd)
            wfd = dev.write_fd()
            now = time.monotonic()
            try:
                ready, _, _ = select.select(rlist, [] if wfd is None else [wfd], [], max(0.0, dev.next_wake(now) - now))
            except InterruptedError:
                continue
            now = time.monotonic()
            if wake_r in ready:
                with contextlib.suppress(BlockingIOError):
                    os.read(wake_r, 512)
            if stdin_fd is not None and stdin_fd in ready:
                chunk = os.read(stdin_fd, 4096)
                if not chunk:
                    if args.exit_on_eof:
                        break  # the process driving it has gone (a killed daemon's demo device)
                    stdin_fd = None  # EOF: keep running, commands are optional
                inbuf += chunk
                if b"\n" in inbuf:
                    dev.step(now)  # what fell due before the commands goes out as it was
                while b"\n" in inbuf:
                    line, inbuf = inbuf.split(b"\n", 1)
                    dev.command(line.decode("utf-8", "replace"), now)
            dev.step(now)
            if dev.done and args.exit_when_done:
                break
    except BrokenPipeError:
        pass  # the controlling process went away
    finally:
        signal.set_wakeup_fd(old_wakeup)
        os.close(wake_r)
        os.close(wake_w)
        port.close()
        if tmpdir:
            with contextlib.suppress(OSError):
                os.rmdir(tmpdir)
    return 0


__all__ = ["DeviceProcess", "main", "source_url"]

if __name__ == "__main__":
    sys.exit(main())
