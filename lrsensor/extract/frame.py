"""The compiled road: one call that extracts (and triangulates) the stripes of one frame.

:func:`extract_frame` is the default extractor of :mod:`lrsensor.extract.subpixel`, whole:

1. detection per laser in its band (:func:`.detect.detect_band`), the candidates of all lasers numbered as one
   row of virtual columns ``laser * width_d + column_d``;
2. continuity (:func:`.chains.select_candidates`, :func:`.chains.expand_half`): one candidate per column;
3. frame statistics (:func:`frame_profile_stats`: the typical sigma and clipped run, hence the fit window) and
   the sub-pixel fits, column-parallel by kind of profile (:mod:`.fit_common`, :mod:`.fit_clipped`), the rest by
   the full kernel (:mod:`.fit`);
4. neighbour refits where two lasers' stripes come close (:mod:`.refit`), then the joint stripe-and-glow fits
   where a profile shows the laser sheet's glow (turbid water, :mod:`.glow`);
5. gates, runs, smoothing and quality (:mod:`.finish`; through a port the smoothing's line fits run where a
   pinhole in the water at the camera centre would see the stripe's points);
6. with ``triangulate``: the body-frame points (:mod:`.geometry`; through the calibration's port when it has one)
   and the range-limit gate on camera depth.

Inputs: the image (H, W, 3) uint8 BGR, C-contiguous, and the settings records built once per (calibration,
configuration) in :mod:`lrsensor.extract.subpixel`. Outputs: pixel coordinates (M, 2), laser (M,), quality (M,),
body-frame points (M, 3) in metres (empty without ``triangulate``) and the band noise (L,) in DN.

Why one call: a frame takes about half a millisecond; passing arrays between Python and the kernels stage by
stage would cost as much again. The numpy reference (:mod:`lrsensor.extract.reference`) implements the same
algorithm readably for tests and for machines without numba.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import njit, stage
from .chains import expand_half, select_candidates, sorted_blocks
from .columns import put_fit
from .detect import detect_band
from .finish import finish_points
from .fit import flank_offset
from .fit_clipped import core_peaks, fit_columns_clipped
from .fit_common import fit_columns_common
from .geometry import max_fwhm_at, triangulate_geo
from .glow import glow_refit
from .refit import NEIGHBOUR_REFITS, point_table, refit_columns, refit_full, refit_targets, rows_overlap


@njit
def frame_profile_stats(image, cols, rows, half, sat_dn, max_sigma, max_fwhm):  # type: ignore[no-untyped-def]
    """The frame statistics (the reference computes them in ``reference.extract_frame``): from the green
    profiles ``rows +- half`` of a few picked columns, the median Gaussian-equivalent sigma of the unsaturated ones (see
    ``reference._typical_sigma``; at most ``max_sigma`` or the median wide limit), the 90th percentile of their
    clipped-sample counts, and the median of ``max_fwhm`` (M,) at those columns.

    Returns:
        ``(sigma_px, plateau_px, wide_limit_px)``.
    """
    h = image.shape[0]
    n = cols.size
    m = 2 * half + 1
    R = m // 2
    q = max(2, m // 4)
    X = np.empty(m)
    widths = np.empty(n)
    n_sat = np.empty(n)
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
    wide = np.median(max_fwhm) if max_fwhm.size > 0 else 0.0
    sigma = 1.0
    if nw > 0:
        sg = np.median(widths[:nw]) / 2.3548200450309493
        if math.isfinite(sg):
            sigma = min(max(sg, 0.6), max(max_sigma, wide / 2.3548200450309493))
    srt = np.sort(n_sat)
    plateau = srt[int(0.9 * (n - 1))] if n > 0 else 0.0
    return sigma, plateau, wide


@stage
def process_candidates(image, U, Vr, Ar, noise_l, s, geo, glow_side):  # type: ignore[no-untyped-def]
    """Steps 2-5 of :func:`extract_frame` (chains, sub-pixel fits, neighbour refits, gates, smoothing, quality).

    Args:
        image: (H, W, 3) uint8 C-contiguous; U, Vr, Ar: the candidates of every laser (detection columns with
            the laser's offset, full rows, strengths), sorted by column then row; noise_l: (L,) band noise, DN.
        s: :class:`~lrsensor.extract.settings.Settings`; geo: :class:`~lrsensor.extract.settings.Geometry`.

    Returns:
        ``(u, v, laser, quality)``: (M,) each, pixel columns and rows, laser index, quality in [0, 1].
    """
    w = image.shape[1]
    n_l = noise_l.size
    max_cand, min_run_cols, half0, iterations = s.max_candidates, s.min_run_cols, s.window_half_px, s.iterations
    sat_dn, min_fwhm, max_sigma, sheet_mm = s.saturation_dn, s.min_fwhm_px, s.max_sigma_px, s.max_sheet_mm
    wide_fwhm = s.wide_fwhm_px
    fwhm_per_sigma = 2.3548200450309493
    wide_sigma = wide_fwhm / fwhm_per_sigma  # profiles wider than this are flat-topped (wide)
    wd = (w + 1) // 2  # detection at half resolution: column c stands for 2c and 2c + 1
    n_cols_d = n_l * wd
    jump = s.max_jump_px * 1.5
    min_run = max(2, (min_run_cols + 1) // 2)
    e_u = np.empty(0)
    e_i = np.empty(0, np.int64)
    if U.size == 0:
        return e_u, e_u, e_i, e_u
    # 3. chains
    cnt = np.zeros(n_cols_d, np.int64)
    kk = 0
    for t in range(U.size):
        cnt[U[t]] += 1
        kk = max(kk, cnt[U[t]])
    k = min(max_cand, kk)
    col_d, rows_f, chain, chain_len = select_candidates(U, Vr, Ar, n_cols_d, k, jump, wd, 3, min_run)
    if col_d.size == 0:
        return e_u, e_u, e_i, e_u
    col_v, rows_f, chain, chain_len = expand_half(col_d, rows_f, chain, chain_len, wd, w)
    n = col_v.size
    rows = np.empty(n, np.int64)
    laser = sorted_blocks(col_v, w)
    cols = np.empty(n, np.int64)
    for t in range(n):
        rows[t] = int(np.rint(rows_f[t]))
        cols[t] = col_v[t] - laser[t] * w
    # 3. frame statistics (window length), common fits, full fits of the special columns
    floor = fwhm_per_sigma * max_sigma
    mfw = np.full(n, np.nan)
    m_sub = min(n, 48)
    sub = np.empty(m_sub, np.int64)
    if m_sub == 1:
        sub[0] = 0
    else:
        step = (n - 1) / (m_sub - 1)
        for i in range(m_sub):
            sub[i] = int(i * step)
        sub[m_sub - 1] = n - 1
    mf = max_fwhm_at(cols[sub], rows[sub], laser[sub], floor, sheet_mm, geo)
    for i in range(m_sub):
        mfw[sub[i]] = mf[i]
    sig_med, plateau, wide_lim = frame_profile_stats(image, cols[sub], rows[sub], half0, sat_dn, max_sigma, mf)
    half = int(min(max(half0, math.ceil(wide_lim) + 4), math.ceil(3.0 * sig_med + 0.5 * plateau + 4)))
    min_sig = min_fwhm / fwhm_per_sigma
    # each column's integer peak among the 2 e + 1 rows around its candidate; those with a clipped sample there
    # are special (the common fit's window holds that sample): where they are many (close to the wall), they skip
    # the common fit
    peaks, clip = core_peaks(image, cols, rows, 3, sat_dn)
    n_clip = 0
    for t in range(n):
        n_clip += clip[t]
    if 4 * n_clip <= n:
        vv, amp, sig, sat, ok, lnoise, rise, special = fit_columns_common(
            image, cols, peaks, half, sig_med, sat_dn, min_sig, max_sigma, 3, iterations, wide_fwhm
        )
        for t in range(n):
            special[t] |= clip[t]
    else:
        vv = np.full(n, np.nan)
        amp = np.zeros(n)
        sig = np.full(n, np.nan)
        sat = np.zeros(n, np.bool_)
        ok = np.zeros(n, np.bool_)
        lnoise = np.zeros(n)
        rise = np.zeros((3, n))
        special = clip.copy()
        keep = np.flatnonzero(~clip)
        if keep.size:
            r_c = fit_columns_common(
                image, cols[keep], peaks[keep], half, sig_med, sat_dn, min_sig, max_sigma, 3, iterations, wide_fwhm
            )
            out = (vv, amp, sig, sat, ok, lnoise, rise)
            for i in range(keep.size):
                put_fit(out, r_c, i, keep[i])
                special[keep[i]] = r_c[7][i]
    # the fit's settings, the width limits and the per-column results that the refits update in place
    fit = (half, sig_med, sat_dn, min_sig, max_sigma, iterations, wide_fwhm)
    limits = (mfw, floor, sheet_mm)
    res = (vv, amp, sig, sat, ok, lnoise, rise)
    n_sp = 0
    for t in range(n):
        n_sp += special[t]
    if n_sp:  # clipped peaks (close to the wall), then the unclipped narrow ones, column-parallel; the rest
        # (flat tops) by the full kernel
        rest = np.flatnonzero(special)
        r_s = fit_columns_clipped(
            image, cols[rest], peaks[rest], half, sig_med, sat_dn, 3, iterations, min_sig, max_sigma, wide_fwhm
        )
        n_rest = 0
        for i in range(rest.size):
            t = rest[i]
            if r_s[7][i]:
                put_fit(res, r_s, i, t)
            else:
                rest[n_rest] = t
                n_rest += 1
        rest = rest[:n_rest]
        if rest.size:
            nan = np.full(rest.size, np.nan)  # flat tops, which only the full kernel fits
            refit_full(image, cols, rows, laser, rest, nan, nan, nan, fit, limits, geo, res)
    # stripes of two lasers close together: refit each with the other's Gaussian subtracted, a few times
    if n_l > 1:
        max_d = half + 3.0 * sig_med + 2.0
        good = np.empty(n, np.bool_)  # the points that can be a neighbour (updated where refitted)
        for t in range(n):
            good[t] = ok[t] and not sat[t]
        if rows_overlap(laser, vv, good, n_l, max_d):  # else the common case: stripes far apart
            # the rows the fits read: background flanks of 3 rows (as the fits take them; no clipped sample) and
            # the whole window
            read = (float(flank_offset(sig_med, 0, half, 3) + 2), half + 1.0, wide_sigma)
            last = np.full((3, n), np.nan)  # the neighbour each point was last refitted with
            at = point_table(laser, cols, n_l, w)
            look = np.arange(w)  # the columns where a neighbour can have changed: all, then the refits'
            touched = np.zeros(w, np.bool_)
            for _ in range(NEIGHBOUR_REFITS):
                idx, nb_v, nb_a, nb_s = refit_targets(laser, cols, vv, amp, sig, sat, good, at, max_d, read, look, last)
                if idx.size == 0:
                    break
                refit_columns(image, cols, rows, laser, idx, nb_v, nb_a, nb_s, fit, limits, geo, res)
                for i in range(idx.size):
                    t = idx[i]
                    good[t] = ok[t] and not sat[t]
                    touched[cols[t]] = True
                look = np.flatnonzero(touched)
                touched[look] = False
    # turbid water: the stripes that show the sheet's glow, fitted jointly with its edge
    if s.glow_fit:
        v_g, _s_g, _f_g = glow_refit(
            image,
            cols,
            laser,
            glow_side,
            vv,
            amp,
            sig,
            sat,
            ok,
            lnoise,
            noise_l,
            min_sig,
            max_sigma,
            sat_dn,
            s.min_green_ratio,
        )
        for t in range(n):
            vv[t] = v_g[t]
    # 5. gates, runs, smoothing, quality
    return finish_points(col_v, laser, res, chain, chain_len, noise_l, w, s, geo)


@njit
def extract_frame(image, bands, s, geo, triangulate):  # type: ignore[no-untyped-def]
    """The whole default extractor on one frame in one compiled call (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR, C-contiguous.
        bands: :class:`~lrsensor.extract.settings.Bands`; s: :class:`~lrsensor.extract.settings.Settings`;
            geo: :class:`~lrsensor.extract.settings.Geometry`.
        triangulate: also triangulate the points and keep only those whose camera depth is within
            ``[s.min_range_m, s.max_range_m]`` (NaN points dropped); else no points and no depth gate.

    Returns:
        ``(uv, laser, quality, xyz, noise)``: the kept points' pixel coordinates (M, 2), laser (M,), quality (M,)
        and body-frame points (M, 3), metres ((0, 3) without ``triangulate``), and the band noise (L,), DN.
    """
    n_l = bands.rows.shape[0]
    w = image.shape[1]
    wd = (w + 1) // 2
    noise = np.ones(n_l)
    parts_u = []
    parts_v = []
    parts_a = []
    total = 0
    for i in range(n_l):
        r0 = bands.rows[i, 0]
        r1 = bands.rows[i, 1]
        if r1 <= r0:
            continue
        u, v, a, noise[i] = detect_band(
            image,
            r0,
            r1,
            s.contrast_px,
            s.snr_threshold,
            s.area_noise,
            s.min_response_dn,
            bands.v_lo[i],
            bands.v_hi[i],
            i * wd,
        )
        parts_u.append(u)
        parts_v.append(v)
        parts_a.append(a)
        total += u.size
    U = np.empty(total, np.int64)
    Vr = np.empty(total, np.int64)
    Ar = np.empty(total)
    k = 0
    for j in range(len(parts_u)):
        m = parts_u[j].size
        U[k : k + m] = parts_u[j]
        Vr[k : k + m] = parts_v[j]
        Ar[k : k + m] = parts_a[j]
        k += m
    u_o, v_o, l_o, q_o = process_candidates(image, U, Vr, Ar, noise, s, geo, bands.glow_side)
    n = u_o.size
    if not triangulate:
        uv = np.empty((n, 2))
        for t in range(n):
            uv[t, 0] = u_o[t]
            uv[t, 1] = v_o[t]
        return uv, l_o, q_o, np.empty((0, 3)), noise
    xyz = triangulate_geo(u_o, v_o, l_o, geo)
    r_z = geo.R_cam_body[2]
    keep = np.empty(n, np.bool_)
    m = 0
    for t in range(n):
        depth = xyz[t, 0] * r_z[0] + xyz[t, 1] * r_z[1] + xyz[t, 2] * r_z[2] + geo.cam_z_offset_m
        keep[t] = depth >= s.min_range_m and depth <= s.max_range_m  # NaN fails both
        m += keep[t]
    uv = np.empty((m, 2))
    if m == n:
        for t in range(n):
            uv[t, 0] = u_o[t]
            uv[t, 1] = v_o[t]
        return uv, l_o, q_o, xyz, noise
    idx = np.flatnonzero(keep)
    for j in range(m):
        uv[j, 0] = u_o[idx[j]]
        uv[j, 1] = v_o[idx[j]]
    return uv, l_o[idx], q_o[idx], xyz[idx], noise
