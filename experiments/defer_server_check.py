"""Does the server's deferral (``mcsm serve --gate-defer``, :mod:`mcsm.map.deferral`) decide as the
client-side policy the outlier benchmark measured (:class:`mcsm_client.outliers.DeferringMap`)?

Feeds the benchmark's pose-graph cases (``experiments/outliers.py``: graphs, kinds of wrong
closures, rates, seeds) to a :class:`mcsm.map.state.MapState` with deferral (the server's worker
code, without Zenoh) and to ``DeferringMap`` over the same inputs, and prints per case whether
the final digests and every closure's final status agree, and the time per update of both.

Usage: ``.venv/bin/python -m experiments.defer_server_check [--graphs planar 3d long drift]
[--seeds 8] [--n-samples 200]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

import numpy as np
from mcsm import StochasticMap, wire
from mcsm.map.deferral import DeferOptions
from mcsm.map.state import MapState
from mcsm_client.outliers import DeferringMap, Ledger, Record

from experiments.outliers import GATE, KINDS, RATES, corrupt, make_graph
from experiments.posegraph_sim import sample_measurement

SIZES = {"planar": 500, "3d": 500, "long": 700, "drift": 700}


def check(name: str, kind: str, rate: float, seed: int, n_samples: int
          ) -> tuple[bool, int, int, int, float, float]:
    """(same digest, closures with the same final status, closures, closures held, server and
    client ms per update)."""
    graph = make_graph(name, SIZES[name], seed)
    meas, _ = corrupt(graph, kind, rate, seed)
    g = replace(graph, measurements=meas)
    draw = np.random.default_rng([seed, 99])  # the same draws as outliers.pose_graph_rows
    samples = [sample_measurement(z, c, n_samples, rng=draw)
               for z, c in zip(g.measurements, g.covariances, strict=True)]

    def fresh() -> StochasticMap:
        return StochasticMap(n_samples, gain="endpoints", inflation=1.002, gate=GATE)

    st = MapState("default", fresh(), gate_defer=DeferOptions())
    t0 = time.perf_counter()
    for k, ((i, j), x) in enumerate(zip(g.edges, samples, strict=True)):
        st.apply("update", wire.UpdateRequest(f"r{k}", f"p{i}", f"p{j}", x), time_ns=0)
    t_server = time.perf_counter() - t0
    client = DeferringMap(Ledger(fresh(), snapshot_every=100))
    t0 = time.perf_counter()
    for k, ((i, j), x) in enumerate(zip(g.edges, samples, strict=True)):
        client.update(Record(k, f"p{i}", f"p{j}", x))
    t_client = time.perf_counter() - t0
    loops = np.flatnonzero(g.is_loop)
    differ = [int(k) for k in loops
              if st.verdict_of(f"r{k}").verdict.status  # type: ignore[union-attr]
              != client.final_status(int(k))]
    same = st.map.state_digest() == client.map.state_digest()
    n = len(g.edges)
    held = sum(1 for k in loops if st.verdict_of(f"r{k}").kind == "pending")
    return (same, len(loops) - len(differ), len(loops), held, 1e3 * t_server / n,
            1e3 * t_client / n)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--graphs", nargs="*", default=["planar", "3d", "long", "drift"])
    ap.add_argument("--kinds", nargs="*", default=list(KINDS))
    ap.add_argument("--rates", nargs="*", type=float, default=list(RATES))
    ap.add_argument("--seeds", nargs="*", type=int, default=[8])
    ap.add_argument("--n-samples", type=int, default=200)
    args = ap.parse_args(argv)
    print("| case | same digest | same final status (closures) | held | server ms/update "
          "| client ms/update |")
    print("|---|---|---|---|---|---|")
    for seed in args.seeds:
        for name in args.graphs:
            for kind in args.kinds:
                for rate in args.rates:
                    same, agree, n, held, ms_s, ms_c = check(name, kind, rate, seed,
                                                             args.n_samples)
                    print(f"| {name} {kind} {int(round(rate * 100))} %, seed {seed} "
                          f"| {'yes' if same else 'NO'} | {agree} / {n} | {held} "
                          f"| {ms_s:.2f} | {ms_c:.2f} |", flush=True)


if __name__ == "__main__":
    main()
