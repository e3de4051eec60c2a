"""Maps over several servers behind one Zenoh router (issue 18, part 1).

A router (``mcsm router``), two servers joined to it (``mcsm serve --connect``) serving
different maps, clients that connect to the router only and find each map by key alone;
``mcsm-client servers`` lists both; a third server claiming an already served map is refused.
All processes on 127.0.0.1.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm_client.cli import main as client_main
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon, start_router

N = 32


def test_two_servers_behind_one_router(tmp_path: Path, daemons: list[Daemon],
                                       capsys: pytest.CaptureFixture[str]) -> None:
    router, ep = start_router(tmp_path)
    try:
        a = start_daemon(tmp_path, "--samples", str(N), "--map", "a", "--connect", ep,
                         name="a", endpoint="-")
        daemons.append(a)
        b = start_daemon(tmp_path, "--samples", str(N), "--map", "b", "--connect", ep,
                         name="b", endpoint="-")
        daemons.append(b)
        rng = np.random.default_rng(20261128)
        digests = {}
        for name in ("a", "b"):
            local = StochasticMap(N)
            with MapClient(map=name, connect=ep, timeout_s=15.0) as c:
                for k in range(4):
                    x = noisy_at(rng, N, [1.0, 0.0, 0.0])
                    c.update(f"{name}{k}", f"{name}{k + 1}", x)
                    local.update(f"{name}{k}", f"{name}{k + 1}", x)
                x = local.query(f"{name}0", f"{name}4")[rng.permutation(N)]
                assert c.update(f"{name}0", f"{name}4", x).kind == "loop_closure"
                local.update(f"{name}0", f"{name}4", x)
                info = c.info()
                assert info.digest == local.state_digest()
                digests[name] = info.server_id
        assert digests["a"] != digests["b"]  # two processes
        assert client_main(["servers", "--json", "--connect", ep]) == 0
        rows = json.loads(capsys.readouterr().out)["servers"]
        assert {(r["map"], r["server"]) for r in rows} == {("a", digests["a"]),
                                                         ("b", digests["b"])}
        # a second server for map a is refused
        third = subprocess.run(
            [sys.executable, "-m", "mcsm.cli", "serve", "--samples", str(N), "--map", "a",
             "--connect", ep, "--record", str(tmp_path / "third.mcap")],
            capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert third.returncode == 2
        assert "already served by server" in third.stderr
        assert "start this server with --standby-of a" in third.stderr
        for d in (a, b):
            assert d.stop(signal.SIGINT) == 0, d.log_text()
    finally:
        router.stop()
