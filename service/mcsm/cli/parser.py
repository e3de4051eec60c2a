"""``mcsm``'s argument parser (every subcommand, its help and the exit-code table), the
subcommands other packages add through the entry-point group ``mcsm.commands``, and
:func:`main`, which dispatches to the command modules."""


from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Any

from mcsm.cli.common import (
    EXIT_CODES_HELP,
    _version_text,
)
from mcsm.cli.log_cmds import cat_cmd, inspect_cmd, recover_cmd, replay_cmd
from mcsm.cli.serve_cmd import (
    _bytes,
    _defer,
    _every,
    _gate,
    _gate_scale,
    _history,
    _inflation,
    _shrink,
    _spread,
    router_cmd,
    serve,
)
from mcsm.core.relinearize import DEFAULT_HISTORY_BYTES, Policy
from mcsm.core.smap import DEFAULT_GATE, DEFAULT_GATE_SCALE, DEFAULT_POLICY
from mcsm.map.deferral import DEFAULT_EXPIRY

log = logging.getLogger("mcsm")



LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
DESCRIPTION = ("The Monte Carlo stochastic map server: serve a map over Zenoh; replay, inspect,\n"
               "plot and export its recordings; bridge ROS 2 and Foxglove.")


def build_parser() -> argparse.ArgumentParser:
    from mcsm.serve.connect import add_connection_args

    p = argparse.ArgumentParser(prog="mcsm", description=DESCRIPTION, epilog=EXIT_CODES_HELP,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=_version_text())
    sub = p.add_subparsers(dest="command", required=True)

    # choices and defaults come from the code that applies them (core, server), never copies
    from mcsm.core.smap import GAINS, METHODS, RULES, SPACES, StochasticMap
    from mcsm.serve.replication_defaults import (
        DEFAULT_LEASE_TTL_S,
        DEFAULT_LOG_MAX_AGE_S,
        DEFAULT_LOG_MAX_BYTES,
        DEFAULT_REPLICAS,
    )
    from mcsm.serve.server import ServerOptions

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
    rt.add_argument("--log-level", default="INFO", type=str.upper,
                    choices=LOG_LEVELS, help="default %(default)s")
    from mcsm.serve.natsrun import add_arguments as add_nats_cluster_args

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
    s.add_argument("--relinearize-spread", type=_spread, default=pol.spread, metavar="S",
                   help="every relinearisation draws S x the posterior's deviations (1: the "
                        "posterior itself; at most 2; default %(default)s, "
                        "docs/relinearisation.md 'Redraw spread')")
    s.add_argument("--relinearize-recentre", action=argparse.BooleanOptionalAction,
                   default=None,
                   help="after every accepted loop closure that was not followed by a "
                        "relinearisation, solve its component and move its samples' means to "
                        "the solution, keeping their deviations: one solve of the component "
                        "per closure (default: on; --no-relinearize-recentre turns it off, "
                        "docs/relinearisation.md 'Re-centring')")
    s.add_argument("--relinearize-readmit", type=_every, default=pol.readmit, metavar="K|none",
                   help="keep the loop closures the gate refused within the last K inputs and "
                        "admit those a later solve agrees with (with --relinearize-recentre: "
                        "at every closure; default %(default)s)")
    s.add_argument("--relinearize-calibrate", type=lambda t: 0 if t == "none" else _defer(t),
                   default=None, metavar="K|none",
                   help="scale the gate by at least the lower quartile of how far the last K "
                        "closures it refused and admitted later were beyond it (default "
                        f"{pol.calibrate} "
                        "with --relinearize-readmit; docs/relinearisation.md 'Calibrating the "
                        "gate')")
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
    s.add_argument("--log-level", default="INFO", type=str.upper,
                    choices=LOG_LEVELS, help="default %(default)s")

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
                       description=_para("Print every recorded input, a line each: map, seq, "
                                   "operation, frames, sender and request id, and each AT's "
                                   "sample count and mean; its covariance (or with --samples "
                                   "every sample) follows on indented lines."),
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
    from mcsm.serve.connect import flags_after_command

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
            from mcsm.serve.natsrun import run as nats_cluster

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
    except KeyboardInterrupt:  # Ctrl-C in a long replay, recover or export: no traceback
        print(f"mcsm {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `mcsm inspect FILE | head`: the reader went away
        import os

        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
