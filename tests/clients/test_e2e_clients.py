"""End to end over real Zenoh sessions: ``mcsm serve`` subprocesses on free loopback ports.

The sim client and the multi-robot demo must give over the wire exactly what they give
in-process with the same seed (same samples in the same order, so bit-identical maps), and the
joined multi-robot map must be consistent with ground truth. The CLI's commands and exit codes
are exercised against the same server.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm_client.cli import main as cli_main
from mcsm_client.client import MapClient
from mcsm_client.demo import DemoConfig, run_demo
from mcsm_client.multirobot import MultiRobotConfig, run_multirobot
from mcsm_client.process import ServerProcess, free_port
from mcsm_client.sim import SimConfig, run_sim

N = 200  # the served maps' N (conftest.SERVER_N)


def test_sim_over_zenoh_equals_in_process(server: ServerProcess) -> None:
    cfg = SimConfig(n_iterations=40, score_every=20)
    local = run_sim(cfg, StochasticMap(N), rng=np.random.default_rng(20261201))
    with MapClient(map="sim", connect=server.endpoint, timeout_s=20.0) as c:
        remote = run_sim(cfg, c, rng=np.random.default_rng(20261201))
    assert remote.digest == local.digest
    assert [r.iteration for r in remote.rows] == [20, 40]
    assert remote.final.rms_m == local.final.rms_m
    assert remote.n_updates == local.n_updates > 40
    # σ_laser = 0.4 m per axis: one sighting gives ~0.57 m RMS; the map does better
    assert 0.0 < remote.final.rms_m < 0.6
    assert 0.2 < remote.final.nees_per_dof < 5.0


def test_multirobot_two_servers_join_and_close_loops_consistently(
        server: ServerProcess, server_b: ServerProcess) -> None:
    cfg = MultiRobotConfig(n_landmarks=100)
    with MapClient(map="robots", connect=server.endpoint, timeout_s=20.0) as ca, \
            MapClient(map="robots", connect=server_b.endpoint, timeout_s=20.0) as cb:
        res = run_multirobot(cfg, ca, cb, rng=np.random.default_rng(20261202))
        frames_a = set(ca.info().frames)
    assert res.import_kind == "import" and res.join_kind == "join"
    assert res.cross_loop_closures > 10
    assert any(f.startswith("A.") for f in frames_a) and any(f.startswith("B.") for f in frames_a)
    # the same run in two in-process maps (B's exported and imported as between the
    # servers): identical estimates. (B as a component of A's own map is not the same run: the
    # gate's scale and the relinearisation policy's failure window belong to a map.)
    local = run_multirobot(cfg, StochasticMap(N), StochasticMap(N),
                           rng=np.random.default_rng(20261202))
    assert [s.rms_m for s in res.scores] == [s.rms_m for s in local.scores]
    # Consistency of the joined map with ground truth, both robots' landmarks. At a fixed N
    # the core's own NEES drifts above 1 (issue 6; one robot's map here: 1.3-1.9 per dof at
    # N = 200 over 5 seeds); the join and the cross loop closures must not add much to that.
    for robot in ("A", "B"):
        alone = res.score(f"{robot} alone").nees_per_dof
        s = res.score(f"after loop closures: {robot}'s")
        assert s.n_landmarks > 30
        assert s.rms_m < 0.8, s
        assert s.nees_per_dof < 4.0, s
        assert s.nees_per_dof < 1.5 * alone, (s, alone)
    # the cross-robot loop closures pull B's landmarks towards the truth
    assert res.score("after loop closures: B's").rms_m < res.score("joined: B's landmarks").rms_m


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = cli_main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_cli_commands_and_exit_codes(server: ServerProcess, tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    conn = ("--connect", server.endpoint, "--map", "cli")
    code, out, _ = _cli(capsys, "update", "w", "r", "--planar", "1", "0", "0.1",
                        "--sigma", "0.1", "0.1", "0.01", "--seed", "1", *conn)
    assert code == 0 and "new_component" in out
    code, out, _ = _cli(capsys, "update", "r", "p", "--point", "2", "1", "--sigma", "0.2",
                        "0.2", "--json", *conn)
    assert code == 0 and json.loads(out)["kind"] == "new_frame"
    code, out, _ = _cli(capsys, "query", "w", "r", "--json", "--samples-out",
                        str(tmp_path / "s.npy"), *conn)
    got = json.loads(out)
    assert code == 0 and abs(got["mean"][0] - 1.0) < 0.1
    assert np.load(tmp_path / "s.npy").shape == (N, 7)
    # like every writer, --samples-out refuses an existing file without --force
    code, _, err = _cli(capsys, "query", "w", "r", "--samples-out", str(tmp_path / "s.npy"),
                        *conn)
    assert code == 2 and "exists (--force overwrites it)" in err
    code, _, _ = _cli(capsys, "query", "w", "r", "--samples-out", str(tmp_path / "s"),
                      "--force", *conn)  # np.save's own suffix: the same file
    assert code == 0
    code, out, _ = _cli(capsys, "info", "--json", *conn)
    info = json.loads(out)
    assert code == 0 and info["n_samples"] == N and info["n_frames"] == 3
    code, out, _ = _cli(capsys, "remove", "p", *conn)
    assert code == 0 and "remove" in out
    # the server refuses: exit 1 with its typed error
    code, _, err = _cli(capsys, "query", "w", "nowhere", *conn)
    assert code == 1 and "UnknownFrame" in err
    # usage errors: exit 2
    code, _, err = _cli(capsys, "update", "w", "r", "--planar", "1", "0", "0", "--sigma", "1",
                        *conn)
    assert code == 2 and "--sigma needs 3" in err
    code, _, err = _cli(capsys, "play", str(tmp_path / "missing.g2o"), *conn)
    assert code == 2 and "no such dataset file" in err


def test_cli_play_and_watch(server: ServerProcess, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("gtsam")
    conn = ("--connect", server.endpoint, "--map", "play")
    with MapClient(map="play", connect=server.endpoint, timeout_s=20.0) as c, c.watch() as ev:
        code, out, err = _cli(capsys, "play", "gtsam:victoria_park.txt", "--max-constraints",
                              "60", "--bounded", "--no-progress", "--json", *conn)
        assert code == 0, err
        summary = json.loads(out)
        assert summary["total"] == 60 and sum(summary["applied"].values()) == 60
        assert summary["removed"] > 0
        first = ev.get(10.0)
    assert first is not None and first.seq >= 1
    code, out, _ = _cli(capsys, "watch", "--duration-s", "0.3", *conn)
    assert code == 0


def test_cli_timeout_exit_code_and_help() -> None:
    # nobody listens on this port: the client cannot connect -> exit 3
    ep = f"tcp/127.0.0.1:{free_port()}"
    r = subprocess.run([sys.executable, "-m", "mcsm_client.cli", "info", "--connect", ep,
                        "--timeout-s", "1"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 3, r.stderr
    assert f"cannot connect to {ep}: no Zenoh session opened" in r.stderr
    r = subprocess.run([sys.executable, "-m", "mcsm_client.cli", "play", "--help"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "--bounded" in r.stdout


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_cli_interrupted_exit_code(server: ServerProcess) -> None:
    """Exit code 130 (README, ``mcsm-client --help``): Ctrl-C (SIGINT) during a command."""
    # As a terminal's foreground command: SIGINT at its default. A suite started in the
    # background (CI, `make test &`, nohup) ignores SIGINT and its children inherit that: the
    # command then never sees the Ctrl-C (SigIgn in /proc showed it). -X faulthandler: should
    # it hang anyway, SIGABRT prints every thread's stack into the failure.
    p = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "mcsm_client.cli",
                          "watch", "--connect", server.endpoint], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)
    assert p.stderr is not None
    line = p.stderr.readline()  # "watching map 'default' (Ctrl-C to stop)": it is running
    assert "watching map" in line, line
    p.send_signal(signal.SIGINT)
    try:
        _, err = p.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        status = Path(f"/proc/{p.pid}/status").read_text()
        p.send_signal(signal.SIGABRT)
        _, err = p.communicate(timeout=10)
        raise AssertionError(f"no exit 30 s after SIGINT\n{status}\n{err}") from None
    assert p.returncode == 130, err
    assert "interrupted" in err and "Traceback" not in err


def test_demo_end_to_end_small(tmp_path: Path) -> None:
    lines: list[str] = []
    rep = run_demo(DemoConfig(n_samples=50, n_iterations=20, score_every=10,
                              out_dir=tmp_path / "run", multirobot=False), log=lines.append)
    names = {p.name for p in rep.files}
    assert {"server.mcap", "sim.csv", "summary.json"} <= names
    assert all(p.exists() for p in rep.files)
    assert any("accuracy summary" in s for s in lines)
    assert any("exit codes [0]" in s for s in lines)
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["sim"]["final"]["iteration"] == 20
    assert summary["server"]["seq"] > 20
    assert summary["server_exit_codes"] == [0]


def test_cli_watch_prints_events(server: ServerProcess) -> None:
    """``watch --count 2`` exits after two events; updates are sent until it has seen them
    (polling with a deadline: the subscription's start is not observable from outside)."""
    proc = subprocess.Popen([sys.executable, "-m", "mcsm_client.cli", "watch", "--count", "2",
                             "--json", "--duration-s", "60", "--connect", server.endpoint,
                             "--map", "cli"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        x = np.zeros((N, 7))
        x[:, 3] = 1.0
        x[:, 0] = np.linspace(0.9, 1.1, N)
        deadline = time.monotonic() + 60.0
        k = 0
        with MapClient(map="cli", connect=server.endpoint, timeout_s=20.0) as c:
            while proc.poll() is None and time.monotonic() < deadline:
                c.update(f"watch{k}", f"watch{k + 1}", x)
                k += 1
                try:
                    proc.wait(timeout=0.5)
                except subprocess.TimeoutExpired:
                    pass
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)
    assert proc.returncode == 0, err
    events = [json.loads(line) for line in out.splitlines()]
    assert len(events) == 2
    assert events[1]["seq"] > events[0]["seq"]
    assert events[0]["op"] == "update"


def test_cli_in_process_sim_multirobot_and_zenoh_config(
        server: ServerProcess, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib")
    code, out, err = _cli(capsys, "sim", "--in-process", "50", "--iterations", "20",
                          "--score-every", "10", "--csv", str(tmp_path / "s.csv"), "--png",
                          str(tmp_path / "s.png"), "--json")
    assert code == 0, err
    assert json.loads(out)["final"]["iteration"] == 20
    assert (tmp_path / "s.csv").exists() and (tmp_path / "s.png").stat().st_size > 1000
    code, out, err = _cli(capsys, "multirobot", "--in-process", "50", "--landmarks", "40",
                          "--json")
    assert code == 0, err
    assert json.loads(out)["join"] == "join"
    # a Zenoh JSON5 file instead of --connect
    conf = tmp_path / "client.json5"
    conf.write_text(json.dumps({
        "mode": "client", "connect": {"endpoints": [server.endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
    code, out, err = _cli(capsys, "info", "--zenoh-config", str(conf), "--map", "cli",
                          "--json")
    assert code == 0, err
    assert json.loads(out)["n_samples"] == N
