"""Recording size per operation, and what lossless compression would save (prints figures).

Run by hand: ``.venv/bin/python benchmarks/recording_size.py [--samples 1000]
[--iterations 120] [--layouts flat,indexed,indexed-lz4,indexed-zstd] [FILE.mcap ...]``.

Without files, it records two workloads with a real ``mcsm serve`` subprocess (loopback,
default recording layout): the paper's planar simulation (``mcsm-client sim``: odometry,
point landmarks, removes) and the 3-D stream of ``benchmarks/service_throughput.py``
(``small``). For each recording it prints the bytes per input, then, on the recorded input
records, the size and the encoding cost per input of lossless candidates, each applied per
input as the recorder must (one chunk per flushed input):

* ``zstd`` / ``lz4``: MCAP chunk compression of the record;
* ``shuffle+zstd``: the request's float64 samples transposed to column planes and
  byte-shuffled (all first bytes, all second bytes, ...), the rest of the record as is, then
  zstd; decodes to the identical request bytes (checked here for every input).

The issue's rule: make compression the default only if files get >= 20 % smaller without
lowering the acknowledged throughput. No assertions, no pass/fail.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import lz4.frame
import numpy as np
import zstandard
from mcsm import wire
from mcsm.log.reader import RecordingReader
from mcsm.log.topics import TOPIC_OPS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from service_throughput import (  # noqa: E402
    send,
    small_map_ops,
    start_server,
)


def record_sim(work: Path, n: int, iterations: int, layout: str = "indexed",
               name: str = "sim") -> Path:
    server = start_server(work, n, name, layout)
    try:
        subprocess.run([sys.executable, "-m", "mcsm_client.cli", "sim", "--connect",
                        server.endpoint, "--iterations", str(iterations), "--json"], check=True,
                       capture_output=True, timeout=3600)
    finally:
        server.stop(timeout_s=60)
    return server.record


def record_3d(work: Path, n: int, steps: int, layout: str = "indexed",
              name: str = "small3d") -> Path:
    from mcsm_client.client import MapClient

    setup, ops = small_map_ops(np.random.default_rng(7), n, steps)
    server = start_server(work, n, name, layout)
    try:
        with MapClient(connect=server.endpoint, timeout_s=60) as c:
            for op in setup + ops:
                send(c, op)
    finally:
        server.stop(timeout_s=60)
    return server.record


def shuffle_planes(record: dict[str, Any]) -> tuple[bytes, bytes]:
    """(record without the samples' bytes, byte-shuffled column planes of the samples)."""
    req = wire.unpack(record["request"])
    data = req.get("samples", {}).get("data")
    if not isinstance(data, bytes) or len(data) % 8:
        return wire.pack(record), b""
    cols = int(req["samples"]["shape"][-1])
    x = np.frombuffer(data, np.uint8).reshape(-1, cols, 8)
    planes = np.ascontiguousarray(x.transpose(1, 2, 0)).tobytes()  # column, byte, sample
    at = record["request"].index(data)
    rest = dict(record, request=record["request"][:at] + record["request"][at + len(data):])
    # the inverse, checked: the exact request bytes come back
    back = np.frombuffer(planes, np.uint8).reshape(cols, 8, -1).transpose(2, 0, 1).tobytes()
    assert back == data
    return wire.pack(rest), planes


def measure(path: Path) -> None:
    rd = RecordingReader(path)
    records = [it.data for it in rd if it.topic in TOPIC_OPS]
    size = path.stat().st_size
    raw = [wire.pack(r) for r in records]
    print(f"\n{path.name}: {len(records)} inputs, {size / 1e6:.2f} MB, "
          f"{size / len(records) / 1e3:.1f} kB per input (whole file), "
          f"{sum(map(len, raw)) / len(raw) / 1e3:.1f} kB per input record")
    zc1 = zstandard.ZstdCompressor(level=1)
    zc3 = zstandard.ZstdCompressor(level=3)

    def sh(level: zstandard.ZstdCompressor, r: dict[str, Any]) -> int:
        head, planes = shuffle_planes(r)
        return len(level.compress(head + planes))

    cands = [("none", lambda i: len(raw[i])),
             ("lz4", lambda i: len(lz4.frame.compress(raw[i]))),
             ("zstd-1", lambda i: len(zc1.compress(raw[i]))),
             ("zstd-3", lambda i: len(zc3.compress(raw[i]))),
             ("shuffle+zstd-1", lambda i: sh(zc1, records[i])),
             ("shuffle+zstd-3", lambda i: sh(zc3, records[i]))]
    base = sum(map(len, raw))
    print(f"{'candidate':<16} {'kB/input':>9} {'vs none':>8} {'us/input':>9}")
    for name, f in cands:
        t0 = time.perf_counter()
        total = sum(f(i) for i in range(len(raw)))
        us = 1e6 * (time.perf_counter() - t0) / len(raw)
        print(f"{name:<16} {total / len(raw) / 1e3:>9.1f} {total / base - 1:>+8.1%} {us:>9.0f}")


def acked_rate(path: Path) -> tuple[int, float, float]:
    """(inputs, bytes per input, inputs per second between the first and last receive time)."""
    recv = [int(it.data["recv_ns"]) for it in RecordingReader(path) if it.topic in TOPIC_OPS]
    span_s = (recv[-1] - recv[0]) / 1e9
    return len(recv), path.stat().st_size / len(recv), (len(recv) - 1) / span_s


def compare_layouts(work: Path, n: int, iterations: int, layouts: list[str],
                    repeats: int) -> None:
    """Record the same workloads once per layout, interleaved, ``repeats`` times."""
    import statistics

    for label, rec in (("sim (planar)", lambda lay, k: record_sim(work, n, iterations, lay,
                                                                   f"sim-{lay}-{k}")),
                       ("small (3-D)", lambda lay, k: record_3d(work, n, 60, lay,
                                                                 f"small-{lay}-{k}"))):
        rates: dict[str, list[float]] = {lay: [] for lay in layouts}
        sizes: dict[str, float] = {}
        for k in range(repeats):
            for lay in layouts:
                _, per, rate = acked_rate(rec(lay, k))
                rates[lay].append(rate)
                sizes[lay] = per
        print(f"\n{label}: acknowledged inputs/s (median of {repeats}, [min-max]) and size")
        base = sizes[layouts[0]]
        for lay in layouts:
            r = rates[lay]
            print(f"  {lay:<13} {statistics.median(r):7.0f} [{min(r):.0f}-{max(r):.0f}] "
                  f"{sizes[lay] / 1e3:6.1f} kB/input ({sizes[lay] / base - 1:+.1%} vs "
                  f"{layouts[0]})")


def recorder_cpu(work: Path, n: int, layouts: list[str], repeats: int) -> None:
    """CPU time of ``Recorder.input`` per input, in-process (no server, no network), on 3-D
    updates and on planar ones (z, qx, qy zero), per layout."""
    import statistics

    from mcsm import StochasticMap
    from mcsm.core.quat import qexp
    from mcsm.log.writer import Recorder
    from mcsm.map.state import MapState

    rng = np.random.default_rng(11)

    def sample(planar: bool) -> np.ndarray:
        x = np.empty((n, 7))
        x[:, :3] = [1.0, 0.0, 0.0] + 0.05 * rng.standard_normal((n, 3))
        w = 0.01 * rng.standard_normal((n, 3))
        if planar:
            x[:, 2] = 0.0
            w[:, :2] = 0.0
        x[:, 3:] = qexp(w)
        return x

    print(f"\nRecorder.input CPU per input (N = {n}, in-process, median of {repeats} x 300)")
    for planar in (False, True):
        payloads = [wire.encode_update(f"i{i}", f"p{i}", f"p{i + 1}", sample(planar))
                    for i in range(300)]
        cpu: dict[str, list[float]] = {lay: [] for lay in layouts}
        for k in range(repeats):
            for lay in layouts:
                rec = Recorder(work / f"cpu-{lay}-{planar}-{k}.mcap", layout=lay)
                rec.config(MapState("default", StochasticMap(n)), 100)
                t0 = time.process_time()
                for i, pl in enumerate(payloads):
                    rec.input("update", "default", i + 1, time.time_ns(), "s", f"i{i}", pl)
                cpu[lay].append(1e6 * (time.process_time() - t0) / len(payloads))
                rec.close()
        print(f"  {'planar' if planar else '3-D':<7}" + "".join(
            f"  {lay} {statistics.median(v):.0f} us" for lay, v in cpu.items()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0] if __doc__ else None)
    p.add_argument("files", nargs="*", type=Path)
    p.add_argument("--samples", type=int, default=1000)
    p.add_argument("--iterations", type=int, default=120, help="sim iterations")
    p.add_argument("--layouts", default="",
                   help="also record the workloads once per layout (e.g. "
                        "flat,indexed,indexed-lz4,indexed-zstd) and compare throughput/size")
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    if args.files:
        for f in args.files:
            measure(f)
        return
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        measure(record_sim(work, args.samples, args.iterations))
        measure(record_3d(work, args.samples, 60))
        if args.layouts:
            recorder_cpu(work, args.samples, [x for x in args.layouts.split(",") if x],
                         args.repeats)
            compare_layouts(work, args.samples, args.iterations,
                            [x for x in args.layouts.split(",") if x], args.repeats)


if __name__ == "__main__":
    main()
