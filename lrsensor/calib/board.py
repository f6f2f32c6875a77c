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
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..camera import Camera
from ..errors import CalibrationFitError
from .planefit import Plane

FloatArray = NDArray[np.float64]


class BoardCalibrationError(CalibrationFitError):
    """A calibration from checkerboard images was refused; ``not_found`` lists the images without a board."""

    def __init__(self, message: str, not_found: Sequence[str] = ()) -> None:
        super().__init__(message)
        self.not_found = list(not_found)


def image_table_lines(per_image_rms_px: dict[str, float], not_found: Sequence[str]) -> list[str]:
    """The per-image lines of a board calibration's report: a heading, each used image's RMS reprojection
    error (pixels) and each image without a board, names cut to 40 characters."""
    lines = [f"{'image':<40} {'RMS px':>8}"]
    lines += [f"{_cut(n):<40} {e:>8.4f}" for n, e in per_image_rms_px.items()]
    lines += [f"{_cut(n):<40} {'no board':>8}" for n in not_found]
    return lines


def _cut(name: str) -> str:
    return name if len(name) <= 40 else "..." + name[-37:]


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


def stripe_mask(image: NDArray[np.uint8]) -> NDArray[np.bool_]:
    """Pixels (H, W) of the green laser stripes: much greener than blue and red (``G - max(B, R) > 25`` DN),
    dilated by 2 px. All false for a grey image."""
    if image.ndim == 2:
        return np.zeros(image.shape, dtype=bool)
    import cv2

    b = image[:, :, 0].astype(np.int16)
    g = image[:, :, 1].astype(np.int16)
    r = image[:, :, 2].astype(np.int16)
    stripe = np.asarray((g - np.maximum(b, r)) > 25, dtype=np.uint8)
    if not stripe.any():
        return stripe.astype(bool)
    return np.asarray(cv2.dilate(stripe, np.ones((5, 5), np.uint8)), dtype=bool)


def _gray_candidates(image: NDArray[np.uint8]) -> list[NDArray[np.uint8]]:
    """Grey images to search: with the green laser stripe painted out first (it shifts corners), then as is.

    The stripe pixels (:func:`stripe_mask`) are filled with ``cv2.inpaint`` (Telea) from their surroundings.
    """
    import cv2

    if image.ndim == 2:
        return [image]
    gray = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
    mask = stripe_mask(image)
    if not mask.any():
        return [gray]
    painted = np.asarray(cv2.inpaint(gray, mask.astype(np.uint8), 3, cv2.INPAINT_TELEA), dtype=np.uint8)
    return [painted, gray]


def corners_clear_of_stripes(
    image: NDArray[np.uint8], corners: FloatArray, spec: BoardSpec, min_keep: int = 6
) -> NDArray[np.bool_]:
    """Mask (N,) of corners whose refinement window holds no laser-stripe pixel (a stripe shifts a corner).

    When fewer than ``min_keep`` corners would remain, all are kept (the robust pose then trims outliers).
    """
    import cv2

    mask = stripe_mask(image)
    keep = np.ones(corners.shape[0], dtype=bool)
    if not mask.any():
        return keep
    grid = corners.reshape(spec.rows, spec.cols, 2)
    spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    radius = int(np.clip(spacing * 0.35, 2, 11)) + 2
    dist = cv2.distanceTransform(np.asarray(~mask, dtype=np.uint8), cv2.DIST_L2, 3)
    h, w = mask.shape
    u = np.clip(np.rint(corners[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(corners[:, 1]).astype(int), 0, h - 1)
    keep = dist[v, u] > radius
    return keep if int(keep.sum()) >= min_keep else np.ones(corners.shape[0], dtype=bool)


def _refine(gray: NDArray[np.uint8], corners: FloatArray, spec: BoardSpec) -> FloatArray:
    """``cv2.cornerSubPix`` with a half-window below half the corner spacing (never reaching a neighbour)."""
    import cv2

    c = corners.reshape(-1, 2).astype(np.float32)
    grid = c.reshape(spec.rows, spec.cols, 2)
    spacing = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    half = int(np.clip(spacing * 0.35, 2, 11))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    refined = cv2.cornerSubPix(gray, c.reshape(-1, 1, 2), (half, half), (-1, -1), crit)
    return np.asarray(refined, dtype=float).reshape(-1, 2)


def find_board_corners(image: NDArray[np.uint8], spec: BoardSpec) -> FloatArray | None:
    """Sub-pixel inner corners (cols*rows, 2) of the board in ``image`` (BGR or grey), or ``None``.

    The corners are ordered as :meth:`BoardSpec.object_points`. Search order, cheapest first (a failed
    ``findChessboardCorners`` on a large cluttered image can take minutes, a downscaled one milliseconds):
    the stripe-free grey image at half size, the plain grey at half size, the stripe-free one at full size,
    then ``findChessboardCornersSB`` at half size; corners found on a half-size image are refined at full size.
    """
    import cv2

    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    grays = _gray_candidates(image)
    big = max(grays[0].shape) > 1000
    halves = [cv2.resize(g, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for g in grays] if big else grays
    attempts = [(h, g, 2.0 if big else 1.0) for h, g in zip(halves, grays, strict=True)]
    if big:
        attempts.append((grays[0], grays[0], 1.0))
    for small, full, scale in attempts:
        found, corners = cv2.findChessboardCorners(small, spec.pattern_size, flags=flags)
        if found and corners is not None:
            c = np.asarray(corners, dtype=float).reshape(-1, 2)
            c = (c + 0.5) * scale - 0.5  # pixel-centre convention
            return _refine(full, c, spec)
    if hasattr(cv2, "findChessboardCornersSB"):
        found, corners = cv2.findChessboardCornersSB(halves[0], spec.pattern_size, flags=cv2.CALIB_CB_ACCURACY)
        if found and corners is not None:
            c = np.asarray(corners, dtype=float).reshape(-1, 2)
            scale = 2.0 if big else 1.0
            return _refine(grays[0], (c + 0.5) * scale - 0.5, spec)
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
        corners_used: corners kept for the pose (stray corners, e.g. under a stripe, are dropped).
    """

    R_cam_from_board: FloatArray
    t_cam_from_board: FloatArray
    corners_uv: FloatArray
    reprojection_rms_px: float
    reprojection_max_px: float
    corners_used: int = 0

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
    obj_all = spec.object_points()
    img_all = corners.astype(np.float32)
    keep = corners_clear_of_stripes(image, corners, spec)
    err = np.zeros(0)
    used = keep
    for it in range(4):
        used = keep
        obj, img = obj_all[used], img_all[used]
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, camera.dist)
        if not ok:
            msg = f"{name}: solvePnP failed for the checkerboard"
            raise CalibrationFitError(msg)
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.dist, rvec, tvec)
        proj, _ = cv2.projectPoints(obj_all, rvec, tvec, camera.K, camera.dist)
        err_all = np.linalg.norm(proj.reshape(-1, 2) - corners, axis=1)
        err = err_all[used]
        # Drop corners far off the others (a stripe or a reflection across them), keeping >= 70 % of them.
        limit = max(4.0 * float(np.median(err)), 0.5)
        new_keep = err_all <= limit
        if it == 3 or new_keep.sum() < 0.7 * keep.size or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    R, _ = cv2.Rodrigues(rvec)
    return BoardPose(
        np.asarray(R, dtype=float),
        np.asarray(tvec, dtype=float).reshape(3),
        corners,
        float(np.sqrt(np.mean(err * err))),
        float(np.max(err)),
        int(used.sum()),
    )
