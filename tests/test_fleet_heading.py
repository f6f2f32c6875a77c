"""The depth-only fleet's compass biases from the launch fixes and shared walls (mapping/fleet_heading.py,
mapping/graph_fleet.py; issue 27): estimated on a synthetic fleet with known biases within their predicted standard
deviations, the prior kept where no wall is shared, and each graph robot's nav saying what its heading rests on."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from lrsensor.frames import Pose
from mapping.fleet_heading import View, estimate, wall_lines
from mapping.graph_fleet import heading_source
from mapping.nav_config import NavEstimate

#: the room's walls: (a point on it (north, east), its normal into the room), a box 8 x 6 m
ROOM = (((0.0, 3.0), (1.0, 0.0)), ((8.0, 3.0), (-1.0, 0.0)), ((4.0, 0.0), (0.0, 1.0)), ((4.0, 6.0), (0.0, -1.0)))


def _rot(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s], [s, c]])


def _scan(
    rng: np.random.Generator, at: np.ndarray, bias: float, walls: tuple[Any, ...] = ROOM, max_range: float = 6.0
) -> np.ndarray:
    """A full-circle scan from ``at`` (true NED) of ``walls``, 2 mm range noise, turned by a compass biased by
    ``bias``: points (M, 2) relative to the vehicle in its compass frame."""
    ang = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    dirs = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    best = np.full(ang.size, np.inf)
    for p, n in walls:
        p, n = np.asarray(p), np.asarray(n)
        den = dirs @ n
        with np.errstate(divide="ignore"):
            t = (p - at) @ n / den
        best = np.where((den < -1e-9) & (t > 0) & (t < best), t, best)
    ok = best <= max_range
    r = best[ok] + 0.002 * rng.standard_normal(int(ok.sum()))
    pts = dirs[ok] * r[:, None]
    return pts @ _rot(bias).T


def _fleet(seed: int, biases: dict[str, float], launches: dict[str, tuple[float, float]], fix_sd: float = 0.005,
           **kw: Any) -> tuple[list[View], dict[str, float]]:  # fmt: skip
    rng = np.random.default_rng(seed)
    views = []
    for robot, b in biases.items():
        at = np.asarray(launches[robot])
        fix = at + fix_sd * rng.standard_normal(2)
        pts = _scan(rng, at, b + math.radians(0.15) * float(rng.standard_normal()), **kw)
        views.append(View(robot, (float(fix[0]), float(fix[1])), pts))
    return views, biases


LAUNCHES = {"rov1": (1.2, 1.2), "rov2": (3.3, 4.8), "rov3": (2.0, 1.3)}


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_the_biases_and_the_common_heading_come_out_within_their_predicted_spread(seed: int) -> None:
    rng = np.random.default_rng([seed, 9])
    biases = {r: math.radians(float(rng.choice([-1.5, 1.5]) + rng.uniform(-0.5, 0.5))) for r in LAUNCHES}
    views, truth = _fleet(seed, biases, LAUNCHES)
    got = estimate(views)
    assert got.walls >= 2
    common = float(np.mean(list(truth.values())))
    # the compasses' mean bias is 0.5-2 deg here; the estimate puts it within a few tenths of a degree
    assert got.common_sd_rad < math.radians(0.3)
    assert abs(got.common_rad - common) < 4 * got.common_sd_rad, (math.degrees(got.common_rad), math.degrees(common))
    for r, b in truth.items():
        assert abs(got.bias_rad[r] - b) < 4 * got.sd_rad[r] + math.radians(0.05), r
        assert got.observed(r)


def test_the_estimate_is_no_better_than_the_fixes_allow() -> None:
    # launch fixes 5 cm off instead of 5 mm, and the estimator told so: its standard deviation grows with the
    # fixes' (the baselines turn 5 cm into degrees) and still covers the errors
    from mapping.fleet_heading import FleetHeadingConfig

    biases = dict.fromkeys(LAUNCHES, math.radians(1.5))
    errs, sds = [], []
    for seed in range(6):
        views, _ = _fleet(seed, biases, LAUNCHES, fix_sd=0.05)
        got = estimate(views, FleetHeadingConfig(fix_sigma_m=0.05))
        errs.append(got.common_rad - math.radians(1.5))
        sds.append(got.common_sd_rad)
    assert float(np.mean(sds)) > math.radians(0.5)
    assert float(np.sqrt(np.mean(np.square(errs)))) < 3 * float(np.mean(sds))


def test_robots_that_share_no_wall_keep_their_compass() -> None:
    # each robot sees one wall of its own (the others out of range): nothing relates them
    walls = {"rov1": (ROOM[0],), "rov2": (ROOM[1],), "rov3": (ROOM[3],)}
    rng = np.random.default_rng(3)
    views = [View(r, LAUNCHES[r], _scan(rng, np.asarray(LAUNCHES[r]), math.radians(1.5), walls[r])) for r in LAUNCHES]
    got = estimate(views)
    assert got.walls == 0
    for r in LAUNCHES:
        assert got.bias_rad[r] == 0.0
        assert got.sd_rad[r] == pytest.approx(math.radians(3.0))
        assert not got.observed(r)
        assert heading_source(r, False, got) == "compass"


def test_a_wall_seen_from_launches_along_it_fixes_its_direction_and_both_biases() -> None:
    # two robots 3 m apart along the west wall, each seeing only it: the offsets' difference along the baseline gives
    # the wall's direction, the directions each bias
    west = (ROOM[2],)
    launches = {"a": (1.0, 1.0), "b": (4.0, 1.2)}
    rng = np.random.default_rng(5)
    truth = {"a": math.radians(1.8), "b": math.radians(-1.1)}
    views = [View(r, launches[r], _scan(rng, np.asarray(launches[r]), truth[r], west)) for r in launches]
    got = estimate(views)
    assert got.walls == 1
    for r in launches:
        assert abs(got.bias_rad[r] - truth[r]) < math.radians(0.3), (r, math.degrees(got.bias_rad[r]))
    # seen from launches across it instead (the baseline along the normal): the direction is not observed
    launches = {"a": (2.0, 1.0), "b": (2.0, 3.0)}
    views = [View(r, launches[r], _scan(rng, np.asarray(launches[r]), truth[r], west)) for r in launches]
    got = estimate(views)
    assert got.common_sd_rad > math.radians(1.0)


def test_scan_lines_give_each_wall_s_direction_and_distance() -> None:
    rng = np.random.default_rng(1)
    at = np.array([1.5, 2.0])
    lines = wall_lines(_scan(rng, at, 0.0, max_range=5.0))
    got = sorted((round(math.degrees(ln.alpha_rad)) % 360, round(ln.c_m, 2)) for ln in lines)
    # the south wall 1.5 m behind (its normal to the vehicle: north), the west 2 m (east), the east 4 m (west); the
    # north wall, 6.5 m off, is out of range
    for line in ((0, 1.5), (90, 2.0), (270, 4.0)):
        assert line in got, got


def test_a_heading_on_the_compasses_alone_is_published_as_unconstrained() -> None:
    pose = Pose(1.0, 2.0, 1.0, 0.0, 0.0, 0.3)
    std = {"north_m": 0.02, "east_m": 0.02, "down_m": 0.01, "roll_deg": 0.2, "pitch_deg": 0.2, "yaw_deg": 0.5}
    pinned = {"north": True, "east": True, "yaw": True}
    est = NavEstimate("rov1", 0, pose, std, pinned, True, "scan-odometry", heading="compass")
    js = est.to_json()
    assert js["heading"] == "compass"
    assert "yaw" in js["unconstrained"]
    assert "yaw" not in js["constrained"]
    js = NavEstimate("rov1", 0, pose, std, pinned, True, "scan-odometry", heading="launch-walls").to_json()
    assert js["constrained"] == ["north", "east", "yaw"]
    assert heading_source("rov1", True, None) == "fixes"
    assert heading_source("rov1", False, None) == "compass"


def test_the_graphs_start_from_their_compasses_minus_the_fleet_s_biases() -> None:
    pytest.importorskip("gtsam")
    from mapping.navigation import NavConfig
    from mapping.synth import replay_dive, simulate_dive, tank, three_rov_plans

    frames = simulate_dive(
        tank(), three_rov_plans(), duration_s=3.0, rate_hz=10.0, n_rays=400, seed=2, navigation="depth-only"
    )
    launch = {}
    for f in frames:
        launch.setdefault(f.robot, []).append(math.remainder(f.pose_est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi))
    truth = {r: float(np.mean(b[:10])) for r, b in launch.items()}
    import mapping.navigator as navigator_module

    seen: dict[str, Any] = {}
    original = navigator_module.Navigator.update

    def update(self: Any, robot: str, *args: Any) -> Any:
        seen["nav"] = self
        return original(self, robot, *args)

    navigator_module.Navigator.update = update  # type: ignore[method-assign]
    try:
        on = NavConfig(graph_without_fix=True, frame_graph_launches=True, fleet_heading=True)
        run_on = replay_dive(frames, navigate=True, nav_cfg=on)
        nav_on = seen["nav"]
        run_off = replay_dive(frames, navigate=True, nav_cfg=replace(on, fleet_heading=False))
    finally:
        navigator_module.Navigator.update = original  # type: ignore[method-assign]
    assert nav_on.fleet_heading.result is not None
    for robot, b in truth.items():
        graph = nav_on.robots[robot]
        assert graph.compass_bias is not None
        assert abs(graph.compass_bias[0] - b) < math.radians(0.4), (robot, math.degrees(graph.compass_bias[0]))
        # the graph's heading now: the compass minus the bias, not the compass
        assert abs(graph.x[4] + b) < math.radians(0.5), (robot, math.degrees(graph.x[4]))
        assert run_on.estimates[robot].heading == "launch-walls"
        assert run_off.estimates[robot].heading == "compass"
    # the first second's clouds waited for the estimate and then went in
    assert sum(run_on.unplaced.values()) <= sum(run_off.unplaced.values()) + 3, (run_on.unplaced, run_off.unplaced)
    assert sum(len(v) for v in run_on.placed.values()) > 0.8 * len(frames)
    # the map's heading is the estimate's: the graphs' launch points no longer turn it
    assert run_on.frame.yaw_rad == 0.0
    assert run_off.frame.yaw_rad != 0.0
