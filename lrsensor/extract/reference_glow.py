"""The reference of the turbid-water stage: the joint stripe-and-glow fit in numpy, vectorized over the points.

It computes what :func:`lrsensor.extract.glow.glow_refit` computes (same arguments, same results to rounding); the
model, the trigger and why are documented in :mod:`lrsensor.extract.glow`, whose constants both read.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import glow_fit
from .glow import (
    ALPHA_GRID,
    ALPHA_HALF_PX,
    ALPHA_SAMPLE,
    ALPHA_SHARE,
    F_SELECT,
    HOLD_ROUNDS,
    MAX_HALF_PX,
    MEDIAN_VAR,
    MIN_SIGMA_PX,
    PAIR_MIN_SIGMA,
    PAIR_SIGMAS,
    POOL_COLS,
    RAMP_EVERY,
    RAMP_MARGIN,
    RAMP_MIN_STEP,
    SHAPE_MIN_SIGMA,
    SHAPE_MIN_STEP,
    TREND_VAR,
    TRIGGER_FRAC,
    TRIGGER_ROWS,
    TRIGGER_SIGMAS,
    TRIGGER_SNR,
    WATER_FRAMES,
    WINDOW_SIGMAS,
)
from .glow_fit import GLOW_MIN_FRAC, ITERATIONS, MAX_MOVE_PX, MAX_STEP_PX, N_LIN, ROUND_TOL_PX, ROUNDS, STOP_PX
from .held import ALONG_MIN, HELD_EVERY, HELD_MAX_STEP, HELD_MIN_FITS, HELD_STEP, UNTOLD
from .water import WATER_POINTS, WATER_STEP, vertex

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_upper_tail: Any = getattr(glow_fit.upper_tail, "py_func", glow_fit.upper_tail)
_vertex: Any = getattr(vertex, "py_func", vertex)
_sheet_edge: Any = getattr(glow_fit.sheet_edge, "py_func", glow_fit.sheet_edge)
_INV_SQRT_2PI = 0.3989422804014327
#: Columns of the linear parameters: background level and slope, stripe, glow step, glow ramp, neighbour.
_A, _G, _R, _Q, _N, _NG = 2, 3, 4, 5, 6, 7


def _solve(M: FloatArray, b: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Solve the systems ``M`` (n, k, k) ``x = b`` (n, k); ``(x, solved)``, the singular ones marked unsolved."""
    ok: BoolArray = np.abs(np.linalg.det(M)) > 1e-300
    Ms = np.where(ok[:, None, None], M, np.eye(M.shape[1]))
    try:
        x: FloatArray = np.asarray(np.linalg.solve(Ms, b[..., None])[..., 0], dtype=np.float64)
    except np.linalg.LinAlgError:  # pragma: no cover - det > 0 but numerically singular
        x = np.zeros_like(b)
        for i in range(M.shape[0]):
            try:
                x[i] = np.linalg.solve(Ms[i], b[i])
            except np.linalg.LinAlgError:
                ok[i] = False
    return x, ok & np.isfinite(x).all(axis=1)


def fit_profiles(
    Y: FloatArray,
    mask: FloatArray,
    side: FloatArray,
    c: FloatArray,
    sg: FloatArray,
    nb_c: FloatArray,
    nb_s: FloatArray,
    min_sig: float,
    max_sig: float,
    sat_dn: float,
    use_glow: BoolArray | None = None,
    nb_side: FloatArray | None = None,
    ramp: bool = True,
    lin0: FloatArray | None = None,
    warm: BoolArray | None = None,
    d_rc: FloatArray | None = None,
    kap_k: FloatArray | None = None,
    nb_d: FloatArray | None = None,
    nb_kap: FloatArray | None = None,
    rho: FloatArray | None = None,
) -> tuple[
    FloatArray, FloatArray, FloatArray, FloatArray, BoolArray, FloatArray, FloatArray, FloatArray, FloatArray
]:
    """The joint fit of ``n`` profiles ``Y`` (n, K) on rows ``q = -(K // 2) ... K // 2`` (those where ``mask`` (n, K) is
    0 left out, and the clipped ones, at or above ``sat_dn``), from centres ``c`` and sigmas ``sg`` (n,) (rows
    relative to the window's middle), glow side ``side`` (n,) +-1, another stripe's centre and sigma ``nb_c``,
    ``nb_s`` (n,) (NaN: none); ``use_glow`` (n,) (default all): the glow's step and ramp in the model (False: a
    stripe beside another one, no glow), ``nb_side`` (n,) the side of the other stripe's glow (0: none, default),
    ``ramp``: the glow's linear and quadratic growth outward in the model; ``warm`` (n,): one Gauss-Newton step from
    the linear parameters ``lin0`` (n, N_LIN) (an earlier fit of the same model at ``c``, ``sg``), no linear start.
    Returns ``(c, sigma, A, g, ok, rss, dof, lin, ldet)``, (n,) each, (n, N_LIN) and (n,): the fit, its residual sum of
    squares (at the last step's start, as :func:`lrsensor.extract.glow_fit.fit_into`), degrees of freedom, linear
    parameters and the log-determinant of its last normal matrix. ``d_rc``, ``kap_k`` (n,): the sheet's glow shape
    (:func:`lrsensor.extract.glow_fit.fit_one`; default none, the plain step); ``nb_d``, ``nb_kap`` (n,): the same for
    the other stripe's glow (its edge's distance from its sheet's vanishing row and its ``kap d``; default none);
    ``min_sig == max_sig``: the width held, no parameter; ``rho`` (n,): where positive, the glow's step held at that
    share of the stripe's amplitude (no parameter of its own, no glow test); where negative, the step free and the
    glow test left to the caller (default 0: the step free and tested)."""
    n, k_rows = Y.shape
    d_rc = np.ones(n) if d_rc is None else d_rc
    kap_k = np.zeros(n) if kap_k is None else kap_k
    shaped = (kap_k > 0.0)[:, None]
    glow_on = np.ones(n, bool) if use_glow is None else use_glow
    rho = np.zeros(n) if rho is None else rho
    held = glow_on & (rho > 0.0)
    rho_h = np.where(held, rho, 0.0)[:, None]
    mask = mask * (sat_dn > Y)  # clipped samples left out
    q = (np.arange(k_rows) - k_rows // 2).astype(np.float64)[None, :]
    has_nb = np.isfinite(nb_c)
    c = c.copy()
    sg = sg.copy()
    good = np.ones(n, bool)
    lin = np.zeros((n, N_LIN))
    s = side[:, None]
    nb_sd = np.zeros(n) if nb_side is None else nb_side
    # the linear parameters a point's model leaves out (an identity row and column each)
    active = np.ones((n, N_LIN + 2), bool)
    for drop, cols in ((~glow_on, [_G, _R, _Q]), (~has_nb, [_N]), (~has_nb | (nb_sd == 0.0), [_NG])):
        active[np.ix_(drop, np.array(cols))] = False
    if not ramp:
        active[:, [_R, _Q]] = False
    active[held, _G] = False  # (a held step rides on the stripe's column)
    if not min_sig < max_sig:
        active[:, N_LIN + 1] = False
    warm = np.zeros(n, bool) if warm is None else warm
    live = np.ones(n, bool)  # the fits still stepping (the others' steps are below STOP_PX: they stay)
    ldet = np.full(n, np.nan)  # the log-determinant of each fit's last normal matrix
    rss = np.full(n, np.nan)
    for it in range(ITERATIONS + 1):
        z = (q - c[:, None]) / sg[:, None]
        gz = np.exp(-0.5 * z * z)
        u = s * z
        tail = _upper_tail(np.abs(u), gz)
        F = np.where(u >= 0.0, 1.0 - tail, tail)
        ph = gz * _INV_SQRT_2PI
        R = sg[:, None] * (u * F + ph)  # the blurred edge of a glow that grows linearly outward (px)
        Qd = sg[:, None] ** 2 * ((u * u + 1.0) * F + u * ph)  # ... quadratically
        d_e = np.maximum(d_rc + side * c, 1.0)[:, None]
        with np.errstate(invalid="ignore", over="ignore"):
            B, B_t, B_s = _sheet_edge(u * sg[:, None], u, F, ph, sg[:, None], d_e, (kap_k[:, None] / d_e))
        G = np.where(shaped, B, F)  # the glow's column: the sheet's shape where it is known
        d = (q - np.where(has_nb, nb_c, 0.0)[:, None]) / nb_s[:, None]
        N = np.where(has_nb[:, None], np.exp(-0.5 * d * d), 0.0)
        ud = np.where(has_nb[:, None], nb_sd[:, None] * d, 0.0)  # the neighbour's own glow edge
        tail_d = _upper_tail(np.abs(ud), np.exp(-0.5 * ud * ud))
        NG = np.where(ud >= 0.0, 1.0 - tail_d, tail_d)
        if nb_kap is not None and nb_d is not None:  # the other stripe's glow in the sheet's shape too
            nd = np.maximum(nb_d, 1.0)[:, None]
            with np.errstate(invalid="ignore", over="ignore"):
                NB = _sheet_edge(ud * nb_s[:, None], ud, NG, np.exp(-0.5 * ud * ud) * _INV_SQRT_2PI, nb_s[:, None], nd,
                                 nb_kap[:, None] / nd)[0]  # fmt: skip
            NG = np.where((nb_kap > 0.0)[:, None], NB, NG)
        X = np.stack([np.ones_like(z), np.broadcast_to(q, z.shape), gz + rho_h * G, G, R, Qd, N, NG], axis=2)
        if it == 0:  # the linear parameters alone at the start
            J, r = X, Y
        else:  # a Gauss-Newton step in all of them
            A, g, gr, gq = lin[:, _A : _A + 1], lin[:, _G : _G + 1], lin[:, _R : _R + 1], lin[:, _Q : _Q + 1]
            g = np.where(held[:, None], rho_h * A, g)
            dc = (A * gz * z - g * ph * s) / sg[:, None] - gr * s * F - 2.0 * gq * s * R
            ds = (A * gz * z * z - g * ph * s * z) / sg[:, None] + gr * ph + 2.0 * gq * sg[:, None] * F
            sh = shaped & glow_on[:, None]
            dc = np.where(sh, A * gz * z / sg[:, None] - s * (g * B_t + gr * F + 2.0 * gq * R), dc)
            ds = np.where(sh, A * gz * z * z / sg[:, None] + g * B_s + gr * ph + 2.0 * gq * sg[:, None] * F, ds)
            J = np.concatenate([X, dc[:, :, None], ds[:, :, None]], axis=2)
            r = Y - np.einsum("nik,nk->ni", X, lin)
            rss = np.where(live, ((r * mask) ** 2).sum(axis=1), rss)  # at the step's start (glow_fit.fit_into says why)
        J = J * mask[:, :, None]
        act = active[:, : J.shape[2]]
        J = J * act[:, None, :]
        M = np.einsum("nik,nij->nkj", J, J) + np.eye(J.shape[2])[None] * ~act[:, :, None]
        b = np.einsum("nik,ni->nk", J, r * mask)
        if it > 0:
            ldet = np.where(live, np.linalg.slogdet(M)[1], ldet)
        step, solved = _solve(M, b)
        good &= solved | (warm & (it == 0))
        step = np.where((good & live)[:, None], step, 0.0)
        if it == 0:
            lin = step if lin0 is None else np.where(warm[:, None], lin0, step)
            continue
        lin = lin + step[:, :N_LIN]
        dc = np.clip(step[:, N_LIN], -MAX_STEP_PX, MAX_STEP_PX)
        ds = np.clip(sg + np.clip(step[:, N_LIN + 1], -MAX_STEP_PX, MAX_STEP_PX), min_sig, max_sig) - sg
        c = c + dc
        sg = sg + ds
        live &= ((np.abs(dc) > STOP_PX) | (np.abs(ds) > STOP_PX)) & ~warm
    dof = mask.sum(axis=1) - active.sum(axis=1)
    # the glow two sigmas outward of the edge (where its step is complete) is a glow: positive
    x2 = 2.0 * sg
    g_out = lin[:, _G] + lin[:, _R] * x2 + lin[:, _Q] * x2 * x2
    good &= np.isfinite(c) & (lin[:, _A] > 0.0) & (~glow_on | (rho != 0.0) | (g_out > GLOW_MIN_FRAC * lin[:, _A]))
    return c, sg, lin[:, _A], np.where(held, rho * lin[:, _A], lin[:, _G]), good, rss, dof, lin, ldet


def _neighbours(
    idx: IntArray,
    at: IntArray,
    cols: IntArray,
    laser: IntArray,
    usable: BoolArray,
    v_nb: FloatArray,
    s_nb: FloatArray,
    reach: IntArray,
) -> IntArray:
    """Per point of ``idx`` the nearest usable point of another laser in its column whose stripe reaches within
    ``reach`` rows by 3 sigma (as :func:`lrsensor.extract.glow_fit.neighbour`); -1: none."""
    nb = np.full(idx.size, -1, np.int64)
    best = np.full(idx.size, np.inf)
    for li in range(at.shape[0]):
        j = at[li, cols[idx]]
        jc = np.maximum(j, 0)
        with np.errstate(invalid="ignore"):
            dj = np.abs(v_nb[jc] - v_nb[idx])
            take = (laser[idx] != li) & (j >= 0) & usable[jc] & (dj < reach[idx] + 3.0 * s_nb[jc]) & (dj < best)
        nb = np.where(take, j, nb)
        best = np.where(take, dj, best)
    return nb


def _stripe_sigma(
    laser: IntArray, cand: BoolArray, sg0: FloatArray, n_l: int, counted: BoolArray | None = None
) -> FloatArray:
    """The widths :func:`lrsensor.extract.glow.glow_refit` fits with: at each candidate of a blurred stripe (the mean
    of ``sg0`` over its laser's candidates, those in ``counted`` if given, at least PAIR_MIN_SIGMA) the larger of its
    own and that mean; ``sg0`` elsewhere."""
    cn = cand if counted is None else cand & counted
    tot = np.bincount(laser[cn], weights=sg0[cn], minlength=n_l)
    cnt = np.bincount(laser[cn], minlength=n_l)
    whole = tot / np.maximum(cnt, 1)
    return np.where(cand & (tot[laser] >= PAIR_MIN_SIGMA * cnt[laser]), np.maximum(sg0, whole[laser]), sg0)


def glow_refit(
    image: NDArray[np.uint8],
    cols: IntArray,
    laser: IntArray,
    side_tab: IntArray,
    vv: FloatArray,
    amp: FloatArray,
    sig: FloatArray,
    sat: BoolArray,
    ok: BoolArray,
    lnoise: FloatArray,
    noise_l: FloatArray,
    min_sig: float,
    max_sig: float,
    sat_dn: float,
    green_ratio: float,
    vanish: FloatArray,
    path_k: FloatArray,
    water: FloatArray,
    retry: BoolArray | None = None,
) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray, FloatArray]:
    """What :func:`lrsensor.extract.glow.glow_refit` computes (same arguments and results; ``retry`` None: none), in
    numpy."""
    h, w = image.shape[:2]
    n = cols.size
    n_l = side_tab.shape[0]
    green = image[:, :, 1]
    at = np.full((n_l, w), -1, np.int64)
    at[laser, cols] = np.arange(n)
    lo_sig = max(min_sig, MIN_SIGMA_PX)
    with np.errstate(invalid="ignore"):
        usable = ok & np.isfinite(vv) & (sat | (sig <= max_sig))
    retry = np.zeros(n, bool) if retry is None else retry
    nb_ok = usable & ~sat & ~retry  # neighbours: unclipped fits (not the common fit's refused: glow.glow_refit)
    side = np.where(usable, side_tab[laser, cols], 0).astype(np.float64)
    sg0 = np.clip(np.where(usable, sig, 1.0), lo_sig, max_sig)
    rc = np.floor(np.where(usable, vv, 0.0) + 0.5).astype(np.int64)
    hw = np.minimum(np.ceil(WINDOW_SIGMAS * sg0).astype(np.int64) + 2, MAX_HALF_PX)
    kt = np.ceil(TRIGGER_SIGMAS * sg0).astype(np.int64) + 1
    reach = np.maximum(hw, 2 * kt + 1 + TRIGGER_ROWS)
    cand = usable & (side != 0.0) & (rc - reach >= 0) & (rc + reach <= h - 1)
    # does a glow show? the outer rows over the inner ones (another laser's stripe subtracted), pooled along
    idx = np.flatnonzero(cand)
    nb0 = np.full(n, -1, np.int64)
    nb0[idx] = _neighbours(idx, at, cols, laser, nb_ok, vv, sig, reach)
    diff = np.zeros((4, n))  # the step in green (neighbour subtracted), and raw in green, red and blue
    nb = nb0[idx]
    have = nb >= 0
    nbc = np.maximum(nb, 0)
    i = np.arange(TRIGGER_ROWS)[None, :]
    s_i = side[idx].astype(np.int64)[:, None]
    for k0, wgt in ((kt[idx], 2.0), (2 * kt[idx] + 1, -1.0)):
        for sgn in (1, -1):
            rr = rc[idx][:, None] + sgn * s_i * (k0[:, None] + i)
            val = green[rr, cols[idx][:, None]].astype(np.float64)
            diff[1, idx] += wgt * sgn * val.sum(axis=1)
            e = (rr - vv[nbc][:, None]) / np.maximum(sig[nbc], lo_sig)[:, None]
            val = val - np.where(have[:, None], amp[nbc][:, None] * np.exp(-0.5 * e * e), 0.0)
            diff[0, idx] += wgt * sgn * val.sum(axis=1)
            for row, ch in ((2, 2), (3, 0)):
                diff[row, idx] += wgt * sgn * image[rr, cols[idx][:, None], ch].astype(np.float64).sum(axis=1)
    diff /= TRIGGER_ROWS
    pool = np.full((4, idx.size, 2 * POOL_COLS + 1), np.nan)
    for k, off in enumerate(range(-POOL_COLS, POOL_COLS + 1)):
        cc = cols[idx] + off
        inside = (cc >= 0) & (cc < w)
        j = np.where(inside, at[laser[idx], np.clip(cc, 0, w - 1)], -1)
        # (the common fit's refused points take no part: glow.glow_refit)
        use = (j >= 0) & cand[np.maximum(j, 0)] & ~retry[np.maximum(j, 0)]
        pool[:, :, k] = np.where(use, diff[:, np.maximum(j, 0)], np.nan)
    cnt = np.isfinite(pool[0]).sum(axis=1)
    noise = noise_l[laser[idx]] * np.sqrt(2.0 * TREND_VAR / TRIGGER_ROWS * MEDIAN_VAR / np.maximum(cnt, 1))
    thr = np.maximum(TRIGGER_SNR * noise, TRIGGER_FRAC * amp[idx])
    with np.errstate(invalid="ignore"):
        above = (pool[0] > thr[:, None]).sum(axis=1)
    sums = np.nansum(pool[1:], axis=2)  # (3, n_idx): raw green, red, blue
    glowing = np.zeros(n, bool)
    # the median step exceeds the threshold, and the pooled raw step has the laser's colour
    glowing[idx] = (2 * above > cnt) & (sums[0] > green_ratio * sums[1]) & (sums[0] > green_ratio * sums[2])
    # and so does the majority of the points around
    both = np.zeros(idx.size, np.int64)
    for off in range(-POOL_COLS, POOL_COLS + 1):
        cc = cols[idx] + off
        inside = (cc >= 0) & (cc < w)
        j = np.where(inside, at[laser[idx], np.clip(cc, 0, w - 1)], -1)
        jc = np.maximum(j, 0)
        both += (j >= 0) & cand[jc] & glowing[jc] & ~retry[jc]
    glowing[idx] &= 2 * both > cnt
    # the whole stripe where it shows the glow as a whole (glow._whole_stripe): a pool's worth of its points show it,
    # and its median step over all its points exceeds the trigger's share of their median amplitude and its noise
    # (the common fit's refused points left out of the test)
    n_c = np.bincount(laser[cand & ~retry], minlength=n_l)
    n_g = np.bincount(laser[cand & glowing & ~retry], minlength=n_l)
    whole = np.zeros(n_l, bool)
    for li in np.flatnonzero(n_g >= 2 * POOL_COLS + 1):
        sel = cand & ~retry & (laser == li)
        noise_m = noise_l[li] * np.sqrt(2.0 * TREND_VAR / TRIGGER_ROWS * MEDIAN_VAR / n_c[li])
        whole[li] = np.median(diff[0, sel]) > max(TRIGGER_SNR * noise_m, TRIGGER_FRAC * np.median(amp[sel]))
    glowing |= cand & whole[laser]
    # the blurred stripes beside another laser's whose Gaussians overlap within PAIR_SIGMAS sigmas each: fitted with
    # it (no glow term where none shows)
    # (the stripes' widths taken along them: glow.glow_refit)
    sgp = _stripe_sigma(laser, cand, sg0, n_l, ~retry)
    idx = np.flatnonzero(cand & (nb0 >= 0))
    nbc = nb0[idx]
    with np.errstate(invalid="ignore"):
        s_nb = sgp[nbc]
        near = (np.abs(vv[nbc] - vv[idx]) < PAIR_SIGMAS * (sgp[idx] + s_nb)) & (
            np.minimum(sgp[idx], s_nb) >= PAIR_MIN_SIGMA
        )
    paired = np.zeros(n, bool)
    paired[idx[near]] = True
    # the fits start from the pooled width, on a window of that width (inside the image)
    todo = glowing | paired
    sg0 = np.where(todo, sgp, sg0)
    hw = np.where(todo, np.minimum(np.ceil(WINDOW_SIGMAS * sg0).astype(np.int64) + 2, MAX_HALF_PX), hw)
    todo &= (rc - hw >= 0) & (rc + hw <= h - 1)
    if not (todo & ~retry).any():  # the refused points only where the common fits' are fitted (glow.glow_refit)
        todo[:] = False
    reach = np.maximum(hw, 2 * kt + 1 + TRIGGER_ROWS)

    def rounds(
        ramp: bool,
        todo: BoolArray,
        v_init: FloatArray,
        s_init: FloatArray,
        n_rounds: int = ROUNDS,
        kap: FloatArray | None = None,
        hw: IntArray = hw,
        vv: FloatArray = vv,
        sg0: FloatArray = sg0,
        lo_sig: float = lo_sig,
        max_sig: float = max_sig,
        rho: FloatArray | None = None,
    ) -> tuple[FloatArray, FloatArray, BoolArray, FloatArray, FloatArray, FloatArray]:
        kap = kap_k if kap is None else kap
        rho = np.zeros(n) if rho is None else rho
        v_out, s_out = v_init.copy(), s_init.copy()
        fitted = np.zeros(n, bool)
        steps = np.zeros((3, n))
        rss = np.full(n, np.nan)
        dof = np.full(n, np.nan)
        last = np.full((3, n), np.nan)  # the other stripe (centre, sigma, its glow's side) in each point's last fit
        lin_t = np.zeros((n, N_LIN))  # each point's last fit's linear parameters
        for rnd in range(n_rounds):
            v1, s1 = v_out.copy(), s_out.copy()
            idx = np.flatnonzero(todo if rnd == 0 else todo & (nb0 >= 0) & fitted)
            if idx.size == 0:
                break
            nb = nb0[idx] if rnd == 0 else _neighbours(idx, at, cols, laser, nb_ok, v1, s1, reach)
            have = nb >= 0
            nbc = np.maximum(nb, 0)
            nb_s = np.where(have, np.maximum(s1[nbc], lo_sig), 1.0)
            nb_c = np.where(have, v1[nbc] - rc[idx], np.nan)
            with np.errstate(invalid="ignore"):
                nb_c = np.where(np.abs(nb_c) < hw[idx] + 3.0 * nb_s, nb_c, np.nan)  # it reaches the fit's window
            if rnd > 0:  # refitted only where the other stripe moved
                l_c, l_s = last[0, idx], last[1, idx]
                with np.errstate(invalid="ignore"):
                    e = np.maximum(np.abs(nb_c) - hw[idx], 0.0) / nb_s  # glow_fit.reach_weight
                    moved = np.maximum(np.abs(nb_c - l_c), np.abs(nb_s - l_s)) * np.exp(-0.5 * e * e)
                    same = (np.isnan(nb_c) & np.isnan(l_c)) | (moved <= ROUND_TOL_PX)
                idx, nb, have, nbc, nb_s, nb_c = (x[~same] for x in (idx, nb, have, nbc, nb_s, nb_c))
                if idx.size == 0:
                    break
            nb_side = np.where(have & glowing[nbc] & (np.abs(nb_c) <= hw[idx]), side[nbc], 0.0)  # its glow's edge
            # one step from the last fit where its model stays (glow_fit.fit_rounds)
            with np.errstate(invalid="ignore"):
                tail = (np.abs(nb_c) > hw[idx]) & (np.abs(last[0, idx]) > hw[idx])
            cold = (rnd == 0) | (glowing[idx] & ~tail)
            warm = ~cold & (np.isnan(nb_c) == np.isnan(last[0, idx])) & (nb_side == last[2, idx])
            last[0, idx] = nb_c
            last[1, idx] = nb_s
            last[2, idx] = nb_side
            big = int(hw[idx].max())
            rel = np.arange(-big, big + 1)[None, :]
            mask = (np.abs(rel) <= hw[idx][:, None]).astype(np.float64)
            rr = np.clip(rc[idx][:, None] + rel, 0, h - 1)
            Y = green[rr, cols[idx][:, None]].astype(np.float64)
            # the common fit, then each point's last fit (glowing points: the common fit again, glow_fit.fit_rounds)
            start = (np.where(cold, vv[idx], v_out[idx]), np.where(cold, sg0[idx], s_out[idx]))
            c, sg, a_, g_, good, rs, df, lin, ld = fit_profiles(
                Y,
                mask,
                side[idx],
                start[0] - rc[idx],
                start[1],
                nb_c,
                nb_s,
                lo_sig,
                max_sig,
                sat_dn,
                glowing[idx],
                nb_side,
                ramp,
                lin_t[idx],
                warm,
                d_rc[idx],
                kap[idx],
                np.where(have, d_rc[nbc] + side[nbc] * (v1[nbc] - rc[nbc]), 1.0),
                np.where(have, kap[nbc], 0.0),
                rho[idx],
            )
            with np.errstate(invalid="ignore"):
                keep = good & (np.abs(rc[idx] + c - vv[idx]) <= MAX_MOVE_PX)
            sel = idx[keep]
            v_out[sel] = rc[sel] + c[keep]
            s_out[sel] = sg[keep]
            rss[sel] = rs[keep]
            steps[:, sel] = np.stack([a_[keep], g_[keep], ld[keep]])
            dof[sel] = df[keep]
            fitted[sel] = True
            lin_t[sel] = lin[keep]
        return v_out, s_out, fitted, rss, dof, steps

    def pooled(values: FloatArray) -> FloatArray:
        """Sums (k, n) of ``values`` (k, n) over each point's stripe within POOL_COLS columns either side."""
        acc = np.zeros_like(values)
        for off in range(-POOL_COLS, POOL_COLS + 1):
            cc = cols + off
            inside = (cc >= 0) & (cc < w)
            j = np.where(inside, at[laser, np.clip(cc, 0, w - 1)], -1)
            acc += np.where(j >= 0, values[:, np.maximum(j, 0)], 0.0)
        return acc

    # the glow's shape: the sheet's, with the water's attenuation and the stripe's width told at a sample
    # (glow._attenuation)
    d_rc = np.where(todo, side * (rc - vanish[laser, cols]), 1.0)
    k_pt = np.where(todo & (d_rc > 1.0), path_k[laser, cols], 0.0)
    kap_k = np.zeros(n)
    g_fit = todo & glowing & ~retry
    alpha, s_w = 0.0, 0.0
    carried = bool(g_fit.sum() >= ALPHA_SAMPLE and water[2] < WATER_FRAMES)
    if g_fit.sum() >= ALPHA_SAMPLE:
        if carried:  # (glow.glow_refit's water)
            alpha, s_w = float(water[0]), float(water[1])
        else:
            told = glowing & ~retry
            alpha, s_w = _attenuation(rounds, vv, sig, cols, laser, at, amp, todo, told, k_pt, rc, hw, sg0, h)
            if s_w < SHAPE_MIN_SIGMA:  # a sharp stripe: the step and its ramp (glow.SHAPE_MIN_SIGMA)
                alpha, s_w = 0.0, 0.0
            water[:3] = (alpha, s_w, 0.0)
        water[2] += 1.0
    kap_k = alpha * k_pt
    hold = np.zeros(n, bool)
    if s_w > 0.0:
        hw_t = min(int(np.ceil(WINDOW_SIGMAS * s_w)) + 2, MAX_HALF_PX)
        hold = todo & glowing & (rc - hw_t >= 0) & (rc + hw_t <= h - 1)
        sg0 = np.where(hold, s_w, sg0)
        hw = np.where(hold, hw_t, hw)
    # the step model; then the ramp where the glow is strong enough to tell its ramp from the stripe (the pooled step
    # over the stripe's peak), with the other stripes where the step model put them
    s_h_in = np.where(hold, s_w, sig)
    # a weak glow's step held at its stripe's proportion, told at a sample of the stripes that glow all along
    # (held.held_share)
    rho = np.zeros(n)
    n_cl = np.bincount(laser[cand], minlength=n_l)
    along = (n_cl >= ALONG_MIN) & (np.bincount(laser[cand & ~glowing], minlength=n_l) == 0)
    shares = water[3:]  # (the share told with the water is carried with it: glow.glow_refit)
    told_now = bool(g_fit.sum() >= ALPHA_SAMPLE and not carried)
    if told_now:
        shares[:] = UNTOLD
    fresh = True
    if HELD_STEP and along.any() and carried:
        known = np.array([li < shares.size and shares[li] != UNTOLD for li in range(n_l)])
        fresh = bool((along & ~known).any())
        if not fresh:
            r_c = np.array([shares[li] if li < shares.size else 0.0 for li in range(n_l)])
            use = todo & glowing & along[laser] & (r_c[laser] <= HELD_MAX_STEP)
            rho[use] = np.maximum(r_c[laser[use]], 1e-3)
    if HELD_STEP and along.any() and fresh:
        sample = todo & glowing & along[laser] & ~retry & (cols % HELD_EVERY == 0)
        r_s = np.where(sample, -1.0, 0.0)
        _v, _s, f1, _r, _d, st1 = rounds(False, sample & ~hold, vv, sig, hw=hw, sg0=sg0, rho=r_s)
        if (sample & hold).any():
            _v, _s, f2, _r, _d, st2 = rounds(
                False, sample & hold, vv, s_h_in, HOLD_ROUNDS, hw=hw, sg0=sg0, lo_sig=s_w, max_sig=s_w, rho=r_s
            )
            f1, st1 = np.where(hold, f2, f1), np.where(hold, st2, st1)
        told = sample & f1 & (st1[0] > 0.0)
        for lh in range(n_l):
            mine = told & (laser == lh)
            if mine.sum() < HELD_MIN_FITS:
                continue
            r_l = float(np.median(st1[1, mine] / st1[0, mine]))
            if told_now and lh < shares.size:
                shares[lh] = r_l
            if r_l <= HELD_MAX_STEP:
                rho[todo & glowing & (laser == lh)] = max(r_l, 1e-3)
    v0, s0, f0, rss0, d0, st0 = rounds(False, todo & ~hold, vv, sig, hw=hw, sg0=sg0, rho=rho)
    if s_w > 0.0:
        v_h, s_h, f_h, rss_h, d_h, st_h = rounds(
            False, hold, vv, s_h_in, HOLD_ROUNDS, hw=hw, sg0=sg0, lo_sig=s_w, max_sig=s_w, rho=rho
        )
        v0, s0, f0 = np.where(hold, v_h, v0), np.where(hold, s_h, s0), np.where(hold, f_h, f0)
        rss0, d0, st0 = np.where(hold, rss_h, rss0), np.where(hold, d_h, d0), np.where(hold, st_h, st0)
    g_on = f0 & glowing
    a_g = pooled(np.stack([np.where(g_on, st0[0], 0.0), np.where(g_on, st0[1], 0.0)]))
    strong = glowing & (a_g[0] > 0.0) & (a_g[1] >= RAMP_MIN_STEP * a_g[0])

    def pooled_f(f2: BoolArray, rss2: FloatArray, dof2: FloatArray) -> FloatArray:
        """The ramp's F statistic at each point, pooled over its stretch's glowing points fitted with and without
        it (glow._pooled_f); NaN where none is."""
        pair = f0 & f2 & glowing
        acc = pooled(np.stack([np.where(pair, x, 0.0) for x in (rss0 - rss2, rss2, dof2, np.ones(n))]))
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.asarray((acc[0] / (2.0 * acc[3])) / (acc[1] / acc[2]))

    # the ramp's F test, first per stretch at every RAMP_EVERY-th column's strong points; then at every strong point
    # of the stretches that come within RAMP_MARGIN of the bar, taken where the F pooled over all of them passes it
    # (the sampled test in one round: glow_refit)
    # (not where the sheet's shape is in use: it is the glow's growth)
    if alpha <= 0.0:
        _v2, _s2, f2, rss2, dof2, _st2 = rounds(True, strong & (cols % RAMP_EVERY == 0), v0, s0, 1, hw=hw, sg0=sg0)
        maybe = strong & (pooled_f(f2, rss2, dof2) > RAMP_MARGIN * F_SELECT)
        v3, s3, f3, rss3, dof3, st3 = rounds(True, maybe, v0, s0, hw=hw, sg0=sg0)
        f3 &= pooled_f(f3, rss3, dof3) > F_SELECT
    else:
        v3, s3, f3, rss3, dof3, st3 = v0, s0, np.zeros(n, bool), rss0, d0, st0
    # the gate's amplitude and noise: the fit taken's (glow.glow_refit)
    with np.errstate(divide="ignore", invalid="ignore"):
        n0 = np.sqrt(np.where(d0 > 0.0, rss0 / d0, np.nan))
        n3 = np.sqrt(np.where(dof3 > 0.0, rss3 / dof3, np.nan))
    a_out = np.where(f3, st3[0], np.where(f0, st0[0], amp))
    n_out = np.where(f3, n3, np.where(f0, n0, lnoise))
    n_out = np.where(np.isfinite(n_out), n_out, lnoise)
    return np.where(f3, v3, v0), np.where(f3, s3, s0), f0 | f3, a_out, n_out


def _attenuation(
    rounds: Any,
    vv: FloatArray,
    sig: FloatArray,
    cols: IntArray,
    laser: IntArray,
    at: IntArray,
    amp: FloatArray,
    todo: BoolArray,
    glowing: BoolArray,
    k_pt: FloatArray,
    rc: IntArray,
    hw: IntArray,
    sg0: FloatArray,
    h: int,
) -> tuple[float, float]:
    """:func:`lrsensor.extract.glow._attenuation`: ``(alpha, sigma)`` of the frame from a sample (``rounds``: the
    reference's fits)."""
    n = cols.size
    n_l = at.shape[0]
    sample = np.zeros(n, bool)
    h_a = np.maximum(hw, ALPHA_HALF_PX)
    elig = todo & glowing & (k_pt > 0.0) & (rc - h_a >= 0) & (rc + h_a <= h - 1)
    for li in range(n_l):
        pts = at[li][at[li] >= 0]
        pts = pts[elig[pts]]  # along the stripe's columns
        m = pts.size
        if m == 0:
            continue
        bins = np.arange(m) * ALPHA_SAMPLE // m
        for b in np.unique(bins):
            in_b = pts[bins == b]
            sample[in_b[int(np.argmax(amp[in_b]))]] = True
    n_s = int(sample.sum())
    if n_s == 0:
        return 0.0, 0.0
    hw_s = np.where(sample, h_a, hw)

    def fits(grid: FloatArray) -> tuple[FloatArray, BoolArray, BoolArray]:
        rss_a = np.full((grid.size, n), np.nan)
        fit_a = np.zeros((grid.size, n), bool)
        for i, a in enumerate(grid):
            kap = a * k_pt
            v1, s1, f1, _r, _d, _st = rounds(False, sample, vv, sig, ROUNDS, kap, hw_s)
            v1 = np.where(f1, v1, vv)
            s1 = np.where(f1, s1, sg0)
            _v, _s, f2, rss, _d2, _st2 = rounds(False, sample & f1, v1, s1, 1, kap, hw_s, v1, s1)
            with np.errstate(invalid="ignore"):
                fit_a[i] = sample & f1 & f2 & (rss > 0.0)
            rss_a[i] = rss
        return rss_a, fit_a, fit_a.sum(axis=1) >= ALPHA_SHARE * n_s

    def total(rss_a: FloatArray, fit_a: BoolArray, use: BoolArray) -> FloatArray:
        every = sample & np.all(fit_a | ~use[:, None], axis=0)
        tot = np.full(use.size, np.inf)
        if every.any():
            with np.errstate(invalid="ignore"):
                sums = np.log(np.where(every[None, :], rss_a, 1.0)).sum(axis=1)
            tot = np.where(use, sums, np.inf)
        return tot

    grid = np.array(ALPHA_GRID, np.float64)
    rss_a, fit_a, use = fits(grid)
    tot = total(rss_a, fit_a, use)
    b = int(np.argmin(tot))
    if np.isinf(tot[b]):
        return 0.0, 0.0
    alpha = float(grid[b])
    if 0 < b < grid.size - 1 and use[b - 1] and use[b + 1]:
        alpha = float(_vertex(grid[b - 1], grid[b], grid[b + 1], tot[b - 1], tot[b], tot[b + 1]))
    _v, s1, f1, _r, _d, st1 = rounds(False, sample, vv, sig, ROUNDS, alpha * k_pt, hw_s)
    f1 = f1 & (st1[0] > 0.0)
    if alpha <= 0.0 or f1.sum() < 16:
        return alpha, 0.0
    if np.median(st1[1, f1] / st1[0, f1]) < SHAPE_MIN_STEP:  # a weak glow (glow.SHAPE_MIN_STEP)
        return 0.0, 0.0
    return _retell(rounds, vv, sig, cols, at, todo, glowing, k_pt, rc, sg0, h, sample, n_s, hw_s, alpha,
                   float(np.median(s1[f1])))  # fmt: skip


def _retell(
    rounds: Any,
    vv: FloatArray,
    sig: FloatArray,
    cols: IntArray,
    at: IntArray,
    todo: BoolArray,
    glowing: BoolArray,
    k_pt: FloatArray,
    rc: IntArray,
    sg0: FloatArray,
    h: int,
    sample: BoolArray,
    n_s: int,
    hw_s: IntArray,
    alpha: float,
    s_w: float,
) -> tuple[float, float]:
    """:func:`lrsensor.extract.water.retell`: the attenuation and width told again with the sample's other stripes
    where the told water puts them."""
    n = cols.size
    part = np.zeros(n, bool)
    for li in range(at.shape[0]):
        j = at[li, cols[sample]]
        part[j[j >= 0]] = True
    hw_p = min(int(np.ceil(WINDOW_SIGMAS * s_w)) + 2, MAX_HALF_PX)
    part &= todo & glowing & ~sample & (rc - hw_p >= 0) & (rc + hw_p <= h - 1)
    hw_o = np.where(part, hw_p, hw_s)
    vp, sp, fp, _r, _d, _st = rounds(
        False, part, vv, np.where(part, s_w, sig), HOLD_ROUNDS, alpha * k_pt, hw_o, vv, np.where(part, s_w, sg0), s_w,
        s_w,
    )  # fmt: skip
    v_o = np.where(fp, vp, vv)
    s_o = np.where(fp, sp, sig)
    sig_h = np.where(sample, s_w, s_o)
    sg0_h = np.where(sample, s_w, sg0)
    fine = alpha + WATER_STEP * (np.arange(WATER_POINTS) - WATER_POINTS // 2)
    rss_a = np.full((fine.size, n), np.nan)
    fit_a = np.zeros((fine.size, n), bool)
    cr_a = np.zeros((fine.size, n))
    for i, a in enumerate(fine):
        if a <= 0.0:
            continue
        kap = a * k_pt
        v1, s1, f1, _r, _d, _st = rounds(False, sample, v_o, sig_h, ROUNDS, kap, hw_s, v_o, sg0_h, s_w, s_w)
        v1 = np.where(f1, v1, v_o)
        s1 = np.where(f1, s1, sg0_h)
        _v, _s, f2, rss, d2, st2 = rounds(False, sample & f1, v1, sig_h, 1, kap, hw_s, v1, s1, s_w, s_w)
        with np.errstate(invalid="ignore"):
            fit_a[i] = sample & f1 & f2 & (rss > 0.0)
            cr_a[i] = np.where(fit_a[i], d2 * np.log(np.where(fit_a[i], rss, 1.0)) + st2[2], 0.0)
        rss_a[i] = rss
    use = fit_a.sum(axis=1) >= ALPHA_SHARE * n_s
    every = sample & np.all(fit_a | ~use[:, None], axis=0)
    tot = np.where(use & every.any(), np.where(every[None, :], cr_a, 0.0).sum(axis=1), np.inf)
    c = int(np.argmin(tot))
    if np.isinf(tot[c]):
        return alpha, s_w
    a2 = float(fine[c])
    if 0 < c < fine.size - 1 and use[c - 1] and use[c + 1]:
        a2 = float(_vertex(fine[c - 1], fine[c], fine[c + 1], tot[c - 1], tot[c], tot[c + 1]))
    _v, s2, f2, _r, _d, st2 = rounds(False, sample, v_o, s_o, ROUNDS, a2 * k_pt, hw_s)
    f2 = f2 & (st2[0] > 0.0)
    if f2.sum() < 16:
        return a2, s_w
    return a2, float(np.median(s2[f2]))
