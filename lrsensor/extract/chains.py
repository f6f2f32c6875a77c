"""Continuity: from the candidates of every column to one candidate per column on a stripe piece.

:func:`select_candidates` merges plateaus (maxima of one column closer than 3 rows), keeps the ``k`` strongest
candidates per column, links the candidates of neighbouring columns when they are mutually nearest and closer
than a row step (then across gaps of up to 2 empty columns: dim or occluded columns do not cut a stripe), and
per column picks the candidate on the strongest chain of at least ``min_run`` nodes; shorter chains (speckle,
marine snow, small blobs) are dropped. Columns of different lasers (blocks of the virtual column numbering)
are never linked. :func:`expand_half` maps the picks of the half-resolution detection columns to full columns
(column c stands for 2c and 2c + 1, the latter between c and c + 1 when both are on one chain).

Inputs and outputs are sorted by virtual column ``laser * width + column``; rows in pixels (full resolution).
Why chains: a bright distractor (a streak, a blob) rarely continues over many columns at the stripe's row step,
the stripe does.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import arange, empty, inline, njit, zeros


@njit
def select_candidates(u, v, a, n_cols, k_max, max_jump, block, max_gap, min_run):  # type: ignore[no-untyped-def]
    """Merge plateaus, keep the k strongest candidates per column, link chains, pick per column.

    Args:
        u, v, a: (N,) int64 columns, int64 rows and float64 strengths of the candidates, sorted by column then row.
        n_cols: number of (virtual) columns; k_max: candidates kept per column; max_jump: row step of a link;
        block: columns per laser (no links across); max_gap: largest column step of a link; min_run: shortest
        accepted chain (nodes).

    Returns:
        ``(cols, rows, chain, chain_len)`` of the picked candidate per column that has one: (M,) int64, float64,
        int64, int64.
    """
    n = u.size
    # 1. merge plateaus: maxima of one column closer than 3 rows
    mu = empty(n, np.int64)
    mv = empty(n, np.float64)
    ma = empty(n, np.float64)
    m = 0
    i = 0
    while i < n:
        j = i
        s = float(v[i])
        best = a[i]
        while j + 1 < n and u[j + 1] == u[i] and v[j + 1] - v[j] <= 3:
            j += 1
            s += v[j]
            if a[j] > best:
                best = a[j]
        mu[m] = u[i]
        mv[m] = s / (j - i + 1)
        ma[m] = best
        m += 1
        i = j + 1
    # 2. k strongest per column, stored by rank: VT[q, c], AT[q, c] (entries q >= cnt[c] are never read)
    K = k_max
    VT = empty((K, n_cols), np.float64)
    AT = empty((K, n_cols), np.float64)
    cnt = zeros(n_cols, np.int64)  # candidates per column
    t = 0
    while t < m:
        c = mu[t]
        if t + 1 == m or mu[t + 1] != c:  # the only candidate of its column (the common case)
            VT[0, c] = mv[t]
            AT[0, c] = ma[t]
            cnt[c] = 1
            t += 1
            continue
        while t < m and mu[t] == c:
            # insert by strength (descending; after equal ones)
            pos = K
            for q in range(K):
                if q >= cnt[c] or not (AT[q, c] >= ma[t]):
                    pos = q
                    break
            if pos < K:
                for q in range(K - 1, pos, -1):
                    VT[q, c] = VT[q - 1, c]
                    AT[q, c] = AT[q - 1, c]
                VT[pos, c] = mv[t]
                AT[pos, c] = ma[t]
                cnt[c] = min(cnt[c] + 1, K)
            t += 1
    # 3. chains: mutual nearest links, first between neighbouring columns, then across small gaps. Within one
    # lag the columns are independent (column c only touches its own "has next" flags and column c + lag's "has
    # previous" flags and links), so each lag takes the columns with one candidate on both sides in one
    # branch-free pass and the others one by one. Flags and links by rank: [q, c]; links hold node ids c K + q.
    nn = n_cols * K
    prevT = empty((K, n_cols), np.int64)
    for q in range(K):
        for c in range(n_cols):
            prevT[q, c] = c * K + q
    has_next = zeros((K, n_cols), np.uint8)
    has_prev = zeros((K, n_cols), np.uint8)
    blk = sorted_blocks(arange(n_cols, np.int64), block)  # the block (laser) of each column, no division per link
    one = zeros(n_cols, np.uint8)  # exactly one candidate
    multi = empty(n_cols, np.int64)  # the columns with more than one
    n_multi = 0
    for c in range(n_cols):
        one[c] = cnt[c] == 1
        if cnt[c] > 1:
            multi[n_multi] = c
            n_multi += 1
    v0 = VT[0]
    hn0 = has_next[0]
    hp0 = has_prev[0]
    pv0 = prevT[0]
    for lag in range(1, max_gap + 1):
        ul = np.uint64(lag)
        kl = np.int64(K * lag)
        for c in range(n_cols - lag):  # one candidate each side (the common case): nearest and mutual
            uc = np.uint64(c)
            ud = uc + ul
            ok = (one[uc] & one[ud] & ~hn0[uc] & ~hp0[ud]) & np.uint8(blk[uc] == blk[ud])
            ok &= np.uint8(abs(v0[uc] - v0[ud]) <= max_jump)
            hn0[uc] |= ok
            hp0[ud] |= ok
            pv0[ud] = pv0[ud] - kl if ok else pv0[ud]
        # the pairs with more candidates on a side: c multi, or c + lag multi
        for i in range(2 * n_multi):
            c = multi[i] if i < n_multi else multi[i - n_multi] - lag
            if c < 0 or c + lag >= n_cols:
                continue
            d = c + lag
            if cnt[c] == 0 or cnt[d] == 0 or blk[c] != blk[d]:
                continue
            if cnt[c] == 1 and cnt[d] == 1:  # handled above
                continue
            if i >= n_multi and cnt[c] > 1:  # counted once, as c multi
                continue
            for i0 in range(cnt[c]):
                va = VT[i0, c]
                if math.isnan(va) or has_next[i0, c]:
                    continue
                jb = -1
                db = np.inf
                for j0 in range(cnt[d]):
                    vb = VT[j0, d]
                    if math.isnan(vb) or has_prev[j0, d]:
                        continue
                    dd = abs(va - vb)
                    if dd < db:
                        db = dd
                        jb = j0
                if jb < 0 or db > max_jump:
                    continue
                # mutual: is i0 the nearest free node of column c for jb?
                ib = -1
                dbb = np.inf
                vb = VT[jb, d]
                for q in range(cnt[c]):
                    vq = VT[q, c]
                    if math.isnan(vq) or has_next[q, c]:
                        continue
                    dd = abs(vq - vb)
                    if dd < dbb:
                        dbb = dd
                        ib = q
                if ib != i0:
                    continue
                prevT[jb, d] = c * K + i0
                has_next[i0, c] = 1
                has_prev[jb, d] = 1
    # chain roots, lengths and summed strengths (links point to lower columns: one pass in column order). The
    # current chain's length and strength stay in registers while its nodes follow each other (the common case),
    # not read back from memory node after node; stored when another chain's node comes (the same additions in the
    # same order)
    root = empty(nn, np.int64)
    length = zeros(nn, np.int64)
    strength = zeros(nn, np.float64)
    r_cur = -1
    l_cur = 0
    s_cur = 0.0
    for c in range(n_cols):
        for q in range(cnt[c]):
            node = c * K + q
            p = prevT[q, c]
            r = root[p] if p != node else node
            root[node] = r
            if r != r_cur:
                if r_cur >= 0:
                    length[r_cur] = l_cur
                    strength[r_cur] = s_cur
                r_cur = r
                l_cur = length[r]
                s_cur = strength[r]
            l_cur += 1
            s_cur += AT[q, c]
    if r_cur >= 0:
        length[r_cur] = l_cur
        strength[r_cur] = s_cur
    # 4. per column the candidate on the strongest long-enough chain
    cols = empty(n_cols, np.int64)
    rows = empty(n_cols, np.float64)
    chain = empty(n_cols, np.int64)
    clen = empty(n_cols, np.int64)
    out = 0
    for c in range(n_cols):
        if cnt[c] == 1:  # the common case, without branches: stored, and counted if its chain is long enough
            r = root[c * K]
            cols[out] = c
            rows[out] = VT[0, c]
            chain[out] = r
            clen[out] = length[r]
            out += length[r] >= min_run
            continue
        best_s = -1.0
        best_q = -1
        for q in range(cnt[c]):
            node = c * K + q
            r = root[node]
            if length[r] >= min_run and strength[r] > best_s:
                best_s = strength[r]
                best_q = q
        if best_q >= 0:
            node = c * K + best_q
            cols[out] = c
            rows[out] = VT[best_q, c]
            chain[out] = root[node]
            clen[out] = length[root[node]]
            out += 1
    return cols[:out], rows[:out], chain[:out], clen[:out]


@inline
def sorted_blocks(col_v, width):  # type: ignore[no-untyped-def]
    """The block ``col_v // width`` of each sorted virtual column (N,) int64, without a division per element
    (block ``l`` holds ``[l width, (l + 1) width)``: a laser's columns, at full or detection resolution)."""
    n = col_v.size
    out = empty(n, np.int64)
    b = 0
    for t in range(n):
        while col_v[t] >= (b + 1) * width:
            b += 1
        out[t] = b
    return out


@inline
def expand_half(col_d, rows_f, chain, chain_len, wd, w):  # type: ignore[no-untyped-def]
    """Picks of half-resolution detection columns to full columns: column c stands for 2c and 2c + 1.

    The row of 2c + 1 is the mean of the rows at c and c + 1 when both are on one chain. Input and output are
    sorted by (virtual) column; ``chain_len`` is doubled (full columns).
    """
    n = col_d.size
    cols = empty(2 * n, np.int64)
    rows = empty(2 * n, np.float64)
    ch = empty(2 * n, np.int64)
    cl = empty(2 * n, np.int64)
    k = 0
    lasers = sorted_blocks(col_d, wd)
    for i in range(n):
        laser = lasers[i]
        c = col_d[i] - laser * wd
        cols[k] = laser * w + 2 * c
        rows[k] = rows_f[i]
        ch[k] = chain[i]
        cl[k] = 2 * chain_len[i]
        k += 1
        if 2 * c + 1 < w:
            r = rows_f[i]
            if i + 1 < n and col_d[i + 1] == col_d[i] + 1 and chain[i + 1] == chain[i]:
                r = 0.5 * (rows_f[i] + rows_f[i + 1])
            cols[k] = laser * w + 2 * c + 1
            rows[k] = r
            ch[k] = chain[i]
            cl[k] = 2 * chain_len[i]
            k += 1
    return cols[:k], rows[:k], ch[:k], cl[:k]
