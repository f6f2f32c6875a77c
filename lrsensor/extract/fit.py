"""The full sub-pixel fit of one column at a time (:func:`fit_columns`): every kind of profile.

For each picked (column, row) the green profile ``row +- (half + e)`` is cut from the image, re-centred on its
integer peak (the middle of a clipped run), and fitted: linear background from two flank windows of ``flank``
rows (murk gradients and the glow beside the stripe cancel), a three-point log-parabola start (Gaussian through
the peak and its neighbours), then a Gaussian-weighted centroid with the Newton gain of a Gaussian profile
(unbiased for any symmetric profile, noise close to the Cramer-Rao bound). Saturated profiles (clipped tops) take
the symmetric-window centroid from the middle of the clipped samples; flat-topped wide profiles (thick sheets
close to the wall, wider than ``wide_fwhm`` at half level) take it from the midpoint of their half-level
crossings, with the background flanks moved beyond the top. Another laser's stripe close by (``nb_v, nb_a,
nb_s``) is subtracted first as a Gaussian.

It is the slowest fit (a column at a time, branches) and the most general: the column-parallel fits
(:mod:`.fit_common`, :mod:`.fit_clipped`, :mod:`.refit`) take the common kinds of profile with the same results
and leave it the rest (flat tops, clipped profiles with a neighbour). Its vectorized twin in numpy is
:func:`lrsensor.extract.centre.fit_profiles` (the reference's fit).
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit

#: Half-width (rows) of the box smoothing of a profile before its flat-top test.
FLAT_SMOOTH = 2


@njit
def _level_crossings(P, o, R, m, bl, slope, xl, level):  # type: ignore[no-untyped-def]
    """First crossings below ``level`` left and right of ``R`` of a profile (window ``P[o:o + m]`` minus the line
    ``bl + slope (q - xl)``), linearly interpolated: ``(xa, xb)``, -1 where there is none."""
    xa = -1.0
    for q in range(R - 1, -1, -1):
        aq = P[o + q] - (bl + slope * (q - xl))
        if aq < level:
            an = P[o + q + 1] - (bl + slope * (q + 1 - xl))
            xa = q + (level - aq) / (an - aq)
            break
    xb = -1.0
    for q in range(R + 1, m):
        aq = P[o + q] - (bl + slope * (q - xl))
        if aq < level:
            an = P[o + q - 1] - (bl + slope * (q - 1 - xl))
            xb = q - (level - aq) / (an - aq)
            break
    return xa, xb


@njit
def _level_width(P, o, R, m, bl, slope, xl, level):  # type: ignore[no-untyped-def]
    """Width at ``level`` between :func:`_level_crossings`; inf when one is missing."""
    xa, xb = _level_crossings(P, o, R, m, bl, slope, xl, level)
    return xb - xa if (xa >= 0 and xb >= 0) else np.inf


@njit
def _flank_line(P, o, R, off, flank):  # type: ignore[no-untyped-def]
    """Background line through the means of the two flank windows ``R -+ (off .. off + flank - 1)`` of the profile
    window ``P[o:]``: ``(bl, slope, xl)``, the line being ``bl + slope (q - xl)``."""
    bl = 0.0
    br = 0.0
    for q in range(flank):
        bl += P[o + R - off - q]
        br += P[o + R + off + q]
    bl /= flank
    br /= flank
    xl = R - off - 0.5 * (flank - 1)
    return bl, (br - bl) / (2.0 * off + flank - 1), xl


@inline
def flank_offset(sigma_hint, n_sat, half, flank):  # type: ignore[no-untyped-def]
    """Rows from the peak to the inner row of each background flank of ``flank`` rows: beyond 3 ``sigma_hint`` and
    half of ``n_sat`` clipped samples, inside the window of ``half`` rows either side (every fit places its flanks
    so; :func:`read_reach` takes them as the rows a fit reads)."""
    return int(min(math.ceil(3.0 * sigma_hint + 0.5 * n_sat + 1.0), half - flank + 1))


@njit
def _subtract_gaussian(P, mu, a, sigma):  # type: ignore[no-untyped-def]
    """``P[q] -= a exp(-(q - mu)^2 / (2 sigma^2))`` for every sample of the profile ``P`` (K,), in place.

    Four ``exp`` in all: the weights by recurrence outward from the sample nearest ``mu``, where each step
    multiplies by a ratio that itself shrinks by ``exp(-1 / sigma^2)`` (so they only fall: no overflow, and an
    underflow to zero is the true value's)."""
    k = P.size
    inv = 0.5 / (sigma * sigma)
    g2 = math.exp(-2.0 * inv)
    qc = min(max(int(math.floor(mu + 0.5)), 0), k - 1)  # noqa: RUF046 (numba: floor of a float is a float)
    d = qc - mu
    w0 = a * math.exp(-(d * d) * inv)
    w = w0
    ratio = math.exp(-(2.0 * d + 1.0) * inv)  # w(d + 1) / w(d)
    for q in range(qc, k):
        P[q] -= w
        w *= ratio
        ratio *= g2
    w = w0
    ratio = math.exp((2.0 * d - 1.0) * inv)  # w(d - 1) / w(d)
    for q in range(qc - 1, -1, -1):
        w *= ratio
        ratio *= g2
        P[q] -= w


@njit
def fit_columns(  # type: ignore[no-untyped-def]
    image,
    cols,
    rows,
    half,
    e,
    sigma_hint,
    sat_dn,
    min_sig,
    max_sig,
    flank,
    iterations,
    nb_v,
    nb_a,
    nb_s,
    max_fwhm,
    wide_fwhm,
):
    """Sub-pixel centre per column (the reference's vectorized fit is :func:`lrsensor.extract.centre.fit_profiles`).

    For each (column, integer row) the green profile ``rows +- (half + e)`` is cut from ``image`` (H, W, 3)
    uint8, re-centred on its integer peak (the middle of a clipped run), and fitted: linear background from two
    flank windows, three-point log-parabola start, Gaussian-weighted centroid with the Newton gain (saturated:
    symmetric-window centroid from the middle of the clipped samples, accepted anywhere on the clipped top). The
    rises of blue, green and red at the peak over the window ends are returned for the colour test, which is
    pooled along the stripe (:func:`finish_points`).
    ``nb_v, nb_a, nb_s`` (N,): row, amplitude and sigma of another laser's stripe close by in the same column
    (NaN row = none); its Gaussian is subtracted from the profile first (stripes overlapping at long range).
    Profiles whose half-level width exceeds ``wide_fwhm`` (flat-topped thick sheets close to the wall) take the
    symmetric-window centroid from the midpoint of their half-level crossings, with the background flanks moved
    beyond them; they pass while that width is at most ``max_fwhm`` (N,) (the physical limit at that row).

    Returns:
        ``(centre_row, amplitude, sigma, saturated, ok, local_noise, rise)``: (N,) each, and rise (3, N) in B, G, R.
    """
    h = image.shape[0]
    n = cols.size
    m = 2 * half + 1
    R = half
    centre = np.full(n, np.nan)
    amp_out = np.zeros(n)
    sig_out = np.full(n, np.nan)
    sat_out = np.zeros(n, np.bool_)
    ok_out = np.zeros(n, np.bool_)
    noise_out = np.zeros(n)
    rise = np.zeros((3, n))
    P = np.empty(m + 2 * e)
    B = np.empty(m)
    S = np.empty(m)
    for t in range(n):
        col = cols[t]
        r0 = rows[t] - half - e
        for q in range(m + 2 * e):
            rr = min(max(r0 + q, 0), h - 1)
            P[q] = image[rr, col, 1]
        if math.isfinite(nb_v[t]):
            _subtract_gaussian(P, nb_v[t] - r0, nb_a[t], nb_s[t])
        # re-centre on the integer peak within +-e
        bq = e + R
        bv = -1.0
        nsat_core = 0
        first = -1
        last = -1
        for q in range(R, R + 2 * e + 1):
            if P[q] > bv:
                bv = P[q]
                bq = q
            if P[q] >= sat_dn:
                nsat_core += 1
                if first < 0:
                    first = q
                last = q
        if nsat_core > 0:
            bq = (first + last) // 2
        shift = bq - (e + R)
        o = e + shift  # window start in P
        pk_row = rows[t] + shift
        # saturation
        n_sat = 0
        q_first = m
        q_last = -1
        for q in range(m):
            if P[o + q] >= sat_dn:
                n_sat += 1
                q_first = min(q_first, q)
                q_last = q
        saturated = P[o + R] >= sat_dn and n_sat >= 2
        # 1. linear background
        off = flank_offset(sigma_hint, n_sat, R, flank)
        bl, slope, xl = _flank_line(P, o, R, off, flank)
        ss = 0.0
        for q in range(flank):
            r1 = P[o + R - off - q] - (bl + slope * (R - off - q - xl))
            r2 = P[o + R + off + q] - (bl + slope * (R + off + q - xl))
            ss += r1 * r1 + r2 * r2
        noise_out[t] = math.sqrt(ss / max(2 * flank - 2, 1))
        # 2. log-parabola start
        s = max(1, int(round(0.8 * sigma_hint)))  # noqa: RUF046 (numba: round() of a float is a float)
        am = P[o + R - s] - (bl + slope * (R - s - xl))
        a0 = P[o + R] - (bl + slope * (R - xl))
        ap = P[o + R + s] - (bl + slope * (R + s - xl))
        ym = math.log(max(am, 0.5))
        y0 = math.log(max(a0, 0.5))
        yp = math.log(max(ap, 0.5))
        den = ym - 2.0 * y0 + yp
        curved = den < -1e-6
        if curved:
            delta = min(max(0.5 * s * (ym - yp) / den, -1.0), 1.0)
            sigma = s / math.sqrt(-den)
        else:
            delta = 0.0
            sigma = np.inf
        c = R + delta
        if saturated:  # start from the middle of the clipped samples (the log-parabola sees a flat top)
            c = 0.5 * (q_first + q_last)
            sigma = max(0.5 * n_sat / 1.1774, sigma_hint)
        ok = saturated or (curved and sigma >= min_sig and sigma <= max_sig)
        sig_p = sigma if math.isfinite(sigma) else sigma_hint
        sig_p = min(max(sig_p, min_sig), max_sig)
        sig_w = max(sig_p, 1.1)
        inv2 = 0.5 / (sig_w * sig_w)
        gain = 1.0 if saturated else 1.0 + sig_p * sig_p * 2.0 * inv2
        hs = 0.5 * n_sat + 2.5 * sigma_hint + 1.0
        # half-level width and midpoint (flat tops: the log-parabola sees no curvature there)
        wide = False
        fw = np.inf
        if not saturated and a0 > 0:
            xa, xb = _level_crossings(P, o, R, m, bl, slope, xl, 0.5 * a0)
            fw = xb - xa if (xa >= 0 and xb >= 0) else np.inf
            # flat-topped (a thick sheet): steep edges, the widths at 1/4 and 3/4 of the peak differ by at most
            # half the half-level width (a Gaussian: 0.77 of it; glow and haze ridges are smooth like that)
            flat = False
            if fw > wide_fwhm:  # (only then does the shape matter)
                # on the profile box-smoothed over 2 FLAT_SMOOTH + 1 rows (noise on a plateau must not decide)
                k = FLAT_SMOOTH
                for q in range(m):
                    acc = 0.0
                    for j in range(max(q - k, 0), min(q + k, m - 1) + 1):
                        acc += P[o + j] - (bl + slope * (j - xl))
                    S[q] = acc / (2 * k + 1)
                a0s = max(S[R], 0.5 * a0)
                w25 = _level_width(S, 0, R, m, 0.0, 0.0, 0.0, 0.25 * a0s)
                w75 = _level_width(S, 0, R, m, 0.0, 0.0, 0.0, 0.75 * a0s)
                flat = w25 - w75 <= 0.5 * fw + k
            if fw > wide_fwhm and math.isfinite(fw):
                c = 0.5 * (xa + xb)  # wide: the peak sample may be anywhere on the top; start from the middle
            if fw > wide_fwhm and flat:
                wide = True
                ok = fw <= max_fwhm[t]
                if math.isfinite(fw):
                    c = 0.5 * (xa + xb)
                    sigma = fw / 2.3548200450309493
                    # background flanks beyond the flat top and its edges
                    off = int(min(max(off, math.ceil(0.5 * fw + 4.0)), R - flank + 1))
                    bl, slope, xl = _flank_line(P, o, R, off, flank)
                    hs = min(0.5 * fw + 3.0, off - 1.0) + 0.5
                    a0 = P[o + R] - (bl + slope * (R - xl))
        # 3. centroid iterations on the background-free profile B
        for q in range(m):
            B[q] = P[o + q] - (bl + slope * (q - xl))
        if saturated or wide:
            for _ in range(iterations):
                s0 = 0.0
                s1 = 0.0
                for q in range(m):
                    d = q - c
                    wa = min(max(hs - abs(d), 0.0), 1.0) * B[q]
                    s0 += wa
                    s1 += wa * d
                if s0 != 0.0:
                    step = s1 / s0
                    if math.isfinite(step):
                        c += min(max(step, -1.0), 1.0)
        else:
            g2 = math.exp(-2.0 * inv2)
            reach = 4.0 * sig_w + 1.0  # weights beyond are below exp(-8)
            for _ in range(iterations):
                if not math.isfinite(c):
                    break
                q0 = max(int(math.floor(c - reach)), 0)  # noqa: RUF046 (numba: floor of a float is a float)
                q1 = min(int(math.ceil(c + reach)) + 1, m)  # noqa: RUF046
                s0 = 0.0
                s1 = 0.0
                # Gaussian weights by recurrence: w(q+1) = w(q) r(q), r(q+1) = r(q) exp(-2 inv2) (two exp per column)
                d0 = q0 - c
                w = math.exp(-(d0 * d0) * inv2)
                ratio = math.exp(-(2.0 * d0 + 1.0) * inv2)
                for q in range(q0, q1):
                    wa = w * B[q]
                    s0 += wa
                    s1 += wa * (q - c)
                    w *= ratio
                    ratio *= g2
                if s0 != 0.0:
                    step = gain * s1 / s0
                    if math.isfinite(step):
                        c += min(max(step, -1.0), 1.0)
        if saturated:
            amp = P[o + R] - (bl + slope * (R - xl))
        else:
            amp = a0
        lim_c = 0.5 * fw + 1.0 if (fw > wide_fwhm and math.isfinite(fw)) else 2.0
        if saturated:  # anywhere on the clipped top
            lim_c = 0.5 * n_sat + 1.0
        ok = ok and math.isfinite(c) and abs(c - R) <= lim_c and amp > 0
        # colour: the rises of blue, green and red at the peak over the window ends (judged along the stripe later)
        rp = min(max(pk_row, 0), h - 1)
        rl = min(max(pk_row - half, 0), h - 1)
        rh = min(max(pk_row + half, 0), h - 1)
        for ch in range(3):
            rise[ch, t] = image[rp, col, ch] - 0.5 * (float(image[rl, col, ch]) + image[rh, col, ch])
        if ok:
            centre[t] = pk_row - half + c
        amp_out[t] = amp
        sig_out[t] = sigma
        sat_out[t] = saturated
        ok_out[t] = ok
    return centre, amp_out, sig_out, sat_out, ok_out, noise_out, rise
