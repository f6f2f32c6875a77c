"""The compact cloud, schema 2: one frame as the sensor measured it (:class:`StripeMsg`), and the calibration
fingerprint it names (:func:`calibration_fingerprint`).

Why the compact cloud carries the measurement, not quantized points (figures: ``benchmarks/results/wire.md``):
a schema-1 cloud spends 12 bytes a point on float32 coordinates, 8 on float32 uv, 4 on quality and 1 on the
laser, 25 bytes in all (96 kB for a 3840-point frame). What the sensor measured is smaller: per laser at most
one row per image column, the columns mostly consecutive integers (a run costs 9 bytes however long), and a
sub-pixel row that changes little from one column to the next. Schema 2 therefore sends runs
``(laser, first column, length, first row)`` and, inside a run, the row's change from the previous column as an
int16 in 1/4096 px (a larger jump starts a new run): 2 bytes a point, plus 1 byte of quality, 3.1 bytes a point
on the simulator's named scenes, 8x fewer than schema 1. 1/4096 px moves the base's points by at most 0.0022 %
of their range there (the bar is 0.01 %); 1/1024 px would come to about four times that, too close to the bar.
Quantized points with delta coding were the alternative: 0.01 % of a 0.3 m range is 30 um, so three int16
deltas at 10 um overflow at every depth step and cost 6 bytes a point before the quality and the laser; they
also fix the precision in metres where the sensor's own precision is in pixels. The price of sending pixels is
that the base needs the calibration the points were measured with: every schema-2 cloud names it by a 64-bit
fingerprint (:func:`calibration_fingerprint`), and the base station refuses a cloud whose calibration it does
not hold rather than place it wrongly (see :mod:`services.calibbook`). zlib on top would save another 20-80 %
(most on smooth walls), for a layout that outside tools can no longer read with ``numpy.frombuffer`` alone;
8x already puts a robot at 30 Hz under 3 Mbit/s, so the layout stays plain.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from lrsensor.scan import Scan

from .errors import WireError
from .wire_cloud import CloudMsg
from .wire_fields import MAX_POINTS, _bytes_field, _checked_header, _header_from_map, _int_field, _pack, _unpack

#: Schema version of the compact cloud (:class:`StripeMsg`).
STRIPE_SCHEMA_VERSION = 2
#: Fixed-point scale of a stripe's sub-pixel row: rows travel in units of 1/ROW_SCALE pixel.
ROW_SCALE = 4096
#: Bytes of a calibration fingerprint (:func:`calibration_fingerprint`).
FINGERPRINT_BYTES = 8
#: Largest pixel column a stripe may carry (uint16).
MAX_COLUMN = 65_535
#: Largest run (columns); a longer stretch of consecutive columns is split.
MAX_RUN = 65_535
_INT16 = 32_767
_INT32_MIN, _INT32_MAX = -(2**31), 2**31 - 1
#: Significant digits of each number hashed by :func:`calibration_fingerprint`.
_FINGERPRINT_DIGITS = 12


def calibration_fingerprint(calibration: Calibration) -> bytes:
    """A short name of a calibration's geometry: the first :data:`FINGERPRINT_BYTES` bytes of a SHA-256.

    Hashed: the calibration file's mapping (:meth:`Calibration.to_dict`) without ``metadata``, as JSON with
    sorted keys, no spaces, and every number written with 12 significant digits (``%.12g``), so that a
    calibration read back from its file (re-orthonormalized rotation) keeps its fingerprint. Two calibrations
    that differ in any number beyond its 12th digit have different fingerprints.
    """

    def canon(x: Any) -> Any:
        if isinstance(x, bool) or x is None or isinstance(x, str):
            return x
        if isinstance(x, int | float):
            return format(float(x), f".{_FINGERPRINT_DIGITS}g")
        if isinstance(x, Mapping):
            return {str(k): canon(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [canon(v) for v in x]
        msg = f"calibration holds a value of type {type(x).__name__} that cannot be fingerprinted"
        raise WireError(msg)

    data = {k: v for k, v in calibration.to_dict().items() if k != "metadata"}
    text = json.dumps(canon(data), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).digest()[:FINGERPRINT_BYTES]


@dataclass(frozen=True, eq=False)
class StripeMsg:
    """One processed frame of one robot as the sensor measured it (cloud schema 2).

    Per point: the laser, the pixel column, the sub-pixel row in 1/:data:`ROW_SCALE` px, the quality in
    1/255. The base station triangulates the points with the calibration whose fingerprint ``calib_id`` is
    (:meth:`to_cloud`). On the wire the points are grouped into runs of consecutive columns of one laser (see
    ``docs/conventions.md``, "The cloud payload, schema 2"); the order of the points is kept.

    Attributes:
        robot: robot name (the ``<robot>`` chunk of its keys).
        seq: sequence number, 0, 1, 2, ... per robot, never reused.
        t_ns: capture time of the frame, ns since the Unix epoch.
        pose: vehicle pose in NED at ``t_ns`` (``north_m``/``east_m`` NaN, null on the wire: no fix).
        calib_id: :func:`calibration_fingerprint` of the calibration the frame was measured with (8 bytes).
        laser: (N,) uint8, laser index of each point.
        column: (N,) uint16, pixel column ``u`` of each point.
        row_fx: (N,) int32, sub-pixel row ``v`` of each point, 1/:data:`ROW_SCALE` px.
        quality_u8: (N,) uint8, extractor confidence, 1/255.
        sent_ns: publication time, ns since the Unix epoch (0 if unknown).
    """

    robot: str
    seq: int
    t_ns: int
    pose: Pose
    calib_id: bytes
    laser: NDArray[np.uint8]
    column: NDArray[np.uint16]
    row_fx: NDArray[np.int32]
    quality_u8: NDArray[np.uint8]
    sent_ns: int = 0

    TYPE = "cloud"
    VERSION = STRIPE_SCHEMA_VERSION

    def __post_init__(self) -> None:
        n = self.laser.shape[0] if self.laser.ndim == 1 else -1
        where = f"cloud {self.robot}#{self.seq}"
        shapes = (self.laser.shape, self.column.shape, self.row_fx.shape, self.quality_u8.shape)
        if any(s != (n,) for s in shapes):
            msg = f"{where}: inconsistent arrays: laser, column, row, quality have shapes {shapes}"
            raise WireError(msg)
        dtypes = (self.laser.dtype, self.column.dtype, self.row_fx.dtype, self.quality_u8.dtype)
        if dtypes != (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.int32), np.dtype(np.uint8)):
            msg = f"{where}: laser, column, row, quality must be uint8, uint16, int32, uint8, got {dtypes}"
            raise WireError(msg)
        if n > MAX_POINTS:
            msg = f"{where}: {n} points, more than the {MAX_POINTS} a cloud may carry"
            raise WireError(msg)
        if not isinstance(self.calib_id, bytes) or len(self.calib_id) != FINGERPRINT_BYTES:
            msg = f"{where}: calib_id must be {FINGERPRINT_BYTES} bytes"
            raise WireError(msg)

    def __len__(self) -> int:
        return int(self.laser.shape[0])

    @property
    def uv(self) -> NDArray[np.float64]:
        """(N, 2) float64 pixel coordinates ``(u, v)`` of the points."""
        return np.stack([self.column.astype(np.float64), self.row_fx.astype(np.float64) / ROW_SCALE], axis=1)

    @property
    def quality(self) -> NDArray[np.float32]:
        """(N,) float32 quality in [0, 1] (to 1/255)."""
        return (self.quality_u8.astype(np.float32) / np.float32(255.0)).astype(np.float32)

    @classmethod
    def from_scan(
        cls, robot: str, seq: int, t_ns: int, pose: Pose, scan: Scan, calib_id: bytes, sent_ns: int = 0
    ) -> StripeMsg:
        """The message of a scan, its points ordered by laser, then column (compact runs).

        Raises :class:`WireError` when the scan cannot travel as schema 2: a column that is not a whole pixel
        in ``[0, 65535]`` (the paper's Algorithm 1 measures rows at fractional columns), a laser index outside
        uint8, or a row that is not finite or beyond +-2^31/4096 px.
        """
        where = f"cloud {robot}#{seq}"
        u = np.asarray(scan.uv[:, 0], dtype=np.float64)
        v = np.asarray(scan.uv[:, 1], dtype=np.float64)
        if not np.all(u == np.round(u)) or (u.size and (u.min() < 0 or u.max() > MAX_COLUMN)):
            msg = f"{where}: schema 2 needs whole-pixel columns in [0, {MAX_COLUMN}]"
            raise WireError(msg)
        if np.any(scan.laser < 0) or np.any(scan.laser > 255):
            msg = f"{where}: laser indices must fit in uint8"
            raise WireError(msg)
        if not np.all(np.isfinite(v)) or (v.size and np.abs(v).max() * ROW_SCALE >= _INT32_MAX):
            msg = f"{where}: rows must be finite and within +-{_INT32_MAX // ROW_SCALE} px"
            raise WireError(msg)
        q = np.asarray(scan.quality, dtype=np.float64)
        if not np.all(np.isfinite(q)):
            msg = f"{where}: quality holds non-finite values"
            raise WireError(msg)
        order = np.lexsort((u, scan.laser))
        return cls(
            robot=robot,
            seq=seq,
            t_ns=t_ns,
            pose=pose,
            calib_id=calib_id,
            laser=np.ascontiguousarray(scan.laser[order], dtype=np.uint8),
            column=np.ascontiguousarray(u[order], dtype=np.uint16),
            row_fx=np.ascontiguousarray(np.round(v[order] * ROW_SCALE), dtype=np.int32),
            quality_u8=np.ascontiguousarray(np.round(np.clip(q[order], 0.0, 1.0) * 255.0), dtype=np.uint8),
            sent_ns=sent_ns,
        )

    def with_sent_ns(self, sent_ns: int) -> StripeMsg:
        """A copy stamped with its publication time."""
        return replace(self, sent_ns=sent_ns)

    def runs(self) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """``(starts, lengths)`` of the runs: a run is a stretch of one laser's consecutive columns whose row
        moves by at most 32767/4096 px from one column to the next, at most :data:`MAX_RUN` long."""
        n = len(self)
        if n == 0:
            return np.zeros(0, np.intp), np.zeros(0, np.intp)
        lz = self.laser.astype(np.int64)
        uz = self.column.astype(np.int64)
        vz = self.row_fx.astype(np.int64)
        brk = np.ones(n, dtype=bool)
        brk[1:] = (np.diff(lz) != 0) | (np.diff(uz) != 1) | (np.abs(np.diff(vz)) > _INT16)
        starts = np.flatnonzero(brk)
        lengths = np.diff(np.append(starts, n))
        if lengths.max() > MAX_RUN:  # split over-long runs (a camera wider than 65535 columns)
            pieces = [np.arange(s, s + k, MAX_RUN) for s, k in zip(starts, lengths, strict=True)]
            starts = np.concatenate(pieces)
            lengths = np.diff(np.append(starts, n))
        return starts, lengths

    def to_bytes(self) -> bytes:
        """Encode as msgpack: the runs and the per-point rows' changes and quality as little-endian bytes."""
        _, pose = _checked_header(self.robot, self.seq, self.t_ns, self.sent_ns, self.pose)
        starts, _ = self.runs()
        inner = np.ones(len(self), dtype=bool)
        inner[starts] = False
        dv = np.diff(self.row_fx.astype(np.int64), prepend=0)[inner]
        obj: dict[str, Any] = {
            "v": self.VERSION,
            "type": self.TYPE,
            "robot": self.robot,
            "seq": int(self.seq),
            "t_ns": int(self.t_ns),
            "sent_ns": int(self.sent_ns),
            "pose": pose,
            "calib": bytes(self.calib_id),
            "n": len(self),
            "runs": int(starts.size),
            "run_laser": self.laser[starts].astype("u1").tobytes(),
            "run_u0": self.column[starts].astype("<u2").tobytes(),
            "run_len": np.diff(np.append(starts, len(self))).astype("<u2").tobytes(),
            "run_v0": self.row_fx[starts].astype("<i4").tobytes(),
            "dv": dv.astype("<i2").tobytes(),
            "quality": self.quality_u8.astype("u1").tobytes(),
        }
        return _pack(obj)

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> StripeMsg:
        """Decode and validate a schema-2 cloud; raises :class:`WireError` naming what was wrong."""
        return cls._from_map(_unpack(data, cls.TYPE, (cls.VERSION,)))

    @classmethod
    def _from_map(cls, obj: Mapping[str, Any]) -> StripeMsg:
        robot, seq, where, t_ns, sent_ns, pose = _header_from_map(obj)
        calib_id = _bytes_field(obj, "calib", where, FINGERPRINT_BYTES, what="a calibration fingerprint")
        n = _int_field(obj, "n", where, maximum=MAX_POINTS)
        n_runs = _int_field(obj, "runs", where, minimum=1 if n else 0, maximum=n)
        run_laser = np.frombuffer(_bytes_field(obj, "run_laser", where, n_runs, "the declared runs"), "u1")
        run_u0 = np.frombuffer(_bytes_field(obj, "run_u0", where, 2 * n_runs, "the declared runs"), "<u2")
        run_len = np.frombuffer(_bytes_field(obj, "run_len", where, 2 * n_runs, "the declared runs"), "<u2")
        run_v0 = np.frombuffer(_bytes_field(obj, "run_v0", where, 4 * n_runs, "the declared runs"), "<i4")
        dv = np.frombuffer(_bytes_field(obj, "dv", where, 2 * (n - n_runs), "the declared points and runs"), "<i2")
        quality = np.frombuffer(_bytes_field(obj, "quality", where, n), "u1")
        lengths = run_len.astype(np.int64)
        if n_runs and lengths.min() < 1:
            msg = f"{where}: run {int(np.argmin(lengths))} is empty (run_len 0)"
            raise WireError(msg)
        if int(lengths.sum()) != n:
            msg = f"{where}: the runs hold {int(lengths.sum())} points, the cloud declares n = {n}"
            raise WireError(msg)
        last_u = run_u0.astype(np.int64) + lengths - 1
        if n_runs and last_u.max() > MAX_COLUMN:
            msg = f"{where}: run {int(np.argmax(last_u))} ends at column {int(last_u.max())}, beyond {MAX_COLUMN}"
            raise WireError(msg)
        starts = np.cumsum(lengths) - lengths
        run_of = np.repeat(np.arange(n_runs), lengths)
        steps = np.empty(n, dtype=np.int64)
        first = np.zeros(n, dtype=bool)
        first[starts] = True
        steps[first] = run_v0
        steps[~first] = dv
        total = np.cumsum(steps)
        rows = total - (total[starts] - run_v0)[run_of] if n else total
        if n and (rows.min() < _INT32_MIN or rows.max() > _INT32_MAX):
            msg = f"{where}: a row leaves the int32 range of 1/{ROW_SCALE} px"
            raise WireError(msg)
        columns = run_u0.astype(np.int64)[run_of] + (np.arange(n) - starts[run_of])
        return cls(
            robot,
            seq,
            t_ns,
            pose,
            calib_id,
            np.repeat(run_laser, lengths),
            columns.astype(np.uint16),
            rows.astype(np.int32),
            quality.copy(),
            sent_ns,
        )

    def to_cloud(self, calibration: Calibration) -> CloudMsg:
        """Triangulate with ``calibration`` (whose fingerprint must be ``calib_id``) into a schema-1 cloud.

        Each laser's pixels go through :func:`lrsensor.triangulation.triangulate_plane` (numpy, float64: ray of
        the pixel, met with the laser's plane) or, behind a flat port, :func:`lrsensor.port.triangulate_through_port`
        (the refracted ray), the same geometry the ROV's extractor triangulated with; the
        points are then narrowed to float32 as schema 1 carries them.

        Raises :class:`WireError` when the fingerprint differs, a laser index names no laser of the
        calibration, a pixel lies outside its image, or a pixel does not triangulate (ray parallel to the
        plane or meeting it behind the camera).
        """
        from lrsensor.port import triangulate_through_port
        from lrsensor.triangulation import triangulate_plane

        where = f"cloud {self.robot}#{self.seq}"
        if calibration_fingerprint(calibration) != self.calib_id:
            msg = (
                f"calibration mismatch: {where} was measured with calibration {self.calib_id.hex()}, "
                f"not {calibration_fingerprint(calibration).hex()}"
            )
            raise WireError(msg)
        n_lasers = len(calibration.lasers)
        if len(self) and int(self.laser.max()) >= n_lasers:
            msg = f"{where}: laser index {int(self.laser.max())} but the calibration has {n_lasers} lasers"
            raise WireError(msg)
        cam = calibration.camera
        uv = self.uv
        if len(self) and (uv[:, 0].max() >= cam.width or uv[:, 1].min() < -1 or uv[:, 1].max() > cam.height):
            msg = f"{where}: a pixel lies outside the {cam.width}x{cam.height} image"
            raise WireError(msg)
        # through the camera's flat port where the calibration has one (exact refraction, as the ROV's extractor)
        triangulate = triangulate_plane if calibration.port is None else triangulate_through_port
        points = np.empty((len(self), 3), dtype=np.float64)
        for li in np.unique(self.laser):
            sel = self.laser == li
            points[sel] = triangulate(calibration, uv[sel], calibration.lasers[int(li)])
        bad = ~np.all(np.isfinite(points), axis=1)
        if bad.any():
            msg = f"{where}: {int(bad.sum())} of {len(self)} pixels do not triangulate with the calibration"
            raise WireError(msg)
        return CloudMsg(
            robot=self.robot,
            seq=self.seq,
            t_ns=self.t_ns,
            pose=self.pose,
            points_body=points.astype(np.float32),
            laser=self.laser,
            quality=self.quality,
            uv=uv.astype(np.float32),
            sent_ns=self.sent_ns,
        )
