"""Pieces of the column-parallel fit (:mod:`.fit`): gathering windows, colour rises, storing a fit.

The fit lays its profiles out as (rows, columns) arrays so that every inner loop runs over columns and vectorizes:
a window of ``m = 2 half + 1`` rows of ``n`` columns is (m, n). This module gathers those windows from the image
(:func:`gather_green`), reads the colour rises at the peaks (:func:`colour_rises`, for the colour test pooled along
the stripe in :mod:`.finish`) and stores one point's fit into a frame's (:func:`put_fit`); :func:`take` picks
elements by index for every kernel of the frame.
"""

from __future__ import annotations

import numpy as np

from ._jit import callee, empty, inline


@callee
def gather_green(image, cols, top, out):  # type: ignore[no-untyped-def]
    """Green samples of ``out.shape[0]`` consecutive rows per column into ``out`` (K, N), any dtype: sample ``k``
    of column ``t`` is row ``top[t] + k`` (clamped to the image) of column ``cols[t]``. Where all of them lie in
    the image: one unsigned base index per column and a row stride per sample (no clamping, no wrap-around), four
    rows per pass over the columns (one base load for four samples)."""
    h = image.shape[0]
    wid = image.shape[1]
    flat = image.reshape(-1)
    n = cols.size
    k_rows = out.shape[0]
    inside = True
    for t in range(n):
        inside &= top[t] >= 0 and top[t] + k_rows - 1 <= h - 1
    if not inside:
        for k in range(k_rows):
            for t in range(n):
                rr = min(max(top[t] + k, 0), h - 1)
                out[k, t] = flat[(rr * wid + cols[t]) * 3 + 1]
        return
    stride = np.uint64(wid * 3)
    base = empty(n, np.uint64)
    for t in range(n):
        base[t] = np.uint64((top[t] * wid + cols[t]) * 3 + 1)
    k = 0
    while k + 4 <= k_rows:
        o = np.uint64(k) * stride
        b0 = out[k]
        b1 = out[k + 1]
        b2 = out[k + 2]
        b3 = out[k + 3]
        for t in range(n):
            ut = np.uint64(t)
            i0 = base[ut] + o
            b0[ut] = flat[i0]
            b1[ut] = flat[i0 + stride]
            b2[ut] = flat[i0 + stride + stride]
            b3[ut] = flat[i0 + stride + stride + stride]
        k += 4
    while k < k_rows:
        o = np.uint64(k) * stride
        bk = out[k]
        for t in range(n):
            bk[np.uint64(t)] = flat[base[t] + o]
        k += 1


@inline
def colour_rises(image, cols, pk_rows, half, channels, rise):  # type: ignore[no-untyped-def]
    """The rise of the ``channels`` (of 0, 1, 2: blue, green, red) at each column's peak row over the mean of the
    rows ``half`` above and below (clamped to the image): into their rows of ``rise`` (3, N), for the colour test
    pooled along the stripe."""
    h = image.shape[0]
    wid = image.shape[1]
    flat = image.reshape(-1)
    n = cols.size
    inside = True
    for t in range(n):
        inside &= pk_rows[t] - half >= 0 and pk_rows[t] + half <= h - 1
    hstride = np.uint64(half * wid * 3)
    for t in range(n):
        pk_row = pk_rows[t]
        if inside:  # flat unsigned indices, no clamping
            rp = np.uint64((pk_row * wid + cols[t]) * 3)
            rl = rp - hstride
            rh = rp + hstride
        else:
            rp = np.uint64((min(max(pk_row, 0), h - 1) * wid + cols[t]) * 3)
            rl = np.uint64((min(max(pk_row - half, 0), h - 1) * wid + cols[t]) * 3)
            rh = np.uint64((min(max(pk_row + half, 0), h - 1) * wid + cols[t]) * 3)
        for ch in channels:
            uc = np.uint64(ch)
            rise[ch, t] = flat[rp + uc] - 0.5 * (float(flat[rl + uc]) + flat[rh + uc])


@inline
def take(a, idx):  # type: ignore[no-untyped-def]
    """``a[idx]`` of a 1-D array ``a`` and indices ``idx`` (K,), in a loop: numba's fancy indexing compiles its
    general machinery (any dimensions, broadcasting, negative indices) at every place it is used."""
    out = empty(idx.size, a.dtype)
    for i in range(idx.size):
        out[i] = a[idx[i]]
    return out


@inline
def put_fit(res, r, i, t):  # type: ignore[no-untyped-def]
    """Store fit ``i`` of ``r`` as point ``t`` of ``res`` (both :class:`~lrsensor.extract.fit.Fits`)."""
    res.centre[t] = r.centre[i]
    res.amplitude[t] = r.amplitude[i]
    res.sigma[t] = r.sigma[i]
    res.saturated[t] = r.saturated[i]
    res.ok[t] = r.ok[i]
    res.local_noise[t] = r.local_noise[i]
    for c in range(3):
        res.rise[c, t] = r.rise[c, i]
