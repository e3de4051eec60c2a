"""Connection flags and Zenoh configs, shared by ``mcsm``, ``mcsm-client`` and every example;
and two helpers on Zenoh entities (:func:`undeclare_all`, :func:`query_source`).

Defaults work on one machine with no router: the server is an embedded Zenoh *peer* listening
on ``tcp/127.0.0.1:7457`` (not 7447, zenohd's own port, so a Zenoh router and an mcsm server
can run on one host without a clash); clients open a Zenoh *client* session connected to it.
Both turn off multicast and gossip scouting (nothing leaves loopback), and the server turns off
shared memory (it bypasses ``max_message_size``), turns off batching (a 56 KB reply takes
~1.3 ms batched vs ~0.2 ms not) and caps incoming messages at 8 MiB
(measured: docs/design.md, "Wire contract").

A ``--zenoh-config FILE`` (JSON5), or else the file named by the ``ZENOH_CONFIG`` environment
variable (as Zenoh's own tools read it), replaces these defaults entirely, for real deployments
(routers, TLS, access control: ``deploy/``); an explicit ``--connect``/``--listen`` is still
applied on top. Relative file paths inside such a config (the users file, certificates and
keys) are resolved against the config file's directory, so a deployment directory can be
used from anywhere.

Example::

    parser = argparse.ArgumentParser()
    add_connection_args(parser)                    # --connect --map --prefix --zenoh-config
    args = parser.parse_args()
    with MapClient(**client_kwargs(args)) as client:
        ...
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import logging
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import zenoh

from mcsm import wire
from mcsm.errors import BadMessage

log = logging.getLogger(__name__)

DEFAULT_PORT = 7457
DEFAULT_ENDPOINT = f"tcp/127.0.0.1:{DEFAULT_PORT}"
DEFAULT_MAP = wire.DEFAULT_MAP
DEFAULT_PREFIX = wire.DEFAULT_PREFIX
MAX_MESSAGE_BYTES = 8 * 1024 * 1024
CONNECT_TIMEOUT_MS = 2000

ZenohConfigLike = str | os.PathLike[str] | Mapping[str, Any] | zenoh.Config | None


def add_connection_args(parser: argparse.ArgumentParser,
                        role: Literal["client", "server"] = "client", *,
                        suppress: bool = False) -> None:
    """Add ``--connect`` (client) or ``--listen`` (server), ``--map``, ``--prefix``,
    ``--zenoh-config`` to ``parser``.

    For the server ``--map`` may be repeated (one server, several maps); for a client it names
    the one map to talk to. Read the values back with :func:`client_kwargs` or directly
    (``args.connect``, ``args.listen``, ``args.map``, ``args.prefix``, ``args.zenoh_config``).
    ``suppress=True`` leaves absent flags out of the namespace, so the same flags can be
    added to a parser and its subcommands' parsers (``mcsm-client --connect X info`` and
    ``mcsm-client info --connect X``); then call :func:`fill_connection_defaults`.
    """
    g = parser.add_argument_group("connection")
    d: dict[str, Any] = {"default": argparse.SUPPRESS} if suppress else {}
    if role == "server":
        g.add_argument("--listen", metavar="ENDPOINT", **(d or {"default": None}),
                       help=f"Zenoh endpoint to listen on (default {DEFAULT_ENDPOINT}, "
                            "or the config file's)")
        g.add_argument("--map", action="append", metavar="NAME", **(d or {"default": None}),
                       help=f"map to serve; repeat for several (default {DEFAULT_MAP!r})")
    else:
        g.add_argument("--connect", metavar="ENDPOINT", **(d or {"default": None}),
                       help=f"server endpoint, e.g. tcp/HOST:PORT (default {DEFAULT_ENDPOINT}, "
                            "or the config file's)")
        g.add_argument("--map", metavar="NAME", **(d or {"default": DEFAULT_MAP}),
                       help=f"map name (default {DEFAULT_MAP!r})")
        g.add_argument("--namespace", metavar="NS", **(d or {"default": None}),
                       help="write through the keys update/NS and remove/NS (a robot "
                            "identity's keys under the shipped access control; frames must "
                            "be NS/...); sim, play and multirobot write NS/... frames (NS may "
                            "be robot1/run2)")
    g.add_argument("--prefix", **(d or {"default": DEFAULT_PREFIX}),
                   help=f"key expression prefix (default {DEFAULT_PREFIX!r})")
    g.add_argument("--zenoh-config", metavar="FILE", **(d or {"default": None}),
                   help="Zenoh JSON5 config file (default: $ZENOH_CONFIG if set); replaces "
                        "the loopback defaults")


def fill_connection_defaults(args: argparse.Namespace,
                             role: Literal["client", "server"] = "client") -> None:
    """Set the defaults of connection flags that were given nowhere (see ``suppress``)."""
    defaults: dict[str, Any] = {"prefix": DEFAULT_PREFIX, "zenoh_config": None}
    if role == "server":
        defaults.update(listen=None, map=None)
    else:
        defaults.update(connect=None, map=DEFAULT_MAP, namespace=None)
    for k, v in defaults.items():
        if not hasattr(args, k):
            setattr(args, k, v)


SERVER_FLAGS = ("--listen", "--connect", "--map", "--prefix", "--zenoh-config")


def flags_after_command(argv: list[str], command: str,
                        flags: tuple[str, ...] = SERVER_FLAGS) -> list[str]:
    """``argv`` with the given value flags written before ``command`` moved after it, so
    ``mcsm --listen X serve`` parses like ``mcsm serve --listen X``. Anything else is left
    where it is (argparse then reports it as usual)."""
    if command not in argv:
        return list(argv)
    at = argv.index(command)
    moved: list[str] = []
    head: list[str] = []
    i = 0
    while i < at:
        tok = argv[i]
        name = tok.split("=", 1)[0]
        if name in flags and "=" in tok:
            moved.append(tok)
        elif name in flags and i + 1 < at:
            moved += [tok, argv[i + 1]]
            i += 1
        else:
            head.append(tok)
        i += 1
    return [*head, command, *moved, *argv[at + 1:]]


def client_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """``MapClient`` keyword arguments from flags added by :func:`add_connection_args`."""
    kw = {"map": args.map, "connect": args.connect, "zenoh_config": args.zenoh_config,
          "prefix": args.prefix}
    if getattr(args, "namespace", None):
        # "robot1/run2": the keys are robot1's; the frames of sim/play/multirobot robot1/run2/...
        kw["namespace"] = str(args.namespace).split("/", 1)[0]
    return kw


_ENDPOINT_RE = re.compile(r"[a-z][a-z0-9-]*/\S+")
_PORTED = ("tcp", "udp", "tls", "quic", "ws")


def check_endpoint(endpoint: str, flag: str = "--connect") -> str:
    """Return ``endpoint`` if it looks like a Zenoh endpoint (``tcp/HOST:PORT``), else raise.

    Raises
    ------
    BadMessage
        With a one-line message naming the flag and an example (``127.0.0.1:7457`` without
        ``tcp/`` is the common mistake).
    """
    ok = isinstance(endpoint, str) and _ENDPOINT_RE.fullmatch(endpoint) is not None
    if ok:
        proto, _, addr = endpoint.partition("/")
        addr = addr.split("#", 1)[0].split("?", 1)[0]
        port = re.search(r":(\d{1,5})$", addr)
        ok = proto not in _PORTED or port is not None
        if port is not None and int(port.group(1)) > 65535:
            raise BadMessage(flag, "a port from 0 to 65535", repr(endpoint))
    if not ok:
        raise BadMessage(flag, f"a Zenoh endpoint <protocol>/<address>, e.g. "
                               f"tcp/127.0.0.1:{DEFAULT_PORT} or tls/robot-host:{DEFAULT_PORT}",
                         repr(endpoint))
    return endpoint


_PATH_KEYS = ("transport/auth/usrpwd/dictionary_file", "transport/link/tls/root_ca_certificate",
              "transport/link/tls/listen_private_key", "transport/link/tls/listen_certificate",
              "transport/link/tls/connect_private_key",
              "transport/link/tls/connect_certificate")


def _load(zenoh_config: ZenohConfigLike) -> zenoh.Config | None:
    if zenoh_config is None:
        env = os.environ.get("ZENOH_CONFIG")
        if not env:
            return None
        zenoh_config = env
    if isinstance(zenoh_config, zenoh.Config):
        return zenoh_config
    if isinstance(zenoh_config, Mapping):
        return zenoh.Config.from_json5(json.dumps(dict(zenoh_config)))
    path = Path(os.fspath(zenoh_config))
    if not path.is_file():
        raise BadMessage("--zenoh-config", "a readable Zenoh JSON5 file", str(path))
    c = zenoh.Config.from_file(str(path))
    for key in _PATH_KEYS:
        val = json.loads(c.get_json(key))
        if isinstance(val, str) and val and not Path(val).is_absolute():
            c.insert_json5(key, json.dumps(str((path.parent / val).resolve())))
    return c


def _no_scouting(c: zenoh.Config) -> None:
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/gossip/enabled", "false")


def client_config(connect: str | None = None, zenoh_config: ZenohConfigLike = None,
                  connect_timeout_ms: int = CONNECT_TIMEOUT_MS) -> zenoh.Config:
    """Zenoh config of a client session.

    Parameters
    ----------
    connect : str, optional
        Endpoint of the server (``tcp/127.0.0.1:7457`` when neither this nor a config is given).
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
        c.insert_json5("connect/endpoints", json.dumps([check_endpoint(connect)]))
    return c


def server_config(listen: str | None = None, zenoh_config: ZenohConfigLike = None,
                  max_message_bytes: int = MAX_MESSAGE_BYTES,
                  connect: list[str] | None = None) -> zenoh.Config:
    """Zenoh config of the server's embedded peer.

    Defaults: mode peer, listen on ``listen`` (``tcp/127.0.0.1:7457``), connect nowhere,
    multicast and gossip scouting off, shared memory off, batching off,
    ``transport/link/rx/max_message_size`` = ``max_message_bytes``. With ``connect``
    (routers, ``mcsm serve --connect``) and no ``listen``, the server is a Zenoh *client* of
    the routers (a peer would expect direct links to the other peers) and listens nowhere:
    clients reach it through the routers. A ``zenoh_config`` replaces
    the defaults; ``listen`` and ``connect``, when given, are applied on top.
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
        if not connect:
            listen = listen or DEFAULT_ENDPOINT
        elif not listen:  # reached through the routers only: a client of theirs
            c.insert_json5("mode", '"client"')
            c.insert_json5("listen/endpoints", "[]")
    if connect:
        c.insert_json5("connect/endpoints",
                       json.dumps([check_endpoint(e, "--connect") for e in connect]))
    if listen:
        c.insert_json5("listen/endpoints", json.dumps([check_endpoint(listen, "--listen")]))
    return c


def router_config(listen: str, zenoh_config: ZenohConfigLike = None,
                  max_message_bytes: int = MAX_MESSAGE_BYTES) -> zenoh.Config:
    """Zenoh config of ``mcsm router``: a session in router mode listening on ``listen``,
    scouting, shared memory and batching off, messages capped like the server's. A
    ``zenoh_config`` replaces the defaults (its mode is set to router)."""
    c = _load(zenoh_config)
    if c is None:
        c = zenoh.Config()
        c.insert_json5("connect/endpoints", "[]")
        _no_scouting(c)
        c.insert_json5("transport/shared_memory/enabled", "false")
        c.insert_json5("transport/link/tx/queue/batching/enabled", "false")
        c.insert_json5("transport/link/rx/max_message_size", str(int(max_message_bytes)))
    c.insert_json5("mode", '"router"')
    c.insert_json5("listen/endpoints", json.dumps([check_endpoint(listen, "--listen")]))
    return c


def listen_endpoints(c: zenoh.Config) -> list[str]:
    """The listen endpoints a config names (for the ``listening on`` line)."""
    raw = json.loads(c.get_json("listen/endpoints"))
    if isinstance(raw, dict):  # per-mode form {"router": [...], "peer": [...]}
        mode = json.loads(c.get_json("mode") or "null") or "peer"
        raw = raw.get(mode, [])
    return [str(e) for e in raw]


def _loopback(endpoint: str) -> bool:
    proto, _, addr = endpoint.partition("/")
    if proto.startswith("unix"):
        return True
    host = addr.split("#", 1)[0].split("?", 1)[0].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:  # a host name: assume it is reachable from the network
        return False


def security_warning(c: zenoh.Config) -> str | None:
    """One line warning about a server config reachable off this host without
    authentication (or without access control), or None when there is nothing to say."""
    exposed = [e for e in listen_endpoints(c) if not _loopback(e)]
    if not exposed:
        return None
    usrpwd = json.loads(c.get_json("transport/auth/usrpwd/dictionary_file")) is not None
    mtls = json.loads(c.get_json("transport/link/tls/enable_mtls")) is True
    acl = json.loads(c.get_json("access_control/enabled")) is True
    where = " ".join(exposed)
    if not (usrpwd or mtls):
        return (f"listening on {where} without authentication: anyone who reaches it can "
                "read and write every map (use a config from deploy/, docs/deploy.md)")
    if not acl:
        return (f"listening on {where} without access control: every authenticated "
                "identity can write every map (docs/deploy.md)")
    return None


def undeclare_all(entities: list[Any]) -> None:
    """Undeclare Zenoh entities (queryables, tokens, subscribers, publishers) and empty the
    list; an entity the session already dropped is only logged."""
    for ent in entities:
        try:
            ent.undeclare()
        except zenoh.ZError as exc:
            log.debug("undeclare: %s", exc)
    entities.clear()


def query_source(query: zenoh.Query) -> str:
    """The Zenoh id of a query's sender, or '' where the query carries none."""
    try:
        si = query.source_info
    except (AttributeError, zenoh.ZError):
        return ""
    return str(si.source_id) if si is not None else ""


_ZENOH_SOURCE = re.compile(r" at /[^\s\]]*\.rs:\d+\.?")


def zenoh_error_text(exc: BaseException) -> str:
    """A Zenoh error as one line a user can act on: without Zenoh's source locations, and
    with the fix for the common mistakes (a port in use, an address not of this host)."""
    text = _ZENOH_SOURCE.sub("", str(exc)).strip()
    if "Address already in use" in text:
        return (f"{text}: another process (an mcsm serve or router?) listens there; pick a "
                "free port with --listen tcp/127.0.0.1:PORT")
    if "Cannot assign requested address" in text:
        return (f"{text}: that address is not one of this host's; listen on 127.0.0.1 or an "
                "address this host has")
    return text


def listening_at(conf: zenoh.Config, timeout_s: float = 0.5) -> list[str]:
    """The config's tcp/tls connect endpoints at which something accepts a TCP connection.

    After ``zenoh.open`` failed to connect, an endpoint listed here refused Zenoh's handshake
    rather than the connection: it wants credentials or TLS that the config lacks (Zenoh says
    only "Timeout!" either way)."""
    import socket

    try:
        endpoints = json.loads(conf.get_json("connect/endpoints")) or []
    except (zenoh.ZError, ValueError, TypeError):
        return []
    out = []
    for e in endpoints if isinstance(endpoints, list) else []:
        proto, _, addr = str(e).partition("/")
        addr = addr.split("#", 1)[0].split("?", 1)[0]
        host, _, port = addr.rpartition(":")
        if proto not in ("tcp", "tls") or not port.isdigit():
            continue
        try:
            with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
                out.append(str(e))
        except (OSError, ValueError, OverflowError):
            continue
    return out
