"""What the base station and its plane workers say to each other over Zenoh (msgpack, schema 1).

Keys, under the fleet's root ``<prefix>/<fleet>``:

* ``<root>/map/workers/<worker>``: a worker's liveliness token while it is up (the base's view of who is alive);
* ``<root>/map/work/<worker>``: the base's jobs for that worker (:class:`MapJob`, :class:`MapControl`);
* ``<root>/map/obs/<worker>``: the worker's plane observations (:class:`PlaneObservations`) and, with navigation
  in the workers, its robots' estimates (:class:`NavReport`);
* ``<root>/map/landmarks``: the merged map's snapshots as registration targets, for the workers' navigation
  (:func:`services.map_worker_nav.encode_snapshots`).

A job is one accepted cloud of one robot with the pose to place it with (the navigation's, when it runs) and the
robot's assignment *epoch*: the base bumps a robot's epoch each time the robot moves to another worker, and takes
observations only of the current epoch from the current owner, so a slow or dying worker's late answer is never
counted next to the new owner's (see :mod:`services.map_workers`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

from .errors import WireError
from .keys import FleetKeys, check_name

SCHEMA = 1
#: The merge key of a flush's observations: after every cloud's own (``PlaneObservations.key_ns``).
FLUSH_KEY = 2**62


def workers_key(keys: FleetKeys, worker: str = "*") -> str:
    """``<root>/map/workers/<worker>``: liveliness tokens of the plane workers."""
    return f"{keys.root}/map/workers/{worker}"


def work_key(keys: FleetKeys, worker: str) -> str:
    """``<root>/map/work/<worker>``: the jobs of one worker."""
    return f"{keys.root}/map/work/{check_name(worker, 'worker name')}"


def landmarks_key(keys: FleetKeys) -> str:
    """``<root>/map/landmarks``: the merged map's planes for the workers' navigation."""
    return f"{keys.root}/map/landmarks"


def obs_key(keys: FleetKeys, worker: str = "*") -> str:
    """``<root>/map/obs/<worker>``: plane observations of one worker (``*``: all)."""
    return f"{keys.root}/map/obs/{worker}"


@dataclass(frozen=True)
class MapJob:
    """One cloud to place and extract.

    Attributes:
        robot, seq, t_ns: the cloud's robot, sequence number and capture time (ns since the epoch).
        epoch: the robot's assignment epoch at the base.
        pose: the pose to place it with (NED; the navigation's corrected pose when it runs at the base), or with
            ``navigate`` the raw pose the robot sent: the worker corrects it (:mod:`services.map_worker_nav`).
        points_body: (N, 3) float32, body frame, metres.
        navigate: whether the worker runs the robot's navigation on this cloud.
        lag_ns: with ``navigate``, the snapshot lag (ns): a registered scan uses ``snapshot(T)`` of the merged map,
            T = :func:`mapping.landmarks.snapshot_time` (``t_ns``, ``lag_ns``), waiting for it when needed; 0: the
            worker's mirror of the moment.
        no_fix: with ``navigate``, the base's ``--no-fix`` choice (``lost`` or ``graph``,
            :data:`services.map_worker_nav.NO_FIX_CHOICES`); absent on the wire: ``lost``.
        heading: with ``navigate``, the fleet heading's word on this cloud (:mod:`services.map_worker_heading`):
            ``collect`` (keep the graph robot's scan), ``hold`` (keep it and hold the cloud), or empty.
        range_error_per_px: the range error per pixel (1/(m px)) of the calibration the cloud was measured with
            (:func:`lrsensor.range_theory.range_error_per_px`), its range noise in the extraction
            (:mod:`mapping.range_noise`); 0 (absent on the wire): none known.
    """

    robot: str
    seq: int
    t_ns: int
    epoch: int
    pose: Pose
    points_body: NDArray[np.float32]
    navigate: bool = False
    lag_ns: int = 0
    no_fix: str = "lost"
    heading: str = ""
    range_error_per_px: float = 0.0

    def to_bytes(self) -> bytes:
        """Schema-1 msgpack."""
        p = self.pose
        return msgpack.packb(
            {
                "v": SCHEMA,
                "type": "job",
                "robot": self.robot,
                "seq": self.seq,
                "t_ns": self.t_ns,
                "epoch": self.epoch,
                "pose": [p.north_m, p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad],
                "points": np.ascontiguousarray(self.points_body, "<f4").tobytes(),
                "nav": self.navigate,
                "lag": self.lag_ns,
                "nofix": self.no_fix,
            }
            | ({"heading": self.heading} if self.heading else {})
            | ({"perpx": self.range_error_per_px} if self.range_error_per_px else {})
        )


@dataclass(frozen=True)
class MapControl:
    """A control message: ``flush`` (extract every pending window now; with ``robot``, only that robot's, if it
    is served here under ``epoch`` and has no scan waiting for its snapshot), ``drop`` (forget ``robot``'s window:
    it moved to another worker at ``epoch``) or ``adopt`` (``robot`` moved here at ``epoch``: continue its
    navigation from ``state``, :func:`services.map_worker_nav.encode_state` of the state after its last committed
    cloud; the clouds not committed follow). An ``adopt`` carries the base's ``--no-fix`` choice (``no_fix``), so
    a pose graph's state is restored with the graph's configuration. The fleet heading
    (:mod:`services.map_worker_heading`): ``views`` (send ``robot``'s views, :class:`HeadingViews`, once its jobs
    before this are done) and ``heading`` (``state``: :func:`services.map_worker_nav.encode_state` of
    ``{"bias_rad", "sd_rad", "t_ns"}``, ``robot``'s compass bias for its graph)."""

    kind: str
    robot: str = ""
    epoch: int = 0
    state: bytes = b""
    no_fix: str = "lost"

    def to_bytes(self) -> bytes:
        """Schema-1 msgpack."""
        d: dict[str, Any] = {"v": SCHEMA, "type": self.kind, "robot": self.robot, "epoch": self.epoch}
        if self.state:
            d["state"] = self.state
        if self.no_fix != "lost":
            d["nofix"] = self.no_fix
        return msgpack.packb(d)


@dataclass(frozen=True)
class PlaneObservations:
    """What one extraction of one robot's window gave: the plane observations (exact sufficient statistics, see
    :func:`mapping.plane_map.record_to_wire`) and the sequence numbers of the clouds it committed.

    Attributes:
        worker: the worker that extracted it.
        robot, epoch: the robot and its assignment epoch the clouds were sent under.
        seqs: the clouds this extraction committed (each reaches the map with these observations).
        records: the observations, wire form (merged by the base as they are: it only adds statistics).
        key_ns: where the base merges them in its canonical order: the capture time of the cloud that triggered
            the extraction, or :data:`FLUSH_KEY` for the extraction of a flush (then by robot name).
        unplaced: of ``seqs``, the clouds navigation could not place (committed without planes).
        nav_state: with navigation in the worker, the robot's navigation state after the last cloud of ``seqs``
            (:func:`services.map_worker_nav.encode_state`); empty otherwise (or when the message commits a cloud
            out of its window's order: an unplaced one).
        snap_waited, snap_wait_ms, snap_not_exact: the worker's counters so far (all robots): scans that waited for
            their snapshot of the merged map, the longest such wait (ms), and scans registered against another
            snapshot than theirs (late past ``SNAPSHOT_WAIT_S``, or a snapshot the merger marked not exact).
    """

    worker: str
    robot: str
    epoch: int
    seqs: tuple[int, ...]
    records: tuple[dict[str, Any], ...]
    key_ns: int = 0
    unplaced: tuple[int, ...] = ()
    nav_state: bytes = b""
    snap_waited: int = 0
    snap_wait_ms: int = 0
    snap_not_exact: int = 0

    def to_bytes(self) -> bytes:
        """Schema-1 msgpack."""
        return msgpack.packb(
            {
                "v": SCHEMA,
                "type": "planeobs",
                "worker": self.worker,
                "robot": self.robot,
                "epoch": self.epoch,
                "seqs": list(self.seqs),
                "records": list(self.records),
                "key_ns": self.key_ns,
                "unplaced": list(self.unplaced),
                "nav_state": self.nav_state,
                "snap": [self.snap_waited, self.snap_wait_ms, self.snap_not_exact],
            }
        )

    @classmethod
    def from_bytes(cls, payload: bytes) -> PlaneObservations:
        """Decode (raises :class:`~services.errors.WireError`)."""
        d = _unpack(payload, "planeobs")
        try:
            return cls(
                str(d["worker"]),
                str(d["robot"]),
                int(d["epoch"]),
                tuple(int(s) for s in d["seqs"]),
                tuple(dict(r) for r in d["records"]),
                int(d["key_ns"]),
                tuple(int(s) for s in d.get("unplaced", ())),
                bytes(d.get("nav_state", b"")),
                *(int(x) for x in d.get("snap", (0, 0, 0))[:3]),
            )
        except (KeyError, TypeError, ValueError) as err:
            msg = f"plane observations: malformed: {err!r}"
            raise WireError(msg) from err


@dataclass(frozen=True)
class HeadingViews:
    """A graph robot's views for the fleet heading (:mod:`services.map_worker_heading`), the answer to a ``views``
    control: ``views`` is :func:`services.map_worker_nav.encode_state` of its :class:`mapping.fleet_heading.View`
    list (``worker``, ``robot``, ``epoch`` as in :class:`PlaneObservations`)."""

    worker: str
    robot: str
    epoch: int
    views: bytes

    def to_bytes(self) -> bytes:
        """Schema-1 msgpack."""
        d = {"v": SCHEMA, "type": "views", "worker": self.worker, "robot": self.robot, "epoch": self.epoch}
        return msgpack.packb(d | {"views": self.views})


@dataclass(frozen=True)
class NavReport:
    """A robot's registered estimate, from the worker that navigates it (at most every ``nav_publish_s`` of capture
    time per robot): the base serves and publishes it (turned by the fleet's frame) as it does its own.

    Attributes:
        worker, robot, epoch: as in :class:`PlaneObservations` (a stale epoch's report is ignored).
        estimate: :func:`services.map_worker_nav.encode_state` of the :class:`mapping.navigation.NavEstimate`.
    """

    worker: str
    robot: str
    epoch: int
    estimate: bytes

    def to_bytes(self) -> bytes:
        """Schema-1 msgpack."""
        d = {"v": SCHEMA, "type": "nav", "worker": self.worker, "robot": self.robot, "epoch": self.epoch}
        return msgpack.packb(d | {"estimate": self.estimate})


def decode_obs(payload: bytes) -> PlaneObservations | NavReport | HeadingViews:
    """A message of ``<root>/map/obs/<worker>`` (raises :class:`~services.errors.WireError`)."""
    d = _unpack(payload, None)
    if d.get("type") in ("nav", "views"):
        try:
            who = (str(d["worker"]), str(d["robot"]), int(d["epoch"]))
            if d["type"] == "nav":
                return NavReport(*who, bytes(d["estimate"]))
            return HeadingViews(*who, bytes(d["views"]))
        except (KeyError, TypeError, ValueError) as err:
            msg = f"{d['type']} report: malformed: {err!r}"
            raise WireError(msg) from err
    return PlaneObservations.from_bytes(payload)


def decode_work(payload: bytes) -> MapJob | MapControl:
    """A worker's incoming message (raises :class:`~services.errors.WireError`)."""
    d = _unpack(payload, None)
    try:
        kind = d["type"]
        if kind == "job":
            pts = np.frombuffer(d["points"], "<f4")
            if pts.size % 3:
                msg = f"job {d['robot']}#{d['seq']}: {pts.size} floats is not N x 3"
                raise WireError(msg)
            return MapJob(
                str(d["robot"]),
                int(d["seq"]),
                int(d["t_ns"]),
                int(d["epoch"]),
                Pose(*(float(x) for x in d["pose"])),
                pts.reshape(-1, 3),
                bool(d.get("nav", False)),
                int(d.get("lag", 0)),
                str(d.get("nofix", "lost")),
                str(d.get("heading", "")),
                _per_px(d.get("perpx", 0.0)),
            )
        if kind in ("flush", "drop", "adopt", "views", "heading"):
            return MapControl(
                kind,
                str(d.get("robot", "")),
                int(d.get("epoch", 0)),
                bytes(d.get("state", b"")),
                str(d.get("nofix", "lost")),
            )
    except (KeyError, TypeError, ValueError) as err:
        msg = f"map work: malformed: {err!r}"
        raise WireError(msg) from err
    msg = f"map work: unknown type {kind!r}"
    raise WireError(msg)


def _per_px(value: Any) -> float:
    """A job's ``perpx``: a finite number >= 0 (ValueError otherwise, a malformed job)."""
    per_px = float(value)
    if not math.isfinite(per_px) or per_px < 0.0:
        msg = f"perpx must be a finite number >= 0, got {value!r}"
        raise ValueError(msg)
    return per_px


def _unpack(payload: bytes, kind: str | None) -> dict[str, Any]:
    try:
        d = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except (ValueError, msgpack.UnpackException) as err:
        msg = f"map worker message does not decode: {err!r}"
        raise WireError(msg) from err
    if not isinstance(d, dict) or d.get("v") != SCHEMA or (kind is not None and d.get("type") != kind):
        msg = f"not a schema-{SCHEMA} map worker message{f' of type {kind}' if kind else ''}"
        raise WireError(msg)
    return d
