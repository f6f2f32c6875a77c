"""The base station's map feed: accepted clouds -> one map thread -> ``mapping.MapBuilder`` -> map updates.

Road: an ingest worker that accepted a cloud hands it to :meth:`MapFeed.take`, which puts it in a bounded
queue; the one map thread (``MapBuilder.add_cloud`` is single-writer) transforms its points to NED, feeds the
builder, and publishes what changed. Each cloud is then reported to the ledger (``on_mapped``): taken in by
the map, it is acknowledgeable at the next checkpoint. Without the map (``--map off``, or Open3D missing with
``--map auto``) :meth:`MapFeed.take` reports the cloud at once.

Every cloud goes into the map by default (``MapConfig.max_cloud_rate_hz`` = 0). An operator who sets a per-robot
cap gets it counted: ``map.rate_skipped`` in the status (those clouds only make the robot's track).

The backlog policy (bounded, counted, shown): the map queue holds at most ``queue_size`` clouds (``map.backlog``
and ``map.backlog_limit`` in the status). A full map queue blocks the ingest worker for up to ``map_wait_s``,
which in turn fills the ingest queue and blocks the Zenoh callback, which pushes back on the robots' BLOCK
publishers: a map that falls behind slows the fleet's delivery (the robots' outboxes hold the clouds) instead of
thinning. A map stalled longer than ``map_wait_s`` loses the cloud (``map.skipped``, logged); the cloud is
still received and acknowledged, or the robot would re-send it forever to a map that cannot take it.

A cloud *reaches the map* when the extraction of its robot's window commits it (``robots.<robot>.mapped`` counts
those clouds; ``map.latency_ms.p50``/``p99`` is capture time to that moment, over the recent clouds; clouds
waiting in a window for their extraction are ``map.pending``). With plane workers (:mod:`services.map_workers`)
the same counters come from the workers' observations.

Wire form of the updates (``<root>/map/updates``, JSON, one message per cloud that changed the map)::

    {"t_ns": capture time of the cloud (or publication time for a flush), "robot", "seq",
     "planes": [plane as in the map JSON, or {"id", "removed": true, "merged_into"}]}

The builder returns typed :class:`mapping.MapChange` values; they become JSON only here, at the wire
(:func:`change_json`), and only when the base publishes.

Navigation (``mapping.navigation``; on by default in the base station): before a cloud goes into the map, the map
thread corrects its pose. The robot's estimator registers the cloud against the map's planes and fuses that with
the raw pose's dead reckoning, fixes or a motion prior; the cloud is placed with the corrected pose. The raw pose
stays what the robot sent (the ledger's track, the wire). Each estimate is published on ``<root>/<robot>/nav``
(JSON, at most every ``nav_publish_s`` of capture time per robot; the latest is also served by the base's
queryable) and summarized per robot in the status (:meth:`MapFeed.nav_status`). The map and the poses are served in
NED, turned by the fleet's frame (:class:`mapping.navigation.NavFrame`).

Clouds the map cannot place: a cloud whose robot has no position yet (no horizontal fix ever, or, with
navigation, an estimate too uncertain to place: ``NavConfig.place_std_m``), is not mapped, never placed at
north = east = 0. Without navigation, every cloud without a horizontal fix (``north_m``/``east_m`` null: a
pose source with attitude and depth only) is such a cloud. It is counted (``map.unplaced`` here, per robot in
:meth:`MapFeed.nav_status`), logged once per robot at warning level, and reported to the ledger as done with
(acknowledgeable: it is held in the received counters, and the robot must not re-send it forever to a map that
cannot take it).

Also here: the end-to-end latency statistics (capture time to the moment a cloud is handed to the map) and
the publication-to-base transit times (:class:`LatencyStats`), and :func:`load_map_builder`, which finds out
whether the map can run on this install (Open3D lives behind the ``mapping`` import).
"""

from __future__ import annotations

import collections
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from lrsensor.frames import body_to_ned

from .capture_order import CaptureOrder, QuietFlush
from .errors import MappingUnavailableError
from .posetrack import has_fix
from .wire import CloudMsg

if TYPE_CHECKING:
    from mapping import MapBuilder, MapChange
    from mapping.navigation import NavEstimate, NavFrame, Navigator
    from mapping.smoother import FleetPlacements

    from .map_workers import WorkerPool

log = logging.getLogger(__name__)

#: How long :meth:`MapFeed.close` waits for the map thread to finish its queue, seconds.
CLOSE_TIMEOUT_S = 60.0
#: Marker in the map queue: flush the map.
_FLUSH: Any = object()
#: how often an idle map thread looks for silent robots whose clouds wait in their hold (s)
SILENT_CHECK_S = 1.0
#: Publish a robot's corrected pose at most this often (seconds of capture time).
NAV_PUBLISH_S = 0.2


class LatencyStats:
    """End-to-end latencies (base processing time minus capture time), ns, of the most recent clouds.

    Thread-safe: any thread may :meth:`add` while another asks for percentiles.
    """

    def __init__(self, maxlen: int = 200_000) -> None:
        self.values: collections.deque[int] = collections.deque(maxlen=maxlen)
        self.transit: collections.deque[int] = collections.deque(maxlen=maxlen)
        self._lock = threading.Lock()

    def add(self, latency_ns: int, transit_ns: int | None) -> None:
        """Record one cloud."""
        with self._lock:
            self.values.append(latency_ns)
            if transit_ns is not None:
                self.transit.append(transit_ns)

    def percentiles_ms(self, qs: Iterable[float] = (50, 99), transit: bool = False) -> dict[str, float]:
        """Percentiles in ms (NaN when empty) of the end-to-end latencies, or with ``transit`` of the
        publication-to-base times (meaningful also when a recorded dive with old capture times is replayed)."""
        with self._lock:
            arr = np.asarray(self.transit if transit else self.values, dtype=float)
        return {f"p{q:g}": float(np.percentile(arr, q) / 1e6) if arr.size else float("nan") for q in qs}


def load_map_builder(map_dir: Path, mode: str) -> MapBuilder | None:
    """``mapping.MapBuilder`` for ``map_dir`` (reloading its map), or None when the map is off.

    ``mode``: ``"on"`` (missing mapping is an error), ``"auto"`` (missing mapping is a warning), ``"off"``.
    """
    if mode == "off":
        return None
    try:
        from mapping import MapBuilder, MapConfig  # Open3D lives behind this import
    except (ImportError, OSError) as err:
        text = (
            f"the shared map needs the 'mapping' package with Open3D (pip install 'lrsensor[base]'; the open3d "
            f"wheel also needs the system library libusb-1.0-0): {err}"
        )
        if mode == "on":
            raise MappingUnavailableError(text) from err
        log.warning("map disabled: %s", text)
        return None
    map_dir.mkdir(parents=True, exist_ok=True)
    return MapBuilder(MapConfig(), map_dir)


def change_json(change: MapChange) -> dict[str, Any]:
    """The wire form of one map change: the plane's serving dict, or ``{"id", "removed", "merged_into"}``."""
    if change.plane is not None:
        return change.plane.to_json()
    return {"id": change.plane_id, "removed": True, "merged_into": change.merged_into}


def json_default(obj: Any) -> Any:
    """``json.dumps`` fallback for numpy values and sets in map data."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    msg = f"not JSON serialisable: {type(obj).__name__}"
    raise TypeError(msg)


class MapFeed:
    """The map queue, the map thread and the publication of map changes (see the module docstring).

    Args:
        builder: the map (None: the map is off; clouds are reported to ``on_mapped`` at once).
        on_mapped: called with ``(robot, seq)`` once a cloud is taken in by the map or left out of it.
        queue_size: map queue capacity, clouds.
        map_wait_s: how long :meth:`take` waits for room in the map queue before the cloud is left out of
            the map (counted as ``skipped``).
        navigation: correct the poses from the scans before mapping (needs the map; the base station turns it
            on by default).
        nav_publish_s: publish a robot's corrected pose at most this often (capture time, seconds).
    """

    def __init__(
        self,
        builder: MapBuilder | None,
        on_mapped: Callable[[str, int], None],
        *,
        queue_size: int = 1024,
        map_wait_s: float = 5.0,
        navigation: bool = False,
        nav_publish_s: float = NAV_PUBLISH_S,
    ) -> None:
        self.builder = builder
        self.on_mapped = on_mapped
        self.map_wait_s = map_wait_s
        self.latency = LatencyStats()
        #: clouds the builder has taken, clouds left out because the map was too far behind, map failures
        self.clouds = 0
        self.skipped = 0
        self.errors = 0
        #: clouds left out because their pose has no horizontal fix, and the robots already warned about
        self.unplaced = 0
        self._unplaced_robots: set[str] = set()
        self.queue_size = queue_size
        self._queue: queue.Queue[CloudMsg | None] = queue.Queue(maxsize=queue_size)
        #: the clouds taken from the queue, released to the map in capture order across robots
        self._order = CaptureOrder(queue_size)
        #: the end of a dive seen live (the fleet silent): the map flushed as at a close
        self.quiet = QuietFlush()
        #: capture time -> map update latencies of the clouds that reached the map
        self.map_latency = LatencyStats()
        #: per robot: clouds that reached the map; (seq, t_ns) of those waiting in the builder's window
        self._mapped: dict[str, int] = {}
        self._pending: dict[str, list[tuple[int, int]]] = {}
        self._count_lock = threading.Lock()
        self._publish: Callable[[str], object] | None = None
        self._thread: threading.Thread | None = None
        self._planes = 0
        self._planes_stale = True
        self.navigator: Navigator | None = None
        #: with navigation, the smoothers' bookkeeping (past poses re-estimated, their clouds re-placed)
        self.fleet: FleetPlacements | None = None
        self._nav_on = builder is not None and navigation
        if self._nav_on:
            from mapping.navigation import NavFrame

            self._frame: NavFrame = NavFrame()
            self.set_smoothing(True)
        #: plane workers (None: the map thread extracts in this process)
        self.pool: WorkerPool | None = None
        self.nav_publish_s = nav_publish_s
        self._per_px: dict[tuple[str, int], float] = {}  # (robot, seq) -> its calibration's range error per px
        self._publish_nav: Callable[[str, str], object] | None = None
        self._nav_lock = threading.Lock()
        #: per robot: the latest estimate (turned to NED), clouds placed / not placed, last publication
        self._nav_latest: dict[str, NavEstimate] = {}
        self._nav_counts: dict[str, list[int]] = {}
        #: per robot, the held clouds its pose graph dropped so far (counted as unplaced), and when a cloud of it
        #: last came (monotonic s: a silent robot's held clouds are settled, _settle_silent)
        self._dropped: dict[str, int] = {}
        self._last_seen: dict[str, float] = {}
        self._nav_published: dict[str, int] = {}

    def set_smoothing(self, on: bool, wait: bool = False) -> None:
        """With navigation (before :meth:`start`): smooth each robot's past poses and re-place its clouds
        (``mapping.smoother``, the default), or correct each cloud once with the filter alone. Plane workers
        (:meth:`use_workers`) turn it off: the re-placement needs the observations in this process. ``wait``: the
        map thread waits for each run to finish and takes it over at once (``lrsensor base --smoother wait``: the
        map the in-process replays make, whatever the machine's speed), instead of going on while it runs."""
        if not self._nav_on:
            return
        from mapping.navigation import Navigator
        from mapping.smoother import SMOOTHED_NAV, FleetPlacements, SmootherConfig

        if on:
            self.navigator = Navigator(SMOOTHED_NAV, SmootherConfig())
            assert self.builder is not None
            # the re-filter and rebuild run on a thread of their own: the map thread is held only to start a
            # run and hand its result over (docs/navigation-design.md, "The smoother")
            self.fleet = FleetPlacements(self.navigator, self.builder, background="wait" if wait else True)
        else:
            self.navigator = Navigator()
            self.fleet = None
            if self.builder is not None:
                self.builder.keep_placements = False

    @property
    def smoothing(self) -> bool:
        """Whether past poses are smoothed and their clouds re-placed."""
        return self.fleet is not None

    @property
    def navigation(self) -> bool:
        """Whether the poses are corrected from the scans before mapping."""
        return self.navigator is not None

    @property
    def enabled(self) -> bool:
        """Whether there is a map to feed."""
        return self.builder is not None

    def start(
        self, publish: Callable[[str], object] | None, publish_nav: Callable[[str, str], object] | None = None
    ) -> None:
        """Start the map thread (when the map is on); ``publish`` puts one JSON map update on the wire,
        ``publish_nav(robot, json)`` one corrected pose."""
        self._publish = publish
        self._publish_nav = publish_nav
        if self.builder is not None:
            self._thread = threading.Thread(target=self._worker, name="base-map", daemon=True)
            self._thread.start()

    def use_workers(self, pool: WorkerPool) -> None:
        """Send the per-robot work to plane workers (before :meth:`start`); the map thread then only dispatches,
        ``pool`` merges what the workers observe (see :mod:`services.map_workers`), and with navigation the
        workers navigate too (:mod:`services.map_worker_nav`): this feed keeps their robots' states for the fleet's
        frame and serves their estimates."""
        self.pool = pool
        if self.fleet is not None:
            self.set_smoothing(False)
        pool.on_commit = self._commit_done
        pool.on_changes = lambda changes: self._publish_changes(None, changes)
        if self.navigator is not None:
            from .map_worker_heading import attach

            pool.navigate = True
            pool.landmark_min_points = self.navigator.cfg.min_landmark_points
            pool.on_nav_state = self._worker_nav_state
            attach(pool, self.navigator, lambda est: self._nav_publish(est.turned(self._frame)))  # + fleet heading

    def close(self, save: bool) -> None:
        """Stop publishing, let the map thread finish its queue, flush the map, and save it when ``save``."""
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join(timeout=CLOSE_TIMEOUT_S)
            self._thread = None
        if self.pool is not None:
            if not self.pool.flush(CLOSE_TIMEOUT_S):
                log.warning("map workers: %d clouds not committed at close (not acknowledged)", self.pool.in_flight)
            self.pool.close()
        self._publish = None
        self._publish_nav = None
        if self.builder is not None:
            try:
                self.builder.flush()
                if save:
                    self.builder.save()
            except Exception as err:
                log.error("map flush/save failed: %s", err)

    def save(self) -> None:
        """Write the map to its folder (no-op when the map is off)."""
        if self.builder is not None:
            self.builder.save()

    # ------------------------------------------------------------------ input
    def take(self, msg: CloudMsg, recv_ns: int, range_error_per_px: float = 0.0) -> None:
        """Hand an accepted cloud, received at ``recv_ns``, to the map (blocks up to ``map_wait_s``); a cloud
        without a horizontal fix is counted as unplaced instead (see the module docstring). ``range_error_per_px``:
        its calibration's when known (its range noise in the map, :mod:`mapping.range_noise`; 0: none)."""
        if not has_fix(msg.pose) and self.navigator is None:
            self._count_unplaced(msg, "its pose source gives attitude and depth only")
            self.on_mapped(msg.robot, msg.seq)  # done with: acknowledgeable, or the robot re-sends it forever
        elif self.builder is not None and len(msg):
            if range_error_per_px > 0.0:
                self._per_px[(msg.robot, msg.seq)] = range_error_per_px
            try:
                # back-pressure while the map keeps up; a map stalled for map_wait_s loses the cloud (counted)
                self._queue.put(msg, timeout=self.map_wait_s)
            except queue.Full:
                self.skipped += 1
                self._per_px.pop((msg.robot, msg.seq), None)
                self.on_mapped(msg.robot, msg.seq)  # counted, not silent; or the robot re-sends it forever
                if self.skipped <= 5 or self.skipped % 100 == 0:
                    text = "map is %.0f s behind: cloud %s#%d not mapped (%d so far)"
                    log.warning(text, self.map_wait_s, msg.robot, msg.seq, self.skipped)
        else:
            self.on_mapped(msg.robot, msg.seq)
        self.latency.add(time.time_ns() - msg.t_ns, recv_ns - msg.sent_ns if msg.sent_ns else None)

    def _count_unplaced(self, msg: CloudMsg, why: str) -> None:
        """Count a cloud the map cannot place (the caller reports it to the ledger)."""
        self.unplaced += 1
        with self._nav_lock:
            self._nav_counts.setdefault(msg.robot, [0, 0])[1] += 1
        if msg.robot not in self._unplaced_robots:
            self._unplaced_robots.add(msg.robot)
            text = "cloud %s#%d has no horizontal position (%s): such clouds of %s are not mapped, counted as unplaced"
            log.warning(text, msg.robot, msg.seq, why, msg.robot)

    def idle(self) -> bool:
        """Whether every cloud handed over has been through the map."""
        return self._queue.unfinished_tasks == 0

    def flush(self) -> None:
        """Let the map thread finish its queue and extract what the map still holds (end of a dive)."""
        if self.builder is None:
            return
        self._queue.put(_FLUSH)
        self._queue.join()
        if self.pool is not None:
            self.pool.flush(CLOSE_TIMEOUT_S)

    # ------------------------------------------------------------------ the map thread
    def _worker(self) -> None:
        """The one thread that feeds the map (``MapBuilder.add_cloud`` is single-writer)."""
        while True:
            try:
                msg = self._order.next_from(self._queue, SILENT_CHECK_S)
            except queue.Empty:
                try:
                    self._settle_silent()
                    if self.pool is None and self.quiet.due(time.monotonic()):
                        self._end_of_dive()
                        self.quiet.flushed()
                except Exception as err:  # the map must never stop the ingest
                    self.errors += 1
                    log.exception("settling a silent robot's held clouds failed: %s", err)
                continue
            deferred = False
            try:
                if msg is None:
                    return
                if msg is _FLUSH:
                    self._end_of_dive()
                    continue
                self.quiet.cloud(time.monotonic())
                deferred = self._map_one(msg)
            except Exception as err:  # the map must never stop the ingest
                self.errors += 1
                log.exception("map update failed: %s", err)
            finally:
                # taken in (or refused by the map): acknowledgeable; with workers, once committed (_commit_done)
                if isinstance(msg, CloudMsg) and not deferred:
                    self.on_mapped(msg.robot, msg.seq)
                self._queue.task_done()

    def _end_of_dive(self) -> None:
        """A flush (:meth:`flush`, or the fleet silent for ``QuietFlush.quiet_s``): held clouds settled, every
        window extracted, the smoothers' last run, the pending clouds committed."""
        if self.builder is not None:
            self._settle()
        self._publish_changes(None, self.builder.flush() if self.builder is not None else [])
        if self.fleet is not None:  # the map as the last smoothing leaves it
            self._publish_changes(None, self.fleet.step("", 0, force=True))
            assert self.navigator is not None
            self._frame = self.navigator.frame()
        for robot in list(self._pending):
            self._commit(robot)

    def _map_one(self, msg: CloudMsg) -> bool:
        """Place one cloud; True when plane workers will commit (and acknowledge) it later."""
        assert self.builder is not None
        per_px = self._per_px.pop((msg.robot, msg.seq), 0.0)
        self.builder.set_range_error(msg.robot, per_px)  # its clouds' range noise, held ones' too
        if self.pool is not None and self.pool.navigate:  # the workers navigate (services.map_worker_nav)
            self.pool.dispatch(msg.robot, msg.seq, msg.t_ns, msg.pose, msg.points_body, per_px)
            self.clouds += 1
            return True
        points_body = msg.points_body.astype(np.float64)
        pose = msg.pose
        if self.fleet is not None:
            # when the robot's smoother is due: past poses re-estimated, their clouds re-placed, the map rebuilt
            self._publish_changes(None, self.fleet.step(msg.robot, msg.t_ns))
        if self.navigator is not None:
            lm = self.builder.landmarks(self.navigator.cfg.min_landmark_points)
            est = self.navigator.update(msg.robot, msg.t_ns, msg.pose, points_body, lm)
            self._frame = self.navigator.frame()
            self._nav_publish(est.turned(self._frame))
            self._place_released(msg.robot, self.navigator.released(msg.robot))
            self._last_seen[msg.robot] = time.monotonic()
            if est.held:  # received; it goes into the map once its track's next check passes (mapping.graph_hold)
                changes = self.builder.advance_time(msg.robot, msg.t_ns)  # released clouds due by time
                if self.builder.uncommitted(msg.robot) == 0:
                    self._commit(msg.robot)
                self._publish_changes(msg, changes)
                return False
            if est.pose is None or not est.placed:
                self._count_unplaced(
                    msg,
                    "navigation has no position for it yet"
                    if est.pose is None
                    else "navigation's position is too uncertain",
                )
                changes = self.builder.advance_time(msg.robot, msg.t_ns)  # its placed clouds due by time
                if self.builder.uncommitted(msg.robot) == 0:
                    self._commit(msg.robot)
                self._publish_changes(msg, changes)
                return False
            pose = est.pose
            with self._nav_lock:
                self._nav_counts.setdefault(msg.robot, [0, 0])[0] += 1
        if self.pool is not None:
            self.pool.dispatch(msg.robot, msg.seq, msg.t_ns, pose, msg.points_body, per_px)
            self.clouds += 1
            return True
        points_ned = body_to_ned(points_body, pose)
        skipped_before = self.builder.rate_skipped
        changes = self.builder.add_cloud(msg.robot, msg.t_ns, points_ned, pose)
        if self.fleet is not None:
            self.fleet.placed(msg.robot, msg.t_ns, pose)
        self.clouds += 1
        if self.builder.rate_skipped == skipped_before:  # not left out by an operator's cap
            with self._count_lock:
                self._pending.setdefault(msg.robot, []).append((msg.seq, msg.t_ns))
            if self.builder.uncommitted(msg.robot) == 0:
                self._commit(msg.robot)
        self._publish_changes(msg, changes)
        return False

    def _place_released(self, robot: str, released: list[tuple[int, Any, Any]]) -> None:
        """Put a held robot's clouds its last check vouched for into the map (they were acknowledged when they
        came: counted as placed, timed from their capture when their window commits)."""
        assert self.builder is not None
        hold = self.navigator.hold_counts(robot) if self.navigator is not None else None
        dropped = int(hold["dropped"]) if hold is not None else 0
        gone = dropped - self._dropped.get(robot, 0)
        if gone > 0:  # held clouds no check vouched for: never placed, counted as unplaced now
            self._dropped[robot] = dropped
            self.unplaced += gone
            with self._nav_lock:
                self._nav_counts.setdefault(robot, [0, 0])[1] += gone
        for t_ns, pose, pts in released:
            self.clouds += 1
            changes = self.builder.add_cloud(robot, t_ns, body_to_ned(pts.astype(np.float64), pose), pose)
            if self.fleet is not None:
                self.fleet.placed(robot, t_ns, pose)
            with self._nav_lock:
                self._nav_counts.setdefault(robot, [0, 0])[0] += 1
            with self._count_lock:
                self._pending.setdefault(robot, []).append((-1, t_ns))
            if self.builder.uncommitted(robot) == 0:
                self._commit(robot)
            self._publish_changes(None, changes)

    def _settle_silent(self) -> None:
        """Without plane workers: each robot silent for ``IDLE_FLUSH_S`` whose clouds wait in its hold gets them
        checked alone (no later check will come), and its window extracted."""
        if self.builder is None or self.navigator is None or self.pool is not None:
            return
        from .map_workers import IDLE_FLUSH_S

        now = time.monotonic()
        for robot, nav in sorted(self.navigator.robots.items()):
            hold = getattr(nav, "hold", None)
            if hold is None or not hold.clouds or now - self._last_seen.get(robot, now) < IDLE_FLUSH_S:
                continue
            lm = self.builder.landmarks(self.navigator.cfg.min_landmark_points)
            self._place_released(robot, self.navigator.settle(robot, lm))
            self._publish_changes(None, self.builder.merge(self.builder.flush_robot_observations(robot)))
            if self.builder.uncommitted(robot) == 0:
                self._commit(robot)

    def _settle(self) -> None:
        """The end of a dive: each robot's held clouds checked alone, those vouched for into the map."""
        assert self.builder is not None
        if self.navigator is None or self.pool is not None:
            return
        lm = self.builder.landmarks(self.navigator.cfg.min_landmark_points)
        for robot in sorted(self.navigator.robots):
            self._place_released(robot, self.navigator.settle(robot, lm))

    def _commit(self, robot: str) -> None:
        """The robot's pending clouds reached the map (their window was extracted): count them, time them."""
        now = time.time_ns()
        with self._count_lock:
            done = self._pending.pop(robot, [])
            self._mapped[robot] = self._mapped.get(robot, 0) + len(done)
        for _seq, t_ns in done:
            self.map_latency.add(now - t_ns, None)

    def _commit_done(self, robot: str, done: list[tuple[int, int]], unplaced: tuple[int, ...] = ()) -> None:
        """Plane workers committed these ``(seq, t_ns)`` clouds of ``robot``: count, time, acknowledge (of them,
        ``unplaced`` are those the workers' navigation could not place: counted as such, not as mapped)."""
        now = time.time_ns()
        left_out = set(unplaced)
        n_out = sum(1 for seq, _ in done if seq in left_out)
        with self._count_lock:
            self._mapped[robot] = self._mapped.get(robot, 0) + len(done) - n_out
        if n_out:
            self.unplaced += n_out
            with self._nav_lock:
                counts = self._nav_counts.setdefault(robot, [0, 0])
                counts[1] += n_out
        if self.navigator is not None and self.pool is not None and self.pool.navigate:
            with self._nav_lock:
                self._nav_counts.setdefault(robot, [0, 0])[0] += len(done) - n_out
        for seq, t_ns in done:
            if seq not in left_out:
                self.map_latency.add(now - t_ns, None)
            self.on_mapped(robot, seq)

    def _worker_nav_state(self, robot: str, state: bytes) -> None:
        """A worker's navigation state of ``robot`` after its committed clouds: kept in this feed's
        :class:`~mapping.navigation.Navigator` for the fleet's frame (the mean heading correction)."""
        from mapping.navigation import RobotNav

        from .map_worker_nav import decode_state

        nav = self.navigator
        if nav is None:
            return
        try:
            snap = decode_state(state)["nav"]
        except Exception as err:  # the frame goes on without this robot's newest state
            log.debug("navigation state of %s not decoded: %s", robot, err)
            return
        from mapping.posegraph import GraphNav, is_graph_state

        rn = nav.robots.get(robot)
        if is_graph_state(snap) != isinstance(rn, GraphNav):
            rn = None
        if rn is None:
            graph = is_graph_state(snap)
            rn = nav.robots[robot] = GraphNav(robot, nav.cfg, nav.graph_cfg) if graph else RobotNav(robot, nav.cfg)
        if isinstance(rn, GraphNav):
            rn.restore(snap, solve=False)  # read for the frame only: the worker runs the graph
            if self.pool is not None:
                self.pool.holding(robot, bool(rn.hold.clouds))
        else:
            rn.restore(snap)
        if nav.origin_ne is None and rn.started:
            nav.origin_ne = (float(rn.start_ne[0]), float(rn.start_ne[1]))
        self._frame = nav.frame()

    def mapped(self, robot: str) -> int:
        """Clouds of ``robot`` that reached the map."""
        with self._count_lock:
            return self._mapped.get(robot, 0)

    def _nav_publish(self, est: NavEstimate) -> None:
        with self._nav_lock:
            self._nav_latest[est.robot] = est
            last = self._nav_published.get(est.robot)
            due = last is None or not 0 <= est.t_ns - last < self.nav_publish_s * 1e9
            if due:
                self._nav_published[est.robot] = est.t_ns
        publish = self._publish_nav
        if not due or publish is None:
            return
        try:
            publish(est.robot, json.dumps(est.to_json(), default=json_default))
        except Exception as err:
            log.debug("nav of %s not published: %s", est.robot, err)

    def _publish_changes(self, msg: CloudMsg | None, changes: list[MapChange]) -> None:
        if not changes:
            return
        self._planes_stale = True
        publish = self._publish
        if publish is None:
            return
        planes = [change_json(c) for c in changes]
        if self.navigator is not None:
            planes = [self._frame.plane_json(p) for p in planes]
        update: dict[str, Any] = {"t_ns": time.time_ns(), "planes": planes}
        if msg is not None:
            update.update(t_ns=msg.t_ns, robot=msg.robot, seq=msg.seq)
        try:
            publish(json.dumps(update, default=json_default))
        except Exception as err:
            log.debug("map update not published: %s", err)

    # ------------------------------------------------------------------ views
    def map_json(self) -> dict[str, Any]:
        """The whole map as JSON-ready data (``{"planes": [], "enabled": False}`` when the map is off)."""
        if self.builder is None:
            return {"planes": [], "enabled": False}
        data: dict[str, Any] = self.builder.map_json()
        if self.navigator is not None:
            frame = self._frame
            data["planes"] = [frame.plane_json(p) for p in data.get("planes", [])]
            data["nav_frame"] = frame.to_json()
        self._planes = len(data.get("planes", []))
        self._planes_stale = False
        out: dict[str, Any] = json.loads(json.dumps(data, default=json_default))
        return out

    def status_json(self) -> dict[str, Any]:
        """The ``map`` part of the status JSON."""
        if self.builder is not None and self._planes_stale:
            self._planes = self.builder.n_planes  # counted under the builder's lock, no JSON built
            self._planes_stale = False
        with self._count_lock:
            pending = sum(len(v) for v in self._pending.values())
        lat = self.map_latency.percentiles_ms()
        backlog = self._queue.qsize() + len(self._order)
        pool = self.pool.status_json() if self.pool is not None else None
        if pool is not None:
            pending = pool["in_flight"]  # sent to a worker (or waiting for one), not committed yet
        return (
            {
                "planes": self._planes,
                "enabled": self.builder is not None,
                "clouds": self.clouds,
                "skipped": self.skipped,
                "unplaced": self.unplaced,
                "queued": backlog,
                "backlog": backlog,
                "backlog_limit": self.queue_size,
                "pending": pending,
                "rate_skipped": self.builder.rate_skipped if self.builder is not None else 0,
                "latency_ms": {k: (None if v != v else round(v, 3)) for k, v in lat.items()},
                "workers": len(pool["workers"]) if pool is not None else 0,
                "errors": self.errors,
                "quiet_flushes": self.quiet.count,
                "order_forced": self._order.forced,
            }
            | ({"navigation": self.navigator is not None} if self.builder is not None else {})
            | ({"smoothing": self._smoothing_json()} if self.fleet is not None else {})
            | ({"worker_pool": pool} if pool is not None else {})
        )

    def _smoothing_json(self) -> dict[str, Any]:
        """The smoother's runs, the longest and last run's wall time (ms), the longest the map thread was held by
        one (``max_hold_ms``: the runs themselves go on a thread of their own), and the observations re-placed."""
        fleet = self.fleet
        if fleet is None:
            return {}
        runs = list(fleet.runs_s)
        holds = list(fleet.holds_s)
        return {
            "runs": len(runs),
            "last_ms": round(1e3 * runs[-1], 1) if runs else None,
            "max_ms": round(1e3 * max(runs), 1) if runs else None,
            "max_hold_ms": round(1e3 * max(holds), 1) if holds else None,
            "replaced": fleet.replaced,
        }

    # ------------------------------------------------------------------ navigation views
    def nav_json(self, robot: str) -> dict[str, Any] | None:
        """The latest corrected pose of ``robot`` (the ``<root>/<robot>/nav`` JSON), or None."""
        with self._nav_lock:
            est = self._nav_latest.get(robot)
        return est.to_json() if est is not None else None

    def nav_robots(self) -> list[str]:
        """Robots with a navigation estimate."""
        with self._nav_lock:
            return sorted(self._nav_latest)

    def nav_status(self, robot: str) -> dict[str, Any] | None:
        """What the status says of a robot's navigation: ``placed``/``unplaced`` clouds, the axes its scans
        constrain now, ``position`` (``constrained``, ``partly`` (one horizontal direction: ``degenerate`` then
        gives the free one's bearing, ``{"free_bearing_deg"}``, e.g. along one flat wall), ``unconstrained``,
        ``lost`` (no fix and too uncertain to trust its scans until the next fix), ``unknown``), the horizontal
        and heading standard deviations, how it moved (``motion``); for a robot whose clouds wait for its track's
        checks (``GraphConfig.hold_until_verified``), ``hold``: clouds ``held`` now, ``committed``, ``replaced``,
        ``dropped`` (never placed: no check vouched for them), the mean and largest wait ``lag_mean_s``,
        ``lag_max_s``; ``heading``: for a robot on its pose graph, what its absolute heading rests on (``fixes``,
        ``launch-walls``, ``compass``: :func:`mapping.graph_fleet.heading_source`), else None. None when navigation
        is off or the robot sent nothing yet."""
        with self._nav_lock:
            est = self._nav_latest.get(robot)
            counts = list(self._nav_counts.get(robot, [0, 0]))
        if self.navigator is None or est is None:
            return None
        js = est.to_json()
        # horizontal directions the scan pinned (an oblique wall pins one, though neither axis alone)
        n_axes = max(est.pinned, sum(1 for a in ("north", "east") if est.constrained.get(a)))
        position = "unknown" if est.pose is None else ("constrained", "partly", "unconstrained")[2 - n_axes]
        if est.motion == "lost":
            position = "lost"
        hold = self.navigator.hold_counts(robot)
        held = (
            {} if hold is None else {"hold": {k: round(v, 2) if isinstance(v, float) else v for k, v in hold.items()}}
        )
        return held | {
            "placed": counts[0],
            "unplaced": counts[1],
            "position": position,
            "constrained": js["constrained"],
            "unconstrained": js["unconstrained"],
            "north_m_std": js.get("north_m_std"),
            "east_m_std": js.get("east_m_std"),
            "yaw_deg_std": js.get("yaw_deg_std"),
            "motion": est.motion,
            "heading": js["heading"],
            "degenerate": js["degenerate"],
            "t_ns": est.t_ns,
        }
