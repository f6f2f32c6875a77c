"""The schema-1 cloud: one processed frame as float32 points in the body frame (:class:`CloudMsg`).

Per point 25 bytes: three float32 coordinates, the laser in a byte, a float32 quality and, optionally, the
float32 pixel ``(u, v)`` it was measured at. The ROV sends it when a scan cannot travel as the compact schema 2
(:mod:`services.wire_stripe`), and the base station turns every schema-2 cloud into one
(:meth:`services.wire_stripe.StripeMsg.to_cloud`). :func:`services.wire.decode_cloud` reads either schema.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose
from lrsensor.scan import Scan

from .errors import WireError
from .wire_fields import (
    MAX_POINTS,
    SCHEMA_VERSION,
    _bytes_field,
    _checked_header,
    _header_from_map,
    _int_field,
    _pack,
    _unpack,
)


@dataclass(frozen=True, eq=False)
class CloudMsg:
    """One processed frame of one robot.

    Attributes:
        robot: robot name (the ``<robot>`` chunk of its keys).
        seq: sequence number, 0, 1, 2, ... per robot, never reused.
        t_ns: capture time of the frame, ns since the Unix epoch.
        pose: vehicle pose in NED at ``t_ns`` (interpolated from the IMU); ``north_m``/``east_m`` NaN (null on
            the wire) when the pose source had no horizontal fix then.
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
        where, pose = _checked_header(self.robot, self.seq, self.t_ns, self.sent_ns, self.pose)
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
        """Decode and validate a schema-1 cloud; raises :class:`WireError` naming what was wrong (a schema-2
        cloud too: :func:`decode_cloud` reads both)."""
        return cls._from_map(_unpack(data, cls.TYPE))

    @classmethod
    def _from_map(cls, obj: Mapping[str, Any]) -> CloudMsg:
        robot, seq, where, t_ns, sent_ns, pose = _header_from_map(obj)
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
