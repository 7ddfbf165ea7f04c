"""Plans as a library, and which plan a test ran, from the recording alone.

A machine's check is a set of tests: XY over 360 deg, the vertical planes ZX
and YZ over 220 deg, often at two feeds.  The daemon knows them as a library
of named plans (``[plans.<name>]``; a single ``[plan]`` is a library of one,
named ``default``), and tells which plan each test ran without an operator.

The result fields a set stands on (the contract with the set result)
--------------------------------------------------------------------
Every circle and test result names its plan beside the plan's keys:

``result["plan"]["name"]``
    the plan's name in the library (``"default"`` for a single ``[plan]``).
``result["plan"]["plane"]``
    ``XY``, ``YZ`` or ``ZX``, as before.
``result["plan"]["axes"]``
    the machine axes of the plane's first and second axis, ``["X", "Y"]``,
    ``["Y", "Z"]`` or ``["Z", "X"]``.  Every ``_x`` field of the result
    (``backlash_x_um``, ``reversal_spike_x_*``, ``lateral_play_x_um``, ...) is
    about ``axes[0]``, every ``_y`` field about ``axes[1]``;
    ``servo_mismatch_ms`` is ``lag(axes[0]) - lag(axes[1])``,
    ``scale_mismatch_ppm`` is ``e(axes[0]) - e(axes[1])`` and
    ``squareness_urad`` is ``S`` of ``D(axes[0]) = S * axes[1]`` (urad).  So
    the three planes' squareness values are, on one convention,
    ``S_XY: DX = S Y``, ``S_YZ: DY = S Z``, ``S_ZX: DZ = S X``
    (analysis/README.md, "Three planes, one machine").
``result["recognition"]``
    how the plan was known: ``method`` (``only``: a library of one;
    ``signature``: the code its program carries before the feed-in;
    ``timing``: the only plan whose timing fits the test; ``chosen``: named
    by an operator or service), ``signature`` (the code read, or null),
    ``feed_ratio`` (the feed-in to feed-out span's feed over the plan's, or
    null), ``candidates`` (the plans that fitted the timing) and ``message``.

A test that matches no plan, or more than one, gets no result: an event
``test_unrecognised`` (``reason``: ``no_match`` or ``ambiguous``,
``candidates``, ``message``) says why.  The monitor's history
(``<state_dir>/monitor/<m>-history.jsonl``) keeps each test's
``conditions.plan``; trends, limits and alerts are per plan.

The configuration (``Config.plans``, ``Config.sets``; recorded as
``config["plans"]`` and ``config["sets"]``): ``plans`` maps each name to
its plan's keys plus ``signature`` (the code, 0..124) and ``limits`` (its
own ``[limits]`` over the global one, or absent); ``sets`` maps each name to
``plans`` (names) and ``window_minutes`` (the time within which a set's tests
must all have run).
"""

from __future__ import annotations

import fnmatch
import math
import re
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np

from .errors import PlanError
from .plan import PLANE_AXES, TestPlan
from .program import Move, arc_start_deg, feed_from_span, schedule

if TYPE_CHECKING:
    from ballbar.protocol.messages import results

# --------------------------------------------------------------------------- the signature
#
# A program that ``ballbar gcode`` writes for a library of several plans begins, after the bar is mounted and
# before the feed-in, with its plan's code: four short radial excursions from the wait point at R + f toward
# the pivot and back, each a dwell at a depth of 1..5 eighths of the feed-in.  Three carry the code (5^3 =
# 125 codes), the fourth is a check.  Depths are lengths the bar reads to micrometres whatever the feed, the
# override or the sample rate; the dwells hold each depth for SIGNATURE_ON_S, enough for 9 samples at
# 15.625 Hz.  Every excursion returns to R + f, so repeated symbols stay apart; none comes within a quarter of
# the feed-in of R, so the test detector never takes one for a feed-in.

SIGNATURE_LEVELS = 5  # depths 1..5 x SIGNATURE_STEP of the feed-in
SIGNATURE_STEP = 1.0 / 8.0  # of the feed-in: the deepest (5/8) stays clear of the detector's band about R (3/4)
SIGNATURE_DATA = 3  # symbols carrying the code
SIGNATURE_CODES = SIGNATURE_LEVELS**SIGNATURE_DATA  # 125
SIGNATURE_ON_S = 0.6  # dwell at each depth
SIGNATURE_OFF_S = 0.6  # dwell back at R + f between excursions
SIGNATURE_REST_S = 1.0  # dwell at R + f after the last excursion, before the feed-in
SIGNATURE_WINDOW_S = 15.0  # how far before a feed-in the signature is looked for
SIGNATURE_MIN_S = 0.5 * SIGNATURE_ON_S  # an excursion shorter than this is a move's samples, not a dwell
_SLACK_S = 1.0  # beyond the programmed dwells: moves, acceleration, feed override, the sample period
_SYMBOL_TOL = 0.3  # of a depth step: how far a plateau may read from its symbol's depth

NAME_RE = re.compile(r"[A-Za-z0-9_-]{1,40}")


def signature_symbols(code: int) -> tuple[int, ...]:
    """The four depths (1..5) of ``code`` (0..124): three digits base 5, most significant first, and the
    check ``(d1 + 2 d2 + 3 d3) mod 5``, each plus one."""
    if isinstance(code, bool) or not isinstance(code, int) or not 0 <= code < SIGNATURE_CODES:
        raise PlanError(f"a signature is a whole number within 0..{SIGNATURE_CODES - 1}, not {code!r}")
    d = [(code // SIGNATURE_LEVELS**k) % SIGNATURE_LEVELS for k in range(SIGNATURE_DATA - 1, -1, -1)]
    check = sum((k + 1) * v for k, v in enumerate(d)) % SIGNATURE_LEVELS
    return (*(v + 1 for v in d), check + 1)


def signature_code(symbols: Sequence[int]) -> int | None:
    """The code of four symbols (1..5), or None where they are not a signature (the check fails): a misread
    depth or two neighbours swapped never reads as another code."""
    if len(symbols) != SIGNATURE_DATA + 1 or not all(1 <= s <= SIGNATURE_LEVELS for s in symbols):
        return None
    code = 0
    for s in symbols[:SIGNATURE_DATA]:
        code = code * SIGNATURE_LEVELS + (s - 1)
    return code if signature_symbols(code) == tuple(symbols) else None


def default_signature(name: str) -> int:
    """A plan's code unless configured: from its name alone, so that adding or removing other plans never
    changes the code of a program already at the machine (two names may share one: the library says so)."""
    return zlib.crc32(name.encode("utf-8")) % SIGNATURE_CODES


def signature_depths_mm(code: int, feed_in_mm: float) -> tuple[float, ...]:
    """How far (mm) each excursion of ``code``'s signature goes toward the pivot."""
    return tuple(s * SIGNATURE_STEP * feed_in_mm for s in signature_symbols(code))


def signature_moves(plan: TestPlan, code: int) -> list[Move]:
    """The signature as moves in the plane's frame (mm from the pivot): from the wait point at ``R + f`` on the
    first arc's start angle, each excursion in and out with its dwells, then the rest before the feed-in."""
    u = math.radians(arc_start_deg(plan, plan.direction_list[0]))
    R, f = plan.radius_mm, plan.feed_in_mm
    out_p = ((R + f) * math.cos(u), (R + f) * math.sin(u))
    moves: list[Move] = []
    depths = signature_depths_mm(code, f)
    for k, depth in enumerate(depths, 1):
        r = R + f - depth
        in_p = (r * math.cos(u), r * math.sin(u))
        moves.append(Move("line", f"sig_in_{k}", out_p, in_p))
        moves.append(Move("dwell", f"sig_on_{k}", in_p, in_p, duration_s=SIGNATURE_ON_S))
        moves.append(Move("line", f"sig_out_{k}", in_p, out_p))
        last = k == len(depths)
        moves.append(Move("dwell", "sig_rest" if last else f"sig_off_{k}", out_p, out_p,
                          duration_s=SIGNATURE_REST_S if last else SIGNATURE_OFF_S))
    return moves


def signature_duration_s(plan: TestPlan, code: int) -> float:
    """The signature's length in time at the plan's feed, moves taken at the feed (no acceleration)."""
    moving = 2.0 * sum(signature_depths_mm(code, plan.feed_in_mm)) / plan.feed_mm_s
    n = SIGNATURE_DATA + 1
    return moving + n * SIGNATURE_ON_S + (n - 1) * SIGNATURE_OFF_S + SIGNATURE_REST_S


@dataclass(frozen=True)
class SignatureReading:
    """What the samples before a feed-in say.  ``code``: the code read, None where there is none;
    ``symbols``: the depths read (1..5, in order); ``note``: why no code (none seen, a partial or unreadable
    one), empty when one was read."""

    code: int | None
    symbols: tuple[int, ...] = ()
    note: str = ""

    def describe(self) -> str:
        return f"signature {self.code}" if self.code is not None else (self.note or "no signature")


def read_signature(t: np.ndarray, L: np.ndarray, t_end: float, rest_mm: float, feed_in_mm: float,
                   ) -> SignatureReading:
    """The signature in the samples ``(t, L)`` before ``t_end`` (the feed-in's last sample at rest), read
    against the rest level ``rest_mm`` (``R + f`` as the bar reads it).

    Each sample is at rest (within half a depth step of the level), in an excursion (deeper, but short of the
    detector's band about R) or neither (the test before, the bar off its cups): only what follows the last
    such sample counts.  An excursion is a run between rest samples at least :data:`SIGNATURE_MIN_S` long
    (shorter runs are samples of a move, reordered by jitter); the signature is the chain of
    excursions ending within the rest's time before ``t_end``, each at most the programmed gap after the one
    before.  Its depths must read within a third of a step of a symbol.
    """
    step = SIGNATURE_STEP * feed_in_mm
    m = (t > t_end - SIGNATURE_WINDOW_S) & (t <= t_end)
    tw, depth = t[m], rest_mm - L[m]
    if tw.size == 0:
        return SignatureReading(None, (), "no samples before the feed-in")
    rest = np.abs(depth) < 0.5 * step
    exc = (depth >= 0.5 * step) & (depth < (SIGNATURE_LEVELS + 0.5) * step)
    other = ~(rest | exc)
    start = int(np.flatnonzero(other)[-1]) + 1 if other.any() else 0
    # the excursions: runs of ``exc`` with a rest sample on both sides
    runs: list[tuple[int, int]] = []
    i, n = start, tw.size
    while i < n:
        if not exc[i]:
            i += 1
            continue
        j = i
        while j < n and exc[j]:
            j += 1
        # bounded by rest on both sides, and as long as a dwell at a depth: not a sample or two of a move
        # through the threshold (timestamp jitter reorders them there)
        if i > start and j < n and tw[j - 1] - tw[i] >= SIGNATURE_MIN_S:
            runs.append((i, j))
        i = j
    if not runs:
        return SignatureReading(None, (), "no signature before the feed-in")
    chain = [runs[-1]]
    if t_end - tw[runs[-1][1] - 1] > SIGNATURE_REST_S + _SLACK_S:
        return SignatureReading(None, (), "no signature before the feed-in (the last excursion toward the pivot "
                                f"ended {t_end - tw[runs[-1][1] - 1]:.1f} s before it)")
    for a, b in reversed(runs[:-1]):
        if tw[chain[0][0]] - tw[b - 1] > SIGNATURE_OFF_S + _SLACK_S:
            break
        chain.insert(0, (a, b))
    symbols: list[int] = []
    for a, b in chain:
        d = depth[a:b] / step
        level = float(np.median(d))
        s = round(level)
        near = np.abs(d - s) <= _SYMBOL_TOL
        if abs(level - s) > _SYMBOL_TOL or near.sum() < 2 or not 1 <= s <= SIGNATURE_LEVELS:
            return SignatureReading(None, tuple(symbols), f"an unreadable signature: an excursion of "
                                    f"{level * step:.3f} mm at t={tw[a]:.3f} s is no depth of the code")
        symbols.append(s)
    if len(symbols) != SIGNATURE_DATA + 1:
        return SignatureReading(None, tuple(symbols), f"a partial signature: {len(symbols)} excursion(s) before "
                                f"the feed-in, a signature has {SIGNATURE_DATA + 1}")
    code = signature_code(symbols)
    if code is None:
        return SignatureReading(None, tuple(symbols), f"an unreadable signature: depths {symbols} fail the check")
    return SignatureReading(code, tuple(symbols))


# --------------------------------------------------------------------------- the library

#: What a result's ``plan`` carries beside the plan's keys (see the module docstring).
RESULT_PLAN_KEYS = ("name", "axes")


def plan_of_result(plan: Mapping[str, Any]) -> TestPlan:
    """The :class:`~.plan.TestPlan` of a result's ``plan`` (its name and axes set aside)."""
    return TestPlan.from_dict({k: v for k, v in plan.items() if k not in RESULT_PLAN_KEYS})



@dataclass(frozen=True)
class NamedPlan:
    """A plan of the library: its ``name``, the ``plan`` and the ``signature`` its program carries (None: no
    signature, a library of one)."""

    name: str
    plan: TestPlan
    signature: int | None = None
    program: str | None = None  # the CNC controller's main program while it runs: a name or a glob ([controller])

    @property
    def axes(self) -> tuple[str, str]:
        return PLANE_AXES[self.plan.plane]


@dataclass(frozen=True)
class PlanLibrary:
    """The plans a machine runs, in configuration order.

    Lengths.  A ball-bar reads its displacement about the length it is
    assembled to (the base bar and its extensions); the daemon adds the
    calibration ``cal_mm`` of the bar as assembled for the first plan.  So
    every plan's feed-in is the same step of the same readings, ``R0 + f`` to
    ``R0`` (``R0``: the first plan's radius), and a plan of radius ``R``
    reads ``L + (R - R0)`` (:meth:`offset_mm`).  The radius therefore shows
    in the timing (the arcs' length), not in the level; every plan of a
    library has the same feed-in ``f``.
    """

    plans: tuple[NamedPlan, ...]

    def __post_init__(self) -> None:
        if not self.plans:
            raise PlanError("a plan library needs at least one plan")
        seen: dict[str, str] = {}
        codes: dict[int, str] = {}
        f0 = self.plans[0].plan.feed_in_mm
        for p in self.plans:
            if not NAME_RE.fullmatch(p.name):
                raise PlanError(f"plan name {p.name!r}: 1..40 letters, digits, _ or -")
            if p.name in seen:
                raise PlanError(f"plan name {p.name!r} twice")
            seen[p.name] = p.name
            if p.plan.feed_in_mm != f0:
                raise PlanError(f"plans.{p.name}.feed_in_mm = {p.plan.feed_in_mm:g}: every plan of a library has "
                                f"the feed-in of the first ({self.plans[0].name}: {f0:g} mm), the step the "
                                "detector looks for")
            if p.signature is not None:
                signature_symbols(p.signature)
                if p.signature in codes:
                    raise PlanError(f"plans {codes[p.signature]} and {p.name} have the same signature "
                                    f"{p.signature}: give one of them its own (signature = 0..{SIGNATURE_CODES - 1})")
                codes[p.signature] = p.name
        if len(self.plans) > 1 and any(p.signature is None for p in self.plans):
            raise PlanError("every plan of a library of several has a signature")

    def by_program(self, program: str | None) -> NamedPlan | None:
        """The first plan, in order, whose ``program`` pattern (``fnmatch``, case-sensitive) matches the
        controller's main program (None: none, or no program)."""
        if not program:
            return None
        return next((p for p in self.plans if p.program and fnmatch.fnmatchcase(program, p.program)), None)

    @classmethod
    def single(cls, plan: TestPlan, name: str = "default") -> PlanLibrary:
        return cls((NamedPlan(name, plan),))

    @classmethod
    def from_plans(cls, plans: Mapping[str, TestPlan], signatures: Mapping[str, int | None] | None = None,
                   ) -> PlanLibrary:
        """A library of ``plans`` in order; with more than one, each signature is ``signatures``'s or
        :func:`default_signature` of its name."""
        sig = dict(signatures or {})
        many = len(plans) > 1
        return cls(tuple(NamedPlan(n, p, (sig.get(n) if sig.get(n) is not None else default_signature(n))
                                   if many else sig.get(n)) for n, p in plans.items()))

    def __len__(self) -> int:
        return len(self.plans)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.plans)

    @property
    def first(self) -> NamedPlan:
        return self.plans[0]

    def get(self, name: str) -> NamedPlan:
        for p in self.plans:
            if p.name == name:
                return p
        raise PlanError(f"no plan {name!r} (plans: {', '.join(self.names)})")

    def by_signature(self, code: int) -> NamedPlan | None:
        return next((p for p in self.plans if p.signature == code), None)

    def offset_mm(self, name: str) -> float:
        """What to add to the readings for plan ``name`` (its radius less the first plan's)."""
        return self.get(name).plan.radius_mm - self.first.plan.radius_mm

    def detection_plan(self) -> TestPlan:
        """The plan the test detector looks for steps with: the first plan's levels, the shortest dwell of any
        plan (the level after a step is read within the dwell).  Each test's steps are timed again with its
        own plan once it is known (:meth:`same_steps`)."""
        return self.first.plan.with_(dwell_s=min(p.plan.dwell_s for p in self.plans))

    def same_steps(self, name: str) -> bool:
        """Whether the detector times plan ``name``'s steps as :meth:`detection_plan`'s (same feed and dwell)."""
        p, d = self.get(name).plan, self.detection_plan()
        return p.feed_mm_min == d.feed_mm_min and p.dwell_s == d.dwell_s

    def to_dict(self) -> dict[str, Any]:
        return {p.name: {**p.plan.to_dict(), "signature": p.signature} for p in self.plans}


# --------------------------------------------------------------------------- recognition

#: The feed overrides a test may run at and still be recognised by its timing (and the check of a signature).
OVERRIDE = (0.8, 1.2)
OVERRIDE_TOL = 0.03  # beyond them: the measured span's own spread, the overhead's
MAX_OVERHEAD_S = 0.3  # the per-move overhead (acceleration, in-position waits) a plan's timing allows

Method = Literal["only", "signature", "timing", "chosen", "controller"]


@dataclass(frozen=True)
class Recognition:
    """Which plan a test ran (see the module docstring).  ``name`` None: no match (``reason`` ``no_match``
    or ``ambiguous``), the test is not analysed as any plan."""

    name: str | None
    method: Method | None
    signature: int | None = None
    feed_ratio: float | None = None
    candidates: tuple[str, ...] = ()
    reason: str = ""
    message: str = ""
    controller: results.ControllerUse | None = None  # what the CNC controller said (None: no controller)

    def to_dict(self) -> results.Recognition:
        """As a result states it (a recognised test's: ``method`` is set)."""
        return {"method": cast("Method", self.method), "signature": self.signature, "feed_ratio": self.feed_ratio,
                "candidates": list(self.candidates), "message": self.message}


def feed_ratio_range(plan: TestPlan, span_s: float, max_overhead_s: float = MAX_OVERHEAD_S) -> tuple[float, float]:
    """The feed ratios (actual / programmed) that give a feed-in to feed-out centroid span of ``span_s`` with a
    per-move overhead of 0..``max_overhead_s``: a longer overhead leaves less time to move, a higher feed."""
    lo = feed_from_span(plan, span_s, 0.0) / plan.feed_mm_s
    hi = feed_from_span(plan, span_s, max_overhead_s) / plan.feed_mm_s
    return (lo, hi) if hi >= lo else (hi, lo)


def timing_fits(library: PlanLibrary, span_s: float, names: Iterable[str] | None = None) -> dict[str, float]:
    """The plans whose program, at a feed override within :data:`OVERRIDE` (widened by :data:`OVERRIDE_TOL`),
    takes ``span_s`` from feed-in to feed-out; each with the feed ratio at no overhead."""
    lo_ok, hi_ok = OVERRIDE[0] * (1 - OVERRIDE_TOL), OVERRIDE[1] * (1 + OVERRIDE_TOL)
    out: dict[str, float] = {}
    for name in library.names if names is None else names:
        plan = library.get(name).plan
        lo, hi = feed_ratio_range(plan, span_s)
        if math.isfinite(lo) and math.isfinite(hi) and hi >= lo_ok and lo <= hi_ok:
            out[name] = lo
    return out


def _spans(plan: TestPlan) -> str:
    """The plan's feed-in to feed-out span at the override's ends."""
    a = schedule(plan, plan.feed_mm_s * OVERRIDE[1]).feed_out_centroid_s
    b = schedule(plan, plan.feed_mm_s * OVERRIDE[0], MAX_OVERHEAD_S).feed_out_centroid_s
    return f"{a:.1f}..{b:.1f} s"


def at_feed_in(library: PlanLibrary, reading: SignatureReading | None, chosen: str | None = None,
               ) -> Recognition | None:
    """What is known at the feed-in: the plan of a library of one, a chosen one, or a signature's (checked
    against the timing at the feed-out); a signature that names no plan (no match); else None (the timing
    decides at the feed-out)."""
    if len(library) == 1:
        return Recognition(library.first.name, "only")
    if chosen is not None:
        library.get(chosen)
        return Recognition(chosen, "chosen", reading.code if reading else None,
                           message=f"{chosen}: chosen for this test")
    if reading is None or reading.code is None:
        return None
    p = library.by_signature(reading.code)
    if p is None:
        codes = ", ".join(f"{q.name} {q.signature}" for q in library.plans)
        return Recognition(None, None, reading.code, reason="no_match", message=(
            f"the program's signature reads code {reading.code}, which no plan of the library carries ({codes}): "
            "a program of another configuration; not analysed"))
    return Recognition(p.name, "signature", reading.code, message=f"{p.name}: its signature {reading.code}")


def at_feed_out(library: PlanLibrary, early: Recognition | None, reading: SignatureReading | None,
                span_s: float) -> Recognition:
    """The plan of a test whose feed-in to feed-out centroid span is ``span_s`` (see the module docstring)."""
    fits = timing_fits(library, span_s)
    if early is not None and early.method in ("only", "chosen", "controller"):
        assert early.name is not None
        ratio = feed_from_span(library.get(early.name).plan, span_s, 0.0) / library.get(early.name).plan.feed_mm_s
        return replace(early, feed_ratio=ratio if math.isfinite(ratio) else None, candidates=tuple(fits))
    if early is not None and early.name is None:
        return replace(early, candidates=tuple(fits))
    window = f"{100 * OVERRIDE[0]:g}..{100 * OVERRIDE[1]:g} %"
    if early is not None:  # a signature: the timing must agree
        assert early.name is not None
        if early.name in fits:
            return replace(early, feed_ratio=fits[early.name], candidates=tuple(fits))
        plan = library.get(early.name).plan
        return Recognition(None, None, early.signature, None, tuple(fits), "no_match", (
            f"the signature names {early.name}, but the test took {span_s:.1f} s from feed-in to feed-out and "
            f"{early.name}'s program takes {_spans(plan)} at a feed override of {window}; not analysed"))
    why = reading.describe() if reading is not None else "no signature"
    if len(fits) == 1:
        (name, ratio), = fits.items()
        return Recognition(name, "timing", None, ratio, (name,), message=(
            f"{name}: the only plan whose timing fits ({span_s:.1f} s from feed-in to feed-out; {why})"))
    if not fits:
        each = "; ".join(f"{p.name} {_spans(p.plan)}" for p in library.plans)
        return Recognition(None, None, None, None, (), "no_match", (
            f"no plan's timing fits: the test took {span_s:.1f} s from feed-in to feed-out, the plans' programs "
            f"take at a feed override of {window}: {each} ({why}); not analysed"))
    return Recognition(None, None, None, None, tuple(fits), "ambiguous", (
        f"{len(fits)} plans' timing fits ({', '.join(fits)}: {span_s:.1f} s from feed-in to feed-out) and {why} "
        "tells them apart; not analysed as any of them (their programs from ballbar gcode carry signatures)"))


def by_controller(library: PlanLibrary, early: Recognition | None, reading: SignatureReading | None,
                  program: str | None, plan: str | None) -> tuple[Recognition | None, results.ControllerUse]:
    """What the CNC controller says at the feed-in: the main ``program`` it runs, and the ``plan`` whose program
    pattern that matches (None: none).  A plan it names is the test's, whatever the signature says (checked at
    the feed-out, :func:`controller_checked`); else the recognition stays ``early``.  With the controller's
    account of the test (the result's ``controller`` block)."""
    sig = library.by_signature(reading.code) if reading is not None and reading.code is not None else None
    sig_plan = sig.name if sig is not None else None
    if plan is None:
        what = (f"the controller ran {program}, which no plan's program names" if program
                else "the controller ran no program at the feed-in")
        use: results.ControllerUse = {"program": program, "plan": None, "used": False, "signature_plan": sig_plan,
                                      "timing_fits": None, "agrees": True, "message": what}
        return early, use
    library.get(plan)
    use = {"program": program, "plan": plan, "used": True, "signature_plan": sig_plan, "timing_fits": None,
           "agrees": sig_plan in (None, plan), "message": f"{plan}: the controller ran its program {program}"}
    return Recognition(plan, "controller", reading.code if reading is not None else None,
                       message=f"{plan}: the controller ran its program {program} at the feed-in", controller=use), use


def controller_program(msg: Mapping[str, Any]) -> tuple[bool | None, str | None]:
    """What a ``controller`` message (``ballbar.Controller``) says of the main program: ``(True, program)`` (None:
    none runs), ``(False, None)``: the controller is lost, not known; ``(None, None)``: nothing about it.  The
    daemon's live rule and the offline one (a recording's ``/ballbar/controller`` records)."""
    if msg.get("state") == "lost":
        return False, None
    values = [v.get("value") for v in msg.get("values") or () if isinstance(v, Mapping) and v.get("name") == "program"]
    if not values:
        return None, None
    last = values[-1]
    return True, last if isinstance(last, str) and last else None


def controller_checked(rec: Recognition) -> tuple[Recognition, str | None]:
    """A recognition by the controller checked against the signature and the timing at the feed-out: the
    recognition with its controller block completed, and the disagreement in words (None: they agree)."""
    use = rec.controller
    if use is None or not use["used"] or rec.name is None:
        return rec, None
    fits = rec.name in rec.candidates
    problems = []
    if use["signature_plan"] not in (None, rec.name):
        problems.append(f"its signature names {use['signature_plan']}")
    if not fits:
        others = f" ({', '.join(rec.candidates)} fit)" if rec.candidates else ""
        problems.append(f"{rec.name}'s timing does not fit the test at a feed override of "
                        f"{100 * OVERRIDE[0]:g}..{100 * OVERRIDE[1]:g} %{others}")
    agrees = not problems
    text = (f"{rec.name}: the controller ran its program {use['program']}" + ("; the signature and the timing agree"
            if agrees else f", but {' and '.join(problems)}; analysed as {rec.name}, the controller's"))
    done: results.ControllerUse = {**use, "timing_fits": fits, "agrees": agrees, "message": text}
    return replace(rec, controller=done, message=text), None if agrees else text


# --------------------------------------------------------------------------- samples before the feed-in


@dataclass
class RecentSamples:
    """The last ``keep_s`` seconds of samples (for the signature, and to time a test's steps again), appended
    chunk by chunk at amortised constant cost."""

    keep_s: float = SIGNATURE_WINDOW_S + 10.0
    _t: np.ndarray = field(default_factory=lambda: np.empty(4096))
    _L: np.ndarray = field(default_factory=lambda: np.empty(4096))
    _lo: int = 0
    _hi: int = 0

    def add(self, t: np.ndarray, L: np.ndarray) -> None:
        if not t.size:
            return
        need = self._hi + t.size
        if need > self._t.size:
            n = self._hi - self._lo
            cap = max(2 * (n + t.size), 4096)
            for name in ("_t", "_L"):
                new = np.empty(cap)
                new[:n] = getattr(self, name)[self._lo : self._hi]
                setattr(self, name, new)
            self._lo, self._hi = 0, n
            need = n + t.size
        self._t[self._hi : need] = t
        self._L[self._hi : need] = L
        self._hi = need
        cut = float(t[-1]) - self.keep_s
        if self._t[self._lo] < cut:
            self._lo += int(np.searchsorted(self._t[self._lo : self._hi], cut))

    def before(self, t_lim: float) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the samples kept that come before ``t_lim``."""
        t = self._t[self._lo : self._hi]
        k = int(np.searchsorted(t, t_lim))
        return t[:k].copy(), self._L[self._lo : self._lo + k].copy()


__all__ = [
    "OVERRIDE",
    "RESULT_PLAN_KEYS",
    "SIGNATURE_CODES",
    "NamedPlan",
    "PlanLibrary",
    "RecentSamples",
    "Recognition",
    "SignatureReading",
    "at_feed_in",
    "at_feed_out",
    "default_signature",
    "feed_ratio_range",
    "plan_of_result",
    "read_signature",
    "signature_code",
    "signature_depths_mm",
    "signature_duration_s",
    "signature_moves",
    "signature_symbols",
    "timing_fits",
]
