"""The joint update (``method="joint"``, case II): one ensemble-Kalman analysis of a whole
component, run by the compiled kernel.

The observation is predicted per sample, ``h = (r→a)^R ⊕ (r→b)`` (statistical linearisation,
no re-rooting), and every edge moves by ``Δ_i = C_xy w_i`` where ``C_xy`` is the edge's
cross-covariance with ``h`` and ``w_i`` a per-sample weight vector of the analysis rule
(:mod:`mcsm.core.analysis` documents the rules; ``_kernel.c`` computes them). ``C_xy`` comes
from one of two estimators (``gain``): ``"direct"``, every edge's sample cross-covariance with
``h`` damped entry by entry by its significance (correlation shrink); ``"endpoints"``, every
edge regressed on the principal components of the two endpoint edges, chained with the
components' cross-covariance with ``h`` (:func:`mcsm.core.analysis.endpoint_cross_covariance`).

Cost: :func:`prepare` is O(N); then one fused kernel pass per frame (moments from sums of
deviations from the frame's first sample, gain, move, inflation, renormalisation) reads each
frame once while it sits in cache and writes it into a spare buffer; the component's buffer is
swapped only after every frame passed its checks, so a failed update leaves the map as it was.
Frames are split into contiguous ranges over up to ``threads`` threads; a frame's arithmetic
never depends on the split, so digests do not depend on the thread count.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel, relin
from mcsm.core.device import DeviceComponent
from mcsm.core.storage import Component
from mcsm.errors import NumericalError

Array = npt.NDArray[np.float64]

RULE_CODES = {"ensrf": 0, "denkf": 1, "enkf": 2}
SPACE_CODES = {"tangent": 0, "quaternion": 1}
# adaptive inflation (issue 8): running-average rate, strength, largest factor
ADAPT_RATE, ADAPT_STRENGTH, ADAPT_MAX = 0.05, 0.008, 1.01
# frames per task (about 20 us each at N = 1000): enough work per call to hide the thread
# hand-off
_MIN_FRAMES_PER_TASK = 32
_POOLS: dict[int, ThreadPoolExecutor] = {}


def default_threads() -> int:
    """Threads for the joint update's frame pass: the cores this process may use, at most 4."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(4, cores))


def run_ranges(fn: Callable[[int, int], int], m: int, threads: int) -> list[int]:
    """``fn(lo, hi)`` over contiguous frame ranges covering [0, m), on up to ``threads``
    threads (the kernel releases the GIL); the codes, in range order."""
    tasks = min(threads, max(1, m // _MIN_FRAMES_PER_TASK))
    if tasks <= 1:
        return [fn(0, m)]
    bounds = [m * t // tasks for t in range(tasks + 1)]
    return list(_pool(tasks).map(lambda t: fn(bounds[t], bounds[t + 1]), range(tasks)))


def _pool(threads: int) -> ThreadPoolExecutor:
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="mcsm-core")
    return _POOLS[threads]


@dataclass
class Prepared:
    """The O(N) part of one loop closure: prediction, weights and the normalised innovation
    squared (NIS) of the observation's mean against the map's prediction."""

    yc: Array
    w: Array
    info: Array
    point: bool

    @property
    def p(self) -> int:
        return int(self.w.shape[0])

    @property
    def nis(self) -> float:
        """NIS over the live dimensions of ``S = C_yy + R``."""
        return float(self.info[1])

    @property
    def dof(self) -> int:
        return int(self.info[2])


def prepare(comp: Component | DeviceComponent, ia: int, ib: int, x_rows: Array, point: bool,
            space: str, rule: str) -> Prepared:
    """Predict, analyse and measure the innovation of an observation between frames ``ia``
    and ``ib`` of ``comp``; ``x_rows`` ``(7, N)`` or ``(3, N)``."""
    rc, yc, w, info = kernel.analysis(comp.edge_rows(ia), comp.edge_rows(ib), x_rows, point,
                                      SPACE_CODES[space], RULE_CODES[rule])
    if rc != kernel.OK:
        raise NumericalError("the analysis produced non-finite weights")
    return Prepared(yc, w, info, point)


def inflation_factor(prep: Prepared, inflation: float | str, nis_avg: float
                     ) -> tuple[float, float]:
    """This loop closure's inflation and the new running NIS average (adaptive inflation:
    ``λ = clip(1 + 0.008 (avg − 1), 1, 1.01)``, ``avg ← 0.95 avg + 0.05 NIS/dof``)."""
    if inflation != "adaptive":
        return float(inflation), nis_avg
    per_dof = prep.nis / max(1, prep.dof)
    avg = (1.0 - ADAPT_RATE) * nis_avg + ADAPT_RATE * per_dof
    lam = 1.0 + ADAPT_STRENGTH * (avg - 1.0)
    return min(max(lam, 1.0), ADAPT_MAX), avg


def frame_args(comp: Component | DeviceComponent, ia: int, ib: int, prep: Prepared, *,
               space: str, gain: str, shrink: float | None, inflation: float
               ) -> tuple[kernel.JointArgs, dict[str, Array]]:
    """The frame pass's arguments (``mk_joint_args``) and the arrays they point to (by
    name; the CPU sets the pointers, the device copies the arrays first)."""
    p, n = prep.p, comp.n_samples
    info = prep.info
    var_y = np.ascontiguousarray(info[3: 3 + p])
    sum_yc = np.ascontiguousarray(info[3 + p: 3 + 2 * p])
    wbar = np.ascontiguousarray(info[3 + 2 * p: 3 + 3 * p])
    args = kernel.JointArgs()
    args.n, args.p, args.space = n, p, SPACE_CODES[space]
    args.gain = 1 if gain == "endpoints" else 0
    args.shrink = -1.0 if shrink is None else float(shrink)
    args.inflation = float(inflation)
    args.wmax = float(info[3 + 3 * p])
    arrays = {"yc": np.ascontiguousarray(prep.yc), "w": prep.w, "var_y": var_y,
              "sum_yc": sum_yc, "wbar": wbar}
    if gain == "endpoints":
        pcs, lam, cpy, sum_pc, args.k = kernel.endpoint_prep(
            comp.edge_rows(ia), comp.edge_rows(ib), prep.point, prep.yc, var_y, args.shrink)
        arrays.update(pcs=pcs, lam=lam, cpy=cpy, sum_pc=sum_pc)
    return args, arrays


def apply(comp: Component | DeviceComponent, ia: int, ib: int, prep: Prepared, *, space: str,
          gain: str, shrink: float | None, inflation: float, threads: int, spare: Any,
          means: bool = False) -> Any:
    """Move every frame of ``comp``; returns the replaced buffer (the next update's spare).
    A component in device memory runs the same frame pass on the device
    (:meth:`DeviceComponent.apply_joint`). ``means`` (a re-centring follows): a component in
    host memory keeps its frames' means, taken in the same pass (:meth:`Component.pass_means`).

    Raises
    ------
    NumericalError
        If a frame's gain is not finite or a quaternion would go to zero (map unchanged).
    """
    args, arrays = frame_args(comp, ia, ib, prep, space=space, gain=gain, shrink=shrink,
                              inflation=inflation)
    if isinstance(comp, DeviceComponent):
        return comp.apply_joint(args, arrays, threads, spare)
    for name, a in arrays.items():
        setattr(args, name, kernel.ptr(a))
    keep = list(arrays.values())
    buf = comp.buffer
    out = spare if spare is not None and spare.shape == buf.shape else np.empty_like(buf)
    flags = comp.point_flags
    m = len(comp)
    fm, big = (np.empty((m, 7)), np.empty(m)) if means else (None, None)
    parts: dict[int, npt.NDArray[np.int64]] = {}

    def frames(lo: int, hi: int) -> int:
        if fm is None or big is None:
            return kernel.joint_frames(args, buf, out, flags, lo, hi)
        ls = parts[lo] = np.zeros(4, dtype=np.int64)
        return relin.joint_frames_means(args, buf, out, flags, lo, hi, fm, big, ls)

    codes = run_ranges(frames, m, threads)
    del keep
    for rc in codes:
        if rc == kernel.NONFINITE_GAIN:
            raise NumericalError("the update's gain is not finite")
        if rc != kernel.OK:
            raise NumericalError("the update pushed quaternions to zero or non-finite values")
    old = comp.swap_buffer(out)
    if fm is not None and big is not None:
        comp.keep_means(fm, np.bitwise_or.reduce(list(parts.values())), big)
    return old
