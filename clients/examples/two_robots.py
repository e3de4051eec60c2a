"""Two robots, two maps: join them at a rendezvous, then close loops across them.

PAPER §3: robot A and robot B each map half of the §6 circle world in their own map; A then
observes B (an AT between their poses), B's component is exported and imported into A's map
and the observation joins the two (case I); B drives on into A's area and its sightings of A's
landmarks close loops across the two maps (case II). Scores against ground truth are printed
per stage. With ``--connect-b`` robot B uses its own server; by default B's map is an
in-process map (or, with ``--in-process``, both are).

    python clients/examples/two_robots.py --in-process 200
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.serve.connect import add_connection_args, client_kwargs
from mcsm_client.client import MapClient
from mcsm_client.multirobot import MultiRobotConfig, run_multirobot


def main(config: MultiRobotConfig, map_a: Any, map_b: Any, seed: int = 7) -> str:
    """Run the two-robot scenario; return the per-stage summary."""
    return run_multirobot(config, map_a, map_b, rng=np.random.default_rng(seed)).summary()


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    add_connection_args(p)
    p.add_argument("--connect-b", default=None, metavar="ENDPOINT",
                   help="robot B's server (default: an in-process map for B)")
    p.add_argument("--in-process", type=int, default=None, metavar="N")
    p.add_argument("--landmarks", type=int, default=200)
    args = p.parse_args()
    cfg = MultiRobotConfig(n_landmarks=args.landmarks)
    if args.in_process:
        print(main(cfg, StochasticMap(args.in_process), StochasticMap(args.in_process)))
    else:
        with MapClient(**client_kwargs(args)) as a:
            if args.connect_b:
                with MapClient(**dict(client_kwargs(args), connect=args.connect_b)) as b:
                    print(main(cfg, a, b))
            else:
                print(main(cfg, a, StochasticMap(a.info().n_samples)))
