"""Calibration fitting: laser planes from wall images, wall pose from a checkerboard, camera intrinsics.

Loading and validating calibration files stays in :mod:`lrsensor.calibration` (one place); this package
only estimates calibrations and reports their residuals.

>>> from lrsensor.calib import WallImage, calibrate_lasers          # doctest: +SKIP
>>> result = calibrate_lasers([WallImage("w40.png", 0.4), WallImage("w50.png", 0.5)], calibration)
>>> result.calibration.save("calib.json"); print(result.report.format_table())
"""

from __future__ import annotations

from .board import BoardPose, BoardSpec, estimate_board_pose, find_board_corners
from .camera import CameraCalibrationError, CameraCalibrationResult, calibrate_camera
from .laser_records import (
    ImageReport,
    LaserCalibrationConfig,
    LaserCalibrationError,
    LaserCalibrationReport,
    LaserCalibrationResult,
    LaserFitReport,
)
from .lasers import calibrate_lasers
from .planefit import Plane, fit_plane_lsq, fit_plane_through_point, ransac_plane, robust_plane_fit, wall_plane
from .port import PortCalibrationError, PortCalibrationResult, calibrate_port
from .walls import WallImage, wall_points

__all__ = [
    "BoardPose",
    "BoardSpec",
    "CameraCalibrationError",
    "CameraCalibrationResult",
    "ImageReport",
    "LaserCalibrationConfig",
    "LaserCalibrationError",
    "LaserCalibrationReport",
    "LaserCalibrationResult",
    "LaserFitReport",
    "Plane",
    "PortCalibrationError",
    "PortCalibrationResult",
    "WallImage",
    "calibrate_camera",
    "calibrate_lasers",
    "calibrate_port",
    "estimate_board_pose",
    "find_board_corners",
    "fit_plane_lsq",
    "fit_plane_through_point",
    "ransac_plane",
    "robust_plane_fit",
    "wall_plane",
    "wall_points",
]
