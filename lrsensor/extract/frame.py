"""The compiled road: seven calls that extract (and triangulate) the stripes of one frame.

:func:`extract_frame` is the default extractor of :mod:`lrsensor.extract.subpixel`, whole, in seven compiled calls
(six on a clear frame):

- :func:`locate_candidates`:

  1. detection per laser in its band (:func:`.detect.detect_band`), the candidates of all lasers numbered as
     one row of virtual columns ``laser * width_d + column_d``;
  2. continuity (:func:`.chains.select_candidates`, :func:`.chains.expand_half`): one candidate per column;

- :func:`.geometry.max_fwhm_at`: the width limit of every point (the laser sheet's thickness at its depth; the
  points' triangulation and the widths, two calls);

- :func:`fit_points`:

  3. frame statistics (:func:`frame_profile_stats`: the typical sigma and clipped run, hence the fit window) and
     the sub-pixel fit of every point, one column-parallel fit for every kind of profile (:mod:`.fit`), then the
     neighbour refits where two lasers' stripes come close (:mod:`.refit`);

- :func:`refine_points` (:func:`glow_starts` and :func:`.glow.glow_refit`, two calls):

  4. the joint stripe-and-glow fits where a profile shows the laser sheet's glow (turbid water, :mod:`.glow`);

- :func:`finish_located`:

  5. gates, runs, smoothing and quality (:mod:`.finish`; through a port the smoothing's line fits run where a
     pinhole in the water at the camera centre would see the stripe's points);

- :func:`pool_ends` (where the glow stage ran):

  6. on the stripes the glow stage fitted, their dim ends beyond the long runs measured pooled along the stripe
     (:mod:`.pooled`);

- :func:`.geometry.triangulate_geo` and :func:`place_points`:

  7. with ``triangulate``: the body-frame points (:mod:`.geometry`; through the calibration's port when it has
     one) and the range-limit gate on camera depth.

The first two calls and the records they hand on (:class:`Picked`, :class:`Located`) are in
:mod:`.frame_locate` (steps 1-3, the compile's first part), and this module exports them; the rest is here.

Inputs: the image (H, W, 3) uint8 BGR, C-contiguous, and the settings records built once per (calibration,
configuration) in :mod:`lrsensor.extract.subpixel`. Outputs: pixel coordinates (M, 2), laser (M,), quality (M,),
body-frame points (M, 3) in metres (empty without ``triangulate``) and the band noise (L,) in DN.

Why these calls and not one, nor one per stage: numba compiles a kernel's callees first and then optimises and
generates machine code again for the caller's whole call tree, so a single frame call would compile every
stage again; the calls compile side by side in two processes (:mod:`lrsensor.extract.compile`: the
triangulation, which the width limits and the points both need, is a call of its own, compiled once, and so is
the glow stage, the largest call tree, which a kernel around it would compile again), and
their hand-overs
(:class:`Picked`, :class:`Located`, the points) cost microseconds in a frame of about a millisecond, where a
Python call per stage would cost as much again. The numpy reference
(:mod:`lrsensor.extract.reference`) implements the same algorithm readably for tests and for machines without
numba.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ._jit import empty, njit, zeros
from .finish import BLURRED_SIGMA_PX, finish_points

# (the first part of the frame, steps 1-3, and its records: exported here, where the compile and tests find them)
from .frame_locate import FWHM_PER_SIGMA as FWHM_PER_SIGMA
from .frame_locate import STATS_POINTS as STATS_POINTS
from .frame_locate import Located as Located
from .frame_locate import Picked as Picked
from .frame_locate import fit_points as fit_points
from .frame_locate import frame_profile_stats as frame_profile_stats
from .frame_locate import locate_candidates as locate_candidates
from .frame_locate import no_points as no_points
from .geometry import max_fwhm_at, triangulate_geo
from .glow import glow_refit, new_water
from .pooled import extend_ends, glowing_widths, shaped_growth
from .settings import Bands, Geometry, Settings

#: The points whose profile the common fit refused (no curved three-point start, a width outside the limits, the
#: centre away from the peak: noise at a dim column of a blurred stripe) enter the glow stage at their candidate row
#: with the frame's typical width, and are kept where their joint fit is taken (docs/water-design.md); on blurred frames
#: only (the typical sigma at least :data:`~lrsensor.extract.finish.BLURRED_SIGMA_PX`: forward scatter), where the
#: start's three samples 0.8 sigma apart read the noise of a dim column. Clear water's few refusals (0-8 a frame on
#: the named scenes) are left as they were, and its frames keep their cost.
RETRY_REFUSED = True
#: A glowing stripe's dim ends beyond its long runs are measured pooled along it (:mod:`.pooled`; docs/water-design.md).
POOLED_ENDS = True


@njit
def glow_starts(p):  # type: ignore[no-untyped-def]
    """The starts of step 4 of :func:`extract_frame` (:func:`lrsensor.extract.glow.glow_refit`, a call of its own) for
    the :class:`Located` points ``p``: the points the common fit refused enter at their candidate row with the frame's
    width (see :data:`RETRY_REFUSED`).

    Returns:
        ``(centre_row, sigma, ok, retry)``: (N,) each, the fits' own arrays where no point is retried (clear water
        refuses few or none: no copies), and the points retried.
    """
    n = p.cols.size
    res = p.fits
    vv, sig, sat, ok = res.centre, res.sigma, res.saturated, res.ok
    retry = zeros(n, np.bool_)
    n_retry = 0
    if RETRY_REFUSED and p.sigma_px >= BLURRED_SIGMA_PX:
        for t in range(n):
            retry[t] = not ok[t] and not sat[t]
            n_retry += retry[t]
    if n_retry == 0:
        return vv, sig, ok, retry
    v_in = vv.copy()
    s_in = sig.copy()
    ok_in = ok.copy()
    for t in range(n):
        if retry[t]:
            v_in[t] = float(p.rows[t])
            s_in[t] = p.sigma_px
            ok_in[t] = True
    return v_in, s_in, ok_in, retry


@njit
def finish_located(p, glow, w, s, geo):  # type: ignore[no-untyped-def]
    """The end of step 4 of :func:`extract_frame` and step 5 (gates, smoothing, quality) of the :class:`Located`
    points ``p`` of an image ``w`` px wide.

    Args:
        glow: :func:`lrsensor.extract.glow.glow_refit`'s ``(centre_row, sigma, fitted, amplitude, noise)`` (N,) each
            and the points it retried (N,) (:func:`glow_starts`); where it did not run (``s.glow_fit`` False), the
            fits' own centres, sigmas, amplitudes and noise, nothing fitted and nothing retried.

    Returns:
        ``(u, v, laser, quality)``: (M,) each, the points' pixel columns and rows, laser and quality in [0, 1].
    """
    n = p.cols.size
    if n == 0:
        return empty(0, np.float64), empty(0, np.float64), empty(0, np.int64), empty(0, np.float64)
    res = p.fits
    vv, amp, sig, ok = res.centre, res.amplitude, res.sigma, res.ok
    v_g, s_g, own, a_g, n_g, retry = glow
    # the gate takes the joint fit's own amplitude and residual noise where it is taken (the common fit's line
    # takes part of the glow's step as a slope)
    for t in range(n):
        vv[t] = v_g[t]
        amp[t] = a_g[t]
        res.local_noise[t] = n_g[t]
    for t in range(n):  # a refused point only where its joint fit is taken
        if retry[t] and own[t]:
            ok[t] = True
            sig[t] = s_g[t]
        elif retry[t]:  # (the glow stage hands back its start, the candidate row)
            vv[t] = np.nan
    # gates, runs, smoothing, quality
    return finish_points(p.col_v, p.laser, res, p.chain, p.chain_len, p.noise, w, s, geo, own)


def refine_points(
    image: NDArray[np.uint8], p: Located, glow_side: IntArray, s: Settings, geo: Geometry, water: FloatArray
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_], FloatArray, FloatArray, NDArray[np.bool_]]:
    """Step 4 of :func:`extract_frame`: the joint stripe-and-glow fits of the :class:`Located` points ``p``
    (:func:`lrsensor.extract.glow.glow_refit`, from :func:`glow_starts`; ``water`` read and updated), for
    :func:`finish_located`. A Python call of the kernel, not a kernel: a kernel that called it would compile its
    whole call tree again into its own machine code (:mod:`lrsensor.extract.compile`)."""
    res = p.fits
    if not s.glow_fit:  # (nothing fitted, nothing retried)
        n = p.cols.size
        return res.centre, res.sigma, np.zeros(n, np.bool_), res.amplitude, res.local_noise, np.zeros(n, np.bool_)
    if RETRY_REFUSED and p.sigma_px >= BLURRED_SIGMA_PX:
        v_in, s_in, ok_in, retry = glow_starts(p)
    else:  # (a sharp frame retries none: no call)
        v_in, s_in, ok_in, retry = res.centre, res.sigma, res.ok, np.zeros(p.cols.size, np.bool_)
    v_g, s_g, own, a_g, n_g = glow_refit(
        image, p.cols, p.laser, glow_side, v_in, res.amplitude, s_in, res.saturated, ok_in, res.local_noise, p.noise,
        s.min_fwhm_px / FWHM_PER_SIGMA, s.max_sigma_px, s.saturation_dn, s.min_green_ratio, geo.glow_vanish,
        geo.glow_path, water, retry,
    )  # fmt: skip
    return v_g, s_g, own, a_g, n_g, retry


@njit
def pool_ends(image, u, v, laser, quality, glow_side, p_laser, own, sigma, vanish, path, water):  # type: ignore[no-untyped-def]
    """Step 6 of :func:`extract_frame`: the points ``(u, v, laser, quality)`` (M,) of :func:`finish_located` with
    the dim ends of the stripes the glow stage fitted measured pooled along them (:mod:`.pooled`); ``own`` (N,) the
    :class:`Located` points (laser ``p_laser`` (N,)) whose joint fit was taken, ``sigma`` (N,) their widths, px;
    ``vanish``, ``path`` (L, W) the glow's geometry and ``water`` the glow stage's record
    (:func:`.pooled.shaped_growth`).
    A call of its own: :func:`finish_located` does not link the pooled fits' tree, and a frame where the glow stage
    took no fit (clear water) does not call it.

    Returns:
        ``(u, v, laser, quality)`` (K,) each, as :func:`.pooled.extend_ends`.
    """
    use, sig_l = glowing_widths(p_laser, own, sigma, glow_side.shape[0])
    return extend_ends(image, u, v, laser, quality, glow_side, use, sig_l, vanish, shaped_growth(water, path))


@njit
def place_points(u, v, laser, quality, xyz, s, geo, triangulate):  # type: ignore[no-untyped-def]
    """Step 7 of :func:`extract_frame`: with ``triangulate`` the range-limit gate on the camera depth of the
    body-frame points ``xyz`` (M, 3) (:func:`.geometry.triangulate_geo` of the pixels ``(u, v)`` (M,) of ``laser``
    (M,); NaN points dropped), else the pixels as they are (``xyz`` unused).

    Returns:
        ``(uv, laser, quality, xyz)``: the kept points' pixel coordinates (K, 2), laser (K,), quality (K,) and
        body-frame points (K, 3), metres ((0, 3) without ``triangulate``).
    """
    m = u.size
    if not triangulate:
        uv = empty((m, 2), np.float64)
        for t in range(m):
            uv[t, 0] = u[t]
            uv[t, 1] = v[t]
        return uv, laser, quality, empty((0, 3), np.float64)
    r_z = geo.R_cam_body[2]
    keep = empty(m, np.bool_)
    kept = 0
    for t in range(m):
        depth = xyz[t, 0] * r_z[0] + xyz[t, 1] * r_z[1] + xyz[t, 2] * r_z[2] + geo.cam_z_offset_m
        keep[t] = depth >= s.min_range_m and depth <= s.max_range_m  # NaN fails both
        kept += keep[t]
    uv = empty((kept, 2), np.float64)
    if kept == m:
        for t in range(m):
            uv[t, 0] = u[t]
            uv[t, 1] = v[t]
        return uv, laser, quality, xyz
    xyz_k = empty((kept, 3), np.float64)
    laser_k = empty(kept, np.int64)
    quality_k = empty(kept, np.float64)
    j = 0
    for t in range(m):
        if keep[t]:
            uv[j, 0] = u[t]
            uv[j, 1] = v[t]
            for a in range(3):
                xyz_k[j, a] = xyz[t, a]
            laser_k[j] = laser[t]
            quality_k[j] = quality[t]
            j += 1
    return uv, laser_k, quality_k, xyz_k


FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
#: The points :func:`place_points` gets without ``triangulate`` (not read).
_NO_XYZ = empty((0, 3), np.float64)


def extract_frame(
    image: NDArray[np.uint8],
    bands: Bands,
    s: Settings,
    geo: Geometry,
    triangulate: bool,
    water: FloatArray | None = None,
) -> tuple[FloatArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """The whole default extractor on one frame in six compiled calls (see the module documentation).

    Args:
        image: (H, W, 3) uint8 BGR, C-contiguous.
        bands: :class:`~lrsensor.extract.settings.Bands`; s: :class:`~lrsensor.extract.settings.Settings`;
            geo: :class:`~lrsensor.extract.settings.Geometry`.
        triangulate: also triangulate the points and keep only those whose camera depth is within
            ``[s.min_range_m, s.max_range_m]`` (NaN points dropped); else no points and no depth gate.
        water: the turbid water's attenuation and width as a camera's earlier frames told them, read and updated
            (:func:`lrsensor.extract.glow.glow_refit`; None: told on this frame alone).

    Returns:
        ``(uv, laser, quality, xyz, noise)``: the kept points' pixel coordinates (M, 2), laser (M,), quality (M,)
        and body-frame points (M, 3), metres ((0, 3) without ``triangulate``), and the band noise (L,), DN.
    """
    picked = locate_candidates(image, bands, s)
    # the width limit of every point (the refits need any of them), compiled beside the triangulation
    mfw = max_fwhm_at(picked.cols, picked.rows, picked.laser, FWHM_PER_SIGMA * s.max_sigma_px, s.max_sheet_mm, geo)
    located = fit_points(image, picked, mfw, s)
    w_rec = new_water() if water is None else water
    glow = refine_points(image, located, bands.glow_side, s, geo, w_rec)
    u, v, laser, quality = finish_located(located, glow, image.shape[1], s, geo)
    if POOLED_ENDS and glow[2].any():  # 6. a glowing stripe's dim ends, measured pooled along it (clear water: none)
        u, v, laser, quality = pool_ends(
            image, u, v, laser, quality, bands.glow_side, located.laser, glow[2], glow[1], geo.glow_vanish,
            geo.glow_path, w_rec,
        )  # fmt: skip
    # the points in a call of their own: a kernel that triangulated would compile the triangulation again
    xyz = triangulate_geo(u, v, laser, geo) if triangulate else _NO_XYZ
    uv, laser, quality, xyz = place_points(u, v, laser, quality, xyz, s, geo, triangulate)
    return uv, laser, quality, xyz, located.noise
