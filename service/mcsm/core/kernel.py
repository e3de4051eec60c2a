"""Bindings of the compiled kernel (``_kernel.c``), loaded with ctypes.

The kernel does every computation that changes map state in a fixed order of operations
(``_kernel.c`` says how), so a map's digest depends on its inputs and the code's version only,
never on the CPU, the BLAS build or the thread count. It is built by ``pip install`` (setup.py);
there is no fallback: if the library is missing, importing the core fails with one line saying
how to build it. ``MCSM_KERNEL_LIBRARY`` names another build of the same source (the
portability tests load one compiled for the native CPU).

All arrays are float64, C-contiguous, in the kernel's *rows* layout: an AT is ``(7, N)``
(x, y, z, qw, qx, qy, qz rows), a block of frames ``(M, 7, N)``.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

KERNEL_VERSION = 3
OK, NONFINITE_GAIN, BAD_QUATERNION, NONFINITE, BAD_ARGS = range(5)


class KernelMissing(ImportError):
    """The compiled kernel could not be loaded."""


def _built(module: str) -> str | None:
    spec = importlib.util.find_spec(module)
    return None if spec is None or spec.origin is None else spec.origin


def _open(path: str) -> ctypes.CDLL:
    try:
        lib = ctypes.CDLL(path)
    except OSError as exc:
        raise KernelMissing(f"mcsm's compiled kernel at {path} does not load: {exc}; "
                            "reinstall with a C compiler present (`pip install -e .`)") from None
    if lib.mk_version() != KERNEL_VERSION:
        raise KernelMissing(f"mcsm's compiled kernel at {path} is version {lib.mk_version()}, "
                            f"this code needs {KERNEL_VERSION}: reinstall (`pip install -e .`)")
    return lib


def _load() -> tuple[ctypes.CDLL, str]:
    """The kernel library: ``MCSM_KERNEL_LIBRARY`` if set, else the AVX2 build where the CPU
    has AVX2, else the baseline build (all three give the same bits)."""
    override = os.environ.get("MCSM_KERNEL_LIBRARY")
    if override:
        return _open(override), override
    base = _built("mcsm.core._kernel")
    if base is None:
        raise KernelMissing(
            f"mcsm's compiled kernel (mcsm.core._kernel) is not built in "
            f"{Path(__file__).parent}: reinstall with a C compiler present "
            "(`pip install -e .` or `make test`)")
    lib = _open(base)
    fast = _built("mcsm.core._kernel_avx2")
    if fast is not None and lib.mk_cpu_has_avx2():
        return _open(fast), fast
    return lib, base


_lib, LIBRARY = _load()
_P = ctypes.c_void_p
_L = ctypes.c_long
_I = ctypes.c_int
_D = ctypes.c_double
for _name, _args, _res in (
        ("mk_compound", (_P, _P, _P, _L), None),
        ("mk_invert", (_P, _P, _L), None),
        ("mk_relative", (_P, _P, _P, _L), None),
        ("mk_relative_nm7", (_P, _P, _P, _L), None),
        ("mk_point_edge", (_P, _P, _P, _L), None),
        ("mk_canonicalize", (_P, _L, _I), None),
        ("mk_transform_frames", (_P, _P, _P, _P, _L, _L, _L), _I),
        ("mk_canonicalize_frames", (_P, _P, _L, _L, _L, _I), _I),
        ("mk_analysis", (_P, _P, _P, _L, _I, _I, _I, _P, _P, _P, _P), _I),
        ("mk_endpoint_prep", (_P, _P, _L, _I, _P, _I, _P, _D, _P, _P, _P, _P, _P), _I),
        ("mk_joint_frames", (_P, _P, _P, _P, _L, _L), _I),
        ("mk_joint_args_size", (), _L),
        ("mk_paper_main_edge", (_P, _P, _L, _I, _P, _P), None),
        ("mk_paper_frames", (_P, _P, _P, _P, _P, _L, _L, _L, _L, _P), _I)):
    _fn = getattr(_lib, _name)
    _fn.argtypes = list(_args)
    _fn.restype = _res


class JointArgs(ctypes.Structure):
    """``mk_joint_args`` of ``_kernel.c``: everything a frame of the joint update needs."""

    _fields_ = [("n", _L), ("p", _I), ("space", _I), ("gain", _I), ("shrink", _D),
                ("inflation", _D), ("wmax", _D), ("yc", _P), ("w", _P), ("var_y", _P),
                ("sum_yc", _P), ("wbar", _P), ("k", _I), ("pcs", _P), ("lam", _P), ("cpy", _P),
                ("sum_pc", _P)]


if ctypes.sizeof(JointArgs) != _lib.mk_joint_args_size():
    raise KernelMissing("mcsm's compiled kernel does not match its bindings: reinstall")


def ptr(a: npt.NDArray[np.generic]) -> int:
    """The data pointer of a C-contiguous array (checked)."""
    if not a.flags.c_contiguous:
        raise ValueError("kernel arrays must be C-contiguous")
    return int(a.__array_interface__["data"][0])


def compound(a: Array, b: Array, out: Array | None = None) -> Array:
    """``a ⊕ b`` on rows ``(7, N)``."""
    o = np.empty_like(a) if out is None else out
    _lib.mk_compound(ptr(a), ptr(b), ptr(o), a.shape[-1])
    return o


def invert(a: Array) -> Array:
    """``a^R`` on rows ``(7, N)``."""
    o = np.empty_like(a)
    _lib.mk_invert(ptr(a), ptr(o), a.shape[-1])
    return o


def relative(a: Array, b: Array) -> Array:
    """``a^R ⊕ b`` on rows ``(7, N)`` (the query)."""
    o = np.empty_like(a)
    _lib.mk_relative(ptr(a), ptr(b), ptr(o), a.shape[-1])
    return o


def relative_nm7(a: Array, b: Array) -> Array:
    """``a^R ⊕ b`` from rows ``(7, N)`` into a new ``(N, 7)`` array (a query's answer)."""
    n = a.shape[-1]
    o = np.empty((n, 7))
    _lib.mk_relative_nm7(ptr(a), ptr(b), ptr(o), n)
    return o


def point_edge(a: Array, p: Array) -> Array:
    """Edge of a point ``p`` (rows ``(3, N)``) seen from ``a``: ``t_a + R(q_a) p``, identity q."""
    o = np.empty_like(a)
    _lib.mk_point_edge(ptr(a), ptr(p), ptr(o), a.shape[-1])
    return o


def canonicalize(x: Array, normalize: bool = True) -> Array:
    """In place on rows ``(7, N)``: renormalise (if asked), then every quaternion on the
    hemisphere of the mean rotation. Returns ``x``."""
    _lib.mk_canonicalize(ptr(x), x.shape[-1], int(normalize))
    return x


def transform_frames(pre: Array, frames: Array, out: Array, point: npt.NDArray[np.uint8],
                     lo: int, hi: int) -> int:
    """``out[f] = canonical(pre ⊕ frames[f])`` (points pinned) for f in [lo, hi)."""
    return int(_lib.mk_transform_frames(ptr(pre), ptr(frames), ptr(out), ptr(point), lo, hi,
                                        frames.shape[-1]))


def canonicalize_frames(frames: Array, point: npt.NDArray[np.uint8], lo: int, hi: int,
                        normalize: bool) -> int:
    """Frames [lo, hi) of ``(M, 7, N)`` canonicalised in place (points pinned)."""
    return int(_lib.mk_canonicalize_frames(ptr(frames), ptr(point), lo, hi, frames.shape[-1],
                                           int(normalize)))


def analysis(e_a: Array, e_b: Array, x: Array, point: bool, space: int, rule: int,
             ) -> tuple[int, Array, Array, Array]:
    """Prediction, analysis weights and NIS of one loop closure; ``(code, yc, w, info)``."""
    n = e_a.shape[-1]
    p = 3 if point else (7 if space == 1 else 6)
    yc = np.empty((7, n))
    w = np.empty((p, n))
    info = np.zeros(4 + 3 * 7)
    work = np.empty(21 * n)
    rc = _lib.mk_analysis(ptr(e_a), ptr(e_b), ptr(x), n, int(point), space, rule, ptr(yc),
                          ptr(w), ptr(info), ptr(work))
    return int(rc), yc[:p], w, info


def endpoint_prep(e_a: Array, e_b: Array, point: bool, yc: Array, var_y: Array,
                  shrink: float) -> tuple[Array, Array, Array, Array, int]:
    """Endpoint components ``(K, N)``, their variances ``(K,)``, shrunk cross-covariances
    with the prediction ``(K, p)`` and row sums ``(K,)``, in buffers of 12 components, and K
    (``shrink`` < 0: no shrink)."""
    n = e_a.shape[-1]
    p = yc.shape[0]
    pcs = np.empty((12, n))
    lam = np.empty(12)
    cpy = np.empty((12, p))
    sums = np.empty(12)
    work = np.empty(12 * n)
    k = _lib.mk_endpoint_prep(ptr(e_a), ptr(e_b), n, int(point), ptr(yc), p, ptr(var_y),
                              float(shrink), ptr(pcs), ptr(lam), ptr(cpy), ptr(sums), ptr(work))
    return pcs, lam, np.ascontiguousarray(cpy), sums, int(k)


def joint_frames(args: JointArgs, edges: Array, out: Array, point: npt.NDArray[np.uint8],
                 lo: int, hi: int) -> int:
    """Frames [lo, hi) of the joint update from ``edges`` into ``out``; an ``OK``... code.
    Releases the GIL (ctypes), so ranges may run on several threads."""
    return int(_lib.mk_joint_frames(ctypes.byref(args), ptr(edges), ptr(out), ptr(point), lo,
                                    hi))


def paper_main_edge(g: Array, x: Array, point: bool) -> Array:
    """The merged main edge ``G ⊗ X`` (PAPER Fig. 3, tangent chart; points: translations)."""
    n = g.shape[-1]
    out = np.empty((7, n))
    work = np.empty(36 * n)
    _lib.mk_paper_main_edge(ptr(g), ptr(x), n, int(point), ptr(out), ptr(work))
    return out


def paper_frames(pre: Array | None, shift: Array, frames: Array, out: Array,
                 point: npt.NDArray[np.uint8], lo: int, hi: int, dst_offset: int) -> int:
    """``out[f + dst_offset] = merge(C, shift ⊕ C)`` with ``C = pre ⊕ frames[f]`` (or
    ``frames[f]``) for f in [lo, hi); releases the GIL."""
    n = frames.shape[-1]
    work = np.empty(17 * n)
    return int(_lib.mk_paper_frames(None if pre is None else ptr(pre), ptr(shift), ptr(frames),
                                    ptr(out), ptr(point), lo, hi, dst_offset, n, ptr(work)))


__all__ = ["KernelMissing", "JointArgs", "compound", "invert", "relative", "point_edge",
           "canonicalize", "canonicalize_frames", "transform_frames", "analysis",
           "endpoint_prep", "joint_frames", "paper_main_edge", "paper_frames"]
