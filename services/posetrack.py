"""Pose interpolation at a frame's capture time: slerp for attitude, linear for position, no extrapolation.

A :class:`PoseTrack` holds IMU/navigation samples (time, NED position, attitude) in time order. It answers the
pose at any time inside its span; outside the span it answers ``None`` (the frame is skipped and counted by
the caller, never guessed). It is thread-safe: a reader thread (serial IMU) appends while the frame loop
queries, and it can wait for a sample at or after a time (live sources).
"""

from __future__ import annotations

import bisect
import threading
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_from_quat, R_ned_from_body, quat_from_R, slerp

from .errors import ImuError


class PoseTrack:
    """Time-ordered pose samples with interpolation.

    Args:
        max_samples: keep at most this many samples (oldest are dropped); ``None`` keeps all (recorded logs).
    """

    def __init__(self, max_samples: int | None = None) -> None:
        self._t: list[int] = []
        self._q: list[NDArray[np.float64]] = []
        self._p: list[NDArray[np.float64]] = []
        self._max = max_samples
        self._cond = threading.Condition()
        self.rejected = 0

    def __len__(self) -> int:
        with self._cond:
            return len(self._t)

    @classmethod
    def from_arrays(cls, t_ns: Sequence[int] | NDArray[np.int64], poses: Sequence[Pose]) -> PoseTrack:
        """A track from sample times (M,) ns and poses (M,); times must be strictly increasing."""
        track = cls()
        for t, pose in zip(t_ns, poses, strict=True):
            track.append(int(t), pose)
        return track

    def append(self, t_ns: int, pose: Pose) -> bool:
        """Add a sample; returns False (and counts it in :attr:`rejected`) if it is not after the last one
        or not finite."""
        vals = np.array([pose.north_m, pose.east_m, pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad])
        with self._cond:
            if not np.all(np.isfinite(vals)) or (self._t and t_ns <= self._t[-1]):
                self.rejected += 1
                return False
            self._t.append(int(t_ns))
            self._q.append(quat_from_R(R_ned_from_body(pose.roll_rad, pose.pitch_rad, pose.yaw_rad)))
            self._p.append(vals[:3])
            if self._max is not None and len(self._t) > self._max:
                drop = len(self._t) - self._max
                del self._t[:drop], self._q[:drop], self._p[:drop]
            self._cond.notify_all()
        return True

    @property
    def span(self) -> tuple[int, int] | None:
        """``(first, last)`` sample time in ns, or None when empty."""
        with self._cond:
            return (self._t[0], self._t[-1]) if self._t else None

    def pose_at(self, t_ns: int) -> Pose | None:
        """The pose at ``t_ns``: slerp between the neighbouring attitudes, linear between positions.

        Returns None when ``t_ns`` lies outside ``[first, last]`` sample time (no extrapolation).
        """
        with self._cond:
            if not self._t or t_ns < self._t[0] or t_ns > self._t[-1]:
                return None
            i = bisect.bisect_left(self._t, t_ns)
            if self._t[i] == t_ns:
                q, p = self._q[i], self._p[i]
            else:
                t0, t1 = self._t[i - 1], self._t[i]
                a = (t_ns - t0) / (t1 - t0)
                q = slerp(self._q[i - 1], self._q[i], a)
                p = (1.0 - a) * self._p[i - 1] + a * self._p[i]
        return Pose.from_R_p(R_from_quat(q), p)

    def samples(self) -> tuple[list[int], list[Pose]]:
        """Copies of the sample times (ns) and poses."""
        with self._cond:
            t = list(self._t)
            qs = list(self._q)
            ps = list(self._p)
        return t, [Pose.from_R_p(R_from_quat(q), p) for q, p in zip(qs, ps, strict=True)]

    def wait_covering(self, t_ns: int, timeout_s: float) -> bool:
        """Block until a sample at or after ``t_ns`` exists (live IMU behind the camera), or the timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: bool(self._t) and self._t[-1] >= t_ns, timeout=timeout_s)


def check_monotonic(t_ns: NDArray[np.int64], where: str) -> None:
    """Raise :class:`ImuError` unless ``t_ns`` (M,) is strictly increasing."""
    if t_ns.size > 1 and np.any(np.diff(t_ns) <= 0):
        i = int(np.argmax(np.diff(t_ns) <= 0)) + 1
        msg = f"{where}: sample times must increase strictly; sample {i} ({t_ns[i]}) is not after {t_ns[i - 1]}"
        raise ImuError(msg)
