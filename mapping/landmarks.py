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
