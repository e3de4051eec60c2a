"""Quaternion kernels on stacked arrays (scalar first: ``w x y z``).

Every function works along the last axis and accepts any leading axes, so one call serves a
single quaternion ``(4,)``, an AT's samples ``(N, 4)`` and a whole component ``(M, N, 4)``.
No Python loops. ``q`` and ``-q`` are the same rotation; functions that need one sign say so.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

# Below this rotation angle (rad) log/exp use their Taylor series: the closed forms divide 0/0.
_SMALL_ANGLE = 1e-6


def _one_set_over_many(small: Array, big: Array) -> bool:
    """True when ``small`` is one sample set ``(..1.., N, k)`` broadcast over a stack
    ``(M.., N, k')`` of at least 16 of them."""
    if small.ndim < 2 or big.ndim < 3:
        return False
    n = small.shape[-2]
    return bool(small.size == n * small.shape[-1] and big.shape[-2] == n
                and big.size >= 16 * n * big.shape[-1])


# qmul(p, q) = L(p) q with L(p)[i, j] = L_SIGN[i, j] * p[L_INDEX[i, j]]
L_INDEX = np.array([[0, 1, 2, 3], [1, 0, 3, 2], [2, 3, 0, 1], [3, 2, 1, 0]])
L_SIGN = np.array([[1, -1, -1, -1], [1, 1, -1, 1], [1, 1, 1, -1], [1, -1, 1, 1]], dtype=float)


def qmul(p: Array, q: Array) -> Array:
    """Hamilton product ``p q`` of ``(..., 4)`` arrays (broadcasting).

    When ``p`` is broadcast over a much larger ``q`` (one AT applied to a whole component),
    the product is one contraction with the precomputed matrices ``L(p)``: far fewer passes
    over the large array than component-wise arithmetic on its strided columns.
    """
    if p.ndim >= 2 and p.shape[-2] == 1 and q.ndim == p.ndim and q.shape[-2] >= 16 and \
            p.shape[:-2] == q.shape[:-2]:
        # one quaternion per sample set (a per-edge reference) times all its samples
        left = p.reshape(-1, 4)[:, L_INDEX] * L_SIGN  # (M, 4, 4)
        per_set: Array = np.einsum("mij,mnj->mni", left, q.reshape(left.shape[0], -1, 4),
                                   optimize=True).reshape(q.shape)
        return per_set
    if _one_set_over_many(p, q):
        left = p.reshape(-1, 4)[:, L_INDEX] * L_SIGN  # (N, 4, 4)
        over_many: Array = np.einsum("nij,mnj->mni", left, q.reshape(-1, p.shape[-2], 4),
                                     optimize=True).reshape(q.shape)
        return over_many
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        (
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ),
        axis=-1,
    )


def qconj(q: Array) -> Array:
    """Conjugate, the inverse of a unit quaternion."""
    out = np.array(q, dtype=np.float64, copy=True)
    out[..., 1:] *= -1.0
    return out


def rotation_matrix(q: Array) -> Array:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)``."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def _cross(a: Array, b: Array) -> Array:
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0), axis=-1)


def qrot(q: Array, v: Array) -> Array:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``: ``R(q) v``.

    A ``q`` broadcast over a much larger ``v`` goes through its rotation matrices (one
    contraction over the large array), as in :func:`qmul`.
    """
    if _one_set_over_many(q, v):
        r = rotation_matrix(q.reshape(-1, 4))  # (N, 3, 3)
        out: Array = np.einsum("nij,mnj->mni", r, v.reshape(-1, q.shape[-2], 3),
                               optimize=True).reshape(v.shape)
        return out
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def qnormalize(q: Array) -> Array:
    """Scale to unit norm. A zero quaternion gives NaN (callers check finiteness)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        out: Array = q / np.linalg.norm(q, axis=-1, keepdims=True)
        return out


def align_hemisphere(q: Array, ref: Array) -> Array:
    """Flip each quaternion onto the hemisphere of ``ref`` (``q·ref >= 0``); broadcasting."""
    q, ref = np.broadcast_arrays(q, ref)
    sign = np.where(np.einsum("...k,...k->...", q, ref) < 0.0, -1.0, 1.0)
    return q * sign[..., None]


def mean_rotation(q: Array) -> Array:
    """Chordal mean over the sample axis (-2) of ``(..., N, 4)``: aligned, averaged, normalised.

    Samples are put on the hemisphere of the first sample first, so the result does not depend
    on the signs the samples came with (for spreads below 90° around the mean).
    """
    m = np.mean(align_hemisphere(q, q[..., :1, :]), axis=-2)
    return qnormalize(m)


def qlog(q: Array) -> Array:
    """Rotation vector ``(..., 3)`` of unit quaternions (angle in [0, pi]); sign-invariant."""
    q = np.where(q[..., :1] < 0.0, -q, q)
    w = q[..., 0]
    u = q[..., 1:]
    n = np.linalg.norm(u, axis=-1)
    small = n < 0.5 * _SMALL_ANGLE
    with np.errstate(invalid="ignore", divide="ignore"):
        big = 2.0 * np.arctan2(n, w) / np.where(small, 1.0, n)
    # series of 2 atan(n/w)/n for small n: 2/w (1 - n²/(3 w²))
    series = 2.0 / w * (1.0 - n * n / (3.0 * w * w))
    out: Array = u * np.where(small, series, big)[..., None]
    return out


def qexp(w: Array) -> Array:
    """Unit quaternion ``(..., 4)`` of rotation vectors ``(..., 3)``; ``qexp(0)`` is exactly 1."""
    theta = np.linalg.norm(w, axis=-1)
    small = theta < _SMALL_ANGLE
    half = 0.5 * theta
    with np.errstate(invalid="ignore", divide="ignore"):
        big = np.sin(half) / np.where(small, 1.0, theta)
    series = 0.5 - theta * theta / 48.0
    s = np.where(small, series, big)
    return np.concatenate((np.cos(half)[..., None], w * s[..., None]), axis=-1)
