"""The default extractor: one sub-pixel stripe centre per image column per laser.

Pipeline (per laser, only inside the image band the laser can reach for the configured depth limits, see
:mod:`lrsensor.extract.bands`; that band is what makes it fast):

1. **Response**: on the green channel averaged over 2x2 pixels and then 3 of those columns (averages the noise
   along the stripe, quarters the work), the two-sided contrast ``G(v) - max(G(v - d), G(v + d))`` with ``d`` just
   beyond the widest stripe: positive on thin ridges only, not on murk gradients, the backscatter glow of the
   laser sheet, haze or wide blobs.
2. **Candidates**: its vertical local maxima above a threshold from the measured noise (robust second
   differences, blind to smooth gradients); several per column (up to ``max_candidates``).
3. **Continuity**: candidates of neighbouring columns are linked when they are mutually nearest and closer than
   a row step (small gaps bridged); linked chains are stripe pieces. Per column the candidate on the strongest
   chain wins; chains shorter than ``min_run_cols`` (speckle, marine snow, small blobs) are dropped.
4. **Sub-pixel centre** of the chosen candidate on the raw full-resolution green profile of its column
   (:func:`lrsensor.extract.centre.fit_profiles`, or its compiled twin): re-centred on the integer peak (the
   middle of a clipped run), local linear background from two flanks, width check (too narrow = speckle or a
   hot pixel, too wide = glow/haze/blob), Gaussian-weighted centroid with a Newton step (saturated: symmetric
   window centroid). Unbiased for any symmetric profile. Then a colour check (green must rise more than red
   and blue) and a signal-to-noise gate with the local noise of the flanks, both pooled over the point's
   neighbours on its stripe piece (``gate_pool_cols``), so that single noisy pixels do not decide.
5. **Along-stripe smoothing** (default on): per run of a chain (wide pieces within ``max_jump_px`` rows of each
   other joined: a flat top's candidate row wanders and splits its chain), local straight-line fits over up to
   ``2 (16 smooth_half_cols) + 1`` columns; of the centred, left and right windows the one with the smallest
   residual is kept (corners and steps are not rounded), and the largest window whose residual matches the
   local noise wins (the longest must match in each of its quarters too). It averages the independent
   per-column noise (the dim ends of a stripe and far walls most).
6. **Quality** in [0, 1] from the signal-to-noise ratio, the width and the chain length.

Compressed frames (JPEG, MJPEG, H.264: colour stored at half resolution) take ``channel="luma"``: the pipeline
then reads, in place of green, the full-resolution luma on green's scale (:func:`luma_as_green`).

With numba installed the whole pipeline, and the triangulation (eq. 29 with the calibration's distortion) for
:class:`lrsensor.sensor.Sensor`, runs as one compiled call (:func:`lrsensor.extract.frame.extract_frame`);
otherwise as numpy and OpenCV code with the same algorithm.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import ExtractionError
from ..triangulation import _arrays, triangulate
from . import CHANNELS, Detections, _jit, config_with_options, detect, fit, frame, geometry, refit, smooth
from . import compile as _compile
from .bands import LaserBands, laser_bands
from .centre import FWHM_PER_SIGMA, WIDE_FWHM_PX, fit_profiles

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


#: Luma (ITU-R BT.601, as JPEG's) over its green weight, per B, G, R: ``G + 0.194 B + 0.509 R``.
_LUMA_ON_GREEN = np.array([[1.0, 0.0, 0.0], [0.114 / 0.587, 1.0, 0.299 / 0.587], [0.0, 0.0, 1.0]], np.float32)


def luma_as_green(image: NDArray[np.uint8]) -> NDArray[np.uint8]:
    """A copy of the BGR ``image`` (H, W, 3) uint8 whose green channel is the luma over its green weight,
    ``(0.114 B + 0.587 G + 0.299 R) / 0.587`` rounded and clipped at 255; blue and red unchanged.

    A JPEG (and MJPEG, H.264) frame stores luma at full resolution and colour at half: its green is luma plus
    colour sampled every other pixel, which blurs a thin stripe and moves its centre by up to tenths of a pixel,
    depending on where the stripe falls between the colour samples. The luma of the decoded pixels is the
    stored full-resolution one (up to rounding); on green's scale it keeps green's levels for a green stripe
    (the DN limits hold) and adds what the stripe leaks into red and blue. A clipped green stays clipped.
    """
    return np.asarray(cv2.transform(image, _LUMA_ON_GREEN), np.uint8)  # uint8 in, uint8 out (saturated)


@dataclass(frozen=True)
class SubpixelConfig:
    """Options of the sub-pixel extractor (units in the names; defaults suit the paper's camera).

    Attributes:
        min_range_m, max_range_m: depth limits along the optical axis, metres; only the image band where a
            laser can light a surface between them is searched.
        max_sigma_px: widest stripe profile accepted (Gaussian sigma across the stripe, pixels).
        min_fwhm_px: narrowest accepted stripe (full width at half maximum); narrower peaks are speckle.
        saturation_dn: green level from which a sample counts as clipped.
        min_contrast_dn: smallest accepted stripe peak above the local background, DN.
        snr_threshold: detection threshold in units of the measured background noise.
        max_candidates: candidates kept per column (strongest first).
        max_jump_px: largest row change between neighbouring columns of one stripe piece (x1.5 per detection
            column when ``detect_scale`` is 2).
        min_run_cols: shortest accepted stripe piece, columns.
        smooth_half_cols: half-width of the middle scale of the along-stripe line fits, columns; the scales are
            16x, 4x, 1x and 1/4x this (0 = no smoothing); the 16x windows must fit in each quarter too.
        min_green_ratio: the green rise of a point (summed with its neighbours', see ``gate_pool_cols``) must
            exceed this multiple of the red and of the blue rise.
        smooth_detect_cols: horizontal box smoothing of the detection response at full scale, columns.
        detect_scale: 2 = detect candidates on the 2x2-averaged band (faster, averages noise), 1 = full
            resolution; the centres are always fitted at full resolution.
        min_snr: smallest accepted peak-to-noise ratio of a point (noise: the larger of the band's and the
            profile's flanks'); saturated peaks always pass.
        max_sheet_mm: thickest laser sheet on the surface (mm, divergence included): a stripe may be as wide
            as this sheet seen at the range of its row (``max_sheet_mm * f / range``) plus 4 px of blur, or
            ``FWHM_PER_SIGMA * max_sigma_px`` where that is larger; close to the wall a thick sheet draws a
            wide, flat-topped stripe, far away the same width would be glow or haze.
        gate_pool_cols: the colour test and the signal-to-noise ratio of a point are pooled over the fitted
            columns of its stripe piece within this many columns either side (rises summed, ratios' median);
            0 = per column. A dim stripe is then not decimated by single noisy pixels.
        channel: what the stripe is found and fitted in. ``"green"`` (default): the green channel, best for
            lossless frames. ``"luma"``: the luma on green's scale (:func:`luma_as_green`), for frames whose
            colour was stored at half resolution (JPEG, MJPEG and H.264 cameras), where green blurs and shifts
            the stripe by chroma sampled every other pixel; it costs about a millisecond more per 1920x1080
            frame, and on lossless frames a dim pure-green stripe loses about an eighth of its SNR to the red
            and blue noise it adds.
    """

    min_range_m: float = 0.2
    max_range_m: float = 5.0
    max_sigma_px: float = 5.0
    min_fwhm_px: float = 0.8
    saturation_dn: float = 250.0
    min_contrast_dn: float = 5.0
    snr_threshold: float = 4.0
    max_candidates: int = 4
    max_jump_px: float = 3.0
    min_run_cols: int = 8
    smooth_half_cols: int = 24
    min_green_ratio: float = 1.2
    smooth_detect_cols: int = 7
    detect_scale: int = 2
    min_snr: float = 2.5
    max_sheet_mm: float = 20.0
    gate_pool_cols: int = 4
    channel: str = "green"

    def __post_init__(self) -> None:
        if self.channel not in CHANNELS:
            msg = f"channel must be one of {CHANNELS}, got {self.channel!r}"
            raise ExtractionError(msg)
        if not (0 < self.min_range_m < self.max_range_m):
            msg = f"need 0 < min_range_m < max_range_m, got {self.min_range_m} and {self.max_range_m}"
            raise ExtractionError(msg)
        if not self.max_sigma_px > 0 or not self.min_fwhm_px >= 0:
            msg = f"stripe width limits must be positive, got max_sigma_px={self.max_sigma_px}"
            raise ExtractionError(msg)
        if self.detect_scale not in (1, 2):
            msg = f"detect_scale must be 1 or 2, got {self.detect_scale}"
            raise ExtractionError(msg)
        if self.max_candidates < 1 or self.min_run_cols < 1 or self.smooth_half_cols < 0 or self.gate_pool_cols < 0:
            msg = "max_candidates and min_run_cols must be >= 1, smooth_half_cols and gate_pool_cols >= 0"
            raise ExtractionError(msg)

    @classmethod
    def from_options(cls, config: SubpixelConfig | None = None, **options: Any) -> SubpixelConfig:
        """``config`` (or the defaults) with keyword overrides; unknown names raise :class:`ExtractionError`."""
        if config is None and not options and cls is SubpixelConfig:
            return _default_config()  # the per-frame common case: one frozen instance
        return config_with_options(cls, config, "subpixel", options)

    @property
    def contrast_px(self) -> int:
        """Row offset d of the two-sided contrast (even): about 2 sigma beyond the widest stripe's centre."""
        return 2 * math.ceil(self.max_sigma_px + 2.0)

    @property
    def window_half_px(self) -> int:
        """Half-length of the profile cut out around each stripe for the centre fit."""
        return math.ceil(2.6 * 0.5 * FWHM_PER_SIGMA * self.max_sigma_px + 5.0)


@lru_cache(maxsize=1)
def _default_config() -> SubpixelConfig:
    """The default :class:`SubpixelConfig` (frozen, so one instance serves every call)."""
    return SubpixelConfig()


@dataclass(frozen=True)
class _Plan:
    """Per (calibration, depth limits) precomputed data: the bands and their bounding rows per laser."""

    bands: LaserBands
    rows: tuple[tuple[int, int], ...]


@lru_cache(maxsize=16)
def _plan(calibration: Calibration, min_range_m: float, max_range_m: float, margin_px: int) -> _Plan:
    bands = laser_bands(calibration, min_range_m, max_range_m, margin_px)
    return _Plan(bands, tuple(bands.row_range(i) for i in range(bands.n_lasers)))


def _max_fwhm(
    calibration: Calibration, cols: IntArray, rows: IntArray, laser: IntArray, cfg: SubpixelConfig
) -> FloatArray:
    """Widest physically plausible stripe (half-level width, px) at each candidate (N,).

    The candidate pixel is triangulated on its laser's plane; a sheet ``max_sheet_mm`` thick at that depth
    (along the optical axis) spans ``max_sheet_mm * f / depth`` pixels, plus 4 px for blur and the edges;
    never below ``FWHM_PER_SIGMA * max_sigma_px``. Pixels whose ray misses the plane get that floor.
    """
    floor = FWHM_PER_SIGMA * cfg.max_sigma_px
    if cols.size == 0 or cfg.max_sheet_mm <= 0:
        return np.full(cols.size, floor)
    cam = calibration.camera
    if _compile.ready():
        u, v = cols.astype(np.float64), rows.astype(np.float64)
        pts = geometry.triangulate_points(u, v, laser, *_arrays(calibration))
    else:
        pts = triangulate(calibration, np.stack([cols.astype(np.float64), rows.astype(np.float64)], axis=1), laser)
    depth = (pts - calibration.camera_center_body) @ _optical_axis(calibration)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = 1e-3 * cfg.max_sheet_mm * cam.fy / depth + 4.0
    return np.where(np.isfinite(w) & (depth > 0), np.maximum(w, floor), floor)


@lru_cache(maxsize=16)
def _optical_axis(calibration: Calibration) -> FloatArray:
    """Unit vector (3,) of the camera's optical axis in the body frame."""
    cam = calibration.camera
    axis = calibration.rays_body(np.array([[cam.cx, cam.cy]], dtype=np.float64))[0]
    return axis / np.linalg.norm(axis)  # type: ignore[no-any-return]


def _noise_dn(g: NDArray[np.uint8], step: int = 8) -> float:
    """Robust pixel noise (DN) of a band of a green channel, insensitive to smooth gradients (glow, murk).

    Second differences ``g[r] - 2 g[r + 2] + g[r + 4]`` (rows two apart, so independent; linear gradients cancel)
    on every ``step``-th row triple and every 2nd to 8th column (``detect.noise_col_step``: about 6000
    samples); for Gaussian noise of std s their median absolute value is 0.6745 sqrt(6) s.
    """
    if g.shape[0] < 5:
        return 1.0
    n = (g.shape[0] - 4 + step - 1) // step
    cs = getattr(detect.noise_col_step, "py_func", detect.noise_col_step)(n, g.shape[1])  # not compiled
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
    image: NDArray[np.uint8],
    laser: int,
    rows: tuple[int, int],
    bands: LaserBands,
    cfg: SubpixelConfig,
    fast: bool,
    col_offset: int,
) -> tuple[IntArray, IntArray, FloatArray, float]:
    """Stripe candidates of ``laser`` inside its band: rows ``[r0, r1)`` (the band's bounding rows), then the band
    per column.

    The response is a two-sided contrast ``G(v) - max(G(v - d), G(v + d))`` with ``d`` beyond the widest stripe
    (and the same at ``d / 2``, the larger of the two): positive only on ridges narrower than ``2 d`` (not on glow
    ramps, haze or wide blobs). Candidates are its vertical local maxima above the noise-scaled threshold. With
    ``detect_scale == 2`` this runs on the green channel averaged over 2x2 pixels and then over 3 of those
    columns (along the stripe): it averages the noise where the stripe is long and quarters the work; the
    sub-pixel fit later works on the full-resolution profiles. ``fast``: the compiled kernels do the copying,
    noise and maxima (same results).

    Returns:
        ``(cols, rows, strength, noise)``: detection-scale columns plus ``col_offset`` (N,), full-resolution rows
        (N,), contrast (N,), sorted by column then row, and the full-resolution pixel noise (DN).
    """
    r0, r1 = rows
    h, w = image.shape[:2]
    scale = cfg.detect_scale
    d = cfg.contrast_px
    if fast and scale == 2:  # all of it in one compiled pass over the band
        return detect.detect_band(  # type: ignore[no-any-return]
            image,
            r0,
            r1,
            d,
            float(cfg.snr_threshold),
            _AREA_NOISE,
            0.7 * cfg.min_contrast_dn,
            bands.v_lo[laser],
            bands.v_hi[laser],
            col_offset,
        )
    a0, a1 = max(r0 - d, 0), min(r1 + d, h)
    if scale == 2 and (a1 - a0) % 2 and a1 < h:
        a1 += 1  # an even number of rows for the 2x2 average (one more row below: the band check drops it)
    g: Any = detect.green_rows(image.reshape(-1), w, a0, a1) if fast else cv2.extractChannel(image[a0:a1], 1)
    top, bot = d - (r0 - a0), d - (a1 - r1)
    odd_r, odd_c = (g.shape[0] + max(top, 0) + max(bot, 0)) % 2 * (scale - 1), w % 2 * (scale - 1)
    if top > 0 or bot > 0 or odd_r or odd_c:  # pad to the full shift range and even sizes (replicate the border)
        g = cv2.copyMakeBorder(g, max(top, 0), max(bot, 0) + odd_r, 0, odd_c, cv2.BORDER_REPLICATE)
    step = min(max(g.shape[0] // 24, 2), 16)
    noise = max(detect.noise_dn(g, step) if fast else _noise_dn(g, step), 0.5)
    if scale == 2:
        # row y <-> full rows r0 - d + 2 y (+1), column c <-> full columns 2 c (+1)
        g = cv2.resize(g, (g.shape[1] // 2, g.shape[0] // 2), interpolation=cv2.INTER_AREA)
        g = cv2.blur(g, (3, 1))
        noise_s = noise * _AREA_NOISE
        ds = d // 2
        thr = max(0.7 * cfg.min_contrast_dn, cfg.snr_threshold * noise_s)
        kernel = _KERNEL_3
    else:
        ds = d
        if cfg.smooth_detect_cols > 1:
            g = cv2.blur(g, (cfg.smooth_detect_cols, 1))
        thr = max(cfg.min_contrast_dn, cfg.snr_threshold * noise / math.sqrt(max(cfg.smooth_detect_cols, 1)))
        kernel = _KERNEL_5
    resp: Any = cv2.subtract(g[ds:-ds], cv2.max(g[: -2 * ds], g[2 * ds :]))
    # the same at half the offset (a thin stripe next to another ridge at exactly +-d keeps its response)
    hd = ds // 2
    if hd >= 2:
        inner = g[ds - hd : g.shape[0] - ds + hd]
        resp = cv2.max(resp, cv2.subtract(g[ds:-ds], cv2.max(inner[: -2 * hd], inner[2 * hd :])))
    v_lo, v_hi = bands.v_lo[laser], bands.v_hi[laser]
    if fast:
        u, v, a = detect.local_maxima(cv2.transpose(resp), float(thr), r0, scale, v_lo, v_hi, w, col_offset)
        return u, v, a, noise
    loc = cv2.dilate(resp, kernel)
    pk: Any = cv2.compare(resp, loc, cv2.CMP_GE)
    pk &= cv2.compare(resp, thr, cv2.CMP_GT)  # type: ignore[call-overload]
    nz = cv2.findNonZero(pk)
    if nz is None:
        z = np.zeros(0, np.int64)
        return z, z, np.zeros(0), noise
    xy = nz.reshape(-1, 2).astype(np.int64)
    u, v = xy[:, 0], r0 + scale * xy[:, 1]
    a = resp[xy[:, 1], u].astype(np.float64)
    uf = np.minimum(u * scale, w - 1)
    inside = (v >= v_lo[uf]) & (v <= v_hi[uf])  # the band need not be a rectangle
    order = np.argsort(u[inside], kind="stable")  # by column; rows stay ascending (findNonZero is row-major)
    return u[inside][order] + col_offset, v[inside][order], a[inside][order], noise


#: Noise reduction of the detection smoothing: 2x2 average (1/2), then a 3-column box (1/sqrt(3)).
_AREA_NOISE = 0.5 / math.sqrt(3.0)
_KERNEL_3 = cv2.getStructuringElement(cv2.MORPH_RECT, (1, 3))
_KERNEL_5 = cv2.getStructuringElement(cv2.MORPH_RECT, (1, 5))


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


def _smooth(y: FloatArray, run: IntArray, scales: tuple[int, ...]) -> FloatArray:
    """Edge-preserving local linear smoothing of ``y`` (N,) (NaN = no measurement) within runs.

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
    idx = np.arange(n, dtype=np.float64)
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
        cf = c.astype(np.float64)
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
        if k >= smooth.SUBBLOCK_MIN_K:
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
                accept &= (q0 < 1.0) | (r_q <= vv * q1 * (1.0 + smooth.SUBBLOCK_SIGMAS * np.sqrt(2.0 / q1)))
        best = np.full(n, np.inf)
        val = np.full(n, np.nan)
        for shift in (0, -k, k):  # window centre at u + shift
            u = c - shift
            inside = (u >= 0) & (u < n)
            u, ci = u[inside], np.flatnonzero(inside)
            ok = have[u] & accept[ci] & (c[ci] - k >= run_lo[u]) & (c[ci] + k <= run_hi[u]) & (rss[ci] < best[u])
            uu, cc = u[ok], ci[ok]
            best[uu] = rss[cc]
            val[uu] = a[cc] + b[cc] * float(-shift) + base[uu]
        take = ~done & np.isfinite(val)
        out[take] = val[take]
        done |= take
    return out


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


def _read_reach(
    sig: FloatArray, sat: NDArray[np.bool_], read: tuple[float, float, float]
) -> tuple[FloatArray, FloatArray]:
    """How many rows from their centres the points' fits read (N,) each, ``(core, flanks)``: their centroids and
    their background flanks, from their sigma and saturation (N,) and ``read = (near, far, wide_sigma)`` (numpy
    twin of :func:`lrsensor.extract.refit.read_reach`)."""
    near, far, wide_sigma = read
    with np.errstate(invalid="ignore"):
        plain = ~sat & (sig <= wide_sigma)
        core = np.minimum(far, 1.0 + np.ceil(3.0 * np.maximum(sig, 1.1)))
    return np.where(plain, core, far), np.where(plain, min(far, 1.0 + near), far)


def _neighbours(
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
    reads, or :data:`~lrsensor.extract.refit.NEIGHBOUR_FLANK_TAIL` in its background flanks (:func:`_read_reach`
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
    core, flanks = _read_reach(sig, sat, read)
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


#: The pooled signal-to-noise ratio of a column is at most its own divided by this.
_SNR_FLOOR_FRAC = 0.75


def _pooled_gates(
    col_v: IntArray,
    chain: IntArray,
    ok: NDArray[np.bool_],
    sat: NDArray[np.bool_],
    rise: FloatArray,
    snr: FloatArray,
    cfg: SubpixelConfig,
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Colour test and signal-to-noise ratio pooled along the stripe (numpy twin of ``finish_points``' gates).

    The rises (3, N) of the fitted columns ``ok`` on the same chain within ``cfg.gate_pool_cols`` columns are
    summed: green must rise ``min_green_ratio`` times more than red and blue (saturated columns pass). The ratio
    of a column becomes the median of those columns' (still passing) ratios, at most its own over
    ``_SNR_FLOOR_FRAC``. Columns (N,) are sorted and unique.

    Returns:
        ``(ok, snr)``: the columns passing the colour test, and the pooled ratios (N,).
    """
    pool = cfg.gate_pool_cols
    n_pad = int(col_v.max()) + 1 + 2 * pool if col_v.size else 1
    ch = np.full(n_pad, -1, np.int64)
    ch[col_v + pool] = chain
    dense = np.zeros((3, n_pad))
    dense[:, col_v + pool] = np.where(ok, rise, 0.0)
    acc = np.zeros((3, col_v.size))
    for o in range(-pool, pool + 1):
        acc += np.where(ch[col_v + pool + o] == chain, dense[:, col_v + pool + o], 0.0)
    good = ok & ((acc[1] >= cfg.min_green_ratio * np.maximum(acc[0], acc[2])) | sat)
    vals = np.full(n_pad, np.nan)
    vals[col_v + pool] = np.where(good, snr, np.nan)
    st = np.stack(
        [np.where(ch[col_v + pool + o] == chain, vals[col_v + pool + o], np.nan) for o in range(-pool, pool + 1)]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows (columns that fail anyway)
        pooled = np.nanmedian(st, axis=0)
    pooled = np.where(np.isfinite(pooled), pooled, snr)
    return good, np.minimum(pooled, snr / _SNR_FLOOR_FRAC)


def _gather(image: NDArray[np.uint8], cols: IntArray, rows: IntArray, half: int, channel: int) -> NDArray[np.uint8]:
    """(2 half + 1, N) samples of ``channel`` in columns ``cols`` around ``rows`` (clamped at the border)."""
    h, w = image.shape[:2]
    rr = np.clip(rows[None, :] + np.arange(-half, half + 1)[:, None], 0, h - 1)
    return image.reshape(-1)[(rr * w + cols[None, :]) * 3 + channel]


def _pick_numpy(
    U: IntArray,
    Vr: IntArray,
    Ar: FloatArray,
    n_cols: int,
    cfg: SubpixelConfig,
    block: int,
    jump: float,
    min_run: int,
) -> tuple[IntArray, FloatArray, IntArray, IntArray]:
    """Numpy path of candidate selection: plateaus, k strongest, chains, pick (see ``select_candidates``)."""
    U, Vf, Ar = _merge_plateaus(U, Vr, Ar)
    k = int(min(cfg.max_candidates, np.bincount(U).max()))
    V, A = _top_k(U, Vf, Ar, n_cols, k)
    root, length, strength = _chains(V, A, jump, block)
    score = np.where(np.isfinite(V.ravel()) & (length >= min_run), strength, -np.inf).reshape(n_cols, k)
    pick = np.argmax(score, axis=1) if k > 1 else np.zeros(n_cols, np.int64)
    col_v = np.flatnonzero(np.isfinite(score[np.arange(n_cols), pick]))
    node = col_v * k + pick[col_v]
    return col_v, V.ravel()[node], root[node], length[node]


def _fit_numpy(
    image: NDArray[np.uint8],
    cols: IntArray,
    rows: IntArray,
    half: int,
    sig: float,
    cfg: SubpixelConfig,
    nb: tuple[FloatArray, FloatArray, FloatArray],
    max_fwhm: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.bool_], FloatArray, FloatArray]:
    """Numpy path of the profile fits (see ``fit_columns``): centre row, amplitude, sigma, saturated, ok, noise."""
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
    satc = core >= cfg.saturation_dn
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
        saturation_dn=cfg.saturation_dn,
        min_sigma_px=cfg.min_fwhm_px / FWHM_PER_SIGMA,
        max_sigma_px=cfg.max_sigma_px,
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


#: Use the compiled kernels when numba is installed (tests switch this to compare both paths).
USE_NUMBA = _jit.HAVE_NUMBA

#: Centroid iterations of the sub-pixel fit.
_ITERATIONS = 2
#: Rows per background flank of the sub-pixel fit (as the compiled kernels take them).
_FLANK_PX = 3


def extract(
    image: NDArray[np.uint8], calibration: Calibration, config: SubpixelConfig | None = None, **options: Any
) -> Detections:
    """Sub-pixel stripe centres of every laser: one per column per laser (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR of the calibration's size.
        calibration: the sensor's calibration (the search bands are derived from it).
        config: extractor options (default :class:`SubpixelConfig`).
        **options: overrides of single :class:`SubpixelConfig` fields (e.g. ``min_range_m=0.3``).

    Returns:
        :class:`Detections` with pixel coordinates (N, 2), laser index (N,) and quality (N,).
    """
    return extract_points(image, calibration, config, triangulate=False, **options)[0]


def extract_points(
    image: NDArray[np.uint8],
    calibration: Calibration,
    config: SubpixelConfig | None = None,
    *,
    triangulate: bool = True,
    **options: Any,
) -> tuple[Detections, FloatArray | None]:
    """:func:`extract`, and with ``triangulate`` the body-frame points (N, 3) of the detections, metres, when the
    compiled kernels computed them in the same call (else None: triangulate the detections yourself). Points so
    triangulated are depth-gated too: only those with a camera depth within the range limits are returned."""
    cfg = SubpixelConfig.from_options(config, **options)
    image = np.ascontiguousarray(image) if cfg.channel == "green" else luma_as_green(image)
    fast = USE_NUMBA and _compile.ready()  # the numpy path runs while the kernels compile in the background
    if fast and triangulate and cfg.detect_scale == 2:  # all of it in one compiled call
        last = _LAST_SETTINGS
        if last[0] is calibration and last[1] is cfg:  # the same sensor frame after frame: no hashing
            settings = last[2]
        else:
            settings = _frame_settings(calibration, cfg)
            _remember_settings(calibration, cfg, settings)
        uv, l_o, q_o, xyz, _ = frame.extract_frame(image, *settings)
        return Detections(uv, l_o, q_o), xyz
    plan = _plan(calibration, cfg.min_range_m, cfg.max_range_m, 2)
    w = image.shape[1]
    n_l = plan.bands.n_lasers
    # 1-2. candidates of every laser in its band; laser l's detection columns are numbered l * wd + c
    scale = cfg.detect_scale
    wd = (w + scale - 1) // scale
    parts = []
    noise = np.ones(n_l)
    bands = plan.bands
    for i in range(n_l):
        r0, r1 = plan.rows[i]
        if r1 <= r0:
            continue
        u, v, a, noise[i] = _candidates(image, i, (r0, r1), bands, cfg, fast, i * wd)
        parts.append((u, v, a))
    if not parts or sum(p[0].size for p in parts) == 0:
        return Detections.empty(), None
    # laser by laser, each sorted by column then row: the concatenation is sorted by (virtual) column
    U = np.concatenate([p[0] for p in parts])
    Vr = np.concatenate([p[1] for p in parts])
    Ar = np.concatenate([p[2] for p in parts])
    scales = _scales(cfg.smooth_half_cols)
    if fast:  # steps 3-6 in one compiled call
        u_o, v_o, l_o, q_o, _ = frame.process_candidates(
            image,
            U,
            Vr,
            Ar,
            noise,
            *_fast_settings(cfg, n_l, scales),
            *_geometry(calibration),
            WIDE_FWHM_PX,
            False,
        )
        return Detections(_uv(u_o, v_o), l_o, q_o), None
    return _finish_numpy(image, calibration, cfg, U, Vr, Ar, noise, n_l, scales), None


def _uv(u: FloatArray, v: FloatArray) -> FloatArray:
    """The (N, 2) pixel coordinates of columns ``u`` and rows ``v`` (N,) (a quarter of ``np.stack``'s overhead)."""
    uv = np.empty((u.size, 2))
    uv[:, 0] = u
    uv[:, 1] = v
    return uv


def _scales(k0: int) -> tuple[int, ...]:
    """Half-widths (columns) of the along-stripe line fits, largest first: 16, 4, 1 and 1/4 times ``k0``."""
    return tuple(sorted({16 * k0, 4 * k0, k0, max(1, k0 // 4)}, reverse=True)) if k0 >= 1 else ()


#: The calibration and configuration of the last compiled frame and their :func:`_frame_settings` (identity-keyed:
#: a calibration's hash walks all its fields, tens of microseconds when the caches are cold).
_LAST_SETTINGS: tuple[Any, Any, tuple[Any, ...]] = (None, None, ())


def _remember_settings(calibration: Calibration, cfg: SubpixelConfig, settings: tuple[Any, ...]) -> None:
    global _LAST_SETTINGS
    _LAST_SETTINGS = (calibration, cfg, settings)  # one tuple, replaced whole (safe across threads)


@lru_cache(maxsize=16)
def _frame_settings(calibration: Calibration, cfg: SubpixelConfig) -> tuple[Any, ...]:
    """The arguments of :func:`frame.extract_frame` after the image, for this calibration and configuration
    (cached: the same arrays every frame; the kernels only read them)."""
    plan = _plan(calibration, cfg.min_range_m, cfg.max_range_m, 2)
    n_l = plan.bands.n_lasers
    scales = _scales(cfg.smooth_half_cols)
    detect = np.array([cfg.contrast_px, cfg.snr_threshold, _AREA_NOISE, 0.7 * cfg.min_contrast_dn], np.float64)
    r_z = np.asarray(calibration.R_cam_body, np.float64)[2]
    gate = np.array([r_z[0], r_z[1], r_z[2], float(calibration.t_cam_body[2]), cfg.min_range_m, cfg.max_range_m])
    return (
        np.array(plan.rows, np.int64).reshape(n_l, 2),
        np.ascontiguousarray(plan.bands.v_lo),
        np.ascontiguousarray(plan.bands.v_hi),
        detect,
        *_fast_settings(cfg, n_l, scales),
        *_geometry(calibration),
        WIDE_FWHM_PX,
        gate,
    )


@lru_cache(maxsize=16)
def _fast_settings(
    cfg: SubpixelConfig, n_lasers: int, scales: tuple[int, ...]
) -> tuple[IntArray, FloatArray, IntArray]:
    """The integer and real settings of :func:`frame.process_candidates` and its smoothing scales."""
    ints = np.array(
        [
            cfg.detect_scale,
            cfg.max_candidates,
            cfg.min_run_cols,
            cfg.gate_pool_cols,
            cfg.window_half_px,
            n_lasers,
            _ITERATIONS,
        ],
        np.int64,
    )
    reals = np.array(
        [
            cfg.max_jump_px,
            cfg.saturation_dn,
            cfg.min_fwhm_px,
            cfg.max_sigma_px,
            cfg.min_contrast_dn,
            cfg.min_snr,
            cfg.min_green_ratio,
            cfg.max_sheet_mm,
            _SNR_FLOOR_FRAC,
        ],
        np.float64,
    )
    return ints, reals, np.asarray(scales, np.int64)


@lru_cache(maxsize=16)
def _geometry(calibration: Calibration) -> tuple[FloatArray, ...]:
    """The calibration as the compiled kernels' arrays (see ``_arrays``) and the optical axis (3,), body frame."""
    return (*_arrays(calibration), _optical_axis(calibration))


def _finish_numpy(
    image: NDArray[np.uint8],
    calibration: Calibration,
    cfg: SubpixelConfig,
    U: IntArray,
    Vr: IntArray,
    Ar: FloatArray,
    noise: FloatArray,
    n_l: int,
    scales: tuple[int, ...],
) -> Detections:
    """Steps 3-6 of :func:`extract` in numpy (while the compiled kernels are not ready, or without numba)."""
    w = image.shape[1]
    scale = cfg.detect_scale
    wd = (w + scale - 1) // scale
    n_cols_d = n_l * wd
    n_cols = n_l * w
    # 3. continuity: chains; per column the candidate on the strongest long-enough chain
    jump = cfg.max_jump_px * (1.5 if scale == 2 else 1.0)
    min_run = max(2, math.ceil(cfg.min_run_cols / scale))
    col_d, rows_f, chain, chain_len = _pick_numpy(U, Vr, Ar, n_cols_d, cfg, wd, jump, min_run)
    if col_d.size == 0:
        return Detections.empty()
    if scale == 2:
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
    else:
        col_v = col_d
    rows = np.rint(rows_f).astype(np.int64)
    laser = col_v // w
    cols = col_v - laser * w
    # 4. sub-pixel centre on the green profile; window and spacing from the typical width of this frame
    # the widest plausible stripe per column, computed where it is needed (frame statistics, wide profiles)
    max_fwhm = np.full(cols.size, np.nan)

    def max_fwhm_at(idx: IntArray) -> FloatArray:
        need = idx[np.isnan(max_fwhm[idx])]
        if need.size:
            max_fwhm[need] = _max_fwhm(calibration, cols[need], rows[need], laser[need], cfg)
        return max_fwhm[idx]

    sub = np.linspace(0, cols.size - 1, min(cols.size, 48)).astype(np.int64)
    half0 = cfg.window_half_px
    P0 = _gather(image, cols[sub], rows[sub], half0, 1)
    wide_lim = float(np.median(max_fwhm_at(sub)))  # a wide-sheet frame needs a longer window
    sig_med = _typical_sigma(P0, cfg.saturation_dn, max(cfg.max_sigma_px, wide_lim / FWHM_PER_SIGMA))
    n_sat = np.sort((cfg.saturation_dn <= P0).sum(axis=0))
    plateau = float(n_sat[int(0.9 * (n_sat.size - 1))])
    half = int(min(max(half0, math.ceil(wide_lim) + 4), math.ceil(3.0 * sig_med + 0.5 * plateau + 4)))

    no_nb = np.full(cols.size, np.nan)
    vv, amp, sig, _sat, ok, lnoise, rise = _fit_numpy(
        image, cols, rows, half, sig_med, cfg, (no_nb, no_nb, no_nb), max_fwhm_at(np.arange(cols.size))
    )
    # stripes of two lasers that come close (long range): refit each with the other's Gaussian subtracted,
    # alternating a few times (both estimates start pulled toward each other)
    # (until no point's neighbour moves by more than refit.NEIGHBOUR_TOL: a point's fit depends on nothing
    # else that changes between the rounds)
    wide_sigma = WIDE_FWHM_PX / FWHM_PER_SIGMA  # profiles wider than this are flat-topped (wide)
    if n_l > 1:
        # the rows the fits read: background flanks (flank_px rows from off, as fit_profiles places them without a
        # clipped sample) and the whole window
        flank_offset = getattr(fit.flank_offset, "py_func", fit.flank_offset)  # not compiled
        off = flank_offset(sig_med, 0, half, _FLANK_PX)
        read = (float(off + _FLANK_PX - 1), half + 1.0, wide_sigma)
        last = np.full((3, cols.size), np.nan)  # the neighbour of each point's last refit
        tol = refit.NEIGHBOUR_TOL
        for _ in range(refit.NEIGHBOUR_REFITS):
            nb = _neighbours(laser, cols, vv, amp, sig, _sat, ok & ~_sat, n_l, w, half + 3.0 * sig_med + 2.0, read)
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
            *res, rise_i = _fit_numpy(
                image, cols[idx], rows[idx], half, sig_med, cfg, (nb[0][idx], nb[1][idx], nb[2][idx]), max_fwhm_at(idx)
            )
            for arr, new in zip((vv, amp, sig, _sat, ok, lnoise), res, strict=True):
                arr[idx] = new
            rise[:, idx] = rise_i
    # signal-to-noise per point: the local noise (flanks) where it exceeds the band's (shot noise on bright
    # backgrounds, speckle, haze)
    snr = amp / np.maximum(np.maximum(noise[col_v // w], lnoise), 0.5)
    ok, snr = _pooled_gates(col_v, chain, ok, _sat, rise, snr, cfg)
    ok &= (amp >= cfg.min_contrast_dn) & ((snr >= cfg.min_snr) | _sat)
    col_v, chain, chain_len = col_v[ok], chain[ok], chain_len[ok]
    vv, amp, sig, snr, sat = vv[ok], amp[ok], sig[ok], snr[ok], _sat[ok]
    if col_v.size == 0:
        return Detections.empty()
    # runs: columns of one laser with gaps of at most 3 columns, on one chain, or both wide (saturated or
    # flat-topped: their candidate rows wander on the top and split the chains) and within max_jump_px rows
    with np.errstate(invalid="ignore"):
        wide = sat | (sig > wide_sigma)
    joined = (chain[1:] == chain[:-1]) | (wide[1:] & wide[:-1] & (np.abs(np.diff(vv)) <= cfg.max_jump_px))
    lz = col_v // w
    new = np.ones(col_v.size, bool)
    new[1:] = (np.diff(col_v) > 3) | (lz[1:] != lz[:-1]) | ~joined
    run_id = np.cumsum(new) - 1
    keep = np.bincount(run_id)[run_id] >= max(2, cfg.min_run_cols // 2)
    col_v, vv, sig, chain_len, run_id, snr = col_v[keep], vv[keep], sig[keep], chain_len[keep], run_id[keep], snr[keep]
    # 5. along-stripe smoothing
    if scales and col_v.size:
        y = np.full(n_cols, np.nan)
        run = np.full(n_cols, -1, np.int64)
        y[col_v] = vv
        run[col_v] = run_id
        vv = _smooth(y, run, scales)[col_v]
    # 6. quality
    laser = col_v // w
    q_snr = 1.0 - np.exp(-snr / 8.0)
    sig = np.where(np.isfinite(sig), sig, cfg.max_sigma_px)
    q_w = np.clip(np.minimum(sig / 0.6, 1.5 * cfg.max_sigma_px / np.maximum(sig, 1e-6) - 0.5), 0.2, 1.0)
    q_run = np.clip(chain_len / (4.0 * cfg.min_run_cols), 0.0, 1.0)
    quality = np.clip(q_snr * q_w * (0.5 + 0.5 * q_run), 0.0, 1.0)
    uv = np.stack([(col_v - laser * w).astype(np.float64), vv], axis=1)
    return Detections(uv, laser.astype(np.int64), quality)
