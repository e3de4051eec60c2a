"""Linear-Gaussian oracle: a translation-only pose chain with loop closures.

With every rotation exactly the identity, compounding is addition and the exact posterior of the
frames' positions relative to x0 is the weighted least-squares solution of the graph (closed
form). The map must reach it as N grows (PAPER §3; issue: joint update convergence).
"""

from __future__ import annotations

import numpy as np
from mcsm import StochasticMap

N_FRAMES = 10
ODO_COV = np.diag([0.04, 0.09, 0.01])
LOOP_COV = np.diag([0.01, 0.01, 0.04])
LOOPS = [(0, 4), (2, 7), (5, 9), (0, 9), (3, 8), (1, 6)]


def make_problem(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list]:
    """True positions, odometry readings and loop-closure readings."""
    truth = np.cumsum(np.r_[np.zeros((1, 3)), rng.normal(0, 1.0, (N_FRAMES - 1, 3))], axis=0)
    odo = np.diff(truth, axis=0) + rng.multivariate_normal(np.zeros(3), ODO_COV, N_FRAMES - 1)
    loops = [(i, j, truth[j] - truth[i] + rng.multivariate_normal(np.zeros(3), LOOP_COV))
             for i, j in LOOPS]
    return truth, odo, loops


def wls(odo: np.ndarray, loops: list) -> tuple[np.ndarray, np.ndarray]:
    """Exact posterior mean (N_FRAMES-1, 3) and covariance of frames 1.. relative to frame 0."""
    k = N_FRAMES - 1
    rows, vals, infos = [], [], []
    for i in range(k):
        rows.append((i, i + 1))
        vals.append(odo[i])
        infos.append(np.linalg.inv(ODO_COV))
    for i, j, z in loops:
        rows.append((i, j))
        vals.append(z)
        infos.append(np.linalg.inv(LOOP_COV))
    h = np.zeros((3 * k, 3 * k))
    g = np.zeros(3 * k)
    for (i, j), z, info in zip(rows, vals, infos, strict=True):
        a = np.zeros((3, 3 * k))
        if i > 0:
            a[:, 3 * (i - 1):3 * i] = -np.eye(3)
        a[:, 3 * (j - 1):3 * j] = np.eye(3)
        h += a.T @ info @ a
        g += a.T @ info @ z
    cov = np.linalg.inv(h)
    return (cov @ g).reshape(k, 3), cov


def run_map(odo: np.ndarray, loops: list, n: int, rng: np.random.Generator,
            **options: object) -> StochasticMap:
    """Odometry as new frames, then the loop closures, all as sampled ATs."""
    m = StochasticMap(n, **options)  # type: ignore[arg-type]

    def at(mean: np.ndarray, cov: np.ndarray) -> np.ndarray:
        x = np.zeros((n, 7))
        x[:, :3] = rng.multivariate_normal(mean, cov, n)
        x[:, 3] = 1.0
        return x

    for i in range(N_FRAMES - 1):
        m.update(f"x{i}", f"x{i + 1}", at(odo[i], ODO_COV))
    for i, j, z in loops:
        m.update(f"x{i}", f"x{j}", at(z, LOOP_COV))
    return m


def normalised_errors(m: StochasticMap, mean: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    """RMS of (map mean − exact mean)/exact σ, and RMS relative error of the marginal σ."""
    k = N_FRAMES - 1
    got = np.array([m.marginal("x0", f"x{i + 1}")[0][:3] for i in range(k)])
    got_sd = np.array([np.sqrt(np.diag(m.marginal("x0", f"x{i + 1}")[1])[:3]) for i in range(k)])
    sd = np.sqrt(np.diag(cov)).reshape(k, 3)
    return float(np.sqrt(np.mean(((got - mean) / sd) ** 2))), float(
        np.sqrt(np.mean((got_sd / sd - 1.0) ** 2)))
