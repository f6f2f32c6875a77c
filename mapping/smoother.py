"""Letting past poses move: a per-robot fixed-window smoother over :class:`mapping.navigation.RobotNav`.

The filter of :mod:`mapping.navigation` places each cloud once, with the pose it had then; a robot's early,
drifted placements would stay in the map forever (duplicates, offsets). The smoother keeps each robot's recent
scans (the registration's sub-sample, body frame, float32) and the filter's state before each, and on
:meth:`RobotSmoother.smooth`:

1. **Re-filter.** From the filter's state just before the window (the last ``window_s`` of capture time), the
   window's scans are run through the same Kalman filter again, now registered against the map as it is (its
   planes placed from better poses than when the scans first came).
2. **Smooth.** A Rauch-Tung-Striebel backward pass over the window's (north, east, yaw correction) uses every
   later scan for each earlier pose: the exact fixed-interval smoother of the filter's linearization (dead
   reckoning's increment turned by the yaw correction, and its velocity bias times the time, couple the states).
3. **Report.** The revised poses of the window's scans (robot, t_ns -> Pose); the map re-places the clouds whose
   pose moved (:mod:`mapping.replace`). The live filter continues from the re-filtered state.

Per robot the interface is: input the robot's clouds and the map's planes (:class:`PlaneLandmarks`); output the
corrected poses and the revised placements. Nothing here knows about other robots or Zenoh, so a map worker
can run it for the robots it owns.

Cost: a re-filter registers each window scan again (``rerun_points`` points each), so smoothing every
``every_s`` a window of ``window_s`` costs about ``window_s / every_s`` registrations per scan.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

from .landmarks import PlaneLandmarks, subsample
from .navigation import NavConfig, NavEstimate, RobotNav

FloatArray = NDArray[np.float64]

log = logging.getLogger(__name__)

#: The smoothed state: with the dead reckoning's velocity bias (``NavConfig.dr_bias_sigma_m_s`` > 0) all of
#: RobotNav's five (north, east, the bias, yaw correction): the bias couples the positions of consecutive scans, so a
#: pass over a sub-state would not be the exact smoother; without it north, east and yaw correction (the velocity
#: states are then unused). The yaw correction is last in both.
_SUB = [0, 1, 2, 3, 4]
_SUB_NO_BIAS = [0, 1, 4]
#: with the dead reckoning's error as a state (``NavConfig.dr_error_state``): all seven, the yaw correction last
_SUB_ERROR = [0, 1, 2, 3, 5, 6, 4]


def _sub(nav: RobotNav) -> list[int]:
    if nav.cfg.dr_error_state:
        return _SUB_ERROR
    return _SUB if nav.cfg.dr_bias_sigma_m_s > 0 else _SUB_NO_BIAS


#: The filter's tuning under the smoother: fixes weighted by 5x (not 1.5x) their RMS disagreement with the estimate. A
#: drifting dead reckoning's fixes are the sum of the increments the filter already uses; weighted as independent
#: measurements every 0.2 s they dragged the smoothed tracks toward the drift. A robot's own recent planes count more
#: than under the filter alone (10 s at 0.1, not 20 s at 0.03): the smoother's re-filter needs them to hold a drifting
#: robot between its passes; but while the map has not joined a robot's part to another robot's, they move its position
#: only, not its heading (on the short rendered dives they turned a drifting robot's heading the wrong way;
#: docs/navigation-design.md, "Own recent planes"). The dead reckoning's velocity bias is in the model but held at zero
#: per robot until its fixes' disagreement persists (a drift): always open, it bent good poses; never, a drifting
#: robot's error outgrew its covariance along walls no scan pinned (docs/navigation-design.md, "The dead reckoning's
#: velocity bias"). A map plane's own offset error (``plane_sigma_m``) stays off: it holds good fixes on the extracted
#: dives but costs the traced ones faces (docs/navigation-design.md, "A plane's own offset error").
SMOOTHED_NAV = NavConfig(
    fix_quality_factor=5.0,
    own_recent_s=10.0,
    own_recent_weight=0.1,
    own_recent_turns_alone=False,
    dr_bias_sigma_m_s=0.003,
    dr_bias_adaptive=True,
)


@dataclass(frozen=True)
class SmootherConfig:
    """Tuning of :class:`RobotSmoother`.

    Re-filter and smooth the last ``window_s`` of capture time every ``every_s`` or ``every_fraction`` of the
    window's length, whichever is longer (so a growing window costs about ``1 + 1 / every_fraction``
    registrations per scan, not one per smoothing); the re-filter registers ``rerun_points`` points per scan with
    ``rerun_iterations`` re-associations (the re-filter is most of the smoother's cost).

    With ``drift_max_m_s`` > 0 (off by default: docs/navigation-design.md, "Extracted clouds with good poses"), a
    run's result for a robot whose live filter has not opened its velocity bias (its fixes taken as good) is refused
    (its clouds and its live filter stay as they were) where it leaves the robot's horizontal fixes faster than a
    dead reckoning can drift (:func:`leaves_fixes`): its revised disagreement with a fix may differ from the
    disagreement at the window's first scan by at most ``drift_slack_m`` plus ``drift_max_m_s`` times the time
    between them. A dead reckoning's error grows slowly and smoothly (a velocity bias of a few cm/s); scans
    registered to a wrong plane pull an estimate off in a jump.
    """

    window_s: float = 120.0
    every_s: float = 10.0
    every_fraction: float = 0.5
    rerun_points: int = 200
    rerun_iterations: int = 4
    drift_max_m_s: float = 0.0
    drift_slack_m: float = 0.1


def leaves_fixes(
    t_s: FloatArray, off_ne: FloatArray, t0_s: float, off0_ne: FloatArray, scfg: SmootherConfig
) -> NDArray[np.bool_]:
    """Which revised poses leave their fixes faster than a dead reckoning can drift.

    Args:
        t_s: (N,) capture times of the scans with a fix, s.
        off_ne: (N, 2) each revised position minus its fix (north, east), m.
        t0_s, off0_ne: the same at the anchor (the window's first scan, as it was before the run), s and (2,) m.
        scfg: ``drift_max_m_s`` (the fastest a dead reckoning's error grows, m/s) and ``drift_slack_m`` (the
            fixes' own noise and the anchor's error, m).

    Returns (N,) True where the disagreement moved by more than ``drift_slack_m + drift_max_m_s * |t - t0|``.
    """
    moved = np.linalg.norm(np.asarray(off_ne, dtype=np.float64) - off0_ne, axis=1)
    return np.asarray(moved > scfg.drift_slack_m + scfg.drift_max_m_s * np.abs(t_s - t0_s))


@dataclass
class _Scan:
    t_ns: int
    raw: Pose
    points: NDArray[np.float32]
    #: the filter's state before this scan (to restart the filter here)
    before: dict[str, Any]
    #: after the update: the prediction (S,), (S, S), the transition from the previous scan (S, S), the
    #: posterior (S,), (S, S) (S: the smoothed state, :func:`_sub`, yaw correction last); None where the scan did
    #: not move the filter (start, unknown, late)
    prior_x: FloatArray | None = None
    prior_p: FloatArray | None = None
    trans: FloatArray | None = None
    post_x: FloatArray | None = None
    post_p: FloatArray | None = None
    est: NavEstimate | None = None


def _record(nav: RobotNav, scan: _Scan, est: NavEstimate) -> None:
    """Keep what ``nav``'s last update of ``scan`` did (for the backward pass)."""
    scan.est = est
    sub = _sub(nav)
    if nav.prior is None or nav.transition is None or est.pose is None:
        scan.prior_x = scan.prior_p = scan.trans = scan.post_x = scan.post_p = None
        if est.pose is not None:
            scan.post_x = nav.x[sub].copy()
            scan.post_p = nav.P[np.ix_(sub, sub)].copy()
        return
    scan.prior_x = nav.prior[0][sub].copy()
    scan.prior_p = nav.prior[1][np.ix_(sub, sub)].copy()
    scan.trans = nav.transition[np.ix_(sub, sub)].copy()
    scan.post_x = nav.x[sub].copy()
    scan.post_p = nav.P[np.ix_(sub, sub)].copy()


def _anchor(scan: _Scan) -> tuple[float, FloatArray] | None:
    """The window's first scan as the filter had it before a run: (time s, its position minus its fix (2,) m),
    or None without a pose or a fix."""
    est, raw = scan.est, scan.raw
    if est is None or est.pose is None or not np.isfinite(raw.north_m + raw.east_m):
        return None
    return scan.t_ns * 1e-9, np.array([est.pose.north_m - raw.north_m, est.pose.east_m - raw.east_m])


def _refilter(nav: RobotNav, scans: list[_Scan], landmarks: PlaneLandmarks) -> None:
    """Run ``nav`` over ``scans`` in order against ``landmarks``, keeping in each scan the state before its update and
    what the update did (:func:`_record`)."""
    for s in scans:
        s.before = nav.snapshot()
        est = nav.update(s.t_ns, s.raw, s.points.astype(np.float64), landmarks)
        _record(nav, s, est)


class SmoothJob:
    """One robot's smoothing run, detached from its live filter: the window's scans (copies) re-filtered from the
    state before the first one by a filter of its own, then smoothed backward. :meth:`run` touches
    nothing but the job, so it may run on another thread (:class:`FleetPlacements` with ``background``)."""

    def __init__(
        self,
        robot: str,
        cfg: NavConfig,
        scans: list[_Scan],
        first_ns: int | None,
        scfg: SmootherConfig | None = None,
    ) -> None:
        self.robot = robot
        self.cfg = cfg
        self.scfg = scfg or SmootherConfig()
        self.scans = scans
        self.first_ns = first_ns
        #: after :meth:`run`: t_ns -> revised pose, the filter's state after the last scan, the launch's position
        self.revised: dict[int, Pose] = {}
        self.end: dict[str, Any] | None = None
        self.start_map_ne: tuple[float, float] | None = None
        self._nav: RobotNav | None = None
        #: the live filter's :attr:`RobotNav.joined` when the job was made
        self.joined = True
        #: whether the run's result is checked against the robot's fixes (:func:`leaves_fixes`): while the live
        #: filter takes them as good (its velocity bias not open), a run may not leave them faster than a drift can
        self.check_fixes = True
        #: after :meth:`run`: whether its result was refused (it left the robot's fixes faster than a drift can)
        self.refused = False

    def run(self, landmarks: PlaneLandmarks) -> None:
        """Re-filter against ``landmarks`` and smooth (fills :attr:`revised`, :attr:`end`)."""
        nav = RobotNav(self.robot, self.cfg)
        nav.joined = self.joined
        anchor = _anchor(self.scans[0])
        nav.restore(self.scans[0].before)
        _refilter(nav, self.scans, landmarks)
        xs = RobotSmoother._rts(self.scans)
        for s, x in zip(self.scans, xs, strict=True):
            if x is None or s.est is None or s.est.pose is None:
                continue
            r = s.raw
            self.revised[s.t_ns] = Pose(
                float(x[0]), float(x[1]), r.down_m, r.roll_rad, r.pitch_rad, r.yaw_rad + float(x[-1])
            )
            if s.t_ns == self.first_ns:
                self.start_map_ne = (float(x[0]), float(x[1]))
        if anchor is not None and self.check_fixes and self.scfg.drift_max_m_s > 0 and self._leaves_fixes(anchor):
            # scans registered to a wrong plane moved the estimate: keep the robot as it was (the next run tries
            # again against the map as it is then)
            self.refused = True
            self.revised = {}
            self.start_map_ne = None
            log.info("%s: a smoothing run left the fixes faster than a drift can: refused", self.robot)
            return
        self.end = nav.snapshot()
        self._nav = nav

    def _offsets(self) -> FloatArray:
        """(N, 3): per revised scan with a fix, its time (s) and its revised position minus the fix (north, east; m)."""
        rows = [
            (s.t_ns * 1e-9, p.north_m - s.raw.north_m, p.east_m - s.raw.east_m)
            for s in self.scans
            if (p := self.revised.get(s.t_ns)) is not None and np.isfinite(s.raw.north_m + s.raw.east_m)
        ]
        return np.asarray(rows, dtype=np.float64).reshape(-1, 3)

    def _leaves_fixes(self, anchor: tuple[float, FloatArray]) -> bool:
        """Whether the revised poses leave the raw fixes faster than a dead reckoning drifts (:func:`leaves_fixes`)."""
        a = self._offsets()
        return bool(np.any(leaves_fixes(a[:, 0], a[:, 1:], anchor[0], anchor[1], self.scfg)))

    def catch_up(self, newer: list[_Scan], landmarks: PlaneLandmarks) -> None:
        """Carry the re-filtered state on over ``newer`` scans (copies of what the live filter took since the job
        was made), so that the hand-over has few left to re-run on the map thread."""
        nav = self._nav
        if nav is None or self.end is None:
            return
        _refilter(nav, newer, landmarks)
        self.scans.extend(newer)
        self.end = nav.snapshot()


class RobotSmoother:
    """One robot's filter and its fixed-window smoother (see the module docstring). One thread feeds it."""

    def __init__(self, robot: str, cfg: NavConfig, scfg: SmootherConfig | None = None) -> None:
        self.robot = robot
        self.nav = RobotNav(robot, cfg)
        self.scfg = scfg or SmootherConfig()
        self.scans: deque[_Scan] = deque()
        self.last_smooth_ns: int | None = None
        #: where the map now places the robot's launch (its first scan's smoothed position), north/east
        self.start_map_ne: tuple[float, float] | None = None
        self._first_ns: int | None = None

    def update(self, t_ns: int, raw: Pose, points_body: Any, landmarks: PlaneLandmarks) -> NavEstimate:
        """One cloud through the filter (:meth:`RobotNav.update`), remembered for the smoother."""
        pts = np.asarray(points_body, dtype=np.float64).reshape(-1, 3)
        keep = subsample(pts[np.all(np.isfinite(pts), axis=1)], self.scfg.rerun_points).astype(np.float32)
        scan = _Scan(int(t_ns), raw, keep, self.nav.snapshot())
        est = self.nav.update(t_ns, raw, pts, landmarks)
        _record(self.nav, scan, est)
        if est.motion == "start":
            self._first_ns = scan.t_ns
            self.start_map_ne = (float(self.nav.x[0]), float(self.nav.x[1]))
        if est.motion != "late":
            self.scans.append(scan)
            self._trim()
        return est

    def _trim(self) -> None:
        newest = self.scans[-1].t_ns
        while self.scans and newest - self.scans[0].t_ns > self.scfg.window_s * 1e9:
            self.scans.popleft()

    def due(self, t_ns: int) -> bool:
        """Whether ``every_s`` of capture time passed since the last smoothing."""
        if self.last_smooth_ns is None:
            self.last_smooth_ns = int(t_ns)
            return False
        span = (self.scans[-1].t_ns - self.scans[0].t_ns) * 1e-9 if self.scans else 0.0
        every = max(self.scfg.every_s, self.scfg.every_fraction * span)
        return t_ns - self.last_smooth_ns >= every * 1e9

    def smooth(self, landmarks: PlaneLandmarks) -> dict[int, Pose]:
        """Re-filter the window against ``landmarks`` and smooth it; returns t_ns -> the revised pose of each
        window scan that has one (placed or not: the caller decides what to re-place)."""
        job = self.prepare()
        if job is None:
            return {}
        job.run(landmarks)
        return self.apply(job, landmarks)

    def prepare(self) -> SmoothJob | None:
        """The next run's work, detached from the live filter (its scans copied): :meth:`SmoothJob.run` may run on
        another thread while this smoother keeps taking clouds; :meth:`apply` hands the result back. None when
        there is nothing to smooth."""
        if not self.scans:
            return None
        self.last_smooth_ns = self.scans[-1].t_ns
        scans = [replace(s) for s in self.scans]
        cfg = replace(self.nav.cfg, iterations=self.scfg.rerun_iterations)
        job = SmoothJob(self.robot, cfg, scans, self._first_ns, self.scfg)
        job.joined = self.nav.joined
        job.check_fixes = not self.nav.bias_open
        return job

    def apply(self, job: SmoothJob, landmarks: PlaneLandmarks) -> dict[int, Pose]:
        """Take a finished :class:`SmoothJob` back: its scans' re-filtered steps replace the window's, and the live
        filter continues from its end, re-running (against ``landmarks``) the scans that came in meanwhile.
        Returns the job's revised poses (t_ns -> Pose)."""
        if job.end is None:
            return {}
        done = {s.t_ns: s for s in job.scans}
        newer: list[_Scan] = []
        for i, s in enumerate(self.scans):
            if s.t_ns in done:
                self.scans[i] = done[s.t_ns]
            elif s.t_ns > job.scans[-1].t_ns:
                newer.append(s)
        self.nav.restore(job.end)
        _refilter(self.nav, newer, landmarks)
        if job.start_map_ne is not None:
            self.start_map_ne = job.start_map_ne
        return job.revised

    @staticmethod
    def _rts(scans: list[_Scan]) -> list[FloatArray | None]:
        """Rauch-Tung-Striebel over the scans' recorded filter steps: the smoothed state (:func:`_sub`) per scan
        (None where the filter had no state). A scan without a transition (a restart) ends the pass."""
        n = len(scans)
        xs: list[FloatArray | None] = [None] * n
        nxt: FloatArray | None = None
        for k in range(n - 1, -1, -1):
            s = scans[k]
            if s.post_x is None or s.post_p is None:
                nxt = None
                continue
            if nxt is None:
                xs[k] = s.post_x.copy()
            else:
                after = scans[k + 1]
                assert after.trans is not None
                assert after.prior_x is not None
                assert after.prior_p is not None
                c = s.post_p @ after.trans.T @ np.linalg.inv(after.prior_p)
                xs[k] = s.post_x + c @ (nxt - after.prior_x)
            nxt = xs[k] if s.trans is not None else None
        return xs


class _FleetJob:
    """One smoothing run of every robot, detached from the map thread (see :class:`FleetPlacements`)."""

    #: catch up with the live filters until at most this many scans per robot are left for the hand-over
    CATCH_UP_LEFT = 3
    CATCH_UP_PASSES = 5

    def __init__(
        self,
        jobs: dict[str, SmoothJob],
        landmarks: PlaneLandmarks,
        snap: Any,
        poses: dict[str, dict[int, Pose]],
        live: dict[str, deque[_Scan]] | None = None,
    ) -> None:
        self.jobs = jobs
        #: the live smoothers' scan windows, read (never written) to catch up with what came meanwhile
        self.live = live or {}
        self.landmarks = landmarks
        #: the builder's kept observations when the run started (copies the run may move), and the poses they
        #: were placed with
        self.snap = snap
        self.poses: dict[str, dict[int, Pose]] = poses
        self.moved = 0
        self.new_map: Any = None
        self.compute_s = 0.0
        self.error: BaseException | None = None
        self.done = threading.Event()

    def run(self) -> None:
        t0 = time.perf_counter()
        try:
            for name, job in sorted(self.jobs.items()):
                job.run(self.landmarks)
                old = self.poses.get(name, {})
                new = {t: p for t, p in job.revised.items() if t in old}
                self.moved += self.snap.move(name, old, new)
            if self.moved:
                self.new_map = self.snap.rebuild()
            self._catch_up()
        except BaseException as err:  # handed to the map thread, which logs it
            self.error = err
        finally:
            self.compute_s = time.perf_counter() - t0
            self.done.set()

    def _catch_up(self) -> None:
        """Re-run, on this thread, the scans the live filters took while the run went on (the map thread then
        re-runs only the last few at the hand-over)."""
        for _ in range(self.CATCH_UP_PASSES):
            left = 0
            for name, job in sorted(self.jobs.items()):
                window = self.live.get(name)
                if window is None or not job.scans:
                    continue
                try:
                    current = list(window)  # one C call under the GIL; retried if the map thread changed it
                except RuntimeError:
                    current = list(window)
                newer = [replace(s) for s in current if s.t_ns > job.scans[-1].t_ns]
                job.catch_up(newer, self.landmarks)
                left = max(left, len(newer))
            if left <= self.CATCH_UP_LEFT:
                return


class _GraphJob:
    """A pose graph's part of a run (:class:`mapping.posegraph.GraphNav`): its revised poses, read from the graph
    on the map thread when the run starts (the graph is its own smoother: nothing to re-run)."""

    def __init__(self, revised: dict[int, Pose]) -> None:
        self.revised = revised
        self.scans: list[Any] = []

    def run(self, landmarks: PlaneLandmarks) -> None:
        """Nothing to compute: the graph already holds every pose's smoothed estimate."""

    def catch_up(self, scans: list[Any], landmarks: PlaneLandmarks) -> None:
        """Nothing to catch up with: the live graph keeps going."""


class FleetPlacements:
    """The poses each robot's clouds are in the map with, and the step that lets the map follow the smoothers.

    The map thread calls :meth:`placed` for every cloud it puts into the map and :meth:`step` after each cloud;
    when a robot's smoother is due (or at the end of a dive, ``force``), every robot's window is smoothed against
    the map as it is, the clouds whose poses moved are re-placed (:meth:`mapping.MapBuilder.replace_poses`) and the
    map is rebuilt once. Needs ``builder.keep_placements`` (set here).
    """

    def __init__(self, nav: Any, builder: Any, background: bool | str = False) -> None:
        self.nav = nav
        self.builder = builder
        builder.keep_placements = True
        self.poses: dict[str, dict[int, Pose]] = {}
        #: with ``background`` True, a due run's re-filter, smoothing and rebuild happen on a thread of their own
        #: while the map thread goes on; the next :meth:`step` after it finished hands the result over (the
        #: scans that came meanwhile re-run, the observations merged meanwhile fused on top). ``"wait"``: the same
        #: split, but the next step waits for the run (reproducible, for benchmarks: as without background)
        self.background = background
        self._job: _FleetJob | None = None
        self._thread: threading.Thread | None = None
        #: wall time of each smoothing run (s), and the clouds it re-placed
        self.runs_s: list[float] = []
        #: how long each run during the dive held the map thread (s): all of it without background, else its start
        #: and hand-over; the end of a dive's runs (``force``), always on the map thread, in ``final_s``
        self.holds_s: list[float] = []
        self.final_s: list[float] = []
        self.replaced = 0
        self.frozen = 0
        self.errors = 0
        #: capture time of each pose graph's last run (graphs are due every ``SmootherConfig.every_s`` too)
        self._graph_runs: dict[str, int] = {}

    def placed(self, robot: str, t_ns: int, pose: Pose) -> None:
        """``robot``'s cloud of ``t_ns`` went into the map with ``pose``."""
        self.poses.setdefault(robot, {})[int(t_ns)] = pose

    def step(self, robot: str, t_ns: int, *, force: bool = False) -> list[Any]:
        """Smooth and re-place when due; returns the map's changes (:class:`mapping.types.MapChange`). ``force``
        (the end of a dive) hands over any background run and smooths once more, on this thread."""
        changes: list[Any] = []
        job = self._job
        if job is not None and (force or self.background == "wait" or job.done.is_set()):
            changes += self._hand_over()
        if force:
            return changes + self._run_here(final=True)
        sm = self.nav.smoothers.get(robot)
        if sm is None:
            if not self._graph_due(robot, t_ns):
                return changes
        elif not sm.due(t_ns):
            return changes
        if not self.background:
            return changes + self._run_here()
        if self._job is None:
            self._start()
            if self.background == "wait":
                changes += self._hand_over()
        return changes

    def _graphs(self) -> dict[str, Any]:
        """The robots navigated by a pose graph (``revised_poses``), by name."""
        return {n: r for n, r in sorted(self.nav.robots.items()) if hasattr(r, "revised_poses") and r.started}

    def _graph_due(self, robot: str, t_ns: int) -> bool:
        graph = self.nav.robots.get(robot)
        if not hasattr(graph, "revised_poses"):
            return False
        last = self._graph_runs.setdefault(robot, int(t_ns))
        every = self.nav.smoother_cfg.every_s if self.nav.smoother_cfg is not None else 10.0
        if t_ns - last < every * 1e9:
            return False
        self._graph_runs[robot] = int(t_ns)
        return True

    def _run_here(self, final: bool = False) -> list[Any]:
        """Every robot's run on this thread (``final``: the end of a dive's, timed in :attr:`final_s`)."""
        t0 = time.perf_counter()
        lm = self.builder.landmarks(self.nav.cfg.min_landmark_points)
        moved = 0
        for name, smoother in sorted(self.nav.smoothers.items()):
            try:
                revised = smoother.smooth(lm)
            except Exception as err:  # a run works on copies: the live filter and the map go on as they are
                self.errors += 1
                log.error("smoothing %s failed: %r", name, err, exc_info=err)
                continue
            mine = self.poses.get(name, {})
            new = {t: p for t, p in revised.items() if t in mine}
            moved += self.builder.replace_poses(name, mine, new)
            mine.update(new)
        for name, graph in self._graphs().items():
            mine = self.poses.get(name, {})
            new = {t: p for t, p in graph.revised_poses().items() if t in mine}
            moved += self.builder.replace_poses(name, mine, new)
            mine.update(new)
        changes: list[Any] = self.builder.rebuild() if moved else []
        self.replaced += moved
        self._freeze()
        dt = time.perf_counter() - t0
        self.runs_s.append(dt)
        (self.final_s if final else self.holds_s).append(dt)
        return changes

    def _freeze(self) -> None:
        # what left every window will not move again: fuse it once, forget its points and poses
        cut = {name: sm.scans[0].t_ns for name, sm in self.nav.smoothers.items() if sm.scans}
        cut.update({name: graph.window_start_ns for name, graph in self._graphs().items()})
        self.frozen += self.builder.freeze(cut)
        for name, t0_ns in cut.items():
            poses = self.poses.get(name)
            if poses:
                self.poses[name] = {t: p for t, p in poses.items() if t >= t0_ns}

    def _start(self) -> None:
        """Detach a run: each robot's window, the landmarks and the kept observations as they are now."""
        t0 = time.perf_counter()
        lm = self.builder.landmarks(self.nav.cfg.min_landmark_points)
        jobs = {}
        for name, smoother in sorted(self.nav.smoothers.items()):
            job = smoother.prepare()
            if job is not None:
                jobs[name] = job
        for name, graph in self._graphs().items():
            jobs[name] = _GraphJob(graph.revised_poses())  # type: ignore[assignment]
        poses = {name: dict(p) for name, p in self.poses.items()}
        live = {name: self.nav.smoothers[name].scans for name in jobs if name in self.nav.smoothers}
        self._job = _FleetJob(jobs, lm, self.builder.placements_snapshot(), poses, live)
        self._thread = threading.Thread(target=self._job.run, name="nav-smoother", daemon=True)
        self._thread.start()
        self._hold_start = time.perf_counter() - t0

    def _hand_over(self) -> list[Any]:
        """Take a background run's result into the live filters and the map (waits for it to finish)."""
        job, thread = self._job, self._thread
        assert job is not None
        assert thread is not None
        thread.join()
        t0 = time.perf_counter()
        self._job = self._thread = None
        self.runs_s.append(job.compute_s)
        if job.error is not None:
            # the live filters and the map go on as they are; the next run starts from them
            self.errors += 1
            log.error("background smoothing failed: %r", job.error, exc_info=job.error)
            return []
        lm = self.builder.landmarks(self.nav.cfg.min_landmark_points)
        for name, sj in job.jobs.items():
            revised = self.nav.smoothers[name].apply(sj, lm) if name in self.nav.smoothers else sj.revised
            mine = self.poses.setdefault(name, {})
            old = job.poses.get(name, {})
            mine.update({t: p for t, p in revised.items() if t in old})
        changes: list[Any] = self.builder.adopt(job.snap, job.new_map) if job.moved else []
        self.replaced += job.moved
        self._freeze()
        self.holds_s.append(self._hold_start + time.perf_counter() - t0)
        return changes
