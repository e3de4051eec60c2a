"""The shipped secure fleet (``deploy/<variant>/router.json5`` and the server identities
``server1.json5``, ``server2.json5``): a router with deny-by-default access control, a primary
and a hot standby joined to it with their own credentials, clients with the role configs of the
single-server deployment. Real ``mcsm router`` and ``mcsm serve`` subprocesses, secrets made at
test time by ``deploy/make_secrets.py``, everything on 127.0.0.1, every wait bounded.

Both variants (user/password over TCP, mutual TLS): replication and a takeover through the
secured router; no client identity can push into a standby, read the primary's catch-up log or
pose as a standby or a server; a session without valid credentials cannot connect.
"""

from __future__ import annotations

import json
import signal
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcsm import wire
from mcsm.connect import client_config
from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_OPS
from mcsm_client.client import MapClient
from mcsm_client.process import McsmProcess

from tests.security.test_deploy import _open_fails, make_secrets
from tests.service.daemon_util import Daemon, free_port, noisy_at, start_daemon, wait_for

N = 32
DENIED_S = 1.0  # how long a denied get waits for a reply that never comes
CLIENTS = ("robot1", "viewer", "admin")


@dataclass
class Fleet:
    variant: str
    dir: Path
    endpoint: str
    router: McsmProcess
    servers: dict[str, Daemon]

    def conf(self, ident: str) -> Path:
        return self.dir / f"{ident}.json5"

    def client(self, ident: str, map: str = "m", **kw: Any) -> MapClient:
        kw.setdefault("timeout_s", 15.0)
        return MapClient(map=map, connect=self.endpoint, zenoh_config=self.conf(ident), **kw)

    def session(self, ident: str) -> zenoh.Session:
        return zenoh.open(client_config(self.endpoint, self.conf(ident)))

    def serve(self, work: Path, ident: str, name: str, *args: str) -> Daemon:
        """``mcsm serve`` as server identity ``ident`` joined to the router."""
        d = start_daemon(work, "--zenoh-config", str(self.conf(ident)), "--samples", str(N),
                         "--connect", self.endpoint, *args, name=name, endpoint="-")
        self.servers[name] = d
        return d

    def restart_router(self) -> None:
        """Stop the router (SIGINT) and start it again on the same endpoint."""
        self.router.stop()
        assert self.router.log_path is not None
        self.router = McsmProcess(self.router.cmd[3:], ready="routing on",
                                  log_path=self.router.log_path.with_suffix(".2.log"),
                                  cwd=self.router.cwd, ready_timeout_s=30.0).start()

    def stop(self) -> None:
        for d in self.servers.values():
            d.stop(signal.SIGKILL)
        self.router.stop()


@pytest.fixture(scope="module")
def secrets_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fleet-secrets")
    make_secrets(out)
    return out


def start_fleet(secrets: Path, variant: str, work: Path) -> Fleet:
    """The router of ``variant`` on a free loopback port, with no server yet."""
    d = secrets / variant
    proto = "tcp" if variant == "usrpwd" else "tls"
    port = free_port()
    router = McsmProcess(["router", "--zenoh-config", str(d / "router.json5"), "--listen",
                          f"{proto}/127.0.0.1:{port}"], ready="routing on",
                         log_path=work / "router.log", cwd=work, ready_timeout_s=30.0)
    router.start()
    # mtls: the router's certificate names localhost and 127.0.0.1 (make_secrets.py)
    return Fleet(variant, d, f"{proto}/127.0.0.1:{port}", router, {})


def _inputs(path: Path) -> dict[int, str]:
    """seq -> request id of every input of map ``m`` in a recording."""
    return {int(item.data["seq"]): str(item.data["id"]) for item in RecordingReader(path)
            if item.topic in TOPIC_OPS and item.data.get("map") == "m"}


@pytest.fixture(scope="module", params=["usrpwd", "mtls"])
def fleet(request: pytest.FixtureRequest, secrets_dir: Path,
          tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    """A primary (server1, ``--sync-standbys 1``) and its standby (server2) of map ``m``."""
    work = tmp_path_factory.mktemp(f"fleet-{request.param}")
    f = start_fleet(secrets_dir, request.param, work)
    try:
        f.serve(work, "server1", "primary", "--map", "m", "--sync-standbys", "1")
        f.serve(work, "server2", "standby", "--standby-of", "m")
        with f.client("viewer") as v:
            wait_for("the standby joins", lambda: len(v.info().standbys) == 1)
        yield f
    finally:
        f.stop()


def _standby_seq(f: Fleet) -> int:
    """The standby's seq, asked on its queryable by a server identity (as the primary does)."""
    s = f.session("server2")
    try:
        replies = [r for r in s.get("mcsm/m/@standby/*", payload=wire.pack(
            {"v": wire.VERSION, "t": "status"}), timeout=5.0) if r.ok is not None]
    finally:
        s.close()
    assert len(replies) == 1
    return int(wire.unpack(replies[0].ok.payload.to_bytes())["seq"])


@pytest.mark.parametrize("variant", ["usrpwd", "mtls"])
def test_secured_fleet_replicates_and_a_standby_takes_over(secrets_dir: Path, tmp_path: Path,
                                                           variant: str) -> None:
    """Through the secured router (both variants): every acknowledged update of a robot is on the
    primary and its synchronous standby; the primary is SIGKILLed, the standby takes over, the
    old primary's identity comes back as the new standby, and the robot goes on with the same
    credentials: nothing lost or doubled, both recordings replay identical."""
    f = start_fleet(secrets_dir, variant, tmp_path)
    rng = np.random.default_rng(1801)
    try:
        p = f.serve(tmp_path, "server1", "p", "--map", "m", "--sync-standbys", "1")
        s = f.serve(tmp_path, "server2", "s", "--standby-of", "m")
        with f.client("robot1", namespace="robot1", timeout_s=30.0) as robot:
            wait_for("the standby joins", lambda: len(robot.info().standbys) == 1)
            xs = [noisy_at(rng, N, [1, 0, 0]) for _ in range(20)]
            acks = [robot.update(f"robot1/p{i}", f"robot1/p{i + 1}", xs[i], request_id=f"r{i}")
                    for i in range(10)]
            assert [a.seq for a in acks] == list(range(1, 11))
            before = robot.info()
            assert list(before.standbys.values()) == [10]  # the standby holds all 10
            p.proc.send_signal(signal.SIGKILL)
            p.proc.wait(timeout=10)
            wait_for("the standby takes over", lambda: robot.info().server_id != before.server_id)
            # K = 1 is kept: the new primary acknowledges once a standby holds the update
            p2 = f.serve(tmp_path, "server1", "p2", "--standby-of", "m")
            acks += [robot.update(f"robot1/p{i}", f"robot1/p{i + 1}", xs[i], request_id=f"r{i}")
                     for i in range(10, 20)]
            again = robot.update("robot1/p0", "robot1/p1", xs[0], request_id="r0")
            after = robot.info()
        assert again.duplicate and again.seq == 1
        assert [a.seq for a in acks] == list(range(1, 21))
        assert all(a.server == before.server_id for a in acks[:10])
        assert all(a.server == after.server_id != before.server_id for a in acks[10:])
        assert after.seq == 20 and list(after.standbys.values()) == [20]
        assert p2.stop() == 0 and s.stop() == 0  # the standby first: it would take over
    finally:
        f.stop()
    ids = {a.seq: f"r{a.seq - 1}" for a in acks}
    assert _inputs(p.record) == {k: v for k, v in ids.items() if k <= 10}
    assert _inputs(s.record) == ids
    assert _inputs(p2.record) == ids
    for d in (s, p2):
        rep = replay(d.record)
        assert rep.divergence is None and rep.final_digests()["m"] == after.digest


def test_router_restart_with_the_standbys_stopped(secrets_dir: Path, tmp_path: Path) -> None:
    """The procedure docs/fleet.md gives for changing the router's rules (a restart): stop the
    standbys, restart the router, start them again. The primary keeps the map (one server
    claims it), the robot goes on with the same client, the new standby catches up."""
    f = start_fleet(secrets_dir, "usrpwd", tmp_path)
    rng = np.random.default_rng(1804)
    try:
        p = f.serve(tmp_path, "server1", "p", "--map", "m", "--sync-standbys", "1")
        s = f.serve(tmp_path, "server2", "s", "--standby-of", "m")
        with f.client("robot1", namespace="robot1", timeout_s=30.0) as robot:
            wait_for("the standby joins", lambda: len(robot.info().standbys) == 1)
            acks = [robot.update(f"robot1/p{i}", f"robot1/p{i + 1}", noisy_at(rng, N, [1, 0, 0]))
                    for i in range(5)]
            assert s.stop() == 0
            f.restart_router()
            s2 = f.serve(tmp_path, "server2", "s2", "--standby-of", "m")
            acks += [robot.update(f"robot1/p{i}", f"robot1/p{i + 1}",
                                  noisy_at(rng, N, [1, 0, 0])) for i in range(5, 10)]
            info = robot.info()
            assert robot.servers() == [info.server_id]
        assert [a.seq for a in acks] == list(range(1, 11))
        assert {a.server for a in acks} == {info.server_id}
        assert list(info.standbys.values()) == [10]
        assert s2.stop() == 0 and p.stop() == 0
    finally:
        f.stop()
    assert replay(s2.record).final_digests()["m"] == info.digest


@pytest.mark.parametrize("ident", CLIENTS)
def test_clients_cannot_push_into_a_standby_or_read_the_log(fleet: Fleet, ident: str) -> None:
    """A well-formed push (the next seq, naming the live primary as its sender: the standby
    would apply it) and a status request on ``mcsm/m/@standby/*``, and a catch-up request on
    ``mcsm/m/@log``, sent with each client identity: no reply, the standby's seq unchanged and
    it still follows the primary. The same status and log requests with a server identity are
    answered (the keys are served; only the identity differs)."""
    rng = np.random.default_rng(1802)
    with fleet.client("admin") as admin:
        admin.update(f"{ident}/a", f"{ident}/b", noisy_at(rng, N, [1, 0, 0]))
        info = admin.info()
        assert _standby_seq(fleet) == info.seq
        forged = {"v": wire.VERSION, "t": "push", "primary": info.server_id, "entry": {
            "seq": info.seq + 1, "op": "update", "recv_ns": time.time_ns(), "sender": ident,
            "id": f"forged-{ident}", "digest": None, "request": wire.encode_update(
                f"forged-{ident}", f"{ident}/b", f"{ident}/c", noisy_at(rng, N, [1, 0, 0]))}}
        requests = [("mcsm/m/@standby/*", wire.pack(forged)),
                    (f"mcsm/m/@standby/{next(iter(info.standbys))}", wire.pack(forged)),
                    ("mcsm/m/@standby/*", wire.pack({"v": wire.VERSION, "t": "status"})),
                    ("mcsm/m/@log", wire.pack({"v": wire.VERSION, "from": 0})),
                    ("mcsm/m/@log", wire.pack({"v": wire.VERSION, "snapshot": [0, 0]}))]
        s = fleet.session(ident)
        seen: list[str] = []
        try:
            for key, payload in requests:
                assert list(s.get(key, payload=payload, timeout=DENIED_S)) == [], (ident, key)
            # nor can it watch the standbys' tokens
            sub = s.liveliness().declare_subscriber("mcsm/m/@standby/*",
                                                    lambda smp: seen.append(str(smp.key_expr)),
                                                    history=True)
            assert list(s.liveliness().get("mcsm/m/@standby/*", timeout=DENIED_S)) == []
            sub.undeclare()
        finally:
            s.close()
        assert seen == []
        srv = fleet.session("server2")
        try:
            for key, payload in requests[2:4]:
                replies = list(srv.get(key, payload=payload, timeout=5.0))
                assert len(replies) == 1 and replies[0].ok is not None, key
            assert len(list(srv.liveliness().get("mcsm/m/@standby/*", timeout=5.0))) == 1
            # a server identity is no client: its requests on the map's keys are denied
            assert list(srv.get("mcsm/m/info", payload=wire.pack({"v": wire.VERSION}),
                                timeout=DENIED_S)) == []
        finally:
            srv.close()
        assert _standby_seq(fleet) == info.seq
        ack = admin.update(f"{ident}/b", f"{ident}/c", noisy_at(rng, N, [1, 0, 0]))
        assert ack.seq == info.seq + 1 and not ack.duplicate  # the seq the forgery aimed at
        assert admin.info().standbys == {next(iter(info.standbys)): ack.seq}
        assert _standby_seq(fleet) == ack.seq


@pytest.mark.parametrize("ident", CLIENTS)
def test_clients_cannot_pose_as_a_standby_or_a_server(fleet: Fleet, ident: str) -> None:
    """A client identity declares a queryable and a liveliness token on
    ``mcsm/m/@standby/<its zid>`` (where the primary would push every input) and on the map's
    own keys: the router drops them, so the primary counts one standby, pushes nothing to the
    rogue, and clients see one server; a synchronous update is acknowledged as before."""
    rng = np.random.default_rng(1803)
    rogue = fleet.session(ident)
    got: list[str] = []

    def answer(q: zenoh.Query) -> None:
        got.append(str(q.key_expr))
        q.reply(q.key_expr, wire.pack({"v": wire.VERSION, "zid": str(rogue.zid()), "seq": 10**6}))

    zid = str(rogue.zid())
    entities = [rogue.declare_queryable(f"mcsm/m/@standby/{zid}", answer, complete=True),
                rogue.liveliness().declare_token(f"mcsm/m/@standby/{zid}"),
                rogue.declare_queryable("mcsm/m/**", answer, complete=True),
                rogue.liveliness().declare_token(f"mcsm/m/alive/{zid}")]
    try:
        with fleet.client("robot1", namespace="robot1") as r1:
            real = r1.info()
            for i in range(3):
                ack = r1.update(f"robot1/{ident}{i}", f"robot1/{ident}{i + 1}",
                                noisy_at(rng, N, [1, 0, 0]))
                assert ack.server == real.server_id
            after = r1.info()
            assert r1.servers() == [real.server_id] and r1.foreign_replies == 0
        assert set(after.standbys) == set(real.standbys) and zid not in after.standbys
        assert after.standbys[next(iter(real.standbys))] == after.seq
        assert got == []
    finally:
        for e in entities:
            e.undeclare()
        rogue.close()


def test_sessions_without_valid_credentials_cannot_join_the_fleet(fleet: Fleet,
                                                                  tmp_path: Path) -> None:
    """No credentials, a wrong password, an unknown user (usrpwd); plain TCP to the TLS port,
    no client certificate (mtls): the session does not open, so it can neither reach the map
    nor the replication keys."""
    bad: list[zenoh.Config] = [client_config(fleet.endpoint)]  # the loopback defaults
    if fleet.variant == "usrpwd":
        text = fleet.conf("server1").read_text()
        password = json.loads(text[text.index("{"):])["transport"]["auth"]["usrpwd"]["password"]
        wrong = tmp_path / "wrong.json5"
        wrong.write_text(text.replace(password, password[::-1]))
        unknown = tmp_path / "unknown.json5"
        unknown.write_text(text.replace('"server1"', '"server9"'))
        bad += [client_config(fleet.endpoint, wrong), client_config(fleet.endpoint, unknown)]
    else:
        bad.append(client_config(fleet.endpoint.replace("tls/", "tcp/"), fleet.conf("server1")))
        nocert = {"mode": "client", "scouting": {"multicast": {"enabled": False}},
                  "transport": {"link": {"tls": {
                      "root_ca_certificate": str(fleet.dir / "certs" / "ca.pem")}}}}
        bad.append(client_config(fleet.endpoint, nocert))
    for conf in bad:
        assert _open_fails(conf)
    with fleet.client("viewer") as v:
        assert len(v.info().standbys) == 1
