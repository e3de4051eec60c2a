"""ROS conventions for mcsm's maps, in numpy alone: poses, covariances, frames, markers.

Nothing here imports ROS; the ROS 2 node (``mcsm_client.ros2``) and ``mcsm export-rosbag``
(:mod:`mcsm.viz.rosbag`) turn what it computes into messages of their own message libraries
(rclpy's, rosbags').

**Poses.** A ``geometry_msgs/Pose`` is a position ``(x, y, z)`` and a unit quaternion
``(x, y, z, w)`` (REP 103: metres, right-handed). It is the pose of the *child* in the *header*
frame, the same relation as mcsm's AT ``header -> child``: mcsm's 7-vector is
``x y z qw qx qy qz`` (scalar first).

**Covariances.** ``PoseWithCovariance.covariance`` is a row-major 6x6 matrix over
``(x, y, z, rotation about X, rotation about Y, rotation about Z)``; the ROS message
definition says the rotations are about *fixed* axes, and the pose is in the header frame, so
a ROS perturbation moves a pose ``(t̄, R̄)`` to ``(t̄ + δt, exp([δr]×) R̄)``: translation and
rotation both in the header (parent) frame. mcsm's tangent chart (``mcsm.core.at.mean_and_cov``,
``MapClient.marginal``, ``sample_pose(translation_frame="parent")``) is
``(t̄ + δt, R̄ exp([δb]×))``: translation in the parent frame, rotation in the body frame.
Because ``exp([δr]×) R̄ = R̄ exp([R̄ᵀδr]×)`` exactly, ``δb = R̄ᵀ δr``: with
``J = diag(I₃, R̄ᵀ)``, ``Σ_mcsm = J Σ_ros Jᵀ`` and ``Σ_ros = Jᵀ Σ_mcsm J``. A yaw-only
covariance of a yaw-only pose is the same in both charts.

**Markers.** The 95 % regions drawn are the translation covariance's, with the definitions of
:func:`mcsm.viz.scene.ellipse` (a flat disc for a planar map) and
:func:`mcsm.viz.scene.ellipsoid` (3-D), the ones ``mcsm plot`` draws.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from mcsm.core.names import FRAME_RULE, is_frame_name, namespace_of
from mcsm.core.quat import rotation_matrix
from mcsm.viz.scene import P_REGION, ellipse, ellipsoid

Array = npt.NDArray[np.float64]

__all__ = ["MarkerSpec", "PlacedFrame", "frame_from_ros", "is_planar_frames", "map_markers",
           "paths_by_robot", "place_frames", "pose_from_ros", "pose_to_ros",
           "ros_cov_to_tangent", "tangent_cov_to_ros", "yaw_quat_xyzw"]


# --------------------------------------------------------------------------- poses, covariances

def pose_from_ros(position: Sequence[float], orientation_xyzw: Sequence[float]) -> Array:
    """mcsm's 7-vector ``x y z qw qx qy qz`` of a ROS pose (quaternion normalised).

    Raises
    ------
    ValueError
        A non-finite value or a quaternion of norm below 1e-9.
    """
    p = np.asarray(position, dtype=np.float64).reshape(3)
    x, y, z, w = (float(v) for v in np.asarray(orientation_xyzw, dtype=np.float64).reshape(4))
    q = np.array([w, x, y, z])
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
        raise ValueError("the pose is not finite")
    n = float(np.linalg.norm(q))
    if n < 1e-9:
        raise ValueError("the pose's quaternion is zero")
    return np.concatenate((p, q / n))


def pose_to_ros(mean: npt.ArrayLike) -> tuple[tuple[float, float, float],
                                             tuple[float, float, float, float]]:
    """Position ``(x, y, z)`` and quaternion ``(x, y, z, w)`` of mcsm's 7-vector."""
    m = np.asarray(mean, dtype=np.float64).reshape(7)
    return ((float(m[0]), float(m[1]), float(m[2])),
            (float(m[4]), float(m[5]), float(m[6]), float(m[3])))


def _jacobian(mean: npt.ArrayLike) -> Array:
    """``J = diag(I₃, R̄ᵀ)``: ROS's ``(δt, δr)`` to mcsm's ``(δt, δb)``."""
    m = np.asarray(mean, dtype=np.float64).reshape(7)
    q = m[3:] / np.linalg.norm(m[3:])
    j = np.eye(6)
    j[3:, 3:] = rotation_matrix(q).T
    return j


def _cov6(cov: npt.ArrayLike) -> Array:
    c = np.asarray(cov, dtype=np.float64)
    if c.size != 36:
        raise ValueError(f"expected 36 covariance entries, got {c.size}")
    c = c.reshape(6, 6)
    if not np.all(np.isfinite(c)):
        raise ValueError("the covariance is not finite")
    return c


def ros_cov_to_tangent(mean: npt.ArrayLike, cov: npt.ArrayLike) -> Array:
    """A ROS pose covariance (36 row-major entries or 6x6) in mcsm's tangent chart.

    ``J Σ Jᵀ`` with ``J = diag(I₃, R̄ᵀ)``, ``R̄`` the rotation of ``mean`` (mcsm 7-vector):
    the rotation block moves from the header frame's fixed axes to the body frame.
    """
    j = _jacobian(mean)
    out: Array = j @ _cov6(cov) @ j.T
    return 0.5 * (out + out.T)


def tangent_cov_to_ros(mean: npt.ArrayLike, cov: npt.ArrayLike) -> Array:
    """mcsm's tangent covariance (6x6) as ROS's (6x6; ``.ravel()`` is the message's field)."""
    j = _jacobian(mean)
    out: Array = j.T @ _cov6(cov) @ j
    return 0.5 * (out + out.T)


def yaw_quat_xyzw(yaw: float) -> tuple[float, float, float, float]:
    """Quaternion ``(x, y, z, w)`` of a rotation by ``yaw`` about z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def frame_from_ros(frame_id: str, prefix: str = "") -> str:
    """mcsm's name of a ROS frame id: leading ``/`` dropped (tf2 style), ``prefix/`` added.

    Raises
    ------
    ValueError
        The result is not a frame name (``mcsm.core.names.FRAME_RULE``).
    """
    name = str(frame_id).lstrip("/")
    if prefix:
        name = f"{prefix.strip('/')}/{name}"
    if not is_frame_name(name):
        raise ValueError(f"ROS frame id {frame_id!r} does not give {FRAME_RULE}")
    return name


# --------------------------------------------------------------------------- the map's frames

@dataclass(frozen=True)
class PlacedFrame:
    """One frame of a map as ROS shows it: its marginal in the frame ``parent``.

    ``parent`` is the ROS frame the pose is published in: the configured map frame for the
    frames of the origin's component (the origin itself sits at the identity there), the
    component's root otherwise. ``order`` is the frame's position in the map's frame list
    (the order in which frames were added).
    """

    name: str
    parent: str
    is_point: bool
    mean: Array  # (7,) x y z qw qx qy qz
    cov: Array  # (6, 6) mcsm tangent chart
    order: int
    is_origin: bool = False  # the origin itself (identity under the map frame)

    @property
    def robot(self) -> str:
        """The frame's namespace (``robot1`` of ``robot1/x3``), ``""`` without one."""
        return namespace_of(self.name)


def place_frames(smap: Any, *, origin: str | None = None,
                 map_frame: str = "map") -> list[PlacedFrame]:
    """Every frame of ``smap`` (a ``StochasticMap``) with its marginal, in map order.

    The frames of ``origin``'s component are expressed in ``origin`` and published under
    ``map_frame`` (``origin`` itself included, at the identity); every other component's
    frames in its root (the root itself left out: it is the frame they hang from).
    """
    roots = list(smap.components())
    ref_of: dict[str, str] = {}
    for r in roots:
        members = list(smap.component(r))
        ref = origin if origin is not None and origin in members else r
        for f in members:
            ref_of[f] = ref
    out = []
    for order, name in enumerate(smap.frames()):
        ref = ref_of[name]
        anchored = origin is not None and ref == origin
        if name == ref and not anchored:
            continue
        if name == ref:
            mean = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
            cov = np.zeros((6, 6))
        else:
            m, c = smap.marginal(ref, name)
            mean, cov = np.asarray(m, dtype=np.float64), np.asarray(c, dtype=np.float64)
        out.append(PlacedFrame(name, map_frame if anchored else ref, bool(smap.is_point(name)),
                               mean, cov, order, is_origin=name == ref))
    return out


def paths_by_robot(frames: Iterable[PlacedFrame]) -> dict[str, list[PlacedFrame]]:
    """The pose (non-point) frames of each robot (namespace) in the order they were added;
    only those in the parent frame of the robot's latest pose (one path per robot)."""
    by: dict[str, list[PlacedFrame]] = {}
    for f in sorted((f for f in frames if not f.is_point), key=lambda f: f.order):
        by.setdefault(f.robot, []).append(f)
    return {r: [f for f in fs if f.parent == fs[-1].parent] for r, fs in by.items()}


def is_planar_frames(frames: Sequence[PlacedFrame], rel_tol: float = 1e-9) -> bool:
    """True when every frame lies in its parent's x-y plane, turned about z only, with no
    spread out of the plane (the rule of :func:`mcsm.viz.scene.is_planar`)."""
    if not frames:
        return True
    scale = max(1.0, max(float(np.max(np.abs(f.mean[:2]))) for f in frames))
    tol = rel_tol * scale
    for f in frames:
        if abs(f.mean[2]) > tol or abs(f.mean[4]) > 1e-9 or abs(f.mean[5]) > 1e-9:
            return False
        if f.cov[2, 2] > tol * tol or f.cov[3, 3] > 1e-18 or f.cov[4, 4] > 1e-18:
            return False
    return True


# --------------------------------------------------------------------------- markers

MarkerKind = Literal["sphere", "cylinder", "text", "deleteall"]

#: ``visualization_msgs/Marker`` type constants (and DELETEALL's action)
MARKER_TYPE = {"sphere": 2, "cylinder": 3, "text": 9, "deleteall": 2}
MARKER_ACTION_ADD, MARKER_ACTION_DELETEALL = 0, 3

#: RGBA of landmarks' and poses' regions, and of labels
LANDMARK_RGBA = (1.0, 0.55, 0.0, 0.45)
POSE_RGBA = (0.15, 0.45, 1.0, 0.45)
LABEL_RGBA = (1.0, 1.0, 1.0, 0.9)
#: a planar map's discs are this thin (m)
DISC_THICKNESS_M = 0.01


@dataclass(frozen=True)
class MarkerSpec:
    """One ``visualization_msgs/Marker``, independent of any ROS message library."""

    kind: MarkerKind
    ns: str
    id: int
    frame_id: str
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    rgba: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    text: str = ""

    @property
    def type(self) -> int:
        return MARKER_TYPE[self.kind]

    @property
    def action(self) -> int:
        return MARKER_ACTION_DELETEALL if self.kind == "deleteall" else MARKER_ACTION_ADD


def marker_id(name: str) -> int:
    """A stable id of a frame's markers (CRC-32 of its name, as a non-negative int32), so a
    frame keeps its marker from one publication to the next."""
    return zlib.crc32(name.encode()) & 0x3FFFFFFF


def map_markers(frames: Sequence[PlacedFrame], *, label_height_m: float | None = None,
                p: float = P_REGION) -> list[MarkerSpec]:
    """A DELETEALL, then per frame its ``p`` region and a label with its name.

    Regions: planar maps (:func:`is_planar_frames`) get flat cylinders with the axes of
    :func:`mcsm.viz.scene.ellipse`; others spheres scaled and turned as
    :func:`mcsm.viz.scene.ellipsoid`. Namespaces ``mcsm/landmarks``, ``mcsm/poses``,
    ``mcsm/labels``. Labels are ``label_height_m`` tall (default: 2 % of the map's extent,
    at least 0.05 m) and sit just above their frame.
    """
    out = [MarkerSpec("deleteall", "mcsm", 0, frames[0].parent if frames else "map")]
    if not frames:
        return out
    planar = is_planar_frames(frames)
    pos = np.array([f.mean[:3] for f in frames])
    extent = float(np.max(np.ptp(pos, axis=0))) if len(frames) > 1 else 1.0
    h = label_height_m if label_height_m is not None else max(0.05, 0.02 * extent)
    for f in frames:
        mid = marker_id(f.name)
        ns = "mcsm/landmarks" if f.is_point else "mcsm/poses"
        rgba = LANDMARK_RGBA if f.is_point else POSE_RGBA
        t = f.mean[:3]
        if planar:
            e = ellipse(t[:2], f.cov[:2, :2], p)
            out.append(MarkerSpec("cylinder", ns, mid, f.parent, (e.center[0], e.center[1], 0.0),
                                  yaw_quat_xyzw(math.radians(e.angle_deg)),
                                  (max(e.width, 1e-6), max(e.height, 1e-6), DISC_THICKNESS_M),
                                  rgba))
        else:
            s = ellipsoid(t, f.cov[:3, :3], p)
            out.append(MarkerSpec("sphere", ns, mid, f.parent, s.center, s.quat_xyzw,
                                  (max(s.sizes[0], 1e-6), max(s.sizes[1], 1e-6),
                                   max(s.sizes[2], 1e-6)), rgba))
        out.append(MarkerSpec("text", "mcsm/labels", mid, f.parent,
                              (float(t[0]), float(t[1]), float(t[2]) + 0.75 * h),
                              scale=(h, h, h), rgba=LABEL_RGBA, text=f.name))
    return out
