"""Tests of the seeded pose-graph simulator (experiments/posegraph_sim.py, issue 8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from experiments.posegraph_sim import (
    PoseGraph,
    compose,
    dead_reckoning,
    from_constraints,
    invert,
    qlog,
    qmul,
    relative,
    sample_measurement,
    simulate_2d,
    simulate_3d,
    write_g2o,
)

IDENTITY = np.array([0, 0, 0, 1.0, 0, 0, 0])


def _residuals(graph: PoseGraph) -> np.ndarray:
    """Tangent noise ``[t_z - t_true, log(q_true^-1 q_z)]`` of every measurement."""
    true_rel = relative(graph.poses_true[graph.edges[:, 0]], graph.poses_true[graph.edges[:, 1]])
    q_inv = true_rel[:, 3:] * np.array([1.0, -1.0, -1.0, -1.0])
    return np.concatenate([graph.measurements[:, :3] - true_rel[:, :3],
                           qlog(qmul(q_inv, graph.measurements[:, 3:]))], axis=1)


@pytest.mark.parametrize("sim", [simulate_3d, simulate_2d])
def test_same_seed_same_graph_and_structure(sim):
    a = sim(400, rng=np.random.default_rng(80101))
    b = sim(400, rng=np.random.default_rng(80101))
    for name in ("poses_true", "edges", "measurements", "covariances", "is_loop"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(a.poses_true[0], IDENTITY)
    np.testing.assert_allclose(np.linalg.norm(a.poses_true[:, 3:], axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(a.measurements[:, 3:], axis=1), 1.0, atol=1e-12)
    odo = a.edges[~a.is_loop]
    np.testing.assert_array_equal(odo[:, 1] - odo[:, 0], 1)
    assert len(odo) == a.n_poses - 1
    loops = a.edges[a.is_loop]
    assert a.n_loops > 50
    assert np.all(loops[:, 1] - loops[:, 0] >= a.settings["min_gap"])
    # arrival order: by target pose, odometry into a pose before the loop closures ending there
    assert np.all(np.diff(a.edges[:, 1]) >= 0)
    assert [c.kind for c in a.constraints()].count("loop") == a.n_loops


def test_acceptance_sizes_are_reached():
    g3 = simulate_3d(1200, rng=np.random.default_rng(80102))
    g2 = simulate_2d(1200, rng=np.random.default_rng(80103))
    assert g3.n_poses >= 1000 and g3.n_loops >= 500
    assert g2.n_poses >= 1000 and g2.n_loops >= 500


def test_3d_path_moves_all_six_degrees_of_freedom():
    g = simulate_3d(600, rng=np.random.default_rng(80104))
    rot = qlog(g.poses_true[:, 3:])
    assert np.ptp(g.poses_true[:, 2]) > 1.0  # climbs
    assert np.all(np.ptp(rot, axis=0) > 0.1)  # roll, pitch and yaw all vary
    # revisits: loop closures join poses that are truly close
    loops = g.edges[g.is_loop]
    d = np.linalg.norm(g.poses_true[loops[:, 0], :3] - g.poses_true[loops[:, 1], :3], axis=1)
    assert np.all(d < g.settings["loop_radius_m"])


def test_planar_graph_stays_planar():
    g = simulate_2d(500, rng=np.random.default_rng(80105))
    for x in (g.poses_true, g.measurements, dead_reckoning(g)):
        np.testing.assert_array_equal(x[:, [2, 4, 5]], 0.0)
    assert g.dof == 3
    np.testing.assert_array_equal(np.diag(g.covariances[0])[[2, 3, 4]], 0.0)


@pytest.mark.parametrize("planar", [False, True])
def test_measurement_noise_has_the_stated_covariance(planar):
    sim = simulate_2d if planar else simulate_3d
    g = sim(3000, rng=np.random.default_rng(80106 + planar))
    res = _residuals(g)
    for loop in (False, True):
        sel = res[g.is_loop == loop]
        cov = g.covariances[g.is_loop == loop][0]
        n = len(sel)
        var = np.diag(cov)
        got = np.mean(sel**2, axis=0)
        # sample variance of a zero-mean Gaussian: spread sqrt(2) var / sqrt(n)
        tol = 4.0 * np.sqrt(2.0) * var / np.sqrt(n)
        np.testing.assert_array_less(np.abs(got - var), tol + 1e-15)
        np.testing.assert_array_less(np.abs(sel.mean(0)), 4.0 * np.sqrt(var / n) + 1e-15)


def test_noise_free_graph_dead_reckons_to_truth():
    g = simulate_3d(300, rng=np.random.default_rng(80108), sigma_odo_t_m=0.0,
                    sigma_odo_r_rad=0.0, sigma_loop_t_m=0.0, sigma_loop_r_rad=0.0)
    dr = dead_reckoning(g)
    np.testing.assert_allclose(dr[:, :3], g.poses_true[:, :3], atol=1e-9)
    for (i, j), z in zip(g.edges, g.measurements, strict=True):
        np.testing.assert_allclose(compose(g.poses_true[i], z)[:3], g.poses_true[j, :3],
                                   atol=1e-9)


def test_sample_measurement_matches_mean_and_covariance():
    rng = np.random.default_rng(80109)
    z = compose(IDENTITY, np.array([1.0, -2.0, 0.5, 0.8, 0.2, -0.5, 0.26]))
    z[3:] /= np.linalg.norm(z[3:])
    cov = np.diag([0.04, 0.09, 0.01, 0.0004, 0.0009, 0.0001])
    n = 20000
    x = sample_measurement(z, cov, n, rng=rng)
    dev = np.concatenate([x[:, :3] - z[:3],
                          qlog(qmul(invert(z)[3:][None], x[:, 3:]))], axis=1)
    sd = np.sqrt(np.diag(cov))
    np.testing.assert_array_less(np.abs(dev.mean(0)), 4.0 * sd / np.sqrt(n))
    emp = dev.T @ dev / n
    spread = np.sqrt(cov**2 + np.outer(np.diag(cov), np.diag(cov)))
    np.testing.assert_array_less(np.abs(emp - cov), 4.0 * spread / np.sqrt(n) + 1e-15)


def test_own_transform_helpers_follow_the_cores_conventions():
    # The simulator keeps its own SE(3) helpers so that ground truth does not depend on the code
    # it judges; this pins them to the core's conventions (layout, Hamilton product, frames).
    from mcsm.core import compound as core_compound
    from mcsm.core import invert as core_invert

    rng = np.random.default_rng(80111)
    n = 500
    a = np.concatenate([rng.normal(0.0, 3.0, (n, 3)), rng.standard_normal((n, 4))], axis=1)
    b = np.concatenate([rng.normal(0.0, 3.0, (n, 3)), rng.standard_normal((n, 4))], axis=1)
    a[:, 3:] /= np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
    b[:, 3:] /= np.linalg.norm(b[:, 3:], axis=1, keepdims=True)

    def same_pose(x: np.ndarray, y: np.ndarray) -> None:
        np.testing.assert_allclose(x[:, :3], y[:, :3], atol=1e-12)
        # q and -q are one rotation
        np.testing.assert_allclose(np.abs(np.sum(x[:, 3:] * y[:, 3:], axis=1)), 1.0, atol=1e-12)

    same_pose(compose(a, b), core_compound(a, b))
    same_pose(invert(a), core_invert(a))
    same_pose(relative(a, b), core_compound(core_invert(a), b))


@pytest.mark.parametrize("planar", [False, True])
def test_g2o_round_trip_through_the_clients_reader(tmp_path: Path, planar: bool):
    datasets = pytest.importorskip("mcsm_client.datasets")
    sim = simulate_2d if planar else simulate_3d
    g = sim(300, rng=np.random.default_rng(80110 + planar))
    truth_path = write_g2o(g, tmp_path / "sim.g2o")
    ds = datasets.read_dataset(tmp_path / "sim.g2o")
    truth = datasets.read_dataset(truth_path)
    assert ds.dim == (2 if planar else 3)
    back = from_constraints(ds.constraints, planar=planar)
    np.testing.assert_array_equal(back.edges, g.edges)
    np.testing.assert_array_equal(back.is_loop, g.is_loop)
    # quaternion sign is free: compare the rotation through the relative rotation angle
    np.testing.assert_allclose(back.measurements[:, :3], g.measurements[:, :3], atol=1e-12)
    dq = qmul(back.measurements[:, 3:] * np.array([1.0, -1, -1, -1]), g.measurements[:, 3:])
    np.testing.assert_allclose(np.linalg.norm(qlog(dq), axis=1), 0.0, atol=1e-7)
    np.testing.assert_allclose(back.covariances, g.covariances, rtol=1e-9, atol=1e-15)
    assert len(truth.initial) == g.n_poses
    pos = np.array([truth.initial[k][:2] for k in range(g.n_poses)])
    np.testing.assert_allclose(pos, g.poses_true[:, :2], atol=1e-12)
