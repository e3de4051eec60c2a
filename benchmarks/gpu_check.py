"""The map on a GPU, checked once (issue 25): bits against the CPU kernel, the shipped
recordings replayed on the device, the timing table, loop closures per second through
``mcsm serve --device cuda`` over Zenoh, and two datasets' digests.

Run once on a machine with an NVIDIA GPU, unattended, within about 4 minutes; mcsm need not be
installed there (benchmarks/results/README gives the wheels to carry, the one command and
where the output goes)::

    PYTHONPATH=service:clients:.:/tmp/site python3 benchmarks/gpu_check.py \\
        --out "$OUT" --data .gpu-carry/data

Sections, each guarded (one that fails is reported and the others still run):

1. environment: GPU, CuPy, NVRTC, and a device-to-device copy's bandwidth (the practical peak);
2. bits: every case of ``tests/core/device_cases.py`` (each option set of the joint update,
   point observations, the three forced failures) at N = 50 and 1003, then the timing
   sizes M = 400 and 4,000 at N = 1000: per-frame codes and every value (as 64-bit
   patterns) of the GPU's frame pass against the CPU kernel's;
3. replays: each recording of ``recordings/`` rebuilt on the device: identical digests;
4. tune (``benchmarks/gpu_tune.py``): the frame pass's three launches timed one by one at
   ``--tune-frames`` (100,000) for each block size and samples per thread of the apply step,
   every shape's output compared bit for bit; ``--keep-tuned`` keeps the fastest shapes for
   the sections that follow;
5. timings (state resident on the device, median of ``--repeats``, CUDA events): the frame
   pass of a loop closure (three launches, inputs already on the device), the whole
   ``StochasticMap.update`` of a loop closure (wall clock: the O(N) analysis on the CPU, two
   edges down, the weights up, the pass, the check), and the CPU kernel on one thread where
   ``--cpu-max-frames`` allows; the bandwidth counts 3 x 7 N M x 8 bytes (the sums read the
   component, the apply step reads and writes it);
6. serve (``benchmarks/gpu_serve.py``): ``mcsm serve --device cuda`` as a subprocess, a map of
   ``--serve-frames`` (100,000) frames built over Zenoh by acknowledged imports and joins,
   then acknowledged loop closures per second from ``MapClient``s (the issue's >= 200/s
   target), within ``--serve-budget-s``;
7. datasets (``benchmarks/gpu_datasets.py``), if time is left: Victoria Park and sphere2500
   streamed into a CPU map and a device map with the same samples, four processes at once:
   the same digest every ``--dataset-every`` updates and at the end of each file (or as far
   as each got).

Every section is saved as soon as it ends, in this order: the bits first, then the timings.

Exit status: 0 when every comparison that ran agreed (or when there is no GPU: it says so),
1 when one differed, 2 on bad arguments. ``--emulate`` runs every section on the emulated
device (``mcsm.core.emulation``, small sizes, timings meaningless): the rehearsal the test
suite runs.
"""

from __future__ import annotations

import argparse
import ast
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: in the order they run (and are saved): the bits first, then the timings
SECTIONS = ("environment", "bits", "replays", "tune", "timings", "serve", "datasets")


def _source_package() -> Path:
    """``mcsm`` laid out as pip installs it, made of links to this checkout: the package's
    files and ``mcsm.schemas`` (which lives in ``schemas/``; the recorder of the serve
    section reads its JSON Schemas as package data). The folder to put first on the path."""
    site = Path(tempfile.mkdtemp(prefix="mcsm-site-"))
    (site / "mcsm").mkdir()
    for entry in (ROOT / "service" / "mcsm").iterdir():
        if entry.name != "__pycache__":
            (site / "mcsm" / entry.name).symlink_to(entry)
    (site / "mcsm" / "schemas").symlink_to(ROOT / "schemas")
    return site


def bootstrap() -> str:
    """Make ``mcsm`` importable from this checkout when it is not installed (for this
    process and the ``mcsm serve`` it starts), building the CPU kernel with setup.py's flags
    unless ``MCSM_KERNEL_LIBRARY`` names one; a line saying what was done."""
    for p in (ROOT, ROOT / "clients"):  # tests.*, mcsm_client
        if str(p) not in sys.path:
            sys.path.insert(0, str(p))
    try:
        importlib.metadata.version("mcsm")
        return "mcsm: installed"
    except importlib.metadata.PackageNotFoundError:
        pass
    site = _source_package()
    sys.path.insert(0, str(site))
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [str(site), str(ROOT / "clients"), str(ROOT), os.environ.get("PYTHONPATH", "")])
    if os.environ.get("MCSM_KERNEL_LIBRARY"):
        return f"mcsm: from {ROOT}, kernel {os.environ['MCSM_KERNEL_LIBRARY']}"
    tree = ast.parse((ROOT / "setup.py").read_text())
    names = {getattr(n.targets[0], "id", ""): n.value for n in tree.body
             if isinstance(n, ast.Assign)}
    flags = ast.literal_eval(names["KERNEL_FLAGS"])
    sources = [str(ROOT / s) for s in ast.literal_eval(names["SOURCE"])]  # the kernel's files
    cpu = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    extra = ["-mavx2"] if " avx2" in cpu and platform.machine() == "x86_64" else []
    lib = Path(tempfile.mkdtemp(prefix="mcsm-kernel-")) / "kernel.so"
    subprocess.run(["gcc", *flags, *extra, "-shared", "-fPIC", *sources, "-lm", "-o", str(lib)],
                   check=True, timeout=300)
    os.environ["MCSM_KERNEL_LIBRARY"] = str(lib)
    return f"mcsm: from {ROOT}, CPU kernel built here ({' '.join(extra) or 'baseline'})"


class Report:
    def __init__(self, out: Path | None) -> None:
        self.lines: list[str] = []
        self.data: dict[str, Any] = {}
        self.failed: list[str] = []
        self.out = out

    def say(self, line: str = "") -> None:
        print(line, flush=True)
        self.lines.append(line)

    def save(self) -> None:
        if self.out is None:
            return
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "gpu_check.txt").write_text("\n".join(self.lines) + "\n")
        (self.out / "gpu_check.json").write_text(json.dumps(self.data, indent=1,
                                                            default=str) + "\n")


class Timer:
    """CUDA events on a GPU, the wall clock on the emulated device."""

    def __init__(self, be: Any) -> None:
        self.cupy = be.xp if be.name.startswith("cuda") else None

    def run(self, fn: Any, repeats: int, warmup: int = 2) -> list[float]:
        for _ in range(warmup):
            fn()
        times = []
        for _ in range(repeats):
            if self.cupy is not None:
                a, b = self.cupy.cuda.Event(), self.cupy.cuda.Event()
                a.record()
                fn()
                b.record()
                b.synchronize()
                times.append(float(self.cupy.cuda.get_elapsed_time(a, b)))
            else:
                t0 = time.perf_counter()
                fn()
                times.append((time.perf_counter() - t0) * 1e3)
        return times


def median(xs: list[float]) -> float:
    s = sorted(xs)
    k = len(s) // 2
    return s[k] if len(s) % 2 else 0.5 * (s[k - 1] + s[k])


# ------------------------------------------------------------------ sections

def environment(rep: Report, be: Any, emulate: bool) -> float:
    """The device and a copy's bandwidth (bytes read + written per second), or 0."""
    import numpy as np

    rep.say(f"device: {be.name} ({be.description}); numpy {np.__version__}; "
            f"python {platform.python_version()}")
    if emulate:
        return 0.0
    cp = be.xp
    props = cp.cuda.runtime.getDeviceProperties(0)
    rep.say(f"cupy {cp.__version__}; CUDA runtime {cp.cuda.runtime.runtimeGetVersion()}, "
            f"driver {cp.cuda.runtime.driverGetVersion()}; NVRTC {cp.cuda.nvrtc.getVersion()}; "
            f"{props.get('multiProcessorCount')} SMs; "
            f"{cp.cuda.runtime.memGetInfo()[1] / 2**30:.1f} GiB")
    peak = 0.0
    if props.get("memoryClockRate") and props.get("memoryBusWidth"):
        peak = 2.0 * props["memoryClockRate"] * 1e3 * props["memoryBusWidth"] / 8
        rep.say(f"nominal memory bandwidth {peak / 1e12:.2f} TB/s")
    a = cp.ones(2**28)  # 2 GiB
    b = cp.empty_like(a)
    ms = median(Timer(be).run(lambda: cp.copyto(b, a), 10))
    copy_bw = 2 * a.nbytes / (ms * 1e-3)
    rep.say(f"device-to-device copy: {copy_bw / 1e12:.2f} TB/s (read + written, median of 10)")
    rep.data["environment"] = {"device": be.description, "copy_bytes_per_s": copy_bw,
                               "nominal_bytes_per_s": peak}
    return copy_bw


def bits(rep: Report, be: Any) -> None:
    import numpy as np

    from tests.core import device_cases

    rep.say("\n## bits: device frame pass vs the CPU kernel (codes and every value)")
    rows = []
    for name in sorted(device_cases.CASES):
        for n in (50, 1003):
            case, _ = device_cases.frame_case(name, n)
            cpu_codes, cpu_out = device_cases.cpu_pass(case)
            dev_codes, dev_out = device_cases.device_pass(case, be)
            ok = cpu_codes == 0
            codes_same = bool(np.array_equal(cpu_codes, dev_codes))
            differ = int((cpu_out[ok].view(np.uint64) != dev_out[ok].view(np.uint64)).sum())
            good = codes_same and differ == 0
            rows.append({"case": name, "n": n, "codes_same": codes_same,
                         "failing_frames": int((~ok).sum()), "values": int(cpu_out[ok].size),
                         "values_differ": differ})
            rep.say(f"{'identical' if good else 'DIFFERENT'}  {name:34s} N={n:5d}  "
                    f"frames failing {int((~ok).sum()):2d} (codes "
                    f"{'same' if codes_same else 'differ'}), {differ} of "
                    f"{cpu_out[ok].size} values differ")
            if not good:
                rep.failed.append(f"bits {name} N={n}")
    rep.data["bits"] = rows


def replays(rep: Report, be: Any) -> None:
    from mcsm.log.replay import replay

    rep.say("\n## the shipped recordings replayed on the device")
    out = {}
    for path in sorted((ROOT / "recordings").glob("*.mcap")):
        t0 = time.perf_counter()
        r = replay(path, device=be)
        dt = time.perf_counter() - t0
        out[path.name] = {"identical": r.identical, "divergence": r.divergence,
                          "final": r.final_digests(), "seconds": dt}
        why = "" if r.identical else f" {r.divergence}"
        rep.say(f"{'identical' if r.identical else 'DIVERGED'}  {path.name}  "
                f"({r.n_inputs} inputs, {dt:.1f} s){why}")
        if not r.identical:
            rep.failed.append(f"replay {path.name}")
    rep.data["replays"] = out


def _base(n: int, frames: int, seed: int) -> Any:
    """A real 3-D chain component of ``frames`` frames (CPU) and one loop closure on it."""
    import numpy as np
    from gpu_serve import chain
    from mcsm.core import joint
    from mcsm.core.storage import to_rows

    m = chain(n, frames, seed, threads=4)
    rng = np.random.default_rng(seed + 1)
    c = m._comps[m._where["p0"]]
    a, b = "p2", f"p{frames - 3}"
    x_rows = to_rows(m.query(a, b)[rng.permutation(n)])
    prep = joint.prepare(c, c.index[a], c.index[b], x_rows, False, "tangent", "ensrf")
    args, arrays = joint.frame_args(c, c.index[a], c.index[b], prep, space="tangent",
                                    gain="direct", shrink=4.0, inflation=1.0)
    return m, c, args, arrays, x_rows


def timings(rep: Report, be: Any, sizes: list[tuple[int, int]], repeats: int,
            cpu_max: int, bits_max: int, copy_bw: float, deadline: float) -> None:
    rep.say(f"\n## timings: loop closure, state resident, median of {repeats} "
            f"({'CUDA events' if be.name.startswith('cuda') else 'wall clock, emulated'})")
    rep.say("| M | N | device pass ms | bandwidth | of copy bw | whole update ms | "
            "CPU kernel 1 thread ms | bits at this size |")
    rep.say("|---|---|---|---|---|---|---|---|")
    out_rows: list[dict[str, Any]] = []
    bases: dict[int, Any] = {}
    for m_frames, n in sizes:
        if time.perf_counter() > deadline:
            rep.say(f"| {m_frames} | {n} | skipped: out of time | | | | | |")
            continue
        try:
            if n not in bases:
                bases[n] = _base(n, 200 if n <= 2000 else 40, 20261205 + n)
            row = _time_one(rep, be, bases[n], m_frames, n, repeats, cpu_max, bits_max,
                            copy_bw)
            out_rows.append(row)
        except Exception as exc:  # report and go on
            rep.say(f"| {m_frames} | {n} | failed: {type(exc).__name__}: {exc} | | | | | |")
            rep.data.setdefault("errors", []).append(traceback.format_exc())
    rep.data["timings"] = out_rows


def _time_one(rep: Report, be: Any, base: Any, m_frames: int, n: int, repeats: int,
              cpu_max: int, bits_max: int, copy_bw: float) -> dict[str, Any]:
    """One row of the timing table (and, up to ``bits_max`` frames, every value compared)."""
    import numpy as np
    from mcsm import StochasticMap
    from mcsm.core import kernel
    from mcsm.core.device import DeviceComponent, first_failure
    from mcsm.core.storage import from_rows

    timer, xp = Timer(be), be.xp
    m0, c0, args, arrays, x_rows = base
    base_rows = c0.rows  # (M0, 7, N)
    reps = -(-m_frames // base_rows.shape[0])
    dev_base = be.upload(np.ascontiguousarray(np.transpose(base_rows, (1, 2, 0))))
    be.reserve(2 * 7 * n * m_frames * 8, "the timing component")
    buf = xp.ascontiguousarray(xp.tile(dev_base, (1, 1, reps))[:, :, :m_frames])
    del dev_base
    frames = [f"f{i}" for i in range(m_frames)]
    dc = DeviceComponent(be, frames, [False] * m_frames, buf)
    out = be.empty(buf.shape)
    inputs = dc.pass_inputs(args, arrays)
    t_pass = timer.run(lambda: dc.launch_pass(inputs, out), repeats)
    rc, flags = dc.launch_pass(inputs, out)
    code = first_failure(xp, rc, flags)
    ms = median(t_pass)
    bw = 3 * 7 * n * m_frames * 8 / (ms * 1e-3)
    row: dict[str, Any] = {"M": m_frames, "N": n, "pass_ms": t_pass, "pass_median_ms": ms,
                           "bytes_per_s": bw, "code": code}
    same = "-"
    if m_frames <= bits_max:  # every frame at this size against the CPU kernel
        cpu_rows = np.ascontiguousarray(np.tile(base_rows, (reps, 1, 1))[:m_frames])
        cpu_out = np.empty_like(cpu_rows)
        for name_, arr in arrays.items():
            setattr(args, name_, kernel.ptr(arr))
        flags_h = np.zeros(m_frames, dtype=np.uint8)
        t_cpu = []
        for _ in range(max(1, min(repeats, 5)) if m_frames <= cpu_max else 1):
            t0 = time.perf_counter()
            cpu_code = kernel.joint_frames(args, cpu_rows, cpu_out, flags_h, 0, m_frames)
            t_cpu.append((time.perf_counter() - t0) * 1e3)
        if m_frames <= cpu_max:
            row["cpu_ms"] = t_cpu
        dev_out = np.transpose(be.download(out), (2, 0, 1))
        differ = int((dev_out.view(np.uint64) != cpu_out.view(np.uint64)).sum())
        same = "identical" if differ == 0 and cpu_code == code else \
            f"DIFFERENT ({differ} values, codes {cpu_code} / {code})"
        row["bits_values_differ"] = differ
        if same != "identical":
            rep.failed.append(f"bits at M={m_frames} N={n}")
    # the whole update on a map holding this component
    smap = StochasticMap(n, gate=None, device=be)
    smap._install(dc, new_frames=frames)
    rng = np.random.default_rng(7)
    x = from_rows(x_rows)
    a, b = "f2", f"f{min(m_frames - 3, 197)}"
    t_upd = []
    for _ in range(max(3, repeats // 2)):
        t0 = time.perf_counter()
        smap.update(a, b, x[rng.permutation(n)])
        be.synchronize()
        t_upd.append((time.perf_counter() - t0) * 1e3)
    row["update_ms"] = t_upd
    cpu_txt = f"{median(row['cpu_ms']):.2f}" if "cpu_ms" in row else "not run"
    share = f"{100 * bw / copy_bw:.0f} %" if copy_bw else "-"
    rep.say(f"| {m_frames} | {n} | {ms:.3f} | {bw / 1e12:.2f} TB/s | {share} | "
            f"{median(t_upd):.2f} | {cpu_txt} | {same} |")
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="write gpu_check.txt/.json here")
    ap.add_argument("--data", type=Path, default=None,
                    help="folder with victoria_park.txt and sphere2500.txt (default: gtsam's)")
    ap.add_argument("--emulate", action="store_true",
                    help="rehearse on the emulated device (no GPU; small sizes)")
    ap.add_argument("--budget-s", type=float, default=225.0,
                    help="stop starting work after this many seconds (default 225)")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--sizes", default="400x1000,4000x1000,40000x1000,100000x1000,10000x10000",
                    help="the timing table's M x N")
    ap.add_argument("--cpu-max-frames", type=int, default=4000,
                    help="time the CPU kernel up to this M (default 4000)")
    ap.add_argument("--bits-max-frames", type=int, default=4000,
                    help="compare every value of the timing passes up to this M")
    ap.add_argument("--serve-frames", type=int, default=100_000,
                    help="frames of the served map (default 100000)")
    ap.add_argument("--serve-samples", type=int, default=1000,
                    help="N of the served map (default 1000)")
    ap.add_argument("--serve-clients", type=int, default=4,
                    help="clients with a request in flight at once (default 4)")
    ap.add_argument("--serve-seconds", type=float, default=5.0,
                    help="seconds of loop closures per measurement (default 5)")
    ap.add_argument("--serve-block-frames", type=int, default=128,
                    help="frames per import (default 128: 7.2 MB at N = 1000)")
    ap.add_argument("--serve-budget-s", type=float, default=120.0,
                    help="the serve section's own time limit (default 120)")
    ap.add_argument("--dataset-samples", type=int, default=100)
    ap.add_argument("--dataset-every", type=int, default=500,
                    help="compare the datasets' digests every this many updates (default 500)")
    ap.add_argument("--max-constraints", type=int, default=None)
    ap.add_argument("--tune-frames", type=int, default=100_000,
                    help="M of the tuning section (N = 1000; default 100000)")
    ap.add_argument("--tune-blocks", default="128,256",
                    help="block sizes the tuning section tries (a block larger than a kernel "
                         "can launch is cut to its limit)")
    ap.add_argument("--tune-spt", default="8,16,32",
                    help="samples per thread of the apply step the tuning section tries")
    ap.add_argument("--tune-caps", default="0,128,96",
                    help="register caps (NVRTC --maxrregcount; 0: none) the tuning section "
                         "recompiles the kernels with")
    ap.add_argument("--keep-tuned", action="store_true",
                    help="the fastest launch shapes stay set for the sections that follow")
    ap.add_argument("--skip", nargs="*", default=[],
                    choices=list(SECTIONS))
    args = ap.parse_args(argv)
    t_start = time.perf_counter()
    deadline = t_start + args.budget_s
    try:
        sizes = [tuple(int(v) for v in s.split("x")) for s in args.sizes.split(",") if s]
        assert all(len(s) == 2 and s[0] >= 8 and s[1] >= 2 for s in sizes)
    except (ValueError, AssertionError):
        print(f"gpu_check: bad --sizes {args.sizes!r} (M x N, comma-separated)")
        return 2
    rep = Report(args.out)
    rep.say(f"# gpu_check {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}; "
            f"{bootstrap()}")
    from mcsm.core import kernel

    rep.say(f"CPU kernel: {kernel.LIBRARY}")
    if args.emulate:
        from mcsm.core.emulation import EmulatedBackend

        be: Any = EmulatedBackend()
    else:
        try:
            import cupy

            count = int(cupy.cuda.runtime.getDeviceCount())
        except Exception as exc:
            rep.say(f"no GPU here ({type(exc).__name__}: {exc}): nothing to check on a "
                    "device; run this on a machine with an NVIDIA GPU (exit 0)")
            rep.save()
            return 0
        if count < 1:
            rep.say("no GPU here (CuPy sees 0 CUDA devices): nothing to check (exit 0)")
            rep.save()
            return 0
        from mcsm.core.device import backend_for

        be = backend_for("cuda")
    copy_bw = 0.0
    for name in SECTIONS:
        if name in args.skip:
            rep.say(f"\n## {name}: skipped (--skip)")
            continue
        try:
            if name == "environment":
                copy_bw = environment(rep, be, args.emulate)
            elif name == "bits":
                bits(rep, be)
            elif name == "replays":
                replays(rep, be)
            elif name == "tune":
                from gpu_tune import tune_section

                blocks = [int(v) for v in args.tune_blocks.split(",") if v]
                spts = [int(v) for v in args.tune_spt.split(",") if v]
                tune_section(rep, be, _base(1000, 200, 20261205 + 1000),
                             max(8, args.tune_frames), args.repeats, blocks, spts,
                             args.keep_tuned, median,
                             tuple(int(v) for v in args.tune_caps.split(",") if v))
            elif name == "timings":
                timings(rep, be, sizes, args.repeats, args.cpu_max_frames,
                        args.bits_max_frames, copy_bw, deadline)
            elif name == "serve":
                from gpu_serve import serve_section

                serve_section(rep, be, args.emulate, args.serve_frames, args.serve_samples,
                              max(1, args.serve_clients), args.serve_seconds,
                              min(deadline, time.perf_counter() + args.serve_budget_s),
                              max(2, args.serve_block_frames))
            else:
                from gpu_datasets import datasets_section

                datasets_section(rep, args.emulate, args.data, args.dataset_samples, deadline,
                                 args.max_constraints, max(1, args.dataset_every))
        except Exception as exc:
            rep.say(f"\n## {name}: FAILED to run: {type(exc).__name__}: {exc}")
            rep.data.setdefault("errors", []).append(traceback.format_exc())
            if name in ("bits", "replays", "serve"):
                rep.failed.append(f"{name} did not run")
        rep.save()
    verdict = "FAILED: " + ", ".join(rep.failed) if rep.failed else "every comparison agreed"
    rep.say(f"\ntotal {time.perf_counter() - t_start:.0f} s; {verdict}")
    rep.data["failed"] = rep.failed
    rep.save()
    return 1 if rep.failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
