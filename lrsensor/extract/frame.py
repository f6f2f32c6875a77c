"""The compiled road: seven calls that extract (and triangulate) the stripes of one frame.

:func:`extract_frame` is the default extractor of :mod:`lrsensor.extract.subpixel`, whole, in seven compiled calls
(six on a clear frame):

- :func:`locate_candidates`:

  1. detection per laser in its band (:func:`.detect.detect_band`), the candidates of all lasers numbered as
     one row of virtual columns ``laser * width_d + column_d``;
  2. continuity (:func:`.chains.select_candidates`, :func:`.chains.expand_half`): one candidate per column;

- :func:`.geometry.max_fwhm_at`: the width limit of every point (the laser sheet's thickness at its depth; the
  points' triangulation and the widths, two calls);

- :func:`fit_points`:

  3. frame statistics (:func:`frame_profile_stats`: the typical sigma and clipped run, hence the fit window) and
     the sub-pixel fit of every point, one column-parallel fit for every kind of profile (:mod:`.fit`), then the
     neighbour refits where two lasers' stripes come close (:mod:`.refit`);

- :func:`refine_points` (:func:`glow_starts` and :func:`.glow.glow_refit`, two calls):

  4. the joint stripe-and-glow fits where a profile shows the laser sheet's glow (turbid water, :mod:`.glow`);

- :func:`finish_located`:

  5. gates, runs, smoothing and quality (:mod:`.finish`; through a port the smoothing's line fits run where a
     pinhole in the water at the camera centre would see the stripe's points);

- :func:`pool_ends` (where the glow stage ran):

  6. on the stripes the glow stage fitted, their dim ends beyond the long runs measured pooled along the stripe
     (:mod:`.pooled`);

- :func:`.geometry.triangulate_geo` and :func:`place_points`:

  7. with ``triangulate``: the body-frame points (:mod:`.geometry`; through the calibration's port when it has
     one) and the range-limit gate on camera depth.

Inputs: the image (H, W, 3) uint8 BGR, C-contiguous, and the settings records built once per (calibration,
configuration) in :mod:`lrsensor.extract.subpixel`. Outputs: pixel coordinates (M, 2), laser (M,), quality (M,),
body-frame points (M, 3) in metres (empty without ``triangulate``) and the band noise (L,) in DN.

Why these calls and not one, nor one per stage: numba compiles a kernel's callees first and then optimises and
generates machine code again for the caller's whole call tree, so a single frame call would compile every
stage again; the calls compile side by side in two processes (:mod:`lrsensor.extract.compile`: the
triangulation, which the width limits and the points both need, is a call of its own, compiled once, and so is
the glow stage, the largest call tree, which a kernel around it would compile again), and
their hand-overs
(:class:`Picked`, :class:`Located`, the points) cost microseconds in a frame of about a millisecond, where a
Python call per stage would cost as much again. The numpy reference
(:mod:`lrsensor.extract.reference`) implements the same algorithm readably for tests and for machines without
numba.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ._jit import arange, empty, full, inline, njit, zeros
from .chains import expand_half, select_candidates, sorted_blocks
from .columns import take
from .detect import detect_band
from .finish import BLURRED_SIGMA_PX, finish_points
from .fit import FLANK_PX, Fits, fit_columns, flank_offset
from .geometry import max_fwhm_at, triangulate_geo
from .glow import glow_refit, new_water
from .pooled import extend_ends, glowing_widths, shaped_growth
from .refit import NEIGHBOUR_REFITS, point_table, refit_columns, refit_targets, rows_overlap
from .settings import Bands, Geometry, Settings
from .sorting import kth, median

#: Sigma of a Gaussian per full width at half maximum.
FWHM_PER_SIGMA = 2.3548200450309493
#: Profiles sampled for the frame statistics (:func:`frame_profile_stats`).
STATS_POINTS = 48
#: The points whose profile the common fit refused (no curved three-point start, a width outside the limits, the
#: centre away from the peak: noise at a dim column of a blurred stripe) enter the glow stage at their candidate row
#: with the frame's typical width, and are kept where their joint fit is taken (docs/water-design.md); on blurred frames
#: only (the typical sigma at least :data:`~lrsensor.extract.finish.BLURRED_SIGMA_PX`: forward scatter), where the
#: start's three samples 0.8 sigma apart read the noise of a dim column. Clear water's few refusals (0-8 a frame on
#: the named scenes) are left as they were, and its frames keep their cost.
RETRY_REFUSED = True
#: A glowing stripe's dim ends beyond its long runs are measured pooled along it (:mod:`.pooled`; docs/water-design.md).
POOLED_ENDS = True


class Located(NamedTuple):
    """What :func:`fit_points` hands to :func:`refine_points` and :func:`finish_located`: the frame's ``N`` picked
    candidates (one per laser and column, sorted by virtual column) and their fits so far. Every array is
    C-contiguous and freshly allocated (the calls after it are compiled once, for exactly these types)."""

    #: (N,) int64 virtual columns ``laser * W + column``, the laser and the image column of each point.
    col_v: NDArray[np.int64]
    laser: NDArray[np.int64]
    cols: NDArray[np.int64]
    #: (N,) int64 the candidate row of each point; its chain and the chain's length (:mod:`.chains`).
    rows: NDArray[np.int64]
    chain: NDArray[np.int64]
    chain_len: NDArray[np.int64]
    #: The fits of the points (:func:`.fit.fit_columns`).
    fits: Fits
    #: (N,) the widest profile the laser sheet allows at each point, px (:func:`.geometry.max_fwhm_at`).
    max_fwhm: NDArray[np.float64]
    #: Half-length of the fit window, px, and the frame's typical Gaussian sigma, px (:func:`frame_profile_stats`).
    half: int
    sigma_px: float
    #: (L,) the band noise of each laser, DN.
    noise: NDArray[np.float64]


class Picked(NamedTuple):
    """What :func:`locate_candidates` hands on: the frame's ``N`` picked candidates, one per laser and column,
    sorted by virtual column (C-contiguous, freshly allocated: the calls after it are compiled for these types)."""

    #: (N,) int64 virtual columns ``laser * W + column``, the laser and the image column of each point.
    col_v: NDArray[np.int64]
    laser: NDArray[np.int64]
    cols: NDArray[np.int64]
    #: (N,) int64 the candidate row of each point; its chain and the chain's length (:mod:`.chains`).
    rows: NDArray[np.int64]
    chain: NDArray[np.int64]
    chain_len: NDArray[np.int64]
    #: (L,) the band noise of each laser, DN.
    noise: NDArray[np.float64]
    #: (N,) int64: 1 where the point's candidate is the detection's second pass's (on the glow's rising side, turbid
    #: water), else 0.
    second: NDArray[np.int64]


@njit
def frame_profile_stats(image, cols, rows, half, sat_dn, max_sigma, max_fwhm):  # type: ignore[no-untyped-def]
    """The frame statistics (the reference computes them in ``reference.extract_frame``): from the green
    profiles ``rows +- half`` of a few picked columns, the median Gaussian-equivalent sigma of the unsaturated ones (see
    ``reference_fit._typical_sigma``; at most ``max_sigma`` or the median wide limit), the 90th percentile of their
    clipped-sample counts, and the median of ``max_fwhm`` (M,) at those columns.

    Returns:
        ``(sigma_px, plateau_px, wide_limit_px)``.
    """
    h = image.shape[0]
    n = cols.size
    m = 2 * half + 1
    R = m // 2
    q = max(2, m // 4)
    X = empty(m, np.float64)
    widths = empty(n, np.float64)
    n_sat = empty(n, np.float64)
    nw = 0
    for t in range(n):
        ns = 0
        for k in range(m):
            rr = min(max(rows[t] - half + k, 0), h - 1)
            X[k] = image[rr, cols[t], 1]
            if X[k] >= sat_dn:
                ns += 1
        n_sat[t] = ns
        b1 = 0.0
        b2 = 0.0
        for k in range(q):
            b1 += X[k]
            b2 += X[m - q + k]
        bg = min(b1, b2) / q
        pk = -1.0
        p = R - 3
        for k in range(R - 3, R + 4):
            if X[k] > pk:
                pk = X[k]
                p = k
        half_level = 0.5 * (pk + bg)
        left = -1
        for k in range(p - 1, -1, -1):
            if X[k] < half_level:
                left = k
                break
        right = m
        for k in range(p + 1, m):
            if X[k] < half_level:
                right = k
                break
        if left < 0 or right >= m or not (pk < sat_dn) or not (pk - bg > 5.0):
            continue
        xl = left + (half_level - X[left]) / max(X[left + 1] - X[left], 1e-9)
        xr = right - (half_level - X[right]) / max(X[right - 1] - X[right], 1e-9)
        widths[nw] = xr - xl
        nw += 1
    wide = median(max_fwhm) if max_fwhm.size > 0 else 0.0
    sigma = 1.0
    if nw > 0:
        sg = median(widths[:nw]) / 2.3548200450309493
        if math.isfinite(sg):
            sigma = min(max(sg, 0.6), max(max_sigma, wide / 2.3548200450309493))
    plateau = kth(n_sat, int(0.9 * (n - 1))) if n > 0 else 0.0
    return sigma, plateau, wide


@inline
def no_points(noise, half):  # type: ignore[no-untyped-def]
    """The :class:`Located` of a frame without candidates."""
    e_i = empty(0, np.int64)
    e_f = empty(0, np.float64)
    e_b = empty(0, np.bool_)
    return Located(
        col_v=e_i,
        laser=e_i,
        cols=e_i,
        rows=e_i,
        chain=e_i,
        chain_len=e_i,
        fits=Fits(e_f, e_f, e_f, e_b, e_b, e_f, empty((3, 0), np.float64)),
        max_fwhm=e_f,
        half=half,
        sigma_px=1.0,
        noise=noise,
    )


@inline
def refit_neighbours(image, cols, rows, laser, n_l, good, max_d, half, sig_med, s, max_fwhm, res):  # type: ignore[no-untyped-def]
    """Where two lasers' stripes come close (long range), refit the points of each with the other's Gaussian
    within ``max_d`` rows subtracted, a few rounds (:mod:`.refit`; ``n_l`` lasers); ``res``, the
    :class:`~lrsensor.extract.fit.Fits` of every point, is updated in place, and so is ``good`` (N,), whether
    each point can be a neighbour (accepted, not saturated)."""
    w = image.shape[1]
    n = cols.size
    vv, amp, sig, sat, ok = res.centre, res.amplitude, res.sigma, res.saturated, res.ok
    # the rows the fits read: background flanks (as the fits place them without a clipped sample) and the whole
    # window
    read = (
        float(flank_offset(sig_med, 0, half, FLANK_PX) + FLANK_PX - 1),
        half + 1.0,
        s.wide_fwhm_px / FWHM_PER_SIGMA,
    )
    last = full((3, n), np.nan, np.float64)  # the neighbour each point was last refitted with
    at = point_table(laser, cols, n_l, w)
    look = arange(w, np.int64)  # the columns where a neighbour can have changed: all, then the refits'
    touched = zeros(w, np.bool_)
    for _ in range(NEIGHBOUR_REFITS):
        idx, nb_v, nb_a, nb_s = refit_targets(laser, cols, vv, amp, sig, sat, good, at, max_d, read, look, last)
        if idx.size == 0:
            break
        refit_columns(image, cols, rows, idx, nb_v, nb_a, nb_s, half, sig_med, s, max_fwhm, res)
        n_look = 0
        for i in range(idx.size):
            t = idx[i]
            good[t] = ok[t] and not sat[t]
            if not touched[cols[t]]:
                n_look += 1
                touched[cols[t]] = True
        look = empty(n_look, np.int64)
        k = 0
        for c in range(w):  # (in order: refit_targets keeps the points' order)
            if touched[c]:
                look[k] = c
                k += 1
                touched[c] = False


@inline
def _no_candidates(noise):  # type: ignore[no-untyped-def]
    """The :class:`Picked` of a frame without candidates."""
    e_i = empty(0, np.int64)
    return Picked(col_v=e_i, laser=e_i, cols=e_i, rows=e_i, chain=e_i, chain_len=e_i, noise=noise, second=e_i)


@njit
def locate_candidates(image, bands, s):  # type: ignore[no-untyped-def]
    """Steps 1-2 of :func:`extract_frame` (detection, chains).

    Args:
        image: (H, W, 3) uint8 C-contiguous; bands, s: the :class:`~lrsensor.extract.settings.Bands` and
            :class:`~lrsensor.extract.settings.Settings`.

    Returns:
        :class:`Picked` (none where the frame has no candidates).
    """
    n_l = bands.rows.shape[0]
    w = image.shape[1]
    wd = (w + 1) // 2  # detection at half resolution: column c stands for 2c and 2c + 1
    # 1. detection
    noise = full(n_l, 1.0, np.float64)
    parts_u = []
    parts_v = []
    parts_a = []
    parts_s = []
    total = 0
    for i in range(n_l):
        r0 = bands.rows[i, 0]
        r1 = bands.rows[i, 1]
        if r1 <= r0:
            continue
        u, v, a, noise[i], sec = detect_band(
            image,
            r0,
            r1,
            s.contrast_px,
            s.snr_threshold,
            s.area_noise,
            s.min_response_dn,
            bands.v_lo[i],
            bands.v_hi[i],
            bands.glow_side[i],
            i * wd,
        )
        parts_u.append(u)
        parts_v.append(v)
        parts_a.append(a)
        parts_s.append(sec)
        total += u.size
    U = empty(total, np.int64)
    Vr = empty(total, np.int64)
    Ar = empty(total, np.float64)
    Sr = empty(total, np.int64)
    k = 0
    for j in range(len(parts_u)):
        for t in range(parts_u[j].size):
            U[k] = parts_u[j][t]
            Vr[k] = parts_v[j][t]
            Ar[k] = parts_a[j][t]
            Sr[k] = parts_s[j][t]
            k += 1
    if total == 0:
        return _no_candidates(noise)
    # 2. chains
    max_cand, min_run_cols = s.max_candidates, s.min_run_cols
    n_cols_d = n_l * wd
    jump = s.max_jump_px * 1.5
    min_run = max(2, (min_run_cols + 1) // 2)
    cnt = zeros(n_cols_d, np.int64)
    kk = 0
    for t in range(U.size):
        cnt[U[t]] += 1
        kk = max(kk, cnt[U[t]])
    k = min(max_cand, kk)
    col_d, rows_f, chain, chain_len = select_candidates(U, Vr, Ar, n_cols_d, k, jump, wd, 3, min_run)
    if col_d.size == 0:
        return _no_candidates(noise)
    # whether each pick is the second pass's: the candidate of its column nearest its row (the first of a tie)
    sec_d = zeros(n_cols_d, np.int64)
    start = zeros(n_cols_d + 1, np.int64)
    for c in range(n_cols_d):
        start[c + 1] = start[c] + cnt[c]
    for i in range(col_d.size):
        c = col_d[i]
        best = np.inf
        for j in range(start[c], start[c + 1]):
            dj = abs(Vr[j] - rows_f[i])
            if dj < best:
                best = dj
                sec_d[c] = Sr[j]
    col_v, rows_f, chain, chain_len = expand_half(col_d, rows_f, chain, chain_len, wd, w)
    n = col_v.size
    laser = sorted_blocks(col_v, w)
    rows = empty(n, np.int64)
    cols = empty(n, np.int64)
    second = empty(n, np.int64)
    for t in range(n):
        rows[t] = int(np.rint(rows_f[t]))
        cols[t] = col_v[t] - laser[t] * w
        second[t] = sec_d[laser[t] * wd + cols[t] // 2]
    return Picked(
        col_v=col_v, laser=laser, cols=cols, rows=rows, chain=chain, chain_len=chain_len, noise=noise, second=second
    )


@njit
def fit_points(image, p, mfw, s):  # type: ignore[no-untyped-def]
    """Step 3 of :func:`extract_frame` (frame statistics, the fit of every point, neighbour refits).

    Args:
        image: (H, W, 3) uint8 C-contiguous; p: the :class:`Picked` candidates of :func:`locate_candidates`;
            mfw: (N,) their width limits (:func:`.geometry.max_fwhm_at`), px; s: the
            :class:`~lrsensor.extract.settings.Settings`.

    Returns:
        :class:`Located` (no points where the frame has no candidates).
    """
    n_l = p.noise.size
    n = p.cols.size
    half0, sat_dn, max_sigma = s.window_half_px, s.saturation_dn, s.max_sigma_px
    if n == 0:
        return no_points(p.noise, half0)
    col_v, laser, cols, rows, chain, chain_len, noise = p.col_v, p.laser, p.cols, p.rows, p.chain, p.chain_len, p.noise
    # frame statistics (window length), then the fit of every point; the statistics from the first detection pass's
    # points where it has STATS_POINTS of them: the second pass's lie on the glow's rising side, whose step widens
    # their profiles' half-maximum width, and with it every fit's window and the glow stage's fits
    # (docs/water-design.md, "Detection on the glow")
    pool = empty(n, np.int64)
    n_pool = 0
    for t in range(n):
        if p.second[t] == 0:
            pool[n_pool] = t
            n_pool += 1
    if n_pool < STATS_POINTS:
        for t in range(n):
            pool[t] = t
        n_pool = n
    m_sub = min(n_pool, STATS_POINTS)
    sub = empty(m_sub, np.int64)
    if m_sub == 1:
        sub[0] = pool[0]
    else:
        step = (n_pool - 1) / (m_sub - 1)
        for i in range(m_sub):
            sub[i] = pool[int(i * step)]
        sub[m_sub - 1] = pool[n_pool - 1]
    sig_med, plateau, wide_lim = frame_profile_stats(
        image, take(cols, sub), take(rows, sub), half0, sat_dn, max_sigma, take(mfw, sub)
    )
    half = int(min(max(half0, math.ceil(wide_lim) + 4), math.ceil(3.0 * sig_med + 0.5 * plateau + 4)))
    nan = full(n, np.nan, np.float64)
    fits = fit_columns(image, cols, rows, half, sig_med, s, nan, nan, nan, mfw)
    if n_l > 1:  # stripes of two lasers close together (long range): refit each with the other subtracted
        max_d = half + 3.0 * sig_med + 2.0
        good = empty(n, np.bool_)  # the points that can be a neighbour
        for t in range(n):
            good[t] = fits.ok[t] and not fits.saturated[t]
        if rows_overlap(laser, fits.centre, good, n_l, max_d):  # else the common case: stripes far apart
            refit_neighbours(image, cols, rows, laser, n_l, good, max_d, half, sig_med, s, mfw, fits)
    return Located(
        col_v=col_v,
        laser=laser,
        cols=cols,
        rows=rows,
        chain=chain,
        chain_len=chain_len,
        fits=fits,
        max_fwhm=mfw,
        half=half,
        sigma_px=sig_med,
        noise=noise,
    )


@njit
def glow_starts(p):  # type: ignore[no-untyped-def]
    """The starts of step 4 of :func:`extract_frame` (:func:`lrsensor.extract.glow.glow_refit`, a call of its own) for
    the :class:`Located` points ``p``: the points the common fit refused enter at their candidate row with the frame's
    width (see :data:`RETRY_REFUSED`).

    Returns:
        ``(centre_row, sigma, ok, retry)``: (N,) each, the fits' own arrays where no point is retried (clear water
        refuses few or none: no copies), and the points retried.
    """
    n = p.cols.size
    res = p.fits
    vv, sig, sat, ok = res.centre, res.sigma, res.saturated, res.ok
    retry = zeros(n, np.bool_)
    n_retry = 0
    if RETRY_REFUSED and p.sigma_px >= BLURRED_SIGMA_PX:
        for t in range(n):
            retry[t] = not ok[t] and not sat[t]
            n_retry += retry[t]
    if n_retry == 0:
        return vv, sig, ok, retry
    v_in = vv.copy()
    s_in = sig.copy()
    ok_in = ok.copy()
    for t in range(n):
        if retry[t]:
            v_in[t] = float(p.rows[t])
            s_in[t] = p.sigma_px
            ok_in[t] = True
    return v_in, s_in, ok_in, retry


@njit
def finish_located(p, glow, w, s, geo):  # type: ignore[no-untyped-def]
    """The end of step 4 of :func:`extract_frame` and step 5 (gates, smoothing, quality) of the :class:`Located`
    points ``p`` of an image ``w`` px wide.

    Args:
        glow: :func:`lrsensor.extract.glow.glow_refit`'s ``(centre_row, sigma, fitted, amplitude, noise)`` (N,) each
            and the points it retried (N,) (:func:`glow_starts`); where it did not run (``s.glow_fit`` False), the
            fits' own centres, sigmas, amplitudes and noise, nothing fitted and nothing retried.

    Returns:
        ``(u, v, laser, quality)``: (M,) each, the points' pixel columns and rows, laser and quality in [0, 1].
    """
    n = p.cols.size
    if n == 0:
        return empty(0, np.float64), empty(0, np.float64), empty(0, np.int64), empty(0, np.float64)
    res = p.fits
    vv, amp, sig, ok = res.centre, res.amplitude, res.sigma, res.ok
    v_g, s_g, own, a_g, n_g, retry = glow
    # the gate takes the joint fit's own amplitude and residual noise where it is taken (the common fit's line
    # takes part of the glow's step as a slope)
    for t in range(n):
        vv[t] = v_g[t]
        amp[t] = a_g[t]
        res.local_noise[t] = n_g[t]
    for t in range(n):  # a refused point only where its joint fit is taken
        if retry[t] and own[t]:
            ok[t] = True
            sig[t] = s_g[t]
        elif retry[t]:  # (the glow stage hands back its start, the candidate row)
            vv[t] = np.nan
    # gates, runs, smoothing, quality
    return finish_points(p.col_v, p.laser, res, p.chain, p.chain_len, p.noise, w, s, geo, own)


def refine_points(
    image: NDArray[np.uint8], p: Located, glow_side: IntArray, s: Settings, geo: Geometry, water: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], FloatArray, FloatArray, NDArray[np.bool_]]:
    """Step 4 of :func:`extract_frame`: the joint stripe-and-glow fits of the :class:`Located` points ``p``
    (:func:`lrsensor.extract.glow.glow_refit`, from :func:`glow_starts`; ``water`` read and updated), for
    :func:`finish_located`. A Python call of the kernel, not a kernel: a kernel that called it would compile its
    whole call tree again into its own machine code (:mod:`lrsensor.extract.compile`)."""
    res = p.fits
    if not s.glow_fit:  # (nothing fitted, nothing retried)
        n = p.cols.size
        return res.centre, res.sigma, np.zeros(n, np.bool_), res.amplitude, res.local_noise, np.zeros(n, np.bool_)
    if RETRY_REFUSED and p.sigma_px >= BLURRED_SIGMA_PX:
        v_in, s_in, ok_in, retry = glow_starts(p)
    else:  # (a sharp frame retries none: no call)
        v_in, s_in, ok_in, retry = res.centre, res.sigma, res.ok, np.zeros(p.cols.size, np.bool_)
    v_g, s_g, own, a_g, n_g = glow_refit(
        image, p.cols, p.laser, glow_side, v_in, res.amplitude, s_in, res.saturated, ok_in, res.local_noise, p.noise,
        s.min_fwhm_px / FWHM_PER_SIGMA, s.max_sigma_px, s.saturation_dn, s.min_green_ratio, geo.glow_vanish,
        geo.glow_path, water, retry,
    )  # fmt: skip
    return v_g, s_g, own, a_g, n_g, retry


@njit
def pool_ends(image, u, v, laser, quality, glow_side, p_laser, own, sigma, vanish, path, water):  # type: ignore[no-untyped-def]
    """Step 6 of :func:`extract_frame`: the points ``(u, v, laser, quality)`` (M,) of :func:`finish_located` with
    the dim ends of the stripes the glow stage fitted measured pooled along them (:mod:`.pooled`); ``own`` (N,) the
    :class:`Located` points (laser ``p_laser`` (N,)) whose joint fit was taken, ``sigma`` (N,) their widths, px;
    ``vanish``, ``path`` (L, W) the glow's geometry and ``water`` the glow stage's record
    (:func:`.pooled.shaped_growth`).
    A call of its own: :func:`finish_located` does not link the pooled fits' tree, and a frame where the glow stage
    took no fit (clear water) does not call it.

    Returns:
        ``(u, v, laser, quality)`` (K,) each, as :func:`.pooled.extend_ends`.
    """
    use, sig_l = glowing_widths(p_laser, own, sigma, glow_side.shape[0])
    return extend_ends(image, u, v, laser, quality, glow_side, use, sig_l, vanish, shaped_growth(water, path))


@njit
def place_points(u, v, laser, quality, xyz, s, geo, triangulate):  # type: ignore[no-untyped-def]
    """Step 7 of :func:`extract_frame`: with ``triangulate`` the range-limit gate on the camera depth of the
    body-frame points ``xyz`` (M, 3) (:func:`.geometry.triangulate_geo` of the pixels ``(u, v)`` (M,) of ``laser``
    (M,); NaN points dropped), else the pixels as they are (``xyz`` unused).

    Returns:
        ``(uv, laser, quality, xyz)``: the kept points' pixel coordinates (K, 2), laser (K,), quality (K,) and
        body-frame points (K, 3), metres ((0, 3) without ``triangulate``).
    """
    m = u.size
    if not triangulate:
        uv = empty((m, 2), np.float64)
        for t in range(m):
            uv[t, 0] = u[t]
            uv[t, 1] = v[t]
        return uv, laser, quality, empty((0, 3), np.float64)
    r_z = geo.R_cam_body[2]
    keep = empty(m, np.bool_)
    kept = 0
    for t in range(m):
        depth = xyz[t, 0] * r_z[0] + xyz[t, 1] * r_z[1] + xyz[t, 2] * r_z[2] + geo.cam_z_offset_m
        keep[t] = depth >= s.min_range_m and depth <= s.max_range_m  # NaN fails both
        kept += keep[t]
    uv = empty((kept, 2), np.float64)
    if kept == m:
        for t in range(m):
            uv[t, 0] = u[t]
            uv[t, 1] = v[t]
        return uv, laser, quality, xyz
    xyz_k = empty((kept, 3), np.float64)
    laser_k = empty(kept, np.int64)
    quality_k = empty(kept, np.float64)
    j = 0
    for t in range(m):
        if keep[t]:
            uv[j, 0] = u[t]
            uv[j, 1] = v[t]
            for a in range(3):
                xyz_k[j, a] = xyz[t, a]
            laser_k[j] = laser[t]
            quality_k[j] = quality[t]
            j += 1
    return uv, laser_k, quality_k, xyz_k


FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
#: The points :func:`place_points` gets without ``triangulate`` (not read).
_NO_XYZ = empty((0, 3), np.float64)


def extract_frame(
    image: NDArray[np.uint8],
    bands: Bands,
    s: Settings,
    geo: Geometry,
    triangulate: bool,
    water: FloatArray | None = None,
) -> tuple[FloatArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """The whole default extractor on one frame in six compiled calls (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR, C-contiguous.
        bands: :class:`~lrsensor.extract.settings.Bands`; s: :class:`~lrsensor.extract.settings.Settings`;
            geo: :class:`~lrsensor.extract.settings.Geometry`.
        triangulate: also triangulate the points and keep only those whose camera depth is within
            ``[s.min_range_m, s.max_range_m]`` (NaN points dropped); else no points and no depth gate.
        water: the turbid water's attenuation and width as a camera's earlier frames told them, read and updated
            (:func:`lrsensor.extract.glow.glow_refit`; None: told on this frame alone).

    Returns:
        ``(uv, laser, quality, xyz, noise)``: the kept points' pixel coordinates (M, 2), laser (M,), quality (M,)
        and body-frame points (M, 3), metres ((0, 3) without ``triangulate``), and the band noise (L,), DN.
    """
    picked = locate_candidates(image, bands, s)
    # the width limit of every point (the refits need any of them), compiled beside the triangulation
    mfw = max_fwhm_at(picked.cols, picked.rows, picked.laser, FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo)
    located = fit_points(image, picked, mfw, s)
    w_rec = new_water() if water is None else water
    glow = refine_points(image, located, bands.glow_side, s, geo, w_rec)
    u, v, laser, quality = finish_located(located, glow, image.shape[1], s, geo)
    if POOLED_ENDS and glow[2].any():  # 6. a glowing stripe's dim ends, measured pooled along it (clear water: none)
        u, v, laser, quality = pool_ends(
            image, u, v, laser, quality, bands.glow_side, located.laser, glow[2], glow[1], geo.glow_vanish,
            geo.glow_path, w_rec,
        )  # fmt: skip
    # the points in a call of their own: a kernel that triangulated would compile the triangulation again
    xyz = triangulate_geo(u, v, laser, geo) if triangulate else _NO_XYZ
    uv, laser, quality, xyz = place_points(u, v, laser, quality, xyz, s, geo, triangulate)
    return uv, laser, quality, xyz, located.noise
