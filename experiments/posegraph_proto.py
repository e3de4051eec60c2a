"""A small stand-alone reference of the joint full-AT update, for measuring design choices.

Not the product: ``mcsm.StochasticMap`` is. This is a minimal pose-graph-only map (one component,
root ``p0``, every pose kept) with the joint ensemble update of issue 3/8 written out in ~60 lines,
so that variants (iteration, shrink, inflation, frame of the edge deviations) can be measured on
the same data as the core, and proposed changes come with numbers.

Update of a loop closure ``z: a -> b`` with tangent covariance ``R`` (PAPER §5.2, joint form):

1. predict ``h_k = (r->a)_k^R ⊕ (r->b)_k`` per sample;
2. observation space: ``y_k = [t_h,k - mean(t_h), log(qbar^-1 q_h,k)]`` (6-D, ``qbar`` the
   hemisphere-aligned normalised mean rotation of ``h``), target ``d = [t_z - mean(t_h),
   log(qbar^-1 q_z)]``;
3. edge anomalies ``A_m,k = [t_m,k - tbar_m, log(qbar_m^-1 q_m,k)]``;
4. ``C_xy = A^T Y / (N-1)``, ``S = C_yy + R``; mean moves by ``C_xy S^-1 (d - ybar)``; anomalies by
   the square-root gain (EnSRF, ``C_xy S^-1/2 (S^1/2 + R^1/2)^-1``) or half the gain (DEnKF);
5. retract: ``t = tbar' + A'_t``, ``q = qbar_m exp(dbar_r) exp(A'_r)``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import numpy.typing as npt

from experiments.posegraph_sim import compose, invert, qexp, qlog, qmul

Array = npt.NDArray[np.float64]


def _sym_sqrt(s: Array) -> Array:
    w, v = np.linalg.eigh(s)
    return (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T


def _mean_rot(q: Array) -> Array:
    """Hemisphere-aligned normalised mean of quaternions over axis -2; shape ``(..., 4)``."""
    ref = q[..., :1, :]
    sign = np.where(np.sum(q * ref, axis=-1, keepdims=True) < 0.0, -1.0, 1.0)
    m = np.mean(q * sign, axis=-2)
    return m / np.linalg.norm(m, axis=-1, keepdims=True)


def _tangent(x: Array) -> tuple[Array, Array, Array]:
    """Means and 6-D anomalies of ``x (..., N, 7)``: ``(tbar, qbar, A (..., N, 6))``."""
    tbar = x[..., :3].mean(axis=-2)
    qbar = _mean_rot(x[..., 3:])
    qinv = qbar * np.array([1.0, -1.0, -1.0, -1.0])
    rot = qlog(qmul(qinv[..., None, :], x[..., 3:]))
    return tbar, qbar, np.concatenate([x[..., :3] - tbar[..., None, :], rot], axis=-1)


class ProtoMap:
    """One-component pose-graph map with the joint deterministic full-AT update.

    Parameters
    ----------
    n_samples : int
        N.
    analysis : {"ensrf", "denkf"}
        Anomaly update.
    shrink : float or None
        Correlation shrink constant c (sampling-error correction), None for none.
    inflation : float
        Multiplier of every edge's anomalies after each loop closure.
    planar : bool
        Restrict the observation to ``x, y, yaw`` (the other components are exactly zero).
    """

    def __init__(self, n_samples: int, *, analysis: Literal["ensrf", "denkf"] = "ensrf",
                 shrink: float | None = None, inflation: float = 1.0,
                 planar: bool = False) -> None:
        self.n_samples = n_samples
        self.analysis = analysis
        self.shrink = shrink
        self.inflation = inflation
        self.obs_index = np.array([0, 1, 5]) if planar else np.arange(6)
        self.edges = np.zeros((0, n_samples, 7))
        self.index: dict[str, int] = {}

    def update(self, a: str, b: str, samples: Array) -> None:
        """Odometry (``b`` new) or loop closure (both known) ``a -> b``."""
        if a not in self.index:  # first edge: a becomes the root
            self.index[a] = 0
            self.edges = np.zeros((1, self.n_samples, 7))
            self.edges[0, :, 3] = 1.0
        if b not in self.index:
            new = compose(self.edges[self.index[a]], samples)
            self.index[b] = len(self.edges)
            self.edges = np.concatenate([self.edges, new[None]], axis=0)
            return
        self._loop(self.index[a], self.index[b], samples)

    def _loop(self, ia: int, ib: int, samples: Array) -> None:
        n = self.n_samples
        idx = self.obs_index
        h = compose(invert(self.edges[ia]), self.edges[ib])
        th, qh, y = _tangent(h)
        zt, zq, zr = _tangent(samples)
        z_mean = np.concatenate([zt - th, qlog(qmul(qh * [1, -1, -1, -1], zq))])[idx]
        r = (zr[:, idx].T @ zr[:, idx]) / (n - 1)
        y = y[:, idx]
        ybar = y.mean(0)
        y = y - ybar
        tbar, qbar, a = _tangent(self.edges)
        cxy = np.swapaxes(a, 1, 2) @ y / (n - 1)
        cyy = y.T @ y / (n - 1)
        if self.shrink is not None:
            sd_x = np.sqrt(np.sum(a * a, axis=1) / (n - 1))
            sd_y = np.sqrt(np.diag(cyy))
            corr = cxy / np.maximum(sd_x[:, :, None] * sd_y[None, None, :], 1e-300)
            r2 = np.clip(corr**2, 1e-12, 1.0)
            cxy = cxy * np.clip(1.0 - self.shrink * (1.0 - r2) ** 2 / (n * r2), 0.0, 1.0)
        s = cyy + r
        s_inv = np.linalg.inv(s)
        gain = cxy @ s_inv  # (M, 6, d)
        dmean = gain @ (z_mean - ybar)  # (M, 6)
        if self.analysis == "ensrf":
            s_half = _sym_sqrt(s)
            g = s_inv @ s_half @ np.linalg.inv(s_half + _sym_sqrt(r))
            a_new = a - y @ np.swapaxes(cxy @ g, 1, 2)
        else:
            a_new = a - 0.5 * (y @ np.swapaxes(gain, 1, 2))
        a_new *= self.inflation
        q_mean = qmul(qbar, qexp(dmean[:, 3:]))
        t = (tbar + dmean[:, :3])[:, None, :] + a_new[..., :3]
        q = qmul(q_mean[:, None, :], qexp(a_new[..., 3:]))
        q /= np.linalg.norm(q, axis=-1, keepdims=True)
        out = np.concatenate([t, q], axis=-1)
        out[0] = self.edges[0]
        if not np.isfinite(out).all():
            raise FloatingPointError("non-finite update")
        self.edges = out

    def marginal(self, a: str, b: str) -> tuple[Array, Array]:
        """Mean ``(7,)`` and tangent covariance ``(6, 6)`` of ``a -> b`` (``a`` the root here)."""
        x = compose(invert(self.edges[self.index[a]]), self.edges[self.index[b]])
        t, q, anom = _tangent(x)
        return np.concatenate([t, q]), anom.T @ anom / (self.n_samples - 1)
