"""Seeded 6-DoF and planar pose-graph simulator with ground truth (issue 8).

A robot drives along a path that revisits the same places many times; it measures the relative
pose between consecutive poses (odometry) and between revisiting poses (loop closures). Every
measurement is the true relative pose perturbed by known Gaussian noise:

* translation: ``t_z = t_ij + dt`` with ``dt ~ N(0, sigma_t**2 I)`` expressed in frame ``i``
  (isotropic, so the frame does not change the distribution);
* rotation, in the body frame (right perturbation): ``q_z = q_ij ⊗ exp(dr)``,
  ``dr ~ N(0, sigma_r**2 I)``.

This is the tangent convention of ``mcsm.core.at.mean_and_cov`` (order ``[tx ty tz rx ry rz]``),
so a measurement's 6x6 covariance is ``diag(sigma_t**2 * 3, sigma_r**2 * 3)``. In the planar
variant z, roll and pitch are exactly zero and the noise acts on ``(x, y, yaw)`` only; the 6x6
covariance then has zeros in the z, rx and ry rows.

Paths:

* 3D (:func:`simulate_3d`): a helix around a vertical axis that climbs for half of its
  revolutions and descends along the same helix for the rest, with a roll/pitch wobble, so each
  place is seen once per revolution pair (short loops between adjacent revolutions, long loops
  between the way up and the way down).
* planar (:func:`simulate_2d`): repeated laps of a circle whose radius breathes a little from lap
  to lap.

Loop closures join a pose ``j`` to earlier poses ``i`` (``j - i >= min_gap``) whose true
positions are within ``loop_radius``; at most ``max_loops_per_pose`` per pose, kept with
probability ``p_loop``.

Poses are AT samples in the layout of ``mcsm.core`` (``x y z qw qx qy qz``, scalar-first unit
quaternion); pose 0 is the identity. The module is pure numpy and does not import ``mcsm``: it
is the ground truth the map is measured against, so its quaternion helpers (``qmul``, ``qexp``,
``qlog``, ``qrot``) are a second, independent implementation on purpose (a sign error in
``mcsm.core.quat`` must not reach the truth too); other experiments can use it on their own.

Output: a :class:`PoseGraph` (arrays) whose :meth:`PoseGraph.constraints` is the common
constraint list (``Constraint(i, j, z, cov, kind)``, in the order a robot would receive them),
and :func:`write_g2o` for ``EDGE_SE3:QUAT`` / ``EDGE_SE2`` files (g2o information matrices), with
the ground truth in a second file, so the same runs can be repeated by the g2o readers.

It reproduces no figure by itself: :mod:`experiments.pose_graph`, :mod:`experiments.eval3d` and
the tests draw their graphs from it. On its own it prints one graph's summary and can write it::

    .venv/bin/python -m experiments.posegraph_sim --seed 8 --poses 1000 --g2o /tmp/helix.g2o
    .venv/bin/python -m experiments.posegraph_sim --planar --seed 8 --poses 1000

Example
-------
>>> import numpy as np
>>> g = simulate_3d(n_poses=300, rng=np.random.default_rng(1))
>>> g.n_poses, g.n_loops > 0
(300, True)
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

__all__ = [
    "Constraint",
    "PoseGraph",
    "compose",
    "dead_reckoning",
    "from_constraints",
    "invert",
    "perturb",
    "qexp",
    "qlog",
    "qmul",
    "qrot",
    "relative",
    "sample_measurement",
    "simulate_2d",
    "simulate_3d",
    "write_g2o",
]


# ---------------------------------------------------------------------------------------------
# Small batched SE(3) helpers on (..., 7) arrays, columns x y z qw qx qy qz.
# Kept private to this module (it must run without mcsm); they follow mcsm.core's conventions.
# ---------------------------------------------------------------------------------------------
def qmul(p: Array, q: Array) -> Array:
    """Hamilton product ``p q`` of scalar-first quaternions, shapes ``(..., 4)``."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def qrot(q: Array, v: Array) -> Array:
    """Rotate vectors ``v (..., 3)`` by unit quaternions ``q (..., 4)``."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def qexp(w: Array) -> Array:
    """Unit quaternion ``(..., 4)`` of rotation vectors ``w (..., 3)`` (radians)."""
    theta = np.linalg.norm(w, axis=-1, keepdims=True)
    half = 0.5 * theta
    # sin(x/2)/x with its series near 0 to stay exact for tiny angles.
    small = theta < 1e-8
    k = np.where(small, 0.5 - theta**2 / 48.0, np.sin(half) / np.where(small, 1.0, theta))
    return np.concatenate([np.cos(half), k * w], axis=-1)


def qlog(q: Array) -> Array:
    """Rotation vector ``(..., 3)`` of unit quaternions ``(..., 4)``, angle in ``[0, pi]``."""
    q = np.where(q[..., :1] < 0.0, -q, q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    theta = 2.0 * np.arctan2(s, q[..., :1])
    small = s < 1e-10
    k = np.where(small, 2.0 / np.maximum(q[..., :1], 1e-300), theta / np.where(small, 1.0, s))
    return k * v


def compose(x_a_b: Array, x_b_c: Array) -> Array:
    """Compound ``x_a_b ⊕ x_b_c`` (PAPER §1), shapes ``(..., 7)``."""
    t = x_a_b[..., :3] + qrot(x_a_b[..., 3:], x_b_c[..., :3])
    q = qmul(x_a_b[..., 3:], x_b_c[..., 3:])
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.concatenate([t, q], axis=-1)


def invert(x_a_b: Array) -> Array:
    """Inverse ``x_a_b^R`` (PAPER §1), shape ``(..., 7)``."""
    qc = x_a_b[..., 3:] * np.array([1.0, -1.0, -1.0, -1.0])
    return np.concatenate([-qrot(qc, x_a_b[..., :3]), qc], axis=-1)


def relative(x_w_a: Array, x_w_b: Array) -> Array:
    """Relative pose ``x_a_b = x_w_a^R ⊕ x_w_b``, shapes ``(..., 7)``."""
    return compose(invert(x_w_a), x_w_b)


def perturb(x: Array, delta: Array) -> Array:
    """Apply tangent deviations ``delta (..., 6)`` = ``[dt, dr]`` to poses ``x (..., 7)``.

    ``t' = t + dt``, ``q' = q ⊗ exp(dr)`` (rotation in the body frame), the convention of
    ``mcsm.core.at.mean_and_cov``.
    """
    t = x[..., :3] + delta[..., :3]
    q = qmul(x[..., 3:], qexp(delta[..., 3:]))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return np.concatenate([t, q], axis=-1)


def _yaw_pitch_roll(yaw: Array, pitch: Array, roll: Array) -> Array:
    """Quaternions ``Rz(yaw) Ry(pitch) Rx(roll)``, shape ``(n, 4)``."""
    z = np.zeros_like(yaw)
    qz = qexp(np.stack([z, z, yaw], axis=-1))
    qy = qexp(np.stack([z, pitch, z], axis=-1))
    qx = qexp(np.stack([roll, z, z], axis=-1))
    return qmul(qmul(qz, qy), qx)


# ---------------------------------------------------------------------------------------------
# Graph containers
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Constraint:
    """One relative-pose measurement ``z: i -> j`` (pose ``j`` in the frame of pose ``i``).

    Attributes
    ----------
    i, j : int
        Pose indices; ``j`` is measured in the frame of ``i``.
    z : (7,) float64
        Measured relative pose ``x y z qw qx qy qz``.
    cov : (6, 6) float64
        Noise covariance in the tangent order ``[tx ty tz rx ry rz]`` (m², rad²), rotation
        noise in the body frame (``q_z = q_ij ⊗ exp(dr)``).
    kind : {"odometry", "loop"}
        Odometry (``j == i + 1``) or loop closure.
    """

    i: int
    j: int
    z: Array
    cov: Array
    kind: Literal["odometry", "loop"]


@dataclass(frozen=True)
class PoseGraph:
    """A simulated pose graph with ground truth.

    Attributes
    ----------
    poses_true : (P, 7) float64
        True poses in the world frame; pose 0 is the identity.
    edges : (E, 2) int64
        ``(i, j)`` of every measurement, in arrival order (odometry ``j-1 -> j`` first, then the
        loop closures ending at ``j``).
    measurements : (E, 7) float64
        Measured relative poses ``i -> j``.
    covariances : (E, 6, 6) float64
        Noise covariances, tangent order ``[tx ty tz rx ry rz]``.
    is_loop : (E,) bool
        True for loop closures.
    planar : bool
        True for the 2D variant (z = roll = pitch = 0 everywhere).
    settings : dict
        The generator's arguments (seed excluded), for printing.
    """

    poses_true: Array
    edges: npt.NDArray[np.int64]
    measurements: Array
    covariances: Array
    is_loop: npt.NDArray[np.bool_]
    planar: bool
    settings: dict[str, object]

    @property
    def n_poses(self) -> int:
        """Number of poses ``P``."""
        return int(self.poses_true.shape[0])

    @property
    def n_loops(self) -> int:
        """Number of loop closures."""
        return int(self.is_loop.sum())

    @property
    def dof(self) -> int:
        """Degrees of freedom of one pose: 6 (3D) or 3 (planar)."""
        return 3 if self.planar else 6

    @property
    def dof_index(self) -> npt.NDArray[np.int64]:
        """Indices of the free tangent components: all 6, or ``[tx, ty, rz]`` when planar."""
        return np.array([0, 1, 5]) if self.planar else np.arange(6)

    def constraints(self) -> list[Constraint]:
        """The measurements as the common constraint list, in arrival order."""
        return [
            Constraint(
                int(i), int(j), self.measurements[k], self.covariances[k],
                "loop" if self.is_loop[k] else "odometry",
            )
            for k, (i, j) in enumerate(self.edges)
        ]

    def truncated(self, n_poses: int) -> PoseGraph:
        """The first ``n_poses`` poses and the measurements among them (same arrival order)."""
        keep = np.all(self.edges < n_poses, axis=1)
        return PoseGraph(
            self.poses_true[:n_poses], self.edges[keep], self.measurements[keep],
            self.covariances[keep], self.is_loop[keep], self.planar,
            {**self.settings, "n_poses": n_poses},
        )


def sample_measurement(
    z: Array, cov: Array, n_samples: int, *, rng: np.random.Generator, exact: bool = False,
    legacy: bool = False,
) -> Array:
    """Draw an AT ``(n_samples, 7)`` centred on measurement ``z`` with tangent covariance ``cov``.

    Parameters
    ----------
    z : (7,) float64
        Measured relative pose.
    cov : (6, 6) float64
        Covariance in tangent order ``[tx ty tz rx ry rz]``; may be singular (planar).
    n_samples : int
        Number of samples N.
    rng : numpy.random.Generator
        Source of randomness.
    exact : bool
        If True, the tangent deviations are centred and whitened so that their sample mean is
        exactly 0 and their sample covariance (``ddof=1``) exactly ``cov`` (needs
        ``n_samples`` > the rank of ``cov``); the rows stay independent draws otherwise.
    legacy : bool
        If True, draw 6 standard normals per sample whatever the rank of ``cov``, as the first
        version of this function did (commit 30bbb71). Same distribution, but another random
        stream for a planar ``cov``: only for reproducing runs made with that version.

    Returns
    -------
    (n_samples, 7) float64
        ``perturb(z, delta_k)`` for ``delta_k ~ N(0, cov)``; exactly zero deviation in the
        directions where ``cov`` is zero (planar: z, roll, pitch stay 0).
    """
    w, v = np.linalg.eigh(cov)
    if legacy:
        delta = rng.standard_normal((n_samples, 6)) @ (v * np.sqrt(np.clip(w, 0.0, None))).T
        delta[:, np.diag(cov) == 0.0] = 0.0
        return perturb(np.broadcast_to(z, (n_samples, 7)), delta)
    live = w > 1e-12 * max(float(w.max()), 1e-300)
    root = v[:, live] * np.sqrt(w[live])
    white = rng.standard_normal((n_samples, int(live.sum())))
    if exact:
        white -= white.mean(axis=0)
        c = white.T @ white / (n_samples - 1)
        white = white @ np.linalg.inv(np.linalg.cholesky(c)).T
    delta = white @ root.T
    zero_var = np.diag(cov) == 0.0
    delta[:, zero_var] = 0.0
    return perturb(np.broadcast_to(z, (n_samples, 7)), delta)


def dead_reckoning(graph: PoseGraph) -> Array:
    """Poses ``(P, 7)`` obtained by compounding the odometry measurements from the identity."""
    out = np.empty_like(graph.poses_true)
    out[0] = graph.poses_true[0]
    odo = ~graph.is_loop
    by_j = {int(j): graph.measurements[k] for k, j in zip(np.flatnonzero(odo), graph.edges[odo, 1],
                                                          strict=True)}
    for j in range(1, graph.n_poses):
        out[j] = compose(out[j - 1], by_j[j])
    return out


def _noise_cov(sigma_t: float, sigma_r: float, planar: bool) -> Array:
    if planar:
        return np.diag([sigma_t**2, sigma_t**2, 0.0, 0.0, 0.0, sigma_r**2])
    return np.diag([sigma_t**2] * 3 + [sigma_r**2] * 3)


def _measure(
    poses: Array,
    pairs: npt.NDArray[np.int64],
    cov: Array,
    planar: bool,
    rng: np.random.Generator,
) -> Array:
    true_rel = relative(poses[pairs[:, 0]], poses[pairs[:, 1]])
    delta = rng.multivariate_normal(np.zeros(6), cov, size=len(pairs), method="eigh")
    if planar:
        delta[:, 2:5] = 0.0
    return perturb(true_rel, delta)


def _loop_pairs(
    positions: Array,
    *,
    loop_radius: float,
    min_gap: int,
    max_loops_per_pose: int,
    p_loop: float,
    rng: np.random.Generator,
) -> list[list[int]]:
    """For each pose j the earlier poses i it closes a loop with (closest first)."""
    out: list[list[int]] = []
    for j in range(len(positions)):
        if j < min_gap:
            out.append([])
            continue
        d = np.linalg.norm(positions[: j - min_gap + 1] - positions[j], axis=1)
        cand = np.flatnonzero(d < loop_radius)
        # One closure per earlier pass: keep the closest candidate of each run of consecutive
        # indices, so a pose does not close five loops with the same neighbourhood.
        picks: list[int] = []
        if cand.size:
            runs = np.split(cand, np.flatnonzero(np.diff(cand) > 1) + 1)
            best = [int(r[np.argmin(d[r])]) for r in runs]
            best.sort(key=lambda i: d[i])
            picks = [i for i in best[:max_loops_per_pose] if rng.random() < p_loop]
        out.append(sorted(picks))
    return out


def _assemble(
    poses: Array,
    loops: list[list[int]],
    odo_cov: Array,
    loop_cov: Array,
    planar: bool,
    rng: np.random.Generator,
    settings: dict[str, object],
) -> PoseGraph:
    pairs: list[tuple[int, int]] = []
    kinds: list[bool] = []
    for j in range(1, len(poses)):
        pairs.append((j - 1, j))
        kinds.append(False)
        for i in loops[j]:
            pairs.append((i, j))
            kinds.append(True)
    edges = np.asarray(pairs, dtype=np.int64)
    is_loop = np.asarray(kinds, dtype=bool)
    covs = np.where(is_loop[:, None, None], loop_cov, odo_cov)
    meas = np.empty((len(edges), 7))
    # Odometry and loop noise drawn in two blocks so changing p_loop leaves odometry unchanged.
    meas[~is_loop] = _measure(poses, edges[~is_loop], odo_cov, planar, rng)
    if is_loop.any():
        meas[is_loop] = _measure(poses, edges[is_loop], loop_cov, planar, rng)
    return PoseGraph(poses, edges, meas, covs, is_loop, planar, settings)


def simulate_3d(
    n_poses: int = 1200,
    *,
    rng: np.random.Generator,
    poses_per_rev: int = 100,
    radius_m: float = 10.0,
    climb_per_rev_m: float = 1.0,
    wobble_rad: float = 0.15,
    sigma_odo_t_m: float = 0.05,
    sigma_odo_r_rad: float = 0.01,
    sigma_loop_t_m: float = 0.1,
    sigma_loop_r_rad: float = 0.02,
    loop_radius_m: float = 2.5,
    min_gap: int = 50,
    max_loops_per_pose: int = 2,
    p_loop: float = 0.35,
) -> PoseGraph:
    """Simulate a 6-DoF pose graph on an up-and-down helix.

    Parameters
    ----------
    n_poses : int
        Number of poses P (odometry edges: P - 1).
    rng : numpy.random.Generator
        Source of all randomness (loop selection, then odometry noise, then loop noise).
    poses_per_rev : int
        Poses per revolution of the helix.
    radius_m, climb_per_rev_m : float
        Helix radius and rise per revolution (m). The robot climbs for the first half of the
        poses and descends along the same helix for the second half.
    wobble_rad : float
        Amplitude of the roll and pitch oscillation added to the heading (rad), so all three
        rotation axes move.
    sigma_odo_t_m, sigma_odo_r_rad : float
        Odometry noise: translation (m, per axis) and body-frame rotation (rad, per axis).
    sigma_loop_t_m, sigma_loop_r_rad : float
        Loop-closure noise, same meaning.
    loop_radius_m : float
        Two poses closer than this (true positions) are candidates for a loop closure.
    min_gap : int
        Minimum index difference ``j - i`` of a loop closure.
    max_loops_per_pose : int
        At most this many loop closures end at one pose (closest earlier passes first).
    p_loop : float
        Probability of keeping each candidate loop closure.

    Returns
    -------
    PoseGraph
        Ground truth and measurements; pose 0 is the identity.
    """
    settings = {k: v for k, v in locals().items() if k not in ("rng",)}
    k = np.arange(n_poses, dtype=float)
    phase = 2.0 * np.pi * k / poses_per_rev
    half = 0.5 * (n_poses - 1)
    height = climb_per_rev_m / poses_per_rev * np.where(k <= half, k, 2.0 * half - k)
    pos = np.stack([radius_m * np.sin(phase), radius_m * (1.0 - np.cos(phase)), height], axis=1)
    yaw = phase
    slope = np.where(k <= half, 1.0, -1.0) * climb_per_rev_m / (2.0 * np.pi * radius_m)
    pitch = -np.arctan(slope) + wobble_rad * np.sin(3.7 * phase)
    roll = wobble_rad * np.sin(2.3 * phase + 0.5)
    q = _yaw_pitch_roll(yaw, pitch, roll)
    world = np.concatenate([pos, q], axis=1)
    # Express everything relative to pose 0 so that pose 0 is exactly the identity.
    poses = relative(np.broadcast_to(world[0], world.shape), world)
    poses[0] = np.array([0, 0, 0, 1.0, 0, 0, 0])
    loops = _loop_pairs(
        poses[:, :3], loop_radius=loop_radius_m, min_gap=min_gap,
        max_loops_per_pose=max_loops_per_pose, p_loop=p_loop, rng=rng,
    )
    return _assemble(
        poses, loops, _noise_cov(sigma_odo_t_m, sigma_odo_r_rad, False),
        _noise_cov(sigma_loop_t_m, sigma_loop_r_rad, False), False, rng, settings,
    )


def simulate_2d(
    n_poses: int = 1200,
    *,
    rng: np.random.Generator,
    poses_per_rev: int = 100,
    radius_m: float = 10.0,
    breathing_m: float = 1.0,
    sigma_odo_t_m: float = 0.05,
    sigma_odo_r_rad: float = 0.01,
    sigma_loop_t_m: float = 0.1,
    sigma_loop_r_rad: float = 0.02,
    loop_radius_m: float = 2.0,
    min_gap: int = 50,
    max_loops_per_pose: int = 2,
    p_loop: float = 0.35,
) -> PoseGraph:
    """Simulate a planar pose graph: repeated laps of a circle whose radius changes per lap.

    Parameters
    ----------
    n_poses : int
        Number of poses P.
    rng : numpy.random.Generator
        Source of all randomness.
    poses_per_rev : int
        Poses per lap.
    radius_m, breathing_m : float
        Mean lap radius and the amplitude of its slow lap-to-lap variation (m).
    sigma_odo_t_m, sigma_odo_r_rad, sigma_loop_t_m, sigma_loop_r_rad : float
        Noise of odometry and loop closures on (x, y) (m, per axis) and yaw (rad).
    loop_radius_m, min_gap, max_loops_per_pose, p_loop
        Loop-closure selection, as in :func:`simulate_3d`.

    Returns
    -------
    PoseGraph
        With ``planar=True``: z, roll and pitch are exactly 0 in truth and measurements.
    """
    settings = {k: v for k, v in locals().items() if k not in ("rng",)}
    k = np.arange(n_poses, dtype=float)
    phase = 2.0 * np.pi * k / poses_per_rev
    lap = k / poses_per_rev
    r = radius_m + breathing_m * np.sin(2.0 * np.pi * lap / 7.3)
    pos = np.stack([r * np.sin(phase), radius_m - r * np.cos(phase), np.zeros_like(k)], axis=1)
    step = np.diff(pos, axis=0, append=pos[-1:] + (pos[-1:] - pos[-2:-1]))
    yaw = np.arctan2(step[:, 1], step[:, 0])
    zero = np.zeros_like(k)
    q = _yaw_pitch_roll(yaw, zero, zero)
    world = np.concatenate([pos, q], axis=1)
    poses = relative(np.broadcast_to(world[0], world.shape), world)
    poses[0] = np.array([0, 0, 0, 1.0, 0, 0, 0])
    poses[:, 2] = 0.0
    poses[:, 4:6] = 0.0
    loops = _loop_pairs(
        poses[:, :3], loop_radius=loop_radius_m, min_gap=min_gap,
        max_loops_per_pose=max_loops_per_pose, p_loop=p_loop, rng=rng,
    )
    return _assemble(
        poses, loops, _noise_cov(sigma_odo_t_m, sigma_odo_r_rad, True),
        _noise_cov(sigma_loop_t_m, sigma_loop_r_rad, True), True, rng, settings,
    )


# ---------------------------------------------------------------------------------------------
# g2o output
# ---------------------------------------------------------------------------------------------
def _upper(m: Array) -> list[float]:
    return [float(m[r, c]) for r in range(m.shape[0]) for c in range(r, m.shape[0])]


def _fmt(values: list[float] | Array) -> str:
    return " ".join(f"{float(v):.17g}" for v in values)


def write_g2o(graph: PoseGraph, path: str | Path, *, vertices: Array | None = None) -> Path:
    """Write the graph as a g2o file and the ground truth beside it.

    3D: ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` and ``EDGE_SE3:QUAT i j x y z qx qy qz qw``
    followed by the 21-entry upper triangle of the 6x6 **information** matrix, translation
    first (g2o convention). Planar: ``VERTEX_SE2 id x y theta`` and ``EDGE_SE2 i j dx dy dtheta``
    followed by the 6-entry upper triangle of the 3x3 information matrix.

    Parameters
    ----------
    graph : PoseGraph
        The graph to write.
    path : str or Path
        Output file; the ground truth goes to ``<stem>_groundtruth<suffix>`` (vertices only).
    vertices : (P, 7) float64, optional
        Initial guess written as the vertices; default dead reckoning (as g2o files ship).

    Returns
    -------
    Path
        The path of the ground-truth file.
    """
    path = Path(path)
    init = dead_reckoning(graph) if vertices is None else vertices
    truth_path = path.with_name(f"{path.stem}_groundtruth{path.suffix}")

    def vertex_lines(poses: Array) -> list[str]:
        lines = []
        for idx, p in enumerate(poses):
            if graph.planar:
                lines.append(f"VERTEX_SE2 {idx} {_fmt([p[0], p[1], _yaw(p[3:])])}")
            else:
                lines.append(f"VERTEX_SE3:QUAT {idx} {_fmt([*p[:3], *p[4:], p[3]])}")
        return lines

    lines = vertex_lines(init)
    for (i, j), z, cov in zip(graph.edges, graph.measurements, graph.covariances, strict=True):
        if graph.planar:
            sub = cov[np.ix_([0, 1, 5], [0, 1, 5])]
            info = np.linalg.inv(sub)
            lines.append(f"EDGE_SE2 {i} {j} {_fmt([z[0], z[1], _yaw(z[3:])])} {_fmt(_upper(info))}")
        else:
            info = np.linalg.inv(cov)
            lines.append(
                f"EDGE_SE3:QUAT {i} {j} {_fmt([*z[:3], *z[4:], z[3]])} {_fmt(_upper(info))}"
            )
    path.write_text("\n".join(lines) + "\n")
    truth_path.write_text("\n".join(vertex_lines(graph.poses_true)) + "\n")
    return truth_path


def from_constraints(
    constraints: Sequence[Any], *, planar: bool, truth: Array | None = None
) -> PoseGraph:
    """Build a :class:`PoseGraph` from a reader's constraint list (real or written files).

    Parameters
    ----------
    constraints : list
        Objects with ``kind`` (``"odometry"``, ``"loop_closure"``/``"loop"``), ``source``/``i``,
        ``target``/``j``, ``mean``/``z`` and ``cov`` in the layout of
        ``mcsm_client.datasets.Constraint`` (planar ``[dx, dy, dtheta]`` with a 3x3 covariance,
        3D ``(7,)`` with a 6x6 covariance) or of :class:`Constraint`. Pose ids must be
        ``0..P-1``; landmark observations are refused.
    planar : bool
        Planar graph (3-DoF means and covariances are lifted to the 7/6-D layout).
    truth : (P, 7) float64, optional
        Ground truth poses; default NaN (ATE/NEES then cannot be computed).

    Returns
    -------
    PoseGraph
    """
    # The readers' constraints come from mcsm_client, so their planar layout is the client's:
    # one lift for both (the simulator above stays free of mcsm).
    from mcsm_client.sampling import planar_cov_to_pose_cov, pose_from_planar

    pairs, means, covs, loops = [], [], [], []
    for c in constraints:
        kind = str(c.kind)
        if kind == "landmark":
            raise ValueError("point observations are not part of a pose graph")
        i = int(getattr(c, "source", getattr(c, "i", -1)))
        j = int(getattr(c, "target", getattr(c, "j", -1)))
        z = np.asarray(getattr(c, "mean", getattr(c, "z", None)), dtype=float)
        cov = np.asarray(c.cov, dtype=float)
        if z.shape == (3,):
            z, cov = pose_from_planar(z), planar_cov_to_pose_cov(cov)
        pairs.append((i, j))
        means.append(z)
        covs.append(cov)
        loops.append(kind != "odometry")
    edges = np.asarray(pairs, dtype=np.int64)
    n_poses = int(edges.max()) + 1
    poses = np.full((n_poses, 7), np.nan) if truth is None else np.asarray(truth, dtype=float)
    return PoseGraph(poses, edges, np.asarray(means), np.asarray(covs),
                     np.asarray(loops, dtype=bool), planar, {"source": "constraints"})


def _yaw(q: Array) -> float:
    return float(2.0 * np.arctan2(q[3], q[0]))


def main(argv: list[str] | None = None) -> None:
    """Command line: simulate one graph, print a summary, optionally write g2o files."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--planar", action="store_true", help="2D variant")
    ap.add_argument("--poses", type=int, default=1200)
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--g2o", type=Path, default=None, help="write the graph to this g2o file")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    sim = simulate_2d if args.planar else simulate_3d
    graph = sim(args.poses, rng=rng)
    dr = dead_reckoning(graph)
    err = np.linalg.norm(dr[:, :3] - graph.poses_true[:, :3], axis=1)
    print(f"poses {graph.n_poses}  loop closures {graph.n_loops}  planar {graph.planar}")
    print(f"dead-reckoning position error: final {err[-1]:.3f} m, max {err.max():.3f} m")
    if args.g2o is not None:
        truth = write_g2o(graph, args.g2o)
        print(f"wrote {args.g2o} and {truth}")


if __name__ == "__main__":
    main()
