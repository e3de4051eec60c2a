"""Classic EKF-SLAM stochastic map: planar robot pose plus 2D point landmarks, full covariance.

The baseline the Monte Carlo map is measured against (issue 6, issue 7). State
``[x, y, θ, l0x, l0y, l1x, l1y, ...]`` in the frame of the first pose (``x0``), one joint
Gaussian with full covariance (Smith, Self & Cheeseman's stochastic map):

- :meth:`EkfSlam.predict` composes the pose with an odometry reading ``(dx, dy, dθ)`` given in the
  current pose's frame (the same model as :mod:`mcsm_client.scenario`): O(M) per step.
- :meth:`EkfSlam.observe` takes a Cartesian point sighting ``(x, y)`` of landmark j in the robot
  frame, ``z = R(θ)ᵀ (l_j − p) + v``; a new landmark is initialised from it (augmentation), a
  known one is updated with the Kalman gain: O(M²) per sighting.

With zero heading noise and an exactly known initial heading the model is linear in the unknowns
(every heading is known) and this filter is the exact Kalman filter; ``tests/experiments/
test_ekf.py`` checks it against the closed-form weighted least-squares posterior.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence

import numpy as np
import numpy.typing as npt
from mcsm_client.scenario import Scenario

Array = npt.NDArray[np.float64]


class EkfSlam:
    """EKF-SLAM over one planar pose and point landmarks (full covariance).

    Parameters
    ----------
    odometry_cov : (3, 3) float64
        Default covariance of an odometry reading ``(dx, dy, dθ)`` (m², rad²).
    laser_cov : (2, 2) float64
        Default covariance of a sighting ``(x, y)`` in the robot frame (m²).
    initial_pose : (3,) float64, optional
        Mean of the first pose (default the origin: estimates are in ``x0``'s frame).
    initial_cov : (3, 3) float64, optional
        Its covariance (default zero: ``x0`` is the anchor).
    """

    def __init__(self, odometry_cov: Array, laser_cov: Array,
                 initial_pose: Array | None = None, initial_cov: Array | None = None) -> None:
        self.odometry_cov = np.asarray(odometry_cov, dtype=np.float64)
        self.laser_cov = np.asarray(laser_cov, dtype=np.float64)
        self._cap = 64
        self._n = 3
        self._x = np.zeros(self._cap)
        self._p = np.zeros((self._cap, self._cap))
        if initial_pose is not None:
            self._x[:3] = initial_pose
        if initial_cov is not None:
            self._p[:3, :3] = initial_cov
        self._slot: dict[int, int] = {}

    # -- state access -------------------------------------------------------------------------

    @property
    def state_dim(self) -> int:
        """Length of the state vector (3 + 2 · number of landmarks)."""
        return self._n

    @property
    def mean(self) -> Array:
        """A copy of the state mean ``(3 + 2L,)``."""
        return self._x[: self._n].copy()

    @property
    def cov(self) -> Array:
        """A copy of the full state covariance ``(3 + 2L, 3 + 2L)``."""
        return self._p[: self._n, : self._n].copy()

    @property
    def pose(self) -> Array:
        """Current pose mean ``(x, y, θ)``."""
        return self._x[:3].copy()

    @property
    def pose_cov(self) -> Array:
        """Current pose covariance ``(3, 3)``."""
        return self._p[:3, :3].copy()

    def landmark_ids(self) -> list[int]:
        """Ids of the landmarks in the state, in the order they were first seen."""
        return list(self._slot)

    def __contains__(self, landmark_id: object) -> bool:
        return landmark_id in self._slot

    def landmark_estimates(self, landmark_ids: Iterable[int] | None = None
                           ) -> tuple[npt.NDArray[np.int64], Array, Array]:
        """Means and marginal covariances of landmarks.

        Parameters
        ----------
        landmark_ids : iterable of int, optional
            Ids to return (those not in the state are skipped); default all, sorted.

        Returns
        -------
        ids : (K,) int64
        means : (K, 2) float64
        covs : (K, 2, 2) float64
        """
        wanted = sorted(self._slot) if landmark_ids is None else [
            int(j) for j in landmark_ids if int(j) in self._slot]
        idx = np.asarray([self._slot[j] for j in wanted], dtype=np.int64)
        ids = np.asarray(wanted, dtype=np.int64)
        if idx.size == 0:
            return ids, np.zeros((0, 2)), np.zeros((0, 2, 2))
        cols = idx[:, None] + np.arange(2)
        means = self._x[cols]
        covs = self._p[cols[:, :, None], cols[:, None, :]]
        return ids, means, covs

    # -- filter steps ---------------------------------------------------------------------------

    def predict(self, reading: Array, cov: Array | None = None) -> None:
        """Move the pose by an odometry reading ``(dx, dy, dθ)`` in the current pose's frame.

        Parameters
        ----------
        reading : (3,) float64
            Displacement (m, rad).
        cov : (3, 3) float64, optional
            Its covariance (default ``odometry_cov``).
        """
        q = self.odometry_cov if cov is None else np.asarray(cov, dtype=np.float64)
        dx, dy, dth = (float(v) for v in reading)
        x, y, th = self._x[:3]
        c, s = np.cos(th), np.sin(th)
        f = np.array([[1.0, 0.0, -s * dx - c * dy],
                      [0.0, 1.0, c * dx - s * dy],
                      [0.0, 0.0, 1.0]])
        g = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._x[:3] = [x + c * dx - s * dy, y + s * dx + c * dy, th + dth]
        n = self._n
        p = self._p
        p[:3, 3:n] = f @ p[:3, 3:n]
        p[3:n, :3] = p[:3, 3:n].T
        p[:3, :3] = f @ p[:3, :3] @ f.T + g @ q @ g.T

    def observe(self, landmark_id: int, xy: Sequence[float] | Array,
                cov: Array | None = None) -> bool:
        """Incorporate one Cartesian sighting of a landmark from the current pose.

        Parameters
        ----------
        landmark_id : int
            The landmark's id.
        xy : (2,) float64
            Its measured position in the robot frame (m).
        cov : (2, 2) float64, optional
            Measurement covariance (default ``laser_cov``).

        Returns
        -------
        bool
            True if the landmark was new (added to the state), False if it was updated.
        """
        r = self.laser_cov if cov is None else np.asarray(cov, dtype=np.float64)
        z = np.asarray(xy, dtype=np.float64)
        x, y, th = self._x[:3]
        c, s = np.cos(th), np.sin(th)
        rot = np.array([[c, -s], [s, c]])
        if landmark_id not in self._slot:
            self._augment(landmark_id, z, r, rot)
            return True
        i = self._slot[landmark_id]
        n = self._n
        d = self._x[i:i + 2] - self._x[:2]
        z_hat = rot.T @ d
        # H is nonzero on the pose (3 columns) and on the landmark (2 columns) only.
        h_pose = np.array([[-c, -s, z_hat[1]], [s, -c, -z_hat[0]]])
        h_lm = rot.T
        p = self._p
        ph = p[:n, :3] @ h_pose.T + p[:n, i:i + 2] @ h_lm.T          # P Hᵀ, (n, 2)
        hph = h_pose @ ph[:3] + h_lm @ ph[i:i + 2]
        s_mat = hph + r
        gain = np.linalg.solve(s_mat, ph.T).T                           # (n, 2)
        self._x[:n] += gain @ (z - z_hat)
        p[:n, :n] -= gain @ s_mat @ gain.T
        p[:n, :n] = 0.5 * (p[:n, :n] + p[:n, :n].T)
        return False

    def _augment(self, landmark_id: int, z: Array, r: Array, rot: Array) -> None:
        n = self._n
        if n + 2 > self._cap:
            cap = 2 * self._cap
            x_new = np.zeros(cap)
            x_new[:n] = self._x[:n]
            p_new = np.zeros((cap, cap))
            p_new[:n, :n] = self._p[:n, :n]
            self._x, self._p, self._cap = x_new, p_new, cap
        rz = rot @ z
        j_pose = np.array([[1.0, 0.0, -rz[1]], [0.0, 1.0, rz[0]]])
        p = self._p
        self._x[n:n + 2] = self._x[:2] + rz
        cross = j_pose @ p[:3, :n]                                      # (2, n)
        p[n:n + 2, :n] = cross
        p[:n, n:n + 2] = cross.T
        p[n:n + 2, n:n + 2] = j_pose @ p[:3, :3] @ j_pose.T + rot @ r @ rot.T
        self._slot[landmark_id] = n
        self._n = n + 2


def run_ekf_on_scenario(scenario: Scenario,
                        callback: Callable[[int, EkfSlam], None] | None = None,
                        n_iterations: int | None = None) -> EkfSlam:
    """Run EKF-SLAM on a scenario's readings (the same readings the Monte Carlo map gets).

    Iteration k: ``predict(odometry[k-1])``, then ``observe`` each sighting taken at pose k,
    then ``callback(k, ekf)``.

    Parameters
    ----------
    scenario : Scenario
        Readings and noise model.
    callback : callable, optional
        Called after each iteration.
    n_iterations : int, optional
        Stop early.

    Returns
    -------
    EkfSlam
        The filter after the last iteration.
    """
    ekf = EkfSlam(scenario.config.odometry_cov, scenario.config.laser_cov)
    t_end = scenario.n_iterations if n_iterations is None else min(n_iterations,
                                                                   scenario.n_iterations)
    for k in range(t_end):
        ekf.predict(scenario.odometry[k])
        for j, xy in scenario.observations[k]:
            ekf.observe(j, xy)
        if callback is not None:
            callback(k + 1, ekf)
    return ekf
