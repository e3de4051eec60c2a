"""Reproduce the paper's Figs. 4-6 and put EKF-SLAM and GTSAM next to the map (issue 7).

PAPER §4 (the paper's §6). Everything runs on one seeded scenario from
:func:`mcsm_client.scenario.generate_paper_scenario`, fed identically to

* the Monte Carlo map (:class:`mcsm.StochasticMap`) through ``run_scenario_on_map`` (bounded
  map: ``x0``, the current pose and the landmarks), for each listed variant
  (method, space, analysis, shrink, inflation) and N;
* the classic EKF-SLAM (``experiments/baselines/ekf_slam.py``);
* GTSAM iSAM2, step by step, and GTSAM's batch Levenberg-Marquardt optimum at the end
  (``experiments/baselines/gtsam_slam.py``, Cartesian point factors, same noise model).

Outputs (under ``--results``, default ``experiments/results``):

* ``fig4_accuracy.csv`` / ``fig5_accuracy.csv``: one row per (estimator, logged iteration): RMS
  of the landmark means against ground truth (m), NEES per degree of freedom with its two-sided
  95% chi-square bounds, number of landmarks, and CPU time per iteration (ms,
  ``time.process_time``: the machine is shared);
* ``fig4_rms.png``, ``fig4_nees.png`` and the same for fig5: the paper's plots plus NEES;
* ``fig6_timing.csv`` / ``fig6_timing.png``: time per update against the number of frames;
* ``paper_summary.csv``: the headline table (last logged iteration of every estimator).

Each accuracy run is cached as ``runs/<figure>_<label>.csv`` (the settings are in the file), so
an interrupted sweep resumes and the plots can be redrawn with ``--plot-only``.

Run ``python experiments/paper_figures.py --quick`` for the short settings used by
``make bench`` (stated in every output), ``--full`` for the paper's settings.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

from mcsm import StochasticMap  # noqa: E402
from mcsm_client.scenario import (  # noqa: E402
    PaperScenarioConfig,
    Scenario,
    generate_paper_scenario,
    landmark_estimates,
    landmark_nees,
    landmark_rms,
    landmarks_in_frame,
    run_scenario_on_map,
)

Array = npt.NDArray[np.float64]

SCENARIO_SEED = 20120137
SAMPLE_SEED = 4104


@dataclass(frozen=True)
class Variant:
    """One configuration of the map (the keyword arguments of ``StochasticMap``).

    Parameters
    ----------
    method, space, analysis : str
        As in :class:`mcsm.StochasticMap`.
    shrink : float or None
        Correlation-shrink constant.
    inflation : float
        Multiplicative inflation per loop closure.
    """

    method: str = "joint"
    space: str = "tangent"
    analysis: str = "ensrf"
    shrink: float | None = None
    inflation: float = 1.0

    def label(self, n_samples: int) -> str:
        """Short, file-name-safe name, e.g. ``joint-tangent-ensrf-N1000``."""
        parts = [self.method, self.space]
        if self.method == "joint":
            parts.append(self.analysis)
        if self.shrink is not None:
            parts.append(f"shrink{self.shrink:g}")
        if self.inflation != 1.0:
            parts.append(f"infl{self.inflation:g}")
        return "-".join(parts) + f"-N{n_samples}"


@dataclass(frozen=True)
class AccuracyRun:
    """A map variant at one N for a number of iterations."""

    variant: Variant
    n_samples: int
    n_iterations: int


FIELDS = [
    "figure",
    "sigma_theta_deg",
    "estimator",
    "label",
    "n_samples",
    "iteration",
    "rms_m",
    "nees_per_dof",
    "nees_lo95",
    "nees_hi95",
    "n_landmarks",
    "ms_per_iteration",
    "ms_per_update",
]


def nees_bounds(n_landmarks: int, dof: int = 2) -> tuple[float, float]:
    """Two-sided 95% bounds of the average NEES per dof over ``n_landmarks`` independent errors.

    ``sum NEES ~ chi2(dof * K)``; divided by ``dof * K``. Landmark errors share the robot's
    pose errors, so the bounds are a guide, not an exact test.
    """
    from scipy.stats import chi2

    k = dof * max(n_landmarks, 1)
    return float(chi2.ppf(0.025, k) / k), float(chi2.ppf(0.975, k) / k)


def _row(
    figure: str,
    scenario: Scenario,
    estimator: str,
    label: str,
    n_samples: int,
    iteration: int,
    means: Array,
    covs: Array | None,
    truth: Array,
    ms_iter: float,
    ms_update: float,
) -> dict[str, Any]:
    k = means.shape[0]
    lo, hi = nees_bounds(k)
    nees = landmark_nees(means, covs, truth) if covs is not None else float("nan")
    return {
        "figure": figure,
        "sigma_theta_deg": scenario.config.sigma_theta_deg,
        "estimator": estimator,
        "label": label,
        "n_samples": n_samples,
        "iteration": iteration,
        "rms_m": landmark_rms(means, truth),
        "nees_per_dof": nees,
        "nees_lo95": lo,
        "nees_hi95": hi,
        "n_landmarks": k,
        "ms_per_iteration": ms_iter,
        "ms_per_update": ms_update,
    }


def _log_steps(n_iterations: int, every: int) -> set[int]:
    steps = set(range(every, n_iterations + 1, every))
    steps.update({1, n_iterations})
    return steps


def run_map(
    figure: str,
    scenario: Scenario,
    run: AccuracyRun,
    *,
    log_every: int,
    seed: int,
    partial: Callable[[list[dict[str, Any]]], None] | None = None,
) -> list[dict[str, Any]]:
    """Feed the scenario into one map variant; score it every ``log_every`` iterations.

    CPU time (``time.process_time``; the machine is shared, wall time would count waits
    for a core) per iteration covers the odometry update, the point updates and the removal of
    the old pose (scoring excluded); ``ms_per_update`` divides it by the number of updates in the
    logging window (odometry + sightings). ``partial(rows)`` is called every 5 logged
    iterations, so a run cut short still leaves its curve.
    """
    v = run.variant
    smap = StochasticMap(
        run.n_samples,
        method=v.method,
        space=v.space,
        analysis=v.analysis,
        shrink=v.shrink,
        inflation=v.inflation,
        gate=None,  # the paper's filter alone (the gate: experiments/outliers.py)
    )
    truth_all = landmarks_in_frame(scenario, 0)
    rows: list[dict[str, Any]] = []
    wanted = _log_steps(run.n_iterations, log_every)
    clock = {"t": time.process_time(), "busy": 0.0, "iters": 0, "updates": 0}
    label = v.label(run.n_samples)

    def callback(k: int, m: Any) -> None:
        now = time.process_time()
        clock["busy"] += now - clock["t"]
        clock["iters"] += 1
        clock["updates"] += 1 + len(scenario.observations[k - 1])
        if k in wanted:
            ids, means, covs = landmark_estimates(m, range(truth_all.shape[0]))
            rows.append(
                _row(
                    figure,
                    scenario,
                    "mcsm",
                    label,
                    run.n_samples,
                    k,
                    means,
                    covs,
                    truth_all[ids],
                    1e3 * clock["busy"] / clock["iters"],
                    1e3 * clock["busy"] / clock["updates"],
                )
            )
            clock.update(busy=0.0, iters=0, updates=0)
            if partial is not None and len(rows) % 5 == 0:
                partial(rows)
        clock["t"] = time.process_time()

    rng = np.random.default_rng(seed)
    try:
        run_scenario_on_map(
            scenario, smap, run.n_samples, rng, callback=callback, n_iterations=run.n_iterations
        )
    except Exception as e:  # a diverged run is a result, not a crash of the sweep
        failed_at = (rows[-1]["iteration"] if rows else 0) + 1
        print(
            f"  {label}: stopped after iteration {failed_at - 1}: {type(e).__name__}: {e}",
            flush=True,
        )
        if rows:
            nan = float("nan")
            rows.append({**rows[-1], "iteration": failed_at, "rms_m": nan, "nees_per_dof": nan})
    return rows


def run_ekf(figure: str, scenario: Scenario, n_iterations: int, log_every: int) -> list[dict]:
    """EKF-SLAM on the same readings, scored like the map."""
    from experiments.baselines.ekf_slam import run_ekf_on_scenario

    truth_all = landmarks_in_frame(scenario, 0)
    rows: list[dict[str, Any]] = []
    wanted = _log_steps(n_iterations, log_every)
    clock = {"t": time.process_time(), "busy": 0.0, "iters": 0, "updates": 0}

    def callback(k: int, ekf: Any) -> None:
        now = time.process_time()
        clock["busy"] += now - clock["t"]
        clock["iters"] += 1
        clock["updates"] += 1 + len(scenario.observations[k - 1])
        if k in wanted:
            ids, means, covs = ekf.landmark_estimates()
            rows.append(
                _row(
                    figure,
                    scenario,
                    "ekf",
                    "ekf",
                    0,
                    k,
                    means,
                    covs,
                    truth_all[ids],
                    1e3 * clock["busy"] / clock["iters"],
                    1e3 * clock["busy"] / clock["updates"],
                )
            )
            clock.update(busy=0.0, iters=0, updates=0)
        clock["t"] = time.process_time()

    run_ekf_on_scenario(scenario, callback=callback, n_iterations=n_iterations)
    return rows


def run_gtsam(
    figure: str, scenario: Scenario, n_iterations: int, log_every: int, nees_every: int
) -> list[dict]:
    """iSAM2 step by step (scored every ``log_every``) and the batch LM optimum at the end."""
    import gtsam

    from experiments.baselines import gtsam_slam as gs

    truth_all = landmarks_in_frame(scenario, 0)
    problem = gs.problem_from_scenario(scenario, n_iterations)
    wanted = sorted(_log_steps(n_iterations, log_every))
    params = gtsam.ISAM2Params()
    isam = gtsam.ISAM2(params)
    estimate: dict[int, Array] = {}
    landmarks: dict[int, Array] = {}
    rows: list[dict[str, Any]] = []
    busy, iters, updates = 0.0, 0, 0
    for k, step in enumerate(problem.steps):
        graph, values = gs.step_factors(step, estimate, landmarks, problem.first_pose)
        t0 = time.process_time()
        isam.update(graph, values)
        busy += time.process_time() - t0
        if k == 0:
            continue
        iters += 1
        updates += 1 + len(step.sightings)
        if k in wanted:
            current = isam.calculateEstimate()
            ids = sorted(landmarks)
            pos = gs.landmark_positions(current, ids)
            means = np.stack([pos[j] for j in ids]) if ids else np.zeros((0, 2))
            covs = None
            if k % nees_every == 0 or k == n_iterations:
                covs = np.stack([np.asarray(isam.marginalCovariance(gs.L(j))) for j in ids])
            rows.append(
                _row(
                    figure,
                    scenario,
                    "isam2",
                    "isam2",
                    0,
                    k,
                    means,
                    covs,
                    truth_all[ids],
                    1e3 * busy / iters,
                    1e3 * busy / updates,
                )
            )
            busy, iters, updates = 0.0, 0, 0
            last = current.atPose2(gs.X(step.pose))
            estimate[step.pose] = np.array([last.x(), last.y(), last.theta()])
    # Batch optimum of the whole run, started from iSAM2's final estimate.
    graph, initial = gs.build_graph_2d(problem)
    t0 = time.process_time()
    start = isam.calculateEstimate()
    result = gs.batch_optimum(graph, start)
    lm_s = time.process_time() - t0
    ids = sorted(landmarks)
    pos = gs.landmark_positions(result, ids)
    covs_d = gs.landmark_covariances(graph, result, ids)
    rows.append(
        _row(
            figure,
            scenario,
            "gtsam-lm",
            "gtsam-lm",
            0,
            n_iterations,
            np.stack([pos[j] for j in ids]),
            np.stack([covs_d[j] for j in ids]),
            truth_all[ids],
            1e3 * lm_s,
            float("nan"),
        )
    )
    return rows


def _write_csv(path: Path, rows: Sequence[dict[str, Any]], header: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        f.write("# " + json.dumps(header, sort_keys=True) + "\n")
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        for r in rows:
            if r:
                w.writerow(r)


def read_csv(path: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """Read a results CSV written by this module: ``(header settings, rows)``."""
    with open(path) as f:
        first = f.readline()
        header = json.loads(first[2:]) if first.startswith("# ") else {}
        if not first.startswith("# "):
            f.seek(0)
        rows = list(csv.DictReader(f))
    for r in rows:
        for key in FIELDS[5:]:
            r[key] = float(r[key]) if r[key] not in ("", None) else float("nan")
        r["sigma_theta_deg"] = float(r["sigma_theta_deg"])
        r["n_samples"] = int(float(r["n_samples"]))
    return header, rows


def read_run(path: Path) -> list[dict[str, Any]]:
    """Rows of one cached run; map rows are labelled by the run's file name.

    The file name carries the shortened-run suffix (``-it400``) and ``.partial`` for a run that
    was cut short, which the plots and tables then show.
    """
    rows = read_csv(path)[1]
    figure = path.name.split("_", 1)[0]
    name = path.name[len(figure) + 1 : -len(".csv")]
    if name.endswith(".partial"):
        name = name[: -len(".partial")] + " (partial)"
    for r in rows:
        if r["estimator"] == "mcsm":
            r["label"] = name
    return rows


def accuracy_figure(
    figure: str,
    sigma_theta_deg: float,
    runs: Sequence[AccuracyRun],
    *,
    n_iterations: int,
    log_every: int,
    results: Path,
    baselines: bool = True,
    force: bool = False,
    only_runs: Sequence[str] | None = None,
) -> list[dict[str, Any]]:
    """Run (or reuse cached) accuracy runs for one figure; returns all rows.

    ``only_runs`` restricts the map runs to labels starting with one of its strings (several
    processes can then share a sweep; the baselines are skipped too).
    """
    config = PaperScenarioConfig(n_iterations=n_iterations, sigma_theta_deg=sigma_theta_deg)
    scenario = generate_paper_scenario(config, np.random.default_rng(SCENARIO_SEED))
    base_header = {
        "scenario": asdict(config),
        "scenario_seed": SCENARIO_SEED,
        "sample_seed": SAMPLE_SEED,
        "n_sightings": scenario.n_sightings,
    }
    rows: list[dict[str, Any]] = []
    jobs: list[tuple[str, Callable[[], list[dict[str, Any]]], dict[str, Any]]] = []
    if only_runs:
        runs = [
            r for r in runs if any(r.variant.label(r.n_samples).startswith(o) for o in only_runs)
        ]
        baselines = False
    if baselines:
        jobs.append(("ekf", lambda: run_ekf(figure, scenario, n_iterations, log_every), {}))
        jobs.append(
            (
                "gtsam",
                lambda: run_gtsam(figure, scenario, n_iterations, log_every, 10 * log_every),
                {},
            )
        )
    for run in runs:
        its = min(run.n_iterations, n_iterations)
        run_i = AccuracyRun(run.variant, run.n_samples, its)
        name = run.variant.label(run.n_samples) + (f"-it{its}" if its != n_iterations else "")
        jobs.append(
            (
                name,
                lambda r=run_i, name=name: run_map(
                    figure,
                    scenario,
                    r,
                    log_every=log_every,
                    seed=SAMPLE_SEED,
                    partial=lambda rows, name=name: _write_csv(
                        results / "runs" / f"{figure}_{name}.partial.csv", rows, {"partial": True}
                    ),
                ),
                {"variant": asdict(run.variant), "n_samples": run.n_samples, "iterations": its},
            )
        )
    for name, job, extra in jobs:
        path = results / "runs" / f"{figure}_{name}.csv"
        header = {**base_header, **extra, "log_every": log_every}
        if path.exists() and not force:
            old_header, _ = read_csv(path)
            old_header.pop("wall_s", None)
            if old_header == json.loads(json.dumps(header, sort_keys=True)):
                print(f"{figure} {name}: cached ({path.relative_to(results)})", flush=True)
                rows.extend(read_run(path))
                continue
        t0 = time.perf_counter()
        new_rows = job()
        header["wall_s"] = round(time.perf_counter() - t0, 1)
        _write_csv(path, new_rows, header)
        path.with_name(path.stem + ".partial.csv").unlink(missing_ok=True)
        rows.extend(read_run(path))
        last = [r for r in new_rows if r and r["iteration"] > 0]
        if last:
            r = last[-1]
            print(
                f"{figure} {name}: it {r['iteration']} rms {r['rms_m']:.3f} m "
                f"nees {r['nees_per_dof']:.3g} ({header['wall_s']} s)",
                flush=True,
            )
    return rows


# --------------------------------------------------------------------------- Fig. 6: timing


def _random_pose(rng: np.random.Generator, scale_m: float) -> Array:
    """One random AT mean ``x y z qw qx qy qz``: a translation and a moderate rotation."""
    from mcsm.core.quat import qexp

    t = rng.normal(0.0, scale_m, 3)
    q = qexp(rng.normal(0.0, 0.3, 3))
    return np.concatenate([t, q])


def _noisy_samples(mean: Array, sigma_t: float, sigma_r: float, n: int, rng: np.random.Generator):
    """``(n, 7)`` samples around ``mean``: additive translation, body-frame rotation noise."""
    from mcsm.core.quat import qexp, qmul

    out = np.empty((n, 7))
    out[:, :3] = mean[:3] + rng.normal(0.0, sigma_t, (n, 3))
    out[:, 3:] = qmul(mean[3:], qexp(rng.normal(0.0, sigma_r, (n, 3))))
    return out


def time_map_updates(
    n_samples: int,
    frame_counts: Sequence[int],
    *,
    method: str,
    space: str,
    updates_per_point: int,
    rng: np.random.Generator,
) -> list[dict[str, Any]]:
    """Time per AT update (case II, full 6-DoF) against the number of frames.

    The map grows by attaching each new frame to a random existing one (case I, O(N)); at each
    count in ``frame_counts`` it takes ``updates_per_point`` full-AT updates between random
    existing frames (the paper's "10 random updates between existing frames"), each timed. Only
    the updates at the listed counts are timed and applied, which keeps the sweep affordable at
    N = 5000; the cost of an update depends on M and N, not on the history.
    """
    from mcsm.core.at import compound, invert

    smap = StochasticMap(n_samples, method=method, space=space, gate=None)
    truth: dict[str, Array] = {"f0": np.array([0, 0, 0, 1.0, 0, 0, 0])}
    n_frames = 1
    rows: list[dict[str, Any]] = []
    for target in sorted(frame_counts):
        while n_frames < target:
            name = f"f{n_frames}"
            parent = f"f{int(rng.integers(n_frames))}"
            rel = _random_pose(rng, 5.0)
            truth[name] = compound(truth[parent], rel)
            smap.update(parent, name, _noisy_samples(rel, 0.1, 0.01, n_samples, rng))
            n_frames += 1
        times = []
        for _ in range(updates_per_point):
            a, b = rng.choice(n_frames, size=2, replace=False)
            rel = compound(invert(truth[f"f{a}"]), truth[f"f{b}"])
            x = _noisy_samples(rel, 0.05, 0.005, n_samples, rng)
            t0 = time.process_time()
            smap.update(f"f{a}", f"f{b}", x)
            times.append(time.process_time() - t0)
        rows.append(
            {
                "estimator": "mcsm",
                "method": method,
                "space": space,
                "n_samples": n_samples,
                "n_frames": n_frames,
                "median_ms": 1e3 * float(np.median(times)),
                "min_ms": 1e3 * float(np.min(times)),
                "max_ms": 1e3 * float(np.max(times)),
                "repeats": len(times),
            }
        )
        print(
            f"fig6 {method}/{space} N={n_samples} M={n_frames}: {rows[-1]['median_ms']:.2f} ms",
            flush=True,
        )
    return rows


def time_ekf_updates(
    frame_counts: Sequence[int], *, dof: int, updates_per_point: int, rng: np.random.Generator
) -> list[dict[str, Any]]:
    """Time of one EKF stochastic-map update between two frames of an ``M``-frame map.

    The classic stochastic map (Smith, Self and Cheeseman) holds all ``M`` frames' poses
    (``dof`` each) in one state with a full covariance; a relative-pose observation between two
    frames has a Jacobian that is nonzero only on their two blocks, so ``P Hᵀ`` is
    ``O(M · dof²)`` and the covariance update ``P - K S Kᵀ`` is ``O((M · dof)²)``: the same
    operations as ``EkfSlam.observe``, generalised to pose-to-pose observations. The values of
    the state do not change the cost; a random SPD covariance stands in.
    """
    rows: list[dict[str, Any]] = []
    for m in sorted(frame_counts):
        n = m * dof
        a_mat = rng.normal(size=(n, n)) / np.sqrt(n)
        p = a_mat @ a_mat.T + np.eye(n)
        x = np.zeros(n)
        r = np.eye(dof) * 0.01
        times = []
        for _ in range(updates_per_point):
            a, b = rng.choice(m, size=2, replace=False)
            ia, ib = a * dof, b * dof
            h_a = -np.eye(dof)
            h_b = np.eye(dof)
            t0 = time.process_time()
            ph = p[:, ia : ia + dof] @ h_a.T + p[:, ib : ib + dof] @ h_b.T  # (n, dof)
            s = h_a @ ph[ia : ia + dof] + h_b @ ph[ib : ib + dof] + r
            gain = np.linalg.solve(s, ph.T).T
            innov = rng.normal(size=dof) * 0.01
            x += gain @ innov
            p -= gain @ s @ gain.T
            p = 0.5 * (p + p.T)
            times.append(time.process_time() - t0)
        rows.append(
            {
                "estimator": "ekf",
                "method": f"ekf-{dof}dof",
                "space": "",
                "n_samples": 0,
                "n_frames": m,
                "median_ms": 1e3 * float(np.median(times)),
                "min_ms": 1e3 * float(np.min(times)),
                "max_ms": 1e3 * float(np.max(times)),
                "repeats": len(times),
            }
        )
        print(f"fig6 ekf {dof}-dof M={m}: {rows[-1]['median_ms']:.2f} ms", flush=True)
    return rows


TIMING_FIELDS = [
    "estimator",
    "method",
    "space",
    "n_samples",
    "n_frames",
    "median_ms",
    "min_ms",
    "max_ms",
    "repeats",
]


def timing_figure(
    results: Path,
    *,
    sample_counts: Sequence[int],
    frame_counts: Sequence[int],
    updates_per_point: int,
    variants: Sequence[tuple[str, str]],
    paper_max_n: int,
    force: bool = False,
) -> list[dict[str, Any]]:
    """Fig. 6 sweep (cached per configuration under ``runs/``)."""
    rows: list[dict[str, Any]] = []
    header = {"frame_counts": list(frame_counts), "updates_per_point": updates_per_point}
    jobs: list[tuple[str, Callable[[], list[dict[str, Any]]]]] = []
    for method, space in variants:
        for n in sample_counts:
            if method == "paper" and n > paper_max_n:
                continue
            jobs.append(
                (
                    f"fig6_{method}-{space}-N{n}",
                    lambda m=method, s=space, n=n: time_map_updates(
                        n,
                        frame_counts,
                        method=m,
                        space=s,
                        updates_per_point=updates_per_point,
                        rng=np.random.default_rng(SCENARIO_SEED + n),
                    ),
                )
            )
    for dof in (3, 6):
        jobs.append(
            (
                f"fig6_ekf-{dof}dof",
                lambda d=dof: time_ekf_updates(
                    frame_counts,
                    dof=d,
                    updates_per_point=updates_per_point,
                    rng=np.random.default_rng(SCENARIO_SEED),
                ),
            )
        )
    for name, job in jobs:
        path = results / "runs" / f"{name}.csv"
        if path.exists() and not force:
            with open(path) as f:
                first = f.readline()
                if first.startswith("# ") and json.loads(first[2:]) == header:
                    rows.extend(list(csv.DictReader(f)))
                    print(f"{name}: cached", flush=True)
                    continue
        new = job()
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "w", newline="") as f:
            f.write("# " + json.dumps(header, sort_keys=True) + "\n")
            w = csv.DictWriter(f, fieldnames=TIMING_FIELDS)
            w.writeheader()
            w.writerows(new)
        rows.extend(new)
    for r in rows:
        for key in ("n_samples", "n_frames", "repeats"):
            r[key] = int(float(r[key]))
        for key in ("median_ms", "min_ms", "max_ms"):
            r[key] = float(r[key])
    return rows


# --------------------------------------------------------------------------- plots and tables


def _series(rows: Sequence[dict[str, Any]]) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        if r["iteration"] > 0:
            out.setdefault(r["label"], []).append(r)
    for v in out.values():
        v.sort(key=lambda r: r["iteration"])
    # The same configuration run to different lengths (same seeds, so identical where they
    # overlap): keep the longest.
    best: dict[str, str] = {}
    for label, v in out.items():
        base = label.split("-it")[0].split(" (")[0]
        if base not in best or v[-1]["iteration"] > out[best[base]][-1]["iteration"]:
            best[base] = label
    return {label: v for label, v in out.items() if label in best.values()}


def _style(label: str) -> dict[str, Any]:
    if label == "ekf":
        return {"color": "black", "lw": 2.0, "ls": "-"}
    if label == "isam2":
        return {"color": "0.5", "lw": 1.5, "ls": "--"}
    colors = {"N200": "tab:blue", "N1000": "tab:orange", "N5000": "tab:green"}
    n_key = (
        label.split("-")[-1] if not label.split("-")[-1].startswith("it") else label.split("-")[-2]
    )
    style: dict[str, Any] = {"color": colors.get(n_key, "tab:purple"), "lw": 1.2}
    if label.startswith("paper"):
        style["ls"] = ":"
    elif "shrink" in label or "infl" in label:
        style["ls"] = "-."
    elif "quaternion" in label:
        style["ls"] = (0, (5, 1))
    else:
        style["ls"] = "-"
    return style


def plot_accuracy(rows: Sequence[dict[str, Any]], figure: str, title: str, out: Path) -> None:
    """RMS vs iteration (``<figure>_rms.png``) and NEES vs iteration (``<figure>_nees.png``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series = _series(rows)
    lm = [r for r in rows if r["label"] == "gtsam-lm"]
    series.pop("gtsam-lm", None)
    fig, ax = plt.subplots(figsize=(8, 4.8))
    for label, rs in series.items():
        ax.plot(
            [r["iteration"] for r in rs], [r["rms_m"] for r in rs], label=label, **_style(label)
        )
    for r in lm:
        ax.plot([r["iteration"]], [r["rms_m"]], "k*", ms=10, label="GTSAM batch optimum")
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("RMS landmark error (m)")
    ax.axvline(340, color="0.8", lw=0.8)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / f"{figure}_rms.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(8, 4.8))
    for label, rs in series.items():
        pts = [(r["iteration"], r["nees_per_dof"]) for r in rs if np.isfinite(r["nees_per_dof"])]
        if pts:
            ax.plot(*zip(*pts, strict=True), label=label, **_style(label))
    for r in lm:
        ax.plot([r["iteration"]], [r["nees_per_dof"]], "k*", ms=10, label="GTSAM batch optimum")
    bounds = series.get("ekf") or next(iter(series.values()), [])
    if bounds:
        its = [r["iteration"] for r in bounds]
        ax.fill_between(
            its,
            [r["nees_lo95"] for r in bounds],
            [r["nees_hi95"] for r in bounds],
            color="0.85",
            label="95% bounds (independent landmarks)",
        )
    ax.axhline(1.0, color="0.4", lw=0.8)
    ax.set_yscale("log")
    ax.set_xlabel("iteration")
    ax.set_ylabel("landmark NEES per dof")
    ax.set_title(title + ": consistency")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / f"{figure}_nees.png", dpi=110)
    plt.close(fig)


def plot_timing(rows: Sequence[dict[str, Any]], title: str, out: Path) -> None:
    """Fig. 6: median time per update against the number of frames (log y)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        key = (
            f"{r['method']}-{r['space']}-N{r['n_samples']}"
            if r["estimator"] == "mcsm"
            else f"EKF stochastic map ({r['method'].split('-')[1]})"
        )
        groups.setdefault(key, []).append(r)
    fig, ax = plt.subplots(figsize=(8, 4.8))
    for key, rs in sorted(groups.items()):
        rs.sort(key=lambda r: r["n_frames"])
        style = (
            _style(key)
            if not key.startswith("EKF")
            else {"color": "black", "ls": "-" if "6dof" in key else "--", "lw": 2.0}
        )
        ax.plot(
            [r["n_frames"] for r in rs],
            [r["median_ms"] for r in rs],
            marker="o",
            ms=3,
            label=key,
            **style,
        )
    ax.set_yscale("log")
    ax.set_xlabel("frames in the map")
    ax.set_ylabel("time per update (ms, median)")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(out / "fig6_timing.png", dpi=110)
    plt.close(fig)


def growth_exponents(rows: Sequence[dict[str, Any]], min_frames: int = 100) -> list[dict]:
    """Fitted ``b`` of ``time ≈ a · M^b`` per series (least squares in log-log, M >= min_frames).

    ``b ≈ 1`` is linear growth with the number of frames (the map), ``b ≈ 2`` quadratic (EKF).
    """
    groups: dict[tuple[str, str, str, int], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["estimator"], r["method"], r["space"], r["n_samples"]), []).append(r)
    out = []
    for (est, method, space, n), rs in sorted(groups.items()):
        pts = [(r["n_frames"], r["median_ms"]) for r in rs if r["n_frames"] >= min_frames]
        if len(pts) < 2:
            continue
        m, t = np.log([p[0] for p in pts]), np.log([p[1] for p in pts])
        slope = float(np.polyfit(m, t, 1)[0])
        at_max = max(rs, key=lambda r: r["n_frames"])
        out.append(
            {
                "estimator": est,
                "method": method,
                "space": space,
                "n_samples": n,
                "exponent": round(slope, 2),
                "max_frames": at_max["n_frames"],
                "ms_at_max_frames": round(at_max["median_ms"], 2),
            }
        )
    return out


def summary_rows(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Last logged iteration of each estimator, with the ratio of its RMS to the EKF's."""
    out = []
    by_fig: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        by_fig.setdefault(r["figure"], []).append(r)
    for fig_name, rs in sorted(by_fig.items()):
        series = _series(rs)
        ekf = series.get("ekf", [])
        for label, s in series.items():
            last = s[-1]
            ref = [e for e in ekf if e["iteration"] == last["iteration"]]
            # gtsam-lm has one row whose time is the whole batch solve, not per iteration
            mean_ms = (
                float("nan")
                if label == "gtsam-lm"
                else float(np.mean([r["ms_per_iteration"] for r in s]))
            )
            out.append(
                {
                    "figure": fig_name,
                    "estimator": label,
                    "iteration": int(last["iteration"]),
                    "rms_m": last["rms_m"],
                    "rms_vs_ekf": last["rms_m"] / ref[0]["rms_m"] if ref else float("nan"),
                    "nees_per_dof": last["nees_per_dof"],
                    "nees_95": f"[{last['nees_lo95']:.2f}, {last['nees_hi95']:.2f}]",
                    "ms_per_iteration": mean_ms,
                }
            )
    return out


def print_table(rows: Sequence[dict[str, Any]]) -> str:
    """Markdown table of :func:`summary_rows`."""
    lines = [
        "| figure | estimator | iteration | RMS (m) | × EKF | NEES/dof | 95% bounds "
        "| ms/iteration |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['figure']} | {r['estimator']} | {r['iteration']} | {r['rms_m']:.3f} | "
            f"{r['rms_vs_ekf']:.2f} | {r['nees_per_dof']:.3g} | {r['nees_95']} | "
            f"{r['ms_per_iteration']:.2f} |"
        )
    return "\n".join(lines)


# --------------------------------------------------------------------------- settings and CLI


def settings(quick: bool) -> dict[str, Any]:
    """The sweep: ``--full`` is the paper's, ``--quick`` what ``make bench`` runs."""
    joint = Variant()
    tuned200 = Variant(shrink=4.0, inflation=1.0002)
    paper_t = Variant(method="paper")
    if quick:
        its = 360  # just past the loop closure at ~340
        return {
            "iterations": its,
            "log_every": 20,
            "fig4_runs": [
                AccuracyRun(joint, 200, its),
                AccuracyRun(joint, 1000, its),
                AccuracyRun(paper_t, 200, its),
            ],
            "fig5_runs": [AccuracyRun(joint, 200, its)],
            "sample_counts": [200, 1000],
            "frame_counts": [25, 50, 100, 200, 400],
            "updates_per_point": 3,
            "paper_max_n": 200,
        }
    its = 2000
    # Cheap runs first, so an interrupted sweep still has them. The machine (2 cores shared by
    # several jobs, ~8% of a core per process during these runs) could not afford 2000
    # iterations at N = 5000 or for the paper method: N = 5000 stops at 400 iterations (past the
    # loop closure at ~340) in Fig. 5 and at 1000 in Fig. 4, the paper method at 600, and the
    # run names say so ("-it400").
    return {
        "iterations": its,
        "log_every": 20,
        "fig4_runs": [
            AccuracyRun(joint, 200, its),
            AccuracyRun(tuned200, 200, its),
            AccuracyRun(paper_t, 200, 600),
            AccuracyRun(joint, 1000, its),
            AccuracyRun(joint, 5000, 400),
            AccuracyRun(joint, 5000, 1000),
            AccuracyRun(paper_t, 200, its),
        ],
        "fig5_runs": [
            AccuracyRun(joint, 200, its),
            AccuracyRun(tuned200, 200, its),
            AccuracyRun(paper_t, 200, 600),
            AccuracyRun(joint, 1000, its),
            AccuracyRun(joint, 5000, 400),
            AccuracyRun(paper_t, 200, its),
        ],
        "sample_counts": [200, 1000, 5000],
        "frame_counts": [25, 50, 100, 200, 300, 400],
        "updates_per_point": 5,
        "paper_max_n": 1000,
    }


def main(
    results: Path,
    *,
    quick: bool,
    figures: Sequence[str],
    plot_only: bool = False,
    force: bool = False,
    only_runs: Sequence[str] | None = None,
) -> str:
    """Run the requested figures, write CSV and PNG under ``results``, return the table."""
    results.mkdir(parents=True, exist_ok=True)
    cfg = settings(quick)
    mode = "quick" if quick else "full"
    all_rows: list[dict[str, Any]] = []
    for figure, sigma in (("fig4", 0.0), ("fig5", 0.1)):
        if figure not in figures:
            continue
        csv_path = results / f"{figure}_accuracy.csv"
        if plot_only:
            # Gather whatever runs exist (a sweep may still be going on or have been cut short).
            rows = [
                r for p in sorted((results / "runs").glob(f"{figure}_*.csv")) for r in read_run(p)
            ]
            _write_csv(csv_path, rows, {"mode": mode, "sigma_theta_deg": sigma})
        else:
            rows = accuracy_figure(
                figure,
                sigma,
                cfg[f"{figure}_runs"],
                n_iterations=cfg["iterations"],
                log_every=cfg["log_every"],
                results=results,
                force=force,
                only_runs=only_runs,
            )
            if only_runs:
                continue
            _write_csv(csv_path, rows, {"mode": mode, "sigma_theta_deg": sigma})
            rows = read_csv(csv_path)[1]
        title = (
            f"Fig. {figure[-1]}: σ_θ = {sigma:g}°, {cfg['iterations']} iterations ({mode} settings)"
        )
        plot_accuracy(rows, figure, title, results)
        all_rows.extend(rows)
    if "fig6" in figures:
        variants = [("joint", "tangent"), ("joint", "quaternion"), ("paper", "tangent")]
        if plot_only:
            t_rows = []
            for p in sorted((results / "runs").glob("fig6_*.csv")):
                with open(p) as f:
                    f.readline()
                    t_rows.extend(csv.DictReader(f))
            for r in t_rows:
                for key in ("n_samples", "n_frames", "repeats"):
                    r[key] = int(float(r[key]))
                for key in ("median_ms", "min_ms", "max_ms"):
                    r[key] = float(r[key])
        else:
            t_rows = timing_figure(
                results,
                sample_counts=cfg["sample_counts"],
                frame_counts=cfg["frame_counts"],
                updates_per_point=cfg["updates_per_point"],
                variants=variants,
                paper_max_n=cfg["paper_max_n"],
                force=force,
            )
        with open(results / "fig6_timing.csv", "w", newline="") as f:
            f.write(f"# mode={mode}\n")
            w = csv.DictWriter(f, fieldnames=TIMING_FIELDS)
            w.writeheader()
            w.writerows(t_rows)
        growth = growth_exponents(t_rows)
        with open(results / "fig6_growth.csv", "w", newline="") as f:
            f.write(f"# mode={mode}; time ~ a * frames^exponent fitted over frames >= 100\n")
            w = csv.DictWriter(f, fieldnames=list(growth[0]))
            w.writeheader()
            w.writerows(growth)
        for g in growth:
            print(
                f"fig6 {g['estimator']} {g['method']}/{g['space']} N={g['n_samples']}: "
                f"time ~ frames^{g['exponent']}, {g['ms_at_max_frames']} ms at "
                f"{g['max_frames']} frames"
            )
        plot_timing(
            t_rows,
            f"Fig. 6: time per 6-DoF update vs frames ({cfg['updates_per_point']} updates per "
            f"point, {mode} settings)",
            results,
        )
    table = ""
    if all_rows:
        summary = summary_rows(all_rows)
        with open(results / "paper_summary.csv", "w", newline="") as f:
            f.write(f"# mode={mode}\n")
            w = csv.DictWriter(f, fieldnames=list(summary[0]))
            w.writeheader()
            w.writerows(summary)
        table = print_table(summary)
    return table


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="short settings (make bench)")
    mode.add_argument("--full", action="store_true", help="the paper's settings (default)")
    parser.add_argument("--results", type=Path, default=None, help="output directory")
    parser.add_argument("--figures", nargs="+", default=["fig4", "fig5", "fig6"])
    parser.add_argument(
        "--plot-only", action="store_true", help="gather the cached runs, redraw, no new runs"
    )
    parser.add_argument("--force", action="store_true", help="ignore cached runs")
    parser.add_argument("--only-runs", nargs="+", help="only map runs whose label starts so")
    args = parser.parse_args()
    default = ROOT / "experiments" / "results" / ("quick" if args.quick else "")
    out = main(
        args.results or default,
        quick=args.quick,
        figures=args.figures,
        plot_only=args.plot_only,
        force=args.force,
        only_runs=args.only_runs,
    )
    print(out)
