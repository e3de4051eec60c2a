"""What a picture of a map shows, computed with numpy only: marginals, ellipses, ellipsoids.

A :class:`MapView` holds, for every frame of a map, its component, whether it is a point frame,
its marginal (mean 7-vector and 6×6 tangent covariance, ``StochasticMap.marginal(root,
frame)``) and optionally its samples. Every frame is expressed in the root frame of its own
component: components of one map are unrelated (PAPER §3), so a picture draws each one around
its own root.

The 95 % regions are those of a Gaussian with the marginal's translation covariance: an
ellipse ``{x : (x − μ)ᵀ Σ⁻¹ (x − μ) ≤ χ²₂(0.95)}`` for a 2-D projection and an ellipsoid with
``χ²₃(0.95)`` in 3-D. Full axis lengths are ``2 sqrt(χ² λᵢ)`` for the eigenvalues ``λᵢ`` of Σ.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from mcsm.core import StochasticMap
from mcsm.errors import McsmError

Array = npt.NDArray[np.float64]

#: probability mass inside every drawn ellipse / ellipsoid
P_REGION = 0.95


def chi2_quantile(p: float, dof: int) -> float:
    """Quantile of the χ² distribution with 1, 2 or 3 degrees of freedom.

    Closed-form CDFs (``erf`` for 1 and 3 dof, ``1 − exp(−x/2)`` for 2), inverted by bisection
    to machine precision; no scipy needed.
    """
    if not 0.0 < p < 1.0:
        raise ValueError(f"p must be in (0, 1), got {p}")
    if dof == 2:
        return -2.0 * math.log1p(-p)

    def cdf(x: float) -> float:
        if dof == 1:
            return math.erf(math.sqrt(x / 2.0))
        if dof == 3:
            return (math.erf(math.sqrt(x / 2.0))
                    - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0))
        raise ValueError(f"dof must be 1, 2 or 3, got {dof}")

    lo, hi = 0.0, 1.0
    while cdf(hi) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if cdf(mid) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-15 * hi:
            break
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class Ellipse:
    """A 2-D confidence ellipse: centre, full axis lengths, angle of ``width`` from +x (deg)."""

    center: tuple[float, float]
    width: float
    height: float
    angle_deg: float


@dataclass(frozen=True)
class Ellipsoid:
    """A 3-D confidence ellipsoid: centre, full axis lengths along its own x, y, z, and the
    rotation of those axes into the parent frame as a unit quaternion ``(x, y, z, w)``
    (Foxglove's order)."""

    center: tuple[float, float, float]
    sizes: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]

    def rotation(self) -> Array:
        """The 3×3 rotation matrix of :attr:`quat_xyzw`."""
        x, y, z, w = self.quat_xyzw
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def ellipse(mean2: npt.ArrayLike, cov2: npt.ArrayLike, p: float = P_REGION) -> Ellipse:
    """The ``p`` confidence ellipse of a 2-D Gaussian (``width`` along the major axis).

    Parameters
    ----------
    mean2 : (2,) float64, metres
    cov2 : (2, 2) float64, m²; negative eigenvalues from round-off count as 0
    """
    c = np.asarray(cov2, dtype=np.float64)
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    lam = np.clip(lam, 0.0, None)
    k = chi2_quantile(p, 2)
    major = vec[:, 1]
    m = np.asarray(mean2, dtype=np.float64)
    return Ellipse((float(m[0]), float(m[1])), float(2.0 * math.sqrt(k * lam[1])),
                   float(2.0 * math.sqrt(k * lam[0])),
                   float(math.degrees(math.atan2(major[1], major[0]))))


def _quat_xyzw(r: Array) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    t = float(np.trace(r))
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, \
            (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, \
            (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, \
            (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, \
            (r[1, 2] + r[2, 1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (float(x / n), float(y / n), float(z / n), float(w / n))


def ellipsoid(mean3: npt.ArrayLike, cov3: npt.ArrayLike, p: float = P_REGION) -> Ellipsoid:
    """The ``p`` confidence ellipsoid of a 3-D Gaussian.

    Its axes are the eigenvectors of ``cov3`` (one flipped if needed to make a rotation), its
    full lengths ``2 sqrt(χ²₃(p) λᵢ)``.
    """
    c = np.asarray(cov3, dtype=np.float64)
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    lam = np.clip(lam, 0.0, None)
    if np.linalg.det(vec) < 0:
        vec[:, 0] = -vec[:, 0]
    k = chi2_quantile(p, 3)
    sizes = 2.0 * np.sqrt(k * lam)
    m = np.asarray(mean3, dtype=np.float64)
    return Ellipsoid((float(m[0]), float(m[1]), float(m[2])),
                     (float(sizes[0]), float(sizes[1]), float(sizes[2])), _quat_xyzw(vec))


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

    def options_text(self) -> str:
        o = self.options
        parts = [str(o.get(k)) for k in ("method", "space", "analysis") if k in o]
        extra = [f"{k} {o[k]}" for k in ("shrink", "inflation", "gain") if k in o]
        return "/".join(parts) + (", " + ", ".join(extra) if extra else "")


def map_view(smap: StochasticMap, *, map_name: str = "default", seq: int = 0,
             samples: bool = False) -> MapView:
    """A :class:`MapView` of ``smap``: every frame's marginal relative to its component root.

    Parameters
    ----------
    smap : the map (read only)
    samples : also copy every frame's samples ``(N, 7)`` (``smap.query(root, frame)``)
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
    return MapView(map_name, int(seq), dict(smap.options()), list(roots), frames)


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
    rep = replay(path, stop_after=stop_after)
    notes = []
    if rep.divergence is not None:
        notes.append(f"replay diverged from the recording; showing the map as replayed up to "
                     f"there ({rep.divergence})")
    if rep.tail_error is not None:
        notes.append(f"recording is cut short ({rep.tail_error}); showing every complete input")
    st = rep.states.get(name)
    if st is None:
        raise McsmError(f"{path}: map {name!r} has no config record before seq {at_seq}")
    return LoadedMap(st.map, name, st.seq, last_seq, notes)


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
