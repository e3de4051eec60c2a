"""Test helpers, written once: AT generators and a sign-aware comparison.

Generators cover uniform rotations, tangent-normal clouds, near-identity and near-pi angles,
with random quaternion signs, since ``q`` and ``-q`` must give the same results everywhere.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from mcsm.core.quat import qexp, qmul

Array = npt.NDArray[np.float64]


def random_unit_quats(rng: np.random.Generator, n: int) -> Array:
    """Uniformly distributed rotations with random signs."""
    q = rng.standard_normal((n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_at(rng: np.random.Generator, n: int, *, kind: str = "uniform",
              t_scale: float = 3.0, t_sigma: float = 0.2, r_sigma: float = 0.05) -> Array:
    """An ``(n, 7)`` AT. ``kind``: uniform (independent rotations), cloud (a tangent-normal
    cloud around a random mean), near_identity, near_pi (mean rotation of almost 180°)."""
    x = np.empty((n, 7))
    if kind == "uniform":
        x[:, :3] = t_scale * rng.standard_normal((n, 3))
        x[:, 3:] = random_unit_quats(rng, n)
        return x
    if kind == "near_identity":
        mean_q = np.array([1.0, 0.0, 0.0, 0.0])
    elif kind == "near_pi":
        axis = rng.standard_normal(3)
        mean_q = qexp(axis / np.linalg.norm(axis) * (np.pi - 0.01))
    else:
        mean_q = random_unit_quats(rng, 1)[0]
    x[:, :3] = t_scale * rng.standard_normal(3) + t_sigma * rng.standard_normal((n, 3))
    q = qmul(mean_q, qexp(r_sigma * rng.standard_normal((n, 3))))
    signs = rng.choice([-1.0, 1.0], size=(n, 1))
    x[:, 3:] = q * signs
    return x


def gaussian_at(rng: np.random.Generator, n: int, mean_t: Array, mean_rotvec: Array,
                cov6: Array) -> Array:
    """Samples ``[t, q_mean ⊗ exp(δ)]`` with ``[t − mean_t, δ] ~ N(0, cov6)``."""
    d = rng.multivariate_normal(np.zeros(6), cov6, size=n)
    x = np.empty((n, 7))
    x[:, :3] = np.asarray(mean_t) + d[:, :3]
    x[:, 3:] = qmul(qexp(np.asarray(mean_rotvec, dtype=float)), qexp(d[:, 3:]))
    return x


def assert_at_close(got: Array, want: Array, atol: float = 1e-9) -> None:
    """Per-sample equality of ATs, quaternion sign ignored; fails on NaN."""
    assert got.shape == want.shape
    assert np.isfinite(got).all(), "non-finite samples"
    np.testing.assert_allclose(got[..., :3], want[..., :3], atol=atol, rtol=0)
    dot = np.abs(np.sum(got[..., 3:] * want[..., 3:], axis=-1))
    np.testing.assert_allclose(dot, 1.0, atol=atol)
