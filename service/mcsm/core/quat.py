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


def qmul(p: Array, q: Array) -> Array:
    """Hamilton product ``p q`` of ``(..., 4)`` arrays (broadcasting)."""
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


def qrot(q: Array, v: Array) -> Array:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``: ``R(q) v``."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def qnormalize(q: Array) -> Array:
    """Scale to unit norm. A zero quaternion gives NaN (callers check finiteness)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return q / np.linalg.norm(q, axis=-1, keepdims=True)


def align_hemisphere(q: Array, ref: Array) -> Array:
    """Flip each quaternion onto the hemisphere of ``ref`` (``q·ref >= 0``); broadcasting."""
    dot = np.sum(q * ref, axis=-1, keepdims=True)
    return np.where(dot < 0.0, -q, q)


def mean_rotation(q: Array) -> Array:
    """Chordal mean over the sample axis (-2) of ``(..., N, 4)``: aligned, averaged, normalised.

    Samples are first put on the hemisphere of the first sample, then on that of the first
    mean, so the result does not depend on the signs the samples came with.
    """
    first = q[..., :1, :]
    m = qnormalize(np.mean(align_hemisphere(q, first), axis=-2, keepdims=True))
    m = qnormalize(np.mean(align_hemisphere(q, m), axis=-2, keepdims=True))
    return m[..., 0, :]


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
    return u * np.where(small, series, big)[..., None]


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
