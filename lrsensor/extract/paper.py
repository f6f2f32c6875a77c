"""The paper's Algorithm 1 (section 3), faithfully: the baseline every report compares against.

For the whole image: BGR -> HSV, keep the greens (``cv2.inRange``), thin the mask to a morphological skeleton
(the classic erode/open construction; ``cv2.ximgproc`` is not part of opencv-python-headless). Then for each of
``n_rois`` vertical strips across the width: ``cv2.HoughLinesP`` on the skeleton, and per found line the ROI
centre point of eq. (32), read as the midpoint: ``u = (u_min + u_max) / 2`` of the ROI and ``v`` the line's row
at that ``u``. Each point is assigned to the laser whose reachable image band contains it (the bands are
derived from the calibration, see :mod:`lrsensor.extract.bands`); per ROI and laser the longest line wins. The
triangulation (eq. 29) is done by :class:`lrsensor.sensor.Sensor`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import ExtractionError
from . import Detections, config_with_options
from .bands import laser_bands


@dataclass(frozen=True)
class PaperConfig:
    """Options of the paper's method.

    Attributes:
        n_rois: number of vertical regions of interest across the image width.
        hsv_lower, hsv_upper: the green filter, OpenCV HSV (H in 0..180, S and V in 0..255).
        hough_threshold: accumulator votes of ``cv2.HoughLinesP``.
        min_line_frac: shortest line as a fraction of the ROI width.
        max_line_gap_px: largest gap bridged by ``cv2.HoughLinesP``, pixels.
        min_range_m, max_range_m: depth limits of the laser bands used to assign points to lasers, metres.
    """

    n_rois: int = 64
    hsv_lower: tuple[int, int, int] = (35, 60, 60)
    hsv_upper: tuple[int, int, int] = (90, 255, 255)
    hough_threshold: int = 8
    min_line_frac: float = 0.3
    max_line_gap_px: int = 5
    min_range_m: float = 0.2
    max_range_m: float = 5.0

    def __post_init__(self) -> None:
        if self.n_rois < 1:
            msg = f"n_rois must be >= 1, got {self.n_rois}"
            raise ExtractionError(msg)

    @classmethod
    def from_options(cls, config: PaperConfig | None = None, **options: Any) -> PaperConfig:
        """``config`` (or the defaults) with keyword overrides; unknown names raise :class:`ExtractionError`."""
        return config_with_options(cls, config, "paper", options)


def green_mask(image: NDArray[np.uint8], cfg: PaperConfig) -> NDArray[np.uint8]:
    """Algorithm 1, lines 2-3: HSV conversion and the green filter; (H, W) uint8 mask (255 = green)."""
    hsv = cv2.cvtColor(image, cv2.COLOR_BGR2HSV)
    mask: Any = cv2.inRange(hsv, np.array(cfg.hsv_lower, np.uint8), np.array(cfg.hsv_upper, np.uint8))
    return mask


def skeletonize(mask: NDArray[np.uint8], max_iterations: int = 64) -> NDArray[np.uint8]:
    """Algorithm 1, line 4: the morphological skeleton ``union_k (E^k(A) - open(E^k(A)))`` of a binary mask.

    Whole-image OpenCV operations per iteration (vectorized); stops when the eroded mask is empty.
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    skel: Any = np.zeros_like(mask)
    img: Any = mask.copy()
    for _ in range(max_iterations):
        if cv2.countNonZero(img) == 0:
            break
        opened = cv2.morphologyEx(img, cv2.MORPH_OPEN, kernel)
        skel = cv2.bitwise_or(skel, cv2.subtract(img, opened))
        img = cv2.erode(img, kernel)
    return skel


def extract(
    image: NDArray[np.uint8], calibration: Calibration, config: PaperConfig | None = None, **options: Any
) -> Detections:
    """The paper's Algorithm 1: one centre point per ROI and laser (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR of the calibration's size.
        calibration: the sensor's calibration (for assigning points to lasers).
        config: options (default :class:`PaperConfig`); ``**options`` override single fields.

    Returns:
        :class:`Detections`: ROI-centre pixels (N, 2), laser index (N,), quality (N,) = line length / ROI width.
    """
    cfg = PaperConfig.from_options(config, **options)
    _h, w = image.shape[:2]
    bands = laser_bands(calibration, cfg.min_range_m, cfg.max_range_m, 2)
    skel = skeletonize(green_mask(image, cfg))
    edges = np.linspace(0, w, cfg.n_rois + 1)
    uvs: list[tuple[float, float]] = []
    lasers: list[int] = []
    quals: list[float] = []
    for r in range(cfg.n_rois):
        u_min, u_max = math.floor(edges[r]), math.floor(edges[r + 1])
        if u_max - u_min < 2:
            continue
        roi = np.ascontiguousarray(skel[:, u_min:u_max])
        roi_w = u_max - u_min
        lines = cv2.HoughLinesP(
            roi,
            rho=1.0,
            theta=np.pi / 180.0,
            threshold=cfg.hough_threshold,
            minLineLength=max(2.0, cfg.min_line_frac * roi_w),
            maxLineGap=cfg.max_line_gap_px,
        )
        if lines is None:
            continue
        seg = lines.reshape(-1, 4).astype(np.float64)
        x1, y1, x2, y2 = seg[:, 0] + u_min, seg[:, 1], seg[:, 2] + u_min, seg[:, 3]
        u_c = 0.5 * (u_min + (u_max - 1))  # eq. (32) read as the midpoint of the ROI's pixel columns
        dx = x2 - x1
        steep = np.abs(dx) < 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            v_c = np.where(steep, 0.5 * (y1 + y2), y1 + (y2 - y1) * (u_c - x1) / np.where(steep, 1.0, dx))
        length = np.hypot(dx, y2 - y1)
        pts = np.stack([np.full(v_c.shape, u_c), v_c], axis=1)
        for i in range(bands.n_lasers):
            inside = bands.contains(i, pts, slack_px=2.0) & ~steep
            if not np.any(inside):
                continue
            j = int(np.flatnonzero(inside)[np.argmax(length[inside])])
            uvs.append((u_c, float(v_c[j])))
            lasers.append(i)
            quals.append(float(min(1.0, length[j] / roi_w)))
    if not uvs:
        return Detections.empty()
    return Detections(np.asarray(uvs, dtype=float), np.asarray(lasers, dtype=np.int64), np.asarray(quals, dtype=float))
