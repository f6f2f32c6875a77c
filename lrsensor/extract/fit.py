"""The sub-pixel fit of the stripe's profile in each picked column: one fit for every kind of profile.

:func:`fit_columns` takes the picked (column, row) points of a frame and, for all of them at once (the inner
loops run over columns and vectorize), fits the green profile of each:

1. the profile ``row +- (half + RECENTRE_PX)``, another laser's stripe close by subtracted first as a Gaussian
   (the neighbour refits, :mod:`.refit`), re-centred on its integer peak (the middle of a clipped run, else the
   first maximum within ``RECENTRE_PX`` rows of the row);
2. a linear background through two flank windows of :data:`FLANK_PX` rows beyond the stripe (murk gradients and
   the glow beside the stripe cancel) and beyond half of a clipped run (:func:`flank_offset`);
3. the start: a three-point log-parabola (a Gaussian through the peak and its neighbours); saturated profiles
   (clipped tops) start from the middle of their clipped samples; flat-topped wide profiles (thick sheets close to
   the wall, wider than ``wide_fwhm_px`` at half level, steep edges) from the midpoint of their half-level
   crossings, with the background flanks moved beyond the top;
4. centroid iterations: a Gaussian-weighted centroid with the Newton gain of a Gaussian profile (unbiased for any
   symmetric profile, noise close to the Cramer-Rao bound); for saturated and flat-topped profiles the plain
   centroid in a window symmetric about the current estimate (the plateau carries no noise);
5. acceptance (a peak, a width within the limits, the centre near the peak) and the colour rises at the peak
   over the window ends, for the colour test pooled along the stripe (:mod:`.finish`).

The numpy reference is :func:`lrsensor.extract.reference_fit._fit` with
:func:`lrsensor.extract.centre.fit_profiles` (the same steps in float32).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ._jit import callee, empty, full, inline, njit, zeros
from .columns import colour_rises, gather_green

#: Rows either side of the picked row within which a profile is re-centred on its integer peak.
RECENTRE_PX = 3
#: Rows per background flank.
FLANK_PX = 3
#: Half-width (rows) of the box smoothing of a profile before its flat-top test.
FLAT_SMOOTH = 2
#: Sigma of a Gaussian per full width at half maximum.
FWHM_PER_SIGMA = 2.3548200450309493


class Fits(NamedTuple):
    """The fits of ``N`` points, (N,) each; rows in pixels, amplitudes and noise in DN."""

    #: Centre row (NaN where not accepted).
    centre: NDArray[np.float64]
    #: Peak height above the local background.
    amplitude: NDArray[np.float64]
    #: Gaussian-equivalent width (saturated: of the clipped run; flat tops: of the half-level width), px.
    sigma: NDArray[np.float64]
    #: Clipped top (at least two clipped samples, the peak one among them).
    saturated: NDArray[np.bool_]
    #: Accepted.
    ok: NDArray[np.bool_]
    #: Spread of the flank samples about the background line.
    local_noise: NDArray[np.float64]
    #: (3, N) the rises of blue, green and red at the peak row over the mean of the window's ends.
    rise: NDArray[np.float64]


@inline
def flank_offset(sigma_hint, n_sat, half, flank):  # type: ignore[no-untyped-def]
    """Rows from the peak to the inner row of each background flank of ``flank`` rows: beyond 3 ``sigma_hint`` and
    half of a clipped run of ``n_sat`` samples, inside the window of ``half`` rows either side (every fit places
    its flanks so; :func:`.refit.read_reach` takes them as the rows a fit reads)."""
    return int(min(math.ceil(3.0 * sigma_hint + 0.5 * n_sat + 1.0), half - flank + 1))


@callee
def _profiles(image, cols, top, k_rows, mu, amp, inv, g2):  # type: ignore[no-untyped-def]
    """The green profiles of rows ``top ... top + k_rows - 1`` (clamped to the image) of columns ``cols`` less the
    Gaussian ``amp exp(-(row - mu)^2 inv)`` of each column (``g2 = exp(-2 inv)``; (N,) each; ``amp`` 0: none):
    (k_rows, N) float64.

    Three ``exp`` per column: each column's Gaussian by recurrence from the first row where it exceeds ``e^-30``
    of its peak (a start further out could underflow to zero and stay there); none where nothing is subtracted."""
    n = cols.size
    P = empty((k_rows, n), np.float64)
    gather_green(image, cols, top, P)
    nb_any = False
    for t in range(n):
        nb_any |= amp[t] != 0.0
    if not nb_any:  # nothing to subtract (the first fit of every point)
        return P
    qs = empty(n, np.int64)
    ex = empty(2 * n, np.float64)
    for t in range(n):
        r30 = math.sqrt(30.0 / inv[t])
        q0 = min(max(int(math.ceil(mu[t] - r30 - top[t])), 0), k_rows) if amp[t] != 0.0 else k_rows  # noqa: RUF046
        qs[t] = q0
        d = top[t] + q0 - mu[t] if q0 < k_rows else 0.0
        ex[t] = -(d * d) * inv[t]
        ex[n + t] = -(2.0 * d + 1.0) * inv[t]
    ex = np.exp(ex)
    w = ex[:n].copy()
    ratio = ex[n:].copy()
    for q in range(k_rows):
        pq = P[q]
        for t in range(n):
            on = q >= qs[t]
            pq[t] = pq[t] - (amp[t] * w[t] if on else 0.0)
            w[t] = w[t] * ratio[t] if on else w[t]
            ratio[t] = ratio[t] * g2[t] if on else ratio[t]
    return P


@callee
def _clipped_runs(P, sat_dn):  # type: ignore[no-untyped-def]
    """Per column of the profiles ``P`` (k, n): how many samples are clipped (at least ``sat_dn``) and the rows of
    the first and the last of them, (n,) int64 each (first ``k`` and last -1 where none)."""
    k, n = P.shape
    cnt = zeros(n, np.int64)
    first = full(n, k, np.int64)
    last = full(n, -1, np.int64)
    for q in range(k):
        pq = P[q]
        for t in range(n):
            c = pq[t] >= sat_dn
            cnt[t] += c
            first[t] = min(first[t], q) if c else first[t]
            last[t] = q if c else last[t]
    return cnt, first, last


@inline
def _flank_line(p, o, flank):  # type: ignore[no-untyped-def]
    """The background line of the profile ``p`` (m,) through the means of its two flank windows
    ``R -+ (o .. o + flank - 1)``: ``(bl, slope, xl, noise)``, the line being ``bl + slope (q - xl)`` and ``noise``
    the spread of the flank samples about it."""
    R = p.size // 2
    a = 0.0
    b = 0.0
    for q in range(flank):
        a += p[R - o - q]
        b += p[R + o + q]
    a /= flank
    b /= flank
    slope = (b - a) / (2.0 * o + flank - 1)
    xl = R - o - 0.5 * (flank - 1)
    ss = 0.0
    for q in range(flank):
        r1 = p[R - o - q] - (a + slope * (R - o - q - xl))
        r2 = p[R + o + q] - (a + slope * (R + o + q - xl))
        ss += r1 * r1 + r2 * r2
    return a, slope, xl, math.sqrt(ss / max(2 * flank - 2, 1))


@inline
def _flank_lines(P, o, flank, line, noise):  # type: ignore[no-untyped-def]
    """:func:`_flank_line` of every column of the profiles ``P`` (m, n) at the flank offset ``o``, into ``line``
    (3, n) and ``noise`` (n,): the same arithmetic in the same order, row by row over all the columns (the loops run
    over contiguous rows of ``P`` and vectorize; a column at a time reads a row of ``P`` per sample)."""
    m, n = P.shape
    R = m // 2
    a = line[0]
    slope = line[1]
    xl = R - o - 0.5 * (flank - 1)
    b = zeros(n, np.float64)
    a[:] = 0.0
    for q in range(flank):
        pa = P[R - o - q]
        pb = P[R + o + q]
        for t in range(n):
            a[t] += pa[t]
            b[t] += pb[t]
    ss = zeros(n, np.float64)
    for t in range(n):
        a[t] /= flank
        slope[t] = (b[t] / flank - a[t]) / (2.0 * o + flank - 1)
        line[2, t] = xl
    for q in range(flank):
        pa = P[R - o - q]
        pb = P[R + o + q]
        for t in range(n):
            r1 = pa[t] - (a[t] + slope[t] * (R - o - q - xl))
            r2 = pb[t] - (a[t] + slope[t] * (R + o + q - xl))
            ss[t] += r1 * r1 + r2 * r2
    for t in range(n):
        noise[t] = math.sqrt(ss[t] / max(2 * flank - 2, 1))


@inline
def _crossings(S, level):  # type: ignore[no-untyped-def]
    """The first crossings below ``level`` of the profile ``S`` (m,) left and right of its middle sample, linearly
    interpolated: ``(xa, xb)`` in rows (-1 where there is none)."""
    m = S.size
    R = m // 2
    xa = -1.0
    for q in range(R - 1, -1, -1):
        if S[q] < level:
            xa = q + (level - S[q]) / (S[q + 1] - S[q])
            break
    xb = -1.0
    for q in range(R + 1, m):
        if S[q] < level:
            xb = q - (level - S[q]) / (S[q - 1] - S[q])
            break
    return xa, xb


@inline
def _level_width(S, level):  # type: ignore[no-untyped-def]
    """Width at ``level`` of the profile ``S`` (m,) between its :func:`_crossings`; inf where one is missing."""
    xa, xb = _crossings(S, level)
    return xb - xa if (xa >= 0 and xb >= 0) else np.inf


@inline
def _is_flat(a, a0, fw):  # type: ignore[no-untyped-def]
    """Whether the background-free profile ``a`` (m,) of peak ``a0`` and half-level width ``fw`` is flat-topped
    (a thick sheet): steep edges, its widths at 1/4 and 3/4 of the peak differ by at most half the half-level
    width (a Gaussian: 0.77 of it; glow and haze ridges are smooth like that), measured on the profile
    box-smoothed over ``2 FLAT_SMOOTH + 1`` rows (noise on a plateau must not decide)."""
    m = a.size
    k = FLAT_SMOOTH
    S = empty(m, np.float64)
    for q in range(m):
        acc = 0.0
        for j in range(max(q - k, 0), min(q + k, m - 1) + 1):
            acc += a[j]
        S[q] = acc / (2 * k + 1)
    a0s = max(S[m // 2], 0.5 * a0)
    return _level_width(S, 0.25 * a0s) - _level_width(S, 0.75 * a0s) <= 0.5 * fw + k


@njit
def fit_columns(image, cols, rows, half, sigma_hint, s, nb_v, nb_a, nb_s, max_fwhm):  # type: ignore[no-untyped-def]
    """The sub-pixel fit of the green profile at each (column, row) (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR, C-contiguous; cols, rows: (N,) int64 the picked columns and rows.
        half: the window's half-length, rows; sigma_hint: the frame's typical sigma, px (the log-parabola's
            spacing, the flanks' offset and the saturated profiles' window).
        s: the :class:`~lrsensor.extract.settings.Settings` (saturation, widths, iterations).
        nb_v, nb_a, nb_s: (N,) row, amplitude (DN) and sigma (px) of another laser's stripe close by in the same
            column, subtracted first (NaN row: none).
        max_fwhm: (N,) the widest half-level width the laser sheet allows at each point, px (flat tops pass
            while theirs is at most that).

    Returns:
        :class:`Fits`.
    """
    n = cols.size
    m = 2 * half + 1
    R = half
    e = RECENTRE_PX
    flank = FLANK_PX
    sat_dn = s.saturation_dn
    min_sig = s.min_fwhm_px / FWHM_PER_SIGMA
    max_sig = s.max_sigma_px
    wide_fwhm = s.wide_fwhm_px
    # the neighbour's Gaussian: amplitude, 1 / (2 sigma^2) and exp(-2 / (2 sigma^2)) per column (amplitude 0: none)
    amp_nb = empty(n, np.float64)
    inv_nb = empty(n, np.float64)
    g2_nb = empty(n, np.float64)
    for t in range(n):
        has = math.isfinite(nb_v[t])
        amp_nb[t] = nb_a[t] if has else 0.0
        inv_nb[t] = 0.5 / (nb_s[t] * nb_s[t]) if has else 1.0
        g2_nb[t] = math.exp(-2.0 * inv_nb[t]) if has else 1.0
    # 1. re-centre on the integer peak of rows - e ... rows + e: the middle of its clipped run, else the first
    # maximum
    top = empty(n, np.int64)
    for t in range(n):
        top[t] = rows[t] - e
    C = _profiles(image, cols, top, 2 * e + 1, nb_v, amp_nb, inv_nb, g2_nb)
    bv = full(n, -1.0, np.float64)
    arg = full(n, e, np.int64)  # (nothing above -1, as can happen less a neighbour: the picked row)
    for q in range(2 * e + 1):
        cq = C[q]
        for t in range(n):
            up = cq[t] > bv[t]
            bv[t] = cq[t] if up else bv[t]
            arg[t] = q if up else arg[t]
    _, c_first, c_last = _clipped_runs(C, sat_dn)
    pk = empty(n, np.int64)
    for t in range(n):
        mid = (c_first[t] + c_last[t]) // 2 if c_first[t] <= c_last[t] else arg[t]
        pk[t] = rows[t] - e + mid
        top[t] = pk[t] - half
    P = _profiles(image, cols, top, m, nb_v, amp_nb, inv_nb, g2_nb)
    # 2. saturation and the background line (beyond half of a clipped run: a single clipped sample is a peak
    # just reaching the top of the range, not a run)
    n_sat, q_first, q_last = _clipped_runs(P, sat_dn)
    saturated = empty(n, np.bool_)
    off = empty(n, np.int64)
    for t in range(n):
        saturated[t] = P[R, t] >= sat_dn and n_sat[t] >= 2
        off[t] = flank_offset(sigma_hint, n_sat[t] if n_sat[t] >= 2 else 0, R, flank)
    line = empty((3, n), np.float64)
    noise = empty(n, np.float64)
    o_c = flank_offset(sigma_hint, 0, R, flank)  # every column's but those of clipped runs
    _flank_lines(P, o_c, flank, line, noise)
    for t in range(n):
        if off[t] != o_c:
            line[0, t], line[1, t], line[2, t], noise[t] = _flank_line(P[:, t], off[t], flank)
    A = empty((m, n), np.float64)
    _subtract_lines(P, line, A)
    # 3. the start: log-parabola at a spacing matched to the width; saturated: the middle of the clipped run
    sp = max(1, int(round(0.8 * sigma_hint)))  # noqa: RUF046 (numba: round() of a float is a float)
    # of the samples a_-, a_0, a_+ (at least 0.5): ln(a_- / a_+), ln(a_- a_+ / a_0^2), in float32 (the centroid
    # iterations take the start to 1e-7 px; sigma, the width limits' and the quality's, to 1e-5 of itself)
    # (scalar logf: numpy's logarithm of a float32 array would compile its ufunc loop for that type too)
    lv = empty(2 * n, np.float32)
    for t in range(n):
        am = max(A[R - sp, t], 0.5)
        a0 = max(A[R, t], 0.5)
        ap = max(A[R + sp, t], 0.5)
        lv[t] = math.log(np.float32(am / ap))
        lv[n + t] = math.log(np.float32((am / a0) * (ap / a0)))
    c = empty(n, np.float64)
    sigma = empty(n, np.float64)
    ok = empty(n, np.bool_)
    for t in range(n):
        odd = float(lv[t])
        den = float(lv[n + t])
        curved = den < -1e-6
        c[t] = R + (min(max(0.5 * sp * odd / (den if curved else -1.0), -1.0), 1.0) if curved else 0.0)
        sigma[t] = sp / math.sqrt(-den) if curved else np.inf
        ok[t] = curved and sigma[t] >= min_sig and sigma[t] <= max_sig
        if saturated[t]:
            c[t] = 0.5 * (q_first[t] + q_last[t])
            sigma[t] = max(0.5 * n_sat[t] / 1.1774, sigma_hint)
            ok[t] = True
    # half-level widths (not saturated): wide profiles start from the middle of their crossings; flat-topped ones
    # (few) also take the window centroid, their flanks beyond the top
    window = saturated.copy()  # the columns of the window centroid (else Gaussian weights)
    hs = empty(n, np.float64)  # its half-width
    lim_c = empty(n, np.float64)  # the largest accepted distance of the centre from the peak row
    # (a profile below half level k_w rows either side of the peak row is narrower than 2 k_w <= wide_fwhm: most
    # are, and skip the search for their crossings)
    k_w = min(max(int(0.5 * wide_fwhm), 0), R)
    for t in range(n):
        hs[t] = 0.5 * n_sat[t] + 2.5 * sigma_hint + 1.0
        lim_c[t] = 0.5 * n_sat[t] + 1.0 if saturated[t] else 2.0
        lvl = 0.5 * A[R, t]
        if saturated[t] or not lvl > 0 or (A[R - k_w, t] < lvl and A[R + k_w, t] < lvl):
            continue
        xa, xb = _crossings(A[:, t], lvl)
        fw = xb - xa if (xa >= 0 and xb >= 0) else np.inf
        if not fw > wide_fwhm:
            continue
        if math.isfinite(fw):  # the peak sample may be anywhere on the top
            c[t] = 0.5 * (xa + xb)
            lim_c[t] = 0.5 * fw + 1.0
        if not _is_flat(A[:, t].copy(), A[R, t], fw):
            continue
        window[t] = True
        ok[t] = fw <= max_fwhm[t]
        if math.isfinite(fw):
            sigma[t] = fw / FWHM_PER_SIGMA
            o = int(min(max(off[t], math.ceil(0.5 * fw + 4.0)), R - flank + 1))
            hs[t] = min(0.5 * fw + 3.0, o - 1.0) + 0.5
            bl, slope, xl, _noise = _flank_line(P[:, t], o, flank)
            for q in range(m):
                A[q, t] = P[q, t] - (bl + slope * (q - xl))
    # 4. centroid iterations
    inv2 = empty(n, np.float64)
    gain = empty(n, np.float64)
    reach = empty(n, np.float64)
    for t in range(n):
        sig_p = min(max(sigma[t] if math.isfinite(sigma[t]) else sigma_hint, min_sig), max_sig)
        sig_w = max(sig_p, 1.1)  # narrower Gaussian weights alias on the pixel grid (a biased first moment)
        inv2[t] = 0.5 / (sig_w * sig_w)
        gain[t] = 1.0 if window[t] else 1.0 + sig_p * sig_p * 2.0 * inv2[t]
        reach[t] = 4.0 * sig_w + 1.0  # Gaussian weights beyond are below exp(-8)
    _centroids(A, c, window, hs, inv2, gain, reach, s.iterations)
    # 5. acceptance and the results
    centre = empty(n, np.float64)
    amp = empty(n, np.float64)
    for t in range(n):
        amp[t] = A[R, t]
        good = ok[t] and math.isfinite(c[t]) and abs(c[t] - R) <= lim_c[t] and amp[t] > 0
        ok[t] = good
        centre[t] = pk[t] - half + c[t] if good else np.nan
    rise = empty((3, n), np.float64)
    colour_rises(image, cols, pk, half, (0, 1, 2), rise)
    return Fits(centre, amp, sigma, saturated, ok, noise, rise)


@inline
def _subtract_lines(P, line, A):  # type: ignore[no-untyped-def]
    """``A = P - (bl + slope (q - xl))`` for the profiles ``P`` (m, n) and their lines ``line`` (3, n)."""
    m, n = P.shape
    bl = line[0]
    slope = line[1]
    xl = line[2]
    for q in range(m):
        pq = P[q]
        aq = A[q]
        for t in range(n):
            aq[t] = pq[t] - (bl[t] + slope[t] * (q - xl[t]))


@callee
def _centroids(A, c, window, hs, inv2, gain, reach, iterations):  # type: ignore[no-untyped-def]
    """Centroid iterations on the background-free profiles ``A`` (m, n) from the centres ``c`` (n,) (window
    rows, updated in place): where ``window``, the plain centroid with weights 1 within ``hs - 1`` rows of the
    centre, 0 beyond ``hs`` and linear between; elsewhere Gaussian weights ``exp(-d^2 inv2)`` out to ``reach``
    rows (by recurrence from the first row's, taken as 1: the centroid takes only their ratios; one ``exp`` per
    column and iteration, in float32: a third of float64's time, and the weights' shape, hence the centre, to
    about 1e-6 of a px), the step times ``gain``. A step is at most a row;
    a column whose centre is not finite stays so."""
    m, n = A.shape
    q0 = empty(n, np.int64)
    q1 = empty(n, np.int64)
    w = empty(n, np.float64)
    ratio = empty(n, np.float64)
    g2 = empty(n, np.float64)
    s0 = empty(n, np.float64)
    s1 = empty(n, np.float64)
    ex = empty(n, np.float32)
    for t in range(n):
        g2[t] = math.exp(np.float32(-2.0 * inv2[t]))
    for _ in range(iterations):
        lo = m  # the rows any Gaussian weight reaches
        hi = 0
        for t in range(n):
            s0[t] = 0.0
            s1[t] = 0.0
            fin = math.isfinite(c[t])
            gauss = fin and not window[t]
            q0[t] = max(int(math.floor(c[t] - reach[t])), 0) if gauss else 0  # noqa: RUF046
            q1[t] = min(int(math.ceil(c[t] + reach[t])) + 1, m) if gauss else (m if fin else 0)  # noqa: RUF046
            d0 = q0[t] - c[t] if gauss else 0.0
            ex[t] = np.float32(-(2.0 * d0 + 1.0) * inv2[t])
            lo = min(lo, q0[t] if gauss else m)
            hi = max(hi, q1[t] if gauss else 0)
        for t in range(n):  # (the exponentials in a loop of their own: the loop above then vectorizes)
            w[t] = 1.0  # the first row's weight: the centroid takes the weights' ratios only
            ratio[t] = math.exp(ex[t])  # (scalar expf, as the logarithms)
        for q in range(lo, hi):  # every column with Gaussian weights (the window columns' sums are taken below)
            aq = A[q]
            for t in range(n):
                inr = (q >= q0[t]) & (q < q1[t])
                d = q - c[t]
                wa = w[t] * aq[t]
                s0[t] += wa if inr else 0.0
                s1[t] += wa * d if inr else 0.0
                w[t] = w[t] * ratio[t] if inr else w[t]
                ratio[t] = ratio[t] * g2[t] if inr else ratio[t]
        for tw in range(n):  # (few: saturated and flat-topped profiles)
            if not window[tw]:
                continue
            s0[tw] = 0.0
            s1[tw] = 0.0
            for q in range(q0[tw], q1[tw]):
                d = q - c[tw]
                wa = min(max(hs[tw] - abs(d), 0.0), 1.0) * A[q, tw]
                s0[tw] += wa
                s1[tw] += wa * d
        for t in range(n):
            if s0[t] != 0.0:
                step = gain[t] * s1[t] / s0[t]
                if math.isfinite(step):
                    c[t] += min(max(step, -1.0), 1.0)
