"""The stochastic map: structure (cases I/II, remove, submaps), errors, determinism."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap, compound, invert
from mcsm.core.quat import qexp
from mcsm.errors import (
    FrameExists,
    InvalidOperation,
    InvalidSamples,
    McsmError,
    NotRelated,
    SampleCountMismatch,
    UnknownFrame,
)

from tests.helpers import assert_at_close, random_at

N = 64
METHODS = [("joint", "tangent"), ("joint", "quaternion"), ("paper", "tangent"),
           ("paper", "quaternion")]


def _cloud(rng: np.random.Generator, n: int = N) -> np.ndarray:
    return random_at(rng, n, kind="cloud", t_sigma=0.1, r_sigma=0.03)


def _check_star_consistency(m: StochasticMap) -> None:
    """query(a, b) equals compounding through the root, sample by sample, for all pairs."""
    for root in m.components():
        frames = m.component(root)
        for a in frames[:4]:
            for b in frames[-4:]:
                if a == b:
                    continue
                want = compound(invert(m.query(root, a)), m.query(root, b))
                assert_at_close(m.query(a, b), want, atol=1e-9)


@pytest.mark.parametrize(("a_is_root", "b_is_root"), [(True, True), (True, False),
                                                        (False, True), (False, False)])
def test_case_one_join_in_all_four_configurations(a_is_root: bool, b_is_root: bool) -> None:
    """PAPER Fig. 2: r1→l = (r1→a) ⊕ X ⊕ (r2→b)^R ⊕ (r2→l), checked per sample."""
    rng = np.random.default_rng(301)
    m = StochasticMap(N)
    m.update("r1", "a1", _cloud(rng))
    m.update("r2", "b1", _cloud(rng))
    m.update("b1", "b2", _cloud(rng))
    a = "r1" if a_is_root else "a1"
    b = "r2" if b_is_root else "b1"
    before = {f: m.query(m.root(f), f) for f in ("a1", "r2", "b1", "b2")}
    x = _cloud(rng)
    r = m.update(a, b, x)
    assert r.kind == "join" and r.component == "r1"
    assert m.components() == ["r1"] and sorted(m.component("r1")) == ["a1", "b1", "b2", "r1",
                                                                       "r2"]
    x_r1_a = m.query("r1", a)
    x_r2_b = before[b] if b != "r2" else np.tile([0, 0, 0, 1.0, 0, 0, 0], (N, 1))
    t = compound(compound(x_r1_a, x), invert(x_r2_b))
    for leaf in ("r2", "b1", "b2"):
        want = t if leaf == "r2" else compound(t, before[leaf])
        assert_at_close(m.query("r1", leaf), want, atol=1e-9)
    assert_at_close(m.query(a, b), x, atol=1e-9)
    _check_star_consistency(m)


@pytest.mark.parametrize(("method", "space"), METHODS)
def test_loop_closure_keeps_the_star_consistent(method: str, space: str) -> None:
    rng = np.random.default_rng(302)
    m = StochasticMap(N, method=method, space=space)
    for k in range(6):
        m.update(f"x{k}", f"x{k + 1}", _cloud(rng))
    m.update("x2", "p", rng.normal([2.0, 1.0, 0.0], 0.2, (N, 3)))
    r = m.update("x1", "x5", m.query("x1", "x5"))
    assert r.kind == "loop_closure"
    r = m.update("x4", "p", rng.normal(m.query("x4", "p")[:, :3].mean(0), 0.2, (N, 3)))
    assert r.kind == "loop_closure"
    assert all(np.isfinite(m.query("x0", f)).all() for f in m.frames())
    _check_star_consistency(m)
    # a point frame keeps its root's orientation exactly
    assert np.array_equal(m.query(m.root("p"), "p")[:, 3:], np.tile([1.0, 0, 0, 0], (N, 1)))


def test_remove_leaves_other_frames_bit_identical() -> None:
    rng = np.random.default_rng(303)
    m = StochasticMap(N)
    for k in range(5):
        m.update(f"x{k}", f"x{k + 1}", _cloud(rng))
    before = {f: m.query("x0", f) for f in m.frames() if f != "x0"}
    m.remove("x3")
    assert "x3" not in m and m.n_frames == 5
    for f, samples in before.items():
        if f != "x3":
            assert np.array_equal(m.query("x0", f), samples)
    # removing the root re-roots; relations between the others are kept (to rounding)
    rel = m.query("x2", "x5")
    m.remove("x0")
    assert m.root("x5") == "x1"
    assert_at_close(m.query("x2", "x5"), rel, atol=1e-9)
    for f in list(m.frames()):
        m.remove(f)
    assert m.n_frames == 0 and m.components() == []


def test_new_frames_in_every_direction() -> None:
    rng = np.random.default_rng(304)
    m = StochasticMap(N)
    x = _cloud(rng)
    assert m.update("a", "b", x).kind == "new_component"
    assert m.update("c", "b", x).kind == "new_frame"  # c is new: placed through X^R
    assert_at_close(m.query("c", "b"), x, atol=1e-9)
    assert_at_close(m.query("a", "c"), compound(x, invert(x)), atol=1e-9)
    r = m.update("b", "p", rng.normal(1.0, 0.1, (N, 3)))
    assert r.kind == "new_frame" and m.is_point("p")
    assert not m.is_point("a")


ERRORS = [
    ("self loop", "a", "a", lambda rng: _cloud(rng), InvalidOperation),
    ("wrong width", "a", "z", lambda rng: np.zeros((N, 6)), InvalidSamples),
    ("1-D", "a", "z", lambda rng: np.zeros(N * 7), InvalidSamples),
    ("N off by one", "a", "z", lambda rng: _cloud(rng, N + 1), SampleCountMismatch),
    ("NaN", "a", "z", lambda rng: np.where(np.arange(7) == 0, np.nan, _cloud(rng)), InvalidSamples),
    ("inf", "a", "z", lambda rng: np.where(np.arange(7) == 1, np.inf, _cloud(rng)), InvalidSamples),
    ("zero quaternion", "a", "z", lambda rng: np.zeros((N, 7)), InvalidSamples),
    ("non-unit quaternion", "a", "z", lambda rng: _cloud(rng) * 1.01, InvalidSamples),
    ("integer dtype", "a", "z", lambda rng: np.zeros((N, 7), dtype=int), InvalidSamples),
    ("not an array", "a", "z", lambda rng: [[0.0] * 7] * N, InvalidSamples),
    ("bad name", "a", "z//y", lambda rng: _cloud(rng), InvalidOperation),
    ("name with a newline", "a", "p\n", lambda rng: _cloud(rng), InvalidOperation),
    ("empty name", "", "a", lambda rng: _cloud(rng), InvalidOperation),
    ("point from unknown observer", "new", "a", lambda rng: np.zeros((N, 3)), InvalidOperation),
    ("point observer", "p", "z", lambda rng: np.zeros((N, 3)), InvalidOperation),
    ("full AT to a point", "a", "p", lambda rng: _cloud(rng), InvalidOperation),
    ("point samples to a full frame", "a", "b", lambda rng: np.zeros((N, 3)), InvalidOperation),
    ("point join of two components", "a", "d", lambda rng: np.zeros((N, 3)), InvalidOperation),
]


@pytest.mark.parametrize(("what", "a", "b", "make", "error"), ERRORS, ids=[e[0] for e in ERRORS])
def test_bad_updates_raise_typed_errors_and_change_nothing(what, a, b, make, error) -> None:
    rng = np.random.default_rng(305)
    m = StochasticMap(N)
    m.update("a", "b", _cloud(rng))
    m.update("b", "p", rng.normal(0.0, 0.1, (N, 3)))
    m.update("c", "d", _cloud(rng))
    m.update("d", "e", _cloud(rng))
    digest = m.state_digest()
    with pytest.raises(error) as info:
        m.update(a, b, make(rng))
    assert isinstance(info.value, McsmError) and info.value.message
    assert m.state_digest() == digest


def test_queries_and_removes_of_unknown_or_unrelated_frames() -> None:
    rng = np.random.default_rng(306)
    m = StochasticMap(N)
    m.update("a", "b", _cloud(rng))
    m.update("c", "d", _cloud(rng))
    digest = m.state_digest()
    with pytest.raises(UnknownFrame):
        m.query("a", "zz")
    with pytest.raises(UnknownFrame):
        m.remove("zz")
    with pytest.raises(NotRelated):
        m.marginal("a", "c")
    assert m.state_digest() == digest


def test_same_inputs_same_digest_and_options_matter() -> None:
    def build(**opts: object) -> str:
        rng = np.random.default_rng(307)
        m = StochasticMap(N, **opts)  # type: ignore[arg-type]
        for k in range(4):
            m.update(f"x{k}", f"x{k + 1}", _cloud(rng))
        m.update("x0", "x4", _cloud(rng))
        return m.state_digest()

    assert build() == build()
    assert build() != build(method="paper")
    assert build() != build(space="quaternion")


def test_export_and_import_a_component_round_trip() -> None:
    rng = np.random.default_rng(308)
    m = StochasticMap(N)
    m.update("a", "b", _cloud(rng))
    m.update("b", "p", rng.normal(0.0, 0.1, (N, 3)))
    sub = m.export_component("b")
    other = StochasticMap(N)
    other.update("z", "y", _cloud(rng))
    r = other.import_component(sub)
    assert r.kind == "import" and other.components() == ["z", "a"]
    for f in ("b", "p"):
        assert np.array_equal(other.query("a", f), m.query("a", f))
    with pytest.raises(FrameExists):
        other.import_component(sub)
    assert other.is_point("p")


@pytest.mark.parametrize(("method", "space"), METHODS)
def test_planar_and_3d_loops_past_180_degrees_stay_finite(method: str, space: str) -> None:
    """Planar use (zero-variance z, qx, qy) and full 3-D, headings through ±180°."""
    rng = np.random.default_rng(309)
    for planar in (True, False):
        m = StochasticMap(200, method=method, space=space)
        n_steps = 24
        step_rot = 2 * np.pi / n_steps
        for k in range(n_steps):
            x = np.zeros((200, 7))
            x[:, 0] = 1.0 + 0.02 * rng.standard_normal(200)
            x[:, 1] = 0.02 * rng.standard_normal(200)
            rv = np.zeros((200, 3))
            rv[:, 2] = step_rot + 0.01 * rng.standard_normal(200)
            if not planar:
                x[:, 2] = 0.02 * rng.standard_normal(200)
                rv[:, :2] = 0.01 * rng.standard_normal((200, 2))
            x[:, 3:] = qexp(rv)
            m.update(f"x{k}", f"x{k + 1}", x)
            if k % 6 == 5:
                centre = (m.query(f"x{k + 1}", "lm")[:, :3].mean(0) if "lm" in m
                          else np.array([2.0, 0.5, 0.0]))
                p = rng.normal(centre, 0.1, (200, 3))
                if planar:
                    p[:, 2] = 0.0
                m.update(f"x{k + 1}", "lm", p)
        # close the loop: back at the start
        close = np.zeros((200, 7))
        close[:, :2] = 0.01 * rng.standard_normal((200, 2))
        close[:, 3:] = qexp(np.c_[np.zeros((200, 2)), 0.005 * rng.standard_normal(200)])
        r = m.update(f"x{n_steps}", "x0", close)
        assert r.kind == "loop_closure"
        for f in m.frames():
            q = m.query("x0", f) if f != "x0" else m.query("x1", "x0")
            assert np.isfinite(q).all()
        mean, cov = m.marginal("x0", f"x{n_steps}")
        assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > -1e-12)
        if planar:
            assert np.allclose(m.query("x0", f"x{n_steps // 2}")[:, 2], 0.0, atol=1e-9)


def test_adaptive_inflation_reacts_to_surprising_loop_closures_only() -> None:
    """NIS ≈ 1 keeps the factor at 1; innovations far beyond the predicted spread raise it."""
    rng = np.random.default_rng(310)
    n = 400

    def build() -> StochasticMap:
        m = StochasticMap(n, inflation="adaptive", gate=None)  # surprising closures on purpose
        r = np.random.default_rng(311)
        for k in range(8):
            m.update(f"x{k}", f"x{k + 1}", random_at(r, n, kind="cloud", t_sigma=0.05,
                                                    r_sigma=0.01))
        return m

    honest, surprised = build(), build()
    for k in range(3):
        honest.update("x0", f"x{5 + k}", honest.query("x0", f"x{5 + k}")[rng.permutation(n)])
        far = surprised.query("x0", f"x{5 + k}")[rng.permutation(n)]
        far[:, :3] += 2.0  # 2 m off: tens of predicted σ
        surprised.update("x0", f"x{5 + k}", far)
    assert honest.nis_avg < 1.2
    assert surprised.nis_avg > 5.0
    assert honest.state_digest() != surprised.state_digest()
    with pytest.raises(InvalidOperation):
        StochasticMap(n, inflation="sometimes")


@pytest.mark.parametrize("space", ["tangent", "quaternion"])
def test_planar_loop_closures_count_three_dof_and_keep_dead_dimensions_zero(space: str) -> None:
    """Planar: z, qx, qy have exactly zero variance; the adaptive NIS counts the 3 live dof
    (not 6, nor 4 in the quaternion space, where the unit norm removes one of qw, qz).

    Each trial is a fresh two-pose map (odometry x0→x1, then an honest loop closure x0→x1 drawn
    around an independent measurement): the innovation's covariance is P + R, so the NIS per
    dof averages to 1 when the 3 live dof are counted (0.5 if the dead ones were too).
    """
    rng = np.random.default_rng(312)
    n, trials = 200, 600
    sd = np.array([0.05, 0.03, 0.02])  # x (m), y (m), yaw (rad) of odometry and loop closure

    def planar(mean: np.ndarray) -> np.ndarray:
        d = mean + sd * rng.standard_normal((n, 3))
        x = np.zeros((n, 7))
        x[:, :2] = d[:, :2]
        x[:, 3:] = qexp(np.c_[np.zeros((n, 2)), d[:, 2]])
        return x

    truth = np.array([1.0, 0.2, 0.3])
    nis = []
    for _ in range(trials):
        m = StochasticMap(n, space=space, inflation="adaptive")
        m.update("x0", "x1", planar(truth + sd * rng.standard_normal(3)))
        m.update("x0", "x1", planar(truth + sd * rng.standard_normal(3)))
        nis.append((m.nis_avg - 0.95) / 0.05)  # one closure: avg = 0.95 · 1 + 0.05 · NIS
        e = m.edges("x0")
        assert not np.any(e[..., [2, 4, 5]])  # dead dimensions exactly zero
    # NIS/dof of one closure is about chi2(3)/3: spread sqrt(2/3); plus the 1/N-order bias of
    # the sample S⁻¹ (about (N - 1) / (N - 5) - 1 = 2 %)
    assert abs(np.mean(nis) - 1.0) < 4.0 * np.sqrt(2.0 / 3.0) / np.sqrt(trials) + 0.03


@pytest.mark.parametrize(("method", "space"), METHODS)
def test_portable_is_false_only_for_paper_in_the_quaternion_space(method: str,
                                                                  space: str) -> None:
    assert StochasticMap(N, method=method, space=space).portable == \
        ((method, space) != ("paper", "quaternion"))


def test_results_are_copies_and_failing_calls_change_nothing() -> None:
    """query, edges and marginal hand out new arrays (writing to them leaves the map as it
    was); a failing import (a name taken, even only its second frame's), relinearize or
    export of an unknown frame leaves the map bit-identical."""
    rng = np.random.default_rng(309)
    m = StochasticMap(N)
    m.update("a", "b", _cloud(rng))
    m.update("b", "c", _cloud(rng))
    before = m.state_digest()
    for got in (m.query("a", "c"), m.query("a", "b"), m.edges("a"), m.marginal("a", "c")[0]):
        got[...] = 0.0
    assert m.state_digest() == before
    other = StochasticMap(N)
    other.update("q", "c", _cloud(rng))  # "c" taken: the submap's second frame
    sub = m.export_component("a")
    taken = other.state_digest()
    with pytest.raises(FrameExists):
        other.import_component(sub)
    assert other.state_digest() == taken and other.frames() == ["q", "c"]
    for call in (lambda: m.relinearize("nope"), lambda: m.export_component("nope")):
        with pytest.raises(McsmError):
            call()
        assert m.state_digest() == before
