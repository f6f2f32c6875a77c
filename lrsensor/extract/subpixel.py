"""Sub-pixel stripe extractor (interim version: per-column peak with a Gaussian three-point fit)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..calibration import Calibration
from . import Detections


def extract(image: np.ndarray, calibration: Calibration, **_: Any) -> Detections:
    """Per column and per image half, the brightest green pixel refined by a Gaussian 3-point fit."""
    g = image[:, :, 1].astype(np.float64) - 0.5 * (image[:, :, 0].astype(np.float64) + image[:, :, 2])
    h, w = g.shape
    cy = int(round(calibration.camera.cy))
    uvs, lasers, quals = [], [], []
    cols = np.arange(w)
    for idx, (lo, hi) in enumerate(((1, cy), (cy + 1, h - 1))):
        band = g[lo:hi]
        r = np.argmax(band, axis=0)
        peak = band[r, cols]
        ok = (peak > 30) & (r > 0) & (r < band.shape[0] - 1)
        rr, cc = r[ok], cols[ok]
        ym, y0, yp = (np.log(np.maximum(band[rr + k, cc], 1.0)) for k in (-1, 0, 1))
        den = ym - 2 * y0 + yp
        off = np.where(den < 0, 0.5 * (ym - yp) / np.where(den < 0, den, -1), 0.0)
        uvs.append(np.stack([cc.astype(float), lo + rr + np.clip(off, -1, 1)], axis=1))
        lasers.append(np.full(cc.size, idx))
        quals.append(np.clip(peak[ok] / 255.0, 0, 1))
    return Detections(np.concatenate(uvs), np.concatenate(lasers), np.concatenate(quals))
