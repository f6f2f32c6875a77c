"""A plane worker: the per-robot half of the map (NED transform, windows, plane extraction) in its own process.

A worker joins a fleet over Zenoh (``lrsensor map-worker --connect EP --fleet F``, or started by
``lrsensor base --map-workers N``), declares its liveliness token ``<root>/map/workers/<name>``, and takes the
jobs the base sends to ``<root>/map/work/<name>`` (:mod:`services.map_worker_wire`): one cloud each, with the pose
to place it with. It transforms the points to NED, feeds them to its own :class:`mapping.MapBuilder` (used
through :meth:`~mapping.MapBuilder.observe_cloud`: windows and extraction, no map of its own), and publishes
what each extraction gives on ``<root>/map/obs/<name>``: the plane observations (exact sufficient statistics)
and the sequence numbers of the clouds they commit. The base (the merger) only adds them to the shared map.

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
import uuid
from typing import Any

import numpy as np

from lrsensor.frames import body_to_ned

from .errors import WireError
from .keys import FleetKeys
from .map_worker_wire import (
    FLUSH_KEY,
    MapControl,
    MapJob,
    PlaneObservations,
    decode_work,
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
    """

    def __init__(self, session: Any, keys: FleetKeys, name: str | None = None, cfg: Any = None) -> None:
        from mapping import MapBuilder, MapConfig  # Open3D lives behind this import

        self.session = session
        self.keys = keys
        self.name = name or worker_name()
        self.builder = MapBuilder(cfg or MapConfig())
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

    def _on_work(self, sample: Any) -> None:
        self._queue.put(sample.payload.to_bytes())  # never blocks (see the module docstring)

    def _run(self) -> None:
        while True:
            payload = self._queue.get()
            if payload is None:
                return
            try:
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
        if isinstance(msg, MapControl):
            if msg.kind == "flush":
                for robot, records in self.builder.flush_observations().items():
                    out.append(self._observed(robot, records, FLUSH_KEY))
                for robot in sorted(r for r, seqs in self._pending.items() if seqs):  # nothing left to extract
                    out.append(self._observed(robot, [], FLUSH_KEY))
            elif msg.kind == "drop" and self._epoch.get(msg.robot, -1) < msg.epoch:
                self._forget(msg.robot)
        else:
            out.extend(self._job(msg))
        for obs in out:
            if self._pub is not None:
                self._pub.put(obs.to_bytes())
            self.published += 1
        return out

    def _forget(self, robot: str) -> None:
        self.builder.drop_robot(robot)
        self._pending.pop(robot, None)
        self._epoch.pop(robot, None)

    def _job(self, job: MapJob) -> list[PlaneObservations]:
        held = self._epoch.get(job.robot)
        if held is not None and job.epoch < held:
            self.stale += 1
            return []
        if held is None or job.epoch > held:  # (re)assigned here: the base re-sends what is not committed
            self._forget(job.robot)
            self._epoch[job.robot] = job.epoch
        self.jobs += 1
        self._pending.setdefault(job.robot, []).append(job.seq)
        try:
            pts = job.points_body.astype(np.float64)
            records = self.builder.observe_cloud(job.robot, job.t_ns, body_to_ned(pts, job.pose), job.pose)
        except Exception as err:  # done with, not stuck in flight at the base: commit what is pending, no planes
            self.errors += 1
            log.warning("map worker %s: cloud %s#%d not mapped: %s", self.name, job.robot, job.seq, err)
            return [self._observed(job.robot, [], job.t_ns)]
        if records is None:
            if self.builder.uncommitted(job.robot) == 0:  # an operator's cap left it out: done with it
                return [self._observed(job.robot, [], job.t_ns)]
            return []
        return [self._observed(job.robot, records, job.t_ns)]

    def _observed(self, robot: str, records: list[Any], key_ns: int) -> PlaneObservations:
        from mapping.plane_map import record_to_wire

        seqs = tuple(self._pending.pop(robot, []))
        return PlaneObservations(
            self.name, robot, self._epoch.get(robot, 0), seqs, tuple(record_to_wire(r) for r in records), key_ns
        )
