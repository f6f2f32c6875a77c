"""Laser-plane calibration from images of a flat wall (paper section 2.6, made robust and self-checking).

Procedure, per image: find the stripe pixels with the sub-pixel extractor (laser assignment from the
extractor, using the input calibration), intersect their camera rays with the wall plane (eq. 30-31; through
the calibration's flat port, if it has one, the refracted rays in the water), and collect the 3D points per
laser. Per laser: RANSAC plane, then least-squares refits on the inliers
(:func:`~lrsensor.calib.planefit.robust_plane_fit`). All stripe points of one wall position lie on one line,
which does not fix a plane: with a single wall position the plane is fit through the laser's mounting point
(when one is given) or the calibration is refused.

The wall of an image is given by its distance and normal, or measured with a checkerboard on it: see
:mod:`lrsensor.calib.walls`.

Refusals raise :class:`LaserCalibrationError` (a :class:`~lrsensor.errors.CalibrationFitError`) with a
message that says what is wrong and where, and the report as far as it got.

Layout: this module is the procedure (:func:`calibrate_lasers`, the fit of one laser, the thresholds it
reports) and re-exports the rest, so that ``lrsensor.calib.lasers`` stays the name callers import:

* :mod:`lrsensor.calib.laser_records`: the options (:class:`LaserCalibrationConfig`), the reports per image
  and per laser, the result and the refusal;
* :mod:`lrsensor.calib.walls`: each image's wall (:class:`WallImage`, :func:`resolve_wall`) and the stripe
  pixels' points on it (:func:`wall_points`).
"""

from __future__ import annotations

import datetime as _dt
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration, LaserPlane
from ..errors import CalibrationFitError, LrsensorError
from .laser_records import (
    FloatArray,
    ImageReport,
    LaserCalibrationConfig,
    LaserCalibrationError,
    LaserCalibrationReport,
    LaserCalibrationResult,
    LaserFitReport,
)
from .planefit import Plane, RobustPlaneFit, normal_angle_deg, principal_spreads, robust_plane_fit
from .walls import (
    ImageLike,
    WallImage,
    _distinct_walls,
    _load_image,
    _stripes_on_wall,
    resolve_wall,
    wall_points,
)

#: Extractor depth limits of the second look for a stripe that the default band missed, metres.
WIDE_RANGE_OPTIONS: dict[str, float] = {"min_range_m": 0.1, "max_range_m": 20.0}


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


def _partial_report(images: list[ImageReport], cfg: LaserCalibrationConfig) -> LaserCalibrationReport:
    return LaserCalibrationReport((), tuple(images), None, _thresholds(cfg))


def _progress(items: Sequence[WallImage], enabled: bool) -> Any:
    if not enabled:
        return items
    from tqdm import tqdm

    return tqdm(items, desc="wall images", unit="img", disable=None)


__all__ = [
    "WIDE_RANGE_OPTIONS",
    "FloatArray",
    "ImageLike",
    "ImageReport",
    "LaserCalibrationConfig",
    "LaserCalibrationError",
    "LaserCalibrationReport",
    "LaserCalibrationResult",
    "LaserFitReport",
    "WallImage",
    "calibrate_lasers",
    "resolve_wall",
    "wall_points",
]
