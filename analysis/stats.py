"""The two distribution tails the fit's tests need, as ``scipy.stats`` spells them: ``f.sf`` and ``chi2.sf``.

Why not ``scipy``: ``scipy.stats`` takes about half a second to import and
``scipy.special`` some 25 to 40 ms (it rewrites the docstrings of ninety
functions as it loads), more than the analysis of a 15.625 Hz test; ``ballbar
analyze`` pays every import at every run.  The p-values need only the
regularised incomplete beta (F) and gamma (chi-squared) functions, computed
here by their continued fractions and series (Numerical Recipes, 3rd ed.,
6.2 and 6.4: modified Lentz), with Stirling's series where the degrees of
freedom are large: to a relative 1e-10 or better, against closed forms and
arbitrary-precision values, over the degrees of freedom a test has (1 to some
10^6; ``tests/test_stats.py``).  The rules of ``scipy.stats`` around
them are kept: invalid degrees of freedom or NaN give NaN, an argument at or
below the support's start gives a tail of 1, ``+inf`` a tail of 0.  Scalars
only.

A p-value is compared with a level of 0.05 over a few tests and printed to
two digits: 1e-10 is far below anything that reads it.
"""

from __future__ import annotations

import math

_EPS = 1e-16  # a continued fraction or series stops once a step changes it by less than this
_TINY = 1e-300  # Lentz's guard against a zero denominator
_MAX_STEPS = 1_000_000  # the fractions converge in O(sqrt(df)) steps at worst (df up to ~10^6)


def _beta_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of the regularised incomplete beta ``I_x(a, b)`` (without its prefactor);
    converges fast for ``x < (a + 1) / (a + b + 2)``."""
    qab, qap, qam = a + b, a + 1.0, a - 1.0
    c = 1.0
    d = 1.0 - qab * x / qap
    d = 1.0 / (d if abs(d) > _TINY else _TINY)
    h = d
    for m in range(1, _MAX_STEPS):
        m2 = 2 * m
        aa = m * (b - m) * x / ((qam + m2) * (a + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = 1.0 + aa / c
        c = c if abs(c) > _TINY else _TINY
        h *= d * c
        aa = -(a + m) * (qab + m) * x / ((a + m2) * (qap + m2))
        d = 1.0 + aa * d
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = 1.0 + aa / c
        c = c if abs(c) > _TINY else _TINY
        step = d * c
        h *= step
        if abs(step - 1.0) < _EPS:
            break
    return h


_STIRLING_FROM = 30.0  # above this, lgamma(z) = (z - 1/2) ln z - z + ln(2 pi)/2 + _stirling_tail(z) to 1e-16


def _stirling_tail(z: float) -> float:
    """The remainder of Stirling's series for ``lgamma(z)`` (its first four terms: below 1e-16 for z >= 30)."""
    z2 = z * z
    return (1.0 / 12.0 - (1.0 / 360.0 - (1.0 / 1260.0 - 1.0 / (1680.0 * z2)) / z2) / z2) / z


def _beta_upper(a: float, b: float, x: float, y: float) -> float:
    """``1 - I_x(a, b)`` = ``I_y(b, a)``, with ``y = 1 - x`` given exactly by the caller (no cancellation)."""
    # log of x^a y^b / B(a, b): the prefactor both branches share
    log_x = math.log1p(-y) if y < 0.5 else math.log(x)
    log_y = math.log1p(-x) if x < 0.5 else math.log(y)
    small, large = min(a, b), max(a, b)
    e = x * b - y * a  # x (a + b) - a: how far x lies from the distribution's mean, a / (a + b), times a + b
    if small >= _STIRLING_FROM and abs(e) < 0.5 * small:
        # both large, near the mean: Stirling's series for all three lgammas, the logs taken about the mean
        log_front = (a * math.log1p(e / a) + b * math.log1p(-e / b) + 0.5 * math.log(a * b / (a + b))
                     - 0.5 * math.log(2.0 * math.pi) - _stirling_tail(a) - _stirling_tail(b) + _stirling_tail(a + b))
    elif large < _STIRLING_FROM:
        log_front = math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * log_x + b * log_y
    else:  # lgamma(small + large) - lgamma(large) by Stirling's series, without the difference of two large logs
        rise = (large - 0.5) * math.log1p(small / large) + small * math.log(small + large) - small
        rise += _stirling_tail(small + large) - _stirling_tail(large)
        log_front = rise - math.lgamma(small) + a * log_x + b * log_y
    if y < (b + 1.0) / (a + b + 2.0):  # the fraction converges for I_y(b, a) directly: the small tail
        return math.exp(log_front) * _beta_fraction(b, a, y) / b
    return 1.0 - math.exp(log_front) * _beta_fraction(a, b, x) / a


def _gamma_upper(a: float, x: float) -> float:
    """The regularised upper incomplete gamma ``Q(a, x)``: the series of ``P`` below ``a + 1``, else the
    continued fraction of ``Q``."""
    log_front = a * math.log(x) - x - math.lgamma(a)
    if x < a + 1.0:
        term = total = 1.0 / a
        ap = a
        for _ in range(_MAX_STEPS):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * _EPS:
                break
        return 1.0 - total * math.exp(log_front)
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, _MAX_STEPS):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = 1.0 / (d if abs(d) > _TINY else _TINY)
        c = b + an / c
        c = c if abs(c) > _TINY else _TINY
        step = d * c
        h *= step
        if abs(step - 1.0) < _EPS:
            break
    return math.exp(log_front) * h


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
        # P(F > x) = I_w(dfd/2, dfn/2), w = dfd / (dfd + dfn x); both w and 1 - w formed without a difference
        den = dfd + dfn * x
        if den == math.inf:  # dfn x beyond the floats: the tail is far below them
            return 0.0
        w, v = dfd / den, dfn * x / den
        if w == 0.0:
            return 0.0
        if v == 0.0:
            return 1.0
        return min(max(_beta_upper(dfn / 2.0, dfd / 2.0, v, w), 0.0), 1.0)


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
        return min(max(_gamma_upper(df / 2.0, x / 2.0), 0.0), 1.0)


f = _F()
chi2 = _Chi2()

__all__ = ["chi2", "f"]
