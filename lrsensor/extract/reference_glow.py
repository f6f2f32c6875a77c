"""The reference of the turbid-water stage: the joint stripe-and-glow fit in numpy, vectorized over the points.

It computes what :func:`lrsensor.extract.glow.glow_refit` computes (same arguments, same results to rounding); the
model, the trigger and why are documented in :mod:`lrsensor.extract.glow`, whose constants both read.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from . import glow
from .glow import (
    ITERATIONS,
    MAX_HALF_PX,
    MAX_MOVE_PX,
    MAX_STEP_PX,
    MEDIAN_VAR,
    MIN_SIGMA_PX,
    POOL_COLS,
    TREND_VAR,
    TRIGGER_FRAC,
    TRIGGER_ROWS,
    TRIGGER_SIGMAS,
    TRIGGER_SNR,
    WINDOW_SIGMAS,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

_upper_tail: Any = getattr(glow.upper_tail, "py_func", glow.upper_tail)


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
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, BoolArray]:
    """The joint fit of ``n`` profiles ``Y`` (n, K) on rows ``q = -(K // 2) ... K // 2`` (those where ``mask`` (n, K) is
    0 left out, and the clipped ones, at or above ``sat_dn``), from centres ``c`` and sigmas ``sg`` (n,) (rows
    relative to the window's middle), glow side ``side`` (n,) +-1, another stripe's centre and sigma ``nb_c``,
    ``nb_s`` (n,) (NaN: none). Returns ``(c, sigma, A, g, ok)``, (n,) each."""
    n, k_rows = Y.shape
    mask = mask * (sat_dn > Y)  # clipped samples left out
    q = (np.arange(k_rows) - k_rows // 2).astype(np.float64)[None, :]
    has_nb = np.isfinite(nb_c)
    c = c.copy()
    sg = sg.copy()
    good = np.ones(n, bool)
    lin = np.zeros((n, 5))
    s = side[:, None]
    for it in range(ITERATIONS + 1):
        z = (q - c[:, None]) / sg[:, None]
        gz = np.exp(-0.5 * z * z)
        u = s * z
        tail = _upper_tail(np.abs(u), gz)
        F = np.where(u >= 0.0, 1.0 - tail, tail)
        d = (q - np.where(has_nb, nb_c, 0.0)[:, None]) / nb_s[:, None]
        N = np.where(has_nb[:, None], np.exp(-0.5 * d * d), 0.0)
        X = np.stack([np.ones_like(z), np.broadcast_to(q, z.shape), gz, F, N], axis=2)
        if it == 0:  # the linear parameters alone at the start
            J, r = X, Y
        else:  # a Gauss-Newton step in all of them
            A, g = lin[:, 2:3], lin[:, 3:4]
            ph = gz * 0.3989422804014327
            dc = (A * gz * z - g * ph * s) / sg[:, None]
            ds = (A * gz * z * z - g * ph * s * z) / sg[:, None]
            J = np.concatenate([X, dc[:, :, None], ds[:, :, None]], axis=2)
            r = Y - np.einsum("nik,nk->ni", X, lin)
        J = J * mask[:, :, None]
        M = np.einsum("nik,nij->nkj", J, J)
        M[~has_nb, 4, :] = 0.0
        M[~has_nb, :, 4] = 0.0
        M[~has_nb, 4, 4] = 1.0
        step, solved = _solve(M, np.einsum("nik,ni->nk", J, r * mask))
        good &= solved
        step = np.where(good[:, None], step, 0.0)
        if it == 0:
            lin = step
            continue
        lin = lin + step[:, :5]
        c = c + np.clip(step[:, 5], -MAX_STEP_PX, MAX_STEP_PX)
        sg = np.clip(sg + np.clip(step[:, 6], -MAX_STEP_PX, MAX_STEP_PX), min_sig, max_sig)
    good &= np.isfinite(c) & (lin[:, 2] > 0.0) & (lin[:, 3] > TRIGGER_FRAC * lin[:, 2])
    return c, sg, lin[:, 2], lin[:, 3], good


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
    ``reach`` rows by 3 sigma (as :func:`lrsensor.extract.glow._neighbour`); -1: none."""
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
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """What :func:`lrsensor.extract.glow.glow_refit` computes (same arguments and results), in numpy."""
    h, w = image.shape[:2]
    n = cols.size
    n_l = side_tab.shape[0]
    green = image[:, :, 1]
    at = np.full((n_l, w), -1, np.int64)
    at[laser, cols] = np.arange(n)
    lo_sig = max(min_sig, MIN_SIGMA_PX)
    with np.errstate(invalid="ignore"):
        usable = ok & np.isfinite(vv) & (sat | (sig <= max_sig))
    nb_ok = usable & ~sat  # neighbours: unclipped fits
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
        use = (j >= 0) & cand[np.maximum(j, 0)]
        pool[:, :, k] = np.where(use, diff[:, np.maximum(j, 0)], np.nan)
    cnt = np.isfinite(pool[0]).sum(axis=1)
    noise = noise_l[laser[idx]] * np.sqrt(2.0 * TREND_VAR / TRIGGER_ROWS * MEDIAN_VAR / cnt)
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
        both += (j >= 0) & cand[jc] & glowing[jc]
    glowing[idx] &= 2 * both > cnt
    # the fits: round 1 with the neighbours of the common fit, round 2 (points with a neighbour) with round 1's
    v_out, s_out = vv.copy(), sig.copy()
    fitted = np.zeros(n, bool)
    for rnd in range(2):
        v1, s1 = v_out.copy(), s_out.copy()
        idx = np.flatnonzero(glowing if rnd == 0 else glowing & (nb0 >= 0) & fitted)
        if idx.size == 0:
            continue
        nb = nb0[idx] if rnd == 0 else _neighbours(idx, at, cols, laser, nb_ok, v1, s1, reach)
        have = nb >= 0
        nbc = np.maximum(nb, 0)
        nb_s = np.where(have, np.maximum(s1[nbc], lo_sig), 1.0)
        nb_c = np.where(have, v1[nbc] - rc[idx], np.nan)
        with np.errstate(invalid="ignore"):
            nb_c = np.where(np.abs(nb_c) < hw[idx] + 3.0 * nb_s, nb_c, np.nan)  # it reaches the fit's window
        big = int(hw[idx].max())
        rel = np.arange(-big, big + 1)[None, :]
        mask = (np.abs(rel) <= hw[idx][:, None]).astype(np.float64)
        rr = np.clip(rc[idx][:, None] + rel, 0, h - 1)
        Y = green[rr, cols[idx][:, None]].astype(np.float64)
        c, sg, _a, _g, good = fit_profiles(
            Y, mask, side[idx], vv[idx] - rc[idx], sg0[idx], nb_c, nb_s, lo_sig, max_sig, sat_dn
        )
        with np.errstate(invalid="ignore"):
            keep = good & (np.abs(rc[idx] + c - vv[idx]) <= MAX_MOVE_PX)
        sel = idx[keep]
        v_out[sel] = rc[sel] + c[keep]
        s_out[sel] = sg[keep]
        fitted[sel] = True
    return v_out, s_out, fitted
