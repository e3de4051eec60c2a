"""Stream real data into the map: the Victoria Park ODOMETRY/LANDMARK file shipped with gtsam.

PAPER §3 on real data: odometry readings become pose-to-pose ATs, Cartesian landmark sightings
become point updates, re-sightings close loops (case II); ``bounded`` removes each superseded
pose so the map holds the first pose, the current pose and the landmarks. The file's noise is
covariance (:mod:`mcsm_client.datasets` documents each format's convention); needs the optional
``gtsam`` extra for the file (``pip install 'mcsm[eval]'``), or pass any dataset path with
``--file``.

    python clients/examples/play_victoria_park.py --in-process 300 --max-constraints 500
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.serve.connect import add_connection_args, client_kwargs
from mcsm_client.client import MapClient
from mcsm_client.datasets import read_dataset
from mcsm_client.players import MapTarget, play


@dataclass(frozen=True)
class Config:
    """Which file, how much of it, and the seed of the sample draws."""

    file: str = "gtsam:victoria_park.txt"
    max_constraints: int = 500
    bounded: bool = True
    seed: int = 5


def main(config: Config, target: Any) -> dict[str, Any]:
    """Play the file's first constraints; return the player's summary and the map size."""
    ds = read_dataset(config.file)
    stats = play(ds, target, rng=np.random.default_rng(config.seed), bounded=config.bounded,
                 max_constraints=config.max_constraints)
    return {"summary": stats.summary(), "frames": len(MapTarget(target).frames())}


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_connection_args(p)
    p.add_argument("--in-process", type=int, default=None, metavar="N")
    p.add_argument("--file", default=Config.file)
    p.add_argument("--max-constraints", type=int, default=Config.max_constraints)
    args = p.parse_args()
    cfg = Config(file=args.file, max_constraints=args.max_constraints)
    if args.in_process:
        print(main(cfg, StochasticMap(args.in_process)))
    else:
        with MapClient(**client_kwargs(args)) as client:
            print(main(cfg, client))
