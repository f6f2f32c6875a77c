"""Plane extraction that knows the sensor's range noise: each cloud's k from its robot's calibration
(``mapping.range_noise``), or ``MapConfig.range_noise_per_m`` as an override."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lrsensor.calibration import Calibration, LaserPlane
from lrsensor.frames import Pose
from lrsensor.port import triangulate_through_port
from lrsensor.range_theory import range_error_per_px
from lrsensor.sim import named_scene
from lrsensor.sim.scenes import acrylic_port
from lrsensor.triangulation import triangulate_plane
from mapping import MapBuilder, MapConfig
from mapping import builder_window as window_module
from mapping.errors import MapInputError
from mapping.planes import cell_normals
from mapping.range_noise import STRIPE_SIGMA_PX, cloud_noise_per_m, window_noise


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


# ---------------------------------------------------------------------- each robot's k from its calibration
CAL = Calibration.paper(0.1, 640, 360)  # the simulated dives' 640x360 camera: fy 184.76 px, lasers 5 cm off


def _slope(cal: Calibration, row: float, laser: int, triangulate: Any) -> tuple[float, float]:
    """Range change per pixel of row change per squared metre at the centre column's pixel ``row``, and the
    range there (m): the triangulation's own slope."""
    uv = np.array([[cal.camera.cx, row], [cal.camera.cx, row + 0.01]])
    r = np.linalg.norm(triangulate(cal, uv, cal.lasers[laser]), axis=1)
    return float(abs(r[1] - r[0]) / (r[0] ** 2 * 0.01)), float(r[0])


def test_k_of_a_calibration_is_sigma_over_focal_length_times_laser_offset() -> None:
    per_px = range_error_per_px(CAL)
    assert per_px == pytest.approx(1.0 / (184.76 * 0.05), rel=1e-12)
    on = MapConfig(stripe_sigma_px=STRIPE_SIGMA_PX)
    assert cloud_noise_per_m(on, per_px) == pytest.approx(0.0185 / (184.76 * 0.05), rel=1e-12)  # 0.0020
    assert cloud_noise_per_m(MapConfig(stripe_sigma_px=0.0), per_px) == 0.0  # off
    slope, r = _slope(CAL, CAL.camera.cy - 184.76 * 0.05 / 2.0, 0, triangulate_plane)  # a wall 2 m ahead
    assert r == pytest.approx(2.0, abs=0.01)
    assert slope == pytest.approx(per_px, rel=0.01)


def test_the_nearest_laser_and_a_flat_port_set_k() -> None:
    near = CAL.with_lasers([CAL.lasers[0], LaserPlane.make("bottom", (0.0, 0.0, 0.025), (0.0, 0.0, 1.0))])
    assert range_error_per_px(near) == pytest.approx(2.0 * range_error_per_px(CAL), rel=1e-12)
    setup = named_scene("wall_1.0").with_port(acrylic_port(2.0))
    cal = setup.calibration
    assert cal.port is not None
    per_px = range_error_per_px(cal)
    assert per_px == pytest.approx(cal.port.n_air / (cal.port.n_water * cal.camera.fy * 0.05), rel=1e-3)
    slope, r = _slope(cal, cal.camera.cy + 15.0, 1, triangulate_through_port)  # the refracted rays' own slope
    assert 1.0 < r < 5.0
    assert slope == pytest.approx(per_px, rel=0.03)


def test_the_override_wins_and_a_bad_factor_is_refused() -> None:
    assert cloud_noise_per_m(MapConfig(range_noise_per_m=0.003), 0.108) == 0.003
    assert cloud_noise_per_m(MapConfig(stripe_sigma_px=0.0), 0.108) == 0.0
    assert cloud_noise_per_m(MapConfig(stripe_sigma_px=STRIPE_SIGMA_PX), 0.0) == 0.0  # no calibration known
    with pytest.raises(MapInputError):
        cloud_noise_per_m(MapConfig(stripe_sigma_px=STRIPE_SIGMA_PX), float("nan"))


def test_per_point_noise_reads_each_points_own_k() -> None:
    pts, veh = _far_wall(4.0, 0.025)
    off = cell_normals(pts, veh, MapConfig())
    zeros = cell_normals(pts, veh, MapConfig(), np.zeros(pts.shape[0]))
    assert np.array_equal(off.valid, zeros.valid)  # points without a calibration: the fixed test
    on = cell_normals(pts, veh, MapConfig(range_noise_per_m=0.002))
    each = cell_normals(pts, veh, MapConfig(), np.full(pts.shape[0], 0.002))
    assert np.array_equal(on.valid, each.valid)
    assert np.allclose(on.normal[on.valid], each.normal[each.valid])
    # the same wall, half of its points from a robot without a calibration: its cells between the two
    half = cell_normals(pts, veh, MapConfig(), np.where(np.arange(pts.shape[0]) % 2 == 0, 0.004, 0.0))
    assert np.mean(off.valid) < np.mean(half.valid)


def test_window_noise_is_one_number_for_one_calibration_and_per_point_otherwise() -> None:
    lens = np.array([3, 2], dtype=np.int64)
    assert window_noise([0.002, 0.002], lens) == 0.002
    assert window_noise([], np.zeros(0, dtype=np.int64)) == 0.0
    assert np.array_equal(np.asarray(window_noise([0.002, 0.0], lens)), [0.002] * 3 + [0.0] * 2)


def _wall_clouds(n: int, t0_ns: int = 0) -> list[tuple[int, np.ndarray, Pose]]:
    """``n`` clouds of a wall 3 m north of a vehicle moving east, two stripes each (NED points, pose)."""
    out = []
    for i in range(n):
        pose = Pose(0.0, 0.05 * i, 2.0, 0.0, 0.0, 0.0)
        east = np.linspace(-1.0, 1.0, 300) + pose.east_m
        pts = np.concatenate(
            [np.stack([np.full_like(east, 3.0), east, np.full_like(east, z)], 1) for z in (1.95, 2.05)]
        )
        out.append((t0_ns + i * 100_000_000, pts, pose))
    return out


@pytest.fixture
def extractions(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    """The range noise each extraction of :class:`mapping.MapBuilder` is given, in order."""
    seen: list[Any] = []
    real = window_module.extract_planes

    def spy(points: np.ndarray, vehicle: np.ndarray, cfg: MapConfig, seed: int, noise: Any = None) -> Any:
        seen.append(noise)
        return real(points, vehicle, cfg, seed, noise)

    monkeypatch.setattr(window_module, "extract_planes", spy)
    return seen


def test_a_cloud_with_a_calibration_gets_its_k_in_the_extraction(extractions: list[Any]) -> None:
    b = MapBuilder(MapConfig(extract_every_clouds=4, window_clouds=8, stripe_sigma_px=STRIPE_SIGMA_PX))
    k = STRIPE_SIGMA_PX * range_error_per_px(CAL)
    b.set_range_error("calibrated", range_error_per_px(CAL))
    assert b.range_noise("calibrated") == pytest.approx(k)
    assert b.range_noise("traced") == 0.0  # never told: the fixed thresholds
    for t, pts, pose in _wall_clouds(4):
        b.add_cloud("calibrated", t, pts, pose)
        b.add_cloud("traced", t, pts, pose)
    assert extractions == [pytest.approx(k), 0.0]
    b.set_range_error("calibrated", 0.0)  # its clouds now come without a calibration (schema 1)
    for t, pts, pose in _wall_clouds(4, 10**9):
        b.add_cloud("calibrated", t, pts, pose)
    mixed = np.asarray(extractions[-1])  # a window of both: each point its own cloud's k
    assert mixed.ndim == 1
    assert mixed.max() == pytest.approx(k)
    assert mixed.min() == 0.0
    assert b.flush() == []  # nothing pending
    override = MapBuilder(MapConfig(extract_every_clouds=4, range_noise_per_m=0.003))
    for t, pts, pose in _wall_clouds(4):
        override.add_cloud("traced", t, pts, pose)
    assert extractions[-1] == 0.003  # the explicit override: every cloud's k


def test_the_windows_k_survives_a_save(tmp_path: Path, extractions: list[Any]) -> None:
    cfg = MapConfig(extract_every_clouds=5, window_clouds=5, extract_every_s=0.0, stripe_sigma_px=STRIPE_SIGMA_PX)
    b = MapBuilder(cfg, tmp_path)
    b.set_range_error("rov1", range_error_per_px(CAL))
    for t, pts, pose in _wall_clouds(3):
        b.add_cloud("rov1", t, pts, pose)
    b.save()
    again = MapBuilder(None, tmp_path)  # told nothing of rov1's calibration: its next clouds get k 0
    for t, pts, pose in _wall_clouds(2, 10**9):
        again.add_cloud("rov1", t, pts, pose)
    k = np.asarray(extractions[-1])
    assert k.ndim == 1
    assert np.count_nonzero(k[: 3 * k.size // 5]) == 3 * k.size // 5  # the 3 saved clouds (of 5 alike) kept their k
    assert np.count_nonzero(k[3 * k.size // 5 :]) == 0


def test_a_calibrated_cloud_has_range_noise_by_default() -> None:
    # the simulated dives' 640x360 camera: f 184.76 px, lasers 5 cm from the camera centre: k 0.002 per metre
    assert cloud_noise_per_m(MapConfig(), 1.0 / (184.76 * 0.05)) == pytest.approx(0.002, rel=0.01)
    assert cloud_noise_per_m(MapConfig(), 0.0) == 0.0  # a cloud without a calibration keeps the fixed thresholds
