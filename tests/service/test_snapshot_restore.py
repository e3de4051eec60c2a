"""State snapshots in the recording: ``--restore`` starts from the latest one plus the tail.

The restored map equals the full replay and the in-process map (digest); inputs before the
snapshot are not applied again but their ids are remembered (a retry is not applied twice);
the restored server's new file starts from that snapshot and replays on its own.
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
from mcsm import StochasticMap
from mcsm.recording import replay
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 32


def test_restore_starts_from_the_latest_snapshot(tmp_path: Path, daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N), "--disk-snapshot-every", "10")
    daemons.append(d)
    rng = np.random.default_rng(20261127)
    local = StochasticMap(N)
    sent = []
    j = 0  # the chain's last pose
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        for k in range(35):
            if k % 5 == 4:  # a loop closure back to the start
                x = local.query("p0", f"p{j}")[rng.permutation(N)]
                a, b = "p0", f"p{j}"
            else:
                x = noisy_at(rng, N, [1.0, 0.0, 0.0])
                a, b = f"p{j}", f"p{j + 1}"
                j += 1
            c.update(a, b, x, request_id=f"u{k}")
            local.update(a, b, x)
            sent.append((f"u{k}", a, b, x))
        assert c.info().digest == local.state_digest()
    assert d.stop(signal.SIGKILL) != 0
    full = replay(d.record)
    fast = replay(d.record, from_snapshot=True)
    assert full.states["default"].digest() == fast.states["default"].digest() \
        == local.state_digest()
    assert fast.snapshots_loaded == 1 and fast.n_skipped == 30 and fast.n_inputs == 5
    assert full.n_inputs == 35 and full.snapshots_loaded == 0
    d2 = start_daemon(tmp_path, "--samples", str(N), "--restore", str(d.record), name="d2",
                      listen_on=d.endpoint)
    daemons.append(d2)
    with MapClient(connect=d2.endpoint, timeout_s=10.0) as c:
        assert c.info().digest == local.state_digest()
        rid, a, b, x = sent[3]  # applied before the snapshot: a retry is not applied again
        ack = c.update(a, b, x, request_id=rid)
        assert ack.duplicate and ack.seq == 4
        assert c.info().digest == local.state_digest()
    assert d2.stop(signal.SIGINT) == 0, d2.log_text()
    # the log says what was restored: the snapshot it started from and the inputs after it
    assert "map 'default': snapshot at seq 30 + 5 inputs" in d2.log_text(), d2.log_text()
    rep = replay(d2.record)
    assert rep.identical, rep.divergence
    assert rep.snapshots_loaded == 1 and rep.n_inputs == 5
    assert rep.states["default"].digest() == local.state_digest()
