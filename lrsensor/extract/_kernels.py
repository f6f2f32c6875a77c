"""Compiled kernels of the sub-pixel extractor (numba), with the same results as the numpy/OpenCV code.

:func:`extract_frame` runs the whole default extractor on one frame in one call: :func:`detect_band` per laser
(one pass over the band, read in place: noise, 2x2 average, two-sided contrast, local maxima, bit for bit the
OpenCV steps of ``subpixel._candidates``), then :func:`process_candidates` (candidate chains, column-parallel
sub-pixel fits, neighbour refits, pooled gates, along-stripe smoothing, quality), the triangulation and the
range-limit gate. The loops are written so that the compiler vectorizes them across columns: unsigned indices
where an index could be negative (no wrap-around select per access), few arrays per loop (cheap run-time alias
checks) and selects instead of branches. Multiplies and adds may be fused (``fastmath={"contract"}``: one
rounding instead of two, nothing else of fast-math), so floating-point results agree with the numpy twins to
rounding, not bit for bit; the
detection is integer arithmetic and stays bit for bit.
These compile once (``cache=True``, tens of seconds the very first time, about a second from the on-disk cache).

Compilation never blocks a caller: :func:`ready` starts it in a background thread on first use and returns False
until every kernel is compiled for the argument types the extractor uses; meanwhile the extractor runs its numpy
path (same algorithm). :func:`warm_up` compiles synchronously (benchmarks, tests). Without numba
(:data:`HAVE_NUMBA` False) the numpy path is used throughout.
"""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import Any

import numpy as np

try:  # pragma: no cover - depends on the platform
    import numba
    from numba.cpython.unsafe.numbers import trailing_zeros as _ctz

    HAVE_NUMBA = True
    _njit: Any = numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract"})
    trailing_zeros: Any = _ctz  # the number of trailing zero bits of an unsigned integer (one instruction)
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def _njit(f: Any) -> Any:
        return f

    def _trailing_zeros_py(x: Any) -> int:
        """The number of trailing zero bits of a positive integer."""
        return (int(x) & -int(x)).bit_length() - 1

    trailing_zeros = _trailing_zeros_py


@_njit
def select_candidates(u, v, a, n_cols, k_max, max_jump, block, max_gap, min_run):  # type: ignore[no-untyped-def]
    """Merge plateaus, keep the k strongest candidates per column, link chains, pick per column.

    Args:
        u, v, a: (N,) int64 columns, int64 rows and float64 strengths of the candidates, sorted by column then row.
        n_cols: number of (virtual) columns; k_max: candidates kept per column; max_jump: row step of a link;
        block: columns per laser (no links across); max_gap: largest column step of a link; min_run: shortest
        accepted chain (nodes).

    Returns:
        ``(cols, rows, chain, chain_len)`` of the picked candidate per column that has one: (M,) int64, float64,
        int64, int64.
    """
    n = u.size
    # 1. merge plateaus: maxima of one column closer than 3 rows
    mu = np.empty(n, np.int64)
    mv = np.empty(n, np.float64)
    ma = np.empty(n, np.float64)
    m = 0
    i = 0
    while i < n:
        j = i
        s = float(v[i])
        best = a[i]
        while j + 1 < n and u[j + 1] == u[i] and v[j + 1] - v[j] <= 3:
            j += 1
            s += v[j]
            if a[j] > best:
                best = a[j]
        mu[m] = u[i]
        mv[m] = s / (j - i + 1)
        ma[m] = best
        m += 1
        i = j + 1
    # 2. k strongest per column, stored by rank: VT[q, c], AT[q, c] (entries q >= cnt[c] are never read)
    K = k_max
    VT = np.empty((K, n_cols))
    AT = np.empty((K, n_cols))
    cnt = np.zeros(n_cols, np.int64)  # candidates per column
    t = 0
    while t < m:
        c = mu[t]
        if t + 1 == m or mu[t + 1] != c:  # the only candidate of its column (the common case)
            VT[0, c] = mv[t]
            AT[0, c] = ma[t]
            cnt[c] = 1
            t += 1
            continue
        while t < m and mu[t] == c:
            # insert by strength (descending; after equal ones)
            pos = K
            for q in range(K):
                if q >= cnt[c] or not (AT[q, c] >= ma[t]):
                    pos = q
                    break
            if pos < K:
                for q in range(K - 1, pos, -1):
                    VT[q, c] = VT[q - 1, c]
                    AT[q, c] = AT[q - 1, c]
                VT[pos, c] = mv[t]
                AT[pos, c] = ma[t]
                cnt[c] = min(cnt[c] + 1, K)
            t += 1
    # 3. chains: mutual nearest links, first between neighbouring columns, then across small gaps. Within one
    # lag the columns are independent (column c only touches its own "has next" flags and column c + lag's "has
    # previous" flags and links), so each lag takes the columns with one candidate on both sides in one
    # branch-free pass and the others one by one. Flags and links by rank: [q, c]; links hold node ids c K + q.
    nn = n_cols * K
    prevT = np.empty((K, n_cols), np.int64)
    for q in range(K):
        for c in range(n_cols):
            prevT[q, c] = c * K + q
    has_next = np.zeros((K, n_cols), np.uint8)
    has_prev = np.zeros((K, n_cols), np.uint8)
    blk = sorted_blocks(np.arange(n_cols), block)  # the block (laser) of each column, no division per link
    one = np.zeros(n_cols, np.uint8)  # exactly one candidate
    multi = np.empty(n_cols, np.int64)  # the columns with more than one
    n_multi = 0
    for c in range(n_cols):
        one[c] = cnt[c] == 1
        if cnt[c] > 1:
            multi[n_multi] = c
            n_multi += 1
    v0 = VT[0]
    hn0 = has_next[0]
    hp0 = has_prev[0]
    pv0 = prevT[0]
    for lag in range(1, max_gap + 1):
        ul = np.uint64(lag)
        kl = np.int64(K * lag)
        for c in range(n_cols - lag):  # one candidate each side (the common case): nearest and mutual
            uc = np.uint64(c)
            ud = uc + ul
            ok = (one[uc] & one[ud] & ~hn0[uc] & ~hp0[ud]) & np.uint8(blk[uc] == blk[ud])
            ok &= np.uint8(abs(v0[uc] - v0[ud]) <= max_jump)
            hn0[uc] |= ok
            hp0[ud] |= ok
            pv0[ud] = pv0[ud] - kl if ok else pv0[ud]
        # the pairs with more candidates on a side: c multi, or c + lag multi
        for i in range(2 * n_multi):
            c = multi[i] if i < n_multi else multi[i - n_multi] - lag
            if c < 0 or c + lag >= n_cols:
                continue
            d = c + lag
            if cnt[c] == 0 or cnt[d] == 0 or blk[c] != blk[d]:
                continue
            if cnt[c] == 1 and cnt[d] == 1:  # handled above
                continue
            if i >= n_multi and cnt[c] > 1:  # counted once, as c multi
                continue
            for i0 in range(cnt[c]):
                va = VT[i0, c]
                if math.isnan(va) or has_next[i0, c]:
                    continue
                jb = -1
                db = np.inf
                for j0 in range(cnt[d]):
                    vb = VT[j0, d]
                    if math.isnan(vb) or has_prev[j0, d]:
                        continue
                    dd = abs(va - vb)
                    if dd < db:
                        db = dd
                        jb = j0
                if jb < 0 or db > max_jump:
                    continue
                # mutual: is i0 the nearest free node of column c for jb?
                ib = -1
                dbb = np.inf
                vb = VT[jb, d]
                for q in range(cnt[c]):
                    vq = VT[q, c]
                    if math.isnan(vq) or has_next[q, c]:
                        continue
                    dd = abs(vq - vb)
                    if dd < dbb:
                        dbb = dd
                        ib = q
                if ib != i0:
                    continue
                prevT[jb, d] = c * K + i0
                has_next[i0, c] = 1
                has_prev[jb, d] = 1
    # chain roots, lengths and summed strengths (links point to lower columns: one pass in column order). The
    # current chain's length and strength stay in registers while its nodes follow each other (the common case),
    # not read back from memory node after node; stored when another chain's node comes (the same additions in the
    # same order)
    root = np.empty(nn, np.int64)
    length = np.zeros(nn, np.int64)
    strength = np.zeros(nn)
    r_cur = -1
    l_cur = 0
    s_cur = 0.0
    for c in range(n_cols):
        for q in range(cnt[c]):
            node = c * K + q
            p = prevT[q, c]
            r = root[p] if p != node else node
            root[node] = r
            if r != r_cur:
                if r_cur >= 0:
                    length[r_cur] = l_cur
                    strength[r_cur] = s_cur
                r_cur = r
                l_cur = length[r]
                s_cur = strength[r]
            l_cur += 1
            s_cur += AT[q, c]
    if r_cur >= 0:
        length[r_cur] = l_cur
        strength[r_cur] = s_cur
    # 4. per column the candidate on the strongest long-enough chain
    cols = np.empty(n_cols, np.int64)
    rows = np.empty(n_cols, np.float64)
    chain = np.empty(n_cols, np.int64)
    clen = np.empty(n_cols, np.int64)
    out = 0
    for c in range(n_cols):
        if cnt[c] == 1:  # the common case, without branches: stored, and counted if its chain is long enough
            r = root[c * K]
            cols[out] = c
            rows[out] = VT[0, c]
            chain[out] = r
            clen[out] = length[r]
            out += length[r] >= min_run
            continue
        best_s = -1.0
        best_q = -1
        for q in range(cnt[c]):
            node = c * K + q
            r = root[node]
            if length[r] >= min_run and strength[r] > best_s:
                best_s = strength[r]
                best_q = q
        if best_q >= 0:
            node = c * K + best_q
            cols[out] = c
            rows[out] = VT[best_q, c]
            chain[out] = root[node]
            clen[out] = length[root[node]]
            out += 1
    return cols[:out], rows[:out], chain[:out], clen[:out]


@_njit
def noise_col_step(n_triples, cols):  # type: ignore[no-untyped-def]
    """Column step (even, 2 to 8) of the noise samples of a band of ``n_triples`` row triples and ``cols``
    columns: about 6000 samples or more, every 2nd column in small images."""
    return 2 * max(1, min(4, (n_triples * cols) // 12000))


#: Half-width (rows) of the box smoothing of a profile before its flat-top test.
FLAT_SMOOTH = 2
#: Smallest half-width of the along-stripe line fits whose four quarters are tested on their own too (a kink
#: near one end of a long window is diluted in the whole window's residual, not in its quarter's).
SUBBLOCK_MIN_K = 192
#: Tolerance of that quarter test, in standard deviations of the chi-square residual.
SUBBLOCK_SIGMAS = 6.0


@_njit
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


@_njit
def _level_width(P, o, R, m, bl, slope, xl, level):  # type: ignore[no-untyped-def]
    """Width at ``level`` between :func:`_level_crossings`; inf when one is missing."""
    xa, xb = _level_crossings(P, o, R, m, bl, slope, xl, level)
    return xb - xa if (xa >= 0 and xb >= 0) else np.inf


@_njit
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


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _flank_offset(sigma_hint, n_sat, half, flank):  # type: ignore[no-untyped-def]
    """Rows from the peak to the inner row of each background flank of ``flank`` rows: beyond 3 ``sigma_hint`` and
    half of ``n_sat`` clipped samples, inside the window of ``half`` rows either side (every fit places its flanks
    so; :func:`read_reach` takes them as the rows a fit reads)."""
    return int(min(math.ceil(3.0 * sigma_hint + 0.5 * n_sat + 1.0), half - flank + 1))


@_njit
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


@_njit
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
    """Sub-pixel centre per column, the loop twin of :func:`lrsensor.extract.centre.fit_profiles`.

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
        off = _flank_offset(sigma_hint, n_sat, R, flank)
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


@_njit
def _gather_green(image, cols, top, out):  # type: ignore[no-untyped-def]
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


@_njit
def _colour_rises(image, cols, pk_rows, half, channels, rise):  # type: ignore[no-untyped-def]
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


@_njit
def _half_crossings(B, level):  # type: ignore[no-untyped-def]
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


@_njit
def _fit_common_chunk(  # type: ignore[no-untyped-def]
    image, cols, peaks, half, sigma_hint, sat_dn, min_sig, max_sig, flank, iterations, wide_fwhm, out, t0
):
    """:func:`fit_columns_common` on one chunk of columns (its arrays stay in the cache): the results written
    into ``out`` (as :func:`_fit_results`, columns ``t0`` on; no copy of a chunk's results)."""
    n = cols.size
    m = 2 * half + 1
    R = half
    special = np.zeros(n, np.bool_)
    # the window centred on the peak, rows peak - half ... peak + half: (m, n)
    top_row = np.empty(n, np.int64)
    for t in range(n):
        top_row[t] = peaks[t] - half
    W = np.empty((m, n), np.uint8)
    _gather_green(image, cols, top_row, W)  # bytes, then converted in a vector pass (cheaper than float stores)
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
    s16 = _clip_level(sat_dn)
    for q in range(m):
        wq = W[q]
        for t in range(n):
            n_clip[t] = min(n_clip[t], np.uint8(254)) + np.uint8(np.uint16(wq[t]) >= s16)
    for t in range(n):
        special[t] |= n_clip[t] >= np.uint8(2)
    # 1. linear background from the two flanks, subtracted; noise of the flanks
    off = _flank_offset(sigma_hint, 0, R, flank)
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
    xa, xb = _half_crossings(B, h0)
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
    _store_chunk(out, t0, image, cols, peaks, half, c, ok, a0, sigma, no_sat, noise, special, g_lo, g_pk, g_hi)


@_njit
def _store_chunk(out, t0, image, cols, peaks, half, c, good, a0, sigma, sat, noise, flag, g_lo, g_pk, g_hi):  # type: ignore[no-untyped-def]
    """Store the fits of one chunk of ``n`` columns into ``out`` (as :func:`_fit_results`) from column ``t0`` on:
    the centre row ``peaks - half + c`` where ``good`` (else NaN), ``good`` as ok, and ``a0``, ``sigma``, ``sat``,
    ``noise`` and ``flag`` (n,) each as they are; the green rise from the window's first, middle and last rows
    (``g_lo``, ``g_pk``, ``g_hi``, (n,) each), blue and red read at the same rows (:func:`_colour_rises`)."""
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
    _colour_rises(image, cols, peaks, half, (0, 2), o_ri[:, t0 : t0 + n])  # blue and red at the same rows


@_njit
def _fit_results(n):  # type: ignore[no-untyped-def]
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


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _put_fit(res, r, i, t):  # type: ignore[no-untyped-def]
    """Store result ``i`` of a column-parallel fit ``r`` (as :func:`_fit_results`) as column ``t`` of the
    per-column results ``res = (centre, amplitude, sigma, saturated, ok, local_noise, rise)``."""
    res[0][t] = r[0][i]
    res[1][t] = r[1][i]
    res[2][t] = r[2][i]
    res[3][t] = r[3][i]
    res[4][t] = r[4][i]
    res[5][t] = r[5][i]
    for c in range(3):
        res[6][c, t] = r[6][c, i]


@_njit
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
    out = _fit_results(cols.size)
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


@_njit
def _plain_fit64(B, a0, c, sg, sigma_hint, min_sig, max_sig, wide_fwhm, iterations):  # type: ignore[no-untyped-def]
    """The unclipped branch of :func:`fit_columns` column-parallel, in its float64 arithmetic: from the
    background-free profiles ``B`` (m, n), their peak values ``a0`` (n,) and the log-parabola start (centre ``c``,
    updated in place, and sigma ``sg``, inf without curvature; (n,) each): the Gaussian-weighted centroid (per
    column reach, weights by recurrence from two exps per column and iteration). Returns ``(centre, sigma, ok,
    done)``, (n,) each, ``centre`` in window rows; ``done`` False where :func:`fit_columns` would take its wide
    (flat-topped) branch instead."""
    m, n = B.shape
    ok = np.empty(n, np.bool_)
    inv2 = np.empty(n)
    gain = np.empty(n)
    reach = np.empty(n)
    g2 = np.empty(n)
    for t in range(n):
        ok[t] = math.isfinite(sg[t]) and sg[t] >= min_sig and sg[t] <= max_sig  # (finite: curved)
        sig_p = min(max(sg[t] if math.isfinite(sg[t]) else sigma_hint, min_sig), max_sig)
        sig_w = max(sig_p, 1.1)
        inv2[t] = 0.5 / (sig_w * sig_w)
        gain[t] = 1.0 + sig_p * sig_p * 2.0 * inv2[t]
        reach[t] = 4.0 * sig_w + 1.0
        g2[t] = -2.0 * inv2[t]
    g2 = np.exp(g2)
    # half-level width: wider profiles take the full kernel's flat-top branch
    lvl = np.empty(n)
    for t in range(n):
        lvl[t] = 0.5 * a0[t]
    xa, xb = _half_crossings(B, lvl)
    done = np.empty(n, np.bool_)
    for t in range(n):
        fw = xb[t] - xa[t] if (xa[t] >= 0 and xb[t] >= 0) else np.inf
        done[t] = a0[t] <= 0 or fw <= wide_fwhm
    # Gaussian-weighted centroid, each column over its own reach; a column stops for good once not finite
    act = np.ones(n, np.bool_)
    q0 = np.empty(n, np.int64)
    q1 = np.empty(n, np.int64)
    w = np.empty(n)
    ratio = np.empty(n)
    s0 = np.empty(n)
    s1 = np.empty(n)
    ex = np.empty(2 * n)
    for _ in range(iterations):
        for t in range(n):
            act[t] = act[t] and math.isfinite(c[t])
            s0[t] = 0.0
            s1[t] = 0.0
            if act[t]:
                q0[t] = max(int(math.floor(c[t] - reach[t])), 0)  # noqa: RUF046 (numba: floor is a float)
                q1[t] = min(int(math.ceil(c[t] + reach[t])) + 1, m)  # noqa: RUF046
                d0 = q0[t] - c[t]
                ex[t] = -(d0 * d0) * inv2[t]
                ex[n + t] = -(2.0 * d0 + 1.0) * inv2[t]
            else:
                q0[t] = 0
                q1[t] = 0
                ex[t] = 0.0
                ex[n + t] = 0.0
        ex = np.exp(ex)  # the weights' start and ratio
        for t in range(n):
            w[t] = ex[t] if act[t] else 0.0
            ratio[t] = ex[n + t] if act[t] else 0.0
        for q in range(m):
            bq_ = B[q]
            for t in range(n):
                inr = (q >= q0[t]) & (q < q1[t])
                wa = w[t] * bq_[t]
                s0[t] += wa if inr else 0.0
                s1[t] += wa * (q - c[t]) if inr else 0.0
                w[t] = w[t] * ratio[t] if inr else w[t]
                ratio[t] = ratio[t] * g2[t] if inr else ratio[t]
        for t in range(n):
            if act[t] and s0[t] != 0.0:
                step = gain[t] * s1[t] / s0[t]
                if math.isfinite(step):
                    c[t] += min(max(step, -1.0), 1.0)
    return c, sg, ok, done


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _clip_level(sat_dn):  # type: ignore[no-untyped-def]
    """The level from which a byte sample counts as clipped (at least ``sat_dn``), uint16: 256 (nothing clipped)
    for a level above 255."""
    return np.uint16(min(max(math.ceil(sat_dn), 0), 256))


@_njit
def _clipped_runs(W, sat_dn):  # type: ignore[no-untyped-def]
    """Per column of ``W`` (m, n) uint8: how many samples are clipped (at least ``sat_dn``) and the rows of the
    first and the last of them: (n,) uint16 each (first 65535 and last 0 where none; 32 lanes; a level above 255
    clips nothing)."""
    m, n = W.shape
    s16 = _clip_level(sat_dn)
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


@_njit
def _columns(W, idx):  # type: ignore[no-untyped-def]
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


@_njit
def _plain_fit(W, a0, bl, slope, xl, sigma_hint, min_sig, max_sig, wide_fwhm, iterations):  # type: ignore[no-untyped-def]
    """The unclipped branch of :func:`fit_columns` for the windows ``W`` (m, n) uint8 (peak at the middle row) less
    their linear backgrounds (``bl + slope (q - xl)``, (n,) each; ``a0`` (n,) the background-free peak):
    log-parabola start, then :func:`_plain_fit64`. Returns ``(centre, sigma, ok, done)``, (n,) each."""
    m, n = W.shape
    B = np.empty((m, n))
    for q in range(m):
        wq = W[q]
        bq_ = B[q]
        for t in range(n):
            bq_[t] = wq[t] - (bl[t] + slope[t] * (q - xl[t]))
    return _plain_fit_profiles(B, a0, sigma_hint, min_sig, max_sig, wide_fwhm, iterations)


@_njit
def _plain_fit_profiles(B, a0, sigma_hint, min_sig, max_sig, wide_fwhm, iterations):  # type: ignore[no-untyped-def]
    """The unclipped branch of :func:`fit_columns` for background-free profiles ``B`` (m, n) float64 (peak at the
    middle row; ``a0`` (n,) its value): log-parabola start, then :func:`_plain_fit64`.
    Returns ``(centre, sigma, ok, done)``, (n,) each."""
    m, n = B.shape
    R = m // 2
    s = max(1, int(round(0.8 * sigma_hint)))  # noqa: RUF046 (numba: round() of a float is a float)
    lv = np.empty(3 * n)
    for t in range(n):
        lv[t] = max(B[R - s, t], 0.5)
        lv[n + t] = max(a0[t], 0.5)
        lv[2 * n + t] = max(B[R + s, t], 0.5)
    lv = np.log(lv)
    c = np.empty(n)
    sg = np.empty(n)
    for t in range(n):
        ym = lv[t]
        y0 = lv[n + t]
        yp = lv[2 * n + t]
        den = ym - 2.0 * y0 + yp
        curved = den < -1e-6
        c[t] = R + (min(max(0.5 * s * (ym - yp) / (den if curved else -1.0), -1.0), 1.0) if curved else 0.0)
        sg[t] = s / math.sqrt(-den) if curved else np.inf
    return _plain_fit64(B, a0, c, sg, sigma_hint, min_sig, max_sig, wide_fwhm, iterations)


@_njit
def _neighbour_profiles(image, cols, top, k_rows, mu, amp, inv, g2):  # type: ignore[no-untyped-def]
    """The green profiles of rows ``top ... top + k_rows - 1`` (clamped to the image) of columns ``cols`` less the
    Gaussian ``amp exp(-(row - mu)^2 inv)`` of each column (``g2 = exp(-2 inv)``; (N,) each): (k_rows, N) float64.

    Column-parallel, three ``exp`` per column: each column's Gaussian by recurrence from the first row where it
    exceeds ``e^-30`` of its peak (a start further out could underflow to zero and stay there)."""
    n = cols.size
    W = np.empty((k_rows, n), np.uint8)
    _gather_green(image, cols, top, W)
    qs = np.empty(n, np.int64)
    ex = np.empty(2 * n)
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
    P = np.empty((k_rows, n))
    for q in range(k_rows):
        wq = W[q]
        pq = P[q]
        for t in range(n):
            on = q >= qs[t]
            pq[t] = wq[t] - (amp[t] * w[t] if on else 0.0)
            w[t] = w[t] * ratio[t] if on else w[t]
            ratio[t] = ratio[t] * g2[t] if on else ratio[t]
    return P


@_njit
def fit_columns_neighbour(  # type: ignore[no-untyped-def]
    image, cols, rows, half, e, sigma_hint, sat_dn, min_sig, max_sig, flank, iterations, nb_v, nb_a, nb_s, wide_fwhm
):
    """:func:`fit_columns` column-parallel (the inner loops run over columns) for the columns without a clipped
    sample: with the same arguments but the width limits, the same results up to rounding.

    The stripes of two lasers close together at long range take this path: there the columns of both that the
    other's Gaussian reaches are refitted with it subtracted, a few rounds, and :func:`fit_columns` costs about ten
    times more per column. Returns ``(centre_row, amplitude, sigma, saturated, ok, local_noise, rise, done)`` as
    :func:`_fit_results`: ``done`` (N,) False marks the columns to fit with :func:`fit_columns` instead (a clipped
    sample in the core or the window, or a profile wider than ``wide_fwhm`` at half level).
    """
    n = cols.size
    m = 2 * half + 1
    R = half
    out = _fit_results(n)
    # the neighbour's Gaussian: amplitude, 1 / (2 sigma^2) and exp(-2 / (2 sigma^2)) per column (0: none)
    amp_nb = np.empty(n)
    inv = np.empty(n)
    g2 = np.empty(n)
    for t in range(n):
        has = math.isfinite(nb_v[t])
        amp_nb[t] = nb_a[t] if has else 0.0
        inv[t] = 0.5 / (nb_s[t] * nb_s[t]) if has else 1.0
        g2[t] = -2.0 * inv[t]
    g2 = np.exp(g2)
    # re-centre on the integer peak of the core rows - e ... rows + e (the first of equal ones); a clipped core
    # sample: not here
    top = np.empty(n, np.int64)
    for t in range(n):
        top[t] = rows[t] - e
    Pc = _neighbour_profiles(image, cols, top, 2 * e + 1, nb_v, amp_nb, inv, g2)
    bv = np.full(n, -1.0)
    o = np.zeros(n, np.int64)
    done = out[7]
    done[:] = True
    for q in range(2 * e + 1):
        pq = Pc[q]
        for t in range(n):
            x = pq[t]
            up = x > bv[t]
            bv[t] = x if up else bv[t]
            o[t] = q if up else o[t]
            done[t] &= x < sat_dn
    pk = np.empty(n, np.int64)
    for t in range(n):
        pk[t] = rows[t] + (o[t] if bv[t] != -1.0 else e) - e  # nothing above -1: the candidate row
        top[t] = pk[t] - half
    # the window pk - half ... pk + half, clipped samples anywhere in it: not here
    off = _flank_offset(sigma_hint, 0, R, flank)
    xl = R - off - 0.5 * (flank - 1)
    Wn = _neighbour_profiles(image, cols, top, m, nb_v, amp_nb, inv, g2)
    for q in range(m):
        wq = Wn[q]
        for t in range(n):
            done[t] &= wq[t] < sat_dn
    # 1. linear background from the two flanks, and the noise of the flanks
    bl = np.zeros(n)
    br = np.zeros(n)
    for q in range(flank):
        for t in range(n):
            bl[t] += Wn[R - off - q, t]
            br[t] += Wn[R + off + q, t]
    slope = np.empty(n)
    for t in range(n):
        bl[t] /= flank
        br[t] /= flank
        slope[t] = (br[t] - bl[t]) / (2.0 * off + flank - 1)
    B = np.empty((m, n))
    for q in range(m):
        for t in range(n):
            B[q, t] = Wn[q, t] - (bl[t] + slope[t] * (q - xl))
    ss = np.zeros(n)
    for q in range(flank):
        for t in range(n):
            ss[t] += B[R - off - q, t] ** 2 + B[R + off + q, t] ** 2
    # 2. log-parabola start, 3. Gaussian-weighted centroid (the unclipped branch of fit_columns)
    a0 = B[R].copy()
    c, sigma, okp, plain = _plain_fit_profiles(B, a0, sigma_hint, min_sig, max_sig, wide_fwhm, iterations)
    for t in range(n):
        good = okp[t] and math.isfinite(c[t]) and abs(c[t] - R) <= 2.0 and a0[t] > 0
        out[0][t] = pk[t] - half + c[t] if good else np.nan
        out[1][t] = a0[t]
        out[2][t] = sigma[t]
        out[3][t] = False
        out[4][t] = good
        out[5][t] = math.sqrt(ss[t] / max(2 * flank - 2, 1))
        done[t] &= plain[t]
    _colour_rises(image, cols, pk, half, (0, 1, 2), out[6])  # from the image, as fit_columns takes them
    return out


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _window_sums(a, b, ht, dq, x):  # type: ignore[no-untyped-def]
    """One row of :func:`_clipped_centroid`'s sums (float32): the sample ``x`` at ``dq`` rows from the centre,
    weighted 1 within ``ht - 1`` rows, 0 beyond ``ht`` and linearly between: ``(a + w x, b + w x dq)``."""
    wa = min(max(ht - abs(dq), np.float32(0.0)), np.float32(1.0)) * x
    return a + wa, b + wa * dq


@_njit
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


@_njit
def _fit_clipped_chunk(image, cols, peaks, half, sigma_hint, sat_dn, flank, iterations, out, t0):  # type: ignore[no-untyped-def]
    """:func:`fit_columns_clipped` on one chunk of columns (its arrays stay in the cache): the results of the
    saturated columns written into ``out`` (as :func:`_fit_results`, columns ``t0`` on; the others' left to do),
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
    _gather_green(image, cols, top_row, W)
    n16, first, last = _clipped_runs(W, sat_dn)
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
        off[t] = _flank_offset(sigma_hint, n_sat[t], R, flank)
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
                _columns(W, idx), bl[idx], slope[idx], xl[idx], n_sat[idx], c0[idx], sigma_hint, iterations
            )
            for i in range(n_s):
                c[idx[i]] = c_k[i]
                sigma[idx[i]] = sig_k[i]
    # 4. acceptance (anywhere on the clipped top) and the colour rises (green from the window: its peak row and
    # ends)
    good = np.empty(n, np.bool_)
    for t in range(n):  # branch-free (vectorizes); |c - R| <= lim is False for NaN and inf
        good[t] = sat[t] & (abs(c[t] - R) <= 0.5 * n_sat[t] + 1.0) & (a0[t] > 0)
    _store_chunk(out, t0, image, cols, peaks, half, c, good, a0, sigma, sat, noise, sat, W[0], W[R], W[m - 1])
    return W, bl, slope, xl, sat


@_njit
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
    _gather_green(image, cols, top_row, C)
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
    _cnt, first, last = _clipped_runs(C, sat_dn)
    peak = np.empty(n, np.int64)
    clipped = np.empty(n, np.bool_)
    for t in range(n):
        cl = first[t] <= last[t]
        clipped[t] = first[t] < last[t]
        mid = (np.int64(first[t]) + np.int64(last[t])) >> 1
        peak[t] = rows[t] - e + (mid if cl else np.int64(d[t]))
    return peak, clipped


@_njit
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
    out = _fit_results(N)
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
        Wk[q] = Wp[q, :n_p]
    a0 = np.empty(n_p)
    for i in range(n_p):
        a0[i] = out[1][ip[i]]
    c, sigma, okp, done = _plain_fit(
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


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _quarter_ok(p0, p1, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz):  # type: ignore[no-untyped-def]
    """Whether the line ``a + b (x - c)`` fits the columns ``[p0, p1)`` within the noise ``vv`` (or they are empty)."""
    q0 = c_m[p1] - c_m[p0]
    qx = c_mx[p1] - c_mx[p0] - c * q0
    qxx = c_mxx[p1] - c_mxx[p0] - 2.0 * c * (c_mx[p1] - c_mx[p0]) + c * c * q0
    qt = c_z[p1] - c_z[p0]
    qtx = c_zx[p1] - c_zx[p0] - c * qt
    qyy = c_zz[p1] - c_zz[p0]
    r_q = qyy - 2.0 * a * qt - 2.0 * b * qtx + a * a * q0 + 2.0 * a * b * qx + b * b * qxx
    # r_q <= vv q1 (1 + S sqrt(2 / q1)), squared (no square root, no division): the excess over vv q1 is at most
    # vv S sqrt(2 q1)
    q1 = max(q0, 1.0)
    ex = r_q - vv * q1
    return (q0 < 1.0) | (ex <= 0.0) | (ex * ex <= (2.0 * SUBBLOCK_SIGMAS * SUBBLOCK_SIGMAS) * (vv * vv * q1))


@_njit
def _fit_windows(k, i0, i1, c_m, c_mx, c_mxx, c_z, c_zx, c_zz, c_d2, c_n2, var_all, a_c, b_c, rss_c, acc_c):  # type: ignore[no-untyped-def]
    """The line fits of :func:`smooth_runs` over every window ``[c - k, c + k]`` (same arithmetic), without
    branches: fills ``a_c``, ``b_c``, ``rss_c`` (N,) and ``acc_c`` (N,) bool for the centres ``c = i + k``,
    ``i`` in ``[i0, i1)`` (all of them: ``[0, N - 2 k)``).

    Unsigned indices (no negative-index wrap-around), no branches, and the quarter checks of long windows in a
    second pass (one loop with all of it has too many arrays for the compiler's alias checks): both vectorize.
    """
    full_n = 0.6 * (2 * k + 1)
    m = np.uint64(2 * k + 1)
    uk = np.uint64(k)
    for i in range(i0, i1):
        lo = np.uint64(i)
        hi = lo + m
        c = float(i + k)
        s0 = c_m[hi] - c_m[lo]
        sx = c_mx[hi] - c_mx[lo]
        sxx = c_mxx[hi] - c_mxx[lo]
        t0 = c_z[hi] - c_z[lo]
        tx = c_zx[hi] - c_zx[lo]
        yy = c_zz[hi] - c_zz[lo]
        s1 = sx - c * s0
        s2 = sxx - 2.0 * c * sx + c * c * s0
        t1 = tx - c * t0
        det = s0 * s2 - s1 * s1
        full = (s0 >= full_n) & (det > 1e-9)
        b = (s0 * t1 - s1 * t0) / (det if full else 1.0)
        a = (t0 - b * s1) / max(s0, 1.0)
        rss = max(yy - a * t0 - b * t1, 0.0)
        nvv = c_n2[hi] - c_n2[lo]
        var = (c_d2[hi] - c_d2[lo]) / (6.0 * max(nvv, 1.0)) if nvv >= 5 else var_all
        dof = max(s0 - 2.0, 1.0)
        vv = max(var, 1e-8)
        ci = lo + uk
        ex = rss - vv * dof  # rss <= vv dof (1 + 3 sqrt(2 / dof)), squared as in _quarter_ok
        acc_c[ci] = full & ((ex <= 0.0) | (ex * ex <= 18.0 * (vv * vv * dof)))
        a_c[ci] = a
        b_c[ci] = b
        rss_c[ci] = rss
    if k < SUBBLOCK_MIN_K:
        return
    # long windows: each quarter must fit the line too (a kink near one end is diluted in the whole window's
    # residual, not in its quarter's)
    uq = np.uint64((2 * k + 1) // 4)
    for i in range(i0, i1):
        lo = np.uint64(i)
        hi = lo + m
        c = float(i + k)
        ci = lo + uk
        a = a_c[ci]
        b = b_c[ci]
        nvv = c_n2[hi] - c_n2[lo]
        var = (c_d2[hi] - c_d2[lo]) / (6.0 * max(nvv, 1.0)) if nvv >= 5 else var_all
        vv = max(var, 1e-8)
        p1 = lo + uq
        p2 = p1 + uq
        p3 = p2 + uq
        acc = acc_c[ci]
        acc &= _quarter_ok(lo, p1, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc &= _quarter_ok(p1, p2, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc &= _quarter_ok(p2, p3, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc &= _quarter_ok(p3, hi, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc_c[ci] = acc


@_njit
def smooth_runs(y, run, scales):  # type: ignore[no-untyped-def]
    """Loop twin of :func:`lrsensor.extract.subpixel._smooth` (edge-preserving local linear smoothing).

    ``run`` labels are non-decreasing along the measured columns (runs are intervals). Each scale fits only the
    windows that the columns still to do can use, and the scales stop once every column is done.
    """
    n = y.size
    out = y.copy()
    lag = 4
    have = run >= 0
    if n <= 2 * lag + 2:
        return out
    # run extents and each run's first value (the base of the window sums): one pass over the runs' ends
    n_run = 0
    n_have = 0  # integer reductions (they vectorize; a float sum is one serial chain of adds)
    for q in range(n):
        n_run = max(n_run, run[q] + 1)
        n_have += run[q] >= 0
    first = np.full(max(n_run, 1), n, np.int64)
    last = np.full(max(n_run, 1), -1, np.int64)
    prev = -1
    for q in range(n):  # (a run's first column where its label first appears: no load of what was just stored)
        r = run[q]
        if r >= 0:
            if r != prev:
                first[r] = q
                prev = r
            last[r] = q
    # local noise: lag-4 second differences inside runs (branch-free over all columns; compacted for the pooled
    # median only where a window needs it)
    d2 = np.zeros(n)
    cnt2 = np.zeros(n)
    ul = np.uint64(lag)
    nv = 0
    for q in range(lag, n - lag):  # unsigned indices: no wrap-around test, the loop vectorizes
        uq = np.uint64(q)
        rq = run[uq]
        same = (rq >= 0) & (run[uq - ul] == rq) & (run[uq + ul] == rq)
        dd = y[uq - ul] - 2.0 * y[uq] + y[uq + ul]
        d2[uq] = dd * dd if same else 0.0
        cnt2[uq] = 1.0 if same else 0.0
        nv += same
    if nv < 8:
        return out
    var_all = np.nan  # the pooled noise: only windows with fewer than 5 samples of their own use it (computed then)
    c_m = np.empty(n + 1)  # running sums: every element is written below
    c_mx = np.empty(n + 1)
    c_mxx = np.empty(n + 1)
    c_z = np.empty(n + 1)
    c_zx = np.empty(n + 1)
    c_zz = np.empty(n + 1)
    c_d2 = np.empty(n + 1)
    c_n2 = np.empty(n + 1)
    c_m[0] = c_mx[0] = c_mxx[0] = c_z[0] = c_zx[0] = c_zz[0] = c_d2[0] = c_n2[0] = 0.0
    # the sums run in registers (read back from the arrays, each would wait on its own store); values relative to
    # the first of their run
    s_m = s_mx = s_mxx = s_z = s_zx = s_zz = s_d2 = s_n2 = 0.0
    for q in range(n):
        r = run[q]
        h = r >= 0
        b = y[min(first[max(r, 0)], n - 1)] if h else 0.0
        mq = 1.0 if h else 0.0
        zq = y[q] - b if h else 0.0
        s_m += mq
        s_mx += mq * q
        s_mxx += mq * q * q
        s_z += zq
        s_zx += zq * q
        s_zz += zq * zq
        s_d2 += d2[q]
        s_n2 += cnt2[q]
        c_m[q + 1] = s_m
        c_mx[q + 1] = s_mx
        c_mxx[q + 1] = s_mxx
        c_z[q + 1] = s_z
        c_zx[q + 1] = s_zx
        c_zz[q + 1] = s_zz
        c_d2[q + 1] = s_d2
        c_n2[q + 1] = s_n2
    done = ~have
    a_c = np.empty(n)
    b_c = np.empty(n)
    rss_c = np.empty(n)
    acc_c = np.zeros(n, np.bool_)
    left = n_have  # columns still to do
    for k in scales:
        if left == 0:
            break
        if k < 1 or 2 * k + 1 > n:
            continue
        for r in range(n_run):
            f = first[r]
            la = last[r]
            if la - f < 2 * k:  # no window of this scale fits in the run
                continue
            # the run's columns still to do span [u_lo, u_hi]; the windows they can use lie in the run and
            # have their centres within k of that span
            u_lo = f
            while u_lo <= la and done[u_lo]:
                u_lo += 1
            if u_lo > la:
                continue
            u_hi = la
            while done[u_hi]:
                u_hi -= 1
            i0 = max(u_lo - 2 * k, f)
            i1 = min(u_hi + 1, la - 2 * k + 1)
            if i1 <= i0:
                continue
            # those windows' fits, branch-free (vectorized: cheaper than skipping the windows no column needs)
            if math.isnan(var_all):
                few = False
                for i in range(i0, i1):
                    few |= c_n2[i + 2 * k + 1] - c_n2[i] < 5
                if few:
                    vals = np.empty(n)
                    m = 0
                    for q in range(lag, n - lag):
                        if cnt2[q] > 0.0:
                            vals[m] = d2[q]
                            m += 1
                    var_all = np.median(vals[:m]) / (6.0 * 0.4549) + 1e-8
            _fit_windows(k, i0, i1, c_m, c_mx, c_mxx, c_z, c_zx, c_zz, c_d2, c_n2, var_all, a_c, b_c, rss_c, acc_c)
            left -= _pick_windows(k, u_lo, u_hi, f, la, n, done, acc_c, rss_c, a_c, b_c, y[f], out)
    return out


@_njit
def _pick_windows(k, u_lo, u_hi, f, la, n, done, acc_c, rss_c, a_c, b_c, y0, out):  # type: ignore[no-untyped-def]
    """For the columns ``[u_lo, u_hi]`` still to do (``done`` False) of the run ``[f, la]`` (whose values are
    relative to its first, ``y0``): the value of the best accepted line of :func:`smooth_runs` at scale ``k``
    (centred, left or right window, inside the run; smallest residual, the first of equal ones) into ``out``, and
    ``done`` set. Returns how many columns got one.

    One branch-free pass over the columns per window position (centre at ``u``, ``u - k``, ``u + k``, in that
    order), each over the columns whose window lies in the run and in ``[0, n)``: contiguous reads, the loops
    vectorize.
    """
    span = u_hi - u_lo + 1
    best = np.full(span, np.inf)
    val = np.full(span, np.nan)
    for sh in (0, -k, k):
        a0 = max(u_lo, k - sh, f + k - sh)  # window of centre c = u + sh from c - k >= max(0, f)
        a1 = min(u_hi + 1, n - k - sh, la - k - sh + 1)  # to c + k <= min(n - 1, la)
        fs = float(-sh)
        for u in range(a0, a1):
            c = np.uint64(u + sh)
            i = np.uint64(u - u_lo)
            r = rss_c[c]
            ok = acc_c[c] & (r < best[i])
            v = a_c[c] + b_c[c] * fs + y0
            best[i] = r if ok else best[i]
            val[i] = v if ok else val[i]
    got = 0
    for u in range(u_lo, u_hi + 1):
        uu = np.uint64(u)
        v = val[np.uint64(u - u_lo)]
        take = (not done[uu]) & math.isfinite(v)
        out[uu] = v if take else out[uu]
        done[uu] |= take
        got += take
    return got


@_njit
def sorted_blocks(col_v, width):  # type: ignore[no-untyped-def]
    """The block ``col_v // width`` of each sorted virtual column (N,) int64, without a division per element
    (block ``l`` holds ``[l width, (l + 1) width)``: a laser's columns, at full or detection resolution)."""
    n = col_v.size
    out = np.empty(n, np.int64)
    b = 0
    for t in range(n):
        while col_v[t] >= (b + 1) * width:
            b += 1
        out[t] = b
    return out


@_njit
def expand_half(col_d, rows_f, chain, chain_len, wd, w):  # type: ignore[no-untyped-def]
    """Picks of half-resolution detection columns to full columns: column c stands for 2c and 2c + 1.

    The row of 2c + 1 is the mean of the rows at c and c + 1 when both are on one chain. Input and output are
    sorted by (virtual) column; ``chain_len`` is doubled (full columns).
    """
    n = col_d.size
    cols = np.empty(2 * n, np.int64)
    rows = np.empty(2 * n, np.float64)
    ch = np.empty(2 * n, np.int64)
    cl = np.empty(2 * n, np.int64)
    k = 0
    lasers = sorted_blocks(col_d, wd)
    for i in range(n):
        laser = lasers[i]
        c = col_d[i] - laser * wd
        cols[k] = laser * w + 2 * c
        rows[k] = rows_f[i]
        ch[k] = chain[i]
        cl[k] = 2 * chain_len[i]
        k += 1
        if 2 * c + 1 < w:
            r = rows_f[i]
            if i + 1 < n and col_d[i + 1] == col_d[i] + 1 and chain[i + 1] == chain[i]:
                r = 0.5 * (rows_f[i] + rows_f[i + 1])
            cols[k] = laser * w + 2 * c + 1
            rows[k] = r
            ch[k] = chain[i]
            cl[k] = 2 * chain_len[i]
            k += 1
    return cols[:k], rows[:k], ch[:k], cl[:k]


@_njit
def _rows_overlap(laser, v, good, n_lasers, max_dist):  # type: ignore[no-untyped-def]
    """Whether the row ranges of two lasers' ``good`` points come within ``max_dist`` of each other (else no point
    has an other-laser neighbour for :func:`refit_targets`: a cheap test that spares its dense arrays)."""
    lo = np.full(n_lasers, np.inf)
    hi = np.full(n_lasers, -np.inf)
    n = v.size
    t = 0
    while t < n:  # runs of one laser (the points are sorted by laser): each run's bounds kept in registers
        li = laser[t]
        a = np.inf
        b = -np.inf
        while t < n and laser[t] == li:
            x = v[t] if good[t] else np.nan
            a = min(a, x) if x == x else a
            b = max(b, x) if x == x else b
            t += 1
        lo[li] = min(lo[li], a)
        hi[li] = max(hi[li], b)
    for a in range(n_lasers):
        for b in range(n_lasers):
            if a != b and lo[a] <= hi[b] + max_dist and lo[b] <= hi[a] + max_dist:
                return True
    return False


#: A neighbour stripe is subtracted only where its Gaussian exceeds this fraction of the point's own amplitude
#: (at least 1 DN) somewhere in the rows the point's centroid reads (:func:`read_reach`, :func:`refit_targets`).
#: Below it, the refit moves centres by hundredths of a pixel at most, and not toward the truth (walls at 4.5-6 m
#: and the tank against no gate: at most 0.048 px, on few points, the gated output as close to the truth or
#: closer): a thin stripe (sigma 0.8 px) 11 rows away, as two lasers' stripes are on a wall at 5 m, adds less than
#: 1e-3 of its peak 7 rows away.
NEIGHBOUR_TAIL = 1e-2
#: The same threshold for the rows of the background flanks only (beyond the centroid's reach). There the tail
#: tilts the background line instead of adding to the peak: a contamination ``eps`` (fraction of the amplitude)
#: of one flank's mean moves a centroid of weight sigma ``s`` by about ``sqrt(2) eps s^2 / D`` pixels, ``D`` the
#: rows between the flanks' centres (10 or more). A tail of 5 % at the outer flank row averages less than 2.5 % over
#: the flank's 3 rows, so a centre moves by at most about 0.01 px (``s`` up to 2 px) and typically 0.003 px (``s``
#: 1.1 px): a tenth to a thirtieth of the centre's noise where the stripes meet (about 0.09 px on a wall at 5 m).
#: There the two stripes' tails reach 1-5 % of the other's peak at the outer flank rows, depending on each frame's
#: window (``refit_targets``).
NEIGHBOUR_FLANK_TAIL = 5e-2
#: ``log(NEIGHBOUR_TAIL / NEIGHBOUR_FLANK_TAIL)``: the flank rows' tail scaled to :data:`NEIGHBOUR_TAIL`'s test.
LOG_FLANK_TAIL = math.log(NEIGHBOUR_TAIL / NEIGHBOUR_FLANK_TAIL)
#: Rounds of refits of the points with another laser's stripe close by (:func:`process_candidates`).
NEIGHBOUR_REFITS = 4
#: A point is refitted again only if its neighbour moved by more than this since its last refit: row and sigma
#: in pixels, amplitude relative (:func:`refit_targets`). A point's fit depends on nothing else that changes
#: between the rounds, and it moves by less than its neighbour does.
NEIGHBOUR_TOL = 1e-2


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def read_reach(sig, sat, near, far, wide_sigma):  # type: ignore[no-untyped-def]
    """How many rows from its centre a point's fit reads, one row of re-centring included: ``(core, flanks)``, the
    Gaussian-weighted centroid out to 3 of its weight's sigma (``max(sig, 1.1)``; the weights beyond are below
    1.1 % of the peak's) and the log-parabola and background flanks out to ``near`` rows from the peak (a
    neighbour's Gaussian matters only there, and less in the flanks: :data:`NEIGHBOUR_FLANK_TAIL`); the whole
    window (``far``) for both for a saturated or wide profile (``sig`` above ``wide_sigma`` or not finite: their
    flanks move out with the plateau). Twin of :func:`lrsensor.extract.subpixel._read_reach`."""
    if sat or not sig <= wide_sigma:  # (True for a NaN sigma)
        return far, far
    return min(far, 1.0 + math.ceil(3.0 * max(sig, 1.1))), min(far, 1.0 + near)


@_njit
def point_table(laser, cols, n_lasers, width):  # type: ignore[no-untyped-def]
    """The index of the point of each laser and column, (L, W) int32 (-1 = none; the points of
    :func:`process_candidates` are one per laser and column)."""
    at = np.full((n_lasers, width), -1, np.int32)
    for t in range(laser.size):
        at[laser[t], cols[t]] = t
    return at


@_njit
def refit_targets(laser, cols, v, amp, sig, sat, good, at, max_dist, read, look, last):  # type: ignore[no-untyped-def]
    """The points to refit with another laser's stripe subtracted in one round, and that stripe (loop twin of
    :func:`lrsensor.extract.subpixel._neighbours` and its round's selection).

    A point's neighbour is the nearest ``good`` point of another laser in its column closer than ``max_dist``
    rows, kept only where its Gaussian exceeds :data:`NEIGHBOUR_TAIL` of the point's amplitude (at least
    1 DN) in the rows the point's fit reads (:func:`read_reach` of its sigma and saturation, ``read`` = ``(near,
    far, wide_sigma)``). A point is picked when its neighbour's
    row, amplitude or sigma differ from ``last`` (3, N) (the neighbour of its previous refit, NaN = none yet) by
    more than :data:`NEIGHBOUR_TOL`; ``last`` is updated there. Only the points in the columns ``look`` (K,)
    (sorted) are looked at: a neighbour can change only in the columns of the last round's refits.

    Args:
        laser, cols, v, amp, sig, sat, good: (N,) per point: laser, column, row (NaN = no fit), amplitude (DN),
            sigma (px, NaN = 1), saturated, and whether it can be a neighbour.
        at: (L, W) the point of each laser and column (:func:`point_table`).

    Returns:
        ``(idx, nb_v, nb_a, nb_s)``: the picked points (M,), in the order of the points, and their neighbours'
        row, amplitude and sigma (M,).
    """
    near, far, wide_sigma = read
    n_lasers = at.shape[0]
    n = min(v.size, n_lasers * look.size)
    cand = np.empty(n, np.int64)
    nbj = np.empty(n, np.int64)
    arg = np.empty(n)  # the log of the neighbour's Gaussian at the nearest row read, the flanks' scaled
    m = 0
    for li in range(n_lasers):  # laser by laser, columns in order: the points' order
        for c in look:
            t = at[li, c]
            if t < 0 or not math.isfinite(v[t]):
                continue
            best = max_dist
            jb = -1
            for other in range(n_lasers):
                j = at[other, c]
                if other == li or j < 0 or not good[j]:
                    continue
                dist = abs(v[j] - v[t])
                if dist < best:  # (False for a NaN row)
                    best = dist
                    jb = j
            if jb >= 0:
                cand[m] = t
                nbj[m] = jb
                core, flanks = read_reach(sig[t], sat[t], near, far, wide_sigma)
                s_j = sig[jb] if math.isfinite(sig[jb]) else 1.0
                g_c = max(best - core, 0.0) / s_j
                g_f = max(best - flanks, 0.0) / s_j
                arg[m] = max(-0.5 * g_c * g_c, -0.5 * g_f * g_f + LOG_FLANK_TAIL)
                m += 1
    tail = np.exp(arg[:m])
    idx = np.empty(m, np.int64)
    nb_v = np.empty(m)
    nb_a = np.empty(m)
    nb_s = np.empty(m)
    k = 0
    for i in range(m):
        t = cand[i]
        j = nbj[i]
        if not amp[j] * tail[i] > NEIGHBOUR_TAIL * max(amp[t], 1.0):
            continue
        s_j = sig[j] if math.isfinite(sig[j]) else 1.0
        same = (
            abs(v[j] - last[0, t]) <= NEIGHBOUR_TOL
            and abs(amp[j] - last[1, t]) <= NEIGHBOUR_TOL * max(abs(last[1, t]), 1.0)
            and abs(s_j - last[2, t]) <= NEIGHBOUR_TOL
        )
        if same:
            continue
        last[0, t] = v[j]
        last[1, t] = amp[j]
        last[2, t] = s_j
        idx[k] = t
        nb_v[k] = v[j]
        nb_a[k] = amp[j]
        nb_s[k] = s_j
        k += 1
    return idx[:k], nb_v[:k], nb_a[:k], nb_s[:k]


#: A 9-input sorting network with 25 compare-exchanges (Floyd's; checked on all 512 0-1 inputs in the tests),
#: for the default pooled window of 9 columns (odd-even transposition needs 36).
SORT9 = np.array(
    [
        *((0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (0, 3), (3, 6), (0, 3), (1, 4)),
        *((4, 7), (1, 4), (2, 5), (5, 8), (2, 5), (1, 3), (5, 7), (2, 6), (4, 6), (2, 4), (2, 3), (5, 6)),
    ],
    np.int64,
)


@_njit
def _sorting_network(n):  # type: ignore[no-untyped-def]
    """Compare-exchange pairs (P, 2) that sort ``n`` values: :data:`SORT9` for 9, else odd-even transposition."""
    if n == 9:
        return SORT9.copy()
    pairs = np.empty((n * (n // 2), 2), np.int64)
    p = 0
    for r in range(n):
        for j in range(r % 2, n - 1, 2):
            pairs[p, 0] = j
            pairs[p, 1] = j + 1
            p += 1
    return pairs[:p]


@_njit
def _pooled_median(ch, ds, own, nw, nd):  # type: ignore[no-untyped-def]
    """The pooled signal-to-noise medians of :func:`finish_points` for any window ``nw``: as
    :func:`_pooled_median9`, each compare-exchange a pass over all columns. Returns (nd,) float64."""
    # the pooled windows of every column: (2 pool + 1, n_cols), missing values (+inf) sorted last by
    # branch-free odd-even transposition compare-exchanges that run over all columns at once
    vals = np.empty((nw, nd), np.float32)
    cnt_d = np.zeros(nd, np.int32)
    inf32 = np.float32(np.inf)
    for j in range(nw):
        cj = ch[j : j + nd]
        xj = ds[j : j + nd]
        vj = vals[j]
        for q in range(nd):
            x = xj[q]
            use = (cj[q] == own[q]) & (x == x)  # same piece, passing (not NaN)
            vj[q] = x if use else inf32
            cnt_d[q] += np.int32(use)
    net = _sorting_network(nw)
    for p in range(net.shape[0]):
        va = vals[net[p, 0]]
        vb = vals[net[p, 1]]
        for q in range(nd):
            lo = min(va[q], vb[q])
            vb[q] = max(va[q], vb[q])
            va[q] = lo
    med = np.empty(nd)
    for q in range(nd):
        k = cnt_d[q]
        med[q] = float(vals[k // 2, q]) if k % 2 else 0.5 * (float(vals[k // 2 - 1, q]) + float(vals[k // 2, q]))
    return med


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _pooled_value(ch, ds, uq, j, o, inf):  # type: ignore[no-untyped-def]
    """Value ``j`` of the window at ``uq`` for :func:`_pooled_median9`: ``(value, used)``, +inf when it is not of
    the piece ``o`` or not passing (NaN)."""
    i = uq + np.uint64(j)
    x = ds[i]
    u = (ch[i] == o) & (x == x)
    return (x if u else inf), u


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _exchange(a, b):  # type: ignore[no-untyped-def]
    """One compare-exchange: ``(min, max)``."""
    return min(a, b), max(a, b)


@_njit
def _pooled_median9(ch, ds, nd):  # type: ignore[no-untyped-def]
    """The pooled signal-to-noise medians of :func:`finish_points` for windows of 9 columns (``pool`` 4), each
    column's window sorted in registers by the compare-exchanges of :data:`SORT9` (the same operations, in the
    same order, as its pass-per-exchange twin over rows of ``vals``), so only the median is stored.

    ``ch``, ``ds``: (nd + 8,) the padded chains and passing ratios (NaN: none). Returns the median of each
    column's window over the values of its own piece (NaN and other pieces left out), as
    ``0.5 (v[k / 2 - 1] + v[k / 2])`` for an even count ``k`` (inf for none): (nd,) float64.
    """
    med = np.empty(nd)
    inf32 = np.float32(np.inf)
    for q in range(nd):
        uq = np.uint64(q)
        o = ch[uq + np.uint64(4)]
        v0, u0 = _pooled_value(ch, ds, uq, 0, o, inf32)
        v1, u1 = _pooled_value(ch, ds, uq, 1, o, inf32)
        v2, u2 = _pooled_value(ch, ds, uq, 2, o, inf32)
        v3, u3 = _pooled_value(ch, ds, uq, 3, o, inf32)
        v4, u4 = _pooled_value(ch, ds, uq, 4, o, inf32)
        v5, u5 = _pooled_value(ch, ds, uq, 5, o, inf32)
        v6, u6 = _pooled_value(ch, ds, uq, 6, o, inf32)
        v7, u7 = _pooled_value(ch, ds, uq, 7, o, inf32)
        v8, u8 = _pooled_value(ch, ds, uq, 8, o, inf32)
        k = np.int32(u0) + np.int32(u1) + np.int32(u2) + np.int32(u3) + np.int32(u4)
        k += np.int32(u5) + np.int32(u6) + np.int32(u7) + np.int32(u8)
        # SORT9, written out
        v0, v1 = _exchange(v0, v1)
        v3, v4 = _exchange(v3, v4)
        v6, v7 = _exchange(v6, v7)
        v1, v2 = _exchange(v1, v2)
        v4, v5 = _exchange(v4, v5)
        v7, v8 = _exchange(v7, v8)
        v0, v1 = _exchange(v0, v1)
        v3, v4 = _exchange(v3, v4)
        v6, v7 = _exchange(v6, v7)
        v0, v3 = _exchange(v0, v3)
        v3, v6 = _exchange(v3, v6)
        v0, v3 = _exchange(v0, v3)
        v1, v4 = _exchange(v1, v4)
        v4, v7 = _exchange(v4, v7)
        v1, v4 = _exchange(v1, v4)
        v2, v5 = _exchange(v2, v5)
        v5, v8 = _exchange(v5, v8)
        v2, v5 = _exchange(v2, v5)
        v1, v3 = _exchange(v1, v3)
        v5, v7 = _exchange(v5, v7)
        v2, v6 = _exchange(v2, v6)
        v4, v6 = _exchange(v4, v6)
        v2, v4 = _exchange(v2, v4)
        v2, v3 = _exchange(v2, v3)
        v5, v6 = _exchange(v5, v6)
        h = k // 2
        a = v0
        a = v1 if h == 1 else a
        a = v2 if h == 2 else a
        a = v3 if h == 3 else a
        a = v4 if h == 4 else a
        a = v5 if h == 5 else a
        a = v6 if h == 6 else a
        a = v7 if h == 7 else a
        a = v8 if h == 8 else a
        b = v8  # index h - 1 = -1 (no value: wraps to the last, as the row view does)
        b = v0 if h == 1 else b
        b = v1 if h == 2 else b
        b = v2 if h == 3 else b
        b = v3 if h == 4 else b
        b = v4 if h == 5 else b
        b = v5 if h == 6 else b
        b = v6 if h == 7 else b
        b = v7 if h == 8 else b
        med[uq] = float(a) if k % 2 else 0.5 * (float(b) + float(a))
    return med


@_njit
def finish_points(  # type: ignore[no-untyped-def]
    col_v,
    lz,
    vv,
    amp,
    sig,
    sat,
    ok,
    lnoise,
    chain,
    chain_len,
    noise_l,
    w,
    n_cols,
    min_contrast,
    min_snr,
    min_run,
    max_sigma,
    scales,
    rise,
    green_ratio,
    pool,
    floor_frac,
    max_jump,
    wide_sigma,
):
    """Colour and signal-to-noise gates, runs, along-stripe smoothing and quality (loop twin of the numpy tail of
    ``extract``).

    The colour test (green must rise more than ``green_ratio`` times red and blue; ``rise`` (3, N) in B, G, R)
    and the signal-to-noise test are pooled over the fitted columns of the same chain within ``pool`` columns:
    the rises are summed, and the ratio is the median of the neighbours' (at most ``1 / floor_frac`` times the
    column's own). One noisy pixel then cannot drop a column of a dim stripe, nor keep one of a white blob.

    The smoothing runs along the kept columns of one laser with gaps of at most 3 columns, on one chain; wide
    profiles (saturated, or sigma above ``wide_sigma``: thick sheets close to the wall) also join the run of the
    column before them when both are wide and their rows differ by at most ``max_jump``, because the candidate row
    of a flat top wanders across it and splits the chain into short pieces, whose runs would be too short for the
    long line fits.

    ``lz`` (N,) is the laser of each point, ``col_v // w`` (:func:`sorted_blocks`).

    Returns ``(u, v, laser, quality)`` of the accepted points, (M,) each.
    """
    n = col_v.size
    snr = np.empty(n)
    # dense per (virtual) column, padded by pool: chain (-1 = none), rises of fitted columns, ratios
    ch = np.full(n_cols + 2 * pool, -1, np.int32)  # chain ids < n_cols * k: 16 lanes in the float32 pooling
    # the rises are halves of integers below 256 in magnitude: their sums over the window are exact in float32
    # (twice the vector lanes of float64)
    dr = np.zeros((3, n_cols + 2 * pool), np.float32)
    zero = np.float32(0.0)
    d_b = dr[0]
    d_g = dr[1]
    d_r = dr[2]
    for t in range(n):  # the points' signal-to-noise ratios and their dense rows, one pass (no branch)
        noise = max(max(noise_l[lz[t]], lnoise[t]), 0.5)
        snr[t] = amp[t] / noise
        qp = np.uint64(col_v[t] + pool)
        ch[qp] = chain[t]
        okt = ok[t]
        d_b[qp] = np.float32(rise[0, t]) if okt else zero
        d_g[qp] = np.float32(rise[1, t]) if okt else zero
        d_r[qp] = np.float32(rise[2, t]) if okt else zero
    # the colour test pooled over the window, for every (virtual) column at once: shifted contiguous reads of
    # the dense arrays, no branches (vectorizes); the sums add the same terms in the same order as per point
    nw = 2 * pool + 1
    nd = n_cols
    sums = np.zeros((3, nd), np.float32)
    own = ch[pool : pool + nd]
    sb = sums[0]
    sg = sums[1]
    sr = sums[2]
    db = dr[0]
    dg = dr[1]
    dR = dr[2]
    j = 0
    while j + 3 <= nw:  # three offsets per pass, the running sums in registers (one store per three terms)
        u1 = np.uint64(j)
        u2 = u1 + np.uint64(1)
        u3 = u1 + np.uint64(2)
        for q in range(nd):
            uq = np.uint64(q)
            o = own[uq]
            m1 = ch[uq + u1] == o
            m2 = ch[uq + u2] == o
            m3 = ch[uq + u3] == o
            b1, b2, b3 = db[uq + u1], db[uq + u2], db[uq + u3]
            g1, g2, g3 = dg[uq + u1], dg[uq + u2], dg[uq + u3]
            r1, r2, r3 = dR[uq + u1], dR[uq + u2], dR[uq + u3]
            x = sb[uq]
            x += b1 if m1 else zero
            x += b2 if m2 else zero
            x += b3 if m3 else zero
            sb[uq] = x
            x = sg[uq]
            x += g1 if m1 else zero
            x += g2 if m2 else zero
            x += g3 if m3 else zero
            sg[uq] = x
            x = sr[uq]
            x += r1 if m1 else zero
            x += r2 if m2 else zero
            x += r3 if m3 else zero
            sr[uq] = x
        j += 3
    while j < nw:
        uj = np.uint64(j)
        for c in range(3):
            sc = sums[c]
            dc = dr[c]
            for q in range(nd):
                uq = np.uint64(q)
                sc[uq] += dc[uq + uj] if ch[uq + uj] == own[uq] else zero
        j += 1
    good = np.empty(n, np.bool_)
    ds = np.full(n_cols + 2 * pool, np.nan, np.float32)  # float32: twice the lanes in the sorting network
    nan32 = np.float32(np.nan)
    for t in range(n):  # the colour gate and the passing ratios, one branch-free pass
        qc = np.uint64(col_v[t])
        g = ok[t] & (sat[t] | (float(sg[qc]) >= green_ratio * float(max(sb[qc], sr[qc]))))
        good[t] = g
        ds[qc + np.uint64(pool)] = np.float32(snr[t]) if g else nan32
    keep = np.empty(n, np.bool_)
    if nw == 9:  # the default pool: each window sorted in registers
        medv = _pooled_median9(ch, ds, nd)
    else:
        medv = _pooled_median(ch, ds, own, nw, nd)
    e_arg = np.empty(n, np.float32)
    for t in range(n):  # branch-free: the pooled ratio of the points that pass the colour gate, and the gates
        g = good[t]
        s = min(medv[np.uint64(col_v[t])], snr[t] / floor_frac) if g else snr[t]
        snr[t] = s
        keep[t] = g & (amp[t] >= min_contrast) & ((s >= min_snr) | sat[t]) & math.isfinite(vv[t])
        e_arg[t] = -s / 8.0
    # runs: kept columns of one laser with gaps of at most 3 columns, on one chain, or both wide (saturated or
    # flat-topped: their candidate rows wander on the top and split the chains) and within max_jump rows
    run_id = np.full(n, -1, np.int64)
    counts = np.empty(n, np.int64)  # points per run (a run's count kept in a register while it grows)
    cur = 0
    r = -1
    last_col = -10
    last_chain = -1
    last_l = -1
    last_v = np.nan
    last_wide = False
    for t in range(n):
        if not keep[t]:
            continue
        wide = sat[t] or sig[t] > wide_sigma  # (False for a NaN sigma)
        joined = chain[t] == last_chain or (wide and last_wide and abs(vv[t] - last_v) <= max_jump)
        if col_v[t] - last_col > 3 or lz[t] != last_l or not joined:
            if r >= 0:
                counts[r] = cur
            r += 1
            cur = 0
        cur += 1
        run_id[t] = r
        last_col = col_v[t]
        last_chain = chain[t]
        last_l = lz[t]
        last_v = vv[t]
        last_wide = wide
    if r >= 0:
        counts[r] = cur
    need = max(2, min_run // 2)
    y = np.full(n_cols, np.nan)
    run = np.full(n_cols, -1, np.int64)
    long_ = np.empty(n, np.bool_)  # in a run long enough
    m = 0
    for t in range(n):
        ri = run_id[t]
        lg = ri >= 0 and counts[ri] >= need
        long_[t] = lg
        if lg:
            y[col_v[t]] = vv[t]
            run[col_v[t]] = ri
            m += 1
    ys = smooth_runs(y, run, scales) if scales.size > 0 else y
    u_out = np.empty(m)
    v_out = np.empty(m)
    l_out = np.empty(m, np.int64)
    q_out = np.empty(m)
    e_snr = np.exp(e_arg)  # float32 is plenty for a score
    qual = np.empty(n)
    for t in range(n):  # every point's quality, branch-free (vectorizes), before the kept ones are packed
        s = sig[t] if math.isfinite(sig[t]) else max_sigma
        q_snr = 1.0 - float(e_snr[t])
        q_w = min(max(min(s / 0.6, 1.5 * max_sigma / max(s, 1e-6) - 0.5), 0.2), 1.0)
        q_run = min(max(chain_len[t] / (4.0 * min_run), 0.0), 1.0)
        qual[t] = min(max(q_snr * q_w * (0.5 + 0.5 * q_run), 0.0), 1.0)
    k = 0
    for t in range(n):
        if not long_[t]:
            continue
        laser = lz[t]
        u_out[k] = col_v[t] - laser * w
        v_out[k] = ys[col_v[t]]
        l_out[k] = laser
        q_out[k] = qual[t]
        k += 1
    return u_out, v_out, l_out, q_out


@_njit
def green_rows(flat, width, r0, r1):  # type: ignore[no-untyped-def]
    """The green channel of image rows ``[r0, r1)``: (r1 - r0, width) uint8, from ``flat``, the (H * W * 3,)
    view of a C-contiguous BGR image (a plain strided copy the compiler vectorizes; faster than OpenCV's)."""
    n = (r1 - r0) * width
    out = np.empty(n, np.uint8)
    base = np.uint64(r0 * width * 3 + 1)
    for i in range(n):
        out[np.uint64(i)] = flat[base + np.uint64(3 * i)]
    return out.reshape((r1 - r0, width))


@_njit
def noise_dn(g, step):  # type: ignore[no-untyped-def]
    """Loop twin of :func:`lrsensor.extract.subpixel._noise_dn` (robust noise from second differences, DN)."""
    rows, cols = g.shape
    return _noise_samples(np.ascontiguousarray(g).reshape(-1), cols, 1, 0, np.arange(rows), cols, step)


@_njit
def noise_dn_rows(flat, width, src, step):  # type: ignore[no-untyped-def]
    """:func:`noise_dn` of the green rows ``src`` (R,) of an image given as ``flat``, the (H * W * 3,) view of a
    C-contiguous BGR image of ``width`` columns, evened (as the band of :func:`detect_band`, whose extra column
    is never sampled: the column step is even): the same samples, read in place (no copy of the band)."""
    return _noise_samples(flat, 3 * width, 3, 1, src, width + width % 2, step)


@_njit
def _noise_samples(flat, row_bytes, px_bytes, offset, src, cols, step):  # type: ignore[no-untyped-def]
    """The noise of :func:`noise_dn` from the rows ``src`` (R,) of a flat byte image: sample ``x`` of row ``r`` is
    ``flat[src[r] * row_bytes + offset + px_bytes * x]``; ``cols`` (the band's width) sets the column step."""
    rows = src.size
    if rows < 5:
        return 1.0
    # four interleaved histograms: consecutive equal bins do not wait on each other's increments
    h4 = np.zeros((4, 1024), np.int64)
    n = (rows - 4 + step - 1) // step
    cs = noise_col_step(n, cols)
    ns = (cols + cs - 1) // cs
    for i in range(n):
        r = i * step
        ba = np.uint64(src[r] * row_bytes + offset)
        bb = np.uint64(src[r + 2] * row_bytes + offset)
        bc = np.uint64(src[r + 4] * row_bytes + offset)
        for j in range(ns):
            o = np.uint64(px_bytes * cs * j)
            d = abs(np.int32(flat[ba + o]) + np.int32(flat[bc + o]) - 2 * np.int32(flat[bb + o]))
            h4[j & 3, min(int(d), 1023)] += 1
    return _noise_from_histograms(h4)


@_njit
def _noise_from_histograms(h4):  # type: ignore[no-untyped-def]
    """The noise (DN) from four interleaved histograms (4, 1024) of |second differences|: their median, within its
    integer bin, over 0.6745 sqrt(6) (see :func:`lrsensor.extract.subpixel._noise_dn`)."""
    hist = np.empty(1024, np.int64)
    total = 0
    for k in range(1024):
        hist[k] = h4[0, k] + h4[1, k] + h4[2, k] + h4[3, k]
        total += hist[k]
    half = 0.5 * total
    cum = 0
    k = 0
    while k < 1023 and cum + hist[k] < half:
        cum += hist[k]
        k += 1
    lo, width = (0.0, 0.5) if k == 0 else (k - 0.5, 1.0)
    med = lo + width * (half - cum) / max(float(hist[k]), 1.0)
    return max(med / (0.6745 * math.sqrt(6.0)), 0.05)


@_njit
def local_maxima(resp_t, thr, row0, scale, v_lo, v_hi, width, col_offset):  # type: ignore[no-untyped-def]
    """Vertical local maxima above ``thr`` of a detection response, given transposed: (W', H') uint8.

    Row y of the response is full-resolution row ``row0 + scale * y``, column x stands for full column
    ``scale * x``; only maxima inside the laser's band (``v_lo``, ``v_hi``: (W,) first and last row per full
    column) count.

    Returns:
        ``(cols, rows, strength)``: detection columns plus ``col_offset`` (N,), full rows (N,) and response (N,),
        sorted by column, then row.
    """
    wo, ho = resp_t.shape
    cap = 4 * wo + 64
    cu = np.empty(cap, np.int64)
    cv = np.empty(cap, np.int64)
    ca = np.empty(cap, np.float64)
    n = 0
    t8 = np.uint8(min(max(int(math.floor(thr)), 0), 255))  # noqa: RUF046 (v > thr for an integer v)
    for x in range(wo):
        uf = min(x * scale, width - 1)
        lo = v_lo[uf]
        hi = v_hi[uf]
        if hi < lo:
            continue
        y0 = max((lo - row0 + scale - 1) // scale, 0)
        y1 = min((hi - row0) // scale + 1, ho)
        col = resp_t[x]
        for y in range(y0, y1):
            v = col[y]
            if v <= t8:
                continue
            if y > 0 and col[y - 1] > v:
                continue
            if y < ho - 1 and col[y + 1] > v:
                continue
            if n == cap:
                cap *= 2
                cu2 = np.empty(cap, np.int64)
                cv2_ = np.empty(cap, np.int64)
                ca2 = np.empty(cap, np.float64)
                cu2[:n] = cu[:n]
                cv2_[:n] = cv[:n]
                ca2[:n] = ca[:n]
                cu, cv, ca = cu2, cv2_, ca2
            cu[n] = x + col_offset
            cv[n] = row0 + scale * y
            ca[n] = v
            n += 1
    return cu[:n], cv[:n], ca[:n]


@_njit
def detect_band(image, r0, r1, d, snr_thr, area_noise, thr_min, v_lo, v_hi, col_offset):  # type: ignore[no-untyped-def]
    """Candidates of one laser at detection scale 2 in one pass over its band (the compiled twin of
    ``subpixel._candidates``: the same arithmetic as its OpenCV steps, bit for bit).

    The green channel of rows ``[r0 - d, r1 + d)`` (replicated beyond the image, evened), its robust noise
    (:func:`noise_dn`), the 2x2 area average (rounded as ``cv2.resize(INTER_AREA)``), a 3-column box
    (``cv2.blur``, reflected at the ends), the saturating two-sided contrast at ``d / 2`` and ``d / 4`` detection
    rows, and its vertical local maxima above ``max(thr_min, snr_thr * noise * area_noise)`` inside the band ``v_lo``,
    ``v_hi`` (W,).

    Args:
        image: (H, W, 3) uint8 C-contiguous; r0, r1: the band's bounding rows; d: contrast offset (even), rows.

    Returns:
        ``(cols, rows, strength, noise)``: detection columns plus ``col_offset`` (N,) int64, full rows (N,)
        int64, response (N,) float64, sorted by column then row; and the pixel noise, DN.
    """
    h = image.shape[0]
    w = image.shape[1]
    flat = image.reshape(-1)
    a0 = max(r0 - d, 0)
    a1 = min(r1 + d, h)
    if (a1 - a0) % 2 and a1 < h:
        a1 += 1
    top = max(d - (r0 - a0), 0)
    bot = max(d - (a1 - r1), 0)
    rows_g = a1 - a0 + top + bot
    rows_g += rows_g % 2
    # padded green row i -> image row src[i] (replicated border)
    src = np.empty(rows_g, np.int64)
    for i in range(rows_g):
        src[i] = min(max(a0 - top + i, a0), a1 - 1)
    # 2x2 area average straight from the image (green bytes 3 apart; an odd last column is paired with itself),
    # then the 3-column box: (gh, wo)
    gh = rows_g // 2
    wo = (w + 1) // 2
    w2 = w // 2
    B = np.empty((gh, wo), np.uint8)
    A = np.empty(wo + 2, np.int32)
    two = np.uint16(2)
    third = np.uint64(3)
    for y in range(gh):
        b0 = np.uint64(src[2 * y] * w * 3 + 1)
        b1 = np.uint64(src[2 * y + 1] * w * 3 + 1)
        for x in range(w2):  # in uint16 (16 lanes; the sum of four bytes and 2 fits)
            o = np.uint64(6 * x)
            s4 = np.uint16(
                np.uint16(flat[b0 + o])
                + np.uint16(flat[b0 + o + third])
                + np.uint16(flat[b1 + o])
                + np.uint16(flat[b1 + o + third])
                + two
            )
            A[np.uint64(x + 1)] = np.int32(np.uint16(s4 >> two))
        if wo > w2:
            o = np.uint64(3 * (w - 1))
            A[wo] = (2 * np.int32(flat[b0 + o]) + 2 * np.int32(flat[b1 + o]) + 2) >> 2
        if wo > 1:
            A[0] = A[2]
            A[wo + 1] = A[wo - 1]
        else:
            A[0] = A[1]
            A[2] = A[1]
        by = B[y]
        for x in range(wo):  # round(s / 3) = floor((s + 1) / 3) = ((s + 1) * 21846) >> 16 for 0 <= s <= 765
            ux = np.uint64(x)
            s3 = np.int32(A[ux] + A[ux + 1] + A[ux + 2] + 1)  # int32 throughout: 8 lanes, not 4
            by[ux] = np.uint8(np.int32(s3 * np.int32(21846)) >> np.int32(16))
    # the noise after the pass over the band, whose rows its samples read: cached now, not scattered misses
    noise = max(noise_dn_rows(flat, w, src, min(max(rows_g // 24, 2), 16)), 0.5)
    # two-sided contrast, saturating at 0 (uint8 arithmetic), and at half the offset
    ds = d // 2
    hd = ds // 2
    ho = gh - 2 * ds
    thr = max(thr_min, snr_thr * (noise * area_noise))
    t8 = min(max(int(math.floor(thr)), 0), 255)  # noqa: RUF046 (v > thr for an integer v)
    if ho <= 0:
        e_i = np.empty(0, np.int64)
        return e_i, e_i, np.empty(0), noise
    # in uint8, saturating (the response of ``c - max(..)`` clipped at 0 is ``c - min(c, ..)``): 32 lanes
    resp = np.empty((ho, wo), np.uint8)
    for y in range(ho):
        bc = B[y + ds]
        b0 = B[y]
        b1 = B[y + 2 * ds]
        ry = resp[y]
        if hd >= 2:
            h0 = B[y + ds - hd]
            h1 = B[y + ds + hd]
            for x in range(wo):
                ux = np.uint64(x)
                c = bc[ux]
                m = min(max(b0[ux], b1[ux]), max(h0[ux], h1[ux]))
                ry[ux] = c - min(c, m)
        else:
            for x in range(wo):
                ux = np.uint64(x)
                c = bc[ux]
                ry[ux] = c - min(c, max(b0[ux], b1[ux]))
    # vertical local maxima inside the band: counted per column, then placed column by column
    y0 = np.empty(wo, np.uint16)
    y1 = np.empty(wo, np.uint16)
    for x in range(wo):
        uf = min(2 * x, w - 1)
        lo = v_lo[uf]
        hi = v_hi[uf]
        if hi < lo:
            y0[x] = 0
            y1[x] = 0
        else:
            y0[x] = min(max((lo - r0 + 1) // 2, 0), 65535)
            y1[x] = min(max(min((hi - r0) // 2 + 1, ho), 0), 65535)
    cnt16 = np.zeros(wo, np.uint16)
    w8 = (wo + 7) // 8 * 8  # rows of the peak mask padded to whole 8-byte words
    pk = np.zeros((ho, w8), np.uint8)
    tu = np.uint8(t8)
    row_pk = np.empty(ho, np.uint8)  # any peak in the row: the rows without any are skipped below
    for y in range(ho):
        rm = resp[max(y - 1, 0)]
        rc = resp[y]
        rp = resp[min(y + 1, ho - 1)]
        py = pk[y]
        fy = np.uint16(y)
        for x in range(wo):
            ux = np.uint64(x)
            v = rc[ux]
            is_pk = (v > tu) & (rm[ux] <= v) & (rp[ux] <= v) & (fy >= y0[ux]) & (fy < y1[ux])
            py[ux] = is_pk
            cnt16[ux] += np.uint16(is_pk)
        any_pk = np.uint8(0)
        for x in range(wo):  # an integer OR (vectorizes)
            any_pk |= py[np.uint64(x)]
        row_pk[y] = any_pk
    cnt = np.zeros(wo + 1, np.int64)  # running count: the first candidate of each column
    for x in range(wo):
        cnt[x + 1] = cnt[x] + np.int64(cnt16[x])
    n = cnt[wo]
    cu = np.empty(n, np.int64)
    cv = np.empty(n, np.int64)
    ca = np.empty(n)
    pos = cnt[:wo].copy()
    words = pk.reshape(-1).view(np.uint64)
    nw8 = w8 // 8
    for y in range(ho):
        if row_pk[y] == 0:
            continue
        ry = resp[y]
        vy = r0 + 2 * y
        for k in range(nw8):
            wk = words[y * nw8 + k]  # the peaks of 8 columns, one byte (0 or 1) each
            while wk:  # the set bytes, lowest first (none in the common case)
                x = 8 * k + (trailing_zeros(wk) >> 3)
                wk &= wk - np.uint64(1)
                j = pos[x]
                cu[j] = x + col_offset
                cv[j] = vy
                ca[j] = ry[x]
                pos[x] = j + 1
    return cu, cv, ca, noise


@_njit
def frame_profile_stats(image, cols, rows, half, sat_dn, max_sigma, max_fwhm):  # type: ignore[no-untyped-def]
    """Loop twin of the frame statistics of ``subpixel.extract``: from the green profiles ``rows +- half`` of a
    few picked columns, the median Gaussian-equivalent sigma of the unsaturated ones (see
    ``subpixel._typical_sigma``; at most ``max_sigma`` or the median wide limit), the 90th percentile of their
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


@numba.njit(inline="always", error_model="numpy") if HAVE_NUMBA else _njit
def _distortion_residual(x, y, xd, yd, dist):  # type: ignore[no-untyped-def]
    """The Brown-Conrady model (``dist``: ``k1, k2, p1, p2, k3``) at the undistorted normalized point ``(x, y)``
    minus the distorted one ``(xd, yd)``: ``(rx, ry, r2, radial)`` with ``r2 = x^2 + y^2`` and the radial factor."""
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    rx = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) - xd
    ry = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y - yd
    return rx, ry, r2, radial


@_njit
def triangulate_points(u, v, laser, cam, dist, R, origin, normals, points):  # type: ignore[no-untyped-def]
    """Loop twin of :func:`lrsensor.triangulation.triangulate` (eq. 29 with the Brown-Conrady model).

    Args:
        u, v: (N,) float64 pixel coordinates; laser: (N,) int64 plane index of each pixel.
        cam: (4,) ``fx, fy, cx, cy``; dist: (5,) ``k1, k2, p1, p2, k3``; R: (3, 3) ``R_cam_from_body``.
        origin: (3,) camera centre in the body frame; normals, points: (L, 3) laser planes in the body frame.

    Returns:
        (N, 3) body-frame points, metres; NaN rows where undistortion does not converge, the ray is parallel
        to the plane or meets it behind the camera.
    """
    n = u.size
    out = np.empty((n, 3))
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    distorted = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
    n_l = normals.shape[0]
    off = np.empty(n_l)
    for i in range(n_l):
        off[i] = (
            (points[i, 0] - origin[0]) * normals[i, 0]
            + (points[i, 1] - origin[1]) * normals[i, 1]
            + (points[i, 2] - origin[2]) * normals[i, 2]
        )
    xs = np.empty(n)  # normalized undistorted image coordinates
    ys = np.empty(n)
    for t in range(n):
        xs[t] = (u[t] - cx) / fx
        ys[t] = (v[t] - cy) / fy
    if distorted:
        # Newton on the Brown-Conrady model, all points a step at a time (vectorizes): a point stops once its
        # step is below 1e-15 (converged quadratically), exactly as it would on its own
        xd = xs.copy()
        yd = ys.copy()
        act = np.ones(n, np.bool_)
        for _ in range(8):
            left = 0
            for t in range(n):
                x = xs[t]
                y = ys[t]
                rx, ry, r2, radial = _distortion_residual(x, y, xd[t], yd[t], dist)
                dr = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
                a = radial + 2.0 * x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
                b = 2.0 * x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
                d = radial + 2.0 * y * y * dr + 6.0 * p1 * y + 2.0 * p2 * x
                det = a * d - b * b
                sx = (d * rx - b * ry) / det
                sy = (-b * rx + a * ry) / det
                on = act[t]
                xs[t] = x - sx if on else x
                ys[t] = y - sy if on else y
                on &= not (abs(sx) + abs(sy) < 1e-15)
                act[t] = on
                left += on
            if left == 0:
                break
        for t in range(n):
            x = xs[t]
            y = ys[t]
            ex, ey, _, _ = _distortion_residual(x, y, xd[t], yd[t], dist)
            xs[t] = x if math.sqrt(ex * ex + ey * ey) < 1e-9 else np.nan
    # body-frame ray (x, y, 1) @ R met with the laser's plane: branch-free over the points (vectorizes)
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    o0, o1, o2 = origin[0], origin[1], origin[2]
    nx = normals[:, 0].copy()
    ny = normals[:, 1].copy()
    nz = normals[:, 2].copy()
    for t in range(n):
        x = xs[t]
        y = ys[t]
        bx = x * r00 + y * r10 + r20
        by = x * r01 + y * r11 + r21
        bz = x * r02 + y * r12 + r22
        li = np.uint64(laser[t])  # unsigned: no wrap-around select per access
        denom = bx * nx[li] + by * ny[li] + bz * nz[li]
        scale = math.sqrt(bx * bx + by * by + bz * bz)
        lam = off[li] / denom
        good = (abs(denom) > 1e-9 * scale) & (lam > 0)
        lam = lam if good else np.nan
        out[t, 0] = o0 + lam * bx
        out[t, 1] = o1 + lam * by
        out[t, 2] = o2 + lam * bz
    return out


@_njit
def max_fwhm_at(cols, rows, laser, floor, sheet_mm, geo):  # type: ignore[no-untyped-def]
    """Loop twin of ``subpixel._max_fwhm``: the widest plausible stripe (half-level width, px) at each pixel (N,).

    ``floor``: the width limit where the ray misses the plane (and the least limit); ``sheet_mm``: the thickest
    sheet (<= 0: the floor everywhere); ``geo``: ``(cam, dist, R, origin, normals, points, axis)``, the
    calibration as :func:`triangulate_points` takes it and the unit optical axis (3,) in the body frame.
    """
    cam, dist, R, origin, normals, points, axis = geo
    n = cols.size
    out = np.full(n, floor)
    if n == 0 or sheet_mm <= 0:
        return out
    pts = triangulate_points(
        cols.astype(np.float64), rows.astype(np.float64), laser, cam, dist, R, origin, normals, points
    )
    for t in range(n):
        depth = (
            (pts[t, 0] - origin[0]) * axis[0] + (pts[t, 1] - origin[1]) * axis[1] + (pts[t, 2] - origin[2]) * axis[2]
        )
        wv = 1e-3 * sheet_mm * cam[1] / depth + 4.0
        if math.isfinite(wv) and depth > 0:
            out[t] = max(wv, floor)
    return out


@_njit
def process_candidates(  # type: ignore[no-untyped-def]
    image,
    U,
    Vr,
    Ar,
    noise_l,
    ints,
    reals,
    scales,
    cam,
    dist,
    R,
    origin,
    normals,
    points,
    axis,
    wide_fwhm,
    tri,
):
    """Steps 3-6 of ``subpixel.extract`` (chains, sub-pixel fits, neighbour refits, gates, smoothing, quality) in
    one compiled call, the same kernels in the same order as the Python glue of its numpy-free path.

    Args:
        image: (H, W, 3) uint8 C-contiguous; U, Vr, Ar: the candidates of every laser (detection columns with
            the laser's offset, full rows, strengths), sorted by column then row; noise_l: (L,) band noise, DN.
        ints: (scale, max_candidates, min_run_cols, gate_pool_cols, window_half_px, n_lasers, iterations);
        reals: (max_jump_px, saturation_dn, min_fwhm_px, max_sigma_px, min_contrast_dn, min_snr,
            min_green_ratio, max_sheet_mm, snr_floor_frac); scales: smoothing half-widths, largest first.
        cam, dist, R, origin, normals, points: the calibration (see :func:`triangulate_points`); axis: (3,) unit
            optical axis, body frame; wide_fwhm: flat-top width limit of the common fit; tri: also triangulate.

    Returns:
        ``(u, v, laser, quality, xyz)``: (M,) each and (M, 3) body points (empty (0, 3) unless ``tri``).
    """
    w = image.shape[1]
    scale, max_cand, min_run_cols, pool, half0, n_l, iterations = (
        ints[0],
        ints[1],
        ints[2],
        ints[3],
        ints[4],
        ints[5],
        ints[6],
    )
    max_jump, sat_dn, min_fwhm, max_sigma = reals[0], reals[1], reals[2], reals[3]
    min_contrast, min_snr, green_ratio, sheet_mm, floor_frac = reals[4], reals[5], reals[6], reals[7], reals[8]
    fwhm_per_sigma = 2.3548200450309493
    wide_sigma = wide_fwhm / fwhm_per_sigma  # profiles wider than this are flat-topped (wide)
    wd = (w + scale - 1) // scale
    n_cols_d = n_l * wd
    n_cols = n_l * w
    jump = max_jump * (1.5 if scale == 2 else 1.0)
    min_run = max(2, (min_run_cols + scale - 1) // scale)
    e_u = np.empty(0)
    e_i = np.empty(0, np.int64)
    if U.size == 0:
        return e_u, e_u, e_i, e_u, np.empty((0, 3))
    # 3. chains
    cnt = np.zeros(n_cols_d, np.int64)
    kk = 0
    for t in range(U.size):
        cnt[U[t]] += 1
        kk = max(kk, cnt[U[t]])
    k = min(max_cand, kk)
    col_d, rows_f, chain, chain_len = select_candidates(U, Vr, Ar, n_cols_d, k, jump, wd, 3, min_run)
    if col_d.size == 0:
        return e_u, e_u, e_i, e_u, np.empty((0, 3))
    if scale == 2:
        col_v, rows_f, chain, chain_len = expand_half(col_d, rows_f, chain, chain_len, wd, w)
    else:
        col_v = col_d
    n = col_v.size
    rows = np.empty(n, np.int64)
    laser = sorted_blocks(col_v, w)
    cols = np.empty(n, np.int64)
    for t in range(n):
        rows[t] = int(np.rint(rows_f[t]))
        cols[t] = col_v[t] - laser[t] * w
    # 4. frame statistics (window length), common fits, full fits of the special columns
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
    geo = (cam, dist, R, origin, normals, points, axis)
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
                _put_fit(out, r_c, i, keep[i])
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
                _put_fit(res, r_s, i, t)
            else:
                rest[n_rest] = t
                n_rest += 1
        rest = rest[:n_rest]
        if rest.size:
            nan = np.full(rest.size, np.nan)  # flat tops, which only the full kernel fits
            _refit_full(image, cols, rows, laser, rest, nan, nan, nan, fit, limits, geo, res)
    # stripes of two lasers close together: refit each with the other's Gaussian subtracted, a few times
    if n_l > 1:
        max_d = half + 3.0 * sig_med + 2.0
        good = np.empty(n, np.bool_)  # the points that can be a neighbour (updated where refitted)
        for t in range(n):
            good[t] = ok[t] and not sat[t]
        if _rows_overlap(laser, vv, good, n_l, max_d):  # else the common case: stripes far apart
            # the rows the fits read: background flanks of 3 rows (as the fits take them; no clipped sample) and
            # the whole window
            read = (float(_flank_offset(sig_med, 0, half, 3) + 2), half + 1.0, wide_sigma)
            last = np.full((3, n), np.nan)  # the neighbour each point was last refitted with
            at = point_table(laser, cols, n_l, w)
            look = np.arange(w)  # the columns where a neighbour can have changed: all, then the refits'
            touched = np.zeros(w, np.bool_)
            for _ in range(NEIGHBOUR_REFITS):
                idx, nb_v, nb_a, nb_s = refit_targets(laser, cols, vv, amp, sig, sat, good, at, max_d, read, look, last)
                if idx.size == 0:
                    break
                _refit(image, cols, rows, laser, idx, nb_v, nb_a, nb_s, fit, limits, geo, res)
                for i in range(idx.size):
                    t = idx[i]
                    good[t] = ok[t] and not sat[t]
                    touched[cols[t]] = True
                look = np.flatnonzero(touched)
                touched[look] = False
    # 5-6. gates, runs, smoothing, quality
    u_o, v_o, l_o, q_o = finish_points(
        col_v,
        laser,
        vv,
        amp,
        sig,
        sat,
        ok,
        lnoise,
        chain,
        chain_len,
        noise_l,
        w,
        n_cols,
        min_contrast,
        min_snr,
        min_run_cols,
        max_sigma,
        scales,
        rise,
        green_ratio,
        pool,
        floor_frac,
        max_jump,
        wide_sigma,
    )
    xyz = triangulate_points(u_o, v_o, l_o, cam, dist, R, origin, normals, points) if tri else np.empty((0, 3))
    return u_o, v_o, l_o, q_o, xyz


@_njit
def extract_frame(  # type: ignore[no-untyped-def]
    image,
    band_rows,
    v_lo,
    v_hi,
    detect,
    ints,
    reals,
    scales,
    cam,
    dist,
    R,
    origin,
    normals,
    points,
    axis,
    wide_fwhm,
    depth_gate,
):
    """The whole default extractor on one frame in one compiled call: :func:`detect_band` for every laser (at
    detection scale 2), then :func:`process_candidates` with the triangulation, and the depth gate.

    Args:
        band_rows: (L, 2) bounding rows ``[r0, r1)`` of each laser's band; v_lo, v_hi: (L, W) the bands.
        detect: ``(contrast_px, snr_threshold, area_noise, min_response)`` of :func:`detect_band`.
        depth_gate: ``(r_x, r_y, r_z, t_z, min_depth, max_depth)``: camera z of a body point is
            ``r . p + t_z`` (metres); points outside ``[min_depth, max_depth]`` (or NaN) are dropped.
        the rest: as :func:`process_candidates`.

    Returns:
        ``(uv, laser, quality, xyz, noise)``: the kept points' pixel coordinates (M, 2), laser (M,), quality (M,)
        and body-frame points (M, 3), and the band noise (L,), DN.
    """
    n_l = band_rows.shape[0]
    w = image.shape[1]
    wd = (w + 1) // 2
    noise = np.ones(n_l)
    parts_u = []
    parts_v = []
    parts_a = []
    total = 0
    for i in range(n_l):
        r0 = band_rows[i, 0]
        r1 = band_rows[i, 1]
        if r1 <= r0:
            continue
        u, v, a, noise[i] = detect_band(
            image, r0, r1, int(detect[0]), detect[1], detect[2], detect[3], v_lo[i], v_hi[i], i * wd
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
    u_o, v_o, l_o, q_o, xyz = process_candidates(
        image, U, Vr, Ar, noise, ints, reals, scales, cam, dist, R, origin, normals, points, axis, wide_fwhm, True
    )
    n = u_o.size
    keep = np.empty(n, np.bool_)
    m = 0
    for t in range(n):
        depth = xyz[t, 0] * depth_gate[0] + xyz[t, 1] * depth_gate[1] + xyz[t, 2] * depth_gate[2] + depth_gate[3]
        keep[t] = depth >= depth_gate[4] and depth <= depth_gate[5]  # NaN fails both
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


@_njit
def _refit(image, cols, rows, laser, idx, nb_v, nb_a, nb_s, fit, limits, geo, res):  # type: ignore[no-untyped-def]
    """Fit the columns ``idx`` again with the other laser's stripe subtracted (neighbour model ``nb_*``, NaN rows =
    none) and store the results in place: column-parallel (:func:`fit_columns_neighbour`) where no sample is
    clipped and the profile is not flat-topped, the rest by :func:`_refit_full`. Arguments as :func:`_refit_full`.
    """
    half, sig_med, sat_dn, min_sig, max_sigma, iterations, wide_fwhm = fit
    m = idx.size
    cols_i = cols[idx]
    rows_i = rows[idx]
    par = fit_columns_neighbour(
        image, cols_i, rows_i, half, 3, sig_med, sat_dn, min_sig, max_sigma, 3, iterations, nb_v, nb_a, nb_s, wide_fwhm
    )
    n_rest = 0
    rest = np.empty(m, np.int64)
    for i in range(m):
        if par[7][i]:
            _put_fit(res, par, i, idx[i])
        else:
            rest[n_rest] = i
            n_rest += 1
    if n_rest:
        rest = rest[:n_rest]
        _refit_full(image, cols, rows, laser, idx[rest], nb_v[rest], nb_a[rest], nb_s[rest], fit, limits, geo, res)


@_njit
def _refit_full(image, cols, rows, laser, idx, nb_v, nb_a, nb_s, fit, limits, geo, res):  # type: ignore[no-untyped-def]
    """Fit the columns ``idx`` again with the full kernel (neighbour model ``nb_*``, NaN rows = none) and store the
    results in place.

    ``fit``: ``(half, sigma_hint, sat_dn, min_sig, max_sig, iterations, wide_fwhm)`` of :func:`fit_columns`;
    ``limits``: ``(max_fwhm, floor, sheet_mm)``, the width limits (N,) (computed here where still NaN, see
    :func:`max_fwhm_at`); ``geo``: as :func:`max_fwhm_at`; ``res``: ``(centre, amplitude, sigma, saturated,
    ok, local_noise, rise)`` of every column, updated at ``idx``.
    """
    half, sig_med, sat_dn, min_sig, max_sigma, iterations, wide_fwhm = fit
    mfw, floor, sheet_mm = limits
    m = idx.size
    need = np.empty(m, np.int64)
    nn = 0
    for i in range(m):
        if math.isnan(mfw[idx[i]]):
            need[nn] = idx[i]
            nn += 1
    if nn:
        nd = need[:nn]
        mf = max_fwhm_at(cols[nd], rows[nd], laser[nd], floor, sheet_mm, geo)
        for i in range(nn):
            mfw[nd[i]] = mf[i]
    new = fit_columns(
        image,
        cols[idx],
        rows[idx],
        half,
        3,
        sig_med,
        sat_dn,
        min_sig,
        max_sigma,
        3,
        iterations,
        nb_v,
        nb_a,
        nb_s,
        mfw[idx],
        wide_fwhm,
    )
    for i in range(m):
        _put_fit(res, new, i, idx[i])


# --------------------------------------------------------------------------- compilation management
_READY = threading.Event()
_LOCK = threading.Lock()
_STARTED = False


def warm_up() -> None:
    """Compile (or load from the cache) every kernel for the extractor's argument types; blocks until done."""
    if not HAVE_NUMBA or _READY.is_set():
        return
    with _LOCK:
        if _READY.is_set():
            return
        i64 = np.zeros(4, np.int64)
        f64 = np.zeros(4)
        nan = np.full(4, np.nan)
        b = np.zeros(4, np.bool_)
        img = np.zeros((8, 8, 3), np.uint8)
        select_candidates(np.arange(4, dtype=np.int64), i64 + 2, f64 + 1.0, 8, 2, 3.0, 4, 3, 2)
        expand_half(i64, f64, i64, i64, 4, 8)
        fit_columns(img, i64, i64 + 4, 2, 1, 1.0, 250.0, 0.5, 5.0, 1, 2, nan, nan, nan, f64 + 20.0, 4.7)
        refit_targets(
            i64,
            i64,
            f64,
            f64,
            f64,
            b,
            b,
            point_table(i64, i64, 2, 8),
            10.0,
            (6.0, 8.0, 2.0),
            i64,
            np.full((3, 4), np.nan),
        )
        finish_points(
            i64,
            i64,
            f64,
            f64,
            f64,
            b,
            b,
            f64,
            i64,
            i64,
            np.ones(2),
            8,
            16,
            5.0,
            2.5,
            8,
            5.0,
            np.array([4, 1]),
            np.zeros((3, 4)),
            1.2,
            4,
            0.75,
            3.0,
            2.0,
        )
        smooth_runs(np.full(16, np.nan), np.full(16, -1, np.int64), np.array([4, 1]))
        eye = np.eye(3)
        g = green_rows(img.reshape(-1), 8, 0, 8)
        noise_dn(g, 2)
        noise_dn_rows(img.reshape(-1), 8, np.arange(8), 2)
        local_maxima(g, 1.0, 0, 2, i64, i64 + 8, 8, 0)
        detect_band(img, 2, 6, 2, 4.0, 0.3, 3.5, np.zeros(8, np.int64), np.full(8, 7, np.int64), 0)
        frame_profile_stats(img, i64, i64 + 4, 2, 250.0, 5.0, f64)
        core_peaks(img, i64, i64 + 4, 1, 250.0)
        fit_columns_common(img, i64, i64 + 4, 2, 1.0, 250.0, 0.5, 5.0, 1, 2, 4.7)
        fit_columns_clipped(img, i64, i64 + 4, 2, 1.0, 250.0, 1, 2, 0.5, 5.0, 4.7)
        triangulate_points(f64, f64, i64, np.ones(4), np.zeros(5), eye, np.zeros(3), eye[:2], eye[:2])
        process_candidates(
            img,
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            np.zeros(0),
            np.ones(2),
            np.array([2, 4, 8, 4, 20, 2, 2], np.int64),
            np.array([3.0, 250.0, 0.8, 5.0, 5.0, 2.5, 1.2, 20.0, 0.75]),
            np.array([4, 1], np.int64),
            np.ones(4),
            np.zeros(5),
            eye,
            np.zeros(3),
            eye[:2],
            eye[:2],
            np.array([0.0, 0.0, 1.0]),
            4.7,
            True,
        )
        extract_frame(
            img,
            np.array([[2, 6]], np.int64),
            np.zeros((1, 8), np.int64),
            np.full((1, 8), 7, np.int64),
            np.array([2.0, 4.0, 0.3, 3.5]),
            np.array([2, 4, 8, 4, 20, 1, 2], np.int64),
            np.array([3.0, 250.0, 0.8, 5.0, 5.0, 2.5, 1.2, 20.0, 0.75]),
            np.array([4, 1], np.int64),
            np.ones(4),
            np.zeros(5),
            eye,
            np.zeros(3),
            eye[:1],
            eye[:1],
            np.array([0.0, 0.0, 1.0]),
            4.7,
            np.array([0.0, 0.0, 1.0, 0.0, 0.2, 5.0]),
        )
        _READY.set()


def ready() -> bool:
    """True when the compiled kernels can be called without compiling; starts the background compile once."""
    global _STARTED
    if not HAVE_NUMBA:
        return False
    if _READY.is_set():
        return True
    if not _STARTED:
        _STARTED = True
        if _cached():
            warm_up()  # loading from the on-disk cache takes about a second: do it now
            return True
        threading.Thread(target=warm_up, name="lrsensor-numba-warmup", daemon=True).start()
    return False


_KERNEL_NAMES = (
    "select_candidates",
    "expand_half",
    "fit_columns",
    "point_table",
    "refit_targets",
    "finish_points",
    "smooth_runs",
    "triangulate_points",
    "green_rows",
    "noise_dn",
    "noise_dn_rows",
    "local_maxima",
    "frame_profile_stats",
    "fit_columns_common",
    "fit_columns_clipped",
    "core_peaks",
    "max_fwhm_at",
    "process_candidates",
    "detect_band",
    "_refit",
    "_refit_full",
    "extract_frame",
)


def _cached() -> bool:
    """Whether numba's on-disk cache holds an index for every kernel as defined now (then loading is quick)."""
    cache_dir = Path(__file__).parent / "__pycache__"
    stem = Path(__file__).stem
    try:
        for name in _KERNEL_NAMES:
            line = globals()[name].py_func.__code__.co_firstlineno
            if not any(cache_dir.glob(f"{stem}.{name}-{line}.*.nbi")):
                return False
    except (OSError, AttributeError, KeyError):
        return False
    return True
