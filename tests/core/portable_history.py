"""A scripted map history for the portability test (run as a subprocess).

Usage: ``python -m tests.core.portable_history [--threads K] [--replay FILE.mcap ...]``.
Prints one JSON object: the state digest of the same 3-D history (a chain with loop
closures, point landmarks, relinearisations on request and by the maps' policies, a join of two
components, a submap import, removals including a root's) under each option set that
``mcsm serve`` offers for the joint update, and, for each
``--replay`` file, whether it replays identical and its final digests; and a revisit under
the service's ``--gate-defer`` policy (its digest and every verdict). The parent test runs
this under other BLAS kernels, other numpy CPU features, other thread counts and other
builds of the compiled kernel, and requires one answer for all.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
from mcsm import StochasticMap

from tests.helpers import random_at

N = 50  # not a multiple of 4: the kernel's lane tails are part of the history
OPTION_SETS: dict[str, dict[str, object]] = {
    "defaults": {},
    "endpoints+1.002": {"gain": "endpoints", "inflation": 1.002},
    "adaptive": {"inflation": "adaptive"},
    "quaternion+enkf": {"space": "quaternion", "analysis": "enkf", "shrink": None},
    "denkf+1.01": {"analysis": "denkf", "inflation": 1.01},
    "no gate": {"gate": None},
    "paper": {"method": "paper"},
    "relinearize often": {"relinearize": {"nis": 0.5, "every": 4, "gap": 2, "regate": 1,
                                          "spread": 1.3},
                          "gate_scale": {"window": 3, "open": 1.0, "max": 4.0}},
    "recentre": {"relinearize": {"nis": 0.5, "gap": 2, "regate": 1, "spread": 1.3,
                                 "recentre": True}},
}


def history(threads: int, device: object = "cpu", **opts: object) -> str:
    """The digest of the scripted history; ``device``: where the maps keep their edges (the
    device tests run it on the emulated GPU)."""
    rng = np.random.default_rng(20261123)
    m = StochasticMap(N, threads=threads, device=device, **opts)  # type: ignore[arg-type]
    side = StochasticMap(N, threads=threads, device=device, **opts)  # type: ignore[arg-type]
    for k in range(30):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, N, kind="cloud", t_sigma=0.2,
                                                  r_sigma=0.05))
        if k % 4 == 0:
            m.update(f"p{k}", f"l{k}", 2.0 + 0.2 * rng.standard_normal((N, 3)))
        if k % 6 == 5:  # loop closures: pose-pose and pose-point
            a = int(rng.integers(0, k))
            m.update(f"p{a}", f"p{k + 1}",
                     m.query(f"p{a}", f"p{k + 1}")[rng.permutation(N)])
            m.update(f"p{k + 1}", f"l{4 * (a // 4)}",
                     m.query(f"p{k + 1}", f"l{4 * (a // 4)}")[:, :3][rng.permutation(N)])
        if k in (12, 24):
            m.remove(f"p{k - 8}")  # a removed pose, then a relinearisation on request
            m.relinearize()
    for k in range(8):  # a second robot's map, exported and imported
        side.update(f"r2/q{k}", f"r2/q{k + 1}", random_at(rng, N, kind="cloud", t_sigma=0.2))
    m.import_component(side.export_component("r2/q0"))
    m.update("p30", "r2/q3", random_at(rng, N, kind="cloud", t_sigma=0.3))  # join (case I)
    m.update("p10", "r2/q7", m.query("p10", "r2/q7")[rng.permutation(N)])  # loop across
    m.remove("p5")
    m.remove("p0")  # the root: re-root at the next full frame
    m.update("p1", "p29", m.query("p1", "p29")[rng.permutation(N)])
    m.remove("r2/q8")
    m.relinearize("p1")  # an imported submap's component: skipped, the digest unchanged
    return m.state_digest()


def deferral_history(threads: int, device: object = "cpu") -> str:
    """A revisit under ``--gate-defer`` (the service's policy over the core): its closures are
    held, paired through the map's joint samples (the cycle test) and decided; the digest and
    every verdict's status and NIS."""
    from mcsm import wire
    from mcsm.map.deferral import DeferOptions, Deferral

    rng = np.random.default_rng(20261124)
    m = StochasticMap(N, threads=threads, device=device)
    dfr = Deferral(DeferOptions(expiry=6, revisit_gap=3), m.gate)
    statuses = []

    def send(seq: int, a: str, b: str, x: np.ndarray) -> None:
        out = dfr.update(m, seq, wire.UpdateRequest(f"r{seq}", a, b, x))
        statuses.append(f"{out.verdict.status}:{out.verdict.nis!r}")
        statuses.extend(f"{rid}={v.status}" for rid, v in sorted(out.decided.items()))

    seq = 0
    for k in range(24):
        seq += 1
        send(seq, f"p{k}", f"p{k + 1}", random_at(rng, N, kind="cloud", t_sigma=0.1,
                                                   r_sigma=0.02))
        if k in (12, 13, 14, 20, 21):  # revisits: true closures, then a wrong one
            a = k - 10
            x = m.query(f"p{a}", f"p{k + 1}")[rng.permutation(N)]
            if k == 21:
                x = x.copy()
                x[:, 0] += 3.0
            seq += 1
            send(seq, f"p{a}", f"p{k + 1}", x)
    return m.state_digest() + ";" + ",".join(statuses)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--replay", nargs="*", default=[])
    args = ap.parse_args(argv)
    out: dict[str, object] = {name: history(args.threads, **opts)
                              for name, opts in OPTION_SETS.items()}
    out["gate-defer"] = deferral_history(args.threads)
    if args.replay:
        from mcsm.log.replay import replay

        for path in args.replay:
            rep = replay(path)
            out[path] = {"identical": rep.identical, "divergence": rep.divergence,
                         "final": rep.final_digests()}
    json.dump(out, sys.stdout, sort_keys=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
