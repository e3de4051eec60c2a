"""Regenerate ``recordings/*.mcap`` and their ``.digest`` files with our own tools (by hand).

Usage: ``.venv/bin/python tests/recording/make_recordings.py`` from the repository root.

Each recording comes from a real ``mcsm serve`` subprocess fed by ``MapClient`` over Zenoh
loopback (fixed seeds). The ``.digest`` beside it holds one line per map,
``<map> <seq> <sha256>``: the state after applying the same operations to an in-process
``StochasticMap`` (never a number read back from the recording itself).

* ``loop-small``: one map, N=100, odometry chain with loop closures, points and removes,
  closed cleanly (SIGINT).
* ``two-maps``: maps ``a`` and ``b``, N=50; a component exported from ``a``, imported into
  ``b`` and joined there (case I), then a loop closed across (case II); closed cleanly.
* ``killed``: N=64, SIGKILLed mid-stream: no footer, no summary (the streaming reader case).
"""

from __future__ import annotations

import shutil
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository root

from mcsm import StochasticMap  # noqa: E402
from mcsm.errors import McsmError  # noqa: E402
from mcsm.log.reader import RecordingReader  # noqa: E402
from mcsm_client.client import MapClient  # noqa: E402

from tests.service.daemon_util import noisy_at, start_daemon  # noqa: E402

OUT = Path(__file__).resolve().parents[2] / "recordings"


def chain(rng: np.random.Generator, n: int, count: int) -> list[tuple[str, str, str, object]]:
    ops: list[tuple[str, str, str, object]] = []
    for i in range(count):
        if i % 7 == 6:  # loop closure back to the start
            ops.append(("update", "p0", f"p{i}", noisy_at(rng, n, [float(i), 0.0, 0.0])))
        if i % 5 == 2:
            lm = f"lm{i % 3}"
            pt = np.array([2.0 + i % 3, 1.0, 0.0]) - [float(i), 0, 0]
            ops.append(("point", f"p{i}", lm, pt + 0.05 * rng.standard_normal((n, 3))))
        ops.append(("update", f"p{i}", f"p{i + 1}", noisy_at(rng, n, [1.0, 0, 0])))
        if i in (12, 25):
            ops.append(("remove", f"p{i - 3}", "", None))
    return ops


def run(c: MapClient, m: StochasticMap, op: str, a: str, b: str, x: object) -> None:
    if op == "remove":
        c.remove(a)
        m.remove(a)
    elif op == "point":
        c.update_point(a, b, x)
        m.update(a, b, np.asarray(x))
    else:
        c.update(a, b, x)
        m.update(a, b, np.asarray(x))


def digest_line(name: str, m: StochasticMap, seq: int) -> str:
    return f"{name} {seq} {m.state_digest()}\n"


def loop_small(work: Path) -> None:
    rng = np.random.default_rng(20240601)
    n = 100
    d = start_daemon(work, "--samples", str(n), "--checkpoint-every", "10", name="loop-small")
    m = StochasticMap(n)
    ops = chain(rng, n, 36)
    with MapClient(connect=d.endpoint, timeout_s=30) as c:
        for op in ops:
            run(c, m, *op)
        seq = c.info().seq
    assert d.stop(signal.SIGINT) == 0
    shutil.copy(d.record, OUT / "loop-small.mcap")
    (OUT / "loop-small.digest").write_text(digest_line("default", m, seq))


def two_maps(work: Path) -> None:
    rng = np.random.default_rng(20240602)
    n = 50
    d = start_daemon(work, "--samples", str(n), "--map", "a", "--map", "b",
                     "--checkpoint-every", "3", name="two-maps")
    ma, mb = StochasticMap(n), StochasticMap(n)
    with MapClient(map="a", connect=d.endpoint, timeout_s=30) as ca, \
            MapClient(map="b", connect=d.endpoint, timeout_s=30) as cb:
        for op in chain(rng, n, 8):
            run(ca, ma, *op)
        for op in [("update", "q0", "q1", noisy_at(rng, n, [0, 1.0, 0])),
                   ("update", "q1", "q2", noisy_at(rng, n, [0, 1.0, 0]))]:
            run(cb, mb, *op)
        sub = ca.export_submap("p0")
        cb.import_submap(sub)
        mb.import_component(ma.export_component("p0"))
        run(cb, mb, "update", "q2", "p3", noisy_at(rng, n, [1.0, 1.0, 0]))   # join
        run(cb, mb, "update", "q0", "p5", noisy_at(rng, n, [3.0, 3.0, 0]))   # loop closure
        seq_a, seq_b = ca.info().seq, cb.info().seq
    assert d.stop(signal.SIGTERM) == 0
    shutil.copy(d.record, OUT / "two-maps.mcap")
    (OUT / "two-maps.digest").write_text(digest_line("a", ma, seq_a) + digest_line("b", mb, seq_b))


def killed(work: Path) -> None:
    rng = np.random.default_rng(20240603)
    n = 64
    d = start_daemon(work, "--samples", str(n), "--checkpoint-every", "5", name="killed")
    ops = chain(rng, n, 300)
    acked: list[int] = []

    def stream(c: MapClient) -> None:
        scratch = StochasticMap(n)
        for op in ops:
            try:
                run(c, scratch, *op)
            except McsmError:
                return
            acked.append(1)

    with MapClient(connect=d.endpoint, timeout_s=1.0, retries=0) as c:
        t = threading.Thread(target=stream, args=(c,))
        t.start()
        deadline = time.monotonic() + 60
        while len(acked) < 30 and time.monotonic() < deadline:
            time.sleep(0.01)
        d.proc.send_signal(signal.SIGKILL)
        d.proc.wait(timeout=10)
        t.join(timeout=30)
    # how many inputs reached the file: count the complete input records (no map applied)
    recorded = sum(1 for r in RecordingReader(d.record) if r.topic.startswith("/mcsm/in/"))
    assert len(acked) <= recorded <= len(acked) + 1, (len(acked), recorded)
    m = StochasticMap(n)
    for op, a, b, x in ops[:recorded]:
        if op == "remove":
            m.remove(a)
        else:
            m.update(a, b, np.asarray(x))
    shutil.copy(d.record, OUT / "killed.mcap")
    (OUT / "killed.digest").write_text(digest_line("default", m, recorded))


def main() -> None:
    OUT.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for fn in (loop_small, two_maps, killed):
            work = Path(tmp) / fn.__name__
            work.mkdir()
            fn(work)
            print(f"wrote recordings/{fn.__name__.replace('_', '-')}.mcap")


if __name__ == "__main__":
    main()
