"""The ``mcsm plot`` and ``mcsm export-foxglove`` subcommands (``mcsm view``, a client of a live
server, comes from the client package: :mod:`mcsm_client.view_command`).

Exit codes: 0 done; 2 a user's mistake or an unusable input, said in one line on stderr (missing
or unreadable recording, unknown map, a sequence number the map never reached, bad ground-truth
file, output path not writable, the ``viz`` extra not installed).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from mcsm.errors import McsmError

COMMANDS = ("plot", "export-foxglove")


def add_parsers(sub: Any) -> None:
    """Add the subcommands to ``mcsm``'s subparsers."""
    p = sub.add_parser("plot", help="draw a recorded map (replayed) into a PNG with matplotlib",
                       description="Replay a recording and draw one map: landmarks with 95 % "
                                   "covariance ellipses, pose frames and their path, one "
                                   "colour per component.")
    p.add_argument("file", type=Path, help="recording (.mcap) written by mcsm serve")
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


def run(args: argparse.Namespace) -> int:
    """Run one of :data:`COMMANDS`; a user's mistake becomes one line on stderr and exit 2."""
    name = args.command
    try:
        if name == "plot":
            return _plot(args)
        return _export(args)
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
    from mcsm.viz import require
    from mcsm.viz.scene import load_map, map_view, read_truth

    _check_input(args.file)
    _check_output(args.output)
    require("matplotlib")  # before the replay: a missing extra is said at once
    truth = read_truth(args.truth) if args.truth is not None else None
    from mcsm.viz.plot import plot_map

    loaded = load_map(args.file, args.map, args.at)
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
