"""``mcsm plot``: a PNG of a replayed map whose drawn ellipses are the map's 95 % regions."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from mcsm import StochasticMap, cli
from mcsm.viz.plot import plot_map
from mcsm.viz.scene import is_planar, load_map, map_view
from scipy.stats import chi2

from tests.viz.conftest import Recording, build_map, planar_at

matplotlib.use("Agg")


def chi2_for(lam: np.ndarray) -> float:
    """χ²(0.95) for as many degrees of freedom as eigenvalues ``lam`` span (a planar map's
    side view spans 1, its top view 2)."""
    lam = np.clip(lam, 0, None)
    return float(chi2.ppf(0.95, max(1, int(np.count_nonzero(lam > 1e-12 * lam.max())))))


def expected_ellipses(m: object, axes: tuple[int, int]) -> dict[str, tuple[float, ...]]:
    """Centre and full axes of each frame's 95 % ellipse, from the samples with numpy/scipy."""
    out = {}
    for root in m.components():  # type: ignore[attr-defined]
        for f in m.component(root):  # type: ignore[attr-defined]
            xyz = m.query(root, f)[:, :3][:, list(axes)]  # type: ignore[attr-defined]
            lam = np.linalg.eigvalsh(np.cov(xyz.T))
            k = chi2_for(lam)
            lam[lam <= 1e-12 * lam.max()] = 0.0
            c = xyz.mean(axis=0)
            out[f] = (c[0], c[1], 2 * np.sqrt(k * max(lam[1], 0)), 2 * np.sqrt(k * max(lam[0], 0)))
    return out


def test_plot_map_draws_the_marginals_of_the_replayed_map(recording: Recording,
                                                          tmp_path: Path) -> None:
    loaded = load_map(recording.path)
    assert loaded.name == "default" and loaded.notes == []
    ops = recording.ops["default"]
    assert loaded.seq == loaded.last_seq == len(ops)
    mv = map_view(loaded.map, map_name=loaded.name, seq=loaded.seq, samples=True)
    assert is_planar(mv)
    res = plot_map(mv, tmp_path / "m.png", samples=True)
    assert res.view == "top"
    want = expected_ellipses(build_map(ops), (0, 1))
    assert set(res.ellipses) == set(want) and "x3" not in want  # x3 was removed
    # the second component is drawn to the right of the first (a display shift along x)
    assert res.offsets["x0"] == (0.0, 0.0, 0.0) and res.offsets["q0"][0] > 0
    comp = {f.name: f.component for f in mv.frames}
    for name, (cx, cy, w, h) in want.items():
        e = res.ellipses[name]
        dx = res.offsets[comp[name]][0]
        np.testing.assert_allclose([e.center[0] - dx, e.center[1], e.width, e.height],
                                   [cx, cy, w, h], rtol=1e-9, atol=1e-12, err_msg=name)
    assert any(e.width > 0.05 for e in res.ellipses.values())
    # one colour per component; the path runs through the pose frames in the order added
    assert set(res.colours) == {"x0", "q0"} and res.colours["x0"] != res.colours["q0"]
    assert res.paths == {"x0": ["x0", "x1", "x2", "x4", "x5", "x6", "x7", "x8"],
                         "q0": ["q0", "q1"]}
    # one robot per component here: x2 -> x4 joins over the removed x3
    assert res.robot_paths == {"x0": [["x0", "x1", "x2", "x4", "x5", "x6", "x7", "x8"]],
                               "q0": [["q0", "q1"]]}
    assert loaded.parents["x4"] == "x3" and loaded.parents["x1"] == "x0"
    assert res.n_sample_points == len(want) * 64  # N = 64 < 250: every sample is drawn
    img = matplotlib.image.imread(res.path)
    assert img.ndim == 3 and img.shape[0] > 300 and img.shape[1] > 300
    assert float(np.std(img[..., :3])) > 0.01  # not a blank canvas
    assert "N=64" in res.title and f"seq {len(ops)}:" in res.title
    assert f"{len(want)} frames (5 landmarks, 10 poses), 2 components" in res.title


def test_plot_at_seq_shows_the_past_map(recording: Recording, tmp_path: Path) -> None:
    ops = recording.ops["default"]
    loaded = load_map(recording.path, "default", at_seq=5)
    assert loaded.seq == 5
    past = build_map(ops, 5)
    assert loaded.map.frames() == past.frames()  # type: ignore[attr-defined]
    assert loaded.map.state_digest() == past.state_digest()  # type: ignore[attr-defined]
    res = plot_map(map_view(loaded.map, seq=5), tmp_path / "p.png", view="xz")
    assert res.view == "xz"
    want = expected_ellipses(past, (0, 2))
    for name, (cx, cz, w, _h) in want.items():
        e = res.ellipses[name]
        np.testing.assert_allclose([*e.center, e.width], [cx, cz, w], rtol=1e-9, atol=1e-12)


def test_plot_3d_and_truth(recording: Recording, tmp_path: Path) -> None:
    loaded = load_map(recording.path)
    mv = map_view(loaded.map, map_name="default", seq=loaded.seq)
    truth = {"l0": np.array([1.0, 1.0, 0.0]), "nowhere": np.zeros(3)}
    res = plot_map(mv, tmp_path / "t.png", view="3d", truth=truth)
    assert res.view == "3d" and len(res.ellipsoids) == len(mv.frames)
    assert res.truth_drawn == ["l0"] and res.truth_missing == ["nowhere"]
    for f in mv.frames:
        lam = np.clip(np.linalg.eigvalsh(f.cov[:3, :3]), 0, None)
        k = chi2_for(lam)
        lam[lam <= 1e-12 * lam.max()] = 0.0
        np.testing.assert_allclose(sorted(res.ellipsoids[f.name].sizes), 2 * np.sqrt(k * lam),
                                   atol=1e-12)


def run_cli(*args: str) -> tuple[int, str, str]:
    p = subprocess.run([sys.executable, "-m", "mcsm.cli", *args], capture_output=True,
                       text=True, timeout=300)
    return p.returncode, p.stdout, p.stderr


def test_cli_plot_writes_a_png(recording: Recording, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    truth = tmp_path / "truth.csv"
    truth.write_text("frame,x,y\nl0,1.2,0.9\n")
    out = tmp_path / "map.png"
    code, stdout, stderr = run_cli("plot", str(recording.path), "-o", str(out), "--samples",
                                   "--truth", str(truth))
    assert code == 0, stderr
    assert "map 'default' at seq 16 of 16, 15 frames, 2 components, view top" in stdout
    assert out.stat().st_size > 10_000
    assert matplotlib.image.imread(out).shape[2] in (3, 4)
    # every writer refuses an existing output unless --force
    assert cli.main(["plot", str(recording.path), "-o", str(out), "--map", "other"]) == 2
    assert capsys.readouterr().err.strip() == f"mcsm plot: output {out} exists (--force " \
        "overwrites it)"
    code, stdout, stderr = run_cli("plot", str(recording.path), "-o", str(out), "--map",
                                   "other", "--at", "1", "--view", "yz", "--force")
    assert code == 0, stderr
    assert "map 'other' at seq 1 of 1, 2 frames" in stdout


@pytest.mark.parametrize(("args", "needle"), [
    (["--map", "nope"], "has no map 'nope' (maps: default, other)"),
    (["--at", "99"], "has sequence numbers 1..16, not 99"),
    (["-o", "/nonexistent-dir/m.png"], "output folder /nonexistent-dir does not exist"),
    (["--truth", "/nonexistent.csv"], "cannot read ground truth"),
])
def test_cli_plot_user_mistakes(recording: Recording, tmp_path: Path, args: list[str],
                                needle: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["plot", str(recording.path), "-o", str(tmp_path / "x.png"), *args]
    if "-o" in args:
        argv = ["plot", str(recording.path), *args]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_cli_plot_missing_file_and_not_mcap(tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["plot", str(tmp_path / "none.mcap")]) == 2
    assert "no such recording" in capsys.readouterr().err
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    assert cli.main(["plot", str(junk), "-o", str(tmp_path / "j.png")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def test_cli_plot_without_matplotlib_names_the_extra(recording: Recording, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str]
                                                     ) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    assert cli.main(["plot", str(recording.path), "-o", str(tmp_path / "x.png")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("mcsm plot: matplotlib is not installed; install the extra: "
                   "pip install 'mcsm[viz]'")
    assert not (tmp_path / "x.png").exists()


def test_cli_plot_of_a_cut_recording_warns(recording: Recording, tmp_path: Path) -> None:
    data = recording.path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    code, stdout, stderr = run_cli("plot", str(cut), "-o", str(tmp_path / "c.png"))
    assert code == 0, stderr
    assert "mcsm plot: warning: recording is cut short" in stderr and "Traceback" not in stderr
    assert (tmp_path / "c.png").stat().st_size > 0


def test_plot_map_opens_no_window_and_leaves_pyplot_alone(tmp_path: Path) -> None:
    """In a fresh interpreter: drawing a map loads neither pyplot nor an interactive backend."""
    code = ("import sys, numpy as np; from mcsm import StochasticMap; "
            "from mcsm.viz.scene import map_view; from mcsm.viz.plot import plot_map; "
            "m = StochasticMap(8); x = np.zeros((8, 7)); x[:, 3] = 1; "
            "x[:, 0] = np.linspace(0.9, 1.1, 8); m.update('a', 'b', x); "
            f"r = plot_map(map_view(m), {str(tmp_path / 'w.png')!r}, view='3d'); "
            "print(sorted(k for k in sys.modules if k.startswith('matplotlib.pyplot') "
            "or k.startswith('matplotlib.backends.backend_') and 'agg' not in k))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env={**os.environ, "MPLBACKEND": "TkAgg"})
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
    assert (tmp_path / "w.png").stat().st_size > 0


def two_robots(n: int, steps: int, history: bool) -> tuple[object, dict[str, str] | None]:
    """Robots A and B drive two circles of ``steps`` poses each, B's map joined to A's by a
    rendezvous (one component), landmarks seen by both; with ``history`` the creating updates
    are recorded (as replay does), else the paths come from the frame names."""
    from mcsm import StochasticMap
    from mcsm.viz.layout import FrameHistory

    from tests.viz.conftest import planar_at, planar_point

    rng = np.random.default_rng(20261127)
    m = StochasticMap(n)
    h = FrameHistory()

    def up(a: str, b: str, x: np.ndarray) -> None:
        m.update(a, b, x)
        h.observe("update", (a, b), m)

    for k in range(steps):
        up(f"A.x{k}", f"A.x{k + 1}", planar_at(rng, n, [1.0, 0.0], 2 * np.pi / steps,
                                                 sigma_t=0.01, sigma_yaw=0.002))
        up(f"B.x{k}", f"B.x{k + 1}", planar_at(rng, n, [0.8, 0.0], -2 * np.pi / steps,
                                                 sigma_t=0.01, sigma_yaw=0.002))
        if k % 25 == 0:
            up(f"A.x{k + 1}", f"l{k}", planar_point(rng, n, [0.5, 2.0], sigma=0.05))
    up("A.x0", "B.x0", planar_at(rng, n, [0.0, -5.0], 0.0, sigma_t=0.01, sigma_yaw=0.002))
    return m, (h.parent if history else None)


def test_two_robots_draw_two_paths_thinned_with_a_legend(tmp_path: Path) -> None:
    """Paths from the creating updates (as replay records them) and, without that history
    (a live view), from the frame names: the same two paths either way."""
    from mcsm.viz.plot import MAX_POSE_ELLIPSES

    steps = 200  # 402 poses: every dashed ellipse drawn made a solid ring
    m, parents = two_robots(16, steps, True)
    for history in (True, False):
        mv = map_view(m, seq=1, parents=parents if history else None)  # type: ignore[arg-type]
        assert len(mv.components) == 1
        res = plot_map(mv, tmp_path / f"two-{history}.png")
        (paths,) = res.robot_paths.values()
        assert sorted(p[0] for p in paths) == ["A.x0", "B.x0"]
        assert sorted(len(p) for p in paths) == [steps + 1, steps + 1]
        for p in paths:  # each path is one robot's chain in order, never a zig-zag
            robot = p[0].split(".")[0]
            assert p == [f"{robot}.x{k}" for k in range(steps + 1)]
        assert len(res.drawn_pose_ellipses) <= 2 * MAX_POSE_ELLIPSES
        assert {"A.x0", f"A.x{steps}", "B.x0", f"B.x{steps}"} <= set(res.drawn_pose_ellipses)
        assert res.pose_colours["A.x5"] != res.pose_colours["B.x5"]  # one colour per robot
        assert any(s.startswith(f"path A.x0 \u2192 A.x{steps} ({steps + 1} poses, ")
                   for s in res.legend)
        assert any(s.startswith(f"path B.x0 \u2192 B.x{steps} ({steps + 1} poses, ")
                   for s in res.legend)
        assert any(s.startswith(f"component A.x0: 8 landmarks, {2 * steps + 2} poses")
                   for s in res.legend)


def test_auto_view_is_top_for_a_planar_map_and_3d_otherwise(recording: Recording,
                                                            tmp_path: Path) -> None:
    from tests.viz.test_exchange import three_d_recording

    flat = load_map(recording.path)
    assert plot_map(map_view(flat.map, map_name="default", seq=flat.seq),
                    tmp_path / "flat.png").view == "top"
    three_d_recording(tmp_path / "3d.mcap")
    solid = load_map(tmp_path / "3d.mcap")
    assert plot_map(map_view(solid.map, map_name="default", seq=solid.seq),
                    tmp_path / "solid.png").view == "3d"


def test_cli_plot_of_a_diverging_recording_warns(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A recording whose replay diverges (a checkpoint's digest tampered with) is drawn as
    replayed up to there, with a warning naming the divergence."""
    from tests.recording.test_recording import _rewrite

    shipped = Path(__file__).parents[2] / "recordings" / "loop-small.mcap"
    bad = tmp_path / "diverged.mcap"
    _rewrite(shipped, bad, "digest")  # the checkpoint at seq 10 says another digest
    assert cli.main(["plot", str(bad), "-o", str(tmp_path / "d.png")]) == 0
    err = capsys.readouterr().err
    assert "mcsm plot: warning: replay diverged from the recording; showing the map as " \
           "replayed up to there" in err and "seq 10" in err, err
    assert (tmp_path / "d.png").stat().st_size > 0


def test_map_choice_and_the_sample_cap(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                       ) -> None:
    """--map: a recording with several maps and no `default` must name one (exit 2 naming
    them), the only map needs no name; --samples draws at most 250 per frame, evenly strided
    rows."""
    shipped = Path(__file__).parents[2] / "recordings"
    out = tmp_path / "m.png"
    assert cli.main(["plot", str(shipped / "two-maps.mcap"), "-o", str(out)]) == 2
    assert "holds maps a, b: choose one with --map" in capsys.readouterr().err
    assert cli.main(["plot", str(shipped / "two-maps.mcap"), "-o", str(out), "--map", "b"]) == 0
    assert cli.main(["plot", str(shipped / "loop-small.mcap"), "-o", str(tmp_path / "o.png")]) \
        == 0  # its only map, `default`
    rng = np.random.default_rng(20261130)
    m = StochasticMap(1000)
    for k in range(3):
        m.update(f"x{k}", f"x{k + 1}", planar_at(rng, 1000, [1.0, 0.0], 0.3))
    mv = map_view(m, map_name="default", seq=3, samples=True)
    res = plot_map(mv, tmp_path / "s.png", samples=True)
    drawn = [f for f in mv.frames if f.samples is not None]
    assert drawn and res.n_sample_points == 250 * len(drawn)
