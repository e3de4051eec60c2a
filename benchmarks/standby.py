"""What replication on NATS JetStream costs and how fast a standby takes over (issue 23).

Part 1, ack latency: ``mcsm router`` plus a primary serving map ``m`` (N samples): alone (no
``--nats``), with its log in a three-node JetStream cluster (``--nats``, R = 3, no standby),
and with one standby (``--standby-of m``) as well; one client streams ``--updates``
acknowledged updates (odometry, a loop closure every 5th) through the router. Prints
updates/s and ack latency p50/p99.

Part 2, takeover: a primary and two standbys on the log; a client streams updates; the
primary is SIGKILLed ``--kills`` times at random points (the killed one comes back as a new
standby each time). For each kill: the time from SIGKILL to the client's next acknowledged
update (what a robot sees: the lease's TTL, ``--lease-ttl``, 2 s by default, then the
standby applying the log's tail and declaring the map); before each kill both standbys hold
the log (lag <= 2). Then one
graceful stop (SIGINT: the lease is released): SIGINT -> next ack. Prints median and worst.

All processes on 127.0.0.1; the machine has 2 cores shared by every process here.
Part 3 (``--steady S``), the lease's false alarms: a primary, two standbys and two clients
streaming for S seconds with no fault; prints the acks, the changes of primary and the
updates refused ``NotReplicated`` (each one a stall of the primary longer than 0.75 TTL).

Run: ``.venv/bin/python benchmarks/standby.py [--samples 1000] [--updates 300] [--kills 5]
[--lease-ttl 2] [--takeover-only] [--steady S]``.
"""

from __future__ import annotations

import argparse
import signal
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from mcsm_client.process import McsmProcess, ServerProcess, loopback_endpoint
from mcsm_client.sampling import sample_planar

NATS: list[str] = []
LEASE: list[str] = []  # --lease-ttl S for every server (the first server sets the bucket's)


def _router() -> tuple[McsmProcess, str]:
    ep = loopback_endpoint()
    return McsmProcess(["router", "--listen", ep], ready="routing on").start(), ep


def _server(run: Path, name: str, n: int, *args: str) -> ServerProcess:
    """``mcsm serve`` joined to the router (``--connect`` in ``args``), log beside its file."""
    extra = [*args, *LEASE] if "--nats" in args else list(args)
    return ServerProcess(run / f"{name}.mcap", n_samples=n, extra_args=extra, endpoint="-",
                         listen=False).start()


def _odometry(rng: np.random.Generator, n: int, x: float, sigma: float) -> np.ndarray:
    cov = np.diag([sigma**2, sigma**2, (0.02 * sigma) ** 2])
    return sample_planar([x, 0.0, 0.0], cov, n_samples=n, rng=rng)


def _stream(ep: str, n: int, updates: int, seed: int,
            stamps: list[tuple[float, str]] | None = None,
            stop: threading.Event | None = None, prefix: str = "mcsm") -> list[float]:
    from mcsm_client.client import MapClient

    rng = np.random.default_rng(seed)
    lat: list[float] = []
    with MapClient(map="m", connect=ep, timeout_s=60.0, prefix=prefix) as c:
        c.info()
        for k in range(updates):
            if stop is not None and stop.is_set():
                break
            todo = [(f"p{k}", f"p{k + 1}", _odometry(rng, n, 1.0, 0.05))]
            if k % 5 == 4 and k >= 5:  # a loop closure back four steps
                todo.append((f"p{k + 1}", f"p{k - 3}", _odometry(rng, n, -4.0, 0.2)))
            for a, b, t in todo:
                t0 = time.perf_counter()
                ack = c.update(a, b, t)
                lat.append(time.perf_counter() - t0)
                if stamps is not None:
                    stamps.append((time.monotonic(), ack.server))
    return lat


def part1(n: int, updates: int, tmp: Path) -> None:
    print(f"ack latency, one client, N = {n}, {updates} updates, through one router")
    print(f"{'setup':34s} {'updates/s':>10s} {'p50 ms':>8s} {'p99 ms':>8s}")
    for label, nats, standby in (("primary alone (no log)", False, False),
                                 ("log R = 3, no standby", True, False),
                                 ("log R = 3 + 1 standby", True, True)):
        run = tmp / label.replace(" ", "_").replace("+", "")
        run.mkdir()
        router, ep = _router()
        procs: list[ServerProcess] = []
        try:
            log = ["--nats", ",".join(NATS)] if nats else []
            procs.append(_server(run, "p", n, "--map", f"m{len(label)}" if False else "m",
                                 "--connect", ep, *log, "--prefix", f"b{len(label)}"))
            if standby:
                procs.append(_server(run, "s", n, "--standby-of", "m", "--connect", ep, *log,
                                     "--prefix", f"b{len(label)}"))
                time.sleep(1.0)  # its token reaches the primary
            t0 = time.perf_counter()
            lat = _stream(ep, n, updates, 1, prefix=f"b{len(label)}")
            dt = time.perf_counter() - t0
        finally:
            for d in reversed(procs):
                d.stop()
            router.stop()
        ms = np.array(lat) * 1e3
        print(f"{label:34s} {len(lat) / dt:10.0f} {np.percentile(ms, 50):8.2f} "
              f"{np.percentile(ms, 99):8.2f}", flush=True)


def part2(n: int, kills: int, tmp: Path, seed: int, ttl: float) -> None:
    run = tmp / "takeover"
    run.mkdir()
    router, ep = _router()
    rng = np.random.default_rng(seed)
    log = ["--nats", ",".join(NATS), "--prefix", "takeover"]
    procs: dict[str, ServerProcess] = {}
    kill_to_ack: list[float] = []
    stop_to_ack: list[float] = []
    try:
        procs["s0"] = _server(run, "s0", n, "--map", "m", "--connect", ep, *log)
        for name in ("s1", "s2"):
            procs[name] = _server(run, name, n, "--standby-of", "m", "--connect", ep, *log)
        primary = "s0"
        stamps: list[tuple[float, str]] = []
        stop = threading.Event()
        th = threading.Thread(target=_stream, args=(ep, n, 1_000_000, 2, stamps, stop,
                                                    "takeover"), daemon=True)
        th.start()
        from mcsm_client.client import MapClient

        watcher = MapClient(map="m", connect=ep, timeout_s=60.0, prefix="takeover")
        for k in range(kills + 1):
            t_wait = time.monotonic()
            while time.monotonic() - t_wait < 120:  # both standbys hold the log
                info = watcher.info()
                if len(info.standbys) == 2 and \
                        all(info.seq - s <= 2 for s in info.standbys.values()):
                    break
                time.sleep(0.05)
            time.sleep(float(rng.uniform(0.5, 1.5)))
            before = len(stamps)
            old_id = watcher.info().server_id
            took = {name: d.log_text().count("took over") for name, d in procs.items()}
            t_kill = time.monotonic()
            graceful = k == kills
            procs[primary].stop(signal.SIGINT if graceful else signal.SIGKILL)
            deadline = time.monotonic() + 60
            new: list[float] = []  # acks of the new primary (not replies in flight)
            while time.monotonic() < deadline and not new:
                time.sleep(0.002)
                new = [t for t, srv in stamps[before:] if t > t_kill and srv != old_id]
            (stop_to_ack if graceful else kill_to_ack).append(min(new) - t_kill)
            t_end = time.monotonic() + 10
            new_primary = ""
            while not new_primary and time.monotonic() < t_end:
                new_primary = next((name for name, d in procs.items() if name != primary and
                                    d.log_text().count("took over") > took[name]), "")
                time.sleep(0.01)
            assert new_primary, "no takeover logged"
            back = f"s{len(procs)}"
            procs[back] = _server(run, back, n, "--standby-of", "m", "--connect", ep, *log)
            primary = new_primary
            print(f"{'stop' if graceful else 'kill'} {k + 1}: -> next ack "
                  f"{(stop_to_ack if graceful else kill_to_ack)[-1] * 1e3:.0f} ms", flush=True)
        stop.set()
        th.join(timeout=60)
        watcher.close()
    finally:
        for d in procs.values():
            d.stop(signal.SIGKILL)
        router.stop()
    print(f"takeover over {kills} kills (primary + 2 standbys, log R = 3, lease TTL {ttl:g} s, "
          f"N = {n}):")
    for label, xs in (("SIGKILL -> client's next ack", kill_to_ack),
                      ("SIGINT -> client's next ack", stop_to_ack)):
        if xs:
            print(f"  {label:30s} median {statistics.median(xs) * 1e3:7.1f} ms, "
                  f"worst {max(xs) * 1e3:7.1f} ms")


def part3(n: int, seconds: float, tmp: Path, ttl: float) -> None:
    """No fault: a primary, two standbys and two clients streaming for ``seconds``; every
    change of primary and every ``NotReplicated`` is then a false alarm of the lease (the
    primary could not renew in time under the machine's load)."""
    run = tmp / "steady"
    run.mkdir()
    router, ep = _router()
    log = ["--nats", ",".join(NATS), "--prefix", "steady"]
    procs: list[ServerProcess] = []
    stop = threading.Event()
    counts: list[int] = []
    try:
        procs.append(_server(run, "p", n, "--map", "m", "--connect", ep, *log))
        procs += [_server(run, f"s{k}", n, "--standby-of", "m", "--connect", ep, *log)
                  for k in (1, 2)]
        time.sleep(1.0)

        def client(seed: int) -> None:
            stamps: list[tuple[float, str]] = []
            _stream(ep, n, 1_000_000, seed, stamps, stop, "steady")
            counts.append(len(stamps))

        threads = [threading.Thread(target=client, args=(10 + k,), daemon=True)
                   for k in range(2)]
        for th in threads:
            th.start()
        time.sleep(seconds)
        stop.set()
        for th in threads:
            th.join(timeout=120)
    finally:
        for d in procs:
            d.stop()
        router.stop()
    text = "".join(d.log_text() for d in procs)
    print(f"no fault, {seconds:g} s, primary + 2 standbys, 2 clients, lease TTL {ttl:g} s, "
          f"N = {n}: {sum(counts)} acks, {text.count('took over as primary')} takeovers, "
          f"{text.count('not serving it any more')} primaries stopped, "
          f"{text.count('NotReplicated')} updates refused NotReplicated", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--updates", type=int, default=300)
    ap.add_argument("--kills", type=int, default=5)
    ap.add_argument("--seed", type=int, default=20261123)
    ap.add_argument("--lease-ttl", type=float, default=2.0,
                    help="every server's --lease-ttl (default 2, mcsm serve's default)")
    ap.add_argument("--takeover-only", action="store_true", help="part 2 only")
    ap.add_argument("--steady", type=float, default=0.0, metavar="S",
                    help="then S seconds of two clients streaming with no fault, counting "
                         "the lease's false alarms (0: skip)")
    args = ap.parse_args()
    from mcsm.serve.natsrun import NatsCluster

    LEASE[:] = ["--lease-ttl", f"{args.lease_ttl:g}"]
    with tempfile.TemporaryDirectory() as d:
        with NatsCluster(Path(d) / "nats") as cluster:
            NATS[:] = cluster.urls
            if not args.takeover_only:
                part1(args.samples, args.updates, Path(d))
            if args.kills > 0:
                part2(args.samples, args.kills, Path(d), args.seed, args.lease_ttl)
            if args.steady > 0:
                part3(args.samples, args.steady, Path(d), args.lease_ttl)


if __name__ == "__main__":
    main()
