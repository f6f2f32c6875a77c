"""A fleet seen from outside the base station: the subscriber the recording and the live views are built on.

:class:`FleetTap` subscribes to a fleet like the base station does (every robot's clouds, the map's updates;
optionally the base's status, and the whole map again now and then for viewers that join late), decodes and
de-duplicates, and hands typed values to its sinks (:class:`TapSink`): the Foxglove views
(:class:`services.foxglove_views.FoxgloveSink`, for the MCAP recording and the WebSocket live view) and the
ROS 2 views (:class:`services.ros2_views.Ros2FleetSink`).

* Each distinct cloud (robot, sequence number) reaches the sinks **once**, however often the robot sent it
  (re-sends are counted as duplicates): first its wire payload (``raw_cloud``), then, placed as a
  :class:`~services.wire.CloudMsg` with body-frame points (``cloud``).
* A compact (schema 2) cloud carries pixels: it is triangulated with the calibration it was measured with,
  asked from the robot (``<root>/<robot>/calib``) or else the base station's store
  (``<root>/base/calib/<robot>``); ``calibration`` is called once per calibration. A cloud whose calibration
  cannot be found yet waits (``pending``) and is placed as soon as it is known.
* Map updates and whole maps reach ``map_update`` as the planes' JSON (``{"id", "normal", "d", "extent",
  ...}`` or ``{"id", "removed": True}``); the status as the base's status JSON.

Zenoh callbacks only queue; one thread decodes and calls the sinks, so a slow sink never blocks the session.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

from lrsensor.calibration import Calibration

from .calibbook import CalibrationBook
from .errors import WireError
from .keys import FleetKeys
from .seqset import SeqSet
from .wire import CalibMsg, CloudMsg, StripeMsg, calibration_fingerprint, decode_cloud
from .zconfig import undeclare_all

log = logging.getLogger(__name__)

#: How long a query (calibration, map, status) may take, seconds.
QUERY_TIMEOUT_S = 2.0


class TapSink(Protocol):
    """What a :class:`FleetTap` hands its values to (called from the tap's one thread, in arrival order)."""

    def raw_cloud(self, robot: str, payload: bytes, log_ns: int) -> None:
        """A distinct cloud's wire payload, as it arrived."""

    def cloud(self, msg: CloudMsg, log_ns: int) -> None:
        """A distinct cloud with its body-frame points (a compact cloud once its calibration is known)."""

    def calibration(self, robot: str, calibration: Calibration, log_ns: int) -> None:
        """A calibration ``robot`` measured with (once per calibration)."""

    def map_update(self, planes: list[dict[str, Any]], t_ns: int, log_ns: int) -> None:
        """Changed planes (or the whole map) as the map keys serve them."""

    def status(self, data: dict[str, Any], log_ns: int) -> None:
        """The base station's status JSON."""


@dataclass
class TapCounters:
    """What a tap has handed on so far.

    Attributes:
        clouds: distinct clouds, by robot.
        duplicates: clouds received again (re-sends), not handed on again.
        rejected: payloads that did not decode, or whose robot does not match their key; sink failures.
        pending: compact clouds whose calibration is not known yet.
        map_updates: map updates and whole maps handed on.
    """

    clouds: dict[str, int] = field(default_factory=dict)
    duplicates: int = 0
    rejected: int = 0
    pending: int = 0
    map_updates: int = 0

    def to_json(self) -> dict[str, Any]:
        """JSON-ready copy."""
        return {
            "clouds": dict(self.clouds),
            "total_clouds": sum(self.clouds.values()),
            "duplicates": self.duplicates,
            "rejected": self.rejected,
            "pending": self.pending,
            "map_updates": self.map_updates,
        }


class FleetTap:
    """Subscribes to a fleet and hands what it sees to ``sinks`` (see the module docstring).

    Args:
        session: an open Zenoh session (the caller owns it).
        keys: the fleet's key expressions.
        sinks: where the values go.
        map_refresh_s: fetch the whole map again this often, seconds (None: only at the start).
        status_period_s: poll the base station's status this often, seconds (None: never).
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        sinks: Sequence[TapSink],
        *,
        map_refresh_s: float | None = None,
        status_period_s: float | None = None,
    ) -> None:
        self.session = session
        self.keys = keys
        self.sinks = list(sinks)
        self.counters = TapCounters()
        self._seen: dict[str, SeqSet] = {}
        self._calib_sent: set[tuple[str, bytes]] = set()
        self._waiting: dict[str, list[StripeMsg]] = {}
        self.calibrations = CalibrationBook(lambda robot: None, self._fetch_calibration, retry_s=2.0)
        self._queue: queue.Queue[tuple[str, str, bytes, int] | None] = queue.Queue()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="fleet-tap", daemon=True)
        self._thread.start()
        self._subs = [
            session.declare_subscriber(keys.all_clouds, self._on_cloud),
            session.declare_subscriber(keys.map_updates, self._on_map_update),
        ]
        self._fetch_into_queue(self.keys.map, "map")
        self._pollers = [
            threading.Thread(target=self._poll, args=(key, kind, period), name=f"fleet-tap-{kind}", daemon=True)
            for key, kind, period in ((keys.map, "map", map_refresh_s), (keys.base_status, "status", status_period_s))
            if period
        ]
        for t in self._pollers:
            t.start()

    # ------------------------------------------------------------------ callbacks and pollers (queue only)
    def _on_cloud(self, sample: Any) -> None:
        self._queue.put(("cloud", str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def _on_map_update(self, sample: Any) -> None:
        self._queue.put(("map", str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def _fetch_into_queue(self, key: str, kind: str) -> None:
        try:
            replies = list(self.session.get(key, timeout=QUERY_TIMEOUT_S))
        except Exception as err:  # no base station yet: the updates will come
            log.info("fleet tap: %s not fetched: %s", key, err)
            return
        for reply in replies:
            if reply.ok is not None:
                self._queue.put((kind, key, reply.ok.payload.to_bytes(), time.time_ns()))
                return

    def _poll(self, key: str, kind: str, period_s: float) -> None:
        while not self._stop.wait(period_s):
            self._fetch_into_queue(key, kind)

    # ------------------------------------------------------------------ the tap's thread
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                self._queue.task_done()
                return
            kind, key, payload, recv_ns = item
            try:
                if kind == "cloud":
                    self._take_cloud(key, payload, recv_ns)
                elif kind == "map":
                    data = json.loads(payload)
                    t_ns = int(data.get("t_ns", recv_ns))
                    for sink in self.sinks:
                        sink.map_update(list(data.get("planes", [])), t_ns, recv_ns)
                    with self._lock:
                        self.counters.map_updates += 1
                else:
                    status = json.loads(payload)
                    for sink in self.sinks:
                        sink.status(status, recv_ns)
            except Exception as err:  # never let the thread die: count and go on
                with self._lock:
                    self.counters.rejected += 1
                log.warning("fleet tap: %s on %s not handed on: %s", kind, key, err)
            finally:
                self._queue.task_done()

    def _take_cloud(self, key: str, payload: bytes, recv_ns: int) -> None:
        robot = self.keys.robot_of(key)
        try:
            msg = decode_cloud(payload)
        except WireError as err:
            with self._lock:
                self.counters.rejected += 1
            log.warning("fleet tap: payload on %s refused: %s", key, err)
            return
        if robot is None or msg.robot != robot:
            with self._lock:
                self.counters.rejected += 1
            log.warning("fleet tap: cloud of %r arrived on %s; not taken", msg.robot, key)
            return
        if not self._seen.setdefault(robot, SeqSet()).add(msg.seq):
            with self._lock:
                self.counters.duplicates += 1
            return
        for sink in self.sinks:
            sink.raw_cloud(robot, payload, recv_ns)
        with self._lock:
            self.counters.clouds[robot] = self.counters.clouds.get(robot, 0) + 1
        if isinstance(msg, StripeMsg):
            self._waiting.setdefault(robot, []).append(msg)
            self._place_waiting(robot, recv_ns)
        else:
            for sink in self.sinks:
                sink.cloud(msg, recv_ns)

    def _place_waiting(self, robot: str, log_ns: int) -> None:
        still: list[StripeMsg] = []
        for stripe in self._waiting.get(robot, []):
            calib, _ = self.calibrations.lookup(robot, stripe.calib_id)
            if calib is None:
                still.append(stripe)
                continue
            fp = calibration_fingerprint(calib)
            if (robot, fp) not in self._calib_sent:
                self._calib_sent.add((robot, fp))
                for sink in self.sinks:
                    sink.calibration(robot, calib, log_ns)
            cloud = stripe.to_cloud(calib)
            for sink in self.sinks:
                sink.cloud(cloud, log_ns)
        self._waiting[robot] = still
        with self._lock:
            self.counters.pending = sum(len(v) for v in self._waiting.values())

    def _fetch_calibration(self, robot: str) -> Calibration | None:
        for key in (self.keys.calib(robot), self.keys.base_calib(robot)):
            for reply in self.session.get(key, timeout=QUERY_TIMEOUT_S):
                if reply.ok is None:
                    continue
                try:
                    msg = CalibMsg.from_bytes(reply.ok.payload.to_bytes())
                except WireError as err:
                    log.warning("fleet tap: calibration answer on %s refused: %s", key, err)
                    continue
                if msg.robot == robot:
                    self.calibrations.add(robot, msg.calibration)
                    return msg.calibration
        return None

    # ------------------------------------------------------------------ control
    def stats(self) -> dict[str, Any]:
        """The counters as JSON-ready data."""
        with self._lock:
            return self.counters.to_json()

    def idle(self) -> bool:
        """True when everything received so far has been handed on."""
        return self._queue.unfinished_tasks == 0

    def close(self) -> dict[str, Any]:
        """Stop subscribing, hand on what is queued (one last try for waiting calibrations); the counters."""
        if self._closed:
            return self.stats()
        self._closed = True
        self._stop.set()
        undeclare_all(self._subs, "fleet tap")
        for t in self._pollers:
            t.join(timeout=QUERY_TIMEOUT_S + 1.0)
        self._queue.put(None)
        self._thread.join()
        self.calibrations.retry_s = 0.0
        for robot in list(self._waiting):
            if self._waiting[robot]:
                self._place_waiting(robot, time.time_ns())
        if self.counters.pending:
            log.warning("fleet tap: %d compact clouds had no calibration: not placed", self.counters.pending)
        return self.stats()
