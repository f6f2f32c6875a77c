"""The reference's detection (numpy and OpenCV): step 1 of :func:`lrsensor.extract.reference.extract_frame`, bit
for bit what :func:`lrsensor.extract.detect.detect_band` computes.

- :func:`_candidates`: one laser's stripe candidates in its band (OpenCV's 2x2 area average, a 3-column box, the
  two-sided contrast and its vertical local maxima above the noise-scaled threshold);
- :func:`_glow_shows` and :func:`_glow_candidates`: where the band shows the laser sheet's glow, the second pass
  for the stripe on the glow's rising side;
- :func:`_noise_dn`: the band's pixel noise (DN) that scales the threshold.

Candidates come in detection columns (half resolution: column ``c`` stands for the full columns ``2c`` and
``2c + 1``) and full-resolution rows. The names keep the underscore they had in :mod:`lrsensor.extract.reference`,
which still exports them: the reference is read and tested, not called by other code.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .detect import GLOW_PASS_MIN, noise_col_step
from .settings import Bands, Settings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def _py(f: Any) -> Any:
    """The Python function of a compiled kernel (its plain arithmetic: the reference compiles nothing)."""
    return getattr(f, "py_func", f)


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
