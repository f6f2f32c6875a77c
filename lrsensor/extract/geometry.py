"""Geometry inside the compiled road: triangulation and the widest plausible stripe.

:func:`triangulate_points` is eq. 29 with the Brown-Conrady distortion: each pixel (u, v) is undistorted by
Newton steps, its body-frame ray met with its laser's plane; (N, 3) body-frame points in metres, NaN rows where
undistortion does not converge, the ray is parallel to the plane or meets it behind the camera. It is the
compiled twin of :func:`lrsensor.triangulation.triangulate` (which calls it for 16 points or more).
:func:`triangulate_points_port` is the same through a flat port (vector Snell at the port's two surfaces, the
twin of :func:`lrsensor.port.rays_in_water`), and :func:`triangulate_geo` picks one of them for a
:class:`~lrsensor.extract.settings.Geometry` (the port when it has one, so without a port the points are those of
:func:`triangulate_points`, bit for bit).

:func:`max_fwhm_at` bounds the width of a stripe at a pixel: a sheet ``max_sheet_mm`` thick seen at the range of
that pixel's ray on its plane, plus 4 px of blur and edges, and never below the floor; close to the wall a thick
sheet draws a wide, flat-topped stripe, far away the same width would be glow or haze.

The calibration is passed as :class:`Geometry` (arrays; :func:`lrsensor.triangulation._arrays` builds them).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ._jit import empty, full, inline, njit

if TYPE_CHECKING:
    from .settings import Geometry

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@inline
def _distortion_residual(x, y, xd, yd, dist):  # type: ignore[no-untyped-def]
    """The Brown-Conrady model (``dist``: ``k1, k2, p1, p2, k3``) at the undistorted normalized point ``(x, y)``
    minus the distorted one ``(xd, yd)``: ``(rx, ry, r2, radial)`` with ``r2 = x^2 + y^2`` and the radial factor."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    rx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
    ry = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
    return rx, ry, r2, radial


@inline
def _undistort(u, v, cam, dist):  # type: ignore[no-untyped-def]
    """Pixels (N,) ``u, v`` to normalized undistorted image coordinates ``(xs, ys)`` (N,) of the camera ``cam``
    (4,) ``fx, fy, cx, cy`` and ``dist`` (5,) ``k1, k2, p1, p2, k3``; ``xs`` is NaN where undistortion does not
    converge."""
    n = u.size
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    xs = empty(n, np.float64)  # normalized undistorted image coordinates
    ys = empty(n, np.float64)
    for t in range(n):
        xs[t] = (u[t] - cx) / fx
        ys[t] = (v[t] - cy) / fy
    if distorted:
        # Newton on the Brown-Conrady model, all points a step at a time (vectorizes): a point stops once its
        # step is below 1e-15 (converged quadratically), exactly as it would on its own
        xd = xs.copy()
        yd = ys.copy()
        act = full(n, True, np.bool_)
        for _ in range(8):
            left = 0
            for t in range(n):
                x = xs[t]
                y = ys[t]
                rx, ry, r2, radial = _distortion_residual(x, y, xd[t], yd[t], dist)
                dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
                a = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
                b = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
                d = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
                det = a * d - b * b
                sx = (d * rx - b * ry) / det
                sy = (-b * rx + a * ry) / det
                on = act[t]
                xs[t] = x - sx if on else x
                ys[t] = y - sy if on else y
                on &= not (abs(sx) + abs(sy) < 1e-15)
                act[t] = on
                left += on
            if left == 0:
                break
        for t in range(n):
            x = xs[t]
            y = ys[t]
            ex, ey, _, _ = _distortion_residual(x, y, xd[t], yd[t], dist)
            xs[t] = x if math.sqrt(ex * ex + ey * ey) < 1e-9 else np.nan
    return xs, ys


@njit
def triangulate_points(u, v, laser, cam, dist, R, origin, normals, points):  # type: ignore[no-untyped-def]
    """Eq. 29 with the Brown-Conrady model, as :func:`lrsensor.triangulation.triangulate` in numpy.

    Args:
        u, v: (N,) float64 pixel coordinates; laser: (N,) int64 plane index of each pixel.
        cam: (4,) ``fx, fy, cx, cy``; dist: (5,) ``k1, k2, p1, p2, k3``; R: (3, 3) ``R_cam_from_body``.
        origin: (3,) camera centre in the body frame; normals, points: (L, 3) laser planes in the body frame.

    Returns:
        (N, 3) body-frame points, metres; NaN rows where undistortion does not converge, the ray is parallel
        to the plane or meets it behind the camera.
    """
    n = u.size
    out = empty((n, 3), np.float64)
    n_l = normals.shape[0]
    off = empty(n_l, np.float64)
    for i in range(n_l):
        off[i] = (
            (points[i, 0] - origin[0]) * normals[i, 0]
            + (points[i, 1] - origin[1]) * normals[i, 1]
            + (points[i, 2] - origin[2]) * normals[i, 2]
        )
    xs, ys = _undistort(u, v, cam, dist)
    # body-frame ray (x, y, 1) @ R met with the laser's plane: branch-free over the points (vectorizes)
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    nx = normals[:, 0].copy()
    ny = normals[:, 1].copy()
    nz = normals[:, 2].copy()
    for t in range(n):
        x = xs[t]
        y = ys[t]
        bx = x * r00 + y * r10 + r20
        by = x * r01 + y * r11 + r21
        bz = x * r02 + y * r12 + r22
        li = np.uint64(laser[t])  # unsigned: no wrap-around select per access
        denom = bx * nx[li] + by * ny[li] + bz * nz[li]
        scale = math.sqrt(bx * bx + by * by + bz * bz)
        lam = off[li] / denom
        good = (abs(denom) > 1e-9 * scale) & (lam > 0)
        lam = lam if good else np.nan
        out[t, 0] = o0 + lam * bx
        out[t, 1] = o1 + lam * by
        out[t, 2] = o2 + lam * bz
    return out


@inline
def _refract(dx, dy, dz, nx, ny, nz, cos_in, mu):  # type: ignore[no-untyped-def]
    """Snell's law in vector form (as :func:`lrsensor.port._refract`): the unit direction ``d`` crossing a surface
    of unit normal ``n`` with ``cos_in = d . n > 0`` and index ratio ``mu = n1 / n2``; NaN when totally reflected."""
    sin2_out = mu * mu * (1.0 - cos_in * cos_in)
    cos_out = math.sqrt(1.0 - sin2_out) if sin2_out <= 1.0 else np.nan
    k = cos_out - mu * cos_in
    return mu * dx + k * nx, mu * dy + k * ny, mu * dz + k * nz


@inline
def _water_ray(x, y, port):  # type: ignore[no-untyped-def]
    """The ray in the water of the in-air ray ``(x, y, 1)`` (normalized image coordinates) through the
    :class:`~lrsensor.extract.settings.Port` ``port``: its exit point on the outer surface and its unit direction,
    camera frame, ``(qx, qy, qz, wx, wy, wz)``; NaN where the ray cannot reach the water."""
    pn = port.normal_cam
    pnx, pny, pnz = pn[0], pn[1], pn[2]
    norm = math.sqrt(x * x + y * y + 1.0)
    rx = x / norm
    ry = y / norm
    rz = 1.0 / norm
    cos_air = rx * pnx + ry * pny + rz * pnz
    cos_air = cos_air if cos_air > 1e-12 else np.nan  # parallel to or away from the port
    s_in = port.distance_m / cos_air
    gx, gy, gz = _refract(rx, ry, rz, pnx, pny, pnz, cos_air, port.n_air / port.n_glass)
    cos_glass = gx * pnx + gy * pny + gz * pnz
    s_glass = port.thickness_m / cos_glass
    wx, wy, wz = _refract(gx, gy, gz, pnx, pny, pnz, cos_glass, port.n_glass / port.n_water)
    return s_in * rx + s_glass * gx, s_in * ry + s_glass * gy, s_in * rz + s_glass * gz, wx, wy, wz


@njit
def triangulate_points_port(u, v, laser, cam, dist, R, origin, normals, points, port):  # type: ignore[no-untyped-def]
    """:func:`triangulate_points` through a flat port: each pixel's in-air ray (camera model with distortion) is
    refracted at the port's two surfaces (:func:`lrsensor.port.rays_in_water`, the numpy reference) and the ray in
    the water, from its exit point on the outer surface, is met with its laser's plane.

    Args:
        u, v, laser, cam, dist, R, origin, normals, points: as :func:`triangulate_points`.
        port: :class:`~lrsensor.extract.settings.Port`, camera frame, metres.

    Returns:
        (N, 3) body-frame points, metres; NaN rows where undistortion does not converge, the pixel cannot see
        into the water (ray parallel to or away from the port, total internal reflection), the water ray is
        parallel to the plane or meets it behind the port.
    """
    n = u.size
    out = empty((n, 3), np.float64)
    xs, ys = _undistort(u, v, cam, dist)
    o0, o1, o2 = origin[0], origin[1], origin[2]
    for t in range(n):
        qx, qy, qz, wx, wy, wz = _water_ray(xs[t], ys[t], port)
        # camera vectors to body vectors: R^T v
        ox = o0 + qx * R[0, 0] + qy * R[1, 0] + qz * R[2, 0]
        oy = o1 + qx * R[0, 1] + qy * R[1, 1] + qz * R[2, 1]
        oz = o2 + qx * R[0, 2] + qy * R[1, 2] + qz * R[2, 2]
        bx = wx * R[0, 0] + wy * R[1, 0] + wz * R[2, 0]
        by = wx * R[0, 1] + wy * R[1, 1] + wz * R[2, 1]
        bz = wx * R[0, 2] + wy * R[1, 2] + wz * R[2, 2]
        li = laser[t]
        denom = bx * normals[li, 0] + by * normals[li, 1] + bz * normals[li, 2]
        lam = (
            (points[li, 0] - ox) * normals[li, 0]
            + (points[li, 1] - oy) * normals[li, 1]
            + (points[li, 2] - oz) * normals[li, 2]
        ) / denom
        lam = lam if (abs(denom) > 1e-9) and (lam > 0) else np.nan
        out[t, 0] = ox + lam * bx
        out[t, 1] = oy + lam * by
        out[t, 2] = oz + lam * bz
    return out


def triangulate_geo(u: FloatArray, v: FloatArray, laser: IntArray, geo: Geometry) -> FloatArray:
    """Pixels (N,) ``u, v`` (float64) of lasers ``laser`` (N,) (int64) to body-frame points (N, 3), metres, with
    the :class:`~lrsensor.extract.settings.Geometry` ``geo``: through its port when it has one
    (:func:`triangulate_points_port`), else the pinhole (:func:`triangulate_points`).

    A Python call of one of the two kernels, not a kernel: a kernel that called them would compile both again
    into its own machine code (:mod:`lrsensor.extract.compile`)."""
    if geo.port.present:
        return triangulate_points_port(  # type: ignore[no-any-return]
            u, v, laser, geo.camera, geo.distortion, geo.R_cam_body, geo.origin_body, geo.normals_body,
            geo.points_body, geo.port,
        )  # fmt: skip
    return triangulate_points(  # type: ignore[no-any-return]
        u, v, laser, geo.camera, geo.distortion, geo.R_cam_body, geo.origin_body, geo.normals_body, geo.points_body
    )


#: Row step of the numerical derivative of :func:`central_view`, px.
CENTRAL_VIEW_STEP_PX = 0.25


@njit
def central_view(u, v, laser, geo):  # type: ignore[no-untyped-def]
    """Where a pinhole in the water at the camera centre would see the points that pixels ``(u, v)`` (N,) of
    lasers ``laser`` (N,) triangulate to through the port of ``geo``: its columns and rows (N,) and the rows'
    derivative by ``v`` (N,) (the numpy twin: :func:`lrsensor.port.central_view`).

    The pinhole is the camera's with ``fx``, ``fy`` scaled by ``n_water / n_air`` (the two agree near the axis).
    A straight line in the water (a laser plane on a flat surface) is a straight line in any central view, where
    the port's image curves it; the along-stripe line fits run there. NaN where the ray misses the plane.
    """
    n = u.size
    port = geo.port
    cam = geo.camera
    ratio = port.n_water / port.n_air
    h = CENTRAL_VIEW_STEP_PX
    uu = empty(3 * n, np.float64)
    vv = empty(3 * n, np.float64)
    ll = empty(3 * n, np.int64)
    for t in range(n):
        for j in range(3):
            uu[3 * t + j] = u[t]
            vv[3 * t + j] = v[t] + (j - 1) * h
            ll[3 * t + j] = laser[t]
    pts = triangulate_points_port(
        uu, vv, ll, cam, geo.distortion, geo.R_cam_body, geo.origin_body, geo.normals_body, geo.points_body, port
    )
    R = geo.R_cam_body
    o = geo.origin_body
    g = empty(3 * n, np.float64)
    cols = empty(n, np.float64)
    for t in range(3 * n):
        dx = pts[t, 0] - o[0]
        dy = pts[t, 1] - o[1]
        dz = pts[t, 2] - o[2]
        x = R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * dz
        y = R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * dz
        z = R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * dz
        g[t] = cam[3] + cam[1] * ratio * y / z
        if t % 3 == 1:
            cols[t // 3] = cam[2] + cam[0] * ratio * x / z
    rows = empty(n, np.float64)
    slope = empty(n, np.float64)
    for t in range(n):
        rows[t] = g[3 * t + 1]
        slope[t] = (g[3 * t + 2] - g[3 * t]) / (2.0 * h)
    return cols, rows, slope


def max_fwhm_at(
    cols: IntArray, rows: IntArray, laser: IntArray, floor: float, sheet_mm: float, geo: Geometry
) -> FloatArray:
    """The widest plausible stripe (half-level width, px) at each pixel ``(cols, rows)`` (N,) of ``laser`` (N,).

    ``floor``: the width limit where the ray misses the plane (and the least limit), px; ``sheet_mm``: the thickest
    sheet, mm (<= 0: the floor everywhere); ``geo``: the :class:`~lrsensor.extract.settings.Geometry`. The pixels'
    points come from :func:`triangulate_geo`, the widths from :func:`fwhm_from_points`.
    """
    n = cols.size
    if n == 0 or sheet_mm <= 0:
        return full(n, floor, np.float64)
    pts = triangulate_geo(cols.astype(np.float64), rows.astype(np.float64), laser, geo)
    return fwhm_from_points(pts, floor, sheet_mm, geo)  # type: ignore[no-any-return]


@njit
def fwhm_from_points(pts, floor, sheet_mm, geo):  # type: ignore[no-untyped-def]
    """The widths of :func:`max_fwhm_at` (N,), px, of the body-frame points ``pts`` (N, 3), metres, that the
    pixels triangulate to (NaN rows: the floor)."""
    cam, origin, axis = geo.camera, geo.origin_body, geo.axis_body
    n = pts.shape[0]
    out = full(n, floor, np.float64)
    for t in range(n):
        depth = (
            (pts[t, 0] - origin[0]) * axis[0] + (pts[t, 1] - origin[1]) * axis[1] + (pts[t, 2] - origin[2]) * axis[2]
        )
        wv = 1e-3 * sheet_mm * cam[1] / depth + 4.0
        if math.isfinite(wv) and depth > 0:
            out[t] = max(wv, floor)
    return out
