"""The ``mcsm plot`` and ``mcsm export FORMAT`` subcommands (``foxglove``, ``g2o``, ``tum``;
``mcsm export-foxglove`` is ``export foxglove``). ``mcsm view``, a client of a live server,
comes from the client package: :mod:`mcsm_client.view_command`.

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

COMMANDS = ("plot", "export", "export-foxglove")


def add_parsers(sub: Any) -> None:
    """Add the subcommands to ``mcsm``'s subparsers."""
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

    p.add_argument("--force", action="store_true", help="overwrite an existing output file")

    x = sub.add_parser("export", help="write a recorded map for other tools: foxglove (a "
                       "scene over time), g2o (a pose graph), tum (trajectories)",
                       description="Replay a recording and write one map in another tool's "
                                   "format (docs/exchange.md, docs/visualising.md). Every "
                                   "writer refuses an existing output unless --force.")
    fmt = x.add_subparsers(dest="format", required=True, metavar="FORMAT")
    _foxglove_args(fmt.add_parser(
        "foxglove", help="a Foxglove/Lichtblick scene over time (MCAP, protobuf schemas)",
        description="Replay a recording and write one map's scene (regions, paths, "
                    "transforms, sample clouds, verdict log, counters) with foxglove-sdk's "
                    "schemas; open the file in Foxglove or Lichtblick."))
    g = fmt.add_parser("g2o", help="a g2o pose graph: vertices at the means, every held "
                       "constraint an edge with its information matrix",
                       description="Replay a recording and write one map as a g2o file that "
                                   "g2o and GTSAM's readG2o read (EDGE_SE2 / EDGE_SE3:QUAT, "
                                   "point landmarks as EDGE_SE2_XY / EDGE_SE3_TRACKXYZ).")
    _common(g, "map.g2o", "G2O")
    g.add_argument("--landmarks", choices=("g2o", "br"), default="g2o",
                   help="planar landmark edges as g2o's EDGE_SE2_XY (default) or GTSAM's BR "
                        "bearing-range lines (GTSAM's readG2o skips EDGE_SE2_XY)")
    t = fmt.add_parser("tum", help="TUM trajectories, one file per robot (evo reads them)",
                       description="Replay a recording and write each robot path of one map "
                                   "as a TUM file (t x y z qx qy qz qw): PREFIX-ROBOT.tum.")
    _common(t, "map", "PREFIX")

    e = sub.add_parser("export-foxglove", help="the same as `mcsm export foxglove`",
                       description="Replay a recording and write one map's scene for "
                                   "Foxglove or Lichtblick (the same as `mcsm export "
                                   "foxglove`).")
    _foxglove_args(e)


def _common(p: Any, default: str, metavar: str) -> None:
    p.add_argument("file", type=Path, help="recording (.mcap) written by mcsm serve")
    p.add_argument("-o", "--output", type=Path, default=Path(default), metavar=metavar,
                   help=f"output (default {default})")
    p.add_argument("--map", default=None, metavar="NAME",
                   help="which map (default: 'default' or the recording's only map)")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")


def _foxglove_args(e: Any) -> None:
    _common(e, "scene.mcap", "MCAP")
    e.add_argument("--every", type=int, default=None, metavar="K",
                   help="a snapshot after every K-th operation of the map, and the last one "
                        "(default: K giving at most 100 snapshots)")
    e.add_argument("--samples-per-frame", type=int, default=100, metavar="M",
                   help="sample points per frame in the point cloud (default 100; 0: none)")


def run(args: argparse.Namespace) -> int:
    """Run one of :data:`COMMANDS`; a user's mistake becomes one line on stderr and exit 2."""
    name = args.command
    if name == "export":
        name = f"export {args.format}"
    try:
        if args.command == "plot":
            return _plot(args)
        if args.command == "export" and args.format == "g2o":
            return _g2o(args)
        if args.command == "export" and args.format == "tum":
            return _tum(args)
        return _export(args)
    except (McsmError, OSError) as exc:
        print(f"mcsm {name}: {exc}", file=sys.stderr)
        return 2


def _check_input(path: Path) -> None:
    from mcsm.filetype import not_a_recording

    if not path.is_file():
        raise McsmError(f"no such recording: {path}")
    why = not_a_recording(path)
    if why:
        raise McsmError(f"{path}: {why}")


def _check_output(path: Path, overwrite: bool = False) -> None:
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
    _check_output(args.output, overwrite=args.force)
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
          f"{len(mv.frames)} frame{'' if len(mv.frames) == 1 else 's'}, "
          f"{n_comp} component{'' if n_comp == 1 else 's'}, "
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
        print(f"mcsm {_name(args)}: warning: {note}", file=sys.stderr)
    n = len(rep.snapshots)
    print(f"{args.output}: map {rep.map!r}, {n} snapshot{'' if n == 1 else 's'} (every "
          f"{rep.every} operation{'' if rep.every == 1 else 's'}) up to seq {rep.final_seq}; "
          f"open it in the Foxglove app (3D panel, display frame "
          f"mcsm@{rep.map})")
    return 0


def _name(args: argparse.Namespace) -> str:
    return f"export {args.format}" if args.command == "export" else str(args.command)


def _g2o(args: argparse.Namespace) -> int:
    from mcsm.exchange import collect, frames_file, write_g2o

    _check_input(args.file)
    _check_output(args.output, overwrite=args.force)
    _check_output(frames_file(args.output), overwrite=args.force)
    data = collect(args.file, args.map)
    rep = write_g2o(data, args.output, landmarks=args.landmarks)
    for note in [*data.notes, *rep.notes]:
        print(f"mcsm export g2o: note: {note}", file=sys.stderr)
    print(f"{args.output}: map {data.view.map!r} at seq {data.view.seq}, "
          f"{'planar (SE2)' if rep.planar else '3-D (SE3)'}: {rep.vertices} vertices "
          f"({rep.landmarks} landmarks), {rep.edges} edges ({rep.landmark_edges} to "
          f"landmarks); vertex ids named in {frames_file(args.output)}")
    return 0


def _tum(args: argparse.Namespace) -> int:
    from mcsm.exchange import collect, tum_paths, write_tum

    _check_input(args.file)
    _check_output(Path(f"{args.output}-x.tum"), overwrite=True)  # the folder, before replay
    data = collect(args.file, args.map)
    for _robot, path, _poses in tum_paths(data, args.output):
        _check_output(path, overwrite=args.force)
    for note in data.notes:
        print(f"mcsm export tum: note: {note}", file=sys.stderr)
    trajs = write_tum(data, args.output)
    if not trajs:
        print(f"mcsm export tum: map {data.view.map!r} has no pose frames: nothing written",
              file=sys.stderr)
    for t in trajs:
        n = len(t.poses)
        span = f" ({t.poses[0]} .. {t.poses[-1]})" if t.poses else ""
        left = (f"; left out, sharing a time with the next pose: {', '.join(t.dropped)}"
                if t.dropped else "")
        print(f"{t.path}: robot {t.robot}, {n} pose{'' if n == 1 else 's'}{span}{left}")
    return 0
