"""Triangulation of stripe pixels into body-frame points: the paper's eq. (24) and eq. (29).

Both are vectorized over all points; degenerate rows (ray parallel to the plane, point behind the camera)
are NaN, never dropped, so row ``i`` of the output always belongs to row ``i`` of the input.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .calibration import Calibration, LaserPlane
from .camera import Camera
from .errors import GeometryError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int_]

#: Rays whose cosine with the plane is below this are treated as parallel to it.
PARALLEL_COS = 1e-9


def triangulate_right_angled(uv: ArrayLike, camera: Camera, z_b_m: float) -> FloatArray:
    """Paper eq. (24) for the default mounting and a laser plane ``z_b = z_b_m`` parallel to the viewing axis.

    ``x_b = z_b f / y_c``, ``y_b = z_b x_c / y_c``, ``z_b = c``, with ``(x_c, y_c)`` the undistorted image
    coordinates relative to the principal point (here in focal-length units, so ``f = 1``).

    Args:
        uv: pixels, shape (N, 2).
        camera: intrinsics (distortion is removed first).
        z_b_m: the laser's signed offset along body z, metres (``-c`` top laser, ``+c`` bottom laser).

    Returns:
        Body-frame points, shape (N, 3), metres; NaN rows where the pixel's ray cannot meet the plane in front
        of the camera (``y_c`` zero or of the wrong sign).
    """
    xy = camera.normalized(uv)
    x_c, y_c = xy[:, 0], xy[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        x_b = z_b_m / y_c
        y_b = z_b_m * x_c / y_c
    out = np.stack([x_b, y_b, np.full_like(x_b, z_b_m)], axis=1)
    out[~(x_b > 0) | ~np.isfinite(x_b)] = np.nan
    return out


def intersect_rays_plane(
    origin: ArrayLike, directions: ArrayLike, plane_point: ArrayLike, plane_normal: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Paper eq. (28)-(29): points where rays ``origin + d * direction`` meet a plane.

    Args:
        origin: the rays' common origin (the camera centre), shape (3,).
        directions: ray directions, shape (N, 3) (any length).
        plane_point: a point of the plane, shape (3,).
        plane_normal: the plane's normal, shape (3,) (any length).

    Returns:
        ``(points, d)``: points of shape (N, 3) and the ray parameters ``d`` (N,); NaN where the ray is parallel
        to the plane or meets it behind the origin (``d <= 0``).
    """
    o = np.asarray(origin, dtype=float).reshape(3)
    dirs = np.asarray(directions, dtype=float)
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        msg = f"directions must have shape (N, 3), got {dirs.shape}"
        raise GeometryError(msg)
    n = np.asarray(plane_normal, dtype=float).reshape(3)
    p0 = np.asarray(plane_point, dtype=float).reshape(3)
    denom = dirs @ n
    scale = np.linalg.norm(dirs, axis=1) * np.linalg.norm(n)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = float((p0 - o) @ n) / denom
    bad = ~(np.abs(denom) > PARALLEL_COS * scale) | ~(d > 0)
    d[bad] = np.nan
    return o + d[:, None] * dirs, d


def triangulate_plane(calibration: Calibration, uv: ArrayLike, laser: LaserPlane) -> FloatArray:
    """General ray/plane triangulation (eq. 29) of pixels (N, 2) on one laser plane; body frame (N, 3), metres."""
    rays = calibration.rays_body(np.asarray(uv, dtype=float).reshape(-1, 2))
    pts, _ = intersect_rays_plane(calibration.camera_center_body, rays, laser.point_body, laser.normal_body)
    return pts


def triangulate(
    calibration: Calibration, uv: ArrayLike, laser_index: ArrayLike, *, compiled: bool = True
) -> FloatArray:
    """Triangulate pixels (N, 2), each on the laser plane ``laser_index`` (N,), into body points (N, 3).

    With a port (``calibration.port``) each pixel's ray is refracted into the water first (exact, from its exit
    point on the port's outer surface: :func:`lrsensor.port.triangulate_through_port`); without one it is the
    pinhole ray from the camera centre (eq. 29).

    ``compiled``: use the compiled kernel (:func:`lrsensor.extract.geometry.triangulate_points`, or
    ``triangulate_points_port`` through a port) for 16 pixels or more once numba has it (never waits for it);
    False: numpy only (the extractor's reference)."""
    q = np.asarray(uv, dtype=float).reshape(-1, 2)
    idx = np.asarray(laser_index, dtype=int).reshape(-1)
    if idx.shape[0] != q.shape[0]:
        msg = f"uv has {q.shape[0]} rows but laser_index has {idx.shape[0]}"
        raise GeometryError(msg)
    if idx.size and (idx.min() < 0 or idx.max() >= len(calibration.lasers)):
        msg = f"laser_index out of range 0..{len(calibration.lasers) - 1}"
        raise GeometryError(msg)
    from .extract import compile, geometry  # the compiled twin, once numba has compiled it (never waits for it)

    if compiled and q.shape[0] >= 16 and compile.ready():
        cam, dist, R, o, n_all, p_all = _arrays(calibration)
        u, v, li = np.ascontiguousarray(q[:, 0]), np.ascontiguousarray(q[:, 1]), idx.astype(np.int64)
        if calibration.port is not None:
            from .extract.settings import port_record

            return geometry.triangulate_points_port(  # type: ignore[no-any-return]
                u, v, li, cam, dist, R, o, n_all, p_all, port_record(calibration.port)
            )
        return geometry.triangulate_points(u, v, li, cam, dist, R, o, n_all, p_all)  # type: ignore[no-any-return]
    if calibration.port is not None:
        from .port import triangulate_through_port

        return triangulate_through_port(calibration, q, idx)
    rays = calibration.rays_body(q)
    normals = np.array([l.normal_body for l in calibration.lasers])[idx]
    points = np.array([l.point_body for l in calibration.lasers])[idx]
    o = calibration.camera_center_body
    denom = np.einsum("ij,ij->i", rays, normals)
    scale = np.linalg.norm(rays, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        d = np.einsum("ij,ij->i", points - o, normals) / denom
    d[~(np.abs(denom) > PARALLEL_COS * scale) | ~(d > 0)] = np.nan
    return o + d[:, None] * rays


@lru_cache(maxsize=16)
def _arrays(calibration: Calibration) -> tuple[FloatArray, ...]:
    """The calibration as the compiled kernel's arrays: (fx, fy, cx, cy), distortion (5,), R_cam_from_body (3, 3),
    camera centre (3,), laser normals (L, 3) and points (L, 3), body frame."""
    cam = calibration.camera
    return (
        np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
        np.ascontiguousarray(cam.dist, dtype=np.float64),
        np.ascontiguousarray(calibration.R_cam_body),
        np.ascontiguousarray(calibration.camera_center_body),
        np.array([l.normal_body for l in calibration.lasers], dtype=np.float64),
        np.array([l.point_body for l in calibration.lasers], dtype=np.float64),
    )
