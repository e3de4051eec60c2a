"""Regression guard for full-pose loop closures (issue 8): pose graphs, fixed seeds.

The joint update (square-root analysis, correlation shrink c = 4, inflation 1.002 per loop
closure, tangent space) runs at N = 200 over short simulated 3D and planar graphs with the
default ``gain="direct"``, and over issue 8's acceptance graphs (1000 poses, ~580 loop
closures, seed 8) with ``gain="endpoints"``, the configuration recommended for pose graphs.
The test fails if the absolute trajectory error or the NEES per degree of freedom of the poses
drifts above the acceptance bounds of issue 8 (ATE ≤ 2x GTSAM's batch optimum, NEES/dof ≤ 2)
or above a margin over what the current code measures, and if any value is non-finite. The
figures over many seeds come from ``experiments/pose_graph.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from experiments.pose_graph import (
    ate,
    dead_reckoning,
    gtsam_optimum,
    make_graph,
    nees_per_dof,
    plain_update,
    run_map,
)

pytest.importorskip("mcsm")

# Measured on the current code with these seeds (short 3D: ATE 0.253 m = 1.67x GTSAM, NEES/dof
# 1.52; short planar: ATE 0.170 m = 0.93x GTSAM, NEES/dof 0.65; acceptance 3D with the endpoint
# gain: 0.191 m = 1.57x, NEES/dof 0.86; acceptance planar: 0.156 m = 1.84x, NEES/dof 0.57).
# The bounds leave room for platform rounding and small changes of the core, not for a drift
# of the error or the consistency.
CASES = [
    # scenario, poses, graph seed, map seed, gain, max ATE (m), max NEES/dof
    ("3d", 200, 80120, 80121, "direct", 0.30, 2.0),
    ("2d", 200, 80122, 80123, "direct", 0.21, 1.0),
    ("3d", 1000, 8, 9, "endpoints", 0.22, 1.3),
    ("2d", 1000, 8, 9, "endpoints", 0.168, 0.9),
]


@pytest.mark.parametrize(("scenario", "poses", "seed", "map_seed", "gain", "max_ate", "max_nees"),
                         CASES)
def test_joint_update_on_pose_graphs(scenario, poses, seed, map_seed, gain, max_ate, max_nees):
    from mcsm import StochasticMap

    graph = make_graph(scenario, poses, seed)
    assert graph.n_loops >= 30 if poses < 1000 else graph.n_loops >= 500
    smap = StochasticMap(200, method="joint", space="tangent", analysis="ensrf", shrink=4.0,
                         inflation=1.002, gain=gain)
    run = run_map(graph, smap, rng=np.random.default_rng(map_seed), loop_update=plain_update)
    assert run.error == ""
    assert np.isfinite(run.means).all() and np.isfinite(run.covs).all()
    err = ate(run.means, graph.poses_true)
    nees = float(nees_per_dof(run.means[1:], run.covs[1:], graph.poses_true[1:],
                              graph.dof_index).mean())
    assert err < max_ate, f"ATE drifted up: {err:.3f} m"
    assert nees < max_nees, f"NEES/dof drifted up: {nees:.3f}"
    assert err < 0.5 * ate(dead_reckoning(graph), graph.poses_true)
    opt = gtsam_optimum(graph, dead_reckoning(graph))
    if opt is not None:
        assert err <= 2.0 * ate(opt, graph.poses_true)  # issue 8's acceptance bound


def test_ate_ignores_a_rigid_motion_and_nees_is_one_for_honest_covariances():
    from experiments.posegraph_sim import compose, perturb, qexp, simulate_3d

    rng = np.random.default_rng(80128)
    graph = simulate_3d(300, rng=rng)
    truth = graph.poses_true
    motion = np.concatenate([[3.0, -1.0, 2.0], qexp(np.array([0.3, -0.2, 1.1]))])
    moved = compose(np.broadcast_to(motion, truth.shape), truth)
    assert ate(moved, truth) < 1e-9
    # estimates = truth perturbed by their own stated covariance: NEES/dof averages to 1
    n = 4000
    cov = np.diag([0.04, 0.01, 0.09, 0.0004, 0.0009, 0.0001])
    est = np.repeat(truth[5:6], n, axis=0)
    delta = rng.multivariate_normal(np.zeros(6), cov, size=n)
    means = perturb(est, -delta)  # truth = mean ⊞ delta, to first order
    per = nees_per_dof(means, np.broadcast_to(cov, (n, 6, 6)), est, np.arange(6))
    # NEES/dof of one pose is chi2(6)/6: spread sqrt(2/6)
    assert abs(per.mean() - 1.0) < 4.0 * np.sqrt(2.0 / 6.0) / np.sqrt(n) + 0.01


def test_sphere2500_reader_matches_ground_truth_and_its_noise():
    datasets = pytest.importorskip("mcsm_client.datasets")
    from experiments.pose_graph import read_toro3d
    from experiments.posegraph_sim import qlog, qmul, relative

    data = datasets.gtsam_data_dir()
    if data is None or not (data / "sphere2500_groundtruth.txt").is_file():
        pytest.skip("gtsam's Data folder is not installed")
    g = read_toro3d(data / "sphere2500.txt", data / "sphere2500_groundtruth.txt")
    assert (g.n_poses, g.n_loops) == (2500, 2450)
    truth_rel = relative(g.poses_true[g.edges[:, 0]], g.poses_true[g.edges[:, 1]])
    q_inv = truth_rel[:, 3:] * np.array([1.0, -1.0, -1.0, -1.0])
    res = np.concatenate([g.measurements[:, :3] - truth_rel[:, :3],
                          qlog(qmul(q_inv, g.measurements[:, 3:]))], axis=1)
    # the covariance we read (1 / diag² of the file's numbers) is the noise the data has
    stated = np.sqrt(np.diag(g.covariances[0]))
    n = len(res)
    np.testing.assert_allclose(res.std(axis=0), stated, rtol=4.0 / np.sqrt(2.0 * n) + 0.02)
