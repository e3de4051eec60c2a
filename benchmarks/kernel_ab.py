"""Two builds of the CPU kernel timed against each other in one process, interleaved: the
loop-closure frame pass (``mk_joint_frames``), a join's / re-root's transform
(``mk_transform_frames``) and an import's canonicalisation (``mk_canonicalize_frames``), one
thread, on the same inputs; and every output compared bit for bit between the two builds.

``--ref main`` builds that git revision's ``_kernel.c`` (with its ``kernel_common.h`` where
it has one) into a temporary folder with setup.py's flags; the other build is this checkout's
source, built the same way (``-mavx2`` by default; ``--baseline`` for the x86-64 baseline).
Each round times one call of every (case, build) pair, the builds alternating which goes
first, so that a shared machine's load falls on both alike; the table gives each median, the
ratio new / old and the load average before and after::

    nice -n 10 .venv/bin/python benchmarks/kernel_ab.py --ref main --rounds 41
"""

from __future__ import annotations

import argparse
import ast
import ctypes
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SRC = "service/mcsm/core"


def flags() -> list[str]:
    tree = ast.parse((ROOT / "setup.py").read_text())
    return list(next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                     and getattr(n.targets[0], "id", "") == "KERNEL_FLAGS"))


def build(ref: str | None, out: Path, extra: list[str]) -> Path:
    """The kernel of git revision ``ref`` (None: this checkout) built into ``out``."""
    src = ROOT / SRC
    if ref is not None:
        src = out / f"src-{ref.replace('/', '_')}"
        src.mkdir(parents=True, exist_ok=True)
        for name in ("_kernel.c", "kernel_common.h"):
            r = subprocess.run(["git", "-C", str(ROOT), "show", f"{ref}:{SRC}/{name}"],
                               capture_output=True, check=name == "_kernel.c")
            if r.returncode == 0:
                (src / name).write_bytes(r.stdout)
    lib = out / f"kernel-{ref or 'this'}.so".replace("/", "_")
    subprocess.run(["gcc", *flags(), *extra, "-shared", "-fPIC", str(src / "_kernel.c"),
                    "-o", str(lib)], check=True, timeout=600)
    return lib


def cases(n: int, frames: list[int]) -> dict[str, dict[str, Any]]:
    """name -> inputs: the device comparison's loop closures (tests/core/device_cases.py)
    tiled to ``frames`` frames."""
    sys.path[:0] = [str(ROOT), str(ROOT / "service"), str(ROOT / "clients")]
    from tests.core import device_cases

    out: dict[str, dict[str, Any]] = {}
    for name, label in (("default", "loop closure"), ("endpoints", "loop closure, endpoints"),
                        ("denkf-point", "loop closure, point obs.")):
        case, _ = device_cases.frame_case(name, n)
        rows, pts = case["rows"], np.asarray(case["flags"], dtype=np.uint8)
        for m in frames:
            reps = -(-m // rows.shape[0])
            out[f"{label} M={m}"] = {
                "kind": "joint", "args": case["args"], "arrays": case["arrays"],
                "rows": np.ascontiguousarray(np.tile(rows, (reps, 1, 1))[:m]),
                "point": np.ascontiguousarray(np.tile(pts, reps)[:m])}
    pre = out[f"loop closure M={frames[0]}"]["rows"][5]
    for m in frames:
        base = out[f"loop closure M={m}"]
        out[f"join/re-root M={m}"] = {"kind": "transform", "rows": base["rows"],
                                      "point": base["point"], "pre": np.ascontiguousarray(pre)}
        out[f"import M={m}"] = {"kind": "canon", "rows": base["rows"], "point": base["point"]}
    return out


def runner(lib: ctypes.CDLL, case: dict[str, Any]) -> tuple[Any, np.ndarray]:
    """A call of ``lib`` on ``case`` (returns its code) and its output array."""
    P = ctypes.c_void_p
    rows, point = case["rows"], case["point"]
    m, n = rows.shape[0], rows.shape[2]
    out = np.empty_like(rows)

    def ptr(a: np.ndarray) -> P:
        return P(a.ctypes.data)

    if case["kind"] == "joint":
        args = case["args"]
        for name, arr in case["arrays"].items():
            setattr(args, name, arr.ctypes.data)
        fn = lib.mk_joint_frames
        fn.restype = ctypes.c_int
        return (lambda: fn(ctypes.byref(args), ptr(rows), ptr(out), ptr(point),
                           ctypes.c_long(0), ctypes.c_long(m))), out
    if case["kind"] == "transform":
        fn = lib.mk_transform_frames
        fn.restype = ctypes.c_int
        return (lambda: fn(ptr(case["pre"]), ptr(rows), ptr(out), ptr(point), ctypes.c_long(0),
                           ctypes.c_long(m), ctypes.c_long(n))), out
    fn = lib.mk_canonicalize_frames
    fn.restype = ctypes.c_int

    def canon() -> int:
        np.copyto(out, rows)
        return int(fn(ptr(out), ptr(point), ctypes.c_long(0), ctypes.c_long(m),
                      ctypes.c_long(n), ctypes.c_int(1)))

    return canon, out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ref", default="main", help="the old build's git revision (default main)")
    ap.add_argument("--new", default=None, help="the new build's git revision (default: "
                    "this checkout's files)")
    ap.add_argument("--baseline", action="store_true", help="build for baseline x86-64 "
                    "instead of -mavx2")
    ap.add_argument("--rounds", type=int, default=31)
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--frames", default="200,2000")
    args = ap.parse_args(argv)
    extra = [] if args.baseline else ["-mavx2"]
    tmp = Path(tempfile.mkdtemp(prefix="mcsm-kernel-ab-"))
    libs = {"old": ctypes.CDLL(str(build(args.ref, tmp, extra))),
            "new": ctypes.CDLL(str(build(args.new, tmp, extra)))}
    todo = cases(args.n, [int(f) for f in args.frames.split(",")])
    calls = {(c, b): runner(lib, todo[c]) for c in todo for b, lib in libs.items()}
    same = {}
    for c in todo:
        codes = [calls[(c, b)][0]() for b in libs]
        a, b = (calls[(c, k)][1] for k in libs)
        same[c] = codes[0] == codes[1] and bool(np.array_equal(a.view(np.uint64),
                                                                b.view(np.uint64)))
    load0 = os.getloadavg()
    wall: dict[tuple[str, str], list[float]] = {k: [] for k in calls}
    cpu: dict[tuple[str, str], list[float]] = {k: [] for k in calls}
    order = list(libs)
    for r in range(args.rounds):
        for c in todo:
            for b in order if r % 2 == 0 else order[::-1]:
                fn = calls[(c, b)][0]
                t0, c0 = time.perf_counter(), time.thread_time()
                fn()
                c1, t1 = time.thread_time(), time.perf_counter()
                wall[(c, b)].append((t1 - t0) * 1e3)
                cpu[(c, b)].append((c1 - c0) * 1e3)
    load1 = os.getloadavg()
    print(f"# kernel A/B: old = {args.ref}, new = {args.new or 'this checkout'}; "
          f"{'baseline x86-64' if args.baseline else '-mavx2'}; N = {args.n}; one thread; "
          f"{args.rounds} interleaved rounds; load average {load0[0]:.1f} -> {load1[0]:.1f}")
    print("ms per call, medians: wall clock, and the thread's CPU time (what a shared machine's "
          "load disturbs less)")
    print("| pass | old wall | new wall | new / old | old CPU | new CPU | new / old | bits |")
    print("|---|---|---|---|---|---|---|---|")
    for c in todo:
        o, n = (float(np.median(wall[(c, b)])) for b in libs)
        oc, nc = (float(np.median(cpu[(c, b)])) for b in libs)
        print(f"| {c} | {o:.3f} | {n:.3f} | {n / o:.3f} | {oc:.3f} | {nc:.3f} | {nc / oc:.3f} | "
              f"{'identical' if same[c] else 'DIFFERENT'} |")
    return 0 if all(same.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
