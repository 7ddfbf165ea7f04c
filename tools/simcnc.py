"""A simulated CNC: an OPC UA server (asyncua) serving the part of OPC 40502 (OPC UA for CNC Systems) that the
daemon's ``[controller]`` client reads, for trials and tests without a machine.

The address space, under Objects, with the specification's browse names (in the CNC namespace,
``http://opcfoundation.org/UA/CNC``; the instances' own names, ``Channel_1`` and the axes, in the server's)::

    CncInterface/
      CncChannelList/Channel_1/   ActMainProgramName (String), ActOverride (Double, %), ActFeedrate (Double,
                                  mm/min), ActGFunctions (UInt32[]), ActProgramBlock (String[]: the previous, the
                                  actual and the next block)
      CncAxisList/<X|Y|Z>/PosIndirect/   ActPos, CmdPos (Double, mm)

(In the specification ``PosIndirect`` is a variable of ``CncPositionDataType`` with the components ``ActPos``,
``CmdPos`` and ``RemDist``; here it is an object holding the two components the daemon reads.)

The story it tells, on repeat: idle (no program) for ``--idle-s``, then the program ``--program`` runs a circular
test: the feed-in, a dwell, the counter-clockwise arc (overshoot, data arc, overshoot), a dwell, the clockwise
arc, a dwell, the feed-out; then idle again.  Each block is served in ``ActProgramBlock`` as it runs; the axes of
``--plane`` move on the circle of ``--radius`` at ``--feed`` times the override; ``ActPos`` lags ``CmdPos`` by
the following error of a position loop of gain ``--kv`` (1/s).  The override can be scheduled
(``--override-at SECONDS=PERCENT``, from the server's start) or changed live (``override PERCENT`` on stdin);
``--omit NAME`` leaves a node out (a server that lacks it).  The values change every ``1/--update-hz`` seconds,
each with its source timestamp.

    python -m ballbar.tools.simcnc --port 4840 --program O9101 --override-at 20=80

stdout: the endpoint on the first line (``opc.tcp://127.0.0.1:PORT/ballbar/simcnc``), then one JSON object per
command answered.  Commands on stdin: ``override PERCENT``, ``program NAME`` (the next runs' name), ``clock
SECONDS`` (the server's clock that far ahead of the host's from now: a clock that jumps).  SIGTERM or
EOF on stdin (with ``--exit-on-eof``) stops it.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime as dt
import json
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from ballbar.analysis import TestPlan

log = logging.getLogger(__name__)

CNC_NAMESPACE = "http://opcfoundation.org/UA/CNC"
SERVER_NAMESPACE = "urn:ballbar:simcnc"
PLANE_AXES = {"XY": ("X", "Y"), "YZ": ("Y", "Z"), "ZX": ("Z", "X")}
G_PLANE = {"XY": 17, "ZX": 18, "YZ": 19}


@dataclass
class Block:
    """One block of the test program: its text, its duration at 100 % (s), and where it moves."""

    text: str
    duration_s: float
    kind: str  # idle, line_in, line_out, dwell, arc_ccw, arc_cw
    arc_deg: float = 0.0
    start_deg: float = 0.0


@dataclass
class Story:
    """The program the simulated machine runs on repeat, and the override's schedule."""

    program: str = "O9101"
    plan: TestPlan = field(default_factory=TestPlan)  # the test program's geometry and feed (the daemon's plan)
    idle_s: float = 5.0
    kv_per_s: float = 30.0
    override_at: list[tuple[float, float]] = field(default_factory=list)  # (seconds from start, percent)

    def blocks(self) -> list[Block]:
        p = self.plan
        arc = p.overshoot_deg * 2 + p.data_arc_deg
        arc_s = math.radians(arc) * p.radius_mm / p.feed_mm_min * 60.0
        line_s = p.feed_in_mm / p.feed_mm_min * 60.0
        g2, g3 = "G02", "G03"
        return [
            Block("", self.idle_s, "idle"),
            Block(f"N10 G{G_PLANE[p.plane]} G90 G01 F{p.feed_mm_min:g}", line_s, "line_in"),
            Block(f"N20 G04 P{p.dwell_s:g}", p.dwell_s, "dwell"),
            Block(f"N30 {g3} (ccw {arc:g} deg)", arc_s, "arc_ccw", arc, p.start_deg - p.overshoot_deg),
            Block(f"N40 G04 P{p.dwell_s:g}", p.dwell_s, "dwell"),
            Block(f"N50 {g2} (cw {arc:g} deg)", arc_s, "arc_cw", arc, p.start_deg + p.data_arc_deg
                  + p.overshoot_deg),
            Block(f"N60 G04 P{p.dwell_s:g}", p.dwell_s, "dwell"),
            Block("N70 G01 (feed-out)", line_s, "line_out"),
            Block("N80 M30", 0.05, "dwell"),
        ]


class Machine:
    """The simulated machine's state at a time: program, block, override, positions; advanced by :meth:`step`."""

    def __init__(self, story: Story) -> None:
        self.story = story
        self.blocks = story.blocks()
        self.override = 100.0
        self.program_name = story.program
        self._tau = 0.0  # program time (s at 100 %) into the cycle
        self._index = 0
        self._elapsed = 0.0  # since the start (wall s)
        self._overrides = sorted(story.override_at)

    @property
    def cycle_s(self) -> float:
        return sum(b.duration_s for b in self.blocks)

    def step(self, dt_s: float) -> None:
        self._elapsed += dt_s
        while self._overrides and self._overrides[0][0] <= self._elapsed:
            self.override = self._overrides.pop(0)[1]
        self._tau = (self._tau + dt_s * self.override / 100.0) % self.cycle_s

    def _at(self, tau: float) -> tuple[int, float]:
        """The block running at program time ``tau`` and how far into it (0..1)."""
        t = tau % self.cycle_s
        for i, b in enumerate(self.blocks):
            if t < b.duration_s:
                return i, t / b.duration_s if b.duration_s else 1.0
            t -= b.duration_s
        return len(self.blocks) - 1, 1.0

    def position(self, tau: float) -> dict[str, float]:
        """Each axis' commanded position (mm) at program time ``tau``: the plane's two on the circle (the feed-in
        from ``feed_in_mm`` inside it), the third at 0."""
        s = self.story
        i, f = self._at(tau)
        b = self.blocks[i]
        r, angle = s.plan.radius_mm, s.plan.start_deg
        if b.kind == "idle":
            r = s.plan.radius_mm - s.plan.feed_in_mm
        elif b.kind == "line_in":
            r = s.plan.radius_mm - s.plan.feed_in_mm * (1 - f)
        elif b.kind == "line_out":
            r = s.plan.radius_mm - s.plan.feed_in_mm * f
        elif b.kind == "arc_ccw":
            angle = b.start_deg + b.arc_deg * f
        elif b.kind == "arc_cw":
            angle = b.start_deg - b.arc_deg * f
        elif b.kind == "dwell":
            after = [x for x in self.blocks[:i] if x.kind.startswith("arc")]
            if after:
                last = after[-1]
                angle = last.start_deg + (last.arc_deg if last.kind == "arc_ccw" else -last.arc_deg)
            if i == len(self.blocks) - 1:
                r = s.plan.radius_mm - s.plan.feed_in_mm
        a, b2 = PLANE_AXES[s.plan.plane]
        out = {"X": 0.0, "Y": 0.0, "Z": 0.0}
        out[a] = r * math.cos(math.radians(angle))
        out[b2] = r * math.sin(math.radians(angle))
        return out

    def snapshot(self) -> dict[str, Any]:
        """What the server serves now."""
        i, _f = self._at(self._tau)
        b = self.blocks[i]
        running = b.kind != "idle"
        texts = [x.text for x in self.blocks]
        lag_tau = self._tau - (1.0 / self.story.kv_per_s) * self.override / 100.0  # the following error's lag
        moving = b.kind.startswith("arc") or b.kind.startswith("line")
        return {
            "ActMainProgramName": self.program_name if running else "",
            "ActOverride": float(self.override),
            "ActFeedrate": self.story.plan.feed_mm_min * self.override / 100.0 if moving else 0.0,
            "ActGFunctions": [G_PLANE[self.story.plan.plane], 90, 94, 2 if b.kind == "arc_cw" else 3 if
                              b.kind == "arc_ccw" else 1],
            "ActProgramBlock": [texts[i - 1] if i > 1 else "", b.text, texts[i + 1] if i + 1 < len(texts) else ""]
            if running else [],
            "cmd": self.position(self._tau),
            "act": self.position(lag_tau if lag_tau >= 0 else 0.0),
        }


class SimCnc:
    """The server on a thread of its own, with its own event loop::

        with SimCnc(Story(program="O9101"), port=free_port()) as cnc:
            ...  # a client connects to cnc.endpoint
            cnc.set_override(80)
    """

    def __init__(self, story: Story | None = None, host: str = "127.0.0.1", port: int = 4840,
                 update_hz: float = 50.0, omit: Sequence[str] = (), axes: Sequence[str] = ("X", "Y", "Z")) -> None:
        self.machine = Machine(story or Story())
        self.host = host
        self.port = port
        self.update_hz = update_hz
        self.omit = set(omit)
        self.axes = tuple(axes)
        self.endpoint = f"opc.tcp://{host}:{port}/ballbar/simcnc"
        self.updates = 0
        self.clock_offset_s = 0.0  # the server's clock ahead of the host's (s): set_clock() makes it jump
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    def __enter__(self) -> SimCnc:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def set_override(self, percent: float) -> None:
        with self._lock:
            self.machine.override = float(percent)

    def set_clock(self, offset_s: float) -> None:
        """The server's clock (its source timestamps) ``offset_s`` ahead of the host's from now: a clock that
        jumps."""
        with self._lock:
            self.clock_offset_s = float(offset_s)

    def set_program(self, name: str) -> None:
        with self._lock:
            self.machine.program_name = name

    def start(self, timeout: float = 20.0) -> None:
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), name="simcnc", daemon=True)
        self._thread.start()
        if not self._started.wait(timeout):
            raise TimeoutError(f"simcnc: not serving within {timeout} s")
        if self._error is not None:
            raise self._error

    def stop(self, timeout: float = 10.0) -> None:
        loop, ev = self._loop, self._stop
        if loop is not None and ev is not None:
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(ev.set)
        if self._thread is not None:
            self._thread.join(timeout)

    async def _main(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        try:
            server, nodes = await self._serve()
        except BaseException as err:
            self._error = err
            self._started.set()
            return
        self._started.set()
        try:
            await self._play(server, nodes)
        finally:
            with contextlib.suppress(Exception):
                await server.stop()

    async def _serve(self) -> tuple[Any, dict[str, Any]]:
        from asyncua import Server, ua

        server = Server()
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("ballbar simulated CNC")
        server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        cnc = await server.register_namespace(CNC_NAMESPACE)
        own = await server.register_namespace(SERVER_NAMESPACE)
        objects = server.nodes.objects
        iface = await objects.add_object(_node_id("CncInterface", own), ua.QualifiedName("CncInterface", cnc))
        channels = await iface.add_object(_node_id("CncChannelList", own), ua.QualifiedName("CncChannelList", cnc))
        channel = await channels.add_object(_node_id("Channel_1", own), ua.QualifiedName("Channel_1", own))
        snap = self.machine.snapshot()
        types = {"ActMainProgramName": ua.VariantType.String, "ActOverride": ua.VariantType.Double,
                 "ActFeedrate": ua.VariantType.Double, "ActGFunctions": ua.VariantType.UInt32,
                 "ActProgramBlock": ua.VariantType.String}
        nodes: dict[str, Any] = {}
        for name, vt in types.items():
            if name not in self.omit:
                var = await channel.add_variable(_node_id(f"Channel_1.{name}", own), ua.QualifiedName(name, cnc),
                                                 snap[name], vt)
                nodes[name] = (var, vt)
        axes = await iface.add_object(_node_id("CncAxisList", own), ua.QualifiedName("CncAxisList", cnc))
        for axis in self.axes:
            a = await axes.add_object(_node_id(axis, own), ua.QualifiedName(axis, own))
            pos = await a.add_object(_node_id(f"{axis}.PosIndirect", own), ua.QualifiedName("PosIndirect", cnc))
            for comp, key in (("ActPos", "act"), ("CmdPos", "cmd")):
                if f"{comp}.{axis}" in self.omit or comp in self.omit:
                    continue
                var = await pos.add_variable(_node_id(f"{axis}.PosIndirect.{comp}", own), ua.QualifiedName(comp, cnc),
                                             snap[key][axis], ua.VariantType.Double)
                nodes[f"{key}.{axis}"] = (var, ua.VariantType.Double)
        await server.start()
        return server, nodes

    async def _play(self, server: Any, nodes: dict[str, Any]) -> None:

        period = 1.0 / self.update_hz
        last: dict[str, Any] = {}
        t_prev = time.monotonic()
        assert self._stop is not None
        while not self._stop.is_set():
            now = time.monotonic()
            with self._lock:
                self.machine.step(now - t_prev)
                snap = self.machine.snapshot()
            t_prev = now
            stamp = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=self.clock_offset_s)
            for key, (node, vt) in nodes.items():
                if key.startswith(("act.", "cmd.")):
                    kind, axis = key.split(".")
                    value = snap[kind][axis]
                else:
                    value = snap[key]
                if last.get(key) == value:
                    continue  # a data change only when the value changes, as a controller's server does
                last[key] = value
                dv = _data_value(value, vt, stamp)
                await server.write_attribute_value(node.nodeid, dv)
                self.updates += 1
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), max(0.0, period - (time.monotonic() - now)))


@contextlib.contextmanager
def simulated_cnc(cfg: Any) -> Iterator[str]:
    """``ballbar run --simulate --simulate-cnc``: the simulated CNC as a child process on a free port of 127.0.0.1,
    playing the configured plan (its radius, feed, plane; the program the first plan with a plain ``program``
    names, else O9101) in real time; its endpoint.  (Its schedule is its own, not the simulated bar's tests.)"""
    import socket
    import subprocess

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    p = cfg.plan
    program = next((e.program for e in cfg.plans.values() if e.program and not set(e.program) & set("*?[")),
                   "O9101")
    proc = subprocess.Popen(
        [sys.executable, "-m", "ballbar.tools.simcnc", "--port", str(port), "--exit-on-eof", "--program", program,
         "--plane", p.plane, "--radius", f"{p.radius_mm:g}", "--feed", f"{p.feed_mm_min:g}"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        endpoint = proc.stdout.readline().strip()
        if not endpoint.startswith("opc.tcp://"):
            raise RuntimeError(f"the simulated CNC did not start (exit {proc.poll()})")
        log.info("simulated CNC on %s, running %s", endpoint, program)
        yield endpoint
    finally:
        if proc.stdin is not None:
            proc.stdin.close()  # --exit-on-eof: it stops
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if proc.stdout is not None:
            proc.stdout.close()


def _node_id(name: str, ns: int) -> Any:
    """A string node id in namespace ``ns`` (stable across the server's restarts)."""
    from asyncua import ua

    u: Any = ua  # asyncua's stubs want its own int and str subclasses
    return u.NodeId(name, ns)


def _data_value(value: Any, vt: Any, t: dt.datetime) -> Any:
    """``value`` with its source and server timestamps ``t``."""
    from asyncua import ua

    u: Any = ua
    return u.DataValue(u.Variant(value, vt), SourceTimestamp=t, ServerTimestamp=t)


def _override_at(text: str) -> tuple[float, float]:
    at, sep, pct = text.partition("=")
    try:
        if not sep:
            raise ValueError
        return float(at), float(pct)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected SECONDS=PERCENT, not {text!r}") from None


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ballbar-simcnc", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default: 127.0.0.1)")
    p.add_argument("--port", type=int, default=4840, help="TCP port (default: 4840)")
    p.add_argument("--program", default="O9101", help="the main program's name while the test runs")
    p.add_argument("--plane", choices=sorted(PLANE_AXES), default="XY")
    p.add_argument("--radius", type=float, default=100.0, help="the circle's radius (mm)")
    p.add_argument("--feed", type=float, default=1000.0, help="the programmed feed (mm/min)")
    p.add_argument("--idle-s", type=float, default=5.0, help="idle before each run (s)")
    p.add_argument("--kv", type=float, default=30.0, help="the position loops' gain (1/s): ActPos lags CmdPos")
    p.add_argument("--override-at", type=_override_at, action="append", default=[], metavar="SECONDS=PERCENT",
                   help="set the override at this time from the start (repeatable)")
    p.add_argument("--omit", action="append", default=[], metavar="NAME",
                   help="leave this node out (ActProgramBlock, ActPos.X, CmdPos, ...); repeatable")
    p.add_argument("--update-hz", type=float, default=50.0, help="how often values change (Hz)")
    p.add_argument("--exit-on-eof", action="store_true", help="stop when stdin ends")
    p.add_argument("-v", "--verbose", action="store_true")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.WARNING,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    if not args.verbose:  # asyncua warns that a server without security has no signing policy: it is meant so
        logging.getLogger("asyncua").setLevel(logging.ERROR)
    if not 1 <= args.port <= 65535 or not args.update_hz > 0 or not args.feed > 0 or not args.radius > 0:
        print("ballbar-simcnc: --port within 1..65535, --update-hz, --feed and --radius > 0", file=sys.stderr)
        return 2
    plan = TestPlan(plane=args.plane, radius_mm=args.radius, feed_mm_min=args.feed)
    story = Story(program=args.program, plan=plan, idle_s=args.idle_s, kv_per_s=args.kv,
                  override_at=list(args.override_at))
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    signal.signal(signal.SIGINT, lambda *_: done.set())
    cnc = SimCnc(story, args.host, args.port, args.update_hz, args.omit)
    try:
        cnc.start()
    except OSError as err:
        print(f"ballbar-simcnc: cannot serve on {args.host}:{args.port}: {err.strerror or err}", file=sys.stderr)
        return 1
    print(cnc.endpoint, flush=True)

    def commands() -> None:
        for line in sys.stdin:
            word, _, arg = line.strip().partition(" ")
            try:
                if word == "override":
                    cnc.set_override(float(arg))
                elif word == "program":
                    cnc.set_program(arg.strip())
                elif word == "clock":
                    cnc.set_clock(float(arg))
                else:
                    print(json.dumps({"error": f"unknown command {word!r}"}), flush=True)
                    continue
                print(json.dumps({"done": word, "arg": arg.strip()}), flush=True)
            except ValueError:
                print(json.dumps({"error": f"bad argument {arg!r}"}), flush=True)
        if args.exit_on_eof:
            done.set()

    threading.Thread(target=commands, name="stdin", daemon=True).start()
    try:
        done.wait()
    finally:
        cnc.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
