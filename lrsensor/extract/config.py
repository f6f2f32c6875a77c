"""The options of the sub-pixel extractor: :class:`SubpixelConfig`, one frozen record validated on creation.

Units are in the names (``_m``, ``_px``, ``_dn``, ``_cols``, ``_mm``). The defaults suit the paper's camera
(1920x1080, f = 554 px) and lasers 0.1 m apart; :meth:`SubpixelConfig.from_options` applies keyword overrides
(``Sensor.process(image, min_range_m=0.3)``) and refuses unknown names. The compiled road and the reference read
the options through one record built from this one (:mod:`lrsensor.extract.settings`).

The candidates are always detected on the green channel averaged over 2x2 pixels (the compiled detection is
written for that scale; full-resolution detection had no user and is gone), and the centres always fitted at full
resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

from ..errors import ExtractionError
from . import CHANNELS, config_with_options
from .centre import FWHM_PER_SIGMA

#: Centroid iterations of the sub-pixel fits.
ITERATIONS = 2
#: The pooled signal-to-noise ratio of a column is at most its own divided by this.
SNR_FLOOR_FRAC = 0.75


@dataclass(frozen=True)
class SubpixelConfig:
    """Options of the sub-pixel extractor (units in the names; defaults suit the paper's camera).

    Attributes:
        min_range_m, max_range_m: depth limits along the optical axis, metres; only the image band where a
            laser can light a surface between them is searched.
        max_sigma_px: widest stripe profile accepted (Gaussian sigma across the stripe, pixels).
        min_fwhm_px: narrowest accepted stripe (full width at half maximum); narrower peaks are speckle.
        saturation_dn: green level from which a sample counts as clipped.
        min_contrast_dn: smallest accepted stripe peak above the local background, DN.
        snr_threshold: detection threshold in units of the measured background noise.
        max_candidates: candidates kept per column (strongest first).
        max_jump_px: largest row change between neighbouring columns of one stripe piece (x1.5 per detection
            column: the candidates are detected at half resolution).
        min_run_cols: shortest accepted stripe piece, columns.
        smooth_half_cols: half-width of the middle scale of the along-stripe line fits, columns; the scales are
            16x, 4x, 1x and 1/4x this (0 = no smoothing); the 16x windows must fit in each quarter too.
        min_green_ratio: the green rise of a point (summed with its neighbours', see ``gate_pool_cols``) must
            exceed this multiple of the red and of the blue rise.
        min_snr: smallest accepted peak-to-noise ratio of a point (noise: the larger of the band's and the
            profile's flanks'); saturated peaks always pass.
        max_sheet_mm: thickest laser sheet on the surface (mm, divergence included): a stripe may be as wide
            as this sheet seen at the range of its row (``max_sheet_mm * f / range``) plus 4 px of blur, or
            ``FWHM_PER_SIGMA * max_sigma_px`` where that is larger; close to the wall a thick sheet draws a
            wide, flat-topped stripe, far away the same width would be glow or haze.
        gate_pool_cols: the colour test and the signal-to-noise ratio of a point are pooled over the fitted
            columns of its stripe piece within this many columns either side (rises summed, ratios' median);
            0 = per column. A dim stripe is then not decimated by single noisy pixels.
        channel: what the stripe is found and fitted in. ``"green"`` (default): the green channel, best for
            lossless frames. ``"luma"``: the luma on green's scale (:func:`luma_as_green`), for frames whose
            colour was stored at half resolution (JPEG, MJPEG and H.264 cameras), where green blurs and shifts
            the stripe by chroma sampled every other pixel; it costs about a millisecond more per 1920x1080
            frame, and on lossless frames a dim pure-green stripe loses about an eighth of its SNR to the red
            and blue noise it adds.
        glow_fit: in turbid water, fit the centre of the stripes whose profile shows the laser sheet's glow
            jointly with the glow's edge (:mod:`lrsensor.extract.glow`; False: the common fit everywhere, which
            reads glowing walls short).
    """

    min_range_m: float = 0.2
    max_range_m: float = 5.0
    max_sigma_px: float = 5.0
    min_fwhm_px: float = 0.8
    saturation_dn: float = 250.0
    min_contrast_dn: float = 5.0
    snr_threshold: float = 4.0
    max_candidates: int = 4
    max_jump_px: float = 3.0
    min_run_cols: int = 8
    smooth_half_cols: int = 24
    min_green_ratio: float = 1.2
    min_snr: float = 2.5
    max_sheet_mm: float = 20.0
    gate_pool_cols: int = 4
    channel: str = "green"
    glow_fit: bool = True

    def __post_init__(self) -> None:
        if self.channel not in CHANNELS:
            msg = f"channel must be one of {CHANNELS}, got {self.channel!r}"
            raise ExtractionError(msg)
        if not (0 < self.min_range_m < self.max_range_m):
            msg = f"need 0 < min_range_m < max_range_m, got {self.min_range_m} and {self.max_range_m}"
            raise ExtractionError(msg)
        if not self.max_sigma_px > 0 or not self.min_fwhm_px >= 0:
            msg = f"stripe width limits must be positive, got max_sigma_px={self.max_sigma_px}"
            raise ExtractionError(msg)
        if self.max_candidates < 1 or self.min_run_cols < 1 or self.smooth_half_cols < 0 or self.gate_pool_cols < 0:
            msg = "max_candidates and min_run_cols must be >= 1, smooth_half_cols and gate_pool_cols >= 0"
            raise ExtractionError(msg)

    @classmethod
    def from_options(cls, config: SubpixelConfig | None = None, **options: Any) -> SubpixelConfig:
        """``config`` (or the defaults) with keyword overrides; unknown names raise :class:`ExtractionError`."""
        if config is None and not options and cls is SubpixelConfig:
            return _default_config()  # the per-frame common case: one frozen instance
        return config_with_options(cls, config, "subpixel", options)

    @property
    def contrast_px(self) -> int:
        """Row offset d of the two-sided contrast (even): about 2 sigma beyond the widest stripe's centre."""
        return 2 * math.ceil(self.max_sigma_px + 2.0)

    @property
    def window_half_px(self) -> int:
        """Half-length of the profile cut out around each stripe for the centre fit."""
        return math.ceil(2.6 * 0.5 * FWHM_PER_SIGMA * self.max_sigma_px + 5.0)


@lru_cache(maxsize=1)
def _default_config() -> SubpixelConfig:
    """The default :class:`SubpixelConfig` (frozen, so one instance serves every call)."""
    return SubpixelConfig()
