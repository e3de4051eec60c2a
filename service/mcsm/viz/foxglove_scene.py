"""A map as a Foxglove scene: ``mcsm export-foxglove`` (MCAP file) and the live ``mcsm view``.

Each snapshot of a map is three messages with foxglove-sdk's own protobuf schemas:

==============================  ==========================  ===================================
topic                           schema                      content
==============================  ==========================  ===================================
``/mcsm/<map>/scene``           ``foxglove.SceneUpdate``    delete-all, then one entity per
                                                            frame (95 % ellipsoid of its
                                                            position, label) and one path per
                                                            component
``/mcsm/<map>/tf``              ``foxglove.FrameTransforms``  ``mcsm@<map>`` → each component
                                                            root (identity), root → each pose
                                                            frame (its mean)
``/mcsm/<map>/samples``         ``foxglove.PointCloud``     samples of every frame (a stride
                                                            of at most ``samples_per_frame``
                                                            rows each), fields x y z component
==============================  ==========================  ===================================

Components of a map are unrelated (no transform joins them); like ``mcsm plot``, the scene puts
every component's root at the origin of one display frame ``mcsm@<map>`` (``@`` cannot occur in
an mcsm frame name, so it never collides). Entities are in their root frame. foxglove-sdk is
imported only by :func:`load_foxglove` (the ``viz`` extra).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, cast

import numpy as np

from mcsm.viz import require
from mcsm.viz.ellipse import Ellipsoid, ellipsoid
from mcsm.viz.scene import MapView, map_view

#: component colours (RGB), the first ones of matplotlib's tab10 like ``mcsm plot``
PALETTE = [(0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.84, 0.15, 0.16),
           (0.58, 0.4, 0.74), (0.55, 0.34, 0.29), (0.89, 0.47, 0.76), (0.5, 0.5, 0.5),
           (0.74, 0.74, 0.13), (0.09, 0.75, 0.81)]
DEFAULT_SAMPLES_PER_FRAME = 100
#: snapshots of an export without ``every``: K = ceil(operations / 100)
MAX_AUTO_SNAPSHOTS = 100


def display_frame(map_name: str) -> str:
    return f"mcsm@{map_name}"


def topics(map_name: str) -> dict[str, str]:
    """The three topics of one map's scene."""
    return {"scene": f"/mcsm/{map_name}/scene", "tf": f"/mcsm/{map_name}/tf",
            "samples": f"/mcsm/{map_name}/samples"}


def load_foxglove() -> ModuleType:
    """``foxglove`` with its messages and channels submodules loaded (``MissingExtra`` if
    foxglove-sdk is not installed)."""
    fg = require("foxglove")
    require("foxglove.messages")
    require("foxglove.channels")
    return fg


@dataclass
class SceneSnapshot:
    """The messages of one snapshot plus the ellipsoids they carry (for tests and logs)."""

    scene: Any
    transforms: Any
    cloud: Any | None
    ellipsoids: dict[str, Ellipsoid] = field(default_factory=dict)


def _ts(m: ModuleType, time_ns: int) -> Any:
    return m.Timestamp(sec=int(time_ns // 1_000_000_000), nsec=int(time_ns % 1_000_000_000))


def build_snapshot(mv: MapView, time_ns: int, *, samples_per_frame: int =
                   DEFAULT_SAMPLES_PER_FRAME) -> SceneSnapshot:
    """Foxglove messages showing ``mv`` (see the module docstring).

    ``samples_per_frame`` 0, or a view without samples, gives no point cloud.
    """
    m = load_foxglove().messages
    ts = _ts(m, time_ns)
    disp = display_frame(mv.map)
    out = SceneSnapshot(None, None, None)
    entities = []
    tfs = []
    cloud_parts = []
    for ci, root in enumerate(mv.components):
        r, g, b = PALETTE[ci % len(PALETTE)]
        tfs.append(m.FrameTransform(timestamp=ts, parent_frame_id=disp, child_frame_id=root,
                                    translation=m.Vector3(x=0.0, y=0.0, z=0.0),
                                    rotation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)))
        frames = mv.of_component(root)
        for f in frames:
            e = ellipsoid(f.position, f.cov[:3, :3])
            out.ellipsoids[f.name] = e
            pose = m.Pose(position=m.Vector3(x=e.center[0], y=e.center[1], z=e.center[2]),
                          orientation=m.Quaternion(x=e.quat_xyzw[0], y=e.quat_xyzw[1],
                                                   z=e.quat_xyzw[2], w=e.quat_xyzw[3]))
            sphere = m.SpherePrimitive(pose=pose, size=m.Vector3(x=e.sizes[0], y=e.sizes[1],
                                                                 z=e.sizes[2]),
                                       color=m.Color(r=r, g=g, b=b,
                                                     a=0.45 if f.is_point else 0.25))
            label_pose = m.Pose(position=m.Vector3(x=e.center[0], y=e.center[1],
                                                   z=e.center[2]),
                                orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
            text = m.TextPrimitive(pose=label_pose, billboard=True, font_size=12.0,
                                   scale_invariant=True, color=m.Color(r=r, g=g, b=b, a=1.0),
                                   text=f.name)
            meta = [m.KeyValuePair(key="kind", value="landmark" if f.is_point else "pose"),
                    m.KeyValuePair(key="component", value=root)]
            entities.append(m.SceneEntity(timestamp=ts, frame_id=root, id=f"frame/{f.name}",
                                          metadata=meta, spheres=[sphere], texts=[text]))
            if not f.is_point and f.name != root:
                q = f.mean[3:7]  # w x y z
                tfs.append(m.FrameTransform(
                    timestamp=ts, parent_frame_id=root, child_frame_id=f.name,
                    translation=m.Vector3(x=float(f.mean[0]), y=float(f.mean[1]),
                                          z=float(f.mean[2])),
                    rotation=m.Quaternion(x=float(q[1]), y=float(q[2]), z=float(q[3]),
                                          w=float(q[0]))))
            if f.samples is not None and samples_per_frame > 0:
                step = max(1, -(-len(f.samples) // samples_per_frame))
                xyz = f.samples[::step, :3]
                cloud_parts.append(np.column_stack([xyz, np.full(len(xyz), float(ci))]))
        path = [f for f in frames if not f.is_point]
        if len(path) > 1:
            line = m.LinePrimitive(type=m.LinePrimitiveLineType.LineStrip, thickness=2.0,
                                   scale_invariant=True,
                                   points=[m.Point3(x=float(f.mean[0]), y=float(f.mean[1]),
                                                    z=float(f.mean[2])) for f in path],
                                   color=m.Color(r=r, g=g, b=b, a=0.8))
            entities.append(m.SceneEntity(timestamp=ts, frame_id=root, id=f"path/{root}",
                                          lines=[line]))
    out.scene = m.SceneUpdate(
        deletions=[m.SceneEntityDeletion(timestamp=ts, type=m.SceneEntityDeletionType.All)],
        entities=entities)
    out.transforms = m.FrameTransforms(transforms=tfs)
    if cloud_parts:
        pts = np.concatenate(cloud_parts).astype("<f4")
        f32 = m.PackedElementFieldNumericType.Float32
        out.cloud = m.PointCloud(
            timestamp=ts, frame_id=disp,
            pose=m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0),
                        orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            point_stride=16,
            fields=[m.PackedElementField(name=n, offset=4 * k, type=f32)
                    for k, n in enumerate(("x", "y", "z", "component"))],
            data=pts.tobytes())
    return out


class SceneChannels:
    """The three channels of one map's scene in a foxglove ``Context`` (file or server)."""

    def __init__(self, map_name: str, context: Any) -> None:
        fg = load_foxglove()
        t = topics(map_name)
        self.scene = fg.channels.SceneUpdateChannel(t["scene"], context=context)
        self.tf = fg.channels.FrameTransformsChannel(t["tf"], context=context)
        self.samples = fg.channels.PointCloudChannel(t["samples"], context=context)

    def log(self, snap: SceneSnapshot, time_ns: int | None = None) -> None:
        kw = {} if time_ns is None else {"log_time": int(time_ns)}
        self.tf.log(snap.transforms, **kw)
        self.scene.log(snap.scene, **kw)
        if snap.cloud is not None:
            self.samples.log(snap.cloud, **kw)


# --------------------------------------------------------------------------------------------
# mcsm export-foxglove
# --------------------------------------------------------------------------------------------

@dataclass
class ExportReport:
    path: Path
    map: str
    every: int = 1
    snapshots: list[int] = field(default_factory=list)  # the seq of each snapshot
    final_seq: int = 0
    notes: list[str] = field(default_factory=list)
    final_view: MapView | None = None  # the map at its last snapshot (for a PNG of it)


class _SnapshotSink:
    """Passed to ``mcsm.recording.replay`` as its ``sink``: replay calls ``config`` with each
    map's live state and ``input`` after applying each input, so snapshots are taken in one
    pass over the file with replay's own checks."""

    def __init__(self, map_name: str, every: int, emit: Any) -> None:
        self.map_name = map_name
        self.every = every
        self.emit = emit
        self.state: Any = None
        self.last_seq = 0
        self.last_emitted = -1
        self.last_time_ns = 0

    def config(self, state: Any, *_args: Any, **_kw: Any) -> None:
        if state.name == self.map_name:
            self.state = state

    def input(self, _op: str, map_name: str, seq: int, recv_ns: int, *_args: Any) -> None:
        if map_name != self.map_name or self.state is None:
            return
        self.last_seq, self.last_time_ns = seq, recv_ns
        if seq % self.every == 0:
            self.emit(self.state.map, seq, recv_ns)
            self.last_emitted = seq

    def checkpoint(self, *_args: Any, **_kw: Any) -> None:
        return None

    def snapshot(self, *_args: Any, **_kw: Any) -> None:
        return None  # a state snapshot in the file: replay has verified it; nothing to draw

    def finish(self) -> None:
        if self.state is not None and self.last_emitted != self.last_seq:
            self.emit(self.state.map, self.last_seq, self.last_time_ns)
            self.last_emitted = self.last_seq


def export_foxglove(path: str | os.PathLike[str], out: str | os.PathLike[str], *,
                    every: int | None = None, map_name: str | None = None,
                    samples_per_frame: int = DEFAULT_SAMPLES_PER_FRAME,
                    overwrite: bool = False) -> ExportReport:
    """Replay ``path`` and write one map's scene over time into the MCAP file ``out``.

    A snapshot is written after every ``every``-th input of the map and after its last one,
    stamped with the input's receive time. ``every=None`` picks the smallest K that gives at
    most :data:`MAX_AUTO_SNAPSHOTS` snapshots. The output is foxglove-sdk's MCAP writer's own
    (chunked, indexed, zstd).

    Raises
    ------
    McsmError
        Unreadable recording, unknown map; ``MissingExtra`` without foxglove-sdk.
    """
    from mcsm.recording import replay
    from mcsm.viz.scene import choose_map, recording_maps

    if every is not None and every < 1:
        raise ValueError("every must be >= 1")
    fg = load_foxglove()
    counts = recording_maps(path)
    name = choose_map(list(counts), map_name, str(path))
    if every is None:
        every = max(1, -(-len(counts[name]) // MAX_AUTO_SNAPSHOTS))
    report = ExportReport(Path(out), name, every=every)
    ctx = fg.Context()
    with fg.open_mcap(str(out), allow_overwrite=overwrite, context=ctx):
        chans = SceneChannels(name, ctx)

        def emit(smap: Any, seq: int, time_ns: int) -> None:
            mv = map_view(smap, map_name=name, seq=seq, samples=samples_per_frame > 0)
            chans.log(build_snapshot(mv, time_ns, samples_per_frame=samples_per_frame),
                      time_ns)
            report.snapshots.append(seq)
            report.final_view = mv

        sink = _SnapshotSink(name, every, emit)
        rep = replay(path, sink=cast(Any, sink))
        sink.finish()
    report.final_seq = sink.last_seq
    if rep.divergence is not None:
        report.notes.append(f"replay diverged from the recording; the scene ends there "
                            f"({rep.divergence})")
    if rep.tail_error is not None:
        report.notes.append(f"recording is cut short ({rep.tail_error}); exported every "
                            "complete input")
    return report
