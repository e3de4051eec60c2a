"""Re-admitting refused loop closures after a relinearisation (``Policy.readmit``): a
refused closure that the relinearised map agrees with is admitted into the history, a wrong one
is not; the pending closures are part of the state (snapshot, digest, replay). The default
policy keeps them (``readmit=300``) and re-checks them at every re-centring."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm.core import relin
from mcsm.core.relinearize import Policy
from mcsm.errors import NumericalError

N = 200
POLICY = Policy(regate=6, gap=1, readmit=50)


def at(rng: np.random.Generator, x: float, t_sd: float, r_sd: float = 0.002) -> np.ndarray:
    """(N, 7) samples of a translation (x, 0, 0) with spread ``t_sd`` and small rotations."""
    s = np.zeros((N, 7))
    s[:, :3] = rng.standard_normal((N, 3)) * t_sd
    s[:, 0] += x
    s[:, 4:] = rng.standard_normal((N, 3)) * (r_sd / 2)
    s[:, 3] = 1.0
    s[:, 3:] /= np.linalg.norm(s[:, 3:], axis=1, keepdims=True)
    return s


def script(m: StochasticMap, stop: int | None = None) -> list[object]:
    """Odometry p0 -> p1 of 1 m, overconfident (sd 1 cm); the truth is 1.5 m, seen by precise
    closures (sd 5 mm). The first closures are refused (NIS in the thousands) and so is a wrong
    one (3 m); at the sixth failure ``regate`` relinearises (still refused: the history holds
    only the odometry); then the truth arrives trusted, and after 8 passes the ``readmit``
    relinearisation checks the refused ones against the map that now sits at 1.5 m."""
    rng = np.random.default_rng(20261126)
    steps: list[tuple[float, bool]] = [(1.0, False)] + [(1.5, False)] * 3 + [(3.0, False)] \
        + [(1.5, False)] * 2 + [(1.5, True)] * 8
    out: list[object] = []
    for k, (x, trusted) in enumerate(steps[:stop]):
        sd = 0.01 if k == 0 else 0.005
        out.append(m.update("p0", "p1", at(rng, x, sd), trusted=trusted))
    return out


def test_a_refused_closure_is_admitted_after_a_relinearisation_and_a_wrong_one_is_not() -> None:
    m = StochasticMap(N, relinearize=POLICY)
    rs = script(m)
    kinds = [r.kind for r in rs]  # type: ignore[attr-defined]
    assert kinds[1:7] == ["rejected"] * 6, kinds
    assert "relinearised first" in rs[6].verdict.reason  # type: ignore[attr-defined]
    readmit = [r.relin for r in rs if r.relin is not None  # type: ignore[attr-defined]
               and r.relin.trigger == "readmit"]
    assert len(readmit) == 1
    c = readmit[0].components[0]
    h = m.factor_history
    assert h is not None
    # the five right closures (1.5 m) are admitted, the wrong one (3 m) is not
    assert c.readmitted == 5 and h.n_readmitted == 5 and c.to_dict()["readmitted"] == 5
    assert h.pending.n == 0  # the checked ones are forgotten
    # the posterior of the odometry (1 m, information 1e4) and the 13 right closures (1.5 m,
    # 4e4 each) is 1.4906 m; without the 5 admitted ones it would be 1.4848 m (the inputs'
    # sample means scatter by 0.005 / sqrt(N) = 0.00035 m)
    with_them = (1e4 * 1.0 + 13 * 4e4 * 1.5) / (1e4 + 13 * 4e4)
    assert abs(m.query("p0", "p1")[:, 0].mean() - with_them) < 0.002
    # the admitted closures are gated factors: trimmable like any other
    assert h.factors["robust"][-5:].all()


def test_with_the_gate_off_every_closure_is_in_and_none_is_trimmed() -> None:
    """``gate=None`` (docs/relinearisation.md, "the gate off"): the wrong closure (3 m) goes
    in with the rest, no factor is trimmable, and a relinearisation lands on the least-squares
    posterior of every input, the wrong one included."""
    m = StochasticMap(N, gate=None, relinearize=POLICY)
    seen: list[np.ndarray] = []
    update = m.update

    def recording(a: str, b: str, x: np.ndarray, trusted: bool = False) -> object:
        seen.append(x[:, 0].copy())
        return update(a, b, x, trusted=trusted)
    m.update = recording  # type: ignore[method-assign]
    rs = script(m)
    assert all(r.kind != "rejected" for r in rs)  # type: ignore[attr-defined]
    h = m.factor_history
    assert h is not None and h.pending.n == 0
    assert not h.factors["robust"].any()
    rep = m.relinearize()
    assert rep.components[0].trimmed == 0
    # each input weighted by the information of its own samples (x is independent of the
    # other coordinates up to the samples' 1/sqrt(N) correlations)
    w = np.array([1.0 / x.var() for x in seen])
    least_squares = float(np.sum(w * [x.mean() for x in seen]) / w.sum())
    assert abs(m.query("p0", "p1")[:, 0].mean() - least_squares) < 1e-3
    without_wrong = float(np.sum(np.delete(w * [x.mean() for x in seen], 4))
                          / np.delete(w, 4).sum())
    assert least_squares - without_wrong > 0.08  # the wrong closure's pull: 0.1 m


def test_pending_refusals_are_state_and_replay_bit_identical() -> None:
    a = StochasticMap(N, relinearize=POLICY)
    script(a, stop=9)
    h = a.factor_history
    assert h is not None and h.pending.n == 6 and int(h.pending["burst"].sum()) == 6
    b = StochasticMap.from_snapshot(a.snapshot())
    assert b.state_digest() == a.state_digest()
    c = StochasticMap(N, relinearize=POLICY)
    script(c, stop=9)
    assert c.state_digest() == a.state_digest()
    # and without pending refusals the digest does not depend on them
    d = StochasticMap(N, relinearize=Policy(regate=6, gap=1))
    script(d, stop=9)
    assert d.state_digest() != a.state_digest()
    assert "readmit" not in d.options()["relinearize"]
    assert a.options()["relinearize"]["readmit"] == 50
    assert StochasticMap.from_options(a.options()).policy == POLICY


def test_without_readmit_no_refusal_is_kept_and_the_default_keeps_them() -> None:
    from dataclasses import replace

    from mcsm.core.smap import DEFAULT_POLICY

    assert DEFAULT_POLICY is not None and DEFAULT_POLICY.readmit == 300
    m = StochasticMap(N, relinearize=replace(DEFAULT_POLICY, readmit=None, calibrate=None))
    script(m)
    h = m.factor_history
    assert h is not None and h.pending.n == 0 and h.n_readmitted == 0
    assert "pending" not in h.to_plain()
    d = StochasticMap(N)  # the default re-centres at every trusted closure and re-checks them
    script(d)
    h = d.factor_history
    assert h is not None and h.n_readmitted == 5 and h.pending.n == 1  # the wrong one waits


def test_a_failed_solve_after_an_admission_changes_nothing(monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    m = StochasticMap(N, relinearize=POLICY)
    script(m, stop=13)  # six refusals kept and marked, seven trusted closures, none admitted
    before = m.state_digest()
    real, full = relin.solve, []

    def failing(problem: relin.Problem, **kw: object) -> relin.Solution:
        if kw.get("max_iter") != 0:  # the whole solves, not the one-factor chi-squares
            full.append(1)
            if len(full) == 2:  # the solve with the admitted closures
                raise NumericalError("the test's failure")
        return real(problem, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(relin, "solve", failing)
    rep = m.relinearize()
    assert len(full) == 2 and rep.components[0].skipped.startswith("failed: NumericalError")
    assert m.state_digest() == before
    h = m.factor_history
    assert h is not None and h.pending.n == 6 and h.n_readmitted == 0


CALIBRATED = Policy(regate=6, gap=1, readmit=50, calibrate=3)


def test_calibrate_scales_the_gate_by_the_closures_admitted_later() -> None:
    """``Policy.calibrate``: the five right closures refused and admitted later keep their
    arrival ratios (NIS over the unscaled threshold); the gate's threshold is then at least
    the lower quartile of the last K, so a closure 5 cm off (NIS far above the 0.99 quantile,
    far below the refused ones') passes with a verdict that says why; the same map without it
    refuses it."""
    from mcsm.core.gate import chi2_quantile

    # without the recent-NIS scale (which these refusals open too) only the calibration acts
    plain = StochasticMap(N, relinearize=POLICY, gate_scale=None)
    cal = StochasticMap(N, relinearize=CALIBRATED, gate_scale=None)
    rs = script(cal)
    script(plain)
    h = cal.factor_history
    assert h is not None and h.n_readmitted == 5
    # the right ones (1.5 m: inputs 1-3, 5, 6; the 3 m one stays pending), in arrival order
    right = [rs[k].verdict for k in (1, 2, 3, 5, 6)]  # type: ignore[attr-defined]
    assert h.admitted_u == [v.nis / chi2_quantile(0.99, v.dof) for v in right]
    assert min(h.admitted_u) > 1.0  # each was beyond the gate when it came
    low = sorted(h.admitted_u[-3:])[0]  # the lower quartile of three: the smallest
    assert cal.learnt_factor() == min(max(low, 1.0), 30.0) and plain.learnt_factor() == 1.0
    rng = np.random.default_rng(7)
    x = at(rng, 1.55, 0.005)
    got, ref = cal.update("p0", "p1", x.copy()), plain.update("p0", "p1", x.copy())
    thr = chi2_quantile(0.99, got.verdict.dof)
    assert thr < got.verdict.nis < got.verdict.threshold and got.kind == "loop_closure"
    assert "by the closures admitted later" in got.verdict.reason
    assert ref.kind == "rejected" and ref.verdict.nis > thr


def test_calibration_is_state_and_needs_readmit() -> None:
    from mcsm.errors import InvalidOperation

    a = StochasticMap(N, relinearize=CALIBRATED)
    script(a)
    h = a.factor_history
    assert h is not None and len(h.admitted_u) == 5
    b = StochasticMap.from_snapshot(a.snapshot())
    assert b.state_digest() == a.state_digest() and b.learnt_factor() == a.learnt_factor()
    assert b.factor_history is not None and b.factor_history.admitted_u == h.admitted_u
    c = StochasticMap(N, relinearize=CALIBRATED)
    script(c)
    assert c.state_digest() == a.state_digest()
    h.admitted_u[-1] += 1e-9  # the ratios are part of the digest
    assert a.state_digest() != c.state_digest()
    assert a.options()["relinearize"]["calibrate"] == 3
    assert StochasticMap.from_options(a.options()).policy == CALIBRATED
    with pytest.raises(InvalidOperation, match="calibrate"):
        Policy(regate=6, calibrate=3)  # without readmit
    with pytest.raises(InvalidOperation, match="calibrate"):
        Policy(readmit=50, calibrate=65)
