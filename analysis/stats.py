"""The few distribution functions the fit needs, as ``scipy.stats`` spells them, from ``scipy.special``.

``scipy.stats`` takes about half a second to import, more than the rest of the
daemon's start-up; the p-values need only the F and chi-squared tails, which
``scipy.stats`` itself computes with these ``scipy.special`` functions
(``fdtrc``, ``chdtrc``, ``chdtri``).  The rules of ``scipy.stats`` around them are
kept: invalid degrees of freedom or NaN give NaN, an argument at or below the
support's start gives a tail of 1, ``+inf`` a tail of 0, and ``isf`` of 0 and 1
the support's ends; the values are the same floats (``tests/test_stats.py``).
Scalars only.
"""

from __future__ import annotations

import math

from scipy import special


class _F:
    """``scipy.stats.f``: Fisher's F distribution with ``dfn``, ``dfd`` degrees of freedom."""

    @staticmethod
    def sf(x: float, dfn: float, dfd: float) -> float:
        if not (dfn > 0 and dfd > 0) or math.isnan(x):
            return math.nan
        if x <= 0:
            return 1.0
        if x == math.inf:
            return 0.0
        return float(special.fdtrc(dfn, dfd, x))


class _Chi2:
    """``scipy.stats.chi2``: the chi-squared distribution with ``df`` degrees of freedom."""

    @staticmethod
    def sf(x: float, df: float) -> float:
        if not df > 0 or math.isnan(x):
            return math.nan
        if x <= 0:
            return 1.0
        if x == math.inf:
            return 0.0
        return float(special.chdtrc(df, x))

    @staticmethod
    def isf(q: float, df: float) -> float:
        if not (df > 0 and 0 <= q <= 1):
            return math.nan
        if q == 0:
            return math.inf
        if q == 1:
            return 0.0
        return float(special.chdtri(df, q))


f = _F()
chi2 = _Chi2()

__all__ = ["chi2", "f"]
