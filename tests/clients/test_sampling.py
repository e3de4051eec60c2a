"""Sampling helpers: moments against their closed forms, layouts, correlation, input errors."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import mean_and_cov
from mcsm.core.quat import qconj, qlog, qmul, qrot
from mcsm_client.sampling import (
    correlated_with,
    planar_cov_to_pose_cov,
    pose_from_planar,
    sample_planar,
    sample_point,
    sample_pose,
)


def _random_spd(rng: np.random.Generator, d: int, scale: float) -> np.ndarray:
    a = rng.standard_normal((d, d)) * scale
    return a @ a.T + np.eye(d) * scale**2 * 0.1


def _cov_tol(c: np.ndarray, n: int) -> np.ndarray:
    """4 sigma of a sample covariance entry: sqrt(c_ij² + c_ii c_jj) / sqrt(n)."""
    d = np.diag(c)
    return 4.0 * np.sqrt(c**2 + np.outer(d, d)) / np.sqrt(n)


def test_sample_pose_moments_match_mean_and_cov() -> None:
    rng = np.random.default_rng(20261122)
    n = 20000
    c = _random_spd(rng, 6, 0.05)
    q = rng.standard_normal(4)
    mean = np.concatenate([[1.0, -2.0, 0.5], q / np.linalg.norm(q)])
    x = sample_pose(mean, c, n_samples=n, rng=rng)
    assert x.shape == (n, 7) and x.dtype == np.float64 and x.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), 1.0, atol=1e-12)
    mu, cov = mean_and_cov(x)
    sd = np.sqrt(np.diag(c))
    assert np.all(np.abs(mu[:3] - mean[:3]) < 4.0 * sd[:3] / np.sqrt(n))
    # rotation of the estimated mean relative to the true mean, in the tangent chart
    dq = qlog(qmul(qconj(mean[3:]), mu[3:]))
    assert np.all(np.abs(dq) < 4.0 * sd[3:] / np.sqrt(n) + 1e-3 * np.max(sd[3:]) ** 2)
    assert np.all(np.abs(cov - c) < _cov_tol(c, n))


def test_body_translation_frame_rotates_the_deviation() -> None:
    rng = np.random.default_rng(20261123)
    n = 20000
    c = np.diag([0.3**2, 0.01**2, 0.0, 0.0, 0.0, 0.0])
    theta = np.pi / 2
    mean = np.array([0.0, 0.0, 0.0, np.cos(theta / 2), 0.0, 0.0, np.sin(theta / 2)])
    x = sample_pose(mean, c, n_samples=n, rng=rng, translation_frame="body")
    _, cov = mean_and_cov(x)
    # body x is parent y after a quarter turn about z
    expected = np.diag([0.01**2, 0.3**2, 0.0, 0.0, 0.0, 0.0])
    assert np.all(np.abs(cov - expected) < _cov_tol(expected, n) + 1e-15)
    # deterministic check of the same statement on one sample
    rng2 = np.random.default_rng(5)
    y = sample_pose(mean, c, n_samples=2, rng=rng2, translation_frame="body")
    rng3 = np.random.default_rng(5)
    z = sample_pose(mean, c, n_samples=2, rng=rng3, translation_frame="parent")
    np.testing.assert_allclose(y[:, :3], qrot(np.broadcast_to(mean[3:], (2, 4)), z[:, :3]),
                               atol=1e-15)


def test_sample_planar_layout_and_moments() -> None:
    rng = np.random.default_rng(20261124)
    n = 20000
    c = np.array([[0.04, 0.01, 0.0], [0.01, 0.09, 0.002], [0.0, 0.002, 0.0025]])
    x = sample_planar([2.0, -1.0, 0.3], c, n_samples=n, rng=rng)
    assert np.all(x[:, 2] == 0.0) and np.all(x[:, 4] == 0.0) and np.all(x[:, 5] == 0.0)
    theta = 2.0 * np.arctan2(x[:, 6], x[:, 3])
    d = np.stack([x[:, 0], x[:, 1], theta], axis=1)
    assert np.all(np.abs(d.mean(axis=0) - [2.0, -1.0, 0.3]) < 4.0 * np.sqrt(np.diag(c) / n))
    assert np.all(np.abs(np.cov(d, rowvar=False) - c) < _cov_tol(c, n))
    np.testing.assert_allclose(pose_from_planar([1.0, 2.0, np.pi]),
                               [1.0, 2.0, 0.0, np.cos(np.pi / 2), 0.0, 0.0, 1.0], atol=1e-15)
    big = planar_cov_to_pose_cov(c)
    assert big[5, 5] == c[2, 2] and big[0, 5] == c[0, 2] and big[2, 2] == 0.0


@pytest.mark.parametrize("dim", [2, 3])
def test_sample_point(dim: int) -> None:
    rng = np.random.default_rng(20261125 + dim)
    n = 20000
    c = _random_spd(rng, dim, 0.4)
    mean = np.arange(1.0, dim + 1.0)
    p = sample_point(mean, c, n_samples=n, rng=rng)
    assert p.shape == (n, 3)
    if dim == 2:
        assert np.all(p[:, 2] == 0.0)
    assert np.all(np.abs(p[:, :dim].mean(axis=0) - mean) < 4.0 * np.sqrt(np.diag(c) / n))
    assert np.all(np.abs(np.cov(p[:, :dim], rowvar=False) - c) < _cov_tol(c, n))


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.9, -0.6])
def test_correlated_with_planar_gives_rho_and_keeps_moments(rho: float) -> None:
    rng = np.random.default_rng(20261130 + int(10 * rho))
    n = 20000
    c = np.diag([0.05**2, 0.01**2, 0.002**2])
    prev = sample_planar([1.0, 0.0, 0.1], c, n_samples=n, rng=rng)
    new = correlated_with(prev, [0.5, 0.2, -0.1], c, rho=rho, rng=rng, planar=True)
    assert new.shape == (n, 7)
    th_p = 2.0 * np.arctan2(prev[:, 6], prev[:, 3])
    th_n = 2.0 * np.arctan2(new[:, 6], new[:, 3])
    tol_r = 4.0 * (1.0 - rho**2) / np.sqrt(n) + 1e-3
    for a, b in ((prev[:, 0], new[:, 0]), (prev[:, 1], new[:, 1]), (th_p, th_n)):
        assert abs(np.corrcoef(a, b)[0, 1] - rho) < tol_r
    d = np.stack([new[:, 0], new[:, 1], th_n], axis=1)
    assert np.all(np.abs(d.mean(axis=0) - [0.5, 0.2, -0.1]) < 4.0 * np.sqrt(np.diag(c) / n))
    assert np.all(np.abs(np.cov(d, rowvar=False) - c) < _cov_tol(c, n))
    # planar structure survives: no z, roll or pitch
    assert np.all(new[:, 2] == 0.0)
    np.testing.assert_allclose(new[:, 4:6], 0.0, atol=1e-15)


def test_correlated_with_point_and_3d() -> None:
    rng = np.random.default_rng(20261140)
    n = 20000
    c2 = np.diag([0.16, 0.25])
    prev = sample_point([3.0, 4.0], c2, n_samples=n, rng=rng)
    new = correlated_with(prev, [3.5, 4.0], c2, rho=0.7, rng=rng)
    assert new.shape == (n, 3) and np.all(new[:, 2] == 0.0)
    for k in range(2):
        assert abs(np.corrcoef(prev[:, k], new[:, k])[0, 1] - 0.7) < 4.0 * 0.51 / np.sqrt(n)
    c6 = _random_spd(rng, 6, 0.03)
    mean = np.array([1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0])
    p6 = sample_pose(mean, c6, n_samples=n, rng=rng)
    n6 = correlated_with(p6, mean, c6, rho=1.0, rng=rng)
    # rho = 1 reproduces the previous draw's (whitened) noise: same samples up to round-off
    np.testing.assert_allclose(n6, p6, atol=5e-3)
    _, cov = mean_and_cov(n6)
    assert np.all(np.abs(cov - c6) < _cov_tol(c6, n))


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda r: sample_pose([0, 0, 0, 1, 0, 0, 0], np.eye(5), n_samples=10, rng=r), "(6, 6)"),
        (lambda r: sample_pose([0, 0, 0, 0, 0, 0, 0], np.eye(6), n_samples=10, rng=r), "zero"),
        (lambda r: sample_planar([0, 0, 0], -np.eye(3), n_samples=10, rng=r), "semi-definite"),
        (lambda r: sample_planar([0, 0, 0], [[1, 2, 0], [0, 1, 0], [0, 0, 1]], n_samples=10,
                                 rng=r), "symmetric"),
        (lambda r: sample_point([0.0, np.nan], np.eye(2), n_samples=10, rng=r), "finite"),
        (lambda r: sample_point([0.0, 0.0], np.eye(2), n_samples=1, rng=r), "n_samples"),
        (lambda r: sample_pose([0, 0, 0, 1, 0, 0, 0], np.eye(6), n_samples=10, rng=r,
                               translation_frame="world"), "translation_frame"),
        (lambda r: correlated_with(np.zeros((10, 7)), [0, 0, 0], np.eye(3), rho=2.0, rng=r,
                                   planar=True), "rho"),
        (lambda r: correlated_with(np.zeros((10, 5)), [0, 0], np.eye(2), rho=0.5, rng=r),
         "previous"),
    ],
)
def test_bad_inputs_raise_value_error(call, match: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=match):
        call(np.random.default_rng(1))


def test_same_seed_same_samples() -> None:
    c = np.diag([0.1, 0.1, 0.01])
    a = sample_planar([1, 2, 0.5], c, n_samples=50, rng=np.random.default_rng(99))
    b = sample_planar([1, 2, 0.5], c, n_samples=50, rng=np.random.default_rng(99))
    assert np.array_equal(a, b)
