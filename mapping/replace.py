"""Re-placing clouds whose poses a smoother revised: the map follows the poses.

Every observation that entered the map (:class:`Placement`, kept by :class:`mapping.MapBuilder` when
``keep_placements`` is on) remembers the thinned, quantized points it claimed and which cloud each came from.
When a robot's past poses move (:mod:`mapping.smoother`), each affected cloud's points are moved by the rigid
change of its pose (``p' = R' R^T (p - v) + v'``; with roll and pitch measured, ``R' R^T`` is the turn by the
change of the yaw correction), the observation's exact statistics are recomputed from them, and the map is
rebuilt by fusing every observation again in its original order (:func:`rebuild`). Segmentation is not redone:
within one extraction window (about a second) the poses barely move relative to each other.

Points rather than moments: a plane's statistics alone would transform exactly (``sum p -> R sum p + n t``), but
its bounding box and export voxels, which association and extents use, need the points. They are the thinned
points already in the map (one per 1 cm voxel of a cloud), held as int32, and only while a smoother may still
move them: an observation whose clouds are all older than its robot's smoothing window is frozen (fused once
into a base map that every rebuild starts from, its points dropped), so memory and a rebuild's cost follow the
window, not the dive.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

from .ned import quantize
from .plane_map import PlaneMap, PlaneRecord
from .types import MapChange, MapConfig

FloatArray = NDArray[np.float64]


@dataclass
class Placement:
    """One observation as it entered the map.

    Attributes:
        robot: whose window it came from.
        points_q: (N, 3) int32 quanta, NED, as placed now.
        cloud_t: (N,) int64 capture time of each point's cloud.
        normal: (3,) the window's oriented normal, NED, as placed now.
        first_ns, last_ns: the capture times of the window's new clouds.
        record: the observation's exact record as placed now.
    """

    robot: str
    points_q: NDArray[np.int32]
    cloud_t: NDArray[np.int64]
    normal: FloatArray
    first_ns: int
    last_ns: int
    record: PlaneRecord


def _rz(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def move_placement(pl: Placement, old: dict[int, Pose], new: dict[int, Pose], cfg: MapConfig) -> bool:
    """Move ``pl``'s points of every cloud whose pose changed from ``old`` to ``new`` (t_ns -> Pose; clouds
    missing from ``new`` stay); recomputes its record. Returns whether anything moved."""
    times = np.unique(pl.cloud_t)
    moved_any = False
    p = pl.points_q.astype(np.float64) * cfg.quantum_m
    turn = 0.0
    weight = 0
    for t in times:
        t = int(t)
        a, b = old.get(t), new.get(t)
        if a is None or b is None:
            continue
        dyaw = b.yaw_rad - a.yaw_rad
        va, vb = a.p_ned, b.p_ned
        if abs(dyaw) < 1e-9 and float(np.abs(vb - va).max()) < 0.5 * cfg.quantum_m:
            continue
        sel = pl.cloud_t == t
        p[sel] = (p[sel] - va) @ _rz(dyaw).T + vb
        turn += dyaw * int(sel.sum())
        weight += int(sel.sum())
        moved_any = True
    if not moved_any:
        return False
    pl.points_q = quantize(p, cfg.quantum_m, "re-placed observation")
    pl.normal = _rz(turn / weight) @ pl.normal
    pl.record = PlaneRecord.from_points(pl.points_q, pl.normal, pl.robot, pl.first_ns, pl.last_ns, cfg, pl.record.noise)
    return True


def rebuild(placements: list[Placement], cfg: MapConfig, frozen: PlaneMap | None = None) -> PlaneMap:
    """A new map: the ``frozen`` map (observations no smoother moves any more, fused once) and every other
    observation fused again on top, in order (where the association decides as before, planes keep their ids)."""
    m = PlaneMap(cfg)
    if frozen is not None:
        m.planes = dict(frozen.planes)  # MapPlanes are never edited: sharing them is safe
        m.next_id = frozen.next_id
    for pl in placements:
        m.add(pl.record)
    return m


def freeze(
    placements: list[Placement], before_ns: dict[str, int], frozen: PlaneMap | None, cfg: MapConfig
) -> tuple[list[Placement], PlaneMap | None, int]:
    """Fuse for good into ``frozen`` (made when None; else added to in place) the observations of each robot whose
    clouds are all older than ``before_ns[robot]``; returns the observations kept, the frozen map and how many
    were frozen."""
    keep: list[Placement] = []
    n = 0
    for pl in placements:
        cut = before_ns.get(pl.robot)
        if cut is not None and pl.cloud_t.size and int(pl.cloud_t.max()) < cut:
            if frozen is None:
                frozen = PlaneMap(cfg)
            frozen.add(pl.record)
            n += 1
        else:
            keep.append(pl)
    return keep, frozen, n


def rebuild_changes(old: PlaneMap, new: PlaneMap) -> list[MapChange]:
    """The changes from map ``old`` to its rebuild ``new``: every plane of ``new`` as updated, and every id of
    ``old`` that ``new`` lacks as removed into the plane of ``new`` whose centroid is nearest to it."""
    changes = [MapChange.updated(mp) for _, mp in sorted(new.planes.items())]
    gone = sorted(set(old.planes) - set(new.planes))
    if gone and new.planes:
        ids = np.array(sorted(new.planes))
        cents = np.array([new.planes[int(i)].fit.centroid for i in ids])
        for pid in gone:
            c = old.planes[pid].fit.centroid
            into = int(ids[np.argmin(np.linalg.norm(cents - c, axis=1))])
            changes.append(MapChange.removed(pid, into))
    return changes


class PlacementSnapshot:
    """A builder's kept observations at one moment (:meth:`mapping.MapBuilder.placements_snapshot`), moved and
    rebuilt off the builder's thread: the observations are copies (moving one replaces its arrays and record,
    never edits them), so the builder goes on merging meanwhile; :meth:`mapping.MapBuilder.adopt` takes the
    result back."""

    def __init__(self, placements: list[Placement], cfg: MapConfig, frozen: PlaneMap | None) -> None:
        self.original = placements
        self.placements = [replace(pl) for pl in placements]
        self.cfg = cfg
        self.frozen = frozen

    def move(self, robot: str, old: dict[int, Pose], new: dict[int, Pose]) -> int:
        """Move ``robot``'s observations from the cloud poses ``old`` to ``new``; returns how many moved."""
        return sum(1 for pl in self.placements if pl.robot == robot and move_placement(pl, old, new, self.cfg))

    def rebuild(self) -> PlaneMap:
        """The map of the (moved) observations on top of the frozen ones (:func:`rebuild`)."""
        return rebuild(self.placements, self.cfg, self.frozen)
