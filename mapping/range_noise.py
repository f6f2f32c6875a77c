"""Each cloud's range noise k for the map's plane extraction: from its robot's calibration, or one override.

A triangulating sensor's range error grows as ``r^2``: a stripe row error of ``sigma_v`` pixels moves a point at
range ``r`` by about ``k r^2``, ``k = sigma_v / (f_px c)`` (focal length in pixels, the laser plane's distance from
the camera centre: :func:`lrsensor.range_theory.range_error_per_px` gives ``1 / (f_px c)`` of a calibration). So
one k cannot fit every robot: a 640x360 camera's clouds are several times noisier at 3 m than a 1920x1080 one's,
and the traced benchmark clouds (2 mm of noise at any range) have no such growth at all.

Policy, per cloud (:func:`cloud_noise_per_m`):

- ``MapConfig.range_noise_per_m`` > 0: that k for every cloud (an explicit override, as before);
- else the base knows the calibration the cloud was measured with (a schema-2 cloud carries its fingerprint,
  :mod:`services.calibbook`): ``MapConfig.stripe_sigma_px`` times that calibration's ``1 / (f_px c)``;
- else (a schema-1 cloud, a replayed or traced one): 0, the fixed thresholds.

``stripe_sigma_px`` is :data:`STRIPE_SIGMA_PX` by default; 0 turns the per-robot k off (docs/mapping.md, "Range
noise", gives the dozen extracted dives it was judged on).

The builder keeps each cloud's k with the cloud in its robot's window; an extraction reads one k for the window
when its clouds share one (every cloud of one robot, as a rule) and one per point otherwise
(:func:`window_noise`): :mod:`mapping.planes` then takes a cell's mean and a region's median of its points' own
expected errors ``k r^2``, so a region with points of a robot without a calibration leans to the fixed thresholds.

:data:`STRIPE_SIGMA_PX` (0.0185 px) lies within the extractor's measured row error at 2-2.5 m of depth (0.018 px
robust standard deviation against the ray-traced truth; 0.028 at 2.5-3 m), where ``k r^2`` reaches the fixed
thresholds (``python -m benchmarks.diag_stripe_error``). Within that band it is the value that gives the 640x360
camera of the simulated dives the one k (0.002) that mapped a dozen extracted dives best under every robot order
tried: the choice is the measurement's, the last digit the maps'.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from .errors import MapInputError
from .types import MapConfig

FloatArray = NDArray[np.float64]

#: The extractor's stripe row error (pixels, standard deviation) at 2-2.5 m: ``MapConfig.stripe_sigma_px``'s
#: default, which turns each robot's calibration into its clouds' range noise.
STRIPE_SIGMA_PX: float = MapConfig.stripe_sigma_px


def cloud_noise_per_m(cfg: MapConfig, range_error_per_px: float) -> float:
    """The range noise k (1/m) of a cloud measured with a calibration whose range error per pixel per squared
    metre is ``range_error_per_px`` (1/(m px); 0: no calibration known): ``cfg.range_noise_per_m`` when > 0 (the
    override), else ``cfg.stripe_sigma_px * range_error_per_px``."""
    if cfg.range_noise_per_m > 0.0:
        return cfg.range_noise_per_m
    per_px = float(range_error_per_px)
    if not np.isfinite(per_px) or per_px < 0.0:
        msg = f"range error per pixel must be a finite number >= 0, got {range_error_per_px!r}"
        raise MapInputError(msg)
    return cfg.stripe_sigma_px * per_px


def window_noise(noise_per_m: Sequence[float], lens: NDArray[np.int64]) -> float | FloatArray:
    """The range noise of a window for :func:`mapping.planes.extract_planes`: its clouds' common k (1/m) when they
    share one, else (N,) each point its cloud's k (``lens``: (C,) points per cloud, in window order)."""
    ks = np.asarray(noise_per_m, dtype=np.float64)
    if ks.size == 0 or bool(np.all(ks == ks[0])):
        return float(ks[0]) if ks.size else 0.0
    return np.repeat(ks, lens)
