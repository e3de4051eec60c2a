"""``mcsm export-rosbag``: a recorded map as a ROS 2 bag (MCAP storage) that ROS tools read.

Replays a recording (``mcsm.viz.scene.load_map``) and writes, with ``rosbags`` (the ``ros``
extra; no ROS installation needed), one stamp of these topics
(stamped with the receive time of the map's last input up to the exported seq):

* ``/tf`` (``tf2_msgs/TFMessage``): every frame's mean under ``--map-frame`` (the frames of the
  origin's component; the origin at the identity) or under its component's root;
* ``/mcsm/frames`` (``nav_msgs/Odometry``, one per frame): each frame's pose with its ROS
  covariance in that parent (the same message ``mcsm ros2`` reads on a constraint topic, so the
  bag plays back into a map with ``mcsm-client play-rosbag --constraint-topic /mcsm/frames``);
* ``/mcsm/path`` and ``/mcsm/path/<robot>`` (``nav_msgs/Path``): each robot's poses in order;
* ``/mcsm/markers`` (``visualization_msgs/MarkerArray``): 95 % regions and labels
  (:func:`mcsm.viz.ros.map_markers`).

Exit codes: 0 written; 2 a user's mistake (missing recording, unknown map, output exists
without ``--force``, rosbags not installed).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcsm.core.names import is_frame_name
from mcsm.errors import McsmError
from mcsm.viz import ros, rosmsg

__all__ = ["ExportRosbagReport", "add_parser", "export_rosbag", "path_topic", "run"]

TOPIC_TF = "/tf"
TOPIC_FRAMES = "/mcsm/frames"
TOPIC_MARKERS = "/mcsm/markers"


def path_topic(robot: str) -> str:
    """``/mcsm/path`` for frames without a namespace, ``/mcsm/path/<robot>`` otherwise."""
    return "/mcsm/path" + (f"/{robot}" if robot else "")


@dataclass
class ExportRosbagReport:
    out: Path
    map: str
    seq: int
    stamp_ns: int
    topics: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def _load_rosbags() -> tuple[Any, Any, Any]:
    try:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise McsmError("export-rosbag needs rosbags: pip install 'mcsm[ros]'") from None
    return Writer, StoragePlugin, get_typestore(Stores.ROS2_KILTED)


def _input_time_ns(path: Path, map_name: str, seq: int) -> int:
    """When the map's last input up to ``seq`` was received (its ``recv_ns``; 0 if none)."""
    from mcsm.log.reader import RecordingReader
    from mcsm.log.topics import TOPIC_OPS

    t = 0
    for item in RecordingReader(path, edges=False):
        d = item.data
        if (item.topic in TOPIC_OPS and d.get("map") == map_name
                and int(d.get("seq", 0)) <= seq):
            t = int(d.get("recv_ns") or item.log_time_ns)
    return t


def export_rosbag(recording: str | Path, out: str | Path, *, map_name: str | None = None,
                  at_seq: int | None = None, origin: str | None = None,
                  map_frame: str = "map") -> ExportRosbagReport:
    """Write one map of ``recording`` (at its end, or at ``at_seq``) as a ROS 2 MCAP bag.

    ``out`` is the bag's folder (rosbag2's layout: ``metadata.yaml`` and one ``.mcap``); it
    must not exist. ``origin`` (default: the map's first frame) is published as ``map_frame``.

    Raises
    ------
    McsmError
        Unreadable recording, unknown map or seq, unknown origin, no rosbags.
    """
    from mcsm.viz.scene import load_map

    _load_rosbags()  # before the replay: a missing extra is said at once
    loaded = load_map(recording, map_name, at_seq)
    smap = loaded.map
    frames_all = list(smap.frames())
    if origin is None:
        origin = frames_all[0] if frames_all else None
    elif origin not in frames_all:
        raise McsmError(f"--origin {origin!r} is not a frame of map {loaded.name!r}")
    if not is_frame_name(map_frame):
        raise McsmError(f"--map-frame {map_frame!r} is not a frame name")
    placed = ros.place_frames(smap, origin=origin, map_frame=map_frame)
    t_ns = _input_time_ns(Path(recording), loaded.name, loaded.seq)
    rep = ExportRosbagReport(Path(out), loaded.name, loaded.seq, t_ns, notes=list(loaded.notes))
    rep.topics = write_map_bag(placed, t_ns, out)
    return rep


def write_map_bag(placed: list[ros.PlacedFrame], t_ns: int, out: str | Path) -> dict[str, int]:
    """Write placed frames (:func:`mcsm.viz.ros.place_frames`) as a ROS 2 MCAP bag folder
    ``out`` (must not exist), all stamped ``t_ns``; messages per topic."""
    writer_cls, storage, store = _load_rosbags()
    make = rosmsg.rosbags_maker(store)
    messages: list[tuple[str, str, Any]] = [
        (TOPIC_TF, "tf2_msgs/msg/TFMessage", rosmsg.tf_message(make, t_ns, placed))]
    messages += [(TOPIC_FRAMES, "nav_msgs/msg/Odometry", rosmsg.frame_odometry(make, t_ns, f))
                 for f in placed if not f.is_origin]
    for robot, fs in sorted(ros.paths_by_robot(placed).items()):
        messages.append((path_topic(robot), "nav_msgs/msg/Path", rosmsg.path(make, t_ns, fs)))
    messages.append((TOPIC_MARKERS, "visualization_msgs/msg/MarkerArray",
                     rosmsg.marker_array(make, t_ns, ros.map_markers(placed))))
    topics: dict[str, int] = {}
    try:
        with writer_cls(Path(out), version=9, storage_plugin=storage.MCAP) as writer:
            conns: dict[str, Any] = {}
            for topic, msgtype, msg in messages:
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
                writer.write(conns[topic], t_ns, store.serialize_cdr(msg, msgtype))
                topics[topic] = topics.get(topic, 0) + 1
    except Exception:
        shutil.rmtree(out, ignore_errors=True)  # no half-written bag
        raise
    return topics


# --------------------------------------------------------------------------- the subcommand

def add_parser(sub: Any) -> None:
    """Add ``export-rosbag`` to ``mcsm``'s subparsers."""
    e = sub.add_parser("export-rosbag",
                       help="write a recorded map as a ROS 2 bag (MCAP): TF, poses with "
                            "covariance, paths, markers (ros extra)",
                       description="Replay a recording and write one map, at its end (or "
                                   "--at SEQ), as a ROS 2 bag with MCAP storage: /tf, "
                                   "/mcsm/frames (nav_msgs/Odometry: pose and covariance of "
                                   "every frame), /mcsm/path[/ROBOT] (nav_msgs/Path), "
                                   "/mcsm/markers (95 % regions and labels). docs/ros2.md.")
    e.add_argument("file", type=Path, help="recording (.mcap) written by mcsm serve")
    e.add_argument("-o", "--output", type=Path, required=True, metavar="BAG",
                   help="the bag's folder (rosbag2 layout; refused if it exists)")
    e.add_argument("--map", default=None, metavar="NAME",
                   help="which map (default: 'default' or the recording's only map)")
    e.add_argument("--at", type=int, default=None, metavar="SEQ",
                   help="the map as it was after its operation SEQ (default: the end)")
    e.add_argument("--origin", default=None, metavar="FRAME",
                   help="the frame published as the map frame (default: the map's first)")
    e.add_argument("--map-frame", default="map", metavar="NAME",
                   help="the ROS frame of the origin (default map)")
    e.add_argument("--force", action="store_true", help="replace an existing output folder")


def run(args: argparse.Namespace) -> int:
    """``mcsm export-rosbag``; a user's mistake is one line on stderr and exit 2."""
    try:
        if not args.file.is_file():
            raise McsmError(f"no such recording: {args.file}")
        if args.output.exists() and not args.force:
            raise McsmError(f"output {args.output} exists (--force replaces it)")
        parent = args.output.parent if str(args.output.parent) else Path(".")
        if not parent.is_dir():
            raise McsmError(f"output folder {parent} does not exist")
        # written in a folder beside it first (the bag's own name inside, which its file
        # names follow): a failed export leaves an existing bag as it was
        work = parent / f".export-rosbag-{os.getpid()}"
        work.mkdir()
        try:
            rep = export_rosbag(args.file, work / args.output.name, map_name=args.map,
                                at_seq=args.at, origin=args.origin, map_frame=args.map_frame)
            if args.output.exists():
                shutil.rmtree(args.output) if args.output.is_dir() else args.output.unlink()
            (work / args.output.name).rename(args.output)
            rep.out = args.output
        finally:
            shutil.rmtree(work, ignore_errors=True)
    except (McsmError, OSError) as exc:
        print(f"mcsm export-rosbag: {exc}", file=sys.stderr)
        return 2
    for note in rep.notes:
        print(f"mcsm export-rosbag: warning: {note}", file=sys.stderr)
    topics = ", ".join(f"{t} {n}" for t, n in rep.topics.items())
    print(f"{rep.out}: map {rep.map!r} at seq {rep.seq}; {topics}")
    return 0
