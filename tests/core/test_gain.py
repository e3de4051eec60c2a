"""The joint update's two cross-covariance estimators (``gain="direct"`` / ``"endpoints"``)."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.core.quat import qexp
from mcsm.core.smap import Submap
from mcsm.errors import InvalidOperation

from tests.helpers import random_at

N = 64


def _chain(m: StochasticMap, rng: np.random.Generator, n_frames: int) -> None:
    for k in range(n_frames):
        m.update(f"x{k}", f"x{k + 1}", random_at(rng, m.n_samples, kind="cloud", t_sigma=0.1,
                                                  r_sigma=0.03))


def test_without_shrink_both_gains_agree_when_the_observation_is_linear_in_the_endpoints() -> None:
    """Observed from the root, the predicted observation is the other endpoint's own chart
    coordinates: chaining the regressions through the endpoints then gives back the sample
    cross-covariance, so the two estimators agree up to rounding."""
    maps = [StochasticMap(N, shrink=None, gain=g) for g in ("direct", "endpoints")]
    for m in maps:
        rng = np.random.default_rng(31001)
        _chain(m, rng, 6)
        m.update("x3", "l", 1.0 + 0.2 * rng.standard_normal((N, 3)))
        m.update("x0", "x6", random_at(rng, N, kind="cloud", t_sigma=0.1, r_sigma=0.03))
        m.update("x0", "l", 1.5 + 0.1 * rng.standard_normal((N, 3)))
    direct, endpoints = (m.edges("x0") for m in maps)
    np.testing.assert_allclose(endpoints, direct, rtol=0.0, atol=1e-10)
    assert maps[0].state_digest() != maps[1].state_digest()  # the option is part of the state


def _translation_only(rng: np.random.Generator, n: int, sd: tuple[float, float, float]) -> Submap:
    """root r; a ~ N(0, sa²); b ~ N(0, sb²) independent; x = a + N(0, se²): identity rotations."""
    sa, sb, se = sd
    a = sa * rng.standard_normal((n, 3))
    b = sb * rng.standard_normal((n, 3))
    x = a + se * rng.standard_normal((n, 3))
    edges = np.zeros((4, n, 7))
    edges[..., 3] = 1.0
    edges[1, :, :3], edges[2, :, :3], edges[3, :, :3] = a, b, x
    return Submap("r", ("r", "a", "b", "x"), (False,) * 4, edges)


def test_endpoints_gain_keeps_a_weak_but_well_determined_correlation() -> None:
    """Frame x is tied to endpoint a (σ_e = 0.02 m) but the loop a→b is dominated by b's spread:
    x's correlation with the observation is about 0.1, below the direct shrink's noise floor at
    N = 200, so ``gain="direct"`` drops x's share of the correction; ``"endpoints"`` judges x
    against what a does not explain and keeps it. Exact Kalman (linear-Gaussian, per axis):
    Δx = −σ_a² (z − ȳ) / (σ_a² + σ_b² + R)."""
    rng = np.random.default_rng(31002)
    n, trials = 200, 60
    sa, sb, se, sr = 0.1, 1.0, 0.02, 0.1
    innovation = 3.0
    exact = -sa**2 * innovation / (sa**2 + sb**2 + sr**2)
    moves: dict[str, list[float]] = {"direct": [], "endpoints": []}
    for _ in range(trials):
        sub = _translation_only(rng, n, (sa, sb, se))
        z = np.zeros((n, 7))
        z[:, 3] = 1.0
        z[:, :3] = sr * rng.standard_normal((n, 3))
        z[:, :3] += innovation - z[:, :3].mean(axis=0)
        z[:, :3] += sub.edges[2, :, :3].mean(axis=0) - sub.edges[1, :, :3].mean(axis=0)
        for gain in moves:
            m = StochasticMap(n, gain=gain, gate=None)  # a 3 m innovation on purpose
            m.import_component(sub)
            before = m.marginal("r", "x")[0][:3]
            m.update("a", "b", z)
            moves[gain].append(float(np.mean(m.marginal("r", "x")[0][:3] - before)))
    mean = {g: float(np.mean(v)) for g, v in moves.items()}
    # per trial the estimated move scatters by about σ_b σ_a / (√N S) · innovation ≈ 0.02 m
    # (measured: 0.028 m with the endpoint gain)
    tol = 4.0 * 0.03 / np.sqrt(trials)
    assert abs(mean["endpoints"] - exact) < 0.25 * abs(exact) + tol, (mean, exact)
    assert abs(mean["direct"]) < 0.5 * abs(exact), (mean, exact)


def test_planar_dead_dimensions_stay_exactly_zero_with_the_endpoint_gain() -> None:
    rng = np.random.default_rng(31003)
    n = 100
    m = StochasticMap(n, gain="endpoints", inflation="adaptive")

    def planar(x: float, y: float, yaw: float, sd: float) -> np.ndarray:
        d = np.array([x, y, yaw]) + sd * rng.standard_normal((n, 3))
        out = np.zeros((n, 7))
        out[:, :2] = d[:, :2]
        out[:, 3:] = qexp(np.c_[np.zeros((n, 2)), d[:, 2]])
        return out

    for k in range(30):
        m.update(f"p{k}", f"p{k + 1}", planar(1.0, 0.0, 0.2, 0.02))
    for k in range(10):
        m.update(f"p{k}", f"p{k + 20}", m.query(f"p{k}", f"p{k + 20}")[rng.permutation(n)])
        m.update(f"p{k + 5}", f"l{k % 3}", 2.0 + 0.1 * rng.standard_normal((n, 3)) * [1, 1, 0])
    e = m.edges("p0")
    assert np.isfinite(e).all()
    full = ~np.array([m.is_point(f) for f in m.component("p0")])
    assert not np.any(e[full][..., [2, 4, 5]])


@pytest.mark.parametrize(("opts", "match"), [({"gain": "exact"}, "gain must be one of"),
                                             ({"gain": "endpoints", "space": "quaternion"},
                                              "tangent space only")])
def test_bad_gain_options_are_refused(opts: dict[str, object], match: str) -> None:
    with pytest.raises(InvalidOperation, match=match):
        StochasticMap(N, **opts)  # type: ignore[arg-type]


def test_gain_round_trips_through_options() -> None:
    m = StochasticMap(N, gain="endpoints", inflation="adaptive")
    assert m.options()["gain"] == "endpoints"
    assert StochasticMap.from_options(m.options()).options() == m.options()
    legacy = {k: v for k, v in StochasticMap(N).options().items() if k != "gain"}
    assert StochasticMap.from_options(legacy).gain == "direct"  # recordings made before gain
