"""Every example in clients/examples runs to the end, as a real process, with a small N."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from mcsm_client.process import ServerProcess

EXAMPLES = Path(__file__).resolve().parents[2] / "clients" / "examples"


def _run(name: str, *args: str) -> str:
    r = subprocess.run([sys.executable, str(EXAMPLES / name), *args], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, f"{name} failed:\n{r.stdout}\n{r.stderr}"
    return r.stdout


def test_every_example_is_tested() -> None:
    names = {p.name for p in EXAMPLES.glob("*.py")}
    assert names == {"quickstart.py", "autocorrelated_odometry.py", "play_victoria_park.py",
                     "paper_sim.py", "two_robots.py"}


def test_quickstart_against_the_server(server: ServerProcess) -> None:
    out = _run("quickstart.py", "--connect", server.endpoint, "--map", "examples")
    assert "loop_closure" in out and "L_xy" in out


def test_autocorrelated_odometry() -> None:
    out = _run("autocorrelated_odometry.py", "--in-process", "400", "--rho", "0.8")
    got = eval(out.strip(), {})  # the example prints a dict of floats
    assert abs(got["mean_corr_dx"] - 0.8) < 0.1
    # ten 1 m steps with sigma_x 0.05 and rho 0.8: wider than independent (0.158 m)
    assert got["final_sigma_x"] > 0.25


def test_play_victoria_park() -> None:
    pytest.importorskip("gtsam")
    out = _run("play_victoria_park.py", "--in-process", "50", "--max-constraints", "40")
    assert "40/40 constraints applied" in out


def test_paper_sim(tmp_path: Path) -> None:
    out = _run("paper_sim.py", "--in-process", "50", "--iterations", "10", "--csv",
               str(tmp_path / "s.csv"))
    assert "rms_m" in out and (tmp_path / "s.csv").read_text().startswith("iteration,")


def test_two_robots_on_two_servers(server: ServerProcess, server_b: ServerProcess) -> None:
    out = _run("two_robots.py", "--connect", server.endpoint, "--map", "examples",
               "--connect-b", server_b.endpoint, "--landmarks", "60")
    assert "rendezvous update: join" in out
