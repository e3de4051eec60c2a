"""The gate's chi-square quantiles, in plain IEEE arithmetic.

A gated loop closure is rejected when its normalised innovation squared exceeds the
chi-square quantile ``gate`` for its degrees of freedom. The threshold decides the map's
state, so it must have the same bits on every machine: it is computed here with +, -, *, /
and sqrt only (no libm exp, lgamma or erf, whose last bits differ between C libraries), by
bisection on the regularised lower incomplete gamma function's power series.
"""

from __future__ import annotations

import math
from functools import lru_cache

_SQRT_PI = 1.7724538509055159


def _exp_neg(x: float) -> float:
    """``exp(-x)`` for ``x >= 0`` by halving and a Taylor series (deterministic)."""
    k = 0
    while x > 0.5:
        x *= 0.5
        k += 1
    term, total = 1.0, 1.0
    for i in range(1, 30):
        term = term * (-x) / i
        total += term
    for _ in range(k):
        total *= total
    return total


def _gamma_half(k: int) -> float:
    """``Γ(k/2 + 1)`` for a positive integer k."""
    if k % 2 == 0:
        g = 1.0
        for i in range(1, k // 2 + 1):
            g *= i
        return g
    g = _SQRT_PI / 2.0  # Γ(3/2)
    a = 1.5
    while a < k / 2 + 1 - 1e-9:
        g *= a
        a += 1.0
    return g


def chi2_cdf(x: float, dof: int) -> float:
    """P(χ²_dof ≤ x): ``P(a, y)`` with ``a = dof/2``, ``y = x/2``, by its power series
    ``y^a e^-y / Γ(a+1) Σ_n y^n / ((a+1)…(a+n))``."""
    if x <= 0.0:
        return 0.0
    a, y = dof / 2.0, x / 2.0
    term, total = 1.0, 1.0
    for i in range(1, 2000):
        term = term * y / (a + i)
        total += term
        if term < total * 1e-17:
            break
    y_a = 1.0
    for _ in range(dof // 2):  # y ** (dof // 2) by multiplication: no libm pow
        y_a *= y
    if dof % 2:
        y_a *= math.sqrt(y)
    return min(1.0, y_a * _exp_neg(y) / _gamma_half(dof) * total)


@lru_cache(maxsize=256)
def chi2_quantile(p: float, dof: int) -> float:
    """The ``p`` quantile of χ² with ``dof`` degrees of freedom (bisection, 200 steps)."""
    if not 0.0 < p < 1.0 or dof < 1:
        raise ValueError("need 0 < p < 1 and dof >= 1")
    lo, hi = 0.0, 1.0
    while chi2_cdf(hi, dof) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_cdf(mid, dof) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 0.0:
            break
    return hi


__all__ = ["chi2_cdf", "chi2_quantile"]
