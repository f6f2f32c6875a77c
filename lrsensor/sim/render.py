"""Rendering: trace each laser fan into the scene, draw the stripes exactly, add water and sensor effects.

The stripe of a laser is sampled densely along its fan (adaptive, so that consecutive visible samples are at
most ``LaserModel.max_gap_px`` apart in the image and occlusion edges are located to ~1e-6 rad). The image of
the stripe is drawn per image column (or per row where the stripe is steeper than 45 degrees) as a Gaussian
ridge profile evaluated at the exact sub-pixel centre, so the intensity centroid of each column is the true
projected centre (before noise and 8-bit rounding). The ground truth (:class:`Truth`) keeps the dense
samples: body-frame hit points, their distorted pixel coordinates (as ``cv2.projectPoints`` gives) and the
surface hit.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..calibration import Calibration
from ..errors import SimulationError
from ..frames import Pose, body_to_ned
from .scene import Rectangle, Scene
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

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
F32 = NDArray[np.float32]


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


@dataclass(frozen=True)
class LaserTruth:
    """Ground truth of one laser's stripe: the dense visible samples, ordered along the fan.

    The samples are those the camera sees inside the image, plus one sample beyond the image border at
    each end of a stripe piece (so that interpolation covers every column up to the border).

    Attributes:
        index, name: the laser's index in the calibration and its name.
        theta_rad: (N,) fan angle of each sample (positive toward body +y for an untilted laser).
        points_body: (N, 3) true hit points in the body frame, metres.
        uv: (N, 2) their exact projected pixels (distorted, as ``cv2.projectPoints`` gives).
        surface_id: (N,) id of the surface hit (index into the scene's surfaces).
        segment: (N,) index of the continuous stripe piece each sample belongs to (pieces end at occlusion
            edges, shadows, surface changes and the image border).
        peak_dn: (N,) peak of the stripe profile (green channel, before clipping), DN.
        sigma_px: (N,) Gaussian sigma of the stripe profile across the stripe, pixels.
        range_m: (N,) distance from the camera centre to the point, metres.
    """

    index: int
    name: str
    theta_rad: FloatArray
    points_body: FloatArray
    uv: FloatArray
    surface_id: IntArray
    segment: IntArray
    peak_dn: FloatArray
    sigma_px: FloatArray
    range_m: FloatArray

    def __len__(self) -> int:
        return int(self.points_body.shape[0])

    def _pieces(self) -> list[NDArray[np.intp]]:
        """Index arrays of the u-monotonic pieces of each segment."""
        out: list[NDArray[np.intp]] = []
        for s in np.unique(self.segment):
            idx = np.flatnonzero(self.segment == s)
            if idx.size < 2:
                continue
            du = np.diff(self.uv[idx, 0])
            sign = np.sign(du)
            breaks = np.flatnonzero((sign[1:] != sign[:-1]) | (sign[1:] == 0)) + 1
            start = 0
            for b in [*breaks.tolist(), du.size]:
                piece = idx[start : b + 1]
                if piece.size >= 2 and piece.size > 1 and self.uv[piece[-1], 0] != self.uv[piece[0], 0]:
                    out.append(piece if self.uv[piece[-1], 0] > self.uv[piece[0], 0] else piece[::-1])
                start = b
        return out

    def at_columns(self, u: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Truth at image columns ``u`` (M,): stripe centre ``v`` (M,), body points (M, 3), peak DN (M,).

        Interpolated linearly along the dense samples (spacing <= ``max_gap_px``); NaN where the laser is not
        visible in that column. Where two stripe pieces cover a column the brighter one is given.
        """
        v, pts, peak, _ = self._interp_columns(u)
        return v, pts, peak

    def theta_at_columns(self, u: Sequence[float] | FloatArray) -> FloatArray:
        """Fan angle (M,) of the laser ray seen at columns ``u``, radians; NaN where not visible."""
        return self._interp_columns(u)[3]

    def _interp_columns(self, u: Sequence[float] | FloatArray) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        uq = np.asarray(u, dtype=float).reshape(-1)
        v = np.full(uq.shape, np.nan)
        th = np.full(uq.shape, np.nan)
        pts = np.full((uq.size, 3), np.nan)
        peak = np.full(uq.shape, -np.inf)
        for piece in self._pieces():
            pu = self.uv[piece, 0]
            inside = (uq >= pu[0]) & (uq <= pu[-1])
            if not np.any(inside):
                continue
            q = uq[inside]
            pk = np.interp(q, pu, self.peak_dn[piece])
            better = pk > peak[inside]
            sel = np.flatnonzero(inside)[better]
            q = q[better]
            v[sel] = np.interp(q, pu, self.uv[piece, 1])
            th[sel] = np.interp(q, pu, self.theta_rad[piece])
            for k in range(3):
                pts[sel, k] = np.interp(q, pu, self.points_body[piece, k])
            peak[sel] = pk[better]
        peak[~np.isfinite(v)] = np.nan
        return v, pts, peak, th


@dataclass(frozen=True)
class Truth:
    """Ground truth of a render.

    Attributes:
        lasers: per-laser stripe truth (index = laser index of the calibration).
        scene: the scene as given (body or NED frame).
        scene_body: the scene in the body frame at the render's pose (surface ids are the same).
        pose: the vehicle pose in NED (None for body-frame scenes).
        width, height: image size, pixels.
    """

    lasers: tuple[LaserTruth, ...]
    scene: Scene
    scene_body: Scene
    pose: Pose | None
    width: int
    height: int

    def v_at_columns(self, laser: int, u: Sequence[float] | FloatArray | None = None) -> FloatArray:
        """True stripe centre row ``v`` (M,) of ``laser`` at columns ``u`` (default: every column); NaN = unseen."""
        cols = np.arange(self.width, dtype=float) if u is None else np.asarray(u, dtype=float)
        return self.lasers[laser].at_columns(cols)[0]

    def points_at_columns(self, laser: int, u: Sequence[float] | FloatArray | None = None) -> FloatArray:
        """True body-frame points (M, 3) of ``laser`` seen at columns ``u`` (default: every column); NaN = unseen."""
        cols = np.arange(self.width, dtype=float) if u is None else np.asarray(u, dtype=float)
        return self.lasers[laser].at_columns(cols)[1]

    def visible_columns(self, laser: int, min_peak_dn: float = 0.0) -> IntArray:
        """Integer image columns where ``laser``'s stripe is visible (peak above ``min_peak_dn``), sorted."""
        cols = np.arange(self.width, dtype=float)
        v, _, peak = self.lasers[laser].at_columns(cols)
        ok = np.isfinite(v) & (np.nan_to_num(peak, nan=-1.0) > min_peak_dn)
        return np.flatnonzero(ok).astype(np.int64)

    def true_points_on_rays(self, points_body: FloatArray, camera_center_body: FloatArray) -> FloatArray:
        """The first scene point (N, 3) on the camera ray through each measured point (N, 3), body frame.

        With it the relative range error of any measurement is ``(|p - C| - |p_true - C|) / |p_true - C|``,
        whatever column it came from. NaN rows where the ray hits nothing.
        """
        p = np.asarray(points_body, dtype=float).reshape(-1, 3)
        C = np.asarray(camera_center_body, dtype=float).reshape(3)
        d = p - C
        t, _, _ = self.scene_body.raycast(C, d)
        out = C + t[:, None] * d
        out[~np.isfinite(t)] = np.nan
        return out

    def all_points(self) -> tuple[FloatArray, IntArray]:
        """All visible dense samples: body points (N, 3) and their laser index (N,)."""
        if not self.lasers:
            return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
        pts = np.concatenate([lt.points_body for lt in self.lasers])
        idx = np.concatenate([np.full(len(lt), lt.index, dtype=np.int64) for lt in self.lasers])
        return pts, idx

    def boards(self) -> list[dict[str, Any]]:
        """Checkerboards of the scene: body-frame inner corners (rows*cols, 3), the wall plane, board size."""
        out = []
        for sid, s in enumerate(self.scene_body.surfaces):
            if isinstance(s, Rectangle) and s.board is not None:
                n = s.normal
                out.append(
                    {
                        "surface_id": sid,
                        "cols": s.board.cols,
                        "rows": s.board.rows,
                        "square_m": s.board.square_m,
                        "corners_body": s.board_corners(),
                        "plane_normal_body": n,
                        "plane_d_body": float(-n @ np.asarray(s.center)),
                    }
                )
        return out

    def to_dict(self, max_points: int | None = None) -> dict[str, Any]:
        """JSON-ready truth: surfaces (body frame, and NED when a pose is set), boards, per-laser points."""
        lasers = []
        for lt in self.lasers:
            step = 1 if max_points is None or len(lt) <= max_points else math.ceil(len(lt) / max_points)
            cols = self.visible_columns(lt.index)
            lasers.append(
                {
                    "index": lt.index,
                    "name": lt.name,
                    "n_samples": len(lt),
                    "visible_columns": int(cols.size),
                    "points_body": np.round(lt.points_body[::step], 7).tolist(),
                    "uv": np.round(lt.uv[::step], 5).tolist(),
                    "surface_id": lt.surface_id[::step].tolist(),
                }
            )
        out: dict[str, Any] = {
            "width": self.width,
            "height": self.height,
            "frame_of_points": "body",
            "surfaces_body": self.scene_body.to_dicts(),
            "boards": [
                {
                    "surface_id": b["surface_id"],
                    "cols": b["cols"],
                    "rows": b["rows"],
                    "square_m": b["square_m"],
                    "corners_body": np.asarray(b["corners_body"]).tolist(),
                    "plane_normal_body": np.asarray(b["plane_normal_body"]).tolist(),
                    "plane_d_body": b["plane_d_body"],
                }
                for b in self.boards()
            ],
            "lasers": lasers,
        }
        if self.pose is not None:
            p = self.pose
            out["pose_ned"] = {
                "north_m": p.north_m,
                "east_m": p.east_m,
                "down_m": p.down_m,
                "roll_rad": p.roll_rad,
                "pitch_rad": p.pitch_rad,
                "yaw_rad": p.yaw_rad,
            }
            out["surfaces_ned"] = self.scene.to_dicts()
        return out

    def to_json(self, max_points: int | None = 4000) -> str:
        """:meth:`to_dict` as JSON text."""
        return json.dumps(self.to_dict(max_points))

    def points_ned(self) -> FloatArray:
        """All visible truth points in NED (N, 3) (needs a pose)."""
        if self.pose is None:
            msg = "this render has no vehicle pose: its truth is in the body frame only"
            raise SimulationError(msg)
        return body_to_ned(self.all_points()[0], self.pose)


@dataclass(frozen=True)
class Render:
    """The result of :func:`render`.

    Attributes:
        image: (H, W, 3) uint8 BGR, as ``cv2.imread`` gives.
        calibration: the TRUE calibration used to render (tilted lasers, distortion and all).
        truth: the ground truth.
        layers: float32 layers when requested (``"laser"``: the stripe map in DN before noise, (H, W)).
    """

    image: NDArray[np.uint8]
    calibration: Calibration
    truth: Truth
    layers: dict[str, F32] = field(default_factory=dict)


# --------------------------------------------------------------------------- fan tracing
@dataclass
class _Samples:
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


def _trace_samples(
    scene: Scene,
    calib: Calibration,
    origin: FloatArray,
    a: FloatArray,
    b: FloatArray,
    theta: FloatArray,
    max_range_m: float,
    margin_px: float,
) -> _Samples:
    d = np.cos(theta)[:, None] * a + np.sin(theta)[:, None] * b
    t, sid, nrm = scene.raycast(origin, d)
    hit = np.isfinite(t) & (t <= max_range_m)
    p = origin + np.where(hit, t, 0.0)[:, None] * d
    C = calib.camera_center_body
    dc = p - C
    tc, _, _ = scene.raycast(C, dc)
    seen = hit & (tc >= 1.0 - 1e-7)
    pc = calib.body_to_cam(p)
    uv = calib.camera.project(pc)
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
    return _Samples(theta, t, sid, p, uv, ok, cos_inc, np.linalg.norm(dc, axis=1), pc[:, 2])


def _merge(s: _Samples, n: _Samples) -> _Samples:
    order = np.argsort(np.concatenate([s.theta, n.theta]), kind="stable")
    return _Samples(*(np.concatenate([getattr(s, f), getattr(n, f)])[order] for f in _Samples.__dataclass_fields__))


def trace_fan(
    scene_body: Scene,
    calibration: Calibration,
    laser: int,
    model: LaserModel | None = None,
    *,
    margin_px: float = 12.0,
    theta_tol_rad: float = 2e-7,
    max_iterations: int = 24,
) -> tuple[_Samples, IntArray]:
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
    s = _trace_samples(scene_body, calibration, origin, a, b, theta, model.max_range_m, margin_px)
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
        s = _merge(s, _trace_samples(scene_body, calibration, origin, a, b, new_theta, model.max_range_m, margin_px))
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


def _stripe_photometry(
    s: _Samples, scene: Scene, calib: Calibration, laser: int, model: LaserModel, water: WaterModel
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


# --------------------------------------------------------------------------- stripe drawing
def _draw_run(
    prim: FloatArray, sec: FloatArray, amp: FloatArray, sig: FloatArray, n_prim: int, n_sec: int
) -> tuple[IntArray, IntArray, FloatArray]:
    """Profiles across one monotonic (increasing ``prim``) stripe run: (prim index, sec index, value) triples."""
    p0, p1 = float(prim[0]), float(prim[-1])
    c = np.arange(math.floor(p0 + 0.5), math.floor(p1 + 0.5) + 1, dtype=np.float64)
    c = c[(c >= 0) & (c < n_prim)]
    if c.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    cov = np.clip(np.minimum(c + 0.5, p1) - np.maximum(c - 0.5, p0), 0.0, 1.0)
    cc = np.clip(c, p0, p1)
    sc = np.interp(cc, prim, sec)
    a = np.interp(cc, prim, amp)
    sg = np.interp(cc, prim, sig)
    dp = np.diff(prim)
    with np.errstate(divide="ignore", invalid="ignore"):
        slope_iv = np.where(dp > 0, np.diff(sec) / dp, 0.0)
    mid = 0.5 * (prim[:-1] + prim[1:])
    slope = np.interp(cc, mid, slope_iv) if mid.size > 1 else np.full(cc.shape, slope_iv[0])
    sgc = sg * np.sqrt(1.0 + slope * slope)
    half = int(min(math.ceil(4.5 * float(sgc.max())) + 1, 80))
    k = np.arange(-half, half + 1, dtype=np.float64)
    rows = np.floor(sc)[:, None] + k[None, :]
    val = (a * cov)[:, None] * np.exp(-0.5 * ((rows - sc[:, None]) / sgc[:, None]) ** 2)
    cols = np.broadcast_to(c[:, None], rows.shape)
    ok = (rows >= 0) & (rows < n_sec) & (val > 1e-4)
    return cols[ok].astype(np.int64), rows[ok].astype(np.int64), val[ok]


def stripe_splats(
    uv: FloatArray, amp: FloatArray, sigma: FloatArray, segment: IntArray, width: int, height: int
) -> tuple[IntArray, IntArray, FloatArray]:
    """Pixel contributions of a stripe: rows (K,), columns (K,) and values (K,) in DN.

    The dense samples ``uv`` (N, 2) with peak ``amp`` (N,) and cross-stripe ``sigma`` (N,) pixels are drawn per
    continuous ``segment`` (N,) (-1 = skip): per image column where the stripe is flatter than 45 degrees, per
    row where it is steeper, each profile a Gaussian evaluated at the exact sub-pixel centre.
    """
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    vals: list[FloatArray] = []
    for sg in np.unique(segment[segment >= 0]):
        idx = np.flatnonzero(segment == sg)
        u, v = uv[idx, 0], uv[idx, 1]
        du, dv = np.diff(u), np.diff(v)
        steep = np.abs(dv) > np.abs(du)
        direction = np.where(steep, np.sign(dv), np.sign(du))
        key = steep.astype(np.int64) * 4 + direction.astype(np.int64)
        bounds = np.flatnonzero(key[1:] != key[:-1]) + 1
        start = 0
        for end in [*bounds.tolist(), du.size]:
            sl = slice(start, end + 1)
            start = end
            if direction[sl.start] == 0:
                continue
            ru, rv, ra, rs = u[sl], v[sl], amp[idx][sl], sigma[idx][sl]
            if direction[sl.start] < 0:
                ru, rv, ra, rs = ru[::-1], rv[::-1], ra[::-1], rs[::-1]
            if steep[sl.start]:
                r_i, c_i, val = _draw_run(rv, ru, ra, rs, height, width)
            else:
                c_i, r_i, val = _draw_run(ru, rv, ra, rs, width, height)
            rows.append(r_i)
            cols.append(c_i)
            vals.append(val)
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)


def accumulate_band(rows: IntArray, cols: IntArray, vals: FloatArray, width: int) -> tuple[int, F32]:
    """Sum pixel contributions into the smallest band of full-width rows: ``(first_row, band (R, W))``."""
    if rows.size == 0:
        return 0, np.zeros((0, width), np.float32)
    r0, r1 = int(rows.min()), int(rows.max()) + 1
    acc = np.bincount((rows - r0) * width + cols, weights=vals, minlength=(r1 - r0) * width)
    return r0, acc.reshape(r1 - r0, width).astype(np.float32)


def draw_stripe(uv: FloatArray, amp: FloatArray, sigma: FloatArray, segment: IntArray, width: int, height: int) -> F32:
    """The stripe intensity map (H, W) float32 of :func:`stripe_splats`."""
    out = np.zeros((height, width), np.float32)
    r0, band = accumulate_band(*stripe_splats(uv, amp, sigma, segment, width, height), width)
    out[r0 : r0 + band.shape[0]] = band
    return out


# --------------------------------------------------------------------------- glow and ambient light
@functools.lru_cache(maxsize=8)
def _low_res_rays(calib: Calibration, h: int, w: int) -> tuple[FloatArray, FloatArray]:
    """Body-frame viewing rays (M, 3) and their lengths (M,) of the quarter-resolution pixel centres."""
    hl, wl = low_res_shape(h, w)
    f = LOW_RES_FACTOR
    ys, xs = np.mgrid[0:hl, 0:wl]
    uv = np.stack([xs.ravel() * f + (f - 1) / 2.0, ys.ravel() * f + (f - 1) / 2.0], axis=1).astype(float)
    rays = calib.rays_body(uv)
    rays.setflags(write=False)
    norm = np.linalg.norm(rays, axis=1)
    norm.setflags(write=False)
    return rays, norm


def _glow(
    scene: Scene, calib: Calibration, laser: int, model: LaserModel, water: WaterModel, shape: tuple[int, int]
) -> F32:
    """Backscatter glow of one laser sheet at quarter resolution (:func:`low_res_shape`), float32 DN.

    Single-scattering radiance of the sheet seen along each camera ray: the ray crosses the laser plane at a
    point at distance ``s`` from the laser; if that point lies inside the fan and before the laser's first hit,
    it glows with ``exp(-c (s + r_cam)) / (s |cos a|)`` (sheet irradiance ~ 1/s, path through the sheet
    ~ 1/|cos a| for a ray at angle a to the sheet normal) times a phase factor ``1 / (1 + s / 0.5 m)`` that
    makes it brighter near the camera. Computed at quarter resolution and blurred by ``water.glow_sigma_px``
    (sheet thickness and multiple scattering); occlusion of the glow by objects between the camera and the
    sheet is ignored.
    """
    h, w = shape
    hl, wl = low_res_shape(h, w)
    f = LOW_RES_FACTOR
    origin, a, b = fan_basis(calib, laser)
    n = calib.lasers[laser].normal_body
    half = model.fan_angle_rad / 2.0
    # fan table: distance to the first hit per fan angle
    n_rays = 721
    theta_tab = np.linspace(-half, half, n_rays)
    d = np.cos(theta_tab)[:, None] * a + np.sin(theta_tab)[:, None] * b
    t_tab, _, _ = scene.raycast(origin, d)
    c = water.attenuation_per_m
    t_tab = np.minimum(t_tab, min(model.max_range_m, 8.0 / max(c, 0.2)))
    rays, norm = _low_res_rays(calib, h, w)
    C = calib.camera_center_body
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = rays @ n
        tp = ((origin - C) @ n) / denom
        p = C + tp[:, None] * rays
        q = p - origin
        s = np.linalg.norm(q, axis=1)
        th = np.arctan2(q @ b, q @ a)
        ok = np.isfinite(tp) & (tp > 0) & (np.abs(th) <= half)
        ok &= s < np.interp(th, theta_tab, t_tab)
        r_c = tp * norm
        cos_a = np.abs(denom) / norm
        val = np.exp(-c * (s + r_c)) / (np.maximum(s, 0.02) * np.maximum(cos_a, 0.02)) / (1.0 + s / 0.5)
    val = np.where(ok, val, 0.0).reshape(hl, wl).astype(np.float32)
    sig = max(water.glow_sigma_px * w / 1920.0 / f, 0.5)
    val = np.asarray(cv2.GaussianBlur(val, (0, 0), sig), np.float32)
    # 0.2: a gain of 1 gives a faint band of a few DN with the default laser power
    return val * np.float32(0.2 * water.backscatter * model.peak_dn_at_1m / 190.0)


def _ambient(scene: Scene, calib: Calibration, water: WaterModel, img: F32) -> None:
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
        rays = calib.rays_body(uv)
        t, sid, _ = scene.raycast(C, rays)
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
        uvc = calib.project_body(corners)
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
        rays = calib.rays_body(uv)
        t, sid, _ = scene.raycast(C, rays)
        # board coordinates of each pixel centre on the board's plane (occluders checked with sid)
        n = rect.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            tp = ((c0 - C) @ n) / (rays @ n)
        p = C + tp[:, None] * rays
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


# --------------------------------------------------------------------------- the renderer
def trace_truth(
    scene: Scene,
    calibration: Calibration,
    pose: Pose | None = None,
    laser_model: LaserModel | None = None,
    water: WaterModel | None = None,
    *,
    edge_tol_rad: float = 2e-7,
) -> tuple[Truth, list[tuple[_Samples, IntArray, FloatArray, FloatArray]]]:
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
        peak, sigma = _stripe_photometry(s, scene_body, calibration, i, model, water)
        raw.append((s, seg, peak, sigma))
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
    if water.backscatter > 0:
        for i in range(len(calibration.lasers)):
            low_extra += _glow(scene_body, calibration, i, model, water, (h, w))[:, :, None] * colour
        smooth = True
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
        _ambient(scene_body, calibration, water, img)
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
        speckle_band = band
        apply_speckle(speckle_band, water, rng)
        img[r0 : r0 + band.shape[0]] += speckle_band[:, :, None] * np.asarray(model.colour_bgr, np.float32)
    add_snow(img, water, rng)
    image = finish(img, water, rng)
    return Render(image=image, calibration=calibration, truth=truth, layers=layers)
