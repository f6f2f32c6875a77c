"""Stripe extraction: the centre estimator, the laser bands, both extractors on synthetic and simulated images."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from lrsensor import Sensor
from lrsensor.calibration import Calibration
from lrsensor.errors import ExtractionError
from lrsensor.extract.bands import laser_bands
from lrsensor.extract.centre import fit_profiles
from lrsensor.extract.reference_finish import smooth
from lrsensor.extract.subpixel import SubpixelConfig
from lrsensor.extract.subpixel import extract as subpixel_extract

# ----------------------------------------------------------------------------- synthetic profiles


def _profiles(
    centres: np.ndarray,
    sigma: float,
    amp: float,
    m: int,
    *,
    bg: float = 30.0,
    slope: float = 0.0,
    noise: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """(N, m) 8-bit profiles: Gaussian ridge on a linear background, optional noise, clipped and rounded."""
    x = np.arange(m)
    p = bg + slope * (x - m // 2) + amp * np.exp(-0.5 * ((x[None, :] - centres[:, None]) / sigma) ** 2)
    if noise:
        p = p + noise * np.random.default_rng(seed).standard_normal(p.shape)
    return np.clip(np.round(p), 0, 255)


@pytest.mark.parametrize("sigma", [0.8, 1.0, 1.5, 2.5, 4.0])
def test_centre_unbiased_over_subpixel_phase(sigma: float) -> None:
    m = 2 * math.ceil(3 * sigma + 7) + 1
    phases = np.linspace(-0.5, 0.5, 41)
    c = m // 2 + phases
    fit = fit_profiles(_profiles(c, sigma, 150.0, m, slope=0.4), sigma_hint=sigma)
    assert fit.ok.all()
    err = fit.centre - c
    # only 8-bit rounding is left: a few thousandths of a pixel
    assert np.max(np.abs(err)) < 0.012, np.max(np.abs(err))
    assert np.allclose(fit.sigma, sigma, rtol=0.05)


def test_centre_noise_close_to_cramer_rao_and_unbiased() -> None:
    rng = np.random.default_rng(3)
    sigma, amp, noise = 1.0, 100.0, 3.0
    c = 13 + rng.uniform(-0.5, 0.5, 4000)
    fit = fit_profiles(_profiles(c, sigma, amp, 27, noise=noise, seed=4), sigma_hint=sigma)
    err = (fit.centre - c)[fit.ok]
    crlb = math.sqrt(2 * sigma * noise**2 / (math.sqrt(math.pi) * amp**2))
    assert abs(err.mean()) < 0.003
    assert err.std() < 1.3 * crlb


@pytest.mark.parametrize("sigma", [0.8, 1.2, 2.5])
@pytest.mark.parametrize("overexposure", [2.0, 6.0])
def test_centre_of_saturated_flat_top(sigma: float, overexposure: float) -> None:
    m = 2 * math.ceil(3 * sigma + 12) + 1
    phases = np.linspace(-0.5, 0.5, 21)
    c = m // 2 + phases
    P = _profiles(c, sigma, 255.0 * overexposure, m)
    # the window handed to the fit is centred on the middle of the clipped run, as the extractor does
    sat = P >= 250
    first = np.argmax(sat, axis=1)
    last = m - 1 - np.argmax(sat[:, ::-1], axis=1)
    shift = (first + last) // 2 - m // 2
    idx = np.clip(np.arange(m)[None, :] + shift[:, None], 0, m - 1)
    Pc = np.take_along_axis(P, idx, axis=1)
    fit = fit_profiles(Pc, sigma_hint=sigma)
    assert fit.saturated.all()
    assert fit.ok.all()
    err = fit.centre + shift - c
    assert np.max(np.abs(err)) < 0.08
    assert abs(err.mean()) < 0.02


def test_centre_rejects_too_wide_and_too_narrow() -> None:
    c = np.full(4, 20.0)
    wide = fit_profiles(_profiles(c, 9.0, 120.0, 61), sigma_hint=4.0, max_sigma_px=4.0)
    assert not wide.ok.any()  # a haze / glow ridge is not a stripe
    hot = np.full((1, 41), 30.0)
    hot[0, 20] = 200.0  # a single hot pixel / speckle grain
    narrow = fit_profiles(hot, sigma_hint=1.0, min_sigma_px=0.45)
    assert not narrow.ok.any()


# ----------------------------------------------------------------------------- smoothing


def test_smoothing_keeps_corners_and_reduces_noise() -> None:
    rng = np.random.default_rng(5)
    n = 600
    u = np.arange(n, dtype=float)
    truth = np.where(u < 300, 100 + 0.05 * u, 115 - 0.08 * (u - 300))  # a corner (kink) at u = 300
    y = truth + 0.1 * rng.standard_normal(n)
    run = np.zeros(n, np.int64)
    out = smooth(y, run, (48, 12, 3))
    err_raw = np.abs(y - truth)
    err = np.abs(out - truth)
    assert np.median(err) < 0.4 * np.median(err_raw)
    # near the corner the one-sided windows keep the error small
    near = np.abs(u - 300) <= 6
    assert np.max(err[near]) < 0.3
    assert np.median(err[near]) < 0.06


def test_compiled_smoothing_equals_the_reference() -> None:
    """``smooth_runs`` (which fits only the windows the remaining columns can use and stops when all are done)
    gives the same values as the reference's ``smooth`` on runs with gaps, corners, steps and columns without a
    measurement."""
    from lrsensor.extract.smooth import smooth_runs

    rng = np.random.default_rng(11)
    for trial in range(20):
        n = int(rng.integers(60, 1500))
        u = np.arange(n, dtype=float)
        kink = rng.uniform(0.2, 0.8) * n
        y = 200.0 + 0.03 * u + np.where(u > kink, rng.uniform(-0.2, 0.2) * (u - kink), 0.0)
        y += rng.uniform(0.02, 0.5) * rng.standard_normal(n)
        run = np.cumsum(rng.random(n) < 3.0 / n).astype(np.int64)  # a few runs (intervals), ids increasing
        y[run % 2 == 1] += 15.0  # depth steps between runs
        gaps = rng.random(n) < 0.05 * (trial % 3)
        run[gaps] = -1
        y[gaps] = np.nan
        scales = (384, 96, 24, 6) if trial % 2 else (48, 12, 3)
        want = smooth(y, run, scales)
        got = smooth_runs(y, run, np.array(scales, np.int64))
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9, equal_nan=True)
        assert np.any(got[run >= 0] != y[run >= 0])  # it did smooth


def test_smoothing_in_given_coordinates() -> None:
    """``smooth_runs_at`` fits lines in the columns' coordinates ``x`` (a port's central view): a line in ``x``
    that is curved in the index is kept exactly, and the compiled kernel equals the reference's ``smooth``."""
    from lrsensor.extract.smooth import smooth_runs, smooth_runs_at

    rng = np.random.default_rng(12)
    n = 1200
    u = np.arange(n, dtype=float)
    x = u + 4e-5 * (u - 600.0) ** 3 / 60.0  # increasing, curved against the index
    truth = 300.0 + 0.2 * x
    run = np.zeros(n, np.int64)
    scales = (384, 96, 24, 6)
    exact = smooth_runs_at(truth, x, run, np.array(scales, np.int64))
    np.testing.assert_allclose(exact, truth, atol=1e-9)
    y = truth + 0.1 * rng.standard_normal(n)
    got = smooth_runs_at(y, x, run, np.array(scales, np.int64))
    np.testing.assert_allclose(got, smooth(y, run, scales, x), rtol=0, atol=1e-9)
    assert np.median(np.abs(got - truth)) < 0.4 * np.median(np.abs(y - truth))
    # in the index the same stripe is curved: the index's line fits are biased where x bends
    index_fit = smooth_runs(y, run, np.array(scales, np.int64))
    assert np.median(np.abs(index_fit - truth)) > np.median(np.abs(got - truth))
    # the index as coordinates is smooth_runs itself
    np.testing.assert_array_equal(smooth_runs_at(y, u, run, np.array(scales, np.int64)), index_fit)


def test_sorted_blocks_equal_integer_division() -> None:
    """``sorted_blocks`` (the laser of each sorted virtual column, shared by the chains, the half-column expansion,
    the fits and the gates) equals ``col // width``, also across empty blocks and for no columns."""
    from lrsensor.extract.chains import sorted_blocks

    rng = np.random.default_rng(2)
    for width in (1, 7, 960):
        col = np.sort(rng.choice(5 * width, size=min(3 * width, 500), replace=False)).astype(np.int64)
        col = col[(col < width) | (col >= 3 * width)]  # blocks 1 and 2 empty
        np.testing.assert_array_equal(sorted_blocks(col, width), col // width)
    assert sorted_blocks(np.empty(0, np.int64), 4).size == 0


@pytest.mark.parametrize("n", [2, 5, 8, 9, 10])
def test_pooled_median_sorting_network_sorts_every_input(n: int) -> None:
    """The compare-exchange network of the pooled signal-to-noise median sorts all 2^n 0-1 inputs (0-1
    principle: then it sorts any input); n = 9 is the 25-exchange network of the default pool."""
    from lrsensor.extract.finish import sorting_network

    net = sorting_network(n)
    if n == 9:
        assert net.shape == (25, 2)
    bits = (np.arange(2**n)[:, None] >> np.arange(n)[None, :]) & 1
    a = bits.T.copy()  # (n, 2^n): one input per column, as the kernel lays them out
    for i, j in net:
        lo = np.minimum(a[i], a[j])
        a[j] = np.maximum(a[i], a[j])
        a[i] = lo
    np.testing.assert_array_equal(a.T, np.sort(bits, axis=1))


def test_pooled_median_is_the_median_of_each_window() -> None:
    """The pooled medians (9-column windows, one pass over all columns per compare-exchange) are the median of
    each window of its own piece's passing values: windows with holes (NaN), piece changes, even and odd counts
    and columns without any value."""
    from lrsensor.extract.finish import pooled_median

    rng = np.random.default_rng(5)
    nd = 700
    ch = np.repeat(np.arange(nd // 25 + 1, dtype=np.int32), 25)[: nd + 8].copy()
    ch[rng.random(nd + 8) < 0.1] = -1
    ds = (rng.random(nd + 8) * 20).astype(np.float32)
    ds[rng.random(nd + 8) < 0.3] = np.nan
    own = ch[4 : 4 + nd]
    fast = pooled_median(ch, ds, own, 9, nd)
    for q in range(nd):
        win = ds[q : q + 9][(ch[q : q + 9] == own[q]) & np.isfinite(ds[q : q + 9])]
        if win.size:
            assert fast[q] == pytest.approx(float(np.median(win.astype(np.float64))), rel=1e-6)
        else:
            assert fast[q] == np.inf


# ----------------------------------------------------------------------------- bands


def test_bands_of_the_paper_sensor_match_eq_33() -> None:
    cal = Calibration.paper(0.1)
    b = laser_bands(cal, 0.25, 4.0, 0)
    f, cy = cal.camera.fy, cal.camera.cy
    # top laser: v from cy - f c / z_min to cy - f c / z_max (eq. 33 with y_c = f c / x_b)
    assert b.v_min[0, 960] == pytest.approx(cy - f * 0.05 / 0.25, abs=0.05)
    assert b.v_max[0, 960] == pytest.approx(cy - f * 0.05 / 4.0, abs=0.05)
    assert b.v_min[1, 960] == pytest.approx(cy + f * 0.05 / 4.0, abs=0.05)
    assert b.v_max[1, 960] == pytest.approx(cy + f * 0.05 / 0.25, abs=0.05)
    assert b.valid(0).all()
    assert b.valid(1).all()


def test_bands_of_tilted_lasers_contain_their_stripes() -> None:
    from lrsensor.sim import tilted_calibration, wall_scene

    cal = tilted_calibration(Calibration.paper(0.1))
    b = laser_bands(cal, 0.3, 3.0, 0)
    nominal = laser_bands(Calibration.paper(0.1), 0.3, 3.0, 0)
    assert not np.allclose(b.v_min, nominal.v_min, atol=2.0)  # the tilt moves the band
    for d in (0.3, 1.0, 3.0):
        truth = wall_scene(d, calibration=cal).render(seed=0).truth
        for lt in truth.lasers:
            assert b.contains(lt.index, lt.uv, slack_px=0.05).all()
            other = 1 - lt.index
            assert not b.contains(other, lt.uv).any()
    with pytest.raises(ExtractionError, match="range limits"):
        laser_bands(cal, 2.0, 1.0, 0)


# ----------------------------------------------------------------------------- synthetic images


def _small_calibration() -> Calibration:
    cal = Calibration.paper(0.1)
    cam = replace(cal.camera, width=640, height=360, fx=184.76, fy=184.76, cx=319.5, cy=179.5)
    return replace(cal, camera=cam)


def _stripe_image(
    cal: Calibration, depth_m: float, sigma: float, amp: float, seed: int = 0
) -> tuple[np.ndarray, float]:
    """A flat wall at ``depth_m``: both stripes as Gaussian ridges (green), on a noisy murky background."""
    cam = cal.camera
    rng = np.random.default_rng(seed)
    img = np.empty((cam.height, cam.width, 3), np.float64)
    img[:] = (38.0, 34.0, 12.0)
    rows = np.arange(cam.height)[:, None]
    v_top = cam.cy - cam.fy * 0.05 / depth_m
    for v0 in (v_top, 2 * cam.cy - v_top):
        ridge = amp * np.exp(-0.5 * ((rows - v0) / sigma) ** 2)
        img[:, :, 1] += ridge
        img[:, :, 0] += 0.3 * ridge
    img += rng.normal(0.0, 2.0, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), float(v_top)


def test_subpixel_on_synthetic_walls() -> None:
    cal = _small_calibration()
    for depth, sigma in ((0.4, 1.0), (1.0, 2.0), (2.0, 0.9)):
        img, v_top = _stripe_image(cal, depth, sigma, 120.0)
        det = subpixel_extract(img, cal)
        top = det.laser == 0
        assert top.sum() >= 0.98 * cal.camera.width
        assert (~top).sum() >= 0.98 * cal.camera.width
        assert np.median(np.abs(det.uv[top, 1] - v_top)) < 0.02
        assert np.all((det.quality >= 0) & (det.quality <= 1))
        scan = Sensor(cal).process(img)
        x = scan.points[:, 0]
        assert np.median(np.abs(x - depth) / depth) < 0.002


def test_subpixel_prefers_the_continuous_stripe_over_a_brighter_distractor() -> None:
    cal = _small_calibration()
    img, v_top = _stripe_image(cal, 1.0, 1.2, 80.0, seed=1)
    f = img.astype(np.float64)
    # a bright, stripe-like green streak 14 px above the stripe over 40 columns, and a round green blob
    rows = np.arange(cal.camera.height)[:, None]
    cols = np.arange(cal.camera.width)[None, :]
    streak = 170.0 * np.exp(-0.5 * ((rows - (v_top - 14)) / 1.2) ** 2) * ((cols > 300) & (cols < 340))
    blob = 150.0 * np.exp(-0.5 * (((rows - v_top) / 9.0) ** 2 + ((cols - 500) / 9.0) ** 2))
    f[:, :, 1] += streak + blob
    f[:, :, 0] += 0.4 * (streak + blob)
    img = np.clip(np.round(f), 0, 255).astype(np.uint8)
    det = subpixel_extract(img, cal)
    top = det.laser == 0
    dv = np.abs(det.uv[top, 1] - v_top)
    u = det.uv[top, 0]
    in_streak = (u > 300) & (u < 340)
    assert in_streak.sum() >= 35  # the stripe is still found under the streak
    assert np.max(dv[in_streak]) < 0.3
    assert np.percentile(dv, 99) < 0.3  # nothing follows the blob or the streak


def test_subpixel_ignores_a_glow_ramp_and_white_objects() -> None:
    cal = _small_calibration()
    img, v_top = _stripe_image(cal, 1.0, 1.0, 60.0, seed=2)
    f = img.astype(np.float64)
    rows = np.arange(cal.camera.height)[:, None]
    # backscatter glow: a broad ramp beside the stripe, toward the near range
    glow = 50.0 * np.exp(-0.5 * ((rows - (v_top - 30)) / 18.0) ** 2)
    f[:, :, 1] += glow
    f[:, :, 0] += 0.3 * glow
    # a bright white (not green) thin object across the bottom laser's band
    f[cal.camera.height - 120 : cal.camera.height - 117, :, :] += 120.0
    img = np.clip(np.round(f), 0, 255).astype(np.uint8)
    det = subpixel_extract(img, cal)
    top = det.laser == 0
    assert top.sum() > 0.95 * cal.camera.width
    assert np.median(np.abs(det.uv[top, 1] - v_top)) < 0.05
    bottom_v = det.uv[~top, 1]
    assert not np.any(np.abs(bottom_v - (cal.camera.height - 119)) < 3)


def test_pooled_gates_keep_a_dim_stripe() -> None:
    cal = _small_calibration()
    img, v_top = _stripe_image(cal, 1.0, 1.0, 9.0, seed=5)  # peak 4.5x the pixel noise, blue leaking 30 %
    pooled = subpixel_extract(img, cal)
    single = subpixel_extract(img, cal, gate_pool_cols=0)
    width = cal.camera.width
    assert (pooled.laser == 0).sum() > 0.95 * width
    assert (pooled.laser == 0).sum() > (single.laser == 0).sum() + 0.05 * width  # one noisy pixel decided before
    top = pooled.uv[pooled.laser == 0, 1]
    assert np.median(np.abs(top - v_top)) < 0.1
    with pytest.raises(ExtractionError, match="gate_pool_cols"):
        SubpixelConfig(gate_pool_cols=-1)


def test_options_are_validated() -> None:
    cal = _small_calibration()
    img, _ = _stripe_image(cal, 1.0, 1.0, 100.0)
    with pytest.raises(ExtractionError, match="unknown subpixel extractor option"):
        Sensor(cal).process(img, min_range=0.3)
    with pytest.raises(ExtractionError, match="min_range_m"):
        SubpixelConfig(min_range_m=1.0, max_range_m=0.5)
    with pytest.raises(ExtractionError, match="unknown extraction method"):
        Sensor(cal).process(img, method="nope")
    # a narrower search band still finds the stripe at 1 m
    scan = Sensor(cal).process(img, min_range_m=0.5, max_range_m=2.0)
    assert len(scan) > 0.98 * 2 * cal.camera.width


def test_paper_method_one_point_per_roi_and_laser() -> None:
    cal = _small_calibration()
    img, _v_top = _stripe_image(cal, 0.8, 1.5, 150.0)
    sensor = Sensor(cal)
    scan = sensor.process(img, method="paper", n_rois=16)
    assert scan.method == "paper"
    assert 24 <= len(scan) <= 32
    assert set(np.unique(scan.laser)) == {0, 1}
    # ROI centres are the midpoints of 40-px strips
    assert np.allclose(np.sort(np.unique(scan.uv[:, 0])), 40 * np.arange(16) + 19.5)
    err = np.abs(scan.points[:, 0] - 0.8) / 0.8
    assert np.median(err) < 0.03


def test_compiled_noise_read_in_place_equals_the_reference() -> None:
    """``noise_dn_rows`` (the green rows read in place from the BGR image) gives the reference's ``_noise_dn`` of
    a copy of the green band exactly, for several widths and row steps."""
    from lrsensor.extract.compile import HAVE_NUMBA
    from lrsensor.extract.detect import noise_dn_rows
    from lrsensor.extract.reference import _noise_dn

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(11)
    for w in (640, 642, 1920):  # (detect_band evens odd widths, as the reference pads them)
        img = np.clip(rng.normal(60.0, 7.0, (90, w, 3)), 0, 255).astype(np.uint8)
        g = np.ascontiguousarray(img[:, :, 1])
        for step in (2, 5, 16):
            assert noise_dn_rows(img.reshape(-1), w, np.arange(90), step) == _noise_dn(g, step)
    assert 6.0 < _noise_dn(g, 2) < 8.0  # about the noise drawn


def _profiles_image() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A test image of one stripe profile per column (120 x 400): Gaussians of sigma 0.8-3 px and peaks from 120 DN
    to 6 times the range (clipped runs) on a sloped background, a tenth of them flat tops 9 px wide (thick
    sheets), ten columns with a single clipped sample, the first ten windows cut by the top border.

    Returns ``(image, cols, rows, true_rows, sigma, flat)``: the candidate rows within 2 rows of the true ones."""
    rng = np.random.default_rng(3)
    h, w = 120, 400
    rows_c = rng.uniform(4.0, h - 5.0, w)
    rows_c[:10] = np.linspace(0.5, 3.0, 10)  # windows beyond the top
    sigma = rng.uniform(0.8, 3.0, w)
    amp = rng.choice([120.0, 230.0, 255.0 * 1.5, 255.0 * 6.0], w)
    y = np.arange(h)[:, None]
    green = 20.0 + 0.05 * y + amp * np.exp(-0.5 * ((y - rows_c) / sigma) ** 2)
    flat = rng.random(w) < 0.1  # thick sheets: flat tops 9 px wide, unclipped
    green[:, flat] = 20.0 + 150.0 * (np.abs(y - rows_c[flat]) <= 4.5)
    green += rng.normal(0.0, 1.5, green.shape)
    img = np.zeros((h, w, 3), np.uint8)
    img[:, :, 1] = np.clip(np.round(green), 0, 255)
    img[:, :, 0] = np.clip(np.round(0.3 * green), 0, 255)
    img[:, :, 2] = np.clip(np.round(0.2 * green), 0, 255)
    img[40, 200:210, 1] = 255  # single clipped samples
    cols = np.arange(w, dtype=np.int64)
    rows = np.rint(rows_c).astype(np.int64) + rng.integers(-2, 3, w)
    return img, cols, rows, rows_c, sigma, flat


def _fit_settings(iterations: int) -> Any:
    """The settings records of the fit tests: saturation 250 DN, sigma 0.3-5 px, wide above 4.7 px."""
    from lrsensor.extract.settings import frame_settings

    s = frame_settings(Calibration.paper(0.1, 64, 48), SubpixelConfig())[1]
    return s._replace(
        saturation_dn=250.0, min_fwhm_px=0.3 * 2.3548200450309493, max_sigma_px=5.0, wide_fwhm_px=4.7,
        iterations=iterations,
    )  # fmt: skip


def _assert_fit_matches_reference(
    fast: Any, ref: tuple[np.ndarray, ...], kinds: dict[str, np.ndarray], inside: np.ndarray
) -> None:
    """The compiled fit (float64) against the reference's (float32): the same acceptance and saturation for all
    but a few columns (a float32 width at a limit), colour rises equal, amplitudes and noise to float32
    rounding; centres within 2e-4 px of each other in the median of every kind of profile, and within 0.02 px
    for every column whose window lies ``inside`` the image (a clipped top's window centroid moves by its steps'
    float32 rounding; where a window is cut by the border, the reference's Gaussian weights reach the repeated
    border rows beyond the compiled fit's reach). Two kinds agree less (both roads read them as they did before
    the fits became one): a single clipped sample (a log-parabola start off the Gaussian's: a few columns end
    up tenths of a pixel apart) and flat tops (the plateau's window centroid: most within 0.02 px, all within a
    row)."""
    centre, amp, sigma, sat, ok, noise, rise = ref
    np.testing.assert_array_equal(fast.saturated, sat)
    np.testing.assert_array_equal(fast.rise, rise)
    assert (fast.ok != ok).mean() < 0.01
    both = fast.ok & ok
    d = np.abs(fast.centre - centre)
    for kind, sel in kinds.items():
        assert (sel & both).sum() >= 5, kind
        if kind == "flat tops":
            assert np.mean(d[sel & both] < 0.02) > 0.5
            assert np.max(d[sel & both]) < 1.01
            continue
        assert np.median(d[sel & both]) < 2e-4, kind
        if kind != "one clipped sample":
            assert np.max(d[sel & both & inside], initial=0.0) < 0.02, kind
    np.testing.assert_allclose(fast.amplitude[both], amp[both], rtol=1e-4, atol=1e-2)
    np.testing.assert_allclose(fast.local_noise, noise, rtol=1e-3, atol=1e-3)
    fin = both & np.isfinite(sigma)
    np.testing.assert_allclose(fast.sigma[fin], sigma[fin], rtol=1e-3)


def test_kernels_take_order_statistics_as_numpy_does() -> None:
    """The kernels' ``k``-th smallest value is ``np.sort(a)[k]`` and their median (a selection) is numba's
    ``np.median`` (on values without NaN, numpy's) to the bit: the middle of the sorted order (NaN last), ties,
    reversed and sorted inputs, NaN among the values included."""
    from lrsensor.extract.sorting import kth, median

    def middle(a: np.ndarray) -> float:
        srt = np.sort(a)  # NaN last
        h = a.size // 2
        return float(srt[h] if a.size % 2 else (srt[h - 1] + srt[h]) / 2)

    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 7, 48, 1000, 5001):
        a = rng.normal(size=n).round(1)
        for k in {0, n // 3, int(0.9 * (n - 1)), n - 1}:
            assert kth(a, k) == np.sort(a)[k]
        assert median(a) == np.median(a)
        for b in (np.sort(a), np.sort(a)[::-1].copy(), a.round(0)):
            assert median(b) == np.median(b)
        for share in (0.2, 0.5, 0.8):
            b = a.copy()
            b[rng.random(n) < share] = np.nan
            np.testing.assert_equal(median(b), middle(b))


def test_fit_equals_the_reference_for_every_kind_of_profile() -> None:
    """``fit.fit_columns`` (one column-parallel fit, float64) gives the reference's fit (``reference._fit``,
    float32): unclipped narrow profiles, single clipped samples, saturated profiles (flat tops of several widths
    and sub-pixel phases on a sloped background), flat-topped wide ones (thick sheets), windows cut by the image
    border; clipped Gaussians whose top the window holds are read within a few hundredths of a pixel."""
    from lrsensor.extract import reference
    from lrsensor.extract.compile import HAVE_NUMBA
    from lrsensor.extract.fit import fit_columns

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    img, cols, rows, rows_c, _sigma, flat = _profiles_image()
    h, w = img.shape[:2]
    nan = np.full(w, np.nan)
    max_fwhm = nan * 0 + 20.0
    for half, it in ((8, 2), (12, 3), (90, 2), (130, 2)):
        s = _fit_settings(it)
        fast = fit_columns(img, cols, rows, half, 1.2, s, nan, nan, nan, max_fwhm)
        ref = reference._fit(img, cols, rows, half, 1.2, s, (nan, nan, nan), max_fwhm)
        win = np.clip(rows[None, :] + np.arange(-half, half + 1)[:, None], 0, h - 1)
        n_clip = (img[win, cols[None, :], 1] >= 250).sum(axis=0)
        kinds = {"unclipped": (n_clip == 0) & ~flat, "saturated": fast.saturated}
        if half < 90:  # (a long window holds more than one clipped sample)
            kinds["one clipped sample"] = n_clip == 1
            kinds["flat tops"] = flat
        _assert_fit_matches_reference(fast, ref, kinds, (rows - half - 3 >= 0) & (rows + half + 3 < h))
        if half == 12:  # clipped Gaussians (whose top the window holds): from the middle of the clipped run to
            # the true centre
            inside = fast.saturated & (rows_c > half + 3)
            err = np.abs(fast.centre[inside] - rows_c[inside])
            assert np.isfinite(err).all()
            assert np.median(err) < 0.05
            assert np.percentile(err, 95) < 0.15


def test_fit_with_a_neighbour_equals_the_reference() -> None:
    """With another laser's stripe close by (either side, near and far; a tenth of the columns not told of it),
    ``fit.fit_columns`` subtracts its Gaussian as the reference does, and the subtraction matters: without it the
    centres move."""
    from lrsensor.extract import reference
    from lrsensor.extract.compile import HAVE_NUMBA
    from lrsensor.extract.fit import fit_columns

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    img, cols, rows, rows_c, _sigma, flat = _profiles_image()
    w = cols.size
    rng = np.random.default_rng(5)
    # a second stripe 4-14 rows away, of 10-60 DN and sigma 0.6-2.5 px, drawn into the image; a tenth without
    side = rng.choice([-1.0, 1.0], w)
    nb_v = rows_c + side * rng.uniform(4.0, 14.0, w)
    nb_a = rng.uniform(10.0, 60.0, w)
    nb_s = rng.uniform(0.6, 2.5, w)
    y = np.arange(img.shape[0])[:, None]
    g = img[:, :, 1].astype(float) + nb_a * np.exp(-0.5 * ((y - nb_v) / nb_s) ** 2)
    img[:, :, 1] = np.clip(np.round(g), 0, 255)
    none = rng.random(w) < 0.1
    nb_v[none] = np.nan
    max_fwhm = np.full(w, 20.0)
    for half, it in ((7, 2), (12, 3)):
        s = _fit_settings(it)
        fast = fit_columns(img, cols, rows, half, 1.2, s, nb_v, nb_a, nb_s, max_fwhm)
        ref = reference._fit(img, cols, rows, half, 1.2, s, (nb_v, nb_a, nb_s), max_fwhm)
        win = np.clip(rows[None, :] + np.arange(-half, half + 1)[:, None], 0, img.shape[0] - 1)
        unclipped = (img[win, cols[None, :], 1] < 250).all(axis=0)
        kinds = {"with a neighbour": ~none & ~flat & unclipped}
        h = img.shape[0]
        _assert_fit_matches_reference(fast, ref, kinds, (rows - half - 3 >= 0) & (rows + half + 3 < h))
        nan = np.full(w, np.nan)
        plain = fit_columns(img, cols, rows, half, 1.2, s, nan, nan, nan, max_fwhm)
        both = ~none & np.isfinite(plain.centre) & np.isfinite(fast.centre)
        assert np.max(np.abs(plain.centre[both] - fast.centre[both])) > 0.1


def test_neighbour_refits_only_where_the_neighbour_moved() -> None:
    """``refit_targets`` picks the points with a neighbour that is new or moved by more than the tolerance (row,
    sigma in px, amplitude relative) and remembers it; a second call with the same neighbours picks none; only
    the ``touched`` columns are looked at."""
    from lrsensor.extract.compile import HAVE_NUMBA
    from lrsensor.extract.refit import NEIGHBOUR_TOL, point_table, refit_targets

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    w = 5
    laser = np.repeat([0, 1], w)
    cols = np.tile(np.arange(w), 2)
    v = np.array([100.0] * w + [103.0, 103.0, 103.0, 103.0, 200.0])  # column 4: the stripes far apart
    amp = np.full(2 * w, 50.0)
    sig = np.ones(2 * w)
    sat = np.zeros(2 * w, bool)
    good = np.ones(2 * w, bool)
    last = np.full((3, 2 * w), np.nan)
    every = np.ones(w, bool)

    at = point_table(laser, cols, 2, w)

    def pick(touched: np.ndarray = every) -> list[int]:
        look = np.flatnonzero(touched)
        idx, nb_v, _, _ = refit_targets(laser, cols, v, amp, sig, sat, good, at, 9.0, (6.0, 8.0, 2.0), look, last)
        np.testing.assert_array_equal(nb_v, v[(idx + w) % (2 * w)])  # the other laser, same column
        return idx.tolist()

    assert pick() == [0, 1, 2, 3, 5, 6, 7, 8]
    assert pick() == []
    v[6] += 0.5 * NEIGHBOUR_TOL  # within the tolerance
    v[7] += 3.0 * NEIGHBOUR_TOL  # point 2 sees it move, point 7 sees its neighbour (2) unchanged
    amp[8] *= 1.0 + 3.0 * NEIGHBOUR_TOL  # relative
    assert pick(np.array([True, True, True, False, True])) == [2]  # column 3 not looked at
    assert pick() == [3]
    sig[5] += 1.0
    assert pick() == [0]


@pytest.mark.parametrize(
    ("own_sig", "own_sat", "near", "picked"),
    [
        (1.0, False, 5.0, False),  # reads 6 rows (flanks to 5, a row of re-centring): tail e^-5.6 at 5 rows out
        (1.0, True, 5.0, True),  # saturated: the whole window (8 rows), tail e^-2
        (2.5, False, 5.0, True),  # wide: the whole window
        (1.9, False, 5.0, True),  # its centroid weights reach 6 rows (3 sigma), 7 with re-centring: tail e^-3.6
        (1.0, False, 6.0, False),  # flanks to 6 rows, 7 read: tail e^-3.6 = 2.8 %, below the flanks' 5 %
        (1.0, False, 7.0, True),  # flanks to 7 rows, 8 read: tail e^-2 = 13.5 %
    ],
)
def test_far_neighbours_are_not_subtracted(own_sig: float, own_sat: bool, near: float, picked: bool) -> None:
    """A neighbour within the distance is subtracted only if its Gaussian reaches ``NEIGHBOUR_TAIL`` of the
    point's amplitude in the rows the point's centroid reads (``read_reach``: 3 sigma of its weights, the whole
    window when saturated or wide) or ``NEIGHBOUR_FLANK_TAIL`` in its background flanks, in the compiled kernel
    and its reference alike."""
    from lrsensor.extract.compile import HAVE_NUMBA
    from lrsensor.extract.reference_finish import neighbours
    from lrsensor.extract.refit import point_table, refit_targets

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    laser = np.array([0, 1])
    cols = np.array([3, 3])
    v = np.array([100.0, 111.0])
    amp = np.array([50.0, 50.0])
    sig = np.array([own_sig, 1.5])  # the neighbour (point 1): sigma 1.5 px, 11 rows away
    sat = np.array([own_sat, False])
    good = np.array([True, True])
    read = (near, 8.0, 2.0)
    last = np.full((3, 2), np.nan)
    at = point_table(laser, cols, 2, 8)
    idx, *_ = refit_targets(laser, cols, v, amp, sig, sat, good, at, 12.0, read, np.arange(8), last)
    assert (0 in idx.tolist()) == picked
    assert bool(np.isfinite(neighbours(laser, cols, v, amp, sig, sat, good, 2, 8, 12.0, read)[0][0])) == picked


def test_read_reach_matches_the_reference() -> None:
    from lrsensor.extract import reference_finish
    from lrsensor.extract.refit import read_reach

    rng = np.random.default_rng(5)
    sig = np.concatenate([rng.uniform(0.3, 4.0, 500), [np.nan, np.inf, 2.0, 1.1, 0.0]])
    sat = rng.random(sig.size) < 0.2
    for read in ((6.0, 8.0, 2.0), (3.0, 12.0, 3.5), (9.0, 8.0, 2.0)):
        twin = np.stack(reference_finish.read_reach(sig, sat, read), axis=1)
        kernel = [read_reach(s, bool(b), *read) for s, b in zip(sig, sat, strict=True)]
        np.testing.assert_array_equal(twin, kernel)
        assert np.all(twin <= read[1])
        assert np.all(twin[sat | ~np.isfinite(sig)] == read[1])  # saturated or wide: the whole window
        plain = ~sat & (sig <= read[2])
        assert np.all(twin[plain, 1] == min(read[0] + 1.0, read[1]))  # flanks out to near, a row of re-centring
        assert np.all(twin[plain, 0] >= 5.0)  # the centroid's weights: 3 sigma of at least 1.1 px


def test_row_overlap_test_never_hides_a_neighbour() -> None:
    """``rows_overlap`` (which lets the fit skip the neighbour refits) is False only when ``refit_targets`` finds
    no other-laser point within the distance, and False for stripes far apart; ``refit_targets`` picks the points
    the reference gives a neighbour."""
    from lrsensor.extract.reference_finish import neighbours
    from lrsensor.extract.refit import point_table, refit_targets, rows_overlap

    rng = np.random.default_rng(3)
    w, max_d = 200, 9.0
    for trial in range(300):
        n_l = 2 + trial % 2
        laser = np.repeat(np.arange(n_l), w)
        cols = np.tile(np.arange(w), n_l)
        gap = rng.uniform(0.0, 40.0)
        v = 100.0 + gap * laser + rng.normal(0.0, rng.uniform(0.1, 5.0), laser.size)
        good = rng.random(laser.size) < 0.9
        v[rng.random(laser.size) < 0.05] = np.nan
        amp = rng.uniform(1.0, 50.0, laser.size)
        sig = rng.uniform(0.5, 3.0, laser.size)
        sat = rng.random(laser.size) < 0.1
        read = (4.0, 5.0, 2.0)
        last = np.full((3, laser.size), np.nan)
        at = point_table(laser, cols, n_l, w)
        idx, *_ = refit_targets(laser, cols, v, amp, sig, sat, good, at, max_d, read, np.arange(w), last)
        nb_v, _, _ = neighbours(laser, cols, v, amp, sig, sat, good, n_l, w, max_d, read)  # the reference
        np.testing.assert_array_equal(idx, np.flatnonzero(np.isfinite(nb_v)))
        if idx.size:
            assert rows_overlap(laser, v, good, n_l, max_d)
    far = np.array([100.0, 101.0, 130.0, 131.0])
    lz = np.array([0, 0, 1, 1])
    assert not rows_overlap(lz, far, np.ones(4, bool), 2, 9.0)
    assert rows_overlap(lz, far, np.ones(4, bool), 2, 29.5)


@pytest.mark.parametrize(("width", "band"), [(96, (30, 70)), (97, (3, 40)), (64, (65, 99))])
def test_compiled_detection_equals_the_opencv_steps(width: int, band: tuple[int, int]) -> None:
    """``detect_band`` (one pass) gives the same candidates and noise as the reference's OpenCV steps
    (``_candidates``), also for an odd width and for bands whose contrast margin runs past the top or bottom of
    the image."""
    from lrsensor.extract.compile import HAVE_NUMBA
    from lrsensor.extract.detect import detect_band
    from lrsensor.extract.reference import _candidates
    from lrsensor.extract.settings import Bands, frame_settings

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    rng = np.random.default_rng(width)
    h = 100
    img = rng.normal(40.0, 3.0, (h, width, 3))
    cols = np.arange(width)
    mid = 0.5 * (band[0] + band[1])
    for row0, amp in ((mid - 4.0, 120.0), (mid + 4.0, 40.0)):  # a stripe and a dimmer one close by
        rows = row0 + 4.0 * np.sin(cols / 15.0)
        img[:, :, 1] += amp * np.exp(-0.5 * ((np.arange(h)[:, None] - rows[None, :]) / 1.3) ** 2)
    img = np.ascontiguousarray(np.clip(np.round(img), 0, 255).astype(np.uint8))
    v_lo = np.full((1, width), band[0], np.int64)
    v_hi = np.full((1, width), band[1] - 1, np.int64)
    v_hi[0, width // 3 : width // 2] = band[0] - 1  # an empty stretch: the band need not be a rectangle
    bands = Bands(np.array([band], np.int64), v_lo, v_hi, np.zeros((1, width), np.int64))
    s = frame_settings(Calibration.paper(), SubpixelConfig())[1]
    args = (s.contrast_px, s.snr_threshold, s.area_noise, s.min_response_dn, v_lo[0], v_hi[0], bands.glow_side[0], 5)
    fast = detect_band(img, band[0], band[1], *args)
    slow = _candidates(img, 0, bands, s, 5)
    assert fast[0].size > 0.8 * width
    for a, b in zip(fast[:3], slow[:3], strict=True):
        np.testing.assert_array_equal(a, b)
    assert fast[3] == slow[3]


def test_real_frames_compile_nothing_beyond_the_cached_calls() -> None:
    """The compile calls the frame's calls with the :class:`~lrsensor.extract.frame.Picked` candidates and
    :class:`~lrsensor.extract.frame.Located` points of a blank frame; real frames (stripes, clipped tops, close
    stripes, glow) hand over records of exactly the same types, so they run the cached machine code and never
    compile a call again."""
    from lrsensor.extract import compile as kernels
    from lrsensor.extract.frame import finish_located, fit_points, glow_starts, locate_candidates, pool_ends
    from lrsensor.extract.glow import glow_refit
    from lrsensor.sim import named_scene, scenes

    if not kernels.HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    kernels.warm_up()
    close_stripes = scenes.wall_scene(5.0, width=1920, height=1080)  # the neighbour refits run
    for setup in [named_scene(name) for name in ("paper_box", "wall_0.3", "turbid")] + [close_stripes]:
        Sensor(setup.calibration).process(setup.render(0).image)
        subpixel_extract(setup.render(1).image, setup.calibration)
    for kernel in (locate_candidates, fit_points, glow_starts, glow_refit, finish_located, pool_ends):
        assert len(kernel.signatures) == 1, kernel


@pytest.mark.parametrize("seed", [0, 1])
def test_glow_test_decides_as_the_reference_where_stripes_overlap(seed: int) -> None:
    """On a clear wall at 5 m the two lasers' stripes lie about 11 rows apart, inside each other's glow-test rows:
    the compiled test (the other stripe subtracted, pools compared only where prefix counts leave a majority, the
    colour read only where the steps pass) takes the reference's decisions and fits, point for point."""
    from lrsensor.extract import frame as compiled
    from lrsensor.extract import glow, reference_glow
    from lrsensor.extract.compile import HAVE_NUMBA, warm_up
    from lrsensor.extract.settings import frame_settings
    from lrsensor.sim.scenes import wall_scene

    if not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    warm_up()
    r = wall_scene(5.0, width=1920, height=1080).render(seed=seed)
    bands, s, geo = frame_settings(r.calibration, SubpixelConfig())
    picked = compiled.locate_candidates(r.image, bands, s)
    mfw = compiled.max_fwhm_at(
        picked.cols, picked.rows, picked.laser, compiled.FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo
    )
    p = compiled.fit_points(r.image, picked, mfw, s)
    f = p.fits
    args = (
        r.image, p.cols, p.laser, bands.glow_side, f.centre, f.amplitude, f.sigma, f.saturated, f.ok, f.local_noise,
        p.noise, s.min_fwhm_px / compiled.FWHM_PER_SIGMA, s.max_sigma_px, s.saturation_dn, s.min_green_ratio,
        geo.glow_vanish, geo.glow_path, glow.new_water(), np.zeros(p.cols.size, np.bool_),
    )  # fmt: skip
    v_road, s_road, f_road = glow.glow_refit(*(a.copy() if isinstance(a, np.ndarray) else a for a in args))[:3]
    v_ref, s_ref, f_ref = reference_glow.glow_refit(*(a.copy() if isinstance(a, np.ndarray) else a for a in args))[:3]
    assert np.count_nonzero(f.ok) > 2000
    np.testing.assert_array_equal(f_road, f_ref)
    np.testing.assert_allclose(v_road, v_ref, atol=1e-6)
    np.testing.assert_allclose(s_road, s_ref, atol=1e-6)
