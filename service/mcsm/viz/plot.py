"""``mcsm plot``: a map drawn with matplotlib, written as a PNG.

Drawn with matplotlib's object API on an Agg canvas: no pyplot, no window, and a caller's own
backend and figures are left alone.

Drawn per component (one colour each, every frame relative to the component's root):
landmarks (point frames) as dots with their 95 % covariance ellipses, pose frames as triangles
with a heading tick and their ellipses (dashed), the path through the pose frames in the order
they were added, optionally each frame's samples, and ground truth (``x``) when given.
Views: ``top`` (x-y), ``xz``, ``yz`` or ``3d`` (ellipsoids as wireframes).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mcsm.viz import require
from mcsm.viz.ellipse import P_REGION, Ellipse, Ellipsoid, ellipse, ellipsoid
from mcsm.viz.layout import colour_plan, offsets_text, thin
from mcsm.viz.scene import Array, MapView, is_planar

VIEWS = ("auto", "top", "xz", "yz", "3d")
_AXES = {"top": (0, 1), "xz": (0, 2), "yz": (1, 2)}
_NAMES = "xyz"
#: most samples drawn per frame (a random-free stride through the rows)
MAX_SAMPLES_PER_FRAME = 250
#: frames are labelled by name when a component has at most this many of a kind
MAX_LABELS = 40
#: a zoomed inset is added when the map is this many times wider than its largest ellipse
INSET_RATIO = 25.0
#: pose ellipses (and markers, heading ticks) drawn along one path at most, evenly spread
MAX_POSE_ELLIPSES = 30


@dataclass
class PlotResult:
    """What :func:`plot_map` drew (the tests compare it with the map's marginals)."""

    path: Path
    view: str
    title: str
    ellipses: dict[str, Ellipse] = field(default_factory=dict)  # 2-D views
    ellipsoids: dict[str, Ellipsoid] = field(default_factory=dict)  # 3-D view
    truth_drawn: list[str] = field(default_factory=list)
    truth_missing: list[str] = field(default_factory=list)
    n_sample_points: int = 0
    inset: tuple[float, float, float, float] | None = None  # zoomed region x0, x1, y0, y1
    colours: dict[str, tuple[float, ...]] = field(default_factory=dict)  # component -> RGB
    paths: dict[str, list[str]] = field(default_factory=dict)  # component -> its pose frames
    robot_paths: dict[str, list[list[str]]] = field(default_factory=dict)  # component -> paths
    drawn_pose_ellipses: list[str] = field(default_factory=list)  # after thinning
    offsets: dict[str, tuple[float, ...]] = field(default_factory=dict)  # display shifts (m)
    pose_colours: dict[str, tuple[float, ...]] = field(default_factory=dict)  # pose -> its path's
    legend: list[str] = field(default_factory=list)  # the legend's entries


def resolve_view(view: str, mv: MapView) -> str:
    """``auto`` becomes ``top`` for a planar map and ``3d`` otherwise."""
    if view not in VIEWS:
        raise ValueError(f"view must be one of {VIEWS}, got {view!r}")
    if view == "auto":
        return "top" if is_planar(mv) else "3d"
    return view


def title_of(mv: MapView, view: str, extra: str = "") -> str:
    n_points = sum(f.is_point for f in mv.frames)
    n_poses, n_frames = len(mv.frames) - n_points, len(mv.frames)
    first = (f"map {mv.map!r} at seq {mv.seq}: {n_frames} frame{'' if n_frames == 1 else 's'} "
             f"({n_points} landmark{'' if n_points == 1 else 's'}, {n_poses} "
             f"pose{'' if n_poses == 1 else 's'}), {len(mv.components)} component"
             f"{'s' if len(mv.components) != 1 else ''}")
    second = f"N={mv.n_samples}, {mv.options_text()}; view {view}, {int(P_REGION * 100)} % regions"
    return first + "\n" + second + (f"\n{extra}" if extra else "")


def _stride(n: int) -> slice:
    return slice(None, None, max(1, math.ceil(n / MAX_SAMPLES_PER_FRAME)))


def _heading(mean: Array) -> Array:
    """The frame's x axis in the root frame (rotation of the mean quaternion w x y z)."""
    w, x, y, z = mean[3:7]
    return np.array([1 - 2 * (y * y + z * z), 2 * (x * y + z * w), 2 * (x * z - y * w)])


def plot_map(mv: MapView, out: str | os.PathLike[str], *, view: str = "auto",
             samples: bool = False, truth: dict[str, Array] | None = None,
             title_extra: str = "", dpi: int = 110) -> PlotResult:
    """Draw ``mv`` into the PNG ``out``; returns the drawn ellipses/ellipsoids.

    Components are shifted side by side (:meth:`MapView.offsets`); each robot path (a chain
    of pose frames, :meth:`MapView.paths`) is a line in its own colour (the first path of a
    component takes the component's colour), with at most :data:`MAX_POSE_ELLIPSES` pose
    ellipses, markers and heading ticks along it; landmarks all get theirs.

    Parameters
    ----------
    mv : the map (with samples if ``samples``)
    view : ``auto``, ``top``, ``xz``, ``yz`` or ``3d``
    samples : draw every frame's samples (at most 250 per frame)
    truth : ground truth positions by frame name, in the frame's root frame

    Raises
    ------
    MissingExtra
        If matplotlib is not installed.
    """
    # matplotlib's object API with an Agg canvas: no pyplot, no window, and the caller's
    # backend and global figure state stay as they were
    require("matplotlib")  # first: a missing extra is named as matplotlib
    figure_mod = require("matplotlib.figure")
    agg = require("matplotlib.backends.backend_agg")
    patches = require("matplotlib.patches")
    lines_mod = require("matplotlib.lines")

    v = resolve_view(view, mv)
    res = PlotResult(Path(out), v, "")
    res.offsets = {r: tuple(float(x) for x in d) for r, d in mv.offsets().items()}
    shift_note = offsets_text({r: np.asarray(d) for r, d in res.offsets.items()})
    if shift_note:
        shift_note = f"components side by side (display shift, not a transform): {shift_note}"
    res.title = title_of(mv, v, "; ".join([title_extra, shift_note, *mv.notes]).strip("; "))
    mv = mv.shifted({r: np.asarray(d) for r, d in res.offsets.items()})
    if truth:
        comp = {f.name: f.component for f in mv.frames}
        truth = {n: np.asarray(p, dtype=np.float64) + np.asarray(res.offsets[comp[n]])
                 if n in comp else p for n, p in truth.items()}
    all_paths = {r: mv.paths(r) for r in mv.components}
    comp_col, pose_col = colour_plan(mv.components, {r: [[f.name for f in p] for p in ps]
                                                     for r, ps in all_paths.items()})
    axz: Any = None
    if v == "3d":
        fig = figure_mod.Figure(figsize=(8.5, 7.5))
        ax: Any = fig.add_subplot(projection="3d")
    else:
        i, j = _AXES[v]
        sel = np.ix_([i, j], [i, j])
        for f in mv.frames:
            res.ellipses[f.name] = ellipse(f.position[[i, j]], f.cov[:3, :3][sel])
        res.inset = _zoom_region(mv, v, res)
        if res.inset is None:
            fig = figure_mod.Figure(figsize=(8.5, 7.5))
            ax = fig.add_subplot()
        else:  # ellipses too small to see at the map's scale: a magnified panel beside it
            fig = figure_mod.Figure(figsize=(13, 7.2))
            ax, axz = fig.subplots(1, 2, gridspec_kw={"width_ratios": [1.9, 1]})
    handles: list[Any] = []
    all_xyz = np.array([f.position for f in mv.frames]) if mv.frames else np.zeros((0, 3))
    span = float(np.ptp(all_xyz, axis=0).max()) if len(all_xyz) > 1 else 1.0
    tick = 0.02 * max(span, 1e-3)
    for root in mv.components:
        col = comp_col[root]
        frames = mv.of_component(root)
        pts = [f for f in frames if f.is_point]
        res.colours[root] = tuple(float(c) for c in col)
        paths = all_paths[root]
        res.paths[root] = [f.name for f in mv.pose_path(root)]
        res.robot_paths[root] = [[f.name for f in p] for p in paths]
        if samples:
            cloud = [f.samples[_stride(len(f.samples)), :3] for f in frames
                     if f.samples is not None]
            if cloud:
                c = np.concatenate(cloud)
                res.n_sample_points += len(c)
                if v == "3d":
                    ax.scatter(c[:, 0], c[:, 1], c[:, 2], s=1, color=col, alpha=0.08,
                               depthshade=False)
                else:
                    i, j = _AXES[v]
                    ax.scatter(c[:, i], c[:, j], s=1, color=col, alpha=0.25, linewidths=0,
                               zorder=1)
        n_poses = sum(len(p) for p in paths)
        handles.append(lines_mod.Line2D(
            [], [], color=col, marker="o", ls="",
            label=f"component {root}: {len(pts)} landmark{'s' if len(pts) != 1 else ''}, "
                  f"{n_poses} pose{'s' if n_poses != 1 else ''}"))
        _draw_landmarks(ax, v, pts, col, res)
        for path in paths:
            pcol = pose_col[path[0].name]
            shown = thin(len(path), MAX_POSE_ELLIPSES)
            res.pose_colours.update({f.name: pcol for f in path})
            res.drawn_pose_ellipses.extend(path[m].name for m in shown)
            _draw_path(ax, v, path, shown, pcol, res, tick, patches)
            if len(path) > 1:
                handles.append(lines_mod.Line2D(
                    [], [], color=pcol, marker="^", ls="-",
                    label=f"path {path[0].name} \u2192 {path[-1].name} ({len(path)} poses"
                          + (f", {len(shown)} ellipses" if len(shown) < len(path) else "")
                          + ")"))
            named = path if len(path) <= MAX_LABELS else [path[0], path[-1]]
            for f in named:  # a path's last pose is labelled below it (loops end at the start)
                _label(ax, v, f.position, f.name, pcol, below=f is path[-1] and len(path) > 1)
        if len(pts) <= MAX_LABELS:
            for f in pts:
                _label(ax, v, f.position, f.name, col, small=True)
    if truth:
        shown_t = [(f, truth[f.name]) for f in mv.frames if f.name in truth]
        res.truth_drawn = [f.name for f, _ in shown_t]
        res.truth_missing = sorted(set(truth) - {f.name for f in mv.frames})
        if shown_t:
            t = np.array([p for _, p in shown_t])
            if v == "3d":
                ax.scatter(t[:, 0], t[:, 1], t[:, 2], marker="x", color="black", s=18)
            else:
                i, j = _AXES[v]
                ax.scatter(t[:, i], t[:, j], marker="x", color="black", s=18, linewidths=0.9,
                           zorder=5)
                for f, p in shown_t:
                    ax.plot([f.position[i], p[i]], [f.position[j], p[j]], color="black",
                            lw=0.4, alpha=0.5, zorder=4)
            plural = "s" if len(shown_t) != 1 else ""
            handles.append(lines_mod.Line2D([], [], color="black", marker="x", ls="",
                                            label=f"ground truth ({len(shown_t)} frame{plural})"))
    if any(f.is_point for f in mv.frames):
        handles.append(lines_mod.Line2D([], [], color="grey", marker="o", ls="", ms=4,
                                        label=f"landmark, {int(P_REGION * 100)} % region"))
    if any(not f.is_point for f in mv.frames):
        handles.append(lines_mod.Line2D([], [], color="grey", marker="^", ls="--",
                                        label=f"pose, heading, {int(P_REGION * 100)} % region "
                                              "(dashed)"))
    if samples:
        handles.append(lines_mod.Line2D([], [], color="grey", marker=".", ls="", alpha=0.4,
                                        label="samples"))
    if axz is not None and res.inset is not None:
        _draw_zoom(ax, axz, mv, v, res, truth, comp_col, patches)
    if v == "3d":
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        if len(all_xyz):
            # equal metres on every axis; a flat axis still gets 10 % of the span
            lo, hi = all_xyz.min(axis=0), all_xyz.max(axis=0)
            half = np.maximum(hi - lo, 0.1 * max(span, 1e-3)) * 0.55
            mid = 0.5 * (lo + hi)
            ax.set_xlim(mid[0] - half[0], mid[0] + half[0])
            ax.set_ylim(mid[1] - half[1], mid[1] + half[1])
            ax.set_zlim(mid[2] - half[2], mid[2] + half[2])
            ax.set_box_aspect(half)
    else:
        i, j = _AXES[v]
        ax.set_xlabel(f"{_NAMES[i]} [m] (root frame of each component)")
        ax.set_ylabel(f"{_NAMES[j]} [m]")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    fig.suptitle(res.title, fontsize=9)
    if handles:
        res.legend = [h.get_label() for h in handles]
        ax.legend(handles=handles, fontsize=7, loc="best", framealpha=0.85)
    fig.tight_layout()
    agg.FigureCanvasAgg(fig)
    fig.savefig(res.path, dpi=dpi, format="png")
    return res


def _label(ax: Any, v: str, p: Array, text: str, col: Any, small: bool = False,
           below: bool = False) -> None:
    size = 6 if small else 7
    if v == "3d":
        ax.text(p[0], p[1], p[2], f" {text}", fontsize=size, color=col,
                va="top" if below else "bottom")
    else:
        i, j = _AXES[v]
        ax.annotate(text, (p[i], p[j]), xytext=(3, -9 if below else 3),
                    textcoords="offset points", fontsize=size, color=col, zorder=6)


def _wireframe(ax: Any, e: Ellipsoid, col: Any, alpha: float) -> None:
    u, w = np.meshgrid(np.linspace(0, 2 * np.pi, 16), np.linspace(0, np.pi, 9))
    sphere = np.stack([np.cos(u) * np.sin(w), np.sin(u) * np.sin(w), np.cos(w)], axis=-1)
    xyz = (sphere * (np.array(e.sizes) / 2.0)) @ e.rotation().T + np.array(e.center)
    ax.plot_wireframe(xyz[..., 0], xyz[..., 1], xyz[..., 2], color=col, lw=0.3, alpha=alpha)


def _draw_landmarks(ax: Any, v: str, pts: list[Any], col: Any, res: PlotResult) -> None:
    if not pts:
        return
    p = np.array([f.position for f in pts])
    if v == "3d":
        for f in pts:
            e = ellipsoid(f.position, f.cov[:3, :3])
            res.ellipsoids[f.name] = e
            _wireframe(ax, e, col, 0.45)
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=9, color=col, depthshade=False)
        return
    patches = require("matplotlib.patches")
    i, j = _AXES[v]
    for f in pts:
        el = res.ellipses[f.name]
        ax.add_patch(patches.Ellipse(el.center, el.width, el.height, angle=el.angle_deg,
                                     fill=False, edgecolor=col, lw=0.8, zorder=3))
    ax.scatter(p[:, i], p[:, j], s=9, color=col, zorder=4)


def _draw_path(ax: Any, v: str, path: list[Any], shown: list[int], col: Any,
               res: PlotResult, tick: float, patches: Any) -> None:
    """One robot's path: the line through all its poses; ellipses, markers and heading
    ticks at the ``shown`` ones."""
    p = np.array([f.position for f in path])
    sel = [path[m] for m in shown]
    q = np.array([f.position for f in sel])
    if v == "3d":
        for f in path:  # every pose's region is computed (tests, logs); thinned when drawn
            res.ellipsoids[f.name] = ellipsoid(f.position, f.cov[:3, :3])
        for f in sel:
            _wireframe(ax, res.ellipsoids[f.name], col, 0.3)
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color=col, lw=1.0, alpha=0.8)
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], marker="^", s=30, color=col, depthshade=False)
        for f in sel:
            h = _heading(f.mean) * tick
            ax.plot([f.position[0], f.position[0] + h[0]], [f.position[1], f.position[1] + h[1]],
                    [f.position[2], f.position[2] + h[2]], color="black", lw=1.0)
        return
    i, j = _AXES[v]
    for f in sel:
        el = res.ellipses[f.name]
        ax.add_patch(patches.Ellipse(el.center, el.width, el.height, angle=el.angle_deg,
                                     fill=False, edgecolor=col, lw=0.8, ls="--", zorder=3))
    ax.plot(p[:, i], p[:, j], color=col, lw=1.2, alpha=0.8, zorder=2)
    ax.scatter(q[:, i], q[:, j], marker="^", s=30, color=col, edgecolors="black",
               linewidths=0.4, zorder=5)
    for f in sel:
        h = _heading(f.mean)[[i, j]]
        n = float(np.hypot(*h))
        if n > 0.2:  # a heading nearly along the view axis is not drawn
            ax.plot([f.position[i], f.position[i] + tick * h[0] / n],
                    [f.position[j], f.position[j] + tick * h[1] / n], color="black",
                    lw=1.0, zorder=5)


def _zoom_region(mv: MapView, v: str, res: PlotResult
                 ) -> tuple[float, float, float, float] | None:
    """A square region around the frame with the largest ellipse, when the map is more than
    :data:`INSET_RATIO` times wider than that ellipse (else None): ``x0, x1, y0, y1``."""
    if len(res.ellipses) < 2:
        return None
    i, j = _AXES[v]
    pos = np.array([[f.position[i], f.position[j]] for f in mv.frames])
    extent = float(np.max(pos.max(axis=0) - pos.min(axis=0)))
    focus = max(res.ellipses, key=lambda n: res.ellipses[n].width)
    e = res.ellipses[focus]
    if e.width <= 0 or extent < INSET_RATIO * e.width:
        return None
    half = max(3.0 * e.width, 0.03 * extent)
    cx, cy = e.center
    return (cx - half, cx + half, cy - half, cy + half)


def _draw_zoom(ax: Any, axz: Any, mv: MapView, v: str, res: PlotResult,
               truth: dict[str, Array] | None, colours: Any, patches: Any) -> None:
    """The frames inside ``res.inset`` drawn magnified in ``axz``; the region marked on ``ax``."""
    assert res.inset is not None
    x0, x1, y0, y1 = res.inset
    i, j = _AXES[v]
    drawn = set(res.drawn_pose_ellipses)
    for f in mv.frames:
        px, py = f.position[i], f.position[j]
        el = res.ellipses[f.name]
        if not (x0 - el.width <= px <= x1 + el.width and y0 - el.width <= py <= y1 + el.width):
            continue
        col = res.pose_colours.get(f.name) or colours[f.component]
        if not f.is_point and f.name not in drawn:
            continue  # thinned like on the main panel
        axz.add_patch(patches.Ellipse(el.center, el.width, el.height, angle=el.angle_deg,
                                      fill=False, edgecolor=col, lw=1.2,
                                      ls="-" if f.is_point else "--"))
        axz.scatter([px], [py], s=14, color=col, marker="o" if f.is_point else "^", zorder=4)
        if x0 <= px <= x1 and y0 <= py <= y1:
            axz.annotate(f.name, (px, py), xytext=(4, 4), textcoords="offset points",
                         fontsize=8, color=col)
        if f.samples is not None and res.n_sample_points:
            c = f.samples[_stride(len(f.samples)), :3]
            axz.scatter(c[:, i], c[:, j], s=2, color=col, alpha=0.3, linewidths=0)
        if truth and f.name in truth:
            t = truth[f.name]
            axz.scatter([t[i]], [t[j]], marker="x", color="black", s=30, linewidths=1.0,
                        zorder=5)
            axz.plot([px, t[i]], [py, t[j]], color="black", lw=0.5, alpha=0.6)
    for root in mv.components:
        for p in mv.paths(root):
            path = np.array([f.position for f in p])
            if len(path) > 1:
                axz.plot(path[:, i], path[:, j], color=res.pose_colours[p[0].name], lw=1.0,
                         alpha=0.7)
    axz.set_xlim(x0, x1)
    axz.set_ylim(y0, y1)
    axz.set_aspect("equal")
    axz.grid(alpha=0.3)
    axz.set_xlabel(f"{_NAMES[i]} [m]")
    axz.set_ylabel(f"{_NAMES[j]} [m]")
    axz.set_title(f"magnified: the {x1 - x0:.3g} m square in the grey box", fontsize=9)
    ax.add_patch(patches.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor="0.35",
                                   lw=1.0, zorder=6))
