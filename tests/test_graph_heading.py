"""The heading of a depth-only robot checked against one wall's direction (mapping.graph_heading)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from lrsensor.frames import Pose
from mapping.graph_heading import heading_offset
from mapping.landmarks import PlaneLandmarks
from mapping.nav_config import NavConfig


def _north_wall() -> PlaneLandmarks:
    """The wall north = 3 m, east -2..2 m, down 0..2 m, facing south (toward a vehicle at the origin)."""
    return PlaneLandmarks(
        ids=np.array([7], dtype=np.int64),
        normal=np.array([[-1.0, 0.0, 0.0]]),
        d=np.array([3.0]),
        centroid=np.array([[3.0, 0.0, 1.0]]),
        u=np.array([[0.0, 1.0, 0.0]]),
        v=np.array([[0.0, 0.0, 1.0]]),
        u_range=np.array([[-2.0, 2.0]]),
        v_range=np.array([[-1.0, 1.0]]),
    )


def _scan(rng: np.random.Generator) -> np.ndarray:
    """Points on the wall relative to a vehicle at (0, 0, 1) heading north, level (body = NED here)."""
    east = rng.uniform(-1.2, 1.2, 300)
    down = rng.uniform(-0.4, 0.4, 300)
    north = 3.0 + 0.005 * rng.standard_normal(300)
    return np.stack([north, east, down], axis=1)


def test_one_wall_gives_the_heading_error_whatever_the_position_along_it() -> None:
    rng = np.random.default_rng(3)
    pts = _scan(rng)
    raw = Pose(math.nan, math.nan, 1.0, 0.0, 0.0, 0.0)
    for along in (0.0, 0.4):  # the position along the wall is unobservable; the heading is not
        for err_deg in (-1.5, 0.0, 2.0):
            x = np.array([0.02, along, math.radians(err_deg)])
            got = heading_offset(pts, raw, x, _north_wall(), NavConfig())
            assert got is not None
            off, sd, used = got
            assert used == 1
            assert abs(math.degrees(off) - err_deg) < 0.1
            assert 0.0 < math.degrees(sd) < 0.5


def test_no_wall_or_a_narrow_patch_says_nothing() -> None:
    rng = np.random.default_rng(4)
    pts = _scan(rng)
    raw = Pose(math.nan, math.nan, 1.0, 0.0, 0.0, 0.0)
    far = np.array([-2.0, 0.0, 0.0])  # the wall out of the gate
    assert heading_offset(pts, raw, far, _north_wall(), NavConfig()) is None
    narrow = pts[np.abs(pts[:, 1]) < 0.2]  # too short a line to tell a direction
    assert heading_offset(narrow, raw, np.zeros(3), _north_wall(), NavConfig()) is None


class _Graph:
    """A pose graph's face to the fleet frame: its launch (map frame, fix) and its mean heading correction."""

    def __init__(self, start: tuple[float, float], corr_deg: float, poses: int = 50) -> None:
        self.start_map_ne = start
        self.start_ne = np.array(start)
        self.lost = False
        self.x = np.zeros(5)
        self.yaw_scans = 0
        self._corr = (math.radians(corr_deg), poses)

    def mean_correction(self) -> tuple[float, int]:
        return self._corr


def test_a_graph_s_mean_correction_is_its_estimated_heading_minus_its_compass() -> None:
    from mapping.posegraph import GraphNav

    g = GraphNav("rov1")
    assert g.mean_correction() is None
    g._t = [0, 1, 2, 3]
    g._compass = [math.pi - 0.01, -math.pi + 0.01, 0.5, 0.5]
    # estimates 1 deg to the east of each compass reading; the first two across the +-pi wrap
    g._est = np.array([[0.0, 0.0, c + math.radians(1.0)] for c in g._compass])
    got = g.mean_correction()
    assert got is not None
    assert abs(math.degrees(got[0]) - 1.0) < 1e-9
    assert got[1] == 4
    g._first_key = 2  # poses before the window no longer count
    assert g.mean_correction() == (pytest.approx(math.radians(1.0)), 2)


def test_the_fleet_compass_turns_the_frame_by_the_robots_mean_correction() -> None:
    from mapping.nav_filter import RobotNav
    from mapping.navigator import Navigator

    launches = {"rov1": ((1.2, 1.2), -3.0), "rov2": ((3.3, 4.8), 0.2), "rov3": ((2.0, 1.3), 0.4, 5)}
    for fleet in (False, True):
        nav = Navigator(NavConfig(frame_graph_launches=True, frame_fleet_compass=fleet))
        for name, spec in launches.items():
            nav.robots[name] = _Graph(*spec)  # type: ignore[arg-type]
        frame = nav.frame()
        if not fleet:
            # the launches sit on their fixes: the launch frame does not turn
            assert abs(frame.yaw_rad) < 1e-12
        else:
            # rov3 has too few poses to count; each robot once: (-3.0 + 0.2) / 2
            assert math.degrees(frame.yaw_rad) == pytest.approx(-1.4)
            assert frame.pivot_ne == pytest.approx((2.1666667, 2.4333333))
    # a robot with fixes (on the filter, no mean correction) gives the map its heading: no turn
    nav = Navigator(NavConfig(frame_graph_launches=True, frame_fleet_compass=True))
    for name, spec in launches.items():
        nav.robots[name] = _Graph(*spec)  # type: ignore[arg-type]
    nav.robots["rov4"] = RobotNav("rov4", nav.cfg)
    assert abs(nav.frame().yaw_rad) < 1e-12


def _turned_plane(face: Any, pid: int, deg: float) -> dict[str, Any]:
    """A map plane (``map_json`` layout) of ``face`` turned by ``deg`` about its centre (north towards east)."""
    a = math.radians(deg)
    r = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    c = np.array(face.center)
    u, v = r @ np.array(face.u), r @ face.v
    corners = [c + su * face.half_u * u + sv * face.half_v * v for su in (-1, 1) for sv in (-1, 1)]
    n = r @ np.array(face.normal)
    return {"id": pid, "normal": list(n), "d": float(-n @ c),
            "extent": {"centroid": list(c), "corners": [list(p) for p in corners]}}  # fmt: skip


def test_the_map_s_walls_say_its_heading_error_with_its_sign() -> None:
    from mapping.synth import hit_faces, score_map, tank, wall_yaw_deg

    scene = tank()
    faces = {f.name: f for f in scene.faces}
    planes = [_turned_plane(faces["wall.west"], 1, 1.0), _turned_plane(faces["wall.south"], 2, -0.5)]
    planes.append(_turned_plane(faces["wall.east"], 3, 1.0))
    score = score_map(planes, scene, hit_faces(scene, []))
    assert sorted(wall_yaw_deg(planes, score)) == pytest.approx([-0.5, 1.0, 1.0])


def test_the_unbiased_fleet_keeps_each_robot_s_bias_about_a_zero_mean() -> None:
    from benchmarks.bench_nav import unbias_fleet
    from mapping.synth import simulate_dive, tank, three_rov_plans

    frames = simulate_dive(tank(), three_rov_plans(), duration_s=2.0, rate_hz=5.0, n_rays=40, seed=3,
                           navigation="depth-only")  # fmt: skip

    def bias(fs: list[Any]) -> dict[str, float]:
        out: dict[str, list[float]] = {}
        for f in fs:
            out.setdefault(f.robot, []).append(math.remainder(f.pose_est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi))
        return {r: float(np.mean(v)) for r, v in out.items()}

    before, after = bias(frames), bias(unbias_fleet(frames))
    shift = {r: before[r] - after[r] for r in before}
    assert abs(float(np.mean([after[r] for r in after]))) < 1e-3  # the robots weigh alike here (same frame rate)
    assert max(shift.values()) - min(shift.values()) < 1e-12  # one shift for all: each keeps its own bias
    assert abs(math.degrees(next(iter(shift.values())))) > 0.1
