"""A small NC interpreter for the programs of :mod:`ballbar.tools.gcode`, and a check against the plan.

:func:`interpret` executes exactly the subset that :func:`~ballbar.tools.gcode.generate`
writes, per dialect, the way the controller would: modal plane, feed and
path mode; rapids, lines, centre-format arcs, dwells, program stops.  Anything
else (an unknown word or G/M code, incremental coordinates, a helix, an arc
whose end radius differs from its start radius by more than
:data:`ARC_RADIUS_ALARM_MM` as a controller would alarm, a feed move without a
feed) raises :class:`NcError` with the line number.

:func:`test_moves` turns the executed blocks into the moves of one test as
:func:`ballbar.analysis.program.moves` describes them: plane frame (first,
second axis), millimetres from the pivot, angles counter-clockwise from the
first axis, every move starting and ending at rest.  Feed blocks that the
controller runs without stopping are merged into one move: consecutive blocks
at the same feed, in continuous-path mode, tangent at their junction (within
:data:`TANGENT_TOL_RAD`).  The motion stops at a dwell (also of 0 s), a program
stop, a rapid, the end of a block in exact-stop mode, a corner and a feed
change.  Rapids are taken to end at rest (positioning; the generated program
approaches in exact-stop mode anyway).

:func:`signatures` reads the signature each test's program carries before its
feed-in (radial excursions that do not reach the circle; :mod:`ballbar.analysis.plans`),
which the split into tests leaves out.

:func:`check_against_plan` compares a program with the plan and with the
timing the analyzer assumes (:func:`ballbar.analysis.program.schedule`).
:func:`model_limits` says where the plan itself breaks that timing model at a
given acceleration (an overshoot too short to reach the feed): then
no program can pass the check, and the plan, not the program, needs changing.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from ballbar.analysis.errors import BallbarError
from ballbar.analysis.plan import TestPlan
from ballbar.analysis.program import Move, arc_start_deg, model_limits, moves, schedule
from ballbar.tools.gcode import DIALECTS, PLANE_INDEX, WORK_OFFSETS
from ballbar.tools.simulator import _Profile

ARC_RADIUS_ALARM_MM = 0.01  # end vs start radius of an arc block beyond which a controller alarms
TANGENT_TOL_RAD = 1.0e-3  # a junction whose direction turns by less runs through without stopping
TIME_TOL_S = 1.0e-6
ANGLE_TOL_DEG = 1.0e-6
DWELL_TOL_S = 1.0e-9

BlockKind = Literal["rapid", "line", "arc", "dwell", "stop", "end"]
Vec3 = tuple[float, float, float]
_NAN3: Vec3 = (math.nan, math.nan, math.nan)
_PLANE_OF_G = {"17": "XY", "18": "ZX", "19": "YZ"}
_PLANE_OF_TOOL_AXIS = {"Z": "XY", "X": "YZ", "Y": "ZX"}
_AXES = "XYZ"
_CENTRE = "IJK"


class NcError(BallbarError, ValueError):
    """The program cannot be run as written: ``line`` is the 1-based line of the text (None: the whole program)."""

    def __init__(self, line: int | None, message: str) -> None:
        self.line = line
        super().__init__(f"line {line}: {message}" if line is not None else message)


@dataclass(frozen=True)
class Block:
    """One executed block, in machine coordinates (mm, X Y Z of the work offset).

    ``arc``: ``centre`` is absolute, ``direction`` +1 for G03/DR+ (counter-clockwise
    in the plane's (first, second) frame), ``sweep_rad`` signed likewise.
    ``exact_stop``: the controller stops at this block's end (exact-stop mode or
    a one-shot exact stop).  ``feed_mm_min`` is the modal feed (None before any).
    """

    line: int
    kind: BlockKind
    start: Vec3
    end: Vec3
    plane: str
    feed_mm_min: float | None
    exact_stop: bool
    centre: Vec3 | None = None
    direction: int = 0
    sweep_rad: float = 0.0
    duration_s: float = 0.0
    text: str = ""


@dataclass(frozen=True)
class Program:
    """What :func:`interpret` read: the executed blocks and the final modal state.

    ``decimals``: the most digits after the decimal point of any coordinate
    (the rounding the tolerances of :func:`check_against_plan` allow for).
    """

    dialect: str
    name: str | None
    blocks: tuple[Block, ...]
    plane: str
    feed_mm_min: float | None
    exact_stop: bool
    work_offset: str | None
    decimals: int


# --------------------------------------------------------------------------- execution


@dataclass
class _State:
    dialect: str
    plane: str = "XY"
    feed: float | None = None
    exact: bool = False
    motion: str | None = None
    pos: list[float] = field(default_factory=lambda: [math.nan] * 3)
    blocks: list[Block] = field(default_factory=list)
    work_offset: str | None = None
    decimals: int = 0
    name: str | None = None
    ended: bool = False
    pole: tuple[float, float] | None = None  # HEIDENHAIN CC, in the plane's (first, second)

    def emit(self, line: int, kind: BlockKind, end: Sequence[float], text: str, *, exact: bool = False,
             centre: Vec3 | None = None, direction: int = 0, sweep: float = 0.0, duration: float = 0.0) -> None:
        start = (self.pos[0], self.pos[1], self.pos[2])
        e = (float(end[0]), float(end[1]), float(end[2]))
        self.blocks.append(
            Block(line, kind, start, e, self.plane, self.feed, self.exact or exact, centre, direction, sweep,
                  duration, text)
        )
        self.pos = list(e)

    def rapid(self, ln: int, target: list[float], text: str) -> None:
        self.emit(ln, "rapid", target, text)

    def line(self, ln: int, target: list[float], text: str, exact: bool) -> None:
        self._need_feed(ln)
        if any(math.isnan(v) for v, t in zip(self.pos, target, strict=True) if not math.isnan(t)):
            raise NcError(ln, "feed move from an unknown position (no rapid to a start point before it)")
        self.emit(ln, "line", target, text, exact=exact)

    def arc(self, ln: int, target: list[float], centre: list[float], direction: int, text: str,
            exact: bool) -> None:
        self._need_feed(ln)
        i1, i2, i3 = PLANE_INDEX[self.plane]
        if any(math.isnan(self.pos[i]) for i in (i1, i2)):
            raise NcError(ln, "arc from an unknown position (no rapid to a start point before it)")
        if target[i3] != self.pos[i3] and not (math.isnan(target[i3]) and math.isnan(self.pos[i3])):
            raise NcError(ln, f"helical arc: {_AXES[i3]} moves in a {self.plane} arc (not supported)")
        s = (self.pos[i1] - centre[i1], self.pos[i2] - centre[i2])
        e = (target[i1] - centre[i1], target[i2] - centre[i2])
        r0, r1 = math.hypot(*s), math.hypot(*e)
        if r0 < 1e-9:
            raise NcError(ln, "arc centre on its start point")
        if abs(r1 - r0) > ARC_RADIUS_ALARM_MM:
            raise NcError(
                ln, f"arc end radius {r1:.6f} mm differs from the start radius {r0:.6f} mm by "
                f"{abs(r1 - r0):.6f} mm (more than {ARC_RADIUS_ALARM_MM} mm: a controller alarms)"
            )
        a0, a1 = math.atan2(s[1], s[0]), math.atan2(e[1], e[0])
        if math.hypot(e[0] - s[0], e[1] - s[1]) < 1e-9:
            sweep = direction * 2 * math.pi  # end = start in centre format: a full circle
        else:
            sweep = (a1 - a0) % (2 * math.pi)
            if direction < 0:
                sweep -= 2 * math.pi
        c3 = (float(centre[0]), float(centre[1]), float(centre[2]))
        self.emit(ln, "arc", target, text, exact=exact, centre=c3, direction=direction, sweep=sweep)

    def dwell(self, ln: int, seconds: float, text: str, exact: bool = False) -> None:
        if not (math.isfinite(seconds) and seconds >= 0):
            raise NcError(ln, f"dwell time must be >= 0 s, not {seconds!r}")
        self.emit(ln, "dwell", self.pos, text, duration=seconds, exact=exact)

    def _need_feed(self, ln: int) -> None:
        if self.feed is None:
            raise NcError(ln, "feed move without a feed (no F programmed)")

    def program(self) -> Program:
        return Program(self.dialect, self.name, tuple(self.blocks), self.plane, self.feed, self.exact,
                       self.work_offset, self.decimals)


_NUM = r"[+-]?(?:\d+\.?\d*|\.\d+)"
_WORD = re.compile(rf"([A-Z])({_NUM})")
_WORDS = re.compile(rf"(?:[A-Z]{_NUM})*")

# Per ISO dialect: accepted letters, G codes by role, M codes.
_ISO = {
    "fanuc": dict(
        letters="NGMXYZIJKFP", units={"21"}, extra={"80", "40", "90", "94"}, exact={"61"}, cont={"64"},
        oneshot={"9"}, arcdist=set(), m_ok={"0", "1", "2", "5", "30"},
    ),
    "siemens": dict(
        letters="NGMXYZIJKF", units={"71", "710"}, extra={"40", "90", "94"}, exact={"60"},
        cont={"64", "641", "642"}, oneshot={"9"}, arcdist=set(), m_ok={"0", "1", "2", "5", "30"},
    ),
    "linuxcnc": dict(
        letters="NGMXYZIJKFPQ", units={"21"}, extra={"80", "40", "90", "94"}, exact={"61", "61.1"},
        cont={"64"}, oneshot=set(), arcdist={"91.1"}, m_ok={"0", "1", "2", "5", "30", "48", "49"},
    ),
}


def _norm_code(text: str) -> str:
    return f"{float(text):g}"


def _strip_parens(line: str, ln: int) -> str:
    out, depth = [], 0
    for ch in line:
        if ch == "(":
            if depth:
                raise NcError(ln, "nested comment parentheses")
            depth = 1
        elif ch == ")":
            if not depth:
                raise NcError(ln, "')' without '('")
            depth = 0
        elif not depth:
            out.append(ch)
    if depth:
        raise NcError(ln, "comment not closed with ')'")
    return "".join(out)


def _decimals_of(text: str) -> int:
    return len(text.split(".", 1)[1]) if "." in text else 0


def _iso_block(st: _State, ln: int, raw: str) -> None:
    d = st.dialect
    spec = _ISO[d]
    if d == "siemens":
        code = raw.split(";", 1)[0]
    else:
        code = _strip_parens(raw, ln)
        if d == "linuxcnc":
            code = code.split(";", 1)[0]
    code = code.replace(" ", "").replace("\t", "")
    if d != "fanuc":
        code = code.upper()
    if not code:
        return
    if code.startswith("/"):
        raise NcError(ln, "block delete '/' is not supported")
    if not _WORDS.fullmatch(code):
        raise NcError(ln, f"cannot read {code!r}")
    words = _WORD.findall(code)
    gs: list[str] = []
    ms: list[str] = []
    vals: dict[str, str] = {}
    for letter, text in words:
        if letter not in spec["letters"]:
            raise NcError(ln, f"unknown word {letter}{text}")
        if letter == "G":
            gs.append(_norm_code(text))
        elif letter == "M":
            ms.append(_norm_code(text))
        elif letter == "N":
            continue
        else:
            if letter in vals:
                raise NcError(ln, f"word {letter} twice in one block")
            vals[letter] = text
    motion: str | None = None
    dwell = False
    oneshot = False
    plane_set = None
    offset = None
    for g in gs:
        if g in {"0", "1", "2", "3"}:
            if motion is not None:
                raise NcError(ln, "two motion G-codes in one block")
            motion = g
        elif g in _PLANE_OF_G:
            plane_set = _PLANE_OF_G[g]
        elif g in spec["units"] or g in spec["extra"] or g in spec["arcdist"]:
            continue
        elif g in spec["exact"]:
            st.exact = True
        elif g in spec["cont"]:
            st.exact = False
        elif g in spec["oneshot"]:
            oneshot = True
        elif g == "4":
            dwell = True
        else:
            word = f"G{g}" + (f" P{vals['P']}" if g == "54.1" and "P" in vals else "")
            if WORK_OFFSETS[d].fullmatch(word):
                offset = word
            else:
                raise NcError(ln, f"unknown or unsupported G-code G{g}")
    for m in ms:
        if m not in spec["m_ok"]:
            raise NcError(ln, f"unknown or unsupported M-code M{m}")
    if plane_set:
        st.plane = plane_set
    if offset:
        st.work_offset = offset
    # P and Q: dwell time (LinuxCNC G4, FANUC G04 P in ms), G64 tolerance (LinuxCNC), G54.1 P (FANUC)
    if "Q" in vals and not (d == "linuxcnc" and "64" in gs):
        raise NcError(ln, f"word Q{vals['Q']} without G64")
    if "P" in vals and not (dwell or "64" in gs or (offset and "P" in offset)):
        raise NcError(ln, f"word P{vals['P']} without G4/G64")

    def value(letter: str, coordinate: bool = True) -> float:
        text = vals[letter]
        if d == "fanuc" and "." not in text:
            # FANUC IS-B: a number without a decimal point counts least increments (0.001 mm, 0.001 s)
            if coordinate:
                st.decimals = max(st.decimals, 3)
            return int(text) * 0.001
        if coordinate:
            st.decimals = max(st.decimals, _decimals_of(text))
        return float(text)

    if dwell:
        if motion is not None:
            raise NcError(ln, "dwell and motion in one block")
        if d == "fanuc":
            if "X" in vals:
                seconds = value("X", coordinate=False)
            elif "P" in vals:
                if "." in vals["P"]:
                    raise NcError(ln, "G04 P takes whole milliseconds")
                seconds = int(vals["P"]) / 1000.0
            else:
                raise NcError(ln, "G04 without X or P")
            extra = set(vals) - {"X", "P"}
        elif d == "siemens":
            if "F" not in vals:
                raise NcError(ln, "G4 without F (seconds)")
            seconds = float(vals["F"])
            extra = set(vals) - {"F"}
        else:
            if "P" not in vals:
                raise NcError(ln, "G4 without P (seconds)")
            seconds = float(vals["P"])
            extra = set(vals) - {"P"}
        if extra:
            raise NcError(ln, f"words {''.join(sorted(extra))} in a dwell block")
        st.dwell(ln, seconds, raw.strip(), exact=oneshot)
    else:
        if "F" in vals:
            f = float(vals["F"])
            if not f > 0:
                raise NcError(ln, f"feed must be > 0, not F{vals['F']}")
            st.feed = f
        if motion is not None:
            st.motion = motion
        axes = [a for a in _AXES if a in vals]
        centre = [c for c in _CENTRE if c in vals]
        if axes or centre:
            if st.motion is None:
                raise NcError(ln, "coordinates without a motion mode (G00/G01/G02/G03)")
            target = list(st.pos)
            for a in axes:
                target[_AXES.index(a)] = value(a)
            if st.motion == "0":
                if centre:
                    raise NcError(ln, "centre words in a rapid block")
                st.rapid(ln, target, raw.strip())
            elif st.motion == "1":
                if centre:
                    raise NcError(ln, "centre words in a linear block")
                st.line(ln, target, raw.strip(), oneshot)
            else:
                i1, i2, _ = PLANE_INDEX[st.plane]
                allowed = {_CENTRE[i1], _CENTRE[i2]}
                if not centre:
                    raise NcError(ln, "arc without a centre (I/J/K)")
                bad = set(centre) - allowed
                if bad:
                    raise NcError(ln, f"centre word {''.join(sorted(bad))} outside the {st.plane} plane")
                c = list(st.pos)
                for i in (i1, i2):
                    c[i] = st.pos[i] + (value(_CENTRE[i]) if _CENTRE[i] in vals else 0.0)
                st.arc(ln, target, c, 1 if st.motion == "3" else -1, raw.strip(), oneshot)
    for m in ms:
        if m in {"0", "1"}:
            st.emit(ln, "stop", st.pos, raw.strip())
        elif m in {"2", "30"}:
            st.emit(ln, "end", st.pos, raw.strip())
            st.ended = True


def _interpret_iso(text: str, dialect: str) -> _State:
    st = _State(dialect)
    lines = text.splitlines()
    content = [i for i, s in enumerate(lines) if s.strip()]
    for i, raw in enumerate(lines):
        ln = i + 1
        s = raw.strip()
        if not s:
            continue
        if dialect == "fanuc":
            if s == "%":
                if i not in (content[0], content[-1]):
                    raise NcError(ln, "'%' only opens and closes the program")
                continue
            if i == content[0]:
                raise NcError(ln, "a FANUC program starts with '%'")
            m = re.fullmatch(r"O(\d{1,8})\s*(\(.*\))?", s)
            if m:
                if st.name is not None or st.blocks:
                    raise NcError(ln, "O-number inside the program")
                st.name = "O" + m.group(1)
                continue
        if st.ended:
            raise NcError(ln, "block after the end of program")
        _iso_block(st, ln, raw)
    if dialect == "fanuc" and (not content or lines[content[-1]].strip() != "%"):
        raise NcError(len(lines), "a FANUC program ends with '%'")
    return st


_HH_AXIS = re.compile(rf"([XYZ])({_NUM})")


def _hh_coords(st: _State, ln: int, tokens: list[str]) -> tuple[dict[str, float], list[str]]:
    coords: dict[str, float] = {}
    rest: list[str] = []
    for tok in tokens:
        m = _HH_AXIS.fullmatch(tok)
        if m:
            if m.group(1) in coords:
                raise NcError(ln, f"axis {m.group(1)} twice in one block")
            coords[m.group(1)] = float(m.group(2))
            st.decimals = max(st.decimals, _decimals_of(m.group(2)))
        elif re.fullmatch(r"I[XYZ].*", tok):
            raise NcError(ln, f"incremental coordinate {tok} is not supported")
        else:
            rest.append(tok)
    return coords, rest


def _hh_tail(st: _State, ln: int, rest: list[str], *, allow_fmax: bool) -> tuple[bool, list[str]]:
    """R0, FMAX, F and M words; returns (rapid, M codes)."""
    rapid = False
    ms: list[str] = []
    for tok in rest:
        if tok == "R0":
            continue
        if tok in ("RL", "RR", "R+", "R-"):
            raise NcError(ln, f"radius compensation {tok} is not supported")
        if tok == "FMAX" and allow_fmax:
            rapid = True
        elif re.fullmatch(rf"F{_NUM}", tok):
            f = float(tok[1:])
            if not f > 0:
                raise NcError(ln, f"feed must be > 0, not {tok}")
            st.feed = f
        elif re.fullmatch(r"M\d+", tok):
            ms.append(str(int(tok[1:])))
        else:
            raise NcError(ln, f"unknown word {tok}")
    for m in ms:
        if m not in {"0", "1", "2", "5", "30"}:
            raise NcError(ln, f"unknown or unsupported M-code M{m}")
    return rapid, ms


def _hh_m(st: _State, ln: int, ms: list[str], text: str) -> None:
    for m in ms:
        if m in {"0", "1"}:
            st.emit(ln, "stop", st.pos, text)
        elif m in {"2", "30"}:
            st.emit(ln, "end", st.pos, text)


def _interpret_heidenhain(text: str) -> _State:
    st = _State("heidenhain")
    lines = text.splitlines()
    expect_n = 0
    pending_dwell: int | None = None
    name: str | None = None
    for i, raw in enumerate(lines):
        ln = i + 1
        if not raw.strip():
            continue
        if st.ended:
            raise NcError(ln, "block after END PGM")
        m = re.fullmatch(r"\s*(\d+)\s+(.*?)\s*", raw)
        if not m:
            raise NcError(ln, "a HEIDENHAIN block starts with its block number")
        n = int(m.group(1))
        if n != expect_n:
            raise NcError(ln, f"block number {n}, expected {expect_n}")
        expect_n += 1
        body = m.group(2)
        if body.startswith(";"):
            continue
        body = body.split(";", 1)[0].strip()
        if pending_dwell is not None:
            dm = re.fullmatch(rf"CYCL DEF 9\.1 DWELL ({_NUM})", body)
            if not dm:
                raise NcError(ln, "CYCL DEF 9.0 must be followed by CYCL DEF 9.1 DWELL <s>")
            st.dwell(ln, float(dm.group(1)), body)
            pending_dwell = None
            continue
        if n == 0:
            bm = re.fullmatch(r"BEGIN PGM (\S+) (MM|INCH)", body)
            if not bm:
                raise NcError(ln, "block 0 must be BEGIN PGM <name> MM")
            if bm.group(2) != "MM":
                raise NcError(ln, "inch programs are not supported")
            name = st.name = bm.group(1)
            continue
        em = re.fullmatch(r"END PGM (\S+) (MM|INCH)", body)
        if em:
            if em.group(1) != name or em.group(2) != "MM":
                raise NcError(ln, f"END PGM {em.group(1)} {em.group(2)} does not match BEGIN PGM {name} MM")
            st.emit(ln, "end", st.pos, body)
            st.ended = True
            continue
        tm = re.fullmatch(r"TOOL CALL(?: (\d+))? ([XYZ])(?: S\d+(?:\.\d*)?)?", body)
        if tm:
            st.plane = _PLANE_OF_TOOL_AXIS[tm.group(2)]
            st.pole = None
            continue
        if body == "CYCL DEF 9.0 DWELL TIME":
            pending_dwell = ln
            continue
        sm = re.fullmatch(r"STOP((?: M\d+)*)", body)
        if sm:
            st.emit(ln, "stop", st.pos, body)
            _, ms = _hh_tail(st, ln, sm.group(1).split(), allow_fmax=False)
            _hh_m(st, ln, [x for x in ms if x not in {"0", "1"}], body)
            continue
        tokens = body.split()
        head, rest = tokens[0], tokens[1:]
        i1, i2, i3 = PLANE_INDEX[st.plane]
        if head == "L":
            coords, rest = _hh_coords(st, ln, rest)
            rapid, ms = _hh_tail(st, ln, rest, allow_fmax=True)
            target = list(st.pos)
            for a, v in coords.items():
                target[_AXES.index(a)] = v
            if coords:
                if rapid:
                    st.rapid(ln, target, body)
                else:
                    st.line(ln, target, body, False)
            _hh_m(st, ln, ms, body)
            st.ended = st.ended or any(x in {"2", "30"} for x in ms)
        elif head == "CC":
            coords, rest = _hh_coords(st, ln, rest)
            if rest:
                raise NcError(ln, f"unknown word {rest[0]}")
            need = {_AXES[i1], _AXES[i2]}
            if set(coords) != need:
                raise NcError(ln, f"CC needs the {st.plane} plane's axes {' and '.join(sorted(need))}")
            st.pole = (coords[_AXES[i1]], coords[_AXES[i2]])
        elif head == "C":
            coords, rest = _hh_coords(st, ln, rest)
            drs = [t for t in rest if t in ("DR+", "DR-")]
            if len(drs) != 1:
                raise NcError(ln, "C needs one DR+ or DR-")
            rest = [t for t in rest if t not in drs]
            _, ms = _hh_tail(st, ln, rest, allow_fmax=False)
            if _AXES[i3] in coords:
                raise NcError(ln, f"helical arc: {_AXES[i3]} in a {st.plane} circle (not supported)")
            if st.pole is None:
                raise NcError(ln, "C without a circle centre CC")
            target = list(st.pos)
            for a, v in coords.items():
                target[_AXES.index(a)] = v
            c = list(st.pos)
            c[i1], c[i2] = st.pole
            st.arc(ln, target, c, 1 if drs[0] == "DR+" else -1, body, False)
            _hh_m(st, ln, ms, body)
            st.ended = st.ended or any(x in {"2", "30"} for x in ms)
        else:
            raise NcError(ln, f"unknown or unsupported block {body!r}")
    if pending_dwell is not None:
        raise NcError(pending_dwell, "CYCL DEF 9.0 without CYCL DEF 9.1")
    return st


def interpret(text: str, dialect: str) -> Program:
    """Execute ``text`` as ``dialect``'s controller would (the subset :mod:`~ballbar.tools.gcode` writes).

    Raises :class:`NcError` (with the 1-based line) on anything it does not
    understand or that a controller would refuse, and when the program has no end.
    """
    if dialect not in DIALECTS:
        raise NcError(None, f"unknown dialect {dialect!r} (known: {', '.join(DIALECTS)})")
    st = _interpret_heidenhain(text) if dialect == "heidenhain" else _interpret_iso(text, dialect)
    if not st.ended:
        what = "END PGM" if dialect == "heidenhain" else "M30 or M2"
        raise NcError(len(text.splitlines()), f"the program has no end ({what})")
    return st.program()


# --------------------------------------------------------------------------- moves


@dataclass(frozen=True)
class _Seg:
    """A rest-to-rest move of the program with the blocks it came from."""

    move: Move
    blocks: tuple[Block, ...]
    feed: float | None
    stop_reason: str = ""  # why the motion stops after it (for merged feed moves)


def _plane2(p: Vec3, plane: str, origin: Sequence[float]) -> tuple[float, float]:
    i1, i2, _ = PLANE_INDEX[plane]
    return (p[i1] - origin[i1], p[i2] - origin[i2])


def _tangent(b: Block, plane: str, at_end: bool) -> tuple[float, float]:
    """Unit direction of travel at the start or end of a feed block, in the plane's frame."""
    i1, i2, _ = PLANE_INDEX[plane]
    if b.kind == "line":
        dx, dy = b.end[i1] - b.start[i1], b.end[i2] - b.start[i2]
    else:
        assert b.centre is not None
        p = b.end if at_end else b.start
        rx, ry = p[i1] - b.centre[i1], p[i2] - b.centre[i2]
        dx, dy = -b.direction * ry, b.direction * rx
    n = math.hypot(dx, dy)
    return (dx / n, dy / n) if n > 0 else (0.0, 0.0)


def _junction(a: Block, b: Block, plane: str) -> str:
    """Why the motion stops between feed blocks ``a`` and ``b`` ('' if it runs through)."""
    if a.exact_stop:
        return f"exact stop at the end of line {a.line}"
    if a.feed_mm_min != b.feed_mm_min:
        return f"feed change at line {b.line}"
    ta, tb = _tangent(a, plane, True), _tangent(b, plane, False)
    turn = math.atan2(ta[0] * tb[1] - ta[1] * tb[0], ta[0] * tb[0] + ta[1] * tb[1])
    if abs(turn) > TANGENT_TOL_RAD:
        return f"corner of {math.degrees(abs(turn)):.3g} deg at line {b.line}"
    if a.kind != b.kind:
        raise NcError(b.line, "a line and an arc meet tangentially: the controller does not stop there, "
                              "and no rest-to-rest move describes them")
    return ""


def _feed_move(run: list[Block], plane: str, origin: Sequence[float], u_ref: float) -> tuple[Move, float]:
    first, last = run[0], run[-1]
    p0, p1 = _plane2(first.start, plane, origin), _plane2(last.end, plane, origin)
    if first.kind == "line":
        return Move("line", "line", p0, p1), u_ref
    u = math.atan2(p0[1], p0[0])
    u += 2 * math.pi * round((u_ref - u) / (2 * math.pi))
    sweep = math.fsum(b.sweep_rad for b in run)
    radius = math.hypot(*p0)
    name = "ccw" if sweep > 0 else "cw"
    return Move("arc", name, p0, p1, radius, u, sweep), u + sweep


def _segments(program: Program, plane: str, origin: Sequence[float], start_deg: float) -> list[_Seg]:
    """The program from its first feed move on, as rest-to-rest moves (feed blocks merged)."""
    _, _, i3 = PLANE_INDEX[plane]
    out: list[_Seg] = []
    run: list[Block] = []
    u_ref = math.radians(start_deg)
    started = False

    def close(reason: str) -> None:
        nonlocal run, u_ref
        if run:
            mv, u_ref = _feed_move(run, plane, origin, u_ref)
            out.append(_Seg(mv, tuple(run), run[0].feed_mm_min, reason))
            run = []

    for b in program.blocks:
        if b.kind in ("line", "arc"):
            started = True
            if b.kind == "arc" and b.plane != plane:
                raise NcError(b.line, f"arc in the {b.plane} plane, the test's is {plane}")
            if b.kind == "line" and abs(b.end[i3] - b.start[i3]) > 1e-12:
                raise NcError(b.line, f"feed move along {_AXES[i3]}, out of the {plane} plane")
            if run:
                reason = _junction(run[-1], b, plane)
                if reason:
                    close(reason)
            run.append(b)
            continue
        if not started:
            continue
        close(f"{b.kind} at line {b.line}")
        p = _plane2(b.start, plane, origin)
        if b.kind == "dwell":
            out.append(_Seg(Move("dwell", "dwell", p, p, duration_s=b.duration_s), (b,), None))
        elif b.kind == "rapid":
            out.append(_Seg(Move("line", "rapid", p, _plane2(b.end, plane, origin)), (b,), None))
        elif b.kind == "stop":
            out.append(_Seg(Move("dwell", "stop", p, p, duration_s=math.inf), (b,), None))
        else:
            break
    close("end of program")
    return out


def _split_tests(segs: list[_Seg], start_deg: float) -> list[list[_Seg]]:
    """Tests: from an inward line (feed-in) to the next outward line (feed-out), moves named as ``moves``.

    Each test's arcs are shifted by whole turns so that its first arc starts
    within half a turn of ``start_deg`` (a repeated test starts where the plan does).
    """
    tests: list[list[_Seg]] = []
    cur: list[_Seg] | None = None
    for s in segs:
        mv = s.move
        radial = math.hypot(*mv.end) - math.hypot(*mv.start) if mv.kind == "line" and mv.name == "line" else 0.0
        if cur is None:
            if radial < 0:
                cur = [replace(s, move=replace(mv, name="feed_in"))]
            continue
        if radial > 0:
            if not any(x.move.kind == "arc" for x in cur):  # in and out with no arc: a signature's excursion
                cur = None
                continue
            cur.append(replace(s, move=replace(mv, name="feed_out")))
            tests.append(_rewind(cur, math.radians(start_deg)))
            cur = None
            continue
        if mv.kind == "dwell" and mv.name == "dwell":
            prev = cur[-1].move.name
            name = {"feed_in": "dwell_in", "ccw": "dwell_ccw", "cw": "dwell_cw"}.get(prev, "dwell")
            s = replace(s, move=replace(mv, name=name))
        elif radial < 0:
            s = replace(s, move=replace(mv, name="feed_in"))
        cur.append(s)
    return tests


def program_moves(program: Program, plane: str, *, origin: Sequence[float] = (0.0, 0.0, 0.0),
                  start_deg: float = 0.0) -> list[Move]:
    """The whole program from its first feed move on (signatures, tests, the moves between) as rest-to-rest
    moves in the plane's frame, as :func:`test_moves` takes each test's; arcs' angles unwound from
    ``start_deg``.  Names are the program's (``line``, ``arc`` as ``ccw``/``cw``, ``dwell``, ``rapid``,
    ``stop``), not the plan's."""
    return [s.move for s in _segments(program, plane, origin, start_deg)]


def signatures(program: Program, plane: str, *, origin: Sequence[float] = (0.0, 0.0, 0.0)) -> list[list[float]]:
    """Per test, the depths (mm toward the pivot) of the excursions before its feed-in: its signature
    (:mod:`ballbar.analysis.plans`); an empty list where a test has none.  An excursion is an inward line
    followed by an outward one with only dwells between; a test begins at an inward line followed by an arc."""
    out: list[list[float]] = []
    pending: list[float] = []
    segs = _segments(program, plane, origin, 0.0)
    k = 0
    while k < len(segs):
        mv = segs[k].move
        if mv.kind == "line" and mv.name == "line" and math.hypot(*mv.end) < math.hypot(*mv.start):
            j = k + 1
            while j < len(segs) and segs[j].move.kind == "dwell":
                j += 1
            nxt = segs[j].move if j < len(segs) else None
            if nxt is not None and nxt.kind == "line" and math.hypot(*nxt.end) > math.hypot(*nxt.start):
                pending.append(math.hypot(*mv.start) - math.hypot(*mv.end))
                k = j + 1
                continue
            if nxt is not None and nxt.kind == "arc":
                out.append(pending)
                pending = []
                while k < len(segs) and not (segs[k].move.kind == "line"
                                             and math.hypot(*segs[k].move.end) > math.hypot(*segs[k].move.start)):
                    k += 1  # to the test's feed-out
        k += 1
    return out


def _rewind(test: list[_Seg], u_ref: float) -> list[_Seg]:
    first = next((s.move for s in test if s.move.kind == "arc"), None)
    if first is None:
        return test
    shift = 2 * math.pi * round((u_ref - first.u_start) / (2 * math.pi))
    if shift == 0:
        return test
    return [replace(s, move=replace(s.move, u_start=s.move.u_start + shift)) if s.move.kind == "arc" else s
            for s in test]


def test_moves(
    program: Program,
    plane: str,
    *,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    index: int = 0,
    start_deg: float = 0.0,
) -> list[Move]:
    """The moves of test ``index`` (0: the first) from its feed-in to its feed-out.

    Coordinates in ``plane``'s (first, second) frame, mm from the pivot at
    ``origin`` (work coordinates, X Y Z); names as :func:`ballbar.analysis.program.moves`
    gives them (``feed_in``, ``dwell_in``, ``ccw``, ``dwell_ccw``, ``cw``,
    ``dwell_cw``, ``feed_out``; a program stop inside the test is a dwell named
    ``stop`` of infinite duration, a rapid a line named ``rapid``).  The first
    arc's start angle is unwrapped to within 180 deg of ``start_deg`` (pass
    :func:`~ballbar.analysis.program.arc_start_deg` of the plan's first direction
    to get the plan's angles), later ones continue from the arc before.
    Raises :class:`NcError` when the program holds no such test or cannot be
    cut into rest-to-rest moves.
    """
    tests = _split_tests(_segments(program, plane, origin, start_deg), start_deg)
    if not 0 <= index < len(tests):
        raise NcError(None, f"the program holds {len(tests)} test(s) (feed-in to feed-out), no test {index}")
    return [s.move for s in tests[index]]


test_moves.__test__ = False  # type: ignore[attr-defined]  # not a pytest test, whoever imports it


# --------------------------------------------------------------------------- the check


def _dist(a: tuple[float, float], b: tuple[float, float]) -> float:
    return math.hypot(a[0] - b[0], a[1] - b[1])


def _geometry_ok(got: Move, want: Move, tol: float) -> list[str]:
    """Differences of one move beyond ``tol`` (mm, per coordinate); empty when it matches."""
    out: list[str] = []
    t2 = tol * math.sqrt(2.0)
    if got.kind == "dwell":
        if abs(got.duration_s - want.duration_s) > DWELL_TOL_S:
            out.append(f"lasts {got.duration_s:g} s, the plan's {want.duration_s:g} s")
        return out
    if _dist(got.start, want.start) > t2:
        out.append(f"starts at ({got.start[0]:.6f}, {got.start[1]:.6f}), the plan's "
                   f"({want.start[0]:.6f}, {want.start[1]:.6f})")
    if _dist(got.end, want.end) > t2:
        out.append(f"ends at ({got.end[0]:.6f}, {got.end[1]:.6f}), the plan's ({want.end[0]:.6f}, {want.end[1]:.6f})")
    if got.kind == "arc":
        R = want.radius
        if abs(got.radius - R) > t2:
            out.append(f"radius {got.radius:.6f} mm, the plan's {R:g} mm")
        if abs(got.u_start - want.u_start) > t2 / R:
            u_got, u_want = math.degrees(got.u_start), math.degrees(want.u_start)
            out.append(f"starts at {u_got:.6f} deg, the plan's {u_want:.6f} deg")
        if abs(got.sweep - want.sweep) > 2 * t2 / R:
            out.append(f"sweeps {math.degrees(got.sweep):.6f} deg, the plan's {math.degrees(want.sweep):.6f} deg")
    return out


def _angle_at(moves_: list[Move], profiles: list[_Profile | None], t0: list[float], t: np.ndarray) -> np.ndarray:
    """Commanded angle (rad) at times ``t`` (from the feed-in's start): arcs move it, the rest holds it."""
    first_arc = next((m for m in moves_ if m.kind == "arc"), None)
    out = np.full(t.size, first_arc.u_start if first_arc else math.nan)
    for mv, prof, ts in zip(moves_, profiles, t0, strict=True):
        if mv.kind != "arc" or prof is None:
            continue
        after = t >= ts
        s = prof.position(t[after] - ts)
        out[after] = mv.u_start + math.copysign(1.0, mv.sweep) * s / mv.radius
    return out


def _timing(test: list[_Seg], plan: TestPlan, want: list[Move], matched: list[bool], accel: float) -> list[str]:
    """Angle vs time on the data arcs and the feed-out centroid against :func:`schedule`.

    Each move runs a trapezoid from rest to rest at its own feed.  A move whose
    geometry matched the plan's within the rounding runs the plan's geometry,
    so that the comparison sees the timing (merging, stops, feeds, dwells), not
    the rounding of the coordinates, which the geometry check has bounded.
    """
    mvs: list[Move] = []
    profiles: list[_Profile | None] = []
    starts: list[float] = []
    t = 0.0
    for k, s in enumerate(test):
        mv = want[k] if matched[k] else s.move
        mvs.append(mv)
        starts.append(t)
        if mv.kind == "dwell":
            profiles.append(None)
            t += s.move.duration_s
        else:
            V = (s.feed or plan.feed_mm_min) / 60.0
            prof = _Profile(mv.length_mm, V, accel, 0.0)
            profiles.append(prof)
            t += prof.duration
    if not all(math.isfinite(x) for x in starts):
        return ["timing: not comparable (the test holds a program stop)"]
    out: list[str] = []
    V = plan.feed_mm_s
    out += [f"timing: {x}" for x in model_limits(plan, accel)]  # the plan's own breaks of the model first
    sch = schedule(plan, V, V / accel)
    fi = profiles[0]
    assert fi is not None
    t_fi = starts[0] + fi.duration / 2.0
    for d in plan.direction_list:
        name = "ccw" if d > 0 else "cw"
        rel = np.linspace(sch.data_start_s[d], sch.data_end_s[d], 2001)
        got = np.degrees(_angle_at(mvs, profiles, starts, rel + t_fi))
        exp = sch.angle_deg(plan, d, rel)
        err = np.abs(got - exp)
        k = int(np.argmax(err))
        if not err[k] <= ANGLE_TOL_DEG:
            out.append(
                f"timing: on the {name} data arc the commanded angle departs from the analyzer's schedule by "
                f"{err[k]:.6g} deg (at {rel[k]:.6f} s after the feed-in centroid: {got[k]:.6f} deg, "
                f"the schedule {exp[k]:.6f} deg)"
            )
    fo = profiles[-1]
    if fo is not None and test[-1].move.name == "feed_out":
        t_fo = starts[-1] + fo.duration / 2.0 - t_fi
        if abs(t_fo - sch.feed_out_centroid_s) > TIME_TOL_S:
            out.append(
                f"timing: the feed-out centroid comes {t_fo:.6f} s after the feed-in's, "
                f"the schedule {sch.feed_out_centroid_s:.6f} s"
            )
    return out


def _structure(test: list[_Seg], want: list[Move]) -> list[str]:
    got_names = [s.move.name for s in test]
    want_names = [m.name for m in want]
    if got_names == want_names:
        return []
    out = [f"moves: the program runs {' '.join(got_names)}; the plan {' '.join(want_names)}"]
    for a, b in itertools.pairwise(test):
        if a.move.kind == "arc" and b.move.kind == "arc" and a.move.name == b.move.name:
            out.append(f"the {a.move.name} arc stops ({a.stop_reason}); the plan runs it as one move")
    for k in range(1, len(test) - 1):
        before, m, after = test[k - 1].move, test[k].move, test[k + 1].move
        if m.kind == "dwell" and before.kind == "arc" and after.kind == "arc" and before.name == after.name:
            what = "program stop" if m.name == "stop" else "dwell"
            out.append(f"a {what} at line {test[k].blocks[0].line} splits the {before.name} arc")
    if any(s.move.name == "rapid" for s in test):
        out.append("a rapid inside the test")
    return out


def check_against_plan(
    text: str,
    dialect: str,
    plan: TestPlan,
    accel_mm_s2: float = 2000.0,
    *,
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    decimals: int | None = None,
) -> list[str]:
    """Problems of the program ``text`` against ``plan``; empty when it runs exactly the plan's path and timing.

    Each test of the program (feed-in .. feed-out) is compared with
    :func:`~ballbar.analysis.program.moves`: the moves' kinds and order, end
    points, radius, start angle and sweep within the rounding (``0.6 *
    10**-decimals`` mm per coordinate, ``decimals`` read from the program unless
    given), every arc block's centre and radius, the third axis at the pivot's
    level, the feed equal to ``plan.feed_mm_min`` exactly, the dwells.  Then the
    timing: each move as a trapezoid at ``V = F / 60`` and ``accel_mm_s2`` from
    rest to rest, the commanded angle on both data arcs and the feed-out
    centroid against :func:`~ballbar.analysis.program.schedule` ``(plan, V, V / A)``
    to 1e-6 deg and 1e-6 s.  A program the interpreter refuses gives its
    :class:`NcError` message as the one problem.
    """
    o = (float(origin[0]), float(origin[1]), float(origin[2]))
    try:
        prog = interpret(text, dialect)
        first_dir = plan.direction_list[0]
        u0 = arc_start_deg(plan, first_dir)
        tests = _split_tests(_segments(prog, plan.plane, o, u0), u0)
    except NcError as err:
        return [str(err)]
    if not tests:
        return ["no test found: no feed-in (a feed move toward the pivot) followed by a feed-out"]
    dec = prog.decimals if decimals is None else decimals
    unit = 10.0**-dec
    # The pivot rounds to the grid too, and every point with it.
    tol = 0.6 * unit + max(abs(v - round(v / unit) * unit) for v in o)
    t2 = tol * math.sqrt(2.0)
    want = moves(plan)
    R = plan.radius_mm
    _, _, i3 = PLANE_INDEX[plan.plane]
    problems: list[str] = []
    for k, test in enumerate(tests):
        pre = f"test {k + 1}: " if len(tests) > 1 else ""
        out: list[str] = []
        structure = _structure(test, want)
        out += structure
        matched = [False] * len(test)
        if not structure:
            for j, (s, w) in enumerate(zip(test, want, strict=True)):
                diffs = _geometry_ok(s.move, w, tol)
                matched[j] = not diffs
                where = f" (line {s.blocks[0].line})" if s.blocks else ""
                out += [f"{w.name}{where}: {d}" for d in diffs]
        wrong_feed: dict[float | None, list[int]] = {}
        for s in test:
            for b in s.blocks:
                if b.kind in ("line", "arc") and b.feed_mm_min != plan.feed_mm_min:
                    wrong_feed.setdefault(b.feed_mm_min, []).append(b.line)
                if b.kind in ("line", "arc") and abs(b.end[i3] - o[i3]) > tol:
                    out.append(f"line {b.line}: {_AXES[i3]} {b.end[i3]:g}, the pivot's {o[i3]:g}")
                if b.kind == "arc":
                    assert b.centre is not None
                    c = _plane2(b.centre, plan.plane, o)
                    if math.hypot(*c) > t2:
                        out.append(f"line {b.line}: arc centre {math.hypot(*c):.6f} mm from the pivot")
                    for end, p in (("start", b.start), ("end", b.end)):
                        r = math.hypot(*_plane2(p, plan.plane, o))
                        if abs(r - R) > t2:
                            out.append(f"line {b.line}: arc {end} radius {r:.6f} mm, the plan's {R:g} mm")
        for f, lines in wrong_feed.items():
            out.append(f"feed {f!r} mm/min on lines {_ranges(lines)}, the plan's {plan.feed_mm_min!r}")
        out += _timing(test, plan, want, matched, accel_mm_s2) if _comparable(test) else []
        problems += [pre + p for p in dict.fromkeys(out)]
    return problems


def _ranges(lines: list[int]) -> str:
    return ", ".join(str(n) for n in lines[:6]) + (f" and {len(lines) - 6} more" if len(lines) > 6 else "")


def _comparable(test: list[_Seg]) -> bool:
    return (
        test[0].move.name == "feed_in"
        and test[-1].move.name == "feed_out"
        and all(s.move.name != "rapid" for s in test)
    )


__all__ = ["Block", "NcError", "Program", "check_against_plan", "interpret", "model_limits", "signatures",
           "test_moves"]
