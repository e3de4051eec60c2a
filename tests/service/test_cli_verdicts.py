"""``mcsm-client verdict``, ``retract`` and ``reinstate`` against a real server."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np
import pytest
from mcsm_client.cli import main
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, noisy_at, start_daemon

N = 32


def test_cli_verdict_retract_reinstate(tmp_path: Path, daemons: list[Daemon],
                                       capsys: pytest.CaptureFixture[str]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N), "--gate", "0.99")
    daemons.append(d)
    rng = np.random.default_rng(77)
    with MapClient(connect=d.endpoint, timeout_s=10.0) as c:
        c.update("a", "b", noisy_at(rng, N, [1, 0, 0]), request_id="u1")
        c.update("b", "c", noisy_at(rng, N, [1, 0, 0]), request_id="u2")
    conn = ["--connect", d.endpoint]
    assert main(["verdict", "u2", "--json", *conn]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["verdict"]["status"] == "accepted"
    assert main(["retract", "u2", *conn]) == 0
    assert "verdict=retracted" in capsys.readouterr().out
    assert main(["verdict", "u2", *conn]) == 0
    assert "u2: retracted" in capsys.readouterr().out
    assert main(["reinstate", "u2", *conn]) == 0
    assert "verdict=reinstated" in capsys.readouterr().out
    assert main(["retract", "nope", *conn]) == 1  # refused by the server
    assert "InvalidOperation" in capsys.readouterr().err
    assert d.stop(signal.SIGINT) == 0
