"""Approximate transformations (ATs): ordered Monte Carlo sample sets of rigid transforms.

An AT ``x_t_u`` from frame t to frame u is an ``(N, 7)`` float64 array, columns
``x y z qw qx qy qz``; row i of every AT of one map component is one joint draw (PAPER §1-2),
so nothing here reorders rows. All functions accept leading axes (``(..., N, 7)``).

Linear algebra on sample covariances (PAPER §5: singular covariances are the normal case):
:func:`scaled_pinv` scales every dimension to unit variance, drops dimensions with (numerically)
zero variance, and truncates eigenvalues below ``RTOL`` times the largest. Metres and
quaternion units differ by orders of magnitude; the scaling makes one relative tolerance
meaningful for both.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
import numpy.typing as npt

from mcsm.core.quat import (
    L_INDEX,
    L_SIGN,
    align_hemisphere,
    mean_rotation,
    qconj,
    qlog,
    qmul,
    qnormalize,
    qrot,
    rotation_matrix,
)
from mcsm.errors import InvalidSamples, SampleCountMismatch

Array = npt.NDArray[np.float64]
Space = Literal["tangent", "quaternion"]

#: |‖q‖² − 1| accepted on input before renormalisation.
QUAT_NORM_TOL = 1e-6
#: a variance below this (in the data's own units²) is treated as exactly zero.
ZERO_VARIANCE = 1e-20
#: eigenvalues of a unit-diagonal covariance below RTOL × the largest are truncated.
RTOL = 1e-9


def identity(n_samples: int) -> Array:
    """The identity AT: ``n_samples`` copies of ``(0, 0, 0, 1, 0, 0, 0)``."""
    x = np.zeros((n_samples, 7))
    x[:, 3] = 1.0
    return x


def compound(x_a_b: Array, x_b_c: Array) -> Array:
    """Compound ``x_a_b ⊕ x_b_c`` sample by sample (PAPER §1); broadcasting over leading axes.

    ``t = t_ab + R(q_ab) t_bc``, ``q = q_ab q_bc``.
    """
    q_ab = x_a_b[..., 3:]
    t = x_a_b[..., :3] + qrot(q_ab, x_b_c[..., :3])
    q = qmul(q_ab, x_b_c[..., 3:])
    return np.concatenate((t, q), axis=-1)


def invert(x_a_b: Array) -> Array:
    """Invert ``x_a_b^R`` sample by sample: ``q' = q⁻¹``, ``t' = −R(q)ᵀ t`` (PAPER §1)."""
    q = qconj(x_a_b[..., 3:])
    t = -qrot(q, x_a_b[..., :3])
    return np.concatenate((t, q), axis=-1)


# Rows of [q; −q] (indices 0-3 and 4-7) that make the 4×4 matrices of the Hamilton products
# q* v = L(q*) v and v q = R(q) v, entry by entry (rows 1-3 of R: the vector part).
_CONJ_LEFT = np.array([[0, 1, 2, 3], [5, 0, 3, 6], [6, 7, 0, 1], [7, 2, 5, 0]])
_RIGHT_VEC = np.array([[1, 0, 3, 6], [2, 7, 0, 1], [3, 2, 5, 0]])


def relative(x_r_a: Array, x_r_b: Array) -> Array:
    """``x_r_a^R ⊕ x_r_b`` (the AT a→b from two edges of one star), in one step.

    ``t = vec(q_a* (0, t_b − t_a) q_a)``, ``q = q_a* q_b``; the query of PAPER §3, O(N).
    Works on component rows (contiguous ``(7, N)`` copies) with the products' 4×4 matrices
    gathered per sample: a query is a dozen kernels on length-N rows, and their count is its
    cost (the strided ``(N, 4)`` column arithmetic of :func:`compound` takes about 60).
    """
    shape = np.broadcast_shapes(np.shape(x_r_a), np.shape(x_r_b))
    if len(shape) == 2 and np.shape(x_r_a) == np.shape(x_r_b):  # a query: two (N, 7) edges
        a, b = np.ascontiguousarray(x_r_a.T), np.ascontiguousarray(x_r_b.T)
    else:
        a = np.ascontiguousarray(np.broadcast_to(x_r_a, shape).reshape(-1, 7).T)
        b = np.ascontiguousarray(np.broadcast_to(x_r_b, shape).reshape(-1, 7).T)
    q_pm = np.concatenate((a[3:], -a[3:]))
    conj_left = q_pm[_CONJ_LEFT]  # (4, 4, n): L(q_a*)
    rows = np.empty((7, a.shape[1]))
    half = np.einsum("ijn,jn->in", conj_left[:, 1:], b[:3] - a[:3])  # q_a* (0, d)
    np.einsum("ijn,jn->in", q_pm[_RIGHT_VEC], half, out=rows[:3])  # (q_a* (0, d)) q_a
    np.einsum("ijn,jn->in", conj_left, b[3:], out=rows[3:])
    return rows.T.reshape(shape)


def canonicalize(x: Array, normalize: bool = True) -> Array:
    """Put every AT's quaternion samples on the hemisphere of its own mean (sign flips only,
    exact), after renormalising them unless ``normalize`` is False.

    ``x``: ``(..., N, 7)``. Needed before any linear step in quaternion space (PAPER §5).
    """
    q = qnormalize(x[..., 3:]) if normalize else x[..., 3:]
    ref = mean_rotation(q)[..., None, :]
    out = np.empty_like(x)
    out[..., :3] = x[..., :3]
    out[..., 3:] = align_hemisphere(q, ref)
    return out


def check_samples(x: object, n_samples: int | None, width: int) -> Array:
    """Validate a sample set and return it as a fresh, C-contiguous float64 array.

    Parameters
    ----------
    x : array-like, expected ``(N, width)`` with ``width`` 7 (AT) or 3 (point)
    n_samples : the map's N, or None to accept any N >= 2
    width : 7 or 3

    Raises
    ------
    InvalidSamples, SampleCountMismatch
    """
    if not isinstance(x, np.ndarray):
        raise InvalidSamples(f"expected a numpy array, got {type(x).__name__}")
    if x.dtype.kind != "f":
        raise InvalidSamples(f"expected a floating-point dtype, got {x.dtype}")
    if x.ndim != 2 or x.shape[1] != width:
        raise InvalidSamples(f"expected shape (N, {width}), got {x.shape}")
    if n_samples is not None and x.shape[0] != n_samples:
        raise SampleCountMismatch(n_samples, int(x.shape[0]))
    if x.shape[0] < 2:
        raise InvalidSamples("at least 2 samples are needed")
    a = np.array(x, dtype=np.float64, order="C", copy=True)
    if not np.isfinite(a).all():
        raise InvalidSamples("non-finite values")
    if width == 7:
        q = a[:, 3:]  # |q|² elementwise in a fixed order: the result enters the map's state
        norm2 = q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3]
        off = np.abs(norm2 - 1.0)
        k = int(np.argmax(off))
        if float(off[k]) > QUAT_NORM_TOL:
            raise InvalidSamples(f"the quaternion of sample {k} "
                                 f"{quaternion_problem(float(norm2[k]))}")
        a[:, 3:] /= np.sqrt(norm2)[:, None]
    return a


def quaternion_problem(norm2: float) -> str:
    """Why a quaternion with squared norm ``norm2`` is refused, in words (the core's and the
    wire's one message)."""
    if norm2 == 0.0:
        return "is zero (0, 0, 0, 0): not a rotation; the identity is (1, 0, 0, 0) in w x y z"
    return (f"has norm {math.sqrt(norm2):.6g}, not 1 (|q|² = {norm2:.6g}; a unit quaternion "
            f"is needed: | |q|² − 1 | <= {QUAT_NORM_TOL:g})")


# --------------------------------------------------------------------------- linear algebra


def sample_cov(a: Array, b: Array | None = None) -> Array:
    """Sample (cross-)covariance over axis -2: ``(..., N, p)``, ``(..., N, q)`` -> ``(p, q)``."""
    ac = a - a.mean(axis=-2, keepdims=True)
    bc = ac if b is None else b - b.mean(axis=-2, keepdims=True)
    n = a.shape[-2]
    out: Array = np.swapaxes(ac, -1, -2) @ bc / (n - 1)
    return out


def scaled_eigh(s: Array) -> tuple[Array, Array, Array]:
    """Eigen-decompose ``D s D`` with ``D = diag(1/sqrt(diag s))`` (0 for dead dimensions).

    Returns (d, lam, v): the scale vector, eigenvalues with truncated ones set to 0, vectors.
    """
    diag = np.diagonal(s, axis1=-2, axis2=-1)
    live = diag > ZERO_VARIANCE
    d = np.where(live, 1.0 / np.sqrt(np.where(live, diag, 1.0)), 0.0)
    sn = s * d[..., :, None] * d[..., None, :]
    lam, v = np.linalg.eigh(0.5 * (sn + np.swapaxes(sn, -1, -2)))
    cut = RTOL * np.max(np.abs(lam), axis=-1, keepdims=True)
    lam = np.where(lam > cut, lam, 0.0)
    return d, lam, v


def _apply_fn(d: Array, lam: Array, v: Array, f: Array) -> Array:
    """``D V diag(f) Vᵀ D``."""
    m = (v * f[..., None, :]) @ np.swapaxes(v, -1, -2)
    return m * d[..., :, None] * d[..., None, :]


def scaled_pinv(s: Array) -> Array:
    """Scaled, truncated pseudo-inverse of symmetric PSD matrices ``(..., p, p)``."""
    d, lam, v = scaled_eigh(s)
    with np.errstate(divide="ignore"):
        f = np.where(lam > 0.0, 1.0 / np.where(lam > 0.0, lam, 1.0), 0.0)
    return _apply_fn(d, lam, v, f)


def sym_sqrt(s: Array) -> Array:
    """Symmetric PSD square root ``(..., p, p)`` (negative eigenvalues clipped to 0)."""
    lam, v = np.linalg.eigh(0.5 * (s + np.swapaxes(s, -1, -2)))
    out: Array = (v * np.sqrt(np.clip(lam, 0.0, None))[..., None, :]) @ np.swapaxes(v, -1, -2)
    return out


# --------------------------------------------------------------------------- merge spaces


def to_space(x: Array, space: Space, q_ref: Array | None = None) -> tuple[Array, Array]:
    """Express ATs ``(..., N, 7)`` as plain vectors for a linear step.

    ``quaternion``: the 7-vector, quaternions on the hemisphere of ``q_ref`` (the paper).
    ``tangent``: ``[t, δ]`` (6-D) with ``δ = 2 vec(q_ref⁻¹ q)`` on ``q_ref``'s hemisphere: a
    ⊞ chart of SO(3) around ``q_ref`` (PAPER §5) that equals the body-frame rotation vector to
    first order (``2 sin(θ/2)`` for ``θ``: 1 % apart at 30°) and needs no trigonometry, so it
    is cheap on whole components. The joint update works in the same chart.
    ``q_ref`` ``(..., 4)`` defaults to each AT's mean rotation. Returns (vectors, q_ref).
    """
    q = x[..., 3:]
    if q_ref is None:
        q_ref = mean_rotation(q)
    ref = q_ref[..., None, :]
    if space == "quaternion":
        return np.concatenate((x[..., :3], align_hemisphere(q, ref)), axis=-1), q_ref
    rel = align_hemisphere(qmul(qconj(ref), q), np.array([1.0, 0.0, 0.0, 0.0]))
    return np.concatenate((x[..., :3], 2.0 * rel[..., 1:]), axis=-1), q_ref


def from_space(v: Array, space: Space, q_ref: Array) -> Array:
    """Inverse of :func:`to_space`: vectors back to ATs with unit quaternions."""
    if space == "quaternion":
        return np.concatenate((v[..., :3], qnormalize(v[..., 3:])), axis=-1)
    half = 0.5 * v[..., 3:]
    w = np.sqrt(np.clip(1.0 - np.einsum("...k,...k->...", half, half), 0.0, None))
    rel = qnormalize(np.concatenate((w[..., None], half), axis=-1))
    return np.concatenate((v[..., :3], qmul(q_ref[..., None, :], rel)), axis=-1)


def merge_vectors(p_a: Array, p_b: Array, c_a: Array, c_sum: Array) -> Array:
    """``P_A + C_A (C_sum)⁺ (P_B − P_A)`` sample by sample (PAPER eq. 2-3)."""
    gain = c_a @ scaled_pinv(c_sum)
    return p_a + (p_b - p_a) @ np.swapaxes(gain, -1, -2)


def merge(x_a: Array, x_b: Array, space: Space = "tangent") -> Array:
    """Merge two independent estimates of the same relation (PAPER §1, eqs. 2-3).

    ``K = C_A (C_A + C_B)⁺``, ``P = P_A + K (P_B − P_A)`` on ``(..., N, 7)``; the Ensemble
    Kalman update where state and observation share variables. Quaternions are renormalised.
    """
    p_a, q_ref = to_space(x_a, space)
    p_b, _ = to_space(x_b, space, q_ref)
    c_a = sample_cov(p_a)
    return from_space(merge_vectors(p_a, p_b, c_a, c_a + sample_cov(p_b)), space, q_ref)


def merge_correlated(x_c: Array, x_d: Array, space: Space = "tangent") -> Array:
    """Revised merge for possibly correlated estimates (PAPER §2, eq. 6).

    ``C_X = (cov C + cov D − cov(C − D)) / 2``, ``C_A = cov C − C_X``, ``C_B = cov D − C_X``,
    then eqs. 2-3 with ``C_A``, ``C_B`` (``C_A + C_B = cov(C − D)``). Idempotent:
    ``merge_correlated(a, a)`` returns ``a`` (up to renormalisation).
    """
    p_c, q_ref = to_space(x_c, space)
    p_d, _ = to_space(x_d, space, q_ref)
    n = p_c.shape[-2]
    a_c = p_c - p_c.mean(axis=-2, keepdims=True)
    a_d = p_d - p_d.mean(axis=-2, keepdims=True)
    a_diff = a_c - a_d
    cov_c, cov_d, cov_diff = (np.swapaxes(a, -1, -2) @ a / (n - 1) for a in (a_c, a_d, a_diff))
    c_x = 0.5 * (cov_c + cov_d - cov_diff)
    return from_space(merge_vectors(p_c, p_d, cov_c - c_x, cov_diff), space, q_ref)


def mean_and_cov(x: Array) -> tuple[Array, Array]:
    """Mean 7-vector and 6×6 tangent covariance of an AT ``(N, 7)``.

    The mean rotation is the chordal mean; the covariance is over ``[t, δ]`` with
    ``q = q_mean ⊗ exp(δ)`` (body-frame rotation vector), order ``tx ty tz rx ry rz``.
    """
    q_ref = mean_rotation(x[..., 3:])
    rotvec = qlog(qmul(qconj(q_ref)[..., None, :], x[..., 3:]))  # exact rotation vector
    v = np.concatenate((x[..., :3], rotvec), axis=-1)
    mean = np.concatenate((v[..., :3].mean(axis=-2), q_ref), axis=-1)
    return mean, sample_cov(v)


# --------------------------------------------------------------------------- paper propagation

#: samples (frames × N) per block of :func:`merge_correlated_shifted`: the block's ~40 planes
#: stay in the L2 cache while it is transformed, reduced and merged.
_BLOCK_SAMPLES = 16384
_CONJ = np.array([1.0, -1.0, -1.0, -1.0])
# rows of p_C = [t_C, v_C] and Δ = [Δt, Δv] among the block's rows 1..13
_PC = np.array([3, 4, 5, 0, 1, 2])
_DELTA = np.arange(7, 13)


def _lmul_rows(q: Array) -> Array:
    """Left-multiplication matrices ``L(q)`` (``qmul(q, p) = L(q) p``): ``(..., 4)`` ->
    ``(..., 4, 4)``."""
    out: Array = q[..., L_INDEX] * L_SIGN
    return out


def _planar_at(x: Array, minus_identity: bool = False) -> tuple[Array, Array]:
    """An AT ``(N, 7)`` as per-sample planes: ``[R | t]`` ``(3, 4, N)`` (``R − I`` if
    ``minus_identity``), acting on ``[v; 1]``, and ``L(q)`` ``(4, 4, N)``."""
    r = rotation_matrix(x[:, 3:])
    if minus_identity:
        r -= np.eye(3)
    rt = np.concatenate((r, x[:, :3, None]), axis=2)
    return (np.ascontiguousarray(np.moveaxis(rt, 0, -1)),
            np.ascontiguousarray(np.moveaxis(_lmul_rows(x[:, 3:]), 0, -1)))


def _flip_to_identity(rel: Array) -> None:
    """``align_hemisphere(rel, 1)`` in place on planes ``(m, 4, N)`` (rows w x y z)."""
    w = rel[:, 0]
    if w.min(initial=0.0) < 0.0:
        rel *= np.where(w < 0.0, -1.0, 1.0)[:, None, :]


def merge_correlated_shifted(edges: Array, shift: Array, pre: Array | None = None,
                             pin: npt.NDArray[np.bool_] | None = None,
                             out: Array | None = None) -> Array:
    """``merge_correlated(e, shift ⊕ e, "tangent")`` for every AT ``e`` of a stack, fused.

    ``edges`` ``(M, N, 7)``; ``shift`` ``(N, 7)`` is one AT applied to every edge. With ``pre``
    ``(N, 7)`` every edge is first replaced by ``pre ⊕ e`` (a re-rooting), and rows of ``pin``
    ``(M,)`` then get identity quaternions (point frames), as PAPER Fig. 3 does before the merge.
    Returns ``(M, N, 7)`` (into ``out`` if given; it must not overlap ``edges``).

    Same mathematics as :func:`merge_correlated` in the tangent chart (PAPER §2, eq. 6), with
    ``C = e``, ``D = shift ⊕ e`` and ``Δ = p_D − p_C``: ``C_A = −sym(cov(p_C, Δ))`` and
    ``C_A + C_B = cov(Δ)`` (the same matrices, without the cancellation of
    ``cov C + cov D − cov(C − D)``), ``p = p_C + K Δ``, ``K = C_A (cov Δ)⁺``. The edges are
    processed in blocks of frames held as planes ``(m, k, N)``: every per-sample step is one
    einsum or batched matmul over a block, the output is written by BLAS straight into
    ``(M, N, 7)`` order.
    """
    n_frames, n, _ = edges.shape
    if out is None:
        out = np.empty_like(edges)
    # Δt = t_D − t_C = (R_s − I) t_C + t_s in one contraction
    a_s, l_s = _planar_at(shift, minus_identity=True)
    a_p, l_p = _planar_at(pre) if pre is not None else (None, None)
    step = max(1, _BLOCK_SAMPLES // n)
    m = min(step, n_frames)
    # rows: 0 w_C, 1-3 v_C, 4-6 t_C, 7 ones, 8-10 Δt, 11-13 Δv; v = vec(q_ref⁻¹ q) = δ / 2
    p = np.empty((m, 14, n))
    p[:, 7] = 1.0
    x_in = np.empty((m, 8, n))  # [t, 1, q] of the input edges (re-rooting only)
    x_in[:, 3] = 1.0
    q_c = np.empty((m, 4, n))
    q_d = np.empty((m, 4, n))
    rel_d = np.empty((m, 4, n))
    y = np.empty((m, 4, n))  # (w, v) of the result
    tmp = np.empty((m, n))
    # the covariances in δ units from those in v units, exactly (powers of two)
    s = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
    ss = s[:, None] * s[None, :]
    for lo in range(0, n_frames, step):
        hi = min(lo + step, n_frames)
        k = hi - lo
        p_k, q_c_k, q_d_k, rel_d_k, y_k, tmp_k = (
            p[:k], q_c[:k], q_d[:k], rel_d[:k], y[:k], tmp[:k])
        src = np.swapaxes(edges[lo:hi], 1, 2)
        if a_p is not None and l_p is not None:
            x_k = x_in[:k]
            x_k[:, :3] = src[:, :3]
            x_k[:, 4:] = src[:, 3:]
            np.einsum("ijn,mjn->min", a_p, x_k[:, :4], out=p_k[:, 4:7])
            np.einsum("ijn,mjn->min", l_p, x_k[:, 4:], out=q_c_k)
        else:
            p_k[:, 4:7] = src[:, :3]
            q_c_k[...] = src[:, 3:]
        if pin is not None and pin[lo:hi].any():
            q_c_k[pin[lo:hi]] = np.array([1.0, 0.0, 0.0, 0.0])[:, None]
        np.einsum("ijn,mjn->min", a_s, p_k[:, 4:8], out=p_k[:, 8:11])
        np.einsum("ijn,mjn->min", l_s, q_c_k, out=q_d_k)
        # reference rotation: chordal mean of q_C on the hemisphere of its first sample
        np.einsum("mkn,mk->mn", q_c_k, q_c_k[:, :, 0], out=tmp_k)
        np.add(tmp_k, 0.0, out=tmp_k)  # -0.0 -> +0.0: only a negative dot flips
        np.copysign(1.0, tmp_k, out=tmp_k)
        q_ref = np.matmul(q_c_k, tmp_k[..., None])[..., 0]
        q_ref /= np.linalg.norm(q_ref, axis=-1, keepdims=True)
        # v of C and D: q_ref⁻¹ q on the hemisphere of the identity
        l_inv = _lmul_rows(q_ref * _CONJ)
        np.matmul(l_inv, q_c_k, out=p_k[:, 0:4])
        np.matmul(l_inv, q_d_k, out=rel_d_k)
        _flip_to_identity(p_k[:, 0:4])
        _flip_to_identity(rel_d_k)
        np.subtract(rel_d_k[:, 1:], p_k[:, 1:4], out=p_k[:, 11:14])
        mean = p_k.mean(axis=-1)  # (k, 14)
        p_k[:, 1:7] -= mean[:, 1:7, None]
        p_k[:, 8:14] -= mean[:, 8:14, None]
        # one product of the 13 rows 1..13 with Δ gives cov(p_C, Δ) and cov(Δ), [t, v] order
        p_1 = p_k[:, 1:]
        cross = np.matmul(p_1, np.swapaxes(p_1[:, 7:], 1, 2))  # (k, 13, 6)
        cross /= n - 1
        c_cd = cross[:, _PC] * ss
        c_a = -0.5 * (c_cd + np.swapaxes(c_cd, 1, 2))
        gain = (c_a @ scaled_pinv(cross[:, _DELTA] * ss)) * (s / s[:, None])
        # [t, v] of the result = p_C + K Δ as one matrix on the rows 1..13 (ones at 6)
        w = np.zeros((k, 6, 13))
        w[:, :, _DELTA] = gain
        w[:, np.arange(6), _PC] = 1.0
        w[:, :, 6] = mean[:, _PC + 1] + np.einsum("mij,mj->mi", gain, mean[:, _DELTA + 1])
        np.matmul(np.swapaxes(p_1, 1, 2), np.swapaxes(w[:, :3], 1, 2), out=out[lo:hi, :, :3])
        np.matmul(w[:, 3:], p_1, out=y_k[:, 1:])
        # back from the chart: (w, v) with w = sqrt(1 − |v|²), unit unless |v| > 1; q_ref (w, v)
        np.einsum("mkn,mkn->mn", y_k[:, 1:], y_k[:, 1:], out=tmp_k)
        np.subtract(1.0, tmp_k, out=y_k[:, 0])
        np.maximum(y_k[:, 0], 0.0, out=y_k[:, 0])
        np.sqrt(y_k[:, 0], out=y_k[:, 0])
        if tmp_k.max(initial=0.0) > 1.0:
            y_k[:, 1:] /= np.sqrt(np.maximum(tmp_k, 1.0))[:, None]
        np.matmul(np.swapaxes(y_k, 1, 2), np.swapaxes(_lmul_rows(q_ref), 1, 2),
                  out=out[lo:hi, :, 3:])
    return out
