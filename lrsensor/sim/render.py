"""Rendering: trace each laser fan into the scene, draw the stripes exactly, add water and sensor effects.

What: :func:`render` turns a scene, the TRUE calibration, an optional vehicle pose, a water model and a laser
model into the image the camera sees, a (H, W, 3) uint8 BGR array as ``cv2.imread`` gives, together with
its ground truth (:class:`~lrsensor.sim.truth.Render`). :func:`trace_truth` does only the geometric part:
the truth and the raw fan samples, without drawing (cheap enough for whole dives).

The stages, each in its own module:

1. :mod:`.fan`: every laser fan is sampled densely and adaptively (consecutive visible samples at most
   ``LaserModel.max_gap_px`` apart in the image, occlusion edges located to ~1e-6 rad), in the body frame,
   and each sample gets a stripe peak (DN) and width (pixels).
2. :mod:`.truth`: the visible samples become the ground truth (:class:`~lrsensor.sim.truth.Truth`): body-frame
   hit points, their distorted pixel coordinates (as ``cv2.projectPoints`` gives) and the surface hit.
3. :mod:`.lighting` and :mod:`.water`: the background, the glow of the laser sheets, large distractor blobs
   (smooth layers, painted at quarter resolution), ambient light and checkerboards, small blobs.
4. :mod:`.stripe`: the stripes are drawn per image column (or per row where steeper than 45 degrees) as
   Gaussian profiles at the exact sub-pixel centre, so each column's intensity centroid is the true projected
   centre before noise and 8-bit rounding; an optional wide halo; speckle on the stripe band.
5. :mod:`.water`: marine snow, sensor noise, clipping and rounding to 8 bits.

Every random effect draws from one generator (``seed``) in this fixed order, so a seed gives the same image;
reordering the stages changes the images of every seed.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..frames import Pose
from .fan import FanSamples, LaserModel, fan_basis, stripe_photometry, trace_fan, trace_samples
from .lighting import laser_glow, paint_ambient
from .scene import Rectangle, Scene
from .stripe import accumulate_band, draw_stripe, stripe_splats
from .truth import LaserTruth, Render, Truth
from .water import (
    LOW_RES_FACTOR,
    WaterModel,
    add_snow,
    apply_speckle,
    background,
    draw_blobs,
    finish,
    low_res_shape,
    paint_blobs,
)

__all__ = [
    "FanSamples",
    "LaserModel",
    "LaserTruth",
    "Render",
    "Truth",
    "accumulate_band",
    "draw_stripe",
    "fan_basis",
    "render",
    "stripe_splats",
    "trace_fan",
    "trace_samples",
    "trace_truth",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
F32 = NDArray[np.float32]


def trace_truth(
    scene: Scene,
    calibration: Calibration,
    pose: Pose | None = None,
    laser_model: LaserModel | None = None,
    water: WaterModel | None = None,
    *,
    edge_tol_rad: float = 2e-7,
) -> tuple[Truth, list[tuple[FanSamples, IntArray, FloatArray, FloatArray]]]:
    """Trace every laser into the scene without drawing: the ground truth and the raw samples.

    The raw samples per laser are ``(samples, segment, peak_dn, sigma_px)``.

    ``edge_tol_rad`` is how precisely (fan angle) occlusion and shadow edges are located.
    """
    model = laser_model or LaserModel()
    water = water or WaterModel.clean()
    scene_body = scene.in_body(pose)
    cam = calibration.camera
    lts = []
    raw = []
    for i, lp in enumerate(calibration.lasers):
        s, seg = trace_fan(scene_body, calibration, i, model, theta_tol_rad=edge_tol_rad)
        peak, sigma = stripe_photometry(s, scene_body, calibration, i, model, water)
        raw.append((s, seg, peak, sigma))
        # the truth describes the stripe as the camera sees it: forward scatter widens it and lowers its peak
        scatter_px = water.forward_scatter_px * cam.width / 1920.0
        if scatter_px > 0:
            seen_sigma = np.hypot(sigma, scatter_px)
            peak, sigma = peak * sigma / seen_sigma, seen_sigma
        with np.errstate(invalid="ignore"):
            vis = (
                (seg >= 0)
                & (s.uv[:, 0] >= -0.5)
                & (s.uv[:, 0] <= cam.width - 0.5)
                & (s.uv[:, 1] >= -0.5)
                & (s.uv[:, 1] <= cam.height - 0.5)
            )
        # keep the neighbour beyond the image border at each end, so that interpolation covers every column
        same = (seg[1:] == seg[:-1]) & (seg[1:] >= 0)
        vis[:-1] |= vis[1:] & same
        vis[1:] |= vis[:-1].copy() & same
        lts.append(
            LaserTruth(
                index=i,
                name=lp.name,
                theta_rad=s.theta[vis],
                points_body=s.points[vis],
                uv=s.uv[vis],
                surface_id=s.sid[vis],
                segment=seg[vis],
                peak_dn=peak[vis],
                sigma_px=sigma[vis],
                range_m=s.r_cam[vis],
            )
        )
    truth = Truth(tuple(lts), scene, scene_body, pose, cam.width, cam.height)
    return truth, raw


def render(
    scene: Scene,
    calibration: Calibration,
    *,
    pose: Pose | None = None,
    water: WaterModel | None = None,
    laser_model: LaserModel | None = None,
    seed: int | np.random.Generator | None = 0,
    keep_layers: bool = False,
) -> Render:
    """Render what the camera sees, with ground truth.

    Args:
        scene: the surfaces, in the body frame, or in NED together with ``pose``.
        calibration: the TRUE calibration (camera with distortion, mounting, laser planes).
        pose: vehicle pose in NED (needed for NED scenes).
        water: water and sensor model (default :meth:`WaterModel.default`).
        laser_model: laser optics and power (default :class:`LaserModel`).
        seed: seed or generator of every random effect (background, noise, distractors).
        keep_layers: keep the float32 stripe map in ``Render.layers["laser"]`` (tests).

    Returns:
        :class:`Render` with the (H, W, 3) uint8 BGR image, the calibration and the :class:`Truth`.
    """
    water = WaterModel.default() if water is None else water
    model = laser_model or LaserModel()
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    truth, raw = trace_truth(scene, calibration, pose, model, water)
    scene_body = truth.scene_body
    cam = calibration.camera
    h, w = cam.height, cam.width
    has_boards = any(isinstance(sf, Rectangle) and sf.board is not None for sf in scene_body.surfaces)
    colour = np.asarray(model.colour_bgr, np.float32)
    # smooth layers (glow, large blobs) are painted at quarter resolution
    low_extra = np.zeros((*low_res_shape(h, w), 3), np.float32)
    smooth = False
    glow: F32 | None = None  # the physical glow, full resolution, added to the laser light below
    if water.backscatter > 0:
        for i in range(len(calibration.lasers)):
            layer = laser_glow(scene_body, calibration, i, model, water, (h, w))
            if water.glow_model == "blurred":
                low_extra += layer[:, :, None] * colour
                smooth = True
            else:
                glow = layer if glow is None else glow + layer
    blobs = draw_blobs(h, w, water, rng)
    big = [bl for bl in blobs if bl.s_across >= 2.0 * LOW_RES_FACTOR]
    small = [bl for bl in blobs if bl.s_across < 2.0 * LOW_RES_FACTOR]
    if big:
        paint_blobs(low_extra, big, LOW_RES_FACTOR)
        smooth = True
    if smooth and water.ambient_dn <= 0 and not has_boards:
        img = background(h, w, water, rng, extra_low=low_extra)
    else:
        img = background(h, w, water, rng)
        paint_ambient(scene_body, calibration, water, img)
        if smooth:
            img += cv2.resize(low_extra, (w, h), interpolation=cv2.INTER_LINEAR)
    paint_blobs(img, small)
    splats = [stripe_splats(s.uv, peak, sigma, seg, w, h) for s, seg, peak, sigma in raw]
    if model.halo_fraction > 0:
        hf, k = model.halo_fraction, model.halo_sigma_scale
        splats += [
            stripe_splats(s.uv, peak * hf / max(1.0 - hf, 1e-6) / k, sigma * k, seg, w, h)
            for s, seg, peak, sigma in raw
        ]
    r0, band = accumulate_band(
        np.concatenate([sp[0] for sp in splats]),
        np.concatenate([sp[1] for sp in splats]),
        np.concatenate([sp[2] for sp in splats]),
        w,
    )
    layers: dict[str, F32] = {}
    if keep_layers:
        laser_full = np.zeros((h, w), np.float32)
        laser_full[r0 : r0 + band.shape[0]] = band
        layers["laser"] = laser_full
    if band.shape[0]:
        apply_speckle(band, water, rng)
    scatter_px = water.forward_scatter_px * w / 1920.0
    if glow is None and scatter_px <= 0:
        if band.shape[0]:
            img[r0 : r0 + band.shape[0]] += band[:, :, None] * colour
    else:
        # stripe and glow travel to the camera through the same water: one forward-scatter blur for both
        light = np.zeros((h, w), np.float32) if glow is None else glow
        light[r0 : r0 + band.shape[0]] += band
        if scatter_px > 0:
            light = np.asarray(cv2.GaussianBlur(light, (0, 0), scatter_px), np.float32)
        img += light[:, :, None] * colour
    add_snow(img, water, rng)
    image = finish(img, water, rng)
    return Render(image=image, calibration=calibration, truth=truth, layers=layers)
