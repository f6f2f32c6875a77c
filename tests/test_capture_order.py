"""The map thread takes the robots' clouds in capture-time order across robots (services.capture_order): a robot
whose clouds reach the base late does not see the map built without it, within a bounded wait."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import zenoh
from waiting import wait_until

from services.capture_order import CaptureOrder, QuietFlush
from services.testnet import TestNetwork
from services.wire import CloudMsg

S = 1_000_000_000


@dataclass
class _Msg:
    robot: str
    t_ns: int


def test_the_oldest_cloud_waits_for_a_robot_behind() -> None:
    order = CaptureOrder(limit=10)
    order.push(_Msg("a", 1 * S), 0.0)
    order.push(_Msg("b", 1 * S), 0.0)
    order.push(_Msg("a", 3 * S), 0.0)
    assert [order.pop_ready(0.1).t_ns for _ in range(2)] == [1 * S, 1 * S]  # type: ignore[union-attr]
    assert order.pop_ready(0.1) is None  # b may still send a cloud older than a's 3 s
    order.push(_Msg("b", 2 * S), 0.1)
    assert order.pop_ready(0.1).robot == "b"  # type: ignore[union-attr]
    assert order.pop_ready(0.1) is None
    order.push(_Msg("b", 4 * S), 0.2)
    assert order.pop_ready(0.2).t_ns == 3 * S  # type: ignore[union-attr]
    assert order.forced == 0


def test_clouds_of_one_capture_time_go_by_robot_name_whatever_came_first() -> None:
    for arrival in (["b", "c", "a"], ["c", "a", "b"]):
        order = CaptureOrder(limit=10)
        for robot in arrival:
            order.push(_Msg(robot, 1 * S), 0.0)
        assert [order.pop_ready(0.0).robot for _ in range(3)] == ["a", "b", "c"]  # type: ignore[union-attr]


def test_the_wait_is_bounded_by_time_quiet_robots_and_size() -> None:
    order = CaptureOrder(limit=3, max_wait_s=1.0, quiet_s=5.0)
    order.push(_Msg("a", 1 * S), 0.0)
    order.push(_Msg("b", 5 * S), 0.0)
    assert order.pop_ready(0.0).robot == "a"  # type: ignore[union-attr]
    assert order.pop_ready(0.5) is None
    assert order.pop_ready(1.0).robot == "b"  # type: ignore[union-attr]  # waited max_wait_s
    order.push(_Msg("b", 6 * S), 1.0)
    assert order.pop_ready(5.5).robot == "b"  # type: ignore[union-attr]  # a is quiet: not waited for
    for t in (7, 8):
        order.push(_Msg("b", t * S), 6.0)
    order.push(_Msg("a", 2 * S), 6.0)
    assert order.pop_ready(6.0).robot == "a"  # type: ignore[union-attr]
    assert order.pop_ready(6.0) is None
    for t in (9, 10):
        order.push(_Msg("b", t * S), 6.0)
    assert order.pop_ready(6.0).t_ns == 7 * S  # type: ignore[union-attr]  # beyond the limit
    assert order.forced == 2


def test_a_robot_delivered_late_still_shares_the_fleet_heading() -> None:
    """A depth-only 3-robot dive whose third robot's clouds reach the base 5 s of capture time behind the others
    (as one ingest worker's robots ran ahead when fed faster than real time): the fleet heading estimate, made over
    every graph robot's first second, still sees all three robots."""
    pytest.importorskip("gtsam")
    from mapping.synth import simulate_dive, tank, three_rov_plans

    frames = simulate_dive(
        tank(), three_rov_plans(), duration_s=8.0, rate_hz=10.0, n_rays=400, seed=1, navigation="depth-only"
    )
    late = [f for f in frames if f.robot == "rov3"]
    early = [f for f in frames if f.robot != "rov3"]
    skew = 5 * S
    # every robot's first cloud first (the base has heard from each), then rov3's clouds 5 s late
    order = sorted(
        early + late,
        key=lambda f: (f.t_ns + (skew if f.robot == "rov3" and f is not late[0] else 0), f.robot),
    )
    with TestNetwork("co") as net:
        base = net.start_base(map_mode="on", navigation=True)
        pubs = {
            r: net.session().declare_publisher(net.keys.cloud(r), congestion_control=zenoh.CongestionControl.BLOCK)
            for r in ("rov1", "rov2", "rov3")
        }
        seqs = dict.fromkeys(pubs, 0)
        for f in order:
            pts = f.points_body.astype(np.float32)
            n = len(pts)
            flags, weights = np.zeros(n, np.uint8), np.ones(n, np.float32)
            msg = CloudMsg(f.robot, seqs[f.robot], f.t_ns, f.pose_est, pts, flags, weights)
            pubs[f.robot].put(msg.to_bytes())
            seqs[f.robot] += 1
        assert wait_until(lambda: base.processed >= len(frames), 120.0)
        assert base.drain(120)
        nav = base.feed.navigator
        assert nav is not None
        assert nav.fleet_heading is not None
        assert nav.fleet_heading.result is not None
        assert sorted(nav.fleet_heading.result.bias_rad) == ["rov1", "rov2", "rov3"]


def test_quiet_flush_is_due_once_per_silence() -> None:
    quiet = QuietFlush(quiet_s=5.0)
    assert not quiet.due(100.0)  # no cloud yet: nothing to flush
    quiet.cloud(0.0)
    assert not quiet.due(4.9)
    assert quiet.due(5.0)
    quiet.flushed()
    assert not quiet.due(50.0)  # once per silence
    quiet.cloud(60.0)  # a new dive
    assert quiet.due(65.5)
    quiet.flushed()
    assert quiet.count == 2


def test_a_silent_fleet_gets_the_map_flushed_as_at_a_close() -> None:
    """A live base (no flush_map, no close) whose robots stopped sending: once the fleet is silent for the quiet
    time, the clouds still waiting in a robot's window are extracted (and the smoother's last run made), so the map
    served after a dive is the finished one."""
    from mapping.synth import simulate_dive, tank, three_rov_plans

    frames = [f for f in simulate_dive(tank(), three_rov_plans(), duration_s=0.6, rate_hz=10.0, n_rays=400, seed=1)
              if f.robot == "rov1"]  # fmt: skip
    with TestNetwork("qf") as net:
        base = net.start_base(map_mode="on", navigation=True)
        base.feed.quiet.quiet_s = 1.5
        pub = net.session().declare_publisher(net.keys.cloud("rov1"), congestion_control=zenoh.CongestionControl.BLOCK)
        for seq, f in enumerate(frames):  # fewer clouds than one extraction takes (MapConfig.extract_every_clouds)
            pts = f.points_body.astype(np.float32)
            n = len(pts)
            pub.put(
                CloudMsg("rov1", seq, f.t_ns, f.pose_est, pts, np.zeros(n, np.uint8), np.ones(n, np.float32)).to_bytes()
            )
        assert wait_until(lambda: base.processed >= len(frames), 30.0)
        assert base.drain(30)
        before = base.status()["map"]
        assert before["pending"] == len(frames)
        assert before["quiet_flushes"] == 0
        assert wait_until(lambda: base.status()["map"]["quiet_flushes"] == 1, 30.0)
        after = base.status()["map"]
        assert after["pending"] == 0
        assert base.status()["robots"]["rov1"]["mapped"] == len(frames)
