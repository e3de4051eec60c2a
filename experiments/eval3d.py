"""3D evaluation (issue 7): a 6-DoF pose graph through both update methods and both merge spaces.

The scenario is the pose-graph engineer's simulator (:func:`experiments.posegraph_sim.simulate_3d`:
an up-and-down helix with roll/pitch wobble, odometry plus loop closures, body-frame rotation
noise, ground truth). Every pose is kept in the map (PAPER §3: one case I update per odometry
edge, one case II update per loop closure). The map is run with the driver of
``experiments/pose_graph.py`` for each (method, space), and compared with

* ground truth: absolute trajectory error (ATE, RMS position error after a rigid alignment) and
  pose NEES per degree of freedom (tangent covariance of ``marginal("p0", pose)``);
* GTSAM's batch optimum (Levenberg-Marquardt, same measurements and noise model): its ATE, and
  the RMS position difference between our means and the optimum (no alignment: both are pinned
  at pose 0);
* GTSAM iSAM2 fed edge by edge: its final ATE and its CPU time per update, next to our CPU time
  per loop closure (``time.process_time``: the machine is shared).

Outputs under ``--results`` (default ``experiments/results``): ``eval3d.csv`` (one row per
estimator) and ``eval3d.png`` (top view of the trajectories and ATE/time bars).

Usage::

    .venv/bin/python experiments/eval3d.py --quick     # 200 poses, N = 100 (make bench)
    .venv/bin/python experiments/eval3d.py             # 500 poses: the committed results
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from experiments.pose_graph import (  # noqa: E402
    ate,
    gtsam_optimum,
    make_map,
    nees_per_dof,
    run_config,
)
from experiments.posegraph_sim import PoseGraph, dead_reckoning, simulate_3d  # noqa: E402
from experiments.realdata import TimedMap  # noqa: E402

Array = npt.NDArray[np.float64]
SEED = 71


def _timed_factory(holder: list[TimedMap]) -> Callable[[dict[str, object]], object]:
    """A ``map_factory`` for ``run_config`` that wraps the map in a CPU timer kept in ``holder``."""

    def factory(cfg: dict[str, object]) -> object:
        holder.append(TimedMap(make_map(cfg)))  # type: ignore[arg-type]
        return holder[-1]

    return factory


def isam2_run(graph: PoseGraph) -> tuple[Array, Array]:
    """iSAM2 over the graph's edges in arrival order: final poses ``(P, 7)``, time per edge (s)."""
    from experiments.baselines import gtsam_slam as gs

    perm = [3, 4, 5, 0, 1, 2]  # map tangent [t, r] -> GTSAM Pose3 tangent [r, t]
    edges = [
        gs.PoseEdge3D(int(i), int(j), z, cov[np.ix_(perm, perm)])
        for (i, j), z, cov in zip(graph.edges, graph.measurements, graph.covariances, strict=True)
    ]
    estimate, times = gs.isam2_pose_graph_3d(edges, np.array([0, 0, 0, 1.0, 0, 0, 0]))
    return gs.pose3_rows(estimate, range(graph.n_poses)), times


def main(
    results: Path, *, n_poses: int, n_samples: int, configs: list[tuple[str, str]], seed: int
) -> list[dict[str, Any]]:
    """Run the comparison, write ``eval3d.csv`` and ``eval3d.png``, return the rows."""
    results.mkdir(parents=True, exist_ok=True)
    graph = simulate_3d(n_poses, rng=np.random.default_rng(seed))
    truth = graph.poses_true
    print(
        f"3D helix: {graph.n_poses} poses, {graph.n_loops} loop closures, N = {n_samples}, "
        f"seed {seed}",
        flush=True,
    )
    dr = dead_reckoning(graph)
    t0 = time.process_time()
    opt = gtsam_optimum(graph, dr)
    lm_s = time.process_time() - t0
    rows: list[dict[str, Any]] = []
    curves: dict[str, Array] = {"ground truth": truth, "dead reckoning": dr}

    def diff_to(est: Array, ref: Array | None) -> float:
        if ref is None:
            return float("nan")
        return float(np.sqrt(np.mean(np.sum((est[:, :3] - ref[:, :3]) ** 2, axis=1))))

    base = {"n_poses": graph.n_poses, "n_loops": graph.n_loops, "n_samples": 0}
    rows.append(
        {
            **base,
            "estimator": "dead reckoning",
            "ate_m": ate(dr, truth),
            "rms_vs_gtsam_m": diff_to(dr, opt),
            "nees_per_dof": float("nan"),
            "ms_per_loop": float("nan"),
            "ms_per_update": float("nan"),
            "error": "",
        }
    )
    if opt is not None:
        curves["GTSAM LM"] = opt
        rows.append(
            {
                **base,
                "estimator": "gtsam-lm",
                "ate_m": ate(opt, truth),
                "rms_vs_gtsam_m": 0.0,
                "nees_per_dof": float("nan"),
                "ms_per_loop": float("nan"),
                "ms_per_update": 1e3 * lm_s,
                "error": "time = whole batch solve",
            }
        )
        est, times = isam2_run(graph)
        loops = graph.is_loop
        rows.append(
            {
                **base,
                "estimator": "gtsam-isam2",
                "ate_m": ate(est, truth),
                "rms_vs_gtsam_m": diff_to(est, opt),
                "nees_per_dof": float("nan"),
                "ms_per_loop": 1e3 * float(np.mean(times[loops])),
                "ms_per_update": 1e3 * float(np.mean(times)),
                "error": "",
            }
        )
    ate_gt = rows[1]["ate_m"] if opt is not None else float("nan")
    for method, space in configs:
        config: dict[str, object] = {
            "n_samples": n_samples,
            "method": method,
            "space": space,
            "analysis": "ensrf",
            "shrink": None,
            "inflation": 1.0,
            "loop_update": "single",
        }
        t0 = time.perf_counter()
        holder: list[TimedMap] = []
        row, run = run_config(
            graph,
            config,
            scenario="3d",
            seed=seed,
            ate_gtsam=ate_gt,
            ate_dr=rows[0]["ate_m"],
            map_factory=_timed_factory(holder),
        )
        timed = holder[-1]
        ok = not run.error and np.isfinite(run.means).all()
        nees = (
            float(np.mean(nees_per_dof(run.means[1:], run.covs[1:], truth[1:], graph.dof_index)))
            if ok
            else float("nan")
        )
        rows.append(
            {
                **base,
                "n_samples": n_samples,
                "estimator": f"mcsm {method}/{space}",
                "ate_m": row.ate_map_m,
                "rms_vs_gtsam_m": diff_to(run.means, opt) if ok else np.nan,
                "nees_per_dof": nees,
                "ms_per_loop": timed.mean_ms(kind="loop_closure"),
                "ms_per_update": timed.mean_ms(),
                "error": run.error,
            }
        )
        if ok:
            curves[f"mcsm {method}/{space}"] = run.means
        print(
            f"  {method}/{space}: ATE {row.ate_map_m:.3f} m (GTSAM {ate_gt:.3f} m), NEES/dof "
            f"{nees:.2f}, {timed.mean_ms(kind='loop_closure'):.1f} ms CPU per loop closure "
            f"({time.perf_counter() - t0:.0f} s) {run.error}",
            flush=True,
        )
    with open(results / "eval3d.csv", "w", newline="") as f:
        f.write(f"# simulate_3d(n_poses={n_poses}, seed={seed}), N={n_samples}\n")
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    plot(results / "eval3d.png", rows, curves, n_samples)
    return rows


def plot(path: Path, rows: list[dict[str, Any]], curves: dict[str, Array], n_samples: int) -> None:
    """Top view of the trajectories, and ATE / time-per-update bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax0, ax1, ax2) = plt.subplots(1, 3, figsize=(14, 4.5))
    fixed = {"ground truth": ("k", 2.0), "dead reckoning": ("0.6", 1.0), "GTSAM LM": ("r", 1.2)}
    palette = iter(["tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown"])
    for name, poses in curves.items():
        color, lw = fixed[name] if name in fixed else (next(palette, "tab:cyan"), 0.8)
        ax0.plot(poses[:, 0], poses[:, 1], color=color, lw=lw, label=name)
    ax0.set_aspect("equal")
    ax0.set_title("top view (x, y), pinned at pose 0")
    ax0.legend(fontsize=7)
    names = [r["estimator"] for r in rows]
    ax1.barh(names, [r["ate_m"] for r in rows], color="tab:blue")
    ax1.set_xlabel("ATE after rigid alignment (m)")
    ax1.set_title(f"accuracy (N = {n_samples})")
    timed = [r for r in rows if np.isfinite(r["ms_per_loop"])]
    ax2.barh([r["estimator"] for r in timed], [r["ms_per_loop"] for r in timed], color="tab:orange")
    ax2.set_xscale("log")
    ax2.set_xlabel("time per loop-closure update (ms)")
    ax2.set_title("cost")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="200 poses, N = 100 (make bench)")
    parser.add_argument("--poses", type=int, default=None)
    parser.add_argument("--n-samples", type=int, default=None, help="default 200 (quick: 100)")
    parser.add_argument("--seed", type=int, default=SEED)
    parser.add_argument("--results", type=Path, default=ROOT / "experiments" / "results")
    args = parser.parse_args()
    n_poses = args.poses or (200 if args.quick else 500)
    n_samples = args.n_samples or (100 if args.quick else 200)
    all_configs = [
        ("joint", "tangent"),
        ("joint", "quaternion"),
        ("paper", "tangent"),
        ("paper", "quaternion"),
    ]
    out_rows = main(
        args.results,
        n_poses=n_poses,
        n_samples=n_samples,
        configs=all_configs,
        seed=args.seed,
    )
    print("| estimator | ATE (m) | RMS vs GTSAM (m) | NEES/dof | ms/loop closure | ms/update |")
    print("|---|---|---|---|---|---|")
    for r in out_rows:
        print(
            f"| {r['estimator']} | {r['ate_m']:.3f} | {r['rms_vs_gtsam_m']:.3f} | "
            f"{r['nees_per_dof']:.2f} | {r['ms_per_loop']:.2f} | {r['ms_per_update']:.2f} |"
        )
