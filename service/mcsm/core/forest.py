"""The forest of star graphs (PAPER §3): components, frames, joins, re-rooting, removal,
submaps, queries and the state digest.

Each component has a root frame and one edge root→frame for every frame, the root's own edge
being the exact identity at index 0 (:class:`mcsm.core.storage.Component` keeps them). Row i
of every edge of a component is one joint draw: nothing here reorders samples. Every
computation that changes an edge runs in the compiled kernel (:mod:`mcsm.core.kernel`);
numpy only allocates, copies and checks. Every operation computes into new arrays and swaps
them in after its checks: a failing call raises an :class:`mcsm.errors.McsmError` and leaves
the forest bit-identical.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import kernel
from mcsm.core.at import QUAT_NORM_TOL, mean_and_cov
from mcsm.core.device import Backend, DeviceComponent
from mcsm.core.names import FRAME_RULE, is_frame_name
from mcsm.core.storage import Component, from_rows, identity_rows, to_rows
from mcsm.errors import (
    FrameExists,
    InvalidOperation,
    InvalidSamples,
    NotRelated,
    NumericalError,
    SampleCountMismatch,
    UnknownFrame,
)

Array = npt.NDArray[np.float64]
Store = Component | DeviceComponent
"""A component's storage: host memory, or device memory for a map on a GPU."""


def check_frame_name(name: object) -> str:
    """Return ``name`` if it is a valid frame name (:data:`mcsm.core.names.FRAME_RULE`)."""
    if not is_frame_name(name):
        raise InvalidOperation(f"invalid frame name {name!r}: {FRAME_RULE}")
    assert isinstance(name, str)
    return name


def unit_quaternion_norms(q: Array) -> Array:
    """``|q|²`` of ``(..., 4)`` quaternions, elementwise in a fixed order (no reduction)."""
    return q[..., 0] * q[..., 0] + q[..., 1] * q[..., 1] + q[..., 2] * q[..., 2] \
        + q[..., 3] * q[..., 3]


@dataclass(frozen=True)
class Verdict:
    """What the map did with one constraint (the gate of a loop closure).

    ``status``: ``accepted`` or ``rejected`` (more statuses exist at the server: pending,
    retracted, reinstated). ``nis``: the normalised innovation squared of the observation's mean
    against the map's prediction, over ``dof`` live dimensions of ``P + R``; ``threshold``:
    the gate's chi-square quantile for ``dof`` (None: not gated). ``reason`` says why there was
    nothing to test (a new frame or a join has no prediction to test against) or that the
    request was trusted.
    """

    status: str = "accepted"
    nis: float | None = None
    dof: int = 0
    threshold: float | None = None
    reason: str = ""


@dataclass(frozen=True)
class UpdateResult:
    """What an update did: ``kind`` is new_component, new_frame, join, loop_closure, import or
    rejected (the gate refused a loop closure; the map is unchanged, unless ``relin`` says
    that it was relinearised before the gate judged the closure again). ``relin``: the
    relinearisation this update triggered (:class:`mcsm.core.relinearize.RelinReport`), if
    any."""

    kind: str
    component: str
    frames_added: tuple[str, ...] = ()
    verdict: Verdict = field(default_factory=Verdict)
    relin: Any = None


@dataclass(frozen=True)
class RemoveResult:
    """What a remove did: the root of what is left of the component (None if nothing)."""

    component: str | None
    frames_removed: tuple[str, ...] = ()


@dataclass(frozen=True)
class Submap:
    """A whole component: frames (root first), point flags, edges ``(M, N, 7)`` in sample order."""

    root: str
    frames: tuple[str, ...]
    is_point: tuple[bool, ...]
    edges: Array = field(repr=False)


class Forest:
    """Components of one map with N samples each; the structure under :class:`StochasticMap`."""

    def __init__(self, n_samples: int, backend: Backend | None = None) -> None:
        self.n_samples = n_samples
        self.backend = backend  # None: components in host memory
        self._comps: dict[int, Store] = {}
        self._where: dict[str, int] = {}  # frame -> component id
        self._order: dict[str, None] = {}  # frames in insertion order
        self._next_id = 0

    # ------------------------------------------------------------------ introspection
    def __contains__(self, frame: object) -> bool:
        return frame in self._where

    @property
    def n_frames(self) -> int:
        return len(self._where)

    def frames(self) -> list[str]:
        """All frames, in the order they were added."""
        return list(self._order)

    def components(self) -> list[str]:
        """The root frame of every component, oldest component first."""
        return [c.root for _, c in sorted(self._comps.items())]

    def component(self, frame: str) -> list[str]:
        """The frames of ``frame``'s component, root first."""
        return list(self._comp_of(frame).frames)

    def root(self, frame: str) -> str:
        return self._comp_of(frame).root

    def is_point(self, frame: str) -> bool:
        c = self._comp_of(frame)
        return c.is_point(c.index[frame])

    def edges(self, frame: str) -> Array:
        """A copy of the ``(M, N, 7)`` edge array of ``frame``'s component (root first)."""
        return self._comp_of(frame).edges()

    def _digest_header(self, h: Any) -> None:
        """Options and option-dependent state hashed before the components (the facade's)."""

    def state_digest(self) -> str:
        """SHA-256 (hex) of the whole logical state: options, components, names, flags and the
        sample bytes of every edge in ``(M, N, 7)`` order (never the storage layout)."""
        h = hashlib.sha256()
        self._digest_header(h)
        h.update(json.dumps(list(self._order)).encode())
        for cid, c in sorted(self._comps.items()):
            h.update(json.dumps([cid, c.frames]).encode())
            h.update(np.array(c.point_list(), dtype=bool).tobytes())
            h.update(np.ascontiguousarray(c.edges(), dtype="<f8").tobytes())
        return h.hexdigest()

    # ------------------------------------------------------------------ queries
    def query(self, a: str, b: str) -> Array:
        """Samples of the AT a→b: ``(root→a)^R ⊕ (root→b)``, O(N) (PAPER §3)."""
        c, ia, ib = self._pair(a, b)
        if ia == 0:
            return c.edge(ib)
        if ib == 0:
            return from_rows(kernel.invert(c.edge_rows(ia)))
        return kernel.relative_nm7(c.edge_rows(ia), c.edge_rows(ib))

    def marginal(self, a: str, b: str) -> tuple[Array, Array]:
        """Mean 7-vector and 6×6 tangent covariance of a→b (see :func:`mean_and_cov`)."""
        return mean_and_cov(self.query(a, b))

    # ------------------------------------------------------------------ removal
    def remove(self, frame: str) -> RemoveResult:
        """Drop ``frame``'s edge; other frames' samples stay bit-identical (PAPER §3).

        Removing a root first re-roots the component at its first full frame (O(M·N)).
        """
        cid = self._cid(frame)
        c = self._comps[cid]
        i = c.index[frame]
        if len(c) == 1:
            self._forget_component(cid)
            return RemoveResult(None, (frame,))
        if i == 0:
            full = [k for k in range(1, len(c)) if not c.is_point(k)]
            c = self._rerooted(c, full[0] if full else 1)
            i = c.index[frame]
        c.delete(i)
        self._comps[cid] = c
        del self._where[frame]
        del self._order[frame]
        return RemoveResult(c.root, (frame,))

    # ------------------------------------------------------------------ submaps
    def export_component(self, frame: str) -> Submap:
        """A copy of ``frame``'s whole component (sample order intact)."""
        c = self._comp_of(frame)
        return Submap(c.root, tuple(c.frames), tuple(c.point_list()), c.edges())

    def import_component(self, submap: Submap) -> UpdateResult:
        """Add an exported component as a new component of this map (names must be new)."""
        frames = [check_frame_name(f) for f in submap.frames]
        if len(set(frames)) != len(frames):
            raise InvalidOperation("a submap names a frame twice")
        for f in frames:
            if f in self._where:
                raise FrameExists(f)
        e = submap.edges
        if not isinstance(e, np.ndarray) or e.dtype.kind != "f" or e.ndim != 3 or \
                e.shape[0] != len(frames) or e.shape[2] != 7:
            raise InvalidSamples(f"submap edges must be ({len(frames)}, N, 7) floats")
        if e.shape[1] != self.n_samples:
            raise SampleCountMismatch(self.n_samples, int(e.shape[1]))
        if len(submap.is_point) != len(frames):
            raise InvalidOperation("submap point flags do not match its frames")
        edges = np.array(e, dtype=np.float64, order="C", copy=True)
        if not np.isfinite(edges).all():
            raise InvalidSamples("non-finite values in submap edges")
        norm2 = unit_quaternion_norms(edges[..., 3:])
        off = float(np.max(np.abs(norm2 - 1.0)))
        if off > QUAT_NORM_TOL:
            raise InvalidSamples("non-unit quaternions in submap edges")
        ident = from_rows(identity_rows(self.n_samples))
        if float(np.max(np.abs(edges[0] - ident))) > 1e-12:
            raise InvalidSamples("the root edge of a submap must be the identity")
        # An exported submap is already unit and canonical: keep its bits (digests compare).
        renormalize = off > 1e-12
        if renormalize:
            edges[..., 3:] /= np.sqrt(norm2)[..., None]
        rows = to_rows(edges)
        rows[0] = identity_rows(self.n_samples)
        is_point = [bool(p) for p in submap.is_point]
        flags = np.array(is_point, dtype=np.uint8)
        if kernel.canonicalize_frames(rows, flags, 1, len(frames), renormalize) != kernel.OK:
            raise NumericalError("the submap import produced non-finite samples")
        self._install(self._store(frames, is_point, rows), new_frames=frames)
        return UpdateResult("import", frames[0], tuple(frames))

    # ------------------------------------------------------------------ snapshots
    def snapshot(self) -> dict[str, Any]:
        """The whole structure as plain values and ``(M, N, 7)`` arrays (see
        :meth:`restore_snapshot`); ``state_digest`` of a restored forest is the same."""
        return {"next_id": self._next_id, "order": list(self._order),
                "components": [{"id": cid, "frames": list(c.frames), "is_point": c.point_list(),
                                "edges": c.edges()} for cid, c in sorted(self._comps.items())]}

    def restore_snapshot(self, snap: dict[str, Any]) -> None:
        """Replace the structure by a :meth:`snapshot`'s (trusted input: our own file)."""
        comps: dict[int, Store] = {}
        where: dict[str, int] = {}
        for c in snap["components"]:
            edges = np.asarray(c["edges"], dtype=np.float64)
            if edges.ndim != 3 or edges.shape[1] != self.n_samples or edges.shape[2] != 7:
                raise InvalidSamples("snapshot edges do not match the map's N")
            comp = self._store(list(c["frames"]), list(c["is_point"]), to_rows(edges))
            comps[int(c["id"])] = comp
            for f in comp.frames:
                where[f] = int(c["id"])
        self._comps, self._where = comps, where
        self._order = {str(f): None for f in snap["order"]}
        self._next_id = int(snap["next_id"])

    # ------------------------------------------------------------------ internals
    def _cid(self, frame: str) -> int:
        try:
            return self._where[frame]
        except (KeyError, TypeError):
            raise UnknownFrame(str(frame)) from None

    def _store(self, frames: list[str], is_point: list[bool], rows: Array) -> Store:
        """A component in this map's memory (host, or the backend's device) from host rows
        ``(M, 7, N)``."""
        if self.backend is None:
            return Component(frames, is_point, rows)
        return DeviceComponent.from_rows(self.backend, frames, is_point, rows)

    def storage_bytes(self) -> int:
        """Bytes of every component's edges and flags (device memory for a map on a GPU)."""
        return sum(c.nbytes for c in self._comps.values())

    def _comp_of(self, frame: str) -> Store:
        return self._comps[self._cid(frame)]

    def _pair(self, a: str, b: str) -> tuple[Store, int, int]:
        ca, cb = self._cid(a), self._cid(b)
        if ca != cb:
            raise NotRelated(a, b)
        c = self._comps[ca]
        return c, c.index[a], c.index[b]

    def _install(self, comp: Store, new_frames: list[str], cid: int | None = None) -> int:
        if cid is None:
            cid = self._next_id
            self._next_id += 1
        self._comps[cid] = comp
        for f in comp.frames:
            self._where[f] = cid
        for f in new_frames:
            self._order[f] = None
        return cid

    def _forget_component(self, cid: int) -> None:
        for f in self._comps.pop(cid).frames:
            del self._where[f]
            del self._order[f]

    def _leaf_rows(self, e_known: Array, x_rows: Array, point: bool, inverse: bool) -> Array:
        """Edge root→new = root→known ⊕ X (or ⊕ X^R); a point: root→known ⊕ p."""
        if point:
            return kernel.point_edge(e_known, x_rows)
        x = kernel.invert(x_rows) if inverse else x_rows
        leaf = kernel.compound(e_known, x)
        kernel.canonicalize(leaf)
        return leaf

    def _new_component(self, a: str, b: str, x_rows: Array, point: bool) -> UpdateResult:
        n = self.n_samples
        rows = np.empty((2, 7, n))
        rows[0] = identity_rows(n)
        rows[1] = self._leaf_rows(identity_rows(n), x_rows, point, inverse=False)
        _check_finite(rows[1], "adding a frame")
        self._install(self._store([a, b], [False, point], rows), new_frames=[a, b])
        return UpdateResult("new_component", a, (a, b),
                            Verdict(reason="new component: nothing to test against"))

    def _add_leaf(self, known: str, new: str, x_rows: Array, point: bool, inverse: bool
                  ) -> UpdateResult:
        c = self._comp_of(known)
        leaf = self._leaf_rows(c.edge_rows(c.index[known]), x_rows, point, inverse)
        _check_finite(leaf, "adding a frame")
        c.append(new, point, leaf)
        self._where[new] = self._where[known]
        self._order[new] = None
        return UpdateResult("new_frame", c.root, (new,),
                            Verdict(reason="new frame: nothing to test against"))

    def _join(self, a: str, b: str, x_rows: Array, point: bool) -> UpdateResult:
        """Case I (PAPER §3, Fig. 2): r1→l = (r1→a) ⊕ X ⊕ (r2→b)^R ⊕ (r2→l) for l in b's tree."""
        c1, c2 = self._comp_of(a), self._comp_of(b)
        if point:
            if len(c2) > 1:
                raise InvalidOperation(
                    f"joining two multi-frame components through one point observation is "
                    f"under-determined (the orientation between them is unknown): observe a "
                    f"full frame of {b!r}'s component with an (N, 7) AT instead")
            rows = kernel.point_edge(c1.edge_rows(c1.index[a]), x_rows)[None]
            _check_finite(rows, "the join")
            moved = c1.block_from_rows(rows)
        else:
            x_r1_b = kernel.compound(c1.edge_rows(c1.index[a]), x_rows)
            x_r1_r2 = kernel.compound(x_r1_b, kernel.invert(c2.edge_rows(c2.index[b])))
            moved = c2.transformed(x_r1_r2, "the join")
        cid1, cid2 = self._where[a], self._where[b]
        c1.extend(list(c2.frames), c2.point_list(), moved)
        del self._comps[cid2]
        self._install(c1, new_frames=[], cid=cid1)
        return UpdateResult("join", c1.root, (),
                            Verdict(reason="join (case I): nothing to test against"))

    def _rerooted(self, c: Store, k: int) -> Store:
        """The component re-rooted at index k (:meth:`Component.rerooted`)."""
        return c.rerooted(k)


def _check_finite(rows: Array, what: str) -> None:
    if not np.isfinite(rows).all():
        raise NumericalError(f"{what} produced non-finite samples")
