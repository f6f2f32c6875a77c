"""The navigation's tuning and what it reports: :class:`NavConfig` (the parameters of the filter, of the
smoother's re-runs and of the fleet's frame) and :class:`NavEstimate` (a robot's corrected pose at one cloud, what
``<root>/<robot>/nav`` publishes).

The estimator is :class:`mapping.nav_filter.RobotNav`, the fleet's :class:`mapping.navigator.Navigator`;
:mod:`mapping.navigation` exports all of them (and describes the method).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

from .landmarks import subsample
from .nav_frame import NavFrame

__all__ = ["AXES", "NavConfig", "NavEstimate", "registration_points", "scan_constraint"]

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
    drift is not white noise. With ``dr_bias_adaptive`` the bias is a robot's own choice: held at
    ``dr_bias_closed_sigma_m_s`` (no walk: the filter is then the one without the bias, fixes weighted as there)
    until its fixes' disagreement persists (persistence at least ``dr_bias_open_persist``, 0-1) with an RMS beyond
    ``fix_persist_min_m``: a drift shows, and the bias opens to ``dr_bias_sigma_m_s`` for the rest of the dive
    (:attr:`RobotNav.bias_open`). With ``dr_bias_open_rate_m_s`` > 0 the opening test is the scans' instead: the
    running mean (over ``fix_quality_s``) of the velocity of the registrations' corrections of the position, each
    correction clipped to what a drift of ``dr_drift_max_m_s`` does in its scan's time, reaches
    ``dr_bias_open_rate_m_s``. A dead reckoning's drift is corrected a little every scan; scans registered to a
    wrong plane jump the estimate once, and its fixes' disagreement then persists as a drift's would (the fixes'
    test opened the bias on good fixes). ``fix_quality_factor_open`` (> 0) replaces ``fix_quality_factor`` once
    the bias is open. Initial ``launch_sigma_m``, ``init_speed_sigma_m_s`` (the velocity states without the
    bias), ``init_yaw_sigma_deg``.

    The dead reckoning's error as a state (``dr_error_state``; off): two more states, the error d = raw - true
    position (north, east; m), and the velocity states become its rate. Each raw position measures the position
    plus d at the fix's own white noise (``dr_error_fix_sigma_m``), whatever the estimate says; d moves only as a
    dead reckoning's error can: its rate (``dr_error_bias_sigma_m_s`` at launch, a random walk of
    ``dr_error_bias_walk_m_s_per_sqrt_s``: a current, a scale or heading error times the speed) and a random walk
    of its own (``dr_error_walk_m_per_sqrt_s``). A good robot's d stays near 0 and scans that jump to a wrong
    plane cannot move it quickly; a drifting robot's grows, and the scans observe it. The velocity-bias options,
    the fixes' quality from their disagreement and their persistence are then unused (docs/navigation-design.md,
    "The dead reckoning's error as a state": measured, left off). ``dr_error_bound_fraction`` (> 0) bounds d as
    the physics does: per axis, its change since the scans last pinned that axis has a variance of at most
    (the fraction x the distance travelled since)^2 + (``dr_error_bound_current_m_s`` x the time since)^2 plus
    the fix's, and its rate at most (the fraction x the speed)^2 + the current's^2 (soft pseudo-measurements,
    applied only where the covariance exceeds the bound; ``dr_error_bound_pins`` False: since the launch, the
    scans never restart it). ``dr_error_rate_weight`` (below 1): a registration's gain for the error's rate is
    scaled by it (0: a Schmidt consider update, the registration moves the position, heading and d but not the
    rate; :mod:`mapping.nav_error`), with ``dr_error_rate_young_s`` > 0 only where the registration used a plane
    first seen less than that before the scan.

    A plane's own offset error (``plane_sigma_m`` > 0; 0 turns it off; :mod:`mapping.nav_planes`): each associated
    plane's residuals share an error of that standard deviation along its normal (the map placed the plane with
    poses good to a few centimetres), so one scan's information along a plane's normal saturates at
    1 / ``plane_sigma_m``^2 however many points it has; with ``plane_carry`` the error is also the same for every
    later scan: ``"consider"``, a Schmidt consider parameter per plane (its cross-covariance with the state dropped
    under ``plane_carry_min_corr``); ``"estimate"``, a state of the robot's per plane while the plane is in the map.
    With ``plane_fix_jitter_m`` > 0 only while the raw positions' white noise (from the RMS of their second
    differences over ``fix_quality_s``) exceeds it: absolute fixes (a USBL's, a good IMU's) are white, a dead
    reckoning's track is smooth, and a robot whose position rests on the map must count its planes as exact (with
    the plane's error a drifting robot's fixes agreed with its estimate, its bias never opened, and it ran away).

    Reporting: ``constrained_std_m`` / ``constrained_std_deg`` (registration-only standard deviation under which
    an axis counts as constrained), ``place_std_m`` (clouds of a robot whose horizontal standard deviation
    exceeds it are not placed in the map), ``lost_std_m`` (without a fix, a robot whose predicted standard
    deviation exceeds it is lost: its scans are not registered or placed until the next fix), ``depth_std_m`` /
    ``attitude_std_deg`` (reported for the measured axes); ``frame_min_scans``: a robot's yaw correction counts
    in :meth:`Navigator.frame` once that many scans constrained its heading; with smoothing, launch points
    ``frame_min_baseline_m`` apart fix the frame's heading instead.

    Evidence: a plane only this robot contributed to, first seen by it less than ``own_recent_s`` before the scan,
    holds the robot's own recent poses and so no absolute information; its residuals count ``own_recent_weight``
    of their information. Such planes were placed with the robot's own heading and say nothing of its compass's
    bias: with ``own_recent_turns_alone`` False they move the position only, not the heading, while the map has not
    joined the robot's part to another robot's (:attr:`RobotNav.joined`). A registration whose correction lies
    beyond the prediction's error model (squared Mahalanobis distance over north, east, yaw above ``gate_chi2``) is
    a wrong association, not drift: it is rejected and counted (:attr:`RobotNav.gated`). A cloud without a fix is
    placed only when its scan pinned both horizontal axes to the map.

    Pose graph (``graph_without_fix``; off in this record, on with ``lrsensor base --no-fix graph``, the base's
    default where GTSAM is installed, which also sets the graphs' gates :data:`mapping.graph_config.TRACKED` and
    ``frame_graph_launches``): a robot whose fixes stop within ``launch_window_s`` of its first (a launch fix only)
    is navigated by a pose graph of its own (:class:`mapping.posegraph.GraphNav`, GTSAM) instead of this filter,
    from its last launch cloud on. Without the gates the graphs track such a robot for tens of seconds, then slide
    along walls the scans do not pin while their covariance still says centimetres, and the map gains spurious
    planes (docs/navigation-design.md, "Tracked anchors"). Off (``--no-fix lost``), such a robot is reported
    ``lost`` and its clouds stay unplaced: an empty part of the map rather than a wrong one.
    ``frame_graph_launches``: the launch frame
    (:meth:`Navigator.frame` with smoothing) takes a graph robot's launch as its graph places it (else its
    smoother's, which no longer moves, and the mean heading correction turns the map).
    ``frame_fleet_compass`` (off): with pose graphs, the frame's heading is instead the fleet's mean compass: the
    mean over the graph robots of each one's mean heading correction over its window
    (:meth:`mapping.posegraph.GraphNav.mean_correction`), as if the compasses' biases averaged to zero over the
    robots and the dive (docs/navigation-design.md, "Measured and left off": in the simulator they do not); only
    while every robot is on its pose graph (a robot with fixes gives the map its heading).
    ``fleet_heading`` (on; it acts only where two robots or more are on pose graphs): the graph robots' compass
    biases estimated jointly from their scans of the first ``fleet_heading_s`` after their launches and the walls
    two of them see, their launch fixes taken to be within ``fleet_heading_fix_sigma_m``
    (:mod:`mapping.graph_fleet`); each graph then starts from its compass minus its bias, and its clouds of that
    span wait for the estimate.
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
    dr_bias_adaptive: bool = False
    dr_bias_closed_sigma_m_s: float = 1e-5
    dr_bias_open_persist: float = 0.5
    fix_persistence: bool = True
    fix_persist_min_m: float = 0.1
    walk_speed_m_s: float = 0.3
    yaw_walk_deg_per_sqrt_s: float = 0.1
    fix_sigma_m: float = 0.5
    fix_quality_factor: float = 1.5
    fix_quality_factor_open: float = 0.0
    dr_bias_open_rate_m_s: float = 0.0
    dr_error_state: bool = False
    dr_error_fix_sigma_m: float = 0.02
    dr_error_bias_sigma_m_s: float = 0.02
    dr_error_bias_walk_m_s_per_sqrt_s: float = 0.005
    dr_error_walk_m_per_sqrt_s: float = 0.01
    dr_error_bound_fraction: float = 0.0
    dr_error_bound_current_m_s: float = 0.03
    dr_error_bound_pins: bool = True
    dr_error_rate_weight: float = 1.0
    dr_error_rate_young_s: float = 0.0
    dr_drift_max_m_s: float = 0.05
    plane_sigma_m: float = 0.0
    plane_carry: str = ""
    plane_carry_min_corr: float = 0.05
    plane_fix_jitter_m: float = 0.0
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
    own_recent_s: float = 20.0
    own_recent_weight: float = 0.03
    own_recent_turns_alone: bool = True
    gate_chi2: float = 0.0
    graph_without_fix: bool = False
    launch_window_s: float = 2.0
    frame_graph_launches: bool = False
    frame_fleet_compass: bool = False
    fleet_heading: bool = True
    fleet_heading_s: float = 1.0
    fleet_heading_fix_sigma_m: float = 0.005


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
        held: the cloud may be placed but waits for its track's next check (``placed`` is then False: what goes
            into the map comes later, :mod:`mapping.graph_hold`).
        heading: for a robot on its pose graph, what its absolute heading rests on
            (:func:`mapping.graph_fleet.heading_source`: ``fixes``, ``launch-walls``, ``compass``); None on the
            filter. With ``compass`` the JSON lists ``yaw`` as unconstrained whatever the scan pinned: the map's
            heading is then the compasses'.
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
    held: bool = False
    heading: str | None = None

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
        # a heading pinned against a map whose own heading is the compasses' is not an absolute heading
        pinned = {a: bool(self.constrained.get(a)) and not (a == "yaw" and self.heading == "compass") for a in AXES}
        out["constrained"] = [a for a in AXES if pinned[a]]
        out["unconstrained"] = [a for a in AXES if not pinned[a]]
        out["heading"] = self.heading
        out.update(placed=self.placed, motion=self.motion, inliers=self.inliers, planes=list(self.planes))
        out["correction"] = dict(self.correction)
        out["degenerate"] = {"free_bearing_deg": self.free_bearing_deg} if self.free_bearing_deg is not None else None
        return out


def scan_constraint(h3: NDArray[np.float64], inliers: int, cfg: NavConfig) -> tuple[dict[str, bool], int, float | None]:
    """What one scan's registration pinned: per axis of :data:`AXES` whether it is constrained, how many horizontal
    directions are pinned (0-2), and with one pinned the bearing (deg, 0-180, from north) of the free one.

    ``h3`` (3, 3) is the registration's information over north (m), east (m) and yaw (rad) from ``inliers``
    point-to-plane residuals. A 1 m / 1 rad prior is added, so an unconstrained axis reads as ~1. The pinned
    directions are the covariance's eigenvectors, so a wall at 30 deg reads as degenerate along it, not as both
    axes unconstrained.
    """
    if not inliers:
        return dict.fromkeys(AXES, False), 0, None
    reg_cov = np.linalg.inv(h3 + np.eye(3))
    reg_std = np.sqrt(np.maximum(np.diag(reg_cov), 0.0))
    limits = (cfg.constrained_std_m, cfg.constrained_std_m, math.radians(cfg.constrained_std_deg))
    constrained = {a: bool(sd <= lim) for a, sd, lim in zip(AXES, reg_std, limits, strict=True)}
    evals, evecs = np.linalg.eigh(reg_cov[0:2, 0:2])
    pinned = int(np.sum(evals <= cfg.constrained_std_m**2))
    free_bearing = None
    if pinned == 1:
        free = evecs[:, 1]
        free_bearing = math.degrees(math.atan2(float(free[1]), float(free[0]))) % 180.0
    return constrained, pinned, free_bearing


def registration_points(points_body: Any, cfg: NavConfig) -> NDArray[np.float64]:
    """The points of a cloud a registration uses: (M, 3) body frame, metres; the finite ones within
    ``cfg.max_range_m``, evenly sub-sampled to at most ``cfg.max_points``."""
    pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    pts = pts[np.einsum("ij,ij->i", pts, pts) <= cfg.max_range_m**2]
    return subsample(pts, cfg.max_points)
