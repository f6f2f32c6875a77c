"""Acceptance-style mapping tests: a tank dived by two ROVs with realistic IMU noise, scored against the truth.

The synthetic dive (``mapping.synth``) traces the two laser fans into a box tank with two square pillars (one
turned 30 degrees); the base station sees body-frame points placed with a noisy navigation solution: attitude
white noise 0.2 deg, position white noise 1.5 cm plus a 2 mm/sqrt(s) random walk, range noise 2 mm.
"""

from __future__ import annotations

import json

import pytest

from mapping import MapBuilder, MapConfig
from mapping.synth import hit_faces, score_map, simulate_dive, tank, two_rov_plans


@pytest.fixture(scope="module")
def dive() -> tuple:
    scene = tank()
    plans = two_rov_plans()  # 0.3 m/s: one full loop of the tank in the 62 s
    frames = simulate_dive(
        scene, plans, duration_s=62.0, rate_hz=30.0, n_rays=400, seed=1, attitude_noise_deg=0.2, position_noise_m=0.015
    )
    return scene, frames


def _build(frames: list) -> MapBuilder:
    b = MapBuilder(MapConfig())
    for f in frames:
        b.add_cloud(f.robot, f.t_ns, f.points_ned_est, f.pose_est)
    b.flush()
    return b


@pytest.mark.slow
def test_two_rov_tank_map_has_every_hit_face_once(dive: tuple) -> None:
    scene, frames = dive
    b = _build(frames)
    planes = b.map_json()["planes"]
    score = score_map(planes, scene, hit_faces(scene, frames))
    hit = [f.face.name for f in score.faces if f.hit]
    assert len(hit) == 12, score.table()  # 4 walls + 8 pillar faces; the floor is never hit
    assert score.missing(angle_deg=2.0, offset_m=0.05) == [], score.table()
    assert score.duplicates() == [], score.table()
    assert len(score.spurious) <= 1, score.table()
    for p in planes:
        if p["id"] not in score.spurious and p["n_points"] > 50_000:  # the walls are seen by both robots
            assert p["robots"] == ["rov1", "rov2"]

    # the same dive replayed gives the same map, bit for bit
    again = _build(frames).map_json(include_tracks=True)
    assert json.dumps(again, sort_keys=True) == json.dumps(b.map_json(include_tracks=True), sort_keys=True)
