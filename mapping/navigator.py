"""The fleet's navigation, :class:`Navigator`: one estimator per robot (:class:`mapping.nav_filter.RobotNav`; with
smoothing, its :class:`mapping.smoother.RobotSmoother`; opted in, a :class:`mapping.posegraph.GraphNav` for a robot
without fixes after its launch) and the fleet's frame (:class:`mapping.nav_frame.NavFrame`: the turn and shift
from the map's frame to NED).
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Any

import numpy as np

from lrsensor.frames import Pose

from .errors import MapInputError
from .graph_fleet import FleetHeadingTracker, heading_source
from .landmarks import PlaneLandmarks
from .nav_config import NavConfig, NavEstimate
from .nav_filter import RobotNav
from .nav_frame import NavFrame

__all__ = ["Navigator"]

log = logging.getLogger(__name__)


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
        #: whether it has fixes; the pose graphs' tuning (:class:`mapping.graph_config.GraphConfig`, None: default)
        self._launches: dict[str, tuple[int, Pose, Any]] = {}
        self._first_fix: dict[str, int] = {}
        self.graph_cfg: Any = None
        #: robots whose pose graph could not start (GTSAM missing): they keep the filter
        self.graph_failed: set[str] = set()
        #: with ``fleet_heading``: the graph robots' first scans and the fleet's compass biases from them (made on
        #: first use: the base sets ``cfg`` after making the navigator)
        self.fleet_heading: FleetHeadingTracker | None = None

    def frame(self) -> NavFrame:
        """The map frame's turn to NED: the mean yaw correction of the robots whose heading the scans have
        constrained at least ``frame_min_scans`` times, about the first robot's start."""
        graphs = self.cfg.frame_graph_launches and any(hasattr(n, "start_map_ne") for n in self.robots.values())
        if self.smoothers or graphs:
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
        # a robot on its pose graph: its launch pose as the graph places it now, not its old smoother's
        for name, nav in self.robots.items():
            if hasattr(nav, "start_map_ne") and self.cfg.frame_graph_launches:
                usable.pop(name, None)
                start = nav.start_map_ne
                if start is not None and float(np.hypot(*(np.asarray(start) - nav.start_ne))) <= lim:
                    usable[name] = (start, nav.start_ne)
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
        if self.cfg.frame_fleet_compass:
            yaw = self._fleet_compass(yaw)
        fh = self.fleet_heading
        if fh is not None and fh.result is not None and fh.result.common_sd_rad <= math.radians(1.0):
            # the graphs started at the heading the launch fixes and shared walls gave: the launch points as the
            # graphs now place them (their prior 5 cm, moved by the planes) would only turn it by their noise
            yaw = 0.0
        shift = cb - ca
        return NavFrame(yaw, (float(ca[0]), float(ca[1])), (float(shift[0]), float(shift[1])))

    def _fleet_compass(self, yaw: float) -> float:
        """The fleet's mean compass as the frame's heading (``NavConfig.frame_fleet_compass``): each graph robot's
        mean heading correction over its window (poses estimated minus compass, radians), averaged over the robots
        with at least ``frame_min_scans`` poses, each robot once (its bias is its own, whatever its scan count);
        ``yaw`` when there is none, or when a robot has fixes (on the filter: its fixes give the map its heading)."""
        if any(getattr(nav, "mean_correction", None) is None for nav in self.robots.values()):
            return yaw
        cs = []
        for nav in self.robots.values():
            got = nav.mean_correction()
            if got is not None and got[1] >= self.cfg.frame_min_scans:
                cs.append(got[0])
        return float(np.mean(cs)) if cs else yaw

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
        if not isinstance(nav, RobotNav):
            est = self._heading(robot, nav, int(t_ns), raw, points_body, est)
        if self.origin_ne is None and nav.started:
            self.origin_ne = (float(nav.start_ne[0]), float(nav.start_ne[1]))
        return est

    def _heading(self, robot: str, nav: Any, t_ns: int, raw: Pose, points_body: Any, est: NavEstimate) -> NavEstimate:
        """A graph robot's cloud: its first scans kept (and its clouds held) for the fleet's compass biases, given to
        the graphs once every robot has its span (``fleet_heading``); the estimate says what the robot's heading
        rests on."""
        fh = self._tracker()
        if fh is not None and fh.result is None:
            est = fh.step(robot, t_ns, raw, points_body, self.robots, est)
            got = fh.result
            if got is not None:
                biases = ", ".join(f"{r} {math.degrees(b):+.2f}" for r, b in sorted(got.bias_rad.items()))
                log.info("fleet heading from %d shared walls: compass biases %s deg (common +-%.2f deg)", got.walls,
                         biases, math.degrees(got.common_sd_rad))  # fmt: skip
        has_fixes = any(
            isinstance(n, RobotNav) and n.started and name not in self._launches for name, n in self.robots.items()
        )
        return replace(est, heading=heading_source(robot, has_fixes, fh.result if fh is not None else None))

    def _tracker(self) -> FleetHeadingTracker | None:
        if self.fleet_heading is None and self.cfg.fleet_heading:
            self.fleet_heading = FleetHeadingTracker(self.cfg)
        return self.fleet_heading

    def _keep_launch(self, robot: str, t_ns: int, raw: Pose, points_body: Any) -> None:
        """A cloud with a fix: while the robot's fixes are only those of its launch (within ``launch_window_s`` of
        its first), the latest such cloud is where its pose graph starts if the fixes stop; a robot with fixes
        after that (dead reckoning, a USBL) keeps the filter."""
        first = self._first_fix.setdefault(robot, t_ns)
        if t_ns - first <= self.cfg.launch_window_s * 1e9:
            self._launches[robot] = (t_ns, raw, points_body)
            fh = self._tracker()
            if fh is not None:
                fh.launch(robot, t_ns, raw, points_body)
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
        if self.fleet_heading is not None:
            self.fleet_heading.started(robot)
        return graph

    def released(self, robot: str) -> list[tuple[int, Pose, Any]]:
        """``robot``'s held clouds released to the map since the last call (t_ns, pose in the map frame, body
        points (M, 3)), in capture order; empty unless its pose graph holds clouds (:mod:`mapping.graph_hold`)."""
        hold = getattr(self.robots.get(robot), "hold", None)
        return hold.take() if hold is not None else []

    def settle(self, robot: str, landmarks: PlaneLandmarks) -> list[tuple[int, Pose, Any]]:
        """``robot`` went silent or the dive ends: its pose graph's held clouds checked alone; those released (as
        :meth:`released`)."""
        nav: Any = self.robots.get(robot)
        if getattr(nav, "hold", None) is None:
            return []
        nav.settle(landmarks)
        return self.released(robot)

    def hold_counts(self, robot: str) -> dict[str, float] | None:
        """What ``robot``'s hold did (:meth:`mapping.graph_hold.CloudHold.counts`); None when it holds nothing."""
        nav: Any = self.robots.get(robot)
        hold = getattr(nav, "hold", None)
        if hold is None or not nav.gcfg.hold_until_verified:
            return None
        counts: dict[str, float] = hold.counts()
        return counts

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
