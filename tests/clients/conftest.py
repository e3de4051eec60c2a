"""Fixtures for the client tests: GTSAM reference solutions of datasets, a real server."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
from mcsm_client.datasets import Dataset
from mcsm_client.process import ServerProcess

#: N of the maps served to the client tests.
SERVER_N = 200


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """``mcsm serve`` (real subprocess, free loopback port, N = 200) with several maps."""
    d = tmp_path_factory.mktemp("srv")
    with ServerProcess(d / "a.mcap", n_samples=SERVER_N,
                       maps=("default", "sim", "cli", "play", "robots", "examples")) as srv:
        yield srv
    assert srv.returncode == 0, srv.log_tail()


@pytest.fixture(scope="session")
def server_b(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerProcess]:
    """A second server (robot B's), N = 200."""
    d = tmp_path_factory.mktemp("srv_b")
    with ServerProcess(d / "b.mcap", n_samples=SERVER_N, maps=("robots", "examples")) as srv:
        yield srv
    assert srv.returncode == 0, srv.log_tail()


def _point_error(z: np.ndarray):  # type: ignore[no-untyped-def]
    """GTSAM CustomFactor error of a Cartesian point sighting ``z`` (2,) from a Pose2."""

    def err(this, values, jac):  # type: ignore[no-untyped-def]
        # landmark in the pose's frame: q = R(θ)ᵀ (l − t); Jacobians for Pose2's right
        # retraction (t + R δt, θ + δθ) and for the point.
        p = values.atPose2(this.keys()[0])
        lm = values.atPoint2(this.keys()[1])
        co, si = np.cos(p.theta()), np.sin(p.theta())
        rot = np.array([[co, -si], [si, co]])
        q = rot.T @ (lm - np.array([p.x(), p.y()]))
        if jac is not None:
            jac[0] = np.array([[-1.0, 0.0, q[1]], [0.0, -1.0, -q[0]]])
            jac[1] = rot.T
        return q - z

    return err


def _solve(ds: Dataset) -> tuple[Any, Any, float, int]:
    """(graph, optimum, chi2, dof): our constraints as a GTSAM graph, optimised with LM."""
    gtsam = pytest.importorskip("gtsam")

    def xk(i: int) -> int:
        return int(gtsam.symbol("x", i))

    def lk(j: int) -> int:
        return int(gtsam.symbol("l", j))

    graph = gtsam.NonlinearFactorGraph()
    est: dict[int, object] = {}
    m = 0
    for c in ds.constraints:
        noise = gtsam.noiseModel.Gaussian.Covariance(c.cov)
        if c.is_point:
            graph.add(gtsam.CustomFactor(noise, [xk(c.source), lk(c.target)],
                                         _point_error(c.mean.copy())))
            if lk(c.target) not in est:
                est[lk(c.target)] = est[xk(c.source)].transformFrom(c.mean)  # type: ignore
            m += 2
            continue
        if ds.dim == 2:
            z = gtsam.Pose2(*c.mean)
            graph.add(gtsam.BetweenFactorPose2(xk(c.source), xk(c.target), z, noise))
            m += 3
        else:
            z = gtsam.Pose3(gtsam.Rot3.Quaternion(*c.mean[3:]), c.mean[:3])
            perm = [3, 4, 5, 0, 1, 2]  # ours [t, r] -> gtsam's [r, t]
            cov = c.cov[np.ix_(perm, perm)]
            graph.add(gtsam.BetweenFactorPose3(xk(c.source), xk(c.target), z,
                                               gtsam.noiseModel.Gaussian.Covariance(cov)))
            m += 6
        a, b = xk(c.source), xk(c.target)
        if a not in est and b not in est:
            est[a] = gtsam.Pose2() if ds.dim == 2 else gtsam.Pose3()
        if b not in est:
            est[b] = est[a].compose(z)  # type: ignore[attr-defined]
        elif a not in est:
            est[a] = est[b].compose(z.inverse())  # type: ignore[attr-defined]
    values = gtsam.Values()
    n_par = 0
    for key, val in est.items():
        values.insert(key, val)
        n_par += val.dim() if hasattr(val, "dim") else 2  # Point2 is a numpy array
    pd = 3 if ds.dim == 2 else 6
    anchor = xk(ds.constraints[0].source)
    prior = (gtsam.PriorFactorPose2 if ds.dim == 2 else gtsam.PriorFactorPose3)(
        anchor, est[anchor], gtsam.noiseModel.Isotropic.Sigma(pd, 1e-6))
    graph.add(prior)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(100)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return graph, result, 2.0 * graph.error(result), m - (n_par - pd)




@pytest.fixture
def gtsam_chi2() -> Callable[[Dataset], tuple[float, int]]:
    """``f(ds) -> (chi2, dof)`` of our constraints at GTSAM's LM optimum (skips without gtsam).

    Built from *our* parsed constraints: Pose2/Pose3 between factors with our covariances
    (Pose3 blocks reordered to GTSAM's rotation-first tangent) and a Cartesian point factor;
    pose 0 is fixed by a tight prior that is not counted. dof = residual dims − free params.
    """
    pytest.importorskip("gtsam")

    def f(ds: Dataset) -> tuple[float, int]:
        _, _, chi2, dof = _solve(ds)
        return chi2, dof

    return f


@pytest.fixture
def gtsam_solution() -> Callable[[Dataset], dict[str, np.ndarray]]:
    """``f(ds) -> {frame name: optimum}``: poses ``x{i}`` as ``(x, y, θ)`` (planar) and
    landmarks ``l{j}`` as ``(x, y)``, in the frame of the first constraint's source pose."""
    gtsam = pytest.importorskip("gtsam")

    def f(ds: Dataset) -> dict[str, np.ndarray]:
        _, result, _, _ = _solve(ds)
        out: dict[str, np.ndarray] = {}
        for key in result.keys():
            sym = gtsam.Symbol(key)
            ch, idx = chr(sym.chr()), int(sym.index())
            if ch == "x":
                p = result.atPose2(key)
                out[f"x{idx}"] = np.array([p.x(), p.y(), p.theta()])
            else:
                out[f"l{idx}"] = np.asarray(result.atPoint2(key), dtype=np.float64)
        return out

    return f
