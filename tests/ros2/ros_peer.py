"""A real rclpy process for the node test: publishes the simulation's messages to ``mcsm ros2``,
subscribes to what it publishes, calls its services and parameters, writes what it saw.

``python tests/ros2/ros_peer.py IN.json OUT.json``; IN holds the messages (topic, stamp, frames,
pose, covariance), the frames to wait for, and a request id to retract and reinstate. Every wait
is bounded; OUT says what arrived (also when a wait ran out).
"""

from __future__ import annotations

import json
import sys
import time
from typing import Any

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseWithCovarianceStamped
from mcsm.viz.rosmsg import odometry
from mcsm_client.ros2.tf2 import load_tfmessage
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

NODE = "/mcsm_ros2"


def main() -> int:
    spec = json.loads(open(sys.argv[1]).read())
    out: dict[str, Any] = {"tf": {}, "path": 0, "markers": 0, "diagnostics": {}}
    tfmsg = load_tfmessage()
    classes = {"nav_msgs/msg/Odometry": Odometry}

    def make(name: str, **fields: Any) -> Any:
        import importlib

        if name not in classes:
            pkg, _, cls = name.split("/")
            classes[name] = getattr(importlib.import_module(f"{pkg}.msg"), cls)
        return classes[name](**fields)

    rclpy.init()
    node = rclpy.create_node("mcsm_test_peer")
    reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    pubs = {t: node.create_publisher(Odometry, t, reliable)
            for t in sorted({m["topic"] for m in spec["messages"]})}

    def on_tf(msg: Any) -> None:
        for t in msg.transforms:
            out["tf"][t.child_frame_id] = [t.header.frame_id, t.transform.translation.x,
                                           t.transform.translation.y]

    def on_path(msg: Any) -> None:
        out["path"] = len(msg.poses)
        out["path_frame"] = msg.header.frame_id

    def on_markers(msg: Any) -> None:
        out["markers"] = len(msg.markers)
        out["marker_ns"] = sorted({m.ns for m in msg.markers})
        out["labels"] = sorted(m.text for m in msg.markers if m.text)

    def on_diag(msg: Any) -> None:
        for s in msg.status:
            out["diagnostics"] = {kv.key: kv.value for kv in s.values}
            out["diagnostics_level"] = int.from_bytes(s.level, "little") \
                if isinstance(s.level, bytes) else int(s.level)

    node.create_subscription(tfmsg, "/tf", on_tf, 100)
    node.create_subscription(Path, "/mcsm/path", on_path, latched)
    node.create_subscription(MarkerArray, "/mcsm/markers", on_markers, latched)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)

    def on_pose(msg: Any) -> None:
        p = msg.pose.pose.position
        out["pose"] = [msg.header.frame_id, p.x, p.y, list(msg.pose.covariance)]

    node.create_subscription(PoseWithCovarianceStamped, "/mcsm/pose/x5", on_pose, latched)

    def spin_until(cond: Any, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if cond():
                return True
            rclpy.spin_once(node, timeout_sec=0.05)
        return bool(cond())

    out["matched"] = spin_until(lambda: all(p.get_subscription_count() > 0
                                            for p in pubs.values()), 20.0)
    for m in spec["messages"]:
        pubs[m["topic"]].publish(odometry(make, m["stamp_ns"], m["frame_id"], m["child"],
                                          np.array(m["mean"]), np.array(m["cov"])))
    want = set(spec["frames"])
    out["complete"] = spin_until(lambda: want <= set(out["tf"]) and
                                 out["path"] >= spec["poses"] and
                                 out["markers"] >= 1 + 2 * len(want) and "pose" in out, 30.0)

    def call(srv_type: Any, name: str, req: Any) -> Any:
        cli = node.create_client(srv_type, name)
        if not cli.wait_for_service(timeout_sec=10.0):
            return None
        fut = cli.call_async(req)
        rclpy.spin_until_future_complete(node, fut, timeout_sec=20.0)
        return fut.result()

    for action, rid in (("retract", spec["retract"]), ("reinstate", spec["retract"]),
                        ("retract_unknown", "ros-constraint-unknown")):
        req = SetParameters.Request(parameters=[Parameter(
            name=action.split("_")[0], value=ParameterValue(
                type=ParameterType.PARAMETER_STRING, string_value=rid))])
        r = call(SetParameters, f"{NODE}/set_parameters", req)
        out[action] = [r.results[0].successful, r.results[0].reason] if r else None
    r = call(Trigger, f"{NODE}/snapshot", Trigger.Request())
    out["snapshot"] = [r.success, r.message] if r else None
    n_diag = spec["n_constraints"]
    # the publications after the reinstate (diagnostics come last in each round), kept before
    # the relinearisation below changes the map
    spin_until(lambda: out["diagnostics"].get("received") == str(len(spec["messages"]))
               and int(out["diagnostics"].get("applied", -1)) >= n_diag
               and out["diagnostics"].get("last_action", "").startswith("reinstate"), 10.0)
    out["diagnostics_reinstated"] = dict(out["diagnostics"])
    r = call(Trigger, f"{NODE}/relinearize", Trigger.Request())
    out["relinearize"] = [r.success, r.message] if r else None
    spin_until(lambda: False, 0.3)
    with open(sys.argv[2], "w") as f:
        json.dump(out, f)
    node.destroy_node()
    rclpy.shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
