"""Autocorrelated odometry: consecutive readings whose errors are correlated, sample by sample.

PAPER §3 (the paper's §5.2 remark): a sensor whose errors persist from one reading to the next
(wheel slip, a miscalibrated wheel radius) must produce sample sets whose sample i continues the
error of sample i of the previous reading; the map's revised merge (PAPER §2) then accounts for
the correlation. :func:`mcsm_client.sampling.correlated_with` does it with an AR(1) model of
correlation ``rho`` in whitened coordinates. This example drives a straight line with such
odometry and prints the correlation between consecutive readings' samples and the spread of
the final pose (a positive ``rho`` makes errors add up coherently: a wider spread than ``rho=0``).

    python clients/examples/autocorrelated_odometry.py --in-process 1000 --rho 0.8
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.serve.connect import add_connection_args, client_kwargs
from mcsm_client.client import MapClient
from mcsm_client.players import MapTarget
from mcsm_client.sampling import correlated_with, sample_planar


@dataclass(frozen=True)
class Config:
    """Steps, the reading's noise and its step-to-step correlation."""

    n_steps: int = 10
    rho: float = 0.8
    sigma: tuple[float, float, float] = (0.05, 0.01, 0.005)
    seed: int = 3


def main(config: Config, target: Any) -> dict[str, Any]:
    """Drive ``n_steps`` 1 m steps; return the measured correlation and final spread."""
    m = MapTarget(target)
    n = m.n_samples
    rng = np.random.default_rng(config.seed)
    cov = np.diag(np.square(config.sigma))
    step = [1.0, 0.0, 0.0]
    prev = sample_planar(step, cov, n_samples=n, rng=rng)
    m.update("x0", "x1", prev)
    corr = []
    for k in range(1, config.n_steps):
        nxt = correlated_with(prev, step, cov, rho=config.rho, rng=rng, planar=True)
        corr.append(float(np.corrcoef(prev[:, 0], nxt[:, 0])[0, 1]))
        m.update(f"x{k}", f"x{k + 1}", nxt)
        prev = nxt
    mean, cov_end = m.marginal("x0", f"x{config.n_steps}")
    return {"mean_corr_dx": float(np.mean(corr)), "final_x": float(mean[0]),
            "final_sigma_x": float(np.sqrt(cov_end[0, 0]))}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_connection_args(p)
    p.add_argument("--in-process", type=int, default=None, metavar="N")
    p.add_argument("--rho", type=float, default=Config.rho)
    p.add_argument("--steps", type=int, default=Config.n_steps)
    args = p.parse_args()
    cfg = Config(rho=args.rho, n_steps=args.steps)
    if args.in_process:
        print(main(cfg, StochasticMap(args.in_process)))
    else:
        with MapClient(**client_kwargs(args)) as client:
            print(main(cfg, client))
