"""GTSAM side of the real-data benchmark: factors of a :class:`~experiments.realdata_data.Problem`,
iSAM2 step by step with one joint marginal per step, and the batch Levenberg-Marquardt optimum.

Keys: pose ``i`` is ``X(i)``, landmark ``j`` is ``L(j)``; the anchor (the first step's pose) is
pinned at the identity by a prior of sigma 1e-9. Planar poses: ``BetweenFactorPose2``; 3-D:
``BetweenFactorPose3`` with the covariance permuted to GTSAM's (rotation, translation) order;
Cartesian sightings: :func:`experiments.baselines.gtsam_slam.point_factor_2d` (a Python
``CustomFactor``: GTSAM's wrapper has no pose-to-point factor, so iSAM2 calls back into Python
for every sighting and its Victoria Park times are an upper bound for GTSAM in C++).

An edge may be given another mean (``means[k]``, the k-th edge in arrival order): the sample
means a map was fed, so that iSAM2 sees the same numbers (realdata.md: a map fed sampled inputs
cannot get below 2-10 cm of the file's optimum; fed the same means, iSAM2 has the same floor).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt
from gtsam.symbol_shorthand import L, X

from experiments.baselines.gtsam_slam import gaussian, point_factor_2d, pose3_from_row
from experiments.realdata_data import Edge, Problem, planar_compose, planar_inverse

Array = npt.NDArray[np.float64]
PRIOR_SIGMA = 1e-9
_PERM = [3, 4, 5, 0, 1, 2]


def edge_factor(e: Edge, dim: int, mean: Array | None = None,
                cov: Array | None = None, cpp_points: bool = False,
                kernel: Any = None) -> gtsam.NonlinearFactor:
    """The factor of one edge (``mean``/``cov`` replace the edge's own when given).

    ``kernel``: a robust kernel (``gtsam.noiseModel.mEstimator``) on a sighting's or loop
    closure's whitened residual; odometry stays least squares.

    ``cpp_points``: a sighting becomes GTSAM's C++ ``BearingRangeFactor2D`` (bearing and range
    of the Cartesian reading, sigmas ``sqrt(c11)/range`` and ``sqrt(c11)``, the first-order
    equivalent of an isotropic Cartesian covariance): a timing proxy for iSAM2 without
    Python callbacks, not the same model.
    """
    z = e.mean if mean is None else mean
    c = e.cov if cov is None else cov
    if e.is_point and cpp_points:
        rng = float(np.hypot(z[0], z[1]))
        sigma = float(np.sqrt(c[0, 0]))
        return gtsam.BearingRangeFactor2D(
            X(e.i), L(e.j), gtsam.Rot2(float(np.arctan2(z[1], z[0]))), rng,
            gtsam.noiseModel.Diagonal.Sigmas(np.array([sigma / max(rng, 1e-3), sigma])))
    robust = kernel is not None and e.kind != "odometry"
    if e.is_point:
        return point_factor_2d(X(e.i), L(e.j), z, c, kernel if robust else None)
    noise = gaussian(c if dim == 2 else np.asarray(c)[np.ix_(_PERM, _PERM)])
    if robust:
        noise = gtsam.noiseModel.Robust.Create(kernel, noise)
    if dim == 2:
        return gtsam.BetweenFactorPose2(X(e.i), X(e.j), gtsam.Pose2(*z), noise)
    return gtsam.BetweenFactorPose3(X(e.i), X(e.j), pose3_from_row(z), noise)


def anchor_prior(problem: Problem) -> gtsam.NonlinearFactor:
    """Prior pinning the anchor at the identity."""
    a = X(problem.steps[0][0])
    if problem.dim == 2:
        return gtsam.PriorFactorPose2(a, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3,
                                                                                     PRIOR_SIGMA))
    return gtsam.PriorFactorPose3(a, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6,
                                                                                 PRIOR_SIGMA))


class Builder:
    """Factors and initial values step by step (initial guesses from a running estimate)."""

    def __init__(self, problem: Problem, means: list[Array] | None = None,
                 cpp_points: bool = False, kernel: Any = None) -> None:
        self.p = problem
        self.means = means
        self.cpp_points = cpp_points
        self.kernel = kernel
        self.k = 0  # edge counter
        self.guess: dict[int, Any] = {}  # pose id -> gtsam pose (latest estimate)
        self.landmarks: set[int] = set()

    def step(self, index: int) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """Factors and new values of step ``index``."""
        pose, edges = self.p.steps[index]
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if index == 0:
            graph.add(anchor_prior(self.p))
            ident = gtsam.Pose2() if self.p.dim == 2 else gtsam.Pose3()
            values.insert(X(pose), ident)
            self.guess[pose] = ident
        for e in edges:
            z = e.mean if self.means is None else self.means[self.k]
            self.k += 1
            graph.add(edge_factor(e, self.p.dim, z, cpp_points=self.cpp_points,
                                  kernel=self.kernel))
            if e.kind == "odometry":
                if self.p.dim == 2:
                    zz = z if e.j == pose else planar_inverse(z)
                    g = self.guess[e.i if e.j == pose else e.j]
                    new = planar_compose(np.array([g.x(), g.y(), g.theta()]), zz)
                    self.guess[pose] = gtsam.Pose2(*new)
                else:
                    zp = pose3_from_row(z)
                    self.guess[pose] = (self.guess[e.i].compose(zp) if e.j == pose
                                        else self.guess[e.j].compose(zp.inverse()))
                values.insert(X(pose), self.guess[pose])
            elif e.is_point and e.j not in self.landmarks:
                g = self.guess[e.i]
                c, s = np.cos(g.theta()), np.sin(g.theta())
                values.insert(L(e.j), gtsam.Point2(g.x() + c * z[0] - s * z[1],
                                                   g.y() + s * z[0] + c * z[1]))
                self.landmarks.add(e.j)
        return graph, values


def whole_graph(problem: Problem, means: list[Array] | None = None, kernel: Any = None
                ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """All factors and a dead-reckoning initial estimate (``kernel``: robust sightings and
    loop closures, :func:`edge_factor`)."""
    b = Builder(problem, means, kernel=kernel)
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for k in range(len(problem.steps)):
        g, v = b.step(k)
        graph.push_back(g)
        values.insert(v)
    return graph, values


def estimates(values: gtsam.Values, problem: Problem, poses: list[int] | None = None,
              landmarks: list[int] | None = None) -> tuple[Array, Array]:
    """Positions of poses ``(P, dim)`` and landmarks ``(K, 2)`` in ``values`` (anchor frame)."""
    poses = [p for p, _ in problem.steps] if poses is None else poses
    if problem.dim == 2:
        pp = np.array([[v.x(), v.y()] for v in (values.atPose2(X(p)) for p in poses)])
    else:
        pp = np.array([np.asarray(values.atPose3(X(p)).translation()) for p in poses])
    lm = np.array([np.asarray(values.atPoint2(L(j))) for j in (landmarks or [])]).reshape(-1, 2)
    return pp.reshape(len(poses), problem.dim), lm


@dataclass
class IsamRun:
    """An iSAM2 pass: CPU time per step (update + estimate of the pair + its joint marginal),
    errors at the checkpoints, the final estimate."""

    estimate: gtsam.Values
    step_s: Array
    checkpoints: dict[int, float] = field(default_factory=dict)
    total_s: float = 0.0
    marginal_s: float = 0.0


def query_pair(problem: Problem, index: int, last_landmark: int | None) -> tuple[int, int]:
    """The keys of the step's joint marginal: current pose with the landmark seen last (bounded
    landmark maps) or with the anchor (pose graphs, and before any sighting)."""
    pose = problem.steps[index][0]
    if last_landmark is not None:
        return X(pose), L(last_landmark)
    return X(pose), X(problem.steps[0][0])


def run_isam2(problem: Problem, *, means: list[Array] | None = None, threshold: float = 0.1,
              skip: int = 10, query: bool = True, checkpoint_every: int = 500,
              error_fn: Callable[[gtsam.Values, int], float] | None = None,
              progress: bool = False, cpp_points: bool = False) -> IsamRun:
    """iSAM2 one step at a time; GTSAM's defaults are ``threshold=0.1, skip=10``.

    The timed step is ``update`` plus, with ``query``, the estimate of the step's pair of
    variables and their ``jointMarginalCovariance`` (what one map ``marginal`` returns).
    ``error_fn(estimate, step)`` is evaluated (untimed) every ``checkpoint_every`` steps and at
    the last step.
    """
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(threshold)
    params.relinearizeSkip = skip
    isam = gtsam.ISAM2(params)
    b = Builder(problem, means, cpp_points)
    n = len(problem.steps)
    times = np.empty(n)
    run = IsamRun(gtsam.Values(), times)
    last_lm: int | None = None
    t_all = time.process_time()
    for k in range(n):
        graph, values = b.step(k)
        for e in problem.steps[k][1]:
            if e.is_point:
                last_lm = e.j
        t0 = time.process_time()
        isam.update(graph, values)
        if query and k > 0:
            a, c = query_pair(problem, k, last_lm if problem.bounded else None)
            tq = time.process_time()
            pose_est = isam.calculateEstimatePose2 if problem.dim == 2 else \
                isam.calculateEstimatePose3
            pose_est(a)
            (isam.calculateEstimatePoint2 if problem.bounded and last_lm is not None
             else pose_est)(c)
            isam.jointMarginalCovariance([a, c]).fullMatrix()
            run.marginal_s += time.process_time() - tq
        times[k] = time.process_time() - t0
        # Guesses for the next poses start from the current estimate (as a user would).
        pose = problem.steps[k][0]
        b.guess[pose] = (isam.calculateEstimatePose2(X(pose)) if problem.dim == 2
                         else isam.calculateEstimatePose3(X(pose)))
        if error_fn is not None and ((k + 1) % checkpoint_every == 0 or k == n - 1):
            run.checkpoints[k + 1] = error_fn(isam.calculateEstimate(), k + 1)
        if progress and (k + 1) % 1000 == 0:
            print(f"      isam2 step {k + 1}/{n} {time.process_time() - t_all:.0f} s", flush=True)
    run.total_s = float(times.sum())
    run.estimate = isam.calculateEstimate()
    return run


def batch_lm(graph: gtsam.NonlinearFactorGraph, init: gtsam.Values,
             max_iterations: int = 100) -> tuple[gtsam.Values, float]:
    """Levenberg-Marquardt from ``init``; the optimum and its CPU seconds."""
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-12)
    t0 = time.process_time()
    out = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    return out, time.process_time() - t0


def trimmed_lm(problem: Problem, graph: gtsam.NonlinearFactorGraph, init: gtsam.Values,
               quantile: float = 0.999, rounds: int = 5
               ) -> tuple[gtsam.Values, list[int], float]:
    """Batch LM without the inputs that are outliers at its own optimum: every sighting and
    loop closure (not odometry) whose chi-square at the optimum exceeds ``quantile`` for its
    dimension (the map's trim rule) is left out and LM runs again from there, until the set
    left out is stable (at most ``rounds`` times). ``graph`` is :func:`whole_graph`'s (the
    anchor prior, then one factor per edge in arrival order). The optimum, the edges left out
    (indices in arrival order) and the CPU seconds."""
    from mcsm.core.gate import chi2_quantile

    edges = [e for _, es in problem.steps for e in es]
    if graph.size() != len(edges) + 1:
        raise ValueError("graph is not whole_graph(problem)'s")
    gated = [k for k, e in enumerate(edges) if e.kind != "odometry"]
    limit = {d: chi2_quantile(quantile, d) for d in {graph.at(k + 1).dim() for k in gated}}
    values, secs = batch_lm(graph, init)
    out: list[int] = []
    for _ in range(rounds):
        bad = [k for k in gated
               if 2.0 * graph.at(k + 1).error(values) > limit[graph.at(k + 1).dim()]]
        if bad == out:
            break
        out = bad
        left, kept = set(out), gtsam.NonlinearFactorGraph()
        for i in range(graph.size()):
            if i - 1 not in left:
                kept.push_back(graph.at(i))
        values, s = batch_lm(kept, values)
        secs += s
    return values, out, secs


HUBER_K = 1.345
"""The Huber kernel's threshold on the whitened residual (GTSAM's and the usual 95 % efficiency
value)."""


def huber_lm(problem: Problem, init: gtsam.Values, k: float = HUBER_K
             ) -> tuple[gtsam.Values, float]:
    """Batch LM with a Huber kernel on every sighting and loop closure (odometry least
    squares), from ``init`` (the least-squares optimum): a robust smoother's optimum, where a
    sighting far off its landmark's other sightings counts linearly, not quadratically. The
    optimum and the CPU seconds."""
    graph, _ = whole_graph(problem, kernel=gtsam.noiseModel.mEstimator.Huber.Create(k))
    return batch_lm(graph, init)


def marginal_covariances(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values,
                         problem: Problem, poses: list[int], landmarks: list[int]
                         ) -> tuple[Array, Array]:
    """Marginal covariances at ``values``: poses ``(P, 6, 6)`` over ``[t (anchor frame), r]``
    (the map's convention; planar rows/columns x, y, yaw filled) and landmarks ``(K, 2, 2)``."""
    m = gtsam.Marginals(graph, values)
    pc = np.zeros((len(poses), 6, 6))
    for k, p in enumerate(poses):
        c = np.asarray(m.marginalCovariance(X(p)))
        if problem.dim == 2:
            th = values.atPose2(X(p)).theta()
            r = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
            idx = [0, 1, 5]
            j = np.eye(3)
            j[:2, :2] = r
            pc[k][np.ix_(idx, idx)] = j @ c @ j.T
        else:
            rot = values.atPose3(X(p)).rotation().matrix()
            c = c[np.ix_(_PERM, _PERM)]  # (t_body, r)
            j = np.eye(6)
            j[:3, :3] = rot
            pc[k] = j @ c @ j.T
    lc = np.array([np.asarray(m.marginalCovariance(L(j))) for j in landmarks]).reshape(-1, 2, 2)
    return pc, lc
