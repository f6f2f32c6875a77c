"""A tracked depth-only robot's clouds wait for its track's next check (``GraphConfig.hold_until_verified``,
:mod:`mapping.graph_hold`): committed when it passes, checked one by one when it fails, dropped and counted where
nothing vouches for them; the held clouds travel with the graph's state."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from lrsensor.frames import Pose
from mapping import graph_hold
from mapping.graph_config import TRACKED, GraphConfig
from mapping.graph_gate import TrackGate
from mapping.graph_hold import CloudHold, check_held, hold_step
from mapping.landmarks import PlaneLandmarks
from mapping.nav_config import AXES, NavConfig, NavEstimate

S = 1_000_000_000


class FakeGraph:
    """What the hold reads of a :class:`mapping.posegraph.GraphNav`: its gate, configs and revised poses."""

    def __init__(self) -> None:
        self.robot = "rov3"
        self.cfg = NavConfig()
        self.gcfg = TRACKED
        self.track = TrackGate(TRACKED.track_break_std_m)
        self.hold = CloudHold()
        #: t_ns -> (north, east): what the graph estimates now for each pose
        self.now: dict[int, tuple[float, float]] = {}

    def revised_poses(self) -> dict[int, Pose]:
        return {t: Pose(n, e, 1.0, 0.0, 0.0, 0.0) for t, (n, e) in self.now.items()}


def _est(t: int, placed: bool = True, pinned: int = 2) -> NavEstimate:
    std = dict.fromkeys(("north_m", "east_m", "down_m", "roll_deg", "pitch_deg", "yaw_deg"), 0.02)
    pose = Pose(1.0, 1.0, 1.0, 0.0, 0.0, 0.0)
    return NavEstimate("rov3", t, pose, std, dict.fromkeys(AXES, True), placed, "scan-odometry", pinned=pinned)


def _cloud() -> np.ndarray:
    rng = np.random.default_rng(1)
    return rng.uniform(-1, 1, (300, 3))


def _step(g: FakeGraph, k: int, *, verified: bool = False, moved: bool = False, pinned: int = 2) -> NavEstimate:
    t = k * S // 10
    g.now[t] = (1.0 + 0.01 * k, 1.0)
    if verified:
        g.track.verified_ns = t
    raw = Pose(float("nan"), float("nan"), 1.0, 0.0, 0.0, 0.0)
    est: NavEstimate = hold_step(g, k, t, raw, _cloud(), _est(t, pinned=pinned), PlaneLandmarks.empty(), moved)
    return est


def test_the_launch_fix_vouches_until_a_first_check_passes() -> None:
    g = FakeGraph()
    assert _step(g, 1).placed  # no map yet to check against: placed as before
    assert not g.hold.clouds


def test_clouds_wait_for_the_next_passed_check_then_go_in_with_the_graphs_poses() -> None:
    g = FakeGraph()
    _step(g, 1, verified=True)  # the first check: the hold starts (this cloud is released at once)
    assert [t for t, _, _ in g.hold.take()] == [S // 10]
    for k in range(2, 6):
        est = _step(g, k)
        assert est.held  # received, not in the map, nobody registers to it
        assert not est.placed
    assert len(g.hold.clouds) == 4
    assert not g.hold.take()
    g.now = {t: (n + 0.05, e) for t, (n, e) in g.now.items()}  # the graph smoothed them since
    _step(g, 6, verified=True)
    out = g.hold.take()
    assert [t for t, _, _ in out] == [k * S // 10 for k in range(2, 7)]
    assert out[0][1].north_m == pytest.approx(1.0 + 0.02 + 0.05)  # the pose the graph gives it now
    counts = g.hold.counts()
    assert (counts["committed"], counts["dropped"], counts["held"]) == (6, 0, 0)
    assert counts["lag_max_s"] == pytest.approx(0.4)  # the cloud of 0.2 s went in at 0.6 s


def test_after_a_slide_each_held_cloud_goes_in_only_where_its_own_scan_confirms_it(monkeypatch: Any) -> None:
    g = FakeGraph()
    _step(g, 1, verified=True)
    g.hold.take()
    for k in range(2, 6):
        _step(g, k, pinned=2 if k < 5 else 1)

    # clouds 2 and 3 match one place at their poses, 4 one place 0.3 m off, 5 (one wall) none and fits nothing
    def place(rel: Any, down: float, at: Any, radius: float, lm: Any) -> Any:
        t = next(t for t, (n, _) in g.now.items() if n == at[0])
        return {2: at, 3: at + 0.02, 4: at + np.array([0.3, 0.0])}.get(t * 10 // S)

    monkeypatch.setattr(graph_hold, "unique_place", place)
    monkeypatch.setattr(graph_hold, "fits_at", lambda *a: False)
    _step(g, 6, verified=True, moved=True)  # the check re-anchored the track: a slide
    assert [t * 10 // S for t, _, _ in g.hold.take()] == [2, 3, 6]
    counts = g.hold.counts()
    assert (counts["replaced"], counts["dropped"], counts["committed"]) == (2, 2, 2)  # the first and the 6th


def test_a_one_wall_scan_without_a_unique_place_goes_in_where_it_fits_the_map(monkeypatch: Any) -> None:
    g = FakeGraph()
    _step(g, 1, verified=True)
    g.hold.take()
    _step(g, 2, pinned=1)
    _step(g, 3, pinned=2)
    monkeypatch.setattr(graph_hold, "unique_place", lambda *a: None)
    monkeypatch.setattr(graph_hold, "fits_at", lambda *a: True)
    check_held(g, 4 * S // 10, PlaneLandmarks.empty())  # as at a break or the end
    assert [t * 10 // S for t, _, _ in g.hold.take()] == [2]  # a slide along the wall copies none of its faces
    assert g.hold.dropped == 1


@pytest.mark.parametrize(("share", "placed"), [(0.6, [2]), (0.9, [])])
def test_a_one_wall_cloud_must_fit_the_map_with_the_share_asked(
    monkeypatch: Any, share: float, placed: list[int]
) -> None:
    # 70 % of its points on the map's planes: the rest may be a face along the free direction, placed off by the slide
    g = FakeGraph()
    g.gcfg = replace(TRACKED, hold_one_wall_share=share)
    _step(g, 1, verified=True)
    g.hold.take()
    _step(g, 2, pinned=1)
    monkeypatch.setattr(graph_hold, "unique_place", lambda *a: None)
    monkeypatch.setattr(graph_hold, "fits_at", lambda rel, down, at, lm, cfg: cfg.min_share <= 0.7)
    check_held(g, 3 * S // 10, PlaneLandmarks.empty())
    assert [t * 10 // S for t, _, _ in g.hold.take()] == placed


def test_a_broken_track_settles_its_held_clouds_at_once(monkeypatch: Any) -> None:
    g = FakeGraph()
    _step(g, 1, verified=True)
    g.hold.take()
    _step(g, 2)
    monkeypatch.setattr(graph_hold, "unique_place", lambda *a: None)
    g.track.break_now(0.15, 3 * S // 10)
    est = hold_step(g, 3, 3 * S // 10, Pose(0, 0, 1, 0, 0, 0), _cloud(), _est(3 * S // 10, placed=False),
                    PlaneLandmarks.empty(), False)  # fmt: skip
    assert not est.held
    assert not g.hold.clouds
    assert g.hold.dropped == 1


def test_the_held_clouds_travel_with_the_state() -> None:
    g = FakeGraph()
    _step(g, 1, verified=True)
    _step(g, 2, pinned=1)
    back = CloudHold()
    back.load(g.hold.state())
    assert [(c.key, c.t_ns, c.pinned) for c in back.clouds] == [(2, 2 * S // 10, 1)]
    np.testing.assert_array_equal(back.clouds[0].points, g.hold.clouds[0].points)
    assert back.committed == 1


def test_tracked_holds_and_the_plain_graph_does_not() -> None:
    assert TRACKED.hold_until_verified
    assert not GraphConfig().hold_until_verified
    assert not replace(TRACKED, hold_until_verified=False).hold_until_verified


def test_the_map_thread_settles_a_silent_robots_held_clouds() -> None:
    """Without plane workers: a robot silent for IDLE_FLUSH_S whose clouds wait in its hold gets them checked
    (no later check comes) and those that go in reach the map, counted as placed."""
    import time

    from mapping import MapBuilder
    from services.map_workers import IDLE_FLUSH_S
    from services.mapfeed import MapFeed

    feed = MapFeed(MapBuilder(), lambda robot, seq: None, navigation=True)
    assert feed.navigator is not None
    g = FakeGraph()
    _step(g, 1, verified=True)
    g.hold.take()
    for k in range(2, 5):
        _step(g, k)

    def settle(landmarks: object) -> None:  # as check_held with every held cloud confirmed
        for c in g.hold.clouds:
            g.hold.out.append((c.t_ns, Pose(1.0, 1.0, 1.0, 0.0, 0.0, 0.0), c.points))
        g.hold.replaced += len(g.hold.clouds)
        g.hold.clouds = []

    g.settle = settle  # type: ignore[attr-defined]
    feed.navigator.robots["rov3"] = g  # type: ignore[assignment]
    feed._last_seen["rov3"] = time.monotonic() - 1.0
    feed._settle_silent()  # not silent long enough
    assert len(g.hold.clouds) == 3
    feed._last_seen["rov3"] = time.monotonic() - IDLE_FLUSH_S - 1.0
    feed._settle_silent()
    assert not g.hold.clouds
    assert feed.clouds == 3
    assert feed.builder is not None
    assert feed.builder.uncommitted("rov3") == 0  # its window extracted: nothing waits for a later cloud
    assert feed._nav_counts["rov3"][0] == 3


def test_held_clouds_go_in_at_the_checks_place_and_stay_there_when_asked() -> None:
    g = FakeGraph()
    g.gcfg = replace(TRACKED, commit_at_place=True)
    _step(g, 1, verified=True)
    g.hold.take()
    for k in range(2, 5):
        _step(g, k)
    g.track.place_shift = np.array([-0.05, 0.01])  # the check of 0.5 s found its place 5 cm south of the estimate
    _step(g, 5, verified=True)
    out = g.hold.take()
    assert [t * 10 // S for t, _, _ in out] == [2, 3, 4, 5]
    assert out[0][1].north_m == pytest.approx(1.0 + 0.02 - 0.05)
    assert out[0][1].east_m == pytest.approx(1.01)
    # frozen there: the graph's later estimates do not take them back
    assert g.track.frozen[2 * S // 10][0:2] == pytest.approx([0.97, 1.01])
    assert g.track.place_shift.tolist() == [0.0, 0.0]  # that check's alone
    _step(g, 6, verified=True)
    assert g.hold.take()[0][1].north_m == pytest.approx(1.06)
