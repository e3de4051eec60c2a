"""The compiled kernel against the numpy reference of the same math (the core before the
kernel, ``tests/core/numpy_reference.py``).

Over long runs, before every loop closure the reference is given the kernel map's exact state
and applies the same observation; the two results must agree to 1e-9 of the update's move
(what differs is only the order of additions, and the kernel's moments from shifted sums).
"""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap

from tests.core import device_cases
from tests.core import numpy_reference as ref
from tests.helpers import random_at

N = 64


def _reference_of(m: StochasticMap, opts: dict[str, object]) -> ref.StochasticMap:
    """A reference map holding exactly ``m``'s state."""
    return ref.from_snapshot(m.snapshot(), threads=1, **opts)


def _run(opts: dict[str, object], n_updates: int, seed: int) -> tuple[int, float]:
    """(loop closures compared, worst error relative to the move)."""
    rng = np.random.default_rng(seed)
    # the update alone (the reference has no relinearisation or re-centring)
    m = StochasticMap(N, threads=2, relinearize=None, **opts)  # type: ignore[arg-type]
    k, compared, worst = 0, 0, 0.0
    for step in range(n_updates):
        if step % 3 == 0 or k < 3:  # odometry: a new pose (and now and then a landmark)
            m.update(f"p{k}", f"p{k + 1}", random_at(rng, N, kind="cloud", t_sigma=0.2,
                                                      r_sigma=0.05))
            if k % 4 == 0:
                m.update(f"p{k}", f"l{k}", 1.0 + 0.3 * rng.standard_normal((N, 3)))
            k += 1
            continue
        a = int(rng.integers(0, k))
        if rng.random() < 0.3 and a // 4 * 4 < k:  # re-observe a landmark
            lm = f"l{a // 4 * 4}"
            x = m.query(f"p{k}", lm)[:, :3] + 0.05 * rng.standard_normal((N, 3))
            b_frame, a_frame = lm, f"p{k}"
        else:
            x = m.query(f"p{a}", f"p{k}")[rng.permutation(N)]
            a_frame, b_frame = f"p{a}", f"p{k}"
        r = _reference_of(m, opts)
        before = m.edges(a_frame)
        m.update(a_frame, b_frame, x)
        r.update(a_frame, b_frame, x)
        got, want = m.edges(a_frame), r.edges(a_frame)
        move = float(np.max(np.abs(want - before)))
        err = float(np.max(np.abs(got - want)))
        worst = max(worst, err / move)
        compared += 1
    return compared, worst


@pytest.mark.slow
@pytest.mark.parametrize(("opts", "n_updates", "tol"), [
    ({}, 1000, 1e-9),
    ({"gain": "endpoints", "shrink": None}, 300, 1e-9),
    ({"inflation": "adaptive"}, 300, 1e-9),
    ({"space": "quaternion", "analysis": "enkf", "shrink": None}, 200, 1e-9),
    ({"analysis": "denkf", "inflation": 1.01}, 200, 1e-9),
    # The endpoint gain's t-statistic shrink divides by the residual variance left by the
    # endpoint components, which for the endpoint frames themselves is a difference of nearly
    # equal numbers (the frames are almost fully explained): measured 2.4e-9 of the move at
    # worst, on the endpoint frames only; every other frame agrees to 1e-10.
    ({"gain": "endpoints", "inflation": 1.002}, 300, 1e-8),
])
def test_kernel_agrees_with_the_numpy_reference(opts: dict[str, object], n_updates: int,
                                                tol: float) -> None:
    compared, worst = _run(opts, n_updates, seed=20261123)
    assert compared >= n_updates // 2
    assert worst < tol, f"worst error {worst:.3g} of the update's move"


def test_paper_kernel_agrees_with_its_numpy_version() -> None:
    """method="paper" in the tangent chart: the kernel against mcsm.core.paper.paper_update
    (numpy), from the same state, pose-pose and point closures, 1e-9 of the move."""
    from mcsm.core import paper

    rng = np.random.default_rng(20261124)
    m = StochasticMap(N, method="paper", relinearize=None)
    for k in range(40):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, N, kind="cloud", t_sigma=0.2,
                                                  r_sigma=0.05))
        if k % 4 == 0:
            m.update(f"p{k}", f"l{k}", 1.0 + 0.3 * rng.standard_normal((N, 3)))
    compared, worst = 0, 0.0
    for step in range(60):
        a, b = (int(v) for v in rng.choice(40, 2, replace=False))
        if step % 3 == 0:
            lm = f"l{4 * (b // 4)}"
            x = m.query(f"p{a}", lm)[:, :3] + 0.05 * rng.standard_normal((N, 3))
            af, bf = f"p{a}", lm
        else:
            x = m.query(f"p{a}", f"p{b}")[rng.permutation(N)]
            af, bf = f"p{a}", f"p{b}"
        comp = m._comps[m._where[af]]
        want = paper.paper_update(comp, af, bf, x, x.shape[1] == 3, "tangent")
        before = comp.edges()[[comp.index[f] for f in want.frames]]
        m.update(af, bf, x)
        got = m._comps[m._where[af]]
        assert got.frames == want.frames
        move = float(np.max(np.abs(want.edges() - before)))
        worst = max(worst, float(np.max(np.abs(got.edges() - want.edges()))) / move)
        compared += 1
    assert compared == 60
    assert worst < 1e-9, f"worst error {worst:.3g} of the update's move"


@pytest.mark.parametrize("n", [50, 200, 1003])
def test_a_sample_opposite_its_frames_centre_is_moved_on_the_manifold(n: int) -> None:
    """The update that used to be refused ("pushed quaternions to zero") is applied: the
    collapsed sample is moved by its rotation step on the manifold (checked against the numpy
    reference, which writes the rescue again), every quaternion stays unit, and the sample
    comes back towards the others instead of staying opposite them."""
    m, obs = device_cases.opposite_sample_map(n)
    r = ref.from_snapshot(m.snapshot(), threads=1)
    before = m.edges("a")
    m.update("a", "b", obs)
    r.update("a", "b", obs)
    assert r.rescued == 1, "the linear move did not collapse: the case tests nothing"
    got, want = m.edges("a"), r.edges("a")
    assert np.max(np.abs(got - want)) < 1e-9 * np.max(np.abs(want - before))
    q = m.query("a", "b")[:, 3:]
    assert np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)) < 1e-15
    heading = 2.0 * np.arctan2(q[:, 3], q[:, 0])
    assert abs(heading[0] - np.median(heading)) < 1.5  # was 3 rad away
