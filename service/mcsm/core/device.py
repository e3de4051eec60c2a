"""The map's storage on a GPU (``StochasticMap(..., device="cuda")``): the accelerator
backends and :class:`DeviceComponent`, the device twin of :class:`mcsm.core.storage.Component`.

A device component keeps its edges in device memory in the *frame-minor* layout
``(7, N, capacity)``: row d, sample i of frame f at ``(d N + i) capacity + f``, so that the
threads of a warp, which take consecutive frames, read and write consecutive doubles
(``_kernel_cuda.cu`` says why; docs/kernel.md, "The device kernel"). What grows with the map
runs on the device, with the arithmetic of ``kernel_common.h`` (the CPU kernel's): a loop
closure's frame pass, the transform of a join and of a re-root, removal's shift, the
re-root's reordering. What is O(N) runs in the CPU kernel on one or two edges copied from the
device (a query, the loop closure's prediction, weights and gate, a new frame's edge, the
endpoint components): "a small transfer" of 7 N doubles per edge, plus the weights
(``p N`` doubles) copied to the device per loop closure. Exports, snapshots and the digest
copy the whole component to the host (O(M N), as the CPU's digest reads it all).

Every operation computes into new device arrays, checks, and only then swaps them in; the
device memory it needs is checked against what is free *before* anything is allocated, and a
request that would not fit raises :class:`mcsm.errors.DeviceMemoryExceeded` with the map
unchanged.

The backend is pluggable: :class:`CudaBackend` (CuPy, the kernels compiled by NVRTC with
``--fmad=false``) and :class:`mcsm.core.emulation.EmulatedBackend` (numpy arrays, the same
kernel source compiled as host C++ and launched thread by thread) run the same code below, so
the test suite exercises it without a GPU.
"""

from __future__ import annotations

import ctypes
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel
from mcsm.core.storage import from_rows, identity_rows
from mcsm.errors import DeviceMemoryExceeded, InvalidOperation, NumericalError

Array = npt.NDArray[np.float64]
HERE = Path(__file__).resolve().parent
SOURCE = HERE / "_kernel_cuda.cu"
HEADER = HERE / "kernel_common.h"
#: NVRTC options: no fused multiply-add (the rule that makes the bits the CPU's); IEEE
#: division and square root and no flush-to-zero (the defaults, stated). The language
#: standard is NVRTC's default (C++17): the source needs C++11 templates only.
NVRTC_OPTIONS = ("--fmad=false", "--prec-div=true", "--prec-sqrt=true", "--ftz=false")
#: threads per block. 128 was the fastest of 128 and 256 for each of the frame pass's three
#: launches on an H100 (benchmarks/results/gpu_check.txt, "tuning"); a 512-thread block of the
#: apply step cannot launch there (172 registers a thread). Launch shapes never change a value:
#: no thread reads another's result.
BLOCK = 128
#: per-kernel block sizes where they differ from :data:`BLOCK`
BLOCKS: dict[str, int] = {}
#: samples per thread of the apply step (each thread loads its frame's gain once for them):
#: SAMPLES_PER_THREAD, or SAMPLES_PER_THREAD_LARGE where that still leaves at least
#: LARGE_THREADS threads. On the H100, M = 100,000 and N = 1000: 32 samples 5.4 ms, 8 samples
#: 6.3 ms; smaller maps were measured with 8 only.
SAMPLES_PER_THREAD = 8
SAMPLES_PER_THREAD_LARGE = 32
LARGE_THREADS = 1 << 21
#: device memory left free for the CUDA context and the library's own temporaries
HEADROOM_BYTES = 256 << 20
_I64, _I32 = np.int64, np.int32


def device_source() -> str:
    """The device kernel's source with ``kernel_common.h`` pasted in place of its
    ``#include`` (one text: a compiler cache keyed on it sees a change of either file)."""
    src = SOURCE.read_text()
    return src.replace('#include "kernel_common.h"', HEADER.read_text(), 1)


def apply_samples_per_thread(m: int, n: int) -> int:
    """Samples per thread of the apply step for ``m`` frames of ``n`` samples."""
    big = SAMPLES_PER_THREAD_LARGE
    return big if m * -(-n // big) >= LARGE_THREADS else SAMPLES_PER_THREAD


class Backend:
    """An accelerator as the device storage sees it: an array module ``xp`` with numpy's
    interface, a kernel launcher, transfers and free memory."""

    name = "backend"
    description = ""
    xp: Any = None

    def launch(self, kernel_name: str, threads: int, args: Sequence[object]) -> None:
        """Run ``kernel_name`` over ``threads`` threads (1-D blocks of :data:`BLOCK` or
        ``BLOCKS[kernel_name]``, at most what the compiled kernel can launch) with
        ``args``: device arrays, ``np.int64`` (``long long``), ``np.int32`` (``int``)."""
        raise NotImplementedError

    def free_bytes(self) -> int:
        raise NotImplementedError

    def address(self, a: Any) -> int:
        """A device array's address (for the argument struct)."""
        raise NotImplementedError

    def download(self, a: Any) -> npt.NDArray[Any]:
        raise NotImplementedError

    def _allocate(self, shape: tuple[int, ...], dtype: Any) -> Any:
        raise NotImplementedError

    def synchronize(self) -> None:
        """Wait for every launch so far."""
        raise NotImplementedError

    def reserve(self, nbytes: int, what: str) -> None:
        """Refuse, before anything is allocated, an operation needing ``nbytes`` more."""
        free = self.free_bytes() - HEADROOM_BYTES
        if nbytes > free:
            raise DeviceMemoryExceeded(f"{what} on {self.name}", int(nbytes), max(0, free))

    def empty(self, shape: tuple[int, ...], dtype: Any = np.float64) -> Any:
        return self._allocate(shape, dtype)

    def zeros(self, shape: tuple[int, ...], dtype: Any = np.float64) -> Any:
        a = self._allocate(shape, dtype)
        a[...] = 0
        return a

    def upload(self, host: npt.NDArray[Any]) -> Any:
        a = self._allocate(host.shape, host.dtype)
        a[...] = self.xp.asarray(host)
        return a


class CudaBackend(Backend):
    """CuPy on CUDA device ``device_id``; the kernels compiled by NVRTC once per process
    (and cached on disk by CuPy)."""

    def __init__(self, device_id: int = 0, options: Sequence[str] = ()) -> None:
        """``options``: NVRTC options added to :data:`NVRTC_OPTIONS` (a register cap such as
        ``--maxrregcount=96`` for the benchmarks; none may change the arithmetic)."""
        try:
            import cupy
        except ImportError as exc:
            raise InvalidOperation(
                f"device='cuda' needs CuPy ({exc}): pip install 'mcsm[gpu]' (cupy-cuda13x) "
                "on a machine with an NVIDIA GPU and its driver") from None
        try:
            count = int(cupy.cuda.runtime.getDeviceCount())
            if count <= device_id:
                raise RuntimeError(f"{count} CUDA device(s) visible")
            self._device = cupy.cuda.Device(device_id)
            self._device.use()
            props = cupy.cuda.runtime.getDeviceProperties(device_id)
            self._module = cupy.RawModule(code=device_source(),
                                          options=(*NVRTC_OPTIONS, *options))
            self._module.get_function("mk_d_joint_apply")  # compile now, fail here
        except Exception as exc:  # CUDARuntimeError, CompileException, no driver, ...
            raise InvalidOperation(f"device='cuda': no usable CUDA GPU: "
                                   f"{type(exc).__name__}: {exc}") from None
        self.xp = cupy
        self._cupy = cupy
        self.name = f"cuda:{device_id}"
        name = props.get("name", b"")
        self.description = name.decode() if isinstance(name, bytes) else str(name)
        self._functions: dict[str, Any] = {}
        self._max_block: dict[str, int] = {}

    def launch(self, kernel_name: str, threads: int, args: Sequence[object]) -> None:
        if threads <= 0:
            return
        fn = self._functions.get(kernel_name)
        if fn is None:
            fn = self._functions[kernel_name] = self._module.get_function(kernel_name)
            try:  # the most threads a block of it can have (its registers decide)
                self._max_block[kernel_name] = int(fn.max_threads_per_block)
            except Exception:  # an older CuPy: the hardware's limit
                self._max_block[kernel_name] = 1024
        block = min(BLOCKS.get(kernel_name, BLOCK), self._max_block[kernel_name])
        fn(((threads + block - 1) // block,), (block,), tuple(args))

    def free_bytes(self) -> int:
        free, _total = self._cupy.cuda.runtime.memGetInfo()
        return int(free) + int(self._cupy.get_default_memory_pool().free_bytes())

    def address(self, a: Any) -> int:
        return int(a.data.ptr)

    def download(self, a: Any) -> npt.NDArray[Any]:
        out: npt.NDArray[Any] = self._cupy.asnumpy(a)
        return out

    def _allocate(self, shape: tuple[int, ...], dtype: Any) -> Any:
        try:
            return self._cupy.empty(shape, dtype=dtype)
        except self._cupy.cuda.memory.OutOfMemoryError:
            need = int(np.prod(shape)) * np.dtype(dtype).itemsize
            raise DeviceMemoryExceeded(f"an allocation on {self.name}", need,
                                       self.free_bytes()) from None

    def upload(self, host: npt.NDArray[Any]) -> Any:
        try:  # one device allocation, filled from the host
            return self._cupy.asarray(host)
        except self._cupy.cuda.memory.OutOfMemoryError:
            raise DeviceMemoryExceeded(f"an allocation on {self.name}", int(host.nbytes),
                                       self.free_bytes()) from None

    def synchronize(self) -> None:
        self._cupy.cuda.Device().synchronize()


_BACKENDS: dict[str, Backend] = {}


def backend_for(device: object) -> Backend | None:
    """The backend of a map's ``device`` argument: None for ``"cpu"``; one shared
    :class:`CudaBackend` for ``"cuda"`` / ``"cuda:K"``; a :class:`Backend` as given."""
    if device == "cpu":
        return None
    if isinstance(device, Backend):
        return device
    if isinstance(device, str) and (device == "cuda" or device.startswith("cuda:")):
        key = "cuda:0" if device == "cuda" else device
        if key not in _BACKENDS:
            try:
                dev_id = int(key.split(":", 1)[1])
            except ValueError:
                raise InvalidOperation(f"device must be 'cpu', 'cuda' or 'cuda:K', "
                                       f"got {device!r}") from None
            _BACKENDS[key] = CudaBackend(dev_id)
        return _BACKENDS[key]
    raise InvalidOperation(f"device must be 'cpu', 'cuda' or 'cuda:K', got {device!r}")


def first_failure(xp: Any, rc: Any, flags: Any) -> int:
    """The code of the first failing frame in frame order (the CPU's, which stops there):
    the gain's code, else a bad quaternion, else a non-finite translation; OK if none."""
    codes = xp.where(rc != 0, rc, xp.where((flags & 1) != 0, kernel.BAD_QUATERNION,
                                           xp.where((flags & 2) != 0, kernel.NONFINITE, 0)))
    bad = xp.flatnonzero(codes)
    if int(bad.size) == 0:
        return kernel.OK
    return int(codes[int(bad[0])])


class DeviceComponent:
    """The frames of one component, root first, with their edges in device memory
    (``(7, N, capacity)``, frame-minor) and their point flags on both sides."""

    def __init__(self, backend: Backend, frames: list[str], is_point: list[bool], buf: Any
                 ) -> None:
        """``buf``: the edges on the device, ``(7, N, capacity)`` with capacity >= M."""
        self.backend = backend
        self.frames = list(frames)
        self.index = {f: i for i, f in enumerate(self.frames)}
        self.n_samples = int(buf.shape[1])
        self._buf = buf
        self._m = len(frames)
        self._flags = [bool(p) for p in is_point]
        self._point = backend.upload(self._flag_bytes(buf.shape[2]))

    @classmethod
    def from_rows(cls, backend: Backend, frames: list[str], is_point: list[bool], rows: Array
                  ) -> DeviceComponent:
        """Upload host edges ``(M, 7, N)`` (the CPU's rows layout) as they are, then make them
        frame-minor on the device (a copy; a transpose on the host costs more than the
        upload)."""
        rows = np.ascontiguousarray(rows)
        backend.reserve(2 * rows.nbytes + len(frames), "storing a component")
        staged = backend.upload(rows)
        buf = backend.empty((7, rows.shape[2], rows.shape[0]))
        buf[...] = backend.xp.transpose(staged, (1, 2, 0))
        del staged
        return cls(backend, frames, is_point, buf)

    def _flag_bytes(self, cap: int) -> npt.NDArray[np.uint8]:
        flags = np.zeros(cap, dtype=np.uint8)
        flags[: self._m] = self._flags
        return flags

    # ------------------------------------------------------------------ reading
    @property
    def root(self) -> str:
        return self.frames[0]

    def __len__(self) -> int:
        return self._m

    @property
    def capacity(self) -> int:
        return int(self._buf.shape[2])

    @property
    def buffer(self) -> Any:
        """The device buffer ``(7, N, capacity)``."""
        return self._buf

    @property
    def nbytes(self) -> int:
        return int(self._buf.nbytes) + int(self._point.nbytes)

    def is_point(self, i: int) -> bool:
        return self._flags[i]

    def point_list(self) -> list[bool]:
        return list(self._flags)

    def edge_rows(self, i: int) -> Array:
        """Edge root→frame ``i`` as host rows ``(7, N)`` (a copy: 7 N doubles moved)."""
        out: Array = np.ascontiguousarray(self.backend.download(self._buf[:, :, i]),
                                          dtype=np.float64)
        return out

    def edge(self, i: int) -> Array:
        return from_rows(self.edge_rows(i))

    def edges(self) -> Array:
        """All edges as host ``(M, N, 7)``: the component copied row by row (no device
        temporary)."""
        n, m = self.n_samples, self._m
        host = np.empty((7, n, m))
        for d in range(7):
            host[d] = self.backend.download(self._buf[d])[:, :m]
        out: Array = np.ascontiguousarray(np.transpose(host, (2, 1, 0)))
        return out

    # ------------------------------------------------------------------ changing
    def _grow(self, need: int, what: str) -> None:
        if need <= self.capacity:
            return
        cap = max(4, 2 * self.capacity, need)
        be = self.backend
        be.reserve(7 * self.n_samples * cap * 8 + cap, what)
        buf = be.empty((7, self.n_samples, cap))
        buf[:, :, : self._m] = self._buf[:, :, : self._m]
        point = be.upload(self._flag_bytes(cap))
        self._buf, self._point = buf, point

    def append(self, frame: str, point: bool, rows: Array) -> None:
        """Add one frame with host edge ``rows`` ``(7, N)``; O(N) amortised."""
        self._grow(self._m + 1, "adding a frame")
        self._buf[:, :, self._m] = self.backend.xp.asarray(rows)
        self._point[self._m] = int(bool(point))
        self._flags.append(bool(point))
        self.frames.append(frame)
        self.index[frame] = self._m
        self._m += 1

    def block_from_rows(self, rows: Array) -> Any:
        """Host edges ``(k, 7, N)`` as a block for :meth:`extend` (uploaded)."""
        host = np.ascontiguousarray(np.transpose(rows, (1, 2, 0)))
        self.backend.reserve(host.nbytes, "storing frames")
        return self.backend.upload(host)

    def extend(self, frames: list[str], is_point: list[bool], block: Any) -> None:
        """Add several frames (a join): ``block`` is a device ``(7, N, k)`` array, from
        :meth:`transformed` or :meth:`block_from_rows`."""
        k = len(frames)
        self._grow(self._m + k, "a join")
        self._buf[:, :, self._m: self._m + k] = block
        self._point[self._m: self._m + k] = self.backend.xp.asarray(
            np.asarray(is_point, dtype=np.uint8))
        self._flags.extend(bool(p) for p in is_point)
        for f in frames:
            self.index[f] = len(self.frames)
            self.frames.append(f)
        self._m += k

    def delete(self, i: int) -> None:
        """Drop frame ``i`` (not the root); other frames' bits are unchanged. The shift
        goes through one temporary of ``N (M - i - 1)`` doubles, allocated first."""
        if i == 0:
            raise ValueError("re-root before deleting the root")
        m, be = self._m, self.backend
        tail = m - i - 1
        if tail > 0:
            be.reserve(8 * self.n_samples * tail + tail, "removing a frame")
            tmp = be.empty((self.n_samples, tail))
            ptmp = self._point[i + 1: m].copy()
            for d in range(7):
                row = self._buf[d]
                tmp[...] = row[:, i + 1: m]
                row[:, i: m - 1] = tmp
            self._point[i: m - 1] = ptmp
        self._point[m - 1] = 0
        del self._flags[i]
        del self.frames[i]
        self._m -= 1
        self.index = {f: j for j, f in enumerate(self.frames)}

    def swap_buffer(self, buf: Any) -> Any:
        if buf.shape != self._buf.shape:
            raise ValueError("buffer shapes differ")
        old, self._buf = self._buf, buf
        return old

    # ------------------------------------------------------------------ O(M N) passes
    def transformed(self, pre: Array, what: str, perm: npt.NDArray[np.int64] | None = None
                    ) -> Any:
        """``canonical(pre ⊕ edge_f)`` of every frame (points pinned) into a new device
        ``(7, N, M)`` array, frame f at ``perm[f]`` (default: in place). Raises
        NumericalError (nothing changed) on a non-finite result."""
        be, n, m = self.backend, self.n_samples, self._m
        order = np.arange(m, dtype=np.int64) if perm is None else perm.astype(np.int64)
        flags_out = np.zeros(m, dtype=np.uint8)
        flags_out[order] = np.asarray(self._flags, dtype=np.uint8)
        be.reserve(8 * (7 * n * m + 7 * n + 20 * m) + 16 * m, what)
        pre_d, perm_d, pt_out = (be.upload(np.ascontiguousarray(pre, dtype=np.float64)),
                                 be.upload(order), be.upload(flags_out))
        out = be.empty((7, n, m))
        part, mrot, bad = be.empty((16 * m,)), be.empty((4 * m,)), be.zeros((m,), np.int32)
        cap, mm, nn = _I64(self.capacity), _I64(m), _I64(n)
        be.launch("mk_d_transform", m * n, (pre_d, self._buf, cap, out, mm, mm, nn,
                                            self._point, perm_d))
        be.launch("mk_d_meanrot_lanes", 4 * m, (out, mm, mm, nn, pt_out, part))
        be.launch("mk_d_meanrot_finish", m, (out, mm, mm, nn, pt_out, part, mrot))
        be.launch("mk_d_canon_check", m * n, (out, mm, mm, nn, pt_out, mrot, bad))
        if int(be.xp.count_nonzero(bad)) != 0:
            raise NumericalError(f"{what} produced non-finite samples")
        return out

    def rerooted(self, k: int) -> DeviceComponent:
        """The component re-rooted at index k (``Component.rerooted``'s arithmetic)."""
        m = self._m
        perm = np.arange(m, dtype=np.int64) + (np.arange(m) < k)
        perm[k] = 0
        out = self.transformed(kernel.invert(self.edge_rows(k)), "re-rooting", perm)
        out[:, :, 0] = self.backend.xp.asarray(identity_rows(self.n_samples))
        order = [k] + [i for i in range(m) if i != k]
        return DeviceComponent(self.backend, [self.frames[i] for i in order],
                               [self._flags[i] for i in order], out)

    def apply_joint(self, args: kernel.JointArgs, arrays: dict[str, Array], threads: int,
                    spare: Any | None) -> Any:
        """The joint update's frame pass on the device (``mcsm.core.joint.apply``): sums,
        per-frame gain, apply; the component's buffer is swapped only if every frame passed.
        ``arrays``: the host arrays ``args`` points to (yc, w, var_y, sum_yc, wbar and, for
        the endpoint gain, pcs, lam, cpy, sum_pc), copied to the device here. Returns the
        replaced buffer (the next update's spare)."""
        del threads
        reuse = spare is not None and spare.shape == self._buf.shape
        self.backend.reserve(0 if reuse else int(self._buf.nbytes), "the loop closure")
        out = spare if reuse else self.backend.empty(self._buf.shape)
        codes = self.frame_pass(args, arrays, out)
        code = first_failure(self.backend.xp, *codes)
        if code == kernel.NONFINITE_GAIN:
            raise NumericalError("the update's gain is not finite")
        if code != kernel.OK:
            raise NumericalError("the update pushed quaternions to zero or non-finite values")
        return self.swap_buffer(out)

    def frame_pass(self, args: kernel.JointArgs, arrays: dict[str, Array], out: Any
                   ) -> tuple[Any, Any]:
        """The joint update's frame pass into ``out`` (a buffer shaped like this
        component's): its inputs copied to the device, then :meth:`launch_pass`; the
        per-frame gain codes and apply flags (device arrays)."""
        inputs = self.pass_inputs(args, arrays)
        codes = self.launch_pass(inputs, out)
        self.backend.synchronize()  # the uploaded inputs must outlive the launches
        del inputs
        return codes

    def pass_inputs(self, args: kernel.JointArgs, arrays: dict[str, Array]) -> dict[str, Any]:
        """The frame pass's inputs on the device (the weights, the prediction, the argument
        struct pointing at them) and its work arrays."""
        be, m = self.backend, self._m
        p, gain = int(args.p), int(args.gain)
        mm = int(args.k) if gain else p
        ntask, nacc = (17 if gain else 7), 2 + mm
        small = sum(int(a.nbytes) for a in arrays.values()) + ctypes.sizeof(args)
        be.reserve(small + 8 * m * (4 * ntask * nacc + 7 * p + 7) + 8 * m, "the loop closure")
        dev = {name: be.upload(np.ascontiguousarray(a)) for name, a in arrays.items()}
        dargs = kernel.JointArgs.from_buffer_copy(args)
        for name, a in dev.items():
            setattr(dargs, name, be.address(a))
        return {"arrays": dev, "args": be.upload(np.frombuffer(bytes(dargs), dtype=np.uint8)
                                                 .copy()),
                "p": p, "ntask": ntask, "nacc": nacc,
                "part": be.empty((4 * ntask * nacc * m,)), "cxy": be.empty((7 * p * m,)),
                "nmean": be.empty((7 * m,)), "rc": be.empty((m,), np.int32),
                "flags": be.empty((m,), np.int32)}

    def launch_pass(self, inputs: dict[str, Any], out: Any) -> tuple[Any, Any]:
        """The three launches of the frame pass (sums per (frame, row, lane); per-frame
        gain; per-sample apply), everything already on the device; ``(rc, flags)``."""
        be, n, m, cap = self.backend, self.n_samples, self._m, self.capacity
        a, part, rc, flags = inputs["args"], inputs["part"], inputs["rc"], inputs["flags"]
        ntask, nacc, spt = inputs["ntask"], inputs["nacc"], apply_samples_per_thread(m, n)
        rc[...] = 0
        flags[...] = 0
        be.launch("mk_d_joint_sums", 4 * ntask * m, (a, self._buf, _I64(cap), _I64(m),
                                                      _I32(ntask), _I32(nacc), part))
        be.launch("mk_d_joint_gain", m, (a, self._buf, _I64(cap), _I64(m), _I32(nacc), part,
                                         inputs["cxy"], inputs["nmean"], rc))
        be.launch("mk_d_joint_apply", m * ((n + spt - 1) // spt),
                  (a, self._buf, _I64(cap), out, _I64(m), self._point, inputs["cxy"],
                   inputs["nmean"], rc, _I32(spt), flags))
        return rc, flags

    def copy(self) -> DeviceComponent:
        self.backend.reserve(self.nbytes, "copying a component")
        return DeviceComponent(self.backend, list(self.frames), self.point_list(),
                               self._buf.copy())
