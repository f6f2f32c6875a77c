"""Plane extraction that knows the sensor's range noise (``MapConfig.range_noise_per_m``, off by default)."""

from __future__ import annotations

import numpy as np

from mapping import MapConfig
from mapping.planes import cell_normals


def _far_wall(range_m: float, sigma_m: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two horizontal stripes 0.1 m apart on a wall ``range_m`` ahead (north), seen from the origin, each point
    moved along its ray by normal noise of ``sigma_m``: (N, 3) points and (N, 3) vehicle positions, NED m."""
    rng = np.random.default_rng(seed)
    east = np.linspace(-1.0, 1.0, 400)
    pts = np.concatenate(
        [np.stack([np.full_like(east, range_m), east, np.full_like(east, z)], 1) for z in (-0.05, 0.05)]
    )
    ray = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    pts = pts + ray * sigma_m * rng.standard_normal((pts.shape[0], 1))
    return pts, np.zeros_like(pts)


def test_far_noisy_stripes_get_cell_normals_only_when_their_noise_is_expected() -> None:
    pts, veh = _far_wall(4.0, 0.025)
    off = cell_normals(pts, veh, MapConfig())
    on = cell_normals(pts, veh, MapConfig(range_noise_per_m=0.002))
    assert np.mean(off.valid) < 0.3  # the noise makes the cells thicker than cell_planarity allows
    assert np.mean(on.valid) > 0.7
    normals = on.normal[on.valid]
    assert np.median(np.abs(normals[:, 0])) > 0.9  # they face the vehicle (north)


def test_expected_noise_changes_nothing_for_clean_near_stripes() -> None:
    pts, veh = _far_wall(1.0, 0.0005)
    off = cell_normals(pts, veh, MapConfig())
    on = cell_normals(pts, veh, MapConfig(range_noise_per_m=0.002))
    assert np.array_equal(off.valid, on.valid)
