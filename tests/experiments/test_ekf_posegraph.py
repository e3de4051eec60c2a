"""The exact-covariance pose-graph EKF (issue 8's reference): Jacobians and a short run."""

from __future__ import annotations

import numpy as np
import pytest

from experiments.baselines.ekf_posegraph import (
    boxminus,
    loop_jacobians,
    odometry_jacobians,
    run_ekf_posegraph,
)
from experiments.pose_graph import ate, dead_reckoning, gtsam_optimum, make_graph, nees_per_dof
from experiments.posegraph_sim import compose, perturb, qexp, relative


def _random_pose(rng: np.random.Generator, scale: float = 3.0) -> np.ndarray:
    return np.concatenate([rng.normal(0.0, scale, 3), qexp(rng.normal(0.0, 1.0, 3))])


@pytest.mark.parametrize("seed", [71101, 71102, 71103])
def test_jacobians_match_finite_differences(seed: int) -> None:
    rng = np.random.default_rng(seed)
    x_i, z, x_a, x_b = (_random_pose(rng) for _ in range(4))
    eps = 1e-6
    f, g = odometry_jacobians(x_i, z)
    _, h_a, h_b = loop_jacobians(x_a, x_b)
    x_j = compose(x_i, z)
    h0 = relative(x_a, x_b)
    num_f, num_g, num_a, num_b = (np.empty((6, 6)) for _ in range(4))
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        num_f[:, k] = boxminus(compose(perturb(x_i, d), z), x_j) / eps
        num_g[:, k] = boxminus(compose(x_i, perturb(z, d)), x_j) / eps
        num_a[:, k] = boxminus(relative(perturb(x_a, d), x_b), h0) / eps
        num_b[:, k] = boxminus(relative(x_a, perturb(x_b, d)), h0) / eps
    # pose error convention: [t' − t, log(q⁻¹ q')], so boxminus(p ⊞ δ, p) = δ
    for got, want in ((f, num_f), (g, num_g), (h_a, num_a), (h_b, num_b)):
        np.testing.assert_allclose(got, want, atol=1e-4 * max(1.0, np.abs(want).max()))


def test_ekf_reaches_the_batch_optimum_on_a_short_graph() -> None:
    graph = make_graph("3d", 250, 71104)
    assert graph.n_loops >= 40
    run = run_ekf_posegraph(graph)
    assert np.isfinite(run.means).all() and np.isfinite(run.covs).all()
    err = ate(run.means, graph.poses_true)
    nees = float(nees_per_dof(run.means[1:], run.covs[1:], graph.poses_true[1:],
                              graph.dof_index).mean())
    assert 0.3 < nees < 2.0, nees
    assert err < 0.25 * ate(dead_reckoning(graph), graph.poses_true)
    opt = gtsam_optimum(graph, dead_reckoning(graph))
    if opt is not None:  # the sequential filter is within a few percent of LM here
        assert err <= 1.15 * ate(opt, graph.poses_true), (err, ate(opt, graph.poses_true))


def test_shrink_with_huge_n_is_the_plain_ekf_and_a_small_n_costs_accuracy() -> None:
    graph = make_graph("2d", 200, 71105)
    exact = run_ekf_posegraph(graph)
    huge = run_ekf_posegraph(graph, shrink_n=10**15)
    np.testing.assert_allclose(huge.means, exact.means, atol=1e-9)
    damped = run_ekf_posegraph(graph, shrink_n=50)
    # The Kalman gain minimises the posterior covariance, so damped gains leave more of it
    # (stated by the Joseph form); that covariance stays honest (NEES/dof ~ 1).
    def spread(covs: np.ndarray) -> float:
        return float(np.trace(covs[:, :2, :2], axis1=1, axis2=2).sum())

    assert spread(damped.covs) > 1.2 * spread(exact.covs)
    nees = nees_per_dof(damped.means[1:], damped.covs[1:], graph.poses_true[1:], graph.dof_index)
    assert 0.3 < float(nees.mean()) < 2.0


def test_out_of_order_odometry_is_refused() -> None:
    graph = make_graph("2d", 120, 71106)
    order = np.arange(len(graph.edges))
    order[[0, 1]] = order[[1, 0]]
    shuffled = type(graph)(graph.poses_true, graph.edges[order], graph.measurements[order],
                           graph.covariances[order], graph.is_loop[order], graph.planar,
                           graph.settings)
    with pytest.raises(ValueError, match="out of order"):
        run_ekf_posegraph(shuffled)
