"""Letting past poses move (issue 27): the smoother over a robot's filter, re-placing clouds in the map, and the
launch-point fleet frame."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from test_navigation import scene_landmarks

from lrsensor.frames import Pose
from mapping.builder import MapBuilder
from mapping.navigation import NavConfig, Navigator
from mapping.smoother import RobotSmoother, SmootherConfig
from mapping.synth import Scene, hit_faces, replay_dive, score_map, simulate_dive, tank, three_rov_plans


@pytest.fixture(scope="module")
def drift_dive() -> tuple[Scene, list[Any]]:
    scene = tank()
    frames = simulate_dive(
        scene, three_rov_plans(), duration_s=40.0, rate_hz=10.0, n_rays=300, seed=2, navigation="drift"
    )
    return scene, frames


def _mean_error(run: Any) -> float:
    return float(np.mean([e for v in run.final_error_m.values() for e in v]))


def test_smoothing_moves_past_poses_and_the_map_follows(drift_dive: tuple[Scene, list[Any]]) -> None:
    scene, frames = drift_dive
    hits = hit_faces(scene, frames)
    cfg = NavConfig(fix_quality_factor=5.0)
    filtered = replay_dive(frames, navigate=True, nav_cfg=cfg)
    smoothed = replay_dive(frames, navigate=True, nav_cfg=cfg, smoother=SmootherConfig())
    assert smoothed.smooth_cost_s, "the smoother never ran"
    s_f = score_map(filtered.planes(), scene, hits)
    s_s = score_map(smoothed.planes(), scene, hits)
    # the poses the clouds are in the map with end up closer to the truth, and the map is at least as good
    assert _mean_error(smoothed) < _mean_error(filtered)
    assert len(s_s.spurious) <= 1, s_s.table()
    assert len(s_s.missing()) <= len(s_f.missing()), s_s.table()


def test_rebuilding_with_unchanged_poses_gives_the_same_map(drift_dive: tuple[Scene, list[Any]]) -> None:
    _, frames = drift_dive
    b = MapBuilder()
    b.keep_placements = True
    poses: dict[int, Pose] = {}
    for f in frames[:300]:
        if f.robot == "rov1":
            b.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
            poses[f.t_ns] = f.pose_est
    b.flush()
    before = b.map_json()["planes"]
    assert before
    assert b.replace_poses("rov1", poses, dict(poses)) == 0
    b.rebuild()
    assert b.map_json()["planes"] == before
    # moving every pose 10 cm north moves every plane with it
    moved = {t: Pose(p.north_m + 0.1, p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad) for t, p in poses.items()}
    assert b.replace_poses("rov1", poses, moved) > 0
    changes = b.rebuild()
    assert changes
    after = b.map_json()["planes"]
    assert len(after) == len(before)
    for p0, p1 in zip(before, after, strict=True):
        shift = np.asarray(p1["extent"]["centroid"]) - np.asarray(p0["extent"]["centroid"])
        assert shift == pytest.approx([0.1, 0.0, 0.0], abs=2e-3)


def test_the_smoother_uses_later_scans_for_earlier_poses() -> None:
    """A robot whose first scans see nothing and later scans see the tank: the smoothed early poses follow."""
    scene = tank()
    lm = scene_landmarks(scene)
    sm = RobotSmoother("r", NavConfig(), SmootherConfig(every_s=1.0, every_fraction=0.0))
    frames = simulate_dive(scene, three_rov_plans()[:1], duration_s=6.0, rate_hz=10.0, n_rays=300, seed=3)
    empty = type(lm).empty()
    bias = math.radians(1.0)
    for i, f in enumerate(frames):
        # dead reckoning 8 cm off from the second scan on, with a biased compass
        raw = Pose(
            f.pose_true.north_m + (0.08 if i else 0.0),
            f.pose_true.east_m,
            f.pose_true.down_m,
            f.pose_true.roll_rad,
            f.pose_true.pitch_rad,
            f.pose_true.yaw_rad + bias,
        )
        sm.update(f.t_ns, raw, f.points_body, empty if i < 30 else lm)
    revised = sm.smooth(lm)
    early = list(frames[5:25])
    err = [abs(revised[f.t_ns].north_m - f.pose_true.north_m) for f in early]
    assert float(np.mean(err)) < 0.04


def test_the_fleet_frame_carries_the_map_launch_points_onto_the_launch_fixes() -> None:
    nav = Navigator(NavConfig(), SmootherConfig())
    lm = scene_landmarks(tank())
    for i, (n, e) in enumerate([(1.0, 1.0), (6.0, 1.0), (3.0, 4.0)]):
        nav.update(f"r{i}", 1_000, Pose(n, e, 2.0, 0.0, 0.0, 0.0), np.zeros((0, 3)), lm)
    # the map places the launches turned by 1 deg about (0, 0) and 2 cm east: the frame undoes both
    a = math.radians(1.0)
    for sm in nav.smoothers.values():
        n, e = sm.nav.start_ne
        sm.start_map_ne = (math.cos(a) * n - math.sin(a) * e, math.sin(a) * n + math.cos(a) * e + 0.02)
    frame = nav.frame()
    for sm in nav.smoothers.values():
        assert sm.start_map_ne is not None
        p = frame.points([sm.start_map_ne[0], sm.start_map_ne[1], 0.0])[0]
        assert p[:2] == pytest.approx(sm.nav.start_ne, abs=1e-9)
    assert math.degrees(frame.yaw_rad) == pytest.approx(1.0, abs=1e-6)


def test_scan_odometry_recovers_the_move_between_two_scans_of_a_corner() -> None:
    from mapping.odometry import OdometryConfig, increment

    # two walls meeting at a corner, sampled along a stripe (in order), seen from the origin
    a = np.stack([np.full(60, 1.5), np.linspace(-1.0, 0.5, 60), np.zeros(60)], axis=1)
    b = np.stack([np.linspace(1.5, 0.0, 60), np.full(60, 0.5), np.zeros(60)], axis=1)
    prev = np.concatenate([a, b])
    move = np.array([0.03, -0.02])
    new = prev - np.array([move[0], move[1], 0.0])  # the same points seen from 3 cm north, 2 cm west
    delta, cov, pairs = increment(prev, new, np.eye(2) * 0.01, OdometryConfig())
    assert pairs >= 20
    assert delta == pytest.approx(move, abs=2e-3)
    assert np.sqrt(np.diag(cov)).max() < 0.01
    # one flat wall: the move along it is not observed, its variance stays the prior's
    delta, cov, pairs = increment(a, a - np.array([move[0], move[1], 0.0]), np.eye(2) * 0.01, OdometryConfig())
    assert delta[0] == pytest.approx(move[0], abs=2e-3)
    assert cov[1, 1] > 0.5 * 0.01


def test_what_leaves_the_window_is_frozen_and_the_map_stays(drift_dive: tuple[Scene, list[Any]]) -> None:
    scene, frames = drift_dive
    hits = hit_faces(scene, frames)
    scfg = SmootherConfig(window_s=10.0, every_s=5.0, every_fraction=0.0)
    run = replay_dive(frames, navigate=True, nav_cfg=NavConfig(fix_quality_factor=5.0), smoother=scfg)
    b = run.builder
    assert b._frozen is not None
    assert len(b._frozen.planes) > 0
    # only the observations of the last window keep their points
    newest = max(f.t_ns for f in frames)
    assert all(int(pl.cloud_t.max()) >= newest - 11e9 for pl in b._placements)
    s = score_map(run.planes(), scene, hits)
    assert len(s.spurious) <= 2, s.table()
    assert sum(1 for f in s.faces if f.hit and f.plane_ids) >= len([f for f in s.faces if f.hit]) - 1, s.table()


def test_the_base_smooths_by_default_and_not_with_plane_workers() -> None:
    from types import SimpleNamespace

    from services.mapfeed import MapFeed

    feed = MapFeed(MapBuilder(), lambda robot, seq: None, navigation=True)
    assert feed.smoothing
    assert feed.builder is not None
    assert feed.builder.keep_placements
    assert "smoothing" in feed.status_json()
    feed.set_smoothing(False)  # lrsensor base --nav filter
    assert not feed.smoothing
    assert feed.navigation
    feed.set_smoothing(True)
    feed.use_workers(SimpleNamespace())  # type: ignore[arg-type]
    assert not feed.smoothing
    assert not feed.builder.keep_placements
    off = MapFeed(MapBuilder(), lambda robot, seq: None, navigation=False)
    off.set_smoothing(True)
    assert not off.smoothing
    assert not off.navigation


def test_a_background_run_gives_the_same_map_and_holds_the_map_thread_briefly(
    drift_dive: tuple[Scene, list[Any]],
) -> None:
    _, frames = drift_dive
    cfg = NavConfig(fix_quality_factor=5.0)
    here = replay_dive(frames, navigate=True, nav_cfg=cfg, smoother=SmootherConfig())
    # the same runs detached from the map thread (the next step waits for each, so the result is reproducible)
    away = replay_dive(frames, navigate=True, nav_cfg=cfg, smoother=SmootherConfig(), background="wait")
    a, b = here.planes(), away.planes()
    assert len(a) == len(b)
    for p, q in zip(a, b, strict=True):
        assert p["normal"] == pytest.approx(q["normal"], abs=1e-9)
        assert p["d"] == pytest.approx(q["d"], abs=1e-9)
    assert len(away.smooth_hold_s) == len(here.smooth_hold_s) >= 2
    # the map thread only starts a run and hands it over; the run itself went on another thread
    assert max(away.smooth_hold_s) < 0.5 * max(here.smooth_hold_s), (away.smooth_hold_s, here.smooth_hold_s)


def test_observations_merged_during_a_background_run_stay_in_the_map(drift_dive: tuple[Scene, list[Any]]) -> None:
    _, frames = drift_dive
    mine = [f for f in frames if f.robot == "rov1"]
    b = MapBuilder()
    b.keep_placements = True
    poses: dict[int, Pose] = {}
    for f in mine[:150]:
        b.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
        poses[f.t_ns] = f.pose_est
    snap = b.placements_snapshot()
    n0 = len(snap.placements)
    assert n0 > 0
    # a run moves every cloud 10 cm north while the map thread goes on merging
    moved = {t: Pose(p.north_m + 0.1, p.east_m, p.down_m, p.roll_rad, p.pitch_rad, p.yaw_rad) for t, p in poses.items()}
    for f in mine[150:250]:
        b.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
    later = len(b._placements) - n0
    assert later > 0
    assert snap.move("rov1", poses, moved) == n0
    changes = b.adopt(snap, snap.rebuild())
    assert changes
    assert len(b._placements) == n0 + later
    # the snapshot's observations moved, the later ones are as merged
    assert all(x is y for x, y in zip(b._placements[:n0], snap.placements, strict=True))
    assert b.map_json()["planes"]
    # a snapshot whose observations were frozen meanwhile is refused
    snap2 = b.placements_snapshot()
    b.freeze({"rov1": 2**62})
    with pytest.raises(Exception, match="changed under a placement snapshot"):
        b.adopt(snap2, None)


def test_launches_turn_the_map_only_where_the_map_joins_their_robots() -> None:
    from test_navigation_bounds import _plane

    from mapping.landmarks import PlaneLandmarks

    def frame_yaw_deg(contributions: list[dict[str, tuple[int, int]]]) -> float:
        nav = Navigator(NavConfig(), SmootherConfig())
        lm = PlaneLandmarks.from_planes([_plane(i, c) for i, c in enumerate(contributions)])
        for i, (n, e) in enumerate([(1.0, 1.0), (6.0, 1.0)]):
            nav.update(f"r{i}", 1_000, Pose(n, e, 2.0, 0.0, 0.0, 0.0), np.zeros((0, 3)), lm)
        a = math.radians(1.0)
        for sm in nav.smoothers.values():
            n, e = sm.nav.start_ne
            sm.start_map_ne = (math.cos(a) * n - math.sin(a) * e, math.sin(a) * n + math.cos(a) * e)
        return math.degrees(nav.frame().yaw_rad)

    # each robot built its own part of the map: the launches' turn is their fixes' noise, the compasses decide
    assert frame_yaw_deg([{"r0": (500, 0)}, {"r1": (500, 0)}]) == pytest.approx(0.0, abs=1e-9)
    # a plane both contributed to joins the parts: the launch points fix the heading
    assert frame_yaw_deg([{"r0": (500, 0)}, {"r0": (500, 0), "r1": (500, 0)}]) == pytest.approx(1.0, abs=1e-6)


def test_lrsensor_base_smooths_by_default() -> None:
    import argparse

    from services.cli_base import configure

    parser = argparse.ArgumentParser()
    configure(parser)
    assert parser.parse_args(["--fleet", "f"]).nav == "on"
    assert parser.parse_args(["--fleet", "f", "--nav", "filter"]).nav == "filter"


def test_a_run_on_its_own_thread_hands_over_without_holding_the_map_thread(
    drift_dive: tuple[Scene, list[Any]],
) -> None:
    _, frames = drift_dive
    # as the base runs it: the map thread goes on while a run is away and takes it over when it is done. Replayed
    # as fast as the map takes the clouds, a run lags by many seconds of the dive (it does not in real time: see
    # docs/navigation-design.md, "The smoother"), so only the mechanics are checked here
    run = replay_dive(
        frames, navigate=True, nav_cfg=NavConfig(fix_quality_factor=5.0), smoother=SmootherConfig(), background=True
    )
    assert len(run.smooth_hold_s) >= 1
    assert max(run.smooth_hold_s) < 0.5 * max(run.smooth_cost_s), (run.smooth_hold_s, run.smooth_cost_s)
    assert sum(len(v) for v in run.placed.values()) == len(frames)
    assert len(run.planes()) >= 10


def test_a_job_catches_up_so_the_hand_over_re_runs_few_scans(drift_dive: tuple[Scene, list[Any]]) -> None:
    from dataclasses import replace as copy

    _, frames = drift_dive
    mine = [f for f in frames if f.robot == "rov1"][:160]
    cfg = NavConfig(fix_quality_factor=5.0)
    sm = RobotSmoother("rov1", cfg, SmootherConfig())
    b = MapBuilder()

    def feed(fs: list[Any]) -> None:
        for f in fs:
            sm.update(f.t_ns, f.pose_est, f.points_body, b.landmarks(cfg.min_landmark_points))
            b.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)

    feed(mine[:100])
    job = sm.prepare()
    assert job is not None
    lm = b.landmarks(cfg.min_landmark_points)
    job.run(lm)
    feed(mine[100:150])  # the live filter went on meanwhile
    job.catch_up([copy(s) for s in sm.scans if s.t_ns > job.scans[-1].t_ns], lm)
    feed(mine[150:])
    assert job.scans[-1].t_ns == mine[149].t_ns
    sm.apply(job, lm)
    # the window holds the job's scans up to its end, then the live ones re-run from it; the live filter is at the
    # newest scan
    assert [s.t_ns for s in sm.scans] == [f.t_ns for f in mine]
    assert all(a is b for a, b in zip(list(sm.scans)[:150], job.scans[-150:], strict=True))
    assert sm.nav.t_ns == mine[-1].t_ns


def test_a_failed_background_run_is_counted_and_the_map_goes_on(drift_dive: tuple[Scene, list[Any]]) -> None:
    from mapping.smoother import SmoothJob

    _, frames = drift_dive
    orig = SmoothJob.run

    def broken(self: SmoothJob, landmarks: Any) -> None:
        raise ValueError("boom")

    SmoothJob.run = broken  # type: ignore[method-assign]
    try:
        scfg = SmootherConfig(every_s=5.0)
        cfg = NavConfig(fix_quality_factor=5.0)
        run = replay_dive(frames[:300], navigate=True, nav_cfg=cfg, smoother=scfg, background="wait")
    finally:
        SmoothJob.run = orig  # type: ignore[method-assign]
    assert sum(len(v) for v in run.placed.values()) == 300
    assert run.planes()
    assert not run.smooth_hold_s or max(run.smooth_hold_s) < 1.0
