"""The fleet heading with plane workers (services/map_worker_heading.py): the base decides which clouds are kept and
held and when the estimate is due, the workers keep the views and give their graphs the biases the base estimates."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pytest

from lrsensor.frames import Pose
from mapping.synth import DiveFrame, simulate_dive, tank, three_rov_plans
from services.map_worker_heading import HeadingRelay
from services.map_worker_wire import HeadingViews, MapControl, MapJob, decode_obs, decode_work

NAN = float("nan")


def _depth_only(seconds: float = 3.0) -> list[DiveFrame]:
    return simulate_dive(
        tank(), three_rov_plans(), duration_s=seconds, rate_hz=10.0, n_rays=400, seed=2, navigation="depth-only"
    )


def _launch_biases(frames: list[DiveFrame]) -> dict[str, float]:
    """Each robot's compass bias over its first second (radians): what the fleet heading estimates."""
    got: dict[str, list[float]] = {}
    for f in frames:
        got.setdefault(f.robot, []).append(math.remainder(f.pose_est.yaw_rad - f.pose_true.yaw_rad, 2 * math.pi))
    return {r: float(np.mean(b[:10])) for r, b in got.items()}


def _in_process_biases(frames: list[DiveFrame]) -> dict[str, float]:
    """The biases the map thread's Navigator estimates on the same dive (``--no-fix graph``)."""
    import mapping.navigator as navigator_module
    from mapping.navigation import NavConfig
    from mapping.synth import replay_dive
    from services.map_worker_nav import no_fix_config

    seen: dict[str, Any] = {}
    original = navigator_module.Navigator.update

    def update(self: Any, *args: Any) -> Any:
        seen["nav"] = self
        return original(self, *args)

    cfg, graph_cfg = no_fix_config(NavConfig(), "graph")
    navigator_module.Navigator.update = update  # type: ignore[method-assign]
    try:
        replay_dive(frames, navigate=True, nav_cfg=cfg, graph_cfg=graph_cfg)
    finally:
        navigator_module.Navigator.update = original  # type: ignore[method-assign]
    result = seen["nav"].fleet_heading.result
    assert result is not None
    return dict(result.bias_rad)


def test_worker_navigated_graphs_get_the_fleet_heading_of_one_process() -> None:
    pytest.importorskip("gtsam")
    import zenoh

    from services.map_worker import MapWorker
    from services.testnet import TestNetwork
    from services.wire import CloudMsg

    frames = _depth_only()
    truth = _launch_biases(frames)
    robots = sorted(truth)
    with TestNetwork("fh") as net:
        base = net.start_base(map_mode="on", navigation=True, remote_workers=True, workers=2, no_fix="graph")
        workers = [MapWorker(net.session(), net.keys, f"w{i}") for i in range(2)]
        for w in workers:
            w.start()
        try:
            pool = base.feed.pool
            assert pool is not None
            assert pool.wait_for_workers(2, 20)
            s = net.session()
            pubs = {r: s.declare_publisher(net.keys.cloud(r), congestion_control=zenoh.CongestionControl.BLOCK)
                    for r in robots}  # fmt: skip
            seqs: dict[str, int] = {}
            for f in frames:  # in capture order, the robots interleaved
                seq = seqs[f.robot] = seqs.get(f.robot, -1) + 1
                pts = f.points_body.astype(np.float32)
                ones = np.ones(len(pts), np.float32)
                pubs[f.robot].put(CloudMsg(f.robot, seq, f.t_ns, f.pose_est, pts, np.zeros(len(pts), np.uint8),
                                           ones).to_bytes())  # fmt: skip
            deadline = time.monotonic() + 60
            while base.processed < len(frames) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert base.drain(60)
            base.flush_map(60)
            graphs = {r: nav for w in workers for r, nav in w.nav._navs.items()}
            assert len({pool.assignment()[r] for r in robots}) == 2  # the fleet spans both workers
            status = base.status()
            frame = base.feed._frame
            fh = pool.status_json().get("fleet_heading", {})
        finally:
            for w in workers:
                w.close()
    ref = _in_process_biases(frames)
    for r in robots:
        bias = graphs[r].compass_bias
        assert bias is not None, r  # without the base's estimate the worker's graph keeps its compass
        assert abs(bias[0] - truth[r]) < math.radians(0.4), (r, math.degrees(bias[0]), math.degrees(truth[r]))
        assert abs(bias[0] - ref[r]) < math.radians(0.05), (r, math.degrees(bias[0]), math.degrees(ref[r]))
        assert abs(graphs[r].x[4] + truth[r]) < math.radians(0.5)  # its heading now: the compass minus the bias
        nav = status["robots"][r]["nav"]
        assert nav["heading"] == "launch-walls"
        assert nav["hold"]["held"] == 0
        assert nav["hold"]["committed"] >= 8  # the first second's clouds waited for the biases, then went in
        assert nav["placed"] + nav["unplaced"] == len(frames) // len(robots)
        assert nav["unplaced"] <= 3
    assert fh["robots"] == robots
    assert fh["walls"] >= 2
    assert frame.yaw_rad == 0.0  # the map's heading is the estimate's: the launch points no longer turn it


class _Nav:
    def __init__(self, **cfg: Any) -> None:
        from mapping.navigation import NavConfig

        self.cfg = NavConfig(graph_without_fix=True, **cfg)
        self.fleet_heading: Any = None

    def _tracker(self) -> Any:
        from mapping.graph_fleet import FleetHeadingTracker

        if self.fleet_heading is None:
            self.fleet_heading = FleetHeadingTracker(self.cfg)
        return self.fleet_heading


def _pose(fixed: bool) -> Pose:
    return Pose(1.0 if fixed else NAN, 2.0 if fixed else NAN, 1.0, 0.0, 0.0, 0.1)


def test_the_base_holds_graph_robots_clouds_once_two_collect_and_is_due_when_all_passed_their_span() -> None:
    relay = HeadingRelay(_Nav())
    ms = 1_000_000
    # a robot with fixes all along (a mixed fleet) is never kept
    assert [relay.phase("fix", t * 100 * ms, _pose(True)) for t in range(40)] == [""] * 40
    assert relay.phase("a", 0, _pose(True)) == ""  # the launch fixes
    assert relay.phase("a", 100 * ms, _pose(True)) == ""
    assert relay.phase("a", 200 * ms, _pose(False)) == "collect"  # its graph starts: alone, nothing to wait for
    assert relay.phase("b", 150 * ms, _pose(True)) == ""
    assert relay.phase("b", 250 * ms, _pose(False)) == "hold"  # two graph robots: their clouds wait
    assert relay.phase("a", 300 * ms, _pose(False)) == "hold"
    assert relay.t0 == {"a": 100 * ms, "b": 150 * ms}  # from their last fix
    assert relay.robots() == ["a", "b"]  # in the order their graphs started
    assert relay.phase("a", 1102 * ms, _pose(False)) == "hold"  # past its span (from its launch, 100 ms)
    assert not relay.due()
    assert relay.phase("b", 1152 * ms, _pose(False)) == "hold"  # the last one past: due at this cloud
    assert relay.due()
    assert relay.due_ns == 1152 * ms
    sent: list[tuple[str, str]] = []
    relay.take_views("a", [])
    relay.take_views("b", [])
    relay.settle(lambda robot, kind, state=b"": sent.append((robot, kind)))
    assert sent == [("a", "views"), ("b", "views"), ("a", "heading"), ("b", "heading")]
    assert relay.result is not None
    assert relay.phase("a", 1200 * ms, _pose(False)) == ""  # estimated: nothing kept or held any more
    assert HeadingRelay(_Nav(fleet_heading=False)).phase("a", 0, _pose(False)) == ""


def test_a_robot_whose_views_do_not_come_keeps_its_compass_and_is_released() -> None:
    relay = HeadingRelay(_Nav())
    for robot in ("a", "b"):
        relay.phase(robot, 0, _pose(True))
        relay.phase(robot, 100_000_000, _pose(False))
    for robot in ("a", "b"):
        relay.phase(robot, 1_200_000_000, _pose(False))
    assert relay.due()
    relay.take_views("a", [])
    states: dict[str, bytes] = {}
    relay.settle(lambda robot, kind, state=b"": states.update({robot: state}) if kind == "heading" else None, 0.05)
    from services.map_worker_nav import decode_state

    got = decode_state(states["b"])
    assert got["bias_rad"] == 0.0
    assert got["sd_rad"] == pytest.approx(math.radians(3.0))  # its prior: the worker leaves its graph as it is
    assert got["t_ns"] == 1_200_000_000


def test_the_fleet_heading_messages_survive_the_wire() -> None:
    from mapping.fleet_heading import View
    from services.map_worker_nav import decode_state, encode_state

    pts = np.zeros((3, 3), np.float32)
    job = MapJob("a", 1, 2, 3, _pose(False), pts, navigate=True, lag_ns=4, no_fix="graph", heading="hold")
    back = decode_work(job.to_bytes())
    assert isinstance(back, MapJob)
    assert back.heading == "hold"
    assert decode_work(MapJob("a", 1, 2, 3, _pose(True), pts).to_bytes()).heading == ""  # type: ignore[union-attr]
    views = [View("a", (1.0, 2.0), np.arange(6, dtype=np.float64).reshape(3, 2), (0.1, 0.2), 0.003)]
    msg = decode_obs(HeadingViews("w0", "a", 5, encode_state(views)).to_bytes())
    assert isinstance(msg, HeadingViews)
    assert (msg.worker, msg.robot, msg.epoch) == ("w0", "a", 5)
    (v,) = decode_state(msg.views)
    assert (v.robot, v.fix_ne, v.offset_ne, v.offset_sigma_m) == ("a", (1.0, 2.0), (0.1, 0.2), 0.003)
    assert np.array_equal(v.points_ne, views[0].points_ne)
    for kind in ("views", "heading"):
        ctl = decode_work(MapControl(kind, "a", 2, encode_state({"bias_rad": 0.01})).to_bytes())
        assert isinstance(ctl, MapControl)
        assert (ctl.kind, ctl.robot, ctl.epoch) == (kind, "a", 2)


def test_a_workers_held_clouds_are_settled_against_the_newest_snapshot(monkeypatch: pytest.MonkeyPatch) -> None:
    """With the snapshot rule the mirror of the moment never comes: the end of a dive checks the held clouds
    against the newest snapshot of the merged map (as the map thread checks them against its planes), not
    against no plane at all."""
    from mapping.landmarks import SnapshotRange
    from mapping.navigation import PlaneLandmarks
    from services.keys import FleetKeys
    from services.map_worker import MapWorker

    worker = MapWorker(None, FleetKeys("t"), "w1")
    worker._epoch["rov1"] = 0
    old, new = PlaneLandmarks.empty(), PlaneLandmarks.empty()
    worker.take_snapshots("base", [SnapshotRange(0, 100, old), SnapshotRange(200, 300, new)])
    seen: list[Any] = []
    monkeypatch.setattr(worker.nav, "settle", lambda robot, lm: seen.append(lm) or [])
    worker.handle(MapControl("flush", "rov1", 0))
    assert len(seen) == 1
    assert seen[0] is new


def test_graph_robots_whose_clouds_share_a_capture_time_are_ordered_by_name() -> None:
    """The base may take two clouds of one capture time in either order: the views' order (the estimate's RANSAC
    seeds) must not follow it."""
    orders = []
    for first, second in (("a", "b"), ("b", "a")):
        relay = HeadingRelay(_Nav())
        for robot in (first, second):
            relay.phase(robot, 0, _pose(True))
        for robot in (first, second):
            relay.phase(robot, 100_000_000, _pose(False))
        orders.append(relay.robots())
    assert orders == [["a", "b"], ["a", "b"]]
