"""Range theory of the paper, eq. (33)-(34).

The image offset of a stripe from the principal row is ``y_c = v * h_s / h_p`` (eq. 34, metres on the
sensor) and the range along the viewing axis is ``x_b = b f / y_c`` (eq. 33). In pixels, with the focal
length in pixels ``f_px = f h_p / h_s``: ``v = b f_px / x_b``. Following the paper, ``b`` is the baseline
that enters eq. (33); a single laser of this sensor sits at ``c = b / 2`` from the camera axis.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

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
