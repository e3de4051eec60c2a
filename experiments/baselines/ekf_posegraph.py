"""Error-state EKF on a pose graph: the exact-covariance reference for issue 8.

The same sequential problem the map solves (every pose kept, odometry then loop closures in
arrival order, pose 0 fixed at the identity), but with one dense ``(6P, 6P)`` covariance instead
of N samples. It answers two questions about the ensemble's error on pose graphs:

* how far a *sequential* filter that never relinearises past updates is from GTSAM's batch
  optimum (if far, the gap is linearisation; measured: it is not, see
  ``experiments/results/pose_graph_summary.md``);
* what the ensemble's correlation shrink costs by itself: with ``shrink_n`` set, every gain
  entry is multiplied by the factor :func:`mcsm.core.analysis.shrink_correlations` would apply
  to an N-sample estimate with that exact correlation (bias only, no sampling noise), and the
  covariance follows the Joseph form for that suboptimal gain.

Conventions are those of ``mcsm.core`` and :mod:`experiments.posegraph_sim`: a pose is
``x y z qw qx qy qz``; its error is ``[t_true − t, log(q⁻¹ q_true)]`` (world-frame translation,
body-frame rotation); a measurement ``z`` of ``i → j`` is ``h ⊞ n`` with ``t_z = t_h + n_t``
and ``q_z = q_h ⊗ exp(n_r)``. Planar graphs use the live rows ``[tx, ty, rz]`` of each
observation (the others have zero noise and zero prior variance).

Cost: O(P²) per loop closure and O(P) per odometry step, memory ``(6P)² × 8`` bytes
(288 MB at 1000 poses).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from experiments.posegraph_sim import PoseGraph, qexp, qlog, qmul, relative

Array = npt.NDArray[np.float64]
_CONJ = np.array([1.0, -1.0, -1.0, -1.0])


def rotation_matrix(q: Array) -> Array:
    """3×3 rotation matrix of a unit quaternion ``(4,)`` (scalar first)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def skew(v: Array) -> Array:
    """``[v]×``: ``skew(v) @ u == cross(v, u)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def odometry_jacobians(x_i: Array, z: Array) -> tuple[Array, Array]:
    """Jacobians of ``x_j = x_i ⊕ z`` w.r.t. the error of ``x_i`` and the noise of ``z``.

    Returns ``(F, G)``, both 6×6: ``δ_j ≈ F δ_i + G n``.
    """
    r_i = rotation_matrix(x_i[3:])
    f = np.eye(6)
    f[:3, 3:] = -r_i @ skew(z[:3])
    f[3:, 3:] = rotation_matrix(z[3:]).T
    g = np.eye(6)
    g[:3, :3] = r_i
    return f, g


def loop_jacobians(x_a: Array, x_b: Array) -> tuple[Array, Array, Array]:
    """Predicted ``h = x_a^R ⊕ x_b`` and its Jacobians w.r.t. the errors of ``x_a``, ``x_b``.

    Returns ``(h, H_a, H_b)``: the innovation ``z ⊟ h`` is ``H_a δ_a + H_b δ_b + n`` to first
    order.
    """
    h = relative(x_a, x_b)
    r_a = rotation_matrix(x_a[3:])
    h_a = np.zeros((6, 6))
    h_a[:3, :3] = -r_a.T
    h_a[:3, 3:] = skew(h[:3])
    h_a[3:, 3:] = -rotation_matrix(h[3:]).T
    h_b = np.zeros((6, 6))
    h_b[:3, :3] = r_a.T
    h_b[3:, 3:] = np.eye(3)
    return h, h_a, h_b


def boxminus(z: Array, h: Array) -> Array:
    """``z ⊟ h = [t_z − t_h, log(q_h⁻¹ q_z)]``, shape ``(6,)``."""
    return np.concatenate([z[:3] - h[:3], qlog(qmul(h[3:] * _CONJ, z[3:]))])


def shrink_factor(r2: Array, n_samples: int, c: float) -> Array:
    """The correlation-shrink factor ``max(0, 1 − c (1 − r²)² / (N r²))`` of the map's core."""
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(r2 > 0, 1.0 - c * (1.0 - r2) ** 2 / (n_samples * np.where(r2 > 0, r2, 1.0)),
                     0.0)
    return np.clip(f, 0.0, 1.0)


@dataclass
class EkfRun:
    """Final pose means ``(P, 7)``, marginal covariances ``(P, 6, 6)`` and timings."""

    means: Array
    covs: Array
    loop_times_s: list[float]


def _endpoint_gain_cross(p: Array, c_xy: Array, var_y: Array, ends: Array, h_v: Array,
                         n_samples: int, c: float) -> Array:
    """The map's ``gain="endpoints"`` estimator applied to exact covariances (its bias alone).

    ``ends`` the 12 state indices of the two endpoints, ``h_v`` ``(p, 12)`` the observation's
    Jacobian on them; see :func:`mcsm.core.analysis.endpoint_cross_covariance`.
    """
    c_vv = p[np.ix_(ends, ends)]
    var_v = np.diagonal(c_vv)
    live = var_v > 1e-20
    scale = np.where(live, 1.0 / np.sqrt(np.where(live, var_v, 1.0)), 0.0)
    lam, vec = np.linalg.eigh(c_vv * scale[:, None] * scale[None, :])
    keep = lam > 1e-9 * lam.max()
    lam, t = lam[keep], scale[:, None] * vec[:, keep]  # components = tᵀ v
    c_xp = p[:, ends] @ t
    c_py = t.T @ c_vv @ h_v.T
    beta = c_xp / lam
    var_e = np.clip(np.diagonal(p) - np.sum(c_xp * beta, axis=1), 0.0, None)
    dof = max(n_samples - lam.size - 1, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t2 = beta**2 * lam * dof / var_e[:, None]
        f = np.where(t2 > 0, 1.0 - 2.0 * c / np.where(t2 > 0, t2, 1.0), 0.0)
    beta = beta * np.clip(np.nan_to_num(f, nan=0.0), 0.0, 1.0)
    r2 = c_py**2 / (lam[:, None] * np.where(var_y > 0, var_y, np.inf)[None, :])
    return beta @ (c_py * shrink_factor(r2, n_samples, c))


def run_ekf_posegraph(graph: PoseGraph, *, shrink_n: int | None = None,
                      shrink_c: float = 4.0, gain: str = "direct") -> EkfRun:
    """Run the EKF over ``graph``'s measurements in arrival order.

    Parameters
    ----------
    graph : PoseGraph
        Odometry edges must be ``j − 1 → j`` and arrive before any loop closure ending at
        ``j`` (the simulator's and the readers' order).
    shrink_n : int, optional
        If set, multiply every entry of the gain's cross-covariance by the map's shrink factor
        for an N = ``shrink_n`` sample estimate of that (exact) correlation; the covariance
        update is then the Joseph form of that gain.
    shrink_c : float
        The shrink constant c (the map's default is 4).
    gain : {"direct", "endpoints"}
        Which of the map's cross-covariance estimators the shrink imitates (with
        ``shrink_n``): per entry of the gain, or through the endpoints' principal components.
    """
    if gain not in ("direct", "endpoints"):
        raise ValueError(f"gain must be 'direct' or 'endpoints', got {gain!r}")
    gain_mode = gain
    n_poses = graph.n_poses
    x = np.zeros((n_poses, 7))
    x[0] = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]
    cov = np.zeros((6 * n_poses, 6 * n_poses))
    live = graph.dof_index
    known = 1  # poses 0..known-1 exist
    loop_times: list[float] = []
    for (i, j), z, r_full, loop in zip(graph.edges, graph.measurements, graph.covariances,
                                       graph.is_loop, strict=True):
        i, j = int(i), int(j)
        if not loop:
            if j != known or i != j - 1:
                raise ValueError(f"odometry edge {i}->{j} out of order (next pose {known})")
            f, g = odometry_jacobians(x[i], z)
            x[j, :3] = x[i, :3] + rotation_matrix(x[i, 3:]) @ z[:3]
            q = qmul(x[i, 3:], z[3:])
            x[j, 3:] = q / np.linalg.norm(q)
            si, sj = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
            cov[sj, : 6 * j] = f @ cov[si, : 6 * j]
            cov[: 6 * j, sj] = cov[sj, : 6 * j].T
            cov[sj, sj] = f @ cov[si, si] @ f.T + g @ r_full @ g.T
            known = j + 1
            continue
        t0 = time.perf_counter()
        h, h_a, h_b = loop_jacobians(x[i], x[j])
        nu, h_a, h_b = boxminus(z, h)[live], h_a[live], h_b[live]
        r = r_full[np.ix_(live, live)]
        d = 6 * known
        p = cov[:d, :d]
        sa, sb = slice(6 * i, 6 * i + 6), slice(6 * j, 6 * j + 6)
        c_xy = p[:, sa] @ h_a.T + p[:, sb] @ h_b.T  # (d, p)
        s = h_a @ c_xy[sa] + h_b @ c_xy[sb] + r
        if shrink_n is None:
            k_gain = np.linalg.solve(s, c_xy.T).T
            p -= k_gain @ c_xy.T
        else:
            var_y = np.diagonal(s - r)
            if gain_mode == "endpoints":
                ends = np.r_[6 * i:6 * i + 6, 6 * j:6 * j + 6]
                c_tilde = _endpoint_gain_cross(p, c_xy, var_y, ends, np.hstack((h_a, h_b)),
                                               shrink_n, shrink_c)
            else:
                var_x = np.diagonal(p).copy()
                den = var_x[:, None] * var_y[None, :]
                r2 = np.where(den > 0, c_xy**2 / np.where(den > 0, den, 1.0), 0.0)
                c_tilde = c_xy * shrink_factor(r2, shrink_n, shrink_c)
            k_gain = np.linalg.solve(s, c_tilde.T).T
            p += k_gain @ s @ k_gain.T - k_gain @ c_xy.T - c_xy @ k_gain.T
        p[...] = 0.5 * (p + p.T)
        delta = (k_gain @ nu).reshape(known, 6)
        x[:known, :3] += delta[:, :3]
        q = qmul(x[:known, 3:], qexp(delta[:, 3:]))
        x[:known, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
        loop_times.append(time.perf_counter() - t0)
    blocks = cov.reshape(n_poses, 6, n_poses, 6)
    covs = np.ascontiguousarray(np.einsum("kikj->kij", blocks))
    return EkfRun(x, covs, loop_times)


__all__ = ["EkfRun", "boxminus", "loop_jacobians", "odometry_jacobians", "run_ekf_posegraph",
           "shrink_factor"]
