"""Detection: the stripe candidates of one laser in its image band, in one pass over the band.

:func:`detect_band` reads the green channel of the band's rows in place from the (H, W, 3) uint8 BGR image (no
copy of the band), averages it over 2x2 pixels and then over 3 of those columns (along the stripe: it averages the
noise and quarters the work), takes the two-sided contrast ``G(v) - max(G(v - d), G(v + d))`` (and the same at
``d / 2``, the larger of the two) saturating at 0, and keeps its vertical local maxima above a threshold from the
band's noise. The contrast is positive only on ridges narrower than ``2 d``: thin stripes, not murk gradients,
the backscatter glow of the laser sheet, haze or wide blobs.

In turbid water the sheet's glow lies on the stripe's outer side, ends at the stripe and brightens outward; on far
walls so steeply that the stripe is a shoulder on a step, not a ridge, and the contrast finds nothing. Where the
band shows the glow at the first pass's candidates (counted as they are listed), a second pass
(:func:`glow_candidates`) takes the local maxima of the centre over the mean of the rows ``d / 4`` either side (a
blurred step cancels at its centre) where the outer side is the brighter: first in the columns without a candidate,
then, where it found the stripe there, in all. Clear water never runs it.

The noise (:func:`noise_dn`, :func:`noise_dn_rows`) is robust: the median of second differences of rows two apart
(independent; linear gradients cancel) on a subsample of about 6000 pixels, for Gaussian noise of std s
``0.6745 sqrt(6) s``; histograms, not sorting (integer differences).

Output: per laser, candidates as (N,) detection columns (half resolution, plus the laser's offset so that all
lasers share one column numbering), (N,) full-resolution rows, (N,) response (DN), sorted by column then row,
and the band's pixel noise (DN). Every step is integer arithmetic rounded as OpenCV rounds it
(``cv2.resize(INTER_AREA)``, ``cv2.blur``), so the reference (:mod:`lrsensor.extract.reference_detect`), which calls
those OpenCV functions, finds the same candidates bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import callee, empty, inline, njit, trailing_zeros, zeros

#: Noise of the detection response over the pixel noise: 2x2 average (1/2), then a 3-column box (1/sqrt(3)).
AREA_NOISE = 0.5 / math.sqrt(3.0)


@inline
def noise_col_step(n_triples, cols):  # type: ignore[no-untyped-def]
    """Column step (even, 2 to 8) of the noise samples of a band of ``n_triples`` row triples and ``cols``
    columns: about 6000 samples or more, every 2nd column in small images."""
    return 2 * max(1, min(4, (n_triples * cols) // 12000))


@inline
def noise_dn_rows(flat, width, src, step):  # type: ignore[no-untyped-def]
    """:func:`noise_dn` of the green rows ``src`` (R,) of an image given as ``flat``, the (H * W * 3,) view of a
    C-contiguous BGR image of ``width`` columns, evened (as the band of :func:`detect_band`, whose extra column
    is never sampled: the column step is even): the same samples, read in place (no copy of the band)."""
    return _noise_samples(flat, 3 * width, 3, 1, src, width + width % 2, step)


@callee
def _noise_samples(flat, row_bytes, px_bytes, offset, src, cols, step):  # type: ignore[no-untyped-def]
    """The noise of :func:`noise_dn` from the rows ``src`` (R,) of a flat byte image: sample ``x`` of row ``r`` is
    ``flat[src[r] * row_bytes + offset + px_bytes * x]``; ``cols`` (the band's width) sets the column step."""
    rows = src.size
    if rows < 5:
        return 1.0
    # four interleaved histograms: consecutive equal bins do not wait on each other's increments
    h4 = zeros((4, 1024), np.int64)
    n = (rows - 4 + step - 1) // step
    cs = noise_col_step(n, cols)
    ns = (cols + cs - 1) // cs
    for i in range(n):
        r = i * step
        ba = np.uint64(src[r] * row_bytes + offset)
        bb = np.uint64(src[r + 2] * row_bytes + offset)
        bc = np.uint64(src[r + 4] * row_bytes + offset)
        for j in range(ns):
            o = np.uint64(px_bytes * cs * j)
            d = abs(np.int32(flat[ba + o]) + np.int32(flat[bc + o]) - 2 * np.int32(flat[bb + o]))
            h4[j & 3, min(int(d), 1023)] += 1
    return _noise_from_histograms(h4)


@inline
def _noise_from_histograms(h4):  # type: ignore[no-untyped-def]
    """The noise (DN) from four interleaved histograms (4, 1024) of |second differences|: their median, within its
    integer bin, over 0.6745 sqrt(6) (see :func:`lrsensor.extract.reference_detect._noise_dn`)."""
    hist = empty(1024, np.int64)
    total = 0
    for k in range(1024):
        hist[k] = h4[0, k] + h4[1, k] + h4[2, k] + h4[3, k]
        total += hist[k]
    half = 0.5 * total
    cum = 0
    k = 0
    while k < 1023 and cum + hist[k] < half:
        cum += hist[k]
        k += 1
    lo, width = (0.0, 0.5) if k == 0 else (k - 0.5, 1.0)
    med = lo + width * (half - cum) / max(float(hist[k]), 1.0)
    return max(med / (0.6745 * math.sqrt(6.0)), 0.05)


#: Second-pass candidates in the columns without any first-pass one from which the glow counts as hiding the stripe
#: in this band, and the second pass also searches the columns that have candidates (see :func:`glow_candidates`).
GLOW_PASS_MIN = 8


@inline
def glow_candidates(B, resp, pk, cnt16, row_pk, y0, y1, side, w, ds, hd, t8):  # type: ignore[no-untyped-def]
    """The second pass of :func:`detect_band` (the compiled twin of ``reference_detect._glow_candidates``): a stripe on
    the rising side of the sheet's glow. First in the columns without a candidate whose glow side ``side[2 x]`` is
    known, then, where that found at least :data:`GLOW_PASS_MIN` candidates, in the other columns too: the rows that
    are vertical local maxima of the centre-over-mean response (the centre over the mean of the rows ``hd`` either
    side, rounded half up, at least 0) above ``t8``, whose centre stands above both inner rows (``d / 2`` and ``d /
    4`` inward) by more than ``t8``, and whose outer row at ``d / 2`` is at least as bright as the centre. They are
    marked 2 in ``pk`` (first-pass peaks are 1), counted in ``cnt16``, ``row_pk``, and their response written to
    ``resp`` (all in place). The second sweep runs over all columns: an empty column's hits are marked already and
    skipped (only unmarked rows are tested). Column by column in plain scalar loops: it runs only where a band shows
    the glow, and the vectorized loops it had over the rows cost more of the one-time compile than of a frame
    (:mod:`lrsensor.extract.compile`). The pixels are read as int64 (``int()`` of a uint8 is unsigned in numba: a
    difference would wrap)."""
    ho = resp.shape[0]
    wo = resp.shape[1]
    for sweep in range(2):
        found = 0
        for x in range(wo):
            sd = side[min(2 * x, w - 1)]
            if sd == 0 or (sweep == 0 and cnt16[x] > 0):
                continue
            # the response down the column: at the row before, this one and the next (clamped to the response's rows)
            y_a = int(y0[x])
            r_prev = 0
            r_cur = 0  # (the first two rows only fill these)
            for y in range(y_a - 1, int(y1[x]) + 1):
                yy = min(max(y, 0), ho - 1) + ds
                diff = np.int64(B[yy, x]) - ((np.int64(B[yy - hd, x]) + np.int64(B[yy + hd, x]) + 1) >> 1)
                r_next = int(diff) if diff > 0 else 0  # (int() of a signed integer: signed)
                yc = y - 1  # the row now decided, its response r_cur
                if yc >= y_a and pk[yc, x] == 0 and r_cur > t8 and r_prev <= r_cur and r_next <= r_cur:
                    c = np.int64(B[yc + ds, x])
                    inner = max(np.int64(B[yc + (0 if sd > 0 else 2 * ds), x]), np.int64(B[yc + ds - sd * hd, x]))
                    if c - inner > t8 and np.int64(B[yc + (2 * ds if sd > 0 else 0), x]) >= c:
                        pk[yc, x] = 2
                        cnt16[x] += 1
                        resp[yc, x] = r_cur
                        row_pk[yc] = 1
                        found += 1
                r_prev = r_cur
                r_cur = r_next
        if found < GLOW_PASS_MIN:
            return


@njit
def detect_band(image, r0, r1, d, snr_thr, area_noise, thr_min, v_lo, v_hi, side, col_offset):  # type: ignore[no-untyped-def]
    """Candidates of one laser at detection scale 2 in one pass over its band (the compiled twin of
    ``reference_detect._candidates``: the same arithmetic as its OpenCV steps, bit for bit).

    The green channel of rows ``[r0 - d, r1 + d)`` (replicated beyond the image, evened), its robust noise
    (:func:`noise_dn`), the 2x2 area average (rounded as ``cv2.resize(INTER_AREA)``), a 3-column box
    (``cv2.blur``, reflected at the ends), the saturating two-sided contrast at ``d / 2`` and ``d / 4`` detection
    rows, and its vertical local maxima above ``max(thr_min, snr_thr * noise * area_noise)`` inside the band ``v_lo``,
    ``v_hi`` (W,).

    Args:
        image: (H, W, 3) uint8 C-contiguous; r0, r1: the band's bounding rows; d: contrast offset (even), rows.

    Returns:
        ``(cols, rows, strength, noise, second)``: detection columns plus ``col_offset`` (N,) int64, full rows (N,)
        int64, response (N,) float64, sorted by column then row; the pixel noise, DN; and (N,) int64, 1 where the
        candidate is the second pass's (on the glow's rising side, :func:`glow_candidates`), else 0 (int64, not bool:
        the types the frame's call already has, no list and array code compiled for one more).
    """
    h = image.shape[0]
    w = image.shape[1]
    flat = image.reshape(-1)
    a0 = max(r0 - d, 0)
    a1 = min(r1 + d, h)
    if (a1 - a0) % 2 and a1 < h:
        a1 += 1
    top = max(d - (r0 - a0), 0)
    bot = max(d - (a1 - r1), 0)
    rows_g = a1 - a0 + top + bot
    rows_g += rows_g % 2
    # padded green row i -> image row src[i] (replicated border)
    src = empty(rows_g, np.int64)
    for i in range(rows_g):
        src[i] = min(max(a0 - top + i, a0), a1 - 1)
    # 2x2 area average straight from the image (green bytes 3 apart; an odd last column is paired with itself),
    # then the 3-column box: (gh, wo)
    gh = rows_g // 2
    wo = (w + 1) // 2
    w2 = w // 2
    B = empty((gh, wo), np.uint8)
    A = empty(wo + 2, np.int32)
    two = np.uint16(2)
    third = np.uint64(3)
    for y in range(gh):
        b0 = np.uint64(src[2 * y] * w * 3 + 1)
        b1 = np.uint64(src[2 * y + 1] * w * 3 + 1)
        for x in range(w2):  # in uint16 (16 lanes; the sum of four bytes and 2 fits)
            o = np.uint64(6 * x)
            s4 = np.uint16(
                np.uint16(flat[b0 + o])
                + np.uint16(flat[b0 + o + third])
                + np.uint16(flat[b1 + o])
                + np.uint16(flat[b1 + o + third])
                + two
            )
            A[np.uint64(x + 1)] = np.int32(np.uint16(s4 >> two))
        if wo > w2:
            o = np.uint64(3 * (w - 1))
            A[wo] = (2 * np.int32(flat[b0 + o]) + 2 * np.int32(flat[b1 + o]) + 2) >> 2
        if wo > 1:
            A[0] = A[2]
            A[wo + 1] = A[wo - 1]
        else:
            A[0] = A[1]
            A[2] = A[1]
        by = B[y]
        for x in range(wo):  # round(s / 3) = floor((s + 1) / 3) = ((s + 1) * 21846) >> 16 for 0 <= s <= 765
            ux = np.uint64(x)
            s3 = np.int32(A[ux] + A[ux + 1] + A[ux + 2] + 1)  # int32 throughout: 8 lanes, not 4
            by[ux] = np.uint8(np.int32(s3 * np.int32(21846)) >> np.int32(16))
    # the noise after the pass over the band, whose rows its samples read: cached now, not scattered misses
    noise = max(noise_dn_rows(flat, w, src, min(max(rows_g // 24, 2), 16)), 0.5)
    # two-sided contrast, saturating at 0 (uint8 arithmetic), and at half the offset
    ds = d // 2
    hd = ds // 2
    ho = gh - 2 * ds
    thr = max(thr_min, snr_thr * (noise * area_noise))
    t8 = min(max(int(math.floor(thr)), 0), 255)  # noqa: RUF046 (v > thr for an integer v)
    if ho <= 0:
        e_i = empty(0, np.int64)
        return e_i, e_i, empty(0, np.float64), noise, e_i
    # in uint8, saturating (the response of ``c - max(..)`` clipped at 0 is ``c - min(c, ..)``): 32 lanes
    resp = empty((ho, wo), np.uint8)
    for y in range(ho):
        bc = B[y + ds]
        b0 = B[y]
        b1 = B[y + 2 * ds]
        ry = resp[y]
        if hd >= 2:
            h0 = B[y + ds - hd]
            h1 = B[y + ds + hd]
            for x in range(wo):
                ux = np.uint64(x)
                c = bc[ux]
                m = min(max(b0[ux], b1[ux]), max(h0[ux], h1[ux]))
                ry[ux] = c - min(c, m)
        else:
            for x in range(wo):
                ux = np.uint64(x)
                c = bc[ux]
                ry[ux] = c - min(c, max(b0[ux], b1[ux]))
    # vertical local maxima inside the band: counted per column, then placed column by column
    y0 = empty(wo, np.uint16)
    y1 = empty(wo, np.uint16)
    for x in range(wo):
        uf = min(2 * x, w - 1)
        lo = v_lo[uf]
        hi = v_hi[uf]
        if hi < lo:
            y0[x] = 0
            y1[x] = 0
        else:
            y0[x] = min(max((lo - r0 + 1) // 2, 0), 65535)
            y1[x] = min(max(min((hi - r0) // 2 + 1, ho), 0), 65535)
    cnt16 = zeros(wo, np.uint16)
    w8 = (wo + 7) // 8 * 8  # rows of the peak mask padded to whole 8-byte words
    pk = zeros((ho, w8), np.uint8)
    tu = np.uint8(t8)
    row_pk = empty(ho, np.uint8)  # any peak in the row: the rows without any are skipped below
    for y in range(ho):
        rm = resp[max(y - 1, 0)]
        rc = resp[y]
        rp = resp[min(y + 1, ho - 1)]
        py = pk[y]
        fy = np.uint16(y)
        for x in range(wo):
            ux = np.uint64(x)
            v = rc[ux]
            is_pk = (v > tu) & (rm[ux] <= v) & (rp[ux] <= v) & (fy >= y0[ux]) & (fy < y1[ux])
            py[ux] = is_pk
            cnt16[ux] += np.uint16(is_pk)
        any_pk = np.uint8(0)
        for x in range(wo):  # an integer OR (vectorizes)
            any_pk |= py[np.uint64(x)]
        row_pk[y] = any_pk
    # the candidates, column by column; where the band shows the laser sheet's glow at them (the twin of
    # reference_detect._glow_shows: at a quarter of them or more the row d / 4 outward, on the glow's side, is brighter
    # than the row d / 4 inward by more than the threshold; in clear water both are background, in turbid water the
    # glow's edge lies between them), the second pass's too (the candidates listed once more: one call site of each
    # part)
    for pass_ in range(2):
        cnt = zeros(wo + 1, np.int64)  # running count: the first candidate of each column
        for x in range(wo):
            cnt[x + 1] = cnt[x] + np.int64(cnt16[x])
        n = cnt[wo]
        cu = empty(n, np.int64)
        cv = empty(n, np.int64)
        ca = empty(n, np.float64)
        c2 = empty(n, np.int64)
        pos = cnt[:wo].copy()
        words = pk.reshape(-1).view(np.uint64)
        nw8 = w8 // 8
        n_glow = 0
        for y in range(ho):
            if row_pk[y] == 0:
                continue
            ry = resp[y]
            vy = r0 + 2 * y
            for k in range(nw8):
                wk = words[y * nw8 + k]  # the peaks of 8 columns, one byte (0, 1 or 2) each
                while wk:  # the set bytes, lowest first (none in the common case)
                    x = 8 * k + (trailing_zeros(wk) >> 3)
                    wk &= wk - np.uint64(1)
                    j = pos[x]
                    cu[j] = x + col_offset
                    cv[j] = vy
                    ca[j] = ry[x]
                    c2[j] = pk[y, x] > 1
                    sd = side[min(2 * x, w - 1)]
                    step = np.int64(B[y + ds + hd, x]) - np.int64(B[y + ds - hd, x])
                    if (sd > 0 and step > t8) or (sd < 0 and -step > t8):
                        n_glow += 1
                    pos[x] = j + 1
        if pass_ > 0 or hd < 2 or not (n > 0 and 4 * n_glow >= n):
            return cu, cv, ca, noise, c2
        glow_candidates(B, resp, pk, cnt16, row_pk, y0, y1, side, w, ds, hd, t8)
    return cu, cv, ca, noise, c2
