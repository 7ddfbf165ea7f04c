"""How a number is shown: a value to what its standard error and its unit allow (analysis/README.md, "Numbers").

One rule for every place a person reads a figure (the live view, the report, the log, the alerts):

- the standard error is shown to 2 significant digits when its first digit is 1 or 2, else to 1
  (0.012 -> 0.012, 0.56 -> 0.6, 37 -> 40);
- the value to the same decimal place;
- never finer than the display resolution of its unit (:data:`RESOLUTION`: 0.1 um, 0.01 ms, 0.1 urad ...),
  the finer digits being below what any adjustment or acceptance can use; a standard error smaller than
  that resolution is shown as the resolution (an upper bound, never ``+- 0.00``);
- without a standard error, the unit's resolution (3 significant digits for a unit without one);
- a limit and its margin ("over by") at the value's decimal place;
- never ``-0.0``.

Pure: numbers in, text out.
"""

from __future__ import annotations

import math
import re
from typing import Any

#: The finest step worth showing, by result unit (ASCII units, as in the results).
RESOLUTION: dict[str, float] = {
    "um": 0.1, "urad": 0.1, "ppm": 0.1, "um/m": 0.1, "ms": 0.01, "deg": 0.1, "1/s": 0.01, "um/min": 0.01,
    "mm/min": 0.1, "mm": 0.001, "s": 0.001, "Hz": 0.01, "%": 0.1,
}


def resolution(unit: str) -> float | None:
    """The display resolution of ``unit`` (ASCII or as displayed: ``µm``); a rate ``X/day`` takes ``X``'s; None
    for a unit not listed."""
    u = str(unit or "").strip().replace("µ", "u")
    if u in RESOLUTION:
        return RESOLUTION[u]
    if u.endswith("/day"):
        return RESOLUTION.get(u[: -len("/day")])
    return None


def _finite(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def _res_decimals(res: float) -> int:
    return max(0, -math.floor(math.log10(res) + 1e-9))


def decimals(value: Any, stderr: Any = None, unit: str = "") -> int:
    """The decimal place of ``value`` shown with ``stderr`` in ``unit`` (negative: tens, hundreds ...)."""
    se = _finite(stderr)
    res = resolution(unit)
    floor = _res_decimals(res) if res is not None else None
    if se is not None and se > 0:
        e = math.floor(math.log10(se))
        first = int(se / 10.0**e + 1e-9)
        nd = -e + (1 if first <= 2 else 0)
        return min(nd, floor) if floor is not None else nd
    if floor is not None:
        return floor
    v = _finite(value)
    if v is None or v == 0:
        return 2
    return max(0, 2 - math.floor(math.log10(abs(v))))  # 3 significant digits


def fixed(value: float, nd: int, signed: bool = False) -> str:
    """``value`` rounded at decimal place ``nd`` (negative: to tens ...), without ``-0``."""
    r = round(value, nd) + 0.0  # + 0.0: -0.0 becomes 0.0
    if r == 0:
        r = 0.0
    text = f"{r:.{max(nd, 0)}f}"
    return ("+" + text if r > 0 else text) if signed else text


def _glyphs(unit: str, ascii_: bool) -> tuple[str, str]:
    if ascii_:
        return "+-", unit
    return "±", re.sub(r"\burad\b", "µrad", re.sub(r"\bum\b", "µm", unit))


def shown_stderr(stderr: float, nd: int) -> float:
    """The standard error as shown at ``nd``: rounded, but never below one step of that place."""
    return max(round(stderr, nd), 10.0**-nd)


def measured(value: Any, stderr: Any = None, unit: str = "", *, shown: Any = None, signed: bool = False,
             with_unit: bool = True, ascii: bool = False) -> str:
    """``3.03 ± 0.01 ms``: ``value`` with its ``stderr`` by the module's rule (``shown``: the uncertainty the line
    quotes, such as k standard errors, at the same place; default the standard error); ``–`` without a value."""
    v = _finite(value)
    pm, u = _glyphs(str(unit or ""), ascii)
    if v is None:
        return "-" if ascii else "–"
    nd = decimals(v, stderr, unit)
    text = fixed(v, nd, signed)
    q = _finite(shown) if shown is not None else _finite(stderr)
    if q is not None and q > 0:
        text += f" {pm} {fixed(shown_stderr(q, nd), nd)}"
    return f"{text} {u}" if with_unit and u else text


def limit_texts(value: Any, stderr: Any, limit: Any, margin: Any, unit: str = "") -> tuple[str, str]:
    """A limit and the margin to it (``over by`` when negative) as numbers at the value's decimal place,
    never finer than the unit's resolution and never coarser than whole units: ``("2.00", "1.03")``."""
    nd = max(decimals(value, stderr, unit), 0)
    lim, m = _finite(limit), _finite(margin)
    return ("–" if lim is None else fixed(lim, nd)), ("–" if m is None else fixed(abs(m), nd))


__all__ = ["RESOLUTION", "decimals", "fixed", "limit_texts", "measured", "resolution", "shown_stderr"]
