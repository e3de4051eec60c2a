"""Readers for public pose-graph datasets, into one ordered list of constraints.

Formats (each line one record; unknown tags are counted and skipped):

* g2o 2D: ``VERTEX_SE2 id x y theta``, ``EDGE_SE2 i j dx dy dtheta`` + 6 noise numbers, and the
  iSAM-style point edge ``LANDMARK2 i j dx dy`` + 3 noise numbers.
* g2o 3D: ``VERTEX_SE3:QUAT id x y z qx qy qz qw``,
  ``EDGE_SE3:QUAT i j x y z qx qy qz qw`` + 21 information numbers (translation first).
* TORO ``.graph`` 2D: ``VERTEX2 id x y theta``, ``EDGE2 i j dx dy dtheta`` + 6 information
  numbers in TORO order ``xx xy yy tt xt yt``; ``EQUIV`` lines are ignored.
* GTSAM's Victoria Park text: ``ODOMETRY i j dx dy dtheta`` + 3x3 covariance upper triangle,
  ``LANDMARK i j dx dy`` + 2x2 covariance upper triangle (Cartesian, not bearing/range).

Noise conventions follow the datasets' own documentation (checked against the data by the chi2
test in ``tests/clients/test_datasets_gtsam.py``). "Upper triangle" means the entries of a
symmetric (or, for square-root information, upper-triangular) matrix written row by row. The
iSAM-style files that contain ``LANDMARK2`` (``victoriaPark_reduced_1k.g2o``,
``cityTrees_reduced_1k.g2o``) hold the upper-triangular *square-root information* ``R``
(information ``RᵀR``) on both ``EDGE_SE2`` and ``LANDMARK2``, not g2o's information matrix;
``read_g2o(noise="auto")`` detects them by that tag.

``EDGE_SE3:QUAT`` information is read over the rotation *vector* (GTSAM's reading). g2o itself
defines the rotation error as the quaternion's vector part (about half the rotation vector),
which would make the rotation information four times smaller; on ``pose3example-grid.txt`` the
GTSAM reading gives chi2/dof 0.81 at the optimum and the strict g2o reading 0.30, so the files
shipped with GTSAM follow GTSAM's. TORO 3D (``EDGE3``/``VERTEX3``) is not read.

Measurement convention everywhere: an edge ``i j z`` measures pose (or point) ``j`` in the frame
of pose ``i``, ``z = x_i⁻¹ x_j`` (GTSAM's ``BetweenFactor(i, j, z)``). A pose covariance is over
the tangent vector ``[t, r]`` of a *right* (body-frame) perturbation of the measurement:
``z_true = z ⊕ Exp(δ)``, translation first, as GTSAM and g2o use it. The sampling helpers take
it with ``translation_frame="body"`` (``mcsm_client.sampling``).

Each constraint is classified while reading, in file order: an edge that brings in a pose not
seen in any earlier edge is ``"odometry"``, an edge between two poses already seen is a
``"loop_closure"``, a point edge is a ``"landmark"`` observation (first sighting or not).
"""

from __future__ import annotations

import importlib.util
import math
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]
ConstraintKind = Literal["odometry", "loop_closure", "landmark"]
NoiseFormat = Literal["information", "sqrt_information", "covariance"]

__all__ = [
    "Constraint",
    "Dataset",
    "DatasetError",
    "gtsam_data_dir",
    "parse_dataset",
    "read_dataset",
    "resolve_dataset_path",
]


class DatasetError(ValueError):
    """A dataset line cannot be read: the message names the source, line number and reason."""

    def __init__(self, source: str, line: int, reason: str) -> None:
        super().__init__(f"{source}:{line}: {reason}")
        self.source = source
        self.line = line
        self.reason = reason


@dataclass(frozen=True)
class Constraint:
    """One measurement of pose or point ``target`` in the frame of pose ``source``.

    Attributes
    ----------
    kind : {"odometry", "loop_closure", "landmark"}
    source, target : int
        Dataset ids (poses and landmarks may share one id space or not; see ``Dataset``).
    mean : (3,) or (7,) or (2,) or (3,) float64
        Planar pose ``[dx, dy, dtheta]`` (m, m, rad); 3D pose ``[x, y, z, qw, qx, qy, qz]``
        (scalar-first unit quaternion, our AT layout); point ``[x, y]`` or ``[x, y, z]`` (m).
    cov : (3, 3) or (6, 6) or (2, 2) or (3, 3) float64
        Covariance. For poses over the body-frame tangent ``[tx, ty, (tz,) (rx, ry,) rz]``
        (translation first); for points over the point coordinates.
    line : int
        1-based line number in the source, for error messages.
    """

    kind: ConstraintKind
    source: int
    target: int
    mean: Array
    cov: Array
    line: int = 0

    @property
    def is_point(self) -> bool:
        """True for a landmark (point) observation."""
        return self.kind == "landmark"


@dataclass
class Dataset:
    """A dataset read into memory: constraints in file order, plus initial guesses if given.

    Attributes
    ----------
    name : str
        File name or ``"<text>"``.
    dim : int
        2 (planar) or 3.
    constraints : list of Constraint
        In file order.
    initial : dict of int to ndarray
        ``VERTEX*`` lines: initial pose guesses (planar ``[x, y, theta]`` or 3D
        ``[x, y, z, qw, qx, qy, qz]``). Not constraints; players ignore them.
    skipped : dict of str to int
        Count of lines skipped per unknown or ignored tag (``EQUIV``, ``BR``, ...).
    noise : str
        The noise conventions the records were read with (``"covariance"``,
        ``"information"``, ``"sqrt_information"``, ``"toro_information"``; joined by ``+``).
    """

    name: str
    dim: int
    constraints: list[Constraint] = field(default_factory=list)
    initial: dict[int, Array] = field(default_factory=dict)
    skipped: dict[str, int] = field(default_factory=dict)
    noise: str = ""

    def counts(self) -> dict[str, int]:
        """Number of constraints per kind, plus ``poses`` and ``landmarks`` (distinct ids)."""
        out = {"odometry": 0, "loop_closure": 0, "landmark": 0}
        poses: set[int] = set()
        landmarks: set[int] = set()
        for c in self.constraints:
            out[c.kind] += 1
            poses.add(c.source)
            (landmarks if c.is_point else poses).add(c.target)
        out["poses"] = len(poses)
        out["landmarks"] = len(landmarks)
        return out

    def pose_ids(self) -> list[int]:
        """Pose ids in order of first appearance."""
        seen: dict[int, None] = {}
        for c in self.constraints:
            seen.setdefault(c.source)
            if not c.is_point:
                seen.setdefault(c.target)
        return list(seen)

    def landmark_ids(self) -> list[int]:
        """Landmark ids in order of first sighting."""
        seen: dict[int, None] = {}
        for c in self.constraints:
            if c.is_point:
                seen.setdefault(c.target)
        return list(seen)


# ----------------------------------------------------------------------------- noise matrices

def _upper_to_full(values: Array, n: int, *, symmetric: bool) -> Array:
    """Matrix from its upper triangle written row by row (``a11 a12 .. a1n a22 .. ann``)."""
    m = np.zeros((n, n))
    m[np.triu_indices(n)] = values
    if symmetric:
        m = m + np.triu(m, 1).T
    return m


def _noise_to_cov(values: Array, n: int, noise: NoiseFormat) -> Array:
    """Covariance from an upper triangle given as information, sqrt-information or covariance.

    Raises
    ------
    ValueError
        If the matrix is not symmetric positive definite (or R is singular).
    """
    if noise == "covariance":
        cov = _upper_to_full(values, n, symmetric=True)
    elif noise == "information":
        cov = _spd_inverse(_upper_to_full(values, n, symmetric=True))
    elif noise == "sqrt_information":
        r = _upper_to_full(values, n, symmetric=False)
        cov = _spd_inverse(r.T @ r)
    else:  # pragma: no cover - guarded by the typed API
        raise ValueError(f"unknown noise format {noise!r}")
    sym: Array = 0.5 * (cov + cov.T)
    _check_spd(sym)
    return sym


def _spd_inverse(m: Array) -> Array:
    _check_spd(m)
    return np.asarray(np.linalg.inv(m), dtype=np.float64)


def _check_spd(m: Array) -> None:
    if not np.all(np.isfinite(m)):
        raise ValueError("noise matrix is not finite")
    try:
        np.linalg.cholesky(0.5 * (m + m.T))
    except np.linalg.LinAlgError:
        raise ValueError("noise matrix is not positive definite") from None


def _toro_info_to_cov(values: Array) -> Array:
    """TORO ``EDGE2`` information ``xx xy yy tt xt yt`` to a (3, 3) covariance."""
    xx, xy, yy, tt, xt, yt = values
    info = np.array([[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]], dtype=np.float64)
    return _spd_inverse(info)


def _quat_xyzw_to_wxyz(q: Array) -> Array:
    n = float(np.linalg.norm(q))
    if not math.isfinite(n) or n < 1e-9:
        raise ValueError("zero or non-finite quaternion")
    x, y, z, w = q / n
    out = np.array([w, x, y, z], dtype=np.float64)
    return out if w >= 0.0 else -out


# ----------------------------------------------------------------------------- parsing

_TAG_FORMAT = {
    "VERTEX_SE2": "g2o",
    "EDGE_SE2": "g2o",
    "LANDMARK2": "g2o",
    "VERTEX_SE3:QUAT": "g2o",
    "EDGE_SE3:QUAT": "g2o",
    "VERTEX2": "toro",
    "EDGE2": "toro",
    "EQUIV": "toro",
    "ODOMETRY": "victoria",
    "LANDMARK": "victoria",
}


class _Builder:
    """Accumulates constraints and classifies pose edges as odometry or loop closure."""

    def __init__(self, name: str, noise: str) -> None:
        self.ds = Dataset(name=name, dim=0, noise=noise)
        self.seen_poses: set[int] = set()
        self.used: set[str] = set()

    def set_dim(self, dim: int, line: int) -> None:
        if self.ds.dim == 0:
            self.ds.dim = dim
        elif self.ds.dim != dim:
            raise DatasetError(self.ds.name, line, "mixes planar and 3D records")

    def pose_edge(self, i: int, j: int, mean: Array, cov: Array, line: int) -> None:
        if i == j:
            raise DatasetError(self.ds.name, line, f"edge from pose {i} to itself")
        # A pose never seen in an earlier edge extends the trajectory; the first edge of the
        # file (both ends new) is odometry too.
        new = (i not in self.seen_poses) or (j not in self.seen_poses)
        kind: ConstraintKind = "odometry" if new else "loop_closure"
        self.seen_poses.update((i, j))
        self.ds.constraints.append(Constraint(kind, i, j, mean, cov, line))

    def point_edge(self, i: int, j: int, mean: Array, cov: Array, line: int) -> None:
        self.seen_poses.add(i)
        self.ds.constraints.append(Constraint("landmark", i, j, mean, cov, line))

    def skip(self, tag: str) -> None:
        self.ds.skipped[tag] = self.ds.skipped.get(tag, 0) + 1


def _numbers(name: str, line: int, tokens: list[str], count: int) -> Array:
    if len(tokens) < count:
        raise DatasetError(name, line, f"expected {count} numbers after the tag, got {len(tokens)}")
    try:
        vals = np.array([float(t) for t in tokens[:count]], dtype=np.float64)
    except ValueError as exc:
        raise DatasetError(name, line, f"not a number: {exc}") from None
    if not np.all(np.isfinite(vals)):
        raise DatasetError(name, line, "non-finite number")
    return vals


def _ids(name: str, line: int, tokens: list[str], count: int) -> list[int]:
    try:
        return [int(t) for t in tokens[:count]]
    except ValueError:
        raise DatasetError(name, line, f"expected {count} integer ids") from None


def _detect_format(lines: list[str]) -> str:
    for raw in lines:
        tok = raw.split(maxsplit=1)
        if tok and tok[0] in _TAG_FORMAT:
            return _TAG_FORMAT[tok[0]]
    raise ValueError("cannot recognise the dataset format from its tags")


def parse_dataset(
    lines: Iterable[str],
    *,
    fmt: Literal["auto", "g2o", "toro", "victoria"] = "auto",
    noise: Literal["auto"] | NoiseFormat = "auto",
    name: str = "<text>",
    max_lines: int | None = None,
) -> Dataset:
    """Parse dataset text into a :class:`Dataset`.

    Parameters
    ----------
    lines : iterable of str
        The file's lines (or any text split into lines).
    fmt : {"auto", "g2o", "toro", "victoria"}
        Line format; ``"auto"`` checks that some tag is known. The formats share one parser
        (tags do not collide), so a file may mix tags of one dimension.
    noise : {"auto", "information", "sqrt_information", "covariance"}
        How to read the noise numbers of ``EDGE_SE2``/``EDGE_SE3:QUAT``/``LANDMARK2``.
        ``"auto"``: square-root information when the text has a ``LANDMARK2`` record (iSAM
        files), otherwise g2o's information. ``ODOMETRY``/``LANDMARK`` are always covariances
        and ``EDGE2`` always TORO information, whatever this says.
    name : str
        Used in error messages and as ``Dataset.name``.
    max_lines : int, optional
        Parse only this many lines (a prefix of a long file); the noise convention is still
        detected from the whole text.

    Returns
    -------
    Dataset

    Raises
    ------
    DatasetError
        On a malformed line (too few numbers, non-finite values, a noise matrix that is not
        positive definite, a zero quaternion), naming the line.
    """
    everything = list(lines)
    text = everything[:max_lines] if max_lines is not None else everything
    if fmt == "auto":
        fmt = _detect_format(text)  # type: ignore[assignment]
    if noise == "auto":
        # Decide from the whole text, so that a prefix reads with the file's convention.
        has_lm2 = any(raw.lstrip().startswith("LANDMARK2") for raw in everything)
        edge_noise: NoiseFormat = "sqrt_information" if has_lm2 else "information"
    else:
        edge_noise = noise
    b = _Builder(name, edge_noise)
    for lineno, raw in enumerate(text, start=1):
        tokens = raw.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        tag, rest = tokens[0], tokens[1:]
        try:
            _parse_record(b, tag, rest, lineno, edge_noise)
        except DatasetError:
            raise
        except ValueError as exc:
            raise DatasetError(name, lineno, f"{tag}: {exc}") from None
    if b.ds.dim == 0:
        b.ds.dim = 2
    if b.used:
        b.ds.noise = "+".join(sorted(b.used))
    return b.ds


def _parse_record(b: _Builder, tag: str, rest: list[str], lineno: int, edge_noise: NoiseFormat
                  ) -> None:
    name = b.ds.name
    if tag in ("VERTEX_SE2", "VERTEX2"):
        b.set_dim(2, lineno)
        (vid,) = _ids(name, lineno, rest, 1)
        b.ds.initial[vid] = _numbers(name, lineno, rest[1:], 3)
    elif tag == "VERTEX_SE3:QUAT":
        b.set_dim(3, lineno)
        (vid,) = _ids(name, lineno, rest, 1)
        v = _numbers(name, lineno, rest[1:], 7)
        b.ds.initial[vid] = np.concatenate([v[:3], _quat_xyzw_to_wxyz(v[3:7])])
    elif tag in ("EDGE_SE2", "ODOMETRY", "EDGE2"):
        b.set_dim(2, lineno)
        i, j = _ids(name, lineno, rest, 2)
        v = _numbers(name, lineno, rest[2:], 9)
        if tag == "ODOMETRY":
            cov = _noise_to_cov(v[3:], 3, "covariance")
            b.used.add("covariance")
        elif tag == "EDGE2":
            cov = _toro_info_to_cov(v[3:])
            b.used.add("toro_information")
        else:
            cov = _noise_to_cov(v[3:], 3, edge_noise)
            b.used.add(edge_noise)
        b.pose_edge(i, j, v[:3].copy(), cov, lineno)
    elif tag in ("LANDMARK2", "LANDMARK"):
        b.set_dim(2, lineno)
        i, j = _ids(name, lineno, rest, 2)
        v = _numbers(name, lineno, rest[2:], 5)
        fmt: NoiseFormat = "covariance" if tag == "LANDMARK" else edge_noise
        b.used.add(fmt)
        b.point_edge(i, j, v[:2].copy(), _noise_to_cov(v[2:], 2, fmt), lineno)
    elif tag == "EDGE_SE3:QUAT":
        b.set_dim(3, lineno)
        i, j = _ids(name, lineno, rest, 2)
        v = _numbers(name, lineno, rest[2:], 28)
        mean = np.concatenate([v[:3], _quat_xyzw_to_wxyz(v[3:7])])
        b.used.add(edge_noise)
        b.pose_edge(i, j, mean, _noise_to_cov(v[7:], 6, edge_noise), lineno)
    else:
        b.skip(tag)


def read_dataset(
    path: str | os.PathLike[str],
    *,
    fmt: Literal["auto", "g2o", "toro", "victoria"] = "auto",
    noise: Literal["auto"] | NoiseFormat = "auto",
    max_lines: int | None = None,
) -> Dataset:
    """Read a dataset file (see :func:`parse_dataset` for the parameters).

    Parameters
    ----------
    path : path-like
        A file, or ``gtsam:NAME`` for a file shipped in the installed gtsam wheel's ``Data``
        folder (see :func:`resolve_dataset_path`).

    Returns
    -------
    Dataset

    Raises
    ------
    FileNotFoundError
        If the file does not exist (or gtsam is not installed for a ``gtsam:`` name).
    DatasetError
        On a malformed line.
    """
    p = resolve_dataset_path(path)
    with open(p, encoding="utf-8", errors="strict") as f:
        return parse_dataset(f, fmt=fmt, noise=noise, name=p.name, max_lines=max_lines)


def gtsam_data_dir() -> Path | None:
    """The ``Data`` folder of the installed gtsam wheel (optional ``eval`` extra), or None.

    Found without importing gtsam.
    """
    spec = importlib.util.find_spec("gtsam")
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        d = Path(loc) / "Data"
        if d.is_dir():
            return d
    return None


def resolve_dataset_path(path: str | os.PathLike[str]) -> Path:
    """Turn ``gtsam:NAME`` into a path in gtsam's data folder; other paths pass through.

    Raises
    ------
    FileNotFoundError
        If the file does not exist.
    """
    s = os.fspath(path)
    if s.startswith("gtsam:"):
        d = gtsam_data_dir()
        if d is None:
            raise FileNotFoundError(
                f"{s}: gtsam is not installed (pip install 'mcsm[eval]' provides its data files)")
        p = d / s.removeprefix("gtsam:")
    else:
        p = Path(s)
    if not p.is_file():
        raise FileNotFoundError(f"no such dataset file: {p}")
    return p


def iter_kind(ds: Dataset, kind: ConstraintKind) -> Iterator[Constraint]:
    """The constraints of one kind, in file order."""
    return (c for c in ds.constraints if c.kind == kind)
