"""Marginalisation of a bounded history: the oldest removed variables of a component become a
dense prior on the variables they touch (:attr:`mcsm.core.factors.FactorHistory.priors`), so
that a long-running bounded map keeps a bounded history (docs/relinearisation.md)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import relin
from mcsm.core.factors import FactorHistory, Prior
from mcsm.core.relinearize import Relinearizable, _problem
from mcsm.errors import McsmError


def marginalise(smap: Relinearizable) -> int:
    """While the history is over its bound: marginalise the oldest quarter of the removed
    variables of the component holding the oldest one into a dense prior on the variables
    they touch (at their current estimates), until the history is at 3/4 of its bound or no
    removed variable is left. Returns how many variables went."""
    h = smap.factor_history
    assert h is not None
    target = h.bound_bytes * 3 // 4
    gone = 0
    while h.nbytes() > target:
        removed = np.flatnonzero(h.vars["alive"] == 0)
        if not len(removed):
            break
        cid = int(h.vars["group"][removed[0]])
        mine = removed[h.vars["group"][removed] == cid]
        s = mine[: max(1, (len(mine) + 3) // 4)]
        root = h.var_of.get(smap._comps[cid].root)
        if root is None or h.vars["kind"][root] != 0:
            break  # a component rooted at a point anchors no prior: over the bound for now
        try:
            _marginalise_set(smap, h, cid, s)
        except McsmError:  # never raised out of an applied update; tried again next time
            break
        gone += len(s)
    _trim_heap()
    return gone


def _trim_heap() -> None:
    """Give the C heap's free pages back to the system after a marginalisation (glibc keeps
    the solve's freed blocks otherwise, and a bounded map would not stay a bounded process)."""
    if _LIBC is not None:
        _LIBC.malloc_trim(0)


def _libc() -> Any:
    import ctypes
    import ctypes.util
    import sys

    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim.argtypes = [ctypes.c_size_t]
        return libc
    except (OSError, AttributeError):  # not glibc
        return None


_LIBC = _libc()


def _marginalise_set(smap: Relinearizable, h: FactorHistory, cid: int,
                     s: npt.NDArray[np.int64]) -> None:
    in_s = np.zeros(h.vars.n, dtype=bool)
    in_s[s] = True
    fv = h.factors["vars"]
    fmask = in_s[fv[:, 0]] | in_s[fv[:, 1]]
    priors = [p for p in h.priors if np.any(in_s[p.vars])]
    root = h.var_of[smap._comps[cid].root]
    touched = [fv[fmask].ravel(), np.array([root])] + [p.vars for p in priors]
    ids = np.unique(np.concatenate(touched).astype(np.int64))
    kept = (~in_s[ids]).astype(np.uint8)
    prob = _problem(smap, h, cid, ids, fmask, priors, kept)
    border = ids[(kept != 0) & (ids != root)]
    if len(border):
        with relin.solve(prob, max_iter=0) as sol:
            r, d = sol.marginal()
        live = np.any(r != 0.0, axis=1) | (d != 0.0)
        if np.any(live):
            sel = (kept != 0) & (ids != root)
            h.priors.append(Prior(np.concatenate([[root], border]).astype(np.int32),
                                  np.ascontiguousarray(prob.x[sel]),
                                  np.ascontiguousarray(r[live]), np.ascontiguousarray(d[live])))
    h._delete_vars(in_s)
    h.n_marginalised += len(s)


__all__ = ["marginalise"]
