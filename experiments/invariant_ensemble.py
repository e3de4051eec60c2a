"""Relinearisation prototype (b) for issue 22: the ensemble update of a bounded landmark map in
an invariant (Lie-group) error chart, optionally iterated (multiple data assimilation).

Experiment code in numpy, not the core. One joint ensemble of N samples of the current pose
``(x, y, theta)`` and the landmarks seen so far, all in the anchor's frame (the bounded map of
the real-data benchmark, with the same input samples: :func:`experiments.realdata_run.draw`
from the same seed). Odometry composes each sample with its odometry sample; a first sighting
adds ``l_i = p_i + R(theta_i) z_i``; a re-sighting is the square-root ensemble update the map
uses (statistical linearisation ``y_i = R(theta_i)^T (l_i - p_i)``, gain from the sample cross-
covariance with the map's correlation shrink, mean moved with the full gain on the observation's
sample mean and covariance, anomalies with the square-root gain), done in one of two charts:

* ``"standard"``: the state vector ``(x, y, theta, l_1, ..., l_K)`` itself, as the map does;
* ``"invariant"``: the right-invariant chart of the group SE_{K+1}(2) (Barrau and Bonnabel's
  invariant EKF for SLAM; Zhang, Zhang and Huang analyse it in 3-D): with a reference
  ``Xbar`` (mean heading, mean positions), sample ``i`` is ``X_i = Exp(xi_i) Xbar``, i.e.
  ``omega_i = theta_i - thetabar``, ``V(omega_i) rho = p_i - R(omega_i) pbar`` (same for every
  landmark). A heading correction is then a rotation of the robot *and every landmark* about
  the anchor along the arc, where the standard chart moves them along the tangent.

``mda = K`` repeats the update K times with the observation covariance multiplied by K,
re-predicting ``y`` from the updated ensemble each time (Emerick and Reynolds' MDA).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from experiments.realdata_data import Problem
from experiments.realdata_run import RunResult, draw

Array = npt.NDArray[np.float64]


def _v_coeffs(w: Array) -> tuple[Array, Array]:
    """``a = sin(w)/w``, ``b = (1 - cos(w))/w`` of SE(2)'s ``V(w) = [[a, -b], [b, a]]``."""
    small = np.abs(w) < 1e-8
    ws = np.where(small, 1.0, w)
    return (np.where(small, 1.0 - w * w / 6.0, np.sin(w) / ws),
            np.where(small, 0.5 * w, (1.0 - np.cos(w)) / ws))


def _rot(w: Array, v: Array) -> Array:
    """Rotate 2-vectors ``v (N, ..., 2)`` by per-sample angles ``w (N,)``."""
    c, s = np.cos(w), np.sin(w)
    shape = (len(w),) + (1,) * (v.ndim - 2)
    c, s = c.reshape(shape), s.reshape(shape)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], axis=-1)


def _sqrtm(s: Array) -> Array:
    w, v = np.linalg.eigh(0.5 * (s + s.T))
    return (v * np.sqrt(np.clip(w, 0.0, None))) @ v.T


def shrink_factor(cross: Array, var_x: Array, var_y: Array, n: int, c: float) -> Array:
    """The map's correlation shrink ``max(0, 1 - c (1 - r^2)^2 / (N r^2))`` per entry."""
    den = var_x[:, None] * var_y[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(den > 0, cross**2 / np.where(den > 0, den, 1.0), 0.0)
        f = np.where(r2 > 0, 1.0 - c * (1.0 - r2) ** 2 / (n * np.where(r2 > 0, r2, 1.0)), 0.0)
    return np.clip(f, 0.0, 1.0)


def ensrf_step(s_mat: Array, y: Array, z: Array, *, shrink: float | None,
               mda: int = 1) -> tuple[Array, float]:
    """One square-root ensemble update of the chart coordinates ``s_mat (N, D)`` by observation
    samples ``z (N, p)`` of the predicted ``y (N, p)``, the observation covariance multiplied
    by ``mda``; the updated coordinates and the NIS of the whole observation."""
    n = len(s_mat)
    zbar = z.mean(0)
    r = np.atleast_2d(np.cov(z.T))
    a = s_mat - s_mat.mean(0)
    ya = y - y.mean(0)
    cross = a.T @ ya / (n - 1)
    syy = ya.T @ ya / (n - 1)
    if shrink is not None:
        cross = cross * shrink_factor(cross, np.einsum("ij,ij->j", a, a) / (n - 1),
                                      np.diag(syy), n, shrink)
    nu = zbar - y.mean(0)
    nis = float(nu @ np.linalg.solve(syy + r, nu))
    rk = r * mda
    s_inn = syy + rk
    gain = np.linalg.solve(s_inn, cross.T).T
    root_s = _sqrtm(s_inn)
    sq_gain = cross @ np.linalg.inv(root_s) @ np.linalg.inv(root_s + _sqrtm(rk))
    return s_mat.mean(0) + gain @ nu + a - ya @ sq_gain.T, nis


class EnsembleSlam:
    """The bounded landmark map as one numpy ensemble (module docstring).

    Parameters
    ----------
    n_samples : N
    chart : ``"standard"`` or ``"invariant"``
    mda : number of partial updates per re-sighting (1: one update)
    shrink : correlation-shrink constant (None: off); the map's default is 4
    gate : chi-square quantile of a gate on re-sightings, or None
    """

    def __init__(self, n_samples: int, *, chart: str = "invariant", mda: int = 1,
                 shrink: float | None = 4.0, gate: float | None = None) -> None:
        if chart not in ("standard", "invariant"):
            raise ValueError("chart must be 'standard' or 'invariant'")
        self.n = n_samples
        self.chart = chart
        self.mda = mda
        self.shrink = shrink
        self.threshold = None
        if gate is not None:
            from scipy.stats import chi2

            self.threshold = float(chi2.ppf(gate, 2))
        self.pose = np.zeros((n_samples, 3))
        self.lms = np.zeros((n_samples, 0, 2))
        self.slot: dict[int, int] = {}

    # ------------------------------------------------------------------ charts
    def _to_chart(self) -> tuple[Array, tuple[Array, ...]]:
        """State matrix ``(N, 3 + 2K)`` in the chart, and the reference to come back with."""
        th = self.pose[:, 2]
        thbar = float(np.arctan2(np.sin(th).mean(), np.cos(th).mean()))
        w = np.arctan2(np.sin(th - thbar), np.cos(th - thbar))
        if self.chart == "standard":
            return np.concatenate([self.pose[:, :2], w[:, None],
                                   self.lms.reshape(self.n, -1)], axis=1), (np.array(thbar),)
        pbar = self.pose[:, :2].mean(0)
        lbar = self.lms.mean(0)
        u_p = self.pose[:, :2] - _rot(w, np.broadcast_to(pbar, (self.n, 2)))
        u_l = self.lms - _rot(w, np.broadcast_to(lbar, self.lms.shape))
        a, b = _v_coeffs(w)
        den = a * a + b * b
        inv = np.stack([a / den, b / den], axis=-1)  # V^-1 = [[a, b], [-b, a]] / den

        def vinv(u: Array) -> Array:
            sh = (self.n,) + (1,) * (u.ndim - 2)
            ia, ib = inv[:, 0].reshape(sh), inv[:, 1].reshape(sh)
            return np.stack([ia * u[..., 0] + ib * u[..., 1], -ib * u[..., 0] + ia * u[..., 1]],
                            axis=-1)

        return (np.concatenate([vinv(u_p), w[:, None], vinv(u_l).reshape(self.n, -1)], axis=1),
                (np.array(thbar), pbar, lbar))

    def _from_chart(self, s: Array, ref: tuple[Array, ...]) -> None:
        thbar = float(ref[0])
        w = s[:, 2]
        if self.chart == "standard":
            self.pose = np.concatenate([s[:, :2], (thbar + w)[:, None]], axis=1)
            self.lms = s[:, 3:].reshape(self.n, -1, 2)
            return
        pbar, lbar = ref[1], ref[2]
        a, b = _v_coeffs(w)

        def vmul(r: Array) -> Array:
            sh = (self.n,) + (1,) * (r.ndim - 2)
            aa, bb = a.reshape(sh), b.reshape(sh)
            return np.stack([aa * r[..., 0] - bb * r[..., 1], bb * r[..., 0] + aa * r[..., 1]],
                            axis=-1)

        rho_l = s[:, 3:].reshape(self.n, -1, 2)
        p = vmul(s[:, :2]) + _rot(w, np.broadcast_to(pbar, (self.n, 2)))
        self.pose = np.concatenate([p, (thbar + w)[:, None]], axis=1)
        self.lms = vmul(rho_l) + _rot(w, np.broadcast_to(lbar, rho_l.shape))

    # ------------------------------------------------------------------ steps
    def odometry(self, x: Array) -> None:
        """Compose every pose sample with its odometry sample (an ``(N, 7)`` planar AT)."""
        d = np.stack([x[:, 0], x[:, 1], 2.0 * np.arctan2(x[:, 6], x[:, 3])], axis=1)
        c, s = np.cos(self.pose[:, 2]), np.sin(self.pose[:, 2])
        self.pose = np.stack([self.pose[:, 0] + c * d[:, 0] - s * d[:, 1],
                              self.pose[:, 1] + s * d[:, 0] + c * d[:, 1],
                              self.pose[:, 2] + d[:, 2]], axis=1)

    def predict(self, k: int) -> Array:
        """Predicted sightings ``(N, 2)`` of landmark slot ``k``."""
        return _rot(-self.pose[:, 2], self.lms[:, k] - self.pose[:, :2])

    def sighting(self, j: int, pts: Array) -> tuple[float | None, bool]:
        """A sighting ``(N, 3)`` of landmark ``j``; returns (NIS, applied)."""
        z = pts[:, :2]
        if j not in self.slot:
            self.slot[j] = self.lms.shape[1]
            new = self.pose[:, :2] + _rot(self.pose[:, 2], z)
            self.lms = np.concatenate([self.lms, new[:, None, :]], axis=1)
            return None, True
        k = self.slot[j]
        nis0: float | None = None
        for step in range(self.mda):
            s_mat, ref = self._to_chart()
            new, nis = ensrf_step(s_mat, self.predict(k), z, shrink=self.shrink, mda=self.mda)
            if step == 0:
                nis0 = nis
                if self.threshold is not None and nis > self.threshold:
                    return nis, False
            self._from_chart(new, ref)
        return nis0, True

    def landmark_means(self, ids: list[int]) -> Array:
        """Mean landmark positions ``(K, 2)`` (NaN for unseen)."""
        out = np.full((len(ids), 2), np.nan)
        for n, j in enumerate(ids):
            if j in self.slot:
                out[n] = self.lms[:, self.slot[j]].mean(0)
        return out


def run_ensemble(problem: Problem, ens: EnsembleSlam, *, seed: int, checkpoint_every: int = 500,
                 error_fn: Callable[[Any, int], float] | None = None) -> RunResult:
    """Stream a bounded landmark problem into ``ens`` with the map's input samples; timed like
    :func:`experiments.realdata_run.run_map` (the step's query: the joint covariance of the
    current pose and the landmark seen last)."""
    if not problem.bounded or problem.dim != 2:
        raise ValueError("the ensemble prototype is the bounded planar landmark map")
    rng = np.random.default_rng(seed)
    n = len(problem.steps)
    res = RunResult(step_s=np.zeros(n))
    last: int | None = None
    for k, (_, edges) in enumerate(problem.steps):
        xs = [draw(e, 2, ens.n, rng) for e in edges]
        t0 = time.process_time()
        for e, x in zip(edges, xs, strict=True):
            if e.kind == "odometry":
                ens.odometry(x)
                continue
            nis, applied = ens.sighting(e.j, x)
            last = e.j
            if nis is not None:
                res.tested += 1
                res.rejected += not applied
                res.nis.append((k, nis, 2, "accepted" if applied else "rejected"))
        if last is not None:
            joint = np.concatenate([ens.pose, ens.lms[:, ens.slot[last]]], axis=1)
            np.cov(joint.T)
        res.step_s[k] = time.process_time() - t0
        if error_fn is not None and ((k + 1) % checkpoint_every == 0 or k == n - 1):
            res.checkpoints[k + 1] = error_fn(ens, k + 1)
    res.total_s = float(res.step_s.sum())
    return res
