"""Turbid water: a weak glow's step held at its stripe's share of the stripe's amplitude (:func:`held_share`), for
the glow stage (:mod:`lrsensor.extract.glow`; docs/water-design.md, "The weak glow's held share").

The glow is the water's and lies along the whole sheet in proportion to the stripe: a stripe that glows all along
has one share of glow, not one per column. A free step per column trades with the stripe's edge where the glow is
weak, and the fits whose glow passes their own test are the ones whose step came out large (selection); held at the
stripe's share, each fit loses that parameter and needs no test of its own. The share is the median of step fits
at a sample of the stripe's columns, untested (a test would select the large steps again).
"""

from __future__ import annotations

import numpy as np

from ._jit import callee, empty, full, zeros
from .glow_fit import fit_rounds
from .sorting import median

#: A weak glow's step is held at its stripe's share of the amplitude (:func:`held_share`; False: free per point)...
HELD_STEP = True
#: ... told from the step fits at every HELD_EVERY-th column (at least HELD_MIN_FITS of them)...
HELD_EVERY = 4
HELD_MIN_FITS = 16
#: ... where that share is at most this (stronger glows read better with the free step: at 3 m with 4 px of blur,
#: glow 0.3 and 0.5, held read 0.22 / 0.65 % with 1.8 / 7.3 % outliers against 0.24 / 0.43 and 0.4 / 0.6).
HELD_MAX_STEP = 0.2
#: A stripe glows all along where at least this many of its candidates do (a pool: glow.POOL_COLS either side).
ALONG_MIN = 17
#: A laser's share not told (its stripe did not glow all along, or too few of its sample's fits held).
UNTOLD = -2.0


@callee
def held_share(  # type: ignore[no-untyped-def]
    image, cols, laser, at, vv, sig, nb_ok, nb0, fit_me, glowing, retry, hold, cand, side, rc, hw, reach_rows, sg0,
    lo_sig, max_sig, sat_dn, ramp, n_rounds, d_rc, kap_k, s_w, shares,
):
    """(N,) the share of the stripe's amplitude the glow's step is held at in each point's fit (0: a free step). On
    each laser's stripe that glows all along (:func:`glows_along`), the step model is fitted at every
    :data:`HELD_EVERY`-th column's glowing points with the step free and untested (a test would select the fits
    whose step came out large); where the median of their steps over their amplitudes is at most
    :data:`HELD_MAX_STEP`, the stripe's glowing points take it. ``shares`` (L,) float64, written: each laser's median
    (also above :data:`HELD_MAX_STEP`), :data:`UNTOLD` where none was told."""
    n = cols.size
    n_l = at.shape[0]
    rho = zeros(n, np.float64)
    whole = glows_along(cand, glowing, laser, n_l)
    if not whole.any():
        return rho
    sample = zeros(n, np.bool_)
    for t in range(n):
        sample[t] = fit_me[t] and glowing[t] and whole[laser[t]] and not retry[t] and cols[t] % HELD_EVERY == 0
        rho[t] = -1.0 if sample[t] else 0.0
    _v, _s, f1, _r, _d, st1 = fit_rounds(
        image, cols, laser, at, vv, sig, vv, sig, nb_ok, nb0, sample & ~hold, glowing, side, rc, hw, reach_rows, sg0,
        lo_sig, max_sig, sat_dn, ramp, n_rounds[1], d_rc, kap_k, rho,
    )  # fmt: skip
    if (sample & hold).any():  # (the stripe's width held where the water told it)
        s_in = sig.copy()
        for t in range(n):
            if hold[t]:
                s_in[t] = s_w
        _v, _s, f2, _r, _d, st2 = fit_rounds(
            image, cols, laser, at, vv, sig, vv, s_in, nb_ok, nb0, sample & hold, glowing, side, rc, hw, reach_rows,
            sg0, s_w, s_w, sat_dn, ramp, n_rounds[2], d_rc, kap_k, rho,
        )  # fmt: skip
        for t in range(n):
            if hold[t]:
                f1[t] = f2[t]
                st1[0, t] = st2[0, t]
                st1[1, t] = st2[1, t]
    for t in range(n):
        rho[t] = 0.0
    for li in range(n_l):
        k = 0
        for t in range(n):
            k += sample[t] and laser[t] == li and f1[t] and st1[0, t] > 0.0
        if k < HELD_MIN_FITS:
            continue
        ratio = empty(k, np.float64)
        k = 0
        for t in range(n):
            if sample[t] and laser[t] == li and f1[t] and st1[0, t] > 0.0:
                ratio[k] = st1[1, t] / st1[0, t]
                k += 1
        r_l = median(ratio)
        shares[li] = r_l
        if not r_l <= HELD_MAX_STEP:
            continue
        for t in range(n):
            if laser[t] == li and fit_me[t] and glowing[t]:
                rho[t] = max(r_l, 1e-3)
    return rho


@callee
def carried_share(shares, cand, glowing, laser, fit_me, n_l):  # type: ignore[no-untyped-def]
    """``(rho, fresh)``: :func:`held_share`'s (N,) shares from ``shares`` (S,), each laser's as told on an earlier
    frame of the same water; ``fresh`` True where a laser whose stripe glows all along now has none told (beyond
    ``S`` or :data:`UNTOLD`): then the share must be told on this frame."""
    n = cand.size
    rho = zeros(n, np.float64)
    whole = glows_along(cand, glowing, laser, n_l)
    for li in range(n_l):
        if whole[li] and (li >= shares.size or shares[li] == UNTOLD):
            return rho, True
    for t in range(n):
        li = laser[t]
        if whole[li] and fit_me[t] and glowing[t] and shares[li] <= HELD_MAX_STEP:
            rho[t] = max(shares[li], 1e-3)
    return rho, False


@callee
def glows_along(cand, glowing, laser, n_l):  # type: ignore[no-untyped-def]
    """(L,) bool: each laser's stripe glows all along: at least a pool's worth of candidates (``cand`` (N,)), every one
    of them ``glowing`` (N,) (:func:`lrsensor.extract.glow._whole_stripe` made them so, or each showed it)."""
    n_c = zeros(n_l, np.int64)
    ok = full(n_l, True, np.bool_)
    for t in range(cand.size):
        if cand[t]:
            n_c[laser[t]] += 1
            ok[laser[t]] &= glowing[t]
    for li in range(n_l):
        ok[li] &= n_c[li] >= ALONG_MIN
    return ok
