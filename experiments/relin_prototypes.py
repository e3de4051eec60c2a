"""Relinearisation prototype (a) for issue 22: a batch Gauss-Newton over everything the map has
seen, then the map's samples redrawn around the optimum with the posterior's joint covariance.

Experiment code (numpy, scipy, gtsam), not the shipped operation; it is the independent
reference the portable-kernel relinearisation can be checked against, and one of the two
prototypes compared in docs/evaluation.md ("Relinearisation: the prototypes compared";
prototype (b), the ensemble update in an invariant chart, is
:mod:`experiments.invariant_ensemble` and :mod:`experiments.invariant_posegraph`).

:class:`BatchRelinearizer` is a :class:`experiments.realdata_run.Hook`. It records every input
the map accepted as its sample mean and sample covariance (GTSAM's body-frame tangent), and at
chosen steps

1. builds the factor graph of all of them (removed poses included: their information stays at
   full fidelity, realdata.md), anchor pinned at the identity;
2. runs Gauss-Newton from the previous optimum, the map's current means for the frames it holds
   and its estimate of each removed pose when it was current (``graph.linearize(values)
   .optimize()``, step halving when the error grows, at most ``max_iterations``);
3. draws N joint samples of the frames the map holds, conditional on the anchor, from the
   Gaussian at the optimum: ``Marginals.jointMarginalCovariance`` of the kept variables when
   they are few (a bounded map), otherwise perturbation sampling on the sparse whitened Jacobian
   ``A`` (anchor columns dropped, so the draw is conditional on it):
   ``delta = (A^T A)^-1 A^T eps`` with ``eps ~ N(0, I)``, exactly ``N(0, (A^T A)^-1)``;
4. retracts them the way GTSAM's solver does (``Pose2``/``Pose3``: ``p ∘ Exp(delta)``;
   points: ``p + delta``) and writes them as the component's root->frame edges through
   ``snapshot()`` / ``from_snapshot`` (same options, adaptive-inflation state kept).

Triggers: ``"periodic"`` (every ``every`` steps, the first after ``offset`` steps: by default
half a period, so that errors sampled every ``every`` steps fall between two
relinearisations, not right after one) or ``"nis"`` (a tested update of the step had
an NIS above the chi-square ``nis_quantile`` for its dof, 9.21 for 2 dof at 0.99, at least
``min_gap`` steps after the last one).

:data:`PROTOTYPES` are the configurations of the comparison (``benchmarks/realdata.py
--prototypes``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from gtsam.symbol_shorthand import L, X
from mcsm.core.gate import chi2_quantile

from experiments.realdata_data import Edge, Problem
from experiments.realdata_gtsam import anchor_prior, edge_factor
from experiments.realdata_run import Hook, RunResult, sample_moments

Array = npt.NDArray[np.float64]
DENSE_MAX_DIMS = 2000  # kept dimensions up to which the joint covariance is formed densely


PROTOTYPES: list[dict[str, Any]] = [
    {"name": "map, gate off, no relinearisation", "options": {"gate": None}},
    {"name": "(a) batch relin., every 500 steps", "options": {"gate": None},
     "driver": {"prototype": "batch", "trigger": "periodic", "every": 500}},
    {"name": "(a) batch relin., NIS > chi2 0.99, >= 50 steps apart", "options": {"gate": None},
     "driver": {"prototype": "batch", "trigger": "nis", "nis_quantile": 0.99, "min_gap": 50}},
    {"name": "(a) batch relin., NIS > chi2 0.99, >= 25 steps apart", "options": {"gate": None},
     "driver": {"prototype": "batch", "trigger": "nis", "nis_quantile": 0.99, "min_gap": 25}},
    {"name": "(b) numpy ensemble, standard chart (the map's update)",
     "driver": {"ensemble": {"chart": "standard"}}, "datasets": ["victoria"]},
    {"name": "(b) numpy ensemble, invariant chart", "driver": {"ensemble": {"chart": "invariant"}}},
    {"name": "(b) numpy ensemble, invariant chart + MDA x4",
     "driver": {"ensemble": {"chart": "invariant", "mda": 4}}, "datasets": ["victoria"]},
    {"name": "(b) map + MDA x4 (iterated update)", "options": {"gate": None},
     "driver": {"mda": 4}},
]


# --------------------------------------------------------------------------- retractions
def pose2_retract(p: Array, delta: Array) -> Array:
    """GTSAM's ``Pose2.retract``: ``p ∘ Exp(delta)``; ``p`` (3,), ``delta`` (N, 3) ``vx vy w``;
    the heading is not wrapped (samples stay next to ``p``'s angle)."""
    v, w = delta[:, :2], delta[:, 2]
    small = np.abs(w) < 1e-9
    ws = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w * w / 6.0, np.sin(w) / ws)
    b = np.where(small, 0.5 * w, (1.0 - np.cos(w)) / ws)
    t = np.stack([a * v[:, 0] - b * v[:, 1], b * v[:, 0] + a * v[:, 1]], axis=1)
    c, s = np.cos(p[2]), np.sin(p[2])
    return np.stack([p[0] + c * t[:, 0] - s * t[:, 1], p[1] + s * t[:, 0] + c * t[:, 1],
                     p[2] + w], axis=1)


def pose3_retract(p: Array, delta: Array) -> Array:
    """GTSAM's ``Pose3.retract`` (``p ∘ Exp(delta)``, ``delta = [w, v]``) as ``(N, 7)`` rows
    ``x y z qw qx qy qz`` in the hemisphere of ``p``'s quaternion; ``p`` (7,)."""
    from mcsm.core.quat import qexp, qmul, qrot

    w, v = delta[:, :3], delta[:, 3:]
    th = np.linalg.norm(w, axis=1)
    small = th < 1e-6
    ts = np.where(small, 1.0, th)
    c1 = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(th)) / ts**2)
    c2 = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (th - np.sin(th)) / ts**3)
    wxv = np.cross(w, v)
    t = v + c1[:, None] * wxv + c2[:, None] * np.cross(w, wxv)
    q = qmul(p[3:], qexp(w))
    return np.concatenate([p[:3] + qrot(p[3:], t), q], axis=1)


def planar_rows(xyt: Array) -> Array:
    """Planar poses ``(N, 3)`` as AT rows ``(N, 7)`` (continuous in the heading)."""
    out = np.zeros((len(xyt), 7))
    out[:, :2] = xyt[:, :2]
    out[:, 3] = np.cos(0.5 * xyt[:, 2])
    out[:, 6] = np.sin(0.5 * xyt[:, 2])
    return out


def point_rows(xy: Array) -> Array:
    """Points ``(N, 2)`` as point-frame rows ``(N, 7)`` (z = 0, identity quaternion)."""
    out = np.zeros((len(xy), 7))
    out[:, :2] = xy
    out[:, 3] = 1.0
    return out


# --------------------------------------------------------------------------- the sampler
def key_dims(values: gtsam.Values, keys: list[int], dim: int) -> dict[int, int]:
    """Tangent dimension of each key: poses 3 (planar) or 6, landmarks 2."""
    return {k: (2 if gtsam.Symbol(k).chr() == ord("l") else (3 if dim == 2 else 6)) for k in keys}


def joint_samples(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, kept: list[int],
                  anchor: int, dim: int, n_samples: int, rng: np.random.Generator
                  ) -> dict[int, Array]:
    """Tangent deviations ``(N, d)`` of every kept key, jointly Gaussian with the posterior's
    covariance at ``values``, conditional on ``anchor``."""
    dims = key_dims(values, kept, dim)
    total = sum(dims.values())
    if total <= DENSE_MAX_DIMS:
        marg = gtsam.Marginals(graph, values)
        cov = np.asarray(marg.jointMarginalCovariance(gtsam.KeyVector(kept)).fullMatrix())
        cov = 0.5 * (cov + cov.T)
        w, v = np.linalg.eigh(cov)
        root = v * np.sqrt(np.clip(w, 0.0, None))
        draw = rng.standard_normal((n_samples, total)) @ root.T
    else:
        lin = graph.linearize(values)
        keys = sorted(lin.keys())
        kd = key_dims(values, keys, dim)
        offs, o = {}, 0
        for k in keys:
            offs[k] = o
            o += kd[k]
        tri = lin.sparseJacobian_()
        rows, cols, vals = tri[0].astype(np.int64) - 1, tri[1].astype(np.int64) - 1, tri[2]
        keep = cols < o  # the last column is the right-hand side
        a = sp.csc_matrix((vals[keep], (rows[keep], cols[keep])), shape=(int(rows.max()) + 1, o))
        live = np.ones(o, dtype=bool)
        live[offs[anchor]:offs[anchor] + kd[anchor]] = False
        a = a[:, np.flatnonzero(live)]
        h = (a.T @ a).tocsc()
        lu = spla.splu(h, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                       options={"SymmetricMode": True})
        eps = rng.standard_normal((a.shape[0], n_samples))
        full = np.zeros((o, n_samples))
        full[live] = lu.solve(np.asarray(a.T @ eps))
        draw = np.concatenate([full[offs[k]:offs[k] + kd[k]].T for k in kept], axis=1)
    out, o = {}, 0
    for k in kept:
        out[k] = draw[:, o:o + dims[k]]
        o += dims[k]
    return out


def gauss_newton(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                 max_iterations: int = 10, tol: float = 1e-6) -> tuple[gtsam.Values, int, float]:
    """Gauss-Newton with step halving; the result, iterations and final error."""
    err = graph.error(values)
    it = 0
    while it < max_iterations:
        it += 1
        delta = graph.linearize(values).optimize()
        step = 1.0
        while True:
            trial = values.retract(delta.scale(step))
            e = graph.error(trial)
            if e <= err * (1 + 1e-12) or step < 1e-3:
                break
            step *= 0.5
        values, err_old, err = trial, err, e
        size = float(np.abs(np.asarray(delta.vector())).max())
        if step * size < tol or abs(err_old - err) <= 1e-10 * max(err, 1.0):
            break
    return values, it, err


# --------------------------------------------------------------------------- the hook
@dataclass
class RelinStats:
    """What the relinearisations of one run cost and did."""

    count: int = 0
    total_s: float = 0.0
    worst_s: float = 0.0
    iterations: list[int] = field(default_factory=list)
    steps: list[int] = field(default_factory=list)


class BatchRelinearizer(Hook):
    """Prototype (a) as a hook of :func:`experiments.realdata_run.run_map` (module docstring).

    Parameters
    ----------
    problem : the data set (anchor, dimension)
    trigger : ``"periodic"`` or ``"nis"``
    every, offset : steps between periodic relinearisations, and the step of the first one
        (default ``every // 2``)
    nis_quantile, min_gap : the NIS trigger's chi-square quantile (of one tested update's NIS
        for its dof) and the least number of steps between two relinearisations
    include_rejected : also put the inputs the gate refused into the batch
    seed : of the redraw's own generator (the input stream's is not touched)
    """

    def __init__(self, problem: Problem, *, trigger: str = "nis", every: int = 500,
                 offset: int | None = None, nis_quantile: float = 0.99, min_gap: int = 50,
                 include_rejected: bool = False, seed: int = 0,
                 max_iterations: int = 10) -> None:
        if trigger not in ("periodic", "nis"):
            raise ValueError("trigger must be 'periodic' or 'nis'")
        self.p = problem
        self.trigger = trigger
        self.every = every
        self.offset = every // 2 if offset is None else offset
        self.nis_quantile = nis_quantile
        self.min_gap = min_gap
        self.include_rejected = include_rejected
        self.rng = np.random.default_rng([seed, 22])
        self.max_iterations = max_iterations
        self.inputs: list[tuple[Edge, Array, Array]] = []
        self.values = gtsam.Values()
        self.fired = False
        self.last = -(10**9)
        self.stats = RelinStats()
        self.anchor = X(problem.steps[0][0])

    def describe(self) -> str:
        s = self.stats
        return (f"{s.count} relinearisations, {s.total_s:.1f} s in all, worst {s.worst_s:.2f} s, "
                f"GN iterations {int(np.median(s.iterations)) if s.iterations else 0} median")

    def after(self, smap: Any, edge: Edge, samples: Array, result: Any) -> tuple[Any, Any]:
        applied = result.kind != "rejected"
        if applied or self.include_rejected:
            mean, cov = sample_moments(samples, self.p.dim)
            self.inputs.append((edge, mean, cov))
        v = result.verdict
        if v.nis is not None and v.dof > 0 and v.nis > chi2_quantile(self.nis_quantile, v.dof):
            self.fired = True
        return smap, result

    def end_step(self, smap: Any, k: int, pose: int, run: RunResult) -> Any:
        if self.trigger == "periodic":
            due = (k + 1) % self.every == self.offset % self.every
        else:
            due = self.fired and k - self.last >= self.min_gap
        if not due or k == 0:
            return smap
        self.fired = False
        self.last = k
        t0 = time.process_time()
        smap = self.relinearize(smap, run)
        dt = time.process_time() - t0
        s = self.stats
        s.count += 1
        s.total_s += dt
        s.worst_s = max(s.worst_s, dt)
        s.steps.append(k + 1)
        return smap

    # ----------------------------------------------------------------------------------
    def _initial(self, smap: Any, run: RunResult, graph_keys: set[int]) -> gtsam.Values:
        anchor = f"x{self.p.steps[0][0]}"
        vals = gtsam.Values()
        for key in graph_keys:
            sym = gtsam.Symbol(key)
            idx, is_lm = int(sym.index()), sym.chr() == ord("l")
            name = f"l{idx}" if is_lm else f"x{idx}"
            if key == self.anchor:
                mean = np.array([0, 0, 0, 1.0, 0, 0, 0])
            elif name in smap:
                mean = smap.marginal(anchor, name)[0]
            elif self.values.exists(key):
                vals.insert(key, self.values.atPoint2(key) if is_lm else (
                    self.values.atPose2(key) if self.p.dim == 2 else self.values.atPose3(key)))
                continue
            else:
                mean = run.pose_means[idx]
            if is_lm:
                vals.insert(key, gtsam.Point2(mean[0], mean[1]))
            elif self.p.dim == 2:
                vals.insert(key, gtsam.Pose2(mean[0], mean[1], 2.0 * np.arctan2(mean[6], mean[3])))
            else:
                from experiments.baselines.gtsam_slam import pose3_from_row
                vals.insert(key, pose3_from_row(mean))
        return vals

    def relinearize(self, smap: Any, run: RunResult) -> Any:
        """One relinearisation (module docstring); returns the new map."""
        from mcsm import StochasticMap

        graph = gtsam.NonlinearFactorGraph()
        graph.add(anchor_prior(self.p))
        for e, mean, cov in self.inputs:
            graph.add(edge_factor(e, self.p.dim, mean, cov))
        keys = set(graph.keys())
        values = self._initial(smap, run, keys)
        values, iters, _ = gauss_newton(graph, values, self.max_iterations)
        self.stats.iterations.append(iters)
        self.values = values
        anchor = f"x{self.p.steps[0][0]}"
        snap = smap.snapshot()
        comp = next(c for c in snap["components"] if anchor in c["frames"])
        frames = comp["frames"]
        if frames[0] != anchor:
            raise RuntimeError("the anchor is not the component's root")
        kept = [(L(int(f[1:])) if f.startswith("l") else X(int(f[1:]))) for f in frames[1:]]
        dev = joint_samples(graph, values, kept, self.anchor, self.p.dim, smap.n_samples,
                            self.rng)
        edges = np.array(comp["edges"], dtype=np.float64)
        for m, key in enumerate(kept, start=1):
            d = dev[key]
            if gtsam.Symbol(key).chr() == ord("l"):
                edges[m] = point_rows(np.asarray(values.atPoint2(key)) + d)
            elif self.p.dim == 2:
                p = values.atPose2(key)
                edges[m] = planar_rows(pose2_retract(np.array([p.x(), p.y(), p.theta()]), d))
            else:
                from experiments.baselines.gtsam_slam import row_from_pose3
                edges[m] = pose3_retract(row_from_pose3(values.atPose3(key)), d)
        comp["edges"] = edges
        return StochasticMap.from_snapshot(snap, threads=smap.threads)
