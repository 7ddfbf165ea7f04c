"""Circular-test figures of other standards beside ISO 230-4 (analysis/README.md, "Standards").

ISO 230-4 (:mod:`.iso230`) is always computed (``iso230_4``: the verdict's
limits read it).  ``[analysis] standards`` adds, under ``standards.<id>`` of
a test result, the figures of:

- ``jis_b6190_4``: JIS B 6190-4:2008, the Japanese adoption of ISO 230-4:2005.
  Circular deviation ``G`` per direction and bidirectional ``G(b)`` about the
  least-squares circle, radial deviation ``F`` about the pivot.  The 2005
  edition replaced the circular hysteresis ``H`` (of ISO 230-4:1996) by
  ``G(b)``: there is no ``H``.  Otherwise the same numbers as ``iso230_4``.
- ``asme_b5_54``: ASME B5.54-2005, the circular test of a machining centre.
  Circular deviation per direction and bidirectional, each the minimum radial
  separation of two concentric circles enclosing the path, their centre the
  one that makes it smallest (the minimum-zone centre, not the least-squares
  one); circular hysteresis, the largest radial difference between the two
  directions at one angle; radial deviation about the pivot.  A minimum-zone
  deviation is never larger than the least-squares one.

The standards' texts were not at hand: that JIS B 6190-4:2008 is ISO
230-4:2005 is stated on its own title page; that ASME B5.54 takes the
minimum-zone centre where ISO 230-4 takes the least-squares one is an
assumption, stated in every result (``assumption``).

Pure: the measured radial deviation of each data arc in, figures out.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any, TypedDict

import numpy as np

from .errors import PlanError
from .iso230 import _hysteresis, _lsc_residual
from .plan import STANDARDS

ISO = "iso230_4"


class Definition(TypedDict):
    title: str
    computes: str
    differs_from_iso230_4: str
    assumption: str
    centre_removal: str


DEFINITIONS: dict[str, Definition] = {
    ISO: Definition(
        title="ISO 230-4:2022",
        computes="G per direction and G(b) about the least-squares circle; H; F about the pivot",
        differs_from_iso230_4="-",
        assumption="",
        centre_removal="least squares circle: per direction for G, common for G(b) and H; none for F",
    ),
    "jis_b6190_4": Definition(
        title="JIS B 6190-4:2008 (ISO 230-4:2005)",
        computes="circular deviation G per direction and bidirectional G(b) about the least-squares circle; radial "
                 "deviation F (largest and smallest) about the pivot",
        differs_from_iso230_4="no circular hysteresis H: the 2005 edition of ISO 230-4, which JIS B 6190-4:2008 "
                              "adopts, replaced it by G(b); G, G(b) and F are the same numbers",
        assumption="JIS B 6190-4:2008 is ISO 230-4:2005 (its title page says so); the text was not at hand",
        centre_removal="least squares circle: per direction for G, common for G(b); none for F",
    ),
    "asme_b5_54": Definition(
        title="ASME B5.54-2005",
        computes="circular deviation per direction and bidirectional: the minimum radial separation of two "
                 "concentric circles enclosing the path, about the centre that makes it smallest (minimum zone); "
                 "circular hysteresis H, the largest radial difference between the directions at one angle; radial "
                 "deviation F about the pivot",
        differs_from_iso230_4="the circular deviations are about the minimum-zone centre, not the least-squares one: "
                              "never larger than ISO's G and G(b), smaller where the path is lopsided (a step, a "
                              "spike); H and F are the same numbers (H does not depend on the centre)",
        assumption="that ASME B5.54 takes the minimum-zone centre where ISO 230-4 takes the least-squares one: the "
                   "standard's text was not at hand",
        centre_removal="minimum zone: per direction for the circular deviation, common for the bidirectional one; "
                       "none for F",
    ),
}
KNOWN = tuple(DEFINITIONS)
assert KNOWN == STANDARDS  # the options' list (analysis/plan.py) names these


def check_names(names: Iterable[str]) -> tuple[str, ...]:
    """The standards asked for, as ids; an unknown one is a :class:`PlanError` naming the known."""
    out = tuple(names)
    for n in out:
        if n not in DEFINITIONS:
            raise PlanError(f"standards: unknown standard {n!r} (known: {', '.join(KNOWN)})")
    return out


def min_zone_residual(u: np.ndarray, dr: np.ndarray) -> np.ndarray:
    """The radial deviation about the minimum-zone centre: the centre ``(a, b)`` (the linear model of a shifted
    centre, ``dr - a cos u - b sin u``, as the least-squares circle uses) that makes its range smallest.

    A linear programme in ``(a, b, hi, lo)``: minimise ``hi - lo`` with every
    point between ``lo`` and ``hi``.  Solved on the extreme points of the
    least-squares residual and grown by the points outside the zone until none
    is: exact, and a few small programmes for any number of samples.
    """
    from scipy.optimize import linprog

    c, s = np.cos(u), np.sin(u)
    r0 = _lsc_residual(u, dr, (c, s))
    n = u.size
    if n < 4:
        return r0
    order = np.argsort(r0)
    k = min(n, 64)
    active = np.unique(np.concatenate([order[:k], order[-k:], np.linspace(0, n - 1, 32).astype(int)]))
    tol = 1e-9 * max(1.0, float(np.ptp(r0)))
    x = np.zeros(4)
    for _ in range(50):
        cc, ss, rr = c[active], s[active], dr[active]
        m = active.size
        # r - a c - b s <= hi  ->  -a c - b s - hi <= -r ;  r - a c - b s >= lo  ->  a c + b s + lo <= r
        A = np.vstack([np.column_stack([-cc, -ss, -np.ones(m), np.zeros(m)]),
                       np.column_stack([cc, ss, np.zeros(m), np.ones(m)])])
        bnd = np.concatenate([-rr, rr])
        res = linprog([0.0, 0.0, 1.0, -1.0], A_ub=A, b_ub=bnd, bounds=[(None, None)] * 4, method="highs")
        if res.status != 0:  # pragma: no cover - a bounded, feasible programme: defensive
            return r0
        x = res.x
        r = dr - x[0] * c - x[1] * s
        out = np.flatnonzero((r > x[2] + tol) | (r < x[3] - tol))
        if out.size == 0:
            return np.asarray(r)
        worst = out[np.argsort(-np.maximum(r[out] - x[2], x[3] - r[out]))[:256]]
        active = np.union1d(active, worst)
    return np.asarray(dr - x[0] * c - x[1] * s)  # pragma: no cover - converges in a few rounds


def _range(r: np.ndarray) -> float:
    return float(r.max() - r.min())


def figures(per_direction: Mapping[int, tuple[np.ndarray, np.ndarray]], chosen: Iterable[str],
            iso: Mapping[str, Any] | None = None) -> dict[str, dict[str, Any]]:
    """The figures of each chosen standard but ISO 230-4 from ``{direction: (u_rad, dR_um)}``, um.

    ``iso``: the test's ``iso230_4`` figures, which the others share where
    they agree with it (the same numbers, computed once).
    """
    out: dict[str, dict[str, Any]] = {}
    iso = dict(iso or {})
    for sid in chosen:
        if sid == ISO:
            continue
        d = DEFINITIONS[sid]
        figs: dict[str, float | None]
        if sid == "jis_b6190_4":
            figs = {k: iso.get(k) for k in ("G_ccw_um", "G_cw_um", "G_b_um", "F_max_um", "F_min_um")}
        else:
            figs = _asme(per_direction, iso)
        out[sid] = {"standard": d["title"], **figs, "centre_removal": d["centre_removal"], "computes": d["computes"],
                    "differs_from_iso230_4": d["differs_from_iso230_4"], "assumption": d["assumption"]}
    return out


def _asme(per_direction: Mapping[int, tuple[np.ndarray, np.ndarray]], iso: Mapping[str, Any]
          ) -> dict[str, float | None]:
    out: dict[str, float | None] = {"circular_deviation_ccw_um": None, "circular_deviation_cw_um": None,
                                    "circular_deviation_b_um": None, "H_um": None,
                                    "F_max_um": iso.get("F_max_um"), "F_min_um": iso.get("F_min_um")}
    for d, key in ((1, "circular_deviation_ccw_um"), (-1, "circular_deviation_cw_um")):
        if d in per_direction and per_direction[d][0].size >= 4:
            out[key] = _range(min_zone_residual(*per_direction[d]))
    if len(per_direction) == 2:
        u = np.concatenate([per_direction[1][0], per_direction[-1][0]])
        r = np.concatenate([per_direction[1][1], per_direction[-1][1]])
        if u.size >= 4:
            rz = min_zone_residual(u, r)
            out["circular_deviation_b_um"] = _range(rz)
            n = per_direction[1][0].size
            h = _hysteresis((per_direction[1][0], rz[:n]), (per_direction[-1][0], rz[n:]))
            out["H_um"] = h if h is not None and math.isfinite(h) else None
    return out


#: Each standard's figures as the report and the verdict name them: (field, label).
FIGURES: dict[str, tuple[tuple[str, str], ...]] = {
    ISO: (("G_ccw_um", "G CCW"), ("G_cw_um", "G CW"), ("G_b_um", "G(b)"), ("H_um", "H"), ("F_max_um", "F max"),
          ("F_min_um", "F min")),
    "jis_b6190_4": (("G_ccw_um", "G CCW"), ("G_cw_um", "G CW"), ("G_b_um", "G(b)"), ("F_max_um", "F max"),
                    ("F_min_um", "F min")),
    "asme_b5_54": (("circular_deviation_ccw_um", "circular deviation CCW"),
                   ("circular_deviation_cw_um", "circular deviation CW"),
                   ("circular_deviation_b_um", "bidirectional circular deviation"), ("H_um", "circular hysteresis"),
                   ("F_max_um", "radial deviation max"), ("F_min_um", "radial deviation min")),
}


def lines(result: Mapping[str, Any]) -> list[str]:
    """The other standards' figures of a test result, a few readable lines (``ballbar analyze``)."""
    out = []
    for sid, body in (result.get("standards") or {}).items():
        labels = FIGURES.get(sid, ())
        figs = "  ".join(f"{label} {body[k]:.3f}" for k, label in labels if isinstance(body.get(k), int | float))
        out.append(f"{body.get('standard', sid)}: {figs} um")
        out.append(f"  ({body.get('differs_from_iso230_4')})")
    return out


__all__ = ["DEFINITIONS", "FIGURES", "ISO", "KNOWN", "check_names", "figures", "lines", "min_zone_residual"]
