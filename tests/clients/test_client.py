"""MapClient against an in-process server (real Zenoh sessions on loopback), plus the
connection helper. Timeouts, retries with one request id, typed errors, events."""

from __future__ import annotations

import argparse
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh
from mcsm import StochasticMap, wire
from mcsm.connect import (
    add_connection_args,
    client_config,
    client_kwargs,
    listen_endpoints,
    server_config,
)
from mcsm.core.quat import qexp
from mcsm.errors import (
    Busy,
    InvalidSamples,
    LimitExceeded,
    NoPermittedServer,
    NoServer,
    NotRelated,
    SampleCountMismatch,
    Timeout,
    UnknownFrame,
)
from mcsm.recording import replay
from mcsm.server import Server, ServerOptions
from mcsm_client.client import MapClient

N = 24


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def at(rng: np.random.Generator, t: list[float], n: int = N) -> np.ndarray:
    x = np.empty((n, 7))
    x[:, :3] = np.asarray(t) + 0.05 * rng.standard_normal((n, 3))
    x[:, 3:] = qexp(0.01 * rng.standard_normal((n, 3)))
    return x


@pytest.fixture
def served(tmp_path: Path) -> Iterator[tuple[str, Server]]:
    ep = free_endpoint()
    session = zenoh.open(server_config(ep))
    srv = Server(session, ServerOptions(maps=["default", "other"], map_options={"n_samples": N},
                                        record=tmp_path / "rec.mcap", checkpoint_every=3))
    srv.start()
    try:
        yield ep, srv
    finally:
        srv.close()
        session.close()


def test_round_trip_and_typed_errors(served: tuple[str, Server]) -> None:
    ep, srv = served
    rng = np.random.default_rng(6601)
    local = StochasticMap(N)
    with MapClient(connect=ep, timeout_s=5) as c:
        for a, b, t in (("w", "r", [1, 0, 0]), ("r", "s", [1, 0, 0]), ("w", "s", [2, 0, 0]),
                        ("u", "v", [0, 1, 0])):
            x = at(rng, t)
            ack = c.update(a, b, x)
            want = local.update(a, b, x)
            assert (ack.kind, ack.component, ack.frames_added) == (
                want.kind, want.component, want.frames_added)
        pt = np.array([1.0, 1.0, 0.0]) + 0.1 * rng.standard_normal((N, 3))
        assert c.update_point("s", "lm", pt).kind == local.update("s", "lm", pt).kind
        assert c.query("lm", "w").tobytes() == local.query("lm", "w").tobytes()
        assert c.info().digest == local.state_digest()
        with pytest.raises(UnknownFrame) as e:
            c.remove("nope")
        assert e.value.fields["name"] == "nope"
        with pytest.raises(NotRelated):
            c.marginal("w", "u")
        with pytest.raises(SampleCountMismatch):
            c.update("w", "r", at(rng, [1, 0, 0], n=N + 1))
        bad = at(rng, [1, 0, 0])
        bad[0, 3:] = 0.0
        with pytest.raises(InvalidSamples):
            c.update("w", "r", bad)
        info = c.info()
        assert info.rejected == 4
        assert info.rejected_by_error == {"UnknownFrame": 1, "NotRelated": 1,
                                          "SampleCountMismatch": 1, "InvalidSamples": 1}
    with MapClient(map="other", connect=ep) as c2:  # maps are independent
        assert c2.info().frames == () and c2.info().seq == 0


def test_oversized_request_is_refused_before_sending(served: tuple[str, Server]) -> None:
    ep, _ = served
    m = wire.MAX_PAYLOAD_BYTES // (N * 56) + 1  # frames in a submap just over the limit
    edges = np.zeros((m, N, 7))
    edges[..., 3] = 1.0
    sub = wire.SubmapData("g0", tuple(f"g{i}" for i in range(m)), (False,) * m, edges)
    with MapClient(connect=ep, timeout_s=5) as c:
        t0 = time.monotonic()
        with pytest.raises(LimitExceeded, match="request bytes"):
            c.import_submap(sub)
        assert time.monotonic() - t0 < 1.0
        assert c.info().seq == 0


def test_open_without_server_times_out_quickly() -> None:
    ep = free_endpoint()  # nothing listens here
    t0 = time.monotonic()
    with pytest.raises(Timeout):
        MapClient(connect=ep, timeout_s=1.0)
    assert time.monotonic() - t0 < 10.0


def test_silence_is_retried_with_the_same_id_until_the_full_timeout() -> None:
    """A server (token + queryable) that stays silent on the first attempt and answers the
    second: the client sends the very same payload (same request id) again and returns the
    answer. A request never answered fails after its full timeout (not milliseconds), as
    NoPermittedServer (alive server, no reply at all); with no server: NoServer."""
    ep = free_endpoint()
    srv = zenoh.open(server_config(ep))
    seen: list[str] = []
    lock = threading.Lock()

    def on_query(q: zenoh.Query) -> None:
        req = wire.decode_update(q.payload.to_bytes() if q.payload else b"", None)
        with lock:
            seen.append(req.request_id)
            first = len(seen) == 1
        if not first:
            q.reply(q.key_expr, wire.encode_ack(wire.Ack(req.request_id, 1, "update",
                                                         "new_component", req.a,
                                                         (req.a, req.b),
                                                         server=str(srv.zid()))))
        q.drop()

    qa = srv.declare_queryable("mcsm/default/update", on_query)
    tok = srv.liveliness().declare_token(f"mcsm/default/alive/{srv.zid()}")
    try:
        rng = np.random.default_rng(6602)
        with MapClient(connect=ep, timeout_s=1.0) as c:
            ack = c.update("a", "b", at(rng, [1, 0, 0]))
            assert len(seen) == 2 and seen[0] == seen[1] == ack.request_id
            assert ack.server == c.server_id == str(srv.zid())
            t0 = time.monotonic()
            with pytest.raises(NoPermittedServer, match="no permitted server"):
                c.remove("a")
            assert 1.0 <= time.monotonic() - t0 < 6.0
            tok.undeclare()
            deadline = time.monotonic() + 10
            while c.servers(0.2) and time.monotonic() < deadline:
                pass  # the token's removal reaches the client
            t0 = time.monotonic()
            with pytest.raises(NoServer, match="no server serves map"):
                c.remove("a", timeout_s=0.5)
            assert 0.5 <= time.monotonic() - t0 < 5.0
    finally:
        qa.undeclare()
        srv.close()


def test_watch_with_callback(served: tuple[str, Server]) -> None:
    ep, _ = served
    rng = np.random.default_rng(6603)
    got: list[wire.Event] = []
    done = threading.Event()

    def cb(ev: wire.Event) -> None:
        got.append(ev)
        if len(got) >= 3:
            done.set()

    with MapClient(connect=ep) as c:
        stream = c.watch(cb)
        for i in range(3):
            c.update(f"f{i}", f"f{i + 1}", at(rng, [1, 0, 0]))
        assert done.wait(10.0)
        stream.close()
    assert [e.seq for e in got] == [1, 2, 3]
    assert got[2].digest is not None  # seq 3 is a checkpoint (checkpoint_every=3)
    assert got[0].digest is None


def test_server_close_writes_a_replayable_recording(tmp_path: Path) -> None:
    ep = free_endpoint()
    session = zenoh.open(server_config(ep))
    rec = tmp_path / "r.mcap"
    srv = Server(session, ServerOptions(map_options={"n_samples": N}, record=rec))
    srv.start()
    rng = np.random.default_rng(6604)
    with MapClient(connect=ep) as c:
        for i in range(4):
            c.update(f"k{i}", f"k{i + 1}", at(rng, [1, 0, 0]))
        digest = c.info().digest
    srv.close()
    session.close()
    rep = replay(rec)
    assert rep.identical and rep.complete and rep.checkpoints_ok == 1  # the close checkpoint
    assert rep.states["default"].map.state_digest() == digest


def test_connection_args_and_configs(tmp_path: Path) -> None:
    p = argparse.ArgumentParser()
    add_connection_args(p)
    a = p.parse_args([])
    assert client_kwargs(a) == {"map": "default", "connect": None, "zenoh_config": None,
                                "prefix": "mcsm"}
    a = p.parse_args(["--connect", "tcp/127.0.0.1:9", "--map", "m", "--prefix", "x/y"])
    assert client_kwargs(a)["connect"] == "tcp/127.0.0.1:9" and a.map == "m"
    ps = argparse.ArgumentParser()
    add_connection_args(ps, role="server")
    s = ps.parse_args(["--map", "a", "--map", "b"])
    assert s.map == ["a", "b"] and s.listen is None

    sc = server_config()
    assert listen_endpoints(sc) == ["tcp/127.0.0.1:7447"]
    assert json.loads(sc.get_json("mode")) == "peer"
    assert json.loads(sc.get_json("scouting/multicast/enabled")) is False
    assert json.loads(sc.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(sc.get_json("transport/link/tx/queue/batching/enabled")) is False
    assert json.loads(sc.get_json("transport/link/rx/max_message_size")) == 8 * 1024 * 1024
    cc = client_config()
    assert json.loads(cc.get_json("mode")) == "client"
    assert json.loads(cc.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(cc.get_json("scouting/multicast/enabled")) is False
    # a config file replaces the defaults; an explicit endpoint still applies on top
    f = tmp_path / "c.json5"
    f.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:1234"] } }')
    assert json.loads(client_config(None, f).get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:1234"]
    cd: dict[str, Any] = {"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:5"]}}
    assert json.loads(client_config("tcp/127.0.0.1:6", cd).get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:6"]


def test_full_queue_answers_busy_at_once(tmp_path: Path) -> None:
    """Queue of 1, worker held on the first request: the second waits in the queue, the third
    is refused at once with Busy (a LimitExceeded); releasing the worker completes the first two."""
    ep = free_endpoint()
    session = zenoh.open(server_config(ep))
    srv = Server(session, ServerOptions(map_options={"n_samples": N}, record=tmp_path / "q.mcap",
                                        queue_size=1))
    release, holding = threading.Event(), threading.Event()
    handle = srv._handle

    def held(item: Any) -> None:
        holding.set()
        release.wait(20.0)
        handle(item)

    srv._handle = held  # type: ignore[method-assign]
    srv.start()
    rng = np.random.default_rng(6605)
    results: dict[str, Any] = {}

    def call(name: str, a: str, b: str) -> None:
        with MapClient(connect=ep, timeout_s=20) as c:
            results[name] = c.update(a, b, at(rng, [1, 0, 0]))

    try:
        t1 = threading.Thread(target=call, args=("first", "a", "b"))
        t1.start()
        assert holding.wait(10.0)
        with MapClient(connect=ep, timeout_s=20) as c:
            t2 = threading.Thread(target=call, args=("second", "c", "d"))
            t2.start()
            deadline = time.monotonic() + 10
            while srv._queue.qsize() < 1 and time.monotonic() < deadline:
                time.sleep(0.005)  # polling the queue length
            assert srv._queue.qsize() == 1
            with pytest.raises(Busy, match="queue"):
                c.update("e", "f", at(rng, [1, 0, 0]))
            release.set()
            t1.join(20)
            t2.join(20)
            assert {results["first"].seq, results["second"].seq} == {1, 2}
            info = c.info()
            assert info.seq == 2 and info.rejected_by_error == {"Busy": 1}
    finally:
        release.set()
        srv.close()
        session.close()
