"""The pose graph's scan odometry: one scan-to-scan increment as a between-factor's mean and information, with the
guards for a broken track (issue 27; docs/navigation-design.md, "Depth-only robots on extracted clouds").

:meth:`mapping.posegraph.GraphNav._odometry` predicts the move from the graph's velocity, lets
:func:`mapping.odometry.increment` register the new scan to the previous one about that prediction with the velocity
walk as prior, and takes the prior back out (:func:`mapping.odometry.own_increment`). Three things make that
increment wrong while it claims a few millimetres, or the graph claim it:

- **The speed bound** (``GraphConfig.odometry_speed_bound``, :func:`speed_bound`). The bound on one scan's move
  (``max_speed_m_s``) had its information added to the scan's while the move stayed the scan's: where the scan
  barely observes a direction its move there (the posterior's noise divided by that little information) can be
  decimetres, then claimed within the bound's few centimetres. ``prediction`` combines the two by their
  information; ``rest`` centres the bound at no move.
- **The weak direction** (``odometry_spread_m``, :func:`spread_bound`; ``odometry_residual_scale``). Along one
  wall a few noisy stripe normals leaning its way give the scan an information along it, more the noisier the
  stripes. How far the points pin a direction is measured, not modelled: the registration runs again from
  predictions that far either side along the weakest direction. Where the points pin the move the three runs
  agree; where they do not each stays near its start, and the spread of the results becomes the increment's
  variance there, so a broken track's standard deviation grows as its error does. The residuals' scatter beyond
  the sigma assumed scales the information down too (``OdometryConfig.residual_scale``).
- **The prediction.** The scan matching's prior is the velocity walk over one scan (about 7 mm); a prediction
  off by centimetres pulls the registration to a wrong nearest-neighbour solution. Predicting from the robot's own
  last increments, or refusing a direction whose move lies beyond the prior, was measured worse (the increments'
  errors feed the next prediction; the prior is narrower than a lost graph's velocity is wrong) and left out
  (docs/navigation-design.md, "The odometry while the track is broken").

``odometry_guard_broken_only`` applies the guards only while the track is broken (:func:`guards`): on an unbroken
track they break it sooner, where the map's planes held the estimate though the odometry could not say so.

All off by default (``GraphConfig``). Pure numpy.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from .errors import MapInputError
from .graph_config import GraphConfig
from .odometry import OdometryConfig, increment, own_increment

FloatArray = NDArray[np.float64]


def _own_move(
    prev_level: FloatArray, new_rel: FloatArray, pred: FloatArray, prior_cov: FloatArray, info_scale: float,
    observed_std_m: float, ocfg: OdometryConfig,
) -> tuple[FloatArray, FloatArray, int]:  # fmt: skip
    """The scan's own move (2,) and information (2, 2) registered about ``pred``; pairs used (0: none)."""
    shifted = new_rel + np.array([pred[0], pred[1], 0.0])
    d, cov, pairs = increment(prev_level, shifted, prior_cov, ocfg)
    if not pairs:
        return pred.copy(), np.zeros((2, 2)), 0
    dz, h = own_increment(d, cov, prior_cov, info_scale, observed_std_m)
    return pred + dz, h, pairs


def spread_bound(z: FloatArray, h: FloatArray, others: list[FloatArray]) -> FloatArray:
    """The information (2, 2) of a move ``z`` (2,) claimed with ``h`` (2, 2), bounded by the spread of the same
    registration's results ``others`` (each (2,)) from other starting points: per eigen-direction of ``h``, the
    variance ``1/lambda`` plus the squared half-spread of ``others`` plus the squared offset of their mean from
    ``z``. Where the points pin a direction the results agree and the information stays; where they do not, each
    result stays near its start and the information falls to that of the spread."""
    lam, vec = np.linalg.eigh(0.5 * (h + h.T))
    o = np.asarray(others, dtype=np.float64) @ vec
    half = 0.5 * (o.max(axis=0) - o.min(axis=0))
    off = o.mean(axis=0) - z @ vec
    var = 1.0 / np.maximum(lam, 1e-12) + half**2 + off**2
    return np.asarray((vec / var) @ vec.T, dtype=np.float64)


def scan_move(
    prev_level: FloatArray, new_rel: FloatArray, pred: FloatArray, prior_cov: FloatArray, gcfg: GraphConfig,
    ocfg: OdometryConfig,
) -> tuple[FloatArray, FloatArray, int]:  # fmt: skip
    """One scan increment for the graph: the move (2,) in the previous pose's level frame (m), the scan's
    information on it (2, 2; zero where it says nothing) and the pairs used (0: none, the move is ``pred``).

    Args:
        prev_level: (M, 3) the previous scan's points relative to its vehicle, level frame, stripe order.
        new_rel: (K, 3) the new scan's points turned into the previous level frame plus the measured change of
            depth, the horizontal move left out.
        pred: (2,) the predicted move (m); ``prior_cov`` (2, 2) its covariance as the registration's prior.
        gcfg: ``odometry_info_scale``, ``odometry_observed_std_m``, ``odometry_spread_m``.
    """
    args = (gcfg.odometry_info_scale, gcfg.odometry_observed_std_m, ocfg)
    z, h, pairs = _own_move(prev_level, new_rel, pred, prior_cov, *args)
    if not pairs:
        return z, h, 0
    if gcfg.odometry_spread_m > 0.0 and np.any(h):
        weak = np.linalg.eigh(h)[1][:, 0]
        others = [z]
        for sign in (1.0, -1.0):
            start = pred + sign * gcfg.odometry_spread_m * weak
            zo, _, po = _own_move(prev_level, new_rel, start, prior_cov, *args)
            if not po:
                # a start a few centimetres off finds no pairs: the scan does not hold the move
                return pred.copy(), np.zeros((2, 2)), 0
            others.append(zo)
        h = spread_bound(z, h, others)
    return z, h, pairs


def rot3(a: float) -> FloatArray:
    """The rotation (3, 3) about the down axis by ``a`` (rad)."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def guards(gcfg: GraphConfig, ocfg: OdometryConfig, broken: bool) -> tuple[GraphConfig, OdometryConfig]:
    """The settings one scan's odometry runs with: ``gcfg`` and ``ocfg`` as they are, or, with
    ``GraphConfig.odometry_guard_broken_only`` on an unbroken track, without the guards of this module (the
    registration to the map's planes holds the position there; the guards would only break the track sooner)."""
    if broken or not gcfg.odometry_guard_broken_only:
        return gcfg, ocfg
    off = replace(gcfg, odometry_spread_m=0.0, odometry_speed_bound="added")
    return off, replace(ocfg, residual_scale=False)


def odometry_factor(
    prev_level: FloatArray, new_rel: FloatArray, pred: FloatArray, prior_cov: FloatArray, speed_var: float,
    gcfg: GraphConfig, ocfg: OdometryConfig,
) -> tuple[FloatArray, FloatArray, int]:  # fmt: skip
    """The between-factor of one scan: its move (2,) and information (2, 2) in the previous pose's level frame,
    the scan's (:func:`scan_move`) joined with the bound on one scan's move (``speed_var``, m^2;
    :func:`speed_bound`), and the pairs the scan used (0: the move is the prediction's and the bound's alone)."""
    z, h, pairs = scan_move(prev_level, new_rel, pred, prior_cov, gcfg, ocfg)
    z, info = speed_bound(z, h, pred, speed_var, gcfg.odometry_speed_bound)
    return z, info, pairs


def speed_bound(
    z: FloatArray, h: FloatArray, pred: FloatArray, speed_var: float, how: str
) -> tuple[FloatArray, FloatArray]:
    """The between-factor's move (2,) and information (2, 2) from the scan's move ``z`` (2,) with information ``h``
    (2, 2) and the bound on one scan's move, an isotropic variance ``speed_var`` (m^2), by ``how``:

    - ``added`` (what the graph did first): the bound's information added, the move left at ``z``. Where the scan
      barely observes a direction, its move there (the posterior's noise divided by that little information) is
      then claimed with the bound's information, a few centimetres, however far it went.
    - ``prediction``: the scan's move and the bound, centred at the prediction ``pred`` (2,), combined by their
      information: a barely observed direction stays near the prediction.
    - ``rest``: the same with the bound centred at no move (a prior on the speed; the prediction, the graph's own
      velocity, is not measured again at every scan).
    """
    if how not in ("added", "prediction", "rest"):
        msg = f"odometry_speed_bound must be 'added', 'prediction' or 'rest', not {how!r}"
        raise MapInputError(msg)
    bound = np.eye(2) / speed_var
    info = h + bound
    if how == "added":
        return z, info
    centre = pred if how == "prediction" else np.zeros(2)
    return np.asarray(np.linalg.solve(info, h @ z + bound @ centre), dtype=np.float64), info
