"""One surface seen twice: two parallel planes whose points cover the same place of the face.

Association (:mod:`mapping.plane_map`) fuses an observation with a map plane when its points lie within
``merge_offset_m`` of it. A robot whose pose is wrong by more than that (dead reckoning that drifted while no wall
pinned the direction, a filter that believed it) puts its view of a wall beside the wall's plane: a second plane,
parallel, a few centimetres to a few decimetres behind or in front of it. Navigation then registers that robot to
the nearer of the two, its own copy, and the copy holds the wrong pose.

The physics that tells such a copy from a real second surface is occlusion. The lasers' rays are near
horizontal: a ray that hits a face at some depth crosses every plane in front of it at that same depth. Two
planes facing the same way, ``delta`` apart, cannot both be surfaces where their points cover the same in-plane
place (along the face and in depth) when the vehicle that saw the far one was in front of the near one: its rays
would have stopped at the near one. Every observation comes from a vehicle at least ``min_sensor_distance_m``
from its plane (a plane closer to the vehicle is the laser sheet itself and is refused), so for ``delta`` below
that, overlapping cover means one surface seen from two poses that disagree, whatever either pose's reported
uncertainty says.

Real structures that look alike stay apart:

* a face in front of a wall (a box, a plate, a pillar standing against it) hides the wall behind it, so the two
  covers only meet along the face's border; cover counts only where the other plane covers a whole block of
  cells around the place (``same_face_block_cells``), which a border never does;
* a step or recess (the upper part of a wall 10 cm behind its lower part) has covers side by side in depth, never
  one over the other;
* parallel faces farther apart than ``same_face_offset_m`` (a pillar's face and the wall it faces, 0.3 m or
  more) are never tested.

Everything here works on the planes' export voxels (exact per-voxel sums, :class:`mapping.stats.VoxelSet`), so the
test is the same for a plane built in one process or from a plane worker's observations.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: packing of 2-D cell indices into one int64 key (cells of a plane stay far inside +-2**30)
_SHIFT = 2**31
_BIAS = 2**30


def _cells(points: FloatArray, u: FloatArray, v: FloatArray, cell_m: float) -> IntArray:
    """(K,) packed in-plane cell keys of points (K, 3): coordinates along ``u`` and ``v`` in cells of ``cell_m``."""
    iu = np.floor(points @ u / cell_m).astype(np.int64) + _BIAS
    iv = np.floor(points @ v / cell_m).astype(np.int64) + _BIAS
    return iu * _SHIFT + iv


def shared_fraction(
    a_points: FloatArray,
    a_counts: IntArray,
    b_points: FloatArray,
    b_counts: IntArray,
    u: FloatArray,
    v: FloatArray,
    cell_m: float,
    block: int,
) -> float:
    """Share of the smaller plane's points that lie where both planes cover the face over a whole block (0..1).

    The in-plane cells (``cell_m`` squares along ``u`` and ``v``) where both planes have points are the shared
    cover; only the parts of it at least ``block`` cells wide in both directions count (a morphological opening
    with a ``block`` x ``block`` square): a face standing in front of a wall shares a thin ring of cells with the
    wall's cover along its border, never a block.

    Args:
        a_points, b_points: (K, 3), (M, 3) the planes' voxel centroids (NED, m); ``a_counts``, ``b_counts`` their
            points per voxel.
        u, v: (3,) the common in-plane unit axes (``u`` horizontal, ``v`` toward down for a vertical face).
        cell_m: in-plane cell edge (m).
        block: the opening's square, in cells (>= 1).
    """
    na, nb = int(a_counts.sum()), int(b_counts.sum())
    if na == 0 or nb == 0:
        return 0.0
    ka = _cells(a_points, u, v, cell_m)
    kb = _cells(b_points, u, v, cell_m)
    shared = np.intersect1d(ka, kb)
    if shared.size == 0:
        return 0.0
    # a shared cell is kept when some block x block square containing it is all shared
    offsets = [du * _SHIFT + dv for du in range(block) for dv in range(block)]
    corner_ok = np.ones(shared.shape[0], dtype=bool)  # squares by their lowest corner
    for off in offsets:
        corner_ok &= np.isin(shared + off, shared)
    corners = shared[corner_ok]
    opened = np.unique(np.concatenate([corners + off for off in offsets])) if corners.size else corners
    keys, counts = (ka, a_counts) if na <= nb else (kb, b_counts)
    return float(counts[np.isin(keys, opened)].sum()) / min(na, nb)
