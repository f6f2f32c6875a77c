"""The laser calibration's records: its options, what it reports, what it returns and how it refuses.

:class:`LaserCalibrationConfig` holds the thresholds and options of
:func:`~lrsensor.calib.lasers.calibrate_lasers`; :class:`ImageReport` (one per image) and :class:`LaserFitReport`
(one per laser) make up :class:`LaserCalibrationReport`, which renders itself as JSON (the calibration file's
``laser_calibration`` block) and as plain-text tables; :class:`LaserCalibrationResult` is an accepted
calibration with its report, and :class:`LaserCalibrationError` a refused one with the report as far as it got.
Plain data: no image, no extractor, no fit here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import CalibrationFitError
from .board import BoardSpec

FloatArray = NDArray[np.float64]


class LaserCalibrationError(CalibrationFitError):
    """The laser calibration was refused; ``report`` holds what was measured before the refusal (or None)."""

    def __init__(self, message: str, report: LaserCalibrationReport | None = None) -> None:
        super().__init__(message)
        self.report = report


@dataclass(frozen=True)
class LaserCalibrationConfig:
    """Thresholds and options of :func:`calibrate_lasers` (units in the names).

    Attributes:
        method: stripe extractor name (``lrsensor.extract``).
        extractor_options: keyword options passed to the extractor.
        max_rms_m: refuse a laser whose inlier RMS residual exceeds this.
        max_residual_m: refuse a laser whose largest inlier residual exceeds this.
        outlier_m: points farther than this from the plane are outliers (never used in the fit).
        ransac_threshold_m: RANSAC inlier distance.
        max_outlier_fraction: refuse when more than this fraction of one image's points of a laser are outliers
            (a wrong distance or wall normal for that image, or a stripe that is not the laser's).
        min_points_per_image: fewer stripe points of a laser in an image means "no stripe found": refuse.
        min_points: refuse a laser fit on fewer inlier points than this.
        min_spread_m: the inliers must span at least this (RMS) across the stripe direction, else they form
            a line (one wall position) and the mounting point is needed.
        mounting: known laser mounting points (body frame, metres) by laser name; used as a constraint when the
            points of a laser lie on a line (a single wall position).
        use_calibration_points: use each input laser's ``point`` as its mounting point when none is given.
        distance_from: ``"body"`` (distances from the body origin) or ``"camera"`` (from the optical centre).
        board: checkerboard on the wall; when set, each image's wall plane comes from the board.
        max_reprojection_px: refuse a board pose whose RMS corner reprojection error exceeds this.
        seed: RANSAC seed (results are deterministic).
        progress: show a tqdm progress bar over the images.
    """

    method: str = "subpixel"
    extractor_options: Mapping[str, Any] = field(default_factory=dict)
    max_rms_m: float = 0.002
    max_residual_m: float = 0.006
    outlier_m: float = 0.010
    ransac_threshold_m: float = 0.002
    max_outlier_fraction: float = 0.5
    min_points_per_image: int = 100
    min_points: int = 50
    min_spread_m: float = 0.01
    mounting: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)
    use_calibration_points: bool = False
    distance_from: str = "body"
    board: BoardSpec | None = None
    max_reprojection_px: float = 1.0
    seed: int = 0
    progress: bool = False


@dataclass(frozen=True)
class ImageReport:
    """What one image gave: its wall plane and, per laser, points and residuals.

    Attributes:
        name: the image's name.
        wall_normal: wall normal in the body frame (3,).
        wall_distance_m: distance of the wall from the camera's optical centre along the normal, metres.
        wall_source: ``"distance"`` (given) or ``"board"`` (measured with a checkerboard).
        given_distance_m: the distance the user gave (or None).
        board_reprojection_px: RMS corner reprojection error when the board was used, else None.
        points: per laser name, number of stripe points on the wall.
        inliers: per laser name, points used in the fit.
        rms_mm: per laser name, RMS of the inlier residuals, mm.
        bias_mm: per laser name, mean signed inlier residual, mm (a wrong distance shows up here).
    """

    name: str
    wall_normal: tuple[float, float, float]
    wall_distance_m: float
    wall_source: str
    given_distance_m: float | None
    board_reprojection_px: float | None
    points: dict[str, int] = field(default_factory=dict)
    inliers: dict[str, int] = field(default_factory=dict)
    rms_mm: dict[str, float] = field(default_factory=dict)
    bias_mm: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class LaserFitReport:
    """One laser's fit.

    Attributes:
        name: laser name.
        points: stripe points collected over all images.
        inliers: points used in the final fit.
        rms_mm, max_mm: RMS and largest absolute inlier residual, mm.
        tilt_deg: angle between the fitted and the input (nominal) plane, degrees.
        normal: fitted unit normal (body frame), oriented like the nominal one.
        point: the plane's point: the mounting (or input) point projected onto the plane, metres.
        constrained: True when the fit was forced through the mounting point (a single wall position).
        mounting_offset_mm: distance of the mounting / input point from the fitted plane, mm.
        spread_mm: RMS spread of the inliers across the stripe direction, mm (the fit's lever arm).
    """

    name: str
    points: int
    inliers: int
    rms_mm: float
    max_mm: float
    tilt_deg: float
    normal: tuple[float, float, float]
    point: tuple[float, float, float]
    constrained: bool
    mounting_offset_mm: float
    spread_mm: float


def _json_float(value: float, digits: int) -> float | None:
    """``value`` rounded, or None when not finite (calibration files must hold finite numbers only)."""
    return round(float(value), digits) if np.isfinite(value) else None


@dataclass(frozen=True)
class LaserCalibrationReport:
    """The full report: per laser, per image, and the angle between the lasers."""

    lasers: tuple[LaserFitReport, ...]
    images: tuple[ImageReport, ...]
    angle_between_deg: float | None
    thresholds: dict[str, float]
    residuals: dict[str, list[tuple[FloatArray, FloatArray, NDArray[np.bool_]]]] = field(
        default_factory=dict, compare=False, repr=False
    )
    """Per laser name, per image: ``(u_px (N,), residual_m (N,), inlier mask (N,))`` for plots."""
    notes: tuple[str, ...] = ()
    """Warnings that do not refuse the calibration (e.g. too few wall positions for a self-check)."""

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no per-point arrays)."""
        return {
            "lasers": [
                {
                    "name": l.name,
                    "points": l.points,
                    "inliers": l.inliers,
                    "rms_mm": _json_float(l.rms_mm, 5),
                    "max_mm": _json_float(l.max_mm, 5),
                    "tilt_deg": round(l.tilt_deg, 6),
                    "constrained_by_mounting": l.constrained,
                    "mounting_offset_mm": round(l.mounting_offset_mm, 4),
                    "spread_mm": round(l.spread_mm, 3),
                }
                for l in self.lasers
            ],
            "angle_between_lasers_deg": None if self.angle_between_deg is None else round(self.angle_between_deg, 6),
            "images": [
                {
                    "name": im.name,
                    "wall_source": im.wall_source,
                    "wall_normal": [round(x, 8) for x in im.wall_normal],
                    "wall_distance_m": round(im.wall_distance_m, 6),
                    "given_distance_m": im.given_distance_m,
                    "board_reprojection_px": (
                        None if im.board_reprojection_px is None else round(im.board_reprojection_px, 4)
                    ),
                    "points": im.points,
                    "inliers": im.inliers,
                    "rms_mm": {k: _json_float(v, 5) for k, v in im.rms_mm.items()},
                    "bias_mm": {k: _json_float(v, 5) for k, v in im.bias_mm.items()},
                }
                for im in self.images
            ],
            "thresholds": self.thresholds,
            "notes": list(self.notes),
        }

    def format_table(self) -> str:
        """The report as plain-text tables (per laser, then per image)."""
        lines = [
            f"{'laser':<10} {'points':>7} {'used':>7} {'RMS mm':>8} {'max mm':>8} {'tilt deg':>9} "
            f"{'spread mm':>10} {'fit':>12}"
        ]
        for l in self.lasers:
            fit = "via mounting" if l.constrained else "free"
            lines.append(
                f"{l.name:<10} {l.points:>7d} {l.inliers:>7d} {l.rms_mm:>8.3f} {l.max_mm:>8.3f} "
                f"{l.tilt_deg:>9.4f} {l.spread_mm:>10.1f} {fit:>12}"
            )
        if self.angle_between_deg is not None:
            lines.append(f"angle between the laser planes: {self.angle_between_deg:.4f} deg")
        if self.images:
            names = [l.name for l in self.lasers] or sorted({k for im in self.images for k in im.points})
            head = f"{'image':<32} {'wall':>9} {'dist m':>8}"
            for n in names:
                head += f" {n + ' pts':>10} {n + ' rms':>9} {n + ' bias':>9}"
            lines.append("")
            lines.append(head)
            for im in self.images:
                label = im.name if len(im.name) <= 32 else "..." + im.name[-29:]
                row = f"{label:<32} {im.wall_source:>9} {im.wall_distance_m:>8.4f}"
                for n in names:
                    row += (
                        f" {im.points.get(n, 0):>10d} {im.rms_mm.get(n, float('nan')):>9.3f}"
                        f" {im.bias_mm.get(n, float('nan')):>9.3f}"
                    )
                lines.append(row)
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


@dataclass(frozen=True)
class LaserCalibrationResult:
    """A calibration accepted by :func:`calibrate_lasers`: the new calibration and its report."""

    calibration: Calibration
    report: LaserCalibrationReport
