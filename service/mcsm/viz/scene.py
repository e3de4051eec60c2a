"""What a picture of a map shows, computed with numpy only: marginals, ellipses, ellipsoids.

A :class:`MapView` holds, for every frame of a map, its component, whether it is a point frame,
its marginal (mean 7-vector and 6×6 tangent covariance, ``StochasticMap.marginal(root,
frame)``) and optionally its samples. Every frame is expressed in the root frame of its own
component: components of one map are unrelated (PAPER §3), so a picture draws each one around
its own root.

The 95 % regions are those of a Gaussian with the marginal's translation covariance, defined
once in :mod:`mcsm.viz.ellipse` (χ² with as many degrees of freedom as the covariance spans).
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import numpy.typing as npt

from mcsm.core import StochasticMap
from mcsm.errors import McsmError

# the one region definition of every picture (re-exported here for older imports)
from mcsm.viz.ellipse import P_REGION as P_REGION
from mcsm.viz.ellipse import Ellipse as Ellipse
from mcsm.viz.ellipse import Ellipsoid as Ellipsoid
from mcsm.viz.ellipse import chi2_quantile as chi2_quantile
from mcsm.viz.ellipse import ellipse as ellipse
from mcsm.viz.ellipse import ellipsoid as ellipsoid

Array = npt.NDArray[np.float64]

# --------------------------------------------------------------------------------------------
# The map as pictures see it
# --------------------------------------------------------------------------------------------

@dataclass
class FrameView:
    """One frame: its component's root, point flag, marginal in the root frame, samples."""

    name: str
    component: str
    is_point: bool
    mean: Array  # (7,) x y z qw qx qy qz
    cov: Array  # (6, 6) tx ty tz rx ry rz
    samples: Array | None = field(default=None, repr=False)  # (N, 7) root -> frame

    @property
    def position(self) -> Array:
        return self.mean[:3]


@dataclass
class MapView:
    """Everything a picture of one map shows, at one sequence number."""

    map: str
    seq: int
    options: dict[str, Any]
    components: list[str]
    frames: list[FrameView]
    notes: list[str] = field(default_factory=list)  # warnings (truncated file, divergence)
    #: the update that created each frame, when known (:class:`mcsm.viz.layout.FrameHistory`)
    parents: dict[str, str] | None = None

    @property
    def n_samples(self) -> int:
        return int(self.options.get("n_samples", 0))

    def frame(self, name: str) -> FrameView:
        for f in self.frames:
            if f.name == name:
                return f
        raise KeyError(name)

    def of_component(self, root: str) -> list[FrameView]:
        """Frames of one component, in the order they were added to the map."""
        return [f for f in self.frames if f.component == root]

    def pose_path(self, root: str) -> list[FrameView]:
        """The pose (non-point) frames of one component in the order they were added."""
        return [f for f in self.of_component(root) if not f.is_point]

    def paths(self, root: str) -> list[list[FrameView]]:
        """One component's pose frames split into robot paths (:func:`mcsm.viz.layout.
        robot_paths`: odometry chains, or name stems where the history is unknown)."""
        from mcsm.viz.layout import robot_paths

        by_name = {f.name: f for f in self.pose_path(root)}
        return [[by_name[n] for n in path]
                for path in robot_paths(by_name.values(), self.parents)]

    def offsets(self) -> dict[str, Array]:
        """Display shift of each component so that none overlaps another
        (:func:`mcsm.viz.layout.component_offsets`)."""
        from mcsm.viz.layout import component_offsets

        return component_offsets(self.frames, self.components)

    def shifted(self, offsets: dict[str, Array]) -> MapView:
        """A copy with every frame's position and samples moved by its component's display
        shift (``offsets``: root -> (3,) metres, :meth:`offsets`); covariances unchanged."""
        frames = []
        for f in self.frames:
            d = offsets.get(f.component)
            if d is None or not np.any(d):
                frames.append(f)
                continue
            mean = f.mean.copy()
            mean[:3] += d
            smp = None
            if f.samples is not None:
                smp = f.samples.copy()
                smp[:, :3] += d
            frames.append(FrameView(f.name, f.component, f.is_point, mean, f.cov, smp))
        return MapView(self.map, self.seq, self.options, self.components, frames,
                       list(self.notes), self.parents)

    def options_text(self) -> str:
        o = self.options
        parts = [str(o.get(k)) for k in ("method", "space", "analysis") if k in o]
        extra = [f"{k} {o[k]}" for k in ("shrink", "inflation", "gain") if k in o]
        return "/".join(parts) + (", " + ", ".join(extra) if extra else "")


def map_view(smap: StochasticMap, *, map_name: str = "default", seq: int = 0,
             samples: bool = False, parents: dict[str, str] | None = None) -> MapView:
    """A :class:`MapView` of ``smap``: every frame's marginal relative to its component root.

    Parameters
    ----------
    smap : the map (read only)
    samples : also copy every frame's samples ``(N, 7)`` (``smap.query(root, frame)``)
    parents : the update that created each frame, if known (robot paths follow it)
    """
    roots = smap.components()
    root_of = {f: r for r in roots for f in smap.component(r)}
    frames = []
    for name in smap.frames():
        root = root_of[name]
        mean, cov = smap.marginal(root, name)
        frames.append(FrameView(name, root, bool(smap.is_point(name)),
                                np.asarray(mean, dtype=np.float64),
                                np.asarray(cov, dtype=np.float64),
                                smap.query(root, name) if samples else None))
    return MapView(map_name, int(seq), dict(smap.options()), list(roots), frames,
                   parents=dict(parents) if parents is not None else None)


def is_planar(view: MapView, rel_tol: float = 1e-9) -> bool:
    """True when every frame lies in its root's x-y plane with yaw-only rotation and no
    out-of-plane spread (a 2-D map: drawn top down)."""
    if not view.frames:
        return True
    pos = np.array([f.position for f in view.frames])
    scale = max(1.0, float(np.max(np.abs(pos[:, :2]))))
    tol = rel_tol * scale
    for f in view.frames:
        if abs(f.mean[2]) > tol or abs(f.mean[4]) > 1e-9 or abs(f.mean[5]) > 1e-9:
            return False
        if f.cov[2, 2] > tol * tol or f.cov[3, 3] > 1e-18 or f.cov[4, 4] > 1e-18:
            return False
    return True


# --------------------------------------------------------------------------------------------
# Loading a map from a recording, ground truth from CSV
# --------------------------------------------------------------------------------------------

@dataclass
class LoadedMap:
    """A map replayed from a recording up to a sequence number."""

    map: StochasticMap
    name: str
    seq: int
    last_seq: int  # the map's last sequence number in the file
    notes: list[str]
    parents: dict[str, str] = field(default_factory=dict)  # creating updates (robot paths)


class ReplaySink:
    """Passed to ``mcsm.recording.replay`` as its ``sink``: replay calls ``config`` with each
    map's live state, ``input`` after applying each input, ``snapshot`` when it starts from
    (or verifies) a state snapshot. This one follows one map and records the update that
    created each of its frames (:class:`mcsm.viz.layout.FrameHistory`); subclasses draw."""

    def __init__(self, map_name: str) -> None:
        from mcsm.viz.layout import FrameHistory

        self.map_name = map_name
        self.state: Any = None
        self.history = FrameHistory()
        self.last_frames: tuple[str, ...] = ()  # what the last input named

    def config(self, state: Any, *_args: Any, **_kw: Any) -> None:
        if state.name == self.map_name:
            self.state = state

    def input(self, op: str, map_name: str, seq: int, recv_ns: int, _sender: str = "",
              _request_id: str = "", request: bytes = b"") -> None:
        if map_name != self.map_name or self.state is None:
            return
        try:
            self.last_frames = self.history.observe_request(op, request, self.state.map)
        except McsmError:
            self.last_frames = ()
            self.history.reset(self.state.map)  # unreadable: paths fall back to names
        self.on_input(op, seq, recv_ns, _request_id)

    def on_input(self, op: str, seq: int, recv_ns: int, request_id: str) -> None:
        """Called after each input of the map (for subclasses)."""

    def checkpoint(self, *_args: Any, **_kw: Any) -> None:
        return None

    def snapshot(self, state: Any, *_args: Any, **_kw: Any) -> None:
        # replay started from (or verified) a state snapshot: a start from one loses the
        # history before it; a verified one changes nothing
        if state.name == self.map_name and not self.history.parent and state.seq:
            self.history.reset(state.map)


def recording_maps(path: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]
                   ) -> dict[str, list[int]]:
    """Map names of a recording (one file, or a split recording's files in order) and, for
    each, the running input count (all maps together) after each of its inputs:
    ``counts[name][s - 1 - base]`` inputs bring map ``name`` to seq ``s``, where ``base`` is
    :func:`recording_bases`' (0 unless the recording starts from a snapshot).

    Reads records only (no arithmetic). Raises ``RecordingError`` if the file is unreadable.
    """
    return _scan(path)[0]


def recording_bases(path: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]
                    ) -> dict[str, int]:
    """Per map, the seq before its first input in the recording (0, or the seq of the snapshot
    a restored or split file starts from)."""
    return _scan(path)[1]


def _scan(path: str | os.PathLike[str] | Sequence[str | os.PathLike[str]]
          ) -> tuple[dict[str, list[int]], dict[str, int]]:
    from mcsm.recording import TOPIC_CONFIG, TOPIC_OPS, RecordingReader

    paths = [path] if isinstance(path, (str, os.PathLike)) else list(path)
    counts: dict[str, list[int]] = {}
    bases: dict[str, int] = {}
    n_inputs = 0
    for p in paths:
        reader = RecordingReader(p)
        for item in reader:
            name = item.data.get("map")
            if not isinstance(name, str):
                continue
            if item.topic == TOPIC_CONFIG:
                counts.setdefault(name, [])
            elif item.topic in TOPIC_OPS:
                n_inputs += 1
                if name not in bases:
                    bases[name] = int(item.data.get("seq", 1)) - 1
                counts.setdefault(name, []).append(n_inputs)
        if not reader.complete:
            break
    return counts, bases


def choose_map(names: list[str], wanted: str | None, path: str) -> str:
    """``wanted`` if the recording has it; else ``default`` or the only map; else an error."""
    if wanted is not None:
        if wanted not in names:
            raise McsmError(f"{path} has no map {wanted!r} (maps: {', '.join(names) or 'none'})")
        return wanted
    if not names:
        raise McsmError(f"{path} holds no map")
    if "default" in names or len(names) == 1:
        return "default" if "default" in names else names[0]
    raise McsmError(f"{path} holds maps {', '.join(names)}: choose one with --map")


def load_map(path: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
             map_name: str | None = None, at_seq: int | None = None) -> LoadedMap:
    """Replay a recording (``mcsm.recording.replay``) up to seq ``at_seq`` of one map.

    Parameters
    ----------
    path : the recording (complete or cut short)
    map_name : which map (default: ``default``, or the only one)
    at_seq : stop once this map reached this sequence number (default: the end of the file)

    Raises
    ------
    McsmError
        Unreadable file (``RecordingError``), unknown map, or a sequence number the file does
        not reach.
    """
    from mcsm.recording import replay

    counts, bases = _scan(path)
    label = str(path) if isinstance(path, (str, os.PathLike)) else ", ".join(map(str, path))
    name = choose_map(list(counts), map_name, label)
    base = bases.get(name, 0)
    last_seq = base + len(counts[name])
    stop_after = None
    if at_seq is not None:
        if not base + 1 <= at_seq <= last_seq:
            raise McsmError(f"map {name!r} of {label} has sequence numbers "
                            f"{base + 1}..{last_seq}, not {at_seq}")
        # every input of every map up to this map's input number at_seq
        stop_after = counts[name][at_seq - base - 1]
    sink = ReplaySink(name)
    rep = replay(path, stop_after=stop_after, sink=cast(Any, sink))
    notes = []
    if rep.divergence is not None:
        notes.append(f"replay diverged from the recording; showing the map as replayed up to "
                     f"there ({rep.divergence})")
    if rep.tail_error is not None:
        notes.append(f"recording is cut short ({rep.tail_error}); showing every complete input")
    st = rep.states.get(name)
    if st is None:
        raise McsmError(f"{path}: map {name!r} has no config record before seq {at_seq}")
    return LoadedMap(st.map, name, st.seq, last_seq, notes, dict(sink.history.parent))


def read_truth(path: str | os.PathLike[str]) -> dict[str, Array]:
    """Ground truth positions from a CSV file ``frame,x,y[,z]``, one frame per line.

    Coordinates are in metres in the root frame of the frame's component. A first line
    starting with ``frame`` is a header; blank lines and lines starting with ``#`` are skipped.

    Raises
    ------
    McsmError
        If the file cannot be read or a line is malformed (the line number is given).
    """
    out: dict[str, Array] = {}
    try:
        with open(Path(path), newline="", encoding="utf-8") as fh:
            for lineno, row in enumerate(csv.reader(fh), start=1):
                if not row or not row[0].strip() or row[0].lstrip().startswith("#"):
                    continue
                if lineno == 1 and row[0].strip().lower() == "frame":
                    continue
                if len(row) not in (3, 4):
                    raise McsmError(f"{path}:{lineno}: expected frame,x,y[,z], got {len(row)} "
                                    "fields")
                try:
                    xyz = [float(v) for v in row[1:]] + ([0.0] if len(row) == 3 else [])
                except ValueError:
                    raise McsmError(f"{path}:{lineno}: coordinates must be numbers") from None
                if not all(math.isfinite(v) for v in xyz):
                    raise McsmError(f"{path}:{lineno}: coordinates must be finite")
                out[row[0].strip()] = np.array(xyz)
    except OSError as exc:
        raise McsmError(f"cannot read ground truth {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise McsmError(f"{path}: ground truth is not a UTF-8 CSV file") from None
    return out
