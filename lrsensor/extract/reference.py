"""The readable reference of the extractor: the whole frame in numpy and OpenCV, the same algorithm as the
compiled road (:mod:`lrsensor.extract.frame`).

It runs where the compiled road cannot: without numba, while numba compiles the kernels in the background (the
first use on a machine without numba's cache), and where a test asks for it
(:data:`lrsensor.extract.subpixel.USE_REFERENCE`). Tests compare the two on whole frames; they are never mixed
step by step. Read it to learn what the kernels compute; read the kernels to learn how they compute it fast.

:func:`extract_frame` takes the frame (H, W, 3) uint8 BGR and the records of
:func:`lrsensor.extract.settings.frame_settings`, and:

1. detects candidates per laser in its band (:func:`_candidates`: OpenCV's 2x2 area average, 3-column box,
   two-sided contrast and local maxima, and where the band shows the sheet's glow a second pass for the stripe on
   the glow's rising side, :func:`_glow_candidates`; bit for bit what :func:`lrsensor.extract.detect.detect_band`
   computes);
2. links them into chains and picks one per column (:func:`_pick`: :func:`_merge_plateaus`, :func:`_top_k`,
   :func:`_chains`), expanded from the half-resolution detection columns to full columns;
3. fits the sub-pixel centre of every picked column on its green profile (:func:`_fit`, with
   :func:`lrsensor.extract.centre.fit_profiles`), the window from the frame's typical width (:func:`_typical_sigma`)
   and the widest plausible stripe per column (:func:`_max_fwhm`);
4. refits the points with another laser's stripe close by, with its Gaussian subtracted
   (:func:`lrsensor.extract.reference_finish.neighbours`), the rounds and tolerances of
   :mod:`lrsensor.extract.refit`;
5. fits the stripes that show the laser sheet's glow (turbid water) jointly with its edge
   (:func:`lrsensor.extract.reference_glow.glow_refit`);
6. pools the colour and signal-to-noise gates along the stripe, forms runs, smooths them and scores quality
   (:mod:`lrsensor.extract.reference_finish`);
7. with ``triangulate``, triangulates in numpy and applies the depth gate.

Floating-point results agree with the compiled road to rounding (the kernels fuse multiplies and adds, and some
fits run in float32); ties in the chain linking may be broken differently at a few columns.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..triangulation import triangulate as _triangulate
from . import reference_finish, reference_glow, reference_pooled, refit
from .centre import FWHM_PER_SIGMA, WIDE_FWHM_PX, fit_profiles
from .detect import GLOW_PASS_MIN, noise_col_step
from .finish import BLURRED_SIGMA_PX, CENTRE_SD, RUN_MAX_SD_PX, STRIPE_NOISE_MIN
from .fit import flank_offset
from .frame import POOLED_ENDS, RETRY_REFUSED, STATS_POINTS
from .glow import new_water
from .reference_finish import pooled_gates, smooth, smooth_through_port
from .settings import Bands, Geometry, Settings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Rows per background flank of the sub-pixel fit (as the compiled kernels take them).
_FLANK_PX = 3


def _py(f: Any) -> Any:
    """The Python function of a compiled kernel (its plain arithmetic: the reference compiles nothing)."""
    return getattr(f, "py_func", f)


def _nothing() -> tuple[FloatArray, IntArray, FloatArray, FloatArray]:
    """No points: ``(uv, laser, quality, xyz)`` empty."""
    return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))


def extract_frame(
    image: NDArray[np.uint8],
    calibration: Calibration,
    bands: Bands,
    s: Settings,
    geo: Geometry,
    triangulate: bool,
    water: FloatArray | None = None,
) -> tuple[FloatArray, IntArray, FloatArray, FloatArray]:
    """The whole extractor on one frame in numpy and OpenCV: what :func:`lrsensor.extract.frame.extract_frame`
    computes (same arguments; ``calibration`` for the triangulation).

    Returns:
        ``(uv, laser, quality, xyz)``: pixel coordinates (M, 2), laser (M,), quality (M,), and with
        ``triangulate`` the body-frame points (M, 3), metres, of the points whose camera depth is within the range
        limits (the others dropped); without, (0, 3) and no depth gate.
    """
    w = image.shape[1]
    n_l = bands.rows.shape[0]
    wd = (w + 1) // 2  # detection at half resolution: column c stands for the full columns 2c and 2c + 1
    # 1. candidates of every laser in its band; laser l's detection columns are numbered l * wd + c
    parts = []
    noise = np.ones(n_l)
    for i in range(n_l):
        if bands.rows[i, 1] <= bands.rows[i, 0]:
            continue
        u, v, a, noise[i], sec = _candidates(image, i, bands, s, i * wd)
        parts.append((u, v, a, sec))
    if not parts or sum(p[0].size for p in parts) == 0:
        return _nothing()
    # laser by laser, each sorted by column then row: the concatenation is sorted by (virtual) column
    U = np.concatenate([p[0] for p in parts])
    Vr = np.concatenate([p[1] for p in parts])
    Ar = np.concatenate([p[2] for p in parts])
    Sr = np.concatenate([p[3] for p in parts])
    n_cols = n_l * w
    # 2. continuity: chains; per column the candidate on the strongest long-enough chain
    jump = s.max_jump_px * 1.5
    min_run = max(2, math.ceil(s.min_run_cols / 2))
    col_d, rows_f, chain, chain_len = _pick(U, Vr, Ar, n_l * wd, s, wd, jump, min_run)
    if col_d.size == 0:
        return _nothing()
    # whether each pick is the second detection pass's: the candidate of its column nearest its row (the first of a
    # tie; rows ascend within a column)
    pick_of = np.full(n_l * wd, -1)
    pick_of[col_d] = np.arange(col_d.size)
    has = pick_of[U] >= 0
    j_c = np.flatnonzero(has)
    dist = np.abs(Vr[j_c] - rows_f[pick_of[U[j_c]]])
    o_n = np.lexsort((dist, U[j_c]))  # stable: by column, then distance, then row
    first_of = np.ones(o_n.size, bool)
    first_of[1:] = U[j_c][o_n][1:] != U[j_c][o_n][:-1]
    sec_d = np.zeros(n_l * wd, bool)
    sec_d[U[j_c][o_n][first_of]] = Sr[j_c][o_n][first_of]
    # every detection column c stands for the full columns 2c and 2c + 1 (between c and c + 1)
    laser_d = col_d // wd
    c = col_d - laser_d * wd
    nxt = np.ones(col_d.size, bool)
    nxt[:-1] = ~((col_d[1:] == col_d[:-1] + 1) & (chain[1:] == chain[:-1]))
    rows_next = np.where(nxt, rows_f, np.concatenate([rows_f[1:], rows_f[-1:]]))
    u_odd = 2 * c + 1
    keep_odd = u_odd < w
    col_v = np.concatenate([laser_d * w + 2 * c, (laser_d * w + u_odd)[keep_odd]])
    rows_f = np.concatenate([rows_f, (0.5 * (rows_f + rows_next))[keep_odd]])
    chain = np.concatenate([chain, chain[keep_odd]])
    chain_len = np.concatenate([chain_len, chain_len[keep_odd]]) * 2
    o2 = np.argsort(col_v, kind="stable")
    col_v, rows_f, chain, chain_len = col_v[o2], rows_f[o2], chain[o2], chain_len[o2]
    rows = np.rint(rows_f).astype(np.int64)
    laser = col_v // w
    cols = col_v - laser * w
    # 3. sub-pixel centre on the green profile; window and spacing from the typical width of this frame
    # the widest plausible stripe per column, computed where it is needed (frame statistics, wide profiles)
    max_fwhm = np.full(cols.size, np.nan)

    def max_fwhm_at(idx: IntArray) -> FloatArray:
        need = idx[np.isnan(max_fwhm[idx])]
        if need.size:
            max_fwhm[need] = _max_fwhm(calibration, geo, cols[need], rows[need], laser[need], s)
        return max_fwhm[idx]

    # the frame statistics from the first detection pass's points where it has enough (frame.fit_points says why)
    pool = np.flatnonzero(~sec_d[laser * wd + cols // 2])
    if pool.size < STATS_POINTS:
        pool = np.arange(cols.size)
    sub = pool[np.linspace(0, pool.size - 1, min(pool.size, STATS_POINTS)).astype(np.int64)]
    half0 = s.window_half_px
    P0 = _gather(image, cols[sub], rows[sub], half0, 1)
    wide_lim = float(np.median(max_fwhm_at(sub)))  # a wide-sheet frame needs a longer window
    sig_med = _typical_sigma(P0, s.saturation_dn, max(s.max_sigma_px, wide_lim / FWHM_PER_SIGMA))
    n_sat = np.sort((s.saturation_dn <= P0).sum(axis=0))
    plateau = float(n_sat[int(0.9 * (n_sat.size - 1))])
    half = int(min(max(half0, math.ceil(wide_lim) + 4), math.ceil(3.0 * sig_med + 0.5 * plateau + 4)))

    no_nb = np.full(cols.size, np.nan)
    vv, amp, sig, _sat, ok, lnoise, rise = _fit(
        image, cols, rows, half, sig_med, s, (no_nb, no_nb, no_nb), max_fwhm_at(np.arange(cols.size))
    )
    # 4. stripes of two lasers that come close (long range): refit each with the other's Gaussian subtracted,
    # alternating a few times (both estimates start pulled toward each other)
    # (until no point's neighbour moves by more than refit.NEIGHBOUR_TOL: a point's fit depends on nothing
    # else that changes between the rounds)
    wide_sigma = WIDE_FWHM_PX / FWHM_PER_SIGMA  # profiles wider than this are flat-topped (wide)
    if n_l > 1:
        # the rows the fits read: background flanks (flank_px rows from off, as fit_profiles places them without a
        # clipped sample) and the whole window
        off = _py(flank_offset)(sig_med, 0, half, _FLANK_PX)
        read = (float(off + _FLANK_PX - 1), half + 1.0, wide_sigma)
        last = np.full((3, cols.size), np.nan)  # the neighbour of each point's last refit
        tol = refit.NEIGHBOUR_TOL
        for _ in range(refit.NEIGHBOUR_REFITS):
            nb = reference_finish.neighbours(
                laser, cols, vv, amp, sig, _sat, ok & ~_sat, n_l, w, half + 3.0 * sig_med + 2.0, read
            )
            with np.errstate(invalid="ignore"):
                same = (
                    (np.abs(nb[0] - last[0]) <= tol)
                    & (np.abs(nb[1] - last[1]) <= tol * np.maximum(np.abs(last[1]), 1.0))
                    & (np.abs(nb[2] - last[2]) <= tol)
                )
            idx = np.flatnonzero(np.isfinite(nb[0]) & ~same)
            if idx.size == 0:
                break
            last[:, idx] = np.stack(nb)[:, idx]
            *res, rise_i = _fit(
                image, cols[idx], rows[idx], half, sig_med, s, (nb[0][idx], nb[1][idx], nb[2][idx]), max_fwhm_at(idx)
            )
            for arr, new in zip((vv, amp, sig, _sat, ok, lnoise), res, strict=True):
                arr[idx] = new
            rise[:, idx] = rise_i
    # turbid water: the stripes that show the sheet's glow, fitted jointly with its edge
    own = np.zeros(cols.size, bool)
    pool_use, pool_sig = np.zeros(n_l, bool), np.zeros(n_l)  # the lasers whose dim ends are pooled (frame.POOLED_ENDS)
    w_rec = new_water() if water is None else water
    if s.glow_fit:  # (the gate takes the amplitude and noise of the joint fits where they are taken)
        # the points the common fit refused enter at their candidate row with the frame's width (frame.RETRY_REFUSED)
        retry = ~ok & ~_sat if RETRY_REFUSED and sig_med >= BLURRED_SIGMA_PX else np.zeros(cols.size, bool)
        v_g, s_g, own, a_g, n_g = reference_glow.glow_refit(
            image,
            cols,
            laser,
            bands.glow_side,
            np.where(retry, rows.astype(np.float64), vv),
            amp,
            np.where(retry, sig_med, sig),
            _sat,
            ok | retry,
            lnoise,
            noise,
            s.min_fwhm_px / FWHM_PER_SIGMA,
            s.max_sigma_px,
            s.saturation_dn,
            s.min_green_ratio,
            geo.glow_vanish,
            geo.glow_path,
            w_rec,
            retry,
        )
        if POOLED_ENDS:
            pool_use, pool_sig = reference_pooled.glowing_widths(laser, own, s_g, n_l)
        take = ~retry | own  # a refused point only where its joint fit is taken
        vv, amp, lnoise = np.where(take, v_g, vv), np.where(take, a_g, amp), np.where(take, n_g, lnoise)
        ok = ok | (retry & own)
        sig = np.where(retry & own, s_g, sig)
    # signal-to-noise per point: the local noise (flanks) where it exceeds the band's (shot noise on bright
    # backgrounds, speckle, haze)
    # (where the glow stage's joint fit is taken, its residual noise alone: finish.finish_points)
    noise_b = noise.copy()  # (finish.stripe_noise: the joint fits' residual noise, where they tell it)
    for li in range(noise.size):
        x = lnoise[own & (col_v // w == li) & np.isfinite(lnoise)]
        if x.size >= STRIPE_NOISE_MIN:  # the lower median
            noise_b[li] = min(noise_b[li], float(np.partition(x, (x.size - 1) // 2)[(x.size - 1) // 2]))
    snr = amp / np.maximum(np.maximum(np.where(own, 0.0, noise_b[col_v // w]), lnoise), 0.5)
    # 5. gates, runs, smoothing, quality
    ok, snr = pooled_gates(col_v, chain, ok, _sat, rise, snr, s)
    ok &= (amp >= s.min_contrast_dn) & ((snr >= s.min_snr) | _sat)
    col_v, chain, chain_len = col_v[ok], chain[ok], chain_len[ok]
    vv, amp, sig, snr, sat = vv[ok], amp[ok], sig[ok], snr[ok], _sat[ok]
    if col_v.size == 0:
        return _nothing()
    # runs: columns of one laser with gaps of at most 3 columns, on one chain, or both wide (saturated or
    # flat-topped: their candidate rows wander on the top and split the chains) and within max_jump_px rows
    with np.errstate(invalid="ignore"):
        wide = sat | (sig > wide_sigma)
    joined = (chain[1:] == chain[:-1]) | (wide[1:] & wide[:-1] & (np.abs(np.diff(vv)) <= s.max_jump_px))
    lz = col_v // w
    new = np.ones(col_v.size, bool)
    new[1:] = (np.diff(col_v) > 3) | (lz[1:] != lz[:-1]) | ~joined
    run_id = np.cumsum(new) - 1
    counts = np.bincount(run_id)
    keep = counts[run_id] >= max(2, s.min_run_cols // 2)
    # on a blurred stripe, the runs whose line fit is sure enough at its ends (finish.run_certain)
    for li in range(n_l):
        mine = lz == li
        fin = sig[mine][np.isfinite(sig[mine])]
        if fin.size == 0:
            continue
        s_l = float(fin.sum()) / fin.size
        if s_l < BLURRED_SIGMA_PX:
            continue
        inv = np.bincount(run_id[mine], weights=1.0 / np.maximum(snr[mine], 1e-9), minlength=counts.size)
        k = np.maximum(counts, 1)
        sd = 2.0 * CENTRE_SD * math.sqrt(s_l) * inv / k / np.sqrt(k)
        keep[mine] &= sd[run_id[mine]] <= RUN_MAX_SD_PX
    col_v, vv, sig, chain_len, run_id, snr = col_v[keep], vv[keep], sig[keep], chain_len[keep], run_id[keep], snr[keep]
    # along-stripe smoothing
    scales = tuple(int(k) for k in s.smooth_scales)
    if scales and col_v.size:
        y = np.full(n_cols, np.nan)
        run = np.full(n_cols, -1, np.int64)
        y[col_v] = vv
        run[col_v] = run_id
        if calibration.port is None:
            vv = smooth(y, run, scales)[col_v]
        else:
            vv = smooth_through_port(y, run, scales, w, calibration)[col_v]
    # quality
    laser = col_v // w
    q_snr = 1.0 - np.exp(-snr / 8.0)
    sig = np.where(np.isfinite(sig), sig, s.max_sigma_px)
    q_w = np.clip(np.minimum(sig / 0.6, 1.5 * s.max_sigma_px / np.maximum(sig, 1e-6) - 0.5), 0.2, 1.0)
    q_run = np.clip(chain_len / (4.0 * s.min_run_cols), 0.0, 1.0)
    quality = np.clip(q_snr * q_w * (0.5 + 0.5 * q_run), 0.0, 1.0)
    uv = np.stack([(col_v - laser * w).astype(np.float64), vv], axis=1)
    laser = laser.astype(np.int64)
    # a glowing stripe's dim ends, measured pooled along it
    uv, laser, quality = reference_pooled.extend_ends(
        image, uv, laser, quality, bands.glow_side, pool_use, pool_sig, geo.glow_vanish,
        reference_pooled.shaped_growth(w_rec, geo.glow_path),
    )  # fmt: skip
    if not triangulate:
        return uv, laser, quality, np.empty((0, 3))
    # 6. the body-frame points and the depth gate
    xyz = _triangulate(calibration, uv, laser, compiled=False)
    depth = xyz @ geo.R_cam_body[2] + geo.cam_z_offset_m  # camera z, metres
    with np.errstate(invalid="ignore"):
        keep = (depth >= s.min_range_m) & (depth <= s.max_range_m)  # NaN rows fail both: dropped too
    return uv[keep], laser[keep], quality[keep], xyz[keep]


def _noise_dn(g: NDArray[np.uint8], step: int = 8) -> float:
    """Robust pixel noise (DN) of a band of a green channel, insensitive to smooth gradients (glow, murk).

    Second differences ``g[r] - 2 g[r + 2] + g[r + 4]`` (rows two apart, so independent; linear gradients cancel)
    on every ``step``-th row triple and every 2nd to 8th column (``noise_col_step``: about 6000
    samples); for Gaussian noise of std s their median absolute value is 0.6745 sqrt(6) s.
    """
    if g.shape[0] < 5:
        return 1.0
    n = (g.shape[0] - 4 + step - 1) // step
    cs = _py(noise_col_step)(n, g.shape[1])
    a = g[0 : step * n : step][:n, ::cs]
    b = g[2 : step * n + 2 : step][:n, ::cs]
    c = g[4 : step * n + 4 : step][:n, ::cs]
    ac: Any = cv2.add(a, c, dtype=cv2.CV_16U)
    bb: Any = cv2.add(b, b, dtype=cv2.CV_16U)
    d = cv2.absdiff(ac, bb)
    hist = np.bincount(np.minimum(d.ravel(), 1023), minlength=1024)
    cum = np.cumsum(hist)
    half = 0.5 * float(cum[-1])
    k = int(np.searchsorted(cum, half))
    below = float(cum[k - 1]) if k > 0 else 0.0
    # the median inside its integer bin (|d| = k covers [k - 0.5, k + 0.5) of the continuous value; 0 covers [0, 0.5))
    lo, width = (0.0, 0.5) if k == 0 else (k - 0.5, 1.0)
    med = lo + width * (half - below) / max(float(hist[k]), 1.0)
    return max(med / (0.6745 * math.sqrt(6.0)), 0.05)


def _candidates(
    image: NDArray[np.uint8], laser: int, bands: Bands, s: Settings, col_offset: int
) -> tuple[IntArray, IntArray, FloatArray, float, BoolArray]:
    """Stripe candidates of ``laser`` inside its band (:func:`lrsensor.extract.detect.detect_band`).

    The green channel of the band's rows (and ``d`` more either side, replicated beyond the image, evened) is
    averaged over 2x2 pixels and then over 3 of those columns (along the stripe); the response is the two-sided
    contrast ``G(v) - max(G(v - d), G(v + d))`` with ``d`` beyond the widest stripe (and the same at ``d / 2``, the
    larger of the two), saturating at 0: positive only on ridges narrower than ``2 d`` (not on glow ramps, haze or
    wide blobs). Candidates are its vertical local maxima above the noise-scaled threshold, inside the band.

    Returns:
        ``(cols, rows, strength, noise, second)``: detection-scale columns plus ``col_offset`` (N,),
        full-resolution rows (N,), contrast (N,), sorted by column then row, the full-resolution pixel noise (DN),
        and (N,) whether each is the second pass's (:func:`_glow_candidates`).
    """
    r0, r1 = int(bands.rows[laser, 0]), int(bands.rows[laser, 1])
    h, w = image.shape[:2]
    d = s.contrast_px
    a0, a1 = max(r0 - d, 0), min(r1 + d, h)
    if (a1 - a0) % 2 and a1 < h:
        a1 += 1  # an even number of rows for the 2x2 average (one more row below: the band check drops it)
    g: Any = cv2.extractChannel(image[a0:a1], 1)
    top, bot = d - (r0 - a0), d - (a1 - r1)
    odd_r, odd_c = (g.shape[0] + max(top, 0) + max(bot, 0)) % 2, w % 2
    if top > 0 or bot > 0 or odd_r or odd_c:  # pad to the full shift range and even sizes (replicate the border)
        g = cv2.copyMakeBorder(g, max(top, 0), max(bot, 0) + odd_r, 0, odd_c, cv2.BORDER_REPLICATE)
    step = min(max(g.shape[0] // 24, 2), 16)
    noise = max(_noise_dn(g, step), 0.5)
    # row y <-> full rows r0 - d + 2 y (+1), column c <-> full columns 2 c (+1)
    g = cv2.resize(g, (g.shape[1] // 2, g.shape[0] // 2), interpolation=cv2.INTER_AREA)
    g = cv2.blur(g, (3, 1))
    ds = d // 2
    thr = max(s.min_response_dn, s.snr_threshold * (noise * s.area_noise))
    resp: Any = cv2.subtract(g[ds:-ds], cv2.max(g[: -2 * ds], g[2 * ds :]))
    # the same at half the offset (a thin stripe next to another ridge at exactly +-d keeps its response)
    hd = ds // 2
    if hd >= 2:
        inner = g[ds - hd : g.shape[0] - ds + hd]
        resp = cv2.max(resp, cv2.subtract(g[ds:-ds], cv2.max(inner[: -2 * hd], inner[2 * hd :])))
    v_lo, v_hi = bands.v_lo[laser], bands.v_hi[laser]
    loc = cv2.dilate(resp, _KERNEL_3)
    pk: Any = cv2.compare(resp, loc, cv2.CMP_GE)
    pk &= cv2.compare(resp, thr, cv2.CMP_GT)  # type: ignore[call-overload]
    nz = cv2.findNonZero(pk)
    xy = np.zeros((0, 2), np.int64) if nz is None else nz.reshape(-1, 2).astype(np.int64)
    u, v = xy[:, 0], r0 + 2 * xy[:, 1]
    a = resp[xy[:, 1], u].astype(np.float64)
    uf = np.minimum(u * 2, w - 1)
    inside = (v >= v_lo[uf]) & (v <= v_hi[uf])  # the band need not be a rectangle
    u, v, a = u[inside], v[inside], a[inside]
    sec = np.zeros(u.size, bool)
    if hd >= 2 and _glow_shows(g, u, v, r0, thr, bands.glow_side[laser], ds, hd):
        u2, v2, a2 = _glow_candidates(g, u, v, r0, thr, v_lo, v_hi, bands.glow_side[laser], ds, hd)
        u, v, a = np.concatenate([u, u2]), np.concatenate([v, v2]), np.concatenate([a, a2])
        sec = np.concatenate([sec, np.ones(u2.size, bool)])
    order = np.lexsort((v, u))  # by column, then row
    return u[order] + col_offset, v[order], a[order], noise, sec[order]


def _glow_shows(
    g: NDArray[np.uint8], u: IntArray, v: IntArray, r0: int, thr: float, side: IntArray, ds: int, hd: int
) -> bool:
    """Whether the band shows the laser sheet's glow at the first pass's candidates ``u`` (detection columns), ``v``
    (full rows) (as ``detect.detect_band`` counts them): at a quarter of them or more the detection row ``hd``
    outward (the glow ``side`` (W,)) is brighter than the row ``hd`` inward by more than ``thr``. In clear water
    both are background; in turbid water the glow's edge lies between them. Only then does the second pass run."""
    if u.size == 0:
        return False
    y = (v - r0) // 2 + ds
    sd = side[np.minimum(2 * u, side.size - 1)]
    gi = g.astype(np.int64)
    step = sd * (gi[y + hd, u] - gi[y - hd, u])
    return bool(4 * int(np.sum((sd != 0) & (step > thr))) >= u.size)


def _glow_candidates(
    g: NDArray[np.uint8],
    u_first: IntArray,
    v_first: IntArray,
    r0: int,
    thr: float,
    v_lo: IntArray,
    v_hi: IntArray,
    side: IntArray,
    ds: int,
    hd: int,
) -> tuple[IntArray, IntArray, FloatArray]:
    """The second detection pass (``detect.glow_candidates``): a stripe on the rising side of the sheet's glow.

    Where the glow brightens steeply outward (far walls in turbid water) the stripe is a shoulder on a step, not a
    ridge, and the two-sided contrast finds nothing in its column. There, first in the columns of the band without
    any candidate of the first pass (``u_first``, ``v_first``: detection columns, full rows), the response is the centre
    over the mean of the rows ``hd`` either side, ``G(v) - (G(v - hd) + G(v + hd)) / 2`` (rounded half up,
    saturating at 0): a blurred step's edge cancels at its centre, a convex glow gives nothing, the stripe its
    peak. A candidate is a vertical local maximum of it above ``thr`` whose centre stands above both inner rows
    (``ds`` and ``hd`` towards the vanishing line, away from the glow ``side`` (W,)) by more than ``thr`` and
    whose outer row at ``ds`` is at least as bright as the centre (the glow, which is why the first pass failed).
    Where that finds at least :data:`~lrsensor.extract.detect.GLOW_PASS_MIN` candidates, the glow hides the stripe
    in this band, and the columns with first-pass candidates get the second pass's too (at rows that are no
    first-pass peak): a speck of the glow (noise, a particle) found there alone would cut the stripe's chain.
    Clear water never gets that far.

    Args:
        g: (gh, wo) the detection image (2x2 average, 3-column box); u_first: detection columns with a candidate.

    Returns:
        ``(cols, rows, strength)``: detection columns (N,), full rows (N,), response (N,).
    """
    gi = g.astype(np.int32)
    ho, wo = gi.shape[0] - 2 * ds, gi.shape[1]
    c, b0, b1 = gi[ds : ds + ho], gi[:ho], gi[2 * ds : 2 * ds + ho]
    h0, h1 = gi[ds - hd : ds - hd + ho], gi[ds + hd : ds + hd + ho]
    r2 = np.maximum(c - ((h0 + h1 + 1) >> 1), 0)
    sd = side[np.minimum(2 * np.arange(wo), side.size - 1)][None, :]
    b_in, h_in, b_out = np.where(sd > 0, b0, b1), np.where(sd > 0, h0, h1), np.where(sd > 0, b1, b0)
    up = np.concatenate([r2[:1], r2[:-1]])
    down = np.concatenate([r2[1:], r2[-1:]])
    pk = (r2 > thr) & (r2 >= up) & (r2 >= down) & (sd != 0) & (c - np.maximum(b_in, h_in) > thr) & (b_out >= c)
    y, x = np.nonzero(pk)
    v = r0 + 2 * y
    uf = np.minimum(2 * x, side.size - 1)
    empty = np.ones(wo, bool)
    empty[u_first] = False
    inside = (v >= v_lo[uf]) & (v <= v_hi[uf])
    keep = inside & empty[x]
    if int(keep.sum()) >= GLOW_PASS_MIN:
        first = np.zeros(pk.shape, bool)
        first[(v_first - r0) // 2, u_first] = True
        keep = inside & ~first[y, x]
    return x[keep], v[keep], r2[y[keep], x[keep]].astype(np.float64)


_KERNEL_3 = cv2.getStructuringElement(cv2.MORPH_RECT, (1, 3))


def _merge_plateaus(u: IntArray, v: IntArray, a: FloatArray) -> tuple[IntArray, FloatArray, FloatArray]:
    """Sort by column then row and merge maxima of one column closer than 3 rows (plateaus) into their mean."""
    order = np.argsort(u, kind="stable")  # rows stay ascending within a column (findNonZero is row-major)
    u, v, a = u[order], v[order], a[order]
    new = np.ones(u.size, bool)
    new[1:] = (u[1:] != u[:-1]) | (v[1:] - v[:-1] > 3)
    if bool(new.all()):
        return u, v.astype(np.float64), a
    gid = np.cumsum(new) - 1
    cnt = np.bincount(gid)
    vm = np.bincount(gid, weights=v.astype(np.float64)) / cnt
    am = np.zeros(cnt.size)
    np.maximum.at(am, gid, a)
    return u[new], vm, am


def _top_k(u: IntArray, v: FloatArray, a: FloatArray, n_cols: int, k: int) -> tuple[FloatArray, FloatArray]:
    """(n_cols, k) rows and strengths of the k strongest candidates per column (NaN / 0 where fewer)."""
    if k > 1:
        order = np.lexsort((-a, u))
        u, v, a = u[order], v[order], a[order]
    first = np.searchsorted(u, u, side="left")
    rank = np.arange(u.size) - first
    keep = rank < k
    V = np.full((n_cols, k), np.nan)
    A = np.zeros((n_cols, k))
    V[u[keep], rank[keep]] = v[keep]
    A[u[keep], rank[keep]] = a[keep]
    return V, A


def _chains(
    V: FloatArray, A: FloatArray, max_jump: float, block: int, max_gap: int = 3
) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any]]:
    """Link candidates of nearby columns into chains (stripe pieces).

    A node (column c, candidate i) is linked to the mutually nearest candidate of column c + 1 when their rows
    differ by at most ``max_jump``; nodes left without a partner are then tried across gaps of up to
    ``max_gap - 1`` empty columns (dim or occluded columns do not cut a stripe). Columns in different blocks
    of ``block`` columns (one block per laser) are never linked.

    Returns per node (n_cols * k,): chain id, chain length (nodes) and chain strength (sum of strengths).
    """
    n_cols, k = V.shape
    n = n_cols * k
    if k == 1:
        cols = np.flatnonzero(np.isfinite(V[:, 0]))
        if cols.size == 0:
            return np.arange(n), np.ones(n, np.int64), A.ravel().copy()
        v = V[cols, 0]
        link = (np.diff(cols) <= max_gap) & (np.abs(np.diff(v)) <= max_jump) & (cols[1:] // block == cols[:-1] // block)
        rid = np.cumsum(np.concatenate([[True], ~link])) - 1
        root = np.arange(n)
        root[cols] = cols[np.flatnonzero(np.concatenate([[True], ~link]))][rid]
        length = np.bincount(root, minlength=n)[root]
        strength = np.bincount(root, weights=A.ravel(), minlength=n)[root]
        return root, length, strength
    prev = np.arange(n)
    has_next = np.zeros((n_cols, k), bool)
    has_prev = np.zeros((n_cols, k), bool)
    ii = np.arange(k)[None, :]
    for lag in range(1, max_gap + 1):
        if n_cols <= lag:
            break
        a_ok = ~has_next[:-lag] & np.isfinite(V[:-lag])
        b_ok = ~has_prev[lag:] & np.isfinite(V[lag:])
        D = np.abs(V[:-lag, :, None] - V[lag:, None, :])
        D = np.where(a_ok[:, :, None] & b_ok[:, None, :], D, np.inf)
        j_best = np.argmin(D, axis=2)  # for node (c, i) the nearest in c + lag
        i_best = np.argmin(D, axis=1)  # for node (c + lag, j) the nearest in c
        dmin = np.take_along_axis(D, j_best[:, :, None], axis=2)[:, :, 0]
        mutual = np.take_along_axis(i_best, j_best, axis=1) == ii
        c = np.arange(n_cols - lag)
        same_block = (c // block) == ((c + lag) // block)
        link = mutual & (dmin <= max_jump) & same_block[:, None]
        if not np.any(link):
            continue
        cc = c[:, None]
        src = (cc * k + ii)[link]
        dst = ((cc + lag) * k + j_best)[link]
        prev[dst] = src
        has_next.reshape(-1)[src] = True
        has_prev.reshape(-1)[dst] = True
    root = prev
    for _ in range(math.ceil(math.log2(max(n_cols, 2))) + 1):
        nxt = root[root]
        if np.array_equal(nxt, root):
            break
        root = nxt
    length = np.bincount(root, minlength=n)[root]
    strength = np.bincount(root, weights=A.ravel(), minlength=n)[root]
    return root, length, strength


def _pick(
    U: IntArray,
    Vr: IntArray,
    Ar: FloatArray,
    n_cols: int,
    s: Settings,
    block: int,
    jump: float,
    min_run: int,
) -> tuple[IntArray, FloatArray, IntArray, IntArray]:
    """Candidate selection: plateaus, k strongest, chains, pick (as ``chains.select_candidates``)."""
    U, Vf, Ar = _merge_plateaus(U, Vr, Ar)
    k = int(min(s.max_candidates, np.bincount(U).max()))
    V, A = _top_k(U, Vf, Ar, n_cols, k)
    root, length, strength = _chains(V, A, jump, block)
    score = np.where(np.isfinite(V.ravel()) & (length >= min_run), strength, -np.inf).reshape(n_cols, k)
    pick = np.argmax(score, axis=1) if k > 1 else np.zeros(n_cols, np.int64)
    col_v = np.flatnonzero(np.isfinite(score[np.arange(n_cols), pick]))
    node = col_v * k + pick[col_v]
    return col_v, V.ravel()[node], root[node], length[node]


def _gather(image: NDArray[np.uint8], cols: IntArray, rows: IntArray, half: int, channel: int) -> NDArray[np.uint8]:
    """(2 half + 1, N) samples of ``channel`` in columns ``cols`` around ``rows`` (clamped at the border)."""
    h, w = image.shape[:2]
    rr = np.clip(rows[None, :] + np.arange(-half, half + 1)[:, None], 0, h - 1)
    return image.reshape(-1)[(rr * w + cols[None, :]) * 3 + channel]


def _typical_sigma(P: NDArray[np.uint8], saturation_dn: float, max_sigma_px: float) -> float:
    """Median Gaussian-equivalent sigma (px) of a few unsaturated profiles (M, N) from their half-level width.

    The background is the lower of the mean of the outer quarter at both ends (beyond any stripe of up to
    ``max_sigma_px``), so the width is right for narrow and wide stripes alike. 1.0 when nothing is measurable.
    """
    X = P.astype(np.float64)
    m = X.shape[0]
    R = m // 2
    q = max(2, m // 4)
    bg = np.minimum(X[:q].mean(axis=0), X[-q:].mean(axis=0))
    core = X[R - 3 : R + 4]
    pk = core.max(axis=0)
    p = np.argmax(core, axis=0) + R - 3
    half = 0.5 * (pk + bg)
    idx = np.arange(m)[:, None]
    below = half[None, :] > X
    left = np.where(below & (idx < p[None, :]), idx, -1).max(axis=0)
    right = np.where(below & (idx > p[None, :]), idx, m).min(axis=0)
    ok = (left >= 0) & (right < m) & (pk < saturation_dn) & (pk - bg > 5.0)
    if not np.any(ok):
        return 1.0
    cols = np.flatnonzero(ok)
    lf, rt = left[cols], right[cols]
    xl = lf + (half[cols] - X[lf, cols]) / np.maximum(X[lf + 1, cols] - X[lf, cols], 1e-9)
    xr = rt - (half[cols] - X[rt, cols]) / np.maximum(X[rt - 1, cols] - X[rt, cols], 1e-9)
    sigma = float(np.median(xr - xl)) / FWHM_PER_SIGMA
    return float(np.clip(sigma, 0.6, max_sigma_px)) if math.isfinite(sigma) else 1.0


def _max_fwhm(
    calibration: Calibration, geo: Geometry, cols: IntArray, rows: IntArray, laser: IntArray, s: Settings
) -> FloatArray:
    """Widest physically plausible stripe (half-level width, px) at each candidate (N,).

    The candidate pixel is triangulated on its laser's plane; a sheet ``max_sheet_mm`` thick at that depth
    (along the optical axis) spans ``max_sheet_mm * f / depth`` pixels, plus 4 px for blur and the edges;
    never below ``FWHM_PER_SIGMA * max_sigma_px``. Pixels whose ray misses the plane get that floor.
    """
    floor = FWHM_PER_SIGMA * s.max_sigma_px
    if cols.size == 0 or s.max_sheet_mm <= 0:
        return np.full(cols.size, floor)
    uv = np.stack([cols.astype(np.float64), rows.astype(np.float64)], axis=1)
    pts = _triangulate(calibration, uv, laser, compiled=False)
    depth = (pts - geo.origin_body) @ geo.axis_body
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1e-3 * s.max_sheet_mm * geo.camera[1] / depth + 4.0
    return np.where(np.isfinite(w) & (depth > 0), np.maximum(w, floor), floor)


def _fit(
    image: NDArray[np.uint8],
    cols: IntArray,
    rows: IntArray,
    half: int,
    sig: float,
    s: Settings,
    nb: tuple[FloatArray, FloatArray, FloatArray],
    max_fwhm: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.bool_], FloatArray, FloatArray]:
    """The profile fits (as ``fit.fit_columns``): centre row, amplitude, sigma, saturated, ok, noise, rises."""
    h, w = image.shape[:2]
    e = 3
    Pb: Any = _gather(image, cols, rows, half + e, 1).astype(np.float64)
    nb_v, nb_a, nb_s = nb
    has_nb = np.isfinite(nb_v)
    if bool(has_nb.any()):
        rr = rows[None, :] + np.arange(-half - e, half + e + 1)[:, None]
        model = nb_a * np.exp(-0.5 * ((rr - nb_v) / np.where(has_nb, nb_s, 1.0)) ** 2)
        Pb = Pb - np.where(has_nb[None, :], model, 0.0)
    core = Pb[half : half + 2 * e + 1]
    shift = np.argmax(core, axis=0) - e
    satc = core >= s.saturation_dn
    has_sat = satc.any(axis=0)
    if bool(has_sat.any()):
        first = np.argmax(satc, axis=0)
        last = 2 * e - np.argmax(satc[::-1], axis=0)
        shift = np.where(has_sat, (first + last) // 2 - e, shift)
    rows = rows + shift
    P = np.take_along_axis(Pb, (e + shift)[None, :] + np.arange(2 * half + 1)[:, None], axis=0)
    fit = fit_profiles(
        P,
        transposed=True,
        sigma_hint=sig,
        saturation_dn=s.saturation_dn,
        min_sigma_px=s.min_fwhm_px / FWHM_PER_SIGMA,
        max_sigma_px=s.max_sigma_px,
        flank_px=_FLANK_PX,
        max_fwhm_px=max_fwhm,
    )
    ok = fit.ok.copy()
    flat = image.reshape(-1)
    rp = np.clip(rows, 0, h - 1)
    pix = (rp * w + cols) * 3
    lo = (np.clip(rows - half, 0, h - 1) * w + cols) * 3
    hi = (np.clip(rows + half, 0, h - 1) * w + cols) * 3
    rise = [
        flat[pix + ch].astype(np.float64) - 0.5 * (flat[lo + ch].astype(np.float64) + flat[hi + ch]) for ch in (0, 1, 2)
    ]
    centre = np.where(ok, rows - half + fit.centre, np.nan)
    return centre, fit.amplitude, fit.sigma, fit.saturated, ok, fit.noise, np.stack(rise)
