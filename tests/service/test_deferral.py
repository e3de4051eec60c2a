"""Server-side deferral of first closures (``mcsm serve --gate-defer``, :mod:`mcsm.map.deferral`).

The policy runs inside :class:`mcsm.map.state.MapState`, so the live server, replay and
``--restore`` decide every held closure by the same code. Checked here: it decides exactly as
the measured client-side :class:`mcsm_client.outliers.DeferringMap`; a held closure is
``pending`` and is applied when a second one agrees, rejected when it disagrees, released on
expiry; replay and a restore from a recorded snapshot reproduce verdicts and digests;
retract/reinstate stay exact (or refuse a pending target); and over the wire, a SIGKILL plus
``--restore`` keeps the held closure.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcsm import StochasticMap, wire
from mcsm.errors import InvalidOperation
from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.writer import Recorder
from mcsm.map.deferral import DeferOptions
from mcsm.map.state import MapState
from mcsm_client.client import MapClient
from mcsm_client.outliers import DeferringMap, Ledger, Record

from experiments.posegraph_sim import perturb, sample_measurement, simulate_2d
from tests.service.daemon_util import Daemon, start_daemon

N = 64


def _graph(seed: int, n_poses: int = 140) -> tuple[list[wire.UpdateRequest], list[int]]:
    """A planar graph of 40-pose laps (loop closures from the second lap on) as requests,
    and the indices of its loop closures."""
    rng = np.random.default_rng(seed)
    g = simulate_2d(n_poses, rng=rng, poses_per_rev=40, radius_m=5.0, breathing_m=0.2,
                    min_gap=30, loop_radius_m=1.0)
    reqs = [wire.UpdateRequest(f"r{k}", f"p{i}", f"p{j}", sample_measurement(z, c, N, rng=rng))
            for k, ((i, j), z, c) in enumerate(zip(g.edges, g.measurements, g.covariances,
                                                   strict=True))]
    return reqs, [int(k) for k in np.flatnonzero(g.is_loop)]


def _wrong(req: wire.UpdateRequest, metres: float = 2.0) -> wire.UpdateRequest:
    moved = perturb(req.samples, np.broadcast_to([metres, 0.0, 0, 0, 0, 0.2], (N, 6)))
    return wire.UpdateRequest(req.request_id, req.a, req.b, moved)


def _state(**defer: Any) -> MapState:
    return MapState("default", StochasticMap(N, inflation=1.002), snapshot_every=10,
                    snapshots_kept=50, gate_defer=DeferOptions(**defer))


def _feed(st: MapState, reqs: list[wire.UpdateRequest]) -> dict[str, list[str]]:
    """Apply every request; per request id, the statuses it was given (its own ack's, then
    any later decision)."""
    seen: dict[str, list[str]] = {}
    for r in reqs:
        ack = st.apply("update", r, time_ns=0)
        assert ack.verdict is not None
        seen.setdefault(r.request_id, []).append(ack.verdict.status)
        for rid, v in st.last_changed.items():
            seen.setdefault(rid, []).append(v.status)
    return seen


def _status(st: MapState, rid: str) -> str:
    v = st.verdict_of(rid).verdict
    assert v is not None
    return v.status


def test_server_deferral_decides_as_the_client_deferring_map() -> None:
    """Same inputs (a wrong first closure, then true ones): the same statuses and the same map
    as the measured client-side policy (whose expiry comes at the next input, the same place
    in the order)."""
    reqs, loops = _graph(4)
    reqs[loops[0]] = _wrong(reqs[loops[0]])
    st = _state()
    _feed(st, reqs)
    client = DeferringMap(Ledger(StochasticMap(N, inflation=1.002)), revisit_gap=25, expiry=25)
    for k, r in enumerate(reqs):
        client.update(Record(k, r.a, r.b, r.samples))
    assert st.map.state_digest() == client.map.state_digest()
    for k, r in enumerate(reqs):
        assert _status(st, r.request_id) == client.final_status(k), k
    assert _status(st, f"r{loops[0]}") == "rejected"
    assert "cycle" in st.verdict_of(f"r{loops[0]}").verdict.reason  # type: ignore[union-attr]


def test_pending_then_applied_when_a_second_closure_agrees() -> None:
    reqs, loops = _graph(5)
    first, second = loops[0], loops[1]
    st = _state()
    seen = _feed(st, reqs[:first + 1])
    ack = st.verdict_of(f"r{first}")
    assert ack.kind == "pending" and seen[f"r{first}"] == ["pending"]
    from mcsm_client.cli import _ack_text  # what mcsm-client update prints

    assert "pending" in _ack_text(ack) and "verdict=pending [first closure" in _ack_text(ack)
    assert st.verdicts["pending"] == 1
    assert st.deferral is not None and st.deferral.pending_id() == f"r{first}"
    before = st.digest()
    seen = _feed(st, reqs[first + 1:second])  # odometry: the map goes on, the closure waits
    assert st.deferral.pending_id() == f"r{first}" and st.digest() != before
    ack = st.apply("update", reqs[second], time_ns=0)
    assert ack.kind == "loop_closure" and ack.verdict.status == "accepted"  # type: ignore
    assert st.last_changed[f"r{first}"].status == "accepted"
    assert _status(st, f"r{first}") == "accepted" and st.deferral.pending_id() is None
    assert "pending" not in st.verdicts
    # the same map as applying both, in that order, without deferral
    plain = StochasticMap(N, inflation=1.002)
    for r in reqs[:first] + reqs[first + 1:second] + [reqs[first], reqs[second]]:
        plain.update(r.a, r.b, r.samples)
    assert st.map.state_digest() == plain.state_digest()


def test_pending_then_rejected_when_the_second_disagrees() -> None:
    reqs, loops = _graph(4)
    first, second = loops[0], loops[1]
    reqs[first] = _wrong(reqs[first])
    st = _state()
    _feed(st, reqs[:second])
    assert _status(st, f"r{first}") == "pending"
    ack = st.apply("update", reqs[second], time_ns=0)
    assert ack.kind == "pending"  # the newer one waits for a partner in turn
    v = st.last_changed[f"r{first}"]
    assert v.status == "rejected" and "cycle" in v.reason and v.nis is not None
    assert v.threshold is not None and v.nis > v.threshold
    assert _status(st, f"r{first}") == "rejected"
    assert st.verdicts["pending"] == 1 and st.verdicts["rejected"] == 1


@pytest.mark.parametrize("on_expiry", ["gate", "reject"])
def test_a_lone_closure_expires_after_k_updates(on_expiry: str) -> None:
    reqs, loops = _graph(5)
    first = loops[0]
    odometry = [r for r in reqs[first + 1:] if int(r.b[1:]) == int(r.a[1:]) + 1]
    st = _state(expiry=5, on_expiry=on_expiry)
    _feed(st, reqs[:first + 1])
    _feed(st, odometry[:4])
    assert _status(st, f"r{first}") == "pending"
    ack = st.apply("update", odometry[4], time_ns=0)  # the 5th update after it
    assert ack.kind == "new_frame"
    want = "accepted" if on_expiry == "gate" else "rejected"
    assert st.last_changed[f"r{first}"].status == want
    assert _status(st, f"r{first}") == want and st.deferral.pending_id() is None  # type: ignore


def _record(path: Path, st: MapState, reqs: list[wire.UpdateRequest],
            disk_snapshot_at: int = 0) -> dict[str, wire.Verdict | None]:
    """Apply and record as the server's worker does; the final verdict of every id."""
    rec = Recorder(path)
    rec.config(st, 7)
    for k, r in enumerate(reqs):
        payload = wire.encode_update(r.request_id, r.a, r.b, r.samples, trusted=r.trusted)
        ack = st.apply("update", r, time_ns=1_000 + k)
        rec.input("update", st.name, ack.seq, 1_000 + k, "test", r.request_id, payload)
        if ack.seq % 7 == 0:
            rec.checkpoint(st.name, ack.seq, st.digest(), "periodic")
        if ack.seq == disk_snapshot_at:
            rec.snapshot(st)
    rec.checkpoint(st.name, st.seq, st.digest(), "close")
    rec.close()
    return {r.request_id: st.verdict_of(r.request_id).verdict for r in reqs}


def test_replay_and_restore_from_a_snapshot_reproduce_verdicts_and_digests(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    reqs, loops = _graph(4)
    reqs[loops[0]] = _wrong(reqs[loops[0]])
    # a disk snapshot while the first closure is held
    held_at = loops[0] + 3
    st = _state()
    verdicts = _record(tmp_path / "a.mcap", st, reqs, disk_snapshot_at=held_at)
    config = next(i.data for i in RecordingReader(tmp_path / "a.mcap")
                  if i.topic == "/mcsm/config")
    assert config["gate_defer"] == DeferOptions().to_dict()
    from mcsm.cli import main as mcsm_main

    assert mcsm_main(["inspect", str(tmp_path / "a.mcap")]) == 0
    assert "--gate-defer {'expiry': 25" in capsys.readouterr().out
    snap = next(i.data for i in RecordingReader(tmp_path / "a.mcap")
                if i.topic == "/mcsm/snapshot")
    assert snap["deferral"]["held"]["id"] == f"r{loops[0]}"
    # the records and a pending ack match their schemas
    from jsonschema import Draft202012Validator
    from mcsm.log.topics import schema_bytes

    for record, name in ((config, "record_config.json"), (snap, "record_snapshot.json")):
        schema = json.loads(schema_bytes(name))
        assert list(Draft202012Validator(schema).iter_errors(record)) == [], name
    pending = _state()
    _feed(pending, reqs[:loops[0] + 1])
    ack = wire.unpack(wire.encode_ack(pending.verdict_of(f"r{loops[0]}")))
    assert ack["kind"] == "pending" and ack["verdict"]["status"] == "pending"
    schema = json.loads(schema_bytes("ack.json"))
    assert list(Draft202012Validator(schema).iter_errors(ack)) == []
    for from_snapshot in (False, True):
        rep = replay(tmp_path / "a.mcap", from_snapshot=from_snapshot)
        assert rep.identical, rep.divergence
        assert rep.snapshots_loaded == int(from_snapshot)
        got = rep.states["default"]
        assert got.digest() == st.digest()
        assert got.verdicts == st.verdicts
        for rid, v in verdicts.items():
            if from_snapshot and int(rid[1:]) < held_at:
                continue  # before the snapshot: only the id is remembered, not its ack
            assert got.verdict_of(rid).verdict == v, rid
        # the closure held across the snapshot was decided after it: its verdict is known
        assert got.verdict_of(f"r{loops[0]}").verdict == verdicts[f"r{loops[0]}"]
        assert verdicts[f"r{loops[0]}"].status == "rejected"  # type: ignore[union-attr]
    # without --gate-defer in the recording, the same inputs give another map
    plain = MapState("default", StochasticMap(N, inflation=1.002))
    for r in reqs:
        plain.apply("update", r, time_ns=0)
    assert plain.digest() != st.digest()


def test_retract_and_reinstate_stay_exact_with_deferral() -> None:
    reqs, loops = _graph(4)
    first, second = loops[0], loops[1]
    reqs[first] = _wrong(reqs[first])
    st = _state()
    _feed(st, reqs[:second])
    for op in ("retract", "reinstate"):  # a held closure is neither in nor out yet
        with pytest.raises(InvalidOperation, match="pending"):
            st.apply(op, wire.RetractRequest(f"x1-{op}", f"r{first}"), time_ns=0)
    _feed(st, reqs[second:])
    accepted = next(f"r{k}" for k in loops[2:] if _status(st, f"r{k}") == "accepted")

    def fresh(skip: str = "", trusted: tuple[str, ...] = ()) -> MapState:
        m = _state()
        _feed(m, [r if r.request_id not in trusted else
                  wire.UpdateRequest(r.request_id, r.a, r.b, r.samples, trusted=True)
                  for r in reqs if r.request_id != skip])
        return m

    before = st.digest()
    st.apply("retract", wire.RetractRequest("x2", accepted), time_ns=0)
    never = fresh(skip=accepted)
    assert st.digest() == never.digest() != before
    for r in reqs:
        if r.request_id != accepted:
            assert _status(st, r.request_id) == _status(never, r.request_id), r.request_id
    assert _status(st, accepted) == "retracted"
    # reinstated: applied as trusted at its place (trusted closures bypass deferral)
    st.apply("reinstate", wire.RetractRequest("x3", accepted), time_ns=0)
    assert _status(st, accepted) == "reinstated"
    assert st.digest() == fresh(trusted=(accepted,)).digest()
    # the closure the cycle test rejected goes back in as trusted, at its place
    st.apply("reinstate", wire.RetractRequest("x4", f"r{first}"), time_ns=0)
    assert _status(st, f"r{first}") == "reinstated"
    both = fresh(trusted=(accepted, f"r{first}"))
    assert st.digest() == both.digest()
    for r in reqs:
        if r.request_id not in (accepted, f"r{first}"):
            assert _status(st, r.request_id) == _status(both, r.request_id), r.request_id


OPTS = ("--samples", str(N), "--gate-defer", "--inflation", "1.002",
        "--disk-snapshot-every", "2", "--checkpoint-every", "3")


def test_held_closure_survives_sigkill_and_restore(tmp_path: Path,
                                                    daemons: list[Daemon]) -> None:
    reqs, loops = _graph(5)
    first, second = loops[0], loops[1]
    d = start_daemon(tmp_path, *OPTS)
    daemons.append(d)
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        for r in reqs[:second]:
            ack = c.update(r.a, r.b, r.samples, request_id=r.request_id)
        assert c.verdict(f"r{first}").status == "pending"  # type: ignore[union-attr]
        assert c.info().verdicts.get("pending") == 1
    assert d.stop(signal.SIGKILL) != 0
    # --restore starts from the last recorded snapshot, taken while the closure was held
    snaps = [i.data for i in RecordingReader(d.record) if i.topic == "/mcsm/snapshot"]
    assert snaps[-1]["seq"] == ack.seq and snaps[-1]["deferral"]["held"]["id"] == f"r{first}"
    d2 = start_daemon(tmp_path, "--samples", str(N), "--inflation", "1.002", "--restore",
                      str(d.record), name="d2", listen_on=d.endpoint)
    daemons.append(d2)
    with MapClient(connect=d2.endpoint, timeout_s=10.0) as c, c.watch() as events:
        assert c.verdict(f"r{first}").status == "pending"  # type: ignore[union-attr]
        ack = c.update(reqs[second].a, reqs[second].b, reqs[second].samples,
                       request_id=reqs[second].request_id)
        assert ack.verdict is not None and ack.verdict.status == "accepted"
        assert c.verdict(f"r{first}").status == "accepted"  # type: ignore[union-attr]
        # the event of the update that decided it says so
        ev = None
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and (ev is None or ev.seq < ack.seq):
            ev = events.get(0.2)
        assert ev is not None and ev.seq == ack.seq
        assert ev.extra["changed"][f"r{first}"]["status"] == "accepted"
        for r in reqs[second + 1:]:
            c.update(r.a, r.b, r.samples, request_id=r.request_id)
        final = c.info().digest
    assert d2.stop(signal.SIGINT) == 0, d2.log_text()
    reference = _state()
    _feed(reference, reqs)
    assert final == reference.digest()
    rep = replay(d2.record)
    assert rep.identical, rep.divergence
    assert rep.states["default"].digest() == final


def test_refused_inputs_are_never_held_and_removed_frames_reject_the_held_one() -> None:
    reqs, loops = _graph(5)
    first = loops[0]
    st = _state(expiry=3)
    _feed(st, reqs[:first])
    before, seq = st.digest(), st.seq
    same = wire.UpdateRequest("self", reqs[first].a, reqs[first].a, reqs[first].samples)
    with pytest.raises(InvalidOperation):
        st.apply("update", same, time_ns=0)  # a -> a: refused by the core, not held
    assert st.digest() == before and st.seq == seq and st.deferral.pending_id() is None  # type: ignore
    _feed(st, [reqs[first]])
    assert _status(st, f"r{first}") == "pending"
    st.apply("remove", wire.RemoveRequest("rm", reqs[first].b), time_ns=0)
    odometry = [r for r in reqs[first + 1:] if int(r.b[1:]) == int(r.a[1:]) + 1]
    _feed(st, odometry[:3])
    v = st.verdict_of(f"r{first}").verdict
    assert v is not None and v.status == "rejected" and "removed" in v.reason


def test_a_restored_servers_file_keeps_the_held_closure(tmp_path: Path) -> None:
    """--restore of a file written by a restored server (snapshot + tail only: the held
    closure's own input is not in it): the closure is still pending and then decided."""
    reqs, loops = _graph(5)
    first, second = loops[0], loops[1]
    st = _state()
    _record(tmp_path / "a.mcap", st, reqs[:second], disk_snapshot_at=second)
    sink = Recorder(tmp_path / "b.mcap")
    rep = replay(tmp_path / "a.mcap", sink=sink, from_snapshot=True)
    sink.close()
    assert rep.identical and rep.snapshots_loaded == 1
    rep = replay(tmp_path / "b.mcap", from_snapshot=True)
    assert rep.identical and rep.snapshots_loaded == 1
    got = rep.states["default"]
    assert _status(got, f"r{first}") == "pending"
    got.apply("update", reqs[second], time_ns=0)
    st.apply("update", reqs[second], time_ns=0)
    assert _status(got, f"r{first}") == _status(st, f"r{first}") == "accepted"
    assert got.digest() == st.digest() and got.verdicts == st.verdicts
