"""ROS 2 messages -> map constraints: the one mapping shared by ``mcsm ros2`` and ``play-rosbag``.

Every input is a ``nav_msgs/Odometry``: the only standard ROS message that names two frames
(``header.frame_id``, ``child_frame_id``) and carries a pose with its 6x6 covariance
(``geometry_msgs/PoseWithCovarianceStamped`` names one frame, ``PointStamped`` one and has no
covariance). The twist is ignored. What a message means depends on its topic
(:class:`MappingOptions`):

* **odometry topics** (default ``/odom``): a robot's cumulative odometry, the pose of
  ``child_frame_id`` (``base_link``) in ``header.frame_id`` (``odom``). Keyframes are made as
  slam_toolbox does: the first message, then each one that moved ``keyframe_distance_m`` or
  turned ``keyframe_angle_rad`` since the last keyframe, becomes frame ``<child>.<k>``. The
  first keyframe is the AT ``odom -> base_link.0`` with the message's pose and covariance;
  each later one the increment ``base_link.<k-1> -> base_link.<k>`` (mean ``T_{k-1}⁻¹ T_k``),
  whose covariance is the growth of the odometry's own covariance since the last keyframe,
  ``Σ_k − Σ_{k-1}`` (negative eigenvalues clipped to 0), turned into the last keyframe's axes.
* **constraint topics** (default ``/mcsm/constraints``): an AT ``header.frame_id ->
  child_frame_id`` as given (a relative pose between robots, an odometry increment between
  named keyframes, a loop closure: the map decides which from the frames it has).
* **landmark topics** (default ``/mcsm/landmarks``): the point ``child_frame_id`` seen from
  ``header.frame_id``: the pose's position and the covariance's translation block (metres,
  header frame); the orientation and rotation rows are ignored.

A frame named on a constraint or landmark topic that is an odometry child (``base_link``) means
that robot *now*: its latest odometry message becomes a keyframe first (if it is not one) and the
constraint attaches to it.

Pose covariances are ROS's (:mod:`mcsm.viz.ros`: translation and rotation about the header
frame's fixed axes) and become mcsm's tangent chart with ``J = diag(I₃, R̄ᵀ)`` before samples are
drawn (``sample_pose(translation_frame="parent")``). A negative variance (ROS's "unknown"),
a non-symmetric or non-PSD covariance, equal frames or a bad frame id make the message invalid
(:class:`MappingError`; counted, never sent).

**Determinism.** The samples of a constraint are drawn from a generator seeded with a SHA-256
of the message (kind, stamp, frame ids, pose and covariance), and its request id is derived from
the same hash (``ros-<kind>-<32 hex>``): the same bag gives the same samples (on one machine:
numpy's eigendecomposition is the client's), and a message sent twice is applied once.
Messages are applied in the order of :func:`order_key` (header stamp, then odometry before
constraints before landmarks, then topic, then arrival), by the node and the bag player alike.
"""

from __future__ import annotations

import hashlib
import struct
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from mcsm.core.at import relative
from mcsm.core.quat import qlog, rotation_matrix
from mcsm.viz.ros import frame_from_ros, pose_from_ros, ros_cov_to_tangent

from mcsm_client.sampling import sample_point, sample_pose

Array = npt.NDArray[np.float64]
Kind = Literal["odometry", "constraint", "landmark"]

#: order of kinds at one stamp: motion first, then what is seen from where the robot is
RANK: dict[str, int] = {"odometry": 0, "constraint": 1, "landmark": 2}
#: the message type every input topic carries
INPUT_TYPE = "nav_msgs/msg/Odometry"
#: bumped if the hash's content changes (ids and samples of old bags would change)
HASH_VERSION = b"mcsm-ros2-v1"

__all__ = ["Constraint", "MappingError", "MappingOptions", "MessageMapper", "RANK",
           "message_digest", "order_key", "stamp_ns"]


class MappingError(ValueError):
    """A message that cannot become a constraint (the reason is the message)."""


@dataclass(frozen=True)
class MappingOptions:
    """Which topics mean what, and the keyframe rule (the node's parameters of the same
    names; ``play-rosbag``'s flags)."""

    odometry_topics: tuple[str, ...] = ("/odom",)
    constraint_topics: tuple[str, ...] = ("/mcsm/constraints",)
    landmark_topics: tuple[str, ...] = ("/mcsm/landmarks",)
    frame_prefix: str = ""
    keyframe_distance_m: float = 0.5
    keyframe_angle_rad: float = 0.5

    def kind_of(self, topic: str) -> Kind | None:
        """The kind of a topic's messages, or None if it is not an input."""
        if topic in self.odometry_topics:
            return "odometry"
        if topic in self.constraint_topics:
            return "constraint"
        if topic in self.landmark_topics:
            return "landmark"
        return None

    @property
    def topics(self) -> tuple[str, ...]:
        return self.odometry_topics + self.constraint_topics + self.landmark_topics


@dataclass(frozen=True)
class Constraint:
    """One update to send: the AT ``a -> b`` (``(N, 7)``) or the point ``b`` seen from ``a``
    (``(N, 3)``), with its request id and the message's stamp."""

    kind: Kind
    topic: str
    a: str
    b: str
    samples: Array = field(repr=False)
    request_id: str
    stamp_ns: int

    @property
    def is_point(self) -> bool:
        return bool(self.samples.shape[1] == 3)


# --------------------------------------------------------------------------- reading messages

def stamp_ns(msg: Any) -> int:
    """``header.stamp`` in nanoseconds."""
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def order_key(topic: str, kind: str, msg: Any, arrival: int) -> tuple[int, int, str, int]:
    """The order messages are applied in: stamp, kind (:data:`RANK`), topic, arrival."""
    return (stamp_ns(msg), RANK[kind], topic, arrival)


def _pose(msg: Any) -> tuple[Array, Array]:
    """(mcsm 7-vector, ROS 6x6 covariance) of an Odometry's pose."""
    p = msg.pose.pose.position
    o = msg.pose.pose.orientation
    try:
        mean = pose_from_ros((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))
    except ValueError as exc:
        raise MappingError(str(exc)) from None
    cov = np.asarray(msg.pose.covariance, dtype=np.float64)
    if cov.size != 36 or not np.all(np.isfinite(cov)):
        raise MappingError("the covariance is not 36 finite numbers")
    cov = cov.reshape(6, 6)
    if np.any(np.diag(cov) < 0):
        raise MappingError("a negative variance (ROS's 'unknown covariance')")
    if not np.allclose(cov, cov.T, rtol=1e-9, atol=1e-15):
        raise MappingError("the covariance is not symmetric")
    return mean, cov


def message_digest(kind: str, msg: Any) -> bytes:
    """SHA-256 of what a message says: kind, stamp, frame ids, pose and covariance."""
    p = msg.pose.pose.position
    o = msg.pose.pose.orientation
    h = hashlib.sha256(HASH_VERSION)
    for text in (kind, str(msg.header.frame_id), str(msg.child_frame_id)):
        b = text.encode()
        h.update(struct.pack("<I", len(b)) + b)
    h.update(struct.pack("<qI", int(msg.header.stamp.sec), int(msg.header.stamp.nanosec)))
    h.update(struct.pack("<7d", p.x, p.y, p.z, o.x, o.y, o.z, o.w))
    h.update(np.ascontiguousarray(msg.pose.covariance, dtype="<f8").tobytes())
    return h.digest()


def _rng(digest: bytes) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence(int.from_bytes(digest[:16], "little")))


def _request_id(kind: str, digest: bytes) -> str:
    return f"ros-{kind}-{digest[:16].hex()}"


def _psd(cov: Array) -> Array:
    """The nearest PSD matrix by clipping eigenvalues at 0 (symmetrised first)."""
    s = 0.5 * (cov + cov.T)
    lam, v = np.linalg.eigh(s)
    if lam.min() >= 0:
        return s
    out: Array = (v * np.clip(lam, 0.0, None)) @ v.T
    return 0.5 * (out + out.T)


def _pose_samples(mean: Array, ros_cov: Array, n: int, digest: bytes) -> Array:
    try:
        return sample_pose(mean, ros_cov_to_tangent(mean, ros_cov), n_samples=n,
                           rng=_rng(digest), translation_frame="parent")
    except ValueError as exc:
        raise MappingError(str(exc)) from None


# --------------------------------------------------------------------------- the mapper

@dataclass
class _Odometry:
    """One odometry message, as far as keyframes need it."""

    mean: Array
    cov: Array  # ROS chart, header frame
    digest: bytes
    stamp_ns: int
    topic: str


@dataclass
class _Stream:
    """A robot's odometry: its odometry frame, its last keyframe, its latest message."""

    parent: str
    k: int = -1
    key: _Odometry | None = None
    pending: _Odometry | None = None


class MessageMapper:
    """Turns messages into :class:`Constraint` s; keeps the keyframe state of each robot.

    Feed it every message of every input topic in :func:`order_key` order.
    """

    def __init__(self, options: MappingOptions | None = None) -> None:
        self.options = options or MappingOptions()
        self._streams: dict[str, _Stream] = {}

    def kind_of(self, topic: str) -> Kind | None:
        return self.options.kind_of(topic)

    def keyframe_name(self, child: str) -> str | None:
        """The frame of ``child``'s latest keyframe (``base_link.7``), or None."""
        s = self._streams.get(child)
        return f"{child}.{s.k}" if s is not None and s.k >= 0 else None

    def map(self, topic: str, msg: Any, n_samples: int) -> list[Constraint]:
        """The constraints one message gives (none: not a keyframe yet).

        Raises
        ------
        MappingError
            The message is invalid; nothing changed.
        """
        kind = self.kind_of(topic)
        if kind is None:
            raise MappingError(f"topic {topic} is not an input topic")
        prefix = self.options.frame_prefix
        try:
            a = frame_from_ros(msg.header.frame_id, prefix)
            b = frame_from_ros(msg.child_frame_id, prefix)
        except ValueError as exc:
            raise MappingError(str(exc)) from None
        if a == b:
            raise MappingError(f"header.frame_id and child_frame_id are both {a!r}")
        mean, cov = _pose(msg)
        digest = message_digest(kind, msg)
        t = stamp_ns(msg)
        if kind == "odometry":
            return self._odometry(topic, a, b, _Odometry(mean, cov, digest, t, topic),
                                  n_samples)
        out: list[Constraint] = []
        a = self._attach(a, out, n_samples)
        if kind == "landmark":
            try:
                samples = sample_point(mean[:3], cov[:3, :3], n_samples=n_samples,
                                       rng=_rng(digest))
            except ValueError as exc:
                raise MappingError(str(exc)) from None
            out.append(Constraint(kind, topic, a, b, samples, _request_id(kind, digest), t))
            return out
        b = self._attach(b, out, n_samples)
        out.append(Constraint(kind, topic, a, b, _pose_samples(mean, cov, n_samples, digest),
                              _request_id(kind, digest), t))
        return out

    # -- odometry keyframes
    def _odometry(self, topic: str, parent: str, child: str, odo: _Odometry,
                  n_samples: int) -> list[Constraint]:
        s = self._streams.get(child)
        if s is not None and s.parent != parent:
            raise MappingError(f"{child} moved from odometry frame {s.parent} to {parent}")
        if s is None:
            s = self._streams[child] = _Stream(parent)
        s.pending = odo
        if s.key is None:
            return [self._keyframe(child, s, n_samples)]
        rel = relative(s.key.mean[None, :], odo.mean[None, :])[0]
        moved = float(np.linalg.norm(rel[:3]))
        turned = float(np.linalg.norm(qlog(rel[3:])))
        if moved >= self.options.keyframe_distance_m or turned >= self.options.keyframe_angle_rad:
            return [self._keyframe(child, s, n_samples)]
        return []

    def _keyframe(self, child: str, s: _Stream, n_samples: int) -> Constraint:
        """Make the stream's pending message its next keyframe."""
        odo, key = s.pending, s.key
        assert odo is not None
        k = s.k + 1
        if key is None:  # the first keyframe: odom -> base_link.0 as the message says
            c = Constraint("odometry", odo.topic, s.parent, f"{child}.0",
                           _pose_samples(odo.mean, odo.cov, n_samples, odo.digest),
                           _request_id("odometry", odo.digest), odo.stamp_ns)
        else:  # the increment since the last keyframe, with the covariance grown since
            digest = hashlib.sha256(key.digest + odo.digest).digest()
            rel = relative(key.mean[None, :], odo.mean[None, :])[0]
            r_t = rotation_matrix(key.mean[3:] / np.linalg.norm(key.mean[3:])).T
            turn = np.zeros((6, 6))
            turn[:3, :3] = r_t
            turn[3:, 3:] = r_t
            grown = turn @ _psd(odo.cov - key.cov) @ turn.T
            c = Constraint("odometry", odo.topic, f"{child}.{s.k}", f"{child}.{k}",
                           _pose_samples(rel, grown, n_samples, digest),
                           _request_id("odometry", digest), odo.stamp_ns)
        s.k, s.key, s.pending = k, odo, None
        return c

    def _attach(self, frame: str, out: list[Constraint], n_samples: int) -> str:
        """``frame``, or its robot's current keyframe when it is an odometry child."""
        s = self._streams.get(frame)
        if s is None:
            return frame
        if s.pending is not None:
            out.append(self._keyframe(frame, s, n_samples))
        return f"{frame}.{s.k}"
