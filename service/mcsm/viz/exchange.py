"""A recorded map in the formats other tools read: g2o pose graphs and TUM trajectories.

``mcsm export g2o FILE.mcap`` and ``mcsm export tum FILE.mcap`` replay the recording once
(``mcsm.log.replay.replay``, with its checks) and collect, for one map:

* the map at the end: every frame's mean relative to its component's root (the vertices, and
  the trajectories' poses);
* every constraint the map holds: each recorded update whose verdict is ``accepted`` or
  ``reinstated`` at the end (the gate's rejections, retracted and still-pending updates are
  left out and counted), as its observation's sample mean and covariance;
* when each pose frame was made (the creating update's ``stamp_ns``, else its receive time),
  and the robot paths of :mod:`mcsm.viz.layout`.

**Covariances in the convention g2o files use (and GTSAM reads).** An observation's
covariance is taken from its samples over the body-frame (right) perturbation
``x = x̄ ⊕ δ``: translation ``R̄ᵀ (t − t̄)`` and rotation ``log(q̄⁻¹ q)``, the error GTSAM's
``BetweenFactor`` and g2o's ``EdgeSE2`` use; the information matrix is its inverse (its
eigenvalues below :data:`MIN_VARIANCE` are raised to it, so a noise-free constraint stays
finite). In
``EDGE_SE3:QUAT`` the 21 numbers are the upper triangle over (translation, rotation vector),
which is how GTSAM's ``readG2o`` reads them; g2o's own ``EdgeSE3`` measures rotation by the
quaternion's vector part (about half the angle), so in g2o itself rotations weigh a quarter.

**Point landmarks.** 3-D: ``VERTEX_TRACKXYZ`` and g2o's ``EDGE_SE3_TRACKXYZ`` (with the
identity ``PARAMS_SE3OFFSET 0``), which GTSAM 4.3 reads as a bearing-range factor. Planar:
``VERTEX_XY`` and g2o's ``EDGE_SE2_XY``, which GTSAM's ``readG2o`` does not read (it keeps the
vertices and drops those edges); ``landmarks="br"`` writes them as GTSAM's own ``BR`` lines
instead (bearing, range and their standard deviations, first order; the bearing-range
correlation is dropped).

g2o vertices have integer ids: ``OUT.frames.csv`` names them (``id,frame,kind,component``);
the g2o file itself carries no comment (GTSAM's planar reader stops at one).

A frame removed from the map (a bounded run keeps the first and the current pose) has no
mean: constraints that name one are left out and counted. Components are unrelated: each one's
vertices are in its own root frame (a g2o graph with several connected parts).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import numpy as np
import numpy.typing as npt

from mcsm.core.at import mean_and_cov
from mcsm.core.quat import qconj, qlog, qmul, qrot
from mcsm.errors import McsmError
from mcsm.viz.scene import MapView, ReplaySink, choose_map, is_planar, map_view, recording_maps

Array = npt.NDArray[np.float64]

#: the smallest variance written (m², rad²): a noise-free constraint gets σ = 1 µm / 1 µrad
MIN_VARIANCE = 1e-12
#: verdicts whose constraints the map holds
HELD = ("accepted", "reinstated")


@dataclass
class Constraint:
    """One recorded update: ``a -> b`` (a point ``b`` seen from ``a`` when ``point``)."""

    request_id: str
    a: str
    b: str
    point: bool
    mean: Array  # (7,) x y z qw qx qy qz, or (3,) for a point
    cov: Array  # (6, 6) over body-frame [t, rotvec], or (3, 3) for a point
    seq: int
    status: str = "accepted"


@dataclass
class Collected:
    """What one replay of a recording gives the exporters."""

    view: MapView
    constraints: list[Constraint]
    made_ns: dict[str, int]  # frame -> when it was made (stamp_ns, else receive time)
    notes: list[str] = field(default_factory=list)

    @property
    def planar(self) -> bool:
        return is_planar(self.view) and all(_planar_constraint(c) for c in self.constraints)


def body_frame_cov(samples: npt.ArrayLike) -> tuple[Array, Array]:
    """Mean ``(7,)`` and covariance ``(6, 6)`` of an AT over the body-frame perturbation
    (translation ``R̄ᵀ (t − t̄)``, rotation ``log(q̄⁻¹ q)``): the module docstring's
    convention. (:func:`mcsm.core.at.mean_and_cov` has the same mean and rotation block; its
    translation deviations are in the parent frame.)"""
    x = np.asarray(samples, dtype=np.float64)
    mean, _ = mean_and_cov(x)
    q_inv = qconj(mean[3:7])[None, :]
    v = np.concatenate([qrot(q_inv, x[:, :3] - mean[:3]), qlog(qmul(q_inv, x[:, 3:]))],
                       axis=1)
    v -= v.mean(axis=0)
    return mean, np.asarray((v.T @ v) / max(len(v) - 1, 1), dtype=np.float64)


def _planar_constraint(c: Constraint) -> bool:
    tol = 1e-9
    if c.point:
        return abs(float(c.mean[2])) <= tol and float(c.cov[2, 2]) <= tol * tol
    return (abs(float(c.mean[2])) <= tol and abs(float(c.mean[4])) <= tol
            and abs(float(c.mean[5])) <= tol and float(c.cov[2, 2]) <= tol * tol
            and float(c.cov[3, 3]) <= tol * tol and float(c.cov[4, 4]) <= tol * tol)


def information(cov: npt.ArrayLike) -> Array:
    """The information matrix of a covariance whose eigenvalues (variances along its
    principal axes) are floored at :data:`MIN_VARIANCE`."""
    c = np.asarray(cov, dtype=np.float64)
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    lam = np.maximum(lam, MIN_VARIANCE)
    return np.asarray((vec / lam) @ vec.T, dtype=np.float64)


class _CollectSink(ReplaySink):
    """Replay's sink: every update's observation and verdict, each frame's making time."""

    def __init__(self, map_name: str) -> None:
        super().__init__(map_name)
        self.constraints: dict[str, Constraint] = {}
        self.made_ns: dict[str, int] = {}
        self.skipped_undecodable = 0

    def input(self, op: str, map_name: str, seq: int, recv_ns: int, _sender: str = "",
              _request_id: str = "", request: bytes = b"") -> None:
        if map_name == self.map_name and self.state is not None:
            before = set(self.history.parent)
            super().input(op, map_name, seq, recv_ns, _sender, _request_id, request)
            if op == "update":
                self._update(seq, recv_ns, request, before)
            for rid, v in (self.state.last_changed or {}).items():
                if rid in self.constraints:
                    self.constraints[rid].status = v.status

    def _update(self, seq: int, recv_ns: int, request: bytes, before: set[str]) -> None:
        from mcsm.log.topics import decode_input

        st = self.state
        try:
            req = decode_input("update", request, st.n_samples)
        except McsmError:
            self.skipped_undecodable += 1
            return
        when = int(req.stamp_ns) if req.stamp_ns is not None else int(recv_ns)
        for f in set(self.history.parent) - before:
            self.made_ns.setdefault(f, when)
        for f in (req.a, req.b):
            self.made_ns.setdefault(f, when)  # a new component's root
        x = np.asarray(req.samples, dtype=np.float64)
        if x.shape[1] == 3:
            mean = x.mean(axis=0)
            d = x - mean
            cov = (d.T @ d) / max(len(d) - 1, 1)
        else:
            mean, cov = body_frame_cov(x)
        try:
            status = st.verdict_of(req.request_id).verdict
        except McsmError:
            status = None
        self.constraints[req.request_id] = Constraint(
            req.request_id, req.a, req.b, x.shape[1] == 3, mean, cov, seq,
            status.status if status is not None else "accepted")


def collect(path: str | os.PathLike[str], map_name: str | None = None) -> Collected:
    """Replay ``path`` once and gather one map's constraints and final means.

    Raises
    ------
    McsmError
        Unreadable recording (``RecordingError``) or unknown map.
    """
    from mcsm.log.replay import replay

    counts = recording_maps(path)
    name = choose_map(list(counts), map_name, str(path))
    sink = _CollectSink(name)
    rep = replay(path, sink=cast(Any, sink))
    st = rep.states.get(name)
    if st is None:
        raise McsmError(f"{path}: map {name!r} has no config record")
    notes = []
    if rep.divergence is not None:
        notes.append(f"replay diverged from the recording; exported the map as replayed up "
                     f"to there ({rep.divergence})")
    if rep.tail_error is not None:
        notes.append(f"recording is cut short ({rep.tail_error}); exported every complete "
                     "input")
    if sink.skipped_undecodable:
        notes.append(f"{sink.skipped_undecodable} updates did not decode and were left out")
    view = map_view(st.map, map_name=name, seq=st.seq, parents=sink.history.parent)
    return Collected(view, list(sink.constraints.values()), sink.made_ns, notes)


# --------------------------------------------------------------------------------------------
# g2o
# --------------------------------------------------------------------------------------------

@dataclass
class G2oReport:
    path: Path
    planar: bool  # SE2 types (else SE3)
    vertices: int = 0
    landmarks: int = 0
    edges: int = 0
    landmark_edges: int = 0
    not_held: dict[str, int] = field(default_factory=dict)  # verdict -> constraints left out
    removed_frames: int = 0  # constraints naming a frame no longer in the map
    notes: list[str] = field(default_factory=list)


def _num(x: float) -> str:
    return repr(float(x))


def _upper(m: Array) -> list[str]:
    return [_num(m[i, j]) for i in range(len(m)) for j in range(i, len(m))]


def _yaw(q_wxyz: Array) -> float:
    w, x, y, z = (float(v) for v in q_wxyz)
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def write_g2o(data: Collected, out: str | os.PathLike[str],
              landmarks: Literal["g2o", "br"] = "g2o") -> G2oReport:
    """Write ``data`` as a g2o file (module docstring); returns what was written."""
    mv = data.view
    planar = data.planar
    rep = G2oReport(Path(out), planar)
    ids = {f.name: i for i, f in enumerate(mv.frames)}
    lines: list[str] = []  # no comments: GTSAM's planar reader stops at a '#' line
    names = ["id,frame,kind,component"]
    if not planar:
        lines.append("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1")
    for f in mv.frames:
        i = ids[f.name]
        names.append(f"{i},{f.name},{'landmark' if f.is_point else 'pose'},{f.component}")
        p = f.mean
        if f.is_point:
            rep.landmarks += 1
            lines.append(f"VERTEX_XY {i} {_num(p[0])} {_num(p[1])}" if planar else
                         f"VERTEX_TRACKXYZ {i} {_num(p[0])} {_num(p[1])} {_num(p[2])}")
        elif planar:
            lines.append(f"VERTEX_SE2 {i} {_num(p[0])} {_num(p[1])} {_num(_yaw(p[3:7]))}")
        else:
            lines.append(f"VERTEX_SE3:QUAT {i} {_num(p[0])} {_num(p[1])} {_num(p[2])} "
                         f"{_num(p[4])} {_num(p[5])} {_num(p[6])} {_num(p[3])}")
        rep.vertices += 1
    for c in sorted(data.constraints, key=lambda c: c.seq):
        if c.status not in HELD:
            rep.not_held[c.status] = rep.not_held.get(c.status, 0) + 1
            continue
        if c.a not in ids or c.b not in ids:
            rep.removed_frames += 1
            continue
        i, j = ids[c.a], ids[c.b]
        m = c.mean
        if c.point:
            rep.landmark_edges += 1
            if planar and landmarks == "br":
                lines.append(_bearing_range(i, j, m[:2], c.cov[:2, :2]))
            elif planar:
                info = information(c.cov[:2, :2])
                lines.append(f"EDGE_SE2_XY {i} {j} {_num(m[0])} {_num(m[1])} "
                             + " ".join(_upper(info)))
            else:
                info = information(c.cov)
                lines.append(f"EDGE_SE3_TRACKXYZ {i} {j} 0 {_num(m[0])} {_num(m[1])} "
                             f"{_num(m[2])} " + " ".join(_upper(info)))
        elif planar:
            info = information(c.cov[np.ix_([0, 1, 5], [0, 1, 5])])
            lines.append(f"EDGE_SE2 {i} {j} {_num(m[0])} {_num(m[1])} {_num(_yaw(m[3:7]))} "
                         + " ".join(_upper(info)))
        else:
            info = information(c.cov)
            lines.append(f"EDGE_SE3:QUAT {i} {j} {_num(m[0])} {_num(m[1])} {_num(m[2])} "
                         f"{_num(m[4])} {_num(m[5])} {_num(m[6])} {_num(m[3])} "
                         + " ".join(_upper(info)))
        rep.edges += 1
    if rep.removed_frames:
        rep.notes.append(f"{rep.removed_frames} constraints name frames no longer in the map "
                         "(removed): left out")
    if rep.not_held:
        rep.notes.append("constraints the map does not hold, left out: " + ", ".join(
            f"{n} {k}" for k, n in sorted(rep.not_held.items())))
    if planar and landmarks == "g2o" and rep.landmark_edges:
        rep.notes.append("planar landmark edges are g2o's EDGE_SE2_XY, which GTSAM's readG2o "
                         "skips; --landmarks br writes GTSAM's BR lines instead")
    Path(out).write_text("\n".join(lines) + "\n", encoding="utf-8")
    frames_file(out).write_text("\n".join(names) + "\n", encoding="utf-8")
    return rep


def frames_file(out: str | os.PathLike[str]) -> Path:
    """The CSV beside a g2o file that names its vertex ids: ``OUT.frames.csv``."""
    return Path(f"{out}.frames.csv")


def _bearing_range(i: int, j: int, p: Array, cov: Array) -> str:
    """GTSAM's ``BR i j bearing range sigma_bearing sigma_range`` of a planar point
    observation (first-order propagation of its covariance; correlation dropped)."""
    x, y = float(p[0]), float(p[1])
    r = math.hypot(x, y)
    if r <= 0.0:
        raise McsmError(f"landmark {j} is observed at range 0 from {i}: no bearing")
    jac = np.array([[-y / (r * r), x / (r * r)], [x / r, y / r]])
    c = jac @ np.asarray(cov) @ jac.T
    sb, sr = (math.sqrt(max(float(c[k, k]), MIN_VARIANCE)) for k in (0, 1))
    return f"BR {i} {j} {_num(math.atan2(y, x))} {_num(r)} {_num(sb)} {_num(sr)}"


# --------------------------------------------------------------------------------------------
# TUM
# --------------------------------------------------------------------------------------------

@dataclass
class Trajectory:
    robot: str
    path: Path
    poses: list[str]  # the poses written, in time order
    dropped: list[str] = field(default_factory=list)  # poses sharing a time with another


def robot_name(first_pose: str) -> str:
    """A file-name-safe robot name from a path's first pose (its name stem)."""
    from mcsm.viz.layout import name_stem

    stem = name_stem(first_pose).rstrip("._-:/") or first_pose
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", stem)


def tum_paths(data: Collected, prefix: str | os.PathLike[str]) -> list[tuple[str, Path,
                                                                            list[str]]]:
    """``(robot, file, poses)`` of each robot path with at least one pose: files
    ``<prefix>-<robot>.tum`` (``-2``, ... appended when two robots share a name)."""
    out = []
    taken: set[str] = set()
    for root in data.view.components:
        for path in data.view.paths(root):
            robot = robot_name(path[0].name)
            name, k = robot, 2
            while name in taken:
                name, k = f"{robot}-{k}", k + 1
            taken.add(name)
            out.append((name, Path(f"{prefix}-{name}.tum"), [f.name for f in path]))
    return out


def write_tum(data: Collected, prefix: str | os.PathLike[str]) -> list[Trajectory]:
    """One TUM file per robot path: ``t x y z qx qy qz qw`` per line, ``t`` in seconds (the
    time the pose was made: its creating update's ``stamp_ns``, else its receive time), the
    pose's final mean in its component's root frame.

    Times must increase: a component's root is made by the same update as the pose after it
    and has no time of its own, so it is left out when it shares that time (as is any later
    pose that repeats the time before it); :attr:`Trajectory.dropped` names them."""
    frames = {f.name: f for f in data.view.frames}
    roots = set(data.view.components)
    written = []
    for robot, path, poses in tum_paths(data, prefix):
        order = sorted(poses, key=lambda n: (data.made_ns.get(n, 0), poses.index(n)))
        rows: list[str] = []
        dropped: list[str] = []
        for k, n in enumerate(order):
            t = data.made_ns.get(n, 0)
            if rows and data.made_ns.get(rows[-1], 0) == t:
                dropped.append(n)
            elif (n in roots and k + 1 < len(order)
                  and data.made_ns.get(order[k + 1], 0) == t):
                dropped.append(n)
            else:
                rows.append(n)
        lines = []
        for n in rows:
            m = frames[n].mean
            t = int(data.made_ns.get(n, 0))
            lines.append(f"{t // 1_000_000_000}.{t % 1_000_000_000:09d} " + " ".join(
                _num(v) for v in (m[0], m[1], m[2], m[4], m[5], m[6], m[3])))
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
        written.append(Trajectory(robot, path, rows, dropped))
    return written


__all__ = ["Collected", "Constraint", "G2oReport", "Trajectory", "body_frame_cov", "collect",
           "information", "write_g2o", "frames_file", "write_tum", "tum_paths", "robot_name",
           "MIN_VARIANCE"]
