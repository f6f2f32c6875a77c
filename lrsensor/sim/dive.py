"""Simulated dives in the tank: smooth trajectories, a noisy IMU, recorded dives and cheap truth clouds.

- :class:`Trajectory`: a vehicle flying a closed loop at constant speed, time (ns since the epoch) -> :class:`Pose`
  in NED; yaw keeps the camera facing the structure, roll/pitch/heave wobble a little.
- :func:`tank_trajectories`: N distinct, mutually non-colliding trajectories in the :func:`tank_scene` that keep
  walls, pillars or the pipe 0.4-3 m in front of the camera most of the time.
- :func:`simulate_imu`: IMU/navigation samples ``t_ns, roll, pitch, yaw, north, east, down`` with realistic
  noise (attitude white noise, a yaw bias and drift, position noise and a slow position random walk), or the
  ``drift`` (DVL dead reckoning) and ``depth-only`` navigation of :mod:`lrsensor.sim.navigation`.
- :func:`record_dive`: writes a recorded dive folder: ``<t_ns>.png`` frames, ``imu.csv``, ``calib.json``,
  ``truth.json``.
- :func:`trace_dive_clouds`: per frame the TRUE laser points (body frame) and pose, without rendering.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import SimulationError
from ..frames import Pose
from .fan import LaserModel, fan_basis, trace_samples
from .navigation import DriftNoise, check_mode, simulate_navigation
from .render import render, trace_truth
from .scene import Scene
from .scenes import TANK_PILLARS, TANK_SIZE_M, paper_calibration, tank_scene
from .water import WaterModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Default start of simulated dives: 2023-11-14T22:13:20Z, integer ns since the Unix epoch.
DEFAULT_T0_NS = 1_700_000_000_000_000_000
#: Header of the IMU CSV (CONVENTIONS / the fleet issue).
IMU_CSV_HEADER = ("t_ns", "roll_deg", "pitch_deg", "yaw_deg", "north_m", "east_m", "down_m")


# --------------------------------------------------------------------------- closed curves
def offset_loop(
    core: Sequence[Sequence[float]], radius_m: float, step_m: float = 0.02
) -> tuple[FloatArray, FloatArray]:
    """Closed curve at distance ``radius_m`` around a convex core polygon (or a segment), in (north, east).

    Args:
        core: (K, 2) vertices of a convex polygon in positive order (north toward east), or 2 points for a
            segment (a capsule around it).
        radius_m: offset distance, metres.
        step_m: sampling step along the curve, metres.

    Returns:
        points (M, 2) along the curve (positive order, not repeating the first point) and the unit outward
        normal (M, 2) at each point (from the core toward the curve).
    """
    v = np.asarray(core, dtype=float)
    k = v.shape[0]
    if k < 2 or radius_m <= 0:
        msg = f"offset_loop needs >= 2 core vertices and a positive radius, got {k} and {radius_m}"
        raise SimulationError(msg)
    edges = np.roll(v, -1, axis=0) - v
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    pts: list[FloatArray] = []
    nrm: list[FloatArray] = []
    for i in range(k):
        n_prev, n_next = normals[i - 1], normals[i]
        a0 = math.atan2(n_prev[1], n_prev[0])
        a1 = math.atan2(n_next[1], n_next[0])
        turn = (a1 - a0) % (2 * math.pi)
        if turn > math.pi + 1e-9 and k > 2:
            turn -= 2 * math.pi  # concave vertex: should not happen for convex cores
        n_arc = max(2, math.ceil(abs(turn) * radius_m / step_m))
        ang = a0 + turn * np.arange(n_arc) / n_arc
        dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        pts.append(v[i] + radius_m * dirs)
        nrm.append(dirs)
        length = float(np.linalg.norm(edges[i]))
        n_line = max(1, math.ceil(length / step_m))
        s = np.arange(n_line)[:, None] / n_line
        pts.append(v[i] + radius_m * n_next + s * edges[i])
        nrm.append(np.broadcast_to(n_next, (n_line, 2)).copy())
    return np.concatenate(pts), np.concatenate(nrm)


@dataclass(frozen=True, eq=False)
class Trajectory:
    """A vehicle flying a closed loop at constant speed, looking along the loop's normal.

    Attributes:
        name: free text (the robot's name).
        points_ne: (M, 2) the loop in (north, east), metres, closed implicitly.
        look_ne: (M, 2) unit look direction (the camera's heading) at each loop point.
        speed_m_s: speed along the loop, m/s (negative: the other way round).
        down_m: mean depth, metres.
        start_m: arc-length position at ``t0_ns``, metres.
        t0_ns: time of the start, ns since the Unix epoch.
        heave_m, roll_amp_rad, pitch_amp_rad: wobble amplitudes (depth, roll, pitch).
        phase: phase of the wobble, radians.
    """

    name: str
    points_ne: FloatArray
    look_ne: FloatArray
    speed_m_s: float = 0.2
    down_m: float = 1.5
    start_m: float = 0.0
    t0_ns: int = DEFAULT_T0_NS
    heave_m: float = 0.1
    roll_amp_rad: float = math.radians(2.0)
    pitch_amp_rad: float = math.radians(3.0)
    phase: float = 0.0
    _s: FloatArray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        p = np.asarray(self.points_ne, dtype=float)
        seg = np.linalg.norm(np.diff(np.vstack([p, p[:1]]), axis=0), axis=1)
        object.__setattr__(self, "_s", np.concatenate([[0.0], np.cumsum(seg)]))

    @property
    def length_m(self) -> float:
        """Length of the loop, metres."""
        return float(self._s[-1])

    def arrays(self, t_ns: Iterable[int] | IntArray) -> dict[str, FloatArray]:
        """Vectorized poses at times ``t_ns`` (M,): north/east/down (m) and roll/pitch/yaw (rad), each (M,)."""
        t = (np.asarray(list(t_ns) if not isinstance(t_ns, np.ndarray) else t_ns, dtype=np.int64) - self.t0_ns) * 1e-9
        s = np.mod(self.start_m + self.speed_m_s * t, self.length_m)
        p = np.vstack([self.points_ne, self.points_ne[:1]])
        look = np.vstack([self.look_ne, self.look_ne[:1]])
        north = np.interp(s, self._s, p[:, 0])
        east = np.interp(s, self._s, p[:, 1])
        ln = np.interp(s, self._s, look[:, 0])
        le = np.interp(s, self._s, look[:, 1])
        ph = self.phase
        return {
            "north_m": north,
            "east_m": east,
            "down_m": self.down_m + self.heave_m * np.sin(2 * math.pi * t / 23.0 + ph),
            "roll_rad": self.roll_amp_rad * np.sin(2 * math.pi * t / 7.0 + 1.3 * ph),
            "pitch_rad": self.pitch_amp_rad * np.sin(2 * math.pi * t / 11.0 + 0.7 * ph + 0.5),
            "yaw_rad": np.arctan2(le, ln),
        }

    def pose_at(self, t_ns: int) -> Pose:
        """The pose at ``t_ns`` (ns since the epoch)."""
        a = self.arrays(np.array([t_ns], dtype=np.int64))
        return Pose(
            float(a["north_m"][0]),
            float(a["east_m"][0]),
            float(a["down_m"][0]),
            float(a["roll_rad"][0]),
            float(a["pitch_rad"][0]),
            float(a["yaw_rad"][0]),
        )

    def poses(self, t_ns: Iterable[int] | IntArray) -> list[Pose]:
        """Poses at several times."""
        a = self.arrays(t_ns)
        keys = ("north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "yaw_rad")
        return [Pose(*(float(a[k][i]) for k in keys)) for i in range(a["north_m"].size)]

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready summary (not the loop points)."""
        return {
            "name": self.name,
            "speed_m_s": self.speed_m_s,
            "down_m": self.down_m,
            "length_m": self.length_m,
            "start_m": self.start_m,
            "t0_ns": self.t0_ns,
        }


def tank_trajectories(
    n: int,
    *,
    speed_m_s: float = 0.2,
    t0_ns: int = DEFAULT_T0_NS,
    names: Sequence[str] | None = None,
) -> list[Trajectory]:
    """``n`` distinct, non-colliding trajectories in the tank (:func:`~lrsensor.sim.scenes.tank_scene`).

    Robot k flies on depth level ``k % 5`` (1.0, 1.7, 2.4, 3.1 or 0.4 m); the level fixes its loop:
    level % 3 == 0: along the walls 1.3 m off them, looking at the walls; == 1: around both pillars and the
    pipe 0.9 m off the pillars' centres, looking at them; == 2: along the walls 1.7 m off, the other way
    round. Robots sharing a level fly the same loop at the same speed, spread along it (0, 1/2, 1/4, 3/4, ...
    of a lap), so they never meet; loops on nearby levels stay apart in plan. Trajectory k does not depend
    on ``n``. Walls, pillars or the pipe fill a quarter of the fan within 0.4-3 m about 90 % of the time.
    """
    if n < 1:
        msg = f"need at least one trajectory, got {n}"
        raise SimulationError(msg)
    ln, le, depth = TANK_SIZE_M
    (p1, _), (p2, _) = TANK_PILLARS
    out = []
    depths = [1.0, 1.7, 2.4, 3.1, 0.4]
    for k in range(n):
        level, j = k % len(depths), k // len(depths)
        kind = level % 3
        if kind == 1:
            pts, nrm = offset_loop([p1, p2], 0.9)
            look = -nrm
            speed = speed_m_s * 0.8
        else:
            d = 1.3 if kind == 0 else 1.7
            r = 0.8
            core = [(d + r, d + r), (ln - d - r, d + r), (ln - d - r, le - d - r), (d + r, le - d - r)]
            # positive order north -> east: (n, e) = (0,0) -> (1,0) -> (1,1) -> (0,1)
            pts, nrm = offset_loop(core, r)
            look = nrm
            speed = speed_m_s if kind == 0 else -speed_m_s
        traj = Trajectory(
            name=(names[k] if names is not None else f"rov{k + 1}"),
            points_ne=pts,
            look_ne=look,
            speed_m_s=speed,
            down_m=min(depths[level], depth - 0.6),
            t0_ns=t0_ns,
            phase=0.9 * k,
        )
        start = ((0.37 * level + _van_der_corput(j)) % 1.0) * traj.length_m
        out.append(replace(traj, start_m=start))
    return out


def _van_der_corput(j: int) -> float:
    """The j-th term of the base-2 van der Corput sequence: 0, 1/2, 1/4, 3/4, 1/8, ..."""
    x, denom = 0.0, 1.0
    while j:
        denom *= 2.0
        x += (j & 1) / denom
        j >>= 1
    return x


def min_separation_m(trajectories: Sequence[Trajectory], duration_s: float, step_s: float = 0.5) -> float:
    """Smallest 3-D distance between any two vehicles over ``duration_s`` (sampled every ``step_s``), metres."""
    if len(trajectories) < 2:
        return math.inf
    t0 = trajectories[0].t0_ns
    ts = t0 + (np.arange(0.0, duration_s + 1e-9, step_s) * 1e9).astype(np.int64)
    pos = []
    for tr in trajectories:
        a = tr.arrays(ts)
        pos.append(np.stack([a["north_m"], a["east_m"], a["down_m"]], axis=1))
    best = math.inf
    for i in range(len(pos)):
        for j in range(i + 1, len(pos)):
            best = min(best, float(np.linalg.norm(pos[i] - pos[j], axis=1).min()))
    return best


def front_ranges_m(
    trajectory: Trajectory,
    t_ns: IntArray,
    scene: Scene | None = None,
    fan_angle_rad: float = math.radians(120.0),
    n_rays: int = 31,
) -> FloatArray:
    """What the lasers see: ranges (M, n_rays) to the first surface along rays spread over the fan in the
    vehicle's horizontal body plane at times ``t_ns`` (M,); inf where a ray hits nothing."""
    scene = scene or tank_scene()
    theta = np.linspace(-fan_angle_rad / 2, fan_angle_rad / 2, n_rays)
    d_body = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=1)
    out = np.empty((len(t_ns), n_rays))
    for i, pose in enumerate(trajectory.poses(t_ns)):
        t, _, _ = scene.raycast(pose.p_ned, d_body @ pose.R_ned_from_body.T)
        out[i] = t
    return out


def in_range_fraction(
    trajectory: Trajectory, duration_s: float, step_s: float = 1.0, lo_m: float = 0.4, hi_m: float = 3.0
) -> float:
    """Fraction of times (sampled every ``step_s`` over ``duration_s``) at which at least a quarter of the fan
    sees a surface between ``lo_m`` and ``hi_m``."""
    ts = trajectory.t0_ns + (np.arange(0.0, duration_s + 1e-9, step_s) * 1e9).astype(np.int64)
    r = front_ranges_m(trajectory, ts)
    good = ((r >= lo_m) & (r <= hi_m)).mean(axis=1) >= 0.25
    return float(good.mean())


def clearance_m(trajectory: Trajectory, duration_s: float, step_s: float = 0.5, scene: Scene | None = None) -> float:
    """Smallest distance from the vehicle's origin to any tank surface over ``duration_s``, metres."""
    scene = scene or tank_scene()
    ts = trajectory.t0_ns + (np.arange(0.0, duration_s + 1e-9, step_s) * 1e9).astype(np.int64)
    a = trajectory.arrays(ts)
    p = np.stack([a["north_m"], a["east_m"], a["down_m"]], axis=1)
    return float(scene.distance_to_surface(p).min())


# --------------------------------------------------------------------------- IMU
@dataclass(frozen=True)
class ImuNoise:
    """Noise of the simulated IMU / navigation solution (SI units; angles in radians).

    Attributes:
        attitude_sigma_rad: white noise on roll, pitch and yaw.
        yaw_bias_rad: magnitude of a constant yaw bias (its sign drawn from the seed).
        yaw_drift_rad_per_sqrt_s: random-walk drift of the yaw.
        position_sigma_m: white noise on north and east.
        position_walk_m_per_sqrt_s: random walk of north and east (dead-reckoning drift).
        depth_sigma_m: white noise of the depth sensor.
    """

    attitude_sigma_rad: float = math.radians(0.15)
    yaw_bias_rad: float = math.radians(0.3)
    yaw_drift_rad_per_sqrt_s: float = math.radians(0.01)
    position_sigma_m: float = 0.015
    position_walk_m_per_sqrt_s: float = 0.002
    depth_sigma_m: float = 0.01

    @classmethod
    def none(cls) -> ImuNoise:
        """A perfect IMU (for exact tests)."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ImuLog:
    """IMU samples: ``t_ns`` (N,) int64 and the pose channels (N,) in SI units (radians, metres)."""

    t_ns: IntArray
    roll_rad: FloatArray
    pitch_rad: FloatArray
    yaw_rad: FloatArray
    north_m: FloatArray
    east_m: FloatArray
    down_m: FloatArray

    def __len__(self) -> int:
        return int(self.t_ns.size)

    def write_csv(self, path: str | os.PathLike[str]) -> None:
        """Write ``t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m`` (yaw wrapped to (-180, 180]); a
        sample without a horizontal fix (NaN north/east) gets empty ``north_m`` and ``east_m`` fields."""
        yaw = np.degrees(np.angle(np.exp(1j * self.yaw_rad)))

        def pos(x: float) -> str:
            return f"{x:.5f}" if math.isfinite(x) else ""

        with Path(path).open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(IMU_CSV_HEADER)
            for i in range(len(self)):
                w.writerow(
                    [
                        int(self.t_ns[i]),
                        f"{math.degrees(self.roll_rad[i]):.5f}",
                        f"{math.degrees(self.pitch_rad[i]):.5f}",
                        f"{yaw[i]:.5f}",
                        pos(float(self.north_m[i])),
                        pos(float(self.east_m[i])),
                        f"{self.down_m[i]:.5f}",
                    ]
                )

    @classmethod
    def read_csv(cls, path: str | os.PathLike[str]) -> ImuLog:
        """Read a CSV written by :meth:`write_csv` (empty north/east fields become NaN)."""
        with Path(path).open(encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
        if not rows or tuple(rows[0]) != IMU_CSV_HEADER:
            msg = f"{path}: header must be {','.join(IMU_CSV_HEADER)}"
            raise SimulationError(msg)
        data = np.array([[float(x) if x != "" else math.nan for x in r[1:]] for r in rows[1:]]).reshape(-1, 6)
        t = np.array([int(r[0]) for r in rows[1:]], dtype=np.int64)
        return cls(
            t,
            np.radians(data[:, 0]),
            np.radians(data[:, 1]),
            np.radians(data[:, 2]),
            data[:, 3],
            data[:, 4],
            data[:, 5],
        )


def simulate_imu(
    trajectory: Trajectory,
    t_start_ns: int,
    t_end_ns: int,
    *,
    rate_hz: float = 100.0,
    noise: ImuNoise | None = None,
    seed: int | np.random.Generator | None = 0,
    navigation: str = "good",
    drift: DriftNoise | None = None,
    launch_fix_s: float = 0.0,
) -> ImuLog:
    """IMU samples of ``trajectory`` from ``t_start_ns`` to ``t_end_ns`` (inclusive) at ``rate_hz``.

    ``navigation``: ``good`` (``noise``, an :class:`ImuNoise`), or ``drift`` / ``depth-only`` (``drift``, a
    :class:`~lrsensor.sim.navigation.DriftNoise`; see :mod:`lrsensor.sim.navigation`). ``depth-only`` samples
    have NaN north/east after the first, or after the first ``launch_fix_s`` (the launch fix).
    """
    check_mode(navigation)
    noise = noise or ImuNoise()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    period_ns = round(1e9 / rate_hz)
    t = np.arange(t_start_ns, t_end_ns + 1, period_ns, dtype=np.int64)
    a = trajectory.arrays(t)
    m = t.size
    if navigation != "good":
        r = simulate_navigation(navigation, (t - t[0]) * 1e-9, a, rng, drift, launch_fix_s)
        return ImuLog(t, r["roll_rad"], r["pitch_rad"], r["yaw_rad"], r["north_m"], r["east_m"], r["down_m"])
    dt = period_ns * 1e-9

    def walk(sigma_per_sqrt_s: float) -> FloatArray:
        return np.cumsum(rng.standard_normal(m) * sigma_per_sqrt_s * math.sqrt(dt))

    bias = noise.yaw_bias_rad * (1.0 if rng.uniform() < 0.5 else -1.0)
    att = noise.attitude_sigma_rad
    return ImuLog(
        t_ns=t,
        roll_rad=a["roll_rad"] + att * rng.standard_normal(m),
        pitch_rad=a["pitch_rad"] + att * rng.standard_normal(m),
        yaw_rad=a["yaw_rad"] + bias + walk(noise.yaw_drift_rad_per_sqrt_s) + att * rng.standard_normal(m),
        north_m=a["north_m"] + noise.position_sigma_m * rng.standard_normal(m) + walk(noise.position_walk_m_per_sqrt_s),
        east_m=a["east_m"] + noise.position_sigma_m * rng.standard_normal(m) + walk(noise.position_walk_m_per_sqrt_s),
        down_m=a["down_m"] + noise.depth_sigma_m * rng.standard_normal(m),
    )


# --------------------------------------------------------------------------- clouds and recorded dives
@dataclass(frozen=True)
class DiveCloud:
    """The TRUE laser points of one frame of a dive.

    Attributes:
        t_ns: capture time, ns since the epoch.
        pose: the true vehicle pose in NED.
        points_body: (N, 3) true hit points in the body frame, metres (about one per image column per laser,
            exactly on the surfaces).
        laser: (N,) laser index of each point.
        uv: (N, 2) their pixels (u within a small fraction of a pixel of the integer columns).
    """

    t_ns: int
    pose: Pose
    points_body: FloatArray
    laser: IntArray
    uv: FloatArray


def frame_times_ns(duration_s: float, rate_hz: float, t0_ns: int = DEFAULT_T0_NS) -> IntArray:
    """Frame capture times: ``t0_ns + k / rate_hz`` for ``0 <= k < duration_s * rate_hz``, int64 ns."""
    n = max(1, math.floor(duration_s * rate_hz + 1e-9))
    return np.int64(t0_ns) + np.round(np.arange(n) * 1e9 / rate_hz).astype(np.int64)


def trace_dive_clouds(
    trajectory: Trajectory,
    t_ns: Iterable[int] | IntArray,
    *,
    calibration: Calibration | None = None,
    scene: Scene | None = None,
    laser_model: LaserModel | None = None,
) -> Iterator[DiveCloud]:
    """Yield per frame the TRUE laser points (body frame, one per visible column per laser) and the pose.

    No image is rendered (about 10-30 ms a frame). ``calibration`` defaults to the paper's at 1920x1080 and
    ``scene`` to the tank.
    """
    calib = calibration or paper_calibration()
    scene = scene or tank_scene()
    model = laser_model or LaserModel(max_gap_px=1.0)
    cols = np.arange(calib.camera.width, dtype=float)
    for t in np.asarray(list(t_ns) if not isinstance(t_ns, np.ndarray) else t_ns, dtype=np.int64):
        pose = trajectory.pose_at(int(t))
        truth, _ = trace_truth(scene, calib, pose, model, edge_tol_rad=2e-5)
        pts, lasers, uvs = [], [], []
        for lt in truth.lasers:
            # the fan angle seen at each column, traced again exactly: points lie on the surfaces
            th = lt.theta_at_columns(cols)
            th = th[np.isfinite(th)]
            origin, a, b = fan_basis(calib, lt.index)
            s = trace_samples(truth.scene_body, calib, origin, a, b, th, model.max_range_m, 0.0)
            pts.append(s.points[s.ok])
            lasers.append(np.full(int(s.ok.sum()), lt.index, dtype=np.int64))
            uvs.append(s.uv[s.ok])
        yield DiveCloud(int(t), pose, np.concatenate(pts), np.concatenate(lasers), np.concatenate(uvs))


@dataclass(frozen=True)
class DiveRecord:
    """What :func:`record_dive` wrote: the folder, the frame times and files, the trajectory."""

    out_dir: Path
    t_ns: IntArray
    frames: tuple[Path, ...]
    imu_csv: Path
    calib_json: Path
    truth_json: Path
    trajectory: Trajectory


def _pose_dict(p: Pose) -> dict[str, float]:
    return {
        "north_m": p.north_m,
        "east_m": p.east_m,
        "down_m": p.down_m,
        "roll_rad": p.roll_rad,
        "pitch_rad": p.pitch_rad,
        "yaw_rad": p.yaw_rad,
    }


def record_dive(
    out_dir: str | os.PathLike[str],
    *,
    robot: str = "rov1",
    robot_index: int = 0,
    n_robots: int = 1,
    trajectory: Trajectory | None = None,
    duration_s: float = 10.0,
    rate_hz: float = 5.0,
    imu_rate_hz: float = 100.0,
    width: int = 960,
    height: int = 540,
    calibration: Calibration | None = None,
    water: WaterModel | None = None,
    imu_noise: ImuNoise | None = None,
    t0_ns: int = DEFAULT_T0_NS,
    seed: int = 0,
    progress: bool = False,
    navigation: str = "good",
) -> DiveRecord:
    """Record a simulated dive in the tank into ``out_dir``.

    Writes ``<t_ns>.png`` frames (BGR PNG, named by their capture time in integer ns since the epoch),
    ``imu.csv`` (header ``t_ns,roll_deg,pitch_deg,yaw_deg,north_m,east_m,down_m``, ``imu_rate_hz``, spanning
    0.5 s before the first frame to 0.5 s after the last), ``calib.json`` (the TRUE calibration) and
    ``truth.json`` (true pose per frame, the tank's surfaces in NED, the trajectory).

    Args:
        robot: the robot's name; ``robot_index`` / ``n_robots`` pick its trajectory from
            :func:`tank_trajectories` unless ``trajectory`` is given.
        duration_s, rate_hz: length of the dive and frame rate.
        width, height: image size (the paper's camera scaled).
        seed: seeds the images and the IMU noise (each robot should get its own).
        navigation: what ``imu.csv`` knows: ``good``, ``drift`` or ``depth-only`` (see
            :mod:`lrsensor.sim.navigation`; ``depth-only`` rows after the first frame have empty north/east).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if trajectory is None:
        trajs = tank_trajectories(max(n_robots, robot_index + 1), t0_ns=t0_ns)
        trajectory = trajs[robot_index]
    calib = calibration or paper_calibration(width, height)
    water = water if water is not None else WaterModel.default()
    scene = tank_scene()
    times = frame_times_ns(duration_s, rate_hz, t0_ns)
    rng = np.random.default_rng(seed)
    imu = simulate_imu(
        trajectory,
        int(times[0]) - 500_000_000,
        int(times[-1]) + 500_000_000,
        rate_hz=imu_rate_hz,
        noise=imu_noise,
        seed=rng,
        navigation=navigation,
        launch_fix_s=0.5 + 2.0 / imu_rate_hz,  # the launch fix straddles the first frame
    )
    imu_path = out / "imu.csv"
    imu.write_csv(imu_path)
    calib_path = out / "calib.json"
    calib.save(calib_path)
    import cv2

    frames: list[Path] = []
    truth_frames: list[dict[str, Any]] = []
    it: Iterable[int] = (int(t) for t in times)
    if progress:
        from tqdm import tqdm

        it = tqdm(list(it), desc=f"dive {robot}", unit="frame")
    for t in it:
        pose = trajectory.pose_at(t)
        r = render(scene, calib, pose=pose, water=water, seed=rng)
        path = out / f"{t}.png"
        if not cv2.imwrite(str(path), r.image):
            msg = f"could not write {path}"
            raise SimulationError(msg)
        frames.append(path)
        pts, _ = r.truth.all_points()
        truth_frames.append(
            {"t_ns": t, "file": path.name, "pose": _pose_dict(pose), "n_truth_samples": int(pts.shape[0])}
        )
    truth = {
        "format": "lrsensor-sim-dive",
        "version": 1,
        "robot": robot,
        "scene": "tank",
        "frame_rate_hz": rate_hz,
        "imu_rate_hz": imu_rate_hz,
        "navigation": navigation,
        "t0_ns": int(times[0]),
        "trajectory": trajectory.to_dict(),
        "surfaces_ned": scene.to_dicts(),
        "frames": truth_frames,
    }
    truth_path = out / "truth.json"
    truth_path.write_text(json.dumps(truth, indent=1) + "\n", encoding="utf-8")
    return DiveRecord(out, times, tuple(frames), imu_path, calib_path, truth_path, trajectory)
