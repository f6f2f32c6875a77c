"""Laser-aided navigation: each robot's horizontal position and heading correction, estimated from its scans.

Attitude (roll, pitch) and depth are measured well by every pose source; what a small ROV does not know is
where it is horizontally (no fix at all, or dead reckoning that drifts) and its true heading (a compass near
steel is off by degrees). So the estimator has five states per robot, in NED (metres, m/s, radians)::

    x = [north, east, bias_north, bias_east, yaw_correction]

(``bias``: the dead reckoning's velocity bias, m/s, as from a current's drag) and the corrected pose is
``(north, east, raw down, raw roll, raw pitch, raw yaw + yaw_correction)``.

One step per cloud (:meth:`RobotNav.update`), a Kalman filter whose measurement update is a robust
scan-to-map registration:

1. **Predict.** With dead reckoning (the raw pose has a horizontal position, and had one at the previous
   cloud), the raw position's increment, turned by the current yaw correction (the compass bias turned it
   too), moves the position, and so does the velocity bias times the time (a slow random walk,
   ``dr_bias_sigma_m_s`` / ``dr_bias_walk_m_s_per_sqrt_s``): the error of a dead reckoning in a current grows
   with time, not with its square root, and registrations that pin an axis estimate the bias along it, so the
   prediction follows the drift along an axis no scan pins and its covariance grows as the drift can. With
   ``dr_bias_adaptive`` (the smoothed default, ``--nav on``) each robot's bias stays closed until its fixes'
   disagreement persists, then opens for the rest of the dive: good dead reckoning keeps the model without it. The
   noise also grows with the distance (``dr_scale_sigma``) and with time (``dr_velocity_sigma_m_s``, white).
   Without a fix, the position is a random walk (``walk_speed_m_s``).
   The yaw correction is a random walk (``yaw_walk_deg_per_sqrt_s``).
2. **Fix.** A raw horizontal position is also a weak absolute measurement (``fix_sigma_m``, at most once per
   ``fix_every_s``): dead reckoning's absolute error is unknown, so it only anchors a robot the scans cannot.
3. **Register.** The cloud's points (sub-sampled) are placed with the predicted pose and associated with the
   nearest map plane (:class:`PlaneLandmarks`) that faces the vehicle, whose extent (inflated) contains the
   point and which lies within a gate set by the predicted uncertainty along its normal. The point-to-plane
   residuals (Huber-weighted) over the three unknowns (north, east, yaw correction) and the prediction are
   solved together by Gauss-Newton (a few re-associations): the MAP estimate of an iterated Kalman update.
   Points of one scan share pose and map errors, so the registration counts at most
   ``max_independent_points`` of them.
4. **Report.** The registration's own information matrix ``H`` (3x3 over north, east, yaw) says what the scan
   constrains: an axis whose standard deviation from ``H`` alone exceeds ``constrained_std_m`` /
   ``constrained_std_deg`` is not constrained (one flat wall: the position along it). The posterior covariance
   gives the ``*_std`` of the estimate; a cloud is *placed* (mapped) only while both horizontal standard
   deviations stay below ``place_std_m``.

The map (``mapping.MapBuilder``) owns the planes; the estimator only reads them (:meth:`MapBuilder.landmarks`).
Everything here is numpy: the problem is three unknowns with a Kalman prior, solved in well under a millisecond
(see docs/navigation.md for the choice against GTSAM, Open3D ICP and scipy).

The code is in five modules, by what each part does: :mod:`mapping.nav_config` (:class:`NavConfig`,
:class:`NavEstimate`), :mod:`mapping.nav_filter` (:class:`RobotNav`: the state, prediction, fixes, the
registration update and the report), :mod:`mapping.nav_error` (the dead reckoning's error as a state: its
prediction, bound and rate update), :mod:`mapping.navigator` (:class:`Navigator`: one estimator per robot and the
fleet's frame) and :mod:`mapping.nav_frame` (:class:`NavFrame`); this module exports their public names.
"""

from __future__ import annotations

from .landmarks import PlaneLandmarks, associate, subsample
from .nav_config import AXES, NavConfig, NavEstimate
from .nav_filter import RobotNav
from .nav_frame import NavFrame
from .navigator import Navigator

__all__ = [
    "AXES",
    "NavConfig",
    "NavEstimate",
    "NavFrame",
    "Navigator",
    "PlaneLandmarks",
    "RobotNav",
    "associate",
    "subsample",
]
