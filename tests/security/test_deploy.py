"""The shipped secure deployment (``deploy/``), as shipped: real ``mcsm serve`` subprocesses with
``deploy/<variant>/server.json5``, clients with the role configs, secrets made at test time by
``deploy/make_secrets.py`` (random passwords, openssl certificates), everything on 127.0.0.1.

Both variants (user/password over TCP, mutual TLS) run every test: who can connect at all,
what a viewer, a robot and the admin may do, wildcard keys, a robot posing as the server, and
the hostile-input table with authentication on.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcsm import wire
from mcsm.errors import Forbidden, McsmError, NoPermittedServer
from mcsm.serve.connect import client_config
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, free_port, noisy_at, start_daemon
from tests.wire_cases import CASES

N = 16
REPO = Path(__file__).resolve().parents[2]
MAPS = ("ns", "view", "imp", "imp2", "wild", "rogue", "table", "load", "retr")
DENIED_S = 1.0  # timeout of calls the access control denies (they fail after it, not before)


@dataclass
class Deployment:
    variant: str
    dir: Path
    endpoint: str
    daemon: Daemon

    def conf(self, ident: str) -> Path:
        return self.dir / f"{ident}.json5"

    def client(self, ident: str, map: str, **kw: Any) -> MapClient:
        kw.setdefault("timeout_s", 10.0)
        return MapClient(map=map, connect=self.endpoint, zenoh_config=self.conf(ident), **kw)

    def session(self, ident: str) -> zenoh.Session:
        return zenoh.open(client_config(self.endpoint, self.conf(ident)))


def make_secrets(out: Path) -> None:
    r = subprocess.run([sys.executable, str(REPO / "deploy" / "make_secrets.py"), str(out)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


@pytest.fixture(scope="module")
def secrets_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("secrets")
    make_secrets(out)
    return out


@pytest.fixture(scope="module", params=["usrpwd", "mtls"])
def dep(request: pytest.FixtureRequest, secrets_dir: Path,
        tmp_path_factory: pytest.TempPathFactory) -> Iterator[Deployment]:
    variant = request.param
    d = secrets_dir / variant
    proto = "tcp" if variant == "usrpwd" else "tls"
    ep = f"{proto}/127.0.0.1:{free_port()}"
    work = tmp_path_factory.mktemp(f"srv-{variant}")
    maps = [a for m in MAPS for a in ("--map", m)]
    daemon = start_daemon(work, "--zenoh-config", str(d / "server.json5"), "--samples", str(N),
                          *maps, listen_on=ep)
    yield Deployment(variant, d, ep, daemon)
    code = daemon.stop(signal.SIGTERM)
    assert code == 0, daemon.log_text()
    assert "without authentication" not in daemon.log_text()


def _open_fails(conf: zenoh.Config) -> bool:
    conf.insert_json5("connect/timeout_ms", "1000")
    try:
        s = zenoh.open(conf)
    except zenoh.ZError:
        return True
    s.close()
    return False


def test_sessions_without_valid_credentials_cannot_connect(dep: Deployment,
                                                           tmp_path: Path) -> None:
    """No credentials, a wrong password, plain TCP to the TLS port, no client certificate, a
    certificate from another CA: the session does not even open, so it cannot update, query or
    declare anything."""
    bad: list[zenoh.Config] = [client_config(dep.endpoint)]  # the loopback defaults
    if dep.variant == "usrpwd":
        text = dep.conf("robot1").read_text()
        password = json.loads(text[text.index("{"):])["transport"]["auth"]["usrpwd"]["password"]
        wrong = tmp_path / "wrong.json5"
        wrong.write_text(text.replace(password, password[::-1]))
        unknown = tmp_path / "unknown.json5"
        unknown.write_text(text.replace('"robot1"', '"robot9"'))
        bad += [client_config(dep.endpoint, wrong), client_config(dep.endpoint, unknown)]
    else:
        bad.append(client_config(dep.endpoint.replace("tls/", "tcp/"), dep.conf("robot1")))
        nocert = {"mode": "client", "scouting": {"multicast": {"enabled": False}},
                  "transport": {"link": {"tls": {
                      "root_ca_certificate": str(dep.dir / "certs" / "ca.pem")}}}}
        bad.append(client_config(dep.endpoint, nocert))
        other = tmp_path / "other"
        make_secrets(other)  # a second CA: its robot1 certificate is not trusted here
        bad.append(client_config(dep.endpoint, other / "mtls" / "robot1.json5"))
    for conf in bad:
        assert _open_fails(conf)
    with dep.client("admin", "view") as admin:
        assert admin.info().seq == 0


def test_viewer_reads_but_cannot_write(dep: Deployment) -> None:
    rng = np.random.default_rng(1201)
    with dep.client("robot1", "view", namespace="robot1") as robot, \
            dep.client("viewer", "view", timeout_s=DENIED_S) as viewer:
        with viewer.watch() as events:
            robot.update("robot1/base", "robot1/p1", noisy_at(rng, N, [1, 0, 0]))
            ev = events.get(10.0)
        assert ev is not None and ev.frames == ("robot1/base", "robot1/p1")
        assert viewer.info().frames == ("robot1/base", "robot1/p1")
        assert viewer.query("robot1/base", "robot1/p1").shape == (N, 7)
        x = noisy_at(rng, N, [1, 0, 0])
        for call in (lambda: viewer.update("robot1/p1", "robot1/p2", x),
                     lambda: viewer.remove("robot1/p1")):
            t0 = time.monotonic()
            with pytest.raises(NoPermittedServer):
                call()
            assert time.monotonic() - t0 >= DENIED_S
        with dep.client("viewer", "view", namespace="robot1", timeout_s=DENIED_S) as v2:
            with pytest.raises(NoPermittedServer):
                v2.update("robot1/p1", "robot1/p2", x)
            with pytest.raises(NoPermittedServer):
                v2.export_submap("robot1/p1")
        assert robot.info().seq == 1


def test_robot_writes_only_its_own_namespace(dep: Deployment) -> None:
    rng = np.random.default_rng(1202)

    def x() -> np.ndarray:
        return noisy_at(rng, N, [1, 0, 0])

    with dep.client("robot1", "ns", namespace="robot1") as r1, \
            dep.client("robot2", "ns", namespace="robot2") as r2:
        r1.update("robot1/base", "robot1/p1", x())
        r2.update("robot2/base", "robot2/p1", x())
        seq, digest = r1.info().seq, r1.info().digest
        recorded = dep.daemon.record.stat().st_size
        # observed from robot2's frame, through robot1's own key: refused by the server
        with pytest.raises(Forbidden, match="another namespace"):
            r1.update("robot2/p1", "robot2/p2", x())
        with pytest.raises(Forbidden):
            r1.update_point("robot2/p1", "robot1/lm", rng.standard_normal((N, 3)))
        with pytest.raises(Forbidden, match="another namespace's frame"):
            r1.remove("robot2/p1")
        with pytest.raises(Forbidden, match="new frame"):  # no squatting on robot2's names
            r1.update("robot1/p1", "robot2/p9", x())
        with pytest.raises(Forbidden):  # a frame in no namespace: the admin's alone
            r1.update("world", "robot1/p7", x())
        # nothing applied, nothing recorded
        assert (r1.info().seq, r1.info().digest) == (seq, digest)
        assert dep.daemon.record.stat().st_size == recorded
        # robot2's or the admin's keys with robot1's identity: denied by the access control
        for kw in ({"namespace": "robot2"}, {}):
            with dep.client("robot1", "ns", timeout_s=DENIED_S, **kw) as wrong:
                with pytest.raises(NoPermittedServer):
                    wrong.update("robot2/p1", "robot2/p2", x())
                with pytest.raises(NoPermittedServer):
                    wrong.remove("robot2/p1")
        # observing robot2's (existing) frame from its own: allowed, that is how maps join
        ack = r1.update("robot1/p1", "robot2/p1", x())
        assert ack.kind == "join"
        assert r1.remove("robot1/p1").frames_removed == ("robot1/p1",)
        assert r2.info().seq == seq + 2


def test_a_longer_namespace_uses_its_first_segments_keys(
        dep: Deployment, capsys: pytest.CaptureFixture[str]) -> None:
    """docs/deploy.md: ``--namespace robot1/sim1`` with robot1's identity writes frames
    robot1/sim1/... through robot1's keys."""
    from mcsm_client.cli import main as client_main

    code = client_main(["sim", "--iterations", "3", "--landmarks", "5", "--json",
                        "--connect", dep.endpoint, "--map", "ns", "--zenoh-config",
                        str(dep.conf("robot1")), "--namespace", "robot1/sim1"])
    assert code == 0, capsys.readouterr().err
    with dep.client("admin", "ns") as admin:
        frames = admin.info().frames
    assert any(f.startswith("robot1/sim1/") for f in frames), frames


def test_admin_imports_a_submap_robots_cannot(dep: Deployment) -> None:
    rng = np.random.default_rng(1203)
    with dep.client("admin", "imp") as admin, dep.client("admin", "imp2") as admin2:
        admin.update("robot1/a", "robot1/b", noisy_at(rng, N, [1, 0, 0]))
        admin.update("robot2/a", "robot1/a", noisy_at(rng, N, [0, 1, 0]))  # any namespace
        sub = admin.export_submap("robot1/a")
        ack = admin2.import_submap(sub)
        assert set(ack.frames_added) == {"robot1/a", "robot1/b", "robot2/a"}
        assert admin2.remove("robot2/a").frames_removed == ("robot2/a",)
    with dep.client("robot1", "imp2", namespace="robot1", timeout_s=DENIED_S) as r1:
        with pytest.raises(NoPermittedServer):
            r1.import_submap(sub)
        with pytest.raises(NoPermittedServer):
            r1.export_submap("robot1/a")
        assert r1.info().seq == 2


@pytest.mark.parametrize("ident", ["robot1", "viewer", "admin"])
def test_wildcard_keys_get_nothing_through(dep: Deployment, ident: str) -> None:
    """Valid updates and removes sent on wildcard keys: no ack, nothing applied. The access
    control denies the robot's and the viewer's; the admin's reach the server, which refuses
    every non-concrete key with BadMessage."""
    rng = np.random.default_rng(1204)
    with dep.client("admin", "wild") as admin:
        if not admin.info().frames:
            admin.update("robot1/base", "robot1/p1", noisy_at(rng, N, [1, 0, 0]))
        before = admin.info()
        s = dep.session(ident)
        try:
            up = wire.encode_update("w-up", "robot1/base", "robot1/p2",
                                    noisy_at(rng, N, [1, 0, 0]))
            rm = wire.encode_remove("w-rm", "robot1/p1")
            keys = ["mcsm/**", "mcsm/wild/*", "mcsm/wild/up$*", "mcsm/wild/update/*",
                    "mcsm/*/update/robot1", "mcsm/wild/**", "mcsm/*/remove/robot1",
                    "mcsm/wild/remove/*", "mcsm/wild/re$*/robot1", "mcsm/wild/update/robot1/**"]
            for key in keys:
                for payload in (up, rm):
                    replies = list(s.get(key, payload=payload, timeout=2.0))
                    assert all(r.ok is None for r in replies), (ident, key)
                    for r in replies:  # what does come back is the server's refusal
                        err = wire.decode_error(r.err.payload.to_bytes())
                        assert type(err).__name__ == "BadMessage", err
        finally:
            s.close()
        after = admin.info()
    assert (after.seq, after.digest, after.frames) == (before.seq, before.digest, before.frames)


def test_a_robot_cannot_pose_as_the_server(dep: Deployment) -> None:
    """robot2 declares a queryable and a liveliness token on the map's keys: the access control
    drops both, so robot1's calls all reach the real server; 0 forged acks."""
    rng = np.random.default_rng(1205)
    rogue = dep.session("robot2")
    got_queries = 0

    def answer(q: zenoh.Query) -> None:
        nonlocal got_queries
        got_queries += 1
        q.reply(q.key_expr, b"forged")

    qa = rogue.declare_queryable("mcsm/rogue/**", answer, complete=True)
    tok = rogue.liveliness().declare_token(f"mcsm/rogue/alive/{rogue.zid()}")
    try:
        with dep.client("robot1", "rogue", namespace="robot1") as r1:
            real = r1.info().server_id
            assert r1.servers() == [real]
            acks = [r1.update(f"robot1/p{i}", f"robot1/p{i + 1}", noisy_at(rng, N, [1, 0, 0]))
                    for i in range(10)]
            assert [a.seq for a in acks] == list(range(1, 11))
            assert all(a.server == real for a in acks)
            assert r1.foreign_replies == 0 and got_queries == 0
    finally:
        tok.undeclare()
        qa.undeclare()
        rogue.close()


def test_hostile_inputs_with_authentication(dep: Deployment) -> None:
    """The malformed-payload table through an authenticated admin session: every case gets its
    typed error, the map and the recording are unchanged."""
    rng = np.random.default_rng(1206)
    with dep.client("admin", "table") as c:
        if "w" not in c.info().frames:
            c.update("w", "r", noisy_at(rng, N, [1, 0, 0]))
            c.update("lonely", "lonely2", noisy_at(rng, N, [0, 1, 0]))
        before = c.info()
        size_before = dep.daemon.record.stat().st_size
        for case_id, op, build, error, _ in CASES:
            replies = list(c.session.get(getattr(c.keys, op), payload=build(N), timeout=5.0))
            assert len(replies) == 1 and replies[0].ok is None, case_id
            err = wire.decode_error(replies[0].err.payload.to_bytes())
            assert type(err).__name__ == error, (case_id, err)
        after = c.info()
    assert (after.seq, after.digest) == (before.seq, before.digest)
    assert after.rejected == before.rejected + len(CASES)
    assert dep.daemon.record.stat().st_size == size_before


def test_denied_call_names_the_cause(dep: Deployment) -> None:
    with dep.client("viewer", "view", timeout_s=DENIED_S) as v:
        try:
            v.remove("robot1/p1")
        except NoPermittedServer as exc:
            assert "no permitted server for mcsm/view/remove" in exc.message
            assert exc.fields["server_id"] == v.info().server_id
        except McsmError as exc:  # pragma: no cover - the failure message
            raise AssertionError(f"wrong error: {exc!r}") from None
        else:
            raise AssertionError("a viewer's remove was accepted")


def test_concurrent_robots_with_authentication(dep: Deployment) -> None:
    """The load test's shape with authentication on: robots stream into their own namespaces
    at once, every op gets a distinct seq, the recording replays to the live digest."""
    from mcsm.log.replay import replay

    per_robot = 8
    acks: list[wire.Ack] = []
    errors: list[Exception] = []

    def run(ident: str, seed: int) -> None:
        rng = np.random.default_rng(seed)
        try:
            with dep.client(ident, "load", namespace=ident, timeout_s=20) as c:
                for i in range(per_robot):
                    acks.append(c.update(f"{ident}/p{i}", f"{ident}/p{i + 1}",
                                         noisy_at(rng, N, [1, 0, 0])))
        except McsmError as exc:
            errors.append(exc)

    threads = [threading.Thread(target=run, args=(r, 1210 + k))
               for k, r in enumerate(("robot1", "robot2"))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not errors and not any(t.is_alive() for t in threads)
    assert sorted(a.seq for a in acks) == list(range(1, 2 * per_robot + 1))
    with dep.client("viewer", "load") as v:
        info = v.info()
    rep = replay(dep.daemon.record)
    assert rep.identical and rep.states["load"].map.state_digest() == info.digest


def test_robot_streams_across_sigkill_and_restore_with_authentication(
        secrets_dir: Path, tmp_path: Path, daemons: list[Daemon]) -> None:
    """A robot (usrpwd config) streaming while its server is SIGKILLed and restarted with
    --restore on the same port: every call succeeds, nothing lost or doubled."""

    conf = secrets_dir / "usrpwd" / "server.json5"
    ep = f"tcp/127.0.0.1:{free_port()}"
    d1 = start_daemon(tmp_path, "--zenoh-config", str(conf), "--samples", str(N), name="first",
                      listen_on=ep)
    daemons.append(d1)
    rng = np.random.default_rng(1207)
    ops = [(f"robot1/p{i}", f"robot1/p{i + 1}", noisy_at(rng, N, [1, 0, 0])) for i in range(60)]
    acks: list[wire.Ack] = []
    errors: list[Exception] = []
    c = MapClient(connect=ep, zenoh_config=secrets_dir / "usrpwd" / "robot1.json5",
                  namespace="robot1", timeout_s=30)

    def stream() -> None:
        for i, (a, b, x) in enumerate(ops):
            try:
                acks.append(c.update(a, b, x, request_id=f"k{i}"))
            except McsmError as exc:
                errors.append(exc)
                return

    try:
        t = threading.Thread(target=stream)
        t.start()
        deadline = time.monotonic() + 30
        while len(acks) < 10 and time.monotonic() < deadline and t.is_alive():
            time.sleep(0.01)  # polling the ack count
        d1.proc.send_signal(signal.SIGKILL)
        d1.proc.wait(timeout=10)
        d2 = start_daemon(tmp_path, "--zenoh-config", str(conf), "--restore", str(d1.record),
                          name="second", listen_on=ep)
        daemons.append(d2)
        t.join(timeout=120)
        assert not t.is_alive() and not errors, errors
        assert [a.seq for a in acks] == list(range(1, len(ops) + 1))
        assert c.info().seq == len(ops)
    finally:
        c.close()
    assert d2.stop(signal.SIGTERM) == 0, d2.log_text()


def test_only_the_admin_retracts_and_relinearizes_everyone_reads_verdicts(dep: Deployment) -> None:
    rng = np.random.default_rng(1210)
    with dep.client("robot1", "retr", namespace="robot1") as robot, \
            dep.client("viewer", "retr", timeout_s=DENIED_S) as viewer, \
            dep.client("admin", "retr") as admin:
        robot.update("robot1/a", "robot1/b", noisy_at(rng, N, [1, 0, 0]), request_id="r1-u1")
        robot.update("robot1/b", "robot1/c", noisy_at(rng, N, [1, 0, 0]), request_id="r1-u2")
        for who in (robot, viewer):
            v = who.verdict("r1-u2")
            assert v is not None and v.status == "accepted"
        with pytest.raises(NoPermittedServer):
            viewer.retract("r1-u2")
        with dep.client("robot1", "retr", namespace="robot1", timeout_s=DENIED_S) as r1:
            with pytest.raises(NoPermittedServer):
                r1.retract("r1-u2")
            with pytest.raises(NoPermittedServer):
                r1.reinstate("r1-u2")
        assert admin.retract("r1-u2").verdict.status == "retracted"  # type: ignore[union-attr]
        assert viewer.verdict("r1-u2").status == "retracted"  # type: ignore[union-attr]
        assert admin.reinstate("r1-u2").verdict.status == "reinstated"  # type: ignore[union-attr]
        # relinearisation rewrites every sample of a component: admin only, like retract
        with pytest.raises(NoPermittedServer):
            viewer.relinearize("robot1/a")
        with dep.client("robot1", "retr", namespace="robot1", timeout_s=DENIED_S) as r1:
            with pytest.raises(NoPermittedServer):
                r1.relinearize("robot1/a")
        ack = admin.relinearize("robot1/a")
        assert ack.op == ack.kind == "relinearize" and ack.relin is not None
        assert ack.relin["components"][0]["frames"] == 3


def test_fleet_server_identities_have_no_rights_on_a_single_server(dep: Deployment) -> None:
    """``make_secrets.py`` gives the fleet's server identities (server1, server2) a password or
    certificate from the same users.txt / CA; ``server.json5`` names them in no subject, so on
    a single server they can open a session and do nothing: no request answered, a queryable
    and a token they declare on the map's keys reach nobody."""
    rng = np.random.default_rng(1211)
    s = dep.session("server1")
    got: list[str] = []
    entities = [s.declare_queryable("mcsm/rogue/**", lambda q: got.append(str(q.key_expr)),
                                    complete=True),
                s.liveliness().declare_token(f"mcsm/rogue/alive/{s.zid()}")]
    try:
        for key in ("mcsm/view/info", "mcsm/view/query", "mcsm/view/update"):
            assert list(s.get(key, payload=wire.pack({"v": wire.VERSION}),
                              timeout=DENIED_S)) == [], key
        admin = dep.session("admin")  # the same request with a client identity is answered
        try:
            replies = list(admin.get("mcsm/view/info", payload=wire.pack({"v": wire.VERSION}),
                                     timeout=5.0))
        finally:
            admin.close()
        assert len(replies) == 1 and replies[0].ok is not None
        with dep.client("robot1", "rogue", namespace="robot1") as r1:
            real = r1.info().server_id
            assert r1.servers() == [real]
            ack = r1.update("robot1/s1a", "robot1/s1b", noisy_at(rng, N, [1, 0, 0]))
            assert ack.server == real and r1.foreign_replies == 0
        assert got == []
    finally:
        for e in entities:
            e.undeclare()
        s.close()
