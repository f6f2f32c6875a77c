"""Turbid water: the held fits' own bias, measured on the profiles they describe and removed (:func:`held_bias`).

PROTOTYPE.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import callee, full, zeros
from .glow_fit import fit_rounds, sheet_edge
from .sorting import median

#: The telling's windows (:data:`.glow.ALPHA_HALF_PX`).
ALPHA_HALF_PX = 22

#: The correction is on (False: the held fits as they are).
HELD_BIAS = False
#: PROTOTYPE: the held fits' shape about the cut Gaussian's mean.
MEAN_HELD = True
#: The bias is smoothed along the stripe over this many columns either side (mean of the points' biases).
BIAS_COLS = 32
#: The rendered profiles' peak, DN (an 8-bit image like the frame's: the fits read the same kind of image).
RENDER_PEAK_DN = 250.0
_SQRT1_2 = 0.7071067811865476
_INV_SQRT_2PI = 0.3989422804014327


#: The glow rendered as the sheet's shape convolved with the blur numerically (False: the fit's expansion).
EXACT_GLOW = True
#: The told width's own bias measured on the render too, and the rows' bias measured at the width it implies.
WIDTH_BOOT = False
#: Simpson intervals of the numerical convolution, over -+ 6 sigma.
_N_QUAD = 48


@callee
def _exact_edge(t, s, d_e, kap):  # type: ignore[no-untyped-def]
    """The sheet's glow ``h(t') = exp(kap t' / (d_e + t'))`` for ``t' >= 0`` (0 inward), convolved with a Gaussian of
    ``s`` px, at ``t`` px outward of its edge: Simpson's rule over the Gaussian's variable."""
    x_hi = min(t / s, 6.0)
    x_lo = -6.0
    if x_hi <= x_lo:
        return 0.0
    hstep = (x_hi - x_lo) / _N_QUAD
    acc = 0.0
    for k in range(_N_QUAD + 1):
        x = x_lo + k * hstep
        tp = max(t - s * x, 0.0)
        f = math.exp(kap * tp / (d_e + tp) - 0.5 * x * x)
        wgt = 1.0 if k == 0 or k == _N_QUAD else (4.0 if k % 2 == 1 else 2.0)
        acc += wgt * f
    return acc * hstep / 3.0 * _INV_SQRT_2PI


@callee
def _profile(r, c, s, a, g, side, d_e, kap):  # type: ignore[no-untyped-def]
    """One stripe's Gaussian of amplitude ``a`` and its glow of step ``g`` at row ``r`` (centre ``c``, sigma ``s``),
    the glow's shape the sheet's (:func:`.glow_fit.sheet_edge`) at ``d_e`` rows from its vanishing row."""
    z = (r - c) / s
    y = a * math.exp(-0.5 * z * z)
    if g != 0.0 and side != 0.0:
        u = side * z
        if kap > 0.0 and EXACT_GLOW:
            y += g * _exact_edge(u * s, s, d_e, kap)
            return y
        f = 0.5 * math.erfc(-u * _SQRT1_2)
        if kap > 0.0:
            y += g * sheet_edge(u * s, u, f, math.exp(-0.5 * u * u) * _INV_SQRT_2PI, s, d_e, kap)[0]
        else:
            y += g * f
    return y


@callee
def _render(img, k_of, row0, row1, at, side, rc, d_rc, kap_k, vv, sig, amp, nb_ok, drawn, v_d, s_d, st_h):  # type: ignore[no-untyped-def]
    """Render each column ``k_of`` (W,) -> image column of the held fits: the ``drawn`` points at ``v_d``, ``s_d``
    with amplitude and glow ``st_h``, the other points ``nb_ok`` at their common fit without glow."""
    n_l = at.shape[0]
    w = at.shape[1]
    prof = zeros(img.shape[0], np.float64)
    for cc in range(w):
        k = k_of[cc]
        if k < 0:
            continue
        m = row1[k] - row0[k] + 1
        for i in range(m):
            prof[i] = 0.0
        for li in range(n_l):
            j = at[li, cc]
            if j < 0:
                continue
            if drawn[j]:
                c, s, a, g = v_d[j], s_d, st_h[0, j], st_h[1, j]
            elif nb_ok[j]:
                c, s, a, g = vv[j], sig[j], amp[j], 0.0
            else:
                continue
            d_e = max(d_rc[j] + side[j] * (c - rc[j]), 1.0)
            kap = kap_k[j] / d_e
            for i in range(m):
                prof[i] += _profile(float(row0[k] + i), c, s, a, g, side[j], d_e, kap)
        top = 0.0
        for i in range(m):
            top = max(top, prof[i])
        if not top > 0.0:
            continue
        sc = RENDER_PEAK_DN / top
        for i in range(m):
            img[i, k, 1] = np.uint8(min(max(math.floor(prof[i] * sc + 0.5), 0.0), 255.0))


@callee
def held_bias(  # type: ignore[no-untyped-def]
    cols, laser, at, vv, sig, amp, s_in, nb_ok, nb0, hold, glowing, side, rc, hw, reach_rows, sg0, s_w, lo_sig,
    max_sig, sat_dn, ramp, n_rounds, d_rc, kap_k, rho, v_h, f_h, st_h,
):
    """(N,) the held fits' bias, smoothed along each stripe (0 where none is measured)."""
    n = cols.size
    n_l = at.shape[0]
    w = at.shape[1]
    drawn = hold & f_h
    k_of = full(w, -1, np.int64)
    n_k = 0
    for t in range(n):
        if drawn[t] and k_of[cols[t]] < 0:
            k_of[cols[t]] = n_k
            n_k += 1
    out = zeros(n, np.float64)
    if n_k == 0:
        return out
    hw_t = hw.copy()  # the telling's windows
    for t in range(n):
        hw_t[t] = max(hw[t], ALPHA_HALF_PX)
    row0 = full(n_k, 1 << 30, np.int64)
    row1 = full(n_k, -1, np.int64)
    for t in range(n):
        if drawn[t]:
            k = k_of[cols[t]]
            row0[k] = min(row0[k], rc[t] - hw_t[t])
            row1[k] = max(row1[k], rc[t] + hw_t[t])
    h2 = 1
    for k in range(n_k):
        h2 = max(h2, row1[k] - row0[k] + 1)
    img = zeros((h2, n_k, 3), np.uint8)
    _render(img, k_of, row0, row1, at, side, rc, d_rc, kap_k, vv, sig, amp, nb_ok, drawn, v_h, s_w, st_h)
    cols2 = zeros(n, np.int64)
    rc2 = rc.copy()
    vv2 = vv.copy()
    vh2 = v_h.copy()
    for t in range(n):
        k = k_of[cols[t]]
        if k >= 0:
            cols2[t] = k
            rc2[t] = rc[t] - row0[k]
            vv2[t] = vv[t] - row0[k]
            vh2[t] = v_h[t] - row0[k]
    v_r, _s, f_r, _r, _d, _st = fit_rounds(
        img, cols2, laser, at, vv2, sig, vv2, s_in, nb_ok, nb0, drawn, glowing, side, rc2, hw, reach_rows, sg0,
        s_w, s_w, sat_dn, ramp, n_rounds, d_rc, kap_k, rho,
    )  # fmt: skip
    if WIDTH_BOOT:
        # the width told on the render: free fits on the telling's windows, the other stripe at its held fit there
        s_nb = s_in.copy()
        for t in range(n):
            if not (drawn[t] and f_r[t]):
                v_r[t] = vh2[t]
        v_w, s_f, f_w, _r, _d, _st = fit_rounds(
            img, cols2, laser, at, vh2, sig, v_r, s_nb, nb_ok, nb0, drawn, glowing, side, rc2, hw_t, reach_rows, sg0,
            lo_sig, max_sig, sat_dn, ramp, n_rounds, d_rc, kap_k, rho,
        )  # fmt: skip
        m = 0
        for t in range(n):
            m += f_w[t]
        if m >= 16:
            pool = zeros(m, np.float64)
            m = 0
            for t in range(n):
                if f_w[t]:
                    pool[m] = s_f[t]
                    m += 1
            s_true = s_w - (median(pool) - s_w)
            print("width", s_w, median(pool), s_true)
            img[:] = 0
            _render(img, k_of, row0, row1, at, side, rc, d_rc, kap_k, vv, sig, amp, nb_ok, drawn, v_h, s_true, st_h)
            v_r, _s, f_r, _r, _d, _st = fit_rounds(
                img, cols2, laser, at, vv2, sig, vv2, s_in, nb_ok, nb0, drawn, glowing, side, rc2, hw, reach_rows,
                sg0, s_w, s_w, sat_dn, ramp, n_rounds, d_rc, kap_k, rho,
            )  # fmt: skip
    # each point's bias, then its mean over the stripe's points within BIAS_COLS columns
    bias = full(n, np.nan, np.float64)
    for t in range(n):
        if drawn[t] and f_r[t]:
            bias[t] = v_r[t] - vh2[t]
    bsum = 0.0
    bcnt = 0
    for t in range(n):
        if math.isfinite(bias[t]):
            bsum += bias[t]
            bcnt += 1
    print("bias", bsum / max(bcnt, 1), bcnt)
    for li in range(n_l):
        csum = zeros(w + 1, np.float64)
        ccnt = zeros(w + 1, np.float64)
        for cc in range(w):
            j = at[li, cc]
            ok = j >= 0 and math.isfinite(bias[j])
            csum[cc + 1] = csum[cc] + (bias[j] if ok else 0.0)
            ccnt[cc + 1] = ccnt[cc] + (1.0 if ok else 0.0)
        for cc in range(w):
            j = at[li, cc]
            if j < 0 or not drawn[j]:
                continue
            lo = max(cc - BIAS_COLS, 0)
            hi = min(cc + BIAS_COLS + 1, w)
            cnt = ccnt[hi] - ccnt[lo]
            if cnt > 0.0:
                out[j] = (csum[hi] - csum[lo]) / cnt
    return out
