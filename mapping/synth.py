"""A small, fast ground-truth generator for the mapping tests and benchmarks (no rendering).

It ray-traces the two horizontal laser fans of the sensor (body planes z = -c and z = +c, paper eq. 17 mounting)
from a moving vehicle into a scene of rectangles and vertical cylinders in NED, and returns the true hit points
per frame. The simulator of the sensor core (``lrsensor.sim``) renders images; this module only needs geometry,
so mapping tests stay fast and independent of the image pipeline.

Scene convention: every face is a rectangle with a unit ``normal`` pointing into the water; a laser ray hits it
only from the front. The truth of a face is its plane ``normal . p + d = 0`` in NED.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose, body_to_ned, ned_to_body

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class Face:
    """A rectangle in NED: centre (3,), unit normal (3,) into the water, in-plane axis ``u`` (3,), half sizes."""

    name: str
    center: tuple[float, float, float]
    normal: tuple[float, float, float]
    u: tuple[float, float, float]
    half_u: float
    half_v: float

    @property
    def d(self) -> float:
        """Plane offset: ``normal . p + d = 0``."""
        return -float(np.dot(self.normal, self.center))

    @property
    def v(self) -> FloatArray:
        """Second in-plane axis, ``normal x u``."""
        return np.cross(np.array(self.normal), np.array(self.u))


@dataclass(frozen=True)
class Cylinder:
    """A vertical cylinder (a standing pipe): axis at (north, east), radius, from ``top_m`` to ``bottom_m`` down."""

    name: str
    north_m: float
    east_m: float
    radius_m: float
    top_m: float
    bottom_m: float


@dataclass(frozen=True)
class Scene:
    """Faces and cylinders in NED."""

    faces: tuple[Face, ...]
    cylinders: tuple[Cylinder, ...] = ()


def box_pillar(
    name: str, north_m: float, east_m: float, size_m: float, top_m: float, bottom_m: float, yaw_rad: float = 0.0
) -> list[Face]:
    """The four vertical faces of a square pillar (outward normals), centre (north, east), edge ``size_m``."""
    faces = []
    h = size_m / 2
    zc, hz = (top_m + bottom_m) / 2, (bottom_m - top_m) / 2
    for k, side in enumerate(("n", "e", "s", "w")):
        a = yaw_rad + k * math.pi / 2
        n = (math.cos(a), math.sin(a), 0.0)
        u = (-math.sin(a), math.cos(a), 0.0)
        c = (north_m + h * n[0], east_m + h * n[1], zc)
        faces.append(Face(f"{name}.{side}", c, n, u, h, hz))
    return faces


def tank(
    length_m: float = 8.0, width_m: float = 6.0, depth_m: float = 3.0, pillars: bool = True, pipe: bool = False
) -> Scene:
    """A box tank from (0, 0, 0) to (length, width, depth) NED, with walls facing inward, a floor, and by
    default two square pillars (0.5 m and 0.4 m, one turned 30 degrees); optionally a standing pipe."""
    L, W, D = length_m, width_m, depth_m
    faces = [
        Face("wall.south", (0.0, W / 2, D / 2), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), W / 2, D / 2),
        Face("wall.north", (L, W / 2, D / 2), (-1.0, 0.0, 0.0), (0.0, -1.0, 0.0), W / 2, D / 2),
        Face("wall.west", (L / 2, 0.0, D / 2), (0.0, 1.0, 0.0), (-1.0, 0.0, 0.0), L / 2, D / 2),
        Face("wall.east", (L / 2, W, D / 2), (0.0, -1.0, 0.0), (1.0, 0.0, 0.0), L / 2, D / 2),
        Face("floor", (L / 2, W / 2, D), (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), L / 2, W / 2),
    ]
    if pillars:
        faces += box_pillar("pillar1", 0.4 * L, 0.35 * W, 0.5, 0.0, D)
        faces += box_pillar("pillar2", 0.65 * L, 0.65 * W, 0.4, 0.0, D, yaw_rad=math.radians(30))
    cyl = (Cylinder("pipe", 0.5 * L, 0.8 * W, 0.1, 0.0, D),) if pipe else ()
    return Scene(tuple(faces), cyl)


@dataclass(frozen=True)
class Hits:
    """True laser hits of one frame: points (N, 3) NED, laser index (N,) 0 top / 1 bottom, surface (N,) index
    into ``scene.faces`` or ``-1 - k`` for cylinder k."""

    points_ned: FloatArray
    laser: NDArray[np.int64]
    surface: NDArray[np.int64]


def trace(
    scene: Scene,
    pose: Pose,
    n_rays: int = 1900,
    fan_deg: float = 120.0,
    baseline_m: float = 0.1,
    max_range_m: float = 6.0,
) -> Hits:
    """Intersect both laser fans (``n_rays`` each) with the scene from ``pose``; nearest front-facing hit."""
    R = pose.R_ned_from_body
    a = np.radians(np.linspace(-fan_deg / 2, fan_deg / 2, n_rays))
    dirs_b = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1)
    pts, lasers, surfs = [], [], []
    fn = np.array([f.normal for f in scene.faces], dtype=np.float64).reshape(-1, 3)
    fc = np.array([f.center for f in scene.faces], dtype=np.float64).reshape(-1, 3)
    fu = np.array([f.u for f in scene.faces], dtype=np.float64).reshape(-1, 3)
    fv = np.cross(fn, fu)
    fd = -np.einsum("ij,ij->i", fn, fc)
    hu = np.array([f.half_u for f in scene.faces])
    hv = np.array([f.half_v for f in scene.faces])
    for li, zb in enumerate((-baseline_m / 2, baseline_m / 2)):
        o = pose.p_ned + R @ np.array([0.0, 0.0, zb])
        dirs = dirs_b @ R.T
        best_t = np.full(n_rays, np.inf)
        best_s = np.full(n_rays, -999, dtype=np.int64)
        if fn.shape[0]:
            den = dirs @ fn.T  # (R, F)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = -(fn @ o + fd)[None, :] / den
            # in-plane coordinates of the hit: (o + t dir - c) . u = (o - c) . u + t (dir . u)
            ou = np.einsum("fk,fk->f", o[None, :] - fc, fu)
            ov = np.einsum("fk,fk->f", o[None, :] - fc, fv)
            hu_ = ou[None, :] + t * (dirs @ fu.T)
            hv_ = ov[None, :] + t * (dirs @ fv.T)
            ok = (den < -1e-9) & (t > 1e-6) & (np.abs(hu_) <= hu[None, :]) & (np.abs(hv_) <= hv[None, :])
            t = np.where(ok, t, np.inf)
            k_best = np.argmin(t, axis=1)
            t_best = t[np.arange(n_rays), k_best]
            hit_f = np.isfinite(t_best)
            best_t[hit_f] = t_best[hit_f]
            best_s[hit_f] = k_best[hit_f]
        for k, c in enumerate(scene.cylinders):
            ox, oy = o[0] - c.north_m, o[1] - c.east_m
            dx, dy = dirs[:, 0], dirs[:, 1]
            qa = dx * dx + dy * dy
            qb = 2 * (ox * dx + oy * dy)
            qc = ox * ox + oy * oy - c.radius_m**2
            disc = qb * qb - 4 * qa * qc
            with np.errstate(invalid="ignore", divide="ignore"):
                t = (-qb - np.sqrt(disc)) / (2 * qa)
            z = o[2] + t * dirs[:, 2]
            ok = (disc >= 0) & (t > 1e-6) & (z >= c.top_m) & (z <= c.bottom_m)
            better = ok & (t < best_t)
            best_t[better] = t[better]
            best_s[better] = -1 - k
        hit = best_t <= max_range_m
        pts.append(o + best_t[hit, None] * dirs[hit])
        lasers.append(np.full(int(hit.sum()), li, dtype=np.int64))
        surfs.append(best_s[hit])
    return Hits(np.concatenate(pts), np.concatenate(lasers), np.concatenate(surfs))


@dataclass(frozen=True)
class DiveFrame:
    """One frame of a simulated dive: capture time, true and estimated (noisy IMU) pose, hits.

    ``points_body`` (N, 3) is what the robot measures (true points in the body frame plus range noise);
    ``points_ned_est`` is what a base station computes when it trusts the pose: those points placed with the
    estimated pose (NaN rows when the pose has no horizontal fix, ``navigation="depth-only"``).
    """

    robot: str
    t_ns: int
    pose_true: Pose
    pose_est: Pose
    hits: Hits
    points_ned_est: FloatArray
    points_body: FloatArray


def _smooth_noise(rng: np.random.Generator, t: FloatArray, sigma: float, n_waves: int = 4) -> FloatArray:
    """A slowly varying zero-mean signal with standard deviation ~``sigma`` (sum of random sinusoids)."""
    out = np.zeros_like(t)
    for _ in range(n_waves):
        f = rng.uniform(0.02, 0.3)
        out += np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out * sigma * math.sqrt(2.0 / n_waves)


@dataclass(frozen=True)
class DivePlan:
    """A loop around a rectangle at a depth, yaw sweeping around the direction of travel.

    Attributes: waypoints (north, east) of the loop; depth_m; speed_mps; sweep amplitude/period of the yaw;
    pitch/roll oscillation amplitude (deg); heave amplitude (m); phase offset (s); ``look_deg``: a fixed yaw
    (deg) to sweep around instead of the direction of travel.
    """

    robot: str
    waypoints: tuple[tuple[float, float], ...]
    depth_m: float
    speed_mps: float = 0.3
    sweep_deg: float = 50.0
    sweep_period_s: float = 8.0
    tilt_deg: float = 3.0
    heave_m: float = 0.15
    phase_s: float = 0.0
    look_deg: float | None = None


def _path(plan: DivePlan, t: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    wp = np.array((*plan.waypoints, plan.waypoints[0]), dtype=np.float64)
    seg = np.diff(wp, axis=0)
    seglen = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seglen)])
    s = (plan.speed_mps * (t + plan.phase_s)) % cum[-1]
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    frac = (s - cum[i]) / seglen[i]
    pos = wp[i] + frac[:, None] * seg[i]
    heading = np.arctan2(seg[i, 1], seg[i, 0])
    return pos[:, 0], pos[:, 1], heading


def simulate_dive(
    scene: Scene,
    plans: list[DivePlan],
    duration_s: float,
    rate_hz: float = 30.0,
    n_rays: int = 1900,
    attitude_noise_deg: float = 0.2,
    position_noise_m: float = 0.015,
    position_walk_m_per_sqrt_s: float = 0.002,
    range_noise_m: float = 0.002,
    seed: int = 0,
    t0_ns: int = 1_700_000_000_000_000_000,
    bad_frame_fraction: float = 0.0,
    bad_frame_yaw_deg: float = 25.0,
    bad_frame_scale: float = 1.15,
    navigation: str | dict[str, str] = "good",
    launch_fix_s: float = 0.0,
) -> list[DiveFrame]:
    """Frames of all robots in capture-time order (robots interleaved as a base station would receive them).

    Attitude noise is white per frame (``attitude_noise_deg``); position noise is white per frame
    (``position_noise_m``) plus a random walk (``position_walk_m_per_sqrt_s``, dead-reckoning drift), as in
    ``lrsensor.sim.dive.ImuNoise``; range noise is white along each ray.

    ``bad_frame_fraction`` > 0 corrupts that fraction of the frames (drawn from a separate generator, so the
    other frames do not change) the way one wrongly triangulated image does (seen in the camera-in-the-loop demo
    near the tank's corners): all its body-frame points are turned about the vehicle's z axis by a random angle
    within +-``bad_frame_yaw_deg`` and scaled by a random factor in [1, ``bad_frame_scale``], so both stripes
    stay straight and parallel but land on a plane that is not there.

    ``navigation`` (one mode, or a mode per robot name): ``good`` is the noise above; ``drift`` and
    ``depth-only`` replace the estimated pose with :func:`lrsensor.sim.navigation.simulate_navigation`'s (DVL
    dead reckoning; attitude and depth with a launch fix only, kept for the first ``launch_fix_s``), drawn from
    a generator of their own per robot.
    """
    from lrsensor.sim.navigation import check_mode, simulate_navigation

    modes = {
        p.robot: check_mode(navigation if isinstance(navigation, str) else navigation.get(p.robot, "good"))
        for p in plans
    }
    rng = np.random.default_rng(seed)
    bad_rng = np.random.default_rng([seed, 1])
    t = np.arange(0.0, duration_s, 1.0 / rate_hz)
    frames: list[DiveFrame] = []
    per_robot: list[tuple[Any, ...]] = []
    for plan in plans:
        n, e, heading = _path(plan, t)
        w = 2 * np.pi / plan.sweep_period_s
        if plan.look_deg is not None:
            heading = np.full_like(heading, math.radians(plan.look_deg))
        yaw = heading + math.radians(plan.sweep_deg) * np.sin(w * (t + plan.phase_s))
        pitch = math.radians(plan.tilt_deg) * np.sin(0.7 * w * t + 1.0)
        roll = math.radians(plan.tilt_deg) * np.sin(1.3 * w * t + 2.0)
        down = plan.depth_m + plan.heave_m * np.sin(0.5 * w * t)
        dt = 1.0 / rate_hz
        walk = np.cumsum(rng.normal(0.0, position_walk_m_per_sqrt_s * math.sqrt(dt), size=(t.shape[0], 3)), axis=0)
        pos_err = rng.normal(0.0, position_noise_m, size=(t.shape[0], 3)) + walk
        att_err = rng.normal(0.0, math.radians(attitude_noise_deg), size=(t.shape[0], 3))
        nav = None
        if modes[plan.robot] != "good":
            truth = {"north_m": n, "east_m": e, "down_m": down, "roll_rad": roll, "pitch_rad": pitch, "yaw_rad": yaw}
            nav_rng = np.random.default_rng([seed, 2, sum(plan.robot.encode()), len(per_robot)])
            nav = simulate_navigation(modes[plan.robot], t, truth, nav_rng, launch_fix_s=launch_fix_s)
        per_robot.append((plan, n, e, down, roll, pitch, yaw, pos_err, att_err, nav))
    keys = ("north_m", "east_m", "down_m", "roll_rad", "pitch_rad", "yaw_rad")
    for k in range(t.shape[0]):
        for plan, n, e, down, roll, pitch, yaw, pos_err, att_err, nav in per_robot:
            true = Pose(float(n[k]), float(e[k]), float(down[k]), float(roll[k]), float(pitch[k]), float(yaw[k]))
            if nav is not None:
                est = Pose(*(float(nav[key][k]) for key in keys))
            else:
                est = Pose(
                    true.north_m + pos_err[k, 0],
                    true.east_m + pos_err[k, 1],
                    true.down_m + pos_err[k, 2],
                    true.roll_rad + att_err[k, 0],
                    true.pitch_rad + att_err[k, 1],
                    true.yaw_rad + att_err[k, 2],
                )
            hits = trace(scene, true, n_rays=n_rays)
            pb = ned_to_body(hits.points_ned, true)
            rng_b = np.linalg.norm(pb, axis=1, keepdims=True)
            pb = pb + pb / np.maximum(rng_b, 1e-9) * rng.normal(0.0, range_noise_m, size=(pb.shape[0], 1))
            if bad_frame_fraction > 0 and bad_rng.uniform() < bad_frame_fraction:
                a = math.radians(bad_rng.uniform(-bad_frame_yaw_deg, bad_frame_yaw_deg))
                turn = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
                pb = bad_rng.uniform(1.0, bad_frame_scale) * pb @ turn.T
            frames.append(DiveFrame(plan.robot, t0_ns + round(t[k] * 1e9), true, est, hits, body_to_ned(pb, est), pb))
    return frames


def two_rov_plans(length_m: float = 8.0, width_m: float = 6.0) -> list[DivePlan]:
    """Two robots looping the tank of :func:`tank` in opposite directions at different depths."""
    L, W = length_m, width_m
    loop = ((1.2, 1.2), (L - 1.2, 1.2), (L - 1.2, W - 1.2), (1.2, W - 1.2))
    return [
        DivePlan("rov1", loop, 1.0, phase_s=0.0),
        DivePlan("rov2", tuple(reversed(loop)), 1.8, sweep_period_s=10.0, phase_s=7.0),
    ]


@dataclass
class FaceTruth:
    """Per-face hit bookkeeping over a dive: points, and frames in which both lasers hit the face."""

    face: Face
    n_points: int = 0
    frames_both: int = 0
    robots: set[str] = field(default_factory=set)


def hit_faces(scene: Scene, frames: list[DiveFrame]) -> list[FaceTruth]:
    """How often each face of ``scene`` was hit during a dive."""
    out = [FaceTruth(f) for f in scene.faces]
    for fr in frames:
        s, las = fr.hits.surface, fr.hits.laser
        for k in np.unique(s[s >= 0]):
            sel = s == k
            out[k].n_points += int(sel.sum())
            out[k].robots.add(fr.robot)
            if np.any(las[sel] == 0) and np.any(las[sel] == 1):
                out[k].frames_both += 1
    return out


@dataclass
class FaceScore:
    """How the map represents one true face: matched plane ids, and the best match's errors."""

    face: Face
    hit: bool
    plane_ids: list[int] = field(default_factory=list)
    angle_deg: float = math.inf
    offset_m: float = math.inf


@dataclass
class MapScore:
    """Score of a map against the scene: per-face results and the planes that match no face."""

    faces: list[FaceScore]
    spurious: list[int]

    def missing(self, angle_deg: float = 2.0, offset_m: float = 0.05) -> list[str]:
        """Hit faces without a plane within the tolerances."""
        return [f.face.name for f in self.faces if f.hit and not (f.angle_deg <= angle_deg and f.offset_m <= offset_m)]

    def duplicates(self) -> list[str]:
        """Faces represented by more than one plane."""
        return [f.face.name for f in self.faces if len(f.plane_ids) > 1]

    def table(self) -> str:
        """A markdown table of the per-face results."""
        rows = ["| face | hit | planes | angle (deg) | offset (m) |", "|---|---|---|---|---|"]
        for f in self.faces:
            rows.append(
                f"| {f.face.name} | {'yes' if f.hit else 'no'} | {f.plane_ids} | {f.angle_deg:.2f} | {f.offset_m:.3f} |"
            )
        rows.append(f"\nspurious planes: {self.spurious}")
        return "\n".join(rows)


def score_map(
    planes: list[dict[str, object]],
    scene: Scene,
    hits: list[FaceTruth],
    min_points: int = 3000,
    min_frames_both: int = 30,
) -> MapScore:
    """Match map planes (``map_json()["planes"]``) to the scene's faces.

    A plane belongs to the face whose normal it matches within 15 degrees (same orientation: both point into the
    water), whose rectangle (inflated by 0.3 m) contains the plane's centroid, and whose plane lies within
    0.15 m of all the plane's extent corners; the closest such face wins. A face counts as *hit* when it got at
    least ``min_points`` true hits and both lasers hit it in at least ``min_frames_both`` frames. The errors of a
    face are those of its best plane: the angle between normals and the largest distance of the plane's extent
    corners to the true plane.
    """
    scores = [FaceScore(h.face, h.n_points >= min_points and h.frames_both >= min_frames_both) for h in hits]
    spurious: list[int] = []
    for p in planes:
        n = np.array(p["normal"], dtype=float)  # type: ignore[arg-type]
        ext = p["extent"]
        assert isinstance(ext, dict)
        cen = np.array(ext["centroid"], dtype=float)
        corners = np.array(ext["corners"], dtype=float)
        best: tuple[float, int, float, float] | None = None
        for k, fs in enumerate(scores):
            f = fs.face
            fn = np.array(f.normal)
            ang = math.degrees(math.acos(max(-1.0, min(1.0, float(n @ fn)))))
            if ang > 15.0:
                continue
            rel = cen - np.array(f.center)
            if abs(rel @ np.array(f.u)) > f.half_u + 0.3 or abs(rel @ f.v) > f.half_v + 0.3:
                continue
            off = float(np.max(np.abs(corners @ fn + f.d)))
            if off > 0.15:
                continue
            cost = off + ang / 100.0
            if best is None or cost < best[0]:
                best = (cost, k, ang, off)
        if best is None:
            spurious.append(int(p["id"]))  # type: ignore[call-overload]
            continue
        fs = scores[best[1]]
        fs.plane_ids.append(int(p["id"]))  # type: ignore[call-overload]
        if best[3] + best[2] / 100.0 < fs.offset_m + fs.angle_deg / 100.0:
            fs.angle_deg, fs.offset_m = best[2], best[3]
    return MapScore(scores, spurious)


def wall_yaw_deg(planes: list[dict[str, Any]], score: MapScore) -> list[float]:
    """The yaw error (deg; positive turns north towards east, the yaw's sense) of each plane of ``planes`` that
    ``score`` matched to a vertical face: the angle from the face's horizontal normal to the plane's. A map built at
    a heading off by a common angle has its walls turned by it."""
    by_id = {int(p["id"]): p for p in planes}
    out = []
    for fs in score.faces:
        fn = np.array(fs.face.normal, dtype=float)
        if abs(float(fn[2])) > 0.5:
            continue
        for pid in fs.plane_ids:
            n = np.array(by_id[pid]["normal"], dtype=float)
            out.append(math.degrees(math.atan2(fn[0] * n[1] - fn[1] * n[0], fn[0] * n[0] + fn[1] * n[1])))
    return out


def three_rov_plans(length_m: float = 8.0, width_m: float = 6.0) -> list[DivePlan]:
    """:func:`two_rov_plans` and a third robot on a tighter loop at 2.5 m, around the pillars."""
    L, W = length_m, width_m
    inner = ((2.0, 1.3), (L - 2.0, 1.3), (L - 2.0, W - 1.3), (2.0, W - 1.3))
    return [*two_rov_plans(length_m, width_m), DivePlan("rov3", inner, 2.5, speed_mps=0.25, sweep_period_s=9.0)]


@dataclass
class DiveMap:
    """A dive replayed into a map: the builder, and per robot the placed clouds' horizontal errors (m) and the
    yaw errors (deg) of the poses they were placed with, the clouds left unplaced, the navigation's wall time per
    cloud (s, empty when the poses were trusted), each robot's last estimate, the fleet frame, the scans whose
    registration constrained both horizontal axes; with smoothing, each smoothing run's wall time (s); and per
    robot the poses its clouds are in the map with at the end (t_ns -> Pose, map frame) and their horizontal
    errors (m, served in NED)."""

    builder: Any
    position_error_m: dict[str, list[float]] = field(default_factory=dict)
    yaw_error_deg: dict[str, list[float]] = field(default_factory=dict)
    unplaced: dict[str, int] = field(default_factory=dict)
    nav_cost_s: list[float] = field(default_factory=list)
    estimates: dict[str, Any] = field(default_factory=dict)
    frame: Any = None
    constrained_scans: int = 0
    smooth_cost_s: list[float] = field(default_factory=list)
    #: how long each smoothing run held the map thread (all of it, unless it ran in the background), s
    smooth_hold_s: list[float] = field(default_factory=list)
    final_error_m: dict[str, list[float]] = field(default_factory=dict)
    placed: dict[str, dict[int, Pose]] = field(default_factory=dict)
    #: each frame's time on the map thread (s): the smoother's step, navigation and placing the cloud
    step_s: list[float] = field(default_factory=list)
    #: per robot whose clouds were held until verified, what the hold did (``CloudHold.counts``; its dropped
    #: clouds are in ``unplaced`` too)
    hold: dict[str, dict[str, float]] = field(default_factory=dict)

    def planes(self) -> list[dict[str, Any]]:
        """The served map's planes (in NED: turned by the navigation's frame when there is one)."""
        planes: list[dict[str, Any]] = self.builder.map_json()["planes"]
        return planes if self.frame is None else [self.frame.plane_json(p) for p in planes]


def replay_dive(
    frames: list[DiveFrame],
    navigate: bool,
    cfg: Any = None,
    nav_cfg: Any = None,
    smoother: Any = None,
    background: bool | str = False,
    realtime: bool = False,
    graph_cfg: Any = None,
    range_error_per_px: dict[str, float] | None = None,
) -> DiveMap:
    """Feed a simulated dive into a :class:`mapping.MapBuilder` the way the base station does.

    ``navigate`` False: trust the poses (clouds without a horizontal fix are left out, as ``unplaced``).
    True: correct each cloud's pose with :class:`mapping.navigation.Navigator` against the map's planes first,
    and place the cloud while the estimator says so. With a ``smoother`` (:class:`mapping.smoother.SmootherConfig`),
    past poses are smoothed and their clouds re-placed (``background``: see
    :class:`mapping.smoother.FleetPlacements`; ``"wait"`` measures what a run would hold the map thread for).
    ``realtime``: each frame is fed at its capture time (from the first frame's, on the wall clock), as a base
    station receives a live dive: background runs then truly overlap the feed; :attr:`DiveMap.step_s` keeps each
    frame's time on the map thread (smoother step, navigation and placing). ``graph_cfg``: the pose graphs' tuning
    (:class:`mapping.graph_config.GraphConfig`) for robots without a fix, with ``NavConfig.graph_without_fix``.
    ``range_error_per_px``: robot -> its calibration's range error per pixel (the clouds' range noise,
    :meth:`mapping.MapBuilder.set_range_error`; absent: none, the fixed thresholds).
    """
    import time

    from .builder import MapBuilder
    from .navigation import Navigator
    from .smoother import FleetPlacements
    from .types import MapConfig

    b = MapBuilder(cfg or MapConfig())
    for robot, per_px in (range_error_per_px or {}).items():
        b.set_range_error(robot, per_px)
    nav = Navigator(nav_cfg, smoother) if navigate else None
    if nav is not None:
        nav.graph_cfg = graph_cfg  # the pose graphs' tuning (mapping.graph_config.GraphConfig; None: its default)
    out = DiveMap(b)
    min_pts = nav.cfg.min_landmark_points if nav is not None else 0
    placed: dict[str, dict[int, Pose]] = {}
    truth = {(f.robot, f.t_ns): f.pose_true for f in frames}
    fleet = FleetPlacements(nav, b, background) if nav is not None and smoother is not None else None

    def follow() -> None:
        # the smoother's revisions of the poses still in its windows (older ones no longer move)
        assert fleet is not None
        for robot, poses in fleet.poses.items():
            placed.setdefault(robot, {}).update(poses)

    def place(robot: str, t_ns: int, pose: Pose, pts: Any) -> None:
        b.add_cloud(robot, t_ns, pts, pose)
        if fleet is not None:
            fleet.placed(robot, t_ns, pose)
        placed.setdefault(robot, {})[t_ns] = pose
        served = nav.frame().pose(pose) if nav is not None else pose
        tp = truth[(robot, t_ns)]
        out.position_error_m.setdefault(robot, []).append(math.hypot(served.north_m - tp.north_m,
                                                                     served.east_m - tp.east_m))  # fmt: skip
        dyaw = math.degrees(math.remainder(served.yaw_rad - tp.yaw_rad, 2 * math.pi))
        out.yaw_error_deg.setdefault(robot, []).append(dyaw)

    wall0 = time.perf_counter()
    step0 = 0.0
    for f in frames:
        if realtime:
            due = wall0 + (f.t_ns - frames[0].t_ns) * 1e-9
            time.sleep(max(0.0, due - time.perf_counter()))
        step0 = time.perf_counter()
        if fleet is not None:
            runs = len(fleet.runs_s)
            fleet.step(f.robot, f.t_ns)
            if len(fleet.runs_s) > runs:
                follow()
        pose = f.pose_est
        if nav is not None:
            t0 = time.perf_counter()
            est = nav.update(f.robot, f.t_ns, f.pose_est, f.points_body, b.landmarks(min_pts))
            out.nav_cost_s.append(time.perf_counter() - t0)
            out.estimates[f.robot] = est
            out.constrained_scans += int(est.constrained["north"] and est.constrained["east"])
            for t_held, p_held, pts_held in nav.released(f.robot):  # a held robot's clouds its check vouched for
                place(f.robot, t_held, p_held, body_to_ned(pts_held, p_held))
            if est.pose is None or not est.placed:
                if not est.held:
                    out.unplaced[f.robot] = out.unplaced.get(f.robot, 0) + 1
                out.step_s.append(time.perf_counter() - step0)
                continue
            pose = est.pose
            pts = body_to_ned(f.points_body, pose)
        else:
            if not (math.isfinite(pose.north_m) and math.isfinite(pose.east_m)):
                out.unplaced[f.robot] = out.unplaced.get(f.robot, 0) + 1
                continue
            pts = f.points_ned_est
        place(f.robot, f.t_ns, pose, pts)
        out.step_s.append(time.perf_counter() - step0)
    if nav is not None:  # the end: held clouds checked alone
        held_lm = b.landmarks(min_pts)
        for robot in sorted(nav.robots):
            for t_held, p_held, pts_held in nav.settle(robot, held_lm):
                place(robot, t_held, p_held, body_to_ned(pts_held, p_held))
        for robot in nav.robots:
            counts = nav.hold_counts(robot)
            if counts is not None:
                out.hold[robot] = counts
                out.unplaced[robot] = out.unplaced.get(robot, 0) + int(counts["dropped"])
    b.flush()
    if fleet is not None:
        fleet.step("", 0, force=True)  # the end of the dive: the map as the last smoothing leaves it
        follow()
        out.smooth_cost_s = fleet.runs_s
        out.smooth_hold_s = fleet.holds_s
    out.frame = nav.frame() if nav is not None else None
    # the poses each cloud is in the map with now (after any smoothing), against the truth
    out.final_error_m = {}
    for robot, poses in placed.items():
        errs = []
        for t, p in poses.items():
            served = out.frame.pose(p) if out.frame is not None else p
            tp = truth[(robot, t)]
            errs.append(math.hypot(served.north_m - tp.north_m, served.east_m - tp.east_m))
        out.final_error_m[robot] = errs
    out.placed = placed
    return out
