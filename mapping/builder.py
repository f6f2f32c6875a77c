"""The object the base station feeds: per-robot windows of NED clouds -> planes -> the shared map.

Cost model: :meth:`MapBuilder.add_cloud` only quantizes the cloud and appends it to the robot's window (tens of
microseconds); every ``extract_every_clouds`` clouds (or ``extract_every_points`` points, or
``extract_every_s`` of capture time) the robot's window goes through :func:`mapping.planes.extract_planes`, and
the planes found claim the points of the clouds that arrived since the last extraction. Every point enters the
map's statistics exactly once, even when ``window_clouds > extract_every_clouds`` gives extraction more context.

Threading: one thread calls :meth:`add_cloud` / :meth:`flush` (the base station's map worker); :meth:`map_json`,
:attr:`tracks`, :meth:`save` may be called from any thread. A lock guards the map, the tracks and the windows;
the expensive extraction runs outside it.

Output: :meth:`add_cloud` and :meth:`flush` return typed :class:`~mapping.types.MapChange` values (a plane's new
state, or its removal into another plane), at most one per plane per call, in the order they happened. Applied
in order to the previous map's planes, they give the new ones; turning them into JSON is the publisher's job.
(:meth:`map_json` serves the planes with bands of one face joined, :mod:`mapping.served`; the changes and the
landmarks are the planes as built.)

Layout: this module holds :class:`MapBuilder` (input, merge, re-placement, output, save and reload, under its
lock); :mod:`mapping.builder_window` a robot's window (thinning, the extraction triggers) and the extraction of
a window into observations; :mod:`mapping.builder_state` the state as the header and arrays that
:mod:`mapping.store` saves, and back; :mod:`mapping.replace` the re-placement helpers (``freeze``,
``rebuild_changes``) next to ``rebuild``.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from lrsensor.frames import Pose

from .builder_state import decode_state, encode_state
from .builder_window import RobotWindow, WindowCloud, extract_window, extraction_due, spans_time, thin_cloud
from .errors import MapInputError, MapStoreError
from .landmarks import SNAPSHOT_GRID_NS, LandmarkSnapshots, PlaneLandmarks, SnapshotRange, snapshot_time
from .ned import check_cloud
from .plane_map import PlaneMap, PlaneRecord
from .range_noise import cloud_noise_per_m
from .replace import Placement, PlacementSnapshot, freeze, move_placement, rebuild, rebuild_changes
from .served import served_planes
from .store import JSON_FILE, load_state, save_json, save_state, saved_config
from .types import MapChange, MapConfig

log = logging.getLogger(__name__)


@dataclass
class _Counters:
    clouds: int = 0
    skipped: int = 0
    points: int = 0
    extractions: int = 0
    observations: int = 0
    curved: int = 0
    single_frame: int = 0
    extract_s: float = 0.0


class MapBuilder:
    """Builds and serves the shared plane map (see the module docstring).

    Args:
        cfg: thresholds and rates (None: the saved configuration when ``state_dir`` holds a map, else defaults).
        state_dir: where the map persists (``map_state.npz`` + ``map.json``); reloaded when present.
    """

    def __init__(self, cfg: MapConfig | None = None, state_dir: Path | str | None = None) -> None:
        self.state_dir = Path(state_dir) if state_dir is not None else None
        loaded = load_state(self.state_dir) if self.state_dir is not None else None
        if cfg is None:
            cfg = saved_config(loaded[0]) if loaded is not None else MapConfig()
        self.cfg = cfg
        self._lock = threading.RLock()
        self._save_lock = threading.Lock()
        self._map = PlaneMap(self.cfg)
        self._windows: dict[str, RobotWindow] = {}
        self._tracks: dict[str, list[tuple[int, float, float, float]]] = {}
        self._counters = _Counters()
        self._last_save = time.monotonic()
        self._last_taken: dict[str, int] = {}
        #: bumped whenever the planes change (the navigation's landmarks are cached per version)
        self._version = 0
        self._landmarks: tuple[int, int, PlaneLandmarks] | None = None
        #: with navigation against snapshots (:meth:`snapshot_landmarks`): the planes as they were at each grid
        #: time, the minimum points of a landmark, the last grid time recorded
        self._snaps: LandmarkSnapshots | None = None
        self._snap_min_points = 0
        self._snap_upto: int | None = None
        #: keep every merged observation's points (:class:`mapping.replace.Placement`) so that clouds can be
        #: re-placed when a smoother revises their poses (:meth:`replace_poses`); only for one-process use
        #: (observations merged in the order this builder extracted them)
        self.keep_placements = False
        self._placements: list[Placement] = []
        self._pending: dict[int, Placement] = {}
        #: the observations no smoother moves any more, fused once (:meth:`freeze`)
        self._frozen: PlaneMap | None = None
        #: per robot, the range error per pixel of the calibration its clouds are measured with (set_range_error)
        self._per_px: dict[str, float] = {}
        if loaded is not None:
            self._load(*loaded)

    # ------------------------------------------------------------------ input
    def add_cloud(self, robot: str, t_ns: int, points_ned: Any, pose: Pose) -> list[MapChange]:
        """Add one cloud of ``robot`` captured at ``t_ns`` (ns).

        Args:
            robot: robot name.
            t_ns: capture time, integer nanoseconds since the epoch.
            points_ned: (N, 3) points in NED, metres (non-finite rows are dropped).
            pose: vehicle pose at capture time (its position orients normals and makes the track).

        Returns:
            The changes: planes updated (``change.plane.to_json()`` is the dict :meth:`map_json` lists) and
            planes removed (fused into ``change.merged_into``); empty unless this cloud triggered an extraction.
            With a per-robot cap (``max_cloud_rate_hz`` > 0), clouds closer in time than 1 / ``max_cloud_rate_hz``
            to the robot's last one taken only extend its track (counted: :attr:`rate_skipped`).
        """
        self._record_snapshots(int(t_ns))  # before this cloud's merge: its key is not before any grid time <= t_ns
        records = self.observe_cloud(robot, t_ns, points_ned, pose)
        changes = self.merge(records) if records else []
        self._maybe_autosave()
        return changes

    def observe_cloud(self, robot: str, t_ns: int, points_ned: Any, pose: Pose) -> list[PlaneRecord] | None:
        """The per-robot half of :meth:`add_cloud`: take the cloud into the robot's window and, when an extraction
        is due, return its plane observations without merging them (a plane worker sends them to the merger,
        which calls :meth:`merge`). None: no extraction ran (the cloud waits in the window, or the cap skipped it).
        """
        if not isinstance(robot, str) or not robot:
            msg = f"robot must be a non-empty string, got {robot!r}"
            raise MapInputError(msg)
        if not isinstance(pose, Pose):
            msg = f"{robot}: pose must be a lrsensor.frames.Pose, got {type(pose).__name__}"
            raise MapInputError(msg)
        t = int(t_ns)
        p = check_cloud(points_ned, f"{robot} cloud at {t} ns")
        veh = pose.p_ned
        if not np.all(np.isfinite(veh)):
            msg = f"{robot} cloud at {t} ns: pose position is not finite"
            raise MapInputError(msg)
        with self._lock:
            self._counters.clouds += 1
            track = self._tracks.setdefault(robot, [])
            if not track or t - track[-1][0] >= self.cfg.track_interval_s * 1e9:
                track.append((t, float(veh[0]), float(veh[1]), float(veh[2])))
            last = self._last_taken.get(robot)
            if (
                self.cfg.max_cloud_rate_hz > 0
                and last is not None
                and 0 <= t - last < 0.999e9 / self.cfg.max_cloud_rate_hz
            ):
                self._counters.skipped += 1
                return None
            self._last_taken[robot] = t
        q_veh = np.rint(veh / self.cfg.quantum_m).astype(np.int64)
        cloud = WindowCloud(t, thin_cloud(p, veh, self.cfg), q_veh, self.range_noise(robot))
        with self._lock:
            win = self._windows.setdefault(robot, RobotWindow())
            win.clouds.append(cloud)
            win.n_new += 1
            win.new_points += cloud.points_q.shape[0]
            self._counters.points += cloud.points_q.shape[0]
            due = extraction_due(win, self.cfg)
        return self._observe(robot) if due else None

    def advance_time(self, robot: str, t_ns: int) -> list[MapChange]:
        """The robot's capture clock reached ``t_ns`` without a cloud for the map (navigation could not place it):
        extract and merge its window's pending clouds once they span ``extract_every_s``, as a placed cloud would
        have. Without it a robot that stops being placed keeps its last clouds out of the map until a flush (and a
        plane worker never commits them: their acknowledgement waits). Returns the changes (empty when not due)."""
        self._record_snapshots(int(t_ns))
        records = self.observe_time(robot, t_ns)
        changes = self.merge(records) if records else []
        self._maybe_autosave()
        return changes

    def observe_time(self, robot: str, t_ns: int) -> list[PlaneRecord] | None:
        """The per-robot half of :meth:`advance_time` (plane workers): the observations of the robot's pending
        clouds when they are due by capture time, without merging them; None when nothing is due."""
        with self._lock:
            win = self._windows.get(robot)
            if win is None or win.n_new == 0 or not spans_time(win, int(t_ns), self.cfg):
                return None
        return self._observe(robot)

    def merge(self, records: list[PlaneRecord]) -> list[MapChange]:
        """Fuse plane observations (of :meth:`observe_cloud`, here or in a plane worker) into the map; returns
        the changes. The merger's whole job: association and exact addition of statistics."""
        changes: list[MapChange] = []
        with self._lock:
            for rec in records:
                pl = self._pending.pop(id(rec), None)
                if pl is not None:
                    self._placements.append(pl)
                changes.extend(self._map.add(rec))
            self._version += 1 if records else 0
            self._counters.observations += len(records)
        return _squash(changes)

    def set_range_error(self, robot: str, per_px: float) -> None:
        """``robot``'s next clouds are measured with a calibration of ``per_px`` range error per pixel per squared
        metre (1/(m px), :func:`lrsensor.range_theory.range_error_per_px`; 0: none known): their range noise k
        (:func:`mapping.range_noise.cloud_noise_per_m`)."""
        with self._lock:
            self._per_px[robot] = float(per_px)

    def range_noise(self, robot: str) -> float:
        """The range noise k (1/m) ``robot``'s next cloud gets (:func:`mapping.range_noise.cloud_noise_per_m`)."""
        with self._lock:
            return cloud_noise_per_m(self.cfg, self._per_px.get(robot, 0.0))

    def uncommitted(self, robot: str) -> int:
        """Clouds of ``robot`` in its window that no extraction has committed yet (0 once they reached the map)."""
        with self._lock:
            win = self._windows.get(robot)
            return win.n_new if win is not None else 0

    def drop_robot(self, robot: str) -> None:
        """Forget ``robot``'s window (a plane worker whose robot moved to another worker; its uncommitted clouds
        are processed again there)."""
        with self._lock:
            self._windows.pop(robot, None)
            self._last_taken.pop(robot, None)

    @property
    def rate_skipped(self) -> int:
        """Clouds the per-robot cap (``max_cloud_rate_hz``) left out of the map (they only made the track)."""
        with self._lock:
            return self._counters.skipped

    def add_cloud_body(self, robot: str, t_ns: int, points_body: Any, pose: Pose) -> list[MapChange]:
        """Like :meth:`add_cloud` for body-frame points (transformed with ``pose`` first)."""
        from .ned import cloud_to_ned

        return self.add_cloud(robot, t_ns, cloud_to_ned(points_body, pose), pose)

    def flush(self) -> list[MapChange]:
        """Run the pending extraction of every robot now (end of a dive, tests); returns the changes."""
        changes: list[MapChange] = []
        with self._lock:
            robots = sorted(r for r, w in self._windows.items() if w.n_new > 0)
        for robot in robots:
            changes.extend(self.merge(self._observe(robot)))
        return changes

    def flush_robot_observations(self, robot: str) -> list[PlaneRecord]:
        """The observations of ``robot``'s pending clouds now, without merging (a plane worker whose robot went
        silent: its last window has no trigger to come); empty when nothing is pending."""
        with self._lock:
            win = self._windows.get(robot)
            if win is None or win.n_new == 0:
                return []
        return self._observe(robot)

    def flush_observations(self) -> dict[str, list[PlaneRecord]]:
        """Like :meth:`flush` without merging: robot -> the observations of its pending clouds (plane workers)."""
        with self._lock:
            robots = sorted(r for r, w in self._windows.items() if w.n_new > 0)
        return {robot: self._observe(robot) for robot in robots}

    # ------------------------------------------------------------- extraction
    def _observe(self, robot: str) -> list[PlaneRecord]:
        """Extract the robot's window; the observations of its new clouds (not merged)."""
        cfg = self.cfg
        with self._lock:
            win = self._windows[robot]
            clouds = list(win.clouds)
            n_new = win.n_new
            win.n_new = 0
            win.new_points = 0
            # Keep the newest window_clouds clouds (all committed now) within the age limit as context.
            newest = clouds[-1].t_ns
            while len(win.clouds) > cfg.window_clouds or (
                win.clouds and newest - win.clouds[0].t_ns > cfg.window_max_age_s * 1e9
            ):
                win.clouds.popleft()
        t0 = time.perf_counter()
        obs = extract_window(robot, clouds, n_new, cfg, self.keep_placements)
        if obs is None:
            return []
        with self._lock:
            for rec, pl in obs.placements:
                self._pending[id(rec)] = pl
            self._counters.extractions += 1
            self._counters.curved += obs.curved
            self._counters.single_frame += obs.single_frame
            self._counters.extract_s += time.perf_counter() - t0
        return obs.records

    def replace_poses(self, robot: str, old: dict[int, Pose], new: dict[int, Pose]) -> int:
        """Move ``robot``'s kept observations (``keep_placements``) from the cloud poses ``old`` to ``new``
        (t_ns -> Pose) without touching the map; returns how many moved. :meth:`rebuild` makes the map follow."""
        with self._lock:
            n = 0
            for pl in self._placements:
                if pl.robot == robot and move_placement(pl, old, new, self.cfg):
                    n += 1
            return n

    def freeze(self, before_ns: dict[str, int]) -> int:
        """Fuse for good the kept observations of each robot whose clouds are all older than ``before_ns[robot]``
        (its smoothing window's start) and drop their points; returns how many were frozen."""
        with self._lock:
            self._placements, self._frozen, frozen = freeze(self._placements, before_ns, self._frozen, self.cfg)
            return frozen

    def rebuild(self) -> list[MapChange]:
        """Fuse every kept observation again (after :meth:`replace_poses`); returns the changes from the map
        before: every plane of the new map as updated, and every old id the new map lacks as removed (into the
        new plane nearest to it)."""
        with self._lock:
            return self._swap_map(rebuild(self._placements, self.cfg, self._frozen))

    def placements_snapshot(self) -> PlacementSnapshot:
        """The kept observations as they are now, for re-placing and rebuilding off this builder's thread
        (:class:`PlacementSnapshot`; :meth:`adopt` takes the result back). No :meth:`freeze` may run until then."""
        with self._lock:
            return PlacementSnapshot(list(self._placements), self.cfg, self._frozen)

    def adopt(self, snap: PlacementSnapshot, new_map: PlaneMap | None) -> list[MapChange]:
        """Take a snapshot's moved observations and the map rebuilt from them; the observations merged since the
        snapshot are fused on top. Returns the changes as :meth:`rebuild` does."""
        with self._lock:
            n0 = len(snap.original)
            kept = self._placements[:n0]
            if len(kept) != n0 or any(a is not b for a, b in zip(kept, snap.original, strict=True)):
                msg = "the kept observations changed under a placement snapshot (freeze while smoothing?)"
                raise MapInputError(msg)
            later = self._placements[n0:]
            self._placements = snap.placements + later
            if new_map is None:
                new_map = rebuild(snap.placements, self.cfg, self._frozen)
            for pl in later:
                new_map.add(pl.record)
            return self._swap_map(new_map)

    def _swap_map(self, new: PlaneMap) -> list[MapChange]:
        old = self._map
        self._map = new
        self._version += 1
        return rebuild_changes(old, new)

    # ----------------------------------------------------------------- output
    def map_json(self, include_tracks: bool = False, include_tentative: bool = False) -> dict[str, Any]:
        """The whole map: ``{"planes": [...]}`` (+ ``"tracks"`` when asked), NED, ``normal . p + d = 0``.

        Each plane: ``id``, ``normal`` [nx, ny, nz] (unit, toward the observing vehicles), ``d`` (m),
        ``n_points``, ``robots`` (names), ``extent`` (centroid, in-plane axes ``u`` (horizontal) and ``v``,
        their ranges, ``size_m``, 4 NED ``corners``, ``aabb_min``/``aabb_max``), ``rms_m``, ``updated_ns`` and
        ``created_ns`` (capture times), ``n_obs`` (observations fused), ``contributions`` per robot.
        Tentative planes (seen in fewer than ``min_obs_publish`` windows) are left out unless asked for.
        """
        with self._lock:
            # bands of one face joined in what is served only (mapping.served); landmarks() keeps the map's planes
            out: dict[str, Any] = {"frame": "NED", "planes": served_planes(self._map, include_tentative)}
            if include_tracks:
                out["tracks"] = {r: [list(s) for s in tr] for r, tr in sorted(self._tracks.items())}
            return out

    def landmarks(self, min_points: int = 0) -> PlaneLandmarks:
        """Every plane (tentative ones too) with at least ``min_points`` points, as registration targets for
        :mod:`mapping.navigation`; cached until the planes change."""
        with self._lock:
            cached = self._landmarks
            if cached is not None and cached[0] == self._version and cached[1] == min_points:
                return cached[2]
            planes = [mp.to_json() for _, mp in sorted(self._map.planes.items())]
            lm = PlaneLandmarks.from_planes(planes, min_points)
            self._landmarks = (self._version, min_points, lm)
            return lm

    def snapshot_landmarks(self, t_ns: int, lag_ns: int, min_points: int = 0) -> PlaneLandmarks:
        """The planes a scan captured at ``t_ns`` registers against in one process, by the rule plane workers
        follow (docs/scaling.md): ``snapshot(T)`` for ``T`` = :func:`~mapping.landmarks.snapshot_time` (``t_ns``,
        ``lag_ns``), the map after merging exactly the observations whose trigger capture time is before ``T``.
        The first call starts the bookkeeping (:meth:`add_cloud` then records the planes at each grid time before
        the merge that passes it); clouds must come in capture order, as they do to one map thread."""
        with self._lock:
            if self._snaps is None:
                self._snaps = LandmarkSnapshots()
                self._snap_min_points = min_points
            elif min_points != self._snap_min_points:
                msg = f"snapshot_landmarks: min_points {min_points} differs from the first call's"
                raise MapInputError(msg)
            self._record_snapshots(int(t_ns))
            want = snapshot_time(t_ns, lag_ns)
            rng = self._snaps.get(want) or self._snaps.newest_before(want)
            assert rng is not None  # a range up to t_ns was just recorded
            return rng.landmarks

    def _record_snapshots(self, t_ns: int) -> None:
        """The planes now are ``snapshot(T)`` for every grid time not recorded yet up to ``t_ns`` (every merge so
        far had a key at or before the previous cloud's capture time)."""
        with self._lock:
            if self._snaps is None:
                return
            hi = (t_ns // SNAPSHOT_GRID_NS) * SNAPSHOT_GRID_NS
            lo = 0 if self._snap_upto is None else self._snap_upto + SNAPSHOT_GRID_NS
            if hi >= lo:
                self._snaps.put(SnapshotRange(lo, hi, self.landmarks(self._snap_min_points)))
                self._snap_upto = hi

    @property
    def version(self) -> int:
        """A number that grows whenever the map's planes change (a merge with observations, a rebuild)."""
        with self._lock:
            return self._version

    @property
    def tracks(self) -> dict[str, list[tuple[int, float, float, float]]]:
        """Robot -> list of (t_ns, north_m, east_m, down_m), one sample per ``track_interval_s``."""
        with self._lock:
            return {r: list(tr) for r, tr in sorted(self._tracks.items())}

    @property
    def n_planes(self) -> int:
        """Number of confirmed planes in the map (what :meth:`map_json` serves)."""
        with self._lock:
            return sum(1 for p in self._map.planes.values() if p.record.n_obs >= self.cfg.min_obs_publish)

    def stats(self) -> dict[str, Any]:
        """Counters: clouds, points, extractions, observations, mean extraction time (s), planes."""
        with self._lock:
            c = self._counters
            return {
                "clouds": c.clouds,
                "skipped_rate": c.skipped,
                "points": c.points,
                "extractions": c.extractions,
                "observations": c.observations,
                "curved_rejected": c.curved,
                "single_frame_rejected": c.single_frame,
                "extract_mean_s": c.extract_s / c.extractions if c.extractions else 0.0,
                "planes": sum(1 for p in self._map.planes.values() if p.record.n_obs >= self.cfg.min_obs_publish),
                "tentative": sum(1 for p in self._map.planes.values() if p.record.n_obs < self.cfg.min_obs_publish),
            }

    def planes_records(self) -> dict[int, PlaneRecord]:
        """Id -> exact record of every plane (for tests and tools)."""
        with self._lock:
            return {pid: mp.record for pid, mp in sorted(self._map.planes.items())}

    # ------------------------------------------------------------ persistence
    def _maybe_autosave(self) -> None:
        if self.state_dir is None or self.cfg.autosave_every_s <= 0:
            return
        if time.monotonic() - self._last_save >= self.cfg.autosave_every_s:
            self.save()

    def save(self, state_dir: Path | str | None = None) -> Path:
        """Write the state atomically to ``state_dir`` (default: the builder's); returns the state file."""
        target = Path(state_dir) if state_dir is not None else self.state_dir
        if target is None:
            msg = "save() needs a state directory: none was given to MapBuilder or save()"
            raise MapStoreError(msg)
        with self._save_lock:
            with self._lock:
                header, arrays = self._snapshot()
                serving = self.map_json(include_tracks=True)
            path = save_state(target, header, arrays)
            save_json(target / JSON_FILE, serving)
            self._last_save = time.monotonic()
        return path

    def _snapshot(self) -> tuple[dict[str, Any], dict[str, NDArray[Any]]]:
        return encode_state(self.cfg, self._map, self._tracks, self._windows, self._last_taken)

    def _load(self, header: dict[str, Any], a: dict[str, NDArray[Any]]) -> None:
        assert self.state_dir is not None
        where = self.state_dir / "map_state.npz"
        pm, tracks, windows, last_taken = decode_state(self.cfg, header, a, where)
        with self._lock:
            self._map = pm
            self._tracks = tracks
            self._windows = windows
            self._last_taken = last_taken
        log.info("map reloaded from %s: %d planes, %d robots", where, len(pm), len(header["robots"]))


def _squash(changes: list[MapChange]) -> list[MapChange]:
    """Keep the last change per plane id (a plane updated twice in one extraction is reported once)."""
    last: dict[int, MapChange] = {}
    for ch in changes:
        last.pop(ch.plane_id, None)
        last[ch.plane_id] = ch
    return list(last.values())
