"""Finishing: the pooled colour and signal-to-noise gates, runs, smoothing and quality of the fitted points.

:func:`finish_points` takes the fitted points of every laser, one per virtual column (N,): centre row (px),
amplitude (DN), sigma (px), saturated, ok, local noise (DN), chain and chain length, colour rises (3, N), and:

1. the colour test (green must rise ``min_green_ratio`` times more than red and blue) and the signal-to-noise
   ratio, pooled over the fitted columns of the same chain within ``pool`` columns: rises summed, the ratio the
   median of the neighbours' (:func:`pooled_median`, a sorting network over all columns at once), at most
   ``1 / snr_floor_frac`` times the column's own. One noisy pixel then cannot drop a column of a dim
   stripe, nor keep one of a white blob;
2. runs: kept columns of one laser with gaps of at most 3 columns, on one chain, or both wide (saturated or
   flat-topped, whose candidate rows wander on the top and split the chains) and within ``max_jump`` rows;
3. along-stripe smoothing of each run long enough (:func:`.smooth.smooth_runs_at`; through a port on the rows a
   pinhole in the water would see, :func:`port_view`);
4. quality in [0, 1] from the signal-to-noise ratio, the width and the chain length.

Returns the accepted points ``(u, v, laser, quality)``: columns and rows (px), laser index, quality; (M,) each.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import arange, empty, full, inline, njit, zeros
from .geometry import central_view
from .smooth import smooth_runs_at
from .sorting import select

#: A 9-input sorting network with 25 compare-exchanges (Floyd's; checked on all 512 0-1 inputs in the tests),
#: for the default pooled window of 9 columns (odd-even transposition needs 36).
SORT9 = np.array(
    [
        *((0, 1), (3, 4), (6, 7), (1, 2), (4, 5), (7, 8), (0, 1), (3, 4), (6, 7), (0, 3), (3, 6), (0, 3), (1, 4)),
        *((4, 7), (1, 4), (2, 5), (5, 8), (2, 5), (1, 3), (5, 7), (2, 6), (4, 6), (2, 4), (2, 3), (5, 6)),
    ],
    np.int64,
)


@inline
def sorting_network(n):  # type: ignore[no-untyped-def]
    """Compare-exchange pairs (P, 2) that sort ``n`` values: :data:`SORT9` for 9, else odd-even transposition."""
    if n == 9:
        return SORT9.copy()
    pairs = empty((n * (n // 2), 2), np.int64)
    p = 0
    for r in range(n):
        for j in range(r % 2, n - 1, 2):
            pairs[p, 0] = j
            pairs[p, 1] = j + 1
            p += 1
    return pairs[:p]


@njit
def pooled_median(ch, ds, own, nw, nd):  # type: ignore[no-untyped-def]
    """The pooled signal-to-noise medians of :func:`finish_points` for any window ``nw``: each column's window
    sorted by branch-free compare-exchanges, each a pass over all columns. ``ch``, ``ds``:
    (nd + nw - 1,) the padded chains and passing ratios (NaN: none); ``own`` (nd,) each column's chain. Returns
    the median of each column's window over the values of its own piece (NaN and other pieces left out), as
    ``0.5 (v[k / 2 - 1] + v[k / 2])`` for an even count ``k`` (inf for none): (nd,) float64."""
    # the pooled windows of every column: (2 pool + 1, n_cols), missing values (+inf) sorted last by
    # branch-free odd-even transposition compare-exchanges that run over all columns at once
    vals = empty((nw, nd), np.float32)
    cnt_d = zeros(nd, np.int32)
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
    net = sorting_network(nw)
    for p in range(net.shape[0]):
        va = vals[net[p, 0]]
        vb = vals[net[p, 1]]
        for q in range(nd):
            lo = min(va[q], vb[q])
            vb[q] = max(va[q], vb[q])
            va[q] = lo
    med = empty(nd, np.float64)
    for q in range(nd):
        k = cnt_d[q]
        med[q] = float(vals[k // 2, q]) if k % 2 else 0.5 * (float(vals[k // 2 - 1, q]) + float(vals[k // 2, q]))
    return med


@inline
def port_view(y, run, w, geo):  # type: ignore[no-untyped-def]
    """The rows ``y`` (N,) (virtual columns ``laser * w + column``, NaN = none) and their run labels ``run`` (N,)
    seen through the port of ``geo`` where a pinhole in the water at the camera centre would see the points
    (:func:`.geometry.central_view`): there a stripe on a flat surface is straight (the port curves it, and line
    fits would pull a curved stripe towards its chords). Rows whose ray misses their laser's plane leave their
    run (label -1).

    Returns:
        ``(yw, x, run_w, idx, rows, slope)``: the rows seen (N,), the columns' coordinates (N,) (the view's where
        seen, interpolated by the index between them), the runs (N,); the measured columns (M,), their rows in
        the view and its derivative by the image row (M,), for :func:`from_port_view`.
    """
    # (loops, not np.flatnonzero, fancy or masked indexing and astype: each of those compiles numpy's own helpers)
    n_fin = 0
    for q in range(y.size):
        n_fin += math.isfinite(y[q])
    idx = empty(n_fin, np.int64)
    u_fin = empty(n_fin, np.float64)
    v_fin = empty(n_fin, np.float64)
    l_fin = empty(n_fin, np.int64)
    i_fin = 0
    for q in range(y.size):
        if math.isfinite(y[q]):
            idx[i_fin] = q
            u_fin[i_fin] = q % w
            v_fin[i_fin] = y[q]
            l_fin[i_fin] = q // w
            i_fin += 1
    cols, rows, slope = central_view(u_fin, v_fin, l_fin, geo)
    yw = full(y.size, np.nan, np.float64)
    run_w = run.copy()
    n_seen = 0
    for j in range(n_fin):
        if math.isfinite(rows[j]) and math.isfinite(cols[j]):
            yw[idx[j]] = rows[j]
            n_seen += 1
        else:
            run_w[idx[j]] = -1
    # the columns' coordinates: the view's where seen, linear in the index between them and constant beyond the
    # first and the last (np.interp's arithmetic, in a loop that compiles in a fraction of its time)
    x = arange(y.size, np.float64)
    known = empty(n_seen, np.int64)
    fk = empty(n_seen, np.float64)
    i_fin = 0
    for j in range(n_fin):
        if math.isfinite(rows[j]) and math.isfinite(cols[j]):
            known[i_fin] = idx[j]
            fk[i_fin] = cols[j]
            i_fin += 1
    if known.size:
        for q in range(known[0]):
            x[q] = fk[0]
        for i in range(known.size - 1):
            k0 = known[i]
            x[k0] = fk[i]
            sl = (fk[i + 1] - fk[i]) / (known[i + 1] - k0)
            for q in range(k0 + 1, known[i + 1]):
                x[q] = sl * (q - k0) + fk[i]
        for q in range(known[-1], y.size):
            x[q] = fk[-1]
    return yw, x, run_w, idx, rows, slope


@inline
def from_port_view(y, sw, idx, rows, slope):  # type: ignore[no-untyped-def]
    """The smoothed rows ``sw`` (N,) of :func:`port_view` back in the image: each measured row ``y`` moved by its
    correction in the view over the view's derivative (the corrections are below a pixel: the first order is
    exact to far below 1e-3 px)."""
    out = y.copy()
    for j in range(idx.size):
        step = (sw[idx[j]] - rows[j]) / slope[j]
        if math.isfinite(step):
            out[idx[j]] = y[idx[j]] + step
    return out


#: A laser's joint fits (:func:`.glow.glow_refit`) tell the noise at its stripe where there are at least this many.
STRIPE_NOISE_MIN = 64


@inline
def own_values(lz, own, x, li):  # type: ignore[no-untyped-def]
    """The finite values of ``x`` (N,) at laser ``li``'s points with their own joint fit (``own`` (N,), their laser
    ``lz`` (N,)), in point order, (K,); None where there are fewer than :data:`STRIPE_NOISE_MIN`."""
    cnt = 0
    for t in range(lz.size):
        cnt += own[t] and lz[t] == li and math.isfinite(x[t])
    if cnt < STRIPE_NOISE_MIN:
        return None
    vals = empty(cnt, np.float64)
    k = 0
    for t in range(lz.size):
        if own[t] and lz[t] == li and math.isfinite(x[t]):
            vals[k] = x[t]
            k += 1
    return vals


@inline
def stripe_noise(lz, lnoise, own, noise_l):  # type: ignore[no-untyped-def]
    """The noise of each laser's band for the signal-to-noise gate, DN (L,): ``noise_l``, or where the laser has at
    least :data:`STRIPE_NOISE_MIN` points with their own joint fit (``own`` (N,), their residual noise ``lnoise``),
    the (lower) median of those residual noises (:func:`.sorting.select`) if lower. In turbid water the band's noise
    holds the glow's bright rows beyond the stripe (their shot noise: 1.2-1.45x the noise at the stripe's row on the
    turbidity model), and it is the gate's noise at the points whose glow is too faint for the glow stage."""
    out = noise_l.copy()
    for li in range(noise_l.size):
        vals = own_values(lz, own, lnoise, li)
        if vals is not None:
            out[li] = min(out[li], select(vals, vals.size, (vals.size - 1) // 2))
    return out


#: A blurred stripe (its laser's kept points' mean sigma at least this, px: forward scatter; the glow stage's
#: pair test's width, :data:`lrsensor.extract.glow.PAIR_MIN_SIGMA`) keeps a run only where the line fitted along it is
#: sure to RUN_MAX_SD_PX at its ends (:func:`run_sure`).
BLURRED_SIGMA_PX = 2.0
RUN_MAX_SD_PX = 0.25
#: A Gaussian stripe's centre from one column: its standard deviation is this times ``sqrt(sigma) / snr`` (the
#: Cramer-Rao bound ``(2 sigma / sqrt(pi))^(1/2) noise / peak``, background known).
CENTRE_SD = 1.0622


@inline
def run_sure(sigma, inv_snr, k):  # type: ignore[no-untyped-def]
    """Whether a run of ``k`` points on a stripe of width ``sigma`` (px; its laser's kept points' mean) is sure enough:
    on a blurred stripe (``sigma`` at least :data:`BLURRED_SIGMA_PX`) the standard deviation of a line fitted along
    it at its ends, ``2 CENTRE_SD sqrt(sigma) mean(1 / snr) / sqrt(k)`` (``inv_snr``: the sum of its points' ``1 /
    snr``), is at most :data:`RUN_MAX_SD_PX`; every run of a sharp stripe is.

    At the dim ends of a blurred stripe the signal-to-noise gate leaves short pieces split by the columns it drops
    (3 m, 4 px of blur: peaks 1.6-3x the noise, 4-37 columns): their line fits are a pixel off at a third to all of
    their columns (5 % of range at 3 m is 0.46 px), while the stripe's long run holds its points to 0.3 %. Sharp
    stripes (clear water) keep every run as it was."""
    return sigma < BLURRED_SIGMA_PX or 2.0 * CENTRE_SD * math.sqrt(sigma) * inv_snr / k / math.sqrt(k) <= RUN_MAX_SD_PX


@inline
def finish_points(col_v, lz, fits, chain, chain_len, noise_l, w, s, geo, own_noise):  # type: ignore[no-untyped-def]
    """Colour and signal-to-noise gates, runs, along-stripe smoothing and quality of the fitted points.

    The colour test (green must rise more than ``green_ratio`` times red and blue; ``rise`` (3, N) in B, G, R)
    and the signal-to-noise test are pooled over the fitted columns of the same chain within ``pool`` columns:
    the rises are summed, and the ratio is the median of the neighbours' (at most ``1 / floor_frac`` times the
    column's own). One noisy pixel then cannot drop a column of a dim stripe, nor keep one of a white blob.

    The smoothing runs along the kept columns of one laser with gaps of at most 3 columns, on one chain; wide
    profiles (saturated, or sigma above ``wide_sigma``: thick sheets close to the wall) also join the run of the
    column before them when both are wide and their rows differ by at most ``max_jump``, because the candidate row
    of a flat top wanders across it and splits the chain into short pieces, whose runs would be too short for the
    long line fits.

    Args:
        col_v: (N,) sorted virtual columns ``laser * w + column``; lz: (N,) the laser of each, ``col_v // w``.
        fits: ``(centre_row, amplitude, sigma, saturated, ok, local_noise, rise)`` (N,) each, rise (3, N) in B, G, R
            (:func:`.columns.fit_results` without its flag); chain, chain_len: (N,) each point's chain and length.
        noise_l: (L,) the band noise of each laser, DN; w: image width; s: the
            :class:`~lrsensor.extract.settings.Settings` (``green_ratio`` above is its ``min_green_ratio``, ``pool``
            its ``gate_pool_cols``, ``floor_frac`` its ``snr_floor_frac``, ``max_jump`` its ``max_jump_px``);
            geo: the :class:`~lrsensor.extract.settings.Geometry` (through a port the line fits run on the rows a
            pinhole in the water would see, :func:`port_view`).
        own_noise: (N,) bool: the point's amplitude and local noise are its own joint fit's (the glow stage's: the
            stripe's amplitude and the fit's residual noise, :func:`.glow.glow_refit`), and that noise is the
            signal-to-noise ratio's alone: the band's noise holds the glow's brighter rows (more shot noise), and
            the residuals of a fit that models the glow are the noise at the stripe. Elsewhere the noise is the
            larger of the band's and the flanks' spread about the common fit's line.

    Returns ``(u, v, laser, quality)`` of the accepted points, (M,) each.
    """
    vv, amp, sig, sat, ok, lnoise, rise = fits
    n_cols = noise_l.size * w
    min_contrast, min_snr, min_run, max_sigma = s.min_contrast_dn, s.min_snr, s.min_run_cols, s.max_sigma_px
    scales, green_ratio, pool, floor_frac = s.smooth_scales, s.min_green_ratio, s.gate_pool_cols, s.snr_floor_frac
    max_jump = s.max_jump_px
    wide_sigma = s.wide_fwhm_px / 2.3548200450309493
    n = col_v.size
    snr = empty(n, np.float64)
    # dense per (virtual) column, padded by pool: chain (-1 = none), rises of fitted columns, ratios
    ch = full(n_cols + 2 * pool, -1, np.int32)  # chain ids < n_cols * k: 16 lanes in the float32 pooling
    # the rises are halves of integers below 256 in magnitude: their sums over the window are exact in float32
    # (twice the vector lanes of float64)
    dr = zeros((3, n_cols + 2 * pool), np.float32)
    zero = np.float32(0.0)
    d_b = dr[0]
    d_g = dr[1]
    d_r = dr[2]
    noise_b = stripe_noise(lz, lnoise, own_noise, noise_l)
    for t in range(n):  # the points' signal-to-noise ratios and their dense rows, one pass (no branch)
        noise = max(max(0.0 if own_noise[t] else noise_b[lz[t]], lnoise[t]), 0.5)
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
    sums = zeros((3, nd), np.float32)
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
    good = empty(n, np.bool_)
    ds = full(n_cols + 2 * pool, np.nan, np.float32)  # float32: twice the lanes in the sorting network
    nan32 = np.float32(np.nan)
    for t in range(n):  # the colour gate and the passing ratios, one branch-free pass
        qc = np.uint64(col_v[t])
        g = ok[t] & (sat[t] | (float(sg[qc]) >= green_ratio * float(max(sb[qc], sr[qc]))))
        good[t] = g
        ds[qc + np.uint64(pool)] = np.float32(snr[t]) if g else nan32
    keep = empty(n, np.bool_)
    medv = pooled_median(ch, ds, own, nw, nd)
    e_arg = empty(n, np.float32)
    for t in range(n):  # branch-free: the pooled ratio of the points that pass the colour gate, and the gates
        g = good[t]
        s = min(medv[np.uint64(col_v[t])], snr[t] / floor_frac) if g else snr[t]
        snr[t] = s
        keep[t] = g & (amp[t] >= min_contrast) & ((s >= min_snr) | sat[t]) & math.isfinite(vv[t])
        e_arg[t] = -s / 8.0
    # runs: kept columns of one laser with gaps of at most 3 columns, on one chain, or both wide (saturated or
    # flat-topped: their candidate rows wander on the top and split the chains) and within max_jump rows
    run_id = full(n, -1, np.int64)
    counts = empty(n, np.int64)  # points per run (a run's count kept in a register while it grows)
    cur = 0
    r = -1
    inv_run = zeros(n, np.float64)  # each run's sum of 1 / snr, and each laser's kept points' sigmas summed and counted
    sig_l = zeros((2, noise_l.size), np.float64)
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
        inv_run[r] += 1.0 / max(snr[t], 1e-9)
        if math.isfinite(sig[t]):
            sig_l[0, lz[t]] += sig[t]
            sig_l[1, lz[t]] += 1.0
        last_col = col_v[t]
        last_chain = chain[t]
        last_l = lz[t]
        last_v = vv[t]
        last_wide = wide
    if r >= 0:
        counts[r] = cur
    need = max(2, min_run // 2)
    y = full(n_cols, np.nan, np.float64)
    run = full(n_cols, -1, np.int64)
    long_ = empty(n, np.bool_)  # in a run long enough (and, on a blurred stripe, sure enough)
    m = 0
    for t in range(n):
        ri = run_id[t]
        lg = ri >= 0 and counts[ri] >= need
        lg = lg and run_sure(sig_l[0, lz[t]] / max(sig_l[1, lz[t]], 1.0), inv_run[ri], counts[ri])
        long_[t] = lg
        if lg:
            y[col_v[t]] = vv[t]
            run[col_v[t]] = ri
            m += 1
    ys = y
    if scales.size:  # through a port the line fits run in its central view (port_view)
        if geo.port.present:
            yw, x, run_w, idx, rows_w, slope_w = port_view(y, run, w, geo)
        else:
            yw, x, run_w = y, arange(n_cols, np.float64), run
            idx, rows_w, slope_w = empty(0, np.int64), empty(0, np.float64), empty(0, np.float64)
        ys = smooth_runs_at(yw, x, run_w, scales)
        if geo.port.present:
            ys = from_port_view(y, ys, idx, rows_w, slope_w)
    u_out = empty(m, np.float64)
    v_out = empty(m, np.float64)
    l_out = empty(m, np.int64)
    q_out = empty(m, np.float64)
    e_snr = np.exp(e_arg)  # float32 is plenty for a score
    qual = empty(n, np.float64)
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
