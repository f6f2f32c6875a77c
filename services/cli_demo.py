"""``lrsensor demo``: an in-process fleet of simulated ROVs and a base station (the README's main command)."""

from __future__ import annotations

import argparse
from pathlib import Path


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of ``lrsensor demo``."""
    parser.add_argument("--robots", type=int, default=3, help="number of simulated ROVs (default 3)")
    parser.add_argument("--duration-s", type=float, default=45.0, help="wall-clock dive time (default 45 s)")
    parser.add_argument("--size", default="640x360", help="simulated camera size WxH (default 640x360)")
    parser.add_argument("--rate-hz", type=float, default=2.0, help="simulated frame rate (default 2 Hz)")
    parser.add_argument("--speed-m-s", type=float, default=0.4, help="vehicle speed (default 0.4 m/s)")
    parser.add_argument("--out", default="lrsensor-demo", help="output folder (map.json, status.json, map.png)")
    parser.add_argument("--state", default=None, help="base-station state folder (default: a temporary one)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the simulation")
    parser.add_argument("--no-progress", action="store_true", help="no live progress display")
    parser.add_argument(
        "--nav",
        choices=("on", "off"),
        default="off",
        # the demo's robots have good simulated poses: correcting them from the scans costs centimetres there
        # (docs/navigation.md); navigation is for poses that drift
        help="correct the poses from the scans at the base (default off: the simulated poses are good)",
    )


def run(args: argparse.Namespace) -> int:
    """Run the demo; 0 when every published cloud reached the base station."""
    from .demo import DemoConfig, format_summary, run_demo
    from .errors import ServiceError

    w, sep, h = args.size.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit():
        msg = f"--size must be WxH, e.g. 640x360, got {args.size!r}"
        raise ServiceError(msg)
    cfg = DemoConfig(
        n_robots=args.robots,
        duration_s=args.duration_s,
        width=int(w),
        height=int(h),
        rate_hz=args.rate_hz,
        speed_m_s=args.speed_m_s,
        out_dir=Path(args.out),
        state_dir=Path(args.state) if args.state else None,
        seed=args.seed,
        progress=not args.no_progress,
        navigation=args.nav == "on",
    )
    print(
        f"lrsensor demo: {cfg.n_robots} simulated ROVs dive the tank for {cfg.duration_s:.0f} s "
        f"({cfg.width}x{cfg.height} camera, the paper's scaled), base station building the shared map ...",
        flush=True,
    )
    from .signals import stop_on_signals

    with stop_on_signals() as stop:  # SIGINT/SIGTERM end the dives early; sessions close, summary printed
        res = run_demo(cfg, stop)
    print(format_summary(res, cfg), flush=True)
    return 0 if res.ok else 1
