"""Scene geometry of the simulator: planes, rectangles (boxes), cylinders, and vectorized ray casting.

Every surface is an immutable value in one frame (the body frame, or NED when the scene is given in NED
together with a vehicle pose). All functions are pure numpy and vectorized over rays / points.

Ray casting convention: a ray is ``origin + t * dir`` with ``t > T_MIN``; ``t`` is in units of ``|dir|``
(metres when ``dir`` is a unit vector). A ray that hits nothing gives ``t = inf``, ``surface_id = -1`` and a
zero normal.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..errors import SimulationError
from ..frames import Pose, check_points

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Smallest accepted ray parameter (m for unit directions): hits closer than this are ignored.
T_MIN = 1e-9

Frame = Literal["body", "ned"]


def _unit(v: ArrayLike, what: str) -> FloatArray:
    a = np.asarray(v, dtype=float).reshape(3)
    n = float(np.linalg.norm(a))
    if not (n > 1e-12 and np.isfinite(n)):
        msg = f"{what} must be a non-zero finite 3-vector, got {a.tolist()}"
        raise SimulationError(msg)
    return a / n


def _vec3(v: ArrayLike, what: str) -> FloatArray:
    a = np.asarray(v, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        msg = f"{what} must be a finite 3-vector, got {np.asarray(v).tolist()}"
        raise SimulationError(msg)
    return a


def _rays(origins: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, FloatArray]:
    d = check_points(dirs, "dirs")
    o = np.asarray(origins, dtype=float)
    if o.shape in ((3,), (1, 3)):
        o = o.reshape(1, 3)
        if not np.all(np.isfinite(o)):
            msg = f"origin must be finite, got {o.tolist()}"
            raise SimulationError(msg)
        return o, d  # one origin for every ray: surfaces broadcast it
    o = check_points(o, "origins")
    if o.shape != d.shape:
        msg = f"origins {o.shape} and dirs {d.shape} must have the same shape (or origins (3,))"
        raise SimulationError(msg)
    return o, d


@dataclass(frozen=True)
class Checkerboard:
    """A printed checkerboard on a rectangle (for camera / wall-pose calibration, issue 4).

    The board has ``cols x rows`` INNER corners, i.e. ``(cols + 1) x (rows + 1)`` squares of ``square_m``
    metres, plus a white margin of ``margin_m`` around it. Its centre sits at ``(offset_u_m, offset_v_m)`` in
    the rectangle's (u, v) coordinates (metres from the rectangle centre along ``axis_u``/``axis_v``), and
    its own axes are turned by ``rotation_rad`` from the rectangle's (positive from u toward v).

    Attributes:
        cols, rows: inner corners along the board's x and y axes.
        square_m: side of a square, metres.
        offset_u_m, offset_v_m: board centre in rectangle coordinates, metres.
        margin_m: white border around the squares, metres.
        white, black: reflectance (0..1) of the white and black squares.
        rotation_rad: in-plane rotation of the board on the rectangle, radians.
    """

    cols: int = 9
    rows: int = 6
    square_m: float = 0.04
    offset_u_m: float = 0.0
    offset_v_m: float = 0.0
    margin_m: float = 0.04
    white: float = 0.85
    black: float = 0.08
    rotation_rad: float = 0.0

    def to_board(self, su: FloatArray, sv: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Rectangle coordinates (metres) to board coordinates (metres from the board centre, board axes)."""
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        du, dv = su - self.offset_u_m, sv - self.offset_v_m
        return c * du + s * dv, -s * du + c * dv

    def from_board(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Board coordinates to rectangle coordinates (metres)."""
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        return self.offset_u_m + c * x - s * y, self.offset_v_m + s * x + c * y

    def corners_uv(self) -> FloatArray:
        """Inner corners in rectangle coordinates (u, v), metres, shape (rows*cols, 2).

        Ordered row by row (board y outer, x inner), the first corner at the most negative board (x, y): with
        the scenes' walls (u to the right in the image, v down) this is OpenCV's order for an unrotated board.
        """
        s = self.square_m
        ix = (np.arange(self.cols) - (self.cols - 1) / 2.0) * s
        iy = (np.arange(self.rows) - (self.rows - 1) / 2.0) * s
        xx, yy = np.meshgrid(ix, iy)
        u, v = self.from_board(xx.ravel(), yy.ravel())
        return np.stack([u, v], axis=1)

    def half_extent_m(self) -> tuple[float, float]:
        """Half size of the board including its margin along its x and y axes, metres."""
        return (
            (self.cols + 1) * self.square_m / 2.0 + self.margin_m,
            (self.rows + 1) * self.square_m / 2.0 + self.margin_m,
        )

    def outline_uv(self) -> FloatArray:
        """The board's outer corners (margin included) in rectangle coordinates, shape (4, 2)."""
        hx, hy = self.half_extent_m()
        x = np.array([-hx, hx, hx, -hx])
        y = np.array([-hy, -hy, hy, hy])
        u, v = self.from_board(x, y)
        return np.stack([u, v], axis=1)

    def reflectance(self, su: FloatArray, sv: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Reflectance at rectangle coordinates (N,) (point samples), and the mask (N,) of points on the board."""
        x, y = self.to_board(su, sv)
        hx, hy = self.half_extent_m()
        on_board = (np.abs(x) <= hx) & (np.abs(y) <= hy)
        qx = (self.cols + 1) * self.square_m / 2.0
        qy = (self.rows + 1) * self.square_m / 2.0
        in_squares = (np.abs(x) < qx) & (np.abs(y) < qy)
        ix = np.floor((x + qx) / self.square_m).astype(np.int64)
        iy = np.floor((y + qy) / self.square_m).astype(np.int64)
        dark = ((ix + iy) % 2 == 0) & in_squares
        refl = np.where(dark, self.black, self.white)
        return refl, on_board

    def filtered_reflectance(
        self, x: FloatArray, y: FloatArray, wx: FloatArray, wy: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Box-filtered reflectance of the board (margin included) over pixel footprints ``wx x wy``.

        Args:
            x, y: BOARD coordinates (:meth:`to_board`) of pixel centres (any shape), metres.
            wx, wy: the pixels' footprint widths along the board's x and y axes, metres.

        Returns:
            the mean reflectance over the board part of each footprint, and the covered fraction (0..1) of
            the footprint that lies on the board (squares plus margin).
        """
        s = self.square_m
        qx = (self.cols + 1) * s / 2.0
        qy = (self.rows + 1) * s / 2.0
        hx, hy = self.half_extent_m()
        wx = np.maximum(wx, 1e-9)
        wy = np.maximum(wy, 1e-9)

        def tri(z: FloatArray) -> FloatArray:
            # integral of the +-1 square wave (+1 on [0, s), -1 on [s, 2s)), a triangle wave
            m = np.mod(z, 2.0 * s)
            return np.where(m < s, m, 2.0 * s - m)

        def box(z: FloatArray, width: FloatArray, lo: float, hi: float) -> FloatArray:
            return np.clip((np.minimum(z + width / 2, hi) - np.maximum(z - width / 2, lo)) / width, 0.0, 1.0)

        px, py = x + qx, y + qy  # from the first square's outer corner
        sq_x = (tri(px + wx / 2) - tri(px - wx / 2)) / wx
        sq_y = (tri(py + wy / 2) - tri(py - wy / 2)) / wy
        in_sq = box(x, wx, -qx, qx) * box(y, wy, -qy, qy)
        cover = box(x, wx, -hx, hx) * box(y, wy, -hy, hy)
        dark = in_sq * (1.0 + np.clip(sq_x * sq_y, -1.0, 1.0)) / 2.0
        refl = self.white + (self.black - self.white) * dark / np.maximum(cover, 1e-9)
        return np.clip(refl, min(self.black, self.white), max(self.black, self.white)), cover


@dataclass(frozen=True)
class Surface:
    """Base class of scene surfaces.

    Attributes:
        name: free text (used in truth files).
        albedo: diffuse reflectance (0..1).
        stain: relative variation (0..1) of the albedo over the surface (dirt, growth, concrete), a smooth
            procedural pattern fixed to the surface (it moves with it; rectangles only); 0 = uniform.
    """

    name: str = ""
    albedo: float = 0.6
    stain: float = 0.0

    def surface_coords(self, points: FloatArray) -> FloatArray | None:
        """2-D coordinates (N, 2), metres, fixed to the surface (for its stain pattern); None if it has none."""
        return None

    def albedo_at(self, points: FloatArray) -> FloatArray:
        """Albedo (N,) at points (N, 3) on the surface (the stain pattern included)."""
        base = np.full(points.shape[0], self.albedo)
        uv = self.surface_coords(points) if self.stain > 0 else None
        if uv is None:
            return base
        rng = np.random.default_rng(zlib.crc32(self.name.encode()))
        pattern = np.zeros(points.shape[0])
        for _ in range(5):
            ang = rng.uniform(0, 2 * np.pi)
            wavelength = rng.uniform(0.04, 0.4)
            phase = rng.uniform(0, 2 * np.pi)
            pattern += np.sin((uv[:, 0] * np.cos(ang) + uv[:, 1] * np.sin(ang)) * (2 * np.pi / wavelength) + phase)
        return base * np.clip(1.0 + self.stain * pattern / np.sqrt(2.5), 0.05, None)

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Nearest hit ``t`` (N,) (inf for none) and the outward normal for rays ``dirs`` (N, 3).

        ``origins`` is (N, 3) or (1, 3) (one origin for every ray). The normal is (N, 3), or (3,) for flat
        surfaces (the same for every ray).
        """
        raise NotImplementedError

    def distance(self, points: FloatArray) -> FloatArray:
        """Unsigned distance (N,) of points (N, 3) to the surface, metres."""
        raise NotImplementedError

    def transformed(self, R: FloatArray, t: FloatArray) -> Surface:
        """The surface moved by ``p' = R p + t``."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """A JSON-ready description."""
        raise NotImplementedError


@dataclass(frozen=True)
class Plane(Surface):
    """An infinite plane through ``point`` with unit ``normal`` (both in the scene's frame, metres)."""

    point: tuple[float, float, float] = (0.0, 0.0, 0.0)
    normal: tuple[float, float, float] = (1.0, 0.0, 0.0)

    @classmethod
    def make(cls, point: ArrayLike, normal: ArrayLike, name: str = "", albedo: float = 0.6) -> Plane:
        """Build a plane, normalising ``normal``."""
        p = _vec3(point, "plane point")
        n = _unit(normal, "plane normal")
        return cls(name=name, albedo=albedo, point=(p[0], p[1], p[2]), normal=(n[0], n[1], n[2]))

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """See :meth:`Surface.intersect`."""
        n = np.asarray(self.normal)
        denom = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((np.asarray(self.point) - origins) @ n) / denom
        t = np.where(np.isfinite(t) & (t > T_MIN), t, np.inf)
        return t, n

    def distance(self, points: FloatArray) -> FloatArray:
        """See :meth:`Surface.distance`."""
        return np.abs((points - np.asarray(self.point)) @ np.asarray(self.normal))

    def transformed(self, R: FloatArray, t: FloatArray) -> Plane:
        """See :meth:`Surface.transformed`."""
        p = R @ np.asarray(self.point) + t
        n = R @ np.asarray(self.normal)
        return replace(self, point=(p[0], p[1], p[2]), normal=(n[0], n[1], n[2]))

    def to_dict(self) -> dict[str, Any]:
        """See :meth:`Surface.to_dict`."""
        n = np.asarray(self.normal)
        return {
            "type": "plane",
            "name": self.name,
            "point": list(self.point),
            "normal": list(self.normal),
            "d": float(-n @ np.asarray(self.point)),
        }


@dataclass(frozen=True)
class Rectangle(Surface):
    """A finite planar patch: ``center + a * axis_u + b * axis_v`` with ``|a| <= half_u``, ``|b| <= half_v``.

    ``axis_u`` and ``axis_v`` are orthonormal; the normal is ``axis_u x axis_v``. An optional
    :class:`Checkerboard` is printed on it.
    """

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis_u: tuple[float, float, float] = (0.0, 1.0, 0.0)
    axis_v: tuple[float, float, float] = (0.0, 0.0, 1.0)
    half_u: float = 1.0
    half_v: float = 1.0
    board: Checkerboard | None = None

    @classmethod
    def make(
        cls,
        center: ArrayLike,
        axis_u: ArrayLike,
        axis_v: ArrayLike,
        size_u_m: float,
        size_v_m: float,
        name: str = "",
        albedo: float = 0.6,
        board: Checkerboard | None = None,
    ) -> Rectangle:
        """Build a rectangle of ``size_u_m x size_v_m`` metres; ``axis_v`` is orthogonalised against ``axis_u``."""
        c = _vec3(center, "rectangle center")
        eu = _unit(axis_u, "rectangle axis_u")
        v = np.asarray(axis_v, dtype=float)
        ev = _unit(v - (v @ eu) * eu, "rectangle axis_v (orthogonalised)")
        if not (size_u_m > 0 and size_v_m > 0):
            msg = f"rectangle {name!r}: sizes must be positive, got {size_u_m} x {size_v_m}"
            raise SimulationError(msg)
        return cls(
            name=name,
            albedo=albedo,
            center=(c[0], c[1], c[2]),
            axis_u=(eu[0], eu[1], eu[2]),
            axis_v=(ev[0], ev[1], ev[2]),
            half_u=size_u_m / 2.0,
            half_v=size_v_m / 2.0,
            board=board,
        )

    @cached_property
    def normal(self) -> FloatArray:
        """Unit normal ``axis_u x axis_v``, shape (3,)."""
        return np.cross(np.asarray(self.axis_u), np.asarray(self.axis_v))

    def local(self, points: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Rectangle coordinates ``(a, b, h)`` (N,) of points: along u, along v, height along the normal."""
        d = points - np.asarray(self.center)
        return d @ np.asarray(self.axis_u), d @ np.asarray(self.axis_v), d @ self.normal

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """See :meth:`Surface.intersect`."""
        n = self.normal
        eu, ev = np.asarray(self.axis_u), np.asarray(self.axis_v)
        w = origins - np.asarray(self.center)
        denom = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = -(w @ n) / denom
            a = w @ eu + t * (dirs @ eu)
            b = w @ ev + t * (dirs @ ev)
            inside = np.isfinite(t) & (t > T_MIN) & (np.abs(a) <= self.half_u) & (np.abs(b) <= self.half_v)
        return np.where(inside, t, np.inf), n

    def distance(self, points: FloatArray) -> FloatArray:
        """See :meth:`Surface.distance`."""
        a, b, h = self.local(points)
        da = np.maximum(np.abs(a) - self.half_u, 0.0)
        db = np.maximum(np.abs(b) - self.half_v, 0.0)
        return np.sqrt(da * da + db * db + h * h)

    def surface_coords(self, points: FloatArray) -> FloatArray | None:
        """See :meth:`Surface.surface_coords`: the rectangle coordinates (a, b)."""
        a, b, _ = self.local(points)
        return np.stack([a, b], axis=1)

    def corners(self) -> FloatArray:
        """The four corners, shape (4, 3), in order (-u,-v), (+u,-v), (+u,+v), (-u,+v)."""
        c, eu, ev = np.asarray(self.center), np.asarray(self.axis_u), np.asarray(self.axis_v)
        s = [(-1, -1), (1, -1), (1, 1), (-1, 1)]
        return np.array([c + i * self.half_u * eu + j * self.half_v * ev for i, j in s])

    def board_corners(self) -> FloatArray:
        """The checkerboard's inner corners in the scene frame, shape (rows*cols, 3) (OpenCV order)."""
        if self.board is None:
            msg = f"rectangle {self.name!r} carries no checkerboard"
            raise SimulationError(msg)
        ab = self.board.corners_uv()
        return np.asarray(self.center) + ab[:, :1] * np.asarray(self.axis_u) + ab[:, 1:] * np.asarray(self.axis_v)

    def transformed(self, R: FloatArray, t: FloatArray) -> Rectangle:
        """See :meth:`Surface.transformed`."""
        c = R @ np.asarray(self.center) + t
        eu = R @ np.asarray(self.axis_u)
        ev = R @ np.asarray(self.axis_v)
        return replace(
            self,
            center=(c[0], c[1], c[2]),
            axis_u=(eu[0], eu[1], eu[2]),
            axis_v=(ev[0], ev[1], ev[2]),
        )

    def to_dict(self) -> dict[str, Any]:
        """See :meth:`Surface.to_dict` (the plane ``normal . p + d = 0`` and the 4 corners included)."""
        n = self.normal
        out: dict[str, Any] = {
            "type": "rectangle",
            "name": self.name,
            "center": list(self.center),
            "axis_u": list(self.axis_u),
            "axis_v": list(self.axis_v),
            "size_u_m": 2 * self.half_u,
            "size_v_m": 2 * self.half_v,
            "normal": n.tolist(),
            "d": float(-n @ np.asarray(self.center)),
            "corners": self.corners().tolist(),
        }
        if self.board is not None:
            b = self.board
            out["board"] = {
                "cols": b.cols,
                "rows": b.rows,
                "square_m": b.square_m,
                "offset_u_m": b.offset_u_m,
                "offset_v_m": b.offset_v_m,
                "rotation_rad": b.rotation_rad,
                "corners": self.board_corners().tolist(),
            }
        return out


@dataclass(frozen=True)
class Cylinder(Surface):
    """The side surface of a finite cylinder (a pipe): axis through ``center`` along unit ``axis``.

    Attributes:
        center: centre of the axis segment, metres.
        axis: unit axis direction.
        radius_m: radius, metres.
        half_length_m: half length along the axis, metres (``inf`` for an infinite pipe).
    """

    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius_m: float = 0.1
    half_length_m: float = 1.0

    @classmethod
    def make(
        cls,
        center: ArrayLike,
        axis: ArrayLike,
        radius_m: float,
        length_m: float = float("inf"),
        name: str = "",
        albedo: float = 0.6,
    ) -> Cylinder:
        """Build a cylinder of ``radius_m`` and ``length_m`` (both metres)."""
        c = _vec3(center, "cylinder center")
        a = _unit(axis, "cylinder axis")
        if not (radius_m > 0 and length_m > 0):
            msg = f"cylinder {name!r}: radius and length must be positive, got {radius_m}, {length_m}"
            raise SimulationError(msg)
        return cls(
            name=name,
            albedo=albedo,
            center=(c[0], c[1], c[2]),
            axis=(a[0], a[1], a[2]),
            radius_m=float(radius_m),
            half_length_m=length_m / 2.0,
        )

    def intersect(self, origins: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray]:
        """See :meth:`Surface.intersect` (the nearer root whose axial position lies on the pipe)."""
        c, a, r = np.asarray(self.center), np.asarray(self.axis), self.radius_m
        w = origins - c
        dp = dirs - (dirs @ a)[:, None] * a
        wp = w - (w @ a)[:, None] * a
        qa = (dp * dp).sum(axis=1)
        qb = 2.0 * (dp * wp).sum(axis=1)
        qc = (wp * wp).sum(axis=1) - r * r
        disc = qb * qb - 4.0 * qa * qc
        ok = (disc >= 0.0) & (qa > 1e-18)
        sq = np.sqrt(np.where(ok, disc, 0.0))
        with np.errstate(divide="ignore", invalid="ignore"):
            # numerically stable roots
            q = -0.5 * (qb + np.copysign(sq, qb))
            r1 = q / qa
            r2 = qc / q
        t1 = np.where(ok, np.minimum(r1, r2), np.inf)
        t2 = np.where(ok, np.maximum(r1, r2), np.inf)
        t1 = np.where(np.isfinite(t1), t1, np.inf)
        t2 = np.where(np.isfinite(t2), t2, np.inf)
        best = np.full(dirs.shape[0], np.inf)
        for tc in (t2, t1):  # t1 last so that it wins when valid
            good = np.isfinite(tc) & (tc > T_MIN)
            with np.errstate(invalid="ignore"):
                axial = (w + np.where(good, tc, 0.0)[:, None] * dirs) @ a
            good &= np.abs(axial) <= self.half_length_m
            best = np.where(good, tc, best)
        p = w + np.where(np.isfinite(best), best, 0.0)[:, None] * dirs
        radial = p - (p @ a)[:, None] * a
        nrm = np.linalg.norm(radial, axis=1, keepdims=True)
        with np.errstate(divide="ignore", invalid="ignore"):
            normal = np.where(nrm > 0, radial / nrm, 0.0)
        normal[~np.isfinite(best)] = 0.0
        return best, normal

    def distance(self, points: FloatArray) -> FloatArray:
        """See :meth:`Surface.distance` (to the side surface, rims included)."""
        c, a = np.asarray(self.center), np.asarray(self.axis)
        w = points - c
        ax = w @ a
        rad = np.linalg.norm(w - np.outer(ax, a), axis=1)
        dr = np.abs(rad - self.radius_m)
        da = np.maximum(np.abs(ax) - self.half_length_m, 0.0)
        return np.sqrt(dr * dr + da * da)

    def transformed(self, R: FloatArray, t: FloatArray) -> Cylinder:
        """See :meth:`Surface.transformed`."""
        c = R @ np.asarray(self.center) + t
        a = R @ np.asarray(self.axis)
        return replace(self, center=(c[0], c[1], c[2]), axis=(a[0], a[1], a[2]))

    def to_dict(self) -> dict[str, Any]:
        """See :meth:`Surface.to_dict`."""
        return {
            "type": "cylinder",
            "name": self.name,
            "center": list(self.center),
            "axis": list(self.axis),
            "radius_m": self.radius_m,
            "length_m": 2 * self.half_length_m if np.isfinite(self.half_length_m) else None,
        }


def box(
    center: ArrayLike,
    size_m: ArrayLike,
    R: ArrayLike | None = None,
    name: str = "box",
    albedo: float = 0.6,
) -> list[Rectangle]:
    """The six outward-facing faces of a box as rectangles.

    Args:
        center: box centre (3,), metres.
        size_m: edge lengths (3,) along the box's own x, y, z axes, metres.
        R: rotation (3, 3) of the box's axes into the scene frame (identity when None).
        name: prefix of the faces' names (``name+x``, ``name-x``, ...).
        albedo: diffuse reflectance.
    """
    c = _vec3(center, "box center")
    s = _vec3(size_m, "box size")
    Rm = np.eye(3) if R is None else np.asarray(R, dtype=float)
    faces = []
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        for sign in (1.0, -1.0):
            n = sign * Rm[:, k]
            eu = Rm[:, i]
            ev = sign * Rm[:, j]  # eu x ev = sign * e_k: outward
            fc = c + n * s[k] / 2.0
            tag = "xyz"[k]
            faces.append(Rectangle.make(fc, eu, ev, s[i], s[j], f"{name}{'+' if sign > 0 else '-'}{tag}", albedo))
    return faces


@dataclass(frozen=True)
class Scene:
    """A set of surfaces in one frame. ``surface_id`` in ray casts is the index into ``surfaces``.

    Attributes:
        surfaces: the surfaces.
        frame: ``"body"`` (surfaces given in the vehicle's body frame) or ``"ned"`` (earth-fixed; rendering
            then needs a vehicle :class:`~lrsensor.frames.Pose`).
    """

    surfaces: tuple[Surface, ...] = field(default_factory=tuple)
    frame: Frame = "body"

    def __post_init__(self) -> None:
        if self.frame not in ("body", "ned"):
            msg = f"scene frame must be 'body' or 'ned', got {self.frame!r}"
            raise SimulationError(msg)

    @classmethod
    def of(cls, surfaces: Iterable[Surface], frame: Frame = "body") -> Scene:
        """Build a scene from any iterable of surfaces (nested lists from :func:`box` are flattened)."""
        flat: list[Surface] = []
        for s in surfaces:
            if isinstance(s, Surface):
                flat.append(s)
            else:
                flat.extend(s)  # type: ignore[arg-type]
        return cls(tuple(flat), frame)

    def __len__(self) -> int:
        return len(self.surfaces)

    def names(self) -> list[str]:
        """Surface names, index = surface id."""
        return [s.name for s in self.surfaces]

    def raycast(self, origins: ArrayLike, dirs: ArrayLike) -> tuple[FloatArray, IntArray, FloatArray]:
        """Nearest hit of each ray.

        Args:
            origins: ray origins (N, 3) or one origin (3,), scene frame, metres.
            dirs: ray directions (N, 3) (any length; ``t`` is in units of ``|dir|``).

        Returns:
            ``t`` (N,) (inf where nothing is hit), ``surface_id`` (N,) (-1 for none), outward ``normal`` (N, 3)
            of the surface hit (zero for none).
        """
        o, d = _rays(origins, dirs)
        n = d.shape[0]
        best_t = np.full(n, np.inf)
        best_id = np.full(n, -1, dtype=np.int64)
        best_n = np.zeros((n, 3))
        for k, s in enumerate(self.surfaces):
            t, nrm = s.intersect(o, d)
            closer = t < best_t
            if np.any(closer):
                best_t = np.where(closer, t, best_t)
                best_id[closer] = k
                best_n[closer] = nrm if nrm.ndim == 1 else nrm[closer]
        return best_t, best_id, best_n

    def distance_to_surface(self, points: ArrayLike) -> FloatArray:
        """Distance (N,) of points (N, 3) (scene frame, metres) to the nearest surface; inf for an empty scene."""
        p = check_points(points)
        out = np.full(p.shape[0], np.inf)
        for s in self.surfaces:
            out = np.minimum(out, s.distance(p))
        return out

    def nearest_surface(self, points: ArrayLike) -> tuple[FloatArray, IntArray]:
        """Distance (N,) to, and id (N,) of, the nearest surface of each point (N, 3)."""
        p = check_points(points)
        if not self.surfaces:
            return np.full(p.shape[0], np.inf), np.full(p.shape[0], -1, dtype=np.int64)
        dist = np.stack([s.distance(p) for s in self.surfaces])
        idx = np.argmin(dist, axis=0)
        return dist[idx, np.arange(p.shape[0])], idx.astype(np.int64)

    def transformed(self, R: ArrayLike, t: ArrayLike, frame: Frame) -> Scene:
        """Every surface moved by ``p' = R p + t``; the result is labelled with ``frame``."""
        Rm = np.asarray(R, dtype=float)
        tv = np.asarray(t, dtype=float)
        return Scene(tuple(s.transformed(Rm, tv) for s in self.surfaces), frame)

    def in_body(self, pose: Pose | None = None) -> Scene:
        """This scene in the vehicle's body frame (NED scenes need ``pose``; body scenes are returned as is)."""
        if self.frame == "body":
            return self
        if pose is None:
            msg = "the scene is in NED: a vehicle pose is needed to render or ray-cast it in the body frame"
            raise SimulationError(msg)
        R = pose.R_ned_from_body
        # p_body = R^T (p_ned - p)
        return self.transformed(R.T, -R.T @ pose.p_ned, "body")

    def to_dicts(self) -> list[dict[str, Any]]:
        """JSON-ready list of surface descriptions, index = surface id."""
        out = []
        for i, s in enumerate(self.surfaces):
            d = s.to_dict()
            d["id"] = i
            d["albedo"] = s.albedo
            out.append(d)
        return out


def stained(surfaces: Iterable[Surface], amount: float) -> list[Surface]:
    """Copies of ``surfaces`` with an albedo stain pattern of relative amplitude ``amount`` (0..1)."""
    return [replace(s, stain=float(amount)) for s in surfaces]


def surfaces_named(scene: Scene, names: Sequence[str]) -> list[int]:
    """Ids of the surfaces whose name is in ``names``."""
    return [i for i, s in enumerate(scene.surfaces) if s.name in names]
