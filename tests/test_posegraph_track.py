"""What a depth-only robot's pose graph may place (mapping/graph_gate.py, mapping/relocalize.py, issue 27): an
unbroken track, a broken one taken up again only where a scan matches one place alone, the placed poses frozen at
the break, and the launch frame from the graphs' launches."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from lrsensor.frames import Pose
from mapping.graph_gate import TrackGate, check_planes
from mapping.landmarks import PlaneLandmarks
from mapping.navigation import NavConfig, Navigator
from mapping.relocalize import unique_place
from mapping.synth import simulate_dive, tank, three_rov_plans

pytest.importorskip("gtsam")

from mapping.graph_config import GraphConfig
from mapping.posegraph import GraphNav

NOFIX = Pose(math.nan, math.nan, 1.0, 0.0, 0.0, 0.0)


def _wall(pid: int, normal: tuple[float, float], at: float, centre: tuple[float, float]) -> dict[str, Any]:
    """A vertical wall ``normal . p + d = 0`` (normal toward the water, horizontal), 3 m wide, 2 m tall at depth
    1 m, made by another robot."""
    n = np.array([normal[0], normal[1], 0.0])
    u = np.array([-normal[1], normal[0], 0.0])
    extent = {"centroid": [centre[0], centre[1], 1.0], "u": u.tolist(), "v": [0.0, 0.0, 1.0],
              "u_range_m": [-1.5, 1.5], "v_range_m": [-1.0, 1.0]}  # fmt: skip
    return {"id": pid, "normal": n.tolist(), "d": float(-at), "n_points": 10_000, "extent": extent,
            "contributions": {"other": {"n_points": 10_000, "first_ns": 0}}}  # fmt: skip


#: a corner: a wall at north 2 m facing south, one at east 2 m facing west
CORNER = [_wall(1, (-1.0, 0.0), -2.0, (2.0, 1.0)), _wall(2, (0.0, -1.0), -2.0, (1.0, 2.0))]


def _corner_scan(both: bool = True) -> np.ndarray:
    """Points (M, 3) seen from (1, 1) at heading 0 (body = NED there): the north wall 1 m ahead, and the east wall
    1 m to the right when ``both``."""
    s = np.linspace(-0.6, 0.6, 60)
    north = np.stack([np.full_like(s, 1.0), s, np.zeros_like(s)], axis=1)
    east = np.stack([s, np.full_like(s, 1.0), np.zeros_like(s)], axis=1)
    return np.concatenate([north, east]) if both else north


def test_the_track_breaks_once_past_its_std_and_keeps_the_first_frozen_pose() -> None:
    gate = TrackGate(0.1)
    assert not gate.step(0.08, 1)
    assert gate.step(0.12, 2)
    assert not gate.step(0.5, 3)  # already broken
    assert gate.breaks == 1
    assert gate.broke_ns == 2
    gate.freeze({10: np.array([1.0, 2.0, 0.0])})
    gate.freeze({10: np.array([5.0, 5.0, 0.0]), 11: np.array([1.0, 1.0, 0.0])})
    assert gate.frozen[10].tolist() == [1.0, 2.0, 0.0]  # a pose frozen at an earlier break stays
    other = TrackGate(0.1)
    other.load(gate.state())
    assert other.broken
    assert sorted(other.frozen) == [10, 11]
    other.resume()
    assert not other.broken
    assert other.relocalized == 1


def test_a_corner_is_one_place_one_wall_and_a_mirrored_corner_are_not() -> None:
    lm = PlaneLandmarks.from_planes(CORNER)
    found = unique_place(_corner_scan(), 1.0, np.array([1.3, 0.8]), 0.6, lm)
    assert found is not None
    assert np.hypot(*(found - np.array([1.0, 1.0]))) < 0.03
    # one wall: every place along it fits as well (a ridge)
    assert unique_place(_corner_scan(both=False), 1.0, np.array([1.3, 0.8]), 0.6, lm) is None
    # a second corner 0.5 m east (its walls as long): two places fit
    twin = [*CORNER, _wall(3, (-1.0, 0.0), -2.0, (2.0, 1.5)), _wall(4, (0.0, -1.0), -2.5, (1.0, 2.5))]
    assert unique_place(_corner_scan(), 1.0, np.array([1.0, 1.25]), 0.6, PlaneLandmarks.from_planes(twin)) is None


def _broken_then(scan: np.ndarray, steps: int, **gate: Any) -> tuple[GraphNav, list[Any]]:
    """A graph launched at (1, 1) whose track breaks at once (its break std below the launch sigma), fed ``scan``
    without a fix ``steps`` times at 10 Hz, re-localization on (and ``gate``'s other options)."""
    lm = PlaneLandmarks.from_planes(CORNER)
    cfg = GraphConfig(track_break_std_m=0.045, relocalize=True, relocalize_every_s=0.5, **gate)
    g = GraphNav("rov1", NavConfig(), cfg)
    g.update(0, Pose(1.0, 1.0, 1.0, 0.0, 0.0, 0.0), scan, lm)
    ests = [g.update(k * 100_000_000, NOFIX, scan, lm) for k in range(1, steps + 1)]
    return g, ests


def test_a_broken_track_is_taken_up_again_only_where_the_scan_pins_one_place() -> None:
    g, ests = _broken_then(_corner_scan(), 15)
    assert g.track.breaks >= 1
    assert g.track.relocalized >= 1
    # the scan that re-localized says so
    assert any(e.motion == "relocalized" for e in ests)
    last = ests[-1]
    assert last.placed
    assert last.pose is not None
    assert math.hypot(last.pose.north_m - 1.0, last.pose.east_m - 1.0) < 0.05
    # one wall: the robot stays lost, nothing placed, and the status says so
    g1, ests1 = _broken_then(_corner_scan(both=False), 15)
    assert g1.track.relocalized == 0
    assert not any(e.placed for e in ests1)
    assert all(e.motion == "lost" for e in ests1)


def test_a_broken_track_says_how_far_the_robot_can_have_gone_since_the_break() -> None:
    g, ests = _broken_then(_corner_scan(both=False), 15)
    assert g.track.broken
    grown = []
    for k, est in enumerate(ests, start=1):
        if est.motion != "lost":
            continue
        reach = 3.0 * g.track.std_at_break + 0.6 * (k * 0.1 - g.track.broke_ns * 1e-9) + 0.1
        assert min(est.std["north_m"], est.std["east_m"]) >= reach / 3.0 - 1e-9, k
        grown.append(est.std["north_m"])
    assert grown == sorted(grown)
    assert grown[-1] > 0.3
    # the graph's own marginal claims far less: the odometry along the wall holds north while nothing places it
    assert math.sqrt(g._cov[0, 0]) < 0.5 * grown[-1]
    assert ests[-1].to_json()["north_m_std"] == pytest.approx(grown[-1])


@pytest.fixture(scope="module")
def depth_only() -> list[Any]:
    return simulate_dive(
        tank(), three_rov_plans(), duration_s=8.0, rate_hz=10.0, n_rays=300, seed=1, navigation="depth-only"
    )


def test_what_was_placed_before_the_break_stays_where_it_was(depth_only: list[Any]) -> None:
    fr = [f for f in depth_only if f.robot == "rov2"]
    g = GraphNav("rov2", NavConfig(), GraphConfig(track_break_std_m=0.06))
    lm = PlaneLandmarks.empty()
    ests = [g.update(f.t_ns, f.pose_est, f.points_body, lm) for f in fr]
    broke = next(i for i, e in enumerate(ests) if not e.placed)
    assert g.track.broken
    assert all(not e.placed and e.motion == "lost" for e in ests[broke:])
    before = g.revised_poses()
    frozen = {t: p for t, p in before.items() if t in g.track.frozen}
    assert len(frozen) >= broke - 1
    for t, p in frozen.items():
        assert (p.north_m, p.east_m) == (g.track.frozen[t][0], g.track.frozen[t][1])
    # no gate: the same poses keep moving with the later scans (what the freeze holds still)
    g2 = GraphNav("rov2")
    for f in fr:
        g2.update(f.t_ns, f.pose_est, f.points_body, lm)
    moved = [t for t, p in g2.revised_poses().items() if t in frozen and abs(p.north_m - frozen[t].north_m) > 1e-6]
    assert moved


def test_the_launch_frame_takes_the_graphs_launches_when_asked() -> None:
    pts = np.zeros((0, 3))
    lm = PlaneLandmarks.empty()
    frames = {}
    for flag in (False, True):
        nav = Navigator(NavConfig(graph_without_fix=True, frame_graph_launches=flag))
        for name, (n, e) in {"a": (1.0, 1.0), "b": (4.0, 1.0)}.items():
            nav.update(name, 0, Pose(n, e, 1.0, 0.0, 0.0, 0.0), pts, lm)
            nav.update(name, 100_000_000, NOFIX, pts, lm)
            # the graph now places its launch 10 cm north of its fix
            nav.robots[name]._est[0, 0] += 0.1
        frames[flag] = nav.frame()
    assert frames[False].shift_ne == (0.0, 0.0)
    assert frames[True].shift_ne[0] == pytest.approx(-0.1, abs=1e-6)


def test_a_passed_check_beside_the_place_anchors_the_track_there_when_asked() -> None:
    # launched 6 cm north of where it is (the corner scan is seen from (1, 1)); each check finds (1, 1) within
    # verify_tol_m: it passes, and with verify_anchor_m the place also becomes a prior on the checked pose
    lm = PlaneLandmarks.from_planes(CORNER)

    def north_error(**gate: Any) -> float:
        cfg = GraphConfig(track_break_std_m=0.1, relocalize=True, verify_every_s=0.2, **gate)
        g = GraphNav("rov1", NavConfig(), cfg)
        g.update(0, Pose(1.06, 1.0, 1.0, 0.0, 0.0, 0.0), _corner_scan(), lm)
        ests = [g.update(k * 100_000_000, NOFIX, _corner_scan(), lm) for k in range(1, 11)]
        assert g.track.relocalized == 0  # every check passed
        assert ests[-1].pose is not None
        return abs(ests[-1].pose.north_m - 1.0)

    free, anchored = north_error(), north_error(verify_anchor_m=0.01)
    assert anchored < free
    assert anchored < 0.015


def test_the_checks_leave_out_the_planes_a_robot_made_mostly_itself_when_asked() -> None:
    # a slid robot's own copy of a face would vouch for its slide: with a share below 1 its check does without it
    walls = [_wall(1, (-1.0, 0.0), -2.0, (2.0, 1.0)), _wall(2, (0.0, -1.0), -2.0, (1.0, 2.0)),
             _wall(3, (-1.0, 0.0), -2.07, (2.07, 1.0))]  # fmt: skip
    walls[1]["contributions"] = {"other": {"n_points": 3000, "first_ns": 0}, "me": {"n_points": 7000, "first_ns": 0}}
    walls[2]["contributions"] = {"me": {"n_points": 10_000, "first_ns": 0}}
    lm = PlaneLandmarks.from_planes(walls)
    assert check_planes(lm, "me", GraphConfig()) is lm  # off (1): every plane
    assert check_planes(lm, "new", GraphConfig(verify_own_share=0.5)).ids.tolist() == [1, 2, 3]
    assert check_planes(lm, "me", GraphConfig(verify_own_share=0.9)).ids.tolist() == [1, 2]
    assert check_planes(lm, "me", GraphConfig(verify_own_share=0.5)).ids.tolist() == [1]


def test_a_passed_check_gives_its_place_for_the_held_clouds_when_asked() -> None:
    # launched 6 cm north of where it is: the checks pass ((1, 1) lies within verify_tol_m), and with
    # commit_at_place each says how far its place lies from the estimate (the held clouds go in moved by it)
    lm = PlaneLandmarks.from_planes(CORNER)

    def shifts(**gate: Any) -> list[tuple[float, float, float]]:
        cfg = GraphConfig(track_break_std_m=0.1, relocalize=True, verify_every_s=0.2, **gate)
        g = GraphNav("rov1", NavConfig(), cfg)
        g.update(0, Pose(1.06, 1.0, 1.0, 0.0, 0.0, 0.0), _corner_scan(), lm)
        out = []
        for k in range(1, 11):
            est = g.update(k * 100_000_000, NOFIX, _corner_scan(), lm)
            assert est.pose is not None
            if g.track.verified_ns == k * 100_000_000:
                out.append((est.pose.north_m, *g.track.place_shift))
        assert g.track.relocalized == 0  # every check passed
        return out

    assert all(dn == de == 0.0 for _, dn, de in shifts())  # off
    got = shifts(commit_at_place=True)
    assert got
    assert got[0][1] < -0.03  # the first check: the estimate still 6 cm north
    for north, dn, de in got:
        assert north + dn == pytest.approx(1.0, abs=0.02)  # moved by it, a held cloud goes in at the place
        assert abs(de) < 0.02
