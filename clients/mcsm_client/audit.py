"""The auditor of issue 16 §6: GNC over the recorded inputs, retract/reinstate with hysteresis.

A sequential gate cannot see a self-consistent burst of wrong closures at a place seen for the
first time, and it can lock in after an early wrong closure. The auditor looks at every
recorded input at once: it builds a pose graph from the inputs' sample means and covariances
(spanning-tree inputs, i.e. new frames and joins, are known inliers; every loop closure, applied
or rejected, is a candidate), runs GTSAM's graduated non-convexity with the truncated least
squares loss (``GncLMOptimizer``, TLS) and compares its verdicts with the map's:

* an applied closure (``accepted``/``reinstated``) is to be **retracted** when GNC gives it
  weight < 0.5 *and* its residual at the GNC estimate exceeds ``retract_above`` times the
  chi-square threshold of its dof;
* a closure that is out (``rejected``/``retracted``) is to be **reinstated** when GNC gives it
  weight >= 0.5 *and* its residual is under ``reinstate_below`` times the threshold.

The band between the two margins is the hysteresis: a closure near the threshold keeps the
state it has, so clean runs do not flap between retract and reinstate (the note measured
needless replays without it). ``pending`` closures are left alone.

When to audit (:meth:`Auditor.observe`): every ``every`` loop closures, or when ``pile`` of
the last ``window`` closures were rejected (rejections piling up at one place: consecutive
closures of one revisit are at one place), at most once per ``window`` closures.

It is a client: the map never needs gtsam. gtsam (the ``eval`` extra) is imported when an
audit runs. Point (landmark) observations are not part of the audited graph (they are neither
candidates nor constraints) in this version.

Example (offline, on recorded inputs)::

    auditor = Auditor()
    for inp in inputs:                       # AuditInput(request_id, a, b, samples, status)
        if auditor.observe(inp.status):
            for d in auditor.decide(inputs_so_far):
                ...                          # server: retract(d.request_id) / reinstate(...)
"""

from __future__ import annotations

import collections
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt
from mcsm.core import mean_and_cov
from mcsm.core.at import scaled_eigh
from mcsm.core.gate import chi2_quantile
from mcsm.core.quat import rotation_matrix

Array = npt.NDArray[np.float64]

IN = ("accepted", "reinstated")
OUT = ("rejected", "retracted")


@dataclass(frozen=True)
class AuditInput:
    """One recorded input: request id, frames, samples ``(N, 7)`` and its current status."""

    request_id: int
    a: str
    b: str
    samples: Array = field(repr=False)
    status: str = "accepted"


@dataclass(frozen=True)
class Decision:
    """What the auditor asks for one closure: ``action`` ``retract`` or ``reinstate``."""

    request_id: int
    action: str
    weight: float
    residual_nis: float
    threshold: float
    dof: int


@dataclass(frozen=True)
class GncResult:
    """Per loop closure: GNC weight (1 inlier, 0 outlier) and residual NIS at the estimate."""

    weights: dict[int, float]
    residual_nis: dict[int, float]
    dof: dict[int, int]
    closures: tuple[int, ...]


def _compose(a: Array, b: Array) -> Array:
    from mcsm.core import compound

    return np.asarray(compound(a, b))


def _invert(a: Array) -> Array:
    from mcsm.core import invert

    return np.asarray(invert(a))


class _Moments:
    """Mean and gtsam-ordered covariance of each input's samples (computed once)."""

    def __init__(self) -> None:
        self._cache: dict[int, tuple[Array, Array, int]] = {}

    def get(self, inp: AuditInput) -> tuple[Array, Array, int]:
        hit = self._cache.get(inp.request_id)
        if hit is not None:
            return hit
        mean, cov = mean_and_cov(np.asarray(inp.samples, dtype=np.float64))
        # mcsm: t' = t + dt (parent frame), q' = q exp(dr); gtsam Pose3: [dr, R^T dt].
        r = rotation_matrix(mean[3:])
        j = np.zeros((6, 6))
        j[:3, 3:] = np.eye(3)
        j[3:, :3] = r.T
        c = j @ cov @ j.T
        c = 0.5 * (c + c.T)
        w = np.linalg.eigvalsh(c)
        _, lam, _ = scaled_eigh(c)
        dof = int(np.sum(lam > 0))  # the live dimensions, by the core's rule (its NIS's dof)
        c = c + np.eye(6) * max(1e-10, 1e-8 * float(w.max()))  # planar: z, roll, pitch fixed
        self._cache[inp.request_id] = (mean, c, dof)
        return mean, c, dof


def run_gnc(inputs: Sequence[AuditInput], *, moments: _Moments | None = None,
            max_iterations: int = 30) -> GncResult:
    """GNC (TLS) over the full-frame inputs; weights and residuals of every loop closure.

    Structure follows the inputs in order, as the map does: an input between two frames not yet
    connected is a spanning-tree input (known inlier), one between connected frames a loop
    closure. Rejected and retracted closures are in the graph as candidates too.
    """
    import gtsam

    moments = moments or _Moments()
    parent: dict[str, str] = {}
    members: dict[str, list[str]] = {}
    pose: dict[str, Array] = {}
    key: dict[str, int] = {}

    def find(f: str) -> str:
        while parent[f] != f:
            parent[f] = parent[parent[f]]
            f = parent[f]
        return f

    def add(f: str, p: Array) -> None:
        parent[f] = f
        members[f] = [f]
        pose[f] = p
        key[f] = len(key)

    graph = gtsam.NonlinearFactorGraph()
    known: list[int] = []
    closures: list[int] = []
    factor_of: dict[int, int] = {}
    ident = np.array([0, 0, 0, 1.0, 0, 0, 0])
    for inp in inputs:
        if np.asarray(inp.samples).shape[-1] != 7:
            continue
        mean, cov, dof = moments.get(inp)
        a, b = inp.a, inp.b
        closure = False
        if a not in parent and b not in parent:
            add(a, ident)
            graph.add(gtsam.PriorFactorPose3(key[a], _pose3(ident),
                                             gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
            known.append(graph.size() - 1)
            add(b, _compose(ident, mean))
            _union(parent, members, a, b)
        elif a in parent and b not in parent:
            add(b, _compose(pose[a], mean))
            _union(parent, members, a, b)
        elif b in parent and a not in parent:
            add(a, _compose(pose[b], _invert(mean)))
            _union(parent, members, b, a)
        elif find(a) != find(b):
            # a join: move b's component so that b = a (+) mean
            ra, rb = find(a), find(b)
            move = _compose(_compose(pose[a], mean), _invert(pose[b]))
            for f in members[rb]:
                pose[f] = _compose(move, pose[f])
            _union(parent, members, ra, rb)
        else:
            closure = True
        graph.add(gtsam.BetweenFactorPose3(key[a], key[b], _pose3(mean),
                                           gtsam.noiseModel.Gaussian.Covariance(cov)))
        idx = graph.size() - 1
        if closure:
            closures.append(inp.request_id)
            factor_of[inp.request_id] = idx
        else:
            known.append(idx)
    values = gtsam.Values()
    for f, k in key.items():
        values.insert(k, _pose3(pose[f]))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(max_iterations)
    lm.setRelativeErrorTol(1e-6)
    params = gtsam.GncLMParams(lm)
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(known)
    opt = gtsam.GncLMOptimizer(graph, values, params)
    result = opt.optimize()
    weights = np.asarray(opt.getWeights())
    w_out: dict[int, float] = {}
    r_out: dict[int, float] = {}
    d_out: dict[int, int] = {}
    by_id = {inp.request_id: inp for inp in inputs}
    for rid, idx in factor_of.items():
        w_out[rid] = float(weights[idx])
        r_out[rid] = 2.0 * float(graph.at(idx).error(result))
        d_out[rid] = moments.get(by_id[rid])[2]
    return GncResult(w_out, r_out, d_out, tuple(closures))


def _union(parent: dict[str, str], members: dict[str, list[str]], keep: str, other: str) -> None:
    def find(f: str) -> str:
        while parent[f] != f:
            f = parent[f]
        return f

    rk, ro = find(keep), find(other)
    if rk == ro:
        return
    parent[ro] = rk
    members[rk].extend(members.pop(ro))


def _pose3(row: Array) -> Any:
    import gtsam

    return gtsam.Pose3(gtsam.Rot3.Quaternion(float(row[3]), float(row[4]), float(row[5]),
                                             float(row[6])),
                       gtsam.Point3(float(row[0]), float(row[1]), float(row[2])))


class Auditor:
    """When to run GNC over the recorded inputs, and what to retract or reinstate.

    Parameters
    ----------
    every : audit after this many loop closures since the last audit
    pile, window : audit when ``pile`` of the last ``window`` closures were rejected
    gate : chi-square quantile of the residual thresholds (the map's gate)
    retract_above, reinstate_below : the hysteresis margins, as multiples of the threshold
    """

    def __init__(self, *, every: int = 50, pile: int = 5, window: int = 10, gate: float = 0.99,
                 retract_above: float = 2.0, reinstate_below: float = 0.5) -> None:
        if not 0 < reinstate_below <= 1 <= retract_above:
            raise ValueError("need 0 < reinstate_below <= 1 <= retract_above")
        self.every = every
        self.pile = pile
        self.window = window
        self.gate = gate
        self.retract_above = retract_above
        self.reinstate_below = reinstate_below
        self._recent: collections.deque[bool] = collections.deque(maxlen=window)
        self._since = 0
        self._moments = _Moments()
        self.audits = 0
        self.last: GncResult | None = None

    def observe(self, status: str) -> bool:
        """Count one loop closure's verdict; True when an audit is due now."""
        self._since += 1
        self._recent.append(status in OUT)
        piled = sum(self._recent) >= self.pile and self._since >= self.window
        if self._since >= self.every or piled:
            self._since = 0
            self._recent.clear()
            return True
        return False

    def decide(self, inputs: Sequence[AuditInput],
               status: Mapping[int, str] | None = None) -> list[Decision]:
        """Run GNC over ``inputs`` and return the retractions/reinstatements it asks for.

        ``status`` overrides the inputs' own statuses (request id → current status).
        """
        self.audits += 1
        res = run_gnc(inputs, moments=self._moments)
        self.last = res
        current = {i.request_id: i.status for i in inputs}
        if status:
            current.update(status)
        out: list[Decision] = []
        for rid in res.closures:
            w, nis, dof = res.weights[rid], res.residual_nis[rid], res.dof[rid]
            thr = chi2_quantile(self.gate, max(dof, 1))
            st = current.get(rid, "accepted")
            if st in IN and w < 0.5 and nis > self.retract_above * thr:
                out.append(Decision(rid, "retract", w, nis, thr, dof))
            elif st in OUT and w >= 0.5 and nis < self.reinstate_below * thr:
                out.append(Decision(rid, "reinstate", w, nis, thr, dof))
        return out


__all__ = ["AuditInput", "Auditor", "Decision", "GncResult", "run_gnc"]
