"""Issue 6: consistency of the Monte Carlo stochastic map at a fixed sample count.

Measures, on the paper's §6 circle scenario (PAPER §4; ``mcsm_client.scenario``), the landmark
RMS error and the landmark NEES per degree of freedom (1 = honest uncertainty) against ground
truth, iteration by iteration, for several update rules of :class:`mcsm.StochasticMap` and the
classic EKF-SLAM on identical readings (``experiments.baselines.ekf_slam``; with σ_θ = 0 it is
the exact Kalman filter). Optionally runs the public Victoria Park file (bounded map) and
compares the landmarks with GTSAM's batch optimum (Levenberg–Marquardt started from an iSAM2
pass) on the same Cartesian noise model.

Every run (variant, N, σ_θ, seed) is written to its own CSV under
``experiments/results/consistency/runs/`` and skipped when it exists (``--force`` re-runs), so
long settings can be split over background jobs and resumed; the summary, the acceptance
figures and the PNG plots are built from every run file present.

Examples
--------
Short settings (a few minutes)::

    .venv/bin/python -m experiments.consistency --quick

Full acceptance settings (long: run it in the background)::

    OMP_NUM_THREADS=1 nohup .venv/bin/python -m experiments.consistency --full > cons.log &

Rebuild tables and plots from the run files only::

    .venv/bin/python -m experiments.consistency --report-only
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from mcsm import StochasticMap
from mcsm.errors import McsmError
from mcsm_client.scenario import (
    PaperScenarioConfig,
    Scenario,
    generate_paper_scenario,
    landmark_nees,
    landmark_rms,
    landmarks_in_frame,
    run_scenario_on_map,
    score_map,
)

from experiments.baselines.ekf_slam import EkfSlam, run_ekf_on_scenario

Array = npt.NDArray[np.float64]

RESULTS = Path(__file__).resolve().parent / "results" / "consistency"

#: Acceptance thresholds of issue 6.
NEES_MAX = {1000: 2.0, 200: 3.0}
RMS_RATIO_MAX = 1.2


@dataclass(frozen=True)
class Variant:
    """One configuration of the map's update (the constructor options of StochasticMap)."""

    name: str
    method: str = "joint"
    analysis: str = "ensrf"
    shrink: float | None = None
    inflation: float = 1.0
    space: str = "tangent"

    def build(self, n_samples: int) -> StochasticMap:
        """A fresh map with these options, without a gate (the filter alone, as in the
        paper; the gate is measured in experiments/outliers.py)."""
        return StochasticMap(n_samples, method=self.method, space=self.space,
                             analysis=self.analysis, shrink=self.shrink,
                             inflation=self.inflation, gate=None)


VARIANTS: dict[str, Variant] = {v.name: v for v in (
    Variant("paper", method="paper"),
    Variant("enkf", analysis="enkf"),
    Variant("ensrf"),
    Variant("denkf", analysis="denkf"),
    Variant("ensrf-shrink4", shrink=4.0),
    Variant("ensrf-shrink4-infl1.0002", shrink=4.0, inflation=1.0002),
    Variant("ensrf-infl1.0002", inflation=1.0002),
    Variant("enkf-shrink4", analysis="enkf", shrink=4.0),
)}

#: Which variants the acceptance figures are printed for, per N (the remedies).
ACCEPT_VARIANTS = {1000: ("ensrf", "ensrf-shrink4"),
                   200: ("ensrf-shrink4", "ensrf-shrink4-infl1.0002")}

CSV_FIELDS = ["variant", "n_samples", "sigma_theta_deg", "seed", "iteration", "rms_m",
              "nees_per_dof", "n_landmarks", "ekf_rms_m", "ekf_nees_per_dof", "elapsed_s",
              "error", "core"]


# ---------------------------------------------------------------------------- runs


def core_revision() -> str:
    """Last git commit touching ``service/mcsm/core`` (``+dirty`` if it has local changes)."""
    import subprocess

    root = Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(["git", "log", "-1", "--format=%h", "--", "service/mcsm/core"],
                             cwd=root, capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "service/mcsm/core"],
                               cwd=root, capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev or "unknown") + ("+dirty" if dirty.strip() else "")


CORE_REVISION = core_revision()


def log_iterations(n_iterations: int, every: int) -> list[int]:
    """Iterations at which a run is scored: every ``every``, plus 340 (loop) and the last."""
    its = set(range(every, n_iterations + 1, every)) | {n_iterations}
    if n_iterations >= 340:
        its.add(340)
    return sorted(its)


def ekf_curve(scenario: Scenario, iterations: Sequence[int]) -> dict[int, tuple[float, float]]:
    """EKF-SLAM RMS and NEES per dof at the given iterations (identical readings)."""
    truth = landmarks_in_frame(scenario, 0)
    wanted = set(iterations)
    out: dict[int, tuple[float, float]] = {}

    def cb(k: int, ekf: EkfSlam) -> None:
        if k in wanted:
            ids, means, covs = ekf.landmark_estimates()
            out[k] = (landmark_rms(means, truth[ids]), landmark_nees(means, covs, truth[ids]))

    run_ekf_on_scenario(scenario, cb, n_iterations=max(iterations))
    return out


def run_file(variant: str, n_samples: int, sigma_theta_deg: float, seed: int,
             n_iterations: int, results: Path) -> Path:
    """Path of one run's CSV."""
    return (results / "runs" /
            f"{variant}_N{n_samples}_th{sigma_theta_deg:g}_s{seed}_T{n_iterations}.csv")


def run_one(variant: Variant, n_samples: int, scenario: Scenario, seed: int,
            iterations: Sequence[int], ekf: dict[int, tuple[float, float]],
            deadline_s: float | None = None) -> list[dict[str, Any]]:
    """Run one map on a scenario and score it at ``iterations``.

    A refused update (``McsmError``, e.g. ``NumericalError``) ends the run; the row at the next
    logged iteration records the error. The sample noise uses ``default_rng(seed + 1)`` (the
    scenario itself was drawn from ``default_rng(seed)``).
    """
    smap = variant.build(n_samples)
    rng = np.random.default_rng(seed + 1)
    wanted = set(iterations)
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    base = {"variant": variant.name, "n_samples": n_samples,
            "sigma_theta_deg": scenario.config.sigma_theta_deg, "seed": seed,
            "core": CORE_REVISION}

    class _Stop(Exception):
        pass

    def cb(k: int, m: StochasticMap) -> None:
        if k not in wanted:
            return
        s = score_map(m, scenario)
        e_rms, e_nees = ekf.get(k, (math.nan, math.nan))
        rows.append({**base, "iteration": k, "rms_m": s["rms_m"],
                     "nees_per_dof": s["nees_per_dof"], "n_landmarks": int(s["n_landmarks"]),
                     "ekf_rms_m": e_rms, "ekf_nees_per_dof": e_nees,
                     "elapsed_s": time.perf_counter() - t0, "error": ""})
        if deadline_s is not None and time.perf_counter() - t0 > deadline_s:
            raise _Stop

    try:
        run_scenario_on_map(scenario, smap, n_samples, rng, bounded=True, callback=cb,
                            n_iterations=max(iterations))
    except _Stop:
        pass
    except McsmError as err:
        done = rows[-1]["iteration"] if rows else 0
        nxt = [k for k in iterations if k > done]
        rows.append({**base, "iteration": nxt[0] if nxt else done, "rms_m": math.nan,
                     "nees_per_dof": math.nan, "n_landmarks": 0, "ekf_rms_m": math.nan,
                     "ekf_nees_per_dof": math.nan, "elapsed_s": time.perf_counter() - t0,
                     "error": f"{type(err).__name__}: {err}"})
    return rows


def write_rows(path: Path, rows: Iterable[dict[str, Any]]) -> None:
    """Write rows as CSV (atomically: a partial file never looks like a finished run)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: r.get(k, "") for k in CSV_FIELDS})
    tmp.replace(path)


def read_rows(results: Path) -> list[dict[str, Any]]:
    """Every row of every run file."""
    rows: list[dict[str, Any]] = []
    for p in sorted((results / "runs").glob("*.csv")):
        with open(p, newline="") as f:
            for r in csv.DictReader(f):
                row: dict[str, Any] = dict(r)
                for k in ("n_samples", "seed", "iteration", "n_landmarks"):
                    row[k] = int(float(row[k]))
                for k in ("sigma_theta_deg", "rms_m", "nees_per_dof", "ekf_rms_m",
                          "ekf_nees_per_dof", "elapsed_s"):
                    row[k] = float(row[k]) if row[k] not in ("", None) else math.nan
                row["n_iterations"] = int(p.stem.rsplit("_T", 1)[1])
                rows.append(row)
    return rows


# ---------------------------------------------------------------------------- report


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One line per run: values at 1000 and at the last iteration, max NEES over the run."""
    runs: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        key = (r["variant"], r["n_samples"], r["sigma_theta_deg"], r["seed"], r["n_iterations"])
        runs.setdefault(key, []).append(r)
    out = []
    for key, rs in sorted(runs.items(), key=lambda kv: (kv[0][2], kv[0][1], kv[0][0], kv[0][3])):
        rs.sort(key=lambda r: r["iteration"])
        last = rs[-1]
        at1000 = next((r for r in rs if r["iteration"] == 1000), None)
        nees = np.array([r["nees_per_dof"] for r in rs])
        err = next((r["error"] for r in rs if r["error"]), "")
        out.append({
            "variant": key[0], "n_samples": key[1], "sigma_theta_deg": key[2], "seed": key[3],
            "n_iterations": key[4], "last_iteration": last["iteration"],
            "rms_1000": at1000["rms_m"] if at1000 else math.nan,
            "ratio_1000": at1000["rms_m"] / at1000["ekf_rms_m"] if at1000 else math.nan,
            "nees_1000": at1000["nees_per_dof"] if at1000 else math.nan,
            "rms_final": last["rms_m"], "ekf_rms_final": last["ekf_rms_m"],
            "ratio_final": last["rms_m"] / last["ekf_rms_m"],
            "nees_final": last["nees_per_dof"], "ekf_nees_final": last["ekf_nees_per_dof"],
            "nees_max": float(np.nanmax(nees)) if np.isfinite(nees).any() else math.nan,
            "seconds": last["elapsed_s"], "error": err,
        })
    return out


def _fmt(x: float, digits: int = 3) -> str:
    if not np.isfinite(x):
        return "nan"
    if abs(x) >= 1e4 or (x != 0 and abs(x) < 1e-3):
        return f"{x:.2e}"
    return f"{x:.{digits}g}"


def print_summary(summary: list[dict[str, Any]], file: Any = sys.stdout) -> None:
    """A readable table (markdown) of :func:`summarise` output."""
    print("| σθ° | N | variant | seed | T | RMS@1000 (×EKF) / NEES | RMS final (×EKF) / NEES "
          "| EKF final RMS / NEES | max NEES | s | note |", file=file)
    print("|---|---|---|---|---|---|---|---|---|---|---|", file=file)
    for s in summary:
        print(f"| {s['sigma_theta_deg']:g} | {s['n_samples']} | {s['variant']} | {s['seed']} | "
              f"{s['last_iteration']}/{s['n_iterations']} | "
              f"{_fmt(s['rms_1000'])} ({_fmt(s['ratio_1000'])}×) / {_fmt(s['nees_1000'])} | "
              f"{_fmt(s['rms_final'])} ({_fmt(s['ratio_final'])}×) / {_fmt(s['nees_final'])} | "
              f"{_fmt(s['ekf_rms_final'])} / {_fmt(s['ekf_nees_final'])} | "
              f"{_fmt(s['nees_max'])} | {s['seconds']:.0f} | {s['error'][:60]} |", file=file)


def acceptance(summary: list[dict[str, Any]], n_iterations: int,
               file: Any = sys.stdout) -> bool:
    """Print issue 6's acceptance figures; True if every checked criterion holds."""
    ok_all = True
    print(f"\nAcceptance (σθ = 0, {n_iterations} iterations, NEES/dof at every logged "
          f"iteration, final RMS ≤ {RMS_RATIO_MAX}× EKF):", file=file)
    for n, nees_max in NEES_MAX.items():
        for name in ACCEPT_VARIANTS[n]:
            ok_all &= _accept_one(summary, name, n, nees_max, n_iterations, file)
    return ok_all


def _accept_one(summary: list[dict[str, Any]], name: str, n: int, nees_max: float,
                n_iterations: int, file: Any) -> bool:
    """Print and check one variant's acceptance lines (every complete seed)."""
    ok_all = True
    cands = [s for s in summary if s["variant"] == name and s["n_samples"] == n
             and s["sigma_theta_deg"] == 0.0 and s["n_iterations"] == n_iterations
             and s["last_iteration"] == n_iterations]
    if not cands:
        print(f"  N={n} {name}: no complete run at T={n_iterations}", file=file)
        return False
    for s in cands:
        ok = bool(s["nees_max"] <= nees_max and s["ratio_final"] <= RMS_RATIO_MAX)
        ok_all &= ok
        print(f"  N={n} {name} seed {s['seed']}: max NEES {_fmt(s['nees_max'])} "
              f"(≤ {nees_max}), final RMS {_fmt(s['rms_final'])} m = "
              f"{_fmt(s['ratio_final'])}× EKF {_fmt(s['ekf_rms_final'])} m "
              f"(≤ {RMS_RATIO_MAX}×): {'PASS' if ok else 'FAIL'}", file=file)
    return ok_all


def plot(rows: list[dict[str, Any]], results: Path, n_iterations: int) -> list[Path]:
    """RMS and NEES vs iteration, one PNG per σθ (first seed of each configuration)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    thetas = sorted({r["sigma_theta_deg"] for r in rows if r["n_iterations"] == n_iterations})
    for th in thetas:
        sel = [r for r in rows if r["sigma_theta_deg"] == th and r["n_iterations"] == n_iterations]
        seed0 = min(r["seed"] for r in sel)
        sel = [r for r in sel if r["seed"] == seed0]
        fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(11, 9), sharex=True)
        keys = sorted({(r["variant"], r["n_samples"]) for r in sel},
                      key=lambda k: (k[1], k[0]))
        styles = {200: ":", 1000: "-", 5000: "--"}
        for variant, n in keys:
            rs = sorted((r for r in sel if r["variant"] == variant and r["n_samples"] == n),
                        key=lambda r: r["iteration"])
            it = [r["iteration"] for r in rs]
            ax1.plot(it, [r["rms_m"] for r in rs], styles.get(n, "-."),
                     label=f"{variant} N={n}")
            ax2.plot(it, [r["nees_per_dof"] for r in rs], styles.get(n, "-."),
                     label=f"{variant} N={n}")
        ekf = {r["iteration"]: (r["ekf_rms_m"], r["ekf_nees_per_dof"]) for r in sel}
        it = sorted(ekf)
        ax1.plot(it, [ekf[k][0] for k in it], "k-", lw=2.5, label="EKF-SLAM")
        ax2.plot(it, [ekf[k][1] for k in it], "k-", lw=2.5, label="EKF-SLAM")
        ax1.set_yscale("log")
        ax1.set_ylabel("landmark RMS error (m)")
        ax2.set_yscale("log")
        ax2.axhline(1.0, color="grey", lw=0.8)
        ax2.axhline(2.0, color="red", lw=0.8, ls="--")
        ax2.set_ylabel("landmark NEES per dof")
        ax2.set_xlabel("iteration")
        ax1.axvline(340, color="grey", lw=0.8, ls=":")
        ax2.axvline(340, color="grey", lw=0.8, ls=":")
        ax1.set_title(f"§6 scenario, σθ = {th:g}°, seed {seed0}, bounded map")
        ax1.legend(fontsize=7, ncol=3)
        fig.tight_layout()
        p = results / f"consistency_theta{th:g}_T{n_iterations}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


# ---------------------------------------------------------------------------- Victoria Park


def _victoria_problem(max_poses: int | None) -> tuple[Any, str]:
    from mcsm_client.datasets import read_dataset

    from experiments.baselines import gtsam_slam as gs

    ds = read_dataset("gtsam:victoria_park.txt")
    tag = "full" if max_poses is None else f"P{max_poses}"
    return gs.problem_from_dataset(ds, max_poses=max_poses), tag


def _read_xy(path: Path, cols: tuple[str, str] = ("x", "y")) -> dict[int, Array]:
    out: dict[int, Array] = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if r[cols[0]] not in ("", "nan"):
                out[int(r["landmark"])] = np.array([float(r[cols[0]]), float(r[cols[1]])])
    return out


def _ekf_pass(problem: Any) -> tuple[EkfSlam, dict[int, Array]]:
    """EKF-SLAM over a PlanarProblem; also returns the filtered pose after each step."""
    ekf = EkfSlam(np.eye(3), np.eye(2))
    poses: dict[int, Array] = {}
    for st in problem.steps:
        if st.odometry is not None:
            ekf.predict(st.odometry.delta, st.odometry.cov)
        for s in st.sightings:
            ekf.observe(s.landmark, s.xy, s.cov)
        poses[st.pose] = ekf.pose
    return ekf, poses


def victoria_reference(max_poses: int | None, results: Path, init: str = "isam2") -> Path:
    """GTSAM batch optimum of Victoria Park on the Cartesian model, cached as a CSV.

    ``init="isam2"``: Levenberg–Marquardt started from an incremental iSAM2 pass (the issue's
    prescription; dead reckoning alone falls into a local minimum). ``init="ekf"``: LM started from
    the EKF-SLAM filtered trajectory and final landmarks (a cheaper fallback, labelled as such).
    """
    import gtsam
    from gtsam.symbol_shorthand import L, X

    from experiments.baselines import gtsam_slam as gs

    problem, tag = _victoria_problem(max_poses)
    path = results / f"victoria_reference_{init}_{tag}.csv"
    if path.exists():
        return path
    graph, initial = gs.build_graph_2d(problem)
    t0 = time.perf_counter()
    if init == "isam2":
        start = gs.isam2_incremental(problem).estimate
    else:
        ekf, poses = _ekf_pass(problem)
        start = gtsam.Values(initial)
        for i, p in poses.items():
            start.update(X(i), gtsam.Pose2(float(p[0]), float(p[1]), float(p[2])))
        ids, means, _ = ekf.landmark_estimates()
        for j, m in zip(ids, means, strict=True):
            start.update(L(int(j)), gtsam.Point2(float(m[0]), float(m[1])))
    t_init = time.perf_counter() - t0
    opt = gs.batch_optimum(graph, start)
    lm_ids = sorted({s.landmark for st in problem.steps for s in st.sightings})
    ref = gs.landmark_positions(opt, lm_ids)
    print(f"victoria reference ({init}, {tag}): init {t_init:.0f} s, LM error "
          f"{graph.error(start):.1f} -> {graph.error(opt):.1f}", flush=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["landmark", "x", "y"])
        for j in lm_ids:
            w.writerow([j, repr(float(ref[j][0])), repr(float(ref[j][1]))])
    return path


def run_victoria(n_samples: int, variant: Variant, seed: int, max_poses: int | None,
                 results: Path, log_every: int = 1000) -> Path:
    """Victoria Park (``gtsam:victoria_park.txt``) through a bounded map; estimates to a CSV.

    Frames ``x{i}`` / ``l{j}`` (dataset ids); odometry sampled with its covariance over the
    body-frame tangent (GTSAM's convention), sightings as Cartesian points. After each step the
    previous pose is removed (pose 0 kept as the anchor). The landmark means of the map, of the
    EKF-SLAM and of dead reckoning (first sighting) on the same readings are written to
    ``victoria_estimates_<variant>_N<N>_s<seed>_<length>.csv`` with run facts in
    ``victoria_runs.csv``; :func:`score_victoria` compares them with the GTSAM references.
    """
    from mcsm_client.sampling import sample_planar, sample_point

    problem, tag = _victoria_problem(max_poses)
    ekf, _ = _ekf_pass(problem)
    ekf_ids, ekf_means, _ = ekf.landmark_estimates()
    ekf_est = {int(j): m for j, m in zip(ekf_ids, ekf_means, strict=True)}

    pose = np.zeros(3)
    dr: dict[int, Array] = {}
    for st in problem.steps:
        if st.odometry is not None:
            dx, dy, dth = st.odometry.delta
            c, s_ = np.cos(pose[2]), np.sin(pose[2])
            pose = pose + np.array([c * dx - s_ * dy, s_ * dx + c * dy, dth])
        for s in st.sightings:
            if s.landmark not in dr:
                c, s_ = np.cos(pose[2]), np.sin(pose[2])
                dr[s.landmark] = pose[:2] + np.array([c * s.xy[0] - s_ * s.xy[1],
                                                      s_ * s.xy[0] + c * s.xy[1]])

    smap = variant.build(n_samples)
    rng = np.random.default_rng(seed)
    anchor = f"x{problem.steps[0].pose}"
    prev: str | None = None
    n_updates = 0
    t0 = time.perf_counter()
    error = ""
    try:
        for k, st in enumerate(problem.steps):
            cur = f"x{st.pose}"
            if st.odometry is not None:
                o = st.odometry
                smap.update(f"x{o.i}", f"x{o.j}",
                            sample_planar(o.delta, o.cov, n_samples=n_samples, rng=rng,
                                          translation_frame="body"))
                n_updates += 1
            for s in st.sightings:
                smap.update(f"x{s.pose}", f"l{s.landmark}",
                            sample_point(s.xy, s.cov, n_samples=n_samples, rng=rng))
                n_updates += 1
            if prev is not None and prev != anchor and prev != cur and prev in smap:
                smap.remove(prev)
            prev = cur
            if log_every and k % log_every == 0 and k > 0:
                print(f"  victoria {variant.name} N={n_samples} step {k}/{len(problem.steps)}: "
                      f"{smap.n_frames} frames, {time.perf_counter() - t0:.0f} s", flush=True)
    except McsmError as err:
        error = f"{type(err).__name__}: {err}"
    elapsed = time.perf_counter() - t0
    ids = sorted(set(dr))
    mc = _map_landmarks(smap, anchor, ids)
    finite = not error and all(np.isfinite(smap.query(anchor, f)).all() for f in smap.frames())
    name = f"victoria_estimates_{variant.name}_N{n_samples}_s{seed}_{tag}.csv"
    with open(results / name, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["landmark", "mc_x", "mc_y", "ekf_x", "ekf_y", "dr_x", "dr_y"])
        for j in ids:
            row = [j]
            for est in (mc, ekf_est, dr):
                v = est.get(j)
                row += ["nan", "nan"] if v is None else [repr(float(v[0])), repr(float(v[1]))]
            w.writerow(row)
    out = {"estimates": name, "variant": variant.name, "n_samples": n_samples, "seed": seed,
           "length": tag, "steps": len(problem.steps), "updates": n_updates,
           "frames_at_end": smap.n_frames, "finite": finite, "seconds": round(elapsed, 1),
           "ms_per_update": round(1e3 * elapsed / max(n_updates, 1), 2), "error": error}
    path = results / "victoria_runs.csv"
    new = not path.exists()
    with open(path, "a", newline="") as f:
        w2 = csv.DictWriter(f, fieldnames=list(out))
        if new:
            w2.writeheader()
        w2.writerow(out)
    print("victoria run:", out, flush=True)
    return results / name


def score_victoria(results: Path, file: Any = sys.stdout) -> None:
    """Landmark RMS of every Victoria estimates file against every cached GTSAM reference."""
    refs = sorted(results.glob("victoria_reference_*.csv"))
    ests = sorted(results.glob("victoria_estimates_*.csv"))
    if not ests:
        return
    print("\nVictoria Park: landmark RMS (m) against GTSAM's batch LM optimum "
          "(Cartesian model)", file=file)
    print("| estimates | reference | map | EKF-SLAM | dead reckoning | landmarks |", file=file)
    print("|---|---|---|---|---|---|", file=file)
    for e in ests:
        length = e.stem.rsplit("_", 1)[1]
        for r in refs:
            if not r.stem.endswith("_" + length):
                continue
            ref = _read_xy(r)
            row = []
            n = 0
            for cols in (("mc_x", "mc_y"), ("ekf_x", "ekf_y"), ("dr_x", "dr_y")):
                est = _read_xy(e, cols)
                ids = [j for j in ref if j in est]
                n = max(n, len(ids))
                d = np.array([est[j] - ref[j] for j in ids]) if ids else np.zeros((0, 2))
                row.append(float(np.sqrt(np.mean(np.sum(d**2, axis=1)))) if ids else math.nan)
            print(f"| {e.stem.removeprefix('victoria_estimates_')} | "
                  f"{r.stem.removeprefix('victoria_reference_')} | {_fmt(row[0])} | "
                  f"{_fmt(row[1])} | {_fmt(row[2])} | {n} |", file=file)


def _map_landmarks(smap: StochasticMap, anchor: str, ids: Iterable[int]) -> dict[int, Array]:
    out = {}
    for j in ids:
        name = f"l{int(j)}"
        if name in smap:
            out[int(j)] = smap.query(anchor, name)[:, :2].mean(axis=0)
    return out


# ---------------------------------------------------------------------------- main


@dataclass
class Settings:
    """What one invocation runs (printed at start)."""

    n_iterations: int = 2000
    n_samples: tuple[int, ...] = (200, 1000)
    sigma_theta_deg: tuple[float, ...] = (0.0, 0.1)
    variants: tuple[str, ...] = tuple(VARIANTS)
    seeds: tuple[int, ...] = (6001,)
    log_every: int = 20
    victoria: bool = False
    victoria_n_samples: tuple[int, ...] = (1000,)
    victoria_variants: tuple[str, ...] = ("ensrf",)
    victoria_max_poses: int | None = None
    victoria_seeds: tuple[int, ...] = (7001,)
    victoria_reference: tuple[str, ...] = ("isam2",)
    force: bool = False
    report_only: bool = False
    deadline_s: float | None = None


QUICK = Settings(n_iterations=500, n_samples=(200, 1000), sigma_theta_deg=(0.0,),
                 variants=("paper", "enkf", "ensrf", "ensrf-shrink4-infl1.0002"), log_every=20)
FULL = Settings(n_iterations=2000, n_samples=(200, 1000), sigma_theta_deg=(0.0, 0.1),
                variants=tuple(VARIANTS), victoria=True)


def main(settings: Settings, results: Path = RESULTS) -> bool:
    """Run what ``settings`` asks for, then print the summary and the acceptance figures."""
    print("settings:", asdict(settings), flush=True)
    results.mkdir(parents=True, exist_ok=True)
    iterations = log_iterations(settings.n_iterations, settings.log_every)
    if not settings.report_only:
        for seed in settings.seeds:
            for th in settings.sigma_theta_deg:
                cfg = PaperScenarioConfig(n_iterations=settings.n_iterations,
                                          sigma_theta_deg=th)
                scenario = generate_paper_scenario(cfg, np.random.default_rng(seed))
                ekf: dict[int, tuple[float, float]] | None = None
                for n in settings.n_samples:
                    for name in settings.variants:
                        path = run_file(name, n, th, seed, settings.n_iterations, results)
                        if path.exists() and not settings.force:
                            print(f"skip (exists): {path.name}", flush=True)
                            continue
                        if ekf is None:
                            ekf = ekf_curve(scenario, iterations)
                        t0 = time.perf_counter()
                        rows = run_one(VARIANTS[name], n, scenario, seed, iterations, ekf,
                                       settings.deadline_s)
                        write_rows(path, rows)
                        last = rows[-1]
                        print(f"{name:>26} N={n:<5} σθ={th:g} seed={seed}: it {last['iteration']}"
                              f" RMS {_fmt(last['rms_m'])} m (EKF {_fmt(last['ekf_rms_m'])}) "
                              f"NEES {_fmt(last['nees_per_dof'])} "
                              f"[{time.perf_counter() - t0:.0f} s] {last['error']}", flush=True)
        if settings.victoria:
            for init in settings.victoria_reference:
                print("victoria reference:",
                      victoria_reference(settings.victoria_max_poses, results, init), flush=True)
            for n in settings.victoria_n_samples:
                for name in settings.victoria_variants:
                    for seed in settings.victoria_seeds:
                        run_victoria(n, VARIANTS[name], seed, settings.victoria_max_poses,
                                     results)
    rows = read_rows(results)
    if not rows:
        print(f"no scenario run files under {results / 'runs'}")
        _print_victoria(results)
        return settings.victoria
    summary = summarise(rows)
    with open(results / "summary.md", "w") as f:
        print_summary(summary, f)
        acceptance(summary, settings.n_iterations, f)
    print_summary(summary)
    ok = acceptance(summary, settings.n_iterations)
    for p in plot(rows, results, settings.n_iterations):
        print("plot:", p)
    _print_victoria(results)
    return ok


def _print_victoria(results: Path) -> None:
    vp = results / "victoria_runs.csv"
    if vp.exists():
        print("\nVictoria Park runs:")
        print(vp.read_text())
    score_victoria(results)
    with open(results / "victoria_summary.md", "w") as f:
        score_victoria(results, f)


def parse_args(argv: Sequence[str] | None = None) -> tuple[Settings, Path]:
    """Command-line flags to :class:`Settings` and the output folder."""
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    g = p.add_mutually_exclusive_group()
    g.add_argument("--quick", action="store_true", help="500 iterations, N 200/1000, 4 variants")
    g.add_argument("--full", action="store_true",
                   help="2000 iterations, N 200/1000, σθ 0/0.1, all variants, Victoria Park")
    p.add_argument("--iterations", type=int)
    p.add_argument("--n-samples", type=int, nargs="+")
    p.add_argument("--sigma-theta", type=float, nargs="+")
    p.add_argument("--variants", nargs="+", choices=sorted(VARIANTS))
    p.add_argument("--seeds", type=int, nargs="+")
    p.add_argument("--log-every", type=int)
    p.add_argument("--victoria", action="store_true", help="also run Victoria Park")
    p.add_argument("--victoria-only", action="store_true", help="only Victoria Park")
    p.add_argument("--victoria-n-samples", type=int, nargs="+")
    p.add_argument("--victoria-variants", nargs="+", choices=sorted(VARIANTS))
    p.add_argument("--victoria-max-poses", type=int)
    p.add_argument("--victoria-seeds", type=int, nargs="+")
    p.add_argument("--victoria-reference", nargs="*", choices=("isam2", "ekf"),
                   help="GTSAM references to compute first (LM from iSAM2 and/or from the EKF); "
                        "give none to run the map only and score later")
    p.add_argument("--force", action="store_true", help="re-run runs whose CSV exists")
    p.add_argument("--report-only", action="store_true", help="only rebuild tables and plots")
    p.add_argument("--deadline-s", type=float, help="stop each run after this wall time")
    p.add_argument("--results", type=Path, default=RESULTS, help="output folder")
    a = p.parse_args(argv)
    s = QUICK if a.quick else FULL if a.full else Settings()
    upd: dict[str, Any] = {}
    if a.iterations is not None:
        upd["n_iterations"] = a.iterations
    for flag, key in (("n_samples", "n_samples"), ("sigma_theta", "sigma_theta_deg"),
                      ("variants", "variants"), ("seeds", "seeds"),
                      ("victoria_n_samples", "victoria_n_samples"),
                      ("victoria_variants", "victoria_variants"),
                      ("victoria_seeds", "victoria_seeds"),
                      ("victoria_reference", "victoria_reference")):
        if getattr(a, flag) is not None:
            upd[key] = tuple(getattr(a, flag))
    if a.log_every is not None:
        upd["log_every"] = a.log_every
    if a.victoria or a.victoria_only:
        upd["victoria"] = True
    if a.victoria_only:
        upd["n_samples"] = ()
    if a.victoria_max_poses is not None:
        upd["victoria_max_poses"] = a.victoria_max_poses
    upd["force"] = a.force
    upd["report_only"] = a.report_only
    if a.deadline_s is not None:
        upd["deadline_s"] = a.deadline_s
    return replace(s, **upd), a.results


if __name__ == "__main__":
    _settings, _results = parse_args()
    sys.exit(0 if main(_settings, _results) else 1)
