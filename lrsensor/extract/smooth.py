"""Along-stripe smoothing: edge-preserving local line fits within the runs of a stripe.

:func:`smooth_runs` takes the centre rows of the kept columns (N,) (NaN = none) and their run labels (-1 = none;
runs are intervals of columns: one stripe piece, small gaps allowed) and, for each half-width ``k`` of
``scales`` (largest first), fits straight lines over the centred, left and right windows of ``2 k + 1`` columns
inside the column's run by running sums (O(1) per window). Of the three the smallest residual wins (corners and
depth steps are not rounded), and a column takes the largest scale whose residual is consistent with the local
noise (lag-4 second differences within the run; windows of at least :data:`SUBBLOCK_MIN_K` must fit in each of
their quarters too). It averages the independent per-column noise: the dim ends of a stripe and far walls most.
Rows in pixels.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import arange, callee, empty, full, inline, njit, zeros
from .sorting import median

#: Smallest half-width of the along-stripe line fits whose four quarters are tested on their own too (a kink
#: near one end of a long window is diluted in the whole window's residual, not in its quarter's).
SUBBLOCK_MIN_K = 192


#: Tolerance of that quarter test, in standard deviations of the chi-square residual.
SUBBLOCK_SIGMAS = 6.0


@inline
def _quarter_ok(p0, p1, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz):  # type: ignore[no-untyped-def]
    """Whether the line ``a + b (x - c)`` fits the columns ``[p0, p1)`` within the noise ``vv`` (or they are empty)."""
    q0 = c_m[p1] - c_m[p0]
    qx = c_mx[p1] - c_mx[p0] - c * q0
    qxx = c_mxx[p1] - c_mxx[p0] - 2.0 * c * (c_mx[p1] - c_mx[p0]) + c * c * q0
    qt = c_z[p1] - c_z[p0]
    qtx = c_zx[p1] - c_zx[p0] - c * qt
    qyy = c_zz[p1] - c_zz[p0]
    r_q = qyy - 2.0 * a * qt - 2.0 * b * qtx + a * a * q0 + 2.0 * a * b * qx + b * b * qxx
    # r_q <= vv q1 (1 + S sqrt(2 / q1)), squared (no square root, no division): the excess over vv q1 is at most
    # vv S sqrt(2 q1)
    q1 = max(q0, 1.0)
    ex = r_q - vv * q1
    return (q0 < 1.0) | (ex <= 0.0) | (ex * ex <= (2.0 * SUBBLOCK_SIGMAS * SUBBLOCK_SIGMAS) * (vv * vv * q1))


@callee
def _fit_windows(k, i0, i1, x, c_m, c_mx, c_mxx, c_z, c_zx, c_zz, c_d2, c_n2, var_all, a_c, b_c, rss_c, acc_c):  # type: ignore[no-untyped-def]
    """The line fits of :func:`smooth_runs` over every window ``[c - k, c + k]`` (same arithmetic), without
    branches: fills ``a_c``, ``b_c``, ``rss_c`` (N,) and ``acc_c`` (N,) bool for the centres ``c = i + k``,
    ``i`` in ``[i0, i1)`` (all of them: ``[0, N - 2 k)``); the lines are in the coordinates ``x`` (N,) of the
    columns, about the centre's.

    Unsigned indices (no negative-index wrap-around), no branches, and the quarter checks of long windows in a
    second pass (one loop with all of it has too many arrays for the compiler's alias checks): both vectorize.
    """
    full_n = 0.6 * (2 * k + 1)
    m = np.uint64(2 * k + 1)
    uk = np.uint64(k)
    for i in range(i0, i1):
        lo = np.uint64(i)
        hi = lo + m
        c = x[np.uint64(i + k)]
        s0 = c_m[hi] - c_m[lo]
        sx = c_mx[hi] - c_mx[lo]
        sxx = c_mxx[hi] - c_mxx[lo]
        t0 = c_z[hi] - c_z[lo]
        tx = c_zx[hi] - c_zx[lo]
        yy = c_zz[hi] - c_zz[lo]
        s1 = sx - c * s0
        s2 = sxx - 2.0 * c * sx + c * c * s0
        t1 = tx - c * t0
        det = s0 * s2 - s1 * s1
        full = (s0 >= full_n) & (det > 1e-9)
        b = (s0 * t1 - s1 * t0) / (det if full else 1.0)
        a = (t0 - b * s1) / max(s0, 1.0)
        rss = max(yy - a * t0 - b * t1, 0.0)
        nvv = c_n2[hi] - c_n2[lo]
        var = (c_d2[hi] - c_d2[lo]) / (6.0 * max(nvv, 1.0)) if nvv >= 5 else var_all
        dof = max(s0 - 2.0, 1.0)
        vv = max(var, 1e-8)
        ci = lo + uk
        ex = rss - vv * dof  # rss <= vv dof (1 + 3 sqrt(2 / dof)), squared as in _quarter_ok
        acc_c[ci] = full & ((ex <= 0.0) | (ex * ex <= 18.0 * (vv * vv * dof)))
        a_c[ci] = a
        b_c[ci] = b
        rss_c[ci] = rss
    if k < SUBBLOCK_MIN_K:
        return
    # long windows: each quarter must fit the line too (a kink near one end is diluted in the whole window's
    # residual, not in its quarter's)
    uq = np.uint64((2 * k + 1) // 4)
    for i in range(i0, i1):
        lo = np.uint64(i)
        hi = lo + m
        c = x[np.uint64(i + k)]
        ci = lo + uk
        a = a_c[ci]
        b = b_c[ci]
        nvv = c_n2[hi] - c_n2[lo]
        var = (c_d2[hi] - c_d2[lo]) / (6.0 * max(nvv, 1.0)) if nvv >= 5 else var_all
        vv = max(var, 1e-8)
        p1 = lo + uq
        p2 = p1 + uq
        p3 = p2 + uq
        acc = acc_c[ci]
        acc &= _quarter_ok(lo, p1, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc &= _quarter_ok(p1, p2, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc &= _quarter_ok(p2, p3, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc &= _quarter_ok(p3, hi, c, a, b, vv, c_m, c_mx, c_mxx, c_z, c_zx, c_zz)
        acc_c[ci] = acc


@inline
def smooth_runs(y, run, scales):  # type: ignore[no-untyped-def]
    """Edge-preserving local linear smoothing (the reference's is :func:`lrsensor.extract.reference_finish.smooth`):
    :func:`smooth_runs_at` with the columns' own indices as their coordinates."""
    return smooth_runs_at(y, arange(y.size, np.float64), run, scales)


@njit
def smooth_runs_at(y, x, run, scales):  # type: ignore[no-untyped-def]
    """Edge-preserving local linear smoothing of the rows ``y`` (N,) (NaN = none) whose columns have the
    coordinates ``x`` (N,) (finite, increasing within each run; the index for image columns): the windows are
    ``2 k + 1`` columns, the lines straight in ``x``.

    ``run`` labels are non-decreasing along the measured columns (runs are intervals). Each scale fits only the
    windows that the columns still to do can use, and the scales stop once every column is done.
    """
    n = y.size
    out = y.copy()
    lag = 4
    have = run >= 0
    if n <= 2 * lag + 2:
        return out
    # run extents and each run's first value (the base of the window sums): one pass over the runs' ends
    n_run = 0
    n_have = 0  # integer reductions (they vectorize; a float sum is one serial chain of adds)
    for q in range(n):
        n_run = max(n_run, run[q] + 1)
        n_have += run[q] >= 0
    first = full(max(n_run, 1), n, np.int64)
    last = full(max(n_run, 1), -1, np.int64)
    prev = -1
    for q in range(n):  # (a run's first column where its label first appears: no load of what was just stored)
        r = run[q]
        if r >= 0:
            if r != prev:
                first[r] = q
                prev = r
            last[r] = q
    # local noise: lag-4 second differences inside runs (branch-free over all columns; compacted for the pooled
    # median only where a window needs it)
    d2 = zeros(n, np.float64)
    cnt2 = zeros(n, np.float64)
    ul = np.uint64(lag)
    nv = 0
    for q in range(lag, n - lag):  # unsigned indices: no wrap-around test, the loop vectorizes
        uq = np.uint64(q)
        rq = run[uq]
        same = (rq >= 0) & (run[uq - ul] == rq) & (run[uq + ul] == rq)
        dd = y[uq - ul] - 2.0 * y[uq] + y[uq + ul]
        d2[uq] = dd * dd if same else 0.0
        cnt2[uq] = 1.0 if same else 0.0
        nv += same
    if nv < 8:
        return out
    var_all = np.nan  # the pooled noise: only windows with fewer than 5 samples of their own use it (computed then)
    c_m = empty(n + 1, np.float64)  # running sums: every element is written below
    c_mx = empty(n + 1, np.float64)
    c_mxx = empty(n + 1, np.float64)
    c_z = empty(n + 1, np.float64)
    c_zx = empty(n + 1, np.float64)
    c_zz = empty(n + 1, np.float64)
    c_d2 = empty(n + 1, np.float64)
    c_n2 = empty(n + 1, np.float64)
    c_m[0] = c_mx[0] = c_mxx[0] = c_z[0] = c_zx[0] = c_zz[0] = c_d2[0] = c_n2[0] = 0.0
    # the sums run in registers (read back from the arrays, each would wait on its own store); values relative to
    # the first of their run
    s_m = s_mx = s_mxx = s_z = s_zx = s_zz = s_d2 = s_n2 = 0.0
    for q in range(n):
        r = run[q]
        h = r >= 0
        b = y[min(first[max(r, 0)], n - 1)] if h else 0.0
        mq = 1.0 if h else 0.0
        zq = y[q] - b if h else 0.0
        s_m += mq
        s_mx += mq * x[q]
        s_mxx += mq * x[q] * x[q]
        s_z += zq
        s_zx += zq * x[q]
        s_zz += zq * zq
        s_d2 += d2[q]
        s_n2 += cnt2[q]
        c_m[q + 1] = s_m
        c_mx[q + 1] = s_mx
        c_mxx[q + 1] = s_mxx
        c_z[q + 1] = s_z
        c_zx[q + 1] = s_zx
        c_zz[q + 1] = s_zz
        c_d2[q + 1] = s_d2
        c_n2[q + 1] = s_n2
    done = ~have
    a_c = empty(n, np.float64)
    b_c = empty(n, np.float64)
    rss_c = empty(n, np.float64)
    acc_c = zeros(n, np.bool_)
    left = n_have  # columns still to do
    for k in scales:
        if left == 0:
            break
        if k < 1 or 2 * k + 1 > n:
            continue
        for r in range(n_run):
            f = first[r]
            la = last[r]
            if la - f < 2 * k:  # no window of this scale fits in the run
                continue
            # the run's columns still to do span [u_lo, u_hi]; the windows they can use lie in the run and
            # have their centres within k of that span
            u_lo = f
            while u_lo <= la and done[u_lo]:
                u_lo += 1
            if u_lo > la:
                continue
            u_hi = la
            while done[u_hi]:
                u_hi -= 1
            i0 = max(u_lo - 2 * k, f)
            i1 = min(u_hi + 1, la - 2 * k + 1)
            if i1 <= i0:
                continue
            # those windows' fits, branch-free (vectorized: cheaper than skipping the windows no column needs)
            if math.isnan(var_all):
                few = False
                for i in range(i0, i1):
                    few |= c_n2[i + 2 * k + 1] - c_n2[i] < 5
                if few:
                    vals = empty(n, np.float64)
                    m = 0
                    for q in range(lag, n - lag):
                        if cnt2[q] > 0.0:
                            vals[m] = d2[q]
                            m += 1
                    var_all = median(vals[:m]) / (6.0 * 0.4549) + 1e-8
            _fit_windows(k, i0, i1, x, c_m, c_mx, c_mxx, c_z, c_zx, c_zz, c_d2, c_n2, var_all, a_c, b_c, rss_c, acc_c)
            left -= _pick_windows(k, u_lo, u_hi, f, la, n, done, acc_c, rss_c, a_c, b_c, y[f], x, out)
    return out


@callee
def _pick_windows(k, u_lo, u_hi, f, la, n, done, acc_c, rss_c, a_c, b_c, y0, x, out):  # type: ignore[no-untyped-def]
    """For the columns ``[u_lo, u_hi]`` still to do (``done`` False) of the run ``[f, la]`` (whose values are
    relative to its first, ``y0``): the value of the best accepted line of :func:`smooth_runs` at scale ``k``
    (centred, left or right window, inside the run; smallest residual, the first of equal ones) into ``out``, and
    ``done`` set. Returns how many columns got one.

    One branch-free pass over the columns per window position (centre at ``u``, ``u - k``, ``u + k``, in that
    order), each over the columns whose window lies in the run and in ``[0, n)``: contiguous reads, the loops
    vectorize.
    """
    span = u_hi - u_lo + 1
    best = full(span, np.inf, np.float64)
    val = full(span, np.nan, np.float64)
    for sh in (0, -k, k):
        a0 = max(u_lo, k - sh, f + k - sh)  # window of centre c = u + sh from c - k >= max(0, f)
        a1 = min(u_hi + 1, n - k - sh, la - k - sh + 1)  # to c + k <= min(n - 1, la)
        for u in range(a0, a1):
            c = np.uint64(u + sh)
            i = np.uint64(u - u_lo)
            r = rss_c[c]
            ok = acc_c[c] & (r < best[i])
            v = a_c[c] + b_c[c] * (x[np.uint64(u)] - x[c]) + y0
            best[i] = r if ok else best[i]
            val[i] = v if ok else val[i]
    got = 0
    for u in range(u_lo, u_hi + 1):
        uu = np.uint64(u)
        v = val[np.uint64(u - u_lo)]
        take = (not done[uu]) & math.isfinite(v)
        out[uu] = v if take else out[uu]
        done[uu] |= take
        got += take
    return got
