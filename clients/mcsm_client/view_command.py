"""``mcsm view``, as a command of the ``mcsm`` program contributed by the client package.

``mcsm`` finds :func:`add_parser` through the entry-point group ``mcsm.commands``
(pyproject.toml): it adds the subparser and sets ``run(args) -> int`` as ``plugin_run``. The
server package never imports the client package; this module is light to import (it only adds
arguments) and loads the live view when it runs.

Exit codes: 0 stopped by SIGINT/SIGTERM; 2 a user's mistake or an unusable input, said in one
line on stderr (the ``viz`` extra not installed, no server answering within ``--timeout``, the
WebSocket port taken, a bad option).
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from typing import Any

from mcsm.errors import McsmError


def add_parser(sub: Any) -> None:
    """Add ``view`` to ``mcsm``'s subparsers (the ``mcsm.commands`` entry point)."""
    from mcsm.serve.connect import add_connection_args

    v = sub.add_parser("view", help="serve a live map to Foxglove or Lichtblick (WebSocket)",
                       description="Follow a running mcsm serve over Zenoh and publish its "
                                   "map as a Foxglove scene, its verdicts as a log and its "
                                   "counters for plotting, on a WebSocket (subprotocol "
                                   "foxglove.sdk.v1 or foxglove.websocket.v1); connect "
                                   "Foxglove or Lichtblick to ws://HOST:PORT and load "
                                   "docs/foxglove-layout.json.")
    add_connection_args(v, role="client")
    v.add_argument("--foxglove-port", type=int, default=8765, metavar="P",
                   help="WebSocket port for the viewer (default 8765; 0 picks one)")
    v.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address to bind the WebSocket to (default 127.0.0.1)")
    v.add_argument("--samples-per-frame", type=int, default=100, metavar="M",
                   help="sample points per frame in the point cloud (default 100; 0: none)")
    v.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="wait this long for the map server (default 10 s)")
    v.add_argument("--log-level", default="INFO", type=str.upper,
                   choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="default %(default)s")
    v.set_defaults(plugin_run=run)


def run(args: argparse.Namespace) -> int:
    """Run ``mcsm view``; a user's mistake becomes one line on stderr and exit 2."""
    try:
        return _view(args)
    except (McsmError, OSError) as exc:
        print(f"mcsm view: {exc}", file=sys.stderr)
        return 2


def _view(args: argparse.Namespace) -> int:
    from mcsm.viz.foxglove_scene import load_foxglove

    if not 0 <= args.foxglove_port <= 65535:
        raise McsmError(f"--foxglove-port must be in 0..65535, got {args.foxglove_port}")
    if args.samples_per_frame < 0:
        raise McsmError("--samples-per-frame must be at least 0")
    if not args.timeout > 0:
        raise McsmError("--timeout must be positive")
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    load_foxglove()  # a missing extra is said before any connection is tried
    from mcsm_client.view import ViewOptions, run_view

    stop = threading.Event()

    def on_signal(_signum: int, _frame: Any) -> None:
        stop.set()

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    opts = ViewOptions(map=args.map, connect=args.connect, zenoh_config=args.zenoh_config,
                       prefix=args.prefix, host=args.foxglove_host,
                       foxglove_port=args.foxglove_port,
                       samples_per_frame=args.samples_per_frame, timeout_s=args.timeout)
    try:
        return run_view(opts, stop, ready=lambda url: print(f"foxglove websocket on {url}",
                                                            flush=True))
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
