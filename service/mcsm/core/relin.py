"""Bindings of the relinearisation kernel (``_relin.c``, ``_relin_draw.c``, linked into the
same library as ``_kernel.c``), loaded with ctypes.

:func:`moments` reduces an input's samples to its mean and the square-root information of its
covariance in the project's chart; :func:`solve` runs Gauss-Newton / Levenberg-Marquardt over
a set of factors (:class:`Problem`) and keeps the factorisation, from which :func:`redraw`
draws a component's edges and :func:`marginal` takes the Gaussian of the kept variables. All of
it in a fixed order of operations (only +, −, ×, ÷, √; an integer-arithmetic ordering; a
counter-based normal generator), so a relinearisation replays to the same bits on every CPU.
docs/design.md ("Relinearisation") describes the method.
"""

from __future__ import annotations

import ctypes
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel
from mcsm.errors import NumericalError

Array = npt.NDArray[np.float64]
Ints = npt.NDArray[np.int32]

RELIN_VERSION = 7
SPREAD_ROTATION_CAP = 0.3
"""Radians: a redraw's ``spread`` is lowered for a pose whose rotation deviations would get an
RMS above this (to this, never below the posterior itself): the chart and the filter's updates
after the redraw degrade at such spreads (w10000, whose far poses' rotation RMS exceeds it, had
updates refused at 0.43 rad)."""
EXACT_MAX = 2048
"""Largest number of kept dimensions redrawn with an exact sample covariance (the whitening
costs O(K² N + K³))."""
OK, NONFINITE, BAD_ARGS, NO_MEMORY = 0, 3, 4, 5

_P = ctypes.c_void_p
_L = ctypes.c_long
_I = ctypes.c_int
_I64 = ctypes.c_int64
_D = ctypes.c_double
_U64 = ctypes.c_uint64


class _Problem(ctypes.Structure):
    _fields_ = [("nv", _I64), ("vkind", _P), ("vfixed", _P), ("vkept", _P), ("x", _P),
                ("nf", _I64), ("fkind", _P), ("fvars", _P), ("fz", _P), ("fw", _P),
                ("ftrim", _P),
                ("np", _I64), ("pvoff", _P), ("pvars", _P), ("pdoff", _P), ("prows", _P),
                ("pdata", _P), ("pose_active", _I64), ("point_active", _I64),
                ("max_iter", _I64), ("tol", _D), ("keep_factor", _I64), ("stats", _D * 11),
                ("state", _P)]


_lib = kernel._lib
for _name, _args, _res in (
        ("mr_version", (), _I),
        ("mr_problem_size", (), _L),
        ("mr_moments", (_P, _L, _I, _P, _P), _I),
        ("mr_means", (_P, _P, _L, _L, _P, _P), None),
        ("mr_recentre", (_P, _P, _L, _L, _L, _P, _P, _L, _P, _P), _I),
        ("mr_active", (_P, _P, _L, _L, _P, _P), None),
        ("mr_means_active", (_P, _P, _L, _L, _P, _P, _P), None),
        ("mr_means_live", (_P, _P, _L, _L, _P, _P, _P), None),
        ("mr_joint_frames_means", (_P, _P, _P, _P, _L, _L, _P, _P, _P), _I),
        ("mr_spread", (_P, _P, _L, _L, _P, _P), None),
        ("mr_transform", (_P, _I, _P, _P, _L, _P), None),
        ("mr_solve", (_P,), _I),
        ("mr_free", (_P,), None),
        ("mr_marginal", (_P, _P, _P), _I),
        ("mr_redraw", (_P, _P, _P, _L, _U64, _L, _D, _D), _I),
        ("mr_normals", (_U64, _U64, _L, _P), None)):
    _fn = getattr(_lib, _name)
    _fn.argtypes = list(_args)
    _fn.restype = _res
if _lib.mr_version() != RELIN_VERSION or _lib.mr_problem_size() != ctypes.sizeof(_Problem):
    raise kernel.KernelMissing("mcsm's compiled kernel does not match its relinearisation "
                               "bindings: reinstall (`pip install -e .`)")

ptr = kernel.ptr
Runner = Callable[[Callable[[int, int], int], int], list[int]]
"""``run(fn, m)``: ``fn(lo, hi)`` over frame ranges covering ``[0, m)``, the codes in range
order (:func:`mcsm.core.joint.run_ranges` with a thread count)."""


def _one(fn: Callable[[int, int], int], m: int) -> list[int]:
    return [fn(0, m)]


def moments(x_rows: Array, point: bool) -> tuple[Array, Array]:
    """Mean ``(7,)`` (t, q; a point: t and the identity) and packed square-root information
    ``(21,)`` of an input's samples in rows ``(7, N)`` or ``(3, N)`` (a point: 6 used)."""
    xr = np.ascontiguousarray(x_rows, dtype=np.float64)
    z = np.empty(7)
    w = np.zeros(21)
    if _lib.mr_moments(ptr(xr), xr.shape[-1], int(point), ptr(z), ptr(w)) != OK:
        raise NumericalError("the input's moments are not finite")
    return z, w


def means(buf: Array, idx: npt.NDArray[np.int64], point: npt.NDArray[np.uint8]) -> Array:
    """Mean poses ``(k, 7)`` of frames ``idx`` of a component buffer ``(cap, 7, N)``."""
    out = np.empty((len(idx), 7))
    if len(idx):
        i = np.ascontiguousarray(idx, dtype=np.int64)
        p = np.ascontiguousarray(point, dtype=np.uint8)
        _lib.mr_means(ptr(buf), ptr(i), len(i), buf.shape[-1], ptr(p), ptr(out))
    return out


def recentre(src: Array, dst: Array, length: int, point: npt.NDArray[np.uint8],
             idx: npt.NDArray[np.int64], mu: Array, target: Array,
             run: Runner | None = None) -> int:
    """Frames ``[0, length)`` of a component buffer ``src`` ``(cap, 7, N)`` into ``dst`` (the
    same array or one of its shape), frames ``idx`` (not the root) moved on the way from their
    means ``mu`` ``(k, 7)`` (:func:`means`) to ``target`` ``(k, 7)``, every sample keeping its
    chart deviation from the mean; frames ``1..length-1`` canonicalised as the kernel does
    (``point``: the component's flags). ``run(fn, m)``: how to run ``fn(lo, hi)`` over frame
    ranges covering ``[0, m)`` (threads; the values do not depend on the split), else one
    call. The kernel's status, the first range's that failed (non-finite: ``dst`` is partly
    written)."""
    if src.shape != dst.shape or not (src.flags.c_contiguous and dst.flags.c_contiguous):
        raise ValueError("src and dst must be C-contiguous buffers of one shape")
    i = np.ascontiguousarray(idx, dtype=np.int64)
    p = np.ascontiguousarray(point, dtype=np.uint8)
    m = np.ascontiguousarray(mu, dtype=np.float64)
    t = np.ascontiguousarray(target, dtype=np.float64)
    args = (ptr(src), ptr(dst))
    rest = (src.shape[-1], ptr(p), ptr(i), len(i), ptr(m), ptr(t))

    def one(lo: int, hi: int) -> int:
        return int(_lib.mr_recentre(*args, lo, hi, *rest))

    codes = (run or _one)(one, length)
    return next((c for c in codes if c != OK), OK)


def active(buf: Array, idx: npt.NDArray[np.int64], point: npt.NDArray[np.uint8]
           ) -> tuple[int, int]:
    """Bit masks of the pose (x y z rx ry rz) and point (x y z) chart coordinates in which some
    frame of ``idx`` of a component buffer ``(cap, 7, N)`` varies (a kind with no frame: every
    bit)."""
    out = np.zeros(2, dtype=np.int64)
    i = np.ascontiguousarray(idx, dtype=np.int64)
    p = np.ascontiguousarray(point, dtype=np.uint8)
    _lib.mr_active(ptr(buf), ptr(i), len(i), buf.shape[-1], ptr(p), ptr(out))
    return int(out[0]), int(out[1])


def means_active(buf: Array, idx: npt.NDArray[np.int64], point: npt.NDArray[np.uint8],
                 run: Runner | None = None) -> tuple[Array, tuple[int, int]]:
    """:func:`means` of frames ``idx`` and :func:`active` of those other than frame 0, in one
    pass over the frames (the same values as the two calls); ``run`` as :func:`recentre`'s
    (over parts of ``idx``: the masks are unions, so the split changes no value)."""
    out = np.empty((len(idx), 7))
    i = np.ascontiguousarray(idx, dtype=np.int64)
    p = np.ascontiguousarray(point, dtype=np.uint8)
    parts: dict[int, npt.NDArray[np.int64]] = {}

    def one(lo: int, hi: int) -> int:
        ls = parts[lo] = np.zeros(4, dtype=np.int64)
        if hi > lo:
            _lib.mr_means_live(ptr(buf), ptr(i[lo:hi]), hi - lo, buf.shape[-1], ptr(p[lo:hi]),
                               ptr(out[lo:hi]), ptr(ls))
        return OK

    (run or _one)(one, len(i))
    ls = np.bitwise_or.reduce(list(parts.values())) if parts else np.zeros(4, dtype=np.int64)
    return out, finish_masks(ls)


def joint_frames_means(args: kernel.JointArgs, edges: Array, out: Array,
                       point: npt.NDArray[np.uint8], lo: int, hi: int, means: Array,
                       big: Array, ls: npt.NDArray[np.int64]) -> int:
    """:func:`kernel.joint_frames` over frames [lo, hi) and, in the same pass, each output
    frame's mean into ``means[f]`` (``(M, 7)``), the largest magnitude of its translations into
    ``big[f]`` and the live chart coordinates of those other than frame 0 into ``ls`` (``(4,)``:
    pose and point bits, pose and point seen; OR-ed in): the values of :func:`means_active`
    over the output afterwards."""
    return int(_lib.mr_joint_frames_means(ctypes.byref(args), ptr(edges), ptr(out), ptr(point),
                                          lo, hi, ptr(means), ptr(big), ptr(ls)))


def finish_masks(ls: npt.NDArray[np.int64]) -> tuple[int, int]:
    """The masks of :func:`means_active` from the union ``ls`` of live bits and kinds seen (a
    kind with no frame: every bit)."""
    return int(ls[0]) if ls[2] else 0b111111, int(ls[1]) if ls[3] else 0b111


def spread(buf: Array, idx: npt.NDArray[np.int64], point: npt.NDArray[np.uint8]) -> Array:
    """``(k, 6)``: per frame of ``idx``, the largest difference of a sample from the first in
    each chart coordinate (0: the coordinate does not vary in the map): the definition
    :func:`active` answers from, kept as its reference (tests)."""
    out = np.zeros((len(idx), 6))
    if len(idx):
        i = np.ascontiguousarray(idx, dtype=np.int64)
        p = np.ascontiguousarray(point, dtype=np.uint8)
        _lib.mr_spread(ptr(buf), ptr(i), len(i), buf.shape[-1], ptr(p), ptr(out))
    return out


def transform(a: Array, b: Array, kind: Ints, invert: bool = False) -> Array:
    """``A ∘ b_j`` for poses ``b`` ``(k, 7)`` with ``A = a`` or ``a⁻¹`` (points: the identity
    rotation)."""
    out = np.empty_like(b)
    if len(b):
        aa = np.ascontiguousarray(a, dtype=np.float64)
        bb = np.ascontiguousarray(b, dtype=np.float64)
        kk = np.ascontiguousarray(kind, dtype=np.int32)
        _lib.mr_transform(ptr(aa), int(invert), ptr(bb), ptr(kk), len(bb), ptr(out))
    return out


def normals(key: int, counter: int, n: int) -> Array:
    """``n`` draws of the kernel's normal generator (stream ``key`` from ``counter``)."""
    out = np.empty(n)
    _lib.mr_normals(key & (2**64 - 1), counter, n, ptr(out))
    return out


@dataclass
class Problem:
    """The arrays of one solve (see ``_relin.h``). ``x`` ``(nv, 7)`` is updated in place."""

    vkind: Ints
    vfixed: npt.NDArray[np.uint8]
    vkept: npt.NDArray[np.uint8]
    x: Array
    fkind: Ints
    fvars: Ints
    fz: Array
    fw: Array
    pvoff: npt.NDArray[np.int64]
    pvars: Ints
    pdoff: npt.NDArray[np.int64]
    prows: npt.NDArray[np.int64]
    pdata: Array
    ftrim: Array | None = None  # per factor: chi-square above which a closure is left out
    pose_active: int = 0b111111
    point_active: int = 0b111


@dataclass
class SolveStats:
    """What one solve did."""

    iterations: int
    cost_before: float
    cost_after: float
    active: int  # bits 0-5: pose coordinates solved for; bits 6-8: point coordinates
    scalars: int
    kept_scalars: int
    factor_values: int
    factorisations: int
    dead: int
    trimmed: int = 0


class Solution:
    """A finished solve: its statistics and the factorisation (freed with :meth:`close`)."""

    def __init__(self, problem: Problem, max_iter: int, tol: float,
                 keep_factor: bool = True) -> None:
        self.problem = problem
        ftrim = problem.ftrim if problem.ftrim is not None else np.zeros(len(problem.fkind))
        self._arrays: list[npt.NDArray[Any]] = [np.ascontiguousarray(a) for a in (
            problem.vkind, problem.vfixed, problem.vkept, problem.fkind, problem.fvars,
            problem.fz, problem.fw, problem.pvoff, problem.pvars, problem.pdoff, problem.prows,
            problem.pdata, np.asarray(ftrim, dtype=np.float64))]
        (vkind, vfixed, vkept, fkind, fvars, fz, fw, pvoff, pvars, pdoff, prows,
         pdata, ftrim) = self._arrays
        x = problem.x
        if not x.flags.c_contiguous or x.dtype != np.float64:
            raise ValueError("x must be C-contiguous float64")
        s = _Problem()
        s.nv, s.vkind, s.vfixed, s.vkept, s.x = len(vkind), ptr(vkind), ptr(vfixed), \
            ptr(vkept), ptr(x)
        s.nf, s.fkind, s.fvars, s.fz, s.fw = len(fkind), ptr(fkind), ptr(fvars), ptr(fz), \
            ptr(fw)
        s.ftrim = ptr(ftrim)
        s.np = len(prows)
        s.pvoff, s.pvars, s.pdoff, s.prows, s.pdata = ptr(pvoff), ptr(pvars), ptr(pdoff), \
            ptr(prows), ptr(pdata)
        s.pose_active, s.point_active = int(problem.pose_active), int(problem.point_active)
        s.max_iter, s.tol, s.keep_factor = int(max_iter), float(tol), int(keep_factor)
        s.state = None
        self._s = s
        rc = _lib.mr_solve(ctypes.byref(s))
        if rc != OK:
            self.close()
            raise NumericalError(f"the relinearisation's solve failed (code {rc})")
        st = list(s.stats)
        self.stats = SolveStats(int(st[0]), st[1], st[2], int(st[3]), int(st[4]), int(st[5]),
                                int(st[6]), int(st[7]), int(st[8]), int(st[10]))

    def close(self) -> None:
        if self._s.state:
            _lib.mr_free(ctypes.byref(self._s))

    def __enter__(self) -> Solution:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def redraw(self, out: Array, slot: npt.NDArray[np.int64], key: int,
               exact_max: int = EXACT_MAX, spread: float = 1.0) -> None:
        """Draw the kept variables into ``out`` ``(cap, 7, N)`` at ``slot[v]`` (-1: skip);
        with fewer kept dimensions than N (and at most ``exact_max``) the samples' covariance
        is exactly the posterior's; ``spread`` multiplies every frame's deviations (its
        covariance by ``spread**2``), less for a pose whose rotation deviations would exceed
        :data:`SPREAD_ROTATION_CAP` RMS."""
        sl = np.ascontiguousarray(slot, dtype=np.int64)
        if _lib.mr_redraw(ctypes.byref(self._s), ptr(out), ptr(sl), out.shape[-1],
                          key & (2**64 - 1), int(exact_max), float(spread),
                          SPREAD_ROTATION_CAP) != OK:
            raise NumericalError("the relinearisation's redraw failed")

    def marginal(self) -> tuple[Array, Array]:
        """``R`` ``(m, cols)`` and ``y`` ``(m,)`` of the kept variables' Gaussian (rows: kept
        scalars; columns: full dimensions of the kept, non-fixed variables, ascending)."""
        p = self.problem
        keep = (p.vkept != 0) & (p.vfixed == 0)
        cols = int(np.sum(np.where(p.vkind[keep] == 0, 6, 3)))
        m = self.stats.kept_scalars
        r = np.empty((m, cols))
        d = np.empty(m)
        if _lib.mr_marginal(ctypes.byref(self._s), ptr(r), ptr(d)) != OK:
            raise NumericalError("the marginal could not be taken")
        return r, d


def solve(problem: Problem, *, max_iter: int = 20, tol: float = 1e-6,
          keep_factor: bool = True) -> Solution:
    """Gauss-Newton / Levenberg-Marquardt from ``problem.x`` (updated in place; a step that
    does not lower the cost is halved up to 6 times before the damping grows, and only a whole
    step's decrease below ``tol`` of the cost stops it), then the factorisation at the result
    (``max_iter=0``: the factorisation at ``x`` only). With
    ``keep_factor=False`` the solution and its statistics only (the same ``x``, one
    factorisation fewer: a re-centring); :meth:`Solution.redraw` and
    :meth:`Solution.marginal` then raise.

    Raises
    ------
    NumericalError
        If the problem is malformed or its cost is not finite.
    """
    return Solution(problem, max_iter, tol, keep_factor)


__all__ = ["Problem", "Solution", "SolveStats", "moments", "means", "recentre", "spread",
           "transform",
           "normals",
           "solve", "means_active", "joint_frames_means", "finish_masks", "RELIN_VERSION"]
