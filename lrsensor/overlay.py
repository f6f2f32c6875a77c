"""A picture of what the extractor saw: the scan's stripe points and the search bands drawn on the image.

Looking at it is the quickest check that a real rig's images are read right: the stripes covered, nothing found
on reflections or blobs, the bands (from the calibration and the range limits) around the stripes.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .calibration import Calibration
from .errors import ExtractionError
from .scan import Scan

#: BGR colour of each laser's points (laser index modulo the list): magenta, yellow, cyan, orange.
LASER_COLOURS = ((255, 0, 255), (0, 255, 255), (255, 255, 0), (0, 128, 255))
#: BGR colour of the band outlines.
BAND_COLOUR = (200, 120, 40)


def draw_scan(
    image: NDArray[np.uint8],
    scan: Scan,
    calibration: Calibration | None = None,
    min_range_m: float = 0.2,
    max_range_m: float = 5.0,
) -> NDArray[np.uint8]:
    """The image (H, W, 3) uint8 BGR, darkened, with the scan's points drawn on it.

    Each point is a 1x3 pixel mark at its rounded ``uv`` in its laser's colour (``LASER_COLOURS``), from dim at
    quality 0 to full at quality 1. With ``calibration``, the outline of every laser's search band for the
    depth limits ``[min_range_m, max_range_m]`` (metres) is drawn too.

    Returns:
        A new (H, W, 3) uint8 BGR image; ``image`` is not modified.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        msg = f"image must be (H, W, 3) uint8 BGR, got shape {img.shape} and dtype {img.dtype}"
        raise ExtractionError(msg)
    h, w = img.shape[:2]
    out = (img.astype(np.float32) * 0.6).astype(np.uint8)
    if calibration is not None:
        from .extract.bands import laser_bands

        bands = laser_bands(calibration, min_range_m, max_range_m, 0)
        for i in range(bands.n_lasers):
            cols = np.flatnonzero(bands.valid(i) & (np.arange(bands.v_lo.shape[1]) < w))
            for edge in (bands.v_lo[i][cols], bands.v_hi[i][cols]):
                ok = (edge >= 0) & (edge < h)
                out[edge[ok], cols[ok]] = BAND_COLOUR
    if len(scan):
        u = np.rint(scan.uv[:, 0]).astype(np.int64)
        v = np.rint(scan.uv[:, 1]).astype(np.int64)
        colour = np.array([LASER_COLOURS[int(k) % len(LASER_COLOURS)] for k in range(int(scan.laser.max()) + 1)])
        rgb = colour[scan.laser] * (0.35 + 0.65 * np.clip(scan.quality, 0.0, 1.0))[:, None]
        for dv in (-1, 0, 1):
            vv = v + dv
            ok = (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
            out[vv[ok], u[ok]] = rgb[ok].astype(np.uint8)
    return out
