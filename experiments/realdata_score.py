"""Scoring for the real-data benchmark (``benchmarks/realdata.py``): errors of a map, of GTSAM
values and of EKF-SLAM against the batch optimum (along the run and at the end), ATE against
ground truth, NEES per degree of freedom, and the exact-covariance EKF pose-graph row.

Errors are RMS position differences in the anchor's frame: landmarks seen so far for a bounded
landmark map (Victoria Park), poses so far for a pose graph; ATE after a rigid alignment
(:func:`experiments.pose_graph.ate`).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np


class Scorer:
    """Errors of any estimator against the batch optimum, along the run and at the end."""

    def __init__(self, problem: Any, lm: Any) -> None:
        from experiments import realdata_gtsam as rg

        self.p = problem
        self.poses = [p for p, _ in problem.steps]
        seen: dict[int, int] = {}
        for k, (_, es) in enumerate(problem.steps):
            for e in es:
                if e.is_point:
                    seen.setdefault(e.j, k)
        self.lm_first = seen
        self.landmarks = sorted(seen)
        pp, ll = rg.estimates(lm, problem, self.poses, self.landmarks)
        self.ref_poses, self.ref_lms = pp, ll

    def _ids(self, step: int) -> tuple[list[int], np.ndarray]:
        if self.p.bounded:
            idx = [n for n, j in enumerate(self.landmarks) if self.lm_first[j] < step]
            return [self.landmarks[n] for n in idx], self.ref_lms[idx]
        return self.poses[:step], self.ref_poses[:step]

    @staticmethod
    def rms(est: np.ndarray, ref: np.ndarray) -> float:
        if len(ref) == 0:
            return float("nan")
        return float(np.sqrt(np.mean(np.sum((est - ref) ** 2, axis=1))))

    def map_error(self, smap: Any, step: int) -> float:
        from experiments.realdata_run import positions

        ids, ref = self._ids(step)
        names = [f"l{j}" for j in ids] if self.p.bounded else [f"x{i}" for i in ids]
        est = positions(smap, f"x{self.poses[0]}", names)[:, :self.p.dim]
        return self.rms(est, ref)

    def values_error(self, values: Any, step: int) -> float:
        from experiments import realdata_gtsam as rg

        ids, ref = self._ids(step)
        pp, ll = (rg.estimates(values, self.p, [], ids) if self.p.bounded
                  else rg.estimates(values, self.p, ids, []))
        return self.rms(ll if self.p.bounded else pp, ref)

    def dict_error(self, lms: dict[int, np.ndarray], step: int) -> float:
        ids, ref = self._ids(step)
        return self.rms(np.stack([lms[j] for j in ids]), ref)

    def ate(self, est_positions: np.ndarray) -> float:
        from experiments.pose_graph import ate

        if self.p.truth is None:
            return float("nan")
        truth = np.stack([self.p.truth[i] for i in self.poses])
        pad = np.zeros((len(truth), 7))
        pad[:, :self.p.dim] = est_positions
        tr = np.zeros((len(truth), 7))
        tr[:, :self.p.dim] = truth[:, :self.p.dim]
        return ate(pad, tr)


def map_final(scorer: Scorer, smap: Any) -> dict[str, float]:
    """Final error, ATE and NEES/dof of a map."""
    from experiments.pose_graph import nees_per_dof

    p = scorer.p
    anchor = f"x{scorer.poses[0]}"
    out = {"final": scorer.map_error(smap, len(p.steps))}
    if p.bounded:
        e, nees = [], []
        for j, ref in zip(scorer.landmarks, scorer.ref_lms, strict=True):
            mean, cov = smap.marginal(anchor, f"l{j}")
            d = ref - mean[:2]
            nees.append(float(d @ np.linalg.solve(cov[:2, :2], d)) / 2.0)
            e.append(d)
        out["nees"] = float(np.mean(nees))
        return out
    means = np.zeros((len(scorer.poses), 7))
    covs = np.zeros((len(scorer.poses), 6, 6))
    means[0, 3] = 1.0
    for n, i in enumerate(scorer.poses[1:], start=1):
        means[n], covs[n] = smap.marginal(anchor, f"x{i}")
    out["ate"] = scorer.ate(means[:, :p.dim])
    if p.truth is not None:
        from mcsm_client.sampling import pose_from_planar

        truth = np.stack([p.truth[i] if p.dim == 3 else pose_from_planar(p.truth[i])
                          for i in scorer.poses])
        idx = np.arange(6) if p.dim == 3 else np.array([0, 1, 5])
        out["nees"] = float(nees_per_dof(means[1:], covs[1:], truth[1:], idx).mean())
    return out


def gtsam_nees(problem: Any, scorer: Scorer, ref: dict[str, Any]) -> float:
    """NEES/dof of the batch optimum's marginals against ground truth (poses)."""
    from mcsm_client.sampling import pose_from_planar

    from experiments import realdata_gtsam as rg
    from experiments.pose_graph import nees_per_dof

    covs, _ = rg.marginal_covariances(ref["graph"], ref["lm"], problem, scorer.poses[1:], [])
    means = np.stack([pose_from_planar(np.r_[p[:2], 0.0]) for p in scorer.ref_poses[1:]]) \
        if problem.dim == 2 else None
    if problem.dim == 2:
        th = [ref["lm"].atPose2(rg.X(i)).theta() for i in scorer.poses[1:]]
        means = np.stack([pose_from_planar([x, y, t]) for (x, y), t
                          in zip(scorer.ref_poses[1:], th, strict=True)])
        truth = np.stack([pose_from_planar(problem.truth[i]) for i in scorer.poses[1:]])
        idx = np.array([0, 1, 5])
    else:
        from experiments.baselines.gtsam_slam import row_from_pose3

        means = np.stack([row_from_pose3(ref["lm"].atPose3(rg.X(i))) for i in scorer.poses[1:]])
        truth = np.stack([problem.truth[i] for i in scorer.poses[1:]])
        idx = np.arange(6)
    return float(nees_per_dof(means, covs, truth, idx).mean())


def ekf_posegraph(problem: Any, scorer: Scorer, max_gb: float = 1.0) -> dict[str, Any]:
    """The exact-covariance EKF on a pose graph (row fields), when its dense covariance fits
    ``max_gb``."""
    from mcsm_client.sampling import pose_from_planar

    from experiments.baselines.ekf_posegraph import run_ekf_posegraph
    from experiments.posegraph_sim import PoseGraph

    p = len(problem.steps)
    gb = (6 * p) ** 2 * 8 / 1e9
    if gb > max_gb:
        return {"status": f"not run: its dense covariance is {gb:.1f} GB "
                          f"((6 x {p})^2 doubles), over {max_gb} GB here"}
    edges = problem.edges()
    if any(e.kind == "odometry" and e.j != e.i + 1 for e in edges) or \
            scorer.poses != list(range(p)):
        return {"status": "not run: needs odometry edges i -> i + 1"}
    idx = [0, 1, 5]
    meas, covs = [], []
    for e in edges:
        if problem.dim == 2:
            meas.append(pose_from_planar(e.mean))
            c = np.zeros((6, 6))
            c[np.ix_(idx, idx)] = e.cov
            covs.append(c)
        else:
            meas.append(e.mean)
            covs.append(e.cov)
    g = PoseGraph(np.zeros((p, 7)), np.array([(e.i, e.j) for e in edges]), np.array(meas),
                  np.array(covs), np.array([e.kind != "odometry" for e in edges]),
                  problem.dim == 2, {})
    t0 = time.process_time()
    run = run_ekf_posegraph(g)
    dt = time.process_time() - t0
    pos = run.means[:, :problem.dim]
    return {"final_m": scorer.rms(pos, scorer.ref_poses), "ate_m": scorer.ate(pos), "total_s": dt,
            "note": f"{1e3 * float(np.mean(run.loop_times_s)):.1f} ms per loop closure (steps "
                    "not timed one by one)"}
