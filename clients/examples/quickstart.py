"""Quickstart: a robot drives two steps, sees a landmark twice, and asks the map where it is.

PAPER §3: the first odometry reading creates a component (world ``w`` → pose ``p1``), the next
adds a frame, the first landmark sighting adds a point frame, and the second sighting of the
same landmark closes a loop (case II), which sharpens every estimate in the component. Samples
come from :mod:`mcsm_client.sampling` (an explicit seed makes the run reproducible).

Run against a server (``mcsm serve`` in another shell) or without one::

    python clients/examples/quickstart.py                 # tcp/127.0.0.1:7457, map "default"
    python clients/examples/quickstart.py --in-process 500
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
from mcsm_client.sampling import sample_planar, sample_point


@dataclass(frozen=True)
class Config:
    """Noise of the two sensors (standard deviations) and the seed."""

    sigma_odometry: tuple[float, float, float] = (0.05, 0.05, 0.01)  # m, m, rad
    sigma_landmark_m: float = 0.2
    seed: int = 1


def main(config: Config, target: Any) -> dict[str, Any]:
    """Send the four observations and return what the map says about pose p2 and landmark L."""
    m = MapTarget(target)
    n = m.n_samples
    rng = np.random.default_rng(config.seed)
    odo_cov = np.diag(np.square(config.sigma_odometry))
    lm_cov = np.eye(2) * config.sigma_landmark_m**2
    kinds = [
        m.update("w", "p1", sample_planar([1.0, 0.0, 0.1], odo_cov, n_samples=n, rng=rng)),
        m.update("p1", "L", sample_point([3.0, 1.0], lm_cov, n_samples=n, rng=rng)),
        m.update("p1", "p2", sample_planar([1.0, 0.0, 0.1], odo_cov, n_samples=n, rng=rng)),
        m.update("p2", "L", sample_point([2.1, 0.8], lm_cov, n_samples=n, rng=rng)),
    ]
    mean_p2, cov_p2 = m.marginal("w", "p2")
    mean_l, cov_l = m.marginal("w", "L")
    return {"kinds": kinds, "p2_xy": mean_p2[:2], "p2_sigma_xy": np.sqrt(np.diag(cov_p2)[:2]),
            "L_xy": mean_l[:2], "L_sigma_xy": np.sqrt(np.diag(cov_l)[:2])}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_connection_args(p)
    p.add_argument("--in-process", type=int, default=None, metavar="N",
                   help="no server: an in-process map with N samples")
    p.add_argument("--seed", type=int, default=Config.seed)
    args = p.parse_args()
    cfg = Config(seed=args.seed)
    if args.in_process:
        out = main(cfg, StochasticMap(args.in_process))
    else:
        with MapClient(**client_kwargs(args)) as client:
            out = main(cfg, client)
    with np.printoptions(precision=3, suppress=True):
        for k, v in out.items():
            print(f"{k}: {v}")
