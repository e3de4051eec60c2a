"""The ``mcsm plot``, ``mcsm export-foxglove`` and ``mcsm view`` subcommands.

Exit codes: 0 done; 2 a user's mistake or an unusable input, said in one line on stderr (missing
or unreadable recording, unknown map, a sequence number the map never reached, bad ground-truth
file, output path not writable, the ``viz`` extra not installed, no server answering, the
WebSocket port taken).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from mcsm.errors import McsmError

COMMANDS = ("plot", "export-foxglove", "view")


def add_parsers(sub: Any) -> None:
    """Add the three subcommands to ``mcsm``'s subparsers."""
    from mcsm.connect import add_connection_args

    p = sub.add_parser("plot", help="draw a recorded map (replayed) into a PNG with matplotlib",
                       description="Replay a recording and draw one map: landmarks with 95 % "
                                   "covariance ellipses, pose frames and their path, one "
                                   "colour per component.")
    p.add_argument("file", type=Path, nargs="+",
                   help="recording (.mcap) written by mcsm serve; a split recording's files "
                        "(several paths, a directory or a pattern, docs/recordings.md)")
    p.add_argument("-o", "--output", type=Path, default=Path("map.png"), metavar="PNG",
                   help="output image (default map.png)")
    p.add_argument("--map", default=None, metavar="NAME",
                   help="which map (default: 'default' or the recording's only map)")
    p.add_argument("--at", type=int, default=None, metavar="SEQ",
                   help="draw the map as it was after its operation SEQ (default: the end)")
    p.add_argument("--samples", action="store_true",
                   help="also draw the samples of every frame (at most 250 per frame)")
    p.add_argument("--truth", type=Path, default=None, metavar="CSV",
                   help="ground truth to overlay: CSV lines frame,x,y[,z] in the frame's "
                        "component root frame")
    p.add_argument("--view", choices=("auto", "top", "xz", "yz", "3d"), default="auto",
                   help="projection (default auto: top for a planar map, else 3d)")

    e = sub.add_parser("export-foxglove",
                       help="write a recorded map as a Foxglove scene over time (MCAP)",
                       description="Replay a recording and write one map's scene (ellipsoids, "
                                   "transforms, sample clouds) with foxglove-sdk's schemas; "
                                   "open the file in the Foxglove app.")
    e.add_argument("file", type=Path, help="recording (.mcap) written by mcsm serve")
    e.add_argument("-o", "--output", type=Path, default=Path("scene.mcap"), metavar="MCAP",
                   help="output scene file (default scene.mcap)")
    e.add_argument("--every", type=int, default=None, metavar="K",
                   help="a snapshot after every K-th operation of the map, and the last one "
                        "(default: K giving at most 100 snapshots)")
    e.add_argument("--map", default=None, metavar="NAME",
                   help="which map (default: 'default' or the recording's only map)")
    e.add_argument("--samples-per-frame", type=int, default=100, metavar="M",
                   help="sample points per frame in the point cloud (default 100; 0: none)")
    e.add_argument("--force", action="store_true", help="overwrite the output file")

    v = sub.add_parser("view", help="serve a live map to the Foxglove app (WebSocket)",
                       description="Follow a running mcsm serve over Zenoh and publish its "
                                   "map as a Foxglove scene on a WebSocket; connect the "
                                   "Foxglove app to ws://HOST:PORT.")
    add_connection_args(v, role="client")
    v.add_argument("--foxglove-port", type=int, default=8765, metavar="P",
                   help="WebSocket port for the Foxglove app (default 8765; 0 picks one)")
    v.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address to bind the WebSocket to (default 127.0.0.1)")
    v.add_argument("--samples-per-frame", type=int, default=100, metavar="M",
                   help="sample points per frame in the point cloud (default 100; 0: none)")
    v.add_argument("--timeout", type=float, default=10.0, metavar="S",
                   help="wait this long for the map server (default 10 s)")
    v.add_argument("--log-level", default="INFO")


def run(args: argparse.Namespace) -> int:
    """Run one of :data:`COMMANDS`; a user's mistake becomes one line on stderr and exit 2."""
    name = args.command
    try:
        if name == "plot":
            return _plot(args)
        if name == "export-foxglove":
            return _export(args)
        return _view(args)
    except (McsmError, OSError) as exc:
        print(f"mcsm {name}: {exc}", file=sys.stderr)
        return 2


def _check_input(path: Path) -> None:
    if not path.is_file():
        raise McsmError(f"no such recording: {path}")


def _check_output(path: Path, overwrite: bool = True) -> None:
    """Refuse an unwritable output before a long replay starts."""
    if path.is_dir():
        raise McsmError(f"output {path} is a directory")
    if path.exists() and not overwrite:
        raise McsmError(f"output {path} exists (--force overwrites it)")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise McsmError(f"output folder {parent} does not exist")
    if not os.access(parent, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise McsmError(f"output {path} is not writable")


def _plot(args: argparse.Namespace) -> int:
    from mcsm.recset import resolve
    from mcsm.viz import require
    from mcsm.viz.scene import load_map, map_view, read_truth

    files = resolve(args.file)
    for f in files:
        _check_input(f)
    _check_output(args.output)
    require("matplotlib")  # before the replay: a missing extra is said at once
    truth = read_truth(args.truth) if args.truth is not None else None
    from mcsm.viz.plot import plot_map

    loaded = load_map(files, args.map, args.at)
    mv = map_view(loaded.map, map_name=loaded.name, seq=loaded.seq, samples=args.samples)
    mv.notes = loaded.notes
    for note in loaded.notes:
        print(f"mcsm plot: warning: {note}", file=sys.stderr)
    res = plot_map(mv, args.output, view=args.view, samples=args.samples, truth=truth)
    if res.truth_missing:
        n = len(res.truth_missing)
        print(f"mcsm plot: {n} ground-truth frame{' is' if n == 1 else 's are'} not in the map "
              f"(e.g. {res.truth_missing[0]})", file=sys.stderr)
    n_comp = len(mv.components)
    print(f"{args.output}: map {loaded.name!r} at seq {loaded.seq} of {loaded.last_seq}, "
          f"{len(mv.frames)} frames, {n_comp} component{'' if n_comp == 1 else 's'}, "
          f"view {res.view}")
    return 0


def _export(args: argparse.Namespace) -> int:
    from mcsm.viz.foxglove_scene import export_foxglove, load_foxglove

    if args.every is not None and args.every < 1:
        raise McsmError("--every must be at least 1")
    if args.samples_per_frame < 0:
        raise McsmError("--samples-per-frame must be at least 0")
    _check_input(args.file)
    _check_output(args.output, overwrite=args.force)
    load_foxglove()
    rep = export_foxglove(args.file, args.output, every=args.every, map_name=args.map,
                          samples_per_frame=args.samples_per_frame, overwrite=args.force)
    for note in rep.notes:
        print(f"mcsm export-foxglove: warning: {note}", file=sys.stderr)
    n = len(rep.snapshots)
    print(f"{args.output}: map {rep.map!r}, {n} snapshot{'' if n == 1 else 's'} (every "
          f"{rep.every} operation{'' if rep.every == 1 else 's'}) up to seq {rep.final_seq}; "
          f"open it in the Foxglove app (3D panel, display frame "
          f"mcsm@{rep.map})")
    return 0


def _view(args: argparse.Namespace) -> int:
    from mcsm.viz.foxglove_scene import load_foxglove
    from mcsm.viz.live import ViewOptions, run_view

    if not 0 <= args.foxglove_port <= 65535:
        raise McsmError(f"--foxglove-port must be in 0..65535, got {args.foxglove_port}")
    if args.samples_per_frame < 0:
        raise McsmError("--samples-per-frame must be at least 0")
    if not args.timeout > 0:
        raise McsmError("--timeout must be positive")
    logging.basicConfig(level=getattr(logging, str(args.log_level).upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        stream=sys.stderr)
    load_foxglove()
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
