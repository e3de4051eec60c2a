"""``mcsm export-foxglove``: an indexed MCAP scene with foxglove's schemas whose ellipsoids are
the replayed map's 95 % regions."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import SeekingReader, make_reader
from mcsm import cli
from mcsm.log.reader import RecordingReader
from mcsm.viz.foxglove_scene import export_foxglove

from tests.viz.conftest import N, Recording, build_map
from tests.viz.foxglove_util import check_scene_against_map, message_class

SCHEMAS = {"/mcsm/default/scene": "foxglove.SceneUpdate",
           "/mcsm/default/tf": "foxglove.FrameTransforms",
           "/mcsm/default/samples": "foxglove.PointCloud"}
EXTRA = {"/mcsm/default/log": ("foxglove.Log", "protobuf", "protobuf"),
         "/mcsm/default/stats": ("mcsm.MapStats", "jsonschema", "json")}


def recv_times(path: Path, map_name: str) -> dict[int, int]:
    return {int(r.data["seq"]): int(r.data["recv_ns"]) for r in RecordingReader(path)
            if r.topic.startswith("/mcsm/in/") and r.data["map"] == map_name}


def test_export_reads_back_indexed_with_the_maps_ellipsoids(
        recording: Recording, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "scene.mcap"
    assert cli.main(["export-foxglove", str(recording.path), "-o", str(out), "--every",
                     "5"]) == 0
    assert "4 snapshots (every 5 operations) up to seq 16" in capsys.readouterr().out
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        assert isinstance(reader, SeekingReader)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes  # chunked and indexed
        channels = {c.topic: c for c in summary.channels.values()}
        assert set(channels) == set(SCHEMAS) | set(EXTRA)
        for topic, want in EXTRA.items():
            ch = channels[topic]
            schema = summary.schemas[ch.schema_id]
            assert (schema.name, schema.encoding, ch.message_encoding) == want
        log_cls = message_class("foxglove.Log",
                                summary.schemas[channels["/mcsm/default/log"].schema_id].data)
        classes = {}
        for topic, name in SCHEMAS.items():
            ch = channels[topic]
            schema = summary.schemas[ch.schema_id]
            assert (schema.name, schema.encoding, ch.message_encoding) == \
                (name, "protobuf", "protobuf")
            classes[topic] = message_class(name, schema.data)
        msgs = [(ch.topic, msg) for _s, ch, msg in reader.iter_messages()]
    by_topic: dict[str, list[object]] = {t: [] for t in [*SCHEMAS, *EXTRA]}
    for topic, msg in msgs:
        by_topic[topic].append(msg)
    assert [len(v) for v in by_topic.values()] == [4, 4, 4, 16, 16]  # a line per input
    times = recv_times(recording.path, "default")
    ops = recording.ops["default"]
    # the verdict log: one line per input at its receive time; the loop closure's verdict
    logs = [log_cls.FromString(m.data) for m in by_topic.pop("/mcsm/default/log")]  # type: ignore
    assert [lg.timestamp.ToNanoseconds() for lg in logs] == \
        [times[s] for s in range(1, 17)]
    closure = logs[12].message  # seq 13: the update x0 -> x8, which the gate refused
    assert closure.startswith("seq 13 update x0 -> x8: rejected (NIS "), closure
    assert " over 3 dof, threshold 11.3) id " in closure and logs[12].level == 3  # WARNING
    assert logs[11].level == 2  # INFO
    assert logs[13].message.startswith("seq 14 remove x3: remove")
    assert logs[0].message.startswith("seq 1 update x0 -> x1: new_component, accepted")
    stats = [json.loads(m.data) for m in by_topic.pop("/mcsm/default/stats")]  # type: ignore
    assert [s["seq"] for s in stats] == list(range(1, 17))
    assert stats[-1] == {"seq": 16, "frames": 15, "components": 2, "accepted": 14,
                         "rejected": 1, "pending": 0, "retracted": 0, "reinstated": 0,
                         "refused_requests": 0, "queue_length": 0}
    seqs = [5, 10, 15, 16]  # every 5th operation and the last one
    assert [m.log_time for m in by_topic["/mcsm/default/scene"]] == [times[s] for s in seqs]
    for seq, raw_scene, raw_tf, raw_cloud in zip(seqs, *by_topic.values(), strict=True):
        m = build_map(ops, seq)  # the map after the first `seq` operations, built in process
        scene = classes["/mcsm/default/scene"].FromString(raw_scene.data)  # type: ignore
        check_scene_against_map(scene, m)
        tf = classes["/mcsm/default/tf"].FromString(raw_tf.data)  # type: ignore
        roots = m.components()  # type: ignore[attr-defined]
        pairs = {(t.parent_frame_id, t.child_frame_id): t for t in tf.transforms}
        shift = {r: np.array([pairs[("mcsm@default", r)].translation.x, 0.0, 0.0])
                 for r in m.components()}  # type: ignore[attr-defined]
        assert shift[roots[0]][0] == 0.0 and all(  # components side by side, not stacked
            shift[r][0] > 0 for r in roots[1:])
        for r in roots:
            assert ("mcsm@default", r) in pairs
            for f in m.component(r):  # type: ignore[attr-defined]
                if f != r and not m.is_point(f):  # type: ignore[attr-defined]
                    t = pairs[(r, f)].translation
                    mean, _ = m.marginal(r, f)  # type: ignore[attr-defined]
                    np.testing.assert_allclose([t.x, t.y, t.z], mean[:3], rtol=1e-12)
                    q = pairs[(r, f)].rotation  # the mean rotation too (w x y z up to sign)
                    got = np.array([q.w, q.x, q.y, q.z])
                    np.testing.assert_allclose(got * np.sign(got @ mean[3:]), mean[3:],
                                               atol=1e-12)
        assert len(pairs) == len(roots) + sum(
            1 for r in roots for f in m.component(r)  # type: ignore[attr-defined]
            if f != r and not m.is_point(f))  # type: ignore[attr-defined]
        cloud = classes["/mcsm/default/samples"].FromString(raw_cloud.data)  # type: ignore
        assert cloud.frame_id == "mcsm@default" and cloud.point_stride == 16
        assert [f.name for f in cloud.fields] == ["x", "y", "z", "component"]
        pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 4)
        want = np.concatenate([m.query(r, f)[:, :3] + shift[r]  # type: ignore[attr-defined]
                               for r in roots for f in m.component(r)])  # type: ignore
        assert len(pts) == len(want) == m.n_frames * N  # type: ignore[attr-defined]
        np.testing.assert_allclose(np.sort(pts[:, 0]), np.sort(want[:, 0]), atol=1e-5)


def test_export_other_map_and_refusals(recording: Recording, tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "other.mcap"
    assert cli.main(["export-foxglove", str(recording.path), "-o", str(out), "--map", "other",
                     "--samples-per-frame", "0"]) == 0
    with open(out, "rb") as fh:
        summary = make_reader(fh).get_summary()
        assert summary is not None
        topics = {c.topic for c in summary.channels.values()}
        assert topics == {"/mcsm/other/scene", "/mcsm/other/tf", "/mcsm/other/log",
                          "/mcsm/other/stats"}  # no samples: no cloud
    assert "1 snapshot (every 1 operation) up to seq 1" in capsys.readouterr().out
    assert cli.main(["export-foxglove", str(recording.path), "-o", str(out), "--map",
                     "other"]) == 2
    assert "exists (--force overwrites it)" in capsys.readouterr().err
    assert cli.main(["export-foxglove", str(recording.path), "-o", str(out), "--every",
                     "0"]) == 2
    assert "--every must be at least 1" in capsys.readouterr().err


def test_export_default_every_and_a_cut_recording(recording: Recording, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "all.mcap"
    rep = export_foxglove(recording.path, out, map_name="default", samples_per_frame=0)
    assert rep.every == 1 and rep.snapshots == list(range(1, 17))  # 16 ops: K = ceil(16/100)
    # 250 operations: K = ceil(250 / 100) = 3, every 3rd and the last, 84 snapshots
    from tests.recording.test_recording import record_session

    long = tmp_path / "long.mcap"
    record_session(long, 8, 250, seed=20261132)
    many = export_foxglove(long, tmp_path / "long-scene.mcap", samples_per_frame=0)
    assert many.every == 3 and many.snapshots == [*range(3, 250, 3), 250]
    assert len(many.snapshots) == 84
    assert rep.final_view is not None and rep.final_view.seq == 16 and rep.notes == []
    # a copy cut in the middle (like a SIGKILLed server's file): every complete input, a warning
    data = recording.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    want_seq = max(int(r.data["seq"]) for r in RecordingReader(cut)
                    if r.topic.startswith("/mcsm/in/") and r.data["map"] == "default")
    assert 0 < want_seq < 16
    assert cli.main(["export-foxglove", str(cut), "-o", str(tmp_path / "c.mcap")]) == 0
    cap = capsys.readouterr()
    assert f"up to seq {want_seq};" in cap.out
    assert "warning: recording is cut short" in cap.err


def test_export_and_view_without_foxglove_name_the_extra(
        recording: Recording, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove -> ImportError
    out = tmp_path / "s.mcap"
    assert cli.main(["export-foxglove", str(recording.path), "-o", str(out)]) == 2
    want = "foxglove is not installed; install the extra: pip install 'mcsm[viz]'"
    assert capsys.readouterr().err.strip() == f"mcsm export-foxglove: {want}"
    assert not out.exists()
    assert cli.main(["view", "--connect", "tcp/127.0.0.1:9", "--timeout", "1"]) == 2
    assert capsys.readouterr().err.strip() == f"mcsm view: {want}"


def test_export_of_a_recording_with_state_snapshots(tmp_path: Path) -> None:
    """A recording holding state snapshots (mcsm serve --disk-snapshot-every) exports: the
    snapshots are verified by replay and draw nothing of their own."""
    from mcsm import StochasticMap, wire
    from mcsm.log.topics import decode_input
    from mcsm.log.writer import Recorder
    from mcsm.map.state import MapState

    from tests.helpers import random_at

    rng = np.random.default_rng(9)
    path = tmp_path / "snap.mcap"
    rec = Recorder(path)
    st = MapState("default", StochasticMap(16))
    rec.config(st, 100)
    for i in range(6):
        payload = wire.encode_update(f"i{i}", f"p{i}", f"p{i + 1}",
                                     random_at(rng, 16, kind="cloud", t_sigma=0.2))
        ack = st.apply("update", decode_input("update", payload, 16))
        rec.input("update", st.name, ack.seq, 1_000 + i, "t", f"i{i}", payload)
        if ack.seq == 3:
            rec.snapshot(st)
    rec.close()
    rep = export_foxglove(path, tmp_path / "scene.mcap", every=2)
    assert (tmp_path / "scene.mcap").stat().st_size > 0
    assert rep is not None


def test_shipped_layout_matches_the_topics_the_view_and_export_write() -> None:
    """docs/foxglove-layout.json is ``foxglove_layout('default')``: its 3D panel follows the
    display frame, shows the scene and samples, its Log panel reads the verdicts and its Plot
    panel the counters, all topics and fields that exist."""
    from mcsm.viz.foxglove_scene import STATS_FIELDS, display_frame, foxglove_layout, topics

    shipped = json.loads((Path(__file__).parents[2] / "docs" / "foxglove-layout.json")
                         .read_text())
    assert shipped == foxglove_layout("default")
    cfg, t = shipped["configById"], topics("default")
    assert cfg["3D!mcsm"]["followTf"] == display_frame("default")
    assert set(cfg["3D!mcsm"]["topics"]) == {t["scene"], t["samples"]}
    assert cfg["RosOut!mcsm"]["topicToRender"] == t["log"]
    for p in cfg["Plot!mcsm"]["paths"]:
        topic, fieldname = p["value"].split(".")
        assert topic == t["stats"] and fieldname in STATS_FIELDS
    panels = json.dumps(shipped["layout"])
    assert all(f'"{k}"' in panels for k in cfg)  # every configured panel is placed


def test_commands_given_a_foxglove_export_say_not_an_mcsm_recording(
        recording: Recording, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """mcsm's own Foxglove scene is MCAP but not a recording: every command reading
    recordings says so in one line and exits 2 (replay said DAMAGED, exit 5; recover said
    "complete" and wrote an empty copy)."""
    scene = tmp_path / "scene.mcap"
    assert cli.main(["export", "foxglove", str(recording.path), "-o", str(scene),
                     "--samples-per-frame", "0"]) == 0
    capsys.readouterr()
    out = tmp_path / "copy.mcap"
    for argv in (["replay", str(scene)], ["inspect", str(scene)], ["cat", str(scene)],
                 ["recover", str(scene), "-o", str(out)], ["plot", str(scene), "-o",
                                                           str(tmp_path / "p.png")],
                 ["export", "g2o", str(scene), "-o", str(tmp_path / "m.g2o")]):
        assert cli.main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err, err
        assert f"{scene}: not an mcsm recording (its first message is on /mcsm/default/" in err
    assert not out.exists()
    assert cli.main(["replay", str(recording.path)]) == 0  # a recording still is one


@pytest.mark.parametrize("status, level", [("accepted", "Info"), ("reinstated", "Info"),
                                           ("pending", "Warning"), ("rejected", "Warning"),
                                           ("retracted", "Warning")])
def test_log_levels_of_verdicts(status: str, level: str) -> None:
    """docs/visualising.md: a held, refused or retracted constraint is a WARNING line."""
    from mcsm.viz.foxglove_scene import verdict_text

    got, text = verdict_text(7, "update", "loop_closure", ("x0", "x5"),
                             {"status": status, "nis": 3.2, "dof": 3, "threshold": 11.3},
                             "rid")
    assert got == level
    assert text.startswith("seq 7 update x0 -> x5: loop_closure") and text.endswith(" id rid")


def test_the_point_cloud_holds_100_samples_per_frame_by_default() -> None:
    """docs/visualising.md: samples of every frame, at most 100 per frame by default, evenly
    strided (N = 1000: every 10th row); 0 gives no cloud."""
    from mcsm import StochasticMap
    from mcsm.viz.foxglove_scene import build_snapshot
    from mcsm.viz.scene import map_view

    from tests.viz.conftest import planar_at

    rng = np.random.default_rng(20261131)
    m = StochasticMap(1000)
    for k in range(3):
        m.update(f"x{k}", f"x{k + 1}", planar_at(rng, 1000, [1.0, 0.0], 0.2))
    mv = map_view(m, map_name="default", seq=3, samples=True)
    snap = build_snapshot(mv, 1)
    schema = snap.cloud.get_schema()
    cloud = message_class(schema.name, schema.data).FromString(snap.cloud.encode())
    pts = np.frombuffer(cloud.data, dtype="<f4").reshape(-1, 4)
    assert len(pts) == 100 * m.n_frames
    x1 = m.query("x0", "x1")[::10, 0].astype(np.float32)
    assert any(np.array_equal(pts[i:i + 100, 0], x1) for i in range(0, len(pts), 100))
    assert build_snapshot(mv, 1, samples_per_frame=0).cloud is None
