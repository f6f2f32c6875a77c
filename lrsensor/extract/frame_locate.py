"""Steps 1-3 of the compiled road (:func:`lrsensor.extract.frame.extract_frame`): from the image to the fitted
points, the first of the compile's two parts (:data:`lrsensor.extract.compile.PARTS`).

- :func:`locate_candidates`: detection per laser in its band (:func:`.detect.detect_band`) and continuity
  (:func:`.chains.select_candidates`, :func:`.chains.expand_half`), one candidate per laser and column, handed on
  as :class:`Picked`;
- :func:`fit_points`: the frame statistics (:func:`frame_profile_stats`: the typical sigma and clipped run, hence
  the fit window), the sub-pixel fit of every point (:func:`.fit.fit_columns`) and the neighbour refits where two
  lasers' stripes come close (:func:`refit_neighbours`, :mod:`.refit`), handed on as :class:`Located`.

:mod:`lrsensor.extract.frame` runs them, then the glow stage, the finish and the points (the second part), and
exports every name defined here. The numpy reference of these steps is :mod:`lrsensor.extract.reference_detect`,
:mod:`lrsensor.extract.reference_chains` and :mod:`lrsensor.extract.reference_fit`.
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
from .fit import FLANK_PX, Fits, fit_columns, flank_offset
from .refit import NEIGHBOUR_REFITS, point_table, refit_columns, refit_targets, rows_overlap
from .sorting import kth, median

#: Sigma of a Gaussian per full width at half maximum.
FWHM_PER_SIGMA = 2.3548200450309493
#: Profiles sampled for the frame statistics (:func:`frame_profile_stats`).
STATS_POINTS = 48


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
