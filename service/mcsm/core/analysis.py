"""Analysis rules of the joint update: per-sample weights ``w_i`` with ``Δx_i = C_xy w_i``.

Every rule sees the centred predicted observations ``yc`` ``(N, p)``, their mean ``y_mean``
``(p,)`` and the observation's samples ``z`` ``(N, p)``, and returns ``w`` ``(N, p)``. The
state moves by one affine map per update, so sample order and O(M·N) cost are preserved, and
a rule can be swapped without touching the map. With ``S = C_yy + R`` (``R = cov(z)``):

* ``enkf``: perturbed observations, ``w_i = S⁺ (z_i − y_i)``: the plain joint update. Over
  thousands of updates it collapses at fixed N (docs/design.md, "Consistency at fixed N").
* ``denkf``: deterministic EnKF (Sakov & Oke 2008): the mean moves with the full gain using the
  observation's mean, the anomalies with half the gain: ``w_i = S⁺ (z̄ − ȳ) − ½ S⁺ yc_i``.
* ``ensrf``: ensemble square-root filter (Whitaker & Hamill 2002), mean as in ``denkf``,
  anomalies with ``K̃ = C_xy S^-½ (S^½ + R^½)⁻¹``, which yields exactly ``(I − KH) P``.

The deterministic rules use the observation only through its sample mean and covariance: a
non-Gaussian observation sample set is reduced to two moments. All products use the scaled,
truncated pseudo-inverses of :mod:`mcsm.core.at` (dead dimensions and rank deficiency are normal).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from mcsm.core.at import sample_cov, scaled_eigh, sym_sqrt

Array = npt.NDArray[np.float64]
Rule = Callable[[Array, Array, Array], Array]


def _moments(yc: Array, z: Array) -> tuple[Array, Array, Array]:
    n = yc.shape[0]
    c_yy = yc.T @ yc / (n - 1)
    r = sample_cov(z)
    return c_yy, r, c_yy + r


def _pinv_parts(s: Array) -> tuple[Array, Array, Array, Array]:
    """Scale vector d, eigenvectors v, and the kept eigenvalues' inverse and inverse root."""
    d, lam, v = scaled_eigh(s)
    live = lam > 0.0
    safe = np.where(live, lam, 1.0)
    return d, v, np.where(live, 1.0 / safe, 0.0), np.where(live, 1.0 / np.sqrt(safe), 0.0)


def enkf(yc: Array, y_mean: Array, z: Array) -> Array:
    """Perturbed-observation weights ``S⁺ (z_i − y_i)``."""
    _, _, s = _moments(yc, z)
    d, v, inv, _ = _pinv_parts(s)
    s_pinv = ((v * inv) @ v.T) * d[:, None] * d[None, :]
    return (z - (yc + y_mean)) @ s_pinv


def denkf(yc: Array, y_mean: Array, z: Array) -> Array:
    """Deterministic EnKF weights ``S⁺ (z̄ − ȳ) − ½ S⁺ yc_i``."""
    _, _, s = _moments(yc, z)
    d, v, inv, _ = _pinv_parts(s)
    s_pinv = ((v * inv) @ v.T) * d[:, None] * d[None, :]
    out: Array = (z.mean(axis=0) - y_mean)[None, :] @ s_pinv - 0.5 * yc @ s_pinv
    return out


def ensrf(yc: Array, y_mean: Array, z: Array) -> Array:
    """Square-root weights ``S⁺ (z̄ − ȳ) − S^-½ (S^½ + R^½)⁺ yc_i`` (scaled coordinates)."""
    _, r, s = _moments(yc, z)
    d, v, inv, inv_sqrt = _pinv_parts(s)
    s_pinv = ((v * inv) @ v.T) * d[:, None] * d[None, :]
    # in the scaled coordinates ỹ = D y: S̃ = V Λ Vᵀ, R̃ = D R D
    s_sqrt = (v * np.sqrt(np.where(inv > 0, 1.0 / np.where(inv > 0, inv, 1.0), 0.0))) @ v.T
    s_isqrt = (v * inv_sqrt) @ v.T
    r_sqrt = sym_sqrt(r * d[:, None] * d[None, :])
    dd = s_isqrt @ np.linalg.pinv(s_sqrt + r_sqrt, rcond=1e-12, hermitian=True)
    gain_tilde = dd * d[:, None] * d[None, :]  # back to the original coordinates: D (.) D
    out: Array = (z.mean(axis=0) - y_mean)[None, :] @ s_pinv - yc @ gain_tilde.T
    return out


RULES: dict[str, Rule] = {"ensrf": ensrf, "denkf": denkf, "enkf": enkf}


def shrink_correlations(c_xy_t: Array, var_x: Array, yc: Array, c: float) -> Array:
    """Sampling-error correction of cross-covariances (after Anderson 2012).

    Multiplies each entry by ``max(0, 1 − c (1 − r²)² / (N r²))``, ``r`` its sample
    correlation. ``c_xy_t`` ``(M, p, d)``, ``var_x`` ``(M, d)`` the state's sample variances,
    ``yc`` ``(N, p)``.
    """
    n = yc.shape[0]
    var_y = np.einsum("np,np->p", yc, yc) / (n - 1)
    return c_xy_t * _shrink_factor(c_xy_t, var_y[None, :, None] * var_x[:, None, :], n, c)


def _shrink_factor(cov: Array, denom: Array, n: int, c: float) -> Array:
    """``max(0, 1 − c (1 − r²)² / (N r²))`` for covariances ``cov`` with ``r² = cov² / denom``
    (0 where ``denom`` is 0)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = np.where(denom > 0, cov**2 / np.where(denom > 0, denom, 1.0), 0.0)
        factor = np.where(r2 > 0, 1.0 - c * (1.0 - r2) ** 2 / (n * np.where(r2 > 0, r2, 1.0)), 0.0)
    return np.clip(factor, 0.0, 1.0)


# ------------------------------------------------------------------ gain="endpoints"


def endpoint_components(v: Array, zero_variance: float, rtol: float) -> tuple[Array, Array]:
    """Principal components of the endpoint coordinates ``v`` ``(N, L)``.

    Dimensions with (numerically) zero variance (the root edge, planar dead dimensions, pinned
    point orientations) are dropped, the rest scaled to unit variance, then rotated onto their
    principal axes; axes with eigenvalues below ``rtol`` times the largest are dropped.
    Returns the centred components ``(N, K)`` (mutually uncorrelated in the sample) and their
    variances ``(K,)``; ``K = 0`` if nothing varies.
    """
    n = v.shape[0]
    vc = v - v.mean(axis=0)
    var = np.einsum("nk,nk->k", vc, vc) / (n - 1)
    live = var > zero_variance
    if not live.any():
        return np.zeros((n, 0)), np.zeros(0)
    vs = vc[:, live] / np.sqrt(var[live])
    lam, vec = np.linalg.eigh(vs.T @ vs / (n - 1))
    keep = lam > rtol * lam.max()
    return vs @ vec[:, keep], lam[keep]


def endpoint_cross_covariance(c_xp: Array, var_x: Array, lam: Array, c_py: Array,
                              var_y: Array, n: int, c: float | None) -> Array:
    """Cross-covariance of every state coordinate with the observation, through the endpoints.

    The state coordinates are regressed on the endpoint components (coefficients
    ``β = C_xp / λ``, the components being uncorrelated), and ``C_xy = β C_py``. Both factors
    are damped by their significance at N samples:

    * each coefficient by ``max(0, 1 − 2c / t²)``, ``t² = β² λ (N − K − 1) / σ²_e`` its
      t-statistic, ``σ²_e`` the coordinate's variance left unexplained by the K components:
      an edge tied to the endpoints keeps a small but well-determined gain that the direct
      shrink would zero because its correlation with the observation is small;
    * each component-observation cross-covariance by the correlation shrink
      (:func:`shrink_correlations`) with constant ``c``: these are shared by every edge.

    Without shrinking (``c`` None) and for an observation linear in the endpoints this is the
    sample cross-covariance itself.

    Parameters
    ----------
    c_xp : (M, K, d) cross-covariances of the state coordinates with the components
    var_x : (M, d) the state coordinates' sample variances
    lam : (K,) the components' variances
    c_py : (K, p) the components' cross-covariances with the predicted observation
    var_y : (p,) the predicted observation's variances
    n : N
    c : shrink constant, or None

    Returns
    -------
    (M, p, d)
    """
    k = lam.shape[0]
    if k == 0:
        return np.zeros((c_xp.shape[0], c_py.shape[1], c_xp.shape[2]))
    beta = c_xp / lam[None, :, None]
    if c is not None:
        var_e = np.clip(var_x - np.einsum("mkd,mkd->md", c_xp, beta), 0.0, None)
        dof = max(n - k - 1, 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            t2 = beta**2 * (lam[None, :, None] * dof) / var_e[:, None, :]
            factor = np.where(t2 > 0, 1.0 - 2.0 * c / np.where(t2 > 0, t2, 1.0), 0.0)
        # σ²_e = 0 (fully explained) gives t² = inf: factor 1; β = 0 gives 0: no change
        beta = beta * np.clip(np.nan_to_num(factor, nan=0.0), 0.0, 1.0)
        c_py = c_py * _shrink_factor(c_py, lam[:, None] * var_y[None, :], n, c)
    out: Array = np.einsum("mkd,kp->mpd", beta, c_py)
    return out
