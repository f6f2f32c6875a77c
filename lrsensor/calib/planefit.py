"""Plane fitting for calibration: least squares (SVD), RANSAC, fits through a fixed point, wall planes.

Pure numpy, vectorized. Planes are ``normal . p = offset`` with a unit ``normal`` (body frame, metres) unless a
function says otherwise. Everything random takes a seeded :class:`numpy.random.Generator`.

The paper (section 2.6) intersects the camera rays of the stripe pixels with a wall of known pose (eq. 30-31)
and fits the laser plane by least squares; here the fit is made robust (RANSAC, then an iteratively
re-gated least-squares refit on the inliers) and its degeneracy is detected: all points of one wall position
lie on one line, which does not determine a plane unless a point of the plane off that line is known (the
laser's mounting point).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import CalibrationFitError, GeometryError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int_]

#: MAD to standard deviation for normally distributed residuals.
MAD_TO_SIGMA = 1.4826


def _points(points: ArrayLike, what: str = "points") -> FloatArray:
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        msg = f"{what} must have shape (N, 3), got {p.shape}"
        raise GeometryError(msg)
    if not np.all(np.isfinite(p)):
        msg = f"{what} hold {int(np.sum(~np.all(np.isfinite(p), axis=1)))} non-finite rows"
        raise GeometryError(msg)
    return p


@dataclass(frozen=True)
class Plane:
    """A plane ``normal . p = offset`` (unit normal, metres).

    Attributes:
        normal: unit normal, shape (3,).
        offset: signed distance of the plane from the origin along ``normal``, metres.
    """

    normal: FloatArray
    offset: float

    @classmethod
    def from_point_normal(cls, point: ArrayLike, normal: ArrayLike) -> Plane:
        """The plane through ``point`` (3,) with normal ``normal`` (3,) (normalised here)."""
        n = np.asarray(normal, dtype=float).reshape(3)
        norm = float(np.linalg.norm(n))
        if not (norm > 1e-12 and np.isfinite(norm)):
            msg = f"plane normal must be a non-zero finite vector, got {n.tolist()}"
            raise GeometryError(msg)
        n = n / norm
        return cls(n, float(n @ np.asarray(point, dtype=float).reshape(3)))

    def signed_distance(self, points: ArrayLike) -> FloatArray:
        """Signed distances (N,) of points (N, 3) to the plane, metres (positive on the normal's side)."""
        return np.asarray(points, dtype=float).reshape(-1, 3) @ self.normal - self.offset

    def project(self, point: ArrayLike) -> FloatArray:
        """The foot of the perpendicular from ``point`` (3,) onto the plane, shape (3,)."""
        p = np.asarray(point, dtype=float).reshape(3)
        return p - (float(p @ self.normal) - self.offset) * self.normal

    def oriented_like(self, reference: ArrayLike) -> Plane:
        """The same plane with its normal flipped, if needed, to have a non-negative dot with ``reference``."""
        if float(self.normal @ np.asarray(reference, dtype=float).reshape(3)) < 0:
            return Plane(-self.normal, -self.offset)
        return self

    def angle_to_deg(self, other_normal: ArrayLike) -> float:
        """Angle in degrees between this plane and a plane of normal ``other_normal`` (0..90, sign-free)."""
        return normal_angle_deg(self.normal, other_normal)


def normal_angle_deg(n1: ArrayLike, n2: ArrayLike) -> float:
    """Angle in degrees (0..90) between two planes given by their normals (orientation ignored)."""
    a = np.asarray(n1, dtype=float).reshape(3)
    b = np.asarray(n2, dtype=float).reshape(3)
    c = abs(float(a @ b)) / (float(np.linalg.norm(a)) * float(np.linalg.norm(b)))
    # atan2 of |a x b| and |a . b| keeps precision for tiny angles (arccos does not).
    s = float(np.linalg.norm(np.cross(a, b))) / (float(np.linalg.norm(a)) * float(np.linalg.norm(b)))
    return float(np.degrees(np.arctan2(s, c)))


def fit_plane_lsq(points: ArrayLike, weights: ArrayLike | None = None) -> Plane:
    """Total least-squares plane of points (N, 3), N >= 3: centroid and the smallest singular vector.

    Args:
        points: shape (N, 3), metres.
        weights: optional non-negative weights (N,) (e.g. inverse variances).

    Returns:
        The plane minimising ``sum w_i * dist_i**2``.
    """
    p = _points(points)
    if p.shape[0] < 3:
        msg = f"a plane needs at least 3 points, got {p.shape[0]}"
        raise CalibrationFitError(msg)
    w = np.ones(p.shape[0]) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    centroid = (w[:, None] * p).sum(axis=0) / w.sum()
    q = (p - centroid) * np.sqrt(w)[:, None]
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    return Plane.from_point_normal(centroid, vt[2])


def fit_plane_through_point(points: ArrayLike, anchor: ArrayLike, weights: ArrayLike | None = None) -> Plane:
    """Least-squares plane constrained to pass through ``anchor`` (3,): minimises ``sum w ((p - a) . n)**2``.

    With the points of one wall (a line) and the laser's mounting point this is the plane through the point
    that contains the line.

    Args:
        points: shape (N, 3), N >= 2, metres.
        anchor: the fixed point of the plane, shape (3,), metres.
        weights: optional non-negative weights (N,).
    """
    p = _points(points)
    a = np.asarray(anchor, dtype=float).reshape(3)
    if p.shape[0] < 2:
        msg = f"a plane through a fixed point needs at least 2 more points, got {p.shape[0]}"
        raise CalibrationFitError(msg)
    w = np.ones(p.shape[0]) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    q = (p - a) * np.sqrt(w)[:, None]
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    return Plane.from_point_normal(a, vt[-1])


def principal_spreads(points: ArrayLike) -> FloatArray:
    """RMS spread of points (N, 3) along their three principal axes, largest first, shape (3,), metres.

    A single straight stripe has a large first, and tiny second and third spreads; stripes of walls at two
    distances span a plane (large first and second, tiny third).
    """
    p = _points(points)
    if p.shape[0] < 2:
        return np.zeros(3)
    s = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    out = np.zeros(3)
    out[: s.size] = s / np.sqrt(p.shape[0])
    return out


def line_fit(points: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Least-squares 3D line ``(centroid (3,), unit direction (3,))`` of points (N, 3)."""
    p = _points(points)
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    return c, vt[0]


def distance_to_line(point: ArrayLike, centroid: ArrayLike, direction: ArrayLike) -> float:
    """Distance (metres) of ``point`` (3,) from the line through ``centroid`` along unit ``direction``."""
    d = np.asarray(point, dtype=float).reshape(3) - np.asarray(centroid, dtype=float).reshape(3)
    u = np.asarray(direction, dtype=float).reshape(3)
    return float(np.linalg.norm(d - (d @ u) * u))


def _sample_planes(
    p: FloatArray, n_samples: int, rng: np.random.Generator, groups: IntArray | None, anchor: FloatArray | None
) -> tuple[FloatArray, FloatArray]:
    """Candidate planes ``(normals (K, 3), offsets (K,))`` from random minimal samples, degenerate ones dropped."""
    n = p.shape[0]
    k = 3 * n_samples
    i1 = rng.integers(0, n, k)
    i2 = rng.integers(0, n, k)
    if anchor is not None:
        a, b, c = np.broadcast_to(anchor, (k, 3)), p[i1], p[i2]
        keep = i1 != i2
    else:
        i3 = rng.integers(0, n, k)
        a, b, c = p[i1], p[i2], p[i3]
        keep = (i1 != i2) & (i1 != i3) & (i2 != i3)
        if groups is not None and np.unique(groups).size > 1:
            # A triple from one wall is (nearly) collinear: take one point from another wall.
            keep &= (groups[i1] != groups[i2]) | (groups[i1] != groups[i3])
    normals = np.cross(b - a, c - a)
    norms = np.linalg.norm(normals, axis=1)
    scale = np.linalg.norm(b - a, axis=1) * np.linalg.norm(c - a, axis=1)
    keep &= norms > 1e-6 * np.maximum(scale, 1e-300)
    normals = normals[keep][:n_samples] / norms[keep][:n_samples, None]
    offsets = np.einsum("ij,ij->i", normals, a[keep][:n_samples])
    return normals, offsets


def ransac_plane(
    points: ArrayLike,
    threshold_m: float,
    rng: np.random.Generator,
    *,
    iterations: int = 300,
    groups: ArrayLike | None = None,
    anchor: ArrayLike | None = None,
    max_score_points: int = 3000,
) -> tuple[Plane, BoolArray]:
    """RANSAC plane (MSAC scoring) of points (N, 3).

    Args:
        points: shape (N, 3), metres.
        threshold_m: inlier distance, metres.
        rng: seeded random generator (the result is deterministic for a given seed).
        iterations: number of minimal samples tried.
        groups: optional group label (N,) per point (the wall image it came from); triples are drawn across
            groups, since three points of one wall are nearly collinear.
        anchor: optional fixed point (3,) the plane must contain (then two points per sample).
        max_score_points: candidates are scored on at most this many points (a random subset).

    Returns:
        ``(plane, inliers)``: the best candidate plane (not refit) and the inlier mask (N,) over all points.
    """
    p = _points(points)
    need = 2 if anchor is not None else 3
    if p.shape[0] < need:
        msg = f"RANSAC needs at least {need} points, got {p.shape[0]}"
        raise CalibrationFitError(msg)
    g = None if groups is None else np.asarray(groups).reshape(-1)
    a = None if anchor is None else np.asarray(anchor, dtype=float).reshape(3)
    normals, offsets = _sample_planes(p, iterations, rng, g, a)
    if normals.shape[0] == 0:
        msg = "RANSAC found no non-degenerate sample: the points are (nearly) collinear or coincident"
        raise CalibrationFitError(msg)
    score_idx = rng.choice(p.shape[0], size=min(p.shape[0], max_score_points), replace=False)
    ps = p[score_idx]
    t2 = threshold_m * threshold_m
    best_cost = np.inf
    best = 0
    for start in range(0, normals.shape[0], 64):  # chunks keep the (K, N) residual matrix small
        res = ps @ normals[start : start + 64].T - offsets[start : start + 64]
        cost = np.minimum(res * res, t2).sum(axis=0)
        j = int(np.argmin(cost))
        if cost[j] < best_cost:
            best_cost, best = float(cost[j]), start + j
    plane = Plane(normals[best], float(offsets[best]))
    inliers = np.abs(plane.signed_distance(p)) <= threshold_m
    return plane, inliers


@dataclass(frozen=True)
class RobustPlaneFit:
    """Result of :func:`robust_plane_fit`.

    Attributes:
        plane: the refit plane.
        inliers: mask (N,) of the points used in the final least-squares fit.
        residuals: signed distances (N,) of all points to ``plane``, metres.
        gate_m: final inlier distance, metres.
        sigma_m: robust (MAD) standard deviation of the inlier residuals, metres.
    """

    plane: Plane
    inliers: BoolArray
    residuals: FloatArray
    gate_m: float
    sigma_m: float

    @property
    def rms_m(self) -> float:
        """RMS of the inlier residuals, metres."""
        r = self.residuals[self.inliers]
        return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")

    @property
    def max_abs_m(self) -> float:
        """Largest absolute inlier residual, metres."""
        r = self.residuals[self.inliers]
        return float(np.max(np.abs(r))) if r.size else float("nan")


def robust_plane_fit(
    points: ArrayLike,
    rng: np.random.Generator,
    *,
    ransac_threshold_m: float = 0.002,
    outlier_m: float = 0.010,
    min_gate_m: float = 0.0005,
    gate_sigmas: float = 4.0,
    groups: ArrayLike | None = None,
    anchor: ArrayLike | None = None,
    weights: ArrayLike | None = None,
    iterations: int = 300,
    refits: int = 4,
) -> RobustPlaneFit:
    """RANSAC, then least-squares refits on inliers with a gate adapted to the residual spread.

    The gate after each refit is ``clip(gate_sigmas * sigma, min_gate_m, outlier_m)`` where ``sigma`` is the
    MAD-based spread of the residuals of the points within ``outlier_m``; so isolated stray points are dropped
    while a genuinely noisy (or inconsistent) data set keeps its points and shows a large RMS.

    Args:
        points: shape (N, 3), metres.
        rng: seeded random generator.
        ransac_threshold_m: RANSAC inlier distance, metres.
        outlier_m: points farther than this from the plane are never inliers, metres.
        min_gate_m: the gate never goes below this, metres.
        gate_sigmas: gate in robust standard deviations.
        groups, anchor: as for :func:`ransac_plane`; with ``anchor`` every fit passes through it.
        weights: optional weights (N,) for the least-squares refits.
        iterations: RANSAC samples.
        refits: number of re-gated least-squares refits.
    """
    p = _points(points)
    w = None if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    plane, inl = ransac_plane(p, ransac_threshold_m, rng, iterations=iterations, groups=groups, anchor=anchor)
    gate = ransac_threshold_m
    sigma = float("nan")
    for _ in range(max(1, refits)):
        need = 2 if anchor is not None else 3
        if int(inl.sum()) < need:
            msg = f"only {int(inl.sum())} points lie within {gate * 1000:.2f} mm of the best plane"
            raise CalibrationFitError(msg)
        wi = None if w is None else w[inl]
        new = fit_plane_through_point(p[inl], anchor, wi) if anchor is not None else fit_plane_lsq(p[inl], wi)
        plane = new.oriented_like(plane.normal)
        res = plane.signed_distance(p)
        near = np.abs(res) <= outlier_m
        r = res[near]
        sigma = float(MAD_TO_SIGMA * np.median(np.abs(r - np.median(r)))) if r.size else float("nan")
        gate = float(np.clip(gate_sigmas * sigma, min_gate_m, outlier_m)) if np.isfinite(sigma) else outlier_m
        new_inl = np.abs(res) <= gate
        if np.array_equal(new_inl, inl):
            break
        inl = new_inl
    res = plane.signed_distance(p)
    inl = np.abs(res) <= gate
    return RobustPlaneFit(plane, inl, res, gate, sigma)


def wall_plane(distance_m: float, normal: ArrayLike, origin: ArrayLike | None = None) -> Plane:
    """The wall plane ``n . (p - origin) = distance_m`` with ``n`` the unit wall normal.

    The wall's point nearest to ``origin`` (the body origin by default) lies at ``distance_m`` along ``n``.
    """
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=float).reshape(3)
    n = np.asarray(normal, dtype=float).reshape(3)
    norm = float(np.linalg.norm(n))
    if not (norm > 1e-12 and np.isfinite(norm)):
        msg = f"wall normal must be a non-zero finite vector, got {n.tolist()}"
        raise GeometryError(msg)
    n = n / norm
    return Plane(n, float(distance_m + n @ o))
