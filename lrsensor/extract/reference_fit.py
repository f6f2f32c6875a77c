"""The reference's sub-pixel fit (numpy): step 3 of :func:`lrsensor.extract.reference.extract_frame`, what
:func:`lrsensor.extract.fit.fit_columns` computes for every picked column.

- :func:`_gather`: the profiles, (2 half + 1, N) samples of one channel around each point's row;
- :func:`_typical_sigma`: the frame's typical Gaussian-equivalent width, which sets the fit window;
- :func:`_max_fwhm`: the widest stripe the laser sheet allows at each point (triangulated on its plane);
- :func:`_fit`: the profile fits (:func:`lrsensor.extract.centre.fit_profiles`), optionally with a neighbouring
  stripe's Gaussian subtracted (the refits of step 4), and each point's rise in the three colour channels.

Rows, widths and sigmas in pixels, amplitudes in DN. The names keep the underscore they had in
:mod:`lrsensor.extract.reference`, which still exports them (tests compare :func:`_fit` with the compiled fit).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..triangulation import triangulate as _triangulate
from .centre import FWHM_PER_SIGMA, fit_profiles
from .settings import Geometry, Settings

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Rows per background flank of the sub-pixel fit (as the compiled kernels take them).
_FLANK_PX = 3


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
