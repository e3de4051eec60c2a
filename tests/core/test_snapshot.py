"""State snapshots (issue 16 §4): a restored snapshot plus the tail equals a full replay.

``StochasticMap.snapshot()`` / ``from_snapshot`` must give back the exact state (same
``state_digest``), so that restoring a snapshot taken after input k and re-applying inputs
k+1.. gives the bits of a map that applied every input from the start; and so that a map
rebuilt from a snapshot taken before input t, re-fed the later inputs without t, is the map
that never had t (the exact retraction of :mod:`mcsm_client.audit`).
"""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap

from experiments.posegraph_sim import sample_measurement, simulate_2d, simulate_3d

N = 64


def _inputs(planar: bool, seed: int, n_poses: int = 160) -> list[tuple[str, str, np.ndarray]]:
    """The updates of a short simulated pose graph (odometry and loop closures, in order),
    followed by a landmark seen three times (point closures)."""
    rng = np.random.default_rng(seed)
    graph = (simulate_2d if planar else simulate_3d)(n_poses, rng=rng, min_gap=30)
    out = [(f"p{i}", f"p{j}", sample_measurement(z, c, N, rng=rng))
           for (i, j), z, c in zip(graph.edges, graph.measurements, graph.covariances,
                                   strict=True)]
    for k in (10, 50, 150):
        pt = np.zeros((N, 3))
        pt[:, :2] = [1.0, 2.0] + 0.1 * rng.standard_normal((N, 2))
        out.append((f"p{k}", "l0", pt))
    assert graph.n_loops > 10
    return out


def _run(m: StochasticMap, inputs: list[tuple[str, str, np.ndarray]]) -> StochasticMap:
    for a, b, x in inputs:
        m.update(a, b, x)
    return m


OPTIONS = [
    {"gate": 0.99, "inflation": 1.002, "gain": "endpoints"},
    {"inflation": "adaptive"},  # the running NIS average is part of the state
    {"method": "paper"},
]


@pytest.mark.parametrize("options", OPTIONS, ids=["gated", "adaptive", "paper"])
@pytest.mark.parametrize("planar", [True, False], ids=["planar", "3d"])
def test_snapshot_then_tail_equals_full_replay(options: dict[str, object], planar: bool) -> None:
    inputs = _inputs(planar, 11 if planar else 12)
    full = _run(StochasticMap(N, **options), inputs)  # type: ignore[arg-type]
    for k in (0, 1, len(inputs) // 3, len(inputs) - 1):
        head = _run(StochasticMap(N, **options), inputs[:k])  # type: ignore[arg-type]
        snap = head.snapshot()
        copy = StochasticMap.from_snapshot(snap)
        assert copy.state_digest() == head.state_digest()
        assert copy.options() == head.options()
        _run(copy, inputs[k:])
        assert copy.state_digest() == full.state_digest(), k


def test_snapshot_is_a_copy() -> None:
    inputs = _inputs(True, 13)
    half = len(inputs) // 2
    m = _run(StochasticMap(N, gate=0.99), inputs[:half])
    snap = m.snapshot()
    digest = m.state_digest()
    _run(m, inputs[half:])  # keeps changing the map the snapshot came from
    assert StochasticMap.from_snapshot(snap).state_digest() == digest
    # and a restored map does not share storage with the snapshot either
    r = StochasticMap.from_snapshot(snap)
    _run(r, inputs[half:])
    assert StochasticMap.from_snapshot(snap).state_digest() == digest


def test_restore_and_replay_without_an_input_is_a_map_that_never_had_it() -> None:
    inputs = _inputs(False, 14)
    loops = [k for k, (a, b, _) in enumerate(inputs)
             if b.startswith("p") and int(b[1:]) - int(a[1:]) != 1]
    t = loops[len(loops) // 2]
    never = _run(StochasticMap(N, gate=0.99), inputs[:t] + inputs[t + 1:])
    snap = _run(StochasticMap(N, gate=0.99), inputs[:t - 5]).snapshot()
    retracted = _run(StochasticMap.from_snapshot(snap), inputs[t - 5:t] + inputs[t + 1:])
    assert retracted.state_digest() == never.state_digest()
    reinstated = _run(StochasticMap.from_snapshot(snap), inputs[t - 5:])
    assert reinstated.state_digest() == _run(StochasticMap(N, gate=0.99), inputs).state_digest()
    assert reinstated.state_digest() != never.state_digest()
