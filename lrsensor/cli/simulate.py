"""``lrsensor simulate``: render simulated scenes and dives with ground truth.

Sub-commands::

    lrsensor simulate list
    lrsensor simulate scene NAME --out DIR [--seed N] [--width W --height H] [--water KIND] [--pose N,E,D,R,P,Y]
    lrsensor simulate wall --distance-m D [--normal NX,NY,NZ] [--calib TRUE.json] [--board] --out DIR
    lrsensor simulate dive --out DIR [--robot NAME] [--robot-index K --robots N] [--duration-s S]
                           [--rate-hz R] [--seed N] [--width W --height H]

``scene`` and ``wall`` write ``image.png``, ``calib.json`` (the TRUE calibration), ``truth.json`` (surfaces,
per-laser true points and pixels, boards) and ``truth_points.ply`` (x, y, z body frame, laser, surface).
``dive`` writes a recorded dive: ``<t_ns>.png`` frames, ``imu.csv``, ``calib.json``, ``truth.json``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

WATER_KINDS = ("scene", "clean", "default", "turbid", "cluttered")


def _size_flags(p: argparse.ArgumentParser, width: int, height: int) -> None:
    p.add_argument("--width", type=int, default=width, help=f"image width in pixels (default {width})")
    p.add_argument("--height", type=int, default=height, help=f"image height in pixels (default {height})")


def configure(parser: argparse.ArgumentParser) -> None:
    """Add the flags of this sub-command."""
    sub = parser.add_subparsers(dest="sim_command", metavar="WHAT")
    sub.required = True
    sub.add_parser("list", help="list the named scenes", description="List the named scenes.")

    p = sub.add_parser("scene", help="render a named scene", description="Render a named scene with truth.")
    p.add_argument("name", help="scene name (see 'lrsensor simulate list')")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--water", choices=WATER_KINDS, default="scene", help="water model (default: the scene's own)")
    p.add_argument(
        "--pose",
        help="vehicle pose for NED scenes (tank): NORTH_M,EAST_M,DOWN_M,ROLL_DEG,PITCH_DEG,YAW_DEG",
    )
    _size_flags(p, 1920, 1080)

    p = sub.add_parser(
        "wall", help="render a flat wall at a distance", description="Render one flat wall n.p = D in front."
    )
    p.add_argument("--distance-m", type=float, required=True, help="wall distance along its normal, metres")
    p.add_argument("--normal", default="1,0,0", help="wall normal NX,NY,NZ in the body frame (default 1,0,0)")
    p.add_argument("--calib", type=Path, help="TRUE calibration to render with (default: the paper's)")
    p.add_argument("--tilted", action="store_true", help="use the built-in tilted-laser true calibration")
    p.add_argument("--board", action="store_true", help="put a 9x6 checkerboard (5 cm squares) on the wall")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--water", choices=WATER_KINDS[1:], default="default", help="water model (default: default)")
    _size_flags(p, 1920, 1080)

    p = sub.add_parser(
        "dive", help="record a simulated dive in the tank", description="Record a simulated dive in the tank."
    )
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--robot", default="rov1", help="robot name (default rov1)")
    p.add_argument("--robot-index", type=int, default=None, help="which trajectory (default: from the name)")
    p.add_argument("--robots", type=int, default=3, help="number of robots in the fleet (default 3)")
    p.add_argument("--duration-s", type=float, default=10.0, help="dive length, seconds (default 10)")
    p.add_argument("--rate-hz", type=float, default=5.0, help="frame rate, Hz (default 5)")
    p.add_argument("--imu-rate-hz", type=float, default=100.0, help="IMU rate, Hz (default 100)")
    p.add_argument("--seed", type=int, default=None, help="random seed (default: from the robot index)")
    p.add_argument("--water", choices=WATER_KINDS[1:], default="default", help="water model (default: default)")
    p.add_argument("--t0-ns", type=int, default=None, help="time of the first frame, ns since the epoch")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    _size_flags(p, 960, 540)


def _water(kind: str, default: Any) -> Any:
    from ..sim import WaterModel

    return {
        "scene": default,
        "clean": WaterModel.clean(),
        "default": WaterModel.default(),
        "turbid": WaterModel.turbid(),
        "cluttered": WaterModel.cluttered(),
    }[kind]


def write_ply(path: Path, points: Any, laser: Any, surface: Any) -> None:
    """Binary little-endian PLY with float x, y, z, uchar laser, int surface."""
    import numpy as np

    pts = np.asarray(points, dtype="<f4").reshape(-1, 3)
    rec = np.zeros(pts.shape[0], dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("laser", "u1"), ("surface", "<i4")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["laser"] = np.asarray(laser)
    rec["surface"] = np.asarray(surface)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment lrsensor simulate: true laser hits, body frame, metres\n"
        f"element vertex {pts.shape[0]}\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar laser\nproperty int surface\nend_header\n"
    )
    with path.open("wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(rec.tobytes())


def _write_render(out: Path, r: Any, setup: Any) -> None:
    import json

    import cv2
    import numpy as np

    out.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out / "image.png"), r.image):
        from ..errors import SimulationError

        msg = f"could not write {out / 'image.png'}"
        raise SimulationError(msg)
    r.calibration.save(out / "calib.json")
    truth = r.truth.to_dict(max_points=4000)
    truth["scene"] = setup.name
    truth["description"] = setup.description
    if setup.wall_distance_m is not None:
        truth["wall"] = {"distance_m": setup.wall_distance_m, "normal_body": list(setup.wall_normal)}
    for lt, d in zip(r.truth.lasers, truth["lasers"], strict=True):
        cols = r.truth.visible_columns(lt.index)
        v = r.truth.v_at_columns(lt.index, cols)
        d["columns"] = {"u": cols.tolist(), "v": np.round(v, 5).tolist()}
    (out / "truth.json").write_text(json.dumps(truth) + "\n", encoding="utf-8")
    pts, las = r.truth.all_points()
    sid = np.concatenate([lt.surface_id for lt in r.truth.lasers]) if r.truth.lasers else np.zeros(0)
    write_ply(out / "truth_points.ply", pts, las, sid)


def run(args: argparse.Namespace) -> int:
    """Run the sub-command."""
    from ..sim import SCENES, named_scene

    if args.sim_command == "list":
        for name in SCENES:
            setup = named_scene(name, 192, 108)
            print(f"{name:18s} {setup.description}")
        return 0
    if args.sim_command == "scene":
        setup = named_scene(args.name, args.width, args.height)
        setup = setup.with_(water=_water(args.water, setup.water))
        if args.pose:
            setup = setup.with_(pose=_parse_pose(args.pose))
        r = setup.render(seed=args.seed)
        _write_render(args.out, r, setup)
        n = sum(len(lt) for lt in r.truth.lasers)
        print(f"{args.name}: wrote {args.out}/image.png, calib.json, truth.json, truth_points.ply ({n} points)")
        return 0
    if args.sim_command == "wall":
        return _run_wall(args)
    if args.sim_command == "dive":
        return _run_dive(args)
    print(f"lrsensor simulate: unknown command {args.sim_command!r}", file=sys.stderr)
    return 2


def _parse_pose(text: str) -> Any:
    import math

    from ..errors import SimulationError
    from ..frames import Pose

    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 6:
        msg = f"--pose must be NORTH_M,EAST_M,DOWN_M,ROLL_DEG,PITCH_DEG,YAW_DEG (6 numbers), got {text!r}"
        raise SimulationError(msg)
    return Pose(v[0], v[1], v[2], math.radians(v[3]), math.radians(v[4]), math.radians(v[5]))


def _run_wall(args: argparse.Namespace) -> int:
    from ..calibration import Calibration
    from ..errors import SimulationError
    from ..sim import checkerboard_wall_scene, paper_calibration, scale_calibration, tilted_calibration, wall_scene

    try:
        normal = [float(x) for x in args.normal.split(",")]
    except ValueError:
        normal = []
    if len(normal) != 3:
        msg = f"--normal must be three numbers NX,NY,NZ, got {args.normal!r}"
        raise SimulationError(msg)
    if args.calib is not None:
        calib = Calibration.load(args.calib)
    else:
        calib = paper_calibration(args.width, args.height)
        if args.tilted:
            calib = tilted_calibration(calib)
    if (calib.camera.width, calib.camera.height) != (args.width, args.height) and args.calib is None:
        calib = scale_calibration(calib, args.width, args.height)
    water = _water(args.water, None)
    if args.board:
        setup = checkerboard_wall_scene(args.distance_m, normal, calibration=calib)
        setup = setup.with_(water=water.with_(ambient_dn=max(water.ambient_dn, 120.0)))
    else:
        setup = wall_scene(args.distance_m, normal, calibration=calib, water=water)
    r = setup.render(seed=args.seed)
    _write_render(args.out, r, setup)
    print(f"wall at {args.distance_m:g} m: wrote {args.out}/image.png, calib.json, truth.json, truth_points.ply")
    return 0


def _run_dive(args: argparse.Namespace) -> int:
    import re

    from ..sim.dive import DEFAULT_T0_NS, record_dive

    index = args.robot_index
    if index is None:
        m = re.search(r"(\d+)$", args.robot)
        index = max(int(m.group(1)) - 1, 0) if m else 0
    robots = max(args.robots, index + 1)
    seed = args.seed if args.seed is not None else 1000 + index
    rec = record_dive(
        args.out,
        robot=args.robot,
        robot_index=index,
        n_robots=robots,
        duration_s=args.duration_s,
        rate_hz=args.rate_hz,
        imu_rate_hz=args.imu_rate_hz,
        width=args.width,
        height=args.height,
        seed=seed,
        water=_water(args.water, None),
        t0_ns=DEFAULT_T0_NS if args.t0_ns is None else args.t0_ns,
        progress=not args.no_progress,
    )
    print(f"dive {args.robot}: wrote {len(rec.frames)} frames, imu.csv, calib.json, truth.json to {rec.out_dir}")
    return 0
