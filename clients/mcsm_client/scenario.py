"""The paper's §6 simulation: a robot on a 50 m circle observing 200 point landmarks.

PAPER §4 (the paper's §6): the robot drives a circle of radius 50 m; at regular intervals the
odometry gives the displacement ``(dx, dy, dθ)`` since the last reading, in the previous pose's
frame, and a laser observes a random subset of the landmarks in the front 180° field of view
within 30 m, as ``(x, y)`` in the robot frame. White Gaussian noise: σ = (0.4, 0.4) m for the
laser, (0.01, 0.002) m for the odometry translation and ``sigma_theta_deg`` for its heading. The
first revolution closes the large loop at about iteration 340.

Everything here is pure numpy and draws random numbers only from an explicit
``rng: np.random.Generator``:

- :class:`PaperScenarioConfig` and :func:`generate_paper_scenario` build a :class:`Scenario`
  (ground truth plus noisy readings), reproducible from the seed of ``rng``.
- :func:`odometry_samples` and :func:`point_samples` turn one reading into the sample sets the
  core expects: an AT ``(N, 7)`` ``x y z qw qx qy qz`` and a point ``(N, 3)`` (planar: z = 0,
  rotation about z).
- :func:`run_scenario_on_map` feeds a scenario into a :class:`mcsm.StochasticMap` with frames
  ``"x{k}"`` (poses) and ``"l{j}"`` (landmarks), optionally bounded (old poses removed, ``x0``
  kept as the anchor).
- :func:`landmark_estimates`, :func:`landmark_rms` and :func:`landmark_nees` score a map (or any
  estimate) against ground truth expressed in ``x0``'s frame.

Frame convention: ``x0`` is the world origin with heading 0 (the circle's centre is at
``(0, radius_m)``, the robot turns left), so ground truth in ``x0``'s frame is the world frame.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

#: One sighting: ``(landmark_id, (x, y))``, the landmark's noisy position in the robot frame.
Sighting = tuple[int, tuple[float, float]]


@dataclass(frozen=True)
class PaperScenarioConfig:
    """Parameters of the §6 circle scenario (defaults are the paper's, PAPER §4).

    Parameters
    ----------
    radius_m : float
        Radius of the circular trajectory.
    n_landmarks : int
        Number of point landmarks.
    n_iterations : int
        Number of odometry steps T (poses ``x0 .. xT``).
    steps_per_revolution : int
        Odometry steps per full circle; the first revolution ends at this iteration (≈ 340).
    fov_deg : float
        Field of view of the laser, centred on the robot's heading.
    range_m : float
        Maximum sensing range of the laser.
    sigma_laser_m : tuple of float
        Standard deviation of the laser's ``(x, y)`` noise, robot frame.
    sigma_odometry_m : tuple of float
        Standard deviation of the odometry's ``(dx, dy)`` noise, previous pose's frame.
    sigma_theta_deg : float
        Standard deviation of the odometry's heading noise ``dθ``, degrees (0 in Fig. 4,
        0.1 in Fig. 5).
    p_observe : float
        Probability that a visible landmark is observed at a given step.
    landmark_band_m : float
        Landmarks are placed uniformly in angle around the circle's centre at a distance
        uniform in ``radius_m ± landmark_band_m``.
    """

    radius_m: float = 50.0
    n_landmarks: int = 200
    n_iterations: int = 2000
    steps_per_revolution: int = 340
    fov_deg: float = 180.0
    range_m: float = 30.0
    sigma_laser_m: tuple[float, float] = (0.4, 0.4)
    sigma_odometry_m: tuple[float, float] = (0.01, 0.002)
    sigma_theta_deg: float = 0.0
    p_observe: float = 0.15
    landmark_band_m: float = 20.0

    @property
    def sigma_theta_rad(self) -> float:
        """The odometry heading noise in radians."""
        return float(np.deg2rad(self.sigma_theta_deg))

    @property
    def odometry_cov(self) -> Array:
        """``(3, 3)`` covariance of an odometry reading ``(dx, dy, dθ)`` (m², rad²)."""
        sx, sy = self.sigma_odometry_m
        return np.diag([sx**2, sy**2, self.sigma_theta_rad**2]).astype(np.float64)

    @property
    def laser_cov(self) -> Array:
        """``(2, 2)`` covariance of a sighting ``(x, y)`` in the robot frame (m²)."""
        sx, sy = self.sigma_laser_m
        return np.diag([sx**2, sy**2]).astype(np.float64)


@dataclass(frozen=True)
class Scenario:
    """Ground truth and noisy readings of one run of the §6 scenario.

    Attributes
    ----------
    config : PaperScenarioConfig
        The parameters it was generated with.
    poses : (T+1, 3) float64
        True poses ``(x, y, θ)`` in the world (= ``x0``) frame; ``poses[0]`` is ``(0, 0, 0)``.
    landmarks : (L, 2) float64
        True landmark positions in the world frame (m).
    odometry : (T, 3) float64
        Noisy readings ``(dx, dy, dθ)``: pose k+1 in pose k's frame (m, rad).
    observations : list of list of Sighting
        ``observations[k]`` holds the sightings taken at pose k+1 (after odometry step k), as
        ``(landmark_id, (x, y))`` in that pose's frame, noisy.
    """

    config: PaperScenarioConfig
    poses: Array
    landmarks: Array
    odometry: Array
    observations: list[list[Sighting]] = field(repr=False)

    @property
    def n_iterations(self) -> int:
        """Number of odometry steps T."""
        return int(self.odometry.shape[0])

    @property
    def n_sightings(self) -> int:
        """Total number of landmark sightings over the run."""
        return sum(len(obs) for obs in self.observations)


def se2_relative(pose_a: Array, pose_b: Array) -> Array:
    """Pose b in pose a's frame, ``(dx, dy, dθ)``, for planar poses ``(..., 3)``.

    Parameters
    ----------
    pose_a, pose_b : (..., 3) float64
        Planar poses ``(x, y, θ)`` in a common frame.

    Returns
    -------
    (..., 3) float64
        ``pose_a⁻¹ ∘ pose_b``, with the heading difference wrapped to ``(-π, π]``.
    """
    pose_a = np.asarray(pose_a, dtype=np.float64)
    pose_b = np.asarray(pose_b, dtype=np.float64)
    c, s = np.cos(pose_a[..., 2]), np.sin(pose_a[..., 2])
    dx = pose_b[..., 0] - pose_a[..., 0]
    dy = pose_b[..., 1] - pose_a[..., 1]
    dth = wrap_angle(pose_b[..., 2] - pose_a[..., 2])
    return np.stack([c * dx + s * dy, -s * dx + c * dy, dth], axis=-1)


def se2_compose(pose: Array, delta: Array) -> Array:
    """Compose planar poses: ``pose ∘ delta`` for ``(..., 3)`` arrays ``(x, y, θ)``.

    Parameters
    ----------
    pose : (..., 3) float64
        Pose in the world frame.
    delta : (..., 3) float64
        Displacement in ``pose``'s frame.

    Returns
    -------
    (..., 3) float64
        The composed pose; heading not wrapped.
    """
    pose = np.asarray(pose, dtype=np.float64)
    delta = np.asarray(delta, dtype=np.float64)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    return np.stack([pose[..., 0] + c * delta[..., 0] - s * delta[..., 1],
                     pose[..., 1] + s * delta[..., 0] + c * delta[..., 1],
                     pose[..., 2] + delta[..., 2]], axis=-1)


def wrap_angle(theta: Array | float) -> Array:
    """Wrap angles (rad) to ``(-π, π]``."""
    t = np.asarray(theta, dtype=np.float64)
    return np.asarray(np.pi - np.mod(np.pi - t, 2.0 * np.pi), dtype=np.float64)


def world_to_robot(pose: Array, points: Array) -> Array:
    """Express world points ``(..., 2)`` in the frame of the planar pose ``(3,)``."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    d = np.asarray(points, dtype=np.float64) - pose[:2]
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def generate_paper_scenario(config: PaperScenarioConfig, rng: np.random.Generator) -> Scenario:
    """Generate ground truth and noisy readings for the §6 circle scenario.

    The robot starts at the origin with heading 0 and drives counter-clockwise around the circle
    of centre ``(0, radius_m)``: pose k is at angle ``φ_k = 2π k / steps_per_revolution``,
    ``(R sin φ_k, R (1 − cos φ_k), φ_k)``. Random numbers are drawn in a fixed order: landmark
    placement, then per step odometry noise (dx, dy, dθ), visibility draws, laser noise.

    Parameters
    ----------
    config : PaperScenarioConfig
        Scenario parameters.
    rng : np.random.Generator
        Source of all randomness.

    Returns
    -------
    Scenario
        Ground truth poses and landmarks, noisy odometry and sightings.
    """
    r = float(config.radius_m)
    t = int(config.n_iterations)
    if t < 1 or config.steps_per_revolution < 1 or config.n_landmarks < 0:
        raise ValueError("n_iterations and steps_per_revolution must be >= 1, n_landmarks >= 0")
    centre = np.array([0.0, r])

    ang = rng.uniform(0.0, 2.0 * np.pi, size=config.n_landmarks)
    rad = r + rng.uniform(-config.landmark_band_m, config.landmark_band_m, size=config.n_landmarks)
    # Angle measured like the robot's φ: the robot at φ sits at centre + R (sin φ, −cos φ).
    landmarks = np.stack([centre[0] + rad * np.sin(ang), centre[1] - rad * np.cos(ang)], axis=-1)

    phi = 2.0 * np.pi * np.arange(t + 1) / config.steps_per_revolution
    poses = np.stack([r * np.sin(phi), r * (1.0 - np.cos(phi)), phi], axis=-1)

    true_odo = se2_relative(poses[:-1], poses[1:])
    sigma_odo = np.array([config.sigma_odometry_m[0], config.sigma_odometry_m[1],
                          config.sigma_theta_rad])
    half_fov = np.deg2rad(config.fov_deg) / 2.0
    sigma_laser = np.asarray(config.sigma_laser_m, dtype=np.float64)

    odometry = np.empty((t, 3))
    observations: list[list[Sighting]] = []
    for k in range(t):
        odometry[k] = true_odo[k] + sigma_odo * rng.standard_normal(3)
        local = world_to_robot(poses[k + 1], landmarks)
        dist = np.hypot(local[:, 0], local[:, 1])
        bearing = np.arctan2(local[:, 1], local[:, 0])
        visible = (dist <= config.range_m) & (np.abs(bearing) <= half_fov)
        chosen = visible & (rng.uniform(size=config.n_landmarks) < config.p_observe)
        ids = np.flatnonzero(chosen)
        noisy = local[ids] + sigma_laser * rng.standard_normal((ids.size, 2))
        observations.append([(int(j), (float(p[0]), float(p[1]))) for j, p in zip(ids, noisy,
                                                                                   strict=True)])
    # Headings are kept unwrapped in ``poses``; relative quantities wrap where needed.
    return Scenario(config=config, poses=poses, landmarks=landmarks, odometry=odometry,
                    observations=observations)


def planar_at(x: Array, y: Array, theta: Array) -> Array:
    """Planar transforms as AT samples ``(N, 7)`` ``x y z qw qx qy qz`` (z = 0, rotation about z).

    Parameters
    ----------
    x, y : (N,) float64
        Translation (m).
    theta : (N,) float64
        Rotation about z (rad).

    Returns
    -------
    (N, 7) float64
        C-contiguous sample set with unit quaternions on the ``qw >= 0`` hemisphere.
    """
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[0]
    out = np.zeros((n, 7))
    out[:, 0] = x
    out[:, 1] = y
    half = wrap_angle(np.asarray(theta, dtype=np.float64)) / 2.0
    out[:, 3] = np.cos(half)
    out[:, 6] = np.sin(half)
    return out


def odometry_samples(reading: Array, cov: Array, n_samples: int,
                     rng: np.random.Generator) -> Array:
    """Sample set of one odometry reading: the AT ``x{k} → x{k+1}`` as ``(N, 7)``.

    Draws ``(dx, dy, dθ) ~ N(reading, cov)`` sample by sample (a zero heading variance gives a
    constant rotation), then converts to the core's layout.

    Parameters
    ----------
    reading : (3,) float64
        ``(dx, dy, dθ)`` in the previous pose's frame (m, rad).
    cov : (3, 3) float64
        Its covariance (diagonal or not; may be singular).
    n_samples : int
        N.
    rng : np.random.Generator
        Source of the noise.

    Returns
    -------
    (N, 7) float64
        AT samples ``x y z qw qx qy qz``.
    """
    draws = np.asarray(reading, dtype=np.float64) + _gaussian(cov, n_samples, rng)
    return planar_at(draws[:, 0], draws[:, 1], draws[:, 2])


def point_samples(reading: Sequence[float] | Array, cov: Array, n_samples: int,
                  rng: np.random.Generator) -> Array:
    """Sample set of one point sighting: ``(N, 3)`` ``x y z`` in the observer's frame (z = 0).

    Parameters
    ----------
    reading : (2,) float64
        ``(x, y)`` of the landmark in the robot frame (m).
    cov : (2, 2) float64
        Its covariance.
    n_samples : int
        N.
    rng : np.random.Generator
        Source of the noise.

    Returns
    -------
    (N, 3) float64
        Point samples.
    """
    out = np.zeros((n_samples, 3))
    out[:, :2] = np.asarray(reading, dtype=np.float64) + _gaussian(cov, n_samples, rng)
    return out


def _gaussian(cov: Array, n_samples: int, rng: np.random.Generator) -> Array:
    """Draws ``(N, d)`` from ``N(0, cov)`` for a symmetric PSD (possibly singular) ``cov``."""
    cov = np.asarray(cov, dtype=np.float64)
    w, v = np.linalg.eigh(cov)
    root = v * np.sqrt(np.clip(w, 0.0, None))
    return np.asarray(rng.standard_normal((n_samples, cov.shape[0])) @ root.T, dtype=np.float64)


class MapLike(Protocol):
    """What :func:`run_scenario_on_map` and the metrics need from a stochastic map."""

    def update(self, a: str, b: str, samples: Array, /) -> Any: ...

    def remove(self, frame: str, /) -> Any: ...

    def marginal(self, a: str, b: str, /) -> tuple[Array, Array]: ...

    def __contains__(self, frame: object, /) -> bool: ...


def pose_frame(k: int) -> str:
    """Name of pose k's frame in the map (``"x{k}"``)."""
    return f"x{k}"


def landmark_frame(j: int) -> str:
    """Name of landmark j's frame in the map (``"l{j}"``)."""
    return f"l{j}"


IterationCallback = Callable[[int, Any], None]


def run_scenario_on_map(scenario: Scenario, smap: MapLike, n_samples: int,
                        rng: np.random.Generator, *, bounded: bool = True,
                        callback: IterationCallback | None = None,
                        n_iterations: int | None = None) -> None:
    """Feed a scenario's readings into a stochastic map, iteration by iteration.

    Iteration k (1-based after it completes) does, in order:
    ``update("x{k-1}", "x{k}", odometry samples)``, then for each sighting j at pose k
    ``update("x{k}", "l{j}", point samples)``, then, when ``bounded``, ``remove("x{k-1}")``
    unless it is ``x0`` (kept as the anchor: the map holds x0, the current pose and the
    landmarks). Then ``callback(k, smap)``.

    Parameters
    ----------
    scenario : Scenario
        Readings to feed (the filter's noise model is the scenario's config).
    smap : MapLike
        The map, usually a fresh ``mcsm.StochasticMap(n_samples, ...)``.
    n_samples : int
        N, the map's sample count.
    rng : np.random.Generator
        Source of the sample sets' noise.
    bounded : bool
        Remove superseded poses (keeps the map at L + 2 frames).
    callback : callable, optional
        ``callback(iteration, smap)`` after each iteration.
    n_iterations : int, optional
        Stop after this many iterations (default: all of them).
    """
    odo_cov = scenario.config.odometry_cov
    laser_cov = scenario.config.laser_cov
    t_end = scenario.n_iterations if n_iterations is None else min(n_iterations,
                                                                   scenario.n_iterations)
    for k in range(t_end):
        smap.update(pose_frame(k), pose_frame(k + 1),
                    odometry_samples(scenario.odometry[k], odo_cov, n_samples, rng))
        for j, xy in scenario.observations[k]:
            smap.update(pose_frame(k + 1), landmark_frame(j),
                        point_samples(xy, laser_cov, n_samples, rng))
        if bounded and k >= 1:
            smap.remove(pose_frame(k))
        if callback is not None:
            callback(k + 1, smap)


def landmarks_in_frame(scenario: Scenario, k: int = 0) -> Array:
    """True landmark positions ``(L, 2)`` in pose k's frame (default x0, i.e. the world)."""
    return world_to_robot(scenario.poses[k], scenario.landmarks)


def landmark_estimates(smap: MapLike, landmark_ids: Sequence[int] | Array,
                       anchor: str = "x0") -> tuple[Array, Array, Array]:
    """Mean and covariance of each landmark's ``(x, y)`` in the anchor's frame.

    Uses ``smap.marginal(anchor, "l{j}")``: the first two entries of its mean and the top-left
    ``2 × 2`` of its tangent covariance (the translation block).

    Parameters
    ----------
    smap : MapLike
        The map.
    landmark_ids : sequence of int
        Candidate landmark ids; those not (yet) in the map are skipped.
    anchor : str
        Frame the estimates are expressed in.

    Returns
    -------
    ids : (K,) int64
        Ids of the landmarks present in the map.
    means : (K, 2) float64
        Estimated positions (m).
    covs : (K, 2, 2) float64
        Their covariances (m²).
    """
    ids: list[int] = []
    means: list[Array] = []
    covs: list[Array] = []
    for j in landmark_ids:
        name = landmark_frame(int(j))
        if name not in smap:
            continue
        mean, cov = smap.marginal(anchor, name)
        ids.append(int(j))
        means.append(np.asarray(mean[:2], dtype=np.float64))
        covs.append(np.asarray(cov[:2, :2], dtype=np.float64))
    if not ids:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2))
    return np.asarray(ids, dtype=np.int64), np.stack(means), np.stack(covs)


def landmark_rms(means: Array, truth: Array) -> float:
    """RMS distance (m) between estimated and true positions, ``(K, 2)`` each; NaN if K = 0."""
    if means.shape[0] == 0:
        return float("nan")
    return float(np.sqrt(np.mean(np.sum((means - truth) ** 2, axis=-1))))


def landmark_nees(means: Array, covs: Array, truth: Array) -> float:
    """Average normalised estimation error squared per degree of freedom.

    ``mean_j (e_jᵀ C_j⁻¹ e_j) / 2`` with ``e_j = mean_j − truth_j``: about 1 for an honest
    estimator, larger when it is overconfident. Singular covariances use a pseudo-inverse.

    Parameters
    ----------
    means : (K, 2) float64
        Estimated positions.
    covs : (K, 2, 2) float64
        Their covariances.
    truth : (K, 2) float64
        True positions.

    Returns
    -------
    float
        NEES per dof; NaN if K = 0, ``inf`` if a covariance is exactly zero with a nonzero error.
    """
    if means.shape[0] == 0:
        return float("nan")
    err = means - truth
    dof = err.shape[-1]
    with np.errstate(divide="ignore", invalid="ignore"):
        sol = np.linalg.pinv(covs, hermitian=True) @ err[..., None]
    nees = np.einsum("ki,ki->k", err, sol[..., 0])
    return float(np.mean(nees) / dof)


def score_map(smap: MapLike, scenario: Scenario, anchor: str = "x0") -> dict[str, float]:
    """RMS and NEES per dof of the landmarks present in the map, against ground truth.

    Parameters
    ----------
    smap : MapLike
        The map (frames named ``"x{k}"`` / ``"l{j}"``).
    scenario : Scenario
        Provides ground truth; it is expressed in ``x0``'s frame (the world frame).
    anchor : str
        Must be ``"x0"`` (ground truth is expressed there).

    Returns
    -------
    dict
        ``{"rms_m": ..., "nees_per_dof": ..., "n_landmarks": ...}``.
    """
    truth_all = landmarks_in_frame(scenario, 0)
    ids, means, covs = landmark_estimates(smap, range(truth_all.shape[0]), anchor)
    truth = truth_all[ids]
    return {"rms_m": landmark_rms(means, truth), "nees_per_dof": landmark_nees(means, covs, truth),
            "n_landmarks": float(ids.size)}
