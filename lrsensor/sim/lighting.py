"""Light in the image other than the stripe: the glow of the laser sheets and ambient light.

What: :func:`laser_glow` is the backscatter of one laser sheet in the water (a faint band along the fan,
brighter near the camera), at quarter resolution; :func:`paint_ambient` blends the surfaces lit by ambient
light, and printed checkerboards, over the water background.

Inputs: a scene in the body frame (metres), the TRUE :class:`~lrsensor.calibration.Calibration`, the
:class:`~lrsensor.sim.water.WaterModel` (attenuation per metre, backscatter gain, glow blur, ambient level in
DN) and, for the glow, the laser index and :class:`~lrsensor.sim.fan.LaserModel`.

Outputs: :func:`laser_glow` returns a float32 image in DN of shape
:func:`~lrsensor.sim.water.low_res_shape` (H/4, W/4); the renderer multiplies it by the laser's colour and
upsamples it with the other smooth layers. :func:`paint_ambient` changes an (H, W, 3) float32 BGR image in
DN in place.

Why these approximations: the glow is single scattering only (multiple scattering and the sheet's thickness
are a blur) and ignores objects between the camera and the sheet, and ambient shading is computed at quarter
resolution: both are smooth, and what matters for the extractor is their shape and level, not their
radiometry. Checkerboards, on the other hand, are drawn at full resolution with an exact box filter over
each pixel's footprint, because the camera calibration detects their corners to a few hundredths of a pixel.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import SimulationError
from .fan import LaserModel, fan_basis
from .scene import Rectangle, Scene
from .water import LOW_RES_FACTOR, WaterModel, low_res_shape

FloatArray = NDArray[np.float64]
F32 = NDArray[np.float32]


@functools.lru_cache(maxsize=4)  # a full-resolution 1080p entry holds about 100 MB
def _grid_rays(calib: Calibration, h: int, w: int, factor: int) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Body-frame viewing rays in the water of the pixel centres of the image at 1/``factor`` resolution:
    origins ((3,) the camera centre, or (M, 3) the exit points on the port), directions (M, 3) and their lengths
    (M,)."""
    hl, wl = low_res_shape(h, w) if factor == LOW_RES_FACTOR else (h, w)
    f = factor
    ys, xs = np.mgrid[0:hl, 0:wl]
    uv = np.stack([xs.ravel() * f + (f - 1) / 2.0, ys.ravel() * f + (f - 1) / 2.0], axis=1).astype(float)
    return _rays_of(calib, uv)


def _rays_of(calib: Calibration, uv: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    origins, rays = calib.water_rays_body(uv)
    norm = np.linalg.norm(rays, axis=1)
    for a in (origins, rays, norm):
        a.setflags(write=False)
    return origins, rays, norm


class _Sheet:
    """The single-scatter radiance of one laser sheet along camera rays (see :func:`laser_glow`)."""

    def __init__(self, scene: Scene, calib: Calibration, laser: int, model: LaserModel, water: WaterModel) -> None:
        self.origin, self.a, self.b = fan_basis(calib, laser)
        self.n = calib.lasers[laser].normal_body
        self.half = model.fan_angle_rad / 2.0
        # fan table: distance to the first hit per fan angle
        self.theta_tab = np.linspace(-self.half, self.half, 721)
        d = np.cos(self.theta_tab)[:, None] * self.a + np.sin(self.theta_tab)[:, None] * self.b
        t_tab, _, _ = scene.raycast(self.origin, d)
        self.c = water.attenuation_per_m
        self.t_tab = np.minimum(t_tab, min(model.max_range_m, 8.0 / max(self.c, 0.2)))

    def radiance(self, C: FloatArray, rays: FloatArray, norm: FloatArray) -> FloatArray:
        """Glow (arbitrary units) along rays from ``C`` (3,) or (M, 3), directions (M, 3) of lengths (M,)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = rays @ self.n
            tp = ((self.origin - C) @ self.n) / denom
            p = C + tp[:, None] * rays
            q = p - self.origin
            s = np.linalg.norm(q, axis=1)
            th = np.arctan2(q @ self.b, q @ self.a)
            ok = np.isfinite(tp) & (tp > 0) & (np.abs(th) <= self.half)
            ok &= s < np.interp(th, self.theta_tab, self.t_tab)
            r_c = tp * norm
            cos_a = np.abs(denom) / norm
            val = np.exp(-self.c * (s + r_c)) / (np.maximum(s, 0.02) * np.maximum(cos_a, 0.02)) / (1.0 + s / 0.5)
        return np.where(ok, val, 0.0)


#: Sub-rows per pixel where the physical glow ends inside the pixel (its coverage is integrated there).
EDGE_SUBROWS = 8


def laser_glow(
    scene: Scene, calib: Calibration, laser: int, model: LaserModel, water: WaterModel, shape: tuple[int, int]
) -> F32:
    """Backscatter glow of one laser sheet, float32 DN.

    Single-scattering radiance of the sheet seen along each camera ray: the ray crosses the laser plane at a
    point at distance ``s`` from the laser; if that point lies inside the fan and before the laser's first hit,
    it glows with ``exp(-c (s + r_cam)) / (s |cos a|)`` (sheet irradiance ~ 1/s, path through the sheet
    ~ 1/|cos a| for a ray at angle a to the sheet normal) times a phase factor ``1 / (1 + s / 0.5 m)`` that
    makes it brighter near the camera; occlusion of the glow by objects between the camera and the sheet is
    ignored.

    ``water.glow_model == "physical"``: full resolution (H, W); the sheet ends where it meets the surface, so
    the glow ends at the stripe's centre: pixels the end crosses are integrated over :data:`EDGE_SUBROWS`
    sub-rows, and the only blur is the forward scatter the renderer applies to stripe and glow together.
    ``"blurred"``: quarter resolution (:func:`low_res_shape`), blurred by ``water.glow_sigma_px`` (sheet
    thickness and multiple scattering, the older model).
    """
    if water.glow_model not in ("physical", "blurred"):
        msg = f"water.glow_model must be 'physical' or 'blurred', got {water.glow_model!r}"
        raise SimulationError(msg)
    h, w = shape
    sheet = _Sheet(scene, calib, laser, model, water)
    # 0.2: a gain of 1 gives a faint band of a few DN with the default laser power
    gain = np.float32(0.2 * water.backscatter * model.peak_dn_at_1m / 190.0)
    if water.glow_model == "blurred":
        hl, wl = low_res_shape(h, w)
        low = sheet.radiance(*_grid_rays(calib, h, w, LOW_RES_FACTOR)).reshape(hl, wl).astype(np.float32)
        sig = max(water.glow_sigma_px * w / 1920.0 / LOW_RES_FACTOR, 0.5)
        return np.asarray(cv2.GaussianBlur(low, (0, 0), sig), np.float32) * gain
    val = sheet.radiance(*_grid_rays(calib, h, w, 1)).reshape(h, w)
    lit = val > 0
    edge = np.zeros_like(lit)
    edge[:-1] |= lit[:-1] != lit[1:]
    edge[1:] |= lit[1:] != lit[:-1]
    rows, cols = np.nonzero(edge)
    if rows.size:
        k = (np.arange(EDGE_SUBROWS) + 0.5) / EDGE_SUBROWS - 0.5
        uv = np.stack(
            [np.repeat(cols.astype(float), EDGE_SUBROWS), (rows[:, None] + k[None, :]).ravel()], axis=1
        )
        sub = sheet.radiance(*_rays_of(calib, uv)).reshape(-1, EDGE_SUBROWS)
        val[rows, cols] = sub.mean(axis=1)
    return val.astype(np.float32) * gain


def paint_ambient(scene: Scene, calib: Calibration, water: WaterModel, img: F32) -> None:
    """Surfaces lit by ambient light, and printed checkerboards, blended over the water background in place.

    With ``water.ambient_dn > 0`` every surface is shaded (at quarter resolution: it is smooth). Checkerboards
    are drawn at full resolution with an analytic box filter over each pixel's footprint on the board (exact
    anti-aliasing, so corner detectors find the true corners to a few hundredths of a pixel); when the water
    has no ambient light the board is lit by a lamp of 170 DN.
    """
    cam = calib.camera
    h, w = cam.height, cam.width
    boards = [i for i, s in enumerate(scene.surfaces) if isinstance(s, Rectangle) and s.board is not None]
    if water.ambient_dn <= 0 and not boards:
        return
    level = water.ambient_dn if water.ambient_dn > 0 else 170.0
    C = calib.camera_center_body
    colour = np.array([0.95, 1.0, 0.9], np.float32)
    albedo = np.array([sf.albedo for sf in scene.surfaces] + [0.0])
    c_att = water.attenuation_per_m

    if water.ambient_dn > 0:
        f = 4
        ys, xs = np.mgrid[0:h:f, 0:w:f]
        uv = np.stack([xs.ravel() + (f - 1) / 2.0, ys.ravel() + (f - 1) / 2.0], axis=1).astype(float)
        origins, rays = calib.water_rays_body(uv)
        t, sid, _ = scene.raycast(np.where(np.isfinite(origins), origins, C), rays)
        hit = np.isfinite(t)
        dist = np.where(hit, t * np.linalg.norm(rays, axis=1), 0.0)
        val = np.where(hit, level * albedo[sid] * np.exp(-c_att * dist), 0.0)
        hl, wl = ys.shape
        vimg = cv2.resize(val.reshape(hl, wl).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        himg = cv2.resize(hit.reshape(hl, wl).astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
        trans = np.float32(1.0)
        img *= (1.0 - trans * himg)[:, :, None] + trans * himg[:, :, None] * 0.15
        img += vimg[:, :, None] * colour
    for bi in boards:
        rect = scene.surfaces[bi]
        assert isinstance(rect, Rectangle)
        assert rect.board is not None
        board = rect.board
        eu, ev, c0 = np.asarray(rect.axis_u), np.asarray(rect.axis_v), np.asarray(rect.center)
        outline = board.outline_uv()
        corners = c0 + outline[:, :1] * eu + outline[:, 1:] * ev
        uvc = calib.project_water_body(corners)
        if not np.all(np.isfinite(uvc)):
            continue
        x0 = int(max(0, math.floor(uvc[:, 0].min()) - 3))
        x1 = int(min(w, math.ceil(uvc[:, 0].max()) + 4))
        y0 = int(max(0, math.floor(uvc[:, 1].min()) - 3))
        y1 = int(min(h, math.ceil(uvc[:, 1].max()) + 4))
        if x0 >= x1 or y0 >= y1:
            continue
        ys, xs = np.mgrid[y0:y1, x0:x1]
        uv = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(float)
        o, rays = calib.water_rays_body(uv)  # o: the camera centre, or each ray's exit point on the port
        o = np.where(np.isfinite(o), o, C)
        t, sid, _ = scene.raycast(o, rays)
        # board coordinates of each pixel centre on the board's plane (occluders checked with sid)
        n = rect.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            tp = ((c0 - o) @ n) / (rays @ n)
        p = o + tp[:, None] * rays
        ca, cb, _ = rect.local(p)
        bx, by = board.to_board(ca.reshape(ys.shape), cb.reshape(ys.shape))
        # pixel footprint on the board (metres, along the board's axes), from the local Jacobian
        wa = np.abs(np.gradient(bx, axis=1)) + np.abs(np.gradient(bx, axis=0))
        wb = np.abs(np.gradient(by, axis=1)) + np.abs(np.gradient(by, axis=0))
        refl, cover = board.filtered_reflectance(bx, by, wa, wb)
        on = (sid == bi).reshape(ys.shape) & np.isfinite(bx) & (tp.reshape(ys.shape) > 0)
        dist = np.linalg.norm(p - C, axis=1).reshape(ys.shape)
        val = level * refl * np.exp(-c_att * np.where(on, dist, 0.0))
        frac = np.where(on, cover, 0.0).astype(np.float32)
        patch = img[y0:y1, x0:x1]
        patch *= (1.0 - frac)[:, :, None]
        patch += (frac * val.astype(np.float32))[:, :, None] * colour
