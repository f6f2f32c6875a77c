"""What the turbid water's told width follows: the added noise, or the common fit's window (docs/water-design.md,
"Measured and left off", turbid24).

    python -m benchmarks.diag_told_width [--cell 3:0.5:4] [--noise 0,2,4,6,model] [--seeds 6] [--window frame,1,3.5]
        [--oracle none|sigma|rows|both]
    python -m benchmarks.diag_told_width --bench 3:0.5:4,3:0.3:4 --window onesided [--noise-free]

Each frame of the turbidity model (``benchmarks/turbid_model.py``) is rendered without noise, then given Gaussian noise
of ``--noise`` DN in every channel (rounded to 8 bits; ``model``: the model's own read and shot noise and particles),
and run through the default extractor's first four steps (:mod:`lrsensor.extract.frame`) with a fresh water record.
``--window``: ``frame`` runs :func:`lrsensor.extract.frame.fit_points` as the product does, ``onesided`` takes the
statistic with :func:`one_sided_sigma`'s fallback, a number forces the frame statistic's sigma
(:func:`lrsensor.extract.frame.frame_profile_stats`, which sets the common fit's half window) to it. ``--oracle``: every
point's common fit given the true width (``sigma``), the true row (``rows``) or both before the glow stage. Per noise
level and window, one value per seed: the attenuation and width the frame tells, the frame statistic's sigma and half
window, the median common-fit sigma and row error (px, positive outward, the glow's side) over columns 700-1220, and the
glow stage's median row error there. ``--bench``: ``bench_turbid.py``'s table of those cells with every frame's common
fits at the window given. A diagnostic: prints markdown."""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from lrsensor.extract import frame as stages
from lrsensor.extract import frame_locate as locate
from lrsensor.extract.fit import fit_columns
from lrsensor.extract.geometry import max_fwhm_at
from lrsensor.extract.glow import new_water
from lrsensor.extract.refit import rows_overlap
from lrsensor.extract.settings import frame_settings
from lrsensor.extract.subpixel import SubpixelConfig

from . import bench_turbid
from .bench_turbid import parse_cells
from .turbid_model import LASER_BGR, VEIL_BGR, TurbidFrame, render

#: The middle columns the medians are taken over (the stripe's middle third at 1920 px).
MID_COLS = (700, 1220)


def with_noise(frame: TurbidFrame, noise_dn: float, rng: np.random.Generator) -> NDArray[np.uint8]:
    """The noise-free layers of ``frame`` (no particles) in BGR with Gaussian noise of ``noise_dn`` in every channel,
    rounded and clipped to 8 bits: (H, W, 3) uint8."""
    lay = frame.layers
    laser = lay["stripe"] + lay["glow"] + lay["speckle"]
    ambient = lay["veil"] + lay["snow"]
    out = np.empty((*laser.shape, 3), np.uint8)
    for ch in range(3):
        sig = LASER_BGR[ch] * laser + VEIL_BGR[ch] * ambient
        out[:, :, ch] = np.clip(np.rint(sig + noise_dn * rng.standard_normal(laser.shape)), 0, 255)
    return out


def one_sided_sigma(
    image: NDArray[np.uint8],
    cols: NDArray[np.int64],
    rows: NDArray[np.int64],
    half: int,
    sat_dn: float,
    max_sigma: float,
    max_fwhm: NDArray[np.float64],
) -> float:
    """The frame statistic of :func:`lrsensor.extract.frame.frame_profile_stats` (its sigma, px) with a fallback: a
    profile whose half level is crossed on one side only (a glow of half the peak on the other) gives twice that
    side's half width from the peak's row; profiles crossed on both sides give their width as there."""
    h = image.shape[0]
    m = 2 * half + 1
    mid = m // 2
    q = max(2, m // 4)
    widths = []
    for c, r in zip(cols, rows, strict=True):
        x = image[np.clip(r - half + np.arange(m), 0, h - 1), c, 1].astype(float)
        bg = min(x[:q].sum(), x[m - q :].sum()) / q
        p = mid - 3 + int(np.argmax(x[mid - 3 : mid + 4]))
        pk = x[p]
        level = 0.5 * (pk + bg)
        if not (pk < sat_dn and pk - bg > 5.0):
            continue
        left = next((k for k in range(p - 1, -1, -1) if x[k] < level), -1)
        right = next((k for k in range(p + 1, m) if x[k] < level), m)
        xl = left + (level - x[left]) / max(x[left + 1] - x[left], 1e-9) if left >= 0 else math.nan
        xr = right - (level - x[right]) / max(x[right - 1] - x[right], 1e-9) if right < m else math.nan
        width = xr - xl if left >= 0 and right < m else 2.0 * (p - xl) if left >= 0 else 2.0 * (xr - p)
        if math.isfinite(width):
            widths.append(width)
    if not widths:
        return 1.0
    wide = float(np.median(max_fwhm)) if max_fwhm.size else 0.0
    return min(max(float(np.median(widths)) / locate.FWHM_PER_SIGMA, 0.6), max(max_sigma, wide / locate.FWHM_PER_SIGMA))


def fit_points_at(
    image: NDArray[np.uint8], p: locate.Picked, mfw: NDArray[np.float64], s: object, window: str
) -> locate.Located:
    """:func:`lrsensor.extract.frame.fit_points` with the frame statistic's sigma (which sets the common fit's window
    and start) the frame's own (``window`` ``frame``: the product's fits), :func:`one_sided_sigma`'s (``onesided``)
    or forced to ``float(window)`` px."""
    n = p.cols.size
    half0, sat_dn, max_sigma = s.window_half_px, s.saturation_dn, s.max_sigma_px  # type: ignore[attr-defined]
    pool = np.flatnonzero(p.second == 0)
    if pool.size < locate.STATS_POINTS:
        pool = np.arange(n)
    m_sub = min(pool.size, locate.STATS_POINTS)
    sub = pool[(np.arange(m_sub) * ((pool.size - 1) / max(m_sub - 1, 1))).astype(np.int64)]
    sub[-1] = pool[-1]
    own, plateau, wide_lim = locate.frame_profile_stats(
        image, p.cols[sub], p.rows[sub], half0, sat_dn, max_sigma, mfw[sub]
    )
    if window == "frame":
        sigma = own
    elif window == "onesided":
        sigma = one_sided_sigma(image, p.cols[sub], p.rows[sub], half0, sat_dn, max_sigma, mfw[sub])
    else:
        sigma = float(window)
    half = int(min(max(half0, math.ceil(wide_lim) + 4), math.ceil(3.0 * sigma + 0.5 * plateau + 4)))
    nan = np.full(n, np.nan)
    fits = fit_columns(image, p.cols, p.rows, half, sigma, s, nan, nan, nan, mfw)
    max_d = half + 3.0 * sigma + 2.0
    good = fits.ok & ~fits.saturated
    if rows_overlap(p.laser, fits.centre, good, p.noise.size, max_d):
        locate.refit_neighbours(image, p.cols, p.rows, p.laser, p.noise.size, good, max_d, half, sigma, s, mfw, fits)
    return locate.Located(
        col_v=p.col_v, laser=p.laser, cols=p.cols, rows=p.rows, chain=p.chain, chain_len=p.chain_len, fits=fits,
        max_fwhm=mfw, half=half, sigma_px=sigma, noise=p.noise,
    )  # fmt: skip


def tell(frame: TurbidFrame, image: NDArray[np.uint8], window: str, oracle: str, true_sigma: float) -> list[float]:
    """One frame: ``[alpha, width, frame sigma, half window, common sigma, common row error, glow-stage row
    error]`` (1/m, px; the row errors' medians over :data:`MID_COLS`, positive outward); ``true_sigma``: the
    blurred stripe's true width, px, which ``oracle`` ``sigma`` and ``both`` give every common fit."""
    bands, s, geo = frame_settings(frame.calibration, SubpixelConfig())
    picked = locate.locate_candidates(image, bands, s)
    mfw = max_fwhm_at(
        picked.cols, picked.rows, picked.laser, locate.FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo
    )
    p = locate.fit_points(image, picked, mfw, s) if window == "frame" else fit_points_at(image, picked, mfw, s, window)
    res = p.fits
    truth = frame.rows[p.laser, p.cols]
    out_sign = np.where(p.laser == 0, -1.0, 1.0)  # the top laser's glow lies above its stripe
    mid = (p.cols >= MID_COLS[0]) & (p.cols <= MID_COLS[1]) & res.ok
    c_sig = float(np.median(res.sigma[mid]))
    c_row = float(np.median(((res.centre - truth) * out_sign)[mid]))
    if oracle in ("sigma", "both"):
        res.sigma[:] = true_sigma
    if oracle in ("rows", "both"):
        res.centre[:] = np.where(np.isfinite(truth), truth, res.centre)
    water = new_water()
    v_g, _s, own, *_ = stages.refine_points(image, p, bands.glow_side, s, geo, water)
    g_row = float(np.median(((v_g - truth) * out_sign)[mid & own])) if (mid & own).any() else math.nan
    return [float(water[0]), float(water[1]), p.sigma_px, float(p.half), c_sig, c_row, g_row]


def bench_at(window: str, bench_args: Sequence[str]) -> int:
    """``benchmarks/bench_turbid.py`` with ``bench_args`` (``--cells ...``), every frame's common fits at ``window``
    (:func:`fit_points_at`; the product's own function replaced for the run: a diagnostic's what-if)."""
    product = locate.fit_points

    def fits_at(image: NDArray[np.uint8], p: locate.Picked, mfw: NDArray[np.float64], s: object) -> locate.Located:
        return product(image, p, mfw, s) if p.cols.size < 2 else fit_points_at(image, p, mfw, s, window)

    locate.fit_points = fits_at  # (extract_frame calls it through the module)
    try:
        return bench_turbid.main(bench_args)
    finally:
        locate.fit_points = product


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cell", default="3:0.5:4", help="range_m:glow_step:blur_px (bench_turbid's --cells form)")
    ap.add_argument("--noise", default="0,2,4,6,model", help="added Gaussian noise, DN, or 'model'")
    ap.add_argument("--seeds", type=int, default=6)
    ap.add_argument(
        "--window", default="frame", help="'frame', 'onesided' or the frame statistic's sigma, px; comma-separated"
    )
    ap.add_argument("--oracle", default="none", choices=("none", "sigma", "rows", "both"))
    ap.add_argument(
        "--bench",
        metavar="CELLS",
        help="instead: bench_turbid.py --cells CELLS with the common fits at the one --window given",
    )
    ap.add_argument("--noise-free", action="store_true", help="with --bench: bench_turbid's --noise-free")
    args = ap.parse_args(argv)
    if args.bench is not None:
        print(f"common fits at the frame statistic {args.window}")
        return bench_at(args.window, ["--cells", args.bench] + (["--noise-free"] if args.noise_free else []))
    (cell,) = parse_cells(args.cell)
    print(f"`python -m benchmarks.diag_told_width --cell {args.cell} --seeds {args.seeds} --oracle {args.oracle}`\n")
    print(
        "| window | noise, DN | alpha, 1/m | told width, px | frame sigma, px | half | common sigma, px "
        "| common row, px out | glow stage's row, px out |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for window in args.window.split(","):
        for level in args.noise.split(","):
            rows = []
            for seed in range(args.seeds):
                model = level == "model"
                t = replace(cell, noise_free=not model).turbid(seed)
                frame = render(t)
                image = frame.image if model else with_noise(frame, float(level), np.random.default_rng(100 + seed))
                fy = frame.calibration.camera.fy
                true_sigma = math.hypot(t.sheet_sigma_m * fy / t.distance_m, t.blur_px)  # (a perpendicular wall)
                rows.append(tell(frame, image, window, args.oracle, true_sigma))
            r = np.array(rows)
            cols = [" ".join(f"{x:.2f}" if j != 3 else f"{x:.0f}" for x in r[:, j]) for j in range(7)]
            print(f"| {window} | {level} | " + " | ".join(cols) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
