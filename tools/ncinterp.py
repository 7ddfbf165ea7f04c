"""A small NC interpreter for the programs of :mod:`ballbar.tools.gcode`: four dialects' parsers.

:func:`interpret` executes exactly the subset that :func:`~ballbar.tools.gcode.generate`
writes, per dialect, the way the controller would: modal plane, feed and
path mode; rapids, lines, centre-format arcs, dwells, program stops.  Anything
else (an unknown word or G/M code, incremental coordinates, a helix, an arc
whose end radius differs from its start radius by more than
:data:`ARC_RADIUS_ALARM_MM` as a controller would alarm, a feed move without a
feed) raises :class:`NcError` with the line number.

What the executed program does against the plan: :mod:`ballbar.tools.nccheck`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

from ballbar.analysis.errors import BallbarError
from ballbar.tools.gcode import DIALECTS, PLANE_INDEX, WORK_OFFSETS

ARC_RADIUS_ALARM_MM = 0.01  # end vs start radius of an arc block beyond which a controller alarms

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



__all__ = ["Block", "NcError", "Program", "interpret"]
