"""Summarise ``pose_graph_runs_<tag>.csv`` files (issue 8) as a markdown table and tallies.

Rows are grouped by scenario, method, space, gain, N, inflation and loop update; each group
gets its accepted count (ATE ≤ 2× GTSAM, NEES/dof ≤ 2, nothing non-finite), the median and the
worst ATE ratio and NEES/dof, and the seeds it covers. ``--rows`` adds one line per run.

Usage::

    .venv/bin/python experiments/pose_graph_table.py --tags gains_seed8 gains_seed9 ...
    .venv/bin/python experiments/pose_graph_table.py --glob 'pose_graph_runs_gains_seed*.csv'
"""

from __future__ import annotations

import argparse
import csv
import statistics
from collections import defaultdict
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"
KEY = ("scenario", "method", "space", "gain", "n_samples", "inflation", "loop_update")


def load(paths: list[Path]) -> list[dict[str, str]]:
    """All rows of the given CSV files (a missing ``gain`` column reads as ``direct``)."""
    rows: list[dict[str, str]] = []
    for p in paths:
        with p.open(newline="") as f:
            for r in csv.DictReader(f):
                r.setdefault("gain", "direct")
                r["file"] = p.name
                rows.append(r)
    return rows


def _f(x: str) -> float:
    try:
        return float(x)
    except ValueError:
        return float("nan")


def tally(rows: list[dict[str, str]]) -> list[str]:
    """One markdown line per group of runs sharing ``KEY``."""
    groups: dict[tuple[str, ...], list[dict[str, str]]] = defaultdict(list)
    for r in rows:
        groups[tuple(r[k] for k in KEY)].append(r)
    out = ["| scenario | method | space | gain | N | inflation | loop update | accepted | "
           "ATE ratio median (worst) | NEES/dof median (worst) | seeds |",
           "|---|---|---|---|---|---|---|---|---|---|---|"]
    for key, rs in sorted(groups.items()):
        ratio = [_f(r["ate_ratio_to_gtsam"]) for r in rs]
        nees = [_f(r["nees_per_dof"]) for r in rs]
        ok = sum(r["accepted"] == "True" for r in rs)
        seeds = sorted({int(r["seed"]) for r in rs})
        infl = "adaptive" if key[5] == "nan" else key[5]
        out.append(f"| {key[0]} | {key[1]} | {key[2]} | {key[3]} | {key[4]} | {infl} | {key[6]} "
                   f"| {ok}/{len(rs)} | {statistics.median(ratio):.2f} ({max(ratio):.2f}) | "
                   f"{statistics.median(nees):.2f} ({max(nees):.2f}) | "
                   f"{', '.join(map(str, seeds))} |")
    return out


def run_lines(rows: list[dict[str, str]]) -> list[str]:
    """One markdown line per run."""
    out = ["| scenario | gain | seed | ATE map (m) | ATE GTSAM (m) | ratio | NEES/dof (t, r) | "
           "ms/loop | accepted |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: (r["scenario"], r["gain"], int(r["seed"]))):
        out.append(f"| {r['scenario']} | {r['gain']} | {r['seed']} | {_f(r['ate_map_m']):.3f} | "
                   f"{_f(r['ate_gtsam_m']):.3f} | {_f(r['ate_ratio_to_gtsam']):.2f} | "
                   f"{_f(r['nees_per_dof']):.2f} ({_f(r['nees_t_per_dof']):.2f}, "
                   f"{_f(r['nees_r_per_dof']):.2f}) | {_f(r['ms_per_loop']):.1f} | "
                   f"{'PASS' if r['accepted'] == 'True' else 'FAIL'} |")
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tags", nargs="*", default=[], help="file tags: pose_graph_runs_<tag>.csv")
    ap.add_argument("--glob", default=None, help="or a glob in the results folder")
    ap.add_argument("--rows", action="store_true", help="also one line per run")
    ap.add_argument("--methods", nargs="*", default=None, help="keep only these methods")
    ap.add_argument("--dir", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    paths = [args.dir / f"pose_graph_runs_{t}.csv" for t in args.tags]
    if args.glob:
        paths += sorted(args.dir.glob(args.glob))
    missing = [str(p) for p in paths if not p.is_file()]
    if missing or not paths:
        raise SystemExit(f"no such result files: {missing or 'none given'}")
    rows = load(paths)
    if args.methods:
        rows = [r for r in rows if r["method"] in args.methods]
    print("\n".join(tally(rows)))
    if args.rows:
        print()
        print("\n".join(run_lines(rows)))


if __name__ == "__main__":
    main()
