"""The numpy side of the pictures: χ² quantiles, ellipses, ellipsoids, ground truth files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcsm.errors import McsmError
from mcsm.viz.scene import chi2_quantile, ellipse, ellipsoid, read_truth
from scipy.spatial.transform import Rotation
from scipy.stats import chi2


@pytest.mark.parametrize("dof", [1, 2, 3])
@pytest.mark.parametrize("p", [0.5, 0.9, 0.95, 0.997])
def test_chi2_quantile_matches_scipy(dof: int, p: float) -> None:
    assert chi2_quantile(p, dof) == pytest.approx(chi2.ppf(p, dof), rel=1e-12)


def random_cov(rng: np.random.Generator, d: int) -> np.ndarray:
    a = rng.standard_normal((d, d))
    return a @ a.T + 0.01 * np.eye(d)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_ellipse_is_the_95_percent_contour(seed: int) -> None:
    rng = np.random.default_rng(20261100 + seed)
    cov = random_cov(rng, 2)
    mean = rng.standard_normal(2)
    e = ellipse(mean, cov)
    k = chi2.ppf(0.95, 2)
    th = np.radians(e.angle_deg)
    r = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    # the ellipse's axes give back the covariance: R diag(a², b²) Rᵀ / k
    rebuilt = r @ np.diag([(e.width / 2) ** 2, (e.height / 2) ** 2]) @ r.T / k
    np.testing.assert_allclose(rebuilt, cov, rtol=1e-10, atol=1e-12)
    assert e.width >= e.height
    np.testing.assert_allclose(e.center, mean)
    # points on the drawn boundary have Mahalanobis distance² k
    t = np.linspace(0, 2 * np.pi, 7)
    pts = (r @ np.stack([e.width / 2 * np.cos(t), e.height / 2 * np.sin(t)])).T
    d2 = np.einsum("ni,ij,nj->n", pts, np.linalg.inv(cov), pts)
    np.testing.assert_allclose(d2, k, rtol=1e-9)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_ellipsoid_axes_and_rotation_give_back_the_covariance(seed: int) -> None:
    rng = np.random.default_rng(20261110 + seed)
    cov = random_cov(rng, 3)
    e = ellipsoid(rng.standard_normal(3), cov)
    k = chi2.ppf(0.95, 3)
    r = Rotation.from_quat(e.quat_xyzw).as_matrix()  # scipy's order is x y z w too
    np.testing.assert_allclose(r, e.rotation(), atol=1e-12)
    rebuilt = r @ np.diag((np.array(e.sizes) / 2) ** 2 / k) @ r.T
    np.testing.assert_allclose(rebuilt, cov, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(sorted(e.sizes), 2 * np.sqrt(k * np.linalg.eigvalsh(cov)))


def test_degenerate_covariances_give_flat_regions() -> None:
    e = ellipse([0, 0], np.diag([4.0, 0.0]))  # all spread along one line: the 1-D region
    assert e.dof == 1
    assert e.height == 0.0 and e.width == pytest.approx(2 * np.sqrt(chi2.ppf(0.95, 1) * 4))
    s = ellipsoid([0, 0, 0], np.diag([1.0, 1.0, -1e-20])).sizes
    assert min(s) == 0.0


def test_read_truth(tmp_path: Path) -> None:
    f = tmp_path / "truth.csv"
    f.write_text("frame,x,y,z\n# comment\nl0,1.5,2,0.25\n\nrobot/base,3,4\n")
    t = read_truth(f)
    assert set(t) == {"l0", "robot/base"}
    np.testing.assert_array_equal(t["l0"], [1.5, 2.0, 0.25])
    np.testing.assert_array_equal(t["robot/base"], [3.0, 4.0, 0.0])


@pytest.mark.parametrize(("text", "needle"), [
    ("l0,1\n", ":1: expected frame,x,y[,z]"),
    ("l0,1,2\nl1,a,2\n", ":2: coordinates must be numbers"),
    ("l0,1,nan\n", ":1: coordinates must be finite"),
])
def test_read_truth_errors_name_the_line(tmp_path: Path, text: str, needle: str) -> None:
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(McsmError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        read_truth(f)
    with pytest.raises(McsmError, match="cannot read ground truth"):
        read_truth(tmp_path / "missing.csv")


def test_imports_stay_light() -> None:
    """``import mcsm``, the CLI and the numpy side of mcsm.viz load neither matplotlib nor
    foxglove (they come with the viz extra, imported by the commands that draw)."""
    code = ("import sys, mcsm, mcsm.core, mcsm.cli, mcsm.viz.scene, mcsm.viz.commands; "
            "mcsm.cli.build_parser(); "
            "bad = {'matplotlib', 'foxglove'} & set(sys.modules); print(sorted(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
