"""The water and sensor model of the simulator: background, noise, turbidity, haze, glow, distractors.

Everything here works on float32 images in digital numbers (DN, 0..255 before the final clip) and is seeded
through a :class:`numpy.random.Generator`, so a render with the same seed gives the same image.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]


@dataclass(frozen=True)
class WaterModel:
    """Water, ambient light and camera sensor (SI units; image levels in DN of an 8-bit channel).

    Attributes:
        background_bgr: mean colour of the water background, DN per channel (B, G, R).
        texture: relative amplitude (0..1) of the low-frequency murk texture of the background.
        texture_cells: number of texture cells across the image width (size of the murk blotches).
        vignetting: relative darkening of the image corners (0 = none).
        attenuation_per_m: beam attenuation coefficient c, 1/m; light over a path L is scaled by exp(-c L).
        backscatter: gain of the glow that the laser sheet scatters toward the camera (0 = none; 1 = a
            faint band of a few DN; 5-10 = turbid harbour water).
        glow_sigma_px: blur of the glow band in the ``"blurred"`` glow model, pixels (at 1920 px width; scaled
            with the image).
        glow_model: ``"physical"`` (default): the sheet's single-scatter glow drawn at full resolution, ending
            exactly where the sheet meets the surface (at the stripe's centre), blurred only by the forward
            scatter together with the stripe; ``"blurred"``: the glow at quarter resolution blurred by
            ``glow_sigma_px`` on its own (the simulator's older model, whose blurred end is easy to tell apart
            from the stripe).
        forward_scatter_px: small-angle forward-scatter blur of the laser light (stripe and glow), Gaussian
            sigma in pixels (at 1920 px width; scaled with the image); 0 = none.
        haze_dn: veiling light added everywhere, DN (water-coloured).
        ambient_dn: brightness of a white (albedo 1) surface under the ambient light, DN (0 = dark water, the
            scene is seen only where the lasers hit it). A checkerboard needs about 150-200.
        read_noise_dn: sensor read noise, standard deviation in DN.
        shot_noise_gain: electrons per DN for the shot noise (variance = signal / gain); 0 = no shot noise.
        blobs: number of green distractor blobs (fish, algae, reflections), some elongated like a stripe.
        snow: number of marine-snow particles (small bright dots).
        speckle: contrast (0..1) of the laser speckle, a multiplicative granular noise on the stripe.
        bayer: simulate a colour sensor: the image is sampled on an RGGB Bayer mosaic (noise per photosite)
            and demosaiced by OpenCV (bilinear), as a real colour camera delivers it.
        jpeg_quality: compress the final image as JPEG at this quality (1-100; 0 = lossless, no JPEG).
    """

    background_bgr: tuple[float, float, float] = (38.0, 34.0, 12.0)
    texture: float = 0.25
    texture_cells: float = 7.0
    vignetting: float = 0.25
    attenuation_per_m: float = 0.08
    backscatter: float = 0.0
    glow_sigma_px: float = 8.0
    glow_model: str = "physical"
    forward_scatter_px: float = 0.0
    haze_dn: float = 0.0
    ambient_dn: float = 0.0
    read_noise_dn: float = 1.5
    shot_noise_gain: float = 4.0
    blobs: int = 0
    snow: int = 0
    speckle: float = 0.0
    bayer: bool = False
    jpeg_quality: int = 0

    @classmethod
    def clean(cls) -> WaterModel:
        """Clear water, flat dark background, no noise: for exact geometric tests."""
        return cls(
            background_bgr=(8.0, 8.0, 8.0),
            texture=0.0,
            vignetting=0.0,
            attenuation_per_m=0.0,
            read_noise_dn=0.0,
            shot_noise_gain=0.0,
        )

    @classmethod
    def default(cls) -> WaterModel:
        """Fairly clear water with a murky background and sensor noise."""
        return cls()

    @classmethod
    def turbid(cls) -> WaterModel:
        """Turbid water: strong attenuation, a visible glow of the laser sheet, veiling haze, some snow."""
        return cls(
            background_bgr=(52.0, 50.0, 22.0),
            texture=0.3,
            attenuation_per_m=0.35,
            backscatter=6.0,
            forward_scatter_px=2.0,
            haze_dn=14.0,
            read_noise_dn=2.5,
            shot_noise_gain=3.0,
            snow=120,
            speckle=0.15,
        )

    @classmethod
    def cluttered(cls) -> WaterModel:
        """Clear-ish water full of distractors: green blobs, marine snow and laser speckle."""
        return cls(attenuation_per_m=0.15, backscatter=1.0, blobs=14, snow=250, speckle=0.25, read_noise_dn=2.0)

    def with_(self, **changes: object) -> WaterModel:
        """A copy with some fields changed."""
        return replace(self, **changes)  # type: ignore[arg-type]


#: Resolution factor of the smooth layers (background, glow): they are built at 1/4 resolution and resized.
LOW_RES_FACTOR = 4


def low_res_shape(h: int, w: int) -> tuple[int, int]:
    """Shape (rows, cols) of the smooth layers for an H x W image."""
    f = LOW_RES_FACTOR
    return max(2, (h + f - 1) // f), max(2, (w + f - 1) // f)


def background(h: int, w: int, water: WaterModel, rng: np.random.Generator, extra_low: F32 | None = None) -> F32:
    """The water background, (H, W, 3) float32 BGR in DN: a low-frequency bluish-green murk with vignetting.

    Built at 1/4 resolution (everything in it is smooth) and resized, so it costs a few milliseconds.
    ``extra_low`` (:func:`low_res_shape` + (3,)) is another smooth layer added before the resize (the glow).
    """
    base = np.asarray(water.background_bgr, dtype=np.float32)
    hl, wl = low_res_shape(h, w)
    low = np.empty((hl, wl, 3), np.float32)
    low[:] = base
    if water.texture > 0:
        gw = max(2, round(water.texture_cells) + 2)
        gh = max(2, round(gw * h / w) + 2)
        grid = rng.standard_normal((gh, gw)).astype(np.float32)
        grid = np.asarray(cv2.GaussianBlur(grid, (0, 0), 0.8), np.float32)
        grid /= max(float(grid.std()), 1e-6)
        tex = cv2.resize(grid, (wl, hl), interpolation=cv2.INTER_CUBIC)
        low *= (1.0 + water.texture * 0.5 * tex)[:, :, None]
        # the murk is not uniformly coloured: a second texture shifts blue against green
        grid2 = rng.standard_normal((gh, gw)).astype(np.float32)
        tex2 = cv2.resize(grid2, (wl, hl), interpolation=cv2.INTER_CUBIC)
        low[:, :, 0] *= 1.0 + water.texture * 0.3 * tex2
    if water.vignetting > 0:
        ys = (np.arange(hl, dtype=np.float32) + 0.5 - hl / 2.0) / (hl / 2.0)
        xs = (np.arange(wl, dtype=np.float32) + 0.5 - wl / 2.0) / (wl / 2.0)
        r2 = (xs[None, :] ** 2 * (w / h) + ys[:, None] ** 2 * (h / w)) / (w / h + h / w)
        low *= (1.0 - water.vignetting * r2)[:, :, None]
    if water.haze_dn > 0:
        colour = base / max(float(base.max()), 1e-6)
        low += water.haze_dn * colour
    if extra_low is not None:
        low += extra_low
    elif water.texture == 0 and water.vignetting == 0:
        img = np.empty((h, w, 3), np.float32)
        img[:] = low[0, 0]
        return img
    out: F32 = np.asarray(cv2.resize(low, (w, h), interpolation=cv2.INTER_LINEAR), np.float32)
    return out


@dataclass(frozen=True)
class Blob:
    """A distractor blob: centre (px), sigmas across/along (px), angle (rad), peak (DN), B and R bleed."""

    cx: float
    cy: float
    s_across: float
    s_along: float
    angle: float
    amp: float
    blue: float
    red: float


def draw_blobs(h: int, w: int, water: WaterModel, rng: np.random.Generator) -> list[Blob]:
    """Random green distractor blobs (fish, algae, reflections), about a third elongated like a stripe."""
    scale = w / 1920.0
    out = []
    for _ in range(water.blobs):
        cx, cy = rng.uniform(0, w), rng.uniform(0, h)
        elongated = rng.uniform() < 0.35
        s1 = rng.uniform(3.0, 30.0) * scale
        s2 = s1 * (rng.uniform(3.0, 8.0) if elongated else rng.uniform(1.0, 2.0))
        ang = rng.uniform(-0.4, 0.4) if elongated else rng.uniform(0, np.pi)
        amp = rng.uniform(25.0, 160.0)
        out.append(Blob(cx, cy, s1, s2, ang, amp, rng.uniform(0.2, 0.6), rng.uniform(0.0, 0.3)))
    return out


def paint_blobs(img: F32, blobs: list[Blob], factor: float = 1.0) -> None:
    """Add blobs to a float32 BGR image in place; ``factor`` > 1 paints on an image ``factor`` times smaller."""
    h, w = img.shape[:2]
    for bl in blobs:
        cx = (bl.cx + 0.5) / factor - 0.5
        cy = (bl.cy + 0.5) / factor - 0.5
        s1, s2 = bl.s_across / factor, bl.s_along / factor
        r = int(np.ceil(3.0 * max(s1, s2)))
        x0, x1 = max(0, int(cx) - r), min(w, int(cx) + r + 1)
        y0, y1 = max(0, int(cy) - r), min(h, int(cy) + r + 1)
        if x0 >= x1 or y0 >= y1:
            continue
        yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
        dx, dy = xx - np.float32(cx), yy - np.float32(cy)
        c, s = np.float32(np.cos(bl.angle)), np.float32(np.sin(bl.angle))
        a = (c * dx + s * dy) / np.float32(s2)
        b = (-s * dx + c * dy) / np.float32(s1)
        g = np.float32(bl.amp) * np.exp(np.float32(-0.5) * (a * a + b * b))
        img[y0:y1, x0:x1, 1] += g
        img[y0:y1, x0:x1, 0] += g * np.float32(bl.blue)
        img[y0:y1, x0:x1, 2] += g * np.float32(bl.red)


def add_blobs(img: F32, water: WaterModel, rng: np.random.Generator) -> None:
    """Draw green distractor blobs (some elongated, stripe-like) in place on a float32 BGR image."""
    paint_blobs(img, draw_blobs(img.shape[0], img.shape[1], water, rng))


def add_snow(img: F32, water: WaterModel, rng: np.random.Generator) -> None:
    """Draw marine snow (small bright whitish dots, 0.6-2 px sigma) in place."""
    h, w = img.shape[:2]
    n = water.snow
    if n <= 0:
        return
    cx = rng.uniform(0, w, n)
    cy = rng.uniform(0, h, n)
    sig = rng.uniform(0.6, 2.0, n)
    amp = rng.uniform(20.0, 170.0, n)
    k = np.arange(-6, 7)
    xs = np.floor(cx)[:, None, None] + k[None, None, :]
    ys = np.floor(cy)[:, None, None] + k[None, :, None]
    val = amp[:, None, None] * np.exp(
        -0.5 * (((xs - cx[:, None, None]) ** 2 + (ys - cy[:, None, None]) ** 2) / sig[:, None, None] ** 2)
    )
    xs, ys = np.broadcast_arrays(xs, ys)
    ok = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h) & (val > 0.05)
    pix = (ys[ok] * w + xs[ok]).astype(np.int64)
    flat = img.reshape(-1)
    for ch, gain in ((0, 0.9), (1, 1.0), (2, 0.7)):
        np.add.at(flat, pix * 3 + ch, (gain * val[ok]).astype(np.float32))


def apply_speckle(laser_map: F32, water: WaterModel, rng: np.random.Generator) -> None:
    """Multiply the stripe intensity map by a granular speckle pattern (mean 1), in place."""
    if water.speckle <= 0:
        return
    ys, xs = np.nonzero(laser_map > 1e-3)
    if ys.size == 0:
        return
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    noise = rng.standard_normal((y1 - y0, x1 - x0)).astype(np.float32)
    noise = np.asarray(cv2.GaussianBlur(noise, (0, 0), 0.8), np.float32)
    noise /= max(float(noise.std()), 1e-6)
    laser_map[y0:y1, x0:x1] *= np.clip(1.0 + water.speckle * noise, 0.0, None)


_NOISE_BANK: dict[tuple[int, int], F32] = {}
_BANK_PAD = 61


def _noise_bank(h: int, w: int) -> F32:
    """A fixed bank of unit Gaussian noise, (H + pad, W + pad, 3) float32, generated once per image size."""
    key = (h, w)
    bank = _NOISE_BANK.get(key)
    if bank is None:
        bank = np.random.default_rng(20240601).standard_normal((h + _BANK_PAD, w + _BANK_PAD, 3), np.float32)
        if len(_NOISE_BANK) > 4:
            _NOISE_BANK.clear()
        _NOISE_BANK[key] = bank
    return bank


def add_sensor_noise(img: F32, water: WaterModel, rng: np.random.Generator) -> None:
    """Add Gaussian read noise and signal-dependent shot noise, in place (float32 BGR, DN).

    The unit noise is a randomly offset, sign-flipped window of a fixed noise bank (fresh Gaussian noise for
    6 M values costs more than the rest of a render); the window is drawn from ``rng``, so a render is
    deterministic for its seed and renders with different seeds get different noise. ``img`` is (H, W, 3)
    or a (H, W) Bayer mosaic.
    """
    if water.read_noise_dn <= 0 and water.shot_noise_gain <= 0:
        return
    h, w = img.shape[:2]
    bank = _noise_bank(h, w)
    oy, ox = (int(x) for x in rng.integers(0, _BANK_PAD, 2))
    sign = np.float32(1.0 if rng.uniform() < 0.5 else -1.0)
    noise = bank[oy : oy + h, ox : ox + w]
    if img.ndim == 2:
        noise = np.ascontiguousarray(noise[:, :, 0])
    if water.shot_noise_gain > 0:
        # img >= 0 here (every layer adds light): sd = sqrt(read^2 + img / gain), all in OpenCV (one pass each)
        sd = img * np.float32(1.0 / water.shot_noise_gain)
        sd += np.float32(water.read_noise_dn**2)
        cv2.sqrt(sd, sd)
        cv2.multiply(sd, noise, sd)
        if sign < 0:
            cv2.subtract(img, sd, img)
        else:
            cv2.add(img, sd, img)
    else:
        cv2.scaleAdd(noise, float(sign * water.read_noise_dn), img, img)


def finish(img: F32, water: WaterModel, rng: np.random.Generator) -> NDArray[np.uint8]:
    """Sensor noise, 8-bit quantisation (saturating at 255), optional Bayer mosaic/demosaic and JPEG.

    Args:
        img: (H, W, 3) float32 BGR in DN, light only (>= 0); modified in place.

    Returns:
        (H, W, 3) uint8 BGR.
    """
    if water.bayer:
        mosaic = np.empty(img.shape[:2], np.float32)
        mosaic[0::2, 0::2] = img[0::2, 0::2, 2]  # R
        mosaic[0::2, 1::2] = img[0::2, 1::2, 1]  # G
        mosaic[1::2, 0::2] = img[1::2, 0::2, 1]  # G
        mosaic[1::2, 1::2] = img[1::2, 1::2, 0]  # B
        add_sensor_noise(mosaic, water, rng)
        np.maximum(mosaic, 0.0, out=mosaic)
        raw = np.asarray(cv2.convertScaleAbs(mosaic), np.uint8)
        code = getattr(cv2, "COLOR_BayerRGGB2BGR", cv2.COLOR_BayerBG2BGR)
        image = np.asarray(cv2.cvtColor(raw, code), np.uint8)
    else:
        add_sensor_noise(img, water, rng)
        np.maximum(img, 0.0, out=img)  # cheap; convertScaleAbs would fold negative values up
        image = np.asarray(cv2.convertScaleAbs(img), np.uint8)  # rounds and saturates at 255
    if water.jpeg_quality > 0:
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(min(water.jpeg_quality, 100))])
        if ok:
            image = np.asarray(cv2.imdecode(buf, cv2.IMREAD_COLOR), np.uint8)
    return image
