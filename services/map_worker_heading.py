"""The fleet heading with plane workers: the views in the workers, the estimate at the base (issue 27).

In one process the map thread's :class:`mapping.graph_fleet.FleetHeadingTracker` keeps every graph robot's scans of
its first ``NavConfig.fleet_heading_s`` after launch (its *views*), holds their clouds, and once every graph robot
has its span estimates the fleet's compass biases (:func:`mapping.fleet_heading.estimate`) and gives each graph
its own (:func:`mapping.graph_fleet.give`). With plane workers each robot's graph runs in the worker that owns it,
and no worker sees the whole fleet. So the work is split where the data is:

- **The base decides when** (:class:`HeadingRelay`, fed in the map thread's capture order, from the raw poses it
  dispatches): which robots go on pose graphs (a launch fix, then none) in which order, whether a job's cloud is
  kept as a view and held (``MapJob.heading``: ``collect``, or ``hold`` once two graph robots or more collect, as
  in one process), and the cloud at which every graph robot has passed its span (the estimate is *due*).
- **The worker keeps the views and holds the clouds** (``FleetHeadingTracker.keep``, the in-process code): it has
  the graph's estimate each view is placed with, relative to the launch fix.
- **At the due cloud** the base asks each graph robot's owner for its views (``MapControl("views")``, sent after the
  robot's jobs up to that cloud, so the worker answers once it has processed them: :class:`HeadingViews`), waits
  for the answers (at most :data:`HEADING_WAIT_S`; the map thread holds its next dispatch meanwhile, so each robot's
  bias reaches its graph after the same clouds as in one process, whatever the workers' timing), estimates, and sends
  each robot its bias and standard deviation (``MapControl("heading")``); the worker retunes the graph and commits
  the held clouds (:func:`mapping.graph_fleet.give`), which go into its window at the robot's next job. The base keeps
  the estimate for the fleet frame (``Navigator.fleet_heading``: the frame no longer turns the map by the launch
  points) and the ``heading`` the base serves for each worker-navigated graph robot (:func:`with_heading`).

Why not the estimate in the workers: each sees only its robots' walls; the biases come from walls two robots see,
usually on two workers. Why not the views at the base from the dispatched clouds: a view's place relative to the
launch fix is the graph's (the worker's) estimate, and the holding must happen where the graph is.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

from lrsensor.frames import Pose

log = logging.getLogger(__name__)

#: Longest the base's map thread waits for the graph robots' views at the due cloud, wall seconds (the workers
#: answer once they have processed that robot's jobs before it; a robot whose views do not come keeps its compass).
HEADING_WAIT_S = 30.0


class HeadingRelay:
    """The base's half of the fleet heading with plane workers (see the module docstring).

    Args:
        navigator: the base's :class:`mapping.navigation.Navigator` (its ``cfg``, read at each cloud: ``--no-fix``
            sets it after the pool is made; its ``fleet_heading`` gets the estimate, for the frame and ``heading``).
    """

    def __init__(self, navigator: Any) -> None:
        self.navigator = navigator
        #: per robot: the first fix's capture time; the latest fix within the launch window (ns)
        self._first_fix: dict[str, int] = {}
        self._launch: dict[str, int] = {}
        #: the graph robots collecting views, with their launch times and their graphs' first clouds' (ns)
        self.t0: dict[str, int] = {}
        self._started: dict[str, int] = {}
        self._done: set[str] = set()
        #: the views the workers sent (robot -> views), guarded by ``_cond``
        self._views: dict[str, list[Any]] = {}
        self._cond = threading.Condition()
        #: the estimate once made (None before), and the capture time of the cloud it was due at
        self.result: Any = None
        self.due_ns: int | None = None
        #: how long the map thread waited for the views (wall seconds)
        self.wait_s = 0.0

    def _on(self) -> bool:
        cfg = self.navigator.cfg
        return bool(cfg.fleet_heading and cfg.graph_without_fix)

    def phase(self, robot: str, t_ns: int, raw: Pose) -> str:
        """The ``MapJob.heading`` of ``robot``'s cloud captured at ``t_ns`` with the raw pose ``raw`` (the map thread
        calls this in capture order): ``collect`` (kept as a view), ``hold`` (kept and held), or empty."""
        if self.result is not None or self.due_ns is not None or not self._on():
            return ""
        cfg = self.navigator.cfg
        if math.isfinite(raw.north_m + raw.east_m):
            if robot not in self.t0:  # as Navigator._keep_launch: the latest fix within the launch window
                first = self._first_fix.setdefault(robot, t_ns)
                if t_ns - first <= cfg.launch_window_s * 1e9:
                    self._launch[robot] = t_ns
                else:
                    self._launch.pop(robot, None)
            return ""
        if robot in self._launch:  # its graph starts from its last launch cloud (Navigator._to_graph)
            self.t0[robot] = self._launch.pop(robot)
            self._started[robot] = t_ns
        if robot not in self.t0:
            return ""
        hold = len(self.t0) >= 2  # before this cloud is counted (FleetHeadingTracker.step)
        if (t_ns - self.t0[robot]) * 1e-9 > cfg.fleet_heading_s + 1e-3:
            self._done.add(robot)
        if all(r in self._done for r in self.t0):
            self.due_ns = t_ns
        return "hold" if hold else "collect"

    def robots(self) -> list[str]:
        """The graph robots in the order their graphs started (one process's order of the views; robots whose
        clouds share a capture time, which the base may take in either order, by name)."""
        return sorted(self.t0, key=lambda r: (self._started[r], r))

    def due(self) -> bool:
        """Whether the estimate is due now (every graph robot past its span) and not made yet."""
        return self.result is None and self.due_ns is not None

    def take_views(self, robot: str, views: list[Any]) -> None:
        """A worker's views of ``robot`` (the merger's thread)."""
        with self._cond:
            self._views[robot] = list(views)
            self._cond.notify_all()

    def wait_views(self, timeout_s: float = HEADING_WAIT_S) -> list[str]:
        """Wait until every graph robot's views came (at most ``timeout_s``); the robots whose views are missing."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                missing = [r for r in self.t0 if r not in self._views]
                left = deadline - time.monotonic()
                if not missing or left <= 0:
                    return missing
                self._cond.wait(left)

    def estimate(self) -> dict[str, tuple[float, float]]:
        """The fleet's compass biases from the views that came (robot -> (bias, sd), radians; a robot whose views
        did not come keeps its prior): also kept in the navigator's tracker, for the frame and ``heading``."""
        from mapping.fleet_heading import estimate

        tracker = self.navigator._tracker()
        with self._cond:
            views = [v for r in self.robots() for v in self._views.get(r, [])]
        result = estimate(views, tracker.est_cfg)
        self.result = tracker.result = result
        prior = math.radians(tracker.est_cfg.bias_prior_deg)
        out = {r: (result.bias_rad.get(r, 0.0), result.sd_rad.get(r, prior)) for r in self.robots()}
        biases = ", ".join(f"{r} {math.degrees(b):+.2f}" for r, (b, _) in sorted(out.items()))
        log.info("fleet heading from %d shared walls (plane workers): compass biases %s deg (common +-%.2f deg)",
                 result.walls, biases, math.degrees(result.common_sd_rad))  # fmt: skip
        return out

    def settle(self, control: Callable[..., None], timeout_s: float = HEADING_WAIT_S) -> None:
        """At the due cloud (the map thread, after dispatching it): ask each graph robot's owner for its views
        (``control(robot, "views")``), wait for them, estimate, and send each its bias (``control(robot, "heading",
        state)``); a robot whose views did not come within ``timeout_s`` keeps its compass (its held clouds are
        committed all the same)."""
        from .map_worker_nav import encode_state

        t0 = time.monotonic()
        for robot in self.robots():
            control(robot, "views")
        missing = self.wait_views(timeout_s)
        if missing:
            log.warning("fleet heading: no views from the workers of %s within %.0f s: they keep their compasses",
                        ", ".join(missing), timeout_s)  # fmt: skip
        for robot, (bias, sd) in self.estimate().items():
            control(robot, "heading", encode_state({"bias_rad": bias, "sd_rad": sd, "t_ns": self.due_ns}))
        self.wait_s = time.monotonic() - t0

    def status_json(self) -> dict[str, Any]:
        """The estimate as the pool's status says it: the graph robots, the shared walls, the map thread's wait."""
        r = self.result
        return {"robots": self.robots(), "walls": r.walls if r is not None else None, "wait_s": round(self.wait_s, 2)}


def attach(pool: Any, navigator: Any, publish: Callable[[Any], None]) -> None:
    """Give the plane workers' ``pool`` the fleet heading's base half (a :class:`HeadingRelay` on the base's
    ``navigator``), and have each estimate a worker reports published (``publish``) with its ``heading``
    (:func:`with_heading`)."""
    pool.heading = HeadingRelay(navigator)
    pool.on_nav_report = lambda robot, est: publish(with_heading(navigator, est))


def with_heading(navigator: Any, est: Any) -> Any:
    """A worker's estimate ``est`` with what its robot's heading rests on, as the base says it for its own graph
    robots (:func:`mapping.graph_fleet.heading_source`; the worker does not know the fleet): unchanged for a robot
    on the filter, or without a navigator."""
    from dataclasses import replace

    from mapping.graph_fleet import heading_source
    from mapping.posegraph import GraphNav

    if navigator is None or not isinstance(navigator.robots.get(est.robot), GraphNav):
        return est
    fixes = any(n.started and not isinstance(n, GraphNav) for n in navigator.robots.values())
    fh = navigator.fleet_heading
    return replace(est, heading=heading_source(est.robot, fixes, fh.result if fh is not None else None))
