"""AT algebra: kernels against a per-sample reference, algebraic laws, merges vs closed forms."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from mcsm import compound, identity, invert, mean_and_cov, merge, merge_correlated
from mcsm.core.quat import qexp, qlog, qmul, qrot
from scipy.spatial.transform import Rotation

from tests.helpers import assert_at_close, gaussian_at, random_at

seeds = st.integers(0, 2**32 - 1)
kinds = st.sampled_from(["uniform", "cloud", "near_identity", "near_pi"])


def _ref_compound(x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Plain per-sample reference with scipy (x y z w order)."""
    out = np.empty_like(x1)
    for i in range(len(x1)):
        r1 = Rotation.from_quat(x1[i, [4, 5, 6, 3]])
        r2 = Rotation.from_quat(x2[i, [4, 5, 6, 3]])
        out[i, :3] = x1[i, :3] + r1.apply(x2[i, :3])
        q = (r1 * r2).as_quat()
        out[i, 3:] = q[[3, 0, 1, 2]]
    return out


def test_compound_matches_per_sample_reference() -> None:
    rng = np.random.default_rng(101)
    a, b = random_at(rng, 50), random_at(rng, 50)
    assert_at_close(compound(a, b), _ref_compound(a, b), atol=1e-12)


def test_rotation_vector_round_trip_and_scipy() -> None:
    rng = np.random.default_rng(102)
    d = rng.standard_normal((200, 3))
    w = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0, 3.1, (200, 1))
    w[:5] *= 1e-9  # series branch
    np.testing.assert_allclose(qlog(qexp(w)), w, atol=1e-12)
    q = qexp(w)
    ref = Rotation.from_rotvec(w).as_matrix()
    v = rng.standard_normal((200, 3))
    np.testing.assert_allclose(qrot(q, v), np.einsum("nij,nj->ni", ref, v), atol=1e-12)
    assert np.array_equal(qexp(np.zeros(3)), [1.0, 0.0, 0.0, 0.0])


@given(seed=seeds, kind=kinds)
def test_compound_is_associative(seed: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    a, b, c = (random_at(rng, 20, kind=kind) for _ in range(3))
    assert_at_close(compound(compound(a, b), c), compound(a, compound(b, c)), atol=1e-10)


@given(seed=seeds, kind=kinds)
def test_invert_is_an_involution(seed: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    a = random_at(rng, 20, kind=kind)
    assert_at_close(invert(invert(a)), a, atol=1e-12)


@given(seed=seeds, kind=kinds)
def test_compound_with_inverse_is_identity_per_sample(seed: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    a = random_at(rng, 20, kind=kind)
    scale = max(1.0, float(np.abs(a[:, :3]).max()))
    assert_at_close(compound(a, invert(a)), identity(20), atol=1e-12 * scale)
    assert_at_close(compound(invert(a), a), identity(20), atol=1e-12 * scale)


@given(seed=seeds, kind=st.sampled_from(["cloud", "near_identity", "near_pi"]),
       space=st.sampled_from(["tangent", "quaternion"]))
def test_merge_correlated_with_itself_changes_nothing(seed: int, kind: str, space: str) -> None:
    rng = np.random.default_rng(seed)
    a = random_at(rng, 50, kind=kind)
    assert_at_close(merge_correlated(a, a, space=space), a, atol=1e-9)  # type: ignore[arg-type]


@given(seed=seeds, space=st.sampled_from(["tangent", "quaternion"]))
def test_quaternion_signs_change_no_result(seed: int, space: str) -> None:
    rng = np.random.default_rng(seed)
    a = random_at(rng, 40, kind="cloud")
    b = random_at(rng, 40, kind="cloud")
    b[:, :3] = a[:, :3] + 0.1 * rng.standard_normal((40, 3))
    b[:, 3:] = qmul(a[:, 3:], qexp(0.02 * rng.standard_normal((40, 3))))
    flip = rng.random(40) < 0.5
    a2, b2 = a.copy(), b.copy()
    a2[flip, 3:] *= -1
    b2[~flip, 3:] *= -1
    assert_at_close(compound(a2, b2), compound(a, b), atol=1e-12)
    assert_at_close(invert(a2), invert(a), atol=1e-12)
    for f in (merge, merge_correlated):
        assert_at_close(f(a2, b2, space=space), f(a, b, space=space), atol=1e-9)  # type: ignore[operator]
    m1, c1 = mean_and_cov(a)
    m2, c2 = mean_and_cov(a2)
    assert_at_close(m1[None], m2[None], atol=1e-12)
    np.testing.assert_allclose(c1, c2, atol=1e-12)


@pytest.mark.parametrize("space", ["tangent", "quaternion"])
def test_merge_of_independent_gaussians_matches_the_product(space: str) -> None:
    """Translation-and-rotation Gaussians with small spread: the merge is the Kalman product."""
    rng = np.random.default_rng(20120137)
    n = 20000
    cov_a = np.diag([0.04, 0.09, 0.01, 1e-4, 4e-4, 2e-4])
    cov_a[0, 1] = cov_a[1, 0] = 0.03
    cov_b = np.diag([0.09, 0.01, 0.04, 4e-4, 1e-4, 1e-4])
    mu_a, mu_b = np.array([1.0, 2.0, 0.5]), np.array([1.2, 1.9, 0.3])
    rv_a, rv_b = np.array([0.0, 0.0, 0.30]), np.array([0.0, 0.01, 0.31])
    a = gaussian_at(rng, n, mu_a, rv_a, cov_a)
    b = gaussian_at(rng, n, mu_b, rv_b, cov_b)
    got_mean, got_cov = mean_and_cov(merge(a, b, space=space))  # type: ignore[arg-type]
    gain = cov_a @ np.linalg.inv(cov_a + cov_b)
    want_cov = cov_a - gain @ cov_a
    # translation block: exact closed form (rotation only enters at second order here)
    want_t = mu_a + gain[:3, :3] @ (mu_b - mu_a)
    tol_t = 4.0 * np.sqrt(np.diag(want_cov)[:3]) / np.sqrt(n) + 2e-3
    assert np.all(np.abs(got_mean[:3] - want_t) < tol_t)
    spread = np.sqrt(want_cov**2 + np.outer(np.diag(want_cov), np.diag(want_cov)))
    assert np.all(np.abs(got_cov - want_cov) < 6.0 * spread / np.sqrt(n) + 1e-6)
    # rotation mean: the product's mean rotation vector, to first order
    dq = qlog(qmul(qexp(-rv_a)[None], got_mean[None, 3:]))[0]
    want_dr = gain[3:, 3:] @ qlog(qmul(qexp(-rv_a), qexp(rv_b))[None])[0]
    assert np.all(np.abs(dq - want_dr) < 4.0 * np.sqrt(np.diag(want_cov)[3:]) / np.sqrt(n) + 1e-3)


def test_merge_correlated_of_independent_inputs_equals_plain_merge_in_the_limit() -> None:
    rng = np.random.default_rng(20120138)
    n = 20000
    a = gaussian_at(rng, n, [0, 0, 0], [0, 0, 0], np.diag([0.04] * 3 + [1e-4] * 3))
    b = gaussian_at(rng, n, [0.2, 0, 0], [0, 0, 0], np.diag([0.04] * 3 + [1e-4] * 3))
    m1, c1 = mean_and_cov(merge(a, b))
    m2, c2 = mean_and_cov(merge_correlated(a, b))
    assert np.all(np.abs(m1[:3] - m2[:3]) < 4 * 0.14 / np.sqrt(n))
    np.testing.assert_allclose(c1, c2, atol=6 * 0.02 / np.sqrt(n))


def test_core_imports_no_io_packages() -> None:
    code = ("import sys, mcsm.core; bad = {'zenoh', 'msgpack', 'mcap'} & set(sys.modules); "
            "print(sorted(bad)); sys.exit(1 if bad else 0)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr
