"""The readable reference of the extractor: the whole frame in numpy and OpenCV, the same algorithm as the
compiled road (:mod:`lrsensor.extract.frame`).

It runs where the compiled road cannot: without numba, while numba compiles the kernels in the background (the
first use on a machine without numba's cache), and where a test asks for it
(:data:`lrsensor.extract.subpixel.USE_REFERENCE`). Tests compare the two on whole frames; they are never mixed
step by step. Read it to learn what the kernels compute; read the kernels to learn how they compute it fast.

:func:`extract_frame` takes the frame (H, W, 3) uint8 BGR and the records of
:func:`lrsensor.extract.settings.frame_settings`, and:

1. detects candidates per laser in its band (:mod:`lrsensor.extract.reference_detect`: :func:`_candidates`:
   OpenCV's 2x2 area average, 3-column box, two-sided contrast and local maxima, and where the band shows the
   sheet's glow a second pass for the stripe on the glow's rising side, :func:`_glow_candidates`; bit for bit what
   :func:`lrsensor.extract.detect.detect_band` computes);
2. links them into chains and picks one per column (:mod:`lrsensor.extract.reference_chains`: :func:`_pick`:
   :func:`_merge_plateaus`, :func:`_top_k`, :func:`_chains`), expanded from the half-resolution detection columns
   to full columns;
3. fits the sub-pixel centre of every picked column on its green profile (:mod:`lrsensor.extract.reference_fit`:
   :func:`_fit`, with :func:`lrsensor.extract.centre.fit_profiles`), the window from the frame's typical width
   (:func:`_typical_sigma`) and the widest plausible stripe per column (:func:`_max_fwhm`);
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

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..triangulation import triangulate as _triangulate
from . import reference_finish, reference_glow, reference_pooled, refit
from .centre import FWHM_PER_SIGMA, WIDE_FWHM_PX
from .finish import BLURRED_SIGMA_PX, CENTRE_SD, RUN_MAX_SD_PX, STRIPE_NOISE_MIN
from .fit import flank_offset
from .frame import POOLED_ENDS, RETRY_REFUSED, STATS_POINTS
from .glow import new_water
from .reference_chains import _pick
from .reference_detect import _candidates, _py
from .reference_detect import _noise_dn as _noise_dn  # (tests and the simulator's scoring read it here)
from .reference_finish import pooled_gates, smooth, smooth_through_port
from .reference_fit import _FLANK_PX, _fit, _gather, _max_fwhm, _typical_sigma
from .settings import Bands, Geometry, Settings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


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
