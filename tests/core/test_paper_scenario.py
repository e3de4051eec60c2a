"""PAPER §4 (the paper's §6), short: the joint update's landmark error falls after loop closure."""

from __future__ import annotations

import numpy as np
from mcsm import StochasticMap
from mcsm_client.scenario import (
    PaperScenarioConfig,
    generate_paper_scenario,
    run_scenario_on_map,
    score_map,
)


def test_landmark_error_falls_after_the_loop_closes() -> None:
    scenario = generate_paper_scenario(PaperScenarioConfig(n_iterations=400),
                                       np.random.default_rng(20120141))
    m = StochasticMap(1000, method="joint")
    scores: dict[int, dict[str, float]] = {}

    def log(k: int, smap: StochasticMap) -> None:
        if k in (320, 400):
            scores[k] = score_map(smap, scenario)

    run_scenario_on_map(scenario, m, 1000, np.random.default_rng(20120142), callback=log)
    before, after = scores[320], scores[400]
    print(f"\n§6 N=1000 joint: RMS {before['rms_m']:.3f} m (it 320, loop open) -> "
          f"{after['rms_m']:.3f} m (it 400); NEES/dof {before['nees_per_dof']:.2f} -> "
          f"{after['nees_per_dof']:.2f}")
    assert after["n_landmarks"] >= before["n_landmarks"]
    assert after["rms_m"] < 0.95 * before["rms_m"]
    assert np.isfinite(after["nees_per_dof"]) and after["nees_per_dof"] < 3.0
