"""The sensor: one image in, one body-frame scan out."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .calibration import Calibration
from .extract import DEFAULT_METHOD, check_image, get_extractor
from .scan import Scan
from .triangulation import triangulate


class Sensor:
    """The line-laser range sensor: a calibration plus the stripe extractors.

    >>> sensor = Sensor.from_file("calib.json")          # doctest: +SKIP
    >>> scan = sensor.process(image_bgr)                 # doctest: +SKIP
    >>> scan.points                                      # (N, 3) body frame, metres
    """

    def __init__(self, calibration: Calibration) -> None:
        self.calibration = calibration

    @classmethod
    def from_file(cls, path: str | os.PathLike[str]) -> Sensor:
        """A sensor with the calibration read from ``path``."""
        return cls(Calibration.load(path))

    def process(self, image: np.ndarray, method: str = DEFAULT_METHOD, **options: Any) -> Scan:
        """Extract the laser stripes of ``image`` and triangulate them.

        Args:
            image: (H, W, 3) uint8 BGR, as ``cv2.imread`` returns, of the calibration's size.
            method: extractor name: ``"subpixel"`` (default, best) or ``"paper"`` (the paper's Algorithm 1).
            **options: extractor options (see the extractor's documentation).

        Returns:
            The scan: finite points only, body frame, metres.
        """
        img = check_image(image, self.calibration)
        det = get_extractor(method)(img, self.calibration, **options)
        points = triangulate(self.calibration, det.uv, det.laser)
        scan = Scan(points, det.laser.astype(int), det.uv, det.quality, method)
        return scan if bool(np.isfinite(points).all()) else scan.finite()
