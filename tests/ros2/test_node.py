"""``mcsm ros2`` with real rclpy processes over Fast DDS on this host: a peer publishes the
§6 simulation as ROS messages; the node's map ends bit-identical to the reference (the same
constraints through MapClient); the peer receives TF, the path and the markers, retracts and
reinstates a constraint through the node's parameters and calls its services. Also: importing
the server, or ``mcsm --help``, loads no ROS library."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from mcsm.viz.ros import tangent_cov_to_ros
from mcsm_client.client import MapClient
from mcsm_client.process import McsmProcess, ServerProcess

from tests.ros2.conftest import Reference
from tests.service.daemon_util import free_port

PEER = Path(__file__).with_name("ros_peer.py")


def test_the_server_and_mcsm_help_import_no_ros() -> None:
    code = ("import sys, mcsm.serve.server, mcsm.cli, mcsm.viz.rosbag\n"
            "mcsm.cli.build_parser()\n"
            "bad = sorted(m for m in sys.modules if m.split('.')[0] in ('rclpy', 'rosbags',"
            " 'nav_msgs', 'geometry_msgs', 'tf2_msgs', 'mcsm_client'))\n"
            "print(bad)\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    # mcsm --help finds `ros2` and `view` through their entry points: the plugins' modules,
    # nothing of ROS
    assert r.stdout.strip() == ("['mcsm_client', 'mcsm_client.ros2', 'mcsm_client.ros2.cli', "
                                "'mcsm_client.ros2.params', 'mcsm_client.view_command']")
    r = subprocess.run([sys.executable, "-m", "mcsm.cli", "--help"], capture_output=True,
                       text=True, timeout=60)
    assert "ros2" in r.stdout and "export-rosbag" in r.stdout


def test_node_streams_the_simulation(tmp_path: Path, ros_server: ServerProcess,
                                     reference: Reference, ros_env: dict[str, str]) -> None:
    msgs = reference.messages
    frames = sorted({m.child_frame_id for m in msgs} | {"x0"})
    target = reference.ids[-1]  # the last sighting: retracted, then reinstated
    spec = {"messages": [{"topic": m.topic, "stamp_ns": m.stamp_ns, "frame_id": m.frame_id,
                          "child": m.child_frame_id, "mean": m.mean.tolist(),
                          "cov": m.cov.tolist()} for m in msgs],
            "frames": frames, "poses": sum(f.startswith("x") for f in frames),
            "retract": target, "n_constraints": len(reference.ids)}
    # hostile inputs: a NaN pose, an 'unknown' (negative) variance, equal frames: counted as
    # invalid, never sent, the node goes on
    last = spec["messages"][-1]
    bad_cov = np.diag([-1.0, 1, 1, 1, 1, 1]).tolist()
    spec["messages"] += [dict(last, mean=[float("nan")] + last["mean"][1:]),
                         dict(last, cov=bad_cov), dict(last, child=last["frame_id"])]
    (tmp_path / "in.json").write_text(json.dumps(spec))
    snapshots = tmp_path / "snapshots"
    snapshots.mkdir()
    node = McsmProcess(["ros2", "--connect", ros_server.endpoint, "--map", "live",
                        "--ros-args", "-p", "publish_period_s:=0.3", "-p",
                        "reorder_window_s:=0.3", "-p", f"snapshot_dir:={snapshots}", "-p",
                        "pose_pairs:=['x0:x5']"],
                       ready="mcsm ros2: ready", env=ros_env, log_path=tmp_path / "node.log",
                       ready_timeout_s=60.0)
    with node:
        peer = subprocess.run([sys.executable, str(PEER), str(tmp_path / "in.json"),
                               str(tmp_path / "out.json")], capture_output=True, text=True,
                              timeout=120, env=node.env)
        assert peer.returncode == 0, peer.stderr[-3000:] + node.log_tail(40)
        out = json.loads((tmp_path / "out.json").read_text())
        with MapClient(map="live", connect=ros_server.endpoint) as c:
            deadline = time.monotonic() + 10.0
            has_relin = hasattr(MapClient, "relinearize")
            want_seq = reference.seq + 2 + has_relin
            while c.info().seq < want_seq and time.monotonic() < deadline:
                time.sleep(0.1)
            info = c.info()
            # every message applied once, in order; retract + reinstate + relinearize: three
            # more seqs (the map's digest after the reinstate is checked in the diagnostics)
            assert info.seq == want_seq, node.log_tail(40)
            assert info.digest != reference.digest or not has_relin
            assert c.verdict(target).status == "reinstated"  # type: ignore[union-attr]
            last = f"x{spec['poses'] - 1}"
            mean, _ = c.marginal("x0", last)
            mean5, cov5 = c.marginal("x0", "x5")
        code = node.stop()
    assert code == 0, node.log_tail(20)
    assert out["matched"] and out["complete"], out
    # TF: the map frame at x0 (the origin), every frame under it at its marginal mean
    assert out["tf"]["x0"][0] == "map" and out["tf"]["x0"][1:] == [0.0, 0.0]
    assert set(out["tf"]) == set(frames)
    assert out["tf"][last][0] == "map"
    np.testing.assert_allclose(out["tf"][last][1:], mean[:2], atol=1e-9)
    assert out["path"] == spec["poses"] and out["path_frame"] == "map"
    # pose_pairs x0:x5: x5 in x0 with ROS's covariance
    assert out["pose"][0] == "x0"
    np.testing.assert_allclose(out["pose"][1:3], mean5[:2], atol=1e-12)
    np.testing.assert_allclose(np.reshape(out["pose"][3], (6, 6)),
                               tangent_cov_to_ros(mean5, cov5), atol=1e-15)
    assert out["markers"] == 1 + 2 * len(frames)
    assert out["marker_ns"] == ["mcsm", "mcsm/labels", "mcsm/landmarks", "mcsm/poses"]
    assert out["labels"] == frames
    # parameters retract / reinstate: done (the verdict above); an unknown id is refused
    assert out["retract"][0] and out["reinstate"][0], out
    assert out["retract_unknown"][0] is False and "ros-constraint-unknown" in \
        out["retract_unknown"][1], out
    assert out["snapshot"][0], out
    assert (Path(out["snapshot"][1]) / "metadata.yaml").is_file()
    assert out["relinearize"][0] is has_relin, out  # no relinearize operation before it lands
    # the diagnostics after the reinstate: the map again bit-identical to the reference
    d = out["diagnostics_reinstated"]
    assert d["received"] == str(len(msgs) + 3) and d["applied"] == str(len(reference.ids))
    assert d["refused"] == "0" and d["invalid_messages"] == "3" and d["queue_length"] == "0"
    assert d["last_action"].startswith(f"reinstate {target}: seq {reference.seq + 2}, "
                                       "reinstated"), d
    assert d["digest"] == reference.digest and d["seq"] == str(reference.seq + 2)
    assert out["diagnostics_level"] == 1  # WARN: invalid messages were seen
    log = node.log_text()
    assert "stopped:" in log or "stopped:" in "".join(iter_lines(node))


def iter_lines(proc: McsmProcess) -> list[str]:
    lines = []
    while not proc.lines.empty():
        line = proc.lines.get_nowait()
        if line is None:
            break
        lines.append(line)
    return lines


def test_node_serve_record_refuses_an_existing_file_and_a_missing_folder(
        tmp_path: Path, ros_env: dict[str, str]) -> None:
    old = tmp_path / "old.mcap"
    old.write_bytes(b"")
    typo = tmp_path / "nosuch" / "x.mcap"
    for path, why in ((old, "exists; a recording is never overwritten"),
                      (typo, f"its folder {typo.parent} does not exist")):
        r = subprocess.run([sys.executable, "-m", "mcsm.cli", "ros2", "--serve", "--record",
                            str(path)], capture_output=True, text=True, timeout=60,
                           env={**os.environ, **ros_env})
        assert r.returncode == 2 and f"mcsm ros2: --record {path}: {why}" in r.stderr, r.stderr
    assert not typo.parent.exists() and old.read_bytes() == b""


def test_node_exit_codes_no_server_and_a_bad_parameter(ros_env: dict[str, str]) -> None:
    """No server at the endpoint: exit 3 and a line saying so; a bad parameter: exit 2 at
    once, with or without a server (parameters are read before the node looks for one)."""
    dead = f"tcp/127.0.0.1:{free_port()}"
    env = {**os.environ, **ros_env}
    base = [sys.executable, "-m", "mcsm.cli", "ros2", "--connect", dead, "--timeout-s", "1"]
    r = subprocess.run(base, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 3 and "mcsm ros2: no map server: cannot connect" in r.stderr, \
        r.stderr
    for param, why in (("keyframe_distance_m:=-1.0", "keyframe_distance_m is -1: expected"),
                       ("keyframe_distance_m:=abc", "of type 'STRING', expecting type 'DOUBLE'"),
                       ("publish_period_s:=0.0", "publish_period_s is 0: expected"),
                       ("map_frame:=''", "map_frame '' is not a frame name")):
        r = subprocess.run([*base, "--ros-args", "-p", param], capture_output=True, text=True,
                           timeout=120, env=env)
        assert r.returncode == 2 and why in r.stderr, r.stderr
        assert "no map server" not in r.stderr and "Traceback" not in r.stderr


def test_the_built_tfmessage_has_the_real_type_hash(ros_env: dict[str, str]) -> None:
    """The TFMessage type support built from the IDL (tf2_msgs has no wheel) has the type hash
    docs/ros2.md quotes, which rosbags computes for the real type too: tf2 listeners and RViz
    on a ROS 2 installation match it."""
    code = ("import rclpy, time\n"
            "from mcsm_client.ros2.tf2 import load_tfmessage\n"
            "rclpy.init()\n"
            "n = rclpy.create_node('hash_probe')\n"
            "n.create_publisher(load_tfmessage(), '/tf_probe', 1)\n"
            "(i,) = n.get_publishers_info_by_topic('/tf_probe')\n"
            "print(i.topic_type, i.topic_type_hash)\n"
            "n.destroy_node(); rclpy.shutdown()\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=120, env={**os.environ, **ros_env})
    assert r.returncode == 0, r.stderr
    from rosbags.typesys import Stores, get_typestore

    real = get_typestore(Stores.ROS2_KILTED).hash_rihs01("tf2_msgs/msg/TFMessage")
    doc = (Path(__file__).parents[2] / "docs" / "ros2.md").read_text()
    assert real in doc
    assert r.stdout.split() == ["tf2_msgs/msg/TFMessage", real]


def test_node_serve_runs_its_own_server_and_records(tmp_path: Path,
                                                    ros_env: dict[str, str]) -> None:
    """``mcsm ros2 --serve``: the node with a server in its process on a free loopback port;
    it says where, a client reaches it there, and SIGTERM closes a recording that replays."""
    from mcsm.log.replay import replay

    record = tmp_path / "node.mcap"
    node = McsmProcess(["ros2", "--serve", "--samples", "64", "--record", str(record)],
                       ready="mcsm ros2: serving map", env=ros_env,
                       log_path=tmp_path / "node.log", ready_timeout_s=60.0)
    with node:
        said = node.ready_line
        assert said.endswith(f", recording to {record}"), said
        endpoint = said.split("serving map 'default' on ")[1].split(",")[0]
        assert endpoint.startswith("tcp/127.0.0.1:")
        ready = node.lines.get(timeout=60)
        assert ready is not None and ready.startswith("mcsm ros2: ready"), ready
        with MapClient(connect=endpoint) as c:
            c.update("a", "b", np.tile([1.0, 0, 0, 1, 0, 0, 0], (64, 1)))
            assert c.info().seq == 1
        assert node.stop(signal.SIGTERM) == 0, node.log_tail(40)
    rep = replay(record)
    assert rep.identical and rep.complete and rep.n_inputs == 1
