"""ROS 2 bags: ``mcsm-client play-rosbag`` of bags written with rosbags (MCAP and sqlite3) gives
the reference map's digest, a second play applies nothing; ``mcsm export-rosbag`` writes a bag
rosbags reads back, whose poses are the map's marginals and which plays back into a map."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcsm import cli as mcsm_cli
from mcsm.viz.ros import tangent_cov_to_ros
from mcsm_client import cli as client_cli
from mcsm_client.client import MapClient
from mcsm_client.process import ServerProcess
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from tests.ros2.conftest import Reference

STORE = get_typestore(Stores.ROS2_KILTED)


def write_bag(path: Path, ref: Reference, storage: StoragePlugin,
              shuffled: bool = False) -> None:
    """The simulation's messages as a ROS 2 bag, log time = stamp, plus an unrelated topic;
    ``shuffled``: the stamps written in a random order, with log times that do not follow
    them (as a recorder on a loaded host may log them); messages of one stamp keep their
    order (ties keep the recorded order, docs/ros2.md)."""
    pairs = list(zip(ref.messages, ref.decoded, strict=True))
    log_times = [m.stamp_ns for m, _ in pairs]
    if shuffled:
        stamps = sorted({m.stamp_ns for m, _ in pairs})
        rank = dict(zip(stamps, np.random.default_rng(7207).permutation(len(stamps)),
                        strict=True))
        pairs = sorted(pairs, key=lambda p: rank[p[0].stamp_ns])  # stable: ties keep order
        log_times = sorted(log_times)  # the k-th written gets the k-th time
    with Writer(path, version=9, storage_plugin=storage) as w:
        conns = {}
        for (m, msg), t in zip(pairs, log_times, strict=True):
            if m.topic not in conns:
                conns[m.topic] = w.add_connection(m.topic, "nav_msgs/msg/Odometry",
                                                  typestore=STORE)
            w.write(conns[m.topic], t, STORE.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
        other = w.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
        w.write(other, 1, STORE.serialize_cdr(STORE.types["std_msgs/msg/String"](data="hi"),
                                              "std_msgs/msg/String"))


def play(server: ServerProcess, bag: Path, map_name: str, capsys: pytest.CaptureFixture[str],
         *extra: str) -> tuple[int, dict[str, object]]:
    code = client_cli.main(["play-rosbag", str(bag), "--connect", server.endpoint, "--map",
                            map_name, "--json", "--no-progress", *extra])
    out = capsys.readouterr().out.strip().splitlines()[-1]
    return code, json.loads(out)


@pytest.mark.parametrize("storage,map_name", [(StoragePlugin.MCAP, "mcap"),
                                              (StoragePlugin.SQLITE3, "sqlite")])
def test_play_rosbag_gives_the_reference_map(tmp_path: Path, ros_server: ServerProcess,
                                             reference: Reference, storage: StoragePlugin,
                                             map_name: str,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    bag = tmp_path / f"sim-{map_name}"
    write_bag(bag, reference, storage)
    code, out = play(ros_server, bag, map_name, capsys)
    assert code == 0, out
    assert out["received"] == len(reference.messages)
    assert out["applied"] == {"constraint": reference.stats.applied["constraint"],
                              "landmark": reference.stats.applied["landmark"]}
    with MapClient(map=map_name, connect=ros_server.endpoint) as c:
        info = c.info()
        assert (info.seq, info.digest) == (reference.seq, reference.digest)
        # played again: every request id is known, nothing changes
        code, again = play(ros_server, bag, map_name, capsys)
        assert code == 0 and again["duplicates"] == len(reference.ids)
        assert again["applied"] == {}
        assert c.info().digest == reference.digest


def test_play_rosbag_sorts_by_stamp_and_reads_one_file(tmp_path: Path,
                                                       ros_server: ServerProcess,
                                                       reference: Reference,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """A bag whose messages are logged out of stamp order gives the reference map (the
    messages are applied in header-stamp order, not log order), read from its one .mcap file
    rather than its folder."""
    bag = tmp_path / "shuffled"
    write_bag(bag, reference, StoragePlugin.MCAP, shuffled=True)
    with AnyReader([bag], default_typestore=STORE) as r:
        stamps = [r.deserialize(raw, c.msgtype).header.stamp for c, _, raw in r.messages()
                  if c.topic != "/chatter"]
    ns = [st.sec * 10**9 + st.nanosec for st in stamps]
    assert ns != sorted(ns)  # log order is not stamp order
    (one,) = bag.glob("*.mcap")
    code = client_cli.main(["play-rosbag", str(one), "--connect", ros_server.endpoint, "--map",
                            "shuffled", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    with MapClient(map="shuffled", connect=ros_server.endpoint) as c:
        info = c.info()
        assert (info.seq, info.digest) == (reference.seq, reference.digest)


def test_play_rosbag_refuses_what_it_cannot_read(tmp_path: Path, ros_server: ServerProcess,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    code = client_cli.main(["play-rosbag", str(tmp_path / "none"), "--connect",
                            ros_server.endpoint, "--map", "round"])
    assert code == 2 and "no such bag" in capsys.readouterr().err
    bad = tmp_path / "typed"
    with Writer(bad, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/mcsm/landmarks", "std_msgs/msg/String", typestore=STORE)
        w.write(c, 1, STORE.serialize_cdr(STORE.types["std_msgs/msg/String"](data="x"),
                                          "std_msgs/msg/String"))
    code = client_cli.main(["play-rosbag", str(bad), "--connect", ros_server.endpoint,
                            "--map", "round"])
    assert code == 2 and "not nav_msgs/msg/Odometry" in capsys.readouterr().err
    # a bag without any of the input topics (an exported map, say) names the flags to use
    other = tmp_path / "other"
    with Writer(other, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
        w.write(c, 1, STORE.serialize_cdr(STORE.types["std_msgs/msg/String"](data="x"),
                                          "std_msgs/msg/String"))
    for extra in ([], ["--odometry-topic", "/nope"]):
        code = client_cli.main(["play-rosbag", str(other), "--connect", ros_server.endpoint,
                                "--map", "round", *extra])
        err = capsys.readouterr().err
        assert code == 2 and "has none of the input topics" in err, err
        assert "its topics: /chatter" in err and "--constraint-topic" in err


def test_export_rosbag_round_trip(tmp_path: Path, ros_server: ServerProcess,
                                  reference: Reference,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "map-bag"
    code = mcsm_cli.main(["export-rosbag", str(ros_server.record), "-o", str(out), "--map",
                          "ref"])
    assert code == 0, capsys.readouterr().err
    assert mcsm_cli.main(["export-rosbag", str(ros_server.record), "-o", str(out), "--map",
                          "ref"]) == 2  # exists
    assert "exists" in capsys.readouterr().err
    with MapClient(map="ref", connect=ros_server.endpoint) as c:
        info = c.info()
        frames = [f for comp in info.components.values() for f in comp]
        got: dict[str, list[object]] = {}
        assert len(list(out.glob("*.mcap"))) == 1 and (out / "metadata.yaml").is_file()
        with AnyReader([out], default_typestore=STORE) as r:
            for conn, _t, raw in r.messages():
                got.setdefault(conn.topic, []).append(r.deserialize(raw, conn.msgtype))
        assert sorted(got) == ["/mcsm/frames", "/mcsm/markers", "/mcsm/path", "/tf"]
        odo = {m.child_frame_id: m for m in got["/mcsm/frames"]}  # type: ignore[attr-defined]
        assert sorted(odo) == sorted(set(frames) - {"x0"})
        for name in ("x7", f"x{len([f for f in frames if f.startswith('x')]) - 1}", "l3"):
            if name not in odo:
                continue
            mean, cov = c.marginal("x0", name)
            m = odo[name]
            assert m.header.frame_id == "map"
            p = m.pose.pose.position
            np.testing.assert_allclose([p.x, p.y, p.z], mean[:3], atol=1e-12)
            np.testing.assert_allclose(m.pose.covariance.reshape(6, 6),
                                       tangent_cov_to_ros(mean, cov), atol=1e-12)
        (tf,) = got["/tf"]
        assert {t.child_frame_id for t in tf.transforms} == set(frames)  # type: ignore
        (path,) = got["/mcsm/path"]
        assert [p.pose.position.x for p in path.poses][:2] == \
            pytest.approx([0.0, c.marginal("x0", "x1")[0][0]])  # type: ignore[attr-defined]
        (markers,) = got["/mcsm/markers"]
        assert len(markers.markers) == 1 + 2 * len(frames)  # type: ignore[attr-defined]
    # the exported frames play back into a map: same frames, the same means to sampling error
    code = client_cli.main(["play-rosbag", str(out), "--connect", ros_server.endpoint,
                            "--map", "round", "--constraint-topic", "/mcsm/frames",
                            "--no-progress"])
    assert code == 0, capsys.readouterr().err
    with MapClient(map="round", connect=ros_server.endpoint) as c:
        assert set(c.info().frames) == set(frames) - {"x0"} | {"map"}
        mean, cov = c.marginal("map", "l3") if "l3" in frames else c.marginal("map", "x1")
        want = odo["l3" if "l3" in frames else "x1"].pose.pose.position
        sd = np.sqrt(np.diag(cov)[:2])
        assert np.all(np.abs(mean[:2] - [want.x, want.y]) < 5 * sd / np.sqrt(8) + 1e-9)


def test_export_rosbag_stamp_at_and_force(tmp_path: Path, ros_server: ServerProcess,
                                          reference: Reference,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    """Every message is stamped with the receive time of the map's last input up to the
    exported seq (``--at`` included); ``--force`` replaces a bag only once the new one is
    written."""
    from mcsm.log.reader import RecordingReader
    from mcsm.log.topics import TOPIC_OPS
    from mcsm.viz.scene import load_map

    recv = {int(i.data["seq"]): int(i.data["recv_ns"])
            for i in RecordingReader(ros_server.record, edges=False)
            if i.topic in TOPIC_OPS and i.data.get("map") == "ref"}
    last = max(recv)
    for at, extra in ((last, []), (5, ["--at", "5"])):
        out = tmp_path / f"bag-{at}"
        assert mcsm_cli.main(["export-rosbag", str(ros_server.record), "-o", str(out), "--map",
                              "ref", *extra]) == 0, capsys.readouterr().err
        capsys.readouterr()
        with AnyReader([out], default_typestore=STORE) as r:
            msgs = [(c.topic, t, r.deserialize(raw, c.msgtype)) for c, t, raw in r.messages()]
        assert {t for _, t, _ in msgs} == {recv[at]}
        (tf,) = [m for topic, _, m in msgs if topic == "/tf"]
        st = tf.transforms[0].header.stamp  # type: ignore[attr-defined]
        assert st.sec * 10**9 + st.nanosec == recv[at]
    # --at: the map as it was after seq 5
    smap = load_map(ros_server.record, "ref", 5).map
    odo = {m.child_frame_id: m for topic, _, m in msgs if topic == "/mcsm/frames"}
    assert sorted(odo) == sorted(set(smap.frames()) - {"x0"})
    mean, _ = smap.marginal("x0", sorted(odo)[0])
    p = odo[sorted(odo)[0]].pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], mean[:3], atol=1e-12)
    # --force: a failed export leaves the old bag; a good one replaces it
    old = tmp_path / f"bag-{last}"
    before = sorted((f.name, f.stat().st_size) for f in old.iterdir())
    assert mcsm_cli.main(["export-rosbag", str(ros_server.record), "-o", str(old), "--map",
                          "nope", "--force"]) == 2
    assert sorted((f.name, f.stat().st_size) for f in old.iterdir()) == before
    assert mcsm_cli.main(["export-rosbag", str(ros_server.record), "-o", str(old), "--map",
                          "ref", "--at", "5", "--force"]) == 0
    with AnyReader([old], default_typestore=STORE) as r:
        assert {t for _, t, _ in r.messages()} == {recv[5]}
    assert sorted(f.name for f in tmp_path.iterdir()) == sorted([f"bag-{last}", "bag-5"])


def test_play_rosbag_counts_invalid_messages(tmp_path: Path, ros_server: ServerProcess,
                                             reference: Reference,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """A message the mapping refuses (equal frame ids) is counted, not sent: exit 1."""
    from mcsm.viz.rosmsg import odometry, rosbags_maker

    bad = odometry(rosbags_maker(STORE), 1, "x0", "x0", reference.messages[0].mean,
                   reference.messages[0].cov)
    bag = tmp_path / "bad"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        c = w.add_connection("/mcsm/constraints", "nav_msgs/msg/Odometry", typestore=STORE)
        w.write(c, 1, STORE.serialize_cdr(bad, "nav_msgs/msg/Odometry"))
    code, out = play(ros_server, bag, "round", capsys)
    assert code == 1 and out["invalid"] == 1 and out["applied"] == {}
    assert "both 'x0'" in str(out["first_error"])


def test_play_rosbag_exits_1_on_a_gate_rejection(tmp_path: Path, ros_server: ServerProcess,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A loop closure the gate refuses is counted (`rejected`) and the play exits 1; what was
    applied stays applied."""
    from mcsm.viz.rosmsg import odometry, rosbags_maker

    make = rosbags_maker(STORE)
    cov = np.diag([1e-4] * 6)
    moves = [("a", "b", [1.0, 0, 0]), ("b", "c", [1.0, 0, 0]), ("a", "c", [5.0, 0, 0])]
    bag = tmp_path / "closure"
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/mcsm/constraints", "nav_msgs/msg/Odometry", typestore=STORE)
        for k, (a, b, xyz) in enumerate(moves, start=1):
            msg = odometry(make, k * 10**9, a, b, np.array([*xyz, 1.0, 0, 0, 0]), cov)
            w.write(c, k * 10**9, STORE.serialize_cdr(msg, "nav_msgs/msg/Odometry"))
    code, out = play(ros_server, bag, "gated", capsys)
    assert code == 1 and out["rejected"] == 1, out
    assert out["applied"] == {"constraint": 2}, out
    with MapClient(map="gated", connect=ros_server.endpoint) as cl:
        assert cl.info().seq == 3  # the rejection is recorded and acknowledged too
