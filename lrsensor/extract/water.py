"""The water's attenuation and the stripe's width told again (:func:`retell`), for :func:`.glow._attenuation`.

The first telling fits its sample of glowing points with the other stripes in their windows where the common fit
put them: that fit's centre, pulled outward by the other stripe's own glow, and its width (at 3 m with 4 px of blur
the other stripe lies 18 rows off, inside the sample's windows). The misplaced neighbour is a model error the
attenuation takes up: on noise-free layers of the turbidity model the first telling reads 0.33 /m for 0.30, with the
neighbours at their true rows and width 0.300. :func:`retell` fits those neighbours with the told water held, then
tells the attenuation again on a fine grid about the first, the sample's width held (a free width trades itself for
the glow's growth), scored so that the noise the points' own parameters take up does not bias it, and the width
again at the new attenuation."""

from __future__ import annotations

import math

import numpy as np

from ._jit import callee, empty, full, inline, zeros
from .glow_fit import fit_rounds
from .sorting import median

#: The fine grid of :func:`retell`: WATER_POINTS attenuations WATER_STEP (1/m) apart, centred on the first telling's.
WATER_STEP = 0.02
WATER_POINTS = 5


@callee
def sample_total(score_a, fit_a, use, sample):  # type: ignore[no-untyped-def]
    """The scores of the attenuations tried (:func:`.glow._alpha_fits`, :func:`retell`): the sums of ``score_a``
    (A, N) over the sample's points fitted at every row that most of them fit at (``use``); inf at the others, and
    everywhere when no point is fitted at all of them."""
    n_a, n = score_a.shape
    tot = full(n_a, np.inf, np.float64)
    for t in range(n):
        every = sample[t]
        for i in range(n_a):
            every = every and (fit_a[i, t] or not use[i])
        if not every:
            continue
        for i in range(n_a):
            if use[i]:
                tot[i] = (0.0 if math.isinf(tot[i]) else tot[i]) + score_a[i, t]
    return tot


@inline
def vertex(x0, x1, x2, y0, y1, y2):  # type: ignore[no-untyped-def]
    """The vertex of the parabola through ``(x0, y0), (x1, y1), (x2, y2)`` (``x0 < x1 < x2``, ``y1`` the least of
    the three), within ``[x0, x2]``; ``x1`` where the three do not curve upward."""
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    pa = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    pb = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / den
    return min(max(-pb / (2.0 * pa), x0), x2) if pa > 0.0 else x1


@inline
def least(grid, tot, use):  # type: ignore[no-untyped-def]
    """The ``grid`` (K,) value whose summed score ``tot`` (K,) is least, refined to the vertex of the parabola through
    it and its neighbours where both were scored (``use`` (K,)); NaN where no value was scored at all."""
    b = 0
    for i in range(1, grid.size):
        if tot[i] < tot[b]:
            b = i
    if math.isinf(tot[b]):
        return math.nan
    if 0 < b < grid.size - 1 and use[b - 1] and use[b + 1]:
        return vertex(grid[b - 1], grid[b], grid[b + 1], tot[b - 1], tot[b], tot[b + 1])
    return grid[b]


@callee
def retell(  # type: ignore[no-untyped-def]
    image,
    cols,
    laser,
    at,
    vv,
    sig,
    nb_ok,
    nb0,
    todo,
    glowing,
    side,
    rc,
    hw_s,
    reach_rows,
    sg0,
    lo_sig,
    max_sig,
    sat_dn,
    ramp,
    n_rounds,
    d_rc,
    k_pt,
    sample,
    n_s,
    alpha,
    s_w,
    hw_p,
    share,
):
    """``(alpha, sigma)`` told again (the module's docstring says why): the glowing points ``todo & glowing`` that
    share a column with the ``sample`` (of ``n_s`` points, on windows ``hw_s``) fitted with the first telling's
    ``alpha`` and width ``s_w`` held (``n_rounds[2]`` rounds, windows ``hw_p``); then the sample fitted at each of
    :data:`WATER_POINTS` attenuations about ``alpha`` with its width held at ``s_w`` and those stripes beside it,
    scored by a Cox-Reid adjusted profile likelihood (each point's ``dof log(rss)`` plus the log-determinant of its
    fit's normal matrix: the noise a point's own parameters take up changes with the attenuation, which biased the
    plain sums of log residuals high) over the points fitted at each of those that at least ``share`` of the sample
    fits at, the least refined by a parabola through it and its neighbours; the width the median of the sample's
    fits with it.
    The other arguments are :func:`.glow._attenuation`'s."""
    n = cols.size
    h = image.shape[0]
    part = zeros(n, np.bool_)
    for t in range(n):
        if sample[t]:
            for li in range(at.shape[0]):
                j = at[li, cols[t]]
                if j >= 0:
                    part[j] = True
    s_in = sig.copy()
    sg0_p = sg0.copy()
    hw_o = hw_s.copy()
    for t in range(n):
        part[t] = part[t] and todo[t] and glowing[t] and not sample[t] and rc[t] - hw_p >= 0 and rc[t] + hw_p <= h - 1
        if part[t]:
            s_in[t] = s_w
            sg0_p[t] = s_w
            hw_o[t] = hw_p
    kap = alpha * k_pt
    vp, sp, fp, _r, _d, _st = fit_rounds(
        image, cols, laser, at, vv, sig, vv, s_in, nb_ok, nb0, part, glowing, side, rc, hw_o, reach_rows, sg0_p, s_w,
        s_w, sat_dn, ramp, n_rounds[2], d_rc, kap, 0.0 * d_rc,
    )  # fmt: skip
    v_o = vv.copy()
    s_o = sig.copy()
    sig_h = sig.copy()
    sg0_h = sg0.copy()
    for t in range(n):
        if fp[t]:
            v_o[t] = vp[t]
            s_o[t] = sp[t]
        sig_h[t] = s_w if sample[t] else s_o[t]
        sg0_h[t] = s_w if sample[t] else sg0[t]
    n_f = WATER_POINTS
    fine = empty(n_f, np.float64)
    for i in range(n_f):
        fine[i] = alpha + WATER_STEP * (i - n_f // 2)
    cr_a = zeros((n_f, n), np.float64)
    fit_a = zeros((n_f, n), np.bool_)
    use = zeros(n_f, np.bool_)
    for i in range(n_f):
        if fine[i] <= 0.0:
            continue
        kap = fine[i] * k_pt
        v1, s1, f1, _r, _d, _st = fit_rounds(
            image, cols, laser, at, v_o, sig_h, v_o, sig_h, nb_ok, nb0, sample, glowing, side, rc, hw_s, reach_rows,
            sg0_h, s_w, s_w, sat_dn, ramp, n_rounds[1], d_rc, kap, 0.0 * d_rc,
        )  # fmt: skip
        for t in range(n):
            if not f1[t]:
                v1[t] = v_o[t]
                s1[t] = sg0_h[t]
        _v, _s, f2, rss, d2, st2 = fit_rounds(
            image, cols, laser, at, v1, sig_h, v1, sig_h, nb_ok, nb0, sample & f1, glowing, side, rc, hw_s, reach_rows,
            s1, s_w, s_w, sat_dn, ramp, n_rounds[0], d_rc, kap, 0.0 * d_rc,
        )  # fmt: skip
        k = 0
        for t in range(n):
            fit_a[i, t] = sample[t] and f1[t] and f2[t] and rss[t] > 0.0
            if fit_a[i, t]:
                cr_a[i, t] = d2[t] * math.log(rss[t]) + st2[2, t]
            k += fit_a[i, t]
        use[i] = k >= share * n_s
    a2 = least(fine, sample_total(cr_a, fit_a, use, sample), use)
    if math.isnan(a2):
        return alpha, s_w
    _v, s2, f2, _r, _d, st2 = fit_rounds(
        image, cols, laser, at, vv, sig, v_o, s_o, nb_ok, nb0, sample, glowing, side, rc, hw_s, reach_rows, sg0, lo_sig,
        max_sig, sat_dn, ramp, n_rounds[1], d_rc, a2 * k_pt, 0.0 * d_rc,
    )  # fmt: skip
    m = 0
    for t in range(n):
        m += f2[t] and st2[0, t] > 0.0
    if m < 16:
        return a2, s_w
    pool = empty(m, np.float64)
    m = 0
    for t in range(n):
        if f2[t] and st2[0, t] > 0.0:
            pool[m] = s2[t]
            m += 1
    return a2, float(median(pool))
