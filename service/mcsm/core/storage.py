"""How a component's edges are stored: the one module that knows the layout.

A component of M frames keeps its edges root→frame in one buffer ``(capacity, 7, N)``: frame
``f`` is one contiguous block of 7 rows of N samples (x, y, z, qw, qx, qy, qz), the kernel's
*rows* layout, so that one fused pass per frame reads it once while it sits in cache. The
capacity grows by doubling, so adding a frame costs O(N) amortised, not a copy of the
component. Frame 0 is the root, its edge the exact identity.

Everything outside this module sees edges as ``(N, 7)`` (one AT) or ``(M, N, 7)`` arrays: the
layout of the API, the wire, exports and recordings; conversions are exact copies.

The passes over a whole component that change it (a join's or a re-root's transform) are
methods here, so that a map on a GPU swaps in :class:`mcsm.core.device.DeviceComponent`,
which has the same methods over device memory. A new O(M N) operation adds a method to both:
the CPU one calls the kernel on rows, the device one launches a kernel on the frame-minor
buffer (docs/kernel.md, "The device kernel": how to add one).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel
from mcsm.errors import NumericalError

Array = npt.NDArray[np.float64]


def to_rows(x: Array) -> Array:
    """``(..., N, k)`` -> ``(..., k, N)``, C-contiguous (an exact copy)."""
    return np.ascontiguousarray(np.swapaxes(x, -1, -2))


def from_rows(r: Array) -> Array:
    """``(..., k, N)`` -> ``(..., N, k)``, C-contiguous (an exact copy)."""
    return np.ascontiguousarray(np.swapaxes(r, -1, -2))


def identity_rows(n_samples: int) -> Array:
    x = np.zeros((7, n_samples))
    x[3] = 1.0
    return x


class Component:
    """The frames of one component, root first, their point flags and their edges."""

    __slots__ = ("frames", "index", "n_samples", "_buf", "_point", "_m", "_means")

    def __init__(self, frames: list[str], is_point: list[bool], rows: Array) -> None:
        """``rows``: ``(M, 7, N)`` edges in the rows layout (taken, not copied, when it is
        C-contiguous float64)."""
        m = len(frames)
        if rows.shape[0] != m or rows.ndim != 3 or rows.shape[1] != 7:
            raise ValueError("rows must be (M, 7, N) for M frames")
        self.frames = list(frames)
        self.index = {f: i for i, f in enumerate(self.frames)}
        self.n_samples = int(rows.shape[2])
        self._buf = np.ascontiguousarray(rows, dtype=np.float64)
        self._point = np.zeros(self._buf.shape[0], dtype=np.uint8)
        self._point[:m] = np.asarray(is_point, dtype=bool)
        self._m = m
        self._means: tuple[Array, npt.NDArray[np.int64], Array] | None = None

    @classmethod
    def in_buffer(cls, frames: list[str], is_point: list[bool], buf: Array) -> Component:
        """The component of ``frames`` whose edges are the first rows of ``buf`` ``(capacity,
        7, N)`` (taken, not copied: a C-contiguous float64 buffer)."""
        m = len(frames)
        if (buf.ndim != 3 or buf.shape[0] < m or buf.dtype != np.float64
                or not buf.flags.c_contiguous):
            raise ValueError("buf must be a C-contiguous float64 buffer of at least M frames")
        c = cls(frames, is_point, buf[:m])
        point = np.zeros(buf.shape[0], dtype=np.uint8)
        point[:m] = c._point[:m]
        c._buf, c._point = buf, point
        return c

    # ------------------------------------------------------------------ reading
    @property
    def root(self) -> str:
        return self.frames[0]

    def __len__(self) -> int:
        return self._m

    @property
    def rows(self) -> Array:
        """The edges ``(M, 7, N)``, a view (do not write)."""
        return self._buf[: self._m]

    @property
    def buffer(self) -> Array:
        """The whole buffer ``(capacity, 7, N)`` (for the kernel)."""
        return self._buf

    @property
    def point_flags(self) -> npt.NDArray[np.uint8]:
        """Point flags ``(capacity,)`` as bytes (for the kernel)."""
        return self._point

    def is_point(self, i: int) -> bool:
        return bool(self._point[i])

    def point_list(self) -> list[bool]:
        return [bool(p) for p in self._point[: self._m]]

    def edge_rows(self, i: int) -> Array:
        """Edge root→frame ``i`` as rows ``(7, N)``, a view (do not write)."""
        out: Array = self._buf[i]
        return out

    def edge(self, i: int) -> Array:
        """Edge root→frame ``i`` as ``(N, 7)`` (a copy)."""
        return from_rows(self._buf[i])

    def edges(self) -> Array:
        """All edges as ``(M, N, 7)`` (a copy in the API's layout)."""
        return from_rows(self._buf[: self._m])

    def pass_means(self) -> tuple[Array, npt.NDArray[np.int64], Array] | None:
        """The frames' means ``(M, 7)``, live chart coordinates and largest translation
        magnitudes ``(M,)`` that the joint update's pass took of this buffer
        (:func:`mcsm.core.relin.joint_frames_means`), while no change has been made since;
        else None."""
        return self._means

    # ------------------------------------------------------------------ changing
    def keep_means(self, means: Array, ls: npt.NDArray[np.int64], big: Array) -> None:
        """Keep what :meth:`pass_means` answers until the next change (every changing method
        forgets it)."""
        if means.shape != (self._m, 7) or big.shape != (self._m,):
            raise ValueError("one mean per frame")
        self._means = (means, ls, big)

    def written(self) -> None:
        """The buffer was written in place (a re-centring's shift): forget the kept means."""
        self._means = None

    def append(self, frame: str, point: bool, rows: Array) -> None:
        """Add one frame with edge ``rows`` ``(7, N)``; O(N) amortised."""
        self._means = None
        if self._m == self._buf.shape[0]:
            cap = max(4, 2 * self._buf.shape[0])
            buf = np.empty((cap, 7, self.n_samples))
            buf[: self._m] = self._buf[: self._m]
            flags = np.zeros(cap, dtype=np.uint8)
            flags[: self._m] = self._point[: self._m]
            self._buf, self._point = buf, flags
        self._buf[self._m] = rows
        self._point[self._m] = bool(point)
        self.frames.append(frame)
        self.index[frame] = self._m
        self._m += 1

    def extend(self, frames: list[str], is_point: list[bool], rows: Array) -> None:
        """Add several frames (a join); one copy of the new frames."""
        self._means = None
        k = len(frames)
        need = self._m + k
        if need > self._buf.shape[0]:
            cap = max(4, 2 * self._buf.shape[0], need)
            buf = np.empty((cap, 7, self.n_samples))
            buf[: self._m] = self._buf[: self._m]
            flags = np.zeros(cap, dtype=np.uint8)
            flags[: self._m] = self._point[: self._m]
            self._buf, self._point = buf, flags
        self._buf[self._m: need] = rows
        self._point[self._m: need] = np.asarray(is_point, dtype=bool)
        for f in frames:
            self.index[f] = len(self.frames)
            self.frames.append(f)
        self._m = need

    def delete(self, i: int) -> None:
        """Drop frame ``i`` (not the root); other frames' bits are unchanged."""
        if i == 0:
            raise ValueError("re-root before deleting the root")
        self._means = None
        self._buf[i: self._m - 1] = self._buf[i + 1: self._m]
        self._point[i: self._m - 1] = self._point[i + 1: self._m]
        self._point[self._m - 1] = 0
        del self.frames[i]
        self._m -= 1
        self.index = {f: j for j, f in enumerate(self.frames)}

    def swap_buffer(self, buf: Array) -> Array:
        """Install ``buf`` (same capacity and shape, frames [0, M) filled) and return the old
        buffer (the joint update writes into a spare one and swaps after its checks)."""
        if buf.shape != self._buf.shape:
            raise ValueError("buffer shapes differ")
        old, self._buf, self._means = self._buf, buf, None
        return old

    def copy(self) -> Component:
        return Component(list(self.frames), self.point_list(), self.rows.copy())

    @property
    def nbytes(self) -> int:
        """Bytes of the edge buffer and point flags (host memory)."""
        return int(self._buf.nbytes) + int(self._point.nbytes)

    def block_from_rows(self, rows: Array) -> Array:
        """Edges ``(k, 7, N)`` as a block for :meth:`extend` (here: the same array)."""
        return rows

    # ------------------------------------------------------------------ O(M N) passes
    def transformed(self, pre: Array, what: str) -> Array:
        """``canonical(pre ⊕ edge_f)`` for every frame (points pinned), a new ``(M, 7, N)``
        array. Raises NumericalError (nothing changed) on a non-finite result."""
        moved = np.empty((self._m, 7, self.n_samples))
        if kernel.transform_frames(pre, self.rows, moved, self._point, 0, self._m) != kernel.OK:
            raise NumericalError(f"{what} produced non-finite samples")
        return moved

    def rerooted(self, k: int) -> Component:
        """The component re-rooted at index k: each edge becomes (r→k)^R ⊕ (r→l)
        (PAPER Fig. 3a), canonicalised; frame k first, then the others in order."""
        moved = self.transformed(kernel.invert(self.edge_rows(k)), "re-rooting")
        order = [k] + [i for i in range(self._m) if i != k]
        rows = moved[order]
        rows[0] = identity_rows(self.n_samples)
        flags = self.point_list()
        return Component([self.frames[i] for i in order], [flags[i] for i in order], rows)
