"""benchmarks.diag_told_width: its noisy frames and its common fits at a forced frame statistic."""

from __future__ import annotations

import numpy as np

from benchmarks.bench_turbid import Cell
from benchmarks.diag_told_width import fit_points_at, with_noise
from benchmarks.turbid_model import render
from lrsensor.extract import frame as stages
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
    mfw = stages.max_fwhm_at(
        picked.cols, picked.rows, picked.laser, stages.FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo
    )
    own = stages.fit_points(frame.image, picked, mfw, s)
    forced = fit_points_at(frame.image, picked, mfw, s, own.sigma_px)
    assert forced.half == own.half
    ok = own.fits.ok
    assert np.array_equal(forced.fits.ok, ok)
    np.testing.assert_allclose(forced.fits.centre[ok], own.fits.centre[ok], atol=1e-9)
    np.testing.assert_allclose(forced.fits.sigma[ok], own.fits.sigma[ok], atol=1e-9)
    assert fit_points_at(frame.image, picked, mfw, s, 1.0).half < own.half
