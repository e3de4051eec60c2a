"""Reference estimators the Monte Carlo map is measured against (EKF-SLAM)."""
