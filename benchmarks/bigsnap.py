"""A recorded snapshot of a 100,000-frame map: write and read-back time and peak memory.

Builds a chain of ``--frames`` frames (N = ``--samples``) in the core, wraps it in the
server's ``MapState``, records its config, one ``/mcsm/snapshot`` (``Recorder.snapshot``, as
``--disk-snapshot-every`` does) and ``--after`` inputs after it (new frames and loop
closures), then reads the file back as ``mcsm serve --restore`` does (``replay(...,
from_snapshot=True)``) and checks the digest. Each phase runs in its own process so that its
peak resident memory (``VmHWM``, reset after the map was built) is its own. ``--single``
writes the snapshot as one record, as before chunked snapshots (mcsm.log.snapchunks).

Run: ``nice -n 10 .venv/bin/python benchmarks/bigsnap.py [--frames 100000] [--samples 100]
[--single]`` (figures in docs/kernel.md, "Serving a 100,000-frame map").
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _rss() -> dict[str, int]:
    out = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS:", "VmHWM:")):
                out[line.split(":")[0]] = int(line.split()[1]) * 1024
    return out


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)
    except OSError:
        pass


def write(path: Path, frames: int, n: int, after: int) -> dict[str, object]:
    from mcap.reader import make_reader
    from mcsm import StochasticMap, wire
    from mcsm.log.topics import TOPIC_SNAPSHOT_PART, decode_input
    from mcsm.log.writer import Recorder
    from mcsm.map.state import MapState
    from mcsm_client.sampling import pose_from_planar, sample_pose

    rng = np.random.default_rng(5)
    noise = np.diag([0.02**2] * 3 + [0.01**2] * 3)
    step = sample_pose(pose_from_planar([1.0, 0.0, 0.01]), noise, n_samples=n, rng=rng)
    t0 = time.perf_counter()
    m = StochasticMap(n, history=None)
    for k in range(frames - 1):
        m.update(f"p{k}", f"p{k + 1}", step)
    build_s = time.perf_counter() - t0
    st = MapState("default", StochasticMap(n, history=None))
    st.restore(frames - 1, m, {})
    rec = Recorder(path)
    rec.config(st, 100)
    _reset_peak()
    before = _rss()["VmRSS"]
    t0 = time.perf_counter()
    rec.snapshot(st)
    snap_s = time.perf_counter() - t0
    peak = _rss()["VmHWM"]
    size = rec._size()
    for i in range(after):
        if i % 10 == 9:  # a loop closure across the whole chain
            x = st.map.query("p0", f"p{frames - 1}")[rng.permutation(n)]
            payload = wire.encode_update(f"c{i}", "p0", f"p{frames - 1}", x)
        else:
            payload = wire.encode_update(f"u{i}", f"p{frames - 1}", f"q{i}", step)
        ack = st.apply("update", decode_input("update", payload, n), payload=payload)
        rec.input("update", st.name, ack.seq, time.time_ns(), "bench", f"id{i}", payload)
    rec.checkpoint(st.name, st.seq, st.digest(), "close")
    rec.close()
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    part_ch = [c.id for c in summary.channels.values() if c.topic == TOPIC_SNAPSHOT_PART]
    counts = summary.statistics.channel_message_counts
    return {"parts": sum(counts.get(c, 0) for c in part_ch), "build_s": build_s,
            "snapshot_s": snap_s, "snapshot_bytes": size, "edges_bytes": 56 * n * frames,
            "rss_before": before,
            "peak_over_before": peak - before, "digest": st.digest(), "seq": st.seq}


def read(path: Path) -> dict[str, object]:
    from mcsm.log.replay import replay

    class Probe:
        """A replay sink that only notes when the snapshot was loaded and verified."""

        loaded: tuple[float, int] = (0.0, 0)

        def config(self, *_a: object, **_k: object) -> None:
            pass

        def input(self, *_a: object, **_k: object) -> None:
            pass

        def checkpoint(self, *_a: object, **_k: object) -> None:
            pass

        def snapshot(self, *_a: object, **_k: object) -> None:
            self.loaded = (time.perf_counter(), _rss()["VmHWM"])

    probe = Probe()
    _reset_peak()
    before = _rss()["VmRSS"]
    t0 = time.perf_counter()
    rep = replay(path, from_snapshot=True, sink=probe)  # type: ignore[arg-type]
    read_s = time.perf_counter() - t0
    peak = _rss()["VmHWM"]
    st = rep.states["default"]
    return {"restore_s": read_s, "peak_over_before": peak - before,
            "load_s": probe.loaded[0] - t0, "load_peak": probe.loaded[1] - before,
            "snapshots_loaded": rep.snapshots_loaded, "inputs_after": rep.n_inputs,
            "identical": rep.identical, "digest": st.digest(), "seq": st.seq}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=100_000)
    p.add_argument("--samples", type=int, default=100)
    p.add_argument("--after", type=int, default=20)
    p.add_argument("--single", action="store_true", help="one record (the format before)")
    p.add_argument("--phase", choices=["write", "read"], help=argparse.SUPPRESS)
    p.add_argument("--path", help=argparse.SUPPRESS)
    a = p.parse_args()
    if a.phase == "write":
        print(json.dumps(write(Path(a.path), a.frames, a.samples, a.after)))
        return
    if a.phase == "read":
        print(json.dumps(read(Path(a.path))))
        return
    env = dict(os.environ)
    if a.single:
        env["MCSM_SNAPSHOT_CHUNK_BYTES"] = str(1 << 40)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.mcap"
        common = [sys.executable, __file__, "--path", str(path), "--frames", str(a.frames),
                  "--samples", str(a.samples), "--after", str(a.after)]
        w = json.loads(subprocess.run([*common, "--phase", "write"], env=env, check=True,
                                      capture_output=True, text=True).stdout)
        r = json.loads(subprocess.run([*common, "--phase", "read"], env=env, check=True,
                                      capture_output=True, text=True).stdout)
    gb = 1e9
    print(f"M = {a.frames}, N = {a.samples}: edges {w['edges_bytes'] / gb:.2f} GB, snapshot "
          f"{'in one record' if not w['parts'] else str(w['parts']) + ' parts'} "
          f"({w['snapshot_bytes'] / gb:.2f} GB "
          f"file incl. config); map built in {w['build_s']:.1f} s")
    print(f"  write: {w['snapshot_s']:.2f} s, peak RSS +{w['peak_over_before'] / gb:.2f} GB "
          f"over the process with its map ({w['rss_before'] / gb:.2f} GB)")
    print(f"  restore, to the snapshot loaded and its digest checked: {r['load_s']:.2f} s, "
          f"peak RSS +{r['load_peak'] / gb:.2f} GB")
    print(f"  restore (snapshot + {r['inputs_after']} inputs): {r['restore_s']:.2f} s, peak "
          f"RSS +{r['peak_over_before'] / gb:.2f} GB; snapshots loaded "
          f"{r['snapshots_loaded']}")
    same = r["digest"] == w["digest"] and r["seq"] == w["seq"] and r["identical"]
    print(f"  digest after restore == live digest: {same}")
    if not same:
        sys.exit(1)


if __name__ == "__main__":
    main()
