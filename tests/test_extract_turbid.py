"""The turbid-water stage (:mod:`lrsensor.extract.glow`): unbiased on the independent turbidity model, the same in the
compiled road and the numpy reference, and absent in clear water."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.turbid_model import Turbid, TurbidFrame, render
from lrsensor import Calibration, Sensor
from lrsensor.extract import centre, glow, glow_fit, held, reference_glow, subpixel
from lrsensor.extract.compile import HAVE_NUMBA, warm_up
from lrsensor.extract.settings import glow_sides
from lrsensor.scan import Scan

#: No veil, particles or noise: the laser's layers alone.
QUIET = {"veil_dn": 0.0, "particles_per_mpx": 0.0, "read_noise_dn": 0.0}
#: Columns checked: the centre, both halves and near both edges.
COLUMNS = (200, 400, 959, 1500, 1700)


def _outward_shift(frame: TurbidFrame, **options: object) -> np.ndarray:
    """Row errors of the default extractor's points towards the glow's side (px), both lasers."""
    scan = Sensor(frame.calibration).process(frame.image, **options)
    u = np.rint(scan.uv[:, 0]).astype(int)
    side = np.where(scan.laser == 0, -1.0, 1.0)
    return np.asarray(side * (scan.uv[:, 1] - frame.rows[scan.laser, u]))


def test_glow_sides_are_away_from_the_vanishing_line() -> None:
    """The paper's lasers are horizontal planes above and below the camera: the top stripe's glow lies above it
    (smaller rows), the bottom one's below, in every column."""
    sides = glow_sides(Calibration.paper(), 0.2, 5.0)
    assert (sides[0] == -1).all()
    assert (sides[1] == 1).all()


@pytest.mark.parametrize(
    ("attenuation_per_m", "ramp", "tol_px"), [(0.0, False, 0.02), (0.3, False, 0.1), (0.3, True, 0.02)]
)
def test_joint_fit_finds_the_centre_of_a_noise_free_glowing_profile(
    attenuation_per_m: float, ramp: bool, tol_px: float
) -> None:
    """Glow step 0.5 of the stripe's peak, 4 px of forward-scatter blur, 1 m: the common fit reads the centre about
    0.9 px outward; the joint fit within 0.02 px where the glow is flat along the rows (no attenuation: the step
    model is exact), within 0.1 px with the step model where the glow brightens towards the camera (0.3 /m), and
    within 0.02 px there with the glow's ramp; the compiled fit gives the reference's centre."""
    frame = render(Turbid(distance_m=1.0, glow_step=0.5, blur_px=4.0, attenuation_per_m=attenuation_per_m, **QUIET))
    green = frame.layers["stripe"] + frame.layers["glow"]
    for li, side in ((0, -1.0), (1, 1.0)):
        for u in COLUMNS:
            v_true = float(frame.rows[li, u])
            rc = round(v_true)
            sigma = math.hypot(4.0, 0.0015 * frame.calibration.camera.fy / float(frame.range_m[li, u]))
            half = min(math.ceil(glow.WINDOW_SIGMAS * sigma) + 2, glow.MAX_HALF_PX)
            y = green[rc - half : rc + half + 1, u].astype(np.float64)
            common = centre.fit_profiles(y[None, :], sigma_hint=sigma)
            c_common = rc - half + float(common.centre[0])
            assert side * (c_common - v_true) > 0.8  # today's fit: pulled towards the glow
            q = np.arange(-half, half + 1, dtype=np.float64)
            ref = reference_glow.fit_profiles(
                y[None, :],
                np.ones((1, y.size)),
                np.array([side]),
                np.array([c_common - rc]),
                np.array([sigma]),
                np.array([np.nan]),
                np.array([1.0]),
                0.5,
                5.0,
                250.0,
                ramp=ramp,
            )
            assert ref[4][0]
            assert rc + ref[0][0] == pytest.approx(v_true, abs=tol_px)
            assert ref[3][0] / ref[2][0] == pytest.approx(0.5, abs=0.15)  # the glow's step over the stripe's peak
            assert ref[6][0] == y.size - (8 if ramp else 6)  # degrees of freedom: no neighbour in the model
            if HAVE_NUMBA:
                c, _sg, _a, _g, ok, _rss, _dof = glow_fit.fit_one(
                    y, q, side, c_common - rc, sigma, np.nan, 1.0, 0.0, True, ramp, 0.5, 5.0, 250.0
                )
                assert ok
                assert c == pytest.approx(ref[0][0], abs=1e-9)
                assert _rss == pytest.approx(ref[5][0], rel=1e-6, abs=1e-9)


@pytest.mark.parametrize(("distance_m", "blur_px"), [(1.0, 4.0), (0.5, 1.5)])
def test_glowing_walls_are_read_without_bias(distance_m: float, blur_px: float) -> None:
    """On noisy frames of the turbidity model with a glow step of 0.5: the median row error is within 0.05 px of
    the truth (the common fit alone: 0.5-1 px outward)."""
    frame = render(Turbid(distance_m=distance_m, glow_step=0.5, blur_px=blur_px, seed=3))
    old = _outward_shift(frame, glow_fit=False)
    new = _outward_shift(frame)
    assert np.median(old) > 0.5
    assert abs(np.median(new)) < 0.05
    assert new.size >= 0.95 * old.size


@pytest.mark.parametrize(
    ("turbid", "old_px", "tol_px"),
    [
        # two blurred stripes 18 px apart, no glow: fitted together (the common fit: 0.15 px outward)
        (Turbid(distance_m=3.0, glow_step=0.0, blur_px=4.0, seed=2), 0.1, 0.03),
        # a glow that brightens steeply outward: the ramp in the model (the common fit: 0.4 px outward)
        (Turbid(distance_m=3.0, glow_step=0.5, blur_px=1.5, seed=2), 0.3, 0.02),
    ],
    ids=["3m-close-blurred-stripes", "3m-glow"],
)
def test_far_walls_are_read_without_bias(turbid: Turbid, old_px: float, tol_px: float) -> None:
    """Far walls in turbid water: the median row error of the default extractor's points is within ``tol_px`` of
    the truth, where the common fit alone (``glow_fit=False``) reads the stripe at least ``old_px`` outward."""
    frame = render(turbid)
    assert np.median(_outward_shift(frame, glow_fit=False)) > old_px
    assert abs(np.median(_outward_shift(frame))) < tol_px


def test_the_ramp_follows_a_glow_that_brightens_outward() -> None:
    """Noise-free profiles at 3 m (glow step 0.5, 1.5 px of blur): the glow grows about threefold within the fit's
    window; the step model reads the centre at least 0.05 px inward, the model with the ramp within 0.015 px."""
    frame = render(Turbid(distance_m=3.0, glow_step=0.5, blur_px=1.5, **QUIET))
    green = (frame.layers["stripe"] + frame.layers["glow"]).astype(np.float64)
    for li, side in ((0, -1.0), (1, 1.0)):
        for u in (400, 959, 1500):
            v_true = float(frame.rows[li, u])
            rc = round(v_true)
            sigma = math.hypot(1.5, 0.0015 * frame.calibration.camera.fy / float(frame.range_m[li, u]))
            half = min(math.ceil(glow.WINDOW_SIGMAS * sigma) + 2, glow.MAX_HALF_PX)
            y = green[rc - half : rc + half + 1, u][None, :]
            shift = {}
            for ramp in (False, True):
                c, *_rest = reference_glow.fit_profiles(
                    y,
                    np.ones_like(y),
                    np.array([side]),
                    np.array([v_true - rc + 0.3]),
                    np.array([sigma]),
                    np.array([np.nan]),
                    np.array([1.0]),
                    0.5,
                    5.0,
                    250.0,
                    ramp=ramp,
                )
                shift[ramp] = side * (rc + c[0] - v_true)
            assert shift[False] < -0.05
            assert abs(shift[True]) < 0.015


def test_clear_water_is_untouched() -> None:
    """Without glow the stage changes no point: a clear wall of the turbidity model and the simulator's wall at 1 m
    give exactly the points of the common fit."""
    sim = pytest.importorskip("lrsensor.sim")
    frames = [render(Turbid(distance_m=1.0, glow_step=0.0, blur_px=1.5, seed=1))]
    r = sim.named_scene("wall_1.0").render(seed=0)
    for image, calibration in [(f.image, f.calibration) for f in frames] + [(r.image, r.calibration)]:
        sensor = Sensor(calibration)
        a = sensor.process(image)
        b = sensor.process(image, glow_fit=False)
        np.testing.assert_array_equal(a.uv, b.uv)
        np.testing.assert_array_equal(a.points, b.points)


@pytest.mark.parametrize(
    "turbid",
    [
        Turbid(distance_m=3.0, glow_step=0.5, blur_px=1.5, seed=0),  # two stripes close: the neighbour in the fit
        Turbid(distance_m=1.0, tilt_deg=30.0, glow_step=0.5, blur_px=4.0, seed=0),  # clipped and wide profiles
        Turbid(distance_m=3.0, glow_step=0.1, blur_px=4.0, seed=0),  # a weak glow: its step held
    ],
    ids=["3m-neighbours", "1m-tilt30-clipped", "3m-weak-glow-held"],
)
def test_compiled_glow_stage_equals_the_reference(monkeypatch: pytest.MonkeyPatch, turbid: Turbid) -> None:
    """The kernel and the reference on the same inputs (the reference's own common fits), then on whole frames."""
    if not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    warm_up()
    frame = render(turbid)
    captured: list[tuple[object, ...]] = []
    real = reference_glow.glow_refit

    def spy(*args: object) -> object:
        captured.append(args)
        return real(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(reference_glow, "glow_refit", spy)
    monkeypatch.setattr(subpixel, "USE_REFERENCE", True)
    slow = subpixel.extract(frame.image, frame.calibration)
    (args,) = captured
    args, retry = args[:-2], args[-1]  # (each call below tells the water afresh, as the frame did)
    v_ref, s_ref, f_ref, a_ref, n_ref = real(*args, glow.new_water(), retry)  # type: ignore[arg-type]
    v_road, s_road, f_road, a_road, n_road = glow.glow_refit(*args, glow.new_water(), retry)
    assert f_ref.sum() > 0.8 * np.count_nonzero(args[8])  # most points show the glow and take the joint fit
    np.testing.assert_array_equal(f_road, f_ref)
    np.testing.assert_allclose(v_road, v_ref, atol=1e-6)
    np.testing.assert_allclose(s_road, s_ref, atol=1e-6)
    np.testing.assert_allclose(a_road, a_ref, rtol=1e-6, atol=1e-6)  # the gate's amplitude and noise
    # (the residual noise of a fit that diverged, a glow and a stripe that cancel near the vanishing line, is the
    # root of a sum of squares of 1e13 DN^2: the same to 1e-4, its centre and amplitude to 1e-9; the gate drops it)
    np.testing.assert_allclose(n_road, n_ref, rtol=1e-4, atol=1e-6)
    monkeypatch.setattr(subpixel, "USE_REFERENCE", False)
    fast = subpixel.extract(frame.image, frame.calibration)
    kf = fast.laser * 10_000 + np.rint(fast.uv[:, 0]).astype(int)
    ks = slow.laser * 10_000 + np.rint(slow.uv[:, 0]).astype(int)
    common, i_f, i_s = np.intersect1d(kf, ks, return_indices=True)
    assert common.size >= 0.97 * max(kf.size, ks.size)
    dv = np.abs(fast.uv[i_f, 1] - slow.uv[i_s, 1])
    assert np.median(dv) < 0.01
    assert np.percentile(dv, 90) < 0.06


def _picked_near_truth(frame: TurbidFrame, cand: tuple[np.ndarray, np.ndarray], li: int) -> float:
    """Share of the laser's visible columns with a candidate within 2 px of the true row."""
    u, v = cand
    w = frame.rows.shape[1]
    near = np.zeros(w, bool)
    for uu in (2 * u, np.minimum(2 * u + 1, w - 1)):
        with np.errstate(invalid="ignore"):
            near[uu[np.abs(v - frame.rows[li, uu]) <= 2.0]] = True
    vis = frame.visible[li]
    return float(near[vis].mean())


def test_detection_finds_the_stripe_on_the_rising_glow() -> None:
    """3 m, glow step 0.5, 1.5 px of blur: the glow brightens so steeply outward that the two-sided contrast finds
    the stripe in fewer than 60 % of the visible columns; the second pass (a centre-over-mean response where the
    outer side is the brighter, in the columns without any candidate and then, the glow being found, in all)
    finds it in more than 90 %, keeps every first-pass candidate, and the compiled detection gives the
    reference's candidates bit for bit."""
    from lrsensor.extract import reference
    from lrsensor.extract.detect import detect_band
    from lrsensor.extract.settings import frame_settings

    frame = render(Turbid(distance_m=3.0, glow_step=0.5, blur_px=1.5, seed=0))
    bands, s = frame_settings(frame.calibration, subpixel.SubpixelConfig())[:2]
    no_side = bands._replace(glow_side=np.zeros_like(bands.glow_side))
    for li in (0, 1):
        u, v, a, noise, sec = reference._candidates(frame.image, li, bands, s, 0)
        u0, v0, _, noise0, sec0 = reference._candidates(frame.image, li, no_side, s, 0)
        assert not sec0.any()  # the second pass's candidates, told apart
        assert sec.sum() == u.size - u0.size
        assert noise == noise0
        assert _picked_near_truth(frame, (u0, v0), li) < 0.6
        assert _picked_near_truth(frame, (u, v), li) > 0.9
        first, both = set(zip(u0.tolist(), v0.tolist(), strict=True)), set(zip(u.tolist(), v.tolist(), strict=True))
        assert first <= both  # the first pass's candidates stay
        if HAVE_NUMBA:
            r0, r1 = bands.rows[li]
            args = (s.contrast_px, s.snr_threshold, s.area_noise, s.min_response_dn)
            fast = detect_band(frame.image, r0, r1, *args, bands.v_lo[li], bands.v_hi[li], bands.glow_side[li], 0)
            for x, y in zip((*fast[:3], fast[4]), (u, v, a, sec), strict=True):
                np.testing.assert_array_equal(x, y)
            assert fast[3] == noise


def _columns(frame: TurbidFrame, scan: Scan, li: int) -> tuple[np.ndarray, np.ndarray]:
    """Laser ``li``'s points' columns (N,) int and the image columns (W,) bool that have one of them."""
    u = np.rint(scan.uv[scan.laser == li, 0]).astype(int)
    seen = np.zeros(frame.rows.shape[1], bool)
    seen[u] = True
    return u, seen

def test_far_glowing_walls_are_covered() -> None:
    """3 m, glow step 0.5, 1.5 px of blur (seed 1): the points cover at least 70 % of the visible columns (43 % with
    the two-sided contrast alone) and their median error stays within 0.3 % of range."""
    frame = render(Turbid(distance_m=3.0, glow_step=0.5, blur_px=1.5, seed=1))
    scan = Sensor(frame.calibration).process(frame.image)
    for li in (0, 1):
        m = scan.laser == li
        u, seen = _columns(frame, scan, li)
        assert seen[frame.visible[li]].mean() > 0.7
        rel = np.abs(scan.points[m, 0] - frame.range_m[li, u]) / frame.range_m[li, u]
        assert np.median(rel) < 0.003


def test_the_common_fits_refused_points_are_fitted_with_the_glow() -> None:
    """3 m, glow step 0.5, 4 px of blur (seed 0): at the dim sides the common fit refuses a quarter to a half of the
    columns whose stripe peaks at 4-8x the noise; fitted with the glow from their candidate rows
    (``frame.RETRY_REFUSED``) the points cover more than 55 % of those columns (47-50 % without) and 80 % of all the
    visible ones (77-78 %), with at most 1 % of them more than 5 % off (1.7 % on the bottom laser without)."""
    frame = render(Turbid(distance_m=3.0, glow_step=0.5, blur_px=4.0, seed=0))
    scan = Sensor(frame.calibration).process(frame.image)
    for li in (0, 1):
        m = scan.laser == li
        u, seen = _columns(frame, scan, li)
        snr = frame.peak_dn[li] / frame.noise_dn[li]
        dim = frame.visible[li] & (snr >= 4.0) & (snr < 8.0)
        assert seen[dim].mean() > 0.55
        assert seen[frame.visible[li]].mean() > 0.8
        rel = np.abs(scan.points[m, 0] - frame.range_m[li, u]) / frame.range_m[li, u]
        assert np.mean(rel > 0.05) <= 0.01


def test_the_stripe_noise_is_the_joint_fits_lower_median_where_they_tell_it() -> None:
    """The gate's band noise (finish.stripe_noise): a laser with at least STRIPE_NOISE_MIN joint fits takes the lower
    median of their residual noise where that is lower than the band's; fewer fits, or a higher median, leave the
    band's noise."""
    from lrsensor.extract import finish

    noise_of = getattr(finish.stripe_noise, "py_func", finish.stripe_noise)
    m = finish.STRIPE_NOISE_MIN
    lz = np.repeat([0, 1], m)
    lnoise = np.concatenate([np.linspace(1.0, 3.0, m), np.linspace(6.0, 8.0, m)])
    own = np.ones(2 * m, bool)
    own[0] = False  # one point too few for laser 0
    out = noise_of(lz, lnoise, own, np.array([4.0, 4.0]))
    np.testing.assert_array_equal(out, [4.0, 4.0])  # laser 0: too few fits; laser 1: its fits' noise is higher
    own[0] = True
    out = noise_of(lz, lnoise, own, np.array([4.0, 4.0]))
    assert out[0] == np.sort(lnoise[:m])[(m - 1) // 2]
    assert out[1] == 4.0


def test_the_gate_takes_the_joint_fits_amplitude_and_noise() -> None:
    """2 m, glow step 0.5, 1.5 px of blur (seed 0): with the joint fit's stripe amplitude and residual noise at the
    gate the points cover at least 90 % of the visible columns (about 80 % when the gate took the common fit's
    amplitude, whose line takes part of the glow's step as a slope, over the band's noise); and the glow stage
    returns the common fit's amplitude and noise where it fits nothing."""
    frame = render(Turbid(distance_m=2.0, glow_step=0.5, blur_px=1.5, seed=0))
    scan = Sensor(frame.calibration).process(frame.image)
    for li in (0, 1):
        _u, seen = _columns(frame, scan, li)
        assert seen[frame.visible[li]].mean() >= 0.9
    n = 5
    cols = np.arange(n)
    image = np.zeros((64, 8, 3), np.uint8)
    out = reference_glow.glow_refit(
        image, cols, np.zeros(n, np.int64), np.zeros((1, 8), np.int64), np.full(n, 30.0), np.full(n, 20.0),
        np.full(n, 2.0), np.zeros(n, bool), np.ones(n, bool), np.full(n, 1.5), np.array([1.0]), 0.5, 8.0, 250.0, 1.5,
        np.zeros((1, 8)), np.zeros((1, 8)), np.array([0.0, 0.0, np.inf]),
    )  # fmt: skip
    assert not out[2].any()
    np.testing.assert_array_equal(out[3], 20.0)
    np.testing.assert_array_equal(out[4], 1.5)


def test_a_stripe_that_shows_the_glow_as_a_whole_is_fitted_with_it_all_along() -> None:
    """glow._whole_stripe: all of a laser's candidates glow where a pool's worth of them show the glow and the median
    step over all of them is above the trigger's share of their median amplitude (laser 0: 17 of its 39 show it, the
    step 0.1 of the amplitude, as a weak glow's); not where the step is a small share (laser 1: 0.02, though all
    show it) nor where fewer than a pool show it (laser 2)."""
    f = getattr(glow._whole_stripe, "py_func", glow._whole_stripe)
    n = 40
    laser = np.repeat([0, 1, 2], n)
    cand = np.ones(3 * n, bool)
    cand[5] = False
    glowing = np.zeros(3 * n, bool)
    glowing[:18] = True
    glowing[n : 2 * n] = True
    glowing[2 * n : 2 * n + 2 * glow.POOL_COLS] = True
    glowing &= cand
    amp = np.full(3 * n, 100.0)
    diff = np.concatenate([np.full(n, 10.0), np.full(n, 2.0), np.full(n, 50.0)])
    none = np.zeros(3 * n, bool)
    out = f(glowing, cand, laser, 3, diff, amp, np.full(3, 1.0), none)
    np.testing.assert_array_equal(out[:n], cand[:n])
    np.testing.assert_array_equal(out[n:], glowing[n:])
    # the common fit's refused points (retry) are left out of the test, and fitted with the glow where it holds: half
    # of laser 0's candidates refused, without a step, do not decide it
    retry = none.copy()
    retry[20:n] = True
    diff[20:n] = 0.0
    np.testing.assert_array_equal(f(glowing, cand, laser, 3, diff, amp, np.full(3, 1.0), none)[:n], glowing[:n])
    np.testing.assert_array_equal(f(glowing, cand, laser, 3, diff, amp, np.full(3, 1.0), retry)[:n], cand[:n])


def test_the_dim_ends_of_a_glowing_2m_stripe_are_not_a_pixel_outward() -> None:
    """2 m, glow step 0.5, 4 px of blur, seed 1: 68-71 % of each stripe's points show the glow; its dim ends kept the
    common fit a pixel outward (8.9 % of the points more than 5 % off) and the shape was not used (the glowing
    points' mean width 2.75 px). Now the whole stripe is fitted with the glow's shape: at most 2 % outliers."""
    frame = render(Turbid(distance_m=2.0, glow_step=0.5, blur_px=4.0, seed=1))
    scan = Sensor(frame.calibration).process(frame.image)
    u = np.rint(scan.uv[:, 0]).astype(int)
    x_true = frame.range_m[scan.laser, u]
    rel = np.abs(scan.points[:, 0] - x_true) / x_true
    assert np.mean(rel > 0.05) <= 0.02


def test_the_frame_statistics_take_the_first_detection_passs_points() -> None:
    """2 m, glow step 0.5, 4 px of blur: the second detection pass's points lie on the glow's rising side, whose step
    widens their profiles' half-maximum width; the frame's typical sigma (hence every fit's window) comes from the
    first pass's points, as in the reference. In clear water there is no second pass."""
    if not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    from lrsensor.extract import frame as compiled
    from lrsensor.extract.config import SubpixelConfig
    from lrsensor.extract.settings import frame_settings

    warm_up()
    for step, glowing in ((0.5, True), (0.0, False)):
        f = render(Turbid(distance_m=2.0, glow_step=step, blur_px=4.0, seed=1))
        bands, s, geo = frame_settings(f.calibration, SubpixelConfig())
        p = compiled.locate_candidates(f.image, bands, s)
        assert p.second.any() == glowing
        if not glowing:
            continue
        assert 0.05 * p.cols.size < np.count_nonzero(p.second) < 0.5 * p.cols.size
        mfw = compiled.max_fwhm_at(
            p.cols, p.rows, p.laser, compiled.FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo
        )
        located = compiled.fit_points(f.image, p, mfw, s)
        sub = np.linspace(0, p.cols.size - 1, compiled.STATS_POINTS).astype(np.int64)  # every point's
        sigma_all = compiled.frame_profile_stats(
            f.image, p.cols[sub], p.rows[sub], s.window_half_px, s.saturation_dn, s.max_sigma_px, mfw[sub]
        )[0]
        assert located.sigma_px < 0.7 * sigma_all


@pytest.mark.parametrize(
    ("distance_m", "glow_step", "blur_px", "seed"), [(2.0, 0.3, 4.0, 0), (3.0, 0.1, 1.5, 2), (2.0, 0.3, 4.0, 1)]
)
def test_compiled_second_pass_equals_the_reference(
    distance_m: float, glow_step: float, blur_px: float, seed: int
) -> None:
    """The compiled detection's second pass gives the reference's candidates and flags bit for bit, also where the
    first sweep finds fewer than GLOW_PASS_MIN (kept, the other columns not searched) and where a pixel difference
    is negative (frames on which an unsigned difference once added and dropped candidates)."""
    if not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    from lrsensor.extract import reference
    from lrsensor.extract.detect import detect_band
    from lrsensor.extract.settings import frame_settings

    frame = render(Turbid(distance_m=distance_m, glow_step=glow_step, blur_px=blur_px, seed=seed))
    bands, s = frame_settings(frame.calibration, subpixel.SubpixelConfig())[:2]
    for li in (0, 1):
        ref = reference._candidates(frame.image, li, bands, s, 0)
        r0, r1 = bands.rows[li]
        args = (s.contrast_px, s.snr_threshold, s.area_noise, s.min_response_dn, bands.v_lo[li], bands.v_hi[li])
        fast = detect_band(frame.image, r0, r1, *args, bands.glow_side[li], 0)
        for x, y in zip((*fast[:3], fast[4]), (*ref[:3], ref[4]), strict=True):
            np.testing.assert_array_equal(x, y)


def test_stripe_sigma_pools_blurred_stripes_only() -> None:
    """A blurred stripe's noise-narrowed dim columns take the stripe's mean width, its wider ones keep their own; a
    sharp stripe (clear water) keeps every column's own (the reference's; the kernel's glow stage is compared with
    the reference's whole above)."""
    rng = np.random.default_rng(3)
    w = 200
    laser = np.repeat([0, 1], w)
    sg0 = np.concatenate([4.0 + 0.2 * rng.standard_normal(w), 1.0 + 0.1 * rng.standard_normal(w)])
    sg0[150:170] = 1.5  # laser 0's dim end: noise-narrowed fits
    cand = np.ones(2 * w, bool)
    cand[10] = False
    ref = reference_glow._stripe_sigma(laser, cand, sg0, 2)
    mean0 = sg0[:w][cand[:w]].mean()
    np.testing.assert_allclose(ref[150:170], mean0)  # the dim end takes the stripe's width
    wide = cand[:w] & (sg0[:w] > mean0)
    np.testing.assert_array_equal(ref[:w][wide], sg0[:w][wide])  # the wider columns keep their own
    assert ref[10] == sg0[10]  # not a candidate: its own
    np.testing.assert_array_equal(ref[w:], sg0[w:])  # the sharp stripe: untouched


def test_blurred_stripes_keep_only_sure_runs() -> None:
    """On a blurred stripe a short, dim run (its line fit's ends half a pixel off) is dropped and a long bright one
    kept; a sharp stripe keeps both."""
    from lrsensor.extract.finish import RUN_MAX_SD_PX, run_sure

    # 10 points at 2.5x the noise: 2 * 1.06 * sqrt(4) / 2.5 / sqrt(10) = 0.54 px at the run's ends
    assert not run_sure(4.0, 10 / 2.5, 10)
    assert run_sure(4.0, 50 / 12.0, 50)
    assert run_sure(1.0, 10 / 2.5, 10)  # sharp: kept
    assert 2.0 * 1.0622 * 2.0 / 2.5 / math.sqrt(10) > RUN_MAX_SD_PX


@pytest.mark.parametrize("use_reference", [False, True], ids=["compiled", "reference"])
def test_the_water_told_on_one_frame_is_carried_to_the_next(
    monkeypatch: pytest.MonkeyPatch, use_reference: bool
) -> None:
    """The attenuation and width a glowing frame tells are taken by the next frames (``water``), until
    :data:`~lrsensor.extract.glow.WATER_FRAMES` frames have; then a frame tells them again. A sensor of a stream carries
    them; a sensor of stills (the default) does not."""
    if not use_reference and not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    if not use_reference:
        warm_up()
    monkeypatch.setattr(subpixel, "USE_REFERENCE", use_reference)
    frame = render(Turbid(distance_m=3.0, glow_step=0.5, blur_px=4.0, seed=0))

    def points(water: np.ndarray) -> np.ndarray:
        return subpixel.extract_points(frame.image, frame.calibration, water=water)[0].uv

    water = glow.new_water()
    first = points(water)
    told = water.copy()
    assert 0.15 < told[0] < 0.6  # (the model's 0.3 /m)
    assert 3.0 < told[1] < 5.0  # (4.0 px)
    assert told[2] == 1.0
    assert np.all((told[3:5] > 0.0) & (told[3:5] < 1.0))  # each laser's glow share, told with the water
    np.testing.assert_array_equal(told[5:], held.UNTOLD)  # (two lasers)
    np.testing.assert_array_equal(points(water), first)  # the same frame and water (and shares): the same points
    np.testing.assert_array_equal(water, [told[0], told[1], 2.0, *told[3:]])
    water[:3] = (1.5 * told[0], told[1], 2.0)  # another water carried in: taken, not told again
    assert not np.array_equal(points(water), first)
    np.testing.assert_array_equal(water, [1.5 * told[0], told[1], 3.0, *told[3:]])
    water[2] = glow.WATER_FRAMES  # due: told again
    np.testing.assert_array_equal(points(water), first)
    np.testing.assert_array_equal(water, told)
    sensor = Sensor(frame.calibration, stream=True)
    sensor.process(frame.image)
    sensor.process(frame.image)
    np.testing.assert_array_equal(sensor._water, [told[0], told[1], 2.0, *told[3:]])
    stills = Sensor(frame.calibration)  # images that may each come from other water: each tells its own
    stills.process(frame.image)
    assert stills._water is None


@pytest.mark.parametrize("use_reference", [False, True], ids=["compiled", "reference"])
def test_a_weak_glows_share_is_carried_with_the_water(use_reference: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    """At 3 m with a glow of 0.1 the stripes' shares are held (<= HELD_MAX_STEP); a frame of the same water takes
    the shares told on the first, without their sample's fits, and places the same points as telling them again."""
    if not use_reference and not HAVE_NUMBA:
        pytest.skip("numba is not installed")
    if not use_reference:
        warm_up()
    monkeypatch.setattr(subpixel, "USE_REFERENCE", use_reference)
    frame = render(Turbid(distance_m=3.0, glow_step=0.1, blur_px=4.0, seed=1))
    water = glow.new_water()
    first = subpixel.extract_points(frame.image, frame.calibration, water=water)[0].uv
    assert np.all((water[3:5] > 0.0) & (water[3:5] <= held.HELD_MAX_STEP))
    told = water.copy()
    again = subpixel.extract_points(frame.image, frame.calibration, water=water)[0].uv
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(water, [*told[:2], 2.0, *told[3:]])
    water[3:5] = 0.5 * told[3:5]  # other shares carried in: taken, not told again
    assert not np.array_equal(subpixel.extract_points(frame.image, frame.calibration, water=water)[0].uv, first)
    np.testing.assert_array_equal(water[3:5], 0.5 * told[3:5])


@pytest.mark.parametrize("use_reference", [False, True], ids=["compiled", "reference"])
def test_the_shape_is_used_where_the_told_width_is_blurred(
    monkeypatch: pytest.MonkeyPatch, use_reference: bool
) -> None:
    """The shape's gate is the width told with it (glow.SHAPE_MIN_SIGMA), not the common fits' (which the glow
    narrows: 2.16 px at 2 m, glow 0.5, 4 px, seed 3, for a true 4.0): that frame takes the shape; a sharp stripe
    (1 m, glow 0.5, 1.5 px of blur: told about 1.7 px) keeps the step model, and its water says so (0, 0)."""
    if not use_reference and not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    if not use_reference:
        warm_up()
    monkeypatch.setattr(subpixel, "USE_REFERENCE", use_reference)
    for d, b, blurred in ((2.0, 4.0, True), (1.0, 1.5, False)):
        frame = render(Turbid(distance_m=d, glow_step=0.5, blur_px=b, seed=3))
        water = glow.new_water()
        subpixel.extract_points(frame.image, frame.calibration, water=water)
        assert water[2] == 1.0  # told
        if blurred:
            assert 0.2 < water[0] < 0.5
            assert 3.5 < water[1] < 4.5
        else:
            np.testing.assert_array_equal(water[:2], 0.0)


@pytest.mark.parametrize("use_reference", [False, True], ids=["compiled", "reference"])
def test_the_water_is_told_with_the_other_stripe_in_place(monkeypatch: pytest.MonkeyPatch, use_reference: bool) -> None:
    """At 3 m the other laser's stripe lies 18 rows off, in the telling's windows: told with it where the common fit
    put it (pulled by its own glow, and narrower), a noise-free frame read 0.33-0.35 /m for the model's 0.3 /m; told
    again with it where the told water puts it (:func:`lrsensor.extract.water.retell`), the attenuation and the
    stripe's width are the model's."""
    if not use_reference and not HAVE_NUMBA:
        pytest.skip("numba is not installed: only the reference exists")
    if not use_reference:
        warm_up()
    monkeypatch.setattr(subpixel, "USE_REFERENCE", use_reference)
    frame = render(Turbid(distance_m=3.0, glow_step=0.3, blur_px=4.0, electrons_per_dn=1e9, **QUIET))
    water = glow.new_water()
    subpixel.extract_points(frame.image, frame.calibration, water=water)
    assert abs(water[0] - 0.3) < 0.006  # (1/m; the rows move by about 3.4 px per 1/m)
    assert abs(water[1] - 4.02) < 0.1  # (px: the blur's 4 px, the sheet's thickness and the pixel)


def test_a_weak_glows_step_is_held_at_the_stripes_proportion(monkeypatch: pytest.MonkeyPatch) -> None:
    """3 m, glow step 0.1, 4 px of blur, seed 1: a free step per column trades with the stripe's edge, and the fits
    whose glow passes their own test are the ones biased inward (the others keep the common fit, outward). With the
    step held at the stripe's proportion (glow.HELD_STEP) the median row error falls from 0.07 px to 0.02 (the
    numpy reference, with and without; then the compiled road)."""
    frame = render(Turbid(distance_m=3.0, glow_step=0.1, blur_px=4.0, seed=1))

    def row_error(scan: object) -> float:
        uv, las = scan.uv, scan.laser  # type: ignore[attr-defined]
        u = np.rint(uv[:, 0]).astype(int)
        side = np.where(las == 0, -1.0, 1.0)
        return float(np.median(np.abs(side * (uv[:, 1] - frame.rows[las, u]))))

    monkeypatch.setattr(subpixel, "USE_REFERENCE", True)
    monkeypatch.setattr(reference_glow, "HELD_STEP", False)
    old = row_error(subpixel.extract(frame.image, frame.calibration))
    monkeypatch.setattr(reference_glow, "HELD_STEP", True)
    new = row_error(subpixel.extract(frame.image, frame.calibration))
    assert old > 0.05
    assert new < 0.03
    if HAVE_NUMBA:
        monkeypatch.setattr(subpixel, "USE_REFERENCE", False)
        warm_up()
        assert row_error(subpixel.extract(frame.image, frame.calibration)) < 0.03
