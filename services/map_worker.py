"""A plane worker: the per-robot half of the map (NED transform, windows, plane extraction) in its own process.

A worker joins a fleet over Zenoh (``lrsensor map-worker --connect EP --fleet F``, or started by
``lrsensor base --map-workers N``), declares its liveliness token ``<root>/map/workers/<name>``, and takes the
jobs the base sends to ``<root>/map/work/<name>`` (:mod:`services.map_worker_wire`): one cloud each, with the pose
to place it with. It transforms the points to NED, feeds them to its own :class:`mapping.MapBuilder` (used
through :meth:`~mapping.MapBuilder.observe_cloud`: windows and extraction, no map of its own), and publishes
what each extraction gives on ``<root>/map/obs/<name>``: the plane observations (exact sufficient statistics)
and the sequence numbers of the clouds they commit. The base (the merger) only adds them to the shared map.

With navigation in the workers (the base's jobs say ``navigate``), the worker also corrects each cloud's pose
before it places it: :mod:`services.map_worker_nav` (the registration stride, the robot's state carried to its
next worker through the base). A scan it registers uses the merged map's *snapshot* its capture time names
(``snapshot(T)``, T = :func:`mapping.landmarks.snapshot_time` of the job's capture time and lag: the map after
exactly the observations before T, whatever the timing), which the merger publishes on ``<root>/map/landmarks``
once it is final. When it has not come yet, the robot's jobs wait (in order; the other robots go on) until it
does, or for at most :data:`~services.map_worker_nav.SNAPSHOT_WAIT_S`: then the scan registers against the newest
snapshot before its own and is counted ``not_exact``. Jobs without a lag use the mirror of the moment.

Which robots a worker serves is the base's decision (:mod:`services.map_workers`); the worker follows the
jobs. A job of a newer epoch for a robot means the robot was (re)assigned here: the worker forgets the robot's
old window first, since the base re-sends every cloud not yet committed. Jobs of an older epoch are stale and
ignored. The worker keeps no state worth saving: killed, its robots move and their uncommitted clouds are
processed again by their new worker.

Threading: the Zenoh callback only enqueues; one thread does the work (the builder is single-writer). The queue
is not bounded here: the base bounds what it has in flight (``services.map_workers.MAX_IN_FLIGHT``), and a
callback that blocked would stall the network thread that also carries this worker's own observations out
(a deadlock seen with workers in the base's process).
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import threading
import time
import uuid
from collections import deque
from typing import Any

import numpy as np

from lrsensor.frames import Pose, body_to_ned

from .errors import WireError
from .keys import FleetKeys
from .map_worker_nav import (
    REGISTER_EVERY_S,
    SNAPSHOT_WAIT_S,
    NavStep,
    WorkerNav,
    decode_mirror,
    decode_state,
    encode_state,
)
from .map_worker_wire import (
    FLUSH_KEY,
    HeadingViews,
    MapControl,
    MapJob,
    NavReport,
    PlaneObservations,
    decode_work,
    landmarks_key,
    obs_key,
    work_key,
    workers_key,
)
from .zconfig import undeclare_all

log = logging.getLogger(__name__)


def worker_name() -> str:
    """A name unique to this process: ``<host>-<pid>-<random>`` (a valid key chunk)."""
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:24] or "host"
    return f"{host}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


class MapWorker:
    """One plane worker on an open Zenoh session (the caller owns the session).

    Args:
        session: an open Zenoh session that reaches the base station.
        keys: the fleet's key expressions.
        name: this worker's name (default: :func:`worker_name`).
        cfg: the map configuration (must match the base's; default ``MapConfig()``, the base's default too).
        register_every_s: the navigation's registration stride (:mod:`services.map_worker_nav`).
        nav_publish_s: report a robot's registered estimate to the base at most this often (capture time, s).
        snapshot_wait_s: longest a scan waits for its snapshot (wall time, s; see the module docstring).
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        name: str | None = None,
        cfg: Any = None,
        register_every_s: float = REGISTER_EVERY_S,
        nav_publish_s: float = 0.2,
        snapshot_wait_s: float = SNAPSHOT_WAIT_S,
    ) -> None:
        from mapping import MapBuilder, MapConfig  # Open3D lives behind this import
        from mapping.landmarks import LandmarkSnapshots
        from mapping.navigation import PlaneLandmarks

        self.session = session
        self.keys = keys
        self.name = name or worker_name()
        self.builder = MapBuilder(cfg or MapConfig())
        self.nav = WorkerNav(register_every_s=register_every_s)
        self.nav_publish_s = nav_publish_s
        #: the mirror of the merged map's planes (map frame) and its version at the base
        self.landmarks: Any = PlaneLandmarks.empty()
        self.landmarks_version = -1
        #: the merger's snapshots (the snapshot rule), the merger they came from; guarded by ``_snap_cond``
        self.snapshots = LandmarkSnapshots()
        self._snap_base = ""
        self._snap_cond = threading.Condition()
        self.snapshot_wait_s = snapshot_wait_s
        #: per robot: its jobs waiting for a snapshot, in order, with when the first began to wait (monotonic s)
        self._waiting: dict[str, deque[MapJob]] = {}
        self._woken = threading.Event()
        self._wait_since: dict[str, float] = {}
        #: scans that waited for their snapshot, the longest wait (ms), scans registered against another snapshot
        self.snap_waited = 0
        self.snap_wait_ms = 0
        self.snap_not_exact = 0
        #: per robot: seqs pending that navigation did not place; capture time of the last estimate reported
        self._unplaced: dict[str, list[int]] = {}
        self._reported: dict[str, int] = {}
        self._state_failed = False
        #: per robot: the epoch it is served under and the seqs in its window not yet committed
        self._epoch: dict[str, int] = {}
        self._pending: dict[str, list[int]] = {}
        self._queue: queue.Queue[bytes | None] = queue.Queue()
        self._entities: list[Any] = []
        self._thread: threading.Thread | None = None
        self._pub: Any = None
        #: jobs done, observations published, stale jobs ignored, failures
        self.jobs = 0
        self.published = 0
        self.stale = 0
        self.errors = 0

    def __enter__(self) -> MapWorker:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Declare the publisher, the job subscriber and the liveliness token (last: the base sends jobs only
        once it sees the token, and by then the subscriber is ready)."""
        import zenoh

        from mapping.planes import open3d

        open3d()  # import it before taking robots: a first extraction would otherwise wait seconds for it
        self._thread = threading.Thread(target=self._run, name=f"map-worker-{self.name}", daemon=True)
        self._thread.start()
        self._pub = self.session.declare_publisher(
            obs_key(self.keys, self.name), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self._entities += [
            self._pub,
            self.session.declare_subscriber(landmarks_key(self.keys), self._on_landmarks),
            self.session.declare_subscriber(work_key(self.keys, self.name), self._on_work),
            self.session.liveliness().declare_token(workers_key(self.keys, self.name)),
        ]
        log.info("map worker %s of fleet %r up", self.name, self.keys.fleet)

    def close(self) -> None:
        """Withdraw the token (the base moves the robots), stop the thread."""
        undeclare_all(reversed(self._entities), f"map worker {self.name}")
        self._entities.clear()
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=10.0)
            self._thread = None

    def _on_landmarks(self, sample: Any) -> None:
        try:
            kind, a, b = decode_mirror(sample.payload.to_bytes())
        except WireError as err:
            log.warning("map worker %s: %s", self.name, err)
            return
        if kind == "snapshots":
            self.take_snapshots(a, b)
            self._woken.set()  # seen before the next job: the robots that wait go on first
            self._queue.put(b"")  # and wakes the thread when it is idle
            return
        # one publisher delivers in order, and a restarted base counts from 0 again: the newest message wins
        self.landmarks, self.landmarks_version = b, a  # the work thread sees the old or the new mirror

    def take_snapshots(self, base_id: str, ranges: list[Any]) -> None:
        """Keep snapshots the merger ``base_id`` published (a new merger's replace an old one's)."""
        with self._snap_cond:
            if base_id != self._snap_base:
                self.snapshots.clear()
                self._snap_base = base_id
            for r in ranges:
                self.snapshots.put(r)
            self._snap_cond.notify_all()

    def _on_work(self, sample: Any) -> None:
        self._queue.put(sample.payload.to_bytes())  # never blocks (see the module docstring)

    def _run(self) -> None:
        while True:
            try:
                payload = self._queue.get(timeout=0.25 if self._waiting else None)
            except queue.Empty:
                payload = b""  # a robot's wait may have passed its cap
            if payload is None:
                return
            try:
                if self._waiting and (self._woken.is_set() or not payload):
                    self._woken.clear()
                    self._retry()
                if payload:  # b"": only a wake-up
                    self.handle(decode_work(payload))
            except WireError as err:
                self.errors += 1
                log.warning("map worker %s: %s", self.name, err)
            except Exception as err:  # a bad cloud must not stop the worker
                self.errors += 1
                log.exception("map worker %s failed: %s", self.name, err)

    # ------------------------------------------------------------------ the work (also callable without Zenoh)
    def handle(self, msg: MapJob | MapControl) -> list[PlaneObservations]:
        """Process one message; returns (and publishes, when started) the observations it gave."""
        out: list[PlaneObservations] = []
        early: list[PlaneObservations] = []
        if isinstance(msg, MapControl):
            if msg.kind == "flush" and msg.robot:  # the base saw the robot go silent: its last window
                if self._epoch.get(msg.robot, -1) == msg.epoch and not self._waiting.get(msg.robot):
                    # its held clouds too (mapping.graph_hold): no later check will come for them
                    held = self._settle(msg.robot)
                    records = held + self.builder.flush_robot_observations(msg.robot)
                    if self._pending.get(msg.robot) or records:
                        out.append(self._observed(msg.robot, records, FLUSH_KEY))
            elif msg.kind == "flush":
                early = self._retry(until_done=True)  # the waiting jobs first (published): before the flush
                for robot in self.nav.robots():
                    held = self._settle(robot)
                    if held:
                        out.append(self._observed(robot, held, FLUSH_KEY))
                for robot, records in self.builder.flush_observations().items():
                    out.append(self._observed(robot, records, FLUSH_KEY))
                for robot in sorted(r for r, seqs in self._pending.items() if seqs):  # nothing left to extract
                    out.append(self._observed(robot, [], FLUSH_KEY))
            elif msg.kind == "drop" and self._epoch.get(msg.robot, -1) < msg.epoch:
                self._forget(msg.robot)
            elif msg.kind == "adopt" and self._epoch.get(msg.robot, -1) < msg.epoch:
                self._adopt(msg)
            elif msg.kind in ("views", "heading") and self._epoch.get(msg.robot, -1) == msg.epoch:
                early = self._heading(msg)
        else:
            out.extend(self._take(msg))
        self._publish(out)
        return early + out

    def _publish(self, out: list[PlaneObservations]) -> None:
        for obs in out:
            if self._pub is not None:
                self._pub.put(obs.to_bytes())
            self.published += 1

    # ------------------------------------------------------------------ the snapshot rule
    def _snapshot_of(self, job: MapJob) -> int | None:
        """The grid time of the snapshot ``job`` registers against; None: it needs none (no lag, or a scan
        between registrations)."""
        from mapping.landmarks import snapshot_time

        if not job.navigate or job.lag_ns <= 0 or not self.nav.due(job.robot, job.t_ns, job.pose):
            return None
        return snapshot_time(job.t_ns, job.lag_ns)

    def _has_snapshot(self, t_grid_ns: int | None) -> bool:
        if t_grid_ns is None:
            return True
        with self._snap_cond:
            return self.snapshots.get(t_grid_ns) is not None

    def _current(self, job: MapJob) -> bool:
        """Whether ``job`` is of the robot's current assignment here (counted ``stale`` if it is older); a newer
        epoch means the robot was (re)assigned here, and the base re-sends what is not committed: start afresh."""
        held = self._epoch.get(job.robot)
        if held is not None and job.epoch < held:
            self.stale += 1
            return False
        if held is None or job.epoch > held:
            self._forget(job.robot)
            self._epoch[job.robot] = job.epoch
        return True

    def _take(self, job: MapJob) -> list[PlaneObservations]:
        """A job in the robot's order: behind its waiting jobs, or waiting itself for its snapshot."""
        if not self._current(job):
            return []
        q = self._waiting.get(job.robot)
        if q:
            q.append(job)
            return []
        if not self._has_snapshot(self._snapshot_of(job)):
            self._waiting[job.robot] = deque([job])
            self._wait_since[job.robot] = time.monotonic()
            self.snap_waited += 1
            return []
        return self._job(job)

    def _drop_waiting(self, robot: str) -> None:
        self._waiting.pop(robot, None)
        self._wait_since.pop(robot, None)

    def _retry(self, until_done: bool = False) -> list[PlaneObservations]:
        """Run the waiting jobs whose snapshot came or whose wait passed its cap (publishing each observation at
        once: the merger waits for them); with ``until_done``, wait for the snapshots (each up to its cap) until no
        job waits. Returns the observations published."""
        out: list[PlaneObservations] = []
        while True:
            for robot in sorted(self._waiting):
                q = self._waiting[robot]
                while q:
                    job = q[0]
                    since = self._wait_since.get(robot)
                    waited = since is not None and time.monotonic() - since >= self.snapshot_wait_s
                    if not waited and not self._has_snapshot(self._snapshot_of(job)):
                        break
                    q.popleft()
                    if since is not None:
                        self.snap_wait_ms = max(self.snap_wait_ms, round(1e3 * (time.monotonic() - since)))
                        self._wait_since.pop(robot, None)
                    done = self._job(job)
                    self._publish(done)
                    out += done
                    if q and not self._has_snapshot(self._snapshot_of(q[0])):  # the next one waits anew
                        self._wait_since[robot] = time.monotonic()
                        self.snap_waited += 1
                if not q:
                    self._drop_waiting(robot)
            if not until_done or not self._waiting:
                return out
            with self._snap_cond:
                self._snap_cond.wait(0.05)

    def _forget(self, robot: str) -> None:
        self.builder.drop_robot(robot)
        self.nav.forget(robot)
        self._pending.pop(robot, None)
        self._unplaced.pop(robot, None)
        self._reported.pop(robot, None)
        self._epoch.pop(robot, None)
        self._drop_waiting(robot)

    def _adopt(self, msg: MapControl) -> None:
        """The robot moved here: its navigation continues from the state after its last committed cloud."""
        self._forget(msg.robot)
        self._epoch[msg.robot] = msg.epoch
        if msg.state:
            try:
                self.nav.set_no_fix(msg.no_fix)
                self.nav.restore(msg.robot, decode_state(msg.state))
                return
            except (WireError, KeyError, TypeError, ValueError) as err:
                log.warning("map worker %s: %s's navigation restarts (state refused: %s)", self.name, msg.robot, err)

    def _heading(self, msg: MapControl) -> list[PlaneObservations]:
        """The fleet heading (:mod:`services.map_worker_heading`), after the robot's jobs that wait for their
        snapshot (the base sent this after them): its views sent to the base, or its compass bias given to its
        graph. Returns the observations those jobs gave (published)."""
        early = self._retry(until_done=True) if self._waiting.get(msg.robot) else []
        if msg.kind == "views":
            views = encode_state(self.nav.heading_views(msg.robot))
            if self._pub is not None:
                self._pub.put(HeadingViews(self.name, msg.robot, msg.epoch, views).to_bytes())
            return early
        got = decode_state(msg.state)
        self.nav.give_heading(msg.robot, float(got["bias_rad"]), float(got["sd_rad"]), int(got["t_ns"]))
        return early

    def _landmarks_for(self, job: MapJob) -> Any:
        """The planes ``job``'s scan registers against: its snapshot, else (late past the cap, or dropped) the
        newest before it, counted not exact; without a lag, the mirror of the moment."""
        want = self._snapshot_of(job)
        if want is None:
            return self.landmarks
        with self._snap_cond:
            rng = self.snapshots.get(want)
            if rng is None or not rng.exact:
                self.snap_not_exact += 1
                rng = rng or self.snapshots.newest_before(want)
        if rng is None:
            from mapping.navigation import PlaneLandmarks

            return PlaneLandmarks.empty()
        return rng.landmarks

    def _navigate(self, job: MapJob) -> NavStep:
        self.nav.set_no_fix(job.no_fix)  # the base's --no-fix choice (a bad value fails the cloud, logged)
        step = self.nav.step(job.robot, job.t_ns, job.pose, job.points_body, self._landmarks_for(job), job.heading)
        est = step.estimate
        if est is not None and self._pub is not None:
            last = self._reported.get(job.robot)
            if last is None or not 0 <= est.t_ns - last < self.nav_publish_s * 1e9:
                self._reported[job.robot] = est.t_ns
                self._pub.put(NavReport(self.name, job.robot, job.epoch, encode_state(est)).to_bytes())
        return step

    def _job(self, job: MapJob) -> list[PlaneObservations]:
        if not self._current(job):
            return []
        self.jobs += 1
        self._pending.setdefault(job.robot, []).append(job.seq)
        self.builder.set_range_error(job.robot, job.range_error_per_px)  # its calibration's: the clouds' range noise
        pose = job.pose
        held: list[Any] = []
        try:
            if job.navigate:
                step = self._navigate(job)
                # a held robot's clouds its check vouched for (mapping.graph_hold); acknowledged when they came
                held = self._place_released(job.robot, self.nav.released(job.robot))
                if step.pose is None or not step.placed:  # done with, without planes (or held: placed later)
                    done = (job.seq,) if not (step.estimate is not None and step.estimate.held) else ()
                    self._unplaced.setdefault(job.robot, []).extend(done)
                    if self.builder.uncommitted(job.robot) == 0:
                        return [self._observed(job.robot, held, job.t_ns)]
                    due = self.builder.observe_time(job.robot, job.t_ns)
                    if due is not None:  # the window's clouds are due by time: a lost robot's last clouds commit
                        return [self._observed(job.robot, held + due, job.t_ns)]
                    # mid-window: committed now on its own, or the base, counting it in the window, would bound the
                    # window's next observation too early (and hold the merge and the snapshots back); no state:
                    # the one carried must follow the window's clouds, which are not committed yet
                    self._pending[job.robot].remove(job.seq)
                    for seq in done:
                        self._unplaced[job.robot].remove(seq)
                    from mapping.plane_map import record_to_wire

                    wire = [record_to_wire(r) for r in held]
                    return [self._observations(job.robot, (job.seq,), wire, job.t_ns, done, b"")]
                pose = step.pose
            pts = job.points_body.astype(np.float64)
            records = self.builder.observe_cloud(job.robot, job.t_ns, body_to_ned(pts, pose), pose)
            if held:  # (a placed cloud and released ones together: not expected, not lost)
                records = held + (records or [])
        except Exception as err:  # done with, not stuck in flight at the base: commit what is pending, no planes
            self.errors += 1
            log.warning("map worker %s: cloud %s#%d not mapped: %s", self.name, job.robot, job.seq, err)
            return [self._observed(job.robot, [], job.t_ns)]
        if records is None:
            if self.builder.uncommitted(job.robot) == 0:  # an operator's cap left it out: done with it
                return [self._observed(job.robot, [], job.t_ns)]
            return []
        return [self._observed(job.robot, records, job.t_ns)]

    def _place_released(self, robot: str, released: list[tuple[int, Pose, Any]]) -> list[Any]:
        """Put released held clouds into the robot's window; the plane observations their extractions gave."""
        records: list[Any] = []
        for t_ns, pose, pts in released:
            got = self.builder.observe_cloud(robot, t_ns, body_to_ned(pts.astype(np.float64), pose), pose)
            records.extend(got or [])
        return records

    def _settle(self, robot: str) -> list[Any]:
        """The robot's held clouds checked alone (silent robot, end of the dive) against the newest planes (with
        the snapshot rule the newest snapshot: the mirror of the moment is then never sent, and checked against
        no plane every held cloud would be dropped): the observations of those that go into the map."""
        with self._snap_cond:
            final = self.snapshots.final_ns
            newest = self.snapshots.get(final) if final is not None else None
        landmarks = newest.landmarks if newest is not None else self.landmarks
        return self._place_released(robot, self.nav.settle(robot, landmarks))

    def _observed(self, robot: str, records: list[Any], key_ns: int) -> PlaneObservations:
        from mapping.plane_map import record_to_wire

        seqs = tuple(self._pending.pop(robot, []))
        unplaced = tuple(self._unplaced.pop(robot, []))
        wire = [record_to_wire(r) for r in records]
        return self._observations(robot, seqs, wire, key_ns, unplaced, self._nav_state(robot))

    def _observations(
        self,
        robot: str,
        seqs: tuple[int, ...],
        wire: list[dict[str, Any]],
        key_ns: int,
        unplaced: tuple[int, ...],
        nav_state: bytes,
    ) -> PlaneObservations:
        epoch = self._epoch.get(robot, 0)
        counts = (self.snap_waited, self.snap_wait_ms, self.snap_not_exact)
        return PlaneObservations(self.name, robot, epoch, seqs, tuple(wire), key_ns, unplaced, nav_state, *counts)

    def _nav_state(self, robot: str) -> bytes:
        """The robot's navigation state after its last processed cloud (b"": none, or it does not encode)."""
        snap = self.nav.snapshot(robot)
        if snap is None:
            return b""
        try:
            return encode_state(snap)
        except WireError as err:
            if not self._state_failed:
                self._state_failed = True
                log.warning("map worker %s: navigation state not carried (a moved robot restarts): %s", self.name, err)
            return b""
