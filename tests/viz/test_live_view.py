"""``mcsm view``: a real ``mcsm serve`` and a real ``mcsm view`` subprocess on loopback, and
three viewers: a WebSocket client written here from Foxglove's protocol (serverInfo, advertise,
subscribe, binary message data) offering ``foxglove.sdk.v1``, the same offering only the older
name ``foxglove.websocket.v1``, and npm's ``@foxglove/ws-protocol`` client in its default
setting (a Node script, in its own test: skipped only without node and npm). Each decodes the
scene and compares it with the map; the verdict log and the counters are checked too."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import os
import queue
import shutil
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import websockets

from tests.service.daemon_util import free_port, start_daemon
from tests.viz.conftest import N, apply, build_map, default_ops, planar_point
from tests.viz.foxglove_util import check_scene_against_map, message_class

SUBPROTOCOL = "foxglove.sdk.v1"
OLD_SUBPROTOCOL = "foxglove.websocket.v1"
NODE_CLIENT = Path(__file__).with_name("foxglove_ws_client.cjs")
OP_MESSAGE_DATA = 0x01
DEADLINE_S = 60.0


def start_view(workdir: Path, endpoint: str, port: int) -> tuple[subprocess.Popen[str], str]:
    log = open(workdir / "view.log", "w")  # noqa: SIM115 - closed by the caller's process end
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "mcsm.cli", "view", "--connect", endpoint,
                             "--foxglove-port", str(port), "--samples-per-frame", "8"],
                            stdout=subprocess.PIPE, stderr=log, text=True, env=env)
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stdout is not None
    out = proc.stdout
    threading.Thread(target=lambda: [lines.put(x) for x in out], daemon=True).start()
    deadline = time.monotonic() + DEADLINE_S
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=0.2)
        except queue.Empty:
            if proc.poll() is not None:
                raise AssertionError((workdir / "view.log").read_text()) from None
            continue
        if line.startswith("foxglove websocket on "):
            return proc, line.split()[-1]
    proc.kill()
    raise AssertionError("mcsm view did not start:\n" + (workdir / "view.log").read_text())


class FoxgloveClient:
    """The client side of Foxglove's WebSocket protocol, as much as this test needs."""

    def __init__(self, ws: Any) -> None:
        self.ws = ws
        self.channels: dict[str, dict[str, Any]] = {}
        self.server_info: dict[str, Any] | None = None

    async def recv(self, timeout_s: float) -> str | bytes:
        return await asyncio.wait_for(self.ws.recv(), timeout_s)

    async def handshake(self, topics: set[str]) -> None:
        deadline = time.monotonic() + DEADLINE_S
        while not topics <= set(self.channels):
            m = await self.recv(deadline - time.monotonic())
            assert isinstance(m, str), "binary data before any subscription"
            d = json.loads(m)
            if d["op"] == "serverInfo":
                self.server_info = d
            elif d["op"] == "advertise":
                for c in d["channels"]:
                    self.channels[c["topic"]] = c

    async def subscribe(self, sub_id: int, topic: str) -> None:
        c = self.channels[topic]
        await self.ws.send(json.dumps({"op": "subscribe",
                                       "subscriptions": [{"id": sub_id, "channelId": c["id"]}]}))

    async def next_message(self, sub_id: int, cls: Any, accept: Any) -> Any:
        """The next decoded message on subscription ``sub_id`` for which ``accept`` is true."""
        deadline = time.monotonic() + DEADLINE_S
        while True:
            m = await self.recv(deadline - time.monotonic())
            if isinstance(m, str):
                continue  # more advertisements, status messages
            assert m[0] == OP_MESSAGE_DATA
            sid, log_time = struct.unpack_from("<IQ", m, 1)
            assert log_time > 0
            if sid != sub_id:
                continue
            msg = cls.FromString(m[13:])
            if accept(msg):
                return msg


def frame_ids(scene: Any) -> set[str]:
    return {e.id[len("frame/"):] for e in scene.entities if e.id.startswith("frame/")}


NPM_PACKAGES = ("@foxglove/ws-protocol@0.8", "ws@8")


@pytest.fixture(scope="session")
def node_modules(request: pytest.FixtureRequest,
                 tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``@foxglove/ws-protocol`` and ``ws`` installed with npm into pytest's cache folder
    (once; later runs reuse it), or a temporary folder without pytest's cache; the test is
    skipped only when node or npm is missing."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node and npm are needed to run npm's @foxglove/ws-protocol client "
                    f"(node: {node}, npm: {npm})")
    cache = getattr(request.config, "cache", None)
    where = (cache.mkdir("npm-" + "-".join(NPM_PACKAGES).replace("/", "_").replace("@", ""))
             if cache is not None else tmp_path_factory.mktemp("npm"))
    if not (where / "node_modules" / "@foxglove" / "ws-protocol" / "package.json").is_file():
        p = subprocess.run([npm, "install", "--no-audit", "--no-fund", "--prefer-offline",
                            "--prefix", str(where), *NPM_PACKAGES],
                           capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stdout + p.stderr
    return Path(where) / "node_modules"


async def python_viewer(url: str, subprotocol: str, c: Any, rng: np.random.Generator,
                        ops: list[Any], change: bool = True) -> list[Any]:
    """Connect offering only ``subprotocol``; check the scene against the map, then (with
    ``change``) send one more update and wait for it in the scene, the verdict log and the
    counters."""
    topic = "/mcsm/default/scene"
    async with websockets.connect(url, subprotocols=[subprotocol], max_size=None) as ws:
        assert ws.subprotocol == subprotocol
        fc = FoxgloveClient(ws)
        await fc.handshake({topic, "/mcsm/default/tf", "/mcsm/default/samples",
                            "/mcsm/default/log", "/mcsm/default/stats"})
        assert fc.server_info is not None
        ch = fc.channels[topic]
        assert (ch["schemaName"], ch["encoding"], ch["schemaEncoding"]) == \
            ("foxglove.SceneUpdate", "protobuf", "protobuf")
        cls = message_class(ch["schemaName"], base64.b64decode(ch["schema"]))
        lg = fc.channels["/mcsm/default/log"]
        assert (lg["schemaName"], lg["encoding"]) == ("foxglove.Log", "protobuf")
        log_cls = message_class(lg["schemaName"], base64.b64decode(lg["schema"]))
        st = fc.channels["/mcsm/default/stats"]
        assert (st["schemaName"], st["encoding"], st["schemaEncoding"]) == \
            ("mcsm.MapStats", "json", "jsonschema")
        await fc.subscribe(7, topic)
        m = build_map(ops)
        want = set(m.frames())  # type: ignore[attr-defined]
        scene = await fc.next_message(7, cls, lambda s: frame_ids(s) == want)
        check_scene_against_map(scene, m)
        if not change:
            return ops
        # the map changes: a new landmark shows up in the scene, its verdict in the log,
        # the counters move
        await fc.subscribe(8, "/mcsm/default/log")
        await fc.subscribe(9, "/mcsm/default/stats")
        name = f"l{len(ops)}"
        new = ("update", "x4", name, planar_point(rng, N, [0.3, -0.7]))
        ack = c.update_point(new[1], new[2], new[3])
        ops = [*ops, new]
        line = await fc.next_message(8, log_cls, lambda g: f"x4 -> {name}" in g.message)
        assert line.message == (f"seq {ack.seq} update x4 -> {name}: new_frame, accepted "
                                f"[{ack.verdict.reason}] id {ack.request_id}"), line.message
        assert line.level == 2 and line.name == "mcsm/default"  # INFO
        info = c.info()
        stats = await fc.next_message(9, _Json, lambda j: j.d["seq"] == ack.seq)
        assert stats.d["accepted"] == info.verdicts.get("accepted", 0)
        assert stats.d["rejected"] == info.verdicts.get("rejected", 0)
        assert stats.d["frames"] == info.n_frames and stats.d["queue_length"] >= 0
        scene = await fc.next_message(7, cls, lambda s: name in frame_ids(s))
        check_scene_against_map(scene, build_map(ops))
    return ops


class _Json:
    """A JSON message (the counters' channel) with protobuf's ``FromString`` interface."""

    def __init__(self, d: dict[str, Any]) -> None:
        self.d = d

    @classmethod
    def FromString(cls, data: bytes) -> _Json:  # noqa: N802 - protobuf's name
        return cls(json.loads(data))


def node_viewer(url: str, node_modules: Path, ops: list[Any], workdir: Path) -> None:
    """npm's FoxgloveClient, default setting: it connects, subscribes, and the scene it gets
    (decoded here from the schema it was advertised) is the map's; the counters arrive."""
    env = dict(os.environ, NODE_PATH=str(node_modules))
    proc = subprocess.Popen(["node", str(NODE_CLIENT), url, "60", "/mcsm/default/scene",
                             "/mcsm/default/stats"], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None and proc.stdin is not None
    m = build_map(ops)
    want = set(m.frames())  # type: ignore[attr-defined]
    seen: list[str] = []
    schema: dict[str, Any] = {}
    got_scene = got_stats = False
    try:
        deadline = time.monotonic() + DEADLINE_S
        for raw in proc.stdout:
            ev = json.loads(raw)
            seen.append(ev["event"])
            if ev["event"] == "open":
                assert ev["protocol"] == OLD_SUBPROTOCOL
            elif ev["event"] == "advertise":
                schema[ev["topic"]] = ev
            elif ev["event"] == "message" and ev["topic"] == "/mcsm/default/stats":
                got_stats = json.loads(base64.b64decode(ev["data"]))["frames"] == len(want)
            elif ev["event"] == "message":
                a = schema[ev["topic"]]
                cls = message_class(a["schemaName"], base64.b64decode(a["schema"]))
                scene = cls.FromString(base64.b64decode(ev["data"]))
                if frame_ids(scene) == want:
                    check_scene_against_map(scene, m)
                    got_scene = True
            assert ev["event"] not in ("error", "close"), ev
            if (got_scene and got_stats) or time.monotonic() > deadline:
                break
    finally:
        proc.stdin.close()
        proc.wait(timeout=30)
        err = proc.stderr.read() if proc.stderr else ""
    assert got_scene and got_stats, (seen[:10], err)
    assert seen[:2] == ["open", "serverInfo"], seen[:5]


@contextlib.contextmanager
def viewed_map(tmp_path: Path, name: str,
               seed: int) -> Iterator[tuple[Any, Any, subprocess.Popen[str], str, list[Any],
                                           np.random.Generator]]:
    """A server with the first 9 default operations applied and ``mcsm view`` on it: yields
    (daemon, client, view, url, ops, rng); the view and the server are stopped after."""
    from mcsm_client.client import MapClient

    rng = np.random.default_rng(seed)
    ops = default_ops(rng)[:9]
    d = start_daemon(tmp_path, "--samples", str(N), name=name)
    view: subprocess.Popen[str] | None = None
    try:
        with MapClient(connect=d.endpoint, timeout_s=30) as c:
            for op in ops:
                apply(c, op)
            view, url = start_view(tmp_path, d.endpoint, free_port())
            yield d, c, view, url, ops, rng
    finally:
        if view is not None and view.poll() is None:
            view.kill()
            view.wait(timeout=10)
        d.stop(signal.SIGINT)


@pytest.mark.slow
def test_live_view_serves_the_changing_map_to_python_clients(tmp_path: Path) -> None:
    """Both subprotocols, from a client written from the protocol (no node needed); the view
    never writes to the map; SIGTERM stops it with exit 0."""
    with viewed_map(tmp_path, "live", 20261124) as (d, c, view, url, ops, rng):
        ops = asyncio.run(python_viewer(url, SUBPROTOCOL, c, rng, ops, change=False))
        ops = asyncio.run(python_viewer(url, OLD_SUBPROTOCOL, c, rng, ops))
        # a map nobody serves, and the WebSocket port already taken: one line, exit 2
        port = url.rsplit(":", 1)[1]
        for args, needle in [
                (["--map", "nope"], f"mcsm view: no server answers for map 'nope' at "
                                    f"{d.endpoint} within 1 s"),
                (["--foxglove-port", port], "mcsm view: cannot start the Foxglove "
                                            f"WebSocket server on 127.0.0.1:{port}")]:
            p = subprocess.run([sys.executable, "-m", "mcsm.cli", "view", "--connect",
                                d.endpoint, "--timeout", "1", *args], capture_output=True,
                               text=True, timeout=120)
            assert p.returncode == 2, p.stderr
            err = p.stderr.strip().splitlines()
            assert err[-1].startswith(needle) and "Traceback" not in p.stderr, p.stderr
        assert c.info().seq == len(ops)  # every change is the test's: the view wrote none
        view.send_signal(signal.SIGTERM)
        assert view.wait(timeout=30) == 0, (tmp_path / "view.log").read_text()
    log = (tmp_path / "view.log").read_text()
    assert "Traceback" not in log
    assert "connected with foxglove.websocket.v1" in log  # the relay let the old name in


def test_live_view_serves_npm_foxglove_client(tmp_path: Path, node_modules: Path) -> None:
    """npm's @foxglove/ws-protocol FoxgloveClient in its default setting; SIGINT stops the
    view with exit 0."""
    with viewed_map(tmp_path, "live-npm", 20261125) as (_, _, view, url, ops, _):
        node_viewer(url, node_modules, ops, tmp_path)
        view.send_signal(signal.SIGINT)
        assert view.wait(timeout=30) == 0, (tmp_path / "view.log").read_text()
    assert "Traceback" not in (tmp_path / "view.log").read_text()


def test_view_user_mistakes_exit_2_with_one_line(tmp_path: Path) -> None:
    port = free_port()

    def view(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "mcsm.cli", "view", *args],
                              capture_output=True, text=True, timeout=120)

    p = view("--connect", f"tcp/127.0.0.1:{port}", "--timeout", "1")
    assert p.returncode == 2
    assert p.stderr.strip() == (f"mcsm view: cannot reach a Zenoh peer at "
                                f"tcp/127.0.0.1:{port} within 1 s")
    p = view("--foxglove-port", "70000")
    assert p.returncode == 2
    assert p.stderr.strip() == "mcsm view: --foxglove-port must be in 0..65535, got 70000"
