"""Recording a fleet into an MCAP file (``lrsensor record``), readable by Foxglove and the ``mcap`` reader.

The recorder is a Zenoh subscriber like the base station: it takes every robot's clouds and the map's
updates and writes, with foxglove-sdk's MCAP writer:

* ``/<prefix>/<fleet>/<robot>/points``: ``foxglove.PointCloud`` in ``<robot>/base_link``, **exactly one per
  distinct cloud** (robot, sequence number), however often the robot sent it (re-sends are counted, not
  written again);
* ``/tf``: ``foxglove.FrameTransform`` ``ned`` -> ``<robot>/base_link`` at each cloud's capture time, for the
  clouds whose pose has a horizontal position;
* ``/<prefix>/<fleet>/map``: ``foxglove.SceneUpdate`` of the map's planes (the whole map when recording
  starts, then every update the base station publishes);
* ``<prefix>/<fleet>/<robot>/cloud``: the cloud's wire payload as it arrived (msgpack, schema 1 or 2 of
  docs/conventions.md), and ``<prefix>/<fleet>/<robot>/calib``: the robot's calibration (JSON, the calibration
  file's form) once per calibration it measured with. These two channels make a recording replayable
  (:mod:`services.replay`): a base station fed with them rebuilds the same map.

A compact (schema 2) cloud carries pixels: the recorder triangulates it with the calibration it was measured
with, asked from the robot (``<root>/<robot>/calib``) or else the base station's store
(``<root>/base/calib/<robot>``); a cloud whose calibration cannot be found is still written raw, and its point
cloud is written as soon as the calibration is known (``pending`` counts the ones still waiting).

Zenoh callbacks only queue; one writer thread decodes and writes, so a slow disk never blocks the session.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lrsensor.calibration import Calibration

from .calibbook import CalibrationBook
from .errors import ServiceError, WireError
from .foxglove_views import map_scene, point_cloud, robot_transform
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
#: How long a calibration query may take, seconds.
CALIB_QUERY_TIMEOUT_S = 2.0


class RecordError(ServiceError):
    """The recording cannot be written (the file exists, the folder is missing, foxglove-sdk is absent)."""


@dataclass
class RecordCounters:
    """What a recorder has written so far.

    Attributes:
        clouds: distinct clouds written, by robot.
        duplicates: clouds received again (re-sends), not written again.
        rejected: payloads that did not decode, or whose robot does not match their key.
        pending: clouds written raw whose calibration is not known yet (no point cloud yet).
        map_updates: map scene updates written.
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


class Recorder:
    """Records a fleet's clouds, poses and map into ``path`` (see the module docstring).

    Args:
        session: an open Zenoh session (the caller owns it).
        keys: the fleet's key expressions.
        path: the ``.mcap`` file to write.
        overwrite: replace an existing file (otherwise an existing file is refused).
    """

    def __init__(self, session: Any, keys: FleetKeys, path: str | Path, *, overwrite: bool = False) -> None:
        try:
            import foxglove
            from foxglove.channels import FrameTransformChannel, SceneUpdateChannel
        except ImportError as err:
            msg = f"recording needs foxglove-sdk (pip install 'lrsensor[all]'): {err}"
            raise RecordError(msg) from err
        self.session = session
        self.keys = keys
        self.path = Path(path)
        if self.path.exists() and not overwrite:
            msg = f"{self.path} exists; choose another --out or remove it"
            raise RecordError(msg)
        if not self.path.parent.is_dir():
            msg = f"cannot record to {self.path}: folder {self.path.parent} does not exist"
            raise RecordError(msg)
        self.counters = RecordCounters()
        self._foxglove = foxglove
        self._ctx = foxglove.Context()
        try:
            self._writer = foxglove.open_mcap(str(self.path), allow_overwrite=overwrite, context=self._ctx)
        except Exception as err:
            msg = f"cannot open {self.path} for recording: {err}"
            raise RecordError(msg) from err
        self._writer.write_metadata(
            "lrsensor", {"prefix": keys.prefix, "fleet": keys.fleet, "started_ns": str(time.time_ns())}
        )
        self._raw_schema = foxglove.Schema(
            name=RAW_SCHEMA_NAME, encoding=RAW_SCHEMA_ENCODING, data=b"lrsensor cloud, docs/conventions.md"
        )
        self._tf = FrameTransformChannel(TF_TOPIC, context=self._ctx)
        self._map = SceneUpdateChannel(f"/{keys.root}/map", context=self._ctx)
        self._channels: dict[str, Any] = {}
        self._seen: dict[str, SeqSet] = {}
        self._calib_written: set[tuple[str, bytes]] = set()
        self._waiting: dict[str, list[StripeMsg]] = {}
        self.calibrations = CalibrationBook(lambda robot: None, self._fetch_calibration, retry_s=2.0)
        self._queue: queue.Queue[tuple[str, str, bytes, int] | None] = queue.Queue()
        self._lock = threading.Lock()
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        self._subs = [
            session.declare_subscriber(keys.all_clouds, self._on_cloud),
            session.declare_subscriber(keys.map_updates, self._on_map_update),
        ]
        self._record_whole_map()

    # ------------------------------------------------------------------ callbacks (queue only)
    def _on_cloud(self, sample: Any) -> None:
        self._queue.put(("cloud", str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def _on_map_update(self, sample: Any) -> None:
        self._queue.put(("map", str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))

    def _record_whole_map(self) -> None:
        try:
            replies = list(self.session.get(self.keys.map, timeout=CALIB_QUERY_TIMEOUT_S))
        except Exception as err:  # no base station yet: the updates will come
            log.info("record: whole map not fetched: %s", err)
            return
        for reply in replies:
            if reply.ok is not None:
                self._queue.put(("map", self.keys.map, reply.ok.payload.to_bytes(), time.time_ns()))
                return

    # ------------------------------------------------------------------ the writer thread
    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                self._queue.task_done()
                return
            kind, key, payload, recv_ns = item
            try:
                if kind == "cloud":
                    self._write_cloud(key, payload, recv_ns)
                else:
                    self._write_map(payload, recv_ns)
            except Exception as err:  # never let the writer die: count and go on
                with self._lock:
                    self.counters.rejected += 1
                log.warning("record: %s on %s not written: %s", kind, key, err)
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

    def _write_cloud(self, key: str, payload: bytes, recv_ns: int) -> None:
        robot = self.keys.robot_of(key)
        try:
            msg = decode_cloud(payload)
        except WireError as err:
            with self._lock:
                self.counters.rejected += 1
            log.warning("record: payload on %s refused: %s", key, err)
            return
        if robot is None or msg.robot != robot:
            with self._lock:
                self.counters.rejected += 1
            log.warning("record: cloud of %r arrived on %s; not recorded", msg.robot, key)
            return
        if not self._seen.setdefault(robot, SeqSet()).add(msg.seq):
            with self._lock:
                self.counters.duplicates += 1
            return
        self._raw_channel(self.keys.cloud(robot), "msgpack").log(payload, log_time=recv_ns)
        with self._lock:
            self.counters.clouds[robot] = self.counters.clouds.get(robot, 0) + 1
        if isinstance(msg, StripeMsg):
            self._waiting.setdefault(robot, []).append(msg)
            self._place_waiting(robot, recv_ns)
        else:
            self._write_views(msg, recv_ns)

    def _place_waiting(self, robot: str, log_ns: int) -> None:
        still: list[StripeMsg] = []
        for stripe in self._waiting.get(robot, []):
            calib, _ = self.calibrations.lookup(robot, stripe.calib_id)
            if calib is None:
                still.append(stripe)
                continue
            self._write_calibration(robot, calib, log_ns)
            self._write_views(stripe.to_cloud(calib), log_ns)
        self._waiting[robot] = still
        with self._lock:
            self.counters.pending = sum(len(v) for v in self._waiting.values())

    def _write_calibration(self, robot: str, calib: Calibration, log_ns: int) -> None:
        fp = calibration_fingerprint(calib)
        if (robot, fp) in self._calib_written:
            return
        self._calib_written.add((robot, fp))
        self._raw_channel(self.keys.calib(robot), "json").log(calib.to_dict(), log_time=log_ns)

    def _write_views(self, msg: CloudMsg, log_ns: int) -> None:
        self._points_channel(msg.robot).log(
            point_cloud(msg.robot, msg.t_ns, msg.points_body, msg.laser), log_time=log_ns
        )
        tf = robot_transform(msg.robot, msg.t_ns, msg.pose)
        if tf is not None:
            self._tf.log(tf, log_time=log_ns)

    def _write_map(self, payload: bytes, recv_ns: int) -> None:
        data = json.loads(payload)
        planes = data.get("planes", [])
        self._map.log(map_scene(planes, int(data.get("t_ns", recv_ns))), log_time=recv_ns)
        with self._lock:
            self.counters.map_updates += 1

    def _fetch_calibration(self, robot: str) -> Calibration | None:
        for key in (self.keys.calib(robot), self.keys.base_calib(robot)):
            for reply in self.session.get(key, timeout=CALIB_QUERY_TIMEOUT_S):
                if reply.ok is None:
                    continue
                try:
                    msg = CalibMsg.from_bytes(reply.ok.payload.to_bytes())
                except WireError as err:
                    log.warning("record: calibration answer on %s refused: %s", key, err)
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
        """True when everything received so far has been written."""
        return self._queue.unfinished_tasks == 0

    def close(self) -> dict[str, Any]:
        """Stop subscribing, write what is queued (one last try for waiting calibrations), finish the file."""
        if self._closed:
            return self.stats()
        self._closed = True
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception as err:
                log.debug("record: undeclare failed: %s", err)
        self._queue.put(None)
        self._thread.join()
        for robot in list(self._waiting):
            if self._waiting[robot]:
                self.calibrations.retry_s = 0.0
                self._place_waiting(robot, time.time_ns())
        if self.counters.pending:
            log.warning(
                "record: %d compact clouds had no calibration: written raw only (replay still has them)",
                self.counters.pending,
            )
        self._writer.close()
        return self.stats()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
