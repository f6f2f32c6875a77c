"""The clipped fit, column-parallel: the columns whose candidate has a clipped sample nearby.

Close to the wall the stripe saturates: its top is a run of clipped samples whose middle is the centre's start.
:func:`fit_columns_clipped` gathers each column's window centred on its peak row (:func:`core_peaks`: the middle
of the clipped run in the core rows, else the first maximum), counts the clipped run per column (byte selects,
64 lanes), places the background flanks beyond it (per column, picked by selects over the window's rows) and
moves a symmetric-window centroid from the run's middle (:func:`_clipped_centroid`, float32 sums: centres within
1e-5 px of :func:`.fit.fit_columns`). The unsaturated columns among them take :func:`.fit_plain.plain_fit`.
Wide flat tops are flagged not ``done`` (the last field of :func:`.columns.fit_results`) for the full kernel.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit
from .columns import clipped_runs, fit_results, gather_green, store_chunk, take_columns
from .fit import flank_offset
from .fit_plain import plain_fit


@inline
def _window_sums(a, b, ht, dq, x):  # type: ignore[no-untyped-def]
    """One row of :func:`_clipped_centroid`'s sums (float32): the sample ``x`` at ``dq`` rows from the centre,
    weighted 1 within ``ht - 1`` rows, 0 beyond ``ht`` and linearly between: ``(a + w x, b + w x dq)``."""
    wa = min(max(ht - abs(dq), np.float32(0.0)), np.float32(1.0)) * x
    return a + wa, b + wa * dq


@njit
def _clipped_centroid(W, bl, slope, xl, n_sat, c0, sigma_hint, iterations):  # type: ignore[no-untyped-def]
    """The centre (window rows) and sigma (n,) of saturated profiles: the windows ``W`` (m, n) uint8 less their
    linear backgrounds (``bl + slope (q - xl)``, (n,) each), from ``c0`` (n,), the middle of each clipped run,
    moved ``iterations`` times to the centroid of a symmetric window of half-width
    ``n_sat / 2 + 2.5 sigma_hint + 1`` (weights clipped to [0, 1] at its ends). Float32 sums, four rows per pass
    (the running sums in registers)."""
    m, n = W.shape
    # the background line as an intercept and a slope per column in float32 (twice the lanes; the line is
    # smooth and at most a few hundred DN: its float32 rounding is far below a DN)
    li = np.empty(n, np.float32)
    ls = np.empty(n, np.float32)
    for t in range(n):
        li[t] = np.float32(bl[t] - slope[t] * xl[t])
        ls[t] = np.float32(slope[t])
    B = np.empty((m, n), np.float32)
    for q in range(m):
        wq = W[q]
        bq_ = B[q]
        fq = np.float32(q)
        for t in range(n):
            bq_[t] = np.float32(wq[t]) - (li[t] + ls[t] * fq)
    c = np.empty(n)
    cf = np.empty(n, np.float32)
    hs = np.empty(n, np.float32)
    sigma = np.empty(n)
    for t in range(n):
        c[t] = c0[t]
        sigma[t] = max(0.5 * n_sat[t] / 1.1774, sigma_hint)
        hs[t] = np.float32(0.5 * n_sat[t] + 2.5 * sigma_hint + 1.0)
    s0 = np.empty(n, np.float32)
    s1 = np.empty(n, np.float32)
    one = np.float32(1.0)
    for _ in range(iterations):
        for t in range(n):
            s0[t] = 0.0
            s1[t] = 0.0
            cf[t] = np.float32(c[t])
        q = 0
        while q + 4 <= m:  # four rows per pass, the sums in registers (each row's operations in order)
            w0 = B[q]
            w1 = B[q + 1]
            w2 = B[q + 2]
            w3 = B[q + 3]
            f0 = np.float32(q)
            for t in range(n):
                ht = hs[t]
                dq = f0 - cf[t]
                a_, b_ = _window_sums(s0[t], s1[t], ht, dq, w0[t])
                dq += one
                a_, b_ = _window_sums(a_, b_, ht, dq, w1[t])
                dq += one
                a_, b_ = _window_sums(a_, b_, ht, dq, w2[t])
                dq += one
                s0[t], s1[t] = _window_sums(a_, b_, ht, dq, w3[t])
            q += 4
        while q < m:
            wq = B[q]
            fq = np.float32(q)
            for t in range(n):
                s0[t], s1[t] = _window_sums(s0[t], s1[t], hs[t], fq - cf[t], wq[t])
            q += 1
        for t in range(n):  # branch-free (vectorizes): no step where the sum is zero or the step not finite
            d = float(s0[t])
            nz = d != 0.0
            step = float(s1[t]) / (d if nz else 1.0)
            take = nz & math.isfinite(step)
            c[t] = c[t] + min(max(step, -1.0), 1.0) if take else c[t]
    return c, sigma


@njit
def _fit_clipped_chunk(image, cols, peaks, half, sigma_hint, sat_dn, flank, iterations, out, t0):  # type: ignore[no-untyped-def]
    """:func:`fit_columns_clipped` on one chunk of columns (its arrays stay in the cache): the results of the
    saturated columns written into ``out`` (as :func:`fit_results`, columns ``t0`` on; the others' left to do),
    and returned what the unsaturated ones' fits take: ``(W, bl, slope, xl, sat)``, the windows (m, n) uint8,
    their background lines and whether each is saturated (n,) each."""
    n = cols.size
    m = 2 * half + 1
    R = half
    # the window centred on the peak, rows peak - half ... peak + half: (m, n) bytes
    top_row = np.empty(n, np.int64)
    for t in range(n):
        top_row[t] = peaks[t] - half
    W = np.empty((m, n), np.uint8)
    gather_green(image, cols, top_row, W)
    n16, first, last = clipped_runs(W, sat_dn)
    n_sat = np.empty(n, np.int64)
    c0 = np.empty(n)  # the middle of the clipped run: the saturated profiles' start
    for t in range(n):
        n_sat[t] = n16[t]
        c0[t] = 0.5 * (float(first[t]) + float(last[t])) if first[t] <= last[t] else 0.5 * (m - 1)
    sat = np.empty(n, np.bool_)
    for t in range(n):
        sat[t] = W[R, t] >= sat_dn and n_sat[t] >= 2
    # 1. linear background through the flanks beyond the clipped run (their rows differ per column: gathers)
    bl = np.zeros(n)
    br = np.zeros(n)
    slope = np.empty(n)
    xl = np.empty(n)
    off = np.empty(n, np.int64)
    for t in range(n):
        off[t] = flank_offset(sigma_hint, n_sat[t], R, flank)
    # the flank samples (flank, n) of each side picked by byte selects over the window's rows (64 lanes; the
    # rows differ per column)
    FL = np.zeros((flank, n), np.uint8)
    FR = np.zeros((flank, n), np.uint8)
    if m + R + 2 * flank < 250:
        tl8 = np.empty(n, np.uint8)  # the inner flank rows R -+ off
        tr8 = np.empty(n, np.uint8)
        for t in range(n):
            tl8[t] = np.uint8(R - off[t])
            tr8[t] = np.uint8(R + off[t])
        for j in range(m):
            wj = W[j]
            for q in range(flank):
                jl = np.uint8(j + q)  # row j is R - off - q where R - off = j + q
                jr = np.uint8(j - q if j >= q else 255)  # and R + off + q where R + off = j - q
                fl = FL[q]
                fr = FR[q]
                for t in range(n):
                    mkl = np.uint8(0) - np.uint8(tl8[t] == jl)
                    mkr = np.uint8(0) - np.uint8(tr8[t] == jr)
                    x = wj[t]
                    fl[t] = (x & mkl) | (fl[t] & ~mkl)
                    fr[t] = (x & mkr) | (fr[t] & ~mkr)
    else:  # (windows too long for byte row arithmetic)
        for q in range(flank):
            for t in range(n):
                FL[q, t] = W[R - off[t] - q, t]
                FR[q, t] = W[R + off[t] + q, t]
    for q in range(flank):
        fl = FL[q]
        fr = FR[q]
        for t in range(n):
            bl[t] += fl[t]
            br[t] += fr[t]
    for t in range(n):
        bl[t] /= flank
        br[t] /= flank
        slope[t] = (br[t] - bl[t]) / (2.0 * off[t] + flank - 1)
        xl[t] = R - off[t] - 0.5 * (flank - 1)
    ss = np.zeros(n)
    for q in range(flank):
        fl = FL[q]
        fr = FR[q]
        for t in range(n):
            ql = R - off[t] - q
            qr = R + off[t] + q
            r1 = fl[t] - (bl[t] + slope[t] * (ql - xl[t]))
            r2 = fr[t] - (bl[t] + slope[t] * (qr - xl[t]))
            ss[t] += r1 * r1 + r2 * r2
    noise = np.empty(n)
    for t in range(n):
        noise[t] = math.sqrt(ss[t] / max(2 * flank - 2, 1))
    a0 = np.empty(n)
    for t in range(n):
        a0[t] = W[R, t] - (bl[t] + slope[t] * (R - xl[t]))
    # 2-3. the saturated profiles: from the middle of their clipped run, symmetric-window centroid (the width of a
    # clipped peak is its run; float32); the others are fitted by the caller, all chunks' at once
    n_s = 0
    for t in range(n):
        n_s += sat[t]
    if n_s == n:  # (the common case close to the wall: all of them saturated)
        c, sigma = _clipped_centroid(W, bl, slope, xl, n_sat, c0, sigma_hint, iterations)
    else:
        c = np.full(n, np.nan)
        sigma = np.full(n, np.nan)
        if n_s:
            idx = np.flatnonzero(sat)
            c_k, sig_k = _clipped_centroid(
                take_columns(W, idx), bl[idx], slope[idx], xl[idx], n_sat[idx], c0[idx], sigma_hint, iterations
            )
            for i in range(n_s):
                c[idx[i]] = c_k[i]
                sigma[idx[i]] = sig_k[i]
    # 4. acceptance (anywhere on the clipped top) and the colour rises (green from the window: its peak row and
    # ends)
    good = np.empty(n, np.bool_)
    for t in range(n):  # branch-free (vectorizes); |c - R| <= lim is False for NaN and inf
        good[t] = sat[t] & (abs(c[t] - R) <= 0.5 * n_sat[t] + 1.0) & (a0[t] > 0)
    store_chunk(out, t0, image, cols, peaks, half, c, good, a0, sigma, sat, noise, sat, W[0], W[R], W[m - 1])
    return W, bl, slope, xl, sat


@njit
def core_peaks(image, cols, rows, e, sat_dn):  # type: ignore[no-untyped-def]
    """The integer peak of the green samples of rows ``rows - e ... rows + e`` (clamped to the image) of each
    column, as :func:`fit_columns` re-centres its window: the middle of their clipped run (samples of at least
    ``sat_dn``), else the first maximum. Returns ``(peak_row, clipped)``: (N,) int64 and (N,) bool (two or more
    samples of the core clipped)."""
    n = cols.size
    ne = 2 * e + 1
    top_row = np.empty(n, np.int64)
    for t in range(n):
        top_row[t] = rows[t] - e
    C = np.empty((ne, n), np.uint8)
    gather_green(image, cols, top_row, C)
    # byte selects (64 lanes): the first maximum
    bv = C[0].copy()
    d = np.zeros(n, np.uint8)
    for j in range(ne):
        pj = C[j]
        uj = np.uint8(j)
        for t in range(n):
            x = pj[t]
            mk = np.uint8(0) - np.uint8(x > bv[t])
            bv[t] = max(bv[t], x)
            d[t] = (uj & mk) | (d[t] & ~mk)
    _cnt, first, last = clipped_runs(C, sat_dn)
    peak = np.empty(n, np.int64)
    clipped = np.empty(n, np.bool_)
    for t in range(n):
        cl = first[t] <= last[t]
        clipped[t] = first[t] < last[t]
        mid = (np.int64(first[t]) + np.int64(last[t])) >> 1
        peak[t] = rows[t] - e + (mid if cl else np.int64(d[t]))
    return peak, clipped


@njit
def fit_columns_clipped(  # type: ignore[no-untyped-def]
    image, cols, peaks, half, sigma_hint, sat_dn, flank, iterations, min_sig, max_sig, wide_fwhm
):
    """:func:`fit_columns` column-parallel (the inner loops run over columns), given each column's peak row
    (:func:`core_peaks`) instead of its candidate row, for the columns whose candidate has a clipped sample
    nearby: the saturated profiles (peak sample clipped, at least two clipped samples; symmetric-window centroid
    from the middle of the clipped run, float32 sums: centres within 1e-5 px of :func:`fit_columns`) and the
    profiles that are not saturated and not wider than ``wide_fwhm`` at half level (Gaussian-weighted centroid, in
    :func:`fit_columns`'s float64 arithmetic).

    Same other arguments as :func:`fit_columns` without the neighbour model and the width limits. Returns
    ``(centre_row, amplitude, sigma, saturated, ok, local_noise, rise, done)``: ``done`` (N,) bool marks the
    columns of those two kinds, whose results are :func:`fit_columns`'s; the others (flat-topped wide profiles)
    are to be fitted by it. ``image`` must be C-contiguous. Works in chunks of 512 columns.
    """
    N = cols.size
    m = 2 * half + 1
    out = fit_results(N)
    # the unsaturated columns of every chunk, fitted together at the end: their windows, lines and peak rows
    Wp = np.empty((m, N), np.uint8)
    ip = np.empty(N, np.int64)
    lines = np.empty((3, N))
    pk = np.empty(N, np.int64)
    n_p = 0
    for t0 in range(0, N, 512):
        t1 = min(t0 + 512, N)
        W, bl, slope, xl, sat = _fit_clipped_chunk(
            image, cols[t0:t1], peaks[t0:t1], half, sigma_hint, sat_dn, flank, iterations, out, t0
        )
        p0 = n_p
        for t in range(t1 - t0):
            if not sat[t]:
                ip[n_p] = t
                lines[0, n_p] = bl[t]
                lines[1, n_p] = slope[t]
                lines[2, n_p] = xl[t]
                pk[n_p] = peaks[t0 + t]
                n_p += 1
        for q in range(m):
            wq = W[q]
            pq = Wp[q]
            for i in range(p0, n_p):
                pq[i] = wq[ip[i]]
        for i in range(p0, n_p):
            ip[i] += t0
    if n_p == 0:
        return out
    Wk = np.empty((m, n_p), np.uint8)
    for q in range(m):
        for i in range(n_p):
            Wk[q, i] = Wp[q, i]  # (a loop: an array assignment compiles numpy's broadcasting and its messages)
    a0 = np.empty(n_p)
    for i in range(n_p):
        a0[i] = out[1][ip[i]]
    c, sigma, okp, done = plain_fit(
        Wk, a0, lines[0, :n_p], lines[1, :n_p], lines[2, :n_p], sigma_hint, min_sig, max_sig, wide_fwhm, iterations
    )
    for i in range(n_p):
        t = ip[i]
        good = okp[i] and abs(c[i] - half) <= 2.0 and a0[i] > 0
        out[0][t] = pk[i] - half + c[i] if good else np.nan
        out[2][t] = sigma[i]
        out[4][t] = good
        out[7][t] = done[i]
    return out
