"""``mcsm ros2``: the subcommand, added to ``mcsm`` through the ``mcsm.commands`` entry points.

``mcsm`` finds :func:`add_parser` at run time (``pyproject.toml``'s entry point), so the server
package never imports this client package. This module imports neither rclpy nor any message
package: ``mcsm --help`` stays light; :func:`run` imports them.

Exit codes: 0 stopped by SIGINT/SIGTERM; 2 usage (bad parameters, the ``ros`` extra missing, no
compiler for the tf2_msgs build); 3 no map server answered within ``--timeout-s``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

EPILOG = """ROS parameters (after --ros-args, as -p NAME:=VALUE; docs/ros2.md):
{params}

Topics: subscribes nav_msgs/Odometry on the odometry, constraint and landmark topics;
publishes /tf, /mcsm/path[/ROBOT], /mcsm/markers, /mcsm/pose/<B>, /diagnostics.
Services: ~/relinearize, ~/snapshot (std_srvs/Trigger). Parameters retract and reinstate
take a request id (ros2 param set /mcsm_ros2 retract ros-constraint-...).
Exit codes: 0 stopped (SIGINT/SIGTERM), 2 usage or the ros extra missing, 3 no map server."""


def _epilog() -> str:
    from mcsm_client.ros2.params import PARAMETERS

    return EPILOG.format(params="\n".join(f"  {n} (default {d!r}): {t}"
                                          for n, (d, t) in PARAMETERS.items()))


def add_parser(sub: Any) -> None:
    """Add ``ros2`` to ``mcsm``'s subparsers (the ``mcsm.commands`` entry point)."""
    from mcsm.serve.connect import add_connection_args

    p = sub.add_parser("ros2", help="a ROS 2 node: ROS messages into the map, TF, paths, "
                       "markers and diagnostics out (ros extra)",
                       description="Run the ROS 2 node mcsm_ros2: a client of a map server "
                                   "(--connect, or --serve to start one in this process). "
                                   "ROS arguments go last, after --ros-args.",
                       epilog=_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    add_connection_args(p, role="client")
    p.add_argument("--serve", action="store_true",
                   help="start a map server in this process on a free loopback port "
                        "(no --connect)")
    p.add_argument("--samples", type=int, default=1000, metavar="N",
                   help="with --serve: samples per AT (default %(default)s)")
    p.add_argument("--record", type=Path, default=None, metavar="PATH.mcap",
                   help="with --serve: the recording (default recordings/ros2-<UTC>.mcap)")
    p.add_argument("--timeout-s", type=float, default=10.0,
                   help="how long one request waits for the server (default %(default)s)")
    p.add_argument("--node-name", default="mcsm_ros2", help="the ROS node's name")
    p.add_argument("--log-level", default="INFO", type=str.upper,
                   choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="default %(default)s")
    p.set_defaults(plugin_run=run, ros_args=[])


class _InProcessServer:
    """``mcsm serve`` inside this process, on a free loopback port."""

    def __init__(self, args: argparse.Namespace) -> None:
        import time

        import zenoh
        from mcsm.serve.connect import server_config
        from mcsm.serve.server import Server, ServerOptions

        from mcsm_client.process import loopback_endpoint

        self.endpoint = loopback_endpoint()
        record = args.record or (Path("recordings") /
                                 f"ros2-{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}.mcap")
        opts = ServerOptions(maps=[args.map], prefix=args.prefix,
                             map_options={"n_samples": args.samples}, record=record)
        self.session = zenoh.open(server_config(self.endpoint))
        self.server = Server(self.session, opts)
        try:
            self.server.start()
        except BaseException:
            self.session.close()
            raise
        self.record = record

    def close(self) -> None:
        self.server.close()
        self.session.close()


def run(args: argparse.Namespace) -> int:
    """Run the node until SIGINT or SIGTERM."""
    from mcsm.errors import McsmError, NoPermittedServer, NoServer, Timeout

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    prog = "mcsm ros2"
    if args.serve and args.connect:
        print(f"{prog}: --serve starts its own server: no --connect", file=sys.stderr)
        return 2
    if args.serve and args.record is not None:
        from mcsm.log.writer import new_recording_problem

        if why := new_recording_problem(Path(args.record)):
            print(f"{prog}: --record {args.record}: {why}", file=sys.stderr)
            return 2
    try:
        import rclpy
        from rclpy.executors import ExternalShutdownException
    except ImportError as exc:
        print(f"{prog}: needs the ros extra (pip install 'mcsm[ros]'): {exc}", file=sys.stderr)
        return 2
    from mcsm.serve.connect import client_kwargs

    from mcsm_client.client import MapClient
    from mcsm_client.ros2.node import RosNode, declare_parameters
    from mcsm_client.ros2.tf2 import TfBuildError, load_tfmessage

    try:
        load_tfmessage()  # before anything starts: a failed build is said at once
    except TfBuildError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    server = None
    clients: list[Any] = []
    rclpy.init(args=["mcsm_ros2", *args.ros_args])
    node = None
    ros = None
    try:
        node = rclpy.create_node(args.node_name)
        try:  # before any server: a bad parameter is a usage error, whatever the network
            opts = declare_parameters(node)
        except ValueError as exc:
            print(f"{prog}: {exc}", file=sys.stderr)
            return 2
        if args.serve:
            server = _InProcessServer(args)
            connect = server.endpoint
            print(f"{prog}: serving map {args.map!r} on {connect}, recording to "
                  f"{server.record}", flush=True)
        else:
            connect = args.connect
        kw = client_kwargs(args)
        kw["connect"] = connect
        for _ in range(2):
            clients.append(MapClient(timeout_s=args.timeout_s, sender=args.node_name, **kw))
        info = clients[0].wait_for_server(timeout_s=args.timeout_s)
        ros = RosNode(node, clients[0], clients[1], opts)
        stop = threading.Event()
        old = {sig: signal.signal(sig, lambda *_: stop.set())
               for sig in (signal.SIGINT, signal.SIGTERM)}
        print(f"{prog}: ready: node {node.get_fully_qualified_name()}, map {info.map!r} "
              f"(N = {info.n_samples}, seq {info.seq}) of server {info.server_id}; inputs "
              f"{', '.join(opts.mapping.topics)}", flush=True)
        try:
            while not stop.is_set() and rclpy.ok():
                rclpy.spin_once(node, timeout_sec=0.1)
        except (KeyboardInterrupt, ExternalShutdownException):
            pass
        finally:
            for sig, h in old.items():
                signal.signal(sig, h)
        ros.stop()  # apply what is buffered
        s = ros.stats
        print(f"{prog}: stopped: {s.summary()}", flush=True)
        return 0
    except (NoServer, NoPermittedServer, Timeout) as exc:
        print(f"{prog}: no map server: {exc}", file=sys.stderr)
        return 3
    except McsmError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        for c in clients:
            c.close()
        if server is not None:
            server.close()
