"""Hot standbys (issue 18): a primary, synchronous standbys, takeovers, late standbys.

Every process is real (``mcsm router``, ``mcsm serve`` subprocesses, client processes), on
127.0.0.1 behind one router; every wait has a deadline.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import msgpack
import numpy as np
import pytest
from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_CHECKPOINT, TOPIC_OPS
from mcsm_client.cli import main as client_main
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon, start_router, wait_for

N = 32
REPO = Path(__file__).resolve().parents[2]


def _inputs(path: Path) -> dict[int, str]:
    """seq -> request id of every input of map ``m`` in a recording (cut files too)."""
    out: dict[int, str] = {}
    for item in RecordingReader(path):
        if item.topic in TOPIC_OPS and item.data.get("map") == "m":
            seq = int(item.data["seq"])
            assert seq not in out, f"{path.name}: seq {seq} recorded twice"
            out[seq] = str(item.data["id"])
    return out


def _records_valid(path: Path) -> None:
    """Every config, checkpoint and snapshot record of a recording validates against the JSON
    Schema its MCAP channel names (checkpoint reasons ``takeover`` and ``deposed`` included;
    input records carry msgpack bytes, which JSON Schema cannot type)."""
    from jsonschema import Draft202012Validator
    from mcap.records import Channel, Message, Schema

    schemas: dict[int, Draft202012Validator] = {}
    channels: dict[int, tuple[int, str]] = {}
    seen = 0
    for rec in RecordingReader(path).raw():  # cut files too: up to the cut
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


def _takeover_seq(path: Path) -> int | None:
    for item in RecordingReader(path):
        if item.topic == TOPIC_CHECKPOINT and item.data.get("reason") == "takeover":
            return int(item.data["seq"])
    return None


def _standby(tmp: Path, ep: str, name: str, *extra: str) -> Daemon:
    return start_daemon(tmp, "--samples", str(N), "--standby-of", "m", "--connect", ep,
                        *extra, name=name, endpoint="-")


def test_sync_standby_loses_nothing_over_three_kills(tmp_path: Path,
                                                    daemons: list[Daemon]) -> None:
    router, ep = start_router(tmp_path)
    clients: list[subprocess.Popen[bytes]] = []
    try:
        procs = {"s0": start_daemon(tmp_path, "--samples", str(N), "--map", "m", "--connect",
                                    ep, "--sync-standbys", "1", name="s0", endpoint="-")}
        daemons.append(procs["s0"])
        procs["s1"] = _standby(tmp_path, ep, "s1")
        daemons.append(procs["s1"])
        primary, standby = "s0", "s1"
        watcher = MapClient(map="m", connect=ep, timeout_s=30.0)
        wait_for("the standby joins", lambda: len(watcher.info().standbys) == 1)
        n_clients, count = 4, 40
        for i in range(n_clients):
            clients.append(subprocess.Popen(
                [sys.executable, "-m", "tests.service.fleet_client", ep, "m", str(i),
                 str(count), str(N), str(tmp_path / f"acks{i}.txt")], cwd=REPO,
                stderr=open(tmp_path / f"client{i}.log", "w"),  # noqa: SIM115
                env=dict(os.environ, PYTHONUNBUFFERED="1")))
        rng = np.random.default_rng(20261123)
        succession: list[tuple[str, str]] = []  # (killed, the standby that took over)
        for kill in range(3):
            target = watcher.info().seq + int(rng.integers(5, 30))
            wait_for(f"seq {target} before kill {kill}", lambda t=target: watcher.info().seq >= t)
            old_id = watcher.info().server_id
            procs[primary].proc.send_signal(signal.SIGKILL)
            procs[primary].proc.wait(timeout=30)
            wait_for(f"takeover {kill}", lambda o=old_id: watcher.info().server_id != o)
            succession.append((primary, standby))
            # the killed server comes back as a standby (a new process and recording)
            new = f"s{kill + 2}"
            procs[new] = _standby(tmp_path, ep, new)
            daemons.append(procs[new])
            primary, standby = standby, new
            wait_for("the new standby joins", lambda: len(watcher.info().standbys) == 1)
        for i, c in enumerate(clients):
            assert c.wait(timeout=240) == 0, (tmp_path / f"client{i}.log").read_text()[-3000:]
        final = watcher.info()
        watcher.close()
        assert procs[standby].stop() == 0  # first, or it would take over from the primary
        assert procs[primary].stop() == 0
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
    recorded = _inputs(procs[primary].record)
    assert sorted(recorded) == list(range(1, final.seq + 1))  # seqs 1..seq, each once
    by_id = {rid: seq for seq, rid in recorded.items()}
    assert len(by_id) == len(recorded), "an input was applied twice"
    assert by_id == acks, "an acknowledged update is lost, or applied under another seq"
    rep = replay(procs[primary].record)
    assert rep.divergence is None and rep.final_digests()["m"] == final.digest
    # every recording replays identical; each killed primary agrees with the final map up to
    # the seq its successor took over at (beyond it lie inputs it never acknowledged)
    for name, d in procs.items():
        r = replay(d.record)
        assert r.divergence is None, f"{name}: {r.divergence}"
        _records_valid(d.record)
    for killed, successor in succession:
        t = _takeover_seq(procs[successor].record)
        assert t is not None
        mine = _inputs(procs[killed].record)
        assert {s: mine[s] for s in mine if s <= t} == \
            {s: recorded[s] for s in recorded if s <= t and s >= min(mine, default=1)}


@pytest.mark.parametrize("repl_log", ["5", "2000"], ids=["snapshot", "log"])
def test_late_standby_catches_up(tmp_path: Path, daemons: list[Daemon], repl_log: str,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    router, ep = start_router(tmp_path)
    try:
        p = start_daemon(tmp_path, "--samples", str(N), "--map", "m", "--connect", ep,
                         "--repl-log", repl_log, name="p", endpoint="-")
        daemons.append(p)
        rng = np.random.default_rng(7)
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            x0 = noisy_at(rng, N, [1.0, 0.0, 0.0])
            first = c.update("r/0", "r/1", x0, request_id="first")
            for k in range(1, 30):
                c.update(f"r/{k}", f"r/{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]))
            s = _standby(tmp_path, ep, "s")
            daemons.append(s)
            wait_for("the standby joins", lambda: len(c.info().standbys) == 1)
            assert client_main(["servers", "--json", "--connect", ep]) == 0
            rows = json.loads(capsys.readouterr().out)["servers"]
            assert sorted(r["role"] for r in rows if r["map"] == "m") == ["primary", "standby"]
            for k in range(30, 35):
                c.update(f"r/{k}", f"r/{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]))
            info = c.info()
            wait_for("the standby confirms the head",
                  lambda: c.info().standbys and min(c.info().standbys.values()) >= info.seq)
            # the standby takes over and still knows a request id applied before it came
            p.proc.send_signal(signal.SIGKILL)
            p.proc.wait(timeout=30)
            again = c.update("r/0", "r/1", x0, request_id="first")
            assert again.duplicate and again.seq == first.seq
            after = c.info()
            assert after.server_id != info.server_id and after.digest == info.digest
        assert s.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    rep = replay(s.record)
    assert rep.divergence is None and rep.final_digests()["m"] == info.digest
    assert rep.snapshots_loaded == (1 if repl_log == "5" else 0)


def _primaries(ep: str) -> list[str]:
    with MapClient(map="m", connect=ep, timeout_s=5.0) as c:
        return c.servers(timeout_s=1.0)


def test_a_router_restart_does_not_split_the_map(tmp_path: Path,
                                                 daemons: list[Daemon]) -> None:
    """Both servers lose the router at once: the standby sees the primary's token go, but it
    reaches nobody, so it does not take over; once the router is back it follows again."""
    router, ep = start_router(tmp_path)
    try:
        p = start_daemon(tmp_path, "--samples", str(N), "--map", "m", "--connect", ep,
                         name="p", endpoint="-")
        daemons.append(p)
        s = _standby(tmp_path, ep, "s")
        daemons.append(s)
        rng = np.random.default_rng(3)
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            wait_for("the standby joins", lambda: len(c.info().standbys) == 1)
            for k in range(5):
                c.update(f"r/{k}", f"r/{k + 1}", noisy_at(rng, N, [1.0, 0.0, 0.0]))
            primary = c.info().server_id
        router.stop(signal.SIGKILL)
        wait_for("the standby notices", lambda: "reaches no router" in s.log_text(), 20.0)
        router, _ = start_router(tmp_path, endpoint=ep)
        with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
            wait_for("the standby follows again", lambda: len(c.info().standbys) == 1, 60.0)
            assert _primaries(ep) == [primary]
            for k in range(5, 10):
                assert c.update(f"r/{k}", f"r/{k + 1}",
                                noisy_at(rng, N, [1.0, 0.0, 0.0])).server == primary
            info = c.info()
        assert "took over" not in s.log_text()
        assert s.stop() == 0 and p.stop() == 0
    finally:
        router.stop(signal.SIGKILL)
    for d in (p, s):
        rep = replay(d.record)
        assert rep.divergence is None and rep.final_digests()["m"] == info.digest


def test_two_primaries_that_meet_leave_one(tmp_path: Path, daemons: list[Daemon]) -> None:
    """Two servers of map ``m`` on two separate networks (as after a standby took over from a
    primary that was cut off), then a router joins the networks: the one with the lower epoch,
    here the larger id, steps down and exits 7; the other serves on."""
    ra, ea = start_router(tmp_path)
    rb, eb = start_router(tmp_path)
    bridge = None
    try:
        a = start_daemon(tmp_path, "--samples", str(N), "--map", "m", "--connect", ea,
                         name="a", endpoint="-")
        daemons.append(a)
        b = start_daemon(tmp_path, "--samples", str(N), "--map", "m", "--connect", eb,
                         name="b", endpoint="-")
        daemons.append(b)
        ids = {}
        for name, ep in (("a", ea), ("b", eb)):
            with MapClient(map="m", connect=ep, timeout_s=30.0) as c:
                ids[name] = c.info().server_id
        conf = tmp_path / "bridge.json5"
        conf.write_text(json.dumps({
            "mode": "router", "connect": {"endpoints": [ea, eb]},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
        bridge, _ = start_router(tmp_path, "--zenoh-config", str(conf))
        loser = "a" if ids["a"] > ids["b"] else "b"
        winner = "b" if loser == "a" else "a"
        procs = {"a": a, "b": b}
        assert procs[loser].proc.wait(timeout=60) == 7
        assert "stepping down" in procs[loser].log_text()
        _records_valid(procs[loser].record)  # its last checkpoint says "deposed"
        assert any(r.topic == TOPIC_CHECKPOINT and r.data.get("reason") == "deposed"
                   for r in RecordingReader(procs[loser].record))
        assert procs[winner].proc.poll() is None
        for ep in (ea, eb):
            wait_for("one primary", lambda e=ep: _primaries(e) == [ids[winner]], 30.0)
    finally:
        for r in (ra, rb, bridge):
            if r is not None:
                r.stop(signal.SIGKILL)
