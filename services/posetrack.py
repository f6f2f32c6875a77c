"""Pose interpolation at a frame's capture time: slerp for attitude, linear for position, no extrapolation.

A :class:`PoseTrack` holds IMU/navigation samples (time, NED position, attitude) in time order, in numpy
buffers. It answers the pose at any time inside its span; outside the span it answers ``None`` (the frame is
skipped and counted by the caller, never guessed). It is thread-safe: a reader thread (serial IMU) appends
while the frame loop queries, and a caller can wait for a sample at or after a time (live sources).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrsensor.frames import Pose, R_from_quat, slerp

FloatArray = NDArray[np.float64]


def quat_from_euler(roll_rad: ArrayLike, pitch_rad: ArrayLike, yaw_rad: ArrayLike) -> FloatArray:
    """Unit quaternions ``(w, x, y, z)`` (N, 4) of ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``, vectorized."""
    r = np.asarray(roll_rad, dtype=float) / 2
    p = np.asarray(pitch_rad, dtype=float) / 2
    y = np.asarray(yaw_rad, dtype=float) / 2
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    q = np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )
    return np.atleast_2d(q)


class PoseTrack:
    """Time-ordered pose samples with interpolation.

    Args:
        max_samples: keep at most about this many samples (oldest dropped); ``None`` keeps all (recorded logs).
    """

    def __init__(self, max_samples: int | None = None) -> None:
        self._t = np.empty(0, np.int64)
        self._q = np.empty((0, 4))
        self._p = np.empty((0, 3))
        self._n = 0
        self._max = max_samples
        self._cond = threading.Condition()
        self.rejected = 0

    def __len__(self) -> int:
        with self._cond:
            return self._n

    @classmethod
    def from_arrays(cls, t_ns: Sequence[int] | NDArray[np.int64], poses: Sequence[Pose]) -> PoseTrack:
        """A track from sample times (M,) ns and poses (M,); samples not after their predecessor are rejected."""
        track = cls()
        a = np.array([[p.north_m, p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad] for p in poses])
        track.extend(np.asarray(t_ns, dtype=np.int64), a.reshape(-1, 6))
        return track

    def _reserve(self, extra: int) -> None:
        need = self._n + extra
        if need <= self._t.size:
            return
        cap = max(need, 2 * self._t.size, 64)
        for name, shape in (("_t", (cap,)), ("_q", (cap, 4)), ("_p", (cap, 3))):
            old = getattr(self, name)
            new = np.empty(shape, old.dtype)
            new[: self._n] = old[: self._n]
            setattr(self, name, new)

    def _trim(self) -> None:
        if self._max is not None and self._n > 2 * self._max:
            drop = self._n - self._max
            for name in ("_t", "_q", "_p"):
                arr = getattr(self, name)
                arr[: self._max] = arr[drop : self._n].copy()
            self._n = self._max

    def extend(self, t_ns: NDArray[np.int64], ned_rpy: FloatArray) -> int:
        """Add samples: times (M,) ns and rows ``north, east, down, roll, pitch, yaw`` (M, 6) in m and rad.

        Rows that are not finite or not after the previous accepted sample are rejected (counted in
        :attr:`rejected`). Returns the number accepted.
        """
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(ned_rpy, dtype=float).reshape(-1, 6)
        if t.size != v.shape[0]:
            msg = f"{t.size} sample times for {v.shape[0]} poses"
            raise ValueError(msg)
        with self._cond:
            last = self._t[self._n - 1] if self._n else np.iinfo(np.int64).min
            ok = np.all(np.isfinite(v), axis=1)
            # keep a row only if it is after the running maximum of the accepted times before it
            prev_max = np.maximum.accumulate(np.concatenate([[last], np.where(ok, t, np.iinfo(np.int64).min)]))[:-1]
            keep = ok & (t > prev_max)
            k = int(keep.sum())
            self.rejected += int(t.size - k)
            if k:
                self._reserve(k)
                sl = slice(self._n, self._n + k)
                self._t[sl] = t[keep]
                self._p[sl] = v[keep, :3]
                self._q[sl] = quat_from_euler(v[keep, 3], v[keep, 4], v[keep, 5])
                self._n += k
                self._trim()
                self._cond.notify_all()
        return k

    def append(self, t_ns: int, pose: Pose) -> bool:
        """Add one sample; False (and counted in :attr:`rejected`) if not finite or not after the last one."""
        row = np.array([[pose.north_m, pose.east_m, pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad]])
        return self.extend(np.array([int(t_ns)], np.int64), row) == 1

    @property
    def span(self) -> tuple[int, int] | None:
        """``(first, last)`` sample time in ns, or None when empty."""
        with self._cond:
            return (int(self._t[0]), int(self._t[self._n - 1])) if self._n else None

    def pose_at(self, t_ns: int) -> Pose | None:
        """The pose at ``t_ns``: slerp between the neighbouring attitudes, linear between positions.

        Returns None when ``t_ns`` lies outside ``[first, last]`` sample time (no extrapolation).
        """
        with self._cond:
            n = self._n
            if not n or t_ns < self._t[0] or t_ns > self._t[n - 1]:
                return None
            i = int(np.searchsorted(self._t[:n], t_ns, side="left"))
            if self._t[i] == t_ns:
                q, p = self._q[i].copy(), self._p[i].copy()
            else:
                t0, t1 = int(self._t[i - 1]), int(self._t[i])
                a = (t_ns - t0) / (t1 - t0)
                q = slerp(self._q[i - 1], self._q[i], a)
                p = (1.0 - a) * self._p[i - 1] + a * self._p[i]
        return Pose.from_R_p(R_from_quat(q), p)

    def samples(self) -> tuple[list[int], list[Pose]]:
        """Copies of the sample times (ns) and poses."""
        with self._cond:
            t = self._t[: self._n].copy()
            q = self._q[: self._n].copy()
            p = self._p[: self._n].copy()
        return [int(x) for x in t], [Pose.from_R_p(R_from_quat(qq), pp) for qq, pp in zip(q, p, strict=True)]

    def wait_covering(self, t_ns: int, timeout_s: float) -> bool:
        """Block until a sample at or after ``t_ns`` exists (live IMU behind the camera), or the timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._n > 0 and self._t[self._n - 1] >= t_ns, timeout=timeout_s)
