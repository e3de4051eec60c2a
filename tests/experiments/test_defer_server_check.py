"""The server's deferral decides as the benchmark's client-side policy on a benchmark case
(``experiments/defer_server_check.py``; all 48 cases of seeds 8 and 9 in docs/outliers.md)."""

from __future__ import annotations

from experiments.defer_server_check import check


def test_long_burst_case_agrees_with_the_client_policy() -> None:
    same, agree, n, held, _, _ = check("long", "burst", 0.2, 8, 200)
    assert same and agree == n > 150
    assert held >= 2  # deferral acted: several first closures were held
