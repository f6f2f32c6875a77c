"""Exact, order-independent accumulators: contributions per robot and down-sampled points per plane.

Everything here is integer arithmetic on quantized coordinates, so fusing is associative and commutative and a
reloaded map is bit-identical to the one that was saved.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .planes import pack_keys

IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Contribution:
    """What one robot gave a plane: points, and the capture times (ns) of the first and last of them."""

    n_points: int
    first_ns: int
    last_ns: int

    def __add__(self, other: Contribution) -> Contribution:
        return Contribution(
            self.n_points + other.n_points, min(self.first_ns, other.first_ns), max(self.last_ns, other.last_ns)
        )


def merge_contributions(a: dict[str, Contribution], b: dict[str, Contribution]) -> dict[str, Contribution]:
    """Union of two per-robot contribution tables (sums and min/max), keys sorted."""
    out = dict(a)
    for robot, c in b.items():
        out[robot] = out[robot] + c if robot in out else c
    return dict(sorted(out.items()))


@dataclass(frozen=True)
class VoxelSet:
    """Points of a plane reduced to exact per-voxel sums (for export and extents).

    Attributes:
        keys: (K,) sorted packed voxel keys (voxel edge ``export_voxel_m``).
        counts: (K,) points per voxel.
        sums: (K, 3) int64 sums of the quantized points in each voxel.
    """

    keys: IntArray
    counts: IntArray
    sums: IntArray

    @classmethod
    def empty(cls) -> VoxelSet:
        """No points."""
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.int64))

    @classmethod
    def from_quantized(cls, points_q: NDArray[np.integer], voxel_quanta: int) -> VoxelSet:
        """Reduce quantized points (N, 3) to voxels of ``voxel_quanta`` quanta per edge."""
        p = np.asarray(points_q, dtype=np.int64)
        keys = pack_keys(np.floor_divide(p, voxel_quanta))
        return cls._reduce(keys, np.ones(p.shape[0], np.int64), p)

    @staticmethod
    def reduced(keys: IntArray, counts: IntArray, sums: IntArray) -> VoxelSet:
        """Voxels with these keys, counts and sums (any order, keys may repeat: repeated keys add up)."""
        return VoxelSet._reduce(keys, counts, sums)

    @staticmethod
    def _reduce(keys: IntArray, counts: IntArray, sums: IntArray) -> VoxelSet:
        if keys.shape[0] == 0:
            return VoxelSet.empty()
        order = np.argsort(keys, kind="stable")
        k = keys[order]
        starts = np.concatenate([[0], np.nonzero(np.diff(k))[0] + 1])
        return VoxelSet(
            k[starts].copy(),
            np.add.reduceat(counts[order], starts),
            np.add.reduceat(sums[order], starts, axis=0),
        )

    def __add__(self, other: VoxelSet) -> VoxelSet:
        return VoxelSet._reduce(
            np.concatenate([self.keys, other.keys]),
            np.concatenate([self.counts, other.counts]),
            np.concatenate([self.sums, other.sums]),
        )

    def centroids_m(self, quantum_m: float) -> NDArray[np.float64]:
        """(K, 3) voxel centroids in NED metres."""
        return self.sums.astype(np.float64) / self.counts[:, None] * quantum_m

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, VoxelSet):
            return NotImplemented
        return (
            np.array_equal(self.keys, other.keys)
            and np.array_equal(self.counts, other.counts)
            and np.array_equal(self.sums, other.sums)
        )

    __hash__ = None  # type: ignore[assignment]
