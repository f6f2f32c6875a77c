"""Laser-plane calibration from images of a flat wall (paper section 2.6, made robust and self-checking).

Procedure, per image: find the stripe pixels with the sub-pixel extractor (laser assignment from the
extractor, using the input calibration), intersect their camera rays with the wall plane (eq. 30-31; through
the calibration's flat port, if it has one, the refracted rays in the water), and collect the 3D points per
laser. Per laser: RANSAC plane, then least-squares refits on the inliers
(:func:`~lrsensor.calib.planefit.robust_plane_fit`). All stripe points of one wall position lie on one line,
which does not fix a plane: with a single wall position the plane is fit through the laser's mounting point
(when one is given) or the calibration is refused.

The wall of an image is ``n . (p - o) = distance_m`` in the body frame: ``n`` is the unit wall normal
pointing from the camera towards the wall (default ``(1, 0, 0)``: a wall square to the body x axis, ahead),
and ``o`` is the body origin (``distance_from="body"``, default, the paper's x_b distance) or the camera's
optical centre (``distance_from="camera"``). In words: the wall's point nearest to ``o`` lies
``distance_m`` metres from ``o`` along ``n``. With a checkerboard on the wall, the wall plane of each image
is measured with ``solvePnP`` instead (:mod:`lrsensor.calib.board`).

Refusals raise :class:`LaserCalibrationError` (a :class:`~lrsensor.errors.CalibrationFitError`) with a
message that says what is wrong and where, and the report as far as it got.
"""

from __future__ import annotations

import datetime as _dt
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration, LaserPlane
from ..errors import CalibrationFitError, LrsensorError
from ..triangulation import intersect_rays_plane
from .board import BoardPose, BoardSpec, estimate_board_pose
from .planefit import Plane, RobustPlaneFit, normal_angle_deg, principal_spreads, robust_plane_fit, wall_plane

FloatArray = NDArray[np.float64]
ImageLike = str | os.PathLike[str] | NDArray[np.uint8]


#: Extractor depth limits of the second look for a stripe that the default band missed, metres.
WIDE_RANGE_OPTIONS: dict[str, float] = {"min_range_m": 0.1, "max_range_m": 20.0}


class LaserCalibrationError(CalibrationFitError):
    """The laser calibration was refused; ``report`` holds what was measured before the refusal (or None)."""

    def __init__(self, message: str, report: LaserCalibrationReport | None = None) -> None:
        super().__init__(message)
        self.report = report


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


def _mounting_point(laser: LaserPlane, config: LaserCalibrationConfig, index: int) -> FloatArray | None:
    for key in (laser.name, str(index)):
        if key in config.mounting:
            return np.asarray(config.mounting[key], dtype=float).reshape(3)
    if config.use_calibration_points:
        return laser.point_body
    return None


def _thresholds(config: LaserCalibrationConfig) -> dict[str, float]:
    return {
        "max_rms_mm": config.max_rms_m * 1000,
        "max_residual_mm": config.max_residual_m * 1000,
        "outlier_mm": config.outlier_m * 1000,
        "max_outlier_fraction": config.max_outlier_fraction,
        "min_points_per_image": float(config.min_points_per_image),
        "min_points": float(config.min_points),
        "min_spread_mm": config.min_spread_m * 1000,
        "max_reprojection_px": config.max_reprojection_px,
    }


def _progress(items: Sequence[WallImage], enabled: bool) -> Any:
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc="wall images", unit="img", disable=None)


def calibrate_lasers(
    walls: Sequence[WallImage],
    calibration: Calibration,
    config: LaserCalibrationConfig | None = None,
    *,
    extractor: Callable[..., Any] | None = None,
) -> LaserCalibrationResult:
    """Estimate every laser plane of ``calibration`` from images of a flat wall.

    Args:
        walls: the images and their walls (at least two wall positions, or mounting points; see module doc).
        calibration: input calibration: camera, mounting and nominal lasers (used for the extractor's bands,
            as the reference of the tilt, and as the orientation of the new normals).
        config: thresholds and options.
        extractor: optional extractor function (default: ``lrsensor.extract.get_extractor(config.method)``).

    Returns:
        The new calibration (camera part unchanged, new laser planes, a ``laser_calibration`` metadata block)
        and the report.

    Raises:
        LaserCalibrationError: any refusal; the message says what is wrong and what to do.
    """
    cfg = config or LaserCalibrationConfig()
    if cfg.distance_from not in ("body", "camera"):
        msg = f"distance_from must be 'body' or 'camera', got {cfg.distance_from!r}"
        raise LaserCalibrationError(msg)
    if not walls:
        msg = "no wall images given: pass at least two images of a wall at different distances"
        raise LaserCalibrationError(msg)
    from ..extract import check_image, get_extractor

    extract = extractor or get_extractor(cfg.method)
    names = [l.name for l in calibration.lasers]
    per_laser_pts: dict[int, list[FloatArray]] = {i: [] for i in range(len(names))}
    per_laser_uv: dict[int, list[FloatArray]] = {i: [] for i in range(len(names))}
    per_laser_grp: dict[int, list[NDArray[np.int_]]] = {i: [] for i in range(len(names))}
    walls_planes: list[Plane] = []
    image_reports: list[ImageReport] = []

    for gi, view in enumerate(_progress(list(walls), cfg.progress)):
        image = _load_image(view)
        try:
            image = check_image(image, calibration)
        except LrsensorError as err:
            msg = f"{view.label}: {err}"
            raise LaserCalibrationError(msg) from err
        wall, rep, _ = resolve_wall(view, image, calibration, cfg)
        options = dict(cfg.extractor_options)
        found = _stripes_on_wall(extract(image, calibration, **options), len(names), calibration, wall)
        counts = [p.shape[0] for p, _ in found]
        wide = cfg.method == "subpixel" and extractor is None and not ({"min_range_m", "max_range_m"} & set(options))
        if min(counts) < cfg.min_points_per_image and wide:
            # A strongly tilted laser can leave the band its nominal plane reaches for the default depth
            # limits: look again with generous limits before calling the stripe missing.
            retry = extract(image, calibration, **{**options, **WIDE_RANGE_OPTIONS})
            found2 = _stripes_on_wall(retry, len(names), calibration, wall)
            if min(p.shape[0] for p, _ in found2) > min(counts):
                found = found2
        missing: list[str] = []
        for li, lname in enumerate(names):
            pts, uv = found[li]
            rep.points[lname] = int(pts.shape[0])
            if pts.shape[0] < cfg.min_points_per_image:
                missing.append(f"no stripe of laser {lname!r} found ({pts.shape[0]} points on the wall)")
            per_laser_pts[li].append(pts)
            per_laser_uv[li].append(uv)
            per_laser_grp[li].append(np.full(pts.shape[0], gi, dtype=int))
        if missing:
            msg = (
                f"{view.label}: " + "; ".join(missing) + f"; need >= {cfg.min_points_per_image} points per "
                f"laser. Check that the lasers are on and visible on the wall, and that the stripes lie in the "
                f"image bands the input calibration expects for them"
            )
            raise LaserCalibrationError(msg, _partial_report([*image_reports, rep], cfg))
        walls_planes.append(wall)
        image_reports.append(rep)

    distinct = _distinct_walls(walls_planes)
    rng = np.random.default_rng(cfg.seed)
    fits: list[LaserFitReport] = []
    new_lasers: list[LaserPlane] = []
    residual_plots: dict[str, list[tuple[FloatArray, FloatArray, NDArray[np.bool_]]]] = {}
    problems: list[str] = []
    for li, laser in enumerate(calibration.lasers):
        pts = np.concatenate(per_laser_pts[li])
        uv = np.concatenate(per_laser_uv[li])
        grp = np.concatenate(per_laser_grp[li])
        mount = _mounting_point(laser, cfg, li)
        try:
            fit, constrained, spread = _fit_one_laser(pts, grp, distinct, laser, mount, cfg, rng)
        except LaserCalibrationError:
            raise
        except CalibrationFitError as err:
            msg = f"laser {laser.name!r}: {err}"
            raise LaserCalibrationError(msg) from err
        plane = fit.plane.oriented_like(laser.normal_body)
        anchor = mount if mount is not None else laser.point_body
        point = plane.project(anchor)
        rep_l = LaserFitReport(
            name=laser.name,
            points=int(pts.shape[0]),
            inliers=int(fit.inliers.sum()),
            rms_mm=fit.rms_m * 1000,
            max_mm=fit.max_abs_m * 1000,
            tilt_deg=normal_angle_deg(plane.normal, laser.normal_body),
            normal=(float(plane.normal[0]), float(plane.normal[1]), float(plane.normal[2])),
            point=(float(point[0]), float(point[1]), float(point[2])),
            constrained=constrained,
            mounting_offset_mm=abs(float(plane.signed_distance(anchor)[0])) * 1000,
            spread_mm=spread * 1000,
        )
        fits.append(rep_l)
        new_lasers.append(LaserPlane.make(laser.name, point.tolist(), plane.normal.tolist()))
        residual_plots[laser.name] = []
        for gi, im in enumerate(image_reports):
            m = grp == gi
            r = fit.residuals[m]
            inl = fit.inliers[m]
            im.inliers[laser.name] = int(inl.sum())
            im.rms_mm[laser.name] = float(np.sqrt(np.mean(r[inl] ** 2))) * 1000 if inl.any() else float("nan")
            im.bias_mm[laser.name] = float(np.mean(r[inl])) * 1000 if inl.any() else float("nan")
            residual_plots[laser.name].append((uv[m, 0], r, inl))
            # Far points: beyond the fit's gate AND the RANSAC distance (a tight gate only sharpens the fit).
            far_m = max(fit.gate_m, cfg.ransac_threshold_m)
            out_frac = float(np.mean(np.abs(r) > far_m)) if m.any() else 1.0
            if out_frac > cfg.max_outlier_fraction:
                problems.append(
                    f"{im.name}: {out_frac:.0%} of the {int(m.sum())} points of laser {laser.name!r} are more "
                    f"than {far_m * 1000:.2f} mm off the plane fitted to all images (allowed "
                    f"{cfg.max_outlier_fraction:.0%}); its wall distance or normal is probably wrong, or the "
                    f"stripe found is not this laser's"
                )
        if rep_l.inliers < cfg.min_points:
            problems.append(
                f"laser {laser.name!r}: only {rep_l.inliers} points fit the plane (need >= {cfg.min_points})"
            )
        if not rep_l.rms_mm <= cfg.max_rms_m * 1000:
            problems.append(
                f"laser {laser.name!r}: RMS residual {rep_l.rms_mm:.3f} mm exceeds the threshold "
                f"{cfg.max_rms_m * 1000:.3f} mm (--max-rms-mm): the wall distances/normals are inconsistent "
                f"with one laser plane, the wall is not flat, or the stripe is badly extracted"
            )
        if not rep_l.max_mm <= cfg.max_residual_m * 1000:
            problems.append(
                f"laser {laser.name!r}: largest residual {rep_l.max_mm:.3f} mm exceeds the threshold "
                f"{cfg.max_residual_m * 1000:.3f} mm (--max-residual-mm)"
            )

    angle = None
    if len(new_lasers) >= 2:
        angle = normal_angle_deg(new_lasers[0].normal_body, new_lasers[1].normal_body)
    notes: list[str] = []
    if distinct == 2 and not any(f.constrained for f in fits):
        notes.append(
            "only two wall positions: any two parallel stripe lines fit a plane exactly, so the residuals "
            "cannot reveal a wrong wall distance; a third distance makes the fit check itself"
        )
    report = LaserCalibrationReport(
        tuple(fits), tuple(image_reports), angle, _thresholds(cfg), residual_plots, tuple(notes)
    )
    if problems:
        msg = "calibration refused, no output written:\n  " + "\n  ".join(problems)
        raise LaserCalibrationError(msg, report)

    metadata = dict(calibration.metadata)
    metadata["laser_calibration"] = {
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "tool": "lrsensor calibrate lasers",
        "method": cfg.method,
        "distance_from": cfg.distance_from,
        "board": None
        if cfg.board is None
        else {"cols": cfg.board.cols, "rows": cfg.board.rows, "square_m": cfg.board.square_m},
        "mounting": {k: list(v) for k, v in cfg.mounting.items()},
        "use_calibration_points": cfg.use_calibration_points,
        "seed": cfg.seed,
        "nominal_lasers": [
            {"name": l.name, "point": list(l.point), "normal": list(l.normal)} for l in calibration.lasers
        ],
        **report.to_dict(),
    }
    return LaserCalibrationResult(calibration.with_lasers(new_lasers, metadata), report)


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


def _partial_report(images: list[ImageReport], cfg: LaserCalibrationConfig) -> LaserCalibrationReport:
    return LaserCalibrationReport((), tuple(images), None, _thresholds(cfg))


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


def _fit_one_laser(
    pts: FloatArray,
    grp: NDArray[np.int_],
    distinct_walls: int,
    laser: LaserPlane,
    mount: FloatArray | None,
    cfg: LaserCalibrationConfig,
    rng: np.random.Generator,
) -> tuple[RobustPlaneFit, bool, float]:
    """Fit one laser; returns ``(fit, constrained_by_mounting, spread_m)``."""
    kwargs: dict[str, Any] = {
        "ransac_threshold_m": cfg.ransac_threshold_m,
        "outlier_m": cfg.outlier_m,
    }
    fit: RobustPlaneFit | None = None
    spread = 0.0
    if distinct_walls >= 2:
        fit = robust_plane_fit(pts, rng, groups=grp, **kwargs)
        inl = pts[fit.inliers]
        spread = float(principal_spreads(inl)[1]) if inl.shape[0] >= 3 else 0.0
        if spread >= cfg.min_spread_m:
            return fit, False, spread
    else:
        spread = float(principal_spreads(pts)[1])
    if mount is None:
        if distinct_walls < 2:
            why = "all images show the wall at one position, and one wall position only gives a line"
        else:
            why = (
                f"its stripe points span only {spread * 1000:.1f} mm across the stripe (need >= "
                f"{cfg.min_spread_m * 1000:.0f} mm): the wall positions are too close together, so the points "
                f"form (nearly) a line"
            )
        msg = (
            f"laser {laser.name!r}: cannot fit a plane: {why}. Add a wall image at a second distance (e.g. "
            f"0.4, 0.5 and 0.6 m), or give the laser's mounting point (--mounting {laser.name}=x,y,z, or "
            f"--use-mounting to take it from the input calibration)"
        )
        raise LaserCalibrationError(msg)
    fit = robust_plane_fit(pts, rng, anchor=mount, **kwargs)
    inl = pts[fit.inliers]
    from .planefit import distance_to_line, line_fit

    c, u = line_fit(inl)
    lever = distance_to_line(mount, c, u)
    if lever < cfg.min_spread_m:
        msg = (
            f"laser {laser.name!r}: the mounting point {np.round(mount, 4).tolist()} lies only "
            f"{lever * 1000:.1f} mm from the stripe line on the wall; it cannot fix the plane. Use a wall at a "
            f"second distance instead"
        )
        raise LaserCalibrationError(msg)
    return fit, True, lever
