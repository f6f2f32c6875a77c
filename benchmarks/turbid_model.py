"""An independent model of the two laser stripes in turbid water, written from the physics (issue 26, item 2).

    from benchmarks.turbid_model import Turbid, render
    frame = render(Turbid(distance_m=1.0, glow_step=0.3, blur_px=2.0, seed=1))
    frame.image        # (1080, 1920, 3) uint8 BGR, what the camera delivers
    frame.rows         # (2, 1920) true stripe row per laser (0 top, 1 bottom) and column, NaN where none
    frame.range_m      # (2, 1920) true range along the optical axis (body x) of that stripe point, metres
    frame.visible      # (2, 1920) columns whose noise-free stripe peak is >= 3x the noise there

Nothing here comes from :mod:`lrsensor.sim`: the only thing taken from the product is the paper's nominal
calibration (:meth:`lrsensor.Calibration.paper`), and the geometry is computed here, as in
``benchmarks/bench_foreign_render.py``.

Geometry (body frame: x forward, y starboard, z down; camera at the origin with the default mounting, so a body
point (x, y, z) images at ``u = cx + fx y / x``, ``v = cy + fy z / x``). Laser ``L`` (0 top, 1 bottom) is a fan
in the plane ``z = z_L`` with ``z_L = -c`` (top) or ``+c`` (bottom), ``c = b / 2``, fanning out from
``(0, 0, z_L)`` uniformly in angle over the image's width. The wall is ``cos(a) x + sin(a) y = d`` (a tilt ``a``
about body z). In column ``u`` (``xn = (u - cx) / fx``) the wall lies at range ``x_w = d / (cos a + sin a xn)``
and the stripe's true row is ``v_t = cy + fy z_L / x_w`` (exact: the sheet's mid-plane meets the wall there).

The stripe (wall, Lambertian). The sheet has a Gaussian thickness profile of standard deviation ``sigma_sheet``
(m). At the wall point ``(x_w, y_w, z_L)`` at distance ``r_w`` from the laser and ``R_w`` from the camera, with
incidence cosine ``cos i = d / r_w`` (in the sheet's plane), the wall's radiance at the sheet's centre is
``L_s ~ cos(i) exp(-alpha (r_w + R_w)) / (r_w sigma_sheet)``: the fan's power per unit arc length falls as
``1 / r``, the beam and the returning light are attenuated (``alpha``, 1/m), and the sheet's z profile is not
foreshortened on a wall tilted about z. It images as a Gaussian across the rows of standard deviation
``sigma_v = sigma_sheet fy / x_w`` (px) centred on ``v_t``.

The glow (single scattering by the water inside the sheet). A camera ray through ``(u, v)`` on the laser's side
of the image centre meets the sheet's plane at range ``x(v) = fy z_L / (v - cy)``, i.e. at
``(x, x xn, z_L)``, at distance ``r = x sqrt(1 + xn^2)`` from the laser and ``R = sqrt(r^2 + c^2)`` from the
camera. The ray crosses the sheet's thickness along a path ``R / c`` times the thickness (``c / R`` is the cosine
between the ray and the sheet's normal), so the radiance it collects is

    L_g(u, v) ~ p(theta) * exp(-alpha r) / r * (R / c) * exp(-alpha R)

with ``p`` the Henyey-Greenstein phase function (``g = 0.9``, ocean water) at the scattering angle ``theta``
between the laser's ray and the way back to the camera (``cos theta = -r / R``, close to backscatter). The
same law follows from the sheet's area per pixel (``dx/dv = x^2 / (fy c)`` metres per row times ``x / fx`` per
column) and the ``1 / R^2`` of the light returning to the camera. The sheet exists only in front of the wall,
so the glow covers the rows from the stripe OUTWARD (away from the image centre: above the top stripe, below the
bottom one) and ENDS at the stripe: a thick sheet is cut by the wall along its own Gaussian profile, so the
edge is ``Phi(s (v - v_t) / sigma_v)`` (``s = -1`` top, ``+1`` bottom), whose 50 % point is exactly ``v_t``.
Going outward, the glow brightens as ``exp(2 alpha (x_w - x))`` (shorter paths) and, within ~c of the port,
by ``R / r`` and the phase function.

Amplitudes. The camera's exposure is set on the stripe: the blurred stripe's green peak in the image's centre
column is ``peak_dn``; across the columns the stripe follows ``L_s`` (dimmer at the sides: oblique, further,
more attenuated). ``glow_step`` sets the scattering coefficient: by default per column, so that the glow's
unblurred value at its edge is ``glow_step`` times that column's blurred stripe peak (the continuous Gaussian's
peak, before the pixels integrate it), and one cell of a benchmark is one glow step. The ratio is taken
against the blurred peak because that is what a profile in the image shows: the glow is a plateau that the
blur hardly lowers, the thin stripe's peak it lowers by ``sigma_v / sqrt(sigma_v^2 + blur^2)``. With
``step_per_column=False`` one coefficient holds for the whole frame, set so that the centre column has the
step, and the step then grows towards the image's sides as physics has it (the stripe fades there with
``cos(i) / r_w`` and the glow does not): about 1.25x at ``|xn| = 0.5`` and 4x at the image's edges on a
perpendicular wall. Per column, the columns beyond 5 m, or whose rays miss the wall, take the nearest such
column's coefficient (their stripe is not visible, their glow stays plausible).

Forward scatter blurs the stripe and the glow with an isotropic Gaussian of ``blur_px`` (a real forward-scatter
PSF also has long wings; they add a wide symmetric halo, which moves no centre). Rendering is exact to well
under 0.01 px: the stripe (Gaussian blurred by a Gaussian) is integrated over each pixel row analytically; the
glow is integrated analytically over sub-rows of 1/4 px (its edge term exactly, its smooth factor at the
sub-row's centre), blurred there, then summed over each pixel's four sub-rows (optics before the pixels, a
camera's order). Columns are sampled at their centres: on a planar wall the stripe is a straight line, so
integrating across a column moves no centre.

Background and sensor. A veil (ambient light scattered by the water) of ``veil_dn`` at the image centre that
changes linearly by ``veil_slope`` (relative) from the bottom edge to the top edge, times ``1 + 0.1 f`` with
``f`` a smooth random field of unit standard deviation (correlated over ~60 px). Particles:
``particles_per_mpx`` per megapixel, a quarter of them inside a sheet (backscatter speckle: only on the glow's
side of a stripe, ``Exp(2)`` times the local glow, laser coloured, sigma 0.5-1.2 px) and the rest marine snow
lit by ambient light (anywhere, ``Exp(0.5)`` times the local veil, sigma 0.5-1.5 px). Colours (B, G, R): the
520 nm laser (0.30, 1.00, 0.08) (green dominant, some cross-talk into blue), the water's veil (0.80, 1.00,
0.40). Noise per channel: Gaussian with variance ``read_noise_dn^2 + S / electrons_per_dn`` (read + shot noise
at signal S, DN), then rounding to 8 bits and clipping at 0 and 255 (saturation is kept).

Visible columns: stripe in the image (``0 < v_t < H - 1``), range 0.2-5 m (the product's default limits), and a
noise-free green stripe peak (above what lies under it) of at least 3x the green noise at the stripe's row
(read, shot noise at the full noise-free signal there, and the 1/12 DN^2 of rounding).

Not modelled: multiple scattering beyond the forward-scatter blur (no widening of the sheet in the water),
the sheet's divergence in thickness, a fan that is not uniform in angle, a link between the glow's level and
the attenuation (both are free parameters), the wall's texture and its ambient lighting (the veil stands for
both), speckle of the wall, lens distortion and vignetting, a flat port (the camera is a pinhole in water),
Bayer demosaicing, JPEG, and any light of one laser reaching the other's stripe except through the veil.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from lrsensor import Calibration

#: Sub-rows per pixel row on which the glow is integrated and blurred.
SUB_ROWS = 4
#: Henyey-Greenstein asymmetry of ocean water (Petzold's measurements are fitted by g ~ 0.9).
PHASE_G = 0.9
#: Colours (B, G, R) of the 520 nm laser and of the water's veil, green = 1.
LASER_BGR = (0.30, 1.00, 0.08)
VEIL_BGR = (0.80, 1.00, 0.40)
#: Share of the particles that lie inside a laser sheet (backscatter speckle); the rest is marine snow.
SHEET_PARTICLE_SHARE = 0.25
#: Range limits of a "visible" column, metres (the product's default depth gate).
VISIBLE_RANGE_M = (0.2, 5.0)
#: A visible stripe peak is at least this many times the noise at its row.
VISIBLE_SNR = 3.0

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Turbid:
    """One turbid frame: a flat wall, both lasers, the water and the camera.

    Attributes:
        distance_m: the wall's distance along its normal from the camera, metres (0.5-3 in the benchmark).
        tilt_deg: the wall's tilt about body z, degrees (0: perpendicular to the optical axis).
        glow_step: the glow's unblurred value at its edge over the column's blurred stripe peak (0 = no glow).
        blur_px: forward-scatter blur, standard deviation in pixels (0 = none).
        peak_dn: blurred green stripe peak in the image's centre column, DN (the exposure).
        veil_dn: green veil at the image centre, DN.
        veil_slope: relative change of the veil from the bottom edge to the top edge (0.4: 20 % brighter at
            the top than at the centre).
        particles_per_mpx: particles per megapixel (a quarter in the sheets).
        attenuation_per_m: attenuation of the laser's light along its path and back, 1/m.
        read_noise_dn: read noise, DN (standard deviation).
        electrons_per_dn: conversion gain for shot noise, photo-electrons per DN.
        sheet_sigma_m: the sheet's thickness profile, standard deviation, metres.
        step_per_column: ``glow_step`` holds in every column (default); False: one scattering coefficient for
            the frame, set so that ``glow_step`` holds in the centre column (the step then grows towards the
            image's sides, where the stripe is dimmer and the glow is not).
        baseline_m: distance between the two lasers (each laser ``c = b / 2`` from the camera), metres.
        size: (width, height) in pixels.
        seed: seed of the veil's field, the particles and the noise.
    """

    distance_m: float = 1.0
    tilt_deg: float = 0.0
    glow_step: float = 0.3
    blur_px: float = 2.0
    peak_dn: float = 100.0
    veil_dn: float = 30.0
    veil_slope: float = 0.4
    particles_per_mpx: float = 150.0
    attenuation_per_m: float = 0.3
    read_noise_dn: float = 1.5
    electrons_per_dn: float = 8.0
    sheet_sigma_m: float = 0.0015
    step_per_column: bool = True
    baseline_m: float = 0.1
    size: tuple[int, int] = (1920, 1080)
    seed: int = 0

    def __post_init__(self) -> None:
        checks = {
            "distance_m": self.distance_m > 0,
            "tilt_deg": abs(self.tilt_deg) < 80,
            "glow_step": self.glow_step >= 0,
            "blur_px": self.blur_px >= 0,
            "peak_dn": self.peak_dn > 0,
            "veil_dn": self.veil_dn >= 0,
            "veil_slope": abs(self.veil_slope) < 2,
            "particles_per_mpx": self.particles_per_mpx >= 0,
            "attenuation_per_m": self.attenuation_per_m >= 0,
            "read_noise_dn": self.read_noise_dn >= 0,
            "electrons_per_dn": self.electrons_per_dn > 0,
            "sheet_sigma_m": self.sheet_sigma_m > 0,
            "baseline_m": self.baseline_m > 0,
            "size": min(self.size) >= 16,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            msg = f"Turbid: out of range: {', '.join(f'{k}={getattr(self, k)!r}' for k in bad)}"
            raise ValueError(msg)


@dataclass(frozen=True)
class TurbidFrame:
    """A rendered frame and its truth. Per-laser arrays have shape (2, W): index 0 the top laser, 1 the bottom.

    Attributes:
        image: (H, W, 3) uint8 BGR.
        calibration: the paper's calibration at this size and baseline (what the frame was rendered with).
        rows: true stripe row (sub-pixel, v down), NaN where the column sees no stripe.
        range_m: true range of the stripe point along the optical axis (body x), metres; inf where no wall.
        peak_dn: noise-free green stripe peak as the camera sees it (blurred, pixel-integrated), DN.
        noise_dn: green noise standard deviation at the stripe's row, DN.
        visible: the columns the stripe is visible in (see the module's docstring).
        layers: noise-free green layers (H, W) float32, DN: ``stripe``, ``glow``, ``veil``, ``speckle`` (particles
            in the sheets), ``snow`` (particles lit by ambient light).
    """

    image: NDArray[np.uint8]
    calibration: Calibration
    rows: FloatArray
    range_m: FloatArray
    peak_dn: FloatArray
    noise_dn: FloatArray
    visible: NDArray[np.bool_]
    layers: dict[str, NDArray[np.float32]] = field(repr=False)


def _erf(x: Any) -> Any:
    """Error function (Abramowitz-Stegun 7.1.26, |error| < 1.5e-7); works on arrays of any float dtype."""
    t = 1.0 / (1.0 + 0.3275911 * np.abs(x))
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    return np.sign(x) * (1.0 - poly * np.exp(-x * x))


def _cdf(t: Any) -> Any:
    """Standard normal CDF Phi(t)."""
    return 0.5 * (1.0 + _erf(t / math.sqrt(2.0)))


def _cdf_integral(t: Any) -> Any:
    """Antiderivative of Phi: A(t) = t Phi(t) + phi(t)."""
    return t * _cdf(t) + np.exp(-0.5 * t * t) / math.sqrt(2.0 * math.pi)


def _phase(cos_theta: Any) -> Any:
    """Henyey-Greenstein phase function (1/sr) at scattering angle theta."""
    g = PHASE_G
    return (1.0 - g * g) / (4.0 * math.pi * (1.0 + g * g - 2.0 * g * cos_theta) ** 1.5)


def _glow_terms(x: Any, xn: Any, c: float) -> tuple[Any, Any]:
    """The glow of the sheet point at range ``x`` (m) seen in column ``xn = (u - cx) / fx``, as (geometric
    factor ``p(theta) R / (r c)`` in 1/(sr m^2), path ``r + R`` in m): the radiance is ``factor *
    exp(-alpha path)`` times the fan's power per radian. ``x`` and ``xn`` broadcast; ``c`` is the laser's offset
    from the camera (m)."""
    r = x * np.sqrt(1.0 + xn * xn)  # from the laser, in the sheet's plane
    R = np.sqrt(r * r + c * c)  # from the camera
    return _phase(-r / R) * R / (r * c), r + R


def wall_geometry(t: Turbid, calibration: Calibration) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per column (W,): ``xn = (u - cx) / fx``; the wall's range ``x_w`` along the optical axis (m, inf where the
    column's rays miss the wall); the stripe's relative radiance without attenuation, ``cos(i) / r_w`` (1/m, 0
    where no wall); and the attenuation exponent ``alpha (r_w + R_w)`` of the stripe's light (inf where none)."""
    cam = calibration.camera
    a = math.radians(t.tilt_deg)
    c = t.baseline_m / 2.0
    xn = (np.arange(cam.width, dtype=float) - cam.cx) / cam.fx
    denom = math.cos(a) + math.sin(a) * xn
    hit = denom > 1e-9
    x_w = np.full(cam.width, np.inf)
    x_w[hit] = t.distance_m / denom[hit]
    r_w = np.where(hit, np.where(hit, x_w, 1.0) * np.sqrt(1.0 + xn * xn), 1.0)
    R_w = np.sqrt(r_w * r_w + c * c)
    rel = np.where(hit, (t.distance_m / r_w) / r_w, 0.0)
    att = np.where(hit, t.attenuation_per_m * (r_w + R_w), np.inf)
    return xn, x_w, rel, att


def _smooth_field(rng: np.random.Generator, W: int, H: int, cell_px: int = 60) -> NDArray[np.float32]:
    """A smooth random field of unit standard deviation, (H, W) float32, correlated over ~``cell_px``."""
    coarse = rng.normal(0.0, 1.0, (max(H // cell_px, 2) + 1, max(W // cell_px, 2) + 1))
    f = cv2.resize(coarse, (W, H), interpolation=cv2.INTER_CUBIC)
    return ((f - f.mean()) / max(float(f.std()), 1e-9)).astype(np.float32)


def _stamp(
    layer: NDArray[np.float32],
    u: FloatArray,
    v: FloatArray,
    amp: FloatArray,
    sigma: FloatArray,
) -> None:
    """Add Gaussian blobs (centre ``u, v`` px, peak ``amp`` DN, ``sigma`` px) to ``layer`` in place."""
    H, W = layer.shape
    k = np.arange(-4, 5)
    uu = np.rint(u)[:, None, None] + k[None, None, :]
    vv = np.rint(v)[:, None, None] + k[None, :, None]
    val = amp[:, None, None] * np.exp(
        -((uu - u[:, None, None]) ** 2 + (vv - v[:, None, None]) ** 2) / (2.0 * sigma[:, None, None] ** 2)
    )
    uu, vv, val = np.broadcast_arrays(uu, vv, val)
    ok = (uu >= 0) & (uu < W) & (vv >= 0) & (vv < H)
    np.add.at(layer, (vv[ok].astype(int), uu[ok].astype(int)), val[ok].astype(np.float32))


def render(t: Turbid) -> TurbidFrame:
    """Render one turbid frame and its truth (see :class:`TurbidFrame`)."""
    W, H = t.size
    cal = Calibration.paper(t.baseline_m, W, H)
    cam = cal.camera
    c = t.baseline_m / 2.0
    rng = np.random.default_rng(t.seed)
    xn, x_w, rel, att = wall_geometry(t, cal)
    hit = np.isfinite(x_w)
    cols = np.arange(W)

    # --- per laser and column: true row, the stripe's widths and its blurred peak (continuous, before pixels)
    signs = (-1.0, 1.0)  # z_L / c, and the side of the image centre the laser's stripe and glow lie on
    rows = np.full((2, W), np.nan)
    sigma_v = np.zeros(W)
    sigma_v[hit] = t.sheet_sigma_m * cam.fy / x_w[hit]  # px
    sigma_tot = np.sqrt(sigma_v**2 + t.blur_px**2)
    dilution = np.where(hit, sigma_v / np.maximum(sigma_tot, 1e-12), 0.0)  # the blur lowers a thin stripe's peak
    centre = round(cam.cx)
    if not hit[centre]:
        msg = f"Turbid: the wall is not in front of the image's centre column (tilt {t.tilt_deg} deg)"
        raise ValueError(msg)
    att_c = float(att[centre])
    # the exposure is set on the centre column: its blurred stripe peak is peak_dn; attenuation relative to it
    unatt = t.peak_dn * rel * dilution / (rel[centre] * dilution[centre])  # (W,) DN without the attenuation
    with np.errstate(over="ignore"):
        peak_cont = unatt * np.exp(att_c - att)  # (W,) DN
    for li, s in enumerate(signs):
        rows[li, hit] = cam.cy + cam.fy * s * c / x_w[hit]

    # --- the stripe layer: a Gaussian of sigma_tot integrated over each pixel row, exactly
    stripe = np.zeros((H, W), np.float32)
    half = math.ceil(8.0 * float(sigma_tot[hit].max())) + 2
    k = np.arange(-half, half + 1)[:, None]
    for li in (0, 1):
        ok = np.isfinite(rows[li]) & (peak_cont > 0)
        vt, st = rows[li][ok], sigma_tot[ok]
        rr = np.rint(vt)[None, :] + k  # (2 half + 1, n) pixel rows around the stripe
        area = _cdf((rr + 0.5 - vt) / st) - _cdf((rr - 0.5 - vt) / st)
        val = peak_cont[ok] * math.sqrt(2.0 * math.pi) * st * area
        cc = np.broadcast_to(cols[ok][None, :], rr.shape)
        inside = (rr >= 0) & (rr < H)
        np.add.at(stripe, (rr[inside].astype(int), cc[inside]), val[inside].astype(np.float32))

    # --- the glow: on sub-rows, from each stripe outward, edge Phi(s (v - v_t) / sigma_v), then blurred
    glow = _glow_layer(t, cal, xn, x_w, rows, sigma_v, unatt, att_c)

    # --- veil and particles
    veil_field = _smooth_field(rng, W, H)
    vcol = np.arange(H, dtype=np.float32)[:, None]
    veil = (t.veil_dn * (1.0 + t.veil_slope * (cam.cy - vcol) / H) * (1.0 + 0.1 * veil_field)).astype(np.float32)
    veil = np.maximum(veil, 0.0)
    n_all = rng.poisson(t.particles_per_mpx * W * H / 1e6)
    n_sheet = rng.binomial(n_all, SHEET_PARTICLE_SHARE)
    speckle = np.zeros((H, W), np.float32)
    su, sv = rng.uniform(0, W - 1, n_sheet), rng.uniform(0, H - 1, n_sheet)
    s_amp, s_sig = rng.exponential(2.0, n_sheet), rng.uniform(0.5, 1.2, n_sheet)
    ui = np.clip(np.rint(su).astype(int), 0, W - 1)
    vi = np.clip(np.rint(sv).astype(int), 0, H - 1)
    in_sheet = np.zeros(n_sheet, bool)
    for li, s in enumerate(signs):  # outward of the stripe, on the laser's side: inside that laser's sheet
        vt = rows[li][ui]
        outward = np.where(np.isfinite(vt), s * (sv - vt) > 0, s * (sv - cam.cy) > 0)
        in_sheet |= outward
    s_amp = s_amp * glow[vi, ui] * in_sheet
    _stamp(speckle, su, sv, s_amp, s_sig)
    snow = np.zeros((H, W), np.float32)
    n_snow = n_all - n_sheet
    au, av = rng.uniform(0, W - 1, n_snow), rng.uniform(0, H - 1, n_snow)
    a_amp, a_sig = rng.exponential(0.5, n_snow), rng.uniform(0.5, 1.5, n_snow)
    ai = np.clip(np.rint(au).astype(int), 0, W - 1)
    aj = np.clip(np.rint(av).astype(int), 0, H - 1)
    _stamp(snow, au, av, a_amp * veil[aj, ai], a_sig)

    # --- colour, noise, 8 bits
    laser = stripe + glow + speckle
    ambient = veil + snow
    out = np.empty((H, W, 3), np.uint8)
    var_read = t.read_noise_dn**2
    for ch in range(3):
        sig = LASER_BGR[ch] * laser + VEIL_BGR[ch] * ambient
        noisy = sig + rng.standard_normal((H, W), dtype=np.float32) * np.sqrt(
            var_read + np.maximum(sig, 0.0) / t.electrons_per_dn
        )
        out[:, :, ch] = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)

    # --- truth: the stripe's peak, the noise at its row, visibility
    green = laser + ambient
    peak = np.zeros((2, W))
    noise = np.full((2, W), np.nan)
    visible = np.zeros((2, W), bool)
    for li in (0, 1):
        vt = rows[li]
        ok = np.isfinite(vt) & (vt > 0) & (vt < H - 1)
        r0 = np.rint(vt[ok]).astype(int)
        near = np.stack([stripe[np.clip(r0 + d, 0, H - 1), cols[ok]] for d in range(-2, 3)])
        peak[li, ok] = near.max(axis=0)
        noise[li, ok] = np.sqrt(var_read + np.maximum(green[r0, cols[ok]], 0.0) / t.electrons_per_dn + 1.0 / 12.0)
        with np.errstate(invalid="ignore"):
            visible[li] = (
                ok
                & (x_w >= VISIBLE_RANGE_M[0])
                & (x_w <= VISIBLE_RANGE_M[1])
                & (peak[li] >= VISIBLE_SNR * np.nan_to_num(noise[li], nan=np.inf))
            )
    range_m = np.stack([x_w, x_w])
    layers = {"stripe": stripe, "glow": glow, "veil": veil, "speckle": speckle, "snow": snow}
    return TurbidFrame(out, cal, rows, range_m, peak, noise, visible, layers)


def _glow_layer(
    t: Turbid,
    cal: Calibration,
    xn: FloatArray,
    x_w: FloatArray,
    rows: FloatArray,
    sigma_v: FloatArray,
    unatt: FloatArray,
    att_c: float,
) -> NDArray[np.float32]:
    """The glow of both sheets (H, W) float32, DN: integrated over sub-rows, blurred, summed per pixel row.

    ``unatt`` is each column's blurred stripe peak without the attenuation (DN) and ``att_c`` the centre column's
    attenuation exponent: the per-column scale is formed with the attenuation cancelled analytically, so far
    columns neither underflow nor overflow."""
    W, H = t.size
    cam = cal.camera
    c = t.baseline_m / 2.0
    h = 1.0 / SUB_ROWS
    v_sub = (np.arange(H * SUB_ROWS) + 0.5) * h - 0.5  # sub-row centres, px
    fine = np.zeros((H * SUB_ROWS, W), np.float32)
    hit = np.isfinite(x_w)
    if t.glow_step > 0:
        # glow = coef(u) * factor(x, u) * exp(att_c - alpha path): at the edge (x = x_w) it is glow_step times
        # the column's blurred stripe peak unatt * exp(att_c - att_w)
        factor_w, _ = _glow_terms(np.where(hit, x_w, 1.0), xn, c)
        coef = np.where(hit, t.glow_step * unatt / factor_w, 0.0)
        centre = round(cam.cx)
        if not t.step_per_column:  # one scattering coefficient for the frame, set on the centre column
            coef[:] = coef[centre]
        else:  # beyond the visible ranges, and where the rays miss the wall: the nearest visible column's
            near = hit & (x_w <= VISIBLE_RANGE_M[1])
            coef[~near] = np.interp(np.flatnonzero(~near), np.flatnonzero(near), coef[near])
        xn32 = xn.astype(np.float32)[None, :]
        for li, s in enumerate((-1.0, 1.0)):
            side = np.flatnonzero(s * (v_sub - cam.cy) > 0)  # the sub-rows on this laser's side of the centre
            v_side = v_sub[side]
            x = (cam.fy * s * c / (v_side - cam.cy)).astype(np.float32)[:, None]  # sheet range per sub-row
            factor, path = _glow_terms(x, xn32, c)
            g = factor * np.exp(np.float32(att_c) - np.float32(t.attenuation_per_m) * path)
            vt = np.where(hit, rows[li], cam.cy)  # no wall: the sheet is seen all the way to the horizon
            edge = (s * (v_side[:, None] - vt[None, :]) > 0).astype(np.float32)
            # the exact mean of Phi(s (v - v_t) / sigma_v) over each sub-row near the edge
            band = math.ceil((8.0 * float(sigma_v[hit].max(initial=0.0)) + 1.0) * SUB_ROWS)
            j0 = np.searchsorted(v_side, vt)  # first sub-row of this side at or past the edge, per column
            jj = j0[None, :] + np.arange(-band, band + 1)[:, None]
            inside = (jj >= 0) & (jj < side.size) & hit[None, :]
            jj_c = np.clip(jj, 0, side.size - 1)
            vc = v_side[jj_c]
            sv = np.where(hit, sigma_v, 1.0)[None, :]
            lo, hi = vc - 0.5 * h, vc + 0.5 * h
            mean = (sv / (s * h)) * (_cdf_integral(s * (hi - vt) / sv) - _cdf_integral(s * (lo - vt) / sv))
            cc = np.broadcast_to(np.arange(W)[None, :], jj.shape)
            edge[jj_c[inside], cc[inside]] = np.clip(mean[inside], 0.0, 1.0).astype(np.float32)
            fine[side] += g * edge * coef.astype(np.float32)[None, :]
    if t.blur_px > 0:
        fine = cv2.GaussianBlur(
            fine, (0, 0), sigmaX=t.blur_px, sigmaY=t.blur_px * SUB_ROWS, borderType=cv2.BORDER_REPLICATE
        )
    return np.asarray(fine.reshape(H, SUB_ROWS, W).mean(axis=1), dtype=np.float32)
