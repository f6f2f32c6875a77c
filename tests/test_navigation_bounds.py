"""Bounded corrections (issue 27, round 2): registrations to a robot's own recent planes counted as relative,
corrections beyond the motion model rejected, and a fleet frame that leaves lost robots' launches out."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from lrsensor.frames import Pose, ned_to_body
from mapping.navigation import NavConfig, Navigator, PlaneLandmarks, RobotNav
from mapping.smoother import SmootherConfig
from mapping.synth import tank, trace

S = 1_000_000_000


def _plane(pid: int, contributions: dict[str, tuple[int, int]]) -> dict[str, Any]:
    extent = {"centroid": [0.0, 0.0, 1.0], "u": [0.0, 1.0, 0.0], "v": [0.0, 0.0, 1.0],
              "u_range_m": [-2.0, 2.0], "v_range_m": [-1.0, 1.0]}  # fmt: skip
    return {
        "id": pid,
        "normal": [1.0, 0.0, 0.0],
        "d": 0.0,
        "n_points": 10_000,
        "extent": extent,
        "contributions": {r: {"n_points": n, "first_ns": t} for r, (n, t) in contributions.items()},
    }


def test_own_recent_planes_carry_little_weight() -> None:
    lm = PlaneLandmarks.from_planes(
        [
            _plane(1, {"rov1": (500, 95 * S)}),  # made by rov1 5 s ago: its own recent poses
            _plane(2, {"rov1": (500, 10 * S)}),  # made by rov1 90 s ago: a revisit
            _plane(3, {"rov1": (500, 95 * S), "rov2": (500, 96 * S)}),  # someone else's too
            _plane(4, {"rov2": (500, 99 * S)}),
        ]
    )
    nav = RobotNav("rov1", NavConfig(own_recent_s=10.0, own_recent_weight=0.1))
    assert nav._plane_weights(100 * S, lm)[0].tolist() == [0.1, 1.0, 1.0, 1.0]
    assert nav._plane_weights(100 * S, lm)[1].tolist() == [True] * 4
    off = RobotNav("rov1", NavConfig(own_recent_weight=1.0))
    assert off._plane_weights(100 * S, lm)[0].tolist() == [1.0] * 4
    # own recent planes turn the heading only once the map joined the robot to another (the smoother's tuning)
    alone = RobotNav("rov1", NavConfig(own_recent_s=10.0, own_recent_weight=0.1, own_recent_turns_alone=False))
    alone.joined = False
    assert alone._plane_weights(100 * S, lm)[0].tolist() == [0.1, 1.0, 1.0, 1.0]
    assert alone._plane_weights(100 * S, lm)[1].tolist() == [False, True, True, True]
    alone.joined = True
    assert alone._plane_weights(100 * S, lm)[1].tolist() == [True] * 4


def test_the_navigator_says_which_robots_the_map_joins() -> None:
    from mapping.navigation import Navigator

    nav = Navigator()
    lm = PlaneLandmarks.from_planes(
        [_plane(1, {"rov1": (500, 0)}), _plane(2, {"rov2": (500, 0), "rov3": (500, 0)}), _plane(3, {"rov3": (9, 0)})]
    )
    for robot in ("rov1", "rov2"):
        nav.update(robot, S, Pose(1.0, 1.0, 1.0, 0.0, 0.0, 0.0), np.zeros((0, 3)), lm)
    assert nav.linked == {"rov1": {"rov1"}, "rov2": {"rov2", "rov3"}, "rov3": {"rov2", "rov3"}}
    assert not nav.robots["rov1"].joined
    assert nav.robots["rov2"].joined


def test_a_correction_beyond_the_motion_model_is_rejected_and_counted() -> None:
    scene = tank()
    true = Pose(2.0, 1.5, 1.0, 0.02, -0.03, math.radians(200.0))
    points = ned_to_body(trace(scene, true, n_rays=400).points_ned, true)
    from tests.test_navigation import scene_landmarks

    lm = scene_landmarks(scene)
    raw = Pose(true.north_m + 0.25, true.east_m - 0.2, true.down_m, true.roll_rad, true.pitch_rad, true.yaw_rad)
    # the launch fix claims 2 cm: a registration 30 cm away is a wrong association under that model
    gated = RobotNav("rov1", NavConfig(launch_sigma_m=0.02, gate_chi2=16.0, gate_max_m=0.5, gate_min_m=0.5))
    est = gated.update(0, raw, points, lm)
    assert gated.gated == 1
    assert est.inliers == 0
    assert est.pose is not None
    assert abs(est.pose.north_m - raw.north_m) < 1e-9
    free = RobotNav("rov1", NavConfig(launch_sigma_m=0.02, gate_chi2=0.0, gate_max_m=0.5, gate_min_m=0.5))
    assert free.update(0, raw, points, lm).inliers > 0
    assert free.gated == 0


def test_launch_frame_leaves_lost_robots_out() -> None:
    nav = Navigator(NavConfig(), SmootherConfig())
    empty = PlaneLandmarks.empty()
    for robot, ne in (("rov1", (0.0, 0.0)), ("rov2", (3.0, 0.0)), ("rov3", (0.0, 3.0))):
        nav.update(robot, 0, Pose(ne[0], ne[1], 1.0, 0.0, 0.0, 0.0), np.zeros((0, 3)), empty)
    for sm in nav.smoothers.values():
        sm.start_map_ne = (float(sm.nav.start_ne[0]), float(sm.nav.start_ne[1]))
    sm3 = nav.smoothers["rov3"]
    sm3.start_map_ne = (0.0, 3.5)  # smoothed 50 cm off its launch fix while lost
    sm3.nav.lost = True
    frame = nav.frame()
    assert abs(frame.to_json()["yaw_deg"]) < 1e-6
    assert np.allclose(frame.to_json()["shift_ne"], [0.0, 0.0], atol=1e-9)
    sm3.nav.lost = False
    sm3.start_map_ne = (0.0, 3.1)  # within 3 sigma of its fix: it counts
    assert not np.allclose(nav.frame().to_json()["shift_ne"], [0.0, 0.0], atol=1e-3)


def test_own_recent_planes_are_kept_from_turning_the_heading_until_joined() -> None:
    import dataclasses

    from tests.test_navigation import scene_landmarks

    scene = tank()
    true = Pose(2.0, 1.5, 1.0, 0.02, -0.03, math.radians(200.0))
    points = ned_to_body(trace(scene, true, n_rays=400).points_ned, true)
    lm = scene_landmarks(scene)
    mine = dataclasses.replace(lm, contrib=tuple({"rov1": (1000, 0)} for _ in lm.ids))  # all rov1's, just made
    raw = Pose(true.north_m + 0.05, true.east_m - 0.05, true.down_m, true.roll_rad, true.pitch_rad,
               true.yaw_rad + math.radians(2.0))  # fmt: skip
    turns = RobotNav("rov1", NavConfig(own_recent_weight=1.0)).update(0, raw, points, mine)
    # the smoother's tuning: while the map has not joined the robot to another, its own recent planes do not turn it
    alone = RobotNav("rov1", NavConfig(own_recent_weight=1.0, own_recent_turns_alone=False))
    alone.joined = False
    fixed = alone.update(0, raw, points, mine)
    assert abs(turns.correction["yaw_deg"]) > 1.0
    assert fixed.correction["yaw_deg"] == 0.0
    assert fixed.inliers > 0
