"""Frames and rotations (NED, body, camera) in the Fossen ZYX convention.

``R_ned_from_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; angles in radians. Quaternions are ``(w, x, y, z)``
unit quaternions of the same rotation (active, ``v_ned = q * v_body * q^-1``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GeometryError

FloatArray = NDArray[np.float64]

#: Default camera mounting of the paper, eq. (17): x_b = z_c, y_b = x_c, z_b = y_c.
R_CAM_FROM_BODY_DEFAULT: FloatArray = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])


def rot_x(angle_rad: float) -> FloatArray:
    """Active rotation about x by ``angle_rad``, shape (3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle_rad: float) -> FloatArray:
    """Active rotation about y by ``angle_rad``, shape (3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle_rad: float) -> FloatArray:
    """Active rotation about z by ``angle_rad``, shape (3, 3)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def R_ned_from_body(roll_rad: float, pitch_rad: float, yaw_rad: float) -> FloatArray:
    """Rotation of body vectors into NED, ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (Fossen ZYX), shape (3, 3)."""
    return rot_z(yaw_rad) @ rot_y(pitch_rad) @ rot_x(roll_rad)


def euler_from_R_ned_from_body(R: ArrayLike) -> tuple[float, float, float]:
    """Inverse of :func:`R_ned_from_body`: ``(roll, pitch, yaw)`` in radians, pitch in [-pi/2, pi/2]."""
    m = np.asarray(R, dtype=float)
    pitch = float(np.arcsin(np.clip(-m[2, 0], -1.0, 1.0)))
    roll = float(np.arctan2(m[2, 1], m[2, 2]))
    yaw = float(np.arctan2(m[1, 0], m[0, 0]))
    return roll, pitch, yaw


def quat_from_R(R: ArrayLike) -> FloatArray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix, ``w >= 0``, shape (4,)."""
    m = np.asarray(R, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = np.array([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = np.array([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = np.array([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    q = q / np.linalg.norm(q)
    return -q if q[0] < 0 else q


def R_from_quat(q: ArrayLike) -> FloatArray:
    """Rotation matrix of a quaternion ``(w, x, y, z)`` (normalised first), shape (3, 3)."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def slerp(q0: ArrayLike, q1: ArrayLike, t: float) -> FloatArray:
    """Spherical linear interpolation between unit quaternions ``q0`` (t=0) and ``q1`` (t=1), shape (4,)."""
    a = np.asarray(q0, dtype=float)
    b = np.asarray(q1, dtype=float)
    dot = float(np.dot(a, b))
    if dot < 0.0:
        b, dot = -b, -dot
    if dot > 0.9995:
        q = a + t * (b - a)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    q = (np.sin((1 - t) * theta) * a + np.sin(t * theta) * b) / np.sin(theta)
    return q / np.linalg.norm(q)


@dataclass(frozen=True)
class Pose:
    """Vehicle pose in NED: position of the body origin (m) and ZYX attitude (rad)."""

    north_m: float
    east_m: float
    down_m: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float

    @property
    def p_ned(self) -> FloatArray:
        """Position of the body origin in NED, shape (3,), metres."""
        return np.array([self.north_m, self.east_m, self.down_m])

    @property
    def R_ned_from_body(self) -> FloatArray:
        """Attitude as ``R_ned_from_body``, shape (3, 3)."""
        return R_ned_from_body(self.roll_rad, self.pitch_rad, self.yaw_rad)

    @classmethod
    def identity(cls) -> Pose:
        """The pose at the NED origin with zero attitude."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def from_R_p(cls, R_ned_from_body_: ArrayLike, p_ned: ArrayLike) -> Pose:
        """Build a pose from a rotation matrix and a NED position."""
        roll, pitch, yaw = euler_from_R_ned_from_body(R_ned_from_body_)
        p = np.asarray(p_ned, dtype=float)
        return cls(float(p[0]), float(p[1]), float(p[2]), roll, pitch, yaw)


def check_points(points: ArrayLike, name: str = "points") -> FloatArray:
    """Return ``points`` as a float64 array of shape (N, 3), or raise :class:`GeometryError`."""
    p = np.asarray(points, dtype=float)
    if p.ndim == 1 and p.shape[0] == 3:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        msg = f"{name} must have shape (N, 3), got {p.shape}"
        raise GeometryError(msg)
    return p


def body_to_ned(points_body: ArrayLike, pose: Pose) -> FloatArray:
    """Transform body-frame points to NED with a vehicle pose: ``p_ned = R p_body + t``, shape (N, 3)."""
    p = check_points(points_body, "points_body")
    return p @ pose.R_ned_from_body.T + pose.p_ned


def ned_to_body(points_ned: ArrayLike, pose: Pose) -> FloatArray:
    """Inverse of :func:`body_to_ned`, shape (N, 3)."""
    p = check_points(points_ned, "points_ned")
    return (p - pose.p_ned) @ pose.R_ned_from_body
