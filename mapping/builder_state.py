"""The map builder's state as the header and arrays :mod:`mapping.store` saves, and back.

Part of :class:`mapping.MapBuilder` (:meth:`~mapping.MapBuilder.save`, and the reload when its folder holds a
map). :func:`encode_state` turns the planes (exact statistics, orientation, bounding box, contributions, export
voxels), the robots' tracks, the clouds still waiting in their windows and the per-robot cap's last times into a
JSON header and flat arrays; :func:`decode_state` rebuilds them, so that a restarted builder continues exactly
where the old one stopped. The layout of the file itself (``map_state.npz``, atomic writes) is :mod:`mapping.store`.

Frames and units: NED; points and vehicle positions are int64/int32 quanta of ``MapConfig.quantum_m`` metres,
track positions metres, times integer ns.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .builder_window import RobotWindow, WindowCloud
from .errors import MapStoreError
from .plane_map import MapPlane, PlaneMap, PlaneRecord
from .stats import Contribution, VoxelSet
from .store import six_ints
from .types import MapConfig, PlaneStats

log = logging.getLogger(__name__)

#: robot -> list of (t_ns, north_m, east_m, down_m)
Tracks = dict[str, list[tuple[int, float, float, float]]]


def encode_state(
    cfg: MapConfig,
    plane_map: PlaneMap,
    tracks: Tracks,
    windows: dict[str, RobotWindow],
    last_taken: dict[str, int],
) -> tuple[dict[str, Any], dict[str, NDArray[Any]]]:
    """The builder's state as a JSON header and named arrays (the caller holds the builder's lock)."""
    planes = []
    vox_plane, vox_keys, vox_counts, vox_sums = [], [], [], []
    for pid, mp in sorted(plane_map.planes.items()):
        rec = mp.record
        planes.append(
            {
                "id": pid,
                "stats": rec.stats.to_list(),
                "orient": list(rec.orient),
                "aabb_min": list(rec.aabb_min),
                "aabb_max": list(rec.aabb_max),
                "n_obs": rec.n_obs,
                "within": list(rec.within),
                "noise": rec.noise,
                "contributions": {k: [c.n_points, c.first_ns, c.last_ns] for k, c in rec.contributions.items()},
            }
        )
        vox_plane.append(np.full(rec.voxels.keys.shape[0], pid, np.int64))
        vox_keys.append(rec.voxels.keys)
        vox_counts.append(rec.voxels.counts)
        vox_sums.append(rec.voxels.sums)
    robots = sorted(set(tracks) | set(windows))
    rindex = {r: i for i, r in enumerate(robots)}
    tr_r, tr_t, tr_p = [], [], []
    for robot, tr in tracks.items():
        for t, n, e, d in tr:
            tr_r.append(rindex[robot])
            tr_t.append(t)
            tr_p.append((n, e, d))
    win_r, win_t, win_len, win_veh, win_pts, win_k = [], [], [], [], [], []
    windows_meta = {}
    for robot, w in sorted(windows.items()):
        windows_meta[robot] = {"n_new": w.n_new, "new_points": w.new_points}
        for c in w.clouds:
            win_r.append(rindex[robot])
            win_t.append(c.t_ns)
            win_len.append(c.points_q.shape[0])
            win_veh.append(c.vehicle_q)
            win_pts.append(c.points_q)
            win_k.append(c.noise_per_m)
    header = {
        "config": cfg.to_dict(),
        "next_id": plane_map.next_id,
        "planes": planes,
        "robots": robots,
        "windows": windows_meta,
        "last_taken_ns": dict(sorted(last_taken.items())),
    }

    def cat(parts: list[NDArray[Any]], shape: tuple[int, ...], dtype: Any) -> NDArray[Any]:
        return np.concatenate(parts).astype(dtype) if parts else np.zeros(shape, dtype)

    arrays: dict[str, NDArray[Any]] = {
        "vox_plane": cat(vox_plane, (0,), np.int64),
        "vox_keys": cat(vox_keys, (0,), np.int64),
        "vox_counts": cat(vox_counts, (0,), np.int64),
        "vox_sums": cat(vox_sums, (0, 3), np.int64),
        "track_robot": np.array(tr_r, np.int64),
        "track_t_ns": np.array(tr_t, np.int64),
        "track_ned": np.array(tr_p, np.float64).reshape(-1, 3),
        "win_robot": np.array(win_r, np.int64),
        "win_t_ns": np.array(win_t, np.int64),
        "win_len": np.array(win_len, np.int64),
        "win_vehicle_q": np.array(win_veh, np.int64).reshape(-1, 3),
        "win_points_q": cat(win_pts, (0, 3), np.int32),
        "win_noise_per_m": np.array(win_k, np.float64),
    }
    return header, arrays


def decode_state(
    cfg: MapConfig, header: dict[str, Any], a: dict[str, NDArray[Any]], where: Path
) -> tuple[PlaneMap, Tracks, dict[str, RobotWindow], dict[str, int]]:
    """The planes, tracks, windows and last taken times of a saved state (``where``: its file, for messages);
    raises :class:`~mapping.errors.MapStoreError` when the state is inconsistent."""
    try:
        if header.get("config") != cfg.to_dict():
            log.warning("%s: saved with a different MapConfig; continuing the map with the new one", where)
        pm = PlaneMap(cfg)
        pm.next_id = int(header["next_id"])
        vox_plane = a["vox_plane"]
        for p in header["planes"]:
            pid = int(p["id"])
            sel = vox_plane == pid
            rec = PlaneRecord(
                PlaneStats.from_list(p["stats"]),
                (int(p["orient"][0]), int(p["orient"][1]), int(p["orient"][2])),
                (int(p["aabb_min"][0]), int(p["aabb_min"][1]), int(p["aabb_min"][2])),
                (int(p["aabb_max"][0]), int(p["aabb_max"][1]), int(p["aabb_max"][2])),
                {k: Contribution(int(v[0]), int(v[1]), int(v[2])) for k, v in p["contributions"].items()},
                VoxelSet(a["vox_keys"][sel], a["vox_counts"][sel], a["vox_sums"][sel]),
                int(p["n_obs"]),
                None,
                six_ints(p.get("within", [0] * 6)),
                int(p.get("noise", 0)),
            )
            pm.planes[pid] = MapPlane(pid, rec, cfg)
        robots: list[str] = list(header["robots"])
        tracks: Tracks = {}
        for ri, t, pos in zip(a["track_robot"], a["track_t_ns"], a["track_ned"], strict=False):
            tracks.setdefault(robots[int(ri)], []).append((int(t), float(pos[0]), float(pos[1]), float(pos[2])))
        windows: dict[str, RobotWindow] = {}
        offsets = np.concatenate([[0], np.cumsum(a["win_len"])]).astype(np.int64)
        win_k = a.get("win_noise_per_m", np.zeros(len(a["win_t_ns"])))  # absent: saved before per-cloud k
        for i, (ri, t) in enumerate(zip(a["win_robot"], a["win_t_ns"], strict=False)):
            w = windows.setdefault(robots[int(ri)], RobotWindow())
            pts = a["win_points_q"][offsets[i] : offsets[i + 1]].astype(np.int32)
            w.clouds.append(WindowCloud(int(t), pts, a["win_vehicle_q"][i].astype(np.int64), float(win_k[i])))
        for r, wmeta in header["windows"].items():
            w = windows.setdefault(r, RobotWindow())
            w.n_new = int(wmeta["n_new"])
            w.new_points = int(wmeta["new_points"])
        last_taken = {str(k): int(v) for k, v in header.get("last_taken_ns", {}).items()}
    except (KeyError, IndexError, TypeError, ValueError, AttributeError) as err:
        msg = f"{where}: inconsistent map state: {err!r}"
        raise MapStoreError(msg) from err
    return pm, tracks, windows, last_taken
