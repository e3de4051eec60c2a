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

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel

Array = npt.NDArray[np.float64]

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


def _rows(x: Array) -> Array:
    """``(N, 7)`` samples (already checked: a query's answer, a decoded request) as kernel
    rows ``(7, N)``."""
    return np.ascontiguousarray(np.asarray(x, dtype=np.float64).T)


def _identity(n: int) -> Array:
    e = np.zeros((7, n))
    e[3] = 1.0
    return e


def cycle_samples(*ats: Array) -> Array:
    """``ats[0] ⊕ ats[1] ⊕ ...`` sample by sample (``(N, 7)`` each; the kernel's fixed order)."""
    acc = _rows(ats[0])
    for x in ats[1:]:
        acc = kernel.compound(acc, _rows(x))
    return np.ascontiguousarray(acc.T)


def inverse_samples(x: Array) -> Array:
    """Each sample's inverse transform (kernel)."""
    return np.ascontiguousarray(kernel.invert(_rows(x)).T)


def nis_from_identity(x: Array) -> tuple[float, int]:
    """``(NIS, dof)`` of the samples' mean against the identity, with the samples' own
    covariance over its live dimensions, in the gate's tangent chart: the gate's own
    computation (kernel, fixed order, Jacobi eigenvalues), with an exact prediction."""
    rows = _rows(x)
    ident = _identity(rows.shape[1])
    rc, _, _, info = kernel.analysis(ident, ident, rows, False, 0, 0)
    if rc != kernel.OK:
        raise ValueError("non-finite analysis of a cycle")
    return float(info[1]), int(info[2])


def chart_variance(x: Array) -> float:
    """Total variance (trace of the covariance) of the samples in the gate's tangent chart
    around their mean (kernel, fixed order)."""
    rows = _rows(x)
    ident = _identity(rows.shape[1])
    _, yc, _, info = kernel.analysis(ident, rows, ident, False, 0, 0)
    p = yc.shape[0]
    total = 0.0
    for k in range(p):  # p <= 7 values, in a fixed order
        total += float(info[3 + k])
    return total


def median(values: list[float]) -> float:
    """The median of a non-empty list (sorted; the mean of the middle two for an even
    count): the same bits for the same values on every machine."""
    u, k = sorted(values), len(values)
    return u[k // 2] if k % 2 else 0.5 * (u[k // 2 - 1] + u[k // 2])


def lower_quantile(values: list[float], q: float) -> float:
    """The ``q`` quantile of a non-empty list without interpolation: the sorted values' element
    ``floor(q (k - 1))`` (the median for q = 0.5 and an odd count)."""
    u = sorted(values)
    return u[int(q * (len(u) - 1))]


__all__ = ["median", "lower_quantile",
           "chi2_cdf", "chi2_quantile", "cycle_samples", "inverse_samples",
           "nis_from_identity", "chart_variance"]
