"""The calibration file: camera intrinsics, camera mounting and the laser planes (one loader, one validator).

Format (JSON, see CONVENTIONS.md)::

    {"camera": {"width", "height", "fx", "fy", "cx", "cy", "distortion": [k1, k2, p1, p2, k3]},
     "R_cam_from_body": 3x3, "t_cam_from_body": [3],
     "lasers": [{"name", "point": [3], "normal": [3]}, ...],
     "port": {"type": "flat", "normal_cam": [3], "distance_m", "thickness_m", "n_air", "n_glass", "n_water"}}

``port`` is optional (absent or ``"type": "none"``: the pinhole camera of ``camera``); with a flat port
``camera`` holds the in-air intrinsics and :mod:`lrsensor.port` models the refraction.
``p_cam = R_cam_from_body @ p_body + t_cam_from_body``. A laser plane is every body-frame point ``p`` with
``normal . (p - point) = 0``. Unknown extra keys are accepted and kept (``metadata`` is written back).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .atomic import atomic_write
from .camera import Camera
from .errors import CalibrationFileError, GeometryError
from .frames import R_CAM_FROM_BODY_DEFAULT
from .port import FlatPort, blind_pixels, border_pixels, pixel_rays_in_water, project_pixels_through_port

FloatArray = NDArray[np.float64]
FORMAT_NAME = "lrsensor-calibration"
FORMAT_VERSION = 1
#: Largest accepted calibration file, bytes (a real one is about 1 kB).
MAX_FILE_BYTES = 1_000_000


@dataclass(frozen=True)
class LaserPlane:
    """A laser's plane of light in the body frame: ``normal . (p - point) = 0``.

    Attributes:
        name: laser name (``"top"``, ``"bottom"``).
        point: a point of the plane (the laser's position), body frame, metres, shape (3,).
        normal: unit normal, body frame, shape (3,).
    """

    name: str
    point: tuple[float, float, float]
    normal: tuple[float, float, float]

    @property
    def point_body(self) -> FloatArray:
        """The plane's point as an array, shape (3,), metres."""
        return np.asarray(self.point, dtype=float)

    @property
    def normal_body(self) -> FloatArray:
        """The plane's unit normal as an array, shape (3,)."""
        return np.asarray(self.normal, dtype=float)

    def signed_distance(self, points_body: FloatArray) -> FloatArray:
        """Signed distance (N,) of body points (N, 3) to the plane, metres."""
        return (np.asarray(points_body, dtype=float) - self.point_body) @ self.normal_body

    @classmethod
    def make(cls, name: str, point: Sequence[float], normal: Sequence[float]) -> LaserPlane:
        """Build a plane, normalising ``normal``; raises :class:`GeometryError` for a zero normal."""
        n = np.asarray(normal, dtype=float)
        norm = float(np.linalg.norm(n))
        if not norm > 1e-12 or not math.isfinite(norm):
            msg = f"laser {name!r}: normal must be a non-zero finite vector, got {list(normal)}"
            raise GeometryError(msg)
        n = n / norm
        p = [float(x) for x in point]
        return cls(name, (p[0], p[1], p[2]), (float(n[0]), float(n[1]), float(n[2])))


@dataclass(frozen=True)
class Calibration:
    """Everything the sensor needs to turn pixels into body-frame points.

    Attributes:
        camera: intrinsics and distortion.
        R_cam_from_body: rotation of body vectors into the camera frame, (3, 3) as nested tuples.
        t_cam_from_body: translation, metres, ``p_cam = R p_body + t``.
        lasers: the laser planes, index = laser index used everywhere else.
        port: the camera's flat port (``camera`` then holds in-air intrinsics), or None for a pinhole camera.
        metadata: free-form information kept with the file (date, inputs, residuals).
    """

    camera: Camera
    lasers: tuple[LaserPlane, ...]
    R_cam_from_body: tuple[tuple[float, float, float], ...] = field(
        default_factory=lambda: _rows3(R_CAM_FROM_BODY_DEFAULT)
    )
    t_cam_from_body: tuple[float, float, float] = (0.0, 0.0, 0.0)
    port: FlatPort | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict, compare=False)

    # ----------------------------------------------------------------- derived geometry
    @property
    def R_cam_body(self) -> FloatArray:
        """``R_cam_from_body`` as an array, shape (3, 3)."""
        return np.asarray(self.R_cam_from_body, dtype=float)

    @property
    def t_cam_body(self) -> FloatArray:
        """``t_cam_from_body`` as an array, shape (3,), metres."""
        return np.asarray(self.t_cam_from_body, dtype=float)

    @property
    def camera_center_body(self) -> FloatArray:
        """The camera's optical centre in the body frame, shape (3,), metres (``-R^T t``)."""
        return -self.R_cam_body.T @ self.t_cam_body

    def body_to_cam(self, points_body: FloatArray) -> FloatArray:
        """Body-frame points (N, 3) to the camera frame (N, 3)."""
        return np.asarray(points_body, dtype=float) @ self.R_cam_body.T + self.t_cam_body

    def cam_to_body(self, points_cam: FloatArray) -> FloatArray:
        """Camera-frame points (N, 3) to the body frame (N, 3)."""
        return (np.asarray(points_cam, dtype=float) - self.t_cam_body) @ self.R_cam_body

    def project_body(self, points_body: FloatArray) -> FloatArray:
        """Project body-frame points (N, 3) to pixels (N, 2); NaN rows behind the camera."""
        return self.camera.project(self.body_to_cam(points_body))

    def rays_body(self, uv: FloatArray) -> FloatArray:
        """Viewing-ray directions in the body frame (N, 3) for pixels (N, 2) (not normalised)."""
        return self.camera.unproject(uv) @ self.R_cam_body

    def water_rays_body(self, uv: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The rays along which pixels (N, 2) see into the water, body frame: ``(origins, dirs)``.

        Without a port: the camera centre (3,) and :meth:`rays_body` (N, 3) (not normalised). Through the port:
        each ray's exit point on the port's outer surface (N, 3), metres, and its unit direction in the water
        (N, 3) (:func:`lrsensor.port.pixel_rays_in_water`; NaN rows for pixels that cannot see into the water).
        """
        if self.port is None:
            return self.camera_center_body, self.rays_body(uv)
        origins_cam, dirs_cam = pixel_rays_in_water(self.camera, self.port, uv)
        return self.cam_to_body(origins_cam), dirs_cam @ self.R_cam_body

    def project_water_body(self, points_body: FloatArray) -> FloatArray:
        """Pixels (N, 2) of body-frame points (N, 3) in the water: :meth:`project_body`, or through the port
        exactly when there is one (:func:`lrsensor.port.project_pixels_through_port`); NaN rows for points
        behind the camera (or the port's outer surface)."""
        if self.port is None:
            return self.project_body(points_body)
        return project_pixels_through_port(self.camera, self.port, self.body_to_cam(points_body))

    @classmethod
    def paper(cls, baseline_m: float = 0.1, width: int = 1920, height: int = 1080) -> Calibration:
        """The nominal sensor of the paper: section 5.1 camera, lasers at z_b = -b/2 (top) and +b/2 (bottom)."""
        c = baseline_m / 2.0
        return cls(
            camera=Camera.paper(width, height),
            lasers=(
                LaserPlane("top", (0.0, 0.0, -c), (0.0, 0.0, 1.0)),
                LaserPlane("bottom", (0.0, 0.0, c), (0.0, 0.0, 1.0)),
            ),
        )

    def with_lasers(self, lasers: Sequence[LaserPlane], metadata: Mapping[str, Any] | None = None) -> Calibration:
        """A copy with other laser planes (and optionally other metadata)."""
        return replace(self, lasers=tuple(lasers), metadata=dict(self.metadata if metadata is None else metadata))

    # ----------------------------------------------------------------- (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready mapping of CONVENTIONS.md (plus ``format``/``version`` and ``metadata``)."""
        cam = self.camera
        out: dict[str, Any] = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "camera": {
                "width": cam.width,
                "height": cam.height,
                "fx": cam.fx,
                "fy": cam.fy,
                "cx": cam.cx,
                "cy": cam.cy,
                "distortion": list(cam.distortion),
            },
            "R_cam_from_body": [list(r) for r in self.R_cam_from_body],
            "t_cam_from_body": list(self.t_cam_from_body),
            "lasers": [{"name": l.name, "point": list(l.point), "normal": list(l.normal)} for l in self.lasers],
        }
        if self.port is not None:
            out["port"] = self.port.to_dict()
        if self.metadata:
            out["metadata"] = dict(self.metadata)
        return out

    def to_json(self) -> str:
        """Serialise to a JSON string (indented)."""
        return json.dumps(self.to_dict(), indent=2)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the calibration file atomically (temporary file then rename)."""
        atomic_write(path, self.to_json() + "\n")

    @classmethod
    def from_dict(cls, data: Any, source: str = "calibration") -> Calibration:
        """Validate a decoded mapping; errors name the offending key, e.g. ``camera.fx``."""
        if not isinstance(data, Mapping):
            msg = f"{source}: top level must be a JSON object, got {type(data).__name__}"
            raise CalibrationFileError(msg)
        cam_d = _mapping(data, "camera", source)
        width = _int(cam_d, "width", f"{source}: camera.width", minimum=1)
        height = _int(cam_d, "height", f"{source}: camera.height", minimum=1)
        fx = _num(cam_d, "fx", f"{source}: camera.fx", positive=True)
        fy = _num(cam_d, "fy", f"{source}: camera.fy", positive=True)
        cx = _num(cam_d, "cx", f"{source}: camera.cx")
        cy = _num(cam_d, "cy", f"{source}: camera.cy")
        dist = (
            _vector(cam_d, "distortion", f"{source}: camera.distortion", 5)
            if "distortion" in cam_d
            else (
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            )
        )
        camera = Camera(width, height, fx, fy, cx, cy, (dist[0], dist[1], dist[2], dist[3], dist[4]))

        R = np.asarray(_matrix3(data, "R_cam_from_body", source))
        with np.errstate(over="ignore", invalid="ignore"):  # huge finite entries: inf/nan, refused below
            not_rotation = not (abs(np.linalg.det(R) - 1.0) <= 1e-3 and np.abs(R @ R.T - np.eye(3)).max() <= 1e-3)
        if not_rotation:
            msg = f"{source}: R_cam_from_body is not a rotation matrix (orthonormal, det +1): {R.tolist()}"
            raise CalibrationFileError(msg)
        u, _, vt = np.linalg.svd(R)
        R = u @ vt
        t = _vector(data, "t_cam_from_body", f"{source}: t_cam_from_body", 3)

        lasers_raw = data.get("lasers")
        if not isinstance(lasers_raw, Sequence) or isinstance(lasers_raw, str | bytes):
            msg = f"{source}: missing or invalid key 'lasers' (a list of laser planes)"
            raise CalibrationFileError(msg)
        if len(lasers_raw) == 0:
            msg = f"{source}: 'lasers' is empty; at least one laser plane is required"
            raise CalibrationFileError(msg)
        lasers = []
        for i, ld in enumerate(lasers_raw):
            where = f"{source}: lasers[{i}]"
            if not isinstance(ld, Mapping):
                msg = f"{where} must be an object with point and normal"
                raise CalibrationFileError(msg)
            name = ld.get("name", f"laser{i}")
            if not isinstance(name, str):
                msg = f"{where}.name must be a string"
                raise CalibrationFileError(msg)
            point = _vector(ld, "point", f"{where}.point", 3)
            normal = _vector(ld, "normal", f"{where}.normal", 3)
            try:
                lasers.append(LaserPlane.make(name, point, normal))
            except GeometryError as err:
                msg = f"{where}.normal: {err}"
                raise CalibrationFileError(msg) from err
        port = _port(data, camera, source)
        meta = data.get("metadata", {})
        return cls(
            camera=camera,
            lasers=tuple(lasers),
            R_cam_from_body=_rows3(R),
            t_cam_from_body=(t[0], t[1], t[2]),
            port=port,
            metadata=dict(meta) if isinstance(meta, Mapping) else {},
        )

    @classmethod
    def from_json(cls, text: str | bytes, source: str = "calibration") -> Calibration:
        """Parse and validate JSON text."""
        if len(text) > MAX_FILE_BYTES:
            msg = f"{source}: calibration is {len(text)} bytes, more than the {MAX_FILE_BYTES} accepted"
            raise CalibrationFileError(msg)
        try:
            data = json.loads(text, parse_constant=_reject_constant)
        except (ValueError, UnicodeDecodeError) as err:
            msg = f"{source}: not valid JSON: {err}"
            raise CalibrationFileError(msg) from err
        return cls.from_dict(data, source)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Calibration:
        """Read and validate a calibration file."""
        p = Path(path)
        try:
            raw = p.read_bytes()
        except OSError as err:
            msg = f"{p}: cannot read calibration file: {err.strerror or err}"
            raise CalibrationFileError(msg) from err
        return cls.from_json(raw, str(p))


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read and validate a calibration file (same as :meth:`Calibration.load`)."""
    return Calibration.load(path)


def _rows3(R: FloatArray) -> tuple[tuple[float, float, float], ...]:
    """A (3, 3) array as nested tuples of floats."""
    return tuple((float(r[0]), float(r[1]), float(r[2])) for r in np.asarray(R, dtype=float))


def _reject_constant(name: str) -> float:
    msg = f"non-finite number {name} is not allowed"
    raise ValueError(msg)


def _mapping(d: Mapping[str, Any], key: str, source: str) -> Mapping[str, Any]:
    v = d.get(key)
    if not isinstance(v, Mapping):
        msg = f"{source}: missing or invalid key '{key}' (an object)"
        raise CalibrationFileError(msg)
    return v


def _num(d: Mapping[str, Any], key: str, where: str, positive: bool = False) -> float:
    if key not in d:
        msg = f"{where}: missing required key '{key}'"
        raise CalibrationFileError(msg)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        msg = f"{where}: must be a finite number, got {v!r}"
        raise CalibrationFileError(msg)
    if positive and not v > 0:
        msg = f"{where}: must be positive, got {v!r}"
        raise CalibrationFileError(msg)
    return float(v)


def _int(d: Mapping[str, Any], key: str, where: str, minimum: int) -> int:
    v = _num(d, key, where)
    if v != int(v) or v < minimum:
        msg = f"{where}: must be an integer >= {minimum}, got {d[key]!r}"
        raise CalibrationFileError(msg)
    return int(v)


def _vector(d: Mapping[str, Any], key: str, where: str, n: int) -> tuple[float, ...]:
    if key not in d:
        msg = f"{where}: missing required key '{key}'"
        raise CalibrationFileError(msg)
    v = d[key]
    if not isinstance(v, Sequence) or isinstance(v, str | bytes) or len(v) != n:
        msg = f"{where}: must be a list of {n} numbers, got {v!r}"
        raise CalibrationFileError(msg)
    out = []
    for i, x in enumerate(v):
        if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
            msg = f"{where}[{i}]: must be a finite number, got {x!r}"
            raise CalibrationFileError(msg)
        out.append(float(x))
    return tuple(out)


def _port(data: Mapping[str, Any], camera: Camera, source: str) -> FlatPort | None:
    """The optional ``port``: None when absent or ``"type": "none"``; errors name the key (``port.n_water``)."""
    if "port" not in data:
        return None
    port_d = _mapping(data, "port", source)
    kind = port_d.get("type")
    if kind == "none":
        return None
    if kind != "flat":
        msg = f'{source}: port.type: must be "flat" or "none", got {kind!r}'
        raise CalibrationFileError(msg)
    normal = _vector(port_d, "normal_cam", f"{source}: port.normal_cam", 3)
    values = {
        k: _num(port_d, k, f"{source}: port.{k}") for k in ("distance_m", "thickness_m", "n_air", "n_glass", "n_water")
    }
    try:
        port = FlatPort(normal_cam=(normal[0], normal[1], normal[2]), **values)
    except GeometryError as err:
        msg = f"{source}: {err}"
        raise CalibrationFileError(msg) from err
    if not port.n_water > port.n_air:
        msg = f"{source}: port.n_water: must exceed port.n_air ({port.n_air}) for a port in water, got {port.n_water}"
        raise CalibrationFileError(msg)
    border = border_pixels(camera)
    blind = border[blind_pixels(camera, port, border)]
    if blind.shape[0]:
        u, v = blind[0]
        msg = (
            f"{source}: port: {blind.shape[0]} border pixels of the image cannot see into the water (their rays "
            f"meet the port at grazing incidence or reflect totally), e.g. pixel ({u:g}, {v:g}); "
            "check port.normal_cam and the camera's field of view"
        )
        raise CalibrationFileError(msg)
    return port


def _matrix3(d: Mapping[str, Any], key: str, source: str) -> list[tuple[float, ...]]:
    if key not in d:
        msg = f"{source}: {key}: missing required key '{key}'"
        raise CalibrationFileError(msg)
    v = d[key]
    if not isinstance(v, Sequence) or isinstance(v, str | bytes) or len(v) != 3:
        msg = f"{source}: {key}: must be a 3x3 list of numbers"
        raise CalibrationFileError(msg)
    return [_vector({"row": row}, "row", f"{source}: {key}[{i}]", 3) for i, row in enumerate(v)]
