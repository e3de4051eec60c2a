"""Update and query cost of the stochastic map vs frames M and samples N (PAPER §4, Fig. 6).

Protocol: grow a 3-D map frame by frame (odometry-like ATs); at the checkpoints M = 25, 50,
100, 200, 400 apply ``--updates`` random case II updates between existing frames (the observation
is the current relation with its samples permuted, i.e. an independent sample set with the same
marginal) and time each one. ``--full`` instead applies 10 updates at *every* iteration as in the
paper (slow at N = 5000) and times those at the checkpoints. Each update is also expressed as a
multiple of one streaming pass (``np.copyto``) over the same ``(M, N, 7)`` array, measured right
before it. Prints a table, the fitted exponent of update time in M (M >= 50), query latency,
memory, and one JSON line per configuration on stderr.

Run: ``.venv/bin/python benchmarks/bench_core.py [--sizes 200 1000 5000] [--quick]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tracemalloc

import numpy as np
from mcsm import StochasticMap
from mcsm_client.sampling import pose_from_planar, sample_pose

CHECKPOINTS = (25, 50, 100, 200, 400)


NOISE_COV = np.diag([0.02**2] * 3 + [0.01**2] * 3)  # 2 cm, 0.6 deg per axis


def random_at(rng: np.random.Generator, n: int) -> np.ndarray:
    """A 3-D AT: 1 m forward-ish step, a few degrees of turn, cm/deg noise in all six axes."""
    mean = pose_from_planar(rng.normal([1.0, 0.2, 0.15], [0.05, 0.05, 0.01]))
    mean[2] = rng.normal(0.05, 0.05)
    return sample_pose(mean, NOISE_COV, n_samples=n, rng=rng)


def copy_pass_s(edges: np.ndarray, repeats: int = 5) -> float:
    dst = np.empty_like(edges)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        np.copyto(dst, edges)
        ts.append(time.perf_counter_ns() - t0)
    return float(np.median(ts)) * 1e-9


def timed_updates(m: StochasticMap, frames: list[str], rng: np.random.Generator,
                  count: int) -> tuple[list[float], list[float]]:
    times, passes = [], []
    for _ in range(count):
        a, b = rng.choice(len(frames), 2, replace=False)
        obs = m.query(frames[a], frames[b])[rng.permutation(m.n_samples)]
        cp = copy_pass_s(np.asarray(m.edges(frames[0])), 3)
        t0 = time.perf_counter_ns()
        m.update(frames[a], frames[b], obs)
        dt = (time.perf_counter_ns() - t0) * 1e-9
        times.append(dt)
        passes.append(dt / cp)
    return times, passes


def bench(n: int, method: str, updates: int, full: bool, max_m: int,
          seed: int = 6) -> list[dict[str, object]]:
    rng = np.random.default_rng(seed)
    m = StochasticMap(n, method=method)
    frames = ["f0"]
    rows: list[dict[str, object]] = []
    # warm-up on a throw-away map
    w = StochasticMap(n, method=method)
    for k in range(5):
        w.update(f"w{k}", f"w{k + 1}", random_at(rng, n))
    timed_updates(w, [f"w{k}" for k in range(6)], rng, 3)
    for k in range(1, max_m):
        m.update(frames[-1], f"f{k}", random_at(rng, n))
        frames.append(f"f{k}")
        if full and len(frames) not in CHECKPOINTS:
            timed_updates(m, frames, rng, 10)
        if len(frames) in CHECKPOINTS:
            times, passes = timed_updates(m, frames, rng, updates)
            qt = []
            for _ in range(200):
                a, b = rng.choice(len(frames), 2, replace=False)
                t0 = time.perf_counter_ns()
                m.query(frames[a], frames[b])
                qt.append(time.perf_counter_ns() - t0)
            row = {"bench": "core_update", "n": n, "m": len(frames), "method": method,
                   "space": m.space, "analysis": m.analysis,
                   "update_ms_median": 1e3 * float(np.median(times)),
                   "update_ms_p90": 1e3 * float(np.percentile(times, 90)),
                   "passes_median": float(np.median(passes)),
                   "query_us_median": 1e-3 * float(np.median(qt)),
                   "edges_mib": np.asarray(m.edges("f0")).nbytes / 2**20,
                   "updates_timed": len(times)}
            rows.append(row)
            print(json.dumps(row), file=sys.stderr)
    return rows


def peak_update_mib(n: int, method: str, m_frames: int) -> float:
    rng = np.random.default_rng(7)
    m = StochasticMap(n, method=method)
    for k in range(m_frames - 1):
        m.update(f"f{k}", f"f{k + 1}", random_at(rng, n))
    obs = m.query("f3", f"f{m_frames - 2}")[rng.permutation(n)]
    tracemalloc.start()
    m.update("f3", f"f{m_frames - 2}", obs)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    return peak / 2**20


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[200, 1000, 5000])
    p.add_argument("--methods", nargs="+", default=["joint", "paper"])
    p.add_argument("--updates", type=int, default=15, help="timed updates per checkpoint")
    p.add_argument("--full", action="store_true", help="10 updates at every iteration (paper)")
    p.add_argument("--quick", action="store_true", help="N = 200, 1000 only, 9 updates")
    p.add_argument("--max-frames", type=int, default=400)
    a = p.parse_args()
    if a.quick:
        a.sizes, a.updates = [s for s in a.sizes if s <= 1000], 9
    print(f"numpy {np.__version__}, {os.cpu_count()} cores, protocol: "
          f"{'full (10 updates/iteration)' if a.full else f'{a.updates} updates per checkpoint'}")
    print(f"{'method':7} {'N':>5} {'M':>4} {'update ms':>10} {'p90':>7} {'passes':>7} "
          f"{'query µs':>9} {'edges MiB':>9}")
    all_rows = []
    for method in a.methods:
        for n in a.sizes:
            rows = bench(n, method, a.updates, a.full, a.max_frames)
            all_rows += rows
            for r in rows:
                print(f"{method:7} {n:5d} {r['m']:4d} {r['update_ms_median']:10.2f} "
                      f"{r['update_ms_p90']:7.2f} {r['passes_median']:7.1f} "
                      f"{r['query_us_median']:9.1f} {r['edges_mib']:9.1f}", flush=True)
            ms = np.array([r["m"] for r in rows if int(r["m"]) >= 50], dtype=float)  # type: ignore[call-overload]
            ts = np.array([r["update_ms_median"] for r in rows if int(r["m"]) >= 50], dtype=float)  # type: ignore[call-overload]
            if len(ms) >= 2:
                slope = np.polyfit(np.log(ms), np.log(ts), 1)[0]
                print(f"{method:7} {n:5d}  fitted exponent of update time in M (M>=50): "
                      f"{slope:.2f}")
    n_peak = 1000 if 1000 in a.sizes else a.sizes[0]
    for method in a.methods:
        print(f"tracemalloc peak of one {method} update, N={n_peak}, M={a.max_frames}: "
              f"{peak_update_mib(n_peak, method, a.max_frames):.1f} MiB")


if __name__ == "__main__":
    main()
