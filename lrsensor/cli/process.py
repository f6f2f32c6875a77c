"""``lrsensor process``: extract and triangulate the laser stripes of images into PLY point clouds.

    lrsensor process IMAGE --calib CALIB.json --out OUT.ply [--method paper|subpixel]
    lrsensor process IMAGE... --calib CALIB.json --out-dir DIR        # one DIR/<image stem>.ply per image
    lrsensor process IMAGE... --calib CALIB.json --out-dir DIR --overlay VIEWS   # + VIEWS/<stem>_overlay.png

The PLY is binary little-endian with float x, y, z (body frame, metres), uchar laser, float quality, u, v.
Exit codes: 0 all images written, 2 bad input (missing/unreadable image, wrong size, bad calibration; with
several images the others are still processed), 130 interrupted.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..extract import CHANNELS, DEFAULT_METHOD, METHODS, command_line_options


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="input image(s) (any format cv2.imread reads)")
    parser.add_argument("--calib", required=True, metavar="CALIB.json", help="calibration file (CONVENTIONS format)")
    out = parser.add_mutually_exclusive_group(required=True)
    out.add_argument("--out", metavar="OUT.ply", help="output PLY (exactly one image)")
    out.add_argument("--out-dir", metavar="DIR", help="output directory: one <image stem>.ply per image")
    parser.add_argument(
        "--method",
        choices=sorted(METHODS),
        default=DEFAULT_METHOD,
        help=f"stripe extractor: 'subpixel' (default, sub-pixel per column) or 'paper' (Algorithm 1); "
        f"default {DEFAULT_METHOD}",
    )
    parser.add_argument("--min-range-m", type=float, default=None, help="nearest depth searched, metres (0.2)")
    parser.add_argument("--max-range-m", type=float, default=None, help="farthest depth searched, metres (5.0)")
    parser.add_argument(
        "--channel",
        choices=CHANNELS,
        default=None,
        help="subpixel: what the stripe is fitted in; 'luma' for JPEG/MJPEG/H.264 frames (colour stored at half "
        "resolution), default 'green' (lossless frames)",
    )
    parser.add_argument(
        "--overlay",
        metavar="DIR",
        help="also write DIR/<image stem>_overlay.png: the image darkened, the stripe points drawn in their "
        "laser's colour (brighter = higher quality) and the search bands' outlines",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Process the images; returns the exit code."""
    import cv2
    from tqdm import tqdm

    from ..errors import ExtractionError, LrsensorError
    from ..ply import write_scan_ply
    from ..sensor import Sensor

    images = [Path(p) for p in args.images]
    if args.out is not None and len(images) != 1:
        msg = f"--out takes exactly one image, got {len(images)}; use --out-dir DIR for several"
        raise ExtractionError(msg)
    missing = [str(p) for p in images if not p.is_file()]
    if missing:
        msg = f"image file(s) not found: {', '.join(missing)}"
        raise ExtractionError(msg)
    if args.out_dir is not None:
        stems = [p.stem for p in images]
        dup = sorted({s for s in stems if stems.count(s) > 1})
        if dup:
            msg = f"several images share the stem(s) {dup}: their PLY files in --out-dir would collide"
            raise ExtractionError(msg)
    sensor = Sensor.from_file(args.calib)
    options = command_line_options(args.method, args.channel, args.min_range_m, args.max_range_m)
    failures = 0
    bar = tqdm(images, unit="img", disable=args.no_progress or len(images) < 2, file=sys.stderr)
    for path in bar:
        target = Path(args.out) if args.out is not None else Path(args.out_dir) / f"{path.stem}.ply"
        try:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                msg = f"{path}: cannot read image (not an image file, or an unsupported format)"
                raise ExtractionError(msg)
            try:
                scan = sensor.process(image, method=args.method, **options)
            except ExtractionError as err:
                msg = f"{path}: {err}"
                raise ExtractionError(msg) from err
            write_scan_ply(target, scan, comments=(f"source {path.name}",))
            if args.overlay is not None:
                _write_overlay(Path(args.overlay) / f"{path.stem}_overlay.png", image, scan, sensor, options)
        except LrsensorError as err:
            failures += 1
            if len(images) == 1:
                raise
            tqdm.write(f"lrsensor process: error: {err}", file=sys.stderr)
            continue
        if len(images) == 1:
            print(f"{path}: {len(scan)} points ({args.method}) -> {target}")
    if len(images) > 1:
        print(f"processed {len(images) - failures} of {len(images)} images -> {args.out_dir}")
    return 2 if failures else 0


def _write_overlay(path: Path, image: Any, scan: Any, sensor: Any, options: dict[str, Any]) -> None:
    """Write the picture of ``scan`` on ``image`` (:func:`lrsensor.overlay.draw_scan`) as a PNG at ``path``."""
    import cv2

    from ..errors import ExtractionError
    from ..overlay import draw_scan
    from ..sensor import range_limits

    lo, hi = range_limits(scan.method, options)
    picture = draw_scan(image, scan, sensor.calibration, lo, min(hi, 1e3))
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), picture):
        msg = f"{path}: cannot write the overlay image"
        raise ExtractionError(msg)
