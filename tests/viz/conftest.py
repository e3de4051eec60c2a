"""Fixtures of the picture tests: a small planar recording made by a real ``mcsm serve``.

The recording has two maps: ``default`` (a loop of poses with point landmarks, a loop closure, a
removed pose, and a second component) and ``other`` (two poses), written like
``tests/recording/make_recordings.py`` does: a daemon subprocess fed by ``MapClient`` over
loopback Zenoh, closed with SIGINT.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from mcsm.core.quat import qexp

from tests.service.daemon_util import start_daemon

N = 64


def planar_at(rng: np.random.Generator, n: int, xy: list[float], yaw: float,
              sigma_t: float = 0.05, sigma_yaw: float = 0.02) -> np.ndarray:
    """``(n, 7)`` samples of a planar AT: x-y translation and yaw noise only (z = 0)."""
    x = np.zeros((n, 7))
    x[:, :2] = np.asarray(xy) + sigma_t * rng.standard_normal((n, 2))
    w = np.zeros((n, 3))
    w[:, 2] = yaw + sigma_yaw * rng.standard_normal(n)
    x[:, 3:] = qexp(w)
    return x


def planar_point(rng: np.random.Generator, n: int, xy: list[float],
                 sigma: float = 0.1) -> np.ndarray:
    p = np.zeros((n, 3))
    p[:, :2] = np.asarray(xy) + sigma * rng.standard_normal((n, 2))
    return p


Op = tuple[str, str, str, np.ndarray | None]


def default_ops(rng: np.random.Generator) -> list[Op]:
    ops: list[Op] = []
    for k in range(8):
        ops.append(("update", f"x{k}", f"x{k + 1}", planar_at(rng, N, [1.0, 0.0], 0.6)))
        if k % 2 == 0:
            ops.append(("update", f"x{k + 1}", f"l{k // 2}",
                        planar_point(rng, N, [0.5, 1.0])))
    ops.append(("update", "x0", "x8", planar_at(rng, N, [0.6, 0.5], -1.4)))  # loop closure
    ops.append(("remove", "x3", "", None))
    ops.append(("update", "q0", "q1", planar_at(rng, N, [0.0, 2.0], 0.0)))
    ops.append(("update", "q1", "m0", planar_point(rng, N, [1.0, 0.0])))
    return ops


@dataclass
class Recording:
    path: Path
    ops: dict[str, list[Op]]


def apply(client: object, op: Op) -> None:
    kind, a, b, x = op
    if kind == "remove":
        client.remove(a)  # type: ignore[attr-defined]
    elif x is not None and x.shape[1] == 3:
        client.update_point(a, b, x)  # type: ignore[attr-defined]
    else:
        client.update(a, b, x)  # type: ignore[attr-defined]


@pytest.fixture(scope="session")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Recording]:
    from mcsm_client.client import MapClient

    work = tmp_path_factory.mktemp("viz-rec")
    rng = np.random.default_rng(20261123)
    ops = {"default": default_ops(rng),
           "other": [("update", "a", "b", planar_at(rng, N, [2.0, 0.0], 0.0))]}
    d = start_daemon(work, "--samples", str(N), "--map", "default", "--map", "other",
                     "--checkpoint-every", "4", name="viz")
    try:
        for name, seq in ops.items():
            with MapClient(map=name, connect=d.endpoint, timeout_s=30) as c:
                for op in seq:
                    apply(c, op)
        assert d.stop(signal.SIGINT) == 0
    finally:
        if d.proc.poll() is None:
            d.proc.kill()
            d.proc.wait(timeout=10)
    yield Recording(d.record, ops)


def build_map(ops: list[Op], n_ops: int | None = None) -> object:
    """The map the first ``n_ops`` ops give, built in process with the core (the server's
    default options), independently of replay and of mcsm.viz."""
    from mcsm import StochasticMap

    m = StochasticMap(N)
    for kind, a, b, x in ops[:n_ops]:
        if kind == "remove":
            m.remove(a)
        else:
            assert x is not None
            m.update(a, b, x)
    return m
