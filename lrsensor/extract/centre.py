"""Sub-pixel centre of laser-stripe profiles, vectorized over many 1-D profiles (image columns) at once.

The estimator is unbiased for any symmetric stripe profile (Gaussian, pixel-integrated Gaussian, blurred,
flat-topped by saturation), so it does not depend on the exact optics of one renderer or camera:

1. a local *linear* background through two flank windows outside the stripe (removes murk gradients and the
   smooth backscatter glow beside the stripe);
2. a start value and the width from the three-point log-parabola (a Gaussian fit through the peak and its
   neighbours at a spacing matched to the width);
3. unsaturated profiles: a Gaussian-weighted centroid matched to the width, iterated with the Newton step of a
   Gaussian profile (``c <- c + 2 (m - c)``); its fixed point is the centre of symmetry and its noise is close
   to the Cramer-Rao bound of a Gaussian fit. Saturated (flat-topped) profiles: from the middle of the clipped
   samples, the plain background-subtracted centroid in a window symmetric about the current estimate (the
   clipped plateau carries no noise; the log-parabola sees no curvature on it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]

FWHM_PER_SIGMA = float(2.0 * np.sqrt(2.0 * np.log(2.0)))
#: Half-level width (px) above which a profile is treated as wide / flat-topped (a Gaussian of sigma 2 px).
WIDE_FWHM_PX = 2.0 * FWHM_PER_SIGMA
#: Half-width (rows) of the box smoothing of a profile before its flat-top test (as in the compiled kernel).
FLAT_SMOOTH = 2


@dataclass(frozen=True)
class ProfileFit:
    """Results of :func:`fit_profiles` for N profiles (all arrays (N,)).

    Attributes:
        centre: sub-pixel centre in window coordinates (index 0 = first sample), NaN when rejected.
        amplitude: peak height above the local background, DN.
        sigma: Gaussian-equivalent width (sigma) of the profile, pixels (saturated: of the clipped profile).
        background: local background level at the centre, DN.
        saturated: the peak is clipped (flat-topped).
        ok: the profile passed the checks (a peak, width within limits, centre inside the window).
        noise: local noise (DN): spread of the flank samples about the linear background.
    """

    centre: FloatArray
    amplitude: FloatArray
    sigma: FloatArray
    background: FloatArray
    saturated: NDArray[np.bool_]
    ok: NDArray[np.bool_]
    noise: FloatArray


def _level_width(A: F32, level: F32) -> F32:
    """Width of each profile of A (M, N) at ``level`` (N,): distance of the first crossings below it left and
    right of the middle sample (linear interpolation); inf where one is missing."""
    m, n = A.shape
    R = m // 2
    cols = np.arange(n)
    idx = np.arange(m)[:, None]
    below = level[None, :] > A
    qa = np.where(below & (idx < R), idx, -1).max(axis=0)
    qb = np.where(below & (idx > R), idx, m).min(axis=0)
    qa_c, qb_c = np.clip(qa, 0, m - 2), np.clip(qb, 1, m - 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        xa = qa_c + (level - A[qa_c, cols]) / (A[qa_c + 1, cols] - A[qa_c, cols])
        xb = qb_c - (level - A[qb_c, cols]) / (A[qb_c - 1, cols] - A[qb_c, cols])
    return np.where((qa >= 0) & (qb < m), xb - xa, np.inf).astype(np.float32)


def _flank_line(P: NDArray[np.float32], R: int, off: NDArray[np.int64], flank_px: int) -> tuple[Any, Any, Any]:
    """Background line of profiles ``P`` (M, N) through the means of their two flank windows
    ``R -+ (off .. off + flank_px - 1)`` (``off`` (N,)): ``(bl, slope, xl)`` (N,) each, the line being
    ``bl + slope (q - xl)``."""
    cols = np.arange(P.shape[1])
    bl = np.zeros(P.shape[1], np.float32)
    br = np.zeros(P.shape[1], np.float32)
    for k in range(flank_px):
        bl += P[R - off - k, cols]
        br += P[R + off + k, cols]
    bl /= flank_px
    br /= flank_px
    xl = (R - off - 0.5 * (flank_px - 1)).astype(np.float32)
    return bl, (br - bl) / (2.0 * off + flank_px - 1).astype(np.float32), xl


def fit_profiles(
    profiles: NDArray[np.floating] | NDArray[np.integer],
    *,
    sigma_hint: float = 1.0,
    saturation_dn: float = 250.0,
    min_sigma_px: float = 0.45,
    max_sigma_px: float = 5.0,
    flank_px: int = 3,
    iterations: int = 2,
    transposed: bool = False,
    max_fwhm_px: float | NDArray[np.floating] | None = None,
    wide_fwhm_px: float = WIDE_FWHM_PX,
) -> ProfileFit:
    """Sub-pixel centres of N stripe profiles (N, M) whose integer peak is the middle sample ``M // 2``.

    Args:
        profiles: (N, M) intensities (DN), M odd; the stripe's integer peak is at index ``M // 2``.
        sigma_hint: typical stripe sigma (pixels): sets the log-parabola spacing and the flank positions.
        saturation_dn: samples at or above this value count as clipped.
        min_sigma_px, max_sigma_px: accepted width (narrower: speckle or a hot pixel; wider: glow, haze, a blob).
        flank_px: samples per flank window of the background estimate.
        iterations: centroid iterations.
        transposed: ``profiles`` is given as (M, N) (one profile per column), the faster layout.
        max_fwhm_px: widest accepted half-level width of a *wide* profile, pixels, scalar or (N,) (the physical
            limit at each profile's row); default ``FWHM_PER_SIGMA * max_sigma_px``.
        wide_fwhm_px: flat-topped profiles (wider at half level than the log-parabola's curvature says) with a
            larger half-level width (thick sheets close to the wall) take the
            symmetric-window centroid from the midpoint of their half-level crossings, with the background flanks
            moved beyond them (the log-parabola sees no curvature on a flat top).

    Returns:
        :class:`ProfileFit`; ``centre`` is in sample units of the window (add the window's first row).
    """
    P = np.asarray(profiles, dtype=np.float32)
    P = P if transposed else np.ascontiguousarray(P.T)  # (M, N): reductions over axis 0
    m, n = P.shape
    R = m // 2
    cols = np.arange(n)
    x = np.arange(m, dtype=np.float32)[:, None]
    sat = np.float32(saturation_dn) <= P
    n_sat = sat.sum(axis=0)
    saturated = sat[R] & (n_sat >= 2)
    # 1. linear background through two flank windows at +-off (beyond the stripe and its plateau; a single clipped
    # sample is a peak just reaching the top of the range, not a plateau)
    n_run = np.where(n_sat >= 2, n_sat, 0)
    off = np.minimum(np.ceil(3.0 * sigma_hint + 0.5 * n_run + 1.0), R - flank_px + 1).astype(np.int64)
    bl, slope, xl = _flank_line(P, R, off, flank_px)
    ss = np.zeros(n, np.float32)
    for k in range(flank_px):
        ss += (P[R - off - k, cols] - bl - slope * (R - off - k - xl)) ** 2
        ss += (P[R + off + k, cols] - bl - slope * (R + off + k - xl)) ** 2
    local_noise = np.sqrt(ss / max(2 * flank_px - 2, 1)).astype(np.float64)
    A = P - (bl + slope * (x - xl))
    # 2. start value and width: three-point log-parabola at spacing s
    s = max(1, round(0.8 * sigma_hint))
    ym = np.log(np.maximum(A[R - s], 0.5))
    y0 = np.log(np.maximum(A[R], 0.5))
    yp = np.log(np.maximum(A[R + s], 0.5))
    den = ym - 2.0 * y0 + yp
    curved = den < -1e-6
    safe = np.where(curved, den, np.float32(-1.0))
    delta = np.clip(np.where(curved, 0.5 * s * (ym - yp) / safe, 0.0), -1.0, 1.0)
    sigma = np.where(curved, s / np.sqrt(-safe), np.inf)
    # saturated: from the middle of the clipped samples (the log-parabola sees a flat top)
    idx = np.arange(m)[:, None]
    q_first = np.where(sat, idx, m).min(axis=0)
    q_last = np.where(sat, idx, -1).max(axis=0)
    c = np.where(saturated, 0.5 * (q_first + q_last), R + delta).astype(np.float32)
    # half-level width and midpoint: crossings of half the peak level walking out from R
    a0 = A[R]
    below = (0.5 * a0)[None, :] > A
    qa = np.where(below & (idx < R), idx, -1).max(axis=0)
    qb = np.where(below & (idx > R), idx, m).min(axis=0)
    found = (qa >= 0) & (qb < m) & (a0 > 0) & ~saturated
    qa_c, qb_c = np.clip(qa, 0, m - 2), np.clip(qb, 1, m - 1)
    hl = 0.5 * a0
    with np.errstate(divide="ignore", invalid="ignore"):
        xa = qa_c + (hl - A[qa_c, cols]) / (A[qa_c + 1, cols] - A[qa_c, cols])
        xb = qb_c - (hl - A[qb_c, cols]) / (A[qb_c - 1, cols] - A[qb_c, cols])
    fw = np.where(found, xb - xa, np.inf)
    # flat-topped (a thick sheet): steep edges, the widths at 1/4 and 3/4 of the peak differ by at most half the
    # half-level width (a Gaussian: 0.77 of it; glow and haze ridges are smooth like that); measured on the
    # profile box-smoothed over 2 k + 1 rows (plus k of the 2 k it widens steep edges by: wide Gaussians stay
    # Gaussians), so that noise on a plateau cannot bring the 3/4 crossing next to the peak sample
    k = FLAT_SMOOTH
    As = np.copy(A)
    for o in range(1, k + 1):
        As[o:] += A[:-o]
        As[:-o] += A[o:]
    As /= 2 * k + 1
    a0s = np.maximum(As[R], 0.5 * a0)
    with np.errstate(invalid="ignore"):  # inf - inf where a crossing is missing: not flat
        flat = _level_width(As, 0.25 * a0s) - _level_width(As, 0.75 * a0s) <= 0.5 * fw + k
    wide = ~saturated & (a0 > 0) & (fw > wide_fwhm_px) & flat
    # wide profiles: the peak sample may be anywhere on the top; start from the middle of the crossings
    mid = ~saturated & (a0 > 0) & (fw > wide_fwhm_px) & np.isfinite(fw)
    c = np.where(mid, 0.5 * (xa + xb), c).astype(np.float32)
    any_wide = bool(wide.any())
    hs_w = np.zeros(n, np.float32)
    if any_wide:
        lim = FWHM_PER_SIGMA * max_sigma_px if max_fwhm_px is None else max_fwhm_px
        fin = wide & np.isfinite(fw)
        fwf = np.where(fin, fw, 0.0)
        c = np.where(fin, 0.5 * (xa + xb), c).astype(np.float32)
        sigma = np.where(fin, fwf / FWHM_PER_SIGMA, sigma)
        off_w = np.minimum(np.maximum(off, np.ceil(0.5 * fwf + 4.0)), R - flank_px + 1).astype(np.int64)
        off_w = np.where(fin, off_w, off)
        blw, slw, xlw = _flank_line(P, R, off_w, flank_px)
        bl = np.where(fin, blw, bl)
        slope = np.where(fin, slw, slope)
        xl = np.where(fin, xlw, xl)
        A = P - (bl + slope * (x - xl))
        hs_w = (np.minimum(0.5 * fwf + 3.0, off_w - 1.0) + 0.5).astype(np.float32)
    amp = A[R]
    # saturated: plateau half-width from the clipped run; the edges add the stripe's own width
    half_sat = 0.5 * n_sat + 2.5 * sigma_hint + 0.5
    sigma = np.where(saturated, np.maximum(0.5 * n_sat / 1.1774, sigma_hint), sigma)
    ok = saturated | (curved & (sigma >= min_sigma_px) & (sigma <= max_sigma_px))
    if any_wide:
        ok = np.where(wide, fw <= lim, ok)
    sig_p = np.clip(np.where(np.isfinite(sigma), sigma, sigma_hint), min_sigma_px, max_sigma_px).astype(np.float32)
    # weights at least 1.1 px wide: narrower Gaussian weights alias on the pixel grid (biased first moment)
    sig_w = np.maximum(sig_p, np.float32(1.1))
    inv2 = 0.5 / (sig_w * sig_w)
    # Newton gain of a Gaussian profile (sigma_p) under Gaussian weights (sigma_w): 1 + sigma_p^2 / sigma_w^2
    gain = np.where(saturated | wide, np.float32(1.0), 1.0 + (sig_p * sig_p) * (2.0 * inv2)).astype(np.float32)
    hs = (half_sat + 0.5).astype(np.float32)
    any_sat = bool(saturated.any())
    # 3. centroid iterations
    for _ in range(iterations):
        d = x - c
        w = np.exp(-(d * d) * inv2)
        if any_sat:
            w_s = np.clip(hs - np.abs(d), 0.0, 1.0)
            w = np.where(saturated, w_s, w)
        if any_wide:
            w = np.where(wide, np.clip(hs_w - np.abs(d), 0.0, 1.0), w)
        wa = w * A
        s0 = wa.sum(axis=0)
        s1 = (wa * d).sum(axis=0)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = gain * s1 / s0
        step = np.where(np.isfinite(step), np.clip(step, -1.0, 1.0), np.float32(0.0))
        c = c + step
    c64 = c.astype(np.float64)
    amp = np.where(saturated, P[R] - (bl + slope * (R - xl)), amp).astype(np.float64)
    lim_c = np.where(mid, 0.5 * np.where(mid, fw, 0.0) + 1.0, np.where(saturated, 0.5 * n_sat + 1.0, 2.0))
    ok &= np.isfinite(c64) & (np.abs(c64 - R) <= lim_c) & (amp > 0)
    background = (bl + slope * (c - xl)).astype(np.float64)
    return ProfileFit(np.where(ok, c64, np.nan), amp, sigma.astype(np.float64), background, saturated, ok, local_noise)
