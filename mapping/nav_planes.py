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

import numpy as np
from numpy.typing import NDArray

__all__ = ["PlaneErrors", "joint_prior", "marginal_information", "plane_information"]

FloatArray = NDArray[np.float64]


class PlaneErrors:
    """Per robot: the cross-covariance of the filter's state (n,) with each carried plane's offset error.

    Args:
        n: the filter's state size.
        sigma_m: each plane's offset error, m (``NavConfig.plane_sigma_m``).
        min_corr: a plane whose correlation with every state is below this is dropped.
    """

    def __init__(self, n: int, sigma_m: float, min_corr: float) -> None:
        self.n = n
        self.sigma_m = sigma_m
        self.min_corr = min_corr
        #: plane id -> (n,) cross-covariance of the state with its offset error (m^2, m^2/s, m rad)
        self.c: dict[int, FloatArray] = {}

    def copy(self) -> dict[int, FloatArray]:
        """The carried cross-covariances (a snapshot)."""
        return {k: v.copy() for k, v in self.c.items()}

    def set(self, c: dict[int, FloatArray]) -> None:
        """Back to a :meth:`copy`."""
        self.c = {k: v.copy() for k, v in c.items()}

    def transform(self, m: FloatArray) -> None:
        """Every carried C becomes ``m @ C``: ``m`` (n, n) the transition of a prediction, or ``I - K H`` of an
        update that does not measure the planes (a fix, the compass)."""
        if self.c:
            ids = list(self.c)
            cm = m @ np.stack([self.c[i] for i in ids], axis=1)
            self.c = {i: cm[:, j] for j, i in enumerate(ids)}

    def cross(self, ids: list[int]) -> FloatArray:
        """(n, m) the cross-covariances of ``ids`` (zero for a plane not carried)."""
        out = np.zeros((self.n, len(ids)))
        for j, i in enumerate(ids):
            c = self.c.get(i)
            if c is not None:
                out[:, j] = c
        return out

    def keep(self, ids: list[int], cross: FloatArray, p: FloatArray, present: set[int]) -> None:
        """After a registration: ``cross`` (n, m) the joint posterior's cross-covariances of ``ids``; ``p`` (n, n)
        the state's covariance. Planes no longer in the map (``present``) or no longer correlated are dropped."""
        for j, i in enumerate(ids):
            self.c[i] = cross[:, j].copy()
        sd = np.sqrt(np.maximum(np.diag(p), 1e-30)) * self.sigma_m
        self.c = {i: c for i, c in self.c.items() if i in present and float(np.max(np.abs(c) / sd)) >= self.min_corr}


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


def joint_prior(p: FloatArray, cross: FloatArray, sigma_m: float) -> FloatArray:
    """(n+m, n+m) the joint prior information of the state (covariance ``p``, (n, n)) and m plane offsets (each
    ``sigma_m``, independent, cross-covariance ``cross`` (n, m) with the state)."""
    n, m = cross.shape
    s = np.empty((n + m, n + m))
    s[:n, :n] = p
    s[:n, n:] = cross
    s[n:, :n] = cross.T
    s[n:, n:] = np.eye(m) * sigma_m**2
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
