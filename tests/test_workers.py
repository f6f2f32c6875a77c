"""Plane workers: the assignment rule, the worker's epochs, and a base station mapping through worker processes
(every cloud mapped once, also when a worker is SIGKILLed mid-dive or another joins over TCP)."""

from __future__ import annotations

import signal
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from procs import Proc, lrsensor_cmd

from mapping import MapBuilder, MapConfig
from mapping.synth import DiveFrame, simulate_dive, tank, two_rov_plans
from services.keys import FleetKeys
from services.map_worker import MapWorker
from services.map_worker_wire import FLUSH_KEY, MapControl, MapJob, PlaneObservations, decode_work
from services.map_workers import owner
from services.testnet import TestNetwork
from services.wire import CloudMsg

ROBOTS = [f"r{k}" for k in range(6)]


# ---------------------------------------------------------------------- the rule
def test_rendezvous_assignment_is_stable_balanced_and_moves_only_what_it_must() -> None:
    robots = [f"rov{k:03d}" for k in range(400)]
    workers = ["w-a", "w-b", "w-c", "w-d"]
    before = {r: owner(r, workers) for r in robots}
    assert before == {r: owner(r, list(reversed(workers))) for r in robots}  # any order, same answer
    counts = Counter(before.values())
    assert all(60 <= n <= 140 for n in counts.values()), counts  # about 100 each
    joined = {r: owner(r, [*workers, "w-e"]) for r in robots}
    moved = [r for r in robots if joined[r] != before[r]]
    assert moved
    assert all(joined[r] == "w-e" for r in moved)  # a join takes robots only to the newcomer
    assert 40 <= len(moved) <= 120  # about a fifth
    left = {r: owner(r, ["w-a", "w-c", "w-d"]) for r in robots}
    assert all(left[r] == before[r] for r in robots if before[r] != "w-b")  # a leave moves only its robots
    assert owner("rov1", []) is None


# ---------------------------------------------------------------------- the worker without a network
def _job(robot: str, seq: int, epoch: int, frame: DiveFrame) -> MapJob:
    return MapJob(robot, seq, frame.t_ns, epoch, frame.pose_est, frame.points_body.astype(np.float32))


def _frames(seconds: float, rate_hz: float = 30.0) -> list[DiveFrame]:
    return simulate_dive(tank(), two_rov_plans(), duration_s=seconds, rate_hz=rate_hz, n_rays=500, seed=3)


def test_worker_commits_each_cloud_once_and_forgets_a_robot_that_moved() -> None:
    worker = MapWorker(None, FleetKeys("t"), "w1")
    frames = [f for f in _frames(1.0) if f.robot == "rov1"]
    out: list[PlaneObservations] = []
    for seq, f in enumerate(frames[:15]):
        out += worker.handle(_job("rov1", seq, 0, f))
    assert [o.seqs for o in out] == [tuple(range(10))]  # one extraction of 10 clouds
    assert worker.handle(_job("rov1", 99, -1, frames[15])) == []  # an older epoch: stale
    assert worker.stale == 1
    # moved here again at epoch 2: the base re-sends 10..14; the old window is forgotten, nothing counted twice
    again: list[PlaneObservations] = []
    for seq in range(10, 15):
        again += worker.handle(_job("rov1", seq, 2, frames[seq]))
    again += worker.handle(MapControl("flush"))
    assert [o.seqs for o in again] == [(10, 11, 12, 13, 14)]
    assert again[0].epoch == 2
    worker.handle(MapControl("drop", "rov1", 3))
    assert worker.handle(MapControl("flush")) == []


def test_a_silent_robots_last_window_is_extracted_when_the_base_asks() -> None:
    """The end of a dive: a robot's last clouds wait in its window for a trigger no later cloud brings; the base
    asks its worker to extract that robot's window alone (the others' stay), once it has been silent."""
    worker = MapWorker(None, FleetKeys("t"), "w1")
    frames = [f for f in _frames(1.0) if f.robot == "rov1"]
    out: list[PlaneObservations] = []
    for seq, f in enumerate(frames[:4]):
        out += worker.handle(_job("rov1", seq, 0, f))
        out += worker.handle(_job("rov2", seq, 0, f))
    assert out == []  # 4 clouds each: no trigger yet
    assert worker.handle(MapControl("flush", "rov1", 1)) == []  # not the epoch it is served under here
    got = worker.handle(MapControl("flush", "rov1", 0))
    assert [(o.robot, o.seqs, o.key_ns) for o in got] == [("rov1", (0, 1, 2, 3), FLUSH_KEY)]
    assert worker.handle(MapControl("flush", "rov1", 0)) == []  # nothing left of rov1's
    assert [(o.robot, o.seqs) for o in worker.handle(MapControl("flush"))] == [("rov2", (0, 1, 2, 3))]


def test_the_pool_asks_only_for_robots_silent_long_enough() -> None:
    from lrsensor.frames import Pose
    from services.map_workers import IDLE_FLUSH_S, WorkerPool, _InFlight

    pool = WorkerPool(None, FleetKeys("t"), MapBuilder(MapConfig()), lambda *a: None, lambda c: None)
    sent: list[tuple[str, bytes]] = []
    pool._put = lambda w, payload: sent.append((w, payload))  # type: ignore[method-assign]
    pose = Pose(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    now = time.monotonic()
    for robot, quiet_s in (("old", IDLE_FLUSH_S + 1.0), ("busy", 0.1)):
        pool._in_flight[robot] = {0: _InFlight(0, 1000, pose, np.zeros((3, 3), np.float32))}
        pool._owner[robot] = "w1"
        pool._epoch[robot] = 2
        pool._active[robot] = now - quiet_s
    pool._flush_silent()
    assert [(w, decode_work(p)) for w, p in sent] == [("w1", MapControl("flush", "old", 2))]
    pool._flush_silent()  # asked a moment ago: not again yet
    assert len(sent) == 1
    assert pool.silent_flushes == 1


def test_the_pool_asks_for_a_silent_robot_whose_clouds_wait_in_its_hold() -> None:
    """A depth-only robot's held clouds (mapping.graph_hold) are acknowledged, so none is in flight; once it is
    silent its owner must still be asked to settle them, once per report that it holds some."""
    from services.map_workers import IDLE_FLUSH_S, WorkerPool

    pool = WorkerPool(None, FleetKeys("t"), MapBuilder(MapConfig()), lambda *a: None, lambda c: None)
    sent: list[tuple[str, bytes]] = []
    pool._put = lambda w, payload: sent.append((w, payload))  # type: ignore[method-assign]
    now = time.monotonic()
    for robot in ("held", "done"):
        pool._owner[robot] = "w1"
        pool._epoch[robot] = 1
        pool._active[robot] = now - IDLE_FLUSH_S - 1.0
    pool.holding("held", True)
    pool.holding("done", True)
    pool.holding("done", False)  # its newer state holds nothing
    pool._flush_silent()
    assert [(w, decode_work(p)) for w, p in sent] == [("w1", MapControl("flush", "held", 1))]
    pool._silent_asked.clear()
    pool._flush_silent()  # asked once: not again until a newer state says it still holds clouds
    assert len(sent) == 1


def test_a_silent_flush_settles_a_robots_held_clouds(monkeypatch: pytest.MonkeyPatch) -> None:
    """The worker asked to flush a silent robot checks its held clouds too; those that go in are observed."""
    worker = MapWorker(None, FleetKeys("t"), "w1")
    frames = [f for f in _frames(1.0) if f.robot == "rov1"]
    worker._epoch["rov1"] = 0
    settled: list[str] = []

    def settle(robot: str, landmarks: object) -> list[tuple[int, object, object]]:
        settled.append(robot)
        return [(f.t_ns, f.pose_est, f.points_body.astype(np.float32)) for f in frames[:12]]

    monkeypatch.setattr(worker.nav, "settle", settle)
    got = worker.handle(MapControl("flush", "rov1", 0))
    assert settled == ["rov1"]
    assert len(got) == 1
    assert got[0].robot == "rov1"
    assert got[0].seqs == ()  # acknowledged when they came
    assert got[0].records  # the released clouds' planes


def test_observations_survive_the_wire_and_merge_like_the_builders_own() -> None:
    from mapping.plane_map import record_from_wire

    frames = [f for f in _frames(2.0) if f.robot == "rov1"]
    worker = MapWorker(None, FleetKeys("t"), "w1")
    merger = MapBuilder(MapConfig())
    single = MapBuilder(MapConfig())
    for seq, f in enumerate(frames):
        for obs in worker.handle(_job("rov1", seq, 0, f)):
            back = PlaneObservations.from_bytes(obs.to_bytes())
            merger.merge([record_from_wire(r) for r in back.records])
        single.add_cloud_body("rov1", f.t_ns, f.points_body.astype(np.float32).astype(np.float64), f.pose_est)
    assert merger.planes_records() == single.planes_records()  # one robot: the very same map, bit for bit


# ---------------------------------------------------------------------- through Zenoh
def _publish(net: TestNetwork, frames: list[DiveFrame], robots: list[str], start: int, stop: int) -> int:
    """Publish frames ``start:stop`` of each robot (robot k replays base robot k % 2) and wait until the base
    accepted them (a flush must not overtake the last ones); returns clouds sent."""
    import zenoh

    s = net.session()
    by = {"rov1": [f for f in frames if f.robot == "rov1"], "rov2": [f for f in frames if f.robot == "rov2"]}
    pubs = {r: s.declare_publisher(net.keys.cloud(r), congestion_control=zenoh.CongestionControl.BLOCK) for r in robots}
    n = 0
    for i in range(start, stop):
        for k, r in enumerate(robots):
            f = by["rov1" if k % 2 == 0 else "rov2"][i]
            pts = f.points_body.astype(np.float32)
            msg = CloudMsg(r, i, f.t_ns, f.pose_est, pts, np.zeros(len(pts), np.uint8), np.ones(len(pts), np.float32))
            pubs[r].put(msg.to_bytes())
            n += 1
    for p in pubs.values():
        p.undeclare()
    base = net.base
    assert base is not None
    _wait(lambda: base.processed >= len(robots) * stop, 60, "the base to accept every cloud")
    return n


def _wait(cond: Any, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out waiting for {what}")
        time.sleep(0.05)


def _worker_proc(net: TestNetwork, tmp_path: Path, name: str) -> Proc:
    args = ["map-worker", "--fleet", net.keys.fleet, "--name", name, "--mode", "client", "--connect", net.endpoint]
    return Proc(lrsensor_cmd(*args), tmp_path / f"{name}.log")


def _mapped_once(net: TestNetwork, robots: list[str], per_robot: int) -> None:
    base = net.base
    assert base is not None
    st = base.status()
    got = {r: st["robots"][r]["mapped"] for r in robots}
    assert got == dict.fromkeys(robots, per_robot), st["map"]
    for r in robots:  # acknowledgeable exactly when committed: every one of them
        assert base.ledger.records[r].mapped.ranges() == [[0, per_robot - 1]]
    assert st["map"]["worker_pool"]["in_flight"] == 0


@pytest.fixture
def frames() -> list[DiveFrame]:
    return _frames(3.0)


@pytest.fixture
def net() -> Iterator[TestNetwork]:
    with TestNetwork("wk") as n:
        yield n


def test_in_process_workers_map_every_cloud_once_like_one_process(net: TestNetwork, frames: list[DiveFrame]) -> None:
    # the ingest threads keep each robot's order (a queue per thread, by robot): a seeded replay
    base = net.start_base(map_mode="on", navigation=False, remote_workers=True, workers=2)
    workers = [MapWorker(net.session(), net.keys, f"w{i}") for i in range(2)]
    for w in workers:
        w.start()
    try:
        assert base.feed.pool is not None
        assert base.feed.pool.wait_for_workers(2, 20)
        per = 90
        _publish(net, frames, ROBOTS, 0, per)
        assert base.drain(60)
        base.flush_map(60)
        _mapped_once(net, ROBOTS, per)
        assert set(base.feed.pool.assignment().values()) == {"w0", "w1"}
        assert base.status()["map"]["workers"] == 2
        assert base.status()["map"]["latency_ms"]["p99"] is not None
        planes = base.map_json()["planes"]
        assert base.map is not None
        records = base.map.planes_records()
    finally:
        for w in workers:
            w.close()
    single = MapBuilder(MapConfig())
    by = {"rov1": [f for f in frames if f.robot == "rov1"], "rov2": [f for f in frames if f.robot == "rov2"]}
    for i in range(per):
        for k, r in enumerate(ROBOTS):
            f = by["rov1" if k % 2 == 0 else "rov2"][i]
            single.add_cloud_body(r, f.t_ns, f.points_body.astype(np.float32).astype(np.float64), f.pose_est)
    single.flush()
    ref = single.map_json()["planes"]
    # The merge is order-sensitive; the merger merges in the canonical order (trigger capture time, robot), the
    # order one thread fed in capture order merges in: the very same map, whatever worker answered first.
    assert planes == ref
    assert records == single.planes_records()  # bit for bit, the exact integer statistics too


@pytest.mark.parametrize("navigation", [False, True])
def test_a_sigkilled_worker_moves_its_robots_and_every_cloud_is_mapped_once(
    net: TestNetwork, frames: list[DiveFrame], tmp_path: Path, procs: list[Proc], navigation: bool
) -> None:
    base = net.start_base(map_mode="on", navigation=navigation, remote_workers=True)
    pool = base.feed.pool
    assert pool is not None
    procs += [_worker_proc(net, tmp_path, "wa"), _worker_proc(net, tmp_path, "wb")]
    assert pool.wait_for_workers(2, 60), procs[0].output()
    _publish(net, frames, ROBOTS, 0, 45)
    assert base.drain(60)
    victims = [r for r, w in pool.assignment().items() if w == "wa"]
    assert victims, pool.assignment()
    procs[0].p.send_signal(signal.SIGKILL)  # mid-dive: its windows hold uncommitted clouds
    _wait(lambda: pool.workers == ["wb"], 20, "the dead worker's token to vanish")
    assert all(w == "wb" for w in pool.assignment().values())
    _publish(net, frames, ROBOTS, 45, 90)
    assert base.drain(60)
    base.flush_map(60)
    if navigation:  # every cloud done with once: placed (mapped) or not, each acknowledged
        st = base.status()
        assert all(st["robots"][r]["nav"]["placed"] + st["robots"][r]["nav"]["unplaced"] == 90 for r in ROBOTS)
        assert all(st["robots"][r]["mapped"] == st["robots"][r]["nav"]["placed"] for r in ROBOTS)
        assert all(base.ledger.records[r].mapped.ranges() == [[0, 89]] for r in ROBOTS)
        assert sum(st["robots"][r]["nav"]["placed"] for r in ROBOTS) >= 0.9 * 90 * len(ROBOTS)
    else:
        _mapped_once(net, ROBOTS, 90)
    assert pool.moves >= len(victims)
    assert pool.resent > 0


def test_a_worker_joining_a_running_base_over_tcp_takes_robots(
    net: TestNetwork, frames: list[DiveFrame], tmp_path: Path, procs: list[Proc]
) -> None:
    base = net.start_base(map_mode="on", navigation=False, remote_workers=True)
    pool = base.feed.pool
    assert pool is not None
    procs.append(_worker_proc(net, tmp_path, "wa"))
    assert pool.wait_for_workers(1, 60)
    _publish(net, frames, ROBOTS, 0, 30)
    procs.append(_worker_proc(net, tmp_path, "wb"))  # another process, over TCP, while the dive runs
    assert pool.wait_for_workers(2, 60), procs[1].output()
    _publish(net, frames, ROBOTS, 30, 90)
    assert base.drain(60)
    base.flush_map(60)
    st = pool.status_json()
    assert st["workers"]["wb"]["robots"]
    assert st["workers"]["wb"]["committed"] > 0
    _mapped_once(net, ROBOTS, 90)


def test_base_cli_starts_and_stops_its_local_worker_processes(tmp_path: Path, procs: list[Proc]) -> None:
    import json

    from services.testnet import free_port
    from services.zconfig import NetworkOptions, open_session

    ep = f"tcp/127.0.0.1:{free_port()}"
    args = ["base", "--fleet", "cli", "--listen", ep, "--map", "on", "--map-workers", "1", "--status-every-s", "0"]
    base = Proc(lrsensor_cmd(*args), tmp_path / "base.log")
    procs.append(base)
    keys = FleetKeys("cli")
    _wait(lambda: "running" in base.output(), 60, "the base station to listen")
    with open_session(NetworkOptions(mode="client", connect=(ep,)), "client") as s:

        def workers() -> int:
            for reply in s.get(keys.base_status, timeout=2.0):
                if reply.ok is not None:
                    return int(json.loads(reply.ok.payload.to_string())["map"]["workers"])
            return -1

        _wait(lambda: workers() == 1, 60, "the base's own worker process")
    assert base.stop(timeout_s=30) == 0, base.output()
    assert "map worker stopped" in base.output()  # the worker left with the base, no orphan


# ---------------------------------------------------------------------- navigation in the workers
def _nav_job(robot: str, seq: int, epoch: int, frame: DiveFrame) -> MapJob:
    pts = frame.points_body.astype(np.float32)
    return MapJob(robot, seq, frame.t_ns, epoch, frame.pose_est, pts, navigate=True)


def _tank_landmarks(frames: list[DiveFrame]) -> Any:
    b = MapBuilder(MapConfig())
    for f in frames:
        b.add_cloud_body(f.robot, f.t_ns, f.points_body.astype(np.float64), f.pose_est)
    b.flush()
    return b.landmarks(300)


def test_landmarks_and_navigation_state_survive_the_wire() -> None:
    from mapping.navigation import NavConfig, RobotNav
    from services.map_worker_nav import decode_landmarks, decode_state, encode_landmarks, encode_state

    frames = _frames(2.0)
    lm = _tank_landmarks(frames)
    assert len(lm) >= 4
    version, back = decode_landmarks(encode_landmarks(lm, 7))
    assert version == 7
    assert back.contrib == lm.contrib
    for name in ("ids", "normal", "d", "centroid", "u", "v", "u_range", "v_range"):
        assert np.array_equal(getattr(back, name), getattr(lm, name))
    nav = RobotNav("rov1", NavConfig())
    own = [f for f in frames if f.robot == "rov1"]
    for f in own[:20]:
        nav.update(f.t_ns, f.pose_est, f.points_body, lm)
    twin = RobotNav("rov1", nav.cfg)
    twin.restore(decode_state(encode_state(nav.snapshot())))
    for f in own[20:30]:  # the restored estimator continues exactly
        a = nav.update(f.t_ns, f.pose_est, f.points_body, lm)
        b = twin.update(f.t_ns, f.pose_est, f.points_body, lm)
        assert a == b


def test_the_stride_registers_every_sixth_scan_and_applies_the_latest_correction_between() -> None:
    from services.map_worker_nav import WorkerNav, corrected

    frames = [f for f in _frames(2.0) if f.robot == "rov1"]
    lm = _tank_landmarks(frames)
    wn = WorkerNav()
    steps = [wn.step("rov1", f.t_ns, f.pose_est, f.points_body, lm) for f in frames[:30]]
    registered = [i for i, s in enumerate(steps) if s.estimate is not None]
    assert registered == list(range(0, 30, 6))  # 30 Hz: every sixth scan, 5 Hz of registration
    assert (wn.registered, wn.strided) == (5, 25)
    latest = steps[24].estimate
    assert steps[28].pose == corrected(latest, frames[28].pose_est)
    assert steps[28].pose is not None
    assert abs(steps[28].pose.north_m - frames[28].pose_est.north_m - latest.correction["north_m"]) < 1e-12
    every = WorkerNav(register_every_s=0.0)
    assert all(every.step("rov1", f.t_ns, f.pose_est, f.points_body, lm).estimate for f in frames[:5])


def test_a_robot_moved_to_another_worker_continues_its_navigation_exactly() -> None:
    frames = [f for f in _frames(2.0) if f.robot == "rov1"]
    lm = _tank_landmarks(frames)
    ref, a, b = (MapWorker(None, FleetKeys("t"), n) for n in ("ref", "wa", "wb"))
    for w in (ref, a, b):
        w.landmarks = lm
    out_a: list[PlaneObservations] = []
    for seq, f in enumerate(frames[:25]):
        ref.handle(_nav_job("rov1", seq, 0, f))
        out_a += a.handle(_nav_job("rov1", seq, 0, f))
    committed = out_a[-1].seqs[-1]
    assert committed == 19  # two extractions of 10; 20..24 in flight when wa dies
    b.handle(MapControl("adopt", "rov1", 1, out_a[-1].nav_state))
    for seq in range(committed + 1, 40):  # the base re-sends the clouds in flight, then the new ones
        b.handle(_nav_job("rov1", seq, 1, frames[seq]))
    for seq in range(25, 40):
        ref.handle(_nav_job("rov1", seq, 0, frames[seq]))
    sa, sb = ref.nav.snapshot("rov1"), b.nav.snapshot("rov1")
    assert sa is not None
    assert sb is not None
    assert np.array_equal(sa["nav"]["x"], sb["nav"]["x"])
    assert np.array_equal(sa["nav"]["P"], sb["nav"]["P"])
    assert sa["nav"]["latest"] == sb["nav"]["latest"]
    fresh = MapWorker(None, FleetKeys("t"), "wc")  # without the state: an honest restart from the next fix
    fresh.landmarks = lm
    fresh.handle(MapControl("adopt", "rov1", 1, b""))
    fresh.handle(_nav_job("rov1", 20, 1, frames[20]))
    st = fresh.nav.snapshot("rov1")
    assert st is not None
    assert st["nav"]["latest"].motion == "start"


@contextmanager
def _navigating_workers(net: TestNetwork, frames: list[DiveFrame], per: int) -> Iterator[tuple[Any, list[MapWorker]]]:
    """A base with navigation and two in-process plane workers, after ``per`` frames of each robot are mapped."""
    base = net.start_base(map_mode="on", navigation=True, remote_workers=True, workers=2)
    workers = [MapWorker(net.session(), net.keys, f"w{i}") for i in range(2)]
    for w in workers:
        w.start()
    try:
        pool = base.feed.pool
        assert pool is not None
        assert pool.navigate
        assert pool.snapshot_lag_ns > 0
        assert pool.wait_for_workers(2, 20)
        _publish(net, frames, ROBOTS, 0, per)
        assert base.drain(60)
        base.flush_map(60)
        yield base, workers
    finally:
        for w in workers:
            w.close()


def test_in_process_workers_navigate_their_robots(net: TestNetwork, frames: list[DiveFrame]) -> None:
    per = 90
    with _navigating_workers(net, frames, per) as (base, workers):
        st = base.status()
        placed = {r: st["robots"][r]["nav"]["placed"] for r in ROBOTS}
        unplaced = {r: st["robots"][r]["nav"]["unplaced"] for r in ROBOTS}
        assert all(placed[r] + unplaced[r] == per for r in ROBOTS), (placed, unplaced)
        assert {r: st["robots"][r]["mapped"] for r in ROBOTS} == placed
        assert sum(placed.values()) >= 0.9 * per * len(ROBOTS)
        for r in ROBOTS:  # acknowledgeable once committed, placed or not
            assert base.ledger.records[r].mapped.ranges() == [[0, per - 1]]
        assert base.feed.nav_robots() == sorted(ROBOTS)  # the workers' estimates are served by the base
        assert all(len(w.snapshots) > 0 for w in workers)  # the merger's snapshots arrived
        assert sum(w.nav.registered for w in workers) >= per * len(ROBOTS) // 6
        assert sum(w.nav.strided for w in workers) > 0
        navigator = base.feed.navigator
        assert navigator is not None
        assert set(navigator.robots) == set(ROBOTS)  # their states, for the fleet's frame


def test_the_merge_waits_only_for_observations_that_can_still_precede() -> None:
    from lrsensor.frames import Pose
    from services.map_workers import WorkerPool, _InFlight

    pool = WorkerPool(None, FleetKeys("t"), MapBuilder(MapConfig()), lambda *a: None, lambda c: None)
    cfg = pool.builder.cfg
    pose = Pose(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    def table(n: int, points: int, dt_ns: int = 33_000_000) -> dict[int, _InFlight]:
        return {s: _InFlight(s, 1000 + s * dt_ns, pose, np.zeros((points, 3), np.float32)) for s in range(n)}

    # by count: the window's 10th cloud triggers, so nothing with planes can come before its time
    assert pool._next_key_bound(table(15, 100)) == 1000 + (cfg.extract_every_clouds - 1) * 33_000_000
    assert pool._next_key_bound(table(3, 100)) == 1000 + 2 * 33_000_000  # the trigger is still to come
    assert pool._next_key_bound(table(5, cfg.extract_every_points)) == 1000  # one cloud full of points
    by_time = table(5, 100, dt_ns=600_000_000)  # 2 clouds 1 s apart or more fire by time
    assert pool._next_key_bound(by_time) == 1000 + 2 * 600_000_000


def test_without_a_fix_the_scans_between_registrations_move_on_at_the_registered_velocity() -> None:
    from dataclasses import replace

    from lrsensor.frames import Pose
    from mapping.navigation import NavEstimate
    from services.map_worker_nav import corrected

    def est(t_s: float, north: float) -> NavEstimate:
        pose = Pose(north, 2.0, 1.0, 0.0, 0.0, 0.1)
        return NavEstimate("r", int(t_s * 1e9), pose, {}, {}, True, "motion-prior", correction={"yaw_deg": 1.0})

    raw = Pose(float("nan"), float("nan"), 1.5, 0.0, 0.0, 0.2)
    before, latest = est(0.0, 1.0), est(0.1, 1.03)  # 0.3 m/s north
    p = corrected(latest, raw, before, int(0.15e9))
    assert p is not None
    assert abs(p.north_m - 1.045) < 1e-9
    assert p.east_m == 2.0
    assert p.down_m == 1.5
    assert abs(p.yaw_rad - (0.2 + np.radians(1.0))) < 1e-12
    stale = corrected(latest, raw, replace(before, t_ns=int(-1e9)), int(0.15e9))  # too far apart: stays
    assert stale is not None
    assert stale.north_m == 1.03


def test_clouds_navigation_cannot_place_are_committed_without_planes_and_said_unplaced() -> None:
    from dataclasses import replace

    frames = [f for f in _frames(1.0) if f.robot == "rov1"]
    worker = MapWorker(None, FleetKeys("t"), "w1")
    out: list[PlaneObservations] = []
    for seq, f in enumerate(frames[:5]):  # no horizontal fix ever: no position, nothing placed
        raw = replace(f.pose_est, north_m=float("nan"), east_m=float("nan"))
        job = MapJob("rov1", seq, f.t_ns, 0, raw, f.points_body.astype(np.float32), navigate=True)
        out += worker.handle(job)
    assert [(o.seqs, o.unplaced, o.records) for o in out] == [((s,), (s,), ()) for s in range(5)]  # each at once
    assert all(o.nav_state for o in out)  # the state travels even before the robot has a position


def test_a_robot_that_stops_being_placed_still_commits_its_placed_clouds() -> None:
    """A depth-only robot: its launch cloud is placed, then navigation loses it. The placed clouds wait in the
    window for a trigger no placed cloud brings; the unplaced ones bring it by time (``extract_every_s``), so
    every cloud is committed (and acknowledged) without a flush, and one process merges the same."""
    from dataclasses import replace

    frames = [f for f in _frames(2.0, rate_hz=5.0) if f.robot == "rov1"]
    worker = MapWorker(None, FleetKeys("t"), "w1")
    single = MapBuilder(MapConfig())
    out: list[PlaneObservations] = []
    for seq, f in enumerate(frames):
        raw = f.pose_est if seq == 0 else replace(f.pose_est, north_m=float("nan"), east_m=float("nan"))
        out += worker.handle(MapJob("rov1", seq, f.t_ns, 0, raw, f.points_body.astype(np.float32), navigate=True))
    committed = sorted(s for o in out for s in o.seqs)
    unplaced = {s for o in out for s in o.unplaced}
    assert committed == list(range(len(frames))), (committed, unplaced)
    assert 0 not in unplaced  # the launch cloud, placed by its fix
    # one process does the same: the unplaced clouds' times extract the pending window
    for s, f in enumerate(frames):
        if s in unplaced:
            single.advance_time("rov1", f.t_ns)
        else:
            single.add_cloud_body("rov1", f.t_ns, f.points_body.astype(np.float32).astype(np.float64), f.pose_est)
    assert single.uncommitted("rov1") == 0


def test_advance_time_extracts_a_window_only_once_its_clouds_span_the_time_rule() -> None:
    frames = [f for f in _frames(1.5, rate_hz=5.0) if f.robot == "rov1"]
    b = MapBuilder(MapConfig())
    first = frames[0]
    b.add_cloud_body("rov1", first.t_ns, first.points_body.astype(np.float64), first.pose_est)
    assert b.uncommitted("rov1") == 1
    assert b.advance_time("rov1", first.t_ns + 900_000_000) == []  # not yet due
    assert b.uncommitted("rov1") == 1
    b.advance_time("rov1", first.t_ns + 1_000_000_000)
    assert b.uncommitted("rov1") == 0
    assert b.advance_time("rov2", first.t_ns) == []  # a robot without a window: nothing


# ---------------------------------------------------------------------- the same map with navigation
def _one_process_nav(frames: list[DiveFrame], robots: list[str], per: int, lag_ns: int) -> MapBuilder:
    """One process by the workers' rule: each robot's ``WorkerNav`` (the stride, the filter), a registered scan
    against this builder's own ``snapshot(T)``, the clouds in capture order."""
    from mapping.navigation import NavConfig
    from services.map_worker_nav import WorkerNav

    single = MapBuilder(MapConfig())
    wn = WorkerNav()
    min_points = NavConfig().min_landmark_points
    by = {"rov1": [f for f in frames if f.robot == "rov1"], "rov2": [f for f in frames if f.robot == "rov2"]}
    for i in range(per):
        for k, r in enumerate(robots):
            f = by["rov1" if k % 2 == 0 else "rov2"][i]
            pts = f.points_body.astype(np.float32)
            step = wn.step(r, f.t_ns, f.pose_est, pts, single.snapshot_landmarks(f.t_ns, lag_ns, min_points))
            if step.pose is None or not step.placed:
                single.advance_time(r, f.t_ns)  # as a worker does: the robot's pending clouds due by time
                continue
            single.add_cloud_body(r, f.t_ns, pts.astype(np.float64), step.pose)
    single.flush()
    return single


def _plane_diff(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> tuple[float, float]:
    """Largest angle (deg) and offset (m) between each plane of ``a`` and its nearest in ``b``."""
    worst_a, worst_d = 0.0, 0.0
    for p in a:
        q = min(b, key=lambda q: abs(q["d"] - p["d"]) + 1 - float(np.dot(q["normal"], p["normal"])))
        cos = min(1.0, float(np.dot(q["normal"], p["normal"])))
        worst_a, worst_d = max(worst_a, float(np.degrees(np.arccos(cos)))), max(worst_d, abs(q["d"] - p["d"]))
    return worst_a, worst_d


def test_workers_navigating_by_snapshots_give_one_process_map(net: TestNetwork, frames: list[DiveFrame]) -> None:
    # navigation is a loop (the planes correct the poses that make the planes): each registered scan uses
    # snapshot(T) of the merged map, T fixed by its capture time, in the workers as in one process
    per = 90
    with _navigating_workers(net, frames, per) as (base, workers):
        pool = base.feed.pool
        assert pool is not None
        assert base.map is not None
        planes = base.map.map_json()["planes"]  # the map frame (not turned by the fleet's frame)
        records = base.map.planes_records()
        snaps = base.status()["map"]["worker_pool"]["snapshots"]
        assert sum(w.nav.registered for w in workers) >= per * len(ROBOTS) // 6
    assert (snaps["not_exact"], snaps["late"], snaps["forced"]) == (0, 0, 0), snaps
    single = _one_process_nav(frames, ROBOTS, per, pool.snapshot_lag_ns)
    ref = single.map_json()["planes"]
    assert len(planes) == len(ref) >= 4
    deg, off_m = _plane_diff(ref, planes)
    assert deg <= 0.1
    assert off_m <= 1e-3
    assert records == single.planes_records()  # in fact bit for bit


def test_snapshots_survive_the_wire_and_a_store_finds_each_grid_time() -> None:
    from mapping.landmarks import SNAPSHOT_GRID_NS, LandmarkSnapshots, SnapshotRange, snapshot_time
    from services.errors import WireError
    from services.map_worker_nav import decode_mirror, encode_snapshots

    g = SNAPSHOT_GRID_NS
    assert snapshot_time(10 * g + 5, 0) == 10 * g
    assert snapshot_time(10 * g, 0) == 10 * g  # on the grid: that time itself
    assert snapshot_time(10 * g + 5, 5 * g) == 5 * g
    lm = _tank_landmarks(_frames(1.0))
    ranges = [SnapshotRange(0, 3 * g, lm), SnapshotRange(4 * g, 9 * g, lm, exact=False)]
    kind, base_id, back = decode_mirror(encode_snapshots("b1", ranges))
    assert (kind, base_id) == ("snapshots", "b1")
    assert [(r.lo_ns, r.hi_ns, r.exact) for r in back] == [(0, 3 * g, True), (4 * g, 9 * g, False)]
    assert np.array_equal(back[1].landmarks.normal, lm.normal)
    assert back[0].landmarks.contrib == lm.contrib
    with pytest.raises(WireError):
        decode_mirror(b"\x93garbage")
    store = LandmarkSnapshots(keep_ns=20 * g)
    for r in back:
        store.put(r)
    assert store.final_ns == 9 * g
    got = store.get(3 * g)
    assert got is not None
    assert got.lo_ns == 0
    assert store.get(10 * g) is None  # not final yet: a scan that needs it waits
    assert store.newest_before(10 * g) is back[1]
    store.put(SnapshotRange(40 * g, 41 * g, lm))  # the older ones fall out of the kept span
    assert store.get(3 * g) is None
    assert store.newest_before(3 * g) is not None  # the fallback takes the oldest kept


def test_a_scan_whose_snapshot_does_not_come_waits_its_cap_then_goes_on_not_exact() -> None:
    from mapping.landmarks import SnapshotRange

    frames = [f for f in _frames(1.0) if f.robot == "rov1"]
    lm = _tank_landmarks(frames)
    worker = MapWorker(None, FleetKeys("t"), "w1", snapshot_wait_s=0.2)
    lag = 500_000_000
    worker.take_snapshots("b1", [SnapshotRange(0, frames[0].t_ns - lag, lm)])  # only the first scan's
    out: list[PlaneObservations] = []
    for seq, f in enumerate(frames[:12]):
        job = MapJob("rov1", seq, f.t_ns, 0, f.pose_est, f.points_body.astype(np.float32), True, lag)
        out += worker.handle(job)
    assert worker.nav.registered == 1  # the scan 0.2 s on waits for its snapshot, the later ones behind it
    assert out == []
    assert worker.snap_waited == 1
    assert worker.snap_not_exact == 0
    time.sleep(0.25)
    out += worker.handle(MapControl("flush"))  # no deadlock: past the cap, the newest snapshot before it
    assert [o.seqs for o in out] == [tuple(range(10)), (10, 11)]
    assert worker.nav.registered == 2
    assert worker.snap_not_exact == 1
    assert worker.snap_wait_ms >= 200
    assert out[-1].snap_not_exact == 1  # reported to the base with each observation


def test_one_process_snapshot_is_the_map_before_the_first_merge_at_or_after_its_time() -> None:
    from mapping.landmarks import snapshot_time

    frames = _frames(2.0)
    b = MapBuilder(MapConfig())
    lag = 300_000_000
    before: list[tuple[int, Any]] = []  # (capture time, the planes before that cloud went in)
    older = 0
    for f in frames:
        got = b.snapshot_landmarks(f.t_ns, lag, 300)
        want_t = snapshot_time(f.t_ns, lag)
        first_at = [lm for t, lm in before if t >= want_t]
        expected = first_at[0] if first_at else b.landmarks(300)
        assert np.array_equal(got.ids, expected.ids)
        assert np.array_equal(got.d, expected.d)
        older += not np.array_equal(got.d, b.landmarks(300).d)  # not the planes of the moment
        before.append((f.t_ns, b.landmarks(300)))
        b.add_cloud_body(f.robot, f.t_ns, f.points_body.astype(np.float64), f.pose_est)
    assert len(b.landmarks(300)) >= 4
    assert older > len(frames) // 4
    with pytest.raises(Exception, match="min_points"):
        b.snapshot_landmarks(frames[-1].t_ns, lag, 100)


def test_a_silent_robot_does_not_hold_the_frontier_but_a_slow_workers_due_window_does() -> None:
    from lrsensor.frames import Pose
    from services.map_workers import MAX_HOLD_S, WorkerPool, _InFlight

    pool = WorkerPool(None, FleetKeys("t"), MapBuilder(MapConfig()), lambda *a: None, lambda c: None)
    pose = Pose(0.0, 0.0, 1.0, 0.0, 0.0, 0.0)

    def table(t0_ns: int, n: int) -> dict[int, _InFlight]:
        return {s: _InFlight(s, t0_ns + s * 33_000_000, pose, np.zeros((10, 3), np.float32)) for s in range(n)}

    now = time.monotonic()
    pool._in_flight = {"a": table(5_000_000_000, 3), "b": table(1_000_000_000, 3)}
    pool._active = {"a": now, "b": now}
    assert pool._ready()[1] == 1_000_000_000 + 2 * 33_000_000  # b's window may still fire at its newest cloud
    pool._active["b"] = now - MAX_HOLD_S - 1  # b went silent, its window's trigger still to come
    assert pool._ready()[1] == 5_000_000_000 + 2 * 33_000_000
    pool._in_flight["b"] = table(1_000_000_000, 12)  # a due window in a slow worker's queue: waited for
    assert pool._ready()[1] == 1_000_000_000 + 9 * 33_000_000
