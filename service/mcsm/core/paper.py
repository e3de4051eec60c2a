"""The paper's own loop-closure update (``method="paper"``, PAPER §3 Fig. 3), kept to
reproduce the paper: re-root at ``a``, merge the main edge with the revised merge, propagate to
every leaf with ``E_j ⊗ (G' ⊕ G^R ⊕ E_j)``. It diverges on the paper's own scenario at N = 200
and on pose graphs (README, limitations).

In the tangent chart (the default space) it runs in the compiled kernel, fused per frame
(re-rooting, shift and revised merge of each edge while it sits in cache) and portable like
the joint update. In the quaternion space (the paper's 7-D Euclidean treatment) it runs on
numpy (einsum, BLAS products, LAPACK ``eigh``) and is **machine-bound**: a recording of such a
map replays bit-identically only on the machine family that made it
(``StochasticMap.portable`` is False).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel
from mcsm.core.at import (
    compound,
    identity,
    invert,
    merge_correlated,
    merge_correlated_shifted,
)
from mcsm.core.storage import Component, identity_rows, to_rows
from mcsm.errors import NumericalError

Array = npt.NDArray[np.float64]


def paper_update_tangent(comp: Component, a: str, b: str, x_rows: Array, point: bool,
                         run: Callable[[Callable[[int, int], int], int], list[int]]
                         ) -> Component:
    """The component after the loop closure ``x_rows`` (``(7, N)`` or ``(3, N)``) from a to b,
    re-rooted at a, computed by the kernel; ``run(fn, m)`` calls ``fn(lo, hi)`` over frame
    ranges covering [0, m) (on threads) and returns the codes."""
    n = comp.n_samples
    m = len(comp)
    k, ib_old = comp.index[a], comp.index[b]
    pre = kernel.invert(comp.edge_rows(k)) if k != 0 else None
    if pre is None:
        g = comp.edge_rows(ib_old).copy()
    else:
        g = kernel.compound(pre, comp.edge_rows(ib_old))
        if comp.is_point(ib_old):
            g[3], g[4:] = 1.0, 0.0
    if not np.isfinite(g).all():
        raise NumericalError("re-rooting produced non-finite samples")
    g_new = kernel.paper_main_edge(g, x_rows, point)
    shift = kernel.compound(g_new, kernel.invert(g))
    rows, flags = comp.rows, comp.point_flags
    out = np.empty((m, 7, n))

    def frames(lo: int, hi: int) -> int:
        # old frames 0..k-1 become 1..k, old k+1.. keep their index; old k becomes the root
        codes = [kernel.paper_frames(pre, shift, rows, out, flags, lo, min(hi, k), 1)
                 if lo < k else kernel.OK,
                 kernel.paper_frames(pre, shift, rows, out, flags, max(lo, k + 1), hi, 0)
                 if hi > k + 1 else kernel.OK]
        return max(codes)

    if any(rc != kernel.OK for rc in run(frames, m)):
        raise NumericalError("the loop closure produced non-finite samples")
    order = [k] + [i for i in range(m) if i != k]
    is_point = [bool(flags[i]) for i in order]
    out[order.index(ib_old)] = g_new
    for i, p in enumerate(is_point):
        if p:
            out[i, 3], out[i, 4:] = 1.0, 0.0
    out[0] = identity_rows(n)
    if not np.isfinite(out).all():
        raise NumericalError("the loop closure produced non-finite samples")
    return Component([comp.frames[i] for i in order], is_point, out)


def paper_update(comp: Component, a: str, b: str, x: Array, point: bool, space: str
                 ) -> Component:
    """The component after the loop closure ``x`` (``(N, 7)`` or ``(N, 3)``) from a to b,
    re-rooted at a, on numpy (machine-bound; the reference of :func:`paper_update_tangent`
    in the tangent chart). Raises NumericalError (component unchanged) on non-finite
    results."""
    edges = comp.edges()
    is_point = np.array(comp.point_list(), dtype=bool)
    frames = list(comp.frames)
    n = edges.shape[1]
    k, ib_old = comp.index[a], comp.index[b]
    order = [k] + [i for i in range(len(frames)) if i != k]
    if space == "tangent":
        x_k_r = invert(edges[k]) if k != 0 else None
        g = edges[ib_old] if x_k_r is None else compound(x_k_r, edges[ib_old])
        if x_k_r is not None and is_point[ib_old]:
            g[:, 3:] = (1.0, 0.0, 0.0, 0.0)
        _check_finite(g, "re-rooting")
        g_new, shift = _merge_main_edge(g, x, point, space)
        out = np.empty_like(edges)
        for lo, hi, dst in ((0, k, 1), (k + 1, len(frames), k + 1)):
            if hi > lo:
                merge_correlated_shifted(edges[lo:hi], shift, pre=x_k_r,
                                         pin=is_point[lo:hi] if x_k_r is not None else None,
                                         out=out[dst:dst + hi - lo])
        new_point = is_point[order]
        ib = order.index(ib_old)
        out[ib] = g_new
    else:
        if k != 0:
            x_k_r = invert(edges[k])
            moved = compound(x_k_r[None], edges)
            moved[k] = identity(n)
            edges = moved[order]
            is_point = is_point[order]
            _pin(edges, is_point)
            edges[0] = identity(n)
            frames = [frames[i] for i in order]
            order = list(range(len(frames)))
        new_point = is_point
        ib = frames.index(b)
        g_new, shift = _merge_main_edge(edges[ib], x, point, space)
        others = np.ones(len(frames), dtype=bool)
        others[[0, ib]] = False
        out = edges.copy()
        if others.any():
            e_j = edges[others]
            out[others] = merge_correlated(e_j, compound(shift[None], e_j), "quaternion")
        out[ib] = g_new
    _pin(out, new_point)
    out[0] = identity(n)
    _check_finite(out, "the loop closure")
    names = [frames[i] for i in order]
    return Component(names, [bool(p) for p in new_point], to_rows(out))


def _merge_main_edge(g: Array, x: Array, point: bool, space: str) -> tuple[Array, Array]:
    """The merged main edge G' = G ⊗ X of PAPER Fig. 3 and the shift G' ⊕ G^R."""
    if point:
        g_new = g.copy()
        g_new[:, :3] = _merge_points(g[:, :3], x)
    else:
        g_new = merge_correlated(g, x, space)  # type: ignore[arg-type]
    return g_new, compound(g_new, invert(g))


def _merge_points(p_g: Array, p_x: Array) -> Array:
    """Revised merge (eq. 6) of two 3-D point sample sets (the main edge of a point update)."""
    from mcsm.core.at import merge_vectors, sample_cov

    cov_c, cov_d, cov_diff = sample_cov(p_g), sample_cov(p_x), sample_cov(p_g - p_x)
    c_x = 0.5 * (cov_c + cov_d - cov_diff)
    return merge_vectors(p_g, p_x, cov_c - c_x, cov_diff)


def _pin(edges: Array, is_point: npt.NDArray[np.bool_]) -> None:
    if is_point.any():
        edges[is_point, :, 3:] = (1.0, 0.0, 0.0, 0.0)


def _check_finite(edges: Array, what: str) -> None:
    if not np.isfinite(edges).all():
        raise NumericalError(f"{what} produced non-finite samples")


__all__ = ["paper_update", "paper_update_tangent"]
