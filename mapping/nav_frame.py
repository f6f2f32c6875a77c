"""The fleet frame: from the frame the fleet builds its map in to NED (see docs/navigation.md)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

FloatArray = NDArray[np.float64]


def rot2(a: float) -> FloatArray:
    """The 2x2 turn by ``a`` radians (north, east)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


@dataclass(frozen=True)
class NavFrame:
    """From the frame the fleet builds its map in to NED: a turn by ``-yaw_rad`` about ``pivot_ne`` (north, east),
    then a shift by ``shift_ne``.

    Registration makes the robots agree with each other and with the map, but the map's heading is whatever the
    compasses of its first observations said, and its position what the first placements made of the launch
    fixes. :meth:`mapping.navigation.Navigator.frame` estimates the frame (from the launch points with smoothing,
    else the fleet's mean heading correction); the map and the poses are served through it (the map itself keeps
    its exact statistics in its own frame). See docs/navigation.md.
    """

    yaw_rad: float = 0.0
    pivot_ne: tuple[float, float] = (0.0, 0.0)
    #: then moved by this (north, east), metres
    shift_ne: tuple[float, float] = (0.0, 0.0)

    @property
    def identity(self) -> bool:
        """Whether the frame changes nothing."""
        return self.yaw_rad == 0.0 and self.shift_ne == (0.0, 0.0)

    def _rot(self) -> FloatArray:
        r = np.eye(3)
        r[0:2, 0:2] = rot2(-self.yaw_rad)
        return r

    def points(self, p: Any) -> FloatArray:
        """Points (N, 3) from the map frame to NED."""
        q = np.asarray(p, dtype=np.float64).reshape(-1, 3)
        piv = np.array([self.pivot_ne[0], self.pivot_ne[1], 0.0])
        return (q - piv) @ self._rot().T + piv + np.array([self.shift_ne[0], self.shift_ne[1], 0.0])

    def vectors(self, v: Any) -> FloatArray:
        """Directions (N, 3) from the map frame to NED."""
        return np.asarray(v, dtype=np.float64).reshape(-1, 3) @ self._rot().T

    def pose(self, pose: Pose) -> Pose:
        """A pose from the map frame to NED."""
        if self.identity:
            return pose
        p = self.points(pose.p_ned)[0]
        return Pose(float(p[0]), float(p[1]), pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad - self.yaw_rad)

    def plane_json(self, plane: dict[str, Any]) -> dict[str, Any]:
        """A plane dict (:meth:`mapping.MapBuilder.map_json`) from the map frame to NED (removals unchanged)."""
        if self.identity or "normal" not in plane:
            return plane
        out = dict(plane)
        n = self.vectors(plane["normal"])[0]
        ext = dict(plane["extent"])
        c = self.points(ext["centroid"])[0]
        out["normal"] = [float(x) for x in n]
        out["d"] = float(-n @ c)
        ext["centroid"] = [float(x) for x in c]
        ext["u"] = [float(x) for x in self.vectors(ext["u"])[0]]
        ext["v"] = [float(x) for x in self.vectors(ext["v"])[0]]
        corners = self.points(ext["corners"])
        ext["corners"] = [[float(x) for x in row] for row in corners]
        lo, hi = np.asarray(ext["aabb_min"], dtype=float), np.asarray(ext["aabb_max"], dtype=float)
        box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        turned = self.points(box)
        ext["aabb_min"] = [float(x) for x in turned.min(axis=0)]
        ext["aabb_max"] = [float(x) for x in turned.max(axis=0)]
        out["extent"] = ext
        return out

    def to_json(self) -> dict[str, Any]:
        """``{"yaw_deg", "pivot_ne", "shift_ne"}``."""
        return {"yaw_deg": math.degrees(self.yaw_rad), "pivot_ne": list(self.pivot_ne), "shift_ne": list(self.shift_ne)}
