"""Wire messages of the fleet: one frozen dataclass per message, msgpack with a schema version.

Every message is a msgpack map with ``"v"`` (schema version, :data:`SCHEMA_VERSION`) and ``"type"``. Arrays
travel as little-endian bytes, never as lists of numbers. Decoding is strict: a payload that is not a map,
has another version or type, lacks a field, is truncated, oversized, inconsistent or holds a non-finite
number raises :class:`~services.errors.WireError` whose message says what was wrong. Unknown extra fields of
the same version are ignored (forward compatibility).

Messages:

* :class:`CloudMsg` one processed frame: robot, sequence number, capture time, pose in NED at capture time,
  points in the body frame (N, 3) float32, laser index (N,) uint8, quality (N,) float32, optional uv (N, 2).
* :class:`CalibMsg` a robot's calibration (the mapping of :meth:`lrsensor.Calibration.to_dict`, at top level).
* :class:`StatusMsg` a robot's counters (frames, published, skipped), published while it runs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray

from lrsensor.calibration import Calibration
from lrsensor.errors import CalibrationFileError
from lrsensor.frames import Pose
from lrsensor.scan import Scan

from .errors import KeyNameError, WireError
from .keys import check_robot_name

SCHEMA_VERSION = 1
#: The Zenoh encoding string of every message payload.
ENCODING = "application/msgpack"
#: Largest accepted payload, bytes (a 1920-column two-laser cloud is about 100 kB).
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
#: Largest accepted number of points in one cloud.
MAX_POINTS = 500_000
_MAX_INT64 = 2**63 - 1
_POSE_FIELDS = ("north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "yaw_rad")
STATES = ("starting", "running", "done", "stopped", "failed")


# --------------------------------------------------------------------------- helpers
def _pack(obj: Mapping[str, Any]) -> bytes:
    out: bytes = msgpack.packb(obj, use_bin_type=True)
    return out


def _unpack(data: bytes | bytearray | memoryview, expected_type: str) -> Mapping[str, Any]:
    """Unpack a payload into its top-level map and check version and type."""
    if not isinstance(data, bytes | bytearray | memoryview):
        msg = f"{expected_type}: payload must be bytes, got {type(data).__name__}"
        raise WireError(msg)
    raw = bytes(data)
    if len(raw) > MAX_PAYLOAD_BYTES:
        msg = f"{expected_type}: payload of {len(raw)} bytes is larger than the {MAX_PAYLOAD_BYTES} accepted"
        raise WireError(msg)
    if not raw:
        msg = f"{expected_type}: empty payload"
        raise WireError(msg)
    try:
        obj = msgpack.unpackb(
            raw,
            raw=False,
            strict_map_key=True,
            max_bin_len=MAX_PAYLOAD_BYTES,
            max_str_len=MAX_PAYLOAD_BYTES,
            max_array_len=100_000,
            max_map_len=10_000,
        )
    except msgpack.ExtraData as err:
        msg = f"{expected_type}: trailing bytes after the message ({len(err.extra)} extra)"
        raise WireError(msg) from err
    except (ValueError, msgpack.UnpackException, TypeError, RecursionError) as err:
        msg = f"{expected_type}: payload is not valid msgpack (truncated or garbage): {err}"
        raise WireError(msg) from err
    if not isinstance(obj, dict):
        msg = f"{expected_type}: top level must be a map, got {type(obj).__name__}"
        raise WireError(msg)
    version = obj.get("v")
    if version != SCHEMA_VERSION or isinstance(version, bool):
        msg = f"{expected_type}: unsupported schema version {version!r} (this build reads {SCHEMA_VERSION})"
        raise WireError(msg)
    kind = obj.get("type")
    if kind != expected_type:
        msg = f"{expected_type}: message type is {kind!r}, expected {expected_type!r}"
        raise WireError(msg)
    return obj


def _field(obj: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in obj:
        msg = f"{where}: missing field {key!r}"
        raise WireError(msg)
    return obj[key]


def _int_field(obj: Mapping[str, Any], key: str, where: str, minimum: int = 0, maximum: int = _MAX_INT64) -> int:
    v = _field(obj, key, where)
    if not isinstance(v, int) or isinstance(v, bool):
        msg = f"{where}: field {key!r} must be an integer, got {type(v).__name__}"
        raise WireError(msg)
    if not minimum <= v <= maximum:
        msg = f"{where}: field {key!r} = {v} is outside [{minimum}, {maximum}]"
        raise WireError(msg)
    return v


def _float_field(obj: Mapping[str, Any], key: str, where: str) -> float:
    v = _field(obj, key, where)
    if not isinstance(v, int | float) or isinstance(v, bool):
        msg = f"{where}: field {key!r} must be a number, got {type(v).__name__}"
        raise WireError(msg)
    f = float(v)
    if not math.isfinite(f):
        msg = f"{where}: field {key!r} is not finite ({f})"
        raise WireError(msg)
    return f


def _robot_field(obj: Mapping[str, Any], where: str) -> str:
    robot = _field(obj, "robot", where)
    if not isinstance(robot, str):
        msg = f"{where}: field 'robot' must be a string, got {type(robot).__name__}"
        raise WireError(msg)
    try:
        return check_robot_name(robot)
    except KeyNameError as err:
        msg = f"{where}: {err}"
        raise WireError(msg) from err


def _bytes_field(obj: Mapping[str, Any], key: str, where: str, expected_len: int) -> bytes:
    v = _field(obj, key, where)
    if not isinstance(v, bytes):
        msg = f"{where}: field {key!r} must be binary, got {type(v).__name__}"
        raise WireError(msg)
    if len(v) != expected_len:
        msg = f"{where}: field {key!r} has {len(v)} bytes, expected {expected_len} for the declared point count"
        raise WireError(msg)
    return v


def pose_to_map(pose: Pose) -> dict[str, float]:
    """A pose as a msgpack/JSON-ready map with named fields (metres, radians)."""
    return {name: float(getattr(pose, name)) for name in _POSE_FIELDS}


def pose_from_map(obj: Any, where: str) -> Pose:
    """Validate and build a pose from :func:`pose_to_map`'s map; raises :class:`WireError`."""
    if not isinstance(obj, dict):
        msg = f"{where}: field 'pose' must be a map, got {type(obj).__name__}"
        raise WireError(msg)
    values = [_float_field(obj, name, f"{where}: pose") for name in _POSE_FIELDS]
    return Pose(*values)


# --------------------------------------------------------------------------- CloudMsg
@dataclass(frozen=True, eq=False)
class CloudMsg:
    """One processed frame of one robot.

    Attributes:
        robot: robot name (the ``<robot>`` chunk of its keys).
        seq: sequence number, 0, 1, 2, ... per robot, never reused.
        t_ns: capture time of the frame, ns since the Unix epoch.
        pose: vehicle pose in NED at ``t_ns`` (interpolated from the IMU).
        points_body: (N, 3) float32, body frame, metres.
        laser: (N,) uint8, laser index of each point.
        quality: (N,) float32, extractor confidence of each point.
        uv: (N, 2) float32 pixel coordinates of each point, or None.
        sent_ns: publication time, ns since the Unix epoch (0 if unknown); for latency figures.
    """

    robot: str
    seq: int
    t_ns: int
    pose: Pose
    points_body: NDArray[np.float32]
    laser: NDArray[np.uint8]
    quality: NDArray[np.float32]
    uv: NDArray[np.float32] | None = None
    sent_ns: int = 0

    TYPE = "cloud"

    def __post_init__(self) -> None:
        n = self.points_body.shape[0] if self.points_body.ndim == 2 else -1
        where = f"cloud {self.robot}#{self.seq}"
        if self.points_body.shape != (n, 3) or self.laser.shape != (n,) or self.quality.shape != (n,):
            msg = (
                f"{where}: inconsistent arrays: points {self.points_body.shape}, laser {self.laser.shape}, "
                f"quality {self.quality.shape}"
            )
            raise WireError(msg)
        if self.uv is not None and self.uv.shape != (n, 2):
            msg = f"{where}: uv has shape {self.uv.shape}, expected ({n}, 2)"
            raise WireError(msg)
        if n > MAX_POINTS:
            msg = f"{where}: {n} points, more than the {MAX_POINTS} a cloud may carry"
            raise WireError(msg)

    def __len__(self) -> int:
        return int(self.points_body.shape[0])

    @classmethod
    def from_scan(
        cls, robot: str, seq: int, t_ns: int, pose: Pose, scan: Scan, with_uv: bool = True, sent_ns: int = 0
    ) -> CloudMsg:
        """Build the message of a scan (float64 arrays are narrowed to float32)."""
        if np.any(scan.laser < 0) or np.any(scan.laser > 255):
            msg = f"cloud {robot}#{seq}: laser indices must fit in uint8"
            raise WireError(msg)
        return cls(
            robot=robot,
            seq=seq,
            t_ns=t_ns,
            pose=pose,
            points_body=np.ascontiguousarray(scan.points, dtype=np.float32),
            laser=np.ascontiguousarray(scan.laser, dtype=np.uint8),
            quality=np.ascontiguousarray(scan.quality, dtype=np.float32),
            uv=np.ascontiguousarray(scan.uv, dtype=np.float32) if with_uv else None,
            sent_ns=sent_ns,
        )

    def with_sent_ns(self, sent_ns: int) -> CloudMsg:
        """A copy stamped with its publication time."""
        return CloudMsg(
            self.robot, self.seq, self.t_ns, self.pose, self.points_body, self.laser, self.quality, self.uv, sent_ns
        )

    def to_bytes(self) -> bytes:
        """Encode as msgpack (arrays as little-endian bytes)."""
        check_robot_name(self.robot)
        where = f"cloud {self.robot}#{self.seq}"
        for name, value in (("seq", self.seq), ("t_ns", self.t_ns), ("sent_ns", self.sent_ns)):
            if not 0 <= int(value) <= _MAX_INT64:
                msg = f"{where}: {name} = {value} is outside [0, 2^63)"
                raise WireError(msg)
        pose = pose_to_map(self.pose)
        if not all(math.isfinite(v) for v in pose.values()):
            msg = f"{where}: pose is not finite: {pose}"
            raise WireError(msg)
        if not (np.all(np.isfinite(self.points_body)) and np.all(np.isfinite(self.quality))):
            msg = f"{where}: points or quality hold non-finite values"
            raise WireError(msg)
        obj: dict[str, Any] = {
            "v": SCHEMA_VERSION,
            "type": self.TYPE,
            "robot": self.robot,
            "seq": int(self.seq),
            "t_ns": int(self.t_ns),
            "sent_ns": int(self.sent_ns),
            "pose": pose,
            "n": len(self),
            "points": self.points_body.astype("<f4", copy=False).tobytes(),
            "laser": self.laser.astype("u1", copy=False).tobytes(),
            "quality": self.quality.astype("<f4", copy=False).tobytes(),
            "uv": None if self.uv is None else self.uv.astype("<f4", copy=False).tobytes(),
        }
        return _pack(obj)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> CloudMsg:
        """Decode and validate; raises :class:`WireError` naming what was wrong."""
        obj = _unpack(data, cls.TYPE)
        robot = _robot_field(obj, "cloud")
        seq = _int_field(obj, "seq", f"cloud from {robot}")
        where = f"cloud {robot}#{seq}"
        t_ns = _int_field(obj, "t_ns", where)
        sent_ns = _int_field(obj, "sent_ns", where) if "sent_ns" in obj else 0
        pose = pose_from_map(_field(obj, "pose", where), where)
        n = _int_field(obj, "n", where, maximum=MAX_POINTS)
        points = np.frombuffer(_bytes_field(obj, "points", where, 12 * n), dtype="<f4").reshape(n, 3)
        laser = np.frombuffer(_bytes_field(obj, "laser", where, n), dtype="u1")
        quality = np.frombuffer(_bytes_field(obj, "quality", where, 4 * n), dtype="<f4")
        uv_raw = obj.get("uv")
        uv = None if uv_raw is None else np.frombuffer(_bytes_field(obj, "uv", where, 8 * n), "<f4").reshape(n, 2)
        if not np.all(np.isfinite(points)):
            bad = int(np.count_nonzero(~np.all(np.isfinite(points), axis=1)))
            msg = f"{where}: {bad} of {n} points are not finite"
            raise WireError(msg)
        if not np.all(np.isfinite(quality)):
            msg = f"{where}: quality holds non-finite values"
            raise WireError(msg)
        if uv is not None and not np.all(np.isfinite(uv)):
            msg = f"{where}: uv holds non-finite values"
            raise WireError(msg)
        return cls(robot, seq, t_ns, pose, points, laser, quality, uv, sent_ns)


# --------------------------------------------------------------------------- CalibMsg
@dataclass(frozen=True)
class CalibMsg:
    """A robot's calibration (served by the robot and by the base station's fleet store).

    On the wire the calibration file's own mapping (``Calibration.to_dict``: ``camera``, ``R_cam_from_body``,
    ``t_cam_from_body``, ``lasers``, ...) is the top level of the msgpack map, next to ``v``, ``type`` and
    ``robot``: any msgpack reader gets the calibration as the file format of CONVENTIONS describes it.
    """

    robot: str
    calibration: Calibration

    TYPE = "calib"

    def to_bytes(self) -> bytes:
        """Encode as msgpack: the calibration mapping plus ``v``, ``type`` and ``robot``."""
        check_robot_name(self.robot)
        obj = self.calibration.to_dict()
        obj.update({"v": SCHEMA_VERSION, "type": self.TYPE, "robot": self.robot})
        return _pack(obj)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> CalibMsg:
        """Decode and validate (the calibration with the one validator of ``lrsensor.calibration``)."""
        obj = _unpack(data, cls.TYPE)
        robot = _robot_field(obj, "calib")
        try:
            calib = Calibration.from_dict(obj, f"calib of {robot}")
        except CalibrationFileError as err:
            msg = f"calib of {robot}: invalid calibration: {err}"
            raise WireError(msg) from err
        return cls(robot, calib)


# --------------------------------------------------------------------------- StatusMsg
@dataclass(frozen=True)
class StatusMsg:
    """A robot's own counters, published while it runs and once when it ends.

    Attributes:
        robot: robot name.
        t_ns: time of the report, ns since the Unix epoch.
        state: one of :data:`STATES`.
        frames: frames read from the source.
        published: clouds published.
        skipped: frames skipped because their capture time is outside the IMU's span.
        failed: frames that could not be processed (bad image, extractor error).
        last_seq: sequence number of the last published cloud, -1 if none.
    """

    robot: str
    t_ns: int
    state: str
    frames: int = 0
    published: int = 0
    skipped: int = 0
    failed: int = 0
    last_seq: int = -1

    TYPE = "status"
    _COUNTERS = ("frames", "published", "skipped", "failed")

    def to_bytes(self) -> bytes:
        """Encode as msgpack."""
        check_robot_name(self.robot)
        if self.state not in STATES:
            msg = f"status of {self.robot}: unknown state {self.state!r}; one of {STATES}"
            raise WireError(msg)
        obj: dict[str, Any] = {"v": SCHEMA_VERSION, "type": self.TYPE, "robot": self.robot, "t_ns": int(self.t_ns)}
        obj["state"] = self.state
        for name in (*self._COUNTERS, "last_seq"):
            obj[name] = int(getattr(self, name))
        return _pack(obj)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> StatusMsg:
        """Decode and validate."""
        obj = _unpack(data, cls.TYPE)
        robot = _robot_field(obj, "status")
        where = f"status of {robot}"
        t_ns = _int_field(obj, "t_ns", where)
        state = _field(obj, "state", where)
        if state not in STATES:
            msg = f"{where}: unknown state {state!r}; one of {STATES}"
            raise WireError(msg)
        frames, published, skipped, failed = (_int_field(obj, name, where) for name in cls._COUNTERS)
        last_seq = _int_field(obj, "last_seq", where, minimum=-1)
        return cls(robot, t_ns, state, frames, published, skipped, failed, last_seq)

    def to_json_dict(self) -> dict[str, Any]:
        """The counters as a JSON-ready mapping."""
        return {
            "state": self.state,
            "t_ns": self.t_ns,
            "frames": self.frames,
            "published": self.published,
            "skipped": self.skipped,
            "failed": self.failed,
            "last_seq": self.last_seq,
        }
