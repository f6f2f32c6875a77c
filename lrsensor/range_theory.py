"""Range theory of the paper, eq. (33)-(34).

The image offset of a stripe from the principal row is ``y_c = v * h_s / h_p`` (eq. 34, metres on the
sensor) and the range along the viewing axis is ``x_b = b f / y_c`` (eq. 33). In pixels, with the focal
length in pixels ``f_px = f h_p / h_s``: ``v = b f_px / x_b``. Following the paper, ``b`` is the baseline
that enters eq. (33); a single laser of this sensor sits at ``c = b / 2`` from the camera axis.

:func:`range_error_per_px` gives the same law for a calibrated sensor, one laser at a time: a stripe row error of
``sigma_v`` pixels moves a point at range ``r`` by about ``sigma_v r^2 / (f_px c)``, ``c`` the laser plane's distance
from the camera centre (what the map's plane extraction expects of each robot's points, ``mapping.range_noise``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

if TYPE_CHECKING:
    from .calibration import Calibration

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RangeCamera:
    """The camera quantities of eq. (33)-(34).

    Attributes:
        focal_m: focal length f, metres (paper: 0.009238).
        sensor_height_m: CCD height h_s, metres (paper: 0.018).
        rows_px: vertical resolution h_p, pixels (paper: 1080).
    """

    focal_m: float = 0.009238
    sensor_height_m: float = 0.018
    rows_px: int = 1080

    @property
    def focal_px(self) -> float:
        """Focal length in pixels, ``f h_p / h_s``."""
        return self.focal_m * self.rows_px / self.sensor_height_m


def range_from_pixel(v_px: ArrayLike, baseline_m: float, cam: RangeCamera = RangeCamera()) -> FloatArray:
    """Eq. (33)-(34): range ``x_b`` (m) of a stripe ``v_px`` pixels from the principal row."""
    y_c = np.asarray(v_px, dtype=float) * cam.sensor_height_m / cam.rows_px
    with np.errstate(divide="ignore"):
        return baseline_m * cam.focal_m / y_c


def pixel_from_range(x_m: ArrayLike, baseline_m: float, cam: RangeCamera = RangeCamera()) -> FloatArray:
    """Inverse of :func:`range_from_pixel`: pixel offset ``v = b f_px / x_b`` of a wall at range ``x_m``."""
    return baseline_m * cam.focal_px / np.asarray(x_m, dtype=float)


def pixel_change(
    x_m: ArrayLike, baseline_m: float, step_m: float = 0.1, cam: RangeCamera = RangeCamera()
) -> FloatArray:
    """Pixel change when the range grows from ``x`` to ``x + step_m`` (the paper's Fig. 9, bottom)."""
    x = np.asarray(x_m, dtype=float)
    return pixel_from_range(x, baseline_m, cam) - pixel_from_range(x + step_m, baseline_m, cam)


def depth_resolution(x_m: ArrayLike, baseline_m: float, cam: RangeCamera = RangeCamera()) -> FloatArray:
    """Range change per pixel at range ``x`` (m/px): ``|dx/dv| = x^2 / (b f_px)``."""
    x = np.asarray(x_m, dtype=float)
    return x * x / (baseline_m * cam.focal_px)


def max_range(
    baseline_m: float, min_change_px: float = 1.0, step_m: float = 0.1, cam: RangeCamera = RangeCamera()
) -> float:
    """Largest range at which a ``step_m`` range change still moves the stripe by ``min_change_px`` pixels.

    Solves ``b f_px (1/x - 1/(x + s)) = p``, i.e. ``x^2 + s x - b f_px s / p = 0``.
    """
    k = baseline_m * cam.focal_px * step_m / min_change_px
    return float((-step_m + np.sqrt(step_m * step_m + 4.0 * k)) / 2.0)


def range_table(
    distances_m: ArrayLike, baselines_m: ArrayLike, cam: RangeCamera = RangeCamera(), step_m: float = 0.1
) -> list[dict[str, float]]:
    """Rows ``{baseline_m, distance_m, pixel_px, change_px_per_step, resolution_m_per_px}``."""
    rows = []
    for b in np.atleast_1d(np.asarray(baselines_m, dtype=float)):
        for x in np.atleast_1d(np.asarray(distances_m, dtype=float)):
            rows.append(
                {
                    "baseline_m": float(b),
                    "distance_m": float(x),
                    "pixel_px": float(pixel_from_range(x, b, cam)),
                    "change_px_per_step": float(pixel_change(x, b, step_m, cam)),
                    "resolution_m_per_px": float(depth_resolution(x, b, cam)),
                }
            )
    return rows


def range_error_per_px(calibration: Calibration) -> float:
    """Range error per pixel of stripe row error per squared metre of range, ``1 / (f_px c)`` (1/(m px)), the
    largest of the calibration's lasers (the map cannot tell which laser a point came from).

    A laser plane at distance ``c`` from the camera centre puts the stripe of a surface at depth ``x``
    ``v = f_px c / x`` pixels off the image's horizon line (eq. (33) with the laser's own offset), so a row error
    ``sigma_v`` moves the point by ``x^2 sigma_v / (f_px c)``. ``f_px`` is the focal length along the stripe's
    motion in the image (the laser normal's direction in the image: ``fy`` for horizontal sheets); behind a flat
    port it grows by ``n_water / n_air`` (a pixel sees a narrower angle in the water). 0 when a laser plane passes
    through the camera centre or faces it edge-on (no triangulation).
    """
    cam = calibration.camera
    worst = 0.0
    centre = calibration.camera_center_body
    for laser in calibration.lasers:
        n_cam = calibration.R_cam_body @ laser.normal_body
        motion = math.hypot(float(n_cam[0]), float(n_cam[1]))  # the normal's component across the image
        c_m = abs(float((centre - laser.point_body) @ laser.normal_body))
        if motion < 1e-9 or c_m < 1e-9:
            return 0.0
        f_px = math.hypot(cam.fx * float(n_cam[0]), cam.fy * float(n_cam[1])) / motion
        if calibration.port is not None:
            f_px *= calibration.port.n_water / calibration.port.n_air
        worst = max(worst, 1.0 / (f_px * c_m))
    return worst
