"""Compiled-kernel candidates side by side (issue 13): the joint update's fused frame pass.

One frame of a loop closure with the default options (direct gain, tangent space, correlation
shrink 4, no inflation): moments of each of the 7 rows against the centred prediction ``yc``
(shifted sums), the cross-covariance projected onto the tangent plane at the mean rotation and
shrunk entry by entry, the gain checks, the move ``x + C w`` and the quaternion
renormalisation with its checks (``joint_frame`` in ``service/mcsm/core/_kernel.c``). The
inputs are a real 3-D component of M frames with N samples (rows layout ``(M, 7, N)``) after a
few loop closures, and a real loop closure's ``yc``, ``w`` from the kernel's analysis.

Candidates, all on one thread, all writing into a preallocated output (the real update's spare
buffer):

- ``C avx2``, ``C baseline``: ``mk_joint_frames`` of the two builds of ``_kernel.c`` (the
  second loaded with ctypes straight from ``mcsm.core._kernel``);
- ``numba strict``: the same per-frame math in the C kernel's order of operations (every sum in
  four lanes, sample i to lane i mod 4, combined as (l0 + l1) + (l2 + l3), then the tail),
  ``@njit(error_model="numpy")``, no fastmath;
- ``numba fastmath``: the same source with ``fastmath=True`` (reassociation and contraction);
- ``numpy``: the core before the kernel (``(M, N, 7)`` layout, frame blocks of about 2 MiB:
  one matmul for means and cross-covariances, sums of squares, shrink, matmul increments, add,
  renormalise; variances from ``Σx²/N − x̄²`` as it did).

Timing: ``--repeats`` rounds, the candidates in rotating order (A B C ..., B C ... A, ...);
each call is timed right after one ``np.copyto`` of the ``(M, N, 7)`` array ("a pass"), and
reported as its median per moved frame (M − 1 frames: frame 0, the root, is set to identity)
and its median ratio to the copy ("passes"), so that figures from a shared machine compare.
Agreement: max |candidate − C| over max |C − input| (the move). numba's compile and cache
times come from fresh subprocesses (``NUMBA_CACHE_DIR`` in a temporary directory).

Run: ``.venv/bin/python benchmarks/kernel_candidates.py [--repeats 21] [--install-time]``
(numba is not a dependency of mcsm: ``.venv/bin/pip install numba`` in your own venv to get its
rows; without it they are skipped with one line). Output: benchmarks/results/kernel_candidates.txt.
"""

from __future__ import annotations

import argparse
import ast
import ctypes
import importlib.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from mcsm import StochasticMap
from mcsm.core import kernel
from mcsm_client.sampling import pose_from_planar, sample_pose

Array = npt.NDArray[np.float64]
NOISE_COV = np.diag([0.02**2] * 3 + [0.01**2] * 3)  # 2 cm, 0.6 deg per axis (as bench_core)
SHRINK = 4.0  # the default correlation-shrink constant
BLOCK_BYTES = 2 << 20  # the old core's frame blocks


# ------------------------------------------------------------------ inputs


def random_at(rng: np.random.Generator, n: int) -> Array:
    """A 3-D AT: 1 m forward-ish step, a few degrees of turn, cm/deg noise in all six axes."""
    mean = pose_from_planar(rng.normal([1.0, 0.2, 0.15], [0.05, 0.05, 0.01]))
    mean[2] = rng.normal(0.05, 0.05)
    return sample_pose(mean, NOISE_COV, n_samples=n, rng=rng)


class Inputs:
    """A component's rows ``(M, 7, N)`` and one loop closure's prepared arguments."""

    def __init__(self, n: int, m: int, seed: int = 13) -> None:
        rng = np.random.default_rng(seed)
        smap = StochasticMap(n, threads=1)
        frames = [f"f{k}" for k in range(m)]
        for k in range(m - 1):
            smap.update(frames[k], frames[k + 1], random_at(rng, n))
        for _ in range(3):  # a few loop closures: edges correlated with each other
            a, b = sorted(rng.choice(m, 2, replace=False))
            smap.update(frames[a], frames[b], smap.query(frames[a], frames[b])[rng.permutation(n)])
        order = smap.component("f0")
        self.edges = smap.edges("f0")  # (M, N, 7), order of smap.component
        self.rows = np.ascontiguousarray(self.edges.transpose(0, 2, 1))
        a, b = sorted(rng.choice(m, 2, replace=False))
        ia, ib = order.index(frames[a]), order.index(frames[b])
        x = smap.query(frames[a], frames[b])[rng.permutation(n)]
        rc, yc, w, info = kernel.analysis(self.rows[ia], self.rows[ib],
                                          np.ascontiguousarray(x.T), False, 0, 0)
        if rc != kernel.OK:
            raise RuntimeError(f"the analysis failed ({rc})")
        p = w.shape[0]
        self.n, self.m, self.p = n, m, p
        self.yc, self.w = np.ascontiguousarray(yc), np.ascontiguousarray(w)
        self.var_y = np.ascontiguousarray(info[3:3 + p])
        self.sum_yc = np.ascontiguousarray(info[3 + p:3 + 2 * p])
        self.wbar = np.ascontiguousarray(info[3 + 2 * p:3 + 3 * p])
        self.wmax = float(info[3 + 3 * p])
        self.flags = np.zeros(m, dtype=np.uint8)
        args = kernel.JointArgs()
        args.n, args.p, args.space, args.gain = n, p, 0, 0
        args.shrink, args.inflation, args.wmax = SHRINK, 1.0, self.wmax
        args.yc, args.w = kernel.ptr(self.yc), kernel.ptr(self.w)
        args.var_y, args.sum_yc = kernel.ptr(self.var_y), kernel.ptr(self.sum_yc)
        args.wbar = kernel.ptr(self.wbar)
        self.args = args


# ------------------------------------------------------------------ (a) the C kernel


def c_candidates(inp: Inputs) -> dict[str, Callable[[Array], int]]:
    """The AVX2 and the baseline builds of ``_kernel.c`` (both loaded in this process)."""
    out: dict[str, Callable[[Array], int]] = {}
    spec = importlib.util.find_spec("mcsm.core._kernel")
    base_path = None if spec is None else spec.origin
    loaded = Path(kernel.LIBRARY).name
    if "_kernel_avx2" in loaded:
        out["C avx2"] = lambda o: kernel.joint_frames(inp.args, inp.rows, o, inp.flags, 0, inp.m)
    else:
        print(f"mcsm loaded {loaded} (not the AVX2 build): no 'C avx2' row")
    if base_path is not None:
        lib = ctypes.CDLL(base_path)
        fn = lib.mk_joint_frames
        fn.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_long] * 2
        fn.restype = ctypes.c_int
        if lib.mk_joint_args_size() != ctypes.sizeof(kernel.JointArgs):
            raise RuntimeError("the baseline library does not match mcsm.core.kernel")
        out["C baseline"] = lambda o: int(fn(ctypes.byref(inp.args), kernel.ptr(inp.rows),
                                             kernel.ptr(o), kernel.ptr(inp.flags), 0, inp.m))
    return out


# ------------------------------------------------------------------ (b, c) numba


def frames_py(rows: Array, out: Array, yc: Array, w: Array, var_y: Array, sum_yc: Array,
              shrink: float, wmax: float, point: npt.NDArray[np.uint8]) -> int:
    """``mk_joint_frames`` (direct gain, tangent space, no inflation) in plain Python loops,
    in the C kernel's order of operations; compiled by numba. Returns the kernel's code."""
    m, _, n = rows.shape
    p = yc.shape[0]
    nm1 = float(n - 1)
    dn = float(n)
    n4 = n - n % 4
    mean = np.empty(7)
    var = np.empty(7)
    cxy = np.empty((p, 7))
    norm = np.empty(n)
    qb = np.empty(4)
    for f in range(m):
        o = out[f]
        if f == 0:
            for d in range(7):
                for i in range(n):
                    o[d, i] = 1.0 if d == 3 else 0.0
            continue
        x = rows[f]
        # moments from shifted sums, four lanes then the tail
        for d in range(7):
            xd = x[d]
            s = xd[0]
            a0 = 0.0
            a1 = 0.0
            a2 = 0.0
            a3 = 0.0
            b0 = 0.0
            b1 = 0.0
            b2 = 0.0
            b3 = 0.0
            for i in range(0, n4, 4):
                d0 = xd[i] - s
                d1 = xd[i + 1] - s
                d2 = xd[i + 2] - s
                d3 = xd[i + 3] - s
                a0 += d0
                a1 += d1
                a2 += d2
                a3 += d3
                b0 += d0 * d0
                b1 += d1 * d1
                b2 += d2 * d2
                b3 += d3 * d3
            s1 = (a0 + a1) + (a2 + a3)
            s2 = (b0 + b1) + (b2 + b3)
            for i in range(n4, n):
                dv = xd[i] - s
                s1 += dv
                s2 += dv * dv
            dm = s1 / dn
            mean[d] = s + dm
            v = (s2 - s1 * dm) / nm1
            var[d] = v if v > 0.0 else 0.0
            for k in range(p):
                r = yc[k]
                c0 = 0.0
                c1 = 0.0
                c2 = 0.0
                c3 = 0.0
                for i in range(0, n4, 4):
                    c0 += (xd[i] - s) * r[i]
                    c1 += (xd[i + 1] - s) * r[i + 1]
                    c2 += (xd[i + 2] - s) * r[i + 2]
                    c3 += (xd[i + 3] - s) * r[i + 3]
                c = (c0 + c1) + (c2 + c3)
                for i in range(n4, n):
                    c += (xd[i] - s) * r[i]
                cxy[k, d] = (c - dm * sum_yc[k]) / nm1
        # tangent projection at the mean rotation
        qn = np.sqrt(mean[3] * mean[3] + mean[4] * mean[4] + mean[5] * mean[5]
                     + mean[6] * mean[6])
        for j in range(4):
            qb[j] = mean[3 + j] / qn
        for k in range(p):
            rad = (cxy[k, 3] * qb[0] + cxy[k, 4] * qb[1] + cxy[k, 5] * qb[2]
                   + cxy[k, 6] * qb[3])
            for j in range(4):
                cxy[k, 3 + j] -= rad * qb[j]
        # correlation shrink
        if shrink >= 0.0:
            for k in range(p):
                for d in range(7):
                    cv = cxy[k, d]
                    denom = var_y[k] * var[d]
                    r2 = cv * cv / denom if denom > 0.0 else 0.0
                    fct = 1.0 - shrink * ((1.0 - r2) * (1.0 - r2)) / (dn * r2) if r2 > 0.0 \
                        else 0.0
                    if fct != fct:
                        fct = 0.0
                    fct = 0.0 if fct < 0.0 else (1.0 if fct > 1.0 else fct)
                    cxy[k, d] = cv * fct
        # finite, bounded gain
        cmax = 0.0
        for k in range(p):
            for d in range(7):
                a = abs(cxy[k, d])
                if not (a == a) or a == np.inf:
                    return 1
                cmax = a if a > cmax else cmax
        if not (cmax * wmax * float(p) < 1e100):
            return 1
        # move: o = x + (((0 + w_0 c_0) + w_1 c_1) + ...), written row by row so that the
        # sample loop vectorises (the sum over k per sample is in the C kernel's order)
        for d in range(7):
            xd = x[d]
            od = o[d]
            for i in range(n):
                od[i] = 0.0
            for k in range(p):
                ck = cxy[k, d]
                wk = w[k]
                for i in range(n):
                    od[i] += wk[i] * ck
            for i in range(n):
                od[i] = xd[i] + od[i]
        # renormalise the quaternions; norms in (0.1, 1e10), NaN fails
        for i in range(n):
            norm[i] = np.sqrt(o[3, i] * o[3, i] + o[4, i] * o[4, i] + o[5, i] * o[5, i]
                              + o[6, i] * o[6, i])
        for j in range(3, 7):
            oj = o[j]
            for i in range(n):
                oj[i] = oj[i] / norm[i]
        nmin = np.inf
        nmax = 0.0
        for i in range(n):
            sv = norm[i]
            if sv != sv:
                nmin = -1.0
                break
            nmin = sv if sv < nmin else nmin
            nmax = sv if sv > nmax else nmax
        if not (nmin > 0.1 and nmax < 1e10):
            return 2
        for d in range(3):
            for i in range(n):
                if not np.isfinite(o[d, i]):
                    return 3
        if point[f]:
            return 4  # (no points in this benchmark; the kernel pins them)
    return 0


def numba_candidates(inp: Inputs) -> tuple[dict[str, Callable[[Array], int]], dict[str, float]]:
    """The strict and the fastmath numba kernels (compiled here, uncached) and their cold
    compile times in this process."""
    import numba

    out: dict[str, Callable[[Array], int]] = {}
    compile_s: dict[str, float] = {}
    for name, fast in (("numba strict", False), ("numba fastmath", True)):
        fn = numba.njit(error_model="numpy", fastmath=fast, cache=False)(frames_py)
        scratch = np.empty_like(inp.rows)
        t0 = time.perf_counter()
        fn(inp.rows, scratch, inp.yc, inp.w, inp.var_y, inp.sum_yc, SHRINK, inp.wmax, inp.flags)
        compile_s[name] = time.perf_counter() - t0

        def call(o: Array, fn: Any = fn) -> int:
            return int(fn(inp.rows, o, inp.yc, inp.w, inp.var_y, inp.sum_yc, SHRINK, inp.wmax,
                          inp.flags))

        out[name] = call
    return out, compile_s


def numba_probe(cache_dir: str) -> None:
    """(In a fresh subprocess) import numba, build the strict kernel with ``cache=True`` in
    ``cache_dir`` and call it once; print the times as JSON."""
    os.environ["NUMBA_CACHE_DIR"] = cache_dir
    t0 = time.perf_counter()
    import numba

    t_import = time.perf_counter() - t0
    inp = Inputs(1000, 2)
    fn = numba.njit(error_model="numpy", cache=True)(frames_py)
    o = np.empty_like(inp.rows)
    t0, c0 = time.perf_counter(), time.process_time()
    fn(inp.rows, o, inp.yc, inp.w, inp.var_y, inp.sum_yc, SHRINK, inp.wmax, inp.flags)
    t_first, c_first = time.perf_counter() - t0, time.process_time() - c0
    print(json.dumps({"import_s": t_import, "first_call_s": t_first, "first_call_cpu_s": c_first}))


def numba_compile_times(rounds: int) -> list[tuple[float, float, float, float]]:
    """``rounds`` of (import, cold compile, cache load, cold compile CPU) seconds, each in
    fresh subprocesses."""
    res = []
    for _ in range(rounds):
        with tempfile.TemporaryDirectory(prefix="numba-cache-") as d:
            runs = []
            for _ in range(2):
                r = subprocess.run([sys.executable, __file__, "--numba-probe", d],
                                   capture_output=True, text=True, timeout=300, check=True)
                runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
            res.append((runs[1]["import_s"], runs[0]["first_call_s"], runs[1]["first_call_s"],
                        runs[0]["first_call_cpu_s"]))
    return res


def install_size_mib() -> float:
    """Bytes on disk of the installed numba and llvmlite packages (as ``du``), MiB."""
    total = 0
    for mod in ("numba", "llvmlite"):
        spec = importlib.util.find_spec(mod)
        assert spec is not None and spec.submodule_search_locations is not None
        for root in spec.submodule_search_locations:
            for dirpath, _, files in os.walk(root):
                for f in files:
                    total += os.lstat(os.path.join(dirpath, f)).st_blocks * 512
    return total / 2**20


def install_seconds() -> float:
    """Wall time of ``pip install --no-cache-dir --no-deps numba llvmlite`` into a temporary
    directory (download and unpack; numpy is already there)."""
    with tempfile.TemporaryDirectory(prefix="numba-install-") as d:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pip", "install", "--quiet", "--no-cache-dir",
                        "--no-deps", "--target", d, "numba", "llvmlite"],
                       capture_output=True, timeout=900, check=True)
        return time.perf_counter() - t0


def c_build_seconds() -> tuple[float, float] | None:
    """Wall and CPU time of one gcc build of ``_kernel.c`` with setup.py's flags and ``-mavx2``
    (None if gcc or the source is missing)."""
    root = Path(__file__).resolve().parents[1]
    setup_py, source = root / "setup.py", root / "service/mcsm/core/_kernel.c"
    if not (setup_py.exists() and source.exists()):
        return None
    text = setup_py.read_text()
    start = text.index("KERNEL_FLAGS = ")
    flags = ast.literal_eval(text[start + len("KERNEL_FLAGS = "):text.index("]", start) + 1])
    with tempfile.TemporaryDirectory(prefix="mcsm-kernel-") as d:
        t0 = time.perf_counter()
        cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        try:
            subprocess.run(["gcc", *flags, "-mavx2", "-shared", "-fPIC", "-o",
                            os.path.join(d, "k.so"), str(source)],
                           capture_output=True, timeout=300, check=True)
        except (OSError, subprocess.CalledProcessError):
            return None
        cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        return (time.perf_counter() - t0,
                cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime)


# ------------------------------------------------------------------ (d) numpy, the old core


def numpy_candidate(inp: Inputs) -> Callable[[Array], int]:
    """The old core's two passes over ``(M, N, 7)`` edges in frame blocks (numpy/BLAS)."""
    edges = inp.edges
    n, m = inp.n, inp.m
    yc, w = inp.yc.T, inp.w.T  # (N, p)
    lhs_t = np.concatenate((yc / (n - 1), np.full((n, 1), 1.0 / n)), axis=1).T[None]
    var_y = np.einsum("np,np->p", yc, yc) / (n - 1)
    step = max(1, BLOCK_BYTES // (n * 7 * 8))
    blocks = [slice(i, min(i + step, m)) for i in range(0, m, step)]
    moments = np.empty((m, lhs_t.shape[1], 7))
    sq = np.empty((m, 7))
    w_b = w[None]

    def run(out: Array) -> int:
        for s in blocks:
            e = edges[s]
            np.matmul(lhs_t, e, out=moments[s])
            np.einsum("mnk,mnk->mk", e, e, out=sq[s])
        c_xy_t = moments[:, :-1, :]
        mean = moments[:, -1, :]
        q_bar = mean[:, 3:] / np.linalg.norm(mean[:, 3:], axis=1, keepdims=True)
        radial = np.einsum("mpk,mk->mp", c_xy_t[..., 3:], q_bar)
        c_xy_t[..., 3:] -= radial[..., None] * q_bar[:, None, :]
        var_x = np.clip(sq / n - mean**2, 0.0, None) * (n / (n - 1))
        denom = var_y[None, :, None] * var_x[:, None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            r2 = np.where(denom > 0, c_xy_t**2 / np.where(denom > 0, denom, 1.0), 0.0)
            fct = np.where(r2 > 0, 1.0 - SHRINK * (1.0 - r2) ** 2 / (n * np.where(r2 > 0, r2, 1.0)),
                           0.0)
        c_xy_t = c_xy_t * np.clip(fct, 0.0, 1.0)
        bound = float(np.abs(c_xy_t).max(initial=0.0)) * inp.wmax * w.shape[1]
        if not (np.isfinite(c_xy_t).all() and bound < 1e100):
            return 1
        for s in blocks:
            o = out[s]
            np.matmul(w_b, c_xy_t[s], out=o)
            o += edges[s]
            q = o[..., 3:]
            norm = np.sqrt(np.einsum("mnk,mnk->mn", q, q))
            if not (norm.min() > 0.1 and norm.max() < 1e10):
                return 2
            q /= norm[..., None]
        out[0] = 0.0
        out[0, :, 3] = 1.0
        return 0

    return run


# ------------------------------------------------------------------ measurement


def copy_pass_s(src: Array, dst: Array) -> float:
    t0 = time.perf_counter_ns()
    np.copyto(dst, src)
    return (time.perf_counter_ns() - t0) * 1e-9


def measure(cands: dict[str, Callable[[Array], int]], inp: Inputs, repeats: int
            ) -> tuple[dict[str, list[float]], dict[str, list[float]], dict[str, Array], float]:
    """Times (s) and passes of every candidate, rotating order; their outputs in rows layout;
    median copy pass (s)."""
    names = list(cands)
    outs = {k: np.empty_like(inp.edges if k == "numpy" else inp.rows) for k in names}
    for k in names:  # warm: page faults of the outputs, first-call costs
        if cands[k](outs[k]) != 0:
            raise RuntimeError(f"{k}: the frame pass failed")
    dst = np.empty_like(inp.edges)
    np.copyto(dst, inp.edges)
    times: dict[str, list[float]] = {k: [] for k in names}
    passes: dict[str, list[float]] = {k: [] for k in names}
    copies = []
    for r in range(repeats):
        for k in names[r % len(names):] + names[:r % len(names)]:
            cp = copy_pass_s(inp.edges, dst)
            copies.append(cp)
            t0 = time.perf_counter_ns()
            rc = cands[k](outs[k])
            dt = (time.perf_counter_ns() - t0) * 1e-9
            if rc != 0:
                raise RuntimeError(f"{k}: the frame pass failed ({rc})")
            times[k].append(dt)
            passes[k].append(dt / cp)
    rows_out = {k: (np.ascontiguousarray(v.transpose(0, 2, 1)) if k == "numpy" else v)
                for k, v in outs.items()}
    return times, passes, rows_out, float(np.median(copies))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=1000, help="N")
    ap.add_argument("--frames", type=int, default=400, help="M")
    ap.add_argument("--repeats", type=int, default=21, help="rounds of all candidates")
    ap.add_argument("--compile-rounds", type=int, default=3,
                    help="fresh-subprocess rounds of numba's cold compile and cache load")
    ap.add_argument("--install-time", action="store_true",
                    help="also time `pip install --no-deps numba llvmlite` into a temp dir")
    ap.add_argument("--numba-probe", metavar="CACHE_DIR", help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.numba_probe:
        numba_probe(a.numba_probe)
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # (only the numpy row uses BLAS)
    print(f"kernel candidates, N = {a.samples}, M = {a.frames}, one thread, {a.repeats} rounds "
          f"in rotating order; numpy {np.__version__}, {os.cpu_count()} cores, "
          f"load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    inp = Inputs(a.samples, a.frames)
    cands = c_candidates(inp)
    have_numba = importlib.util.find_spec("numba") is not None
    compile_s: dict[str, float] = {}
    if have_numba:
        import numba

        nb, compile_s = numba_candidates(inp)
        cands.update(nb)
        import llvmlite

        print(f"numba {numba.__version__}, llvmlite {llvmlite.__version__}")
    else:
        print("numba is not installed: skipping the numba rows "
              "(`.venv/bin/pip install numba` in your own venv; it is not a dependency)")
    cands["numpy"] = numpy_candidate(inp)
    times, passes, outs, copy_s = measure(cands, inp, a.repeats)
    ref_name = "C avx2" if "C avx2" in outs else "C baseline"
    ref = outs[ref_name]
    move = float(np.abs(ref - inp.rows).max())
    print(f"copy pass (np.copyto of the ({a.frames}, {a.samples}, 7) edges, "
          f"{inp.edges.nbytes / 2**20:.1f} MiB): median {copy_s * 1e3:.2f} ms; "
          f"agreement and bits against {ref_name}; largest move {move:.3g}")
    print(f"{'candidate':<16} {'µs/frame':>9} {'(min)':>7} {'ms/pass':>8} {'passes':>7} "
          f"{'(min-max)':>13} {'agreement':>10}  bits")
    for k in cands:
        t = np.array(times[k])
        ps = np.array(passes[k])
        diff = outs[k] - ref
        agree = float(np.abs(diff).max()) / move
        ndiff = int(np.count_nonzero(diff))
        bits = "identical" if ndiff == 0 else f"differ in {ndiff} of {diff.size} values"
        print(f"{k:<16} {np.median(t) * 1e6 / (a.frames - 1):9.2f} "
              f"{t.min() * 1e6 / (a.frames - 1):7.2f} {np.median(t) * 1e3:8.2f} "
              f"{np.median(ps):7.2f} {f'({ps.min():.2f}-{ps.max():.2f})':>13} {agree:10.1e}  "
              f"{bits}")
    if have_numba:
        print("numba in this process, first call (cold compile, no cache): " + ", ".join(
            f"{k} {v:.2f} s" for k, v in compile_s.items()))
        rounds = numba_compile_times(a.compile_rounds)
        med = np.median(np.array(rounds), axis=0)
        print(f"numba strict in fresh subprocesses, median of {len(rounds)}: import "
              f"{med[0]:.2f} s, cold compile (empty cache) {med[1]:.1f} s wall, {med[3]:.1f} s "
              f"CPU, load from its on-disk cache {med[2]:.2f} s (rounds, compile/load: "
              + "; ".join(f"{c:.1f}/{ld:.2f}" for _, c, ld, _ in rounds) + ")")
        print(f"installed size of numba + llvmlite (du): {install_size_mib():.0f} MiB")
        if a.install_time:
            print(f"pip install --no-cache-dir --no-deps numba llvmlite into a temp dir: "
                  f"{install_seconds():.1f} s")
    print("C library sizes (with debug info): " + ", ".join(
        f"{Path(p).name} {os.path.getsize(p) / 1024:.0f} KiB" for p in sorted(
            {s.origin for s in (importlib.util.find_spec(m) for m in
                                ("mcsm.core._kernel", "mcsm.core._kernel_avx2"))
             if s is not None and s.origin is not None})))
    build = c_build_seconds()
    if build is not None:
        print(f"C build of _kernel.c with setup.py's flags and -mavx2 (gcc, one library): "
              f"{build[0]:.1f} s wall, {build[1]:.1f} s CPU")
    print(f"load average at the end {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
