"""The scan: what the sensor makes of one image."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .errors import GeometryError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Scan:
    """Points of one image in the body frame.

    Attributes:
        points: (N, 3) float64, body frame, metres.
        laser: (N,) int, index of the laser plane (into ``Calibration.lasers``) each point lies on.
        uv: (N, 2) float64, sub-pixel image coordinates each point was measured at.
        quality: (N,) float64 in [0, 1], the extractor's confidence in each point.
        method: name of the extractor that produced the scan.
    """

    points: FloatArray
    laser: NDArray[np.int_]
    uv: FloatArray
    quality: FloatArray
    method: str = "subpixel"
    info: dict[str, float] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        n = self.points.shape[0]
        if (
            self.points.shape != (n, 3)
            or self.laser.shape != (n,)
            or self.uv.shape != (n, 2)
            or (self.quality.shape != (n,))
        ):
            msg = (
                f"inconsistent scan arrays: points {self.points.shape}, laser {self.laser.shape}, "
                f"uv {self.uv.shape}, quality {self.quality.shape}"
            )
            raise GeometryError(msg)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @classmethod
    def empty(cls, method: str = "subpixel") -> Scan:
        """A scan without points."""
        return cls(np.zeros((0, 3)), np.zeros(0, dtype=int), np.zeros((0, 2)), np.zeros(0), method)

    def finite(self) -> Scan:
        """The scan without rows whose point is not finite."""
        keep = np.all(np.isfinite(self.points), axis=1)
        return Scan(self.points[keep], self.laser[keep], self.uv[keep], self.quality[keep], self.method, self.info)

    def select(self, mask: NDArray[np.bool_]) -> Scan:
        """The rows of the scan where ``mask`` (N,) is true."""
        return Scan(self.points[mask], self.laser[mask], self.uv[mask], self.quality[mask], self.method, self.info)
