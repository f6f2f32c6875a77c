"""Checkerboard detection and pose: the wall's plane from a board on it (the paper's future work, section 5.2).

The board is described by its inner-corner grid (OpenCV's ``patternSize``: ``cols x rows`` inner corners, so a
board of 10 x 7 squares is ``9x6``) and its square size in metres. Board frame: origin at the first detected
inner corner, x along the rows of corners, y along the columns, z = x cross y, the board in its z = 0 plane.

Per image: ``cv2.findChessboardCorners`` (falling back to ``cv2.findChessboardCornersSB``), then
``cv2.cornerSubPix``, then ``cv2.solvePnP`` with the calibration's intrinsics and distortion; the wall plane
is the board's z = 0 plane, moved from the camera frame into the body frame.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..camera import Camera
from ..errors import CalibrationFitError
from .planefit import Plane

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BoardSpec:
    """A checkerboard: ``cols`` x ``rows`` inner corners, squares of ``square_m`` metres."""

    cols: int
    rows: int
    square_m: float

    def __post_init__(self) -> None:
        if self.cols < 2 or self.rows < 2:
            msg = f"a checkerboard needs at least 2x2 inner corners, got {self.cols}x{self.rows}"
            raise CalibrationFitError(msg)
        if not (self.square_m > 0 and np.isfinite(self.square_m)):
            msg = f"checkerboard square size must be a positive number of metres, got {self.square_m}"
            raise CalibrationFitError(msg)

    @classmethod
    def parse(cls, text: str, square_m: float) -> BoardSpec:
        """``"9x6"`` (inner corners, COLSxROWS) and the square size in metres."""
        m = re.fullmatch(r"\s*(\d+)\s*[xX*]\s*(\d+)\s*", text)
        if m is None:
            msg = f"board must be COLSxROWS inner corners, e.g. 9x6, got {text!r}"
            raise CalibrationFitError(msg)
        return cls(int(m.group(1)), int(m.group(2)), float(square_m))

    @property
    def pattern_size(self) -> tuple[int, int]:
        """OpenCV's ``patternSize`` ``(cols, rows)``."""
        return (self.cols, self.rows)

    def object_points(self) -> NDArray[np.float32]:
        """Inner corners in the board frame, row by row, shape (cols*rows, 3), metres (float32 for OpenCV)."""
        xs, ys = np.meshgrid(np.arange(self.cols), np.arange(self.rows))
        pts = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1) * self.square_m
        return pts.astype(np.float32)


def _gray_candidates(image: NDArray[np.uint8]) -> list[NDArray[np.uint8]]:
    """Grey images to search: without the green channel first (the green laser stripe vanishes), then all."""
    if image.ndim == 2:
        return [image]
    import cv2

    b = image[:, :, 0].astype(np.uint16)
    r = image[:, :, 2].astype(np.uint16)
    no_green = np.asarray((b + r) // 2, dtype=np.uint8)
    gray = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    return [no_green, gray]


def find_board_corners(image: NDArray[np.uint8], spec: BoardSpec) -> FloatArray | None:
    """Sub-pixel inner corners (cols*rows, 2) of the board in ``image`` (BGR or grey), or ``None``.

    The corners are ordered as :meth:`BoardSpec.object_points`.
    """
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    for gray in _gray_candidates(image):
        found, corners = cv2.findChessboardCorners(gray, spec.pattern_size, flags=flags)
        if found and corners is not None:
            c = corners.reshape(-1, 2).astype(np.float32)
            # Half-window below half the corner spacing, so that a window never reaches a neighbour corner.
            grid = c.reshape(spec.rows, spec.cols, 2)
            spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
            half = int(np.clip(spacing * 0.35, 2, 11))
            crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
            refined = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (half, half), (-1, -1), crit)
            return np.asarray(refined, dtype=float).reshape(-1, 2)
        if hasattr(cv2, "findChessboardCornersSB"):
            found, corners = cv2.findChessboardCornersSB(gray, spec.pattern_size, flags=cv2.CALIB_CB_ACCURACY)
            if found and corners is not None:
                return np.asarray(corners, dtype=float).reshape(-1, 2)
    return None


@dataclass(frozen=True)
class BoardPose:
    """Pose of a board seen by the camera.

    Attributes:
        R_cam_from_board: rotation (3, 3).
        t_cam_from_board: board origin in the camera frame, metres, shape (3,).
        corners_uv: the detected corners, pixels, shape (N, 2).
        reprojection_rms_px: RMS distance between detected and reprojected corners, pixels.
        reprojection_max_px: largest such distance, pixels.
    """

    R_cam_from_board: FloatArray
    t_cam_from_board: FloatArray
    corners_uv: FloatArray
    reprojection_rms_px: float
    reprojection_max_px: float

    def plane_cam(self) -> Plane:
        """The board's plane in the camera frame, normal pointing away from the camera."""
        n = self.R_cam_from_board[:, 2]
        plane = Plane.from_point_normal(self.t_cam_from_board, n)
        # Camera at the origin: the plane's offset must be positive when the normal points away from it.
        return Plane(-plane.normal, -plane.offset) if plane.offset < 0 else plane

    def plane_body(self, calibration: Calibration) -> Plane:
        """The board's (wall's) plane in the body frame, normal pointing from the camera to the wall."""
        pc = self.plane_cam()
        point_body = calibration.cam_to_body(self.t_cam_from_board[None, :])[0]
        normal_body = calibration.R_cam_body.T @ pc.normal
        return Plane.from_point_normal(point_body, normal_body)


def estimate_board_pose(image: NDArray[np.uint8], camera: Camera, spec: BoardSpec, name: str = "image") -> BoardPose:
    """Find the board in ``image`` and solve its pose with the camera's intrinsics and distortion.

    Raises:
        CalibrationFitError: the board was not found (the message names ``name`` and the pattern size).
    """
    import cv2

    corners = find_board_corners(image, spec)
    if corners is None:
        msg = (
            f"{name}: checkerboard with {spec.cols}x{spec.rows} inner corners not found; check --board "
            f"(inner corners COLSxROWS, e.g. 9x6 for a board of 10x7 squares), lighting and focus"
        )
        raise CalibrationFitError(msg)
    obj = spec.object_points()
    ok, rvec, tvec = cv2.solvePnP(obj, corners.astype(np.float32), camera.K, camera.dist, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rvec, tvec = cv2.solvePnP(obj, corners.astype(np.float32), camera.K, camera.dist)
    if not ok:
        msg = f"{name}: solvePnP failed for the checkerboard"
        raise CalibrationFitError(msg)
    rvec, tvec = cv2.solvePnPRefineLM(obj, corners.astype(np.float32), camera.K, camera.dist, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)
    err = np.linalg.norm(proj.reshape(-1, 2) - corners, axis=1)
    R, _ = cv2.Rodrigues(rvec)
    return BoardPose(
        np.asarray(R, dtype=float),
        np.asarray(tvec, dtype=float).reshape(3),
        corners,
        float(np.sqrt(np.mean(err * err))),
        float(np.max(err)),
    )
