"""A robot's window of clouds in the map builder: when its extraction is due, and what the extraction observes.

Part of :class:`mapping.MapBuilder` (the module docstring there gives the cost model and the threading). Each
robot has one :class:`RobotWindow`: the quantized, thinned clouds it took (:func:`thin_cloud`), the newest
``window_clouds`` of them kept as context, and how many arrived since its last extraction. :func:`extraction_due` and
:func:`spans_time` are the triggers; :func:`extract_window` runs :func:`mapping.planes.extract_planes` on the whole
window and turns the planes found into observations of the new clouds' points only (every point enters the map's
statistics exactly once), checked for support by several frames and for curvature within single frames.

Nothing here takes the builder's lock: the builder copies a window under it and extracts outside it.

Frames and units: NED; points are int32 quanta of ``MapConfig.quantum_m`` metres, times integer ns.
"""

from __future__ import annotations

import zlib
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .frame_checks import frame_sagitta, frame_support
from .ned import quantize
from .noisy_faces import expected_error_m, noise_quanta2, prior_active
from .plane_map import PlaneRecord
from .planes import claim_points, extract_planes, pack_keys
from .range_noise import window_noise
from .replace import Placement
from .types import MapConfig

FloatArray = NDArray[np.float64]


@dataclass
class WindowCloud:
    """One cloud in a robot's window: capture time (ns), thinned points and vehicle position (quanta)."""

    t_ns: int
    points_q: NDArray[np.int32]
    vehicle_q: NDArray[np.int64]
    noise_per_m: float = 0.0  # its range noise k (mapping.range_noise)


@dataclass
class RobotWindow:
    """A robot's window: its kept clouds, and the clouds and points that arrived since its last extraction."""

    clouds: deque[WindowCloud] = field(default_factory=deque)
    n_new: int = 0
    new_points: int = 0


@dataclass
class WindowObservations:
    """What one extraction of a window observed.

    Attributes:
        records: the plane observations of the window's new clouds, not merged.
        placements: with ``keep_placements``, each record's :class:`~mapping.replace.Placement` (record first).
        curved: claims dropped as curved (their stripes bulge within single frames).
        single_frame: claims dropped for too few supporting frames.
    """

    records: list[PlaneRecord]
    placements: list[tuple[PlaneRecord, Placement]]
    curved: int
    single_frame: int


def thin_cloud(p: FloatArray, veh: FloatArray, cfg: MapConfig) -> NDArray[np.int32]:
    """Range-gate, quantize and thin one cloud: (K, 3) int32 quanta.

    Thinning keeps a point when its ``cloud_voxel_m`` voxel differs from the previous point's: the stripes
    arrive in column order, so this removes the near-duplicates of near ranges in O(N) without sorting.
    """
    if p.shape[0]:
        d = p - veh
        p = p[np.einsum("ij,ij->i", d, d) <= cfg.max_range_m**2]
    pq = quantize(p, cfg.quantum_m, "cloud")
    vq = max(1, round(cfg.cloud_voxel_m / cfg.quantum_m))
    if pq.shape[0] > 1 and vq > 1:
        keys = pack_keys(np.floor_divide(pq, vq).astype(np.int64))
        keep = np.empty(keys.shape[0], dtype=bool)
        keep[0] = True
        np.not_equal(keys[1:], keys[:-1], out=keep[1:])
        pq = pq[keep]
    return pq


def extraction_due(win: RobotWindow, cfg: MapConfig) -> bool:
    """Whether the window's new clouds make an extraction due (by clouds, points or capture time)."""
    if win.n_new >= cfg.extract_every_clouds or win.new_points >= cfg.extract_every_points:
        return True
    return win.n_new >= 2 and spans_time(win, win.clouds[-1].t_ns, cfg)


def spans_time(win: RobotWindow, t_ns: int, cfg: MapConfig) -> bool:
    """Whether the window's new clouds, up to capture time ``t_ns``, span ``extract_every_s`` (the time rule
    of an extraction; off when it is 0)."""
    if cfg.extract_every_s <= 0 or win.n_new == 0:
        return False
    first_new = win.clouds[len(win.clouds) - win.n_new]
    return t_ns - first_new.t_ns >= cfg.extract_every_s * 1e9


def extract_window(
    robot: str, clouds: list[WindowCloud], n_new: int, cfg: MapConfig, keep_placements: bool
) -> WindowObservations | None:
    """Extract ``robot``'s window ``clouds`` (oldest first; the last ``n_new`` are new): the observations of its
    new clouds' points, or None when the new clouds hold no point (no extraction ran)."""
    q = cfg.quantum_m
    new = clouds[len(clouds) - n_new :]
    lens = np.array([c.points_q.shape[0] for c in clouds], dtype=np.int64)
    n_total = int(lens.sum())
    n_eligible = int(lens[len(clouds) - n_new :].sum())
    if n_eligible == 0:
        return None
    pts_q = np.concatenate([c.points_q for c in clouds]) if n_total else np.zeros((0, 3), np.int32)
    veh_q = np.repeat(np.stack([c.vehicle_q for c in clouds]), lens, axis=0)
    origin_m = np.round(new[0].vehicle_q * q / 3.0) * 3.0
    pts_m = pts_q * q - origin_m
    veh_m = veh_q * q - origin_m
    seed = (cfg.seed * 1_000_003 + zlib.crc32(robot.encode()) + new[0].t_ns) % (2**31 - 1)
    k = window_noise([c.noise_per_m for c in clouds], lens)
    ex = extract_planes(pts_m, veh_m, cfg, seed, k)
    records: list[PlaneRecord] = []
    placements: list[tuple[PlaneRecord, Placement]] = []
    n_curved = 0
    n_single = 0
    if ex.candidates:
        eligible = np.zeros(n_total, dtype=bool)
        eligible[n_total - n_eligible :] = True
        claims = claim_points(pts_m, ex.grid, ex.candidates, ex.cell_keys, cfg, eligible)
        first_ns, last_ns = new[0].t_ns, new[-1].t_ns
        frame_of = np.repeat(np.arange(len(clouds), dtype=np.int64), lens)
        for cand, idx in zip(ex.candidates, claims, strict=True):
            if idx.shape[0] < cfg.min_commit_points:
                continue
            support = frame_support(pts_m, ex.grid, cand, frame_of, cfg.distance_threshold_m, cfg.min_frame_points)
            if support < cfg.min_obs_frames:
                n_single += 1
                continue
            bulge = frame_sagitta(pts_m[idx], frame_of[idx], cand.normal)
            if bulge > cfg.max_frame_sagitta_m:
                n_curved += 1
                continue
            noise_q2 = 0
            if prior_active(cfg, cand.normal):  # the points' expected variances: the tilt prior, the gates' noise
                kk = k[idx] if isinstance(k, np.ndarray) else k
                noise_q2 = noise_quanta2(expected_error_m(pts_m[idx], veh_m[idx], kk), q)
            rec = PlaneRecord.from_points(pts_q[idx], cand.normal, robot, first_ns, last_ns, cfg, noise_q2)
            records.append(rec)
            if keep_placements:
                cloud_t = np.array([c.t_ns for c in clouds], dtype=np.int64)[frame_of[idx]]
                pl = Placement(robot, pts_q[idx], cloud_t, np.asarray(cand.normal, float), first_ns, last_ns, rec)
                placements.append((rec, pl))
    return WindowObservations(records, placements, n_curved, n_single)
