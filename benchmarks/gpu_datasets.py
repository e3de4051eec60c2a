"""The dataset section of ``gpu_check.py``: Victoria Park and sphere2500 streamed, with the
same samples, into a CPU map and a device map, each in its own process, all four at once.

Each worker prints one JSON line per checkpoint (every ``--every`` updates: the count, the
map's digest, a hash of every update's outcome so far) and one at the end, flushed, so a
worker stopped by the time limit still leaves what it did. The section compares the CPU
worker's checkpoints with the device worker's, one by one, and the final digests where both
reached the end of the file. The device workers share the GPU, so their seconds are not a
timing.

Run as a worker (gpu_check starts these)::

    python benchmarks/gpu_datasets.py --name victoria_park.txt --path FILE --samples 100 \\
        --device cpu|cuda|emulate --every 500 --deadline EPOCH_SECONDS
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
NAMES = ("victoria_park.txt", "sphere2500.txt")
SEED = 20261206


def feed(name: str, path: Any, target: Any, n: int, max_constraints: int | None) -> None:
    """Stream one dataset into ``target`` (a map), drawing every sample from one seeded
    generator: the same samples for every map fed this way."""
    import numpy as np

    rng = np.random.default_rng(SEED)
    if name.startswith("sphere"):
        from mcsm_client.sampling import sample_pose

        from experiments.pose_graph import read_toro3d

        g = read_toro3d(Path(path))
        todo = list(zip(g.edges, g.measurements, g.covariances, strict=True))
        for (i, j), z, cov in todo[:max_constraints]:
            target.update(f"x{i}", f"x{j}", sample_pose(z, cov, n_samples=n, rng=rng,
                                                        translation_frame="body"))
        return
    from mcsm_client.datasets import read_dataset
    from mcsm_client.players import play

    play(read_dataset(path), target, rng=rng, n_samples=n, max_constraints=max_constraints)


def worker(name: str, path: str, n: int, device: str, every: int, deadline: float,
           max_constraints: int | None) -> None:
    """Feed one map, printing a JSON line at every checkpoint and at the end."""
    from mcsm import StochasticMap
    from mcsm.errors import McsmError

    backend: Any = device
    if device == "emulate":
        from mcsm.core.emulation import EmulatedBackend

        backend = EmulatedBackend()
    t0 = time.perf_counter()
    outcomes = hashlib.sha256()
    count = [0]

    def line(**kw: Any) -> None:
        print(json.dumps({"k": count[0], "seconds": time.perf_counter() - t0,
                          "outcomes": outcomes.hexdigest(), **kw}), flush=True)

    class Recorder(StochasticMap):
        def update(self, a: str, b: str, samples: Any, *, trusted: bool = False) -> Any:
            if time.time() > deadline:
                raise TimeoutError
            try:
                r = super().update(a, b, samples, trusted=trusted)
                outcomes.update(f"{r if isinstance(r, str) else type(r).__name__};".encode())
            except McsmError as exc:
                outcomes.update(f"!{type(exc).__name__};".encode())
                raise
            finally:
                count[0] += 1
            if count[0] % every == 0:
                line(digest=self.state_digest())
            return r

    m = Recorder(n, device=backend)
    try:
        feed(name, path, m, n, max_constraints)
    except TimeoutError:
        line(stopped=True, frames=len(m.frames()))
        return
    line(final=True, digest=m.state_digest(), frames=len(m.frames()))


def _read(proc: subprocess.Popen[str]) -> list[dict[str, Any]]:
    out = []
    for raw in (proc.stdout.read() if proc.stdout else "").splitlines():
        try:
            out.append(json.loads(raw))
        except ValueError:
            continue
    return out


def compare(cpu: list[dict[str, Any]], dev: list[dict[str, Any]]) -> dict[str, Any]:
    """Checkpoints in common compared one by one, and the finals where both got there."""
    ck_cpu = {r["k"]: r for r in cpu if "digest" in r and not r.get("final")}
    ck_dev = {r["k"]: r for r in dev if "digest" in r and not r.get("final")}
    common = sorted(set(ck_cpu) & set(ck_dev))
    differ = [k for k in common if (ck_cpu[k]["digest"], ck_cpu[k]["outcomes"])
              != (ck_dev[k]["digest"], ck_dev[k]["outcomes"])]
    fin_cpu = next((r for r in cpu if r.get("final")), None)
    fin_dev = next((r for r in dev if r.get("final")), None)
    res: dict[str, Any] = {"checkpoints": len(common), "checkpoints_differ": differ,
                           "cpu_last": cpu[-1] if cpu else None,
                           "device_last": dev[-1] if dev else None}
    if fin_cpu and fin_dev:
        res["whole_file"] = True
        res["final_same"] = (fin_cpu["digest"], fin_cpu["outcomes"], fin_cpu["k"]) == \
            (fin_dev["digest"], fin_dev["outcomes"], fin_dev["k"])
    else:
        res["whole_file"] = False
    res["same"] = bool(common or res["whole_file"]) and not differ and \
        res.get("final_same", True)
    return res


def datasets_section(rep: Any, emulate: bool, data: Path | None, n: int, deadline: float,
                     max_constraints: int | None, every: int) -> None:
    """Start the four workers, wait for them (until ``deadline``, a ``perf_counter`` time),
    compare and report."""
    from mcsm_client.datasets import resolve_dataset_path

    rep.say(f"\n## datasets: the same samples into a CPU map and a device map (N = {n}), "
            f"each in its own process, all at once; digests compared every {every} updates")
    left = deadline - time.perf_counter()
    if left < 20:
        rep.say("skipped, out of time")
        return
    stop_at = time.time() + left
    procs: dict[tuple[str, str], subprocess.Popen[str]] = {}
    for name in NAMES:
        try:
            path = data / name if data is not None else resolve_dataset_path(f"gtsam:{name}")
        except Exception as exc:
            rep.say(f"{name}: no data ({exc}; benchmarks/results/README: --data)")
            continue
        if not Path(path).exists():
            rep.say(f"{name}: not found at {path} (benchmarks/results/README: --data)")
            continue
        for side in ("cpu", "emulate" if emulate else "cuda"):
            cmd = [sys.executable, str(Path(__file__).resolve()), "--name", name,
                   "--path", str(path), "--samples", str(n), "--device", side,
                   "--every", str(every), "--deadline", repr(stop_at)]
            if max_constraints is not None:
                cmd += ["--max-constraints", str(max_constraints)]
            procs[(name, side)] = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True,
                                                   env={**os.environ, "OMP_NUM_THREADS": "1"})
    for p in procs.values():
        try:  # a worker stops at the deadline by itself; the margin is for its last digest
            p.wait(timeout=max(1.0, stop_at - time.time()) + 60)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()
    lines = {key: _read(p) for key, p in procs.items()}
    out = {}
    for name in NAMES:
        sides = [k for k in lines if k[0] == name]
        if len(sides) != 2:
            continue
        cpu, dev = lines[sides[0]], lines[sides[1]]
        res = compare(cpu, dev)
        out[name] = res
        last_c, last_d = res["cpu_last"] or {}, res["device_last"] or {}
        if res["whole_file"]:
            whole = "the whole file" if max_constraints is None else \
                f"the first {max_constraints} constraints (--max-constraints)"
            what = (f"{whole}: {last_d['k']} updates, {last_d.get('frames')} frames, "
                    f"digest {last_d['digest'][:16]}")
        else:
            what = (f"stopped by the time limit: CPU map at update {last_c.get('k')}, device "
                    f"map at {last_d.get('k')}")
        verdict = "same digest" if res["same"] else "DIFFERENT"
        bad = res["checkpoints_differ"]
        rep.say(f"{verdict}  {name}: {what}; {res['checkpoints']} checkpoints compared"
                f"{', differ at ' + str(bad[:5]) if bad else ''}"
                f"; CPU map {last_c.get('seconds', 0):.1f} s, device map "
                f"{last_d.get('seconds', 0):.1f} s (two device maps share the GPU)")
        rcs = {side: procs[(name, side)].returncode for side in ("cpu", sides[1][1])}
        if any(rcs.values()):
            rep.say(f"  worker exit codes {rcs}")
        if not res["same"]:
            rep.failed.append(f"dataset {name}")
    rep.data["datasets"] = out


def main(argv: list[str] | None = None) -> int:
    for p in (ROOT, ROOT / "clients"):
        if str(p) not in sys.path:
            sys.path.insert(0, str(p))
    ap = argparse.ArgumentParser(description="one dataset worker of gpu_check.py")
    ap.add_argument("--name", required=True, choices=NAMES)
    ap.add_argument("--path", required=True)
    ap.add_argument("--samples", type=int, required=True)
    ap.add_argument("--device", required=True, choices=("cpu", "cuda", "emulate"))
    ap.add_argument("--every", type=int, default=500)
    ap.add_argument("--deadline", type=float, required=True, help="epoch seconds")
    ap.add_argument("--max-constraints", type=int, default=None)
    a = ap.parse_args(argv)
    worker(a.name, a.path, a.samples, a.device, max(1, a.every), a.deadline,
           a.max_constraints)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
