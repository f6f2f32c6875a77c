"""Turbid water: the held fits with each other laser's stripe placed at its own held fit (:func:`placed_fits`), for
the glow stage (:mod:`lrsensor.extract.glow`; docs/water-design.md, "The other stripe at its own fit").

Blurred stripes of two lasers lie in each other's windows at far walls. A held fit (the water's width and
attenuation held) models the other stripe at a given row; at the common fit's row, which a glow pulls outward
(1.25 px at 3 m with 4 px of blur), that stripe sits on the wrong rows of the window and the fit reads it. The held
fits are run laser by laser in order (Gauss-Seidel): each laser's points with the lasers before it placed where
their held fits put them and the lasers after it at their common fits; then the lasers fitted before a neighbour
once more where that neighbour moved by more than :data:`PLACE_MOVE_PX`, started from their first held fit. Full
rounds (every point refitted whole until the rows settle) read the same rows at twice the cost.
"""

from __future__ import annotations

import os

import numpy as np

from ._jit import callee, zeros
from .glow_fit import fit_rounds
from .sorting import median

#: The held fits place the other lasers' stripes at their own held fits (False: at their common fits, one pass).
PLACE = os.environ.get("T22_PLACE", "1") == "1"
#: A laser fitted before its neighbour is fitted again where the neighbour's held fit moved it by more than this, px.
PLACE_MOVE_PX = 0.2
#: The width is told again this many times with the other stripes placed at fits that saw the sample's own.
PLACE_WIDTH = int(os.environ.get("T22_WIDTH", "1"))
#: ... then on a grid: WIDTH_POINTS widths WIDTH_STEP px apart about it, scored by the adjusted profile likelihood.
WIDTH_POINTS = int(os.environ.get("T22_GRID", "0"))
WIDTH_STEP = 0.1


@callee
def placed_fits(  # type: ignore[no-untyped-def]
    image, cols, laser, at, vv, s_in, nb_ok, nb0, hold, glowing, side, rc, hw, reach_rows, sg0, s_w, sat_dn, ramp,
    n_rounds, d_rc, kap_k, rho,
):
    """The held fits of the points ``hold`` (N,) (:func:`.glow_fit.fit_rounds`' arguments, the width ``s_w`` held;
    ``s_in`` (N,): the stripes' widths where they are placed), each laser's with the others' stripes at their own
    held fits where those are fitted first (see the module's documentation). Returns :func:`.glow_fit.fit_rounds`'
    ``(centre_row, sigma, fitted, rss, dof, steps)``."""
    n = cols.size
    n_l = at.shape[0]
    if not PLACE:
        return fit_rounds(
            image, cols, laser, at, vv, s_in, vv, s_in, nb_ok, nb0, hold, glowing, side, rc, hw, reach_rows, sg0, s_w,
            s_w, sat_dn, ramp, n_rounds, d_rc, kap_k, rho,
        )  # fmt: skip
    place = vv.copy()  # where each stripe is modelled in the others' fits
    v_h = vv.copy()
    s_h = s_in.copy()
    f_h = zeros(n, np.bool_)
    rss_h = np.full(n, np.nan)
    d_h = np.full(n, np.nan)
    st_h = zeros((3, n), np.float64)
    start = vv.copy()
    for sweep in range(2):
        for li in range(n_l - sweep):
            todo = zeros(n, np.bool_)
            for t in range(n):
                if not (hold[t] and laser[t] == li):
                    continue
                nb = nb0[t]
                if sweep == 0:
                    todo[t] = True
                else:  # its neighbour, fitted after it, moved
                    todo[t] = f_h[t] and nb >= 0 and laser[nb] > li and abs(place[nb] - vv[nb]) > PLACE_MOVE_PX
            if not todo.any():
                continue
            v, s, f, r, d, st = fit_rounds(
                image, cols, laser, at, start, s_in, place, s_in, nb_ok, nb0, todo, glowing, side, rc, hw, reach_rows,
                sg0, s_w, s_w, sat_dn, ramp, n_rounds, d_rc, kap_k, rho,
            )  # fmt: skip
            for t in range(n):
                if not todo[t] or not (f[t] or sweep == 0):
                    continue
                v_h[t] = v[t]
                s_h[t] = s[t]
                f_h[t] = f[t]
                rss_h[t] = r[t]
                d_h[t] = d[t]
                for k in range(3):
                    st_h[k, t] = st[k, t]
                if f[t]:
                    place[t] = v[t]
                    start[t] = v[t]
    return v_h, s_h, f_h, rss_h, d_h, st_h


@callee
def placed_width(  # type: ignore[no-untyped-def]
    image, cols, laser, at, vv, sig, nb_ok, nb0, part, glowing, side, rc, hw_s, reach_rows, sg0, lo_sig, max_sig,
    sat_dn, ramp, n_rounds, d_rc, kap, sample, v_s, s_s, f_s, s_w, hw_p,
):
    """The stripe's width told again with the other stripes placed at fits that saw the sample where its own fits put
    it: the points ``part`` (N,) (the glowing points sharing a column with the ``sample``) fitted with the water held
    (``kap`` (N,), width ``s_w``, windows ``hw_p``), the sample (its free-width fits ``v_s``, ``s_s``, ``f_s`` (N,))
    placed; then the sample fitted with its width free beside them (windows ``hw_s``). Returns ``(sigma, v, s, f)``:
    the median of those widths (NaN: fewer than 16 fits) and the sample's fits."""
    n = cols.size
    place = vv.copy()
    s_pl = sig.copy()
    sg0_p = sg0.copy()
    hw_o = hw_s.copy()
    todo = zeros(n, np.bool_)
    for t in range(n):
        if sample[t] and f_s[t]:
            place[t] = v_s[t]
            s_pl[t] = s_s[t]
        if part[t] and rc[t] - hw_p >= 0 and rc[t] + hw_p <= image.shape[0] - 1:
            todo[t] = True
            s_pl[t] = s_w
            sg0_p[t] = s_w
            hw_o[t] = hw_p
    vp, sp, fp, _r, _d, _st = fit_rounds(
        image, cols, laser, at, vv, sig, place, s_pl, nb_ok, nb0, todo, glowing, side, rc, hw_o, reach_rows, sg0_p, s_w,
        s_w, sat_dn, ramp, n_rounds[2], d_rc, kap, 0.0 * d_rc,
    )  # fmt: skip
    v_o = vv.copy()
    s_o = sig.copy()
    for t in range(n):
        if fp[t]:
            v_o[t] = vp[t]
            s_o[t] = sp[t]
    v2, s2, f2, _r, _d, st2 = fit_rounds(
        image, cols, laser, at, vv, sig, v_o, s_o, nb_ok, nb0, sample, glowing, side, rc, hw_s, reach_rows, sg0, lo_sig,
        max_sig, sat_dn, ramp, n_rounds[1], d_rc, kap, 0.0 * d_rc,
    )  # fmt: skip
    m = 0
    for t in range(n):
        m += f2[t] and st2[0, t] > 0.0
    if m < 16:
        return np.nan, v2, s2, f2, v_o, s_o
    pool = np.empty(m, np.float64)
    m = 0
    for t in range(n):
        if f2[t] and st2[0, t] > 0.0:
            pool[m] = s2[t]
            m += 1
    return float(median(pool)), v2, s2, f2, v_o, s_o

