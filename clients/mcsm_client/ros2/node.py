"""``mcsm ros2``: a ROS 2 node (rclpy) that feeds a map server and publishes the map back.

Inputs (``nav_msgs/Odometry`` on the topics of :class:`~mcsm_client.ros2.mapping.MappingOptions`,
reliable QoS) are held in a reorder buffer for ``reorder_window_s`` and applied by one worker
thread in :func:`~mcsm_client.ros2.mapping.order_key` order through ``MapClient`` (request ids
from the messages: exactly once, even for a bag replayed twice). When the server does not
answer, the worker retries the same request until it does; nothing is dropped.

Every ``publish_period_s`` (at once after a change) it fetches the map (one export per
component), computes every frame's marginal and publishes ``/tf`` (the map frame to every frame
of the origin's component: ``map -> robot1/odom`` as slam_toolbox does, and the map's own
frames), ``/mcsm/path[/ROBOT]``, ``/mcsm/markers``, ``/mcsm/pose/<B>`` for each ``pose_pairs``
entry ``A:B`` and ``/diagnostics``. Services: ``~/relinearize`` and ``~/snapshot``
(``std_srvs/Trigger``); parameters ``retract`` and ``reinstate`` take a request id.
Everything is documented in docs/ros2.md.
"""

from __future__ import annotations

import heapq
import logging
import math
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcsm.core.names import is_frame_name
from mcsm.errors import McsmError, NoPermittedServer, NoServer, Timeout
from mcsm.viz import ros, rosmsg
from mcsm.viz.rosbag import path_topic, write_map_bag

from mcsm_client.ros2.bag import ApplyStats, send
from mcsm_client.ros2.mapping import MappingOptions, MessageMapper, order_key
from mcsm_client.ros2.params import PARAMETERS

log = logging.getLogger("mcsm.ros2")

__all__ = ["NodeOptions", "RosNode", "PARAMETERS"]

@dataclass
class NodeOptions:
    """The node's parameters as values (see :data:`PARAMETERS`)."""

    mapping: MappingOptions = field(default_factory=MappingOptions)
    reorder_window_s: float = 0.2
    publish_period_s: float = 1.0
    map_frame: str = "map"
    origin_frame: str = ""
    pose_pairs: tuple[tuple[str, str], ...] = ()
    tf_skip: frozenset[str] = frozenset()
    snapshot_dir: Path = Path(".")


def topic_token(name: str) -> str:
    """A frame name as topic name tokens (``/``-separated; invalid characters become ``_``,
    a leading digit gets an ``f``)."""
    parts = []
    for seg in name.split("/"):
        s = re.sub(r"[^A-Za-z0-9_]", "_", seg)
        parts.append(f"f{s}" if not s or s[0].isdigit() else s)
    return "/".join(parts)


def _strings(v: Any) -> list[str]:
    return [str(x) for x in (v or []) if str(x)]


class RosNode:
    """The node: subscriptions, the worker, the publications, services and parameters.

    Parameters
    ----------
    node : rclpy.node.Node
        The rclpy node (its parameters were declared by :func:`declare_parameters`).
    writer, reader : MapClient
        Two clients of the same map: the worker's (updates, retract, reinstate) and the
        publisher's (info, export), so neither waits for the other.
    """

    def __init__(self, node: Any, writer: Any, reader: Any, opts: NodeOptions) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from std_srvs.srv import Trigger
        from visualization_msgs.msg import MarkerArray

        from mcsm_client.ros2.tf2 import load_tfmessage

        self.node, self.writer, self.reader, self.opts = node, writer, reader, opts
        self.mapper = MessageMapper(opts.mapping)
        self.stats = ApplyStats()
        self.n_samples = int(writer.info().n_samples)
        self._lock = threading.Condition()
        self._heap: list[tuple[tuple[int, int, str, int], float, str, Any]] = []
        self._arrivals = 0
        self._busy = False
        self._stop = threading.Event()
        self._write_lock = threading.Lock()
        self._origin: str | None = opts.origin_frame or None
        self._server_ok = True
        self._shown_seq = -1
        self._placed: list[ros.PlacedFrame] = []
        self._make = _rclpy_maker(load_tfmessage())
        self.published = 0
        self.last_action = ""
        inputs = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self._subs = [node.create_subscription(Odometry, t, self._receiver(t), inputs)
                      for t in opts.mapping.topics]
        self._tf = node.create_publisher(self._make.type("tf2_msgs/msg/TFMessage"), "/tf",
                                         QoSProfile(depth=100,
                                                    reliability=ReliabilityPolicy.RELIABLE))
        self._markers = node.create_publisher(MarkerArray, "/mcsm/markers", latched)
        self._diag = node.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._latched = latched
        self._paths: dict[str, Any] = {}
        self._poses = {pair: node.create_publisher(PoseWithCovarianceStamped,
                                                   f"/mcsm/pose/{topic_token(pair[1])}", latched)
                       for pair in opts.pose_pairs}
        node.create_service(Trigger, "~/relinearize", self._relinearize)
        node.create_service(Trigger, "~/snapshot", self._snapshot)
        node.add_on_set_parameters_callback(self._on_parameters)
        self._changed = threading.Event()
        self._changed.set()
        self._timer = node.create_timer(min(opts.publish_period_s, 0.1), self._tick)
        self._last_publish = 0.0
        self._t0 = time.perf_counter()
        self._worker = threading.Thread(target=self._work, name="mcsm-ros2-worker", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ inputs
    def _receiver(self, topic: str) -> Callable[[Any], None]:
        def on_message(msg: Any) -> None:
            kind = self.mapper.kind_of(topic)
            assert kind is not None
            with self._lock:
                self._arrivals += 1
                heapq.heappush(self._heap, (order_key(topic, kind, msg, self._arrivals),
                                            time.monotonic(), topic, msg))
                self._lock.notify()

        return on_message

    @property
    def queue_length(self) -> int:
        with self._lock:
            return len(self._heap)

    def _next(self) -> tuple[str, Any] | None:
        """The next message to apply once its reorder window passed (None: stopping)."""
        with self._lock:
            self._busy = False
            while True:
                if self._heap:
                    wait = self._heap[0][1] + self.opts.reorder_window_s - time.monotonic()
                    if wait <= 0 or self._stop.is_set():
                        _, _, topic, msg = heapq.heappop(self._heap)
                        self._busy = True
                        return topic, msg
                elif self._stop.is_set():
                    return None
                else:
                    wait = 0.5
                self._lock.wait(timeout=min(wait, 0.5))

    def _work(self) -> None:
        while True:
            item = self._next()
            if item is None:
                return
            topic, msg = item
            self.stats.received += 1
            try:
                constraints = self.mapper.map(topic, msg, self.n_samples)
            except Exception as exc:  # MappingError, or numpy on a hostile message: skip it
                self.stats.invalid_message(topic, exc)
                log.warning("invalid message on %s: %s", topic, exc)
                continue
            if not constraints:
                self.stats.not_keyframes += 1
            for c in constraints:
                while True:
                    try:
                        with self._write_lock:
                            ack = send(self.writer, c, self.stats)
                        self._server_ok = True
                        break
                    except (NoServer, NoPermittedServer, Timeout) as exc:
                        self._server_ok = False  # same request id again: applied once
                        log.warning("%s -> %s: %s; sending again", c.a, c.b, exc)
                        if self._stop.wait(0.5):
                            log.error("stopping with the map server unreachable: %d messages "
                                      "not applied (play them again: each applies once)",
                                      self.queue_length + 1)
                            return
                if ack is not None and self._origin is None and not ack.duplicate:
                    self._origin = c.a
                self._changed.set()

    def drain(self, timeout_s: float) -> bool:
        """Wait until every received message was applied (True) or ``timeout_s`` passed."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self._lock:
                idle = not self._heap and not self._busy
            if idle:
                return True
            time.sleep(0.05)
        return False

    def stop(self) -> None:
        """Apply what is buffered (no more waiting), then stop the worker."""
        self._stop.set()
        with self._lock:
            self._lock.notify_all()
        self._worker.join(timeout=30.0)
        self.stats.elapsed_s = time.perf_counter() - self._t0

    # ------------------------------------------------------------------ publications
    def _tick(self) -> None:
        now = time.monotonic()
        if not self._changed.is_set() and now - self._last_publish < self.opts.publish_period_s:
            return
        if self._changed.is_set() and now - self._last_publish < 0.1:
            return
        self._last_publish = now
        self._changed.clear()
        try:
            self.publish()
        except McsmError as exc:
            log.warning("could not fetch the map: %s", exc)
            self._changed.set()
        except Exception:  # never let a publication error stop the node
            log.exception("publishing the map failed")

    def fetch(self) -> list[ros.PlacedFrame]:
        """Every frame's marginal now (one export per component); cached per seq."""
        from mcsm.core import StochasticMap

        info = self.reader.info()
        self.info = info
        if info.seq != self._shown_seq:
            local = StochasticMap.from_options(dict(info.options))
            for root in info.components:
                local.import_component(self.reader.export_submap(root))
            frames = list(local.frames())
            origin = self._origin if self._origin in frames else (frames[0] if frames else None)
            self._placed = ros.place_frames(local, origin=origin,
                                            map_frame=self.opts.map_frame)
            self._shown_seq = info.seq
        return self._placed

    def publish(self) -> None:
        """Fetch the map and publish TF, paths, markers, poses and diagnostics once."""
        from nav_msgs.msg import Path as PathMsg

        placed = self.fetch()
        t_ns = self.node.get_clock().now().nanoseconds
        make = self._make
        tf_frames = [f for f in placed if f.name not in self.opts.tf_skip]
        self._tf.publish(rosmsg.tf_message(make, t_ns, tf_frames))
        for robot, fs in ros.paths_by_robot(placed).items():
            pub = self._paths.get(robot)
            if pub is None:
                pub = self._paths[robot] = self.node.create_publisher(
                    PathMsg, path_topic(robot), self._latched)
            pub.publish(rosmsg.path(make, t_ns, fs))
        self._markers.publish(rosmsg.marker_array(make, t_ns, ros.map_markers(placed)))
        for (a, b), pub in self._poses.items():
            try:
                mean, cov = self.reader.marginal(a, b)
            except (NoServer, NoPermittedServer, Timeout):
                raise
            except McsmError:
                continue  # not (yet) related
            pub.publish(rosmsg.pose_with_covariance_stamped(make, t_ns, a, mean, cov))
        self._diag.publish(self._diagnostics(t_ns))
        self.published += 1

    def _diagnostics(self, t_ns: int) -> Any:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        s = self.stats
        info = getattr(self, "info", None)
        level = (DiagnosticStatus.ERROR if not self._server_ok else
                 DiagnosticStatus.WARN if (s.rejected or s.n_refused or s.invalid) else
                 DiagnosticStatus.OK)
        values = {"received": s.received, "applied": s.n_applied, "duplicates": s.duplicates,
                  "rejected_by_gate": s.rejected, "refused": s.n_refused,
                  "refused_by_error": ", ".join(f"{k} {v}" for k, v in s.refused.items()),
                  "invalid_messages": s.invalid, "odometry_between_keyframes": s.not_keyframes,
                  "queue_length": self.queue_length, "last_verdict": s.last_verdict,
                  "last_request_id": s.last_request_id, "first_error": s.first_error,
                  "last_action": self.last_action,
                  "seq": info.seq if info else "", "digest": info.digest if info else "",
                  "frames": info.n_frames if info else "",
                  "components": len(info.components) if info else ""}
        msg = ("no answer from the map server" if not self._server_ok else
               f"{s.n_applied} applied, {s.rejected} rejected, {s.n_refused} refused, "
               f"{s.invalid} invalid")
        status = DiagnosticStatus(level=level, name=f"mcsm_ros2: map {self.writer.map}",
                                  message=msg, hardware_id=str(self.writer.server_id or ""),
                                  values=[KeyValue(key=k, value=str(v))
                                          for k, v in values.items()])
        return DiagnosticArray(header=rosmsg.header(self._make, t_ns, ""), status=[status])

    # ------------------------------------------------------------------ services, parameters
    def _relinearize(self, _req: Any, resp: Any) -> Any:
        fn = getattr(self.writer, "relinearize", None)
        if fn is None:
            resp.success, resp.message = False, "this mcsm has no relinearize operation"
            return resp
        try:
            with self._write_lock:
                ack = fn()
            resp.success, resp.message = True, f"relinearized: seq {getattr(ack, 'seq', '?')}"
            self._changed.set()
        except Exception as exc:  # McsmError, or a relinearize that wants arguments
            resp.success, resp.message = False, f"{type(exc).__name__}: {exc}"
        return resp

    def _snapshot(self, _req: Any, resp: Any) -> Any:
        try:
            placed = self.fetch()
            out = self.opts.snapshot_dir / f"mcsm-{self.writer.map}-seq{self._shown_seq}"
            if out.exists():
                resp.success, resp.message = True, f"{out} (unchanged since)"
                return resp
            write_map_bag(placed, self.node.get_clock().now().nanoseconds, out)
            resp.success, resp.message = True, str(out)
        except (McsmError, OSError) as exc:
            resp.success, resp.message = False, f"{type(exc).__name__}: {exc}"
        return resp

    def _on_parameters(self, params: list[Any]) -> Any:
        from rcl_interfaces.msg import SetParametersResult

        for p in params:
            if p.name in ("retract", "reinstate") and p.value:
                fn = self.writer.retract if p.name == "retract" else self.writer.reinstate
                try:
                    with self._write_lock:
                        ack = fn(str(p.value))
                except McsmError as exc:
                    return SetParametersResult(successful=False,
                                               reason=f"{type(exc).__name__}: {exc}")
                self._changed.set()
                v = ack.verdict.status if ack.verdict is not None else ack.kind
                # rclpy drops a successful result's reason: diagnostics carry it
                self.last_action = f"{p.name} {p.value}: seq {ack.seq}, {v}"
                log.info("%s", self.last_action)
                return SetParametersResult(successful=True, reason=self.last_action)
        return SetParametersResult(successful=True)


class _Maker:
    """``make(typename, **fields)`` over rclpy's message classes (rosmsg's builders)."""

    def __init__(self, tfmessage: Any) -> None:
        self._classes: dict[str, Any] = {"tf2_msgs/msg/TFMessage": tfmessage}

    def type(self, name: str) -> Any:
        cls = self._classes.get(name)
        if cls is None:
            import importlib

            pkg, _, msg = name.split("/")
            cls = self._classes[name] = getattr(importlib.import_module(f"{pkg}.msg"), msg)
        return cls

    def __call__(self, name: str, **fields: Any) -> Any:
        return self.type(name)(**fields)


def _rclpy_maker(tfmessage: Any) -> _Maker:
    return _Maker(tfmessage)


def declare_parameters(node: Any) -> NodeOptions:
    """Declare :data:`PARAMETERS` on an rclpy node; their values (``--ros-args -p``) as
    :class:`NodeOptions`."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import ParameterException

    for name, (default, text) in PARAMETERS.items():
        try:
            node.declare_parameter(name, default, ParameterDescriptor(description=text))
        except ParameterException as exc:  # e.g. a string given for a number
            raise ValueError(str(exc)) from None

    def get(name: str) -> Any:
        return node.get_parameter(name).value

    for name, low, strict in (("keyframe_distance_m", 0.0, False),
                              ("keyframe_angle_rad", 0.0, False),
                              ("reorder_window_s", 0.0, False), ("publish_period_s", 0.0, True)):
        v = float(get(name))
        if not (v > low if strict else v >= low) or not math.isfinite(v):
            raise ValueError(f"parameter {name} is {v:g}: expected a finite number "
                             f"{'>' if strict else '>='} {low:g}")
    if not is_frame_name(get("map_frame")):
        raise ValueError(f"parameter map_frame {get('map_frame')!r} is not a frame name")

    pairs = []
    for entry in _strings(get("pose_pairs")):
        a, sep, b = entry.partition(":")
        if not sep or not a or not b:
            raise ValueError(f"pose_pairs entry {entry!r}: expected 'A:B'")
        pairs.append((a, b))
    mapping = MappingOptions(odometry_topics=tuple(_strings(get("odometry_topics"))),
                             constraint_topics=tuple(_strings(get("constraint_topics"))),
                             landmark_topics=tuple(_strings(get("landmark_topics"))),
                             frame_prefix=str(get("frame_prefix")),
                             keyframe_distance_m=float(get("keyframe_distance_m")),
                             keyframe_angle_rad=float(get("keyframe_angle_rad")))
    return NodeOptions(mapping=mapping, reorder_window_s=float(get("reorder_window_s")),
                       publish_period_s=float(get("publish_period_s")),
                       map_frame=str(get("map_frame")), origin_frame=str(get("origin_frame")),
                       pose_pairs=tuple(pairs), tf_skip=frozenset(_strings(get("tf_skip"))),
                       snapshot_dir=Path(str(get("snapshot_dir"))))
