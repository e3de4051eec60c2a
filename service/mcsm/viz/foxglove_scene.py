"""A map as a Foxglove scene: ``mcsm export foxglove`` (MCAP file) and the live ``mcsm view``.

Each snapshot of a map is three messages with foxglove-sdk's own protobuf schemas, and the
map's verdicts and counters go on two more topics:

==============================  ==========================  ===================================
topic                           schema                      content
==============================  ==========================  ===================================
``/mcsm/<map>/scene``           ``foxglove.SceneUpdate``    delete-all, then one entity per
                                                            frame (95 % region of its position
                                                            with an outline, label) and one
                                                            line per robot path
``/mcsm/<map>/tf``              ``foxglove.FrameTransforms``  ``mcsm@<map>`` → each component
                                                            root (its display shift), root →
                                                            each pose frame (its mean)
``/mcsm/<map>/samples``         ``foxglove.PointCloud``     samples of every frame (a stride
                                                            of at most ``samples_per_frame``
                                                            rows each), fields x y z component
``/mcsm/<map>/log``             ``foxglove.Log``            one line per update: seq, frames,
                                                            kind, verdict (NIS, threshold),
                                                            request id; rejected = warning
``/mcsm/<map>/stats``           ``mcsm.MapStats`` (JSON)    counters Foxglove's Plot panel
                                                            draws: accepted, rejected, pending,
                                                            retracted, reinstated, frames,
                                                            components, refused requests,
                                                            queue length
==============================  ==========================  ===================================

Components of a map are unrelated (no transform joins them); like ``mcsm plot``, the scene puts
them side by side in one display frame ``mcsm@<map>`` (:mod:`mcsm.viz.layout`; ``@`` cannot
occur in an mcsm frame name, so it never collides). Entities are in their root frame. The
regions are :mod:`mcsm.viz.ellipse`'s, drawn with a minimum thickness and an unlit outline in
the frame's colour (a zero-height disc renders grey in Foxglove). foxglove-sdk is imported only
by :func:`load_foxglove` (the ``viz`` extra).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, cast

import numpy as np

from mcsm.errors import McsmError
from mcsm.viz import require
from mcsm.viz.ellipse import Ellipsoid, ellipsoid
from mcsm.viz.layout import colour_plan, thin
from mcsm.viz.scene import MapView, ReplaySink, map_view

DEFAULT_SAMPLES_PER_FRAME = 100
#: snapshots of an export without ``every``: K = ceil(operations / 100)
MAX_AUTO_SNAPSHOTS = 100
#: points of each region's outline (a closed line loop)
OUTLINE_POINTS = 20
#: pose labels along one path at most (the path's ends always)
MAX_POSE_LABELS = 30
#: the counters of ``/mcsm/<map>/stats`` (JSON schema ``mcsm.MapStats``)
STATS_FIELDS = ("seq", "frames", "components", "accepted", "rejected", "pending", "retracted",
                "reinstated", "refused_requests", "queue_length")
STATS_SCHEMA = {
    "title": "mcsm.MapStats", "type": "object",
    "description": "A map's counters after operation seq: updates per verdict status, frames, "
                   "components, requests refused with an error, requests waiting (live only)",
    "properties": {k: {"type": "integer", "minimum": 0} for k in STATS_FIELDS},
    "required": list(STATS_FIELDS)}


def display_frame(map_name: str) -> str:
    return f"mcsm@{map_name}"


def topics(map_name: str) -> dict[str, str]:
    """The five topics of one map's scene."""
    return {k: f"/mcsm/{map_name}/{k}" for k in ("scene", "tf", "samples", "log", "stats")}


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
    stats: dict[str, int] | None = None


def _ts(m: ModuleType, time_ns: int) -> Any:
    return m.Timestamp(sec=int(time_ns // 1_000_000_000), nsec=int(time_ns % 1_000_000_000))


def _colour(m: ModuleType, rgb: tuple[float, float, float], a: float) -> Any:
    return m.Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


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
    offsets = mv.offsets()
    paths = {r: [[f.name for f in p] for p in mv.paths(r)] for r in mv.components}
    comp_col, pose_col = colour_plan(mv.components, paths)
    labelled = {p[i] for ps in paths.values() for p in ps
                for i in thin(len(p), MAX_POSE_LABELS)}
    ident = m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    for ci, root in enumerate(mv.components):
        d = offsets[root]
        tfs.append(m.FrameTransform(timestamp=ts, parent_frame_id=disp, child_frame_id=root,
                                    translation=m.Vector3(x=float(d[0]), y=float(d[1]),
                                                          z=float(d[2])),
                                    rotation=ident))
        frames = mv.of_component(root)
        for f in frames:
            rgb = comp_col[root] if f.is_point else pose_col.get(f.name, comp_col[root])
            e = ellipsoid(f.position, f.cov[:3, :3])
            out.ellipsoids[f.name] = e
            sx, sy, sz = e.display_sizes()
            pose = m.Pose(position=m.Vector3(x=e.center[0], y=e.center[1], z=e.center[2]),
                          orientation=m.Quaternion(x=e.quat_xyzw[0], y=e.quat_xyzw[1],
                                                   z=e.quat_xyzw[2], w=e.quat_xyzw[3]))
            sphere = m.SpherePrimitive(pose=pose, size=m.Vector3(x=sx, y=sy, z=sz),
                                       color=_colour(m, rgb, 0.5 if f.is_point else 0.3))
            ring = e.outline(OUTLINE_POINTS)
            outline = m.LinePrimitive(
                type=m.LinePrimitiveLineType.LineLoop, thickness=1.5, scale_invariant=True,
                points=[m.Point3(x=float(x), y=float(y), z=float(z)) for x, y, z in ring],
                color=_colour(m, rgb, 1.0))
            texts = []
            if f.is_point or f.name in labelled:
                label_pose = m.Pose(position=m.Vector3(x=e.center[0], y=e.center[1],
                                                       z=e.center[2]), orientation=ident)
                texts.append(m.TextPrimitive(pose=label_pose, billboard=True, font_size=12.0,
                                             scale_invariant=True, color=_colour(m, rgb, 1.0),
                                             text=f.name))
            meta = [m.KeyValuePair(key="kind", value="landmark" if f.is_point else "pose"),
                    m.KeyValuePair(key="component", value=root),
                    m.KeyValuePair(key="region", value=f"95 % ({e.dof}-D)")]
            entities.append(m.SceneEntity(timestamp=ts, frame_id=root, id=f"frame/{f.name}",
                                          metadata=meta, spheres=[sphere], lines=[outline],
                                          texts=texts))
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
                xyz = f.samples[::step, :3] + d
                cloud_parts.append(np.column_stack([xyz, np.full(len(xyz), float(ci))]))
        by_name = {f.name: f for f in frames}
        for k, path in enumerate(paths[root]):
            if len(path) < 2:
                continue
            line = m.LinePrimitive(type=m.LinePrimitiveLineType.LineStrip, thickness=2.0,
                                   scale_invariant=True,
                                   points=[m.Point3(x=float(by_name[n].mean[0]),
                                                    y=float(by_name[n].mean[1]),
                                                    z=float(by_name[n].mean[2])) for n in path],
                                   color=_colour(m, pose_col[path[0]], 0.9))
            entities.append(m.SceneEntity(
                timestamp=ts, frame_id=root, id=f"path/{root}/{k}", lines=[line],
                metadata=[m.KeyValuePair(key="kind", value="path"),
                          m.KeyValuePair(key="first", value=path[0]),
                          m.KeyValuePair(key="last", value=path[-1])]))
    out.scene = m.SceneUpdate(
        deletions=[m.SceneEntityDeletion(timestamp=ts, type=m.SceneEntityDeletionType.All)],
        entities=entities)
    out.transforms = m.FrameTransforms(transforms=tfs)
    if cloud_parts:
        pts = np.concatenate(cloud_parts).astype("<f4")
        f32 = m.PackedElementFieldNumericType.Float32
        out.cloud = m.PointCloud(
            timestamp=ts, frame_id=disp,
            pose=m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0), orientation=ident),
            point_stride=16,
            fields=[m.PackedElementField(name=n, offset=4 * k, type=f32)
                    for k, n in enumerate(("x", "y", "z", "component"))],
            data=pts.tobytes())
    return out


def map_stats(seq: int, n_frames: int, n_components: int, verdicts: dict[str, int],
              refused_requests: int = 0, queue_length: int = 0) -> dict[str, int]:
    """The ``mcsm.MapStats`` message: every field of :data:`STATS_FIELDS`."""
    out = {"seq": int(seq), "frames": int(n_frames), "components": int(n_components),
           "refused_requests": int(refused_requests), "queue_length": int(queue_length)}
    for k in ("accepted", "rejected", "pending", "retracted", "reinstated"):
        out[k] = int(verdicts.get(k, 0))
    return out


#: verdict status -> log level name (foxglove.LogLevel)
_LEVEL = {"accepted": "Info", "reinstated": "Info", "pending": "Warning",
          "rejected": "Warning", "retracted": "Warning"}


def verdict_text(seq: int, op: str, kind: str, frames: tuple[str, ...] | list[str],
                 verdict: dict[str, Any] | None, request_id: str = "") -> tuple[str, str]:
    """``(level, text)`` of one input's log line: what it did and why (its verdict)."""
    what = " -> ".join(frames) if op == "update" and len(frames) == 2 else " ".join(frames)
    text = f"seq {seq} {op} {what}: {kind}".replace("  ", " ")
    level = "Info"
    if verdict:
        status = str(verdict.get("status", ""))
        level = _LEVEL.get(status, "Info")
        if status != kind:
            text += f", {status}"
        nis, thr = verdict.get("nis"), verdict.get("threshold")
        if nis is not None:
            text += f" (NIS {float(nis):.3g} over {verdict.get('dof', 0)} dof"
            text += f", threshold {float(thr):.3g})" if thr is not None else ", not gated)"
        if verdict.get("reason"):
            text += f" [{verdict['reason']}]"
    if request_id:
        text += f" id {request_id}"
    return level, text


def log_message(map_name: str, time_ns: int, level: str, text: str) -> Any:
    """A ``foxglove.Log`` message (name ``mcsm/<map>``)."""
    m = load_foxglove().messages
    return m.Log(timestamp=_ts(m, time_ns), level=getattr(m.LogLevel, level), message=text,
                 name=f"mcsm/{map_name}", file="", line=0)


def foxglove_layout(map_name: str = "default") -> dict[str, Any]:
    """A Foxglove / Lichtblick layout (the apps' "Import from file" JSON) for one map's topics:
    a 3D panel in the display frame with the scene and the samples, a Log panel on the
    verdicts, and a Plot panel of the counters. ``docs/foxglove-layout.json`` is this for the
    map ``default`` (a test keeps the two equal)."""
    t = topics(map_name)
    plot = [{"value": f"{t['stats']}.{k}", "enabled": True, "timestampMethod": "receiveTime",
             "label": k} for k in ("accepted", "rejected", "pending", "queue_length")]
    return {
        "configById": {
            "3D!mcsm": {
                "followTf": display_frame(map_name), "followMode": "follow-none",
                "scene": {"transforms": {"showLabel": False}},
                "cameraState": {"perspective": False, "distance": 80, "phi": 0.0001,
                                "thetaOffset": 0, "target": [0, 0, 0],
                                "targetOffset": [0, 0, 0], "targetOrientation": [0, 0, 0, 1],
                                "fovy": 45, "near": 0.01, "far": 5000},
                "topics": {t["scene"]: {"visible": True},
                           t["samples"]: {"visible": True, "pointSize": 2,
                                          "colorField": "component", "colorMode": "colormap",
                                          "colorMap": "turbo"}},
                "layers": {"grid": {"layerId": "foxglove.Grid", "visible": True,
                                    "frameId": display_frame(map_name), "size": 100,
                                    "divisions": 20, "color": "#80808040"}},
                "transforms": {}},
            "RosOut!mcsm": {"topicToRender": t["log"], "minLogLevel": 1, "searchTerms": []},
            "Plot!mcsm": {"title": f"map {map_name}: verdicts and queue", "paths": plot,
                          "showLegend": True, "xAxisVal": "timestamp", "isSynced": True},
        },
        "globalVariables": {}, "userNodes": {}, "playbackConfig": {"speed": 1},
        "layout": {"direction": "row", "first": "3D!mcsm",
                   "second": {"direction": "column", "first": "RosOut!mcsm",
                              "second": "Plot!mcsm", "splitPercentage": 55},
                   "splitPercentage": 65},
    }


class SceneChannels:
    """The five channels of one map's scene in a foxglove ``Context`` (file or server)."""

    def __init__(self, map_name: str, context: Any) -> None:
        fg = load_foxglove()
        t = topics(map_name)
        self.map_name = map_name
        self.scene = fg.channels.SceneUpdateChannel(t["scene"], context=context)
        self.tf = fg.channels.FrameTransformsChannel(t["tf"], context=context)
        self.samples = fg.channels.PointCloudChannel(t["samples"], context=context)
        self.logs = fg.channels.LogChannel(t["log"], context=context)
        self.stats = fg.Channel(t["stats"], message_encoding="json", context=context,
                                schema=fg.Schema(name="mcsm.MapStats", encoding="jsonschema",
                                                 data=json.dumps(STATS_SCHEMA).encode()))

    def log(self, snap: SceneSnapshot, time_ns: int | None = None) -> None:
        kw = {} if time_ns is None else {"log_time": int(time_ns)}
        self.tf.log(snap.transforms, **kw)
        self.scene.log(snap.scene, **kw)
        if snap.cloud is not None:
            self.samples.log(snap.cloud, **kw)
        if snap.stats is not None:
            self.log_stats(snap.stats, time_ns)

    def log_stats(self, stats: dict[str, int], time_ns: int | None = None) -> None:
        kw = {} if time_ns is None else {"log_time": int(time_ns)}
        self.stats.log(json.dumps(stats).encode(), **kw)

    def log_line(self, time_ns: int, level: str, text: str, *, stamp: bool = True) -> None:
        """One ``foxglove.Log`` line (``stamp``: logged at ``time_ns``, else now)."""
        kw = {"log_time": int(time_ns)} if stamp else {}
        self.logs.log(log_message(self.map_name, time_ns, level, text), **kw)


# --------------------------------------------------------------------------------------------
# mcsm export foxglove (mcsm export-foxglove)
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


class _SnapshotSink(ReplaySink):
    """Replay's sink (:class:`mcsm.viz.scene.ReplaySink`): after each input of the map it
    logs the input's verdict line and the map's counters, and after every K-th a scene
    snapshot, so the export is one pass over the file with replay's own checks."""

    def __init__(self, map_name: str, every: int, emit: Any, chans: Any = None) -> None:
        super().__init__(map_name)
        self.every = every
        self.emit = emit
        self.chans = chans
        self.last_seq = 0
        self.last_emitted = -1
        self.last_time_ns = 0

    def on_input(self, op: str, seq: int, recv_ns: int, request_id: str) -> None:
        self.last_seq, self.last_time_ns = seq, recv_ns
        st = self.state
        if self.chans is not None:
            try:
                ack = st.verdict_of(request_id)
            except McsmError:
                ack = None
            if ack is not None:
                v = ack.verdict.to_dict() if ack.verdict is not None else None
                level, text = verdict_text(seq, op, ack.kind, self.last_frames, v, request_id)
                self.chans.log_line(recv_ns, level, text)
            smap = st.map
            self.chans.log_stats(map_stats(seq, smap.n_frames, len(smap.components()),
                                           dict(st.verdicts), st.rejected), recv_ns)
        if seq % self.every == 0:
            self.emit(st.map, seq, recv_ns)
            self.last_emitted = seq

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
            mv = map_view(smap, map_name=name, seq=seq, samples=samples_per_frame > 0,
                          parents=sink.history.parent)
            chans.log(build_snapshot(mv, time_ns, samples_per_frame=samples_per_frame),
                      time_ns)
            report.snapshots.append(seq)
            report.final_view = mv

        sink = _SnapshotSink(name, every, emit, chans)
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
