"""``mcsm serve`` (or ``mcsm router``) as a child process on a free loopback port.

The one helper that starts a server for ``make run`` (:mod:`mcsm_client.demo`), the tests and
the benchmarks: it runs ``python -m mcsm.cli <command> ...``, waits with a deadline for the
line the command prints when it is ready (``listening on <endpoint>``, ``routing on ...``),
and stops it with SIGINT (the recording is closed cleanly), then SIGKILL if it does not exit.
It only starts the command line the user would type, so it depends on nothing but the CLI.

Example::

    from mcsm_client.process import ServerProcess
    from mcsm_client.client import MapClient

    with ServerProcess("run/server.mcap", n_samples=100) as server:
        with MapClient(connect=server.endpoint) as client:
            print(client.info().seq)
"""

from __future__ import annotations

import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO

READY_TIMEOUT_S = 60.0
"""Default deadline for the ready line (a cold interpreter plus Zenoh take a few seconds)."""

__all__ = ["McsmProcess", "ServerProcess", "free_port", "loopback_endpoint", "READY_TIMEOUT_S"]


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def loopback_endpoint() -> str:
    """``tcp/127.0.0.1:<free port>``: a Zenoh endpoint to listen on."""
    return f"tcp/127.0.0.1:{free_port()}"


class McsmProcess:
    """``python -m mcsm.cli <args>``, ready once a stdout line starts with ``ready``.

    Parameters
    ----------
    args : sequence of str
        The command line after ``mcsm`` (``["serve", "--listen", ...]``).
    ready : str
        The start of the line that says the command is ready.
    log_path : path, optional
        Where its stderr (its log) goes; ``None``: discarded.
    cwd : path, optional
        Its working directory.
    env : mapping, optional
        Environment variables added to this process's.
    ready_timeout_s : float
        How long :meth:`start` waits for the ready line.

    Attributes
    ----------
    proc : subprocess.Popen or None
        The child, once started.
    ready_line : str
        The ready line it printed.
    lines : queue.Queue
        Its later stdout lines (``None`` once stdout closed).
    """

    def __init__(self, args: Sequence[str], *, ready: str = "listening on",
                 log_path: str | os.PathLike[str] | None = None,
                 cwd: str | os.PathLike[str] | None = None, env: Mapping[str, str] | None = None,
                 ready_timeout_s: float = READY_TIMEOUT_S) -> None:
        self.cmd = [sys.executable, "-m", "mcsm.cli", *args]
        self.ready = ready
        self.log_path = Path(log_path) if log_path is not None else None
        self.cwd = cwd
        self.env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        self.ready_timeout_s = float(ready_timeout_s)
        self.proc: subprocess.Popen[str] | None = None
        self.ready_line = ""
        self.lines: queue.Queue[str | None] = queue.Queue()
        self.returncode: int | None = None
        self.killed_after_timeout = False
        """True when :meth:`stop` had to SIGKILL it after its signal was ignored."""
        self._log: IO[str] | None = None

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def start(self) -> McsmProcess:
        """Start it and wait for the ready line.

        Raises
        ------
        RuntimeError
            If it exits or stays silent past ``ready_timeout_s`` (its log's tail included);
            it is stopped first.
        """
        if self.log_path is not None:
            self.log_path.parent.mkdir(parents=True, exist_ok=True)
            self._log = open(self.log_path, "w", encoding="utf-8")  # noqa: SIM115 - see stop
        self.proc = subprocess.Popen(
            self.cmd, stdout=subprocess.PIPE,
            stderr=self._log if self._log is not None else subprocess.DEVNULL, text=True,
            cwd=self.cwd, env=self.env)
        out = self.proc.stdout
        if out is None:  # pragma: no cover - Popen with PIPE always sets it
            raise RuntimeError("no stdout pipe")

        def pump() -> None:
            for line in out:
                self.lines.put(line)
            self.lines.put(None)

        threading.Thread(target=pump, daemon=True).start()
        deadline = time.monotonic() + self.ready_timeout_s
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                self.stop()
                raise RuntimeError(f"{self._name()} did not get ready in "
                                   f"{self.ready_timeout_s:g} s\n{self.log_tail()}")
            try:
                line = self.lines.get(timeout=min(left, 0.5))
            except queue.Empty:
                continue
            if line is None:
                self.stop()
                raise RuntimeError(f"{self._name()} exited early (code {self.returncode})\n"
                                   f"{self.log_tail()}")
            if line.startswith(self.ready):
                self.ready_line = line.rstrip("\n")
                return self

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 20.0) -> int | None:
        """Send ``sig`` (SIGINT: a clean shutdown) and wait up to ``timeout_s`` for the exit;
        SIGKILL after that. Returns the exit code (negative: the signal that ended it).
        Idempotent."""
        if self.proc is not None and self.returncode is None:
            if self.proc.poll() is None:
                self.proc.send_signal(sig)
                try:
                    self.proc.wait(timeout=timeout_s)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait(timeout=timeout_s)
                    self.killed_after_timeout = True
            self.returncode = self.proc.returncode
            if self.proc.stdout is not None:
                self.proc.stdout.close()
        if self._log is not None:
            self._log.close()
            self._log = None
        return self.returncode

    def log_text(self) -> str:
        """The whole log (``""`` without a log file)."""
        try:
            return self.log_path.read_text(encoding="utf-8") if self.log_path else ""
        except OSError:
            return ""

    def log_tail(self, n_lines: int = 20) -> str:
        """The last lines of the log."""
        return "\n".join(self.log_text().splitlines()[-n_lines:])

    def _name(self) -> str:
        return f"mcsm {self.cmd[3] if len(self.cmd) > 3 else ''}".rstrip()

    def __enter__(self) -> McsmProcess:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()


class ServerProcess(McsmProcess):
    """``mcsm serve`` on a free loopback port (or as ``args`` say); a context manager.

    Parameters
    ----------
    record : path
        The MCAP recording to write (``--record``); its log goes next to it unless
        ``log_path`` says otherwise.
    n_samples : int, optional
        N of the served maps (``--samples``; default: the server's).
    maps : sequence of str
        Map names to serve (``--map`` each).
    extra_args : sequence of str
        More ``mcsm serve`` flags (``--method paper``, ``--zenoh-config FILE``, ...).
    endpoint : str, optional
        The endpoint to listen on (a restart on a known port); default a free loopback one.
    listen : bool
        Pass ``--listen endpoint``. False: the endpoint comes from ``extra_args`` (a config
        file, whose listening endpoint must be ``endpoint``), or, with ``endpoint="-"``, the
        server joins a router (``--connect``) and listens nowhere.
    log_path, cwd, env, ready_timeout_s
        As for :class:`McsmProcess`.

    Attributes
    ----------
    endpoint : str
        ``tcp/127.0.0.1:<port>``, for ``MapClient(connect=...)``.
    """

    def __init__(self, record: str | os.PathLike[str], *,
                 n_samples: int | None = None, maps: Sequence[str] = (),
                 extra_args: Sequence[str] = (), endpoint: str | None = None,
                 listen: bool = True, log_path: str | os.PathLike[str] | None = None,
                 cwd: str | os.PathLike[str] | None = None, env: Mapping[str, str] | None = None,
                 ready_timeout_s: float = READY_TIMEOUT_S) -> None:
        self.record = Path(record)
        self.endpoint = endpoint if endpoint is not None else loopback_endpoint()
        args = ["serve", *(["--listen", self.endpoint] if listen else [])]
        if n_samples is not None:
            args += ["--samples", str(int(n_samples))]
        args += ["--record", str(self.record)]
        if log_path is None:
            log_path = self.record.with_suffix(".log")
        args += [a for m in maps for a in ("--map", m)]
        super().__init__([*args, *extra_args], log_path=log_path, cwd=cwd, env=env,
                         ready_timeout_s=ready_timeout_s)

    def start(self) -> ServerProcess:
        """Start the server and wait for ``listening on <endpoint>``.

        Raises
        ------
        RuntimeError
            If it exits, stays silent past ``ready_timeout_s``, or listens elsewhere.
        """
        self.record.parent.mkdir(parents=True, exist_ok=True)
        super().start()
        # "listening on ENDPOINT" or "listening on ENDPOINT (joined ROUTER...)"
        where = self.ready_line.split()[2] if len(self.ready_line.split()) > 2 else ""
        if self.endpoint != "-" and where != self.endpoint:
            self.stop()
            raise RuntimeError(f"mcsm serve listens on {where}, not {self.endpoint}")
        return self

    def __enter__(self) -> ServerProcess:
        return self.start()
