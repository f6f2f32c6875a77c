"""Laser-aided navigation: each robot's horizontal position and heading correction, estimated from its scans.

Attitude (roll, pitch) and depth are measured well by every pose source; what a small ROV does not know is
where it is horizontally (no fix at all, or dead reckoning that drifts) and its true heading (a compass near
steel is off by degrees). So the estimator has five states per robot, in NED (metres, m/s, radians)::

    x = [north, east, bias_north, bias_east, yaw_correction]

(``bias``: the dead reckoning's velocity bias, m/s, as from a current's drag) and the corrected pose is
``(north, east, raw down, raw roll, raw pitch, raw yaw + yaw_correction)``.

One step per cloud (:meth:`RobotNav.update`), a Kalman filter whose measurement update is a robust
scan-to-map registration:

1. **Predict.** With dead reckoning (the raw pose has a horizontal position, and had one at the previous
   cloud), the raw position's increment, turned by the current yaw correction (the compass bias turned it
   too), moves the position, and so does the velocity bias times the time (a slow random walk,
   ``dr_bias_sigma_m_s`` / ``dr_bias_walk_m_s_per_sqrt_s``): the error of a dead reckoning in a current grows
   with time, not with its square root, and registrations that pin an axis estimate the bias along it, so the
   prediction follows the drift along an axis no scan pins and its covariance grows as the drift can. The
   noise also grows with the distance (``dr_scale_sigma``) and with time (``dr_velocity_sigma_m_s``, white).
   Without a fix, the position is a random walk (``walk_speed_m_s``).
   The yaw correction is a random walk (``yaw_walk_deg_per_sqrt_s``).
2. **Fix.** A raw horizontal position is also a weak absolute measurement (``fix_sigma_m``, at most once per
   ``fix_every_s``): dead reckoning's absolute error is unknown, so it only anchors a robot the scans cannot.
3. **Register.** The cloud's points (sub-sampled) are placed with the predicted pose and associated with the
   nearest map plane (:class:`PlaneLandmarks`) that faces the vehicle, whose extent (inflated) contains the
   point and which lies within a gate set by the predicted uncertainty along its normal. The point-to-plane
   residuals (Huber-weighted) over the three unknowns (north, east, yaw correction) and the prediction are
   solved together by Gauss-Newton (a few re-associations): the MAP estimate of an iterated Kalman update.
   Points of one scan share pose and map errors, so the registration counts at most
   ``max_independent_points`` of them.
4. **Report.** The registration's own information matrix ``H`` (3x3 over north, east, yaw) says what the scan
   constrains: an axis whose standard deviation from ``H`` alone exceeds ``constrained_std_m`` /
   ``constrained_std_deg`` is not constrained (one flat wall: the position along it). The posterior covariance
   gives the ``*_std`` of the estimate; a cloud is *placed* (mapped) only while both horizontal standard
   deviations stay below ``place_std_m``.

The map (``mapping.MapBuilder``) owns the planes; the estimator only reads them (:meth:`MapBuilder.landmarks`).
Everything here is numpy: the problem is three unknowns with a Kalman prior, solved in well under a millisecond
(see docs/navigation.md for the choice against GTSAM, Open3D ICP and scipy).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .errors import MapInputError
from .landmarks import PlaneLandmarks, associate, subsample
from .nav_frame import NavFrame, rot2

__all__ = [
    "AXES",
    "NavConfig",
    "NavEstimate",
    "NavFrame",
    "Navigator",
    "PlaneLandmarks",
    "RobotNav",
    "associate",
    "subsample",
]

FloatArray = NDArray[np.float64]
log = logging.getLogger(__name__)

#: The axes whose constraint is reported.
AXES = ("north", "east", "yaw")


@dataclass(frozen=True)
class NavConfig:
    """Tuning of :class:`Navigator` (metres, seconds, degrees where named ``_deg``).

    Registration: ``max_points`` body points per scan (evenly sub-sampled) within ``max_range_m``;
    ``point_sigma_m`` the noise of one point-to-plane residual, Huber-weighted beyond ``huber_m``; at most
    ``max_independent_points`` count as independent; ``iterations`` re-associations; a point joins a plane within
    ``gate_min_m`` .. ``gate_max_m`` (3 sigma of the predicted position along the plane's normal, + 5 cm) and
    within its extent inflated by ``extent_margin_m`` horizontally and ``extent_margin_down_m`` in depth (faces
    are mapped in horizontal bands); a registration needs ``min_inliers`` points; planes with fewer than
    ``min_landmark_points`` points are not used.

    Motion: ``dr_scale_sigma`` per metre of dead-reckoned distance, ``dr_velocity_sigma_m_s`` (white velocity
    noise), the dead reckoning's velocity bias (a state: ``dr_bias_sigma_m_s`` at launch, a random walk of
    ``dr_bias_walk_m_s_per_sqrt_s``; ``dr_bias_sigma_m_s`` 0 leaves it out, the model before it; small at launch,
    so that the first seconds, when a fleet's first scans make the map, keep the dead reckoning's increments),
    ``walk_speed_m_s`` (the random walk of the position without a fix), ``yaw_walk_deg_per_sqrt_s``; fixes are
    absolute measurements at most every ``fix_every_s``, their sigma ``fix_quality_factor`` x the RMS of their
    disagreement with the estimate over ``fix_quality_s`` (a drifting dead reckoning earns a weak one), within
    ``fix_min_sigma_m`` .. ``fix_sigma_m``; the compass's bias is within ``compass_bias_deg`` (a pull of the yaw
    correction to 0, as often as fixes). With the bias state, a fix's sigma is at least its disagreement now, and
    with ``fix_persistence`` the fixes of a disagreement that persists (its running mean near its RMS) beyond
    ``fix_persist_min_m`` count as one per ``fix_quality_s``, not one per ``fix_every_s``: a dead reckoning's
    drift is not white noise. Initial ``launch_sigma_m``, ``init_speed_sigma_m_s`` (the velocity states without the
    bias), ``init_yaw_sigma_deg``.

    Reporting: ``constrained_std_m`` / ``constrained_std_deg`` (registration-only standard deviation under which
    an axis counts as constrained), ``place_std_m`` (clouds of a robot whose horizontal standard deviation
    exceeds it are not placed in the map), ``lost_std_m`` (without a fix, a robot whose predicted standard
    deviation exceeds it is lost: its scans are not registered or placed until the next fix), ``depth_std_m`` /
    ``attitude_std_deg`` (reported for the measured axes); ``frame_min_scans``: a robot's yaw correction counts
    in :meth:`Navigator.frame` once that many scans constrained its heading; with smoothing, launch points
    ``frame_min_baseline_m`` apart fix the frame's heading instead.

    Heading: with ``yaw_bias_tau_s`` > 0 the yaw correction is the negative of a compass bias that wanders as an
    Ornstein-Uhlenbeck process (stationary standard deviation ``yaw_bias_std_deg``, correlation time
    ``yaw_bias_tau_s``): bounded and mean-reverting, so no run of registrations can carry it far past what a
    compass does (the random walk and ``compass_bias_deg`` pulls are then off). ``yaw_bias_tau_s`` 0 restores the
    walk.

    Evidence: a plane only this robot contributed to, first seen by it less than ``own_recent_s`` before the scan,
    holds the robot's own recent poses and so no absolute information; its residuals count ``own_recent_weight``
    of their information. Such planes were placed with the robot's own heading and say nothing of its compass's
    bias: with ``own_recent_turns`` False they move the position only, not the heading; with
    ``own_recent_turns_alone`` False, only while the map has not joined the robot's part to another robot's
    (:attr:`RobotNav.joined`). With ``own_turn_s`` > 0, no plane only this robot contributed to, first seen by it
    less than ``own_turn_s`` before the scan, turns its heading. A registration whose correction lies beyond the
    prediction's error model (squared Mahalanobis distance over north, east, yaw above ``gate_chi2``) is a wrong
    association, not drift: it is rejected and counted (:attr:`RobotNav.gated`).

    Scan odometry (``scan_odometry``, off by default: see docs/navigation.md "Limits"; :mod:`mapping.odometry`):
    without a fix, the increment from the previous scan (at most ``odometry_max_dt_s`` before) replaces the walk
    where the two scans observe it. A cloud without a fix is placed when its scan pinned both horizontal axes to
    the map, or, with scan odometry, while the robot's horizontal standard deviation is within
    ``bootstrap_std_m`` (from its launch fix on): the first scans of a fleet that has no map yet make the map.

    Pose graph (``graph_without_fix``, off by default): a robot whose fixes stop within ``launch_window_s`` of its
    first (a launch fix only) is navigated by a pose graph of its own (:class:`mapping.posegraph.GraphNav`, GTSAM)
    instead of this filter, from its last launch cloud on. Off because the graphs track such a robot for tens of
    seconds, then slide along walls the scans do not pin while their covariance still says centimetres: the map
    gains spurious planes (docs/navigation.md, "Limits"). Off, such a robot is reported ``lost`` and its clouds
    stay unplaced: an empty part of the map rather than a wrong one.
    """

    max_points: int = 300
    max_range_m: float = 4.0
    point_sigma_m: float = 0.02
    huber_m: float = 0.02
    max_independent_points: int = 50
    iterations: int = 4
    gate_min_m: float = 0.1
    gate_max_m: float = 0.3
    extent_margin_m: float = 0.25
    extent_margin_down_m: float = 1.5
    min_inliers: int = 20
    min_landmark_points: int = 300
    dr_scale_sigma: float = 0.03
    dr_velocity_sigma_m_s: float = 0.02
    dr_bias_sigma_m_s: float = 0.0
    dr_bias_walk_m_s_per_sqrt_s: float = 0.003
    fix_persistence: bool = True
    fix_persist_min_m: float = 0.1
    walk_speed_m_s: float = 0.3
    yaw_walk_deg_per_sqrt_s: float = 0.1
    fix_sigma_m: float = 0.5
    fix_quality_factor: float = 1.5
    fix_min_sigma_m: float = 0.02
    fix_quality_s: float = 20.0
    fix_every_s: float = 0.2
    launch_sigma_m: float = 0.05
    init_speed_sigma_m_s: float = 0.3
    init_yaw_sigma_deg: float = 3.0
    compass_bias_deg: float = 3.0
    constrained_std_m: float = 0.05
    constrained_std_deg: float = 1.0
    place_std_m: float = 0.3
    lost_std_m: float = 0.3
    depth_std_m: float = 0.01
    attitude_std_deg: float = 0.2
    frame_min_scans: int = 20
    frame_min_baseline_m: float = 2.0
    scan_odometry: bool = False
    odometry_max_dt_s: float = 0.5
    bootstrap_std_m: float = 0.1
    yaw_bias_std_deg: float = 2.0
    yaw_bias_tau_s: float = 0.0
    own_recent_s: float = 20.0
    own_recent_weight: float = 0.03
    own_recent_turns: bool = True
    own_turn_s: float = 0.0
    own_recent_turns_alone: bool = True
    gate_chi2: float = 0.0
    graph_without_fix: bool = False
    launch_window_s: float = 2.0


@dataclass(frozen=True)
class NavEstimate:
    """A robot's corrected pose at one cloud (what ``<root>/<robot>/nav`` publishes).

    Attributes:
        robot, t_ns: the robot and the cloud's capture time (ns since the epoch).
        pose: the corrected pose (NED, radians); None when the robot's position is unknown (no fix ever).
        std: standard deviations: ``north_m``, ``east_m``, ``down_m`` (m), ``roll_deg``, ``pitch_deg``,
            ``yaw_deg`` (deg).
        constrained: per axis of :data:`AXES`, whether this scan constrained it.
        placed: whether the cloud may go into the map (position known well enough).
        motion: how the position moved since the last cloud: ``dead-reckoning``, ``motion-prior``, ``start``, or
            ``lost`` (no fix, and too uncertain to trust a scan: see ``NavConfig.lost_std_m``).
        inliers: points associated with map planes (0: no registration).
        planes: ids of the planes the scan was registered to.
        correction: the yaw correction (deg) and, with a raw fix, the horizontal offset from it (m).
        pinned: horizontal directions this scan pinned to the map (0, 1 or 2; along the registration
            information's eigenvectors, so an oblique wall counts as one too).
        free_bearing_deg: with one pinned direction (degenerate geometry: one flat wall, parallel walls), the
            bearing of the free one (deg from north, 0-180): the position along it is not observed; else None.
    """

    robot: str
    t_ns: int
    pose: Pose | None
    std: dict[str, float]
    constrained: dict[str, bool]
    placed: bool
    motion: str
    inliers: int = 0
    planes: tuple[int, ...] = ()
    correction: dict[str, float] = field(default_factory=dict)
    pinned: int = 0
    free_bearing_deg: float | None = None

    def turned(self, frame: NavFrame) -> NavEstimate:
        """This estimate with its pose turned from the map frame to NED (see :class:`NavFrame`)."""
        if self.pose is None or frame.identity:
            return self
        free = self.free_bearing_deg
        if free is not None:
            free = (free - math.degrees(frame.yaw_rad)) % 180.0
        return replace(self, pose=frame.pose(self.pose), free_bearing_deg=free)

    def to_json(self) -> dict[str, Any]:
        """The JSON of CONVENTIONS' ``<root>/<robot>/nav`` key (angles in degrees, null when unknown)."""
        p = self.pose
        out: dict[str, Any] = {
            "robot": self.robot,
            "t_ns": self.t_ns,
            "north_m": p.north_m if p else None,
            "east_m": p.east_m if p else None,
            "down_m": p.down_m if p else None,
            "roll_deg": math.degrees(p.roll_rad) if p else None,
            "pitch_deg": math.degrees(p.pitch_rad) if p else None,
            "yaw_deg": math.degrees(p.yaw_rad) if p else None,
        }
        for k, v in self.std.items():
            out[f"{k}_std"] = v if math.isfinite(v) else None
        out["constrained"] = [a for a in AXES if self.constrained.get(a)]
        out["unconstrained"] = [a for a in AXES if not self.constrained.get(a)]
        out.update(placed=self.placed, motion=self.motion, inliers=self.inliers, planes=list(self.planes))
        out["correction"] = dict(self.correction)
        out["degenerate"] = {"free_bearing_deg": self.free_bearing_deg} if self.free_bearing_deg is not None else None
        return out


class RobotNav:
    """The estimator of one robot (see the module docstring). Not thread-safe: one thread feeds it."""

    def __init__(self, robot: str, cfg: NavConfig) -> None:
        self.robot = robot
        self.cfg = cfg
        self.x = np.zeros(5)
        self.P = np.eye(5)
        self.t_ns: int | None = None
        self.last_raw_ne: FloatArray | None = None
        self.last_fix_ns: int | None = None
        self.latest: NavEstimate | None = None
        #: where the robot started (its first fix), and how many scans constrained its heading
        self.start_ne = np.zeros(2)
        self.yaw_scans = 0
        #: running mean square of the fixes' disagreement with the estimate, per axis (m^2)
        self.fix_err2 = 0.0
        #: running mean of the fixes' disagreement (north, east; m): a persistent one is a drift, not noise
        self.fix_mean = np.zeros(2)
        self.last_compass_ns: int | None = None
        #: no fix and an uncertainty past ``lost_std_m``: the scans are not trusted until the next fix
        self.lost = False
        #: the last update's prediction (state, covariance) and transition from the previous state (5x5): what a
        #: smoother (:mod:`mapping.smoother`) needs to run backward; None after a start
        self.prior: tuple[FloatArray, FloatArray] | None = None
        self.transition: FloatArray | None = None
        #: the previous scan for scan odometry: points relative to the vehicle (NED axes), and its depth
        self._prev_scan: tuple[FloatArray, float] | None = None
        self.odometry_pairs = 0
        #: registrations rejected as beyond the motion model's error (see ``NavConfig.gate_chi2``)
        self.gated = 0
        #: whether the map joins this robot's part to another robot's (set by :class:`Navigator` before each update;
        #: see ``NavConfig.own_recent_turns_alone``)
        self.joined = True

    _STATE = (
        "t_ns",
        "gated",
        "last_raw_ne",
        "last_fix_ns",
        "start_ne",
        "yaw_scans",
        "fix_err2",
        "fix_mean",
        "last_compass_ns",
        "lost",
        "_prev_scan",
    )

    def snapshot(self) -> dict[str, Any]:
        """The estimator's whole state (a smoother restarts it from here to re-run later scans)."""
        out: dict[str, Any] = {k: getattr(self, k) for k in self._STATE}
        out.update(x=self.x.copy(), P=self.P.copy(), latest=self.latest)
        return out

    def restore(self, snap: dict[str, Any]) -> None:
        """Back to a :meth:`snapshot`."""
        for k in self._STATE:
            setattr(self, k, snap[k])
        self.x = snap["x"].copy()
        self.P = snap["P"].copy()
        self.latest = snap["latest"]

    @property
    def started(self) -> bool:
        """Whether the robot's position is known (it had a horizontal fix once)."""
        return self.t_ns is not None

    def _start(self, t_ns: int, raw_ne: FloatArray) -> None:
        cfg = self.cfg
        self.x = np.array([raw_ne[0], raw_ne[1], 0.0, 0.0, 0.0])
        bias = cfg.dr_bias_sigma_m_s if cfg.dr_bias_sigma_m_s > 0 else cfg.init_speed_sigma_m_s
        self.P = np.diag(
            [
                cfg.launch_sigma_m**2,
                cfg.launch_sigma_m**2,
                bias**2,
                bias**2,
                math.radians(cfg.init_yaw_sigma_deg) ** 2,
            ]
        )
        self.t_ns = t_ns
        self.last_fix_ns = t_ns
        self.start_ne = raw_ne.copy()
        self.fix_err2 = cfg.launch_sigma_m**2
        self.fix_mean = np.zeros(2)

    def _predict(
        self, dt: float, raw_ne: FloatArray | None, odo: tuple[FloatArray, FloatArray, int] | None = None
    ) -> str:
        cfg = self.cfg
        q = np.zeros((5, 5))
        ou = np.eye(5)
        if cfg.yaw_bias_tau_s > 0:
            # the compass bias is bounded and mean-reverting (Ornstein-Uhlenbeck): the correction decays toward 0
            # and its variance toward yaw_bias_std_deg^2
            a = math.exp(-max(dt, 0.0) / cfg.yaw_bias_tau_s)
            ou[4, 4] = a
            self.x[4] *= a
            self.P = ou @ self.P @ ou.T
            q[4, 4] = math.radians(cfg.yaw_bias_std_deg) ** 2 * (1.0 - a * a)
        else:
            q[4, 4] = math.radians(cfg.yaw_walk_deg_per_sqrt_s) ** 2 * dt
        if raw_ne is not None and self.last_raw_ne is not None:
            step = rot2(float(self.x[4])) @ (raw_ne - self.last_raw_ne)
            f = np.eye(5)
            # the increment turns with the yaw correction: d(step)/dc = ez x step
            f[0:2, 4] = [-step[1], step[0]]
            self.x[0:2] += step
            if cfg.dr_bias_sigma_m_s > 0 and dt > 0:
                # a current's drag (or any slow velocity bias) moves the robot by bias * dt beyond what the dead
                # reckoning says: the position's error grows with time along whatever no scan pins
                f[0, 2] = f[1, 3] = dt
                self.x[0:2] += self.x[2:4] * dt
                q[2, 2] = q[3, 3] = cfg.dr_bias_walk_m_s_per_sqrt_s**2 * dt
            elif dt > 0:
                self.x[2:4] = step / dt
            self.transition = f @ ou
            self.P = f @ self.P @ f.T
            var = (cfg.dr_scale_sigma * float(np.hypot(*step))) ** 2 + (cfg.dr_velocity_sigma_m_s * dt) ** 2
            q[0, 0] = q[1, 1] = var
            motion = "dead-reckoning"
        else:
            # without dead reckoning the robot may be anywhere within its speed: a random walk. (A constant-
            # velocity prior looked better on paper; along a single wall its velocity is unobservable, and a
            # wrong one carried the robot metres away while the scans kept its std small across the wall.)
            # Consecutive scans of the same walls narrow the walk to the increment they see (scan odometry): a
            # relative measurement, so its covariance adds to the position's like dead reckoning's.
            if self.cfg.dr_bias_sigma_m_s <= 0:
                self.x[2:4] = 0.0
            self.transition = ou
            walk = np.eye(2) * cfg.walk_speed_m_s**2 * max(dt, 1e-3)
            motion = "motion-prior"
            if odo is not None and cfg.scan_odometry:
                delta, cov, pairs = odo
                if pairs:
                    # like dead reckoning's, the increment was turned by the yaw correction (the scans were
                    # placed with it): its uncertainty grows the position's with the distance
                    f = np.eye(5)
                    f[0:2, 4] = [-delta[1], delta[0]]
                    self.transition = f
                    self.P = f @ self.P @ f.T
                    self.x[0:2] += delta
                    walk = cov
                    motion = "scan-odometry"
            q[0:2, 0:2] = walk
        self.P = self.P + q
        return motion

    def _odometry(self, raw: Pose, pts: FloatArray, dt: float) -> tuple[FloatArray, FloatArray, int] | None:
        """Scan-to-scan increment (:mod:`mapping.odometry`) from the previous scan to ``pts`` (body, (M, 3)):
        (move (2,), covariance (2, 2), pairs), or None without a previous scan."""
        from .odometry import OdometryConfig, increment

        prev = self._prev_scan
        r_nb = R_ned_from_body(raw.roll_rad, raw.pitch_rad, raw.yaw_rad + float(self.x[4]))
        rel = pts @ r_nb.T
        self._prev_scan = (rel, raw.down_m)
        if prev is None or dt <= 0 or dt > self.cfg.odometry_max_dt_s:
            return None
        new_rel = rel + np.array([0.0, 0.0, raw.down_m - prev[1]])
        prior = np.eye(2) * self.cfg.walk_speed_m_s**2 * dt
        return increment(prev[0], new_rel, prior, OdometryConfig())

    def _compass(self, t_ns: int) -> None:
        """The compass's bias is bounded: a weak pull of the yaw correction toward zero, at most every
        ``fix_every_s`` (it keeps a heading the scans cannot hold from running away)."""
        cfg = self.cfg
        if cfg.yaw_bias_tau_s > 0:
            return  # the Ornstein-Uhlenbeck prediction bounds the correction already
        if self.last_compass_ns is not None and t_ns - self.last_compass_ns < cfg.fix_every_s * 1e9:
            return
        self.last_compass_ns = t_ns
        h = np.zeros((1, 5))
        h[0, 4] = 1.0
        s = float(self.P[4, 4]) + math.radians(cfg.compass_bias_deg) ** 2
        k = (self.P @ h.T) / s
        self.x = self.x - (k * float(self.x[4])).ravel()
        self.P = (np.eye(5) - k @ h) @ self.P

    def _fix(self, t_ns: int, raw_ne: FloatArray) -> None:
        cfg = self.cfg
        if self.last_fix_ns is not None and t_ns - self.last_fix_ns < cfg.fix_every_s * 1e9:
            return
        self.last_fix_ns = t_ns
        # how well the fixes agree with the estimate tells how good they are: a drifting dead reckoning drifts
        # away from what the scans say, a USBL or a good DVL does not
        innov = raw_ne - self.x[0:2]
        a = min(1.0, cfg.fix_every_s / cfg.fix_quality_s) if cfg.fix_every_s > 0 else 0.05
        self.fix_err2 = (1 - a) * self.fix_err2 + a * float(innov @ innov) / 2
        self.fix_mean = (1 - a) * self.fix_mean + a * innov
        err2 = self.fix_err2
        n_fixes = 1.0
        if cfg.dr_bias_sigma_m_s > 0 and cfg.fix_persistence:
            # with the velocity bias in the model the covariance grows as a drift can, and a dead reckoning that
            # drifted away since is no better than its disagreement now (the running mean lags it by seconds)
            err2 = max(err2, float(innov @ innov) / 2)
            # a dead reckoning's error persists (a drift, not noise): its fixes over fix_quality_s are one
            # measurement, not one per fix_every_s; taken as independent they dragged the estimate back to the
            # drift as soon as no scan pinned an axis. Persistence: the disagreement's mean against its RMS
            # (white fixes, a USBL's: about 0; a drift: 1)
            # (white fixes, a USBL's: about 0; a drift: 1). A disagreement within fix_persist_min_m is what the
            # map's own offset from the fixes leaves (good navigation): those fixes stay independent
            rho = float(self.fix_mean @ self.fix_mean) / max(2.0 * self.fix_err2, 1e-12)
            persist = min(1.0, max(0.0, (rho - 0.1) / 0.9))
            if math.sqrt(err2) > cfg.fix_persist_min_m:
                n_fixes = 1.0 + persist * cfg.fix_quality_s / max(cfg.fix_every_s, 1e-3)
        sigma = min(cfg.fix_sigma_m, max(cfg.fix_min_sigma_m, cfg.fix_quality_factor * math.sqrt(err2)))
        sigma *= math.sqrt(n_fixes)
        h = np.zeros((2, 5))
        h[0, 0] = h[1, 1] = 1.0
        s = h @ self.P @ h.T + np.eye(2) * sigma**2
        k = self.P @ h.T @ np.linalg.inv(s)
        self.x = self.x + k @ (raw_ne - self.x[0:2])
        self.P = (np.eye(5) - k @ h) @ self.P

    def _plane_weights(self, t_ns: int, lm: PlaneLandmarks) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(P,) information weight per plane: ``own_recent_weight`` for a plane only this robot made, first seen by
        it within ``own_recent_s`` (its own recent poses, no absolute information), 1 otherwise; and (P,) whether
        the plane may turn the heading (see ``NavConfig.own_turn_s``, ``own_recent_turns``)."""
        cfg = self.cfg
        w = np.ones(len(lm))
        turns = np.ones(len(lm), dtype=bool)
        if not lm.contrib:
            return w, turns
        horizon = t_ns - int(cfg.own_recent_s * 1e9)
        turn_horizon = t_ns - int(cfg.own_turn_s * 1e9) if cfg.own_turn_s > 0 else None
        for i, c in enumerate(lm.contrib):
            mine = c.get(self.robot)
            if mine is None or len(c) != 1:
                continue
            recent_turns = cfg.own_recent_turns and (self.joined or cfg.own_recent_turns_alone)
            if mine[1] >= horizon and (cfg.own_recent_weight < 1.0 or not recent_turns):
                w[i] = min(cfg.own_recent_weight, 1.0 - 1e-9)
                turns[i] = recent_turns
            if turn_horizon is not None and mine[1] >= turn_horizon:
                turns[i] = False
        return w, turns

    def _register(
        self, raw: Pose, points_body: FloatArray, lm: PlaneLandmarks, t_ns: int = 0
    ) -> tuple[FloatArray, int, tuple[int, ...]]:
        """Gauss-Newton MAP update of ``x``/``P`` from point-to-plane residuals; returns the registration's own
        information (3x3 over north, east, yaw correction), the inliers and the planes used."""
        cfg = self.cfg
        h3 = np.zeros((3, 3))
        if len(lm) == 0 or points_body.shape[0] < cfg.min_inliers:
            return h3, 0, ()
        idx = [0, 1, 4]
        x_pred = self.x.copy()
        p_inv = np.linalg.inv(self.P)
        x = x_pred.copy()
        pos_cov = self.P[np.ix_([0, 1], [0, 1])]
        nh = lm.normal[:, 0:2]
        along = np.einsum("pi,ij,pj->p", nh, pos_cov, nh)
        lever2 = 2.0**2 * self.P[4, 4]  # a point 2 m away moves by 2 m * yaw error
        gate = np.clip(3.0 * np.sqrt(along + lever2) + 0.05, cfg.gate_min_m, cfg.gate_max_m)
        inliers = 0
        used: tuple[int, ...] = ()
        plane_w, plane_turns = self._plane_weights(t_ns, lm)
        for it in range(cfg.iterations):
            r_nb = R_ned_from_body(raw.roll_rad, raw.pitch_rad, raw.yaw_rad + float(x[4]))
            veh = np.array([x[0], x[1], raw.down_m])
            rel = points_body @ r_nb.T
            p = rel + veh
            k, dist = associate(p, veh, lm, gate, cfg)
            sel = k >= 0
            inliers = int(sel.sum())
            if inliers < cfg.min_inliers:
                return np.zeros((3, 3)), 0, ()
            n = lm.normal[k[sel]]
            r = dist[sel]
            relh = rel[sel]
            j = np.stack([n[:, 0], n[:, 1], -n[:, 0] * relh[:, 1] + n[:, 1] * relh[:, 0]], axis=1)
            pw = plane_w[k[sel]]
            w = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12)) * pw
            # a robot's own planes were placed with its own heading: they hold its position against the dead
            # reckoning's drift, but say nothing about the compass's bias (NavConfig.own_turn_s)
            j[~plane_turns[k[sel]], 2] = 0.0
            scale = min(1.0, cfg.max_independent_points / inliers) / cfg.point_sigma_m**2
            h3 = scale * (j.T * w) @ j
            g3 = scale * (j.T * w) @ r
            hf = np.zeros((5, 5))
            hf[np.ix_(idx, idx)] = h3
            gf = np.zeros(5)
            gf[idx] = g3
            x = np.asarray(np.linalg.solve(p_inv + hf, p_inv @ x_pred + hf @ x - gf), dtype=np.float64)
            if it >= 1:
                # after the first pass the gate only needs to hold the residual noise and what is left
                gate = np.full(len(lm), max(cfg.gate_min_m, 4 * cfg.huber_m))
            used = tuple(int(i) for i in np.unique(lm.ids[k[sel]]))
        hf = np.zeros((5, 5))
        hf[np.ix_(idx, idx)] = h3
        dx = (x - x_pred)[idx]
        p3 = self.P[np.ix_(idx, idx)]
        if cfg.gate_chi2 > 0 and float(dx @ np.linalg.solve(p3, dx)) > cfg.gate_chi2:
            # a correction the motion model's error cannot explain: a wrong association, not drift
            self.gated += 1
            return np.zeros((3, 3)), 0, ()
        self.x = x
        cov = np.linalg.inv(p_inv + hf)
        self.P = 0.5 * (cov + cov.T)
        return h3, inliers, used

    def update(self, t_ns: int, raw: Pose, points_body: Any, landmarks: PlaneLandmarks) -> NavEstimate:
        """One cloud: predict, apply a fix, register against ``landmarks``; returns the estimate.

        Args:
            t_ns: capture time, ns since the epoch.
            raw: the pose the robot sent (north/east NaN where it has no horizontal fix).
            points_body: (N, 3) the cloud in the body frame, metres.
            landmarks: the map's planes.

        A cloud older than the last one moves nothing: it is placed with the current correction.
        """
        cfg = self.cfg
        t = int(t_ns)
        pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        pts = pts[np.einsum("ij,ij->i", pts, pts) <= cfg.max_range_m**2]
        pts = subsample(pts, cfg.max_points)
        raw_ne = np.array([raw.north_m, raw.east_m]) if math.isfinite(raw.north_m + raw.east_m) else None
        self.prior = self.transition = None
        if not self.started:
            if raw_ne is None:
                est = self._estimate(t, raw, np.zeros((3, 3)), 0, (), "unknown", known=False)
                self.latest = est
                return est
            self._start(t, raw_ne)
            self.last_raw_ne = raw_ne
            if cfg.scan_odometry:
                self._odometry(raw, pts, 0.0)  # keeps the scan for the next increment
            motion = "start"
        elif self.t_ns is not None and t < self.t_ns:
            return self._estimate(t, raw, np.zeros((3, 3)), 0, (), "late", known=True, keep=True)
        else:
            assert self.t_ns is not None
            dt = (t - self.t_ns) * 1e-9
            odo = self._odometry(raw, pts, dt) if self.cfg.scan_odometry else None
            if raw_ne is not None:
                odo = None  # dead reckoning moves the prediction; the scan is only kept for the next increment
            motion = self._predict(dt, raw_ne, odo)
            self.odometry_pairs = odo[2] if odo is not None else 0
            self.prior = (self.x.copy(), self.P.copy())
            self.t_ns = t
            self.last_raw_ne = raw_ne
            if raw_ne is not None:
                self._fix(t, raw_ne)
                self.lost = False
            self._compass(t)
        if raw_ne is None and math.sqrt(max(float(self.P[0, 0]), float(self.P[1, 1]))) > cfg.lost_std_m:
            # the scans alone could now match the wrong wall of a symmetric tank (seen: placed 5 m off); no
            # scan is trusted again until a fix comes
            self.lost = True
        used: tuple[int, ...] = ()
        if self.lost:
            h3, inliers = np.zeros((3, 3)), 0
            motion = "lost"
        else:
            h3, inliers, used = self._register(raw, pts, landmarks, t)
        est = self._estimate(t, raw, h3, inliers, used, motion, known=True)
        self.yaw_scans += int(est.constrained["yaw"])
        self.latest = est
        return est

    def _estimate(
        self,
        t: int,
        raw: Pose,
        h3: FloatArray,
        inliers: int,
        used: tuple[int, ...],
        motion: str,
        *,
        known: bool,
        keep: bool = False,
    ) -> NavEstimate:
        cfg = self.cfg
        constrained = dict.fromkeys(AXES, False)
        pinned, free_bearing = 0, None
        if inliers:
            reg_cov = np.linalg.inv(h3 + np.eye(3) * 1.0)  # a 1 m / 1 rad prior: unconstrained reads as ~1
            reg_std = np.sqrt(np.maximum(np.diag(reg_cov), 0.0))
            limits = (cfg.constrained_std_m, cfg.constrained_std_m, math.radians(cfg.constrained_std_deg))
            constrained = {a: bool(s <= lim) for a, s, lim in zip(AXES, reg_std, limits, strict=True)}
            # which horizontal directions the scan pinned, whatever the walls' orientation
            evals, evecs = np.linalg.eigh(reg_cov[0:2, 0:2])
            pinned = int(np.sum(evals <= cfg.constrained_std_m**2))
            if pinned == 1:
                free = evecs[:, 1]
                free_bearing = math.degrees(math.atan2(float(free[1]), float(free[0]))) % 180.0
        att = cfg.attitude_std_deg
        if not known:
            std = {"north_m": math.inf, "east_m": math.inf, "down_m": cfg.depth_std_m}
            std.update(roll_deg=att, pitch_deg=att, yaw_deg=math.inf)
            return NavEstimate(self.robot, t, None, std, constrained, False, motion)
        sd = np.sqrt(np.maximum(np.diag(self.P), 0.0))
        yaw_std = math.hypot(math.degrees(float(sd[4])), att)
        std = {"north_m": float(sd[0]), "east_m": float(sd[1]), "down_m": cfg.depth_std_m}
        std.update(roll_deg=att, pitch_deg=att, yaw_deg=yaw_std)
        pose = Pose(
            float(self.x[0]), float(self.x[1]), raw.down_m, raw.roll_rad, raw.pitch_rad, raw.yaw_rad + float(self.x[4])
        )
        if keep and self.last_raw_ne is not None and math.isfinite(raw.north_m + raw.east_m):
            # a late cloud: the raw position plus the current offset
            off = self.x[0:2] - self.last_raw_ne
            pose = Pose(
                raw.north_m + off[0], raw.east_m + off[1], pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad
            )
        corr = {"yaw_deg": math.degrees(float(self.x[4]))}
        if math.isfinite(raw.north_m + raw.east_m):
            corr.update(north_m=pose.north_m - raw.north_m, east_m=pose.east_m - raw.east_m)
        placed = max(float(sd[0]), float(sd[1])) <= cfg.place_std_m
        if not math.isfinite(raw.north_m + raw.east_m):
            # without a fix only a scan that pins both horizontal axes to the map places its cloud: a motion
            # prior's guess must not grow the map; but while scan odometry keeps the launch fix's position
            # within bootstrap_std_m, the robot's own scans make the map (nobody else may have one)
            pinned = constrained["north"] and constrained["east"]
            boot = motion in ("scan-odometry", "start") and max(float(sd[0]), float(sd[1])) <= cfg.bootstrap_std_m
            placed = placed and (pinned or boot)
        return NavEstimate(
            self.robot, t, pose, std, constrained, placed, motion, inliers, used, corr, pinned, free_bearing
        )


class Navigator:
    """The fleet's estimators, one :class:`RobotNav` per robot (created on its first cloud), and the fleet's
    :class:`NavFrame`."""

    def __init__(self, cfg: NavConfig | None = None, smoother: Any = None) -> None:
        self.cfg = cfg or NavConfig()
        #: robot -> its estimator: a :class:`RobotNav`, or a :class:`mapping.posegraph.GraphNav` for a robot without
        #: fixes after its launch (the same public methods)
        self.robots: dict[str, Any] = {}
        #: with a :class:`mapping.smoother.SmootherConfig`: one :class:`mapping.smoother.RobotSmoother` per robot
        #: (its ``nav`` is the robot's entry in :attr:`robots`)
        self.smoother_cfg = smoother
        self.smoothers: dict[str, Any] = {}
        #: where the first robot started (the map frame's pivot)
        self.origin_ne: tuple[float, float] | None = None
        #: robot -> the robots whose map parts are joined to its own (they contributed to a common plane,
        #: directly or through others), as the latest landmarks say; None: unknown (planes without contributions)
        self.linked: dict[str, frozenset[str]] | None = None
        self._linked_of: PlaneLandmarks | None = None
        #: with ``graph_without_fix``: each robot's launch cloud (t_ns, raw, points), until its next cloud says
        #: whether it has fixes; the pose graphs' tuning (:class:`mapping.posegraph.GraphConfig`, None: default)
        self._launches: dict[str, tuple[int, Pose, Any]] = {}
        self._first_fix: dict[str, int] = {}
        self.graph_cfg: Any = None
        #: robots whose pose graph could not start (GTSAM missing): they keep the filter
        self.graph_failed: set[str] = set()

    def frame(self) -> NavFrame:
        """The map frame's turn to NED: the mean yaw correction of the robots whose heading the scans have
        constrained at least ``frame_min_scans`` times, about the first robot's start."""
        if self.smoothers:
            return self._launch_frame()
        cs = [float(n.x[4]) for n in self.robots.values() if n.yaw_scans >= self.cfg.frame_min_scans]
        if not cs or self.origin_ne is None:
            return NavFrame()
        return NavFrame(float(np.mean(cs)), self.origin_ne)

    def _launch_frame(self) -> NavFrame:
        """With smoothing: the rigid turn and shift that best carries the robots' launch points as the map now
        places them (each robot's smoothed first pose) onto their launch fixes, which are absolute. Two launch
        points ``frame_min_baseline_m`` apart or more, of robots the map joins (:attr:`linked`: they contributed to
        common planes), fix the heading; otherwise the heading is the mean heading correction (the compasses' mean,
        as without smoothing) and the shift the mean offset."""
        # a lost robot's smoothed launch carries nothing, and a launch moved beyond what its fix allows (3 sigma)
        # is a bad association, not evidence on the frame
        lim = 3.0 * self.cfg.launch_sigma_m
        usable = {
            name: (sm.start_map_ne, sm.nav.start_ne)
            for name, sm in self.smoothers.items()
            if sm.start_map_ne is not None
            and not sm.nav.lost
            and float(np.hypot(*(np.asarray(sm.start_map_ne) - sm.nav.start_ne))) <= lim
        }
        # launches turn the map only where the map joins them: robots that never shared a plane each built their
        # own part of it, and a turn between their launch points would only be their fixes' noise
        linked = self.linked
        if linked is None:
            group = frozenset(usable)
        else:
            group = max(
                (linked.get(name, frozenset({name})) & set(usable) for name in usable), key=len, default=frozenset()
            )
        joined = len(group) >= 2
        pairs = [usable[name] for name in sorted(group)] if joined else list(usable.values())
        if not pairs:
            return NavFrame()
        a = np.array([p[0] for p in pairs])
        b = np.array([p[1] for p in pairs])
        ca, cb = a.mean(axis=0), b.mean(axis=0)
        spread = float(np.linalg.norm(a - ca, axis=1).max())
        if joined and len(pairs) >= 2 and spread >= 0.5 * self.cfg.frame_min_baseline_m:
            h = (a - ca).T @ (b - cb)
            ang = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])  # the turn carrying a onto b
            yaw = -ang
        else:
            cs = [float(n.x[4]) for n in self.robots.values() if n.yaw_scans >= self.cfg.frame_min_scans]
            yaw = float(np.mean(cs)) if cs else 0.0
        shift = cb - ca
        return NavFrame(yaw, (float(ca[0]), float(ca[1])), (float(shift[0]), float(shift[1])))

    def update(self, robot: str, t_ns: int, raw: Pose, points_body: Any, landmarks: PlaneLandmarks) -> NavEstimate:
        """One cloud of ``robot`` (see :meth:`RobotNav.update`)."""
        if not isinstance(raw, Pose):
            msg = f"{robot}: pose must be a lrsensor.frames.Pose, got {type(raw).__name__}"
            raise MapInputError(msg)
        nav = self.robots.get(robot)
        if nav is None:
            if self.smoother_cfg is not None:
                from .smoother import RobotSmoother

                new = self.smoothers[robot] = RobotSmoother(robot, self.cfg, self.smoother_cfg)
                nav = self.robots[robot] = new.nav
            else:
                nav = self.robots[robot] = RobotNav(robot, self.cfg)
        if landmarks is not self._linked_of:
            self._linked_of = landmarks
            self.linked = _joined(landmarks)
        fixed = math.isfinite(raw.north_m + raw.east_m)
        if not fixed and robot in self._launches:
            nav = self._to_graph(robot, nav, self._launches.pop(robot), landmarks)
        nav.joined = self.linked is None or len(self.linked.get(robot, ())) >= 2
        sm = self.smoothers.get(robot)
        if sm is not None:
            est: NavEstimate = sm.update(t_ns, raw, points_body, landmarks)
        else:
            est = nav.update(t_ns, raw, points_body, landmarks)
        if self.cfg.graph_without_fix and fixed and isinstance(nav, RobotNav) and nav.started:
            self._keep_launch(robot, int(t_ns), raw, points_body)
        if self.origin_ne is None and nav.started:
            self.origin_ne = (float(nav.start_ne[0]), float(nav.start_ne[1]))
        return est

    def _keep_launch(self, robot: str, t_ns: int, raw: Pose, points_body: Any) -> None:
        """A cloud with a fix: while the robot's fixes are only those of its launch (within ``launch_window_s`` of
        its first), the latest such cloud is where its pose graph starts if the fixes stop; a robot with fixes
        after that (dead reckoning, a USBL) keeps the filter."""
        first = self._first_fix.setdefault(robot, t_ns)
        if t_ns - first <= self.cfg.launch_window_s * 1e9:
            self._launches[robot] = (t_ns, raw, points_body)
        else:
            self._launches.pop(robot, None)

    def _to_graph(self, robot: str, nav: Any, launch: tuple[int, Pose, Any], landmarks: PlaneLandmarks) -> Any:
        """``robot`` has no fix after its launch: from now on its pose graph (started at its launch cloud)
        navigates it instead of the filter (and its smoother); without GTSAM it keeps the filter."""
        from .posegraph import start_graph

        try:
            graph = start_graph(robot, self.cfg, self.graph_cfg, launch, landmarks)
        except MapInputError as err:
            if robot not in self.graph_failed:
                log.warning("%s: %s; it keeps the filter", robot, err)
            self.graph_failed.add(robot)
            return nav
        self.smoothers.pop(robot, None)
        self.robots[robot] = graph
        return graph

    def latest(self) -> dict[str, NavEstimate]:
        """Robot -> its latest estimate."""
        return {r: n.latest for r, n in sorted(self.robots.items()) if n.latest is not None}


def _joined(landmarks: PlaneLandmarks) -> dict[str, frozenset[str]] | None:
    """Robot -> the robots joined to it through planes they contributed to together (itself included); None when
    the landmarks do not say who contributed."""
    if len(landmarks) and not any(landmarks.contrib):
        return None
    parent: dict[str, str] = {}

    def root(a: str) -> str:
        while parent.setdefault(a, a) != a:
            a = parent[a]
        return a

    for c in landmarks.contrib:
        names = sorted(c)
        for other in names[1:]:
            parent[root(other)] = root(names[0])
        if names:
            root(names[0])
    groups: dict[str, set[str]] = {}
    for name in parent:
        groups.setdefault(root(name), set()).add(name)
    return {name: frozenset(groups[root(name)]) for name in parent}
