"""Relinearisation: the factor history, the kernel's solve against exact and independent
references, the redraw's moments, the history's bound, snapshots and digests."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.core import relin
from mcsm.core.quat import qmul, rotation_matrix
from mcsm.core.relinearize import Policy, _problem
from mcsm.errors import InvalidOperation, NumericalError
from mcsm_client.sampling import sample_planar
from scipy.optimize import least_squares

from tests.helpers import random_at

IDENTITY_Q = np.array([1.0, 0.0, 0.0, 0.0])


def translation_samples(rng: np.random.Generator, n: int, mean: list[float], sd: float
                        ) -> np.ndarray:
    """(n, 7) ATs with exact identity rotations and correlated Gaussian translations."""
    a = rng.standard_normal((3, 3)) * sd
    x = np.zeros((n, 7))
    x[:, :3] = np.asarray(mean) + rng.standard_normal((n, 3)) @ a.T
    x[:, 3] = 1.0
    return x


@pytest.mark.parametrize("spread", [1.0, 1.5])
def test_a_linear_gaussian_chain_relinearises_to_the_exact_posterior(spread: float) -> None:
    """Translation-only inputs (rotations exactly the identity, so no information on them):
    the problem is linear-Gaussian and the posterior of the recorded moments is exact. The
    redrawn edges' means equal it within 1e-9 and their sample covariance the exact one within
    4 standard errors (the redraw is second-order exact here, so far tighter); with a policy's
    ``spread`` (no automatic trigger) the covariance is ``spread**2`` times the exact one."""
    rng = np.random.default_rng(20261201)
    n = 1500
    m = StochasticMap(n, gate=None,
                      relinearize=None if spread == 1.0 else Policy(spread=spread))
    inputs: list[tuple[str, str, np.ndarray]] = []
    for a, b, mean in (("x0", "x1", [1, 0, 0]), ("x1", "x2", [1, 0.2, 0.1]),
                       ("x2", "x3", [0.8, 0.5, 0]), ("x3", "x4", [0, 1, -0.1]),
                       ("x0", "x3", [2.9, 0.6, 0.0]), ("x1", "x4", [1.7, 1.8, 0.1])):
        x = translation_samples(rng, n, mean, 0.05)
        inputs.append((a, b, x))
        m.update(a, b, x)
    for a, mean in (("x1", [0.5, 2.0, 0.3]), ("x3", [-1.3, 1.5, 0.2]), ("x4", [-1.4, 0.6, 0.3])):
        p = np.asarray(mean) + 0.1 * rng.standard_normal((n, 3))
        inputs.append((a, "l0", p))
        m.update(a, "l0", p)
    m.remove("x2")  # a removed frame: eliminated first, its information kept
    rep = m.relinearize()
    assert rep.components[0].frames == 5 and rep.components[0].variables == 6
    # exact posterior of t1..t4, l0 given t0 = 0: linear least squares on the moments
    idx = {"x1": 0, "x2": 1, "x3": 2, "x4": 3, "l0": 4}
    rows, rhs, weights = [], [], []
    for a, b, x in inputs:
        t = x[:, :3]
        info = np.linalg.inv(np.cov(t.T))
        blk = np.zeros((3, 15))
        if a in idx:
            blk[:, 3 * idx[a]: 3 * idx[a] + 3] = -np.eye(3)
        blk[:, 3 * idx[b]: 3 * idx[b] + 3] = np.eye(3)
        rows.append(blk)
        rhs.append(t.mean(axis=0))
        weights.append(info)
    h = sum(r.T @ w @ r for r, w in zip(rows, weights, strict=True))
    g = sum(r.T @ w @ z for r, w, z in zip(rows, weights, rhs, strict=True))
    cov = np.linalg.inv(h)
    mean = cov @ g
    kept = [0, 2, 3, 4]
    got = np.concatenate([m.query("x0", f)[:, :3] for f in ("x1", "x3", "x4", "l0")], axis=1)
    want_mean = np.concatenate([mean[3 * k: 3 * k + 3] for k in kept])
    sel = np.concatenate([np.arange(3 * k, 3 * k + 3) for k in kept])
    want_cov = cov[np.ix_(sel, sel)]
    assert np.max(np.abs(got.mean(axis=0) - want_mean)) < 1e-9
    sd = np.sqrt(want_cov**2 + np.outer(np.diag(want_cov), np.diag(want_cov))) / np.sqrt(n)
    want_cov = spread**2 * want_cov
    sd = spread**2 * sd
    assert np.all(np.abs(np.cov(got.T) - want_cov) < 4.0 * sd)
    # the rotations carried no information: they stay exactly the identity, no spread
    for f in ("x1", "x3", "x4", "l0"):
        assert np.array_equal(m.query("x0", f)[:, 3:], np.tile(IDENTITY_Q, (n, 1)))


def step_at(rng: np.random.Generator, n: int, planar: bool) -> np.ndarray:
    """An odometry-like AT: planar (x, y, yaw only) or a 3-D cloud."""
    if planar:
        mean = np.array([1.0, 0.2, 0.3]) + 0.1 * rng.standard_normal(3)
        return sample_planar(mean, np.diag([0.01, 0.01, 0.003]), n_samples=n, rng=rng)
    return random_at(rng, n, kind="cloud", t_sigma=0.1, r_sigma=0.05)


def _ref_residuals(x_all: np.ndarray, kinds: np.ndarray, fvars: np.ndarray, fz: np.ndarray,
                   fw: np.ndarray, fkind: np.ndarray) -> np.ndarray:
    """The factors' whitened errors, written independently of the kernel (numpy)."""
    out = []
    for k, (a, b), z, wp in zip(fkind, fvars, fz, fw, strict=True):
        m = 6 if k == 0 else 3
        w = np.zeros((m, m))
        w[np.tril_indices(m)] = wp[: m * (m + 1) // 2]
        ra = rotation_matrix(x_all[a, 3:])
        et = ra.T @ (x_all[b, :3] - x_all[a, :3]) - z[:3]
        if k == 1:
            out.append(w @ et)
            continue
        qh = qmul(x_all[a, 3:] * [1, -1, -1, -1], x_all[b, 3:])
        r = qmul(z[3:] * [1, -1, -1, -1], qh)
        er = 2.0 * np.sign(r[0] if r[0] != 0 else 1.0) * r[1:]
        out.append(w @ np.concatenate([et, er]))
    return np.concatenate(out)


def _rotvec_quat(v: np.ndarray) -> np.ndarray:
    th = np.linalg.norm(v)
    if th < 1e-12:
        return np.concatenate([[1.0], 0.5 * v])
    return np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * v / th])


@pytest.mark.parametrize("planar", [True, False])
def test_the_kernel_solve_agrees_with_an_independent_least_squares(planar: bool) -> None:
    """A small graph (poses, points, a loop, a removed pose): the kernel's Gauss-Newton
    solution and the kept variables' covariance against scipy's least squares on the same
    recorded moments, with the errors written again in numpy and an exact exponential map."""
    rng = np.random.default_rng(20261202 + planar)
    n = 400
    m = StochasticMap(n, gate=None, relinearize=None)
    for k in range(5):
        m.update(f"p{k}", f"p{k + 1}", step_at(rng, n, planar))
        if k % 2 == 0:
            pts = np.array([1.0, 0.5, 0.0 if planar else 0.3]) + 0.05 * rng.standard_normal(
                (n, 3)) * ([1, 1, 0] if planar else 1)
            m.update(f"p{k}", f"l{k}", pts)
    m.update("p0", "p5", m.query("p0", "p5")[rng.permutation(n)])
    m.update("p5", "l0", m.query("p5", "l0")[:, :3][rng.permutation(n)])
    m.remove("p2")
    h = m.factor_history
    assert h is not None
    cid = m._where["p0"]
    ids = h.group_vars(cid)
    fmask = h.vars["group"][h.factors["vars"][:, 0]] == cid
    prob = _problem(m, h, cid, ids, fmask, [], h.vars["alive"][ids].astype(np.uint8))
    x0 = prob.x.copy()
    with relin.solve(prob, max_iter=50, tol=1e-15) as sol:
        r_ours, _ = sol.marginal()
        assert sol.stats.active == ((0b011 << 6 | 0b100011) if planar else 0b111_111111)
        kept_stats = sol.stats
    # A re-centring's solve keeps no factor: the same solution bit for bit, one factorisation
    # fewer, and no marginal or redraw from it.
    x_kept = prob.x.copy()
    prob.x[:] = x0
    with relin.solve(prob, max_iter=50, tol=1e-15, keep_factor=False) as bare:
        assert np.array_equal(prob.x, x_kept)
        assert bare.stats.cost_after == kept_stats.cost_after
        assert bare.stats.factorisations == kept_stats.factorisations - 1
        with pytest.raises(NumericalError):
            bare.marginal()
        with pytest.raises(NumericalError):
            bare.redraw(np.zeros((8, 7, n)), np.full(len(ids), -1, dtype=np.int64), 1)
    free = np.flatnonzero(prob.vfixed == 0)
    kinds = prob.vkind
    local = np.searchsorted(ids, h.factors["vars"][fmask])

    pose_act = [k for k in range(6) if prob.pose_active >> k & 1]
    point_act = [k for k in range(3) if prob.point_active >> k & 1]

    def unpack(p: np.ndarray, base: np.ndarray) -> np.ndarray:
        x = base.copy()
        off = 0
        for v in free:
            act = pose_act if kinds[v] == 0 else point_act
            d = np.zeros(6)
            d[act] = p[off: off + len(act)]
            off += len(act)
            x[v, :3] = base[v, :3] + d[:3]
            if kinds[v] == 0:
                x[v, 3:] = qmul(base[v, 3:], _rotvec_quat(d[3:]))
        return x

    dims = sum(len(pose_act) if kinds[v] == 0 else len(point_act) for v in free)

    def fun(p: np.ndarray, base: np.ndarray) -> np.ndarray:
        return _ref_residuals(unpack(p, base), kinds, local, h.factors["z"][fmask],
                              h.factors["w"][fmask], h.factors["kind"][fmask])

    ref = least_squares(fun, np.zeros(dims), args=(x0,), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    x_ref = unpack(ref.x, x0)
    assert np.max(np.abs(x_ref[:, :3] - prob.x[:, :3])) < 1e-7
    dots = np.abs(np.sum(x_ref[:, 3:] * prob.x[:, 3:], axis=1))
    assert np.max(1.0 - dots) < 1e-12
    # covariance of the kept variables, the removed pose eliminated (full-dimension columns)
    jac = least_squares(fun, np.zeros(dims), args=(x_ref,), max_nfev=1).jac
    cov_ref = np.linalg.pinv(jac.T @ jac, rcond=1e-10)
    cols, ours, off, full = [], [], 0, 0
    for v in free:
        act = pose_act if kinds[v] == 0 else point_act
        if h.vars["alive"][ids[v]]:
            cols += list(range(off, off + len(act)))
            ours += [full + a for a in act]
            full += 6 if kinds[v] == 0 else 3
        off += len(act)
    cov_ref = cov_ref[np.ix_(cols, cols)]
    r_act = r_ours[:, ours]
    cov_ours = np.linalg.pinv(r_act.T @ r_act, rcond=1e-10)
    scale = np.sqrt(np.outer(np.diag(cov_ref), np.diag(cov_ref))) + 1e-30
    live = np.diag(cov_ref) > 1e-12
    assert np.max(np.abs(cov_ours - cov_ref)[np.ix_(live, live)] / scale[np.ix_(live, live)]
                  ) < 1e-5


def test_the_generator_is_standard_normal() -> None:
    z = relin.normals(12345, 0, 200_000)
    assert abs(z.mean()) < 4 / np.sqrt(len(z))
    assert abs(z.var() - 1.0) < 4 * np.sqrt(2 / len(z))
    assert abs(np.mean(z**4) - 3.0) < 0.1
    assert np.array_equal(relin.normals(12345, 100, 10), z[100:110])  # counter-based


def test_a_planar_component_stays_exactly_planar() -> None:
    rng = np.random.default_rng(20261203)
    n = 300
    m = StochasticMap(n, gate=None, relinearize=None)
    for k in range(8):
        m.update(f"p{k}", f"p{k + 1}", step_at(rng, n, True))
        m.update(f"p{k + 1}", f"l{k}", np.array([2.0, 1.0, 0.0]) + np.array(
            [0.1, 0.1, 0.0]) * rng.standard_normal((n, 3)))
    m.update("p0", "p8", m.query("p0", "p8")[rng.permutation(n)])
    m.remove("p3")
    rep = m.relinearize()
    assert rep.components[0].iterations >= 1
    e = m.edges("p0")
    assert np.all(e[..., 2] == 0.0) and np.all(e[..., 4] == 0.0) and np.all(e[..., 5] == 0.0)


def test_the_bounded_history_marginalises_exactly_in_the_linear_case() -> None:
    """A long translation-only chain with old poses removed: a history bound forces old
    removed frames into dense priors; in the linear case that loses nothing, so the
    relinearised map's means equal those of an unbounded history's within 1e-9."""
    rng = np.random.default_rng(20261204)
    n = 64
    maps = [StochasticMap(n, gate=None, relinearize=None, history=2**16),
            StochasticMap(n, gate=None, relinearize=None)]
    for k in range(420):
        x = translation_samples(rng, n, [1.0, 0.1 * np.sin(k / 9), 0.0], 0.02)
        p = np.array([3.0, 2.0, 0.5]) - np.array([k + 1.0, 0, 0]) + 0.05 * rng.standard_normal(
            (n, 3))
        for mm in maps:
            mm.update(f"x{k}", f"x{k + 1}", x)
            mm.update(f"x{k + 1}", "l", p)
            if k >= 1:
                mm.remove(f"x{k}")
    bounded, full = maps
    hb, hf = bounded.factor_history, full.factor_history
    assert hb is not None and hf is not None
    assert hb.n_marginalised > 0 and hb.priors and hb.nbytes() <= 2**16
    assert hf.n_marginalised == 0
    for mm in maps:
        mm.relinearize()
    for f in ("x420", "l"):
        assert np.max(np.abs(bounded.query("x0", f).mean(axis=0)
                             - full.query("x0", f).mean(axis=0))) < 1e-9
    snap = bounded.snapshot()
    assert StochasticMap.from_snapshot(snap).state_digest() == bounded.state_digest()


def test_history_options_snapshot_and_digest() -> None:
    rng = np.random.default_rng(20261205)
    n = 40
    m = StochasticMap(n, relinearize={"nis": 0.9, "gap": 5, "regate": 2})
    assert m.options()["relinearize"]["regate"] == 2 and "history" in m.options()
    default = StochasticMap(n).options()["relinearize"]  # the default: DEFAULT_POLICY
    assert (default["nis"], default["regate"], default["spread"]) == (0.95, 1, 1.3)
    for k in range(6):
        m.update(f"p{k}", f"p{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.2))
    before = m.state_digest()
    snap = m.snapshot()
    again = StochasticMap.from_snapshot(snap)
    assert again.state_digest() == before
    m.relinearize("p3")
    assert m.state_digest() != before
    again.relinearize("p3")
    assert again.state_digest() == m.state_digest()  # the redraw is a function of the state
    # an old recording's options (no history, no policy, no gate scale) rebuild such a map
    old = {k: v for k, v in m.options().items()
           if k not in ("history", "relinearize", "gate_scale")}
    legacy = StochasticMap.from_options(old)
    assert legacy.factor_history is None and legacy.policy is None
    assert legacy.relinearize().components == ()
    with pytest.raises(InvalidOperation):
        StochasticMap(n, history=None, relinearize={"nis": 0.9, "gap": 5})


def test_an_imported_component_is_not_relinearised_and_says_why() -> None:
    rng = np.random.default_rng(20261206)
    n = 40
    side = StochasticMap(n)
    for k in range(3):
        side.update(f"q{k}", f"q{k + 1}", random_at(rng, n, kind="cloud", t_sigma=0.2))
    m = StochasticMap(n)
    m.update("p0", "p1", random_at(rng, n, kind="cloud", t_sigma=0.2))
    m.import_component(side.export_component("q0"))
    before = m.edges("q0")
    rep = m.relinearize()
    skipped = {c.root: c.skipped for c in rep.components}
    assert "imported submap" in skipped["q0"] and skipped["p0"] == ""
    assert np.array_equal(m.edges("q0"), before)
    m.update("p1", "q2", random_at(rng, n, kind="cloud", t_sigma=0.2))  # a join taints
    assert "imported submap" in m.relinearize().components[0].skipped


def test_the_policy_spread_is_checked_and_kept_in_the_options() -> None:
    """``spread`` in [1, 2]: anything else is refused as the other fields are; 1 is left out
    of the plain form (the options of maps made before it are unchanged), any other value
    round-trips, and a map's options carry it."""
    for bad in (0.99, 2.5, "1.2", True, float("nan")):
        with pytest.raises(InvalidOperation, match="spread"):
            Policy(spread=bad)  # type: ignore[arg-type]
        with pytest.raises(InvalidOperation, match="spread"):
            Policy.from_plain({"regate": 1, "spread": bad})
    assert "spread" not in Policy(regate=6, gap=25).to_plain()
    p = Policy(nis=0.95, regate=1, gap=25, spread=1.15)
    assert Policy.from_plain(p.to_plain()) == p
    m = StochasticMap(20, relinearize={"regate": 1, "spread": 1.3})
    assert m.options()["relinearize"]["spread"] == 1.3
    assert StochasticMap.from_options(m.options()).policy == m.policy


def test_the_spread_stops_at_the_rotation_cap() -> None:
    """Two planar components redrawn with ``spread=1.3`` against the same maps redrawn with the
    posterior itself: the one whose rotations are tight (0.05 rad per step) gets exactly 1.3 x
    its deviations; in the one whose rotations are wide (0.4 rad per step, every pose's
    rotation RMS above :data:`relin.SPREAD_ROTATION_CAP`) the factor is lowered to 1 and its
    samples are the posterior's, bit for bit."""
    n = 400

    def build(spread: float) -> StochasticMap:
        m = StochasticMap(n, gate=None, relinearize=Policy(spread=spread))
        draw = np.random.default_rng(7)
        for prefix, yaw_sd in (("t", 0.05), ("w", 0.4)):
            for k in range(4):
                m.update(f"{prefix}{k}", f"{prefix}{k + 1}",
                         sample_planar(np.array([1.0, 0.1, 0.2]),
                                       np.diag([0.01, 0.01, yaw_sd**2]), n_samples=n, rng=draw))
        m.relinearize()
        return m

    def yaw_rms(x: np.ndarray) -> float:
        yaw = 2.0 * np.arctan2(x[:, 6], x[:, 3])
        return float(np.sqrt(np.mean((yaw - yaw.mean()) ** 2)))

    exact, wide = build(1.0), build(1.3)
    for k in range(1, 5):
        a, b = exact.query("t0", f"t{k}"), wide.query("t0", f"t{k}")
        da, db = a[:, :2] - a[:, :2].mean(axis=0), b[:, :2] - b[:, :2].mean(axis=0)
        assert np.allclose(db, 1.3 * da, rtol=1e-9, atol=1e-12)
        assert yaw_rms(b) == pytest.approx(1.3 * yaw_rms(a), rel=1e-3)  # chart: 2 sin(yaw / 2)
        w = wide.query("w0", f"w{k}")
        assert np.array_equal(exact.query("w0", f"w{k}"), w)
        assert yaw_rms(w) > relin.SPREAD_ROTATION_CAP


def test_trim_thresholds_follow_their_definition() -> None:
    """Per factor: the trim quantile for its live dimensions (the nonzero diagonal of its
    square-root information) if it is a gated closure, else 0 (the vectorised form against
    the definition, factor by factor)."""
    from mcsm.core.gate import chi2_quantile
    from mcsm.core.relinearize import TRIM_QUANTILE, _trim_thresholds

    rng = np.random.default_rng(20261126)
    n = 500
    robust = (rng.random(n) < 0.6).astype(np.uint8)
    kind = rng.integers(0, 2, n).astype(np.int32)
    w = rng.standard_normal((n, 21)) * (rng.random((n, 21)) < 0.7)
    got = _trim_thresholds(robust, w, kind)
    for i in range(n):
        diag = [0, 2, 5, 9, 14, 20] if kind[i] == 0 else [0, 2, 5]
        dof = int(np.count_nonzero(w[i, diag]))
        want = chi2_quantile(TRIM_QUANTILE, dof) if robust[i] and dof else 0.0
        assert got[i] == want


def _planar_q(th: float) -> np.ndarray:
    return np.array([np.cos(th / 2), 0.0, 0.0, np.sin(th / 2)])


def test_the_solve_crosses_a_long_chains_curved_valley() -> None:
    """A 200-pose planar chain with loose headings and one tight closure from its first pose to
    its last, from a start whose headings drifted (w10000's map at step 1500, in small): the
    whole Gauss-Newton step overshoots the curved valley and a damped one barely moves, so
    without the line search the solve stops far from the optimum. Exact measurements: the
    optimum is the truth, at cost 0, and the default 20 iterations reach it."""
    rng = np.random.default_rng(20261127)
    k, rot_sd, t_sd = 200, 0.05, 0.01
    dth = rot_sd * rng.standard_normal(k)
    truth = np.zeros((k + 1, 7))
    truth[0, 3] = 1.0
    start = truth.copy()
    th = th_start = 0.0
    drift = 0.01 + 0.02 * rng.standard_normal(k)
    for i in range(k):
        truth[i + 1, :3] = truth[i, :3] + [np.cos(th), np.sin(th), 0.0]
        start[i + 1, :3] = start[i, :3] + [np.cos(th_start), np.sin(th_start), 0.0]
        th, th_start = th + dth[i], th_start + dth[i] + drift[i]
        truth[i + 1, 3:], start[i + 1, 3:] = _planar_q(th), _planar_q(th_start)

    def packed(sd: list[float]) -> np.ndarray:
        return np.diag(1.0 / np.asarray(sd))[np.tril_indices(6)]

    fz = [np.r_[1.0, 0.0, 0.0, _planar_q(d)] for d in dth] + [truth[k]]
    fw = [packed([t_sd] * 3 + [rot_sd] * 3)] * k + [packed([0.01] * 6)]
    fv = [(i, i + 1) for i in range(k)] + [(0, k)]
    prob = relin.Problem(
        pose_active=0b100011, point_active=0b011, ftrim=None,
        vkind=np.zeros(k + 1, np.int32), vfixed=(np.arange(k + 1) == 0).astype(np.uint8),
        vkept=np.ones(k + 1, np.uint8), x=start,
        fkind=np.zeros(k + 1, np.int32), fvars=np.array(fv, np.int32), fz=np.array(fz),
        fw=np.array(fw), pvoff=np.zeros(1, np.int64), pvars=np.zeros(0, np.int32),
        pdoff=np.zeros(1, np.int64), prows=np.zeros(0, np.int64), pdata=np.zeros(0))
    with relin.solve(prob, max_iter=20, keep_factor=False) as sol:
        assert sol.stats.cost_before > 1e8
        assert sol.stats.cost_after < 1e-12
    assert np.max(np.abs(prob.x[:, :3] - truth[:, :3])) < 1e-7
    assert np.max(1.0 - np.abs(np.sum(prob.x[:, 3:] * truth[:, 3:], axis=1))) < 1e-12
