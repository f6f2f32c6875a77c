"""A map plane's own offset error in the filter's registration (``NavConfig.plane_sigma_m``; :class:`PlaneErrors`).

**Why.** A registration counts up to ``max_independent_points`` point residuals at ``point_sigma_m`` against each
plane: a few millimetres along the plane's normal per scan, scan after scan. The plane itself was placed by poses
good to a few centimetres (the fixes' error, and the map's own), and that offset error is the same for every
point on it and for every scan that registers to it. Counted as new each scan, a few centimetres of plane error
overrule fixes good to 2 cm, and the fleet and its map drift together (docs/navigation-design.md, "A plane's own
offset error"). The pose graph has an offset of each plane's own (``GraphConfig.map_plane_sigma_m``); this is the
filter's.

**The model.** Each associated plane k's residuals share an error delta_k along its normal, delta_k ~ N(0,
``plane_sigma_m``^2), independent between planes. A registration is solved jointly over the filter's state and the
used planes' delta (Gauss-Newton over ``[x (n,), delta (m,)]``): one scan's information along a plane's normal then
saturates at 1 / ``plane_sigma_m``^2 however many points it has, and what the points say beyond the offset (the
plane's direction against the heading, two planes' corner) is kept.

**Across scans** (``plane_carry``): delta_k is also the same for the next scan that registers to plane k. It is
carried as a Schmidt ("consider") parameter: its estimate stays 0 and its variance ``plane_sigma_m``^2, and the
filter keeps the cross-covariance C_k (n,) between its state and delta_k, moved by every prediction (``F C``) and
every update (``(I - K H) C``, :meth:`PlaneErrors.transform`). The state's update is then the optimal one of the
joint state, its covariance the joint's; only delta's estimate and variance are reset. A robot that keeps
registering to one wall learns its own motion along the wall's normal from it, and the wall's position once.
C_k is dropped when its correlation with every state falls under ``plane_carry_min_corr`` (a fix or another
plane took over) or when the plane leaves the map.

Why not a state per plane (a SLAM filter): the map, not each robot, estimates the planes; a robot's estimate of
delta would move the robot to the map's error and disagree with the other robots'.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from .landmarks import PlaneLandmarks
    from .nav_filter import RobotNav

__all__ = ["PlaneErrors", "PlaneJoint", "joint_prior", "marginal_information", "plane_information"]

FloatArray = NDArray[np.float64]


class PlaneErrors:
    """Per robot: the carried planes' offset errors and their covariance with the filter's state.

    Args:
        n: the filter's state size.
        sigma_m: each plane's offset error, m (``NavConfig.plane_sigma_m``).
        min_corr: as a consider parameter, a plane whose correlation with every state is below this is dropped.
        estimate: the offsets are states (``NavConfig.plane_carry`` ``"estimate"``): their estimates and covariance
            are kept; else consider parameters (estimate 0, variance ``sigma_m``^2 after every update).
    """

    def __init__(self, n: int, sigma_m: float, min_corr: float, estimate: bool = False) -> None:
        self.n = n
        self.sigma_m = sigma_m
        self.min_corr = min_corr
        self.estimate = estimate
        #: the carried planes' ids (m)
        self.ids: list[int] = []
        #: (m,) their offsets' estimates (m); (n, m) the state's cross-covariance with them; (m, m) theirs
        self.delta = np.zeros(0)
        self.c = np.zeros((n, 0))
        self.d = np.zeros((0, 0))

    def __len__(self) -> int:
        return len(self.ids)

    def copy(self) -> tuple[list[int], FloatArray, FloatArray, FloatArray]:
        """The carried planes (a snapshot)."""
        return list(self.ids), self.delta.copy(), self.c.copy(), self.d.copy()

    def restore(self, snap: tuple[list[int], FloatArray, FloatArray, FloatArray] | None) -> None:
        """Back to a :meth:`copy` (None: no plane)."""
        if snap is None:
            snap = ([], np.zeros(0), np.zeros((self.n, 0)), np.zeros((0, 0)))
        self.ids = list(snap[0])
        self.delta, self.c, self.d = snap[1].copy(), snap[2].copy(), snap[3].copy()

    def transform(self, m: FloatArray) -> None:
        """The cross-covariances become ``m @ C``: ``m`` (n, n) the transition of a prediction, or ``I - K H`` of an
        update that does not measure the planes."""
        if self.ids:
            self.c = m @ self.c

    def measured(self, k: FloatArray, h: FloatArray, s: FloatArray, innov: FloatArray) -> None:
        """A Kalman update of the state that does not measure the planes (a fix, the compass), before ``P`` moves:
        ``k`` (n, q) its gain, ``h`` (q, n), ``s`` (q, q) the innovation's covariance, ``innov`` (q,). The state's
        correlation with the offsets moves them too where they are states."""
        if not self.ids:
            return
        hc = h @ self.c
        if self.estimate:
            kd = np.linalg.solve(s, hc).T
            self.delta = self.delta + kd @ innov
            self.d = self.d - kd @ hc
            self.d = 0.5 * (self.d + self.d.T)
        self.c = self.c - k @ hc

    def prior(self, ids: list[int]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """For the joint of ``ids`` (m): the offsets' estimates (m,), the state's cross-covariance (n, m) and their
        covariance (m, m); a plane not carried at 0, uncorrelated, ``sigma_m``^2."""
        m = len(ids)
        delta, cross, dd = np.zeros(m), np.zeros((self.n, m)), np.eye(m) * self.sigma_m**2
        pos = {i: j for j, i in enumerate(self.ids)}
        have = [(j, pos[i]) for j, i in enumerate(ids) if i in pos]
        if have:
            a, b = (np.array(v) for v in zip(*have, strict=True))
            cross[:, a] = self.c[:, b]
            if self.estimate:
                delta[a] = self.delta[b]
                dd[np.ix_(a, a)] = self.d[np.ix_(b, b)]
        return delta, cross, dd

    def keep(self, ids: list[int], delta: FloatArray, cov: FloatArray, present: set[int]) -> None:
        """After a registration: ``ids`` (m) the joint's planes, ``delta`` (m,) their offsets, ``cov`` (n+m, n+m) the
        joint's posterior covariance. Planes no longer in the map (``present``), and consider parameters no longer
        correlated with any state, are dropped; the carried planes outside the joint are marginalized out of it
        (their cross-covariances were in the prior, unchanged by a registration that has none of them)."""
        n = self.n
        keep = [j for j, i in enumerate(ids) if i in present]
        if not self.estimate:
            sd = np.sqrt(np.maximum(np.diag(cov)[:n], 1e-30)) * self.sigma_m
            keep = [j for j in keep if float(np.max(np.abs(cov[:n, n + j]) / sd)) >= self.min_corr]
        self.ids = [ids[j] for j in keep]
        self.delta = delta[keep].copy() if self.estimate else np.zeros(len(keep))
        self.c = cov[:n, [n + j for j in keep]].copy()
        self.d = cov[np.ix_([n + j for j in keep], [n + j for j in keep])].copy()
        if not self.estimate:
            self.d = np.eye(len(keep)) * self.sigma_m**2


def plane_information(
    j: FloatArray, ws: FloatArray, res: FloatArray, col: NDArray[np.int64], m: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The points' information on the state's three registered axes (north, east, yaw) and on each plane's offset.

    Args:
        j: (N, 3) each residual's Jacobian over north (m), east (m), yaw (rad).
        ws: (N,) each residual's weight (1 / sigma^2, Huber and the independent-points scale in).
        res: (N,) the residuals at the current estimate, the plane's current offset in (m).
        col: (N,) each point's plane, 0 .. m-1 (a column of the joint's offsets).
        m: the number of offsets.

    Returns ``a`` (3, 3), ``b`` (3, m) the cross terms, ``c`` (m,) the offsets' own, ``g3`` (3,) and ``gm`` (m,)
    the gradients: the residuals' r = J dx + delta_col, so ``a = sum w J J^T``, ``b[:, k] = sum_k w J``, ``c_k =
    sum_k w``.
    """
    oh = (col[:, None] == np.arange(m)[None, :]).astype(np.float64)
    jw = j.T * ws
    return jw @ j, jw @ oh, ws @ oh, jw @ res, (ws * res) @ oh


def joint_prior(p: FloatArray, cross: FloatArray, dd: FloatArray) -> FloatArray:
    """(n+m, n+m) the joint prior information of the state (covariance ``p``, (n, n)) and m plane offsets
    (covariance ``dd`` (m, m), cross-covariance ``cross`` (n, m) with the state)."""
    n, m = cross.shape
    s = np.empty((n + m, n + m))
    s[:n, :n] = p
    s[:n, n:] = cross
    s[n:, :n] = cross.T
    s[n:, n:] = dd
    try:
        np.linalg.cholesky(s)
    except np.linalg.LinAlgError:
        # rounding left the carried correlations beyond what the variances allow: forget them
        s[:n, n:] = 0.0
        s[n:, :n] = 0.0
    return np.asarray(np.linalg.inv(s), dtype=np.float64)


def marginal_information(a: FloatArray, b: FloatArray, c: FloatArray, sigma_m: float) -> FloatArray:
    """(3, 3) one scan's own information on north, east, yaw with each plane's offset marginalized at its prior
    (``sigma_m``, no carried correlation): along a plane's normal at most 1 / ``sigma_m``^2."""
    return a - (b / (c + 1.0 / sigma_m**2)[None, :]) @ b.T


class PlaneJoint:
    """One registration's Gauss-Newton over the state and the used planes' offset errors (``NavConfig.plane_sigma_m``,
    :mod:`mapping.nav_planes`): the carried planes (``plane_carry``) and the ones this scan hits, their offsets'
    estimates within the scan."""

    def __init__(self, nav: RobotNav, lm: PlaneLandmarks) -> None:
        self.nav = nav
        self.sigma = nav.cfg.plane_sigma_m
        present = {int(i) for i in lm.ids}
        self.ids: list[int] = [i for i in nav.planes.ids if i in present] if nav.cfg.plane_carry else []
        self.delta = nav.planes.prior(self.ids)[0]
        self.lm_ids = lm.ids
        self.col = np.zeros(0, dtype=np.int64)
        self.lam = np.zeros((0, 0))
        self.h = np.zeros((0, 0))
        self.z = np.zeros(0)

    def _grow(self, pid: NDArray[np.int64]) -> None:
        new = [int(i) for i in np.unique(pid) if int(i) not in self.ids]
        if new:
            self.ids += new
            self.delta = np.concatenate([self.delta, np.zeros(len(new))])

    def residuals(self, hit: NDArray[np.int64], r: FloatArray) -> FloatArray:
        """The residuals (N,) of the points on ``hit`` (indices into the landmarks) with their planes' current
        offsets in; sets each point's column of the joint."""
        pid = self.lm_ids[hit]
        self._grow(pid)
        pos = {i: c for c, i in enumerate(self.ids)}
        self.col = np.array([pos[int(i)] for i in pid], dtype=np.int64)
        return r + self.delta[self.col]

    def step(
        self, x_pred: FloatArray, x: FloatArray, j: FloatArray, ws: FloatArray, res: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """One Gauss-Newton step from ``x`` (n,) with the points' Jacobians ``j`` (N, 3), weights ``ws`` (N,) and
        residuals ``res`` (N, from :meth:`residuals`); returns the new state and the scan's own information (3, 3)
        on north, east, yaw with the offsets marginalized."""
        nav = self.nav
        n, m = nav.n, len(self.ids)
        a, b, c, g3, gm = plane_information(j, ws, res, self.col, m)
        if nav.cfg.plane_carry:
            d0, cross, dd = nav.planes.prior(self.ids)
        else:
            d0, cross, dd = np.zeros(m), np.zeros((n, m)), np.eye(m) * self.sigma**2
        self.lam = joint_prior(nav.P, cross, dd)
        idx = [0, 1, 4]
        h = np.zeros((n + m, n + m))
        h[np.ix_(idx, idx)] = a
        h[idx, n:] = b
        h[n:, idx] = b.T
        h[n:, n:] += np.diag(c)
        g = np.zeros(n + m)
        g[idx] = g3
        g[n:] = gm
        self.h = h
        z = np.concatenate([x, self.delta])
        zp = np.concatenate([x_pred, d0])
        self.z = np.asarray(np.linalg.solve(self.lam + h, self.lam @ zp + h @ z - g), dtype=np.float64)
        self.delta = self.z[n:].copy()
        return self.z[:n].copy(), marginal_information(a, b, c, self.sigma)

    def posterior(self, lm: PlaneLandmarks) -> FloatArray:
        """The state's covariance (n, n) after the registration; with ``plane_carry`` the planes are kept in
        ``nav.planes``."""
        nav = self.nav
        n = nav.n
        cov = np.asarray(np.linalg.inv(self.lam + self.h), dtype=np.float64)
        cov = 0.5 * (cov + cov.T)
        if nav.cfg.plane_carry:
            nav.planes.keep(self.ids, self.delta, cov, {int(i) for i in lm.ids})
        return cov[:n, :n].copy()
