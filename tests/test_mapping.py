"""Tests of the mapping package: exact statistics, extraction guards, merging, persistence, export, CLI."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from lrsensor.frames import Pose
from mapping import (
    ChangeKind,
    MapBuilder,
    MapChange,
    MapConfig,
    MapConfigError,
    MapInputError,
    MappingError,
    MapStoreError,
    PlaneStats,
)
from mapping.plane_map import PlaneMap, PlaneRecord
from mapping.synth import Cylinder, DivePlan, Face, Scene, box_pillar, simulate_dive

Q = 1e-4


def _wall_points(
    rng: np.random.Generator,
    n: int,
    north: float,
    east: tuple[float, float],
    down: tuple[float, float],
    noise: float = 0.003,
) -> np.ndarray:
    """Points on the plane north = const (metres, NED)."""
    return np.stack([north + rng.normal(0, noise, n), rng.uniform(*east, n), rng.uniform(*down, n)], 1)


def _quantize(p: np.ndarray) -> np.ndarray:
    return np.rint(p / Q).astype(np.int64)


def _feed(builder: MapBuilder, frames: list) -> None:
    for f in frames:
        builder.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
    builder.flush()


# --------------------------------------------------------------------------- statistics
def test_plane_stats_exact_and_fit_matches_numpy() -> None:
    rng = np.random.default_rng(0)
    p = _wall_points(rng, 2000, 3.0, (0, 2), (1, 2))
    a, b = _quantize(p[:700]), _quantize(p[700:])
    sa, sb = PlaneStats.from_quantized(a), PlaneStats.from_quantized(b)
    assert sa + sb == sb + sa == PlaneStats.from_quantized(np.concatenate([a, b]))
    fit = (sa + sb).fit(Q)
    pq = np.concatenate([a, b]) * Q
    c = pq.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((pq - c).T, bias=True))
    assert np.allclose(fit.centroid, c, atol=1e-12)
    assert abs(abs(fit.normal @ v[:, 0]) - 1) < 1e-9
    assert fit.rms_m == pytest.approx(math.sqrt(w[0]), rel=1e-6)
    assert abs(fit.normal @ fit.centroid + fit.d) < 1e-12


def test_plane_stats_far_from_origin_stay_precise() -> None:
    rng = np.random.default_rng(1)
    p = _wall_points(rng, 5000, 0.0, (0, 2), (0, 1), noise=0.001) + np.array([40_000.0, -35_000.0, 50.0])
    fit = PlaneStats.from_quantized(_quantize(p)).fit(Q)
    assert abs(abs(fit.normal[0]) - 1) < 1e-6
    assert fit.rms_m == pytest.approx(0.001, rel=0.1)


def test_plane_stats_list_round_trip_and_rejects_garbage() -> None:
    s = PlaneStats.from_quantized(np.array([[1, 2, 3], [4, 5, 6], [7, 8, 10]]))
    assert PlaneStats.from_list(s.to_list()) == s
    with pytest.raises(ValueError, match="10 integers"):
        PlaneStats.from_list([1, 2, 3])
    with pytest.raises(ValueError, match="at least 3"):
        PlaneStats.zero().fit(Q)


def test_config_validation_names_the_field() -> None:
    with pytest.raises(MapConfigError, match="distance_threshold_m"):
        MapConfig(distance_threshold_m=-1.0)
    with pytest.raises(MapConfigError, match="window_clouds"):
        MapConfig(window_clouds=5, extract_every_clouds=10)
    with pytest.raises(MapConfigError, match="unknown MapConfig keys: bogus"):
        MapConfig.from_dict({"bogus": 1})
    assert MapConfig.from_dict(MapConfig().to_dict()) == MapConfig()


# --------------------------------------------------------------------------- merging
def _obs(
    rng: np.random.Generator,
    robot: str,
    north: float,
    east: tuple[float, float],
    down: tuple[float, float],
    t_ns: int,
    normal: tuple[float, float, float] = (-1.0, 0.0, 0.0),
) -> PlaneRecord:
    p = _wall_points(rng, 1500, north, east, down)
    return PlaneRecord.from_points(_quantize(p), np.array(normal), robot, t_ns, t_ns + 10, MapConfig())


def test_merge_is_order_independent() -> None:
    rng = np.random.default_rng(2)
    obs = [
        _obs(rng, "rov1", 3.0, (0.0, 1.2), (1.0, 1.2), 100),
        _obs(rng, "rov2", 3.0, (1.0, 2.2), (1.1, 1.3), 50),
        _obs(rng, "rov1", 3.0, (2.0, 3.0), (0.9, 1.1), 300),
        _obs(rng, "rov3", 3.0, (0.5, 2.5), (1.8, 2.0), 200),
    ]
    results = []
    for order in itertools.permutations(range(len(obs))):
        pm = PlaneMap(MapConfig())
        for i in order:
            pm.add(obs[i])
        assert len(pm) == 1
        (plane,) = pm.planes.values()
        results.append((plane.record, {k: v for k, v in plane.to_json().items() if k != "id"}))
    first_rec, first_json = results[0]
    for rec, js in results[1:]:
        assert rec == first_rec  # exact: integer statistics, voxels, contributions, boxes
        assert js == first_json
    assert first_json["robots"] == ["rov1", "rov2", "rov3"]
    assert first_json["created_ns"] == 50
    assert first_json["updated_ns"] == 310
    assert first_json["n_obs"] == 4


def test_bridging_observation_fuses_two_map_planes() -> None:
    rng = np.random.default_rng(3)
    pm = PlaneMap(MapConfig())
    pm.add(_obs(rng, "a", 3.0, (0.0, 1.0), (1.0, 1.2), 1))
    pm.add(_obs(rng, "a", 3.0, (0.0, 1.0), (1.0, 1.2), 2))
    pm.add(_obs(rng, "b", 3.0, (1.6, 2.6), (1.0, 1.2), 3))
    pm.add(_obs(rng, "b", 3.0, (1.6, 2.6), (1.0, 1.2), 4))
    assert len(pm) == 2  # 0.6 m apart: separate faces
    changes = pm.add(_obs(rng, "c", 3.0, (0.8, 1.8), (1.0, 1.2), 5))
    assert len(pm) == 1
    assert MapChange.removed(2, merged_into=1) in changes
    assert changes[0].kind is ChangeKind.UPDATED
    assert changes[0].plane_id == 1
    assert changes[0].plane is not None
    assert changes[0].plane.to_json()["n_obs"] == 5


def test_opposite_faces_of_a_thin_wall_never_merge() -> None:
    rng = np.random.default_rng(4)
    pm = PlaneMap(MapConfig())
    for t in range(3):
        pm.add(_obs(rng, "a", 3.0, (0, 2), (1, 1.3), t, normal=(-1.0, 0.0, 0.0)))
        pm.add(_obs(rng, "b", 3.02, (0, 2), (1, 1.3), t, normal=(1.0, 0.0, 0.0)))
    assert len(pm) == 2
    normals = sorted(round(p.fit.normal[0]) for p in pm.planes.values())
    assert normals == [-1, 1]


def test_coplanar_faces_apart_stay_apart_and_parallel_faces_too() -> None:
    rng = np.random.default_rng(5)
    pm = PlaneMap(MapConfig())
    for t in range(2):
        pm.add(_obs(rng, "a", 3.0, (0.0, 0.5), (1, 1.3), t))
        pm.add(_obs(rng, "a", 3.0, (1.5, 2.0), (1, 1.3), t))  # same plane, 1 m to the side
        pm.add(_obs(rng, "a", 3.3, (0.0, 0.5), (1, 1.3), t))  # parallel, 0.3 m behind
    assert len(pm) == 3


def test_tentative_planes_are_not_served() -> None:
    rng = np.random.default_rng(6)
    pm = PlaneMap(MapConfig())
    assert pm.add(_obs(rng, "a", 3.0, (0, 1), (1, 1.3), 1)) == []
    assert pm.to_json() == []
    assert len(pm.to_json(include_tentative=True)) == 1
    changes = pm.add(_obs(rng, "a", 3.0, (0, 1), (1, 1.3), 2))
    assert [c.plane_id for c in changes] == [1]


def test_a_map_change_is_either_a_plane_or_a_removal() -> None:
    rng = np.random.default_rng(6)
    pm = PlaneMap(MapConfig())
    pm.add(_obs(rng, "a", 3.0, (0, 1), (1, 1.3), 1))
    (change,) = pm.add(_obs(rng, "a", 3.0, (0, 1), (1, 1.3), 2))
    plane = pm.planes[1]
    assert change == MapChange.updated(plane)
    assert (change.kind, change.plane_id, change.plane, change.merged_into) == (ChangeKind.UPDATED, 1, plane, None)
    gone = MapChange.removed(2, merged_into=1)
    assert (gone.kind, gone.plane_id, gone.plane, gone.merged_into) == (ChangeKind.REMOVED, 2, None, 1)
    with pytest.raises(MappingError, match="updated plane 2"):
        MapChange(ChangeKind.UPDATED, 2, plane)  # the id must be the plane's
    with pytest.raises(MappingError, match="updated plane 1"):
        MapChange(ChangeKind.UPDATED, 1)
    with pytest.raises(MappingError, match="removed plane 2"):
        MapChange(ChangeKind.REMOVED, 2)
    with pytest.raises(MappingError, match="removed plane 1"):
        MapChange(ChangeKind.REMOVED, 1, plane, merged_into=3)


# --------------------------------------------------------------------------- extraction guards
def _scene_wall_and(*extra: Face, cylinders: tuple[Cylinder, ...] = ()) -> Scene:
    wall = Face("wall", (4.0, 2.0, 1.5), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), 3.0, 1.5)
    return Scene((wall, *extra), cylinders)


def _run(
    scene: Scene, plans: list[DivePlan], duration_s: float = 6.0, cfg: MapConfig | None = None, **kw: float
) -> MapBuilder:
    frames = simulate_dive(scene, plans, duration_s=duration_s, rate_hz=15.0, n_rays=500, seed=7, **kw)
    b = MapBuilder(cfg or MapConfig())
    _feed(b, frames)
    return b


def test_wall_ahead_is_one_accurate_plane_and_laser_sheets_are_not_planes() -> None:
    # Constant depth, no tilt: all top-laser hits of a window lie in one horizontal sheet.
    plan = DivePlan(
        "r", ((1.0, 1.0), (1.0, 3.0)), 1.0, speed_mps=0.4, sweep_deg=30, tilt_deg=0.0, heave_m=0.0, look_deg=0.0
    )
    b = _run(_scene_wall_and(), [plan], position_noise_m=0.0, attitude_noise_deg=0.0)
    planes = b.map_json()["planes"]
    assert len(planes) == 1
    (p,) = planes
    assert np.allclose(p["normal"], [-1, 0, 0], atol=math.sin(math.radians(1.0)))
    assert abs(p["d"] - 4.0) < 0.01
    assert p["rms_m"] < 0.005


def test_single_laser_line_makes_no_plane() -> None:
    plan = DivePlan(
        "r", ((1.0, 1.0), (1.0, 3.0)), 1.0, speed_mps=0.4, sweep_deg=30, tilt_deg=0.0, heave_m=0.0, look_deg=0.0
    )
    frames = simulate_dive(_scene_wall_and(), [plan], duration_s=6.0, rate_hz=15.0, n_rays=500, seed=7)
    b = MapBuilder(MapConfig())
    for f in frames:
        top = f.hits.laser == 0
        b.add_cloud(f.robot, f.t_ns, f.points_ned_est[top], f.pose_est)
    b.flush()
    assert b.map_json(include_tentative=True)["planes"] == []


def test_pipe_gives_no_plane_but_the_wall_behind_it_does() -> None:
    pipe = Cylinder("pipe", 2.6, 2.0, 0.15, 0.0, 3.0)
    plan = DivePlan("r", ((1.0, 0.8), (1.0, 3.2)), 1.2, speed_mps=0.4, sweep_deg=40, look_deg=0.0)
    b = _run(_scene_wall_and(cylinders=(pipe,)), [plan], duration_s=12.0)
    planes = b.map_json(include_tentative=True)["planes"]
    assert len(planes) >= 1
    for p in planes:  # only the wall: no plane near the pipe's axis
        assert abs(p["normal"][0] + 1) < 0.01, p
        assert abs(p["d"] - 4.0) < 0.03, p


def test_pipe_alone_gives_no_plane() -> None:
    pipe = Cylinder("pipe", 2.5, 2.0, 0.2, 0.0, 3.0)
    plan = DivePlan("r", ((1.0, 0.5), (1.0, 3.5)), 1.2, speed_mps=0.4, sweep_deg=40, look_deg=0.0)
    b = _run(Scene((), (pipe,)), [plan], duration_s=12.0)
    assert b.map_json(include_tentative=True)["planes"] == []


def test_coplanar_pillar_fronts_stay_two_planes() -> None:
    faces = box_pillar("p1", 3.0, 1.0, 0.5, 0.0, 3.0) + box_pillar("p2", 3.0, 3.0, 0.5, 0.0, 3.0)
    plan = DivePlan("r", ((0.8, 0.5), (0.8, 3.5)), 1.2, speed_mps=0.4, sweep_deg=35, look_deg=0.0)
    b = _run(Scene(tuple(faces)), [plan], duration_s=15.0)
    fronts = [p for p in b.map_json()["planes"] if p["normal"][0] < -0.99]
    assert len(fronts) == 2
    easts = sorted(p["extent"]["centroid"][1] for p in fronts)
    assert abs(easts[0] - 1.0) < 0.2
    assert abs(easts[1] - 3.0) < 0.2


# --------------------------------------------------------------------------- builder input, threads, persistence
def test_add_cloud_rejects_bad_input() -> None:
    b = MapBuilder(MapConfig())
    with pytest.raises(MapInputError, match="shape"):
        b.add_cloud("r", 1, np.zeros((5, 2)), Pose.identity())
    with pytest.raises(MapInputError, match="robot"):
        b.add_cloud("", 1, np.zeros((5, 3)), Pose.identity())
    with pytest.raises(MapInputError, match="Pose"):
        b.add_cloud("r", 1, np.zeros((5, 3)), (0, 0, 0))  # type: ignore[arg-type]
    # non-finite rows are dropped, empty clouds are fine
    assert b.add_cloud("r", 1, np.array([[np.nan, 0, 0], [1, 1, 1]]), Pose.identity()) == []
    assert b.add_cloud("r", 2, np.zeros((0, 3)), Pose.identity()) == []
    assert b.stats()["points"] == 1


def _small_dive(seed: int = 11, duration_s: float = 8.0) -> list:
    scene = _scene_wall_and(*box_pillar("p", 2.8, 3.0, 0.5, 0.0, 3.0))
    plans = [
        DivePlan("rov1", ((1.0, 0.8), (1.0, 3.2)), 1.0, speed_mps=0.4, sweep_deg=35, look_deg=0.0),
        DivePlan("rov2", ((1.2, 3.2), (1.2, 0.8)), 1.6, speed_mps=0.4, sweep_deg=35, look_deg=10.0, phase_s=2.0),
    ]
    return simulate_dive(
        scene, plans, duration_s=duration_s, rate_hz=15.0, n_rays=500, seed=seed, position_noise_m=0.01
    )


def test_replay_is_deterministic_and_changes_describe_the_map() -> None:
    frames = _small_dive()
    b1 = MapBuilder(MapConfig())
    changes: dict[int, dict] = {}

    def apply(ch: MapChange) -> None:
        if ch.kind is ChangeKind.REMOVED:
            changes.pop(ch.plane_id, None)
        else:
            assert ch.plane is not None
            changes[ch.plane_id] = ch.plane.to_json()

    for f in frames:
        for ch in b1.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est):
            apply(ch)
    for ch in b1.flush():
        apply(ch)
    b2 = MapBuilder(MapConfig())
    _feed(b2, frames)
    m1, m2 = b1.map_json(include_tracks=True), b2.map_json(include_tracks=True)
    assert json.dumps(m1, sort_keys=True) == json.dumps(m2, sort_keys=True)
    assert len(m1["planes"]) >= 3
    # the published changes, applied in order, give the served map
    assert sorted(changes) == [p["id"] for p in m1["planes"]]
    assert [changes[i] for i in sorted(changes)] == m1["planes"]
    for p in m1["planes"]:
        assert set(p) >= {"id", "normal", "d", "n_points", "robots", "extent", "rms_m", "updated_ns"}
        n = np.array(p["normal"])
        assert abs(np.linalg.norm(n) - 1) < 1e-9
        assert abs(n @ np.array(p["extent"]["centroid"]) + p["d"]) < 1e-9
    assert set(b1.tracks) == {"rov1", "rov2"}
    t, _n, _e, d = b1.tracks["rov1"][0]
    assert isinstance(t, int)
    assert abs(d - 1.0) < 0.3


def test_persistence_round_trip_continues_the_same_map(tmp_path: Path) -> None:
    frames = _small_dive(seed=12)
    half = len(frames) // 2 + 3  # mid-window: pending clouds must survive the restart too
    ref = MapBuilder(MapConfig())
    _feed(ref, frames)

    state = tmp_path / "state"
    a = MapBuilder(MapConfig(), state)
    for f in frames[:half]:
        a.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
    a.save()
    before = a.map_json(include_tracks=True, include_tentative=True)
    assert sorted(p.name for p in state.iterdir()) == ["map.json", "map_state.npz"]  # no temporary left
    b = MapBuilder(None, state)  # a restarted base station
    assert b.cfg == a.cfg
    assert b.map_json(include_tracks=True, include_tentative=True) == before
    assert b.planes_records() == a.planes_records()
    for f in frames[half:]:
        b.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
    b.flush()
    assert json.dumps(b.map_json(include_tracks=True), sort_keys=True) == json.dumps(
        ref.map_json(include_tracks=True), sort_keys=True
    )
    served = json.loads((state / "map.json").read_text())
    assert served["planes"] == json.loads(json.dumps(before["planes"]))


def test_corrupt_state_is_refused_with_the_path(tmp_path: Path) -> None:
    (tmp_path / "map_state.npz").write_bytes(b"not a zip")
    with pytest.raises(MapStoreError, match=r"map_state\.npz"):
        MapBuilder(MapConfig(), tmp_path)
    with pytest.raises(MapStoreError, match="state directory"):
        MapBuilder(MapConfig()).save()


def test_map_json_can_be_read_while_another_thread_feeds() -> None:
    frames = _small_dive(seed=13, duration_s=4.0)
    b = MapBuilder(MapConfig())
    errors: list[BaseException] = []
    done = threading.Event()

    def reader() -> None:
        try:
            while not done.is_set():
                doc = b.map_json(include_tracks=True)
                json.dumps(doc)
                _ = b.tracks, b.n_planes, b.stats()
        except BaseException as err:  # pragma: no cover - reported below
            errors.append(err)

    th = threading.Thread(target=reader)
    th.start()
    try:
        _feed(b, frames)
    finally:
        done.set()
        th.join(timeout=10)
    assert not errors
    assert b.n_planes >= 1


# --------------------------------------------------------------------------- export, view, CLI, imports
def test_cli_export_and_view(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from lrsensor.cli import main
    from lrsensor.ply import read_ply

    state = tmp_path / "state"
    b = MapBuilder(MapConfig(), state)
    _feed(b, _small_dive(seed=14, duration_s=6.0))
    b.save()
    out = tmp_path / "out"
    code = main(
        [
            "map",
            "export",
            "--state",
            str(state),
            "--out",
            str(out / "m.ply"),
            "--json",
            str(out / "m.json"),
            "--png",
            str(out / "top.png"),
        ]
    )
    assert code == 0
    assert "planes" in capsys.readouterr().out
    doc = json.loads((out / "m.json").read_text())
    assert doc["planes"] == b.map_json()["planes"]
    assert set(doc["tracks"]) == {"rov1", "rov2"}
    verts = read_ply(out / "m.ply")  # the sensor core's reader reads the map's vertices too
    assert int((verts["corner"] == 1).sum()) == 4 * len(doc["planes"])
    assert set(np.unique(verts["plane"])) == {p["id"] for p in doc["planes"]}
    assert (out / "top.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["map", "view", "--state", str(state), "--png", str(out / "v.png")]) == 0
    assert (out / "v.png").stat().st_size > 1000
    assert main(["map", "view", "--state", str(tmp_path / "nothing"), "--png", str(out / "x.png")]) == 1


def test_mapping_imports_neither_zenoh_nor_open3d_until_extraction() -> None:
    code = (
        "import sys, mapping, mapping.builder, mapping.export, mapping.view, mapping.store, mapping.cli, "
        "mapping.synth; print('zenoh' in sys.modules, 'open3d' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


def test_missing_open3d_gives_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    import mapping.planes as planes
    from mapping import Open3DMissingError

    monkeypatch.setattr(planes, "_o3d", None)
    monkeypatch.setitem(sys.modules, "open3d", None)
    with pytest.raises(Open3DMissingError, match=r"lrsensor\[base\]"):
        planes.open3d()
