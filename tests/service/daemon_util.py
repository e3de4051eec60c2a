"""Start ``mcsm serve`` as a real subprocess on a free loopback port; AT test data."""

from __future__ import annotations

import signal
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from mcsm.core.quat import qexp
from mcsm_client.process import McsmProcess, ServerProcess, free_port, loopback_endpoint

STARTUP_DEADLINE_S = 30.0

__all__ = ["Daemon", "free_port", "noisy_at", "start_daemon", "start_router", "wait_for"]


class Daemon(ServerProcess):
    """A test's server: :class:`mcsm_client.process.ServerProcess` whose :meth:`stop` fails
    the test when the server ignored the signal."""

    log_path: Path

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 30.0) -> int:
        """Send ``sig`` and wait (bounded) for the exit code."""
        code = super().stop(sig, timeout_s)
        if self.killed_after_timeout:
            raise AssertionError(f"daemon ignored signal {sig}; log:\n{self.log_text()}")
        assert code is not None
        return code


def start_daemon(workdir: Path, *args: str, record: Path | None = None,
                 name: str = "d", endpoint: str | None = None,
                 listen_on: str | None = None, env: dict[str, str] | None = None) -> Daemon:
    """Run ``python -m mcsm.cli serve`` and wait (with a deadline) for ``listening on``.

    With ``endpoint`` given, no ``--listen`` is passed (the endpoint comes from a config file
    in ``args``) and the ``listening on`` line must name it; ``endpoint="-"``: the server
    joins a router (``--connect`` in ``args``) and listens nowhere. ``listen_on`` reuses a known
    endpoint (a restart on the same port); ``env`` adds environment variables.
    """
    d = Daemon(record if record is not None else workdir / f"{name}.mcap",
               extra_args=args, endpoint=endpoint or listen_on, listen=not endpoint,
               log_path=workdir / f"{name}.log", cwd=workdir, env=env,
               ready_timeout_s=STARTUP_DEADLINE_S)
    try:
        d.start()
    except RuntimeError as exc:
        raise AssertionError(str(exc)) from None
    return d


def start_router(workdir: Path, *args: str, endpoint: str | None = None
                 ) -> tuple[McsmProcess, str]:
    """Run ``mcsm router --listen ENDPOINT`` (a free loopback one unless given; ``args``: more
    flags, e.g. ``--zenoh-config``) and wait for ``routing on``; its log goes to
    ``router-<port>.log``. Stop it with ``.stop()`` (or ``.stop(signal.SIGKILL)``)."""
    ep = endpoint or loopback_endpoint()
    r = McsmProcess(["router", "--listen", ep, *args], ready="routing on", cwd=workdir,
                    log_path=workdir / f"router-{ep.rsplit(':', 1)[-1]}.log",
                    ready_timeout_s=STARTUP_DEADLINE_S)
    try:
        r.start()
    except RuntimeError as exc:
        raise AssertionError(str(exc)) from None
    return r, ep


def wait_for(what: str, fn: Callable[[], object], deadline_s: float = 60.0) -> None:
    """Poll ``fn`` every 50 ms until it is true; fail the test naming ``what`` after
    ``deadline_s``."""
    t_end = time.monotonic() + deadline_s
    while time.monotonic() < t_end:
        if fn():
            return
        time.sleep(0.05)
    raise AssertionError(f"{what}: not within {deadline_s} s")


def noisy_at(rng: np.random.Generator, n: int, t: list[float], sigma_t: float = 0.05,
             sigma_r: float = 0.01, yaw: float = 0.0) -> np.ndarray:
    """An ``(n, 7)`` AT around translation ``t`` and a yaw, with small tangent noise."""
    x = np.empty((n, 7))
    x[:, :3] = np.asarray(t) + sigma_t * rng.standard_normal((n, 3))
    w = sigma_r * rng.standard_normal((n, 3))
    w[:, 2] += yaw
    x[:, 3:] = qexp(w)
    return x
