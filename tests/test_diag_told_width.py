"""benchmarks.diag_told_width: its noisy frames and its common fits at a forced frame statistic."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_turbid import Cell
from benchmarks.diag_told_width import fit_points_at, one_sided_sigma, with_noise
from benchmarks.turbid_model import render
from lrsensor.extract import frame_locate as stages
from lrsensor.extract.geometry import max_fwhm_at
from lrsensor.extract.settings import frame_settings
from lrsensor.extract.subpixel import SubpixelConfig


def test_with_noise_adds_the_level_asked() -> None:
    """Without noise the frame is bench_turbid's noise-free frame (up to the rounding of a few pixels that lie on a
    half DN: its float32 sum and a residual shot noise of 1e-6 DN); with 4 DN the green residual's spread is 4 DN."""
    frame = render(Cell(3.0, 0.0, 0.5, 4.0, noise_free=True).turbid(0))
    quiet = with_noise(frame, 0.0, np.random.default_rng(0))
    diff = np.abs(quiet.astype(int) - frame.image)
    assert diff.max() <= 1
    assert diff.mean() < 1e-3
    noisy = with_noise(frame, 4.0, np.random.default_rng(0))
    unclipped = quiet[:, :, 1] < 200  # (the glow near the port saturates)
    resid = noisy[:, :, 1][unclipped].astype(float) - quiet[:, :, 1][unclipped]
    assert abs(float(resid.std()) - 4.0) < 0.05


def test_fit_points_at_the_frame_statistic_is_the_product_s() -> None:
    """Forced to the sigma the frame's own statistic reads, the common fits are the product's, and the half window
    follows the sigma forced (the frame statistic sets the common fit's window)."""
    frame = render(Cell(3.0, 0.0, 0.5, 4.0).turbid(1))
    bands, s, geo = frame_settings(frame.calibration, SubpixelConfig())
    picked = stages.locate_candidates(frame.image, bands, s)
    mfw = max_fwhm_at(
        picked.cols, picked.rows, picked.laser, stages.FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo
    )
    own = stages.fit_points(frame.image, picked, mfw, s)
    forced = fit_points_at(frame.image, picked, mfw, s, "frame")
    assert forced.half == own.half
    ok = own.fits.ok
    assert np.array_equal(forced.fits.ok, ok)
    np.testing.assert_allclose(forced.fits.centre[ok], own.fits.centre[ok], atol=1e-9)
    np.testing.assert_allclose(forced.fits.sigma[ok], own.fits.sigma[ok], atol=1e-9)
    assert fit_points_at(frame.image, picked, mfw, s, "1.0").half < own.half


def test_one_sided_sigma_reads_a_glowing_stripe_that_the_frame_statistic_cannot() -> None:
    """On a noise-free glow of half the peak at 3 m no profile crosses the half level on its glow's side: the frame's
    statistic falls back to 1 px; the one-sided fallback reads the stripe's half width from its inner flank (3.3 px,
    the common fit's Gaussian-equivalent, for a blurred stripe of 4.01 px with its glow's edge at the centre). On a
    stripe without glow, crossed on both sides, both read the same."""
    for glow, lo, hi in ((0.5, 3.0, 3.6), (0.0, 3.8, 4.3)):
        frame = render(Cell(3.0, 0.0, glow, 4.0, noise_free=True).turbid(0))
        bands, s, geo = frame_settings(frame.calibration, SubpixelConfig())
        picked = stages.locate_candidates(frame.image, bands, s)
        mfw = max_fwhm_at(
            picked.cols, picked.rows, picked.laser, stages.FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo
        )
        sub = np.flatnonzero(picked.second == 0)[::40]
        args = (frame.image, picked.cols[sub], picked.rows[sub], s.window_half_px, s.saturation_dn, s.max_sigma_px)
        own = stages.frame_profile_stats(*args, mfw[sub])[0]
        one = one_sided_sigma(*args, mfw[sub])
        assert lo < one < hi
        if glow:
            assert own == 1.0
        else:
            assert abs(own - one) < 1e-6
