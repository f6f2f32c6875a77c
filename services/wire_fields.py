"""The packing and field checks every wire message of :mod:`services.wire` shares.

A payload is a msgpack map with ``"v"`` (schema version) and ``"type"``; :func:`_unpack` refuses one that is not
bytes, is empty, oversized, truncated, followed by trailing bytes, not a map, or of another version or type, and
the ``_*_field`` checks refuse a missing field or one of the wrong type or range, each with a
:class:`~services.errors.WireError` whose message names the field. The pose maps (:func:`pose_to_map`,
:func:`pose_from_map`) and the header every cloud schema carries alike (robot, seq, times, pose:
:func:`_checked_header`, :func:`_header_from_map`) live here too, so that the two cloud schemas
(:mod:`services.wire_cloud`, :mod:`services.wire_stripe`) check them with one code.

The helpers keep their leading underscore: they are shared by the ``services.wire*`` modules only, not an API;
:mod:`services.wire` re-exports the public names.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import msgpack

from lrsensor.frames import Pose

from .errors import KeyNameError, WireError
from .keys import check_robot_name

#: Schema version of every message but the compact cloud (:data:`services.wire_stripe.STRIPE_SCHEMA_VERSION`).
SCHEMA_VERSION = 1
#: The Zenoh encoding string of every message payload.
ENCODING = "application/msgpack"
#: Largest accepted payload, bytes (a 1920-column two-laser cloud is about 100 kB).
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
#: Largest accepted number of points in one cloud.
MAX_POINTS = 500_000
_MAX_INT64 = 2**63 - 1
_POSE_FIELDS = ("north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "yaw_rad")


def _pack(obj: Mapping[str, Any]) -> bytes:
    out: bytes = msgpack.packb(obj, use_bin_type=True)
    return out


def _unpack(
    data: bytes | bytearray | memoryview, expected_type: str, versions: tuple[int, ...] = (SCHEMA_VERSION,)
) -> Mapping[str, Any]:
    """Unpack a payload into its top-level map and check version (one of ``versions``) and type."""
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
    if version not in versions or isinstance(version, bool):
        readable = ", ".join(str(v) for v in versions)
        msg = f"{expected_type}: unsupported schema version {version!r} (this build reads {readable})"
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


def _bytes_field(
    obj: Mapping[str, Any], key: str, where: str, expected_len: int, what: str = "the declared point count"
) -> bytes:
    v = _field(obj, key, where)
    if not isinstance(v, bytes):
        msg = f"{where}: field {key!r} must be binary, got {type(v).__name__}"
        raise WireError(msg)
    if len(v) != expected_len:
        msg = f"{where}: field {key!r} has {len(v)} bytes, expected {expected_len} for {what}"
        raise WireError(msg)
    return v


def pose_to_map(pose: Pose) -> dict[str, float | None]:
    """A pose as a msgpack/JSON-ready map with named fields (metres, radians); a pose without a horizontal
    fix (``north_m`` and ``east_m`` both NaN, see :mod:`services.posetrack`) has them None (null)."""
    out: dict[str, float | None] = {name: float(getattr(pose, name)) for name in _POSE_FIELDS}
    if math.isnan(pose.north_m) and math.isnan(pose.east_m):
        out["north_m"] = out["east_m"] = None
    return out


def _checked_header(robot: str, seq: int, t_ns: int, sent_ns: int, pose: Pose) -> tuple[str, dict[str, Any]]:
    """What every cloud schema encodes alike, checked: the robot's name, the counters within int64 and the pose
    as its wire map; returns the message's name for error messages and that map."""
    check_robot_name(robot)
    where = f"cloud {robot}#{seq}"
    for name, value in (("seq", seq), ("t_ns", t_ns), ("sent_ns", sent_ns)):
        if not 0 <= int(value) <= _MAX_INT64:
            msg = f"{where}: {name} = {value} is outside [0, 2^63)"
            raise WireError(msg)
    pose_map = pose_to_map(pose)
    _check_pose_map(pose_map, where)
    return where, pose_map


def _header_from_map(obj: Mapping[str, Any]) -> tuple[str, int, str, int, int, Pose]:
    """What every cloud schema decodes alike: ``(robot, seq, where, t_ns, sent_ns, pose)``, each checked;
    ``where`` names the message in error messages (the twin of :func:`_checked_header`)."""
    robot = _robot_field(obj, "cloud")
    seq = _int_field(obj, "seq", f"cloud from {robot}")
    where = f"cloud {robot}#{seq}"
    t_ns = _int_field(obj, "t_ns", where)
    sent_ns = _int_field(obj, "sent_ns", where) if "sent_ns" in obj else 0
    pose = pose_from_map(_field(obj, "pose", where), where)
    return robot, seq, where, t_ns, sent_ns, pose


def _check_pose_map(pose: Mapping[str, float | None], where: str) -> None:
    """Refuse a pose map that :func:`pose_from_map` would refuse (non-finite, or only one of north/east)."""
    if (pose["north_m"] is None) != (pose["east_m"] is None) or not all(
        math.isfinite(v) for v in pose.values() if v is not None
    ):
        msg = f"{where}: pose is not finite (north_m and east_m may only be unknown together): {pose}"
        raise WireError(msg)


def pose_from_map(obj: Any, where: str) -> Pose:
    """Validate and build a pose from :func:`pose_to_map`'s map; raises :class:`WireError`.

    ``north_m`` and ``east_m`` both null: no horizontal fix, NaN in the pose; one of them null is refused.
    """
    if not isinstance(obj, dict):
        msg = f"{where}: field 'pose' must be a map, got {type(obj).__name__}"
        raise WireError(msg)
    unknown = [name for name in ("north_m", "east_m") if name in obj and obj[name] is None]
    if len(unknown) == 1:
        msg = f"{where}: pose: field {unknown[0]!r} is null but not the other horizontal coordinate"
        raise WireError(msg)
    values = [math.nan if name in unknown else _float_field(obj, name, f"{where}: pose") for name in _POSE_FIELDS]
    return Pose(*values)
