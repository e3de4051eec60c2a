"""Relinearisation: bring a component back to the maximum a posteriori estimate of everything
it has seen and redraw its samples around it with the posterior's joint covariance.

For one component: every factor of its history (:mod:`mcsm.core.factors`) with the root fixed
(the star forest is conditional on it) is solved by Gauss-Newton / Levenberg-Marquardt in the
compiled kernel (:mod:`mcsm.core.relin`), starting from the map's own means for the frames it
holds and the recorded estimates of removed ones; removed frames are eliminated first, so the
kept frames' joint covariance conditional on the root is the factorisation's trailing block;
then N joint samples are drawn from it (a counter-based generator keyed by the history's
counters), centred so that every edge's mean in the chart is the solution, and written as the
component's root→frame edges (star forest, sample order and O(N) queries kept). Removed frames'
estimates move to the solution too.

The history is bounded (:meth:`FactorHistory.over_bound`): beyond its bound the oldest removed
variables are marginalised, at their current estimates, into a dense Gaussian prior on the
variables they touch (:func:`marginalise`).

:class:`Policy` says when a map relinearises on its own (docs/design.md, "Relinearisation",
gives the measurements behind the defaults).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from mcsm.core import joint, kernel, relin
from mcsm.core.factors import ADMITTED_KEEP, IDENTITY, FactorHistory, Prior
from mcsm.core.forest import Store
from mcsm.core.gate import chi2_quantile
from mcsm.core.storage import Component, to_rows
from mcsm.errors import InvalidOperation, McsmError, NumericalError

Array = npt.NDArray[np.float64]


class Relinearizable(Protocol):
    """What this module reads and writes of a map: its components, its spare buffer, its
    factor history and how it stores a component (:class:`mcsm.core.smap.StochasticMap` is
    one; it calls this module, which therefore does not import it)."""

    _comps: dict[int, Store]
    _spare: Array | None
    factor_history: FactorHistory | None
    policy: Policy | None
    threads: int

    def _store(self, frames: list[str], is_point: list[bool], rows: Array) -> Store: ...

DEFAULT_HISTORY_BYTES = 8 * 2**20
"""The history's default bound: about 30,000 inputs with their frames (Victoria Park: 10,608
inputs, 2.8 MB; city10000: 20,687 edges and 10,000 poses, 5.6 MB), small enough that a
long-running bounded map stays a bounded server."""
REGATE_WINDOW = 8
"""Gated closures over which :attr:`Policy.regate` counts failures."""
MAX_ITERATIONS = 20
TOLERANCE = 1e-6
TRIM_QUANTILE = 0.999
"""A gated loop closure whose chi-square at the solution exceeds this quantile for its dof is
left out of that relinearisation (the whole history contradicts it)."""
CALIBRATE_QUANTILE = 0.25
"""``Policy.calibrate`` scales the gate by this quantile of the recent arrival ratios of the
closures admitted later (measured in docs/relinearisation.md, "Calibrating the gate")."""
_MASK = 2**64 - 1


@dataclass(frozen=True)
class Policy:
    """When a map relinearises a component on its own (none of these is a wall-clock rule:
    replay reproduces every one). ``Policy()`` never does; :data:`RECOMMENDED` is what
    docs/design.md measured on real data.

    nis : after an accepted loop closure whose NIS exceeds this chi-square quantile for its
        dof (None: never)
    every : when the component has had this many inputs since its last relinearisation
        (None: never)
    regate : when a loop closure fails the gate and at least this many of the last
        :data:`REGATE_WINDOW` gated closures of the map failed (it included), relinearise and
        gate it again once (the rejection, if it stays, says so in its verdict); 1: at every
        failure; None: never
    gap : at least this many inputs of the component since its last relinearisation before
        ``nis``, ``regate`` or ``readmit`` relinearises it again
    readmit : keep the loop closures the gate refused within this many inputs of the map's
        history (None: none); when ``regate`` relinearises their component they are marked,
        every later relinearisation of it admits the marked ones whose chi-square at its
        solution is within :data:`TRIM_QUANTILE` (the report's ``readmitted``), and once the
        last :data:`REGATE_WINDOW` gated closures all passed (and ``gap`` inputs went by) one
        more solve checks the marked ones left (the map changes only if it admits one), then
        forgets them (docs/evaluation.md, "Re-admitting refused closures"); with ``recentre``
        every re-centring re-checks them instead (the default policy's way)
    spread : every relinearisation of the map (automatic or asked for) draws its samples'
        deviations from the posterior times this (1: the posterior itself; its covariance
        times ``spread**2``): an allowance for what the inputs' covariances leave out, which a
        filter's inflation gives it and an exact redraw takes away (docs/relinearisation.md,
        "Redraw spread")
    recentre : after every accepted loop closure for which the map did not relinearise, solve its
        component as a relinearisation does and move every frame's samples so that their mean
        is the solution, each sample keeping the filter's deviation (no redraw; the other
        triggers' counters do not change): the map's means stay at the maximum a posteriori
        estimate between relinearisations, for one solve per closure; with ``readmit`` each
        re-centring also admits the component's refused closures it now agrees with (and the
        calm-time check is not needed) (:mod:`mcsm.core.recentre`; docs/relinearisation.md,
        "Re-centring")
    calibrate : with ``readmit``, the gate learns from the refused closures admitted later:
        a new closure's threshold is scaled by at least the lower quartile, over the last K of
        them, of their NIS over the unscaled threshold when they were refused (at most the
        gate scale's ``max``, 30 without one; docs/relinearisation.md, "Calibrating the
        gate")
    """

    nis: float | None = None
    every: int | None = None
    regate: int | None = None
    gap: int = 25
    readmit: int | None = None
    spread: float = 1.0
    recentre: bool = False
    calibrate: int | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.spread, (int, float)) and not isinstance(self.spread, bool)
                and 1.0 <= self.spread <= 2.0):
            raise InvalidOperation(f"relinearise spread must be a number in [1, 2], "
                                   f"got {self.spread!r}")
        if self.nis is not None and not (isinstance(self.nis, (int, float))
                                         and not isinstance(self.nis, bool)
                                         and 0.0 < self.nis < 1.0):
            raise InvalidOperation(f"relinearise nis must be None or a quantile in (0, 1), "
                                   f"got {self.nis!r}")
        if not isinstance(self.recentre, bool):
            raise InvalidOperation(f"relinearise recentre must be true or false, "
                                   f"got {self.recentre!r}")
        for name in ("every", "gap", "regate", "readmit"):
            v = getattr(self, name)
            if (v is not None or name == "gap") and not (
                    isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise InvalidOperation(f"relinearise {name} must be an integer >= 1, got {v!r}")
        if self.regate is not None and self.regate > REGATE_WINDOW:
            raise InvalidOperation(f"relinearise regate must be at most {REGATE_WINDOW}")
        if self.calibrate is not None and not (
                isinstance(self.calibrate, int) and not isinstance(self.calibrate, bool)
                and 1 <= self.calibrate <= ADMITTED_KEEP and self.readmit is not None):
            raise InvalidOperation(f"relinearise calibrate must be None or an integer in [1, "
                                   f"{ADMITTED_KEEP}] with readmit, got {self.calibrate!r}")

    def to_plain(self) -> dict[str, Any]:
        d: dict[str, Any] = {"nis": self.nis, "every": self.every, "regate": self.regate,
                             "gap": self.gap}
        if self.readmit is not None:  # left out when off: the options of maps before it
            d["readmit"] = self.readmit
        if self.spread != 1.0:  # likewise
            d["spread"] = float(self.spread)
        if self.recentre:  # likewise
            d["recentre"] = True
        if self.calibrate is not None:  # likewise
            d["calibrate"] = self.calibrate
        return d

    @classmethod
    def from_plain(cls, d: dict[str, Any]) -> Policy:
        nis, every, regate = d.get("nis"), d.get("every"), d.get("regate")
        if isinstance(regate, bool):  # True: at every failure
            regate = 1 if regate else None
        readmit, recentre = d.get("readmit"), d.get("recentre")
        return cls(None if nis is None else float(nis), None if every is None else int(every),
                   None if regate is None else int(regate), int(d.get("gap", 1)),
                   None if readmit is None else int(readmit), d.get("spread", 1.0),
                   bool(recentre), None if d.get("calibrate") is None else int(d["calibrate"]))


def calibrating(policy: Policy | None) -> bool:
    """Whether the map keeps the arrival ratios of the closures it admits later."""
    return policy is not None and policy.calibrate is not None


@dataclass(frozen=True)
class ComponentRelin:
    """One component's relinearisation: its root, frames redrawn, variables and factors
    solved, Gauss-Newton iterations, cost (sum of squared whitened errors) before and after,
    loop closures left out (trimmed), refused closures admitted (readmitted, with
    :attr:`Policy.readmit`), or why it was skipped."""

    root: str
    frames: int = 0
    variables: int = 0
    factors: int = 0
    iterations: int = 0
    cost_before: float = 0.0
    cost_after: float = 0.0
    trimmed: int = 0
    skipped: str = ""
    readmitted: int = 0

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "root": self.root, "frames": self.frames, "variables": self.variables,
            "factors": self.factors, "iterations": self.iterations,
            "cost_before": self.cost_before, "cost_after": self.cost_after,
            "trimmed": self.trimmed, "skipped": self.skipped}
        if self.readmitted:  # only with Policy.readmit: the ack's keys stay as they were
            d["readmitted"] = self.readmitted
        return d


@dataclass(frozen=True)
class RelinReport:
    """What a relinearisation did: ``trigger`` (request, nis, every, gate), its components,
    and the wall time it took (not part of the map's state)."""

    trigger: str
    components: tuple[ComponentRelin, ...]
    time_s: float

    def to_dict(self) -> dict[str, Any]:
        return {"trigger": self.trigger, "time_s": self.time_s,
                "components": [c.to_dict() for c in self.components]}


RECOMMENDED = Policy(nis=0.95, regate=1, gap=25)
"""The policy that first brought Victoria Park to the batch optimum's neighbourhood
(docs/design.md, "Relinearisation"), with the exact posterior's spread: on the wrong-closure
benchmark its maps were too confident (NEES and precision cases lost), which the default
(:data:`mcsm.core.smap.DEFAULT_POLICY`, the same triggers with ``spread=1.3``) repairs."""
REPAIR_ONLY = Policy(regate=6, gap=25)
"""The default before ``spread``: a consistency repair only, when a closure fails the gate
while 6 of the last 8 did too (kept to reproduce the figures measured with it)."""


def _key(h: FactorHistory, cid: int) -> int:
    return (h.n_inputs * 0x9E3779B97F4A7C15 + h.n_relin * 0xBF58476D1CE4E5B9
            + cid * 0x94D049BB133111EB + 0x2545F4914F6CDD1D) & _MASK


def host_rows(smap: Relinearizable, cid: int) -> tuple[Array, npt.NDArray[np.uint8]]:
    """Component ``cid``'s edges as host rows ``(M, 7, N)`` (a copy) and its point flags: the
    only way this module reads a component, whatever memory it lives in (one in host memory:
    a plain copy of its buffer, not two transposing ones)."""
    c = smap._comps[cid]
    if isinstance(c, Component):
        return c.rows.copy(), c.point_flags[: len(c)].copy()
    return to_rows(c.edges()), np.array(c.point_list(), dtype=np.uint8)


def runner(smap: Relinearizable) -> relin.Runner:
    """The map's frame passes over ranges on its threads (:func:`joint.run_ranges`)."""
    return lambda fn, m: joint.run_ranges(fn, m, smap.threads)


def _redraw_buffer(smap: Relinearizable, c: Component
                   ) -> tuple[Array, npt.NDArray[np.uint8]]:
    """A buffer of ``c``'s capacity holding a copy of its edges, for a redraw to write into:
    the map's spare one where it fits (no fresh memory: its pages are mapped already)."""
    spare = smap._spare
    out = spare if spare is not None and spare.shape == c.buffer.shape else \
        np.empty_like(c.buffer)
    out[: len(c)] = c.rows
    return out, c.point_flags


def replace_rows(smap: Relinearizable, cid: int, rows: Array) -> None:
    """Component ``cid`` with the same frames and the edges ``rows`` (host, ``(M, 7, N)``):
    the only way this module writes one. A map on a device gets the rows uploaded (one
    whole-component transfer: the redraw itself runs in the CPU kernel, docs/kernel.md)."""
    c = smap._comps[cid]
    smap._comps[cid] = smap._store(list(c.frames), c.point_list(), rows)
    smap._spare = None


def estimates(smap: Relinearizable, h: FactorHistory, cid: int, ids: npt.NDArray[np.int64],
              rows: Array, flags: npt.NDArray[np.uint8]) -> Array:
    """Estimates of variables ``ids`` (of group ``cid``) in its root's frame: the map's means
    for frames it holds (from its host ``rows``), the recorded ones for removed frames."""
    return _estimates(smap, h, cid, ids, rows, flags)[0]


def _estimates(smap: Relinearizable, h: FactorHistory, cid: int, ids: npt.NDArray[np.int64],
               rows: Array, flags: npt.NDArray[np.uint8]
               ) -> tuple[Array, tuple[int, int] | None]:
    """:func:`estimates`, and :func:`active_coordinates` read in the same pass where the held
    frames are every frame of the component (else None)."""
    c = smap._comps[cid]
    kind = h.vars["kind"][ids]
    x = relin.transform(h.groups[cid].world, h.vars["est"][ids], kind, invert=True)
    alive = np.flatnonzero(h.vars["alive"][ids])
    masks = None
    if len(alive):
        idx = np.array([c.index[h.frame_of[int(v)]] for v in ids[alive]], dtype=np.int64)
        kept = c.pass_means() if isinstance(c, Component) and rows.base is c.buffer else None
        if len(idx) == len(rows) and np.array_equal(np.sort(idx), np.arange(len(rows))):
            if kept is not None:  # taken by the update's pass over these rows
                x[alive], masks = kept[0][idx], relin.finish_masks(kept[1])
            else:
                x[alive], masks = relin.means_active(rows, idx, flags[idx], runner(smap))
        else:
            x[alive] = relin.means(rows, idx, flags[idx])
    root = h.var_of.get(c.root)
    if root is not None:
        x[ids == root] = IDENTITY
    return np.ascontiguousarray(x), masks


def _trim_thresholds(robust: npt.NDArray[np.uint8], w: Array, kind: npt.NDArray[np.int32]
                     ) -> Array:
    """Per factor: the chi-square quantile :data:`TRIM_QUANTILE` for its live dimensions (the
    nonzero diagonal of its square-root information) if it is a gated loop closure, else 0."""
    diag6 = w[:, [0, 2, 5, 9, 14, 20]] != 0.0
    diag3 = w[:, [0, 2, 5]] != 0.0
    dof = np.where(robust != 0, np.where(kind == 0, diag6.sum(axis=1), diag3.sum(axis=1)), 0)
    out = np.zeros(len(robust))
    for d in np.unique(dof):  # at most 6 distinct values
        if d > 0:
            out[dof == d] = chi2_quantile(TRIM_QUANTILE, int(d))
    return out


def active_coordinates(rows: Array, flags: npt.NDArray[np.uint8]) -> tuple[int, int]:
    """Bit masks of the pose (x y z rx ry rz) and point (x y z) coordinates in which some frame
    of a component (host ``rows``, root first) other than its root varies: the others (a planar
    map's z, qx, qy; rotations an input never let vary) are held, as the filter holds them."""
    idx = np.arange(1, len(rows), dtype=np.int64)
    return relin.active(rows, idx, flags[idx])


def _problem(smap: Relinearizable, h: FactorHistory, cid: int, ids: npt.NDArray[np.int64],
             fmask: npt.NDArray[np.bool_], priors: list[Prior], kept: npt.NDArray[np.uint8],
             host: tuple[Array, npt.NDArray[np.uint8]] | None = None) -> relin.Problem:
    rows, flags = host_rows(smap, cid) if host is None else host
    local = np.full(h.vars.n, -1, dtype=np.int64)
    local[ids] = np.arange(len(ids))
    root = h.var_of[smap._comps[cid].root]
    fv = local[h.factors["vars"][fmask]].astype(np.int32)
    pvoff, pvars, pdoff, prows, pdata = [0], [], [0], [], []
    for p in priors:
        pvars.append(local[p.vars].astype(np.int32))
        pvoff.append(pvoff[-1] + len(p.vars))
        block = np.concatenate([p.zhat.ravel(), p.r.ravel(), p.d])
        pdata.append(block)
        pdoff.append(pdoff[-1] + len(block))
        prows.append(p.r.shape[0])
    x, masks = _estimates(smap, h, cid, ids, rows, flags)
    pose_active, point_active = active_coordinates(rows, flags) if masks is None else masks
    return relin.Problem(
        pose_active=pose_active, point_active=point_active,
        ftrim=_trim_thresholds(h.factors["robust"][fmask], h.factors["w"][fmask],
                               h.factors["kind"][fmask]),
        vkind=np.ascontiguousarray(h.vars["kind"][ids], dtype=np.int32),
        vfixed=(ids == root).astype(np.uint8), vkept=kept,
        x=x,
        fkind=np.ascontiguousarray(h.factors["kind"][fmask], dtype=np.int32),
        fvars=np.ascontiguousarray(fv), fz=np.ascontiguousarray(h.factors["z"][fmask]),
        fw=np.ascontiguousarray(h.factors["w"][fmask]),
        pvoff=np.array(pvoff, dtype=np.int64),
        pvars=np.concatenate(pvars) if pvars else np.zeros(0, np.int32),
        pdoff=np.array(pdoff, dtype=np.int64), prows=np.array(prows, dtype=np.int64),
        pdata=np.concatenate(pdata) if pdata else np.zeros(0))


def why_not(smap: Relinearizable, cid: int) -> str:
    """Why component ``cid`` cannot be relinearised ("" if it can)."""
    h = smap.factor_history
    if h is None:
        return "this map keeps no history (options: history=None)"
    g = h.groups.get(cid)
    if g is None:
        return "no history"
    if g.tainted:
        return g.tainted
    c = smap._comps[cid]
    if len(c) < 2:
        return "a single frame"
    if any(f not in h.var_of for f in c.frames):
        return "frames without history"
    return ""


def relinearize_component(smap: Relinearizable, cid: int, *, readmit_only: bool = False
                          ) -> ComponentRelin:
    """Solve component ``cid`` over its whole history and redraw its edges (see the module
    docstring). A skipped component changes nothing; a failure raises and changes nothing.
    ``readmit_only``: only if the solve admits a refused closure (:attr:`Policy.readmit`);
    else the component is left as it was (skipped, "nothing to re-admit")."""
    c = smap._comps[cid]
    reason = why_not(smap, cid)
    if reason:
        return ComponentRelin(c.root, skipped=reason)
    h = smap.factor_history
    assert h is not None
    ids = h.group_vars(cid)
    fmask = h.vars["group"][h.factors["vars"][:, 0]] == cid
    gset = set(ids.tolist())
    priors = [p for p in h.priors if int(p.vars[0]) in gset]
    kept = h.vars["alive"][ids].astype(np.uint8)
    # a component in host memory is read in place (the redraw writes into a copy)
    host = (c.rows, c.point_flags[: len(c)]) if isinstance(c, Component) else host_rows(smap, cid)
    prob = _problem(smap, h, cid, ids, fmask, priors, kept, host)
    sol = relin.solve(prob, max_iter=MAX_ITERATIONS, tol=TOLERANCE)
    readmitted = 0
    undo = None
    try:
        cand = h.pending_of(cid)
        if len(cand):
            admit = _admissible(h, ids, cand, prob)
            if len(admit):
                readmitted = len(admit)
                undo = _admit(h, admit, calibrating(smap.policy))
                sol.close()
                fmask = h.vars["group"][h.factors["vars"][:, 0]] == cid
                x = prob.x
                prob = _problem(smap, h, cid, ids, fmask, priors, kept, host)
                prob.x[:] = x  # from the solution without them
                sol = relin.solve(prob, max_iter=MAX_ITERATIONS, tol=TOLERANCE)
        if readmit_only and not readmitted:
            sol.close()
            return ComponentRelin(c.root, skipped="nothing to re-admit")
        with sol:
            slot = np.full(len(ids), -1, dtype=np.int64)
            alive = np.flatnonzero(kept)
            slot[alive] = [c.index[h.frame_of[int(v)]] for v in ids[alive]]
            slot[ids == h.var_of[c.root]] = -1
            m = len(c)
            out, flags = _redraw_buffer(smap, c) if isinstance(c, Component) else host
            pol = smap.policy
            sol.redraw(out, slot, _key(h, cid), spread=1.0 if pol is None else pol.spread)
            st = sol.stats
        if kernel.canonicalize_frames(out, flags, 1, m, False) != kernel.OK or \
                not np.isfinite(out[:m]).all():
            raise NumericalError("the relinearisation produced non-finite samples")
    except BaseException:
        sol.close()
        if undo is not None:  # a failure changes nothing: the admitted ones are pending again
            undo()
        raise
    if isinstance(c, Component):  # the old buffer, of the same capacity, is the next spare
        smap._comps[cid] = Component.in_buffer(list(c.frames), c.point_list(), out)
        smap._spare = c.buffer
    else:
        replace_rows(smap, cid, out)
    h.vars["est"][ids] = relin.transform(h.groups[cid].world, prob.x, prob.vkind)
    h.groups[cid].since = 0
    h.n_relin += 1
    return ComponentRelin(c.root, m, len(ids), int(np.count_nonzero(fmask)) + len(priors),
                          st.iterations, st.cost_before, st.cost_after, st.trimmed,
                          readmitted=readmitted)


def _admissible(h: FactorHistory, ids: npt.NDArray[np.int64], cand: npt.NDArray[np.int64],
                prob: relin.Problem) -> npt.NDArray[np.int64]:
    """The refused closures (rows ``cand`` of the history's pending table) whose chi-square
    at the solution ``prob.x`` (variables ``ids``) is within :data:`TRIM_QUANTILE` for their
    dof: those a relinearisation with them would not trim. Each chi-square is the kernel's
    (a one-factor problem at the solution, no iteration), in row order."""
    local = np.full(h.vars.n, -1, dtype=np.int64)
    local[ids] = np.arange(len(ids))
    pend = h.pending
    kinds = pend["kind"][cand]
    thr = _trim_thresholds(np.ones(len(cand), dtype=np.uint8), pend["w"][cand], kinds)
    out = []
    for k, row in enumerate(cand):
        a, b = (int(local[v]) for v in pend["vars"][row])
        if a < 0 or b < 0 or not thr[k] > 0.0:
            continue
        one = relin.Problem(
            vkind=np.ascontiguousarray(prob.vkind[[a, b]]),
            vfixed=np.array([1, 0], dtype=np.uint8), vkept=np.array([0, 1], dtype=np.uint8),
            x=np.ascontiguousarray(prob.x[[a, b]]),
            fkind=np.array([kinds[k]], dtype=np.int32), fvars=np.array([[0, 1]], np.int32),
            fz=np.ascontiguousarray(pend["z"][row][None]),
            fw=np.ascontiguousarray(pend["w"][row][None]),
            pvoff=np.zeros(1, np.int64), pvars=np.zeros(0, np.int32),
            pdoff=np.zeros(1, np.int64), prows=np.zeros(0, np.int64), pdata=np.zeros(0),
            pose_active=prob.pose_active, point_active=prob.point_active)
        try:
            with relin.solve(one, max_iter=0) as s1:
                chi2 = s1.stats.cost_before
        except McsmError:
            continue
        if chi2 <= thr[k]:
            out.append(int(row))
    return np.array(out, dtype=np.int64)


def _admit(h: FactorHistory, rows: npt.NDArray[np.int64], calibrate: bool = False
           ) -> Callable[[], None]:
    """Refused closures (pending rows) become factors of the history, gated (so a later
    relinearisation trims them like any other), and leave the pending table (with
    ``calibrate``, their arrival ratios join ``admitted_u``); returns what undoes it (a solve
    that fails after it)."""
    pend = h.pending
    saved = (h.factors.n, h.n_inputs, h.n_readmitted, pend.to_plain(), list(h.admitted_u))

    def undo() -> None:
        h.factors.n, h.n_inputs, h.n_readmitted = saved[:3]
        pend.load(saved[3])
        h.admitted_u = saved[4]
    if calibrate:
        h.admitted_u = (h.admitted_u + pend["u"][rows].tolist())[-ADMITTED_KEEP:]
    for row in rows:
        a, b = (int(v) for v in pend["vars"][row])
        h.add_factor(bool(pend["kind"][row]), a, b, pend["z"][row].copy(),
                     pend["w"][row].copy(), robust=True)
    keep = np.ones(pend.n, dtype=bool)
    keep[rows] = False
    pend.keep(keep)
    h.n_readmitted += len(rows)
    return undo


def relinearize(smap: Relinearizable, cids: list[int], trigger: str) -> RelinReport:
    """Relinearise components ``cids`` in order; the report. A component whose solve fails is
    left as it was and reported as skipped (never raised: an automatic relinearisation runs
    after its update was applied). Trigger ``readmit`` changes a component only if it admits
    a refused closure."""
    t0 = time.perf_counter()
    comps = []
    for cid in cids:
        try:
            comps.append(relinearize_component(smap, cid, readmit_only=trigger == "readmit"))
        except McsmError as exc:
            comps.append(ComponentRelin(smap._comps[cid].root,
                                        skipped=f"failed: {type(exc).__name__}: {exc}"))
    return RelinReport(trigger, tuple(comps), time.perf_counter() - t0)


__all__ = ["Policy", "RECOMMENDED", "REPAIR_ONLY", "RelinReport", "ComponentRelin", "relinearize",
           "relinearize_component", "why_not", "estimates", "calibrating",
           "DEFAULT_HISTORY_BYTES", "REGATE_WINDOW", "TRIM_QUANTILE", "CALIBRATE_QUANTILE"]
