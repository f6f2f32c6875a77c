"""Turbid water: the stripe's centre fitted jointly with the laser sheet's glow (:func:`glow_refit`).

What the glow is. In turbid water the laser sheet itself is visible: the water inside the sheet scatters light
back to the camera. The sheet between the camera and the wall images on the side of the stripe away from the
plane's vanishing line (above the top laser's stripe, below the bottom one's) and ENDS at the stripe, where the
sheet meets the wall; the wall cuts the sheet along the sheet's own thickness profile, so the glow's edge is a
step whose 50 % point is the stripe's centre, and forward scatter blurs stripe and edge alike. A column's profile
is then, with ``z = (v - c) / sigma``, ``u = s z`` and ``s`` the glow's side (+1: the glow at larger rows)::

    y(v) = b0 + b1 (v - v0) + A exp(-z^2 / 2) + g Phi(u) + g1 sigma R1(u) + g2 sigma^2 R2(u)
           [+ a N(v) + a_g Phi(s' d): another laser's stripe close by, and its own glow's edge]

The stripe (a Gaussian) and the glow's edge (a blurred step) share their centre ``c`` and their width ``sigma``
(a sheet of Gaussian thickness blurred by a Gaussian: both widths are ``sqrt(sigma_sheet^2 + blur^2)``). The glow
is not flat beyond its edge: it brightens outward (the sheet seen there is nearer the camera: shorter paths through
the water, and at far walls the rows outward of the stripe span ranges from the wall nearly to the port). Its
growth over the window, to second order, is ``g1 x + g2 x^2`` (``x = s (v - c)`` px outward); cut by the same edge
and blurred by the same Gaussian, ``x`` and ``x^2`` become ``sigma R1(u)`` and ``sigma^2 R2(u)`` exactly, with
``R1 = u Phi(u) + phi(u)`` and ``R2 = (u^2 + 1) Phi(u) + u phi(u)`` (the first two moments of a Gaussian cut at
zero). Both stay linear parameters.

Why the common fit fails there. Its linear background through two flank windows takes the step as a slope; what
the line leaves of the step is odd about the centre and pulls the Gaussian-weighted centroid towards the glow,
0.1-1.1 px on the independent turbidity model (``benchmarks/turbid_model.py``), which reads walls 0.2-10 % short.
A stripe of another laser close by (far walls: at 3 m the two stripes of the paper's lasers are 18 px apart) lies
in the common fit's inner flank; with 4 px of forward-scatter blur its subtracted Gaussian leaves enough there to
move the centre 0.15 px outward (walls at 3 m read 1.7 % short without any glow).

What this stage does. It fits the model above by least squares on the rows ``c -+ (4.5 sigma + 2)`` (at most
:data:`MAX_HALF_PX`) where a point's profile shows a glow, and also, without the glow's terms, where another laser's
stripe overlaps this one (centres closer than :data:`PAIR_SIGMAS` times the sum of their sigmas, both at least
:data:`PAIR_MIN_SIGMA`: blurred stripes at long range): the linear parameters solved exactly at the common fit's
centre and width, then :data:`ITERATIONS` Gauss-Newton steps in all of them, the other stripe's centre and width
held (its amplitude, and its glow's step where its glow shows and its edge lies in the window, free). :data:`ROUNDS`
rounds: the first with the other stripes where the common fit put them, each next one (points with another stripe in
the fit that moved by more than :data:`~lrsensor.extract.glow_fit.ROUND_TOL_PX` times how much of it reaches the
window) where the previous round's fit put them, so that two close stripes converge to their joint fit. A fit is
kept where it converges to a stripe (``A > 0``) with a glow (where one shows: the glow two sigmas outward of the
edge above 5 % of ``A``) within :data:`MAX_MOVE_PX` of the common fit; elsewhere, and wherever no glow shows and no
stripe is close (clear water), the common fit stands untouched.
Profiles taken as flat tops (thick sheets close to the wall, wider than ``max_sigma_px``) are left alone unless
clipped: the model has no flat top.

Which glow: the step model (``g1 = g2 = 0``) is fitted first; where the glow's step, pooled over the stripe's
glowing points within :data:`POOL_COLS` columns either side, is at least :data:`RAMP_MIN_STEP` of the stripe's peak
(a weaker glow's ramp trades off with the stripe's own shape), the model with the ramp is fitted too, with the other
stripes where the step model put them, and taken where the F statistic of the ramp's two parameters, pooled the same
way (the drop of the residual sum of squares per parameter over the residual variance with the ramp), exceeds
:data:`F_SELECT`: the profiles ask for it beyond their noise. Otherwise the step model's fit stands. The test is
decided per stretch first: the ramp is fitted at every :data:`RAMP_EVERY`-th column, and at the other points only
where that sample's pooled statistic comes within :data:`RAMP_MARGIN` of the bar (below 3 m the ramp is taken at
almost no point, and most of its fits were lost; a sample's decision alone read far walls with much blur worse).

Where a glow shows: the step at each point is estimated from the green rows beyond its flanks, outer less inner, at
``2.5 sigma + 1`` rows from the centre and at twice that (``2 D_near - D_far``: a linear background cancels, a glow
that brightens outward is under-estimated a little), four rows each, another laser's stripe close by subtracted;
its median over the stripe's points within :data:`POOL_COLS` columns either side (one bright particle or a dim
column does not decide) must exceed 3.5x its noise and 5 % of the stripe's amplitude (more than half of those
steps exceed that threshold), and the step summed over them must have the laser's colour: green over red and blue
by ``min_green_ratio``, as the stripe's colour test asks (a step in the wall's shade or the ambient light is not a
glow); and most of the stripe's points within :data:`POOL_COLS` columns must pass that test too: a glow lies along
the stripe, not at a few columns.

Why this estimator, measured on the turbidity model (``python benchmarks/bench_turbid.py``; the results and the
Cramer-Rao bounds are in ``benchmarks/results/extract_turbid.md``; the design in docs/water-design.md):

- Single columns before the along-stripe smoothing: the step model's median row shift is within 0.03 px of zero at
  0.5-2 m for 1.5 and 4 px of blur (the common fit: +0.46 to +1.03 px).
- A background from the inner flank alone cannot work: the glow's edge is half way up at the centre, so even the
  stripe's inner half carries a quarter of the stripe's peak of glow.
- The window must be long (4.5 sigma): at 3 sigma the background's slope, the step and the centre trade off and
  the noise doubles (p5-p95 of single columns +-1.4 px against +-0.7 px at 4 px of blur); on noisy frames the
  medians of the short window's fits move by up to 0.4 px.
- The ramp. On noise-free profiles (attenuation 0.3 /m, glow step 0.5) the step model leaves 0.03-0.09 px inward at
  1-3 m where the glow brightens, 0.3-0.65 px at 3 m with 4 px of blur; with the ramp 0.00-0.02 px at 0.5-3 m
  (1.5 px) and 0.5-2 m (4 px). A linear ramp alone is worse than none over this window (0.1-1.5 px: the glow's
  growth is curved). With the ramp everywhere the per-column noise grows 2-3x and the medians with 4 px of blur
  grow by a half to double (1 m: 0.12 -> 0.20 %, 2 m: 0.33 -> 0.61 %); with the selection it is taken where the
  glow's growth shows (far walls, sharp stripes): 3 m, step 0.5, 1.5 px of blur: median 0.66 % -> 0.19 %. A weak
  glow's ramp (step 0.1) read walls at 3 m 1-2 % long. At 3 m with 4 px of blur the window spans ranges from 3 m
  to about 1 m, where no second-order ramp holds (0.1 px left at 4.5 sigma, noise-free).
- The other stripe close by: in the fit, 3 m without glow, 4 px of blur: median 1.7 % -> 0.24 %.
- Cost: 2-7 us a fit of one column (23-61 rows, up to 10 parameters), against about 0.1 us for the common fit
  (the frames' figures: ``python benchmarks/bench_turbid.py --cost``, docs/water.md). What it takes: the normal
  equations from the Jacobian's columns (summed row by row into the matrix, every sum waited on memory), the
  Gaussians along the rows by ratios (one exponential a row was half the time), Cholesky solves, no allocation per
  fit, the steps stopped where they settle (:data:`STOP_PX`), the rounds' refits of stripes beside another one one
  step from their last fit, the ramp decided per stretch. The fits run only where a glow shows or blurred
  stripes overlap; in clear water the stage is the test alone, cheap there: pools are compared point by point, and
  the colour read, only where prefix counts leave a glow possible. On the simulator's named scenes (clear water, its
  own turbid scene, clutter) and on the independent box-sheet model of ``benchmarks/bench_foreign_render.py`` it
  fits at most a few columns a frame. Without the colour test and the
  majority along the stripe, steps in the background's shade (the same in every channel) were taken for glow: up to
  360 columns of a frame, medians up to 0.0075 points off.

Where a stripe shows the glow as a whole (:func:`_whole_stripe`), all of its points are fitted with it (its dim ends,
and a weak glow's points, where the glow does not show above the noise).
Where every point of a stripe glows, the glow's share of the stripe's amplitude is told once
(:func:`lrsensor.extract.held.held_share`: the median of untested step fits at every few columns) and,
where it is at most 0.2 (a weak glow), each point is fitted with its step held at that share: a free step per column
trades with the stripe's edge, and the fits that pass their own glow test are the ones whose step came out large.
The stage also returns the stripe amplitude
and residual noise of each fit taken, which the signal-to-noise gate uses
(:func:`lrsensor.extract.finish.finish_points`).

The compiled kernel is :func:`glow_refit`; the fits and their rounds are in :mod:`lrsensor.extract.glow_fit`; the
reference's is :func:`lrsensor.extract.reference_glow.glow_refit` (numpy, vectorized over the points). Both read
the constants here and there.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import arange, callee, empty, full, inline, njit, zeros
from .glow_fit import ROUNDS, fit_rounds, neighbour
from .held import HELD_STEP, UNTOLD, carried_share, held_share
from .refit import rows_overlap
from .sorting import median
from .water import least, retell, sample_total

#: A glow shows where the outer rows exceed the inner ones by this many times the noise of the difference...
TRIGGER_SNR = 3.5
#: ... and by this share of the stripe's peak.
TRIGGER_FRAC = 0.05
#: The rows compared start this many sigmas (plus one row) from the centre, and twice as far; rows on each side.
TRIGGER_SIGMAS = 2.5
TRIGGER_ROWS = 4
#: The step is twice the difference at the near rows less that at rows twice as far (a linear background
#: cancels): its variance is TREND_VAR times that of one difference.
TREND_VAR = 5.0
#: The comparison is pooled (median) over the points of the same laser within this many columns either side.
POOL_COLS = 8
#: The variance of a median of Gaussian samples over that of their mean (pi / 2).
MEDIAN_VAR = 0.5 * math.pi
#: The fit's window: the centre -+ (WINDOW_SIGMAS sigma + 2) rows, at most MAX_HALF_PX.
WINDOW_SIGMAS = 4.5
MAX_HALF_PX = 30
#: A stripe is fitted together with another laser's where their centres are closer than this many times the sum
#: of their sigmas (4 px of blur at 3 m: 18 px apart, sigmas of 4 px; sharp stripes of 1.5 px: from 4.6 m on).
PAIR_SIGMAS = 4.0
#: ... and both are blurred: sigmas of at least this, px. Sharp stripes close together (clear water, far walls) keep
#: the common fit with the other's Gaussian subtracted (:mod:`lrsensor.extract.refit`), which is right for them.
PAIR_MIN_SIGMA = 2.0
#: The glow's ramp (its linear and quadratic growth outward) is taken where the F statistic of its two parameters,
#: pooled over the stripe's points within POOL_COLS columns either side, exceeds this.
F_SELECT = 4.0
#: ... and where the glow's step, pooled the same way, is at least this share of the stripe's peak (a weaker glow's
#: ramp trades off with the stripe's own shape: on the turbidity model a step of 0.1 read walls at 3 m 1-2 % long).
RAMP_MIN_STEP = 0.2
#: ... decided per stretch: the ramp is fitted at every RAMP_EVERY-th column first, and where the F statistic pooled
#: over those asks for it, at every point of the stretch (it is taken at few points below 3 m: most fits would be lost).
RAMP_EVERY = 4
#: ... and fitted at every point of the stretches whose sampled F statistic exceeds this share of F_SELECT (the
#: sampled test decides alone where the ramp is plainly not asked for; near the bar, the whole stretch decides).
RAMP_MARGIN = 0.5
#: The water's attenuation (1/m) that shapes the glow (:func:`.glow_fit.sheet_edge`) is the one of these whose step
#: fits at a sample of the glowing points have the least residual sum of squares, refined by a
#: parabola through it and its neighbours (0: a flat glow, the plain step; turbid harbour water is 0.5-2 /m).
ALPHA_GRID = (0.0, 0.1, 0.2, 0.3, 0.45, 0.7, 1.0, 1.5, 2.2)
#: ... at ALPHA_SAMPLE points of each laser's stripe (the strongest of as many stretches of its glowing columns): the
#: attenuation and the stripe's width are the water's, one each for the frame, so a sample tells them and every
#: point is then fitted once with both held.
ALPHA_SAMPLE = 32
#: ... on windows of at least this many rows either side (at 3 m with 4 px of blur, the stripe's own 14 read 0.16 /m
#: for the model's 0.3, 20-26 rows 0.30-0.31).
ALPHA_HALF_PX = 22
#: ... among the attenuations at which at least this share of those points fit.
ALPHA_SHARE = 0.75
#: The sheet's shape is fitted only where the stripe's width told with it is at least this, px (on a narrower
#: stripe the window is too short to tell the attenuation from the width: at 3 m with 1.5 px of blur it read 0.33 /m
#: for the model's 0.3, and the step with its ramp read the wall better). Told: 1.50-2.22 px with 1.5 px of blur at
#: 0.5-3 m, 3.7-4.2 with 4 px; the common fits' widths, which the glow narrows, read 2.16 px at 2 m with 4 px.
SHAPE_MIN_SIGMA = 3.0
#: ... and where the sample's glow step is at least this share of its stripe's amplitude (median; with a weaker glow
#: the attenuation's estimate is noise, and the shape read walls at 2-3 m with a glow step of 0.1 worse than the step).
SHAPE_MIN_STEP = 0.2
#: Rounds of the fits with the width held: one, the other stripes where the common fit put them, at the held width
#: (a dim column's own width is noise). Further rounds, each refitting nearly every glowing point whole, moved the
#: 3 m medians by a few hundredths of a percent either way and cost half the glowing frame.
HOLD_ROUNDS = 1
#: The attenuation and the width told on a frame are taken on this many frames (the first of them tells them again;
#: ``glow_refit``'s ``water``): at 30 Hz, once a second.
WATER_FRAMES = 30
#: Narrowest sigma the fit may take, px (a glow's edge narrower than this is not resolved by the pixels).
MIN_SIGMA_PX = 0.5


#: Lasers whose weak glow's share (:func:`lrsensor.extract.held.held_share`) a ``water`` record carries (the
#: others' is told on every frame).
WATER_LASERS = 8


def new_water() -> np.ndarray:
    """A :func:`glow_refit` ``water`` record that has told nothing yet (the next glowing frame tells it): (3 +
    :data:`WATER_LASERS`,) float64, the attenuation (1/m), the stripe's width (px), the frames since they were told,
    then each laser's glow share told with them (:data:`lrsensor.extract.held.UNTOLD`: none)."""
    return np.array([0.0, 0.0, np.inf] + [UNTOLD] * WATER_LASERS)


@inline
def _pool_noise(noise, cnt):  # type: ignore[no-untyped-def]
    """The noise of a median of ``cnt`` steps (:func:`_raw_step`), each from differences of means of
    :data:`TRIGGER_ROWS` rows of pixel noise ``noise`` (the band's: the flanks' spread about the common fit's line
    holds the glow's own step); it falls as ``cnt`` grows."""
    return noise * math.sqrt(2.0 * TREND_VAR / TRIGGER_ROWS * MEDIAN_VAR / cnt)


@inline
def _raw_step(image, rc, col, out, kt, ch):  # type: ignore[no-untyped-def]
    """The step of channel ``ch`` of column ``col`` about row ``rc``, times :data:`TRIGGER_ROWS`: twice the sum of the
    outer (direction ``out``, +-1) less the inner rows ``kt ... kt + TRIGGER_ROWS - 1`` rows from ``rc``, less that
    at ``2 kt + 1 ...`` (a linear background cancels; sums of integers, exact)."""
    far = 2 * kt + 1
    s = 0.0
    for i in range(TRIGGER_ROWS):
        s += 2.0 * (float(image[rc + out * (kt + i), col, ch]) - float(image[rc - out * (kt + i), col, ch]))
        s -= float(image[rc + out * (far + i), col, ch]) - float(image[rc - out * (far + i), col, ch])
    return s


@inline
def _gauss_step(x0, out, kt, inv_s):  # type: ignore[no-untyped-def]
    """:func:`_raw_step` of a unit Gaussian of ``1 / inv_s`` px centred ``x0`` rows before ``rc``: the other laser's
    stripe in the step, subtracted (runs of rows all beyond 9 sigmas of it, below ``e^-40``, left out). Along a run
    of consecutive rows the Gaussian is a product: with ``e`` the rows' offsets in sigmas and ``d`` their step,
    ``g(e + d) = g(e) r`` where ``r = exp(-d e - d^2 / 2)`` is itself multiplied by ``exp(-d^2)`` row by row: two
    exponentials a run, not one a row."""
    q = math.exp(-inv_s * inv_s)
    s = 0.0
    for k0, wgt in ((kt, 2.0), (2 * kt + 1, -1.0)):
        for sgn in (1, -1):
            d = sgn * out * inv_s
            e = (x0 + sgn * out * k0) * inv_s
            e_end = e + (TRIGGER_ROWS - 1) * d
            if e * e_end > 0.0 and min(abs(e), abs(e_end)) >= 9.0:
                continue
            g = math.exp(-0.5 * e * e)
            r = math.exp(-d * e - 0.5 * d * d)
            run = g
            for _ in range(TRIGGER_ROWS - 1):
                g *= r
                r *= q
                run += g
            s += wgt * sgn * run
    return s


@njit
def glow_refit(  # type: ignore[no-untyped-def]
    image, cols, laser, side_tab, vv, amp, sig, sat, ok, lnoise, noise_l, min_sig, max_sig, sat_dn, green_ratio,
    vanish, path_k, water, retry,
):
    """The joint stripe-and-glow fit of every point whose profile shows a glow (see the module's documentation).

    Args:
        image: (H, W, 3) uint8 BGR; cols, laser: (N,) each point's column and laser (one point per laser and
            column); side_tab: (L, W) int64, the side of each laser's stripe its glow lies on (+1: larger rows,
            -1: smaller, 0: unknown, no fit).
        vv, amp, sig, sat, ok, lnoise: (N,) the common fit's centre rows, amplitudes (DN), sigmas (px), clipped,
            accepted and flank noise (DN); noise_l: (L,) the bands' noise, DN.
        min_sig, max_sig: the accepted sigmas, px; sat_dn: green samples at or above it are clipped (left out of
            the fits: a clipped stripe is fitted on its flanks); green_ratio: a glow's step in green exceeds its steps
            in red and blue by this factor (the stripe's colour test).
        vanish, path_k: (L, W) float64, the row of each laser sheet's vanishing line per column and ``2 s D`` (px m:
            ``D`` the sheet's range times its rows from that line, ``s`` the path's obliqueness; 0: unknown, the glow a
            plain step), :func:`lrsensor.extract.settings.glow_geometry`.
        water: (3 + WATER_LASERS,) float64, read and updated: the water's attenuation (1/m) and the stripe's width
            (px) as last told (:func:`_attenuation`), the frames since (:data:`WATER_FRAMES`; :func:`new_water`: none
            told yet) and each laser's weak-glow share told on the same frame (:func:`held.held_share`). A camera's
            frames share one: the water changes slowly, and the telling is a third of a glowing frame.
        retry: (N,) bool, the points the common fit refused, here at their candidate row with the frame's width
            (:data:`lrsensor.extract.frame.RETRY_REFUSED`): fitted like the others where their stripe glows or
            pairs, but they take no part in what the stripe's points decide together (another stripe's position
            in the fits, the stripe's width, whether the whole stripe glows, the water's telling), which stays
            the common fits'.

    Returns:
        ``(centre_row, sigma, fitted, amplitude, noise)``: (N,) each; the common fit's centre and sigma where
        ``fitted`` is False; the stripe's amplitude (DN) and the residual noise (DN, the root of the residual sum of
        squares over the degrees of freedom) of the fit taken, ``amp`` and ``lnoise`` where none is (the
        signal-to-noise gate's: the common fit's line takes part of the glow's step as a slope, which lowers its
        amplitude and raises its flanks' spread).
    """
    h = image.shape[0]
    w = image.shape[1]
    n = cols.size
    n_l = side_tab.shape[0]
    at = full((n_l, w), -1, np.int64)
    for t in range(n):
        at[laser[t], cols[t]] = t
    lo_sig = max(min_sig, MIN_SIGMA_PX)
    # the points that can take the fit: window and trigger rows inside the image, the glow's side known
    usable = zeros(n, np.bool_)
    cand = zeros(n, np.bool_)
    nb_ok = zeros(n, np.bool_)
    side = zeros(n, np.float64)
    sg0 = full(n, 1.0, np.float64)
    rc = zeros(n, np.int64)
    hw = zeros(n, np.int64)
    kt = zeros(n, np.int64)
    for t in range(n):
        usable[t] = ok[t] and math.isfinite(vv[t]) and (sat[t] or sig[t] <= max_sig)
        if not usable[t]:
            continue
        side[t] = float(side_tab[laser[t], cols[t]])
        sg0[t] = min(max(sig[t], lo_sig), max_sig)
        rc[t] = int(math.floor(vv[t] + 0.5))  # noqa: RUF046 (numba: floor of a float is a float)
        hw[t] = min(int(math.ceil(WINDOW_SIGMAS * sg0[t])) + 2, MAX_HALF_PX)  # noqa: RUF046
        kt[t] = int(math.ceil(TRIGGER_SIGMAS * sg0[t])) + 1  # noqa: RUF046
        reach = max(hw[t], 2 * kt[t] + 1 + TRIGGER_ROWS)
        nb_ok[t] = not sat[t] and not retry[t]
        cand[t] = side[t] != 0.0 and rc[t] - reach >= 0 and rc[t] + reach <= h - 1
    # does a glow show? the outer rows over the inner ones (another laser's stripe close by subtracted), at kt rows
    # from the centre and twice as far (a linear background cancels), pooled over the candidates of the same laser
    # within POOL_COLS columns: first the step in green at every candidate
    nb0 = full(n, -1, np.int64)
    diff = zeros(n, np.float64)
    # (looked for only where two lasers' rows come that close at all, far walls: nb_ok points have sigmas of at
    # most max_sig)
    reach_max = 0
    for t in range(n):
        reach_max = max(reach_max, max(hw[t], 2 * kt[t] + 1 + TRIGGER_ROWS) if cand[t] else 0)
    close = rows_overlap(laser, vv, usable, n_l, reach_max + 3.0 * max_sig)
    for t in range(n):
        if not cand[t]:
            continue
        nb = neighbour(t, at, cols, laser, nb_ok, vv, sig, max(hw[t], 2 * kt[t] + 1 + TRIGGER_ROWS)) if close else -1
        nb0[t] = nb
        d = _raw_step(image, rc[t], cols[t], int(side[t]), kt[t], 1)
        if nb >= 0:
            d -= amp[nb] * _gauss_step(rc[t] - vv[nb], int(side[t]), kt[t], 1.0 / max(sig[nb], lo_sig))
        diff[t] = d / TRIGGER_ROWS
    # the median step exceeds the threshold (more than half of the steps around do): prefix counts along each laser's
    # columns of the candidates and of their steps above the lowest threshold any point can have (a whole pool's), so
    # that the steps are compared one by one only where a majority is possible (in clear water, at few points)
    n_cand = zeros((n_l, w + 1), np.int64)
    n_over = zeros((n_l, w + 1), np.int64)
    for li in range(n_l):
        low = TRIGGER_SNR * _pool_noise(noise_l[li], 2 * POOL_COLS + 1)
        for cc in range(w):
            j = at[li, cc]
            use = j >= 0 and cand[j] and not retry[j]  # (the common fit's refused points take no part)
            n_cand[li, cc + 1] = n_cand[li, cc] + use
            n_over[li, cc + 1] = n_over[li, cc] + (use and diff[j] > low)
    glowing = zeros(n, np.bool_)
    for t in range(n):
        if not cand[t]:
            continue
        li = laser[t]
        lo_c = max(cols[t] - POOL_COLS, 0)
        hi_c = min(cols[t] + POOL_COLS + 1, w)
        cnt = n_cand[li, hi_c] - n_cand[li, lo_c]
        if 2 * (n_over[li, hi_c] - n_over[li, lo_c]) <= cnt:
            continue
        thr = max(TRIGGER_SNR * _pool_noise(noise_l[li], cnt), TRIGGER_FRAC * amp[t])
        above = 0
        for cc in range(lo_c, hi_c):
            j = at[li, cc]
            above += j >= 0 and cand[j] and not retry[j] and diff[j] > thr
        glowing[t] = 2 * above > cnt
    # where it does, the raw step pooled the same way has the laser's colour: green over red and blue as the stripe's
    # colour test asks (a step of the wall's or the water's colour is not a glow; raw, since a neighbour stripe close
    # by is subtracted in green only, and it has the laser's colour too), read only there
    rgb = full((3, n), np.nan, np.float64)  # the raw step in green, red and blue (nothing subtracted)
    for t in range(n):
        if not glowing[t]:
            continue
        sums = zeros(3, np.float64)
        for cc in range(max(cols[t] - POOL_COLS, 0), min(cols[t] + POOL_COLS + 1, w)):
            j = at[laser[t], cc]
            if j >= 0 and cand[j] and not retry[j]:
                for k in range(3):
                    if math.isnan(rgb[k, j]):
                        rgb[k, j] = _raw_step(image, rc[j], cols[j], int(side[j]), kt[j], (1, 2, 0)[k]) / TRIGGER_ROWS
                    sums[k] += rgb[k, j]
        glowing[t] = sums[0] > green_ratio * sums[1] and sums[0] > green_ratio * sums[2]
    # and so does the majority of the points around: a glow lies along the stripe, not at a few columns
    glow_run = zeros(n, np.bool_)
    for t in range(n):
        if glowing[t]:
            li, lo_c, hi_c = laser[t], max(cols[t] - POOL_COLS, 0), min(cols[t] + POOL_COLS + 1, w)
            both = 0
            for cc in range(lo_c, hi_c):
                j = at[li, cc]
                both += j >= 0 and glowing[j] and not retry[j]
            glow_run[t] = 2 * both > n_cand[li, hi_c] - n_cand[li, lo_c]
    glowing = _whole_stripe(glow_run, cand, laser, n_l, diff, amp, noise_l, retry)
    # the blurred stripes beside another laser's whose Gaussians overlap within PAIR_SIGMAS sigmas each: fitted with
    # it (no glow term where none shows); on a blurred stripe (its candidates' mean sigma at least PAIR_MIN_SIGMA)
    # each candidate's width is the larger of its own and that mean, the stripe's (a dim column's own is noise: at
    # 3 m with 4 px of blur, true sigma 4.1 px, the common fit's sigma at peaks below 4x the noise has a median of
    # 1.9-2.4 px, and the pair test failed there; the blur is the water's, the same along the stripe); sharp
    # stripes (clear water) keep their own
    blurred = False
    for li in range(n_l):
        tot = 0.0  # the sigmas of the laser's candidates summed, and counted (registers: one pass per laser)
        cnt = 0.0
        for t in range(n):
            mine = cand[t] and laser[t] == li and not retry[t]
            tot += sg0[t] if mine else 0.0
            cnt += 1.0 if mine else 0.0
        if cnt > 0.0 and tot >= PAIR_MIN_SIGMA * cnt:
            blurred = True
            for t in range(n):
                if cand[t] and laser[t] == li:
                    sg0[t] = max(sg0[t], tot / cnt)
    # (the fits start from that width, on a window of that width inside the image)
    fit_me = zeros(n, np.bool_)
    any_fit = False
    for t in range(n):
        nb = nb0[t]
        s_nb = sg0[nb] if nb >= 0 else 0.0
        fit_me[t] = glowing[t] or (
            cand[t]
            and nb >= 0
            and abs(vv[nb] - vv[t]) < PAIR_SIGMAS * (sg0[t] + s_nb)
            and min(sg0[t], s_nb) >= PAIR_MIN_SIGMA
        )
        if fit_me[t] and blurred:
            hw[t] = min(int(math.ceil(WINDOW_SIGMAS * sg0[t])) + 2, MAX_HALF_PX)  # noqa: RUF046
            fit_me[t] = rc[t] - hw[t] >= 0 and rc[t] + hw[t] <= h - 1
        any_fit |= fit_me[t] and not retry[t]
    if not any_fit:  # (clear water): the common fits stand, and the rounds' tables are not even filled
        # (the refused points are fitted only where the common fits' points are: clear water keeps its cost)
        return vv.copy(), sig.copy(), zeros(n, np.bool_), amp.copy(), lnoise.copy()
    # the step model; then the ramp where the glow is strong enough to tell its ramp from the stripe (the pooled step
    # over the stripe's peak), with the other stripes where the step model put them
    reach_rows = np.maximum(hw, 2 * kt + 1 + TRIGGER_ROWS)  # where another stripe is looked for
    # the rounds' options as run-time values built in place (a literal argument compiles a function once per value)
    ramp_on = arange(2, np.bool_)  # False, True
    n_rounds = full(3, HOLD_ROUNDS, np.int64)
    n_rounds[0], n_rounds[1] = 1, ROUNDS
    # the glow's shape: the sheet's, with the water's attenuation one number for the frame (:func:`_attenuation`)
    d_rc = full(n, 1.0, np.float64)
    k_pt = zeros(n, np.float64)
    for t in range(n):
        if fit_me[t]:
            d_rc[t] = side[t] * (rc[t] - vanish[laser[t], cols[t]])
            k_pt[t] = path_k[laser[t], cols[t]] if d_rc[t] > 1.0 else 0.0
    s_cnt = 0
    for t in range(n):
        s_cnt += fit_me[t] and glowing[t] and not retry[t]
    alpha, s_w = 0.0, 0.0
    carried = s_cnt >= ALPHA_SAMPLE and water[2] < WATER_FRAMES
    if s_cnt >= ALPHA_SAMPLE:  # (a sample's worth of glowing points)
        if carried:  # told a few frames ago: the water changes slowly
            alpha, s_w = water[0], water[1]
        else:
            told = glowing & ~retry  # (the common fits' points tell the water)
            alpha, s_w = _attenuation(
                image, cols, laser, at, vv, sig, amp, nb_ok, nb0, fit_me, told, side, rc, hw, reach_rows, sg0,
                lo_sig, max_sig, sat_dn, ramp_on[0], n_rounds, d_rc, k_pt,
            )  # fmt: skip
            if s_w < SHAPE_MIN_SIGMA:  # a sharp stripe: the step and its ramp
                alpha, s_w = 0.0, 0.0
            water[0] = alpha
            water[1] = s_w
            water[2] = 0.0
        water[2] += 1.0
    kap_k = alpha * k_pt
    # the glowing points fitted with the stripe's width held at the sample's (the blur is the water's: a free width
    # trades itself for the glow's growth at the dim columns), the others (stripes beside another's) free
    hold = zeros(n, np.bool_)
    if s_w > 0.0:
        for t in range(n):
            if fit_me[t] and glowing[t]:
                hw_t = min(int(math.ceil(WINDOW_SIGMAS * s_w)) + 2, MAX_HALF_PX)  # noqa: RUF046
                if rc[t] - hw_t >= 0 and rc[t] + hw_t <= h - 1:
                    hold[t] = True
                    sg0[t] = s_w
                    hw[t] = hw_t
    free = fit_me & ~hold
    no_rho = zeros(n, np.float64)
    # a weak glow's step held at its stripe's proportion, told at a sample (only on stripes that glow all along: a
    # clutter's few glowing columns keep the free step)
    rho_0 = no_rho
    if HELD_STEP:
        # the share told with the water is carried with it (its sample's fits cost more than the held fits save)
        shares = water[3:]
        fresh = True
        if carried:
            rho_0, fresh = carried_share(shares, cand, glowing, laser, fit_me, n_l)
        if fresh:
            told_sh = full(n_l, UNTOLD, np.float64)
            rho_0 = held_share(
                image, cols, laser, at, vv, sig, nb_ok, nb0, fit_me, glowing, retry, hold, cand, side, rc, hw,
                reach_rows, sg0, lo_sig, max_sig, sat_dn, ramp_on[0], n_rounds, d_rc, kap_k, s_w, told_sh,
            )  # fmt: skip
            if s_cnt >= ALPHA_SAMPLE and not carried:  # (told with the water on this frame)
                for li in range(shares.size):
                    shares[li] = told_sh[li] if li < n_l else UNTOLD
    v0, s0, f0, rss0, _d0, st0 = fit_rounds(
        image, cols, laser, at, vv, sig, vv, sig, nb_ok, nb0, free, glowing, side, rc, hw, reach_rows, sg0, lo_sig,
        max_sig, sat_dn, ramp_on[0], n_rounds[1], d_rc, kap_k, rho_0,
    )  # fmt: skip
    if s_w > 0.0:
        # (the other stripes with the held width from the first round: a common fit's width of a dim column is noise)
        s_in = sig.copy()
        for t in range(n):
            if hold[t]:
                s_in[t] = s_w
        v_h, s_h, f_h, rss_h, d_h, st_h = fit_rounds(
            image, cols, laser, at, vv, sig, vv, s_in, nb_ok, nb0, hold, glowing, side, rc, hw, reach_rows, sg0,
            s_w, s_w, sat_dn, ramp_on[0], n_rounds[2], d_rc, kap_k, rho_0,
        )  # fmt: skip
        for t in range(n):
            if hold[t]:
                f0[t] = f_h[t]
                v0[t] = v_h[t]
                s0[t] = s_h[t]
                rss0[t] = rss_h[t]
                _d0[t] = d_h[t]
                st0[0, t] = st_h[0, t]
                st0[1, t] = st_h[1, t]
    strong = zeros(n, np.bool_)
    for t in range(n):
        if not glowing[t]:
            continue
        a_sum = 0.0
        g_sum = 0.0
        for cc in range(max(cols[t] - POOL_COLS, 0), min(cols[t] + POOL_COLS + 1, w)):
            j = at[laser[t], cc]
            if j >= 0 and f0[j] and glowing[j]:
                a_sum += st0[0, j]
                g_sum += st0[1, j]
        strong[t] = a_sum > 0.0 and g_sum >= RAMP_MIN_STEP * a_sum
    # the ramp's F test, first per stretch: the ramp fitted at the strong points of every RAMP_EVERY-th column (both
    # lasers' points of a column together: close stripes are fitted in pairs); then at every strong point whose
    # stretch's sampled F statistic comes within RAMP_MARGIN of the bar, and taken where the F statistic pooled over
    # all of them passes it (none strong, as beside another laser's stripe without a glow: the step model stands)
    take = zeros(n, np.bool_)
    v3, s3, rss3, dof3, _st3 = v0, s0, rss0, _d0, st0
    if strong.any() and alpha <= 0.0:  # (the sheet's shape, where it is known, is the glow's growth)
        sample = zeros(n, np.bool_)
        for t in range(n):
            sample[t] = strong[t] and cols[t] % RAMP_EVERY == 0
        # (the sampled test in one round, with the other stripes where the step model put them: it decides only
        # which stretches the ramp is fitted along, and its further rounds were a fifth of the ramp's fits at 2 m)
        _v2, _s2, f2, rss2, dof2, _st2 = fit_rounds(
            image, cols, laser, at, vv, sig, v0, s0, nb_ok, nb0, sample, glowing, side, rc, hw, reach_rows, sg0,
            lo_sig, max_sig, sat_dn, ramp_on[1], n_rounds[0], d_rc, kap_k, no_rho,
        )  # fmt: skip
        maybe = strong & (
            _pooled_f(cols, laser, at, strong, glowing, f0, f2, rss0, rss2, dof2) > RAMP_MARGIN * F_SELECT
        )
        v3, s3, f3, rss3, dof3, _st3 = fit_rounds(
            image, cols, laser, at, vv, sig, v0, s0, nb_ok, nb0, maybe, glowing, side, rc, hw, reach_rows, sg0,
            lo_sig, max_sig, sat_dn, ramp_on[1], n_rounds[1], d_rc, kap_k, no_rho,
        )  # fmt: skip
        take = f3 & (_pooled_f(cols, laser, at, f3, glowing, f0, f3, rss0, rss3, dof3) > F_SELECT)
    v_out = v0
    s_out = s0
    fitted = f0.copy()
    a_out = amp.copy()
    n_out = lnoise.copy()
    for t in range(n):
        if not (take[t] or f0[t]):
            continue
        rs, df = rss0[t], _d0[t]
        a_out[t] = st0[0, t]
        if take[t]:
            v_out[t] = v3[t]
            s_out[t] = s3[t]
            fitted[t] = True
            rs, df = rss3[t], dof3[t]
            a_out[t] = _st3[0, t]
        n_out[t] = _residual_noise(rs, df, lnoise[t])
    return v_out, s_out, fitted, a_out, n_out


@callee
def _attenuation(  # type: ignore[no-untyped-def]
    image, cols, laser, at, vv, sig, amp, nb_ok, nb0, fit_me, glowing, side, rc, hw, reach_rows, sg0, lo_sig,
    max_sig, sat_dn, ramp, n_rounds, d_rc, k_pt,
):
    """``(alpha, sigma)``: the water's attenuation (1/m) for the glow's shape and the stripe's width, px, for the
    frame (0, 0: none can be told; a plain step, each point's own width). Told at a sample: on each laser's stripe the
    strongest glowing point of each of :data:`ALPHA_SAMPLE` stretches of its glowing columns, on windows of at least
    :data:`ALPHA_HALF_PX` rows either side (a short window trades the glow's growth for the width). There the step
    model is fitted with each of :data:`ALPHA_GRID` (``n_rounds[1]`` rounds, so that close pairs settle, then one
    more from there: a fit's residual sum is its last step's start), compared over the points fitted at every
    attenuation that most of them fit at (too strong a growth fails the fits) by the sum of the logarithms of their
    residual sums (a particle's column weighs no more than another); the least, refined at the midpoints either side
    and by a parabola through the least and its neighbours. The width is the median of the sample's fits with it."""
    n = cols.size
    h = image.shape[0]
    n_l = at.shape[0]
    w = at.shape[1]
    sample = zeros(n, np.bool_)
    elig = zeros(n, np.bool_)
    hw = hw.copy()
    n_s = np.int64(0)  # (not the literal 0: numba would type retell's call for it too, a second compile)
    for li in range(n_l):
        m = 0
        for cc in range(w):
            t = at[li, cc]
            if t >= 0 and fit_me[t] and glowing[t] and k_pt[t] > 0.0:
                h_t = max(hw[t], ALPHA_HALF_PX)
                elig[t] = rc[t] - h_t >= 0 and rc[t] + h_t <= h - 1
                m += elig[t]
        if m == 0:
            continue
        k = 0
        best = -1
        b_prev = 0
        for cc in range(w):
            t = at[li, cc]
            if t < 0 or not elig[t]:
                continue
            bin_k = k * ALPHA_SAMPLE // m
            if bin_k != b_prev and best >= 0:
                sample[best] = True
                best = -1
            b_prev = bin_k
            if best < 0 or amp[t] > amp[best]:
                best = t
            k += 1
        if best >= 0:
            sample[best] = True
    for t in range(n):
        if sample[t]:
            hw[t] = max(hw[t], ALPHA_HALF_PX)
            n_s += 1
    if n_s == 0:
        return 0.0, 0.0
    n_a = len(ALPHA_GRID)
    grid = empty(n_a, np.float64)
    for i in range(n_a):
        grid[i] = ALPHA_GRID[i]
    score_a, fit_a, use = _alpha_fits(
        grid, image, cols, laser, at, vv, sig, nb_ok, nb0, sample, n_s, glowing, side, rc, hw, reach_rows, sg0,
        lo_sig, max_sig, sat_dn, ramp, n_rounds, d_rc, k_pt,
    )  # fmt: skip
    # the least of the summed log residuals, finer at its parabola's vertex (retell refines it)
    alpha = least(grid, sample_total(score_a, fit_a, use, sample), use)
    if math.isnan(alpha):
        return 0.0, 0.0
    # the stripe's width: the sample fitted with that attenuation
    _v, s1, f1, _r, _d, st1 = fit_rounds(
        image, cols, laser, at, vv, sig, vv, sig, nb_ok, nb0, sample, glowing, side, rc, hw, reach_rows, sg0, lo_sig,
        max_sig, sat_dn, ramp, n_rounds[1], d_rc, alpha * k_pt, 0.0 * d_rc,
    )  # fmt: skip
    n_f = 0
    for t in range(n):
        n_f += f1[t] and st1[0, t] > 0.0
    if alpha <= 0.0 or n_f < 16:
        return alpha, 0.0
    pool = empty(n_f, np.float64)
    frac = empty(n_f, np.float64)
    k = 0
    for t in range(n):
        if f1[t] and st1[0, t] > 0.0:
            pool[k] = s1[t]
            frac[k] = st1[1, t] / st1[0, t]
            k += 1
    if median(frac) < SHAPE_MIN_STEP:  # a weak glow: the step model reads the wall better
        return 0.0, 0.0
    s_w = float(median(pool))
    hw_p = min(int(math.ceil(WINDOW_SIGMAS * s_w)) + 2, MAX_HALF_PX)  # noqa: RUF046
    return retell(
        image, cols, laser, at, vv, sig, nb_ok, nb0, fit_me, glowing, side, rc, hw, reach_rows, sg0, lo_sig, max_sig,
        sat_dn, ramp, n_rounds, d_rc, k_pt, sample, n_s, alpha, s_w, hw_p, ALPHA_SHARE,
    )  # fmt: skip


@inline
def _alpha_fits(  # type: ignore[no-untyped-def]
    grid, image, cols, laser, at, vv, sig, nb_ok, nb0, sample, n_s, glowing, side, rc, hw, reach_rows, sg0, lo_sig,
    max_sig, sat_dn, ramp, n_rounds, d_rc, k_pt,
):
    """:func:`_attenuation`'s fits at each attenuation in ``grid``: ``(score, fitted, use)``, (A, N) each and (A,):
    the log residual sums of the fits taken (0 elsewhere), the fits taken and whether most of the sample fits at
    that attenuation."""
    n = cols.size
    n_a = grid.size
    score_a = zeros((n_a, n), np.float64)
    fit_a = zeros((n_a, n), np.bool_)
    use = zeros(n_a, np.bool_)
    for i in range(n_a):
        kap = grid[i] * k_pt
        v1, s1, f1, _r, _d, _st = fit_rounds(
            image, cols, laser, at, vv, sig, vv, sig, nb_ok, nb0, sample, glowing, side, rc, hw, reach_rows, sg0,
            lo_sig, max_sig, sat_dn, ramp, n_rounds[1], d_rc, kap, 0.0 * d_rc,
        )  # fmt: skip
        for t in range(n):
            if not f1[t]:
                v1[t] = vv[t]
                s1[t] = sg0[t]
        _v, _s, f2, rss, _d, _st = fit_rounds(
            image, cols, laser, at, v1, sig, v1, s1, nb_ok, nb0, sample & f1, glowing, side, rc, hw, reach_rows, s1,
            lo_sig, max_sig, sat_dn, ramp, n_rounds[0], d_rc, kap, 0.0 * d_rc,
        )  # fmt: skip
        n_f = 0
        for t in range(n):
            fit_a[i, t] = sample[t] and f1[t] and f2[t] and rss[t] > 0.0
            if fit_a[i, t]:
                score_a[i, t] = math.log(rss[t])
            n_f += fit_a[i, t]
        use[i] = n_f >= ALPHA_SHARE * n_s
    return score_a, fit_a, use


@inline
def _residual_noise(rss, dof, fallback):  # type: ignore[no-untyped-def]
    """A fit's residual noise, DN: ``sqrt(rss / dof)``, ``fallback`` where that is not finite."""
    r = math.sqrt(rss / dof) if dof > 0.0 else np.nan
    return r if math.isfinite(r) else fallback


@njit
def _whole_stripe(glowing, cand, laser, n_l, diff, amp, noise_l, retry):  # type: ignore[no-untyped-def]
    """``glowing`` (N,) and all the candidates (``cand``) of each laser whose stripe shows the glow as a whole: a
    pool's worth of them show it, and their median green step (``diff``, DN) exceeds :data:`TRIGGER_FRAC` times their
    median amplitude (``amp``) and :data:`TRIGGER_SNR` times that median's noise (``noise_l`` (L,)), the candidates
    in ``retry`` (the common fit's refused, :func:`glow_refit`) left out of that test. The glow is the water's, along
    all the stripe in proportion to it; at its dim ends, and at most points of a weak glow, it does not show above the
    noise, and the common fit there read a pixel outward (docs/water-design.md, "The glow along the whole stripe")."""
    out = glowing.copy()
    n = cand.size
    d_m = empty(n, np.float64)  # the laser's candidates' steps and amplitudes, in order (loops: masks and fancy
    a_m = empty(n, np.float64)  # indexing compile numpy's broadcasting and gathers into every kernel linking this)
    for li in range(n_l):
        k = 0
        n_glow = 0
        for t in range(n):
            if cand[t] and laser[t] == li and not retry[t]:
                d_m[k] = diff[t]
                a_m[k] = amp[t]
                n_glow += glowing[t]
                k += 1
        if n_glow >= 2 * POOL_COLS + 1 and median(d_m[:k]) > max(
            TRIGGER_SNR * _pool_noise(noise_l[li], k), TRIGGER_FRAC * median(a_m[:k])
        ):
            for t in range(n):
                out[t] |= cand[t] and laser[t] == li
    return out


@callee
def _pooled_f(cols, laser, at, where, glowing, f0, f2, rss0, rss2, dof2):  # type: ignore[no-untyped-def]
    """At the points ``where`` (N,): the F statistic of the glow's ramp (its two parameters), pooled over the glowing
    points of the same laser within :data:`POOL_COLS` columns fitted with it (``f2``) and without (``f0``): the drop of
    the residual sum of squares per parameter over the residual variance with it; 0 where none is fitted."""
    n = cols.size
    w = at.shape[1]
    out = zeros(n, np.float64)
    for t in range(n):
        if not where[t]:
            continue
        d_rss = 0.0
        r2 = 0.0
        df2 = 0.0
        cnt = 0
        for cc in range(max(cols[t] - POOL_COLS, 0), min(cols[t] + POOL_COLS + 1, w)):
            j = at[laser[t], cc]
            if j >= 0 and f0[j] and f2[j] and glowing[j]:
                d_rss += rss0[j] - rss2[j]
                r2 += rss2[j]
                df2 += dof2[j]
                cnt += 1
        if cnt > 0:
            out[t] = d_rss / (2.0 * cnt) / (r2 / df2)
    return out
