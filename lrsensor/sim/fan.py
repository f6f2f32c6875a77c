"""Laser fans: the lasers' optics, dense tracing of each fan into the scene, and the stripe's photometry.

What: each line laser emits a fan of rays in its calibrated plane. :func:`fan_basis` gives the fan's origin and
two in-plane unit directions, :func:`trace_fan` samples the fan densely and finds where each ray hits the
scene and where that hit appears in the image, and :func:`stripe_photometry` turns every sample into the
peak and width of the stripe's cross profile there. :class:`LaserModel` holds the optics and power that
the calibration does not (fan angle, power, sheet thickness, blur, sampling density).

Inputs: a scene in the body frame (x forward, y starboard, z down; metres), the TRUE
:class:`~lrsensor.calibration.Calibration` (laser planes ``normal_body``/``point_body``, camera intrinsics
with distortion and mounting, and its flat port if any: the hits are then projected exactly through the port,
:func:`lrsensor.port.project_through_port`, and seen along the refracted path from the port), a laser index and
a :class:`LaserModel`.

Outputs: :class:`FanSamples` of N samples sorted by fan angle, all arrays indexed by sample:
``theta`` (N,) fan angle in radians (``cos(theta) a + sin(theta) b``, > 0 toward body +y for an untilted
laser); ``t`` (N,) distance from the laser origin to the hit in metres (the directions are unit vectors;
inf = no hit); ``sid`` (N,) surface id (-1 = none); ``points`` (N, 3) body-frame hits in metres; ``uv``
(N, 2) their distorted pixel coordinates (as ``cv2.projectPoints`` gives; OpenCV origin); ``ok`` (N,)
drawable (hit, seen by the camera, in front of it, inside the image plus a margin); ``cos_inc`` (N,)
|cosine| of the incidence angle; ``r_cam`` (N,) camera-centre-to-hit distance in metres; ``depth`` (N,)
camera-frame z in metres. :func:`trace_fan` also gives a segment index (N,) per sample: runs of
continuous drawable samples on one surface, -1 where not drawable.

Why adaptive: the image of the stripe must be exact to well under a pixel, and occlusion and shadow edges
must be located precisely, but a uniform sampling that fine would cost millions of rays. The fan starts
evenly spaced in ``tan(theta)`` (roughly even in the image), then repeatedly subdivides continuous pairs
more than ``LaserModel.max_gap_px`` apart in the image and splits each edge (a change of visibility or
surface) 64-fold until it is narrower than ``theta_tol_rad``.

The photometry is a simple model, not radiometry: peak DN ``peak_dn_at_1m * (albedo / 0.6) *
(0.15 + 0.85 cos_inc) * exp(-c (r_laser + r_cam)) * r_mean^-range_exponent`` (``c`` the water's
attenuation per metre, ``r_mean`` the mean of the two path lengths) and cross-stripe sigma in pixels
``sqrt(blur_sigma_px^2 + (sheet_sigma_m * f / depth)^2)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import SimulationError
from ..port import project_through_port, rays_in_water
from .scene import Scene
from .water import WaterModel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class LaserModel:
    """The line lasers' optics and power (the geometry comes from the calibration's laser planes).

    Attributes:
        fan_angle_rad: full fan angle, radians (the paper: 120 degrees), centred on the body +x direction
            projected into the laser plane.
        peak_dn_at_1m: stripe peak in the green channel, DN, for a white-ish (albedo 0.6) wall hit head-on at
            1 m in clear water; closer walls saturate (flat-topped peaks, clipped at 255).
        range_exponent: the peak falls as ``(1 m / r)^range_exponent`` with r the mean of the laser and
            camera path lengths (1 for an ideal line laser, 2 for a point source).
        sheet_sigma_m: Gaussian sigma of the light sheet's thickness, metres.
        blur_sigma_px: optical blur (Gaussian sigma) of the camera, pixels.
        colour_bgr: relative response of the (B, G, R) channels to the green laser.
        max_gap_px: largest image spacing between consecutive fan samples, pixels.
        max_range_m: rays that hit nothing within this range are lost in the water.
        halo_fraction: share (0..1) of the stripe's light in a wide symmetric halo (forward scattering in the
            water, lens flare); 0 = a pure Gaussian profile.
        halo_sigma_scale: sigma of the halo relative to the stripe's.
    """

    fan_angle_rad: float = math.radians(120.0)
    peak_dn_at_1m: float = 190.0
    range_exponent: float = 1.0
    sheet_sigma_m: float = 0.0008
    blur_sigma_px: float = 1.0
    colour_bgr: tuple[float, float, float] = (0.3, 1.0, 0.08)
    max_gap_px: float = 1.0
    max_range_m: float = 30.0
    halo_fraction: float = 0.0
    halo_sigma_scale: float = 4.0


@dataclass
class FanSamples:
    """Samples of one laser fan, all (N,) or (N, 3)/(N, 2) arrays indexed alike (fields: the module docstring)."""

    theta: FloatArray
    t: FloatArray
    sid: IntArray
    points: FloatArray
    uv: FloatArray
    ok: NDArray[np.bool_]
    cos_inc: FloatArray
    r_cam: FloatArray
    depth: FloatArray


def fan_basis(calibration: Calibration, laser: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Laser origin (3,), fan centre direction ``a`` (3,) and in-plane side direction ``b`` (3,), body frame.

    ``a`` is the body +x axis projected into the laser plane, ``b = n x a`` (body +y for an untilted laser):
    the fan ray at angle theta is ``cos(theta) a + sin(theta) b``.
    """
    lp = calibration.lasers[laser]
    n = lp.normal_body
    x = np.array([1.0, 0.0, 0.0])
    a = x - (x @ n) * n
    na = float(np.linalg.norm(a))
    if na < 1e-6:
        msg = f"laser {lp.name!r}: its plane is perpendicular to the body x axis; no forward fan"
        raise SimulationError(msg)
    a /= na
    b = np.cross(n, a)
    return lp.point_body, a, b / np.linalg.norm(b)


def trace_samples(
    scene: Scene,
    calib: Calibration,
    origin: FloatArray,
    a: FloatArray,
    b: FloatArray,
    theta: FloatArray,
    max_range_m: float,
    margin_px: float,
) -> FanSamples:
    """Cast the fan rays at angles ``theta`` (N,), then their hits toward the camera (visibility) and into the image."""
    d = np.cos(theta)[:, None] * a + np.sin(theta)[:, None] * b
    t, sid, nrm = scene.raycast(origin, d)
    hit = np.isfinite(t) & (t <= max_range_m)
    p = origin + np.where(hit, t, 0.0)[:, None] * d
    C = calib.camera_center_body
    dc = p - C
    pc = calib.body_to_cam(p)
    if calib.port is None:
        tc, _, _ = scene.raycast(C, dc)
        uv = calib.camera.project(pc)
    else:
        # the camera sees the hit along the refracted path: from its exit point on the port to the hit
        dirs_air = project_through_port(calib.port, pc)
        uv = calib.camera.project(dirs_air)
        exit_body = calib.cam_to_body(rays_in_water(calib.port, dirs_air)[0])
        exit_body = np.where(np.isfinite(exit_body), exit_body, C)  # rows without a path are not drawn anyway
        tc, _, _ = scene.raycast(exit_body, p - exit_body)
    seen = hit & (tc >= 1.0 - 1e-7)
    cam = calib.camera
    with np.errstate(invalid="ignore"):
        inside = (
            (uv[:, 0] >= -margin_px)
            & (uv[:, 0] <= cam.width - 1 + margin_px)
            & (uv[:, 1] >= -margin_px)
            & (uv[:, 1] <= cam.height - 1 + margin_px)
        )
    ok = seen & (pc[:, 2] > 1e-6) & np.isfinite(uv).all(axis=1) & inside
    sid = np.where(hit, sid, -1)
    cos_inc = np.abs(np.einsum("ij,ij->i", nrm, d))
    return FanSamples(theta, t, sid, p, uv, ok, cos_inc, np.linalg.norm(dc, axis=1), pc[:, 2])


def _merge(s: FanSamples, n: FanSamples) -> FanSamples:
    order = np.argsort(np.concatenate([s.theta, n.theta]), kind="stable")
    return FanSamples(*(np.concatenate([getattr(s, f), getattr(n, f)])[order] for f in FanSamples.__dataclass_fields__))


def trace_fan(
    scene_body: Scene,
    calibration: Calibration,
    laser: int,
    model: LaserModel | None = None,
    *,
    margin_px: float = 12.0,
    theta_tol_rad: float = 2e-7,
    max_iterations: int = 24,
) -> tuple[FanSamples, IntArray]:
    """Trace one laser fan densely into a body-frame scene.

    Returns the samples (sorted by fan angle) and a segment index per sample (-1 where not drawable:
    no hit, hidden from the camera, behind it or outside the image plus ``margin_px``).
    """
    model = model or LaserModel()
    origin, a, b = fan_basis(calibration, laser)
    half = model.fan_angle_rad / 2.0
    f = max(calibration.camera.fx, calibration.camera.fy)
    span = 2.0 * math.tan(min(half, math.radians(85.0)))
    n0 = int(min(max(64, math.ceil(f * span / (0.8 * model.max_gap_px))), 200_000))
    theta = np.arctan(np.linspace(-span / 2.0, span / 2.0, n0))
    theta = np.clip(theta, -half, half)
    s = trace_samples(scene_body, calibration, origin, a, b, theta, model.max_range_m, margin_px)
    for _ in range(max_iterations):
        ok0, ok1 = s.ok[:-1], s.ok[1:]
        cont = ok0 & ok1 & (s.sid[:-1] == s.sid[1:])
        gap = np.linalg.norm(np.diff(s.uv, axis=0), axis=1)
        dth = np.diff(s.theta)
        with np.errstate(invalid="ignore"):
            smooth = cont & (gap > model.max_gap_px) & (dth > 1e-12)
            edge = ~cont & (ok0 | ok1) & (dth > theta_tol_rad)
        if not (np.any(smooth) or np.any(edge)):
            break
        # continuous pairs: enough evenly spaced samples to close the gap (x1.5 for curvature);
        # edges (occlusion, shadow, surface change, image border): 63 interior samples (6 bits per pass)
        i_s = np.flatnonzero(smooth)
        k_s = np.minimum(np.ceil(1.5 * gap[i_s] / model.max_gap_px).astype(np.int64), 4096)
        i_e = np.flatnonzero(edge)
        k_e = np.full(i_e.size, 64, dtype=np.int64)
        i_all = np.concatenate([i_s, i_e])
        k_all = np.concatenate([k_s, k_e])
        rep = np.repeat(np.arange(i_all.size), k_all - 1)
        frac = (np.arange(rep.size) - np.repeat(np.cumsum(k_all - 1) - (k_all - 1), k_all - 1) + 1) / k_all[rep]
        new_theta = s.theta[i_all[rep]] + frac * dth[i_all[rep]]
        s = _merge(s, trace_samples(scene_body, calibration, origin, a, b, new_theta, model.max_range_m, margin_px))
    # segments: runs of continuous drawable samples
    cont = s.ok[:-1] & s.ok[1:] & (s.sid[:-1] == s.sid[1:])
    gap = np.linalg.norm(np.diff(s.uv, axis=0), axis=1)
    with np.errstate(invalid="ignore"):
        cont &= gap <= 8.0 * model.max_gap_px
    starts = np.concatenate([[True], ~cont])
    seg = np.cumsum(starts) - 1
    seg = np.where(s.ok, seg, -1)
    # renumber consecutively and drop singletons
    out = np.full(seg.shape, -1, dtype=np.int64)
    k = 0
    for sg in np.unique(seg[seg >= 0]):
        idx = np.flatnonzero(seg == sg)
        if idx.size >= 2:
            out[idx] = k
            k += 1
    return s, out


def stripe_photometry(
    s: FanSamples, scene: Scene, calib: Calibration, laser: int, model: LaserModel, water: WaterModel
) -> tuple[FloatArray, FloatArray]:
    """Peak DN (N,) and profile sigma in pixels (N,) of each sample."""
    albedo = np.array([sf.albedo for sf in scene.surfaces] + [0.0])[s.sid]
    for k, sf in enumerate(scene.surfaces):
        if sf.stain > 0:
            on = s.sid == k
            if np.any(on):
                albedo[on] = sf.albedo_at(s.points[on])
    r_l = np.where(np.isfinite(s.t), s.t, 0.0)
    r_mean = np.maximum(0.5 * (r_l + s.r_cam), 1e-3)
    atten = np.exp(-water.attenuation_per_m * (r_l + s.r_cam))
    cos_term = 0.15 + 0.85 * s.cos_inc
    peak = model.peak_dn_at_1m * (albedo / 0.6) * cos_term * atten * r_mean ** (-model.range_exponent)
    f = 0.5 * (calib.camera.fx + calib.camera.fy)
    sheet_px = model.sheet_sigma_m * f / np.maximum(s.depth, 1e-6)
    sigma = np.sqrt(model.blur_sigma_px**2 + sheet_px**2)
    return peak, sigma
