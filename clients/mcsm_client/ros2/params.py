"""The parameters of the ``mcsm ros2`` node, with their defaults and descriptions (imported by
``mcsm --help`` too, so this module imports nothing)."""

from __future__ import annotations

from typing import Any

#: every parameter: name -> (default, description)
PARAMETERS: dict[str, tuple[Any, str]] = {
    "odometry_topics": (["/odom"], "nav_msgs/Odometry topics of robots' cumulative odometry "
                        "(keyframes)"),
    "constraint_topics": (["/mcsm/constraints"], "nav_msgs/Odometry topics of relative poses "
                          "header.frame_id -> child_frame_id"),
    "landmark_topics": (["/mcsm/landmarks"], "nav_msgs/Odometry topics of point landmarks "
                        "child_frame_id seen from header.frame_id"),
    "frame_prefix": ("", "prepended to every ROS frame id ('robot1' -> 'robot1/base_link')"),
    "keyframe_distance_m": (0.5, "a new odometry keyframe after this much travel (m)"),
    "keyframe_angle_rad": (0.5, "... or this much turn (rad)"),
    "reorder_window_s": (0.2, "inputs wait this long to be applied in stamp order (s)"),
    "publish_period_s": (1.0, "TF, paths, markers, poses and diagnostics every this long (s)"),
    "map_frame": ("map", "the ROS frame of the map (TF parent of the origin's component)"),
    "origin_frame": ("", "the map's frame placed at map_frame's origin (default: the first "
                     "frame this node adds, else the map's first frame)"),
    "pose_pairs": ([""], "'A:B' entries: publish B in A as PoseWithCovarianceStamped on "
                   "/mcsm/pose/<B>"),
    "tf_skip": ([""], "map frames not to publish on /tf (frames another node publishes)"),
    "snapshot_dir": (".", "folder of the bags ~/snapshot writes"),
    "retract": ("", "set to a request id: retract that update (result in the reply)"),
    "reinstate": ("", "set to a request id: reinstate that update"),
}
