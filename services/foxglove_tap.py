"""A fleet seen through Foxglove's schemas: the subscriber both the recording and the live view are built on.

:class:`FleetTap` subscribes to a fleet like the base station does (every robot's clouds, the map's updates)
and logs, on a ``foxglove.Context`` whose sinks the caller chose (an MCAP file, a WebSocket server or both):

* ``/<prefix>/<fleet>/<robot>/points``: ``foxglove.PointCloud`` in ``<robot>/base_link``, **exactly one per
  distinct cloud** (robot, sequence number), however often the robot sent it (re-sends are counted, not
  logged again);
* ``/tf``: ``foxglove.FrameTransform`` ``ned`` -> ``<robot>/base_link`` at each cloud's capture time, for the
  clouds whose pose has a horizontal position;
* ``/<prefix>/<fleet>/map``: ``foxglove.SceneUpdate`` of the map's planes (the whole map at the start, and
  every ``map_refresh_s`` for viewers that join later, then every update the base station publishes);
* with ``raw``: ``<prefix>/<fleet>/<robot>/cloud``, each cloud's wire payload as it arrived (msgpack, schema
  1 or 2 of docs/conventions.md), and ``<prefix>/<fleet>/<robot>/calib``, the robot's calibration (JSON, the
  calibration file's form) once per calibration it measured with: what makes a recording replayable;
* with ``tracks``: ``/<prefix>/<fleet>/tracks``, ``foxglove.SceneUpdate`` with each robot's track in ``ned``
  (a line through its placed positions);
* with ``status_period_s``: ``/<prefix>/<fleet>/status``, the base station's status JSON, polled.

A compact (schema 2) cloud carries pixels: it is triangulated with the calibration it was measured with, asked
from the robot (``<root>/<robot>/calib``) or else the base station's store (``<root>/base/calib/<robot>``); a
cloud whose calibration cannot be found is logged raw, and its point cloud as soon as the calibration is known
(``pending`` counts the ones still waiting).

Zenoh callbacks only queue; one thread decodes and logs, so a slow sink never blocks the session.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lrsensor.calibration import Calibration

from .calibbook import CalibrationBook
from .errors import ServiceError, WireError
from .foxglove_views import has_fix, map_scene, point_cloud, robot_transform, track_scene
from .keys import FleetKeys
from .seqset import SeqSet
from .wire import CalibMsg, CloudMsg, StripeMsg, calibration_fingerprint, decode_cloud

log = logging.getLogger(__name__)

#: Schema of the raw wire channels: msgpack, described in docs/conventions.md.
RAW_SCHEMA_NAME = "lrsensor.cloud"
RAW_SCHEMA_ENCODING = "lrsensor-msgpack"
RAW_MESSAGE_ENCODING = "msgpack"
#: The channel of frame transforms (Foxglove's convention).
TF_TOPIC = "/tf"
#: How long a query (calibration, map, status) may take, seconds.
QUERY_TIMEOUT_S = 2.0
#: At most this many positions per robot track (older ones are thinned out).
TRACK_POINTS = 2000


class FoxgloveUnavailableError(ServiceError):
    """foxglove-sdk (or mcap) is not installed."""


def import_foxglove() -> Any:
    """The ``foxglove`` module, or :class:`FoxgloveUnavailableError` naming the extra to install."""
    try:
        import foxglove
    except ImportError as err:
        msg = f"recording and the live view need foxglove-sdk (pip install 'lrsensor[record]'): {err}"
        raise FoxgloveUnavailableError(msg) from err
    return foxglove


@dataclass
class TapCounters:
    """What a tap has logged so far.

    Attributes:
        clouds: distinct clouds logged, by robot.
        duplicates: clouds received again (re-sends), not logged again.
        rejected: payloads that did not decode, or whose robot does not match their key.
        pending: compact clouds whose calibration is not known yet (no point cloud yet).
        map_updates: map scene updates logged.
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
    """Logs a fleet on a foxglove ``Context`` (see the module docstring).

    Args:
        session: an open Zenoh session (the caller owns it).
        keys: the fleet's key expressions.
        context: the ``foxglove.Context`` to log on (its sinks are the caller's).
        raw: also log the wire payloads and calibrations (a replayable recording).
        tracks: also log the robots' tracks.
        map_refresh_s: fetch and log the whole map again this often, seconds (None: only at the start).
        status_period_s: poll and log the base station's status this often, seconds (None: never).
    """

    def __init__(
        self,
        session: Any,
        keys: FleetKeys,
        context: Any,
        *,
        raw: bool = True,
        tracks: bool = False,
        map_refresh_s: float | None = None,
        status_period_s: float | None = None,
    ) -> None:
        foxglove = import_foxglove()
        from foxglove.channels import FrameTransformChannel, SceneUpdateChannel

        self.session = session
        self.keys = keys
        self.raw = raw
        self.counters = TapCounters()
        self._foxglove = foxglove
        self._ctx = context
        self._raw_schema = foxglove.Schema(
            name=RAW_SCHEMA_NAME, encoding=RAW_SCHEMA_ENCODING, data=b"lrsensor cloud, docs/conventions.md"
        )
        self._tf = FrameTransformChannel(TF_TOPIC, context=context)
        self._map = SceneUpdateChannel(f"/{keys.root}/map", context=context)
        self._tracks_channel = SceneUpdateChannel(f"/{keys.root}/tracks", context=context) if tracks else None
        self._status_channel = (
            foxglove.Channel(f"/{keys.root}/status", message_encoding="json", context=context)
            if status_period_s
            else None
        )
        self._tracks: dict[str, list[tuple[float, float, float]]] = {}
        self._channels: dict[str, Any] = {}
        self._seen: dict[str, SeqSet] = {}
        self._calib_written: set[tuple[str, bytes]] = set()
        self._waiting: dict[str, list[StripeMsg]] = {}
        self.calibrations = CalibrationBook(lambda robot: None, self._fetch_calibration, retry_s=2.0)
        self._queue: queue.Queue[tuple[str, str, bytes, int] | None] = queue.Queue()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="foxglove-tap", daemon=True)
        self._thread.start()
        self._subs = [
            session.declare_subscriber(keys.all_clouds, self._on_cloud),
            session.declare_subscriber(keys.map_updates, self._on_map_update),
        ]
        self._fetch_into_queue(self.keys.map, "map")
        self._pollers = [
            threading.Thread(target=self._poll, args=(key, kind, period), name=f"foxglove-{kind}", daemon=True)
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
            log.info("foxglove tap: %s not fetched: %s", key, err)
            return
        for reply in replies:
            if reply.ok is not None:
                self._queue.put((kind, key, reply.ok.payload.to_bytes(), time.time_ns()))
                return

    def _poll(self, key: str, kind: str, period_s: float) -> None:
        while not self._stop.wait(period_s):
            self._fetch_into_queue(key, kind)

    # ------------------------------------------------------------------ the logging thread
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                self._queue.task_done()
                return
            kind, key, payload, recv_ns = item
            try:
                if kind == "cloud":
                    self._log_cloud(key, payload, recv_ns)
                elif kind == "map":
                    self._log_map(payload, recv_ns)
                elif self._status_channel is not None:
                    self._status_channel.log(json.loads(payload), log_time=recv_ns)
            except Exception as err:  # never let the thread die: count and go on
                with self._lock:
                    self.counters.rejected += 1
                log.warning("foxglove tap: %s on %s not logged: %s", kind, key, err)
            finally:
                self._queue.task_done()

    def _raw_channel(self, topic: str, encoding: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            if encoding == "json":
                ch = self._foxglove.Channel(topic, message_encoding="json", context=self._ctx)
            else:
                ch = self._foxglove.Channel(
                    topic, message_encoding=RAW_MESSAGE_ENCODING, schema=self._raw_schema, context=self._ctx
                )
            self._channels[topic] = ch
        return ch

    def _points_channel(self, robot: str) -> Any:
        topic = f"/{self.keys.root}/{robot}/points"
        ch = self._channels.get(topic)
        if ch is None:
            from foxglove.channels import PointCloudChannel

            ch = PointCloudChannel(topic, context=self._ctx)
            self._channels[topic] = ch
        return ch

    def _log_cloud(self, key: str, payload: bytes, recv_ns: int) -> None:
        robot = self.keys.robot_of(key)
        try:
            msg = decode_cloud(payload)
        except WireError as err:
            with self._lock:
                self.counters.rejected += 1
            log.warning("foxglove tap: payload on %s refused: %s", key, err)
            return
        if robot is None or msg.robot != robot:
            with self._lock:
                self.counters.rejected += 1
            log.warning("foxglove tap: cloud of %r arrived on %s; not logged", msg.robot, key)
            return
        if not self._seen.setdefault(robot, SeqSet()).add(msg.seq):
            with self._lock:
                self.counters.duplicates += 1
            return
        if self.raw:
            self._raw_channel(self.keys.cloud(robot), "msgpack").log(payload, log_time=recv_ns)
        with self._lock:
            self.counters.clouds[robot] = self.counters.clouds.get(robot, 0) + 1
        if isinstance(msg, StripeMsg):
            self._waiting.setdefault(robot, []).append(msg)
            self._place_waiting(robot, recv_ns)
        else:
            self._log_views(msg, recv_ns)

    def _place_waiting(self, robot: str, log_ns: int) -> None:
        still: list[StripeMsg] = []
        for stripe in self._waiting.get(robot, []):
            calib, _ = self.calibrations.lookup(robot, stripe.calib_id)
            if calib is None:
                still.append(stripe)
                continue
            self._log_calibration(robot, calib, log_ns)
            self._log_views(stripe.to_cloud(calib), log_ns)
        self._waiting[robot] = still
        with self._lock:
            self.counters.pending = sum(len(v) for v in self._waiting.values())

    def _log_calibration(self, robot: str, calib: Calibration, log_ns: int) -> None:
        fp = calibration_fingerprint(calib)
        if not self.raw or (robot, fp) in self._calib_written:
            return
        self._calib_written.add((robot, fp))
        self._raw_channel(self.keys.calib(robot), "json").log(calib.to_dict(), log_time=log_ns)

    def _log_views(self, msg: CloudMsg, log_ns: int) -> None:
        self._points_channel(msg.robot).log(
            point_cloud(msg.robot, msg.t_ns, msg.points_body, msg.laser), log_time=log_ns
        )
        tf = robot_transform(msg.robot, msg.t_ns, msg.pose)
        if tf is not None:
            self._tf.log(tf, log_time=log_ns)
        if self._tracks_channel is not None and has_fix(msg.pose):
            track = self._tracks.setdefault(msg.robot, [])
            track.append((msg.pose.north_m, msg.pose.east_m, msg.pose.down_m))
            if len(track) > TRACK_POINTS:
                del track[1::2]  # keep the whole dive's shape at half the resolution
            self._tracks_channel.log(track_scene(msg.robot, np.asarray(track), msg.t_ns), log_time=log_ns)

    def _log_map(self, payload: bytes, recv_ns: int) -> None:
        data = json.loads(payload)
        planes = data.get("planes", [])
        self._map.log(map_scene(planes, int(data.get("t_ns", recv_ns))), log_time=recv_ns)
        with self._lock:
            self.counters.map_updates += 1

    def _fetch_calibration(self, robot: str) -> Calibration | None:
        for key in (self.keys.calib(robot), self.keys.base_calib(robot)):
            for reply in self.session.get(key, timeout=QUERY_TIMEOUT_S):
                if reply.ok is None:
                    continue
                try:
                    msg = CalibMsg.from_bytes(reply.ok.payload.to_bytes())
                except WireError as err:
                    log.warning("foxglove tap: calibration answer on %s refused: %s", key, err)
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
        """True when everything received so far has been logged."""
        return self._queue.unfinished_tasks == 0

    def close(self) -> dict[str, Any]:
        """Stop subscribing, log what is queued (one last try for waiting calibrations); returns the counters."""
        if self._closed:
            return self.stats()
        self._closed = True
        self._stop.set()
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception as err:
                log.debug("foxglove tap: undeclare failed: %s", err)
        for t in self._pollers:
            t.join(timeout=QUERY_TIMEOUT_S + 1.0)
        self._queue.put(None)
        self._thread.join()
        self.calibrations.retry_s = 0.0
        for robot in list(self._waiting):
            if self._waiting[robot]:
                self._place_waiting(robot, time.time_ns())
        if self.counters.pending:
            log.warning(
                "foxglove tap: %d compact clouds had no calibration: logged raw only (no point cloud)",
                self.counters.pending,
            )
        return self.stats()
