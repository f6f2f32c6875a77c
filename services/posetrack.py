"""Pose interpolation at a frame's capture time from what the pose source knows, and only that.

A pose source reports three things, not always together: the attitude (roll, pitch, yaw), the depth, and
sometimes a horizontal position fix (north, east). An OpenROV and a BlueROV2 without a DVL or USBL report
attitude and depth only; a CSV log may leave ``north_m``/``east_m`` empty in a row; ArduSub sends ATTITUDE,
depth and LOCAL_POSITION_NED as separate messages at their own times. A :class:`PoseTrack` therefore keeps
three time series in numpy buffers, each in time order:

* attitude samples (unit quaternions ``(w, x, y, z)`` of ``R_ned_from_body``),
* depth samples (``down_m``),
* horizontal fixes (``north_m``, ``east_m``).

The pose at a time ``t`` (:meth:`PoseTrack.pose_at`):

* attitude: slerp between the two attitude samples around ``t``; depth: linear between the two depth samples
  around ``t``. Both must exist (no extrapolation), and, when the track has a ``max_gap_s`` (live sources),
  the two samples must be at most that far apart: a link that went silent gives no pose for the frames in
  its gap, never an old one. No attitude or no depth at ``t``: no pose at all (``None``; the caller skips
  and counts the frame).
* horizontal position: linear between the two fixes around ``t`` when they are at most ``max_fix_gap_s``
  apart (default :data:`DEFAULT_MAX_FIX_GAP_S`: a DVL at 5 Hz or a USBL at 1 Hz is interpolated, a launch fix
  an hour ago is not carried along); a fix exactly at ``t`` is used as it is. Otherwise the position is
  unknown: the pose's ``north_m`` and ``east_m`` are NaN (:func:`has_fix` says False), never 0 and never the
  last fix. The cloud then travels with ``north_m``/``east_m`` null (see :mod:`services.wire`).

Why NaN and not ``Optional``: :class:`lrsensor.frames.Pose` is the one pose type of every package; NaN keeps
its fields floats, and whatever would use an unknown position by mistake turns NaN instead of a plausible
wrong place (the style of degenerate geometry in pytransform3d). :func:`has_fix` is the test to use.

Why three series and not rows with holes: a MAVLink autopilot stamps each message with its own time; filling
a row's depth from the last depth message would be up to one depth period old (4 cm at 0.2 m/s and 5 Hz).

Retention: recorded logs keep every sample; live sources keep at least the last ``keep_s`` seconds (and at
most about ``2 * max_samples`` samples a series), so that a frame processed late is still posed from the
samples around its capture time. The track is thread-safe: a reader thread appends while the frame loop
queries, and a caller can wait for the samples that cover a time (:meth:`PoseTrack.wait_covering`).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from lrsensor.frames import Pose, R_from_quat, slerp

FloatArray = NDArray[np.float64]

#: Longest time between two horizontal fixes that are interpolated, seconds.
DEFAULT_MAX_FIX_GAP_S = 2.0
_INT64_MIN = np.iinfo(np.int64).min


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


def has_fix(pose: Pose) -> bool:
    """Whether ``pose`` has a horizontal position (``north_m`` and ``east_m`` finite)."""
    return math.isfinite(pose.north_m) and math.isfinite(pose.east_m)


class _Series:
    """One time-ordered series: times (N,) int64 ns and values (N, width) float64 in growable buffers."""

    def __init__(self, width: int) -> None:
        self.t = np.empty(0, np.int64)
        self.v = np.empty((0, width))
        self.n = 0

    @property
    def last_t(self) -> int:
        return int(self.t[self.n - 1]) if self.n else _INT64_MIN

    def add(self, t: NDArray[np.int64], v: FloatArray) -> int:
        """Append rows whose time is after every earlier accepted one; returns how many were accepted."""
        if not t.size:
            return 0
        prev_max = np.maximum.accumulate(np.concatenate([[self.last_t], t]))[:-1]
        keep = t > prev_max
        k = int(keep.sum())
        if k:
            need = self.n + k
            if need > self.t.size:
                cap = max(need, 2 * self.t.size, 64)
                t_new = np.empty(cap, np.int64)
                v_new = np.empty((cap, self.v.shape[1]))
                t_new[: self.n] = self.t[: self.n]
                v_new[: self.n] = self.v[: self.n]
                self.t, self.v = t_new, v_new
            self.t[self.n : need] = t[keep]
            self.v[self.n : need] = v[keep]
            self.n = need
        return k

    def trim(self, max_samples: int | None, keep_ns: int | None) -> None:
        """Drop the oldest samples in batches: beyond ``2 * max_samples``, or older than twice ``keep_ns``."""
        drop = 0
        if max_samples is not None and self.n > 2 * max_samples:
            drop = self.n - max_samples
        if keep_ns is not None and self.n and self.t[0] < self.last_t - 2 * keep_ns:
            drop = max(drop, int(np.searchsorted(self.t[: self.n], self.last_t - keep_ns, side="left")))
        if drop:
            keep = self.n - drop
            self.t[:keep] = self.t[drop : self.n].copy()
            self.v[:keep] = self.v[drop : self.n].copy()
            self.n = keep

    def bracket(self, t_ns: int, max_gap_ns: int | None) -> tuple[int, int, float] | None:
        """Indices ``(i0, i1)`` of the samples around ``t_ns`` and its fraction between them, or None when
        ``t_ns`` is outside the series or the two are more than ``max_gap_ns`` apart."""
        n = self.n
        if not n or t_ns < self.t[0] or t_ns > self.t[n - 1]:
            return None
        i = int(np.searchsorted(self.t[:n], t_ns, side="left"))
        if self.t[i] == t_ns:
            return i, i, 0.0
        t0, t1 = int(self.t[i - 1]), int(self.t[i])
        if max_gap_ns is not None and t1 - t0 > max_gap_ns:
            return None
        return i - 1, i, (t_ns - t0) / (t1 - t0)

    def linear(self, t_ns: int, max_gap_ns: int | None) -> FloatArray | None:
        b = self.bracket(t_ns, max_gap_ns)
        if b is None:
            return None
        i0, i1, a = b
        return np.asarray((1.0 - a) * self.v[i0] + a * self.v[i1], dtype=float)


class PoseTrack:
    """Attitude, depth and horizontal-fix samples with interpolation (see the module docstring).

    Args:
        max_samples: keep at most about this many samples a series (oldest dropped); ``None``: no count bound.
        keep_s: keep at least the samples of the last ``keep_s`` seconds (up to twice that before trimming);
            ``None``: no time bound (recorded logs keep everything).
        max_gap_s: two attitude (or depth) samples further apart than this are not interpolated between:
            the frames in between get no pose (a silent link). ``None``: any gap is interpolated (logs).
        max_fix_gap_s: two horizontal fixes further apart than this are not interpolated between: the
            position of a frame in between is unknown.
    """

    def __init__(
        self,
        max_samples: int | None = None,
        *,
        keep_s: float | None = None,
        max_gap_s: float | None = None,
        max_fix_gap_s: float = DEFAULT_MAX_FIX_GAP_S,
    ) -> None:
        self._att = _Series(4)
        self._depth = _Series(1)
        self._fix = _Series(2)
        self._max = max_samples
        self._keep_ns = None if keep_s is None else int(keep_s * 1e9)
        self.max_gap_ns = None if max_gap_s is None else int(max_gap_s * 1e9)
        self.max_fix_gap_ns = int(max_fix_gap_s * 1e9)
        self._cond = threading.Condition()
        self.rejected = 0

    def __len__(self) -> int:
        """Attitude samples held."""
        with self._cond:
            return self._att.n

    @property
    def n_fixes(self) -> int:
        """Horizontal fixes held."""
        with self._cond:
            return self._fix.n

    @classmethod
    def from_arrays(cls, t_ns: Sequence[int] | NDArray[np.int64], poses: Sequence[Pose]) -> PoseTrack:
        """A track from sample times (M,) ns and poses (M,) (NaN ``north_m``/``east_m``: no fix in that
        sample); samples not after their predecessor are rejected."""
        track = cls()
        a = np.array([[p.north_m, p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad] for p in poses])
        track.extend(np.asarray(t_ns, dtype=np.int64), a.reshape(-1, 6))
        return track

    def _trimmed(self) -> None:
        for s in (self._att, self._depth, self._fix):
            s.trim(self._max, self._keep_ns)
        self._cond.notify_all()

    def extend(self, t_ns: NDArray[np.int64], ned_rpy: FloatArray) -> int:
        """Add whole samples: times (M,) ns and rows ``north, east, down, roll, pitch, yaw`` (M, 6), m and rad.

        ``north`` and ``east`` both NaN: the sample has attitude and depth but no horizontal fix. A row whose
        depth or angles are not finite, that has only one of north/east, an infinite one, or that is not after
        the previous accepted sample is rejected (counted in :attr:`rejected`). Returns the number accepted.
        """
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(ned_rpy, dtype=float).reshape(-1, 6)
        if t.size != v.shape[0]:
            msg = f"{t.size} sample times for {v.shape[0]} poses"
            raise ValueError(msg)
        ne_nan = np.isnan(v[:, :2])
        fixed = ~ne_nan.any(axis=1)
        ok = np.all(np.isfinite(v[:, 2:]), axis=1) & (fixed | ne_nan.all(axis=1))
        ok &= np.all(np.isfinite(v[:, :2]), axis=1) | ~fixed
        with self._cond:
            # one order for the whole rows: a row counts only if it is after every earlier accepted row
            last = max(self._att.last_t, self._depth.last_t)
            prev_max = np.maximum.accumulate(np.concatenate([[last], np.where(ok, t, _INT64_MIN)]))[:-1]
            keep = ok & (t > prev_max)
            k = int(keep.sum())
            self.rejected += int(t.size - k)
            if k:
                tk, vk = t[keep], v[keep]
                self._att.add(tk, quat_from_euler(vk[:, 3], vk[:, 4], vk[:, 5]))
                self._depth.add(tk, vk[:, 2:3])
                fk = fixed[keep]
                self._fix.add(tk[fk], vk[fk, :2])
                self._trimmed()
        return k

    def append(self, t_ns: int, pose: Pose) -> bool:
        """Add one whole sample (NaN north/east: no fix); False (counted in :attr:`rejected`) if refused."""
        row = np.array([[pose.north_m, pose.east_m, pose.down_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad]])
        return self.extend(np.array([int(t_ns)], np.int64), row) == 1

    def _add_one(self, series: _Series, t_ns: int, values: Sequence[float]) -> bool:
        v = np.asarray(values, dtype=float).reshape(1, -1)
        if not np.all(np.isfinite(v)):
            with self._cond:
                self.rejected += 1
            return False
        with self._cond:
            ok = series.add(np.array([int(t_ns)], np.int64), v) == 1
            if ok:
                self._trimmed()
            else:
                self.rejected += 1
        return ok

    def add_attitude(self, t_ns: int, roll_rad: float, pitch_rad: float, yaw_rad: float) -> bool:
        """Add an attitude sample (a source that reports it on its own); False if refused (counted)."""
        if not all(math.isfinite(x) for x in (roll_rad, pitch_rad, yaw_rad)):
            with self._cond:
                self.rejected += 1
            return False
        return self._add_one(self._att, t_ns, quat_from_euler(roll_rad, pitch_rad, yaw_rad)[0])

    def add_depth(self, t_ns: int, down_m: float) -> bool:
        """Add a depth sample (m, positive down); False if refused (counted)."""
        return self._add_one(self._depth, t_ns, (down_m,))

    def add_fix(self, t_ns: int, north_m: float, east_m: float) -> bool:
        """Add a horizontal position fix (m, NED); False if refused (counted)."""
        return self._add_one(self._fix, t_ns, (north_m, east_m))

    @property
    def span(self) -> tuple[int, int] | None:
        """``(first, last)`` time in ns where attitude and depth both exist, or None."""
        with self._cond:
            a, d = self._att, self._depth
            if not a.n or not d.n:
                return None
            lo, hi = max(int(a.t[0]), int(d.t[0])), min(a.last_t, d.last_t)
            return (lo, hi) if lo <= hi else None

    def pose_at(self, t_ns: int) -> Pose | None:
        """The pose at ``t_ns`` (see the module docstring): None without attitude or depth around ``t_ns``;
        NaN ``north_m``/``east_m`` without fixes around it."""
        with self._cond:
            b = self._att.bracket(t_ns, self.max_gap_ns)
            down = self._depth.linear(t_ns, self.max_gap_ns)
            if b is None or down is None:
                return None
            i0, i1, a = b
            q = self._att.v[i0].copy() if i0 == i1 else slerp(self._att.v[i0], self._att.v[i1], a)
            ne = self._fix.linear(t_ns, self.max_fix_gap_ns)
        if ne is None:
            ne = np.array([math.nan, math.nan])
        return Pose.from_R_p(R_from_quat(q), [ne[0], ne[1], down[0]])

    def why_no_pose(self, t_ns: int) -> str:
        """Why :meth:`pose_at` gives no pose at ``t_ns`` (for logs): which series does not cover it."""
        with self._cond:
            parts = []
            for name, s in (("attitude", self._att), ("depth", self._depth)):
                if not s.n:
                    parts.append(f"no {name} sample yet")
                elif t_ns < s.t[0] or t_ns > s.last_t:
                    parts.append(f"{name} samples span [{int(s.t[0])}, {s.last_t}] ns")
                elif s.bracket(t_ns, self.max_gap_ns) is None:
                    parts.append(f"{name} samples around it are more than {self.max_gap_ns} ns apart")
        return "; ".join(parts) or "posed"

    def samples(self) -> tuple[list[int], list[Pose]]:
        """The attitude sample times (ns) and the poses at them (NaN north/east where there is no fix)."""
        with self._cond:
            t = self._att.t[: self._att.n].copy()
        poses = [self.pose_at(int(x)) for x in t]
        keep = [(int(x), p) for x, p in zip(t, poses, strict=True) if p is not None]
        return [x for x, _ in keep], [p for _, p in keep]

    def series(self) -> dict[str, tuple[NDArray[np.int64], FloatArray]]:
        """Copies of the three series: ``attitude`` (N, 4) quaternions, ``depth`` (N, 1) m, ``fix`` (N, 2) m."""
        with self._cond:
            return {
                name: (s.t[: s.n].copy(), s.v[: s.n].copy())
                for name, s in (("attitude", self._att), ("depth", self._depth), ("fix", self._fix))
            }

    def _covers(self, t_ns: int) -> bool:
        if self._att.last_t < t_ns or self._depth.last_t < t_ns:
            return False
        # a live fix stream (its last fix close to t) is waited for too; a source without fixes is not
        f = self._fix
        return not (f.n and t_ns - self.max_fix_gap_ns <= f.last_t < t_ns)

    def _hopeless(self, t_ns: int) -> bool:
        """No later sample can pose ``t_ns``: the samples before it are older than the allowed gap."""
        if self.max_gap_ns is None:
            return False
        return any(s.n and s.last_t < t_ns - self.max_gap_ns for s in (self._att, self._depth))

    def pose_waiting(self, t_ns: int, timeout_s: float) -> Pose | None:
        """The pose at ``t_ns`` from a live source, waiting (at most ``timeout_s``) for the samples after it.

        A pose without a fix waits too: a source may send the depth after a frame before the fix that goes
        with it. A source that sends no fixes, or fell silent, is not waited for (see :meth:`wait_covering`)."""
        pose = self.pose_at(t_ns)
        if (pose is None or not has_fix(pose)) and self.wait_covering(t_ns, timeout_s):
            pose = self.pose_at(t_ns)
        return pose

    def wait_covering(self, t_ns: int, timeout_s: float) -> bool:
        """Block until attitude and depth samples at or after ``t_ns`` exist (a live source behind the camera;
        also the next fix while fixes are coming), or the timeout. Returns at once, False, when the source
        fell silent for longer than ``max_gap_s`` before ``t_ns``: no later sample could pose it."""
        with self._cond:
            self._cond.wait_for(lambda: self._covers(t_ns) or self._hopeless(t_ns), timeout=timeout_s)
            return self._att.last_t >= t_ns and self._depth.last_t >= t_ns
