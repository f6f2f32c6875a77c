"""The depth-only fleet's compass biases, estimated jointly in its first second and given to its pose graphs
(``NavConfig.fleet_heading``; the estimate is :mod:`mapping.fleet_heading`'s).

Each robot on a pose graph (:mod:`mapping.posegraph`) starts at its launch fix with its compass as the heading (a 3
deg prior): the fleet's first clouds, which make the map, are turned by each robot's compass bias, and the map keeps
the compasses' mean error. :class:`FleetHeadingTracker` keeps every graph robot's scans of its first
``fleet_heading_s`` after its launch (turned by its compass; where it was relative to its fix as its graph says,
turned into its compass frame), estimates the biases jointly from the walls two robots see
(:func:`mapping.fleet_heading.estimate`) once every robot has that span, and gives each graph its bias
(:func:`retune`): its launch heading prior becomes the compass minus the bias with the estimate's standard deviation,
its later compass priors the compass minus the bias; the graph is re-solved from its factors. Meanwhile the graph
robots' clouds are held (:func:`mapping.graph_hold.hold_cloud`) and then committed at the poses the retuned graphs
give them: placed at once, they made the map's first planes at the compasses' headings. Once the estimate pins the
common heading, the fleet frame (:meth:`mapping.navigator.Navigator.frame`) no longer turns the map by the launch
points as the graphs place them (their 5 cm prior, moved by the planes: a turn of their noise).

Robots launched after the estimate keep their compass, as does a robot that shares no wall with another (bias 0, 3
deg: its graph is left as it is). :func:`heading_source` says what a robot's heading rests on: ``fixes`` (a robot of
the fleet has fixes after its launch: the map's heading comes from its track), ``launch-walls`` (the estimate pinned
this robot's bias within 1 deg), or ``compass`` (the compass alone: the published ``nav`` then lists ``yaw`` as
unconstrained). What the launch cannot give is the compasses' later wander (the simulator's: 0.5 deg over 30-150 s):
the graphs carry it from their compass turns.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from lrsensor.frames import Pose, R_ned_from_body

from .fleet_heading import FleetHeading, FleetHeadingConfig, View, estimate
from .graph_hold import commit_held, hold_cloud
from .nav_config import NavConfig, NavEstimate

#: how a view's place relative to the launch fix loses precision with the time since (m/s: the scan odometry's)
ODOMETRY_DRIFT_M_S = 0.01


def compass_points(raw: Pose, points_body: Any) -> Any:
    """The finite points (M, 2) of a cloud, north and east relative to the vehicle, turned by the raw attitude (its
    compass's heading)."""
    pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    return (pts @ R_ned_from_body(raw.roll_rad, raw.pitch_rad, raw.yaw_rad).T)[:, 0:2]


def retune(nav: Any, bias_rad: float, sd_rad: float) -> None:
    """Give the pose graph ``nav`` its compass's bias: the launch prior's heading becomes the compass minus
    ``bias_rad`` with ``sd_rad`` (while the launch is in its window), every compass prior's mean the compass minus
    the bias; the graph is rebuilt from its factors and solved."""
    nav.compass_bias = (float(bias_rad), float(sd_rad))
    specs = []
    for i, (kind, keys, data) in enumerate(nav._specs):
        if kind == "prior" and len(keys) == 1:
            mean, info = np.asarray(data[0], dtype=np.float64).copy(), np.asarray(data[1], dtype=np.float64).copy()
            k = keys[0]
            if i == 0 and k == 0 and nav._first_key == 0:
                mean[2] = nav._compass[0] - bias_rad
                info[2, :] = info[:, 2] = 0.0
                info[2, 2] = 1.0 / sd_rad**2
                data = (mean, info)
            elif info[0, 0] <= 1e-9 and not mean[0:2].any() and mean[2] == nav._compass[k]:
                mean[2] -= bias_rad
                data = (mean, info)
        specs.append((kind, keys, data))
    nav._specs = specs
    nav._rebuild(nav._first_key, None)


class FleetHeadingTracker:
    """The graph robots' first scans, the fleet's compass biases from them, and what each robot's heading rests on
    (see the module docstring). The :class:`mapping.navigator.Navigator` feeds it: :meth:`launch` with each cloud
    that has a launch fix, :meth:`started` when a robot's pose graph starts, :meth:`observe` with each later cloud
    of a graph robot."""

    def __init__(self, cfg: NavConfig, estimator: FleetHeadingConfig | None = None) -> None:
        self.cfg = cfg
        self.est_cfg = estimator or FleetHeadingConfig(fix_sigma_m=cfg.fleet_heading_fix_sigma_m)
        #: robot -> its launch cloud's view and capture time, until its graph starts
        self._launch: dict[str, tuple[int, View]] = {}
        #: robot -> its launch time and its views (the launch and the scans within ``fleet_heading_s``)
        self.views: dict[str, tuple[int, list[View]]] = {}
        #: robots past their span
        self._done: set[str] = set()
        #: the estimate once made (None before)
        self.result: FleetHeading | None = None

    def launch(self, robot: str, t_ns: int, raw: Pose, points_body: Any) -> None:
        """A cloud of ``robot`` with a horizontal fix (its launch, if its fixes stop)."""
        fix = (float(raw.north_m), float(raw.east_m))
        self._launch[robot] = (int(t_ns), View(robot, fix, compass_points(raw, points_body)))

    def started(self, robot: str) -> None:
        """``robot`` is on its pose graph from its last launch cloud on."""
        got = self._launch.pop(robot, None)
        if got is not None and self.result is None:
            self.views[robot] = (got[0], [got[1]])

    def observe(self, robot: str, t_ns: int, raw: Pose, points_body: Any, nav: Any) -> None:
        """A cloud of graph robot ``robot`` (after its graph's update): kept while within ``fleet_heading_s`` of its
        launch, placed by the graph relative to its launch fix."""
        if self.result is not None or robot not in self.views or getattr(nav, "_est", None) is None:
            return
        t0, views = self.views[robot]
        dt = (int(t_ns) - t0) * 1e-9
        if dt > self.cfg.fleet_heading_s + 1e-3:
            self._done.add(robot)
        if robot in self._done or nav.lost:
            return
        x = nav._est[len(nav._t) - 1]
        d = np.asarray(x[0:2], dtype=np.float64) - np.asarray(views[0].fix_ne)
        # the graph's frame turned into the compass's: a robot's track and scans turn together with its compass
        a = math.remainder(raw.yaw_rad - float(x[2]), 2 * math.pi)
        u = (math.cos(a) * d[0] - math.sin(a) * d[1], math.sin(a) * d[0] + math.cos(a) * d[1])
        sigma = 0.002 + ODOMETRY_DRIFT_M_S * dt
        views.append(View(robot, views[0].fix_ne, compass_points(raw, points_body), u, sigma))

    def due(self) -> bool:
        """Whether every graph robot is past ``fleet_heading_s`` since its launch and the estimate is still to be
        made."""
        return self.result is None and bool(self.views) and all(r in self._done for r in self.views)

    def step(
        self, robot: str, t_ns: int, raw: Pose, points_body: Any, robots: dict[str, Any], est: NavEstimate
    ) -> NavEstimate:
        """A cloud of graph robot ``robot`` (its estimator ``robots[robot]``, the fleet's ``robots``) after its
        graph's update (estimate ``est``): kept (:meth:`observe`), and while the fleet's biases are still to be
        estimated its cloud is held (:mod:`mapping.graph_hold`: the map's first planes would carry the compasses'
        biases); once every robot has its span the biases are estimated and given to the graphs, and the held clouds
        committed at the poses the graphs then give them (with the checks' hold, those held since a check passed
        in that second too). Returns ``est``, held (``placed`` False, ``held`` True) while the estimate waits."""
        # held only where another graph robot may share its walls (a robot alone keeps its compass: nothing to wait for)
        collecting = self.result is None and robot in self.views and len(self.views) >= 2
        est = self.keep(robot, t_ns, raw, points_body, robots[robot], est, collecting)
        if self.due():
            self.apply(robots, t_ns)
        return est

    def keep(
        self, robot: str, t_ns: int, raw: Pose, points_body: Any, nav: Any, est: NavEstimate, hold: bool
    ) -> NavEstimate:
        """:meth:`observe` the cloud and, with ``hold`` (the fleet's biases still to come), hold it when placed: what
        :meth:`step` does with one robot's cloud (a plane worker runs it alone: the base decides ``hold``)."""
        self.observe(robot, t_ns, raw, points_body, nav)
        if hold and est.placed and est.pose is not None and getattr(nav, "hold", None) is not None:
            hold_cloud(nav, len(nav._t) - 1, t_ns, raw, points_body, est.pinned)
            est = replace(est, placed=False, held=True)
        return est

    def apply(self, robots: dict[str, Any], t_ns: int) -> FleetHeading:
        """Estimate the biases from the views kept, give each graph robot its own (:func:`retune`) and commit the
        clouds held meanwhile."""
        result = estimate([v for _, vs in self.views.values() for v in vs], self.est_cfg)
        self.result = result
        prior = math.radians(self.est_cfg.bias_prior_deg)
        for robot in self.views:
            give(robots.get(robot), result.bias_rad[robot], result.sd_rad[robot], prior, t_ns)
        self.views = {}
        return result


def give(nav: Any, bias_rad: float, sd_rad: float, prior_rad: float, t_ns: int) -> None:
    """Give graph ``nav`` (None: nothing) its compass's bias (:func:`retune`) unless the estimate left it near its
    prior ``prior_rad`` (it shares no wall: its graph stays as it is), and commit its clouds held meanwhile."""
    if nav is not None and hasattr(nav, "compass_bias") and sd_rad < 0.99 * prior_rad:
        retune(nav, bias_rad, sd_rad)
    if nav is not None and getattr(nav, "hold", None) is not None and nav.hold.clouds:
        commit_held(nav, t_ns)


def heading_source(robot: str, fleet_has_fixes: bool, result: FleetHeading | None) -> str:
    """What graph robot ``robot``'s absolute heading rests on: ``fixes`` (a robot of the fleet has fixes after its
    launch), ``launch-walls`` (the fleet's estimate ``result`` pinned its bias within 1 deg) or ``compass``."""
    if fleet_has_fixes:
        return "fixes"
    if result is not None and result.observed(robot):
        return "launch-walls"
    return "compass"
