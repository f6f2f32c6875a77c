"""The image band each laser can reach, derived from the calibration and the configured range limits.

A laser's light lies on its plane. Between the depth limits ``min_range_m <= z_c <= max_range_m`` (depth along
the camera's optical axis, metres; for the default mounting this is the forward distance x_b of the paper) the
lit part of the plane is a strip; projected through the camera (with its distortion, and through the flat port
exactly when the calibration has one: the bands hold the refracted stripe, no bound) that strip covers, in each
image column, an interval of rows ``[v_lo, v_hi]``. Only those pixels can hold that laser's stripe, so the
extractors search nowhere else. The band is computed once per (calibration, limits) and cached.

The stripes are assumed near-horizontal in the image (the paper's lasers above and below the camera): each
column crosses a laser's stripe at most once per surface.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import ExtractionError
from ..port import project_through_port

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class LaserBands:
    """Per-laser, per-column row intervals that the lasers can light for the configured range limits.

    Attributes:
        v_lo, v_hi: (L, W) int64 first and last row (inclusive) of laser l's band in column u; ``v_lo > v_hi``
            where the laser cannot be seen in that column.
        v_min, v_max: (L, W) float64 exact (sub-pixel, margin-free) smallest and largest row of the band
            (NaN where not visible), for assigning a point to a laser.
        min_range_m, max_range_m: the depth limits used, metres.
        margin_px: rows added on both sides of the exact band.
    """

    v_lo: IntArray
    v_hi: IntArray
    v_min: FloatArray
    v_max: FloatArray
    min_range_m: float
    max_range_m: float
    margin_px: int

    @property
    def n_lasers(self) -> int:
        """Number of lasers."""
        return int(self.v_lo.shape[0])

    def valid(self, laser: int) -> NDArray[np.bool_]:
        """(W,) columns where ``laser`` has a non-empty band."""
        return self.v_lo[laser] <= self.v_hi[laser]

    def row_range(self, laser: int) -> tuple[int, int]:
        """``(r0, r1)``: the half-open bounding row range of ``laser``'s band over all columns (empty: r0 == r1)."""
        ok = self.valid(laser)
        if not np.any(ok):
            return 0, 0
        return int(self.v_lo[laser][ok].min()), int(self.v_hi[laser][ok].max()) + 1

    def contains(self, laser: int, uv: FloatArray, slack_px: float = 0.0) -> NDArray[np.bool_]:
        """(N,) whether pixels ``uv`` (N, 2) lie in ``laser``'s exact band (plus ``slack_px`` rows)."""
        q = np.asarray(uv, dtype=float).reshape(-1, 2)
        w = self.v_lo.shape[1]
        col = np.clip(np.rint(q[:, 0]).astype(np.int64), 0, w - 1)
        lo, hi = self.v_min[laser][col], self.v_max[laser][col]
        with np.errstate(invalid="ignore"):
            return (q[:, 1] >= lo - slack_px) & (q[:, 1] <= hi + slack_px)


def _distortion_valid_radius(dist: FloatArray) -> float:
    """Largest normalised radius up to which the radial distortion is monotonic (projection is one-to-one)."""
    k1, k2, _, _, k3 = (float(x) for x in dist)
    r = np.linspace(0.0, 6.0, 6001)
    r2 = r * r
    rd = r * (1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2)
    d = np.diff(rd)
    bad = np.flatnonzero(d <= 0)
    return 6.0 if bad.size == 0 else float(r[bad[0]]) * 0.98


def _plane_cam(calibration: Calibration, laser: int) -> tuple[FloatArray, float]:
    """The laser plane in the camera frame: unit normal (3,) and offset d with ``n . p_cam = d``."""
    lp = calibration.lasers[laser]
    R = calibration.R_cam_body
    n_c = R @ lp.normal_body
    p_c = R @ lp.point_body + calibration.t_cam_body
    return n_c, float(n_c @ p_c)


def band_samples(
    calibration: Calibration,
    laser: int,
    min_range_m: float,
    max_range_m: float,
    n_depths: int = 24,
    n_lateral: int = 6001,
) -> tuple[FloatArray, FloatArray]:
    """Pixels (M, 2) of sample points of the laser plane between the depth limits, and their depths (M,), m.

    The plane strip ``{p : n . p = d, min <= z <= max}`` (camera frame) is sampled on lines of constant depth
    (geometric depth steps) and projected with the camera's distortion, through the calibration's flat port when
    it has one (exact refraction, :func:`lrsensor.port.project_through_port`). Samples outside the distortion's
    one-to-one radius (of the in-air ray), that no pixel sees through the port, or far outside the image are
    dropped.
    """
    cam = calibration.camera
    n, d = _plane_cam(calibration, laser)
    z_axis = np.array([0.0, 0.0, 1.0])
    e = np.cross(n, z_axis)
    ne = float(np.linalg.norm(e))
    corners = np.array(
        [[0.0, 0.0], [cam.width - 1.0, 0.0], [0.0, cam.height - 1.0], [cam.width - 1.0, cam.height - 1.0]]
    )
    xy_c = np.abs(np.stack([(corners[:, 0] - cam.cx) / cam.fx, (corners[:, 1] - cam.cy) / cam.fy], axis=1))
    r_valid = _distortion_valid_radius(cam.dist)
    span = min(float(np.hypot(xy_c[:, 0], xy_c[:, 1]).max()) * 1.6 + 0.2, r_valid)
    zs = np.geomspace(min_range_m, max_range_m, n_depths)
    if ne < 1e-9:
        # plane perpendicular to the optical axis: it is seen (everywhere) only if its depth is in range
        z0 = d / n[2]
        if not (min_range_m <= z0 <= max_range_m):
            return np.zeros((0, 2)), np.zeros(0)
        g = np.linspace(-span, span, 801)
        xx, yy = np.meshgrid(g, g)
        pts = np.stack([xx.ravel() * z0, yy.ravel() * z0, np.full(xx.size, z0)], axis=1)
    else:
        e = e / ne
        nxy2 = n[0] ** 2 + n[1] ** 2
        s = np.linspace(-span, span, n_lateral)
        if calibration.port is not None:
            # through a port the same in-air directions, refracted into the water (as a square port bends them):
            # the samples stay about evenly spread over the image, where the water's angles crowd at its edges
            port = calibration.port
            sin_w = np.sin(np.arctan(np.abs(s))) * (port.n_air / port.n_water)
            s = np.sign(s) * np.tan(np.arcsin(np.minimum(sin_w, 0.9999)))
        base = ((d - n[2] * zs) / nxy2)[:, None] * np.array([n[0], n[1], 0.0])[None, :] + zs[:, None] * z_axis
        pts = (base[:, None, :] + (zs[:, None] * s[None, :])[:, :, None] * e[None, None, :]).reshape(-1, 3)
    # the in-air ray of each point: the point itself for a pinhole, the refracted path's first leg through a port
    rays = pts if calibration.port is None else project_through_port(calibration.port, pts)
    with np.errstate(invalid="ignore", divide="ignore"):
        xn = rays[:, 0] / rays[:, 2]
        yn = rays[:, 1] / rays[:, 2]
        ok = (rays[:, 2] > 0) & (np.hypot(xn, yn) <= r_valid)
    pts = pts[ok]
    uv = cam.project(rays[ok])
    with np.errstate(invalid="ignore"):
        keep = (
            np.isfinite(uv).all(axis=1)
            & (uv[:, 0] >= -2.0)
            & (uv[:, 0] <= cam.width + 1.0)
            & (uv[:, 1] >= -4.0 * cam.height)
            & (uv[:, 1] <= 5.0 * cam.height)
        )
    return uv[keep], pts[keep, 2]


def _column_extent(uv: FloatArray, width: int) -> tuple[FloatArray, FloatArray]:
    """Per integer column, min and max v of samples (W,), NaN where no sample; gaps filled by interpolation."""
    col = np.rint(uv[:, 0]).astype(np.int64)
    ok = (col >= 0) & (col < width)
    col, v = col[ok], uv[ok, 1]
    vmin = np.full(width, np.inf)
    vmax = np.full(width, -np.inf)
    np.minimum.at(vmin, col, v)
    np.maximum.at(vmax, col, v)
    have = np.isfinite(vmin)
    out_lo = np.full(width, np.nan)
    out_hi = np.full(width, np.nan)
    if not np.any(have):
        return out_lo, out_hi
    idx = np.flatnonzero(have)
    span = np.arange(idx[0], idx[-1] + 1)
    out_lo[span] = np.interp(span, idx, vmin[idx])
    out_hi[span] = np.interp(span, idx, vmax[idx])
    return out_lo, out_hi


@lru_cache(maxsize=32)
def laser_bands(calibration: Calibration, min_range_m: float, max_range_m: float, margin_px: int) -> LaserBands:
    """The reachable image band of every laser for depths ``[min_range_m, max_range_m]`` (see module doc).

    Args:
        calibration: camera, mounting and laser planes.
        min_range_m, max_range_m: depth limits along the optical axis, metres (0 < min < max).
        margin_px: rows added on both sides of the exact band (half the widest stripe expected).

    Returns:
        :class:`LaserBands` (cached per arguments).
    """
    if not (math.isfinite(min_range_m) and math.isfinite(max_range_m) and 0 < min_range_m < max_range_m):
        msg = f"range limits must satisfy 0 < min_range_m < max_range_m, got {min_range_m} and {max_range_m}"
        raise ExtractionError(msg)
    cam = calibration.camera
    w, h = cam.width, cam.height
    n_l = len(calibration.lasers)
    v_lo = np.ones((n_l, w), np.int64)
    v_hi = np.zeros((n_l, w), np.int64)
    v_min = np.full((n_l, w), np.nan)
    v_max = np.full((n_l, w), np.nan)
    for i in range(n_l):
        uv, _z = band_samples(calibration, i, min_range_m, max_range_m)
        if uv.shape[0] == 0:
            continue
        lo, hi = _column_extent(uv, w)
        good = np.isfinite(lo)
        v_min[i], v_max[i] = lo, hi
        a = np.clip(np.floor(np.where(good, lo, 0.0)) - margin_px, 0, h - 1)
        b = np.clip(np.ceil(np.where(good, hi, -1.0)) + margin_px, -1, h - 1)
        v_lo[i] = np.where(good, a, 1).astype(np.int64)
        v_hi[i] = np.where(good & (b >= a), b, 0).astype(np.int64)
    return LaserBands(v_lo, v_hi, v_min, v_max, float(min_range_m), float(max_range_m), int(margin_px))
