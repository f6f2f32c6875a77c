"""``lrsensor range``: the paper's range theory (eq. 33-34) as a table and as the Fig. 9 / Fig. 10 plot."""

from __future__ import annotations

import argparse
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    parser.add_argument(
        "--baseline-m",
        type=float,
        nargs="+",
        default=[0.1, 0.2, 0.3, 0.4, 0.5],
        help="baselines b in metres (default: the paper's 0.1 .. 0.5)",
    )
    parser.add_argument(
        "--distance-m",
        type=float,
        nargs="+",
        default=[0.3, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0],
        help="distances of the table rows in metres",
    )
    parser.add_argument("--focal-m", type=float, default=0.009238, help="focal length f in metres (paper: 0.009238)")
    parser.add_argument("--sensor-height-m", type=float, default=0.018, help="sensor height h_s in metres (0.018)")
    parser.add_argument("--rows", type=int, default=1080, help="vertical resolution h_p in pixels (1080)")
    parser.add_argument("--step-m", type=float, default=0.1, help="range step for the pixel change column (0.1 m)")
    parser.add_argument("--plot", type=Path, default=None, help="write the Fig. 9 / Fig. 10 plot to this PNG")
    parser.add_argument("--max-distance-m", type=float, default=8.0, help="x axis extent of the plot")


def run(args: argparse.Namespace) -> int:
    """Print the table (and write the plot)."""
    from ..range_theory import RangeCamera, max_range, range_table

    if any(b <= 0 for b in args.baseline_m) or any(x <= 0 for x in args.distance_m):
        print("lrsensor range: baselines and distances must be positive")
        return 2
    cam = RangeCamera(args.focal_m, args.sensor_height_m, args.rows)
    print(
        f"camera: f = {cam.focal_m * 1000:.3f} mm, h_s = {cam.sensor_height_m * 1000:.1f} mm, "
        f"h_p = {cam.rows_px} px -> f = {cam.focal_px:.1f} px"
    )
    step_cm = args.step_m * 100
    print(f"{'b [m]':>6} {'x [m]':>6} {'v [px]':>8} {f'dv/{step_cm:g}cm [px]':>14} {'dx/px [mm]':>11}")
    for row in range_table(args.distance_m, args.baseline_m, cam, args.step_m):
        print(
            f"{row['baseline_m']:6.2f} {row['distance_m']:6.2f} {row['pixel_px']:8.2f} "
            f"{row['change_px_per_step']:14.3f} {row['resolution_m_per_px'] * 1000:11.2f}"
        )
    print()
    print("largest range where a step still moves the stripe by >= 1 px:")
    for b in args.baseline_m:
        print(f"  b = {b:.2f} m: {max_range(b, 1.0, args.step_m, cam):.2f} m")
    if args.plot is not None:
        from ..plots import plot_range_theory

        plot_range_theory(args.plot, args.baseline_m, cam, args.step_m, args.max_distance_m)
        print(f"plot written to {args.plot}")
    return 0
