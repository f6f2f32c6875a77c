"""The reference's pooled dim ends (numpy): :func:`lrsensor.extract.pooled.extend_ends`, whose module documentation
explains them, with the offsets' grid of each block solved at once.

Rows in pixels, amplitudes in DN.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from . import glow_fit, pooled
from .finish import STRIPE_NOISE_MIN
from .held import HELD_MAX_STEP

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


_sheet_edge = getattr(glow_fit.sheet_edge, "py_func", glow_fit.sheet_edge)


def shaped_growth(water: FloatArray, path: FloatArray) -> FloatArray:
    """:func:`lrsensor.extract.pooled.shaped_growth`: (L, W) each laser's glow growth per column for the pooled fits
    where the glow stage fitted the sheet's shape and the laser's glow is strong, 0 elsewhere."""
    n_l = path.shape[0]
    share = np.array([water[3 + li] if 3 + li < water.size else -np.inf for li in range(n_l)])
    strong = (water[0] > 0.0) & (share > HELD_MAX_STEP)
    return np.where(strong[:, None], water[0] * path, 0.0)


def _erf(x: FloatArray) -> FloatArray:
    return np.vectorize(math.erf, otypes=[np.float64])(x)


def glowing_widths(
    laser: IntArray, own: NDArray[np.bool_], sig: FloatArray, n_l: int
) -> tuple[NDArray[np.bool_], FloatArray]:
    """:func:`lrsensor.extract.pooled.glowing_widths`: the lasers (L,) with enough glow-stage fits taken, and the
    median width (L,) of those fits, px."""
    use = np.zeros(n_l, bool)
    sig_l = np.zeros(n_l)
    for li in range(n_l):
        x = sig[own & (laser == li) & np.isfinite(sig)]
        if x.size >= STRIPE_NOISE_MIN:
            use[li] = True
            sig_l[li] = float(np.median(x))
    return use, sig_l


def _fits(
    y: FloatArray, d: FloatArray, s: float, side: float, nb: float, nb_side: float, d_e: float, kap: float
) -> tuple[FloatArray, ...]:
    """The least squares of :func:`lrsensor.extract.pooled.model_rss` at every offset ``d`` (D,): ``(rss,
    amplitude)`` (D,) each."""
    half = y.size // 2
    q = np.arange(-half, half + 1, dtype=np.float64)
    z = (q[None, :] - d[:, None]) / s
    cols = [
        np.ones_like(z),
        np.broadcast_to(q / half, z.shape),
        np.exp(-0.5 * z * z),
        0.5 * (1.0 + _erf(side * z / math.sqrt(2.0))),
    ]
    if kap > 0.0:  # the sheet's shape
        u = side * z
        cols[3] = _sheet_edge(u * s, u, cols[3], np.exp(-0.5 * u * u) * pooled.INV_SQRT_2PI, s, d_e, kap)[0]
    if math.isfinite(nb) and abs(nb) <= half + 2.0 * s:
        zn = np.broadcast_to((q - nb) / s, z.shape)
        cols.append(np.exp(-0.5 * zn * zn))
        if abs(nb) <= half:
            cols.append(0.5 * (1.0 + _erf(nb_side * zn / math.sqrt(2.0))))
    X = np.stack(cols, axis=2)  # (D, m, p)
    ata = np.einsum("dmp,dmq->dpq", X, X)
    aty = np.einsum("dmp,m->dp", X, y)
    beta = np.linalg.solve(ata, aty[:, :, None])[:, :, 0]
    rss = np.maximum(float(y @ y) - np.einsum("dp,dp->d", beta, aty), 0.0)
    return rss, beta[:, 2]


def _block_fit(
    green: NDArray[np.uint8], cols: IntArray, pred: FloatArray, half: int, s: float, side: float, nb: float,
    nb_side: float, c0: float, d_e: float, kap: float,
) -> tuple[float, float, float, float]:  # fmt: skip
    """:func:`lrsensor.extract.pooled.block_fit` on the green channel (H, W), the offsets searched about ``c0``
    (the edge ``d_e``, ``kap`` as there): ``(d, sd, amplitude, noise)``."""
    r0 = np.floor(pred).astype(np.int64)
    f = pred - r0
    got = np.isfinite(pred) & (r0 - half >= 0) & (r0 + half + 1 < green.shape[0])
    rows = r0[:, None] + np.arange(-half, half + 1)[None, :]
    rows = np.where(got[:, None], rows, half)
    P = (1.0 - f[:, None]) * green[rows, cols[:, None]] + f[:, None] * green[rows + 1, cols[:, None]]
    n = int(got.sum())
    if n < 4:
        return math.nan, math.inf, 0.0, math.inf
    y = P[got].mean(axis=0)
    core = min(half, int(2.5 * s) + 1)
    pair = got[1:] & got[:-1]
    dif = np.abs(P[1:][pair] - P[:-1][pair])[:, half - core : half + core + 1].ravel()
    if dif.size < 8:
        return math.nan, math.inf, 0.0, math.inf
    noise = float(np.median(dif)) / (0.6745 * math.sqrt(2.0))
    span, coarse, fine = pooled.OFFSET_SPAN_PX, pooled.COARSE_STEP_PX, pooled.FINE_STEP_PX
    grid = c0 - span + np.arange(round(2.0 * span / coarse) + 1, dtype=np.float64) * coarse
    rss, _ = _fits(y, grid, s, side, nb, nb_side, d_e, kap)
    j = int(np.argmin(rss))
    if j in (0, grid.size - 1) or not math.isfinite(rss[j]):
        return math.nan, math.inf, 0.0, noise
    den = float(rss[j - 1] - 2.0 * rss[j] + rss[j + 1])
    d1 = c0 - span + (j + (0.5 * float(rss[j - 1] - rss[j + 1]) / den if den > 0.0 else 0.0)) * coarse
    r3, _ = _fits(y, np.array([d1 - fine, d1, d1 + fine]), s, side, nb, nb_side, d_e, kap)
    den = float(r3[0] - 2.0 * r3[1] + r3[2])
    if not den > 0.0:
        return math.nan, math.inf, 0.0, noise
    d = d1 + 0.5 * float(r3[0] - r3[2]) / den * fine
    amp = float(_fits(y, np.array([d]), s, side, nb, nb_side, d_e, kap)[1][0])
    curv = den / (fine * fine)
    sd = math.sqrt(2.0 * noise * noise / n / curv)
    return d, sd, amp, noise


def _walk(
    green: NDArray[np.uint8], occ: NDArray[np.bool_], cu: IntArray, cv: FloatArray, step: int, side_l: IntArray,
    nb_row: FloatArray, nb_side_l: IntArray, s_l: float, van_l: FloatArray, kap_l: FloatArray,
) -> tuple[IntArray, FloatArray, FloatArray]:  # fmt: skip
    """:func:`lrsensor.extract.pooled.walk` from the end of the piece ``(cu, cv)`` on the side of ``step``: the
    pooled columns, rows and qualities."""

    def edge(cols: IntArray, pred: FloatArray) -> tuple[float, float]:  # pooled._edge_at
        mid = int(cols[cols.size // 2])
        if not kap_l[mid] > 0.0:
            return 1.0, 0.0
        d_e = max(side * (float(pred.sum()) / pred.size - float(van_l[mid])), 1.0)
        return d_e, float(kap_l[mid]) / d_e

    out_c: list[int] = []
    out_v: list[float] = []
    out_q: list[float] = []
    done = (np.array(out_c, np.int64), np.array(out_v), np.array(out_q))
    w = green.shape[1]
    n_a = min(pooled.ANCHOR_COLS, cu.size)
    tail = slice(cu.size - n_a, cu.size) if step > 0 else slice(0, n_a)
    e = int(cu[-1] if step > 0 else cu[0])
    x = (cu[tail] - e).astype(np.float64)
    n = float(x.size)
    det = n * float(x @ x) - float(x.sum()) ** 2
    b = (n * float(x @ cv[tail]) - float(x.sum()) * float(cv[tail].sum())) / det if det > 1e-9 else 0.0
    a = (float(cv[tail].sum()) - b * float(x.sum())) / n
    n_r = min(pooled.BLOCK_COLS, n_a)
    rc = cu[::-1][:n_r] if step > 0 else cu[:n_r]
    rp = (a + b * (rc - e)).astype(np.float64)
    mid = int(rc[n_r // 2])
    side = float(side_l[mid])
    if side == 0.0:
        return done
    nb = float(nb_row[mid] - (a + b * (mid - e))) if math.isfinite(nb_row[mid]) else math.nan
    nb_side = float(nb_side_l[mid])
    half = min(math.ceil(pooled.WINDOW_SIGMAS * s_l + 2.0), pooled.MAX_HALF_PX)
    d0, _, amp, _ = _block_fit(green, rc, rp, half, s_l, side, nb, nb_side, 0.0, *edge(rc, rp))
    shaped = edge(rc, rp)[1] > 0.0
    sd_max, amp_min = (pooled.SHAPE_SD_MAX_PX, pooled.SHAPE_AMP_MIN) if shaped else (pooled.SD_MAX_PX, pooled.AMP_MIN)
    if not (math.isfinite(d0) and amp > 0.0):
        return done
    shift = 0.0
    c = e + step
    while 0 <= c < w and not occ[c]:
        blk: list[int] = []
        while 0 <= c < w and not occ[c] and len(blk) < pooled.BLOCK_COLS:
            blk.append(c)
            c += step
        if len(blk) < pooled.BLOCK_COLS // 2:
            break
        cols = np.array(blk, np.int64)
        pred = (a + b * (cols - e) + shift).astype(np.float64)
        if float(side_l[cols[cols.size // 2]]) != side:
            break
        d, sd, amp, noise = _block_fit(green, cols, pred, half, s_l, side, nb, nb_side, d0, *edge(cols, pred))
        move = d - d0
        if not (sd <= sd_max and amp >= amp_min * noise and abs(move) <= pooled.MOVE_MAX_PX):
            break
        out_c += blk
        out_v += list(pred + move)
        out_q += [pooled.QUALITY_SCALE * (1.0 - math.exp(-amp / max(noise, 1e-9) / 8.0))] * cols.size
        shift += move
    return np.array(out_c, np.int64), np.array(out_v), np.array(out_q)


def extend_ends(
    image: NDArray[np.uint8], uv: FloatArray, laser: IntArray, quality: FloatArray, glow_side: IntArray,
    use: NDArray[np.bool_], sig_l: FloatArray, vanish: FloatArray, kap: FloatArray,
) -> tuple[FloatArray, IntArray, FloatArray]:  # fmt: skip
    """:func:`lrsensor.extract.pooled.extend_ends` on the points ``uv`` (M, 2), ``laser`` (M,), ``quality`` (M,)
    (sorted by laser, then column): ``(uv, laser, quality)`` with each glowing stripe's dim ends pooled (``vanish``,
    ``kap`` (L, W): the glow's edge, :func:`shaped_growth`)."""
    if not use.any() or laser.size == 0:
        return uv, laser, quality
    green = np.ascontiguousarray(image[:, :, 1])
    n_l, w = glow_side.shape
    u = uv[:, 0].astype(np.int64)
    row = np.full((n_l, w), np.nan)
    row[laser, u] = uv[:, 1]
    new = np.full((n_l, w), np.nan)
    new_q = np.zeros((n_l, w))
    for li in np.flatnonzero(use):
        mine = laser == li
        cu, cv = u[mine], uv[mine, 1]
        if cu.size < pooled.ANCHOR_MIN:
            continue
        starts = np.flatnonzero(np.concatenate([[True], np.diff(cu) > pooled.GAP_COLS]))
        ends = np.concatenate([starts[1:], [cu.size]])
        occ = np.zeros(w, bool)
        anchors = [(a0, a1) for a0, a1 in zip(starts, ends, strict=True) if a1 - a0 >= pooled.ANCHOR_MIN]
        for a0, a1 in anchors:
            occ[cu[a0] : cu[a1 - 1] + 1] = True
        others = [o for o in range(n_l) if o != li]
        nb_row = np.full(w, np.nan)
        nb_side = np.zeros(w, np.int64)
        for o in others:  # the nearest other laser's returned row in each column
            with np.errstate(invalid="ignore"):
                take = np.isfinite(row[o]) & (
                    ~np.isfinite(nb_row) | (np.abs(row[o] - row[li]) < np.abs(nb_row - row[li]))
                )
            nb_row = np.where(take, row[o], nb_row)
            nb_side = np.where(take, glow_side[o], nb_side)
        for a0, a1 in anchors:
            for step in (1, -1):
                c, v, q = _walk(
                    green, occ, cu[a0:a1], cv[a0:a1], step, glow_side[li], nb_row, nb_side, sig_l[li], vanish[li],
                    kap[li],
                )  # fmt: skip
                new[li, c] = v
                new_q[li, c] = q
    keep = ~np.isfinite(new[laser, u])
    li_n, c_n = np.nonzero(np.isfinite(new))
    col_v = np.concatenate([laser[keep] * w + u[keep], li_n * w + c_n])
    order = np.argsort(col_v, kind="stable")
    v_all = np.concatenate([uv[keep, 1], new[li_n, c_n]])[order]
    uv_o = np.stack([(col_v[order] % w).astype(np.float64), v_all], axis=1)
    q_all = np.concatenate([quality[keep], new_q[li_n, c_n]])[order]
    return uv_o, (col_v[order] // w).astype(np.int64), q_all
