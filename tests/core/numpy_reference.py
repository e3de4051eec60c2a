"""The numpy reference of the core: the map as it was before the compiled kernel (commit
16091e8), kept as a test oracle (``tests/core/test_kernel_reference.py``: the kernel agrees
with it to 1e-9 of every update's move) and as the "old" column of
``benchmarks/bench_core.py``. Never used by the product: its bits depend on the CPU and the
BLAS build (einsum, BLAS products, LAPACK ``eigh``).

The Monte Carlo stochastic map: a forest of star graphs of ATs (PAPER §3).

Each component has a root frame and one edge root→frame for every frame, the root's own edge
being the exact identity at index 0. A component's edges live in one contiguous ``(M, N, 7)``
array. Row i of every edge is one joint draw: nothing here reorders samples.

Case II (loop closure) has two update methods:

* ``method="paper"``: PAPER §3 Fig. 3 literally: re-root at ``a``, merge the main edge with the
  revised merge, propagate to every leaf with ``E_j ⊗ (G' ⊕ G^R ⊕ E_j)``.
* ``method="joint"``: one ensemble-Kalman analysis of the whole component. The observation is
  predicted per sample, ``h = (r→a)^R ⊕ (r→b)`` (statistical linearisation; no re-rooting),
  and every edge moves by ``Δ_i = C_xy w_i`` where ``C_xy`` is the sample cross-covariance of
  the edge with ``h`` and ``w_i`` a per-sample weight vector from the analysis rule
  (:mod:`mcsm.core.analysis`). Two products over the sample axis, O(M·N).

  ``C_xy`` comes from one of two estimators (``gain``): ``"direct"`` takes every edge's sample
  cross-covariance with ``h`` and damps each entry by its significance (correlation shrink);
  ``"endpoints"`` regresses every edge on the principal components of the two endpoint edges
  ``r→a``, ``r→b`` and chains that regression with the components' cross-covariance with
  ``h`` (:func:`endpoint_cross_covariance`), so that an edge's gain is judged against the part
  of its spread the endpoints do not explain. Measured on pose graphs (issue 8): most of the
  information of a loop closure reaches edges whose correlation with ``h`` is below the
  direct shrink's noise floor but whose correlation with the endpoints is high.

Every operation computes into new arrays and swaps them in at the end, after checks: a failing
call raises an :class:`mcsm.errors.McsmError` and leaves the map bit-identical.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

import numpy as np
import numpy.typing as npt
from mcsm.core import analysis as an
from mcsm.core.at import (
    QUAT_NORM_TOL,
    RTOL,
    ZERO_VARIANCE,
    Space,
    canonicalize,
    check_samples,
    compound,
    identity,
    invert,
    mean_and_cov,
    merge_correlated,
    merge_correlated_shifted,
    relative,
    sample_cov,
    scaled_eigh,
    to_space,
)
from mcsm.core.names import FRAME_RULE, is_frame_name
from mcsm.core.quat import L_INDEX, L_SIGN, qconj, qmul, qrot
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
Method = Literal["joint", "paper"]

METHODS = ("joint", "paper")
# adaptive inflation (issue 8): running-average rate, strength, largest factor
ADAPT_RATE, ADAPT_STRENGTH, ADAPT_MAX = 0.05, 0.008, 1.01
SPACES = ("tangent", "quaternion")
GAINS = ("direct", "endpoints")
# The joint update walks the edges in blocks of about this many bytes (a few frames), so that
# its chain of kernels on one block stays in the core's cache; see _blocks.
BLOCK_BYTES = 2 << 20
_T = TypeVar("_T")
_POOLS: dict[int, ThreadPoolExecutor] = {}


def _blocks(m: int, n: int) -> list[slice]:
    """Frame blocks of about BLOCK_BYTES for a component of m frames with n samples each.

    Depends on the shape only (never on the thread count), so every frame sees the same
    kernels whatever the machine.
    """
    step = max(1, BLOCK_BYTES // (n * 7 * 8))
    return [slice(i, min(i + step, m)) for i in range(0, m, step)]


def _pool(threads: int) -> ThreadPoolExecutor:
    """A process-wide pool of ``threads`` workers, made on first use."""
    if threads not in _POOLS:
        _POOLS[threads] = ThreadPoolExecutor(threads, thread_name_prefix="mcsm-core")
    return _POOLS[threads]


def default_threads() -> int:
    """Threads for the joint update's block passes: the cores this process may use, at
    most 4 (measured here on 2 cores only)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cores = os.cpu_count() or 1
    return max(1, min(4, cores))


def check_frame_name(name: object) -> str:
    """Return ``name`` if it is a valid frame name (:data:`mcsm.core.names.FRAME_RULE`)."""
    if not is_frame_name(name):
        raise InvalidOperation(f"invalid frame name {name!r}: {FRAME_RULE}")
    assert isinstance(name, str)
    return name


@dataclass(frozen=True)
class UpdateResult:
    """What an update did: ``kind`` is new_component, new_frame, join, loop_closure or import."""

    kind: str
    component: str
    frames_added: tuple[str, ...] = ()


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


@dataclass
class _Component:
    frames: list[str]
    is_point: npt.NDArray[np.bool_]
    edges: Array  # (M, N, 7), edges[0] is the exact identity
    index: dict[str, int] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.index = {f: i for i, f in enumerate(self.frames)}

    @property
    def root(self) -> str:
        return self.frames[0]


class StochasticMap:
    """A forest of star graphs of ATs with N samples each (PAPER §3).

    Parameters
    ----------
    n_samples : N, constant for the whole map
    method : ``"joint"`` (default) or ``"paper"``, the case II update (module docstring)
    space : ``"tangent"`` (default, the ⊞ chart of PAPER §5) or ``"quaternion"`` (the paper's
        7-D Euclidean treatment), the vector space of every linear step
    analysis : rule of the joint update: ``"ensrf"`` (default; deterministic square root),
        ``"denkf"`` or ``"enkf"`` (perturbed observations, the plain joint update);
        see :mod:`mcsm.core.analysis`
    shrink : correlation-shrink constant c (Anderson 2012) for the cross-covariances of the
        joint update (default 4; None turns it off): damps the spurious sample correlations
        that otherwise collapse the ensemble over thousands of updates at fixed N
    inflation : multiplicative inflation of every edge's anomalies after each loop closure
        (a number in [1, 2)), or ``"adaptive"``: a factor driven by a running average of the
        normalised innovation squared per dof (NIS) of the loop closures,
        ``λ = clip(1 + 0.008 (avg − 1), 1, 1.01)``, ``avg ← 0.95 avg + 0.05 NIS``; an honest
        map has NIS ≈ 1 and so gets no inflation (measured on 3-D pose graphs, issue 8)
    gain : how the joint update estimates every edge's cross-covariance with the predicted
        observation: ``"direct"`` (default; the sample cross-covariance, shrunk entry by entry)
        or ``"endpoints"`` (every edge regressed on the principal components of the two
        endpoint edges, then those on the observation; tangent space only; see
        :func:`endpoint_cross_covariance`). Better on pose graphs, with ``inflation=1.002``
        in 3-D (``experiments/results/pose_graph_summary.md``); the default stays the
        estimator measured on point landmarks
    threads : threads for the joint update's passes over the edges (default
        :func:`default_threads`). Not part of :meth:`options` or the state: every thread
        count gives bit-identical results.
    """

    def __init__(
        self,
        n_samples: int,
        *,
        method: str = "joint",
        space: str = "tangent",
        analysis: str = "ensrf",
        shrink: float | None = 4.0,
        inflation: float | str = 1.0,
        gain: str = "direct",
        threads: int | None = None,
    ) -> None:
        if not isinstance(n_samples, int) or isinstance(n_samples, bool) or n_samples < 2:
            raise InvalidOperation(f"n_samples must be an integer >= 2, got {n_samples!r}")
        if method not in METHODS:
            raise InvalidOperation(f"method must be one of {METHODS}, got {method!r}")
        if space not in SPACES:
            raise InvalidOperation(f"space must be one of {SPACES}, got {space!r}")
        if analysis not in an.RULES:
            raise InvalidOperation(f"analysis must be one of {tuple(an.RULES)}, got {analysis!r}")
        if shrink is not None and not (np.isfinite(shrink) and shrink >= 0):
            raise InvalidOperation(f"shrink must be None or >= 0, got {shrink!r}")
        if inflation != "adaptive" and not (
                isinstance(inflation, (int, float)) and np.isfinite(inflation)
                and 1.0 <= inflation < 2.0):
            raise InvalidOperation(f"inflation must be in [1, 2) or 'adaptive', got {inflation!r}")
        if gain not in GAINS:
            raise InvalidOperation(f"gain must be one of {GAINS}, got {gain!r}")
        if gain == "endpoints" and space != "tangent":
            raise InvalidOperation("gain='endpoints' works in the tangent space only")
        if threads is not None and (not isinstance(threads, int) or isinstance(threads, bool)
                                    or not 1 <= threads <= 64):
            raise InvalidOperation(f"threads must be None or an integer in [1, 64], "
                                   f"got {threads!r}")
        self.n_samples = n_samples
        self.method: Method = method  # type: ignore[assignment]
        self.space: Space = space  # type: ignore[assignment]
        self.analysis = analysis
        self.shrink = None if shrink is None else float(shrink)
        self.inflation: float | str = inflation if inflation == "adaptive" else float(inflation)
        self.gain = gain
        self._nis_avg = 1.0  # running NIS average of adaptive inflation (part of the state)
        self._comps: dict[int, _Component] = {}
        self._where: dict[str, int] = {}  # frame -> component id
        self._order: dict[str, None] = {}  # frames in insertion order
        self._next_id = 0
        self.threads = default_threads() if threads is None else threads
        self._spare: Array | None = None  # the edge array the last joint update replaced
        self.rescued = 0  # samples the joint update's rescue moved on the manifold (_rescue)

    # ------------------------------------------------------------------ introspection

    def options(self) -> dict[str, Any]:
        """The constructor arguments, as a plain dict (round-trips through from_options)."""
        return {"n_samples": self.n_samples, "method": self.method, "space": self.space,
                "analysis": self.analysis, "shrink": self.shrink, "inflation": self.inflation,
                "gain": self.gain}

    @classmethod
    def from_options(cls, options: dict[str, Any]) -> StochasticMap:
        """Build an empty map from :meth:`options` output."""
        o = dict(options)
        n = o.pop("n_samples")
        return cls(int(n), **o)

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
        return bool(c.is_point[c.index[frame]])

    def edges(self, frame: str) -> Array:
        """A copy of the ``(M, N, 7)`` edge array of ``frame``'s component (root first)."""
        return self._comp_of(frame).edges.copy()

    def state_digest(self) -> str:
        """SHA-256 (hex) of the whole state: options, components, names, flags, sample bytes."""
        h = hashlib.sha256()
        options = self.options()
        if options["gain"] == "direct":
            # the arithmetic of every map made before ``gain`` existed: same digest as then,
            # so older recordings still verify
            del options["gain"]
        h.update(json.dumps(options, sort_keys=True).encode())
        if self.inflation == "adaptive":
            h.update(np.float64(self._nis_avg).tobytes())
        h.update(json.dumps(list(self._order)).encode())
        for cid, c in sorted(self._comps.items()):
            h.update(json.dumps([cid, c.frames]).encode())
            h.update(c.is_point.tobytes())
            h.update(np.ascontiguousarray(c.edges, dtype="<f8").tobytes())
        return h.hexdigest()

    # ------------------------------------------------------------------ queries

    def query(self, a: str, b: str) -> Array:
        """Samples of the AT a→b: ``(root→a)^R ⊕ (root→b)``, O(N) (PAPER §3)."""
        c, ia, ib = self._pair(a, b)
        if ia == 0:
            return c.edges[ib].copy()
        if ib == 0:
            return invert(c.edges[ia])
        return relative(c.edges[ia], c.edges[ib])

    def marginal(self, a: str, b: str) -> tuple[Array, Array]:
        """Mean 7-vector and 6×6 tangent covariance of a→b (see :func:`mean_and_cov`)."""
        return mean_and_cov(self.query(a, b))

    # ------------------------------------------------------------------ updates

    def update(self, a: str, b: str, samples: Array) -> UpdateResult:
        """Apply the observation ``samples`` of b seen from a.

        ``samples`` ``(N, 7)``: an AT a→b. ``(N, 3)``: the position of point frame b in a.
        New frames are added, two components are joined (case I) or a loop is closed
        (case II). Raises an McsmError and changes nothing on failure.
        """
        check_frame_name(a)
        check_frame_name(b)
        if a == b:
            raise InvalidOperation(f"an update needs two different frames, got {a!r} twice")
        if not isinstance(samples, np.ndarray):
            raise InvalidSamples(f"expected a numpy array, got {type(samples).__name__}")
        width = samples.shape[-1] if samples.ndim == 2 else -1
        if width not in (3, 7):
            raise InvalidSamples(f"expected shape (N, 7) or (N, 3), got {samples.shape}")
        x = check_samples(samples, self.n_samples, width)
        point = width == 3
        has_a, has_b = a in self._where, b in self._where
        if has_a and self.is_point(a):
            raise InvalidOperation(f"{a!r} is a point frame: it has no orientation to observe from")
        if has_b and not point and self.is_point(b):
            raise InvalidOperation(f"{b!r} is a point frame: observe it with (N, 3) samples")
        if has_b and point and not self.is_point(b):
            raise InvalidOperation(f"{b!r} is a full frame: observe it with (N, 7) samples")

        if not has_a and not has_b:
            return self._new_component(a, b, x, point)
        if has_a and not has_b:
            return self._add_leaf(a, b, x, point)
        if not has_a:
            if point:
                raise InvalidOperation(
                    f"a point observation cannot place the unknown observer {a!r}")
            return self._add_leaf(b, a, None, point, x_inverse=x)
        if self._where[a] != self._where[b]:
            return self._join(a, b, x, point)
        if self.method == "paper":
            return self._paper_update(a, b, x, point)
        return self._joint_update(a, b, x, point)

    def remove(self, frame: str) -> RemoveResult:
        """Drop ``frame``'s edge; other frames' samples stay bit-identical (PAPER §3).

        Removing a root first re-roots the component at its first full frame (O(M·N)).
        """
        cid = self._cid(frame)
        c = self._comps[cid]
        i = c.index[frame]
        if len(c.frames) == 1:
            self._forget_component(cid)
            return RemoveResult(None, (frame,))
        if i == 0:
            full = [k for k in range(1, len(c.frames)) if not c.is_point[k]]
            c = self._rerooted(c, full[0] if full else 1)
            i = c.index[frame]
        keep = np.ones(len(c.frames), dtype=bool)
        keep[i] = False
        new = _Component([f for f, k in zip(c.frames, keep, strict=True) if k],
                         c.is_point[keep], c.edges[keep])
        self._comps[cid] = new
        del self._where[frame]
        del self._order[frame]
        return RemoveResult(new.root, (frame,))

    # ------------------------------------------------------------------ submaps

    def export_component(self, frame: str) -> Submap:
        """A copy of ``frame``'s whole component (sample order intact)."""
        c = self._comp_of(frame)
        return Submap(c.root, tuple(c.frames), tuple(bool(p) for p in c.is_point), c.edges.copy())

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
        norm2 = np.einsum("mnk,mnk->mn", edges[..., 3:], edges[..., 3:])
        if np.max(np.abs(norm2 - 1.0)) > QUAT_NORM_TOL:
            raise InvalidSamples("non-unit quaternions in submap edges")
        if np.max(np.abs(edges[0] - identity(self.n_samples))) > 1e-12:
            raise InvalidSamples("the root edge of a submap must be the identity")
        # An exported submap is already unit and canonical: keep its bits (digests compare).
        renormalize = bool(np.max(np.abs(norm2 - 1.0)) > 1e-12)
        if renormalize:
            edges[..., 3:] /= np.sqrt(norm2)[..., None]
        edges[0] = identity(self.n_samples)
        comp = _Component(frames, np.array(submap.is_point, dtype=bool),
                          canonicalize(edges, normalize=renormalize))
        self._pin_points(comp.edges, comp.is_point)
        self._install(comp, new_frames=frames)
        return UpdateResult("import", frames[0], tuple(frames))

    # ------------------------------------------------------------------ internals: structure

    def _cid(self, frame: str) -> int:
        try:
            return self._where[frame]
        except (KeyError, TypeError):
            raise UnknownFrame(str(frame)) from None

    def _comp_of(self, frame: str) -> _Component:
        return self._comps[self._cid(frame)]

    def _pair(self, a: str, b: str) -> tuple[_Component, int, int]:
        ca, cb = self._cid(a), self._cid(b)
        if ca != cb:
            raise NotRelated(a, b)
        c = self._comps[ca]
        return c, c.index[a], c.index[b]

    def _install(self, comp: _Component, new_frames: list[str], cid: int | None = None) -> int:
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

    @staticmethod
    def _pin_points(edges: Array, is_point: npt.NDArray[np.bool_]) -> None:
        """A point frame's orientation is defined as its root's: identity quaternions."""
        if is_point.any():
            edges[is_point, :, 3:] = (1.0, 0.0, 0.0, 0.0)

    @staticmethod
    def _check_finite(edges: Array, what: str) -> None:
        if not np.isfinite(edges).all():
            raise NumericalError(f"{what} produced non-finite samples")

    def _point_edge(self, x_r_a: Array, p: Array) -> Array:
        e = identity(self.n_samples)
        e[:, :3] = x_r_a[:, :3] + qrot(x_r_a[:, 3:], p)
        return e

    def _new_component(self, a: str, b: str, x: Array, point: bool) -> UpdateResult:
        n = self.n_samples
        leaf = self._point_edge(identity(n), x) if point else x
        edges = np.stack((identity(n), leaf))
        comp = _Component([a, b], np.array([False, point]), canonicalize(edges))
        self._pin_points(comp.edges, comp.is_point)
        self._install(comp, new_frames=[a, b])
        return UpdateResult("new_component", a, (a, b))

    def _add_leaf(self, known: str, new: str, x: Array | None, point: bool,
                  x_inverse: Array | None = None) -> UpdateResult:
        """Add ``new`` to ``known``'s component: root→new = root→known ⊕ X (or ⊕ X^R)."""
        cid = self._cid(known)
        c = self._comps[cid]
        e_known = c.edges[c.index[known]]
        if point:
            assert x is not None
            leaf = self._point_edge(e_known, x)
        elif x is not None:
            leaf = compound(e_known, x)
        else:
            assert x_inverse is not None
            leaf = compound(e_known, invert(x_inverse))
        leaf = canonicalize(leaf)
        self._check_finite(leaf, "adding a frame")
        comp = _Component(c.frames + [new], np.append(c.is_point, point),
                          np.concatenate((c.edges, leaf[None])))
        self._install(comp, new_frames=[new], cid=cid)
        return UpdateResult("new_frame", c.root, (new,))

    def _join(self, a: str, b: str, x: Array, point: bool) -> UpdateResult:
        """Case I (PAPER §3, Fig. 2): r1→l = (r1→a) ⊕ X ⊕ (r2→b)^R ⊕ (r2→l) for l in b's tree."""
        c1, c2 = self._comp_of(a), self._comp_of(b)
        if point:
            if len(c2.frames) > 1:
                raise InvalidOperation(
                    f"joining two multi-frame components through one point observation is "
                    f"under-determined (the orientation between them is unknown): observe a "
                    f"full frame of {b!r}'s component with an (N, 7) AT instead")
            leaf = self._point_edge(c1.edges[c1.frames.index(a)], x)
            moved = leaf[None]
        else:
            ia, ib = c1.frames.index(a), c2.frames.index(b)
            x_r1_r2 = compound(compound(c1.edges[ia], x), invert(c2.edges[ib]))
            moved = compound(x_r1_r2[None], c2.edges)
        moved = canonicalize(moved)
        self._pin_points(moved, c2.is_point)
        self._check_finite(moved, "the join")
        cid1, cid2 = self._where[a], self._where[b]
        comp = _Component(c1.frames + c2.frames, np.concatenate((c1.is_point, c2.is_point)),
                          np.concatenate((c1.edges, moved)))
        del self._comps[cid2]
        self._install(comp, new_frames=[], cid=cid1)
        return UpdateResult("join", c1.root, ())

    def _rerooted(self, c: _Component, k: int, canonical: bool = True) -> _Component:
        """The component re-rooted at index k: each edge becomes (r→k)^R ⊕ (r→l) (PAPER Fig. 3a)."""
        x_k_r = invert(c.edges[k])
        edges = compound(x_k_r[None], c.edges)
        edges[k] = identity(self.n_samples)
        order = [k] + [i for i in range(len(c.frames)) if i != k]
        edges = canonicalize(edges[order]) if canonical else edges[order]
        is_point = c.is_point[order]
        self._pin_points(edges, is_point)
        edges[0] = identity(self.n_samples)
        self._check_finite(edges, "re-rooting")
        return _Component([c.frames[i] for i in order], is_point, edges)

    # ------------------------------------------------------------------ case II: paper

    def _paper_update(self, a: str, b: str, x: Array, point: bool) -> UpdateResult:
        """PAPER Fig. 3: re-root at a, G' = G ⊗ X, E_j' = E_j ⊗ (G' ⊕ G^R ⊕ E_j)."""
        cid = self._where[a]
        c = self._comps[cid]
        if self.space == "tangent":
            return self._paper_update_tangent(cid, c, a, b, x, point)
        if c.frames[0] != a:
            # no canonicalisation here: every re-rooted edge goes through a merge, whose
            # output lies on the hemisphere of its reference rotation
            c = self._rerooted(c, c.index[a], canonical=False)
        ib = c.index[b]
        g = c.edges[ib]
        g_new, shift = self._merge_main_edge(g, x, point)
        others = np.ones(len(c.frames), dtype=bool)
        others[[0, ib]] = False
        edges = c.edges.copy()
        if others.any():
            e_j = c.edges[others]
            edges[others] = merge_correlated(e_j, compound(shift[None], e_j), self.space)
        edges[ib] = g_new
        self._pin_points(edges, c.is_point)
        edges[0] = identity(self.n_samples)
        self._check_finite(edges, "the loop closure")
        self._install(_Component(c.frames, c.is_point, edges), new_frames=[], cid=cid)
        return UpdateResult("loop_closure", a, ())

    def _merge_main_edge(self, g: Array, x: Array, point: bool) -> tuple[Array, Array]:
        """The merged main edge G' = G ⊗ X of PAPER Fig. 3 and the shift G' ⊕ G^R."""
        if point:
            g_new = g.copy()
            g_new[:, :3] = _merge_points(g[:, :3], x)
        else:
            g_new = merge_correlated(g, x, self.space)
        return g_new, compound(g_new, invert(g))

    def _paper_update_tangent(self, cid: int, c: _Component, a: str, b: str, x: Array,
                              point: bool) -> UpdateResult:
        """:meth:`_paper_update` in the tangent chart, fused: the re-rooting, the shift and the
        merge of every other edge happen block by block in one pass over the component
        (:func:`mcsm.core.at.merge_correlated_shifted`); same mathematics, same results up to
        rounding."""
        n = self.n_samples
        k, ib_old = c.index[a], c.index[b]
        n_frames = len(c.frames)
        order = [k] + [i for i in range(n_frames) if i != k]
        is_point = c.is_point[order]
        x_k_r = invert(c.edges[k]) if k != 0 else None
        g = c.edges[ib_old] if x_k_r is None else compound(x_k_r, c.edges[ib_old])
        if x_k_r is not None and c.is_point[ib_old]:
            g[:, 3:] = (1.0, 0.0, 0.0, 0.0)
        self._check_finite(g, "re-rooting")
        g_new, shift = self._merge_main_edge(g, x, point)
        edges = np.empty_like(c.edges)
        # old edges 0..k-1 become 1..k, old k+1.. keep their index; old k becomes the root
        for lo, hi, dst in ((0, k, 1), (k + 1, n_frames, k + 1)):
            if hi > lo:
                merge_correlated_shifted(c.edges[lo:hi], shift, pre=x_k_r,
                                         pin=c.is_point[lo:hi] if x_k_r is not None else None,
                                         out=edges[dst:dst + hi - lo])
        ib = order.index(ib_old)
        edges[ib] = g_new
        self._pin_points(edges, is_point)
        edges[0] = identity(n)
        self._check_finite(edges, "the loop closure")
        self._install(_Component([c.frames[i] for i in order], is_point, edges), new_frames=[],
                      cid=cid)
        return UpdateResult("loop_closure", a, ())

    # ------------------------------------------------------------------ case II: joint

    def _joint_update(self, a: str, b: str, x: Array, point: bool) -> UpdateResult:
        """One ensemble-Kalman analysis of the whole component (module docstring).

        The two passes over the edges run over blocks of frames (:func:`_blocks`), on up to
        :attr:`threads` threads; every frame's arithmetic is the same whatever the blocks or
        the thread count, so the result is bit-identical.
        """
        cid = self._where[a]
        c = self._comps[cid]
        ia, ib = c.index[a], c.index[b]
        y, z = self._predict(c.edges[ia], c.edges[ib], x, point)
        n = self.n_samples
        y_mean = y.mean(axis=0)
        yc = y - y_mean
        try:
            w = an.RULES[self.analysis](yc, y_mean, z)
        except np.linalg.LinAlgError as e:
            raise NumericalError(f"the analysis failed: {e}") from None
        if not np.isfinite(w).all():
            raise NumericalError("the analysis produced non-finite weights")

        edges = c.edges
        blocks = _blocks(edges.shape[0], n)
        if self.gain == "endpoints":
            c_xy_t, mean = self._cross_endpoints(edges, ia, ib, point, yc, blocks)
        else:
            c_xy_t, mean = self._cross_direct(edges, yc, blocks)
        # Finite factors with a bounded product give finite increments: this replaces a full
        # isfinite pass over the (M, N, 7) result.
        bound = float(np.abs(c_xy_t).max(initial=0.0)) * float(np.abs(w).max()) * w.shape[1]
        if not (np.isfinite(c_xy_t).all() and bound < 1e100):
            raise NumericalError("the update's gain is not finite")
        inflation, nis_avg = self._loop_inflation(yc, y_mean, z)
        new_mean = mean + w.mean(axis=0) @ c_xy_t if inflation != 1.0 else None  # (M, 7)
        out = self._spare_buffer(edges.shape)
        w_b = w[None]

        def second(s: slice) -> bool:
            o = out[s]
            np.matmul(w_b, c_xy_t[s], out=o)  # the increments
            o += edges[s]
            if new_mean is not None:
                o -= new_mean[s, None, :]
                o *= inflation
                o += new_mean[s, None, :]
            q = o[..., 3:]
            norm = np.sqrt(np.einsum("mnk,mnk->mn", q, q))
            low = np.nonzero(norm <= 0.1)
            if len(low[0]):  # samples nearly opposite their frame's centre: the kernel's rescue
                self.rescued += _rescue(q, norm, low, w, c_xy_t[s], edges[s],
                                        (mean if new_mean is None else new_mean)[s])
            # the unit quaternions moved by bounded increments; min/max propagate NaN
            if not (norm.min() > 0.1 and norm.max() < 1e10):
                return False
            q /= norm[..., None]
            return True

        if not all(self._run_blocks(second, blocks)):
            raise NumericalError("the update pushed quaternions to zero or non-finite values")
        # The root edge and point orientations have zero anomalies, so the update leaves them
        # unchanged up to rounding; pin them exactly so they stay definitions, not estimates.
        out[0] = identity(n)
        self._pin_points(out, c.is_point)
        c.edges = out  # the only mutations, after every check
        self._spare = edges
        self._nis_avg = nis_avg
        return UpdateResult("loop_closure", c.root, ())

    def _cross_direct(self, edges: Array, yc: Array,
                      blocks: list[slice]) -> tuple[Array, Array]:
        """``gain="direct"``: every edge's sample cross-covariance with the predicted observation,
        ``(M, p, 7)``, shrunk entry by entry, and the edges' means ``(M, 7)`` (pass 1)."""
        n = self.n_samples
        # Pass 1 gives every edge's cross-covariance with the predicted observation and its
        # mean ([yc, 1] is (N, p+1); result (M, p+1, 7)), and the sums of squares for the
        # shrinkage.
        lhs_t = np.concatenate((yc / (n - 1), np.full((n, 1), 1.0 / n)), axis=1).T[None]
        moments = np.empty((edges.shape[0], lhs_t.shape[1], 7))
        sq = np.empty((edges.shape[0], 7)) if self.shrink is not None else None

        def first(s: slice) -> None:
            e = edges[s]
            np.matmul(lhs_t, e, out=moments[s])
            if sq is not None:
                np.einsum("mnk,mnk->mk", e, e, out=sq[s])

        self._run_blocks(first, blocks)
        c_xy_t = moments[:, :-1, :]
        mean = moments[:, -1, :]  # (M, 7)
        if self.space == "tangent":
            # The ⊞ chart δ = 2 vec(q̄* q) around each edge's mean rotation q̄ (edges are stored
            # on q̄'s hemisphere). A change Δ of δ is the quaternion change ½ q̄ ⊗ (0, Δ), so
            # in this chart the update is the quaternion one with every cross-covariance
            # projected onto the tangent plane at q̄: no log/exp over the M·N samples.
            q_bar = mean[:, 3:] / np.linalg.norm(mean[:, 3:], axis=1, keepdims=True)
            radial = np.einsum("mpk,mk->mp", c_xy_t[..., 3:], q_bar)
            c_xy_t[..., 3:] -= radial[..., None] * q_bar[:, None, :]
        if sq is not None:
            assert self.shrink is not None
            # as an oracle: variances about the mean (no Σx²/N − x̄² cancellation)
            dev = edges - mean[:, None, :]
            var_x = np.einsum("mnk,mnk->mk", dev, dev) / (n - 1)
            c_xy_t = an.shrink_correlations(c_xy_t, var_x, yc, self.shrink)
        return c_xy_t, mean

    def _cross_endpoints(self, edges: Array, ia: int, ib: int, point: bool, yc: Array,
                         blocks: list[slice]) -> tuple[Array, Array]:
        """``gain="endpoints"``: the cross-covariances ``(M, p, 7)`` through the principal
        components of the endpoint edges (:func:`mcsm.core.analysis.endpoint_cross_covariance`),
        and the edges' means ``(M, 7)``.

        Every edge is handled in its own tangent chart ``[t, δ]``, ``δ = 2 vec(q̄* q)``: pass 1
        gives the edges' cross-covariances with the components and the second moments of
        their translations and quaternions; a quaternion cross-covariance ``c_q`` is ``2 Bᵀ c_q``
        in the chart (``B`` the last three columns of ``L(q̄)``), a chart covariance ``c_δ`` is
        ``½ B c_δ`` back in the quaternion, on the tangent plane at ``q̄``.
        """
        n = self.n_samples
        e_b = edges[ib]
        v = np.concatenate((to_space(edges[ia], "tangent")[0],
                            e_b[:, :3] if point else to_space(e_b, "tangent")[0]), axis=1)
        pcs, lam = an.endpoint_components(v, ZERO_VARIANCE, RTOL)
        k = lam.shape[0]
        lhs_t = np.concatenate((pcs / (n - 1), np.full((n, 1), 1.0 / n)), axis=1).T[None]
        m = edges.shape[0]
        moments = np.empty((m, k + 1, 7))
        sq_t = np.empty((m, 3))
        sq_q = np.empty((m, 4, 4))

        def first(s: slice) -> None:
            e = edges[s]
            np.matmul(lhs_t, e, out=moments[s])
            np.einsum("mnk,mnk->mk", e[..., :3], e[..., :3], out=sq_t[s])
            np.matmul(np.swapaxes(e[..., 3:], 1, 2), e[..., 3:], out=sq_q[s])

        self._run_blocks(first, blocks)
        mean = moments[:, -1, :]
        q_bar = mean[:, 3:] / np.linalg.norm(mean[:, 3:], axis=1, keepdims=True)
        basis = (q_bar[:, L_INDEX] * L_SIGN)[:, :, 1:]  # (M, 4, 3)
        # (as an oracle: second moments about the mean, not Σx²/N − x̄², whose cancellation
        # costs digits the kernel's shifted sums keep)
        dev = edges - mean[:, None, :]
        var_t = np.einsum("mnk,mnk->mk", dev[..., :3], dev[..., :3]) / (n - 1)
        cov_q = np.matmul(np.swapaxes(dev[..., 3:], 1, 2), dev[..., 3:]) / (n - 1)
        var_d = 4.0 * np.einsum("mki,mkl,mli->mi", basis, cov_q, basis)
        var_x = np.concatenate((var_t, np.clip(var_d, 0.0, None)), axis=1)
        c_xp = moments[:, :-1, :]
        c_xp_chart = np.concatenate(
            (c_xp[..., :3], 2.0 * np.einsum("mki,mjk->mji", basis, c_xp[..., 3:])), axis=-1)
        c_py = pcs.T @ yc / (n - 1)
        var_y = np.einsum("np,np->p", yc, yc) / (n - 1)
        c6 = an.endpoint_cross_covariance(c_xp_chart, var_x, lam, c_py, var_y, n, self.shrink)
        c_xy_t = np.concatenate(
            (c6[..., :3], 0.5 * np.einsum("mki,mpi->mpk", basis, c6[..., 3:])), axis=-1)
        return c_xy_t, mean

    def _spare_buffer(self, shape: tuple[int, ...]) -> Array:
        """An uninitialised array of ``shape``: the edge array the last joint update replaced
        when the shapes agree (no fresh 22 MB allocation and its page faults per update)."""
        spare, self._spare = self._spare, None
        if spare is not None and spare.shape == shape:
            return spare
        return np.empty(shape)

    def _run_blocks(self, fn: Callable[[slice], _T], blocks: list[slice]) -> list[_T]:
        """``fn`` over the blocks, in order, on up to ``threads`` threads (numpy releases the
        GIL in these kernels); results in block order."""
        if self.threads <= 1 or len(blocks) < 2:
            return [fn(s) for s in blocks]
        return list(_pool(self.threads).map(fn, blocks))

    def _loop_inflation(self, yc: Array, y_mean: Array, z: Array) -> tuple[float, float]:
        """The inflation factor of this loop closure and the new running NIS average."""
        if self.inflation != "adaptive":
            return float(self.inflation), self._nis_avg
        n = yc.shape[0]
        innovation = z.mean(axis=0) - y_mean
        if yc.shape[1] == 7:
            # quaternion space: a unit quaternion has 3 dof, not 4; the radial direction at the
            # mean carries only second-order spread and would be counted as one more dof
            # (4 planar, 7 in 3-D), diluting the NIS. Project onto the tangent plane at q̄.
            q_bar = y_mean[3:] / np.linalg.norm(y_mean[3:])
            yc, z, innovation = (_tangent_part(a, q_bar) for a in (yc, z, innovation))
        s = yc.T @ yc / (n - 1) + sample_cov(z)
        d, lam, v = scaled_eigh(s)
        u = v.T @ (innovation * d)
        live = lam > 0.0
        nis = float(np.sum(u[live] ** 2 / lam[live])) / max(1, int(live.sum()))
        avg = (1.0 - ADAPT_RATE) * self._nis_avg + ADAPT_RATE * nis
        return float(np.clip(1.0 + ADAPT_STRENGTH * (avg - 1.0), 1.0, ADAPT_MAX)), avg

    def _predict(self, e_a: Array, e_b: Array, x: Array, point: bool) -> tuple[Array, Array]:
        """Predicted observation y and observation z as plain vectors, per sample."""
        if point:
            y = qrot(qconj(e_a[:, 3:]), e_b[:, :3] - e_a[:, :3])
            return y, x
        h = compound(invert(e_a), e_b)
        y, q_ref = to_space(h, self.space)
        z, _ = to_space(x, self.space, q_ref)
        return y, z


def _rescue(q: Array, norm: Array, low: tuple[Array, ...], w: Array, c_xy_t: Array,
            edges: Array, centre: Array) -> int:
    """The samples ``low`` (frame, sample) whose linear move collapsed their quaternion: the
    move's rotation read in the tangent at the frame's centre, ``h = vec(c⁻¹ ⊗ Δq)``, applied
    on the manifold, ``q ⊗ (√(1 − |h|²), h)`` (kernel_common.h, ``mk_joint_rescue``); written
    to ``q`` with a unit ``norm``. Returns how many."""
    f, i = low
    dq = np.einsum("jp,jpd->jd", w[i], c_xy_t[f])[:, 3:]
    c = centre[f, 3:] / np.linalg.norm(centre[f, 3:], axis=1, keepdims=True)
    h = qmul(qconj(c), dq)[:, 1:]
    hh = np.sum(h * h, axis=1)
    step = np.concatenate([np.sqrt(np.clip(1.0 - hh, 0.0, None))[:, None], h], axis=1)
    moved = qmul(edges[f, i, 3:], step)
    q[f, i] = moved
    norm[f, i] = np.linalg.norm(moved, axis=1)
    return len(f)


def _tangent_part(a: Array, q_bar: Array) -> Array:
    """``a`` ``(..., 7)`` with the quaternion part's component along ``q_bar`` removed."""
    out = a.copy()
    out[..., 3:] -= (a[..., 3:] @ q_bar)[..., None] * q_bar
    return out


def _merge_points(p_g: Array, p_x: Array) -> Array:
    """Revised merge (eq. 6) of two 3-D point sample sets (the main edge of a point update)."""
    from mcsm.core.at import merge_vectors, sample_cov

    cov_c, cov_d, cov_diff = sample_cov(p_g), sample_cov(p_x), sample_cov(p_g - p_x)
    c_x = 0.5 * (cov_c + cov_d - cov_diff)
    return merge_vectors(p_g, p_x, cov_c - c_x, cov_diff)


__all__ = ["StochasticMap", "UpdateResult", "RemoveResult", "Submap", "check_frame_name"]


def from_snapshot(snap: dict[str, Any], **opts: Any) -> StochasticMap:
    """A reference map holding exactly the state of ``mcsm.StochasticMap.snapshot()``."""
    n = int(snap["components"][0]["edges"].shape[1]) if snap["components"] else \
        int(snap["options"]["n_samples"])
    r = StochasticMap(n, **opts)
    r._next_id = snap["next_id"]
    r._order = {f: None for f in snap["order"]}
    r._nis_avg = snap["nis_avg"]
    for c in snap["components"]:
        comp = _Component(list(c["frames"]), np.array(c["is_point"], dtype=bool),
                          np.array(c["edges"]))
        r._comps[c["id"]] = comp
        for f in comp.frames:
            r._where[f] = c["id"]
    return r

