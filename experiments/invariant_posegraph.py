"""Prototype (b) on 3-D pose graphs: the map's loop-closure update as a numpy ensemble, in the
map's chart or in a right-invariant (Lie-group) chart per pose.

Experiment code. Every pose ``k`` is kept as N samples ``X_k`` relative to the anchor (the
map's star with the anchor as root, same input samples as the map: the runner's
:func:`experiments.realdata_run.draw` from the same seed). Odometry composes each sample with
its odometry sample. A loop closure ``i -> j`` predicts ``y = X_i^-1 X_j`` per sample and
updates every pose with :func:`experiments.invariant_ensemble.ensrf_step` (square-root gain,
correlation shrink) in one of two charts of the poses:

* ``"standard"``: ``[t_k, log(qbar_k^-1 q_k)]`` (world translation, body rotation vector about
  the pose's chordal mean): the map's tangent space;
* ``"invariant"``: ``xi_k = Log(X_k Xbar_k^-1)`` in SE(3): ``omega_k = log(q_k qbar_k^-1)``
  (world-frame rotation), ``rho_k = J_l(omega_k)^-1 (t_k - R(omega_k) tbar_k)``; a rotation
  correction turns the pose's translation along the arc about the anchor, not along the tangent.

The observation is charted as the map does it: ``[t_y, log(q_ref^-1 q_y)]`` about the chordal
mean of the predicted rotations, the observation's samples the same way.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt
from mcsm.core.quat import align_hemisphere, mean_rotation, qconj

from experiments.invariant_ensemble import ensrf_step
from experiments.posegraph_sim import qexp, qlog, qmul, qrot
from experiments.realdata_data import Problem
from experiments.realdata_run import RunResult, draw

Array = npt.NDArray[np.float64]


def _skew_apply(w: Array, v: Array) -> Array:
    return np.cross(w, v)


def _jl(w: Array, v: Array, inverse: bool) -> Array:
    """``J_l(w) v`` or ``J_l(w)^-1 v`` of SO(3), batched over leading axes."""
    th = np.linalg.norm(w, axis=-1, keepdims=True)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    wv = _skew_apply(w, v)
    wwv = _skew_apply(w, wv)
    if not inverse:
        c1 = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(th)) / ts**2)
        c2 = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (th - np.sin(th)) / ts**3)
        return v + c1 * wv + c2 * wwv
    c2 = np.where(small, 1.0 / 12.0 + th**2 / 720.0,
                  1.0 / ts**2 - (1.0 + np.cos(th)) / (2.0 * ts * np.sin(np.where(small, 1.0, th))))
    return v - 0.5 * wv + c2 * wwv


class PoseGraphEnsemble:
    """Every pose of a pose graph as N samples relative to the anchor (module docstring)."""

    def __init__(self, n_samples: int, *, chart: str = "invariant", shrink: float | None = 4.0,
                 mda: int = 1) -> None:
        if chart not in ("standard", "invariant"):
            raise ValueError("chart must be 'standard' or 'invariant'")
        self.n, self.chart, self.shrink, self.mda = n_samples, chart, shrink, mda
        self.t = np.zeros((1, n_samples, 3))
        self.q = np.zeros((1, n_samples, 4))
        self.q[..., 0] = 1.0
        self.index: dict[int, int] = {}

    def add(self, pose: int) -> None:
        self.index[pose] = len(self.index)

    def odometry(self, i: int, j: int, x: Array) -> None:
        """New pose ``j`` from pose ``i`` and the odometry samples ``x (N, 7)``."""
        a = self.index[i]
        t = self.t[a] + qrot(self.q[a], x[:, :3])
        q = qmul(self.q[a], x[:, 3:])
        self.index[j] = len(self.t)
        self.t = np.concatenate([self.t, t[None]], axis=0)
        self.q = np.concatenate([self.q, q[None]], axis=0)

    def _chart(self) -> tuple[Array, tuple[Array, Array]]:
        t, q = self.t[1:], self.q[1:]
        qbar = mean_rotation(q)[:, None, :]  # (M-1, 1, 4)
        tbar = t.mean(axis=1, keepdims=True)
        q = align_hemisphere(q, qbar)
        if self.chart == "standard":
            v = np.concatenate([t, qlog(qmul(qconj(qbar), q))], axis=-1)
        else:
            w = qlog(qmul(q, qconj(qbar)))
            rho = _jl(w, t - qrot(qexp(w), np.broadcast_to(tbar, t.shape)), inverse=True)
            v = np.concatenate([rho, w], axis=-1)
        return np.moveaxis(v, 1, 0).reshape(self.n, -1), (qbar, tbar)

    def _unchart(self, s: Array, ref: tuple[Array, Array]) -> None:
        qbar, tbar = ref
        v = np.moveaxis(s.reshape(self.n, -1, 6), 0, 1)  # (M-1, N, 6)
        if self.chart == "standard":
            self.t[1:] = v[..., :3]
            self.q[1:] = qmul(qbar, qexp(v[..., 3:]))
        else:
            w = v[..., 3:]
            self.q[1:] = qmul(qexp(w), qbar)
            self.t[1:] = _jl(w, v[..., :3], inverse=False) + qrot(qexp(w), np.broadcast_to(
                tbar, v[..., :3].shape))

    def loop_closure(self, i: int, j: int, x: Array) -> float:
        """Update every pose with the closure samples ``x (N, 7)`` of ``i -> j``; its NIS."""
        a, b = self.index[i], self.index[j]
        nis0 = float("nan")
        for step in range(self.mda):
            qa_c = qconj(self.q[a])
            ty = qrot(qa_c, self.t[b] - self.t[a])
            qy = qmul(qa_c, self.q[b])
            qref = mean_rotation(qy)
            ry = qlog(qmul(qconj(qref)[None], align_hemisphere(qy, qref[None])))
            rz = qlog(qmul(qconj(qref)[None], align_hemisphere(x[:, 3:], qref[None])))
            y = np.concatenate([ty, ry], axis=1)
            z = np.concatenate([x[:, :3], rz], axis=1)
            s_mat, ref = self._chart()
            new, nis = ensrf_step(s_mat, y, z, shrink=self.shrink, mda=self.mda)
            if step == 0:
                nis0 = nis
            self._unchart(new, ref)
        return nis0

    def positions(self, poses: list[int]) -> Array:
        return np.stack([self.t[self.index[p]].mean(axis=0) for p in poses])


def run_posegraph_ensemble(problem: Problem, ens: PoseGraphEnsemble, *, seed: int,
                           checkpoint_every: int = 500,
                           error_fn: Callable[[Any, int], float] | None = None) -> RunResult:
    """Stream a 3-D pose graph (odometry ``i -> i + 1``) into ``ens``, timed per step with the
    joint covariance of the current pose and the anchor (its samples' covariance)."""
    if problem.dim != 3 or problem.bounded:
        raise ValueError("the pose-graph ensemble takes a 3-D pose graph")
    rng = np.random.default_rng(seed)
    ens.add(problem.steps[0][0])
    n = len(problem.steps)
    res = RunResult(step_s=np.zeros(n))
    for k, (pose, edges) in enumerate(problem.steps):
        xs = [draw(e, 3, ens.n, rng) for e in edges]
        t0 = time.process_time()
        for e, x in zip(edges, xs, strict=True):
            if e.kind == "odometry":
                if e.j != pose:
                    raise ValueError("odometry must go from the known pose to the new one")
                ens.odometry(e.i, e.j, x)
            else:
                nis = ens.loop_closure(e.i, e.j, x)
                res.tested += 1
                res.nis.append((k, nis, 6, "accepted"))
        if k > 0:
            np.cov(ens.t[ens.index[pose]].T)
        res.step_s[k] = time.process_time() - t0
        if error_fn is not None and ((k + 1) % checkpoint_every == 0 or k == n - 1):
            res.checkpoints[k + 1] = error_fn(ens, k + 1)
    res.total_s = float(res.step_s.sum())
    return res
