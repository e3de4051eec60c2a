"""Hot standbys on the NATS JetStream log (issue 23): SIGKILLed primaries under four client
processes, a late standby catching up from the stream (or from a snapshot when retention
dropped the stream's beginning), exactly-once across takeovers, and a graceful handover.

Every process is real (``nats-server`` x 3, ``mcsm router``, ``mcsm serve``, client
processes), on 127.0.0.1; every wait has a deadline.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

import msgpack
import numpy as np
import pytest
from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_CHECKPOINT
from mcsm.serve.natsrun import NatsCluster
from mcsm.wire import Ack
from mcsm_client.cli import main as client_main
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_router, wait_for
from tests.service.fleet_util import REPO, N, inputs, replicated_server


def _records_valid(path: Path) -> None:
    """Every config, checkpoint and snapshot record of a recording validates against the JSON
    Schema its MCAP channel names (checkpoint reasons ``takeover`` and ``deposed`` included)."""
    from jsonschema import Draft202012Validator
    from mcap.records import Channel, Message, Schema

    schemas: dict[int, Draft202012Validator] = {}
    channels: dict[int, tuple[int, str]] = {}
    seen = 0
    for rec in RecordingReader(path).raw():
        if isinstance(rec, Schema):
            schemas[rec.id] = Draft202012Validator(json.loads(rec.data))
        elif isinstance(rec, Channel):
            channels[rec.id] = (rec.schema_id, rec.topic)
        elif isinstance(rec, Message) and not channels[rec.channel_id][1].startswith("/mcsm/in/"):
            data = msgpack.unpackb(rec.data, raw=False)
            errors = list(schemas[channels[rec.channel_id][0]].iter_errors(data))
            assert errors == [], (path.name, channels[rec.channel_id][1], errors[:1])
            seen += 1
    assert seen > 0


def _took_over_at(log_text: str) -> float:
    """The time (``time.time()``) a server's log says it took over a map."""
    for line in log_text.splitlines():
        if "took over as primary" in line:
            return datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
    raise AssertionError(f"no takeover in the log: {log_text[-2000:]}")


def _takeover_seq(path: Path) -> int | None:
    for item in RecordingReader(path):
        if item.topic == TOPIC_CHECKPOINT and item.data.get("reason") == "takeover":
            return int(item.data["seq"])
    return None


def test_kills_under_four_clients_lose_nothing(tmp_path: Path, daemons: list[Daemon],
                                              nats: NatsCluster) -> None:
    """Three SIGKILLs of the primary at random points under four client processes: every
    acknowledged update is in the final map once, under its acked seq; every recording
    replays identical; each killed primary agrees with the final map up to its successor's
    takeover."""
    router, ep = start_router(tmp_path)
    clients: list[subprocess.Popen[bytes]] = []
    try:
        procs = {"s0": replicated_server(tmp_path, "s0", ep, nats.urls, role="primary")}
        procs["s1"] = replicated_server(tmp_path, "s1", ep, nats.urls)
        daemons += procs.values()
        primary, standby = "s0", "s1"
        watcher = MapClient(map="m", connect=ep, timeout_s=30.0)
        wait_for("the standby consumes", lambda: len(watcher.info().standbys) == 1)
        n_clients, count = 4, 60
        for i in range(n_clients):
            clients.append(subprocess.Popen(
                [sys.executable, "-m", "tests.service.fleet_client", ep, "m", str(i),
                 str(count), str(N), str(tmp_path / f"acks{i}.txt")], cwd=REPO,
                stderr=open(tmp_path / f"client{i}.log", "w"),  # noqa: SIM115
                env=dict(os.environ, PYTHONUNBUFFERED="1")))
        rng = np.random.default_rng(20261123)
        succession: list[tuple[str, str]] = []  # (killed, the standby that took over)
        for kill in range(3):
            target = min(watcher.info().seq + int(rng.integers(5, 25)),
                         n_clients * (count + count // 10) - 10 * (3 - kill))
            wait_for(f"seq {target} before kill {kill}", lambda t=target: watcher.info().seq >= t)
            old_id = watcher.info().server_id
            procs[primary].proc.send_signal(signal.SIGKILL)
            procs[primary].proc.wait(timeout=30)
            wait_for(f"takeover {kill}", lambda o=old_id: watcher.info().server_id != o)
            succession.append((primary, standby))
            new = f"s{kill + 2}"  # the killed server comes back as a standby (a new process)
            procs[new] = replicated_server(tmp_path, new, ep, nats.urls)
            daemons.append(procs[new])
            primary, standby = standby, new
        for i, c in enumerate(clients):
            assert c.wait(timeout=240) == 0, (tmp_path / f"client{i}.log").read_text()[-3000:]
        final = watcher.info()
        wait_for("the last standby holds the head",
                 lambda: list(watcher.info().standbys.values()) == [final.seq], 30.0)
        watcher.close()
        assert procs[primary].stop() == 0
        assert procs[standby].stop() == 0
    finally:
        for c in clients:
            if c.poll() is None:
                c.kill()
        router.stop(signal.SIGKILL)
    acks: dict[str, int] = {}
    for i in range(n_clients):
        for line in (tmp_path / f"acks{i}.txt").read_text().splitlines():
            rid, seq, _server = line.split()
            assert rid not in acks
            acks[rid] = int(seq)
    assert len(acks) == n_clients * (count + count // 10)
    recorded = inputs(procs[primary].record)
    assert sorted(recorded) == list(range(1, final.seq + 1))  # seqs 1..seq, each once
    by_id = {rid: seq for seq, rid in recorded.items()}
    assert len(by_id) == len(recorded), "an input was applied twice"
    assert by_id == acks, "an acknowledged update is lost, or applied under another seq"
    assert replay(procs[primary].record).final_digests()["m"] == final.digest
    assert inputs(procs[standby].record) == recorded  # the last standby holds all of it
    for name, d in procs.items():
        r = replay(d.record)
        assert r.divergence is None, f"{name}: {r.divergence}"
        _records_valid(d.record)
    for killed, successor in succession:
        t = _takeover_seq(procs[successor].record)
        assert t is not None
        mine = inputs(procs[killed].record)
        assert all(recorded[s] == rid for s, rid in mine.items())  # never a forked input
        assert max(mine, default=0) <= t


@pytest.mark.parametrize("start", ["stream", "snapshot"])
def test_late_standby_catches_up_and_keeps_every_id(tmp_path: Path, daemons: list[Daemon],
                                                    nats: NatsCluster, start: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A standby started after 30 updates catches up from the stream (``stream``), or, when
    retention dropped the stream's beginning (``--log-max-bytes``), from the latest snapshot
    in the object store plus the stream after it (``snapshot``). The primary is SIGKILLed;
    the late standby takes over, and a resend of every acknowledged request id is answered
    as a duplicate under its original seq, the digest unchanged (exactly-once across the
    catch-up and the takeover)."""
    router, ep = start_router(tmp_path)
    extra = ["--log-max-bytes", "40000", "--disk-snapshot-every", "10"] \
        if start == "snapshot" else []
    try:
        p = replicated_server(tmp_path, "p", ep, nats.urls, *extra, role="primary")
        daemons.append(p)
        rng = np.random.default_rng(7)
        sent: list[tuple[str, str, np.ndarray, str]] = []
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            acks = {}
            for k in range(40):
                sent.append((f"r/{k}", f"r/{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]),
                             f"id{k}"))
                a, b, x, rid = sent[-1]
                acks[rid] = c.update(a, b, x, request_id=rid).seq
            s = replicated_server(tmp_path, "s", ep, nats.urls)
            daemons.append(s)
            wait_for("the standby consumes", lambda: len(c.info().standbys) == 1)
            assert client_main(["servers", "--json", "--connect", ep]) == 0
            rows = json.loads(capsys.readouterr().out)["servers"]
            assert sorted(r["role"] for r in rows if r["map"] == "m") == ["primary", "standby"]
            info = c.info()
            wait_for("the standby holds the head",
                     lambda: min(c.info().standbys.values()) >= info.seq)
            p.proc.send_signal(signal.SIGKILL)
            p.proc.wait(timeout=30)
            again = [c.update(a, b, x, request_id=rid) for a, b, x, rid in sent]
            assert all(g.duplicate for g in again)
            assert {g.request_id: g.seq for g in again} == acks
            after = c.info()
            assert after.server_id != info.server_id and after.digest == info.digest
            assert after.seq == info.seq == 40 and after.epoch > info.epoch
        assert s.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    rep = replay(s.record)
    assert rep.divergence is None and rep.final_digests()["m"] == info.digest
    assert rep.snapshots_loaded == (1 if start == "snapshot" else 0)
    snap = [cp.seq for cp in rep.checkpoints if cp.reason == "snapshot"]
    first = 1 if start == "stream" else snap[0] + 1  # the inputs it applied from the stream
    assert min(inputs(s.record), default=info.seq + 1) == first


@pytest.mark.parametrize("send", ["after", "with"])
def test_a_stopped_primary_hands_over_at_once(tmp_path: Path, daemons: list[Daemon],
                                              nats: NatsCluster, send: str) -> None:
    """SIGINT: the primary answers what it queued, releases its lease, and the standby
    serves within a second (no lease expiry to wait for); a ``--map`` server started while
    the map's lease is held refuses (exit 2) and names ``--standby-of``. The next update is
    sent after the signal, or with it: sent to the primary while it is stopped (SIGSTOP,
    for 0.3 s: well within its lease), which gets it and the SIGINT as it resumes."""
    router, ep = start_router(tmp_path)
    try:
        p = replicated_server(tmp_path, "p", ep, nats.urls, role="primary")
        s = replicated_server(tmp_path, "s", ep, nats.urls)
        daemons += [p, s]
        rng = np.random.default_rng(11)
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            for k in range(5):
                c.update(f"r/{k}", f"r/{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]))
            p_id = c.info().server_id
            wait_for("the standby holds the head", lambda: c.info().standbys == {
                next(iter(c.info().standbys or {"": 0})): 5})
            second = subprocess.run(
                [sys.executable, "-m", "mcsm.cli", "serve", "--samples", str(N), "--map", "m",
                 "--connect", ep, "--nats", ",".join(nats.urls), "--record",
                 str(tmp_path / "x.mcap")], cwd=tmp_path, capture_output=True, text=True,
                timeout=60)
            assert second.returncode == 2 and "--standby-of m" in second.stderr
            assert "holds the map's lease" in second.stderr  # the lease refuses, not a token
            x = noisy_at(rng, N, [1.0, 0.0, 0.0])
            acks: list[Ack] = []
            th = threading.Thread(target=lambda: acks.append(c.update("r/5", "r/6", x)))
            if send == "with":
                p.proc.send_signal(signal.SIGSTOP)
                th.start()
                time.sleep(0.3)
            t0 = time.time()
            p.proc.send_signal(signal.SIGINT)
            if send == "with":
                p.proc.send_signal(signal.SIGCONT)
            else:
                th.start()
            th.join(timeout=60)
            ack, = acks
            assert ack.seq == 6
            assert p.proc.wait(timeout=30) == 0
            # the standby took over well before an unreleased lease could expire (5/6 of the
            # TTL after the last renewal: 1.7 s); the client may take up to 1 s more to see
            # the new primary's token (its liveliness query)
            wait_for("the standby took over", lambda: "took over as primary" in s.log_text())
            took = _took_over_at(s.log_text()) - t0
            assert 0 < took < 1.0, took
        assert s.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    _check_handover(inputs(p.record), inputs(s.record), ack, p_id)


def _check_handover(mine: dict[int, str], theirs: dict[int, str], ack: Ack,
                    p_id: str) -> None:
    """The update sent about the SIGINT reached the primary before it stopped taking requests
    (then the primary applied and answered it) or after (the standby applied it once it took
    over); either way one history holds it once, as seq 6, and its first answer came from
    the server that applied it."""
    assert theirs == {**mine, 6: ack.request_id}
    assert sorted(mine) == list(range(1, 7 if 6 in mine else 6))
    assert (ack.server == p_id) == (6 in mine) and not ack.duplicate


def test_a_primary_without_quorum_rebuilds_from_its_split_recording(
        tmp_path: Path, daemons: list[Daemon], nats: NatsCluster) -> None:
    """Two of the three NATS nodes stop: the primary's next append cannot be stored, so that
    update is not acknowledged, the server stops serving and rebuilds the map from its own
    recording, here a split one (``--split-size``: the rebuild reads the set of files). When
    the nodes are back it takes the lease again and the same request is applied once, as the
    next seq (also when the log kept the refused append: the retry is then its duplicate);
    the set of files replays to the served digest and holds each request once."""
    from mcsm.errors import McsmError
    from mcsm.log.recset import resolve

    router, ep = start_router(tmp_path)
    rng = np.random.default_rng(2311)
    try:
        p = replicated_server(tmp_path, "p", ep, nats.urls, "--split-size", "20000",
                              role="primary")
        daemons.append(p)
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            for k in range(30):
                c.update(f"r/{k}", f"r/{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]),
                         request_id=f"id{k}")
            nats.stop_node(1)
            nats.stop_node(2)
            x = noisy_at(rng, N, [1.0, 0.0, 0.0])
            with pytest.raises(McsmError):  # NotReplicated, then no server until it rebuilt
                c.update("r/30", "r/31", x, request_id="id30", timeout_s=4.0)
            wait_for("the rebuild", lambda: "rebuilt from the recording at seq 30"
                     in p.log_text(), 30.0)
            nats.start_node(1)
            nats.start_node(2)
            ack = c.update("r/30", "r/31", x, request_id="id30", timeout_s=60.0)
            # the lone node may have kept the refused append and committed it once the quorum
            # was back (the rebuilt server then applied it from the log, and the retry is its
            # duplicate): either way it is applied once, as seq 31
            assert ack.seq == 31
            info = c.info()
        assert p.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    files = resolve([str(tmp_path / "p_*.mcap")])
    assert len(files) >= 3, files
    rep = replay(files)
    assert rep.divergence is None and rep.final_digests()["m"] == info.digest
    recorded: dict[int, str] = {}
    for f in files:
        recorded.update(inputs(f))
    assert recorded == {k + 1: f"id{k}" for k in range(31)}
