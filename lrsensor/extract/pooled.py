"""Turbid water: a glowing stripe's dim ends, measured pooled along the stripe (:func:`extend_ends`).

Why. At the image's sides a stripe in turbid water is dim (peaks 3-5x the noise at 3 m), and a single column's
centre there is 0.4-0.9 px uncertain (``1.06 sqrt(sigma) / snr``, more with the glow's terms free), while 5 % of
range is 0.46 px at 3 m: the signal-to-noise gate drops those columns (or detection never finds them), and where
they are kept their runs are too short for the along-stripe line fits to average them (docs/water-design.md,
"The pooled dim ends", "Measured and left off"). A stripe on a wall is smooth in
``v(u)`` (straight on a flat one), so its row beyond the end of a long run is known to a fraction of a pixel, and
many dim columns measured together meet the bound a single one cannot.

What. After the gates and the smoothing (:func:`.finish.finish_points`), on each laser whose stripe the glow stage
fitted (turbid water; clear water never gets here), every piece of returned columns at least :data:`ANCHOR_MIN`
long is followed outward from both its ends, :data:`BLOCK_COLS` columns at a time, up to the next such piece or the
image's edge (the short pieces on the way, whose own line fits are the unsure ones, are replaced):

1. the anchor: a straight line through the piece's last :data:`ANCHOR_COLS` returned rows predicts the row;
2. a block's green profiles are read about the predicted rows (linear interpolation between rows, so the stripe
   lines up to a fraction of a pixel) and averaged into one profile: its noise is the columns' over
   ``sqrt(n)``;
3. that profile is fitted with the glow stage's model (a line, the Gaussian stripe, the glow's edge at its centre
   blurred like it, and another laser's stripe and edge where one lies in the window, at its separation from the
   anchor), the offset ``d`` of the centre from the prediction by least squares on a grid of offsets (the linear
   parameters solved exactly at each, the minimum refined by parabolas), the width held at the stripe's (the glow
   stage's fits' median: the water's, told along the whole stripe); where the glow stage fitted the sheet's shape
   and the laser's glow is strong (:func:`shaped_growth`), the edge is that shape, with the frame's attenuation (at
   4 px of blur the plain edge read the anchor a pixel off and the blocks 0.15-0.25 px uncertain), and the gate is
   the visible stripe's (:data:`SHAPE_AMP_MIN`, :data:`SHAPE_SD_MAX_PX`);
4. the offsets are read relative to the same fit's offset on the anchor's own last block (``d0``): the model's
   bias (the glow's growth over the window, which the edge alone does not follow) is the same along the stripe, and
   the anchor's rows are the extractor's own (better modelled) estimates;
5. the pooled gate: a block is taken where its offset's standard deviation (the residual's curvature in ``d``
   and the columns' noise, from the differences of neighbouring columns' profiles) is at most :data:`SD_MAX_PX`,
   its mean amplitude at least :data:`AMP_MIN` times a column's noise, its minimum inside the grid and its move
   at most :data:`MOVE_MAX_PX`; the walk stops at the first block that fails;
6. each column of a block taken gets one point: the prediction plus the block's offset (the prediction of the
   next block moves with it).

Why not per column with a lower gate, or a corridor for detection: both were measured (docs/water-design.md): the
points gained were single dim columns, 0.4-0.5 px uncertain, and pushed the outliers past the bar. Here no point
rests on one column.

Rows in pixels, amplitudes in DN. The numpy twin is :func:`lrsensor.extract.reference_pooled.extend_ends`.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import callee, empty, full, inline, njit, zeros
from .finish import own_values
from .glow_fit import sheet_edge
from .held import HELD_MAX_STEP
from .sorting import median

#: A piece of returned columns (gaps of at most :data:`GAP_COLS`) anchors an extension where it has this many.
ANCHOR_MIN = 64
GAP_COLS = 3
#: The anchor's line is fitted through its last this many returned rows.
ANCHOR_COLS = 128
#: Columns measured together (a block); a last block of fewer than half of them is not taken.
BLOCK_COLS = 48
#: The pooled gate: the block offset's standard deviation (px), its mean amplitude over a column's noise, its move
#: against the anchor's (px).
SD_MAX_PX = 0.15
AMP_MIN = 1.5
MOVE_MAX_PX = 1.5
#: ... where the glow's edge takes the sheet's shape (a strong glow on a blurred stripe, :func:`shaped_growth`): the
#: offset's standard deviation at most this (px) and the mean amplitude at least the visible stripe's 3x a column's
#: noise (the shaped fit follows the stripe past the columns where it is visible, whose points raised the far walls'
#: medians: 3 m, glow 0.3, 4 px read 0.303 % with the plain gate, 0.271 with this one).
SHAPE_SD_MAX_PX = 0.12
SHAPE_AMP_MIN = 3.0
#: The offsets searched: a grid of this span either side of the anchor's offset and this step, px, then a parabola
#: through the residuals this far either side of the grid's (parabolic) least.
OFFSET_SPAN_PX = 2.0
COARSE_STEP_PX = 0.25
FINE_STEP_PX = 0.05
#: The fit's window: the stripe's width times this plus 2 rows either side, at most MAX_HALF_PX.
WINDOW_SIGMAS = 4.5
MAX_HALF_PX = 24
#: 1 / sqrt(2 pi).
INV_SQRT_2PI = 0.3989422804014327
#: The quality of a pooled point: the usual signal-to-noise term of a column, halved (no single column holds it).
QUALITY_SCALE = 0.5


@callee
def stack(image, cols, pred, half, out):  # type: ignore[no-untyped-def]
    """The green profiles of ``image`` (H, W, 3) of the columns ``cols`` (B,) read at ``pred + q`` (``q = -half ..
    half``, linear interpolation between rows) into ``out`` (B, 2 half + 1); rows of columns whose window leaves
    the image are not written. Returns (B,) bool: the columns read."""
    h = image.shape[0]
    m = 2 * half + 1
    got = zeros(cols.size, np.bool_)
    for j in range(cols.size):
        p = pred[j]
        if not math.isfinite(p):
            continue
        r0 = math.floor(p)
        f = p - r0
        if r0 - half < 0 or r0 + half + 1 >= h:
            continue
        got[j] = True
        c = cols[j]
        for k in range(m):
            r = r0 - half + k
            out[j, k] = (1.0 - f) * image[r, c, 1] + f * image[r + 1, c, 1]
    return got


@callee
def model_rss(y, d, s, side, nb, nb_side, beta, d_e, kap):  # type: ignore[no-untyped-def]
    """Least squares of the profile ``y`` (m,) at rows ``q = -(m // 2) .. m // 2`` on a line, a Gaussian stripe at
    ``d`` of width ``s``, its glow's edge ``Phi(side (q - d) / s)`` and, where ``nb`` is finite, another stripe at
    ``nb`` (its Gaussian, and its edge on ``nb_side`` where its centre lies in the window); with ``kap > 0`` the edge
    is the sheet's shape (:func:`.glow_fit.sheet_edge`, the edge ``d_e`` px from its vanishing row). Returns the
    residual sum
    of squares (inf where the normal equations are singular); ``beta`` (6,) gets the parameters (line's two, the
    stripe's amplitude, the edge's step, the other stripe's amplitude and step; 0 where not fitted)."""
    m = y.size
    half = m // 2
    n_p = 4
    if math.isfinite(nb) and abs(nb) <= half + 2.0 * s:
        n_p = 6 if abs(nb) <= half else 5
    ata = zeros((6, 6), np.float64)
    aty = zeros(6, np.float64)
    x = empty(6, np.float64)
    yy = 0.0
    r2 = 1.0 / math.sqrt(2.0)
    for k in range(m):
        q = float(k - half)
        z = (q - d) / s
        x[0] = 1.0
        x[1] = q / half
        x[2] = math.exp(-0.5 * z * z)
        x[3] = 0.5 * (1.0 + math.erf(side * z * r2))
        if kap > 0.0:
            u = side * z
            x[3] = sheet_edge(u * s, u, x[3], math.exp(-0.5 * u * u) * INV_SQRT_2PI, s, d_e, kap)[0]
        if n_p > 4:
            zn = (q - nb) / s
            x[4] = math.exp(-0.5 * zn * zn)
            x[5] = 0.5 * (1.0 + math.erf(nb_side * zn * r2))
        for a in range(n_p):
            aty[a] += x[a] * y[k]
            for b in range(a + 1):
                ata[a, b] += x[a] * x[b]
        yy += y[k] * y[k]
    # Cholesky, in place in the lower triangle, then the two triangular solves
    for a in range(n_p):
        for b in range(a + 1):
            acc = ata[a, b]
            for c in range(b):
                acc -= ata[a, c] * ata[b, c]
            if a == b:
                if acc <= 1e-9 * max(ata[0, 0], 1.0):
                    return np.inf
                ata[a, a] = math.sqrt(acc)
            else:
                ata[a, b] = acc / ata[b, b]
    w = empty(6, np.float64)
    for a in range(n_p):
        acc = aty[a]
        for c in range(a):
            acc -= ata[a, c] * w[c]
        w[a] = acc / ata[a, a]
    for a in range(6):
        beta[a] = 0.0
    for a in range(n_p - 1, -1, -1):
        acc = w[a]
        for c in range(a + 1, n_p):
            acc -= ata[c, a] * beta[c]
        beta[a] = acc / ata[a, a]
    rss = yy
    for a in range(n_p):
        rss -= beta[a] * aty[a]
    return max(rss, 0.0)


@callee
def best_offset(y, s, side, nb, nb_side, c0, d_e, kap):  # type: ignore[no-untyped-def]
    """The offset of the stripe's centre in the profile ``y`` (m,) (px from its middle row; width ``s`` held): the
    least residual (:func:`model_rss`, ``d_e`` and ``kap`` its) on the grid ``c0 +- OFFSET_SPAN_PX`` by
    ``COARSE_STEP_PX``, refined by a parabola through it and its neighbours, then by one through the residuals
    ``FINE_STEP_PX`` either side of that. Returns ``(d,
    curvature, amplitude)``: the offset (NaN where the least lies on the grid's ends or the residual is not convex
    there), the residual's second derivative in ``d`` (per px^2) and the stripe's amplitude at ``d``."""
    n_d = round(2.0 * OFFSET_SPAN_PX / COARSE_STEP_PX) + 1
    rss = empty(n_d, np.float64)
    beta = empty(6, np.float64)
    j_min = 0
    for j in range(n_d):
        rss[j] = model_rss(y, c0 - OFFSET_SPAN_PX + j * COARSE_STEP_PX, s, side, nb, nb_side, beta, d_e, kap)
        if rss[j] < rss[j_min]:
            j_min = j
    if j_min == 0 or j_min == n_d - 1 or not math.isfinite(rss[j_min]):
        return np.nan, 0.0, 0.0
    r_m, r_0, r_p = rss[j_min - 1], rss[j_min], rss[j_min + 1]
    den = r_m - 2.0 * r_0 + r_p
    d1 = c0 - OFFSET_SPAN_PX + (j_min + (0.5 * (r_m - r_p) / den if den > 0.0 else 0.0)) * COARSE_STEP_PX
    r_m = model_rss(y, d1 - FINE_STEP_PX, s, side, nb, nb_side, beta, d_e, kap)
    r_p = model_rss(y, d1 + FINE_STEP_PX, s, side, nb, nb_side, beta, d_e, kap)
    r_0 = model_rss(y, d1, s, side, nb, nb_side, beta, d_e, kap)
    den = r_m - 2.0 * r_0 + r_p
    if not den > 0.0:
        return np.nan, 0.0, 0.0
    d = d1 + 0.5 * (r_m - r_p) / den * FINE_STEP_PX
    model_rss(y, d, s, side, nb, nb_side, beta, d_e, kap)
    return d, den / (FINE_STEP_PX * FINE_STEP_PX), beta[2]


@callee
def block_fit(image, cols, pred, half, s, side, nb, nb_side, prof, c0, d_e, kap):  # type: ignore[no-untyped-def]
    """One block: the columns ``cols`` (B,) read about ``pred`` (B,) (:func:`stack`, into ``prof`` (B, 2 half +
    1)), averaged and fitted (:func:`best_offset` about ``c0``, ``d_e`` and ``kap`` its). Returns ``(d, sd,
    amplitude, noise)``: the offset (px; NaN: no fit), its standard deviation (px), the stripe's mean amplitude and
    a column's noise (DN; from the differences of neighbouring columns' profiles within 2.5 ``s`` of the centre)."""
    m = 2 * half + 1
    got = stack(image, cols, pred, half, prof)
    y = zeros(m, np.float64)
    n = 0
    for j in range(cols.size):
        if got[j]:
            n += 1
            for k in range(m):
                y[k] += prof[j, k]
    if n < 4:
        return np.nan, np.inf, 0.0, np.inf
    for k in range(m):
        y[k] /= n
    core = min(half, int(2.5 * s) + 1)
    dif = empty((cols.size - 1) * (2 * core + 1), np.float64)
    n_dif = 0
    for j in range(cols.size - 1):
        if got[j] and got[j + 1]:
            for k in range(half - core, half + core + 1):
                dif[n_dif] = abs(prof[j + 1, k] - prof[j, k])
                n_dif += 1
    if n_dif < 8:
        return np.nan, np.inf, 0.0, np.inf
    noise = median(dif[:n_dif]) / (0.6745 * math.sqrt(2.0))
    d, curv, amp = best_offset(y, s, side, nb, nb_side, c0, d_e, kap)
    sd = math.sqrt(2.0 * noise * noise / n / curv) if curv > 0.0 else np.inf
    return d, sd, amp, noise


@callee
def line_through(u, v, lo, hi, e):  # type: ignore[no-untyped-def]
    """The least-squares line ``v = a + b (u - e)`` through the points ``[lo, hi)`` of ``u``, ``v`` (returns ``(a,
    b)``; a flat line through their mean for a single column)."""
    n = hi - lo
    sx = sy = sxx = sxy = 0.0
    for i in range(lo, hi):
        x = u[i] - e
        sx += x
        sy += v[i]
        sxx += x * x
        sxy += x * v[i]
    det = n * sxx - sx * sx
    b = (n * sxy - sx * sy) / det if det > 1e-9 else 0.0
    return (sy - b * sx) / n, b


@callee
def walk(image, occ, new, new_q, l, cu, cv, lo, hi, step, side_l, nb_row, nb_side_l, s_l, van_l, kap_l):  # type: ignore[no-untyped-def]
    """Follow laser ``l``'s piece (columns ``cu`` (P,), rows ``cv`` (P,), its points ``[lo, hi)``) outward from its
    end on the side of ``step`` (+1: its last column, -1: its first), writing the pooled rows into ``new`` (L, W)
    (NaN: none) and their quality into ``new_q`` (L, W) where the blocks pass the gate; ``occ`` (W,) the columns
    of this laser's anchors (the walk stops there), ``nb_row`` (W,) the nearest other laser's returned rows (NaN:
    none), ``side_l`` and ``nb_side_l`` (W,) their glow sides, ``s_l`` the stripe's width (px); ``van_l``, ``kap_l``
    (W,): the row of the sheet's vanishing line and the glow's growth per column (:func:`shaped_growth`; 0: a plain
    edge and the plain gate)."""
    w = image.shape[1]
    n_a = min(ANCHOR_COLS, hi - lo)
    if step > 0:
        e = cu[hi - 1]
        a, b = line_through(cu, cv, hi - n_a, hi, e)
    else:
        e = cu[lo]
        a, b = line_through(cu, cv, lo, lo + n_a, e)
    # the anchor's own last block: the reference offset
    n_r = min(BLOCK_COLS, n_a)
    rc = empty(n_r, np.int64)
    rp = empty(n_r, np.float64)
    for j in range(n_r):
        rc[j] = cu[hi - 1 - j] if step > 0 else cu[lo + j]
        rp[j] = a + b * (rc[j] - e)
    mid = rc[n_r // 2]
    half = min(math.ceil(WINDOW_SIGMAS * s_l + 2.0), MAX_HALF_PX)
    side = float(side_l[mid])
    if side == 0.0:
        return
    nb = np.nan
    if math.isfinite(nb_row[mid]):  # the other stripe's separation, held along the walk
        nb = nb_row[mid] - (a + b * (mid - e))
    nb_side = float(nb_side_l[mid])
    prof = empty((BLOCK_COLS, 2 * half + 1), np.float64)
    d_e, kap = _edge_at(rc, rp, side, van_l, kap_l)
    d0, _sd, amp, _noise = block_fit(image, rc, rp, half, s_l, side, nb, nb_side, prof, 0.0, d_e, kap)
    sd_max, amp_min = (SHAPE_SD_MAX_PX, SHAPE_AMP_MIN) if kap > 0.0 else (SD_MAX_PX, AMP_MIN)
    if not (math.isfinite(d0) and amp > 0.0):
        return
    shift = 0.0
    c = e + step
    bc = empty(BLOCK_COLS, np.int64)
    bp = empty(BLOCK_COLS, np.float64)
    while 0 <= c < w and not occ[c]:
        nb_c = 0
        while 0 <= c < w and not occ[c] and nb_c < BLOCK_COLS:
            bc[nb_c] = c
            bp[nb_c] = a + b * (c - e) + shift
            nb_c += 1
            c += step
        if nb_c < BLOCK_COLS // 2:
            return
        cols = bc[:nb_c]
        pred = bp[:nb_c]
        side_b = float(side_l[cols[nb_c // 2]])
        if side_b != side:
            return
        d_e, kap = _edge_at(cols, pred, side, van_l, kap_l)
        d, sd, amp, noise = block_fit(image, cols, pred, half, s_l, side, nb, nb_side, prof, d0, d_e, kap)
        move = d - d0
        if not (sd <= sd_max and amp >= amp_min * noise and abs(move) <= MOVE_MAX_PX):  # (NaN fails)
            return
        q = QUALITY_SCALE * (1.0 - math.exp(-amp / max(noise, 1e-9) / 8.0))
        for j in range(nb_c):
            new[l, cols[j]] = pred[j] + move
            new_q[l, cols[j]] = q
        shift += move


@inline
def _edge_at(cols, pred, side, van_l, kap_l):  # type: ignore[no-untyped-def]
    """A block's (:func:`walk`) glow edge: its rows from the sheet's vanishing row (px, at least 1) and the growth
    ``kap`` of :func:`.glow_fit.sheet_edge` there (0: a plain edge), at the block's middle column."""
    mid = cols[cols.size // 2]
    k = kap_l[mid]
    if not k > 0.0:
        return 1.0, 0.0
    p = 0.0
    for j in range(pred.size):
        p += pred[j]
    d_e = max(side * (p / pred.size - van_l[mid]), 1.0)
    return d_e, k / d_e


@inline
def shaped_growth(water, path):  # type: ignore[no-untyped-def]
    """(L, W): each laser's glow growth ``alpha 2 s D`` (px; :func:`.glow_fit.sheet_edge`'s ``kap d``) per column for
    the pooled fits, from the glow stage's ``water`` record (the attenuation told, each laser's glow share) and
    ``path`` (L, W) (:func:`lrsensor.extract.settings.glow_geometry`): where the glow stage fitted the sheet's shape
    (an attenuation told) and the laser's glow is strong (its share above :data:`.held.HELD_MAX_STEP`, where the
    glow stage's step is free); 0 elsewhere (the plain edge: a weak glow, a sharp stripe)."""
    out = zeros(path.shape, np.float64)
    alpha = water[0]
    for li in range(path.shape[0]):
        if alpha > 0.0 and 3 + li < water.size and water[3 + li] > HELD_MAX_STEP:
            for c in range(path.shape[1]):
                out[li, c] = alpha * path[li, c]
    return out


@inline
def glowing_widths(laser, own, sig, n_l):  # type: ignore[no-untyped-def]
    """Which of the ``n_l`` lasers the pooled ends take, (L,) bool: those with at least
    :data:`~lrsensor.extract.finish.STRIPE_NOISE_MIN` points whose glow-stage fit is taken (``own`` (N,), their
    ``laser`` (N,)); and their stripe's width (L,), px: the median of those fits' ``sig`` (N,)."""
    use = zeros(n_l, np.bool_)
    sig_l = zeros(n_l, np.float64)
    for li in range(n_l):
        vals = own_values(laser, own, sig, li)
        if vals is not None:
            use[li] = True
            sig_l[li] = median(vals)
    return use, sig_l


@njit
def extend_ends(image, u, v, laser, quality, glow_side, use, sig_l, vanish, kap):  # type: ignore[no-untyped-def]
    """The returned points ``(u, v, laser, quality)`` (M,) each (sorted by laser, then column) with each glowing
    stripe's dim ends pooled along it (see the module documentation); ``glow_side`` (L, W) the glow's side per
    laser and column, ``use`` (L,) bool the lasers whose stripe the glow stage fitted, ``sig_l`` (L,) their
    stripe's width (px); ``vanish``, ``kap`` (L, W): the sheets' vanishing rows and the glow's growth per laser and
    column (:func:`shaped_growth`; 0: the plain edge).

    Returns:
        ``(u, v, laser, quality)`` (K,) each, sorted the same way: the points of the anchors and of the pieces no
        pooled block reached as they were, the pooled blocks' columns with their pooled rows.
    """
    w = image.shape[1]
    n_l = glow_side.shape[0]
    m = u.size
    any_use = False
    for li in range(n_l):
        any_use |= use[li]
    if not any_use or m == 0:
        return u, v, laser, quality
    row = full((n_l, w), np.nan, np.float64)
    for t in range(m):
        row[laser[t], int(u[t])] = v[t]
    new = full((n_l, w), np.nan, np.float64)
    new_q = zeros((n_l, w), np.float64)
    for li in range(n_l):
        if not use[li]:
            continue
        # this laser's points and their pieces (gaps of at most GAP_COLS)
        lo = 0
        while lo < m and laser[lo] != li:
            lo += 1
        hi = lo
        while hi < m and laser[hi] == li:
            hi += 1
        if hi - lo < ANCHOR_MIN:
            continue
        cu = empty(hi - lo, np.int64)
        cv = empty(hi - lo, np.float64)
        for i in range(hi - lo):
            cu[i] = int(u[lo + i])
            cv[i] = v[lo + i]
        occ = zeros(w, np.bool_)
        starts = empty(hi - lo + 1, np.int64)
        n_p = 0
        for i in range(hi - lo):
            if i == 0 or cu[i] - cu[i - 1] > GAP_COLS:
                starts[n_p] = i
                n_p += 1
        starts[n_p] = hi - lo
        for p in range(n_p):
            if starts[p + 1] - starts[p] >= ANCHOR_MIN:
                for c in range(cu[starts[p]], cu[starts[p + 1] - 1] + 1):
                    occ[c] = True
        # the nearest other laser's stripe in each column (for the window)
        nb_row = full(w, np.nan, np.float64)
        nb_side = zeros(w, np.int64)
        for c in range(w):
            for lo2 in range(n_l):
                nearer = not math.isfinite(nb_row[c]) or abs(row[lo2, c] - row[li, c]) < abs(nb_row[c] - row[li, c])
                if lo2 != li and math.isfinite(row[lo2, c]) and nearer:
                    nb_row[c] = row[lo2, c]
                    nb_side[c] = glow_side[lo2, c]
        for p in range(n_p):
            a0, a1 = starts[p], starts[p + 1]
            if a1 - a0 < ANCHOR_MIN:
                continue
            for step in (1, -1):
                walk(
                    image, occ, new, new_q, li, cu, cv, a0, a1, step, glow_side[li], nb_row, nb_side, sig_l[li],
                    vanish[li], kap[li],
                )  # fmt: skip
    # the output: the points whose column no pooled block took, and the pooled columns, by laser and column
    k = 0
    for t in range(m):
        k += not math.isfinite(new[laser[t], int(u[t])])
    for li in range(n_l):
        for c in range(w):
            k += math.isfinite(new[li, c])
    u_o = empty(k, np.float64)
    v_o = empty(k, np.float64)
    l_o = empty(k, np.int64)
    q_o = empty(k, np.float64)
    j = 0
    t = 0
    for li in range(n_l):
        for c in range(w):
            has = t < m and laser[t] == li and int(u[t]) == c
            if math.isfinite(new[li, c]):
                u_o[j] = c
                v_o[j] = new[li, c]
                l_o[j] = li
                q_o[j] = new_q[li, c]
                j += 1
            elif has:
                u_o[j] = u[t]
                v_o[j] = v[t]
                l_o[j] = li
                q_o[j] = quality[t]
                j += 1
            if has:
                t += 1
    return u_o[:j], v_o[:j], l_o[:j], q_o[:j]
