"""The pictures ``make run`` ends with, and the magnified panel of a wide map."""

from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np
from mcap.reader import make_reader
from mcsm import StochasticMap
from mcsm.viz.plot import INSET_RATIO, plot_map
from mcsm.viz.scene import map_view
from mcsm_client.demo import draw_map

from tests.viz.conftest import Recording, planar_at, planar_point

matplotlib.use("Agg")


def test_draw_map_writes_truth_scene_and_png(recording: Recording, tmp_path: Path) -> None:
    lines: list[str] = []
    files = draw_map(recording.path, tmp_path, truth=[("l0", 1.0, 1.0), ("x8", 2.0, 0.5)],
                     every=4, log=lines.append)
    assert [p.name for p in files] == ["truth.csv", "scene.mcap", "map.png"]
    assert (tmp_path / "truth.csv").read_text() == "frame,x,y\nl0,1.0,1.0\nx8,2.0,0.5\n"
    with open(tmp_path / "scene.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
        assert summary is not None and summary.statistics is not None
        n_scene = sum(n for cid, n in summary.statistics.channel_message_counts.items()
                      if summary.channels[cid].topic == "/mcsm/default/scene")
    assert n_scene == 4  # seq 4, 8, 12, 16
    assert matplotlib.image.imread(tmp_path / "map.png").shape[0] > 300
    assert any("the map at seq 16 (15 frames, view top)" in s for s in lines)


def test_wide_map_gets_a_magnified_panel(tmp_path: Path) -> None:
    rng = np.random.default_rng(20261125)
    n = 200
    m = StochasticMap(n)
    for k in range(10):
        m.update(f"x{k}", f"x{k + 1}", planar_at(rng, n, [20.0, 0.0], 0.3, sigma_t=0.02,
                                                 sigma_yaw=0.001))
        m.update(f"x{k + 1}", f"l{k}", planar_point(rng, n, [3.0, 4.0], sigma=0.05))
    mv = map_view(m, seq=20)
    res = plot_map(mv, tmp_path / "wide.png")
    assert res.inset is not None
    x0, x1, y0, y1 = res.inset
    focus = max(res.ellipses.values(), key=lambda e: e.width)
    assert x0 < focus.center[0] < x1 and y0 < focus.center[1] < y1
    assert x1 - x0 >= 2 * focus.width  # the whole largest ellipse fits in the panel
    pos = np.array([f.position[:2] for f in mv.frames])
    assert float(np.ptp(pos, axis=0).max()) > INSET_RATIO * focus.width
    # a compact map gets none
    small = plot_map(map_view(StochasticMap(n), seq=0), tmp_path / "empty.png")
    assert small.inset is None and small.ellipses == {}
