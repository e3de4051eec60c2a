"""The four real-data sets of the issue-22 benchmark, read into one step-by-step form.

Files from the gtsam wheel's ``Data`` folder (``mcsm_client.datasets.gtsam_data_dir``):

* ``victoria_park.txt``: planar poses and Cartesian landmark sightings, the file's own
  covariances (odometry sigma 0.01 m, 0.002 m, 0.002 rad; sightings sigma 0.632 m per axis).
  No ground truth. Run as a *bounded* map (pose 0 kept as the anchor, every older pose removed).
* ``sphere2500.txt`` (+ ``sphere2500_groundtruth.txt``): a 3-D pose graph, 2500 poses, 2450 loop
  closures; read by :func:`experiments.pose_graph.read_toro3d`, whose docstring shows that the
  file's 21 numbers are square-root information (the data's residuals against the ground truth
  have sigma 0.10 m, 0.010/0.010/0.040 rad). Ground truth: the noise-free file's odometry chain.
* ``T1_city10000_04.txt`` (+ ``ISAM2_GT_city10000.txt``): the city10000 pose graph. The file is
  the one GTSAM's ``City10000.h`` parses: ``EDGE2 i 1 j 0 n x y theta [x y theta ...]`` with
  ``n`` hypotheses per line (200 lines have 2; the first is the measurement, as in GTSAM's
  ``ISAM2_City10000.cpp`` without ambiguity). It holds no noise: we use sigma (0.02 m, 0.02 m,
  0.01 rad), the standard deviation of the file's edges against ``ISAM2_GT_city10000.txt``
  (measured 0.0198, 0.0198, 0.0101 on odometry and loops alike; that file is ground truth, one
  ``x y theta`` line per pose: an optimum would fit the edges tighter). 10000 poses, 9999
  odometry edges, 10688 loop closures.
* ``w10000.graph``: Olson's Manhattan world (TORO ``EDGE2``, later pose first), 10000 poses,
  54312 loop closures, identity information on every edge (sigma 1 m, 1 rad: far larger than the
  data's errors). A sample-based map needs noise that describes the sensor (docs/evaluation.md,
  w100), so every covariance is multiplied by ``W10000_SCALE**2``: chi-square / dof of the file's
  own optimum (2 x 144.87 over 3 x 64311 - 3 x 9999 residual dof) = 0.0422**2. A common scale
  does not move a least-squares optimum, so GTSAM's reference is the file's. No ground truth.

Every set becomes a :class:`Problem`: steps in arrival order, each the edges that arrive with one
new pose (its odometry first, then its sightings or loop closures, in file order). Frame names
in the map: ``x{id}`` for poses, ``l{id}`` for landmarks.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

DATASETS = ("victoria", "sphere2500", "city10000", "w10000")
CITY_SIGMA = np.array([0.02, 0.02, 0.01])
W10000_SCALE = 0.0422


@dataclass(frozen=True)
class Edge:
    """One measurement of pose or landmark ``j`` in the frame of pose ``i`` (``z = x_i⁻¹ x_j``).

    ``mean``: planar pose ``(3,)`` ``dx dy dtheta``; 3-D pose ``(7,)`` ``x y z qw qx qy qz``;
    point ``(2,)``. ``cov``: over GTSAM's body-frame tangent, translation first (``(3, 3)``,
    ``(6, 6)``) or over the point's coordinates (``(2, 2)``).
    """

    kind: str  # "odometry", "loop_closure" or "landmark"
    i: int
    j: int
    mean: Array
    cov: Array

    @property
    def is_point(self) -> bool:
        return self.kind == "landmark"


@dataclass
class Problem:
    """A data set as steps: ``steps[k] = (pose id created at step k, edges arriving with it)``.

    ``steps[0]`` creates the anchor (no odometry; sightings from it, if any). ``truth`` maps a
    pose id to its true pose (planar ``(3,)``, 3-D ``(7,)``) when the data set has ground truth.
    """

    name: str
    dim: int
    steps: list[tuple[int, list[Edge]]]
    bounded: bool
    noise: str
    truth: dict[int, Array] | None = None
    info: dict[str, int] = field(default_factory=dict)

    def edges(self) -> list[Edge]:
        """Every edge in arrival order."""
        return [e for _, es in self.steps for e in es]

    def counts(self) -> dict[str, int]:
        """Poses, landmarks and edges per kind (over the steps kept)."""
        out = {"steps": len(self.steps), "odometry": 0, "loop_closure": 0, "landmark": 0}
        landmarks: set[int] = set()
        for e in self.edges():
            out[e.kind] += 1
            if e.is_point:
                landmarks.add(e.j)
        out["poses"] = len(self.steps)
        out["landmarks"] = len(landmarks)
        return out

    def prefix(self, n_steps: int | None) -> Problem:
        """The first ``n_steps`` steps (all when None)."""
        if n_steps is None or n_steps >= len(self.steps):
            return self
        truth = None if self.truth is None else {
            p: self.truth[p] for p, _ in self.steps[:n_steps] if p in self.truth}
        return Problem(self.name, self.dim, self.steps[:n_steps], self.bounded, self.noise, truth,
                       dict(self.info))


def data_dir() -> Path:
    """The gtsam wheel's ``Data`` folder. Raises FileNotFoundError without gtsam."""
    from mcsm_client.datasets import gtsam_data_dir

    d = gtsam_data_dir()
    if d is None:
        raise FileNotFoundError("the real-data benchmark needs gtsam (pip install 'mcsm[eval]')")
    return d


def _group(edges: list[Edge], first: int) -> list[tuple[int, list[Edge]]]:
    """Steps from edges in arrival order: an edge that brings a pose not seen before opens one."""
    steps: list[tuple[int, list[Edge]]] = [(first, [])]
    seen = {first}
    for e in edges:
        if e.kind == "odometry":
            new = e.j if e.i in seen else e.i
            if new in seen or (e.i not in seen and e.j not in seen):
                raise ValueError(f"odometry edge {e.i}->{e.j} does not extend the trajectory")
            seen.add(new)
            steps.append((new, [e]))
        else:
            steps[-1][1].append(e)
    return steps


def _records(path: Path) -> dict[str, list[list[str]]]:
    """The file's lines split into tokens, grouped by tag, in file order within a tag, plus
    ``"order"``: every kept line's tag (for interleaved tags)."""
    out: dict[str, list[list[str]]] = {"order": []}
    for raw in path.read_text().splitlines():
        t = raw.split()
        if t and not t[0].startswith("#"):
            out.setdefault(t[0], []).append(t)
            out["order"].append([t[0]])
    return out


def _upper3(v: Array) -> Array:
    """(E, 6) upper triangles ``a11 a12 a13 a22 a23 a33`` -> (E, 3, 3) symmetric matrices."""
    m = np.empty((len(v), 3, 3))
    for k, (i, j) in enumerate(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))):
        m[:, i, j] = m[:, j, i] = v[:, k]
    return m


def load_victoria(path: Path | None = None) -> Problem:
    """``victoria_park.txt``: bounded landmark SLAM, the file's covariances (``ODOMETRY i j dx
    dy dtheta`` + 3x3 covariance upper triangle, ``LANDMARK i j dx dy`` + 2x2 upper triangle;
    the format of :func:`mcsm_client.datasets.read_dataset`, read here in bulk)."""
    rec = _records(path or data_dir() / "victoria_park.txt")
    odo = np.array([t[1:] for t in rec["ODOMETRY"]], dtype=np.float64)
    lm = np.array([t[1:] for t in rec["LANDMARK"]], dtype=np.float64)
    odo_cov = _upper3(odo[:, 5:11])
    lm_cov = np.stack([lm[:, [4, 5]], lm[:, [5, 6]]], axis=1)
    edges: list[Edge] = []
    io = il = 0
    seen: set[int] = set()
    for (tag,) in rec["order"]:
        if tag == "ODOMETRY":
            i, j = int(odo[io, 0]), int(odo[io, 1])
            kind = "loop_closure" if (i in seen and j in seen) else "odometry"
            seen.update((i, j))
            edges.append(Edge(kind, i, j, odo[io, 2:5].copy(), odo_cov[io]))
            io += 1
        elif tag == "LANDMARK":
            seen.add(int(lm[il, 0]))
            edges.append(Edge("landmark", int(lm[il, 0]), int(lm[il, 1]), lm[il, 2:4].copy(),
                              lm_cov[il]))
            il += 1
    return Problem("victoria", 2, _group(edges, edges[0].i), True,
                   "file covariances (odometry sigma 0.01/0.002 m, 0.002 rad; sightings 0.632 m)")


def _toro3d(path: Path) -> tuple[npt.NDArray[np.int64], Array, Array]:
    """``EDGE3 i j x y z roll pitch yaw`` + 21 numbers: ids, ``(E, 7)`` measurements
    (``Rz(yaw) Ry(pitch) Rx(roll)``, GTSAM's ``Rot3.Ypr``), ``(E, 6, 6)`` covariances
    ``diag(1 / diag**2)`` (the 21 numbers are square-root information, see
    :func:`experiments.pose_graph.read_toro3d`, which this reads the same in bulk)."""
    from experiments.posegraph_sim import qmul

    v = np.array([t[1:] for t in _records(path)["EDGE3"]], dtype=np.float64)
    half = 0.5 * v[:, 5:8]
    zero = np.zeros(len(v))
    qx = np.stack([np.cos(half[:, 0]), np.sin(half[:, 0]), zero, zero], -1)
    qy = np.stack([np.cos(half[:, 1]), zero, np.sin(half[:, 1]), zero], -1)
    qz = np.stack([np.cos(half[:, 2]), zero, zero, np.sin(half[:, 2])], -1)
    z = np.concatenate([v[:, 2:5], qmul(qmul(qz, qy), qx)], axis=1)
    diag = v[:, 8:29][:, [0, 6, 11, 15, 18, 20]]
    covs = np.zeros((len(v), 6, 6))
    covs[:, np.arange(6), np.arange(6)] = 1.0 / diag**2
    return v[:, :2].astype(np.int64), z, covs


def load_sphere2500(path: Path | None = None) -> Problem:
    """``sphere2500.txt``: 3-D pose graph, ground truth from the noise-free file's odometry."""
    from experiments.posegraph_sim import compose

    d = data_dir() if path is None else path.parent
    ij, z, covs = _toro3d(path or d / "sphere2500.txt")
    order = np.lexsort((ij[:, 1] - ij[:, 0] != 1, ij.max(axis=1)))  # arrival order
    edges: list[Edge] = []
    seen: set[int] = set()
    for k in order:
        i, j = int(ij[k, 0]), int(ij[k, 1])
        kind = "loop_closure" if (i in seen and j in seen) else "odometry"
        seen.update((i, j))
        edges.append(Edge(kind, i, j, z[k].copy(), covs[k]))
    truth = None
    gt_path = d / "sphere2500_groundtruth.txt"
    if gt_path.is_file():
        ijt, zt, _ = _toro3d(gt_path)
        by_j = {int(j): zt[k] for k, (i, j) in enumerate(ijt) if j == i + 1}
        truth = {0: np.array([0, 0, 0, 1.0, 0, 0, 0])}
        for j in range(1, int(ij.max()) + 1):
            truth[j] = compose(truth[j - 1], by_j[j])
    return Problem("sphere2500", 3, _group(edges, 0), False,
                   "sqrt-information read as 1/sigma (0.10 m; 0.010, 0.010, 0.040 rad)", truth)


def parse_city10000(lines: list[str], sigma: Array = CITY_SIGMA) -> list[Edge]:
    """Edges of ``T1_city10000_04.txt``-format text (first hypothesis of each line)."""
    cov = np.diag(np.asarray(sigma, dtype=np.float64) ** 2)
    seen: set[int] = set()
    out: list[Edge] = []
    for n, raw in enumerate(lines, start=1):
        t = raw.split()
        if not t:
            continue
        if t[0] != "EDGE2" or len(t) < 9:
            raise ValueError(f"city10000 line {n}: expected 'EDGE2 i _ j _ n x y theta ...'")
        i, j, hyp = int(t[1]), int(t[3]), int(t[5])
        if hyp < 1 or len(t) < 6 + 3 * hyp:
            raise ValueError(f"city10000 line {n}: {hyp} hypotheses announced, fewer given")
        kind = "loop_closure" if (i in seen and j in seen) else "odometry"
        seen.update((i, j))
        out.append(Edge(kind, i, j, np.array([float(v) for v in t[6:9]]), cov.copy()))
    return out


def load_city10000(path: Path | None = None) -> Problem:
    """``T1_city10000_04.txt`` with ``ISAM2_GT_city10000.txt`` as ground truth."""
    d = data_dir() if path is None else path.parent
    edges = parse_city10000((path or d / "T1_city10000_04.txt").read_text().splitlines())
    truth = None
    gt_path = d / "ISAM2_GT_city10000.txt"
    if gt_path.is_file():
        gt = np.loadtxt(gt_path)
        truth = {k: gt[k].copy() for k in range(len(gt))}
    return Problem("city10000", 2, _group(edges, edges[0].i), False,
                   "none in the file; sigma (0.02 m, 0.02 m, 0.01 rad) measured against the "
                   "ground truth", truth)


def load_w10000(path: Path | None = None) -> Problem:
    """``w10000.graph`` (TORO ``EDGE2 i j dx dy dtheta`` + information ``xx xy yy tt xt yt``;
    ``EQUIV`` and ``VERTEX2`` lines skipped) with every covariance scaled by
    ``W10000_SCALE**2``."""
    rec = _records(path or data_dir() / "w10000.graph")
    e2 = np.array([t[1:] for t in rec["EDGE2"]], dtype=np.float64)
    xx, xy, yy, tt, xt, yt = e2[:, 5:11].T
    info = np.stack([np.stack([xx, xy, xt], -1), np.stack([xy, yy, yt], -1),
                     np.stack([xt, yt, tt], -1)], axis=1)
    covs = np.linalg.inv(info) * W10000_SCALE**2
    edges: list[Edge] = []
    seen: set[int] = set()
    for k in range(len(e2)):
        i, j = int(e2[k, 0]), int(e2[k, 1])
        kind = "loop_closure" if (i in seen and j in seen) else "odometry"
        seen.update((i, j))
        edges.append(Edge(kind, i, j, e2[k, 2:5].copy(), covs[k]))
    first = min(edges[0].i, edges[0].j)
    p = Problem("w10000", 2, _group(edges, first), False,
                f"file's identity information x {W10000_SCALE}^2 (chi2/dof of its optimum)")
    p.info["equiv_skipped"] = len(rec.get("EQUIV", []))
    return p


def load(name: str) -> Problem:
    """One of :data:`DATASETS`."""
    loaders = {"victoria": load_victoria, "sphere2500": load_sphere2500,
               "city10000": load_city10000, "w10000": load_w10000}
    if name not in loaders:
        raise ValueError(f"unknown dataset {name!r}; choose from {DATASETS}")
    return loaders[name]()


# ------------------------------------------------------------------------- pose helpers
def planar_compose(a: Array, b: Array) -> Array:
    """``a ⊕ b`` for planar poses ``(..., 3)``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([a[..., 0] + c * b[..., 0] - s * b[..., 1],
                     a[..., 1] + s * b[..., 0] + c * b[..., 1], a[..., 2] + b[..., 2]], axis=-1)


def planar_inverse(a: Array) -> Array:
    """``a⁻¹`` for planar poses ``(..., 3)``."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], -a[..., 2]],
                    axis=-1)


def dead_reckoning(problem: Problem) -> tuple[dict[int, Array], dict[int, Array]]:
    """Poses by composing odometry, landmarks from their first sighting (planar ``(3,)`` or 3-D
    ``(7,)`` poses; landmark ``(2,)``)."""
    from experiments.posegraph_sim import compose, invert

    ident = np.zeros(3) if problem.dim == 2 else np.array([0, 0, 0, 1.0, 0, 0, 0])
    poses: dict[int, Array] = {problem.steps[0][0]: ident}
    lms: dict[int, Array] = {}
    for pose, es in problem.steps:
        for e in es:
            if e.kind == "odometry":
                if problem.dim == 2:
                    poses[pose] = (planar_compose(poses[e.i], e.mean) if e.j == pose
                                   else planar_compose(poses[e.j], planar_inverse(e.mean)))
                else:
                    poses[pose] = (compose(poses[e.i], e.mean) if e.j == pose
                                   else compose(poses[e.j], invert(e.mean)))
            elif e.is_point and e.j not in lms:
                p = poses[e.i]
                c, s = np.cos(p[2]), np.sin(p[2])
                lms[e.j] = p[:2] + np.array([c * e.mean[0] - s * e.mean[1],
                                             s * e.mean[0] + c * e.mean[1]])
    return poses, lms
