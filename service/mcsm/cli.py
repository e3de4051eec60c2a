"""``mcsm``: run the map server, replay, inspect, recover and print its recordings.

::

    mcsm serve [--listen tcp/127.0.0.1:7457] [--map NAME]... [--samples N]
               [--method joint|paper] [--gate Q|none] [--gate-defer [K]]
               [--gate-scale W:T:S|none] [--history BYTES|none] [--relinearize-nis Q|none]
               [--relinearize-every K|none] [--relinearize-gap K] [--relinearize-regate K|none]
               [--record PATH.mcap] [--restore PATH.mcap] [--zenoh-config FILE]
               [--connect ENDPOINT]... [--nats URL]... [--standby-of MAP]...
    mcsm router --listen ENDPOINT
    mcsm nats-cluster --dir DIR [--port 4222] [--nodes 3] [--auth FILE]
    mcsm replay FILE.mcap... [--json]
    mcsm inspect FILE.mcap... [--json]
    mcsm recover IN.mcap... -o OUT.mcap|OUT_DIR
    mcsm cat FILE.mcap... [--json] [--samples]
    mcsm plot FILE.mcap -o map.png [--map NAME] [--at SEQ] [--samples] [--truth CSV]
              [--view auto|top|xz|yz|3d]
    mcsm export foxglove|g2o|tum FILE.mcap [-o OUT] [--map NAME] [--force] (export-foxglove:
                                  the same as export foxglove)
    mcsm view [--connect ENDPOINT] [--map NAME] [--foxglove-port P]   (mcsm_client's, through
                                  the entry-point group mcsm.commands)
    mcsm export-rosbag FILE.mcap -o BAG [--map NAME] [--at SEQ]          (ros extra)
    mcsm ros2 [--connect ENDPOINT | --serve] [--ros-args ...]            (ros extra)
    mcsm --version

``serve`` prints one line ``listening on <endpoint>`` on stdout when it is ready, and closes
the recording cleanly on SIGINT or SIGTERM. Exit codes: see :data:`EXIT_CODES_HELP` (also in
``mcsm --help`` and docs/recordings.md).

A split recording (``serve --split-size`` / ``--split-duration``) is read by naming its files:
several paths, a directory or a glob pattern (:mod:`mcsm.log.recset`); a gap or a mixed set is a
usage error (2).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

from mcsm import wire
from mcsm.core.relinearize import DEFAULT_HISTORY_BYTES, Policy
from mcsm.core.smap import DEFAULT_GATE, DEFAULT_GATE_SCALE, DEFAULT_POLICY
from mcsm.errors import McsmError
from mcsm.map import ops
from mcsm.map.deferral import DEFAULT_EXPIRY, DeferOptions

log = logging.getLogger("mcsm")

# exit codes of every subcommand (documented in docs/recordings.md; keep them stable)
EXIT_OK = 0
EXIT_DIVERGED = 1  # replay: a checkpoint, a sequence number or an input does not match
EXIT_USAGE = 2  # bad arguments, missing or unreadable file, not a recording, unwritable output
EXIT_RECORDING_FAILED = 3  # serve: the recording could not be written; serving stopped
EXIT_CUT = 4  # the file ends before its clean close (SIGKILL, full disk): the prefix was used
EXIT_DAMAGED = 5  # a CRC does not match or a record does not decode: read up to the damage
EXIT_OTHER_ARITHMETIC = 6  # replay: recorded by another arithmetic version; not compared

EXIT_CODES_HELP = """exit codes:
  0  success (replay: every checkpoint matches and the file is complete)
  1  replay diverged (a digest, a sequence number or an input does not match)
  2  usage error: bad arguments, missing or unreadable file, not an mcsm recording,
     output path exists or is not writable, a split recording with a gap or mixed files
  3  serve: the recording could not be written (serving stopped)
  4  the recording is cut (no clean close): inspect/replay used every complete record
  5  the recording is damaged (CRC mismatch or undecodable record): read up to the damage
  6  replay: recorded by another arithmetic version of the core; digests not comparable
(replay reports the first that applies in the order 1, 5, 4, 6)"""


def build_parser() -> argparse.ArgumentParser:
    from mcsm.connect import add_connection_args

    p = argparse.ArgumentParser(prog="mcsm", description=__doc__.split("\n")[0] if __doc__
                                else None, epilog=EXIT_CODES_HELP,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=_version_text())
    sub = p.add_subparsers(dest="command", required=True)

    # choices and defaults come from the code that applies them (core, server), never copies
    from mcsm.core.smap import GAINS, METHODS, RULES, SPACES, StochasticMap
    from mcsm.replication_defaults import (
        DEFAULT_LEASE_TTL_S,
        DEFAULT_LOG_MAX_AGE_S,
        DEFAULT_LOG_MAX_BYTES,
        DEFAULT_REPLICAS,
    )
    from mcsm.server import ServerOptions

    so = ServerOptions()
    mo = StochasticMap(2).options()
    s = sub.add_parser("serve", help="run the map server (embedded Zenoh peer)",
                       description=_para("Run the map server: an embedded Zenoh peer that "
                                         "serves maps, applies updates in one order, records "
                                         "every input to MCAP before it acknowledges it, and "
                                         "answers queries. Prints 'listening on ENDPOINT' "
                                         "when ready; SIGINT/SIGTERM close the recording."),
                       epilog=EXIT_CODES_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_connection_args(s, role="server")
    s.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="join a Zenoh router (repeatable; mcsm router): clients then find "
                        "this server's maps through the router by key alone; without "
                        "--listen the server listens nowhere itself")

    rt = sub.add_parser("router", help="run a Zenoh router that servers and clients join "
                        "(several servers, one key space)",
                        description="Run a Zenoh router (no map of its own) that map servers "
                                    "(mcsm serve --connect) and clients join: several servers, "
                                    "one key space (docs/fleet.md).")
    rt.add_argument("--listen", required=True, metavar="ENDPOINT",
                    help="endpoint to listen on, e.g. tcp/0.0.0.0:7447")
    rt.add_argument("--zenoh-config", default=None, metavar="FILE",
                    help="Zenoh JSON5 config (TLS, access control); its mode becomes router")
    rt.add_argument("--log-level", default="INFO")
    from mcsm.natsrun import add_arguments as add_nats_cluster_args

    add_nats_cluster_args(sub.add_parser(
        "nats-cluster", help="run a NATS JetStream cluster on this machine: the replicated "
        "log of a fleet's maps (docs/fleet.md)"))
    s.add_argument("--samples", type=int, default=so.map_options["n_samples"], metavar="N",
                   help="samples per AT for new maps (default %(default)s)")
    s.add_argument("--method", choices=METHODS, default=mo["method"],
                   help="case II update (default %(default)s)")
    s.add_argument("--space", choices=SPACES, default=mo["space"],
                   help="vector space of the merges (default %(default)s)")
    s.add_argument("--analysis", choices=RULES, default=mo["analysis"],
                   help="analysis rule of the joint update (default %(default)s)")
    s.add_argument("--shrink", type=_shrink, default=mo["shrink"], metavar="C|none",
                   help="correlation shrink constant of the joint update (default "
                        "%(default)g; 'none' turns it off)")
    s.add_argument("--inflation", type=_inflation, default=mo["inflation"], metavar="F|adaptive",
                   help="anomaly inflation per loop closure: a factor in [1, 2) or 'adaptive' "
                        "(default %(default)g: none)")
    s.add_argument("--gain", choices=GAINS, default=mo["gain"],
                   help="cross-covariance estimator of the joint update: 'direct' (default) or "
                        "'endpoints' (through the loop's two endpoint frames; better on pose "
                        "graphs, with --inflation 1.002 in 3-D; tangent space only)")
    s.add_argument("--gate", type=_gate, default=DEFAULT_GATE, metavar="Q|none",
                   help="loop-closure gate: reject a loop closure whose normalised innovation "
                        "exceeds the chi-square quantile Q for its dof; the map is unchanged "
                        f"and the ack's verdict says why (default {DEFAULT_GATE}: one wrong "
                        "closure wrecks a map, see docs/outliers.md; 'none' turns it off; a "
                        "request marked trusted bypasses it)")
    s.add_argument("--device", default="cpu", metavar="cpu|cuda|cuda:K",
                   help="where the maps keep their edges: 'cpu' (default) or 'cuda' (a GPU: "
                        "the passes that grow with the map run there, same digests as on a "
                        "CPU; needs the 'gpu' extra, CuPy; docs/kernel.md)")
    s.add_argument("--gate-defer", type=_defer, nargs="?", const=DEFAULT_EXPIRY, default=None,
                   metavar="K",
                   help="hold the first loop closure of a revisit as 'pending' until a second "
                        "one agrees with it through the map's joint samples, then apply both; "
                        f"after K updates (default {DEFAULT_EXPIRY}) it goes through the gate "
                        "alone (default off; docs/outliers.md)")
    gs = DEFAULT_GATE_SCALE
    s.add_argument("--gate-scale", type=_gate_scale, default=gs, metavar="W:T:S|none",
                   help="scale the gate's threshold by m / T clipped to [1, S], m the median "
                        "over the last W gated closures of their NIS over the chi-square "
                        f"median (default {gs['window']}:{gs['open']:g}:{gs['max']:g}, "
                        "docs/design.md 'Relinearisation'; 'none': a fixed threshold)")
    s.add_argument("--history", type=_history, default=DEFAULT_HISTORY_BYTES,
                   metavar="BYTES|none",
                   help="bound of each map's record of its inputs, from which it relinearises "
                        "(default %(default)s; beyond it the oldest removed frames are "
                        "marginalised into a prior; 'none': no record, no relinearisation)")
    pol = DEFAULT_POLICY or Policy()
    s.add_argument("--relinearize-nis", type=_gate, default=pol.nis, metavar="Q|none",
                   help="relinearise a component after an accepted loop closure whose NIS "
                        "exceeds the chi-square quantile Q (default %(default)s)")
    s.add_argument("--relinearize-every", type=_every, default=pol.every, metavar="K|none",
                   help="relinearise a component every K of its inputs (default %(default)s)")
    s.add_argument("--relinearize-gap", type=_defer, default=pol.gap, metavar="K",
                   help="inputs of a component between two automatic relinearisations "
                        "triggered by NIS or the gate (default %(default)s)")
    s.add_argument("--relinearize-regate", type=_every, default=pol.regate, metavar="K|none",
                   help="when a loop closure fails the gate and K of the last 8 gated closures "
                        "failed, relinearise its component and gate it again (at most once per "
                        "--relinearize-gap inputs; default %(default)s)")
    s.add_argument("--record", type=Path, default=None, metavar="PATH.mcap",
                   help="new recording file (default recordings/run-<UTC time>.mcap)")
    s.add_argument("--restore", type=Path, nargs="+", default=None, metavar="PATH.mcap",
                   help="rebuild the maps from this recording first, then go on; the new "
                        "recording (--record) repeats its inputs so it replays on its own. A "
                        "split recording: its files, a directory or a pattern (only the files "
                        "from the one holding the latest usable snapshot on are read)")
    s.add_argument("--split-size", type=_bytes, default=so.split_bytes, metavar="BYTES",
                   help="start a new recording file once the current one holds this many "
                        "bytes (K, M, G suffixes: KiB, MiB, GiB; default 0: never). --record "
                        "run.mcap then writes run_0000.mcap, run_0001.mcap, ...; each starts "
                        "with a snapshot of every map and replays on its own")
    s.add_argument("--split-duration", type=float, default=so.split_s, metavar="S",
                   help="start a new recording file once the current one is S seconds old "
                        "(default 0: never); with --split-size, whichever comes first")
    s.add_argument("--checkpoint-every", type=int, default=so.checkpoint_every, metavar="K",
                   help="record the state digest every K operations per map "
                        "(default %(default)s)")
    s.add_argument("--queue-size", type=int, default=so.queue_size,
                   help="requests waiting for the worker before 'busy' errors "
                        "(default %(default)s; reads and writes each)")
    s.add_argument("--queue-bytes", type=_bytes, default=so.queue_bytes, metavar="BYTES",
                   help="request payload bytes waiting for the worker before 'busy' errors "
                        "(default %(default)s = 128M; reads and writes each; a queued update "
                        "costs about 3 times its payload in memory)")
    s.add_argument("--fsync", action="store_true",
                   help="fsync the recording before each ack (survives power loss; slow)")
    s.add_argument("--snapshot-every", type=int, default=so.snapshot_every, metavar="K",
                   help="keep an in-memory snapshot of each map every K operations "
                        "(default %(default)s); retract/reinstate restore one and apply the later "
                        "inputs again")
    s.add_argument("--snapshots-kept", type=int, default=so.snapshots_kept, metavar="S",
                   help="snapshots kept per map (default %(default)s): updates of the last "
                        "(S-1)*K to S*K operations can be retracted")
    s.add_argument("--retract-window-bytes", type=_bytes, default=so.retract_window_bytes,
                   metavar="BYTES",
                   help="bytes each map's retract window (its snapshots and logged requests) "
                        "holds at most (default %(default)s = 256M); with large maps or "
                        "requests the window then reaches back fewer operations")
    s.add_argument("--disk-snapshot-every", type=int, default=so.disk_snapshot_every,
                   metavar="K",
                   help="record each map's whole state every K operations (default "
                        "%(default)s; 0: "
                        "never); --restore starts from the latest one plus the inputs after it")
    s.add_argument("--id-ttl-s", type=float, default=so.id_ttl_s, metavar="S",
                   help="remember each applied request id this long, so a retry (also after "
                        "a --restore) is not applied twice (default %(default)g)")
    s.add_argument("--id-memory", type=int, default=so.lru_size, metavar="K",
                   help="remember at most this many request ids per map (default %(default)s)")
    hs = s.add_argument_group("replication (docs/fleet.md; needs the fleet extra)")
    hs.add_argument("--nats", action="append", default=None, metavar="URL",
                    help="replicate every map through this NATS JetStream cluster (repeatable "
                         "or comma-separated, e.g. nats://127.0.0.1:4222; mcsm nats-cluster): "
                         "an update is acknowledged once the log stored it on a quorum")
    hs.add_argument("--nats-auth", default=None, metavar="FILE",
                    help="this server's NATS credentials: JSON {\"user\", \"password\"} "
                         "(deploy/: serverK.nats.json)")
    hs.add_argument("--standby-of", action="append", default=None, metavar="MAP",
                    help="follow MAP's log as a hot standby (repeatable): apply and record "
                         "its inputs, take over when its lease is free")
    hs.add_argument("--replicas", type=int, default=DEFAULT_REPLICAS, metavar="R",
                    help="copies of each new map's log, lease and snapshots (default "
                         "%(default)s; 1 for a one-node cluster)")
    hs.add_argument("--lease-ttl", type=float, default=DEFAULT_LEASE_TTL_S, metavar="S",
                    help="a map's lease lasts this long unless renewed: a SIGKILLed primary's "
                         "standby takes over after it (set by the first server of a "
                         "cluster; default %(default)g)")
    hs.add_argument("--log-max-bytes", type=int, default=DEFAULT_LOG_MAX_BYTES, metavar="B",
                    help="a new map's log keeps at most this many bytes, the oldest inputs "
                         "dropped first (default %(default)s; 0: no limit)")
    hs.add_argument("--log-max-age", type=float, default=DEFAULT_LOG_MAX_AGE_S, metavar="S",
                    help="a new map's log drops inputs older than this (default 0: never; "
                         "at least --id-ttl-s)")
    s.add_argument("--log-level", default="INFO")

    raw = argparse.RawDescriptionHelpFormatter
    r = sub.add_parser("replay", help="rebuild the maps of a recording and check its digests",
                       description=_para("Rebuild every map of a recording with the server's own "
                                   "code and compare the map's digest at every checkpoint "
                                   "and snapshot: 'identical' (exit 0), or what differs, where "
                                   "the file is cut or damaged, or that another arithmetic "
                                   "version made it (docs/recordings.md)."),
                       epilog=EXIT_CODES_HELP, formatter_class=raw)
    r.add_argument("file", type=Path, nargs="+",
                   help="the recording (complete, cut or damaged); a split recording's files: "
                        "several paths, a directory or a pattern")
    r.add_argument("--json", action="store_true", help="print the result as one JSON line")
    r.add_argument("--no-progress", action="store_true",
                   help="no progress bar (terminal) or progress lines (log)")

    i = sub.add_parser("inspect", help="summarise a recording and verify its CRCs",
                       description=_para("Check every CRC of a recording (chunks, data section, "
                                   "summary) and list its maps: options, operations, frames "
                                   "named, senders, checkpoints, the arithmetic version and "
                                   "the size per input; nothing is replayed."),
                       epilog=EXIT_CODES_HELP, formatter_class=raw)
    i.add_argument("file", type=Path, nargs="+",
                   help="the recording; a split recording's files (paths, a directory or a "
                        "pattern): each is inspected, in set order")
    i.add_argument("--json", action="store_true", help="one JSON line per file")

    v = sub.add_parser("recover", help="write a clean, indexed copy of every complete record "
                       "of a cut or damaged recording",
                       description=_para("Copy every complete record of a cut (SIGKILL, full disk) "
                                   "or damaged (bit rot) recording into a new chunked, indexed "
                                   "file that every MCAP reader opens; intact chunks after "
                                   "damage are copied too. Never overwrites a file."),
                       epilog=EXIT_CODES_HELP, formatter_class=raw)
    v.add_argument("file", type=Path, nargs="+", metavar="IN",
                   help="the cut or damaged recording; or a split recording's files (paths, "
                        "a directory or a pattern)")
    v.add_argument("-o", "--output", type=Path, required=True, metavar="OUT",
                   help="the new file (refused if it exists); for a split recording a new "
                        "directory, which gets a copy of each file under its name")
    v.add_argument("--no-progress", action="store_true",
                   help="no progress bar (terminal) or progress lines (log)")

    c = sub.add_parser("cat", help="print the inputs of a recording, one per line",
                       description=_para("Print every recorded input, one per line: map, seq, "
                                   "operation, frames, sender and request id, and each AT as "
                                   "its sample count, mean and covariance (or every sample)."),
                       epilog=EXIT_CODES_HELP, formatter_class=raw)
    c.add_argument("file", type=Path, nargs="+",
                   help="the recording; a split recording's files (paths, a directory or a "
                        "pattern), printed in set order")
    c.add_argument("--json", action="store_true", help="one JSON object per line")
    c.add_argument("--samples", action="store_true",
                   help="print every sample (default: the mean and covariance of each AT)")

    from mcsm.viz.commands import add_parsers as add_viz_parsers

    add_viz_parsers(sub)  # plot, export FORMAT, export-foxglove (docs/visualising.md)
    from mcsm.viz.rosbag import add_parser as add_export_rosbag

    add_export_rosbag(sub)  # export-rosbag (docs/ros2.md)
    add_plugin_commands(sub)  # e.g. view, ros2, from the mcsm_client package
    return p


#: entry-point group of subcommands other packages add to ``mcsm`` (``mcsm view``, ``mcsm ros2``):
#: each entry point is a function ``add_parser(subparsers)`` that adds its subparser and sets
#: its ``run(args) -> int`` with ``set_defaults(plugin_run=...)``. mcsm never imports them by
#: name, so the server package depends on no client package.
PLUGIN_GROUP = "mcsm.commands"


def add_plugin_commands(sub: Any) -> None:
    """Add the subcommands of :data:`PLUGIN_GROUP`; one that fails to load is skipped with a
    warning on stderr (mcsm's own commands still work)."""
    from importlib.metadata import entry_points

    for ep in sorted(entry_points(group=PLUGIN_GROUP), key=lambda e: e.name):
        try:
            ep.load()(sub)
        except Exception as exc:  # a broken plugin must not break mcsm
            print(f"mcsm: warning: subcommand {ep.name!r} ({ep.value}) not loaded: "
                  f"{type(exc).__name__}: {exc}", file=sys.stderr)


def _para(text: str) -> str:
    """A description wrapped for the raw help formatter (which keeps the exit-code table)."""
    import textwrap

    return textwrap.fill(text, 79)


def main(argv: list[str] | None = None) -> int:
    from mcsm.connect import flags_after_command

    # `mcsm --listen X serve` works like `mcsm serve --listen X`
    argv = flags_after_command(sys.argv[1:] if argv is None else list(argv), "serve")
    ros_args: list[str] = []
    if "--ros-args" in argv:  # ROS's convention: everything from --ros-args on is ROS's
        at = argv.index("--ros-args")
        argv, ros_args = argv[:at], argv[at:]
    parser = build_parser()
    args = parser.parse_args(argv)
    if ros_args:
        if not hasattr(args, "ros_args"):
            parser.error(f"--ros-args is for mcsm ros2, not mcsm {args.command}")
        args.ros_args = ros_args
    try:
        if args.command == "serve":
            return serve(args)
        if args.command == "router":
            return router_cmd(args)
        if args.command == "nats-cluster":
            from mcsm.natsrun import run as nats_cluster

            return nats_cluster(args)
        if args.command == "replay":
            return replay_cmd(args)
        if args.command == "recover":
            return recover_cmd(args)
        if args.command == "cat":
            return cat_cmd(args)
        if getattr(args, "plugin_run", None) is not None:
            return int(args.plugin_run(args))
        if args.command == "export-rosbag":
            from mcsm.viz.rosbag import run as run_export_rosbag

            return run_export_rosbag(args)
        if args.command in ("plot", "export", "export-foxglove"):
            from mcsm.viz.commands import run as run_viz

            return run_viz(args)
        return inspect_cmd(args)
    except BrokenPipeError:  # `mcsm inspect FILE | head`: the reader went away
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


# ------------------------------------------------------------------------------------ serve
def _bytes(text: str) -> int:
    """A byte count: digits with an optional K, M or G suffix (KiB, MiB, GiB)."""
    t = text.strip().upper().removesuffix("B").removesuffix("I")
    scale = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(t[-1:], 1)
    try:
        n = int(float(t[:-1] if scale > 1 else t) * scale)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"expected a byte count such as 1048576 or 512M, "
                                         f"got {text!r}")
    return n


def _shrink(text: str) -> float | None:
    if text == "none":
        return None
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0 or 'none', got {text!r}") \
            from None


def _gate(text: str) -> float | None:
    if text == "none":
        return None
    try:
        q = float(text)
    except ValueError:
        q = -1.0
    if not 0.0 < q < 1.0:
        raise argparse.ArgumentTypeError(f"expected a quantile in (0, 1) or 'none', got {text!r}")
    return q


def _gate_scale(text: str) -> dict[str, Any] | None:
    if text == "none":
        return None
    parts = text.split(":")
    try:
        d: dict[str, Any] = {"window": int(parts[0]), "open": float(parts[1]),
                             "max": float(parts[2])}
    except (ValueError, IndexError):
        d = {"window": 0, "open": 0.0, "max": 0.0}
    if len(parts) != 3 or not (1 <= d["window"] <= 999 and d["open"] >= 1.0
                               and d["max"] >= 1.0):
        raise argparse.ArgumentTypeError(f"expected W:T:S (W in [1, 999], T, S >= 1) or "
                                         f"'none', got {text!r}")
    return d


def _history(text: str) -> int | None:
    if text == "none":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if not 2**16 <= n <= 2**40:
        raise argparse.ArgumentTypeError(f"expected a byte count in [65536, 2**40] or 'none', "
                                         f"got {text!r}")
    return n


def _every(text: str) -> int | None:
    return None if text == "none" else _defer(text)


def _policy(args: argparse.Namespace) -> dict[str, Any] | None:
    """The automatic relinearisation policy of the serve flags (None: none asked for)."""
    pol = DEFAULT_POLICY or Policy()
    if args.relinearize_nis is None and args.relinearize_every is None \
            and args.relinearize_regate is None:
        return None
    if args.history is None:
        if (args.relinearize_nis, args.relinearize_every, args.relinearize_regate) == (
                pol.nis, pol.every, pol.regate):
            return None  # --history none turns the default policy off
        raise McsmError("--relinearize-* needs a history (not --history none)")
    return {"nis": args.relinearize_nis, "every": args.relinearize_every,
            "regate": args.relinearize_regate, "gap": args.relinearize_gap}


def _defer(text: str) -> int:
    try:
        k = int(text)
    except ValueError:
        k = 0
    if k < 1:
        raise argparse.ArgumentTypeError(f"expected a number of updates >= 1, got {text!r}")
    return k


def _inflation(text: str) -> float | str:
    if text == "adaptive":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a number in [1, 2) or 'adaptive', got {text!r}") from None


def router_cmd(args: argparse.Namespace) -> int:
    """``mcsm router``: a Zenoh router (no map of its own) until SIGINT or SIGTERM."""
    import zenoh

    from mcsm.connect import router_config

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    try:
        conf = router_config(args.listen, args.zenoh_config)
        session = zenoh.open(conf)
    except (McsmError, zenoh.ZError, OSError) as exc:
        print(f"mcsm router: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    old = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT,
                                                                       signal.SIGTERM)}
    print(f"routing on {args.listen} (zid {session.zid()})", flush=True)
    try:
        while not stop.wait(0.5):
            pass
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        session.close()
    return 0


def serve(args: argparse.Namespace) -> int:
    import zenoh

    from mcsm.connect import listen_endpoints, security_warning, server_config
    from mcsm.log.progress import progress_bar
    from mcsm.server import Server, ServerOptions

    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    record = args.record
    if record is None:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        record = Path("recordings") / f"run-{stamp}.mcap"
        k = 1
        while record.exists() and k < 1000:
            record = Path("recordings") / f"run-{stamp}-{k}.mcap"
            k += 1
    restore: list[Path] | None = None
    if args.restore:
        from mcsm.log.recset import resolve

        try:
            restore = resolve(args.restore)
        except (McsmError, OSError) as exc:
            print(f"mcsm serve: --restore: {exc}", file=sys.stderr)
            return EXIT_USAGE
    # restoring without --map serves the recording's maps (or "default" if it has none)
    standby_of = list(dict.fromkeys(args.standby_of or []))
    maps = args.map or ([] if args.restore or standby_of else [wire.DEFAULT_MAP])
    try:
        policy = _policy(args)
    except McsmError as exc:
        print(f"mcsm serve: {exc}", file=sys.stderr)
        return 2
    opts = ServerOptions(
        maps=list(dict.fromkeys(maps)), prefix=args.prefix,
        map_options={"n_samples": args.samples, "method": args.method, "space": args.space,
                     "analysis": args.analysis, "shrink": args.shrink,
                     "inflation": args.inflation, "gain": args.gain, "gate": args.gate,
                     "gate_scale": args.gate_scale, "history": args.history,
                     "relinearize": policy},
        record=record, restore=restore, checkpoint_every=max(1, args.checkpoint_every),
        queue_size=args.queue_size, queue_bytes=max(1, args.queue_bytes),
        retract_window_bytes=args.retract_window_bytes, split_bytes=args.split_size,
        split_s=max(0.0, args.split_duration), fsync=args.fsync, lru_size=max(1, args.id_memory),
        id_ttl_s=max(0.0, args.id_ttl_s), snapshot_every=max(1, args.snapshot_every),
        snapshots_kept=max(1, args.snapshots_kept),
        disk_snapshot_every=max(0, args.disk_snapshot_every), standby_of=standby_of,
        device=args.device,
        gate_defer=None if args.gate_defer is None else DeferOptions(expiry=args.gate_defer))
    try:
        opts.nats = _nats_options(args)
        for name in [*opts.maps, *opts.standby_of]:
            wire.map_keys(name, opts.prefix)
        if opts.device != "cpu":  # one clear line now, not a traceback at the first map
            from mcsm.core.device import backend_for
            backend_for(opts.device)
        conf = server_config(args.listen, args.zenoh_config, connect=args.connect)
    except (McsmError, zenoh.ZError, OSError) as exc:
        print(f"mcsm serve: {exc}", file=sys.stderr)
        return 2
    warning = security_warning(conf)
    if warning is not None:
        log.warning("%s", warning)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"mcsm serve: cannot open the Zenoh session: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal %d: shutting down", signum)
        stop.set()

    old_handlers = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    server = Server(session, opts, progress=progress_bar() if args.restore else None)
    code = EXIT_OK
    try:
        try:
            server.start()
        except (McsmError, OSError) as exc:
            print(f"\nmcsm serve: {exc}", file=sys.stderr)
            code = EXIT_RECORDING_FAILED if _no_space(exc) else EXIT_USAGE
            return code
        if args.restore:
            sys.stderr.write("\n")
        log.info("recording to %s", opts.record)
        via = f" (joined {' '.join(args.connect)})" if args.connect else ""
        print(f"listening on {' '.join(listen_endpoints(conf)) or '-'}{via}", flush=True)
        while not stop.wait(0.5):
            if server.failed.is_set():
                log.critical("stopping after a recording failure")
                code = EXIT_RECORDING_FAILED
                break
    finally:
        server.close()
        session.close()
        for sig, handler in old_handlers.items():
            signal.signal(sig, handler)
    if server.failed.is_set():  # also when closing the file hit the full disk
        print(f"mcsm serve: stopped: the recording {server.recording_path} could not be "
              "written (see the log); it holds every acknowledged input", file=sys.stderr)
        return EXIT_RECORDING_FAILED
    return code


def _no_space(exc: BaseException) -> bool:
    """An error of writing the recording itself (full disk, quota, file size limit, I/O)."""
    import errno

    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG,
                                                      errno.EIO)


def _nats_options(args: argparse.Namespace) -> Any:
    """``--nats``, ``--nats-auth``, ... as :class:`mcsm.replication.NatsOptions` (None
    without ``--nats``: then nothing of NATS is imported).

    Raises
    ------
    McsmError
        A replication flag without ``--nats``, or unreadable credentials.
    """
    urls = [u.strip() for a in (args.nats or []) for u in a.split(",") if u.strip()]
    if not urls:
        if args.nats_auth is not None:
            raise McsmError("--nats-auth needs --nats URL")
        return None
    from mcsm.replication import NatsOptions

    o = NatsOptions(urls=urls, replicas=max(1, args.replicas),
                    lease_ttl_s=max(0.2, args.lease_ttl),
                    max_bytes=max(0, args.log_max_bytes), max_age_s=max(0.0, args.log_max_age))
    if args.nats_auth is not None:
        a = NatsOptions.load_auth(args.nats_auth)
        o.user, o.password = a.get("user"), a.get("password")
        o.tls_ca, o.tls_cert, o.tls_key = a.get("tls_ca"), a.get("tls_cert"), a.get("tls_key")
    if o.max_age_s and o.max_age_s < args.id_ttl_s:
        raise McsmError(f"--log-max-age {o.max_age_s:g} is below --id-ttl-s {args.id_ttl_s:g}: "
                        "the log's de-duplication window must fit in it")
    return o


# ------------------------------------------------------------------------------------ common
def _version_text() -> str:
    from mcsm import __version__
    from mcsm.core import ARITHMETIC_VERSION

    return (f"mcsm {__version__} (core arithmetic version {ARITHMETIC_VERSION}, wire protocol "
            f"v{wire.VERSION}, recording format v2)")


def _input_files(cmd: str, args: list[Path]) -> tuple[list[Path], str | None]:
    """The files ``args`` name (one recording, or a split recording's files in set order,
    :mod:`mcsm.log.recset`) and why they cannot be read (None if they can)."""
    from mcsm.log.recset import expand, order
    from mcsm.log.topics import RecordingError

    try:
        files = expand(args)
    except RecordingError as exc:
        return [], f"mcsm {cmd}: {exc}"
    for f in files:
        why = _input_file(cmd, f)
        if why:
            return files, why
    try:
        return order(files), None
    except (RecordingError, OSError) as exc:
        return files, f"mcsm {cmd}: {exc}"


def _label(files: list[Path]) -> str:
    return str(files[0]) if len(files) == 1 else f"{files[0]} .. {files[-1].name}"


def _input_file(cmd: str, path: Path) -> str | None:
    """Why ``path`` cannot be read as an input file (None if it can)."""
    if not path.exists():
        return f"mcsm {cmd}: {path}: no such file"
    if path.is_dir():
        return f"mcsm {cmd}: {path}: is a directory, not a recording"
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        return f"mcsm {cmd}: {path}: cannot open: {exc.strerror or exc}"
    from mcsm.log.filetype import not_a_recording

    why = not_a_recording(path)  # e.g. a Foxglove scene: not damaged, not ours
    return f"mcsm {cmd}: {path}: {why}" if why else None


def _output_file(cmd: str, path: Path) -> str | None:
    """Why ``path`` cannot be written as a new output file (None if it can); checked before
    any long work starts."""
    import os

    if path.exists():
        return f"mcsm {cmd}: {path}: exists; refusing to overwrite"
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        return f"mcsm {cmd}: {path}: directory {parent} does not exist"
    if not os.access(parent, os.W_OK | os.X_OK):
        return f"mcsm {cmd}: {path}: directory {parent} is not writable"
    return None


def _progress(args: argparse.Namespace, label: str) -> Any:
    from mcsm.log.progress import progress_bar

    return None if getattr(args, "no_progress", False) else progress_bar(label=label)


def _state_line(complete: bool, cut: bool, damage: str | None, tail: str | None) -> str:
    if complete:
        return "complete"
    if damage is not None:
        return f"DAMAGED: {damage}"
    if cut:
        return f"CUT (no clean close): {tail}"
    return "not read to the end"


# ------------------------------------------------------------------------------------ replay
MACHINE_BOUND = ("method=paper in the quaternion space runs on numpy/BLAS: it replays "
                 "bit-identically only on the machine family that recorded it")


def replay_cmd(args: argparse.Namespace) -> int:
    from mcsm.core import ARITHMETIC_VERSION
    from mcsm.log.replay import replay
    from mcsm.log.topics import RecordingError

    files, why = _input_files("replay", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    label = _label(files)
    bar = _progress(args, f"replay {files[0].name}" + (f" (+{len(files) - 1} files)"
                                                       if len(files) > 1 else ""))
    try:
        rep = replay(files, progress=bar)
    except (RecordingError, OSError) as exc:
        print(f"mcsm replay: cannot read {label}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        if bar is not None:
            bar.close()
    digests = rep.final_digests()
    speed = rep.n_inputs / rep.elapsed_s if rep.elapsed_s > 0 else float("inf")
    other = rep.other_arithmetic
    n_cp = len(rep.checkpoints)
    if rep.divergence is not None:
        code, status = EXIT_DIVERGED, "diverged"
        verdict = f"DIVERGED: {rep.divergence}"
    elif rep.damage is not None:
        code, status = EXIT_DAMAGED, "damaged"
        verdict = (f"DAMAGED: {rep.damage}; replayed {rep.n_inputs} inputs and verified "
                   f"{rep.checkpoints_ok} checkpoints before the damage (`mcsm recover` saves "
                   "the intact records)")
    elif rep.cut:
        code, status = EXIT_CUT, "cut"
        verdict = (f"CUT: the file ends without a clean close ({rep.tail_error}); replayed "
                   f"{rep.n_inputs} inputs and verified {rep.checkpoints_ok} checkpoints "
                   "before the cut; anything after it is not in the file")
    elif other:
        code, status = EXIT_OTHER_ARITHMETIC, "other_arithmetic"
        versions = ", ".join(f"map {n!r} version {v}" for n, v in other.items())
        verdict = (f"OTHER ARITHMETIC: recorded by arithmetic version(s) {versions}; this mcsm "
                   f"computes with version {ARITHMETIC_VERSION}, so its digests cannot be "
                   f"reproduced here (not a divergence): {rep.checkpoints_other_arithmetic} "
                   "checkpoints not compared")
    else:
        code, status = EXIT_OK, "identical"
        verdict = "identical"
    if args.json:
        print(json.dumps({"file": label, "files": [str(f) for f in files],
                          "status": status, "exit_code": code,
                          "identical": code == EXIT_OK, "divergence": rep.divergence,
                          "inputs": rep.n_inputs, "checkpoints": n_cp,
                          "checkpoints_ok": rep.checkpoints_ok,
                          "checkpoints_other_arithmetic": rep.checkpoints_other_arithmetic,
                          "complete": rep.complete, "cut": rep.cut, "damage": rep.damage,
                          "tail_error": rep.tail_error,
                          "arithmetic_versions": rep.arithmetic_versions,
                          "arithmetic_version_here": ARITHMETIC_VERSION, "digests": digests,
                          "seq": {n: s.seq for n, s in rep.states.items()},
                          "elapsed_s": rep.elapsed_s, "ops_per_s": speed}))
        return code
    not_compared = (f", {rep.checkpoints_other_arithmetic} not comparable (other arithmetic)"
                    if rep.checkpoints_other_arithmetic else "")
    print(f"{label}: {rep.n_inputs} inputs replayed in {rep.elapsed_s:.3f} s "
          f"({speed:.0f} ops/s); {rep.checkpoints_ok}/{n_cp} checkpoints match{not_compared}")
    for name, d in digests.items():
        print(f"map {name}: seq {rep.states[name].seq}, digest {d}")
        if not rep.states[name].map.portable:
            print(f"map {name}: {MACHINE_BOUND}")
    print(verdict)
    return code


# ------------------------------------------------------------------------------------ inspect
def inspect_cmd(args: argparse.Namespace) -> int:
    """Inspect each file (of a split recording: in set order); the exit code is the worst:
    5 (damaged) over 4 (cut) over 0."""
    from mcsm.log.recset import set_file

    files, why = _input_files("inspect", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    codes = []
    for k, f in enumerate(files):
        code = _inspect_one(f, args.json)
        if code == EXIT_USAGE:
            return code
        codes.append(code)
        if len(files) > 1 and not args.json:
            sf = set_file(f)
            print(f"  split recording {sf.set_id[:8]}: file {k + 1} of {len(files)} given "
                  f"(index {sf.index} of the set)")
    return max(codes, key=lambda c: {EXIT_DAMAGED: 2, EXIT_CUT: 1}.get(c, 0))


def _inspect_one(path: Path, as_json: bool) -> int:
    from mcsm.core import ARITHMETIC_VERSION
    from mcsm.log.reader import RecordingReader
    from mcsm.log.topics import (
        TOPIC_CHECKPOINT,
        TOPIC_CONFIG,
        TOPIC_OPS,
        TOPIC_SNAPSHOT,
        RecordingError,
    )

    reader = RecordingReader(path, edges=False)  # snapshots checked, not kept
    maps: dict[str, dict[str, Any]] = {}
    times: list[int] = []
    try:
        for item in reader:
            d = item.data
            name = str(d.get("map"))
            m = maps.setdefault(name, {"options": None, "ops": Counter(), "kinds": Counter(),
                                       "frames": set(), "checkpoints": [], "last_seq": 0,
                                       "senders": Counter(), "arithmetic_version": None})
            times.append(item.log_time_ns)
            if item.topic == TOPIC_CONFIG:
                m["options"] = d.get("options")
                m["gate_defer"] = d.get("gate_defer")
                m["restored_from"] = d.get("restored_from")
                m["arithmetic_version"] = d.get("arithmetic_version",
                                                reader.arithmetic_version)
            elif item.topic == TOPIC_CHECKPOINT:
                m["checkpoints"].append((d.get("seq"), d.get("digest"), d.get("reason")))
            elif item.topic == TOPIC_SNAPSHOT:
                m.setdefault("snapshots", []).append(d.get("seq"))
            elif item.topic in TOPIC_OPS:
                op = TOPIC_OPS[item.topic]
                m["ops"][op] += 1
                m["last_seq"] = d.get("seq")
                m["senders"][str(d.get("sender", ""))] += 1
                try:
                    req = wire.unpack(d["request"])
                except (McsmError, KeyError) as exc:
                    m["kinds"]["undecodable"] += 1
                    log.debug("undecodable request: %s", exc)
                    continue
                if op == "update":
                    shape = req.get("samples", {}).get("shape", [0, 7])
                    m["kinds"]["point_update" if shape[-1] == 3 else "update"] += 1
                    m["frames"].update(str(req.get(k)) for k in ("a", "b"))
                elif op == "import":
                    m["frames"].update(map(str, req.get("submap", {}).get("frames", [])))
    except (RecordingError, OSError) as exc:
        print(f"mcsm inspect: cannot read {path}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    size = path.stat().st_size
    span = (max(times) - min(times)) / 1e9 if times else 0.0
    code = EXIT_OK if reader.complete else EXIT_DAMAGED if reader.damage else EXIT_CUT
    if reader.layout == "indexed":
        crcs = (f"{reader.n_chunks_crc}/{reader.n_chunks} chunk CRCs"
                f"{', data section CRC' if reader.data_crc else ''}"
                f"{', summary CRC' if reader.summary_crc else ''} verified"
                f"{'' if reader.complete else ' before it stopped'}")
    elif reader.layout == "flat":
        crcs = "flat layout without CRCs (format 1): integrity not verifiable"
    else:
        crcs = "no records"
    n_in = sum(sum(m["ops"].values()) for m in maps.values())
    per_op = size / n_in if n_in else 0.0
    meta = reader.metadata.get("mcsm", {})
    if as_json:
        print(json.dumps({
            "file": str(path), "bytes": size, "bytes_per_input": per_op,
            "set": meta.get("set"), "set_index": meta.get("set_index"),
            "complete": reader.complete, "cut": reader.cut, "damage": reader.damage,
            "tail_error": reader.tail_error, "exit_code": code, "library": reader.library,
            "layout": reader.layout, "chunks": reader.n_chunks,
            "chunk_crcs": reader.n_chunks_crc, "data_crc": reader.data_crc,
            "summary_crc": reader.summary_crc, "arithmetic_version": reader.arithmetic_version,
            "arithmetic_version_here": ARITHMETIC_VERSION, "span_s": span,
            "maps": {n: {"options": m["options"], "gate_defer": m.get("gate_defer"),
                         "ops": dict(m["ops"]),
                         "arithmetic_version": m["arithmetic_version"],
                         "frames_named": len(m["frames"]), "last_seq": m["last_seq"],
                         "snapshots": m.get("snapshots", []),
                         "checkpoints": m["checkpoints"]} for n, m in maps.items()}}))
        return code
    print(f"file:      {path} ({size} bytes, {per_op / 1e3:.1f} kB per input, written by "
          f"{reader.library or '?'})")
    state = _state_line(reader.complete, reader.cut, reader.damage, reader.tail_error)
    print(f"state:     {state}")
    print(f"integrity: {crcs}")
    print(f"arithmetic version {reader.arithmetic_version} (this mcsm: {ARITHMETIC_VERSION})")
    if times:
        t0 = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(min(times) / 1e9))
        print(f"time span: {span:.3f} s from {t0} UTC")
    for name, m in maps.items():
        print(f"map {name!r}: options {m['options']}")
        opts = m["options"] if isinstance(m["options"], dict) else {}
        if opts.get("method") == "paper" and opts.get("space") == "quaternion":
            print(f"  {MACHINE_BOUND}")
        if m["arithmetic_version"] not in (None, reader.arithmetic_version):
            print(f"  arithmetic version {m['arithmetic_version']}")
        if m.get("restored_from"):
            print(f"  restored from {m['restored_from']}")
        if m.get("gate_defer"):
            print(f"  --gate-defer {m['gate_defer']}")
        ops = ", ".join(f"{k} {v}" for k, v in sorted(m["ops"].items())) or "none"
        print(f"  operations: {sum(m['ops'].values())} ({ops}); last seq {m['last_seq']}")
        if m["kinds"]:
            print("  updates:    " + ", ".join(f"{k} {v}" for k, v in sorted(m["kinds"].items())))
        print(f"  frames named in inputs: {len(m['frames'])}")
        print(f"  senders: {len(m['senders'])}")
        snaps = m.get("snapshots", [])
        if snaps:
            print(f"  snapshots: {len(snaps)} (seq {snaps[0]} .. {snaps[-1]})")
        cps = m["checkpoints"]
        shown = (f" (the first 3 and the last 2 of {len(cps)} listed; --json lists all)"
                 if len(cps) > 5 else "")
        print(f"  checkpoints: {len(cps)}{shown}")
        for seq, dig, why_cp in cps[:3] + (cps[-2:] if len(cps) > 5 else cps[3:]):
            print(f"    seq {seq:>7} {why_cp:<8} {dig}")
    return code


# ------------------------------------------------------------------------------------ recover
def recover_cmd(args: argparse.Namespace) -> int:
    """Recover one file into ``-o FILE``, or each file of a split recording into the new
    directory ``-o DIR`` (same names)."""
    files, why = _input_files("recover", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    if len(files) == 1:
        why = _output_file("recover", args.output)
        if not why and args.output.resolve() == files[0].resolve():
            why = "mcsm recover: the output must be a new file"
        if why:
            print(why, file=sys.stderr)
            return EXIT_USAGE
        return _recover_one(args, files[0], args.output)
    why = _output_file("recover", args.output)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    args.output.mkdir()
    for f in files:
        code = _recover_one(args, f, args.output / f.name)
        if code != EXIT_OK:
            return code
    return EXIT_OK


def _recover_one(args: argparse.Namespace, src: Path, dst: Path) -> int:
    from mcsm.log.recover import recover
    from mcsm.log.topics import TOPIC_CHECKPOINT, TOPIC_CONFIG, RecordingError

    bar = _progress(args, f"recover {src.name}")
    try:
        rep = recover(src, dst, progress=bar)
    except (RecordingError, OSError) as exc:
        dst.unlink(missing_ok=True)
        print(f"mcsm recover: {exc}", file=sys.stderr)
        return EXIT_USAGE
    finally:
        if bar is not None:
            bar.close()
    state = _state_line(rep.source_complete, rep.source_cut, rep.damage, rep.tail_error)
    print(f"{src}: {state}")
    if rep.chunks_after_damage:
        print(f"  {rep.chunks_after_damage} intact chunks after the damage were copied too; the "
              "records lost in the damaged part leave a gap, where a replay of the copy stops")
    print(f"{dst}: {rep.n_inputs} inputs, {rep.messages[TOPIC_CHECKPOINT]} checkpoints, "
          f"{rep.messages[TOPIC_CONFIG]} map configs ({rep.bytes_written} bytes, indexed)")
    return EXIT_OK


# ------------------------------------------------------------------------------------ cat
def _summarise(obj: Any, with_samples: bool) -> Any:
    """An AT as its mean and covariance (or every sample), points as mean and covariance."""
    import numpy as np

    from mcsm.core import mean_and_cov

    x = np.asarray(obj, dtype=np.float64)
    out: dict[str, Any] = {"n": int(x.shape[0])}
    if with_samples:
        out["samples"] = x.tolist()
        return out
    if x.shape[-1] == 7:
        mean, cov = mean_and_cov(x)
    else:
        mean, cov = x.mean(axis=0), np.cov(x, rowvar=False)
    out["mean"] = [float(v) for v in mean]
    out["cov"] = np.asarray(cov).tolist()
    return out


def _input_json(op: str, req: Any, with_samples: bool) -> dict[str, Any]:
    out = ops.get(op).describe(req)
    if isinstance(req, wire.UpdateRequest):
        out["samples"] = _summarise(req.samples, with_samples)
    elif isinstance(req, wire.SubmapImportRequest):
        out["edges"] = [_summarise(e, with_samples) for e in req.submap.edges[1:]]
    return out


def cat_cmd(args: argparse.Namespace) -> int:
    from mcsm.log.reader import RecordingReader

    files, why = _input_files("cat", args.file)
    if why:
        print(why, file=sys.stderr)
        return EXIT_USAGE
    n_samples: dict[str, int] = {}
    for f in files:
        reader = RecordingReader(f, edges=False)
        code = _cat_file(args, f, reader, n_samples)
        if code != EXIT_OK:
            return code
    return EXIT_OK


def _cat_file(args: argparse.Namespace, path: Path, reader: Any,
              n_samples: dict[str, int]) -> int:
    from mcsm.log.topics import TOPIC_CONFIG, TOPIC_OPS, RecordingError
    from mcsm.log.topics import decode_input as decode

    try:
        for item in reader:
            d = item.data
            name = str(d.get("map"))
            if item.topic == TOPIC_CONFIG:
                n_samples.setdefault(name, int(d.get("options", {}).get("n_samples", 0)))
                continue
            op = TOPIC_OPS.get(item.topic)
            if op is None:
                continue
            line: dict[str, Any] = {"map": name, "seq": d.get("seq"), "op": op,
                                    "recv_ns": d.get("recv_ns"), "sender": d.get("sender"),
                                    "id": d.get("id")}
            try:
                req = decode(op, bytes(d["request"]), n_samples.get(name, 0))
                line.update(_input_json(op, req, args.samples))
            except (McsmError, KeyError, TypeError, ValueError) as exc:
                line["error"] = f"{type(exc).__name__}: {exc}"
            if args.json:
                print(json.dumps(line))
            else:
                print(_cat_text(line))
    except BrokenPipeError:
        raise
    except (RecordingError, OSError) as exc:
        print(f"mcsm cat: cannot read {path}: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if not reader.complete:
        print(f"mcsm cat: {path}: "
              f"{_state_line(False, reader.cut, reader.damage, reader.tail_error)}",
              file=sys.stderr)
        return EXIT_DAMAGED if reader.damage else EXIT_CUT
    return EXIT_OK


def _cat_text(line: dict[str, Any]) -> str:
    head = f"{line['map']} seq {line['seq']} {line['op']}"
    if "error" in line:
        return f"{head} undecodable: {line['error']}"
    if "samples" in line:
        s = line["samples"]
        mean = " ".join(f"{v:.4g}" for v in s.get("mean", []))
        body = f"{line['a']} -> {line['b']} N={s['n']}" + (f" mean [{mean}]" if mean else "")
    elif "frame" in line:
        body = line["frame"]
    elif "target" in line:
        body = f"of {line['target']}"
    else:
        body = f"{len(line.get('frames', []))} frames"
    return f"{head} {body} (sender {line['sender']}, id {line['id']})"


if __name__ == "__main__":
    raise SystemExit(main())
