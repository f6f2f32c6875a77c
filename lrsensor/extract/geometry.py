"""Geometry inside the compiled road: triangulation and the widest plausible stripe.

:func:`triangulate_points` is eq. 29 with the Brown-Conrady distortion: each pixel (u, v) is undistorted by
Newton steps, its body-frame ray met with its laser's plane; (N, 3) body-frame points in metres, NaN rows where
undistortion does not converge, the ray is parallel to the plane or meets it behind the camera. It is the
compiled twin of :func:`lrsensor.triangulation.triangulate` (which calls it for 16 points or more).

:func:`max_fwhm_at` bounds the width of a stripe at a pixel: a sheet ``max_sheet_mm`` thick seen at the range of
that pixel's ray on its plane, plus 4 px of blur and edges, and never below the floor; close to the wall a thick
sheet draws a wide, flat-topped stripe, far away the same width would be glow or haze.

The calibration is passed as :class:`Geometry` (arrays; :func:`lrsensor.triangulation._arrays` builds them).
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit


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
    out = np.empty((n, 3))
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    n_l = normals.shape[0]
    off = np.empty(n_l)
    for i in range(n_l):
        off[i] = (
            (points[i, 0] - origin[0]) * normals[i, 0]
            + (points[i, 1] - origin[1]) * normals[i, 1]
            + (points[i, 2] - origin[2]) * normals[i, 2]
        )
    xs = np.empty(n)  # normalized undistorted image coordinates
    ys = np.empty(n)
    for t in range(n):
        xs[t] = (u[t] - cx) / fx
        ys[t] = (v[t] - cy) / fy
    if distorted:
        # Newton on the Brown-Conrady model, all points a step at a time (vectorizes): a point stops once its
        # step is below 1e-15 (converged quadratically), exactly as it would on its own
        xd = xs.copy()
        yd = ys.copy()
        act = np.ones(n, np.bool_)
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


@njit
def max_fwhm_at(cols, rows, laser, floor, sheet_mm, geo):  # type: ignore[no-untyped-def]
    """The widest plausible stripe (half-level width, px) at each pixel ``(cols, rows)`` (N,) of ``laser`` (N,).

    ``floor``: the width limit where the ray misses the plane (and the least limit), px; ``sheet_mm``: the thickest
    sheet, mm (<= 0: the floor everywhere); ``geo``: the :class:`~lrsensor.extract.settings.Geometry`.
    """
    cam, origin, axis = geo.camera, geo.origin_body, geo.axis_body
    n = cols.size
    out = np.full(n, floor)
    if n == 0 or sheet_mm <= 0:
        return out
    pts = triangulate_points(
        cols.astype(np.float64),
        rows.astype(np.float64),
        laser,
        cam,
        geo.distortion,
        geo.R_cam_body,
        origin,
        geo.normals_body,
        geo.points_body,
    )
    for t in range(n):
        depth = (
            (pts[t, 0] - origin[0]) * axis[0] + (pts[t, 1] - origin[1]) * axis[1] + (pts[t, 2] - origin[2]) * axis[2]
        )
        wv = 1e-3 * sheet_mm * cam[1] / depth + 4.0
        if math.isfinite(wv) and depth > 0:
            out[t] = max(wv, floor)
    return out
