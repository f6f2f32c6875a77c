"""Re-localize a robot whose track broke: only where its scan matches one place of the map alone.

A depth-only robot whose pose graph lost its track (:mod:`mapping.graph_gate`) still has a heading (compass and
graph) and a depth; what it lacks is where it is horizontally within its uncertainty. Registration from the
current estimate finds the nearest fit, which in the symmetric tank is often a wrong one. Here the scan's points
(turned by the heading, relative to the vehicle) are scored at every candidate vehicle position on a grid over
the search disc: a candidate's score is the number of points that lie within a tolerance of a wall-like map plane
facing the vehicle and inside its (inflated) extent. The match is accepted only when it is **unique**: every
candidate scoring close to the best lies within a few centimetres of it. One flat wall leaves a ridge of equal
scores along it, two parallel walls too, a mirror-image place a second peak: none of them is unique, and the robot
stays unplaced. The scan must explain most of its wall points at the best candidate as well.

Frames and units: NED, metres; points (M, 3) relative to the vehicle, already turned by roll, pitch and heading.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .landmarks import PlaneLandmarks, take_planes

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class RelocConfig:
    """Tuning of :func:`unique_place` (metres).

    ``step_m`` / ``tol_m``: the coarse grid's spacing and the point-to-plane tolerance there; ``fine_step_m`` /
    ``fine_tol_m``: the refinement's around the best coarse cell, where the rivals must lie within
    ``fine_unique_m`` of their mean; ``near_best``: candidates scoring at least this
    share of the best are rivals; ``unique_m``: rivals must all lie within this of the best; ``min_share``: the best
    must explain at least this share of the scan's points; ``min_points``: and at least this many; ``margin_m`` /
    ``margin_down_m``: the planes' extents inflated by these; ``max_points``: the scan is sub-sampled to these.
    """

    step_m: float = 0.1
    tol_m: float = 0.07
    fine_step_m: float = 0.02
    fine_tol_m: float = 0.03
    fine_unique_m: float = 0.06
    near_best: float = 0.85
    unique_m: float = 0.15
    min_share: float = 0.6
    min_points: int = 40
    margin_m: float = 0.1
    margin_down_m: float = 0.5
    max_points: int = 120


def _scores(
    rel: FloatArray, veh_down: float, cand: FloatArray, lm: PlaneLandmarks, tol: float, cfg: RelocConfig
) -> NDArray[np.int64]:
    """Per candidate vehicle position (C, 2: north, east), how many of the points ``rel`` (M, 3) lie within ``tol``
    of an admissible plane of ``lm`` (P planes)."""
    veh = np.concatenate([cand, np.full((cand.shape[0], 1), veh_down)], axis=1)  # (C, 3)
    # every quantity is linear in the vehicle's position: split it into the points' part and the vehicle's
    dist = (rel @ lm.normal.T + lm.d)[None, :, :] + (veh @ lm.normal.T)[:, None, :]  # (C, M, P)
    rel_c = rel[:, None, :] - lm.centroid[None, :, :]  # (M, P, 3)
    pu = np.einsum("mpk,pk->mp", rel_c, lm.u)[None] + (veh @ lm.u.T)[:, None, :]
    pv = np.einsum("mpk,pk->mp", rel_c, lm.v)[None] + (veh @ lm.v.T)[:, None, :]
    ok = np.abs(dist) <= tol
    # facing the vehicle: normal . (vehicle - point) = -normal . rel, the same at every candidate
    ok &= (-(rel @ lm.normal.T) > 0.0)[None]
    ok &= (pu >= lm.u_range[None, None, :, 0] - cfg.margin_m) & (pu <= lm.u_range[None, None, :, 1] + cfg.margin_m)
    ok &= (pv >= lm.v_range[None, None, :, 0] - cfg.margin_down_m) & (
        pv <= lm.v_range[None, None, :, 1] + cfg.margin_down_m
    )
    return np.asarray(ok.any(axis=2).sum(axis=1), dtype=np.int64)


def _grid(center: FloatArray, radius: float, step: float) -> FloatArray:
    """Candidate positions (C, 2) on a square grid of ``step`` within ``radius`` of ``center``."""
    k = np.arange(-np.floor(radius / step), np.floor(radius / step) + 1) * step
    gn, ge = np.meshgrid(k, k, indexing="ij")
    off = np.stack([gn.ravel(), ge.ravel()], axis=1)
    off = off[np.hypot(off[:, 0], off[:, 1]) <= radius + 1e-9]
    return np.asarray(center[None, :] + off, dtype=np.float64)


def unique_place(
    rel: FloatArray,
    veh_down: float,
    center: FloatArray,
    radius_m: float,
    lm: PlaneLandmarks,
    cfg: RelocConfig | None = None,
) -> FloatArray | None:
    """The one vehicle position (north, east) within ``radius_m`` of ``center`` where the scan's points ``rel``
    (M, 3, relative to the vehicle at depth ``veh_down``, NED) fit the map's wall-like planes, or None when no
    place fits well enough or more than one does (see the module docstring)."""
    cfg = cfg or RelocConfig()
    lm_w = _walls(lm)
    if len(lm_w) < 2 or rel.shape[0] < cfg.min_points:
        return None
    if rel.shape[0] > cfg.max_points:
        rel = rel[np.linspace(0, rel.shape[0] - 1, cfg.max_points).astype(np.int64)]
    cand = _grid(np.asarray(center, dtype=np.float64), max(radius_m, cfg.step_m), cfg.step_m)
    s = _scores(rel, veh_down, cand, lm_w, cfg.tol_m, cfg)
    best = int(np.argmax(s))
    if s[best] < max(cfg.min_points, cfg.min_share * rel.shape[0]):
        return None
    rivals = cand[s >= cfg.near_best * s[best]]
    if float(np.max(np.hypot(*(rivals - cand[best]).T))) > cfg.unique_m:
        return None
    fine = _grid(cand[best], cfg.step_m, cfg.fine_step_m)
    sf = _scores(rel, veh_down, fine, lm_w, cfg.fine_tol_m, cfg)
    if sf.max() < max(cfg.min_points, cfg.min_share * rel.shape[0]):
        return None
    # a plateau (a direction the scan barely pins) is no place either
    top = fine[sf >= cfg.near_best * sf.max()]
    if float(np.max(np.hypot(*(top - top.mean(axis=0)).T))) > cfg.fine_unique_m:
        return None
    top = fine[sf >= sf.max()]
    return np.asarray(top.mean(axis=0), dtype=np.float64)


def fits_at(
    rel: FloatArray, veh_down: float, at: FloatArray, lm: PlaneLandmarks, cfg: RelocConfig | None = None
) -> bool:
    """Whether the scan's points ``rel`` (as :func:`unique_place`'s) fit the map's wall-like planes with the vehicle
    at ``at`` (north, east): as many of them within ``fine_tol_m`` of a plane facing it, inside its extent, as a
    unique place must explain. Where the scan pins one direction only (one wall) this says nothing along it, but a
    cloud that fits adds no copy of a face the map has."""
    cfg = cfg or RelocConfig()
    lm_w = _walls(lm)
    if len(lm_w) == 0 or rel.shape[0] < cfg.min_points:
        return False
    if rel.shape[0] > cfg.max_points:
        rel = rel[np.linspace(0, rel.shape[0] - 1, cfg.max_points).astype(np.int64)]
    s = _scores(rel, veh_down, np.asarray(at, dtype=np.float64).reshape(1, 2), lm_w, cfg.fine_tol_m, cfg)
    return bool(s[0] >= max(cfg.min_points, cfg.min_share * rel.shape[0]))


def _walls(lm: PlaneLandmarks) -> PlaneLandmarks:
    """The wall-like planes of ``lm`` (normal within 30 deg of horizontal)."""
    return take_planes(lm, np.abs(lm.normal[:, 2]) < 0.5)
