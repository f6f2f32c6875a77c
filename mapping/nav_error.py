"""The dead reckoning's error as a state of :class:`mapping.nav_filter.RobotNav` (``NavConfig.dr_error_state``):
its prediction, its physical bound, and how much of a registration's correction its rate takes.

State layout (n = 7; NED metres, m/s, radians): ``[north, east, rate_north, rate_east, yaw_correction, d_north,
d_east]``, d the dead reckoning's error (raw minus true position) and ``rate`` d's rate of change.

**The rate and the registrations.** A registration measures the position; with the fixes (position plus d) that
is d, and over scans d's rate. One registration to a wrong plane (a plane another robot began a second before,
14 cm off its face) therefore also writes a rate, and a confident wrong rate carries the position off along every
axis no scan pins, at minus the rate (docs/navigation-design.md, "Where the runaway starts"). With
``NavConfig.dr_error_rate_weight`` below 1 the Kalman gain's rows for the two rate states are scaled by it
(:func:`consider_update`): at 0 a Schmidt ("consider") update, in which the registration moves the position, the
heading and d but not the rate, and the covariance is the one of that gain (Joseph form), so the rate's variance
and its cross-covariances stay consistent with what the state now holds. With ``dr_error_rate_young_s`` > 0 the
weight applies only to registrations that use a plane first seen less than that before the scan
(:func:`young_planes`, :func:`rate_weight`); the others update the rate in full.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from .nav_frame import rot2

if TYPE_CHECKING:
    from .landmarks import PlaneLandmarks
    from .nav_config import NavConfig

__all__ = ["RATE", "bound_error", "consider_update", "error_prediction", "rate_gain", "rate_weight", "young_planes"]

FloatArray = NDArray[np.float64]

#: the rate states' indices in the 7-state vector
RATE = (2, 3)


def error_prediction(
    x: FloatArray, dr: FloatArray, dt: float, cfg: NavConfig
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The prediction with the dead reckoning's error as a state: the raw increment ``dr`` (north, east; m) turned
    by the yaw correction moves the position, less what the error's rate moved d by; so position plus d moves
    exactly as the raw position does.

    Args:
        x: (7,) the state before (layout in the module docstring).
        dr: (2,) the raw position's increment since the previous scan, m.
        dt: the time since, s (negative counts as 0).
        cfg: ``dr_error_walk_m_per_sqrt_s``, ``dr_error_bias_walk_m_s_per_sqrt_s``, ``dr_scale_sigma``,
            ``dr_velocity_sigma_m_s``.

    Returns (the state after (7,), the transition F (7, 7), the process noise Q (7, 7) without the yaw's).
    """
    dt = max(dt, 0.0)
    n = x.size
    step = rot2(float(x[4])) @ dr
    f = np.eye(n)
    # the increment turns with the yaw correction (d(step)/dc = ez x step); what the turn adds to the position the
    # dead reckoning did not see, so it is error too
    f[0:2, 4] = [-step[1], step[0]]
    f[5:7, 4] = [step[1], -step[0]]
    f[0, 2] = f[1, 3] = -dt
    f[5, 2] = f[6, 3] = dt
    b = x[2:4]
    out = x.copy()
    out[0:2] += step - b * dt
    out[5:7] += (dr - step) + b * dt
    q = np.zeros((n, n))
    # the error's own walk moves the position the other way (the raw increment is what it is)
    walk = cfg.dr_error_walk_m_per_sqrt_s**2 * dt
    for i, j in ((0, 5), (1, 6)):
        q[i, i] = q[j, j] = walk
        q[i, j] = q[j, i] = -walk
    # the increment's own noise (scale, white velocity) moves the position alone: position plus d is then no
    # deterministic sum, and the smoother's backward pass does not invert a near-singular prediction
    inc = (cfg.dr_scale_sigma * float(np.hypot(*step))) ** 2 + (cfg.dr_velocity_sigma_m_s * dt) ** 2
    q[0, 0] += inc
    q[1, 1] += inc
    q[2, 2] = q[3, 3] = cfg.dr_error_bias_walk_m_s_per_sqrt_s**2 * dt
    return out, f, q


def bound_error(
    x: FloatArray,
    p: FloatArray,
    pin_d: FloatArray,
    pin_dist: FloatArray,
    pin_time: FloatArray,
    speed_m_s: float,
    cfg: NavConfig,
) -> tuple[FloatArray, FloatArray]:
    """Bound the dead reckoning's error as the physics does (``NavConfig.dr_error_bound_fraction`` F > 0): per axis,
    d's variance is at most the fix's plus (F x the distance since the scans last pinned the axis)^2 plus (current x
    the time since)^2, and its rate's at most (F x the speed)^2 + current^2. A scalar pseudo-measurement (d toward
    its value at the pin; the rate toward 0) whose noise brings the variance exactly to the bound, applied only where
    it is exceeded: without it the rate's walk, and d with it, ran away while no scan pinned the robot, and the
    registration's gates widened until the scans fit other walls.

    Args:
        x, p: (7,), (7, 7) the state and its covariance.
        pin_d, pin_dist, pin_time: (2,) per axis (north, east) d at the last pin (m), the distance (m) and the
            time (s) since.
        speed_m_s: the last scan's speed.

    Returns the state and covariance (new arrays where bounded).
    """
    frac, cur = cfg.dr_error_bound_fraction, cfg.dr_error_bound_current_m_s
    if frac <= 0:
        return x, p
    fix2 = cfg.dr_error_fix_sigma_m**2
    for axis in range(2):
        bound_d = fix2 + (frac * pin_dist[axis]) ** 2 + (cur * pin_time[axis]) ** 2
        bound_b = (frac * speed_m_s) ** 2 + cur**2
        for i, target, bound in ((5 + axis, pin_d[axis], bound_d), (2 + axis, 0.0, bound_b)):
            var = float(p[i, i])
            if var <= bound * 1.0001:
                continue
            r = var * bound / (var - bound)
            k = p[:, i] / (var + r)
            x = x + k * (target - float(x[i]))
            p = p - np.outer(k, p[i, :])
            p = 0.5 * (p + p.T)
    return x, p


def young_planes(lm: PlaneLandmarks, t_ns: int, young_s: float) -> NDArray[np.bool_]:
    """(P,) whether each plane of ``lm`` was first seen (by any robot) less than ``young_s`` before ``t_ns`` (ns).
    Planes without contributions (built from JSON without them) count as old."""
    out = np.zeros(len(lm), dtype=bool)
    if young_s <= 0 or not lm.contrib:
        return out
    horizon = t_ns - int(young_s * 1e9)
    for i, c in enumerate(lm.contrib):
        if c and min(first for _, first in c.values()) > horizon:
            out[i] = True
    return out


def consider_update(
    x_pred: FloatArray, p_pred: FloatArray, x_opt: FloatArray, p_opt: FloatArray, hf: FloatArray, gain: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """A registration's update with the Kalman gain's rows scaled per state (a Schmidt "consider" update where 0).

    The registration is an information update (``hf``, the points' information over the whole state, zero outside
    north, east, yaw): its optimal result ``x_opt``, ``p_opt = (p_pred^-1 + hf)^-1`` has the gain K with
    ``K H = p_opt hf`` and ``K R K^T = p_opt hf p_opt``. With the gain ``G K`` (G = diag(``gain``)) the state moves by
    ``G (x_opt - x_pred)`` and the covariance is that gain's (Joseph form)::

        P = (I - G p_opt hf) p_pred (I - G p_opt hf)^T + G p_opt hf p_opt G

    which is ``p_opt`` where every factor is 1, and leaves a state whose factor is 0 with its prior variance.

    Args:
        x_pred, p_pred: (n,), (n, n) the prediction.
        x_opt, p_opt: (n,), (n, n) the optimal (full-gain) posterior.
        hf: (n, n) the registration's information.
        gain: (n,) each state's share of its gain row, 0-1.

    Returns the state (n,) and its covariance (n, n), symmetric.
    """
    g = np.asarray(gain, dtype=np.float64)
    a = g[:, None] * (p_opt @ hf)
    i_a = np.eye(x_pred.size) - a
    ph = p_opt @ hf @ p_opt
    p = i_a @ p_pred @ i_a.T + g[:, None] * ph * g[None, :]
    return x_pred + g * (x_opt - x_pred), 0.5 * (p + p.T)


def rate_gain(n: int, weight: float) -> FloatArray:
    """(n,) the gain factors of :func:`consider_update` that scale the two rate states' rows by ``weight``."""
    g = np.ones(n)
    g[list(RATE)] = weight
    return g


def rate_weight(cfg: NavConfig, young: bool) -> float:
    """The share of a registration's gain the error's rate takes (see the module docstring).

    Args:
        cfg: ``dr_error_state``, ``dr_error_rate_weight``, ``dr_error_rate_young_s``.
        young: whether the registration used a young plane (:func:`young_planes`).
    """
    if not cfg.dr_error_state or cfg.dr_error_rate_weight >= 1.0:
        return 1.0
    if cfg.dr_error_rate_young_s > 0 and not young:
        return 1.0
    return cfg.dr_error_rate_weight
