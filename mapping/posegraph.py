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
from .graph_gate import LEVER_M, TrackGate, ambiguous, relocalize, verify
from .graph_heading import heading_offset
from .graph_hold import CloudHold, check_due, check_held, hold_step
from .landmarks import PlaneLandmarks, associate, take_planes
from .nav_config import AXES, NavConfig, NavEstimate, registration_points, scan_constraint
from .odometry import OdometryConfig, increment

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
        self.odo_cfg = OdometryConfig()
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
            h3, inliers, used = self._register(key, raw, pts, landmarks, t)
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
                self._check_heading(key, t, raw, pts, landmarks)
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
        self._isam = isam2(g)
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
        new_rel = (
            level
            @ np.array(
                [[math.cos(dyaw), -math.sin(dyaw), 0.0], [math.sin(dyaw), math.cos(dyaw), 0.0], [0.0, 0.0, 1.0]]
            ).T
        )
        new_rel = new_rel + np.array([pred[0], pred[1], raw.down_m - prev_depth])
        h = np.zeros((2, 2))
        z = pred.copy()
        motion = "motion-prior"
        if prev_level.shape[0] and new_rel.shape[0]:
            d, cov, pairs = increment(prev_level, new_rel, prior_cov, self.odo_cfg)
            if pairs:
                p_inv = np.linalg.inv(prior_cov)
                h = np.linalg.inv(cov) - p_inv
                h = 0.5 * (h + h.T) * gcfg.odometry_info_scale
                # the scan's own solution (the prior's pull taken out): along an unobserved direction it is the
                # prediction, which the information there (none) does not hold
                z = pred + np.linalg.solve(h + np.eye(2) * 1e-6, (p_inv + h) @ d)
                motion = "scan-odometry"
        # the move's information: the scan's, plus a weak bound from the speed
        info2 = h + np.eye(2) / speed_var
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

    def _check_heading(self, key: int, t: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks) -> None:
        """The heading of pose ``key`` checked against the walls (:mod:`mapping.graph_heading`) the robot contributed
        at most ``heading_own_share`` of the points to, every ``heading_every_s``: a prior on it at the heading the
        walls say, ``heading_floor_deg`` at least. Its own walls would carry its own heading error back.
        """
        gcfg = self.gcfg
        if self._last_heading_t is not None and t - self._last_heading_t < gcfg.heading_every_s * 1e9:
            return
        if len(lm) == 0:
            return
        use = np.ones(len(lm), dtype=bool)
        for i, c in enumerate(lm.contrib or ()):
            mine = c.get(self.robot)
            if mine is not None and mine[0] > gcfg.heading_own_share * sum(v[0] for v in c.values()):
                use[i] = False
        if not use.any():
            return
        x = self._est[key]
        got = heading_offset(pts, raw, x, take_planes(lm, use), self.cfg)
        if got is None:
            return
        off, sd, _ = got
        if abs(off) > math.radians(gcfg.heading_max_deg):
            return
        self._last_heading_t = t
        sd = max(sd, math.radians(gcfg.heading_floor_deg))
        mean = np.array([float(x[0]), float(x[1]), float(x[2]) - off])
        self._add("prior", (key,), (mean, np.diag([1e-10, 1e-10, 1.0 / sd**2])))
        self.headings += 1
        self._solve()

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
        self._new_offsets = set()
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

    # -- the map's planes ------------------------------------------------------------------------------------

    def _register(
        self, key: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks, t: int
    ) -> tuple[FloatArray, int, tuple[int, ...]]:
        """Register the scan to the map's planes: the others' as a unary factor, its own (old enough) as a loop
        closure to the pose that made them. Returns the information the scan gave (3x3, north/east/heading,
        global), the inliers and the planes used."""
        cfg = self.cfg
        if len(lm) == 0 or pts.shape[0] < cfg.min_inliers:
            return np.zeros((3, 3)), 0, ()
        own_anchor = np.full(len(lm), -1, dtype=np.int64)
        use = np.ones(len(lm), dtype=bool)
        if lm.contrib:
            horizon = t - int(self.gcfg.own_min_age_s * 1e9)
            for i, c in enumerate(lm.contrib):
                mine = c.get(self.robot)
                if mine is None or len(c) != 1:
                    continue
                use[i] = False
                if self.gcfg.own_planes and mine[1] <= horizon:
                    own_anchor[i] = self._key_at(mine[1])
        usable = use | (own_anchor >= self._first_key)
        if not usable.any():
            return np.zeros((3, 3)), 0, ()
        res = self._fit(key, raw, pts, take_planes(lm, usable), self.gcfg.map_min_sigma_m)
        if res is None:
            return np.zeros((3, 3)), 0, ()
        _, info, inliers, used, per_plane = res
        anchor_of = {int(lm.ids[i]): int(own_anchor[i]) for i in np.flatnonzero(own_anchor >= self._first_key)}
        loops = self._plane_factors(key, raw, per_plane, anchor_of, lm)
        self.loops += int(loops > 0)
        # what the scan pinned (reported as the filter reports it: the planes taken as they are)
        h_total = info
        if self._pending:
            self._solve()
        return h_total, inliers, tuple(used)

    def _plane_factors(
        self,
        key: int,
        raw: Pose,
        per_plane: list[tuple[int, FloatArray, float, FloatArray, int]],
        anchor_of: dict[int, int],
        lm: PlaneLandmarks | None = None,
    ) -> int:
        """One factor per plane this scan saw: the mean of its inliers on the plane, with an offset of the plane's
        own (a variable per plane, its prior ``map_plane_sigma_m``, ``own_sigma_m`` for the robot's own): the scans
        that see one plane share its error instead of each taking it as new evidence. A plane of the robot's own
        (``anchor_of``: plane id -> the pose whose cloud first made it) is expressed in the frame of that pose as
        it was when the cloud was placed, and moves with that pose: seeing it again relates the two poses (a loop
        closure), it does not fix this one. Returns the loop closures added."""
        cfg = self.cfg
        x = self._est[key]
        loops = 0
        for pid, n, d, c, m in per_plane:
            if abs(float(n[2])) > 0.5:
                continue  # a floor or a ceiling: depth is measured, it says nothing horizontal
            anchor = anchor_of.get(pid)
            then = self._then.get(anchor) if anchor is not None else None
            if anchor is not None and then is None:
                continue
            sigma_plane = self.gcfg.own_sigma_m if anchor is not None else self.gcfg.map_plane_sigma_m
            sigma = max(cfg.point_sigma_m, self.gcfg.map_min_sigma_m) / math.sqrt(min(m, cfg.max_independent_points))
            const = float(n[2]) * (raw.down_m + float(c[2])) + d
            nh = n[0:2].astype(np.float64)
            off = self._offset(pid)
            if anchor is None or then is None:
                e = float(nh @ (x[0:2] + rot(float(x[2])) @ c[0:2])) + const + off
                kind, keys = "plane", (key,)  # type: tuple[str, tuple[int, ...]]
                data = (pid, float(nh[0]), float(nh[1]), float(c[0]), float(c[1]), const, sigma)
            else:
                # the plane in the anchor's frame as it was placed: n_loc . q + const_loc = 0 for q in that frame
                n_loc = rot(float(then[2])).T @ nh
                const_loc = const + float(nh @ then[0:2])
                xa = self._est[anchor]
                u = x[0:2] + rot(float(x[2])) @ c[0:2] - xa[0:2]
                e = float(n_loc @ rot(float(xa[2])).T @ u) + const_loc + off
                kind, keys = "anchored", (anchor, key)
                data = (pid, float(n_loc[0]), float(n_loc[1]), float(c[0]), float(c[1]), const_loc, sigma)
            if abs(e) > self.gcfg.plane_gate_m:
                self.gated += 1
                continue
            if self.gcfg.second_hypothesis and lm is not None and self._ambiguous(pid, n, d, c, x, raw, lm):
                self.ambiguous += 1
                continue
            if pid not in self._plane_ids:
                self._plane_ids.add(pid)
                self._add("plane_prior", (), (pid, sigma_plane))
                self._new_offsets.add(pid)
            self._add(kind, keys, data)
            loops += int(kind == "anchored")
        return loops

    def _ambiguous(
        self, pid: int, n: FloatArray, d: float, c: FloatArray, x: FloatArray, raw: Pose, lm: PlaneLandmarks
    ) -> bool:
        """:func:`mapping.graph_gate.ambiguous` at this pose's marginal."""
        margins = (self.cfg.extent_margin_m, self.cfg.extent_margin_down_m)
        return ambiguous(pid, n, d, c, x, raw.down_m, self._cov, lm, margins)

    def _offset(self, pid: int) -> float:
        """The current estimate of plane ``pid``'s offset (0 before it has one)."""
        if pid not in self._plane_ids or pid in self._new_offsets:
            return 0.0
        return float(self._isam.calculateEstimateVector(gtsam_module().symbol("p", pid))[0])

    def _key_at(self, t_ns: int) -> int:
        """The pose at or just after ``t_ns`` (-1 before the window)."""
        import bisect

        k = bisect.bisect_left(self._t, int(t_ns))
        return k if self._first_key <= k < len(self._t) else -1

    def _fit(
        self, key: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks, min_sigma: float
    ) -> tuple[FloatArray, FloatArray, int, list[int], list[tuple[int, FloatArray, float, FloatArray, int]]] | None:
        """Gauss-Newton over north, east and heading from the point-to-plane residuals, the pose's marginal as the
        prior; returns the scan's own solution (3,) and information (3x3, global axes), the inliers and plane ids,
        and per plane (id, normal (3,), d, the mean of its inlier points in the level frame (3,), inliers); or None
        (too few inliers, or a correction beyond the marginal: a wrong association)."""
        cfg = self.cfg
        x_pred = self._est[key].copy()
        p = self._cov
        p_inv = np.linalg.inv(p)
        nh = lm.normal[:, 0:2]
        along = np.einsum("pi,ij,pj->p", nh, p[0:2, 0:2], nh)
        gate = np.clip(3.0 * np.sqrt(along + 2.0**2 * p[2, 2]) + 0.05, cfg.gate_min_m, cfg.gate_max_m)
        x = x_pred.copy()
        h3 = np.zeros((3, 3))
        g3 = np.zeros(3)
        inl = 0
        ids: list[int] = []
        sigma = max(cfg.point_sigma_m, min_sigma)
        x_lin = x.copy()
        per_plane: list[tuple[int, FloatArray, float, FloatArray, int]] = []
        for it in range(cfg.iterations):
            x_lin = x.copy()
            r_nb = R_ned_from_body(raw.roll_rad, raw.pitch_rad, float(x[2]))
            veh = np.array([x[0], x[1], raw.down_m])
            rel = pts @ r_nb.T
            k, dist = associate(rel + veh, veh, lm, gate, cfg)
            sel = k >= 0
            inl = int(sel.sum())
            if inl < cfg.min_inliers:
                return None
            n = lm.normal[k[sel]]
            r = dist[sel]
            relh = rel[sel]
            j = np.stack([n[:, 0], n[:, 1], -n[:, 0] * relh[:, 1] + n[:, 1] * relh[:, 0]], axis=1)
            w = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
            scale = min(1.0, cfg.max_independent_points / inl) / sigma**2
            h3 = scale * (j.T * w) @ j
            g3 = scale * (j.T * w) @ r
            x = np.asarray(np.linalg.solve(p_inv + h3, p_inv @ x_pred + h3 @ x - g3), dtype=np.float64)
            if it >= 1:
                gate = np.full(len(lm), max(cfg.gate_min_m, 4 * cfg.huber_m))
            ids = [int(i) for i in np.unique(lm.ids[k[sel]])]
            # per plane: the mean of its inliers in the level frame (the heading of this linearisation taken out)
            lvl = relh @ R_ned_from_body(0.0, 0.0, -float(x_lin[2])).T
            per_plane = []
            for kk in np.unique(k[sel]):
                on = k[sel] == kk
                per_plane.append(
                    (int(lm.ids[kk]), lm.normal[kk].copy(), float(lm.d[kk]), lvl[on].mean(axis=0), int(on.sum()))
                )
        dx = x - x_pred
        if float(dx @ p_inv @ dx) > self.gcfg.map_gate_chi2:
            # a correction the pose's marginal cannot explain: a wrong association, not drift
            self.gated += 1
            return None
        # the scan's own solution at the last linearisation (the prior taken out): H (z - x_lin) = -g, in the
        # directions the scan observes well enough (in metres, the heading at a 2 m lever): a weakly observed one
        # would carry the linearisation far off with a little information
        unit = np.array([1.0, 1.0, 1.0 / LEVER_M])
        hs = h3 * unit[:, None] * unit[None, :]
        lam, vec = np.linalg.eigh(0.5 * (hs + hs.T))
        keep = lam >= 1.0 / self.gcfg.observed_std_m**2
        if not keep.any():
            return None
        vk, lk = vec[:, keep], lam[keep]
        gs = g3 * unit
        z = x_lin - unit * (vk @ ((vk.T @ gs) / lk))
        h_kept = (vk * lk) @ vk.T / unit[:, None] / unit[None, :]
        return z, 0.5 * (h_kept + h_kept.T), inl, ids, per_plane

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
        planes = {int(s[2][0]) for s in specs if s[0] in ("plane", "anchored")}
        specs = [s for s in self._specs if s[0] == "plane_prior" and int(s[2][0]) in planes] + specs
        self._plane_ids = planes
        self._new_offsets = set(planes)
        if marginal is not None:
            specs.insert(0, ("prior", (first,), marginal))
        self._first_key = first
        self._specs = specs
        self._then = {k: v for k, v in self._then.items() if k >= first}
        self._isam = isam2(g)
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
        placed = placed and (t - max(self._t[0], self.track.verified_ns)) * 1e-9 <= self.gcfg.place_verified_s
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
