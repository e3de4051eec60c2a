"""Taking a constraint back over the wire: retract and reinstate on a real server.

A wrong loop closure forced in (trusted) is retracted: the map becomes bit-identical to a map
that never had it (an in-process ``StochasticMap`` fed the same inputs without it);
reinstating it gives back the first digest; both survive SIGKILL + ``--restore`` and replay
identically; the verdicts say what changed.
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.errors import InvalidOperation
from mcsm.log.replay import replay
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 48
OPTS = ("--samples", str(N), "--gate", "0.99", "--snapshot-every", "4", "--snapshots-kept", "3")


def _inputs(rng: np.random.Generator) -> list[tuple[str, str, str, np.ndarray, bool]]:
    """(id, a, b, samples, trusted): a chain, true closures, one wrong closure forced in."""
    local = StochasticMap(N)
    ops: list[tuple[str, str, str, np.ndarray, bool]] = []
    for k in range(8):
        x = noisy_at(rng, N, [1.0, 0.0, 0.0])
        local.update(f"p{k}", f"p{k + 1}", x)
        ops.append((f"odo{k}", f"p{k}", f"p{k + 1}", x, False))
    true1 = local.query("p0", "p8")[rng.permutation(N)]
    ops.append(("true1", "p0", "p8", true1, False))
    wrong = local.query("p2", "p6")
    wrong[:, 1] += 3.0  # metres off, as confident as a true closure
    ops.append(("wrong", "p2", "p6", wrong, True))
    for k in range(8, 11):
        ops.append((f"odo{k}", f"p{k}", f"p{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]), False))
    local2 = StochasticMap(N)
    for rid, a, b, x, _ in ops:
        if rid != "wrong":
            local2.update(a, b, x)
    ops.append(("true2", "p3", "p11", local2.query("p3", "p11")[rng.permutation(N)], False))
    return ops


def _fresh(ops: list[tuple[str, str, str, np.ndarray, bool]], skip: str = "") -> StochasticMap:
    m = StochasticMap(N, gate=0.99)
    for rid, a, b, x, trusted in ops:
        if rid != skip:
            m.update(a, b, x, trusted=trusted)
    return m


def test_retract_and_reinstate_are_exact_and_survive_a_restart(
        tmp_path: Path, daemons: list[Daemon]) -> None:
    ops = _inputs(np.random.default_rng(20261126))
    d = start_daemon(tmp_path, *OPTS)
    daemons.append(d)
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        for rid, a, b, x, trusted in ops:
            c.update(a, b, x, request_id=rid, trusted=trusted)
        with_wrong = c.info().digest
        assert with_wrong == _fresh(ops).state_digest()
        assert c.verdict("wrong") is not None
        ack = c.retract("wrong")
        assert ack.op == "retract" and ack.verdict is not None
        assert ack.verdict.status == "retracted"
        without = c.info().digest
        assert without == _fresh(ops, skip="wrong").state_digest() != with_wrong
        verdict = c.verdict("wrong")
        assert verdict is not None and verdict.status == "retracted"
        with pytest.raises(InvalidOperation):
            c.retract("wrong")  # already retracted
        with pytest.raises(InvalidOperation):
            c.retract("no-such-request")
    assert d.stop(signal.SIGKILL) != 0
    d2 = start_daemon(tmp_path, *OPTS, "--restore", str(d.record), name="d2",
                      listen_on=d.endpoint)
    daemons.append(d2)
    with MapClient(connect=d2.endpoint, timeout_s=10.0) as c:
        assert c.info().digest == without
        ack = c.reinstate("wrong")
        assert ack.verdict is not None and ack.verdict.status == "reinstated"
        assert c.info().digest == with_wrong
        assert c.verdict("wrong").status == "reinstated"  # type: ignore[union-attr]
    assert d2.stop(signal.SIGINT) == 0, d2.log_text()
    for path, final in ((d.record, without), (d2.record, with_wrong)):
        rep = replay(path)
        assert rep.identical, rep.divergence
        assert rep.states["default"].digest() == final


def test_retract_outside_the_window_is_refused(tmp_path: Path, daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N), "--snapshot-every", "2",
                     "--snapshots-kept", "2")
    daemons.append(d)
    rng = np.random.default_rng(5)
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        for k in range(10):
            c.update(f"p{k}", f"p{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]),
                     request_id=f"u{k}")
        with pytest.raises(InvalidOperation, match="retract window"):
            c.retract("u0")
        c.retract("u9")
    assert d.stop(signal.SIGINT) == 0


def test_a_reinstated_update_stays_in_when_an_earlier_one_is_retracted() -> None:
    """Reinstating puts an update in as trusted; a later retraction of an earlier input
    re-applies it, still trusted and still ``reinstated`` (in process, no server)."""
    from mcsm import wire
    from mcsm.map.state import MapState

    ops = _inputs(np.random.default_rng(20261127))
    st = MapState("default", StochasticMap(N), snapshot_every=4, snapshots_kept=10)
    for rid, a, b, x, _ in ops:  # "wrong" is sent untrusted: the gate refuses it
        st.apply("update", wire.UpdateRequest(rid, a, b, x), time_ns=0)
    assert st.verdict_of("wrong").verdict.status == "rejected"  # type: ignore[union-attr]
    st.apply("reinstate", wire.RetractRequest("i1", "wrong"), time_ns=0)
    st.apply("retract", wire.RetractRequest("i2", "true1"), time_ns=0)
    assert st.verdict_of("wrong").verdict.status == "reinstated"  # type: ignore[union-attr]
    m = StochasticMap(N)
    for rid, a, b, x, _ in ops:
        if rid != "true1":
            m.update(a, b, x, trusted=rid == "wrong")
    assert st.digest() == m.state_digest()


def test_a_true_closure_pushed_out_by_a_wrong_one_comes_back_by_itself() -> None:
    """docs/outliers.md: later inputs go through the gate again when a closure is retracted,
    so a true closure a (trusted) wrong one had pushed out is accepted again."""
    from mcsm import wire
    from mcsm.map.state import MapState

    ops = _inputs(np.random.default_rng(20261126))
    st = MapState("default", StochasticMap(N, gate=0.99), snapshot_every=4, snapshots_kept=8)
    for rid, a, b, x, trusted in ops:
        if rid == "wrong":
            x = x.copy()
            x[:, 1] += 7.0  # 10 m off in all: enough to push true2 out of the gate
        st.apply("update", wire.UpdateRequest(rid, a, b, x, trusted=trusted), time_ns=0)

    def status(rid: str) -> str:
        v = st.verdict_of(rid).verdict
        assert v is not None
        return v.status

    assert status("true2") == "rejected"
    st.apply("retract", wire.RetractRequest("r1", "wrong"), time_ns=0)
    assert (status("wrong"), status("true2")) == ("retracted", "accepted")
    st.apply("reinstate", wire.RetractRequest("r2", "wrong"), time_ns=0)
    assert (status("wrong"), status("true2")) == ("reinstated", "rejected")
