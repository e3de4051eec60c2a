"""Start ``mcsm serve`` as a real subprocess on a free loopback port; AT test data."""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcsm.core.quat import qexp

STARTUP_DEADLINE_S = 30.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Daemon:
    proc: subprocess.Popen[str]
    endpoint: str
    record: Path
    log: Path
    lines: queue.Queue[str] = field(default_factory=queue.Queue)

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 30.0) -> int:
        """Send ``sig`` and wait (bounded) for the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=10)
            raise AssertionError(f"daemon ignored signal {sig}; log:\n{self.log_text()}"
                                 ) from None

    def log_text(self) -> str:
        return self.log.read_text() if self.log.exists() else ""


def start_daemon(workdir: Path, *args: str, record: Path | None = None,
                 name: str = "d", endpoint: str | None = None,
                 listen_on: str | None = None, env: dict[str, str] | None = None) -> Daemon:
    """Run ``python -m mcsm.cli serve`` and wait (with a deadline) for ``listening on``.

    With ``endpoint`` given, no ``--listen`` is passed (the endpoint comes from a config file
    in ``args``) and the ``listening on`` line must name it; ``endpoint="-"``: the server
    joins a router (``--connect`` in ``args``) and listens nowhere. ``listen_on`` reuses a known
    endpoint (a restart on the same port); ``env`` adds environment variables.
    """
    ep = endpoint or listen_on or f"tcp/127.0.0.1:{free_port()}"
    listen = [] if endpoint else ["--listen", ep]
    record = record if record is not None else workdir / f"{name}.mcap"
    log = workdir / f"{name}.log"
    full_env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
    with open(log, "w") as logf:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mcsm.cli", "serve", *listen, "--record", str(record),
             *args], stdout=subprocess.PIPE, stderr=logf, text=True, cwd=workdir,
            env=full_env)
    d = Daemon(proc, ep, record, log)
    assert proc.stdout is not None
    out = proc.stdout

    def pump() -> None:
        for line in out:
            d.lines.put(line)

    threading.Thread(target=pump, daemon=True).start()
    deadline = time.monotonic() + STARTUP_DEADLINE_S
    while time.monotonic() < deadline:
        try:
            line = d.lines.get(timeout=0.2)
        except queue.Empty:
            if proc.poll() is not None:
                raise AssertionError(f"daemon exited with {proc.returncode}:\n{d.log_text()}"
                                     ) from None
            continue
        if line.startswith("listening on "):
            assert endpoint == "-" or line.split()[-1] == ep  # "-": joined a router only
            return d
    proc.kill()
    proc.wait(timeout=10)
    raise AssertionError(f"no 'listening on' within {STARTUP_DEADLINE_S} s:\n{d.log_text()}")


def noisy_at(rng: np.random.Generator, n: int, t: list[float], sigma_t: float = 0.05,
             sigma_r: float = 0.01, yaw: float = 0.0) -> np.ndarray:
    """An ``(n, 7)`` AT around translation ``t`` and a yaw, with small tangent noise."""
    x = np.empty((n, 7))
    x[:, :3] = np.asarray(t) + sigma_t * rng.standard_normal((n, 3))
    w = sigma_r * rng.standard_normal((n, 3))
    w[:, 2] += yaw
    x[:, 3:] = qexp(w)
    return x
