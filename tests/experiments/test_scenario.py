"""Tests of the §6 scenario generator (clients/mcsm_client/scenario.py): geometry, noise, driver."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from mcsm_client.scenario import (
    PaperScenarioConfig,
    generate_paper_scenario,
    landmark_estimates,
    landmark_nees,
    landmark_rms,
    landmarks_in_frame,
    odometry_samples,
    point_samples,
    run_scenario_on_map,
    se2_compose,
    se2_relative,
    world_to_robot,
)


def test_ground_truth_is_the_circle() -> None:
    cfg = PaperScenarioConfig(n_iterations=700, n_landmarks=50)
    sc = generate_paper_scenario(cfg, np.random.default_rng(20260101))
    assert sc.poses.shape == (701, 3)
    assert sc.landmarks.shape == (50, 2)
    assert sc.odometry.shape == (700, 3)
    assert len(sc.observations) == 700
    np.testing.assert_allclose(sc.poses[0], [0.0, 0.0, 0.0], atol=1e-12)
    # Every pose on the circle of radius 50 around (0, 50), heading tangent (counter-clockwise).
    d = sc.poses[:, :2] - np.array([0.0, 50.0])
    np.testing.assert_allclose(np.hypot(d[:, 0], d[:, 1]), 50.0, rtol=1e-12)
    tangent = np.stack([np.cos(sc.poses[:, 2]), np.sin(sc.poses[:, 2])], axis=-1)
    np.testing.assert_allclose(np.sum(d * tangent, axis=-1), 0.0, atol=1e-9)
    # The first revolution closes at iteration 340.
    np.testing.assert_allclose(sc.poses[340, :2], sc.poses[0, :2], atol=1e-9)
    # True step: chord 2 R sin(π/S) along heading + π/S, heading change 2π/S.
    true_rel = se2_relative(sc.poses[:-1], sc.poses[1:])
    half = np.pi / 340
    chord = 2 * 50.0 * np.sin(half)
    np.testing.assert_allclose(true_rel[:, 0], chord * np.cos(half), rtol=1e-9)
    np.testing.assert_allclose(true_rel[:, 1], chord * np.sin(half), rtol=1e-9)
    np.testing.assert_allclose(true_rel[:, 2], 2 * half, rtol=1e-9)
    # Landmarks within the placement band.
    dl = sc.landmarks - np.array([0.0, 50.0])
    r = np.hypot(dl[:, 0], dl[:, 1])
    assert np.all((r >= 30.0) & (r <= 70.0))


def test_se2_helpers_are_inverse() -> None:
    rng = np.random.default_rng(20260102)
    a = rng.normal(size=(20, 3)) * [10, 10, 3]
    b = rng.normal(size=(20, 3)) * [10, 10, 3]
    back = se2_compose(a, se2_relative(a, b))
    np.testing.assert_allclose(back[:, :2], b[:, :2], atol=1e-12)
    np.testing.assert_allclose(np.cos(back[:, 2] - b[:, 2]), 1.0, atol=1e-12)


def test_same_seed_same_scenario() -> None:
    cfg = PaperScenarioConfig(n_iterations=50, n_landmarks=30, sigma_theta_deg=0.1)
    s1 = generate_paper_scenario(cfg, np.random.default_rng(20260103))
    s2 = generate_paper_scenario(cfg, np.random.default_rng(20260103))
    np.testing.assert_array_equal(s1.odometry, s2.odometry)
    np.testing.assert_array_equal(s1.landmarks, s2.landmarks)
    assert s1.observations == s2.observations


@pytest.mark.parametrize("sigma_theta_deg", [0.0, 0.1])
def test_odometry_noise_statistics(sigma_theta_deg: float) -> None:
    t = 6000
    cfg = PaperScenarioConfig(n_iterations=t, n_landmarks=0, sigma_theta_deg=sigma_theta_deg)
    sc = generate_paper_scenario(cfg, np.random.default_rng(20260104 + int(sigma_theta_deg * 10)))
    noise = sc.odometry - se2_relative(sc.poses[:-1], sc.poses[1:])
    sigma = np.array([0.01, 0.002, np.deg2rad(sigma_theta_deg)])
    if sigma_theta_deg == 0.0:
        np.testing.assert_array_equal(noise[:, 2], 0.0)
    k = 3 if sigma_theta_deg > 0 else 2
    assert np.all(np.abs(noise[:, :k].mean(axis=0)) < 4 * sigma[:k] / np.sqrt(t))
    # The sample standard deviation of a Gaussian has spread σ / sqrt(2 T).
    assert np.all(np.abs(noise[:, :k].std(axis=0) - sigma[:k]) < 4 * sigma[:k] / np.sqrt(2 * t))


def test_sightings_visibility_rate_and_noise() -> None:
    cfg = PaperScenarioConfig(n_iterations=1500)
    sc = generate_paper_scenario(cfg, np.random.default_rng(20260105))
    errors = []
    n_visible = 0
    n_seen = 0
    for k, obs in enumerate(sc.observations):
        local = world_to_robot(sc.poses[k + 1], sc.landmarks)
        dist = np.hypot(local[:, 0], local[:, 1])
        vis = (dist <= 30.0) & (local[:, 0] >= 0.0)
        n_visible += int(vis.sum())
        ids = [j for j, _ in obs]
        assert len(set(ids)) == len(ids)
        assert all(vis[j] for j in ids)
        n_seen += len(ids)
        errors.extend(np.asarray(xy) - local[j] for j, xy in obs)
    p_hat = n_seen / n_visible
    assert abs(p_hat - 0.15) < 4 * np.sqrt(0.15 * 0.85 / n_visible)
    err = np.asarray(errors)
    n = err.shape[0]
    assert n > 2000
    assert np.all(np.abs(err.mean(axis=0)) < 4 * 0.4 / np.sqrt(n))
    assert np.all(np.abs(err.std(axis=0) - 0.4) < 4 * 0.4 / np.sqrt(2 * n))
    assert abs(np.corrcoef(err.T)[0, 1]) < 4 / np.sqrt(n)


def test_odometry_samples_layout_and_moments() -> None:
    rng = np.random.default_rng(20260106)
    n = 20000
    reading = np.array([0.9, 0.01, 0.3])
    sig = np.array([0.01, 0.002, 0.05])
    x = odometry_samples(reading, np.diag(sig**2), n, rng)
    assert x.shape == (n, 7) and x.dtype == np.float64 and x.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(x[:, [2, 4, 5]], 0.0)
    theta = 2 * np.arctan2(x[:, 6], x[:, 3])
    draws = np.stack([x[:, 0], x[:, 1], theta], axis=-1)
    assert np.all(np.abs(draws.mean(axis=0) - reading) < 4 * sig / np.sqrt(n))
    assert np.all(np.abs(draws.std(axis=0) - sig) < 4 * sig / np.sqrt(2 * n))
    # Zero heading variance: every sample carries the same rotation.
    y = odometry_samples(reading, np.diag([1e-4, 4e-6, 0.0]), 100, rng)
    np.testing.assert_allclose(2 * np.arctan2(y[:, 6], y[:, 3]), 0.3, atol=1e-14)


def test_point_samples_moments() -> None:
    rng = np.random.default_rng(20260107)
    n = 20000
    p = point_samples((12.0, -3.0), np.diag([0.16, 0.16]), n, rng)
    assert p.shape == (n, 3)
    np.testing.assert_array_equal(p[:, 2], 0.0)
    assert np.all(np.abs(p[:, :2].mean(axis=0) - [12.0, -3.0]) < 4 * 0.4 / np.sqrt(n))
    assert np.all(np.abs(p[:, :2].std(axis=0) - 0.4) < 4 * 0.4 / np.sqrt(2 * n))


def test_nees_of_honest_gaussian_errors_is_one() -> None:
    rng = np.random.default_rng(20260108)
    k = 20000
    a = rng.normal(size=(k, 2, 2))
    covs = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(2)
    truth = rng.normal(size=(k, 2))
    means = truth + np.einsum("kij,kj->ki", np.linalg.cholesky(covs), rng.normal(size=(k, 2)))
    # e^T C^-1 e ~ chi2(2): per dof mean 1, variance 1; averaged over k: spread 1/sqrt(k).
    assert abs(landmark_nees(means, covs, truth) - 1.0) < 4 / np.sqrt(k)
    assert landmark_nees(means, 4 * covs, truth) == pytest.approx(
        landmark_nees(means, covs, truth) / 4)
    assert landmark_rms(np.array([[3.0, 4.0], [0.0, 0.0]]), np.zeros((2, 2))) == pytest.approx(
        np.sqrt(12.5))


class _RecordingMap:
    """A stand-in map that records calls and answers marginals from a table."""

    def __init__(self) -> None:
        self.calls: list[tuple[str, str, str, tuple[int, ...]]] = []
        self.present: set[str] = set()

    def update(self, a: str, b: str, samples: Any, /) -> None:
        self.calls.append(("update", a, b, samples.shape))
        self.present.update((a, b))

    def remove(self, frame: str, /) -> None:
        self.calls.append(("remove", frame, "", ()))
        self.present.discard(frame)

    def marginal(self, a: str, b: str, /) -> tuple[Any, Any]:
        j = int(b[1:])
        mean = np.array([j, -j, 0, 1, 0, 0, 0], dtype=float)
        return mean, np.eye(6) * (j + 1)

    def __contains__(self, frame: object, /) -> bool:
        return frame in self.present


def test_driver_feeds_odometry_then_sightings_and_keeps_x0() -> None:
    cfg = PaperScenarioConfig(n_iterations=30)
    sc = generate_paper_scenario(cfg, np.random.default_rng(20260109))
    m = _RecordingMap()
    seen: list[int] = []
    run_scenario_on_map(sc, m, 16, np.random.default_rng(20260110),
                        callback=lambda k, _m: seen.append(k))
    assert seen == list(range(1, 31))
    it = iter(m.calls)
    for k in range(30):
        assert next(it) == ("update", f"x{k}", f"x{k + 1}", (16, 7))
        for j, _ in sc.observations[k]:
            assert next(it) == ("update", f"x{k + 1}", f"l{j}", (16, 3))
        if k >= 1:
            assert next(it) == ("remove", f"x{k}", "", ())
    assert next(it, None) is None
    assert {f for f in m.present if f.startswith("x")} == {"x0", "x30"}
    ids, means, covs = landmark_estimates(m, range(200))
    expected = sorted({j for obs in sc.observations for j, _ in obs})
    assert ids.tolist() == expected
    np.testing.assert_array_equal(means[:, 0], ids)
    np.testing.assert_array_equal(covs[:, 0, 0], ids + 1)
    np.testing.assert_allclose(landmarks_in_frame(sc, 0), sc.landmarks, atol=1e-12)


def test_estimates_from_a_real_map_match_its_samples() -> None:
    from mcsm import StochasticMap

    cfg = PaperScenarioConfig(n_iterations=40, n_landmarks=30)
    sc = generate_paper_scenario(cfg, np.random.default_rng(20260111))
    m = StochasticMap(64)
    run_scenario_on_map(sc, m, 64, np.random.default_rng(20260112))
    assert [f for f in m.frames() if f.startswith("x")] == ["x0", "x40"]
    ids, means, covs = landmark_estimates(m, range(30))
    assert ids.size > 0
    for j, mean, cov in zip(ids, means, covs, strict=True):
        xy = m.query("x0", f"l{j}")[:, :2]
        np.testing.assert_allclose(mean, xy.mean(axis=0), atol=1e-9)
        np.testing.assert_allclose(cov, np.cov(xy.T), rtol=1e-9, atol=1e-12)
