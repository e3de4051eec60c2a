"""What a relinearisation costs against the length of the history it solves, on Victoria Park.

Protocol: stream the public Victoria Park file (``victoria_park.txt`` from the gtsam wheel) into
a bounded ``StochasticMap(N)`` (pose 0 kept as anchor, each older pose removed), with the
default options but no automatic relinearisation, and every ``--every`` inputs relinearise the
map on request, timing the call (wall and CPU), its parts (the kernel's solve: ordering,
Gauss-Newton, factorisation; the redraw of the edges) and what it holds (the history's bytes,
the Cholesky factor's values). The last row is the whole file: the longest a relinearisation
holds the map's worker (the ack wait of a ``relinearize`` request or of an update that
triggers one). Then the recording's growth: the size of one ``relinearize`` request record and
of the map's state snapshot with and without its factor history.

Run: ``.venv/bin/python benchmarks/bench_relin.py [--samples 1000] [--every 1000]
[--repeats 3]``. One JSON line per checkpoint, then a table. The machine's load varies: the
CPU seconds and the ratios within one run are what compare.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Any

import msgpack
import numpy as np
from mcsm import StochasticMap, wire
from mcsm.core import relin
from mcsm.recording import encode_snapshot
from mcsm_client.datasets import gtsam_data_dir, read_dataset
from mcsm_client.players import play


class Clock:
    """Wall time of the kernel's solve and redraw, accumulated (wraps the bindings)."""

    def __init__(self) -> None:
        self.solve_s = self.redraw_s = 0.0
        self.values = 0
        solve, redraw = relin.solve, relin.Solution.redraw

        def timed_solve(problem: relin.Problem, **kw: Any) -> relin.Solution:
            t0 = time.perf_counter()
            out = solve(problem, **kw)
            self.solve_s += time.perf_counter() - t0
            self.values = max(self.values, out.stats.factor_values)
            return out

        def timed_redraw(sol: relin.Solution, *a: Any, **kw: Any) -> None:
            t0 = time.perf_counter()
            redraw(sol, *a, **kw)
            self.redraw_s += time.perf_counter() - t0

        relin.solve = timed_solve  # type: ignore[assignment]
        relin.Solution.redraw = timed_redraw  # type: ignore[method-assign]

    def reset(self) -> None:
        self.solve_s = self.redraw_s = 0.0
        self.values = 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--every", type=int, default=1000, help="inputs between two checkpoints")
    ap.add_argument("--repeats", type=int, default=3, help="relinearisations per checkpoint")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    data = gtsam_data_dir()
    if data is None:
        raise SystemExit("bench_relin needs victoria_park.txt from the gtsam wheel (eval extra)")
    ds = read_dataset(data / "victoria_park.txt")
    n = args.samples
    m = StochasticMap(n, relinearize=None)
    clock = Clock()
    rows: list[dict[str, Any]] = []
    total = len(ds.constraints)
    marks = {*range(args.every, total, args.every), total}
    print(f"# Victoria Park, N = {n}, numpy {np.__version__}, {os.cpu_count()} cores, "
          f"kernel {relin.kernel.LIBRARY.rsplit('/', 1)[-1]}", flush=True)

    def checkpoint(done: int, _total: int, _stats: Any) -> None:
        if done not in marks:
            return
        h = m.factor_history
        assert h is not None
        walls, cpus, solves, redraws = [], [], [], []
        for _ in range(args.repeats):
            clock.reset()
            t0, c0 = time.perf_counter(), time.process_time()
            rep = m.relinearize()
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            solves.append(clock.solve_s)
            redraws.append(clock.redraw_s)
        comp = rep.components[0]
        row = {"inputs": done, "factors": h.factors.n, "variables": h.vars.n,
               "kept_frames": comp.frames, "history_mb": h.nbytes() / 2**20,
               "factor_mb": 2 * 8 * clock.values / 2**20,
               "iterations": comp.iterations, "wall_s": float(np.median(walls)),
               "cpu_s": float(np.median(cpus)), "solve_s": float(np.median(solves)),
               "redraw_s": float(np.median(redraws)), "worst_wall_s": float(max(walls))}
        rows.append(row)
        print(json.dumps(row), flush=True)

    play(ds, m, rng=np.random.default_rng(args.seed), n_samples=n, bounded=True,
         progress=checkpoint)
    snap = m.snapshot()
    with_h = len(msgpack.packb(encode_snapshot(snap), use_bin_type=True))
    without = len(msgpack.packb(encode_snapshot(
        {k: v for k, v in snap.items() if k != "factor_history"}), use_bin_type=True))
    req = len(wire.encode_relinearize("relin-0001", "x0"))
    print("\n| inputs | factors | variables | history MB | factor MB | iterations | "
          "wall s (median) | CPU s | solve s | redraw s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['inputs']} | {r['factors']} | {r['variables']} | {r['history_mb']:.2f} | "
              f"{r['factor_mb']:.2f} | {r['iterations']} | {r['wall_s']:.3f} | "
              f"{r['cpu_s']:.3f} | {r['solve_s']:.3f} | {r['redraw_s']:.3f} |")
    worst = max(r["worst_wall_s"] for r in rows)
    print(f"\nworst relinearisation (the longest ack wait): {worst:.3f} s wall, "
          f"{rows[-1]['inputs']} inputs")
    print(f"recording: a relinearize request payload {req} bytes; the final state snapshot "
          f"{with_h / 2**20:.2f} MB with its factor history, {without / 2**20:.2f} MB without")


if __name__ == "__main__":
    main()
