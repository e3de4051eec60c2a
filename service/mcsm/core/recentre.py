"""Re-centring (``Policy(recentre=True)``): after an accepted loop closure, solve the component
over its history as a relinearisation does (:mod:`mcsm.core.relinearize`) and move each frame's
samples so that their mean in the chart is the solution, each sample keeping its deviation.

The filter's joint covariance and cross-correlations stay; its means become the maximum a
posteriori estimate of everything the component accepted (ensemble-variational re-centring),
so the filter's updates between two relinearisations no longer carry them away. With
``Policy.readmit`` every re-centring also re-checks the component's refused closures at its
solution and admits those within the trim quantile (the relinearisation's rule), as soon as the
map agrees with them. The shift is the kernel's ``mr_recentre`` (one fixed sequence of
operations per value), so replay recomputes it bit for bit. docs/relinearisation.md
("Re-centring") measures it.
"""

from __future__ import annotations

import time

import numpy as np
import numpy.typing as npt

from mcsm.core import relin
from mcsm.core.relinearize import (
    MAX_ITERATIONS,
    TOLERANCE,
    ComponentRelin,
    Relinearizable,
    RelinReport,
    _admissible,
    _admit,
    _problem,
    calibrating,
    host_rows,
    replace_rows,
    runner,
    why_not,
)
from mcsm.core.storage import Component
from mcsm.errors import McsmError, NumericalError

Array = npt.NDArray[np.float64]


def recentring(smap: Relinearizable) -> bool:
    """Whether the map re-centres after an accepted closure (its joint update then keeps the
    frames' means it takes in its pass, for the solve to start from)."""
    p = smap.policy
    return p is not None and p.recentre and smap.factor_history is not None


def recentre_component(smap: Relinearizable, cid: int) -> ComponentRelin:
    """Solve component ``cid`` (with the refused closures it now agrees with, under
    ``Policy.readmit``) and move every frame's samples so that their mean in the chart is the
    solution. The counters of the other triggers do not change. A skipped component changes
    nothing; a failure raises and changes nothing."""
    c = smap._comps[cid]
    reason = why_not(smap, cid)
    if reason:
        return ComponentRelin(c.root, skipped=reason)
    h = smap.factor_history
    assert h is not None
    ids = h.group_vars(cid)
    gset = set(ids.tolist())
    priors = [p for p in h.priors if int(p.vars[0]) in gset]
    kept = h.vars["alive"][ids].astype(np.uint8)
    free = np.zeros_like(kept)
    # a component in host memory is read in place; else from a host copy, uploaded after
    rows, flags = (c.rows, c.point_flags) if isinstance(c, Component) else host_rows(smap, cid)

    def problem() -> relin.Problem:
        # No redraw follows, so no variable need be eliminated last: the ordering is minimum
        # degree over all of them (less fill where removed poses saw the kept landmarks)
        fmask = h.vars["group"][h.factors["vars"][:, 0]] == cid
        return _problem(smap, h, cid, ids, fmask, priors, free, (rows, flags))

    prob = problem()
    start = prob.x.copy()  # the frames' means (estimates)
    sol = relin.solve(prob, max_iter=MAX_ITERATIONS, tol=TOLERANCE, keep_factor=False)
    readmitted, undo = 0, None
    try:
        pol = smap.policy
        none = np.zeros(0, dtype=np.int64)
        cand = h.pending_of(cid, burst_only=False) if pol is not None and pol.readmit else none
        admit = _admissible(h, ids, cand, prob) if len(cand) else none
        if len(admit):
            readmitted = len(admit)
            undo = _admit(h, admit, calibrating(pol))
            sol.close()
            x = prob.x
            prob = problem()
            prob.x[:] = x  # from the solution without them
            sol = relin.solve(prob, max_iter=MAX_ITERATIONS, tol=TOLERANCE, keep_factor=False)
        with sol:
            st = sol.stats
        _shift(smap, cid, ids[np.flatnonzero(kept)], rows, flags, start[kept != 0],
               prob.x[kept != 0])
    except BaseException:
        sol.close()
        if undo is not None:  # a failure changes nothing: the admitted ones are pending again
            undo()
        raise
    h.vars["est"][ids] = relin.transform(h.groups[cid].world, prob.x, prob.vkind)
    nf = int(np.count_nonzero(h.vars["group"][h.factors["vars"][:, 0]] == cid))
    return ComponentRelin(c.root, len(c), len(ids), nf + len(priors), st.iterations,
                          st.cost_before, st.cost_after, st.trimmed, readmitted=readmitted)


def _shift(smap: Relinearizable, cid: int, alive: npt.NDArray[np.int64], rows: Array,
           flags: npt.NDArray[np.uint8], mean: Array, target: Array) -> None:
    """Move the frames of variables ``alive`` from their means to ``target``: in place where
    no value can come out non-finite (:func:`_shifts_finitely`), else into the spare buffer,
    swapped in after the checks (as the joint update), or into the host copy of a component in
    device memory, uploaded. The same bits every way."""
    comp = smap._comps[cid]
    hist = smap.factor_history
    assert hist is not None
    slot = np.array([comp.index[hist.frame_of[int(v)]] for v in alive], dtype=np.int64)
    moved = slot != 0  # the root's edge is the identity
    slot, mean, target = slot[moved], mean[moved], target[moved]
    out, in_place = rows, False
    if isinstance(comp, Component):
        buf, spare = comp.buffer, smap._spare
        in_place = _shifts_finitely(comp, slot, mean, target)
        if in_place:
            out = buf
        else:
            out = spare if spare is not None and spare.shape == buf.shape else \
                np.empty_like(buf)
        rows = buf
    # copied or in place, moved, canonicalised, checked
    if relin.recentre(rows, out, len(comp), flags, slot, mean, target,
                      runner(smap)) != relin.OK:
        if in_place:  # excluded by _shifts_finitely: the component is partly moved
            raise RuntimeError("mcsm internal error: a re-centring in place produced "
                               "non-finite samples")
        raise NumericalError("the re-centring produced non-finite samples")
    if isinstance(comp, Component):
        if in_place:
            comp.written()
        else:
            smap._spare = comp.swap_buffer(out)
    else:
        replace_rows(smap, cid, out)


SHIFT_LIMIT = 1e300
"""Translations, means and targets within this magnitude cannot overflow in a shift (their sum
is at most 3e300)."""


def _shifts_finitely(comp: Component, slot: npt.NDArray[np.int64], mean: Array,
                     target: Array) -> bool:
    """Whether the shift of frames ``slot`` may write in place (its writes save a pass over
    the spare buffer): a failure would then leave the component partly moved, so only where
    no value can come out non-finite. That holds when the update's pass kept the means of
    this very buffer (nothing written since: every value finite, each frame's largest
    translation magnitude known) and every translation, mean and target is within
    :data:`SHIFT_LIMIT` (no sum overflows), and every target rotation's norm is in [0.5, 2]:
    the means' rotations are unit (chordal means), the samples' too (the pass renormalised
    them), so no rotation normalised on the way is near zero; canonicalisation only flips
    signs, and points are pinned."""
    kept = comp.pass_means()
    if kept is None:
        return False
    norms = np.linalg.norm(target[:, 3:], axis=1)
    return bool(np.all(kept[2][slot] <= SHIFT_LIMIT)
                and np.all(np.abs(mean[:, :3]) <= SHIFT_LIMIT)
                and np.all(np.abs(target[:, :3]) <= SHIFT_LIMIT)
                and np.all((norms >= 0.5) & (norms <= 2.0)))


def recentre(smap: Relinearizable, cids: list[int]) -> RelinReport:
    """Re-centre components ``cids`` in order; the report (trigger ``recentre``). A component
    whose solve fails is left as it was and reported as skipped (never raised: it runs after
    its update was applied)."""
    t0 = time.perf_counter()
    comps = []
    for cid in cids:
        try:
            comps.append(recentre_component(smap, cid))
        except McsmError as exc:
            comps.append(ComponentRelin(smap._comps[cid].root,
                                        skipped=f"failed: {type(exc).__name__}: {exc}"))
    return RelinReport("recentre", tuple(comps), time.perf_counter() - t0)


__all__ = ["recentre", "recentre_component", "recentring"]
