"""ATE and NEES over time on one pose graph, against GTSAM on the same prefix (issue 8 diagnosis).

Runs the map (shipped configuration by default: joint, ensrf, shrink 4, inflation "adaptive")
over a simulated graph of ``experiments/pose_graph.py`` and, every ``--every`` poses, prints for
the poses seen so far: the map's ATE (rigid alignment), GTSAM's batch optimum ATE on the same
prefix of measurements, their ratio, NEES/dof of the poses (all, translation, rotation), the
number of dof the core's adaptive inflation counted in the last loop closure, its running NIS
average, and (planar) the largest |z|, |qx|, |qy| over every sample of every edge (the dead
dimensions must stay exactly zero).

``--map-seed`` changes only the random stream of the measurement samples (default: the CLI's
``seed + 1``), so the spread of the map over draws of its samples on one fixed graph can be
measured.

Usage::

    .venv/bin/python experiments/pose_graph_curves.py --scenario 2d --seed 8
    .venv/bin/python experiments/pose_graph_curves.py --scenario 2d --seed 8 --map-seeds 100 101
    .venv/bin/python experiments/pose_graph_curves.py --scenario 3d --gain endpoints \
        --inflation 1.002
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

if __package__ in (None, ""):  # run as a script: make `experiments` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from experiments.pose_graph import (  # noqa: E402
    ate,
    dead_reckoning,
    frame,
    gtsam_optimum,
    make_graph,
    nees_per_dof,
    plain_update,
)
from experiments.posegraph_sim import PoseGraph  # noqa: E402


def prefix(graph: PoseGraph, k: int) -> PoseGraph:
    """The graph of poses ``0..k-1`` and the measurements between them."""
    sel = graph.edges.max(axis=1) < k
    return PoseGraph(graph.poses_true[:k], graph.edges[sel], graph.measurements[sel],
                     graph.covariances[sel], graph.is_loop[sel], graph.planar, graph.settings)


def run(scenario: str, seed: int, map_seed: int, every: int, space: str, inflation: str,
        poses: int, n_samples: int, gain: str = "direct") -> list[dict[str, float]]:
    """Run one map and return one dict of figures per checkpoint."""
    from mcsm import StochasticMap

    graph = make_graph(scenario, poses, seed)
    infl: float | str = inflation if inflation == "adaptive" else float(inflation)
    smap = StochasticMap(n_samples, method="joint", space=space, analysis="ensrf", shrink=4.0,
                         inflation=infl, gain=gain, gate=None)
    rng = np.random.default_rng(map_seed)
    rows = []
    later = graph.edges.max(axis=1)
    checkpoints = list(range(every, graph.n_poses + 1, every))
    e = 0
    dofs: list[int] = []
    for k in checkpoints:
        while e < len(graph.edges) and later[e] < k:
            i, j = graph.edges[e]
            r = plain_update(smap, int(i), int(j), graph.measurements[e], graph.covariances[e],
                             rng)
            if graph.is_loop[e]:
                dofs.append(int(r.verdict.dof))  # the live dof the core's NIS counted
            e += 1
        sub = prefix(graph, k)
        means = np.empty((k, 7))
        covs = np.empty((k, 6, 6))
        means[0] = [0, 0, 0, 1.0, 0, 0, 0]
        covs[0] = 0.0
        for p in range(1, k):
            means[p], covs[p] = smap.marginal(frame(0), frame(p))
        idx = graph.dof_index
        per = nees_per_dof(means[1:], covs[1:], sub.poses_true[1:], idx)
        nt = nees_per_dof(means[1:], covs[1:], sub.poses_true[1:], idx[idx < 3]).mean()
        nr = nees_per_dof(means[1:], covs[1:], sub.poses_true[1:], idx[idx >= 3]).mean()
        opt = gtsam_optimum(sub, dead_reckoning(sub))
        a_map = ate(means, sub.poses_true)
        a_gt = ate(opt, sub.poses_true) if opt is not None else float("nan")
        edges = smap.edges(frame(0))
        dead = float(np.abs(edges[..., [2, 4, 5]]).max()) if graph.planar else float("nan")
        rows.append({"poses": k, "loops": int(sub.is_loop.sum()), "ate_map": a_map,
                     "ate_gtsam": a_gt, "ratio": a_map / a_gt, "nees": float(per.mean()),
                     "nees_t": float(nt), "nees_r": float(nr),
                     "dof_min": min(dofs, default=-1), "dof_max": max(dofs, default=-1),
                     "nis_avg": smap.nis_avg, "dead_max": dead})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenario", default="2d", choices=["2d", "3d"])
    ap.add_argument("--seed", type=int, default=8)
    ap.add_argument("--map-seeds", type=int, nargs="*", default=None,
                    help="random streams of the measurement samples (default: seed + 1)")
    ap.add_argument("--space", default="tangent", choices=["tangent", "quaternion"])
    ap.add_argument("--inflation", default="adaptive",
                    help="a factor per loop closure or 'adaptive' (default)")
    ap.add_argument("--gain", default="direct", choices=["direct", "endpoints"])
    ap.add_argument("--poses", type=int, default=1000)
    ap.add_argument("--n-samples", type=int, default=200)
    ap.add_argument("--every", type=int, default=100)
    ap.add_argument("--final-only", action="store_true", help="one checkpoint, at the end")
    args = ap.parse_args()
    every = args.poses if args.final_only else args.every
    for ms in args.map_seeds or [args.seed + 1]:
        print(f"[{args.scenario}] seed {args.seed} map seed {ms} space {args.space} "
              f"inflation {args.inflation} gain {args.gain} N={args.n_samples}", flush=True)
        print("  poses loops  ATE map  ATE GTSAM  ratio  NEES/dof (t, r)        "
              "dof counted  NIS avg  max|dead|")
        for r in run(args.scenario, args.seed, ms, every, args.space, args.inflation,
                     args.poses, args.n_samples, args.gain):
            print(f"  {r['poses']:5d} {r['loops']:5d}  {r['ate_map']:7.3f}  {r['ate_gtsam']:9.3f}"
                  f"  {r['ratio']:5.2f}  {r['nees']:6.2f} ({r['nees_t']:5.2f}, {r['nees_r']:5.2f})"
                  f"   {r['dof_min']}-{r['dof_max']}         {r['nis_avg']:6.3f}  "
                  f"{r['dead_max']:.3g}", flush=True)


if __name__ == "__main__":
    main()
