"""Sample sets for the map from a sensor's mean and covariance, so nobody hand-rolls AT samples.

Every function draws from an explicit ``rng: np.random.Generator`` (a required keyword) and
returns C-contiguous float64 arrays in the core's layout:

* an AT: ``(N, 7)`` ``x y z qw qx qy qz`` (scalar-first unit quaternion), see PAPER §1;
* a point: ``(N, 3)`` ``x y z`` (planar points have z = 0).

Pose covariances are over the 6-vector ``[tx, ty, tz, rx, ry, rz]`` (translation first, then a
rotation vector), and a sample is ``t = t_mean + δt`` (``translation_frame="parent"``, the
default, the convention of :func:`mcsm.core.at.mean_and_cov`) or ``t = t_mean + R(q_mean) δt``
(``"body"``, the convention of GTSAM and g2o, used by the dataset players), and always
``q = q_mean ⊗ exp(δr)`` (body-frame rotation). Singular covariances are fine (a planar AT has
zero variance in z, roll and pitch): the square root is taken by eigen-decomposition.

Autocorrelated sensors (PAPER §3, the paper's §5.2 remark): a new AT may be correlated with one
already in the map. :func:`correlated_with` draws the samples of a new reading so that sample i
carries an AR(1) continuation of the noise of sample i of the previous reading.

Example
-------
>>> import numpy as np
>>> from mcsm_client.sampling import sample_planar, correlated_with
>>> rng = np.random.default_rng(7)
>>> cov = np.diag([0.01**2, 0.002**2, 0.001**2])
>>> first = sample_planar([1.0, 0.0, 0.0], cov, n_samples=500, rng=rng)
>>> second = correlated_with(first, [1.0, 0.0, 0.0], cov, rho=0.9, rng=rng, planar=True)
>>> second.shape
(500, 7)
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np
import numpy.typing as npt
from mcsm.core.quat import align_hemisphere, mean_rotation, qconj, qexp, qlog, qmul, qrot

Array = npt.NDArray[np.float64]
ArrayLike = Sequence[float] | npt.NDArray[np.floating]
TranslationFrame = Literal["parent", "body"]

__all__ = [
    "correlated_with",
    "pose_from_planar",
    "planar_cov_to_pose_cov",
    "sample_planar",
    "sample_point",
    "sample_pose",
]


def _cov(cov: ArrayLike | Array, dim: int, what: str) -> Array:
    c = np.asarray(cov, dtype=np.float64)
    if c.shape != (dim, dim):
        raise ValueError(f"{what}: expected a ({dim}, {dim}) covariance, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError(f"{what}: covariance is not finite")
    if not np.allclose(c, c.T, rtol=1e-9, atol=1e-15):
        raise ValueError(f"{what}: covariance is not symmetric")
    lam = np.linalg.eigvalsh(c)
    if lam.min() < -1e-9 * max(1.0, float(lam.max())):
        raise ValueError(f"{what}: covariance is not positive semi-definite")
    return c


def _sqrt_psd(c: Array) -> Array:
    """Symmetric square root of a PSD matrix (clips round-off negative eigenvalues)."""
    lam, v = np.linalg.eigh(0.5 * (c + c.T))
    return np.asarray((v * np.sqrt(np.clip(lam, 0.0, None))) @ v.T, dtype=np.float64)


def _check_n(n_samples: int) -> int:
    n = int(n_samples)
    if n < 2:
        raise ValueError(f"n_samples must be >= 2, got {n_samples}")
    return n


def pose_from_planar(mean: ArrayLike) -> Array:
    """The 7-vector ``x y 0 cos(θ/2) 0 0 sin(θ/2)`` of a planar pose ``(x, y, θ)``."""
    m = np.asarray(mean, dtype=np.float64)
    if m.shape != (3,):
        raise ValueError(f"expected a planar pose (x, y, theta), got shape {m.shape}")
    return np.array([m[0], m[1], 0.0, np.cos(m[2] / 2), 0.0, 0.0, np.sin(m[2] / 2)])


def planar_cov_to_pose_cov(cov: ArrayLike) -> Array:
    """Embed a planar ``(3, 3)`` covariance over ``(x, y, θ)`` into the 6×6 pose layout."""
    c = _cov(cov, 3, "planar covariance")
    idx = np.array([0, 1, 5])
    out = np.zeros((6, 6))
    out[np.ix_(idx, idx)] = c
    return out


def _apply_deltas(mean: Array, delta: Array, translation_frame: TranslationFrame) -> Array:
    """Samples ``(N, 7)`` around ``mean (7,)`` from tangent deviations ``(N, 6)``."""
    q_mean = mean[3:] / np.linalg.norm(mean[3:])
    dt = delta[:, :3]
    if translation_frame == "body":
        dt = qrot(np.broadcast_to(q_mean, (delta.shape[0], 4)), dt)
    elif translation_frame != "parent":
        raise ValueError(f"translation_frame must be 'parent' or 'body', got {translation_frame!r}")
    out = np.empty((delta.shape[0], 7))
    out[:, :3] = mean[:3] + dt
    q = qmul(q_mean[None, :], qexp(delta[:, 3:]))
    # One hemisphere (the mean's), unit length: what the core checks and expects.
    q = align_hemisphere(q, q_mean)
    out[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return out


def _pose_mean(mean: ArrayLike) -> Array:
    m = np.asarray(mean, dtype=np.float64)
    if m.shape != (7,) or not np.all(np.isfinite(m)):
        raise ValueError(f"expected a finite pose (x, y, z, qw, qx, qy, qz), got {m!r}")
    if np.linalg.norm(m[3:]) < 1e-9:
        raise ValueError("the mean pose has a zero quaternion")
    return m


def sample_pose(
    mean: ArrayLike,
    cov: ArrayLike,
    *,
    n_samples: int,
    rng: np.random.Generator,
    translation_frame: TranslationFrame = "parent",
) -> Array:
    """Draw an AT from a mean pose and a 6×6 tangent covariance (3D).

    Parameters
    ----------
    mean : (7,) float
        ``x y z qw qx qy qz`` (m; the quaternion is normalised here).
    cov : (6, 6) float
        Covariance of ``[tx, ty, tz, rx, ry, rz]`` (m², rad²); positive semi-definite.
    n_samples : int
        N, the map's sample count.
    rng : np.random.Generator
        Source of the draws.
    translation_frame : {"parent", "body"}
        Whether the translation deviation is in the parent frame (``t = t̄ + δt``) or in the
        mean pose's own frame (``t = t̄ + R(q̄) δt``, GTSAM/g2o).

    Returns
    -------
    (N, 7) float64
        AT samples, quaternions unit and on the mean's hemisphere.

    Raises
    ------
    ValueError
        On a wrong shape, a non-finite value, or a covariance that is not symmetric PSD.
    """
    m = _pose_mean(mean)
    c = _cov(cov, 6, "pose covariance")
    n = _check_n(n_samples)
    delta = rng.standard_normal((n, 6)) @ _sqrt_psd(c)
    return _apply_deltas(m, delta, translation_frame)


def sample_planar(
    mean: ArrayLike,
    cov: ArrayLike,
    *,
    n_samples: int,
    rng: np.random.Generator,
    translation_frame: TranslationFrame = "parent",
) -> Array:
    """Draw a planar AT from ``(dx, dy, dθ)`` and its 3×3 covariance.

    Parameters
    ----------
    mean : (3,) float
        ``(dx, dy, dθ)`` (m, m, rad): the target frame in the source frame.
    cov : (3, 3) float
        Covariance of ``(dx, dy, dθ)`` (m², rad²); positive semi-definite.
    n_samples : int
        N.
    rng : np.random.Generator
        Source of the draws.
    translation_frame : {"parent", "body"}
        See :func:`sample_pose`.

    Returns
    -------
    (N, 7) float64
        AT samples with z = 0 and rotations about z.
    """
    return sample_pose(pose_from_planar(mean), planar_cov_to_pose_cov(cov), n_samples=n_samples,
                       rng=rng, translation_frame=translation_frame)


def sample_point(
    mean: ArrayLike,
    cov: ArrayLike,
    *,
    n_samples: int,
    rng: np.random.Generator,
) -> Array:
    """Draw a point observation ``(x, y[, z])`` with its covariance.

    Parameters
    ----------
    mean : (2,) or (3,) float
        The point in the observer's frame (m).
    cov : (2, 2) or (3, 3) float
        Its covariance (m²), matching ``mean``'s length.
    n_samples : int
        N.
    rng : np.random.Generator
        Source of the draws.

    Returns
    -------
    (N, 3) float64
        Point samples (z = 0 for a planar point).
    """
    m = np.asarray(mean, dtype=np.float64)
    if m.shape not in ((2,), (3,)) or not np.all(np.isfinite(m)):
        raise ValueError(f"expected a finite point (x, y[, z]), got {m!r}")
    d = m.shape[0]
    c = _cov(cov, d, "point covariance")
    n = _check_n(n_samples)
    out = np.zeros((n, 3))
    out[:, :d] = m + rng.standard_normal((n, d)) @ _sqrt_psd(c)
    return out


def _whiten(dev: Array) -> tuple[Array, Array]:
    """Whitened deviations ``(N, d)`` and the projector onto their span ``(d, d)``.

    ``z = dev S^{+1/2}`` with ``S`` the sample covariance: ``cov(z)`` is the projector ``P``.
    Dimensions with no spread (e.g. z of a planar AT) give 0.
    """
    s = np.atleast_2d(np.cov(dev, rowvar=False))
    lam, v = np.linalg.eigh(0.5 * (s + s.T))
    keep = lam > 1e-12 * max(float(lam.max()), 1e-300)
    inv_sqrt = np.where(keep, 1.0 / np.sqrt(np.where(keep, lam, 1.0)), 0.0)
    w = (v * inv_sqrt) @ v.T
    proj = (v * keep) @ v.T
    return np.asarray(dev @ w, dtype=np.float64), np.asarray(proj, dtype=np.float64)


def correlated_with(
    previous: Array,
    mean: ArrayLike,
    cov: ArrayLike,
    *,
    rho: float,
    rng: np.random.Generator,
    planar: bool = False,
    translation_frame: TranslationFrame = "parent",
) -> Array:
    """Samples of a new reading whose noise is correlated, sample by sample, with a previous one.

    Models a sensor with autocorrelated errors (PAPER §3, the paper's §5.2 remark): the noise
    of sample i of the new reading is ``e_new(i) = ρ e_prev(i) + sqrt(1 − ρ²) w(i)`` in
    whitened coordinates, where ``e_prev(i)`` is sample i of ``previous`` standardised by its
    own sample mean and covariance and ``w`` fresh white noise. The result has the requested
    mean and covariance, and its whitened deviations have correlation ``rho`` with those of
    ``previous`` at the same index. Sample order is the correlation: pass ``previous`` exactly
    as it was sent to the map (never sorted or resampled).

    Parameters
    ----------
    previous : (N, 7) or (N, 3) float64
        The previous reading's samples (an AT, or a point). The output has the same kind.
    mean : (7,) or (3,) for an AT (``planar=True``), or (2,)/(3,) for a point
        Mean of the new reading.
    cov : (6, 6) or (3, 3) for an AT (``planar=True``), or matching the point's length
        Covariance of the new reading (tangent covariance for ATs, see :func:`sample_pose`).
    rho : float
        Correlation coefficient in [-1, 1] between consecutive readings' noises.
    rng : np.random.Generator
        Source of the fresh part of the noise.
    planar : bool
        For an AT: ``mean`` is ``(dx, dy, dθ)`` and ``cov`` 3×3.
    translation_frame : {"parent", "body"}
        See :func:`sample_pose`; the previous reading's deviations are read the same way.

    Returns
    -------
    (N, 7) or (N, 3) float64
        The new reading's samples, same N as ``previous``.

    Raises
    ------
    ValueError
        On a bad shape, ``rho`` outside [-1, 1], or an invalid covariance.

    Examples
    --------
    A wheel-odometry drift that persists from one reading to the next:

    >>> import numpy as np
    >>> from mcsm_client.sampling import sample_planar, correlated_with
    >>> rng = np.random.default_rng(3)
    >>> cov = np.diag([0.05**2, 0.01**2, 0.002**2])
    >>> x_k = sample_planar([1.0, 0.0, 0.0], cov, n_samples=2000, rng=rng)
    >>> x_k1 = correlated_with(x_k, [1.0, 0.0, 0.0], cov, rho=0.8, rng=rng, planar=True)
    >>> r = np.corrcoef(x_k[:, 0], x_k1[:, 0])[0, 1]
    >>> bool(abs(r - 0.8) < 0.05)
    True

    Both ATs are then sent to the map in turn (``update("x0", "x1", x_k)``, then
    ``update("x1", "x2", x_k1)``); the map's revised merge accounts for their correlation.
    """
    prev = np.asarray(previous, dtype=np.float64)
    if prev.ndim != 2 or prev.shape[1] not in (3, 7) or prev.shape[0] < 2:
        raise ValueError(f"previous must be (N, 7) or (N, 3) samples, got shape {prev.shape}")
    if not np.all(np.isfinite(prev)):
        raise ValueError("previous samples are not finite")
    r = float(rho)
    if not -1.0 <= r <= 1.0:
        raise ValueError(f"rho must be in [-1, 1], got {rho}")
    n = prev.shape[0]

    if prev.shape[1] == 3:
        m = np.asarray(mean, dtype=np.float64)
        if m.shape not in ((2,), (3,)):
            raise ValueError(f"expected a point mean (x, y[, z]), got shape {m.shape}")
        d = m.shape[0]
        c = _cov(cov, d, "point covariance")
        dev = prev[:, :d] - prev[:, :d].mean(axis=0)
        z = _mix(dev, r, rng)
        out = np.zeros((n, 3))
        out[:, :d] = m + z @ _sqrt_psd(c)
        return out

    if planar:
        m7 = pose_from_planar(mean)
        c6 = planar_cov_to_pose_cov(cov)
    else:
        m7 = _pose_mean(mean)
        c6 = _cov(cov, 6, "pose covariance")
    q_prev = prev[:, 3:] / np.linalg.norm(prev[:, 3:], axis=1, keepdims=True)
    q_ref = mean_rotation(q_prev)
    t_dev = prev[:, :3] - prev[:, :3].mean(axis=0)
    if translation_frame == "body":
        t_dev = qrot(np.broadcast_to(qconj(q_ref), (n, 4)), t_dev)
    r_dev = qlog(qmul(qconj(q_ref)[None, :], q_prev))
    dev = np.concatenate((t_dev, r_dev - r_dev.mean(axis=0)), axis=1)
    z = _mix(dev, r, rng)
    return _apply_deltas(m7, z @ _sqrt_psd(c6), translation_frame)


def _mix(dev: Array, rho: float, rng: np.random.Generator) -> Array:
    """``ρ z_prev + sqrt(1 − ρ²) P w + (I − P) w``: unit covariance, correlation ρ on P's span."""
    z_prev, proj = _whiten(dev)
    w = rng.standard_normal(dev.shape)
    fresh = np.sqrt(1.0 - rho * rho) * (w @ proj) + w @ (np.eye(dev.shape[1]) - proj)
    return np.asarray(rho * z_prev + fresh, dtype=np.float64)
