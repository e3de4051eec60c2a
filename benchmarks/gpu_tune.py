"""The tuning section of ``gpu_check.py``: the frame pass's three launches timed one by one
(CUDA events) at one size, for each block size and samples-per-thread of the apply step; every
shape's output compared bit for bit with the default shape's, and the default's with the CPU
kernel. Launch shapes cannot change a value (no thread reads another's result); the
comparison checks that they do not.

With ``keep``, the fastest shape of each launch stays set (``mcsm.core.device.BLOCKS`` and
``SAMPLES_PER_THREAD``) for the sections that follow, so the timing table shows it.
"""

from __future__ import annotations

import time
from typing import Any


def _timed(be: Any, fns: list[Any], repeats: int, warmup: int = 2) -> list[list[float]]:
    """Each of ``fns`` run in turn ``repeats`` times; ms per function per repeat."""
    cupy = be.xp if be.name.startswith("cuda") else None
    for _ in range(warmup):
        for fn in fns:
            fn()
    out: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        if cupy is not None:
            ev = [cupy.cuda.Event() for _ in range(len(fns) + 1)]
            ev[0].record()
            for k, fn in enumerate(fns):
                fn()
                ev[k + 1].record()
            ev[-1].synchronize()
            for k in range(len(fns)):
                out[k].append(float(cupy.cuda.get_elapsed_time(ev[k], ev[k + 1])))
        else:
            for k, fn in enumerate(fns):
                t0 = time.perf_counter()
                fn()
                out[k].append((time.perf_counter() - t0) * 1e3)
    return out


def _variant(be: Any, cap: int, emulate: bool) -> Any:
    """The backend with the device source recompiled under a register cap (0: ``be``)."""
    if cap == 0 or emulate:
        return be
    from mcsm.core.device import CudaBackend

    return CudaBackend(0, (f"--maxrregcount={cap}",))


def _registers(rep: Any) -> None:
    """Registers and stack per thread of the frame pass's kernels, from ptxas through NVRTC
    (no GPU needed): registers decide how many warps an SM holds."""
    try:
        from mcsm.core.device import NVRTC_OPTIONS
        from mcsm.core.emulation import ptxas_info

        info = ptxas_info(NVRTC_OPTIONS)
    except Exception as exc:
        rep.say(f"registers: not known ({type(exc).__name__}: {exc})")
        return
    rep.say("registers per thread (sm_90, ptxas): " + ", ".join(
        f"{k} {v.get('registers')}" + (f" (+{v['stack']} B stack)" if v.get("stack") else "")
        for k, v in info.items() if k.startswith("mk_d_joint")))
    rep.data["registers"] = info


def tune_section(rep: Any, be: Any, base: Any, m_frames: int, repeats: int,
                 blocks: list[int], spts: list[int], keep: bool, median: Any,
                 caps: tuple[int, ...] = (0,)) -> None:
    import numpy as np
    from mcsm.core import device, kernel
    from mcsm.core.device import DeviceComponent, first_failure

    xp = be.xp
    _m0, c0, args, arrays, _x = base
    base_rows = c0.rows  # (M0, 7, N)
    n = base_rows.shape[2]
    rep.say(f"\n## tuning: the frame pass's launches one by one, M = {m_frames}, N = {n}, "
            f"median of {repeats}")
    reps = -(-m_frames // base_rows.shape[0])
    be.reserve(3 * 7 * n * m_frames * 8, "the tuning component")
    dev_base = be.upload(np.ascontiguousarray(np.transpose(base_rows, (1, 2, 0))))
    buf = xp.ascontiguousarray(xp.tile(dev_base, (1, 1, reps))[:, :, :m_frames])
    del dev_base
    dc = DeviceComponent(be, [f"f{i}" for i in range(m_frames)], [False] * m_frames, buf)
    inputs = dc.pass_inputs(args, arrays)
    out = be.empty(buf.shape)
    a, part, rc, flags = inputs["args"], inputs["part"], inputs["rc"], inputs["flags"]
    ntask, nacc, capacity = inputs["ntask"], inputs["nacc"], dc.capacity
    i64, i32 = np.int64, np.int32
    default = (device.BLOCK, dict(device.BLOCKS), device.SAMPLES_PER_THREAD)
    _registers(rep)

    kb = [be]  # the backend whose compiled kernels the timed launches use

    def sums() -> None:
        rc[...] = 0
        flags[...] = 0
        kb[0].launch("mk_d_joint_sums", 4 * ntask * m_frames,
                  (a, dc._buf, i64(capacity), i64(m_frames), i32(ntask), i32(nacc), part))

    def gain() -> None:
        kb[0].launch("mk_d_joint_gain", m_frames, (a, dc._buf, i64(capacity), i64(m_frames),
                                                i32(nacc), part, inputs["cxy"],
                                                inputs["nmean"], rc))

    def apply(spt: int) -> Any:
        return lambda: kb[0].launch(
            "mk_d_joint_apply", m_frames * ((n + spt - 1) // spt),
            (a, dc._buf, i64(capacity), out, i64(m_frames), dc._point, inputs["cxy"],
             inputs["nmean"], rc, i32(spt), flags))

    dc.launch_pass(inputs, out)  # the default shapes: the reference
    be.synchronize()
    ref, rc_ref, fl_ref = out.copy(), rc.copy(), flags.copy()
    rows = []
    rep.say("| register cap | block | samples per thread (apply) | sums ms | gain ms | "
            "apply ms | total ms | bits vs default shapes |")
    rep.say("|---|---|---|---|---|---|---|---|")
    emulate = not be.name.startswith("cuda")
    if emulate:  # one compiler there, the host's: register caps mean nothing
        caps = (0,)
    try:
        for rcap in caps:
            try:
                kb[0] = _variant(be, rcap, emulate)
            except Exception as exc:
                rep.say(f"| {rcap} | - | - | could not compile: {exc} | | | | |")
                continue
            for block in blocks:
                device.BLOCK = block
                device.BLOCKS.clear()
                for spt in spts:
                    out[...] = 0
                    try:
                        t = _timed(be, [sums, gain, apply(spt)], repeats)
                        be.synchronize()
                    except Exception as exc:  # a shape this kernel cannot launch
                        rep.say(f"| {rcap or '-'} | {block} | {spt} | cannot launch: "
                                f"{type(exc).__name__}: {str(exc)[:80]} | | | | |")
                        continue
                    same = bool(xp.array_equal(out.view(xp.uint64), ref.view(xp.uint64))
                                and xp.array_equal(rc, rc_ref)
                                and xp.array_equal(flags, fl_ref))
                    if not same:
                        rep.failed.append(f"tuning: cap {rcap} block {block}, spt {spt} "
                                          "changed the bits")
                    row = {"cap": rcap, "block": block, "spt": spt, "sums_ms": median(t[0]),
                           "gain_ms": median(t[1]), "apply_ms": median(t[2]), "same": same,
                           "raw": t}
                    rows.append(row)
                    rep.say(f"| {rcap or '-'} | {block} | {spt} | {row['sums_ms']:.3f} | "
                            f"{row['gain_ms']:.3f} | {row['apply_ms']:.3f} | "
                            f"{row['sums_ms'] + row['gain_ms'] + row['apply_ms']:.3f} | "
                            f"{'identical' if same else 'DIFFERENT'} |")
    finally:
        device.BLOCK, device.BLOCKS, device.SAMPLES_PER_THREAD = \
            default[0], default[1], default[2]
        kb[0] = be
    # the default shapes' output against the CPU kernel, every value
    cpu_rows = np.ascontiguousarray(np.tile(base_rows, (reps, 1, 1))[:m_frames])
    cpu_out = np.empty_like(cpu_rows)
    for name_, arr in arrays.items():
        setattr(args, name_, kernel.ptr(arr))
    flags_h = np.zeros(m_frames, dtype=np.uint8)
    t0 = time.perf_counter()
    cpu_code = kernel.joint_frames(args, cpu_rows, cpu_out, flags_h, 0, m_frames)
    cpu_s = time.perf_counter() - t0
    dev_out = np.transpose(be.download(ref), (2, 0, 1))
    differ = int((dev_out.view(np.uint64) != cpu_out.view(np.uint64)).sum())
    code = first_failure(xp, rc_ref, fl_ref)
    cpu_same = differ == 0 and cpu_code == code
    rep.say(f"default shapes vs the CPU kernel at M = {m_frames}: "
            f"{'identical' if cpu_same else f'DIFFERENT ({differ} values)'} "
            f"(CPU kernel, one thread: {cpu_s:.2f} s)")
    if not cpu_same:
        rep.failed.append(f"tuning: the device pass differs from the CPU kernel at M={m_frames}")
    del cpu_rows, cpu_out, dev_out
    uncapped = [r for r in rows if r["cap"] == 0]
    if not uncapped:
        return
    best_sums = min(uncapped, key=lambda r: r["sums_ms"])
    best_gain = min(uncapped, key=lambda r: r["gain_ms"])
    best_apply = min(uncapped, key=lambda r: r["apply_ms"])
    spt_d = device.apply_samples_per_thread(m_frames, n)
    d = next((r for r in uncapped if r["block"] == default[0] and r["spt"] == spt_d), None)
    total = best_sums["sums_ms"] + best_gain["gain_ms"] + best_apply["apply_ms"]
    rep.say(f"fastest: sums block {best_sums['block']}, gain block {best_gain['block']}, apply "
            f"block {best_apply['block']} x {best_apply['spt']} samples: {total:.3f} ms"
            + (f" (default shapes {d['sums_ms'] + d['gain_ms'] + d['apply_ms']:.3f} ms)"
               if d else ""))
    rep.data["tuning"] = {"M": m_frames, "N": n, "rows": rows, "cpu_same": cpu_same,
                          "best": {"mk_d_joint_sums": best_sums["block"],
                                   "mk_d_joint_gain": best_gain["block"],
                                   "mk_d_joint_apply": best_apply["block"],
                                   "spt": best_apply["spt"]}}
    if keep:
        device.BLOCKS.update({"mk_d_joint_sums": best_sums["block"],
                              "mk_d_joint_gain": best_gain["block"],
                              "mk_d_joint_apply": best_apply["block"]})
        device.SAMPLES_PER_THREAD = device.SAMPLES_PER_THREAD_LARGE = best_apply["spt"]
        rep.say(f"kept for the sections that follow: BLOCKS = {device.BLOCKS}, "
                f"{best_apply['spt']} samples per thread at every size")
