"""Real-data benchmark (issue 22): mcsm beside EKF-SLAM, GTSAM iSAM2 and batch LM, one run.

Data sets from the gtsam wheel (:mod:`experiments.realdata_data`): Victoria Park (bounded map:
pose 0 anchor, each older pose removed), sphere2500 (3-D), city10000 and w10000 (planar pose
graphs, every pose kept). Per data set and seed, every configuration of :data:`CONFIGS` streams
the same input samples (drawn from ``default_rng(seed)``) step by step, a step being one new pose
with the edges that arrive with it; then GTSAM: iSAM2 with its defaults and with a tuned
relinearisation threshold (the file's values), iSAM2 fed each seed's sample means (the same
numbers the map got, for the error along the run), batch Levenberg-Marquardt (the reference,
started from iSAM2's estimate), and EKF-SLAM where it applies.

Columns: final error against the batch optimum (landmark RMS for Victoria Park, pose-position
RMS for the pose graphs, both in the anchor's frame), ATE against ground truth (rigid
alignment) where the data set has it, the worst ratio of the map's error to iSAM2's (fed the
same sample means) at the same step past step 1000, total CPU seconds, median / p99 / worst CPU
time of a step *with one joint marginal query* (mcsm ``marginal`` of the current pose and the
landmark seen last or the anchor; iSAM2 ``jointMarginalCovariance`` of the same pair), NEES per
dof (Victoria Park: landmarks against the batch optimum; sphere2500, city10000: poses against
ground truth), rejections. The error every 500 steps goes to ``<set>_curves.csv`` and
``<set>_curves.png``.

Timings are CPU times (``time.process_time``; numpy and the map single-threaded) on a machine
shared with other jobs: compare within one run.

Usage::

    .venv/bin/python benchmarks/realdata.py --quick                 # seconds: short prefixes
    .venv/bin/python benchmarks/realdata.py --datasets victoria sphere2500   # N 1000 / 200
    .venv/bin/python benchmarks/realdata.py --datasets city10000 --seeds 1
    .venv/bin/python benchmarks/realdata.py --datasets w10000 --seeds 1 --max-steps 3000
    .venv/bin/python benchmarks/realdata.py --list                  # configurations, availability
    .venv/bin/python benchmarks/realdata.py --datasets victoria --reference trimmed
        # errors against the batch optimum without the inputs that are outliers at it
    .venv/bin/python benchmarks/realdata.py --datasets victoria --reference huber
        # errors against the batch optimum with a Huber kernel on sightings and closures

Results: ``benchmarks/results/realdata/`` (``--out``).
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from pathlib import Path
from typing import Any

# One BLAS thread: on the shared 2-core machine a multi-threaded eigh of a few hundred
# dimensions took 5 s instead of 0.1 s. Set before numpy is imported.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

# ---------------------------------------------------------------------------------------------
# The configurations of the map: the shipped StochasticMap with its shipped defaults and named
# configurations. "options" go to StochasticMap(N, **options) (threads=1 added; a Policy as its
# plain dict); "driver" is code run around the map: {"method": "relinearize", "every": K} calls
# StochasticMap.relinearize() every K steps, {"mda": K} splits every re-sighting / loop closure
# into K updates of K x the covariance. "datasets" limits a row. A configuration whose option or
# method this build does not have is reported as "not available in this build", never dropped.
# The batch relinearisation prototypes that came before the shipped one are ``--prototypes``
# (experiments/relin_prototypes.py).
# ---------------------------------------------------------------------------------------------
def _recommended() -> dict[str, Any]:
    try:
        from mcsm.core.relinearize import RECOMMENDED
    except ImportError:  # pragma: no cover - a build without relinearisation
        return {"nis": 0.95, "regate": 1, "gap": 25}
    return RECOMMENDED.to_plain()


def _default_policy() -> dict[str, Any]:
    try:
        from mcsm.core.smap import DEFAULT_POLICY
    except ImportError:  # pragma: no cover - a build without relinearisation
        return {}
    return DEFAULT_POLICY.to_plain() if DEFAULT_POLICY is not None else {}


BEFORE = {"gate_scale": None, "history": None, "relinearize": None}
"""The options before issue 22: the fixed 0.99 gate, no history, no relinearisation."""

CONFIGS: list[dict[str, Any]] = [
    {"name": "mcsm defaults", "options": {}},
    {"name": "mcsm defaults without calibration (the fourth round's defaults)",
     "options": {"relinearize": {**_default_policy(), "calibrate": None}}},
    {"name": "mcsm defaults with the gate off (every input in: the least-squares optimum)",
     "options": {"gate": None}},
    {"name": "mcsm defaults without re-centring (the defaults before it: nis 0.95, regate 1, "
             "gap 25, spread 1.3)",
     "options": {"relinearize": {**_default_policy(), "recentre": False, "readmit": None,
                                 "calibrate": None}}},
    {"name": "mcsm defaults without readmit (re-centring alone)",
     "options": {"relinearize": {**_default_policy(), "readmit": None, "calibrate": None}}},
    {"name": "mcsm RECOMMENDED (nis 0.95, regate 1, gap 25)",
     "options": {"relinearize": _recommended()}},
    {"name": "mcsm repair only (regate 6, gap 25: the defaults before spread)",
     "options": {"relinearize": {"regate": 6, "gap": 25}}},
    {"name": "mcsm defaults + relinearize() every 500 steps",
     "options": {}, "driver": {"method": "relinearize", "every": 500}},
    {"name": "mcsm repair only + readmit 300 (experiment, off by default)",
     "options": {"relinearize": {"regate": 6, "gap": 25, "readmit": 300}}},
    {"name": "mcsm gate off, no relinearisation",
     "options": {"gate": None, "history": None, "relinearize": None}},
    {"name": "mcsm before issue 22 (gate 0.99 fixed, no relinearisation)", "options": BEFORE},
]

QUICK_STEPS = {"victoria": 600, "sphere2500": 200, "city10000": 300, "w10000": 150}
DEFAULT_N = {"victoria": 1000, "sphere2500": 200, "city10000": 1000, "w10000": 1000}
ISAM2_TUNED = {"threshold": 0.01, "skip": 1}


def availability(config: dict[str, Any]) -> str:
    """"" when the installed StochasticMap has what ``config`` needs, else why not."""
    from mcsm import StochasticMap
    from mcsm.errors import McsmError

    try:
        StochasticMap(8, threads=1, **config.get("options", {}))
    except (TypeError, McsmError, ValueError) as exc:
        return f"not available in this build ({type(exc).__name__}: {exc})"
    method = config.get("driver", {}).get("method")
    if method and not hasattr(StochasticMap, method):
        return f"not available in this build (StochasticMap has no {method}())"
    return ""


def make_hooks(config: dict[str, Any], problem: Any, seed: int) -> list[Any]:
    """The experiment code a configuration runs around the map."""
    from experiments.realdata_run import Hook, Mda
    from experiments.relin_prototypes import BatchRelinearizer

    class MethodDriver(Hook):
        """Calls ``smap.<method>()`` every ``every`` steps (the shipped operation)."""

        def __init__(self, method: str, every: int) -> None:
            self.method, self.every, self.count, self.total_s = method, every, 0, 0.0

        def end_step(self, smap: Any, k: int, pose: int, run: Any) -> Any:
            if (k + 1) % self.every == 0:
                t0 = time.process_time()
                out = getattr(smap, self.method)()
                self.total_s += time.process_time() - t0
                self.count += 1
                if out is not None and hasattr(out, "update"):
                    return out
            return smap

        def describe(self) -> str:
            return f"{self.count} x {self.method}(), {self.total_s:.1f} s"

    d = dict(config.get("driver", {}))
    hooks: list[Any] = []
    if "mda" in d:
        hooks.append(Mda(int(d.pop("mda"))))
    if d.get("prototype") == "batch":
        d.pop("prototype")
        hooks.append(BatchRelinearizer(problem, seed=seed, **d))
    elif "method" in d:
        hooks.append(MethodDriver(d["method"], int(d["every"])))
    return hooks


# ---------------------------------------------------------------------------------------------
def reference(problem: Any, log: Any, tuned: bool = True, kind: str = "least-squares"
              ) -> dict[str, Any]:
    """iSAM2 (defaults, tuned; file values; timed with the joint marginal) and batch LM (with
    ``kind`` "trimmed", the reference is LM without the inputs beyond the trim quantile at its
    own optimum, ``experiments.realdata_gtsam.trimmed_lm``; with "huber", LM with a Huber
    kernel on the sightings and closures, ``huber_lm``; the least-squares one is then
    ``lm_ls``)."""
    from experiments import realdata_gtsam as rg

    out: dict[str, Any] = {"snaps": {}, "snaps_tuned": {}, "snaps_cpp": {}}

    def keep(store: dict[int, Any]) -> Any:
        return lambda values, k: store.__setitem__(k, values) or np.nan

    t0 = time.perf_counter()
    out["isam"] = rg.run_isam2(problem, progress=True, error_fn=keep(out["snaps"]))
    log(f"    iSAM2 defaults: {out['isam'].total_s:.1f} s CPU ({time.perf_counter() - t0:.0f} s)")
    graph, _ = rg.whole_graph(problem)
    out["lm"], out["lm_s"] = rg.batch_lm(graph, out["isam"].estimate)
    out["graph"] = graph
    log(f"    LM from iSAM2: {out['lm_s']:.1f} s CPU, error {graph.error(out['isam'].estimate):.1f}"
        f" -> {graph.error(out['lm']):.1f}")
    if kind == "trimmed":
        out["lm_ls"] = out["lm"]
        out["lm"], out["left_out"], s = rg.trimmed_lm(problem, graph, out["lm_ls"])
        out["lm_s"] += s
        log(f"    trimmed LM: {len(out['left_out'])} inputs left out (beyond the 0.999 quantile "
            f"at the optimum), {s:.1f} s CPU")
    elif kind == "huber":
        out["lm_ls"] = out["lm"]
        out["lm"], s = rg.huber_lm(problem, out["lm_ls"])
        out["lm_s"] += s
        log(f"    Huber LM (k = {rg.HUBER_K}): {s:.1f} s CPU")
    if problem.bounded:  # the same structure with C++ factors: iSAM2's time without callbacks
        out["isam_cpp"] = rg.run_isam2(problem, cpp_points=True, error_fn=keep(out["snaps_cpp"]))
        log(f"    iSAM2 defaults, C++ bearing-range factors: {out['isam_cpp'].total_s:.1f} s CPU")
    if tuned:
        # With Python point factors the tuned iSAM2 re-evaluates thousands of callbacks per
        # step (Victoria Park: > 20 min of CPU, stopped); a landmark set gets it with the C++
        # bearing-range proxy.
        out["isam_tuned"] = rg.run_isam2(problem, threshold=ISAM2_TUNED["threshold"],
                                         skip=ISAM2_TUNED["skip"], progress=True,
                                         error_fn=keep(out["snaps_tuned"]),
                                         cpp_points=problem.bounded)
        log(f"    iSAM2 tuned: {out['isam_tuned'].total_s:.1f} s CPU")
    return out




# ---------------------------------------------------------------------------------------------
def row(dataset: str, name: str, **kw: Any) -> dict[str, Any]:
    base = {"dataset": dataset, "estimator": name, "n_samples": "", "seed": "", "status": "ok",
            "final_m": np.nan, "ate_m": np.nan, "worst_ratio": np.nan, "median_ratio": np.nan,
            "total_s": np.nan, "median_ms": np.nan, "p99_ms": np.nan, "worst_ms": np.nan,
            "nees": np.nan, "rejected": "", "note": ""}
    base.update(kw)
    return base


def timing(step_s: np.ndarray) -> dict[str, float]:
    s = step_s[1:] if len(step_s) > 1 else step_s
    return {"total_s": float(step_s.sum()), "median_ms": 1e3 * float(np.median(s)),
            "p99_ms": 1e3 * float(np.percentile(s, 99)), "worst_ms": 1e3 * float(s.max())}


def ratios(curve: dict[int, float], base: dict[int, float],
           past: int = 1000) -> tuple[float, float]:
    r = [curve[k] / base[k] for k in curve if k > past and k in base and base[k] > 0]
    return (float(np.max(r)), float(np.median(r))) if r else (np.nan, np.nan)


def run_dataset(name: str, args: argparse.Namespace, configs: list[dict[str, Any]],
                log: Any) -> tuple[list[dict[str, Any]], list[tuple[str, str, int, int, float]]]:
    """Every estimator on one data set; rows and error curves."""
    from mcsm import StochasticMap

    from experiments import realdata_data as rd
    from experiments import realdata_gtsam as rg
    from experiments.realdata_run import run_ekf_slam, run_map
    from experiments.realdata_score import Scorer, ekf_posegraph, gtsam_nees, map_final

    steps = args.max_steps or (QUICK_STEPS[name] if args.quick else None)
    problem = rd.load(name).prefix(steps)
    n = args.n_samples or (100 if args.quick else DEFAULT_N[name])
    log(f"{name}: {problem.counts()}, noise: {problem.noise}; N = {n}, seeds {args.seeds}")
    ref = reference(problem, log, tuned=not args.no_tuned, kind=args.reference)
    scorer = Scorer(problem, ref["lm"])
    rows: list[dict[str, Any]] = []
    curves: list[tuple[str, str, int, int, float]] = []

    def add_curve(label: str, seed: int, cps: dict[int, float]) -> None:
        curves.extend((name, label, seed, k, v) for k, v in sorted(cps.items()))

    # GTSAM rows: LM (reference), iSAM2 defaults and tuned on the file's values.
    lm_ate = scorer.ate(scorer.ref_poses) if not problem.bounded else np.nan
    nees_lm = np.nan
    if problem.truth is not None and not args.quick:
        nees_lm = gtsam_nees(problem, scorer, ref)
    if args.reference != "least-squares":
        note = (f"without the {len(ref['left_out'])} sightings and closures beyond the 0.999 "
                f"quantile at its optimum" if args.reference == "trimmed" else
                f"Huber {rg.HUBER_K} on the sightings and closures")
        rows.append(row(name, f"GTSAM batch LM, {args.reference} (reference)", final_m=0.0,
                        ate_m=lm_ate, total_s=ref["lm_s"], nees=nees_lm,
                        note=f"{note}; from the least-squares optimum"))
        ls = ref["lm_ls"]
        rows.append(row(name, "GTSAM batch LM, least squares (every input)",
                        final_m=scorer.values_error(ls, len(problem.steps)),
                        ate_m=(scorer.ate(rg.estimates(ls, problem, scorer.poses, [])[0])
                               if not problem.bounded else np.nan),
                        note="the issue's reference"))
    else:
        rows.append(row(name, "GTSAM batch LM (reference)", final_m=0.0, ate_m=lm_ate,
                        total_s=ref["lm_s"], nees=nees_lm, note="started from iSAM2's estimate"))
    isam_file: dict[int, float] = {}
    for key, label in (("isam", "GTSAM iSAM2 defaults (0.1, skip 10)"),
                       ("isam_tuned", f"GTSAM iSAM2 tuned ({ISAM2_TUNED['threshold']}, skip "
                                      f"{ISAM2_TUNED['skip']})" + (
                                          ", C++ bearing-range sightings (proxy)"
                                          if problem.bounded else "")),
                       ("isam_cpp", "GTSAM iSAM2 defaults, C++ bearing-range sightings "
                                    "(timing proxy, another model)")):
        if key not in ref:
            continue
        est = ref[key].estimate
        snaps = ref[{"isam": "snaps", "isam_tuned": "snaps_tuned", "isam_cpp": "snaps_cpp"}[key]]
        cps = {k: scorer.values_error(v, k) for k, v in snaps.items()}
        if key == "isam":
            isam_file = cps
        pp, _ = rg.estimates(est, problem, scorer.poses, [])
        rows.append(row(name, label, final_m=scorer.values_error(est, len(problem.steps)),
                        ate_m=scorer.ate(pp) if not problem.bounded else np.nan,
                        **timing(ref[key].step_s), note="file values"))
        add_curve(label, 0, cps)
    isam_means: dict[int, dict[int, float]] = {}
    for seed in args.seeds:
        for cfg in configs:
            if cfg.get("datasets") and name not in cfg["datasets"]:
                continue
            why = availability(cfg) if "ensemble" not in cfg.get("driver", {}) else ""
            label = cfg["name"]
            if why:
                rows.append(row(name, label, n_samples=n, seed=seed, status=why))
                continue
            t0 = time.perf_counter()
            if "ensemble" in cfg.get("driver", {}):
                from experiments.invariant_ensemble import EnsembleSlam, run_ensemble
                from experiments.invariant_posegraph import (
                    PoseGraphEnsemble,
                    run_posegraph_ensemble,
                )

                kw = cfg["driver"]["ensemble"]
                if problem.bounded:
                    ens = EnsembleSlam(n, **kw)
                    res = run_ensemble(problem, ens, seed=seed, error_fn=lambda e, k: scorer.rms(
                        e.landmark_means(scorer._ids(k)[0]), scorer._ids(k)[1]))
                    fin = {"final": res.checkpoints[len(problem.steps)]}
                elif problem.dim == 3:
                    pge = PoseGraphEnsemble(n, **kw)
                    res = run_posegraph_ensemble(problem, pge, seed=seed, error_fn=lambda e, k:
                                                 scorer.rms(e.positions(scorer.poses[:k]),
                                                            scorer.ref_poses[:k]))
                    fin = {"final": res.checkpoints[len(problem.steps)],
                           "ate": scorer.ate(pge.positions(scorer.poses))}
                else:
                    continue
                note, means = "numpy ensemble", None
            else:
                hooks = make_hooks(cfg, problem, seed)
                opts = dict(cfg.get("options", {}))
                res, smap = run_map(problem, lambda o=opts: StochasticMap(n, threads=1, **o),
                                    n_samples=n, seed=seed, hooks=hooks,
                                    error_fn=scorer.map_error, progress=True,
                                    keep_means=seed not in isam_means)
                fin = map_final(scorer, smap)
                note = "; ".join([h.describe() for h in hooks if h.describe()] + (
                    [f"{res.relins} automatic relinearisations, {res.relin_s:.1f} s"]
                    if res.relins else []))
                means = res.sample_means
                del smap
            if seed not in isam_means and means:
                r = rg.run_isam2(problem, means=means, query=False,
                                 error_fn=scorer.values_error)
                isam_means[seed] = r.checkpoints
                rows.append(row(name, "GTSAM iSAM2 defaults, fed the sample means", seed=seed,
                                n_samples=n, final_m=r.checkpoints[len(problem.steps)],
                                note="the same inputs as the map; untimed"))
                add_curve("GTSAM iSAM2, sample means", seed, r.checkpoints)
            worst, med = ratios(res.checkpoints, isam_means.get(seed, {}))
            if res.errors:
                note = f"{res.errors} updates failed ({res.note}); " + note
            rows.append(row(name, label, n_samples=n, seed=seed, final_m=fin["final"],
                            ate_m=fin.get("ate", np.nan), worst_ratio=worst, median_ratio=med,
                            nees=fin.get("nees", np.nan), rejected=f"{res.rejected}/{res.tested}",
                            note=note, **timing(res.step_s)))
            add_curve(label, seed, res.checkpoints)
            log(f"    {label}, seed {seed}: {fin['final']:.3f} m, ratio worst {worst:.1f}, "
                f"{res.total_s:.0f} s CPU ({time.perf_counter() - t0:.0f} s wall), rejected "
                f"{res.rejected}/{res.tested}{'; ' + note if note else ''}")
    # EKF baselines
    if problem.bounded:
        res, _ = run_ekf_slam(problem, error_fn=scorer.dict_error)
        worst, med = ratios(res.checkpoints, isam_file)
        rows.append(row(name, "EKF-SLAM (file values)", final_m=res.checkpoints[len(
            problem.steps)], worst_ratio=worst, median_ratio=med, **timing(res.step_s),
            note="full covariance; ratio to iSAM2 on the file's values"))
        add_curve("EKF-SLAM", 0, res.checkpoints)
    else:
        rows.append(row(name, "EKF pose graph (exact covariance, file values)",
                        **ekf_posegraph(problem, scorer)))
    return rows, curves




# ---------------------------------------------------------------------------------------------
def aggregate(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One line per (data set, estimator): medians over seeds, the final error's range."""
    out: list[dict[str, Any]] = []
    keys: list[tuple[str, str]] = []
    for r in rows:
        if (r["dataset"], r["estimator"]) not in keys:
            keys.append((r["dataset"], r["estimator"]))
    for ds, est in keys:
        sel = [r for r in rows if r["dataset"] == ds and r["estimator"] == est]
        ok = [r for r in sel if r["status"] == "ok"]
        if not ok:
            out.append({**sel[0], "seed": ""})
            continue
        line = dict(ok[0])
        for k in ("final_m", "ate_m", "worst_ratio", "median_ratio", "total_s", "median_ms",
                  "p99_ms", "worst_ms", "nees"):
            line[k] = float(np.nanmedian([r[k] for r in ok])) if any(
                np.isfinite(r[k]) for r in ok) else np.nan
        line["seed"] = ",".join(str(r["seed"]) for r in ok)
        finals = [r["final_m"] for r in ok]
        line["range"] = f"{min(finals):.3g}-{max(finals):.3g}" if len(ok) > 1 else ""
        rej = [r["rejected"] for r in ok if r["rejected"]]
        line["rejected"] = rej[len(rej) // 2] if rej else ""
        out.append(line)
    return out


def fmt(x: Any, nd: int = 3) -> str:
    if isinstance(x, str):
        return x
    return "-" if x is None or not np.isfinite(x) else f"{x:.{nd}g}"


def table(lines: list[dict[str, Any]]) -> list[str]:
    head = ("| data set | estimator | N | seeds | final vs batch LM (m) [range] | ATE vs truth (m) "
            "| worst / median ratio to iSAM2, same means, past step 1000 | total CPU s | "
            "step median / p99 / worst (ms, with a joint marginal) | NEES/dof | rejected | "
            "note |")
    out = [head, "|" + "---|" * 12]
    for r in lines:
        if r["status"] != "ok":
            out.append(f"| {r['dataset']} | {r['estimator']} | {r['n_samples']} | | "
                       f"{r['status']} | | | | | | | |")
            continue
        rng = f" [{r['range']}]" if r.get("range") else ""
        out.append(
            f"| {r['dataset']} | {r['estimator']} | {r['n_samples']} | {r['seed']} | "
            f"{fmt(r['final_m'])}{rng} | {fmt(r['ate_m'])} | {fmt(r['worst_ratio'], 2)} / "
            f"{fmt(r['median_ratio'], 2)} | {fmt(r['total_s'])} | {fmt(r['median_ms'])} / "
            f"{fmt(r['p99_ms'])} / {fmt(r['worst_ms'])} | {fmt(r['nees'])} | {r['rejected']} | "
            f"{r['note']} |")
    return out


def plot(path: Path, name: str, curves: list[tuple[str, str, int, int, float]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 5.5))
    labels = list(dict.fromkeys(c[1] for c in curves))
    colours = plt.get_cmap("tab20")(np.linspace(0.0, 1.0, 20))
    for n, label in enumerate(labels):
        pts: dict[int, list[float]] = {}
        for _, lab, _, k, v in curves:
            if lab == label and np.isfinite(v):
                pts.setdefault(k, []).append(v)
        if not pts:
            continue
        ks = sorted(pts)
        ax.plot(ks, [np.median(pts[k]) for k in ks], marker="os^vD<>"[n % 7], ms=3.5, lw=1.2,
                color=colours[(2 * n) % 20 + (n // 10) % 2],
                ls="--" if label.startswith(("GTSAM", "EKF")) else "-", label=label)
    ax.set_yscale("log")
    ax.set_xlabel("step (poses so far)")
    ax.set_ylabel("RMS error vs the batch optimum (m), median over seeds")
    ax.set_title(f"{name}: error along the run")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=6.5, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> list[dict[str, Any]]:
    from experiments.realdata_data import DATASETS

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--datasets", nargs="*", default=list(DATASETS), choices=list(DATASETS))
    ap.add_argument("--seeds", nargs="*", type=int, default=None, help="default 1 2 11")
    ap.add_argument("--n-samples", type=int, default=None, help="default per data set")
    ap.add_argument("--max-steps", type=int, default=None, help="a prefix of each data set")
    ap.add_argument("--quick", action="store_true", help="short prefixes, N = 100, one seed")
    ap.add_argument("--configs", nargs="*", default=None,
                    help="configurations to run: a whole name, or a substring of names")
    ap.add_argument("--prototypes", action="store_true",
                    help="the relinearisation prototypes' configurations instead of CONFIGS")
    ap.add_argument("--list", action="store_true", help="configurations and availability")
    ap.add_argument("--tag", default="", help="suffix of the output files")
    ap.add_argument("--no-plot", action="store_true", help="skip the PNG")
    ap.add_argument("--no-tuned", action="store_true", help="skip the tuned iSAM2 row")
    ap.add_argument("--reference", choices=("least-squares", "trimmed", "huber"),
                    default="least-squares",
                    help="the optimum errors are measured against: batch LM of every input "
                         "(default); trimmed: without the inputs beyond the 0.999 chi-square "
                         "quantile at its own optimum, re-solved until that set is stable; "
                         "huber: with a Huber kernel (1.345) on the sightings and closures")
    ap.add_argument("--replot", action="store_true", help="redraw the PNGs from the CSVs")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "realdata")
    args = ap.parse_args(argv)
    configs = CONFIGS
    if args.prototypes:
        from experiments.relin_prototypes import PROTOTYPES

        configs = PROTOTYPES
    if args.configs:  # a whole name selects that configuration alone, else substrings
        names = {c["name"] for c in configs}
        configs = [c for c in configs if any(s == c["name"] or (s not in names and s in c["name"])
                                             for s in args.configs)]
    if args.list:
        for c in configs:
            print(f"{c['name']}: {c.get('options', {})} {c.get('driver', {})} -> "
                  f"{availability(c) or 'available'}")
        return []
    args.seeds = args.seeds or ([1] if args.quick else [1, 2, 11])
    args.out.mkdir(parents=True, exist_ok=True)
    tag = f"_{args.tag}" if args.tag else ""
    if args.replot:
        for name in args.datasets:
            path = args.out / f"{name}{tag}_curves.csv"
            if path.is_file():
                with open(path) as f:
                    got = [(r["dataset"], r["estimator"], int(r["seed"]), int(r["step"]),
                            float(r["error_m"])) for r in csv.DictReader(f)]
                plot(args.out / f"{name}{tag}_curves.png", name, got)
        return []
    cmd = "benchmarks/realdata.py " + " ".join(argv if argv is not None else sys.argv[1:])
    all_rows: list[dict[str, Any]] = []
    for name in args.datasets:
        log_path = args.out / f"{name}{tag}.log"
        with open(log_path, "w") as logf:
            def log(msg: str, f: Any = logf) -> None:
                print(msg, flush=True)
                f.write(msg + "\n")
                f.flush()

            t0 = time.perf_counter()
            log(f"$ {cmd}")
            rows, curves = run_dataset(name, args, configs, log)
            lines = table(aggregate(rows))
            log("\n".join(lines))
            log(f"{name}: {time.perf_counter() - t0:.0f} s wall (machine shared with other jobs)")
        with open(args.out / f"{name}{tag}_rows.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        with open(args.out / f"{name}{tag}_curves.csv", "w", newline="") as f:
            w2 = csv.writer(f)
            w2.writerow(["dataset", "estimator", "seed", "step", "error_m"])
            w2.writerows(curves)
        (args.out / f"{name}{tag}_table.md").write_text(f"`{cmd}`\n\n" + "\n".join(lines) + "\n")
        if not args.no_plot:
            plot(args.out / f"{name}{tag}_curves.png", name, curves)
        all_rows += rows
    return all_rows


if __name__ == "__main__":
    main()
