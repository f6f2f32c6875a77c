"""The reference's neighbours, gates and smoothing (numpy): steps 4 and 5 of
:func:`lrsensor.extract.reference.extract_frame`.

- :func:`neighbours`: for every fitted point the nearest stripe of another laser in its column that the point's
  fit can see (row, amplitude, sigma; NaN row = none), by :func:`read_reach` and the tails of
  :mod:`lrsensor.extract.refit` (:data:`~lrsensor.extract.refit.NEIGHBOUR_TAIL`,
  :data:`~lrsensor.extract.refit.LOG_FLANK_TAIL`, read at each call);
- :func:`pooled_gates`: the colour test and the signal-to-noise ratio pooled along the stripe;
- :func:`smooth`: the edge-preserving along-stripe line fits (:mod:`lrsensor.extract.smooth` explains them).

Rows and sigmas in pixels, amplitudes in DN; (N,) arrays, one entry per point.
"""

from __future__ import annotations

import warnings

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..port import central_view
from . import refit
from .settings import Settings
from .smooth import SUBBLOCK_MIN_K, SUBBLOCK_SIGMAS

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def read_reach(
    sig: FloatArray, sat: NDArray[np.bool_], read: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """How many rows from their centres the points' fits read (N,) each, ``(core, flanks)``: their centroids and
    their background flanks, from their sigma and saturation (N,) and ``read = (near, far, wide_sigma)`` (as
    :func:`lrsensor.extract.refit.read_reach`, for all points at once)."""
    near, far, wide_sigma = read
    with np.errstate(invalid="ignore"):
        plain = ~sat & (sig <= wide_sigma)
        core = np.minimum(far, 1.0 + np.ceil(3.0 * np.maximum(sig, 1.1)))
    return np.where(plain, core, far), np.where(plain, min(far, 1.0 + near), far)


def neighbours(
    laser: IntArray,
    cols: IntArray,
    v: FloatArray,
    amp: FloatArray,
    sig: FloatArray,
    sat: NDArray[np.bool_],
    good: NDArray[np.bool_],
    n_lasers: int,
    width: int,
    max_dist: float,
    read: tuple[float, float, float],
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For every fitted point (N,): the nearest stripe of another laser in the same column (row, amplitude,
    sigma), NaN row when none is closer than ``max_dist`` rows or its Gaussian stays below
    :data:`~lrsensor.extract.refit.NEIGHBOUR_TAIL` of the point's amplitude in the rows the point's centroid
    reads, or :data:`~lrsensor.extract.refit.NEIGHBOUR_FLANK_TAIL` in its background flanks (:func:`read_reach`
    with ``read``)."""
    V = np.full((n_lasers, width), np.nan)
    A = np.zeros((n_lasers, width))
    S = np.ones((n_lasers, width))
    V[laser[good], cols[good]] = v[good]
    A[laser[good], cols[good]] = amp[good]
    S[laser[good], cols[good]] = np.where(np.isfinite(sig[good]), sig[good], 1.0)
    out_v = np.full(v.size, np.nan)
    out_a = np.zeros(v.size)
    out_s = np.ones(v.size)
    best = np.full(v.size, np.inf)
    for other in range(n_lasers):
        ov = V[other, cols]
        with np.errstate(invalid="ignore"):
            dist = np.abs(ov - v)
            take = (laser != other) & (dist < max_dist) & (dist < best)
        out_v = np.where(take, ov, out_v)
        out_a = np.where(take, A[other, cols], out_a)
        out_s = np.where(take, S[other, cols], out_s)
        best = np.where(take, dist, best)
    core, flanks = read_reach(sig, sat, read)
    with np.errstate(invalid="ignore"):
        g_c = np.maximum(best - core, 0.0) / out_s
        g_f = np.maximum(best - flanks, 0.0) / out_s
        log_tail = np.maximum(-0.5 * g_c**2, -0.5 * g_f**2 + refit.LOG_FLANK_TAIL)
        tail = out_a * np.exp(log_tail) > refit.NEIGHBOUR_TAIL * np.maximum(amp, 1.0)
    far = ~tail
    out_v[far] = np.nan
    out_a[far] = 0.0
    out_s[far] = 1.0
    return out_v, out_a, out_s


def pooled_gates(
    col_v: IntArray,
    chain: IntArray,
    ok: NDArray[np.bool_],
    sat: NDArray[np.bool_],
    rise: FloatArray,
    snr: FloatArray,
    s: Settings,
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Colour test and signal-to-noise ratio pooled along the stripe (``finish.finish_points``' gates).

    The rises (3, N) of the fitted columns ``ok`` on the same chain within ``s.gate_pool_cols`` columns are
    summed: green must rise ``min_green_ratio`` times more than red and blue (saturated columns pass). The ratio
    of a column becomes the median of those columns' (still passing) ratios, at most its own over
    ``s.snr_floor_frac``. Columns (N,) are sorted and unique.

    Returns:
        ``(ok, snr)``: the columns passing the colour test, and the pooled ratios (N,).
    """
    pool = s.gate_pool_cols
    n_pad = int(col_v.max()) + 1 + 2 * pool if col_v.size else 1
    ch = np.full(n_pad, -1, np.int64)
    ch[col_v + pool] = chain
    dense = np.zeros((3, n_pad))
    dense[:, col_v + pool] = np.where(ok, rise, 0.0)
    acc = np.zeros((3, col_v.size))
    for o in range(-pool, pool + 1):
        acc += np.where(ch[col_v + pool + o] == chain, dense[:, col_v + pool + o], 0.0)
    good = ok & ((acc[1] >= s.min_green_ratio * np.maximum(acc[0], acc[2])) | sat)
    vals = np.full(n_pad, np.nan)
    vals[col_v + pool] = np.where(good, snr, np.nan)
    st = np.stack(
        [np.where(ch[col_v + pool + o] == chain, vals[col_v + pool + o], np.nan) for o in range(-pool, pool + 1)]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows (columns that fail anyway)
        pooled = np.nanmedian(st, axis=0)
    pooled = np.where(np.isfinite(pooled), pooled, snr)
    return good, np.minimum(pooled, snr / s.snr_floor_frac)


def smooth(y: FloatArray, run: IntArray, scales: tuple[int, ...], x: FloatArray | None = None) -> FloatArray:
    """Edge-preserving local linear smoothing of ``y`` (N,) (NaN = no measurement) within runs.

    ``x`` (N,): the coordinates of the columns in which the lines are straight (finite, increasing within each
    run; None: the column index).

    ``run`` (N,) labels each measured column with its run (a stripe piece: one chain, small gaps allowed;
    -1 = none); runs are intervals of columns. For each column and each half-width k of ``scales`` (largest
    first) the straight-line fits over the centred, the left and the right window of ``2 k + 1`` columns (inside
    the column's run) are compared and the one with the smallest residual is kept, so corners and depth steps
    are not rounded. A column takes the largest scale whose residual variance is consistent with the local
    measurement noise (estimated from lag-4 second differences), otherwise its own value.
    """
    n = y.size
    out = y.copy()
    have = run >= 0
    lag = 4
    if not np.any(have) or n <= 2 * lag + 2:
        return out
    idx = np.arange(n, dtype=np.float64) if x is None else np.asarray(x, dtype=np.float64)
    # run extent of every column
    cols = np.flatnonzero(have)
    r = run[cols]
    starts = np.flatnonzero(np.concatenate([[True], r[1:] != r[:-1]]))
    ends = np.concatenate([starts[1:], [r.size]]) - 1
    run_lo = np.full(n, n, np.int64)
    run_hi = np.full(n, -1, np.int64)
    seg = np.cumsum(np.concatenate([[True], r[1:] != r[:-1]])) - 1
    run_lo[cols] = cols[starts][seg]
    run_hi[cols] = cols[ends][seg]
    # local noise: lag-4 second differences inside runs
    same = have[lag:-lag] & have[: -2 * lag] & have[2 * lag :]
    same &= (run[: -2 * lag] == run[lag:-lag]) & (run[2 * lag :] == run[lag:-lag])
    if int(same.sum()) < 8:
        return out
    yz = np.where(have, y, 0.0)
    d2 = np.zeros(n)
    d2[lag:-lag] = np.where(same, (yz[: -2 * lag] - 2.0 * yz[lag:-lag] + yz[2 * lag :]) ** 2, 0.0)
    var_all = float(np.median(d2[lag:-lag][same])) / (6.0 * 0.4549) + 1e-8
    cnt2 = np.zeros(n)
    cnt2[lag:-lag] = same
    # window sums by cumulative sums (values relative to the first value of each run)
    base = np.zeros(n)
    base[cols] = y[cols][starts][seg]
    z = np.where(have, y - base, 0.0)
    m = have.astype(np.float64)

    def cs(a: FloatArray) -> FloatArray:
        return np.concatenate([[0.0], np.cumsum(a)])

    c_m, c_mx, c_mxx = cs(m), cs(m * idx), cs(m * idx * idx)
    c_z, c_zx, c_zz = cs(z), cs(z * idx), cs(z * z)
    c_d2, c_n2 = cs(d2), cs(cnt2)
    done = ~have
    for k in scales:
        if k < 1 or 2 * k + 1 > n or bool(done.all()):
            continue
        c = np.arange(k, n - k)
        lo, hi = c - k, c + k + 1
        s0 = c_m[hi] - c_m[lo]
        sx = c_mx[hi] - c_mx[lo]
        sxx = c_mxx[hi] - c_mxx[lo]
        t0 = c_z[hi] - c_z[lo]
        tx = c_zx[hi] - c_zx[lo]
        yy = c_zz[hi] - c_zz[lo]
        cf = idx[c]
        s1 = sx - cf * s0
        s2 = sxx - 2.0 * cf * sx + cf * cf * s0
        t1 = tx - cf * t0
        det = s0 * s2 - s1 * s1
        full = (s0 >= 0.6 * (2 * k + 1)) & (det > 1e-9)
        det = np.where(full, det, 1.0)
        b = (s0 * t1 - s1 * t0) / det
        a = (t0 - b * s1) / np.maximum(s0, 1.0)
        rss = np.maximum(yy - a * t0 - b * t1, 0.0)
        nv = c_n2[hi] - c_n2[lo]
        var = np.where(nv >= 5, (c_d2[hi] - c_d2[lo]) / (6.0 * np.maximum(nv, 1.0)), var_all)
        dof = np.maximum(s0 - 2.0, 1.0)
        vv = np.maximum(var, 1e-8)
        accept = full & (rss <= vv * dof * (1.0 + 3.0 * np.sqrt(2.0 / dof)))
        if k >= SUBBLOCK_MIN_K:
            # long windows: each quarter must fit the line too (a kink near one end is diluted in the whole
            # window's residual, not in its quarter's)
            qn = (2 * k + 1) // 4
            for j in range(4):
                p0 = lo + j * qn
                p1 = hi if j == 3 else p0 + qn
                q0 = c_m[p1] - c_m[p0]
                sxq = c_mx[p1] - c_mx[p0]
                qx = sxq - cf * q0
                qxx = c_mxx[p1] - c_mxx[p0] - 2.0 * cf * sxq + cf * cf * q0
                qt = c_z[p1] - c_z[p0]
                qtx = c_zx[p1] - c_zx[p0] - cf * qt
                qyy = c_zz[p1] - c_zz[p0]
                r_q = qyy - 2.0 * a * qt - 2.0 * b * qtx + a * a * q0 + 2.0 * a * b * qx + b * b * qxx
                q1 = np.maximum(q0, 1.0)
                accept &= (q0 < 1.0) | (r_q <= vv * q1 * (1.0 + SUBBLOCK_SIGMAS * np.sqrt(2.0 / q1)))
        best = np.full(n, np.inf)
        val = np.full(n, np.nan)
        for shift in (0, -k, k):  # window centre at u + shift
            u = c - shift
            inside = (u >= 0) & (u < n)
            u, ci = u[inside], np.flatnonzero(inside)
            ok = have[u] & accept[ci] & (c[ci] - k >= run_lo[u]) & (c[ci] + k <= run_hi[u]) & (rss[ci] < best[u])
            uu, cc = u[ok], ci[ok]
            best[uu] = rss[cc]
            val[uu] = a[cc] + b[cc] * (idx[uu] - idx[c[cc]]) + base[uu]
        take = ~done & np.isfinite(val)
        out[take] = val[take]
        done |= take
    return out


def smooth_through_port(
    y: FloatArray, run: IntArray, scales: tuple[int, ...], w: int, calibration: Calibration
) -> FloatArray:
    """:func:`smooth` of rows ``y`` (N,) (virtual columns ``laser * w + column``, NaN = none) seen through the
    calibration's flat port: the line fits run where a pinhole in the water at the camera centre would see the
    points (:func:`lrsensor.port.central_view`), where a stripe on a flat surface is straight, and the
    corrections go back to image rows through the local derivative (``finish.port_view`` and
    ``from_port_view`` are the
    compiled twin). Rows whose ray misses their laser's plane are left as they are."""
    idx = np.flatnonzero(np.isfinite(y))
    uv = np.stack([(idx % w).astype(np.float64), y[idx]], axis=1)
    cols, rows, slope = central_view(calibration, uv, idx // w)
    seen = np.isfinite(rows) & np.isfinite(cols)
    yw = np.full(y.size, np.nan)
    yw[idx[seen]] = rows[seen]
    run_w = run.copy()
    run_w[idx[~seen]] = -1
    # the columns' coordinates: the central view's where seen, interpolated (by the index) between them
    index = np.arange(y.size, dtype=np.float64)
    x = np.interp(index, index[idx[seen]], cols[seen]) if seen.any() else index
    sw = smooth(yw, run_w, scales, x)
    out = y.copy()
    with np.errstate(invalid="ignore"):
        step = (sw[idx] - rows) / slope
    out[idx] = np.where(np.isfinite(step), y[idx] + step, y[idx])
    return out
