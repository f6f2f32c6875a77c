"""The fleet's compass biases from the launch fixes and the walls two robots see near them (issue 27).

A depth-only fleet (attitude, compass, depth; a horizontal fix at launch only) builds its map at the heading its
compasses say: each robot's scans are turned by its compass's bias ``b_i`` about where it is, and nothing a robot
sees alone can tell (its whole world turns with it). What the fleet sees *together* can. Robot ``i`` at its launch
fix ``f_i`` (north, east; a few mm) sees a vertical wall ``k`` as a line of its compass-turned scan: the line's
normal direction ``alpha_ik = phi_k + b_i`` (``phi_k`` the wall's true direction) and its distance from the robot
``e_ik = n(phi_k) . f_i + C_k`` (the wall ``n(phi_k) . x + C_k = 0`` in NED), which no compass turns. For a wall
two robots see, ``n(phi_k) . (f_i - f_j) = e_ik - e_jk`` fixes the wall's absolute direction wherever the baseline
``f_i - f_j`` has a component along it (its precision about ``sigma_e sqrt(2) / (L sin angle)``), and the
directions then give every ``b_i``. Over several walls and robots it is one small least squares
(:func:`estimate`): unknowns the biases (a prior of the compass's bias, ``FleetHeadingConfig.bias_prior_deg``),
each shared wall's direction and offset; Gauss-Newton, the covariance giving each bias's standard deviation and the
common heading's (the biases' mean). A robot that shares no wall with another keeps its prior: its heading is its
compass's, and the standard deviation says so.

The lines are fitted to the scans themselves (:func:`wall_lines`: RANSAC over the horizontal projection, both
laser fans together, a wall being vertical), matched across robots by direction and offset (the biases are a few
degrees, the tank's parallel faces decimetres apart), re-matched once the biases are known. A robot's later scans
(``View.offset_ne``: where it is relative to its fix, *in its compass frame*, as its own odometry says) add lines in
the same frame: a robot's track and scans turn together with its compass.

Frames and units: NED (north, east), metres, radians; a positive angle turns north towards east (the yaw's sense).
A line's normal points from the wall towards the robot that saw it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class FleetHeadingConfig:
    """Tuning of :func:`estimate` (metres, degrees where named ``_deg``).

    ``fix_sigma_m``: a launch fix's standard deviation; ``compass_sigma_deg``: one compass reading's white noise
    (what a single scan's line direction carries besides the bias); ``bias_prior_deg``: the compass's bias (the
    prior of each robot's); ``line_tol_m``: a point's distance from its line (RANSAC inliers); ``min_points`` and
    ``min_spread_m``: a line's points and their standard deviation along it; ``match_deg`` / ``match_m``: how far
    two robots' lines may differ in direction and offset before the biases are known (twice the bias, its lever);
    ``extent_margin_m``: how far apart along a wall two robots' segments may lie and still be one wall."""

    fix_sigma_m: float = 0.005
    compass_sigma_deg: float = 0.15
    bias_prior_deg: float = 3.0
    line_tol_m: float = 0.012
    min_points: int = 40
    min_spread_m: float = 0.25
    max_lines: int = 8
    match_deg: float = 6.0
    match_m: float = 0.2
    extent_margin_m: float = 1.0
    point_sigma_m: float = 0.003


@dataclass(frozen=True)
class Line:
    """A wall in one scan's horizontal projection: ``n(alpha) . x + c = 0`` (``n = (cos alpha, sin alpha)``, north
    and east, pointing to the vehicle, so ``c`` > 0 is its distance), its inliers, their standard deviation along
    it and their extent along the tangent ``(-sin alpha, cos alpha)`` (m, from the foot of the vehicle's
    perpendicular)."""

    alpha_rad: float
    c_m: float
    n_points: int
    spread_m: float
    t_range_m: tuple[float, float]


@dataclass(frozen=True)
class View:
    """A robot's scan for :func:`estimate`: its horizontal points (M, 2; north, east, relative to the vehicle,
    turned by its compass's heading), its launch fix (NED north, east), and where the vehicle was relative to the
    fix in the robot's compass frame (its own odometry; zero for the launch scan) with that offset's standard
    deviation."""

    robot: str
    fix_ne: tuple[float, float]
    points_ne: FloatArray
    offset_ne: tuple[float, float] = (0.0, 0.0)
    offset_sigma_m: float = 0.0


@dataclass(frozen=True)
class FleetHeading:
    """What :func:`estimate` found: per robot its compass bias (compass minus true heading, radians) and its
    standard deviation (the prior's where no shared wall constrains it); the common heading (the biases' mean)
    and its standard deviation; the walls seen by two robots or more and the observations of them used."""

    bias_rad: dict[str, float] = field(default_factory=dict)
    sd_rad: dict[str, float] = field(default_factory=dict)
    common_rad: float = 0.0
    common_sd_rad: float = math.inf
    walls: int = 0
    observations: int = 0

    def observed(self, robot: str, max_sd_deg: float = 1.0) -> bool:
        """Whether the shared walls constrain ``robot``'s bias within ``max_sd_deg`` (else it is its compass's)."""
        return self.sd_rad.get(robot, math.inf) <= math.radians(max_sd_deg)


def _n(a: float) -> FloatArray:
    return np.array([math.cos(a), math.sin(a)])


def _t(a: float) -> FloatArray:
    return np.array([-math.sin(a), math.cos(a)])


def wall_lines(points_ne: FloatArray, cfg: FleetHeadingConfig | None = None, seed: int = 0) -> list[Line]:
    """The straight walls of one scan (points (M, 2), north and east relative to the vehicle, metres): RANSAC lines
    taken greedily (most inliers first, refitted by PCA), each with at least ``min_points`` inliers spreading
    ``min_spread_m``; deterministic for a ``seed``."""
    cfg = cfg or FleetHeadingConfig()
    pts = np.asarray(points_ne, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    rng = np.random.default_rng(seed)
    out: list[Line] = []
    left = pts
    for _ in range(cfg.max_lines):
        m = left.shape[0]
        if m < cfg.min_points:
            break
        ij = rng.integers(0, m, size=(300, 2))
        ij = ij[ij[:, 0] != ij[:, 1]]
        a, b = left[ij[:, 0]], left[ij[:, 1]]
        d = b - a
        norm = np.hypot(d[:, 0], d[:, 1])
        ok = norm > 0.05
        a, d, norm = a[ok], d[ok], norm[ok]
        if a.shape[0] == 0:
            break
        nrm = np.stack([-d[:, 1], d[:, 0]], axis=1) / norm[:, None]  # (H, 2)
        # (H, M): each hypothesis's distance of every point, as one product (no per-point loop)
        dist = np.abs(left @ nrm.T - np.einsum("hk,hk->h", a, nrm)[None, :]).T
        counts = (dist < cfg.line_tol_m).sum(axis=1)
        best = int(np.argmax(counts))
        inl = dist[best] < cfg.line_tol_m
        line = None
        for _refit in range(2):
            q = left[inl]
            if q.shape[0] < cfg.min_points:
                break
            cen = q.mean(axis=0)
            lam, vec = np.linalg.eigh(np.cov((q - cen).T))
            nv = vec[:, 0]
            inl = np.abs((left - cen) @ nv) < cfg.line_tol_m
            line = (cen, nv, lam)
        if line is None or int(inl.sum()) < cfg.min_points:
            break
        cen, nv, _ = line
        q = left[inl]
        cen = q.mean(axis=0)
        lam, vec = np.linalg.eigh(np.cov((q - cen).T))
        nv = vec[:, 0]
        c = -float(nv @ cen)
        if c < 0:
            nv, c = -nv, -c
        alpha = math.atan2(float(nv[1]), float(nv[0]))
        along = q @ _t(alpha)
        spread = math.sqrt(max(float(lam[1]), 0.0))
        left = left[~inl]
        if spread < cfg.min_spread_m:
            continue
        out.append(Line(alpha, c, int(q.shape[0]), spread, (float(along.min()), float(along.max()))))
    return out


@dataclass
class _Obs:
    robot: int
    alpha: float
    c: float  # signed distance from the robot's fix, in its compass frame
    sa: float
    sc: float
    t_range: tuple[float, float]  # extent along the tangent, in the compass frame about the fix


def _robot_lines(views: list[View], cfg: FleetHeadingConfig, index: dict[str, int]) -> list[_Obs]:
    """Every view's lines in its robot's compass frame about its launch fix, a robot's repeated sightings of one
    wall averaged."""
    per: dict[int, list[_Obs]] = {}
    sc_pt = math.radians(cfg.compass_sigma_deg)
    for k, v in enumerate(views):
        u = np.asarray(v.offset_ne, dtype=np.float64)
        for ln in wall_lines(v.points_ne, cfg, seed=k):
            n = _n(ln.alpha_rad)
            c = ln.c_m - float(n @ u)
            sa = math.hypot(sc_pt, cfg.point_sigma_m / (ln.spread_m * math.sqrt(ln.n_points)))
            sc = math.hypot(cfg.point_sigma_m / math.sqrt(ln.n_points), v.offset_sigma_m)
            shift = float(_t(ln.alpha_rad) @ u)
            o = _Obs(index[v.robot], ln.alpha_rad, c, sa, sc, (ln.t_range_m[0] + shift, ln.t_range_m[1] + shift))
            same = [
                p for p in per.setdefault(o.robot, [])
                if abs(math.remainder(p.alpha - o.alpha, 2 * math.pi)) < math.radians(1.0) and abs(p.c - o.c) < 0.03
            ]  # fmt: skip
            if not same:
                per[o.robot].append(o)
                continue
            p = same[0]
            wa, wb = 1 / p.sa**2, 1 / o.sa**2
            p.alpha = p.alpha + math.remainder(o.alpha - p.alpha, 2 * math.pi) * wb / (wa + wb)
            ca, cb = 1 / p.sc**2, 1 / o.sc**2
            p.c = (p.c * ca + o.c * cb) / (ca + cb)
            # repeated sightings share the bias and the fix; their white parts average
            p.sa = 1.0 / math.sqrt(wa + wb)
            p.sc = 1.0 / math.sqrt(ca + cb)
            p.t_range = (min(p.t_range[0], o.t_range[0]), max(p.t_range[1], o.t_range[1]))
    return [o for robot in sorted(per) for o in per[robot]]


def _match(
    obs: list[_Obs], fix: FloatArray, bias: FloatArray, tol_a: float, tol_c: float, margin: float
) -> list[list[int]]:
    """Groups of observations (indices) of one wall by different robots, at the biases ``bias``: the same direction
    within ``tol_a`` and the same offset within ``tol_c`` (NED), segments within ``margin`` along the wall."""
    order = sorted(range(len(obs)), key=lambda i: -1.0 / obs[i].sa)
    groups: list[list[int]] = []
    ref: list[tuple[float, float, float, float]] = []  # phi, C, extent along t(phi) in NED
    for i in order:
        o = obs[i]
        phi = o.alpha - bias[o.robot]
        f = fix[o.robot]
        cw = o.c - float(_n(phi) @ f)
        foot = float(_t(phi) @ f)
        lo, hi = foot + o.t_range[0], foot + o.t_range[1]
        hit = -1
        for g, (p, cg, glo, ghi) in enumerate(ref):
            if any(obs[j].robot == o.robot for j in groups[g]):
                continue
            if abs(math.remainder(phi - p, 2 * math.pi)) > tol_a or abs(cw - cg) > tol_c:
                continue
            if lo > ghi + margin or hi < glo - margin:
                continue
            hit = g
            break
        if hit < 0:
            groups.append([i])
            ref.append((phi, cw, lo, hi))
        else:
            groups[hit].append(i)
            p, cg, glo, ghi = ref[hit]
            ref[hit] = (p, cg, min(glo, lo), max(ghi, hi))
    return [g for g in groups if len(g) >= 2]


def _solve(
    obs: list[_Obs], groups: list[list[int]], fix: FloatArray, n_robots: int, cfg: FleetHeadingConfig
) -> tuple[FloatArray, FloatArray]:
    """Gauss-Newton over the biases (R), and per wall its direction and offset: the biases (R,) and the full
    covariance of the unknowns (R + 2 G square)."""
    g_n = len(groups)
    dim = n_robots + 2 * g_n
    x = np.zeros(dim)
    for g, grp in enumerate(groups):
        x[n_robots + 2 * g] = obs[grp[0]].alpha
        x[n_robots + 2 * g + 1] = obs[grp[0]].c - float(_n(obs[grp[0]].alpha) @ fix[obs[grp[0]].robot])
    prior = 1.0 / math.radians(cfg.bias_prior_deg) ** 2
    h = np.eye(dim) * 1e-12
    for _ in range(6):
        h = np.zeros((dim, dim))
        grad = np.zeros(dim)
        h[:n_robots, :n_robots] += np.eye(n_robots) * prior
        grad[:n_robots] += prior * x[:n_robots]
        for g, grp in enumerate(groups):
            ip, ic = n_robots + 2 * g, n_robots + 2 * g + 1
            phi, cw = x[ip], x[ic]
            for j in grp:
                o = obs[j]
                f = fix[o.robot]
                # the direction: alpha = phi + b
                r = math.remainder(x[o.robot] + phi - o.alpha, 2 * math.pi) / o.sa
                jac = np.zeros(dim)
                jac[o.robot], jac[ip] = 1.0 / o.sa, 1.0 / o.sa
                h += np.outer(jac, jac)
                grad += jac * r
                # the offset from the fix: c = n(phi) . f + C
                sc = math.hypot(o.sc, cfg.fix_sigma_m)
                r = (float(_n(phi) @ f) + cw - o.c) / sc
                jac = np.zeros(dim)
                jac[ip], jac[ic] = float(_t(phi) @ f) / sc, 1.0 / sc
                h += np.outer(jac, jac)
                grad += jac * r
        step = np.linalg.solve(h + np.eye(dim) * 1e-12, -grad)
        x += step
        if float(np.abs(step).max()) < 1e-9:
            break
    return x[:n_robots], np.asarray(np.linalg.inv(h + np.eye(dim) * 1e-12), dtype=np.float64)


def estimate(views: list[View], cfg: FleetHeadingConfig | None = None) -> FleetHeading:
    """The fleet's compass biases from its robots' views near their launch fixes (see the module docstring): each
    bias with its standard deviation, the common heading (their mean) with its; a robot that shares no wall with
    another keeps the prior (bias 0, ``bias_prior_deg``)."""
    cfg = cfg or FleetHeadingConfig()
    robots = sorted({v.robot for v in views})
    index = {r: i for i, r in enumerate(robots)}
    prior = math.radians(cfg.bias_prior_deg)
    if len(robots) < 2:
        alone = prior / math.sqrt(max(1, len(robots)))
        return FleetHeading(dict.fromkeys(robots, 0.0), dict.fromkeys(robots, prior), 0.0, alone)
    fix_of = {v.robot: v.fix_ne for v in views}
    origin = np.mean([fix_of[r] for r in robots], axis=0)
    fix = np.array([np.asarray(fix_of[r], dtype=np.float64) - origin for r in robots])
    obs = _robot_lines(views, cfg, index)
    bias = np.zeros(len(robots))
    groups = _match(obs, fix, bias, math.radians(cfg.match_deg), cfg.match_m, cfg.extent_margin_m)
    cov = np.diag(np.full(len(robots), prior**2))
    if groups:
        bias, cov = _solve(obs, groups, fix, len(robots), cfg)
        # matched again at the biases found, within a few standard deviations
        sd = np.sqrt(np.diag(cov)[: len(robots)])
        tol_a = math.radians(0.5) + 3.0 * float(sd.max())
        groups = _match(obs, fix, bias, min(tol_a, math.radians(cfg.match_deg)), 0.05, cfg.extent_margin_m)
        if groups:
            bias, cov = _solve(obs, groups, fix, len(robots), cfg)
        else:
            bias, cov = np.zeros(len(robots)), np.diag(np.full(len(robots), prior**2))
    r_n = len(robots)
    cb = cov[:r_n, :r_n]
    w = np.full(r_n, 1.0 / r_n)
    return FleetHeading(
        {r: float(bias[i]) for i, r in enumerate(robots)},
        {r: math.sqrt(max(float(cb[i, i]), 0.0)) for i, r in enumerate(robots)},
        float(w @ bias),
        math.sqrt(max(float(w @ cb @ w), 0.0)),
        len(groups),
        sum(len(g) for g in groups),
    )
