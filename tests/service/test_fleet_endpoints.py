"""Every combination of ``--listen`` / ``--connect`` for a replicated map's primary and its
standby, and for clients (issue 23: a server with both once never found its primary).

A server either joins the router only (``connect``: a Zenoh client of the router, listening
nowhere), listens only (``listen``: a peer that clients reach directly), or both (``both``: a
peer that listens and joins the router). Replication never goes through Zenoh (the log is in
NATS JetStream), so every pair works: a client reaches the primary through the router
(``connect``, ``both``) and directly on its endpoint (``listen``, ``both``); after a SIGKILL
the standby takes over and is reached the same ways. The whole matrix is ``make test-fleet``;
``make test`` runs the shape that failed (both flags on both servers).
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
from mcsm.serve.natsrun import NatsCluster
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon, start_router, wait_for
from tests.service.fleet_util import N, inputs

MODES = ("connect", "listen", "both")
IN_MAKE_TEST = {("both", "both")}


def _serve(tmp: Path, name: str, mode: str, ep: str, nats: list[str], *args: str) -> Daemon:
    join = ["--connect", ep] if mode != "listen" else []
    return start_daemon(tmp, "--samples", str(N), *args, *join, "--nats", ",".join(nats),
                        "--lease-ttl", "2", name=name,
                        endpoint="-" if mode == "connect" else None)


def _ways(d: Daemon, mode: str, router: str) -> list[str]:
    """The endpoints a client reaches server ``d`` on."""
    return ([router] if mode != "listen" else []) + ([d.endpoint] if mode != "connect" else [])


@pytest.mark.parametrize(("primary", "standby"), [
    pytest.param(p, s, marks=[] if (p, s) in IN_MAKE_TEST else [pytest.mark.fleet])
    for p in MODES for s in MODES])
def test_listen_and_connect(tmp_path: Path, daemons: list[Daemon], nats: NatsCluster,
                            primary: str, standby: str) -> None:
    router, ep = start_router(tmp_path)
    rng = np.random.default_rng(5)
    try:
        p = _serve(tmp_path, "p", primary, ep, nats.urls, "--map", "m")
        s = _serve(tmp_path, "s", standby, ep, nats.urls, "--standby-of", "m")
        daemons += [p, s]
        seq = 0
        for way in _ways(p, primary, ep):
            with MapClient(map="m", connect=way, timeout_s=30.0) as c:
                for _ in range(2):
                    seq += 1
                    assert c.update(f"r/{seq}", f"r/{seq + 1}",
                                    noisy_at(rng, N, [1, 0, 0])).seq == seq
                wait_for("the standby consumes", lambda c=c, n=seq: c.info().standbys and
                         min(c.info().standbys.values()) == n, 30.0)
                first = c.info()
        p.proc.send_signal(signal.SIGKILL)
        p.proc.wait(timeout=30)
        for way in _ways(s, standby, ep):
            with MapClient(map="m", connect=way, timeout_s=30.0) as c:
                for _ in range(2):
                    seq += 1
                    ack = c.update(f"r/{seq}", f"r/{seq + 1}", noisy_at(rng, N, [1, 0, 0]))
                    assert ack.seq == seq and ack.server != first.server_id
                info = c.info()
        assert s.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    assert sorted(inputs(s.record)) == list(range(1, seq + 1))
    assert info.seq == seq
