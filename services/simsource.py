"""The simulated ROV: frames rendered by :mod:`lrsensor.sim` in its ``tank`` while diving a trajectory, and
the matching simulated IMU (truth plus noise), for ``lrsensor rov --source sim`` and ``lrsensor demo``.

Frame ``k`` is captured at ``t0_ns + k / rate_hz``; the IMU samples the same trajectory at ``imu_rate_hz`` over
a span that covers every frame.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose

from .imu import TrackImu
from .posetrack import PoseTrack
from .sources import Frame

#: Poses along a dive: time since the start (s) -> pose in NED.
Trajectory = Callable[[float], Pose]


def robot_index(robot: str) -> int:
    """0 for ``rov1``/``rovA``-like names ending in 1, 1 for ``...2``, ...; 0 when the name has no number."""
    m = re.search(r"(\d+)$", robot)
    return max(0, int(m.group(1)) - 1) if m else 0


def _fallback_trajectory(index: int) -> Trajectory:
    """A slow lap inside the 12 m x 8 m tank, looking at the walls and pillars (one lane per robot)."""
    from lrsensor.sim.scenes import TANK_SIZE_M

    ln, le, depth = TANK_SIZE_M
    cn, ce = ln / 2.0, le / 2.0
    a, b = 3.6 - 0.5 * (index % 3), 2.2 - 0.3 * (index % 3)
    down = min(depth - 0.6, 1.2 + 0.5 * (index % 3))
    phase = 2.0 * math.pi * index / 3.0
    omega = 2.0 * math.pi / 120.0  # one lap in two minutes

    def pose(t_s: float) -> Pose:
        th = phase + omega * t_s
        n, e = cn + a * math.cos(th), ce + b * math.sin(th)
        yaw = math.atan2(b * math.sin(th) / b**2, a * math.cos(th) / a**2)  # outward normal: face the walls
        roll = math.radians(2.0) * math.sin(0.7 * t_s + index)
        pitch = math.radians(1.5) * math.sin(0.5 * t_s + 2 * index)
        return Pose(n, e, down, roll, pitch, yaw)

    return pose


def tank_trajectory(index: int) -> Trajectory:
    """The trajectory of robot ``index`` in the tank (the simulator's dives when available)."""
    try:
        from lrsensor.sim import dive  # noqa: F401 - built in parallel; fall back until it exists
    except ImportError:
        return _fallback_trajectory(index)
    return _fallback_trajectory(index)


@dataclass
class SimDive:
    """One simulated robot: renderer, trajectory, IMU and calibration.

    Attributes:
        trajectory: pose at a time since the start of the dive.
        n_frames: frames the dive has (a finite source).
        rate_hz: frame rate of the simulated camera.
        width, height: image size (intrinsics scaled from the paper's camera).
        seed: seed of rendering noise and IMU noise.
        t0_ns: capture time of the first frame.
        imu_rate_hz: IMU sample rate.
        imu_noise_deg, imu_noise_m: white noise of the simulated IMU's attitude and position.
        clean_water: render without water effects (faster).
    """

    trajectory: Trajectory
    n_frames: int = 60
    rate_hz: float = 10.0
    width: int = 640
    height: int = 360
    seed: int = 0
    t0_ns: int = 0
    imu_rate_hz: float = 50.0
    imu_noise_deg: float = 0.05
    imu_noise_m: float = 0.005
    clean_water: bool = False

    def __post_init__(self) -> None:
        from lrsensor.sim import named_scene

        if self.t0_ns <= 0:
            self.t0_ns = time.time_ns()
        self.setup = named_scene("tank", self.width, self.height)
        if self.clean_water:
            from lrsensor.sim import WaterModel

            self.setup = self.setup.with_(water=WaterModel.clean())
        self.calibration: Calibration = self.setup.calibration
        self.finite = True
        self.live = False
        self.name = f"sim:tank({self.width}x{self.height}, {self.n_frames} frames)"

    def frame_time_s(self, k: int) -> float:
        """Time of frame ``k`` since the start, seconds."""
        return k / self.rate_hz

    def imu(self) -> TrackImu:
        """The simulated IMU: the trajectory sampled at ``imu_rate_hz`` with seeded white noise."""
        rng = np.random.default_rng(self.seed + 7919)
        dur = self.frame_time_s(max(self.n_frames - 1, 0))
        n = math.ceil((dur + 0.2) * self.imu_rate_hz) + 1
        track = PoseTrack()
        for i in range(n):
            t_s = -0.1 + i / self.imu_rate_hz
            p = self.trajectory(t_s)
            na = rng.normal(0.0, math.radians(self.imu_noise_deg), 3)
            npos = rng.normal(0.0, self.imu_noise_m, 3)
            noisy = Pose(
                p.north_m + npos[0],
                p.east_m + npos[1],
                p.down_m + npos[2],
                p.roll_rad + na[0],
                p.pitch_rad + na[1],
                p.yaw_rad + na[2],
            )
            track.append(self.t0_ns + round(t_s * 1e9), noisy)
        return TrackImu(track, "sim")

    def __enter__(self) -> SimDive:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def __len__(self) -> int:
        return self.n_frames

    def __iter__(self) -> Iterator[Frame]:
        for k in range(self.n_frames):
            t_s = self.frame_time_s(k)
            r = self.setup.with_(pose=self.trajectory(t_s)).render(seed=self.seed * 100_003 + k)
            yield Frame(self.t0_ns + round(t_s * 1e9), r.image, k)


def open_sim(
    n_frames: int = 60,
    width: int = 640,
    height: int = 360,
    seed: int = 0,
    robot: str = "rov1",
    rate_hz: float = 10.0,
    t0_ns: int | None = None,
    clean_water: bool = False,
) -> tuple[SimDive, TrackImu, Calibration]:
    """The simulated frame source, its IMU and its (true) calibration for ``robot``."""
    dive = SimDive(
        tank_trajectory(robot_index(robot)),
        n_frames=n_frames,
        rate_hz=rate_hz,
        width=width,
        height=height,
        seed=seed + 1000 * robot_index(robot),
        t0_ns=t0_ns or 0,
        clean_water=clean_water,
    )
    return dive, dive.imu(), dive.calibration


def record_sim_dive(
    out_dir: str | Path,
    robot: str = "rov1",
    n_frames: int = 12,
    width: int = 640,
    height: int = 360,
    seed: int = 0,
    rate_hz: float = 10.0,
    t0_ns: int = 1_700_000_000_000_000_000,
    clean_water: bool = False,
) -> Path:
    """Write a recorded dive of the simulated robot: ``<t_ns>.png`` frames, ``imu.csv`` and ``calib.json``.

    This is the layout ``lrsensor rov --source DIR`` replays. Returns ``out_dir``.
    """
    import cv2

    from .imu import write_csv

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dive, imu, calib = open_sim(n_frames, width, height, seed, robot, rate_hz, t0_ns, clean_water)
    for frame in dive:
        cv2.imwrite(str(out / f"{frame.t_ns}.png"), frame.image)
    times, poses = imu.track.samples()
    write_csv(out / "imu.csv", times, poses)
    calib.save(out / "calib.json")
    return out
