"""``mcsm-client audit`` against a real server: GNC over the server's recording finds a
self-consistent burst of wrong closures the gate let through and, with ``--apply``, the server
retracts them (the map then equals one that never had them)."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
from mcsm import StochasticMap
from mcsm_client.cli import main
from mcsm_client.client import MapClient

from tests.clients.test_audit import N, burst_graph
from tests.service.daemon_util import Daemon, start_daemon

pytest.importorskip("gtsam")


@pytest.mark.slow
def test_audit_retracts_a_burst_through_the_server(tmp_path: Path, daemons: list[Daemon],
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    recs, _, burst = burst_graph()
    d = start_daemon(tmp_path, "--samples", str(N), "--gate", "0.99",
                     "--snapshots-kept", "1000")
    daemons.append(d)
    with MapClient(connect=d.endpoint, timeout_s=30.0) as c:
        for r in recs:  # the burst forced in (trusted): wrong closures the gate let through
            c.update(r.a, r.b, r.samples, request_id=f"r{r.request_id}",
                     trusted=r.request_id in burst)
        before = c.info()
    let_through = list(burst)
    conn = ["--connect", d.endpoint]
    assert main(["audit", str(d.record), "--json", *conn]) == 0
    dry = json.loads(capsys.readouterr().out)
    assert {r["request_id"] for r in dry["decisions"] if r["action"] == "retract"} \
        >= {f"r{k}" for k in let_through}
    with MapClient(connect=d.endpoint, timeout_s=30.0) as c:  # without --apply: no change
        after = c.info()
    assert (after.seq, after.digest) == (before.seq, before.digest)
    assert main(["audit", str(d.record), "--apply", "--json", *conn]) == 0
    done = json.loads(capsys.readouterr().out)
    retracted = {r["request_id"] for r in done["decisions"] if r.get("verdict") == "retracted"}
    assert retracted >= {f"r{k}" for k in let_through}
    reinstated = {r["request_id"] for r in done["decisions"] if r["action"] == "reinstate"}
    # the map now equals one fed every input but the retracted ones (re-gated, the
    # reinstated ones trusted)
    m = StochasticMap(N, gate=0.99)
    for r in recs:
        rid = f"r{r.request_id}"
        if rid not in retracted:
            m.update(r.a, r.b, r.samples, trusted=rid in reinstated or r.request_id in burst)
    with MapClient(connect=d.endpoint, timeout_s=30.0) as c:
        assert c.info().digest == m.state_digest()
    assert d.stop(signal.SIGINT) == 0
