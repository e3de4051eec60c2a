"""Where a picture puts things: one path per robot, and unrelated components side by side.

**Paths.** A robot's path is its odometry chain: each pose frame was first observed from the
pose before it (the update ``a -> b`` that created ``b``). :class:`FrameHistory` records
those creating updates while a recording is replayed (``mcsm plot``, ``mcsm export``) or as
events arrive (``mcsm view``); :func:`robot_paths` follows them, skipping frames removed since
(a bounded run keeps ``x0`` and the current pose: its path joins the two). A pose frame whose
creation was not seen (imported, created before the view started, or a map built in process)
continues the latest path whose last pose has the same name stem (the name without its
trailing digits: ``A.x12`` follows ``A.x11``, ``robot1/p3`` follows ``robot1/p2``). Two robots
in one component therefore draw two paths, never one zig-zag through both.

**Components side by side.** Components of one map are unrelated (no transform joins them,
PAPER §3). Each is drawn in its own root frame; :func:`component_offsets` shifts the second
and later ones along +x so that their boxes do not overlap (a gap of 10 % of the widest
component, at least 1 m), so their roots and labels do not sit on top of each other at one
origin. A shift is a display choice, not a transform: pictures say so.

numpy only; ``mcsm.wire`` is imported by :meth:`FrameHistory.observe_request` when called.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

_TRAILING_DIGITS = re.compile(r"\d+$")
#: colours (RGB in 0..1) of components and paths: matplotlib's tab10, in its order
PALETTE: list[tuple[float, float, float]] = [
    (0.122, 0.467, 0.706), (1.0, 0.498, 0.055), (0.173, 0.627, 0.173), (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741), (0.549, 0.337, 0.294), (0.890, 0.467, 0.761), (0.498, 0.498, 0.498),
    (0.737, 0.741, 0.133), (0.090, 0.745, 0.812)]
#: gap between components shifted side by side: this fraction of the widest, at least 1 m
GAP_FRACTION = 0.1
MIN_GAP_M = 1.0


class _Frames(Protocol):
    """What the history needs of a map: membership (``StochasticMap`` has it)."""

    def __contains__(self, name: object) -> bool: ...

    def frames(self) -> list[str]: ...


class _Pose(Protocol):
    @property
    def name(self) -> str: ...

    @property
    def is_point(self) -> bool: ...

    @property
    def component(self) -> str: ...

    @property
    def position(self) -> Array: ...


class FrameHistory:
    """The update that created each frame (``parent[b] = a`` for an update ``a -> b`` that
    added ``b``), fed one applied input at a time."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self._alive: set[str] = set()

    def observe(self, op: str, frames: Sequence[str], smap: _Frames) -> None:
        """Record an applied input: ``op`` and, for an update, its frames ``(a, b)``;
        ``smap`` is the map after it."""
        if op == "update" and len(frames) == 2:
            a, b = frames
            if b not in self._alive and b in smap and a in self._alive:
                self.parent[b] = a
            elif a not in self._alive and a in smap and b in self._alive:
                self.parent[a] = b
            elif b not in self._alive and a not in self._alive and b in smap:
                self.parent[b] = a  # a new component: b seen from its root a
            self._alive.update(f for f in (a, b) if f in smap)
        else:  # remove, import, retract, reinstate: rare; take the map's word for it
            self._alive = set(smap.frames())

    def observe_request(self, op: str, request: bytes, smap: _Frames) -> tuple[str, ...]:
        """:meth:`observe` from a recorded request's bytes; returns the frames (or request
        id) it names: an update's ``(a, b)``, a remove's frame, a retract's target."""
        from mcsm import wire

        d = wire.unpack(request)
        frames: tuple[str, ...] = ()
        if op == "update":
            a, b = d.get("a"), d.get("b")
            if isinstance(a, str) and isinstance(b, str):
                frames = (a, b)
        else:
            x = d.get("frame", d.get("target"))
            frames = (x,) if isinstance(x, str) else ()
        self.observe(op, frames, smap)
        return frames

    def reset(self, smap: _Frames) -> None:
        """Start from a map whose history is unknown (a state snapshot)."""
        self.parent.clear()
        self._alive = set(smap.frames())


def name_stem(name: str) -> str:
    """The frame name without its trailing digits (``A.x12`` -> ``A.x``)."""
    return _TRAILING_DIGITS.sub("", name)


def robot_paths(poses: Iterable[_Pose], parents: Mapping[str, str] | None = None
                ) -> list[list[str]]:
    """The pose frames of one component split into paths, each in the order added.

    ``poses`` are the component's pose frames in the order they were added; ``parents`` the
    creating updates (:class:`FrameHistory`), possibly partial (module docstring).
    """
    seq = list(poses)
    alive = {p.name for p in seq}
    parents = parents or {}
    paths: list[list[str]] = []
    tail: dict[str, int] = {}  # last pose of a path -> the path's index
    by_stem: dict[str, int] = {}  # name stem -> the path its latest pose is on
    for p in seq:
        idx: int | None = None
        if p.name in parents:
            anc = parents.get(p.name)
            hops = 0
            while anc is not None and anc not in alive and hops < 1_000_000:
                anc, hops = parents.get(anc), hops + 1
            if anc is not None and anc in tail:
                idx = tail.pop(anc)
        else:
            j = by_stem.get(name_stem(p.name))
            if j is not None and paths[j][-1] in tail:
                idx = tail.pop(paths[j][-1])
        if idx is None:
            paths.append([p.name])
            idx = len(paths) - 1
        else:
            paths[idx].append(p.name)
        tail[p.name] = idx
        by_stem[name_stem(p.name)] = idx
    return paths


def colour_plan(components: Sequence[str], paths: Mapping[str, Sequence[Sequence[str]]]
                ) -> tuple[dict[str, tuple[float, float, float]],
                           dict[str, tuple[float, float, float]]]:
    """Colours of components (their landmarks) and of pose frames (their path's): component
    ``i`` takes ``PALETTE[i]``; a component's first path takes the component's colour, every
    further path (another robot) the next colour not given to a component."""
    comp = {r: PALETTE[i % len(PALETTE)] for i, r in enumerate(components)}
    pose: dict[str, tuple[float, float, float]] = {}
    extra = len(components)
    for r in components:
        for k, path in enumerate(paths.get(r, ())):
            col = comp[r]
            if k > 0:
                col = PALETTE[extra % len(PALETTE)]
                extra += 1
            pose.update({n: col for n in path})
    return comp, pose


def thin(n: int, most: int) -> list[int]:
    """At most ``most`` indices of ``range(n)``, evenly spread, first and last included."""
    if n <= most:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, most)})


def component_offsets(frames: Iterable[_Pose], components: Sequence[str]) -> dict[str, Array]:
    """Display shift of each component (module docstring): the first stays at its origin,
    each next one starts to the right of the previous one's box."""
    pos: dict[str, list[Array]] = {r: [] for r in components}
    for f in frames:
        pos.setdefault(f.component, []).append(np.asarray(f.position, dtype=np.float64))
    boxes = {r: (np.min(p, axis=0), np.max(p, axis=0)) if p else (np.zeros(3), np.zeros(3))
             for r, p in pos.items()}
    widest = max((float(hi[0] - lo[0]) for lo, hi in boxes.values()), default=0.0)
    gap = max(MIN_GAP_M, GAP_FRACTION * widest)
    out: dict[str, Array] = {}
    right = 0.0
    for i, r in enumerate(components):
        lo, hi = boxes.get(r, (np.zeros(3), np.zeros(3)))
        shift = 0.0 if i == 0 else right + gap - float(min(lo[0], 0.0))
        out[r] = np.array([shift, 0.0, 0.0])
        right = shift + float(max(hi[0], 0.0))
    return out


def offsets_text(offsets: Mapping[str, Array]) -> str:
    """``"q0 +12.5 m"`` for each shifted component (empty when nothing is shifted)."""
    parts = [f"{r} +{float(v[0]):.3g} m" for r, v in offsets.items() if float(v[0]) != 0.0]
    return ", ".join(parts)


__all__ = ["FrameHistory", "robot_paths", "component_offsets", "name_stem", "offsets_text"]
