"""The common fit, column-parallel in float32: the unclipped narrow profiles (most of a frame).

:func:`fit_columns_common` takes each column's window centred on its peak row (:func:`.fit_clipped.core_peaks`)
and does :func:`.fit.fit_columns`' steps for all columns of a chunk of 512 at once: linear background from the two
flanks, log-parabola start, Gaussian-weighted centroid with weights by recurrence (two ``exp`` per column and
iteration), four rows per pass over the columns with the running sums in registers. The window, the background,
the start and the sums are float32: twice the vector lanes of float64, centres within about 1e-4 px of the full
kernel, far below the extractor's noise.

Columns with two or more clipped samples in the window, or wider than ``wide_fwhm`` at half level, are flagged
``special`` (the last field of :func:`.columns.fit_results`) for the other fits.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit
from .columns import clip_level, fit_results, gather_green, half_crossings, store_chunk
from .fit import flank_offset


@njit
def _fit_common_chunk(  # type: ignore[no-untyped-def]
    image, cols, peaks, half, sigma_hint, sat_dn, min_sig, max_sig, flank, iterations, wide_fwhm, out, t0
):
    """:func:`fit_columns_common` on one chunk of columns (its arrays stay in the cache): the results written
    into ``out`` (as :func:`fit_results`, columns ``t0`` on; no copy of a chunk's results)."""
    n = cols.size
    m = 2 * half + 1
    R = half
    special = np.zeros(n, np.bool_)
    # the window centred on the peak, rows peak - half ... peak + half: (m, n)
    top_row = np.empty(n, np.int64)
    for t in range(n):
        top_row[t] = peaks[t] - half
    W = np.empty((m, n), np.uint8)
    gather_green(image, cols, top_row, W)  # bytes, then converted in a vector pass (cheaper than float stores)
    B = np.empty((m, n), np.float32)
    for q in range(m):
        wq = W[q]
        bq_ = B[q]
        for t in range(n):
            bq_[t] = np.float32(wq[t])
    # the green samples of the colour rise (peak row and the window's ends), before the background is removed
    g_lo = B[0].copy()
    g_pk = B[R].copy()
    g_hi = B[m - 1].copy()
    # two or more clipped samples in the window: special (saturated, or the full kernel's flanks move out); a
    # single clipped sample (a peak just reaching the top of the range) is fitted here as a Gaussian
    n_clip = np.zeros(n, np.uint8)
    s16 = clip_level(sat_dn)
    for q in range(m):
        wq = W[q]
        for t in range(n):
            n_clip[t] = min(n_clip[t], np.uint8(254)) + np.uint8(np.uint16(wq[t]) >= s16)
    for t in range(n):
        special[t] |= n_clip[t] >= np.uint8(2)
    # 1. linear background from the two flanks, subtracted; noise of the flanks
    off = flank_offset(sigma_hint, 0, R, flank)
    xl = R - off - 0.5 * (flank - 1)
    bl = np.zeros(n, np.float32)
    br = np.zeros(n, np.float32)
    for q in range(flank):
        for t in range(n):
            bl[t] += B[R - off - q, t]
            br[t] += B[R + off + q, t]
    slope = np.empty(n, np.float32)
    xlf = np.float32(xl)
    fl = np.float32(flank)
    dsl = np.float32(2.0 * off + flank - 1)
    for t in range(n):
        bl[t] /= fl
        br[t] /= fl
        slope[t] = (br[t] - bl[t]) / dsl
    for q in range(m):
        for t in range(n):
            B[q, t] -= bl[t] + slope[t] * (np.float32(q) - xlf)
    noise = np.zeros(n, np.float32)
    for q in range(flank):
        for t in range(n):
            noise[t] += B[R - off - q, t] ** 2 + B[R + off + q, t] ** 2
    for t in range(n):
        noise[t] = math.sqrt(noise[t] / np.float32(max(2 * flank - 2, 1)))
    # 2. log-parabola start
    s = max(1, int(round(0.8 * sigma_hint)))  # noqa: RUF046 (numba: round() of a float is a float)
    c = np.empty(n)
    sigma = np.empty(n)
    ok = np.zeros(n, np.bool_)
    inv2 = np.empty(n)
    gain = np.empty(n)
    g2 = np.empty(n, np.float32)
    a0 = np.empty(n, np.float32)
    sw_max = 1.1
    lv = np.empty(3 * n, np.float32)
    f_half = np.float32(0.5)
    for t in range(n):
        a0[t] = B[R, t]
        lv[t] = max(B[R - s, t], f_half)
        lv[n + t] = max(a0[t], f_half)
        lv[2 * n + t] = max(B[R + s, t], f_half)
    lv = np.log(lv)
    # in float32 (twice the lanes of the divisions and square roots): the start is refined by the centroid, and
    # the widths are tested against limits far coarser than its rounding
    fR = np.float32(R)
    sf = np.float32(s)
    f1 = np.float32(1.0)
    f2 = np.float32(2.0)
    sh32 = np.float32(sigma_hint)
    lo32 = np.float32(min_sig)
    hi32 = np.float32(max_sig)
    sws = np.empty(n, np.float32)
    for t in range(n):  # branch-free (vectorizes): a profile without curvature takes the selects' other side
        ym = lv[t]
        y0 = lv[n + t]
        yp = lv[2 * n + t]
        den = ym - f2 * y0 + yp
        curved = den < np.float32(-1e-6)
        dsafe = den if curved else -f1
        c[t] = fR + min(max(f_half * sf * (ym - yp) / dsafe, -f1), f1) if curved else fR
        sg = sf / np.sqrt(-dsafe)  # finite where curved
        ok[t] = curved & (sg >= lo32) & (sg <= hi32)
        sigma[t] = sg if curved else np.inf
        sig_p = min(max(sg if curved else sh32, lo32), hi32)
        sig_w = max(sig_p, np.float32(1.1))
        sws[t] = sig_w
        iv = f_half / (sig_w * sig_w)
        inv2[t] = iv
        gain[t] = f1 + sig_p * sig_p * f2 * iv
        g2[t] = -f2 * iv
    for t in range(n):
        sw_max = max(sw_max, float(sws[t]))
    g2f = np.exp(g2)
    # half-level widths: wide profiles (flat tops) and profiles without both crossings go to the full kernel
    h0 = np.empty(n, np.float32)
    for t in range(n):
        h0[t] = np.float32(0.5) * a0[t]
    xa, xb = half_crossings(B, h0)
    for t in range(n):
        if a0[t] > 0.0 and not (xa[t] >= 0.0 and xb[t] >= 0.0 and xb[t] - xa[t] <= wide_fwhm):
            special[t] = True
    # 3. Gaussian-weighted centroid iterations (weights by recurrence, over the reach of the widest weight)
    reach = int(math.ceil(4.0 * sw_max + 1.0)) + 3  # noqa: RUF046 (numba: ceil of a float is a float)
    q0 = max(R - reach, 0)
    q1 = min(R + reach + 1, m)
    # column-parallel (the inner loop runs over columns: independent recurrences, vectorized), each column's
    # arithmetic in the same order as column by column
    ex = np.empty(2 * n, np.float32)
    a_s0 = np.empty(n, np.float32)
    a_s1 = np.empty(n, np.float32)
    wq = np.empty(n, np.float32)
    rq = np.empty(n, np.float32)
    cf = np.empty(n, np.float32)
    for _ in range(iterations):
        for t in range(n):
            d0 = q0 - c[t]
            ex[t] = np.float32(-(d0 * d0) * inv2[t])
            ex[n + t] = np.float32(-(2.0 * d0 + 1.0) * inv2[t])
            a_s0[t] = 0.0
            a_s1[t] = 0.0
            cf[t] = c[t]
        ex = np.exp(ex)
        for t in range(n):
            wq[t] = ex[t]
            rq[t] = ex[n + t]
        # four rows per pass over the columns, the running values in registers between them (a pass per row
        # stores all four back for every row: store-bound); each row's operations in the same order
        q = q0
        while q + 4 <= q1:
            b0 = B[q]
            b1 = B[q + 1]
            b2 = B[q + 2]
            b3 = B[q + 3]
            f0 = np.float32(q)
            f1 = np.float32(q + 1)
            f2 = np.float32(q + 2)
            f3 = np.float32(q + 3)
            for t in range(n):
                s0 = a_s0[t]
                s1 = a_s1[t]
                w_ = wq[t]
                r_ = rq[t]
                g_ = g2f[t]
                c_ = cf[t]
                wa = w_ * b0[t]
                s0 += wa
                s1 += wa * (f0 - c_)
                w_ *= r_
                r_ *= g_
                wa = w_ * b1[t]
                s0 += wa
                s1 += wa * (f1 - c_)
                w_ *= r_
                r_ *= g_
                wa = w_ * b2[t]
                s0 += wa
                s1 += wa * (f2 - c_)
                w_ *= r_
                r_ *= g_
                wa = w_ * b3[t]
                s0 += wa
                s1 += wa * (f3 - c_)
                w_ *= r_
                r_ *= g_
                a_s0[t] = s0
                a_s1[t] = s1
                wq[t] = w_
                rq[t] = r_
            q += 4
        while q < q1:
            bq_ = B[q]
            fq = np.float32(q)
            for t in range(n):
                wa = wq[t] * bq_[t]
                a_s0[t] += wa
                a_s1[t] += wa * (fq - cf[t])
                wq[t] *= rq[t]
                rq[t] *= g2f[t]
            q += 1
        for t in range(n):  # branch-free (vectorizes): no step where the sum is zero or the step not finite
            d = float(a_s0[t])
            nz = d != 0.0
            step = gain[t] * float(a_s1[t]) / (d if nz else 1.0)
            take = nz & math.isfinite(step)
            c[t] = c[t] + min(max(step, -1.0), 1.0) if take else c[t]
    # 4. acceptance, then the results into ``out`` from column ``t0`` on, with the colour rises
    for t in range(n):  # branch-free (vectorizes); |c - R| <= 2 is False for NaN and inf
        ok[t] = ok[t] & (abs(c[t] - R) <= 2.0) & (a0[t] > 0.0)
    no_sat = np.zeros(n, np.bool_)
    store_chunk(out, t0, image, cols, peaks, half, c, ok, a0, sigma, no_sat, noise, special, g_lo, g_pk, g_hi)


@inline
def fit_columns_common(  # type: ignore[no-untyped-def]
    image, cols, peaks, half, sigma_hint, sat_dn, min_sig, max_sig, flank, iterations, wide_fwhm
):
    """:func:`fit_columns` for the common case, column-parallel (the inner loops run over columns and vectorize),
    given each column's peak row (:func:`core_peaks`) instead of its candidate row.

    Same other arguments (without the neighbour model and ``max_fwhm``) and results for every column that has at
    most one clipped sample in its window and a half-level width of at most ``wide_fwhm`` (up to rounding: the
    window, its background line, the log-parabola start and the centroid sums are float32, twice the lanes of
    float64 in the vector loops, and so are its logs and exps, so centres agree to about 1e-4 px, far below the
    extractor's noise; with one clipped sample the flanks sit up to a row closer than :func:`fit_columns` puts
    them, which moves centres by hundredths of a pixel); the others are flagged in the extra last output
    ``special`` (N,) bool, and their results are to be
    taken from the other fits.
    Returns ``(centre_row, amplitude, sigma, saturated, ok, local_noise, rise, special)``.
    ``image`` must be C-contiguous. Works in chunks of 512 columns.
    """
    out = fit_results(cols.size)
    for t0 in range(0, cols.size, 512):
        t1 = min(t0 + 512, cols.size)
        _fit_common_chunk(
            image,
            cols[t0:t1],
            peaks[t0:t1],
            half,
            sigma_hint,
            sat_dn,
            min_sig,
            max_sig,
            flank,
            iterations,
            wide_fwhm,
            out,
            t0,
        )
    return out
