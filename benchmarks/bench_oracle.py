"""Linear-Gaussian oracle: error of every update rule against the exact posterior vs N.

A translation-only chain of 10 frames, 9 odometry edges and 6 loop closures (tests/core/oracle.py);
the exact posterior is the weighted least-squares solution. Prints, per rule and N, the RMS of
(map mean − exact mean) in posterior σ and the RMS relative error of the marginal σ, averaged
over seeds, and sqrt(N) × the mean error (flat for 1/sqrt(N) convergence, growing for a bias).
Run: ``.venv/bin/python benchmarks/bench_oracle.py [--seeds 4]``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.core.oracle import make_problem, normalised_errors, run_map, wls  # noqa: E402

RULES = {
    "joint/ensrf": {"analysis": "ensrf"},
    "joint/enkf": {"analysis": "enkf"},
    "joint/denkf": {"analysis": "denkf"},
    "paper/tangent": {"method": "paper"},
    "paper/quaternion": {"method": "paper", "space": "quaternion"},
}


def main(seeds: int, sizes: list[int]) -> None:
    print(f"{'rule':18} {'N':>5} {'mean err/σ':>11} {'σ rel err':>10} {'√N·err':>8}")
    for name, opts in RULES.items():
        for n in sizes:
            es, ss = [], []
            for s in range(seeds):
                _, odo, loops = make_problem(np.random.default_rng(1000 + s))
                mean, cov = wls(odo, loops)
                m = run_map(odo, loops, n, np.random.default_rng(2000 + s), **opts)
                e, sd = normalised_errors(m, mean, cov)
                es.append(e)
                ss.append(sd)
            e, sd = float(np.mean(es)), float(np.mean(ss))
            print(f"{name:18} {n:5d} {e:11.4f} {sd:10.4f} {e * np.sqrt(n):8.2f}")
            print(json.dumps({"bench": "oracle", "rule": name, "n": n, "mean_err_sigma": e,
                              "sd_rel_err": sd, "seeds": seeds}), file=sys.stderr)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=4)
    p.add_argument("--sizes", type=int, nargs="+", default=[200, 1000, 5000])
    a = p.parse_args()
    main(a.seeds, a.sizes)
