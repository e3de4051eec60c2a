"""What a hot standby costs and how fast it takes over (issue 18).

Part 1, ack latency: ``mcsm router`` plus a primary serving map ``m`` (N samples), with no
standby, with one asynchronous standby (``--standby-of m``), and with one synchronous standby
(``--sync-standbys 1``); one client streams ``--updates`` acknowledged updates (odometry,
a loop closure every 5th) through the router. Prints updates/s and ack latency p50/p99.

Part 2, takeover: a primary with ``--sync-standbys 1`` and two standbys; a client streams
updates; the primary is SIGKILLed ``--kills`` times at random points (the killed one comes
back as a new standby each time). For each kill: the time from the primary's token going away
to the standby declaring the map (from the new primary's log), and the time from SIGKILL to
the client's next acknowledged update (what a robot sees); before each kill both standbys
hold the stream (lag <= 2), and the time a returning standby took to get there (started,
caught up from the new primary) is printed too. Prints median and worst.

All processes on 127.0.0.1; the machine has 2 cores shared by every process here.
Run: ``.venv/bin/python benchmarks/standby.py [--samples 1000] [--updates 300] [--kills 5]``.
"""

from __future__ import annotations

import argparse
import re
import signal
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from mcsm_client.process import McsmProcess, ServerProcess, loopback_endpoint
from mcsm_client.sampling import sample_planar


def _router() -> tuple[McsmProcess, str]:
    ep = loopback_endpoint()
    return McsmProcess(["router", "--listen", ep], ready="routing on").start(), ep


def _server(run: Path, name: str, n: int, *args: str) -> ServerProcess:
    """``mcsm serve`` joined to the router (``--connect`` in ``args``), log beside its file."""
    return ServerProcess(run / f"{name}.mcap", n_samples=n, extra_args=args, endpoint="-",
                         listen=False).start()


def _odometry(rng: np.random.Generator, n: int, x: float, sigma: float) -> np.ndarray:
    cov = np.diag([sigma**2, sigma**2, (0.02 * sigma) ** 2])
    return sample_planar([x, 0.0, 0.0], cov, n_samples=n, rng=rng)


def _stream(ep: str, n: int, updates: int, seed: int,
            stamps: list[tuple[float, str]] | None = None,
            stop: threading.Event | None = None) -> list[float]:
    from mcsm_client.client import MapClient

    rng = np.random.default_rng(seed)
    lat: list[float] = []
    with MapClient(map="m", connect=ep, timeout_s=60.0) as c:
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
    for label, sync, standby in (("primary alone", 0, False),
                                 ("+ 1 asynchronous standby", 0, True),
                                 ("+ 1 synchronous standby", 1, True)):
        run = tmp / label.replace(" ", "_").replace("+", "")
        run.mkdir()
        router, ep = _router()
        procs: list[ServerProcess] = []
        try:
            procs.append(_server(run, "p", n, "--map", "m", "--connect", ep,
                                 "--sync-standbys", str(sync)))
            if standby:
                procs.append(_server(run, "s", n, "--standby-of", "m", "--connect", ep))
                time.sleep(1.0)  # its token reaches the primary
            t0 = time.perf_counter()
            lat = _stream(ep, n, updates, 1)
            dt = time.perf_counter() - t0
        finally:
            for d in reversed(procs):
                d.stop()
            router.stop()
        ms = np.array(lat) * 1e3
        print(f"{label:34s} {len(lat) / dt:10.0f} {np.percentile(ms, 50):8.2f} "
              f"{np.percentile(ms, 99):8.2f}", flush=True)


def part2(n: int, kills: int, tmp: Path, seed: int) -> None:
    run = tmp / "takeover"
    run.mkdir()
    router, ep = _router()
    rng = np.random.default_rng(seed)
    procs: dict[str, ServerProcess] = {}
    token_to_primary: list[float] = []
    kill_to_ack: list[float] = []
    try:
        procs["s0"] = _server(run, "s0", n, "--map", "m", "--connect", ep,
                              "--sync-standbys", "1")
        for name in ("s1", "s2"):
            procs[name] = _server(run, name, n, "--standby-of", "m", "--connect", ep)
        time.sleep(1.0)
        primary = "s0"
        stamps: list[tuple[float, str]] = []
        stop = threading.Event()
        th = threading.Thread(target=_stream, args=(ep, n, 1_000_000, 2, stamps, stop),
                              daemon=True)
        th.start()
        from mcsm_client.client import MapClient

        watcher = MapClient(map="m", connect=ep, timeout_s=60.0)
        catch_up: list[float] = []
        t_back = time.monotonic()
        for k in range(kills):
            # both standbys hold the stream (lag <= 2) before the kill: the figure is the
            # takeover, not a returning standby's catch-up (timed separately)
            t_wait = time.monotonic()
            while time.monotonic() - t_wait < 120:
                info = watcher.info()
                if len(info.standbys) == 2 and \
                        all(info.seq - s <= 2 for s in info.standbys.values()):
                    break
                time.sleep(0.05)
            if k:
                catch_up.append(time.monotonic() - t_back)
            time.sleep(float(rng.uniform(0.5, 1.5)))
            before = len(stamps)
            old_id = watcher.info().server_id
            t_kill = time.monotonic()
            procs[primary].stop(signal.SIGKILL)
            deadline = time.monotonic() + 60

            new: list[float] = []  # acks of the new primary (not replies in flight)
            while time.monotonic() < deadline and not new:
                time.sleep(0.002)
                new = [t for t, srv in stamps[before:] if t > t_kill and srv != old_id]
            kill_to_ack.append(min(new) - t_kill)
            # who took over, and how long after the token went away
            took = None
            deadline = time.monotonic() + 10
            while took is None and time.monotonic() < deadline:
                for name, d in procs.items():
                    if name == primary or d.returncode is not None:
                        continue  # each live server takes over at most once
                    m = re.search(r"took over as primary at seq \d+ \(([\d.]+) s",
                                  d.log_text())
                    if m:
                        took = (name, float(m.group(1)))
                time.sleep(0.01)
            assert took is not None, "no takeover logged"
            new_primary, t_tok = took
            token_to_primary.append(t_tok)
            back = f"s{len(procs)}"
            t_back = time.monotonic()
            procs[back] = _server(run, back, n, "--standby-of", "m", "--connect", ep)
            primary = new_primary
            print(f"kill {k + 1}: token gone -> new primary {t_tok * 1e3:.1f} ms, "
                  f"SIGKILL -> next ack {kill_to_ack[-1] * 1e3:.1f} ms", flush=True)
        stop.set()
        th.join(timeout=60)
        watcher.close()
    finally:
        for d in procs.values():
            d.stop(signal.SIGKILL)
        router.stop()
    print(f"takeover over {kills} kills (primary + 2 standbys, --sync-standbys 1, N = {n}):")
    for label, xs in (("token gone -> new primary", token_to_primary),
                      ("SIGKILL -> client's next ack", kill_to_ack),
                      ("returning standby caught up", catch_up)):
        if not xs:
            continue  # one kill: no standby came back before a next kill
        print(f"  {label:30s} median {statistics.median(xs) * 1e3:7.1f} ms, "
              f"worst {max(xs) * 1e3:7.1f} ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=1000)
    ap.add_argument("--updates", type=int, default=300)
    ap.add_argument("--kills", type=int, default=5)
    ap.add_argument("--seed", type=int, default=20261123)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        part1(args.samples, args.updates, Path(d))
        part2(args.samples, args.kills, Path(d), args.seed)


if __name__ == "__main__":
    main()
