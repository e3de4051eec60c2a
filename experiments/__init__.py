"""Experiments: consistency measurements, paper figures and baselines (not part of the wheel)."""
