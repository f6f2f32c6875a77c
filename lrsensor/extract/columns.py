"""Shared pieces of the column-parallel fits: gathering windows, colour rises, clipped runs, results.

The column-parallel fits (:mod:`.fit_common`, :mod:`.fit_clipped`, :mod:`.fit_plain`, :mod:`.refit`) lay their
profiles out as (rows, columns) arrays so that every inner loop runs over columns and vectorizes: a window of
``m = 2 half + 1`` rows of ``n`` columns is (m, n). This module gathers those windows from the image
(:func:`gather_green`), reads the colour rises at the peaks (:func:`colour_rises`, for the colour test pooled along
the stripe in :mod:`.finish`), finds half-level crossings and clipped runs column by column with selects, and
holds the results record of a fit: :func:`fit_results` ``(centre_row, amplitude, sigma, saturated, ok,
local_noise, rise, flag)``, (n,) each and rise (3, n) in B, G, R; rows in pixels, amplitudes and noise in DN.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit


@njit
def gather_green(image, cols, top, out):  # type: ignore[no-untyped-def]
    """Green samples of ``out.shape[0]`` consecutive rows per column into ``out`` (K, N), any dtype: sample ``k``
    of column ``t`` is row ``top[t] + k`` (clamped to the image) of column ``cols[t]``. Where all of them lie in
    the image: one unsigned base index per column and a row stride per sample (no clamping, no wrap-around), four
    rows per pass over the columns (one base load for four samples)."""
    h = image.shape[0]
    wid = image.shape[1]
    flat = image.reshape(-1)
    n = cols.size
    k_rows = out.shape[0]
    inside = True
    for t in range(n):
        inside &= top[t] >= 0 and top[t] + k_rows - 1 <= h - 1
    if not inside:
        for k in range(k_rows):
            for t in range(n):
                rr = min(max(top[t] + k, 0), h - 1)
                out[k, t] = flat[(rr * wid + cols[t]) * 3 + 1]
        return
    stride = np.uint64(wid * 3)
    base = np.empty(n, np.uint64)
    for t in range(n):
        base[t] = np.uint64((top[t] * wid + cols[t]) * 3 + 1)
    k = 0
    while k + 4 <= k_rows:
        o = np.uint64(k) * stride
        b0 = out[k]
        b1 = out[k + 1]
        b2 = out[k + 2]
        b3 = out[k + 3]
        for t in range(n):
            ut = np.uint64(t)
            i0 = base[ut] + o
            b0[ut] = flat[i0]
            b1[ut] = flat[i0 + stride]
            b2[ut] = flat[i0 + stride + stride]
            b3[ut] = flat[i0 + stride + stride + stride]
        k += 4
    while k < k_rows:
        o = np.uint64(k) * stride
        bk = out[k]
        for t in range(n):
            bk[np.uint64(t)] = flat[base[t] + o]
        k += 1


@njit
def colour_rises(image, cols, pk_rows, half, channels, rise):  # type: ignore[no-untyped-def]
    """The rise of the ``channels`` (of 0, 1, 2: blue, green, red) at each column's peak row over the mean of the
    rows ``half`` above and below (clamped to the image): into their rows of ``rise`` (3, N), for the colour test
    pooled along the stripe."""
    h = image.shape[0]
    wid = image.shape[1]
    flat = image.reshape(-1)
    n = cols.size
    inside = True
    for t in range(n):
        inside &= pk_rows[t] - half >= 0 and pk_rows[t] + half <= h - 1
    hstride = np.uint64(half * wid * 3)
    for t in range(n):
        pk_row = pk_rows[t]
        if inside:  # flat unsigned indices, no clamping
            rp = np.uint64((pk_row * wid + cols[t]) * 3)
            rl = rp - hstride
            rh = rp + hstride
        else:
            rp = np.uint64((min(max(pk_row, 0), h - 1) * wid + cols[t]) * 3)
            rl = np.uint64((min(max(pk_row - half, 0), h - 1) * wid + cols[t]) * 3)
            rh = np.uint64((min(max(pk_row + half, 0), h - 1) * wid + cols[t]) * 3)
        for ch in channels:
            uc = np.uint64(ch)
            rise[ch, t] = flat[rp + uc] - 0.5 * (float(flat[rl + uc]) + flat[rh + uc])


@njit
def half_crossings(B, level):  # type: ignore[no-untyped-def]
    """The first crossings below ``level`` (n,) left and right of the middle row of profiles ``B`` (m, n), float32
    or float64, linearly interpolated as :func:`_level_crossings` does column by column (-1 where there is
    none): ``(xa, xb)``, (n,) each of ``B``'s type. The row below the level, its value and its inner neighbour's
    are found by selects, four rows per pass over the columns; then one division per column."""
    m, n = B.shape
    R = m // 2
    xq = np.empty_like(B[0])  # the row found, in B's type (-1: none yet)
    qv = np.empty_like(B[0, :4])  # row numbers in B's type
    va = np.zeros_like(B[0])
    vn = np.zeros_like(B[0])
    xa = np.full_like(B[0], -1.0)
    xb = np.full_like(B[0], -1.0)
    for side in (-1, 1):
        q = R + side
        for t in range(n):
            xq[t] = -1.0
        while 0 <= q < m:
            if (q + 1 if side < 0 else m - q) >= 4:
                r0 = B[q]
                r1 = B[q + side]
                r2 = B[q + 2 * side]
                r3 = B[q + 3 * side]
                rn = B[q - side]
                for j in range(4):
                    qv[j] = q + j * side
                q0 = qv[0]
                q1 = qv[1]
                q2 = qv[2]
                q3 = qv[3]
                for t in range(n):
                    x_ = xq[t]
                    a_ = va[t]
                    n_ = vn[t]
                    lv_ = level[t]
                    v0 = r0[t]
                    v1 = r1[t]
                    v2 = r2[t]
                    v3 = r3[t]
                    vp = rn[t]
                    tk = (x_ < 0.0) & (v0 < lv_)
                    x_ = q0 if tk else x_
                    n_ = vp if tk else n_
                    a_ = v0 if tk else a_
                    tk = (x_ < 0.0) & (v1 < lv_)
                    x_ = q1 if tk else x_
                    n_ = v0 if tk else n_
                    a_ = v1 if tk else a_
                    tk = (x_ < 0.0) & (v2 < lv_)
                    x_ = q2 if tk else x_
                    n_ = v1 if tk else n_
                    a_ = v2 if tk else a_
                    tk = (x_ < 0.0) & (v3 < lv_)
                    x_ = q3 if tk else x_
                    n_ = v2 if tk else n_
                    a_ = v3 if tk else a_
                    xq[t] = x_
                    va[t] = a_
                    vn[t] = n_
                q += 4 * side
            else:
                r0 = B[q]
                rn = B[q - side]
                qv[0] = q
                q0 = qv[0]
                for t in range(n):
                    v0 = r0[t]
                    vp = rn[t]
                    x_ = xq[t]
                    tk = (x_ < 0.0) & (v0 < level[t])
                    xq[t] = q0 if tk else x_
                    vn[t] = vp if tk else vn[t]
                    va[t] = v0 if tk else va[t]
                q += side
        xs = xa if side < 0 else xb
        for t in range(n):  # q + (level - a) / (a_inner - a) on the left, q - ... on the right (exact in B's type)
            if xq[t] >= 0.0:
                xs[t] = xq[t] - side * ((level[t] - va[t]) / (vn[t] - va[t]))
    return xa, xb


@njit
def store_chunk(out, t0, image, cols, peaks, half, c, good, a0, sigma, sat, noise, flag, g_lo, g_pk, g_hi):  # type: ignore[no-untyped-def]
    """Store the fits of one chunk of ``n`` columns into ``out`` (as :func:`fit_results`) from column ``t0`` on:
    the centre row ``peaks - half + c`` where ``good`` (else NaN), ``good`` as ok, and ``a0``, ``sigma``, ``sat``,
    ``noise`` and ``flag`` (n,) each as they are; the green rise from the window's first, middle and last rows
    (``g_lo``, ``g_pk``, ``g_hi``, (n,) each), blue and red read at the same rows (:func:`colour_rises`)."""
    n = cols.size
    o_c, o_a, o_sg, o_sat, o_ok, o_no, o_ri, o_fl = out
    nan = np.nan
    for t in range(n):
        u = np.uint64(t0 + t)
        o_c[u] = peaks[t] - half + c[t] if good[t] else nan
        o_ok[u] = good[t]
    for t in range(n):
        u = np.uint64(t0 + t)
        o_a[u] = a0[t]
        o_sg[u] = sigma[t]
        o_sat[u] = sat[t]
        o_no[u] = noise[t]
        o_fl[u] = flag[t]
    r_g = o_ri[1]
    for t in range(n):
        r_g[np.uint64(t0 + t)] = float(g_pk[t]) - 0.5 * (float(g_lo[t]) + float(g_hi[t]))
    colour_rises(image, cols, peaks, half, (0, 2), o_ri[:, t0 : t0 + n])  # blue and red at the same rows


@njit
def fit_results(n):  # type: ignore[no-untyped-def]
    """Empty results of the chunked column-parallel fits for ``n`` columns: ``(centre_row, amplitude, sigma,
    saturated, ok, local_noise, rise, flag)``, (n,) each and rise (3, n)."""
    return (
        np.empty(n),
        np.empty(n),
        np.empty(n),
        np.empty(n, np.bool_),
        np.empty(n, np.bool_),
        np.empty(n),
        np.empty((3, n)),
        np.empty(n, np.bool_),
    )


@inline
def put_fit(res, r, i, t):  # type: ignore[no-untyped-def]
    """Store result ``i`` of a column-parallel fit ``r`` (as :func:`fit_results`) as column ``t`` of the
    per-column results ``res = (centre, amplitude, sigma, saturated, ok, local_noise, rise)``."""
    res[0][t] = r[0][i]
    res[1][t] = r[1][i]
    res[2][t] = r[2][i]
    res[3][t] = r[3][i]
    res[4][t] = r[4][i]
    res[5][t] = r[5][i]
    for c in range(3):
        res[6][c, t] = r[6][c, i]


@inline
def clip_level(sat_dn):  # type: ignore[no-untyped-def]
    """The level from which a byte sample counts as clipped (at least ``sat_dn``), uint16: 256 (nothing clipped)
    for a level above 255."""
    return np.uint16(min(max(math.ceil(sat_dn), 0), 256))


@njit
def clipped_runs(W, sat_dn):  # type: ignore[no-untyped-def]
    """Per column of ``W`` (m, n) uint8: how many samples are clipped (at least ``sat_dn``) and the rows of the
    first and the last of them: (n,) uint16 each (first 65535 and last 0 where none; 32 lanes; a level above 255
    clips nothing)."""
    m, n = W.shape
    s16 = clip_level(sat_dn)
    cnt = np.zeros(n, np.uint16)
    first = np.full(n, np.uint16(65535))
    last = np.zeros(n, np.uint16)
    for q in range(m):
        wq = W[q]
        uq = np.uint16(q)
        for t in range(n):
            sq = np.uint16(wq[t]) >= s16
            cnt[t] += np.uint16(sq)
            first[t] = min(first[t], uq) if sq else first[t]
            last[t] = uq if sq else last[t]
    return cnt, first, last


@njit
def take_columns(W, idx):  # type: ignore[no-untyped-def]
    """The columns ``idx`` (k,) of ``W`` (m, n): (m, k), C-contiguous."""
    m = W.shape[0]
    k = idx.size
    out = np.empty((m, k), W.dtype)
    for q in range(m):
        wq = W[q]
        oq = out[q]
        for i in range(k):
            oq[i] = wq[idx[i]]
    return out
