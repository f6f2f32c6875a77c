"""The camera's flat port: exact refraction at the air/glass and glass/water surfaces, vectorized numpy.

Geometry (camera frame {c}, metres; CONVENTIONS "The camera's port")::

    camera centre (0, 0, 0) -- air -- inner surface  n . x = distance_m
                                  -- glass --   outer surface  n . x = distance_m + thickness_m  -- water -->

``n`` (``normal_cam``) is a unit vector pointing out of the housing. The ``camera`` of the calibration holds the
in-air intrinsics, so a pixel's in-air ray is the pinhole ray of ``Camera.unproject``; the port then bends it
twice. The camera is no longer central: the rays in the water do not meet in one point.

Back-projection (:func:`rays_in_water`) is closed form: Snell's law in vector form at both surfaces. It is exact
up to rounding and fully vectorized. A ray that cannot reach the water (parallel to or away from the port, or
totally reflected) gives a NaN row, never a dropped row; :func:`blind_pixels` and :func:`blind_mask` report the
pixels concerned.

Forward projection (:func:`project_through_port`) has no simple closed form (the two-interface case is a
polynomial of degree 4 and more, badly conditioned near the axis). It uses the two facts every flat port shares:

- the refracted path lies in the plane through the camera centre spanned by ``n`` and the point (the plane of
  incidence is the same at both parallel surfaces), so the 3-D problem is 2-D: the point's axial distance
  ``z = n . p`` and radial distance ``rho = |p - z n|``;
- along the path ``s = n_air sin(a_air) = n_glass sin(a_glass) = n_water sin(a_water)`` is invariant, and the
  radial distance it travels, ``f(s) = s (d / c_air + t / c_glass + (z - d - t) / c_water)`` with
  ``c_i = sqrt(n_i^2 - s^2)``, grows monotonically and convexly from 0 as ``s`` goes from 0 to ``min(n_i)``.

So ``f(s) = rho`` has exactly one root, found for all points at once by Newton's method kept inside a bracket
(a step that leaves the bracket is replaced by bisection), with a fixed iteration cap and a convergence test;
a row that does not converge is NaN. The residual ``f(s) - rho`` is the distance (metres, radial) by which the
re-back-projected ray misses the point, and the test accepts at most ``ROOT_TOL (1 + rho + z)`` metres
(``ROOT_TOL`` = 1e-13: about 70x the rounding of ``f`` at 3 m, and 1e-9 px at the image's edge).
Why not a generic solver on each point: a Python loop per point is ~1000x slower, and a 1-D monotone root
needs nothing more than this.

Triangulation through the port (:func:`triangulate_through_port`) intersects each water ray with a laser plane
(body frame); without a port it is the pinhole intersection of ``triangulation.triangulate_plane``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .camera import Camera
from .errors import GeometryError

if TYPE_CHECKING:
    from .calibration import Calibration, LaserPlane

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Largest accepted angle between the port normal and the optical axis (camera z), degrees.
MAX_TILT_DEG = 30.0
#: A ray whose cosine with the port normal is at most this is treated as parallel to the port (no crossing).
PARALLEL_COS = 1e-12
#: Iteration cap of the forward projection's safeguarded Newton solve (it converges in ~5-10).
MAX_ITERATIONS = 60
#: Relative convergence tolerance of the forward projection: radial miss <= ROOT_TOL (1 + rho + z) metres.
ROOT_TOL = 1e-13
#: A water ray whose cosine with a laser plane's normal is at most this is treated as parallel to the plane.
PLANE_PARALLEL_COS = 1e-9
#: Rows per chunk when a whole image is back-projected (:func:`blind_mask`), to bound memory.
_CHUNK_ROWS = 64


@dataclass(frozen=True)
class FlatPort:
    """A flat window in front of the camera (camera frame, metres).

    Attributes:
        normal_cam: unit normal of the port, camera frame, pointing out of the housing (normalised on
            construction), shape (3,) as a tuple.
        distance_m: distance from the camera centre to the inner surface along ``normal_cam``, metres (> 0).
        thickness_m: glass thickness, metres (>= 0).
        n_air: refractive index inside the housing (>= 1).
        n_glass: refractive index of the window (>= 1).
        n_water: refractive index outside (>= 1).

    Construction refuses non-finite numbers, ``distance_m <= 0``, ``thickness_m < 0``, an index below 1, and a
    normal that is zero, points into the housing (z component <= 0) or is tilted more than ``MAX_TILT_DEG``
    from the optical axis, with :class:`GeometryError` naming the key (``port.thickness_m: ...``). The
    calibration file additionally requires ``n_water > n_air`` (an underwater port); the geometry here also
    handles the other case (total internal reflection then gives NaN rays).
    """

    normal_cam: tuple[float, float, float]
    distance_m: float
    thickness_m: float
    n_air: float = 1.0
    n_glass: float = 1.49
    n_water: float = 1.34

    def __post_init__(self) -> None:
        for key in ("distance_m", "thickness_m", "n_air", "n_glass", "n_water"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                msg = f"port.{key}: must be a finite number, got {v!r}"
                raise GeometryError(msg)
            object.__setattr__(self, key, float(v))
        if not self.distance_m > 0:
            msg = f"port.distance_m: must be positive (the inner surface in front of the camera), got {self.distance_m}"
            raise GeometryError(msg)
        if not self.thickness_m >= 0:
            msg = f"port.thickness_m: must not be negative, got {self.thickness_m}"
            raise GeometryError(msg)
        for key in ("n_air", "n_glass", "n_water"):
            if not getattr(self, key) >= 1.0:
                msg = f"port.{key}: a refractive index must be >= 1, got {getattr(self, key)}"
                raise GeometryError(msg)
        n = np.asarray(self.normal_cam, dtype=float).reshape(-1)
        norm = float(np.linalg.norm(n)) if n.shape == (3,) else math.nan
        if not (math.isfinite(norm) and norm > 1e-12):
            msg = f"port.normal_cam: must be a non-zero finite 3-vector, got {list(self.normal_cam)}"
            raise GeometryError(msg)
        if abs(norm - 1.0) > 4e-16:  # idempotent: a normal read back from a written file keeps its bits
            n = n / norm
        if not n[2] > 0:
            msg = f"port.normal_cam: must point out of the housing (positive z in the camera frame), got {n.tolist()}"
            raise GeometryError(msg)
        tilt_deg = math.degrees(math.acos(min(1.0, float(n[2]))))
        if tilt_deg > MAX_TILT_DEG:
            msg = f"port.normal_cam: tilted {tilt_deg:.1f} deg from the optical axis, more than {MAX_TILT_DEG} deg"
            raise GeometryError(msg)
        object.__setattr__(self, "normal_cam", (float(n[0]), float(n[1]), float(n[2])))

    @property
    def normal(self) -> FloatArray:
        """``normal_cam`` as an array, shape (3,), unit length, camera frame."""
        return np.asarray(self.normal_cam, dtype=float)

    @property
    def outer_distance_m(self) -> float:
        """Distance from the camera centre to the outer (water-side) surface along the normal, metres."""
        return self.distance_m + self.thickness_m

    def to_dict(self) -> dict[str, Any]:
        """The calibration file's ``port`` mapping (``"type": "flat"``)."""
        return {
            "type": "flat",
            "normal_cam": list(self.normal_cam),
            "distance_m": self.distance_m,
            "thickness_m": self.thickness_m,
            "n_air": self.n_air,
            "n_glass": self.n_glass,
            "n_water": self.n_water,
        }


def _unit_rows(v: FloatArray) -> FloatArray:
    """Rows of ``v`` (N, 3) scaled to unit length; zero or non-finite rows become NaN."""
    norm = np.linalg.norm(v, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = v / norm[:, None]
    out[~(norm > 0) | ~np.isfinite(norm)] = np.nan
    return out


def _refract(dirs: FloatArray, normal: FloatArray, cos_in: FloatArray, n1: float, n2: float) -> FloatArray:
    """Snell's law in vector form: unit directions (N, 3) crossing a surface with unit ``normal`` (3,) from
    index ``n1`` to ``n2``; ``cos_in`` (N,) = ``dirs . normal`` > 0. Totally reflected rows are NaN."""
    mu = n1 / n2
    sin2_out = mu * mu * (1.0 - cos_in * cos_in)
    with np.errstate(invalid="ignore"):
        cos_out = np.sqrt(1.0 - sin2_out)  # NaN where sin2_out > 1: total internal reflection
    return mu * dirs + (cos_out - mu * cos_in)[:, None] * normal


def rays_in_water(port: FlatPort, dirs_cam: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Exact back-projection through the port: in-air rays from the camera centre to rays in the water.

    Args:
        port: the flat port.
        dirs_cam: ray directions leaving the camera centre in air, camera frame, shape (N, 3) (normalised here;
            any positive length).

    Returns:
        ``(origins_cam, dirs_water)``, each shape (N, 3), camera frame: the point (metres) where each ray leaves
        the port's outer surface and its unit direction in the water. Rows are NaN where the ray cannot reach
        the water: parallel to or away from the port, zero or non-finite input, or total internal reflection.
    """
    r = np.asarray(dirs_cam, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3:
        msg = f"dirs_cam must have shape (N, 3), got {r.shape}"
        raise GeometryError(msg)
    r = _unit_rows(r)
    n = port.normal
    cos_air = r @ n
    cos_air[~(cos_air > PARALLEL_COS)] = np.nan  # parallel to or away from the port
    p_inner = (port.distance_m / cos_air)[:, None] * r
    g = _refract(r, n, cos_air, port.n_air, port.n_glass)
    cos_glass = g @ n
    p_outer = p_inner + (port.thickness_m / cos_glass)[:, None] * g
    w = _refract(g, n, cos_glass, port.n_glass, port.n_water)
    bad = ~np.isfinite(p_outer).all(axis=1) | ~np.isfinite(w).all(axis=1)
    p_outer[bad] = np.nan
    w[bad] = np.nan
    return p_outer, w


def pixel_rays_in_water(camera: Camera, port: FlatPort, uv: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Pixels (N, 2) to rays in the water through the port, with the camera's in-air intrinsics and distortion.

    Returns:
        ``(origins_cam, dirs_water)``, each shape (N, 3), camera frame (metres; unit directions); NaN rows as
        :func:`rays_in_water`, and where the pixel cannot be undistorted.
    """
    return rays_in_water(port, camera.unproject(uv))


def blind_pixels(camera: Camera, port: FlatPort, uv: ArrayLike) -> BoolArray:
    """Mask (N,) of pixels (N, 2) whose in-air ray exists but cannot reach the water through the port
    (parallel to or away from the port, or totally reflected)."""
    rays = camera.unproject(uv)
    _, w = rays_in_water(port, rays)
    return np.asarray(np.isfinite(rays).all(axis=1) & ~np.isfinite(w).all(axis=1), dtype=bool)


def blind_mask(camera: Camera, port: FlatPort) -> BoolArray:
    """Mask (height, width) of the image's pixels that cannot see into the water (see :func:`blind_pixels`)."""
    u = np.arange(camera.width, dtype=float)
    out = np.zeros((camera.height, camera.width), dtype=bool)
    for v0 in range(0, camera.height, _CHUNK_ROWS):
        v = np.arange(v0, min(v0 + _CHUNK_ROWS, camera.height), dtype=float)
        uu, vv = np.meshgrid(u, v)
        out[v0 : v0 + v.size] = blind_pixels(camera, port, np.stack([uu.ravel(), vv.ravel()], axis=1)).reshape(
            v.size, camera.width
        )
    return out


def border_pixels(camera: Camera) -> FloatArray:
    """The centres of the image's border pixels, shape (2 (width + height) - 4, 2).

    The angle between a pixel's ray and the port normal is largest on the border (the rays of the image fill a
    region whose boundary is the border's rays), so the border tells whether any pixel is blind.
    """
    w, h = camera.width, camera.height
    u = np.arange(w, dtype=float)
    v = np.arange(1, h - 1, dtype=float)
    rows = [np.stack([u, np.zeros(w)], axis=1)]
    if h > 1:
        rows.append(np.stack([u, np.full(w, h - 1.0)], axis=1))
    rows += [np.stack([np.zeros(v.size), v], axis=1), np.stack([np.full(v.size, w - 1.0), v], axis=1)]
    return np.unique(np.concatenate(rows), axis=0)


def _radial_travel(s: FloatArray, heights: Sequence[FloatArray | float], indices: Sequence[float]) -> FloatArray:
    """``sum_i h_i s / sqrt(n_i^2 - s^2)``: the radial distance travelled with ray invariant ``s`` (N,)."""
    total = np.zeros_like(s)
    for h, n in zip(heights, indices, strict=True):
        total = total + h * s / np.sqrt(n * n - s * s)
    return total


def project_through_port(port: FlatPort, points_cam: ArrayLike) -> FloatArray:
    """Exact forward projection through the port: the in-air ray whose refracted path reaches each point.

    Args:
        port: the flat port.
        points_cam: points in the water, camera frame, metres, shape (N, 3).

    Returns:
        Unit ray directions leaving the camera centre in air, camera frame, shape (N, 3) (turn them into pixels
        with the in-air camera model, :func:`project_pixels_through_port`). NaN rows for points not beyond the
        port's outer surface, non-finite points, and (never in practice) rows that did not converge.
        The re-back-projected ray (:func:`rays_in_water`) passes within ``ROOT_TOL (1 + rho + z)`` metres of
        the point (``z``, ``rho``: the point's distances along and across the normal; about 4e-13 m at 3 m).
    """
    p = np.asarray(points_cam, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        msg = f"points_cam must have shape (N, 3), got {p.shape}"
        raise GeometryError(msg)
    n = port.normal
    z = p @ n
    radial = p - z[:, None] * n
    rho = np.linalg.norm(radial, axis=1)
    h_water = z - port.outer_distance_m
    ok = (h_water > 0) & np.isfinite(rho)
    heights: tuple[FloatArray | float, ...] = (port.distance_m, port.thickness_m, np.where(ok, h_water, 1.0))
    indices = (port.n_air, port.n_glass, port.n_water)
    target = np.where(ok, rho, 0.0)
    s_max = min(indices)
    lo = np.zeros_like(target)
    hi = np.full_like(target, s_max)
    # Start at the straight line's invariant (no refraction): inside the bracket, near the root.
    with np.errstate(divide="ignore", invalid="ignore"):
        s = port.n_air * target / np.hypot(target, np.where(ok, z, 1.0))
    s = np.clip(s, 0.0, s_max * (1.0 - 1e-15))
    tol = ROOT_TOL * (1.0 + target + np.where(ok, z, 0.0))
    resid = _radial_travel(s, heights, indices) - target
    for _ in range(MAX_ITERATIONS):
        active = np.abs(resid) > tol  # converged rows keep their root
        if not np.any(active):
            break
        lo = np.where(resid < 0, s, lo)
        hi = np.where(resid > 0, s, hi)
        slope = np.zeros_like(s)
        for h, ni in zip(heights, indices, strict=True):
            c2 = ni * ni - s * s
            slope = slope + h * ni * ni / (c2 * np.sqrt(c2))
        with np.errstate(divide="ignore", invalid="ignore"):
            s_new = s - resid / slope
        inside = (s_new >= lo) & (s_new <= hi) & np.isfinite(s_new)
        s = np.where(active, np.where(inside, s_new, 0.5 * (lo + hi)), s)
        resid = _radial_travel(s, heights, indices) - target
    ok &= np.abs(resid) <= tol
    sin_air = s / port.n_air
    cos_air = np.sqrt(1.0 - sin_air * sin_air)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.where(rho[:, None] > 0, radial / rho[:, None], 0.0)  # radial unit vector (any, on the axis)
    dirs = cos_air[:, None] * n + sin_air[:, None] * e
    dirs[~ok] = np.nan
    return dirs


def project_pixels_through_port(camera: Camera, port: FlatPort, points_cam: ArrayLike) -> FloatArray:
    """Points in the water (N, 3), camera frame, metres, to pixels (N, 2) through the port and the in-air
    camera model (intrinsics and distortion). NaN rows as :func:`project_through_port`."""
    return camera.project(project_through_port(port, points_cam))


def central_view(
    calibration: Calibration, uv: ArrayLike, laser: ArrayLike, step_px: float = 0.25
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Where a pinhole in the water at the camera centre would see the points that pixels (N, 2) of lasers (N,)
    triangulate to through the calibration's port: its columns and rows, and the rows' derivative by the image
    row (a central difference over ``step_px`` rows).

    The pinhole is the camera's with ``fx``, ``fy`` scaled by ``n_water / n_air`` (the two agree near the axis).
    A straight line in the water (a laser plane on a flat surface) is straight in any central view, where the
    port's image curves it; the extractor's along-stripe line fits run there.

    Returns:
        ``(cols, rows, slope)``, each (N,), px, px and px per px; NaN where the ray misses its plane.
    """
    assert calibration.port is not None
    cam = calibration.camera
    q = np.asarray(uv, dtype=float).reshape(-1, 2)
    idx = np.asarray(laser, dtype=int).reshape(-1)
    n = calibration.port.n_water / calibration.port.n_air
    rows = []
    cols = np.full(q.shape[0], np.nan)
    for dv in (-step_px, 0.0, step_px):
        p = calibration.body_to_cam(triangulate_through_port(calibration, q + np.array([0.0, dv]), idx))
        with np.errstate(divide="ignore", invalid="ignore"):
            rows.append(cam.cy + cam.fy * n * p[:, 1] / p[:, 2])
            if dv == 0.0:
                cols = cam.cx + cam.fx * n * p[:, 0] / p[:, 2]
    return cols, rows[1], (rows[2] - rows[0]) / (2.0 * step_px)


def triangulate_through_port(calibration: Calibration, uv: ArrayLike, laser: LaserPlane | ArrayLike) -> FloatArray:
    """Triangulate pixels on laser planes through the calibration's port (exact refraction).

    Args:
        calibration: camera (in-air intrinsics when ``calibration.port`` is set), mounting and laser planes.
            Without a port the pixel's pinhole ray is used, as in ``triangulation.triangulate_plane``.
        uv: pixels, shape (N, 2).
        laser: a :class:`LaserPlane` for all pixels, or laser indices into ``calibration.lasers`` (scalar or
            shape (N,)).

    Returns:
        Body-frame points, shape (N, 3), metres; NaN rows where the pixel cannot see into the water, the water
        ray is parallel to the plane, or meets it behind the port.
    """
    from .calibration import LaserPlane

    q = np.asarray(uv, dtype=float).reshape(-1, 2)
    if isinstance(laser, LaserPlane):
        normals = np.broadcast_to(laser.normal_body, (q.shape[0], 3))
        plane_points = np.broadcast_to(laser.point_body, (q.shape[0], 3))
    else:
        idx = np.broadcast_to(np.asarray(laser, dtype=int).reshape(-1), (q.shape[0],))
        if idx.size and (idx.min() < 0 or idx.max() >= len(calibration.lasers)):
            msg = f"laser index out of range 0..{len(calibration.lasers) - 1}"
            raise GeometryError(msg)
        normals = np.array([l.normal_body for l in calibration.lasers]).reshape(-1, 3)[idx]
        plane_points = np.array([l.point_body for l in calibration.lasers]).reshape(-1, 3)[idx]
    rays_cam = calibration.camera.unproject(q)
    if calibration.port is None:
        origins_cam, dirs_cam = np.zeros_like(rays_cam), _unit_rows(rays_cam)
    else:
        origins_cam, dirs_cam = rays_in_water(calibration.port, rays_cam)
    origins = calibration.cam_to_body(origins_cam)
    dirs = dirs_cam @ calibration.R_cam_body  # camera vectors to body vectors: R^T v
    denom = np.einsum("ij,ij->i", dirs, normals)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = np.einsum("ij,ij->i", plane_points - origins, normals) / denom
    lam[~(np.abs(denom) > PLANE_PARALLEL_COS) | ~(lam > 0)] = np.nan
    return origins + lam[:, None] * dirs
