"""GTSAM baselines on the same readings and noise model as the stochastic map.

Two references for the evaluation (issue 7):

* the batch optimum: Levenberg-Marquardt on the whole factor graph (the full-SLAM maximum a
  posteriori estimate, our accuracy reference), and
* iSAM2: the incremental smoother, our peer for time per step.

Planar landmark SLAM (the paper's §6 scenario, PAPER §4, and the Victoria Park file) is a
chain of ``Pose2`` odometry ``BetweenFactor`` s plus **Cartesian** point sightings
``z = R(θ_i)ᵀ (l - p_i)`` with a 2x2 covariance. GTSAM's Python wrapper has no pose-to-point
factor, so the sighting is a small :class:`gtsam.CustomFactor` with analytic Jacobians
(``point_factor_2d``). We deliberately do not use ``gtsam.load2D``: it turns Cartesian sightings
into bearing/range factors with invented sigmas (bearing sqrt(c11/10) rad, range sqrt(c11) m, as
if the x-y covariance held at 10 m), which is not the model our map is given.

Pose graphs (2D and 3D) use ``BetweenFactorPose2`` / ``BetweenFactorPose3`` directly.

Keys: pose ``i`` is ``X(i)``, landmark ``j`` is ``L(j)``. gtsam is an optional dependency (the
``eval`` extra); importing this module needs it.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import gtsam
import numpy as np
import numpy.typing as npt
from gtsam.symbol_shorthand import L, X

Array = npt.NDArray[np.float64]

#: Smallest standard deviation handed to GTSAM. The §6 scenario with σ_θ = 0 has exactly known
#: headings; a Gaussian with zero spread has no information form, so such sigmas are floored here.
#: 1e-9 rad over a 100 m lever arm is 1e-7 m, far below every other error in the evaluation.
MIN_SIGMA = 1e-9

#: Tight prior that pins the first pose (the gauge), in (m, m, rad) or (rad x3, m x3).
PRIOR_SIGMA = 1e-9


@dataclass(frozen=True)
class Odometry2D:
    """Relative pose of pose ``j`` in the frame of pose ``i`` with its covariance.

    Parameters
    ----------
    i, j : int
        Pose ids (``j`` is the new pose in an incremental run).
    delta : (3,) float64
        ``(dx, dy, dθ)`` in metres and radians.
    cov : (3, 3) float64
        Covariance of ``delta``.
    additive : bool
        True (the §6 scenario): the noise is added to ``(dx, dy, dθ)`` in the frame of pose
        ``i``; converted with :func:`between_noise_2d`. False (the dataset files, read by
        ``mcsm_client.datasets``): ``cov`` is already over GTSAM's body-frame tangent.
    """

    i: int
    j: int
    delta: Array
    cov: Array
    additive: bool = True


@dataclass(frozen=True)
class Sighting2D:
    """Cartesian position of landmark ``landmark`` in the frame of pose ``pose``.

    Parameters
    ----------
    pose, landmark : int
        Pose id and landmark id (separate key spaces, ``X`` and ``L``).
    xy : (2,) float64
        Observed ``(x, y)`` in the robot frame, metres.
    cov : (2, 2) float64
        Covariance of ``xy``.
    """

    pose: int
    landmark: int
    xy: Array
    cov: Array


@dataclass(frozen=True)
class Step2D:
    """One reading: the odometry that creates a pose (``None`` for the first pose), then sightings.

    Parameters
    ----------
    pose : int
        Id of the pose this step creates.
    odometry : Odometry2D or None
        Odometry into ``pose``; ``None`` only for the first step.
    sightings : tuple of Sighting2D
        Landmarks seen from ``pose``.
    loops : tuple of Odometry2D
        Extra pose-to-pose constraints (loop closures) that end at ``pose``.
    """

    pose: int
    odometry: Odometry2D | None
    sightings: tuple[Sighting2D, ...] = ()
    loops: tuple[Odometry2D, ...] = ()


@dataclass
class PlanarProblem:
    """A planar SLAM run as an ordered list of steps plus the first pose.

    Parameters
    ----------
    steps : list of Step2D
        In time order; ``steps[0].odometry`` is ``None``.
    first_pose : (3,) float64
        ``(x, y, θ)`` of the first pose (pinned with a tight prior).
    """

    steps: list[Step2D]
    first_pose: Array = field(default_factory=lambda: np.zeros(3))


def gaussian(cov: Array) -> gtsam.noiseModel.Base:
    """A GTSAM Gaussian noise model from a covariance, sigmas floored at :data:`MIN_SIGMA`.

    Parameters
    ----------
    cov : (d, d) float64
        Covariance matrix.

    Returns
    -------
    gtsam.noiseModel.Base
        Diagonal model when ``cov`` is diagonal, else a full Gaussian.
    """
    cov = np.asarray(cov, dtype=np.float64)
    diag = np.diag(cov)
    if np.count_nonzero(cov - np.diag(diag)) == 0:
        return gtsam.noiseModel.Diagonal.Sigmas(np.sqrt(np.maximum(diag, MIN_SIGMA**2)))
    floored = cov + np.eye(len(cov)) * MIN_SIGMA**2
    return gtsam.noiseModel.Gaussian.Covariance(floored)


def _odometry_noise(odo: Odometry2D) -> gtsam.noiseModel.Base:
    """Noise model of an odometry or loop edge, by its noise convention."""
    return between_noise_2d(odo.delta, odo.cov) if odo.additive else gaussian(odo.cov)


def between_noise_2d(delta: Array, cov: Array) -> gtsam.noiseModel.Base:
    """Noise model for a ``BetweenFactorPose2`` whose reading has additive noise ``cov``.

    The readings carry additive noise on ``(dx, dy, dθ)`` expressed in the frame of pose ``i``.
    GTSAM's between error is ``Log(z⁻¹ T_i⁻¹ T_j)``, a right (frame ``j``) perturbation; to first
    order (exactly, when the heading noise is zero) an additive ``e`` is ``ξ = J e`` with
    ``J = diag(R(dθ)ᵀ, 1)``, so the covariance handed to GTSAM is ``J cov Jᵀ``.

    Parameters
    ----------
    delta : (3,) float64
        The reading ``(dx, dy, dθ)``.
    cov : (3, 3) float64
        Covariance of the additive noise on the reading.

    Returns
    -------
    gtsam.noiseModel.Base
    """
    c, s = np.cos(delta[2]), np.sin(delta[2])
    jac = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = np.asarray(cov, dtype=np.float64)
    if abs(delta[2]) < 1e-15:
        return gaussian(cov)
    return gaussian(jac @ cov @ jac.T)


def transform_to_2d(pose: Array, point: Array) -> Array:
    """Point in the frame of ``pose``: ``R(θ)ᵀ (point - p)``.

    Parameters
    ----------
    pose : (3,) float64
        ``(x, y, θ)``.
    point : (2,) float64
        World point.

    Returns
    -------
    (2,) float64
    """
    c, s = np.cos(pose[2]), np.sin(pose[2])
    dx, dy = point[0] - pose[0], point[1] - pose[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy])


def point_factor_2d(
    pose_key: int, landmark_key: int, xy: Array, cov: Array, kernel: Any = None
) -> gtsam.CustomFactor:
    """Factor for a Cartesian point sighting ``xy = R(θ)ᵀ (l - p) + noise``.

    The Jacobians are with respect to GTSAM's tangent coordinates: ``Pose2.retract`` perturbs in
    the body frame, ``(v_x, v_y, ω)``, and ``Point2`` by plain addition. With ``h`` the predicted
    sighting: ``∂h/∂v = -I``, ``∂h/∂ω = (h_y, -h_x)``, ``∂h/∂l = R(θ)ᵀ``.

    Parameters
    ----------
    pose_key, landmark_key : int
        GTSAM keys of the observing ``Pose2`` and the ``Point2`` landmark.
    xy : (2,) float64
        Observed point in the robot frame, metres.
    cov : (2, 2) float64
        Sighting covariance.
    kernel : gtsam.noiseModel.mEstimator.Base, optional
        A robust kernel on the whitened residual (Huber, Cauchy); None: least squares.

    Returns
    -------
    gtsam.CustomFactor
    """
    measured = np.asarray(xy, dtype=np.float64).copy()

    def error(
        this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[Array] | None
    ) -> Array:
        pose = values.atPose2(this.keys()[0])
        point = values.atPoint2(this.keys()[1])
        theta = pose.theta()
        c, s = np.cos(theta), np.sin(theta)
        rt = np.array([[c, s], [-s, c]])
        h = rt @ (np.asarray(point) - np.array([pose.x(), pose.y()]))
        if jacobians is not None:
            jacobians[0] = np.array([[-1.0, 0.0, h[1]], [0.0, -1.0, -h[0]]])
            jacobians[1] = rt
        return h - measured

    noise = gaussian(cov)
    if kernel is not None:
        noise = gtsam.noiseModel.Robust.Create(kernel, noise)
    return gtsam.CustomFactor(noise, [pose_key, landmark_key], error)


def compose_2d(pose: Array, delta: Array) -> Array:
    """``pose ⊕ delta`` for planar poses ``(x, y, θ)``, θ wrapped to (-π, π]."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    theta = pose[2] + delta[2]
    return np.array(
        [
            pose[0] + c * delta[0] - s * delta[1],
            pose[1] + s * delta[0] + c * delta[1],
            np.arctan2(np.sin(theta), np.cos(theta)),
        ]
    )


def step_factors(
    step: Step2D,
    estimate: dict[int, Array],
    landmarks: dict[int, Array],
    first_pose: Array,
    kernel: Any = None,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Factors and initial values a step adds; updates the dead-reckoning guesses in place
    (``kernel``: a robust kernel on the point sightings, see :func:`point_factor_2d`)."""
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    if step.odometry is None:
        pose = np.asarray(first_pose, dtype=np.float64)
        graph.add(
            gtsam.PriorFactorPose2(
                X(step.pose),
                gtsam.Pose2(*pose),
                gtsam.noiseModel.Isotropic.Sigma(3, PRIOR_SIGMA),
            )
        )
    else:
        odo = step.odometry
        if odo.j == step.pose:
            pose = compose_2d(estimate[odo.i], odo.delta)
        else:  # edge written from the new pose to a known one (TORO files): invert it
            c, s = np.cos(odo.delta[2]), np.sin(odo.delta[2])
            back = np.array(
                [
                    -c * odo.delta[0] - s * odo.delta[1],
                    s * odo.delta[0] - c * odo.delta[1],
                    -odo.delta[2],
                ]
            )
            pose = compose_2d(estimate[odo.j], back)
        graph.add(
            gtsam.BetweenFactorPose2(
                X(odo.i), X(odo.j), gtsam.Pose2(*odo.delta), _odometry_noise(odo)
            )
        )
    estimate[step.pose] = pose
    values.insert(X(step.pose), gtsam.Pose2(*pose))
    for loop in step.loops:
        graph.add(
            gtsam.BetweenFactorPose2(
                X(loop.i),
                X(loop.j),
                gtsam.Pose2(*loop.delta),
                _odometry_noise(loop),
            )
        )
    for sighting in step.sightings:
        if sighting.landmark not in landmarks:
            c, s = np.cos(pose[2]), np.sin(pose[2])
            guess = pose[:2] + np.array([[c, -s], [s, c]]) @ sighting.xy
            landmarks[sighting.landmark] = guess
            values.insert(L(sighting.landmark), gtsam.Point2(*guess))
        graph.add(
            point_factor_2d(
                X(sighting.pose), L(sighting.landmark), sighting.xy, sighting.cov, kernel
            )
        )
    return graph, values


def build_graph_2d(
    problem: PlanarProblem, kernel: Any = None
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The whole factor graph and a dead-reckoning initial estimate.

    Parameters
    ----------
    problem : PlanarProblem
    kernel : gtsam.noiseModel.mEstimator.Base, optional
        A robust kernel on the point sightings (None: least squares).

    Returns
    -------
    graph : gtsam.NonlinearFactorGraph
        Prior on the first pose, odometry, loop closures and point sightings.
    initial : gtsam.Values
        Poses by composing odometry; landmarks placed from their first sighting.
    """
    graph = gtsam.NonlinearFactorGraph()
    initial = gtsam.Values()
    estimate: dict[int, Array] = {}
    landmarks: dict[int, Array] = {}
    for step in problem.steps:
        g, v = step_factors(step, estimate, landmarks, problem.first_pose, kernel)
        graph.push_back(g)
        initial.insert(v)
    return graph, initial


def batch_optimum(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    *,
    max_iterations: int = 100,
    relative_error_tol: float = 1e-10,
) -> gtsam.Values:
    """Levenberg-Marquardt optimum of ``graph`` from ``initial``.

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
    initial : gtsam.Values
        Starting point (dead reckoning, or an iSAM2 pass where dead reckoning is too far off).
    max_iterations : int
    relative_error_tol : float

    Returns
    -------
    gtsam.Values
    """
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(1e-12)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


@dataclass
class IncrementalResult:
    """Outcome of an iSAM2 pass.

    Attributes
    ----------
    estimate : gtsam.Values
        Final estimate.
    step_time_s : (S,) float64
        CPU time (``time.process_time``) of ``ISAM2.update`` for each step (factor
        construction excluded).
    snapshots : dict
        ``{step index: {landmark id: (2,) position}}`` at the requested steps.
    """

    estimate: gtsam.Values
    step_time_s: Array
    snapshots: dict[int, dict[int, Array]]


def isam2_incremental(
    problem: PlanarProblem,
    *,
    snapshot_steps: Sequence[int] = (),
    relinearize_threshold: float = 0.1,
    relinearize_skip: int = 10,
    extra_updates: int = 0,
) -> IncrementalResult:
    """Run iSAM2 one step at a time and time each update.

    Parameters
    ----------
    problem : PlanarProblem
    snapshot_steps : sequence of int
        Step indices after which the landmark estimates are recorded (for error-vs-iteration
        curves; ``calculateEstimate`` is outside the timed region).
    relinearize_threshold, relinearize_skip : float, int
        iSAM2 relinearisation settings (GTSAM defaults).
    extra_updates : int
        Extra empty ``update()`` calls after the last step (more relinearisation).

    Returns
    -------
    IncrementalResult
    """
    params = gtsam.ISAM2Params()
    params.setRelinearizeThreshold(relinearize_threshold)
    params.relinearizeSkip = relinearize_skip
    isam = gtsam.ISAM2(params)
    estimate: dict[int, Array] = {}
    landmarks: dict[int, Array] = {}
    times = np.empty(len(problem.steps))
    wanted = set(snapshot_steps)
    snapshots: dict[int, dict[int, Array]] = {}
    for k, step in enumerate(problem.steps):
        graph, values = step_factors(step, estimate, landmarks, problem.first_pose)
        t0 = time.process_time()
        isam.update(graph, values)
        times[k] = time.process_time() - t0
        # Initial guesses for the next pose and new landmarks start from the current estimate of
        # this pose (not from dead reckoning), as an incremental user would do; untimed.
        last = isam.calculateEstimatePose2(X(step.pose))
        estimate[step.pose] = np.array([last.x(), last.y(), last.theta()])
        if k in wanted:
            snapshots[k] = landmark_positions(isam.calculateEstimate(), landmarks)
    for _ in range(extra_updates):
        isam.update()
    return IncrementalResult(isam.calculateEstimate(), times, snapshots)


def landmark_positions(
    values: gtsam.Values, ids: dict[int, Array] | Sequence[int]
) -> dict[int, Array]:
    """Landmark ``L(j)`` positions from ``values``.

    Parameters
    ----------
    values : gtsam.Values
    ids : iterable of int
        Landmark ids.

    Returns
    -------
    dict
        ``{j: (2,) or (3,) float64}``.
    """
    out: dict[int, Array] = {}
    for j in ids:
        out[int(j)] = np.asarray(values.atPoint2(L(int(j))), dtype=np.float64)
    return out


def pose_array_2d(values: gtsam.Values, ids: Sequence[int]) -> Array:
    """Planar poses ``X(i)`` as an ``(n, 3)`` array ``(x, y, θ)``."""
    out = np.empty((len(ids), 3))
    for k, i in enumerate(ids):
        p = values.atPose2(X(int(i)))
        out[k] = (p.x(), p.y(), p.theta())
    return out


def landmark_covariances(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values, ids: Sequence[int]
) -> dict[int, Array]:
    """Marginal covariances of the landmarks at the optimum (for NEES).

    Parameters
    ----------
    graph : gtsam.NonlinearFactorGraph
    values : gtsam.Values
        Linearisation point (the optimum).
    ids : sequence of int

    Returns
    -------
    dict
        ``{j: (2, 2) float64}``.
    """
    marginals = gtsam.Marginals(graph, values)
    return {int(j): np.asarray(marginals.marginalCovariance(L(int(j)))) for j in ids}


# --- adapters from the project's data sources -------------------------------------------------


def problem_from_scenario(scenario: Any, n_iterations: int | None = None) -> PlanarProblem:
    """The §6 scenario (``mcsm_client.scenario.Scenario``) as a :class:`PlanarProblem`.

    Step ``k`` creates pose ``k`` (``x0`` at the origin, no sightings), then pose ``k+1`` from
    ``odometry[k]`` with the sightings ``observations[k]``: the same readings and order as
    ``run_scenario_on_map`` and the EKF. Odometry noise is additive in the previous pose's frame.

    Parameters
    ----------
    scenario : mcsm_client.scenario.Scenario
    n_iterations : int, optional
        Use only the first iterations.

    Returns
    -------
    PlanarProblem
    """
    cfg = scenario.config
    odo_cov = np.asarray(cfg.odometry_cov, dtype=np.float64)
    laser_cov = np.asarray(cfg.laser_cov, dtype=np.float64)
    t_end = (
        scenario.n_iterations if n_iterations is None else min(n_iterations, scenario.n_iterations)
    )
    steps = [Step2D(0, None)]
    for k in range(t_end):
        odo = Odometry2D(k, k + 1, np.asarray(scenario.odometry[k], dtype=np.float64), odo_cov)
        sightings = tuple(
            Sighting2D(k + 1, int(j), np.asarray(xy, dtype=np.float64), laser_cov)
            for j, xy in scenario.observations[k]
        )
        steps.append(Step2D(k + 1, odo, sightings))
    return PlanarProblem(steps, np.asarray(scenario.poses[0], dtype=np.float64).copy())


def problem_from_dataset(dataset: Any, max_poses: int | None = None) -> PlanarProblem:
    """A planar ``mcsm_client.datasets.Dataset`` (Victoria Park, g2o 2D, TORO) as a problem.

    Constraints are taken in file order: an ``"odometry"`` constraint opens a new step (its
    target is the new pose); ``"landmark"`` and ``"loop_closure"`` constraints join the current
    step (they arrive after the pose they end at exists). Covariances are over the body-frame
    tangent, GTSAM's own convention (``additive=False``). The first pose is pinned at the origin.

    Parameters
    ----------
    dataset : mcsm_client.datasets.Dataset
        With ``dim == 2``.
    max_poses : int, optional
        Stop before the odometry constraint that would create pose number ``max_poses + 1``.

    Returns
    -------
    PlanarProblem
    """
    if dataset.dim != 2:
        raise ValueError("problem_from_dataset needs a planar dataset")
    steps: list[Step2D] = []
    first = dataset.constraints[0].source
    current = Step2D(first, None)
    seen = {first}
    pending_s: list[Sighting2D] = []
    pending_l: list[Odometry2D] = []
    n_poses = 1
    for c in dataset.constraints:
        mean = np.asarray(c.mean, dtype=np.float64)
        cov = np.asarray(c.cov, dtype=np.float64)
        if c.kind == "odometry":
            if max_poses is not None and n_poses >= max_poses:
                break
            steps.append(Step2D(current.pose, current.odometry, tuple(pending_s), tuple(pending_l)))
            pending_s, pending_l = [], []
            new_pose = int(c.target) if int(c.source) in seen else int(c.source)
            seen.update((int(c.source), int(c.target)))
            current = Step2D(
                new_pose, Odometry2D(int(c.source), int(c.target), mean, cov, additive=False)
            )
            n_poses += 1
        elif c.kind == "landmark":
            pending_s.append(Sighting2D(int(c.source), int(c.target), mean[:2], cov[:2, :2]))
        else:
            pending_l.append(Odometry2D(int(c.source), int(c.target), mean, cov, additive=False))
    steps.append(Step2D(current.pose, current.odometry, tuple(pending_s), tuple(pending_l)))
    return PlanarProblem(steps, np.zeros(3))


# --- pose graphs -----------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseEdge3D:
    """Relative pose ``T_i^-1 T_j`` with covariance in GTSAM's tangent order (rot, trans).

    Parameters
    ----------
    i, j : int
        Pose ids.
    pose : (7,) float64
        ``x y z qw qx qy qz`` (the map's layout).
    cov : (6, 6) float64
        Covariance in GTSAM order ``[rx ry rz tx ty tz]`` (body-frame perturbation).
    """

    i: int
    j: int
    pose: Array
    cov: Array


def pose3_from_row(row: Array) -> gtsam.Pose3:
    """A ``gtsam.Pose3`` from one ``x y z qw qx qy qz`` row (the quaternion normalised here)."""
    q = np.asarray(row[3:7], dtype=np.float64)
    q = q / np.linalg.norm(q)
    rot = gtsam.Rot3.Quaternion(float(q[0]), float(q[1]), float(q[2]), float(q[3]))
    return gtsam.Pose3(rot, gtsam.Point3(float(row[0]), float(row[1]), float(row[2])))


def row_from_pose3(pose: gtsam.Pose3) -> Array:
    """``x y z qw qx qy qz`` from a ``gtsam.Pose3`` (scalar-first, qw >= 0)."""
    q = pose.rotation().toQuaternion()
    quat = np.array([q.w(), q.x(), q.y(), q.z()])
    if quat[0] < 0:
        quat = -quat
    return np.concatenate([np.asarray(pose.translation(), dtype=np.float64), quat])


def pose_graph_3d(
    edges: Sequence[PoseEdge3D], first_pose: Array, initial: dict[int, Array] | None = None
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """Factor graph of a 3D pose graph pinned at ``first_pose``.

    Parameters
    ----------
    edges : sequence of PoseEdge3D
        Odometry and loop closures; the first edge into each new pose (in order) seeds its
        initial value by composition unless ``initial`` gives it.
    first_pose : (7,) float64
        Pose of the first edge's ``i`` (id taken from ``edges[0].i``).
    initial : dict, optional
        ``{id: (7,) row}`` initial values.

    Returns
    -------
    graph, initial : gtsam.NonlinearFactorGraph, gtsam.Values
    """
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    first = edges[0].i
    graph.add(
        gtsam.PriorFactorPose3(
            X(first), pose3_from_row(first_pose), gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
        )
    )
    poses: dict[int, gtsam.Pose3] = {first: pose3_from_row(first_pose)}
    for e in edges:
        z = pose3_from_row(e.pose)
        graph.add(gtsam.BetweenFactorPose3(X(e.i), X(e.j), z, gaussian(e.cov)))
        if e.j not in poses and e.i in poses:
            if initial is not None and e.j in initial:
                poses[e.j] = pose3_from_row(initial[e.j])
            else:
                poses[e.j] = poses[e.i].compose(z)
    for i, p in poses.items():
        values.insert(X(i), p)
    return graph, values


def pose3_rows(values: gtsam.Values, ids: Sequence[int]) -> Array:
    """Poses ``X(i)`` as ``(n, 7)`` rows ``x y z qw qx qy qz``."""
    return np.stack([row_from_pose3(values.atPose3(X(int(i)))) for i in ids])


def isam2_pose_graph_3d(
    edges: Sequence[PoseEdge3D], first_pose: Array, *, relinearize_skip: int = 10
) -> tuple[gtsam.Values, Array]:
    """iSAM2 over a 3D pose graph, one edge per update, timing each ``update``.

    Parameters
    ----------
    edges : sequence of PoseEdge3D
        In arrival order; an edge whose ``j`` is new introduces that pose.
    first_pose : (7,) float64
    relinearize_skip : int

    Returns
    -------
    estimate : gtsam.Values
    edge_time_s : (E,) float64
        CPU time of each ``ISAM2.update``.
    """
    params = gtsam.ISAM2Params()
    params.relinearizeSkip = relinearize_skip
    isam = gtsam.ISAM2(params)
    first = edges[0].i
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    graph.add(
        gtsam.PriorFactorPose3(
            X(first), pose3_from_row(first_pose), gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
        )
    )
    values.insert(X(first), pose3_from_row(first_pose))
    isam.update(graph, values)
    current: dict[int, gtsam.Pose3] = {first: pose3_from_row(first_pose)}
    times = np.empty(len(edges))
    for k, e in enumerate(edges):
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        z = pose3_from_row(e.pose)
        graph.add(gtsam.BetweenFactorPose3(X(e.i), X(e.j), z, gaussian(e.cov)))
        if e.j not in current:
            base = current[e.i]
            current[e.j] = base.compose(z)
            values.insert(X(e.j), current[e.j])
        t0 = time.process_time()
        isam.update(graph, values)
        times[k] = time.process_time() - t0
    return isam.calculateEstimate(), times
