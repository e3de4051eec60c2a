"""``mcsm-client``: talk to an ``mcsm serve`` map from the shell.

Commands (each takes the connection flags ``--connect``, ``--map``, ``--prefix``,
``--namespace``, ``--zenoh-config`` and ``--timeout-s``, before or after the command name;
``ZENOH_CONFIG`` names a config file when ``--zenoh-config`` is not given)::

    mcsm-client info [--json]
    mcsm-client update A B --planar DX DY DTH --sigma SX SY STH     # AT a->b, N samples drawn
    mcsm-client update A B --pose X Y Z QW QX QY QZ --sigma S1..S6  # 3D, tangent [t, r] sigmas
    mcsm-client update A B --point X Y [Z] --sigma SX SY [SZ]       # point frame b seen from a
    mcsm-client query A B [--json] [--samples-out FILE.npy]
    mcsm-client remove FRAME
    mcsm-client watch [--count K] [--duration-s S]
    mcsm-client play FILE|gtsam:NAME [--bounded] [--order file|pose] [--max-constraints K]
    mcsm-client play-rosbag BAG [--constraint-topic T] [--landmark-topic T] [--odometry-topic T]
    mcsm-client sim [--iterations 340] [--sigma-theta-deg 0] [--csv F] [--png F]
    mcsm-client multirobot [--connect-b ENDPOINT | --map-b NAME]

``play``, ``sim`` and ``multirobot`` also run without a server with ``--in-process N`` (an
in-process map of N samples); they write only into a frame namespace that has no frames yet
(``--namespace NS``: frames ``NS/...``). ``--cov`` gives a full covariance (row-major) instead
of ``--sigma``. Exit codes: 0 success, 1 the server refused the request (its error is
printed), 2 bad command line or input file (a malformed ``--connect`` too), 3 no answer within
``--timeout-s`` (nothing to connect to, no live server, no permitted server for the key, or a
slow server: the message says which), 4 ``update`` of a constraint the server's gate rejected
(recorded and acknowledged, the map unchanged; the verdict says why), 130 interrupted.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from mcsm.errors import McsmError, NoPermittedServer, NoServer, Timeout, Unreachable
from mcsm.serve.connect import check_endpoint, fill_connection_defaults

from mcsm_client.cli_common import (  # re-exported: the exit codes, UsageError, _ack_text
    EXIT_GATE_REJECTED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_TIMEOUT,
    EXIT_USAGE,
    UsageError,
    _ack_text,
    _add_common,
    _add_in_process,
)
from mcsm_client.cli_map import (
    cmd_audit,
    cmd_info,
    cmd_query,
    cmd_relinearize,
    cmd_remove,
    cmd_retract,
    cmd_servers,
    cmd_update,
    cmd_verdict,
    cmd_watch,
)
from mcsm_client.cli_run import cmd_multirobot, cmd_play, cmd_play_rosbag, cmd_sim
from mcsm_client.client import DEFAULT_TIMEOUT_S

JSON_HELP = "print the result as one JSON object"
NO_PROGRESS_HELP = "no progress bar or progress lines on stderr"


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (exposed for tests and docs)."""
    p = argparse.ArgumentParser(
        prog="mcsm-client",
        description="Client of the Monte Carlo stochastic map server (mcsm serve).",
        epilog="Exit codes: 0 ok, 1 refused by the server, 2 usage or input error, "
               "3 no answer in time (nothing to connect to, no server, access denied, or "
               "slow), 4 update rejected by the server's loop-closure gate (recorded, map "
               "unchanged), 130 interrupted. "
               "Connection flags go before or after the command.")
    _add_common(p)
    p.add_argument("--version", action="version", version=_version_text())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("info", help="frames, components, N, sequence number and digest")
    s.add_argument("--json", action="store_true", help="one JSON object")
    _add_common(s)

    s = sub.add_parser("update", help="send one observation (samples drawn from mean + noise)",
                       description="Draw N samples (N = the map's) from a mean and a Gaussian "
                                   "noise model and apply them as the AT A->B (or the point B "
                                   "seen from A).")
    s.add_argument("a", help="source frame")
    s.add_argument("b", help="target frame")
    kind = s.add_mutually_exclusive_group(required=True)
    kind.add_argument("--planar", nargs=3, type=float, metavar=("DX", "DY", "DTHETA"),
                      help="planar AT: B in A's frame (m, m, rad)")
    kind.add_argument("--pose", nargs=7, type=float,
                      metavar=("X", "Y", "Z", "QW", "QX", "QY", "QZ"),
                      help="3D AT: B in A's frame, scalar-first quaternion")
    kind.add_argument("--point", nargs="+", type=float, metavar="X",
                      help="point B in A's frame: X Y [Z] (m)")
    noise = s.add_mutually_exclusive_group(required=True)
    noise.add_argument("--sigma", nargs="+", type=float, metavar="S",
                       help="standard deviations (planar: 3; pose: 6 as tx ty tz rx ry rz; "
                            "point: 2 or 3)")
    noise.add_argument("--cov", nargs="+", type=float, metavar="C",
                       help="full covariance, row-major (9, 36, 4 or 9 numbers)")
    s.add_argument("--seed", type=int, default=None, help="random seed (default: fresh)")
    s.add_argument("--trusted", action="store_true",
                   help="bypass the server's loop-closure gate for this observation")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    s = sub.add_parser("query", help="the relation A->B: mean and covariance (or samples)")
    s.add_argument("a")
    s.add_argument("b")
    s.add_argument("--samples-out", type=Path, default=None, metavar="FILE.npy",
                   help="also save the (N, 7) samples as a .npy file")
    s.add_argument("--force", action="store_true", help="overwrite an existing --samples-out")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    s = sub.add_parser("remove", help="remove a frame (other estimates unchanged)")
    s.add_argument("frame")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    for name, text in (("retract", "take back an update by its request id (the map becomes "
                                   "what it would be without it)"),
                       ("reinstate", "put back a retracted update, or one the gate "
                                     "rejected (as trusted)")):
        s = sub.add_parser(name, help=text)
        s.add_argument("request_id", help="the update's request id (from its ack or events)")
        s.add_argument("--json", action="store_true", help=JSON_HELP)
        _add_common(s)

    s = sub.add_parser("relinearize", help="bring a component (or every component) back to the "
                       "maximum a posteriori estimate of its recorded inputs and redraw its "
                       "samples (admin)")
    s.add_argument("frame", nargs="?", default="",
                   help="a frame of the component (default: every component)")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    s = sub.add_parser("audit", help="run GTSAM's GNC over a map's recorded inputs and retract "
                       "or reinstate where it disagrees with the map (eval extra)",
                       description="Read the recorded inputs of a map (the server's MCAP "
                                   "file), replay it for each update's current verdict, run "
                                   "the GNC auditor (mcsm_client.audit, hysteresis: marginal "
                                   "closures keep their state) and print its decisions; with "
                                   "--apply, ask the server to retract or reinstate them "
                                   "(admin rights under the shipped access control).")
    s.add_argument("recording", type=Path, help="the map server's recording (.mcap)")
    s.add_argument("--apply", action="store_true",
                   help="send the decisions to the server (default: print them only)")
    s.add_argument("--gate", type=float, default=0.99,
                   help="chi-square quantile the residuals are judged against (default 0.99)")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    s = sub.add_parser("servers", help="every map with a live server, its server id and role "
                       "(all servers reachable from here, e.g. behind a router)")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    s = sub.add_parser("verdict", help="what the map did with a past request (gate verdict)")
    s.add_argument("request_id")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_common(s)

    s = sub.add_parser("watch", help="print the map's events as they happen (Ctrl-C stops)")
    s.add_argument("--count", type=int, default=None, help="stop after this many events")
    s.add_argument("--duration-s", type=float, default=None, help="stop after this long")
    s.add_argument("--json", action="store_true", help="one JSON object per event")
    _add_common(s)

    s = sub.add_parser("play", help="stream a dataset file into the map",
                       description="Read a g2o (2D/3D), TORO .graph or Victoria Park text "
                                   "file (or gtsam:NAME from the gtsam wheel's data) and send "
                                   "its constraints in order: odometry and loop closures as "
                                   "ATs, landmark sightings as point updates.")
    s.add_argument("file", help="dataset path, or gtsam:NAME (e.g. gtsam:victoria_park.txt)")
    s.add_argument("--bounded", action="store_true",
                   help="keep only the first pose, the current pose and the landmarks")
    s.add_argument("--order", choices=("file", "pose"), default="file",
                   help="file order, or each constraint once its newest pose exists")
    s.add_argument("--max-constraints", type=int, default=None, metavar="K",
                   help="send only the first K constraints (default: all)")
    s.add_argument("--noise", choices=("auto", "information", "sqrt_information",
                                       "covariance"), default="auto",
                   help="how to read g2o noise numbers (default: auto-detect)")
    s.add_argument("--stop-on-error", action="store_true",
                   help="stop at the first refused update (default: count and go on)")
    s.add_argument("--no-progress", action="store_true", help=NO_PROGRESS_HELP)
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_in_process(s)
    _add_common(s)

    s = sub.add_parser("play-rosbag", help="stream a ROS 2 bag (MCAP or sqlite3) into the map, "
                       "mapped as mcsm ros2 maps messages (ros extra: rosbags)",
                       description="Read a ROS 2 bag with rosbags (no ROS installation "
                                   "needed) and send its nav_msgs/Odometry messages of the "
                                   "input topics as mcsm ros2 would: in header-stamp order, "
                                   "samples and request ids from each message (a bag played "
                                   "twice is applied once). docs/ros2.md.")
    s.add_argument("bag", type=Path, help="the bag (its folder, or one .mcap/.db3 file)")
    s.add_argument("--odometry-topic", action="append", default=None, metavar="TOPIC",
                   help="a cumulative odometry topic, keyframed (repeatable; default /odom)")
    s.add_argument("--constraint-topic", action="append", default=None, metavar="TOPIC",
                   help="a relative-pose topic (repeatable; default /mcsm/constraints)")
    s.add_argument("--landmark-topic", action="append", default=None, metavar="TOPIC",
                   help="a point-landmark topic (repeatable; default /mcsm/landmarks)")
    s.add_argument("--frame-prefix", default="", metavar="NS",
                   help="prepended to every frame id (NS/base_link)")
    s.add_argument("--keyframe-distance-m", type=float, default=0.5,
                   help="a new odometry keyframe after this much travel (default %(default)s m)")
    s.add_argument("--keyframe-angle-rad", type=float, default=0.5,
                   help="... or this much turn (default %(default)s rad)")
    s.add_argument("--no-progress", action="store_true", help=NO_PROGRESS_HELP)
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    _add_common(s)

    s = sub.add_parser("sim", help="the paper's §6 simulation: RMS and NEES vs ground truth")
    s.add_argument("--iterations", type=int, default=340, help="odometry steps (340: one lap)")
    s.add_argument("--sigma-theta-deg", type=float, default=0.0,
                   help="odometry heading noise, degrees (paper: 0 and 0.1)")
    s.add_argument("--landmarks", type=int, default=200,
                   help="landmarks in the world (default %(default)s)")
    s.add_argument("--score-every", type=int, default=10, metavar="K",
                   help="score RMS and NEES every K iterations (default %(default)s)")
    s.add_argument("--unbounded", action="store_true", help="keep every pose frame")
    s.add_argument("--csv", type=Path, default=None, help="write per-iteration scores here")
    s.add_argument("--png", type=Path, default=None, help="plot here (needs matplotlib)")
    s.add_argument("--force", action="store_true", help="overwrite existing --csv/--png files")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_in_process(s)
    _add_common(s)

    s = sub.add_parser("multirobot", help="two robots' maps joined at a rendezvous, then a "
                                          "loop closed across them")
    s.add_argument("--connect-b", default=None, metavar="ENDPOINT",
                   help="robot B's own server (default: B's component in the same map)")
    s.add_argument("--map-b", default=None, metavar="NAME",
                   help="robot B's own map on the same server")
    s.add_argument("--landmarks", type=int, default=200, help="landmarks in the world")
    s.add_argument("--json", action="store_true", help=JSON_HELP)
    _add_in_process(s)
    _add_common(s)
    return p


# ----------------------------------------------------------------------------- helpers


def _version_text() -> str:
    from mcsm import __version__
    from mcsm.core import ARITHMETIC_VERSION
    from mcsm.wire import VERSION

    return (f"mcsm-client {__version__} (core arithmetic version {ARITHMETIC_VERSION}, wire "
            f"protocol v{VERSION})")


COMMANDS = {"info": cmd_info, "update": cmd_update, "query": cmd_query, "remove": cmd_remove,
            "retract": cmd_retract, "reinstate": cmd_retract, "verdict": cmd_verdict,
            "relinearize": cmd_relinearize,
            "servers": cmd_servers, "audit": cmd_audit,
            "watch": cmd_watch, "play": cmd_play, "play-rosbag": cmd_play_rosbag, "sim": cmd_sim,
            "multirobot": cmd_multirobot}


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mcsm-client`` console script; returns the exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    fill_connection_defaults(args)
    if not hasattr(args, "timeout_s"):
        args.timeout_s = DEFAULT_TIMEOUT_S
    prog = f"mcsm-client {args.command}"
    try:
        if not args.timeout_s > 0:
            raise UsageError("--timeout-s must be > 0")
        if args.connect is not None:
            check_endpoint(args.connect)
        if getattr(args, "connect_b", None):
            check_endpoint(args.connect_b, "--connect-b")
        return COMMANDS[args.command](args)
    except UsageError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (NoServer, NoPermittedServer, Unreachable) as exc:
        print(f"{prog}: {exc.message}", file=sys.stderr)
        return EXIT_TIMEOUT
    except Timeout as exc:
        print(f"{prog}: no answer from the server: {exc.message} (is `mcsm serve` running, "
              f"and do --connect/--map/--prefix match it?)", file=sys.stderr)
        return EXIT_TIMEOUT
    except McsmError as exc:
        if exc.fields.get("field") in ("--connect", "--connect-b", "--zenoh-config",
                                       "namespace"):
            print(f"{prog}: {exc.message}", file=sys.stderr)  # a usage error, found early
            return EXIT_USAGE
        print(f"{prog}: refused: {type(exc).__name__}: {exc.message}", file=sys.stderr)
        return EXIT_REFUSED
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # the reader went away (`... | head`): not an error of ours
        _silence_stdout()
        return EXIT_OK


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not fail again."""

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())


__all__ = ["COMMANDS", "EXIT_GATE_REJECTED", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_REFUSED",
           "EXIT_TIMEOUT", "EXIT_USAGE", "UsageError", "_ack_text", "build_parser", "main"]


if __name__ == "__main__":
    raise SystemExit(main())
