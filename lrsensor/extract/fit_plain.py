"""The unclipped branch of the full fit, column-parallel in float64 (for the clipped and neighbour fits).

:func:`plain_fit_profiles` fits background-free profiles (m, n) float64 whose peak is the middle row: the
log-parabola start, then the Gaussian-weighted centroid (:func:`plain_fit64`), each column over its own reach, in
the full kernel's float64 arithmetic (the same results up to rounding). It also reports which profiles the full
kernel would take as wide (flat-topped) instead: those are left to it.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import inline, njit
from .columns import half_crossings


@njit
def plain_fit64(B, a0, c, sg, sigma_hint, min_sig, max_sig, wide_fwhm, iterations):  # type: ignore[no-untyped-def]
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
    xa, xb = half_crossings(B, lvl)
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


@inline
def plain_fit(W, a0, bl, slope, xl, sigma_hint, min_sig, max_sig, wide_fwhm, iterations):  # type: ignore[no-untyped-def]
    """The unclipped branch of :func:`fit_columns` for the windows ``W`` (m, n) uint8 (peak at the middle row) less
    their linear backgrounds (``bl + slope (q - xl)``, (n,) each; ``a0`` (n,) the background-free peak):
    log-parabola start, then :func:`plain_fit64`. Returns ``(centre, sigma, ok, done)``, (n,) each."""
    m, n = W.shape
    B = np.empty((m, n))
    for q in range(m):
        wq = W[q]
        bq_ = B[q]
        for t in range(n):
            bq_[t] = wq[t] - (bl[t] + slope[t] * (q - xl[t]))
    return plain_fit_profiles(B, a0, sigma_hint, min_sig, max_sig, wide_fwhm, iterations)


@njit
def plain_fit_profiles(B, a0, sigma_hint, min_sig, max_sig, wide_fwhm, iterations):  # type: ignore[no-untyped-def]
    """The unclipped branch of :func:`fit_columns` for background-free profiles ``B`` (m, n) float64 (peak at the
    middle row; ``a0`` (n,) its value): log-parabola start, then :func:`plain_fit64`.
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
    return plain_fit64(B, a0, c, sg, sigma_hint, min_sig, max_sig, wide_fwhm, iterations)
