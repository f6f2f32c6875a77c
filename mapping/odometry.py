"""Scan-to-scan odometry: how far a robot moved horizontally between two consecutive scans.

A robot without a horizontal fix (``depth-only``: attitude, heading and depth) has nothing but its speed to say
where it went, and a random walk at 0.3 m/s loses it within a second. Its own consecutive scans see the same
walls: registering the new scan to the previous one gives the horizontal increment, a *relative* measurement
that moves the prediction like dead reckoning does (its covariance adds to the position's; it never shrinks
it). Along one flat wall the increment along the wall is not observed: there the motion prior's walk stays.

The previous scan's points are placed in a frame at its vehicle (heading from the compass plus the current
yaw correction, roll and pitch as measured), each with the horizontal normal of its laser stripe (the stripe's
tangent from its neighbours, turned by 90 deg in the horizontal plane, toward the vehicle). The new scan's
points, placed the same way about an unknown offset ``delta`` (north, east) plus the measured change of depth,
are associated with the nearest previous point and the point-to-line residuals ``n . (p + delta - q)`` solved
by Huber-weighted Gauss-Newton with the walk as prior. Both scans are the registration's sub-samples
(``NavConfig.max_points``), in the stripes' order. Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class OdometryConfig:
    """Tuning (metres): a previous point serves within ``max_pair_m`` of a new one; its stripe neighbours must
    lie within ``max_gap_m`` (else it sits on an edge and has no normal); ``point_sigma_m`` / ``huber_m`` of a
    residual; at most ``max_independent_points`` count as independent; ``min_pairs`` associations make an
    increment; ``iterations`` re-associations; the new scan's points are sub-sampled to ``max_new_points``.
    ``residual_scale`` (off): the scan's information is divided by the residuals' own variance over
    ``point_sigma_m``'s where they scatter more (an a-posteriori variance factor: noisy stripes and their normals
    claim less)."""

    max_pair_m: float = 0.08
    max_gap_m: float = 0.05
    point_sigma_m: float = 0.01
    huber_m: float = 0.01
    max_independent_points: int = 30
    min_pairs: int = 20
    iterations: int = 3
    max_new_points: int = 100
    residual_scale: bool = False


def stripe_normals(p: FloatArray, vehicle: FloatArray, max_gap_m: float) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Horizontal normals (M, 3) of points ``p`` (M, 3) in stripe order, toward ``vehicle`` (3,); and which
    points have one (both neighbours within ``max_gap_m``)."""
    m = p.shape[0]
    n = np.zeros((m, 3))
    ok = np.zeros(m, dtype=bool)
    if m < 3:
        return n, ok
    prev, nxt = p[:-2], p[2:]
    gap_a = np.linalg.norm(p[1:-1] - prev, axis=1)
    gap_b = np.linalg.norm(nxt - p[1:-1], axis=1)
    t = nxt - prev
    nh = np.stack([-t[:, 1], t[:, 0], np.zeros(m - 2)], axis=1)
    norm = np.linalg.norm(nh, axis=1)
    good = (gap_a <= max_gap_m) & (gap_b <= max_gap_m) & (norm > 1e-6)
    nh = nh / np.maximum(norm, 1e-12)[:, None]
    # toward the vehicle
    flip = np.einsum("ij,ij->i", vehicle[None, :] - p[1:-1], nh) < 0
    nh[flip] *= -1.0
    n[1:-1] = nh
    ok[1:-1] = good
    return n, ok


def increment(
    prev_rel: FloatArray, new_rel: FloatArray, prior_cov: FloatArray, cfg: OdometryConfig
) -> tuple[FloatArray, FloatArray, int]:
    """The horizontal move (2,) between two scans and its covariance (2, 2); and the pairs used (0: none).

    Args:
        prev_rel: (M, 3) the previous scan's points relative to its vehicle (NED axes), in stripe order.
        new_rel: (K, 3) the new scan's points relative to the previous vehicle's position plus the measured change
            of depth (the unknown horizontal move left out), NED axes.
        prior_cov: (2, 2) the motion prior's covariance of the move (the move's prior mean is zero).
    """
    nq, ok = stripe_normals(prev_rel, np.zeros(3), cfg.max_gap_m)
    q = prev_rel[ok]
    nq = nq[ok]
    if q.shape[0] < cfg.min_pairs or new_rel.shape[0] < cfg.min_pairs:
        return np.zeros(2), prior_cov, 0
    if new_rel.shape[0] > cfg.max_new_points:
        new_rel = new_rel[np.linspace(0, new_rel.shape[0] - 1, cfg.max_new_points).round().astype(np.int64)]
    p_inv = np.linalg.inv(prior_cov)
    qq = np.einsum("ij,ij->i", q, q)
    delta = np.zeros(2)
    delta_assoc = delta
    h = np.zeros((2, 2))
    pairs = 0
    for _ in range(cfg.iterations):
        delta_assoc = delta.copy()
        p = new_rel.copy()
        p[:, 0:2] += delta
        # squared distances by one product (|p|^2 + |q|^2 - 2 p.q): the (K, M, 3) difference array cost most
        d2 = np.einsum("ij,ij->i", p, p)[:, None] + qq[None, :] - 2.0 * (p @ q.T)
        j = np.argmin(d2, axis=1)
        near = d2[np.arange(p.shape[0]), j] <= cfg.max_pair_m**2
        pairs = int(near.sum())
        if pairs < cfg.min_pairs:
            return np.zeros(2), prior_cov, 0
        n = nq[j[near]]
        r = np.einsum("ij,ij->i", n, p[near] - q[j[near]])
        jac = n[:, 0:2]
        w = np.minimum(1.0, cfg.huber_m / np.maximum(np.abs(r), 1e-12))
        scale = min(1.0, cfg.max_independent_points / pairs) / cfg.point_sigma_m**2
        h = scale * (jac.T * w) @ jac
        g = scale * (jac.T * w) @ r
        # Gauss-Newton on the residuals with the prior (mean 0) on the move
        delta = np.asarray(np.linalg.solve(p_inv + h, h @ delta - g), dtype=np.float64)
    if cfg.residual_scale and pairs > 2:
        # the residuals at the solution (the last association) against the sigma the information assumed
        r_end = r + jac @ (delta - delta_assoc)
        factor = float(np.sum(w * r_end**2) / np.sum(w)) / cfg.point_sigma_m**2
        h = h / max(1.0, factor)
    cov = np.linalg.inv(p_inv + h)
    return delta, 0.5 * (cov + cov.T), pairs


def own_increment(
    d: FloatArray, cov: FloatArray, prior_cov: FloatArray, info_scale: float, observed_std_m: float
) -> tuple[FloatArray, FloatArray]:
    """The scan's own measurement of the move, the prior's pull taken out of :func:`increment`'s result: its offset
    (2,) from the prior's mean and its information (2, 2), that information scaled by ``info_scale``, in the
    directions it pins the move within ``observed_std_m`` (m, after the scaling; ``inf``: every direction).

    Taking the prior out divides by the scan's information: along a direction it hardly observes (a wall's
    length, where a few noisy stripe normals lean its way) a trace of the posterior's shift becomes centimetres,
    claimed with an information as small. Such a direction is left to the prior (no information, no offset)."""
    p_inv = np.linalg.inv(prior_cov)
    h = np.linalg.inv(cov) - p_inv
    h = 0.5 * (h + h.T) * info_scale
    rhs = (p_inv + h) @ d
    if not np.isfinite(observed_std_m):
        return np.asarray(np.linalg.solve(h + np.eye(2) * 1e-6, rhs), dtype=np.float64), h
    lam, vec = np.linalg.eigh(h)
    keep = lam >= 1.0 / observed_std_m**2
    vk, lk = vec[:, keep], lam[keep]
    return np.asarray(vk @ ((vk.T @ rhs) / lk), dtype=np.float64), (vk * lk) @ vk.T
