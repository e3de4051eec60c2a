"""Update, add-frame and query cost of the stochastic map vs frames M and samples N (PAPER §4,
Fig. 6): the compiled kernel ("new") and the numpy core before it ("old",
``tests/core/numpy_reference.py``) side by side in one run.

Protocol: grow a 3-D map frame by frame (odometry-like ATs) with the kernel; at each checkpoint
M copy its exact state into the old implementation, then apply ``--updates`` random case II
updates between existing frames (the observation is the current relation with its samples
permuted: an independent sample set with the same marginal) on each and time them. Each update
is also expressed in *passes*: its time over one streaming copy (``np.copyto``) of the same
``(M, N, 7)`` array, timed right before it, so figures taken at different hours of a shared
machine compare. Rows: new (default threads), new on one thread, new with the endpoint gain,
old. Then: adding a frame at each checkpoint (median of 20), queries (median of 200), the
fitted exponent of update time in M (M >= 50), the paper method at M = 400, memory.

Run: ``.venv/bin/python benchmarks/bench_core.py [--sizes 200 1000 5000] [--max-frames 1600]
[--quick]``. Output used in README: ``benchmarks/results/bench_core.txt``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.core import kernel
from mcsm_client.sampling import pose_from_planar, sample_pose

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root
from tests.core import numpy_reference as old  # noqa: E402  (the core before the kernel)

CHECKPOINTS = (25, 50, 100, 200, 400, 800, 1600)
NOISE_COV = np.diag([0.02**2] * 3 + [0.01**2] * 3)  # 2 cm, 0.6 deg per axis


def random_at(rng: np.random.Generator, n: int) -> np.ndarray:
    """A 3-D AT: 1 m forward-ish step, a few degrees of turn, cm/deg noise in all six axes."""
    mean = pose_from_planar(rng.normal([1.0, 0.2, 0.15], [0.05, 0.05, 0.01]))
    mean[2] = rng.normal(0.05, 0.05)
    return sample_pose(mean, NOISE_COV, n_samples=n, rng=rng)


def copy_pass_s(edges: np.ndarray, repeats: int = 3) -> float:
    dst = np.empty_like(edges)
    np.copyto(dst, edges)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        np.copyto(dst, edges)
        ts.append(time.perf_counter_ns() - t0)
    return float(np.median(ts)) * 1e-9


def old_copy(m: StochasticMap, **opts: Any) -> old.StochasticMap:
    """The old implementation holding exactly ``m``'s state."""
    return old.from_snapshot(m.snapshot(), **opts)


def timed_updates(m: Any, frames: list[str], rng: np.random.Generator, count: int,
                  edges: np.ndarray) -> tuple[float, float]:
    """(median milliseconds, median passes) of ``count`` random loop closures."""
    times, passes = [], []
    for _ in range(count):
        a, b = rng.choice(len(frames), 2, replace=False)
        obs = m.query(frames[a], frames[b])[rng.permutation(m.n_samples)]
        cp = copy_pass_s(edges)
        t0 = time.perf_counter_ns()
        m.update(frames[a], frames[b], obs)
        dt = (time.perf_counter_ns() - t0) * 1e-9
        times.append(dt)
        passes.append(dt / cp)
    return 1e3 * float(np.median(times)), float(np.median(passes))


def bench(n: int, updates: int, max_m: int, old_max_m: int, seed: int = 6
          ) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    variants: dict[str, dict[str, Any]] = {
        "new": {}, "new-1thread": {"threads": 1}, "new-endpoints": {"gain": "endpoints"}}
    maps = {name: StochasticMap(n, **o) for name, o in variants.items()}
    frames = ["f0"]
    rows: list[dict[str, Any]] = []
    for k in range(1, max_m + 1):
        x = random_at(rng, n)
        for mp in maps.values():
            mp.update(frames[-1], f"f{k}", x)
        frames.append(f"f{k}")
        if len(frames) not in CHECKPOINTS:
            continue
        m_frames = len(frames)
        edges = maps["new"].edges("f0")  # (M, N, 7): the copy pass's array
        row: dict[str, Any] = {"bench": "core_update", "n": n, "m": m_frames,
                               "edges_mib": edges.nbytes / 2**20}
        for name, mp in maps.items():
            row[f"{name}_ms"], row[f"{name}_passes"] = timed_updates(
                mp, frames, np.random.default_rng(k), updates, edges)
        if m_frames <= old_max_m:
            o = old_copy(maps["new"])
            row["old_ms"], row["old_passes"] = timed_updates(
                o, frames, np.random.default_rng(k), updates, edges)
            o_add = old_copy(maps["new"])
        qt = []
        for _ in range(200):
            a, b = rng.choice(m_frames, 2, replace=False)
            t0 = time.perf_counter_ns()
            maps["new"].query(frames[a], frames[b])
            qt.append(time.perf_counter_ns() - t0)
        row["query_us"] = 1e-3 * float(np.median(qt))
        # adding a frame to this component: new (buffer with spare capacity) and old (a copy)
        add_new, add_old = [], []
        scratch = StochasticMap.from_snapshot(maps["new"].snapshot())
        for j in range(20):
            x = random_at(rng, n)
            t0 = time.perf_counter_ns()
            scratch.update(frames[-1] if j == 0 else f"g{j - 1}", f"g{j}", x)
            add_new.append(time.perf_counter_ns() - t0)
            if m_frames <= old_max_m:
                t0 = time.perf_counter_ns()
                o_add.update(frames[-1] if j == 0 else f"g{j - 1}", f"g{j}", x)
                add_old.append(time.perf_counter_ns() - t0)
        row["add_new_ms"] = 1e-6 * float(np.median(add_new))
        if add_old:
            row["add_old_ms"] = 1e-6 * float(np.median(add_old))
        del scratch
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
        print(_line(row), flush=True)
    return rows


def _fmt(row: dict[str, Any], key: str, spec: str) -> str:
    return format(row[key], spec) if key in row else "-"


def _line(r: dict[str, Any]) -> str:
    return (f"{r['n']:5d} {r['m']:5d} | {r['new_ms']:8.2f} {r['new_passes']:5.1f} | "
            f"{r['new-1thread_ms']:8.2f} {r['new-1thread_passes']:5.1f} | "
            f"{r['new-endpoints_ms']:8.2f} {r['new-endpoints_passes']:5.1f} | "
            f"{_fmt(r, 'old_ms', '8.2f'):>8} {_fmt(r, 'old_passes', '5.1f'):>5} | "
            f"{_fmt(r, 'add_new_ms', '.3f'):>6} {_fmt(r, 'add_old_ms', '.2f'):>6} | "
            f"{r['query_us']:7.1f} {r['edges_mib']:8.1f}")


def exponent(rows: list[dict[str, Any]], key: str) -> float | None:
    pts = [(r["m"], r[key]) for r in rows if r["m"] >= 50 and key in r]
    if len(pts) < 2:
        return None
    ms, ts = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
    return float(np.polyfit(ms, ts, 1)[0])


def paper_at(n: int, m_frames: int, updates: int) -> tuple[float, float]:
    rng = np.random.default_rng(9)
    m = StochasticMap(n, method="paper")
    frames = [f"f{k}" for k in range(m_frames)]
    for k in range(m_frames - 1):
        m.update(frames[k], frames[k + 1], random_at(rng, n))
    return timed_updates(m, frames, rng, updates, m.edges("f0"))


def peak_update_mib(n: int, m_frames: int, method: str) -> float:
    rng = np.random.default_rng(7)
    m = StochasticMap(n, method=method)
    for k in range(m_frames - 1):
        m.update(f"f{k}", f"f{k + 1}", random_at(rng, n))
    for _ in range(2):  # the second update reuses the first one's spare buffer
        obs = m.query("f3", f"f{m_frames - 2}")[rng.permutation(n)]
        tracemalloc.start()
        m.update("f3", f"f{m_frames - 2}", obs)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak / 2**20


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[200, 1000, 5000])
    p.add_argument("--updates", type=int, default=9, help="timed updates per checkpoint")
    p.add_argument("--max-frames", type=int, default=1600)
    p.add_argument("--old-max-frames", type=int, default=1600,
                   help="largest M timed with the old implementation (slow at N = 5000)")
    p.add_argument("--quick", action="store_true", help="N = 200, 1000; M <= 400; 5 updates")
    a = p.parse_args()
    if a.quick:
        a.sizes, a.updates, a.max_frames = [s for s in a.sizes if s <= 1000], 5, 400
    print(f"numpy {np.__version__}, {os.cpu_count()} cores, kernel {Path(kernel.LIBRARY).name}, "
          f"{a.updates} updates per checkpoint, load average {os.getloadavg()[0]:.1f}")
    print("update: median ms and passes (update time / one np.copyto of the (M, N, 7) edges)")
    print(f"{'N':>5} {'M':>5} | {'new':>8} {'pass':>5} | {'1 thread':>8} {'pass':>5} | "
          f"{'endpoint':>8} {'pass':>5} | {'old':>8} {'pass':>5} | {'add ms':>6} {'old':>6} | "
          f"{'query µs':>7} {'MiB':>8}")
    for n in a.sizes:
        rows = bench(n, a.updates, a.max_frames, a.old_max_frames)
        exps = {k: exponent(rows, f"{k}_ms") for k in ("new", "new-1thread", "new-endpoints",
                                                         "old")}
        print(f"{n:5d}  exponent of update time in M (M >= 50): " + ", ".join(
            f"{k} {v:.2f}" for k, v in exps.items() if v is not None), flush=True)
    n_paper = 1000 if 1000 in a.sizes else a.sizes[0]
    ms, passes = paper_at(n_paper, 400, a.updates)
    print(f"paper method (tangent chart, kernel), N = {n_paper}, M = 400: {ms:.1f} ms, "
          f"{passes:.1f} passes")
    for method in ("joint", "paper"):
        print(f"tracemalloc peak of one {method} update, N = {n_paper}, M = 400: "
              f"{peak_update_mib(n_paper, 400, method):.1f} MiB "
              f"(edges {400 * n_paper * 7 * 8 / 2**20:.1f} MiB)")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
