"""``bench_nav``'s simulated dives as recorded dive folders, for ``lrsensor rov --imu csv:FILE`` (issue 27).

The in-process benchmarks (``bench_nav``, ``diag_fleet_heading --replay``) feed :func:`mapping.synth.simulate_dive`'s
ray-traced clouds straight into the map. The acceptance check runs the same dives through ``lrsensor base`` and
one ``lrsensor rov`` per robot, which reads images and a pose log. :func:`write_fleet` renders each robot's frames
of the very same dive (the same plans, the same seed, the same navigation noise, :func:`mapping.synth.tank` drawn
by :func:`lrsensor.sim.render.render` at the true poses) into a folder the ROV reads as a recorded dive:

- ``<t_ns>.png``: the frames (BGR), named by their capture time (ns since the epoch);
- ``imu.csv``: one row per frame, the dive's *estimated* pose at that time (``DiveFrame.pose_est``: attitude,
  depth, and ``north_m``/``east_m`` only where the navigation has a fix, empty otherwise: a ``depth-only`` dive's
  launch row alone has one); the ROV's pose track then gives each frame exactly the pose the in-process replay
  uses, so the only differences between the two roads are the clouds (extracted from images instead of traced
  rays) and the road itself;
- ``calib.json``: the true calibration of the rendered camera.

:func:`extracted_frames` gives the in-process replay the clouds the ROVs will send: each image through
:class:`lrsensor.Sensor` (the ROV's extractor and triangulation), cached beside the images as ``clouds.npz``.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.sim.dive import IMU_CSV_HEADER
from mapping.synth import DiveFrame, Scene, simulate_dive, tank, three_rov_plans

#: Frame rate of bench_nav's dives (Hz) and its traced rays per laser.
RATE_HZ = 10.0
N_RAYS = 400


def dive_frames(mode: str, seed: int, seconds: float) -> list[DiveFrame]:
    """``bench_nav``'s 3-robot dive of ``mode`` (``good``, ``drift``, ``depth-only``): frames in capture order."""
    return simulate_dive(
        tank(), three_rov_plans(), duration_s=seconds, rate_hz=RATE_HZ, n_rays=N_RAYS, seed=seed, navigation=mode
    )


def render_scene(scene: Scene) -> Any:
    """:func:`mapping.synth.tank`'s faces as a :class:`lrsensor.sim.scene.Scene` in NED (rectangles; each normal,
    ``axis_u x axis_v``, into the water as the face's)."""
    from lrsensor.sim.scene import Rectangle
    from lrsensor.sim.scene import Scene as SimScene

    rects = [
        Rectangle.make(f.center, f.u, f.v, 2.0 * f.half_u, 2.0 * f.half_v, f.name) for f in scene.faces
    ]  # fmt: skip
    return SimScene(tuple(rects), "ned")


def _csv_row(t_ns: int, pose: Any) -> list[str]:
    fix = math.isfinite(pose.north_m) and math.isfinite(pose.east_m)
    # float(): a numpy scalar's repr is not a number in a CSV
    return [
        str(t_ns),
        repr(math.degrees(float(pose.roll_rad))),
        repr(math.degrees(float(pose.pitch_rad))),
        repr(math.degrees(float(pose.yaw_rad))),
        repr(float(pose.north_m)) if fix else "",
        repr(float(pose.east_m)) if fix else "",
        repr(float(pose.down_m)),
    ]


def write_fleet(root: Path, mode: str, seed: int, seconds: float, size: str = "640x360") -> dict[str, Path]:
    """Write (or find, when ``root/<key>/done.json`` exists) each robot's dive folder of ``mode``'s dive.
    Returns robot -> folder. Rendering costs about 30 ms of CPU per frame (2700 frames for 90 s)."""
    import cv2

    from lrsensor.sim.render import render
    from lrsensor.sim.scenes import paper_calibration
    from lrsensor.sim.water import WaterModel

    width, height = (int(x) for x in size.split("x"))
    key = root / f"{mode}-s{seed}-{seconds:g}s-{size}"
    frames = dive_frames(mode, seed, seconds)
    robots = sorted({f.robot for f in frames})
    out = {r: key / r for r in robots}
    if (key / "done.json").exists():
        return out
    calib = paper_calibration(width, height)
    scene = render_scene(tank())
    water = WaterModel.default()
    for i, r in enumerate(robots):
        out[r].mkdir(parents=True, exist_ok=True)
        calib.save(out[r] / "calib.json")
        mine = [f for f in frames if f.robot == r]
        with (out[r] / "imu.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(IMU_CSV_HEADER)
            for f in mine:
                w.writerow(_csv_row(f.t_ns, f.pose_est))
        for k, f in enumerate(mine):
            img = render(scene, calib, pose=f.pose_true, water=water, seed=np.random.default_rng([seed, i, k])).image
            if not cv2.imwrite(str(out[r] / f"{f.t_ns}.png"), img):
                msg = f"could not write a frame into {out[r]}"
                raise OSError(msg)
    (key / "done.json").write_text(json.dumps({"mode": mode, "seed": seed, "seconds": seconds, "size": size}))
    return out


def extracted_frames(frames: list[DiveFrame], folders: dict[str, Path]) -> list[DiveFrame]:
    """``frames`` with each one's ``points_body`` replaced by what the ROV measures in its rendered image (the
    robot's folder's ``calib.json`` and ``<t_ns>.png``; :class:`lrsensor.Sensor`'s default extractor), cached in
    ``clouds.npz`` of each folder. The traced hits stay (they say which faces the dive saw)."""
    import cv2

    from lrsensor import Sensor
    from lrsensor.frames import body_to_ned

    clouds: dict[tuple[str, int], np.ndarray] = {}
    for robot, d in folders.items():
        cache = d / "clouds.npz"
        if cache.exists():
            with np.load(cache) as z:
                for name in z.files:
                    clouds[(robot, int(name))] = z[name]
            continue
        sensor = Sensor.from_file(d / "calib.json")
        mine: dict[str, np.ndarray] = {}
        for f in (f for f in frames if f.robot == robot):
            img = cv2.imread(str(d / f"{f.t_ns}.png"), cv2.IMREAD_COLOR)
            if img is None:
                msg = f"could not read the frame {f.t_ns}.png in {d}"
                raise OSError(msg)
            mine[str(f.t_ns)] = np.asarray(sensor.process(img).points, dtype=np.float64)
            clouds[(robot, f.t_ns)] = mine[str(f.t_ns)]
        np.savez(cache, **mine)  # type: ignore[arg-type]
    out = []
    for f in frames:
        pts = clouds[(f.robot, f.t_ns)]
        out.append(replace(f, points_body=pts, points_ned_est=body_to_ned(pts, f.pose_est)))
    return out


def depth_only_frames(seed: int, *, traced: bool, max_range_m: float, dives: Path) -> list[DiveFrame]:
    """The 90 s ``depth-only`` dive of ``seed`` as the graph diagnostics read it: its traced clouds, or (``traced``
    False) the clouds extracted from its 640x360 frames rendered once into ``dives``; cut at ``max_range_m`` (m)
    along the optical axis where > 0, as the acceptance check's ROVs are run."""
    frames = dive_frames("depth-only", seed, 90.0)
    if not traced:
        frames = extracted_frames(frames, write_fleet(dives, "depth-only", seed, 90.0, "640x360"))
    if max_range_m > 0:
        frames = [replace(f, points_body=f.points_body[f.points_body[:, 0] <= max_range_m]) for f in frames]
    return frames
