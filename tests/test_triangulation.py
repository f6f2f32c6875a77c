"""Triangulation: eq. (24), eq. (29), round trips through the camera."""

from __future__ import annotations

import numpy as np
import pytest

from lrsensor.calibration import Calibration, LaserPlane
from lrsensor.camera import Camera
from lrsensor.frames import R_ned_from_body
from lrsensor.triangulation import intersect_rays_plane, triangulate, triangulate_right_angled


def test_eq24_hand_value() -> None:
    # wall 1 m ahead, top laser c = 0.05 above: the stripe is f*c/x = 27.714 px above the centre row
    cam = Camera.paper()
    v = cam.cy - cam.fy * 0.05 / 1.0
    u = cam.cx + cam.fx * 0.2 / 1.0  # 0.2 m to starboard
    p = triangulate_right_angled([[u, v]], cam, -0.05)
    np.testing.assert_allclose(p, [[1.0, 0.2, -0.05]], atol=1e-12)


def test_eq24_wrong_side_is_nan() -> None:
    cam = Camera.paper()
    p = triangulate_right_angled([[cam.cx, cam.cy + 10], [cam.cx, cam.cy]], cam, -0.05)
    assert np.isnan(p).all()


def test_eq24_equals_eq29_for_parallel_lasers() -> None:
    cal = Calibration.paper(0.1)
    rng = np.random.default_rng(3)
    u = rng.uniform(0, 1919, 400)
    v_top = rng.uniform(0, cal.camera.cy - 1, 200)
    v_bot = rng.uniform(cal.camera.cy + 1, 1079, 200)
    uv = np.stack([u, np.concatenate([v_top, v_bot])], axis=1)
    laser = np.r_[np.zeros(200, int), np.ones(200, int)]
    general = triangulate(cal, uv, laser)
    right = np.concatenate(
        [
            triangulate_right_angled(uv[:200], cal.camera, -0.05),
            triangulate_right_angled(uv[200:], cal.camera, 0.05),
        ]
    )
    np.testing.assert_allclose(general, right, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("distorted", [False, True])
def test_project_then_triangulate_gives_point_back(distorted: bool) -> None:
    cam = Camera(1920, 1080, 554.28, 554.28, 959.5, 539.5, (-0.2, 0.05, 0.001, -0.001, 0.0) if distorted else (0,) * 5)  # type: ignore[arg-type]
    R = R_ned_from_body(0.01, -0.02, 0.015) @ np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]).T
    R_cam_from_body = R.T
    cal = Calibration(
        camera=cam,
        lasers=(
            LaserPlane.make("top", (0.02, 0.01, -0.06), (0.03, -0.02, 1.0)),
            LaserPlane.make("bottom", (0.0, -0.01, 0.05), (-0.025, 0.01, 1.0)),
        ),
        R_cam_from_body=tuple(tuple(r) for r in R_cam_from_body),  # type: ignore[arg-type]
        t_cam_from_body=(0.01, -0.02, 0.005),
    )
    rng = np.random.default_rng(4)
    pts = []
    for laser in cal.lasers:
        # points on the laser plane in front of the camera: x in 0.3..3, y spread
        x = rng.uniform(0.3, 3.0, 100)
        y = rng.uniform(-0.8, 0.8, 100) * x
        n, p0 = laser.normal_body, laser.point_body
        z = p0[2] - (n[0] * (x - p0[0]) + n[1] * (y - p0[1])) / n[2]
        pts.append(np.stack([x, y, z], axis=1))
    points = np.concatenate(pts)
    idx = np.r_[np.zeros(100, int), np.ones(100, int)]
    uv = cal.project_body(points)
    np.testing.assert_allclose(triangulate(cal, uv, idx), points, atol=1e-9)


def test_parallel_and_behind_rays_are_nan() -> None:
    pts, d = intersect_rays_plane([0, 0, 0], [[1.0, 0, 0], [0, 0, 1.0], [0, 0, -1.0]], [0, 0, 1.0], [0, 0, 1.0])
    assert np.isnan(pts[0]).all()
    assert np.isnan(d[0])
    np.testing.assert_allclose(pts[1], [0, 0, 1.0])
    assert np.isnan(pts[2]).all()


def test_triangulate_bad_index() -> None:
    from lrsensor.errors import GeometryError

    with pytest.raises(GeometryError, match="laser_index"):
        triangulate(Calibration.paper(), [[1.0, 2.0]], [5])


@pytest.mark.parametrize("distorted", [False, True])
def test_compiled_triangulation_matches_numpy(distorted: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    from lrsensor.extract import compile
    from lrsensor.extract.compile import HAVE_NUMBA, warm_up

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    warm_up()
    cal = Calibration.paper(0.1)
    if distorted:
        cam = Camera(1920, 1080, 554.3, 556.0, 950.0, 545.0, (-0.12, 0.03, 0.001, -0.0008, 0.0))
        tilted = LaserPlane("top", (0.0, 0.0, -0.05), (0.02, 0.03, 1.0))
        cal = Calibration(camera=cam, lasers=(tilted, cal.lasers[1]))
    rng = np.random.default_rng(7)
    uv = rng.uniform([0.0, 0.0], [1919.0, 1079.0], (5000, 2))
    laser = rng.integers(0, 2, 5000)
    fast = triangulate(cal, uv, laser)
    monkeypatch.setattr(compile, "ready", lambda: False)
    slow = triangulate(cal, uv, laser)
    assert np.array_equal(np.isnan(fast), np.isnan(slow))
    assert np.isnan(fast).any(axis=1).sum() > 100  # rows on the wrong side of the camera are NaN in both
    assert np.nanmax(np.abs(fast - slow)) < 1e-9
