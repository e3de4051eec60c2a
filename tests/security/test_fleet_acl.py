"""The shipped secure fleet (``deploy/<variant>/router.json5``, the server identities
``server1.json5``, ``server2.json5`` and their NATS users ``serverK.nats.json`` in
``nats-auth.conf``): a router with deny-by-default access control, a three-node NATS
JetStream cluster with user/password authentication, a primary and a hot standby joined to
both with their own credentials, clients with the role configs of the single-server
deployment. Real ``nats-server``, ``mcsm router`` and ``mcsm serve`` subprocesses, secrets
made at test time by ``deploy/make_secrets.py``, everything on 127.0.0.1, every wait bounded.

Both variants (user/password over TCP, mutual TLS): replication through the authenticated log
and a takeover behind the secured router; the log refuses sessions without a server's
credentials (so no client identity can reach the replication at all); no client identity can
pose as a server; a session without valid Zenoh credentials cannot connect.
"""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcsm import wire
from mcsm.log.reader import RecordingReader
from mcsm.log.replay import replay
from mcsm.log.topics import TOPIC_OPS
from mcsm.serve.connect import client_config
from mcsm.serve.natsrun import NatsCluster
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
    nats: NatsCluster

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
                         "--connect", self.endpoint, "--nats", ",".join(self.nats.urls),
                         "--nats-auth", str(self.dir / f"{ident}.nats.json"), *args,
                         name=name, endpoint="-")
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
        self.nats.stop()


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
    nats = NatsCluster(work / "nats", auth=(d / "nats-auth.conf").read_text()).start()
    # mtls: the router's certificate names localhost and 127.0.0.1 (make_secrets.py)
    return Fleet(variant, d, f"{proto}/127.0.0.1:{port}", router, {}, nats)


def _inputs(path: Path) -> dict[int, str]:
    """seq -> request id of every input of map ``m`` in a recording."""
    return {int(item.data["seq"]): str(item.data["id"]) for item in RecordingReader(path)
            if item.topic in TOPIC_OPS and item.data.get("map") == "m"}


@pytest.fixture(scope="module", params=["usrpwd", "mtls"])
def fleet(request: pytest.FixtureRequest, secrets_dir: Path,
          tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    """A primary (server1) and its standby (server2) of map ``m``."""
    work = tmp_path_factory.mktemp(f"fleet-{request.param}")
    f = start_fleet(secrets_dir, request.param, work)
    try:
        f.serve(work, "server1", "primary", "--map", "m")
        f.serve(work, "server2", "standby", "--standby-of", "m")
        with f.client("viewer") as v:
            wait_for("the standby joins", lambda: len(v.info().standbys) == 1)
        yield f
    finally:
        f.stop()


@pytest.mark.parametrize("variant", ["usrpwd", "mtls"])
def test_secured_fleet_replicates_and_a_standby_takes_over(secrets_dir: Path, tmp_path: Path,
                                                           variant: str) -> None:
    """Behind the secured router, through the authenticated log (both variants): every
    acknowledged update of a robot is in the log and on the standby; the primary is
    SIGKILLed, the standby takes over, the old primary's identity comes back as the new
    standby, and the robot goes on with the same credentials: nothing lost or doubled, the
    recordings replay identical."""
    f = start_fleet(secrets_dir, variant, tmp_path)
    rng = np.random.default_rng(1801)
    try:
        p = f.serve(tmp_path, "server1", "p", "--map", "m")
        s = f.serve(tmp_path, "server2", "s", "--standby-of", "m")
        with f.client("robot1", namespace="robot1", timeout_s=30.0) as robot:
            wait_for("the standby joins", lambda: len(robot.info().standbys) == 1)
            xs = [noisy_at(rng, N, [1, 0, 0]) for _ in range(20)]
            acks = [robot.update(f"robot1/p{i}", f"robot1/p{i + 1}", xs[i], request_id=f"r{i}")
                    for i in range(10)]
            assert [a.seq for a in acks] == list(range(1, 11))
            wait_for("the standby holds all 10",
                     lambda: list(robot.info().standbys.values()) == [10])
            before = robot.info()
            p.proc.send_signal(signal.SIGKILL)
            p.proc.wait(timeout=10)
            wait_for("the standby takes over", lambda: robot.info().server_id != before.server_id)
            p2 = f.serve(tmp_path, "server1", "p2", "--standby-of", "m")
            acks += [robot.update(f"robot1/p{i}", f"robot1/p{i + 1}", xs[i], request_id=f"r{i}")
                     for i in range(10, 20)]
            again = robot.update("robot1/p0", "robot1/p1", xs[0], request_id="r0")
            # the new standby's recording is compared below: let it apply the whole log first
            wait_for("the new standby holds all 20",
                     lambda: list(robot.info().standbys.values()) == [20])
            after = robot.info()
        assert again.duplicate and again.seq == 1
        assert [a.seq for a in acks] == list(range(1, 21))
        assert all(a.server == before.server_id for a in acks[:10])
        assert all(a.server == after.server_id != before.server_id for a in acks[10:])
        assert after.seq == 20
        assert p2.stop() == 0 and s.stop() == 0
    finally:
        f.stop()
    ids = {a.seq: f"r{a.seq - 1}" for a in acks}
    assert _inputs(p.record) == {k: v for k, v in ids.items() if k <= 10}
    assert _inputs(s.record) == ids
    assert set(_inputs(p2.record).items()) <= set(ids.items())
    for d in (s, p2):
        rep = replay(d.record)
        assert rep.divergence is None and rep.final_digests()["m"] == after.digest


def test_router_restart_with_the_standbys_stopped(secrets_dir: Path, tmp_path: Path) -> None:
    """The procedure docs/fleet.md gives for changing the router's rules (a restart): stop the
    standbys, restart the router, start them again. The primary keeps the map (it holds the
    lease), the robot goes on with the same client, the new standby catches up."""
    f = start_fleet(secrets_dir, "usrpwd", tmp_path)
    rng = np.random.default_rng(1804)
    try:
        p = f.serve(tmp_path, "server1", "p", "--map", "m")
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
            # one server's token, the primary's (a 1 s liveliness query can come back empty
            # on a loaded machine while the restarted router re-learns the tokens)
            wait_for("the robot sees the primary's token only",
                     lambda: robot.servers() == [info.server_id], 20.0)
        assert [a.seq for a in acks] == list(range(1, 11))
        assert {a.server for a in acks} == {info.server_id}
        with f.client("viewer") as v:
            wait_for("the new standby holds all 10",
                     lambda: list(v.info().standbys.values()) == [10])
        assert s2.stop() == 0 and p.stop() == 0
    finally:
        f.stop()
    assert replay(s2.record).final_digests()["m"] == info.digest


def test_the_log_refuses_sessions_without_a_server_identity(fleet: Fleet,
                                                           tmp_path: Path) -> None:
    """The NATS cluster of the maps' logs: no credentials, a wrong password, and a client
    identity's name (clients have no NATS user) are refused; a server identity's credentials
    open a session. So no robot, viewer or admin can read or append to a map's log, take its
    lease or forge a snapshot."""
    import asyncio
    import json as _json

    import nats as nats_py

    cred = _json.loads((fleet.dir / "server1.nats.json").read_text())

    async def opens(**kw: Any) -> bool:
        try:
            nc = await nats_py.connect(servers=fleet.nats.urls[:1], connect_timeout=2,
                                       allow_reconnect=False, max_reconnect_attempts=0, **kw)
        except Exception:
            return False
        await nc.close()
        return True

    assert not asyncio.run(opens())
    assert not asyncio.run(opens(user="server1", password=cred["password"][::-1]))
    for ident in CLIENTS:
        assert not asyncio.run(opens(user=ident, password=cred["password"]))
    assert asyncio.run(opens(user="server1", password=cred["password"]))
    with fleet.client("viewer") as v:
        assert len(v.info().standbys) == 1


@pytest.mark.parametrize("ident", CLIENTS)
def test_clients_cannot_pose_as_a_server(fleet: Fleet, ident: str) -> None:
    """A client identity declares a queryable and a liveliness token on the map's keys: the
    router drops them, so clients see one server and nothing reaches the rogue; updates are
    acknowledged by the real primary as before."""
    rng = np.random.default_rng(1803)
    rogue = fleet.session(ident)
    got: list[str] = []

    def answer(q: zenoh.Query) -> None:
        got.append(str(q.key_expr))
        q.reply(q.key_expr, wire.pack({"v": wire.VERSION, "zid": str(rogue.zid()), "seq": 10**6}))

    zid = str(rogue.zid())
    entities = [rogue.declare_queryable("mcsm/m/**", answer, complete=True),
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
        assert got == []
    finally:
        for e in entities:
            e.undeclare()
        rogue.close()


def test_sessions_without_valid_credentials_cannot_join_the_fleet(fleet: Fleet,
                                                                  tmp_path: Path) -> None:
    """No credentials, a wrong password, an unknown user (usrpwd); plain TCP to the TLS port,
    no client certificate (mtls): the session does not open, so it can neither reach the map
    nor anything else."""
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
