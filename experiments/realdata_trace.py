"""Trace a map's error along a real-data stream (issue 22): where the error of a configuration
comes from between relinearisations.

Streams a prefix of one data set of :mod:`experiments.realdata_data` into
``StochasticMap(N, **options)`` (the benchmark's own stream, :func:`realdata_run.run_map`) and
prints its error against the batch optimum of the prefix every ``--every`` steps, the error
right after each automatic relinearisation past ``--from``, and at the end the error before and
after a rigid alignment beside GTSAM batch LM and iSAM2 fed the same sample means (the floor of
these inputs). docs/relinearisation.md ("Re-centring") quotes it on w10000.

Usage::

    .venv/bin/python -m experiments.realdata_trace w10000 --steps 1000 --every 100
    .venv/bin/python -m experiments.realdata_trace w10000 --steps 300 \\
        --options '{"relinearize": {"nis": 0.95, "regate": 1, "gap": 25, "spread": 1.3,
                                    "recentre": true}}'
"""

from __future__ import annotations

import argparse
import json
import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    from mcsm.core.smap import StochasticMap

    from experiments import realdata_data as rd
    from experiments import realdata_gtsam as rg
    from experiments import realdata_run as rr
    from experiments.pose_graph import ate
    from experiments.realdata_score import Scorer

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", choices=["city10000", "w10000", "sphere2500"])
    ap.add_argument("--steps", type=int, default=1000, help="prefix length (default 1000)")
    ap.add_argument("--n-samples", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--every", type=int, default=50, help="checkpoint interval in steps")
    ap.add_argument("--from", dest="start", type=int, default=None,
                    help="print every automatic relinearisation from this step on")
    ap.add_argument("--options", default="{}", help="StochasticMap keyword options (JSON)")
    a = ap.parse_args(argv)
    opts = json.loads(a.options)
    p = rd.load(a.dataset)
    p.steps = p.steps[: a.steps]
    graph, _ = rg.whole_graph(p)
    lm, _ = rg.batch_lm(graph, rg.run_isam2(p, query=False).estimate)
    sc = Scorer(p, lm)

    class Trace(rr.Hook):
        def __init__(self) -> None:
            self.k, self.count = 0, 0

        def after(self, smap: object, e: object, x: object, r: object) -> tuple[object, object]:
            rel = getattr(r, "relin", None)
            if rel is not None:
                self.count += 1
                if a.start is not None and self.k >= a.start:
                    c = rel.components[0]
                    print(f"  step {self.k}: {rel.trigger}, {c.iterations} iterations, cost "
                          f"{c.cost_before:.0f} -> {c.cost_after:.0f}, error "
                          f"{sc.map_error(smap, self.k + 1):.3f} m", flush=True)
            return smap, r

        def end_step(self, smap: object, k: int, pose: int, res: object) -> object:
            self.k = k + 1
            return smap

    trace = Trace()
    res, smap = rr.run_map(p, lambda: StochasticMap(a.n_samples, threads=1, **opts),
                           n_samples=a.n_samples, seed=a.seed, hooks=[trace],
                           checkpoint_every=a.every, error_fn=sc.map_error)
    print(f"{a.dataset}, {a.steps} steps, N = {a.n_samples}, seed {a.seed}, options {opts}: "
          f"{res.total_s:.1f} s CPU, rejected {res.rejected}/{res.tested}, errors {res.errors}, "
          f"{trace.count} automatic relinearisations")
    print("error every", a.every, "steps (m):",
          " ".join(f"{k}:{e:.2f}" for k, e in res.checkpoints.items()))
    poses = [q for q, _ in p.steps]
    ref = np.zeros((len(poses), 3))
    ref[:, : p.dim] = sc.ref_poses

    def row(name: str, est: np.ndarray) -> None:
        pad = np.zeros((len(poses), 7))
        pad[:, : p.dim] = est[:, : p.dim]
        print(f"{name}: {sc.rms(est[:, : p.dim], sc.ref_poses):.3f} m from the optimum, "
              f"{ate(pad, np.pad(ref, ((0, 0), (0, 4)))):.3f} m after a rigid alignment")

    row("map", rr.positions(smap, f"x{poses[0]}", [f"x{q}" for q in poses]))
    g2, _ = rg.whole_graph(p, res.sample_means)
    row("batch LM fed the same sample means", rg.estimates(rg.batch_lm(g2, lm)[0], p)[0])
    isam = rg.run_isam2(p, means=res.sample_means, query=False)
    row("iSAM2 fed the same sample means", rg.estimates(isam.estimate, p)[0])


if __name__ == "__main__":
    main()
