"""``mcsm view``: a real ``mcsm serve`` and a real ``mcsm view`` subprocess on loopback, and a
WebSocket client speaking Foxglove's protocol (``foxglove.sdk.v1``: serverInfo, advertise,
subscribe, binary message data) that decodes the scene and compares it with the map."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import queue
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import websockets

from tests.service.daemon_util import free_port, start_daemon
from tests.viz.conftest import N, apply, build_map, default_ops, planar_point
from tests.viz.foxglove_util import check_scene_against_map, message_class

SUBPROTOCOL = "foxglove.sdk.v1"
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


@pytest.mark.slow
def test_live_view_serves_the_changing_map_over_foxglove_websocket(tmp_path: Path) -> None:
    from mcsm_client.client import MapClient

    rng = np.random.default_rng(20261124)
    ops = default_ops(rng)[:9]
    d = start_daemon(tmp_path, "--samples", str(N), name="live")
    view: subprocess.Popen[str] | None = None
    try:
        with MapClient(connect=d.endpoint, timeout_s=30) as c:
            for op in ops:
                apply(c, op)
            view, url = start_view(tmp_path, d.endpoint, free_port())
            topic = "/mcsm/default/scene"

            async def session() -> None:
                async with websockets.connect(url, subprotocols=[SUBPROTOCOL],
                                              max_size=None) as ws:
                    assert ws.subprotocol == SUBPROTOCOL
                    fc = FoxgloveClient(ws)
                    await fc.handshake({topic, "/mcsm/default/tf", "/mcsm/default/samples"})
                    assert fc.server_info is not None
                    ch = fc.channels[topic]
                    assert (ch["schemaName"], ch["encoding"], ch["schemaEncoding"]) == \
                        ("foxglove.SceneUpdate", "protobuf", "protobuf")
                    cls = message_class(ch["schemaName"], base64.b64decode(ch["schema"]))
                    await fc.subscribe(7, topic)
                    m = build_map(ops)
                    want = set(m.frames())  # type: ignore[attr-defined]
                    scene = await fc.next_message(7, cls, lambda s: frame_ids(s) == want)
                    check_scene_against_map(scene, m)
                    # the map changes: a new landmark shows up in the live scene
                    new = ("update", "x4", "l9", planar_point(rng, N, [0.3, -0.7]))
                    apply(c, new)
                    m2 = build_map([*ops, new])
                    scene = await fc.next_message(7, cls, lambda s: "l9" in frame_ids(s))
                    check_scene_against_map(scene, m2)

            asyncio.run(session())
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
        view.send_signal(signal.SIGINT)
        assert view.wait(timeout=30) == 0, (tmp_path / "view.log").read_text()
        log = (tmp_path / "view.log").read_text()
        assert "Traceback" not in log
    finally:
        if view is not None and view.poll() is None:
            view.kill()
            view.wait(timeout=10)
        d.stop(signal.SIGINT)


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
