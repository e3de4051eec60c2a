"""``mcsm export g2o`` and ``mcsm export tum``: GTSAM's ``readG2o`` reads the graph back (vertices
at the map's means, every held constraint with the information of its samples, computed here
independently with scipy), and ``evo_ape`` (PyPI's ``evo``) runs on the trajectories."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import gtsam
import numpy as np
import pytest
from mcsm import StochasticMap, cli, wire
from mcsm.log.replay import replay
from mcsm.log.topics import decode_input
from mcsm.log.writer import Recorder
from mcsm.map.state import MapState
from mcsm.viz.scene import load_map
from scipy.spatial.transform import Rotation

from tests.helpers import gaussian_at
from tests.viz.conftest import Recording, build_map, planar_at


def body_cov(x: np.ndarray, about: Rotation | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Mean (t, q xyzw) and covariance over the body-frame (t, rotvec) of AT samples, with
    scipy only; rotations about ``about`` (default: scipy's mean rotation, the quaternions'
    chordal mean; mcsm's is the matrices', equal to second order in the spread)."""
    r = Rotation.from_quat(x[:, [4, 5, 6, 3]])
    rm = r.mean() if about is None else about
    t = x[:, :3].mean(axis=0)
    d = np.column_stack([rm.inv().apply(x[:, :3] - t), (rm.inv() * r).as_rotvec()])
    return np.concatenate([t, rm.as_quat()]), np.cov(d.T)


def point_cov(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return p.mean(axis=0), np.cov(p.T)


def frame_ids(g2o: Path) -> dict[str, int]:
    """Vertex id of each frame, from the CSV written beside the g2o file."""
    rows = Path(f"{g2o}.frames.csv").read_text().splitlines()
    assert rows[0] == "id,frame,kind,component"
    return {r.split(",")[1]: int(r.split(",")[0]) for r in rows[1:]}


def yaw(q_xyzw: np.ndarray) -> float:
    return float(Rotation.from_quat(q_xyzw).as_euler("xyz")[2])


def test_planar_g2o_reads_back_in_gtsam(recording: Recording, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    ops = recording.ops["default"]
    m = build_map(ops)
    out = tmp_path / "map.g2o"
    assert cli.main(["export", "g2o", str(recording.path), "-o", str(out), "--landmarks",
                     "br"]) == 0
    cap = capsys.readouterr()
    # 8 odometry + 4 landmark updates + q0 -> q1, q1 -> m0; x0 -> x8 was rejected by the gate;
    # x2 -> x3, x3 -> x4 and x3 -> l1 name the removed x3
    assert "planar (SE2): 15 vertices (5 landmarks), 11 edges (4 to landmarks)" in cap.out
    assert "3 constraints name frames no longer in the map" in cap.err
    assert "constraints the map does not hold, left out: 1 rejected" in cap.err
    ids = frame_ids(out)
    assert set(ids) == set(m.frames())  # type: ignore[attr-defined]
    graph, values = gtsam.readG2o(str(out), False)
    between = [graph.at(k) for k in range(graph.size())
               if isinstance(graph.at(k), gtsam.BetweenFactorPose2)]
    bearing = [graph.at(k) for k in range(graph.size())
               if isinstance(graph.at(k), gtsam.BearingRangeFactor2D)]
    assert len(between) == 7 and len(bearing) == 4 and graph.size() == 11
    for root in m.components():  # type: ignore[attr-defined]
        for f in m.component(root):  # type: ignore[attr-defined]
            mean, _ = m.marginal(root, f)  # type: ignore[attr-defined]
            if m.is_point(f):  # type: ignore[attr-defined]
                got = values.atPoint2(gtsam.symbol("l", ids[f]))
                np.testing.assert_allclose(got, mean[:2], rtol=1e-12, atol=1e-12)
            else:
                p = values.atPose2(ids[f])
                np.testing.assert_allclose([p.x(), p.y(), p.theta()],
                                           [mean[0], mean[1], yaw(mean[[4, 5, 6, 3]])],
                                           atol=1e-12)
    samples = {(a, b): x for kind, a, b, x in ops if kind == "update"}
    inv_ids = {i: n for n, i in ids.items()}
    for fa in between:
        a, b = (inv_ids[k] for k in fa.keys())
        z = fa.measured()
        mean, cov = body_cov(samples[(a, b)], Rotation.from_euler("z", z.theta()))
        # (scipy's mean rotation is the quaternions' chordal mean, mcsm's the matrices':
        # they differ at second order in the spread, 1e-7 rad here)
        np.testing.assert_allclose([z.x(), z.y(), z.theta()], [mean[0], mean[1],
                                                               yaw(mean[3:])], atol=1e-6)
        sel = np.ix_([0, 1, 5], [0, 1, 5])  # x y yaw of the planar constraint
        want = np.linalg.inv(cov[sel])
        np.testing.assert_allclose(fa.noiseModel().information(), want, rtol=1e-9)
    for fa in bearing:  # BR: bearing and range of the observation's mean
        a = inv_ids[fa.keys()[0]]
        b = inv_ids[gtsam.Symbol(fa.keys()[1]).index()]
        p, _ = point_cov(samples[(a, b)])
        z = fa.measured()
        assert z.range() == pytest.approx(np.hypot(p[0], p[1]), rel=1e-12)
        assert z.bearing().theta() == pytest.approx(np.arctan2(p[1], p[0]), abs=1e-12)
        # its sigmas: the point's covariance propagated to first order through (bearing, range)
        _, cov = point_cov(samples[(a, b)])
        x, y = p[0], p[1]
        r = np.hypot(x, y)
        jac = np.array([[-y / r**2, x / r**2], [x / r, y / r]])
        np.testing.assert_allclose(fa.noiseModel().sigmas(),
                                   np.sqrt(np.diag(jac @ cov[:2, :2] @ jac.T)), rtol=1e-9)
    # the default keeps g2o's own planar landmark edge: EDGE_SE2_XY with its information
    assert cli.main(["export", "g2o", str(recording.path), "-o", str(out)]) == 2
    assert "exists (--force overwrites it)" in capsys.readouterr().err
    assert cli.main(["export", "g2o", str(recording.path), "-o", str(out), "--force"]) == 0
    assert "GTSAM's readG2o skips" in capsys.readouterr().err
    rows = [ln.split() for ln in out.read_text().splitlines() if ln.startswith("EDGE_SE2_XY")]
    assert len(rows) == 4
    for row in rows:
        a, b = inv_ids[int(row[1])], inv_ids[int(row[2])]
        p, cov = point_cov(samples[(a, b)])
        np.testing.assert_allclose([float(v) for v in row[3:5]], p[:2], atol=1e-12)
        want = np.linalg.inv(cov[:2, :2])
        np.testing.assert_allclose([float(v) for v in row[5:]],
                                   [want[0, 0], want[0, 1], want[1, 1]], rtol=1e-6)


def three_d_recording(path: Path, n: int = 48) -> list[tuple[str, str, np.ndarray]]:
    """A 3-D map: a loop of four poses (a closure) and two point landmarks, recorded."""
    rng = np.random.default_rng(20261128)
    cov = np.diag([0.01, 0.02, 0.015, 0.001, 0.002, 0.0015])
    ops: list[tuple[str, str, np.ndarray]] = []
    for k in range(4):
        ops.append((f"p{k}", f"p{k + 1}", gaussian_at(rng, n, [1.0, 0.2 * k, 0.1],
                                                      [0.1, -0.05, np.pi / 2], cov)))
    ops.append(("p0", "p4", gaussian_at(rng, n, [0.0, 0.0, 0.4], [0.4, -0.2, 0.0], cov)))
    for k, (a, xyz) in enumerate([("p1", [2.0, 1.0, 0.5]), ("p3", [1.0, -1.0, 0.2])]):
        pts = np.asarray(xyz) + rng.multivariate_normal(np.zeros(3), np.diag(
            [0.04, 0.01, 0.02]), size=n)
        ops.append((a, f"l{k}", pts))
    rec = Recorder(path)
    st = MapState("default", StochasticMap(n, gate=None))
    rec.config(st, 100)
    for i, (a, b, x) in enumerate(ops):
        payload = wire.encode_update(f"r{i}", a, b, x)
        ack = st.apply("update", decode_input("update", payload, n), time_ns=10**9 + i)
        rec.input("update", st.name, ack.seq, 10**9 + i, "t", f"r{i}", payload)
    rec.close()
    return ops


def test_3d_g2o_reads_back_in_gtsam(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                    ) -> None:
    ops = three_d_recording(tmp_path / "rec.mcap")
    out = tmp_path / "map.g2o"
    assert cli.main(["export", "g2o", str(tmp_path / "rec.mcap"), "-o", str(out)]) == 0
    assert "3-D (SE3): 7 vertices (2 landmarks), 7 edges (2 to landmarks)" in \
        capsys.readouterr().out
    text = out.read_text()
    ids = frame_ids(out)
    inv_ids = {i: n for n, i in ids.items()}
    graph, values = gtsam.readG2o(str(out), True)
    kinds = [type(graph.at(k)).__name__ for k in range(graph.size())]
    assert kinds.count("BetweenFactorPose3") == 5 and kinds.count("BearingRangeFactor3D") == 2
    m = StochasticMap(48, gate=None)
    for a, b, x in ops:
        m.update(a, b, x)
    for f in m.frames():
        mean, _ = m.marginal("p0", f)
        if m.is_point(f):
            np.testing.assert_allclose(values.atPoint3(gtsam.symbol("l", ids[f])), mean[:3],
                                       atol=1e-12)
        else:
            p = values.atPose3(ids[f])
            np.testing.assert_allclose(p.translation(), mean[:3], atol=1e-12)
            q = p.rotation().toQuaternion()
            assert abs(np.dot([q.w(), q.x(), q.y(), q.z()], mean[3:])) == \
                pytest.approx(1.0, abs=1e-12)
    samples = {(a, b): x for a, b, x in ops}
    for k in range(graph.size()):
        fa = graph.at(k)
        if not isinstance(fa, gtsam.BetweenFactorPose3):
            continue
        a, b = (inv_ids[key] for key in fa.keys())
        z = fa.measured()
        mean, cov = body_cov(samples[(a, b)], Rotation.from_matrix(z.rotation().matrix()))
        info = np.linalg.inv(cov)
        scipy_mean = Rotation.from_quat(body_cov(samples[(a, b)])[0][3:])
        # the two chordal means differ at second order in the spread (variance ~2e-3 rad²)
        assert (scipy_mean.inv() * Rotation.from_matrix(z.rotation().matrix())).magnitude() \
            < 1e-5
        np.testing.assert_allclose(z.translation(), mean[:3], atol=1e-12)
        swap = [3, 4, 5, 0, 1, 2]  # GTSAM's order is (rotation, translation)
        np.testing.assert_allclose(fa.noiseModel().information(), info[np.ix_(swap, swap)],
                                   rtol=1e-9, atol=1e-9)
    # the landmark edges: g2o's EDGE_SE3_TRACKXYZ with the point's information
    rows = [ln.split() for ln in text.splitlines() if ln.startswith("EDGE_SE3_TRACKXYZ")]
    assert len(rows) == 2 and text.startswith("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1\n")
    for row in rows:
        p, cov = point_cov(samples[(inv_ids[int(row[1])], inv_ids[int(row[2])])])
        info = np.linalg.inv(cov)
        assert row[3] == "0"  # the identity sensor offset
        np.testing.assert_allclose([float(v) for v in row[4:7]], p, atol=1e-12)
        np.testing.assert_allclose([float(v) for v in row[7:]],
                                   info[np.triu_indices(3)], rtol=1e-6)


def truth_recording(path: Path, n: int = 32) -> dict[str, list[tuple[int, np.ndarray]]]:
    """Two planar robots (two components) with small odometry noise, each pose stamped;
    returns each robot's true poses (stamp, x y z qx qy qz qw)."""
    rng = np.random.default_rng(20261129)
    rec = Recorder(path)
    st = MapState("default", StochasticMap(n))
    rec.config(st, 100)
    truth: dict[str, list[tuple[int, np.ndarray]]] = {"A.x": [], "B.x": []}
    seq = 0
    for robot, step, turn in (("A.x", 1.0, 0.2), ("B.x", 0.7, -0.3)):
        pose = np.zeros(3)
        t0 = (10 if robot == "A.x" else 20) * 10**9
        truth[robot].append((t0, np.array([0, 0, 0, 0, 0, 0, 1.0])))
        for k in range(12):
            cov = np.diag([1e-4, 1e-4, 0.0, 0.0, 0.0, 1e-5])
            x = gaussian_at(rng, n, [step, 0.0, 0.0], [0.0, 0.0, turn], cov)
            c, s = np.cos(pose[2]), np.sin(pose[2])
            pose = pose + np.array([c * step, s * step, turn])
            stamp = t0 + (k + 1) * 250_000_000
            truth[robot].append((stamp, np.array([pose[0], pose[1], 0.0, 0.0, 0.0,
                                                  np.sin(pose[2] / 2), np.cos(pose[2] / 2)])))
            payload = wire.encode_update(f"{robot}{k}", f"{robot}{k}", f"{robot}{k + 1}", x,
                                         stamp_ns=stamp)
            seq += 1
            ack = st.apply("update", decode_input("update", payload, n), time_ns=seq)
            rec.input("update", st.name, ack.seq, seq, "t", f"{robot}{k}", payload)
    rec.close()
    return truth


def test_tum_trajectories_per_robot_and_evo_ape_reads_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    truth = truth_recording(tmp_path / "rec.mcap")
    prefix = tmp_path / "traj"
    assert cli.main(["export", "tum", str(tmp_path / "rec.mcap"), "-o", str(prefix)]) == 0
    out = capsys.readouterr().out
    # the roots A.x0, B.x0 are made by the update that makes x1: no time of their own
    assert (f"{prefix}-A.x.tum: robot A.x, 12 poses (A.x1 .. A.x12); left out, sharing a "
            "time with the next pose: A.x0") in out
    assert f"{prefix}-B.x.tum: robot B.x, 12 poses (B.x1 .. B.x12); left" in out
    smap = load_map(tmp_path / "rec.mcap", None).map
    rmse = {}
    for robot, poses in truth.items():
        est = np.loadtxt(f"{prefix}-{robot}.tum")
        assert est.shape == (12, 8)
        np.testing.assert_array_equal(est[:, 0], [t / 1e9 for t, _ in poses[1:]])  # stamps
        err = np.linalg.norm(est[:, 1:4] - np.array([v[:3] for _, v in poses[1:]]), axis=1)
        rmse[robot] = float(np.sqrt(np.mean(err**2)))
        assert 0 < rmse[robot] < 0.2  # small odometry noise over 12 m
        np.testing.assert_allclose(np.linalg.norm(est[:, 4:], axis=1), 1.0, atol=1e-12)
        # each row is the pose's final mean in its root's frame, the quaternion last (xyzw)
        for k, row in enumerate(est, start=1):
            mean, _ = smap.marginal(f"{robot}0", f"{robot}{k}")
            np.testing.assert_allclose(row[1:4], mean[:3], atol=1e-9)
            q = mean[3:] * np.sign(mean[3] * row[7] + np.dot(mean[4:], row[4:7]))
            np.testing.assert_allclose(row[4:], [q[1], q[2], q[3], q[0]], atol=1e-9)
    # evo's own reader and metric agree (one robot: evo takes a second to start)
    ref = tmp_path / "truth-A.x.tum"
    np.savetxt(ref, [[t / 1e9, *v] for t, v in truth["A.x"]], fmt="%.9f")
    env = dict(os.environ, HOME=str(tmp_path), MPLBACKEND="Agg")  # evo keeps settings in ~
    evo_ape = Path(sys.executable).with_name("evo_ape")
    r = subprocess.run([str(evo_ape), "tum", str(ref), f"{prefix}-A.x.tum", "--pose_relation",
                        "trans_part", "--no_warnings"], capture_output=True, text=True,
                       timeout=120, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    stat = dict(re.findall(r"^\s*(rmse|sse)\s+([0-9.e+-]+)$", r.stdout, re.M))
    assert float(stat["rmse"]) == pytest.approx(rmse["A.x"], abs=1e-6), r.stdout  # 6 digits
    assert float(stat["sse"]) / float(stat["rmse"]) ** 2 == pytest.approx(12, rel=1e-3)
    assert cli.main(["export", "tum", str(tmp_path / "rec.mcap"), "-o", str(prefix)]) == 2
    assert "exists (--force overwrites it)" in capsys.readouterr().err


def test_information_floors_the_covariances_eigenvalues() -> None:
    """A noise-free constraint stays finite: the eigenvalues below MIN_VARIANCE are raised
    to it, along the principal axes (a degenerate direction off the axes too); the others
    are inverted as they are."""
    from mcsm.viz.exchange import MIN_VARIANCE, information

    rot = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    cov = rot @ np.diag([0.04, 1e-20, 0.0]) @ rot.T  # two directions without noise
    info = information(cov)
    assert np.all(np.isfinite(info))
    np.testing.assert_allclose(rot.T @ info @ rot,
                               np.diag([25.0, 1 / MIN_VARIANCE, 1 / MIN_VARIANCE]), rtol=1e-9,
                               atol=1e-3)  # (1e-17 of the 1e12 entries: rounding)
    full = np.diag([0.01, 0.02, 0.03])
    np.testing.assert_allclose(information(full), np.linalg.inv(full), rtol=1e-12)


def test_g2o_keeps_what_the_map_holds_after_retract_and_reinstate(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A retracted closure is left out and counted, a reinstated one is an edge again; vertex
    ids are 0, 1, ... in the order the frames were added."""
    n = 32
    rng = np.random.default_rng(20261127)
    ups = [(f"u{k}", f"x{k}", f"x{k + 1}", planar_at(rng, n, [1.0, 0.0], np.pi / 2))
           for k in range(4)]
    ups += [("c1", "x0", "x4", planar_at(rng, n, [0.0, 0.0], 0.0)),
            ("c2", "x1", "x4", planar_at(rng, n, [0.0, -1.0], -np.pi / 2))]
    payloads = [("update", wire.encode_update(rid, a, b, x)) for rid, a, b, x in ups]
    payloads += [("retract", wire.encode_retract("t1", "c1")),
                 ("retract", wire.encode_retract("t2", "c2")),
                 ("reinstate", wire.encode_retract("t3", "c1"))]
    path = tmp_path / "r.mcap"
    rec = Recorder(path)
    st = MapState("default", StochasticMap(n, gate=None))
    rec.config(st, 100)
    for i, (op, payload) in enumerate(payloads):
        ack = st.apply(op, decode_input(op, payload, n), time_ns=10**9 + i)
        rec.input(op, st.name, ack.seq, 10**9 + i, "t", ack.request_id, payload)
    rec.close()
    out = tmp_path / "m.g2o"
    assert cli.main(["export", "g2o", str(path), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "constraints the map does not hold, left out: 1 retracted" in err, err
    ids = frame_ids(out)
    assert ids == {f"x{k}": k for k in range(5)}  # in the order the frames were added
    edges = sorted((int(r.split()[1]), int(r.split()[2]))
                   for r in out.read_text().splitlines() if r.startswith("EDGE_SE2 "))
    assert edges == [(0, 1), (0, 4), (1, 2), (2, 3), (3, 4)]  # c1 back, c2 left out
    # TUM: without a stamp_ns, a pose's time is its creating update's receive time
    assert cli.main(["export", "tum", str(path), "-o", str(tmp_path / "t")]) == 0
    capsys.readouterr()
    (traj,) = tmp_path.glob("t-*.tum")
    rows = np.loadtxt(traj)
    np.testing.assert_array_equal(rows[:, 0], [(10**9 + k) / 1e9 for k in range(4)])
    # a cut file: every complete input, and a note saying so
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 6 // 10])
    complete = replay(cut)
    assert complete.cut and 0 < complete.n_inputs < len(payloads)
    out = tmp_path / "cut.g2o"
    assert cli.main(["export", "g2o", str(cut), "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "recording is cut short (" in err and "exported every complete input" in err, err
    assert set(frame_ids(out)) == set(complete.states["default"].map.frames())
