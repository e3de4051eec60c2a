"""Acknowledged updates through a Zenoh router: 1, 2 and 4 server processes, one map each.

For each K: ``mcsm router`` and K ``mcsm serve --connect`` processes (map ``m0`` ... ``mK-1``,
N samples), then K client processes, one per map, each streaming ``--updates`` acknowledged
updates through the router (odometry, a loop closure every 5th); every update is recorded and
flushed before its ack. Prints the total acknowledged updates/s and the ack latency p50/p99,
and the same for one server reached directly (no router) as the baseline. All on 127.0.0.1;
the machine has 2 cores, so beyond 2 busy processes they share them.

Run: ``.venv/bin/python benchmarks/fleet_throughput.py [--samples 1000] [--updates 300]``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import time

import numpy as np
from mcsm_client.process import McsmProcess, loopback_endpoint


def start(args: list[str], word: str, cwd: str) -> McsmProcess:
    return McsmProcess(args, ready=word, cwd=cwd).start()


def client(endpoint: str, map_name: str, n: int, updates: int, seed: int,
           out: mp.Queue) -> None:  # type: ignore[type-arg]
    from mcsm_client.client import MapClient
    from mcsm_client.sampling import sample_planar

    rng = np.random.default_rng(seed)
    lat = []
    cov = np.diag([1e-4, 1e-4, 1e-5])
    with MapClient(map=map_name, connect=endpoint, timeout_s=60.0) as c:
        c.info()
        t0 = time.perf_counter()
        k = 0
        for i in range(updates):
            if i % 5 == 4 and k > 3:
                x = sample_planar([float(k), 0.0, 0.0], cov, n_samples=n, rng=rng)
                a, b = "p0", f"p{k}"
            else:
                x = sample_planar([1.0, 0.0, 0.0], cov, n_samples=n, rng=rng)
                a, b = f"p{k}", f"p{k + 1}"
                k += 1
            t = time.perf_counter()
            c.update(a, b, x)
            lat.append(time.perf_counter() - t)
        out.put((time.perf_counter() - t0, lat))


def run(k_servers: int, n: int, updates: int, routed: bool) -> tuple[float, float, float]:
    with tempfile.TemporaryDirectory() as tmp:
        procs: list[McsmProcess] = []
        try:
            if routed:
                ep = loopback_endpoint()
                procs.append(start(["router", "--listen", ep], "routing on", tmp))
                for j in range(k_servers):
                    procs.append(start(["serve", "--connect", ep, "--map", f"m{j}",
                                        "--samples", str(n), "--record", f"{tmp}/m{j}.mcap",
                                        "--log-level", "WARNING"], "listening on", tmp))
            else:
                ep = loopback_endpoint()
                procs.append(start(["serve", "--listen", ep, "--map", "m0", "--samples",
                                    str(n), "--record", f"{tmp}/m0.mcap", "--log-level",
                                    "WARNING"], "listening on", tmp))
            q: mp.Queue = mp.Queue()  # type: ignore[type-arg]
            clients = [mp.Process(target=client, args=(ep, f"m{j}", n, updates, 7 + j, q))
                       for j in range(k_servers)]
            t0 = time.perf_counter()
            for p in clients:
                p.start()
            results = [q.get(timeout=600) for _ in clients]
            wall = time.perf_counter() - t0
            for p in clients:
                p.join(timeout=60)
        finally:
            for p_ in procs[::-1]:
                p_.stop(timeout_s=30)
    lat = np.concatenate([r[1] for r in results])
    busy = max(r[0] for r in results)
    del wall
    return k_servers * updates / busy, 1e3 * float(np.median(lat)), \
        1e3 * float(np.percentile(lat, 99))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--updates", type=int, default=300)
    a = ap.parse_args()
    print(f"N = {a.samples}, {a.updates} acknowledged updates per map, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"{'setup':34s} {'updates/s':>10s} {'p50 ms':>8s} {'p99 ms':>8s}")
    rows = [("1 server, direct (no router)", 1, False)] + [
        (f"{k} server(s) behind one router", k, True) for k in (1, 2, 4)]
    for label, k, routed in rows:
        rate, p50, p99 = run(k, a.samples, a.updates, routed)
        print(f"{label:34s} {rate:10.0f} {p50:8.2f} {p99:8.2f}", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
