"""``lrsensor base --no-fix {lost,graph}`` (issue 27): what becomes of a robot without a horizontal fix after its
launch. The flag reaches the base's navigator (map thread, ``--nav on`` and ``filter``) and the plane workers
(with every job and adoption, so a worker on another machine navigates as the base says)."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from waiting import wait_until

from lrsensor.calibration import Calibration
from lrsensor.frames import Pose
from lrsensor.sim.dive import record_dive
from mapping import posegraph
from mapping.errors import MapInputError
from mapping.graph_config import TRACKED
from mapping.posegraph import GraphNav
from mapping.synth import simulate_dive, tank, three_rov_plans
from services import cli_base
from services.base import BaseStation
from services.errors import ServiceError, WireError
from services.imu import CsvImu
from services.keys import FleetKeys
from services.map_worker import MapWorker
from services.map_worker_nav import WorkerNav
from services.map_worker_wire import MapControl, MapJob, decode_work
from services.map_workers import WorkerPool
from services.sources import FolderSource
from services.testnet import TestNetwork


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    cli_base.configure(parser)
    return parser.parse_args(["--fleet", "f", *argv])


# ---------------------------------------------------------------------- the flag and the base's navigator
def test_the_flag_parses_defaults_to_graph_and_refuses_other_values(capsys: pytest.CaptureFixture[str]) -> None:
    assert _parse().no_fix is None  # the base's default, resolved where the GTSAM check can run
    assert _parse("--no-fix", "graph").no_fix == "graph"
    assert _parse("--no-fix", "lost").no_fix == "lost"
    with pytest.raises(SystemExit):
        _parse("--no-fix", "kalman")
    assert "invalid choice: 'kalman'" in capsys.readouterr().err
    with pytest.raises(ServiceError, match="no_fix must be one of lost, graph"):
        BaseStation(None, FleetKeys("t"), map_mode="off", no_fix="kalman")
    station = BaseStation(None, FleetKeys("t"), map_mode="on", no_fix=_parse().no_fix)
    assert station.no_fix == "graph"
    station._apply_no_fix()
    assert station.feed.navigator is not None
    assert station.feed.navigator.cfg.graph_without_fix
    assert station.feed.navigator.graph_cfg is TRACKED


def _without_gtsam(monkeypatch: pytest.MonkeyPatch) -> None:
    """``import gtsam`` fails from now on, as in a base installed without the ``graph`` extra."""
    monkeypatch.setattr(posegraph, "_GTSAM", None)
    monkeypatch.setitem(sys.modules, "gtsam", None)  # an ImportError on import
    with pytest.raises(MapInputError):
        posegraph.gtsam_module()


def test_without_gtsam_the_default_falls_back_to_lost_with_one_warning(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    _without_gtsam(monkeypatch)
    with caplog.at_level(logging.WARNING):
        station = BaseStation(None, FleetKeys("t"), map_mode="on", no_fix=_parse().no_fix)
    assert station.no_fix == "lost"
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, warnings
    assert "defaults to lost" in warnings[0]
    assert "pip install 'lrsensor[graph]'" in warnings[0]
    station._apply_no_fix()
    assert station.feed.navigator is not None
    assert not station.feed.navigator.cfg.graph_without_fix
    assert station.feed.navigator.graph_cfg is None
    # lost asked for: no GTSAM needed, no warning; no navigation: GTSAM not looked for
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert BaseStation(None, FleetKeys("t"), map_mode="on", no_fix="lost").no_fix == "lost"
        assert BaseStation(None, FleetKeys("t"), map_mode="on", navigation=False).no_fix == "graph"
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]


def test_without_gtsam_an_explicit_graph_is_an_error_naming_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    _without_gtsam(monkeypatch)
    with pytest.raises(ServiceError, match=r"--no-fix graph: .*pip install 'lrsensor\[graph\]'"):
        BaseStation(None, FleetKeys("t"), map_mode="on", no_fix=_parse("--no-fix", "graph").no_fix)


@pytest.mark.parametrize("nav", ["on", "filter"])
def test_graph_reaches_the_navigator_in_both_navigated_modes(nav: str) -> None:
    for choice, graph in (("lost", False), ("graph", True)):
        args = _parse("--nav", nav, "--no-fix", choice)
        station = BaseStation(None, FleetKeys("t"), map_mode="on", no_fix=args.no_fix)
        if args.nav == "filter":
            station.feed.set_smoothing(False)  # as cli_base.run does, before start
        station._apply_no_fix()  # what start() does before the map thread runs
        navigator = station.feed.navigator
        assert navigator is not None
        assert navigator.cfg.graph_without_fix is graph
        assert navigator.cfg.frame_graph_launches is graph
        assert navigator.graph_cfg is (TRACKED if graph else None)
        assert station.feed.smoothing is (nav == "on")


# ---------------------------------------------------------------------- the plane workers
def test_jobs_and_adoptions_carry_the_choice_and_old_messages_mean_lost() -> None:
    pose = Pose(1.0, 2.0, 3.0, 0.0, 0.0, 0.0)
    pts = np.zeros((2, 3), np.float32)
    job = decode_work(MapJob("rov3", 4, 5, 1, pose, pts, True, 7, "graph").to_bytes())
    assert isinstance(job, MapJob)
    assert job.no_fix == "graph"
    old = decode_work(MapJob("rov3", 4, 5, 1, pose, pts, True).to_bytes())
    assert isinstance(old, MapJob)
    assert old.no_fix == "lost"
    adopt = decode_work(MapControl("adopt", "rov3", 2, b"x", "graph").to_bytes())
    assert isinstance(adopt, MapControl)
    assert adopt.no_fix == "graph"


def test_the_pool_sends_its_choice_with_every_job() -> None:
    from mapping import MapBuilder, MapConfig

    pool = WorkerPool(None, FleetKeys("t"), MapBuilder(MapConfig()), lambda *a: None, lambda c: None, navigate=True)
    pool.no_fix = "graph"  # what BaseStation.start sets
    sent: list[bytes] = []
    pool._put = lambda worker, payload: sent.append(payload)  # type: ignore[method-assign]
    pool._owner["rov3"] = "w1"
    pool._epoch["rov3"] = 0
    from services.map_workers import _InFlight

    pool._send("rov3", [_InFlight(0, 1, Pose(0, 0, 1, 0, 0, 0), np.zeros((1, 3), np.float32))])
    job = decode_work(sent[0])
    assert isinstance(job, MapJob)
    assert job.no_fix == "graph"


@pytest.fixture(scope="module")
def depth_only() -> list[Any]:
    frames = simulate_dive(
        tank(), three_rov_plans(), duration_s=3.0, rate_hz=10.0, n_rays=300, seed=1, navigation="depth-only"
    )
    return [f for f in frames if f.robot == "rov1"]


def _nav_job(seq: int, frame: Any, no_fix: str, epoch: int = 0) -> MapJob:
    return MapJob("rov1", seq, frame.t_ns, epoch, frame.pose_est, frame.points_body.astype(np.float32), True, 0, no_fix)


def test_a_worker_navigates_a_robot_without_a_fix_as_the_base_says(depth_only: list[Any]) -> None:
    assert math.isnan(depth_only[5].pose_est.north_m)  # a depth-only dive: the launch fix only
    lost, graph = MapWorker(None, FleetKeys("t"), "wl"), MapWorker(None, FleetKeys("t"), "wg")
    out = []
    for seq, f in enumerate(depth_only[:15]):
        lost.handle(_nav_job(seq, f, "lost"))
        out += graph.handle(_nav_job(seq, f, "graph"))
    assert not isinstance(lost.nav._navs["rov1"], GraphNav)  # the default: the filter (it says lost)
    g = graph.nav._navs["rov1"]
    assert isinstance(g, GraphNav)
    assert g.gcfg is TRACKED  # the gates, not the ungated graph
    assert graph.nav.cfg.frame_graph_launches
    # moved to another worker: the adoption carries the choice, the gated graph continues there
    other = MapWorker(None, FleetKeys("t"), "wo")
    state = next(o.nav_state for o in reversed(out) if o.nav_state)
    other.handle(MapControl("adopt", "rov1", 1, state, "graph"))
    moved = other.nav._navs["rov1"]
    assert isinstance(moved, GraphNav)
    assert moved.gcfg is TRACKED
    assert moved.track.break_std_m == TRACKED.track_break_std_m  # its gate restored with the gate's threshold


def test_a_bad_choice_is_refused_by_name() -> None:
    nav = WorkerNav()
    with pytest.raises(WireError, match="no-fix choice must be one of lost, graph"):
        nav.set_no_fix("kalman")
    nav.set_no_fix("graph")
    assert nav.graph_cfg is TRACKED
    nav.set_no_fix("lost")
    assert not nav.cfg.graph_without_fix
    assert nav.graph_cfg is None


# ---------------------------------------------------------------------- through the base station
#: 10 Hz: at 5 Hz the first scan after the launch already takes the graph's marginal past the gate's 0.1 m (its
#: track breaks before the map has planes; benchmarks/results/nav.md, "Acceptance through processes")
N_FRAMES, RATE_HZ = 30, 10.0


@pytest.fixture(scope="module")
def depth_only_dive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("nofix") / "rov1"
    record_dive(
        out, robot="rov1", duration_s=N_FRAMES / RATE_HZ, rate_hz=RATE_HZ, width=320, height=180, seed=3,
        navigation="depth-only",
    )  # fmt: skip
    return out


@pytest.mark.slow
def test_the_base_places_a_depth_only_robot_by_its_gated_graph_and_says_so(depth_only_dive: Path) -> None:
    got: list[dict[str, Any]] = []
    with TestNetwork("nofixnet") as net:
        base = net.start_base(None, map_mode="on", navigation=True, no_fix="graph")
        session = net.session()
        sub = session.declare_subscriber(net.keys.nav("rov1"), lambda s: got.append(json.loads(s.payload.to_bytes())))
        folder = depth_only_dive
        calib = Calibration.load(folder / "calib.json")
        h = net.start_rov("rov1", FolderSource(folder), CsvImu(folder / "imu.csv"), calib)
        assert h.join(60)
        assert wait_until(lambda: base.status()["robots"].get("rov1", {}).get("received") == N_FRAMES, 10.0)
        base.flush_map()
        assert wait_until(lambda: len(got) >= 1, 10.0)
        status = base.status()
        navigator = base.feed.navigator
        assert navigator is not None
        graph = navigator.robots["rov1"]
        sub.undeclare()
    assert isinstance(graph, GraphNav)  # the robot left the filter for its graph, with the gates
    assert graph.gcfg is TRACKED
    nav = status["robots"]["rov1"]["nav"]
    assert nav["placed"] + nav["unplaced"] == N_FRAMES
    assert nav["placed"] >= N_FRAMES // 2, nav  # the graph places its clouds (lost: 1-2 of them)
    assert status["map"]["clouds"] == nav["placed"]
    # honest: lost exactly when the graph's track is broken (or it is lost), placed poses near the truth
    broken = graph.lost or graph.track.broken
    assert (nav["position"] == "lost") == (nav["motion"] == "lost")
    assert (nav["motion"] == "lost") == broken or nav["motion"] == "relocalized", (nav, broken)
    truth = {f["t_ns"]: f["pose"] for f in json.loads((folder / "truth.json").read_text())["frames"]}
    placed = [m for m in got if m["north_m"] is not None]
    assert placed
    for m in placed:
        p = truth[m["t_ns"]]
        assert math.hypot(m["north_m"] - p["north_m"], m["east_m"] - p["east_m"]) < 0.2, m


@pytest.mark.slow
def test_plane_workers_of_a_base_with_graph_place_a_depth_only_robot(depth_only: list[Any]) -> None:
    import zenoh

    from services.wire import CloudMsg

    with TestNetwork("nofixwk") as net:
        base = net.start_base(map_mode="on", navigation=True, remote_workers=True, no_fix="graph")
        worker = MapWorker(net.session(), net.keys, "w0")  # knows nothing of the choice: the base's jobs say it
        worker.start()
        try:
            pool = base.feed.pool
            assert pool is not None
            assert pool.wait_for_workers(1, 20)
            pub = net.session().declare_publisher(
                net.keys.cloud("rov1"), congestion_control=zenoh.CongestionControl.BLOCK
            )
            for i, f in enumerate(depth_only):
                pts = f.points_body.astype(np.float32)
                ones = np.ones(len(pts), np.float32)
                pub.put(CloudMsg("rov1", i, f.t_ns, f.pose_est, pts, np.zeros(len(pts), np.uint8), ones).to_bytes())
            assert wait_until(lambda: base.processed >= len(depth_only), 30.0)
            assert base.drain(60)
            base.flush_map(60)
            status = base.status()
            graph = worker.nav._navs["rov1"]
        finally:
            worker.close()
    assert isinstance(graph, GraphNav)
    assert graph.gcfg is TRACKED
    nav = status["robots"]["rov1"]["nav"]
    assert nav["placed"] + nav["unplaced"] == len(depth_only)
    assert nav["placed"] >= len(depth_only) // 2, nav
