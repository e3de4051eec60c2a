"""Re-centring (``Policy(recentre=True)``): after every accepted loop closure the map solves
the component over its history and moves each frame's samples so that their mean is the
solution, every sample keeping the filter's deviation."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.core.relinearize import Policy
from mcsm.errors import InvalidOperation

from tests.core.test_relinearize import translation_samples

FRAMES = ("x1", "x3", "x4", "l0")


def _chain(m: StochasticMap, n: int) -> list[tuple[str, str, np.ndarray]]:
    """Translation-only inputs (linear-Gaussian): odometry, two pose-pose closures, a removed
    frame, then a landmark seen three times; the last input is a closure."""
    rng = np.random.default_rng(20261126)
    inputs = []
    for a, b, mean in (("x0", "x1", [1, 0, 0]), ("x1", "x2", [1, 0.2, 0.1]),
                       ("x2", "x3", [0.8, 0.5, 0]), ("x3", "x4", [0, 1, -0.1]),
                       ("x0", "x3", [2.9, 0.6, 0.0]), ("x1", "x4", [1.7, 1.8, 0.1])):
        x = translation_samples(rng, n, mean, 0.05)
        inputs.append((a, b, x))
        m.update(a, b, x)
    m.remove("x2")
    for a, mean in (("x1", [0.5, 2.0, 0.3]), ("x3", [-1.3, 1.5, 0.2]), ("x4", [-1.4, 0.6, 0.3])):
        p = np.asarray(mean) + 0.1 * rng.standard_normal((n, 3))
        inputs.append((a, "l0", p))
        m.update(a, "l0", p)
    return inputs


def _exact_mean(inputs: list[tuple[str, str, np.ndarray]]) -> np.ndarray:
    """The posterior mean of x1, x3, x4, l0 given x0 = 0 from the inputs' moments."""
    idx = {"x1": 0, "x2": 1, "x3": 2, "x4": 3, "l0": 4}
    h, g = np.zeros((15, 15)), np.zeros(15)
    for a, b, x in inputs:
        t = x[:, :3]
        w = np.linalg.inv(np.cov(t.T))
        r = np.zeros((3, 15))
        if a in idx:
            r[:, 3 * idx[a]: 3 * idx[a] + 3] = -np.eye(3)
        r[:, 3 * idx[b]: 3 * idx[b] + 3] = np.eye(3)
        h += r.T @ w @ r
        g += r.T @ w @ t.mean(axis=0)
    mean = np.linalg.solve(h, g)
    return np.concatenate([mean[3 * k: 3 * k + 3] for k in (0, 2, 3, 4)])


def test_recentring_puts_the_means_at_the_exact_posterior_and_keeps_the_deviations() -> None:
    """On a linear-Gaussian chain the re-centred map's means equal the exact posterior mean
    within 1e-9 (the filter alone is off by far more), and every sample's deviation from its
    frame's mean is the filter's own (the same inputs without a policy), so the filter's joint
    covariance is kept."""
    n = 1200
    rc = StochasticMap(n, gate=None, relinearize=Policy(recentre=True))
    plain = StochasticMap(n, gate=None, relinearize=None)
    inputs = _chain(rc, n)
    _chain(plain, n)
    want = _exact_mean(inputs)
    got = np.concatenate([rc.query("x0", f)[:, :3] for f in FRAMES], axis=1)
    ref = np.concatenate([plain.query("x0", f)[:, :3] for f in FRAMES], axis=1)
    assert np.max(np.abs(got.mean(axis=0) - want)) < 1e-9
    assert np.max(np.abs(ref.mean(axis=0) - want)) > 1e-4  # the filter alone is not there
    dev, dev_ref = got - got.mean(axis=0), ref - ref.mean(axis=0)
    assert np.max(np.abs(dev - dev_ref)) < 1e-9
    for f in FRAMES:  # rotations carried no information: exactly the identity still
        q = rc.query("x0", f)[:, 3:]
        assert np.array_equal(q, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)))


def test_recentring_reports_every_closure_and_is_kept_in_the_options() -> None:
    """Each accepted closure not followed by a relinearisation is re-centred (trigger
    ``recentre`` in its result); the option round-trips, is left out when off, and anything
    but a bool is refused."""
    n = 300
    m = StochasticMap(n, gate=None, relinearize=Policy(recentre=True))
    rng = np.random.default_rng(3)
    for k in range(4):
        r = m.update(f"x{k}", f"x{k + 1}", translation_samples(rng, n, [1, 0, 0], 0.05))
        assert r.relin is None  # new frames: nothing to re-centre
    r = m.update("x0", "x4", translation_samples(rng, n, [4.1, 0.1, 0], 0.05))
    assert r.kind == "loop_closure" and r.relin is not None
    assert r.relin.trigger == "recentre" and r.relin.components[0].frames == 5
    assert m.options()["relinearize"]["recentre"] is True
    assert StochasticMap.from_options(m.options()).policy == m.policy
    assert "recentre" not in Policy(regate=1).to_plain()
    for bad in (1, "yes", None):
        with pytest.raises(InvalidOperation, match="recentre"):
            Policy(recentre=bad)  # type: ignore[arg-type]


def test_recentring_replays_through_a_snapshot() -> None:
    """Snapshot, restore and go on: the same digest as the map that never stopped; two
    runs of the same inputs give the same digest."""
    n = 64

    def run(stop: bool) -> str:
        m = StochasticMap(n, relinearize=Policy(nis=0.5, regate=1, gap=2, spread=1.3,
                                                recentre=True))
        rng = np.random.default_rng(11)
        for k in range(12):
            m.update(f"x{k}", f"x{k + 1}", translation_samples(rng, n, [1, 0.1, 0], 0.05))
            if k % 3 == 2:
                m.update("x0", f"x{k + 1}", m.query("x0", f"x{k + 1}")[rng.permutation(n)])
            if stop and k == 6:
                m = StochasticMap.from_snapshot(m.snapshot())
        return m.state_digest()

    assert run(False) == run(True) == run(False)


def test_recentring_readmits_a_refused_closure_once_the_map_agrees_with_it() -> None:
    """With ``readmit``, every re-centring re-checks the component's refused closures at its
    solution: a closure refused against the odometry alone is admitted (``readmitted`` 1 in
    the report, once) after a trusted closure moved the map to agree with it, and the map's
    means are then the exact posterior of all inputs, the admitted one included."""
    n = 400
    m = StochasticMap(n, relinearize=Policy(recentre=True, readmit=50))
    rng = np.random.default_rng(8)
    inputs = []
    for k in range(4):
        x = translation_samples(rng, n, [1, 0, 0], 0.05)
        inputs.append((f"x{k}", f"x{k + 1}", x))
        m.update(f"x{k}", f"x{k + 1}", x)
    far = translation_samples(rng, n, [4.0, 1.5, 0], 0.05)  # 1.5 m off the odometry's y
    r = m.update("x0", "x4", far)
    assert r.kind == "rejected" and r.relin is None
    agree = translation_samples(rng, n, [4.0, 1.5, 0], 0.005)  # tight: the map goes there
    r = m.update("x0", "x4", agree, trusted=True)
    assert r.kind == "loop_closure" and r.relin is not None
    assert r.relin.trigger == "recentre" and r.relin.components[0].readmitted == 1
    inputs += [("x0", "x4", far), ("x0", "x4", agree)]
    got = np.concatenate([m.query("x0", f"x{k}")[:, :3] for k in (1, 2, 3, 4)], axis=1)
    idx = {f"x{k}": k - 1 for k in range(1, 5)}
    h, g = np.zeros((12, 12)), np.zeros(12)
    for a, b, x in inputs:
        w = np.linalg.inv(np.cov(x[:, :3].T))
        rr = np.zeros((3, 12))
        if a in idx:
            rr[:, 3 * idx[a]: 3 * idx[a] + 3] = -np.eye(3)
        rr[:, 3 * idx[b]: 3 * idx[b] + 3] = np.eye(3)
        h += rr.T @ w @ rr
        g += rr.T @ w @ x[:, :3].mean(axis=0)
    assert np.max(np.abs(got.mean(axis=0) - np.linalg.solve(h, g))) < 1e-9
    r = m.update("x1", "x4", m.query("x1", "x4")[rng.permutation(n)])
    assert r.relin is not None and r.relin.components[0].readmitted == 0  # admitted once


def _buffer(rng: np.random.Generator, frames: int, n: int, planar: bool) -> np.ndarray:
    """A component buffer ``(frames + 2, 7, n)`` (two spare rows) of random poses: planar ones
    (z, qx, qy exactly 0) or 3-D ones."""
    buf = np.zeros((frames + 2, 7, n))
    buf[:, :2] = rng.normal(size=(frames + 2, 2, n))
    yaw = rng.normal(size=(frames + 2, n))
    buf[:, 3], buf[:, 6] = np.cos(yaw / 2), np.sin(yaw / 2)
    if not planar:
        buf[:, 2] = rng.normal(size=(frames + 2, n))
        q = rng.normal(size=(frames + 2, 4, n))
        buf[:, 3:] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return buf


@pytest.mark.parametrize("planar", [True, False])
def test_the_active_coordinates_follow_their_definition(planar: bool) -> None:
    """``relin.active`` (early exit, charts only where they can change the answer) gives the
    masks of its definition (``relin.spread``: a coordinate is active when a frame's samples
    differ from the first in it), also with frames held in some coordinates and points."""
    from mcsm.core import relin

    rng = np.random.default_rng(7)
    buf = _buffer(rng, 12, 33, planar)
    buf[3, 0] = buf[3, 0, 0]  # frame 3 holds x: others still vary in it
    buf[5, 1:3] = 1.5  # a point, pinned rotation; y and z held
    buf[5, 3:] = [[1.0], [0.0], [0.0], [0.0]]
    flags = np.zeros(len(buf), dtype=np.uint8)
    flags[5] = 1

    def reference(idx: np.ndarray) -> tuple[int, int]:
        sp = relin.spread(buf, idx, flags[idx])
        masks = []
        for point, width in ((False, 6), (True, 3)):
            sel = flags[idx].astype(bool) == point
            live = np.any(sp[sel] > 0.0, axis=0)[:width] if np.any(sel) else np.ones(width, bool)
            masks.append(int(sum(1 << k for k in range(width) if live[k])))
        return masks[0], masks[1]

    for idx in ([1, 2, 3, 4, 5], [5], [3], [4, 3], list(range(1, 12)), []):
        i = np.asarray(idx, dtype=np.int64)
        assert relin.active(buf, i, flags[i]) == reference(i), idx
    held = buf.copy()
    held[:, 1] = 0.25  # no frame varies in y
    buf = held
    i = np.arange(1, 12, dtype=np.int64)
    assert relin.active(buf, i, flags[i]) == reference(i)
    assert not relin.active(buf, i, flags[i])[0] & 0b10
    buf[0, 1] = rng.normal(size=buf.shape[-1])  # only the root varies in y: not active
    for perm in (np.arange(12), np.arange(12)[::-1], rng.permutation(12), np.array([0, 5])):
        # one pass: the means of every frame asked, the masks of those other than the root
        p = perm.astype(np.int64)
        means, masks = relin.means_active(buf, p, flags[p])
        assert means.tobytes() == relin.means(buf, p, flags[p]).tobytes()
        rest = p[p != 0]
        assert masks == relin.active(buf, rest, flags[rest]) == reference(rest), perm
        assert not masks[0] & 0b10 or not np.any(flags[rest] == 0)  # (no pose: every bit)


def test_the_recentring_kernel_gives_the_same_bits_copied_or_in_place() -> None:
    """``relin.recentre`` into another buffer (a host component: the spare) equals the same
    call in place (a host copy of a device component), and frames it does not move are copied
    unchanged but canonicalised."""
    from mcsm.core import kernel, relin

    rng = np.random.default_rng(8)
    src = _buffer(rng, 9, 41, planar=False)
    flags = np.zeros(len(src), dtype=np.uint8)
    idx = np.array([2, 4, 5, 7], dtype=np.int64)
    mu = relin.means(src, idx, flags[idx])
    target = mu + rng.normal(scale=0.1, size=mu.shape)
    target[:, 3:] /= np.linalg.norm(target[:, 3:], axis=1, keepdims=True)
    out = np.full_like(src, np.nan)
    assert relin.recentre(src, out, 9, flags, idx, mu, target) == relin.OK
    inplace = src.copy()
    assert relin.recentre(inplace, inplace, 9, flags, idx, mu, target) == relin.OK
    assert np.array_equal(out[:9], inplace[:9])
    np.testing.assert_allclose(relin.means(out, idx, flags[idx]), target, atol=1e-12)
    plain = src.copy()
    assert kernel.canonicalize_frames(plain, flags, 1, 9, False) == kernel.OK
    rest = [f for f in range(9) if f not in idx]
    assert np.array_equal(out[rest], plain[rest])
    assert np.isnan(out[9:]).all()  # rows past the component's length are not written


def _split(bounds: list[int]):  # type: ignore[no-untyped-def]
    """A runner over fixed ranges (their ends scaled into [0, m)), last range first: what a
    thread pool may do, in the worst order."""
    def run(fn, m):  # type: ignore[no-untyped-def]
        cuts = sorted({0, m, *(min(b, m) for b in bounds)})
        codes = [fn(lo, hi) for lo, hi in reversed(list(zip(cuts, cuts[1:], strict=False)))]
        return codes[::-1]
    return run


def test_the_recentring_passes_give_the_same_values_over_any_split_of_the_frames() -> None:
    """The shift and the means pass run over frame ranges on the map's threads: any split,
    run in any order, gives the bytes of one call, and the masks of a split where one part
    holds only points and another only poses are the whole's (a kind no part saw: every
    bit)."""
    from mcsm.core import relin

    rng = np.random.default_rng(9)
    src = _buffer(rng, 12, 37, planar=False)
    flags = np.zeros(len(src), dtype=np.uint8)
    flags[[8, 9, 10]] = 1
    src[[8, 9, 10], 3] = 1.0
    src[[8, 9, 10], 4:] = 0.0
    src[[8, 9, 10], 2] = 0.5  # the points never vary in z
    idx = np.array([2, 4, 5, 7, 9, 10], dtype=np.int64)
    mu = relin.means(src, idx, flags[idx])
    target = mu + rng.normal(scale=0.1, size=mu.shape)
    target[:, 3:] /= np.linalg.norm(target[:, 3:], axis=1, keepdims=True)
    whole = np.full_like(src, np.nan)
    assert relin.recentre(src, whole, 11, flags, idx, mu, target) == relin.OK
    order = np.array([3, 1, 7, 2, 5, 0, 9, 10, 8], dtype=np.int64)  # poses, then points
    means, masks = relin.means_active(src, order, flags[order])
    assert masks[1] == 0b011  # the points vary in x and y only
    points_only = np.array([8, 9], dtype=np.int64)
    assert relin.means_active(src, points_only, flags[points_only])[1][0] == 0b111111
    for bounds in ([1], [4, 5], [1, 2, 3, 6, 10], [6], list(range(1, 12))):
        split = np.full_like(src, np.nan)
        assert relin.recentre(src, split, 11, flags, idx, mu, target, _split(bounds)) == \
            relin.OK
        assert split[:11].tobytes() == whole[:11].tobytes(), bounds
        assert np.isnan(split[11:]).all()
        m2, k2 = relin.means_active(src, order, flags[order], _split(bounds))
        assert m2.tobytes() == means.tobytes() and k2 == masks, bounds
    bad = src.copy()
    bad[7, 0, 3] = np.inf
    out = np.empty_like(src)
    assert relin.recentre(bad, out, 11, flags, idx, mu, target, _split([2, 9])) == \
        relin.NONFINITE  # a range that failed is reported whichever range it was


def test_a_recentring_orders_its_solve_freely_and_finds_the_same_solution() -> None:
    """A re-centring redraws nothing, so its solve need not eliminate the kept frames last:
    on a bounded planar map (each older pose removed, landmarks seen again) the free
    minimum-degree ordering fills less and lands on the kept-last ordering's solution."""
    from mcsm.core import relin
    from mcsm.core.relinearize import _problem

    from tests.core.test_relinearize import step_at

    rng = np.random.default_rng(20261126)
    n = 200
    m = StochasticMap(n, gate=None, relinearize=None)
    marks = np.array([[2.0, 1.0, 0.0], [4.0, -1.0, 0.0], [6.0, 2.0, 0.0], [3.0, 3.0, 0.0]])
    for k in range(40):
        m.update(f"x{k}", f"x{k + 1}", step_at(rng, n, True))
        for j in range(len(marks)):
            if (k + j) % 3 == 0:  # the mark as seen from where the map has the pose
                pose = m.query("x0", f"x{k + 1}").mean(axis=0)
                yaw = 2.0 * np.arctan2(pose[6], pose[3])
                d = marks[j] - pose[:3]
                seen = [np.cos(yaw) * d[0] + np.sin(yaw) * d[1],
                        -np.sin(yaw) * d[0] + np.cos(yaw) * d[1], 0.0]
                p = seen + 0.05 * rng.standard_normal((n, 3)) * [1, 1, 0]
                m.update(f"x{k + 1}", f"l{j}", p)
        if k >= 1:
            m.remove(f"x{k}")
    h = m.factor_history
    assert h is not None
    cid = m._where["x0"]
    ids = h.group_vars(cid)
    fmask = h.vars["group"][h.factors["vars"][:, 0]] == cid
    alive = h.vars["alive"][ids].astype(np.uint8)
    assert 0 < int(alive.sum()) < len(ids)  # removed poses and kept frames
    out = {}
    for name, kept in (("kept last", alive), ("free", np.zeros_like(alive))):
        prob = _problem(m, h, cid, ids, fmask, [], kept)
        with relin.solve(prob, max_iter=20, tol=1e-12, keep_factor=False) as sol:
            out[name] = (prob.x.copy(), sol.stats.factor_values)
    (x_kept, nz_kept), (x_free, nz_free) = out["kept last"], out["free"]
    assert nz_free <= nz_kept
    assert np.max(np.abs(x_free[:, :3] - x_kept[:, :3])) < 1e-9
    assert np.max(1.0 - np.abs(np.sum(x_free[:, 3:] * x_kept[:, 3:], axis=1))) < 1e-12


def _pose_stream(m: StochasticMap, n: int, closures: int = 6) -> None:
    """A 3-D pose chain with rotations, a landmark seen three times and ``closures`` loop
    closures back to the start (every one a re-centring under the defaults)."""
    from mcsm_client.sampling import sample_point, sample_pose

    rng = np.random.default_rng(20261127)
    cov = np.diag([0.01, 0.01, 0.01, 0.001, 0.001, 0.004])
    step = np.array([1.0, 0.1, 0.0, 0.996, 0.0, 0.0, 0.0872])  # 10 degrees of yaw
    for k in range(12):
        m.update(f"x{k}", f"x{k + 1}", sample_pose(step, cov, n_samples=n, rng=rng))
        if k in (2, 5, 8):
            m.update(f"x{k}", "l0", sample_point([2.0, 0.5, 0.1], 0.02 * np.eye(3),
                                                 n_samples=n, rng=rng))
    for k in range(closures):
        a, b = m.query("x0", f"x{12 - k}"), None
        mean = a.mean(axis=0)
        mean[3:] /= np.linalg.norm(mean[3:])
        b = sample_pose(mean, cov, n_samples=n, rng=rng)
        m.update("x0", f"x{12 - k}", b)


def test_the_update_pass_keeps_the_frames_means_for_the_recentring(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A loop closure's frame pass takes every frame's mean and live chart coordinates while
    the frame is in the cache: the bytes :func:`relin.means_active` gives over the updated
    buffer; the re-centring's solve starts from them; its shift (a new buffer) forgets them."""
    from mcsm.core import recentre as rmod
    from mcsm.core import relin

    seen = []
    original = rmod.recentre_component

    def checked(smap, cid):  # type: ignore[no-untyped-def]
        c = smap._comps[cid]
        kept = c.pass_means()
        assert kept is not None
        idx = np.arange(len(c), dtype=np.int64)
        means, masks = relin.means_active(c.rows, idx, c.point_flags[: len(c)])
        assert kept[0].tobytes() == means.tobytes()
        assert relin.finish_masks(kept[1]) == masks
        seen.append(masks)
        out = original(smap, cid)
        assert smap._comps[cid].pass_means() is None  # the shift swapped the buffer
        return out

    monkeypatch.setattr(rmod, "recentre_component", checked)
    m = StochasticMap(64)
    _pose_stream(m, 64)
    assert len(seen) >= 5 and seen[-1] == (0b111111, 0b111)


def test_the_kept_means_give_the_bits_of_a_separate_pass(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """The same stream with the kept means ignored (a separate means pass before each solve)
    ends in the same bytes."""
    from mcsm.core.storage import Component

    a = StochasticMap(64)
    _pose_stream(a, 64)
    monkeypatch.setattr(Component, "pass_means", lambda self: None)
    b = StochasticMap(64)
    _pose_stream(b, 64)
    assert a.state_digest() == b.state_digest()


def test_a_component_forgets_its_kept_means_on_every_change() -> None:
    from mcsm.core.storage import Component

    rng = np.random.default_rng(3)
    rows = np.ascontiguousarray(_buffer(rng, 5, 8, planar=False)[:5])
    c = Component([f"f{k}" for k in range(5)], [False] * 5, rows.copy())
    ls = np.zeros(4, dtype=np.int64)
    with pytest.raises(ValueError, match="one mean per frame"):
        c.keep_means(np.zeros((4, 7)), ls, np.zeros(4))
    changes = (lambda: c.append("g", False, rows[1]),
               lambda: c.extend(["h"], [True], rows[2:3]),
               lambda: c.delete(2),
               lambda: c.swap_buffer(c.buffer.copy()),
               c.written)
    for change in changes:
        c.keep_means(np.zeros((len(c), 7)), ls, np.zeros(len(c)))
        assert c.pass_means() is not None
        change()
        assert c.pass_means() is None


def test_a_recentring_shifts_in_place_only_where_nothing_can_overflow(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """After a loop closure's pass the shift writes into the component's own buffer (no spare
    buffer to fill): the same bytes as the copying shift. It does so only with the pass's
    means of that buffer and every translation, mean and target within 1e300 and every target
    rotation's norm in [0.5, 2]; anything else (a NaN included) copies."""
    from mcsm.core import recentre as rmod
    from mcsm.core import relin
    from mcsm.core.storage import Component

    ways = []
    original, ok = relin.recentre, rmod._shifts_finitely

    def spy(src, dst, *args, **kwargs):  # type: ignore[no-untyped-def]
        ways.append(src is dst)
        return original(src, dst, *args, **kwargs)

    monkeypatch.setattr(relin, "recentre", spy)
    a = StochasticMap(64)
    _pose_stream(a, 64)
    assert len(ways) >= 5 and all(ways)
    monkeypatch.setattr(rmod, "_shifts_finitely", lambda *args: False)
    ways.clear()
    b = StochasticMap(64)
    _pose_stream(b, 64)
    assert ways and not any(ways)
    assert a.state_digest() == b.state_digest()

    rng = np.random.default_rng(4)
    rows = np.ascontiguousarray(_buffer(rng, 4, 8, planar=False)[:4])
    c = Component(["r", "a", "b", "c"], [False] * 4, rows)
    slot = np.array([1, 3], dtype=np.int64)
    mean = relin.means(rows, slot, np.zeros(2, dtype=np.uint8))
    target = mean.copy()
    assert not ok(c, slot, mean, target)  # no kept means
    big = np.ones(4)
    c.keep_means(np.zeros((4, 7)), np.zeros(4, dtype=np.int64), big)
    assert ok(c, slot, mean, target)
    big[3] = 2e300
    assert not ok(c, slot, mean, target)
    big[3], big[2] = 1.0, np.inf  # a frame not moved does not matter
    assert ok(c, slot, mean, target)
    for k, value in ((0, 2e300), (3, 0.4), (3, np.nan), (1, np.inf)):
        bad = target.copy()
        bad[1, k] = value if k != 3 else 0.0
        if k == 3:
            bad[1, 3:] *= 0.0
            bad[1, 3] = value
        assert not ok(c, slot, mean, bad), (k, value)
    far = mean.copy()
    far[0, 2] = -2e300
    assert not ok(c, slot, far, target)


def test_a_relinearisation_redraws_into_the_spare_buffer_and_keeps_the_capacity(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A relinearisation of a component in host memory writes its redraw into the map's spare
    buffer (mapped pages, no fresh memory), keeps the component's capacity (the next frame is
    no copy of the whole component) and leaves the old buffer as the next spare: the same
    bytes as a redraw into a fresh copy."""
    from mcsm.core import relinearize as rz
    from mcsm.core.storage import Component

    a = StochasticMap(64)
    _pose_stream(a, 64)
    (cid, comp), = a._comps.items()
    buf, spare, cap = comp.buffer, a._spare, comp.buffer.shape[0]
    assert spare is not None and spare.shape == buf.shape
    a.relinearize()
    new = a._comps[cid]
    assert new.buffer is spare and a._spare is buf and new.buffer.shape[0] == cap

    def fresh(smap, c):  # type: ignore[no-untyped-def]
        return c.rows.copy(), c.point_flags[: len(c)]

    monkeypatch.setattr(rz, "_redraw_buffer", fresh)
    b = StochasticMap(64)
    _pose_stream(b, 64)
    b.relinearize()
    assert b._comps[cid].buffer.shape[0] == len(b._comps[cid])  # the copy's capacity
    assert a.state_digest() == b.state_digest()
    for m in (a, b):
        m.update("x12", "x13", m.query("x11", "x12"))  # the next frame, the next closure
        m.update("x0", "x13", m.query("x0", "x13"))
    assert a.state_digest() == b.state_digest()
    with pytest.raises(ValueError, match="at least M frames"):
        Component.in_buffer(["r", "a"], [False, False], np.zeros((1, 7, 4)))
