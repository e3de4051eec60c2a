"""ROS 2 messages of a map, built through any message library (rclpy's or rosbags').

Every builder takes ``make(typename, **fields)``, a function that returns a message of the
ROS type ``typename`` (``"geometry_msgs/msg/Pose"``) with the given fields: for rclpy, the
message class called with the fields; for rosbags, :func:`rosbags_maker` (it fills the fields
not given with ROS's defaults, as rclpy's constructors do). So the ROS 2 node and
``mcsm export-rosbag`` write the same messages from one definition. Poses and covariances
follow :mod:`mcsm.viz.ros`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.viz.ros import MarkerSpec, PlacedFrame, pose_to_ros, tangent_cov_to_ros

Make = Callable[..., Any]

__all__ = ["Make", "frame_odometry", "header", "marker_array", "odometry", "path",
           "pose_with_covariance_stamped", "rosbags_maker", "tf_message", "time_msg"]


def time_msg(make: Make, t_ns: int) -> Any:
    """``builtin_interfaces/Time`` of a time in nanoseconds (>= 0)."""
    return make("builtin_interfaces/msg/Time", sec=int(t_ns // 1_000_000_000),
                nanosec=int(t_ns % 1_000_000_000))


def header(make: Make, t_ns: int, frame_id: str) -> Any:
    return make("std_msgs/msg/Header", stamp=time_msg(make, t_ns), frame_id=str(frame_id))


def _vec(make: Make, name: str, xyz: Sequence[float]) -> Any:
    return make(name, x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2]))


def pose(make: Make, mean: npt.ArrayLike) -> Any:
    """``geometry_msgs/Pose`` of mcsm's 7-vector."""
    p, q = pose_to_ros(mean)
    return make("geometry_msgs/msg/Pose", position=_vec(make, "geometry_msgs/msg/Point", p),
                orientation=make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1], z=q[2],
                                 w=q[3]))


def _cov36(cov: npt.ArrayLike) -> npt.NDArray[np.float64]:
    return np.ascontiguousarray(np.asarray(cov, dtype=np.float64).reshape(36))


def odometry(make: Make, t_ns: int, frame_id: str, child_frame_id: str, mean: npt.ArrayLike,
             ros_cov: npt.ArrayLike) -> Any:
    """``nav_msgs/Odometry``: the pose ``mean`` of the child in the header frame with its ROS
    covariance (36 row-major entries or 6x6); zero twist."""
    zero3 = (0.0, 0.0, 0.0)
    twist = make("geometry_msgs/msg/Twist", linear=_vec(make, "geometry_msgs/msg/Vector3", zero3),
                 angular=_vec(make, "geometry_msgs/msg/Vector3", zero3))
    return make("nav_msgs/msg/Odometry", header=header(make, t_ns, frame_id),
                child_frame_id=str(child_frame_id),
                pose=make("geometry_msgs/msg/PoseWithCovariance", pose=pose(make, mean),
                          covariance=_cov36(ros_cov)),
                twist=make("geometry_msgs/msg/TwistWithCovariance", twist=twist,
                           covariance=np.zeros(36)))


def frame_odometry(make: Make, t_ns: int, f: PlacedFrame) -> Any:
    """A map frame as ``nav_msgs/Odometry`` (its marginal, ROS covariance) in its parent."""
    return odometry(make, t_ns, f.parent, f.name, f.mean, tangent_cov_to_ros(f.mean, f.cov))


def pose_with_covariance_stamped(make: Make, t_ns: int, frame_id: str, mean: npt.ArrayLike,
                                 tangent_cov: npt.ArrayLike) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` of a marginal (mcsm tangent covariance)."""
    return make("geometry_msgs/msg/PoseWithCovarianceStamped",
                header=header(make, t_ns, frame_id),
                pose=make("geometry_msgs/msg/PoseWithCovariance", pose=pose(make, mean),
                          covariance=_cov36(tangent_cov_to_ros(mean, tangent_cov))))


def transform_stamped(make: Make, t_ns: int, parent: str, child: str,
                      mean: npt.ArrayLike) -> Any:
    p, q = pose_to_ros(mean)
    return make("geometry_msgs/msg/TransformStamped", header=header(make, t_ns, parent),
                child_frame_id=str(child),
                transform=make("geometry_msgs/msg/Transform",
                               translation=_vec(make, "geometry_msgs/msg/Vector3", p),
                               rotation=make("geometry_msgs/msg/Quaternion", x=q[0], y=q[1],
                                             z=q[2], w=q[3])))


def tf_message(make: Make, t_ns: int, frames: Iterable[PlacedFrame]) -> Any:
    """``tf2_msgs/TFMessage``: each frame's mean under its parent (the origin itself, at the
    identity, under the map frame)."""
    return make("tf2_msgs/msg/TFMessage",
                transforms=[transform_stamped(make, t_ns, f.parent, f.name, f.mean)
                            for f in frames])


def path(make: Make, t_ns: int, frames: Sequence[PlacedFrame]) -> Any:
    """``nav_msgs/Path`` through ``frames`` (one robot's poses, in order), in their parent."""
    frame_id = frames[0].parent if frames else "map"
    return make("nav_msgs/msg/Path", header=header(make, t_ns, frame_id),
                poses=[make("geometry_msgs/msg/PoseStamped", header=header(make, t_ns, frame_id),
                            pose=pose(make, f.mean)) for f in frames])


def marker(make: Make, t_ns: int, m: MarkerSpec) -> Any:
    return make("visualization_msgs/msg/Marker", header=header(make, t_ns, m.frame_id),
                ns=m.ns, id=int(m.id), type=int(m.type), action=int(m.action),
                pose=make("geometry_msgs/msg/Pose",
                          position=_vec(make, "geometry_msgs/msg/Point", m.position),
                          orientation=make("geometry_msgs/msg/Quaternion",
                                           x=float(m.orientation_xyzw[0]),
                                           y=float(m.orientation_xyzw[1]),
                                           z=float(m.orientation_xyzw[2]),
                                           w=float(m.orientation_xyzw[3]))),
                scale=_vec(make, "geometry_msgs/msg/Vector3", m.scale),
                color=make("std_msgs/msg/ColorRGBA", r=float(m.rgba[0]), g=float(m.rgba[1]),
                           b=float(m.rgba[2]), a=float(m.rgba[3])),
                text=m.text)


def marker_array(make: Make, t_ns: int, specs: Iterable[MarkerSpec]) -> Any:
    return make("visualization_msgs/msg/MarkerArray",
                markers=[marker(make, t_ns, m) for m in specs])


# --------------------------------------------------------------------------- rosbags

_BASE_DEFAULTS: dict[str, Any] = {"string": "", "bool": False, "float32": 0.0, "float64": 0.0}


def rosbags_maker(typestore: Any) -> Make:
    """``make`` for rosbags' message classes of ``typestore``: missing fields get ROS's
    defaults (0, "", False, empty sequences, zero arrays, default nested messages)."""

    def default(node: Any) -> Any:
        kind, detail = node
        if kind == 1:  # BASE
            name = detail[0]
            return _BASE_DEFAULTS.get(name, 0)
        if kind == 2:  # NAME
            return make(detail)
        if kind == 3:  # ARRAY
            (sub, length) = detail
            if sub[0] == 1 and sub[1][0] not in ("string", "bool"):
                return np.zeros(length, dtype=_np_type(sub[1][0]))
            return [default(sub) for _ in range(length)]
        if kind == 4:  # SEQUENCE
            sub = detail[0]
            if sub[0] == 1 and sub[1][0] not in ("string", "bool"):
                return np.zeros(0, dtype=_np_type(sub[1][0]))
            return []
        raise ValueError(f"unknown rosbags node type {kind}")

    def make(name: str, **fields: Any) -> Any:
        cls = typestore.types[name]
        _, defs = typestore.fielddefs[name]
        kw = {fname: fields[fname] if fname in fields else default(node)
              for fname, node in defs}
        return cls(**kw)

    return make


def _np_type(ros: str) -> str:
    return {"float64": "<f8", "float32": "<f4", "uint8": "u1", "byte": "u1", "char": "u1",
            "int8": "i1", "int16": "<i2", "uint16": "<u2", "int32": "<i4", "uint32": "<u4",
            "int64": "<i8", "uint64": "<u8"}[ros]
