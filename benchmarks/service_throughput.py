"""Service throughput: acknowledged updates/s, query round trip, replay speed (prints figures).

Run by hand: ``.venv/bin/python benchmarks/service_throughput.py [--samples 1000] [--quick]
[--layouts flat,indexed,indexed-lz4]``.

``--layouts flat,indexed-lz4`` runs every configuration once per recording layout, side by side
in one run: ``flat`` is the unchunked layout of recording format 1 (the recorder before indexed
recordings), ``indexed-lz4`` the chunked, indexed layout with CRCs and lz4 chunks (the
default), ``indexed`` the same uncompressed; the layout reaches the server through the
environment variable ``MCSM_RECORDING_LAYOUT``.

A real ``mcsm serve`` subprocess (embedded Zenoh peer on a free loopback port, recording on,
``Writer.flush()`` before every ack) and a ``MapClient`` in this process. For each
configuration the same operations are also applied in-process (``MapState.apply``, no I/O), so
the table separates the core's cost from transport + decode + recording. Replay speed is
``mcsm.log.replay.replay`` on the very file the live run wrote. No assertions, no pass/fail.

Configurations (N samples per AT, default 1000):

* ``small``: a bounded robot map of at most 10 frames: per step one odometry update (new
  pose frame), one re-observation of one of 5 fixed landmark frames (case II loop closure),
  and one remove of the previous pose. Every one of them is an acknowledged operation.
* ``odometry``: the same small map fed only odometry and removes (cheap core operations):
  the ceiling of the ack pipeline itself.
* ``frames200``: a 200-frame component (odometry chain), then odometry updates and loop
  closures at M ~ 200.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from mcsm import StochasticMap
from mcsm.log.replay import replay
from mcsm.log.topics import decode_input
from mcsm.map.state import MapState
from mcsm_client.client import MapClient
from mcsm_client.process import ServerProcess
from mcsm_client.sampling import pose_from_planar, sample_pose

Op = tuple[str, str, str, np.ndarray | None]


NOISE_COV = np.diag([0.05**2] * 3 + [0.01**2] * 3)  # 5 cm, 0.6 deg per axis


def at(rng: np.random.Generator, n: int, t: list[float], yaw: float = 0.0) -> np.ndarray:
    """An AT of N samples around translation ``t`` (m) and a turn of ``yaw`` (rad) about z."""
    mean = pose_from_planar([t[0], t[1], yaw])
    mean[2] = t[2]
    return sample_pose(mean, NOISE_COV, n_samples=n, rng=rng)


def start_server(workdir: Path, n: int, name: str, layout: str = "indexed-lz4") -> ServerProcess:
    try:
        return ServerProcess(workdir / f"{name}.mcap", n_samples=n,
                             extra_args=("--log-level", "WARNING"),
                             env={"MCSM_RECORDING_LAYOUT": layout}).start()
    except RuntimeError as exc:
        raise SystemExit(f"server did not start: {exc}") from None


def small_map_ops(rng: np.random.Generator, n: int, steps: int) -> tuple[list[Op], list[Op]]:
    """Setup (5 landmarks + first pose) and the measured bounded-map steps (3 ops each)."""
    setup: list[Op] = [("update", "lm0", f"lm{k}", at(rng, n, [float(k), 2.0, 0.0]))
                       for k in range(1, 5)]
    setup.append(("update", "lm0", "pose0", at(rng, n, [0.0, -2.0, 0.0])))
    ops: list[Op] = []
    for i in range(steps):
        ops.append(("update", f"pose{i}", f"pose{i + 1}", at(rng, n, [0.2, 0.0, 0.0], 0.01)))
        ops.append(("update", f"pose{i + 1}", f"lm{i % 5}", at(rng, n, [0.5, 4.0, 0.0])))
        ops.append(("remove", f"pose{i}", "", None))
    return setup, ops


def odometry_ops(rng: np.random.Generator, n: int, steps: int) -> tuple[list[Op], list[Op]]:
    """The cheapest stream for the core: odometry (new pose frame) + remove the old pose, on
    a map of at most 7 frames. Shows the ceiling of the ack pipeline (transport, decode,
    recording) when the core costs little."""
    setup, _ = small_map_ops(rng, n, 0)
    ops: list[Op] = []
    for i in range(steps):
        ops.append(("update", f"pose{i}", f"pose{i + 1}", at(rng, n, [0.2, 0.0, 0.0], 0.01)))
        ops.append(("remove", f"pose{i}", "", None))
    return setup, ops


def frames200_ops(rng: np.random.Generator, n: int, steps: int) -> tuple[list[Op], list[Op]]:
    """A 200-frame chain, then per step: odometry (new frame), remove the oldest frame (M stays
    200; removing the root re-roots), and every other step a loop closure across the chain."""
    setup: list[Op] = [("update", f"f{i}", f"f{i + 1}", at(rng, n, [1.0, 0.0, 0.0]))
                       for i in range(199)]
    ops: list[Op] = []
    head, oldest = 199, 0
    for i in range(steps):
        ops.append(("update", f"f{head}", f"f{head + 1}", at(rng, n, [1.0, 0.0, 0.0])))
        head += 1
        ops.append(("remove", f"f{oldest}", "", None))
        oldest += 1
        if i % 2 == 1:
            ops.append(("update", f"f{oldest}", f"f{head}",
                        at(rng, n, [float(head - oldest), 0.0, 0.0])))
    return setup, ops


def send(c: MapClient, op: Op) -> str:
    kind, a, b, x = op
    if kind == "remove":
        return c.remove(a).kind
    return c.update(a, b, x).kind


def core_only(n: int, setup: list[Op], batches: list[list[Op]]) -> list[float]:
    """Seconds per batch applying the same ops in-process (decode + core, no I/O)."""
    from mcsm import wire

    st = MapState("default", StochasticMap(n))
    rid = iter(range(10**9))

    def apply(op: Op) -> None:
        kind, a, b, x = op
        if kind == "remove":
            st.apply("remove", decode_input("remove", wire.encode_remove(f"r{next(rid)}", a), n))
        else:
            st.apply("update", decode_input("update",
                                            wire.encode_update(f"r{next(rid)}", a, b, x), n))

    for op in setup:
        apply(op)
    out = []
    for batch in batches:
        t0 = time.perf_counter_ns()
        for op in batch:
            apply(op)
        out.append((time.perf_counter_ns() - t0) / 1e9)
    return out


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc), all its threads."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stats(xs: list[float]) -> dict[str, float]:
    s = sorted(xs)
    return {"median": statistics.median(s), "p10": s[max(0, int(0.1 * len(s)) - 1)],
            "p90": s[min(len(s) - 1, int(0.9 * len(s)))]}


def run_config(name: str, n: int, setup: list[Op], ops: list[Op], repeats: int,
               workdir: Path, rng: np.random.Generator, query_pair: tuple[str, str],
               n_queries: int, layout: str = "indexed-lz4", tag: str = "") -> dict[str, Any]:
    per = len(ops) // repeats
    batches = [ops[k * per:(k + 1) * per] for k in range(repeats)]
    server = start_server(workdir, n, f"{name}-{layout}{tag}", layout)
    pid, rec = server.pid, server.record
    assert pid is not None
    try:
        with MapClient(connect=server.endpoint, timeout_s=60) as c:
            cpu0 = cpu_s(pid)
            t_setup = time.perf_counter_ns()
            for op in setup:
                send(c, op)
            setup_s = (time.perf_counter_ns() - t_setup) / 1e9
            live = []
            kinds: dict[str, int] = {}
            for batch in batches:
                t0 = time.perf_counter_ns()
                for op in batch:
                    k = send(c, op)
                    kinds[k] = kinds.get(k, 0) + 1
                live.append((time.perf_counter_ns() - t0) / 1e9)
            # the same operations replay will apply: setup + measured batches
            server_cpu_ms = 1e3 * (cpu_s(pid) - cpu0) / (len(setup) + per * repeats)
            frames = c.info().n_frames
            a, b = query_pair
            for _ in range(20):  # warm-up
                c.query(a, b)
            q_rtt, m_rtt = [], []
            for _ in range(n_queries):
                t0 = time.perf_counter_ns()
                c.query(a, b)
                q_rtt.append((time.perf_counter_ns() - t0) / 1e6)
            for _ in range(max(20, n_queries // 4)):
                t0 = time.perf_counter_ns()
                c.marginal(a, b)
                m_rtt.append((time.perf_counter_ns() - t0) / 1e6)
    finally:
        server.stop(timeout_s=60)
    core = core_only(n, setup, batches)
    c0 = time.process_time()
    rep = replay(rec)
    replay_cpu_ms = 1e3 * (time.process_time() - c0) / max(1, rep.n_inputs)
    n_total = len(setup) + per * repeats
    live_rates = [per / t for t in live]
    core_rates = [per / t for t in core]
    return {
        "config": name, "layout": layout, "n_samples": n, "frames_at_end": frames,
        "ops_per_batch": per,
        "repeats": repeats, "kinds": kinds,
        "acked_ops_per_s": stats(live_rates), "core_only_ops_per_s": stats(core_rates),
        "query_rtt_ms": stats(q_rtt), "marginal_rtt_ms": stats(m_rtt),
        "replay_ops_per_s": rep.n_inputs / rep.elapsed_s, "replay_inputs": rep.n_inputs,
        "replay_identical": rep.identical, "live_ops_incl_setup": n_total,
        "live_whole_file_ops_per_s": n_total / (setup_s + sum(live)),
        "server_cpu_ms_per_op": server_cpu_ms, "replay_cpu_ms_per_op": replay_cpu_ms,
        "recording_bytes": rec.stat().st_size,
        "recording_bytes_per_op": rec.stat().st_size / max(1, rep.n_inputs),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    p.add_argument("--samples", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--rounds", type=int, default=1,
                   help="run every configuration and layout this many times, interleaved "
                        "(the layout order alternates per round); the summary takes medians")
    p.add_argument("--quick", action="store_true", help="fewer operations (a smoke run)")
    p.add_argument("--layouts", default="indexed-lz4",
                   help="comma-separated recording layouts to compare: flat (format 1), "
                        "indexed, indexed-lz4 (the default), indexed-zstd")
    args = p.parse_args()
    layouts = [x for x in args.layouts.split(",") if x]
    n, reps = args.samples, args.repeats
    rng = np.random.default_rng(20260101)
    small_steps = (10 if args.quick else 40) * reps // 3 + 1
    big_steps = (4 if args.quick else 10) * reps
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    print(f"# numpy {np.__version__}, {os.cpu_count()} cores, load average {load}, N={n}, "
          f"{reps} repeats",
          flush=True)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        s_setup, s_ops = small_map_ops(rng, n, small_steps)
        o_setup, o_ops = odometry_ops(rng, n, (15 if args.quick else 60) * reps // 2)
        b_setup, b_ops = frames200_ops(rng, n, big_steps)
        configs = [("small", s_setup, s_ops, ("lm0", "lm3"), 100 if args.quick else 500),
                   ("odometry", o_setup, o_ops, ("lm0", "lm3"), 50),
                   ("frames200", b_setup, b_ops, ("f150", "f190"), 50 if args.quick else 200)]
        for k in range(args.rounds):
            for name, setup, ops, pair, nq in configs:
                # the same operations for every layout, one layout right after the other
                for layout in (layouts if k % 2 == 0 else layouts[::-1]):
                    r = run_config(name, n, setup, ops, reps, work, rng, pair, nq, layout,
                                   f"-{k}")
                    r["round"] = k
                    results.append(r)
    for r in results:
        print(json.dumps(r))
    print()
    hdr = (f"{'config':<10} {'layout':<12} {'kB/op':>6} {'frames':>6} {'acked ops/s':>16} "
           f"{'core-only ops/s':>16} "
           f"{'replay/live (file)':>18} {'CPU ms/op srv|replay':>20} {'query ms (p90)':>15} "
           f"{'marginal ms':>11}")
    print(hdr)
    for r in sorted(results, key=lambda r: (r["config"], r["layout"], r["round"])):
        a, c, q, m = (r["acked_ops_per_s"], r["core_only_ops_per_s"], r["query_rtt_ms"],
                      r["marginal_rtt_ms"])
        print(f"{r['config']:<10} {r['layout']:<12} {r['recording_bytes_per_op'] / 1e3:>6.1f} "
              f"{r['frames_at_end']:>6} "
              f"{a['median']:>7.0f} [{a['p10']:.0f}-{a['p90']:.0f}] "
              f"{c['median']:>7.0f} [{c['p10']:.0f}-{c['p90']:.0f}] "
              f"{r['replay_ops_per_s']:>7.0f}/{r['live_whole_file_ops_per_s']:<7.0f}"
              f"={r['replay_ops_per_s'] / r['live_whole_file_ops_per_s']:4.1f}x"
              f" {r['server_cpu_ms_per_op']:>10.2f} | {r['replay_cpu_ms_per_op']:<7.2f}"
              f" {q['median']:>7.2f} ({q['p90']:.2f}) "
              f"{m['median']:>11.2f}")
    print("\nacked ops/s: median [p10-p90] over the repeats; each op is an acknowledged RPC "
          "(update or remove), recorded and flushed before its ack. replay/live (file): ops/s "
          "of mcsm.log.replay.replay over the whole recording vs the live run that wrote it "
          "(setup included), and their ratio. CPU ms/op: CPU time of the server process (all "
          "threads: zenoh, decode, core, recording) vs of replay, per input of the same file; "
          "the fair comparison when the machine is shared. kB/op: recording size per input "
          "(whole file, checkpoints included).")
    if args.rounds > 1 or len(layouts) > 1:
        print(f"\nsummary over {args.rounds} round(s): median of the per-round medians")
        print(f"{'config':<10} {'layout':<12} {'acked ops/s':>11} {'srv CPU ms/op':>13} "
              f"{'kB/op':>6}")
        for name in dict.fromkeys(r["config"] for r in results):
            for layout in layouts:
                rows = [r for r in results if r["config"] == name and r["layout"] == layout]
                acked = statistics.median(r["acked_ops_per_s"]["median"] for r in rows)
                cpu = statistics.median(r["server_cpu_ms_per_op"] for r in rows)
                kb = rows[0]["recording_bytes_per_op"] / 1e3
                print(f"{name:<10} {layout:<12} {acked:>11.0f} {cpu:>13.2f} {kb:>6.1f}")


if __name__ == "__main__":
    main()
