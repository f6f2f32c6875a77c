"""The pieces of a robot's pose graph (:mod:`mapping.posegraph`) that are GTSAM and geometry, not bookkeeping.

Frames: poses are GTSAM ``Pose2`` (north, east, heading theta); information and covariance matrices are 3x3 over
(north, east, heading) in the NED horizontal frame unless a name says *local* (the Pose2 tangent at theta, its
translation in the pose's own frame). The residuals are :class:`gtsam.CustomFactor` error functions (plain
Python: GTSAM's wrapper calls them with the values and, when it linearises, a list to fill with the Jacobians).
Every function takes the ``gtsam`` module as ``g`` where it needs one, so that importing this module needs no GTSAM.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import MapInputError

FloatArray = NDArray[np.float64]


def isam2(g: Any, threshold: float = 0.1, skip: int = 10, heading_rad: float | None = None) -> Any:
    """An iSAM2 relinearising every ``skip`` updates the variables whose estimate moved by more than ``threshold``
    (m, rad) from their linearisation point, a pose's heading by more than ``heading_rad`` where given (GTSAM's
    defaults: 0.1 every 10 updates; ``GraphConfig.relinearize_threshold``, ``relinearize_skip``,
    ``relinearize_heading_rad``). A depth-only graph's heading is held only by the compass's weak priors, and the
    translation of every between-factor turns with it: linearised up to 0.1 rad off, the estimate can sit degrees
    and decimetres from the optimum of its own factors (tests/test_posegraph.py)."""
    if threshold == 0.1 and skip == 10 and heading_rad is None:
        return g.ISAM2()
    params = g.ISAM2Params()
    if heading_rad is None:
        params.setRelinearizeThreshold(float(threshold))
    else:
        # per variable type (the symbol's character; the poses have plain integer keys): every type must be named,
        # a type left out is never relinearised
        th = g.ISAM2ThresholdMap()
        th.insert(("\x00", np.array([threshold, threshold, heading_rad], dtype=np.float64)))
        th.insert(("p", np.array([threshold], dtype=np.float64)))
        th.insert(("s", np.array([threshold, threshold], dtype=np.float64)))
        params.setRelinearizeThreshold(th)
    params.relinearizeSkip = int(skip)
    return g.ISAM2(params)


def pose2(g: Any, x: FloatArray) -> Any:
    return g.Pose2(float(x[0]), float(x[1]), float(x[2]))


def rot(a: float) -> FloatArray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def local_info(h_global: FloatArray, theta: float) -> FloatArray:
    """Information (3x3, north/east/heading) turned into GTSAM's Pose2 tangent at heading ``theta`` (the
    translation error is in the pose's own frame)."""
    a = np.eye(3)
    a[0:2, 0:2] = rot(theta)
    out = a.T @ h_global @ a
    return 0.5 * (out + out.T)


def global_cov(cov_local: FloatArray, theta: float) -> FloatArray:
    a = np.eye(3)
    a[0:2, 0:2] = rot(theta)
    return a @ cov_local @ a.T


def inflate(h: FloatArray, sigma_m: float, sigma_rad: float) -> FloatArray:
    """Information (3x3, north/east/heading) with the landmarks' own uncertainty added: along each of its
    eigenvectors the variance grows by ``sigma_m``^2 (its horizontal part) and ``sigma_rad``^2 (its heading
    part); a plane is not exact, so no scan pins a pose beyond what its planes are known to."""
    lam, vec = np.linalg.eigh(0.5 * (h + h.T))
    lam = np.maximum(lam, 0.0)
    extra = sigma_m**2 * np.sum(vec[0:2] ** 2, axis=0) + sigma_rad**2 * vec[2] ** 2
    out = (vec * (lam / (1.0 + lam * extra))) @ vec.T
    return np.asarray(0.5 * (out + out.T), dtype=np.float64)


def robust(g: Any, sigma: float) -> Any:
    """A 1-D noise model of ``sigma`` with a Huber loss beyond 1.5 sigma (a wrong association costs linearly)."""
    return g.noiseModel.Robust.Create(g.noiseModel.mEstimator.Huber.Create(1.5), g.noiseModel.Isotropic.Sigma(1, sigma))


def plane_error(n: FloatArray, c: FloatArray, const: float) -> Any:
    """The residual (1,) of a plane seen from a pose: ``n . (t + R(theta) c) + const + offset`` (``n`` the plane's
    horizontal normal, ``c`` the mean of its points in the level frame, ``const`` the vertical part and ``d``)."""
    skew = np.array([[0.0, -1.0], [1.0, 0.0]])

    def err(this: Any, values: Any, jac: Any) -> FloatArray:
        k = this.keys()
        pose = values.atPose2(k[0])
        off = values.atVector(k[1])
        r = pose.rotation().matrix()
        e = float(n @ (pose.translation() + r @ c)) + const + float(off[0])
        if jac is not None:
            jac[0] = np.array([[*(n @ r), float(n @ r @ skew @ c)]])
            jac[1] = np.ones((1, 1))
        return np.array([e])

    return err


def shared_plane_error(n: FloatArray, c: FloatArray, const: float) -> Any:
    """:func:`plane_error` with a shared horizontal offset ``delta`` (2,) of the plane's stretch added:
    ``n . (t + R(theta) c + delta) + const + offset``."""
    skew = np.array([[0.0, -1.0], [1.0, 0.0]])

    def err(this: Any, values: Any, jac: Any) -> FloatArray:
        k = this.keys()
        pose = values.atPose2(k[0])
        off = values.atVector(k[1])
        delta = values.atVector(k[2])
        r = pose.rotation().matrix()
        e = float(n @ (pose.translation() + r @ c + delta)) + const + float(off[0])
        if jac is not None:
            jac[0] = np.array([[*(n @ r), float(n @ r @ skew @ c)]])
            jac[1] = np.ones((1, 1))
            jac[2] = n.reshape(1, 2).copy()
        return np.array([e])

    return err


def anchored_error(n_loc: FloatArray, c: FloatArray, const: float) -> Any:
    """The residual (1,) of a plane fixed to an anchor pose, seen from another: ``n_loc . R_a^T (t + R c - t_a) +
    const + offset`` (``n_loc``, ``const``: the plane in the anchor's frame; ``c`` the mean of the seeing scan's
    points in its level frame)."""
    skew = np.array([[0.0, -1.0], [1.0, 0.0]])

    def err(this: Any, values: Any, jac: Any) -> FloatArray:
        k = this.keys()
        pa, pi = values.atPose2(k[0]), values.atPose2(k[1])
        off = values.atVector(k[2])
        ra, ri = pa.rotation().matrix(), pi.rotation().matrix()
        u = pi.translation() + ri @ c - pa.translation()
        e = float(n_loc @ ra.T @ u) + const + float(off[0])
        if jac is not None:
            jac[0] = np.array([[*(-n_loc), float(-n_loc @ skew @ ra.T @ u)]])
            jac[1] = np.array([[*(n_loc @ ra.T @ ri), float(n_loc @ ra.T @ ri @ skew @ c)]])
            jac[2] = np.ones((1, 1))
        return np.array([e])

    return err


def velocity_error(dt1: float, dt2: float) -> Any:
    """The residual of three poses' mean velocities (2,): (t2 - t1) / dt2 - (t1 - t0) / dt1, NED."""

    def err(this: Any, values: Any, jac: Any) -> FloatArray:
        k = this.keys()
        p0, p1, p2 = values.atPose2(k[0]), values.atPose2(k[1]), values.atPose2(k[2])
        t0, t1, t2 = p0.translation(), p1.translation(), p2.translation()
        e = (t2 - t1) / dt2 - (t1 - t0) / dt1
        if jac is not None:
            z = np.zeros((2, 1))
            r0, r1, r2 = p0.rotation().matrix(), p1.rotation().matrix(), p2.rotation().matrix()
            jac[0] = np.hstack([r0 / dt1, z])
            jac[1] = np.hstack([-r1 * (1.0 / dt2 + 1.0 / dt1), z])
            jac[2] = np.hstack([r2 / dt2, z])
        return np.asarray(e, dtype=np.float64)

    return err


def make_factor(g: Any, kind: str, keys: tuple[int, ...], data: tuple[Any, ...]) -> Any:
    """The GTSAM factor of one of :class:`mapping.posegraph.GraphNav`'s factor specs (kind, keys, plain numbers)."""
    if kind in ("prior", "map"):
        # data: mean (3,) north/east/heading and information (3x3, global axes)
        mean = np.asarray(data[0], dtype=np.float64)
        info = local_info(np.asarray(data[1], dtype=np.float64).reshape(3, 3), float(mean[2]))
        return g.PriorFactorPose2(keys[0], pose2(g, mean), g.noiseModel.Gaussian.Information(info))
    if kind in ("between", "loop"):
        # data: relative pose (3,) in the first pose's frame and its information (3x3, that pose's tangent)
        rel = np.asarray(data[0], dtype=np.float64)
        info = np.asarray(data[1], dtype=np.float64).reshape(3, 3)
        return g.BetweenFactorPose2(keys[0], keys[1], pose2(g, rel), g.noiseModel.Gaussian.Information(info))
    if kind == "velocity":
        dt1, dt2, sigma = (float(v) for v in data)
        return g.CustomFactor(g.noiseModel.Isotropic.Sigma(2, sigma), list(keys), velocity_error(dt1, dt2))
    if kind == "plane":
        pid, nx, ny, cx, cy, const, sigma = data
        return g.CustomFactor(
            robust(g, float(sigma)),
            [keys[0], g.symbol("p", int(pid))],
            plane_error(np.array([nx, ny], dtype=np.float64), np.array([cx, cy], dtype=np.float64), float(const)),
        )
    if kind == "plane_shared":
        pid, nx, ny, cx, cy, const, sigma, sid = data
        return g.CustomFactor(
            robust(g, float(sigma)),
            [keys[0], g.symbol("p", int(pid)), g.symbol("s", int(sid))],
            shared_plane_error(
                np.array([nx, ny], dtype=np.float64), np.array([cx, cy], dtype=np.float64), float(const)
            ),
        )
    if kind == "stretch_prior":
        sid, sigma = data
        return g.PriorFactorVector(g.symbol("s", int(sid)), np.zeros(2), g.noiseModel.Isotropic.Sigma(2, float(sigma)))
    if kind == "anchored":
        pid, nx, ny, cx, cy, const, sigma = data
        return g.CustomFactor(
            robust(g, float(sigma)),
            [keys[0], keys[1], g.symbol("p", int(pid))],
            anchored_error(np.array([nx, ny], dtype=np.float64), np.array([cx, cy], dtype=np.float64), float(const)),
        )
    if kind == "plane_prior":
        pid, sigma = data
        return g.PriorFactorVector(g.symbol("p", int(pid)), np.zeros(1), g.noiseModel.Isotropic.Sigma(1, float(sigma)))
    if kind == "fix":
        n, e, s = (float(v) for v in data)
        info = np.diag([1.0 / s**2, 1.0 / s**2, 1e-8])
        return g.PriorFactorPose2(keys[0], g.Pose2(n, e, 0.0), g.noiseModel.Gaussian.Information(info))
    msg = f"unknown factor kind {kind!r}"
    raise MapInputError(msg)
