"""Stream a dataset's constraints into a map: an in-process ``StochasticMap`` or a ``MapClient``.

:func:`play` walks a :class:`mcsm_client.datasets.Dataset` in file order (or in pose order,
see ``order``) and turns each constraint into samples with the sampling helpers:

* odometry ``i → j``: a pose-to-pose AT ``x{i} → x{j}`` (a new frame joins the component);
* loop closure ``i → j`` between two known poses: the same AT, a case II update (PAPER §3);
* landmark sighting ``i → j``: a point update ``x{i} → l{j}`` (``(N, 3)`` samples).

Dataset covariances are over a body-frame perturbation (GTSAM/g2o), so poses are sampled with
``translation_frame="body"``. With ``bounded=True`` the map is kept at the landmarks plus two
poses, as PAPER §3 describes: the first pose stays as the anchor, and when odometry brings a new
current pose, the previous current pose is removed. Constraints that name a removed pose are
then skipped and counted (``PlayStats.skipped``).

:class:`MapTarget` gives both kinds of map one interface (``update`` routes ``(N, 3)`` samples
to ``MapClient.update_point``), and is what the simulation clients use too.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import numpy.typing as npt
from mcsm.errors import McsmError

from mcsm_client.datasets import Constraint, Dataset
from mcsm_client.sampling import sample_planar, sample_point, sample_pose

Array = npt.NDArray[np.float64]

__all__ = ["MapTarget", "PlayStats", "constraint_samples", "play"]


class MapTarget:
    """One interface over an in-process ``mcsm.StochasticMap`` and a remote ``MapClient``.

    Parameters
    ----------
    target : StochasticMap or MapClient (or a MapTarget, returned unwrapped)
        Anything with ``update``/``remove``/``marginal``/``query``; a client is recognised by
        its ``update_point`` method.
    prefix : str, optional
        A frame namespace such as ``robot1`` or ``robot1/run2``: every frame name given to
        this object means ``<prefix>/<name>`` in the map, and :meth:`frames` lists only that
        namespace's frames (without the prefix). ``None`` keeps a wrapped MapTarget's prefix
        (default ``""``: names as given).
    """

    def __init__(self, target: Any, prefix: str | None = None) -> None:
        inner: str = target.prefix if isinstance(target, MapTarget) else ""
        self.target: Any = target.target if isinstance(target, MapTarget) else target
        self.prefix: str = inner if prefix is None else prefix.strip("/")
        self.remote = hasattr(self.target, "update_point")
        self._frames: set[str] | None = None

    def name(self, frame: str) -> str:
        """The map's name of ``frame`` (``<prefix>/<frame>``)."""
        return f"{self.prefix}/{frame}" if self.prefix else frame

    def _all_frames(self) -> set[str]:
        if self.remote:
            if self._frames is None:
                self._frames = set(self.target.info().frames)
            return self._frames
        return set(self.target.frames())

    def existing(self) -> list[str]:
        """The map's frames inside this target's namespace (all frames without a ``/`` when
        there is no prefix), full names, sorted: what a fresh run must not write into."""
        if self.prefix:
            head = self.prefix + "/"
            return sorted(f for f in self._all_frames() if f.startswith(head))
        return sorted(f for f in self._all_frames() if "/" not in f)

    @property
    def n_samples(self) -> int:
        """The map's N (asks the server once for a remote map)."""
        if self.remote:
            return int(self.target.info().n_samples)
        return int(self.target.n_samples)

    def update(self, a: str, b: str, samples: Array, /) -> str:
        """Apply samples ``(N, 7)`` (AT a→b) or ``(N, 3)`` (point b seen from a); the kind."""
        self._frames = None
        a, b = self.name(a), self.name(b)
        if self.remote and samples.ndim == 2 and samples.shape[1] == 3:
            r = self.target.update_point(a, b, samples)
        else:
            r = self.target.update(a, b, samples)
        return str(r.kind)

    def remove(self, frame: str, /) -> None:
        """Remove a frame."""
        self._frames = None
        self.target.remove(self.name(frame))

    def marginal(self, a: str, b: str, /) -> tuple[Array, Array]:
        """Mean ``(7,)`` and tangent covariance ``(6, 6)`` of a→b."""
        mean, cov = self.target.marginal(self.name(a), self.name(b))
        return np.asarray(mean, dtype=np.float64), np.asarray(cov, dtype=np.float64)

    def query(self, a: str, b: str, /) -> Array:
        """Samples ``(N, 7)`` of a→b."""
        return np.asarray(self.target.query(self.name(a), self.name(b)), dtype=np.float64)

    def frames(self) -> list[str]:
        """All frame names (one ``info`` call for a remote map, cached until the next change);
        with a prefix, that namespace's frames without the prefix."""
        names = self._all_frames()
        if self.prefix:
            head = self.prefix + "/"
            return sorted(f[len(head):] for f in names if f.startswith(head))
        return sorted(names) if self.remote else list(self.target.frames())

    def __contains__(self, frame: object, /) -> bool:
        if not isinstance(frame, str):
            return False
        if not self.remote:
            return self.name(frame) in self.target
        return self.name(frame) in self._all_frames()

    def export_component(self, frame: str) -> Any:
        """The core ``Submap`` of ``frame``'s component (full frame names)."""
        if self.remote:
            return self.target.export_submap(self.name(frame))
        return self.target.export_component(self.name(frame))

    def import_component(self, submap: Any) -> str:
        """Add an exported component as is; returns the result kind (``"import"``)."""
        self._frames = None
        if self.remote:
            return str(self.target.import_submap(submap).kind)
        return str(self.target.import_component(submap).kind)

    def digest(self) -> str:
        """The map's state digest."""
        if self.remote:
            return str(self.target.info().digest)
        return str(self.target.state_digest())


@dataclass
class PlayStats:
    """What :func:`play` did.

    Attributes
    ----------
    total : int
        Constraints considered.
    applied : dict of str to int
        Applied updates per constraint kind.
    results : dict of str to int
        Map result kinds (``new_frame``, ``join``, ``loop_closure``, ...).
    skipped : dict of str to int
        Constraints skipped, per reason.
    rejected : dict of str to int
        Updates the map refused, per error type (``McsmError`` subclass name).
    removed : int
        Pose frames removed (bounded mode).
    elapsed_s : float
        Wall time of the run.
    first_error : str
        The first rejection's message, if any.
    """

    total: int = 0
    applied: dict[str, int] = field(default_factory=dict)
    results: dict[str, int] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    removed: int = 0
    elapsed_s: float = 0.0
    first_error: str = ""

    @property
    def n_applied(self) -> int:
        """Number of updates applied."""
        return sum(self.applied.values())

    def summary(self) -> str:
        """One line for people."""
        parts = [f"{self.n_applied}/{self.total} constraints applied"]
        if self.applied:
            parts.append(", ".join(f"{k} {v}" for k, v in sorted(self.applied.items())))
        if self.results:
            parts.append("map: " + ", ".join(f"{k} {v}" for k, v in sorted(self.results.items())))
        if self.removed:
            parts.append(f"{self.removed} old poses removed")
        if self.skipped:
            parts.append("skipped: " + ", ".join(f"{k} {v}" for k, v in self.skipped.items()))
        if self.rejected:
            parts.append("rejected: " + ", ".join(f"{k} {v}" for k, v in self.rejected.items()))
        parts.append(f"{self.elapsed_s:.1f} s")
        return "; ".join(parts)


def _bump(d: dict[str, int], key: str) -> None:
    d[key] = d.get(key, 0) + 1


def constraint_samples(c: Constraint, dim: int, *, n_samples: int,
                       rng: np.random.Generator) -> Array:
    """Samples of one constraint: ``(N, 7)`` for a pose edge, ``(N, 3)`` for a landmark.

    Parameters
    ----------
    c : Constraint
        The measurement (mean and covariance in the dataset's convention).
    dim : int
        2 (planar: ``c.mean`` is ``(dx, dy, dθ)``) or 3 (``c.mean`` is a 7-vector).
    n_samples : int
        N.
    rng : np.random.Generator
        Source of the draws.
    """
    if c.is_point:
        return sample_point(c.mean, c.cov, n_samples=n_samples, rng=rng)
    if dim == 2:
        return sample_planar(c.mean, c.cov, n_samples=n_samples, rng=rng,
                             translation_frame="body")
    return sample_pose(c.mean, c.cov, n_samples=n_samples, rng=rng, translation_frame="body")


def _ordered(ds: Dataset, order: Literal["file", "pose"]) -> list[Constraint]:
    if order == "file":
        return list(ds.constraints)
    if order != "pose":
        raise ValueError(f"order must be 'file' or 'pose', got {order!r}")
    # Arrival order: a constraint can be applied once its newest pose exists. Stable, so ties
    # keep file order (odometry to pose k before pose k's sightings in iSAM files).
    first_seen: dict[int, int] = {}
    for idx, c in enumerate(ds.constraints):
        if not c.is_point:
            first_seen.setdefault(c.source, idx)
            first_seen.setdefault(c.target, idx)

    def key(ic: tuple[int, Constraint]) -> tuple[int, int, int]:
        idx, c = ic
        if c.is_point:
            return (first_seen.get(c.source, idx), 1, idx)
        return (max(first_seen[c.source], first_seen[c.target]), 0, idx)

    return [c for _, c in sorted(enumerate(ds.constraints), key=key)]


ProgressCallback = Callable[[int, int, PlayStats], None]


def play(
    dataset: Dataset,
    target: Any,
    *,
    rng: np.random.Generator,
    n_samples: int | None = None,
    bounded: bool = False,
    order: Literal["file", "pose"] = "file",
    max_constraints: int | None = None,
    progress: ProgressCallback | None = None,
    stop_on_error: bool = False,
    pose_prefix: str = "x",
    landmark_prefix: str = "l",
) -> PlayStats:
    """Stream a dataset's constraints into a map.

    Parameters
    ----------
    dataset : Dataset
        From :func:`mcsm_client.datasets.read_dataset`.
    target : StochasticMap, MapClient or MapTarget
        The map to feed.
    rng : np.random.Generator
        Source of all sample draws.
    n_samples : int, optional
        N; read from the map when omitted.
    bounded : bool
        Keep only the first pose (anchor), the current pose and the landmarks (PAPER §3).
    order : {"file", "pose"}
        ``"file"``: the file's order. ``"pose"``: each constraint as soon as its newest pose
        exists (files that list all sightings after all odometry, like the iSAM ``.g2o``
        files, need this for ``bounded``).
    max_constraints : int, optional
        Stop after this many constraints.
    progress : callable, optional
        ``progress(done, total, stats)`` after every constraint.
    stop_on_error : bool
        Raise the first ``McsmError`` instead of counting it and going on.
    pose_prefix, landmark_prefix : str
        Frame names are ``f"{pose_prefix}{id}"`` and ``f"{landmark_prefix}{id}"``.

    Returns
    -------
    PlayStats

    Raises
    ------
    McsmError
        Only with ``stop_on_error``. A ``Timeout`` from a remote map always propagates.
    """
    from mcsm.errors import Timeout

    t0 = time.perf_counter()
    m = MapTarget(target)
    n = int(n_samples) if n_samples is not None else m.n_samples
    items: Iterable[Constraint] = _ordered(dataset, order)
    todo = list(items)[: max_constraints] if max_constraints is not None else list(items)
    stats = PlayStats(total=len(todo))
    present: set[int] = set()   # pose ids in the map
    gone: set[int] = set()      # pose ids removed (bounded)
    anchor: int | None = None
    current: int | None = None

    for done, c in enumerate(todo, start=1):
        a = f"{pose_prefix}{c.source}"
        b = f"{(landmark_prefix if c.is_point else pose_prefix)}{c.target}"
        poses = (c.source,) if c.is_point else (c.source, c.target)
        if any(p in gone for p in poses):
            _bump(stats.skipped, "names a removed pose")
        elif c.is_point and c.source not in present and present:
            _bump(stats.skipped, "sighting from an unknown pose")
        else:
            samples = constraint_samples(c, dataset.dim, n_samples=n, rng=rng)
            try:
                kind = m.update(a, b, samples)
            except Timeout:
                raise
            except McsmError as exc:
                if stop_on_error:
                    raise
                _bump(stats.rejected, type(exc).__name__)
                stats.first_error = stats.first_error or f"line {c.line}: {exc}"
            else:
                _bump(stats.applied, c.kind)
                _bump(stats.results, kind)
                new = [p for p in poses if p not in present]
                present.update(poses)
                if anchor is None:
                    # The first edge brings two poses (TORO files write the later one first).
                    anchor, current = min(poses), max(poses)
                elif new:
                    previous, current = current, new[-1]
                    if bounded and previous is not None and previous not in (anchor, current):
                        m.remove(f"{pose_prefix}{previous}")
                        present.discard(previous)
                        gone.add(previous)
                        stats.removed += 1
        if progress is not None:
            progress(done, stats.total, stats)
    stats.elapsed_s = time.perf_counter() - t0
    return stats
