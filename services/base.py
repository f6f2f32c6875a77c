"""The base station: ingests every robot's clouds, follows the fleet, serves calibrations, status and map.

Data path: the Zenoh subscriber callback only enqueues ``(key, payload, receive time)`` into a bounded queue
(blocking when full, which pushes back on the BLOCK publishers instead of dropping); worker threads decode
and validate each :class:`~services.wire.CloudMsg`, de-duplicate it by sequence number, count it, transform
its points to NED and hand them to ``mapping.MapBuilder``. Map changes are published on
``<root>/map/updates``.

Served (queryables):

* ``<root>/base/status``: JSON ``{"robots": {r: {"received", "rejected", "missed", "duplicates", "alive",
  "last_seq", ...}}, "map": {"planes": n}}`` (``?robot=R`` narrows it to one robot);
* ``<root>/base/calib/<robot>``: the fleet calibration stored in ``<state>/calib/<robot>.json`` (CalibMsg,
  or the JSON file with ``?format=json``);
* ``<root>/base/acks/<robot>``: JSON ``{"robot", "ranges": [[lo, hi], ...]}`` of the sequence numbers held
  durably (counters and map saved: see :meth:`BaseStation.checkpoint`);
* ``<root>/map``: the whole map as JSON.

State (``--state DIR``, written atomically): ``fleet.json`` (sequence ranges and counters per robot, so that
``received`` survives restarts), ``calib/<robot>.json`` (fleet calibrations), ``map/`` (the map's own files).
"""

from __future__ import annotations

import collections
import json
import logging
import queue
import tempfile
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lrsensor.atomic import atomic_write
from lrsensor.calibration import Calibration
from lrsensor.errors import LrsensorError
from lrsensor.frames import body_to_ned

from .errors import MappingUnavailableError, ServiceError, WireError
from .keys import FleetKeys
from .seqset import SeqSet
from .wire import ENCODING, CalibMsg, CloudMsg, StatusMsg

log = logging.getLogger(__name__)

STATE_FORMAT = "lrsensor-base-state"
STATE_VERSION = 1
#: Robot name under which payloads on keys that name no valid robot are counted.
UNKNOWN_SENDER = "?"
#: Poses kept per robot for the track plot.
MAX_TRACK_POINTS = 20_000


@dataclass
class RobotRecord:
    """What the base station knows of one robot."""

    seqs: SeqSet = field(default_factory=SeqSet)
    #: clouds the map has taken in (or that had nothing for it); with the map saved after, they are durable
    mapped: SeqSet = field(default_factory=SeqSet)
    #: the sequence ranges persisted in ``--state`` (counters and map): what the base acknowledges
    acked: list[list[int]] = field(default_factory=list)
    rejected: int = 0
    duplicates: int = 0
    points: int = 0
    alive: bool = False
    joined_ns: int = 0
    left_ns: int = 0
    last_t_ns: int = 0
    reported: StatusMsg | None = None
    rejected_reasons: collections.Counter[str] = field(default_factory=collections.Counter)
    track: list[tuple[int, float, float, float]] = field(default_factory=list)

    def to_json(self) -> dict[str, Any]:
        """The robot's entry in the status JSON."""
        out: dict[str, Any] = {
            "received": len(self.seqs),
            "rejected": self.rejected,
            "missed": self.seqs.missed(),
            "duplicates": self.duplicates,
            "alive": self.alive,
            "last_seq": self.seqs.highest,
            "acked": sum(hi - lo + 1 for lo, hi in self.acked),
            "last_t_ns": self.last_t_ns,
            "points": self.points,
        }
        if self.rejected_reasons:
            out["rejected_reasons"] = dict(self.rejected_reasons.most_common(8))
        if self.reported is not None:
            out["reported"] = self.reported.to_json_dict()
        return out


class LatencyStats:
    """End-to-end latencies (base processing time minus capture time), ns, of the most recent clouds."""

    def __init__(self, maxlen: int = 200_000) -> None:
        self.values: collections.deque[int] = collections.deque(maxlen=maxlen)
        self.transit: collections.deque[int] = collections.deque(maxlen=maxlen)

    def add(self, latency_ns: int, transit_ns: int | None) -> None:
        """Record one cloud."""
        self.values.append(latency_ns)
        if transit_ns is not None:
            self.transit.append(transit_ns)

    def percentiles_ms(self, qs: Iterable[float] = (50, 99), transit: bool = False) -> dict[str, float]:
        """Percentiles in ms (NaN when empty) of the end-to-end latencies, or with ``transit`` of the
        publication-to-base times (meaningful also when a recorded dive with old capture times is replayed)."""
        arr = np.asarray(self.transit if transit else self.values, dtype=float)
        return {f"p{q:g}": float(np.percentile(arr, q) / 1e6) if arr.size else float("nan") for q in qs}


def load_map_builder(map_dir: Path, mode: str) -> Any | None:
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


class BaseStation:
    """The base station's services on an open Zenoh session (the caller owns and closes the session).

    Args:
        session: an open Zenoh session (a router in the default deployment).
        keys: the fleet's key expressions.
        state_dir: where counters, calibrations and the map persist (None: in memory only).
        map_mode: ``"auto"``, ``"on"`` or ``"off"`` (see :func:`load_map_builder`).
        robots: if given, the only robots accepted; clouds of others are rejected and counted.
        workers: decode/map worker threads.
        queue_size: ingest queue capacity (clouds); a full queue blocks the Zenoh callback (back-pressure).
        save_period_s: how often changed counters are written to ``state_dir``.
        map_wait_s: how long an ingest worker waits for room in the map queue (back-pressure) before the
            cloud is counted as received but left out of the map (``map.skipped`` in the status).
        ack_period_s: how often a checkpoint (map and counters saved) acknowledges what arrived.
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
    ) -> None:
        self.session = session
        self.keys = keys
        self.state_dir = Path(state_dir) if state_dir is not None else None
        self.allowed = frozenset(robots) if robots is not None else None
        self.n_workers = max(1, workers)
        self.save_period_s = save_period_s
        self.ack_period_s = ack_period_s
        self._last_ack_save = 0.0
        self._save_lock = threading.Lock()
        self.records: dict[str, RobotRecord] = {}
        self.latency = LatencyStats()
        self.processed = 0
        self.map_errors = 0
        self.map_clouds = 0
        self.map_skipped = 0
        self.map_wait_s = map_wait_s
        self._lock = threading.RLock()
        self._queue: queue.Queue[tuple[str, bytes, int] | None] = queue.Queue(maxsize=queue_size)
        self._map_queue: queue.Queue[CloudMsg | None] = queue.Queue(maxsize=queue_size)
        self._closing = threading.Event()
        self._dirty = False
        self._threads: list[threading.Thread] = []
        self._entities: list[Any] = []
        self._map_planes = 0
        self._map_dirty = True
        self.membership_events: list[tuple[str, str, int]] = []
        self._load_state()
        map_dir = (self.state_dir / "map") if self.state_dir is not None else Path(tempfile.mkdtemp(prefix="lrs-map-"))
        self.map = load_map_builder(map_dir, map_mode)
        self._map_pub: Any = None
        self._map_thread: threading.Thread | None = None

    # ------------------------------------------------------------------ state
    @property
    def _state_file(self) -> Path | None:
        return self.state_dir / "fleet.json" if self.state_dir is not None else None

    def _load_state(self) -> None:
        path = self._state_file
        if path is None or not path.exists():
            return
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            if data.get("format") != STATE_FORMAT or data.get("version") != STATE_VERSION:
                msg = f"{path}: not a base-station state file of version {STATE_VERSION}"
                raise ServiceError(msg)
            for robot, rec in data["robots"].items():
                # Only what was acknowledged is known to be in the saved map too: the rest is taken again
                # from the robots' outboxes (they keep every cloud until it is acknowledged).
                acked = rec.get("acked", rec.get("ranges", []))
                self.records[robot] = RobotRecord(
                    seqs=SeqSet(acked),
                    mapped=SeqSet(acked),
                    acked=SeqSet(acked).ranges(),
                    rejected=int(rec.get("rejected", 0)),
                    duplicates=int(rec.get("duplicates", 0)),
                    points=int(rec.get("points", 0)),
                    last_t_ns=int(rec.get("last_t_ns", 0)),
                )
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as err:
            msg = f"{path}: cannot read the base station's state: {err}"
            raise ServiceError(msg) from err
        log.info("state reloaded from %s: %d robots", path, len(self.records))

    def checkpoint(self, save_map: bool = True) -> None:
        """Make what was received durable and acknowledge it (issue 7: nothing acknowledged is ever lost).

        The clouds the map has taken in are noted first, then the map is saved, then the counters with
        those ranges as ``acked``; only after that are they served on ``<root>/base/acks/<robot>``, so a
        robot forgets a cloud only once both the counters and the map hold it on disk. Without the map
        the received ranges are acknowledged as soon as the counters are written.
        """
        with self._lock:
            if self.map is not None:
                acked = {r: rec.mapped.ranges() for r, rec in self.records.items()}
            else:
                acked = {r: rec.seqs.ranges() for r, rec in self.records.items()}
        if self.state_dir is None:
            with self._lock:
                for r, ranges in acked.items():
                    self.records[r].acked = ranges
            return
        if self.map is not None and save_map:
            self.map.save()
        self.save_state(acked)

    def save_state(self, acked: dict[str, list[list[int]]] | None = None) -> None:
        """Write the counters to ``<state>/fleet.json`` atomically (no-op without a state folder).

        ``acked``: per robot, ranges now durable (see :meth:`checkpoint`); they are acknowledged once the
        file is written. Robots not in it keep their previous acknowledgement.
        """
        path = self._state_file
        if path is None:
            return
        with self._save_lock:  # snapshot, write and acknowledge in one order: the file never lags the acks
            self._save_state_locked(path, acked)

    def _save_state_locked(self, path: Path, acked: dict[str, list[list[int]]] | None) -> None:
        with self._lock:
            acked_now = {r: (acked[r] if acked and r in acked else rec.acked) for r, rec in self.records.items()}
            data = {
                "format": STATE_FORMAT,
                "version": STATE_VERSION,
                "saved_ns": time.time_ns(),
                "robots": {
                    r: {
                        "ranges": rec.seqs.ranges(),
                        "acked": acked_now[r],
                        "rejected": rec.rejected,
                        "duplicates": rec.duplicates,
                        "points": rec.points,
                        "last_t_ns": rec.last_t_ns,
                    }
                    for r, rec in self.records.items()
                },
            }
            self._dirty = False
        atomic_write(path, json.dumps(data))
        with self._lock:
            for r, ranges in acked_now.items():
                if r in self.records:
                    self.records[r].acked = ranges

    def calibration_path(self, robot: str) -> Path | None:
        """Where the fleet calibration of ``robot`` is stored."""
        return self.state_dir / "calib" / f"{robot}.json" if self.state_dir is not None else None

    def store_calibration(self, robot: str, calibration: Calibration) -> None:
        """Store a robot's fleet calibration (served on ``<root>/base/calib/<robot>``)."""
        path = self.calibration_path(robot)
        if path is None:
            msg = "the base station has no --state folder to store calibrations in"
            raise ServiceError(msg)
        calibration.save(path)

    def _record(self, robot: str) -> RobotRecord:
        rec = self.records.get(robot)
        if rec is None:
            rec = self.records[robot] = RobotRecord()
        return rec

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
            t = threading.Thread(target=self._worker, name=f"base-ingest-{i}", daemon=True)
            t.start()
            self._threads.append(t)
        if self.map is not None:
            self._map_thread = threading.Thread(target=self._map_worker, name="base-map", daemon=True)
            self._map_thread.start()
        saver = threading.Thread(target=self._saver, name="base-saver", daemon=True)
        saver.start()
        self._threads.append(saver)
        self._map_pub = s.declare_publisher(
            self.keys.map_updates,
            encoding=zenoh.Encoding("application/json"),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        self._entities += [
            self._map_pub,
            s.declare_subscriber(self.keys.all_clouds, self._on_cloud),
            s.declare_subscriber(self.keys.all_rov_status, self._on_rov_status),
            s.liveliness().declare_subscriber(self.keys.all_alive, self._on_alive, history=True),
            s.declare_queryable(self.keys.base_status, self._on_status_query),
            s.declare_queryable(self.keys.base_calib_all, self._on_calib_query),
            s.declare_queryable(self.keys.base_acks_all, self._on_acks_query),
            s.declare_queryable(self.keys.map, self._on_map_query),
        ]
        log.info("base station of fleet %r up: subscribed to %s", self.keys.fleet, self.keys.all_clouds)

    def drain(self, timeout_s: float = 10.0) -> bool:
        """Wait until every queued cloud has been processed; False on timeout."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._queue.unfinished_tasks == 0 and self._map_queue.unfinished_tasks == 0:
                return True
            time.sleep(0.01)
        return False

    def close(self) -> None:
        """Undeclare everything, finish the queued clouds, flush and save map and counters."""
        for e in reversed(self._entities):
            try:
                e.undeclare()
            except Exception as err:
                log.debug("undeclare failed: %s", err)
        self._entities.clear()
        self.drain(timeout_s=10.0)
        self._closing.set()
        for _ in range(self.n_workers):
            self._queue.put(None)
        for t in self._threads:
            t.join(timeout=5.0)
        self._threads.clear()
        if self._map_thread is not None:
            self._map_queue.put(None)
            self._map_thread.join(timeout=60.0)
            self._map_thread = None
        if self.map is not None:
            try:
                self.map.flush()
                if self.state_dir is not None:
                    self.map.save()
            except Exception as err:
                log.error("map flush/save failed: %s", err)
        self.checkpoint(save_map=False)

    # ------------------------------------------------------------------ callbacks (cheap, never block long)
    def _on_cloud(self, sample: Any) -> None:
        item = (str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())
        while not self._closing.is_set():
            try:
                self._queue.put(item, timeout=0.5)
                return
            except queue.Full:
                continue

    def _on_rov_status(self, sample: Any) -> None:
        robot = self.keys.robot_of(str(sample.key_expr))
        try:
            msg = StatusMsg.from_bytes(sample.payload.to_bytes())
        except WireError as err:
            self._reject(robot or UNKNOWN_SENDER, f"status: {err}")
            return
        if robot is None or msg.robot != robot:
            self._reject(robot or UNKNOWN_SENDER, f"status of {msg.robot!r} published under {sample.key_expr}")
            return
        with self._lock:
            self._record(robot).reported = msg

    def _on_alive(self, sample: Any) -> None:
        import zenoh

        robot = self.keys.robot_of(str(sample.key_expr))
        if robot is None:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        now = time.time_ns()
        with self._lock:
            rec = self._record(robot)
            rec.alive = alive
            if alive:
                rec.joined_ns = now
            else:
                rec.left_ns = now
            self.membership_events.append((robot, "joined" if alive else "left", now))
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
            self._ack_now(robot)
            with self._lock:
                rec = self.records.get(robot)
                body = {
                    "robot": robot,
                    # with --state: only what is durable (see checkpoint); without: nothing survives a
                    # restart anyway, so what arrived is acknowledged at once
                    "ranges": (rec.acked if self.state_dir is not None else rec.seqs.ranges()) if rec else [],
                    "received": len(rec.seqs) if rec else 0,
                }
            query.reply(query.key_expr, json.dumps(body), encoding="application/json")
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

    # ------------------------------------------------------------------ workers
    def _reject(self, robot: str, reason: str) -> None:
        with self._lock:
            rec = self._record(robot)
            rec.rejected += 1
            short = reason.split(":")[0] if len(reason) > 60 else reason
            rec.rejected_reasons[short[:60]] += 1
            n = rec.rejected
            self._dirty = True
        if n <= 5 or n % 100 == 0:
            log.warning("payload from %s rejected (%d so far): %s", robot, n, reason)

    def _worker(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                self._ingest(*item)
            except Exception as err:
                log.exception("ingest failed: %s", err)
            finally:
                self._queue.task_done()

    def _ingest(self, key: str, payload: bytes, recv_ns: int) -> None:
        robot = self.keys.robot_of(key)
        if robot is None:
            self._reject(UNKNOWN_SENDER, f"cloud on a key that names no robot: {key}")
            return
        try:
            msg = CloudMsg.from_bytes(payload)
        except WireError as err:
            self._reject(robot, str(err))
            return
        if msg.robot != robot:
            self._reject(robot, f"cloud of robot {msg.robot!r} published under {key}")
            return
        if self.allowed is not None and robot not in self.allowed:
            self._reject(robot, f"robot {robot!r} is not a member of fleet {self.keys.fleet!r}")
            return
        with self._lock:
            rec = self._record(robot)
            if not rec.seqs.add(msg.seq):
                rec.duplicates += 1
                return
            rec.points += len(msg)
            rec.last_t_ns = max(rec.last_t_ns, msg.t_ns)
            p = msg.pose
            if len(rec.track) < MAX_TRACK_POINTS:
                rec.track.append((msg.t_ns, p.north_m, p.east_m, p.down_m))
            self._dirty = True
        if self.map is not None and len(msg):
            try:
                # back-pressure while the map keeps up; a map stalled for map_wait_s loses the cloud (counted)
                self._map_queue.put(msg, timeout=self.map_wait_s)
            except queue.Full:
                self.map_skipped += 1
                with self._lock:  # counted, not silent; acknowledge it or the robot would re-send it forever
                    rec.mapped.add(msg.seq)
                if self.map_skipped <= 5 or self.map_skipped % 100 == 0:
                    log.warning(
                        "map is %.0f s behind: cloud %s#%d not mapped (%d so far)",
                        self.map_wait_s,
                        robot,
                        msg.seq,
                        self.map_skipped,
                    )
        else:
            with self._lock:
                rec.mapped.add(msg.seq)
        done = time.time_ns()
        with self._lock:
            self.processed += 1
            self.latency.add(done - msg.t_ns, recv_ns - msg.sent_ns if msg.sent_ns else None)

    def _map_worker(self) -> None:
        """The one thread that feeds the map (``MapBuilder.add_cloud`` is single-writer)."""
        while True:
            msg = self._map_queue.get()
            try:
                if msg is None:
                    return
                if msg is _FLUSH:
                    self._publish_changes(None, self.map.flush() if self.map is not None else [])
                    continue
                self._map_one(msg)
            except Exception as err:  # the map must never stop the ingest
                self.map_errors += 1
                log.exception("map update failed: %s", err)
            finally:
                if isinstance(msg, CloudMsg):  # taken in (or refused by the map): acknowledgeable
                    with self._lock:
                        self._record(msg.robot).mapped.add(msg.seq)
                self._map_queue.task_done()

    def _map_one(self, msg: CloudMsg) -> None:
        assert self.map is not None
        points_ned = body_to_ned(msg.points_body.astype(np.float64), msg.pose)
        changes = self.map.add_cloud(msg.robot, msg.t_ns, points_ned, msg.pose)
        self.map_clouds += 1
        self._publish_changes(msg, changes)

    def _publish_changes(self, msg: CloudMsg | None, changes: list[dict[str, Any]]) -> None:
        if not changes:
            return
        self._map_dirty = True
        if self._map_pub is None:
            return
        update: dict[str, Any] = {"t_ns": time.time_ns(), "planes": changes}
        if msg is not None:
            update.update(t_ns=msg.t_ns, robot=msg.robot, seq=msg.seq)
        try:
            self._map_pub.put(json.dumps(update, default=_json_default))
        except Exception as err:
            log.debug("map update not published: %s", err)

    def _saver(self) -> None:
        """Write changed counters every ``save_period_s``; every ``ack_period_s`` a :meth:`checkpoint`
        (map saved, then counters with the acknowledged ranges). ``MapBuilder`` also autosaves."""
        last_checkpoint = time.monotonic()
        while not self._closing.wait(self.save_period_s):
            if not self._dirty and not self._unacked():
                continue
            try:
                if time.monotonic() - last_checkpoint >= self.ack_period_s:
                    last_checkpoint = time.monotonic()
                    self.checkpoint()
                elif self._dirty:
                    self.save_state()
            except Exception as err:  # a full disk must not stop the service; acks wait for the next try
                log.error("cannot save state: %s", err)

    def _ack_now(self, robot: str) -> None:
        """Without the map a checkpoint is one small file: write it now (at most every 0.2 s) so that an
        acknowledgement query sees everything received. With the map, the saver's checkpoints answer."""
        if self.map is not None or self.state_dir is None:
            return
        with self._lock:
            rec = self.records.get(robot)
            if rec is None or len(rec.seqs) == sum(hi - lo + 1 for lo, hi in rec.acked):
                return
            if time.monotonic() - self._last_ack_save < 0.2:
                return
            self._last_ack_save = time.monotonic()
            ranges = rec.seqs.ranges()
        try:
            self.save_state({robot: ranges})
        except OSError as err:
            log.error("cannot save state: %s", err)

    def _unacked(self) -> bool:
        with self._lock:
            return any(len(rec.seqs) != sum(hi - lo + 1 for lo, hi in rec.acked) for rec in self.records.values())

    # ------------------------------------------------------------------ views
    def map_json(self) -> dict[str, Any]:
        """The whole map as JSON-ready data (``{"planes": []}`` when the map is off)."""
        if self.map is None:
            return {"planes": [], "enabled": False}
        data: dict[str, Any] = self.map.map_json()
        self._map_planes = len(data.get("planes", []))
        self._map_dirty = False
        return json.loads(json.dumps(data, default=_json_default))

    def flush_map(self, timeout_s: float = 60.0) -> None:
        """Process every queued cloud and let the map extract what it still holds (end of a dive)."""
        if self.map is None:
            return
        self.drain(timeout_s)
        self._map_queue.put(_FLUSH)  # type: ignore[arg-type]
        self._map_queue.join()

    def status(self, robot: str | None = None) -> dict[str, Any]:
        """The status JSON (one robot only when ``robot`` is given)."""
        if self.map is not None and self._map_dirty:
            n = getattr(self.map, "n_planes", None)
            if isinstance(n, int):
                self._map_planes = n
                self._map_dirty = False
            else:
                self.map_json()
        with self._lock:
            robots = {r: rec.to_json() for r, rec in sorted(self.records.items()) if robot in (None, r)}
            lat = self.latency.percentiles_ms()
            transit = self.latency.percentiles_ms(transit=True)
            return {
                "fleet": self.keys.fleet,
                "t_ns": time.time_ns(),
                "robots": robots,
                "map": {
                    "planes": self._map_planes,
                    "enabled": self.map is not None,
                    "clouds": self.map_clouds,
                    "skipped": self.map_skipped,
                    "queued": self._map_queue.qsize(),
                    "errors": self.map_errors,
                },
                "ingest": {
                    "processed": self.processed,
                    "queued": self._queue.qsize(),
                    "latency_ms": {k: (None if v != v else round(v, 3)) for k, v in lat.items()},
                    "transit_ms": {k: (None if v != v else round(v, 3)) for k, v in transit.items()},
                },
            }

    def tracks(self) -> dict[str, np.ndarray]:
        """Per robot, the poses of its accepted clouds: (M, 4) ``t_ns, north_m, east_m, down_m``."""
        with self._lock:
            return {r: np.asarray(rec.track, dtype=float).reshape(-1, 4) for r, rec in self.records.items()}


#: Marker in the map queue: flush the map.
_FLUSH: Any = object()


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    msg = f"not JSON serialisable: {type(obj).__name__}"
    raise TypeError(msg)
