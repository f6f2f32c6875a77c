"""What the fleet looks like in Foxglove's well-known schemas (``foxglove.messages``, foxglove-sdk).

One place turns the fleet's values into the messages the recording (:mod:`services.record`) and the live view
(:mod:`services.liveview`) write, so both show the same scene (:class:`FoxgloveSink` logs them for a
:class:`~services.fleet_tap.FleetTap`):

* a cloud -> ``foxglove.PointCloud`` in the robot's body frame ``<robot>/base_link`` (x, y, z float32,
  metres; a ``laser`` uint8 field), stamped with the capture time;
* a pose with a horizontal position -> ``foxglove.FrameTransform`` from ``ned`` (the fleet's NED frame: x north,
  y east, z down) to ``<robot>/base_link``; a pose without one places nothing (never at north = east = 0);
* the map's planes -> ``foxglove.SceneUpdate`` in ``ned``: one entity per plane id (``plane/<id>``), a
  rectangle of the plane's extent drawn as two triangles; a removed or merged plane becomes a deletion.

foxglove-sdk is imported lazily: the ROV-only install does not need it.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose, quat_from_R

from .errors import ServiceError
from .wire import CloudMsg

#: The frame id of the fleet's NED frame in Foxglove scenes.
NED_FRAME = "ned"

#: RGBA of the map's planes (translucent orange).
PLANE_RGBA = (1.0, 0.55, 0.1, 0.45)


def body_frame(robot: str) -> str:
    """The Foxglove frame id of a robot's body frame (REP 105 style ``<robot>/base_link``)."""
    return f"{robot}/base_link"


def _stamp(t_ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=int(t_ns // 1_000_000_000), nsec=int(t_ns % 1_000_000_000))


def point_cloud(robot: str, t_ns: int, points_body: np.ndarray, laser: np.ndarray) -> Any:
    """``foxglove.PointCloud`` of one cloud.

    Args:
        robot: the robot's name (frame ``<robot>/base_link``).
        t_ns: capture time, ns since the Unix epoch.
        points_body: (N, 3) points in the body frame, metres.
        laser: (N,) laser index of each point (0 top, 1 bottom).
    """
    from foxglove.messages import (
        PackedElementField,
        PackedElementFieldNumericType,
        PointCloud,
        Quaternion,
        Vector3,
    )
    from foxglove.messages import Pose as FgPose

    n = int(points_body.shape[0])
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("laser", "u1")])
    rec["x"], rec["y"], rec["z"] = (np.asarray(points_body, dtype=np.float32)[:, i] for i in range(3))
    rec["laser"] = np.asarray(laser, dtype=np.uint8)
    f32, u8 = PackedElementFieldNumericType.Float32, PackedElementFieldNumericType.Uint8
    fields = [PackedElementField(name=c, offset=4 * i, type=f32) for i, c in enumerate("xyz")]
    fields.append(PackedElementField(name="laser", offset=12, type=u8))
    return PointCloud(
        timestamp=_stamp(t_ns),
        frame_id=body_frame(robot),
        pose=FgPose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
        point_stride=rec.dtype.itemsize,
        fields=fields,
        data=rec.tobytes(),
    )


def has_fix(pose: Pose) -> bool:
    """True when the pose has a horizontal position (north and east are numbers)."""
    return math.isfinite(pose.north_m) and math.isfinite(pose.east_m)


def robot_transform(robot: str, t_ns: int, pose: Pose) -> Any | None:
    """``foxglove.FrameTransform`` ``ned`` -> ``<robot>/base_link`` at ``t_ns``; None without a horizontal fix."""
    if not has_fix(pose):
        return None
    from foxglove.messages import FrameTransform, Quaternion, Vector3

    w, x, y, z = (float(v) for v in quat_from_R(pose.R_ned_from_body))
    return FrameTransform(
        timestamp=_stamp(t_ns),
        parent_frame_id=NED_FRAME,
        child_frame_id=body_frame(robot),
        translation=Vector3(x=float(pose.north_m), y=float(pose.east_m), z=float(pose.down_m)),
        rotation=Quaternion(x=x, y=y, z=z, w=w),
    )


def plane_entity_id(plane_id: int) -> str:
    """The scene entity id of a map plane."""
    return f"plane/{int(plane_id)}"


def map_scene(planes: Iterable[Mapping[str, Any]], t_ns: int) -> Any:
    """``foxglove.SceneUpdate`` of map planes as served on the map keys (``PlaneRecord`` JSON or removals).

    A plane dict with ``extent.corners`` (4 corners in NED, metres) becomes a rectangle entity; a dict with
    ``"removed": True`` becomes a deletion of its entity.
    """
    from foxglove.messages import (
        Color,
        Point3,
        SceneEntity,
        SceneEntityDeletion,
        SceneEntityDeletionType,
        SceneUpdate,
        TriangleListPrimitive,
    )

    r, g, b, a = PLANE_RGBA
    entities, deletions = [], []
    for plane in planes:
        pid = plane_entity_id(int(plane["id"]))
        if plane.get("removed"):
            deletions.append(
                SceneEntityDeletion(timestamp=_stamp(t_ns), type=SceneEntityDeletionType.MatchingId, id=pid)
            )
            continue
        corners = plane.get("extent", {}).get("corners") or []
        if len(corners) != 4:
            continue
        c = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in corners]
        tri = TriangleListPrimitive(points=[c[0], c[1], c[2], c[0], c[2], c[3]], color=Color(r=r, g=g, b=b, a=a))
        entities.append(SceneEntity(timestamp=_stamp(t_ns), frame_id=NED_FRAME, id=pid, triangles=[tri]))
    return SceneUpdate(deletions=deletions, entities=entities)


def track_scene(robot: str, positions_ned: np.ndarray, t_ns: int) -> Any:
    """``foxglove.SceneUpdate`` with the entity ``track/<robot>``: a line through (N, 3) NED positions, metres."""
    from foxglove.messages import Color, LinePrimitive, LinePrimitiveLineType, Point3, SceneEntity, SceneUpdate

    pts = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in np.asarray(positions_ned, dtype=float)]
    line = LinePrimitive(
        type=LinePrimitiveLineType.LineStrip,
        thickness=2.0,
        scale_invariant=True,
        points=pts,
        color=Color(r=0.2, g=0.7, b=1.0, a=1.0),
    )
    entity = SceneEntity(timestamp=_stamp(t_ns), frame_id=NED_FRAME, id=f"track/{robot}", lines=[line])
    return SceneUpdate(entities=[entity])


#: Schema of the raw wire channels of a recording: msgpack, described in docs/conventions.md.
RAW_SCHEMA_NAME = "lrsensor.cloud"
RAW_SCHEMA_ENCODING = "lrsensor-msgpack"
RAW_MESSAGE_ENCODING = "msgpack"
#: The channel of frame transforms (Foxglove's convention).
TF_TOPIC = "/tf"
#: At most this many positions per robot track (older ones are thinned out).
TRACK_POINTS = 2000


class FoxgloveUnavailableError(ServiceError):
    """foxglove-sdk is not installed."""


def import_foxglove() -> Any:
    """The ``foxglove`` module, or :class:`FoxgloveUnavailableError` naming the extra to install."""
    try:
        import foxglove
    except ImportError as err:
        msg = f"recording and the live view need foxglove-sdk (pip install 'lrsensor[record]'): {err}"
        raise FoxgloveUnavailableError(msg) from err
    return foxglove


class FoxgloveSink:
    """Logs what a :class:`~services.fleet_tap.FleetTap` sees on a foxglove ``Context`` (its sinks: an MCAP
    file, a WebSocket server, or both).

    Topics: ``/<root>/<robot>/points`` (``foxglove.PointCloud``), ``/tf`` (``foxglove.FrameTransform``),
    ``/<root>/map`` (``foxglove.SceneUpdate``); with ``raw``: ``<root>/<robot>/cloud`` (wire payloads,
    msgpack) and ``<root>/<robot>/calib`` (JSON); with ``tracks``: ``/<root>/tracks`` (``SceneUpdate``);
    with ``status``: ``/<root>/status`` (JSON).

    Args:
        context: the ``foxglove.Context`` to log on.
        root: the fleet's key root ``<prefix>/<fleet>``.
        raw: log the wire payloads and calibrations (a replayable recording).
        tracks: log the robots' tracks.
        status: log the base station's status.
    """

    def __init__(self, context: Any, root: str, *, raw: bool, tracks: bool = False, status: bool = False) -> None:
        foxglove = import_foxglove()
        from foxglove.channels import FrameTransformChannel, SceneUpdateChannel

        self._fg = foxglove
        self._ctx = context
        self.root = root
        self.raw = raw
        self._raw_schema = foxglove.Schema(
            name=RAW_SCHEMA_NAME, encoding=RAW_SCHEMA_ENCODING, data=b"lrsensor cloud, docs/conventions.md"
        )
        self._tf = FrameTransformChannel(TF_TOPIC, context=context)
        self._map = SceneUpdateChannel(f"/{root}/map", context=context)
        self._tracks_channel = SceneUpdateChannel(f"/{root}/tracks", context=context) if tracks else None
        self._status_channel = (
            foxglove.Channel(f"/{root}/status", message_encoding="json", context=context) if status else None
        )
        self._tracks: dict[str, list[tuple[float, float, float]]] = {}
        self._channels: dict[str, Any] = {}

    def _channel(self, topic: str, kind: str) -> Any:
        ch = self._channels.get(topic)
        if ch is None:
            if kind == "points":
                from foxglove.channels import PointCloudChannel

                ch = PointCloudChannel(topic, context=self._ctx)
            elif kind == "json":
                ch = self._fg.Channel(topic, message_encoding="json", context=self._ctx)
            else:
                ch = self._fg.Channel(
                    topic, message_encoding=RAW_MESSAGE_ENCODING, schema=self._raw_schema, context=self._ctx
                )
            self._channels[topic] = ch
        return ch

    def raw_cloud(self, robot: str, payload: bytes, log_ns: int) -> None:
        """Log the wire payload on ``<root>/<robot>/cloud`` (with ``raw``)."""
        if self.raw:
            self._channel(f"{self.root}/{robot}/cloud", "raw").log(payload, log_time=log_ns)

    def calibration(self, robot: str, calibration: Calibration, log_ns: int) -> None:
        """Log the calibration's file form on ``<root>/<robot>/calib`` (with ``raw``)."""
        if self.raw:
            self._channel(f"{self.root}/{robot}/calib", "json").log(calibration.to_dict(), log_time=log_ns)

    def cloud(self, msg: CloudMsg, log_ns: int) -> None:
        """Log the point cloud, the robot's transform (with a fix) and its track."""
        pc = point_cloud(msg.robot, msg.t_ns, msg.points_body, msg.laser)
        self._channel(f"/{self.root}/{msg.robot}/points", "points").log(pc, log_time=log_ns)
        tf = robot_transform(msg.robot, msg.t_ns, msg.pose)
        if tf is not None:
            self._tf.log(tf, log_time=log_ns)
        if self._tracks_channel is not None and has_fix(msg.pose):
            track = self._tracks.setdefault(msg.robot, [])
            track.append((msg.pose.north_m, msg.pose.east_m, msg.pose.down_m))
            if len(track) > TRACK_POINTS:
                del track[1::2]  # keep the whole dive's shape at half the resolution
            self._tracks_channel.log(track_scene(msg.robot, np.asarray(track), msg.t_ns), log_time=log_ns)

    def map_update(self, planes: list[dict[str, Any]], t_ns: int, log_ns: int) -> None:
        """Log the planes as a scene update."""
        self._map.log(map_scene(planes, t_ns), log_time=log_ns)

    def status(self, data: dict[str, Any], log_ns: int) -> None:
        """Log the base station's status (with ``status``)."""
        if self._status_channel is not None:
            self._status_channel.log(data, log_time=log_ns)
