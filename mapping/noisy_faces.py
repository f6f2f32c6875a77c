"""Faces seen through noisy far stripes: the sensor's expected noise in a plane's thickness, a prior on its tilt.

Why. A triangulating sensor's range error grows as ``k r^2`` (:mod:`mapping.range_noise`): the 640x360 clouds of
the simulated dives are 3-8 cm off at 4-5 m. Such a face's two stripes fix its horizontal direction (each stripe
is a long line along it) and its offset (many points average), but not its vertical tilt: the tilt is the stripes'
difference in range over their 10 cm of height, and a few centimetres of noise tilt it by tens of degrees. The
fixed gates then refuse it (an RMS above ``max_rms_m``), so in a fleet's first seconds, when the robots see the far
walls only, the map stays thin (docs/mapping.md, "Noisy far faces").

What (``MapConfig.tilt_prior_deg``, 10 deg by default; 0 leaves every path as it was before it):

- **The tilt as far as the points determine it.** A near-vertical plane's normal is the smallest axis of the
  points' scatter plus a prior along down, ``sum_i (sigma_i / tan(tilt_prior))^2 e_z e_z^T`` (``sigma_i`` each
  point's expected error): the maximum a posteriori plane for a tilt prior of standard deviation ``tilt_prior``
  about vertical, the data weighted by its own noise. Near views (millimetres of noise, a stripe pair's full
  height) keep the tilt they measure; a far noisy pair is pulled toward vertical. The prior travels with the
  observation in the map (its ``within`` scatter, :func:`prior_within`), so a plane fused from near and far views
  takes its tilt from the near ones. A plane whose data normal is more than ``_PRIOR_MAX_TILT_DEG`` from
  horizontal even with it (floors, a single stripe's near-horizontal ribbon) is judged as without it.
- **Thickness beyond the noise.** Where the extraction and the map test a near-vertical plane's RMS and bulge
  (``max_rms_m``, ``max_sagitta_m`` less one expected error, the
  fusion's ``merge_offset_m`` / ``merge_max_rms_m`` / ``merge_added_rms_m``), they test what is left once its
  points' mean expected variance is taken out (:func:`excess_rms_m`): each record carries the sum of its points'
  expected variances (:attr:`mapping.plane_map.PlaneRecord.noise`, exact quanta^2).

Frames and units: NED metres; noise sums in quanta^2 of ``MapConfig.quantum_m``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from .types import MapConfig

FloatArray = NDArray[np.float64]

#: A plane's data normal within this of horizontal (i.e. the face within this of vertical) gets the tilt prior.
_PRIOR_MAX_TILT_DEG = 45.0


def expected_error_m(points: FloatArray, vehicle: FloatArray, noise_per_m: float | FloatArray) -> FloatArray:
    """Each point's expected range error (metres, :func:`error_at_r2`), (N,): ``points`` and ``vehicle`` (N, 3) in
    one frame (metres), ``noise_per_m`` the range noise k (1/m), one or (N,)."""
    d = points - vehicle
    return error_at_r2(np.asarray(noise_per_m, dtype=np.float64), np.einsum("ij,ij->i", d, d))


#: The extractor's stripe row error grows with range beyond the band ``stripe_sigma_px`` was measured in (robust sd
#: against the ray-traced truth, ``python -m benchmarks.diag_stripe_error``: 0.018 px at 2-2.5 m, 0.046 at 3-4 m,
#: 0.079 at 4-6 m; docs/mapping.md, "Range noise"): beyond :data:`GROWTH_REF_M` the expected error is ``k r^2``
#: times ``(r / GROWTH_REF_M) ** GROWTH`` (0.045 and 0.089 px at 3.5 and 5 m).
GROWTH = 2.0
GROWTH_REF_M = 2.25

#: A near-vertical plane's horizontal direction needs its points spread along it by at least this many expected
#: errors (its second principal spread): a short far stripe pair's yaw is as uncertain as its tilt.
YAW_SPREAD_SIGMAS = 3.0


def error_at_r2(k: float | FloatArray, r2: FloatArray) -> FloatArray:
    """The expected error (metres), (N,), of points at squared ranges ``r2`` (N,) (m^2) for the range noise ``k``
    (1/m, one or (N,)): ``k r^2``, grown beyond :data:`GROWTH_REF_M`."""
    growth = np.maximum(1.0, np.sqrt(r2) / GROWTH_REF_M) ** GROWTH
    return np.asarray(k * r2 * growth, dtype=np.float64)


def noise_quanta2(sigma_m: FloatArray, quantum_m: float) -> int:
    """The sum of the squared expected errors ``sigma_m`` (N,) (metres) in whole quanta^2 (exact once rounded)."""
    return round(float(np.sum(np.square(sigma_m))) / (quantum_m * quantum_m))


def prior_active(cfg: MapConfig, normal: FloatArray) -> bool:
    """Whether a plane of (unit) ``normal`` gets the tilt prior: the option on, and a near-vertical face."""
    return cfg.tilt_prior_deg > 0.0 and abs(float(normal[2])) <= math.sin(math.radians(_PRIOR_MAX_TILT_DEG))


def prior_weight(cfg: MapConfig) -> float:
    """``1 / tan^2(tilt_prior_deg)``: the prior's scatter along down per unit of expected variance."""
    return 1.0 / math.tan(math.radians(cfg.tilt_prior_deg)) ** 2


def prior_within(noise_q2: int, normal: FloatArray, cfg: MapConfig) -> int:
    """The tilt prior of an observation whose points' expected variances sum to ``noise_q2`` (quanta^2) and whose
    data normal is ``normal`` (3,): what it adds to the ``down, down`` element of its ``within`` scatter
    (quanta^2; 0 when the prior is off or the face is not near vertical)."""
    if noise_q2 <= 0 or not prior_active(cfg, normal):
        return 0
    return round(noise_q2 * prior_weight(cfg))


def excess_rms_m(rms_m: float, noise_var_m2: float) -> float:
    """A plane's RMS thickness beyond its points' mean expected variance ``noise_var_m2`` (m^2), metres (``rms_m``
    itself, exactly, without a noise: the fixed gates' arithmetic)."""
    return rms_m if noise_var_m2 <= 0.0 else math.sqrt(max(rms_m * rms_m - noise_var_m2, 0.0))


def mean_var_m2(noise_q2: int, n_points: int, quantum_m: float) -> float:
    """The mean expected variance (m^2) of ``n_points`` points whose expected variances sum to ``noise_q2``."""
    return noise_q2 * quantum_m * quantum_m / n_points if n_points > 0 else 0.0


def horizontal_spread(x: FloatArray, normal: FloatArray) -> float:
    """The standard deviation (metres) of centred points ``x`` (K, 3) along the horizontal in-plane axis of a
    near-vertical plane of ``normal`` (3,): how far its stripes run along the face."""
    u = np.cross(np.array([0.0, 0.0, 1.0]), normal)
    return float(np.std(x @ (u / max(float(np.linalg.norm(u)), 1e-12))))


def prior_fit(
    points: FloatArray, sigma_m: FloatArray, cfg: MapConfig
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """The plane of (K, 3) ``points`` (metres) with the tilt prior, their expected errors ``sigma_m`` (K,) (the
    option on): (centroid (3,), variances (3,) of the points along the axes, axes (3, 3) columns ascending by the
    regularized scatter, the first the normal, the points' expected RMS error in metres). Where the regularized
    normal is near horizontal (a near-vertical face) the first variance has the mean expected variance taken out
    and the expected error is returned; elsewhere (a floor, a single stripe's ribbon) the axes and variances are
    the plain ones and the error 0: the fixed gates judge it."""
    c = points.mean(axis=0)
    x = points - c
    cov = x.T @ x / points.shape[0]
    var = float(np.mean(np.square(sigma_m)))
    reg = cov.copy()
    reg[2, 2] += var * prior_weight(cfg)
    _w, axes = np.linalg.eigh(reg)
    if not prior_active(cfg, axes[:, 0]):
        w, axes = np.linalg.eigh(cov)
        return c, np.maximum(w, 0.0), axes, 0.0
    w = np.maximum(np.einsum("ij,ik,kj->j", axes, cov, axes), 0.0)
    w[0] = max(w[0] - var, 0.0)
    return c, w, axes, math.sqrt(var)
