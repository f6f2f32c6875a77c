"""``lrsensor calibrate``: laser planes from wall images, camera intrinsics and the flat port from checkerboards.

``lrsensor calibrate lasers --calib IN.json --wall IMAGE=DIST_M [--wall IMAGE=DIST_M ...] --out OUT.json``
``lrsensor calibrate camera IMAGE... --board COLSxROWS --square-m S --out OUT.json [--calib IN.json]``
``lrsensor calibrate port IMAGE... --board COLSxROWS --square-m S --calib IN.json --out OUT.json [--no-tilt]``

A refused calibration exits with code 2, prints why, and writes no output file.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

WALL_HELP = (
    "a wall image and the wall's distance in metres, IMAGE=DIST_M (repeat; at least two distances, e.g. 0.4, "
    "0.5, 0.6 m). The wall is the plane n . (p - o) = DIST_M: n is --wall-normal (from the camera towards "
    "the wall) and o the body origin (or the camera centre with --distance-from camera), i.e. the wall's "
    "point nearest to o lies DIST_M metres from o along n. IMAGE=DIST_M@NX,NY,NZ gives this image its own "
    "normal. With --board, IMAGE alone is enough"
)


def _floats3(text: str, what: str) -> tuple[float, float, float]:
    parts = [p for p in text.replace(" ", "").split(",") if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        vals = []
    if len(vals) != 3:
        msg = f"{what} must be three comma-separated numbers x,y,z, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return (vals[0], vals[1], vals[2])


def _parse_wall(text: str) -> tuple[str, float | None, tuple[float, float, float] | None]:
    """``IMAGE[=DIST_M[@NX,NY,NZ]]`` -> (image, distance or None, per-image normal or None)."""
    if "=" in text:
        image, _, rest = text.rpartition("=")
        dist_text, at, normal_text = rest.partition("@")
        try:
            dist = float(dist_text)
        except ValueError:
            return text, None, None
        return image, dist, _floats3(normal_text, f"--wall {text} normal") if at else None
    return text, None, None


def _parse_mounting(items: list[str]) -> dict[str, tuple[float, float, float]]:
    out: dict[str, tuple[float, float, float]] = {}
    for item in items:
        name, sep, xyz = item.partition("=")
        if not sep or not name:
            msg = f"--mounting must be NAME=x,y,z (metres, body frame), got {item!r}"
            raise argparse.ArgumentTypeError(msg)
        out[name] = _floats3(xyz, f"--mounting {name}")
    return out


def _parse_options(items: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            msg = f"--extract-option must be KEY=VALUE, got {item!r}"
            raise argparse.ArgumentTypeError(msg)
        try:
            out[key] = json.loads(value)
        except ValueError:
            out[key] = value
    return out


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    sub = parser.add_subparsers(dest="what", metavar="WHAT")
    sub.required = True
    las = sub.add_parser(
        "lasers",
        help="estimate the laser planes from images of a flat wall at known distances (or with a checkerboard)",
        description=(
            "Estimate every laser plane from images of a flat wall: stripe pixels (sub-pixel extractor, laser "
            "assignment from the input calibration) are intersected with the wall plane, and each laser plane "
            "is fit with RANSAC and a least-squares refit. The camera part of --calib is kept. Refuses (exit 2, "
            "no output file) when residuals exceed the thresholds, a stripe or board is missing, a wall is "
            "behind the camera, or only one wall distance is given without a mounting point."
        ),
    )
    # Let vectors such as "-1,0,0" or "-0.05" be values, not options (--wall-normal -1,0,0).
    if hasattr(las, "_negative_number_matcher"):
        las._negative_number_matcher = re.compile(r"^-[\d.]+([eE][-+]?\d+)?(,[-+\d.eE]+)*$")
    las.add_argument("--calib", required=True, type=Path, help="input calibration (camera, mounting, nominal lasers)")
    las.add_argument("--wall", action="append", required=True, metavar="IMAGE=DIST_M", help=WALL_HELP)
    las.add_argument("--out", required=True, type=Path, help="output calibration file (JSON, written only on success)")
    las.add_argument(
        "--wall-normal",
        default="1,0,0",
        metavar="NX,NY,NZ",
        help="wall normal in the body frame, from the camera towards the wall (default 1,0,0: a wall "
        "square to the body x axis, ahead)",
    )
    las.add_argument(
        "--distance-from",
        choices=("body", "camera"),
        default="body",
        help="measure DIST_M from the body origin (default, the paper's x_b) or the camera centre",
    )
    las.add_argument(
        "--max-rms-mm",
        type=float,
        default=2.0,
        help="refuse a laser whose RMS point-to-plane residual exceeds this (default 2.0 mm)",
    )
    las.add_argument(
        "--max-residual-mm",
        type=float,
        default=6.0,
        help="refuse a laser whose largest inlier residual exceeds this (default 6.0 mm)",
    )
    las.add_argument(
        "--outlier-mm",
        type=float,
        default=10.0,
        help="points farther than this from the plane are outliers, never fitted (default 10 mm)",
    )
    las.add_argument(
        "--max-outlier-fraction",
        type=float,
        default=0.5,
        help="refuse when more than this fraction of one image's points of a laser are outliers (default 0.5)",
    )
    las.add_argument(
        "--min-points",
        type=int,
        default=100,
        help="fewer stripe points of a laser in an image means no stripe found: refuse (default 100; a "
        "stripe across a wall gives about one point per image column)",
    )
    las.add_argument(
        "--min-spread-mm",
        type=float,
        default=10.0,
        help="the points of a laser must span this much across the stripe (walls at different "
        "distances), else one needs a mounting point (default 10 mm)",
    )
    las.add_argument(
        "--mounting",
        action="append",
        default=[],
        metavar="NAME=X,Y,Z",
        help="known mounting point of a laser, body frame, metres (e.g. top=0,0,-0.05); used to fix "
        "the plane when all walls are at one distance",
    )
    las.add_argument(
        "--use-mounting",
        action="store_true",
        help="use each input laser's 'point' as its mounting point when --mounting does not give one",
    )
    las.add_argument(
        "--board",
        default=None,
        metavar="COLSxROWS",
        help="measure each wall's pose with a checkerboard on it (inner corners, e.g. 9x6)",
    )
    las.add_argument("--square-m", type=float, default=None, help="checkerboard square size in metres (with --board)")
    las.add_argument(
        "--max-reproj-px",
        type=float,
        default=1.0,
        help="refuse a board pose whose RMS reprojection error exceeds this (default 1.0 px)",
    )
    las.add_argument("--method", default="subpixel", help="stripe extractor (default subpixel)")
    las.add_argument(
        "--extract-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra option for the extractor (value parsed as JSON when possible)",
    )
    las.add_argument("--seed", type=int, default=0, help="RANSAC seed (default 0)")
    las.add_argument("--plot", type=Path, default=None, help="write a PNG of the residuals per laser per image")
    las.add_argument("--report-json", type=Path, default=None, help="also write the report as JSON")

    cam = sub.add_parser(
        "camera",
        help="estimate the camera intrinsics from checkerboard images (cv2.calibrateCamera)",
        description=(
            "Estimate the camera intrinsics and distortion from images of a checkerboard. Lists the images where "
            "the board was not found; refuses (exit 2, no output) with fewer than --min-images boards or an RMS "
            "reprojection error above --max-rms-px. The lasers and mounting come from --calib, else the paper's "
            "nominal lasers."
        ),
    )
    cam.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="checkerboard images")
    cam.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    cam.add_argument("--square-m", required=True, type=float, help="square size in metres")
    cam.add_argument("--out", required=True, type=Path, help="output calibration file (JSON)")
    cam.add_argument("--calib", type=Path, default=None, help="keep the lasers and mounting of this calibration")
    cam.add_argument(
        "--baseline-m",
        type=float,
        default=0.1,
        help="baseline of the nominal lasers when --calib is not given (default 0.1 m)",
    )
    cam.add_argument("--min-images", type=int, default=3, help="refuse with fewer boards found (default 3)")
    cam.add_argument("--max-rms-px", type=float, default=1.0, help="refuse above this RMS error (default 1.0 px)")
    cam.add_argument("--fix-k3", action="store_true", help="keep k3 at 0 (default: estimate k1, k2, p1, p2, k3)")

    prt = sub.add_parser(
        "port",
        help="measure the flat port (distance_m, tilt) from checkerboard images taken in water",
        description=(
            "Measure the camera's flat port from images of a checkerboard in the water, in several poses: "
            "distance_m and (unless --no-tilt) the tilt of its normal, with every board pose, by least squares "
            "on the corners' exact projections through the port. --calib gives the in-air camera and a port "
            "whose thickness and indices are known (its distance and normal are the first guess). Refuses (exit "
            "2, no output) with fewer than --min-images boards, an RMS error above --max-rms-px, or a distance "
            "the views do not fix to --max-sigma-mm."
        ),
    )
    prt.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="checkerboard images taken in water")
    prt.add_argument("--board", required=True, metavar="COLSxROWS", help="inner corners, e.g. 9x6")
    prt.add_argument("--square-m", required=True, type=float, help="square size in metres")
    prt.add_argument("--calib", required=True, type=Path, help="calibration with the in-air camera and a port")
    prt.add_argument("--out", required=True, type=Path, help="output calibration file (JSON)")
    prt.add_argument("--no-tilt", action="store_true", help="keep the input port's normal (fit distance_m only)")
    prt.add_argument("--min-images", type=int, default=3, help="refuse with fewer boards found (default 3)")
    prt.add_argument("--max-rms-px", type=float, default=1.0, help="refuse above this RMS error (default 1.0 px)")
    prt.add_argument(
        "--max-sigma-mm", type=float, default=0.5, help="refuse when distance_m's standard deviation exceeds this"
    )


def run(args: argparse.Namespace) -> int:
    """Run the sub-command; exit code 0 on success, 2 on a refusal."""
    if args.what == "lasers":
        return _run_lasers(args)
    if args.what == "port":
        return _run_port(args)
    return _run_camera(args)


def _err(msg: str) -> int:
    print(f"lrsensor calibrate: error: {msg}", file=sys.stderr)
    return 2


def _refused(msg: str) -> int:
    """Print a refusal (always worded as one) and return exit code 2."""
    prefix = "calibration refused, no output written"
    return _err(msg if msg.startswith(prefix) else f"{prefix}: {msg}")


def _run_lasers(args: argparse.Namespace) -> int:
    import numpy as np

    from ..calib.board import BoardSpec
    from ..calib.lasers import LaserCalibrationConfig, LaserCalibrationError, WallImage, calibrate_lasers
    from ..calibration import Calibration

    try:
        normal = _floats3(args.wall_normal, "--wall-normal")
        mounting = _parse_mounting(args.mounting)
        options = _parse_options(args.extract_option)
    except argparse.ArgumentTypeError as err:
        return _err(str(err))
    if not np.linalg.norm(normal) > 0:
        return _err(f"--wall-normal must be a non-zero vector, got {args.wall_normal}")
    board = None
    if args.board is not None:
        if args.square_m is None:
            return _err("--board needs --square-m (the square size in metres)")
        board = BoardSpec.parse(args.board, args.square_m)
    walls = []
    for text in args.wall:
        try:
            image, dist, own_normal = _parse_wall(text)
        except argparse.ArgumentTypeError as err:
            return _err(str(err))
        if dist is None and board is None:
            return _err(f"--wall {text!r}: give IMAGE=DIST_M (metres), or use --board to measure the wall pose")
        walls.append(WallImage(image, dist, own_normal or normal, name=image))
    calibration = Calibration.load(args.calib)
    names = {l.name for l in calibration.lasers} | {str(i) for i in range(len(calibration.lasers))}
    unknown = sorted(set(mounting) - names)
    if unknown:
        return _err(
            f"--mounting names {unknown} are not lasers of {args.calib} ({[l.name for l in calibration.lasers]})"
        )
    config = LaserCalibrationConfig(
        method=args.method,
        extractor_options=options,
        max_rms_m=args.max_rms_mm / 1000,
        max_residual_m=args.max_residual_mm / 1000,
        outlier_m=args.outlier_mm / 1000,
        max_outlier_fraction=args.max_outlier_fraction,
        min_points_per_image=args.min_points,
        min_spread_m=args.min_spread_mm / 1000,
        mounting=mounting,
        use_calibration_points=args.use_mounting,
        distance_from=args.distance_from,
        board=board,
        max_reprojection_px=args.max_reproj_px,
        seed=args.seed,
        progress=True,
    )
    if args.out.exists():
        print(f"note: {args.out} exists and will be replaced on success", file=sys.stderr)
    try:
        result = calibrate_lasers(walls, calibration, config)
    except LaserCalibrationError as err:
        if err.report is not None and (err.report.lasers or err.report.images):
            print(err.report.format_table())
            if args.plot is not None and err.report.residuals:
                from ..calib.report import plot_laser_residuals

                plot_laser_residuals(err.report, args.plot)
                print(f"residual plot written to {args.plot}")
        return _refused(str(err))
    print(result.report.format_table())
    meta = dict(result.calibration.metadata)
    meta["laser_calibration"] = {**meta["laser_calibration"], "input_calibration": str(args.calib)}
    result.calibration.with_lasers(result.calibration.lasers, meta).save(args.out)
    print(f"calibration written to {args.out}")
    if args.plot is not None:
        from ..calib.report import plot_laser_residuals

        plot_laser_residuals(result.report, args.plot)
        print(f"residual plot written to {args.plot}")
    if args.report_json is not None:
        args.report_json.parent.mkdir(parents=True, exist_ok=True)
        args.report_json.write_text(json.dumps(result.report.to_dict(), indent=2) + "\n", encoding="utf-8")
    return 0


def _run_camera(args: argparse.Namespace) -> int:
    from ..calib.board import BoardSpec
    from ..calib.camera import CameraCalibrationError, calibrate_camera, image_names
    from ..calibration import Calibration

    board = BoardSpec.parse(args.board, args.square_m)
    base = Calibration.load(args.calib) if args.calib is not None else None
    missing = [str(p) for p in args.images if not p.is_file()]
    if missing:
        return _err("images not found: " + ", ".join(missing))
    try:
        result = calibrate_camera(
            image_names(args.images),
            board,
            base=base,
            min_images=args.min_images,
            max_rms_px=args.max_rms_px,
            fix_k3=args.fix_k3,
            progress=True,
        )
    except CameraCalibrationError as err:
        if err.not_found:
            print("board not found in: " + ", ".join(err.not_found))
        return _refused(str(err))
    if base is None:
        from dataclasses import replace

        nominal = Calibration.paper(args.baseline_m, result.camera.width, result.camera.height)
        cal = replace(result.calibration, lasers=nominal.lasers)
    else:
        cal = result.calibration
    print(result.format_table())
    if result.not_found:
        print("board not found in: " + ", ".join(result.not_found))
    cal.save(args.out)
    print(f"calibration written to {args.out}")
    return 0


def _run_port(args: argparse.Namespace) -> int:
    from ..calib.board import BoardSpec
    from ..calib.camera import image_names
    from ..calib.port import PortCalibrationError, calibrate_port
    from ..calibration import Calibration

    board = BoardSpec.parse(args.board, args.square_m)
    calibration = Calibration.load(args.calib)
    missing = [str(p) for p in args.images if not p.is_file()]
    if missing:
        return _err("images not found: " + ", ".join(missing))
    try:
        result = calibrate_port(
            image_names(args.images),
            board,
            calibration,
            fit_tilt=not args.no_tilt,
            min_images=args.min_images,
            max_rms_px=args.max_rms_px,
            max_distance_sigma_m=1e-3 * args.max_sigma_mm,
        )
    except PortCalibrationError as err:
        if err.not_found:
            print("board not found in: " + ", ".join(err.not_found))
        return _refused(str(err))
    print(result.format_table())
    result.calibration.save(args.out)
    print(f"calibration written to {args.out}")
    return 0
