"""The device kernel on the CPU: ``_kernel_cuda.cu`` compiled as host C++ and launched thread
by thread, behind the same :class:`mcsm.core.device.Backend` interface as CUDA.

This is how the test suite checks the device source and the device backend's Python code
without a GPU (tests/core/test_device_emulation.py), and how ``benchmarks/gpu_check.py
--emulate`` rehearses its GPU run. It is slow (one thread at a time) and never used by a map
unless asked for: ``StochasticMap(n, device=EmulatedBackend())``.

The library is built on first use with g++ and the CPU kernel's flags (setup.py's
``KERNEL_FLAGS``, less the two that are C-only), into a cache directory keyed by the sources'
hash and the flags.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import weakref
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import device
from mcsm.core.device import HEADER, SOURCE, Backend

EMULATION = SOURCE.with_name("_kernel_emulation.cpp")
#: setup.py's KERNEL_FLAGS for C++ (``-std=gnu11`` and ``-fexcess-precision=standard`` are C
#: only; the test suite checks that the rest are setup.py's, flag for flag)
EMULATION_FLAGS = ["-std=c++14", "-O3", "-ffp-contract=off", "-fno-fast-math",
                   "-fno-unsafe-math-optimizations", "-fno-math-errno", "-Wall",
                   "-Wno-unused-function", "-Wno-psabi"]


def build(out_dir: str | os.PathLike[str] | None = None,
          flags: Sequence[str] = tuple(EMULATION_FLAGS)) -> Path:
    """Compile the emulation library (cached); its path. Raises RuntimeError with the
    compiler's output if g++ is missing or the build fails."""
    cxx = shutil.which("g++") or shutil.which("c++")
    if cxx is None:
        raise RuntimeError("the device kernel's emulation needs a C++ compiler (g++)")
    h = hashlib.sha256()
    for f in (SOURCE, HEADER, EMULATION):
        h.update(f.read_bytes())
    h.update(" ".join(flags).encode())
    base = Path(out_dir) if out_dir is not None else Path(tempfile.gettempdir()) / "mcsm-emulation"
    base.mkdir(parents=True, exist_ok=True)
    lib = base / f"emu-{h.hexdigest()[:16]}.so"
    if lib.exists():
        return lib
    tmp = base / f".{lib.name}.{os.getpid()}"
    res = subprocess.run([cxx, *flags, "-shared", "-fPIC", f"-I{SOURCE.parent}", str(EMULATION),
                          "-o", str(tmp)], capture_output=True, text=True, timeout=300,
                         check=False)
    if res.returncode != 0:
        raise RuntimeError(f"building the device kernel's emulation failed:\n{res.stderr}")
    os.replace(tmp, lib)
    return lib


class EmulatedBackend(Backend):
    """numpy arrays as "device memory" (with a byte limit, to test refusals) and the
    emulation library as the launcher."""

    def __init__(self, library: str | os.PathLike[str] | None = None,
                 limit_bytes: int = 1 << 40) -> None:
        self._lib = ctypes.CDLL(str(library if library is not None else build()))
        self._lib.emu_launch.argtypes = [ctypes.c_char_p, ctypes.c_uint, ctypes.c_uint,
                                         ctypes.POINTER(ctypes.c_void_p)]
        self._lib.emu_launch.restype = ctypes.c_int
        self.xp = np
        self.name = "emulated"
        self.description = "the device kernel compiled as host C++, launched thread by thread"
        self.limit_bytes = int(limit_bytes)
        self.in_use = 0
        self.launches: dict[str, int] = {}

    def launch(self, kernel_name: str, threads: int, args: Sequence[object]) -> None:
        if threads <= 0:
            return
        holders: list[Any] = []
        ptrs = (ctypes.c_void_p * len(args))()
        for j, a in enumerate(args):
            if isinstance(a, np.ndarray):
                if not a.flags.c_contiguous:
                    raise ValueError(f"{kernel_name}: argument {j} is not contiguous")
                h: Any = ctypes.c_void_p(a.ctypes.data)
            elif isinstance(a, np.int64):
                h = ctypes.c_longlong(int(a))
            elif isinstance(a, np.int32):
                h = ctypes.c_int(int(a))
            elif isinstance(a, np.float64):
                h = ctypes.c_double(float(a))
            else:
                raise TypeError(f"{kernel_name}: argument {j} of type {type(a).__name__}")
            holders.append(h)
            ptrs[j] = ctypes.cast(ctypes.pointer(h), ctypes.c_void_p)
        block = device.BLOCKS.get(kernel_name, device.BLOCK)
        blocks = (threads + block - 1) // block
        if self._lib.emu_launch(kernel_name.encode(), blocks, block, ptrs) != 0:
            raise ValueError(f"no kernel {kernel_name!r} in the device source")
        self.launches[kernel_name] = self.launches.get(kernel_name, 0) + 1

    def free_bytes(self) -> int:
        return self.limit_bytes - self.in_use

    def address(self, a: Any) -> int:
        return int(a.ctypes.data)

    def download(self, a: Any) -> npt.NDArray[Any]:
        return np.array(a, copy=True)

    def _allocate(self, shape: tuple[int, ...], dtype: Any) -> Any:
        a = np.empty(shape, dtype=dtype)
        self.in_use += a.nbytes
        weakref.finalize(a, self._release, a.nbytes)
        return a

    def _release(self, nbytes: int) -> None:
        self.in_use -= nbytes

    def synchronize(self) -> None:
        return None


def nvrtc_library() -> str | None:
    """The path of an NVRTC library (the ``nvidia-cuda-nvrtc`` wheel's, or the system's)."""
    import ctypes.util
    import importlib.util

    spec = importlib.util.find_spec("nvidia")
    for root in (list(spec.submodule_search_locations or []) if spec is not None else []):
        for pattern in ("cu13/lib/libnvrtc.so*", "cuda_nvrtc/lib/libnvrtc.so*",
                        "cu12/lib/libnvrtc.so*"):
            found = sorted(p for p in Path(root).glob(pattern) if "builtins" not in p.name)
            if found:
                return str(found[0])
    return ctypes.util.find_library("nvrtc")


def ptxas_info(options: Sequence[str], arch: str = "sm_90",
               library: str | None = None) -> dict[str, dict[str, int]]:
    """What the device kernels need per thread once NVRTC has compiled them for ``arch`` (no
    GPU needed): ``{kernel: {"registers", "stack", "spill_stores", "spill_loads"}}``, read
    from ptxas's verbose log. Registers decide how many threads an SM can hold."""
    import re

    log = _nvrtc(options, arch, library, ("--ptxas-options=-v",))[1]
    out: dict[str, dict[str, int]] = {}
    name = ""
    for line in log.splitlines():
        m = re.search(r"Compiling entry function '(\w+)'", line)
        if m:
            name = m.group(1)
            out[name] = {}
        m = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill "
                      r"loads", line)
        if m and name:
            out[name].update(stack=int(m.group(1)), spill_stores=int(m.group(2)),
                             spill_loads=int(m.group(3)))
        m = re.search(r"Used (\d+) registers", line)
        if m and name:
            out[name]["registers"] = int(m.group(1))
    return out


def compile_ptx(options: Sequence[str], arch: str = "compute_90",
                library: str | None = None) -> str:
    """The device kernel's PTX, compiled by NVRTC through ctypes (no GPU needed) with
    ``options`` (e.g. :data:`mcsm.core.device.NVRTC_OPTIONS`). Raises RuntimeError with
    NVRTC's log when it does not compile, or when no NVRTC library is found."""
    return _nvrtc(options, arch, library)[0]


def _nvrtc(options: Sequence[str], arch: str, library: str | None,
           extra: Sequence[str] = ()) -> tuple[str, str]:
    """NVRTC run on the device source: (its PTX, its log)."""
    from mcsm.core.device import device_source

    path = library or nvrtc_library()
    if path is None:
        raise RuntimeError("no NVRTC library (pip install nvidia-cuda-nvrtc)")
    lib = ctypes.CDLL(path)
    prog = ctypes.c_void_p()
    src = device_source().encode()
    if lib.nvrtcCreateProgram(ctypes.byref(prog), src, b"_kernel_cuda.cu", 0, None, None):
        raise RuntimeError("nvrtcCreateProgram failed")
    try:
        opts = [f"--gpu-architecture={arch}", *options, *extra]
        arr = (ctypes.c_char_p * len(opts))(*[o.encode() for o in opts])
        rc = lib.nvrtcCompileProgram(prog, len(opts), arr)
        size = ctypes.c_size_t()
        lib.nvrtcGetProgramLogSize(prog, ctypes.byref(size))
        log = ctypes.create_string_buffer(size.value)
        lib.nvrtcGetProgramLog(prog, log)
        text = log.value.decode(errors="replace")
        if rc != 0:
            raise RuntimeError(f"NVRTC could not compile the device kernel ({rc}):\n{text}")
        lib.nvrtcGetPTXSize(prog, ctypes.byref(size))
        ptx = ctypes.create_string_buffer(size.value)
        lib.nvrtcGetPTX(prog, ptx)
        return ptx.value.decode(), text
    finally:
        lib.nvrtcDestroyProgram(ctypes.byref(prog))
