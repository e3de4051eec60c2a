"""Soak: a real ``mcsm serve`` fed a bounded map for a long time; its resident memory (RSS)
every 10,000 operations (prints figures, no pass/fail).

Run by hand (about 10 minutes and 6 GB of recording at N = 1000; the recording is deleted
at the end unless ``--keep``)::

    nice -n 10 .venv/bin/python benchmarks/soak_memory.py [--ops 100000] [--samples 1000]
        [--every 10000] [--window 60] [--split-size 1G] [--out benchmarks/results/soak.txt]
        [-- SERVE FLAGS...]

The map is a robot's bounded map with a 60-frame window: per step one odometry update (a new
pose frame), one re-observation of one of 5 landmarks (a loop closure) every third step, and
the removal of the pose 60 steps back, each an acknowledged, recorded operation with its own
request id. Requests are pipelined (``--inflight`` in flight) so that the server, not the
round trip, sets the pace. The server runs with its default options (a disk snapshot every
1000 operations, request ids remembered 600 s and at most 100,000 of them, a 256 MiB retract
window), unless flags after ``--`` say otherwise.

Every ``--every`` operations the line ``ops, RSS, peak RSS, ops/s, recording size`` is
printed; at the end the change of RSS from the first line (10,000 operations) to the last,
in MB and in % of the first.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mcsm import wire
from mcsm_client.client import MapClient
from mcsm_client.process import ServerProcess
from mcsm_client.sampling import pose_from_planar, sample_pose

NOISE_COV = np.diag([0.05**2] * 3 + [0.01**2] * 3)


def at(rng: np.random.Generator, n: int, x: float, y: float, yaw: float = 0.0) -> np.ndarray:
    return sample_pose(pose_from_planar([x, y, yaw]), NOISE_COV, n_samples=n, rng=rng)


def status(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, kB."""
    out = {}
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            key = line.split(":")[0]
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(line.split()[1])
    return out


def requests(rng: np.random.Generator, n: int, window: int):  # type: ignore[no-untyped-def]
    """Endless (key, payload) of the bounded map: odometry, closures, removes."""
    pool = [at(rng, n, 0.2, 0.0, 0.01) for _ in range(16)]  # sample sets reused (cheap)
    obs = [at(rng, n, 0.5, 4.0) for _ in range(16)]
    k = 0
    for j in range(1, 5):
        yield "update", wire.encode_update(f"s{j}", "lm0", f"lm{j}", at(rng, n, float(j), 2.0))
    yield "update", wire.encode_update("s0", "lm0", "pose0", at(rng, n, 0.0, -2.0))
    i = 0
    while True:
        yield "update", wire.encode_update(f"o{i}", f"pose{i}", f"pose{i + 1}", pool[k % 16])
        k += 1
        if i % 3 == 2:
            yield "update", wire.encode_update(f"c{i}", f"pose{i + 1}", f"lm{i % 5}",
                                               obs[k % 16])
        if i >= window - 1:
            yield "remove", wire.encode_remove(f"r{i}", f"pose{i - window + 1}")
        i += 1


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ops", type=int, default=100_000)
    p.add_argument("--samples", type=int, default=1000)
    p.add_argument("--every", type=int, default=10_000)
    p.add_argument("--window", type=int, default=60)
    p.add_argument("--inflight", type=int, default=16)
    p.add_argument("--dir", type=Path, default=None, help="where the recording goes")
    p.add_argument("--keep", action="store_true", help="keep the recording")
    p.add_argument("--out", type=Path, default=None, help="also append the lines here")
    p.add_argument("serve", nargs="*", help="more mcsm serve flags (after --)")
    args = p.parse_args()
    work = Path(tempfile.mkdtemp(prefix="mcsm-soak-", dir=args.dir))
    lines: list[str] = []

    def say(text: str) -> None:
        print(text, flush=True)
        lines.append(text)

    srv = ServerProcess(work / "soak.mcap", n_samples=args.samples,
                        extra_args=("--log-level", "WARNING", *args.serve)).start()
    say(f"# soak: N = {args.samples}, bounded map of {args.window} poses + 5 landmarks, "
        f"{args.ops} operations, serve flags {' '.join(args.serve) or '(defaults)'}")
    say(f"{'ops':>8} {'RSS MB':>8} {'peak MB':>8} {'ops/s':>7} {'recording MB':>13}")
    rng = np.random.default_rng(20261126)
    gen = requests(rng, args.samples, args.window)
    first = last = 0.0
    done = 0
    t0 = time.monotonic()
    try:
        with MapClient(connect=srv.endpoint, timeout_s=60) as c:
            keys = {"update": c.keys.update, "remove": c.keys.remove}
            pending: list = []  # type: ignore[type-arg]
            while done < args.ops:
                while len(pending) < args.inflight:
                    key, payload = next(gen)
                    pending.append(c.session.get(keys[key], payload=payload, timeout=60))
                replies = list(pending.pop(0))
                if len(replies) != 1 or replies[0].ok is None:
                    err = (wire.decode_error(replies[0].err.payload.to_bytes())
                           if replies else "no reply")
                    raise SystemExit(f"operation {done + 1} failed: {err}")
                done += 1
                if done % args.every == 0:
                    st = status(srv.proc.pid)  # type: ignore[union-attr]
                    rss = st["VmRSS"] / 1024
                    first = first or rss
                    last = rss
                    size = sum(f.stat().st_size for f in work.glob("*.mcap")) / 1e6
                    say(f"{done:>8} {rss:>8.1f} {st['VmHWM'] / 1024:>8.1f} "
                        f"{done / (time.monotonic() - t0):>7.0f} {size:>13.0f}")
            for h in pending:
                list(h)
    finally:
        srv.stop()
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    if first:
        say(f"# RSS from {args.every} to {done} operations: {first:.1f} -> {last:.1f} MB "
            f"({last - first:+.1f} MB, {100 * (last - first) / first:+.1f} %)")
    if args.out is not None:
        with open(args.out, "a") as f:
            f.write("\n".join(lines) + "\n\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
