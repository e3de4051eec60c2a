"""Stream a real data set into a ``StochasticMap`` step by step, timing each step with one joint
marginal query, and score it against a reference; the EKF-SLAM baseline on the same steps.

A step is one new pose with the edges that arrive with it (:mod:`experiments.realdata_data`).
Its CPU time (``time.process_time``, ``threads=1``) covers every ``update`` of the step, the
removal of the previous pose (bounded maps), any work a hook does in it (a relinearisation) and
one ``marginal`` between the current pose and the landmark seen last (bounded landmark maps) or
the anchor (pose graphs). Drawing the input samples is the client's work and is not timed.

Samples are drawn for every edge in arrival order from ``default_rng(seed)``, whatever the
map does with them, so every configuration of one seed sees the same inputs; their sample
means (``RunResult.sample_means``) are what iSAM2 is fed for a like-for-like comparison.

Hooks (:class:`Hook`) let experiments change what happens around an update without touching
the core: a gate calibrated from past NIS values (``before``), a repair on rejection
(``after``), a relinearisation (``end_step``, which may hand back a new map).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from experiments.realdata_data import Edge, Problem

Array = npt.NDArray[np.float64]


class Hook:
    """Experiment code around the map's updates (every method optional to override)."""

    def before(self, smap: Any, edge: Edge, samples: Array) -> None:
        """Called before ``update``."""

    def split(self, smap: Any, edge: Edge, samples: Array) -> list[Array]:
        """The sample sets to apply for this edge (one update each; default: as given)."""
        return [samples]

    def after(self, smap: Any, edge: Edge, samples: Array, result: Any) -> tuple[Any, Any]:
        """Called after ``update`` with its result; may return another map/result."""
        return smap, result

    def end_step(self, smap: Any, k: int, pose: int, run: RunResult) -> Any:
        """Called at the end of step ``k`` (timed); returns the map to continue with."""
        return smap

    def describe(self) -> str:
        return ""


@dataclass
class RunResult:
    """What one streamed run measured."""

    status: str = "ok"
    step_s: Array = field(default_factory=lambda: np.zeros(0))
    total_s: float = 0.0
    checkpoints: dict[int, float] = field(default_factory=dict)
    final: dict[str, float] = field(default_factory=dict)
    tested: int = 0  # loop closures / re-sightings that met the gate's test
    rejected: int = 0
    errors: int = 0  # McsmError other than a gate rejection
    relins: int = 0  # automatic relinearisations (the map's policy) and their CPU seconds
    relin_s: float = 0.0
    nis: list[tuple[int, float, int, str]] = field(default_factory=list)  # step, nis, dof, status
    sample_means: list[Array] = field(default_factory=list)
    pose_means: dict[int, Array] = field(default_factory=dict)  # estimate when it was current
    note: str = ""


class Mda(Hook):
    """Multiple data assimilation: each loop closure or re-sighting applied as ``k`` updates,
    each with the input's spread about its mean scaled by ``sqrt(k)`` (``k`` x its
    covariance); the map re-predicts the observation before each (an iterated update)."""

    def __init__(self, k: int) -> None:
        self.k = int(k)

    def split(self, smap: Any, edge: Edge, samples: Array) -> list[Array]:
        a, b = frame(edge, "i"), frame(edge, "j")
        if self.k == 1 or edge.kind == "odometry" or a not in smap or b not in smap:
            return [samples]
        return [inflate(samples, np.sqrt(self.k))] * self.k

    def describe(self) -> str:
        return f"MDA x{self.k}"


def inflate(x: Array, factor: float) -> Array:
    """Samples with their spread about the mean scaled by ``factor`` (points: coordinates;
    ATs: translation and body-frame rotation vector about the chordal mean)."""
    from mcsm.core.quat import align_hemisphere, mean_rotation, qexp, qlog, qmul

    out = x.copy()
    out[:, :3] = x[:, :3].mean(0) + factor * (x[:, :3] - x[:, :3].mean(0))
    if x.shape[1] == 7:
        q_ref = mean_rotation(x[:, 3:])
        conj = q_ref * np.array([1.0, -1.0, -1.0, -1.0])
        r = qlog(qmul(conj[None, :], x[:, 3:]))
        out[:, 3:] = align_hemisphere(qmul(q_ref[None, :], qexp(factor * r)), q_ref[None, :])
    return out


def frame(e: Edge, end: str) -> str:
    """Map frame name of an edge's end ``"i"`` or ``"j"``."""
    if end == "i":
        return f"x{e.i}"
    return f"l{e.j}" if e.is_point else f"x{e.j}"


def draw(e: Edge, dim: int, n: int, rng: np.random.Generator) -> Array:
    """Samples of one edge: ``(N, 3)`` point or ``(N, 7)`` AT (GTSAM body-frame noise)."""
    from mcsm_client.sampling import sample_planar, sample_point, sample_pose

    if e.is_point:
        return sample_point(e.mean, e.cov, n_samples=n, rng=rng)
    if dim == 2:
        return sample_planar(e.mean, e.cov, n_samples=n, rng=rng, translation_frame="body")
    return sample_pose(e.mean, e.cov, n_samples=n, rng=rng, translation_frame="body")


def sample_moments(x: Array, dim: int) -> tuple[Array, Array]:
    """Mean and covariance of an input's samples in the edge's own convention: point ``(2,)``;
    planar ``(3,)`` with the covariance over GTSAM's body tangent ``(3, 3)``; 3-D ``(7,)`` with
    ``(6, 6)`` over ``[t_body, r]``."""
    from mcsm.core.at import mean_and_cov
    from mcsm.core.quat import rotation_matrix

    if x.shape[1] == 3:
        xy = x[:, :2]
        return xy.mean(0), np.cov(xy.T)
    mean, cov = mean_and_cov(x)
    rot = rotation_matrix(mean[3:])
    j = np.eye(6)
    j[:3, :3] = rot.T
    cov = j @ cov @ j.T
    if dim == 2:
        idx = [0, 1, 5]
        return (np.array([mean[0], mean[1], 2.0 * np.arctan2(mean[6], mean[3])]),
                cov[np.ix_(idx, idx)])
    return mean, cov


def positions(smap: Any, anchor: str, frames: list[str]) -> Array:
    """Mean positions ``(K, 3)`` of frames relative to the anchor (NaN where missing)."""
    out = np.full((len(frames), 3), np.nan)
    for k, f in enumerate(frames):
        if f in smap and anchor in smap:
            out[k] = smap.query(anchor, f)[:, :3].mean(axis=0)
    return out


def run_map(problem: Problem, make: Callable[[], Any], *, n_samples: int, seed: int,
            hooks: list[Hook] | None = None, checkpoint_every: int = 500,
            error_fn: Callable[[Any, int], float] | None = None, keep_means: bool = True,
            progress: bool = False) -> tuple[RunResult, Any]:
    """Stream ``problem`` into the map ``make()`` returns; see the module docstring."""
    from mcsm.core.at import invert
    from mcsm.errors import McsmError

    hooks = hooks or []
    rng = np.random.default_rng(seed)
    smap = make()
    n = len(problem.steps)
    res = RunResult(step_s=np.zeros(n))
    anchor_id = problem.steps[0][0]
    anchor = f"x{anchor_id}"
    prev: int | None = None
    last_lm: int | None = None
    t_wall = time.perf_counter()
    first = True
    for k, (pose, edges) in enumerate(problem.steps):
        xs = [draw(e, problem.dim, n_samples, rng) for e in edges]
        if keep_means:
            res.sample_means += [sample_moments(x, problem.dim)[0] for x in xs]
        t0 = time.process_time()
        for e, x in zip(edges, xs, strict=True):
            a, b = frame(e, "i"), frame(e, "j")
            if first and not e.is_point and e.i != anchor_id:
                a, b, x = b, a, invert(x)  # the anchor becomes the root of the component
            first = False
            for h in hooks:
                h.before(smap, e, x)
            parts = [x]
            for h in hooks:
                parts = [y for part in parts for y in h.split(smap, e, part)]
            try:
                r = smap.update(a, b, parts[0])  # its verdict is the one counted
                for part in parts[1:]:
                    if r.kind == "rejected":
                        break
                    smap.update(a, b, part)
            except McsmError as exc:
                res.errors += 1
                res.note = res.note or f"step {k}: {type(exc).__name__}: {exc}"
                continue
            for h in hooks:
                smap, r = h.after(smap, e, x, r)
            relin = getattr(r, "relin", None)
            if relin is not None:
                res.relins += 1
                res.relin_s += float(getattr(relin, "time_s", 0.0))
            if r.verdict.nis is not None and r.verdict.dof > 0:
                res.tested += 1
                res.rejected += r.kind == "rejected"
                res.nis.append((k, float(r.verdict.nis), int(r.verdict.dof), r.verdict.status))
            if e.is_point:
                last_lm = e.j
        if problem.bounded and prev is not None and prev != anchor_id and prev != pose:
            smap.remove(f"x{prev}")
        prev = pose
        for h in hooks:
            smap = h.end_step(smap, k, pose, res)
        if k > 0:
            partner = f"l{last_lm}" if (problem.bounded and last_lm is not None) else anchor
            smap.marginal(f"x{pose}", partner)
        res.step_s[k] = time.process_time() - t0
        if k > 0 and f"x{pose}" in smap:
            res.pose_means[pose] = smap.query(anchor, f"x{pose}").copy().mean(axis=0)
        if error_fn is not None and ((k + 1) % checkpoint_every == 0 or k == n - 1):
            res.checkpoints[k + 1] = error_fn(smap, k + 1)
        if progress and (k + 1) % 1000 == 0:
            print(f"      step {k + 1}/{n}: {res.step_s[:k + 1].sum():.0f} s CPU, "
                  f"{time.perf_counter() - t_wall:.0f} s wall, rejected {res.rejected}/"
                  f"{res.tested}", flush=True)
    res.total_s = float(res.step_s.sum())
    return res, smap


def run_ekf_slam(problem: Problem, *, checkpoint_every: int = 500,
                 error_fn: Callable[[dict[int, Array], int], float] | None = None
                 ) -> tuple[RunResult, Any]:
    """Classic EKF-SLAM on a bounded landmark problem (the file's values); the step's query is
    the joint covariance of the current pose and the landmark seen last (indexing)."""
    from experiments.baselines.ekf_slam import EkfSlam

    if not problem.bounded or problem.dim != 2:
        raise ValueError("EKF-SLAM applies to the planar landmark set (Victoria Park)")
    ekf = EkfSlam(np.eye(3), np.eye(2))
    n = len(problem.steps)
    res = RunResult(step_s=np.zeros(n))
    for k, (_, edges) in enumerate(problem.steps):
        t0 = time.process_time()
        last = None
        for e in edges:
            if e.kind == "odometry":
                if e.i != problem.steps[k - 1][0]:
                    raise ValueError("EKF-SLAM needs odometry from the previous pose")
                ekf.predict(e.mean, e.cov)
            else:
                ekf.observe(e.j, e.mean, e.cov)
                last = e.j
        if last is not None:
            i0 = ekf._slot[last]
            idx = [0, 1, 2, i0, i0 + 1]
            ekf._p[np.ix_(idx, idx)].copy()  # the joint covariance of pose and landmark
        res.step_s[k] = time.process_time() - t0
        if error_fn is not None and ((k + 1) % checkpoint_every == 0 or k == n - 1):
            ids, means, _ = ekf.landmark_estimates()
            res.checkpoints[k + 1] = error_fn(dict(zip(ids.tolist(), means, strict=True)), k + 1)
    res.total_s = float(res.step_s.sum())
    return res, ekf
