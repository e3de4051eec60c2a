"""Exactly-once across every restore path, with real ``mcsm serve`` processes on loopback.

The outside tester's case: updates with ids under the default options (a disk snapshot every
1000 operations), SIGKILL, ``--restore``, more updates, SIGKILL, ``--restore`` again, then
every acknowledged id sent again: each is answered ``duplicate`` with its original seq and
the map's digest does not move. Before the remembered ids were recorded with each snapshot,
2000 of 2504 such resends were applied a second time. The same across a split recording: the
restored server splits its file, is killed, and a third server restores from the set.
"""

from __future__ import annotations

import signal
from pathlib import Path

import numpy as np
from mcsm import wire
from mcsm.log.recset import resolve
from mcsm.log.replay import replay
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 4  # the seqs and ids are what this test is about: cheap samples
WINDOW = 200  # requests in flight per round trip of the pipelined sender


def send_all(c: MapClient, reqs: list[tuple[str, bytes]]) -> list[wire.Ack]:
    """Send ``(id, update payload)`` pipelined (up to WINDOW in flight); every reply an ack."""
    acks: list[wire.Ack] = []
    for i in range(0, len(reqs), WINDOW):
        pending = [c.session.get(c.keys.update, payload=p, timeout=60)
                   for _, p in reqs[i:i + WINDOW]]
        for h in pending:
            replies = list(h)
            assert len(replies) == 1, replies
            r = replies[0]
            assert r.ok is not None, wire.decode_error(r.err.payload.to_bytes())
            acks.append(wire.decode_ack(r.ok.payload.to_bytes()))
    return acks


def updates(rng: np.random.Generator, first: int, count: int) -> list[tuple[str, bytes]]:
    """A chain p{k} -> p{k+1} with ids u{k}."""
    return [(f"u{k}", wire.encode_update(f"u{k}", f"p{k}", f"p{k + 1}",
                                         noisy_at(rng, N, [1.0, 0.0, 0.0])))
            for k in range(first, first + count)]


def kill(d: Daemon) -> None:
    assert d.stop(signal.SIGKILL) != 0


def test_every_acknowledged_id_is_a_duplicate_after_two_sigkill_restores(
        tmp_path: Path, daemons: list[Daemon]) -> None:
    rng = np.random.default_rng(23001)
    sent = updates(rng, 0, 2500)
    d1 = start_daemon(tmp_path, "--samples", str(N), name="d1")  # default options
    daemons.append(d1)
    with MapClient(connect=d1.endpoint, timeout_s=30) as c:
        acks = send_all(c, sent)
        assert [a.seq for a in acks] == list(range(1, 2501)) and not any(a.duplicate for a in acks)
    kill(d1)
    d2 = start_daemon(tmp_path, "--samples", str(N), "--restore", str(d1.record), name="d2")
    daemons.append(d2)
    more = updates(rng, 2500, 700)  # across the restored server's own snapshot at 3000
    with MapClient(connect=d2.endpoint, timeout_s=30) as c:
        dup = send_all(c, sent[::50])
        assert all(a.duplicate for a in dup) and [a.seq for a in dup] == list(range(1, 2501, 50))
        # ids from the snapshot d2 started from (seq 2000) say `restored`: their acks' details
        # are not kept; the inputs replayed after it have their own kinds again
        assert {a.kind for a in dup if a.seq <= 2000} == {"restored"}
        assert {a.kind for a in dup if a.seq > 2000} == {"new_frame"}
        acks = send_all(c, more)
        assert [a.seq for a in acks] == list(range(2501, 3201))
        digest = c.info().digest
    kill(d2)
    d3 = start_daemon(tmp_path, "--samples", str(N), "--restore", str(d2.record), name="d3")
    daemons.append(d3)
    with MapClient(connect=d3.endpoint, timeout_s=30) as c:
        again = send_all(c, sent + more)
        info = c.info()
    applied_twice = [a.request_id for a in again if not a.duplicate]
    assert applied_twice == []
    assert [a.seq for a in again] == list(range(1, 3201))
    assert info.seq == 3200 and info.digest == digest
    assert d3.stop(signal.SIGINT) == 0, d3.log_text()
    rep = replay(d3.record)
    assert rep.identical and rep.states["default"].digest() == digest


def test_exactly_once_across_a_split_recording(tmp_path: Path, daemons: list[Daemon]) -> None:
    """A restored server writes a split recording; killed, a third server restores from the
    set (a directory): every id still a duplicate; the set replays to the live digest and
    each file replays on its own."""
    rng = np.random.default_rng(23002)
    sent = updates(rng, 0, 600)
    d1 = start_daemon(tmp_path, "--samples", str(N), "--disk-snapshot-every", "250", name="d1")
    daemons.append(d1)
    with MapClient(connect=d1.endpoint, timeout_s=30) as c:
        send_all(c, sent)
    kill(d1)
    split = tmp_path / "split"
    d2 = start_daemon(tmp_path, "--samples", str(N), "--disk-snapshot-every", "250",
                      "--restore", str(d1.record), "--split-size", "200K",
                      record=split / "run.mcap", name="d2")
    daemons.append(d2)
    more = updates(rng, 600, 900)
    with MapClient(connect=d2.endpoint, timeout_s=30) as c:
        send_all(c, more)
        digest = c.info().digest
    kill(d2)
    files = resolve([split])
    assert len(files) >= 3 and files[0].name == "run_0000.mcap"
    whole = replay(files)
    assert whole.identical and whole.cut and whole.states["default"].digest() == digest
    for f in files[:-1]:  # each file alone, from its snapshot (the last one is cut)
        alone = replay(f)
        assert alone.identical and alone.complete, (f.name, alone.divergence)
    d3 = start_daemon(tmp_path, "--samples", str(N), "--restore", str(split), name="d3")
    daemons.append(d3)
    with MapClient(connect=d3.endpoint, timeout_s=30) as c:
        again = send_all(c, sent + more)
        info = c.info()
    assert [a.request_id for a in again if not a.duplicate] == []
    assert info.seq == 1500 and info.digest == digest
