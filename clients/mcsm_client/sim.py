"""The paper's §6 simulation as a client: stream the circle scenario into a map and score it.

PAPER §4 (the paper's §6): a robot on a 50 m circle, 200 point landmarks, odometry and a 180° /
30 m laser with the paper's noise; the first revolution closes a large loop at about iteration
340. The scenario (ground truth and noisy readings) comes from
:func:`mcsm_client.scenario.generate_paper_scenario`; this module streams it into a map — an
in-process ``mcsm.StochasticMap`` or a server through ``MapClient`` — and every
``score_every`` iterations computes, over the landmarks in the map, the RMS distance between
their mean estimates and the ground truth and their NEES per degree of freedom (1 = the map's
uncertainty is honest; PAPER §4 plots the RMS, issue 6 adds the NEES). Results go to a CSV and,
with matplotlib (the optional ``eval`` extra), a PNG.

Frames: poses ``x{k}``, landmarks ``l{j}``; the map is bounded (``x0`` anchor, the current
pose and the landmarks) unless ``bounded=False``.
"""

from __future__ import annotations

import csv
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mcsm_client.players import MapTarget
from mcsm_client.scenario import (
    PaperScenarioConfig,
    Scenario,
    generate_paper_scenario,
    run_scenario_on_map,
    score_map,
)

__all__ = ["SimConfig", "SimResult", "SimRow", "plot_results", "run_sim"]


@dataclass(frozen=True)
class SimConfig:
    """What to simulate and how often to score.

    Parameters
    ----------
    n_iterations : int
        Odometry steps (340 is one revolution, the paper's loop closure).
    sigma_theta_deg : float
        Odometry heading noise, degrees (0: PAPER Fig. 4; 0.1: Fig. 5).
    n_landmarks : int
        Point landmarks (200 in the paper).
    score_every : int
        Score the map every this many iterations (and at the last one).
    bounded : bool
        Remove superseded poses (map = landmarks + x0 + current pose).
    """

    n_iterations: int = 340
    sigma_theta_deg: float = 0.0
    n_landmarks: int = 200
    score_every: int = 10
    bounded: bool = True

    def scenario_config(self) -> PaperScenarioConfig:
        """The scenario generator's configuration (paper defaults otherwise)."""
        return PaperScenarioConfig(n_iterations=self.n_iterations,
                                   sigma_theta_deg=self.sigma_theta_deg,
                                   n_landmarks=self.n_landmarks)


@dataclass(frozen=True)
class SimRow:
    """One scored iteration."""

    iteration: int
    n_landmarks: int
    rms_m: float
    nees_per_dof: float
    elapsed_s: float


@dataclass
class SimResult:
    """Per-iteration scores of one run, plus what produced them."""

    config: SimConfig
    n_samples: int
    rows: list[SimRow] = field(default_factory=list)
    digest: str = ""
    elapsed_s: float = 0.0
    n_updates: int = 0

    @property
    def final(self) -> SimRow:
        """The last scored iteration."""
        if not self.rows:
            raise ValueError("no iteration was scored")
        return self.rows[-1]

    def write_csv(self, path: str | os.PathLike[str]) -> Path:
        """Write ``iteration,n_landmarks,rms_m,nees_per_dof,elapsed_s`` rows; returns the path."""
        p = Path(path)
        p.parent.mkdir(parents=True, exist_ok=True)
        with open(p, "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(["iteration", "n_landmarks", "rms_m", "nees_per_dof", "elapsed_s"])
            for r in self.rows:
                w.writerow([r.iteration, r.n_landmarks, f"{r.rms_m:.6g}",
                            f"{r.nees_per_dof:.6g}", f"{r.elapsed_s:.3f}"])
        return p

    def summary(self) -> str:
        """One line for people."""
        f = self.final
        return (f"N={self.n_samples} sigma_theta={self.config.sigma_theta_deg} deg: after "
                f"{f.iteration} iterations, {f.n_landmarks} landmarks, RMS {f.rms_m:.3f} m, "
                f"NEES/dof {f.nees_per_dof:.2f} ({self.n_updates} updates, "
                f"{self.elapsed_s:.1f} s)")

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (config, N, final scores, digest)."""
        return {"config": asdict(self.config), "n_samples": self.n_samples,
                "final": asdict(self.final), "digest": self.digest,
                "elapsed_s": self.elapsed_s, "n_updates": self.n_updates}


class _Counting:
    """Counts the updates that reach the map (odometry + sightings)."""

    def __init__(self, target: MapTarget) -> None:
        self.target = target
        self.n_updates = 0

    def update(self, a: str, b: str, samples: Any, /) -> str:
        self.n_updates += 1
        return self.target.update(a, b, samples)

    def remove(self, frame: str, /) -> None:
        self.target.remove(frame)

    def marginal(self, a: str, b: str, /) -> Any:
        return self.target.marginal(a, b)

    def __contains__(self, frame: object, /) -> bool:
        return frame in self.target


def run_sim(
    config: SimConfig,
    target: Any,
    *,
    rng: np.random.Generator,
    scenario: Scenario | None = None,
    progress: Callable[[SimRow], None] | None = None,
) -> SimResult:
    """Run the §6 scenario against a map and score it along the way.

    Parameters
    ----------
    config : SimConfig
        Length, noise and scoring interval.
    target : StochasticMap, MapClient or MapTarget
        An empty map (frames ``x*``/``l*`` must not exist yet).
    rng : np.random.Generator
        Source of all randomness: the scenario draws from one child generator, the sample
        sets from another (``rng.spawn(2)``).
    scenario : Scenario, optional
        Use this scenario instead of generating one (its config wins over ``config``'s
        scenario fields; ``config.n_iterations`` still bounds the run).
    progress : callable, optional
        Called with each scored :class:`SimRow`.

    Returns
    -------
    SimResult
    """
    if config.score_every < 1 or config.n_iterations < 1:
        raise ValueError("n_iterations and score_every must be >= 1")
    scen_rng, map_rng = rng.spawn(2)
    if scenario is None:
        scenario = generate_paper_scenario(config.scenario_config(), scen_rng)
    m = MapTarget(target)
    n = m.n_samples
    counting = _Counting(m)
    result = SimResult(config=config, n_samples=n)
    t_end = min(config.n_iterations, scenario.n_iterations)
    t0 = time.perf_counter()

    def on_iteration(k: int, _smap: Any) -> None:
        if k % config.score_every and k != t_end:
            return
        s = score_map(m, scenario)
        row = SimRow(iteration=k, n_landmarks=int(s["n_landmarks"]), rms_m=s["rms_m"],
                     nees_per_dof=s["nees_per_dof"], elapsed_s=time.perf_counter() - t0)
        result.rows.append(row)
        if progress is not None:
            progress(row)

    run_scenario_on_map(scenario, counting, n, map_rng, bounded=config.bounded,
                        callback=on_iteration, n_iterations=t_end)
    result.elapsed_s = time.perf_counter() - t0
    result.n_updates = counting.n_updates
    result.digest = m.digest()
    return result


def plot_results(results: Mapping[str, SimResult] | SimResult,
                 path: str | os.PathLike[str], *, title: str = "") -> Path:
    """PNG of RMS landmark error and NEES per dof vs iteration (one line per run).

    Needs matplotlib (``pip install 'mcsm[eval]'``); imported here, not at module import.

    Raises
    ------
    ImportError
        If matplotlib is missing (the message says how to install it).
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("plotting needs matplotlib: pip install 'mcsm[eval]'") from exc
    runs = {"run": results} if isinstance(results, SimResult) else dict(results)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for label, r in runs.items():
        it = [row.iteration for row in r.rows]
        ax1.plot(it, [row.rms_m for row in r.rows], label=label)
        ax2.plot(it, [row.nees_per_dof for row in r.rows], label=label)
    ax1.set_ylabel("landmark RMS error [m]")
    ax2.set_ylabel("landmark NEES per dof")
    ax2.set_yscale("log")
    ax2.axhline(1.0, color="grey", lw=0.8, ls="--")
    ax2.set_xlabel("iteration")
    ax1.legend()
    ax1.grid(alpha=0.3)
    ax2.grid(alpha=0.3, which="both")
    fig.suptitle(title or "Monte Carlo stochastic map, paper §6 scenario")
    fig.tight_layout()
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p
