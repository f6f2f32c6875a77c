"""The base station: ingests every robot's clouds, follows the fleet, serves calibrations, status and map.

This module is the Zenoh wiring; the two parts it composes each have their own module:

* :mod:`services.ledger`: the robot records, the state file and the acknowledgement protocol;
* :mod:`services.mapfeed`: the map queue, the one map thread (:mod:`services.map_thread`) and the publication of
  map changes (:mod:`services.mapfeed_views`).

Data path: the Zenoh subscriber callback only enqueues ``(key, payload, receive time)`` into a bounded queue
(blocking when full, which pushes back on the BLOCK publishers instead of dropping); ingest worker threads
decode and validate each cloud of either schema (a payload that fails is counted as rejected, never
raised), triangulate a compact schema-2 cloud (:class:`~services.wire.StripeMsg`) with the calibration it was
measured with (:mod:`services.calibbook`: refused and left in the robot's outbox when the base holds no
calibration of its fingerprint), have the ledger de-duplicate and count it, and hand it to the map feed, which
transforms its points to NED for ``mapping.MapBuilder``. Map changes are published on ``<root>/map/updates``.
The callbacks stay cheap: nothing in them decodes a cloud or touches the disk.

Served (queryables, each on its own key; a failure is answered with ``reply_err``):

* ``<root>/base/status``: JSON ``{"robots": {r: {"received", "rejected", "missed", "duplicates", "alive",
  "last_seq", "range_noise_per_m", ...}}, "map": {"planes": n}}`` (``?robot=R`` narrows it to one robot;
  ``range_noise_per_m``: the k in 1/m of the robot's last cloud the base's own map took, :mod:`mapping.range_noise`);
* ``<root>/base/calib/<robot>``: the fleet calibration stored in ``<state>/calib/<robot>.json`` (CalibMsg,
  or the JSON file with ``?format=json``);
* ``<root>/base/acks/<robot>``: JSON ``{"robot", "ranges": [[lo, hi], ...]}`` of the sequence numbers held
  durably (counters and map saved: see :meth:`BaseStation.checkpoint`);
* ``<root>/map``: the whole map as JSON;
* ``<root>/<robot>/nav``: the robot's latest corrected pose as JSON (``<root>/*/nav``: every robot's), also
  published as it updates (see :mod:`services.mapfeed`, navigation).

State (``--state DIR``, written atomically): ``fleet.json`` (sequence ranges and counters per robot, so that
``received`` survives restarts), ``calib/<robot>.json`` (fleet calibrations), ``map/`` (the map's own files).
"""

from __future__ import annotations

import json
import logging
import queue
import tempfile
import threading
import time
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.errors import LrsensorError
from lrsensor.range_theory import range_error_per_px

from .calibbook import CalibrationBook
from .errors import ServiceError, WireError
from .keys import FleetKeys
from .ledger import MAX_TRACK_POINTS, STATE_FORMAT, STATE_VERSION, UNKNOWN_SENDER, Ledger, RobotRecord
from .mapfeed import LatencyStats, MapFeed, load_map_builder
from .wire import ENCODING, CalibMsg, StatusMsg, StripeMsg, decode_cloud
from .zconfig import undeclare_all

__all__ = [
    "MAX_TRACK_POINTS",
    "STATE_FORMAT",
    "STATE_VERSION",
    "UNKNOWN_SENDER",
    "BaseStation",
    "LatencyStats",
    "RobotRecord",
    "load_map_builder",
]

log = logging.getLogger(__name__)

#: How long the base waits for a robot to answer its calibration query (compact clouds), seconds.
CALIB_FETCH_TIMEOUT_S = 2.0
#: How long :meth:`BaseStation.close` waits for the queued clouds, then for each ingest thread, seconds.
CLOSE_DRAIN_S = 10.0
CLOSE_JOIN_S = 5.0


class BaseStation:
    """The base station's services on an open Zenoh session (the caller owns and closes the session).

    Args:
        session: an open Zenoh session (a router in the default deployment).
        keys: the fleet's key expressions.
        state_dir: where counters, calibrations and the map persist (None: in memory only).
        map_mode: ``"auto"``, ``"on"`` or ``"off"`` (see :func:`~services.mapfeed.load_map_builder`).
        robots: if given, the only robots accepted; clouds of others are rejected and counted.
        workers: decode/map worker threads.
        queue_size: ingest queue capacity (clouds); a full queue blocks the Zenoh callback (back-pressure).
        save_period_s: how often changed counters are written to ``state_dir``.
        map_wait_s: how long an ingest worker waits for room in the map queue (back-pressure) before the
            cloud is counted as received but left out of the map (``map.skipped`` in the status).
        ack_period_s: how often a checkpoint (map and counters saved) acknowledges what arrived.
        navigation: correct each robot's pose from its scans before its clouds go into the map
            (``mapping.navigation``; needs the map). Off: the raw poses are trusted.
        map_workers: plane-worker processes to start on this machine (0: the map thread extracts in this
            process, unless ``remote_workers``); they connect to ``worker_endpoint`` (see docs/scaling.md).
        worker_endpoint: where local workers connect (the router's TCP endpoint, e.g. ``tcp/127.0.0.1:7447``).
        remote_workers: send the per-robot work to plane workers (of any machine) even when none is started
            here (:mod:`services.map_workers`); implied by ``map_workers`` > 0.
        no_fix: with navigation, what becomes of a robot without a horizontal fix after its launch (``--no-fix``):
            ``graph`` (its gated pose graph, :data:`mapping.graph_config.TRACKED`, with the graphs' launch frame;
            needs GTSAM) or ``lost`` (reported lost, its clouds unplaced), in the map thread and in the plane
            workers alike (:func:`services.map_worker_nav.no_fix_config`; docs/navigation.md, "Choosing
            ``--no-fix``"). None (the default): ``graph``, or ``lost`` with a warning where GTSAM is missing
            (:func:`services.map_worker_nav.resolve_no_fix`); the choice made is :attr:`no_fix`.
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        state_dir: str | Path | None = None,
        *,
        map_mode: str = "auto",
        robots: Iterable[str] | None = None,
        workers: int = 2,
        queue_size: int = 1024,
        save_period_s: float = 1.0,
        ack_period_s: float = 2.0,
        map_wait_s: float = 5.0,
        navigation: bool = True,
        map_workers: int = 0,
        worker_endpoint: str | None = None,
        remote_workers: bool = False,
        no_fix: str | None = None,
    ) -> None:
        from .map_worker_nav import resolve_no_fix

        self.no_fix = resolve_no_fix(no_fix, navigated=False)  # the value checked first; GTSAM once the map is known
        self.session = session
        self.keys = keys
        self.state_dir = Path(state_dir) if state_dir is not None else None
        self.allowed = frozenset(robots) if robots is not None else None
        self.n_workers = max(1, workers)
        self.processed = 0
        self._latency = LatencyStats()
        #: latency figures left out because they were negative (a robot's clock ahead, its offset not yet known)
        self.clock_suspect = 0
        self._lock = threading.Lock()
        # One queue per ingest thread, a robot's clouds always to the same one (by its key): they reach the map in
        # the order they arrived, so a robot's windows (and, with plane workers, the map) do not depend on which
        # thread was quicker.
        self._queues: list[queue.Queue[tuple[str, bytes, int] | None]] = [
            queue.Queue(maxsize=max(1, queue_size // self.n_workers)) for _ in range(self.n_workers)
        ]
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []
        self._entities: list[Any] = []
        map_dir = (self.state_dir / "map") if self.state_dir is not None else Path(tempfile.mkdtemp(prefix="lrs-map-"))
        self.map = load_map_builder(map_dir, map_mode)
        self.ledger = Ledger(
            self.state_dir,
            save_map=self.map.save if self.map is not None else None,
            save_period_s=save_period_s,
            ack_period_s=ack_period_s,
        )
        self.feed = MapFeed(
            self.map, self.ledger.mark_mapped, queue_size=queue_size, map_wait_s=map_wait_s, navigation=navigation
        )
        self.no_fix = resolve_no_fix(no_fix, navigated=self.feed.navigator is not None)
        self.calibrations = CalibrationBook(self.ledger.calibration_path, self._fetch_robot_calibration)
        self.n_map_workers = max(0, map_workers)
        self.worker_endpoint = worker_endpoint
        self.use_workers = self.map is not None and (self.n_map_workers > 0 or remote_workers)
        if self.use_workers and self.n_map_workers > 0 and worker_endpoint is None:
            msg = "map workers need the endpoint they connect to (worker_endpoint, a tcp/ listen endpoint)"
            raise ServiceError(msg)
        self._worker_procs: list[Any] = []

    def _apply_no_fix(self) -> None:
        """The ``no_fix`` choice on the feed's navigator (after ``--nav filter`` or the plane workers chose its
        configuration): its graphs' configuration, and the launch frame from the graphs' launches."""
        nav = self.feed.navigator
        if nav is None:
            return
        from .map_worker_nav import no_fix_config

        nav.cfg, nav.graph_cfg = no_fix_config(nav.cfg, self.no_fix)

    # ------------------------------------------------------------------ the parts, by their old names
    @property
    def records(self) -> dict[str, RobotRecord]:
        """Robot name -> what the base station knows of it (see :class:`~services.ledger.RobotRecord`)."""
        return self.ledger.records

    @property
    def membership_events(self) -> list[tuple[str, str, int]]:
        """``(robot, "joined" or "left", t_ns)`` in the order liveliness reported them."""
        return self.ledger.membership_events

    @property
    def latency(self) -> LatencyStats:
        """Capture-to-base latencies and publication-to-base transit times of the recent clouds, on the base
        station's clock (a robot whose clock is off has its times shifted by its measured offset)."""
        return self._latency

    def _record(self, robot: str) -> RobotRecord:
        return self.ledger.record(robot)

    def checkpoint(self, save_map: bool = True) -> None:
        """Make what was received durable and acknowledge it (see :meth:`services.ledger.Ledger.checkpoint`)."""
        self.ledger.checkpoint(save_map)

    def save_state(self, acked: dict[str, list[list[int]]] | None = None) -> None:
        """Write the counters to ``<state>/fleet.json`` (see :meth:`services.ledger.Ledger.save_state`)."""
        self.ledger.save_state(acked)

    def calibration_path(self, robot: str) -> Path | None:
        """Where the fleet calibration of ``robot`` is stored."""
        return self.ledger.calibration_path(robot)

    def store_calibration(self, robot: str, calibration: Calibration) -> None:
        """Store a robot's fleet calibration (served on ``<root>/base/calib/<robot>``)."""
        self.ledger.store_calibration(robot, calibration)

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> BaseStation:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def start(self) -> None:
        """Declare the subscribers and queryables and start the worker threads."""
        import zenoh

        s = self.session
        for i in range(self.n_workers):
            t = threading.Thread(target=self._worker, args=(self._queues[i],), name=f"base-ingest-{i}", daemon=True)
            t.start()
            self._threads.append(t)
        map_pub = s.declare_publisher(
            self.keys.map_updates,
            encoding=zenoh.Encoding("application/json"),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        if self.use_workers:
            from .map_worker_procs import start_local_workers
            from .map_workers import WorkerPool

            assert self.map is not None
            pool = WorkerPool(s, self.keys, self.map, lambda robot, done, unplaced: None, lambda changes: None)
            self.feed.use_workers(pool)
            pool.no_fix = self.no_fix
            pool.start()
            if self.n_map_workers and self.worker_endpoint is not None:
                self._worker_procs = start_local_workers(self.n_map_workers, self.keys, self.worker_endpoint)
        self._apply_no_fix()
        self.feed.start(map_pub.put, self._publish_nav)
        saver = threading.Thread(target=self.ledger.run_saver, args=(self._closing,), name="base-saver", daemon=True)
        saver.start()
        self._threads.append(saver)
        self._entities += [
            map_pub,
            s.declare_subscriber(self.keys.all_clouds, self._on_cloud),
            s.declare_subscriber(self.keys.all_rov_status, self._on_rov_status),
            s.liveliness().declare_subscriber(self.keys.all_alive, self._on_alive, history=True),
            s.declare_queryable(self.keys.base_status, self._on_status_query),
            s.declare_queryable(self.keys.base_calib_all, self._on_calib_query),
            s.declare_queryable(self.keys.base_acks_all, self._on_acks_query),
            s.declare_queryable(self.keys.map, self._on_map_query),
            s.declare_queryable(self.keys.all_nav, self._on_nav_query),
        ]
        log.info("base station of fleet %r up: subscribed to %s", self.keys.fleet, self.keys.all_clouds)

    def drain(self, timeout_s: float = 10.0) -> bool:
        """Wait until every queued cloud has been processed; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(q.unfinished_tasks == 0 for q in self._queues) and self.feed.idle():
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        """Undeclare everything, finish the queued clouds, flush and save map and counters."""
        undeclare_all(reversed(self._entities), "base station")
        self._entities.clear()
        self.drain(timeout_s=CLOSE_DRAIN_S)
        self._closing.set()
        for q in self._queues:
            q.put(None)
        for t in self._threads:
            t.join(timeout=CLOSE_JOIN_S)
        self._threads.clear()
        self.feed.close(save=self.state_dir is not None)
        if self._worker_procs:
            from .map_worker_procs import stop_local_workers

            stop_local_workers(self._worker_procs)
            self._worker_procs = []
        self.checkpoint(save_map=False)

    # ------------------------------------------------------------------ callbacks (cheap, never block long)
    def _on_cloud(self, sample: Any) -> None:
        key = str(sample.key_expr)
        item = (key, sample.payload.to_bytes(), time.time_ns())
        q = self._queues[zlib.crc32(key.encode()) % len(self._queues)]
        while not self._closing.is_set():
            try:
                q.put(item, timeout=0.5)
                return
            except queue.Full:
                continue

    def _on_rov_status(self, sample: Any) -> None:
        recv_ns = time.time_ns()
        robot = self.keys.robot_of(str(sample.key_expr))
        try:
            msg = StatusMsg.from_bytes(sample.payload.to_bytes())
        except WireError as err:
            self.ledger.reject(robot or UNKNOWN_SENDER, f"status: {err}")
            return
        if robot is None or msg.robot != robot:
            self.ledger.reject(robot or UNKNOWN_SENDER, f"status of {msg.robot!r} published under {sample.key_expr}")
            return
        self.ledger.set_reported(robot, msg, recv_ns)

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        robot = self.keys.robot_of(str(sample.key_expr))
        if robot is None:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        self.ledger.set_alive(robot, alive, time.time_ns())
        log.info("robot %s %s", robot, "joined" if alive else "left")

    def _on_status_query(self, query: Any) -> None:
        try:
            only = query.parameters.get("robot") if query.parameters is not None else None
            status = self.status(only)
            query.reply(query.key_expr, json.dumps(status), encoding="application/json")
        except Exception as err:
            log.warning("status query failed: %s", err)

    def _on_acks_query(self, query: Any) -> None:
        robot = self.keys.robot_of_base_key(str(query.key_expr), "acks")
        try:
            if robot is None:
                query.reply_err(f"no such robot key: {query.key_expr}")
                return
            self.ledger.ack_now(robot)
            query.reply(query.key_expr, json.dumps(self.ledger.acks_json(robot)), encoding="application/json")
        except Exception as err:
            log.warning("acks query failed: %s", err)

    def _on_calib_query(self, query: Any) -> None:
        key = str(query.key_expr)
        robot = self.keys.robot_of_base_key(key, "calib")
        try:
            if robot is None:
                query.reply_err(f"not a robot's calibration key: {key}")
                return
            path = self.calibration_path(robot)
            if path is None or not path.is_file():
                query.reply_err(f"no calibration stored for robot {robot!r}")
                return
            try:
                calib = Calibration.load(path)
            except LrsensorError as err:
                query.reply_err(f"stored calibration of {robot!r} is invalid: {err}")
                return
            fmt = query.parameters.get("format") if query.parameters is not None else None
            if fmt == "json":
                query.reply(key, calib.to_json(), encoding="application/json")
            else:
                query.reply(key, CalibMsg(robot, calib).to_bytes(), encoding=ENCODING)
        except Exception as err:
            log.warning("calibration query %s failed: %s", key, err)

    def _on_map_query(self, query: Any) -> None:
        try:
            query.reply(query.key_expr, json.dumps(self.map_json()), encoding="application/json")
        except Exception as err:
            log.warning("map query failed: %s", err)

    def _publish_nav(self, robot: str, payload: str) -> None:
        self.session.put(self.keys.nav(robot), payload, encoding="application/json")

    def _on_nav_query(self, query: Any) -> None:
        try:
            robot = self.keys.robot_of(str(query.key_expr))
            robots = [robot] if robot is not None else self.feed.nav_robots()
            answered = False
            for r in robots:
                js = self.feed.nav_json(r)
                if js is not None:
                    query.reply(self.keys.nav(r), json.dumps(js), encoding="application/json")
                    answered = True
            if not answered:
                why = "navigation is off" if not self.feed.navigation else "no navigation estimate yet"
                query.reply_err(f"{why}: {query.key_expr}")
        except Exception as err:
            log.warning("nav query failed: %s", err)

    # ------------------------------------------------------------------ the ingest loop
    def _worker(self, q: queue.Queue[tuple[str, bytes, int] | None]) -> None:
        while True:
            item = q.get()
            try:
                if item is None:
                    return
                self._ingest(*item)
            except Exception as err:
                log.exception("ingest failed: %s", err)
            finally:
                q.task_done()

    def _ingest(self, key: str, payload: bytes, recv_ns: int) -> None:
        robot = self.keys.robot_of(key)
        if robot is None:
            self.ledger.reject(UNKNOWN_SENDER, f"cloud on a key that names no robot: {key}")
            return
        try:
            any_msg = decode_cloud(payload)
        except WireError as err:
            self.ledger.reject(robot, str(err))
            return
        if any_msg.robot != robot:
            self.ledger.reject(robot, f"cloud of robot {any_msg.robot!r} published under {key}")
            return
        if self.allowed is not None and robot not in self.allowed:
            self.ledger.reject(robot, f"robot {robot!r} is not a member of fleet {self.keys.fleet!r}")
            return
        if isinstance(any_msg, StripeMsg):
            calib, reason = self.calibrations.lookup(robot, any_msg.calib_id)
            if calib is None:  # not acknowledged: the robot's outbox keeps it and offers it again
                self.ledger.reject(robot, reason)
                return
            try:
                msg = any_msg.to_cloud(calib)
            except WireError as err:
                self.ledger.reject(robot, str(err))
                return
            per_px = range_error_per_px(calib)  # the map's range noise of this cloud (mapping.range_noise)
        else:
            msg, per_px = any_msg, 0.0  # schema 1: which calibration measured it is not known
        if not self.ledger.accept(msg):
            return  # a duplicate, counted
        self.feed.take(msg, recv_ns, per_px)
        self._time(msg, recv_ns)
        with self._lock:
            self.processed += 1

    def _time(self, msg: Any, recv_ns: int) -> None:
        """Note the cloud's latency and transit on the base station's clock (docs/reliability.md, "A robot whose
        clock is off"): the robot's times shifted by its measured clock offset when it is beyond
        :data:`~services.ledger.CLOCK_OFFSET_MIN_S`; a figure still negative (clocks a second or so apart) is
        impossible, left out and counted."""
        shift = self.ledger.clock_correction_ns(msg.robot, recv_ns - msg.sent_ns if msg.sent_ns else None)
        latency = time.time_ns() - (msg.t_ns - shift)
        transit = recv_ns - (msg.sent_ns - shift) if msg.sent_ns else None
        if latency < 0 or (transit is not None and transit < 0):
            with self._lock:
                self.clock_suspect += 1
            return
        self._latency.add(latency, transit)

    def _fetch_robot_calibration(self, robot: str) -> Calibration | None:
        """The calibration ``robot`` serves on ``<root>/<robot>/calib`` (None: no valid answer in time)."""
        for reply in self.session.get(self.keys.calib(robot), timeout=CALIB_FETCH_TIMEOUT_S):
            if reply.ok is None:
                continue
            try:
                msg = CalibMsg.from_bytes(reply.ok.payload.to_bytes())
            except WireError as err:
                log.warning("calibration answer of %s refused: %s", robot, err)
                continue
            if msg.robot == robot:
                return msg.calibration
        return None

    # ------------------------------------------------------------------ views
    def map_json(self) -> dict[str, Any]:
        """The whole map as JSON-ready data (``{"planes": []}`` when the map is off)."""
        return self.feed.map_json()

    def flush_map(self, timeout_s: float = 60.0) -> None:
        """Process every queued cloud and let the map extract what it still holds (end of a dive)."""
        if not self.feed.enabled:
            return
        self.drain(timeout_s)
        self.feed.flush()

    def status(self, robot: str | None = None) -> dict[str, Any]:
        """The status JSON (one robot only when ``robot`` is given)."""
        map_status = self.feed.status_json()
        lat = self.latency.percentiles_ms()
        transit = self.latency.percentiles_ms(transit=True)
        robots = self.ledger.robots_json(robot)
        for name, rec in robots.items():
            if self.feed.enabled:
                rec["mapped"] = self.feed.mapped(name)  # clouds whose planes reached the map
            if self.map is not None and not self.use_workers:
                rec["range_noise_per_m"] = self.map.range_noise(name)  # k of its last mapped cloud (0: none known)
            nav = self.feed.nav_status(name)
            if nav is not None:
                rec["nav"] = nav
                rec["unplaced"] = nav["unplaced"]  # with navigation: clouds it could not place yet
        return {
            "fleet": self.keys.fleet,
            "t_ns": time.time_ns(),
            "robots": robots,
            "map": map_status,
            "ingest": {
                "processed": self.processed,
                "queued": sum(q.qsize() for q in self._queues),
                "latency_ms": {k: (None if v != v else round(v, 3)) for k, v in lat.items()},
                "transit_ms": {k: (None if v != v else round(v, 3)) for k, v in transit.items()},
                "clock_suspect": self.clock_suspect,
            },
        }

    def tracks(self) -> dict[str, np.ndarray]:
        """Per robot, the poses of its accepted clouds: (M, 4) ``t_ns, north_m, east_m, down_m``."""
        return self.ledger.tracks()
