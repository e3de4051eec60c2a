"""The auditor (issue 16 §6), offline on recorded inputs of a small graph: GNC finds a
self-consistent burst the gate let through, asks to retract it (and to reinstate a true
closure the map had rejected), leaves marginal closures alone (hysteresis), and its decisions
applied by restore + replay give the map that never had the burst (equal digests)."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm_client.audit import AuditInput, Auditor, run_gnc
from mcsm_client.outliers import Ledger, Record

from experiments.posegraph_sim import (
    perturb,
    qexp,
    qmul,
    qrot,
    relative,
    sample_measurement,
    simulate_2d,
)

pytest.importorskip("gtsam")

N = 64


def burst_graph() -> tuple[list[Record], list[int], list[int]]:
    """A planar graph of 40-pose laps; the first 4 closures of the third lap's revisit are
    replaced by one wrong rigid offset (2.5 m, 10°) of the old place: they agree together."""
    rng = np.random.default_rng(21)
    g = simulate_2d(200, rng=rng, poses_per_rev=40, radius_m=5.0, breathing_m=0.2,
                    min_gap=30, loop_radius_m=1.0)
    loops = [int(k) for k in np.flatnonzero(g.is_loop)]
    later = [k for k in loops if g.edges[k, 1] >= 120]
    burst = later[:4]
    truth = g.poses_true
    c = truth[g.edges[burst[0], 0], :3]
    rot = qexp(np.array([0.0, 0.0, np.radians(10)]))
    d = np.array([2.5, 0.0, 0.0])
    recs = []
    for k, ((i, j), z, cov) in enumerate(zip(g.edges, g.measurements, g.covariances,
                                             strict=True)):
        if k in burst:
            wrong_i = np.concatenate([c + d + qrot(rot, truth[i, :3] - c),
                                      qmul(rot, truth[i, 3:])])
            z = relative(wrong_i, truth[j])
        recs.append(Record(k, f"p{i}", f"p{j}", sample_measurement(z, cov, N, rng=rng)))
    return recs, loops, burst


def _inputs(recs: list[Record], status: dict[int, str]) -> list[AuditInput]:
    return [AuditInput(r.request_id, r.a, r.b, r.samples, status.get(r.request_id, "accepted"))
            for r in recs]


@pytest.mark.slow
def test_gnc_flags_the_burst_and_the_auditor_retracts_exactly_it() -> None:
    recs, loops, burst = burst_graph()
    res = run_gnc(_inputs(recs, {}))
    assert set(res.closures) == set(loops)
    out = {k for k in loops if res.weights[k] < 0.5}
    assert out == set(burst)
    decisions = Auditor().decide(_inputs(recs, {}))
    assert {d.request_id for d in decisions if d.action == "retract"} == set(burst)
    assert all(d.action == "retract" for d in decisions)
    for d in decisions:
        assert d.residual_nis > 2 * d.threshold and d.dof == 3

    # the map accepted the burst as trusted; retracting by replay = never having had it
    ledger = Ledger(StochasticMap(N, gate=0.99, inflation=1.002), snapshot_every=25)
    for r in recs:
        ledger.apply(Record(r.request_id, r.a, r.b, r.samples, trusted=r.request_id in burst))
    ledger.retract([d.request_id for d in decisions])
    never = StochasticMap(N, gate=0.99, inflation=1.002)
    for r in recs:
        if r.request_id not in burst:
            never.update(r.a, r.b, r.samples)
    assert ledger.map.state_digest() == never.state_digest()


@pytest.mark.slow
def test_reinstate_and_hysteresis() -> None:
    recs, loops, burst = burst_graph()
    true_loops = [k for k in loops if k not in burst]
    # a true closure the map had rejected comes back; the burst, already out, stays out
    status = {k: "rejected" for k in burst}
    status[true_loops[3]] = "rejected"
    decisions = Auditor().decide(_inputs(recs, status))
    assert [(d.request_id, d.action) for d in decisions] == [(true_loops[3], "reinstate")]
    # a closure moved to about the threshold is neither retracted (accepted) nor reinstated
    # (rejected): it sits in the band between 0.5x and 2x the threshold
    k = true_loops[5]
    sig = float(np.sqrt(np.var(recs[k].samples[:, 0], ddof=1)))
    moved = perturb(recs[k].samples, np.broadcast_to([3.6 * sig, 0, 0, 0, 0, 0], (N, 6)))
    recs[k] = Record(k, recs[k].a, recs[k].b, moved)
    res = run_gnc(_inputs(recs, {}))
    thr = 11.344866730144073
    assert 0.5 * thr < res.residual_nis[k] < 2 * thr, res.residual_nis[k]
    for st in ("accepted", "rejected"):
        status = {j: "rejected" for j in burst}
        status[k] = st
        assert all(d.request_id != k for d in Auditor().decide(_inputs(recs, status)))


def test_when_to_audit() -> None:
    a = Auditor(every=5, pile=3, window=4)
    assert [a.observe("accepted") for _ in range(5)] == [False] * 4 + [True]
    # three rejections among the last four closures, at least a window after the last audit
    got = [a.observe(s) for s in ("rejected", "accepted", "rejected", "rejected")]
    assert got == [False, False, False, True]
    with pytest.raises(ValueError):
        Auditor(retract_above=0.9)
    # the documented defaults: every 50 closures, or 5 of the last 10 rejected, at most once
    # per 10
    d = Auditor()
    assert [d.observe("accepted") for _ in range(50)] == [False] * 49 + [True]
    got = [d.observe(s) for s in ["rejected"] * 5 + ["accepted"] * 4 + ["rejected"]]
    assert got == [False] * 9 + [True]  # 6 of the last 10, but not before 10 since the last
    got = [d.observe("rejected") for _ in range(10)]
    assert got == [False] * 9 + [True]
