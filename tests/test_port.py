"""The flat port: exact refraction checked against scalar Snell's law, Fermat's principle and round trips.

The independent references here are written from the physics, not from ``lrsensor.port``: a ray traced with
angles (``math.asin``) one surface at a time, and the optical path length minimised numerically (golden-section
search, pure Python) and checked for stationarity in all four degrees of freedom of the two crossing points.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from lrsensor.calibration import Calibration, LaserPlane
from lrsensor.camera import Camera
from lrsensor.errors import CalibrationFileError, GeometryError
from lrsensor.frames import R_ned_from_body
from lrsensor.port import (
    FlatPort,
    blind_mask,
    blind_pixels,
    central_view,
    pixel_rays_in_water,
    project_pixels_through_port,
    project_through_port,
    rays_in_water,
    triangulate_through_port,
)
from lrsensor.triangulation import triangulate_plane

CAMERA = Camera(1920, 1080, 554.28, 554.28, 959.5, 539.5)
CAMERA_DISTORTED = Camera(1920, 1080, 560.0, 557.0, 955.0, 542.0, (-0.05, 0.004, 0.0007, -0.0004, 0.0))  # monotonic


def _tilted_normal(tilt_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    t, a = math.radians(tilt_deg), math.radians(azimuth_deg)
    return (math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t))


def _random_port(rng: np.random.Generator) -> FlatPort:
    """A port from the issue's range: distance 5-50 mm, thickness 3-15 mm, glass 1.47-1.53, water 1.33-1.35,
    normal tilted up to 3 deg."""
    return FlatPort(
        normal_cam=_tilted_normal(rng.uniform(0.0, 3.0), rng.uniform(0.0, 360.0)),
        distance_m=rng.uniform(0.005, 0.05),
        thickness_m=rng.uniform(0.003, 0.015),
        n_air=1.0,
        n_glass=rng.uniform(1.47, 1.53),
        n_water=rng.uniform(1.33, 1.35),
    )


PORTS = [
    FlatPort((0.0, 0.0, 1.0), 0.02, 0.008, 1.0, 1.49, 1.34),
    FlatPort(_tilted_normal(3.0, 30.0), 0.005, 0.015, 1.0, 1.53, 1.33),
    FlatPort(_tilted_normal(2.0, 200.0), 0.05, 0.003, 1.0, 1.47, 1.35),
    FlatPort(_tilted_normal(12.0, 95.0), 0.03, 0.0, 1.0, 1.5, 1.34),  # no glass, larger tilt
]


# ----------------------------------------------------------------------------------------- scalar references
def _dot(a: Any, b: Any) -> float:
    return float(sum(x * y for x, y in zip(a, b, strict=True)))


def _trace_by_angles(port: FlatPort, ray: tuple[float, float, float]) -> tuple[list[float], list[float]] | None:
    """Trace one unit ray by hand: angles with the normal, ``math.asin`` at each surface; None if it is lost."""
    n = port.normal_cam
    cos_a = _dot(ray, n)
    if cos_a <= 0:
        return None
    a = math.acos(min(1.0, cos_a))
    tang = [r - cos_a * ni for r, ni in zip(ray, n, strict=True)]
    tn = math.sqrt(_dot(tang, tang))
    e = [x / tn for x in tang] if tn > 0 else [0.0, 0.0, 0.0]
    sin_g = port.n_air * math.sin(a) / port.n_glass
    if sin_g > 1:
        return None
    g = math.asin(sin_g)
    sin_w = port.n_glass * math.sin(g) / port.n_water
    if sin_w > 1:
        return None
    w = math.asin(sin_w)
    # axial distance d in air, t in glass; radial distance d tan(a) + t tan(g)
    axial = port.distance_m + port.thickness_m
    radial = port.distance_m * math.tan(a) + port.thickness_m * math.tan(g)
    exit_point = [axial * ni + radial * ei for ni, ei in zip(n, e, strict=True)]
    direction = [math.cos(w) * ni + math.sin(w) * ei for ni, ei in zip(n, e, strict=True)]
    return exit_point, direction


def _golden_min(f: Callable[[float], float], a: float, b: float, iterations: int = 90) -> float:
    """Minimiser of a unimodal f on [a, b] by golden-section search (pure Python)."""
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    for _ in range(iterations):
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return 0.5 * (a + b)


def _least_optical_path_in_plane(port: FlatPort, z: float, rho: float) -> tuple[float, float, float]:
    """Minimise the optical path to a point at axial distance z and radial distance rho (metres) over the radial
    crossing distances x1 (inner surface) and x2 (outer surface), nested golden sections; (x1, x2, length)."""
    d, t = port.distance_m, port.thickness_m

    def path(x1: float, x2: float) -> float:
        return (
            port.n_air * math.hypot(d, x1)
            + port.n_glass * math.hypot(t, x2 - x1)
            + port.n_water * math.hypot(z - d - t, rho - x2)
        )

    def best_x2(x1: float) -> float:
        return _golden_min(lambda x2: path(x1, x2), x1, rho)

    x1 = _golden_min(lambda x1: path(x1, best_x2(x1)), 0.0, rho)
    x2 = best_x2(x1)
    return x1, x2, path(x1, x2)


def _optical_path(port: FlatPort, point: Any, q1: Any, q2: Any) -> float:
    """Optical path length camera centre -> q1 (inner surface) -> q2 (outer surface) -> point, metres."""
    d1 = math.dist((0.0, 0.0, 0.0), q1)
    d2 = math.dist(q1, q2)
    d3 = math.dist(q2, point)
    return port.n_air * d1 + port.n_glass * d2 + port.n_water * d3


# ----------------------------------------------------------------------------------------- the dataclass
def test_normal_is_normalised_and_fields_are_floats() -> None:
    port = FlatPort((0.0, 0.1, 2.0), 0.02, 0, 1, 1.5, 1.34)
    assert np.linalg.norm(port.normal) == pytest.approx(1.0, abs=1e-15)
    assert isinstance(port.thickness_m, float)
    assert port.outer_distance_m == pytest.approx(0.02)
    d = port.to_dict()
    assert d.pop("type") == "flat"
    assert FlatPort(**{**d, "normal_cam": tuple(d["normal_cam"])}) == port  # normalising is idempotent


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"thickness_m": -0.001}, "port.thickness_m"),
        ({"distance_m": 0.0}, "port.distance_m"),
        ({"distance_m": -0.01}, "port.distance_m"),
        ({"n_glass": 0.9}, "port.n_glass"),
        ({"n_air": math.nan}, "port.n_air"),
        ({"n_water": math.inf}, "port.n_water"),
        ({"normal_cam": (0.0, 0.0, -1.0)}, "port.normal_cam"),
        ({"normal_cam": (1.0, 0.0, 0.0)}, "port.normal_cam"),
        ({"normal_cam": _tilted_normal(31.0, 10.0)}, "port.normal_cam"),
        ({"normal_cam": (0.0, 0.0, 0.0)}, "port.normal_cam"),
    ],
)
def test_construction_refuses_bad_values_naming_the_key(kwargs: dict[str, Any], key: str) -> None:
    args: dict[str, Any] = {"normal_cam": (0.0, 0.0, 1.0), "distance_m": 0.02, "thickness_m": 0.008, **kwargs}
    with pytest.raises(GeometryError, match=key):
        FlatPort(**args)


# ----------------------------------------------------------------------------------------- back-projection
@pytest.mark.parametrize("port", PORTS)
def test_back_projection_matches_a_ray_traced_by_angles(port: FlatPort) -> None:
    rng = np.random.default_rng(11)
    rays = rng.normal(size=(200, 3)) * [0.6, 0.6, 0.0] + [0.0, 0.0, 1.0]
    rays /= np.linalg.norm(rays, axis=1)[:, None]
    rays[0] = port.normal  # along the normal: no bending at all
    origins, dirs = rays_in_water(port, rays)
    for i, ray in enumerate(rays):
        ref = _trace_by_angles(port, (float(ray[0]), float(ray[1]), float(ray[2])))
        assert ref is not None
        np.testing.assert_allclose(origins[i], ref[0], atol=1e-13)
        np.testing.assert_allclose(dirs[i], ref[1], atol=1e-13)
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-14)
    # the exit points lie on the outer surface; water rays keep n_air sin(a_air) = n_water sin(a_water)
    np.testing.assert_allclose(origins @ port.normal, port.outer_distance_m, atol=1e-15)
    sin_air = np.linalg.norm(np.cross(rays, port.normal), axis=1)
    sin_water = np.linalg.norm(np.cross(dirs, port.normal), axis=1)
    np.testing.assert_allclose(port.n_air * sin_air, port.n_water * sin_water, atol=1e-14)


def test_without_glass_the_ray_bends_once_at_distance_m() -> None:
    port = FlatPort((0.0, 0.0, 1.0), 0.02, 0.0, 1.0, 1.49, 1.34)
    a = math.radians(40.0)
    origins, dirs = rays_in_water(port, np.array([[math.sin(a), 0.0, math.cos(a)]]))
    np.testing.assert_allclose(origins[0], [0.02 * math.tan(a), 0.0, 0.02], atol=1e-15)
    w = math.asin(math.sin(a) / 1.34)
    np.testing.assert_allclose(dirs[0], [math.sin(w), 0.0, math.cos(w)], atol=1e-15)


def test_rays_that_cannot_reach_the_water_are_nan_rows() -> None:
    port = PORTS[1]
    rays = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [math.nan, 0.0, 1.0]])
    rays[2] -= port.normal * (rays[2] @ port.normal)  # exactly parallel to the port
    origins, dirs = rays_in_water(port, rays)
    assert np.isfinite(origins[0]).all()
    assert np.isfinite(dirs[0]).all()
    assert np.isnan(origins[1:]).all()
    assert np.isnan(dirs[1:]).all()
    with pytest.raises(GeometryError, match="shape"):
        rays_in_water(port, np.zeros((3, 2)))


def test_total_internal_reflection_gives_nan_beyond_the_critical_angle() -> None:
    # A water-filled housing looking out into air: rays steeper than asin(1 / 1.33) cannot leave the glass.
    port = FlatPort((0.0, 0.0, 1.0), 0.02, 0.006, n_air=1.33, n_glass=1.5, n_water=1.0)
    critical = math.asin(1.0 / 1.33)
    angles = np.array([0.0, 0.3, critical - 1e-6, critical + 1e-6, 1.2])
    rays = np.stack([np.sin(angles), np.zeros_like(angles), np.cos(angles)], axis=1)
    origins, dirs = rays_in_water(port, rays)
    assert np.isfinite(dirs[:3]).all()
    assert np.isnan(dirs[3:]).all()
    assert np.isnan(origins[3:]).all()
    # the image's blind pixels are exactly those whose ray is beyond the critical angle
    cam = Camera(64, 48, 30.0, 30.0, 31.5, 23.5)
    mask = blind_mask(cam, port)
    vv, uu = np.mgrid[0:48, 0:64]
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    ray = cam.unproject(uv)
    angle = np.arccos(ray[:, 2] / np.linalg.norm(ray, axis=1))
    np.testing.assert_array_equal(mask.ravel(), angle > critical)
    assert 0 < mask.sum() < mask.size
    np.testing.assert_array_equal(blind_pixels(cam, port, uv), mask.ravel())
    # an underwater port sees through every pixel of the paper's camera
    assert not blind_mask(Camera(96, 54, 27.7, 27.7, 47.5, 26.5), PORTS[1]).any()


# ----------------------------------------------------------------------------------------- forward projection
@pytest.mark.parametrize("port", PORTS[:3])
def test_forward_projection_obeys_fermat(port: FlatPort) -> None:
    """The path through the forward projection's crossing points minimises the optical path length."""
    rng = np.random.default_rng(5)
    dirs = rng.normal(size=(6, 3)) * [0.5, 0.4, 0.0] + [0.0, 0.0, 1.0]
    points = dirs / np.linalg.norm(dirs, axis=1)[:, None] * rng.uniform(0.3, 3.0, size=(6, 1))
    rays = project_through_port(port, points)
    n = port.normal
    for point, ray in zip(points, rays, strict=True):
        q1 = ray * port.distance_m / (ray @ n)
        origins, _ = rays_in_water(port, ray[None, :])
        q2 = origins[0]
        opl = _optical_path(port, point, q1, q2)
        # (1) stationary and minimal in all four degrees of freedom (two tangent directions per surface)
        t1 = np.cross(n, [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        h = 1e-6  # metres: truncation ~h^2 n / d^2 and rounding ~1e-16 / h both far below the bound
        for k in range(4):
            step = (t1 if k % 2 == 0 else t2) * h
            moved = [(q1 + step, q2), (q1, q2 + step)][k // 2]
            back = [(q1 - step, q2), (q1, q2 - step)][k // 2]
            plus = _optical_path(port, point, *moved)
            minus = _optical_path(port, point, *back)
            assert plus > opl
            assert minus > opl
            assert abs(plus - minus) / (2 * h) < 1e-7  # the gradient vanishes (central difference)
        # (2) an independent minimisation of the optical path in the plane of the normal and the point
        z = float(point @ n)
        radial = point - z * n
        rho = float(np.linalg.norm(radial))
        e = radial / rho
        x1, x2, best = _least_optical_path_in_plane(port, z, rho)
        assert float(q1 @ e) == pytest.approx(x1, abs=2e-7)
        assert float(q2 @ e) == pytest.approx(x2, abs=2e-7)
        assert opl == pytest.approx(best, rel=1e-13)


@pytest.mark.parametrize("seed", range(8))
def test_round_trip_pixel_ray_point_pixel(seed: int) -> None:
    """Pixel -> water ray -> point at 0.3-3 m -> pixel within 1e-6 px, and the ray passes within 1e-9 m."""
    rng = np.random.default_rng(100 + seed)
    port = _random_port(rng)
    cam = CAMERA_DISTORTED if seed % 2 else CAMERA
    uv = np.stack([rng.uniform(-0.5, 1919.5, 5000), rng.uniform(-0.5, 1079.5, 5000)], axis=1)
    uv[:4] = [[-0.5, -0.5], [1919.5, -0.5], [-0.5, 1079.5], [1919.5, 1079.5]]  # the corners
    origins, dirs = pixel_rays_in_water(cam, port, uv)
    assert np.isfinite(dirs).all()
    r = rng.uniform(0.3, 3.0, uv.shape[0])  # distance of the point from the camera centre, metres
    od = np.einsum("ij,ij->i", origins, dirs)
    lam = -od + np.sqrt(od * od - np.einsum("ij,ij->i", origins, origins) + r * r)
    points = origins + lam[:, None] * dirs
    uv_back = project_pixels_through_port(cam, port, points)
    err_px = np.abs(uv_back - uv).max()
    assert err_px < 1e-6, err_px
    o2, d2 = rays_in_water(port, project_through_port(port, points))
    v = points - o2
    miss_m = np.linalg.norm(v - np.einsum("ij,ij->i", v, d2)[:, None] * d2, axis=1).max()
    assert miss_m < 1e-9, miss_m


def test_forward_projection_of_points_not_in_the_water_is_nan() -> None:
    port = PORTS[0]
    points = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.025], [0.1, 0.0, -1.0], [math.nan, 0.0, 1.0], [0.0, 0.0, 0.0]])
    rays = project_through_port(port, points)
    np.testing.assert_allclose(rays[0], [0.0, 0.0, 1.0], atol=1e-15)  # on the axis: straight through
    assert np.isnan(rays[1:]).all()
    with pytest.raises(GeometryError, match="shape"):
        project_through_port(port, np.zeros(3))


# ----------------------------------------------------------------------------------------- triangulation
def _ported_calibration(port: FlatPort | None) -> Calibration:
    R = R_ned_from_body(0.01, -0.02, 0.015) @ np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]).T
    return Calibration(
        camera=CAMERA_DISTORTED,
        lasers=(
            LaserPlane.make("top", (0.02, 0.01, -0.06), (0.03, -0.02, 1.0)),
            LaserPlane.make("bottom", (0.0, -0.01, 0.05), (-0.025, 0.01, 1.0)),
        ),
        R_cam_from_body=tuple(tuple(float(x) for x in r) for r in R.T),  # type: ignore[arg-type]
        t_cam_from_body=(0.01, -0.02, 0.005),
        port=port,
    )


def _points_on_plane(cal: Calibration, laser: LaserPlane, rng: np.random.Generator, n: int) -> np.ndarray:
    """Body points on the laser plane at 0.3-3 m ahead, spread across the view."""
    nrm = laser.normal_body
    u = np.cross(nrm, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(nrm, u)
    range_m = rng.uniform(0.3, 3.0, n)
    lateral = rng.uniform(-1.5, 1.5, n) * range_m
    # step along the plane's in-plane direction closest to body x (forward), and sideways
    fwd = u if abs(u[0]) > abs(w[0]) else w
    side = w if fwd is u else u
    fwd = fwd * np.sign(fwd[0])
    return laser.point_body + range_m[:, None] * fwd + lateral[:, None] * side


@pytest.mark.parametrize("seed", range(4))
def test_exact_pixels_triangulate_within_a_thousandth_of_a_percent(seed: int) -> None:
    rng = np.random.default_rng(40 + seed)
    cal = _ported_calibration(_random_port(rng))
    assert cal.port is not None
    for index, laser in enumerate(cal.lasers):
        points = _points_on_plane(cal, laser, rng, 3000)
        uv = project_pixels_through_port(cal.camera, cal.port, cal.body_to_cam(points))
        seen = cal.camera.in_image(uv)
        assert seen.sum() > 1000
        uv, points = uv[seen], points[seen]
        got = triangulate_through_port(cal, uv, laser)
        range_m = np.linalg.norm(points - cal.camera_center_body, axis=1)
        rel = np.linalg.norm(got - points, axis=1) / range_m
        assert rel.max() < 1e-5, rel.max()  # 0.001 % of range
        np.testing.assert_array_equal(triangulate_through_port(cal, uv, index), got)
        # the pinhole of the in-air camera, ignoring the port, is far off (the port matters)
        pinhole = triangulate_plane(cal, uv, laser)
        assert np.nanmedian(np.linalg.norm(pinhole - points, axis=1) / range_m) > 0.1


def test_triangulation_without_a_port_is_the_pinhole() -> None:
    cal = _ported_calibration(None)
    rng = np.random.default_rng(8)
    uv = np.stack([rng.uniform(0, 1919, 500), rng.uniform(540, 1079, 500)], axis=1)
    np.testing.assert_allclose(
        triangulate_through_port(cal, uv, cal.lasers[1]), triangulate_plane(cal, uv, cal.lasers[1]), atol=1e-12
    )
    mixed = triangulate_through_port(cal, uv[:4], np.array([0, 1, 1, 0]))
    assert mixed.shape == (4, 3)
    with pytest.raises(GeometryError, match="laser index"):
        triangulate_through_port(cal, uv, 2)


def test_triangulation_nan_where_the_ray_misses_the_plane() -> None:
    cal = _ported_calibration(PORTS[0])
    # the top laser is above the camera: pixels below the image centre never meet it in front
    out = triangulate_through_port(cal, np.array([[959.5, 1000.0], [959.5, 100.0]]), cal.lasers[0])
    assert np.isnan(out[0]).all()
    assert np.isfinite(out[1]).all()


# ----------------------------------------------------------------------------------------- the calibration file
PORT_FILE: dict[str, Any] = {
    "camera": {"width": 1920, "height": 1080, "fx": 554.28, "fy": 554.28, "cx": 959.5, "cy": 539.5},
    "R_cam_from_body": [[0, 1, 0], [0, 0, 1], [1, 0, 0]],
    "t_cam_from_body": [0, 0, 0],
    "lasers": [{"name": "top", "point": [0, 0, -0.05], "normal": [0, 0, 1]}],
    "port": {
        "type": "flat",
        "normal_cam": [0, 0, 1],
        "distance_m": 0.02,
        "thickness_m": 0.008,
        "n_air": 1.0,
        "n_glass": 1.49,
        "n_water": 1.34,
    },
}


@pytest.mark.parametrize(
    ("key", "value", "expect"),
    [
        ("thickness_m", -0.001, "port.thickness_m"),
        ("distance_m", 0.0, "port.distance_m"),
        ("distance_m", -0.02, "port.distance_m"),
        ("n_water", 1.0, "port.n_water"),
        ("n_water", 0.99, "port.n_water"),
        ("n_glass", 0.5, "port.n_glass"),
        ("n_air", 0.9, "port.n_air"),
        ("n_glass", "1.5", "port.n_glass"),
        ("normal_cam", [0, 0, -1], "port.normal_cam"),
        ("normal_cam", [0, 1, 0], "port.normal_cam"),
        ("normal_cam", [0.6, 0, 0.8], "port.normal_cam"),  # 36.9 deg
        ("normal_cam", [0, 0, 0], "port.normal_cam"),
        ("normal_cam", [0, math.inf, 1], r"port.normal_cam\[1\]"),
        ("normal_cam", [0, 1], "port.normal_cam"),
        ("normal_cam", list(_tilted_normal(29.0, 209.4)), "port: .*border pixels"),  # away from a corner
        ("type", "dome", "port.type"),
        ("type", None, "port.type"),
    ],
)
def test_file_refuses_bad_port_values_naming_the_key(key: str, value: Any, expect: str) -> None:
    data = copy.deepcopy(PORT_FILE)
    if value is None:
        del data["port"][key]
    else:
        data["port"][key] = value
    with pytest.raises(CalibrationFileError, match=expect):
        Calibration.from_dict(data, "calib.json")


@pytest.mark.parametrize("key", ["normal_cam", "distance_m", "thickness_m", "n_air", "n_glass", "n_water"])
def test_file_refuses_a_port_without_a_key(key: str) -> None:
    data = copy.deepcopy(PORT_FILE)
    del data["port"][key]
    with pytest.raises(CalibrationFileError, match=f"port.{key}"):
        Calibration.from_dict(data)


def test_file_port_none_and_not_an_object() -> None:
    data = copy.deepcopy(PORT_FILE)
    data["port"] = {"type": "none"}
    assert Calibration.from_dict(data).port is None
    data["port"] = "flat"
    with pytest.raises(CalibrationFileError, match="port"):
        Calibration.from_dict(data)
    cal = Calibration.from_dict(PORT_FILE)
    assert cal.port == FlatPort((0.0, 0.0, 1.0), 0.02, 0.008, 1.0, 1.49, 1.34)


# ----------------------------------------------------------------------------------------- the port in the road
def _exact_pixels(cal: Calibration, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (M, 2), their lasers (M,) and true body points (M, 3) of points on both laser planes, through the
    calibration's port, kept where they fall in the image."""
    assert cal.port is not None
    uvs, lasers, points = [], [], []
    for index, laser in enumerate(cal.lasers):
        p = _points_on_plane(cal, laser, rng, n)
        uv = project_pixels_through_port(cal.camera, cal.port, cal.body_to_cam(p))
        seen = cal.camera.in_image(uv)
        uvs.append(uv[seen])
        lasers.append(np.full(int(seen.sum()), index))
        points.append(p[seen])
    return np.concatenate(uvs), np.concatenate(lasers), np.concatenate(points)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("compiled", [False, True])
def test_triangulate_goes_through_the_port(seed: int, compiled: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    from lrsensor.extract import compile
    from lrsensor.triangulation import triangulate

    if compiled:
        if not compile.HAVE_NUMBA:
            pytest.skip("numba is not installed: only the reference exists")
        compile.warm_up()
    else:
        monkeypatch.setattr(compile, "ready", lambda: False)
    rng = np.random.default_rng(70 + seed)
    cal = _ported_calibration(_random_port(rng))
    uv, laser, points = _exact_pixels(cal, rng, 2000)
    got = triangulate(cal, uv, laser)
    range_m = np.linalg.norm(points - cal.camera_center_body, axis=1)
    rel = np.linalg.norm(got - points, axis=1) / range_m
    assert rel.max() < 1e-5, rel.max()  # 0.001 % of range
    # the same as the numpy road of the port module (to rounding)
    np.testing.assert_allclose(got, triangulate_through_port(cal, uv, laser), rtol=0, atol=1e-9)


def test_compiled_port_triangulation_gives_nan_where_the_numpy_one_does() -> None:
    from lrsensor.extract import compile
    from lrsensor.triangulation import triangulate

    if not compile.HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    compile.warm_up()
    # the medium outside less dense than inside: the image's edges are totally reflected (NaN rows)
    port = FlatPort(_tilted_normal(10.0, 0.0), 0.02, 0.008, 1.33, 1.5, 1.0)
    cal = _ported_calibration(port)
    rng = np.random.default_rng(3)
    uv = rng.uniform([0.0, 0.0], [1919.0, 1079.0], (4000, 2))
    laser = rng.integers(0, 2, 4000)
    fast = triangulate(cal, uv, laser)
    slow = triangulate_through_port(cal, uv, laser)
    assert np.array_equal(np.isnan(fast).any(axis=1), np.isnan(slow).any(axis=1))
    assert blind_pixels(cal.camera, port, uv).any()  # the case is exercised
    assert np.nanmax(np.abs(fast - slow)) < 1e-9


def test_geometry_record_carries_the_port() -> None:
    from lrsensor.extract.config import SubpixelConfig
    from lrsensor.extract.settings import frame_settings

    _, _, plain = frame_settings(_ported_calibration(None), SubpixelConfig())
    assert not plain.port.present
    _, _, ported = frame_settings(_ported_calibration(PORTS[1]), SubpixelConfig())
    assert ported.port.present
    np.testing.assert_array_equal(ported.port.normal_cam, PORTS[1].normal)
    assert (ported.port.distance_m, ported.port.thickness_m) == (PORTS[1].distance_m, PORTS[1].thickness_m)
    assert (ported.port.n_air, ported.port.n_glass, ported.port.n_water) == (1.0, 1.53, 1.33)


@pytest.mark.parametrize("port", [PORTS[0], PORTS[1]])
def test_bands_hold_the_stripe_seen_through_the_port(port: FlatPort) -> None:
    from lrsensor.extract.bands import laser_bands

    cal = _ported_calibration(port)
    bands = laser_bands(cal, 0.3, 3.0, 0)
    rng = np.random.default_rng(11)
    for index, laser in enumerate(cal.lasers):
        p = _points_on_plane(cal, laser, rng, 4000)
        depth = cal.body_to_cam(p)[:, 2]
        p = p[(depth >= 0.31) & (depth <= 2.99)]
        uv = cal.project_water_body(p)
        uv = uv[cal.camera.in_image(uv)]
        assert uv.shape[0] > 500
        assert bands.contains(index, uv, slack_px=0.5).mean() > 0.999
        # the pinhole bands (the port ignored) miss much of the refracted stripe
        pinhole = laser_bands(replace(cal, port=None), 0.3, 3.0, 0)
        assert pinhole.contains(index, uv, slack_px=0.5).mean() < 0.95


def test_water_rays_and_projection_of_the_calibration() -> None:
    cal = _ported_calibration(PORTS[1])
    rng = np.random.default_rng(5)
    p = _points_on_plane(cal, cal.lasers[0], rng, 500)
    uv = cal.project_water_body(p)
    seen = cal.camera.in_image(uv)
    origins, dirs = cal.water_rays_body(uv[seen])
    # each point lies on its pixel's water ray, beyond its origin on the port
    along = np.einsum("ij,ij->i", p[seen] - origins, dirs)
    np.testing.assert_allclose(origins + along[:, None] * dirs, p[seen], atol=1e-9)
    assert (along > 0).all()
    plain = replace(cal, port=None)
    o, d = plain.water_rays_body(uv)
    np.testing.assert_array_equal(o, plain.camera_center_body)
    np.testing.assert_array_equal(d, plain.rays_body(uv))
    np.testing.assert_array_equal(plain.project_water_body(p), plain.project_body(p))


def test_central_view_straightens_a_stripe_on_a_wall() -> None:
    """A laser's stripe on a flat (tilted) wall seen through the port is curved in the image but straight in
    :func:`central_view` (a central pinhole in the water); the compiled twin gives the same view."""
    from lrsensor.extract import compile
    from lrsensor.extract.config import SubpixelConfig
    from lrsensor.extract.geometry import central_view as central_view_compiled
    from lrsensor.extract.settings import frame_settings

    cam = Camera(1920, 1080, 554.28, 554.28, 959.5, 539.5)
    cal = replace(_ported_calibration(PORTS[1]), camera=cam)
    assert cal.port is not None
    laser = cal.lasers[0]
    # the line where the laser plane meets a wall tilted 30 deg: two points of it, then points between
    wall_n = np.array([math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0])
    direction = np.cross(laser.normal_body, wall_n)
    anchor = np.linalg.lstsq(
        np.stack([laser.normal_body, wall_n]), np.array([laser.normal_body @ laser.point_body, 1.2]), rcond=None
    )[0]
    points = anchor + np.linspace(-3.0, 3.0, 4001)[:, None] * direction
    uv = cal.project_water_body(points)
    keep = cam.in_image(uv)
    uv = uv[keep]
    assert uv.shape[0] > 1000
    idx = np.zeros(uv.shape[0], dtype=int)
    cols, rows, slope = central_view(cal, uv, idx)
    bow_image = np.ptp(uv[:, 1] - np.polyval(np.polyfit(uv[:, 0], uv[:, 1], 1), uv[:, 0]))
    bow_view = np.ptp(rows - np.polyval(np.polyfit(cols, rows, 1), cols))
    assert bow_image > 5.0  # the port curves the stripe by pixels
    assert bow_view < 1e-6  # a central view of a line is a line
    assert (slope > 0.3).all()
    if compile.HAVE_NUMBA:
        compile.warm_up()
        _, _, geo = frame_settings(cal, SubpixelConfig())
        u, v = np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1])
        c2, r2, s2 = central_view_compiled(u, v, idx.astype(np.int64), geo)
        np.testing.assert_allclose(c2, cols, atol=1e-7)
        np.testing.assert_allclose(r2, rows, atol=1e-7)
        np.testing.assert_allclose(s2, slope, atol=1e-5)
