"""A depth-only robot's heading checked against the map's walls (``GraphConfig.heading_check``).

The gated graph's checks (:func:`mapping.graph_gate.verify`) confirm where a robot is, not which way it faces: the
plane factors of :mod:`mapping.posegraph` keep only the mean of a scan's points on each plane, which pins the
position across the wall but hardly the heading (the mean moves along the wall as the heading turns). So the
compass's slowly wandering bias went into the map: long walls 1-3 deg off. A wall's *direction* in the scan says the
heading even where the position along it is unknown: the scan's points on a wall-like map plane, turned by the
estimated heading, lie on a line; the angle from the map plane's horizontal direction to that line is the heading's
error. :func:`heading_offset` takes the mean over the walls a scan saw (weighted by each line's precision), and the
graph takes it as a prior on that pose's heading (:func:`check_heading`).

Frames and units: NED, metres, radians; a positive angle turns north towards east (the yaw's sense).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .landmarks import PlaneLandmarks, associate, take_planes
from .nav_config import NavConfig

FloatArray = NDArray[np.float64]


def heading_offset(
    pts: FloatArray,
    raw: Pose,
    x: FloatArray,
    lm: PlaneLandmarks,
    cfg: NavConfig,
    gate_m: float = 0.1,
    min_points: int = 30,
    min_spread_m: float = 0.3,
) -> tuple[float, float, int] | None:
    """The heading error of the pose ``x`` (north, east, heading) from the scan ``pts`` (M, 3, body frame, raw
    attitude ``raw``) against the wall-like planes of ``lm``: (estimated minus true heading, radians; its standard
    deviation, radians; walls used), or None when no wall with ``min_points`` inliers spreading at least
    ``min_spread_m`` (standard deviation along it) was seen."""
    walls = take_planes(lm, np.abs(lm.normal[:, 2]) < 0.5)
    if len(walls) == 0 or pts.shape[0] < min_points:
        return None
    rel = pts @ R_ned_from_body(raw.roll_rad, raw.pitch_rad, float(x[2])).T
    veh = np.array([float(x[0]), float(x[1]), raw.down_m])
    k, _ = associate(rel + veh, veh, walls, np.full(len(walls), gate_m), cfg)
    num = den = 0.0
    used = 0
    for kk in np.unique(k[k >= 0]):
        on = rel[k == kk, 0:2]
        if on.shape[0] < min_points:
            continue
        c = on - on.mean(axis=0)
        lam, vec = np.linalg.eigh(c.T @ c / on.shape[0])
        spread = math.sqrt(max(float(lam[1]), 0.0))
        if spread < min_spread_m:
            continue
        line = vec[:, 1]
        nh = walls.normal[kk, 0:2]
        tangent = np.array([-nh[1], nh[0]]) / max(float(np.hypot(*nh)), 1e-9)
        if float(line @ tangent) < 0.0:
            line = -line
        # the signed angle from the map's wall to the scan's line: how far the estimated heading turned the scan
        ang = math.atan2(float(tangent[0] * line[1] - tangent[1] * line[0]), float(tangent @ line))
        if abs(ang) > math.radians(10.0):
            continue
        n_eff = min(on.shape[0], cfg.max_independent_points)
        sd = max(cfg.point_sigma_m, 0.01) / (spread * math.sqrt(n_eff))
        num += ang / sd**2
        den += 1.0 / sd**2
        used += 1
    if not used:
        return None
    return num / den, 1.0 / math.sqrt(den), used


def check_heading(g: Any, key: int, t: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks) -> None:
    """The heading of pose ``key`` checked against the walls (:mod:`mapping.graph_heading`) the robot contributed
    at most ``heading_own_share`` of the points to, every ``heading_every_s``: a prior on it at the heading the
    walls say, ``heading_floor_deg`` at least. Its own walls would carry its own heading error back.
    """
    gcfg = g.gcfg
    if g._last_heading_t is not None and t - g._last_heading_t < gcfg.heading_every_s * 1e9:
        return
    if len(lm) == 0:
        return
    use = np.ones(len(lm), dtype=bool)
    for i, c in enumerate(lm.contrib or ()):
        mine = c.get(g.robot)
        if mine is not None and mine[0] > gcfg.heading_own_share * sum(v[0] for v in c.values()):
            use[i] = False
    if not use.any():
        return
    x = g._est[key]
    got = heading_offset(pts, raw, x, take_planes(lm, use), g.cfg)
    if got is None:
        return
    off, sd, _ = got
    if abs(off) > math.radians(gcfg.heading_max_deg):
        return
    g._last_heading_t = t
    sd = max(sd, math.radians(gcfg.heading_floor_deg))
    mean = np.array([float(x[0]), float(x[1]), float(x[2]) - off])
    g._add("prior", (key,), (mean, np.diag([1e-10, 1e-10, 1.0 / sd**2])))
    g.headings += 1
    g._solve()
