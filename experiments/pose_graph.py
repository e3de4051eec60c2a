"""Full-pose loop closures: the Monte Carlo stochastic map on 3D and planar pose graphs (issue 8).

Runs the map (``mcsm.StochasticMap``) on a simulated pose graph (:mod:`experiments.posegraph_sim`)
with every pose kept, one case I update per odometry edge and one case II update (PAPER §5.2)
per loop closure, the measurements arriving in time order; then compares the final pose means
with ground truth, with dead reckoning and with GTSAM's batch optimum (Levenberg-Marquardt on the
same measurements and noise model). Printed per (scenario, method, space):

* ATE: RMS position error after a rigid (rotation + translation, no scale) alignment to ground
  truth (Umeyama), in metres;
* NEES per degree of freedom of the poses: ``e^T P^-1 e / dof`` averaged over poses, with ``P``
  the 6x6 tangent covariance of ``map.marginal("p0", pose)`` and ``e`` the tangent error of the
  ground truth around the estimated mean (``[t_true - t_mean, log(q_mean^-1 q_true)]``; planar:
  the ``x, y, yaw`` block). 1 means honest uncertainty;
* non-finite values anywhere in the final means or covariances;
* time per loop closure (mean over the run).

Besides the map, each scenario gets an exact-covariance EKF row (``--ekf exact``, the same
sequential problem with a dense covariance: it shows how far a filter that never relinearises is
from the batch optimum) and optionally ``--ekf shrink`` / ``shrink-endpoints`` (the EKF's gains
formed by the map's direct or endpoint estimator at N samples: what each estimator's shrink
costs without sampling noise).

The map runs once per ``--gains`` entry (``direct``, ``endpoints``; joint update in the tangent
space only, the other rows use ``direct``). Defaults are the configuration issue 8 is judged
on: ``gain="endpoints"``, shrink 4, a fixed inflation of 1.002 per loop closure, one update per
loop closure, seed 8.

A second part times single loop closures on maps of M = 500, 1000, 2500 poses for N = 200, 1000
(the component is built with ``import_component`` from sampled odometry chains, so only the case II
update is timed).

Acceptance (issue 8): ATE ≤ 2x GTSAM, NEES/dof ≤ 2, no non-finite values, 3D and planar, with
≥ 1000 poses, ≥ 500 loop closures, N = 200. Results go to ``experiments/results/`` as
``pose_graph_runs.csv``, ``pose_graph_timing.csv`` and ``pose_graph_<scenario>.png``.

Loop closures go through ``--loop-updates`` wrappers (experiment code, not the core):
``single`` (default: one ``update``), ``adaptive[strength]`` (the map's ``inflation`` set before
each loop closure from an average of the normalised innovation, see
:func:`adaptive_inflation_update`; the core's own ``inflation="adaptive"`` does this inside the
map) or ``mdaxK`` (K partial updates). The paper method ignores inflation, so its rows do not
depend on that choice.

Usage::

    .venv/bin/python experiments/pose_graph.py                  # everything (slow: paper method)
    .venv/bin/python experiments/pose_graph.py --methods joint --spaces tangent   # the fast part
    .venv/bin/python experiments/pose_graph.py --poses 300 --no-timing            # a short run
    .venv/bin/python experiments/pose_graph.py --scenarios --timing-methods joint  # timing only

The committed results (``experiments/results/pose_graph_summary.md``; ``--tag T`` writes
``pose_graph_runs_T.csv``)::

    .venv/bin/python experiments/pose_graph.py --spaces tangent \
        --ekf exact shrink shrink-endpoints --no-timing --tag accept_seed8
    .venv/bin/python experiments/pose_graph.py --seed S --methods joint --spaces tangent \
        --ekf --no-timing --tag accept_seedS                           # S = 9 ... 21
    .venv/bin/python experiments/pose_graph.py --seed S --methods joint --spaces tangent \
        --gains direct endpoints --inflation adaptive --ekf --no-timing \
        --tag gains_seedS                                              # S = 8 ... 14
    .venv/bin/python experiments/pose_graph.py --scenarios --timing-methods joint \
        --tag timing_gains

The N = 1000 runs (``n1000_2d_adaptive``, ``n1000_3d_adaptive``, ``sphere2500_n1000``) were made
at core b006e7c, before ``--gains`` existed; today's equivalent is ``--scenarios 3d`` (or ``2d``,
``sphere2500``) ``--methods joint --spaces tangent --n-samples 1000 --gains direct
--inflation 1.0 --loop-updates adaptive --ekf --no-timing --tag n1000_3d_adaptive``.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

if __package__ in (None, ""):  # run as a script: make `experiments` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.posegraph_sim import (  # noqa: E402
    PoseGraph,
    compose,
    dead_reckoning,
    qlog,
    qmul,
    relative,
    sample_measurement,
    simulate_2d,
    simulate_3d,
)

Array = npt.NDArray[np.float64]
RESULTS = Path(__file__).resolve().parent / "results"


def frame(k: int) -> str:
    """Frame name of pose ``k`` in the map."""
    return f"p{k}"


# ---------------------------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------------------------
def align_rigid(est: Array, ref: Array) -> Array:
    """Rigidly align ``est (P, 3)`` to ``ref (P, 3)`` (Umeyama, no scale), return it aligned."""
    mu_e, mu_r = est.mean(0), ref.mean(0)
    h = (est - mu_e).T @ (ref - mu_r)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return (est - mu_e) @ rot.T + mu_r


def ate(est_poses: Array, true_poses: Array) -> float:
    """Absolute trajectory error (m): RMS position error after rigid alignment."""
    aligned = align_rigid(est_poses[:, :3], true_poses[:, :3])
    return float(np.sqrt(np.mean(np.sum((aligned - true_poses[:, :3]) ** 2, axis=1))))


def tangent_error(mean: Array, truth: Array) -> Array:
    """Tangent error ``[t_true - t_mean, log(q_mean^-1 q_true)]`` of shape ``(..., 6)``."""
    q_inv = mean[..., 3:] * np.array([1.0, -1.0, -1.0, -1.0])
    return np.concatenate([truth[..., :3] - mean[..., :3], qlog(qmul(q_inv, truth[..., 3:]))], -1)


def nees_per_dof(
    means: Array, covs: Array, truth: Array, dof_index: npt.NDArray[np.int64]
) -> Array:
    """Per-pose NEES divided by the degrees of freedom, shape ``(P,)``.

    Parameters
    ----------
    means : (P, 7) float64
        Estimated pose means.
    covs : (P, 6, 6) float64
        Tangent covariances of the estimates, order ``[tx ty tz rx ry rz]``.
    truth : (P, 7) float64
        True poses.
    dof_index : (d,) int
        Free tangent components (all 6, or ``[0, 1, 5]`` planar).
    """
    e = tangent_error(means, truth)[:, dof_index]
    p = covs[:, dof_index][:, :, dof_index]
    sol = np.linalg.solve(p, e[..., None])[..., 0]
    return np.einsum("pi,pi->p", e, sol) / len(dof_index)


# ---------------------------------------------------------------------------------------------
# GTSAM batch optimum
# ---------------------------------------------------------------------------------------------
def gtsam_optimum(graph: PoseGraph, init: Array) -> Array | None:
    """Levenberg-Marquardt optimum of the graph with GTSAM, poses ``(P, 7)``; None without gtsam.

    Pose 0 is held at the identity by a tight prior. 3D: ``BetweenFactorPose3`` with the full
    covariance permuted to GTSAM's ``(rotation, translation)`` order; planar: ``Pose2``.
    """
    try:
        import gtsam

        from experiments.baselines.gtsam_slam import pose3_from_row, row_from_pose3
    except ImportError:
        return None
    from mcsm_client.sampling import pose_from_planar

    fg = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    if graph.planar:
        fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Isotropic.Sigma(3, 1e-8)))
        for (i, j), z, cov in zip(graph.edges, graph.measurements, graph.covariances, strict=True):
            sub = cov[np.ix_([0, 1, 5], [0, 1, 5])]
            yaw = 2.0 * np.arctan2(z[6], z[3])
            fg.add(gtsam.BetweenFactorPose2(
                int(i), int(j), gtsam.Pose2(z[0], z[1], yaw),
                gtsam.noiseModel.Gaussian.Covariance(sub)))
        for k, p in enumerate(init):
            values.insert(k, gtsam.Pose2(p[0], p[1], 2.0 * np.arctan2(p[6], p[3])))
    else:
        perm = [3, 4, 5, 0, 1, 2]
        fg.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Sigma(6, 1e-8)))
        for (i, j), z, cov in zip(graph.edges, graph.measurements, graph.covariances, strict=True):
            fg.add(gtsam.BetweenFactorPose3(
                int(i), int(j), pose3_from_row(z),
                gtsam.noiseModel.Gaussian.Covariance(cov[np.ix_(perm, perm)])))
        for k, p in enumerate(init):
            values.insert(k, pose3_from_row(p))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(200)
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-10)
    result = gtsam.LevenbergMarquardtOptimizer(fg, values, params).optimize()
    out = np.empty((graph.n_poses, 7))
    for k in range(graph.n_poses):
        if graph.planar:
            p2 = result.atPose2(k)
            out[k] = pose_from_planar([p2.x(), p2.y(), p2.theta()])
        else:
            out[k] = row_from_pose3(result.atPose3(k))
    return out


# ---------------------------------------------------------------------------------------------
# Running the map
# ---------------------------------------------------------------------------------------------
@dataclass
class MapRun:
    """Outcome of one run of the map over a graph."""

    means: Array
    covs: Array
    loop_times_s: list[float] = field(default_factory=list)
    odo_times_s: list[float] = field(default_factory=list)
    error: str = ""


UpdateFn = Callable[[object, int, int, Array, Array, np.random.Generator], None]


EXACT_MOMENTS = False  # set by --exact-moments: observation samples with exact mean/covariance
LEGACY_SAMPLER = False  # set by --legacy-sampler: the 30bbb71 random stream (6 normals/sample)


def plain_update(smap: object, i: int, j: int, z: Array, cov: Array,
                 rng: np.random.Generator) -> Any:
    """One ``update(p_i, p_j, samples)`` with samples drawn around the measurement; the core's
    ``UpdateResult`` (its verdict has the loop closure's NIS and live dof)."""
    n = smap.n_samples  # type: ignore[attr-defined]
    x = sample_measurement(z, cov, n, rng=rng, exact=EXACT_MOMENTS, legacy=LEGACY_SAMPLER)
    return smap.update(frame(i), frame(j), x)  # type: ignore[attr-defined]


def mda_update(n_steps: int) -> UpdateFn:
    """Loop closures as ``n_steps`` updates of covariance ``n_steps * cov`` each (MDA).

    For a linear-Gaussian model and a deterministic (square-root) update this gives the same
    posterior as one update; for the nonlinear pose-graph model it re-predicts the observation
    after each partial step (a relinearisation done from outside the core).
    """

    def update(smap: object, i: int, j: int, z: Array, cov: Array,
               rng: np.random.Generator) -> None:
        for _ in range(n_steps):
            plain_update(smap, i, j, z, n_steps * cov, rng)

    return update


def adaptive_inflation_update(
    dof_index: npt.NDArray[np.int64], *, rate: float = 0.05, strength: float = 0.008,
    max_inflation: float = 1.01,
) -> UpdateFn:
    """Loop closures with inflation set from the innovation statistics (experiment wrapper).

    Before each loop closure the normalised innovation ``NIS = e^T (P_h + R)^-1 e / dof`` of the
    predicted relative pose (``map.marginal(a, b)``) against the measurement is folded into an
    exponential average (``rate``); the map's ``inflation`` for this update is then
    ``clip(1 + strength (avg - 1), 1, max_inflation)``: no inflation while the ensemble's
    spread explains the innovations, more when it is overconfident. Sets the map's
    ``inflation`` attribute (the core reads it at every loop closure).
    """
    state = {"avg": 1.0}

    def update(smap: object, i: int, j: int, z: Array, cov: Array,
               rng: np.random.Generator) -> None:
        mean, p_h = smap.marginal(frame(i), frame(j))  # type: ignore[attr-defined]
        e = tangent_error(mean, z)[dof_index]
        s = (p_h + cov)[np.ix_(dof_index, dof_index)]
        nis = float(e @ np.linalg.solve(s, e)) / len(dof_index)
        state["avg"] = (1.0 - rate) * state["avg"] + rate * nis
        smap.inflation = float(np.clip(1.0 + strength * (state["avg"] - 1.0),  # type: ignore[attr-defined]
                                       1.0, max_inflation))
        plain_update(smap, i, j, z, cov, rng)

    return update


def run_map(
    graph: PoseGraph,
    smap: object,
    *,
    rng: np.random.Generator,
    loop_update: UpdateFn = plain_update,
    progress: bool = False,
) -> MapRun:
    """Feed every measurement of ``graph`` to ``smap`` in arrival order; return final marginals.

    Odometry edges are case I updates (a new pose joins the component of pose 0), loop closures
    case II. Failures (an ``McsmError`` or non-finite output) end the run; ``error`` says why.
    """
    p = graph.n_poses
    run = MapRun(np.full((p, 7), np.nan), np.full((p, 6, 6), np.nan))
    t_start = time.perf_counter()
    for k, ((i, j), z, cov, loop) in enumerate(
        zip(graph.edges, graph.measurements, graph.covariances, graph.is_loop, strict=True)
    ):
        t0 = time.perf_counter_ns()
        try:
            if loop:
                loop_update(smap, int(i), int(j), z, cov, rng)
            else:
                plain_update(smap, int(i), int(j), z, cov, rng)
        except Exception as exc:  # noqa: BLE001 - any failure ends this run, reported in the table
            run.error = f"edge {k} ({i}->{j}): {type(exc).__name__}: {exc}"
            break
        dt = (time.perf_counter_ns() - t0) * 1e-9
        (run.loop_times_s if loop else run.odo_times_s).append(dt)
        if progress and k % 500 == 0:
            print(f"    edge {k}/{len(graph.edges)}  {time.perf_counter() - t_start:.1f} s",
                  flush=True)
    run.means[0] = [0, 0, 0, 1.0, 0, 0, 0]
    run.covs[0] = np.zeros((6, 6))
    if not run.error:
        for k in range(1, p):
            mean, c = smap.marginal(frame(0), frame(k))  # type: ignore[attr-defined]
            run.means[k] = mean
            run.covs[k] = c
    return run


# ---------------------------------------------------------------------------------------------
# Experiment table
# ---------------------------------------------------------------------------------------------
@dataclass
class Row:
    """One line of ``pose_graph_runs.csv``."""

    scenario: str
    method: str
    space: str
    analysis: str
    gain: str
    loop_update: str
    shrink: float
    inflation: float
    n_samples: int
    n_poses: int
    n_loops: int
    seed: int
    ate_map_m: float
    ate_gtsam_m: float
    ate_dead_reckoning_m: float
    ate_ratio_to_gtsam: float
    nees_per_dof: float
    nees_per_dof_median: float
    nees_t_per_dof: float
    nees_r_per_dof: float
    nonfinite: int
    ms_per_loop: float
    run_s: float
    accepted: bool
    error: str


def read_toro3d(path: Path, truth_path: Path | None = None) -> PoseGraph:
    """Read a TORO 3D file (``EDGE3 i j x y z roll pitch yaw`` + 21 noise numbers).

    The rotation is ``Rz(yaw) Ry(pitch) Rx(roll)`` (GTSAM's ``Rot3.Ypr``). The 21 numbers of
    GTSAM's ``sphere2500.txt`` (``10 ... 100 100 25`` on the diagonal) are **square-root**
    information: the residuals of the file against ``sphere2500_groundtruth.txt`` have standard
    deviations 0.10 m and (0.010, 0.010, 0.040) rad, i.e. ``1 / diag``, not ``1 / sqrt(diag)``
    (0.32 m, 0.1 rad, 0.2 rad). We use ``cov = diag(1 / diag**2)``, the noise the data has.
    Ground truth: the odometry chain of the noise-free file ``truth_path``. Edges are put in
    arrival order (by their later pose, odometry first).
    """
    def parse(p: Path) -> tuple[npt.NDArray[np.int64], Array, Array]:
        ij, zs, covs = [], [], []
        for line in p.read_text().splitlines():
            t = line.split()
            if not t or t[0] != "EDGE3":
                continue
            v = np.array(t[3:], dtype=float)
            half = 0.5 * v[3:6]
            qx = np.array([np.cos(half[0]), np.sin(half[0]), 0.0, 0.0])
            qy = np.array([np.cos(half[1]), 0.0, np.sin(half[1]), 0.0])
            qz = np.array([np.cos(half[2]), 0.0, 0.0, np.sin(half[2])])
            ij.append((int(t[1]), int(t[2])))
            zs.append(np.concatenate([v[:3], qmul(qmul(qz, qy), qx)]))
            upper = v[6:27]
            diag = upper[[0, 6, 11, 15, 18, 20]]
            covs.append(np.diag(1.0 / diag**2))
        return np.asarray(ij, dtype=np.int64), np.asarray(zs), np.asarray(covs)

    ij, z, cov = parse(path)
    order = np.lexsort((ij[:, 1] - ij[:, 0] != 1, ij.max(axis=1)))
    ij, z, cov = ij[order], z[order], cov[order]
    is_loop = ij[:, 1] - ij[:, 0] != 1
    n = int(ij.max()) + 1
    truth = np.full((n, 7), np.nan)
    if truth_path is not None:
        ijt, zt, _ = parse(truth_path)
        truth[0] = [0, 0, 0, 1.0, 0, 0, 0]
        by_j = {int(j): zt[k] for k, (i, j) in enumerate(ijt) if j == i + 1}
        for j in range(1, n):
            truth[j] = compose(truth[j - 1], by_j[j])
    return PoseGraph(truth, ij, z, cov, is_loop, False, {"source": str(path)})


def make_graph(scenario: str, n_poses: int, seed: int) -> PoseGraph:
    """The graph of a scenario: simulated ``"3d"`` / ``"2d"``, or GTSAM's ``"sphere2500"``."""
    if scenario == "sphere2500":
        from mcsm_client.datasets import gtsam_data_dir

        data = gtsam_data_dir()
        if data is None:
            raise FileNotFoundError("sphere2500 needs the gtsam wheel's Data folder")
        return read_toro3d(data / "sphere2500.txt", data / "sphere2500_groundtruth.txt")
    rng = np.random.default_rng(seed)
    return simulate_2d(n_poses, rng=rng) if scenario == "2d" else simulate_3d(n_poses, rng=rng)


def evaluate(
    graph: PoseGraph,
    run: MapRun,
    *,
    scenario: str,
    config: dict[str, object],
    seed: int,
    ate_gtsam: float,
    ate_dr: float,
    run_s: float,
) -> Row:
    """Metrics of one run against ground truth."""
    truth = graph.poses_true
    idx = graph.dof_index
    finite = np.isfinite(run.means).all(axis=1) & np.isfinite(run.covs).all(axis=(1, 2))
    nonfinite = int((~finite).sum())
    if run.error or nonfinite:
        a = nees = nees_med = nt = nr = float("nan")
    else:
        a = ate(run.means, truth)
        per = nees_per_dof(run.means[1:], run.covs[1:], truth[1:], idx)
        nees, nees_med = float(per.mean()), float(np.median(per))
        t_idx = idx[idx < 3]
        r_idx = idx[idx >= 3]
        nt = float(nees_per_dof(run.means[1:], run.covs[1:], truth[1:], t_idx).mean())
        nr = float(nees_per_dof(run.means[1:], run.covs[1:], truth[1:], r_idx).mean())
    ratio = a / ate_gtsam if ate_gtsam > 0 else float("nan")
    ok = (not run.error) and nonfinite == 0 and bool(ratio <= 2.0) and bool(nees <= 2.0)
    return Row(
        scenario=scenario, method=str(config["method"]), space=str(config["space"]),
        analysis=str(config["analysis"]), gain=str(config.get("gain", "direct")),
        loop_update=str(config["loop_update"]),
        shrink=float("nan") if config["shrink"] is None else float(config["shrink"]),  # type: ignore[arg-type]
        inflation=(float("nan") if config["inflation"] == "adaptive"
                   else float(config["inflation"])),  # type: ignore[arg-type]
        n_samples=int(config["n_samples"]),  # type: ignore[call-overload]
        n_poses=graph.n_poses, n_loops=graph.n_loops, seed=seed,
        ate_map_m=a, ate_gtsam_m=ate_gtsam, ate_dead_reckoning_m=ate_dr,
        ate_ratio_to_gtsam=ratio, nees_per_dof=nees, nees_per_dof_median=nees_med,
        nees_t_per_dof=nt, nees_r_per_dof=nr, nonfinite=nonfinite,
        ms_per_loop=1e3 * float(np.mean(run.loop_times_s)) if run.loop_times_s else float("nan"),
        run_s=run_s, accepted=ok, error=run.error,
    )


def make_map(config: dict[str, object]) -> object:
    """A ``StochasticMap`` with the options in ``config``."""
    from mcsm import StochasticMap

    return StochasticMap(
        int(config["n_samples"]),  # type: ignore[call-overload]
        method=config["method"], space=config["space"], analysis=config["analysis"],
        shrink=config["shrink"],  # type: ignore[arg-type]
        inflation=(config["inflation"] if config["inflation"] == "adaptive"
                   else float(config["inflation"])),  # type: ignore[arg-type]
        gain=str(config.get("gain", "direct")),
        gate=config.get("gate"),  # type: ignore[arg-type]  # none: the filter alone
    )


def run_config(
    graph: PoseGraph,
    config: dict[str, object],
    *,
    scenario: str,
    seed: int,
    ate_gtsam: float,
    ate_dr: float,
    map_factory: Callable[[dict[str, object]], object] = make_map,
    progress: bool = False,
) -> tuple[Row, MapRun]:
    """Run and evaluate one configuration of the map on ``graph``."""
    name = str(config["loop_update"])
    loop_update: UpdateFn = plain_update
    if name.startswith("mdax"):
        loop_update = mda_update(int(name[4:]))
    elif name.startswith("adaptive"):
        # "adaptive" or "adaptive<strength>", e.g. adaptive0.008
        strength = float(name[8:]) if len(name) > 8 else 0.008
        loop_update = adaptive_inflation_update(graph.dof_index, strength=strength)
    smap = map_factory(config)
    t0 = time.perf_counter()
    run = run_map(graph, smap, rng=np.random.default_rng(seed + 1), loop_update=loop_update,
                  progress=progress)
    run_s = time.perf_counter() - t0
    row = evaluate(graph, run, scenario=scenario, config=config, seed=seed,
                   ate_gtsam=ate_gtsam, ate_dr=ate_dr, run_s=run_s)
    return row, run


def run_ekf_row(graph: PoseGraph, variant: str, *, n_samples: int, shrink: float | None,
                scenario: str, seed: int, ate_gtsam: float, ate_dr: float) -> tuple[Row, Array]:
    """Run the exact-covariance EKF (:mod:`experiments.baselines.ekf_posegraph`) on ``graph``.

    ``variant`` ``"exact"``: the plain EKF; ``"shrink"``: its gains multiplied by the map's
    correlation-shrink factor for an ``n_samples`` estimate (the shrink's bias alone);
    ``"shrink-endpoints"``: its gains formed by the map's ``gain="endpoints"`` estimator with
    that shrink (that estimator's bias alone).
    """
    from experiments.baselines.ekf_posegraph import run_ekf_posegraph

    c = 4.0 if shrink is None else shrink
    t0 = time.perf_counter()
    damped = variant != "exact"
    ekf = run_ekf_posegraph(graph, shrink_n=n_samples if damped else None, shrink_c=c,
                            gain="endpoints" if variant == "shrink-endpoints" else "direct")
    run = MapRun(ekf.means, ekf.covs, loop_times_s=ekf.loop_times_s)
    config: dict[str, object] = {
        "method": "ekf", "space": "-",
        "gain": "endpoints" if variant == "shrink-endpoints" else ("direct" if damped else "-"),
        "analysis": f"shrink{c:g}@N" if damped else "exact", "loop_update": "single",
        "shrink": c if damped else None, "inflation": 1.0,
        "n_samples": n_samples if damped else 0}
    row = evaluate(graph, run, scenario=scenario, config=config, seed=seed, ate_gtsam=ate_gtsam,
                   ate_dr=ate_dr, run_s=time.perf_counter() - t0)
    return row, ekf.means


# ---------------------------------------------------------------------------------------------
# Timing of single loop closures
# ---------------------------------------------------------------------------------------------
def build_chain_map(smap: object, graph: PoseGraph, n_samples: int,
                    rng: np.random.Generator) -> None:
    """Put poses 0..P-1 of ``graph`` into ``smap`` as one component from sampled odometry."""
    from mcsm.core.smap import Submap  # type: ignore[attr-defined]

    odo = ~graph.is_loop
    edges = np.empty((graph.n_poses, n_samples, 7))
    edges[0] = [0, 0, 0, 1.0, 0, 0, 0]
    for k, (z, cov) in enumerate(zip(graph.measurements[odo], graph.covariances[odo],
                                     strict=True)):
        edges[k + 1] = compose(edges[k], sample_measurement(z, cov, n_samples, rng=rng))
    frames = tuple(frame(k) for k in range(graph.n_poses))
    smap.import_component(Submap(  # type: ignore[attr-defined]
        root=frames[0], frames=frames, is_point=tuple(False for _ in frames), edges=edges))


def time_loop_closures(
    sizes: Iterable[int],
    sample_counts: Iterable[int],
    configs: list[dict[str, object]],
    *,
    repeats: int,
    seed: int,
    map_factory: Callable[[dict[str, object]], object] = make_map,
) -> list[dict[str, object]]:
    """Median time of one loop closure on a map of M poses, per (M, N, config)."""
    rows: list[dict[str, object]] = []
    for n in sample_counts:
        for m in sizes:
            graph = make_graph("3d", m, seed)
            for config in configs:
                cfg = {**config, "n_samples": n}
                rng = np.random.default_rng(seed + 2)
                smap = map_factory(cfg)
                build_chain_map(smap, graph, n, rng)
                pairs = [(int(i), int(j)) for i, j in graph.edges[graph.is_loop]]
                pairs = pairs[-(repeats + 1):]  # long loops, across the whole chain
                times = []
                for i, j in pairs:
                    z = relative(graph.poses_true[i], graph.poses_true[j])
                    cov = graph.covariances[graph.is_loop][0]
                    samples = sample_measurement(z, cov, n, rng=rng)
                    t0 = time.perf_counter_ns()
                    smap.update(frame(i), frame(j), samples)  # type: ignore[attr-defined]
                    times.append((time.perf_counter_ns() - t0) * 1e-6)
                times = times[1:]  # first call is a warm-up
                copy_ms = _stream_pass_ms(m, n)
                row = {
                    "M": m, "N": n, "method": cfg["method"], "space": cfg["space"],
                    "analysis": cfg["analysis"], "gain": cfg.get("gain", "direct"),
                    "median_ms": float(np.median(times)),
                    "min_ms": float(np.min(times)), "max_ms": float(np.max(times)),
                    "repeats": len(times), "stream_pass_ms": copy_ms,
                    "passes": float(np.median(times)) / copy_ms,
                }
                rows.append(row)
                print("  M={M:5d} N={N:5d} {method:5s} {space:10s} {gain:9s} "
                      "median {median_ms:9.2f} ms (min {min_ms:.2f}, max {max_ms:.2f}, "
                      "{repeats} runs) = {passes:.1f} streaming passes".format(**row), flush=True)
                del smap
    return rows


def _stream_pass_ms(m: int, n: int) -> float:
    a = np.ones((m, n, 7))
    b = np.empty_like(a)
    ts = []
    for _ in range(5):
        t0 = time.perf_counter_ns()
        np.copyto(b, a)
        ts.append((time.perf_counter_ns() - t0) * 1e-6)
    return float(np.median(ts))


# ---------------------------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------------------------
def write_csv(path: Path, rows: list[dict[str, object]]) -> None:
    """Write dict rows to ``path`` (header from the first row)."""
    if not rows:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def plot_scenario(path: Path, graph: PoseGraph, curves: dict[str, Array]) -> None:
    """Top view of truth, dead reckoning, GTSAM and the map runs (aligned), one PNG."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(7, 7))
    truth = graph.poses_true[:, :3]
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=2.0, label="ground truth")
    for name, poses in curves.items():
        if not np.isfinite(poses).all():
            continue
        al = align_rigid(poses[:, :3], truth)
        ax.plot(al[:, 0], al[:, 1], lw=0.8, label=name)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7)
    ax.set_title(f"{'planar' if graph.planar else '3D'}: {graph.n_poses} poses, "
                 f"{graph.n_loops} loop closures (rigidly aligned)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_timing(path: Path, rows: list[dict[str, object]]) -> None:
    """Time per loop closure vs M for each (N, method, space)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    keys = sorted({(r["N"], r["method"], r["space"], r.get("gain", "direct")) for r in rows},
                  key=str)
    for key in keys:
        sel = [r for r in rows
               if (r["N"], r["method"], r["space"], r.get("gain", "direct")) == key]
        ax.loglog([r["M"] for r in sel], [r["median_ms"] for r in sel], "o-",
                  label=f"N={key[0]} {key[1]} {key[2]} {key[3]}")
    ax.set_xlabel("poses in the component M")
    ax.set_ylabel("median time per loop closure (ms)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _fmt_row(r: Row) -> str:
    return (f"{r.scenario:3s} {r.method:5s} {r.space:10s} {r.analysis:5s} {r.gain:9s} "
            f"{r.loop_update:6s} "
            f"N={r.n_samples:<5d} ATE {r.ate_map_m:8.3f} m  GTSAM {r.ate_gtsam_m:6.3f}  "
            f"DR {r.ate_dead_reckoning_m:7.3f}  ratio {r.ate_ratio_to_gtsam:7.2f}  "
            f"NEES/dof {r.nees_per_dof:9.3g} (t {r.nees_t_per_dof:.3g}, r {r.nees_r_per_dof:.3g},"
            f" median {r.nees_per_dof_median:.3g})  nonfinite {r.nonfinite}  "
            f"{r.ms_per_loop:7.2f} ms/loop  {'PASS' if r.accepted else 'FAIL'}"
            + (f"  [{r.error}]" if r.error else ""))


def _core_commit() -> str:
    """Last git commit touching ``service/mcsm/core`` (for the record), or ``"unknown"``."""
    try:
        out = subprocess.run(
            ["git", "log", "-1", "--format=%h", "--", "service/mcsm/core"],
            cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=10,
            check=False)
        return out.stdout.strip() or "unknown"
    except OSError:
        return "unknown"


def main(args: argparse.Namespace) -> list[Row]:
    """Run the experiment described by the parsed ``args``; print and save the figures."""
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tag = f"_{args.tag}" if args.tag else ""
    print("settings:", vars(args))
    print(f"numpy {np.__version__}, python {platform.python_version()}, "
          f"cores {os.cpu_count()}, load average {os.getloadavg()[0]:.1f}, "
          f"core commit {_core_commit()}")
    global EXACT_MOMENTS, LEGACY_SAMPLER
    EXACT_MOMENTS = bool(args.exact_moments)
    LEGACY_SAMPLER = bool(args.legacy_sampler)
    shrink = args.shrink if args.shrink is not None and args.shrink >= 0 else None
    rows: list[Row] = []
    for scenario in args.scenarios:
        graph = make_graph(scenario, args.poses, args.seed)
        print(f"\n[{scenario}] poses {graph.n_poses}, loop closures {graph.n_loops}, "
              f"simulator settings {graph.settings}", flush=True)
        dr = dead_reckoning(graph)
        ate_dr = ate(dr, graph.poses_true)
        opt = None if args.no_gtsam else gtsam_optimum(graph, dr)
        ate_gt = ate(opt, graph.poses_true) if opt is not None else float("nan")
        print(f"  dead reckoning ATE {ate_dr:.3f} m; GTSAM LM optimum ATE {ate_gt:.3f} m",
              flush=True)
        curves: dict[str, Array] = {"dead reckoning": dr}
        if opt is not None:
            curves["GTSAM"] = opt
        for variant in args.ekf:
            row, means = run_ekf_row(graph, variant, n_samples=args.n_samples,
                                     shrink=shrink, scenario=scenario, seed=args.seed,
                                     ate_gtsam=ate_gt, ate_dr=ate_dr)
            rows.append(row)
            print("  " + _fmt_row(row), flush=True)
            curves[f"EKF {variant}"] = means
        for method in args.methods:
            for space in args.spaces:
                gains = args.gains if (method, space) == ("joint", "tangent") else ["direct"]
                for gain, loop_update in ((g, u) for g in gains for u in args.loop_updates):
                    config: dict[str, object] = {
                        "n_samples": args.n_samples, "method": method, "space": space,
                        "analysis": args.analysis, "shrink": shrink, "gain": gain,
                        "inflation": args.inflation, "loop_update": loop_update,
                    }
                    row, run = run_config(graph, config, scenario=scenario, seed=args.seed,
                                          ate_gtsam=ate_gt, ate_dr=ate_dr,
                                          progress=args.progress)
                    rows.append(row)
                    print("  " + _fmt_row(row), flush=True)
                    curves[f"{method}/{space}/{gain}/{loop_update}"] = run.means
        plot_scenario(out / f"pose_graph_{scenario}{tag}.png", graph, curves)
    if rows:
        write_csv(out / f"pose_graph_runs{tag}.csv", [asdict(r) for r in rows])
    if not args.no_timing:
        print("\ntime per loop closure (3D, every pose kept):", flush=True)
        configs = [{"method": m, "space": s, "analysis": args.analysis, "shrink": shrink,
                    "inflation": args.inflation, "gain": g} for m in args.timing_methods
                   for s in args.spaces[:1]
                   for g in (args.gains if (m, s) == ("joint", "tangent") else ["direct"])]
        trows = time_loop_closures(args.timing_m, args.timing_n, configs,
                                   repeats=args.timing_repeats, seed=args.seed)
        write_csv(out / f"pose_graph_timing{tag}.csv", trows)
        plot_timing(out / f"pose_graph_timing{tag}.png", trows)
    print(f"\nresults in {out}")
    return rows


def parse(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options (defaults: the issue 8 acceptance run)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=1000, help="poses in the simulated graph")
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--n-samples", type=int, default=200, help="N")
    ap.add_argument("--scenarios", nargs="*", default=["3d", "2d"],
                    choices=["3d", "2d", "sphere2500"],
                    help="scenarios to run (none: timing only)")
    ap.add_argument("--methods", nargs="+", default=["joint", "paper"])
    ap.add_argument("--spaces", nargs="+", default=["tangent", "quaternion"])
    ap.add_argument("--analysis", default="ensrf", choices=["ensrf", "denkf", "enkf"])
    ap.add_argument("--gains", nargs="+", default=["endpoints", "direct"],
                    choices=["direct", "endpoints"],
                    help="cross-covariance estimators of the joint update (joint/tangent only; "
                         "the other rows use 'direct')")
    ap.add_argument("--shrink", type=float, default=4.0,
                    help="correlation shrink c of the joint update (negative: none)")
    ap.add_argument("--inflation", type=lambda t: t if t == "adaptive" else float(t),
                    default=1.002,
                    help="core inflation per loop closure: a factor (default 1.002), or "
                         "'adaptive' (NIS-driven)")
    ap.add_argument("--loop-updates", nargs="+", default=["single"],
                    help="'single', 'mdaxK' (K partial updates per loop closure) or "
                         "'adaptive[strength]' (inflation from the innovation statistics)")
    ap.add_argument("--exact-moments", action="store_true",
                    help="draw each measurement's N samples with exact mean and covariance")
    ap.add_argument("--legacy-sampler", action="store_true",
                    help="measurement samples from the first simulator's random stream (6 normals "
                         "per sample even when planar): reproduces rows run before commit 952504d")
    ap.add_argument("--ekf", nargs="*", default=["exact"],
                    choices=["exact", "shrink", "shrink-endpoints"],
                    help="exact-covariance EKF rows (experiments/baselines/ekf_posegraph.py): "
                         "'exact'; 'shrink' = its gains damped by the map's shrink factor for N "
                         "samples, 'shrink-endpoints' = formed by the endpoint estimator with "
                         "that shrink (each estimator's bias alone); none: --ekf with no value")
    ap.add_argument("--no-gtsam", action="store_true")
    ap.add_argument("--no-timing", action="store_true")
    ap.add_argument("--timing-m", type=int, nargs="+", default=[500, 1000, 2500])
    ap.add_argument("--timing-n", type=int, nargs="+", default=[200, 1000])
    ap.add_argument("--timing-methods", nargs="+", default=["joint", "paper"])
    ap.add_argument("--timing-repeats", type=int, default=5)
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--out-dir", default=str(RESULTS))
    ap.add_argument("--tag", default="", help="suffix of the output file names")
    return ap.parse_args(argv)


if __name__ == "__main__":
    main(parse())
