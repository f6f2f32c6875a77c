"""Unit tests of the calibration plane math (synthetic points, seeded)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrsensor.calib.planefit import (
    Plane,
    fit_plane_lsq,
    fit_plane_through_point,
    normal_angle_deg,
    principal_spreads,
    ransac_plane,
    robust_plane_fit,
    wall_plane,
)
from lrsensor.errors import CalibrationFitError


def _laser_plane(tilt_deg: float) -> Plane:
    t = np.radians(tilt_deg)
    return Plane.from_point_normal([0.0, 0.0, -0.05], [-np.sin(t), 0.0, np.cos(t)])


def _stripe_points(plane: Plane, distances: list[float], n: int, noise_m: float, rng: np.random.Generator):
    """Points where the laser plane meets walls x = d, spread along y, with noise along z."""
    out, grp = [], []
    for gi, d in enumerate(distances):
        y = rng.uniform(-0.6 * d, 0.6 * d, n)
        x = np.full(n, d)
        # solve n . p = offset for z
        z = (plane.offset - plane.normal[0] * x - plane.normal[1] * y) / plane.normal[2]
        out.append(np.stack([x, y, z + rng.normal(0, noise_m, n)], axis=1))
        grp.append(np.full(n, gi))
    return np.concatenate(out), np.concatenate(grp)


def test_lsq_recovers_exact_plane() -> None:
    rng = np.random.default_rng(1)
    truth = _laser_plane(1.5)
    pts, _ = _stripe_points(truth, [0.4, 0.5, 0.6], 200, 0.0, rng)
    fit = fit_plane_lsq(pts).oriented_like(truth.normal)
    assert normal_angle_deg(fit.normal, truth.normal) < 1e-9
    assert abs(fit.offset - truth.offset) < 1e-12


def test_angle_is_precise_for_tiny_angles() -> None:
    a = np.array([0.0, 0.0, 1.0])
    b = np.array([np.sin(1e-7), 0.0, np.cos(1e-7)])
    assert normal_angle_deg(a, b) == pytest.approx(np.degrees(1e-7), rel=1e-6)
    assert normal_angle_deg(a, -b) == pytest.approx(np.degrees(1e-7), rel=1e-6)


def test_ransac_then_refit_rejects_outliers() -> None:
    rng = np.random.default_rng(2)
    truth = _laser_plane(-2.0)
    pts, grp = _stripe_points(truth, [0.4, 0.5, 0.6], 500, 0.0002, rng)
    n_out = 300  # 17 % gross outliers (blobs, reflections)
    idx = rng.choice(pts.shape[0], n_out, replace=False)
    pts[idx, 2] += rng.uniform(0.02, 0.1, n_out) * rng.choice([-1, 1], n_out)
    fit = robust_plane_fit(pts, np.random.default_rng(0), groups=grp)
    assert normal_angle_deg(fit.plane.normal, truth.normal) < 0.02
    assert not fit.inliers[idx].any()
    assert fit.inliers.sum() > 0.95 * (pts.shape[0] - n_out)
    assert fit.rms_m == pytest.approx(0.0002, rel=0.2)
    # plain least squares is ruined by the same outliers
    assert normal_angle_deg(fit_plane_lsq(pts).normal, truth.normal) > 0.1


def test_robust_fit_is_deterministic_for_a_seed() -> None:
    rng = np.random.default_rng(3)
    pts, grp = _stripe_points(_laser_plane(1.0), [0.4, 0.6], 300, 0.0005, rng)
    a = robust_plane_fit(pts, np.random.default_rng(7), groups=grp)
    b = robust_plane_fit(pts, np.random.default_rng(7), groups=grp)
    assert np.array_equal(a.plane.normal, b.plane.normal)
    assert np.array_equal(a.inliers, b.inliers)


def test_one_wall_is_a_line_and_the_anchor_fixes_the_plane() -> None:
    rng = np.random.default_rng(4)
    truth = _laser_plane(2.0)
    pts, _ = _stripe_points(truth, [0.5], 400, 0.0001, rng)
    spreads = principal_spreads(pts)
    assert spreads[0] > 0.1
    assert spreads[1] < 0.001
    mount = np.array([0.0, 0.0, -0.05])  # on the true plane
    fit = fit_plane_through_point(pts, mount).oriented_like(truth.normal)
    assert normal_angle_deg(fit.normal, truth.normal) < 0.02
    assert abs(fit.signed_distance(mount)[0]) < 1e-12
    rob = robust_plane_fit(pts, np.random.default_rng(0), anchor=mount)
    assert normal_angle_deg(rob.plane.normal, truth.normal) < 0.02


def test_ransac_needs_enough_points() -> None:
    with pytest.raises(CalibrationFitError, match="at least 3"):
        ransac_plane(np.zeros((2, 3)), 0.001, np.random.default_rng(0))
    with pytest.raises(CalibrationFitError, match="collinear"):
        ransac_plane(np.zeros((50, 3)), 0.001, np.random.default_rng(0))


def test_wall_plane_definition() -> None:
    w = wall_plane(0.5, [2.0, 0.0, 0.0])
    assert np.allclose(w.normal, [1, 0, 0])
    assert w.offset == pytest.approx(0.5)
    # measured from another origin: the wall's nearest point to it is 0.5 m away along the normal
    w2 = wall_plane(0.5, [1.0, 0.0, 0.0], origin=[0.1, 0.0, 0.0])
    assert w2.offset == pytest.approx(0.6)
    tilted = wall_plane(0.5, [1.0, 1.0, 0.0])
    foot = tilted.project([0.0, 0.0, 0.0])
    assert np.linalg.norm(foot) == pytest.approx(0.5)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(
    normal=st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.2),
    offset=st.floats(-0.2, 0.2),
    seed=st.integers(0, 2**16),
)
def test_robust_fit_any_orientation(normal: tuple[float, float, float], offset: float, seed: int) -> None:
    """Any plane, sampled as three parallel lines (three wall positions) with noise and 10 % outliers."""
    rng = np.random.default_rng(seed)
    truth = Plane.from_point_normal(np.zeros(3), normal)
    truth = Plane(truth.normal, offset)
    # a line direction inside the plane, and a step direction inside the plane across it
    a = np.cross(truth.normal, [1.0, 0.0, 0.0] if abs(truth.normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(truth.normal, a)
    base = truth.normal * offset
    pts, grp = [], []
    for gi, step in enumerate((-0.1, 0.0, 0.1)):
        t = rng.uniform(-0.5, 0.5, 300)
        p = base + step * b + t[:, None] * a + rng.normal(0, 0.0002, (300, 1)) * truth.normal
        pts.append(p)
        grp.append(np.full(300, gi))
    p_all, g_all = np.concatenate(pts), np.concatenate(grp)
    idx = rng.choice(p_all.shape[0], 90, replace=False)
    p_all[idx] += rng.uniform(0.02, 0.2, (90, 1)) * truth.normal
    fit = robust_plane_fit(p_all, np.random.default_rng(seed), groups=g_all)
    assert normal_angle_deg(fit.plane.normal, truth.normal) < 0.02
    assert abs(fit.plane.oriented_like(truth.normal).offset - offset) < 1e-4
