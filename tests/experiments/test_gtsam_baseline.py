"""The GTSAM baseline solves the problem it is given (experiments/baselines/gtsam_slam.py).

With known headings (σ_θ = 0, as in the paper's Fig. 4) planar landmark SLAM is linear in the
positions, so the batch optimum must equal the closed-form weighted least squares.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from experiments.baselines import gtsam_slam as gs  # noqa: E402


def _rot(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _tiny_problem(rng: np.random.Generator) -> tuple[gs.PlanarProblem, np.ndarray]:
    """Six poses on an arc, four landmarks, exact headings, noisy positions."""
    n_poses, n_landmarks = 6, 4
    headings = np.linspace(0.0, 1.5, n_poses)
    truth = np.zeros((n_poses, 3))
    truth[:, 2] = headings
    for k in range(1, n_poses):
        truth[k, :2] = truth[k - 1, :2] + _rot(headings[k - 1]) @ np.array([1.0, 0.2])
    landmarks = rng.uniform(-2.0, 4.0, size=(n_landmarks, 2))
    cov_odo = np.diag([0.01**2, 0.002**2, 0.0])
    cov_z = np.diag([0.4**2, 0.3**2])
    steps = []
    for k in range(n_poses):
        odo = None
        if k > 0:
            dxy = _rot(headings[k - 1]).T @ (truth[k, :2] - truth[k - 1, :2])
            dxy = dxy + rng.normal(0.0, [0.01, 0.002])
            delta = np.array([dxy[0], dxy[1], headings[k] - headings[k - 1]])
            odo = gs.Odometry2D(k - 1, k, delta, cov_odo)
        sightings = tuple(
            gs.Sighting2D(
                k,
                j,
                _rot(headings[k]).T @ (landmarks[j] - truth[k, :2]) + rng.normal(0.0, [0.4, 0.3]),
                cov_z,
            )
            for j in range(n_landmarks)
            if (k + j) % 2 == 0 or k == j
        )
        steps.append(gs.Step2D(k, odo, sightings))
    return gs.PlanarProblem(steps, truth[0].copy()), headings


def _closed_form(problem: gs.PlanarProblem, headings: np.ndarray) -> np.ndarray:
    """Weighted least squares over positions with headings known; returns landmark positions."""
    n_poses = len(problem.steps)
    landmark_ids = sorted({s.landmark for st in problem.steps for s in st.sightings})
    col = {("p", k): 2 * (k - 1) for k in range(1, n_poses)}
    base = 2 * (n_poses - 1)
    col.update({("l", j): base + 2 * n for n, j in enumerate(landmark_ids)})
    rows, rhs, weights = [], [], []
    p0 = problem.first_pose[:2]

    def add(terms: list[tuple[tuple[str, int], float]], value: np.ndarray, cov: np.ndarray) -> None:
        a = np.zeros((2, base + 2 * len(landmark_ids)))
        v = value.copy()
        for key, sign in terms:
            if key == ("p", 0):
                v = v - sign * p0
            else:
                a[:, col[key] : col[key] + 2] += sign * np.eye(2)
        rows.append(a)
        rhs.append(v)
        weights.append(np.linalg.inv(cov))

    for step in problem.steps:
        k = step.pose
        if step.odometry is not None:
            r = _rot(headings[k - 1])
            cov = r @ step.odometry.cov[:2, :2] @ r.T
            add([(("p", k), 1.0), (("p", k - 1), -1.0)], r @ step.odometry.delta[:2], cov)
        for s in step.sightings:
            r = _rot(headings[k])
            add([(("l", s.landmark), 1.0), (("p", k), -1.0)], r @ s.xy, r @ s.cov @ r.T)
    a = np.vstack(rows)
    b = np.concatenate(rhs)
    w = np.zeros((len(b), len(b)))
    for n, wn in enumerate(weights):
        w[2 * n : 2 * n + 2, 2 * n : 2 * n + 2] = wn
    x = np.linalg.solve(a.T @ w @ a, a.T @ w @ b)
    return np.stack([x[col[("l", j)] : col[("l", j)] + 2] for j in landmark_ids])


def test_batch_optimum_equals_closed_form_least_squares() -> None:
    rng = np.random.default_rng(20120137)
    problem, headings = _tiny_problem(rng)
    graph, initial = gs.build_graph_2d(problem)
    result = gs.batch_optimum(graph, initial)
    ids = sorted({s.landmark for st in problem.steps for s in st.sightings})
    got = np.stack([gs.landmark_positions(result, ids)[j] for j in ids])
    want = _closed_form(problem, headings)
    np.testing.assert_allclose(got, want, atol=1e-6)


def test_a_robust_kernel_on_the_sightings_resists_one_wrong_sighting() -> None:
    """With a sighting moved 8 m (20 sigma), least squares moves its landmark by metres; a
    Huber kernel on the sightings moves it far less; on clean data the two optima are close."""
    rng = np.random.default_rng(20120140)
    problem, _ = _tiny_problem(rng)
    ids = sorted({s.landmark for st in problem.steps for s in st.sightings})
    huber = gtsam.noiseModel.mEstimator.Huber.Create(1.345)

    def landmarks(prob: gs.PlanarProblem, kernel: object = None) -> np.ndarray:
        graph, initial = gs.build_graph_2d(prob, kernel)
        opt = gs.batch_optimum(graph, initial)
        return np.stack([gs.landmark_positions(opt, ids)[j] for j in ids])

    clean_ls, clean_huber = landmarks(problem), landmarks(problem, huber)
    assert np.max(np.linalg.norm(clean_ls - clean_huber, axis=1)) < 0.2
    steps = list(problem.steps)
    k = 4
    bad = steps[k].sightings[0]
    moved = gs.Sighting2D(bad.pose, bad.landmark, np.asarray(bad.xy) + [8.0, 0.0], bad.cov)
    steps[k] = gs.Step2D(steps[k].pose, steps[k].odometry, (moved, *steps[k].sightings[1:]))
    wrong = gs.PlanarProblem(steps, problem.first_pose)
    j = ids.index(bad.landmark)
    pulled_ls = np.linalg.norm(landmarks(wrong)[j] - clean_ls[j])
    pulled_huber = np.linalg.norm(landmarks(wrong, huber)[j] - clean_huber[j])
    assert pulled_ls > 1.0
    assert pulled_huber < 0.5 * pulled_ls


def test_isam2_reaches_the_batch_optimum_on_a_linear_problem() -> None:
    rng = np.random.default_rng(20120138)
    problem, _ = _tiny_problem(rng)
    graph, initial = gs.build_graph_2d(problem)
    batch = gs.batch_optimum(graph, initial)
    inc = gs.isam2_incremental(problem, snapshot_steps=[len(problem.steps) - 1])
    ids = sorted({s.landmark for st in problem.steps for s in st.sightings})
    for j in ids:
        np.testing.assert_allclose(
            gs.landmark_positions(inc.estimate, [j])[j],
            gs.landmark_positions(batch, [j])[j],
            atol=1e-6,
        )
    assert inc.step_time_s.shape == (len(problem.steps),)
    assert np.all(inc.step_time_s > 0)


def test_point_factor_jacobians_match_finite_differences() -> None:
    rng = np.random.default_rng(20120139)
    pose = gtsam.Pose2(1.0, -2.0, 0.7)
    point = gtsam.Point2(4.0, 3.0)
    factor = gs.point_factor_2d(gs.X(0), gs.L(0), rng.normal(size=2), np.eye(2) * 0.16)
    values = gtsam.Values()
    values.insert(gs.X(0), pose)
    values.insert(gs.L(0), point)
    lin = factor.linearize(values)
    a_full = np.asarray(lin.jacobian()[0])  # whitened, columns in key order [pose, point]
    a_pose, a_point = a_full[:, :3], a_full[:, 3:]
    whitened0 = factor.whitenedError(values)
    eps = 1e-6
    num_pose = np.zeros((2, 3))
    for d in range(3):
        v = gtsam.Values()
        v.insert(gs.X(0), pose.retract(np.eye(3)[d] * eps))
        v.insert(gs.L(0), point)
        num_pose[:, d] = (factor.whitenedError(v) - whitened0) / eps
    num_point = np.zeros((2, 2))
    for d in range(2):
        v = gtsam.Values()
        v.insert(gs.X(0), pose)
        v.insert(gs.L(0), gtsam.Point2(*(np.asarray(point) + np.eye(2)[d] * eps)))
        num_point[:, d] = (factor.whitenedError(v) - whitened0) / eps
    np.testing.assert_allclose(a_pose, num_pose, atol=1e-4)
    np.testing.assert_allclose(a_point, num_point, atol=1e-4)


def test_scenario_adapter_matches_the_ekf_when_headings_are_exact() -> None:
    """σ_θ = 0: EKF-SLAM is the exact Kalman filter, so its landmark means are the optimum's."""
    from mcsm_client.scenario import PaperScenarioConfig, generate_paper_scenario

    from experiments.baselines.ekf_slam import run_ekf_on_scenario

    config = PaperScenarioConfig(n_iterations=40, n_landmarks=30, p_observe=0.5)
    scenario = generate_paper_scenario(config, np.random.default_rng(20120140))
    ekf = run_ekf_on_scenario(scenario)
    ids, means, covs = ekf.landmark_estimates()
    problem = gs.problem_from_scenario(scenario)
    graph, initial = gs.build_graph_2d(problem)
    result = gs.batch_optimum(graph, initial)
    got = gs.landmark_positions(result, ids)
    np.testing.assert_allclose(np.stack([got[int(j)] for j in ids]), means, atol=1e-6)
    got_cov = gs.landmark_covariances(graph, result, ids)
    np.testing.assert_allclose(np.stack([got_cov[int(j)] for j in ids]), covs, atol=1e-8)
