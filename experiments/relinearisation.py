"""The measurements behind the relinearisation defaults (docs/relinearisation.md), one mode each.

* ``victoria``: Victoria Park (``victoria_park.txt`` from the gtsam wheel) streamed into a
  bounded ``StochasticMap(N, **options)`` (pose 0 as anchor) by ``mcsm_client.players.play``;
  landmark RMS against GTSAM's batch optimum of the file (``experiments.realdata``), the
  sightings the gate refused, the relinearisations and their time.
* ``sphere``: GTSAM's sphere2500 (every pose kept), ATE against its ground truth, the closures
  refused, the relinearisations; then the ATE after one more relinearisation.
* ``clean``: clean simulated pose graphs (600 poses, seeds 16-19, the outlier benchmark's
  options, N = 200): the share of true closures the gate refused.
* ``robust``: Victoria Park's batch optimum with a robust kernel on the sightings (GTSAM's
  Huber 1.345 and Cauchy 1, each from the least-squares optimum), its distance from the
  least-squares one, the streamed map's landmark RMS against each, and per landmark the
  sightings the map leaves out at its end.
* ``landmarks``: the paper's §6 landmarks with wrong re-sightings as
  ``experiments/outliers.py`` makes them: RMS, NEES, recall, the relinearisations, and the RMS
  after one more.

``--options`` is a JSON object of ``StochasticMap`` keywords (``{}``: the defaults; ``{"gate_scale":
null, "history": null, "relinearize": null}``: the options before issue 22).

Usage::

    .venv/bin/python -m experiments.relinearisation victoria --seeds 1 2 11 --n-samples 1000
    .venv/bin/python -m experiments.relinearisation victoria --options \\
        '{"relinearize": {"nis": 0.95, "regate": 1, "gap": 25}}'
    .venv/bin/python -m experiments.relinearisation sphere --seeds 1
    .venv/bin/python -m experiments.relinearisation clean
    .venv/bin/python -m experiments.relinearisation robust --seeds 1 2 11
    .venv/bin/python -m experiments.relinearisation landmarks --case nearby 0.1 --seeds 8
"""

from __future__ import annotations

import argparse
import functools
import json
import time
from typing import Any

import numpy as np
from mcsm import StochasticMap


class Counting:
    """A map whose updates count refusals and relinearisations (the rest is delegated)."""

    def __init__(self, m: StochasticMap) -> None:
        self.m, self.n_samples = m, m.n_samples
        self.rejected = self.relins = self.readmitted = 0
        self.relin_s = self.worst_s = 0.0

    def update(self, a: str, b: str, x: Any, trusted: bool = False) -> Any:
        t0 = time.perf_counter()
        r = self.m.update(a, b, x, trusted=trusted)
        self.worst_s = max(self.worst_s, time.perf_counter() - t0)
        self.rejected += r.kind == "rejected"
        if r.relin is not None:
            self.relins += 1
            self.relin_s += r.relin.time_s
            self.readmitted += sum(c.readmitted for c in r.relin.components)
        return r

    def __getattr__(self, name: str) -> Any:
        return getattr(self.m, name)

    def __contains__(self, frame: object) -> bool:
        return frame in self.m

    def summary(self) -> str:
        return (f"refused {self.rejected}, readmitted {self.readmitted}, relinearisations "
                f"{self.relins} ({self.relin_s:.1f} s, worst step {self.worst_s:.3f} s)")


@functools.lru_cache(maxsize=1)
def _victoria_reference() -> tuple[Any, dict[str, Any]]:
    """The file and GTSAM's batch optimum of it (iSAM2, then Levenberg-Marquardt: minutes)."""
    from mcsm_client.datasets import read_dataset

    from experiments.realdata import gtsam_reference

    ds = read_dataset("gtsam:victoria_park.txt")
    return ds, gtsam_reference(ds)


def victoria(options: dict[str, Any], seed: int, n: int) -> str:
    from mcsm_client.players import play

    ds, ref = _victoria_reference()
    ids = ref["landmark_ids"]
    lm = np.stack([ref["lm_landmarks"][j] for j in ids])
    m = Counting(StochasticMap(n, **options))
    t0 = time.perf_counter()
    play(ds, m, rng=np.random.default_rng(seed), n_samples=n, bounded=True)
    xy = np.stack([m.marginal(f"x{min(ref['pose_ids'])}", f"l{j}")[0][:2] for j in ids])
    rms = float(np.sqrt(np.mean(np.sum((xy - lm) ** 2, axis=1))))
    return f"landmark RMS {rms:.3f} m; {m.summary()}; stream {time.perf_counter() - t0:.0f} s"


@functools.lru_cache(maxsize=1)
def _robust_optima() -> dict[str, Any]:
    """Victoria Park's landmarks (the reference's order) at GTSAM's batch optimum, least
    squares and with a robust kernel on the point sightings, each robust one from the
    least-squares optimum."""
    import gtsam

    from experiments.baselines import gtsam_slam as gs

    ds, ref = _victoria_reference()
    problem = gs.problem_from_dataset(ds)
    graph, _ = gs.build_graph_2d(problem)
    ls = gs.batch_optimum(graph, gs.isam2_incremental(problem).estimate)
    out = {"least squares": ls}
    for name, kernel in (("Huber 1.345", gtsam.noiseModel.mEstimator.Huber.Create(1.345)),
                         ("Cauchy 1", gtsam.noiseModel.mEstimator.Cauchy.Create(1.0))):
        out[name] = gs.batch_optimum(gs.build_graph_2d(problem, kernel)[0], ls)
    ids = ref["landmark_ids"]
    return {k: np.stack([np.asarray(gs.landmark_positions(v, ids)[j]) for j in ids])
            for k, v in out.items()}


def _rms(a: Any, b: Any) -> tuple[float, float]:
    d = np.sqrt(np.sum((a - b) ** 2, axis=1))
    return float(np.sqrt(np.mean(d**2))), float(d.max())


def left_out(m: StochasticMap, ds: Any) -> str:
    """Per landmark, the sightings the map leaves out at the end: those never admitted (in the
    file, not in the history) and the gated ones whose chi-square at the solution of the
    largest component's history exceeds the trim quantile (with their chi-squares)."""
    from mcsm.core import relin
    from mcsm.core import relinearize as rz

    h = m.factor_history
    assert h is not None
    cid = max(m._comps, key=lambda k: len(m._comps[k]))
    ids = h.group_vars(cid)
    fmask = h.vars["group"][h.factors["vars"][:, 0]] == cid
    prob = rz._problem(m, h, cid, ids, fmask, [], h.vars["alive"][ids].astype(np.uint8))
    relin.solve(prob, max_iter=rz.MAX_ITERATIONS, tol=rz.TOLERANCE).close()
    local = np.full(h.vars.n, -1, dtype=np.int64)
    local[ids] = np.arange(len(ids))
    rows = np.flatnonzero(fmask & (h.factors["robust"] != 0))
    thr = rz._trim_thresholds(h.factors["robust"][rows], h.factors["w"][rows],
                              h.factors["kind"][rows])
    out: dict[str, list[str]] = {}
    for k, r in enumerate(rows):
        a, b = (int(local[v]) for v in h.factors["vars"][r])
        one = relin.Problem(
            vkind=np.ascontiguousarray(prob.vkind[[a, b]]), vfixed=np.array([1, 0], np.uint8),
            vkept=np.array([0, 1], np.uint8), x=np.ascontiguousarray(prob.x[[a, b]]),
            fkind=h.factors["kind"][r:r + 1].astype(np.int32),
            fvars=np.array([[0, 1]], np.int32), fz=np.ascontiguousarray(h.factors["z"][r:r + 1]),
            fw=np.ascontiguousarray(h.factors["w"][r:r + 1]), pvoff=np.zeros(1, np.int64),
            pvars=np.zeros(0, np.int32), pdoff=np.zeros(1, np.int64),
            prows=np.zeros(0, np.int64), pdata=np.zeros(0),
            pose_active=prob.pose_active, point_active=prob.point_active)
        with relin.solve(one, max_iter=0) as s1:
            chi2 = s1.stats.cost_before
        if chi2 > thr[k]:
            name = h.frame_of.get(int(h.factors["vars"][r][1]), "a removed frame")
            out.setdefault(name, []).append(f"{chi2:.0f}")
    in_file: dict[str, int] = {}
    for c in ds.constraints:
        if c.kind == "landmark":
            in_file[f"l{c.target}"] = in_file.get(f"l{c.target}", 0) + 1
    kept = h.factors["vars"][:h.factors.n][h.factors["kind"][:h.factors.n] == 1, 1]
    counts = np.bincount(kept, minlength=h.vars.n)
    never = {f: in_file[f] - int(counts[h.var_of[f]]) for f in in_file if f in h.var_of}
    parts = [f"{f}: {in_file[f]} in the file, {never.get(f, 0)} never admitted, "
             f"{len(out.get(f, []))} trimmed (chi-square {', '.join(out.get(f, [])) or '-'})"
             for f in sorted(set(out) | {f for f, v in never.items() if v}, key=str)]
    return "; ".join(parts) or "none"


def robust(options: dict[str, Any], seed: int, n: int) -> str:
    from mcsm_client.players import play

    ds, ref = _victoria_reference()
    opt = _robust_optima()
    m = StochasticMap(n, **options)
    play(ds, m, rng=np.random.default_rng(seed), n_samples=n, bounded=True)
    xy = np.stack([m.marginal(f"x{min(ref['pose_ids'])}", f"l{j}")[0][:2]
                   for j in ref["landmark_ids"]])
    return ("; ".join(f"vs {k}: RMS {r:.3f} m, worst {w:.2f} m"
                      for k, (r, w) in ((k, _rms(xy, v)) for k, v in opt.items()))
            + (f"; left out at the end: {left_out(m, ds)}" if m.factor_history else ""))


def robust_optima_line() -> str:
    opt = _robust_optima()
    return "; ".join(f"{k} vs least squares: RMS {r:.3f} m, worst {w:.2f} m"
                     for k, (r, w) in ((k, _rms(v, opt["least squares"]))
                                       for k, v in opt.items() if k != "least squares"))


def sphere(options: dict[str, Any], seed: int, n: int) -> str:
    from experiments.pose_graph import ate, make_graph
    from experiments.posegraph_sim import sample_measurement

    g = make_graph("sphere2500", 0, seed)
    draw = np.random.default_rng(seed)
    m = Counting(StochasticMap(n, **options))
    for (i, j), z, c in zip(g.edges, g.measurements, g.covariances, strict=True):
        m.update(f"p{i}", f"p{j}", sample_measurement(z, c, n, rng=draw))

    def score() -> float:
        means = np.array([[0, 0, 0, 1.0, 0, 0, 0]] + [m.marginal("p0", f"p{k}")[0]
                                                      for k in range(1, g.n_poses)])
        return ate(means, g.poses_true)

    before = score()
    m.m.relinearize()
    return f"ATE {before:.3f} m; {m.summary()}; after one more relinearisation {score():.3f} m"


def clean(options: dict[str, Any], seeds: list[int], n: int) -> str:
    from experiments.posegraph_sim import sample_measurement, simulate_2d, simulate_3d

    out = []
    for planar in (True, False):
        lost = total = 0
        for seed in seeds:
            g = (simulate_2d if planar else simulate_3d)(600, rng=np.random.default_rng(seed))
            m = StochasticMap(n, gain="endpoints", inflation=1.002, gate=0.99, **options)
            draw = np.random.default_rng(seed + 1)
            for (i, j), z, cov, loop in zip(g.edges, g.measurements, g.covariances, g.is_loop,
                                            strict=True):
                r = m.update(f"p{i}", f"p{j}", sample_measurement(z, cov, n, rng=draw))
                lost += bool(loop) and r.kind == "rejected"
            total += g.n_loops
        out.append(f"{'planar' if planar else '3-D'} {100 * lost / total:.2f} % of {total}")
    return "; ".join(out)


def landmarks(options: dict[str, Any], kind: str, rate: float, seed: int, n: int) -> str:
    from mcsm_client.scenario import (
        PaperScenarioConfig,
        generate_paper_scenario,
        landmark_frame,
        odometry_samples,
        point_samples,
        pose_frame,
        score_map,
    )

    from experiments.outliers import KINDS, _offset

    cfg = PaperScenarioConfig(n_iterations=340, sigma_theta_deg=0.1)
    sc = generate_paper_scenario(cfg, np.random.default_rng(seed))
    seen: set[int] = set()
    resight = []
    for k, obs in enumerate(sc.observations):
        for s, (j, _) in enumerate(obs):
            if j in seen:
                resight.append((k, s))
            seen.add(j)
    rng = np.random.default_rng([seed, 7, KINDS.index(kind)])
    order = rng.permutation(len(resight))
    bad: dict[tuple[int, int], tuple[float, float]] = {}
    for i in order[: int(round(rate * len(resight)))]:
        k, s = resight[i]
        xy = np.asarray(sc.observations[k][s][1])
        if kind == "random":
            r, a = rng.uniform(1.0, cfg.range_m), rng.uniform(-np.pi / 2, np.pi / 2)
            bad[(k, s)] = (r * np.cos(a), r * np.sin(a))
        else:
            d = _offset(rng, True)
            bad[(k, s)] = (float(xy[0] + d[0]), float(xy[1] + d[1]))
    m = Counting(StochasticMap(n, **options))
    draw = np.random.default_rng([seed, 8])
    caught = 0
    for k in range(sc.n_iterations):
        m.update(pose_frame(k), pose_frame(k + 1),
                 odometry_samples(sc.odometry[k], cfg.odometry_cov, n, draw))
        for s, (j, xy) in enumerate(sc.observations[k]):
            wrong = (k, s) in bad
            pts = point_samples(bad[(k, s)] if wrong else xy, cfg.laser_cov, n, draw)
            caught += wrong and m.update(pose_frame(k + 1), landmark_frame(j),
                                         pts).kind == "rejected"
            if not wrong:
                m.update(pose_frame(k + 1), landmark_frame(j), pts)
        if k >= 1:
            m.m.remove(pose_frame(k))
    s = score_map(m.m, sc)
    out = (f"RMS {s['rms_m']:.3f} m, NEES/dof {s['nees_per_dof']:.2f}, recall "
           f"{caught / max(1, len(bad)):.2f}; {m.summary()}")
    m.m.relinearize()
    return out + f"; after one more relinearisation RMS {score_map(m.m, sc)['rms_m']:.3f} m"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("victoria", "sphere", "clean", "landmarks", "robust"))
    ap.add_argument("--options", action="append", default=None,
                    help="StochasticMap keywords as JSON (repeat: each, one process)")
    ap.add_argument("--seeds", nargs="*", type=int, default=None)
    ap.add_argument("--n-samples", type=int, default=None)
    ap.add_argument("--case", nargs=2, default=("nearby", "0.1"), metavar=("KIND", "RATE"))
    args = ap.parse_args(argv)
    for text in args.options or ["{}"]:
        opts = json.loads(text)
        if args.mode == "clean":
            print(f"clean {opts}: "
                  f"{clean(opts, args.seeds or [16, 17, 18, 19], args.n_samples or 200)}")
            continue
        if args.mode == "robust":
            print(f"robust optima: {robust_optima_line()}", flush=True)
        for seed in args.seeds or {"victoria": [1, 2, 11], "sphere": [1], "robust": [1, 2, 11],
                                   "landmarks": [8]}[args.mode]:
            if args.mode == "victoria":
                line = victoria(opts, seed, args.n_samples or 1000)
            elif args.mode == "robust":
                line = robust(opts, seed, args.n_samples or 1000)
            elif args.mode == "sphere":
                line = sphere(opts, seed, args.n_samples or 200)
            else:
                line = landmarks(opts, args.case[0], float(args.case[1]), seed,
                                 args.n_samples or 500)
            print(f"{args.mode} {opts} seed {seed}: {line}", flush=True)


if __name__ == "__main__":
    main()
