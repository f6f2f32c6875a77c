"""Pinhole camera with Brown-Conrady distortion against OpenCV."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lrsensor.camera import Camera
from lrsensor.errors import GeometryError

DIST = (-0.28, 0.09, 0.0012, -0.0008, -0.012)


def _points(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.3, 5.0, n)
    x = rng.uniform(-0.8, 0.8, n) * z
    y = rng.uniform(-0.45, 0.45, n) * z
    return np.stack([x, y, z], axis=1)


def test_paper_camera_focal_length() -> None:
    cam = Camera.paper()
    assert cam.fx == pytest.approx(554.28, abs=0.01)
    assert (cam.cx, cam.cy) == (959.5, 539.5)


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0, 0.0), DIST])
def test_project_matches_cv2(dist: tuple[float, float, float, float, float]) -> None:
    cam = Camera(1920, 1080, 554.28, 556.0, 955.0, 541.0, dist)
    pts = _points()
    ours = cam.project(pts)
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-6)


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0, 0.0), DIST])
def test_unproject_inverts_project(dist: tuple[float, float, float, float, float]) -> None:
    cam = Camera(1920, 1080, 554.28, 556.0, 955.0, 541.0, dist)
    pts = _points()
    rays = cam.unproject(cam.project(pts))
    np.testing.assert_allclose(rays * pts[:, 2:3], pts, atol=1e-9)


def test_behind_camera_is_nan() -> None:
    cam = Camera.paper()
    uv = cam.project([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    assert np.all(np.isnan(uv[0]))
    np.testing.assert_allclose(uv[1], [cam.cx, cam.cy])


def test_principal_point_unprojects_to_axis() -> None:
    cam = Camera(640, 480, 500.0, 500.0, 320.0, 240.0, DIST)
    np.testing.assert_allclose(cam.unproject([[320.0, 240.0]]), [[0.0, 0.0, 1.0]], atol=1e-12)


def test_invalid_camera() -> None:
    with pytest.raises(GeometryError, match="focal"):
        Camera(640, 480, 0.0, 500.0, 320.0, 240.0)
    with pytest.raises(GeometryError, match="size"):
        Camera(0, 480, 500.0, 500.0, 320.0, 240.0)


def test_in_image() -> None:
    cam = Camera(640, 480, 500.0, 500.0, 320.0, 240.0)
    assert cam.in_image([[0, 0], [639, 479], [-1, 5], [5, 480]]).tolist() == [True, True, False, False]
