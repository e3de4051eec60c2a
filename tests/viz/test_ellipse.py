"""The one 95 % region of every picture (``mcsm.viz.ellipse``): right for the dimensions the
covariance spans, shared by the 2-D plot and the 3-D scene, drawable by renderers."""

from __future__ import annotations

import numpy as np
import pytest
from mcsm.viz.ellipse import (
    MIN_THICKNESS_RATIO,
    P_REGION,
    ellipse,
    ellipsoid,
    spread_rank,
)
from scipy.stats import chi2


def inside(points: np.ndarray, center: np.ndarray, rot: np.ndarray,
           sizes: np.ndarray) -> np.ndarray:
    """Which points lie inside an ellipsoid given by centre, axes (columns of ``rot``) and
    full axis lengths; a zero axis admits only points on its plane (to round-off)."""
    local = (points - center) @ rot
    half = sizes / 2.0
    flat = half == 0.0
    r2 = np.sum((local[:, ~flat] / half[~flat]) ** 2, axis=1)
    on_plane = np.all(np.abs(local[:, flat]) < 1e-9, axis=1) if flat.any() else True
    return (r2 <= 1.0) & on_plane


def test_planar_disc_holds_95_percent_and_equals_the_plot_ellipse() -> None:
    """A planar map's covariance spans 2 dimensions: the scene's disc is the 2-D region
    (χ²₂), the same ellipse ``mcsm plot`` draws, and holds 95 % of draws. The 3-dof disc the
    scene drew before held about 98.0 % (1.142 times wider)."""
    rng = np.random.default_rng(20261124)
    cov2 = np.array([[0.09, 0.05], [0.05, 0.04]])
    cov3 = np.zeros((3, 3))
    cov3[:2, :2] = cov2
    mean = np.array([2.0, -1.0, 0.0])
    e3 = ellipsoid(mean, cov3)
    e2 = ellipse(mean[:2], cov2)
    assert e3.dof == 2 and e2.dof == 2
    assert sorted(e3.sizes)[1:] == pytest.approx(sorted([e2.width, e2.height]), rel=1e-12)
    assert min(e3.sizes) == 0.0
    n = 200_000
    pts = np.zeros((n, 3))
    pts[:, :2] = rng.multivariate_normal(mean[:2], cov2, size=n)
    frac = inside(pts, mean, e3.rotation(), np.array(e3.sizes)).mean()
    assert abs(frac - P_REGION) < 3 * np.sqrt(0.05 * 0.95 / n)
    # the old definition (χ²₃ for a flat region) is the tester's 14 % wider disc
    wide = np.array(e3.sizes) * np.sqrt(chi2.ppf(0.95, 3) / chi2.ppf(0.95, 2))
    assert wide.max() / max(e3.sizes) == pytest.approx(1.1421, abs=1e-4)
    assert inside(pts, mean, e3.rotation(), wide).mean() > 0.975


def test_full_rank_ellipsoid_holds_95_percent() -> None:
    rng = np.random.default_rng(20261125)
    a = rng.standard_normal((3, 3))
    cov = a @ a.T + 0.05 * np.eye(3)
    mean = rng.standard_normal(3)
    e = ellipsoid(mean, cov)
    assert e.dof == 3
    n = 200_000
    pts = rng.multivariate_normal(mean, cov, size=n)
    frac = inside(pts, mean, e.rotation(), np.array(e.sizes)).mean()
    assert abs(frac - P_REGION) < 3 * np.sqrt(0.05 * 0.95 / n)


def test_2d_ellipse_holds_95_percent() -> None:
    rng = np.random.default_rng(20261126)
    cov = np.array([[0.5, -0.2], [-0.2, 0.3]])
    e = ellipse([1.0, 2.0], cov)
    n = 200_000
    pts = rng.multivariate_normal([1.0, 2.0], cov, size=n)
    a = np.radians(e.angle_deg)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    frac = inside(pts, np.array([1.0, 2.0]), rot, np.array([e.width, e.height])).mean()
    assert abs(frac - P_REGION) < 3 * np.sqrt(0.05 * 0.95 / n)
    # the outline lies on the boundary: Mahalanobis distance² = χ²₂(0.95)
    d = e.outline(24) - np.array([1.0, 2.0])
    d2 = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d)
    np.testing.assert_allclose(d2, chi2.ppf(0.95, 2), rtol=1e-9)


def test_display_sizes_never_degenerate_and_outline_is_on_the_region() -> None:
    cov = np.diag([0.04, 0.01, 0.0])
    e = ellipsoid([1.0, 2.0, 0.0], cov)
    shown = e.display_sizes()
    assert min(shown) == pytest.approx(MIN_THICKNESS_RATIO * max(e.sizes))
    assert sorted(shown)[1:] == sorted(e.sizes)[1:]
    assert ellipsoid([0, 0, 0], np.zeros((3, 3))).display_sizes() == (0.0, 0.0, 0.0)
    ring = e.outline(32)
    d = ring[:, :2] - [1.0, 2.0]
    np.testing.assert_allclose(ring[:, 2], 0.0, atol=1e-12)
    d2 = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov[:2, :2]), d)
    np.testing.assert_allclose(d2, chi2.ppf(0.95, 2), rtol=1e-9)


@pytest.mark.parametrize(("eig", "rank"), [([0, 0, 0], 1), ([0, 0, 1], 1), ([0, 1e-14, 1], 1),
                                          ([0, 1e-6, 1], 2), ([1, 2, 3], 3)])
def test_spread_rank(eig: list[float], rank: int) -> None:
    assert spread_rank(eig) == rank
