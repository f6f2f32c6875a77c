"""The simulated ROV: frames rendered by :mod:`lrsensor.sim` in its ``tank`` while flying one of
:func:`lrsensor.sim.dive.tank_trajectories`, and the matching simulated IMU (:func:`lrsensor.sim.dive.simulate_imu`,
truth plus realistic noise), for ``lrsensor rov --source sim`` and ``lrsensor demo``.

Frame ``k`` is captured at ``t0_ns + k / rate_hz``; the IMU log spans 0.5 s before the first frame to 0.5 s
after the last one.
"""

from __future__ import annotations

import re
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose

from .imu import TrackImu
from .posetrack import PoseTrack
from .sources import Frame


def robot_index(robot: str) -> int:
    """0 for names ending in 1 (``rov1``), 1 for ``...2``, ...; 0 when the name ends in no number."""
    m = re.search(r"(\d+)$", robot)
    return max(0, int(m.group(1)) - 1) if m else 0


@dataclass
class SimDive:
    """One simulated robot: renderer, trajectory, IMU and calibration (a finite frame source).

    Attributes:
        robot: the robot's name.
        index: which of :func:`~lrsensor.sim.dive.tank_trajectories` it flies.
        n_frames: frames of the dive.
        rate_hz: frame rate of the simulated camera (capture times are spaced by ``1 / rate_hz``).
        width, height: image size (the paper's camera scaled).
        seed: seed of the rendering noise and of the IMU noise.
        t0_ns: capture time of the first frame (0: now).
        imu_rate_hz: IMU sample rate.
        clean_water: render without water effects (faster, for tests).
    """

    robot: str = "rov1"
    index: int = 0
    n_frames: int = 60
    rate_hz: float = 10.0
    width: int = 640
    height: int = 360
    seed: int = 0
    t0_ns: int = 0
    imu_rate_hz: float = 100.0
    clean_water: bool = False
    finite: bool = field(default=True, init=False)
    live: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        from lrsensor.sim import WaterModel
        from lrsensor.sim.dive import frame_times_ns, tank_trajectories
        from lrsensor.sim.scenes import paper_calibration, tank_scene

        if self.t0_ns <= 0:
            self.t0_ns = time.time_ns()
        self.trajectory: Any = tank_trajectories(self.index + 1, t0_ns=self.t0_ns)[self.index]
        self.calibration: Calibration = paper_calibration(self.width, self.height)
        self.scene = tank_scene()
        self.water = WaterModel.clean() if self.clean_water else WaterModel.default()
        self.times = frame_times_ns(self.n_frames / self.rate_hz, self.rate_hz, self.t0_ns)
        self.name = f"sim:tank({self.robot}, {self.width}x{self.height}, {self.n_frames} frames)"

    def true_pose(self, t_ns: int) -> Pose:
        """The true pose of the vehicle at ``t_ns``."""
        pose: Pose = self.trajectory.pose_at(int(t_ns))
        return pose

    def imu(self) -> TrackImu:
        """The simulated IMU over the dive (seeded noise), as a pose track."""
        from lrsensor.sim.dive import simulate_imu

        log = simulate_imu(
            self.trajectory,
            int(self.times[0]) - 500_000_000,
            int(self.times[-1]) + 500_000_000,
            rate_hz=self.imu_rate_hz,
            seed=self.seed + 7919,
        )
        track = PoseTrack()
        track.extend(
            log.t_ns,
            np.stack([log.north_m, log.east_m, log.down_m, log.roll_rad, log.pitch_rad, log.yaw_rad], axis=1),
        )
        return TrackImu(track, "sim")

    def __enter__(self) -> SimDive:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def __len__(self) -> int:
        return int(self.times.size)

    def __iter__(self) -> Iterator[Frame]:
        from lrsensor.sim import render

        rng = np.random.default_rng(self.seed)
        for k, t in enumerate(self.times):
            r = render(self.scene, self.calibration, pose=self.true_pose(int(t)), water=self.water, seed=rng)
            yield Frame(int(t), r.image, k)


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
    """The simulated frame source, its IMU and its (true) calibration for ``robot``.

    The robot's trajectory follows the number its name ends in (``rov1`` flies trajectory 0).
    """
    index = robot_index(robot)
    dive = SimDive(
        robot=robot,
        index=index,
        n_frames=n_frames,
        rate_hz=rate_hz,
        width=width,
        height=height,
        seed=seed + 1000 * index,
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
    clean_water: bool = False,
) -> Path:
    """Record a dive of the simulated ``robot`` with :func:`lrsensor.sim.dive.record_dive`: ``<t_ns>.png``
    frames, ``imu.csv``, ``calib.json`` and ``truth.json`` (the layout ``lrsensor rov --source DIR`` replays).
    """
    from lrsensor.sim import WaterModel
    from lrsensor.sim.dive import record_dive

    index = robot_index(robot)
    record_dive(
        out_dir,
        robot=robot,
        robot_index=index,
        n_robots=index + 1,
        duration_s=n_frames / rate_hz,
        rate_hz=rate_hz,
        width=width,
        height=height,
        water=WaterModel.clean() if clean_water else None,
        seed=seed + 1000 * index,
    )
    return Path(out_dir)
