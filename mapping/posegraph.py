"""A pose graph per robot without a horizontal fix: its own scans used *relatively* (GTSAM's iSAM2).

A ``depth-only`` robot (attitude, heading with a wandering compass bias, depth; a horizontal fix at launch only)
has nothing absolute after its launch. The Kalman filter of :mod:`mapping.navigation` takes every map plane as
absolute truth, so the planes the robot made itself seconds before carried its own errors back to it and, in the
symmetric tank, pulled it onto the wrong walls. Here each scan is a node of a graph and the robot's own scans
enter only as relations between its poses:

- **Unknowns** per scan: ``Pose2(north, east, theta)`` with ``theta`` the corrected heading (the compass plus the
  correction); depth, roll and pitch are measured.
- **Launch**: a prior at the launch fix (``NavConfig.launch_sigma_m``) and the compass (``compass_bias_deg``).
- **Scan-to-scan odometry** (:func:`mapping.odometry.increment`) between consecutive scans, in the previous
  scan's level frame (heading of the compass): its information is the scan's alone, so along one flat wall the
  along-wall component carries none and the velocity prior holds it; the turn between the scans is the compass's
  (its bias wanders slowly: ``yaw_walk_deg_per_sqrt_s``).
- **Velocity prior**: the horizontal velocity is a random walk (``GraphConfig.velocity_walk_m_s``): a factor on
  three consecutive poses (their two mean velocities differ by the walk).
- **Compass**: a weak heading prior every ``compass_every_s`` (its bias is within ``compass_bias_deg``).
- **The shared map's planes** that other robots made or helped make: point-to-plane residuals against them,
  associated within a gate set by the pose's current marginal covariance (3 sigma along each plane's normal) and
  checked by Mahalanobis distance, linearised into a unary factor (information and mean over north, east, heading).
- **The robot's own planes** (only it contributed, first seen at least ``own_min_age_s`` before): landmarks
  whose pose depends on the pose that made them. A plane is placed with the pose its first cloud had then; seeing
  it again gives where the robot is *relative to that pose*: a between-factor from the anchor pose to this one
  (the relative pose the registration implies, with the registration's information). Re-seeing its own wall after
  a loop closes the loop instead of fixing the robot to where it once thought it was.

The graph is solved incrementally (iSAM2); the window is bounded: once it spans ``window_s + rebase_every_s``,
the graph is rebuilt from the last ``window_s`` of its factors, the first kept pose tied by a prior with its
marginal covariance (a marginalisation), so the cost per scan stays bounded. :meth:`GraphNav.snapshot` is the
factors' plain numbers (a plane worker can send it): :meth:`GraphNav.restore` rebuilds the graph from them.

Its parts: the variables, solve and window here; the map's planes (registration and plane factors) in
:mod:`mapping.graph_planes`; the odometry factor and its guards in :mod:`mapping.graph_odometry`; the factors'
GTSAM form in :mod:`mapping.graph_factors`; the track gate, checks and re-localization in :mod:`mapping.graph_gate`;
the held clouds in :mod:`mapping.graph_hold`; the heading check in :mod:`mapping.graph_heading`; the fleet's
compass biases in :mod:`mapping.graph_fleet`.

GTSAM (``gtsam``, the ``graph`` extra of pyproject.toml) is imported on first use.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .errors import MapInputError
from .graph_config import GraphConfig
from .graph_factors import global_cov, isam2, make_factor, pose2, rot
from .graph_gate import TrackGate, relocalize, verify
from .graph_heading import check_heading
from .graph_hold import CloudHold, check_due, check_held, hold_step
from .graph_odometry import guards, odometry_factor, rot3
from .graph_planes import register
from .landmarks import PlaneLandmarks
from .nav_config import AXES, NavConfig, NavEstimate, registration_points, scan_constraint
from .odometry import OdometryConfig

FloatArray = NDArray[np.float64]

_GTSAM: Any = None


def gtsam_module() -> Any:
    """The ``gtsam`` module; raises :class:`MapInputError` naming the extra to install when it is missing."""
    global _GTSAM
    if _GTSAM is None:
        try:
            import gtsam
        except ImportError as err:
            msg = (
                "navigation of robots without a horizontal fix needs GTSAM: pip install 'lrsensor[graph]' "
                f"(or pip install gtsam) ({err})"
            )
            raise MapInputError(msg) from err
        _GTSAM = gtsam
    return _GTSAM


class GraphNav:
    """The pose graph of one robot without a horizontal fix (see the module docstring). Offers
    :class:`mapping.navigation.RobotNav`'s public methods (``update``, ``snapshot``, ``restore``, ``started``,
    ``latest``, ``lost``, ``start_ne``, ``x``, ``yaw_scans``), so the base's map thread and the plane workers run
    it the same way. Not thread-safe: one thread feeds it."""

    def __init__(self, robot: str, cfg: NavConfig | None = None, graph: GraphConfig | None = None) -> None:
        self.robot = robot
        self.cfg = cfg or NavConfig()
        self.gcfg = graph or GraphConfig()
        self.odo_cfg = OdometryConfig(residual_scale=self.gcfg.odometry_residual_scale)
        self.latest: NavEstimate | None = None
        self.lost = False
        self.joined = True
        self.yaw_scans = 0
        self.start_ne = np.zeros(2)
        #: [north, east, v_north, v_east, heading correction] of the latest pose (the filter's layout)
        self.x = np.zeros(5)
        self.prior = self.transition = None
        self.gated = 0
        self.loops = 0
        #: plane factors left out because another plane was as likely (``GraphConfig.second_hypothesis``)
        self.ambiguous = 0
        #: whether the track since the launch is unbroken (what may be placed), and the placed poses it froze
        self.track = TrackGate(self.gcfg.track_break_std_m)
        #: the clouds held until the next check passes (``GraphConfig.hold_until_verified``)
        self.hold = CloudHold()
        #: heading checks that added a prior (``GraphConfig.heading_check``)
        self.headings = 0
        #: the compass's bias (rad) and its standard deviation as the fleet estimated them (mapping.graph_fleet)
        self.compass_bias: tuple[float, float] | None = None
        self._reset()

    def _reset(self) -> None:
        #: per pose (key = index): capture time, compass yaw (rad), (depth, roll, pitch) as measured, level-frame
        #: points (M, 3) and depth (m) of the last two scans
        self._t: list[int] = []
        self._compass: list[float] = []
        self._att: list[tuple[float, float, float]] = []
        self._scan: dict[int, tuple[FloatArray, float]] = {}
        #: the pose each key's cloud was placed (or estimated) with when it came: the anchor of its planes
        self._then: dict[int, FloatArray] = {}
        #: factors as plain numbers: (kind, keys, data) (see _add)
        self._specs: list[tuple[str, tuple[int, ...], tuple[Any, ...]]] = []
        self._first_key = 0
        self._last_compass_t: int | None = None
        self._last_heading_t: int | None = None
        self._isam: Any = None
        self._est: FloatArray = np.zeros((0, 3))
        self._cov = np.eye(3)
        #: the planes with an offset variable in the graph, and those new since the last solve
        self._plane_ids: set[int] = set()
        self._new_offsets: set[int] = set()
        #: the robot-stretches with a shared offset (GraphConfig.stretch_s), and those new since the last solve
        self._stretch_ids: set[int] = set()
        self._new_stretches: set[int] = set()

    # -- the public interface of RobotNav ------------------------------------------------------------------------

    @property
    def started(self) -> bool:
        """Whether the robot's position is known (it had a launch fix)."""
        return bool(self._t)

    @property
    def t_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    @property
    def window_start_ns(self) -> int:
        """Capture time of the first pose the graph still holds (older ones are frozen)."""
        return self._t[self._first_key] if self._t else 0

    @property
    def start_map_ne(self) -> tuple[float, float] | None:
        """The launch pose (north, east) as the graph places it now (as frozen, past a broken track)."""
        if not self._t:
            return None
        x = self.track.frozen.get(self._t[0], self._est[0])
        return (float(x[0]), float(x[1]))

    def revised_poses(self) -> dict[int, Pose]:
        """t_ns -> each pose of the window as the graph estimates it now (every scan so far re-estimated with the
        later ones: the map re-places the clouds whose pose moved)."""
        if not self._t:
            return {}
        self._refresh(all_keys=True)
        out = {}
        for k in range(self._first_key, len(self._t)):
            down, roll, pitch = self._att[k]
            # a pose placed before the track broke stays as it was then (a later lock would drag it)
            x = self.track.frozen.get(self._t[k], self._est[k])
            out[self._t[k]] = Pose(float(x[0]), float(x[1]), down, roll, pitch, float(x[2]))
            # the map re-places this pose's cloud with it: its planes now hang on this estimate
            self._then[k] = x.copy()
        return out

    def mean_correction(self) -> tuple[float, int] | None:
        """The mean over the window's poses of the heading as estimated minus the compass (radians, the mean of the
        wrapped differences) and the poses counted; None before the launch. Nothing is solved: the estimates as
        last refreshed."""
        n = min(len(self._t), self._est.shape[0])
        if n <= self._first_key:
            return None
        c = np.remainder(self._est[self._first_key : n, 2] - np.asarray(self._compass[self._first_key : n]) + math.pi,
                         2 * math.pi) - math.pi  # fmt: skip
        return float(c.mean()), int(c.size)

    _STATE = ("lost", "yaw_scans", "gated", "loops", "_first_key", "_last_compass_t", "_last_heading_t", "headings",
              "compass_bias")  # fmt: skip

    def snapshot(self) -> dict[str, Any]:
        """The estimator's whole state as plain numbers: the window's factors and estimates, the scans kept."""
        out: dict[str, Any] = {k: getattr(self, k) for k in self._STATE}
        keys = sorted(self._scan)
        out.update(
            graph=True,
            start_ne=self.start_ne.copy(),
            x=self.x.copy(),
            t=list(self._t),
            compass=list(self._compass),
            att=[list(a) for a in self._att],
            scan_keys=keys,
            scans=[self._scan[k][0] for k in keys],
            depths=[self._scan[k][1] for k in keys],
            then_keys=sorted(self._then),
            then=[self._then[k] for k in sorted(self._then)],
            specs=[[kind, list(keys_), list(data)] for kind, keys_, data in self._specs],
            est=self._est.copy(),
            latest=self.latest,
            track=self.track.state(),
            hold=self.hold.state(),
        )
        return out

    def restore(self, snap: dict[str, Any], solve: bool = True) -> None:
        """Back to a :meth:`snapshot` (of this estimator or of another process's): the graph is rebuilt (not with
        ``solve`` False: the state is then only read, as the map thread reads a plane worker's for the frame)."""
        self._reset()
        for k in self._STATE:
            setattr(self, k, snap.get(k, getattr(self, k)))
        self.start_ne = np.asarray(snap["start_ne"], dtype=np.float64)
        self.x = np.asarray(snap["x"], dtype=np.float64)
        self._t = [int(t) for t in snap["t"]]
        self._compass = [float(c) for c in snap["compass"]]
        self._att = [(float(a[0]), float(a[1]), float(a[2])) for a in snap["att"]]
        self._scan = {
            int(k): (np.asarray(s, dtype=np.float64).reshape(-1, 3), float(d))
            for k, s, d in zip(snap["scan_keys"], snap["scans"], snap["depths"], strict=True)
        }
        self._then = {
            int(k): np.asarray(v, dtype=np.float64) for k, v in zip(snap["then_keys"], snap["then"], strict=True)
        }
        self._specs = [(str(kind), tuple(int(k) for k in keys), tuple(data)) for kind, keys, data in snap["specs"]]
        self._est = np.asarray(snap["est"], dtype=np.float64).reshape(-1, 3)
        self.latest = snap["latest"]
        self.track.load(snap.get("track", {}))
        self.hold.load(snap.get("hold", {}))
        if self._specs and solve:
            self._rebuild(self._first_key, None)

    def update(self, t_ns: int, raw: Pose, points_body: Any, landmarks: PlaneLandmarks) -> NavEstimate:
        """One cloud: a new pose, its odometry and velocity factors, the map's planes; returns the estimate.

        Args: as :meth:`mapping.navigation.RobotNav.update` (``raw`` north/east NaN without a fix; a fix, the
        launch's or a later one, is a prior on the position).
        """
        cfg = self.cfg
        t = int(t_ns)
        pts = registration_points(points_body, cfg)
        fix = np.array([raw.north_m, raw.east_m]) if math.isfinite(raw.north_m + raw.east_m) else None
        if not self.started:
            if fix is None:
                est = self._unknown(t, raw)
                self.latest = est
                return est
            self._launch(t, raw, pts, fix)
            est = self._estimate(t, raw, np.zeros((3, 3)), 0, (), "start")
            self.latest = est
            return est
        if t <= self._t[-1]:
            # a late cloud moves nothing: the current correction, as the filter does
            est = self._estimate(t, raw, np.zeros((3, 3)), 0, (), "late")
            self.latest = est
            return est
        key = len(self._t)
        motion = self._odometry(key, t, raw, pts)
        if fix is not None:
            s = cfg.fix_sigma_m
            self._add("fix", (key,), (float(fix[0]), float(fix[1]), s))
            self.lost = False
            self.track.broken = False
        self._compass_prior(key, t)
        self._solve()
        cov = self._cov[0:2, 0:2]
        std = math.sqrt(max(float(cov[0, 0]), float(cov[1, 1])))
        if fix is None and std > self.gcfg.lost_std_m:
            self.lost = True
        if fix is None and self.track.step(std, t):
            self._refresh(all_keys=True)
            self.track.freeze({self._t[k]: self._est[k] for k in range(self._first_key, key)})
        h3, inliers = np.zeros((3, 3)), 0
        used: tuple[int, ...] = ()
        if self.lost or (self.track.broken and self.gcfg.relocalize):
            # a broken track takes no plane factor (a guess would lock it): only a unique re-localization
            motion = "lost"
        else:
            x_pred, p_pred = self._est[key, 0:2].copy(), self._cov[0:2, 0:2].copy()
            h3, inliers, used = register(self, key, raw, pts, landmarks, t)
            dx = self._est[key, 0:2] - x_pred
            if fix is None and float(dx @ np.linalg.solve(p_pred, dx)) > self.gcfg.track_jump_chi2:
                # a correction its marginal cannot explain: the association was a surprise, the track breaks
                self.track.break_now(std, t)
                self.track.freeze({self._t[k]: v for k, v in self._then.items() if k < key})
        moved = None
        if self.track.broken and self.gcfg.relocalize and relocalize(self, key, t, raw, pts, landmarks):
            motion = moved = "relocalized"
        elif not self.track.broken and check_due(self, t):
            if self.gcfg.heading_check:
                check_heading(self, key, t, raw, pts, landmarks)
            moved = verify(self, key, t, raw, pts, landmarks)
            motion = moved or motion
        self._then[key] = self._est[key].copy()
        self._forget(key)
        if self.track.broken:
            motion = "lost"
        est = self._estimate(t, raw, h3, inliers, used, motion)
        if self.gcfg.hold_until_verified:
            est = hold_step(self, key, t, raw, points_body, est, landmarks, moved is not None)
        self.yaw_scans += int(est.constrained["yaw"])
        self.latest = est
        if t - self._t[self._first_key] > (self.gcfg.window_s + self.gcfg.rebase_every_s) * 1e9:
            self._rebase()
        return est

    def settle(self, landmarks: PlaneLandmarks) -> None:
        """The end (a flush, the robot silent): each held cloud checked alone (:func:`mapping.graph_hold.check_held`);
        :meth:`CloudHold.take` then gives those that go into the map."""
        if self._t:
            check_held(self, self._t[-1], landmarks)

    # -- building the graph ----------------------------------------------------------------------------------

    def _add(self, kind: str, keys: tuple[int, ...], data: tuple[Any, ...]) -> None:
        self._specs.append((kind, keys, data))
        self._pending.append((kind, keys, data))

    def _launch(self, t: int, raw: Pose, pts: FloatArray, fix: FloatArray) -> None:
        g = gtsam_module()
        self._reset()
        self._isam = self._new_isam(g)
        self._pending: list[tuple[str, tuple[int, ...], tuple[Any, ...]]] = []
        self.start_ne = fix.copy()
        self._t.append(t)
        self._compass.append(raw.yaw_rad)
        self._att.append((raw.down_m, raw.roll_rad, raw.pitch_rad))
        self._scan[0] = (self._level(raw, pts), raw.down_m)
        b, s_th = self.compass_bias or (0.0, math.radians(self.cfg.compass_bias_deg))
        mean = np.array([fix[0], fix[1], raw.yaw_rad - b])
        s_xy = self.cfg.launch_sigma_m
        self._add("prior", (0,), (mean, np.diag([1 / s_xy**2, 1 / s_xy**2, 1 / s_th**2])))
        self._last_compass_t = t
        self._new_values = {0: mean}
        self._solve()
        self._then[0] = mean.copy()

    def _new_isam(self, g: Any) -> Any:
        gc = self.gcfg
        heading = None if gc.relinearize_heading_rad == gc.relinearize_threshold else gc.relinearize_heading_rad
        return isam2(g, gc.relinearize_threshold, gc.relinearize_skip, heading)

    @staticmethod
    def _level(raw: Pose, pts: FloatArray) -> FloatArray:
        """Points (M, 3) in the level frame at the vehicle: NED axes turned by the compass's heading only."""
        return pts @ R_ned_from_body(raw.roll_rad, raw.pitch_rad, 0.0).T

    def _odometry(self, key: int, t: int, raw: Pose, pts: FloatArray) -> str:
        """The new pose's initial value, its odometry factor from the previous pose and the velocity factor."""
        gcfg = self.gcfg
        prev = key - 1
        dt = (t - self._t[prev]) * 1e-9
        dyaw = math.remainder(raw.yaw_rad - self._compass[prev], 2 * math.pi)
        level = self._level(raw, pts)
        self._t.append(t)
        self._compass.append(raw.yaw_rad)
        self._att.append((raw.down_m, raw.roll_rad, raw.pitch_rad))
        self._scan[key] = (level, raw.down_m)
        x_prev = self._est[prev]
        v = self.x[2:4]
        # the predicted move, in the previous pose's level frame (heading x_prev[2])
        r_prev = rot(float(x_prev[2]))
        pred = r_prev.T @ (v * dt)
        speed_var = (gcfg.max_speed_m_s * dt) ** 2
        walk_var = gcfg.velocity_walk_m_s**2 * dt**3 + (0.05 * dt) ** 2
        prior_cov = np.eye(2) * walk_var + self._vel_cov * dt * dt
        prev_level, prev_depth = self._scan.get(prev, (np.zeros((0, 3)), raw.down_m))
        new_rel = level @ rot3(dyaw).T + np.array([0.0, 0.0, raw.down_m - prev_depth])
        icp_cov = prior_cov + np.eye(2) * (gcfg.odometry_prior_m_s * dt) ** 2
        # the scan's own move (the prior's pull taken out) and a weak bound from the speed
        z, info2, pairs = odometry_factor(
            prev_level, new_rel, pred, icp_cov, speed_var, *guards(gcfg, self.odo_cfg, self.track.broken)
        )
        motion = "scan-odometry" if pairs else "motion-prior"
        # the between-factor's translation error lies in the frame turned by the measured turn
        r_d = rot(dyaw)
        info = np.zeros((3, 3))
        info[0:2, 0:2] = r_d.T @ info2 @ r_d
        yaw_sigma = max(math.radians(self.cfg.yaw_walk_deg_per_sqrt_s) * math.sqrt(dt), math.radians(0.02))
        info[2, 2] = 1.0 / yaw_sigma**2
        self._add("between", (prev, key), (np.array([z[0], z[1], dyaw]), info))
        if prev >= 1 and prev - 1 >= self._first_key:
            dt1 = (self._t[prev] - self._t[prev - 1]) * 1e-9
            sigma = gcfg.velocity_walk_m_s * math.sqrt(max(0.5 * (dt1 + dt), 1e-3))
            self._add("velocity", (prev - 1, prev, key), (dt1, dt, sigma))
        guess = x_prev.copy()
        guess[0:2] += r_prev @ z
        guess[2] = x_prev[2] + dyaw
        self._new_values = {key: guess}
        return motion

    def _compass_prior(self, key: int, t: int) -> None:
        gcfg = self.gcfg
        if self._last_compass_t is not None and t - self._last_compass_t < gcfg.compass_every_s * 1e9:
            return
        self._last_compass_t = t
        s = math.radians(gcfg.compass_bias_deg)
        mean = np.array([0.0, 0.0, self._compass[key] - (self.compass_bias or (0.0,))[0]])
        self._add("prior", (key,), (mean, np.diag([1e-10, 1e-10, 1.0 / s**2])))

    def _solve(self, all_keys: bool = False) -> None:
        """Feed the pending factors and new values to iSAM2; refresh the latest estimate and its covariance."""
        g = gtsam_module()
        graph = g.NonlinearFactorGraph()
        for kind, keys, data in self._pending:
            graph.add(make_factor(g, kind, keys, data))
        values = g.Values()
        for k, x in self._new_values.items():
            values.insert(k, pose2(g, x))
        for pid in self._new_offsets:
            values.insert(g.symbol("p", pid), np.zeros(1))
        for sid in self._new_stretches:
            values.insert(g.symbol("s", sid), np.zeros(2))
        self._new_offsets, self._new_stretches = set(), set()
        self._isam.update(graph, values)
        self._pending = []
        self._new_values = {}
        self._refresh(all_keys)

    def _refresh(self, all_keys: bool = False) -> None:
        """The latest pose's estimate and marginal covariance (every pose's estimate with ``all_keys``)."""
        n = len(self._t)
        last = n - 1
        if self._est.shape[0] < n:
            grown = np.zeros((n, 3))
            grown[: self._est.shape[0]] = self._est
            self._est = grown
        if all_keys:
            est = self._isam.calculateEstimate()
            for k in range(self._first_key, n):
                if est.exists(k):
                    p = est.atPose2(k)
                    self._est[k] = (p.x(), p.y(), p.theta())
        else:
            for k in {last, max(self._first_key, last - 1), max(self._first_key, last - 5)}:
                p = self._isam.calculateEstimatePose2(k)
                self._est[k] = (p.x(), p.y(), p.theta())
        arr = self._est
        self._cov = global_cov(np.asarray(self._isam.marginalCovariance(last)), float(arr[last, 2]))
        # the velocity over the last few poses (what predicts the next move)
        back = max(self._first_key, last - 5)
        if last > back:
            dt = (self._t[last] - self._t[back]) * 1e-9
            v = (arr[last, 0:2] - arr[back, 0:2]) / dt
            speed = float(np.hypot(*v))
            self.x[2:4] = v * min(1.0, self.gcfg.max_speed_m_s / max(speed, 1e-9))
        self._vel_cov = np.eye(2) * (self.gcfg.velocity_walk_m_s**2 * 0.1)
        self.x[0:2] = arr[last, 0:2]
        self.x[4] = math.remainder(float(arr[last, 2]) - self._compass[last], 2 * math.pi)

    _vel_cov = np.eye(2) * 1e-3
    _pending: list[tuple[str, tuple[int, ...], tuple[Any, ...]]]
    _new_values: dict[int, FloatArray]

    def _forget(self, key: int) -> None:
        """Scans older than the previous one are not needed (odometry pairs consecutive scans)."""
        self._scan.pop(key - 2, None)

    # -- the bounded window ----------------------------------------------------------------------------------

    def _rebase(self) -> None:
        """Rebuild the graph from its last ``window_s``: the first kept pose tied by its marginal (a
        marginalisation of everything before it)."""
        t_cut = self._t[-1] - int(self.gcfg.window_s * 1e9)
        import bisect

        first = max(self._first_key, bisect.bisect_left(self._t, t_cut))
        self._refresh(all_keys=True)
        cov = global_cov(np.asarray(self._isam.marginalCovariance(first)), float(self._est[first, 2]))
        self._rebuild(first, (self._est[first].copy(), np.asarray(np.linalg.inv(cov), dtype=np.float64)))

    def _rebuild(self, first: int, marginal: tuple[FloatArray, FloatArray] | None) -> None:
        g = gtsam_module()
        specs = [s for s in self._specs if s[1] and min(s[1]) >= first]
        planes = {int(s[2][0]) for s in specs if s[0] in ("plane", "anchored", "plane_shared")}
        shared = {int(s[2][7]) for s in specs if s[0] == "plane_shared"}
        specs = (
            [s for s in self._specs if s[0] == "plane_prior" and int(s[2][0]) in planes]
            + [s for s in self._specs if s[0] == "stretch_prior" and int(s[2][0]) in shared]
            + specs
        )
        self._plane_ids, self._stretch_ids = planes, shared
        self._new_offsets, self._new_stretches = set(planes), set(shared)
        if marginal is not None:
            specs.insert(0, ("prior", (first,), marginal))
        self._first_key = first
        self._specs = specs
        self._then = {k: v for k, v in self._then.items() if k >= first}
        self._isam = self._new_isam(g)
        self._pending = list(specs)
        self._new_values = {k: self._est[k] for k in range(first, len(self._t))}
        self._solve(all_keys=True)

    # -- the estimate ----------------------------------------------------------------------------------------

    def _unknown(self, t: int, raw: Pose) -> NavEstimate:
        cfg = self.cfg
        att = cfg.attitude_std_deg
        std = {"north_m": math.inf, "east_m": math.inf, "down_m": cfg.depth_std_m}
        std.update(roll_deg=att, pitch_deg=att, yaw_deg=math.inf)
        return NavEstimate(self.robot, t, None, std, dict.fromkeys(AXES, False), False, "unknown")

    def _estimate(
        self, t: int, raw: Pose, h3: FloatArray, inliers: int, used: tuple[int, ...], motion: str
    ) -> NavEstimate:
        cfg = self.cfg
        constrained, pinned, free_bearing = scan_constraint(h3, inliers, cfg)
        x = self._est[-1]
        cov = self._cov
        sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
        if self.track.broken:
            # nothing pins a broken track: its marginal rests on scan odometry that walks off by decimetres while it
            # claims centimetres, so the status says how far the robot can have gone since the break
            sd[0:2] = np.maximum(sd[0:2], self.track.reach_m(t, self.gcfg.max_speed_m_s) / 3.0)
        att = cfg.attitude_std_deg
        std = {"north_m": float(sd[0]), "east_m": float(sd[1]), "down_m": cfg.depth_std_m}
        std.update(roll_deg=att, pitch_deg=att, yaw_deg=math.hypot(math.degrees(float(sd[2])), att))
        corr = math.remainder(float(x[2]) - self._compass[-1], 2 * math.pi)
        pose = Pose(float(x[0]), float(x[1]), raw.down_m, raw.roll_rad, raw.pitch_rad, raw.yaw_rad + corr)
        worst = max(float(sd[0]), float(sd[1]))
        # placed while the position is known well enough: pinned to the map in both directions by this scan, or
        # (before there is a map here: the first scans make it) within boot_std_m of the launch on odometry alone
        pinned_both = constrained["north"] and constrained["east"]
        placed = not self.lost and not self.track.broken and worst <= self.gcfg.place_std_m
        placed = placed and (pinned_both or worst <= self.gcfg.boot_std_m)
        corr_deg = {"yaw_deg": math.degrees(corr)}
        return NavEstimate(self.robot, t, pose, std, constrained, placed, motion, inliers, used, corr_deg, pinned,
                           free_bearing)  # fmt: skip


def start_graph(
    robot: str,
    cfg: NavConfig,
    graph: GraphConfig | None,
    launch: tuple[int, Pose, Any],
    landmarks: PlaneLandmarks,
) -> GraphNav:
    """A robot's pose graph started at its launch cloud ``launch`` (t_ns, raw pose with the fix, body points);
    raises :class:`MapInputError` when GTSAM is missing."""
    nav = GraphNav(robot, cfg, graph)
    nav.update(launch[0], launch[1], launch[2], landmarks)
    return nav


def is_graph_state(snap: Any) -> bool:
    """Whether an estimator's :meth:`snapshot` is a :class:`GraphNav`'s (else a filter's)."""
    return isinstance(snap, dict) and bool(snap.get("graph"))
