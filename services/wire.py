"""Wire messages of the fleet: one frozen dataclass per message, msgpack with a schema version.

Every message is a msgpack map with ``"v"`` (schema version) and ``"type"``. Arrays travel as little-endian
bytes, never as lists of numbers. Decoding is strict: a payload that is not a map, has another version or type,
lacks a field, is truncated, oversized, inconsistent or holds a non-finite number raises
:class:`~services.errors.WireError` whose message says what was wrong. Unknown extra fields of the same version
are ignored (forward compatibility).

Messages:

* :class:`CloudMsg` one processed frame (cloud schema 1): robot, sequence number, capture time, pose in NED at
  capture time, points in the body frame (N, 3) float32, laser index (N,) uint8, quality (N,) float32,
  optional uv (N, 2).
* :class:`StripeMsg` the same frame as the sensor measured it (cloud schema 2, the ROV's default): per laser
  the stripe's pixel columns as runs, the sub-pixel row of each column in fixed point, the quality in a byte,
  and the fingerprint of the calibration it was measured with; the base station triangulates it
  (:meth:`StripeMsg.to_cloud`). :func:`decode_cloud` reads either schema.
* :class:`CalibMsg` a robot's calibration (the mapping of :meth:`lrsensor.Calibration.to_dict`, at top level).
* :class:`StatusMsg` a robot's counters (frames, published, skipped, unplaced), published while it runs.

Layout: this module holds the decode entry of the clouds and the two small messages, and re-exports the rest,
so that ``services.wire`` is the one name callers import. :mod:`services.wire_fields` packs and checks the
fields every message shares (and the pose maps), :mod:`services.wire_cloud` is the schema-1 cloud and
:mod:`services.wire_stripe` the compact schema-2 cloud with the calibration fingerprint; its docstring says why
the compact cloud carries the measurement rather than quantized points. The schema-1 cloud has a module of its
own because the schema-2 cloud triangulates into it: kept here, it would make this module and
:mod:`services.wire_stripe` import each other.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from lrsensor.calibration import Calibration
from lrsensor.errors import CalibrationFileError

from .errors import WireError
from .keys import check_robot_name
from .wire_cloud import CloudMsg
from .wire_fields import (
    ENCODING,
    MAX_PAYLOAD_BYTES,
    MAX_POINTS,
    SCHEMA_VERSION,
    _field,
    _int_field,
    _pack,
    _robot_field,
    _unpack,
    pose_from_map,
    pose_to_map,
)
from .wire_stripe import (
    FINGERPRINT_BYTES,
    MAX_COLUMN,
    MAX_RUN,
    ROW_SCALE,
    STRIPE_SCHEMA_VERSION,
    StripeMsg,
    calibration_fingerprint,
)

__all__ = [
    "CLOUD_SCHEMAS",
    "ENCODING",
    "FINGERPRINT_BYTES",
    "MAX_COLUMN",
    "MAX_PAYLOAD_BYTES",
    "MAX_POINTS",
    "MAX_RUN",
    "ROW_SCALE",
    "SCHEMA_VERSION",
    "STATES",
    "STRIPE_SCHEMA_VERSION",
    "AnyCloud",
    "CalibMsg",
    "CloudMsg",
    "StatusMsg",
    "StripeMsg",
    "calibration_fingerprint",
    "decode_cloud",
    "pose_from_map",
    "pose_to_map",
]

#: Cloud schemas this build reads (:func:`decode_cloud`); schema 1 for every other message type.
CLOUD_SCHEMAS = (SCHEMA_VERSION, STRIPE_SCHEMA_VERSION)
STATES = ("starting", "running", "done", "stopped", "failed")


#: A cloud message of either schema.
AnyCloud = CloudMsg | StripeMsg


def decode_cloud(data: bytes | bytearray | memoryview) -> CloudMsg | StripeMsg:
    """Decode a cloud of either schema: :class:`CloudMsg` (``v`` 1) or :class:`StripeMsg` (``v`` 2)."""
    obj = _unpack(data, CloudMsg.TYPE, CLOUD_SCHEMAS)
    if obj["v"] == STRIPE_SCHEMA_VERSION:
        return StripeMsg._from_map(obj)
    return CloudMsg._from_map(obj)


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
        skipped: frames skipped because the pose source gave no pose at their capture time (outside its
            span, or a silent link).
        failed: frames that could not be processed (bad image, extractor error).
        last_seq: sequence number of the last published cloud, -1 if none.
        unplaced: clouds published whose pose had no horizontal fix (optional on the wire, 0 when absent).
        delivery: the outbox's link-budget counters (``live``, ``queued``, ``forwarded``, ``dropped_budget``,
            ``released``, ``reloaded``; see :class:`services.delivery.DeliveryCounters` and
            docs/reliability.md), optional on the wire: None from a ROV without an outbox or from before the
            counters existed.
    """

    robot: str
    t_ns: int
    state: str
    frames: int = 0
    published: int = 0
    skipped: int = 0
    failed: int = 0
    last_seq: int = -1
    unplaced: int = 0
    delivery: Mapping[str, int] | None = None

    TYPE = "status"
    _COUNTERS = ("frames", "published", "skipped", "failed")
    #: The optional delivery counters, each a non-negative integer; all or none are sent.
    DELIVERY = ("live", "queued", "forwarded", "dropped_budget", "released", "reloaded")

    def to_bytes(self) -> bytes:
        """Encode as msgpack."""
        check_robot_name(self.robot)
        if self.state not in STATES:
            msg = f"status of {self.robot}: unknown state {self.state!r}; one of {STATES}"
            raise WireError(msg)
        obj: dict[str, Any] = {"v": SCHEMA_VERSION, "type": self.TYPE, "robot": self.robot, "t_ns": int(self.t_ns)}
        obj["state"] = self.state
        for name in (*self._COUNTERS, "last_seq", "unplaced"):
            obj[name] = int(getattr(self, name))
        if self.delivery is not None:
            obj["delivery"] = {name: int(self.delivery[name]) for name in self.DELIVERY}
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
        unplaced = _int_field(obj, "unplaced", where) if "unplaced" in obj else 0
        delivery: dict[str, int] | None = None
        if "delivery" in obj:  # absent from a ROV without an outbox, or from before the counters
            raw = obj["delivery"]
            if not isinstance(raw, Mapping):
                msg = f"{where}: 'delivery' is not a mapping"
                raise WireError(msg)
            delivery = {name: _int_field(raw, name, f"{where} delivery") for name in cls.DELIVERY}
        return cls(robot, t_ns, state, frames, published, skipped, failed, last_seq, unplaced, delivery)

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
            "unplaced": self.unplaced,
            **({} if self.delivery is None else {name: int(self.delivery[name]) for name in self.DELIVERY}),
        }
