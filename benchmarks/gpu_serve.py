"""The Zenoh section of ``benchmarks/gpu_check.py`` (issue 25's "``mcsm serve --device cuda``
acknowledged updates on a 100,000-frame map: >= 200/s over Zenoh").

What it runs, all through the real service:

1. ``python -m mcsm.cli serve --device cuda`` (the ``mcsm serve`` command, a subprocess, on a
   free loopback port, recording on) with the periodic whole-map work off:
   ``--checkpoint-every``, ``--snapshot-every`` 10^9 and ``--disk-snapshot-every 0``. Each of
   those copies the whole map off the device (5.6 GB at M = 100,000, N = 1000); what one such
   operation costs is measured separately (the last step).
2. The map is built over Zenoh by acknowledged requests only: one real chain component of up
   to 128 frames (built in this process on the CPU, then exported) is imported again and
   again under new frame names (each import at most 7.2 MB, under the wire's 8 MB payload
   limit; several in flight from ``--serve-clients`` clients), then the blocks are joined
   in order into one component by one update each (case I joins). No snapshot is restored:
   a recording's snapshot record is limited to 1 GiB (about 19,000 frames at N = 1000).
3. Acknowledged loop closures between a frame of the first block and one of the last (each
   moves every frame of the map) from one ``MapClient`` (one request in flight: the latency
   bound) and then from ``--serve-clients`` clients at once (the server's throughput); the
   observation is the map's own relative samples (one query), reshuffled for each update,
   so the gate accepts every one; each ack's kind is checked.
4. One ``info`` (its state digest reads and hashes the whole map): the frame count, the
   component count, the device memory the map holds, and what a whole-map operation costs.

On the emulated device (``--emulate``) the same runs with a small M and N: the CLI is started
through a two-line wrapper that makes ``--device cuda`` mean the emulated backend.
"""

from __future__ import annotations

import gc
import os
import statistics
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

#: the CLI with ``--device cuda`` meaning the emulated device (the rehearsal only)
EMULATED_CLI = ("import sys; from mcsm.core import device; "
                "from mcsm.core.emulation import EmulatedBackend; "
                "device._BACKENDS['cuda:0'] = EmulatedBackend(); "
                "from mcsm.cli import main; sys.exit(main(sys.argv[1:]))")
BIG = "1000000000"


def chain(n: int, frames: int, seed: int, threads: int = 1) -> Any:
    """A CPU map holding one real 3-D chain component ``p0 ... p{frames - 1}`` (odometry
    clouds of 0.2 m and 0.03 rad)."""
    import numpy as np
    from mcsm import StochasticMap

    from tests.helpers import random_at

    rng = np.random.default_rng(seed)
    m = StochasticMap(n, gate=None, threads=threads)
    for k in range(frames - 1):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.2,
                                                  r_sigma=0.03))
    return m


def _block_frames(n: int, most: int) -> int:
    """Frames of one import: ``most``, or fewer where N makes that many frames exceed the
    wire's payload limit."""
    from mcsm import wire

    per_frame = 7 * 8 * n + 64
    return max(2, min(most, (wire.MAX_PAYLOAD_BYTES - 64 * 1024) // per_frame))


def _server(workdir: Path, n: int, emulate: bool) -> Any:
    from mcsm_client.process import ServerProcess

    # the parent's path first (gpu_check's bootstrap puts mcsm there when it is not
    # installed), this checkout after it
    paths = [os.environ.get("PYTHONPATH", ""), str(ROOT / "clients"), str(ROOT)]
    env = {"PYTHONPATH": os.pathsep.join(p for p in paths if p)}
    srv = ServerProcess(workdir / "serve.mcap", n_samples=n, env=env, cwd=str(ROOT),
                        ready_timeout_s=120,
                        extra_args=("--device", "cuda", "--checkpoint-every", BIG,
                                    "--snapshot-every", BIG, "--disk-snapshot-every", "0",
                                    "--log-level", "WARNING"))
    if emulate:
        srv.cmd = [sys.executable, "-c", EMULATED_CLI, *srv.cmd[3:]]
    return srv


def _rate(rep: Any, label: str, clients: int, seconds: float, send: Any) -> dict[str, Any]:
    """``clients`` threads, each with its own MapClient, sending loop closures for
    ``seconds``; the acknowledged count, the rate and each call's latency."""
    lat: list[float] = []
    kinds: dict[str, int] = {}
    lock = threading.Lock()
    t_end = time.perf_counter() + seconds

    def worker(k: int) -> None:
        mine: list[float] = []
        got: dict[str, int] = {}
        i = 0
        while time.perf_counter() < t_end:
            t0 = time.perf_counter()
            kind = send(k, i)
            mine.append(time.perf_counter() - t0)
            got[kind] = got.get(kind, 0) + 1
            i += 1
        with lock:
            lat.extend(mine)
            for key, v in got.items():
                kinds[key] = kinds.get(key, 0) + v

    t0 = time.perf_counter()
    with ThreadPoolExecutor(clients) as pool:
        list(pool.map(worker, range(clients)))
    elapsed = time.perf_counter() - t0
    acked = len(lat)
    lat.sort()
    p90 = lat[min(len(lat) - 1, int(0.9 * len(lat)))] if lat else float("nan")
    row = {"label": label, "clients": clients, "acked": acked, "seconds": elapsed,
           "per_s": acked / elapsed, "latency_ms_median": 1e3 * statistics.median(lat)
           if lat else float("nan"), "latency_ms_p90": 1e3 * p90, "kinds": kinds}
    rep.say(f"| {clients} | {acked} | {elapsed:.1f} | {acked / elapsed:.0f} | "
            f"{row['latency_ms_median']:.1f} ({row['latency_ms_p90']:.1f}) | {kinds} |")
    return row


def serve_section(rep: Any, be: Any, emulate: bool, frames: int, n: int, clients: int,
                  seconds: float, deadline: float, block_frames: int = 128) -> None:
    """The section (see the module's docstring); stops building at the time limit and
    measures the map as far as it got."""
    import numpy as np
    from mcsm import wire
    from mcsm_client.client import MapClient

    from tests.helpers import random_at

    rep.say(f"\n## serve: `mcsm serve --device cuda` (a subprocess) over Zenoh, "
            f"{frames} frames, N = {n}")
    if not emulate:  # what this process still caches on the GPU goes back to the driver
        gc.collect()
        be.xp.get_default_memory_pool().free_all_blocks()
    out: dict[str, Any] = {"target_frames": frames, "n": n}
    rep.data["serve"] = out
    size = min(_block_frames(n, block_frames), frames)
    block = chain(n, size, 20261207).export_component("p0")
    rng = np.random.default_rng(20261208)
    steps = [random_at(rng, n, kind="cloud", t_sigma=0.2, r_sigma=0.03) for _ in range(8)]
    with tempfile.TemporaryDirectory(prefix="mcsm-gpu-serve-") as tmp:
        srv = _server(Path(tmp), n, emulate)
        t0 = time.perf_counter()
        srv.start()
        out["server_start_s"] = time.perf_counter() - t0
        rep.say(f"server ready in {out['server_start_s']:.1f} s: {' '.join(srv.cmd[3:])}")
        try:
            conns = [MapClient(connect=srv.endpoint, timeout_s=120) for _ in range(clients)]
            try:
                _run(rep, out, conns, block, size, frames, steps, seconds, deadline, wire)
            finally:
                for c in conns:
                    c.close()
        finally:
            code = srv.stop(timeout_s=120)
            rec = Path(tmp) / "serve.mcap"
            out["recording_bytes"] = rec.stat().st_size if rec.exists() else 0
            out["server_exit"] = code
            if code not in (0, None):
                rep.say(f"server exit code {code}; its log:\n{srv.log_tail(30)}")


def _run(rep: Any, out: dict[str, Any], conns: list[Any], block: Any, size: int, frames: int,
         steps: list[Any], seconds: float, deadline: float, wire: Any) -> None:
    import numpy as np

    n_blocks = -(-frames // size)
    sizes = [size] * (n_blocks - 1) + [frames - size * (n_blocks - 1)]
    build_end = deadline - 2 * seconds - 30  # leave time to measure and to ask for info

    def submap(k: int) -> Any:
        m = sizes[k]
        names = tuple(f"b{k}_{j}" for j in range(m))
        return wire.SubmapData(root=names[0], frames=names, is_point=block.is_point[:m],
                               edges=block.edges[:m])

    def put(k: int) -> int:
        if time.perf_counter() > build_end:
            return -1
        ack = conns[k % len(conns)].import_submap(submap(k))
        return k if ack.kind == "import" else -2

    t0 = time.perf_counter()
    with ThreadPoolExecutor(len(conns)) as pool:
        got = list(pool.map(put, range(n_blocks)))
    t_import = time.perf_counter() - t0
    imported = 0
    while imported < n_blocks and got[imported] == imported:
        imported += 1
    bad = [k for k in got if k == -2]
    joins = 0
    t1 = time.perf_counter()
    for k in range(1, imported):
        if time.perf_counter() > build_end:
            break
        ack = conns[0].update(f"b{k - 1}_{sizes[k - 1] - 1}", f"b{k}_0", steps[k % len(steps)])
        if ack.kind != "join":
            bad.append(k)
            break
        joins += 1
    t_join = time.perf_counter() - t1
    m = sum(sizes[: joins + 1])
    out.update(imports=imported, joins=joins, frames=m, import_s=t_import, join_s=t_join,
               block_frames=size, failed_blocks=bad)
    mb = 7 * 8 * block.edges.shape[1] * size / 1e6
    rep.say(f"built by {imported} acknowledged imports ({size} frames, {mb:.1f} MB each, "
            f"{len(conns)} clients) in {t_import:.1f} s and {joins} joins (one client) in "
            f"{t_join:.1f} s: {m} frames in one component"
            f"{'' if m == frames else f' (stopped by the time limit; target {frames})'}"
            f"{f'; FAILED blocks {bad}' if bad else ''}")
    if bad:
        rep.failed.append("serve: an import or a join was not acknowledged as such")
        return
    last = joins
    a, b = "b0_2" if sizes[0] > 2 else "b0_0", f"b{last}_{max(0, sizes[last] - 3)}"
    x = conns[0].query(a, b)
    rngs = [np.random.default_rng(20261209 + k) for k in range(len(conns))]  # one per thread

    def send(k: int, i: int) -> str:
        return str(conns[k].update(a, b, x[rngs[k].permutation(len(x))]).kind)

    rep.say(f"loop closures {a} -> {b} (M = {m}; every frame moves), each acknowledged after "
            f"it was applied and recorded:")
    rep.say("| clients in flight | acknowledged | seconds | per second | "
            "ms per update, median (p90) | kinds |")
    rep.say("|---|---|---|---|---|---|")
    for i in range(3):  # warm-up, not counted
        send(0, i)
    rows = [_rate(rep, "one in flight", 1, seconds, send)]
    if len(conns) > 1:
        rows.append(_rate(rep, "several in flight", len(conns), seconds, send))
    out["rates"] = rows
    best = max(r["per_s"] for r in rows)
    closures = all(set(r["kinds"]) == {"loop_closure"} for r in rows)
    if not closures:
        rep.failed.append("serve: an update was not applied as a loop closure")
    rep.say(f"target >= 200 acknowledged loop closures/s at M = 100,000: "
            f"{'met' if best >= 200 and m >= 100_000 else 'NOT met'} here "
            f"(best {best:.0f}/s at M = {m})")
    if time.perf_counter() > deadline:
        rep.say("info: skipped, out of time")
        return
    t2 = time.perf_counter()
    info = conns[0].info(timeout_s=300)
    out["info_s"] = time.perf_counter() - t2
    out.update(info_frames=info.n_frames, info_components=len(info.components),
               device=info.device, device_bytes=info.device_bytes)
    rep.say(f"info: {info.n_frames} frames, {len(info.components)} component(s), device "
            f"{info.device}, {info.device_bytes / 1e6:.1f} MB of device memory; the reply "
            f"(its digest reads and hashes the whole map) took {out['info_s']:.1f} s")
    if info.n_frames != m or len(info.components) != 1:
        rep.failed.append(f"serve: info says {info.n_frames} frames in "
                          f"{len(info.components)} components, not {m} in 1")
