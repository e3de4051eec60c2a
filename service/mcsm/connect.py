"""Connection flags and Zenoh configs, shared by ``mcsm``, ``mcsm-client`` and every example.

Defaults work on one machine with no router: the server is an embedded Zenoh *peer* listening
on ``tcp/127.0.0.1:7447``; clients open a Zenoh *client* session connected to it. Both turn off
multicast and gossip scouting (nothing leaves loopback), and the server turns off shared memory
(it bypasses ``max_message_size``), turns off batching (a 56 KB reply takes ~1.3 ms batched vs
~0.2 ms not) and caps incoming messages at 8 MiB (``shared/notes/ecosystem.md`` §0).

A ``--zenoh-config FILE`` (JSON5) replaces these defaults entirely, for real deployments
(routers, TLS, access control); an explicit ``--connect``/``--listen`` is still applied on top.

Example::

    parser = argparse.ArgumentParser()
    add_connection_args(parser)                    # --connect --map --prefix --zenoh-config
    args = parser.parse_args()
    with MapClient(**client_kwargs(args)) as client:
        ...
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Mapping
from typing import Any, Literal

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_MAP = "default"
DEFAULT_PREFIX = "mcsm"
MAX_MESSAGE_BYTES = 8 * 1024 * 1024
CONNECT_TIMEOUT_MS = 2000

ZenohConfigLike = str | os.PathLike[str] | Mapping[str, Any] | zenoh.Config | None


def add_connection_args(parser: argparse.ArgumentParser,
                        role: Literal["client", "server"] = "client") -> None:
    """Add ``--connect`` (client) or ``--listen`` (server), ``--map``, ``--prefix``,
    ``--zenoh-config`` to ``parser``.

    For the server ``--map`` may be repeated (one server, several maps); for a client it names
    the one map to talk to. Read the values back with :func:`client_kwargs` or directly
    (``args.connect``, ``args.listen``, ``args.map``, ``args.prefix``, ``args.zenoh_config``).
    """
    g = parser.add_argument_group("connection")
    if role == "server":
        g.add_argument("--listen", default=None, metavar="ENDPOINT",
                       help=f"Zenoh endpoint to listen on (default {DEFAULT_ENDPOINT}, "
                            "or the config file's)")
        g.add_argument("--map", action="append", default=None, metavar="NAME",
                       help=f"map to serve; repeat for several (default {DEFAULT_MAP!r})")
    else:
        g.add_argument("--connect", default=None, metavar="ENDPOINT",
                       help=f"server endpoint (default {DEFAULT_ENDPOINT}, "
                            "or the config file's)")
        g.add_argument("--map", default=DEFAULT_MAP, metavar="NAME",
                       help=f"map name (default {DEFAULT_MAP!r})")
    g.add_argument("--prefix", default=DEFAULT_PREFIX,
                   help=f"key expression prefix (default {DEFAULT_PREFIX!r})")
    g.add_argument("--zenoh-config", default=None, metavar="FILE",
                   help="Zenoh JSON5 config file; replaces the loopback defaults")


def client_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``MapClient`` keyword arguments from flags added by :func:`add_connection_args`."""
    return {"map": args.map, "connect": args.connect, "zenoh_config": args.zenoh_config,
            "prefix": args.prefix}


def _load(zenoh_config: ZenohConfigLike) -> zenoh.Config | None:
    if zenoh_config is None:
        return None
    if isinstance(zenoh_config, zenoh.Config):
        return zenoh_config
    if isinstance(zenoh_config, Mapping):
        return zenoh.Config.from_json5(json.dumps(dict(zenoh_config)))
    return zenoh.Config.from_file(os.fspath(zenoh_config))


def _no_scouting(c: zenoh.Config) -> None:
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")


def client_config(connect: str | None = None, zenoh_config: ZenohConfigLike = None,
                  connect_timeout_ms: int = CONNECT_TIMEOUT_MS) -> zenoh.Config:
    """Zenoh config of a client session.

    Parameters
    ----------
    connect : str, optional
        Endpoint of the server (``tcp/127.0.0.1:7447`` when neither this nor a config is given).
        Applied on top of ``zenoh_config`` when both are given.
    zenoh_config : path, dict or zenoh.Config, optional
        A full Zenoh config (JSON5 file path, a dict of the same structure, or a Config). It
        replaces the defaults (mode client, no scouting).
    connect_timeout_ms : int
        How long ``zenoh.open`` tries before failing (defaults only).
    """
    c = _load(zenoh_config)
    if c is None:
        c = zenoh.Config()
        c.insert_json5("mode", '"client"')
        _no_scouting(c)
        c.insert_json5("connect/timeout_ms", str(int(connect_timeout_ms)))
        connect = connect or DEFAULT_ENDPOINT
    if connect:
        c.insert_json5("connect/endpoints", json.dumps([connect]))
    return c


def server_config(listen: str | None = None, zenoh_config: ZenohConfigLike = None,
                  max_message_bytes: int = MAX_MESSAGE_BYTES) -> zenoh.Config:
    """Zenoh config of the server's embedded peer.

    Defaults: mode peer, listen on ``listen`` (``tcp/127.0.0.1:7447``), connect nowhere,
    multicast and gossip scouting off, shared memory off, batching off,
    ``transport/link/rx/max_message_size`` = ``max_message_bytes``. A ``zenoh_config``
    replaces them all; ``listen``, when given, is applied on top.
    """
    c = _load(zenoh_config)
    if c is None:
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("connect/endpoints", "[]")
        _no_scouting(c)
        c.insert_json5("transport/shared_memory/enabled", "false")
        c.insert_json5("transport/link/tx/queue/batching/enabled", "false")
        c.insert_json5("transport/link/rx/max_message_size", str(int(max_message_bytes)))
        listen = listen or DEFAULT_ENDPOINT
    if listen:
        c.insert_json5("listen/endpoints", json.dumps([listen]))
    return c


def listen_endpoints(c: zenoh.Config) -> list[str]:
    """The listen endpoints a config names (for the ``listening on`` line)."""
    raw = json.loads(c.get_json("listen/endpoints"))
    if isinstance(raw, dict):  # per-mode form {"router": [...], "peer": [...]}
        mode = json.loads(c.get_json("mode") or "null") or "peer"
        raw = raw.get(mode, [])
    return [str(e) for e in raw]
