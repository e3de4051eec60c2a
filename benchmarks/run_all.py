"""Regenerate every benchmark and experiment table and plot with short settings (``make bench``).

Runs, one after the other, each script's quick mode, with the outputs of the experiments going to
``experiments/results/quick/`` (the committed full-length results in ``experiments/results/`` are
left alone; ``docs/evaluation.md`` says which settings made which figure):

=====================================  =====================================================
script                                 quick settings
=====================================  =====================================================
benchmarks/bench_core.py               its own ``--quick`` if it has one
benchmarks/service_throughput.py       its own ``--quick`` if it has one
benchmarks/bench_oracle.py             2 seeds, N 200/1000
experiments/consistency.py             ``--quick`` variants, 360 iterations, N = 200
experiments/pose_graph.py              300 poses (3D and 2D), loop-closure timing M = 500
experiments/paper_figures.py           ``--quick``: 360 its, N 200/1000 (Fig. 5 N 200), Fig. 6
experiments/realdata.py                ``--quick``: Victoria Park first 1000 poses, N = 200
experiments/eval3d.py                  ``--quick``: 200-pose 3D helix, N = 100
=====================================  =====================================================

Each step has a time limit (the sum stays under the 15-minute budget on a 2-core machine); a step
that is missing, fails or runs out of time is reported and the others still run. The exit code is
non-zero if any step failed. A summary table (step, status, seconds) ends the output and is
written to ``experiments/results/quick/run_all.md``.

Usage::

    .venv/bin/python benchmarks/run_all.py            # everything
    .venv/bin/python benchmarks/run_all.py --only paper_figures realdata
    .venv/bin/python benchmarks/run_all.py --list
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
QUICK = ROOT / "experiments" / "results" / "quick"


@dataclass(frozen=True)
class Step:
    """One script to run.

    Parameters
    ----------
    name : str
        Short name (``--only`` selects by it).
    script : str
        Path relative to the repository root.
    args : tuple of str
        Arguments for the quick run.
    timeout_s : float
        Wall-time limit.
    quick_if_supported : bool
        Append ``--quick`` when the script's source mentions it (scripts owned by others).
    verdict_exit : bool
        The script exits 1 when its own acceptance criteria are not met (a verdict on the
        results, reported, not a failure of the run).
    """

    name: str
    script: str
    args: tuple[str, ...] = field(default_factory=tuple)
    timeout_s: float = 120.0
    quick_if_supported: bool = False
    verdict_exit: bool = False


_POSE_GRAPH_QUICK = ("--poses", "300", "--timing-m", "500", "--timing-n", "200",
                     "--timing-repeats", "3", "--out-dir", str(QUICK))  # fmt: skip

STEPS = [
    Step("bench_core", "benchmarks/bench_core.py", (), 80.0, quick_if_supported=True),
    Step("service_throughput", "benchmarks/service_throughput.py", (), 80.0, True),
    Step("bench_oracle", "benchmarks/bench_oracle.py", ("--seeds", "2", "--sizes", "200", "1000"),
         60.0),
    Step("soak_memory", "benchmarks/soak_memory.py",
         ("--ops", "20000", "--every", "5000", "--samples", "200"), 90.0),
    Step("consistency", "experiments/consistency.py",
         ("--quick", "--iterations", "360", "--n-samples", "200", "--results",
          str(QUICK / "consistency")), 170.0, verdict_exit=True),
    Step("pose_graph", "experiments/pose_graph.py", _POSE_GRAPH_QUICK, 120.0),
    Step("paper_figures", "experiments/paper_figures.py", ("--quick", "--results", str(QUICK)),
         170.0),
    Step("realdata", "experiments/realdata.py", ("--quick", "--results", str(QUICK)), 110.0),
    Step("eval3d", "experiments/eval3d.py", ("--quick", "--results", str(QUICK)), 80.0),
]  # fmt: skip


def run_step(step: Step, python: str, log_dir: Path) -> tuple[str, float]:
    """Run one step, streaming its output to the terminal and to ``log_dir/<name>.log``."""
    path = ROOT / step.script
    if not path.exists():
        return "missing", 0.0
    args = list(step.args)
    if step.quick_if_supported and "--quick" in path.read_text(encoding="utf-8"):
        args.append("--quick")
    env = dict(
        os.environ,
        OMP_NUM_THREADS="1",
        OPENBLAS_NUM_THREADS="1",
        MKL_NUM_THREADS="1",
        MPLBACKEND="Agg",
    )
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH", "")]))
    log_dir.mkdir(parents=True, exist_ok=True)
    print(
        f"\n=== {step.name}: {step.script} {' '.join(args)} (limit {step.timeout_s:.0f} s)",
        flush=True,
    )
    t0 = time.perf_counter()
    with open(log_dir / f"{step.name}.log", "w") as log:
        proc = subprocess.Popen(
            [python, str(path), *args],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        assert proc.stdout is not None
        # A watchdog kills the step at its limit even when it prints nothing for a long time.
        fired = threading.Event()

        def kill() -> None:
            fired.set()
            proc.kill()

        watchdog = threading.Timer(step.timeout_s, kill)
        watchdog.start()
        try:
            for line in proc.stdout:
                sys.stdout.write("    " + line)
                log.write(line)
            rc = proc.wait()
        finally:
            watchdog.cancel()
    if fired.is_set():
        status = "timeout"
    elif rc == 0:
        status = "ok"
    elif rc == 1 and step.verdict_exit:
        status = "ok (exit 1: its acceptance criteria not met at quick settings)"
    else:
        status = f"failed (exit {rc})"
    return status, time.perf_counter() - t0


def main(only: list[str] | None, python: str) -> int:
    """Run the selected steps; print and save the summary; return the exit code."""
    QUICK.mkdir(parents=True, exist_ok=True)
    steps = [s for s in STEPS if not only or s.name in only]
    print(
        f"make bench: {len(steps)} steps with quick settings; outputs in {QUICK.relative_to(ROOT)}"
        f"; python {platform.python_version()}, {os.cpu_count()} cores; "
        f"budget {sum(s.timeout_s for s in steps) / 60:.1f} min",
        flush=True,
    )
    results: list[tuple[Step, str, float]] = []
    t_all = time.perf_counter()
    for step in steps:
        status, seconds = run_step(step, python, QUICK / "logs")
        results.append((step, status, seconds))
    total = time.perf_counter() - t_all
    lines = [
        "| step | script | status | seconds |",
        "|---|---|---|---|",
        *[f"| {s.name} | {s.script} | {st} | {sec:.0f} |" for s, st, sec in results],
        f"| total | | | {total:.0f} |",
    ]
    table = "\n".join(lines)
    print("\n" + table)
    (QUICK / "run_all.md").write_text(
        "Quick settings (see benchmarks/run_all.py); full-length results: docs/evaluation.md\n\n"
        + table
        + "\n",
        encoding="utf-8",
    )
    bad = [s.name for s, st, _ in results if not (st.startswith("ok") or st == "missing")]
    return 1 if bad else 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", nargs="+", choices=[s.name for s in STEPS])
    parser.add_argument("--list", action="store_true", help="print the steps and exit")
    parser.add_argument("--python", default=sys.executable)
    a = parser.parse_args()
    if a.list:
        for s in STEPS:
            print(f"{s.name:20s} {s.script} {' '.join(s.args)} (limit {s.timeout_s:.0f} s)")
        sys.exit(0)
    sys.exit(main(a.only, a.python))
