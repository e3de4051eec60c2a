"""Regression guard for issue 6: the map's landmark NEES must stay near 1 over hundreds of updates.

A small §6-style scenario (60 landmarks, a loop every 150 steps, 250 iterations, about 400
point updates, N = 100) run through the bounded map. The square-root analysis with correlation
shrink c = 4 (the remedy measured by ``experiments/consistency.py``) must keep NEES per dof at or
below 2 at every logged iteration, with landmark RMS close to the exact Kalman filter
(the EKF baseline with σ_θ = 0) on the same readings. The plain perturbed-observation update
collapses on the same run (NEES several times larger): that check shows the bound bites.
"""

from __future__ import annotations

import numpy as np
import pytest
from mcsm import StochasticMap
from mcsm_client.scenario import (
    PaperScenarioConfig,
    Scenario,
    generate_paper_scenario,
    landmark_rms,
    landmarks_in_frame,
    run_scenario_on_map,
    score_map,
)

from experiments.baselines.ekf_slam import run_ekf_on_scenario

N_SAMPLES = 100
LOG = (50, 100, 150, 200, 250)
CONFIG = PaperScenarioConfig(n_iterations=250, n_landmarks=60, steps_per_revolution=150,
                             p_observe=0.3)
#: The remedy under guard (explicit, so a change of the map's defaults cannot hide a regression).
REMEDY = {"method": "joint", "analysis": "ensrf", "shrink": 4.0, "inflation": 1.0}


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return generate_paper_scenario(CONFIG, np.random.default_rng(20260301))


def _curve(scenario: Scenario, options: dict[str, object]) -> dict[int, dict[str, float]]:
    m = StochasticMap(N_SAMPLES, **options)  # type: ignore[arg-type]
    out: dict[int, dict[str, float]] = {}

    def cb(k: int, smap: StochasticMap) -> None:
        if k in LOG:
            out[k] = score_map(smap, scenario)

    run_scenario_on_map(scenario, m, N_SAMPLES, np.random.default_rng(20260302), callback=cb)
    return out


def _ekf_rms(scenario: Scenario) -> float:
    ekf = run_ekf_on_scenario(scenario)
    ids, means, _ = ekf.landmark_estimates()
    return landmark_rms(means, landmarks_in_frame(scenario)[ids])


def test_remedy_keeps_nees_bounded_and_rms_near_kalman(scenario: Scenario) -> None:
    curve = _curve(scenario, REMEDY)
    nees = {k: v["nees_per_dof"] for k, v in curve.items()}
    assert set(nees) == set(LOG)
    assert all(np.isfinite(v) for v in nees.values())
    # Honest uncertainty: NEES/dof ~ 1 (the exact filter sits at 0.9-1.2 on runs like this).
    assert max(nees.values()) <= 2.0, nees
    # Accuracy close to the exact Kalman filter on identical readings.
    assert curve[250]["rms_m"] <= 1.35 * _ekf_rms(scenario), curve[250]


def test_plain_enkf_update_collapses_on_the_same_run(scenario: Scenario) -> None:
    # the update rule alone: the default relinearisation would repair it
    curve = _curve(scenario, {"method": "joint", "analysis": "enkf", "shrink": None,
                              "relinearize": None})
    assert curve[250]["nees_per_dof"] > 4.0, curve
