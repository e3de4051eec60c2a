"""Verdicts over the wire: the gate of a real server, in acks, events, info and the recording.

A server started with its defaults (the gate at 0.99) accepts a true loop closure (its ack
carries the NIS, dof and threshold), rejects a contradicting one (kind ``rejected``, map
unchanged), applies a trusted one anyway, counts verdicts in ``info``, publishes them in events,
and records every input with its verdict's inputs so that replay reproduces the verdicts and
the digest. With ``--gate none`` nothing is refused.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
from mcsm import StochasticMap, wire
from mcsm.recording import replay
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 64


def test_gate_verdicts_in_acks_events_info_and_replay(tmp_path: Path,
                                                       daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N))  # the default gate: 0.99
    daemons.append(d)
    rng = np.random.default_rng(20261125)
    local = StochasticMap(N)
    assert local.gate == 0.99
    events: list[wire.Event] = []
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        sub = c.session.declare_subscriber(
            c.keys.events, lambda s: events.append(wire.decode_event(s.payload.to_bytes())))
        for k in range(4):
            x = noisy_at(rng, N, [1.0, 0.0, 0.0])
            ack = c.update(f"p{k}", f"p{k + 1}", x, stamp_ns=1_000 + k)
            local.update(f"p{k}", f"p{k + 1}", x)
            assert ack.kind in ("new_component", "new_frame")
            assert ack.verdict is not None and ack.verdict.status == "accepted"
            assert ack.verdict.nis is None and "nothing to test" in ack.verdict.reason
            assert ack.verdict.stamp_ns == 1_000 + k
        true = local.query("p0", "p4")[rng.permutation(N)]
        ack = c.update("p0", "p4", true)
        assert local.update("p0", "p4", true).kind == "loop_closure"
        assert ack.kind == "loop_closure" and ack.verdict is not None
        v = ack.verdict
        assert v.status == "accepted" and v.dof == 6 and v.nis is not None
        assert v.threshold is not None and v.nis <= v.threshold
        before = c.info().digest
        samples = c.query("p0", "p4")
        wrong = local.query("p0", "p4")
        wrong[:, 0] += 50.0 * float(np.std(wrong[:, 0]))  # 50 sigma off
        ack = c.update("p0", "p4", wrong)
        assert ack.kind == "rejected" and ack.verdict is not None
        assert ack.verdict.status == "rejected" and ack.verdict.nis is not None
        assert ack.verdict.threshold is not None and ack.verdict.nis > ack.verdict.threshold
        assert np.array_equal(c.query("p0", "p4"), samples)  # the samples are unchanged
        assert local.update("p0", "p4", wrong).kind == "rejected"
        assert c.info().digest == local.state_digest()  # the gate's window took note of it
        ack = c.update("p0", "p4", wrong, trusted=True)
        assert ack.kind == "loop_closure" and ack.verdict is not None
        assert ack.verdict.status == "accepted" and "trusted" in ack.verdict.reason
        local.update("p0", "p4", wrong, trusted=True)
        info = c.info()
        assert info.digest == local.state_digest() != before
        assert info.verdicts == {"accepted": 6, "rejected": 1}
        deadline = time.monotonic() + 10.0
        while len(events) < 7 and time.monotonic() < deadline:
            time.sleep(0.02)
        sub.undeclare()
    statuses = [e.extra.get("verdict", {}).get("status") for e in sorted(events,
                                                                         key=lambda e: e.seq)]
    assert statuses == ["accepted"] * 5 + ["rejected", "accepted"]
    assert d.stop(signal.SIGINT) == 0, d.log_text()
    rep = replay(d.record)
    assert rep.identical, rep.divergence
    st = rep.states["default"]
    assert dict(st.verdicts) == {"accepted": 6, "rejected": 1}
    assert st.digest() == local.state_digest()


def test_trusted_and_stamp_round_trip_and_are_checked() -> None:
    x = np.zeros((3, 7))
    x[:, 3] = 1.0
    req = wire.decode_update(wire.encode_update("i", "a", "b", x, trusted=True,
                                                stamp_ns=123), 3)
    assert req.trusted and req.stamp_ns == 123
    plain = wire.decode_update(wire.encode_update("i", "a", "b", x), 3)
    assert not plain.trusted and plain.stamp_ns is None
    import msgpack
    import pytest
    from mcsm.errors import BadMessage

    d = msgpack.unpackb(wire.encode_update("i", "a", "b", x))
    for key, bad in (("trusted", 1), ("trusted", "yes"), ("stamp_ns", -1), ("stamp_ns", 1.5)):
        with pytest.raises(BadMessage):
            wire.decode_update(msgpack.packb({**d, key: bad}), 3)



def test_gate_none_applies_every_closure(tmp_path: Path, daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N), "--gate", "none")
    daemons.append(d)
    rng = np.random.default_rng(20261128)
    local = StochasticMap(N, gate=None)
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        for k in range(4):
            x = noisy_at(rng, N, [1.0, 0.0, 0.0])
            c.update(f"p{k}", f"p{k + 1}", x)
            local.update(f"p{k}", f"p{k + 1}", x)
        wrong = local.query("p0", "p4")
        wrong[:, 0] += 50.0 * float(np.std(wrong[:, 0]))  # 50 sigma off
        ack = c.update("p0", "p4", wrong)
        local.update("p0", "p4", wrong)
        assert ack.kind == "loop_closure" and ack.verdict is not None
        assert ack.verdict.threshold is None and ack.verdict.reason == "no gate"
        info = c.info()
        assert "gate" not in info.options and info.digest == local.state_digest()
    assert d.stop(signal.SIGINT) == 0, d.log_text()
    rep = replay(d.record)
    assert rep.identical and rep.states["default"].map.gate is None
