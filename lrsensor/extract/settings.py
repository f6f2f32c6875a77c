"""The settings records of the compiled road: the extractor's options and the calibration as the kernels read them.

The kernels take their parameters as typed records (:class:`typing.NamedTuple`: numba passes them as
heterogeneous tuples and reads their fields by name, compiled to the same loads as positional arguments), never
packed by position into arrays. They are built in one place, :func:`frame_settings`,
once per (calibration, configuration), and read, never written, by the kernels:

- :class:`Bands`: where each laser's stripe can be (:mod:`lrsensor.extract.bands`), rows in pixels;
- :class:`Settings`: the options of :class:`~lrsensor.extract.config.SubpixelConfig` and the constants of the
  algorithm, units in the names;
- :class:`Geometry`: the calibration as arrays (triangulation, the width limits, the depth gate), with its
  flat port as a :class:`Port` (``present`` False without one: the pinhole road, unchanged).

Field types matter: numba compiles one version per record type, so integers are Python ``int`` (int64), reals
``float`` (float64), and arrays C-contiguous of the dtype given here.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..port import FlatPort
from ..triangulation import _arrays
from .bands import _column_extent, band_samples, laser_bands
from .centre import WIDE_FWHM_PX
from .config import ITERATIONS, SNR_FLOOR_FRAC, SubpixelConfig
from .detect import AREA_NOISE

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]


class Bands(NamedTuple):
    """The image band of each of the ``L`` lasers, for an image ``W`` columns wide (rows in pixels)."""

    #: (L, 2) int64: the bounding rows ``[r0, r1)`` of each laser's band (``r1 <= r0``: empty).
    rows: IntArray
    #: (L, W) int64: the first row of each laser's band per column.
    v_lo: IntArray
    #: (L, W) int64: the last row of each laser's band per column (below ``v_lo``: none in that column).
    v_hi: IntArray
    #: (L, W) int64: the side of each laser's stripe on which the sheet's glow in turbid water lies, per column
    #: (+1: larger rows, -1: smaller, 0: unknown): away from the plane's vanishing line, where nearer parts of
    #: the sheet image (:mod:`lrsensor.extract.glow`).
    glow_side: IntArray


class Settings(NamedTuple):
    """The options of the compiled road (see :class:`~lrsensor.extract.config.SubpixelConfig` for their meaning)."""

    #: Row offset ``d`` of the two-sided contrast of the detection (even), px.
    contrast_px: int
    #: Detection threshold in units of the detection response's noise.
    snr_threshold: float
    #: Noise of the detection response over the pixel noise (2x2 average, then a 3-column box).
    area_noise: float
    #: Least detection response, DN.
    min_response_dn: float
    #: Candidates kept per column.
    max_candidates: int
    #: Largest row step between neighbouring full-resolution columns of one stripe piece, px.
    max_jump_px: float
    #: Shortest accepted stripe piece, full-resolution columns.
    min_run_cols: int
    #: Half-length of the profile window before the frame's statistics adapt it, px.
    window_half_px: int
    #: Centroid iterations of the sub-pixel fits.
    iterations: int
    #: Green level from which a sample counts as clipped, DN.
    saturation_dn: float
    #: Narrowest accepted stripe (full width at half maximum), px.
    min_fwhm_px: float
    #: Widest accepted stripe profile (Gaussian sigma), px.
    max_sigma_px: float
    #: Half-level width above which a profile is wide (flat-topped), px.
    wide_fwhm_px: float
    #: Smallest accepted stripe peak above the local background, DN.
    min_contrast_dn: float
    #: Smallest accepted peak-to-noise ratio.
    min_snr: float
    #: The pooled green rise must exceed this multiple of the red and the blue rise.
    min_green_ratio: float
    #: Columns either side over which the colour test and the signal-to-noise ratio are pooled.
    gate_pool_cols: int
    #: The pooled signal-to-noise ratio of a column is at most its own divided by this.
    snr_floor_frac: float
    #: Thickest laser sheet on the surface, mm (<= 0: no width limit from the range).
    max_sheet_mm: float
    #: (K,) int64: half-widths of the along-stripe line fits, columns, largest first (empty: no smoothing).
    smooth_scales: IntArray
    #: Depth limits along the optical axis of the kept points, metres.
    min_range_m: float
    max_range_m: float
    #: Fit the stripes that show a glow jointly with it (:mod:`lrsensor.extract.glow`).
    glow_fit: bool


class Port(NamedTuple):
    """The calibration's flat port as the kernels take it (camera frame, metres; :class:`lrsensor.port.FlatPort`)."""

    #: Whether the camera looks through a port (False: the other fields are placeholders, never read).
    present: bool
    #: (3,) the port's unit normal, camera frame, out of the housing.
    normal_cam: FloatArray
    #: Distance from the camera centre to the inner surface along the normal, metres.
    distance_m: float
    #: Glass thickness, metres.
    thickness_m: float
    #: Refractive indices inside the housing, of the glass and of the water.
    n_air: float
    n_glass: float
    n_water: float


def port_record(port: FlatPort | None) -> Port:
    """The kernels' :class:`Port` of a calibration's port (None: ``present`` False)."""
    if port is None:
        return Port(False, np.array([0.0, 0.0, 1.0]), 0.0, 0.0, 1.0, 1.0, 1.0)
    return Port(
        True,
        np.ascontiguousarray(port.normal, np.float64),
        float(port.distance_m),
        float(port.thickness_m),
        float(port.n_air),
        float(port.n_glass),
        float(port.n_water),
    )


class Geometry(NamedTuple):
    """The calibration as the kernels take it (body frame, metres)."""

    #: (4,) ``fx, fy, cx, cy``, px.
    camera: FloatArray
    #: (5,) Brown-Conrady ``k1, k2, p1, p2, k3``.
    distortion: FloatArray
    #: (3, 3) ``R_cam_from_body``.
    R_cam_body: FloatArray
    #: (3,) the camera centre in the body frame.
    origin_body: FloatArray
    #: (L, 3) the laser planes' normals and points in the body frame.
    normals_body: FloatArray
    points_body: FloatArray
    #: (3,) the unit optical axis in the body frame.
    axis_body: FloatArray
    #: The camera z of a body point ``p`` is ``R_cam_body[2] . p + cam_z_offset_m``.
    cam_z_offset_m: float
    #: The flat port the camera looks through (``port.present`` False: none).
    port: Port
    #: (L, W) per laser and column, the row of the laser sheet's vanishing line, px, and ``2 s D``, px m: ``D`` the
    #: sheet's range times its rows from that line, ``s = sqrt(1 + xn^2)`` the path's obliqueness (0: unknown): the
    #: shape of the sheet's glow in turbid water (:func:`glow_geometry`, :func:`lrsensor.extract.glow_fit.sheet_edge`).
    glow_vanish: FloatArray
    glow_path: FloatArray


def glow_sides(calibration: Calibration, near_m: float, far_m: float) -> IntArray:
    """(L, W) int64: per laser and column, the side of the stripe on which the laser sheet images nearer than
    the stripe (its glow in turbid water): the sign of the row of the sheet at depth ``near_m`` less its row at
    ``far_m`` (metres along the optical axis); 0 where the column sees neither."""
    cam = calibration.camera
    out = np.zeros((len(calibration.lasers), cam.width), np.int64)
    for i in range(len(calibration.lasers)):
        uv, z = band_samples(calibration, i, near_m, far_m, n_depths=2)
        if uv.shape[0] == 0:
            continue
        v_near = _column_extent(uv[z <= near_m * 1.0001], cam.width)[0]
        v_far = _column_extent(uv[z >= far_m * 0.9999], cam.width)[0]
        with np.errstate(invalid="ignore"):
            out[i] = np.where(np.isfinite(v_near) & np.isfinite(v_far), np.sign(v_near - v_far), 0).astype(np.int64)
    return out


def glow_geometry(calibration: Calibration, near_m: float, far_m: float) -> tuple[FloatArray, FloatArray]:
    """``(vanish, path)`` (L, W) float64 of :class:`Geometry`: in each column the sheet images at ``v = v_inf + D /
    z`` (a plane seen by a pinhole; ``z`` its depth along the optical axis), taken from its rows at depths
    ``near_m`` and ``far_m`` (distortion and a port bend this a little: the glow's shape, not a centre); ``path = 2
    sqrt(1 + xn^2) |D|``, 0 where the column sees neither depth."""
    cam = calibration.camera
    n_l = len(calibration.lasers)
    vanish = np.zeros((n_l, cam.width))
    path = np.zeros((n_l, cam.width))
    xn = (np.arange(cam.width) - cam.cx) / cam.fx
    for i in range(n_l):
        uv, z = band_samples(calibration, i, near_m, far_m, n_depths=2)
        if uv.shape[0] == 0:
            continue
        v_near = _column_extent(uv[z <= near_m * 1.0001], cam.width)[0]
        v_far = _column_extent(uv[z >= far_m * 0.9999], cam.width)[0]
        d = (v_near - v_far) / (1.0 / near_m - 1.0 / far_m)
        good = np.isfinite(d) & (np.abs(d) > 1.0)
        vanish[i] = np.where(good, v_far - np.where(good, d, 0.0) / far_m, 0.0)
        path[i] = np.where(good, 2.0 * np.sqrt(1.0 + xn * xn) * np.abs(np.where(good, d, 0.0)), 0.0)
    return vanish, path


@lru_cache(maxsize=16)
def frame_settings(calibration: Calibration, cfg: SubpixelConfig) -> tuple[Bands, Settings, Geometry]:
    """The records of the compiled road (and the reference) for this calibration and configuration; cached (the
    same records every frame: the kernels only read them).

    The bands are where each laser can light a surface between the depth limits, with a margin of 2 px
    (:func:`lrsensor.extract.bands.laser_bands`)."""
    lb = laser_bands(calibration, cfg.min_range_m, cfg.max_range_m, 2)
    n_l = lb.n_lasers
    bands = Bands(
        np.array([lb.row_range(i) for i in range(n_l)], np.int64).reshape(n_l, 2),
        np.ascontiguousarray(lb.v_lo, np.int64),
        np.ascontiguousarray(lb.v_hi, np.int64),
        glow_sides(calibration, cfg.min_range_m, cfg.max_range_m),
    )
    k0 = cfg.smooth_half_cols
    scales = sorted({16 * k0, 4 * k0, k0, max(1, k0 // 4)}, reverse=True) if k0 >= 1 else []
    settings = Settings(
        contrast_px=int(cfg.contrast_px),
        snr_threshold=float(cfg.snr_threshold),
        area_noise=AREA_NOISE,
        min_response_dn=0.7 * cfg.min_contrast_dn,
        max_candidates=int(cfg.max_candidates),
        max_jump_px=float(cfg.max_jump_px),
        min_run_cols=int(cfg.min_run_cols),
        window_half_px=int(cfg.window_half_px),
        iterations=ITERATIONS,
        saturation_dn=float(cfg.saturation_dn),
        min_fwhm_px=float(cfg.min_fwhm_px),
        max_sigma_px=float(cfg.max_sigma_px),
        wide_fwhm_px=WIDE_FWHM_PX,
        min_contrast_dn=float(cfg.min_contrast_dn),
        min_snr=float(cfg.min_snr),
        min_green_ratio=float(cfg.min_green_ratio),
        gate_pool_cols=int(cfg.gate_pool_cols),
        snr_floor_frac=SNR_FLOOR_FRAC,
        max_sheet_mm=float(cfg.max_sheet_mm),
        smooth_scales=np.array(scales, np.int64),
        min_range_m=float(cfg.min_range_m),
        max_range_m=float(cfg.max_range_m),
        glow_fit=bool(cfg.glow_fit),
    )
    cam, dist, R, origin, normals, points = _arrays(calibration)
    axis = calibration.rays_body(np.array([[calibration.camera.cx, calibration.camera.cy]], np.float64))[0]
    geometry = Geometry(
        cam,
        dist,
        R,
        origin,
        normals,
        points,
        axis / np.linalg.norm(axis),
        float(calibration.t_cam_body[2]),
        port_record(calibration.port),
        *glow_geometry(calibration, cfg.min_range_m, cfg.max_range_m),
    )
    return bands, settings, geometry
