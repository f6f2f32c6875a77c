"""The map's planes as registration targets for :mod:`mapping.navigation`, and the association of scan points
with them (NED, metres)."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .navigation import NavConfig

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class PlaneLandmarks:
    """The map's planes as registration targets (P planes; NED, metres).

    Attributes:
        ids: (P,) plane ids.
        normal: (P, 3) unit normals toward the observing vehicles; ``d`` (P,) offsets: ``normal . p + d = 0``.
        centroid: (P, 3); ``u``, ``v``: (P, 3) in-plane axes (``u`` horizontal); ``u_range``, ``v_range``: (P, 2)
            the extent of the plane's points along them, relative to the centroid.
    """

    ids: NDArray[np.int64]
    normal: FloatArray
    d: FloatArray
    centroid: FloatArray
    u: FloatArray
    v: FloatArray
    u_range: FloatArray
    v_range: FloatArray
    #: per plane, robot -> (points it contributed, capture time of its first contribution, ns); empty when
    #: unknown (planes built from JSON without ``contributions``)
    contrib: tuple[Mapping[str, tuple[int, int]], ...] = ()

    def __len__(self) -> int:
        return int(self.ids.size)

    @classmethod
    def empty(cls) -> PlaneLandmarks:
        """No planes."""
        z3 = np.zeros((0, 3))
        z2 = np.zeros((0, 2))
        return cls(np.zeros(0, dtype=np.int64), z3, np.zeros(0), z3, z3, z3, z2, z2)

    @classmethod
    def from_planes(cls, planes: Iterable[Mapping[str, Any]], min_points: int = 0) -> PlaneLandmarks:
        """From plane dicts as :meth:`mapping.MapBuilder.map_json` serves them (``normal``, ``d``, ``extent``)."""
        rows = [p for p in planes if int(p.get("n_points", min_points)) >= min_points]
        if not rows:
            return cls.empty()

        def arr(key: str) -> FloatArray:
            return np.array([p["extent"][key] for p in rows], dtype=np.float64)

        return cls(
            np.array([int(p["id"]) for p in rows], dtype=np.int64),
            np.array([p["normal"] for p in rows], dtype=np.float64),
            np.array([p["d"] for p in rows], dtype=np.float64),
            arr("centroid"),
            arr("u"),
            arr("v"),
            arr("u_range_m"),
            arr("v_range_m"),
            tuple(
                {r: (int(c["n_points"]), int(c["first_ns"])) for r, c in p.get("contributions", {}).items()}
                for p in rows
            ),
        )


def subsample(points: FloatArray, n: int) -> FloatArray:
    """At most ``n`` rows of ``points`` (M, 3), evenly spaced in their order (deterministic)."""
    m = points.shape[0]
    if m <= n:
        return points
    return points[np.linspace(0, m - 1, n).round().astype(np.int64)]


def associate(
    p_ned: FloatArray, veh: FloatArray, lm: PlaneLandmarks, gate_m: FloatArray, cfg: NavConfig
) -> tuple[NDArray[np.int64], FloatArray]:
    """Nearest admissible plane per point: index into ``lm`` (-1: none) and the signed distance (M,).

    Admissible: facing the vehicle (``normal . (vehicle - p) > 0``), within ``gate_m`` (P,) of the plane, and
    inside its extent inflated by the configured margins.
    """
    dist = p_ned @ lm.normal.T + lm.d[None, :]  # (M, P)
    rel = p_ned[:, None, :] - lm.centroid[None, :, :]
    pu = np.einsum("mpk,pk->mp", rel, lm.u)
    pv = np.einsum("mpk,pk->mp", rel, lm.v)
    # v is the in-plane axis closest to down for vertical faces: its margin is the depth margin
    ok = (np.abs(dist) <= gate_m[None, :]) & ((veh - p_ned) @ lm.normal.T > 0.0)
    ok &= (pu >= lm.u_range[None, :, 0] - cfg.extent_margin_m) & (pu <= lm.u_range[None, :, 1] + cfg.extent_margin_m)
    ok &= (pv >= lm.v_range[None, :, 0] - cfg.extent_margin_down_m) & (
        pv <= lm.v_range[None, :, 1] + cfg.extent_margin_down_m
    )
    score = np.where(ok, np.abs(dist), np.inf)
    k = np.argmin(score, axis=1)
    rows = np.arange(p_ned.shape[0])
    best = np.where(np.isfinite(score[rows, k]), k, -1)
    return best.astype(np.int64), dist[rows, k]


# ---------------------------------------------------------------------------------------------- snapshots
#: The grid of snapshot times, ns: a scan registers against the map as it was at a multiple of this.
SNAPSHOT_GRID_NS = 100_000_000


def snapshot_time(t_ns: int, lag_ns: int, grid_ns: int = SNAPSHOT_GRID_NS) -> int:
    """The snapshot a scan captured at ``t_ns`` registers against: the grid time at or before ``t_ns - lag_ns``
    (ns). ``snapshot(T)`` is the merged map after committing, in the canonical order (trigger capture time, robot),
    exactly the observations whose key is before ``T``; it depends on the data only, not on when it was computed."""
    return ((int(t_ns) - int(lag_ns)) // grid_ns) * grid_ns


@dataclass(frozen=True)
class SnapshotRange:
    """The map's planes as they were at every grid time ``lo_ns <= T <= hi_ns`` (``snapshot(T)``, see
    :func:`snapshot_time`): no observation with a key in ``[lo_ns, hi_ns)`` exists.

    Attributes:
        lo_ns, hi_ns: the first and last grid time (ns) this state is ``snapshot(T)`` of.
        landmarks: the planes as registration targets.
        exact: False when the merge that made it could not keep the canonical order (an observation merged past
            its hold cap): then it is only the planes of about that time.
    """

    lo_ns: int
    hi_ns: int
    landmarks: PlaneLandmarks
    exact: bool = True


class LandmarkSnapshots:
    """The recent snapshots of the merged map (:class:`SnapshotRange`, disjoint and ascending), as the merger
    finalizes them: one process's builder records its own; a plane worker keeps those the merger publishes.

    Args:
        keep_ns: ranges whose ``hi_ns`` is more than this before the newest one's are dropped.
    """

    def __init__(self, keep_ns: int = 10_000_000_000) -> None:
        self.keep_ns = keep_ns
        self._ranges: list[SnapshotRange] = []

    def __len__(self) -> int:
        return len(self._ranges)

    @property
    def final_ns(self) -> int | None:
        """The latest grid time whose snapshot is known (None: none yet)."""
        return self._ranges[-1].hi_ns if self._ranges else None

    def put(self, rng: SnapshotRange) -> None:
        """Add a range (a later one wins where they overlap: e.g. re-sent on a worker's join)."""
        self._ranges = [r for r in self._ranges if r.hi_ns < rng.lo_ns or r.lo_ns > rng.hi_ns] + [rng]
        self._ranges.sort(key=lambda r: r.lo_ns)
        cut = self._ranges[-1].hi_ns - self.keep_ns
        self._ranges = [r for r in self._ranges if r.hi_ns >= cut]

    def get(self, t_grid_ns: int) -> SnapshotRange | None:
        """The range holding ``snapshot(t_grid_ns)``; None when not known (not final yet, or dropped)."""
        for r in reversed(self._ranges):
            if r.lo_ns <= t_grid_ns <= r.hi_ns:
                return r
            if r.hi_ns < t_grid_ns:
                return None
        return None

    def newest_before(self, t_grid_ns: int) -> SnapshotRange | None:
        """The latest range starting at or before ``t_grid_ns`` (else the oldest one): the fallback when the exact
        snapshot is late past its cap, or already dropped."""
        best = None
        for r in self._ranges:
            if r.lo_ns <= t_grid_ns:
                best = r
        return best if best is not None else (self._ranges[0] if self._ranges else None)

    def clear(self) -> None:
        """Forget every range (a restarted merger's times start afresh)."""
        self._ranges = []


def take_planes(lm: PlaneLandmarks, sel: NDArray[np.bool_]) -> PlaneLandmarks:
    """The planes of ``lm`` where ``sel`` (P,) is True (their contributors too, when known)."""
    idx = np.flatnonzero(sel)
    return PlaneLandmarks(
        lm.ids[idx],
        lm.normal[idx],
        lm.d[idx],
        lm.centroid[idx],
        lm.u[idx],
        lm.v[idx],
        lm.u_range[idx],
        lm.v_range[idx],
        tuple(lm.contrib[i] for i in idx) if lm.contrib else (),
    )
