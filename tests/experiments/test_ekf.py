"""EKF-SLAM baseline against the closed-form posterior of a linear case (known headings)."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm_client.scenario import PaperScenarioConfig, generate_paper_scenario

from experiments.baselines.ekf_slam import EkfSlam, run_ekf_on_scenario


def _rot(th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s], [s, c]])


def _batch_posterior(odometry: np.ndarray, observations: list, q_xy: np.ndarray,
                     r: np.ndarray) -> tuple[dict, np.ndarray, np.ndarray]:
    """Weighted least squares over p_1..p_T and the landmarks, headings known (p_0 = 0).

    Factors: p_{k+1} − p_k = R(θ_k) u_k (cov R Q Rᵀ); l_j − p_k = R(θ_k) z (cov R Rₗ Rᵀ).
    Returns the index of each unknown, the posterior mean and covariance.
    """
    t = odometry.shape[0]
    theta = np.concatenate([[0.0], np.cumsum(odometry[:, 2])])
    lm_ids = sorted({j for obs in observations for j, _ in obs})
    index = {("p", k): 2 * (k - 1) for k in range(1, t + 1)}
    index.update({("l", j): 2 * t + 2 * i for i, j in enumerate(lm_ids)})
    dim = 2 * t + 2 * len(lm_ids)
    info = np.zeros((dim, dim))
    vec = np.zeros(dim)

    def add(plus: tuple, minus: tuple | None, value: np.ndarray, cov: np.ndarray) -> None:
        w = np.linalg.inv(cov)
        rows = [(index[plus], 1.0)]
        if minus is not None and minus in index:
            rows.append((index[minus], -1.0))
        for ia, sa in rows:
            vec[ia:ia + 2] += sa * w @ value
            for ib, sb in rows:
                info[ia:ia + 2, ib:ib + 2] += sa * sb * w

    for k in range(t):
        rk = _rot(theta[k])
        add(("p", k + 1), ("p", k), rk @ odometry[k, :2], rk @ q_xy @ rk.T)
        r1 = _rot(theta[k + 1])
        for j, xy in observations[k]:
            add(("l", j), ("p", k + 1), r1 @ np.asarray(xy), r1 @ r @ r1.T)
    cov = np.linalg.inv(info)
    return index, cov @ vec, cov


@pytest.mark.parametrize("seed", [20260201, 20260202])
def test_ekf_equals_closed_form_with_known_headings(seed: int) -> None:
    cfg = PaperScenarioConfig(n_iterations=60, n_landmarks=12, steps_per_revolution=40,
                              radius_m=10.0, landmark_band_m=6.0, range_m=15.0, p_observe=0.4,
                              sigma_odometry_m=(0.05, 0.02))
    sc = generate_paper_scenario(cfg, np.random.default_rng(seed))
    assert sc.n_sightings > 30
    ekf = run_ekf_on_scenario(sc)
    index, mean, cov = _batch_posterior(sc.odometry, sc.observations, cfg.odometry_cov[:2, :2],
                                        cfg.laser_cov)
    t = sc.n_iterations
    # Final pose.
    ip = index[("p", t)]
    np.testing.assert_allclose(ekf.pose[:2], mean[ip:ip + 2], atol=1e-9)
    np.testing.assert_allclose(ekf.pose[2], np.sum(sc.odometry[:, 2]), atol=1e-12)
    np.testing.assert_allclose(ekf.pose_cov[:2, :2], cov[ip:ip + 2, ip:ip + 2], atol=1e-10)
    assert ekf.pose_cov[2, 2] == 0.0
    # Landmarks: means, marginals and the joint covariance with the pose.
    ids, means, covs = ekf.landmark_estimates()
    for j, m, c in zip(ids, means, covs, strict=True):
        il = index[("l", int(j))]
        np.testing.assert_allclose(m, mean[il:il + 2], atol=1e-9)
        np.testing.assert_allclose(c, cov[il:il + 2, il:il + 2], atol=1e-10)
    order = [index[("p", t)]] + [index[("l", int(j))] for j in ekf.landmark_ids()]
    sel = np.concatenate([np.arange(i, i + 2) for i in order])
    full = ekf.cov
    keep = np.r_[0, 1, 3:full.shape[0]]
    np.testing.assert_allclose(full[np.ix_(keep, keep)], cov[np.ix_(sel, sel)], atol=1e-10)


def test_ekf_single_sighting_matches_hand_computation() -> None:
    # Pose at the origin with heading known, one step east, then a landmark seen twice.
    q = np.diag([0.04, 0.01, 0.0])
    r = np.diag([0.25, 0.25])
    ekf = EkfSlam(q, r)
    ekf.predict(np.array([1.0, 0.0, np.pi / 2]))
    assert ekf.observe(7, (2.0, 0.0))          # landmark at (1, 2) in the world
    np.testing.assert_allclose(ekf.landmark_estimates()[1][0], [1.0, 2.0], atol=1e-12)
    # The step's noise is in x0's frame (heading 0 before the step): pose cov diag(0.04, 0.01);
    # the sighting's 0.25 is isotropic, so it is unchanged by the 90° heading.
    np.testing.assert_allclose(ekf.landmark_estimates()[2][0], np.diag([0.29, 0.26]),
                               atol=1e-12)
    assert not ekf.observe(7, (2.0, 0.0))
    # A second identical sighting from the same pose: landmark-minus-pose information doubles;
    # the landmark's cov = P_pose + Rₗ / 2.
    np.testing.assert_allclose(ekf.landmark_estimates()[2][0], np.diag([0.165, 0.135]),
                               atol=1e-12)
    assert ekf.state_dim == 5 and 7 in ekf
