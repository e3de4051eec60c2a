"""Restore from a recorded state snapshot vs a full replay (issue 16 §4).

Writes one recording in-process (the server's own Recorder and MapState, no Zenoh): a 3-D map
grown frame by frame with a loop closure every 4th input, and a state snapshot every
``--snapshot-every`` operations; then times ``replay(path)`` (every input applied again) and
``replay(path, from_snapshot=True)`` (the latest snapshot, checked by its digest, plus the
inputs after it), checks that both end at the same digest, and prints the figures.

Run: ``.venv/bin/python benchmarks/bench_restore.py [--inputs 1400] [--samples 200]``
(output: ``benchmarks/results/bench_restore.txt``).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from mcsm import StochasticMap, wire
from mcsm.log.replay import replay
from mcsm.log.topics import decode_input
from mcsm.log.writer import Recorder
from mcsm.map.state import MapState
from mcsm_client.sampling import pose_from_planar, sample_pose

NOISE = np.diag([0.02**2] * 3 + [0.01**2] * 3)


def write(path: Path, n: int, count: int, snapshot_every: int) -> str:
    rng = np.random.default_rng(3)
    rec = Recorder(path)
    st = MapState("default", StochasticMap(n))
    rec.config(st, 100)
    k = 0
    for i in range(count):
        if i % 4 == 3 and k > 10:
            a, b = "p0", f"p{k}"
            x = st.map.query(a, b)[rng.permutation(n)]
        else:
            a, b = f"p{k}", f"p{k + 1}"
            mean = pose_from_planar([1.0, 0.1, 0.1])
            x = sample_pose(mean, NOISE, n_samples=n, rng=rng)
            k += 1
        payload = wire.encode_update(f"id{i}", a, b, x)
        ack = st.apply("update", decode_input("update", payload, n))
        rec.input("update", st.name, ack.seq, time.time_ns(), "bench", f"id{i}", payload)
        if ack.seq % 100 == 0:
            rec.checkpoint(st.name, ack.seq, st.digest(), "periodic")
        if ack.seq % snapshot_every == 0:
            rec.snapshot(st)
    rec.checkpoint(st.name, st.seq, st.digest(), "close")
    rec.close()
    return st.digest()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--inputs", type=int, default=1400)
    p.add_argument("--samples", type=int, default=200)
    p.add_argument("--snapshot-every", type=int, default=500)
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "r.mcap"
        final = write(path, a.samples, a.inputs, a.snapshot_every)
        size = path.stat().st_size
        print(f"{a.inputs} inputs, N = {a.samples}, snapshot every {a.snapshot_every}; file "
              f"{size / 1e6:.1f} MB; load average {os.getloadavg()[0]:.1f}")
        for label, fast in (("full replay", False), ("from snapshot", True),
                            ("full replay", False), ("from snapshot", True)):
            t0 = time.perf_counter()
            rep = replay(path, from_snapshot=fast)
            dt = time.perf_counter() - t0
            st = rep.states["default"]
            assert st.digest() == final and rep.identical, rep.divergence
            print(f"{label:14s} {dt:7.2f} s: {rep.n_inputs} inputs applied, "
                  f"{rep.snapshots_loaded} snapshot loaded, {st.map.n_frames} frames, digest "
                  f"equal")


if __name__ == "__main__":
    main()
