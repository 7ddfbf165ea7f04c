"""The fit of analysis/README.md ("The fit"): weighted residual method, extra sum of squares.

The weighted residual (Galerkin) equations of Suh & Lee (eq. 11-13) with the
masks as weights are the normal equations of least squares.  They are solved
through an orthogonal factor, never by forming and eliminating the normal
matrix: each block of samples is folded into the upper-triangular factor ``R``
of the augmented design ``[A | y]`` (a tall-skinny QR).  The factor of a test is
the factor of its circles stacked and re-factored, so a new circle costs no
pass over old samples, and the fit of any subset of the columns (for the
ranking) is a small problem on ``R`` alone::

    ||A_S x - y||^2 = ||R[:, S] x - R[:, -1]||^2

Uncertainty.  ``sigma^2 = SSE / (n - p)`` assumes independent samples.  Ball-bar
residuals are correlated (the model misfit and low-frequency noise are smooth
in angle), so the covariance is inflated by ``kappa = (1 + rho) / (1 - rho)``
with ``rho`` the residual's lag-1 autocorrelation (the AR(1) variance
inflation, i.e. an effective sample count ``n / kappa``), capped at 400.  The
same ``kappa`` enters the F-tests.  This is stated in every result.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy import linalg as sla

from . import stats
from .patterns import Pattern

if TYPE_CHECKING:
    from ballbar.protocol.messages.results import Parameter

KAPPA_MAX = 400.0


class Factor:
    """Upper-triangular factor of ``[A | y]``, grown block by block.

    Also keeps ``n`` and the sums needed for the residual's lag-1
    autocorrelation, which each block supplies with its own residual.
    """

    def __init__(self, p: int) -> None:
        self.p = p
        self.R = np.zeros((0, p + 1))
        self.n = 0

    def add(self, A: np.ndarray, y: np.ndarray) -> None:
        if y.size == 0:
            return
        # Column-major, as LAPACK takes it: a row-major block is copied first and costs 2 to 4 times as much.
        block = np.empty((self.R.shape[0] + y.size, self.p + 1), order="F")
        block[: self.R.shape[0]] = self.R
        block[self.R.shape[0] :, : self.p] = A
        block[self.R.shape[0] :, self.p] = y
        self.R = _qr_r(block)
        self.n += int(y.size)

    def merged(self, other: Factor) -> Factor:
        out = Factor(self.p)
        out.R = _qr_r(np.vstack([self.R, other.R])) if self.n and other.n else (self.R if self.n else other.R)
        out.n = self.n + other.n
        return out

    @property
    def rows(self) -> np.ndarray:
        """``R`` padded to ``p + 1`` rows (zero rows where fewer samples than columns)."""
        if self.R.shape[0] >= self.p + 1:
            return self.R[: self.p + 1]
        out = np.zeros((self.p + 1, self.p + 1))
        out[: self.R.shape[0]] = self.R
        return out


def _qr_r(M: np.ndarray) -> np.ndarray:
    r = sla.qr(M, mode="r", overwrite_a=True, check_finite=False)[0]
    k = min(M.shape)
    return np.asarray(r[:k])


def sse_subset(R: np.ndarray, cols: Sequence[int]) -> float:
    """Residual sum of squares of the least-squares fit on columns ``cols`` only."""
    y = R[:, -1]
    if len(cols) == 0:
        return float(y @ y)
    A = R[:, list(cols)]
    scale = np.linalg.norm(A, axis=0)
    scale[scale == 0] = 1.0
    x, *_ = np.linalg.lstsq(A / scale, y, rcond=None)
    r = y - (A / scale) @ x
    return float(r @ r)


@dataclass
class ParameterResult:
    field: str
    unit: str
    value: float | None
    stderr: float | None
    p_value: float | None = None
    share_pct: float | None = None
    significant: bool = False
    identifiable: bool = True
    reason: str = ""  # why it was not fitted
    significance_reason: str = ""  # why it is not significant although its F-test passed the level

    def to_dict(self) -> Parameter:
        d: Parameter = {
            "value": _num(self.value),
            "stderr": _num(self.stderr),
            "unit": self.unit,
            "p_value": _num(self.p_value),
            "share_pct": _num(self.share_pct),
            "significant": bool(self.significant),
            "identifiable": bool(self.identifiable),
        }
        if self.reason:
            d["reason"] = self.reason
        if self.significance_reason:
            d["significance_reason"] = self.significance_reason
        return d


def _num(v: float | None) -> float | None:
    if v is None or not math.isfinite(v):
        return None
    return float(v)


@dataclass
class TermResult:
    """One pattern's test: extra sum of squares, F, p-value, share."""

    pattern: str
    ssr: float
    F: float
    p_value: float
    share_pct: float
    significant: bool
    effect_um: float  # largest |contribution| over the data
    reason: str = ""  # why a pattern whose F-test passed the level is still not significant


@dataclass
class FitResult:
    patterns: list[Pattern]
    used: list[bool]  # per pattern: in the final fit
    reasons: dict[str, str]
    x: np.ndarray  # all columns; NaN where left out
    cov: np.ndarray  # all columns; NaN where left out
    sse: float
    n: int
    p: int
    kappa: float
    rho: float
    terms: dict[str, TermResult] = field(default_factory=dict)
    condition: float = float("nan")

    @property
    def dof(self) -> int:
        return max(self.n - self.p, 1)

    @property
    def sigma(self) -> float:
        return math.sqrt(self.sse / self.dof)

    def column_slices(self) -> dict[str, slice]:
        out, j = {}, 0
        for pat in self.patterns:
            out[pat.name] = slice(j, j + pat.q)
            j += pat.q
        return out


def solve(
    factor: Factor,
    patterns: Sequence[Pattern],
    *,
    rho: float = 0.0,
    significance: float = 0.05,
    vif_limit: float = 1e4,
    min_support: float = 2.0,
    min_effect_um: float = 0.05,
    effect_scale: np.ndarray | None = None,
    exclude: dict[str, str] | None = None,
    family_dof: dict[str, int] | None = None,
    family_lr: dict[str, float] | None = None,
    timing_cov: np.ndarray | None = None,
    rank: bool = True,
) -> FitResult:
    """Fit ``patterns`` from ``factor``; rank them; say which cannot be identified.

    ``min_support``: a column whose sum of squares is below this (fewer than
    about two samples' worth of signal) has no data to stand on.
    ``effect_scale``: per column, the largest |column value| over the data, to
    turn a parameter into its largest radial contribution (for ``min_effect_um``).
    ``exclude``: patterns left out beforehand, with the reason.
    ``family_dof``: per family (:func:`family`), parameters its shape was
    searched for (the reversal spikes' width), counted in its joint test.
    ``family_lr``: per family, its likelihood ratio (nats) against the model
    without it at that model's own best search (the spike-free model at its
    own timing): its joint test is also the chi-square test of that ratio,
    and the larger p of the two is the family's.
    ``timing_cov``: the parameters' covariance through a timing the same
    data fixed (the arc start's lag and the feed-in's extra wait, searched
    for; :mod:`.engine`), added to the fit's own: the standard errors count
    it, and each test's statistic keeps the share of its Wald statistic
    that is left once it is counted.
    ``rank``: False for the values and covariance alone (no terms: an
    intermediate fit whose ranking nothing reads).
    """
    patterns = list(patterns)
    R = factor.rows
    p_all = R.shape[1] - 1
    slices: list[slice] = []
    j = 0
    for pat in patterns:
        slices.append(slice(j, j + pat.q))
        j += pat.q
    assert j == p_all, "pattern columns and factor disagree"
    norms = np.linalg.norm(R[:, :p_all], axis=0)
    reasons: dict[str, str] = dict(exclude or {})
    used = [pat.name not in reasons for pat in patterns]
    # Support: the column's energy in units of its own peak, about "samples where it acts";
    # without the peaks only an all-zero column lacks support.
    if effect_scale is None:
        support = np.where(norms > 0, np.inf, 0.0)
    else:
        safe = np.where(effect_scale > 0, effect_scale, 1.0)
        support = np.where(effect_scale > 0, (norms / safe) ** 2, 0.0)
    for i, pat in enumerate(patterns):
        if used[i] and np.any(support[slices[i]] < min_support):
            used[i] = False
            reasons[pat.name] = _no_support_reason(pat)
    # Leave out, lowest priority first, what the data cannot separate.
    condition = float("nan")
    while True:
        cols = _cols(slices, used)
        if not cols:
            break
        An = R[:, cols] / norms[cols]
        s = np.linalg.svd(An, compute_uv=False)
        condition = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
        vif = _vif(An)
        worst = np.nonzero(~(vif <= vif_limit))[0]
        if worst.size == 0:
            break
        col_owner = [i for i, pat in enumerate(patterns) if used[i] for _ in range(pat.q)]
        drop = max(col_owner[k] for k in worst)
        k_drop = int(next(k for k in worst if col_owner[k] == drop))
        partner = _most_collinear(An, k_drop, col_owner, patterns)
        used[drop] = False
        v = vif[k_drop]
        vtxt = "inf" if not math.isfinite(v) else f"{v:.3g}"
        reasons[patterns[drop].name] = (
            f"cannot be separated from {partner} in this data (variance inflation {vtxt} > {vif_limit:g})"
        )
    cols = _cols(slices, used)
    x = np.full(p_all, np.nan)
    cov = np.full((p_all, p_all), np.nan)
    kappa = min(max((1.0 + rho) / (1.0 - rho), 1.0), KAPPA_MAX) if rho < 1 else KAPPA_MAX
    n, p = factor.n, len(cols)
    sse_full = sse_subset(R, cols)
    dof = max(n - p, 1)
    if cols:
        A = R[:, cols]
        Q, Rs = np.linalg.qr(A / norms[cols])
        xs = sla.solve_triangular(Rs, Q.T @ R[:, -1]) / norms[cols]
        Rinv = sla.solve_triangular(Rs, np.eye(len(cols)))
        cs = (Rinv @ Rinv.T) / np.outer(norms[cols], norms[cols]) * (sse_full / dof) * kappa
        x[cols] = xs
        cov[np.ix_(cols, cols)] = cs
    # (A^T A)^-1 of the columns used, by column: the extra sum of squares of leaving out any of them is
    # x_S^T [(A^T A)^-1]_SS^-1 x_S, exactly (the nested least-squares fit, without fitting it)
    gram_inv = np.zeros((p_all, p_all))
    if cols:
        gram_inv[np.ix_(cols, cols)] = (Rinv @ Rinv.T) / np.outer(norms[cols], norms[cols])
    fit_cov = cov.copy()
    if timing_cov is not None and cols:
        cov[np.ix_(cols, cols)] += timing_cov[np.ix_(cols, cols)]
    result = FitResult(patterns, used, reasons, x, cov, sse_full, n, p, kappa, rho, condition=condition)
    if not rank:
        return result

    def counted(own: Sequence[int]) -> float:
        """The share of the Wald statistic of columns ``own`` left once the timing's covariance is counted."""
        if timing_cov is None:
            return 1.0
        idx = np.ix_(own, own)
        v = x[own]
        alone = _quadratic(fit_cov[idx], v)
        return _quadratic(cov[idx], v) / alone if alone > 0 else 1.0

    def extra(own: Sequence[int]) -> float:
        """SSE(all but ``own``) - SSE(all): the extra sum of squares of those columns."""
        return max(_quadratic(gram_inv[np.ix_(own, own)], x[list(own)]), 0.0)

    # Extra sum of squares (Suh & Lee section 4.2): drop each term in turn.
    ssr: dict[str, float] = {}
    for i, pat in enumerate(patterns):
        if not used[i] or pat.kind == "loop":  # a loop's property fitted beside the patterns, not a finding
            continue
        ssr[pat.name] = extra(list(range(slices[i].start, slices[i].stop)))
    total = sum(ssr.values())
    mse = sse_full / dof * kappa
    for i, pat in enumerate(patterns):
        if pat.name not in ssr:
            continue
        sl = slices[i]
        F = (ssr[pat.name] / pat.q) / mse * counted(list(range(sl.start, sl.stop))) if mse > 0 else math.inf
        pv = float(stats.f.sf(F, pat.q, dof)) if math.isfinite(F) else 0.0
        scale = effect_scale[sl] if effect_scale is not None else np.ones(pat.q)
        effect = float(np.sum(np.abs(x[sl]) * scale))
        share = 100.0 * ssr[pat.name] / total if total > 0 else 0.0
        result.terms[pat.name] = TermResult(pat.name, ssr[pat.name], F, pv, share, False, effect)
    # Each family of several patterns is also tested as a whole, with the dof its shape's search cost.
    members: dict[str, list[int]] = {}
    for i, pat in enumerate(patterns):
        if used[i] and pat.kind != "loop":
            members.setdefault(family(pat.name), []).append(i)
    gates: dict[str, tuple[float, int, str]] = {}
    for fam, idx in members.items():
        if len(idx) < 2:
            continue
        own = {c for i in idx for c in range(slices[i].start, slices[i].stop)}
        q = len(own) + (family_dof or {}).get(fam, 0)
        fam_ssr = extra(sorted(own))
        F = (fam_ssr / q) / mse * counted(sorted(own)) if mse > 0 else math.inf
        p_gate = float(stats.f.sf(F, q, dof)) if math.isfinite(F) else 0.0
        how = f"joint F-test over {q} parameters"
        lr = (family_lr or {}).get(fam, math.nan)
        if math.isfinite(lr) and float(stats.chi2.sf(2.0 * lr, q)) > p_gate:
            p_gate = float(stats.chi2.sf(2.0 * lr, q))
            how = (f"likelihood ratio over {q} parameters against the model without them at its own best "
                   f"timing, {lr:.3g} nats")
        gates[fam] = (p_gate, q, how)
    setup = frozenset(pat.name for i, pat in enumerate(patterns) if used[i] and pat.kind == "setup")
    _judge(result.terms, significance, min_effect_um, gates, setup)
    return result


def _quadratic(M: np.ndarray, v: np.ndarray) -> float:
    """``v^T M^-1 v`` (least squares where ``M`` is singular)."""
    try:
        return float(v @ np.linalg.solve(M, v))
    except np.linalg.LinAlgError:
        return float(v @ np.linalg.lstsq(M, v, rcond=None)[0])


def family(name: str) -> str:
    """The family a pattern is tested in: all reversal spikes; the X and Y of one kind; else itself."""
    if name.startswith("reversal_spike_"):
        return "reversal_spike"
    if name.endswith(("_x", "_y")):
        return name[:-2]
    return name


def significance_rule(level: float, min_effect_um: float) -> str:
    """The rule :func:`solve` applies, in words (it goes into every result)."""
    return (
        "the machine's error patterns are tested in families (the reversal spikes; the X and Y patterns of one "
        "kind; each other pattern alone), each family by its joint extra-sum-of-squares F-test (counting the "
        "spikes' fitted width as a parameter; for the spikes also against the spike-free model at its own best "
        "timing, the larger p counting); the families pass Holm's step-down correction at "
        f"{level:g} together, so that a machine with none of them shows any with a chance of at most {level:g}; "
        "within a family that passes, a pattern's own p passes Holm's correction among its members; and a "
        f"pattern's largest radial effect over the data is at least {min_effect_um:g} um. The set-up's terms "
        f"(centre, radius) are tested alone at {level:g}"
    )


def _holm(ps: Sequence[float], level: float) -> list[tuple[bool, float]]:
    """Holm's step-down test of ``ps`` at ``level``: per p, whether it passes, and the threshold it was held to
    (after the first failure, that failure's: every later p is at least as large)."""
    out: list[tuple[bool, float]] = [(False, level)] * len(ps)
    stop = 0.0
    m = len(ps)
    for k, i in enumerate(sorted(range(m), key=lambda i: ps[i])):
        threshold = stop or level / (m - k)
        if not stop and not ps[i] < threshold:
            stop = threshold
        out[i] = (not stop, threshold)
    return out


def _judge(
    terms: dict[str, TermResult],
    level: float,
    min_effect_um: float,
    gates: dict[str, tuple[float, int, str]],
    setup: frozenset[str] = frozenset(),
) -> None:
    """Apply :func:`significance_rule`; a term that passes the F-test but fails a further rule says which."""
    groups: dict[str, list[TermResult]] = {}
    for t in terms.values():
        groups.setdefault(t.pattern if t.pattern in setup else family(t.pattern), []).append(t)
    machine = [f for f in groups if groups[f][0].pattern not in setup]
    fam_p = {f: gates[f][0] if f in gates else min(t.p_value for t in groups[f]) for f in groups}
    fam_pass = dict(zip(machine, _holm([fam_p[f] for f in machine], level), strict=True))
    for f in groups:
        fam_pass.setdefault(f, (fam_p[f] < level, level))
    for fam, members in groups.items():
        m = len(members)
        words = fam.replace("_", " ")
        passed, fam_threshold = fam_pass[fam]
        inner = _holm([t.p_value for t in members], level)
        for t, (own_passes, threshold) in zip(members, inner, strict=True):
            if passed and own_passes and t.effect_um >= min_effect_um:
                t.significant = True
            elif not t.p_value < level:
                continue
            elif passed and own_passes:
                t.reason = (
                    f"statistically significant (p = {t.p_value:.2g}) but its largest radial effect, "
                    f"{t.effect_um:.3g} um, is below the minimum effect of {min_effect_um:g} um"
                )
            elif not passed and fam not in gates:
                t.reason = (
                    f"p = {t.p_value:.2g} is below {level:g} but not below {fam_threshold:.2g}, Holm's threshold "
                    f"for it among the {len(machine)} families of machine errors tested"
                )
            elif not passed:
                together = f"the {m} {words} patterns together ({gates[fam][2]})"
                t.reason = (
                    f"p = {t.p_value:.2g} is below {level:g}, but {together} give p = {fam_p[fam]:.2g}, "
                    + (f"not below {fam_threshold:.2g}, Holm's threshold for the family among the {len(machine)} "
                       "families of machine errors tested" if fam_p[fam] < level else f"not below {level:g}")
                )
            else:
                t.reason = (
                    f"p = {t.p_value:.2g} is below {level:g} but not below {threshold:.2g}, Holm's threshold for it "
                    f"among the {m} {words} patterns tested together"
                )


def _cols(slices: Sequence[slice], used: Sequence[bool]) -> list[int]:
    return [c for sl, u in zip(slices, used, strict=True) if u for c in range(sl.start, sl.stop)]


def _vif(An: np.ndarray) -> np.ndarray:
    """Variance inflation of each (unit-norm) column: diag((A^T A)^-1)."""
    _, s, vt = np.linalg.svd(An, full_matrices=False)
    with np.errstate(divide="ignore"):
        inv = np.where(s > s[0] * 1e-13, 1.0 / s**2, np.inf)
    with np.errstate(invalid="ignore"):
        terms = np.where(vt**2 > 0, vt**2 * inv[:, None], 0.0)
    return np.asarray(np.sum(terms, axis=0))


def _most_collinear(An: np.ndarray, k: int, owner: Sequence[int], patterns: Sequence[Pattern]) -> str:
    """Name the other pattern(s) that best reproduce column ``k``."""
    others = [j for j in range(An.shape[1]) if owner[j] != owner[k]]
    if not others:
        return "the rest of the model"
    coef, *_ = np.linalg.lstsq(An[:, others], An[:, k], rcond=None)
    weight: dict[int, float] = {}
    for c, j in zip(coef, others, strict=True):
        weight[owner[j]] = weight.get(owner[j], 0.0) + abs(float(c))
    top = sorted(weight, key=lambda i: -weight[i])[:2]
    return " and ".join(patterns[i].name for i in top)


def _no_support_reason(pat: Pattern) -> str:
    if pat.reversal is not None:
        axis, at, d = pat.reversal
        return (
            f"the {'CCW' if d > 0 else 'CW'} data arc holds less than two samples' worth of the spike after the "
            f"{axis.upper()} reversal at {at:g} deg: too few to size it"
        )
    return "the data holds no samples where this pattern acts"
