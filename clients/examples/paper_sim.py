"""The paper's §6 experiment, short: a robot on a 50 m circle mapping 200 point features.

PAPER §4: odometry and a 180°/30 m laser with the paper's noise; every ``score_every``
iterations the landmark RMS error and NEES per dof against ground truth are printed (and, with
``--csv PATH``, written to a CSV). 340 iterations is one revolution (the large loop closes);
the default here is shorter. ``mcsm-client sim`` is the full-featured command (PNG plot, σ_θ, ...).

    python clients/examples/paper_sim.py --in-process 300 --iterations 100
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.serve.connect import add_connection_args, client_kwargs
from mcsm_client.client import MapClient
from mcsm_client.sim import SimConfig, run_sim


@dataclass(frozen=True)
class Config:
    """Run length, scoring interval, output CSV and seed."""

    n_iterations: int = 100
    score_every: int = 25
    csv: Path | None = None
    seed: int = 6


def main(config: Config, target: Any) -> dict[str, Any]:
    """Run the simulation; return the final scores."""
    res = run_sim(SimConfig(n_iterations=config.n_iterations, score_every=config.score_every),
                  target, rng=np.random.default_rng(config.seed),
                  progress=lambda r: print(f"iteration {r.iteration}: RMS {r.rms_m:.3f} m, "
                                           f"NEES/dof {r.nees_per_dof:.2f}"))
    if config.csv is not None:
        res.write_csv(config.csv)
    return {"rms_m": res.final.rms_m, "nees_per_dof": res.final.nees_per_dof,
            "landmarks": res.final.n_landmarks}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_connection_args(p)
    p.add_argument("--in-process", type=int, default=None, metavar="N")
    p.add_argument("--iterations", type=int, default=Config.n_iterations)
    p.add_argument("--csv", type=Path, default=None, help="also write the scores here")
    args = p.parse_args()
    cfg = Config(n_iterations=args.iterations, csv=args.csv)
    if args.in_process:
        print(main(cfg, StochasticMap(args.in_process)))
    else:
        with MapClient(**client_kwargs(args)) as client:
            print(main(cfg, client))
