"""What a new user tripped over at the shell, against a real server: request ids in ``update``,
``--json`` and ``watch``; a constraint the gate refused is exit 4; ``retract`` prints no
``component=None``; ``info`` counts failed requests as such and says ``1 frame``; a refused
connection says so at once; ``MapClient.update`` takes points; a zero quaternion is called
zero."""

from __future__ import annotations

import json
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.errors import BadMessage, InvalidSamples, Timeout, UnknownFrame, Unreachable
from mcsm_client.cli import EXIT_GATE_REJECTED, main
from mcsm_client.client import MapClient

from tests.service.daemon_util import Daemon, free_port, noisy_at, start_daemon

N = 32


def test_ids_exit_codes_and_messages_at_the_shell(tmp_path: Path, daemons: list[Daemon],
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N))
    daemons.append(d)
    conn = ["--connect", d.endpoint]
    # watch runs beside the updates and prints each event's request id
    watched: list[int] = []
    t = threading.Thread(target=lambda: watched.append(main(["watch", "--count", "3",
                                                             "--duration-s", "60", *conn])))
    t.start()
    time.sleep(1.0)  # the subscription is declared (events are best effort)
    assert main(["update", "a", "b", "--planar", "1", "0", "0", "--sigma", "0.01", "0.01",
                 "0.001", *conn]) == 0
    assert main(["update", "b", "c", "--planar", "1", "0", "0", "--sigma", "0.01", "0.01",
                 "0.001", "--json", *conn]) == 0
    # a loop closure 50 sigma off: the gate refuses it; the ack says so and so does $?
    code = main(["update", "a", "c", "--planar", "2.5", "0", "0", "--sigma", "0.01", "0.01",
                 "0.001", *conn])
    assert code == EXIT_GATE_REJECTED == 4
    t.join(timeout=60)
    assert watched == [0]
    out = capsys.readouterr().out.splitlines()  # the watch's lines and the updates' replies
    acks = [ln for ln in out if ln.startswith(("ok ", "rejected "))]
    (js,) = [json.loads(ln) for ln in out if ln.startswith("{")]
    events = [ln for ln in out if ln.startswith("seq ")]
    assert acks[0].startswith("ok seq=1 id=") and " new_component component=a" in acks[0]
    update_id = acks[0].split("id=")[1].split()[0]
    assert js["request_id"] and js["seq"] == 2 and js["kind"] == "new_frame"
    # a gated closure is acknowledged, but its line does not start with "ok"
    assert acks[1].startswith("rejected seq=3 id=") and " component=a verdict=rejected " \
        "nis=" in acks[1]
    assert len(events) == 3, out
    assert f"id={update_id} verdict=accepted component=a" in events[0]
    assert f"id={js['request_id']} verdict=accepted" in events[1]
    assert " rejected " in events[2] and "verdict=" not in events[2]  # the kind says it
    # info: a failed query is a request answered with an error, not a rejected input
    with MapClient(connect=d.endpoint, timeout_s=10) as c, pytest.raises(UnknownFrame):
        c.query("a", "nowhere")
    assert main(["info", *conn]) == 0
    out = capsys.readouterr().out
    assert "rejected inputs" not in out
    assert "requests answered with an error (any kind, queries too): 1 (UnknownFrame 1)" in out
    assert "updates by verdict: accepted 2, rejected 1 (rejected: refused by the " \
        "gate" in out
    assert "3 frames in 1 component: a (3 frames)" in out  # not "1 components"
    # retract: the target's verdict, and no "component=None"
    assert main(["retract", update_id, *conn]) == 0
    out = capsys.readouterr().out
    assert "component=None" not in out and f"target={update_id} verdict=retracted" in out
    assert out.count("verdict=") == 1
    assert d.stop(signal.SIGINT) == 0


def test_map_client_takes_points_and_names_update_point(tmp_path: Path,
                                                        daemons: list[Daemon]) -> None:
    d = start_daemon(tmp_path, "--samples", str(N))
    daemons.append(d)
    rng = np.random.default_rng(5)
    with MapClient(connect=d.endpoint, timeout_s=10) as c:
        c.update("a", "b", noisy_at(rng, N, [1, 0, 0]))
        pts = np.array([2.0, 1.0, 0.0]) + 0.05 * rng.standard_normal((N, 3))
        ack = c.update("b", "tree", pts)  # (N, 3): a point, as StochasticMap.update takes
        assert ack.kind == "new_frame" and "tree" in ack.frames_added
        with pytest.raises(BadMessage, match=r"\(N, 3\) for a point \(update_point\)"):
            c.update("b", "bush", np.zeros((N, 5)))
        # a zero quaternion is called zero (the wire's check, the same words as the core's)
        x = noisy_at(rng, N, [1, 0, 0])
        x[4, 3:] = 0.0
        with pytest.raises(InvalidSamples, match=r"the quaternion of sample 4 is zero "
                                                 r"\(0, 0, 0, 0\): not a rotation"):
            c.update("b", "c", x)
        # the server refused nothing it applied: the map has the point
        assert c.info().n_frames == 3
    with pytest.raises(InvalidSamples, match=r"sample 4 is zero \(0, 0, 0, 0\)"):
        StochasticMap(N).update("p", "q", x)
    x[4, 3:] = [2.0, 0.0, 0.0, 0.0]
    with pytest.raises(InvalidSamples, match=r"sample 4 has norm 2, not 1 \(\|q\|² = 4;"):
        StochasticMap(N).update("p", "q", x)
    assert d.stop(signal.SIGINT) == 0


def test_a_refused_connection_says_so_at_once(capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing listens: the message names the endpoint and Zenoh's 2 s connect timeout, not
    "no reply within 10 s" after 2.4 s."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    assert main(["info", "--connect", endpoint]) == 3  # MapClient raised Unreachable
    err = capsys.readouterr().err
    assert err.startswith(f"mcsm-client info: cannot connect to {endpoint}: no Zenoh session "
                          "opened within Zenoh's connect timeout, 2 s")
    assert "no reply within" not in err
    assert "is `mcsm serve` (or a router) running there?" in err and ".rs:" not in err
    assert time.monotonic() - t0 < 9.0
    assert issubclass(Unreachable, Timeout)  # code catching Timeout still catches it


def test_a_refused_handshake_is_not_called_a_missing_server(
        capsys: pytest.CaptureFixture[str]) -> None:
    """Something accepts the TCP connection but the Zenoh session does not open (a server that
    wants credentials or TLS answers Zenoh's handshake no better than this socket does): the
    message says so instead of asking whether a server runs there."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        endpoint = f"tcp/127.0.0.1:{listener.getsockname()[1]}"
        assert main(["info", "--connect", endpoint]) == 3
    err = capsys.readouterr().err
    assert f"cannot connect to {endpoint}" in err and "running there?" not in err
    assert "something listens there but did not complete Zenoh's handshake: it wants " \
           "credentials or TLS" in err


def test_serve_on_a_port_in_use_or_out_of_range_says_what_to_do(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    from mcsm.cli import main as mcsm_main

    monkeypatch.chdir(tmp_path)
    with socket.create_server(("127.0.0.1", 0)) as taken:
        endpoint = f"tcp/127.0.0.1:{taken.getsockname()[1]}"
        for argv in (["serve", "--listen", endpoint], ["router", "--listen", endpoint]):
            assert mcsm_main(argv) == 2
            err = capsys.readouterr().err
            assert "Address already in use" in err and ".rs:" not in err, err
            assert "pick a free port with --listen tcp/127.0.0.1:PORT" in err
    assert mcsm_main(["serve", "--listen", "tcp/127.0.0.1:99999"]) == 2
    assert "expected a port from 0 to 65535" in capsys.readouterr().err
    assert not list(tmp_path.rglob("*.mcap"))  # nothing recorded


def test_serve_record_refuses_an_existing_file_and_a_missing_folder(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A recording is never overwritten (the message says how to go on from it), and a folder
    the user names must exist: a mistyped path is not created and recorded into."""
    from mcsm.cli import main as mcsm_main

    old = tmp_path / "old.mcap"
    old.write_bytes(b"")
    assert mcsm_main(["serve", "--record", str(old)]) == 2
    err = capsys.readouterr().err
    assert err == (f"mcsm serve: --record {old}: exists; a recording is never overwritten: name "
                   f"a new file, or go on from it with --restore {old} --record NEW.mcap\n")
    typo = tmp_path / "nosuch" / "x.mcap"
    assert mcsm_main(["serve", "--record", str(typo)]) == 2
    assert f"its folder {typo.parent} does not exist" in capsys.readouterr().err
    assert not typo.parent.exists() and old.read_bytes() == b""


def test_replication_flags_are_checked_before_anything_starts(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """docs/fleet.md: --log-max-age must hold --id-ttl-s (the log's de-duplication window);
    --nats-auth needs --nats; and a server without --nats imports nothing of NATS."""
    import subprocess
    import sys

    from mcsm.cli import main as mcsm_main

    monkeypatch.chdir(tmp_path)
    listen = ["--listen", f"tcp/127.0.0.1:{free_port()}"]
    assert mcsm_main(["serve", *listen, "--nats", "nats://127.0.0.1:1", "--log-max-age", "10",
                      "--id-ttl-s", "600"]) == 2
    assert "--log-max-age 10 is below --id-ttl-s 600" in capsys.readouterr().err
    assert mcsm_main(["serve", *listen, "--nats-auth", "x.json"]) == 2
    assert "--nats-auth needs --nats URL" in capsys.readouterr().err
    assert not list(tmp_path.rglob("*.mcap"))
    # a server identity's NATS credentials (docs/fleet.md): user, password and TLS files
    from mcsm.cli import build_parser
    from mcsm.cli.serve_cmd import _nats_options
    from mcsm.errors import McsmError

    auth = tmp_path / "server1.nats.json"
    auth.write_text(json.dumps({"user": "server1", "password": "pw", "tls_ca": "ca.pem",
                                "tls_cert": "s.pem", "tls_key": "s.key"}))
    o = _nats_options(build_parser().parse_args(["serve", "--nats", "nats://127.0.0.1:1",
                                                 "--nats-auth", str(auth)]))
    assert (o.user, o.password, o.tls_ca, o.tls_cert, o.tls_key) == \
        ("server1", "pw", "ca.pem", "s.pem", "s.key")
    auth.write_text(json.dumps({"user": "server1", "token": "x"}))
    with pytest.raises(McsmError, match="expected a JSON object of strings with keys"):
        _nats_options(build_parser().parse_args(["serve", "--nats", "nats://127.0.0.1:1",
                                                 "--nats-auth", str(auth)]))
    code = ("import sys\n"
            "from mcsm.cli import build_parser\n"
            "from mcsm.cli.serve_cmd import _nats_options\n"
            "import mcsm.serve.server\n"
            "assert _nats_options(build_parser().parse_args(['serve'])) is None\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'nats'"
            " or m == 'mcsm.serve.replication'))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == "[]", r.stdout + r.stderr
