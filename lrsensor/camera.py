"""The pinhole camera with OpenCV's Brown-Conrady distortion ``[k1, k2, p1, p2, k3]``.

Pixels are ``(u, v)``: u to the right, v down, origin at the centre of the top-left pixel (OpenCV).
Camera frame {c}: z along the optical axis, x right, y down. All functions are vectorized over points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError

FloatArray = NDArray[np.float64]


def _distort(xy: FloatArray, dist: FloatArray) -> FloatArray:
    """Apply Brown-Conrady distortion to normalised coordinates ``xy`` (N, 2)."""
    k1, k2, p1, p2, k3 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def _undistort(xyd: FloatArray, dist: FloatArray, iterations: int = 8) -> FloatArray:
    """Invert :func:`_distort` by Newton's method, vectorized; rows that do not converge become NaN."""
    if not np.any(dist):
        return xyd.copy()
    k1, k2, p1, p2, k3 = dist
    xy = xyd.copy()
    for _ in range(iterations):
        x, y = xy[:, 0], xy[:, 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        res = _distort(xy, dist) - xyd
        a = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
        c = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
        det = a * d - b * c
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = (d * res[:, 0] - b * res[:, 1]) / det
            dy = (-c * res[:, 0] + a * res[:, 1]) / det
        xy = xy - np.stack([dx, dy], axis=1)
    err = np.linalg.norm(_distort(xy, dist) - xyd, axis=1)
    xy[~(err < 1e-9)] = np.nan
    return xy


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics in pixels and Brown-Conrady distortion.

    Attributes:
        width, height: image size in pixels.
        fx, fy: focal lengths in pixels.
        cx, cy: principal point in pixels (OpenCV origin: centre of the top-left pixel).
        distortion: ``(k1, k2, p1, p2, k3)``.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] = field(default=(0.0, 0.0, 0.0, 0.0, 0.0))

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            msg = f"camera size must be positive, got {self.width}x{self.height}"
            raise GeometryError(msg)
        if not (self.fx > 0 and self.fy > 0):
            msg = f"camera focal lengths must be positive, got fx={self.fx}, fy={self.fy}"
            raise GeometryError(msg)
        if len(self.distortion) != 5:
            msg = f"camera distortion must have 5 coefficients [k1, k2, p1, p2, k3], got {len(self.distortion)}"
            raise GeometryError(msg)

    @classmethod
    def paper(cls, width: int = 1920, height: int = 1080) -> Camera:
        """The camera of the paper's simulation (section 5.1): 18 mm sensor height, f = 9.238 mm."""
        f_px = 0.009238 / (0.018 / 1080) * (height / 1080)
        return cls(width, height, f_px, f_px, (width - 1) / 2.0, (height - 1) / 2.0)

    @property
    def K(self) -> FloatArray:
        """The 3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> FloatArray:
        """Distortion coefficients as an array of shape (5,)."""
        return np.asarray(self.distortion, dtype=float)

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return bool(np.any(self.dist))

    def project(self, points_cam: ArrayLike) -> FloatArray:
        """Project camera-frame points (N, 3), metres, to pixels (N, 2); points with z <= 0 give NaN rows."""
        p = np.asarray(points_cam, dtype=float).reshape(-1, 3)
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = p[:, :2] / p[:, 2:3]
        xy[~(p[:, 2] > 0)] = np.nan
        xyd = _distort(xy, self.dist)
        return np.stack([self.fx * xyd[:, 0] + self.cx, self.fy * xyd[:, 1] + self.cy], axis=1)

    def normalized(self, uv: ArrayLike) -> FloatArray:
        """Undistorted normalised image coordinates ``(x/z, y/z)`` of pixels ``uv`` (N, 2)."""
        q = np.asarray(uv, dtype=float).reshape(-1, 2)
        xyd = np.stack([(q[:, 0] - self.cx) / self.fx, (q[:, 1] - self.cy) / self.fy], axis=1)
        return _undistort(xyd, self.dist)

    def unproject(self, uv: ArrayLike) -> FloatArray:
        """Viewing rays of pixels ``uv`` (N, 2) in the camera frame, ``(x, y, 1)`` scaled to z = 1, (N, 3)."""
        xy = self.normalized(uv)
        return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)

    def in_image(self, uv: ArrayLike) -> NDArray[np.bool_]:
        """Mask (N,) of pixels inside the image (the centres of the border pixels included)."""
        q = np.asarray(uv, dtype=float).reshape(-1, 2)
        with np.errstate(invalid="ignore"):
            return (
                (q[:, 0] >= -0.5) & (q[:, 0] <= self.width - 0.5) & (q[:, 1] >= -0.5) & (q[:, 1] <= self.height - 0.5)
            )
