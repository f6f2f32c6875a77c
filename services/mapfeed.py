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

The builder returns typed :class:`mapping.MapChange` values; they become JSON only at the wire, when the base
publishes (``<root>/map/updates``: :mod:`services.mapfeed_views` gives the form).

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

Layout: this module holds :class:`MapFeed` (the queue, its input and back-pressure, the counting and publication
of what reached the map, the navigation estimates served) and :func:`load_map_builder`, which finds out whether
the map can run on this install (Open3D lives behind the ``mapping`` import); :mod:`services.map_thread` the map
thread's work on each cloud (navigation, held clouds, settling at the end of a dive); :mod:`services.mapfeed_views`
the wire form of map changes, the status's ``map`` part and the latency statistics (:class:`LatencyStats`). The
names that moved there are still importable from here.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from . import map_thread, mapfeed_views
from .capture_order import CaptureOrder, QuietFlush
from .errors import MappingUnavailableError
from .map_thread import FLUSH, SILENT_CHECK_S
from .mapfeed_views import LatencyStats, change_json, json_default
from .posetrack import has_fix
from .wire import CloudMsg

if TYPE_CHECKING:
    from mapping import MapBuilder, MapChange
    from mapping.navigation import NavEstimate, NavFrame, Navigator
    from mapping.smoother import FleetPlacements

    from .map_workers import WorkerPool

log = logging.getLogger(__name__)

__all__ = [
    "CLOSE_TIMEOUT_S",
    "NAV_PUBLISH_S",
    "SILENT_CHECK_S",
    "LatencyStats",
    "MapFeed",
    "change_json",
    "json_default",
    "load_map_builder",
]

#: How long :meth:`MapFeed.close` waits for the map thread to finish its queue, seconds.
CLOSE_TIMEOUT_S = 60.0
#: Publish a robot's corrected pose at most this often (seconds of capture time).
NAV_PUBLISH_S = 0.2


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
        self._queue.put(FLUSH)
        self._queue.join()
        if self.pool is not None:
            self.pool.flush(CLOSE_TIMEOUT_S)

    # ------------------------------------------------------------------ the map thread
    def _worker(self) -> None:
        """The one thread that feeds the map (:func:`services.map_thread.run`)."""
        map_thread.run(self)

    def _map_one(self, msg: CloudMsg) -> bool:
        """Place one cloud; True when plane workers will commit (and acknowledge) it later
        (:func:`services.map_thread.map_one`)."""
        return map_thread.map_one(self, msg)

    def _settle_silent(self) -> None:
        """Settle the held clouds of robots silent for ``IDLE_FLUSH_S`` (:func:`services.map_thread.settle_silent`)."""
        map_thread.settle_silent(self)

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
        """The whole map as JSON-ready data (``{"planes": [], "enabled": False}`` when the map is off;
        :func:`services.mapfeed_views.map_json`)."""
        return mapfeed_views.map_json(self)

    def status_json(self) -> dict[str, Any]:
        """The ``map`` part of the status JSON (:func:`services.mapfeed_views.status_json`)."""
        return mapfeed_views.status_json(self)

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
        """What the status says of a robot's navigation (:func:`services.mapfeed_views.nav_status`), or None when
        navigation is off or the robot sent nothing yet."""
        return mapfeed_views.nav_status(self, robot)
