"""How many true loop closures the gate refuses on clean pose graphs, and why.

Feeds clean 600-pose graphs (planar and 3-D, seeds 16-19, N = 200, the benchmark's options) to
a map gated at 0.99 and prints, over all closures: the share above the 0.99 quantile (refused),
the share above it once scaled by the finite-N bias of a sample covariance's inverse
``(N-1)/(N-p-2)``, the share above the 0.995 quantile, and the mean NIS per dof.

Usage: ``.venv/bin/python -m experiments.gate_clean_loss [--seeds 16 17 18 19]``.
"""

from __future__ import annotations

import argparse

import numpy as np
from mcsm import StochasticMap
from mcsm.core.gate import chi2_quantile

from experiments.posegraph_sim import sample_measurement, simulate_2d, simulate_3d

N = 200


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", nargs="*", type=int, default=[16, 17, 18, 19])
    ap.add_argument("--poses", type=int, default=600)
    args = ap.parse_args(argv)
    print("| graph | closures | refused at 0.99 | with (N-1)/(N-p-2) | above 0.995 | NIS/dof |")
    print("|---|---|---|---|---|---|")
    for planar in (True, False):
        nis: list[float] = []
        dof = 3 if planar else 6
        for seed in args.seeds:
            graph = (simulate_2d if planar else simulate_3d)(
                args.poses, rng=np.random.default_rng(seed))
            m = StochasticMap(N, gain="endpoints", inflation=1.002, gate=0.99)
            draw = np.random.default_rng(seed + 1)
            for (i, j), z, cov, loop in zip(graph.edges, graph.measurements, graph.covariances,
                                            graph.is_loop, strict=True):
                r = m.update(f"p{i}", f"p{j}", sample_measurement(z, cov, N, rng=draw))
                if loop:
                    assert r.verdict.nis is not None
                    nis.append(r.verdict.nis)
        x = np.array(nis)
        q = chi2_quantile(0.99, dof)
        corr = (N - 1) / (N - dof - 2)
        print(f"| {'planar' if planar else '3-D'} | {len(x)} | {100 * np.mean(x > q):.2f} % "
              f"| {100 * np.mean(x > q * corr):.2f} % "
              f"| {100 * np.mean(x > chi2_quantile(0.995, dof)):.2f} % "
              f"| {x.mean() / dof:.3f} |")


if __name__ == "__main__":
    main()
