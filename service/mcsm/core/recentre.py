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
    """Move the frames of variables ``alive`` from their means to ``target``: into the spare
    buffer, swapped in after the checks (as the joint update), or into the host copy of a
    component in device memory, uploaded."""
    comp = smap._comps[cid]
    hist = smap.factor_history
    assert hist is not None
    slot = np.array([comp.index[hist.frame_of[int(v)]] for v in alive], dtype=np.int64)
    moved = slot != 0  # the root's edge is the identity
    slot = slot[moved]
    out = rows
    if isinstance(comp, Component):
        buf, spare = comp.buffer, smap._spare
        out = spare if spare is not None and spare.shape == buf.shape else np.empty_like(buf)
        rows = buf
    # copied (a host component) or in place (a host copy), moved, canonicalised, checked
    if relin.recentre(rows, out, len(comp), flags, slot, mean[moved], target[moved],
                      runner(smap)) != relin.OK:
        raise NumericalError("the re-centring produced non-finite samples")
    if isinstance(comp, Component):
        smap._spare = comp.swap_buffer(out)
    else:
        replace_rows(smap, cid, out)


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


__all__ = ["recentre", "recentre_component"]
