"""A robot's pose graph and the map's planes: the scan registered to them, one factor per plane seen.

Part of :class:`mapping.posegraph.GraphNav` (its ``g`` below; the module docstring there gives the design). The
others' planes enter as unary factors, the robot's own old enough planes as loop closures to the pose that made
them; each plane has an offset variable of its own (``GraphConfig.map_plane_sigma_m``), so the scans that see one
plane share its error. :func:`fit` is the registration (Gauss-Newton over north, east and heading, the pose's
marginal as the prior), :func:`register` turns it into factors.

Frames and units: NED (north, east, heading in radians), points (M, 3) in metres, times in ns.
"""

from __future__ import annotations

import math
import zlib
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, R_ned_from_body

from .graph_factors import rot
from .graph_gate import LEVER_M, ambiguous
from .landmarks import PlaneLandmarks, associate, take_planes

FloatArray = NDArray[np.float64]


def _gtsam() -> Any:
    from .posegraph import gtsam_module

    return gtsam_module()


def register(
    g: Any, key: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks, t: int
) -> tuple[FloatArray, int, tuple[int, ...]]:
    """Register the scan to the map's planes: the others' as a unary factor, its own (old enough) as a loop
    closure to the pose that made them. Returns the information the scan gave (3x3, north/east/heading,
    global), the inliers and the planes used."""
    cfg = g.cfg
    if len(lm) == 0 or pts.shape[0] < cfg.min_inliers:
        return np.zeros((3, 3)), 0, ()
    own_anchor = np.full(len(lm), -1, dtype=np.int64)
    use = np.ones(len(lm), dtype=bool)
    if lm.contrib:
        horizon = t - int(g.gcfg.own_min_age_s * 1e9)
        for i, c in enumerate(lm.contrib):
            mine = c.get(g.robot)
            if mine is None or len(c) != 1:
                continue
            use[i] = False
            if g.gcfg.own_planes and mine[1] <= horizon:
                own_anchor[i] = key_at(g, mine[1])
    usable = use | (own_anchor >= g._first_key)
    if not usable.any():
        return np.zeros((3, 3)), 0, ()
    res = fit(g, key, raw, pts, take_planes(lm, usable), g.gcfg.map_min_sigma_m)
    if res is None:
        return np.zeros((3, 3)), 0, ()
    _, info, inliers, used, per_plane = res
    anchor_of = {int(lm.ids[i]): int(own_anchor[i]) for i in np.flatnonzero(own_anchor >= g._first_key)}
    loops = plane_factors(g, key, raw, per_plane, anchor_of, lm)
    g.loops += int(loops > 0)
    # what the scan pinned (reported as the filter reports it: the planes taken as they are)
    h_total = info
    if g._pending:
        g._solve()
    return h_total, inliers, tuple(used)


def plane_factors(
    g: Any,
    key: int,
    raw: Pose,
    per_plane: list[tuple[int, FloatArray, float, FloatArray, int]],
    anchor_of: dict[int, int],
    lm: PlaneLandmarks | None = None,
) -> int:
    """One factor per plane this scan saw: the mean of its inliers on the plane, with an offset of the plane's
    own (a variable per plane, its prior ``map_plane_sigma_m``, ``own_sigma_m`` for the robot's own): the scans
    that see one plane share its error instead of each taking it as new evidence. A plane of the robot's own
    (``anchor_of``: plane id -> the pose whose cloud first made it) is expressed in the frame of that pose as
    it was when the cloud was placed, and moves with that pose: seeing it again relates the two poses (a loop
    closure), it does not fix this one. Returns the loop closures added."""
    cfg = g.cfg
    x = g._est[key]
    loops = 0
    for pid, n, d, c, m in per_plane:
        if abs(float(n[2])) > 0.5:
            continue  # a floor or a ceiling: depth is measured, it says nothing horizontal
        anchor = anchor_of.get(pid)
        then = g._then.get(anchor) if anchor is not None else None
        if anchor is not None and then is None:
            continue
        sigma_plane = g.gcfg.own_sigma_m if anchor is not None else g.gcfg.map_plane_sigma_m
        sigma = max(cfg.point_sigma_m, g.gcfg.map_min_sigma_m) / math.sqrt(min(m, cfg.max_independent_points))
        const = float(n[2]) * (raw.down_m + float(c[2])) + d
        nh = n[0:2].astype(np.float64)
        off = offset(g, pid)
        sid = stretch_of(g, pid, lm) if anchor is None else None
        if anchor is None or then is None:
            e = float(nh @ (x[0:2] + rot(float(x[2])) @ c[0:2])) + const + off
            kind, keys = "plane", (key,)  # type: tuple[str, tuple[int, ...]]
            data = (pid, float(nh[0]), float(nh[1]), float(c[0]), float(c[1]), const, sigma)  # type: tuple[Any, ...]
            if sid is not None:
                e += float(nh @ shared_offset(g, sid))
                kind, data = "plane_shared", (*data, sid)
                sigma_plane = g.gcfg.stretch_plane_sigma_m
        else:
            # the plane in the anchor's frame as it was placed: n_loc . q + const_loc = 0 for q in that frame
            n_loc = rot(float(then[2])).T @ nh
            const_loc = const + float(nh @ then[0:2])
            xa = g._est[anchor]
            u = x[0:2] + rot(float(x[2])) @ c[0:2] - xa[0:2]
            e = float(n_loc @ rot(float(xa[2])).T @ u) + const_loc + off
            kind, keys = "anchored", (anchor, key)
            data = (pid, float(n_loc[0]), float(n_loc[1]), float(c[0]), float(c[1]), const_loc, sigma)
        if abs(e) > g.gcfg.plane_gate_m:
            g.gated += 1
            continue
        if g.gcfg.second_hypothesis and lm is not None and ambiguous_at(g, pid, n, d, c, x, raw, lm):
            g.ambiguous += 1
            continue
        if pid not in g._plane_ids:
            g._plane_ids.add(pid)
            g._add("plane_prior", (), (pid, sigma_plane))
            g._new_offsets.add(pid)
        if sid is not None and kind == "plane_shared" and sid not in g._stretch_ids:
            g._stretch_ids.add(sid)
            g._add("stretch_prior", (), (sid, g.gcfg.map_plane_sigma_m))
            g._new_stretches.add(sid)
        g._add(kind, keys, data)
        loops += int(kind == "anchored")
    return loops


def ambiguous_at(
    g: Any, pid: int, n: FloatArray, d: float, c: FloatArray, x: FloatArray, raw: Pose, lm: PlaneLandmarks
) -> bool:
    """:func:`mapping.graph_gate.ambiguous` at the latest pose's marginal (``g._cov``)."""
    margins = (g.cfg.extent_margin_m, g.cfg.extent_margin_down_m)
    return ambiguous(pid, n, d, c, x, raw.down_m, g._cov, lm, margins)


def offset(g: Any, pid: int) -> float:
    """The current estimate of plane ``pid``'s offset (0 before it has one)."""
    if pid not in g._plane_ids or pid in g._new_offsets:
        return 0.0
    return float(g._isam.calculateEstimateVector(_gtsam().symbol("p", pid))[0])


def stretch_of(g: Any, pid: int, lm: PlaneLandmarks | None) -> int | None:
    """The shared offset's id of plane ``pid`` (``GraphConfig.stretch_s``): the robot that gave it the most points
    and the stretch of its first cloud of it; None when off or unknown."""
    stretch_s = float(g.gcfg.stretch_s)
    if not math.isfinite(stretch_s) or lm is None or not lm.contrib:
        return None
    at = np.flatnonzero(lm.ids == pid)
    if at.size == 0:
        return None
    contrib = lm.contrib[int(at[0])]
    if not contrib:
        return None
    robot, (_, first_ns) = max(contrib.items(), key=lambda kv: (kv[1][0], kv[0]))
    return (zlib.crc32(robot.encode()) % 1000) * 10**9 + int(first_ns * 1e-9 // stretch_s) % 10**9


def shared_offset(g: Any, sid: int) -> FloatArray:
    """The current estimate of stretch ``sid``'s shared offset (north, east; zero before it has one)."""
    if sid not in g._stretch_ids or sid in g._new_stretches:
        return np.zeros(2)
    return np.asarray(g._isam.calculateEstimateVector(_gtsam().symbol("s", sid)), dtype=np.float64)


def key_at(g: Any, t_ns: int) -> int:
    """The pose at or just after ``t_ns`` (-1 before the window)."""
    import bisect

    k = bisect.bisect_left(g._t, int(t_ns))
    return k if g._first_key <= k < len(g._t) else -1


def fit(
    g: Any, key: int, raw: Pose, pts: FloatArray, lm: PlaneLandmarks, min_sigma: float
) -> tuple[FloatArray, FloatArray, int, list[int], list[tuple[int, FloatArray, float, FloatArray, int]]] | None:
    """Gauss-Newton over north, east and heading from the point-to-plane residuals, the pose's marginal as the
    prior; returns the scan's own solution (3,) and information (3x3, global axes), the inliers and plane ids,
    and per plane (id, normal (3,), d, the mean of its inlier points in the level frame (3,), inliers); or None
    (too few inliers, or a correction beyond the marginal: a wrong association)."""
    cfg = g.cfg
    x_pred = g._est[key].copy()
    p = g._cov
    p_inv = np.linalg.inv(p)
    nh = lm.normal[:, 0:2]
    along = np.einsum("pi,ij,pj->p", nh, p[0:2, 0:2], nh)
    gate = np.clip(3.0 * np.sqrt(along + 2.0**2 * p[2, 2]) + 0.05, cfg.gate_min_m, cfg.gate_max_m)
    x = x_pred.copy()
    h3 = np.zeros((3, 3))
    g3 = np.zeros(3)
    inl = 0
    ids: list[int] = []
    sigma = max(cfg.point_sigma_m, min_sigma)
    x_lin = x.copy()
    per_plane: list[tuple[int, FloatArray, float, FloatArray, int]] = []
    for it in range(cfg.iterations):
        x_lin = x.copy()
        r_nb = R_ned_from_body(raw.roll_rad, raw.pitch_rad, float(x[2]))
        veh = np.array([x[0], x[1], raw.down_m])
        rel = pts @ r_nb.T
        k, dist = associate(rel + veh, veh, lm, gate, cfg)
        sel = k >= 0
        inl = int(sel.sum())
        if inl < cfg.min_inliers:
            return None
        n = lm.normal[k[sel]]
        r = dist[sel]
        relh = rel[sel]
        j = np.stack([n[:, 0], n[:, 1], -n[:, 0] * relh[:, 1] + n[:, 1] * relh[:, 0]], axis=1)
        w = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
        scale = min(1.0, cfg.max_independent_points / inl) / sigma**2
        h3 = scale * (j.T * w) @ j
        g3 = scale * (j.T * w) @ r
        x = np.asarray(np.linalg.solve(p_inv + h3, p_inv @ x_pred + h3 @ x - g3), dtype=np.float64)
        if it >= 1:
            gate = np.full(len(lm), max(cfg.gate_min_m, 4 * cfg.huber_m))
        ids = [int(i) for i in np.unique(lm.ids[k[sel]])]
        # per plane: the mean of its inliers in the level frame (the heading of this linearisation taken out)
        lvl = relh @ R_ned_from_body(0.0, 0.0, -float(x_lin[2])).T
        per_plane = []
        for kk in np.unique(k[sel]):
            on = k[sel] == kk
            per_plane.append(
                (int(lm.ids[kk]), lm.normal[kk].copy(), float(lm.d[kk]), lvl[on].mean(axis=0), int(on.sum()))
            )
    dx = x - x_pred
    if float(dx @ p_inv @ dx) > g.gcfg.map_gate_chi2:
        # a correction the pose's marginal cannot explain: a wrong association, not drift
        g.gated += 1
        return None
    # the scan's own solution at the last linearisation (the prior taken out): H (z - x_lin) = -g, in the
    # directions the scan observes well enough (in metres, the heading at a 2 m lever): a weakly observed one
    # would carry the linearisation far off with a little information
    unit = np.array([1.0, 1.0, 1.0 / LEVER_M])
    hs = h3 * unit[:, None] * unit[None, :]
    lam, vec = np.linalg.eigh(0.5 * (hs + hs.T))
    keep = lam >= 1.0 / g.gcfg.observed_std_m**2
    if not keep.any():
        return None
    vk, lk = vec[:, keep], lam[keep]
    gs = g3 * unit
    z = x_lin - unit * (vk @ ((vk.T @ gs) / lk))
    h_kept = (vk * lk) @ vk.T / unit[:, None] / unit[None, :]
    return z, 0.5 * (h_kept + h_kept.T), inl, ids, per_plane
