"""The default extractor: one sub-pixel stripe centre per image column per laser.

Pipeline (per laser, only inside the image band the laser can reach for the configured depth limits, see
:mod:`lrsensor.extract.bands`; that band is what makes it fast):

1. **Response**: on the green channel averaged over 2x2 pixels and then 3 of those columns (averages the noise
   along the stripe, quarters the work), the two-sided contrast ``G(v) - max(G(v - d), G(v + d))`` with ``d`` just
   beyond the widest stripe: positive on thin ridges only, not on murk gradients, the backscatter glow of the
   laser sheet, haze or wide blobs.
2. **Candidates**: its vertical local maxima above a threshold from the measured noise (robust second
   differences, blind to smooth gradients); several per column (up to ``max_candidates``).
3. **Continuity**: candidates of neighbouring columns are linked when they are mutually nearest and closer than
   a row step (small gaps bridged); linked chains are stripe pieces. Per column the candidate on the strongest
   chain wins; chains shorter than ``min_run_cols`` (speckle, marine snow, small blobs) are dropped.
4. **Sub-pixel centre** of the chosen candidate on the raw full-resolution green profile of its column
   (:mod:`lrsensor.extract.fit`; in the reference
   :func:`lrsensor.extract.centre.fit_profiles`): re-centred on the integer peak (the
   middle of a clipped run), local linear background from two flanks, width check (too narrow = speckle or a
   hot pixel, too wide = glow/haze/blob), Gaussian-weighted centroid with a Newton step (saturated: symmetric
   window centroid). Unbiased for any symmetric profile. Then a colour check (green must rise more than red
   and blue) and a signal-to-noise gate with the local noise of the flanks, both pooled over the point's
   neighbours on its stripe piece (``gate_pool_cols``), so that single noisy pixels do not decide.
5. **Along-stripe smoothing** (default on): per run of a chain (wide pieces within ``max_jump_px`` rows of each
   other joined: a flat top's candidate row wanders and splits its chain), local straight-line fits over up to
   ``2 (16 smooth_half_cols) + 1`` columns; of the centred, left and right windows the one with the smallest
   residual is kept (corners and steps are not rounded), and the largest window whose residual matches the
   local noise wins (the longest must match in each of its quarters too). It averages the independent
   per-column noise (the dim ends of a stripe and far walls most).
6. **Quality** in [0, 1] from the signal-to-noise ratio, the width and the chain length.

Compressed frames (JPEG, MJPEG, H.264: colour stored at half resolution) take ``channel="luma"``: the pipeline
then reads, in place of green, the full-resolution luma on green's scale (:func:`luma_as_green`).

One road: with numba installed the whole pipeline, and for :class:`lrsensor.sensor.Sensor` the triangulation
(eq. 29 with the calibration's distortion) and the range-limit gate, runs as seven compiled calls
(:func:`lrsensor.extract.frame.extract_frame`; the stages are the modules of this package, see the package
documentation). The numpy and OpenCV reference (:mod:`lrsensor.extract.reference`) runs the same algorithm where
the compiled road cannot: without numba, while the kernels compile in the background (a ROV's first use, said in
the log; :mod:`lrsensor.extract.compile`), or when a test sets
:data:`USE_REFERENCE`. Both read one set of records built once per (calibration, configuration)
(:func:`lrsensor.extract.settings.frame_settings`).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from . import Detections, reference
from .compile import usable
from .config import SubpixelConfig
from .frame import extract_frame
from .settings import frame_settings

__all__ = ["USE_REFERENCE", "SubpixelConfig", "extract", "extract_points", "luma_as_green"]

FloatArray = NDArray[np.float64]

#: Run the numpy reference instead of the compiled road (tests and the ``--flank-gate`` benchmark set it; the
#: reference also runs wherever the compiled road cannot: without numba, or while it compiles).
USE_REFERENCE = False


#: Luma (ITU-R BT.601, as JPEG's) over its green weight, per B, G, R: ``G + 0.194 B + 0.509 R``.
_LUMA_ON_GREEN = np.array([[1.0, 0.0, 0.0], [0.114 / 0.587, 1.0, 0.299 / 0.587], [0.0, 0.0, 1.0]], np.float32)


def luma_as_green(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """A copy of the BGR ``image`` (H, W, 3) uint8 whose green channel is the luma over its green weight,
    ``(0.114 B + 0.587 G + 0.299 R) / 0.587`` rounded and clipped at 255; blue and red unchanged.

    A JPEG (and MJPEG, H.264) frame stores luma at full resolution and colour at half: its green is luma plus
    colour sampled every other pixel, which blurs a thin stripe and moves its centre by up to tenths of a pixel,
    depending on where the stripe falls between the colour samples. The luma of the decoded pixels is the
    stored full-resolution one (up to rounding); on green's scale it keeps green's levels for a green stripe
    (the DN limits hold) and adds what the stripe leaks into red and blue. A clipped green stays clipped.
    """
    return np.asarray(cv2.transform(image, _LUMA_ON_GREEN), np.uint8)  # uint8 in, uint8 out (saturated)


def extract(
    image: NDArray[np.uint8], calibration: Calibration, config: SubpixelConfig | None = None, **options: Any
) -> Detections:
    """Sub-pixel stripe centres of every laser: one per column per laser (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR of the calibration's size.
        calibration: the sensor's calibration (the search bands are derived from it).
        config: extractor options (default :class:`SubpixelConfig`).
        **options: overrides of single :class:`SubpixelConfig` fields (e.g. ``min_range_m=0.3``).

    Returns:
        :class:`Detections` with pixel coordinates (N, 2), laser index (N,) and quality (N,).
    """
    return extract_points(image, calibration, config, triangulate=False, **options)[0]


def extract_points(
    image: NDArray[np.uint8],
    calibration: Calibration,
    config: SubpixelConfig | None = None,
    *,
    triangulate: bool = True,
    water: FloatArray | None = None,
    **options: Any,
) -> tuple[Detections, FloatArray | None]:
    """:func:`extract`, and with ``triangulate`` the body-frame points (N, 3) of the detections, metres, computed
    in the same call and depth-gated: only the points whose camera depth is within the range limits are returned
    (detections included). Without ``triangulate``: no depth gate, and None for the points. ``water``: (3,) float64,
    what a camera's earlier frames told of turbid water (:func:`lrsensor.extract.glow.new_water`, read and updated;
    None: this frame alone tells it)."""
    cfg = SubpixelConfig.from_options(config, **options)
    image = np.ascontiguousarray(image) if cfg.channel == "green" else luma_as_green(image)
    bands, settings, geometry = frame_settings(calibration, cfg)
    if not USE_REFERENCE and usable():
        uv, laser, quality, xyz, _ = extract_frame(image, bands, settings, geometry, triangulate, water)
    else:
        uv, laser, quality, xyz = reference.extract_frame(
            image, calibration, bands, settings, geometry, triangulate, water
        )
    return Detections(uv, laser, quality), (xyz if triangulate else None)
