"""Turbid water: the stripe's centre fitted jointly with the laser sheet's glow (:func:`glow_refit`).

What the glow is. In turbid water the laser sheet itself is visible: the water inside the sheet scatters light
back to the camera. The sheet between the camera and the wall images on the side of the stripe away from the
plane's vanishing line (above the top laser's stripe, below the bottom one's) and ENDS at the stripe, where the
sheet meets the wall; the wall cuts the sheet along the sheet's own thickness profile, so the glow's edge is a
step whose 50 % point is the stripe's centre, and forward scatter blurs stripe and edge alike. A column's profile
is then, with ``z = (v - c) / sigma`` and ``s`` the glow's side (+1: the glow at larger rows)::

    y(v) = b0 + b1 (v - v0) + A exp(-z^2 / 2) + g Phi(s z)          [+ a N(v): another laser's stripe close by]

The stripe (a Gaussian) and the glow's edge (a blurred step) share their centre ``c`` and their width ``sigma``
(a sheet of Gaussian thickness blurred by a Gaussian: both widths are ``sqrt(sigma_sheet^2 + blur^2)``).

Why the common fit fails there. Its linear background through two flank windows takes the step as a slope; what
the line leaves of the step is odd about the centre and pulls the Gaussian-weighted centroid towards the glow,
0.1-1.1 px on the independent turbidity model (``benchmarks/turbid_model.py``), which reads walls 0.2-10 % short.

What this stage does. Where a point's profile shows a glow, the model above is fitted by least squares on the rows
``c -+ (4.5 sigma + 2)`` (at most :data:`MAX_HALF_PX`): the linear parameters ``b0, b1, A, g`` (and ``a``, with the
neighbour's centre and width held) solved exactly at the common fit's centre and width, then :data:`ITERATIONS`
Gauss-Newton steps in all of them. Points with another laser's fitted stripe
close by are fitted twice, the second time with that stripe where its own fit put it. The fit is kept where it
converges to a stripe and a glow (``A > 0``, ``g > 0.05 A``) within :data:`MAX_MOVE_PX` of the common fit (a second
round that fails keeps the first round's); elsewhere, and wherever no glow shows (clear water), the common fit
stands untouched. Profiles taken as flat tops (thick sheets close to the wall, wider than ``max_sigma_px``) are left
alone unless clipped: the model has no flat top.

Where a glow shows: the step at each point is estimated from the green rows beyond its flanks, outer less inner, at
``2.5 sigma + 1`` rows from the centre and at twice that (``2 D_near - D_far``: a linear background cancels, a glow
that brightens outward is under-estimated a little), four rows each, another laser's stripe close by subtracted;
its median over the stripe's points within :data:`POOL_COLS` columns either side (one bright particle or a dim
column does not decide) must exceed 3.5x its noise and 5 % of the stripe's amplitude (more than half of those
steps exceed that threshold), and the step summed over them must have the laser's colour: green over red and blue
by ``min_green_ratio``, as the stripe's colour test asks (a step in the wall's shade or the ambient light is not a
glow); and most of those points must pass the test too (a glow lies along the stripe, not at a few columns).

Why this estimator, measured on the turbidity model (glow step 0.5 of the peak unless said):

- Single columns before the along-stripe smoothing: the joint fit's median row shift is within 0.03 px of zero at
  0.5-2 m for 1.5 and 4 px of blur (the common fit: +0.46 to +1.03 px).
- A background from the inner flank alone cannot work: the glow's edge is half way up at the centre, so even the
  stripe's inner half carries a quarter of the stripe's peak of glow.
- The window must be long (4.5 sigma): at 3 sigma the background's slope, the step and the centre trade off and
  the noise doubles (p5-p95 of single columns +-1.4 px against +-0.7 px at 4 px of blur).
- The glow brightens away from the wall (shorter paths through the water). On noise-free profiles the step model
  leaves 0.01-0.02 px where the glow is flat and 0.05-0.1 px inward where it brightens (0.3 /m at 1-2 m); a glow
  that grows exponentially with a free rate halves that at 1-2 m, is worse at 3 m, and on noisy frames moves no
  median by more than 0.03 px, for an eighth parameter: left out.
- The joint fit is about twice as noisy as the common fit, and costs 3-8 us a column (4 px of blur: 41 rows) where
  the common fit costs about 0.1 us: it runs only where a glow shows. The test costs about 0.3 ms a frame; on the
  simulator's named scenes (clear water, its own turbid scene with a glow blurred by 8 px, clutter) and on the
  independent box-sheet model of ``benchmarks/bench_foreign_render.py`` it fits at most a few columns a frame,
  and no median moves by more than 0.001 percentage points. Without the colour test and the majority along the
  stripe, steps in the background's shade (the same in every channel) were taken for glow: up to 360 columns of
  a frame, medians up to 0.0075 points off.

The compiled kernel is :func:`glow_refit`; the reference's is :func:`lrsensor.extract.reference_glow.glow_refit`
(numpy, vectorized over the points). Both read the constants here.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit

#: A glow shows where the outer rows exceed the inner ones by this many times the noise of the difference...
TRIGGER_SNR = 3.5
#: ... and by this share of the stripe's peak.
TRIGGER_FRAC = 0.05
#: The rows compared start this many sigmas (plus one row) from the centre, and twice as far; rows on each side.
TRIGGER_SIGMAS = 2.5
TRIGGER_ROWS = 4
#: The step is twice the difference at the near rows less that at rows twice as far (a linear background
#: cancels): its variance is TREND_VAR times that of one difference.
TREND_VAR = 5.0
#: The comparison is pooled (median) over the points of the same laser within this many columns either side.
POOL_COLS = 8
#: The variance of a median of Gaussian samples over that of their mean (pi / 2).
MEDIAN_VAR = 0.5 * math.pi
#: The fit's window: the centre -+ (WINDOW_SIGMAS sigma + 2) rows, at most MAX_HALF_PX.
WINDOW_SIGMAS = 4.5
MAX_HALF_PX = 30
#: Gauss-Newton steps after the linear start, and the largest step of the centre and of sigma per iteration, px.
ITERATIONS = 4
MAX_STEP_PX = 1.0
#: The joint fit is kept within this distance of the common fit's centre, px.
MAX_MOVE_PX = 4.0
#: Narrowest sigma the fit may take, px (a glow's edge narrower than this is not resolved by the pixels).
MIN_SIGMA_PX = 0.5
#: Phi(x) = 1 - phi(x) t P(t), t = 1 / (1 + p x), x >= 0 (Abramowitz-Stegun 26.2.17, |error| < 7.5e-8).
_AS_P = 0.2316419
_INV_SQRT_2PI = 0.3989422804014327


@inline
def upper_tail(a, gauss):  # type: ignore[no-untyped-def]
    """``1 - Phi(a)`` for ``a >= 0`` given ``gauss = exp(-a^2 / 2)`` (Abramowitz-Stegun 26.2.17)."""
    t = 1.0 / (1.0 + _AS_P * a)
    poly = t * (0.319381530 + t * (-0.356563782 + t * (1.781477937 + t * (-1.821255978 + t * 1.330274429))))
    return gauss * _INV_SQRT_2PI * poly


@njit
def _solve(M, b, k):  # type: ignore[no-untyped-def]
    """Solve ``M[:k, :k] x = b[:k]`` in place (Gaussian elimination, partial pivoting); False when singular."""
    for i in range(k):
        p = i
        for r in range(i + 1, k):
            if abs(M[r, i]) > abs(M[p, i]):
                p = r
        if not abs(M[p, i]) > 1e-12:
            return False
        if p != i:
            for j in range(k):
                M[i, j], M[p, j] = M[p, j], M[i, j]
            b[i], b[p] = b[p], b[i]
        for r in range(i + 1, k):
            f = M[r, i] / M[i, i]
            for j in range(i, k):
                M[r, j] -= f * M[i, j]
            b[r] -= f * b[i]
    for i in range(k - 1, -1, -1):
        acc = b[i]
        for j in range(i + 1, k):
            acc -= M[i, j] * b[j]
        b[i] = acc / M[i, i]
    return True


@njit
def _fit_one(y, q, side, c, sg, nb_c, nb_s, min_sig, max_sig, sat_dn):  # type: ignore[no-untyped-def]
    """The joint fit of one profile ``y`` (K,) at rows ``q`` (K,) (relative to the window's middle row) from the
    centre ``c`` and width ``sg``; ``nb_c``, ``nb_s``: another stripe's centre and sigma (NaN: none). Returns
    ``(c, sigma, A, g, ok)``. Samples at or above ``sat_dn`` (clipped) are left out.

    First the linear parameters alone at the start, then :data:`ITERATIONS` Gauss-Newton steps in all of them; each
    pass builds the normal equations row by row (one ``exp`` per row, two with a neighbour)."""
    k_rows = y.size
    has_nb = math.isfinite(nb_c)
    k = 5 if has_nb else 4
    kk = k + 2
    M = np.empty((kk, kk))
    b = np.empty(kk)
    xr = np.empty(kk)
    lin = np.zeros(k)
    for it in range(ITERATIONS + 1):
        full = it > 0
        m_ = kk if full else k
        for a in range(m_):
            b[a] = 0.0
            for j in range(a, m_):
                M[a, j] = 0.0
        for i in range(k_rows):
            if y[i] >= sat_dn:
                continue
            z = (q[i] - c) / sg
            gz = math.exp(-0.5 * z * z)
            u = side * z
            tail = upper_tail(abs(u), gz)
            xr[0] = 1.0
            xr[1] = q[i]
            xr[2] = gz
            xr[3] = 1.0 - tail if u >= 0.0 else tail
            if has_nb:
                d = (q[i] - nb_c) / nb_s
                xr[4] = math.exp(-0.5 * d * d)
            r = y[i]
            if full:
                for j in range(k):
                    r -= xr[j] * lin[j]
                ph = gz * _INV_SQRT_2PI
                xr[k] = (lin[2] * gz * z - lin[3] * ph * side) / sg
                xr[k + 1] = (lin[2] * gz * z * z - lin[3] * ph * side * z) / sg
            for a in range(m_):
                xa = xr[a]
                b[a] += xa * r
                for j in range(a, m_):
                    M[a, j] += xa * xr[j]
        for a in range(m_):
            for j in range(a + 1, m_):
                M[j, a] = M[a, j]
        if not _solve(M, b, m_):
            return c, sg, lin[2], lin[3], False
        if not full:
            for j in range(k):
                lin[j] = b[j]
            continue
        for j in range(k):
            lin[j] += b[j]
        c += min(max(b[k], -MAX_STEP_PX), MAX_STEP_PX)
        sg = min(max(sg + min(max(b[k + 1], -MAX_STEP_PX), MAX_STEP_PX), min_sig), max_sig)
    ok = math.isfinite(c) and lin[2] > 0.0 and lin[3] > TRIGGER_FRAC * lin[2]
    return c, sg, lin[2], lin[3], ok


@njit
def _neighbour(t, at, cols, laser, nb_ok, v_nb, s_nb, reach):  # type: ignore[no-untyped-def]
    """The nearest point of another laser (``nb_ok``: an unclipped fit) in the column of point ``t`` whose stripe
    (centre ``v_nb``, sigma ``s_nb``) reaches within ``reach`` rows of the point's centre ``v_nb[t]`` by 3 sigma;
    -1: none."""
    col = cols[t]
    nb = -1
    best = np.inf
    for li in range(at.shape[0]):
        j = at[li, col]
        if li == laser[t] or j < 0 or not nb_ok[j]:
            continue
        dj = abs(v_nb[j] - v_nb[t])
        if dj < reach + 3.0 * s_nb[j] and dj < best:
            best = dj
            nb = j
    return nb


@njit
def glow_refit(  # type: ignore[no-untyped-def]
    image, cols, laser, side_tab, vv, amp, sig, sat, ok, lnoise, noise_l, min_sig, max_sig, sat_dn, green_ratio
):
    """The joint stripe-and-glow fit of every point whose profile shows a glow (see the module's documentation).

    Args:
        image: (H, W, 3) uint8 BGR; cols, laser: (N,) each point's column and laser (one point per laser and
            column); side_tab: (L, W) int64, the side of each laser's stripe its glow lies on (+1: larger rows,
            -1: smaller, 0: unknown, no fit).
        vv, amp, sig, sat, ok, lnoise: (N,) the common fit's centre rows, amplitudes (DN), sigmas (px), clipped,
            accepted and flank noise (DN); noise_l: (L,) the bands' noise, DN.
        min_sig, max_sig: the accepted sigmas, px; sat_dn: green samples at or above it are clipped (left out of
            the fits: a clipped stripe is fitted on its flanks); green_ratio: a glow's step in green exceeds its steps
            in red and blue by this factor (the stripe's colour test).

    Returns:
        ``(centre_row, sigma, fitted)``: (N,) each; the common fit's centre and sigma where ``fitted`` is False.
    """
    h = image.shape[0]
    w = image.shape[1]
    n = cols.size
    n_l = side_tab.shape[0]
    at = np.full((n_l, w), -1, np.int64)
    for t in range(n):
        at[laser[t], cols[t]] = t
    lo_sig = max(min_sig, MIN_SIGMA_PX)
    # the points that can take the fit: window and trigger rows inside the image, the glow's side known
    usable = np.zeros(n, np.bool_)
    cand = np.zeros(n, np.bool_)
    nb_ok = np.zeros(n, np.bool_)
    side = np.zeros(n)
    sg0 = np.ones(n)
    rc = np.zeros(n, np.int64)
    hw = np.zeros(n, np.int64)
    kt = np.zeros(n, np.int64)
    for t in range(n):
        usable[t] = ok[t] and math.isfinite(vv[t]) and (sat[t] or sig[t] <= max_sig)
        if not usable[t]:
            continue
        side[t] = float(side_tab[laser[t], cols[t]])
        sg0[t] = min(max(sig[t], lo_sig), max_sig)
        rc[t] = int(math.floor(vv[t] + 0.5))  # noqa: RUF046 (numba: floor of a float is a float)
        hw[t] = min(int(math.ceil(WINDOW_SIGMAS * sg0[t])) + 2, MAX_HALF_PX)  # noqa: RUF046
        kt[t] = int(math.ceil(TRIGGER_SIGMAS * sg0[t])) + 1  # noqa: RUF046
        reach = max(hw[t], 2 * kt[t] + 1 + TRIGGER_ROWS)
        nb_ok[t] = not sat[t]
        cand[t] = side[t] != 0.0 and rc[t] - reach >= 0 and rc[t] + reach <= h - 1
    # does a glow show? the outer rows over the inner ones (another laser's stripe close by subtracted), at kt rows
    # from the centre and twice as far (a linear background cancels), pooled over the candidates of the same laser
    # within POOL_COLS columns
    nb0 = np.full(n, -1, np.int64)
    diff = np.zeros(n)
    diff_rgb = np.zeros((3, n))  # the raw step in green, red and blue (nothing subtracted): the glow's colour
    for t in range(n):
        if not cand[t]:
            continue
        nb = _neighbour(t, at, cols, laser, nb_ok, vv, sig, max(hw[t], 2 * kt[t] + 1 + TRIGGER_ROWS))
        nb0[t] = nb
        d = 0.0
        d_g = 0.0
        d_r = 0.0
        d_b = 0.0
        for k0, wgt in ((kt[t], 2.0), (2 * kt[t] + 1, -1.0)):
            for i in range(TRIGGER_ROWS):
                for sgn in (1, -1):
                    rr = rc[t] + sgn * int(side[t]) * (k0 + i)
                    val = float(image[rr, cols[t], 1])
                    d_g += wgt * sgn * val
                    if nb >= 0:
                        e = (rr - vv[nb]) / max(sig[nb], lo_sig)
                        val -= amp[nb] * math.exp(-0.5 * e * e)
                    d += wgt * sgn * val
                    d_r += wgt * sgn * float(image[rr, cols[t], 2])
                    d_b += wgt * sgn * float(image[rr, cols[t], 0])
        diff[t] = d / TRIGGER_ROWS
        diff_rgb[0, t] = d_g / TRIGGER_ROWS
        diff_rgb[1, t] = d_r / TRIGGER_ROWS
        diff_rgb[2, t] = d_b / TRIGGER_ROWS
    glowing = np.zeros(n, np.bool_)
    for t in range(n):
        if not cand[t]:
            continue
        lo_c = max(cols[t] - POOL_COLS, 0)
        hi_c = min(cols[t] + POOL_COLS + 1, w)
        cnt = 0
        sum_g = 0.0
        sum_r = 0.0
        sum_b = 0.0
        for cc in range(lo_c, hi_c):
            j = at[laser[t], cc]
            if j >= 0 and cand[j]:
                cnt += 1
                sum_g += diff_rgb[0, j]
                sum_r += diff_rgb[1, j]
                sum_b += diff_rgb[2, j]
        # the noise of a median of cnt such steps, each from differences of means of TRIGGER_ROWS rows (of the band's
        # pixel noise: the flanks' spread about the common fit's line holds the glow's own step)
        noise = noise_l[laser[t]] * math.sqrt(2.0 * TREND_VAR / TRIGGER_ROWS * MEDIAN_VAR / cnt)
        thr = max(TRIGGER_SNR * noise, TRIGGER_FRAC * amp[t])
        above = 0
        for cc in range(lo_c, hi_c):
            j = at[laser[t], cc]
            above += j >= 0 and cand[j] and diff[j] > thr
        # the median step exceeds the threshold, and the pooled raw step is the laser's colour (green over red and
        # blue as the stripe's colour test asks: a step of the wall's or the water's colour is not a glow; raw, since
        # a neighbour stripe close by is subtracted in green only, and it has the laser's colour too)
        glowing[t] = 2 * above > cnt and sum_g > green_ratio * sum_r and sum_g > green_ratio * sum_b
    # and so does the majority of the points around: a glow lies along the stripe, not at a few columns
    glow_run = np.zeros(n, np.bool_)
    for t in range(n):
        if not glowing[t]:
            continue
        cnt = 0
        both = 0
        for cc in range(max(cols[t] - POOL_COLS, 0), min(cols[t] + POOL_COLS + 1, w)):
            j = at[laser[t], cc]
            if j >= 0 and cand[j]:
                cnt += 1
                both += glowing[j]
        glow_run[t] = 2 * both > cnt
    glowing = glow_run
    # the fits: round 1 with the neighbours of the common fit, round 2 (points with a neighbour) with round 1's
    v_out = vv.copy()
    s_out = sig.copy()
    fitted = np.zeros(n, np.bool_)
    y = np.empty(2 * MAX_HALF_PX + 1)
    q = np.empty(2 * MAX_HALF_PX + 1)
    for rnd in range(2):
        v1 = v_out.copy()
        s1 = s_out.copy()
        for t in range(n):
            if not glowing[t] or (rnd == 1 and not (nb0[t] >= 0 and fitted[t])):
                continue
            nb = (
                nb0[t]
                if rnd == 0
                else _neighbour(t, at, cols, laser, nb_ok, v1, s1, max(hw[t], 2 * kt[t] + 1 + TRIGGER_ROWS))
            )
            nb_s = 1.0 if nb < 0 else max(s1[nb], lo_sig)
            nb_c = np.nan if nb < 0 else v1[nb] - rc[t]
            if not abs(nb_c) < hw[t] + 3.0 * nb_s:  # (also NaN) its stripe does not reach the fit's window
                nb_c = np.nan
            k_rows = 2 * hw[t] + 1
            for i in range(k_rows):
                y[i] = float(image[rc[t] - hw[t] + i, cols[t], 1])
                q[i] = float(i - hw[t])
            c, sg, _a, _g, good = _fit_one(
                y[:k_rows], q[:k_rows], side[t], vv[t] - rc[t], sg0[t], nb_c, nb_s, lo_sig, max_sig, sat_dn
            )
            if good and abs(rc[t] + c - vv[t]) <= MAX_MOVE_PX:
                v_out[t] = rc[t] + c
                s_out[t] = sg
                fitted[t] = True
    return v_out, s_out, fitted
