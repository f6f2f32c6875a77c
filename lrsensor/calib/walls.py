"""Each calibration image's wall: its plane in the body frame, and the stripe pixels' points on it.

The wall of an image is ``n . (p - o) = distance_m`` in the body frame: ``n`` is the unit wall normal
pointing from the camera towards the wall (default ``(1, 0, 0)``: a wall square to the body x axis, ahead),
and ``o`` is the body origin (``distance_from="body"``, default, the paper's x_b distance) or the camera's
optical centre (``distance_from="camera"``). In words: the wall's point nearest to ``o`` lies
``distance_m`` metres from ``o`` along ``n``. With a checkerboard on the wall, the wall plane of each image
is measured with ``solvePnP`` instead (:mod:`lrsensor.calib.board`).

:func:`resolve_wall` gives one image's wall plane, checked to face the camera, with the start of its
:class:`~lrsensor.calib.laser_records.ImageReport`; :func:`wall_points` intersects pixel rays with a wall
(paper eq. 31; through the calibration's flat port, the refracted rays in the water). The laser planes are fit
to these points by :func:`lrsensor.calib.lasers.calibrate_lasers`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import CalibrationFitError
from ..triangulation import intersect_rays_plane
from .board import BoardPose, estimate_board_pose
from .laser_records import FloatArray, ImageReport, LaserCalibrationConfig, LaserCalibrationError
from .planefit import Plane, normal_angle_deg, wall_plane

ImageLike = str | os.PathLike[str] | NDArray[np.uint8]


@dataclass(frozen=True)
class WallImage:
    """One calibration image and the wall it shows.

    Attributes:
        image: a path to the image or the image itself, (H, W, 3) uint8 BGR.
        distance_m: the wall's distance along ``normal`` (see the module docstring), metres; ``None`` when the
            wall pose comes from a checkerboard.
        normal: the wall normal in the body frame, pointing from the camera to the wall (normalised here).
        name: how reports and messages call the image (the file name by default).
    """

    image: ImageLike
    distance_m: float | None = None
    normal: tuple[float, float, float] = (1.0, 0.0, 0.0)
    name: str = ""

    @property
    def label(self) -> str:
        """The image's name for messages."""
        if self.name:
            return self.name
        if isinstance(self.image, np.ndarray):
            return "image"
        return str(self.image)


def _load_image(view: WallImage) -> NDArray[np.uint8]:
    if isinstance(view.image, np.ndarray):
        return view.image
    import cv2

    path = Path(view.image)
    if not path.is_file():
        msg = f"{path}: calibration image not found"
        raise LaserCalibrationError(msg)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        msg = f"{path}: cannot read the image (not an image file OpenCV can decode)"
        raise LaserCalibrationError(msg)
    return np.asarray(img, dtype=np.uint8)


def _optical_axis_body(calibration: Calibration) -> FloatArray:
    return calibration.R_cam_body.T @ np.array([0.0, 0.0, 1.0])


def resolve_wall(
    view: WallImage,
    image: NDArray[np.uint8],
    calibration: Calibration,
    config: LaserCalibrationConfig,
) -> tuple[Plane, ImageReport, BoardPose | None]:
    """The wall plane (body frame, normal from the camera to the wall) of one image, checked to face the camera.

    Raises:
        LaserCalibrationError: wall behind the camera, normal facing away, board not found or imprecise.
    """
    o = calibration.camera_center_body
    axis = _optical_axis_body(calibration)
    pose = None
    if config.board is not None:
        if calibration.port is not None:
            msg = (
                f"{view.label}: a checkerboard's pose through the flat port (port in the calibration) is not "
                f"supported yet: give each wall's distance (IMAGE=DIST_M) instead of --board"
            )
            raise LaserCalibrationError(msg)
        try:
            pose = estimate_board_pose(image, calibration.camera, config.board, view.label)
        except CalibrationFitError as err:
            raise LaserCalibrationError(str(err)) from err
        if pose.reprojection_rms_px > config.max_reprojection_px:
            msg = (
                f"{view.label}: checkerboard reprojection RMS {pose.reprojection_rms_px:.3f} px exceeds "
                f"{config.max_reprojection_px:.3f} px: wrong --board/--square-m, wrong intrinsics or a "
                f"board that is not flat"
            )
            raise LaserCalibrationError(msg)
        plane = pose.plane_body(calibration)
        source = "board"
    else:
        if view.distance_m is None:
            msg = f"{view.label}: no wall distance given (IMAGE=DIST_M) and no checkerboard (--board) to measure it"
            raise LaserCalibrationError(msg)
        d = float(view.distance_m)
        if not np.isfinite(d) or d <= 0:
            msg = (
                f"{view.label}: wall distance {view.distance_m} m is not positive: the wall would be at or "
                f"behind the camera; give the distance in metres along the wall normal, in front of the camera"
            )
            raise LaserCalibrationError(msg)
        n = np.asarray(view.normal, dtype=float)
        if not (np.all(np.isfinite(n)) and np.linalg.norm(n) > 1e-9):
            msg = f"{view.label}: wall normal {list(view.normal)} is not a non-zero finite vector"
            raise LaserCalibrationError(msg)
        origin = None if config.distance_from == "body" else o
        plane = wall_plane(d, n, origin)
        source = "distance"
    cam_dist = plane.offset - float(plane.normal @ o)
    facing = float(plane.normal @ axis)
    if cam_dist <= 0 or facing <= 0:
        msg = (
            f"{view.label}: the wall is behind the camera (wall normal {np.round(plane.normal, 4).tolist()} "
            f"against the viewing direction {np.round(axis, 4).tolist()}, distance from the camera "
            f"{cam_dist:.4f} m). The wall normal points from the camera towards the wall, e.g. 1,0,0 for a "
            f"wall ahead; the distance is positive"
        )
        raise LaserCalibrationError(msg)
    if facing < np.cos(np.radians(80.0)):
        msg = (
            f"{view.label}: the wall is seen at {np.degrees(np.arccos(facing)):.1f} deg from face-on; more than "
            f"80 deg gives no usable stripe geometry"
        )
        raise LaserCalibrationError(msg)
    report = ImageReport(
        name=view.label,
        wall_normal=(float(plane.normal[0]), float(plane.normal[1]), float(plane.normal[2])),
        wall_distance_m=cam_dist,
        wall_source=source,
        given_distance_m=None if view.distance_m is None else float(view.distance_m),
        board_reprojection_px=None if pose is None else pose.reprojection_rms_px,
    )
    return plane, report, pose


def wall_points(uv: FloatArray, calibration: Calibration, wall: Plane) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Paper eq. (31): body-frame points (N, 3) where the rays of pixels ``uv`` (N, 2) meet ``wall``; through the
    calibration's flat port the rays are the refracted ones in the water, from the port's outer surface.

    Returns the points and a mask (N,) of rays that meet the wall in front of the camera (or the port).
    """
    if calibration.port is None:
        rays = calibration.rays_body(uv)
        pts, d = intersect_rays_plane(calibration.camera_center_body, rays, wall.normal * wall.offset, wall.normal)
    else:
        origins, dirs = calibration.water_rays_body(uv)
        with np.errstate(divide="ignore", invalid="ignore"):
            d = (wall.offset - origins @ wall.normal) / (dirs @ wall.normal)
        d[~(d > 0)] = np.nan
        pts = origins + d[:, None] * dirs
    ok = np.isfinite(d) & np.all(np.isfinite(pts), axis=1)
    return pts, ok


def _stripes_on_wall(
    det: Any, n_lasers: int, calibration: Calibration, wall: Plane
) -> list[tuple[FloatArray, FloatArray]]:
    """Per laser, the wall points (N, 3) of its detections and their pixels (N, 2) (rays that miss dropped)."""
    out = []
    lasers = np.asarray(det.laser)
    uv_all = np.asarray(det.uv, dtype=float).reshape(-1, 2)
    for li in range(n_lasers):
        uv = uv_all[lasers == li]
        if uv.shape[0] == 0:
            out.append((np.zeros((0, 3)), np.zeros((0, 2))))
            continue
        pts, ok = wall_points(uv, calibration, wall)
        out.append((pts[ok], uv[ok]))
    return out


def _distinct_walls(planes: Sequence[Plane], angle_tol_deg: float = 0.5, offset_tol_m: float = 0.002) -> int:
    """Number of different wall planes among ``planes`` (same normal within a tolerance and same offset)."""
    reps: list[Plane] = []
    for p in planes:
        if not any(
            normal_angle_deg(p.normal, q.normal) < angle_tol_deg and abs(p.offset - q.offset) < offset_tol_m
            for q in reps
        ):
            reps.append(p)
    return len(reps)
