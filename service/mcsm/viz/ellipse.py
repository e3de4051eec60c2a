"""The one 95 % confidence region every mcsm picture draws (numpy only).

``mcsm plot`` (2-D ellipses, 3-D wireframes), the Foxglove scene of ``mcsm export foxglove``
and ``mcsm view``, and ROS ``visualization_msgs/Marker`` ellipsoids all take their shape from
:func:`ellipse` and :func:`ellipsoid` here.

The region of a Gaussian with mean μ and covariance Σ is ``{x : (x − μ)ᵀ Σ⁺ (x − μ) ≤ k}``
with ``k = χ²_d(p)`` and ``d`` the number of dimensions the distribution actually spans, the
rank of Σ. Its full axis lengths are ``2 √(k λᵢ)`` for the eigenvalues ``λᵢ`` of Σ, along its
eigenvectors.

Why the rank and not always 3: a planar map's frames have no spread out of their plane (Σ has
one zero eigenvalue); the distribution lives in that plane, and its 95 % region there is the
2-D one, ``χ²₂(0.95) = 5.991``. Using ``χ²₃(0.95) = 7.815`` for it drew a disc
``√(7.815 / 5.991) = 1.142`` times too wide (what a tester measured in Foxglove: 14 % wider
than ``mcsm plot``'s ellipse, which was right). A full-rank 3-D covariance still gets
``χ²₃``; its 95 % ellipsoid is not the 95 % ellipse of its top view (a shadow of a 3-D region
holds more than 95 % of the 2-D marginal), which is why a 3-D map's 2-D plot and its 3-D
scene may differ.

Renderers cannot draw an ellipsoid with a zero axis well (Foxglove and RViz light a sphere
through its inverse scale: a zero axis gives undefined normals, and the disc shows grey or
black whatever its colour). :meth:`Ellipsoid.display_sizes` gives the sizes to draw, with
every axis at least :data:`MIN_THICKNESS_RATIO` of the largest; :attr:`Ellipsoid.sizes` stay
the true ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from mcsm.core.gate import chi2_quantile as _core_chi2_quantile

Array = npt.NDArray[np.float64]

#: probability mass inside every drawn ellipse / ellipsoid
P_REGION = 0.95
#: an eigenvalue at most this fraction of the largest counts as zero (no spread that way)
RANK_TOL = 1e-12
#: the thinnest axis a renderer is given, as a fraction of the largest (display only)
MIN_THICKNESS_RATIO = 0.01


def chi2_quantile(p: float, dof: int) -> float:
    """Quantile of the χ² distribution with ``dof`` degrees of freedom (the gate's own,
    :func:`mcsm.core.gate.chi2_quantile`; closed form for 2 dof)."""
    if dof == 2 and 0.0 < p < 1.0:
        return -2.0 * math.log1p(-p)
    return _core_chi2_quantile(p, dof)


def spread_rank(eigenvalues: npt.ArrayLike) -> int:
    """How many dimensions a covariance spans: eigenvalues above ``RANK_TOL`` × the largest
    (at least 1, so that a point mass still gets a region of size 0)."""
    lam = np.clip(np.asarray(eigenvalues, dtype=np.float64), 0.0, None)
    top = float(lam.max()) if lam.size else 0.0
    if top <= 0.0:
        return 1
    return max(1, int(np.count_nonzero(lam > RANK_TOL * top)))


def region_scale(dof: int, p: float = P_REGION) -> float:
    """``χ²_dof(p)``: the squared Mahalanobis radius of the ``p`` region."""
    return chi2_quantile(p, dof)


@dataclass(frozen=True)
class Ellipse:
    """A 2-D confidence ellipse: centre, full axis lengths, angle of ``width`` from +x (deg)."""

    center: tuple[float, float]
    width: float
    height: float
    angle_deg: float
    dof: int = 2  # the χ² degrees of freedom used (the rank of the covariance)

    def outline(self, n: int = 48) -> Array:
        """``(n, 2)`` points around the ellipse, counter-clockwise, the first not repeated."""
        t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        a = math.radians(self.angle_deg)
        u = np.column_stack([0.5 * self.width * np.cos(t), 0.5 * self.height * np.sin(t)])
        rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
        return np.asarray(u @ rot.T + np.asarray(self.center), dtype=np.float64)


@dataclass(frozen=True)
class Ellipsoid:
    """A 3-D confidence ellipsoid: centre, full axis lengths along its own x, y, z, and the
    rotation of those axes into the parent frame as a unit quaternion ``(x, y, z, w)``
    (Foxglove's and ROS's order). ``sizes`` are ascending (the eigenvalue order)."""

    center: tuple[float, float, float]
    sizes: tuple[float, float, float]
    quat_xyzw: tuple[float, float, float, float]
    dof: int = 3  # the χ² degrees of freedom used (the rank of the covariance)

    def rotation(self) -> Array:
        """The 3×3 rotation matrix of :attr:`quat_xyzw`."""
        x, y, z, w = self.quat_xyzw
        return np.array([
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])

    def display_sizes(self, min_ratio: float = MIN_THICKNESS_RATIO
                      ) -> tuple[float, float, float]:
        """Sizes to give a renderer: no axis thinner than ``min_ratio`` × the largest (a flat
        disc gets a thin, lit thickness instead of a degenerate one); the true
        :attr:`sizes` otherwise. All zero stays all zero."""
        top = max(self.sizes)
        floor = min_ratio * top
        a, b, c = (max(s, floor) for s in self.sizes)
        return (a, b, c)

    def outline(self, n: int = 48) -> Array:
        """``(n, 3)`` points around the ellipse of the two largest axes (in the parent frame):
        an unlit outline that shows the region's colour whatever the lighting."""
        t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
        u = np.column_stack([np.zeros(n), 0.5 * self.sizes[1] * np.cos(t),
                             0.5 * self.sizes[2] * np.sin(t)])
        return np.asarray(u @ self.rotation().T + np.asarray(self.center), dtype=np.float64)


def _spread(cov: npt.ArrayLike) -> tuple[Array, Array, int]:
    """Eigenvalues (ascending; round-off negatives and those at most ``RANK_TOL`` of the
    largest set to 0), eigenvectors, and the rank (:func:`spread_rank`) of a covariance."""
    c = np.asarray(cov, dtype=np.float64)
    lam, vec = np.linalg.eigh(0.5 * (c + c.T))
    lam = np.clip(lam, 0.0, None)
    dof = spread_rank(lam)
    lam = np.where(lam > RANK_TOL * float(lam.max(initial=0.0)), lam, 0.0)
    return lam, vec, dof


def ellipse(mean2: npt.ArrayLike, cov2: npt.ArrayLike, p: float = P_REGION) -> Ellipse:
    """The ``p`` confidence ellipse of a 2-D Gaussian (``width`` along the major axis).

    A rank-1 covariance (all spread along one line) gets ``χ²₁(p)`` and height 0.

    Parameters
    ----------
    mean2 : (2,) float64, metres
    cov2 : (2, 2) float64, m²; negative eigenvalues from round-off count as 0
    """
    lam, vec, dof = _spread(cov2)
    k = chi2_quantile(p, dof)
    major = vec[:, 1]
    m = np.asarray(mean2, dtype=np.float64)
    return Ellipse((float(m[0]), float(m[1])), float(2.0 * math.sqrt(k * lam[1])),
                   float(2.0 * math.sqrt(k * lam[0])),
                   float(math.degrees(math.atan2(major[1], major[0]))), dof)


def quat_xyzw(r: npt.ArrayLike) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` of a rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    t = float(np.trace(r))
    if t > 0:
        s = 2.0 * math.sqrt(1.0 + t)
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, \
            (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, \
            (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, \
            (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, \
            (r[1, 2] + r[2, 1]) / s, 0.25 * s
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return (float(x / n), float(y / n), float(z / n), float(w / n))


def ellipsoid(mean3: npt.ArrayLike, cov3: npt.ArrayLike, p: float = P_REGION) -> Ellipsoid:
    """The ``p`` confidence region of a 3-D Gaussian as an ellipsoid.

    Its axes are the eigenvectors of ``cov3`` (one flipped if needed to make a rotation), its
    full lengths ``2 √(χ²_d(p) λᵢ)`` with ``d`` the rank of ``cov3`` (module docstring): a
    planar covariance gives the 2-D region as a flat disc (smallest size 0).

    Parameters
    ----------
    mean3 : (3,) float64, metres
    cov3 : (3, 3) float64, m²; negative eigenvalues from round-off count as 0
    """
    lam, vec, dof = _spread(cov3)
    if np.linalg.det(vec) < 0:
        vec[:, 0] = -vec[:, 0]
    k = chi2_quantile(p, dof)
    sizes = 2.0 * np.sqrt(k * lam)
    m = np.asarray(mean3, dtype=np.float64)
    return Ellipsoid((float(m[0]), float(m[1]), float(m[2])),
                     (float(sizes[0]), float(sizes[1]), float(sizes[2])), quat_xyzw(vec), dof)


__all__ = ["P_REGION", "RANK_TOL", "MIN_THICKNESS_RATIO", "Ellipse", "Ellipsoid",
           "chi2_quantile", "ellipse", "ellipsoid", "quat_xyzw", "region_scale", "spread_rank"]
